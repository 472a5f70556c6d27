"""Batched, vectorised triangle rasterizer with a z-buffer (see :mod:`torchface.conventions`).

The rasterizer answers, for every pixel centre of every sample, which triangle is nearest along the
pixel's ray, where on that triangle the ray lands (perspective-correct barycentric coordinates) and
at which camera depth. Shading, template sampling and self-occlusion tests (the paper's Section 4,
"facets that a z-buffer hides") consume these :class:`Fragments`.

Method
------
Pixel ``(x, y)`` samples the ray ``d = ((x - cx) / fx, (y - cy) / fy, 1)`` from the camera centre.
For a triangle ``(v0, v1, v2)`` in the camera frame the ray meets its plane at the point with
barycentric coordinates proportional to the triple products

    ``e0 = d . (v1 x v2)``,   ``e1 = d . (v2 x v0)``,   ``e2 = d . (v0 x v1)``,

whose sum is ``d . n`` with ``n = (v1 - v0) x (v2 - v0)``. The ray hits the triangle iff the three
normalised coordinates ``lambda_i = e_i / (e0 + e1 + e2)`` are all ``>= 0``, and the hit lies at depth
``Z = (n . v0) / (n . d)`` (equal to ``sum_i lambda_i z_i``). These coordinates are those of the 3D
surface point, hence perspective-correct, and they stay valid for triangles that cross the camera
plane, where projected 2D barycentrics would not. A hit counts only when ``Z > near``.

Because ``e_i = lambda_i (n . v0) / t`` and ``n . d = (n . v0) / t`` for the hit at ``t d``, a hit in
front of the camera (``t > 0``) has all of them of the sign of ``n . v0``; each triangle's
coefficients are multiplied by ``sign(n . v0)`` once; a hit is then ``e_i >= 0`` for all ``i`` and
``n . d > 0`` with no per-pixel division.

Candidate (triangle, pixel) pairs come from each triangle's projected bounding box clamped to the
image (the whole image for a triangle with a vertex at or behind the near plane), enumerated with
``repeat_interleave``/``cumsum`` arithmetic in chunks of bounded size.

Tie rules
---------
Hits are inclusive (``lambda_i >= 0``), so a pixel centre exactly on an edge shared by two triangles
hits both; the z-buffer keeps the smaller depth and, on an exact depth tie, the lower face index.
Each pixel therefore gets exactly one triangle. :func:`torchface.rendering.reference.rasterize_reference`
follows the same rules.

Degenerate triangles
--------------------
A triangle produces no fragment when it has (numerically) zero area, ``|n| <= 16 eps max_edge^2``,
when it is seen exactly edge-on, ``|n . v0| <= 16 eps |n| |v0|`` (``eps`` of the input dtype), when it
lies entirely at or behind the near plane, or when a vertex is not finite.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchface.conventions import NEAR_PLANE_MM
from torchface.geometry.camera import Intrinsics

__all__ = ["Fragments", "rasterize"]

#: Upper bound on the number of (triangle, pixel) candidate pairs evaluated at once.
_MAX_PAIRS_PER_CHUNK: int = 1 << 21

#: Relative tolerance, in units of the dtype's machine epsilon, for degenerate and edge-on triangles.
_DEGENERATE_EPS_FACTOR: float = 16.0

#: Margin (pixels) added to projected bounding boxes so rounding never drops a pixel on an edge.
_BBOX_MARGIN_PX: float = 1e-3

# Columns of the per-face coefficient table built by :func:`_face_coefficients`.
_E0, _E1, _E2, _DEN = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)
_K = 12
_NUM_COEFFS = 13


@dataclass(frozen=True)
class Fragments:
    """What each pixel centre sees: the output of :func:`rasterize`.

    ``pix_to_face[b, y, x] = f`` means triangle ``f`` (an index into ``faces``) is the nearest at that
    pixel centre; ``-1`` is background. ``bary[b, y, x]`` are its perspective-correct barycentric
    coordinates (of the 3D surface point, summing to 1; zeros for background); ``zbuf[b, y, x]`` is
    the camera-frame depth ``Z`` of that point (``+inf`` for background); ``facing[b, y, x]`` is
    ``+1`` where the visible triangle is front-facing, ``-1`` back-facing, ``0`` background.

    Attributes:
        pix_to_face: ``(B, H, W)`` int64.
        bary: ``(B, H, W, 3)`` in the vertices' dtype.
        zbuf: ``(B, H, W)`` in the vertices' dtype, millimetres.
        facing: ``(B, H, W)`` int8.
    """

    pix_to_face: Tensor
    bary: Tensor
    zbuf: Tensor
    facing: Tensor

    @property
    def foreground(self) -> Tensor:
        """``(B, H, W)`` bool, True where some triangle covers the pixel centre."""
        return self.pix_to_face >= 0


def _check_mesh(verts: Tensor, faces: Tensor, name: str = "verts") -> None:
    """Validate a batched vertex tensor ``(B, V, 3)`` and an unbatched face tensor ``(F, 3)``."""
    if not isinstance(verts, Tensor) or not isinstance(faces, Tensor):
        raise TypeError(f"{name} and faces must be tensors, got {type(verts).__name__} and {type(faces).__name__}")
    if verts.ndim != 3 or verts.shape[-1] != 3:
        raise ValueError(f"{name} must be (B, V, 3), got {tuple(verts.shape)}")
    if not verts.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {verts.dtype}")
    if faces.ndim != 2 or faces.shape[-1] != 3:
        raise ValueError(f"faces must be (F, 3), got {tuple(faces.shape)}")
    if faces.dtype not in (torch.int32, torch.int64):
        raise TypeError(f"faces must be int32 or int64, got {faces.dtype}")
    if faces.device != verts.device:
        raise ValueError(f"faces must be on {name}' device {verts.device}, got {faces.device}")


def _triangles(verts: Tensor, faces: Tensor) -> Tensor:
    """Corner positions ``(B, F, 3, 3)`` (last-but-one axis: corner 0, 1, 2) of ``faces (F, 3)``."""
    return verts[:, faces.long()]


def _face_coefficients(tri: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per-triangle ray-test coefficients, oriented so that a hit in front of the camera is positive.

    Args:
        tri: ``(B, F, 3, 3)`` triangle corners in the camera frame.

    Returns:
        ``coeffs (B, F, 13)``: for ``d = (a, b, 1)``, ``e_i = coeffs[3i] a + coeffs[3i+1] b + coeffs[3i+2]``
        (``i = 0, 1, 2``, the triple products ``d . (v_{i+1} x v_{i+2})``), ``den = n . d`` from columns
        9..11 and ``k = n . v0`` in column 12, all multiplied by ``sign(n . v0)``;
        ``front (B, F)`` bool (``n . v0 < 0``); ``usable (B, F)`` bool (finite, non-degenerate,
        not edge-on).
    """
    v0, v1, v2 = tri.unbind(-2)
    e01, e02 = v1 - v0, v2 - v0
    n = torch.linalg.cross(e01, e02, dim=-1)
    # Cross products of differences keep precision: v1 x v2 = v1 x (v2 - v1), etc.
    c0 = torch.linalg.cross(v1, v2 - v1, dim=-1)
    c1 = torch.linalg.cross(v2, v0 - v2, dim=-1)
    c2 = torch.linalg.cross(v0, e01, dim=-1)
    k = (n * v0).sum(-1)
    front = k < 0
    sign = torch.where(front, -1.0, 1.0).to(tri.dtype)  # sign(n . v0)

    eps = torch.finfo(tri.dtype).eps * _DEGENERATE_EPS_FACTOR
    n_norm = torch.linalg.vector_norm(n, dim=-1)
    edge_sq = torch.stack([(e01 * e01).sum(-1), (e02 * e02).sum(-1), ((v2 - v1) ** 2).sum(-1)], -1)
    max_edge_sq = edge_sq.amax(-1)
    usable = (
        torch.isfinite(tri).flatten(-2).all(-1)
        & (n_norm > eps * max_edge_sq)
        & (k.abs() > eps * n_norm * torch.linalg.vector_norm(v0, dim=-1))
    )
    coeffs = torch.cat([c0, c1, c2, n, k.unsqueeze(-1)], -1) * sign.unsqueeze(-1)
    return coeffs, front, usable


def _evaluate(coeffs: Tensor, a: Tensor, b: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Evaluate gathered coefficients ``(P, 13)`` on rays ``(a, b, 1)`` given as ``(P,)`` tensors.

    Returns ``e0, e1, e2, den, k``, each ``(P,)``: oriented triple products, ``n . d`` and ``n . v0``.
    """
    c = coeffs
    e0 = c[:, 0] * a + c[:, 1] * b + c[:, 2]
    e1 = c[:, 3] * a + c[:, 4] * b + c[:, 5]
    e2 = c[:, 6] * a + c[:, 7] * b + c[:, 8]
    den = c[:, 9] * a + c[:, 10] * b + c[:, 11]
    return e0, e1, e2, den, c[:, _K]


def _bounding_boxes(
    tri: Tensor, usable: Tensor, intrinsics: Intrinsics, near: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Inclusive pixel ranges ``x0, x1, y0, y1`` (each ``(B, F)`` int64) of candidate pixels per triangle.

    Triangles with a vertex at or behind the near plane get the whole image; triangles entirely
    behind it, or not ``usable``, get an empty range.
    """
    W, H = intrinsics.width, intrinsics.height
    z = tri[..., 2]
    crosses = (z <= near).any(-1)
    behind = (z <= near).all(-1)
    z_safe = torch.where(crosses.unsqueeze(-1), torch.ones_like(z), z)
    u = tri[..., 0] / z_safe * intrinsics.fx + intrinsics.cx
    v = tri[..., 1] / z_safe * intrinsics.fy + intrinsics.cy
    big = float(max(W, H) + 2)
    u = u.nan_to_num(nan=0.0, posinf=big, neginf=-big).clamp(-big, big)
    v = v.nan_to_num(nan=0.0, posinf=big, neginf=-big).clamp(-big, big)
    x0 = torch.ceil(u.amin(-1) - _BBOX_MARGIN_PX).long().clamp(0, W)
    x1 = torch.floor(u.amax(-1) + _BBOX_MARGIN_PX).long().clamp(-1, W - 1)
    y0 = torch.ceil(v.amin(-1) - _BBOX_MARGIN_PX).long().clamp(0, H)
    y1 = torch.floor(v.amax(-1) + _BBOX_MARGIN_PX).long().clamp(-1, H - 1)
    x0 = torch.where(crosses, torch.zeros_like(x0), x0)
    y0 = torch.where(crosses, torch.zeros_like(y0), y0)
    x1 = torch.where(crosses, torch.full_like(x1, W - 1), x1)
    y1 = torch.where(crosses, torch.full_like(y1, H - 1), y1)
    empty = behind | ~usable
    x1 = torch.where(empty, x0 - 1, x1)
    return x0, x1, y0, y1


def _zbuffer_chunk(
    coeffs: Tensor,
    face_of_bf: Tensor,
    batch_of_bf: Tensor,
    x0: Tensor,
    y0: Tensor,
    width: Tensor,
    counts: Tensor,
    ray_a: Tensor,
    ray_b: Tensor,
    near: float,
    num_pixels: int,
    image_w: int,
    image_hw: int,
) -> tuple[Tensor, Tensor]:
    """Nearest hit per pixel among the candidate pairs of one chunk of (sample, face) rows.

    All arguments indexed by (sample, face) row are ``(R,)`` for the ``R`` rows of the chunk
    (``coeffs`` is ``(R, 13)``). Returns ``zmin (B*H*W,)`` (``+inf`` where nothing hits) and
    ``fmin (B*H*W,)`` int64 (the lowest face index among the hits at ``zmin``; ``F`` sentinel
    where nothing hits is represented by ``int64 max``).
    """
    dtype = coeffs.dtype
    device = coeffs.device
    total = int(counts.sum())
    zmin = torch.full((num_pixels,), float("inf"), dtype=dtype, device=device)
    fmin = torch.full((num_pixels,), torch.iinfo(torch.int64).max, dtype=torch.int64, device=device)
    if total == 0:
        return zmin, fmin
    rows = torch.repeat_interleave(torch.arange(counts.numel(), device=device), counts, output_size=total)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(total, device=device) - starts[rows]
    w = width[rows]
    py = torch.div(local, w, rounding_mode="floor")
    px = local - py * w + x0[rows]
    py = py + y0[rows]
    e0, e1, e2, den, k = _evaluate(coeffs[rows], ray_a[px], ray_b[py])
    depth = k / den
    hit = (e0 >= 0) & (e1 >= 0) & (e2 >= 0) & (den > 0) & (depth > near)
    idx = hit.nonzero().squeeze(-1)
    if idx.numel() == 0:
        return zmin, fmin
    pix = batch_of_bf[rows[idx]] * image_hw + py[idx] * image_w + px[idx]
    depth = depth[idx]
    face = face_of_bf[rows[idx]]
    zmin = zmin.scatter_reduce(0, pix, depth, reduce="amin", include_self=True)
    at_min = depth == zmin[pix]
    fmin = fmin.scatter_reduce(0, pix[at_min], face[at_min], reduce="amin", include_self=True)
    return zmin, fmin


def rasterize(
    verts_cam: Tensor,
    faces: Tensor,
    intrinsics: Intrinsics,
    *,
    cull_backfaces: bool = False,
    near: float = NEAR_PLANE_MM,
) -> Fragments:
    """Rasterize a batch of triangle meshes at the pixel centres of a pinhole camera.

    See the module docstring for the ray-triangle test, the tie rules and which triangles never
    produce fragments. Fully vectorised: no Python loop over samples, pixels or triangles (only over
    a few memory-bounded chunks of candidate pairs).

    Args:
        verts_cam: ``(B, V, 3)`` float vertices in the camera frame (millimetres, ``+z`` forward).
        faces: ``(F, 3)`` int vertex indices shared by the batch, counter-clockwise seen from outside
            (``n = (v1 - v0) x (v2 - v0)`` points out of the surface).
        intrinsics: the camera; the output is ``H x W = intrinsics.height x intrinsics.width``.
        cull_backfaces: drop triangles with ``n . v0 >= 0`` before the depth test.
        near: hits at depth ``Z <= near`` (millimetres) are discarded.

    Returns:
        :class:`Fragments` with ``(B, H, W)`` ``pix_to_face``/``zbuf``/``facing`` and ``(B, H, W, 3)``
        ``bary``. ``bary`` and ``zbuf`` are differentiable with respect to ``verts_cam`` (the choice of
        triangle is not).

    Example:
        >>> cam = Intrinsics.default(32, 24)
        >>> v = torch.tensor([[[-50.0, -50, 100], [50, -50, 100], [0, 50, 100]]])
        >>> frag = rasterize(v, torch.tensor([[0, 2, 1]]), cam)
        >>> frag.pix_to_face.shape, int(frag.facing[0, 12, 16])
        (torch.Size([1, 24, 32]), 1)
    """
    _check_mesh(verts_cam, faces, "verts_cam")
    if not isinstance(intrinsics, Intrinsics):
        raise TypeError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if not near > 0:
        raise ValueError(f"near must be positive (millimetres), got {near}")
    B, F = verts_cam.shape[0], faces.shape[0]
    H, W = intrinsics.height, intrinsics.width
    device, dtype = verts_cam.device, verts_cam.dtype
    num_pixels = B * H * W

    tri = _triangles(verts_cam, faces)  # (B, F, 3, 3)
    coeffs, front, usable = _face_coefficients(tri)
    if cull_backfaces:
        usable = usable & front

    with torch.no_grad():
        x0, x1, y0, y1 = _bounding_boxes(tri.detach(), usable, intrinsics, near)
        width = (x1 - x0 + 1).clamp_min(0).reshape(-1)
        height = (y1 - y0 + 1).clamp_min(0).reshape(-1)
        counts = width * height
        ray_a = (torch.arange(W, device=device, dtype=dtype) - intrinsics.cx) / intrinsics.fx
        ray_b = (torch.arange(H, device=device, dtype=dtype) - intrinsics.cy) / intrinsics.fy
        face_of_bf = torch.arange(F, device=device).repeat(B)
        batch_of_bf = torch.arange(B, device=device).repeat_interleave(F)
        flat_coeffs = coeffs.detach().reshape(B * F, -1)
        x0f, y0f = x0.reshape(-1), y0.reshape(-1)

        # Chunk boundaries over (sample, face) rows so that each chunk has at most ~_MAX_PAIRS_PER_CHUNK pairs.
        ends = torch.cumsum(counts, 0)
        total = int(ends[-1]) if ends.numel() else 0
        n_chunks = max(1, -(-total // _MAX_PAIRS_PER_CHUNK))
        marks = torch.arange(1, n_chunks, device=device) * _MAX_PAIRS_PER_CHUNK
        bounds = [0] + torch.searchsorted(ends, marks, right=True).tolist() + [B * F]

        zbest = torch.full((num_pixels,), float("inf"), dtype=dtype, device=device)
        fbest = torch.full((num_pixels,), torch.iinfo(torch.int64).max, dtype=torch.int64, device=device)
        for lo, hi in zip(bounds[:-1], bounds[1:]):
            if hi <= lo:
                continue
            zc, fc = _zbuffer_chunk(
                flat_coeffs[lo:hi], face_of_bf[lo:hi], batch_of_bf[lo:hi], x0f[lo:hi], y0f[lo:hi],
                width[lo:hi], counts[lo:hi], ray_a, ray_b, near, num_pixels, W, H * W,
            )  # fmt: skip
            take = (zc < zbest) | ((zc == zbest) & (fc < fbest))
            zbest = torch.where(take, zc, zbest)
            fbest = torch.where(take, fc, fbest)

        fg = torch.isfinite(zbest)
        pix_idx = fg.nonzero().squeeze(-1)
        pix_b = torch.div(pix_idx, H * W, rounding_mode="floor")
        pix_yx = pix_idx - pix_b * (H * W)
        pix_y = torch.div(pix_yx, W, rounding_mode="floor")
        pix_x = pix_yx - pix_y * W
        pix_f = fbest[pix_idx]
        pix_to_face = torch.where(fg, fbest, torch.full_like(fbest, -1)).reshape(B, H, W)
        facing = torch.zeros(num_pixels, dtype=torch.int8, device=device)
        is_front = front[pix_b, pix_f]
        facing[pix_idx] = torch.where(is_front, 1, -1).to(torch.int8)

    # Re-evaluate the winners with the same arithmetic, now tracking gradients w.r.t. the vertices.
    e0, e1, e2, den, k = _evaluate(coeffs[pix_b, pix_f], ray_a[pix_x], ray_b[pix_y])
    e = torch.stack([e0, e1, e2], -1)
    bary_fg = e / e.sum(-1, keepdim=True)
    z_fg = k / den
    bary = torch.zeros(num_pixels, 3, dtype=dtype, device=device).index_put((pix_idx,), bary_fg)
    zbuf = torch.full((num_pixels,), float("inf"), dtype=dtype, device=device).index_put((pix_idx,), z_fg)
    return Fragments(
        pix_to_face=pix_to_face,
        bary=bary.reshape(B, H, W, 3),
        zbuf=zbuf.reshape(B, H, W),
        facing=facing.reshape(B, H, W),
    )
