"""Command-line interface: ``torchface <command>``.

Commands:
    ``demo``   render a short synthetic sequence with ground truth (``pose_sweep``, 320x240, 40
               frames by default) into ``./torchface-demo/``.

The parser is built by :func:`build_parser`, one sub-parser per command, each with a handler
``_cmd_<name>(args) -> int``; a ``track`` command registers the same way.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

__all__ = ["build_parser", "main"]


def _progress(label: str, start: float):
    def report(done: int, total: int) -> None:
        rate = done / max(time.perf_counter() - start, 1e-9)
        sys.stdout.write(f"\r{label}: {done}/{total} frames ({rate:.1f} fps)")
        sys.stdout.flush()

    return report


def _cmd_demo(args: argparse.Namespace) -> int:
    from torchface.synth.scenarios import SCENARIOS, make_scenario
    from torchface.synth.sequence import write_sequence

    if args.scenario not in SCENARIOS:
        print(f"unknown scenario {args.scenario!r}; choose from {', '.join(SCENARIOS)}", file=sys.stderr)
        return 2
    spec = make_scenario(args.scenario, args.frames, args.width, args.height)
    start = time.perf_counter()
    files = write_sequence(spec, args.out, batch_size=8, progress=_progress(f"rendering {spec.name}", start))
    sys.stdout.write("\n")
    took = time.perf_counter() - start
    print(f"wrote {files.num_frames} frames ({args.width}x{args.height}, {spec.subject}) in {took:.1f} s:")
    print(f"  video         {files.video} (codec {files.codec.strip()})")
    print(f"  ground truth  {files.ground_truth}")
    print(f"  metadata      {files.metadata}")
    print("load it with torchface.synth.load_ground_truth and torchface.synth.read_video")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``torchface`` argument parser with one sub-command per task."""
    parser = argparse.ArgumentParser(prog="torchface", description="3D face tracking in PyTorch.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    demo = sub.add_parser("demo", help="render a short synthetic sequence with ground truth")
    demo.add_argument("--out", type=Path, default=Path("torchface-demo"), help="output folder (default ./torchface-demo)")
    demo.add_argument("--scenario", default="pose_sweep", help="scenario name (default pose_sweep)")
    demo.add_argument("--frames", type=int, default=40, help="number of frames (default 40)")
    demo.add_argument("--width", type=int, default=320, help="frame width (default 320)")
    demo.add_argument("--height", type=int, default=240, help="frame height (default 240)")
    demo.set_defaults(handler=_cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``torchface`` console script; returns the exit status."""
    args = build_parser().parse_args(list(argv) if argv is not None else None)
    return int(args.handler(args))


if __name__ == "__main__":
    raise SystemExit(main())
