#!/usr/bin/env python
"""Time the textured renderer per frame at 640x480 for CANDIDE-3 and the James scan, B = 1 and 8.

Two figures per case: `render` (rasterize + shade, torchface.rendering.shading.render) and `frame`
(the whole synthetic frame: deformation, normals, background, render, ground-truth landmarks and
their exact visibility). Minimum and median over repeats after one warm-up, in milliseconds per
frame (the minimum is the better estimate on a shared, busy machine).

Example:
    python scripts/benchmark_render.py --repeats 3
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _argtypes beside this script, however it is run
from _argtypes import integer as _integer  # noqa: E402
from _argtypes import run_command  # noqa: E402

import torch

from torchface.geometry.camera import Intrinsics
from torchface.geometry.transforms import transform_points
from torchface.rendering.shading import render
from torchface.synth.scenarios import make_scenario
from torchface.synth.sequence import iter_sequence
from torchface.synth.subjects import get_subject


def _times_ms(fn, repeats: int, frames: int) -> tuple[float, float]:
    """``(min, median)`` milliseconds per frame over ``repeats`` calls after one warm-up."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1000.0 * min(times) / frames, 1000.0 * statistics.median(times) / frames


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--width", type=_integer(8), default=640, help="frame width (default 640)")
    parser.add_argument("--height", type=_integer(8), default=480, help="frame height (default 480)")
    parser.add_argument("--repeats", type=_integer(1), default=3, help="timed renders per row (default 3)")
    parser.add_argument("--threads", type=_integer(0), default=0, help="torch threads (0: leave the default)")
    args = parser.parse_args(argv)
    # one-line errors, not tracebacks (--repeats 0: after the warm-up renders)
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    if args.threads < 0:
        parser.error(f"--threads must be >= 1 (or 0: torch's default), got {args.threads}")
    if args.width < 8 or args.height < 8:
        parser.error(f"--width and --height must be >= 8, got {args.width}x{args.height}")
    if args.threads:
        torch.set_num_threads(args.threads)
    w, h = args.width, args.height
    cam = Intrinsics.default(w, h)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {w}x{h}, {args.repeats} repeats")
    print(f"{'subject':<10} {'B':>3} {'render ms/frame (min / median)':>32} {'frame ms/frame (min / median)':>31}")
    for name, scenario in (("candide3", "pose_sweep"), ("james", "scan_motion")):
        subject = get_subject(name)
        for b in (1, 8):
            spec = make_scenario(scenario, b, w, h)
            verts = subject.deform(subject.shape_coeffs.expand(b, -1), spec.anim.float(), b)
            R, t = spec.rotation.float(), spec.translation.float()
            verts_cam = transform_points(R, t, verts)
            normals = subject.vertex_normals(verts) @ R.transpose(-1, -2)
            light = spec.light.to(dtype=torch.float32)

            def run_render() -> None:
                render(verts_cam, subject.faces, subject.uv, subject.texture, normals, light, cam)

            def run_frame() -> None:
                for _ in iter_sequence(spec, batch_size=b):
                    pass

            r = _times_ms(run_render, args.repeats, b)
            f = _times_ms(run_frame, args.repeats, b)
            print(f"{name:<10} {b:>3} {r[0]:>20.1f} / {r[1]:>8.1f} {f[0]:>19.1f} / {f[1]:>8.1f}")
    return 0


if __name__ == "__main__":
    run_command(main)
