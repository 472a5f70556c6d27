#!/usr/bin/env python
"""Measure the figures README.md, docs/ and the docstrings quote from small experiments that no other script runs.

Each subcommand prints the table its text quotes (one thread, a minute or less of CPU; other-models and
resume-sweep 2):

  face-width   TrackerConfig.min_face_width_px's docstring (and docs/python-api.md's paragraph on it): rotation
               error against the face's width on rendered CANDIDE-3 clips at 320x240, with the test off
               (min_face_width_px=0). Per width, --clips clips of --frames frames: exact first-frame landmarks,
               the head turning out to 15 degrees of yaw each way (pitch and roll up to 8 and 5 degrees, seeded),
               at the depth that makes the frontal face that wide (face_width_px), tracked by a default
               FaceTracker.
  small-frames docs/limitations.md's "Small frames": the `leaves` clip of tests/tracker/test_managed.py (a
               rendered face leaving the frame for 4 frames and coming back 60 mm aside, here for --frames
               frames) at small frame sizes, default FaceTracker, with the default levels and one fewer: the first
               frame found after the return, from the mosaic search at the coarsest level, or with a detector
               (--oracle: the renderer's landmarks stand in for one).
  grid-pan     lookahead.VIEW_TURN_FRACTION's comment: a GRID clip (../shared/assets/grid, first-frame landmarks in
               scripts/data/grid_landmarks) whose frames 30-39 are shifted --shift px sideways (a camera pan), tracked
               by a default FaceTracker (online start on): how far the rest of the clip's rotations are from the
               clean run's, with the view check, with it off (VIEW_TURN_FRACTION = 0) and without the online start.
  grid-bounds  docs/limitations.md's "Expression units at their bounds from the first frame": the 11 GRID clips'
               first-frame landmark fits (the tracker's FitConfig at each --precisions expression prior precision):
               the animation units at a bound that limits them (a nonzero one, or the upper one), the mean |unit|, the
               RMS landmark error, and where dlib's lid points and CANDIDE-3's table put the eyes' lids (eye widths
               from the corners' line); then each clip tracked with each precision (FaceTracker, its default online
               start): the frames, of all clips', at which each unit's coefficient sits at such a bound, and its
               expression (the readout, from the first fit) at an end of its range; --coefficient-bounds tracks with
               the ranges bounding the coefficients (TrackerConfig.expression_range_from_start=False, as before).
  hard-cuts    docs/limitations.md's "Hard cuts": clip A (5 frames, CANDIDE-3 30 mm left of the axis at 450 mm,
               turning 4 degrees) cut straight to clip B (--frames frames) with the face moved --dx mm across,
               --dz mm in depth and turned --dyaw degrees (every combination), tracked as one stream at --size by a
               default FaceTracker, with the renderer's landmarks as the detector and without one (mosaic search):
               the frames after the cut reported successful but over --max-error degrees off (2; and those of
               them at confidence 0.1 or more), and the first frame from which every frame is successful and
               within it. --photo astronaut makes B another person; --restart-after-unmatched 2 sets
               TemplateConfig.restart_after_unmatched (off by default).
  lid-fit      docs/limitations.md's "Eyes closed": how far the first frame's landmark fit puts the eyelids on the
               `expressions` scenario (frame 0 of scripts/evaluate.py's render at --size, cached under --cache) over
               --draws draws of evaluate.py's 2 px landmark noise (seeds 0..), with the default FitConfig and without a
               starting expression (fit_expression=False): the mean vertical distance, in pixels, of the upper lid's
               vertices (those Eyes closed moves down) from the truth's, and of the eye opening (upper minus lower
               lid); the fraction of draws within 0.3 and 0.5 px, next to the upper lid's travel at full closure.
  other-models docs/python-api.md's "Other face models" table: the `scan_motion` (James scan) and `pose_sweep`
               (CANDIDE-3) scenarios rendered at --size, --frames frames, tracked as one stream by a default
               FaceTracker with exact first-frame landmarks and CANDIDE-3, then the ICT Face Model
               (TORCHFACE_ASSETS or ../shared/assets; skipped when absent) with each --areas area ("head": the whole
               head): the rotation error relative to the first frame (mean over every frame, max), the frames LOST and
               at MAX_ITERATIONS, the mean (median) ms of the steps after the first frame and initialise's seconds, of
               the fastest of --runs runs. --video tracks the frames as 8-bit video; --no-expression,
               --expression-prior-precision and --shape-bound change TrackerConfig (use_expression,
               expression_prior_precision, fit.shape_bound).
  resume-sweep docs/cli.md's "Interrupting and resuming" and torchface/job.py's module docstring: a `pose_sweep`
               (--frames frames at --size, saved as 8-bit frames) tracked by torchface.job.track_videos (JobConfig's
               defaults, as `torchface track`), alone and as a batch of its frames from each of --starts on, each plain,
               with --smooth's filter and with a detector (the renderer's landmarks of the frame it is given)
               re-detecting every --redetect-every frames (--videos, --variants: some of them). Each is tracked
               uninterrupted, then interrupted once --stop rows are written (a Ctrl-C between steps, not the signal
               handler's checkpoint) and resumed (--resume) from its last checkpoint (every --every rows from the online
               start's --max-frames on) and, the checkpoint removed, from its CSV's rows: which outputs (CSV, overlay,
               normalised face) are the uninterrupted run's byte for byte, and how far the resumed rows part from the
               uninterrupted ones (the most over the rows and videos: translation, mm; rotation, degrees between the
               r00..r22 matrices; confidence; the first frame that differs); and the first video's frames/s
               (timings_s.fps, the rows replayed from the CSV left out, and counting them: frames tracked over
               timings_s.track).

Examples:
    python scripts/doc_figures.py face-width
    python scripts/doc_figures.py small-frames --sizes 96x72,128x96,160x120
    python scripts/doc_figures.py grid-pan --clip bbaf2n --shift -120
    python scripts/doc_figures.py grid-bounds --precisions 2,20,64
    python scripts/doc_figures.py hard-cuts --dx 90 --dz -120 --dyaw 0,21
    python scripts/doc_figures.py lid-fit --draws 100
    python scripts/doc_figures.py other-models --areas narrow_eyes --no-expression
    python scripts/doc_figures.py resume-sweep
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # evaluate.py beside this script, however it is run
from _argtypes import assets_folder, folder_problem, frame_size, integer, positive  # noqa: E402
from _argtypes import run_command  # noqa: E402

import torch

from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import euler_to_matrix, geodesic_angle_deg, matrix_to_euler
from torchface.model.candide import load_candide3
from torchface.synth.background import BackgroundSpec
from torchface.synth.scenarios import default_light, scenario_size
from torchface.synth.sequence import GroundTruth, SequenceSpec, render_sequence
from torchface.template.management import TemplateConfig
from torchface.tracker import FaceTracker, TrackerConfig, face_width_px

D = torch.float64
ROOT = Path(__file__).resolve().parents[1]

ASSETS = assets_folder()
GRID = ASSETS / "grid"
ICT_NPZ = ASSETS / "ict_facekit" / "ict_face_model_light.npz"


def _render(cam: Intrinsics, rotation: torch.Tensor, translation: torch.Tensor, seed: int,
            photo: str = "james") -> tuple[torch.Tensor, GroundTruth]:  # fmt: skip
    """``frames (T, 3, H, W)`` float in [0, 1] of CANDIDE-3 at ``rotation (T, 3, 3)``, ``translation (T, 3)``."""
    T = rotation.shape[0]
    spec = SequenceSpec(
        name="figure", subject="candide3", intrinsics=cam, rotation=rotation, translation=translation,
        anim=torch.zeros(T, load_candide3().num_animation, dtype=D), light=default_light(T),
        background=BackgroundSpec(seed=seed), photo=photo,
    )  # fmt: skip
    frames, gt = render_sequence(spec)
    return (frames.float() / 255.0 if frames.dtype == torch.uint8 else frames.float()), gt


def face_width(args: argparse.Namespace) -> None:
    model = load_candide3()
    cam = Intrinsics.default(320, 240)
    fw = float(face_width_px(model, torch.tensor([[0.0, 0.0, 1000.0]]), cam)) * 1000.0  # fx w: width x depth
    T = args.frames
    u = torch.linspace(0.0, 1.0, T, dtype=D)[:, None]
    config = TrackerConfig(min_face_width_px=0.0)
    print(f"{args.clips} clips of {T} frames at 320x240 per width; rotation error (degrees) over frames 1-{T - 1}")
    print(f"{'width px':>8} {'mean':>6} {'max':>6} {'clips run off (>30)':>20} {'conf median':>11} {'conf 10%':>8}")
    for width in args.widths:
        errors, confidences, run_off = [], [], 0
        for seed in range(args.clips):
            g = torch.Generator().manual_seed(seed)
            amp = (torch.rand(3, generator=g, dtype=D) * 2 - 1) * torch.tensor([15.0, 8.0, 5.0], dtype=D)
            phase = torch.rand(3, generator=g, dtype=D) * 2 * math.pi
            rate = 2 * math.pi * torch.tensor([1.0, 2.0, 1.5], dtype=D)
            ypr = amp * torch.sin(rate * u + phase) - amp * torch.sin(phase)  # from frontal
            # yaw: out to 15 degrees, back, out to the other side and back (first side by the seed)
            side = 1.0 if seed % 2 == 0 else -1.0
            ypr[:, 0] = side * 15.0 * torch.sin(2 * math.pi * u[:, 0])
            translation = torch.tensor([0.0, 0.0, fw / width], dtype=D).expand(T, 3).clone()
            frames, gt = _render(cam, euler_to_matrix(ypr), translation, seed + 3)
            tracker = FaceTracker(config, model)
            tracker.initialise(frames[:1], gt.landmarks_px[:1].float())
            results = [tracker(frames[i : i + 1]) for i in range(1, T)]
            error = geodesic_angle_deg(torch.cat([r.rotation for r in results]).double(), gt.rotation[1:])
            errors.append(error)
            confidences.append(torch.cat([r.confidence for r in results]))
            run_off += int(float(error.max()) > 30.0)
        e, c = torch.cat(errors), torch.cat(confidences)
        print(f"{width:>8.1f} {float(e.mean()):>6.2f} {float(e.max()):>6.1f} {f'{run_off}/{args.clips}':>20} "
              f"{float(c.median()):>11.2f} {float(c.quantile(0.1)):>8.2f}")


def small_frames(args: argparse.Namespace) -> None:
    model = load_candide3()
    x = [0.0, 5.0, 10.0, 15.0] + [400.0] * 4 + [-60.0] * (args.frames - 8)
    T, back = len(x), 8
    rotation = euler_to_matrix(torch.zeros(T, 3, dtype=D))
    translation = torch.tensor([[a, 0.0, 450.0] for a in x], dtype=D)
    print(f"face out of the frame at frames 4-7, back from frame {back} to {T - 1}; found = first frame from "
          f"{back} on that is a success within 15 mm of the truth, and every frame after it")
    print(f"{'photo':<10} {'size':>8} {'levels':>6} {'coarsest':>8} {'face tall there':>15} {'found at':>8}")
    for photo in args.photos:
        for w, h in args.sizes:
            cam = Intrinsics.default(w, h)
            frames, gt = _render(cam, rotation, translation, 3, photo)
            tall = float(gt.landmarks_px[0, :, 1].amax() - gt.landmarks_px[0, :, 1].amin())
            current = [0]

            def oracle(batch: torch.Tensor) -> torch.Tensor:
                # the renderer's landmarks of the frame being tracked (NaN when the face is not in view)
                i = current[0]
                lm = gt.landmarks_px[i].clone().float()
                if int(gt.landmarks_visible[i].sum()) < 40:
                    lm[:] = float("nan")
                return lm[None].expand(batch.shape[0], -1, -1)

            for fewer in (0, 1):
                config = TrackerConfig()
                if fewer:
                    config = replace(config, num_levels=config.num_levels - 1, iterations=config.iterations[1:])
                tracker = FaceTracker(config, model, detector=oracle if args.oracle else None)
                tracker.initialise(frames[:1], gt.landmarks_px[:1].float())
                good = []
                for i in range(1, T):
                    current[0] = i
                    r = tracker(frames[i : i + 1])
                    near = float((r.translation[0].double() - gt.translation[i]).norm()) < 15.0
                    good.append(bool(r.success[0]) and near)
                found = next((i for i in range(back, T) if all(good[i - 1 :])), None)
                coarse = 2 ** (config.num_levels - 1)
                print(f"{photo:<10} {f'{w}x{h}':>8} {config.num_levels:>6} {f'{w // coarse}x{h // coarse}':>8} "
                      f"{tall / coarse:>12.1f} px {'never' if found is None else found:>8}")


def grid_pan(args: argparse.Namespace) -> None:
    import torchface.tracker.lookahead as lookahead
    from torchface.io.landmarks import read_landmarks
    from torchface.synth.io import read_video_uint8
    from torchface.tracker import view_yaw_deg

    frames = read_video_uint8(args.grid / f"{args.clip}.mpg").float() / 255.0
    T, _, H, W = frames.shape
    landmarks = torch.from_numpy(read_landmarks(args.landmarks_dir / f"{args.clip}.csv", W, H)).float()[None]
    dx, (a, b) = args.shift, (30, 40)
    panned = frames.clone()  # frames a..b-1 shifted dx px sideways, the uncovered strip filled with the edge column
    if dx > 0:
        panned[a:b, ..., dx:], panned[a:b, ..., :dx] = frames[a:b, ..., :-dx], frames[a:b, ..., :1]
    elif dx < 0:
        panned[a:b, ..., :dx], panned[a:b, ..., dx:] = frames[a:b, ..., -dx:], frames[a:b, ..., -1:]

    def track(clip: torch.Tensor, online: bool) -> tuple[torch.Tensor, torch.Tensor, bool]:
        tracker = FaceTracker() if online else FaceTracker(refine_first=None)
        tracker.initialise(clip[:1], landmarks)
        results = [tracker(clip[i : i + 1]) for i in range(1, T)]
        management = None if tracker.state is None else tracker.state.management
        anchor = None if management is None else management.head_rotation
        moved = anchor is not None and not torch.equal(anchor[0], torch.eye(3, dtype=anchor.dtype))
        return (torch.cat([r.rotation for r in results]).double(), torch.cat([r.translation for r in results]).double(),
                moved)  # fmt: skip

    print(f"{args.clip} ({W}x{H}, {T} frames), frames {a}-{b - 1} shifted {dx:+d} px; rotation off the clean run "
          f"(degrees) over frames {b}-{T - 1}")
    fraction = lookahead.VIEW_TURN_FRACTION
    for label, view_fraction, online in (("online start, view check", fraction, True),
                                         ("online start, check off", 0.0, True),
                                         ("no online start", fraction, False)):  # fmt: skip
        lookahead.VIEW_TURN_FRACTION = view_fraction
        try:
            R0, t0, _ = track(frames, online)
            R, t, moved = track(panned, online)
        finally:
            lookahead.VIEW_TURN_FRACTION = fraction
        off = geodesic_angle_deg(R[b - 1 :], R0[b - 1 :])
        yaw = (matrix_to_euler(R) - matrix_to_euler(R0))[a - 1 : b - 1, 0].mean()
        view = (view_yaw_deg(R, t) - view_yaw_deg(R0, t0))[a - 1 : b - 1].mean()
        print(f"{label:<26} mean {float(off.mean()):.2f} max {float(off.max()):.2f}; re-anchored: {moved}; "
              f"frames {a}-{b - 1}: yaw {float(yaw):+.1f} in the camera frame, {float(view):+.1f} seen along the ray")


def _at_bound(anim: torch.Tensor, ranges: torch.Tensor) -> torch.Tensor:
    """``(..., A)`` bool: the units at a bound that stops them, within 1e-3 (a negative lower bound or the upper one; a
    lower bound of 0 is the neutral face's, where a unit such as Eyes closed rests)."""
    lo, hi = ranges[:, 0].to(anim.dtype), ranges[:, 1].to(anim.dtype)
    return (((anim - lo).abs() < 1e-3) & (lo < 0)) | ((anim - hi).abs() < 1e-3)


def grid_bounds(args: argparse.Namespace) -> None:
    from torchface.io.landmarks import read_landmarks
    from torchface.synth.io import read_video_uint8
    from torchface.tracker import fit_landmarks

    clips = sorted(p.stem for p in args.grid.glob("*.mpg") if (args.landmarks_dir / f"{p.stem}.csv").is_file())
    frames = [read_video_uint8(args.grid / f"{c}.mpg").float() / 255.0 for c in clips]
    H, W = frames[0].shape[-2:]
    if any(f.shape[-2:] != (H, W) for f in frames):
        raise SystemExit(f"doc_figures.py: error: the clips in {args.grid} are not all {W}x{H}")
    landmarks = torch.stack([torch.from_numpy(read_landmarks(args.landmarks_dir / f"{c}.csv", W, H)).float()
                             for c in clips])  # fmt: skip
    model, cam = load_candide3(), Intrinsics.default(W, H)
    short = [n.split(" ", 1)[1] for n in model.animation_names]
    print(f"{len(clips)} GRID clips ({W}x{H}), first-frame landmarks of {args.landmarks_dir}")

    def lids(points: torch.Tensor) -> list[float]:
        """The lid points' mean height over the corners' line, eye widths: upper outer, upper inner, lower inner,
        lower outer (iBUG 37, 38, 40, 41 and their mirror 44, 43, 47, 46)."""
        out = []
        for k, m in ((37, 44), (38, 43), (40, 47), (41, 46)):
            v = []
            for p, (c0, c1) in ((k, (36, 39)), (m, (42, 45))):
                mid = (points[..., c0, :] + points[..., c1, :]) / 2
                v.append((mid[..., 1] - points[..., p, 1]) / (points[..., c1, :] - points[..., c0, :]).norm(dim=-1))
            out.append(float(torch.stack(v).mean()))
        return out

    table = model.landmarks_3d(model.mean[None])[0][None, :, :2]
    print("lid points over the eye corners' line (eye widths; iBUG 37/44, 38/43, 40/47, 41/46; + up): "
          f"dlib {' / '.join(f'{v:+.3f}' for v in lids(landmarks))}, CANDIDE-3's table "
          f"{' / '.join(f'{v:+.3f}' for v in lids(table))}")
    configs = {p: replace(TrackerConfig().fit, expression_prior_precision=p) for p in args.precisions}
    for p, fit_config in configs.items():
        fit = fit_landmarks(model, landmarks, cam, config=fit_config)
        at = _at_bound(fit.anim_coeffs, model.animation_ranges)
        which = ", ".join(f"{short[j]} {int(at[:, j].sum())}" for j in range(len(short)) if bool(at[:, j].any()))
        print(f"fit, expression prior precision {p:g}: {int(at.sum())} units at a bound on {int(at.any(1).sum())} "
              f"clips ({which or 'none'}); mean |unit| {float(fit.anim_coeffs.abs().mean()):.3f}; RMS "
              f"{float(fit.rms_px.mean()):.3f} px")
    def listed(counts: torch.Tensor) -> str:
        which = ", ".join(f"{short[j]} {int(counts[j])}" for j in range(len(short)) if int(counts[j]))
        return f"{which or 'none'} ({int(counts.sum())} in all)"

    for p, fit_config in configs.items():
        config = TrackerConfig(fit=fit_config, expression_range_from_start=not args.coefficient_bounds)
        coefficient = torch.zeros(len(short), dtype=torch.int64)
        expression = torch.zeros(len(short), dtype=torch.int64)
        total, past = 0, torch.zeros(len(short))
        for clip, lm in zip(frames, landmarks):
            tracker = FaceTracker(config)
            first = tracker.initialise(clip[:1], lm[None])
            rows = [first] + [tracker(clip[i : i + 1]) for i in range(1, clip.shape[0])]
            anim = torch.cat([r.anim_coeffs for r in rows])
            coefficient += _at_bound(anim, model.animation_ranges).sum(0)
            expression += _at_bound(torch.cat([r.expression for r in rows]), model.animation_ranges).sum(0)
            ranges = model.animation_ranges.to(anim.dtype)
            past = torch.maximum(past, torch.maximum(anim - ranges[:, 1], ranges[:, 0] - anim).amax(0))
            total += clip.shape[0]
        print(f"tracked, precision {p:g}, {'coefficients' if args.coefficient_bounds else 'expressions'} bounded; "
              f"of {total} frames x {len(short)} units: coefficients at a bound: {listed(coefficient)}; expressions "
              f"at an end of their range: {listed(expression)}; coefficients past the ranges by up to "
              f"{float(past.max()):.2f}")


def hard_cuts(args: argparse.Namespace) -> None:
    model = load_candide3()
    w, h = args.size
    cam = Intrinsics.default(w, h)
    cut = 5
    s = torch.linspace(0, 1, cut, dtype=D)[:, None]
    frames_a, gt_a = _render(cam, euler_to_matrix(s * torch.tensor([4.0, -2.0, 1.0], dtype=D)),
                             torch.tensor([-30.0, 0.0, 450.0], dtype=D) + s * torch.tensor([4.0, 0.0, 0.0], dtype=D), 3)
    s = torch.linspace(0, 1, args.frames, dtype=D)[:, None]
    most = args.max_error
    config = TrackerConfig(template=TemplateConfig(restart_after_unmatched=args.restart_after_unmatched))
    print(f"{w}x{h}; cut at frame {cut} to {args.photo!r}, frames {cut}-{cut + args.frames - 1}; wrong = successful "
          f"and over {most:g} degrees off (those at confidence >= 0.1: frame/degrees/confidence); right from = the "
          f"first frame from which every frame is successful and within {most:g} degrees")
    print(f"{'dx mm':>6} {'dz mm':>6} {'dyaw':>5} | {'detector: wrong, at conf >= 0.1, right from':<44} | search: ...")
    for dx in args.dx:
        for dz in args.dz:
            for dyaw in args.dyaw:
                R_b = euler_to_matrix(torch.tensor([4.0 + dyaw, -2.0, 1.0], dtype=D)
                                      + s * torch.tensor([2.0, 0.0, 0.0], dtype=D))  # fmt: skip
                t_b = torch.tensor([-26.0 + dx, 0.0, 450.0 + dz], dtype=D) + s * torch.tensor([3.0, 0.0, 0.0], dtype=D)
                frames_b, gt_b = _render(cam, R_b, t_b, 3, args.photo)
                frames = torch.cat([frames_a, frames_b])
                truth = torch.cat([gt_a.rotation, gt_b.rotation])
                landmarks = torch.cat([gt_a.landmarks_px, gt_b.landmarks_px]).float()
                cells = []
                for with_detector in (True, False):
                    current = [0]

                    def oracle(batch: torch.Tensor) -> torch.Tensor:  # the renderer's landmarks of the frame
                        return landmarks[current[0]][None].expand(batch.shape[0], -1, -1)

                    tracker = FaceTracker(config, model=model, detector=oracle if with_detector else None)
                    results = [tracker.initialise(frames[:1], landmarks[:1])]
                    for i in range(1, frames.shape[0]):
                        current[0] = i
                        results.append(tracker(frames[i : i + 1]))
                    R = torch.cat([r.rotation for r in results]).double()
                    err = geodesic_angle_deg(R @ R[0].mT, truth @ truth[0].mT)
                    right = [bool(r.success[0]) and float(e) <= most for r, e in zip(results, err)]
                    wrong = [i for i in range(cut, len(results)) if bool(results[i].success[0]) and not right[i]]
                    sure = [f"{i}/{float(err[i]):.1f}/{float(results[i].confidence[0]):.2f}" for i in wrong
                            if float(results[i].confidence[0]) >= 0.1]  # fmt: skip
                    back = next((i for i in range(cut, len(results)) if all(right[i:])), None)
                    cells.append(f"{len(wrong)}, [{' '.join(sure)}], {'never' if back is None else back}")
                print(f"{dx:>6.0f} {dz:>6.0f} {dyaw:>5.0f} | {cells[0]:<44} | {cells[1]}")


def lid_fit(args: argparse.Namespace) -> None:
    import evaluate  # scripts/evaluate.py (its render cache and its landmark noise): imported here, as it is slow

    from torchface.geometry.projection import project_points
    from torchface.tracker.fit import fit_landmarks

    model = load_candide3()
    w, h, n = scenario_size("expressions", args.size)
    gt = evaluate.load_sequence("expressions", w, h, n, None if args.cache == "none" else Path(args.cache)).gt
    unit = model.animation_names.index("AUV6 Eyes closed")
    # model y points down (torchface.conventions): Eyes closed moves the upper lid down (+y), the lower one up
    shift = model.animation_units[unit, :, 1]
    upper, lower = (shift > 1e-6).nonzero().flatten(), (shift < -1e-6).nonzero().flatten()

    def lids_y(rotation: torch.Tensor, translation: torch.Tensor, shape: torch.Tensor, anim: torch.Tensor,
               ) -> torch.Tensor:  # fmt: skip
        v = model.deform(shape.to(model.dtype), anim.to(model.dtype)).to(D)
        return project_points(v @ rotation.to(D).mT + translation.to(D)[:, None], gt.intrinsics)[0, :, 1]

    shape = torch.as_tensor(gt.shape_coeffs, dtype=D)[None]
    truth = lids_y(gt.rotation[:1], gt.translation[:1], shape, gt.au[:1])
    closed = gt.au[:1].clone()
    closed[0, unit] = 1.0
    travel = (lids_y(gt.rotation[:1], gt.translation[:1], shape, closed) - truth)[upper].abs().mean()
    print(f"expressions {w}x{h}, frame 0; {args.draws} draws of {evaluate.LANDMARK_NOISE_PX:g} px landmark noise; "
          f"the upper lid moves {float(travel):.1f} px at full closure")
    print(f"{'fit':<26} {'|upper lid| px: median':>22} {'p10':>5} {'p90':>5} {'<0.3':>5} {'<0.5':>5} | "
          f"{'|opening| px: median':>20} {'<0.3':>5} {'<0.5':>5}")
    default = TrackerConfig().fit
    for label, config in (("default", default), ("no starting expression", replace(default, fit_expression=False))):
        up, opening = [], []
        for seed in range(args.draws):
            fit = fit_landmarks(model, evaluate.initial_landmarks(gt, seed).to(model.dtype), gt.intrinsics,
                                config=config)  # fmt: skip
            dy = lids_y(fit.rotation, fit.translation, fit.shape_coeffs, fit.anim_coeffs) - truth
            up.append(float(dy[upper].abs().mean()))
            opening.append(float((dy[upper] - dy[lower]).abs().mean()))
        u, o = torch.tensor(up, dtype=D), torch.tensor(opening, dtype=D)
        q = torch.quantile(u, torch.tensor([0.5, 0.1, 0.9], dtype=D)).tolist()
        within = [float((x < limit).to(D).mean()) for x in (u, o) for limit in (0.3, 0.5)]
        print(f"{label:<26} {q[0]:>22.2f} {q[1]:>5.2f} {q[2]:>5.2f} {within[0]:>5.2f} {within[1]:>5.2f} | "
              f"{float(o.median()):>20.2f} {within[2]:>5.2f} {within[3]:>5.2f}")


def other_models(args: argparse.Namespace) -> None:
    from torchface.model import load_ict_face_model
    from torchface.synth.metrics import relative_rotation_error_deg
    from torchface.synth.scenarios import make_scenario

    w, h = args.size
    config = TrackerConfig(use_expression=not args.no_expression)
    if args.expression_prior_precision is not None:
        config = replace(config, expression_prior_precision=args.expression_prior_precision)
    if args.shape_bound is not None:
        config = replace(config, fit=replace(config.fit, shape_bound=args.shape_bound))
    models = [("CANDIDE-3", load_candide3)]
    if ICT_NPZ.is_file():
        models += [(f"ICT {area}", lambda area=area: load_ict_face_model(ICT_NPZ, area=area)) for area in args.areas]
    else:
        print(f"no ICT Face Model at {ICT_NPZ} (TORCHFACE_ASSETS): CANDIDE-3 only")
    print(f"{w}x{h}, {args.frames} frames{' as 8-bit video' if args.video else ''}, one stream, one thread; "
          f"use_expression={config.use_expression}, expression_prior_precision={config.expression_prior_precision:g}, "
          f"fit.shape_bound={config.fit.shape_bound:g}; ms: mean (median) of the steps after the first frame, "
          f"fastest of {args.runs} runs")
    print(f"{'scenario':<12} {'model':<16} {'rotation mean / max':>20} {'LOST':>4} {'MAX_IT':>6} {'ms per frame':>14} "
          f"{'initialise':>10}")
    for scenario in ("scan_motion", "pose_sweep"):
        frames, gt = render_sequence(make_scenario(scenario, args.frames, w, h))
        if args.video:
            frames = (frames * 255.0).round() / 255.0
        landmarks = gt.landmarks_px[:1].float()
        for label, load in models:
            model = load()
            runs = []
            for _ in range(args.runs):
                tracker = FaceTracker(config, model)
                start = time.perf_counter()
                results = [tracker.initialise(frames[:1], landmarks)]
                first = time.perf_counter() - start
                steps = []
                for t in range(1, frames.shape[0]):
                    start = time.perf_counter()
                    results.append(tracker(frames[t : t + 1]))
                    steps.append(time.perf_counter() - start)
                runs.append((sum(steps), steps, first, results))
            _, steps, first, results = min(runs, key=lambda run: run[0])
            error = relative_rotation_error_deg(torch.cat([r.rotation for r in results]).double(), gt.rotation)
            status = [int(r.status[0]) for r in results[1:]]
            ms = f"{1000 * statistics.mean(steps):.1f} ({1000 * statistics.median(steps):.1f})"
            print(f"{scenario:<12} {label:<16} {f'{float(error.mean()):.2f} / {float(error.max()):.2f}':>20} "
                  f"{status.count(3):>4} {status.count(1):>6} {ms:>14} {first:>8.2f} s", flush=True)


def _sweep_rows(folder: Path, name: str) -> tuple[tuple[str, ...], torch.Tensor]:
    from torchface.io import read_track_csv

    columns, rows = read_track_csv(folder / f"{name}.csv")
    return columns, torch.from_numpy(rows)


def _parting(ref: Path, got: Path, name: str) -> tuple[float, float, float, int | None]:
    """How far video ``name``'s rows in folder ``got`` part from those in ``ref``: the most over its rows of the
    translation's distance (mm), the rotation's angle (degrees, between the ``r00..r22`` matrices) and the
    confidence's difference, and the first frame whose row differs (None: none does)."""
    columns, a = _sweep_rows(ref, name)
    _, b = _sweep_rows(got, name)
    if a.shape != b.shape:
        raise RuntimeError(f"{name}: {b.shape[0]} rows resumed, {a.shape[0]} uninterrupted")
    at = [columns.index(c) for c in ("pose_Tx", "pose_Ty", "pose_Tz")]
    ar = [columns.index(f"r{i}{j}") for i in range(3) for j in range(3)]
    conf = columns.index("confidence")
    mm = (a[:, at] - b[:, at]).norm(dim=-1)
    deg = geodesic_angle_deg(a[:, ar].reshape(-1, 3, 3), b[:, ar].reshape(-1, 3, 3))
    dc = (a[:, conf] - b[:, conf]).abs()
    differ = (a != b).any(dim=-1).nonzero().flatten()
    return (float(mm.max()), float(deg.nan_to_num(0.0).max()), float(dc.max()),
            int(a[differ[0], 0]) if len(differ) else None)  # fmt: skip


def resume_sweep(args: argparse.Namespace) -> None:
    import hashlib
    import json
    import shutil
    import tempfile

    import numpy as np

    import torchface.detect
    import torchface.job
    from torchface.job import JobConfig, track_videos
    from torchface.synth.scenarios import make_scenario
    from torchface.tracker.lookahead import LookaheadConfig
    from torchface.tracker.smoothing import SmoothingConfig

    w, h = args.size
    frames, gt = render_sequence(make_scenario("pose_sweep", args.frames, w, h))
    frames = frames if frames.dtype == torch.uint8 else (frames.clamp(0, 1) * 255).round().to(torch.uint8)
    images = frames.permute(0, 2, 3, 1).contiguous().numpy()  # (T, H, W, 3) uint8 RGB, as the job's inputs
    truth = {hashlib.blake2b(image.tobytes()).digest(): gt.landmarks_px[i].numpy().copy()
             for i, image in enumerate(images)}  # fmt: skip

    def rendered(image_rgb: np.ndarray) -> np.ndarray:  # the detector: the renderer's landmarks of that frame
        key = hashlib.blake2b(np.ascontiguousarray(image_rgb).tobytes()).digest()
        if key not in truth:
            raise RuntimeError("the detector was given a frame that is not one of the sweep's")
        return truth[key].copy()

    root = Path(tempfile.mkdtemp(prefix="resume-sweep-"))
    clips = []
    for start in args.starts:
        video, lm = root / f"from{start}.npy", root / f"from{start}.csv"
        np.save(video, images[start:])
        np.savetxt(lm, gt.landmarks_px[start].numpy(), delimiter=",", header="x,y", comments="")
        clips.append((video, lm))
    every, online = torchface.job.CHECKPOINT_EVERY, LookaheadConfig(max_frames=args.max_frames)
    torchface.job.CHECKPOINT_EVERY = args.every
    torchface.detect.DETECTORS["rendered"] = lambda: rendered
    print(f"pose_sweep {w}x{h}, {args.frames} frames (the batch: from frames {', '.join(map(str, args.starts))}); "
          f"interrupted after {args.stop} rows, a checkpoint every {args.every} rows from row {args.max_frames}; "
          f"from rows: the most over rows and videos (mm, degrees, confidence; the first frame that differs); fps: "
          f"the first video's frames/s uninterrupted, resumed from its checkpoint (replayed rows left out / counted)")
    print(f"{'videos':<7} {'variant':<9} | {'checkpoint at':>13} {'not byte for byte':<18} | "
          f"{'from rows: mm':>13} {'deg':>8} {'conf':>8} {'from':>5} | {'fps: whole':>10} {'resumed':>8} "
          f"{'counted':>8}")  # fmt: skip
    try:
        for videos in args.videos:
            batch = clips[:1] if videos == "alone" else clips
            names = [v.stem for v, _ in batch]
            for variant in args.variants:
                kwargs: dict = {"refine_first": online, "landmarks": tuple(lm for _, lm in batch)}
                if variant == "smooth":
                    kwargs["smoothing"] = SmoothingConfig()
                elif variant == "detector":  # (every frame below the threshold: a re-detection every N frames)
                    kwargs.update(detector="rendered", redetect_after=args.redetect_every, redetect_below=1.01)
                paths = [v for v, _ in batch]
                ref = root / f"{videos}-{variant}-ref"
                track_videos(paths, JobConfig(out_dir=ref, **kwargs))
                outs = {}
                for how in ("checkpoint", "rows"):
                    out = outs[how] = root / f"{videos}-{variant}-{how}"

                    stopped = []

                    def interrupt(p: torchface.job.Progress) -> None:  # (a Ctrl-C between two steps)
                        if p.done == args.stop and p.index == len(batch) - 1:
                            stopped.append(p.done)
                            raise KeyboardInterrupt

                    try:
                        track_videos(paths, JobConfig(out_dir=out, **kwargs), progress=interrupt)
                    except KeyboardInterrupt:
                        if not stopped:  # (the user's)
                            raise
                    if not stopped:
                        raise RuntimeError(f"the run was not interrupted after {args.stop} rows")
                    states = [out / f"{n}.state.partial" for n in names]
                    if not all(s.is_file() for s in states):
                        raise RuntimeError(f"no checkpoint after {args.stop} rows")
                    rows = {int(torch.load(s, weights_only=True)["rows"]) for s in states}
                    if how == "rows":
                        for s in states:
                            s.unlink()
                    track_videos(paths, JobConfig(out_dir=out, resume=True, **kwargs))
                    said = [json.loads((out / f"{n}.json").read_text())["resumed"]["checkpoint"] for n in names]
                    if said != (["exact"] * len(names) if how == "checkpoint" else [False] * len(names)):
                        raise RuntimeError(f"resumed from the {how}: the sidecars say checkpoint {said}")
                differ = [n + x for n in names for x in (".csv", "_overlay.mp4", "_normalised.mp4")
                          if (ref / (n + x)).read_bytes() != (outs["checkpoint"] / (n + x)).read_bytes()]
                parts = [_parting(ref, outs["rows"], n) for n in names]
                first = min((p[3] for p in parts if p[3] is not None), default=None)
                mm, deg, conf = ((0.0, 0.0, 0.0) if first is None else
                                 (max(p[0] for p in parts), max(p[1] for p in parts), max(p[2] for p in parts)))
                timing = [json.loads((d / f"{names[0]}.json").read_text())["timings_s"]
                          for d in (ref, outs["checkpoint"])]  # fmt: skip
                counted = timing[1]["fps"] * (timing[1]["track"] - timing[1]["replay"]) / timing[1]["track"]
                print(f"{videos:<7} {variant:<9} | {'/'.join(map(str, sorted(rows))):>13} "
                      f"{' '.join(differ) or 'none':<18} | {mm:>13.3f} {deg:>8.3f} {conf:>8.3f} "
                      f"{'none' if first is None else first:>5} | {timing[0]['fps']:>10.1f} {timing[1]['fps']:>8.1f} "
                      f"{counted:>8.1f}", flush=True)  # fmt: skip
    finally:
        torchface.job.CHECKPOINT_EVERY = every
        del torchface.detect.DETECTORS["rendered"]
        shutil.rmtree(root, ignore_errors=True)


def _numbers(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers, comma separated, got {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected finite numbers, got {text!r}")
    return values


def _sizes(text: str) -> list[tuple[int, int]]:
    """An argparse type: a comma list of frame sizes (:func:`_argtypes.frame_size`'s ``WxH``)."""
    try:
        return [frame_size(item) for item in text.split(",")]
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"sizes must be WxH[,WxH...] of at least 8x8, got {text!r}") from None


def _widths(text: str) -> list[float]:
    try:
        widths = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"widths must be numbers, comma separated, got {text!r}") from None
    if not all(math.isfinite(v) and v > 0 for v in widths):
        raise argparse.ArgumentTypeError(f"widths must be positive pixels, got {text!r}")
    return widths


def _names(allowed: tuple[str, ...]) -> Callable[[str], list[str]]:
    """An argparse type: a comma list of names from ``allowed`` (a bad one ended the run with a traceback, after the
    rows before it had been measured)."""

    def parse(text: str) -> list[str]:
        names = [v.strip() for v in text.split(",")]
        if bad := [v for v in names if v not in allowed]:
            raise argparse.ArgumentTypeError(f"{', '.join(map(repr, bad))}: choose from {', '.join(allowed)}")
        return names

    return parse


def _counts(text: str) -> list[int]:
    """An argparse type: a comma list of distinct integers >= 0."""
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected integers, comma separated, got {text!r}") from None
    if min(values) < 0 or len(set(values)) < len(values):
        raise argparse.ArgumentTypeError(f"expected distinct integers >= 0, got {text!r}")
    return values


def _positives(text: str) -> list[float]:
    """An argparse type: a comma list of finite numbers > 0."""
    return [_positive(v) for v in text.split(",")]


#: An argparse type: a finite number > 0.
_positive = positive()


def main(argv: list[str] | None = None) -> int:
    from torchface.model.mesh_loader import ICT_AREAS
    from torchface.synth.subjects import PHOTOS

    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    sub = parser.add_subparsers(dest="figure", required=True)
    p = sub.add_parser("face-width", help="rotation error against the face's width (min_face_width_px)")
    p.add_argument("--widths", type=_widths, default=_widths("27,23.5,20,18,16,13"), help="face widths, px")
    p.add_argument("--clips", type=int, default=10, help="clips per width (seeds 0..)")
    p.add_argument("--frames", type=int, default=30, help="frames per clip")
    p.set_defaults(run=face_width)
    p = sub.add_parser("small-frames", help="recovery of a face back in a small frame (docs/limitations.md: Small frames)")
    sizes = "96x72,112x84,128x96,144x108,160x120,176x132,224x168,320x240"
    p.add_argument("--sizes", type=_sizes, default=_sizes(sizes), help="frame sizes WxH, comma separated")
    p.add_argument("--photos", default="james,astronaut", type=_names(PHOTOS), help="face textures")
    p.add_argument("--frames", type=int, default=20, help="frames of the clip (8 before the return)")
    p.add_argument("--oracle", action="store_true", help="with a detector: the renderer's landmarks")
    p.set_defaults(run=small_frames)
    p = sub.add_parser("grid-pan", help="a camera pan in a GRID clip and the online start (VIEW_TURN_FRACTION)")
    p.add_argument("--clip", default="bbaf2n", help="GRID clip name (<name>.mpg)")
    p.add_argument("--shift", type=int, default=-120, help="sideways shift of frames 30-39, px (negative: left)")
    p.add_argument("--grid", type=Path, default=GRID, help="folder of GRID .mpg clips")
    p.add_argument("--landmarks-dir", type=Path, default=ROOT / "scripts" / "data" / "grid_landmarks",
                   help="folder of <clip>.csv first-frame landmarks")  # fmt: skip
    p.set_defaults(run=grid_pan)
    p = sub.add_parser("grid-bounds", help="animation units at their bounds after the GRID clips' first fits")
    p.add_argument("--precisions", type=_positives, default=_positives("2,20,64"),
                   help="the landmark fit's expression prior precisions, comma separated (the tracker's: 2)")
    p.add_argument("--coefficient-bounds", action="store_true",
                   help="track with the ranges bounding the coefficients (expression_range_from_start=False)")
    p.add_argument("--grid", type=Path, default=GRID, help="folder of GRID .mpg clips")
    p.add_argument("--landmarks-dir", type=Path, default=ROOT / "scripts" / "data" / "grid_landmarks",
                   help="folder of <clip>.csv first-frame landmarks")  # fmt: skip
    p.set_defaults(run=grid_bounds)
    p = sub.add_parser("hard-cuts", help="a video cut to the face elsewhere (docs/limitations.md: Hard cuts)")
    p.add_argument("--size", type=frame_size, default=(320, 240), help="frame size WxH")
    p.add_argument("--dx", type=_numbers, default=_numbers("8,20,45"), help="jumps across, mm, comma separated")
    p.add_argument("--dz", type=_numbers, default=_numbers("0,-60,100"), help="jumps in depth, mm")
    p.add_argument("--dyaw", type=_numbers, default=_numbers("0,12,-30"), help="turns at the cut, degrees")
    p.add_argument("--photo", default="james", choices=("james", "astronaut"), help="clip B's face texture")
    p.add_argument("--frames", type=int, default=10, help="frames of clip B")
    p.add_argument("--max-error", type=_positive, default=2.0, help="a frame further off is wrong, degrees")
    p.add_argument("--restart-after-unmatched", type=integer(0), default=0,
                   help="TemplateConfig.restart_after_unmatched (0: off, the default)")
    p.set_defaults(run=hard_cuts)
    p = sub.add_parser("lid-fit", help="the eyelids' error after the first frame's landmark fit (docs/limitations.md: Eyes closed)")
    p.add_argument("--draws", type=int, default=100, help="landmark-noise draws (seeds 0..)")
    p.add_argument("--size", default="full", choices=("small", "full"), help="the scenario's size (full: 640x480)")
    p.add_argument("--cache", default=str(ROOT / "out" / "sequences"),
                   help="evaluate.py's render cache folder; 'none' renders in memory")
    p.set_defaults(run=lid_fit)
    p = sub.add_parser("other-models", help="CANDIDE-3 and the ICT Face Model's areas (docs/python-api.md: Other face models)")
    p.add_argument("--size", type=frame_size, default=(640, 480), help="frame size WxH")
    p.add_argument("--frames", type=int, default=80, help="frames per scenario")
    p.add_argument("--runs", type=int, default=3, help="runs per row; the fastest is reported")
    p.add_argument("--areas", default="narrow_eyes,narrow,face,head", type=_names(tuple(ICT_AREAS)),
                   help="load_ict_face_model areas, comma separated")  # fmt: skip
    p.add_argument("--video", action="store_true", help="track the frames rounded to 8 bits")
    p.add_argument("--no-expression", action="store_true", help="TrackerConfig(use_expression=False)")
    p.add_argument("--expression-prior-precision", type=float, default=None,
                   help="TrackerConfig.expression_prior_precision (default: its default)")
    p.add_argument("--shape-bound", type=float, default=None, help="FitConfig.shape_bound (default: its default)")
    p.set_defaults(run=other_models)
    p = sub.add_parser("resume-sweep", help="a pose sweep interrupted and resumed (docs/cli.md: Interrupting ...)")
    p.add_argument("--size", type=frame_size, default=(160, 120), help="frame size WxH")
    p.add_argument("--frames", type=int, default=200, help="frames of the sweep")
    p.add_argument("--starts", type=_counts, default=_counts("0,3,7"),
                   help="the batch's videos: the sweep from these frames on, comma separated")
    p.add_argument("--stop", type=int, default=170, help="interrupted once this many rows are written")
    p.add_argument("--every", type=integer(1), default=None,
                   help="rows between checkpoints (default: torchface.job.CHECKPOINT_EVERY)")
    p.add_argument("--max-frames", type=integer(1), default=None,
                   help="the online start's LookaheadConfig.max_frames (default: its default)")
    p.add_argument("--redetect-every", type=integer(1), default=5, help="the detector variant's re-detections, frames")
    p.add_argument("--variants", default="plain,smooth,detector", type=_names(("plain", "smooth", "detector")),
                   help="plain, smooth (--smooth), detector; comma separated")
    p.add_argument("--videos", default="alone,batch", type=_names(("alone", "batch")),
                   help="alone (the sweep from its first frame), batch (from each of --starts); comma separated")
    p.set_defaults(run=resume_sweep)
    args = parser.parse_args(argv)
    for name in ("clips", "frames", "draws", "runs"):
        if getattr(args, name, 1) < 1:
            parser.error(f"--{name} must be >= 1")
    if args.figure in ("other-models", "face-width") and args.frames < 2:  # (face-width: a traceback before)
        parser.error("--frames must be >= 2 (the frames after the first are tracked and measured)")
    if args.figure == "small-frames" and args.frames < 10:
        parser.error("--frames must be >= 10 (8 before the face's return)")
    # (each a traceback before, most after some rows had been measured)
    if args.figure == "grid-pan" and not (args.grid / f"{args.clip}.mpg").is_file():
        parser.error(f"no GRID clip {args.clip}.mpg in {args.grid} (--grid, or TORCHFACE_ASSETS's grid folder)")
    if args.figure == "grid-pan" and not (args.landmarks_dir / f"{args.clip}.csv").is_file():
        parser.error(f"--landmarks-dir {args.landmarks_dir}: no {args.clip}.csv (the clip's first-frame landmarks)")
    if args.figure == "grid-bounds" and not any((args.landmarks_dir / f"{p.stem}.csv").is_file()
                                                for p in (args.grid.glob("*.mpg") if args.grid.is_dir() else ())):
        parser.error(f"no GRID clip in {args.grid} with its <clip>.csv in --landmarks-dir {args.landmarks_dir}")
    if args.figure == "lid-fit" and args.cache != "none" and (problem := folder_problem(Path(args.cache))):
        parser.error(f"--cache {args.cache}: {problem}")
    if args.figure == "resume-sweep":
        from torchface.job import CHECKPOINT_EVERY
        from torchface.tracker.lookahead import LookaheadConfig

        args.every = CHECKPOINT_EVERY if args.every is None else args.every
        args.max_frames = LookaheadConfig().max_frames if args.max_frames is None else args.max_frames
        # (the first checkpoint: the first multiple of --every from --max-frames on; the shortest video: the last
        # start's)
        first = -(-args.max_frames // args.every) * args.every
        if not first <= args.stop < args.frames - max(args.starts):
            last = args.frames - max(args.starts) - 1
            parser.error(f"--stop must be from {first} (the first checkpoint's rows) to {last} (the shortest video's "
                         f"frames, less one), got {args.stop}")
    torch.set_num_threads(1)
    args.run(args)
    return 0


if __name__ == "__main__":
    run_command(main)
