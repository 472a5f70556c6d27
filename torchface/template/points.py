"""Template points: visible, informative surface points of the fitted model with their appearance.

Each template point lies on one triangle with fixed barycentric coordinates, so its 3D position and its
expression basis are barycentric interpolations of the triangle's vertices and of the animation units at
those vertices (paper Eq. 3-9): ``X(alpha) = X_0 + sum_j alpha_j B_j`` for all points at once, with no
per-iteration triangle search.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import Tensor

from torchface.appearance.sampling import image_with_gradients
from torchface.backend import Backend, use_native
from torchface.geometry._checks import check_int
from torchface.geometry.camera import Intrinsics
from torchface.geometry.transforms import transform_points
from torchface.model.face_model import FaceModel
from torchface.rendering.rasterizer import Coverage, _cover_windows
from torchface.rendering.visibility import vertex_normals


@dataclass(frozen=True, eq=False)
class Template:
    """Template points of one pyramid level, ``N`` slots per sample (unused slots have ``valid`` False).

    Attributes:
        face_index: ``(B, N)`` int64 triangle of each point.
        bary: ``(B, N, 3)`` barycentric coordinates in that triangle.
        points: ``(B, N, 3)`` head-frame position (mm) with the sample's shape units and zero expression.
        basis: ``(B, N, 3, A)`` expression basis: column ``j`` is the point's displacement per unit of animation
            unit ``j`` (laid out for ``basis @ alpha``).
        normals: ``(B, N, 3)`` unit head-frame normals (zero expression).
        intensity: ``(B, N)`` gray value of the reference frame at the point (``T`` in the paper).
        valid: ``(B, N)`` bool.
    """

    face_index: Tensor
    bary: Tensor
    points: Tensor
    basis: Tensor
    normals: Tensor
    intensity: Tensor
    valid: Tensor

    @property
    def num_points(self) -> Tensor:
        """``(B,)`` number of valid points per sample."""
        return self.valid.sum(-1)

    def select(self, index: Tensor) -> "Template":
        """The templates of samples ``index`` (a ``(B',)`` int64 or bool tensor)."""
        return Template(*(getattr(self, f)[index] for f in self.__dataclass_fields__))

    @property
    def point_last(self) -> tuple[Tensor, Tensor, Tensor]:
        """Contiguous point-last copies ``points (B, 3, N)``, ``normals (B, 3, N)`` and ``basis (B, A, 3, N)``, the
        layout of the fast solver (:mod:`torchface.tracker.fast`). Made on first use and kept with the template (a
        template serves many frames), as normal tensors (usable in and out of inference mode); a copy that carries
        a gradient (a template tensor requires grad) is made again on each use instead."""
        cached = self.__dict__.get("_point_last")
        if cached is None:
            with torch.inference_mode(False):
                cached = (
                    self.points.transpose(1, 2).contiguous(), self.normals.transpose(1, 2).contiguous(),
                    self.basis.permute(0, 3, 2, 1).contiguous(),
                )
            if not any(t.requires_grad for t in cached):
                object.__setattr__(self, "_point_last", cached)  # not a field: equality, copies and repr ignore it
        return cached


@dataclass(frozen=True, eq=False)
class TemplatePixels:
    """The compact form of a :class:`Template`: where its points lie and what they saw (what a mosaic stores).

    Attributes:
        face_index: ``(B, N)`` int64; bary: ``(B, N, 3)``; intensity: ``(B, N)``; valid: ``(B, N)`` bool; as in
            :class:`Template`, whose other fields :func:`template_at` derives from these and the person's shape.
    """

    face_index: Tensor
    bary: Tensor
    intensity: Tensor
    valid: Tensor


def gather_face_attributes(attributes: Tensor, faces: Tensor, face_index: Tensor, bary: Tensor, *, batched: bool) -> Tensor:
    """Barycentric interpolation of per-vertex attributes at points on triangles.

    Args:
        attributes: ``(B, V, *D)`` when ``batched`` else ``(V, *D)`` (shared by the batch) per-vertex values.
        faces: ``(F, 3)`` int64.
        face_index: ``(B, N)`` int64, a triangle per point (clamped to ``>= 0``: mask invalid points yourself).
        bary: ``(B, N, 3)``.

    Returns:
        ``(B, N, *D)``: ``sum_i bary_i * attributes[faces[face_index, i]]``.
    """
    B, N = face_index.shape
    corner = faces[face_index.clamp_min(0)]  # (B, N, 3)
    if batched:
        extra = attributes.shape[2:]
        flat = attributes.flatten(2) if attributes.dim() > 2 else attributes.unsqueeze(-1)  # (B = 0 too)
        idx = corner.reshape(B, N * 3, 1).expand(-1, -1, flat.shape[-1])
        vals = torch.gather(flat, 1, idx).reshape(B, N, 3, *extra)
    else:  # index_select of the flattened rows: several times faster than attributes[corner]
        extra = attributes.shape[1:]
        vals = attributes.reshape(attributes.shape[0], -1).index_select(0, corner.reshape(-1)).reshape(B, N, 3, *extra)
    w = bary.reshape(B, N, 3, *([1] * (vals.dim() - 3))).to(vals.dtype)
    return (vals * w).sum(2)


def _erode(mask: Tensor, radius: int) -> Tensor:
    """Binary erosion of ``(B, H, W)`` bool masks by a ``(2 r + 1)^2`` square (outside the image counts as set).

    Separable: a pixel stays where its ``r`` neighbours either side along the row, then along the column, are set,
    each a logical and of shifted slices (a 196x328 window: 26 against 530 microseconds for the max-pooling of
    the inverted mask as floats, the same result)."""
    if radius <= 0:
        return mask
    rows = mask.clone()
    for d in range(1, radius + 1):
        rows[..., :, d:] &= mask[..., :, :-d]
        rows[..., :, :-d] &= mask[..., :, d:]
    out = rows.clone()
    for d in range(1, radius + 1):
        out[..., d:, :] &= rows[..., :-d, :]
        out[..., :-d, :] &= rows[..., d:, :]
    return out


def _selection_keys(height: int, width: int, device: torch.device, seed: int = 0) -> Tensor:
    """Deterministic pseudo-random keys in ``[0, 1)`` per pixel, the same for every sample and call.

    Used to pick a uniform subset of the candidate pixels; being a function of the pixel alone, a stream
    gets the same template whether it is tracked alone or in a batch. ``seed`` draws another set of keys
    (:attr:`~torchface.tracker.TrackerConfig.selection_seed`; 0 the default draw).
    """
    return _cpu_selection_keys(height, width, seed).to(device)


@functools.lru_cache(maxsize=16)
def _cpu_selection_keys(height: int, width: int, seed: int = 0) -> Tensor:
    """:func:`_selection_keys` on the CPU, drawn once per image size and seed (callers must not modify it)."""
    gen = torch.Generator(device="cpu").manual_seed(height * 100003 + width + seed)
    # float32 whatever torch's default dtype: under torch.set_default_dtype(torch.float64) the same seed drew other
    # keys, another template subset, and a float32 tracker's poses moved (0.24 degrees within 10 GRID frames)
    return torch.rand(height * width, generator=gen, dtype=torch.float32)


def select_template_pixels(
    model: FaceModel,
    shape_coeffs: Tensor,
    anim_coeffs: Tensor,
    rotation: Tensor,
    translation: Tensor,
    gray: Tensor,
    intrinsics: Intrinsics,
    *,
    max_points: int,
    gradient_threshold: float,
    min_facing_cos: float = 0.15,
    erode_pixels: int = 1,
    expression_priority: float = 0.0,
    expression_quota: int = 0,
    offsets: Tensor | None = None,
    seed: int = 0,
    backend: Backend = Backend.AUTO,
) -> TemplatePixels:
    """The template pixels of a frame whose model parameters are known (paper Section 2-3 and 4).

    Rasterizes the posed model, keeps pixels that see a front-facing triangle at an angle steeper than
    ``acos(min_facing_cos)`` (and not on the silhouette, after eroding the face mask by ``erode_pixels``),
    keeps those whose gradient magnitude is at least ``gradient_threshold`` (informative points, Section 4)
    and picks up to ``max_points`` of them uniformly. Each pixel centre becomes a template point on its
    triangle, with its intensity read from ``gray``.

    Args:
        model: the face model.
        shape_coeffs: ``(B, S)``; anim_coeffs: ``(B, A)`` the frame's expression.
        rotation: ``(B, 3, 3)`` and translation ``(B, 3)`` the frame's pose (head -> camera, mm).
        gray: ``(B, 1, H, W)`` the frame, gray in ``[0, 1]``, at ``intrinsics``' size (or windows of it, see
            ``offsets``).
        intrinsics: camera of the frame.
        max_points: N, slots per sample.
        gradient_threshold: minimum ``|grad I|`` (intensity per pixel) of a kept point; 0 keeps all.
        expression_priority: when positive, candidate pixels that an animation unit moves by at least a pixel
            per unit coefficient are picked before the others (their selection key is raised by this much).
        expression_quota: for each animation unit, up to this many candidate pixels that the unit moves by at
            least a pixel per unit coefficient are picked before all others (those with the highest selection
            keys among them). A unit acting on a small region (the eyelids) then gets points; one acting on a
            large region already has that many among the uniform draw, so the draw barely changes. 0: off.
        offsets: ``(B, 2)`` int64 ``(x0, y0)``, or None. When given, ``gray`` ``(B, 1, h, w)`` is per sample the
            window of the camera's ``intrinsics.height x intrinsics.width`` image whose top-left pixel is at
            ``offsets``: only the window is rasterized and searched (faster), and the template equals the one
            the whole image would give provided the window holds the face with a pixel to spare (the pixel
            selection keys are those of the whole image). None: ``gray`` is the whole image.
        seed: which draw of the pixels' selection keys picks the uniform subset (0: the default draw; another
            seed picks another subset of the same candidates).
        backend: :class:`~torchface.backend.Backend` of the rasterization and the candidates' tests (the same
            selection either way: :func:`select_pixels_posed`).

    Returns:
        :class:`TemplatePixels` with ``N = max_points`` slots (:func:`build_template` completes it).

    Raises:
        TypeError: ``gray`` is not a tensor. ValueError: ``gray`` is not float, or a shape, window or count is wrong.
    """
    full_h, full_w = intrinsics.height, intrinsics.width
    seed = check_int(seed, "seed", 0)
    # (a numpy array was "'numpy.ndarray' object has no attribute 'dim'", uint8 gray "result type Float can't be
    # cast to the desired output type Byte")
    if not isinstance(gray, Tensor):
        raise TypeError(f"gray must be a torch.Tensor (B, 1, H, W) float in [0, 1], got {type(gray).__name__}")
    if not gray.is_floating_point():
        hint = " (uint8: pass gray.float() / 255)" if gray.dtype == torch.uint8 else ""
        raise ValueError(f"gray must be (B, 1, H, W) float in [0, 1], got {gray.dtype}{hint}")
    if offsets is None:
        if gray.dim() != 4 or gray.shape[1] != 1 or tuple(gray.shape[-2:]) != intrinsics.size:
            raise ValueError(f"gray must be (B, 1, {full_h}, {full_w}), got {tuple(gray.shape)}")
    else:
        if gray.dim() != 4 or gray.shape[1] != 1 or gray.shape[-2] > full_h or gray.shape[-1] > full_w:
            raise ValueError(f"gray must be (B, 1, h <= {full_h}, w <= {full_w}) windows, got {tuple(gray.shape)}")
        if offsets.shape != (gray.shape[0], 2) or offsets.dtype != torch.int64:
            raise ValueError(f"offsets must be ({gray.shape[0]}, 2) int64, got {tuple(offsets.shape)} {offsets.dtype}")
        inside = (offsets >= 0).all() & (offsets[:, 0] + gray.shape[-1] <= full_w).all()
        if not bool(inside & (offsets[:, 1] + gray.shape[-2] <= full_h).all()):
            raise ValueError(f"every window must lie inside the {full_w}x{full_h} image, got offsets {offsets.tolist()}")
    B, _, H, W = gray.shape
    if not 0 < max_points <= H * W:
        raise ValueError(f"max_points must be in [1, {H * W}] (the pixels of the image), got {max_points}")
    return select_pixels_posed(
        model, posed_mesh(model, shape_coeffs, anim_coeffs, rotation, translation), gray, intrinsics, offsets,
        max_points=max_points, gradient_threshold=gradient_threshold, min_facing_cos=min_facing_cos,
        erode_pixels=erode_pixels, expression_priority=expression_priority, expression_quota=expression_quota,
        seed=seed, backend=backend,
    )  # fmt: skip


@dataclass(frozen=True, eq=False)
class PosedMesh:
    """The model at one expression and pose, as the pixel selection needs it: one per estimate, shared by the
    levels of a pyramid (:func:`select_pixels_posed`).

    Attributes:
        verts_model: ``(B, V, 3)`` head-frame vertices (shape and expression applied, mm).
        verts_cam: ``(B, V, 3)`` the same in the camera frame.
        normals_cam: ``(B, V, 3)`` unit vertex normals in the camera frame.
    """

    verts_model: Tensor
    verts_cam: Tensor
    normals_cam: Tensor


def posed_mesh(model: FaceModel, shape_coeffs: Tensor, anim_coeffs: Tensor, rotation: Tensor, translation: Tensor
               ) -> PosedMesh:
    """:class:`PosedMesh` of ``shape_coeffs (B, S)``, ``anim_coeffs (B, A)``, ``rotation (B, 3, 3)`` and
    ``translation (B, 3)`` (head -> camera, mm)."""
    verts_model = model.deform(shape_coeffs, anim_coeffs)
    verts_cam = transform_points(rotation, translation, verts_model)
    normals_cam = torch.einsum("bij,bvj->bvi", rotation, vertex_normals(verts_model, model.faces))
    return PosedMesh(verts_model, verts_cam, normals_cam)


def _window_verts(verts_cam: Tensor, intrinsics: Intrinsics, offsets: Tensor | None, canvas: Intrinsics) -> Tensor:
    """``verts_cam (B, V, 3)`` moved so that ``canvas``' projection of them is ``intrinsics``' shifted by
    ``-offsets (B, 2)`` (each sample's window; None: no shift): ``X' = (fx / fx_c) X + ((cx - x0 - cx_c) / fx_c) Z``,
    and the same for ``Y``. A linear map with positive determinant that keeps depths: barycentric coordinates,
    depth order and triangle orientation are those of the window seen through ``intrinsics``."""
    B = verts_cam.shape[0]
    off = verts_cam.new_zeros(B, 2) if offsets is None else offsets.to(verts_cam.dtype)
    focal = verts_cam.new_tensor([canvas.fx, canvas.fy])
    scale = verts_cam.new_tensor([intrinsics.fx / canvas.fx, intrinsics.fy / canvas.fy, 1.0])
    shear = (verts_cam.new_tensor([intrinsics.cx - canvas.cx, intrinsics.cy - canvas.cy]) - off) / focal  # (B, 2)
    shear = torch.cat([shear, shear.new_zeros(B, 1)], -1)
    return verts_cam * scale + verts_cam[..., 2:3] * shear.unsqueeze(1)


def strided_window(camera: Intrinsics, offsets: Tensor | None, stride: int) -> tuple[Intrinsics, Tensor | None]:
    """The camera and ``(B, 2)`` offsets whose pixel ``(i, j)`` is pixel ``(stride i, stride j)`` of the windows
    of ``camera`` at ``offsets`` (int64 ``(x0, y0)``, None: the whole image): what :func:`rasterize_windows`
    takes to rasterize :func:`select_pixels_posed`'s grid of ``stride``. The offsets may become fractional
    (float). ``stride`` 1 returns the arguments."""
    if stride == 1:
        return camera, offsets
    s = float(stride)
    cam = Intrinsics(-(-camera.width // stride), -(-camera.height // stride), camera.fx / s, camera.fy / s,
                     camera.cx / s, camera.cy / s)  # fmt: skip
    return cam, None if offsets is None else offsets.to(torch.float64) / s


def rasterize_windows(
    model: FaceModel, verts_cam: Tensor, cameras: list[Intrinsics], offsets: list[Tensor | None],
    backend: Backend = Backend.AUTO,
) -> list[Coverage]:
    """Back-face-culled :func:`~torchface.rendering.rasterizer.rasterize_coverage` of the same posed meshes in
    several windows (the levels of a pyramid), in one call.

    Args:
        verts_cam: ``(B, V, 3)`` camera-frame vertices (mm).
        cameras: per window, the camera of its image; its ``height x width`` is the window's size.
        offsets: per window, ``(B, 2)`` ``(x0, y0)`` of each sample's window in that camera's image (int64, or
            float for a :func:`strided_window`), or None (the whole image).
        backend: of the z-buffer (:func:`~torchface.rendering.rasterizer.rasterize_coverage`).

    Returns:
        Per window, the :class:`~torchface.rendering.rasterizer.Coverage` ``rasterize_coverage`` gives for it (up
        to rounding; its barycentric coordinates and depths are evaluated where the caller asks): the windows are
        stacked along the batch on a canvas of the largest size, each through :func:`_window_verts` (one call's
        fixed cost instead of one per level: an entry's coarse levels cost nearly as much as its finest when
        rasterized alone); the native z-buffer tests and stores each window at its own size
        (:func:`~torchface.rendering.rasterizer._cover_windows`).
    """
    first = cameras[0]  # the canvas projects as the first camera (its window's vertices are only shifted)
    canvas = Intrinsics(max(c.width for c in cameras), max(c.height for c in cameras), first.fx, first.fy, first.cx,
                        first.cy)  # fmt: skip
    stacked = torch.cat([_window_verts(verts_cam, c, o, canvas) for c, o in zip(cameras, offsets)])
    B = verts_cam.shape[0]
    return _cover_windows(stacked, model.faces, canvas, [(B, c.height, c.width) for c in cameras],
                          cull_backfaces=True, backend=backend)  # fmt: skip


#: :func:`select_pixels_posed` tests the facing of every point of a triangle only where the triangle's lower
#: bound on that cosine is within this of the threshold (far more than the cosine's rounding error).
_FACING_MARGIN = 0.01


def select_pixels_posed(
    model: FaceModel,
    posed: PosedMesh,
    gray: Tensor,
    intrinsics: Intrinsics,
    offsets: Tensor | None,
    *,
    max_points: int,
    gradient_threshold: float,
    min_facing_cos: float = 0.15,
    erode_pixels: int = 1,
    expression_priority: float = 0.0,
    expression_quota: int = 0,
    frags: Coverage | None = None,
    stride: int = 1,
    seed: int = 0,
    backend: Backend = Backend.AUTO,
) -> TemplatePixels:
    """:func:`select_template_pixels` of a mesh already posed (:func:`posed_mesh`): the same result, with the
    posing done once for the levels of a pyramid. The arguments are not checked again (callers inside the
    package; :func:`select_template_pixels` documents and checks them). ``frags``: the back-face-culled
    coverage of ``gray``'s windows when the caller has it (:func:`rasterize_windows`), else rasterized here.

    ``stride``: the candidates are only the window's pixels on every ``stride``-th row and column (rows and
    columns ``0, stride, ...`` of ``gray``), with the gradients and selection keys those pixels have in the
    whole window; ``frags`` is then the rasterization of that grid (:func:`strided_window` of the window's
    camera and offsets) and the mask erosion counts in grid steps. 1: every pixel. ``seed``: the selection keys'
    draw (:func:`select_template_pixels`). ``backend``: the candidates' tests and scores by the native kernel
    (``torchface/_native/select_pixels.h``, the same tests with the same arithmetic; every pixel, no expression
    priority or quota) or the torch code; the top-k choice (:func:`top_scores`) and the chosen pixels' triangles,
    barycentric coordinates and gray values by native kernels too where they can run (``top_pixels.h``, the torch
    code's arithmetic: the same template either way)."""
    full_h, full_w = intrinsics.height, intrinsics.width
    B = gray.shape[0]
    verts_model, verts_cam, normals_cam = posed.verts_model, posed.verts_cam, posed.normals_cam
    off = torch.zeros(B, 2, dtype=verts_cam.dtype, device=gray.device) if offsets is None else offsets.to(verts_cam.dtype)
    grads = None
    if stride > 1:  # the gradients at the window's pixels, before the striding
        grads = image_with_gradients(gray)[:, 1:]
        gray, grads = gray[..., ::stride, ::stride], grads[..., ::stride, ::stride]
    H, W = gray.shape[-2:]
    if frags is None:
        window = Intrinsics(gray.shape[-1] * stride, gray.shape[-2] * stride, intrinsics.fx, intrinsics.fy,
                            intrinsics.cx, intrinsics.cy)  # fmt: skip
        cam, cam_off = strided_window(window, offsets, stride)
        frags = rasterize_windows(model, verts_cam, [cam], [cam_off], backend)[0]
    face = frags.pix_to_face
    face_flat = face.flatten(1)  # (flatten: B = 0 too)
    if (stride == 1 and expression_priority <= 0
            and use_native(backend, (gray, verts_cam, normals_cam, frags.coefficients.detach()), "pixel selection")):
        score = _native_scores(model, posed, gray, intrinsics, off, frags, gradient_threshold, min_facing_cos,
                               erode_pixels, seed)  # fmt: skip
        if expression_quota > 0 and model.num_animation > 0:  # keys + 2 lift at the candidates, as below
            flat = (score.reshape(-1) >= 0).nonzero().squeeze(-1)
            lift = _quota_lift(model, frags, flat, score, intrinsics.fx, expression_quota)
            score = torch.where(score >= 0, score + 2.0 * lift, score)
        return _top_pixels(score, face_flat, frags, gray, max_points, verts_model.dtype, backend)
    mask = (face >= 0) & (frags.facing > 0)
    if grads is None:
        grads = image_with_gradients(gray)[:, 1:]
    gmag = grads.pow(2).sum(1).sqrt()
    # A non-finite pixel (a float frame's inf or NaN), or one beside it, is no template point: its intensity or its
    # gradient would be inf/NaN, a dead point of every solve and search (NaN compares False, so only inf is tested).
    candidate = _erode(mask, erode_pixels) & (gmag >= gradient_threshold) & torch.isfinite(gmag)
    candidate &= torch.isfinite(gray[:, 0])
    # Grazing facets sample the image badly: keep points whose normal faces the viewing ray. The normal is only
    # interpolated at the pixels still candidates (every sample's, listed together), not over the whole window,
    # with their barycentric coordinates alone, and only on the triangles that some of their points may fail:
    # the cosine at a point of a triangle is at least the smallest cosine of a corner's (unit) normal with a
    # corner's direction from the camera (the point and its interpolated normal are convex combinations of the
    # corners'; where that bound is non-negative), so a triangle whose bound clears the threshold (and 0) by
    # _FACING_MARGIN passes whole, as the per-point test would pass each of its points.
    flat = candidate.reshape(-1).nonzero().squeeze(-1)  # (M,) over B * H * W
    b_of = torch.div(flat, H * W, rounding_mode="floor")
    face_c = face_flat.reshape(-1).index_select(0, flat)
    num_faces = model.faces.shape[0]
    corner_normals = normals_cam[:, model.faces]  # (B, F, 3, 3)
    corner_rays = torch.nn.functional.normalize(verts_cam[:, model.faces], dim=-1)  # (B, F, 3, 3)
    bound = -torch.matmul(corner_normals, corner_rays.transpose(-1, -2)).flatten(-2).amax(-1)  # (B, F)
    unsure = ~(bound >= max(min_facing_cos, 0.0) + _FACING_MARGIN).reshape(-1)  # NaN: unsure
    test = unsure.index_select(0, b_of * num_faces + face_c).nonzero().squeeze(-1)
    flat, b_of, face_c = flat.index_select(0, test), b_of.index_select(0, test), face_c.index_select(0, test)
    pix = flat - b_of * (H * W)
    pix_row = torch.div(pix, W, rounding_mode="floor")
    pix_col = pix - pix_row * W
    corner = model.faces.index_select(0, face_c)  # (M, 3)
    bary_c = frags.covered_barycentrics(b_of, face_c, pix_row, pix_col).to(normals_cam.dtype)
    V = normals_cam.shape[1]
    n_corner = normals_cam.reshape(-1, 3).index_select(0, (b_of.unsqueeze(-1) * V + corner).reshape(-1))
    n_pix = torch.bmm(bary_c.unsqueeze(1), n_corner.view(-1, 3, 3)).squeeze(1)  # (M, 3): 2.5x the weighted sum
    # The surface point seen at a pixel centre lies on that pixel's ray (perspective-correct barycentrics), so
    # its direction is the ray's: no need to interpolate the positions.
    col = (pix_col * stride).to(verts_cam.dtype) + off[b_of, 0]
    row = (pix_row * stride).to(verts_cam.dtype) + off[b_of, 1]
    rays = torch.stack([(col - intrinsics.cx) / intrinsics.fx, (row - intrinsics.cy) / intrinsics.fy,
                        torch.ones_like(col)], -1)  # fmt: skip
    cos = -(torch.nn.functional.normalize(n_pix, dim=-1) * torch.nn.functional.normalize(rays, dim=-1)).sum(-1)
    candidate = candidate.reshape(-1).index_put((flat,), cos >= min_facing_cos).reshape(B, H, W)
    keys = _selection_keys(full_h, full_w, gray.device, seed)
    if offsets is None:
        if stride > 1:
            keys = keys.view(full_h, full_w)[::stride, ::stride].reshape(-1)
        keys = keys.expand(B, -1)
    else:  # the whole image's keys at the windows' pixels
        pix_rows = offsets[:, 1:2] + stride * torch.arange(H, device=gray.device)
        pix_cols = offsets[:, 0:1] + stride * torch.arange(W, device=gray.device)
        keys = keys[(pix_rows[:, :, None] * full_w + pix_cols[:, None, :]).reshape(B, H * W)]
    if expression_priority > 0 and model.num_animation > 0:
        # Points that some animation unit moves by at least ~1 px per unit are kept first: an AU acting on a
        # small region (eyelids) would otherwise get few of the uniformly drawn points.
        full = frags.fragments()  # every pixel's barycentric coordinates and depth
        bary_flat, zbuf = full.bary.flatten(1, 2), full.zbuf
        au_mm = model.animation_units.norm(dim=-1).amax(0)  # (V,) largest displacement per unit coefficient
        sens = gather_face_attributes(au_mm.unsqueeze(-1), model.faces, face_flat, bary_flat, batched=False)[..., 0]
        px_per_mm = intrinsics.fx / zbuf.flatten(1).clamp(1.0, 1e30)
        keys = keys + expression_priority * (sens * px_per_mm >= 1.0).to(keys.dtype)
    if expression_quota > 0 and model.num_animation > 0:
        keys = keys + 2.0 * _quota_lift(model, frags, candidate.reshape(-1).nonzero().squeeze(-1), keys,
                                        intrinsics.fx, expression_quota)  # fmt: skip
    score = torch.where(candidate.flatten(1), keys, torch.full_like(keys, -1.0))
    return _top_pixels(score, face_flat, frags, gray, max_points, verts_model.dtype, backend)


def _quota_lift(model: FaceModel, frags: Coverage, flat: Tensor, keys: Tensor, fx: float, quota: int) -> Tensor:
    """The expression quota's lift ``(B, H W)`` in ``keys``' dtype: 1 at the ``quota`` candidates with the highest
    ``keys`` among those each animation unit moves by >= 1 px per unit coefficient, 0 elsewhere.

    ``flat``: the candidate pixels ``(M,)`` over ``B H W`` (ascending); ``keys (B, H W)`` their selection keys
    (any values elsewhere). Each candidate's barycentric coordinates and depth are evaluated at it alone
    (:class:`~torchface.rendering.rasterizer.Coverage`'s arithmetic, the values :meth:`Coverage.fragments` gives
    there), not over the whole window."""
    B, H, W = frags.pix_to_face.shape
    A = model.num_animation
    b_of = torch.div(flat, H * W, rounding_mode="floor")
    pix = flat - b_of * (H * W)
    row = torch.div(pix, W, rounding_mode="floor")
    face_c = frags.pix_to_face.reshape(-1).index_select(0, flat)
    bary, depth = frags.covered_depths(b_of, face_c, row, pix - row * W)
    au_mm = model.animation_units.norm(dim=-1).T  # (V, A) displacement per unit coefficient
    sens = gather_face_attributes(au_mm, model.faces, face_c[None], bary[None], batched=False)[0]  # (M, A)
    px_per_mm = fx / depth.clamp(1.0, 1e30)
    moved = sens * px_per_mm[:, None] >= 1.0
    # Each sample's candidates in a (B, A, M_max) block (nonzero lists them sample by sample).
    counts = torch.bincount(b_of, minlength=B)
    first = torch.cumsum(counts, 0) - counts
    slot = torch.arange(flat.shape[0], device=flat.device) - first[b_of]
    m_max = max(int(counts.max()) if B else 0, 1)
    au_keys = torch.full((B, m_max, A), -1.0, dtype=keys.dtype, device=keys.device)
    au_keys[b_of, slot] = torch.where(moved, keys.reshape(-1)[flat][:, None], au_keys.new_tensor(-1.0))
    top_k, top_s = torch.topk(au_keys.transpose(1, 2), min(quota, m_max), dim=-1)  # (B, A, q)
    pix_of = torch.zeros(B, m_max, dtype=torch.int64, device=keys.device)
    pix_of[b_of, slot] = pix
    lift = torch.zeros(B, H * W, dtype=keys.dtype, device=keys.device)
    lift.scatter_reduce_(1, torch.gather(pix_of, 1, top_s.flatten(1)), (top_k >= 0).flatten(1).to(keys.dtype),
                         reduce="amax")
    return lift


def top_scores(score: Tensor, k: int, backend: Backend = Backend.AUTO) -> tuple[Tensor, Tensor]:
    """The ``k`` highest scores of each row of ``score (B, N)`` (no NaN) and their indices, ``(B, k)`` each, in the
    order of a stable descending sort: score descending, equal scores by index ascending.

    ``torch.topk`` leaves the order of equal scores unspecified, and the pixel selection keys of a 640x480 image
    hold equal pairs, which would make a template's point order (and its sums' rounding) depend on the
    implementation. The native kernel (``torchface/_native/top_pixels.h``: a histogram of the scores finds the
    ``k``-th's bucket, and only the scores from that bucket up are sorted) gives the same result as the torch
    code's stable sort; at 1500 of a face window's pixels it takes a fraction of ``torch.topk``'s time."""
    if score.dim() != 2:
        raise ValueError(f"score must be (B, N), got {tuple(score.shape)}")
    if not 1 <= k <= score.shape[-1]:
        raise ValueError(f"k must be in [1, {score.shape[-1]}], got {k}")
    if use_native(backend, (score,), "top-k"):
        from torchface import _native

        B, N = score.shape
        score = score.contiguous()
        index = torch.empty(B, k, dtype=torch.int64)
        value = torch.empty(B, k, dtype=score.dtype)
        prob = _native.TopProblem(B=B, N=N, k=k, score=score.data_ptr(), out_index=index.data_ptr(),
                                  out_value=value.data_ptr())  # fmt: skip
        _native.run("top_pixels", score.dtype == torch.float64, prob, B, torch.get_num_threads())
        return value, index
    value, index = torch.sort(score, dim=1, descending=True, stable=True)
    return value[:, :k], index[:, :k]


def _top_pixels(score: Tensor, face_flat: Tensor, frags: Coverage, gray: Tensor, max_points: int,
                dtype: torch.dtype, backend: Backend = Backend.AUTO) -> TemplatePixels:  # fmt: skip
    """The ``max_points`` highest-scoring pixels ``score (B, H W)`` (-1: not a candidate; :func:`top_scores`'
    order) as :class:`TemplatePixels`: their triangle (``face_flat (B, H W)``), barycentric coordinates
    (``frags``) and gray value (``gray (B, 1, H, W)``), in ``dtype``; by the native kernel where ``backend``, the
    dtypes (float32 scores; gray, coefficients and ``dtype`` one dtype) and the inputs allow (:func:`_native_pick`:
    the torch code's score of tensor operations cost about 0.3 ms per pyramid level of a new mosaic entry)."""
    B, W = gray.shape[0], gray.shape[-1]
    top, pix = top_scores(score, max_points, backend)
    # Natively where no derivative is asked for: the torch code's barycentric coordinates are differentiable in the
    # coefficients (a pose that requires grad) and its gray values in ``gray`` (not an error with Backend.NATIVE:
    # the stages before may have run natively).
    coefficients = frags.coefficients
    if (top.dtype == torch.float32 and gray.dtype == coefficients.dtype == dtype
            and use_native(Backend.AUTO if backend is Backend.NATIVE else backend, (coefficients, gray),
                           "template pixels")):  # fmt: skip
        return _native_pick(top, pix, frags, gray)
    valid = top >= 0
    face_index = torch.gather(face_flat, 1, pix).clamp_min(0)
    rows = torch.arange(B, device=pix.device).repeat_interleave(pix.shape[1])
    pix_row = torch.div(pix.reshape(-1), W, rounding_mode="floor")
    bary = frags.barycentrics(rows, pix_row, pix.reshape(-1) - pix_row * W).reshape(B, pix.shape[1], 3)
    bary = bary.to(dtype)
    intensity = torch.gather(gray.flatten(1), 1, pix).to(dtype)
    return TemplatePixels(face_index, bary, intensity, valid)


def _native_pick(top: Tensor, pix: Tensor, frags: Coverage, gray: Tensor) -> TemplatePixels:
    """:func:`_top_pixels`' pixels at the chosen candidates ``pix (B, k)`` (their float32 scores ``top (B, k)``)
    by the native kernel (``torchface/_native/top_pixels.h``: the same arithmetic as the torch code), in the
    dtype of ``gray (B, 1, H, W)`` and of the coverage's coefficients."""
    from torchface import _native

    B, k = pix.shape
    H, W = gray.shape[-2:]
    dtype = gray.dtype
    inputs = [x.contiguous() for x in (pix, top, frags.pix_to_face, gray, frags.coefficients.detach(), frags.ray_a,
                                       frags.ray_b)]  # fmt: skip
    face_index = torch.empty(B, k, dtype=torch.int64)
    bary, intensity = torch.empty(B, k, 3, dtype=dtype), torch.empty(B, k, dtype=dtype)
    valid = torch.empty(B, k, dtype=torch.bool)
    names = ("index", "value", "pix_to_face", "gray", "coefficients", "ray_a", "ray_b")
    prob = _native.PickProblem(
        B=B, H=H, W=W, F=frags.num_faces, batch_offset=frags.batch_offset, k=k,
        num_columns=frags.coefficients.shape[1], **{n: x.data_ptr() for n, x in zip(names, inputs)},
        out_face=face_index.data_ptr(), out_bary=bary.data_ptr(), out_intensity=intensity.data_ptr(),
        out_valid=valid.data_ptr(),
    )  # fmt: skip
    _native.run("pick_pixels", dtype == torch.float64, prob, B, 1)
    return TemplatePixels(face_index, bary, intensity, valid)


def _native_scores(
    model: FaceModel, posed: PosedMesh, gray: Tensor, intrinsics: Intrinsics, offsets: Tensor, frags: Coverage,
    gradient_threshold: float, min_facing_cos: float, erode_pixels: int, seed: int,
) -> Tensor:
    """:func:`select_pixels_posed`'s scores ``(B, H W)`` float32 by the native kernel: the selection key at each
    candidate pixel of the windows ``gray (B, 1, H, W)`` at ``offsets (B, 2)``, -1 elsewhere."""
    from torchface import _native

    B, _, H, W = gray.shape
    dtype = posed.verts_cam.dtype
    keys = _cpu_selection_keys(intrinsics.height, intrinsics.width, seed)
    inputs = [x.contiguous() for x in (gray.to(dtype), frags.pix_to_face, frags.facing, frags.coefficients.detach(),
                                       frags.ray_a, frags.ray_b, posed.verts_cam, posed.normals_cam,
                                       model.faces.to(torch.int64), offsets.to(dtype), keys)]  # fmt: skip
    score = torch.empty(B, H * W, dtype=torch.float32)
    names = ("gray", "pix_to_face", "facing", "coefficients", "ray_a", "ray_b", "verts", "normals", "faces", "offsets",
             "keys")  # fmt: skip
    prob = _native.SelectProblem(
        B=B, H=H, W=W, V=posed.verts_cam.shape[1], F=model.faces.shape[0], erode=int(erode_pixels),
        full_w=intrinsics.width, batch_offset=frags.batch_offset, num_columns=frags.coefficients.shape[1],
        gradient_threshold=float(gradient_threshold), min_facing_cos=float(min_facing_cos),
        facing_margin=_FACING_MARGIN, fx=intrinsics.fx, fy=intrinsics.fy, cx=intrinsics.cx, cy=intrinsics.cy,
        **{n: x.data_ptr() for n, x in zip(names, inputs)}, out_score=score.data_ptr(),
    )  # fmt: skip
    _native.run("select_pixels", dtype == torch.float64, prob, B, torch.get_num_threads())
    return score


def build_template(
    model: FaceModel,
    shape_coeffs: Tensor,
    anim_coeffs: Tensor,
    rotation: Tensor,
    translation: Tensor,
    gray: Tensor,
    intrinsics: Intrinsics,
    *,
    max_points: int,
    gradient_threshold: float,
    min_facing_cos: float = 0.15,
    erode_pixels: int = 1,
    expression_priority: float = 0.0,
    expression_quota: int = 0,
    offsets: Tensor | None = None,
    seed: int = 0,
    backend: Backend = Backend.AUTO,
) -> Template:
    """Template points of a frame whose model parameters are known (paper Section 2-3 and 4).

    :func:`select_template_pixels` (arguments and selection documented there; ``backend`` of its rasterization
    and candidate tests), then :func:`template_at`.

    Returns:
        :class:`Template` with ``N = max_points`` slots.
    """
    pixels = select_template_pixels(
        model, shape_coeffs, anim_coeffs, rotation, translation, gray, intrinsics, max_points=max_points,
        gradient_threshold=gradient_threshold, min_facing_cos=min_facing_cos, erode_pixels=erode_pixels,
        expression_priority=expression_priority, expression_quota=expression_quota, offsets=offsets, seed=seed,
        backend=backend,
    )  # fmt: skip
    return template_at(model, shape_coeffs, pixels.face_index, pixels.bary, pixels.intensity, pixels.valid,
                       backend=backend)


def template_at(
    model: FaceModel, shape_coeffs: Tensor, face_index: Tensor, bary: Tensor, intensity: Tensor, valid: Tensor,
    *, neutral: tuple[Tensor, Tensor] | None = None, backend: Backend = Backend.AUTO,
) -> Template:
    """The :class:`Template` of points given by triangle and barycentric coordinates (Eq. 3-9).

    Positions, expression basis and normals follow from the person's shape and the points' places on the mesh;
    :func:`build_template` ends here, and a stored template (a mosaic entry) is rebuilt from its compact form.

    Args:
        model: the face model.
        shape_coeffs: ``(B, S)``.
        face_index: ``(B, N)`` int64 triangles; bary: ``(B, N, 3)``; intensity: ``(B, N)``; valid: ``(B, N)`` bool.
        neutral: the person's neutral vertices ``(B, V, 3)`` (``model.deform(shape_coeffs, None)``) and their
            vertex normals ``(B, V, 3)`` when the caller has them (several point sets of one person, such as a
            pyramid's levels); None computes them.
        backend: :class:`~torchface.backend.Backend` of the interpolation: the native kernel
            (``torchface/_native/template_at.h``, the same arithmetic) also makes the template's point-last copies
            (:attr:`Template.point_last`) in the same pass.

    Returns:
        :class:`Template`.

    Raises:
        ValueError: ``neutral`` is not two ``(B, V, 3)`` tensors.
    """
    if neutral is None:
        verts = model.deform(shape_coeffs, None)
        neutral = verts, vertex_normals(verts, model.faces)
    verts, vertex_normals_neutral = neutral
    want = (face_index.shape[0], model.num_vertices, 3)
    if tuple(verts.shape) != want or tuple(vertex_normals_neutral.shape) != want:
        raise ValueError(f"neutral must be two {want} tensors (vertices, vertex normals), got "
                         f"{tuple(verts.shape)} and {tuple(vertex_normals_neutral.shape)}")  # fmt: skip
    if use_native(backend, (verts, vertex_normals_neutral, bary, model.animation_units), "template"):
        return _template_at_native(model, verts, vertex_normals_neutral, face_index, bary, intensity, valid)
    points = gather_face_attributes(verts, model.faces, face_index, bary, batched=True)
    basis = gather_face_attributes(model.animation_units.permute(1, 2, 0), model.faces, face_index, bary, batched=False)
    normals = interpolated_normals(vertex_normals_neutral, model.faces, face_index, bary)
    return Template(face_index, bary, points, basis, normals, intensity, valid)


def _template_at_native(
    model: FaceModel, verts: Tensor, vertex_normals_neutral: Tensor, face_index: Tensor, bary: Tensor,
    intensity: Tensor, valid: Tensor,
) -> Template:
    """:func:`template_at` by the native kernel, with its :attr:`Template.point_last` copies made in the same pass
    (as normal tensors, kept with the template)."""
    from torchface import _native

    B, N = face_index.shape
    V, A = model.num_vertices, model.num_animation
    dtype = verts.dtype
    with torch.inference_mode(False):  # the point-last copies are kept with the template: normal tensors
        inputs = [x.contiguous() for x in (verts, vertex_normals_neutral, model.animation_units,
                                           model.faces.to(torch.int64), face_index.to(torch.int64), bary)]  # fmt: skip
        points, normals = torch.empty(B, N, 3, dtype=dtype), torch.empty(B, N, 3, dtype=dtype)
        basis = torch.empty(B, N, 3, A, dtype=dtype)
        points_t, normals_t = torch.empty(B, 3, N, dtype=dtype), torch.empty(B, 3, N, dtype=dtype)
        basis_t = torch.empty(B, A, 3, N, dtype=dtype)
        names = ("verts", "vertex_normals", "anim_units", "faces", "face_index", "bary")
        prob = _native.TemplateProblem(
            B=B, V=V, A=A, N=N, **{n: x.data_ptr() for n, x in zip(names, inputs)}, out_points=points.data_ptr(),
            out_basis=basis.data_ptr(), out_normals=normals.data_ptr(), out_points_t=points_t.data_ptr(),
            out_normals_t=normals_t.data_ptr(), out_basis_t=basis_t.data_ptr(),
        )  # fmt: skip
        _native.run("template_at", dtype == torch.float64, prob, B, torch.get_num_threads())
    tpl = Template(face_index, bary, points, basis, normals, intensity, valid)
    object.__setattr__(tpl, "_point_last", (points_t, normals_t, basis_t))
    return tpl


def _of_dtype(x: Tensor, dtype: torch.dtype) -> Tensor:
    """``x.to(dtype)``, without the dispatched operation where ``x`` is of ``dtype`` already (``to`` returns it; a
    no-op ``to`` still costs 2-4 microseconds: template management's native calls made seven of them a step; the
    step's result codes, status and iterations, use it too)."""
    return x if x.dtype == dtype else x.to(dtype)


def _rows_writable(model: FaceModel, into: Template, dtype: torch.dtype) -> bool:
    """Whether :func:`_template_rows_native` can write into ``into``: it holds its point-last copies
    (:attr:`Template.point_last`) and its tensors are normal (not inference) tensors that do not require grad
    (autograd would not see the kernel's writes), and those the kernel writes contiguous, of ``dtype`` and of the
    template's layout."""
    cached = into.__dict__.get("_point_last")
    if cached is None:
        return False
    B, N = into.face_index.shape
    A = model.num_animation
    want = ((B, N, 3), (B, N, 3, A), (B, N, 3), (B, 3, N), (B, 3, N), (B, A, 3, N))
    outs = (into.points, into.basis, into.normals, *cached)
    return not any(
        x.is_inference() or x.requires_grad or not x.is_contiguous() or x.dtype != dtype or tuple(x.shape) != shape
        for x, shape in zip(outs, want)
    ) and not any(getattr(into, f).is_inference() for f in ("face_index", "bary", "intensity", "valid"))


def _template_rows_native(
    model: FaceModel, neutral: tuple[Tensor, Tensor], pixels: TemplatePixels, into: Template, rows: Tensor
) -> Template:
    """:func:`template_at` of ``pixels`` (batch ``B'``, as many points as ``into``) written by the native kernel
    straight into rows ``rows`` (int64 ``(B',)``, distinct) of ``into``'s tensors and of its point-last copies
    (:attr:`Template.point_last`), in place (:func:`_rows_writable` must hold; the kernel must be able to run):
    the template of ``into``'s batch with those rows replaced, on the same tensors, as copying a fresh template
    into them gives. ``neutral``: the ``B'`` streams' neutral vertices and vertex normals ``(B', V, 3)``."""
    from torchface import _native

    verts, vertex_normals_neutral = neutral
    dtype = verts.dtype
    cached = into.__dict__["_point_last"]
    with torch.inference_mode(False):
        inputs = [x.contiguous() for x in (verts, vertex_normals_neutral, model.animation_units,
                                           _of_dtype(model.faces, torch.int64),
                                           _of_dtype(pixels.face_index, torch.int64), _of_dtype(pixels.bary, dtype),
                                           _of_dtype(rows, torch.int64))]  # fmt: skip
        names = ("verts", "vertex_normals", "anim_units", "faces", "face_index", "bary", "out_rows")
        outs = ("out_points", "out_basis", "out_normals", "out_points_t", "out_normals_t", "out_basis_t")
        prob = _native.TemplateProblem(
            B=rows.shape[0], V=model.num_vertices, A=model.num_animation, N=into.face_index.shape[1],
            **{n: x.data_ptr() for n, x in zip(names, inputs)},
            **{n: x.data_ptr() for n, x in zip(outs, (into.points, into.basis, into.normals, *cached))},
        )  # fmt: skip
        _native.run("template_at", dtype == torch.float64, prob, rows.shape[0], torch.get_num_threads())
        # in-place changes for autograd, as torch's own writes are: a graph that saved one of these tensors refuses
        # to backpropagate through its old values ("modified by an inplace operation") instead of using the new
        torch.autograd.graph.increment_version((into.points, into.basis, into.normals, *cached))
        for name in ("face_index", "bary", "intensity", "valid"):
            x = getattr(into, name)
            x[rows] = _of_dtype(getattr(pixels, name), x.dtype)
    new = Template(into.face_index, into.bary, into.points, into.basis, into.normals, into.intensity, into.valid)
    object.__setattr__(new, "_point_last", cached)
    return new


def point_normals(model: FaceModel, shape_coeffs: Tensor, face_index: Tensor, bary: Tensor) -> Tensor:
    """``(B, N, 3)`` the unit head-frame normals (zero expression) of points given by triangle ``(B, N)`` and
    barycentric coordinates ``(B, N, 3)``: :attr:`Template.normals` without the rest of :func:`template_at`."""
    return interpolated_normals(vertex_normals(model.deform(shape_coeffs, None), model.faces), model.faces, face_index,
                                bary)  # fmt: skip


def interpolated_normals(normals: Tensor, faces: Tensor, face_index: Tensor, bary: Tensor) -> Tensor:
    """``(B, N, 3)`` unit normals of points given by triangle ``(B, N)`` and barycentric coordinates
    ``(B, N, 3)``, interpolated from vertex normals ``(B, V, 3)`` (:func:`point_normals` once the person's
    vertex normals are known: several point sets of one person, such as a pyramid's levels)."""
    interpolated = gather_face_attributes(normals, faces, face_index, bary, batched=True)
    return torch.nn.functional.normalize(interpolated, dim=-1)
