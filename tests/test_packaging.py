"""The package's metadata as a build makes it (pyproject.toml): version, licence, extras, command, no deprecated
fields."""

from __future__ import annotations

import shutil
import subprocess
import sys
from email.parser import Parser
from pathlib import Path

import pytest

import torchface

ROOT = Path(__file__).resolve().parent.parent


def test_the_built_metadata_declares_what_the_readme_says_without_deprecations(tmp_path):
    setuptools = pytest.importorskip("setuptools")
    if int(setuptools.__version__.split(".")[0]) < 77:
        pytest.skip("pyproject.toml's build needs setuptools 77")
    # A table `license = { text = ... }` made setuptools warn that such builds stop working on 2027-02-18.
    code = "import sys, setuptools.build_meta as b; print(b.prepare_metadata_for_build_wheel(sys.argv[1]))"
    out = subprocess.run([sys.executable, "-W", "always", "-c", code, str(tmp_path)], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "deprecated" not in out.stderr.lower(), out.stderr
    info = tmp_path / out.stdout.strip().splitlines()[-1]
    meta = Parser().parsestr((info / "METADATA").read_text())
    assert meta["Name"] == "torchface" and meta["Version"] == torchface.__version__
    assert meta["License-Expression"] == "MIT"
    assert meta.get_all("License-File") == ["LICENSE"]  # the MIT licence's text ships with the package
    assert "Permission is hereby granted" in (info / "licenses" / "LICENSE").read_text()
    assert set(meta.get_all("Provides-Extra")) == {"dev", "lightning", "detect", "mediapipe", "bench"}
    requires = meta.get_all("Requires-Dist")
    assert any(r.startswith("dlib-bin") and 'extra == "detect"' in r for r in requires)
    assert any(r.startswith("mediapipe") and 'extra == "bench"' in r for r in requires)
    assert any(r.startswith("mediapipe") and 'extra == "mediapipe"' in r for r in requires)
    assert "torchface = torchface.cli:main" in (info / "entry_points.txt").read_text()


def test_the_source_distribution_carries_the_tests_scripts_and_docs(tmp_path):
    # Without MANIFEST.in setuptools put only tests/test_*.py in the sdist: 6 of the suite's files, and none of the
    # scripts that tests/test_peers.py and tests/test_venv_setup.py exercise.
    import tarfile

    pytest.importorskip("setuptools")
    # A copy without an earlier build's egg-info, whose file list setuptools reuses, nor the tools' caches: under
    # pytest-xdist another worker's mypy (tests/test_typing.py) writes .pytest_cache/d/mypy meanwhile, and a
    # journal file it removed between copytree's listing and its copy failed this test ("No such file").
    source = tmp_path / "source"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(".git", ".venv", "*.egg-info", "build", "out",
                                                                 "__pycache__", "*.pyc", "torchface-demo", ".*_cache",
                                                                 ".coverage*"))  # fmt: skip
    code = "import sys, setuptools.build_meta as b; print(b.build_sdist(sys.argv[1]))"
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path)], cwd=source, capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    with tarfile.open(tmp_path / out.stdout.strip().splitlines()[-1]) as sdist:
        names = {name.split("/", 1)[1] for name in sdist.getnames() if "/" in name}
    wanted = {str(p.relative_to(ROOT)) for folder in ("tests", "scripts", "docs") for p in (ROOT / folder).rglob("*")
              if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc"}  # fmt: skip
    # (docs/: the pages tests/test_readme.py reads beside README.md; the sdist had none, so that test failed there)
    assert "tests/tracker/test_native.py" in wanted and "scripts/_venv.sh" in wanted and "docs/cli.md" in wanted
    assert "LICENSE" in names and "CHANGELOG.md" in names  # (the README links to the changelog)
    assert not wanted - names, sorted(wanted - names)[:10]
    assert not any(name.endswith(".pyc") for name in names)


def test_the_wheel_marks_both_packages_typed(tmp_path):
    # PEP 561: without a py.typed marker in the installed package, mypy skips it ("module is installed, but missing
    # library stubs or py.typed marker") and pyright infers from the code: the annotations were not used.
    import zipfile

    pytest.importorskip("setuptools")
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md", "MANIFEST.in"):
        shutil.copy(ROOT / name, source / name)
    for package in ("torchface", "training_hooks"):
        shutil.copytree(ROOT / package, source / package, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    code = "import sys, setuptools.build_meta as b; print(b.build_wheel(sys.argv[1]))"
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path)], cwd=source, capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    with zipfile.ZipFile(tmp_path / out.stdout.strip().splitlines()[-1]) as wheel:
        names = set(wheel.namelist())
    assert {"torchface/py.typed", "training_hooks/py.typed"} <= names, sorted(n for n in names if "typed" in n)
    assert "torchface/data/candide3.wfm" in names


def test_an_editable_install_builds_without_warnings(tmp_path):
    # `pip install -e .` (scripts/_venv.sh) printed setuptools' BuildBackendWarning on every install ("Editable
    # installation. Please be careful with folders in your working directory with the same name as your package"):
    # with two top-level packages and no package-dir, setuptools chose a meta path finder and warned about it.
    setuptools = pytest.importorskip("setuptools")
    if int(setuptools.__version__.split(".")[0]) < 77:
        pytest.skip("pyproject.toml's build needs setuptools 77")
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md", "MANIFEST.in", "LICENSE"):
        shutil.copy(ROOT / name, source / name)
    for package in ("torchface", "training_hooks"):
        shutil.copytree(ROOT / package, source / package, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    code = "import sys, setuptools.build_meta as b; print(b.build_editable(sys.argv[1]))"
    out = subprocess.run([sys.executable, "-W", "always", "-c", code, str(tmp_path)], cwd=source, capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "Warning" not in out.stderr and "meta path finder" not in out.stdout + out.stderr, out.stderr[-3000:]
