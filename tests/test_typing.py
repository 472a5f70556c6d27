"""Static typing: mypy over torchface and training_hooks, whose annotations the README promises to type checkers
(PEP 561)."""

from __future__ import annotations

import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

PACKAGES = ("torchface", "training_hooks")

#: The mypy version the budget below was counted with: another version finds other things.
MYPY_VERSION = (2, 4)

#: mypy's findings per file at the last count; every other file of the packages has none. Lower a figure when you
#: fix findings (to the new count, so that they cannot come back); never raise one.
BUDGET: dict[str, int] = {}  # none left


def test_mypy_finds_no_more_than_the_budget(pytestconfig, tmp_path):
    mypy = pytest.importorskip("mypy.version")
    if tuple(int(p) for p in mypy.__version__.split(".")[:2]) != MYPY_VERSION:
        pytest.skip(f"the budget was counted with mypy {'.'.join(map(str, MYPY_VERSION))}, got {mypy.__version__}")
    # (pytest's cache plugin off, ``-p no:cacheprovider``: the config has no ``cache`` attribute at all)
    cache_plugin = getattr(pytestconfig, "cache", None)
    cache = cache_plugin.mkdir("mypy") if cache_plugin is not None else tmp_path
    command = [sys.executable, "-m", "mypy", "--cache-dir", str(cache), "--no-error-summary", *PACKAGES]
    out = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    errors = [line for line in out.stdout.splitlines() if ": error: " in line]
    assert out.returncode in (0, 1) and (out.returncode == 1) == bool(errors), out.stdout[-2000:] + out.stderr
    found = Counter(Path(line.split(":", 1)[0]).as_posix() for line in errors)
    over = {name: (n, BUDGET.get(name, 0)) for name, n in found.items() if n > BUDGET.get(name, 0)}
    assert not over, "findings over budget (found, budget): " + repr(over) + "\n" + "\n".join(
        line for line in errors if line.split(":", 1)[0] in over
    )
