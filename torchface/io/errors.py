"""Errors raised for bad user input (paths, videos, landmark files, output folders).

Each carries a one-line message that names the file and the problem; the command line prints it and exits
with a non-zero status.
"""

from __future__ import annotations

__all__ = ["InputError", "OutputError"]


class InputError(ValueError):
    """An input file is missing, unreadable, corrupt or not what was expected."""


class OutputError(OSError):
    """An output folder or file cannot be written."""
