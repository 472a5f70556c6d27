"""The check of a path setting that starts with a ``~`` nothing expanded (:func:`check_no_tilde`), which
:class:`~torchface.job.JobConfig` and ``training_hooks``' settings share (:mod:`torchface.extending` names it), and
the rule it and the command line's path arguments share (:func:`unexpanded_home`)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["check_no_tilde", "missing_path_hint", "no_home_reason", "unexpanded_home"]

#: The environment variables :func:`getpass.getuser` takes the user's name from, in its order.
_USER_VARIABLES: tuple[str, ...] = ("LOGNAME", "USER", "LNAME", "USERNAME")


def unexpanded_home(text: str) -> tuple[str, bool] | None:
    """The ``~`` or ``~user`` that ``text`` starts with where it names a home folder, and whether
    ``os.path.expanduser`` expands it here; None where it names none (a name such as ``~draft.mp4`` or ``~cache``).

    It names one where ``expanduser`` expands it (``~/x``; ``~root/x`` where root is a user), and, where
    ``expanduser`` cannot (``HOME`` unset and the password database without the user, as in a container run as an
    uid that has no entry; it left ``~/x`` as it was, and the outputs went to a folder ``~`` in the working folder),
    where the first component is ``~`` itself or ``~`` and the user's own name (``LOGNAME``, ``USER``, ``LNAME`` or
    ``USERNAME``, as :func:`getpass.getuser` reads it): a shell expands them where it can, so given thus they are
    almost surely an expansion that did not happen. Any other ``~name`` that does not expand is a name as any other.

    Example:
        >>> unexpanded_home("~torchface-no-such-user/x") is None
        True
    """
    if not text.startswith("~"):
        return None
    seps = [s for s in (os.sep, os.altsep) if s]
    end = min((i for i in (text.find(s) for s in seps) if i >= 0), default=len(text))
    first = text[:end]
    if os.path.expanduser(text) != text:
        return first, True
    own = {os.environ.get(v) for v in _USER_VARIABLES} - {None, ""}
    return (first, False) if first == "~" or first[1:] in own else None


def check_no_tilde(path: str | os.PathLike[str], name: str) -> None:
    """Refuse a path that starts with a ``~`` or ``~user`` that names a home folder (:func:`unexpanded_home`:
    ``"~/cache"``, ``"~/m.npz"``): it is not expanded (by ``pathlib``, as by a shell), so made absolute it named a
    folder ``~`` in the working folder (outputs or a cache went there without a word; a model file failed at its
    first load with "no such file"); also where ``os.path.expanduser`` cannot expand it (``HOME`` unset, the user
    not in the password database: it was taken then, as a folder ``~``). A name such as ``"~cache"``, which no
    user's home expands, is a name as any other, as ``torchface track`` takes it.

    Raises:
        ValueError: ``path`` starts with a ``~`` that names a home folder: naming ``os.path.expanduser`` where it
            expands, else saying that nothing here knows the home folder, and to give it.

    Example:
        >>> check_no_tilde("~torchface-no-such-user", "out_dir")  # (no such user's home: a name as any other)
    """
    text = os.fspath(path)
    home = unexpanded_home(text)
    if home is None:
        return
    first, expands = home
    said = f"{name} {text!r} starts with '~', which is not expanded (it named a folder '{Path(text).parts[0]}' in the "
    if expands:
        raise ValueError(f"{said}working folder): give os.path.expanduser({text!r})")
    raise ValueError(f"{said}working folder), and os.path.expanduser cannot expand {first!r} here "
                     f"({no_home_reason(first)}): give the home folder's path")  # fmt: skip


def missing_path_hint(path: str | os.PathLike[str]) -> str:
    """Why ``path``, which does not exist, may be missing, as `` (...)``: it starts with a ``~`` or ``~user`` that
    names a home folder (:func:`unexpanded_home`), which nothing expanded (a path given from Python, where no shell
    expands it: ``open_frames("~/clip.mp4")`` and ``read_landmarks("~/lm.csv", W, H)`` were told "no such file"
    alone, where ``torchface track`` names the ``~``); "" otherwise. The words of training_hooks' datasets.

    Example:
        >>> missing_path_hint("clip.mp4")
        ''
    """
    home = unexpanded_home(os.fspath(path))
    if home is None:
        return ""
    first, expands = home
    if expands:
        return f" ('{first}' is not expanded here: os.path.expanduser(path) names the home folder)"
    return (f" ('{first}' is not expanded here, and os.path.expanduser cannot expand it here "
            f"({no_home_reason(first)}): give the home folder's path)")  # fmt: skip


def no_home_reason(first: str) -> str:
    """Why ``os.path.expanduser`` leaves ``first`` (``~`` or ``~user``) as it is, in words."""
    if first == "~":
        return "HOME is not set and the password database has no entry for this user"
    return f"the password database has no user {first[1:]!r}"
