#!/usr/bin/env python
"""``torchface track`` end to end: frames per second of the whole command at 640x480 and 1920x1080.

The command as a user runs it (a new process: imports, first-frame fit, tracking, the CSV, the JSON, the overlay and
normalised face videos, the plot), on ``--frames`` frames of the ``pose_sweep`` scenario rendered by torchface's own
renderer and written as ``mp4v`` MP4 (cached under ``--cache``): 640x480, and the same frames scaled 2.25x and padded
to 1920x1080 (the landmarks moved with them). Printed per size: end-to-end frames per second (frames over the
process's wall time, best of ``--repeats``, median beside it), the CPU time it took (all its threads: steadier than
the wall time on a shared machine) and the tracking loop's frames per second (the sidecar's ``timings_s.fps``:
reading, tracking and writing each frame, without the imports, the start and the finishing).

``--reference DIR`` runs another checkout of torchface (its folder, put first on ``PYTHONPATH``; e.g. a worktree of
the previous version) on the same clips in the same run, alternating which goes first, so that a slow or fast phase
of a shared machine moves both; its outputs are compared with this checkout's (the CSV byte for byte, the JSON but
its timings, every decoded frame of both videos) and a difference is reported.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the modules beside this script, however it is run
from _argtypes import comma_items, folder_problem, integer, remove_dead_partials, written_whole  # noqa: E402
from _argtypes import run_command  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SIZES = {"640x480": 1.0, "1920x1080": 2.25}


def _clips(cache: Path, count: int) -> dict[str, tuple[Path, Path]]:
    """The clip and its first frame's landmarks CSV per size (made once, kept in ``cache``)."""
    import cv2
    import numpy as np

    out = {size: (cache / f"track_pose_sweep_{size}_{count}.mp4", cache / f"track_pose_sweep_{size}_{count}_lm.csv")
           for size in SIZES}  # fmt: skip
    remove_dead_partials(cache)  # (left by runs killed outright, a new name each run: they would pile up)
    if all(v.is_file() and lm.is_file() for v, lm in out.values()):
        return out
    from torchface.synth.io import frames_to_uint8
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import render_sequence

    frames, gt = render_sequence(make_scenario("pose_sweep", max(count, 2), 640, 480))
    frames_bgr = frames_to_uint8(frames[:count])
    lm = gt.landmarks_px[0].double().numpy()
    cache.mkdir(parents=True, exist_ok=True)
    for size, scale in SIZES.items():
        W, H = (int(x) for x in size.split("x"))
        video, lm_csv = out[size]
        pad = (W - round(640 * scale)) // 2
        # each under a temporary name until whole (as the other scripts' outputs): no truncated file under its name
        with written_whole(video) as tmp:
            writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter.fourcc(*"mp4v"), 30.0, (W, H))
            if not writer.isOpened():  # (it writes nothing then: the rename's FileNotFoundError traceback before)
                raise SystemExit(f"benchmark_track.py: error: OpenCV cannot write {video} (cv2.VideoWriter did not "
                                 "open: no mp4v encoder in this OpenCV build?)")  # fmt: skip
            for bgr in frames_bgr:
                if scale != 1.0:
                    big = np.zeros((H, W, 3), np.uint8)
                    big[:, pad : W - pad] = cv2.resize(bgr, (W - 2 * pad, H), interpolation=cv2.INTER_LINEAR)
                    bgr = big
                writer.write(bgr)
            writer.release()
        moved = np.stack([(lm[:, 0] + 0.5) * scale - 0.5 + pad, (lm[:, 1] + 0.5) * scale - 0.5], 1)
        with written_whole(lm_csv) as tmp:
            np.savetxt(tmp, moved, delimiter=",")
    return out


def _run(checkout: Path, video: Path, lm: Path, out: Path) -> tuple[float, float, float]:
    """Wall seconds of one ``torchface track`` run of ``checkout``, its CPU seconds (all its threads), and its loop's
    frames per second."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(checkout), os.environ.get("PYTHONPATH", "")])}
    code = "import sys; from torchface.cli import main; sys.exit(main())"
    cmd = [sys.executable, "-c", code, "track", str(video), "--landmarks", str(lm), "--out", str(out), "--quiet"]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    # (run in the output's folder: `python -c` puts the working folder first on sys.path, and run from a checkout it
    # imported that checkout's torchface whatever PYTHONPATH said)
    out.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, cwd=out)
    if done.returncode != 0:  # (a CalledProcessError's traceback before, under the command's own message)
        raise SystemExit(f"benchmark_track.py: error: torchface track of {checkout} on {video.name} failed (exit "
                         f"status {done.returncode}; its message is above)")
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    sidecar = json.loads((out / f"{video.stem}.json").read_text())
    return wall, cpu, float(sidecar["timings_s"]["fps"])


def _difference(a: Path, b: Path, name: str) -> str | None:
    """What differs between two runs' outputs (None: nothing but the timings)."""
    import cv2
    import numpy as np

    if (a / f"{name}.csv").read_bytes() != (b / f"{name}.csv").read_bytes():
        return "the CSV"

    def sidecar(p: Path) -> dict:
        d = json.loads(p.read_text())
        return {k: v for k, v in d.items() if k not in ("timings_s", "outputs")}

    if sidecar(a / f"{name}.json") != sidecar(b / f"{name}.json"):
        return "the JSON"
    for kind in ("overlay", "normalised"):
        ca, cb = (cv2.VideoCapture(str(d / f"{name}_{kind}.mp4")) for d in (a, b))
        k = 0
        while True:
            (oa, fa), (ob, fb) = ca.read(), cb.read()
            if oa != ob or (oa and not np.array_equal(fa, fb)):
                return f"the {kind} video's frame {k}"
            if not oa:
                break
            k += 1
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--frames", type=integer(2), default=120, help="frames of the clip (default 120)")
    ap.add_argument("--repeats", type=integer(1), default=3, help="runs per checkout and size (default 3)")
    ap.add_argument("--sizes", default=",".join(SIZES), help=f"comma-separated, of {', '.join(SIZES)}")
    ap.add_argument("--reference", type=Path, help="another torchface checkout to run on the same clips")
    ap.add_argument("--cache", type=Path, default=ROOT / "out" / "bench", help="where the clips are kept")
    args = ap.parse_args()
    args.cache = args.cache.resolve()  # (the runs' working folder is their output's: a relative clip was not found)
    sizes = comma_items(args.sizes)  # (a size twice: once)
    if unknown := [s for s in sizes if s not in SIZES]:
        ap.error(f"--sizes: unknown {', '.join(unknown)} (known: {', '.join(SIZES)})")
    if not sizes:  # (the clips were rendered, then nothing run: a header without rows, exit status 0)
        ap.error(f"--sizes: none given; choose from {', '.join(SIZES)}")
    if (problem := folder_problem(args.cache)) is not None:  # (mkdir's traceback once the clips were rendered)
        ap.error(f"--cache {args.cache}: {problem}")
    if args.reference is not None and not (args.reference / "torchface" / "__init__.py").is_file():
        ap.error(f"--reference: {args.reference} is not a torchface checkout (no torchface/__init__.py)")
    clips = _clips(args.cache, args.frames)
    runs = {"this": ROOT} | ({"reference": args.reference.resolve()} if args.reference is not None else {})
    print(f"torchface track, {args.frames} frames of pose_sweep (mp4v), {os.cpu_count()} CPUs, "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; best (median) of {args.repeats}")  # fmt: skip
    print(f"{'size':>10} {'checkout':>10} {'end-to-end fps':>18} {'wall s':>14} {'CPU s':>14} {'loop fps':>14}")
    with tempfile.TemporaryDirectory() as tmp:
        for size in sizes:
            video, lm = clips[size]
            walls: dict[str, list[float]] = {k: [] for k in runs}
            loops: dict[str, list[float]] = {k: [] for k in runs}
            cpus: dict[str, list[float]] = {k: [] for k in runs}
            for r in range(args.repeats):
                order = list(runs) if r % 2 == 0 else list(runs)[::-1]
                for k in order:
                    wall, cpu, loop = _run(runs[k], video, lm, Path(tmp) / k)
                    # (a progress line per run: the rows came only after every run of a size, minutes of silence)
                    print(f"  {size} {k}: run {r + 1}/{args.repeats}, {wall:.1f} s wall", file=sys.stderr, flush=True)
                    walls[k].append(wall)
                    cpus[k].append(cpu)
                    loops[k].append(loop)
            for k in runs:
                best, med = min(walls[k]), statistics.median(walls[k])
                fps = f"{args.frames / best:.1f} ({args.frames / med:.1f})"
                cpu = f"{min(cpus[k]):.2f} ({statistics.median(cpus[k]):.2f})"
                print(f"{size:>10} {k:>10} {fps:>18} {f'{best:.2f} ({med:.2f})':>14} {cpu:>14} "
                      f"{f'{max(loops[k]):.1f} ({statistics.median(loops[k]):.1f})':>14}")  # fmt: skip
            if "reference" in runs:
                diff = _difference(Path(tmp) / "this", Path(tmp) / "reference", video.stem)
                print(f"{'':>10} outputs: {'identical' if diff is None else 'DIFFER in ' + diff}")


if __name__ == "__main__":
    run_command(main)
