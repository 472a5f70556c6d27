"""Counts in words for the messages the command prints: ``1 frame``, ``2 frames`` (a summary said "1 frames")."""

from __future__ import annotations


def plural(n: int, noun: str, many: str | None = None) -> str:
    """``noun``, or its plural (``many``, else ``noun + "s"``) unless ``n`` is 1: for ``done/total frames``.

    Example:
        >>> plural(1, "frame"), plural(40, "frame"), plural(2, "was", "were")
        ('frame', 'frames', 'were')
    """
    return noun if n == 1 else many if many is not None else noun + "s"


def counted(n: int, noun: str, many: str | None = None) -> str:
    """``n`` and :func:`plural` of ``noun``.

    Example:
        >>> counted(1, "frame"), counted(0, "frame"), counted(3, "video")
        ('1 frame', '0 frames', '3 videos')
    """
    return f"{n} {plural(n, noun, many)}"
