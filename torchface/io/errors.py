"""Errors raised for bad user input (paths, videos, landmark files, output folders).

Each carries a one-line message that names the file and the problem; the command line prints it and exits
with a non-zero status.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["InputError", "OutputError", "dangling_link"]


class InputError(ValueError):
    """An input file is missing, unreadable, corrupt or not what was expected."""


class OutputError(OSError):
    """An output folder or file cannot be written."""


def dangling_link(path: Path, *, itself: bool = True) -> Path | None:
    """The first of ``path`` (unless ``itself`` is False) and the folders above it that is a symbolic link whose target
    does not exist, else None: nothing can be made below such a link, and ``mkdir`` or a write there says only "File
    exists" or "No such file or directory". Callers name it with its target, ``os.readlink``."""
    for a in ((path,) if itself else ()) + tuple(path.parents):
        if a.is_symlink() and not a.exists():
            return a
    return None
