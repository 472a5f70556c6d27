"""Time torchface.rendering.rasterize at 640x480 for a CANDIDE-sized mesh and a ~20k-triangle mesh.

Both meshes are posed 450 mm in front of the camera and scaled to cover about 200 x 250 pixels
(the face of a tracked subject). Prints the median wall time (and process CPU time) of several runs
after warm-up, per call, for B = 1 and B = 8 (eight copies, each slightly rotated so that samples
differ).

Usage:
    python scripts/benchmark_raster.py [--threads N] [--runs 15] [--device cpu] [--dtype float32] [--json out.json]
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _argtypes beside this script, however it is run
from _argtypes import device_problem, file_problem, output_file  # noqa: E402
from _argtypes import integer as _integer  # noqa: E402
from _argtypes import run_command  # noqa: E402

import torch
import trimesh

from torchface.geometry.camera import Intrinsics
from torchface.io.sidecar import write_json
from torchface.rendering import rasterize

WIDTH, HEIGHT = 640, 480
DEPTH_MM = 450.0
TARGET_PX = (200.0, 250.0)


def _fit_to_screen(verts: torch.Tensor, cam: Intrinsics) -> torch.Tensor:
    """Centre ``(V, 3)`` head-frame vertices, scale x/y so they span TARGET_PX at DEPTH_MM, move them there."""
    lo, hi = verts.amin(0), verts.amax(0)
    centred = verts - (lo + hi) / 2
    extent = hi - lo
    sx = TARGET_PX[0] * DEPTH_MM / cam.fx / float(extent[0])
    sy = TARGET_PX[1] * DEPTH_MM / cam.fy / float(extent[1])
    scale = torch.tensor([sx, sy, math.sqrt(sx * sy)], dtype=verts.dtype)
    return centred * scale + torch.tensor([0.0, 0.0, DEPTH_MM], dtype=verts.dtype)


def _candide_mesh() -> tuple[str, torch.Tensor, torch.Tensor]:
    try:
        from torchface.model.candide import load_candide3

        model = load_candide3(dtype=torch.float64)
        used = model.surface_vertex_mask
        return "CANDIDE-3", model.mean.where(used[:, None], model.mean[used].mean(0)), model.faces
    except (ImportError, AttributeError) as err:  # the model package is optional for this script
        print(f"(CANDIDE-3 unavailable: {err}; using an icosphere)")
        mesh = trimesh.creation.icosphere(subdivisions=2)
        return "icosphere-2", torch.tensor(mesh.vertices), torch.tensor(mesh.faces)


def _dense_mesh() -> tuple[str, torch.Tensor, torch.Tensor]:
    mesh = trimesh.creation.icosphere(subdivisions=5)
    return "icosphere-5", torch.tensor(mesh.vertices), torch.tensor(mesh.faces)


def _batch(verts_cam: torch.Tensor, batch: int) -> torch.Tensor:
    """``(B, V, 3)``: copies rotated about the vertical axis through the mesh centre by up to 10 degrees."""
    centre = torch.tensor([0.0, 0.0, DEPTH_MM], dtype=verts_cam.dtype)
    out = []
    for i in range(batch):
        a = math.radians(10.0 * i / max(batch - 1, 1))
        rot = torch.tensor(
            [[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]], dtype=verts_cam.dtype
        )
        out.append((verts_cam - centre) @ rot.T + centre)
    return torch.stack(out)


def _time(fn, runs: int, warmup: int, sync) -> tuple[float, float]:
    """Median wall time and median process CPU time (all threads) per call, in milliseconds."""
    for _ in range(warmup):
        fn()
    sync()
    wall, cpu = [], []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        sync()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return 1e3 * statistics.median(wall), 1e3 * statistics.median(cpu)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=_integer(1), default=None, help="torch.set_num_threads (default: torch's)")
    parser.add_argument("--runs", type=_integer(1), default=15, help="timed runs per row (default 15)")
    parser.add_argument("--warmup", type=_integer(0), default=3, help="untimed runs first (default 3)")
    parser.add_argument("--device", default="cpu", help="torch device (default cpu)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                        help="dtype of the vertices rasterized (default float32)")
    parser.add_argument("--batches", type=_integer(1), nargs="+", default=[1, 8], help="batch sizes (default 1 8)")
    parser.add_argument("--json", type=output_file, default=None, help="write the figures to this JSON file")
    args = parser.parse_args(argv)
    # one-line errors before any timing, not tracebacks (a --json folder: after every row was timed)
    # (an unknown device, one torch was built without, or meta: a NotImplementedError's traceback in the first row)
    if (problem := device_problem(args.device)) is not None:
        parser.error(f"--device {args.device}: {problem}")
    device = torch.device(args.device)
    if args.json is not None and (problem := file_problem(args.json)) is not None:
        parser.error(f"--json {args.json}: {problem}")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    cam = Intrinsics.default(WIDTH, HEIGHT)

    rows = []
    for name, verts, faces in (_candide_mesh(), _dense_mesh()):
        verts_cam = _fit_to_screen(verts.double(), cam)
        faces = faces.to(device)
        for batch in args.batches:
            vb = _batch(verts_cam, batch).to(device=device, dtype=dtype)
            frag = rasterize(vb, faces, cam)
            coverage = frag.foreground[0].sum().item()
            ms, cpu_ms = _time(lambda: rasterize(vb, faces, cam), args.runs, args.warmup, sync)
            rows.append(
                {
                    "mesh": name,
                    "V": int(vb.shape[1]),
                    "F": int(faces.shape[0]),
                    "B": batch,
                    "covered_px": int(coverage),
                    "ms": round(ms, 2),
                    "ms_per_sample": round(ms / batch, 2),
                    "cpu_ms": round(cpu_ms, 2),
                }
            )

    print(
        f"rasterize {WIDTH}x{HEIGHT}, {args.dtype}, device={device}, threads={torch.get_num_threads()}, "
        f"torch {torch.__version__}, median of {args.runs} after {args.warmup} warm-up"
    )
    header = f"{'mesh':<12} {'V':>6} {'F':>6} {'B':>3} {'covered px':>11} {'ms':>9} {'ms/sample':>10} {'cpu ms':>9}"
    print(header)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r['mesh']:<12} {r['V']:>6} {r['F']:>6} {r['B']:>3} {r['covered_px']:>11} {r['ms']:>9.2f} "
            f"{r['ms_per_sample']:>10.2f} {r['cpu_ms']:>9.2f}"
        )
    print("ms: wall-clock median; cpu ms: process CPU time median (all threads), less sensitive to other load")
    if args.json is not None:
        meta = {
            "width": WIDTH,
            "height": HEIGHT,
            "dtype": args.dtype,
            "device": str(device),
            "threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "machine": platform.processor() or platform.machine(),
            "runs": args.runs,
            "warmup": args.warmup,
            "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.json, {"meta": meta, "results": rows})  # whole or not at all (a temporary name renamed)
    return 0


if __name__ == "__main__":
    run_command(main)
