"""Normals, back-face tests and point visibility (self-occlusion, the paper's Section 4).

The paper drops template points whose facet turns away from the camera or that a z-buffer hides.
:func:`backfacing` is the first test per triangle, :func:`points_visible` combines both per point
against the :class:`~torchface.rendering.rasterizer.Fragments` of the current pose.
Winding: ``n = (v1 - v0) x (v2 - v0)`` points out of the surface (see :mod:`torchface.conventions`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchface import _native
from torchface.backend import Backend, use_native
from torchface.conventions import NEAR_PLANE_MM
from torchface.geometry import mesh
from torchface.geometry._checks import check_number
from torchface.geometry.camera import Intrinsics
from torchface.rendering.rasterizer import Coverage, Fragments, _check_mesh, _triangles

__all__ = ["face_normals", "vertex_normals", "backfacing", "points_visible"]

#: Default relative depth tolerance of :func:`points_visible` (fraction of the point's depth).
DEFAULT_DEPTH_TOLERANCE: float = 1e-2


def face_normals(verts: Tensor, faces: Tensor) -> Tensor:
    """Unit outward normals ``n = (v1 - v0) x (v2 - v0) / |...|`` of every triangle.

    Args:
        verts: ``(B, V, 3)`` vertex positions in any frame.
        faces: ``(F, 3)`` int vertex indices, counter-clockwise seen from outside.

    Returns:
        ``(B, F, 3)`` unit normals in the frame of ``verts``; zero for zero-area triangles.

    Example:
        >>> v = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
        >>> face_normals(v, torch.tensor([[0, 1, 2]]))
        tensor([[[0., 0., 1.]]])
    """
    _check_mesh(verts, faces)
    return mesh.face_normals(verts, faces.long())


def vertex_normals(verts: Tensor, faces: Tensor) -> Tensor:
    """Area-weighted unit vertex normals (the paper's per-point normals for the illumination basis, Eq. 19).

    Each vertex normal is the sum of the unnormalised normals ``(v1 - v0) x (v2 - v0)`` (twice the
    area times the unit normal) of the triangles that use it, normalised.

    Args:
        verts: ``(B, V, 3)`` vertex positions.
        faces: ``(F, 3)`` int vertex indices.

    Returns:
        ``(B, V, 3)`` unit normals; zero for vertices used by no triangle (or only degenerate ones).

    Example:
        >>> v = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]]])
        >>> vertex_normals(v, torch.tensor([[0, 1, 2]]))[0, :, 2]
        tensor([1., 1., 1., 0.])
    """
    _check_mesh(verts, faces)
    return mesh.vertex_normals(verts, faces.long())


def backfacing(verts_cam: Tensor, faces: Tensor) -> Tensor:
    """Which triangles turn away from the camera at the origin: ``n . v0 >= 0``.

    With outward normals ``n = (v1 - v0) x (v2 - v0)``, a triangle faces the camera iff its normal
    points back toward the camera centre, ``n . (0 - v0) > 0``. Zero-area and edge-on triangles count
    as back-facing.

    Args:
        verts_cam: ``(B, V, 3)`` vertices in the camera frame (millimetres).
        faces: ``(F, 3)`` int vertex indices.

    Returns:
        ``(B, F)`` bool, True where back-facing.

    Example:
        >>> v = torch.tensor([[[0.0, 0, 100], [1, 0, 100], [0, 1, 100]]])
        >>> backfacing(v, torch.tensor([[0, 1, 2], [0, 2, 1]]))
        tensor([[ True, False]])
    """
    _check_mesh(verts_cam, faces, "verts_cam")
    tri = _triangles(verts_cam, faces)
    n = torch.linalg.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :], dim=-1)
    return (n * tri[..., 0, :]).sum(-1) >= 0


def points_visible(
    points_cam: Tensor,
    point_faces: Tensor,
    fragments: Fragments | Coverage,
    intrinsics: Intrinsics,
    *,
    depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE,
    near: float = NEAR_PLANE_MM,
    backend: Backend = Backend.AUTO,
) -> Tensor:
    """Which surface points the camera sees, given the fragments of the same pose.

    A point ``X = (X, Y, Z)`` lying on triangle ``point_faces[b, n]`` is visible iff all hold:

    * it is in front of the near plane, ``Z > near``;
    * it projects inside the image: its nearest pixel centre ``(round(u), round(v))`` with
      ``u = fx X / Z + cx``, ``v = fy Y / Z + cy`` lies in ``[0, W - 1] x [0, H - 1]``;
    * the surface seen at that pixel is front-facing (``fragments.facing == +1``), which also rejects
      points whose pixel is background;
    * it is not hidden: the pixel shows its own triangle, or the z-buffer there is not closer than
      its depth by more than ``depth_tolerance * Z``.

    Nearest-pixel sampling makes the answer conservative at silhouettes, where the pixel centre may
    fall off the mesh.

    Args:
        points_cam: ``(B, N, 3)`` points in the camera frame (millimetres).
        point_faces: ``(B, N)`` or ``(N,)`` int64 index of the triangle each point lies on.
        fragments: :func:`~torchface.rendering.rasterizer.rasterize` output ``(B, H, W)`` for the
            same vertices and ``intrinsics``, or their :func:`~torchface.rendering.rasterizer.rasterize_coverage`
            (the depth is then evaluated at the points' pixels alone: the same answer).
        intrinsics: the camera.
        depth_tolerance: allowed relative depth gap (fraction of ``Z``, non-negative) between the
            z-buffer and the point. The surface seen at the pixel centre differs in depth from a point
            up to half a pixel away by about ``slope * 0.7 Z / f``, so the tolerance should exceed
            ``0.7 slope / f``; the default, 1 %, suits ``f ~ 640`` px up to slopes of about 9
            (surfaces within about 84 degrees of facing the camera).
        near: points at depth ``Z <= near`` (millimetres) are not visible.
        backend: :class:`~torchface.backend.Backend`: with a Coverage, the native kernel tests each point with
            the same arithmetic (the same answer; ``torchface/_native/visible.h``), or this torch code.

    Returns:
        ``(B, N)`` bool.

    Example:
        >>> from torchface.rendering.rasterizer import rasterize
        >>> cam = Intrinsics.default(32, 24)
        >>> tri = torch.tensor([[-50.0, -50, 1], [50, -50, 1], [0, 50, 1]])
        >>> v = torch.cat([tri * torch.tensor([1.0, 1, 100]), tri * torch.tensor([1.0, 1, 150])])[None]
        >>> faces = torch.tensor([[0, 2, 1], [3, 5, 4]])  # the second triangle is behind the first
        >>> frag = rasterize(v, faces, cam)
        >>> pts = torch.tensor([[[0.0, 0.0, 100.0], [0.0, 0.0, 150.0]]])
        >>> points_visible(pts, torch.tensor([0, 1]), frag, cam)
        tensor([[ True, False]])
    """
    if not isinstance(points_cam, Tensor) or not points_cam.is_floating_point():
        raise TypeError(f"points_cam must be a floating-point tensor, got {type(points_cam).__name__}")
    if points_cam.ndim != 3 or points_cam.shape[-1] != 3:
        raise ValueError(f"points_cam must be (B, N, 3), got {tuple(points_cam.shape)}")
    B, N = points_cam.shape[:2]
    if not isinstance(point_faces, Tensor) or point_faces.dtype not in (torch.int32, torch.int64):
        got = point_faces.dtype if isinstance(point_faces, Tensor) else type(point_faces).__name__
        raise TypeError(f"point_faces must be an int32/int64 tensor, got {got}")
    if point_faces.shape not in ((N,), (B, N)):
        raise ValueError(f"point_faces must be (N,) or (B, N) = ({N},) or ({B}, {N}), got {tuple(point_faces.shape)}")
    if not isinstance(fragments, (Fragments, Coverage)):
        raise TypeError(f"fragments must be a Fragments or a Coverage, got {type(fragments).__name__}")
    if not isinstance(intrinsics, Intrinsics):
        raise TypeError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    H, W = intrinsics.height, intrinsics.width
    if fragments.pix_to_face.shape != (B, H, W):
        raise ValueError(
            f"fragments must be (B, H, W) = ({B}, {H}, {W}) to match points_cam and intrinsics, "
            f"got {tuple(fragments.pix_to_face.shape)}"
        )
    if type(depth_tolerance) is not float or not 0 <= depth_tolerance < math.inf:  # (inf passed ">= 0"; a string
        # was "'<=' not supported between instances")
        depth_tolerance = check_number(depth_tolerance, "depth_tolerance", "[0, inf)", unit="a fraction of the depth")
    if type(near) is not float or not 0 < near < math.inf:  # (NaN: no point visible, without a word)
        near = check_number(near, "near", "(0, inf)", unit="millimetres")

    pts = points_cam.detach()
    if isinstance(fragments, Coverage):
        native = _native_visible(pts, point_faces, fragments, intrinsics, depth_tolerance, near, backend)
        if native is not None:
            return native
    z = pts[..., 2]
    in_front = z > near
    z_safe = torch.where(in_front, z, torch.ones_like(z))
    u = pts[..., 0] / z_safe * intrinsics.fx + intrinsics.cx
    v = pts[..., 1] / z_safe * intrinsics.fy + intrinsics.cy
    col = torch.floor(u + 0.5)
    row = torch.floor(v + 0.5)
    inside = in_front & (col >= 0) & (col <= W - 1) & (row >= 0) & (row <= H - 1)
    col = torch.where(inside, col, torch.zeros_like(col)).long()
    row = torch.where(inside, row, torch.zeros_like(row)).long()
    # One flat index for the three gathers (advanced indexing by (batch, row, col) cost 3x as much at one stream).
    flat = (torch.arange(B, device=pts.device).unsqueeze(-1) * H + row) * W + col
    seen_face = fragments.pix_to_face.reshape(-1).take(flat)
    if isinstance(fragments, Coverage):  # the z-buffer's depth evaluated at these pixels alone, by its arithmetic
        covered = (seen_face >= 0).reshape(-1).nonzero().squeeze(-1)
        b_of = torch.arange(B, device=pts.device).repeat_interleave(N).index_select(0, covered)
        depth = fragments.covered_depths(b_of, seen_face.reshape(-1).index_select(0, covered),
                                         row.reshape(-1).index_select(0, covered),
                                         col.reshape(-1).index_select(0, covered))[1]  # fmt: skip
        seen_depth = torch.full((B * N,), float("inf"), dtype=pts.dtype, device=pts.device)
        seen_depth = seen_depth.index_put((covered,), depth.detach().to(pts.dtype)).reshape(B, N)
    else:
        seen_depth = fragments.zbuf.detach().reshape(-1).take(flat).to(pts.dtype)
    seen_facing = fragments.facing.reshape(-1).take(flat)
    own = seen_face == point_faces.to(seen_face.device).long().expand(B, N)
    not_hidden = own | (seen_depth >= z * (1.0 - depth_tolerance))
    return inside & (seen_facing == 1) & not_hidden


def _native_visible(
    pts: Tensor, point_faces: Tensor, coverage: Coverage, intrinsics: Intrinsics, depth_tolerance: float, near: float,
    backend: Backend,
) -> Tensor | None:
    """:func:`points_visible` of ``pts (B, N, 3)`` (detached) against a coverage by the native kernel, or None where
    it does not run (``backend``, the dtypes, a device other than the CPU, a coverage that is a view into a larger
    one's pixels)."""
    coefficients = coverage.coefficients.detach()
    if not (coverage.pix_to_face.is_contiguous() and coverage.facing.is_contiguous()
            and coefficients.dtype == pts.dtype and coverage.ray_a.dtype == pts.dtype
            and coverage.ray_b.dtype == pts.dtype and coverage.pix_to_face.device == pts.device):  # fmt: skip
        return None
    if not use_native(backend, (pts, coefficients, coverage.ray_a.detach(), coverage.ray_b.detach()), "visibility test"):
        return None
    B, N = pts.shape[:2]
    H, W = intrinsics.height, intrinsics.width
    pts = pts.contiguous()
    faces = point_faces.to(torch.int64).contiguous()
    coefficients = coefficients.contiguous()
    ray_a, ray_b = coverage.ray_a.detach().contiguous(), coverage.ray_b.detach().contiguous()
    out = torch.empty(B, N, dtype=torch.bool)
    prob = _native.VisibleProblem(
        B=B, N=N, H=H, W=W, F=coverage.num_faces, batch_offset=coverage.batch_offset,
        faces_batched=int(faces.dim() == 2), num_columns=coefficients.shape[1], fx=intrinsics.fx, fy=intrinsics.fy,
        cx=intrinsics.cx, cy=intrinsics.cy, near=float(near), keep=1.0 - depth_tolerance, points=pts.data_ptr(),
        point_faces=faces.data_ptr(), pix_to_face=coverage.pix_to_face.data_ptr(), facing=coverage.facing.data_ptr(),
        coefficients=coefficients.data_ptr(), ray_a=ray_a.data_ptr(), ray_b=ray_b.data_ptr(), out=out.data_ptr(),
    )  # fmt: skip
    _native.run("visible", pts.dtype == torch.float64, prob, B, torch.get_num_threads())
    return out
