"""The check of a path setting that starts with a ``~`` nothing expanded (:func:`check_no_tilde`), which
:class:`~torchface.job.JobConfig` and ``training_hooks``' settings share (:mod:`torchface.extending` names it)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["check_no_tilde"]


def check_no_tilde(path: str | os.PathLike[str], name: str) -> None:
    """Refuse a path that starts with a ``~`` or ``~user`` that ``os.path.expanduser`` would expand (``"~/cache"``,
    ``"~/m.npz"``): it is not expanded (by ``pathlib``, as by a shell), so made absolute it named a folder ``~`` in
    the working folder (outputs or a cache went there without a word; a model file failed at its first load with "no
    such file"). A name such as ``"~cache"``, which no user's home expands, is a name as any other, as ``torchface
    track`` takes it.

    Raises:
        ValueError: ``path`` starts with a ``~`` that expands, naming ``os.path.expanduser``.

    Example:
        >>> check_no_tilde("~torchface-no-such-user", "out_dir")  # (no such user's home: a name as any other)
    """
    text = os.fspath(path)
    if os.path.expanduser(text) != text:
        raise ValueError(
            f"{name} {text!r} starts with '~', which is not expanded (it named a folder '{Path(text).parts[0]}' in "
            f"the working folder): give os.path.expanduser({text!r})"
        )
