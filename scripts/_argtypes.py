"""Argument types and path and device checks shared by the scripts beside this file (imported with this folder put
first on ``sys.path``, before the scripts' heavy imports: imported by a script run as a command, it makes a Ctrl-C
during those imports one line and an end by SIGINT (status 130 in a shell), as :func:`run_command` does in
``main``)."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, NoReturn

if TYPE_CHECKING:
    from torchface.tracker.smoothing import SmoothingConfig


#: The exit status of a script stopped by Ctrl-C (as ``torchface``'s: 128 + SIGINT).
EXIT_INTERRUPTED = 130
#: The exit status of a script stopped by SIGTERM (``timeout``, ``kill``, ``docker stop``; 128 + SIGTERM).
EXIT_TERMINATED = 143
#: The exit status of a script whose stdout's reader has gone (``| head -1``; 128 + SIGPIPE, as ``cat``'s and
#: ``torchface``'s).
EXIT_BROKEN_PIPE = 141
#: The exit status of a script that ran to its end (its outputs written whole) but whose figures missed a target it
#: judges (evaluate.py's FAIL, train_expression.py's "NOT met"), as ``torchface track``'s 3 for a run that completed
#: with a video not tracked whole: 0 says "ran, every judged target met", 2 a usage error, 1 a failure.
EXIT_TARGET_MISSED = 3


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the script is, so that it stops as on Ctrl-C (its partial outputs removed)."""


def run_command(main: Callable[[], int | None]) -> NoReturn:
    """Run a script's ``main`` as its command and exit with its status; a Ctrl-C is one line on stderr and status
    :data:`EXIT_INTERRUPTED`, a SIGTERM (as ``timeout`` and ``docker stop`` send it) one line and status
    :data:`EXIT_TERMINATED`, as ``torchface``'s own commands do (a KeyboardInterrupt's traceback before, which a
    scripted evaluation's log showed as a crash; a SIGTERM killed the script where it was, its temporary files
    left). The scripts write their outputs under temporary names until whole (:func:`written_whole`), so an
    interrupted run leaves none of them under its final name. A SIGTERM that the parent chose to ignore (or a
    handler set outside Python) is left as it is.

    In a script run as a command (:func:`_run_as_script`), a Ctrl-C then ends the process by SIGINT, as ``torchface``
    does (:func:`torchface.cli._end_by_sigint`): a shell loop over a script (``for c in clips/*; do
    scripts/evaluate.py ...; done``) stops there, where a script that exited with 130 itself was taken for one that
    handled the Ctrl-C, and the loop went on; a shell reports 130 either way (Python's ``subprocess``: -2). Called
    otherwise (a test), it exits with :data:`EXIT_INTERRUPTED`.

    A script whose stdout's reader has gone (``scripts/evaluate.py ... | head -5``) stops there without a word and
    exits with :data:`EXIT_BROKEN_PIPE`, as ``cat`` and ``torchface`` do (a BrokenPipeError's traceback and status 1
    before); its outputs under temporary names are removed, as on an interrupt."""
    previous = signal.getsignal(signal.SIGTERM)

    def terminated(signum: int, frame: object) -> None:
        raise _Terminated

    if previous is not None and previous is not signal.SIG_IGN:
        signal.signal(signal.SIGTERM, terminated)
    try:
        status = main()
    except KeyboardInterrupt as exc:
        stopped = isinstance(exc, _Terminated)
        print(f"\n{Path(sys.argv[0]).name}: {'terminated' if stopped else 'interrupted'}", file=sys.stderr)
        if not stopped:
            _end_by_sigint()
        raise SystemExit(EXIT_TERMINATED if stopped else EXIT_INTERRUPTED) from None
    except BrokenPipeError:  # (stdout to /dev/null: Python's flush of it at exit would fail again, with a message)
        with contextlib.suppress(OSError, ValueError, AttributeError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        raise SystemExit(EXIT_BROKEN_PIPE) from None
    finally:
        if previous is not None and previous is not signal.SIG_IGN:
            signal.signal(signal.SIGTERM, previous)
    raise SystemExit(status)


def _run_as_script() -> bool:
    """Whether the running program (``__main__``) is a script beside this file (not a test, nor another program that
    imported it)."""
    where = getattr(sys.modules.get("__main__"), "__file__", None)
    return where is not None and Path(where).resolve().parent == Path(__file__).resolve().parent


def _end_by_sigint() -> None:
    """In a script run as a command (:func:`_run_as_script`), end the process by SIGINT after a Ctrl-C, as
    ``torchface`` does: :func:`torchface.cli._end_by_sigint` (bash's "wait and cooperative exit": a loop over the
    script stops only where it died of SIGINT; not on Windows). Elsewhere, or where ``torchface.cli`` cannot be
    imported (a Ctrl-C during the imports may have left the package half loaded), nothing: the caller exits with
    :data:`EXIT_INTERRUPTED`."""
    if not _run_as_script():
        return
    try:
        from torchface.cli import _end_by_sigint as end  # (loads no torch)
    except BaseException:  # (an ImportError, or a second Ctrl-C meanwhile: exit with 130 as before)
        return
    end()


def _interrupted_imports_in_one_line() -> None:
    """Where the running program (``__main__``) is a script beside this file, a KeyboardInterrupt that reaches the
    top level (a Ctrl-C during the script's imports: torch takes seconds to load, before :func:`run_command` runs;
    a KeyboardInterrupt's traceback before) is one line on stderr and an end by SIGINT (:func:`_end_by_sigint`, as
    :func:`run_command`'s; else exit status :data:`EXIT_INTERRUPTED`); any other exception goes to the hook before.
    Imported by tests or another program, nothing changes. (From ``sys.excepthook`` the exit is ``os._exit``, after
    flushing stdout and stderr: no ``atexit`` handlers run, harmless here, as only an interrupt outside
    :func:`run_command`, before the script's work, reaches it. A SIGTERM during the imports kills the process
    silently, as the signal's default does: status 143 in a shell.)"""
    if not _run_as_script():
        return
    previous = sys.excepthook

    def hook(kind: type[BaseException], value: BaseException, traceback: TracebackType | None) -> None:
        if not issubclass(kind, KeyboardInterrupt):
            previous(kind, value, traceback)
            return
        print(f"\n{Path(sys.argv[0]).name}: interrupted", file=sys.stderr)
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        _end_by_sigint()
        os._exit(EXIT_INTERRUPTED)

    sys.excepthook = hook


_interrupted_imports_in_one_line()


def integer(minimum: int, even: bool = False) -> Callable[[str], int]:
    """An argparse type: an integer >= ``minimum`` (and even if asked), else a one-line error (a count of 0 or
    less gave a traceback after the setup): the package's :func:`torchface.cli._int_at_least`, which ``torchface``'s
    own options use (the same message: ``must be an integer >= 1, got '0'``)."""
    from torchface.cli import _int_at_least  # (as a parser is built: torchface.cli loads no torch, 0.14 s)

    return _int_at_least(minimum, even)


def positive(kind: str = "a number") -> Callable[[str], float]:
    """An argparse type: a finite number > 0, else a one-line error naming ``kind`` ("must be a number of seconds >
    0, got 'x'"; doc_figures.py and peers.py had one each)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0.0):
            raise argparse.ArgumentTypeError(f"must be {kind} > 0, got {text!r}")
        return value

    return parse


def add_threads_option(parser: argparse.ArgumentParser) -> None:
    """Add the scripts' ``--threads N`` (torch's CPU threads; default: torch's, None): an integer >= 1
    (:func:`integer`), which the script sets with :func:`set_threads` before its work."""
    parser.add_argument("--threads", type=integer(1), default=None, help="torch CPU threads (default: torch's)")


def set_threads(threads: int | None) -> None:
    """Set torch's CPU threads to ``threads`` (:func:`add_threads_option`'s value); None leaves torch's."""
    if threads is not None:
        import torch

        torch.set_num_threads(threads)


def checkout_out(*parts: str) -> str:
    """The default path ``out/<parts>`` of a script's cache: under the checkout the scripts are in (the folder above
    this one, where it holds the package's ``pyproject.toml``), whatever the working folder (relative to the working
    folder, a run from elsewhere rendered every sequence again into a new ``out/``); relative to the working folder
    where the scripts are not in a checkout. An explicit ``--cache`` is taken as given.

    Example:
        >>> Path(checkout_out("sequences")).parts[-2:]
        ('out', 'sequences')
    """
    root = Path(__file__).resolve().parent.parent
    base = root if (root / "pyproject.toml").is_file() and (root / "torchface").is_dir() else Path()
    return str(base.joinpath("out", *parts))


def comma_items(text: str) -> list[str]:
    """The items of a comma list option (``--sizes 640x480,1920x1080``), stripped, in order, each once and empty ones
    skipped (a trailing comma, ``a,,b``): the scripts' one reading of their lists (an item given twice was run twice
    and counted twice, ``pose_sweep,`` was an unknown name ``''``).

    Example:
        >>> comma_items(" a,b,,a, ")
        ['a', 'b']
    """
    return list(dict.fromkeys(item for item in (x.strip() for x in text.split(",")) if item))


def output_file(text: str) -> Path:
    """An argparse type: a file the script writes (``--json``, ``--save-series``, ``--save``), as a Path; a name that
    ends in a path separator (``out/``: a folder, meant or not) is a one-line error. ``Path`` drops the separator: the
    figures were written as a file named ``out`` (its folder made as needed), where the user named a folder."""
    seps = tuple(c for c in (os.sep, os.altsep) if c)
    if text.endswith(seps):
        raise argparse.ArgumentTypeError(f"{text!r} ends in {text[-1]!r}, as a folder's name does: name a file")
    return Path(text)


def assets_folder() -> Path:
    """The shared assets folder the scripts read (GRID clips, the ICT Face Model, the James scan): where the
    ``TORCHFACE_ASSETS`` environment variable says, else ``../shared/assets`` beside the repository (as the tests
    find it; track_grid.py and build_synth_data.py read only the latter, so that a set variable was ignored)."""
    return Path(os.environ.get("TORCHFACE_ASSETS") or Path(__file__).resolve().parents[2] / "shared" / "assets")


def written_whole(path: Path) -> contextlib.AbstractContextManager[Path]:
    """A temporary name beside ``path`` to write the file to, this writer's own (``<stem>.partial-<pid>-<random>
    <suffix>``, without the space: two processes writing the same file at once, as benchmark.py's child runs its
    frame cache, each write their own and the last rename wins, a whole file either way; the one name before was
    shared, the first rename took the other's half-written file and a failed writer's cleanup deleted the other's):
    renamed onto ``path`` when the block ends, removed when it raises (an interrupt, a full disk), so that no
    truncated file is left under the final name, where a cache reader would take it for whole. It ends in ``path``'s
    suffix, so that numpy and OpenCV keep the name as given; numpy's ``save`` / ``savez`` add ``.npy`` / ``.npz`` to a
    name without it: give them ``path`` with that suffix, or write through ``tmp.open("wb")``. The package's
    :func:`torchface._atomic.written_whole`, which its own writers (the synthetic sequences) use too.

    Example:
        >>> # with written_whole(Path("out/frames.npy")) as tmp: np.save(tmp, frames)
    """
    from torchface._atomic import written_whole as whole

    return whole(path)


def remove_dead_partials(folder: Path) -> list[Path]:
    """Remove from ``folder`` (a folder the script owns, as benchmark.py's frame cache) the temporary files of
    :func:`written_whole` left by runs killed outright (``kill -9``: no cleanup, a new name each run) whose process
    is no longer running, and nothing else: :func:`torchface._atomic.remove_dead_partials`. Returns them."""
    from torchface._atomic import remove_dead_partials as remove

    return remove(folder)


def frame_size(text: str) -> tuple[int, int]:
    """An argparse type: a frame size ``WxH`` (``640x480``; ``X`` too), each side at least 8, as ``(W, H)``, else a
    one-line error. Odd sides are left to the caller, which refuses them where a video is written."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WxH (e.g. 640x480), got {text!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"size must be at least 8x8, got {text!r}")
    return w, h


def folder_problem(path: Path) -> str | None:
    """Why ``path`` cannot be made an output folder (None: it can): it, or a folder above it, is a file, or a symbolic
    link whose target does not exist (``mkdir`` said only "File exists", a traceback after the setup)."""
    from torchface.io.errors import dangling_link

    link = dangling_link(path)
    if link is not None:
        return f"{link} is a symbolic link to {os.readlink(link)}, which does not exist"
    if any(a.exists() and not a.is_dir() for a in (path, *path.parents)):
        return "not a folder path (a file, or under a file)"
    return None


def file_problem(path: Path) -> str | None:
    """Why a file cannot be written at ``path`` (None: it can): it is a folder, or a folder above it is a file or a
    symbolic link whose target does not exist (found only when the file was written, after the whole run)."""
    from torchface.io.errors import dangling_link

    link = dangling_link(path, itself=False)
    if link is not None:
        return f"{link} is a symbolic link to {os.readlink(link)}, which does not exist"
    if path.is_dir() or any(a.exists() and not a.is_dir() for a in path.parents):
        return "not a file path (a folder, or under a file)"
    return None


def device_problem(name: str) -> str | None:
    """Why torch cannot compute on device ``name`` here (None: it can): an unknown name, a backend that this torch
    build or this machine lacks, or ``meta`` (no data)."""
    import torch

    try:
        device = torch.device(name)
        torch.empty(1, device=device)
    except (RuntimeError, AssertionError, ValueError) as exc:  # (torch raises each for some backend)
        return " ".join(str(exc).split()) or type(exc).__name__
    return "the meta device holds no data" if device.type == "meta" else None


def smoothing_settings(text: str) -> list[tuple[str, "SmoothingConfig"]]:
    """The scripts' ``--smoothing`` settings: a comma list of ``default`` (:class:`~torchface.tracker.SmoothingConfig`'s
    defaults) or ``MC:BETA[:DC]`` (the rotation's One-Euro filter: ``min_cutoff`` in Hz, ``beta`` in Hz per rad/s,
    ``d_cutoff`` in Hz, default 1; the translation's filter at its default), as ``(label, config)``.

    Raises:
        ValueError: a setting that is neither (the message names it).
    """
    from torchface.tracker.smoothing import OneEuroConfig, SmoothingConfig

    out: list[tuple[str, SmoothingConfig]] = []
    for item in (x.strip() for x in text.split(",")):
        if not item:
            continue
        if item == "default":
            out.append(("smooth default", SmoothingConfig()))
            continue
        try:
            values = [float(v) for v in item.split(":")]
            if len(values) not in (2, 3):
                raise ValueError("two or three numbers")
            rotation = OneEuroConfig(*values)
        except ValueError as exc:
            raise ValueError(f"--smoothing: {item!r} is not default or MC:BETA[:DC] ({exc})") from None
        out.append((f"smooth {item}", SmoothingConfig(rotation=rotation)))
    return out
