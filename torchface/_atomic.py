"""Files written whole: under a temporary name of the writer's own beside the final one, renamed when complete.

The temporary name is ``<stem>.partial-<pid>-<8 hex digits><suffix>`` (:func:`partial_path`): two processes writing
the same file at once (two evaluation runs sharing one ``--cache`` folder, benchmark.py's child runs) each write
their own file, and the last rename wins, a whole file either way; with one name for every writer the first rename
took the other's half-written file and a failed writer's cleanup deleted the other's. The name keeps the final
name's suffix, so that numpy and OpenCV keep it as given.

A writer killed outright (``kill -9``, a power cut) leaves its temporary file; :func:`remove_dead_partials` removes
those, in one folder, of writers that are no longer running. Standard library only: the scripts import it before
their heavy imports.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
import threading
from collections.abc import Collection, Iterator
from pathlib import Path

PARTIAL_NAME = re.compile(r"(?P<stem>.+)\.partial-(?P<pid>[0-9]+)-[0-9a-f]{8}(?P<suffix>\.[^.]*)?")
"""A name :func:`partial_path` makes: ``stem``, the writer's ``pid`` and the final name's ``suffix`` (or None)."""


def partial_path(path: str | os.PathLike[str]) -> Path:
    """A temporary name beside ``path``, this process's own: ``<stem>.partial-<pid>-<8 hex digits><suffix>``.

    Example:
        >>> tmp = partial_path("out/seq.gt.npz")  # e.g. out/seq.gt.partial-4242-9f3a0c1e.npz
        >>> tmp.parent.name, tmp.suffix, PARTIAL_NAME.fullmatch(tmp.name)["stem"], tmp != partial_path("out/seq.gt.npz")
        ('out', '.npz', 'seq.gt', True)
    """
    p = Path(path)
    return p.with_name(f"{p.stem}.partial-{os.getpid()}-{secrets.token_hex(4)}{p.suffix}")


@contextlib.contextmanager
def written_whole(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary name beside ``path`` to write the file to (:func:`partial_path`): renamed onto ``path`` when the
    block ends, removed when it raises (an interrupt, a full disk), so that no truncated file is left under the final
    name, where a reader would take it for whole. numpy's ``save`` / ``savez`` add ``.npy`` / ``.npz`` to a name
    without it: give them ``path`` with that suffix, or write through ``tmp.open("wb")``.

    Example:
        >>> # with written_whole(Path("out/frames.npy")) as tmp: np.save(tmp, frames)
    """
    target = Path(path)
    tmp = partial_path(target)
    try:
        yield tmp
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)


LOCK_FILE = ".torchface-lock"
"""The file :func:`folder_locked` locks where the folder itself cannot be locked (left in the folder)."""
_RECORD_LOCKS = threading.Lock()  # (held by the thread of this process that holds a LOCK_FILE's record lock)


@contextlib.contextmanager
def folder_locked(folder: str | os.PathLike[str]) -> Iterator[None]:
    """Hold an exclusive lock on ``folder`` (an existing folder) for the block: a second process asking for it waits
    until the first's block ends, so that the files one writer puts in place together (write_sequence's video and
    ground truth) are never interleaved with another writer's. On POSIX the lock is ``flock`` on the folder itself:
    nothing is written in it, and the system releases it when its process ends however it ends (``kill -9``). Where
    the folder cannot be locked so (NFS, whose ``flock`` is a record lock that wants a file open for writing: EBADF
    on a folder; a folder that cannot be opened for reading; a file system without ``flock``), and where there is no
    ``fcntl`` (Windows), a file :data:`LOCK_FILE` in the folder is locked instead (``lockf``, ``msvcrt``) and left
    there. Advisory: it orders only the writers that ask for it; the threads of one process are ordered too. Not
    re-entrant: a block that asks again for a folder it holds waits for itself.

    Example:
        >>> # with folder_locked(out): os.replace(tmp_video, video); os.replace(tmp_truth, truth)
    """
    try:
        import fcntl
    except ImportError:  # (Windows)
        import msvcrt

        with open(os.path.join(folder, LOCK_FILE), "a+b") as f:
            f.seek(0)  # (the byte locked: the first; append mode opened it at its end)
            while True:
                try:
                    msvcrt.locking(f.fileno(), msvcrt.LK_LOCK, 1)  # type: ignore[attr-defined]
                    break
                except OSError as exc:  # (LK_LOCK tries for 10 s, then raises EDEADLOCK: held; another error is)
                    if exc.errno not in (errno.EDEADLOCK, errno.EACCES):
                        raise
            try:
                yield
            finally:
                f.seek(0)
                msvcrt.locking(f.fileno(), msvcrt.LK_UNLCK, 1)  # type: ignore[attr-defined]
        return
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # (a folder without read permission: a lock file in it, which needs only write permission)
        fd = None
    if fd is not None:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:  # (NFS: EBADF, a record lock wants a file open for writing; ENOLCK, EOPNOTSUPP elsewhere)
            os.close(fd)
            fd = None
    if fd is None:  # (the folder itself cannot be locked: a record lock on a file in it, as NFS's lock manager holds)
        with _RECORD_LOCKS:  # (a record lock is its process's: every thread of it would hold it at once)
            fd = os.open(os.path.join(folder, LOCK_FILE), os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.lockf(fd, fcntl.LOCK_EX)
                yield
            finally:
                os.close(fd)  # (releases the lock)
        return
    try:
        yield
    finally:
        os.close(fd)  # (releases the lock)


def _running(pid: int) -> bool:
    """Whether process ``pid`` may still be running on this machine (True where it cannot be told: not POSIX, a
    ``pid <= 0``, which ``os.kill`` reads as a process group, a pid too large for it; and this process's own). Its
    near-twin :func:`torchface.job._alive`, for ``torchface track``'s output locks, tells on Windows too and asks
    ``os.kill`` of any pid: kept apart, as a partial file left is harmless while a lock left refuses every run."""
    if os.name != "posix" or pid <= 0 or pid == os.getpid():  # (os.kill(0, ...) signals the process group)
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (OSError, OverflowError):  # PermissionError: another user's process, running
        return True
    return True


def remove_dead_partials(folder: str | os.PathLike[str], names: Collection[str] | None = None) -> list[Path]:
    """Remove the temporary files in ``folder`` (not below it) that :func:`partial_path` named for a process that is
    no longer running on this machine, left by a writer killed outright; returns them.

    Only plain files whose name matches :data:`PARTIAL_NAME` are touched, and only those of final names in ``names``
    where given (e.g. ``{"seq.avi", "seq.gt.npz"}``); a running process's (the pid's liveness as ``kill -0`` tells:
    another user's counts as running, and so does a finished child not yet reaped) is never removed. A file that
    cannot be removed (a read-only folder) is left without a word: the write that follows says what is wrong. The
    pid is this machine's: a folder that writers on other machines (or in other pid namespaces) share at the same
    time must not be cleaned this way.
    """
    removed: list[Path] = []
    wanted = None if names is None else {(Path(n).stem, Path(n).suffix) for n in names}  # as partial_path splits them
    try:
        entries = list(os.scandir(folder))
    except OSError:  # no such folder yet: nothing left in it
        return removed
    for entry in entries:
        m = PARTIAL_NAME.fullmatch(entry.name)
        if m is None or (wanted is not None and (m["stem"], m["suffix"] or "") not in wanted):
            continue
        if _running(int(m["pid"])) or not entry.is_file(follow_symlinks=False):
            continue
        try:
            os.unlink(entry.path)
        except OSError:  # (FileNotFoundError: another run removed it first)
            continue
        removed.append(Path(entry.path))
    return removed
