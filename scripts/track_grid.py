#!/usr/bin/env python
"""Track the GRID talking-head clips (../shared/assets/grid) as one batch and report per clip.

Per clip: fraction of successful frames, mean confidence, tracking fps; saves overlay frames as PNG
(first, middle, last) for a visual check. Landmarks of the first frames come from ``--landmarks-dir``
(``<stem>.csv`` files, 68 iBUG points) or from ``--detector``.

Example:
    python scripts/track_grid.py --landmarks-dir /tmp/grid_lm --out out/grid
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from torchface.cli import ProgressDisplay
from torchface.io import read_track_csv
from torchface.job import JobConfig, output_paths, track_videos

GRID = Path(__file__).resolve().parents[2] / "shared" / "assets" / "grid"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", type=Path, default=GRID, help="folder of GRID .mpg clips")
    parser.add_argument("--landmarks-dir", type=Path, default=None, help="folder of <stem>.csv first-frame landmarks")
    parser.add_argument("--detector", default=None, help="detector name when no landmarks folder is given")
    parser.add_argument("--out", type=Path, default=Path("out/grid"), help="output folder")
    parser.add_argument("--frames", type=int, nargs="*", default=[0, 37, 74], help="overlay frames saved as PNG")
    args = parser.parse_args(argv)
    if not args.grid.is_dir():
        print(f"no GRID clips at {args.grid}", file=sys.stderr)
        return 2
    clips = sorted(args.grid.glob("*.mpg"))
    landmarks = tuple(args.landmarks_dir / f"{c.stem}.csv" for c in clips) if args.landmarks_dir else ()
    config = JobConfig(out_dir=args.out, landmarks=landmarks, detector=args.detector)
    start = time.perf_counter()
    summaries = track_videos(clips, config, progress=ProgressDisplay())
    wall = time.perf_counter() - start
    table = []
    print(f"\n{'clip':<16} {'frames':>6} {'success':>8} {'mean conf':>9} {'min conf':>8} {'fps':>6}")
    for s in summaries:
        cols, rows = read_track_csv(output_paths(args.out, s.name)["csv"])
        ok = rows[:, cols.index("success")]
        conf = rows[:, cols.index("confidence")]
        table.append({"clip": s.name, "frames": s.frames, "success": float(ok.mean()), "mean_confidence": float(conf.mean()),
                      "min_confidence": float(conf.min()), "fps": s.fps})  # fmt: skip
        print(f"{s.name:<16} {s.frames:>6} {ok.mean():>8.3f} {conf.mean():>9.3f} {conf.min():>8.3f} {s.fps:>6.2f}")
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
        if images:
            cv2.imwrite(str(args.out / f"{s.name}_frames.png"), np.hstack(images))
    total = sum(s.frames for s in summaries)
    print(f"all {len(summaries)} clips: {total} frames in {wall:.1f} s wall ({total / wall:.2f} frames/s overall, batched)")
    (args.out / "grid_summary.json").write_text(json.dumps({"clips": table, "wall_s": wall, "frames": total}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
