"""The "James" textured face scan (menpo3d sample data, BSD-3) in the head frame of torchface.

The package ships a compact copy built once from ``james.obj``/``james.jpg``/``james.ljson`` by
:func:`build_james_data` (run by ``scripts/build_synth_data.py``): ``data/james/james.npz`` holds the
vertices in the head frame and millimetres (see :mod:`torchface.conventions`), the triangles, the
per-vertex texture coordinates (top-down ``v``, see :mod:`torchface.rendering.shading`), a weld map
(vertices duplicated along texture seams share one normal) and the 68 iBUG landmarks as points on
the surface (triangle index + barycentric coordinates); ``data/james/james_texture.jpg`` is the
texture downsized to 1024 px wide.

Frame conversion. The OBJ is in millimetres with ``+x`` toward the subject's left, ``+y`` up and
``+z`` toward the viewer (the nose tip has the largest ``z``), and the head is slightly turned. A
180 degree rotation about ``x`` takes it to the head frame's axes; then the rigid motion (Kabsch,
no scale) that best maps the 51 inner landmarks (brows, nose, eyes, mouth: iBUG 17-67) onto those
of the neutral CANDIDE-3 mean is applied, so the identity pose of James is the identity pose of
CANDIDE-3 and ground-truth poses of both subjects are comparable.

The ``.ljson`` lists its 68 points grouped as chin, left eye, right eye, left brow, nose, right brow,
mouth (menpo's old grouping, "left" = image left); :data:`LJSON_TO_IBUG` reorders them into iBUG-68.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

__all__ = ["LJSON_TO_IBUG", "ScanData", "load_james", "build_james_data", "closest_points_on_triangles"]

#: ``ibug[i] = ljson[LJSON_TO_IBUG[i]]``: jaw, right brow (image left), left brow, nose, right eye, left eye, mouth.
LJSON_TO_IBUG: tuple[int, ...] = (
    tuple(range(0, 17))
    + tuple(range(29, 34))
    + tuple(range(43, 48))
    + tuple(range(34, 43))
    + tuple(range(17, 23))
    + tuple(range(23, 29))
    + tuple(range(48, 68))
)

_DATA_DIR = "james"
_NPZ = "james.npz"
_TEXTURE = "james_texture.jpg"


@dataclass(frozen=True, eq=False)
class ScanData:
    """A rigid textured scan in the head frame.

    Attributes:
        verts: ``(V, 3)`` float32 millimetres, head frame.
        faces: ``(F, 3)`` int64, counter-clockwise seen from outside.
        uv: ``(V, 2)`` texture coordinates (``(0, 0)`` = top-left of the texture).
        texture: ``(3, Ht, Wt)`` float32 RGB in ``[0, 1]``.
        weld: ``(V,)`` int64 index of each vertex's welded position (seam duplicates share one).
        landmark_faces: ``(K,)`` int64 triangle of each landmark (``K = 68``, iBUG order).
        landmark_bary: ``(K, 3)`` barycentric coordinates of each landmark in its triangle.
    """

    verts: Tensor
    faces: Tensor
    uv: Tensor
    texture: Tensor
    weld: Tensor
    landmark_faces: Tensor
    landmark_bary: Tensor


def _data_path(name: str) -> Path:
    return Path(str(resources.files("torchface").joinpath("data", _DATA_DIR, name)))


@functools.lru_cache(maxsize=1)
def _load_cached() -> ScanData:
    import cv2

    npz_path, tex_path = _data_path(_NPZ), _data_path(_TEXTURE)
    if not npz_path.is_file() or not tex_path.is_file():
        raise FileNotFoundError(f"packaged James scan missing: expected {npz_path} and {tex_path}")
    with np.load(npz_path) as z:
        arrays = {k: z[k] for k in z.files}
    bgr = cv2.imread(str(tex_path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"could not read {tex_path}")
    texture = torch.from_numpy(np.ascontiguousarray(bgr[:, :, ::-1])).permute(2, 0, 1).float() / 255.0
    return ScanData(
        verts=torch.from_numpy(arrays["verts"]).float(),
        faces=torch.from_numpy(arrays["faces"]).long(),
        uv=torch.from_numpy(arrays["uv"]).float(),
        texture=texture.contiguous(),
        weld=torch.from_numpy(arrays["weld"]).long(),
        landmark_faces=torch.from_numpy(arrays["landmark_faces"]).long(),
        landmark_bary=torch.from_numpy(arrays["landmark_bary"]).float(),
    )


def load_james() -> ScanData:
    """The packaged James scan (read once per process, then served from memory).

    Example:
        >>> scan = load_james()
        >>> scan.verts.shape, scan.landmark_faces.shape
        (torch.Size([6680, 3]), torch.Size([68]))
    """
    return _load_cached()


def closest_points_on_triangles(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest surface point of a triangle soup to each query point (brute force, build time only).

    Uses the region tests of Ericson, "Real-Time Collision Detection" (2005), section 5.1.5,
    vectorised over all (point, triangle) pairs.

    Args:
        points: ``(N, 3)`` query points.
        triangles: ``(F, 3, 3)`` triangle corners.

    Returns:
        ``face (N,)`` index of the nearest triangle, ``bary (N, 3)`` barycentric coordinates of the
        closest point in it, ``distance (N,)``.
    """
    p = points[:, None, :]
    a, b, c = triangles[None, :, 0], triangles[None, :, 1], triangles[None, :, 2]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    tiny = 1e-30
    # Interior by default.
    denom = np.where(np.abs(va + vb + vc) > tiny, va + vb + vc, tiny)
    v = vb / denom
    w = vc / denom
    bary = np.stack([1 - v - w, v, w], axis=-1)

    def put(mask: np.ndarray, value: np.ndarray) -> None:
        bary[mask] = value[mask]

    zeros = np.zeros_like(d1)
    ones = np.ones_like(d1)
    # Edge BC.
    t_bc = np.clip((d4 - d3) / np.where(np.abs((d4 - d3) + (d5 - d6)) > tiny, (d4 - d3) + (d5 - d6), tiny), 0, 1)
    put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), np.stack([zeros, 1 - t_bc, t_bc], -1))
    # Edge AC.
    t_ac = np.clip(d2 / np.where(np.abs(d2 - d6) > tiny, d2 - d6, tiny), 0, 1)
    put((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - t_ac, zeros, t_ac], -1))
    # Vertex C, then edge AB, then vertices B and A (later assignments take precedence, as in Ericson's order).
    put((d6 >= 0) & (d5 <= d6), np.stack([zeros, zeros, ones], -1))
    t_ab = np.clip(d1 / np.where(np.abs(d1 - d3) > tiny, d1 - d3, tiny), 0, 1)
    put((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - t_ab, t_ab, zeros], -1))
    put((d3 >= 0) & (d4 <= d3), np.stack([zeros, ones, zeros], -1))
    put((d1 <= 0) & (d2 <= 0), np.stack([ones, zeros, zeros], -1))
    closest = bary[..., 0:1] * a + bary[..., 1:2] * b + bary[..., 2:3] * c
    dist = np.linalg.norm(closest - p, axis=-1)
    face = dist.argmin(axis=1)
    rows = np.arange(points.shape[0])
    return face, bary[rows, face], dist[rows, face]


def _kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation ``R`` and translation ``t`` minimising ``sum |R src + t - dst|^2`` (no scale)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    h = (src - mu_s).T @ (dst - mu_d)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, mu_d - r @ mu_s


def build_james_data(asset_dir: str | Path, out_dir: str | Path, texture_width: int = 1024) -> dict[str, float]:
    """Convert the James assets into the package's compact form (development-time tool).

    Args:
        asset_dir: folder with ``james.obj``, ``james.jpg``, ``james.ljson`` and ``LICENSE.txt``.
        out_dir: destination folder (``torchface/data/james``).
        texture_width: width of the stored JPEG texture in pixels.

    Returns:
        Figures about the conversion: landmark snapping distances and the alignment residual (mm).
    """
    import shutil

    import cv2
    import trimesh

    from torchface.model import load_candide3

    asset_dir, out_dir = Path(asset_dir), Path(out_dir)
    img = cv2.imread(str(asset_dir / "james.jpg"), cv2.IMREAD_COLOR)  # first: nothing is written without it
    if img is None:
        raise FileNotFoundError(f"could not read the texture image {asset_dir / 'james.jpg'}")
    mesh = trimesh.load(asset_dir / "james.obj", process=False, force="mesh")
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"{asset_dir / 'james.obj'} must hold one triangle mesh, got a {type(mesh).__name__}")
    if not isinstance(mesh.visual, trimesh.visual.TextureVisuals):
        raise ValueError(f"{asset_dir / 'james.obj'} has no texture coordinates")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    uv = np.asarray(mesh.visual.uv, dtype=np.float64).copy()
    uv[:, 1] = 1.0 - uv[:, 1]  # OBJ v runs bottom-up; the shading convention is top-down.
    ljson = json.loads((asset_dir / "james.ljson").read_text())
    lm = np.asarray(ljson["groups"]["LJSON"]["landmarks"]["points"], dtype=np.float64)[list(LJSON_TO_IBUG)]

    flip = np.diag([1.0, -1.0, -1.0])  # 180 degrees about x: (+x left, +y up, +z viewer) -> head frame axes.
    verts, lm = verts @ flip.T, lm @ flip.T
    candide = load_candide3(dtype=torch.float64)
    target = candide.landmarks_3d(candide.deform()).squeeze(0).numpy()
    inner = slice(17, 68)
    r, t = _kabsch(lm[inner], target[inner])
    verts = verts @ r.T + t
    lm = lm @ r.T + t
    residual = np.linalg.norm(lm[inner] - target[inner], axis=1)

    face, bary, dist = closest_points_on_triangles(lm, verts[faces])
    _, weld = np.unique(verts.round(6), axis=0, return_inverse=True)

    out_dir.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out_dir / _NPZ,
        verts=verts.astype(np.float32),
        faces=faces.astype(np.int32),
        uv=uv.astype(np.float32),
        weld=weld.reshape(-1).astype(np.int32),
        landmark_faces=face.astype(np.int32),
        landmark_bary=bary.astype(np.float32),
        landmarks_source=lm.astype(np.float32),
        head_from_file_rotation=(r @ flip),
        head_from_file_translation=t,
    )
    h = int(round(img.shape[0] * texture_width / img.shape[1]))
    small = cv2.resize(img, (texture_width, h), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(out_dir / _TEXTURE), small, [cv2.IMWRITE_JPEG_QUALITY, 88])
    shutil.copyfile(asset_dir / "LICENSE.txt", out_dir / "LICENSE.txt")
    _load_cached.cache_clear()
    return {
        "snap_mean_mm": float(dist.mean()),
        "snap_max_mm": float(dist.max()),
        "align_rms_mm": float(np.sqrt((residual**2).mean())),
        "align_max_mm": float(residual.max()),
    }
