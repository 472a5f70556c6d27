"""scripts/_venv.sh (what scripts/test.sh and scripts/demo.sh run first): which Python makes ./.venv, and a .venv
left half made or made by another Python. Stand-in interpreters (shell scripts that answer ``-c``, ``--version``,
``-m venv`` and ``-m pip`` as their Python version would, and log the rest) keep each run under a second."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.skipif(shutil.which("bash") is None or sys.platform == "win32", reason="needs bash")

_FAKE_PYTHON = r"""#!/bin/sh
# A stand-in Python {version}: -c runs the code under the real interpreter with sys.version_info set to {version};
# -m venv makes a .venv whose bin/python is this script; -m pip logs (or fails where the .venv has no pip).
here=$(cd "$(dirname "$0")" && pwd)
case "$1" in
  --version) echo "Python {version}.1" ;;
  -c) exec "{real}" -c "import sys; sys.version_info = ({major}, {minor}, 1, 'final', 0); exec(sys.argv[1])" "$2" ;;
  -m)
    case "$2" in
      venv)
        for last in "$@"; do :; done
        [ "$3" = --clear ] && rm -rf "$last"
        mkdir -p "$last/bin" && cp "$0" "$last/bin/python"
        echo "command = $0 -m venv $(cd "$last" && pwd -P)" > "$last/pyvenv.cfg" ;;
      pip)
        if [ -e "$here/../no-pip" ]; then echo "$here/python: No module named pip" >&2; exit 1; fi
        shift 2; [ "$1" = --version ] && exit 0; echo "pip {version} $*" >> "$here/../log" ;;
      *) shift; echo "run {version} $*" >> "$here/../log" ;;
    esac ;;
esac
"""


def _fake_python(path: Path, version: str) -> Path:
    major, minor = version.split(".")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(_FAKE_PYTHON.format(version=version, major=major, minor=minor, real=sys.executable))
    path.chmod(0o755)
    return path


@pytest.fixture
def repo(tmp_path):
    """A copy of the scripts in a folder whose path has spaces, and a PATH of the basic tools and no Python."""
    repo = tmp_path / "a repo with spaces"
    (repo / "scripts").mkdir(parents=True)
    for name in ("_venv.sh", "test.sh", "demo.sh"):
        shutil.copy2(ROOT / "scripts" / name, repo / "scripts" / name)
    (repo / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    tools = tmp_path / "tools"
    tools.mkdir()
    for tool in ("dirname", "touch", "rm", "mkdir", "cp", "cat", "pwd", "awk"):
        found = shutil.which(tool)
        if found:
            (tools / tool).symlink_to(found)
    return repo, tools


def _run(repo: Path, path: list[Path], *args: str, script: str = "test.sh", cwd: Path | None = None):
    env = {"PATH": ":".join(str(p) for p in path), "HOME": str(repo)}
    return subprocess.run([shutil.which("bash"), str(repo / "scripts" / script), *args], capture_output=True,
                          text=True, env=env, cwd=cwd or repo.parent, timeout=60)  # fmt: skip


def _log(repo: Path) -> list[str]:
    log = repo / ".venv" / "log"
    return log.read_text().splitlines() if log.exists() else []


def test_python3_being_311_makes_the_venv_once(repo):
    repo, tools = repo
    bin_ = _fake_python(repo.parent / "bin" / "python3", "3.11").parent
    out = _run(repo, [bin_, tools], "tests/x.py")
    assert out.returncode == 0, out.stderr
    log = _log(repo)
    assert [line.split()[:4] for line in log[:3]] == [["pip", "3.11", "install", "-q"]] * 3
    assert log[3:] == ["run 3.11 pytest -q -n auto --maxprocesses=8 tests/x.py"]
    out = _run(repo, [bin_, tools])  # again: nothing installed
    assert out.returncode == 0 and len(_log(repo)) == 5 and "installing" not in out.stderr


def test_another_python_is_refused_with_what_to_do(repo):
    # python3.11 missing, python3 a 3.12: the pinned torch is a CPython 3.11 wheel; a 3.12 .venv went on to ask
    # the registry for torch 2.13.0 for 3.12 (several GB of CUDA packages on PyPI, or "ResolutionImpossible").
    repo, tools = repo
    bin_ = _fake_python(repo.parent / "bin" / "python3", "3.12").parent
    out = _run(repo, [bin_, tools])
    assert out.returncode == 1
    assert "Python 3.11 is needed" in out.stderr and "(python3: Python 3.12.1)" in out.stderr, out.stderr
    assert not (repo / ".venv").exists()
    _fake_python(bin_ / "python3.11", "3.11")
    out = _run(repo, [bin_, tools])
    assert out.returncode == 0, out.stderr
    assert _log(repo)[-1] == "run 3.11 pytest -q -n auto --maxprocesses=8"


def test_a_half_made_venv_is_made_again(repo):
    # `python -m venv` interrupted after writing bin/python, before pip: every later run failed with
    # "No module named pip" until .venv was removed by hand.
    repo, tools = repo
    bin_ = _fake_python(repo.parent / "bin" / "python3.11", "3.11").parent
    _fake_python(repo / ".venv" / "bin" / "python", "3.11")
    (repo / ".venv" / "no-pip").touch()
    out = _run(repo, [bin_, tools])
    assert out.returncode == 0, out.stderr
    assert "making it again" in out.stderr
    assert (repo / ".venv" / ".torchface-installed").exists() and _log(repo)[-1] == "run 3.11 pytest -q -n auto --maxprocesses=8"


def test_a_venv_of_another_python_is_made_again(repo):
    repo, tools = repo
    bin_ = _fake_python(repo.parent / "bin" / "python3.11", "3.11").parent
    _fake_python(repo / ".venv" / "bin" / "python", "3.12")
    (repo / ".venv" / ".torchface-installed").touch()  # a complete install, by a 3.12
    out = _run(repo, [bin_, tools])
    assert out.returncode == 0, out.stderr
    assert _log(repo)[-1] == "run 3.11 pytest -q -n auto --maxprocesses=8" and len(_log(repo)) == 4


def test_demo_runs_in_the_callers_folder(repo):
    # `bash path/to/scripts/demo.sh --out results` from another folder wrote path/to/results, and printed
    # "outputs in results/".
    repo, tools = repo
    bin_ = _fake_python(repo.parent / "bin" / "python3.11", "3.11").parent
    assert _run(repo, [bin_, tools]).returncode == 0  # .venv made
    cli = repo / ".venv" / "bin" / "torchface"
    cli.write_text('#!/bin/sh\necho "$PWD" "$@" > "$(dirname "$0")/../demo-log"\n')
    cli.chmod(0o755)
    elsewhere = repo.parent / "else where"
    elsewhere.mkdir()
    out = _run(repo, [bin_, tools], "--out", "results", script="demo.sh", cwd=elsewhere)
    assert out.returncode == 0, out.stderr
    assert (repo / ".venv" / "demo-log").read_text().strip() == f"{elsewhere} demo --out results"


def test_a_venv_moved_or_copied_with_the_repository_is_made_again(repo):
    # Its scripts and editable install still pointed to the folder it was made in: a copy's demo.sh ran the
    # original's code, and a moved one's failed with "exec: .../old/.venv/bin/python: not found".
    repo, tools = repo
    bin_ = _fake_python(repo.parent / "bin" / "python3.11", "3.11").parent
    assert _run(repo, [bin_, tools]).returncode == 0
    copy = repo.parent / "a copy"
    shutil.copytree(repo, copy, symlinks=True)
    out = _run(copy, [bin_, tools])
    assert out.returncode == 0, out.stderr
    assert (copy / ".venv" / "pyvenv.cfg").read_text().strip().endswith(f" {copy.resolve()}/.venv")
    assert [line.split()[:3] for line in _log(copy)] == [["pip", "3.11", "install"]] * 3 + [["run", "3.11", "pytest"]]
    out = _run(repo, [bin_, tools])  # the original: left as it is
    assert out.returncode == 0 and "making it again" not in out.stderr and len(_log(repo)) == 5
