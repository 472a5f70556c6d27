"""Triangle-mesh normals (outward winding: ``n = (v1 - v0) x (v2 - v0)`` points out of the surface).

Shared by the face model (illumination normals of template points) and the rasterizer's visibility tests.
"""

from __future__ import annotations

import torch
from torch import Tensor


def _face_cross(verts: Tensor, faces: Tensor) -> Tensor:
    """``(B, F, 3)`` un-normalised face normals ``(v1 - v0) x (v2 - v0)`` (length = twice the area)."""
    v0 = verts[:, faces[:, 0]]
    v1 = verts[:, faces[:, 1]]
    v2 = verts[:, faces[:, 2]]
    return torch.linalg.cross(v1 - v0, v2 - v0, dim=-1)


def _safe_normalize(vec: Tensor) -> Tensor:
    """Unit vectors along the last axis; zero vectors stay zero with finite gradients."""
    eps = torch.finfo(vec.dtype).eps
    sq = (vec * vec).sum(dim=-1, keepdim=True)
    return vec * torch.rsqrt(sq.clamp_min(eps * eps))


def face_normals(verts: Tensor, faces: Tensor) -> Tensor:
    """Unit face normals ``n = (v1 - v0) x (v2 - v0) / |...|``.

    With an outward winding (as :class:`~torchface.model.FaceModel` has) they point out of the surface. Degenerate triangles give
    zero vectors (no NaN, finite gradients).

    Args:
        verts: ``(B, V, 3)`` vertices.
        faces: ``(F, 3)`` int64 triangle vertex indices.

    Returns:
        ``(B, F, 3)`` unit normals.

    Example:
        >>> v = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]]])
        >>> face_normals(v, torch.tensor([[0, 1, 2]]))
        tensor([[[0., 0., 1.]]])
    """
    return _safe_normalize(_face_cross(verts, faces))


def vertex_normals(verts: Tensor, faces: Tensor) -> Tensor:
    """Area-weighted unit vertex normals: the normalised sum of the incident faces' cross products.

    Vertices that no face uses get zero vectors (no NaN, finite gradients).

    Args:
        verts: ``(B, V, 3)`` vertices.
        faces: ``(F, 3)`` int64 triangle vertex indices.

    Returns:
        ``(B, V, 3)`` unit normals.

    Example:
        >>> v = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0], [5.0, 5, 5]]])
        >>> vertex_normals(v, torch.tensor([[0, 1, 2]]))[0]
        tensor([[0., 0., 1.],
                [0., 0., 1.],
                [0., 0., 1.],
                [0., 0., 0.]])
    """
    return _vertex_sums_normalized(_face_cross(verts, faces), faces, verts)


def _vertex_sums_normalized(cross: Tensor, faces: Tensor, verts: Tensor) -> Tensor:
    """``(B, V, 3)`` unit sums of the cross products ``(B, F, 3)`` of the faces that use each vertex (zero where
    none does). Both vertex-normal functions sum through here, in one order: a different order changes the
    normals at the rounding level, which moved benchmark results (``vertex_normals_and_backfacing``)."""
    acc = torch.zeros_like(verts)
    for corner in range(3):  # three scatter-adds, one per triangle corner
        acc = acc.index_add(1, faces[:, corner], cross)
    return _safe_normalize(acc)


def vertex_normals_and_backfacing(verts_cam: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`vertex_normals` and the back-facing triangles of camera-frame vertices, from one computation of the
    triangles' cross products (the normals of a posed mesh are its rotated head-frame normals).

    Args:
        verts_cam: ``(B, V, 3)`` vertices in the camera frame (camera at the origin).
        faces: ``(F, 3)`` int64 triangle vertex indices.

    Returns:
        ``(B, V, 3)`` unit vertex normals and ``(B, F)`` bool, True where the triangle turns away from the camera
        (``n . v0 >= 0``, as :func:`~torchface.rendering.visibility.backfacing`).
    """
    B, F = verts_cam.shape[0], faces.shape[0]
    tri = verts_cam.index_select(1, faces.reshape(-1)).view(B, F, 3, 3)
    v0 = tri[:, :, 0]
    cross = torch.linalg.cross(tri[:, :, 1] - v0, tri[:, :, 2] - v0, dim=-1)  # (B, F, 3), length 2 * area
    back = (cross * v0).sum(-1) >= 0
    return _vertex_sums_normalized(cross, faces, verts_cam), back
