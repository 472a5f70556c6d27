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


def switch_hint(value: object, config: str, module: str = "torchface.tracker") -> str:
    """For a setting that takes a ``config`` or None (``refine_first``, ``lookahead``, ``smoothing``, a filter of
    ``SmoothingConfig``), the way from a bool to it, as the command line's switches (``--smooth``, ``--lookahead``,
    ``--no-online-refine``) lead a user to write ``smoothing=True``: ``""`` for any other value (its type says enough).

    Example:
        >>> switch_hint(True, "SmoothingConfig")
        ': on is SmoothingConfig() (its defaults; from torchface.tracker), off is None'
        >>> switch_hint("yes", "SmoothingConfig")
        ''
    """
    if not isinstance(value, bool):
        return ""
    return f": on is {config}() (its defaults; from {module}), off is None"
