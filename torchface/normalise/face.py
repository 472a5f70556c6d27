"""The normalised face: the frame resampled to a frontal, neutral, evenly lit canonical view (paper Section 4).

The paper measures dissimilarity on "the normalised view of the face (frontal, neutral expression, neutral
light)" rebuilt from the estimated pose, expression and light. This module produces that view as an image.

Canonical layout
----------------
:func:`build_normalised_layout` places the model's MEAN shape (``sigma = 0``, ``alpha = 0``) at the identity
rotation in front of a long-focal camera (far away, so nearly orthographic) framed so that the face fills a
``G x G`` image with a margin, and rasterizes it once. Every face pixel ``p`` of that image stores the
triangle ``f_p`` it sees and the barycentric coordinates ``b_p`` of its surface point. Because the layout
uses the mean shape, every person and every expression maps to the same canonical image: a pixel always
shows the same place on the surface (``f_p``, ``b_p``), wherever that place is in a given frame.

Resampling
----------
For a frame with estimated shape ``sigma``, expression ``alpha``, pose ``(R, t)`` and illumination
``lambda``, :func:`normalised_face` moves each canonical surface point with the model (paper Eq. 1 and the
barycentric point model of Eq. 3-9)

    ``X_p = sum_i b_p,i g_(f_p, i)(sigma, alpha)``,   ``X_p,cam = R X_p + t``   (Eq. 14),

projects it into the frame, ``x_p = pi(X_p,cam)`` (Eq. 15), and samples the frame bilinearly there. Sampling
at the CURRENT expression reads the texture where the expression moved it, so the canonical image shows
the neutral face (the expression is undone). The light is then undone with the inverse of Eq. 19,
``T = (I - lambda_2) / (1 + lambda_1 + (lambda_3, lambda_4, lambda_5) . n_cam)``
(:func:`torchface.appearance.illumination.remove_illumination`), with ``n_cam`` the surface normal of the
deformed, posed mesh at the point: the result is the face under the reference light of the template frame.

A canonical pixel is kept (mask 1) when its surface point is visible in the frame: in front of the camera,
projecting inside the image, on a triangle that faces the camera with its normal at least
``acos(min_facing_cos)`` away from grazing, and not hidden by another part of the mesh (z-buffer of the posed
mesh, :func:`torchface.rendering.visibility.points_visible`), and its sampled value is finite (NaN frame pixels
are missing data, as the tracker takes them; the parameters' gradients stay finite). Other pixels, and the
background of the layout, are 0 with mask 0.
A sample whose geometry is not finite (a NaN or inf parameter or vertex) shows no face: image and mask 0, and its
geometry parameters get gradient 0 (never NaN).

The output is differentiable with respect to the frame pixels (it is linear in them) and, almost everywhere,
with respect to the shape, expression, pose and illumination parameters; the mask is not differentiable.
Reverse mode only (autograd, double backward, ``torch.func.grad``, ``vjp``, ``jacrev``): torch's bilinear sampler
(``grid_sample``) has no forward-mode derivative, so ``torch.func.jvp`` and ``jacfwd`` raise torch's
``NotImplementedError``. ``torch.func.vmap`` maps over the frames and the illumination; over the geometry
(shape, expression, pose) it stops at torch's "data-dependent control flow" error (which pixels are visible is
decided from the values): batch the samples in ``B`` instead.

Shapes: ``B`` batch, ``C`` channels, ``H x W`` frames, ``V`` vertices, ``F`` triangles, ``S`` shape units,
``A`` animation units, ``L`` illumination terms, ``G x G`` the normalised image (``G = layout.size``), ``M``
the layout's face pixels. Frames, units and the pixel convention are those of :mod:`torchface.conventions`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple, TypeVar

import torch
from torch import Tensor

from torchface._autocast import full_precision
from torchface._compiling import is_compiling
from torchface._device import DeviceCheckedModule, check_holds_data, tensor_mover
from torchface.appearance.illumination import NUM_ILLUMINATION_TERMS, remove_illumination
from torchface.appearance.sampling import sample_at_pixels
from torchface.backend import Backend, use_native
from torchface.conventions import NEAR_PLANE_MM
from torchface.geometry._checks import check_bool, check_int, check_intrinsics, check_number
from torchface.geometry.camera import Intrinsics
from torchface.geometry.mesh import vertex_normals_and_backfacing
from torchface.geometry.projection import project_points
from torchface.geometry.so3 import axis_angle_to_matrix
from torchface.geometry.transforms import transform_points
from torchface.model.face_model import FaceModel
from torchface.rendering.rasterizer import Coverage, Fragments, rasterize, rasterize_coverage
from torchface.rendering.visibility import points_visible

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

    from torchface.tracker.step import TrackerState, TrackResult

__all__ = [
    "NormalisedFaceLayout",
    "NormalisedFaceResult",
    "build_normalised_layout",
    "normalised_face",
    "normalised_face_posed",
    "NormalisedFace",
]

#: Default relative depth tolerance of the z-buffer visibility test (fraction of the point's depth).
DEFAULT_DEPTH_TOLERANCE: float = 0.02
#: Default minimum cosine between a point's normal and the ray toward the camera (about 84 degrees).
DEFAULT_MIN_FACING_COS: float = 0.1


@dataclass(frozen=True, eq=False)
class NormalisedFaceLayout:
    """The canonical frontal view of a face model, rasterized once (module docstring).

    ``face_index[m] = f`` and ``bary[m]`` say that face pixel ``m`` of the canonical image, the pixel at flat
    index ``pixel_index[m] = row * G + col``, sees the point ``sum_i bary[m, i] verts[faces[f, i]]`` of the
    mean shape; ``mask[row, col]`` is True exactly at those ``M`` pixels.

    Attributes:
        size: ``G``, the canonical image is ``G x G``.
        margin: fraction of ``G`` left empty on the tighter side of the face's bounding box.
        intrinsics: the layout camera (``G x G``).
        translation: ``(3,)`` position (mm) of the head-frame origin in the layout camera; the rotation is the
            identity, and ``translation[0] = 0`` so the model's symmetry plane ``x = 0`` is the centre column.
        num_faces: ``F`` of the model the layout was built for.
        pixel_index: ``(M,)`` int64 flat indices of the face pixels.
        face_index: ``(M,)`` int64 triangle seen at each face pixel.
        bary: ``(M, 3)`` barycentric coordinates (of the 3D surface point) in that triangle.
        mask: ``(G, G)`` bool, True at face pixels.

    Example:
        >>> from torchface.model import load_candide3
        >>> layout = build_normalised_layout(load_candide3(), size=64)
        >>> layout.mask.shape, layout.bary.shape[1]
        (torch.Size([64, 64]), 3)
    """

    size: int
    margin: float
    intrinsics: Intrinsics
    translation: Tensor
    num_faces: int
    pixel_index: Tensor
    face_index: Tensor
    bary: Tensor
    mask: Tensor
    _weights: dict[tuple[int, torch.dtype, torch.device], tuple[Tensor, Tensor]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )  # vertex_weights, made once per faces tensor and dtype

    def __post_init__(self) -> None:
        if not isinstance(self.intrinsics, Intrinsics):
            raise TypeError(f"intrinsics must be an Intrinsics, got {type(self.intrinsics).__name__}")
        g = int(self.size)
        if self.intrinsics.size != (g, g):
            got = f"{self.intrinsics.height}x{self.intrinsics.width}"
            raise ValueError(f"intrinsics must be {g}x{g} like size, got {got}")
        m = self.pixel_index.shape[0]
        if self.pixel_index.shape != (m,) or self.face_index.shape != (m,) or self.bary.shape != (m, 3):
            raise ValueError(
                f"pixel_index, face_index and bary must be (M,), (M,), (M, 3), got {tuple(self.pixel_index.shape)}, "
                f"{tuple(self.face_index.shape)}, {tuple(self.bary.shape)}"
            )
        if self.mask.shape != (g, g) or self.mask.dtype != torch.bool:
            raise ValueError(f"mask must be a ({g}, {g}) bool tensor, got {tuple(self.mask.shape)} {self.mask.dtype}")
        if self.translation.shape != (3,):
            raise ValueError(f"translation must be (3,), got {tuple(self.translation.shape)}")

    @property
    def num_pixels(self) -> int:
        """``M``, the number of face pixels."""
        return int(self.pixel_index.shape[0])

    def vertex_weights(self, faces: Tensor, num_vertices: int, dtype: torch.dtype) -> Tensor:
        """``(M, V)`` the barycentric coordinates as a matrix over the mesh's vertices: row ``m`` holds
        ``bary[m]`` at the corners of triangle ``face_index[m]`` of ``faces (F, 3)``, so that ``weights @ X``
        interpolates any per-vertex attribute ``X (V, D)`` at the face pixels. Made once per ``faces`` tensor
        and dtype, on ``faces``' device, and kept with the layout (a mesh's topology does not change)."""
        key = (num_vertices, dtype, faces.device)
        held = self._weights.get(key)
        if held is not None and held[0] is faces:
            return held[1]
        # Made outside inference mode even when first asked for inside it (a validation pass before training): an
        # inference tensor cannot be saved for a later differentiable call's backward.
        with torch.inference_mode(False):
            m = self.face_index.shape[0]
            corners = faces.index_select(0, self.face_index.to(faces.device)).reshape(-1)  # (M * 3,)
            rows = torch.arange(m, device=faces.device).repeat_interleave(3)
            weights = torch.zeros(m, num_vertices, dtype=dtype, device=faces.device)
            bary = self.bary.to(device=faces.device, dtype=dtype).reshape(-1)
            weights.index_put_((rows, corners), bary, accumulate=True)
        self._weights[key] = (faces, weights)  # the faces held too: their id is not reused while the entry lives
        return weights

    def to(
        self, device: torch.device | str | int | torch.dtype | None = None, dtype: torch.dtype | None = None,
        non_blocking: bool = False, copy: bool = False,
    ) -> "NormalisedFaceLayout":
        """A copy on ``device`` with the floating tensors in ``dtype`` (index and mask tensors keep theirs), called as
        ``Tensor.to`` is (``.to(device)``, ``.to(dtype)``, ``.to(device, dtype)``, keywords, ``non_blocking`` and
        ``copy``: :func:`~torchface._device.tensor_mover`, as ``TrackResult.to``)."""
        move = tensor_mover(device, dtype, non_blocking, copy)  # (a device this machine lacks: a ValueError)
        return NormalisedFaceLayout(
            self.size, self.margin, self.intrinsics, move(self.translation), self.num_faces, move(self.pixel_index),
            move(self.face_index), move(self.bary), move(self.mask),
        )  # fmt: skip


_Frozen = TypeVar("_Frozen", bound="DataclassInstance")  # a frozen dataclass


def apply_to_tensor_fields(fn: Callable[[Tensor], Tensor], obj: _Frozen) -> _Frozen:
    """A copy of the frozen dataclass ``obj`` with ``fn`` (an ``nn.Module._apply`` function: ``.to``, ``.double``,
    ``.cuda``, ...) applied to each of its tensor fields; integer and bool tensors keep their dtype (``fn`` may
    only move them)."""
    changes: dict[str, Tensor] = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if f.init and isinstance(value, Tensor):
            out = fn(value)
            changes[f.name] = out if value.is_floating_point() or out.dtype == value.dtype else out.to(value.dtype)
    return dataclasses.replace(obj, **changes)


def apply_to_model_and_layout(
    fn: Callable[[Tensor], Tensor], model: FaceModel, layout: NormalisedFaceLayout
) -> tuple[FaceModel, NormalisedFaceLayout]:
    """``model`` and ``layout`` with ``fn`` applied to their tensors: what a module holding them (as plain
    attributes) does in its ``_apply``, so that ``.to(...)``, ``.double()``, ``.float()`` and ``.cuda()`` move them.

    Raises:
        TypeError: ``fn`` makes the model's floating tensors non-floating (e.g. ``.to(torch.complex64)``).
    """
    new_model = apply_to_tensor_fields(fn, model)
    if not new_model.mean.is_floating_point():
        raise TypeError(f"the face model's dtype must be floating point, got {new_model.mean.dtype}")
    return new_model, apply_to_tensor_fields(fn, layout)  # the layout's weight cache starts afresh


class NormalisedFaceResult(NamedTuple):
    """What :func:`normalised_face` returns (unpacks as ``image, mask``).

    Attributes:
        image: ``(B, C, G, G)`` the normalised face, 0 where ``mask`` is 0.
        mask: ``(B, 1, G, G)`` float, 1 where the canonical point is visible in the frame.
    """

    image: Tensor
    mask: Tensor


def build_normalised_layout(
    model: FaceModel, size: int = 128, margin: float = 0.05, distance_mm: float = 2000.0,
    backend: Backend = Backend.AUTO,
) -> NormalisedFaceLayout:
    """Rasterize the model's mean shape into the canonical frontal view (module docstring).

    The mean shape (used vertices only) is placed at ``(0, -y_c, distance_mm)`` with the identity rotation,
    ``y_c`` the middle of its vertical extent; the focal length is chosen so that the projected bounding box
    fills ``(1 - 2 margin) G`` pixels along its longer side, centred in the image (the model's symmetry plane
    ``x = 0`` on the centre column). A large distance makes the view nearly orthographic.

    Args:
        model: the face model (its dtype and device are the layout's).
        size: ``G``, at least 4.
        margin: in ``[0, 0.45]``.
        distance_mm: depth of the head-frame origin, larger than the model's depth extent.
        backend: :class:`~torchface.backend.Backend` of the rasterization (the same coverage either way).

    Returns:
        :class:`NormalisedFaceLayout`.

    Raises:
        TypeError: ``model`` is not a :class:`FaceModel`, or not float32 / float64, or ``size`` is not an int.
        ValueError: a setting is out of range, or no pixel sees the face.

    Example:
        >>> from torchface.model import load_candide3
        >>> layout = build_normalised_layout(load_candide3(), size=32, margin=0.1)
        >>> layout.intrinsics.size, layout.num_pixels > 0
        ((32, 32), True)
    """
    if not isinstance(model, FaceModel):  # (a FaceTracker, as the README's example holds one: its model)
        hint = ": pass its model, tracker.model" if isinstance(getattr(model, "model", None), FaceModel) else ""
        raise TypeError(f"model must be a FaceModel, got {type(model).__name__}{hint}")
    _check_precision(model)
    size = check_int(size, "size", 4)
    # ("0.05" was taken as a number, float("x") a ValueError; distance_mm=inf passed, and its faces were empty)
    margin = check_number(margin, "margin", "[0, 0.45]", unit="a fraction of the image size")
    distance_mm = check_number(distance_mm, "distance_mm", "(0, inf)", unit="mm")
    used = model.mean[model.surface_vertex_mask]
    z_extent = float((used[:, 2].amax() - used[:, 2].amin()).abs())
    if not float(distance_mm) > float(used[:, 2].abs().amax()) + NEAR_PLANE_MM:
        raise ValueError(
            f"distance_mm must exceed the model's depth (|z| up to {float(used[:, 2].abs().amax()):.1f} mm, extent "
            f"{z_extent:.1f} mm), got {distance_mm}"
        )
    y_c = 0.5 * float(used[:, 1].amax() + used[:, 1].amin())
    translation = torch.tensor([0.0, -y_c, float(distance_mm)], dtype=model.dtype, device=model.device)
    pts = used + translation
    a = pts[:, 0] / pts[:, 2]
    b = pts[:, 1] / pts[:, 2]
    half_x = float(a.abs().amax())
    b_lo, b_hi = float(b.amin()), float(b.amax())
    span = max(2.0 * half_x, b_hi - b_lo)
    focal = (1.0 - 2.0 * float(margin)) * size / span
    centre = (size - 1) / 2.0
    cam = Intrinsics(size, size, focal, focal, centre, centre - focal * 0.5 * (b_lo + b_hi))
    verts_cam = (model.mean + translation).unsqueeze(0)
    frags = rasterize(verts_cam, model.faces, cam, cull_backfaces=True, backend=backend)
    seen = (frags.pix_to_face[0] >= 0) & (frags.facing[0] > 0)
    pixel_index = seen.reshape(-1).nonzero().squeeze(-1)
    # Mostly the triangles' backs in view (CANDIDE-3 wound inward: 18 pixels of 6866) is no face either.
    all_sides = rasterize(verts_cam, model.faces, cam, cull_backfaces=False, backend=backend)
    covered = int((all_sides.pix_to_face >= 0).sum())
    if pixel_index.numel() == 0 or pixel_index.numel() < covered // 2:
        raise ValueError(
            "no pixel of the canonical (frontal) view sees the face: the model's triangles must be wound outward and "
            "its face look toward -z in the head frame (torchface.conventions; load_mesh_model checks both), and "
            "not all be degenerate"
        )
    face_index = frags.pix_to_face[0].reshape(-1)[pixel_index]
    bary = frags.bary[0].reshape(-1, 3)[pixel_index].detach()
    return NormalisedFaceLayout(
        size=size, margin=float(margin), intrinsics=cam, translation=translation, num_faces=model.num_faces,
        pixel_index=pixel_index, face_index=face_index, bary=bary, mask=seen,
    )  # fmt: skip


def _check_visibility_settings(depth_tolerance: object, min_facing_cos: object) -> tuple[float, float]:
    """``(depth_tolerance, min_facing_cos)`` of :func:`normalised_face` and :class:`NormalisedFace`, each in its range
    (a wrong type a ``TypeError``; NaN or inf a ``ValueError``: an infinite tolerance passed ">= 0")."""
    return (check_number(depth_tolerance, "depth_tolerance", "[0, inf)", unit="a fraction of the depth"),
            check_number(min_facing_cos, "min_facing_cos", "[0, 1)"))  # fmt: skip


def _check_precision(model: FaceModel) -> None:
    """Raise ``TypeError`` unless the model (and so the resampling) is float32 or float64.

    In float16 the z-buffer test and the projections of a face at a few hundred mm lose most pixels (a frontal
    face kept 0 of 216 canonical pixels, 12 without the z-buffer) and the result would be silently empty."""
    if model.dtype not in (torch.float32, torch.float64):
        raise TypeError(
            f"the normalised face is computed in float32 or float64, the model is {model.dtype} (a .half() or "
            ".to(bfloat16) of the module?): keep the model and layout in float32 (module.float()) and cast the "
            "image, or run the network under torch.autocast, which leaves the normalised face in full precision"
        )


def _check_frame_values(frames: Tensor) -> None:
    """Refuse frames outside [0, 1] (0-255 ones: the light's bias and the dissimilarity's thresholds are in [0, 1]
    units) as the tracker's steps do: every :data:`~torchface.tracker.step.STEP_VALUE_ROW_STRIDE`-th row's values
    against :data:`~torchface.tracker.step.FRAME_VALUE_RANGE`, NaN and infinite pixels allowed (missing data, masked
    out). Not under ``torch.compile`` or a ``torch.func`` transform of the frames (no values to read)."""
    if is_compiling() or _transformed(frames):
        return
    from torchface._frame_values import STEP_VALUE_ROW_STRIDE, check_frame_values

    check_frame_values(frames, STEP_VALUE_ROW_STRIDE)


def _frame_hint(frames: Tensor) -> str:
    """The tracker's hint for refused frames (:func:`~torchface.tracker.step.check_frames`: a missing batch
    dimension, uint8 or 16-bit pixels; it said only "got (3, 240, 320)" or "got ... torch.uint8" here)."""
    from torchface.tracker.step import _frame_hint as hint  # (step imports this module)

    return hint(frames)


def _not_tensor_hint(frames: object) -> str:
    """The tracker's hint for frames that are not a tensor (a NumPy image as OpenCV reads it: it said "got ndarray")."""
    from torchface.tracker.step import not_tensor_hint as hint  # (step imports this module)

    return hint(frames)


def _check_params(name: str, x: object, count: int, batch: int, model: FaceModel) -> Tensor:
    """Validate a ``(B, count)`` parameter tensor in the model's dtype and device."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape ({batch}, {count}), got {type(x).__name__}")
    if x.dim() != 2 or tuple(x.shape) != (batch, count):
        raise ValueError(f"{name} must be (B, {count}) with B={batch} like frames, got {tuple(x.shape)}")
    if x.dtype != model.dtype or x.device != model.device:
        raise TypeError(
            f"{name} must have the model's dtype and device ({model.dtype}, {model.device}), "
            f"got ({x.dtype}, {x.device})"
        )
    return x


def _face_crop(verts_cam: Tensor, used: Tensor, intrinsics: Intrinsics) -> Intrinsics:
    """The camera of the smallest pixel window of the frame that holds every sample's projected mesh.

    A point on a triangle in front of the camera projects inside its triangle's projection, so the z-buffer
    of this window (padded by one pixel for nearest-pixel rounding) answers every visibility query of the
    frame; points projecting outside it are outside the mesh's image. The window lies inside the frame;
    when a vertex is at or behind the near plane it is the whole frame.

    Args:
        verts_cam: ``(B, V, 3)`` camera-frame vertices; used: ``(V,)`` bool, the vertices faces refer to.

    Returns:
        The intrinsics of the window (same focal lengths, shifted principal point).
    """
    pts = verts_cam[:, used]
    if pts.numel() == 0:  # an empty batch: no window to fit
        return intrinsics
    if not bool((pts[..., 2] > NEAR_PLANE_MM).all()) or not bool(torch.isfinite(pts).all()):
        return intrinsics
    px = project_points(pts, intrinsics).reshape(-1, 2)
    lo = torch.floor(px.amin(0)) - 1
    hi = torch.ceil(px.amax(0)) + 1
    x0 = int(min(max(float(lo[0]), 0.0), intrinsics.width - 1))
    y0 = int(min(max(float(lo[1]), 0.0), intrinsics.height - 1))
    x1 = int(min(max(float(hi[0]), float(x0)), intrinsics.width - 1))
    y1 = int(min(max(float(hi[1]), float(y0)), intrinsics.height - 1))
    return Intrinsics(
        x1 - x0 + 1, y1 - y0 + 1, intrinsics.fx, intrinsics.fy, intrinsics.cx - x0, intrinsics.cy - y0
    )


def _check_flags(zbuffer: object, check_values: object) -> tuple[bool, bool]:
    """``zbuffer`` and ``check_values`` as bools (check_bool: ``zbuffer="no"`` was taken as true, and
    ``check_values="no"`` too, where ``0`` skipped the frames' check)."""
    return check_bool(zbuffer, "zbuffer"), check_bool(check_values, "check_values")


@full_precision
def normalised_face(
    frames: Tensor,
    model: FaceModel,
    layout: NormalisedFaceLayout,
    shape_coeffs: Tensor,
    anim_coeffs: Tensor,
    axis_angle: Tensor,
    translation: Tensor,
    illumination: Tensor | None,
    intrinsics: Intrinsics,
    *,
    depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE,
    min_facing_cos: float = DEFAULT_MIN_FACING_COS,
    zbuffer: bool = True,
    rotation: Tensor | None = None,
    backend: Backend = Backend.AUTO,
    check_values: bool = True,
) -> NormalisedFaceResult:
    """The frontal, neutral-expression, light-normalised face of each frame (module docstring).

    Args:
        frames: ``(B, C, H, W)`` float images in ``[0, 1]`` (any ``C``; cast to the model's dtype; NaN pixels are
            missing data; values outside :data:`~torchface.tracker.step.FRAME_VALUE_RANGE`, as 0-255 frames have,
            are refused like the tracker's steps refuse them, every 16th row looked at).
        model: the face model the parameters belong to.
        layout: from :func:`build_normalised_layout` for this model (same triangles, dtype and device).
        shape_coeffs: ``(B, S)`` the person's shape coefficients ``sigma``.
        anim_coeffs: ``(B, A)`` the frame's animation coefficients ``alpha`` (undone in the output).
        axis_angle: ``(B, 3)`` head -> camera rotation (radians).
        translation: ``(B, 3)`` head origin in the camera frame (mm).
        illumination: ``(B, L)`` illumination parameters ``[gain, bias, lx, ly, lz]`` of Eq. 19 (undone in
            the output), or ``None`` to keep the frame's light.
        intrinsics: camera of ``frames``.
        depth_tolerance: relative depth gap allowed by the z-buffer test
            (:func:`~torchface.rendering.visibility.points_visible`).
        min_facing_cos: minimum cosine between a point's normal and its ray toward the camera; in ``[0, 1)``.
        zbuffer: test visibility against the z-buffer of the posed mesh. False keeps only the facing tests
            (back-facing triangles and ``min_facing_cos``): about 3x faster (no rasterization), and a part of the
            face hidden behind another (the far cheek behind the nose at a large yaw) is then kept.
        rotation: ``(B, 3, 3)`` the matrix of ``axis_angle`` when the caller has it (not checked against it), or
            None to compute it.
        check_values: refuse frames outside [0, 1] (above); False where the caller has checked them (template
            management: the tracker's step did), which saves a look at the frames (a device sync on a GPU).

    Returns:
        :class:`NormalisedFaceResult` ``(image (B, C, G, G), mask (B, 1, G, G))`` in the model's dtype. A sample
        with a non-finite ``shape_coeffs``, ``anim_coeffs``, ``axis_angle``, ``translation`` or ``rotation`` entry
        has image and mask 0, and those parameters of it get gradient 0. ``B = 0`` gives empty tensors.

    Raises:
        TypeError: an argument has the wrong type, a parameter tensor is not in the model's dtype/device, or the
            model is not float32 / float64 (float16 would lose most of the face without a sign).
        ValueError: a shape does not match (the messages say what was expected and what arrived), or the frames'
            values are not in [0, 1] (0-255 frames: divide them by 255).

    Example:
        >>> from torchface.model import load_candide3
        >>> model = load_candide3()
        >>> layout = build_normalised_layout(model, size=32)
        >>> cam = Intrinsics.default(64, 48)
        >>> out = normalised_face(torch.rand(2, 3, 48, 64), model, layout, torch.zeros(2, model.num_shape),
        ...                       torch.zeros(2, model.num_animation), torch.zeros(2, 3),
        ...                       torch.tensor([[0.0, 0.0, 600.0]]).expand(2, 3), None, cam)
        >>> out.image.shape, out.mask.shape
        (torch.Size([2, 3, 32, 32]), torch.Size([2, 1, 32, 32]))
    """
    if not isinstance(model, FaceModel):
        raise TypeError(f"model must be a FaceModel, got {type(model).__name__}")
    if not isinstance(layout, NormalisedFaceLayout):
        raise TypeError(f"layout must be a NormalisedFaceLayout, got {type(layout).__name__}")
    _check_precision(model)
    zbuffer, check_values = _check_flags(zbuffer, check_values)
    if not isinstance(intrinsics, Intrinsics):
        raise TypeError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if not isinstance(frames, Tensor):
        raise TypeError(f"frames must be a torch.Tensor, got {type(frames).__name__}{_not_tensor_hint(frames)}")
    check_holds_data(frames, "frames")
    if frames.dim() != 4 or not frames.is_floating_point():
        raise ValueError(f"frames must be (B, C, H, W) float in [0, 1], got {tuple(frames.shape)} {frames.dtype}"
                         f"{_frame_hint(frames)}")  # fmt: skip
    if tuple(frames.shape[-2:]) != intrinsics.size:
        # channels-last frames (B, H, W, C) were told their size alone ("got 3x320"), not how to make them (B, C, H, W)
        channels_last = frames.shape[1] not in (1, 3, 4) and frames.shape[-1] in (1, 3, 4)
        raise ValueError(
            f"frames must be {intrinsics.width}x{intrinsics.height} (W x H, the intrinsics' size), got "
            f"{frames.shape[-1]}x{frames.shape[-2]}{_frame_hint(frames) if channels_last else ''}"
        )
    if layout.num_faces != model.num_faces:
        raise ValueError(
            f"layout was built for a model with {layout.num_faces} triangles, this one has {model.num_faces}"
        )
    if layout.face_index.device != model.device:
        raise ValueError(f"layout must be on the model's device {model.device}, got {layout.face_index.device}")
    depth_tolerance, min_facing_cos = _check_visibility_settings(depth_tolerance, min_facing_cos)  # (numbers: a
    # 0-d tensor's too)
    B, C = frames.shape[:2]
    _check_params("shape_coeffs", shape_coeffs, model.num_shape, B, model)
    _check_params("anim_coeffs", anim_coeffs, model.num_animation, B, model)
    _check_params("axis_angle", axis_angle, 3, B, model)
    _check_params("translation", translation, 3, B, model)
    if illumination is not None:
        _check_params("illumination", illumination, NUM_ILLUMINATION_TERMS, B, model)
    if rotation is not None and (not isinstance(rotation, Tensor) or tuple(rotation.shape) != (B, 3, 3)):
        got = tuple(rotation.shape) if isinstance(rotation, Tensor) else type(rotation).__name__
        raise ValueError(f"rotation must be ({B}, 3, 3) like frames, got {got}")
    if check_values:
        _check_frame_values(frames)
    frames = frames.to(dtype=model.dtype, device=model.device)

    # A sample with a non-finite geometry parameter is posed at the layout's canonical pose instead (finite
    # everywhere, so no NaN reaches the sampling or the backward pass) and masked out; torch.where gives its
    # parameters gradient 0 where a product with 0 would give NaN.
    geometry = [shape_coeffs, anim_coeffs, axis_angle, translation]
    if rotation is not None:
        geometry.append(rotation.flatten(1))
    valid = torch.stack([torch.isfinite(x).all(1) for x in geometry]).all(0)  # (B,)
    if not bool(valid.all()):
        ok = valid.unsqueeze(1)
        shape_coeffs = torch.where(ok, shape_coeffs, 0.0)
        anim_coeffs = torch.where(ok, anim_coeffs, 0.0)
        axis_angle = torch.where(ok, axis_angle, 0.0)
        translation = torch.where(ok, translation, layout.translation.to(translation))
        if rotation is not None:
            eye = torch.eye(3, dtype=rotation.dtype, device=rotation.device)
            rotation = torch.where(ok.unsqueeze(2), rotation, eye)

    # Eq. 1 and 14: the person's mesh at the frame's expression and pose.
    verts = model.deform(shape_coeffs, anim_coeffs)  # (B, V, 3)
    if rotation is None:
        rotation = axis_angle_to_matrix(axis_angle)
    verts_cam = transform_points(rotation, translation, verts)
    return _normalised_face_posed(
        frames, model, layout, verts_cam, illumination, intrinsics, depth_tolerance, min_facing_cos, zbuffer,
        backend, valid,
    )  # fmt: skip


@full_precision
def normalised_face_posed(
    frames: Tensor,
    model: FaceModel,
    layout: NormalisedFaceLayout,
    verts_cam: Tensor,
    illumination: Tensor | None,
    intrinsics: Intrinsics,
    *,
    depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE,
    min_facing_cos: float = DEFAULT_MIN_FACING_COS,
    zbuffer: bool = True,
    backend: Backend = Backend.AUTO,
    check_values: bool = True,
) -> NormalisedFaceResult:
    """:func:`normalised_face` of a mesh already posed: ``verts_cam (B, V, 3)``, the model's vertices at the
    frame's shape, expression and pose in the camera frame (mm), e.g. shared with other per-frame work. Only the
    shapes and dtypes of ``frames``, ``verts_cam`` and ``illumination`` and (unless ``check_values`` is False) the
    frames' value range are checked here (:func:`normalised_face` documents and checks the rest).
    Without the z-buffer test (``zbuffer=False``, as template management makes it every frame) and without
    gradients (nor a ``torch.func`` transform or forward AD), :class:`~torchface.backend.Backend` ``AUTO`` samples
    with the native kernel (run eagerly under ``torch.compile``)
    (``torchface/_native/normalised_face.h``: each pixel from its triangle's three corners); the values are the
    torch code's to rounding. A sample with a non-finite vertex has image and mask 0 (and gradient 0).

    The frames are cast to ``verts_cam``'s dtype (float16 or bfloat16 frames were sampled in their own precision:
    images off by up to 1e38).

    Raises:
        TypeError: ``frames`` is not a tensor, the model or ``verts_cam`` is not float32 / float64, or
            ``illumination`` is not in ``verts_cam``'s dtype and device (it was "expected scalar type Float but
            found Double" from inside the sampling).
        ValueError: ``frames`` is not ``(B, C, H, W)`` float or ``verts_cam`` not ``(B, V, 3)`` for the model's
            ``V``, ``illumination`` is not ``(B, L)``, or the frames' values are not in [0, 1] (as
            :func:`normalised_face`).
    """
    _check_precision(model)
    zbuffer, check_values = _check_flags(zbuffer, check_values)
    if not isinstance(frames, Tensor):  # (a numpy array's message named its shape, the right one, as the wrong one)
        raise TypeError(f"frames must be a torch.Tensor (B, C, H, W), got {type(frames).__name__}"
                        f"{_not_tensor_hint(frames)}")  # fmt: skip
    B, C = frames.shape[:2] if frames.dim() == 4 else (-1, -1)
    want = (B, model.num_vertices, 3)
    if B < 0 or not isinstance(verts_cam, Tensor) or tuple(verts_cam.shape) != want:
        got = tuple(verts_cam.shape) if isinstance(verts_cam, Tensor) else type(verts_cam).__name__
        raise ValueError(f"frames must be (B, C, H, W) and verts_cam (B, {model.num_vertices}, 3) with the same B, "
                         f"got frames {tuple(getattr(frames, 'shape', ()))} and verts_cam {got}")  # fmt: skip
    if not frames.is_floating_point():
        raise ValueError(f"frames must be (B, C, H, W) float in [0, 1], got {tuple(frames.shape)} {frames.dtype}"
                         f"{_frame_hint(frames)}")  # fmt: skip
    if verts_cam.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"verts_cam must be float32 or float64, got {verts_cam.dtype}")
    if illumination is not None:
        if not isinstance(illumination, Tensor) or tuple(illumination.shape) != (B, NUM_ILLUMINATION_TERMS):
            got = tuple(illumination.shape) if isinstance(illumination, Tensor) else type(illumination).__name__
            raise ValueError(f"illumination must be (B, {NUM_ILLUMINATION_TERMS}) with B={B} like frames, got {got}")
        if (illumination.dtype, illumination.device) != (verts_cam.dtype, verts_cam.device):
            raise TypeError(f"illumination must have verts_cam's dtype and device ({verts_cam.dtype}, "
                            f"{verts_cam.device}), got ({illumination.dtype}, {illumination.device})")  # fmt: skip
    if check_values:
        _check_frame_values(frames)
    frames = frames.to(dtype=verts_cam.dtype, device=verts_cam.device)
    return _normalised_face_posed(
        frames, model, layout, verts_cam, illumination, intrinsics, depth_tolerance, min_facing_cos, zbuffer,
        backend, None,
    )  # fmt: skip


def _transformed(*tensors: Tensor | None) -> bool:
    """Whether a tensor is wrapped by a ``torch.func`` transform (``grad``, ``jacrev``, ``jacfwd``, ``vmap``) or forward
    AD is active: the native kernels read the tensors' memory, which such tensors do not have ("Cannot access data
    pointer of Tensor that doesn't have storage"), and would drop their tangents."""
    if torch.autograd.forward_ad._current_level >= 0:
        return True
    return any(x is not None and torch._C._functorch.is_functorch_wrapped_tensor(x) for x in tensors)


def _normalised_face_posed(
    frames: Tensor, model: FaceModel, layout: NormalisedFaceLayout, verts_cam: Tensor, illumination: Tensor | None,
    intrinsics: Intrinsics, depth_tolerance: float, min_facing_cos: float, zbuffer: bool, backend: Backend,
    valid: Tensor | None,
) -> NormalisedFaceResult:
    """:func:`normalised_face_posed` after its checks; ``valid (B,)`` bool, or None, marks the samples whose
    parameters were finite (the others are masked out like a sample with a non-finite vertex)."""
    B, C = frames.shape[:2]
    finite = torch.isfinite(verts_cam).flatten(1).all(1)  # (B,)
    valid = finite if valid is None else valid & finite
    all_valid = bool(valid.all())
    if not all_valid:  # the canonical pose's mesh in their place: finite everywhere, masked out below
        canonical = model.mean.to(verts_cam) + layout.translation.to(verts_cam)
        verts_cam = torch.where(valid[:, None, None], verts_cam, canonical)
    normals_cam, back = vertex_normals_and_backfacing(verts_cam, model.faces)
    if (not zbuffer and use_native(backend, (frames, verts_cam, illumination), "normalised face")
            and not _transformed(frames, verts_cam, illumination)):
        # (Not under torch.compile, use_native: traced, its ctypes call got the pointers of the traced tensors, not
        # of the call's, and gave wrong faces without a sign.)
        out = _normalised_face_native(frames, model, layout, verts_cam, normals_cam, back, illumination, intrinsics,
                                      min_facing_cos)  # fmt: skip
        if all_valid:
            return out
        keep = valid[:, None, None, None]
        return NormalisedFaceResult(torch.where(keep, out.image, 0.0), torch.where(keep, out.mask, 0.0))
    if backend is Backend.NATIVE and zbuffer:
        raise RuntimeError("the native normalised face has no z-buffer test: pass zbuffer=False")

    # Eq. 3-9: each canonical pixel's surface point is a fixed barycentric combination of its triangle: positions
    # and normals interpolated by one product with the layout's (M, V) weights, the batch's vertices side by side
    # (B = 32: 2.7 against 12 ms for gathering the corners and summing them).
    V = model.num_vertices
    weights = layout.vertex_weights(model.faces, V, verts_cam.dtype)
    both = torch.cat([verts_cam, normals_cam], -1).transpose(0, 1).reshape(V, B * 6)
    at = torch.mm(weights, both).reshape(weights.shape[0], B, 6).transpose(0, 1).contiguous()  # (B, M, 6)
    points_cam = at[..., :3]
    normals = torch.nn.functional.normalize(at[..., 3:], dim=-1)

    # Eq. 15 and bilinear sampling at the projections.
    points_px = project_points(points_cam, intrinsics)
    values, inside = sample_at_pixels(frames, points_px)  # (B, M, C), (B, M)
    missing = None
    light_grad = illumination is not None and illumination.requires_grad
    if torch.is_grad_enabled() and (points_px.requires_grad or light_grad):
        if not bool(torch.isfinite(frames).all()):
            # A NaN (missing) frame pixel is masked out, but the sampling's and the light's backward multiply its
            # zero incoming gradient by it: NaN pose and light gradients. Sample a copy with 0 there for the values
            # and the gradients (the same at every kept pixel: none of its neighbours is missing).
            missing = ~torch.isfinite(values.detach()).all(-1)  # (B, M)
            values, _ = sample_at_pixels(torch.nan_to_num(frames, nan=0.0, posinf=0.0, neginf=0.0), points_px)

    with torch.no_grad():
        visible = points_cam.detach()[..., 2] > NEAR_PLANE_MM
        if zbuffer:
            # The torch z-buffer (the same fragments) under torch.compile, where the traced native kernel crashed the
            # process, and under torch.func's transforms, where it could not read the wrapped tensors; the whole frame
            # under torch.compile (a window of the face's size would recompile at each new size).
            compiling = is_compiling()
            crop = intrinsics if compiling else _face_crop(verts_cam.detach(), model.surface_vertex_mask, intrinsics)
            raster_backend = Backend.TORCH if compiling or _transformed(verts_cam) else backend
            if raster_backend is Backend.TORCH:
                frags: Fragments | Coverage = rasterize(verts_cam.detach(), model.faces, crop, backend=raster_backend)
            else:
                # The coverage alone, the depth evaluated at the layout's points' pixels only (natively): the same
                # answer as every covered pixel's fragments, evaluated in torch (with the visibility test, in
                # `torchface track`: 3.5 -> 1.1 ms of CPU a 640x480 frame, 10.5 -> 2.3 at 1080p).
                frags = rasterize_coverage(verts_cam.detach(), model.faces, crop, backend=raster_backend)
            visible = points_visible(points_cam, layout.face_index, frags, crop, depth_tolerance=depth_tolerance,
                                     backend=raster_backend)  # fmt: skip
        front = ~back.detach().index_select(1, layout.face_index)  # (B, M)
        ray = torch.nn.functional.normalize(points_cam.detach(), dim=-1)
        facing_cos = -(normals.detach() * ray).sum(-1)
        keep = visible & inside & front & (facing_cos >= min_facing_cos) & valid.unsqueeze(1)

    observed = values.transpose(1, 2)  # (B, C, M)
    if illumination is not None:
        observed = remove_illumination(observed, normals, illumination)
    keep = keep & torch.isfinite(observed.detach()).all(1)  # a NaN (missing) frame pixel is not seen
    if missing is not None:
        keep = keep & ~missing
    keep_f = keep.to(observed.dtype).unsqueeze(1)  # (B, 1, M)
    G = layout.size
    # torch.where, not a product with the mask: 0 (value and gradient) where the mask is 0, even where the
    # frame or the light made the sample NaN.
    kept = torch.where(keep.unsqueeze(1), observed, 0.0)
    image = observed.new_zeros(B, C, G * G).index_copy(2, layout.pixel_index, kept)
    mask = keep_f.new_zeros(B, 1, G * G).index_copy(2, layout.pixel_index, keep_f)
    return NormalisedFaceResult(image.reshape(B, C, G, G), mask.reshape(B, 1, G, G))


def _normalised_face_native(
    frames: Tensor, model: FaceModel, layout: NormalisedFaceLayout, verts_cam: Tensor, normals_cam: Tensor,
    back: Tensor, illumination: Tensor | None, intrinsics: Intrinsics, min_facing_cos: float,
) -> NormalisedFaceResult:
    """:func:`normalised_face_posed` without the z-buffer by the native kernel (its arguments, and the posed mesh's
    unit vertex normals ``(B, V, 3)`` and back-facing triangles ``(B, F)``)."""
    from torchface import _native

    B, C, H, W = frames.shape
    dtype = verts_cam.dtype
    G = layout.size
    cam = check_intrinsics(intrinsics)
    faces = model.faces.to(torch.int64).contiguous()
    face_index, pixel_index = layout.face_index.contiguous(), layout.pixel_index.contiguous()
    bary = layout.bary.to(dtype).contiguous()
    frames_c, verts_c, normals_c = frames.contiguous(), verts_cam.contiguous(), normals_cam.to(dtype).contiguous()
    back_c = back.contiguous()
    light = None if illumination is None else illumination.to(dtype).contiguous()
    image = torch.zeros(B, C, G * G, dtype=dtype)
    mask = torch.zeros(B, 1, G * G, dtype=dtype)
    prob = _native.FaceProblem(
        B=B, V=verts_cam.shape[1], F=faces.shape[0], M=face_index.shape[0], C=C, G=G, height=H, width=W,
        fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, min_facing_cos=float(min_facing_cos), min_gain=0.05,
        depth_eps=torch.finfo(dtype).eps, verts=verts_c.data_ptr(), normals=normals_c.data_ptr(),
        back=back_c.data_ptr(), faces=faces.data_ptr(), face_index=face_index.data_ptr(),
        pixel_index=pixel_index.data_ptr(), bary=bary.data_ptr(), frames=frames_c.data_ptr(),
        illumination=None if light is None else light.data_ptr(), out_image=image.data_ptr(),
        out_mask=mask.data_ptr(),
    )  # fmt: skip
    _native.run("normalised_face", dtype == torch.float64, prob, B, torch.get_num_threads())
    return NormalisedFaceResult(image.reshape(B, C, G, G), mask.reshape(B, 1, G, G))


class NormalisedFace(DeviceCheckedModule):
    """Thin module holding a model and its canonical layout; calls :func:`normalised_face`.

    Args:
        model: the face model (the tracker's).
        size: ``G``, the output is ``G x G``.
        margin: see :func:`build_normalised_layout`.
        distance_mm: see :func:`build_normalised_layout`.
        depth_tolerance: see :func:`normalised_face`.
        min_facing_cos: see :func:`normalised_face`.
        keep_expression: resample a :class:`~torchface.tracker.TrackerState`'s frames at the person's neutral
            expression (:meth:`~torchface.tracker.TrackerState.neutral_anim_coeffs`, the first frame's fitted
            coefficients) instead of the tracked one, so the face keeps its expression with pose and light undone
            (the resampling of ``torchface track --keep-expression``, ``training_hooks``'
            ``FaceTrackingConfig(keep_expression=True)`` and ``LayerConfig(keep_expression=True)``): what an
            expression classifier needs. False (the default) undoes the expression too (paper Section 4). A
            :class:`~torchface.tracker.TrackResult` holds no neutral: with it, a ValueError (pass the state).
            :meth:`from_params` resamples at the ``anim_coeffs`` it is given either way.

    The faces are float images of the model's dtype, 0 where the mask is 0, and not clamped (the light
    normalisation can put a few values a little outside ``[0, 1]``; clamping would zero their gradient w.r.t. the
    frames): ``training_hooks``' datasets store them clamped to ``[0, 1]`` and rounded to ``1 / 255`` by default
    (``FaceStorage.UINT8``), and ``image.clamp(0, 1)`` is what a network trained on those items expects.

    Example:
        >>> from torchface.model import load_candide3
        >>> normaliser = NormalisedFace(load_candide3(), size=64)
        >>> # image, mask = normaliser(frames, tracker.state)                  # a TrackerState (preferred), or
        >>> # image, mask = normaliser(frames, result, shape_coeffs, intrinsics)  # a TrackResult without re-anchoring
        >>> # NormalisedFace(tracker.model, keep_expression=True)(frames, tracker.state)  # the expression kept
    """

    def __init__(
        self,
        model: FaceModel,
        size: int = 128,
        margin: float = 0.05,
        distance_mm: float = 2000.0,
        depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE,
        min_facing_cos: float = DEFAULT_MIN_FACING_COS,
        *,
        keep_expression: bool = False,
    ) -> None:
        super().__init__()
        self.model = model
        self.layout = build_normalised_layout(model, size, margin, distance_mm)
        # (checked by normalised_face too, but only at the first call; "5" was taken by float())
        tolerance, facing = _check_visibility_settings(depth_tolerance, min_facing_cos)
        self.depth_tolerance, self.min_facing_cos = float(tolerance), float(facing)
        self.keep_expression = check_bool(keep_expression, "keep_expression")

    def __setattr__(self, name: str, value: Any) -> None:
        """Attribute assignment, ``keep_expression``, ``depth_tolerance`` and ``min_facing_cos`` checked as the
        constructor checks them (as :class:`~torchface.tracker.FaceTracker` checks its settings): set after
        construction they were taken as given, ``keep_expression = "no"`` keeping the expression, a tolerance of
        ``"5"`` failing at the next call. A refused value leaves the setting as it was."""
        if name == "keep_expression":
            value = check_bool(value, name)
        elif name == "depth_tolerance":
            value = float(_check_visibility_settings(value, DEFAULT_MIN_FACING_COS)[0])
        elif name == "min_facing_cos":
            value = float(_check_visibility_settings(0.0, value)[1])
        super().__setattr__(name, value)

    def _apply(self, fn: Callable[[Tensor], Tensor], recurse: bool = True) -> "NormalisedFace":
        """Move the face model and the layout with the module (``.to``, ``.double``, ``.float``, ``.cuda``, ...)."""
        self.model, self.layout = apply_to_model_and_layout(fn, self.model, self.layout)
        return super()._apply(fn, recurse)

    def forward(
        self,
        frames: Tensor,
        estimate: "TrackResult | TrackerState",
        shape_coeffs: Tensor | None = None,
        intrinsics: Intrinsics | None = None,
    ) -> NormalisedFaceResult:
        """Normalise ``(B, C, H, W)`` frames with a tracker estimate.

        Args:
            frames: ``(B, C, H, W)`` the frames the estimate belongs to.
            estimate: a :class:`~torchface.tracker.TrackerState` (its parameters, shape coefficients and
                intrinsics are used; leave ``shape_coeffs`` and ``intrinsics`` as ``None``) or a
                :class:`~torchface.tracker.TrackResult` (pose, expression, illumination; then
                ``shape_coeffs (B, S)`` is required and ``intrinsics`` defaults to
                :meth:`Intrinsics.default` of the frame size). Prefer the state: once a
                :class:`~torchface.tracker.FaceTracker`'s online start has re-anchored a stream (its default),
                a result's pose is reported in the head frame of the first result
                (:attr:`~torchface.tracker.TrackResult.rotation`) and, with the state's shape coefficients, places
                the mesh off the face (1.5 degrees and 4 mm on a rendered head turn).
            shape_coeffs: ``(B, S)`` with a TrackResult.
            intrinsics: camera of ``frames`` with a TrackResult.

        Returns:
            :class:`NormalisedFaceResult` ``(image (B, C, G, G), mask (B, 1, G, G))``; with ``keep_expression``, the
            expression kept (constructor).

        Raises:
            ValueError: ``keep_expression`` with a TrackResult (it holds no neutral expression: pass the state).
        """
        from torchface.tracker.module import FaceTracker
        from torchface.tracker.params import ParamLayout
        from torchface.tracker.step import TrackerState, TrackResult

        if isinstance(estimate, TrackerState):
            if shape_coeffs is not None or intrinsics is not None:
                raise ValueError("with a TrackerState, shape_coeffs and intrinsics come from the state: pass None")
            layout = ParamLayout(self.model.num_animation, NUM_ILLUMINATION_TERMS)
            if estimate.params.dim() != 2 or estimate.params.shape[1] != layout.size:
                raise ValueError(f"state.params must be (B, {layout.size}), got {tuple(estimate.params.shape)}")
            B = estimate.params.shape[0]
            if isinstance(frames, Tensor) and frames.dim() == 4 and frames.shape[0] != B:
                # (was "shape_coeffs must be (B, 14) with B=1 like frames, got (2, 14)": a tensor never passed)
                raise ValueError(f"expected {B} frames (one per stream of the state), got {frames.shape[0]}")
            kept = (estimate.shape_coeffs.dtype, estimate.shape_coeffs.device)
            if kept != (self.model.dtype, self.model.device):  # (was "shape_coeffs must have the model's dtype ...")
                raise TypeError(f"the state is {kept[0]} on {kept[1]}, this normaliser's model {self.model.dtype} on "
                                f"{self.model.device}: move one of them (normaliser.to(...))")  # fmt: skip
            aa, t, alpha, light = layout.split(estimate.params)
            if self.keep_expression:  # the person's neutral, as NormalisedFaceLayer and torchface track resample at
                alpha = estimate.neutral_anim_coeffs(alpha)
            return self.from_params(frames, estimate.shape_coeffs, alpha, aa, t, light, estimate.intrinsics)
        if isinstance(estimate, TrackResult):
            if self.keep_expression:  # (its expression is measured from the neutral, which it does not hold)
                raise ValueError(
                    "keep_expression resamples at the person's neutral expression, which a TrackResult does not hold: "
                    "pass the tracker's state, normaliser(frames, tracker.state)"
                )
            if shape_coeffs is None:
                raise ValueError(
                    "with a TrackResult, shape_coeffs (B, S) is required; pass tracker.state instead of the result "
                    "(after the online start re-anchors, a result's pose is in its first result's head frame)"
                )
            if intrinsics is None:
                if not isinstance(frames, Tensor):  # a numpy array was "must be (B, C, H, W), got (B, C, H, W)"
                    raise TypeError(f"frames must be a torch.Tensor (B, C, H, W), got {type(frames).__name__}"
                                    f"{_not_tensor_hint(frames)}")  # fmt: skip
                if frames.dim() != 4:
                    raise ValueError(f"frames must be (B, C, H, W), got {tuple(frames.shape)}")
                intrinsics = Intrinsics.default(frames.shape[-1], frames.shape[-2])
            return self.from_params(
                frames, shape_coeffs, estimate.anim_coeffs, estimate.axis_angle, estimate.translation,
                estimate.illumination, intrinsics,
            )  # fmt: skip
        # (tracker.state before initialise, and the arguments swapped, were told the type alone)
        # (the tracker itself, for its state: told the type alone)
        hint = (": tracker.state is None until tracker.initialise(...)" if estimate is None
                else ": the frames come first, normaliser(frames, tracker.state)" if isinstance(estimate, Tensor)
                and isinstance(frames, (TrackResult, TrackerState))
                else ": pass its state, normaliser(frames, tracker.state)" if isinstance(estimate, FaceTracker)
                else "")  # fmt: skip
        raise TypeError(f"estimate must be a TrackResult or a TrackerState, got {type(estimate).__name__}{hint}")

    def from_params(
        self,
        frames: Tensor,
        shape_coeffs: Tensor,
        anim_coeffs: Tensor,
        axis_angle: Tensor,
        translation: Tensor,
        illumination: Tensor | None,
        intrinsics: Intrinsics,
    ) -> NormalisedFaceResult:
        """:func:`normalised_face` with explicit parameter tensors and this module's model and layout."""
        return normalised_face(
            frames, self.model, self.layout, shape_coeffs, anim_coeffs, axis_angle, translation, illumination,
            intrinsics, depth_tolerance=self.depth_tolerance, min_facing_cos=self.min_facing_cos,
        )  # fmt: skip
