"""Argument types shared by the scripts beside this file (imported with this folder put first on ``sys.path``)."""

from __future__ import annotations

import argparse
from collections.abc import Callable


def integer(minimum: int, even: bool = False) -> Callable[[str], int]:
    """An argparse type: an integer >= ``minimum`` (and even if asked), else a one-line error (a count of 0 or
    less gave a traceback after the setup)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum or (even and value % 2):
            kind = "an even integer" if even else "an integer"
            raise argparse.ArgumentTypeError(f"must be {kind} >= {minimum}, got {text!r}")
        return value

    return parse
