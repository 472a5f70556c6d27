"""Batched, vectorised triangle rasterizer with a z-buffer (see :mod:`torchface.conventions`).

The rasterizer answers, for every pixel centre of every sample, which triangle is nearest along the
pixel's ray, where on that triangle the ray lands (perspective-correct barycentric coordinates) and
at which camera depth. Shading, template sampling and self-occlusion tests (the paper's Section 4,
"facets that a z-buffer hides") consume these :class:`Fragments`. :func:`rasterize_coverage` stops at which
triangle each pixel sees (a :class:`Coverage`) and evaluates the rest only at the pixels its caller asks for.

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

Candidate (triangle, pixel) pairs are enumerated with ``repeat_interleave``/``cumsum`` arithmetic in
two levels: first the image rows of each triangle's projected bounding box, then, per row, the columns
between the row's crossings with the projected edges (a scanline span, widened by a hundredth of a
pixel so rounding never loses a pixel). A triangle with a vertex at or behind the near plane, whose
projection is unbounded, is tested on every pixel of the image. The 3D test above, not the spans,
decides coverage; the spans only keep the candidates close to the covered pixels (for a face-sized
mesh at 640x480, about one candidate per covered pixel). Pairs are evaluated in chunks of bounded
size. Where the triangles' bounding boxes hold few pixels in all (:data:`_BBOX_MAX_PAIRS`, e.g. a face
at 160x120), every pixel of each box is a candidate instead: the same test on the same arithmetic, so the
same fragments, without the cost of working out the spans. The float32 z-buffer packs
``(depth bits, face)`` into one int64 key, so one ``scatter_reduce`` finds the nearest hit and breaks
depth ties; other dtypes take the minimum depth, then the minimum face among each pixel's hits at that
depth.

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
lies entirely at or behind the near plane, or when a vertex is not finite. A triangle with large coordinates
(beyond 2.7e8 mm in float32; beyond 1 mm in float16, where a face-sized triangle overflowed) has its
coefficients computed from its corners scaled by a power of two, so that they cannot overflow: a mesh scaled
by ``s`` gives the same fragments with ``s`` times the depths.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, replace
from collections.abc import Callable, Sequence
from typing import Literal, overload

import torch
from torch import Tensor

from torchface._compiling import host_values, is_compiling, is_transformed
from torchface._scalar import isfinite
from torchface.backend import Backend, use_native
from torchface.conventions import NEAR_PLANE_MM
from torchface.geometry._checks import check_bool, check_number
from torchface.geometry.camera import Intrinsics

#: A caller's memory for the native z-buffer's outputs: ``scratch(name, shape, dtype)`` returns a contiguous CPU tensor
#: of that shape and dtype whose values do not matter (every element is written); a coverage made in it is valid
#: while that memory is (:class:`torchface.tracker.step.StepWorkspace`'s buffers, for the tracker's visibility).
Scratch = Callable[[str, tuple[int, ...], torch.dtype], Tensor]

__all__ = ["Coverage", "Fragments", "rasterize", "rasterize_coverage"]

#: Upper bound on the number of (triangle, pixel) candidate pairs evaluated at once.
_MAX_PAIRS_PER_CHUNK: int = 1 << 19

#: Relative tolerance, in units of the dtype's machine epsilon, for degenerate and edge-on triangles.
_DEGENERATE_EPS_FACTOR: float = 16.0

#: Bounding boxes holding at most this many pixels in all are tested whole (module docstring): at one
#: face-sized mesh at 160x120 (about 6k pixels) that took 0.74 instead of 0.88 ms per call on a 2-core CPU,
#: at about 20k the two ways cost the same.
_BBOX_MAX_PAIRS: int = 1 << 14

#: Margin (pixels) added to projected row spans so rounding never drops a pixel on an edge.
_SPAN_MARGIN_PX: float = 1e-2

#: Projected corners farther than this from the origin (pixels) make a triangle use whole image rows,
#: so that span arithmetic never works with coordinates too large for the dtype's precision.
_MAX_PROJECTED_PX: float = 1e4


@dataclass(frozen=True, eq=False)
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


@dataclass(frozen=True, eq=False)
class Coverage:
    """Which triangle each pixel centre sees (:func:`rasterize_coverage`), with what it takes to evaluate the
    barycentric coordinates and depth of :class:`Fragments` at chosen pixels, by :func:`rasterize`'s arithmetic.

    Attributes:
        pix_to_face: ``(B, H, W)`` int64, ``-1`` for background; facing: ``(B, H, W)`` int8; both as in
            :class:`Fragments` (views into a larger batch for a :meth:`part`).
        coefficients: ``(13, B' F)`` the per-triangle ray-test coefficients of the batch ``B'`` rasterized
            (module docstring; differentiable with respect to the vertices).
        ray_a: ``(W',)`` and ray_b ``(H',)``: the rays' ``x`` and ``y`` per image column and row.
        num_faces: ``F``; batch_offset: the first sample of this coverage in the rasterized batch.
    """

    pix_to_face: Tensor
    facing: Tensor
    coefficients: Tensor
    ray_a: Tensor
    ray_b: Tensor
    num_faces: int
    batch_offset: int = 0

    def part(self, batch: slice, height: int, width: int) -> Coverage:
        """The coverage of samples ``batch`` (a step-1 slice) in the top-left ``height x width`` of the image."""
        start = batch.indices(self.pix_to_face.shape[0])[0]
        return replace(self, pix_to_face=self.pix_to_face[batch, :height, :width],
                       facing=self.facing[batch, :height, :width], batch_offset=self.batch_offset + start)  # fmt: skip

    def barycentrics(self, batch: Tensor, row: Tensor, col: Tensor) -> Tensor:
        """``(N, 3)`` :attr:`Fragments.bary` at the pixels ``(batch, row, col)`` (int64 ``(N,)`` each; zeros
        where nothing is seen), bit for bit :func:`rasterize`'s."""
        face = self.pix_to_face[batch, row, col]
        seen = (face >= 0).nonzero().squeeze(-1)
        bary = self.covered_barycentrics(*(x.index_select(0, seen) for x in (batch, face, row, col)))
        return torch.zeros(face.shape[0], 3, dtype=bary.dtype, device=face.device).index_put((seen,), bary)

    def covered_barycentrics(self, batch: Tensor, face: Tensor, row: Tensor, col: Tensor) -> Tensor:
        """:meth:`barycentrics` at pixels known to be covered, with the triangle ``face`` that covers each (its
        :attr:`pix_to_face`, int64 ``(N,)``): without looking them up."""
        return self._evaluate((batch + self.batch_offset) * self.num_faces + face, row, col, depth=False)[0]

    def covered_depths(self, batch: Tensor, face: Tensor, row: Tensor, col: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`covered_barycentrics` and the depths ``(N,)`` (mm) at those pixels: the values
        :meth:`fragments` gives there (``bary`` and ``zbuf``), bit for bit, evaluated at these pixels alone."""
        return self._evaluate((batch + self.batch_offset) * self.num_faces + face, row, col, depth=True)

    def fragments(self) -> Fragments:
        """The :class:`Fragments` of every pixel (what :func:`rasterize` returns)."""
        B, H, W = self.pix_to_face.shape
        flat = self.pix_to_face.reshape(-1)
        pix_idx = (flat >= 0).nonzero().squeeze(-1)
        pix_b = torch.div(pix_idx, H * W, rounding_mode="floor")
        column = (pix_b + self.batch_offset) * self.num_faces + flat.index_select(0, pix_idx)
        return self._fragments(pix_idx, pix_b, column)

    @overload
    def _evaluate(self, column: Tensor, row: Tensor, col: Tensor, depth: Literal[True]) -> tuple[Tensor, Tensor]: ...
    @overload
    def _evaluate(self, column: Tensor, row: Tensor, col: Tensor, depth: Literal[False]) -> tuple[Tensor, None]: ...
    def _evaluate(self, column: Tensor, row: Tensor, col: Tensor, depth: bool) -> tuple[Tensor, Tensor | None]:
        """The module docstring's arithmetic for triangles ``column`` (of the coefficient table) at pixels
        ``(row, col)`` (int64 ``(M,)`` each, covered by them): barycentric coordinates ``(M, 3)`` and, when
        ``depth``, the depths ``(M,)`` (else None). Only the coefficient rows it needs are gathered."""
        c, n = self.coefficients, 4 if depth else 3  # n: e0, e1, e2 (and n . d for the depth)
        cw = torch.cat([c[0:n], c[4 : 4 + n], c[8 : 8 + n]] + ([c[12:13]] if depth else []))
        cw = cw.index_select(1, column)
        a, b = self.ray_a.index_select(0, col), self.ray_b.index_select(0, row)
        e = cw[0:n] * a + (cw[n : 2 * n] * b + cw[2 * n : 3 * n])
        return (e[0:3] / e[0:3].sum(0)).T, (cw[3 * n] / e[3] if depth else None)

    def _fragments(self, pix_idx: Tensor, pix_b: Tensor, column: Tensor) -> Fragments:
        """Fragments with the covered pixels ``pix_idx`` (flat over ``B H W``), their sample ``pix_b`` and their
        triangles' ``column`` in the coefficient table (int64 ``(M,)`` each)."""
        B, H, W = self.pix_to_face.shape
        num_pixels, dtype, device = B * H * W, self.coefficients.dtype, self.coefficients.device
        pix_yx = pix_idx - pix_b * (H * W)
        row = torch.div(pix_yx, W, rounding_mode="floor")
        # Re-evaluate the winners with the same arithmetic, now tracking gradients w.r.t. the vertices.
        bary_fg, z_fg = self._evaluate(column, row, pix_yx - row * W, depth=True)
        bary = torch.zeros(num_pixels, 3, dtype=dtype, device=device).index_put_((pix_idx,), bary_fg)
        zbuf = torch.full((num_pixels,), float("inf"), dtype=dtype, device=device).index_put_((pix_idx,), z_fg)
        return Fragments(
            pix_to_face=self.pix_to_face.reshape(B, H, W),
            bary=bary.reshape(B, H, W, 3),
            zbuf=zbuf.reshape(B, H, W),
            facing=self.facing.reshape(B, H, W),
        )


def _check_options(intrinsics: object, cull_backfaces: object, near: object) -> tuple[bool, float]:
    """The rasterizers' ``cull_backfaces`` (a bool: ``"no"`` was taken as true, and culled) and ``near`` (a finite
    number > 0 in millimetres: inf passed "> 0", every triangle cut, an empty coverage; a string or None was "'<' not
    supported between instances"), after a ``TypeError`` for ``intrinsics`` that are not an :class:`Intrinsics`."""
    if not isinstance(intrinsics, Intrinsics):
        raise TypeError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if type(near) is not float or not 0 < near < math.inf:  # (the default's: no parse of the interval)
        near = check_number(near, "near", "(0, inf)", unit="millimetres")
    return check_bool(cull_backfaces, "cull_backfaces"), near


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
        raise ValueError(f"faces must be on the device of {name}, {verts.device}, got {faces.device}")
    if faces.numel():
        lo, hi = _index_range(faces)
        if lo < 0 or hi >= verts.shape[1]:
            raise ValueError(f"faces must index the {verts.shape[1]} vertices, got indices in [{lo}, {hi}]")


#: :func:`_index_range`'s results: ``id(faces)`` -> (a weak reference to it, its stamp, min, max).
_INDEX_RANGES: dict[int, tuple[weakref.ref[Tensor], tuple[object, ...], int, int]] = {}


def _index_range(faces: Tensor) -> tuple[int, int]:
    """The smallest and largest index of ``faces``, read on the host once per face tensor and change: a mesh's faces
    are checked at every rasterization, and each read waits for the device (on a GPU, a synchronisation; the tracker
    rasterizes twice per frame). A change is its version counter (any in-place operation, through a view too) or
    its memory, shape or strides (``faces.data = other`` keeps the counter); writes the counter does not see
    (through ``faces.data``'s or ``faces.numpy()``'s values, or another tensor on the same memory) are not."""
    # (an inference tensor has no version counter, a torch.func transform's wrapper no memory; while torch.compile
    # traces, no cache: torchface._scalar)
    trackable = not faces.is_inference() and not is_compiling() and not is_transformed(faces)
    stamp: tuple[object, ...] = ()
    if trackable:
        # taken before the values are read: a change made meanwhile (another thread's) is read at the next call
        stamp = (faces._version, faces.data_ptr(), faces.shape, faces.stride())
        cached = _INDEX_RANGES.get(id(faces))
        if cached is not None and cached[0]() is faces and cached[1] == stamp:
            return cached[2], cached[3]
    lo, hi = (int(v) for v in host_values(torch.stack([faces.min(), faces.max()])))
    if trackable:
        key = id(faces)
        _INDEX_RANGES[key] = (weakref.ref(faces, lambda _: _INDEX_RANGES.pop(key, None)), stamp, lo, hi)
    return lo, hi


def _triangles(verts: Tensor, faces: Tensor) -> Tensor:
    """Corner positions ``(B, F, 3, 3)`` (last-but-one axis: corner 0, 1, 2) of ``faces (F, 3)``."""
    B, F = verts.shape[0], faces.shape[0]
    return verts.index_select(1, faces.reshape(-1).long()).reshape(B, F, 3, 3)


def _large_coordinate(dtype: torch.dtype) -> float:
    """Coordinates (mm) up to which :func:`_face_coefficients`' products cannot overflow: ``2**(e / 4 - 4)`` for a
    dtype whose largest value is about ``2**e`` (float32: ``2**28``, 2.7e8 mm; float64: ``2**252``), the squared
    normal's length being of the fourth power of the coordinates."""
    return 2.0 ** (math.frexp(torch.finfo(dtype).max)[1] // 4 - 4)


def _face_coefficients(tri: Tensor, native: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """Per-triangle ray-test coefficients, oriented so that a hit in front of the camera is positive.

    Args:
        tri: ``(N, 3, 3)`` triangle corners in the camera frame (``N = B F`` sample-face rows).
        native: by the native kernel (``torchface/_native/coverage.h``: the same operations in the same order, so
            the same values), for a caller that has checked it can run (no derivative asked for: no grad, no
            forward-AD tangent); the torch code where a triangle needs the scaling below.

    Returns:
        ``table (13, N)``: for the ray ``d = (a, b, 1)``, function ``j = 0..3`` is
        ``table[j] a + (table[4 + j] b + table[8 + j])``, where functions 0..2 are the triple products
        ``e_i = d . (v_{i+1} x v_{i+2})`` and function 3 is ``n . d``; ``table[12]`` is ``k = n . v0``;
        all multiplied by ``sign(n . v0)``. ``front (N,)`` bool (``n . v0 < 0``); ``usable (N,)`` bool
        (finite, non-degenerate, not edge-on).
    """
    tri = tri.reshape(-1, 3, 3)
    if native:
        done = _native_face_coefficients(tri)
        if done is not None:
            return done
    finite = isfinite(tri).reshape(-1, 9).all(-1)  # (N,)
    # A triangle with a non-finite corner is unusable; its corners are zeroed (torch.where, not a product) so that
    # no NaN reaches the coefficients: a zero gradient times a NaN coefficient would be NaN for the shared vertices.
    tri = torch.where(finite[:, None, None], tri, torch.zeros((), dtype=tri.dtype, device=tri.device))
    # A triangle with a coordinate beyond :func:`_large_coordinate` is scaled by a power of two 2**-s (exact) to coordinates
    # near 1: in float32, |n|**2 overflowed to inf from about 3e8 mm (every triangle at 1e10 mm was dropped as
    # edge-on) and k = n . v0 from about 1e12. The triple products scale by 2**-2s, k by 2**-3s; k is scaled back
    # by 2**s so that the depth k / (n . d) is unscaled. Others (s = 0) are computed exactly as before.
    with torch.no_grad():
        largest = tri.detach().abs().reshape(-1, 9).amax(-1)  # (N,)
        s = torch.where(largest > _large_coordinate(tri.dtype), torch.frexp(largest).exponent, 0).to(tri.dtype)
    scaled = bool(s.any())
    if scaled:
        tri = tri * torch.exp2(-s)[:, None, None]
    corners = tri.permute(1, 2, 0)  # (corner, xyz, N)
    v0, v1, v2 = corners.unbind(0)  # (3, N) each
    e01, e02, e12, e20 = v1 - v0, v2 - v0, v2 - v1, v0 - v2
    # The four cross products c0 = v1 x v2 = v1 x e12, c1 = v2 x v0 = v2 x e20, c2 = v0 x v1 = v0 x e01 (cross
    # products of differences keep precision) and n = e01 x e02, componentwise (a_i+1 b_i+2 - a_i+2 b_i+1) at once.
    a, b = torch.stack([v1, v2, v0, e01]), torch.stack([e12, e20, e01, e02])  # (4, 3, N)
    # Components i + 1 and i + 2 (mod 3) of every vector: rolls of the xyz axis (list indexing cost twice as much).
    a_nxt, a_prv, b_nxt, b_prv = a.roll(-1, 1), a.roll(1, 1), b.roll(-1, 1), b.roll(1, 1)
    cr = a_nxt * b_prv - a_prv * b_nxt  # (4, 3, N): c0, c1, c2, n
    n = cr[3]
    k = (n * v0).sum(0)
    front = k < 0
    sign = torch.where(front, -1.0, 1.0).to(tri.dtype)  # sign(n . v0)

    eps = torch.finfo(tri.dtype).eps * _DEGENERATE_EPS_FACTOR
    n_norm = (n * n).sum(0).sqrt()
    max_edge_sq = torch.stack([e01, e02, e12]).square().sum(1).amax(0)
    usable = (
        finite
        & (n_norm > eps * max_edge_sq)
        & (k.abs() > eps * n_norm * (v0 * v0).sum(0).sqrt())
    )
    if scaled:
        k = k * torch.exp2(s)
    # Rows j + 4 i: function j (c0, c1, c2, n) times component i of the ray; then k.
    return torch.cat([cr.transpose(0, 1).reshape(12, -1), k.unsqueeze(0)]) * sign, front, usable


def _native_face_coefficients(tri: Tensor) -> tuple[Tensor, Tensor, Tensor] | None:
    """:func:`_face_coefficients` of ``tri (N, 3, 3)`` by the native kernel, or None where a triangle has a
    coordinate beyond :func:`_large_coordinate` (the torch code scales it)."""
    from torchface import _native

    N, dtype = tri.shape[0], tri.dtype
    tri = tri.detach().contiguous()
    coeffs = torch.empty(13, N, dtype=dtype)
    front, usable, scaled = (torch.empty(N, dtype=torch.bool) for _ in range(3))
    prob = _native.CoeffProblem(
        N=N, large=_large_coordinate(dtype), eps=torch.finfo(dtype).eps * _DEGENERATE_EPS_FACTOR,
        tri=tri.data_ptr(), coefficients=coeffs.data_ptr(), front=front.data_ptr(), usable=usable.data_ptr(),
        scaled=scaled.data_ptr(),
    )  # fmt: skip
    _native.run("face_coefficients", dtype == torch.float64, prob, N, 1)
    return None if bool(scaled.any()) else (coeffs, front, usable)


def _project_corners(tri: Tensor, intrinsics: Intrinsics, near: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Projected corners ``u, v (B, F, 3)`` (pixels), ``wide (B, F)`` and ``behind (B, F)`` bool.

    ``wide``: a corner is at or behind the near plane, or projects beyond :data:`_MAX_PROJECTED_PX` or
    to a non-finite position; such triangles are tested against whole image rows. ``behind``: all
    corners are at or behind the near plane, so no point of the triangle can be hit.
    """
    z = tri[..., 2]
    at_or_behind = z <= near
    crosses = at_or_behind.any(-1)
    z_safe = torch.where(at_or_behind, torch.ones_like(z), z)
    u = tri[..., 0] / z_safe * intrinsics.fx + intrinsics.cx
    v = tri[..., 1] / z_safe * intrinsics.fy + intrinsics.cy
    # Beyond the limit or not finite (a NaN or infinite coordinate fails the test <=): the same as testing both.
    far = ~((u.abs() <= _MAX_PROJECTED_PX) & (v.abs() <= _MAX_PROJECTED_PX))
    wide = crosses | far.any(-1)
    u = torch.where(wide.unsqueeze(-1), torch.zeros_like(u), u)
    v = torch.where(wide.unsqueeze(-1), torch.zeros_like(v), v)
    return u, v, wide, at_or_behind.all(-1)


def _scan_edges(u: Tensor, v: Tensor) -> Tensor:
    """Scanline description ``(R, 8)`` of projected triangles ``u, v (R, 3)`` (pixels).

    Corners sorted by row, ``top <= mid <= bot``: columns are ``v_top, v_mid, v_bot, u_top, u_mid``
    and the column-per-row slopes of the long edge (top to bottom), the upper short edge (top to mid)
    and the lower short edge (mid to bottom); a horizontal edge gets slope 0 (it is never the edge
    that bounds a row strictly inside the triangle's row range).
    """
    v_sorted, order = v.sort(-1)
    u_sorted = u.gather(-1, order)
    v_top, v_mid, v_bot = v_sorted.unbind(-1)
    u_top, u_mid, u_bot = u_sorted.unbind(-1)

    def slope(du: Tensor, dv: Tensor) -> Tensor:
        flat = dv == 0
        return torch.where(flat, torch.zeros_like(du), du / torch.where(flat, torch.ones_like(dv), dv))

    return torch.stack(
        [
            v_top, v_mid, v_bot, u_top, u_mid,
            slope(u_bot - u_top, v_bot - v_top),
            slope(u_mid - u_top, v_mid - v_top),
            slope(u_bot - u_mid, v_bot - v_mid),
        ],
        -1,
    )  # fmt: skip


def _row_spans(scan: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """Column interval ``[x_min, x_max]`` (float, ``(R,)``) of triangles ``scan (R, 8)`` (see
    :func:`_scan_edges`) on image rows ``y (R,)`` (float).

    The row is clamped into the triangle's row range first, so a row just outside it (within the
    margin) gets the span of the nearest vertex row.
    """
    v_top, v_mid, v_bot, u_top, u_mid, s_long, s_up, s_low = scan.unbind(-1)
    yc = torch.minimum(torch.maximum(y, v_top), v_bot)
    x_long = u_top + (yc - v_top) * s_long
    x_short = torch.where(yc < v_mid, u_top + (yc - v_top) * s_up, u_mid + (yc - v_mid) * s_low)
    return torch.minimum(x_long, x_short), torch.maximum(x_long, x_short)


def _enumerate(counts: Tensor) -> tuple[Tensor, Tensor]:
    """For ``counts (R,)`` int64, the owner ``(N,)`` and rank within the owner ``(N,)`` of ``N = sum(counts)`` items."""
    total = int(counts.sum())
    owner = torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts, output_size=total)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(total, device=counts.device) - starts.index_select(0, owner)
    return owner, rank


def _hits_in_chunk(
    table: Tensor, x_lo: Tensor, widths: Tensor, ray_a: Tensor, near: float
) -> tuple[Tensor, Tensor, Tensor]:
    """Hits among the candidate pixels of a chunk of (sample, face, row) spans.

    Args:
        table: ``(9, R)``: rows 0..3 the ``a`` slopes of ``e0, e1, e2, n . d``, rows 4..7 their values
            at ``a = 0`` on the span's image row, row 8 ``k = n . v0`` (all oriented).
        x_lo: ``(R,)`` int64 first column of each span; ``widths (R,)`` int64 its length.
        ray_a: ``(W,)`` ray ``a`` per column.

    Returns:
        ``span (M,)`` int64 index of the span of each hit, ``col (M,)`` int64 its column and
        ``depth (M,)`` its depth.
    """
    owner, rank = _enumerate(widths)
    col = x_lo.index_select(0, owner) + rank
    a = ray_a.index_select(0, col)
    t = table[:8].index_select(1, owner)
    e = t[0:4] * a + t[4:8]
    inside = (e[0:3].amin(0) >= 0) & (e[3] > 0)
    idx = inside.nonzero().squeeze(-1)
    owner, col = owner.index_select(0, idx), col.index_select(0, idx)
    depth = table[8].index_select(0, owner) / e[3].index_select(0, idx)
    keep = (depth > near).nonzero().squeeze(-1)
    return owner.index_select(0, keep), col.index_select(0, keep), depth.index_select(0, keep)


def _bbox_hits(
    coeffs: Tensor, x_first: Tensor, y_first: Tensor, box_w: Tensor, area: Tensor, ray_a: Tensor, ray_b: Tensor,
    F: int, H: int, W: int, near: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Hits among every pixel of each (sample, face) row's bounding box (few pixels in all).

    Args:
        coeffs: ``(13, N)`` :func:`_face_coefficients` of the ``N = B F`` rows.
        x_first, y_first: ``(N,)`` int64 first column and row of each box (inside the image);
            ``box_w (N,)`` its width and ``area (N,)`` its pixel count (0 for a row not tested).
        ray_a: ``(W,)`` and ``ray_b (H,)`` ray ``a`` per column and ``b`` per row; ``F``, ``H``, ``W`` as in
            :func:`_span_hits`.

    Returns:
        As :func:`_span_hits`, in the same order (sample-face row, then image row, then column).
    """
    owner, rank = _enumerate(area)
    w_o = box_w.index_select(0, owner)
    dy = torch.div(rank, w_o, rounding_mode="floor")
    col = x_first.index_select(0, owner) + (rank - dy * w_o)
    y = y_first.index_select(0, owner) + dy
    c = coeffs.index_select(1, owner)
    # The spans' arithmetic: (c[4:8] b + c[8:12]) is their per-row table, then c[0:4] a is added.
    e = c[0:4] * ray_a.index_select(0, col) + (c[4:8] * ray_b.index_select(0, y) + c[8:12])
    inside = (e[0:3].amin(0) >= 0) & (e[3] > 0)
    idx = inside.nonzero().squeeze(-1)
    depth = c[12].index_select(0, idx) / e[3].index_select(0, idx)
    front = (depth > near).nonzero().squeeze(-1)
    keep = idx.index_select(0, front)
    row = owner.index_select(0, keep)
    b = torch.div(row, F, rounding_mode="floor")
    pix = (b * H + y.index_select(0, keep)) * W + col.index_select(0, keep)
    return pix, depth.index_select(0, front), row - b * F


def _span_hits(
    coeffs: Tensor, u: Tensor, v: Tensor, wide: Tensor, y_first: Tensor, heights: Tensor, ray_a: Tensor,
    ray_b: Tensor, F: int, H: int, W: int, near: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Hits of the (sample, face) rows by scanline spans (module docstring).

    Args:
        coeffs: ``(13, N)`` :func:`_face_coefficients` of the ``N = B F`` rows; ``u, v (N, 3)``, ``wide (N,)``:
            :func:`_project_corners`; ``y_first (N,)`` int64 first image row of each and ``heights (N,)`` its
            number of rows (0 for a row not tested); ``ray_a (W,)``, ``ray_b (H,)`` as in :func:`_bbox_hits`;
            ``F`` faces per sample, ``H x W`` the image.

    Returns:
        ``pix (M,)`` int64 flat pixel index ``(b H + y) W + x``, ``depth (M,)`` and ``face (M,)`` int64 of each hit.
    """
    m, dtype, device = _SPAN_MARGIN_PX, ray_a.dtype, ray_a.device
    zero = torch.zeros((), dtype=torch.int64, device=device)
    face_row, row_rank = _enumerate(heights)  # (R,): owner (b * F + f) and rank of each span
    y = y_first.index_select(0, face_row) + row_rank

    # Level 2: the columns of each row the projected triangle may cover (whole rows if wide).
    scan = _scan_edges(u, v).index_select(0, face_row)
    x_min, x_max = _row_spans(scan, y.to(dtype))
    wide_r = wide.index_select(0, face_row)
    x_lo = torch.where(wide_r, zero, torch.ceil(x_min - m).long()).clamp(0, W)
    x_hi = torch.where(wide_r, zero + W - 1, torch.floor(x_max + m).long()).clamp(-1, W - 1)
    widths = (x_hi - x_lo + 1).clamp_min(0)

    # Per-span coefficient table (9, R): the b-dependent part is folded in once per row.
    c = coeffs.index_select(1, face_row)
    at_row = c[4:8] * ray_b.index_select(0, y) + c[8:12]
    table = torch.cat([c[0:4], at_row, c[12:13]], 0)
    row_batch = torch.div(face_row, F, rounding_mode="floor")
    row_pixel = (row_batch * H + y) * W  # flat index of (b, y, 0)
    row_face = face_row - row_batch * F

    # Candidate pairs, in chunks of at most ~_MAX_PAIRS_PER_CHUNK.
    ends = torch.cumsum(widths, 0)
    total = int(ends[-1]) if ends.numel() else 0
    n_chunks = -(-total // _MAX_PAIRS_PER_CHUNK)
    marks = torch.arange(1, max(n_chunks, 1), device=device) * _MAX_PAIRS_PER_CHUNK
    bounds = [0] + host_values(torch.searchsorted(ends, marks, right=True)) + [widths.numel()]
    hit_pix, hit_depth, hit_face = [], [], []
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        if hi <= lo:
            continue
        span, col, depth = _hits_in_chunk(table[:, lo:hi], x_lo[lo:hi], widths[lo:hi], ray_a, near)
        span = span + lo
        hit_pix.append(row_pixel.index_select(0, span) + col)
        hit_depth.append(depth)
        hit_face.append(row_face.index_select(0, span))
    if not hit_pix:
        hit_pix, hit_depth, hit_face = [zero.reshape(1)[:0]], [ray_a[:0]], [zero.reshape(1)[:0]]
    return torch.cat(hit_pix), torch.cat(hit_depth), torch.cat(hit_face)


def _zbuffer(pix: Tensor, depth: Tensor, face: Tensor, num_pixels: int) -> tuple[Tensor, Tensor]:
    """The nearest hit per pixel, depth ties to the lowest face index.

    Args:
        pix: ``(M,)`` int64 flat pixel index of each hit (at most one hit per pixel and face);
            ``depth (M,)`` positive; ``face (M,)`` int64 in ``[0, 2**31)``.

    Returns:
        ``pix_to_face (num_pixels,)`` int64, ``-1`` where nothing hits, and ``winners (N,)`` int64 the
        indices of the winning hits (one per covered pixel).
    """
    empty = torch.iinfo(torch.int64).max
    best = torch.full((num_pixels,), empty, dtype=torch.int64, device=pix.device)
    if depth.dtype == torch.float32:
        # One pass: positive float32 depths order like their bit patterns, so the int64 key
        # (depth bits, face) orders by depth, then face.
        key = (depth.view(torch.int32).long() << 32) | face
        best.scatter_reduce_(0, pix, key, reduce="amin", include_self=True)
        winners = (best.index_select(0, pix) == key).nonzero().squeeze(-1)
        # Keep the low 32 bits, sign-extended: the face, or -1 for the empty key.
        best.bitwise_and_(0xFFFFFFFF).add_(2**31).bitwise_and_(0xFFFFFFFF).sub_(2**31)
        return best, winners
    zmin = torch.full((num_pixels,), float("inf"), dtype=depth.dtype, device=pix.device)
    zmin.scatter_reduce_(0, pix, depth, reduce="amin", include_self=True)
    at_min = depth == zmin.index_select(0, pix)
    best.scatter_reduce_(0, pix, torch.where(at_min, face, empty), reduce="amin", include_self=True)
    winners = (at_min & (best.index_select(0, pix) == face)).nonzero().squeeze(-1)
    best.masked_fill_(best == empty, -1)
    return best, winners


def _native_cover(
    coeffs: Tensor, front: Tensor, usable: Tensor, tri: Tensor, intrinsics: Intrinsics, ray_a: Tensor, ray_b: Tensor,
    B: int, F: int, near: float, windows: Sequence[tuple[int, int, int]] | None = None, scratch: Scratch | None = None,
) -> tuple[Tensor, Tensor]:
    """``pix_to_face (B H W,)`` int64 and ``facing (B H W,)`` int8 by the native kernel (``_native/coverage.h``):
    every pixel of each ``usable`` ``(sample, face)`` row's box (the corners of ``tri (B F, 3, 3)`` projected
    through ``intrinsics`` as :func:`_project_corners` and :func:`_cover` make it, in the kernel) tested with the
    torch code's arithmetic. ``windows``: per group of consecutive samples, ``(count, height, width)``: those
    samples' images are the top-left ``height x width`` of the ``H x W`` one, each stored whole (C order) after the
    previous sample's: outputs of ``sum(count height width)`` elements (:func:`_cover_windows`). ``scratch``: the
    outputs' and the kernel's depth buffer's memory (None: new tensors)."""
    from torchface import _native

    dtype, H, W = coeffs.dtype, intrinsics.height, intrinsics.width
    # (bool tensors are bytes 0 / 1: the kernel reads them as uint8 without a conversion)
    args = [x.contiguous() for x in (coeffs, ray_a, ray_b, tri, usable, front)]
    sizes = starts = None
    total = B * H * W
    if windows is not None:
        hw = [(h, w) for n, h, w in windows for _ in range(n)]
        sizes = torch.tensor(hw, dtype=torch.int64).reshape(-1, 2)
        areas = sizes.prod(-1)
        starts = torch.cumsum(areas, 0) - areas
        total = int(areas.sum())
    if scratch is None:
        pix_to_face = torch.empty(total, dtype=torch.int64)
        facing = torch.empty(total, dtype=torch.int8)
        depth = torch.empty(total, dtype=dtype)
    else:  # (at 128 samples of 160x120 pixels, 30 MB that glibc otherwise gave back and faulted in again each step)
        pix_to_face = scratch("pix_to_face", (total,), torch.int64)
        facing = scratch("facing", (total,), torch.int8)
        depth = scratch("depth", (total,), dtype)
    names = ("coefficients", "ray_a", "ray_b", "tri", "usable", "front")
    prob = _native.CoverProblem(B=B, F=F, H=H, W=W, near=float(near), fx=float(intrinsics.fx),
                                fy=float(intrinsics.fy), cx=float(intrinsics.cx), cy=float(intrinsics.cy),
                                margin=_SPAN_MARGIN_PX, max_projected=_MAX_PROJECTED_PX,
                                **{n: x.data_ptr() for n, x in zip(names, args)},
                                pix_to_face=pix_to_face.data_ptr(), facing=facing.data_ptr(), depth=depth.data_ptr(),
                                sizes=None if sizes is None else sizes.data_ptr(),
                                starts=None if starts is None else starts.data_ptr())  # fmt: skip
    _native.run("coverage", dtype == torch.float64, prob, B, torch.get_num_threads())
    return pix_to_face, facing


@overload
def _cover(
    verts_cam: Tensor, faces: Tensor, intrinsics: Intrinsics, cull_backfaces: bool, near: float,
    backend: Backend = ..., pixels: Literal[True] = ..., windows: None = ..., scratch: None = ...,
) -> tuple[Coverage, tuple[Tensor, Tensor, Tensor]]: ...
@overload
def _cover(
    verts_cam: Tensor, faces: Tensor, intrinsics: Intrinsics, cull_backfaces: bool, near: float,
    backend: Backend = ..., *, pixels: Literal[False], windows: None = ..., scratch: Scratch | None = ...,
) -> tuple[Coverage, None]: ...
@overload
def _cover(
    verts_cam: Tensor, faces: Tensor, intrinsics: Intrinsics, cull_backfaces: bool, near: float,
    backend: Backend = ..., *, pixels: Literal[False], windows: Sequence[tuple[int, int, int]],
    scratch: None = ...,
) -> tuple[list[Coverage], None]: ...
def _cover(
    verts_cam: Tensor, faces: Tensor, intrinsics: Intrinsics, cull_backfaces: bool, near: float,
    backend: Backend = Backend.AUTO, pixels: bool = True, windows: Sequence[tuple[int, int, int]] | None = None,
    scratch: Scratch | None = None,
) -> tuple[Coverage | list[Coverage], tuple[Tensor, Tensor, Tensor] | None]:
    """:func:`rasterize_coverage`, and its covered pixels as found: flat index ``(M,)`` over ``B H W``, sample
    ``(M,)`` and column of their triangle in the coefficient table ``(M,)`` (int64 each); None without ``pixels``
    where the native kernel found the coverage (listing them is a pass over every pixel). With ``windows``
    (without ``pixels``): :func:`_cover_windows`' list of coverages instead. ``scratch`` (without ``pixels`` and
    ``windows``): the native kernel's memory (:data:`Scratch`; the torch code makes new tensors)."""
    _check_mesh(verts_cam, faces, "verts_cam")
    cull_backfaces, near = _check_options(intrinsics, cull_backfaces, near)
    B, F = verts_cam.shape[0], faces.shape[0]
    H, W = intrinsics.height, intrinsics.width
    device, dtype = verts_cam.device, verts_cam.dtype
    num_pixels = B * H * W
    if F >= 2**31:
        raise ValueError(f"at most 2**31 - 1 faces are supported, got {F}")

    tri = _triangles(verts_cam, faces)  # (B, F, 3, 3)
    # The coefficients natively where no derivative is asked for (they are differentiable in the torch code): not
    # for vertices that require grad, nor for a forward-AD dual tensor (its detached copy, which the z-buffer's
    # test below looks at, has no tangent: the native table dropped it, and every zbuf/bary tangent was None).
    # Backend.NATIVE does not refuse such vertices here: its z-buffer runs on them.
    native = use_native(Backend.AUTO if backend is Backend.NATIVE else backend, (verts_cam,), "rasterizer")
    coeffs, front, usable = _face_coefficients(tri, native)  # (13, B F), (B F,), (B F,)
    if cull_backfaces:
        usable = usable & front
    ray_a = (torch.arange(W, device=device, dtype=dtype) - intrinsics.cx) / intrinsics.fx
    ray_b = (torch.arange(H, device=device, dtype=dtype) - intrinsics.cy) / intrinsics.fy

    with torch.no_grad():
        if use_native(backend, (verts_cam.detach(),), "rasterizer"):  # the same coverage, bit for bit (tests)
            # Each row's box made in the kernel: the ~70 small torch operations below cost 3-7% of a one-stream step.
            pix_to_face, facing = _native_cover(
                coeffs.detach(), front, usable, tri.detach(), intrinsics, ray_a, ray_b, B, F, near, windows,
                None if pixels or windows is not None else scratch,
            )  # fmt: skip
            if windows is not None:  # each group's samples stored whole at their window's size, one after another
                parts, start, at = [], 0, 0
                for n, h, w in windows:
                    block = slice(at, at + n * h * w)
                    parts.append(Coverage(pix_to_face[block].view(n, h, w), facing[block].view(n, h, w), coeffs,
                                          ray_a, ray_b, F, start))  # fmt: skip
                    start, at = start + n, at + n * h * w
                return parts, None
            coverage = Coverage(pix_to_face.reshape(B, H, W), facing.reshape(B, H, W), coeffs, ray_a, ray_b, F)
            if not pixels:
                return coverage, None
            pix_idx = (pix_to_face >= 0).nonzero().squeeze(-1)
            pix_b = torch.div(pix_idx, H * W, rounding_mode="floor")
            pix_bf = pix_b * F + pix_to_face.index_select(0, pix_idx)
            return coverage, (pix_idx, pix_b, pix_bf)
        # Level 1: the image rows each (sample, face) may cover.
        u, v, wide, behind = _project_corners(tri.detach().reshape(-1, 3, 3), intrinsics, near)
        m = _SPAN_MARGIN_PX
        zero = torch.zeros((), dtype=torch.int64, device=device)
        x_first = torch.where(wide, zero, torch.ceil(u.amin(-1) - m).long())
        x_last = torch.where(wide, zero + W - 1, torch.floor(u.amax(-1) + m).long())
        y_first = torch.where(wide, zero, torch.ceil(v.amin(-1) - m).long()).clamp(0, H)
        y_last = torch.where(wide, zero + H - 1, torch.floor(v.amax(-1) + m).long()).clamp(-1, H - 1)
        skip = behind | ~usable | (x_first > W - 1) | (x_last < 0)
        heights = torch.where(skip, zero, (y_last - y_first + 1).clamp_min(0))
        box_first = x_first.clamp(0, W)
        box_w = (x_last.clamp(-1, W - 1) - box_first + 1).clamp_min(0)
        area = heights * box_w
        if int(area.sum()) <= _BBOX_MAX_PAIRS:  # few candidates: whole boxes (module docstring)
            hit_pix, hit_depth, hit_face = _bbox_hits(
                coeffs.detach(), box_first, y_first, box_w, area, ray_a, ray_b, F, H, W, near
            )
        else:
            hit_pix, hit_depth, hit_face = _span_hits(
                coeffs.detach(), u, v, wide, y_first, heights, ray_a, ray_b, F, H, W, near
            )
        pix_to_face, winners = _zbuffer(hit_pix, hit_depth, hit_face, num_pixels)

        pix_idx = hit_pix.index_select(0, winners)
        pix_f = hit_face.index_select(0, winners)
        pix_b = torch.div(pix_idx, H * W, rounding_mode="floor")
        pix_bf = pix_b * F + pix_f
        is_front = front.index_select(0, pix_bf)
        facing = torch.zeros(num_pixels, dtype=torch.int8, device=device)
        facing.index_put_((pix_idx,), torch.where(is_front, 1, -1).to(torch.int8))
    coverage = Coverage(pix_to_face.reshape(B, H, W), facing.reshape(B, H, W), coeffs, ray_a, ray_b, F)
    if windows is not None:
        return _parts(coverage, windows), None
    return coverage, (pix_idx, pix_b, pix_bf)


def _parts(coverage: Coverage, windows: Sequence[tuple[int, int, int]]) -> list[Coverage]:
    """``coverage``'s :meth:`Coverage.part` per group of ``windows`` (``(count, height, width)``, in order)."""
    parts, start = [], 0
    for n, h, w in windows:
        parts.append(coverage.part(slice(start, start + n), h, w))
        start += n
    return parts


def _cover_windows(
    verts_cam: Tensor, faces: Tensor, canvas: Intrinsics, windows: Sequence[tuple[int, int, int]], *,
    cull_backfaces: bool = False, near: float = NEAR_PLANE_MM, backend: Backend = Backend.AUTO,
) -> list[Coverage]:
    """:func:`rasterize_coverage` of ``verts_cam (B, V, 3)`` through ``canvas`` split into groups of consecutive
    samples, ``windows`` ``(count, height, width)`` each (counts summing to ``B``, sizes within the canvas): per
    group, the coverage of its samples in the top-left ``height x width`` of the image, what
    ``rasterize_coverage(...).part(...)`` gives, the same triangles at every pixel (the groups' ``batch_offset``
    place them in the shared coefficient table). The native kernel tests and stores each sample's window alone,
    each group's tensors contiguous, instead of every sample's whole canvas (a pyramid's coarse levels on its
    finest level's canvas: 2.3 times the pixels to clear and keep)."""
    if sum(n for n, _, _ in windows) != verts_cam.shape[0] or any(
        not (0 <= h <= canvas.height and 0 <= w <= canvas.width) for _, h, w in windows
    ):
        raise ValueError(f"windows must split the {verts_cam.shape[0]} samples into groups within the "
                         f"{canvas.height}x{canvas.width} canvas, got {list(windows)}")  # fmt: skip
    return _cover(verts_cam, faces, canvas, cull_backfaces, near, backend, pixels=False, windows=windows)[0]


def rasterize(
    verts_cam: Tensor,
    faces: Tensor,
    intrinsics: Intrinsics,
    *,
    cull_backfaces: bool = False,
    near: float = NEAR_PLANE_MM,
    backend: Backend = Backend.AUTO,
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
        backend: :class:`~torchface.backend.Backend` of the z-buffer (which triangle each pixel sees) and, where
            no derivative is asked for (no grad, no forward-AD tangent), of the triangles' ray-test coefficients:
            the native kernels test every pixel of each triangle's bounding box and compute the coefficients with
            the same arithmetic, so the fragments are the same bit for bit; the barycentric coordinates and depths
            are then evaluated (differentiably) by the torch code either way.

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
    coverage, (pix_idx, pix_b, pix_bf) = _cover(verts_cam, faces, intrinsics, cull_backfaces, near, backend)
    return coverage._fragments(pix_idx, pix_b, pix_bf)


def rasterize_coverage(
    verts_cam: Tensor,
    faces: Tensor,
    intrinsics: Intrinsics,
    *,
    cull_backfaces: bool = False,
    near: float = NEAR_PLANE_MM,
    backend: Backend = Backend.AUTO,
) -> Coverage:
    """:func:`rasterize` without its per-pixel barycentric coordinates and depths: which triangle each pixel
    centre sees, and the means to evaluate the rest at the pixels a caller picks (:meth:`Coverage.barycentrics`,
    :meth:`Coverage.fragments`), with the same arithmetic, so the same values. For callers that need them at a
    few of the covered pixels (a template's selected points): over a face-sized window, evaluating every covered
    pixel was about a third of a rasterization's time.

    Arguments, checks and errors as :func:`rasterize`.

    Example:
        >>> cam = Intrinsics.default(32, 24)
        >>> v = torch.tensor([[[-50.0, -50, 100], [50, -50, 100], [0, 50, 100]]])
        >>> cov = rasterize_coverage(v, torch.tensor([[0, 2, 1]]), cam)
        >>> full = rasterize(v, torch.tensor([[0, 2, 1]]), cam)
        >>> at = torch.tensor([[0, 12, 16], [0, 0, 0]])  # (batch, row, column); the second is background
        >>> torch.equal(cov.barycentrics(*at.T), full.bary[at[:, 0], at[:, 1], at[:, 2]])
        True
    """
    return _cover(verts_cam, faces, intrinsics, cull_backfaces, near, backend, pixels=False)[0]
