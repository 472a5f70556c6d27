#!/usr/bin/env python
"""Render synthetic scenarios (the standard set and the long runs) to lossless videos with ground truth.

Writes, per scenario, <out>/<name>.avi (FFV1), <name>.gt.npz and <name>.gt.json. ``--scenario all`` is the
five standard scenarios; ``long`` is the two 3000-frame long runs (``long_run``: CANDIDE-3 textured,
``long_run_scan``: the James scan; large turns back to frontal, light changes, occluders, the face leaving
the frame); ``everything`` is both. A full-size long run is ~0.5 GB and takes several minutes to render.

Examples:
    python scripts/make_sequence.py --scenario all --size small --out out/synth_small
    python scripts/make_sequence.py --scenario pose_sweep --size full --out out/synth
    python scripts/make_sequence.py --scenario occlusion --width 320 --height 240 --frames 60 --out out/x
    python scripts/make_sequence.py --scenario long_run --width 320 --height 240 --frames 600 --out out/long
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _argtypes beside this script, however it is run
from _argtypes import folder_problem  # noqa: E402
from _argtypes import run_command  # noqa: E402

from torchface.cli import is_terminal
from torchface.synth.scenarios import (
    ALL_SCENARIOS,
    LONG_RUN_MIN_FRAMES,
    LONG_SCENARIOS,
    SCENARIOS,
    SIZES,
    make_scenario,
    scenario_size,
)
from torchface.synth.sequence import write_sequence


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument(
        "--scenario", default="all",
        help=f"one of {', '.join(ALL_SCENARIOS)}, 'all' (the standard five), 'long' or 'everything'",
    )  # fmt: skip
    parser.add_argument("--size", default="small", choices=tuple(SIZES), help="named size (default small)")
    parser.add_argument("--width", type=int, help="override the width")
    parser.add_argument("--height", type=int, help="override the height")
    parser.add_argument("--frames", type=int, help="override the number of frames")
    parser.add_argument("--batch", type=int, default=8, help="frames rendered at once")
    parser.add_argument("--out", type=Path, default=Path("out/synth"), help="output folder")
    args = parser.parse_args(argv)
    groups = {"all": list(SCENARIOS), "long": list(LONG_SCENARIOS), "everything": list(ALL_SCENARIOS)}
    names = groups.get(args.scenario, [args.scenario])
    for name in names:
        if name not in ALL_SCENARIOS:
            parser.error(f"unknown scenario {name!r}; choose from {', '.join(ALL_SCENARIOS)}, all, long or everything")
    for option, value in (("--width", args.width), ("--height", args.height)):
        if value is not None and (value < 8 or value % 2):
            parser.error(f"{option} must be even and >= 8 (a video's frames), got {value}")
    if args.frames is not None and args.frames < 1:
        parser.error(f"--frames must be >= 1, got {args.frames}")
    # before any rendering: a long run's timeline needs its frames (with 'everything' the five standard scenarios
    # were rendered first, then a traceback)
    long_names = [n for n in names if n in LONG_SCENARIOS]
    if long_names and args.frames is not None and args.frames < LONG_RUN_MIN_FRAMES:
        parser.error(f"--frames must be >= {LONG_RUN_MIN_FRAMES} for {', '.join(long_names)}, got {args.frames}")
    if args.batch < 1:
        parser.error(f"--batch must be >= 1, got {args.batch}")
    if (problem := folder_problem(args.out)) is not None:
        parser.error(f"--out {args.out}: {problem}")
    # a terminal gets one line redrawn in place; a pipe or a log whole lines, one each 10 s and the last (the \r
    # redraws ran together there: "... (4.4 fps)expressions: 12/12 ..."), as torchface track's progress does
    tty = is_terminal(sys.stdout)  # (the CLI's rule: a stream without isatty, a notebook's, is not one)
    for name in names:
        w, h, t = scenario_size(name, args.size)
        w = args.width if args.width is not None else w
        h = args.height if args.height is not None else h
        t = args.frames if args.frames is not None else t
        spec = make_scenario(name, t, w, h)
        start = time.perf_counter()

        printed = [-math.inf]  # (when the last whole line was printed)

        def progress(
            done: int, total: int, name: str = name, start: float = start, printed: list[float] = printed
        ) -> None:
            now = time.perf_counter()
            line = f"{name}: {done}/{total} frames ({done / max(now - start, 1e-9):.1f} fps)"
            if tty:
                sys.stdout.write(f"\r{line}")
            elif done >= total or now - printed[0] >= 10.0:
                printed[0] = now
                sys.stdout.write(line + "\n")
            sys.stdout.flush()

        files = write_sequence(spec, args.out, batch_size=args.batch, progress=progress)
        took = time.perf_counter() - start
        if tty:
            sys.stdout.write("\n")
        print(
            f"  wrote {files.video} ({files.num_frames} frames {w}x{h}, codec {files.codec.strip()}), "
            f"{files.ground_truth.name}, {files.metadata.name} in {took:.1f} s"
        )
    return 0


if __name__ == "__main__":
    run_command(main)
