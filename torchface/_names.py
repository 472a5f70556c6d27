"""One check shared by the functions that take a sequence of names (CSV columns, blendshape names, units' names):
a ``str`` is itself a sequence of strings, so one name passed alone was taken as its characters."""

from __future__ import annotations

from collections.abc import Iterable


def name_tuple(names: Iterable[str], what: str) -> tuple[str, ...]:
    """``names`` as a tuple.

    Raises:
        TypeError: ``names`` is one string (its characters would be taken as the names); ``what`` names the argument.

    Example:
        >>> name_tuple(["frame", "timestamp"], "columns")
        ('frame', 'timestamp')
    """
    if isinstance(names, str):
        raise TypeError(f"{what} must be a sequence of names, e.g. ({names[:40]!r},), not one string")
    return tuple(names)
