"""The ``torchface`` command: ``track`` videos, run the ``demo`` on the embedded clip, ``render-demo`` a synthetic one.

Examples::

    torchface demo                                   # -> ./torchface-demo/
    torchface track clip.mp4 --out results --landmarks clip_first_frame.csv
    torchface track a.mp4 b.mp4 --out results --detector dlib   # same-size videos are tracked as one batch
    torchface track clip.mp4 --out results --landmarks lm.csv --resume   # continue an interrupted run
    torchface track gray16.avi --out results --landmarks lm.csv --convert  # gray/RGBA/16-bit/odd-sized frames
    torchface track frames/ --out results --landmarks lm.csv --fps 30   # an image folder's frames, 30 per second
    torchface track clip.mp4 --out results --landmarks lm.csv --motion-prediction 1   # constant-velocity starts
    torchface track clip.mp4 --out results --landmarks lm.csv --smooth   # + the pose smoothed over time (smooth_*)
    torchface track clips/*.mp4 --out results --detector dlib --keep-going   # skip the bad ones (status 3)
    torchface track clip.mp4 --out results --landmarks lm.csv --keep-expression   # normalised face keeps expressions
    torchface render-demo --scenario pose_sweep --out synth    # a synthetic clip with ground truth
    torchface track synth/pose_sweep.avi --out results --landmarks synth/pose_sweep_first_frame.csv   # tracked

Errors about the input or the output folder print one line ``torchface: error: ...`` and exit with status 2
(grayscale, RGBA, 16-bit and odd-sized frames are such errors unless ``--convert`` is given; a frame that cannot
be read partway stops that video only: the summary of the others, completed, is printed before the error); with
``--keep-going`` an input that cannot be tracked is skipped instead (one line ``torchface: warning: skipped ...``),
the others tracked, and a run that skipped any, or in which a video stopped partway, exits with status 3 after its
summary, which lists them with why; so does a run, with or without ``--keep-going``, in which a video has no tracked
frame (its outputs written, every row unusable: its start failed, a black first frame, and nothing started it again);
an interrupted run (Ctrl-C, or SIGTERM as ``timeout`` and ``docker stop`` send) exits with status 130 (143 for
SIGTERM) and keeps its rows for ``--resume``, saying what it leaves (the partial CSVs and their rows, the videos
complete, or that nothing was written). A progress display whose reader has gone (``2>&1 | head -1``) stops
and the run goes on; a summary whose reader has gone exits with status 141 (128 + SIGPIPE, as ``cat`` does), the
outputs complete. A closed stdout or stderr (``>&-``) is taken as ``/dev/null``. The job's warnings print one
line ``torchface: warning: ...`` each, above the progress bars.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import math
import os
import shlex
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import TextIO

from torchface import __version__  # (torch is not imported: the package's names load on first use)
from torchface._paths import no_home_reason, unexpanded_home
from torchface._words import counted, plural

__all__ = ["main", "build_parser", "ProgressDisplay"]

EXIT_USAGE = 2
#: ``torchface track --keep-going``: an input was skipped or a video stopped partway; every other one is complete.
#: Also, with or without ``--keep-going``: a video's outputs were written with no tracked frame
#: (:attr:`torchface.job.VideoSummary.no_tracked_frame`).
EXIT_INCOMPLETE = 3
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143  # 128 + SIGTERM
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE
#: ``OPENCV_FFMPEG_LOGLEVEL`` of a ``torchface`` command where the environment sets none: FFmpeg's ``AV_LOG_QUIET``
#: (its messages about a damaged input repeat what torchface says in one line; ``OPENCV_FFMPEG_LOGLEVEL=16``, FFmpeg's
#: errors, shows them).
FFMPEG_LOG_QUIET = "-8"


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the job is so that it stops as on Ctrl-C (partial files kept for --resume)."""


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`_Terminated` (main thread only; the previous handler after)."""
    previous = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None
    if previous is None or previous is signal.SIG_IGN:  # not the main thread, a handler set outside Python, or
        yield  # a parent that chose to ignore SIGTERM: left as it is
        return

    def handler(signum, frame):
        raise _Terminated()

    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def is_terminal(stream: object) -> bool:
    """Whether ``stream`` is a terminal that can redraw a line in place: its ``isatty()`` says so (a stream without
    ``isatty``, some notebook or wrapper streams, is not one) and ``TERM`` is not ``dumb`` (Emacs' shell and
    compilation buffers: no cursor movement). Progress goes to such a stream as a redrawn line, to others as whole
    lines (``torchface track``, ``scripts/make_sequence.py``). One whose ``isatty()`` raises (a closed or detached
    stream's ``ValueError``, ``io.UnsupportedOperation``) is not one either: the progress rule never stops a run."""
    try:
        tty = bool(getattr(stream, "isatty", lambda: False)())
    except (ValueError, OSError):  # (io.UnsupportedOperation is both)
        return False
    return tty and os.environ.get("TERM") != "dumb"


class ProgressDisplay:
    """One progress bar per video (frames, fps, confidence) on a terminal; occasional lines otherwise (and where
    ``TERM=dumb``, a terminal without cursor movement).

    The job reports every stream of a batch after every step (B reports per step). On a terminal the bars are
    redrawn at most every ``redraw_s`` seconds, and at once when a video appears or finishes: a redraw writes every
    bar, so redrawing at each report wrote B * B lines per step (1.4 MB of terminal output per step at 128 streams).
    A video that has finished is drawn or printed once, when it finishes: the job goes on reporting it while the
    longer videos of its batch are tracked, and a log got its line at every step. On a terminal its line then stays
    above the bars, which are those of the videos still tracked (every video's bar was redrawn to the end of the
    run: over many videos, hundreds of lines per redraw), as many as the terminal has rows for, and a line counting
    the others. :meth:`flush` draws the latest reports. Once the stream cannot be written (its reader has gone: a
    broken pipe), the display stops, and the job it reports on goes on.
    """

    def __init__(self, stream: TextIO | None = None, width: int = 24, redraw_s: float = 0.1) -> None:
        stream = sys.stderr if stream is None else stream  # at call time: main() may have replaced a closed one
        self.stream = stream
        self.width = width
        self.redraw_s = redraw_s
        self.tty = is_terminal(stream)  # (TERM=dumb, a terminal that cannot move the cursor, gets log lines)
        self.lines: dict[int, str] = {}  # the videos being tracked (on a terminal: their bars)
        self.drawn = 0
        self.last_print: dict[int, float] = {}
        self.last_draw: float | None = None
        self.finished: dict[int, int] = {}  # the videos reported finished: their frames then
        self.stale = False
        self.broken = False

    def _write(self, text: str) -> None:
        if self.broken:
            return
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # a broken pipe, a closed file: the display stops, the job goes on
            self.broken = True

    def note(self, line: str) -> None:
        """Print ``line`` (a warning) to stay: on a terminal above the bars, which are redrawn below it (written
        between them, the next redraw's cursor movement overwrote it with a bar and left a stale bar above)."""
        if self.tty:
            self._draw(done=line)
        else:
            self._write(line + "\n")

    def _line(self, p) -> str:
        if getattr(p, "searching", False):  # (the job looks for the first frame with a face)
            return f"{p.name[:28]:<28} searching for a face: none in {counted(p.done, 'frame')} {p.fps:5.1f} fps"
        if p.total:
            frac = min(1.0, p.done / p.total)
            bar = "#" * int(round(frac * self.width))
            head = f"[{bar:<{self.width}}] {p.done}/{p.total}"
        else:
            head = counted(p.done, "frame")
        return f"{p.name[:28]:<28} {head} {p.fps:5.1f} fps conf {p.confidence:.2f}"

    def _rows(self) -> int | None:
        """The terminal's height in rows (None: not known)."""
        try:
            return os.get_terminal_size(self.stream.fileno()).lines or None
        except (AttributeError, OSError, ValueError):  # not a file (a test's stream), or not a terminal after all
            return None

    def _draw(self, done: str | None = None) -> None:
        """Redraw the bars, with the line of a video that has just finished (``done``) above them, to stay."""
        up = f"\x1b[{self.drawn}F" if self.drawn else ""
        bars = [self.lines[k] for k in sorted(self.lines)]
        rows = self._rows()
        if rows is not None and len(bars) > rows - 2:  # (the cursor cannot go back above the terminal's first row)
            keep = max(rows - 3, 1)
            bars = bars[:keep] + [f"... and {counted(len(bars) - keep, 'more video')} being tracked"]
        out = ([done] if done is not None else []) + bars
        clear = "\x1b[J" if len(out) < self.drawn else ""  # (a shorter block: the old bars below it erased)
        self._write(up + "".join("\x1b[2K" + line + "\n" for line in out) + clear)
        self.drawn = len(bars)
        self.stale = False

    def flush(self) -> None:
        """Draw the reports not drawn yet (on a terminal; the log lines are written as they come)."""
        if self.tty and self.stale:
            self._draw()
            self.last_draw = time.monotonic()

    def __call__(self, p) -> None:
        if getattr(p, "skipped", False):  # (--keep-going: a warning line says it) its line, a search's, goes
            if self.lines.pop(p.index, None) is not None and self.tty:
                self._draw()
                self.last_draw = time.monotonic()
            return
        if self.finished.get(p.index) == p.done:  # finished before, reported again while its batch goes on
            return
        # (just now; a container whose frame count was an estimate may go on past it: a bar again, finished when
        # its frames, which the job reports as its total once it has ended, are done: its log's last line said
        # the estimate's count, and its bar stayed among those of the videos being tracked)
        finished = p.total is not None and p.done >= p.total and (p.index not in self.finished or p.done == p.total)
        finished = finished and not getattr(p, "searching", False)  # (a video without a face: an error follows)
        new = p.index not in self.lines
        line = self._line(p)
        now = time.monotonic()
        if finished:
            self.finished[p.index] = p.done
        if self.tty:
            if finished:  # its line goes above the bars, to stay
                self.lines.pop(p.index, None)
                self._draw(done=line)
                self.last_draw = now
                return
            self.lines[p.index] = line
            self.stale = True
            if new or self.last_draw is None or now - self.last_draw >= self.redraw_s:
                self._draw()
                self.last_draw = now
        else:
            self.lines[p.index] = line
            if finished or now - self.last_print.get(p.index, 0.0) > 10.0:
                self.last_print[p.index] = now
                self._write(line + "\n")


#: The scenarios ``render-demo`` renders, ``torchface.synth.scenarios.SCENARIOS``' names, which its ``--help`` lists
#: (it said "scenario name", and only a wrong one was told them). Written here: that module imports torch, which
#: the parser does not (tests/test_cli.py holds the two equal).
RENDER_SCENARIOS: tuple[str, ...] = ("pose_sweep", "expressions", "light_switch", "occlusion", "scan_motion")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``torchface`` command."""
    # (python -OO / PYTHONOPTIMIZE=2 strips docstrings: __doc__ is None there)
    description = (__doc__ or "The torchface command: track videos, run the demo, render a synthetic clip.")
    description = description.splitlines()[0].replace("``", "")  # (reST quotes: printed as they were in --help)
    parser = argparse.ArgumentParser(prog="torchface", description=description)
    # (a script recording what made its results asked `torchface --version` and was told a command is required)
    parser.add_argument("--version", action="version", version=f"torchface {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    track = sub.add_parser("track", help="track the face in one or more videos")
    track.add_argument(
        "videos", nargs="+", type=_path,
        help="video files, image folders or .npy frame arrays (each may be followed by its --landmarks: a.mp4 "
        "--landmarks a.csv b.mp4 --landmarks b.csv)",
    )  # fmt: skip
    track.add_argument("--out", type=_path, required=True, help="output folder")
    track.add_argument(
        "--landmarks", type=_path, action="append", default=None,
        help="68 iBUG landmarks of the first frame (with --model, the model's, in its order) (CSV, iBUG/300-W .pts, "
        "NPY, JSON (also a torchface .json "
        "sidecar: the landmarks that run started from), or OpenFace's per-frame CSV: its "
        "first row; a missing point as empty cells or NaN, at least 4 given); give it once per video, in order",
    )  # fmt: skip
    track.add_argument("--detector", default=None,
                       help="detector for initialisation and re-initialisation (dlib or mediapipe)")  # fmt: skip
    track.add_argument(
        "--model", type=_path, default=None, metavar="FILE",
        help="face model file to track with (torchface.model.save_face_model writes one; default: CANDIDE-3); "
        "--landmarks then give its landmarks, in its order, and --detector needs a model of the 68 iBUG points",
    )  # fmt: skip
    track.add_argument("--focal", type=float, default=None, help="focal length in pixels (default max(W, H))")
    track.add_argument("--device", default="cpu", help="torch device (default cpu)")
    track.add_argument("--resume", action="store_true", help="continue after the last complete frame of a previous run")
    track.add_argument(
        "--convert", action="store_true",
        help="convert grayscale, RGBA and 16-bit frames to RGB and crop odd sizes to even (default: reject them)",
    )  # fmt: skip
    track.add_argument(
        "--fps", type=_frame_rate, default=None, metavar="F",
        help="frame rate of the inputs that have none (image folders, .npy arrays, a video whose container gives "
        "none): their timestamps are frame / F and their overlay runs at F (default 25, the sidecar's "
        "input.fps_assumed); a video with its own rate keeps it, with a warning",
    )  # fmt: skip
    track.add_argument("--meshes", action="store_true", help="also write one PLY mesh per frame")
    track.add_argument(
        "--lookahead", action="store_true",
        help="refine the first frame's pose, expression and the shape units the landmark fit held against the "
        "frames where the head turns 10 degrees to each side (one side is enough; reads up to 150 frames ahead and "
        "keeps them in memory; torchface.tracker.lookahead), then track from the first frame; instead of the online "
        "start",
    )  # fmt: skip
    track.add_argument(
        "--no-online-refine", action="store_true",
        help="track without the online look-ahead start (on by default: once the head has turned 10 degrees, the "
        "first pose, its expression and the shape units the landmark fit held are re-estimated from that view, in "
        "one pass)",
    )  # fmt: skip
    track.add_argument(
        "--restart-after-unmatched", type=_int_at_least(0), default=0, metavar="K",
        help="with --detector: a lost video starts afresh from the detector's face after K recovery attempts in a "
        "row that found the same face but not the one being tracked (a cut to another person; TemplateConfig."
        "restart_after_unmatched; default 0, off: a heavy occluder carried with the face can trigger it)",
    )  # fmt: skip
    track.add_argument(
        "--motion-prediction", type=_fraction, default=0.0, metavar="K",
        help="start each frame's solve from a constant-velocity prediction, K times the last two confident frames' "
        "motion (TrackerConfig.motion_prediction; 0 to 1, default 0: off, from the previous frame's estimate); "
        "widens the motion a frame can follow for motion that builds up",
    )  # fmt: skip
    track.add_argument(
        "--smooth", action="store_true",
        help="also smooth the pose over time (a One-Euro filter, torchface.tracker.SmoothingConfig's defaults): the "
        "CSV keeps its raw pose and adds smooth_* columns, the overlay and the meshes show the smoothed pose, the "
        "sidecar's config.smoothing says it (default: off)",
    )  # fmt: skip
    track.add_argument(
        "--keep-expression", action="store_true",
        help="write the normalised face with the expression kept: each frame resampled at the person's neutral "
        "expression (the one the CSV's AUxx_r are measured from) instead of its row's, so that the expression shows; "
        "pose and light undone as without it (for expression classifiers; training_hooks' "
        "FaceTrackingConfig(keep_expression=True)); the sidecar's config.keep_expression says it (default: off, the "
        "face at its neutral expression)",
    )  # fmt: skip
    track.add_argument(
        "--keep-going", action="store_true",
        help="skip the inputs that cannot be tracked (unreadable, empty, a bad landmarks file, no face found, ...), "
        "each named on stderr as it is skipped, and track the others; the summary lists them with why, and the "
        "exit status is 3 where any was skipped or stopped partway (default: one refuses the run, status 2; a video "
        "with no tracked frame gives 3 either way)",
    )  # fmt: skip
    track.add_argument("--quiet", action="store_true", help="no progress bars")
    track.add_argument(
        "--max-batch", type=_threads, default=128,
        help="most videos of one size tracked together (default 128; more are tracked in several batches); every "
        "video of a batch is open and in memory at once",
    )  # fmt: skip
    track.add_argument(
        "--threads", type=_threads, default=None,
        help="torch threads of this process (default: torch's, one per core). Give several torchface processes on "
        "the same cores 1 each: two runs at once on 2 cores tracked the demo clip at 14 frames/s each with torch's "
        "default, 80 with --threads 1",
    )  # fmt: skip

    demo = sub.add_parser("demo", help="track the embedded sample clip and write everything to ./torchface-demo/")
    demo.add_argument(
        "--out", type=_path, default=Path("torchface-demo"), help="output folder (default ./torchface-demo)"
    )
    demo.add_argument("--device", default="cpu", help="torch device (default cpu)")
    demo.add_argument("--meshes", action="store_true", help="also write one PLY mesh per frame")
    demo.add_argument("--quiet", action="store_true", help="no progress bars")
    demo.add_argument("--threads", type=_threads, default=None, help="torch threads of this process (as for track)")

    render = sub.add_parser("render-demo", help="render a short synthetic sequence with ground truth")
    render.add_argument(
        "--out", type=_path, default=Path("torchface-synth"), help="output folder (default ./torchface-synth)"
    )
    render.add_argument("--scenario", default="pose_sweep",
                        help=f"scenario: {', '.join(RENDER_SCENARIOS)} (default pose_sweep)")  # fmt: skip
    render.add_argument("--frames", type=int, default=40, help="number of frames (default 40)")
    render.add_argument("--width", type=int, default=320, help="frame width (default 320)")
    render.add_argument("--height", type=int, default=240, help="frame height (default 240)")
    return parser


def _print_summary(
    summaries, out: TextIO, stopped: tuple[str, ...] = (), reasons: tuple[str, ...] = (), names: tuple[str, ...] = ()
) -> None:
    """Write the run's summary to ``out`` in one piece (one ``write``): written a line at a time (with Python's
    output unbuffered, ``PYTHONUNBUFFERED=1`` as many containers set it), ``torchface track ... | head -1`` exited
    with 141, its reader gone after the first line, where docs/cli.md says the summary reaches the pipe whole.

    ``stopped`` and ``reasons``: the videos a :class:`~torchface.job.VideosStopped` names, and why; ``names`` (its
    ``names``): every input's output name in input order, in which the videos' lines are listed (the stopped ones
    came last, after the others'); a name not in it goes last."""
    blocks: list[tuple[str, list[str]]] = []
    for s in summaries:
        lines: list[str] = []
        blocks.append((s.name, lines))
        if s.refused is not None:  # (--keep-going)
            lines.append(f"  {s.name}: skipped, not tracked: {s.refused}")
            continue
        if s.stopped is not None:  # (--keep-going)
            are = plural(s.frames, "is", "are")
            kept = f"its {counted(s.frames, 'row')} so far {are} kept in {s.name}.csv.partial"
            kept = kept if s.outputs else "no row kept"
            lines.append(f"  {s.name}: stopped partway, not completed ({kept}): {s.stopped}")
            continue
        if s.skipped:
            lines.append(f"  {s.name}: already complete ({counted(s.frames, 'frame')}), skipped")
        else:
            lines.append(f"  {s.name}: {counted(s.frames, 'frame')}, {s.fps:.1f} fps, "
                         f"mean confidence {s.mean_confidence:.2f}, {counted(s.lost, 'lost frame')}")  # fmt: skip
        if s.no_tracked_frame:  # (the run exits with status 3: its last line names it)
            why = (f"its start failed ({s.start_failure}) and nothing started it again" if s.start_failure else
                   "the face was lost at every frame")  # fmt: skip
            lines.append(f"    warning: no tracked frame, every row unusable (success 0): {why}; its outputs are "
                         "written")  # fmt: skip
        if s.skipped:
            continue
        if s.declared_frames is not None:
            lines.append(f"    warning: {s.input} declares {counted(s.declared_frames, 'frame')}, {s.frames} could be "
                         "decoded (truncated or damaged?)")  # fmt: skip
        if s.not_met_again:  # (--resume: the rows tracked again for the online start; warned about as they were)
            were = plural(s.not_met_again, "was", "were")
            lines.append(f"    warning: {counted(s.not_met_again, 'row')} written before the interruption {were} not "
                         f"met again when tracked again: the CSV holds rows of two runs that disagree ({s.name}.json's "
                         "resumed says by how much; track it without --resume for rows of one run)")  # fmt: skip
    for name, why in zip(stopped, reasons):  # (VideosStopped: the error printed after the summary says where and why)
        blocks.append((name, [f"  {name}: {why}, not completed (its rows so far are kept in {name}.csv.partial)"]))
    at = {name: k for k, name in enumerate(names)}
    blocks.sort(key=lambda block: at.get(block[0], len(at)))  # (stable: without names, as they came)
    lines = ["", "summary", *(line for _, said in blocks for line in said)]
    written = [s for s in summaries if s.outputs]  # (--keep-going: a skipped input has none)
    if written:
        folder = Path(written[0].outputs[0]).parent
        meshes = any(Path(o).name.endswith("_meshes") for s in summaries for o in s.outputs)  # (--meshes)
        kinds = ".csv, .json, _overlay.mp4, _plot.png, _normalised.mp4" + (", _meshes/" if meshes else "")
        lines.append(f"outputs in {folder}/ (per video: {kinds})")
    out.write("\n".join(lines) + "\n")
    out.flush()


@contextlib.contextmanager
def _warnings_as_lines(display: ProgressDisplay | None) -> Iterator[None]:
    """Within the block, a warning that torchface issues is printed as one line ``torchface: warning: ...`` on
    stderr, as its errors are (``torchface: error: ...``), through the progress ``display`` where there is one;
    one that other code issues, as Python prints it. (They were printed as Python prints them, with the file and
    line of the code that called ``track_videos`` and the warning's class: ``.../torchface/cli.py:287:
    RuntimeWarning: ...``.)"""
    package = os.path.dirname(os.path.abspath(__file__)) + os.sep
    previous = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        if file is not None or not os.path.abspath(filename).startswith(package):
            previous(message, category, filename, lineno, file, line)
            return
        text = " ".join(str(_focal_hint(message)).split())
        text = f"torchface: warning: {text.removeprefix('torchface: ')}"
        if display is not None and not display.broken:
            display.note(text)
        else:
            _say(text)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = previous


def _focal_hint(message: object) -> object:
    """A :class:`~torchface.geometry.camera.MixedUpIntrinsics` warning of the camera ``torchface track`` makes
    (``Intrinsics.default(W, H, --focal)``: square pixels, the principal point the frames' centre, so a focal length
    under 5 % of the frame is all it can find) as what to type, ``--focal``, not ``Intrinsics``' arguments (which
    the command line takes none of); any other ``message`` as it is."""
    camera = sys.modules.get("torchface.geometry.camera")  # (no import here: a warning's line may be written from a
    # signal handler; the warning's class is loaded where one was made)
    cam = message.intrinsics if camera is not None and isinstance(message, camera.MixedUpIntrinsics) else None
    if cam is None or not (cam.fx == cam.fy and (cam.cx, cam.cy) == ((cam.width - 1) / 2, (cam.height - 1) / 2)):
        return message
    f, side = float(cam.fx), max(cam.width, cam.height)
    units = f" (a focal length in normalised units, f / max(W, H)? --focal {f * side:g})" if f < 10 else ""
    return (f"--focal {f:g} is under 5 % of the {cam.width}x{cam.height} frames' larger side (a field of view over "
            f"175 degrees), tracked as given: --focal is in pixels{units}; without --focal it is max(W, H), {side}")


def _run_track(
    videos, out_dir, landmarks, detector, focal, device, resume, meshes, quiet, convert=False, lookahead=False,
    online_refine=True, max_batch=128, restart_after_unmatched=0, motion_prediction=0.0, model=None, smooth=False,
    keep_going=False, keep_expression=False, fps=None,
) -> int:
    from torchface.geometry._checks import check_number
    from torchface.job import InputSkipped, JobConfig, VideosStopped, _for_command_line, track_videos
    from torchface.template.management import TemplateConfig
    from torchface.tracker.lookahead import LookaheadConfig
    from torchface.tracker.smoothing import SmoothingConfig
    from torchface.tracker.step import TrackerConfig

    tracker = TrackerConfig()
    if restart_after_unmatched:
        if detector is None:  # (main refuses it as a usage error first)
            raise ValueError("--restart-after-unmatched needs --detector (the restart starts from its landmarks)")
        tracker = replace(tracker, template=replace(tracker.template, restart_after_unmatched=restart_after_unmatched))
    if motion_prediction:
        tracker = replace(tracker, motion_prediction=motion_prediction)
    if focal is not None:  # (named as typed: JobConfig's message says "focal")
        check_number(focal, "--focal", "(0, inf)", unit="pixels")
    config = JobConfig(
        out_dir=out_dir, landmarks=tuple(landmarks or ()), detector=detector, focal=focal, device=device,
        resume=resume, convert=convert, meshes=meshes, lookahead=LookaheadConfig() if lookahead else None,
        refine_first=LookaheadConfig() if online_refine else None, max_batch=max_batch, tracker=tracker, model=model,
        smoothing=SmoothingConfig() if smooth else None, keep_going=keep_going, keep_expression=keep_expression,
        fps=fps,
    )  # fmt: skip
    display = None if quiet else ProgressDisplay()
    summaries = None
    stopped: tuple[str, ...] = ()
    reasons: tuple[str, ...] = ()
    try:
        try:
            # (the job's messages name this command's options: --resume, not JobConfig's resume=True)
            with _for_command_line(), _warnings_as_lines(display), warnings.catch_warnings():
                # (each skipped input's line, also where one of the same text was warned before in this process)
                warnings.simplefilter("always", InputSkipped)
                summaries = track_videos(videos, config, progress=display)
        except VideosStopped as exc:  # the other videos are complete: their summary, then the error (status 2)
            stopped, reasons = exc.stopped, exc.reasons
            if display is not None:
                display.flush()
            _print_summary(exc.summaries, sys.stdout, exc.stopped, exc.reasons, exc.names)
            raise
        if display is not None:
            display.flush()  # the last reports, when a redraw was due later
        _print_summary(summaries, sys.stdout)
        # (without --keep-going every video is complete, or an error was raised; a video of no tracked frame is
        # complete, its outputs written with every row unusable: a script over many videos took it for a tracked one)
        if not all(s.complete and not s.no_tracked_frame for s in summaries):
            _say(f"torchface: {_incomplete(summaries)}")
            return EXIT_INCOMPLETE
    except KeyboardInterrupt as exc:  # (the job says what it leaves; interrupted once it has returned: complete)
        if getattr(exc, "kept", None) is None and stopped:  # (it said "nothing was written")
            partial = ", ".join(os.path.join(str(out_dir), f"{name}.csv.partial") for name in stopped)
            whose = "its" if len(stopped) == 1 else "their"
            kept = f"every video is complete but {'; '.join(f'{n}, {why}' for n, why in zip(stopped, reasons))}: "
            exc.kept = kept + f"{whose} rows are kept in {partial}"  # type: ignore[attr-defined]
        elif summaries is not None and getattr(exc, "kept", None) is None:  # (keep_going: some may not be)
            kept_in = {s.name: os.path.join(str(out_dir), f"{s.name}.csv.partial") for s in summaries}
            but = [f"{s.name}, skipped (nothing written)" if s.refused is not None else
                   f"{s.name}, stopped partway: its rows are kept in {kept_in[s.name]}"
                   for s in summaries if not s.complete]  # fmt: skip
            said = ", and ".join([", ".join(but[:-1]), but[-1]] if len(but) > 1 else but)
            exc.kept = "every video is complete" + (f" but {said}" if but else "")  # type: ignore[attr-defined]
        raise
    return 0


def _incomplete(summaries) -> str:
    """The last line of a run (status 3) that skipped inputs or whose videos stopped partway (``--keep-going``), or in
    which videos have no tracked frame (:attr:`~torchface.job.VideoSummary.no_tracked_frame`, their outputs
    written): how many of each, named (the first 10), and how many others are complete."""
    said = []
    for what, names in (("skipped", [s.name for s in summaries if s.refused is not None]),
                        ("stopped partway", [s.name for s in summaries if s.stopped is not None]),
                        ("with no tracked frame", [s.name for s in summaries if s.no_tracked_frame])):  # fmt: skip
        if names:
            shown = ", ".join(names[:10]) + (f" and {len(names) - 10} more" if len(names) > 10 else "")
            said.append(f"{len(names)} {what} ({shown})")
    done = sum(s.complete and not s.no_tracked_frame for s in summaries)
    said = [", ".join(said[:-1]), said[-1]] if len(said) > 1 else said
    return (f"{' and '.join(said)} of the {counted(len(summaries), 'input')}, {done} complete "
            f"(exit status {EXIT_INCOMPLETE}; the summary says why)")  # fmt: skip


def _render_progress(label: str, start: float):
    def report(done: int, total: int) -> None:
        rate = done / max(time.perf_counter() - start, 1e-9)
        sys.stdout.write(f"\r{label}: {done}/{total} {plural(total, 'frame')} ({rate:.1f} fps)")
        sys.stdout.flush()

    return report


def _render_demo(args: argparse.Namespace) -> int:
    """Render a synthetic sequence with ground truth (the renderer's former ``demo`` command), and its first frame's
    68 landmarks as a ``--landmarks`` file, ``<name>_first_frame.csv`` (``x,y`` rows, pixels; empty cells for a point
    outside the frame), so that ``torchface track`` tracks the clip as it is: the ground truth's files are no
    landmarks file (``--landmarks <name>.gt.json`` or ``.gt.npz`` is refused), and a user had to write one in Python."""
    from torchface._atomic import written_whole
    from torchface.io.errors import dangling_link
    from torchface.io.video import opencv_path
    from torchface.synth.scenarios import SCENARIOS, make_scenario
    from torchface.synth.sequence import load_ground_truth, write_sequence

    if args.scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {args.scenario!r}; choose from {', '.join(SCENARIOS)}")
    if args.width < 16 or args.height < 16 or args.width % 2 or args.height % 2:
        raise ValueError(f"--width and --height must be even numbers >= 16, got {args.width}x{args.height}")
    if args.frames < 1:
        raise ValueError(f"--frames must be >= 1, got {args.frames}")
    link = dangling_link(args.out)  # (a dangling link said only "File exists")
    if link is not None:
        raise ValueError(f"--out {args.out}: {link} is a symbolic link to {os.readlink(link)}, which does not exist")
    for folder in (args.out, *args.out.parents):
        if folder.exists() and not folder.is_dir():
            raise ValueError(f"--out {args.out}: {folder} is a file, not a folder")
    opencv_path(args.out, ValueError)  # (the video is written by OpenCV: refused before the folder is made)
    spec = make_scenario(args.scenario, args.frames, args.width, args.height)
    first_frame = args.out / f"{spec.name}_first_frame.csv"
    with contextlib.suppress(FileNotFoundError, NotADirectoryError):  # (an earlier render's: never beside this one's)
        first_frame.unlink()
    start = time.perf_counter()
    files = write_sequence(spec, args.out, batch_size=8, progress=_render_progress(f"rendering {spec.name}", start))
    sys.stdout.write("\n")
    points = load_ground_truth(files.ground_truth).landmarks_px[0].numpy()  # (68, 2) float64 pixels
    u, v = points[:, 0], points[:, 1]
    inside = (u >= -0.5) & (u <= args.width - 0.5) & (v >= -0.5) & (v <= args.height - 0.5)
    rows = [f"{x!r},{y!r}" if ok else "," for (x, y), ok in zip(points.tolist(), inside.tolist())]
    with written_whole(first_frame) as tmp:
        tmp.write_text("x,y\n" + "\n".join(rows) + "\n", encoding="utf-8")
    took = time.perf_counter() - start
    print(f"wrote {counted(files.num_frames, 'frame')} ({args.width}x{args.height}, {spec.subject}) in {took:.1f} s:")
    print(f"  video         {files.video} (codec {files.codec.strip()})")
    print(f"  ground truth  {files.ground_truth}")
    print(f"  metadata      {files.metadata}")
    print(f"  first frame   {first_frame} (its 68 landmarks, pixels: a --landmarks file)")
    print("load it with torchface.synth.load_ground_truth and torchface.synth.read_video; track it with")
    print(f"  torchface track {shlex.quote(str(files.video))} --out results --landmarks "
          f"{shlex.quote(str(first_frame))}")  # (quoted where a shell needs it: a folder 'my synth')
    return 0


def _path(text: str) -> Path:
    """An argparse ``type``: a path, refused (a one-line usage error) where it is empty: ``Path("")`` is ``.``, so
    ``torchface track "$VIDEO" --out "$OUT"`` with the variables unset tracked the current folder's images and wrote
    its outputs there; or where it starts with a ``~`` or ``~user`` that a shell would expand, which it leaves as it is
    after ``=`` and in quotes (``--out=~/res`` wrote the outputs to a folder ``~`` in the working folder)."""
    if not text:
        raise argparse.ArgumentTypeError("an empty path (an unset shell variable?): give a file or folder")
    home = unexpanded_home(text)  # (--out=~/res, or quoted: a folder '~' in the working folder was made; a name
    # such as '~draft.mp4', which no user's home expands, is a name as any other)
    if home is not None and home[1]:
        raise argparse.ArgumentTypeError(
            f"{text!r} starts with '~', which the shell did not expand (quoted, or after '=' as in --out=~/...): give "
            "the path after a space, unquoted, or with $HOME"
        )
    if home is not None:  # (HOME unset, the user not in the password database: a shell cannot expand it either)
        raise argparse.ArgumentTypeError(
            f"{text!r} starts with '~', which nothing expanded ({no_home_reason(home[0])}): give the home folder's path"
        )
    return Path(text)


def _int_at_least(minimum: int, even: bool = False) -> Callable[[str], int]:
    """An argparse ``type``: an integer >= ``minimum`` (``--threads``, ``--max-batch``: 1;
    ``--restart-after-unmatched``: 0), and even if asked (the scripts' frame sides), else a one-line usage error
    (``must be an even integer >= 64, got '63'``). The scripts' ``_argtypes.integer`` is this one.

    Example:
        >>> _int_at_least(1)("3"), _int_at_least(32, even=True)("64")
        (3, 64)
    """

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


_threads = _int_at_least(1)

#: Suffixes of landmarks files (``--landmarks``, :func:`torchface.io.read_landmarks`) that no frame input has
#: (``.npy`` is both).
_LANDMARKS_SUFFIXES: tuple[str, ...] = (".csv", ".tsv", ".txt", ".pts", ".json")


def _landmarks_among_videos(videos: list[Path], landmarks: list[Path] | None) -> str | None:
    """A usage error's text (None: none) where an input of ``torchface track`` is a landmarks file (a file named
    ``.csv``, ``.pts``, ...: :data:`_LANDMARKS_SUFFIXES`): ``clips/*.mp4 --landmarks lm/*.csv`` gave ``--landmarks``
    the first file and took the others as videos, and the error said "give one landmarks file per video: 3 videos,
    1 files" of 2 videos and 2 files; an input that is not a video was refused as one OpenCV cannot open."""
    stray = [v for v in videos if v.suffix.lower() in _LANDMARKS_SUFFIXES and not v.is_dir()]
    if not stray:
        return None
    named = ", ".join(map(str, stray[:3])) + (f" and {len(stray) - 3} more" if len(stray) > 3 else "")
    what = "is a landmarks file" if len(stray) == 1 else "are landmarks files"
    said = f"argument videos: {named} {what}, not a video"
    if landmarks is None:
        return f"{said}: give it with --landmarks FILE"
    return (f"{said}: --landmarks takes one file, so give it before each (--landmarks a.csv --landmarks b.csv, or "
            "a.mp4 --landmarks a.csv b.mp4 --landmarks b.csv); after a glob (--landmarks lm/*.csv) the files after "
            "the first were taken as videos")  # fmt: skip


def _frame_rate(text: str) -> float:
    """An argparse ``type``: a frame rate in :data:`torchface.job.FPS_RANGE` (``--fps``), else a one-line usage error
    (``must be a number of frames per second in (0.001, 1000], got '0'``)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.001 < value <= 1000.0:  # (NaN and inf too; torchface.job.FPS_RANGE, not imported here: it loads torch)
        raise argparse.ArgumentTypeError(f"must be a number of frames per second in (0.001, 1000], got {text!r}")
    return value


def _fraction(text: str) -> float:
    """An argparse ``type``: a number in [0, 1] (``--motion-prediction``), else a one-line usage error."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 <= value <= 1.0:  # (NaN too)
        raise argparse.ArgumentTypeError(f"must be a number in [0, 1], got {text!r}")
    return value


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``torchface`` console script; returns the exit status.

    ``argv`` None (the command's own process: the console script, ``python -m torchface``; its arguments are
    ``sys.argv``'s): a run stopped by Ctrl-C ends the process by SIGINT once it has said what it keeps
    (:func:`_end_by_sigint`), so that a shell loop over videos stops there; a shell reports status 130 either way.
    Called with ``argv`` (from Python), it returns :data:`EXIT_INTERRUPTED`."""
    for name in ("stdout", "stderr"):
        if getattr(sys, name) is None:  # closed by the caller (``>&-``): Python leaves None there
            setattr(sys, name, open(os.devnull, "w", encoding="utf-8"))
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if args.command == "track":
        # inputs after an option: each video with its landmarks (``a.mp4 --landmarks a.csv b.mp4 --landmarks
        # b.csv``, as a script pairs them) was refused as "unrecognized arguments: b.mp4"; after ``--`` any name
        cut = extra.index("--") if "--" in extra else len(extra)
        if not any(x.startswith("-") for x in extra[:cut]):
            try:
                args.videos += [_path(x) for x in extra[:cut] + extra[cut + 1 :]]
            except argparse.ArgumentTypeError as exc:
                parser.error(f"argument videos: {exc}")
            extra = []
    if extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    if args.command == "track" and (stray := _landmarks_among_videos(args.videos, args.landmarks)) is not None:
        parser.error(stray)
    if args.command == "track" and args.restart_after_unmatched and args.detector is None:
        parser.error("--restart-after-unmatched needs --detector (the restart starts from its landmarks)")
    with _ffmpeg_log_quiet():
        status = _run(args)
    if argv is None and status == EXIT_INTERRUPTED:
        _end_by_sigint()
    return status


def _end_by_sigint() -> None:
    """End this process by SIGINT (its default action), its output flushed, as Python ends a program after an
    uncaught ``KeyboardInterrupt``: a shell that runs a command in a loop (``for v in *.mp4; do torchface track "$v"
    ...; done``) and gets the Ctrl-C with it stops the loop only where the command died of SIGINT (bash's "wait and
    cooperative exit"); one that exits with 130 itself is taken for a program that handled the Ctrl-C, and the loop
    went on to the next video. Its status as a shell reports it stays 130 (128 + SIGINT; Python's ``subprocess``:
    -2). Not on Windows (no such signal death: its status stays 130).

    The ``atexit`` functions run first, as Python runs them before it ends that way (the multiprocessing
    finalizers, a private native-kernel folder's removal, the MediaPipe detector's close: the signal's default
    action ran none of them); a second Ctrl-C or an error among them does not keep the process from ending so."""
    if os.name != "posix":
        return
    try:
        atexit._run_exitfuncs()  # (each runs once: the process ends below, before the interpreter would run them)
    except BaseException:  # noqa: BLE001 (a second Ctrl-C among them: the process still ends by SIGINT)
        pass
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError, AttributeError):
            stream.flush()
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    os.kill(os.getpid(), signal.SIGINT)


@contextlib.contextmanager
def _ffmpeg_log_quiet() -> Iterator[None]:
    """Leave FFmpeg's own log lines (``[mov,mp4,m4a,3gp,3g2,mj2 @ 0x...] moov atom not found`` above the one-line
    error of an empty or damaged video, ``[mjpeg @ 0x...] overread 8`` at each damaged frame, between the progress
    bars) out unless asked for: ``OPENCV_FFMPEG_LOGLEVEL`` set to :data:`FFMPEG_LOG_QUIET` where unset, for the
    command's run only (:func:`main` called in a notebook or a test left it set for the rest of the process and the
    processes it started). OpenCV reads it once per process, when its FFmpeg backend is first used: in such a process
    FFmpeg's level stays what the first use found."""
    unset = "OPENCV_FFMPEG_LOGLEVEL" not in os.environ
    if unset:
        os.environ["OPENCV_FFMPEG_LOGLEVEL"] = FFMPEG_LOG_QUIET
    try:
        yield
    finally:
        if unset and os.environ.get("OPENCV_FFMPEG_LOGLEVEL") == FFMPEG_LOG_QUIET:
            del os.environ["OPENCV_FFMPEG_LOGLEVEL"]


def _run(args: argparse.Namespace) -> int:
    """Run the command ``args`` (parsed and checked by :func:`main`); returns its exit status."""
    try:  # torch's import (every command needs it) takes seconds: a Ctrl-C there printed a long traceback
        import torch

        if getattr(args, "threads", None) is not None:
            torch.set_num_threads(args.threads)
        from torchface.detect import DetectorUnavailable
        from torchface.io.errors import InputError, OutputError
    except KeyboardInterrupt:
        _say("\ntorchface: interrupted before it started; run it again")
        return EXIT_INTERRUPTED

    try:
        with _sigterm_as_interrupt():
            return _dispatch(args)
    except (InputError, OutputError, DetectorUnavailable, ValueError) as exc:
        message = " ".join(str(exc).split())
        _say(f"torchface: error: {message}")
        return EXIT_USAGE
    except BrokenPipeError:  # the reader of stdout has gone (``| head -1``): the outputs are written
        with contextlib.suppress(OSError, ValueError, AttributeError):  # where Python flushes it at exit
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except OSError as exc:  # a file system refusal the checks before tracking could not foresee
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        _say(f"torchface: error: {where}{exc.strerror or exc}")
        return EXIT_USAGE
    except KeyboardInterrupt as exc:
        how = "terminated" if isinstance(exc, _Terminated) else "interrupted"
        error = getattr(exc, "error", None)  # (the job's loop stopped by an error while the signal waited)
        said = ""
        if isinstance(error, Exception):
            said = " ".join(str(error).split()) or type(error).__name__
            said = f"\ntorchface: error: {said}"
        if args.command == "track":  # (the job says what it leaves; interrupted outside it, before it wrote)
            then = getattr(exc, "kept", None) or "nothing was written: run the same command again"
        else:
            then = "run it again to start over"
        _say(f"{said}\ntorchface: {how}; {then}")
        return EXIT_TERMINATED if isinstance(exc, _Terminated) else EXIT_INTERRUPTED


def _say(line: str) -> None:
    """Print ``line`` on stderr, if it can still be written (its reader may have gone)."""
    with contextlib.suppress(OSError, ValueError):
        print(line, file=sys.stderr, flush=True)


def _dispatch(args: argparse.Namespace) -> int:
    """Run the parsed command; returns its exit status."""
    if args.command == "track":
        return _run_track(args.videos, args.out, args.landmarks, args.detector, args.focal, args.device,
                          args.resume, args.meshes, args.quiet, args.convert, args.lookahead,
                          not args.no_online_refine, args.max_batch, args.restart_after_unmatched,
                          args.motion_prediction, args.model, args.smooth, args.keep_going,
                          args.keep_expression, args.fps)  # fmt: skip
    if args.command == "demo":
        from torchface.job import DEMO_ATTRIBUTION, demo_inputs

        video, landmarks = demo_inputs()
        print(f"torchface demo: tracking the embedded clip ({DEMO_ATTRIBUTION})")
        return _run_track([video], args.out, [landmarks], None, None, args.device, False, args.meshes, args.quiet)
    if args.command == "render-demo":
        return _render_demo(args)
    raise AssertionError(f"unhandled command {args.command}")  # argparse rejects unknown commands


if __name__ == "__main__":
    raise SystemExit(main())
