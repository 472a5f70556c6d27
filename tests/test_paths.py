"""torchface._paths: a path setting starting with a '~' that names a home folder is refused, expanded or not."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from torchface._paths import check_no_tilde, unexpanded_home

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _helpers import without_home  # noqa: E402

pytest.importorskip("pwd")  # (the password database: POSIX)


@pytest.fixture
def no_home(monkeypatch):
    """No home folder to expand ``~`` to: ``HOME`` unset and the password database without the user (as in a
    container run as an uid without an entry); the user named ``me`` by ``USER`` (and no other variable)."""
    without_home(monkeypatch)
    for name in ("LOGNAME", "LNAME", "USERNAME"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("USER", "me")
    assert os.path.expanduser("~/x") == "~/x" and os.path.expanduser("~me/x") == "~me/x"  # (nothing expands)


def test_a_tilde_that_expands_is_refused_naming_expanduser(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    for text in ("~", "~/cache", os.path.join("~", "a", "b")):
        assert unexpanded_home(text) == ("~", True)
        with pytest.raises(ValueError, match=r"^out_dir '~.*' starts with '~', which is not expanded \(it named a "
                                             r"folder '~' in the working folder\): give os\.path\.expanduser\("):
            check_no_tilde(text, "out_dir")
    # a name that no user's home expands is a name as any other
    for text in ("~torchface-no-such-user", "~cache/x", "a/~/b", "x~"):
        assert unexpanded_home(text) is None
        check_no_tilde(text, "out_dir")


def test_a_tilde_that_nothing_can_expand_is_still_refused(no_home):
    """With ``HOME`` unset and the user not in the password database, ``os.path.expanduser`` left ``~/x`` as it was,
    and it was taken: the outputs went to a folder ``~`` in the working folder. ``~`` as the first component, or
    ``~`` and the user's own name, is an expansion that did not happen: refused, saying why, and what to give."""
    for text, first, why in (("~/x", "~", "HOME is not set and the password database has no entry for this user"),
                             ("~", "~", "HOME is not set"), ("~me/x", "~me", "the password database has no user 'me'")):
        assert unexpanded_home(text) == (first, False)
        with pytest.raises(ValueError) as info:
            check_no_tilde(text, "cache_dir")
        said = str(info.value)
        assert said.startswith(f"cache_dir {text!r} starts with '~', which is not expanded (it named a folder "
                               f"'{first}' in the working folder), and os.path.expanduser cannot expand {first!r} "
                               "here (") and why in said and said.endswith("): give the home folder's path"), said
    # another name is a name as any other, as where homes expand
    for text in ("~cache/x", "~torchface-no-such-user", "~mee/x"):
        assert unexpanded_home(text) is None
        check_no_tilde(text, "cache_dir")
