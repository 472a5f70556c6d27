#!/usr/bin/env python
"""Draw ground-truth landmarks on frames of a rendered sequence and save PNGs (a visual check).

Landmarks are re-projected from the ground-truth 3D landmarks and pose (not copied from
landmarks_px), and the two are compared. Visible landmarks are green, hidden ones red; the
iBUG-68 outline (jaw, brows, nose, eyes, lips) is drawn as polylines.

Example:
    python scripts/overlay_landmarks.py out/synth_small/pose_sweep.avi --out out/overlay
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _argtypes beside this script, however it is run
from _argtypes import folder_problem, written_whole  # noqa: E402
from _argtypes import run_command  # noqa: E402

import cv2
import numpy as np
import torch

from torchface.geometry.projection import project_points
from torchface.geometry.transforms import transform_points
from torchface.synth.io import frames_to_uint8, iter_video_uint8
from torchface.synth.sequence import load_ground_truth

# iBUG-68 polylines: (start, end, closed).
_GROUPS = ((0, 17, False), (17, 22, False), (22, 27, False), (27, 31, False), (31, 36, False),
           (36, 42, True), (42, 48, True), (48, 60, True), (60, 68, True))


def pick_frames(ypr: torch.Tensor) -> list[int]:
    """Frame 0, the middle frame and the frames of extreme yaw (both signs), pitch and roll."""
    t = ypr.shape[0]
    picks = [0, t // 2, int(ypr[:, 0].argmax()), int(ypr[:, 0].argmin()), int(ypr[:, 1].argmax()), int(ypr[:, 2].argmax())]
    return sorted(set(picks))


def draw(image: np.ndarray, pts: np.ndarray, visible: np.ndarray, scale: int) -> np.ndarray:
    big = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    p = (pts + 0.5) * scale - 0.5
    for a, b, closed in _GROUPS:
        cv2.polylines(big, [np.round(p[a:b]).astype(np.int32)], closed, (255, 255, 0), 1, cv2.LINE_AA)
    for k, (q, vis) in enumerate(zip(p, visible)):
        centre = (int(round(q[0])), int(round(q[1])))
        cv2.circle(big, centre, 2 if scale < 3 else 3, (0, 255, 0) if vis else (0, 0, 255), -1, cv2.LINE_AA)
    return big


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("video", type=Path, help="a video written by make_sequence.py (its .gt.npz beside it)")
    parser.add_argument("--frames", type=int, nargs="*", help="frame indices (default: 0, middle, extremes)")
    parser.add_argument("--scale", type=int, default=0, help="upscaling factor (default: to about 640 px wide)")
    parser.add_argument("--out", type=Path, default=Path("out/overlay"),
                        help="folder of the PNGs, <name>_<frame>.png (default out/overlay)")
    args = parser.parse_args(argv)
    if args.scale < 0:
        parser.error(f"--scale must be >= 1 (or 0 for about 640 px wide), got {args.scale}")
    if (problem := folder_problem(args.out)) is not None:
        parser.error(f"--out {args.out}: {problem}")
    try:
        gt = load_ground_truth(args.video)
    except (OSError, ValueError) as exc:
        parser.error(f"{args.video}: no ground truth beside it (a video written by make_sequence.py): {exc}")
    if not args.video.is_file():  # a ground truth without its video: it was a FileNotFoundError's traceback
        parser.error(f"{args.video}: no such video file (its ground truth is there)")
    if args.frames and any(not 0 <= f < gt.num_frames for f in args.frames):
        parser.error(f"--frames must be in 0..{gt.num_frames - 1}, got {args.frames}")
    picks = args.frames if args.frames else pick_frames(gt.ypr_deg)
    kept, count = {}, 0  # only the picked frames are kept (a 3000-frame long run read whole took ~25 GB)
    for count, frame in enumerate(iter_video_uint8(args.video), start=1):
        if count - 1 in picks:
            kept[count - 1] = frame
    if count != gt.num_frames:
        raise SystemExit(f"overlay_landmarks.py: error: {args.video} has {count} frames, its ground truth "
                         f"{gt.num_frames}")
    lm_cam = transform_points(gt.rotation, gt.translation, gt.landmarks_3d)
    reproj = project_points(lm_cam, gt.intrinsics)
    err = (reproj - gt.landmarks_px).norm(dim=-1).max().item()
    print(f"{gt.name}: max |reprojected - landmarks_px| = {err:.2e} px over {gt.num_frames} frames")
    scale = args.scale or max(1, round(640 / gt.intrinsics.width))
    args.out.mkdir(parents=True, exist_ok=True)
    images = frames_to_uint8(torch.cat([kept[i] for i in picks]))
    for i, img in zip(picks, images):
        out = draw(np.ascontiguousarray(img), reproj[i].numpy(), gt.landmarks_visible[i].numpy(), scale)
        ypr = gt.ypr_deg[i].tolist()
        label = f"{gt.name} #{i} ypr=({ypr[0]:.0f},{ypr[1]:.0f},{ypr[2]:.0f})"
        cv2.putText(out, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        path = args.out / f"{gt.name}_{i:04d}.png"
        with written_whole(path) as tmp:  # (an interrupted write left a truncated PNG under its name)
            if not cv2.imwrite(str(tmp), out):
                raise SystemExit(f"overlay_landmarks.py: error: cannot write {path}")
        print(f"  wrote {path} ({int(gt.landmarks_visible[i].sum())}/68 landmarks visible)")
    return 0


if __name__ == "__main__":
    run_command(main)
