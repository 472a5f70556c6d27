"""Time the online look-ahead start's re-anchoring frame when B streams turn together.

An 8-frame 320x240 clip of the CANDIDE-3 face (James photo texture) turning 0 -> 15 degrees of yaw in 3-degree steps;
B streams of it, each with its own first-frame landmark noise (1.5 px), tracked by the default ``FaceTracker``: all
re-anchor on frame 4 (12 degrees), in one batched refinement. Prints, per B, the process CPU time of the slowest
frame (the re-anchoring), of the whole run and the median of the other frames, on one thread.

Usage:
    python scripts/benchmark_reanchor.py [B ...]   (default 1 4 8)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _argtypes beside this script, however it is run
from _argtypes import integer  # noqa: E402
from _argtypes import run_command  # noqa: E402

import torch

from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import euler_to_matrix
from torchface.model.candide import load_candide3
from torchface.synth.background import BackgroundSpec
from torchface.synth.scenarios import default_light
from torchface.synth.sequence import SequenceSpec, render_sequence
from torchface.tracker import FaceTracker, TrackerConfig


def main(batches: list[int]) -> None:
    torch.set_num_threads(1)
    W, H, D = 320, 240, torch.float64
    model = load_candide3()
    yaw = [0.0, 3.0, 6.0, 9.0, 12.0, 15.0, 15.0, 12.0]
    T = len(yaw)
    spec = SequenceSpec(
        name="reanchor", subject="candide3", intrinsics=Intrinsics.default(W, H),
        rotation=euler_to_matrix(torch.tensor([[y, 0.0, 0.0] for y in yaw], dtype=D)),
        translation=torch.tensor([[0.0, 0.0, 450.0]] * T, dtype=D), anim=torch.zeros(T, model.num_animation, dtype=D),
        light=default_light(T), background=BackgroundSpec(seed=3), photo="james",
    )  # fmt: skip
    frames, gt = render_sequence(spec)
    frames = frames.float() / 255.0 if frames.dtype == torch.uint8 else frames.float()
    for B in batches:
        noise = torch.randn(B, model.num_landmarks, 2, generator=torch.Generator().manual_seed(0))
        lm = gt.landmarks_px.float()[:1] + 1.5 * noise
        clip = frames[None].expand(B, -1, -1, -1, -1)
        tracker = FaceTracker(TrackerConfig(), model=model)
        t0 = time.process_time()
        tracker.initialise(clip[:, 0], lm, gt.intrinsics)
        times = [time.process_time() - t0]
        for i in range(1, T):
            t0 = time.process_time()
            tracker(clip[:, i])
            times.append(time.process_time() - t0)
        at = max(range(T), key=lambda i: times[i])
        others = sorted(t for i, t in enumerate(times) if i != at)
        print(f"B={B}: re-anchoring frame {at} {times[at]:.2f} s CPU, run {sum(times):.2f} s "
              f"({100 * times[at] / sum(times):.0f}%), other frames {1000 * others[len(others) // 2]:.0f} ms median",
              flush=True)  # fmt: skip


if __name__ == "__main__":
    # (it read sys.argv as integers: --help, the docs' way to learn a script, was a ValueError traceback)
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("batches", nargs="*", type=integer(1), metavar="B", help="streams per run (default 1 4 8)")
    batches = parser.parse_args().batches or [1, 4, 8]
    run_command(lambda: main(batches))
