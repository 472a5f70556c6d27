"""The ``Example:`` sections of every module's docstrings run as doctests (two had drifted: a ``-0.`` printed where
the example showed ``0.``)."""

from __future__ import annotations

import doctest
import importlib
import pkgutil
import tempfile

import pytest

import torchface
import training_hooks


def _modules() -> list[str]:
    names = []
    for package in (torchface, training_hooks):
        names.append(package.__name__)
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            if not info.name.endswith("__main__"):
                names.append(info.name)
    return sorted(names)


@pytest.mark.parametrize("name", _modules())
def test_docstring_examples(name: str, tmp_path, monkeypatch) -> None:
    """Each module's examples pass, and leave no file behind in the working folder or the temporary folder (the
    model-file example saved into a ``tempfile.mkdtemp()`` folder it never removed: one more in /tmp at each run of
    the suite)."""
    try:
        module = importlib.import_module(name)
    except ImportError as exc:  # an optional extra (lightning, dlib) that is not installed
        pytest.skip(f"{name}: {exc}")
    cwd, tmp = tmp_path / "cwd", tmp_path / "tmp"
    cwd.mkdir()
    tmp.mkdir()
    monkeypatch.chdir(cwd)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))  # (where mkdtemp and its kin make their files)
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
    left = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p not in (cwd, tmp))
    assert not left, f"the examples of {name} left files behind: {left}"
