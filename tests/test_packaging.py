"""The package's metadata as a build makes it (pyproject.toml): version, licence, extras, command, no deprecated
fields."""

from __future__ import annotations

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
    assert set(meta.get_all("Provides-Extra")) == {"dev", "lightning", "detect", "bench"}
    requires = meta.get_all("Requires-Dist")
    assert any(r.startswith("dlib-bin") and 'extra == "detect"' in r for r in requires)
    assert any(r.startswith("mediapipe") and 'extra == "bench"' in r for r in requires)
    assert "torchface = torchface.cli:main" in (info / "entry_points.txt").read_text()
