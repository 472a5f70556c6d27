"""Slow, obviously correct rasterizer: the test oracle for :func:`torchface.rendering.rasterizer.rasterize`.

Plain Python float64 loops over samples, pixels and triangles, with a different ray-triangle test
than the fast path: Möller–Trumbore (Möller and Trumbore, "Fast, minimum storage ray-triangle
intersection", J. Graphics Tools 2(1), 1997). Pixel ``(x, y)`` casts the ray
``d = ((x - cx) / fx, (y - cy) / fy, 1)`` from the camera centre; its parameter ``t`` at the hit is
the hit's depth ``Z`` because ``d_z = 1``. The rules match the fast path: inclusive edges
(barycentrics ``>= 0``), hits only at ``Z > near``, smallest depth wins and an exact depth tie goes to
the lowest face index, and zero-area, edge-on, non-finite or culled triangles produce nothing.
Only for tiny images (tens of pixels a side).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchface.conventions import NEAR_PLANE_MM
from torchface.geometry.camera import Intrinsics
from torchface.rendering.rasterizer import _DEGENERATE_EPS_FACTOR, Fragments, _check_mesh, _check_options

__all__ = ["rasterize_reference"]

Vec = tuple[float, float, float]


def _sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _norm(a: Vec) -> float:
    return math.sqrt(_dot(a, a))


def _moller_trumbore(d: Vec, v0: Vec, v1: Vec, v2: Vec) -> tuple[float, float, float] | None:
    """Ray ``0 + t d`` against triangle ``(v0, v1, v2)``: ``(t, u, v)`` with the hit ``(1-u-v) v0 + u v1 + v v2``.

    Returns None when the ray is parallel to the plane or misses the (closed) triangle.
    """
    e1, e2 = _sub(v1, v0), _sub(v2, v0)
    p = _cross(d, e2)
    det = _dot(e1, p)
    if det == 0.0:
        return None
    inv = 1.0 / det
    s = (-v0[0], -v0[1], -v0[2])
    u = _dot(s, p) * inv
    q = _cross(s, e1)
    v = _dot(d, q) * inv
    if u < 0.0 or v < 0.0 or u + v > 1.0:
        return None
    t = _dot(e2, q) * inv
    return t, u, v


def _face_ok(v0: Vec, v1: Vec, v2: Vec, eps: float) -> tuple[bool, bool]:
    """``(usable, front)`` for one triangle, with the fast path's degeneracy rules."""
    coords = v0 + v1 + v2
    if not all(math.isfinite(c) for c in coords):
        return False, False
    e01, e02, e12 = _sub(v1, v0), _sub(v2, v0), _sub(v2, v1)
    n = _cross(e01, e02)
    n_norm = _norm(n)
    max_edge_sq = max(_dot(e01, e01), _dot(e02, e02), _dot(e12, e12))
    k = _dot(n, v0)
    usable = n_norm > eps * max_edge_sq and abs(k) > eps * n_norm * _norm(v0)
    return usable, k < 0.0


def rasterize_reference(
    verts_cam: Tensor,
    faces: Tensor,
    intrinsics: Intrinsics,
    *,
    cull_backfaces: bool = False,
    near: float = NEAR_PLANE_MM,
) -> Fragments:
    """Reference rasterizer with the same contract as :func:`torchface.rendering.rasterizer.rasterize`.

    Args:
        verts_cam: ``(B, V, 3)`` float vertices in the camera frame (millimetres).
        faces: ``(F, 3)`` int vertex indices, counter-clockwise seen from outside.
        intrinsics: the camera (keep ``H x W`` tiny: the cost is ``B H W F`` Python iterations).
        cull_backfaces: drop triangles with ``n . v0 >= 0``.
        near: hits at depth ``Z <= near`` are discarded.

    Returns:
        :class:`Fragments` on the device of ``verts_cam``, ``bary``/``zbuf`` in its dtype, computed in
        float64. The degeneracy tolerances use the machine epsilon of ``verts_cam``'s dtype, like the
        fast path.

    Example:
        >>> cam = Intrinsics.default(8, 6)
        >>> v = torch.tensor([[[-50.0, -50, 100], [50, -50, 100], [0, 50, 100]]], dtype=torch.float64)
        >>> rasterize_reference(v, torch.tensor([[0, 2, 1]]), cam).pix_to_face[0, 3, 4].item()
        0
    """
    _check_mesh(verts_cam, faces, "verts_cam")
    cull_backfaces, near = _check_options(intrinsics, cull_backfaces, near)
    eps = torch.finfo(verts_cam.dtype).eps * _DEGENERATE_EPS_FACTOR
    verts = verts_cam.detach().cpu().to(torch.float64).numpy()
    tris = faces.detach().cpu().long().numpy()
    B, F = verts.shape[0], tris.shape[0]
    H, W = intrinsics.height, intrinsics.width
    pix_to_face = np.full((B, H, W), -1, dtype=np.int64)
    bary = np.zeros((B, H, W, 3), dtype=np.float64)
    zbuf = np.full((B, H, W), np.inf, dtype=np.float64)
    facing = np.zeros((B, H, W), dtype=np.int8)
    for b in range(B):
        corners = []
        for f in range(F):
            v0, v1, v2 = ((float(verts[b, i, 0]), float(verts[b, i, 1]), float(verts[b, i, 2])) for i in tris[f])
            usable, front = _face_ok(v0, v1, v2, eps)
            if cull_backfaces and not front:
                usable = False
            corners.append((usable, front, v0, v1, v2))
        for y in range(H):
            for x in range(W):
                d = ((x - intrinsics.cx) / intrinsics.fx, (y - intrinsics.cy) / intrinsics.fy, 1.0)
                best_t, best = math.inf, None
                for f, (usable, front, v0, v1, v2) in enumerate(corners):
                    if not usable:
                        continue
                    hit = _moller_trumbore(d, v0, v1, v2)
                    if hit is None:
                        continue
                    t, u, v = hit
                    if t > near and t < best_t:  # strict: an exact tie keeps the lower face index
                        best_t, best = t, (f, front, u, v)
                if best is not None:
                    f, front, u, v = best
                    pix_to_face[b, y, x] = f
                    bary[b, y, x] = (1.0 - u - v, u, v)
                    zbuf[b, y, x] = best_t
                    facing[b, y, x] = 1 if front else -1
    device, dtype = verts_cam.device, verts_cam.dtype
    return Fragments(
        pix_to_face=torch.from_numpy(pix_to_face).to(device),
        bary=torch.from_numpy(bary).to(device=device, dtype=dtype),
        zbuf=torch.from_numpy(zbuf).to(device=device, dtype=dtype),
        facing=torch.from_numpy(facing).to(device),
    )
