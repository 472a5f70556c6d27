#!/usr/bin/env python
"""Tracker throughput on a GPU (or any torch device) against this machine's CPU, measured in the same run.

Each row tracks B streams with the default settings (``TrackerConfig()``: template management on, float32) through
``managed_step``, as :class:`~torchface.tracker.FaceTracker` steps, and prints ms per step, frames per second, the
mean rotation error against the ground truth, the fraction of successful frames, and the peak memory per stream.
On a GPU the device rows run the torch code (the native kernels are CPU only; with ``--device cpu`` they run there
too); the CPU rows, the reference, run the default backend (the native kernels where a C compiler is found) on all
of this machine's cores. The ratio is device frames/s
over CPU frames/s at the same B where both were run.

Frames: the ``pose_sweep`` scenario at ``--width`` x ``--height``, rendered by torchface's renderer (cached under
``--cache`` as for benchmark.py), held on the device before the clock starts (a data loader's upload is not timed).
Stream b starts at frame b and runs back and forth over the sweep's first ``--frames`` frames, so the streams differ
and any B can be run. Initialisation: the ground-truth landmarks of each stream's first frame with 2 px of noise.

Device memory: the peak allocated by torch during a row (initialisation and steps), less what was held before it
(the frames), per stream. CPU memory is not measured here (benchmark.py's rows do that per process).

Usage:
    python scripts/benchmark_device.py [--device cuda] [--batches 1,8,32,128,512,1024] [--cpu-batches 1,32,128]
                                       [--steps 20] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmark.py and _argtypes beside this script
from _argtypes import checkout_out, device_problem, file_problem, folder_problem, output_file  # noqa: E402
from _argtypes import integer as _integer  # noqa: E402
from _argtypes import run_command  # noqa: E402

import torch

from torchface.io.sidecar import write_json

from benchmark import batch_list, frame_size_problem, pose_sweep_frames  # noqa: E402

WARM_STEPS = 3


def _ping_pong(i: torch.Tensor, count: int) -> torch.Tensor:
    """Frame index ``i`` folded back and forth over ``0 .. count - 1``: 0, 1, .., count - 1, count - 2, .., 0, 1, .."""
    period = 2 * (count - 1)
    j = i % period
    return torch.where(j < count, j, period - j)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _row(device: torch.device, batch: int, steps: int, frames: torch.Tensor, landmarks: torch.Tensor,
         rotations: torch.Tensor, intrinsics: object) -> dict[str, float]:
    """B streams tracked for ``WARM_STEPS + steps`` steps on ``device``; the figures of the timed steps."""
    from torchface.geometry.so3 import geodesic_angle_deg
    from torchface.model.candide import load_candide3
    from torchface.tracker import TrackerConfig, initialise_managed, managed_step

    T = frames.shape[0]
    model = load_candide3(device=device)
    config = TrackerConfig()
    on_device = frames.to(device)
    start = torch.arange(batch)
    gen = torch.Generator().manual_seed(0)
    lm0 = landmarks[_ping_pong(start, T)] + 2.0 * torch.randn(batch, landmarks.shape[1], 2, generator=gen)
    cuda = device.type == "cuda"
    if cuda:
        _sync(device)
        held = torch.cuda.memory_allocated(device)
        torch.cuda.reset_peak_memory_stats(device)
    first = _ping_pong(start, T)
    state, res = initialise_managed(model, config, on_device[first.to(device)], lm0.to(device), intrinsics)
    R0 = res.rotation.double().cpu()
    elapsed, errors, success, points, iterations = 0.0, [], 0.0, 0.0, 0.0
    for k in range(1, WARM_STEPS + steps + 1):
        index = _ping_pong(start + k, T)
        batch_frames = on_device[index.to(device)]
        _sync(device)
        t0 = time.perf_counter()
        state, res = managed_step(model, config, state, batch_frames, donate=True)
        _sync(device)
        if k > WARM_STEPS:
            elapsed += time.perf_counter() - t0
            R = res.rotation.double().cpu()
            gt = rotations[index] @ rotations[first].mT
            errors.append(geodesic_angle_deg(R @ R0.mT, gt))
            success += float(res.success.float().mean())
            points += float(res.num_points.float().mean())
            iterations += float(res.iterations.float().mean())
    error = torch.cat(errors)
    row = {"batch": batch, "ms_per_step": 1000 * elapsed / steps, "fps": batch * steps / elapsed,
           "mean_error_deg": float(error.mean()), "max_error_deg": float(error.max()),
           "success": success / steps, "points": points / steps, "iterations": iterations / steps}
    if cuda:
        row["mb_per_stream"] = (torch.cuda.max_memory_allocated(device) - held) / 2**20 / batch
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    ap.add_argument("--device", default="cuda", help="the torch device measured (default cuda)")
    ap.add_argument("--batches", default="1,8,32,128,512,1024",
                    help="streams per batch on the device, comma list (default 1,8,32,128,512,1024)")
    ap.add_argument("--cpu-batches", default="1,32,128",
                    help="streams per batch of the CPU reference rows, comma list ('' for none; default 1,32,128)")
    ap.add_argument("--threads", type=_integer(1), default=os.cpu_count() or 1,
                    help="CPU threads (default: all cores)")
    ap.add_argument("--steps", type=_integer(1), default=20, help=f"timed steps per row, after {WARM_STEPS} warm-up")
    ap.add_argument("--frames", type=_integer(4), default=150, help="frames of the sweep used, at most 150")
    ap.add_argument("--width", type=_integer(64, even=True), default=640, help="frame width (default 640)")
    ap.add_argument("--height", type=_integer(64, even=True), default=480, help="frame height (default 480)")
    ap.add_argument("--cache", default=checkout_out("bench"),
                    help="frame cache folder, benchmark.py's (default: out/bench of this checkout, %(default)s, from "
                    "any working folder)")
    ap.add_argument("--json", type=output_file, default=None, help="write the figures as JSON here")
    args = ap.parse_args(argv)
    try:
        batches, cpu_batches = batch_list(args.batches), batch_list(args.cpu_batches)
    except ValueError:
        ap.error(f"--batches and --cpu-batches must be comma lists of integers, got {args.batches!r}, "
                 f"{args.cpu_batches!r}")  # fmt: skip
    if any(b < 1 for b in batches + cpu_batches):
        ap.error("every batch must be >= 1")
    if not batches + cpu_batches:  # (the frames were rendered, then no row run: a bare header, exit status 0)
        ap.error("--batches and --cpu-batches are both empty: no row to run")
    if args.frames > 150:
        ap.error(f"--frames must be in 4..150 (the sweep's slow first half), got {args.frames}")
    if (problem := frame_size_problem(args.width, args.height, args.frames)) is not None:
        ap.error(f"--width and --height: {problem}")
    if (problem := device_problem(args.device)) is not None:
        ap.error(f"--device {args.device}: {problem}")
    if (problem := folder_problem(Path(args.cache))) is not None:
        ap.error(f"--cache {args.cache}: {problem}")
    if args.json is not None and (problem := file_problem(Path(args.json))) is not None:
        ap.error(f"--json {args.json}: {problem}")
    device = torch.device(args.device)
    torch.set_num_threads(args.threads)
    print(f"rendering / loading {args.frames} frames at {args.width}x{args.height} ...", file=sys.stderr)
    frames, landmarks, intrinsics = pose_sweep_frames(Path(args.cache), args.width, args.height, args.frames)
    from torchface.synth.scenarios import make_scenario

    rotations = make_scenario("pose_sweep", 150, args.width, args.height).rotation[: args.frames].double()
    figures: dict[str, dict[str, float]] = {}
    for label, where, rows in (("device", device, batches), ("cpu", torch.device("cpu"), cpu_batches)):
        for b in rows:
            r = _row(where, b, args.steps, frames, landmarks, rotations, intrinsics)
            figures[f"{label}_batch_{b}"] = r
            print(f"  {where} B={b}: {r['fps']:.0f} frames/s", file=sys.stderr)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else str(device)
    print(f"\ntorchface tracker on {name} ({device}) (device rows) against the CPU (cpu rows; {args.threads} threads "
          f"of {os.cpu_count()} cores), {args.width}x{args.height}, default settings, {args.steps} timed steps per row")
    print(f"{'row':<18}{'ms/step':>10}{'frames/s':>10}{'vs CPU':>8}{'mean err':>10}{'max err':>9}{'success':>9}"
          f"{'points':>8}{'iters':>7}{'MB/stream':>11}")
    for key, r in figures.items():
        cpu = figures.get(f"cpu_batch_{r['batch']}")
        ratio = f"{r['fps'] / cpu['fps']:.2f}x" if cpu is not None and key.startswith("device") else "-"
        if ratio != "-":
            r["ratio_to_cpu"] = r["fps"] / cpu["fps"]
        mb = f"{r['mb_per_stream']:.1f}" if "mb_per_stream" in r else "-"
        print(f"{key:<18}{r['ms_per_step']:>10.1f}{r['fps']:>10.1f}{ratio:>8}{r['mean_error_deg']:>9.2f}°"
              f"{r['max_error_deg']:>8.2f}°{r['success']:>9.3f}{r['points']:>8.0f}{r['iterations']:>7.1f}{mb:>11}")
    print("errors: geodesic rotation error relative to each stream's first frame, degrees, over the timed steps")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)  # (as the other scripts' --json)
        write_json(Path(args.json), figures)
    return 0


if __name__ == "__main__":
    run_command(main)
