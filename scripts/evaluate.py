#!/usr/bin/env python
"""Evaluate the tracker on the standard synthetic scenarios, with ablations.

For each scenario the sequence is rendered once into a cache folder (lossless video + ground truth, see
torchface.synth.sequence.write_sequence) and read back from there on later runs. The tracker is
initialised from frame 0's ground-truth landmarks plus Gaussian noise (fixed seed, the same for every
ablation), tracks every later frame, and is scored with torchface.synth.metrics: rotation error relative to
frame 0 (geodesic and per axis), translation error, animation-unit RMSE (fraction of each unit's range) and
correlation over the units that vary in the ground truth, converged / successful / lost frames, and time
per frame.

Ablations (one row each): full, no_illumination (TrackerConfig.use_illumination=False), no_expression
(use_expression=False), no_robust (robust=RobustKind.NONE), all_pixels (gradient_threshold=0).

Examples:
    python scripts/evaluate.py --scenarios pose_sweep --frames 40 --size 320x240 --ablations none
    python scripts/evaluate.py --scenarios pose_sweep,expressions --ablations none --json out/eval.json
    python scripts/evaluate.py                     # all five scenarios at 640x480, full length, all ablations
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor

import torchface
from torchface.model.candide import load_candide3
from torchface.model.face_model import FaceModel
from torchface.solver.robust import RobustKind
from torchface.synth.io import read_video_uint8
from torchface.synth.metrics import LOST_THRESHOLD_DEG, SequenceMetrics, relative_rotation_error_deg, sequence_metrics
from torchface.synth.scenarios import SCENARIOS, make_scenario, scenario_size
from torchface.synth.sequence import GroundTruth, SequenceSpec, load_ground_truth, render_sequence, write_sequence
from torchface.tracker.step import TrackerConfig, initialise, track_step

#: Ablation name -> how it changes the full configuration.
ABLATIONS: dict[str, Callable[[TrackerConfig], TrackerConfig]] = {
    "full": lambda c: c,
    "no_illumination": lambda c: replace(c, use_illumination=False),
    "no_expression": lambda c: replace(c, use_expression=False),
    "no_robust": lambda c: replace(c, robust=RobustKind.NONE),
    "all_pixels": lambda c: replace(c, gradient_threshold=0.0),
}

#: Standard deviation of the noise added to the initial landmarks (pixels).
LANDMARK_NOISE_PX: float = 2.0


def log(msg: str) -> None:
    sys.stderr.write(msg + "\n")
    sys.stderr.flush()


@dataclass(frozen=True)
class Sequence:
    """A loaded sequence: ``frames (T, 3, H, W)`` uint8 RGB and its ground truth."""

    frames: Tensor
    gt: GroundTruth


@dataclass(frozen=True)
class RunOutput:
    """Per-frame estimates of one tracked sequence and its timing."""

    rotation: Tensor
    translation: Tensor
    anim: Tensor
    status: Tensor
    ms_per_frame: float
    init_ms: float


def _to_uint8(frames: Tensor) -> Tensor:
    return (frames.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)


def spec_fingerprint(spec: SequenceSpec) -> str:
    """Hash of the sequence's specification and of the code and data that render it.

    A cached sequence is reused only while this matches, so a change to the scenarios, the renderer or the
    packaged subjects re-renders it instead of scoring the tracker against stale frames.
    """
    h = hashlib.sha256(repr(spec).encode())
    for field_name in ("rotation", "translation", "anim"):
        h.update(getattr(spec, field_name).detach().cpu().to(torch.float64).numpy().tobytes())
    root = Path(torchface.__file__).parent
    sources = sorted((root / "synth").glob("*.py")) + sorted((root / "rendering").glob("*.py"))
    data = sorted(p for p in (root / "data").rglob("*") if p.is_file())
    for path in sources + data:
        h.update(path.relative_to(root).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def load_sequence(name: str, width: int, height: int, num_frames: int, cache: Path | None) -> Sequence:
    """Read the scenario from ``cache`` or render it there first (in memory when ``cache`` is None)."""
    spec = make_scenario(name, num_frames, width, height)
    if cache is None:
        start = time.perf_counter()
        frames, gt = render_sequence(spec)
        log(f"{name}: rendered {num_frames} frames {width}x{height} in memory in {time.perf_counter() - start:.1f} s")
        return Sequence(_to_uint8(frames), gt)
    folder = cache / f"{name}_{width}x{height}_{num_frames}f"
    video = folder / f"{name}.avi"
    gt_path = folder / f"{name}.gt.npz"
    stamp = folder / f"{name}.fingerprint"
    fingerprint = spec_fingerprint(spec)
    if video.is_file() and gt_path.is_file() and stamp.is_file() and stamp.read_text().strip() == fingerprint:
        gt = load_ground_truth(gt_path)
        frames = read_video_uint8(video)
        size_ok = tuple(frames.shape[-2:]) == (height, width)
        if frames.shape[0] == num_frames and gt.num_frames == num_frames and size_ok:
            log(f"{name}: loaded {num_frames} frames {width}x{height} from {folder}")
            return Sequence(frames, gt)
    if video.is_file():
        log(f"{name}: cache at {folder} is stale (scenario or renderer changed); rendering again")
    start = time.perf_counter()

    def progress(done: int, total: int) -> None:
        if done == total or done % 40 < 8:
            rate = done / max(time.perf_counter() - start, 1e-9)
            log(f"{name}: rendered {done}/{total} frames ({rate:.1f} fps)")

    stamp.unlink(missing_ok=True)
    files = write_sequence(spec, folder, progress=progress)
    stamp.write_text(fingerprint + "\n")
    log(f"{name}: wrote {files.video} ({files.codec.strip()}) in {time.perf_counter() - start:.1f} s")
    return Sequence(read_video_uint8(files.video), load_ground_truth(files.ground_truth))


def initial_landmarks(gt: GroundTruth, seed: int) -> Tensor:
    """``(1, K, 2)`` frame-0 landmarks plus Gaussian noise; landmarks hidden in frame 0 are NaN (missing)."""
    g = torch.Generator().manual_seed(seed)
    lm0 = gt.landmarks_px[:1]
    lm = lm0 + LANDMARK_NOISE_PX * torch.randn(lm0.shape, generator=g, dtype=torch.float64)
    return torch.where(gt.landmarks_visible[:1].unsqueeze(-1), lm, torch.full_like(lm, float("nan")))


def track_sequence(
    model: FaceModel, config: TrackerConfig, seq: Sequence, landmarks: Tensor, label: str, progress_every: int
) -> RunOutput:
    """Initialise on frame 0 and track frames ``1 .. T-1`` of one stream."""
    gt = seq.gt
    dev, dt = model.device, model.dtype
    T = seq.frames.shape[0]

    def frame(i: int) -> Tensor:
        return seq.frames[i : i + 1].to(device=dev).to(dt) / 255.0

    start = time.perf_counter()
    state, res = initialise(model, config, frame(0), landmarks.to(device=dev, dtype=dt), gt.intrinsics)
    init_ms = 1e3 * (time.perf_counter() - start)
    results = [res]
    R0_est = res.rotation.detach().to("cpu", torch.float64)
    start = time.perf_counter()
    for i in range(1, T):
        state, res = track_step(model, config, state, frame(i))
        results.append(res)
        if progress_every and (i % progress_every == 0 or i == T - 1):
            R_pair = torch.cat([R0_est, res.rotation.detach().to("cpu", torch.float64)])
            err = float(relative_rotation_error_deg(R_pair, gt.rotation[[0, i]])[1])
            ms = 1e3 * (time.perf_counter() - start) / i
            log(f"  {label}: frame {i}/{T - 1} rot err {err:.2f} deg, status {int(res.status[0])}, {ms:.0f} ms/frame")
    ms_per_frame = 1e3 * (time.perf_counter() - start) / max(T - 1, 1)

    def cat(field: str) -> Tensor:
        return torch.cat([getattr(r, field).detach().cpu() for r in results])

    return RunOutput(
        rotation=cat("rotation").to(torch.float64),
        translation=cat("translation").to(torch.float64),
        anim=cat("anim_coeffs").to(torch.float64),
        status=cat("status"),
        ms_per_frame=ms_per_frame,
        init_ms=init_ms,
    )


def score(model: FaceModel, gt: GroundTruth, out: RunOutput) -> SequenceMetrics:
    """Metrics of one run; animation units are matched to the ground truth by name."""
    anim_est = anim_gt = ranges = None
    names: tuple[str, ...] = ()
    if gt.au.shape[-1] > 0:
        index = {n: i for i, n in enumerate(model.animation_names)}
        shared = [n for n in gt.au_names if n in index]
        if shared:
            cols = torch.tensor([index[n] for n in shared])
            gt_cols = torch.tensor([gt.au_names.index(n) for n in shared])
            anim_est = out.anim[:, cols]
            anim_gt = gt.au[:, gt_cols]
            ranges = model.animation_ranges.detach().cpu().to(torch.float64)[cols]
            names = tuple(shared)
    return sequence_metrics(
        out.rotation, out.translation, gt.rotation, gt.translation, out.status,
        anim_est=anim_est, anim_gt=anim_gt, anim_ranges=ranges, anim_names=names,
    )


def _fmt(x: float, digits: int = 2) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


COLUMNS = (
    ("config", 16), ("rot mean", 8), ("median", 7), ("max", 7), ("|yaw|", 6), ("|pitch|", 7), ("|roll|", 6),
    ("t mm", 6), ("t rel", 6), ("AU rmse", 7), ("AU r", 6), ("conv", 5), ("succ", 5), ("lost", 5), ("ms/fr", 7),
)


def table(name: str, rows: dict[str, dict[str, float]], info: str) -> str:
    """One scenario's table (rows = configurations)."""
    head = " ".join(h.rjust(w) if i else h.ljust(w) for i, (h, w) in enumerate(COLUMNS))
    title = f"== {name} ({info}); rotation errors relative to frame 0 (deg); lost: error > {LOST_THRESHOLD_DEG:g} deg"
    lines = [title, head, "-" * len(head)]
    for cfg, m in rows.items():
        vals = (
            cfg, _fmt(m["rot_err_mean_deg"]), _fmt(m["rot_err_median_deg"]), _fmt(m["rot_err_max_deg"]),
            _fmt(m["yaw_err_deg"]), _fmt(m["pitch_err_deg"]), _fmt(m["roll_err_deg"]), _fmt(m["trans_err_mm"], 1),
            _fmt(m["trans_rel_err_mm"], 1), _fmt(m["au_rmse"], 3), _fmt(m["au_corr"]), _fmt(m["converged"]),
            _fmt(m["success"]), str(int(m["lost_frames"])), _fmt(m["ms_per_frame"], 0),
        )
        lines.append(" ".join(v.rjust(w) if i else v.ljust(w) for i, (v, (_, w)) in enumerate(zip(vals, COLUMNS))))
    au = sorted({k.split("/", 1)[1] for m in rows.values() for k in m if k.startswith("au_rmse/")})
    if au:
        lines.append("   per active AU: RMSE (fraction of range) / Pearson r")
        lines.append("   " + "config".ljust(16) + "".join(a[:22].rjust(24) for a in au))
        for cfg, m in rows.items():
            nan = float("nan")
            cells = [f"{_fmt(m.get('au_rmse/' + a, nan), 3)} / {_fmt(m.get('au_corr/' + a, nan))}" for a in au]
            lines.append("   " + cfg.ljust(16) + "".join(c.rjust(24) for c in cells))
    return "\n".join(lines)


def _json_safe(results: dict[str, dict[str, float]]) -> dict[str, dict[str, float | None]]:
    """NaN (undefined metric) -> null, so the file is strict JSON."""
    def clean(v: float) -> float | None:
        return None if isinstance(v, float) and math.isnan(v) else v

    return {k: {m: clean(v) for m, v in d.items()} for k, d in results.items()}


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WxH (e.g. 640x480), got {text!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"size must be at least 8x8, got {text!r}")
    return w, h


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", default="all", help=f"comma-separated from {', '.join(SCENARIOS)} (default all)")
    parser.add_argument("--frames", type=int, help="frames per scenario (default: each scenario's full length)")
    parser.add_argument("--size", type=_parse_size, default=None, help="WxH (default 640x480)")
    parser.add_argument("--cache", default="out/sequences", help="sequence cache folder; 'none' renders in memory")
    parser.add_argument(
        "--ablations", default="all", help=f"all, none (full only) or a comma list from {', '.join(ABLATIONS)}"
    )
    parser.add_argument("--json", type=Path, help="write {scenario[/ablation]: {metric: value}} here")
    parser.add_argument("--device", default="cpu", help="torch device of the tracker (default cpu)")
    parser.add_argument("--threads", type=int, help="torch CPU threads")
    parser.add_argument("--seed", type=int, default=0, help="seed of the landmark noise")
    parser.add_argument("--progress-every", type=int, default=20, help="progress line every N frames (0: none)")
    args = parser.parse_args(argv)

    names = list(SCENARIOS) if args.scenarios == "all" else [s.strip() for s in args.scenarios.split(",") if s.strip()]
    for n in names:
        if n not in SCENARIOS:
            parser.error(f"unknown scenario {n!r}; choose from {', '.join(SCENARIOS)}")
    if args.ablations == "all":
        ablations = list(ABLATIONS)
    elif args.ablations == "none":
        ablations = ["full"]
    else:
        ablations = ["full"] + [a.strip() for a in args.ablations.split(",") if a.strip() and a.strip() != "full"]
        for a in ablations:
            if a not in ABLATIONS:
                parser.error(f"unknown ablation {a!r}; choose from {', '.join(ABLATIONS)}, all or none")
    if args.frames is not None and args.frames < 2:
        parser.error(f"--frames must be >= 2, got {args.frames}")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    cache = None if args.cache.lower() == "none" else Path(args.cache)

    model = load_candide3(device=args.device)
    base = TrackerConfig()
    results: dict[str, dict[str, float]] = {}
    tables: list[str] = []
    for name in names:
        w, h, t = scenario_size(name, "full")
        if args.size is not None:
            w, h = args.size
        t = args.frames or t
        seq = load_sequence(name, w, h, t, cache)
        landmarks = initial_landmarks(seq.gt, args.seed)
        rows: dict[str, dict[str, float]] = {}
        for abl in ablations:
            label = f"{name}/{abl}"
            log(f"{label}: tracking {t} frames {w}x{h} on {args.device}")
            out = track_sequence(model, ABLATIONS[abl](base), seq, landmarks, label, args.progress_every)
            m = score(model, seq.gt, out).as_dict()
            m.update(ms_per_frame=out.ms_per_frame, init_ms=out.init_ms, width=w, height=h, num_frames=t)
            rows[abl] = m
            results[name if abl == "full" else label] = m
            log(
                f"{label}: rot err mean {_fmt(m['rot_err_mean_deg'])} max {_fmt(m['rot_err_max_deg'])} deg, "
                f"lost {m['lost_frames']}, AU rmse {_fmt(m['au_rmse'], 3)}, {out.ms_per_frame:.0f} ms/frame"
            )
            if args.json is not None:
                args.json.parent.mkdir(parents=True, exist_ok=True)
                args.json.write_text(json.dumps(_json_safe(results), indent=1) + "\n")
        tables.append(table(name, rows, f"{w}x{h}, {t} frames, init noise {LANDMARK_NOISE_PX:g} px"))
        print(tables[-1] + "\n", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
