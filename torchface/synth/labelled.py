"""Labelled expression clips for learning pipelines: expression classes, more faces, one-clip rendering.

Expression classes (:data:`EXPRESSION_AUS`) are prototypes over CANDIDE-3's animation units (AUVs, linked to
FACS action units in ``data/candide3_auv_facs.csv``): neutral, smile (lip stretcher AU20 with the lip-corner
depressor AU13/15 reversed, corners up), surprise (outer brow raiser AU2, upper lid raiser AU5, jaw drop AU26),
anger (brow lowerer AU4, lid tightener AU7, lip presser AU23/24) and mouth open (jaw drop alone).

Faces (:class:`~torchface.synth.subjects.Subject`) beyond the packaged ones:

* :func:`grid_photo`: frame 0 of the packaged GRID clip with its 68 packaged landmarks, a third photograph to
  texture CANDIDE-3 with (:func:`photo_subject`, the mapping of
  :func:`~torchface.synth.subjects.candide_photo_mapping` computed on first use);
* :func:`animated_scan_subject`: the James scan with CANDIDE-3's animation units transferred to it, so the scan
  can make the same expressions. CANDIDE-3's shape units are fitted to the scan's 68 3D landmarks (linear least
  squares, ridge prior; the scan's head frame is already CANDIDE-3's); each scan vertex then takes the
  animation-unit displacements of the CANDIDE-3 surface point in front of or behind it in the frontal view
  (closest in ``x, y``: the barycentric interpolation of its triangle's displacements, the point model of paper
  Eq. 3-9), weighted down to 0 with the distance outside CANDIDE-3's frontal outline (:data:`TRANSFER_XY_MM`)
  and with the depth behind its surface (:data:`TRANSFER_DEPTH_MM`), so ears, scalp and the back of the head
  stay still. (The closest point in 3D would miss the chin: CANDIDE-3's jaw line lies 15-40 mm in front of the
  scan's.)
* :func:`identity_variant`: another identity from a subject: other shape units, a texture colour gain.

:func:`render_clip` renders one :class:`ClipSpec`: a frontal, neutral first frame under the default light (its
ground-truth landmarks initialise a tracker), then frames moving (eased, ``s^2 (3 - 2 s)``, or by equal steps) to the
target pose, expression and light; the labelled frame is the last. Conventions of :mod:`torchface.conventions`.
"""

from __future__ import annotations

import csv
import functools
import math
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchface.geometry._checks import check_bool, check_int, check_number, check_reals
from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import project_points
from torchface.geometry.so3 import euler_to_matrix
from torchface.geometry.transforms import transform_points
from torchface.rendering.shading import LightState, render
from torchface.synth.background import BackgroundSpec, background_frames
from torchface.synth.james import closest_points_on_triangles
from torchface.synth.subjects import Photo, Subject, candide_photo_mapping, candide_subject, james_subject

__all__ = [
    "EXPRESSION_CLASSES",
    "EXPRESSION_AUS",
    "TRANSFER_XY_MM",
    "TRANSFER_DEPTH_MM",
    "expression_coeffs",
    "grid_photo",
    "photo_subject",
    "animated_scan_subject",
    "identity_variant",
    "ClipSpec",
    "clip_landmarks",
    "render_clip",
]

#: Expression class names, in label order.
EXPRESSION_CLASSES: tuple[str, ...] = ("neutral", "smile", "surprise", "anger", "mouth_open")

#: Class -> animation-unit values (names as in CANDIDE-3's file, without the ``AUVn`` prefix).
EXPRESSION_AUS: dict[str, dict[str, float]] = {
    "neutral": {},
    "smile": {"Lip stretcher": 0.8, "Lip corner depressor": -1.0, "Upper lip raiser": 0.3},
    "surprise": {"Outer brow raiser": 1.0, "Upper lid raiser": 0.8, "Jaw drop": 0.6},
    "anger": {"Brow lowerer": 1.0, "Lid tightener": 0.8, "Lip presser": 0.8},
    "mouth_open": {"Jaw drop": 1.2},
}

#: Scan vertices within the first distance (mm, frontal view) of CANDIDE-3's outline take its animation units
#: fully, beyond the second not at all (linear in between).
TRANSFER_XY_MM: tuple[float, float] = (10.0, 30.0)
#: The same for the depth of a scan vertex behind the CANDIDE-3 surface point in front of it (mm).
TRANSFER_DEPTH_MM: tuple[float, float] = (15.0, 40.0)
#: Ridge prior of the shape-unit fit to the scan's landmarks (per squared unit; landmark errors in mm).
TRANSFER_SHAPE_PRIOR: float = 10.0


def _unit_index(names: tuple[str, ...], unit: str) -> int:
    hits = [i for i, n in enumerate(names) if n.split(" ", 1)[-1].lower() == unit.lower()]
    if len(hits) != 1:
        raise ValueError(f"expected one animation unit named {unit!r} in {names}, got {len(hits)}")
    return hits[0]


def expression_coeffs(names: tuple[str, ...], expression: str, intensity: float = 1.0) -> Tensor:
    """``(A,)`` float64 animation-unit values of ``expression`` scaled by ``intensity``.

    Args:
        names: the subject's animation-unit names (``"AUV11 Jaw drop"`` style).
        expression: one of :data:`EXPRESSION_CLASSES`.
        intensity: scale of the prototype.

    Example:
        >>> from torchface.model import load_candide3
        >>> a = expression_coeffs(load_candide3().animation_names, "mouth_open", 0.5)
        >>> float(a.abs().sum())
        0.6
    """
    if expression not in EXPRESSION_AUS:
        raise ValueError(f"expression must be one of {EXPRESSION_CLASSES}, got {expression!r}")
    out = torch.zeros(len(names), dtype=torch.float64)
    for unit, value in EXPRESSION_AUS[expression].items():
        out[_unit_index(names, unit)] = value * float(intensity)
    return out


def _data_path(*parts: str) -> Path:
    return Path(str(resources.files("torchface").joinpath("data", *parts)))


@functools.lru_cache(maxsize=1)
def grid_photo() -> Photo:
    """Frame 0 of the packaged GRID clip ``bbaf2n.mpg`` and its 68 packaged (dlib) landmarks, as a photograph.

    The camera is a guess like the astronaut portrait's (focal length 3x the width, nearly orthographic).
    """
    from torchface.io.video import open_capture

    video = _data_path("grid", "bbaf2n.mpg")
    cap = open_capture(video, FileNotFoundError)
    ok, bgr = cap.read()
    cap.release()
    if not ok:
        raise FileNotFoundError(f"could not read frame 0 of the packaged clip {video}")
    image = torch.from_numpy(np.ascontiguousarray(bgr[:, :, ::-1])).permute(2, 0, 1).float().div(255.0)
    with open(_data_path("grid", "bbaf2n_landmarks68.csv"), newline="") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    points = torch.tensor([(float(r["x"]), float(r["y"])) for r in rows], dtype=torch.float64)
    if points.shape != (68, 2):
        raise ValueError(f"expected 68 landmarks for the GRID clip, got {tuple(points.shape)}")
    h, w = image.shape[1:]
    cam = Intrinsics(w, h, 3.0 * w, 3.0 * w, (w - 1) / 2.0, (h - 1) / 2.0)
    return Photo("grid", image.contiguous(), points, torch.arange(68), cam)


def photo_subject(photo: Photo) -> Subject:
    """CANDIDE-3 textured from any frontal :class:`~torchface.synth.subjects.Photo` (fitted now, ~1 s).

    Like :func:`~torchface.synth.subjects.candide_subject` (whose mappings are precomputed) with the mapping
    of :func:`~torchface.synth.subjects.candide_photo_mapping`; the fitted shape units are the identity.
    """
    base = candide_subject("james")
    uv, shape, _ = candide_photo_mapping(photo)
    return replace(base, uv=uv.to(base.uv.dtype), shape_coeffs=shape.to(base.mean.dtype), texture=photo.image.float())


def _ramp(x: Tensor, near: float, far: float) -> Tensor:
    """1 up to ``near``, 0 from ``far``, linear in between."""
    return ((far - x) / (far - near)).clamp(0.0, 1.0)


@functools.lru_cache(maxsize=1)
def animated_scan_subject() -> Subject:
    """The James scan with CANDIDE-3's animation units transferred (module docstring); shape units stay ``S = 0``.

    Example:
        >>> s = animated_scan_subject()
        >>> s.num_animation, s.animation_units.shape[1] == s.mean.shape[0]
        (11, True)
    """
    scan = james_subject()
    candide = candide_subject("james")
    dt = torch.float64
    # Shape units fitted to the scan's landmarks: L(mean + S sigma) = L(mean) + sum_s sigma_s L(S_s) (linear).
    target = scan.landmarks_3d(scan.mean.to(dt).unsqueeze(0))[0]
    base = candide.landmarks_3d(candide.mean.to(dt).unsqueeze(0))[0]
    per_unit = candide.landmarks_3d(candide.shape_units.to(dt))  # (S, 68, 3)
    w = torch.ones(68, dtype=dt)
    w[:17] = 0.5  # the jaw contour is a weaker correspondence on CANDIDE-3's coarse outline
    A = per_unit.reshape(candide.num_shape, -1).T * w.repeat_interleave(3).unsqueeze(1)
    b = (target - base).reshape(-1) * w.repeat_interleave(3)
    eye = torch.eye(candide.num_shape, dtype=dt)
    sigma = torch.linalg.solve(A.T @ A + TRANSFER_SHAPE_PRIOR * eye, A.T @ b)
    verts = candide.mean.to(dt) + torch.einsum("s,svc->vc", sigma, candide.shape_units.to(dt))
    # The CANDIDE-3 point in front of / behind each scan vertex in the frontal view (closest in x, y).
    flat = verts.clone()
    flat[:, 2] = 0.0
    points = scan.mean.to(dt).clone()
    depth = points[:, 2].clone()
    points[:, 2] = 0.0
    face, bary, dist_xy = closest_points_on_triangles(points.numpy(), flat[candide.faces].numpy())
    corners = candide.faces[torch.from_numpy(face)]  # (Vs, 3)
    bary_t = torch.from_numpy(bary)
    behind = depth - (verts[corners][..., 2] * bary_t).sum(-1)  # +z is away from the viewer
    weight = _ramp(torch.from_numpy(dist_xy), *TRANSFER_XY_MM) * _ramp(behind, *TRANSFER_DEPTH_MM)
    moved = (candide.animation_units.to(dt)[:, corners] * bary_t[None, :, :, None]).sum(2)  # (A, Vs, 3)
    anim = (moved * weight[None, :, None]).to(scan.mean.dtype)
    return replace(
        scan, animation_units=anim, animation_names=candide.animation_names,
        animation_ranges=candide.animation_ranges.clone(),
    )  # fmt: skip


def identity_variant(
    subject: Subject, shape_offset: Tensor | None = None, colour_gain: Tensor | None = None
) -> Subject:
    """Another identity: the subject's shape units plus ``shape_offset (S,)``, its texture times ``colour_gain (3,)``.

    Raises:
        ValueError: an argument of the wrong shape.
    """
    shape = subject.shape_coeffs
    if shape_offset is not None:
        if tuple(shape_offset.shape) != (subject.num_shape,):
            raise ValueError(f"shape_offset must be ({subject.num_shape},), got {tuple(shape_offset.shape)}")
        shape = shape + shape_offset.to(shape.dtype)
    texture = subject.texture
    if colour_gain is not None:
        if tuple(colour_gain.shape) != (3,):
            raise ValueError(f"colour_gain must be (3,), got {tuple(colour_gain.shape)}")
        texture = (texture * colour_gain.to(texture.dtype).view(3, 1, 1)).clamp(0.0, 1.0)
    return replace(subject, shape_coeffs=shape, texture=texture)


@dataclass(frozen=True, eq=False)
class ClipSpec:
    """One labelled clip: from a frontal neutral frame to a target pose, expression and light.

    Attributes:
        num_frames: ``T >= 2``; frame ``T - 1`` shows the target (the labelled frame).
        width, height: frame size (pixels); the camera is :meth:`Intrinsics.default`.
        distance_mm: depth of the head origin at frame 0.
        ypr_deg: ``(3,)`` target yaw, pitch, roll (degrees; frame 0 is frontal).
        translation_mm: ``(3,)`` target translation offset from ``(0, 0, distance_mm)``.
        anim: ``(A,)`` target animation units (frame 0 is neutral).
        ambient: target ambient level; frame 0 has the default 0.45.
        light_direction: ``(3,)`` target key-light direction (camera frame, toward the light; normalised here).
        light_intensity: target key-light intensity; frame 0 has the default 0.55.
        background_seed: seed of the (static) backdrop.
        easing: ease in and out (``s^2 (3 - 2 s)``); False moves by equal steps (the largest frame-to-frame
            motion is then the smallest possible).
    """

    num_frames: int
    width: int
    height: int
    distance_mm: float
    ypr_deg: tuple[float, float, float]
    translation_mm: tuple[float, float, float]
    anim: Tensor
    ambient: float
    light_direction: tuple[float, float, float]
    light_intensity: float
    background_seed: int = 0
    easing: bool = True

    def __post_init__(self) -> None:
        for name in ("num_frames", "width", "height", "background_seed"):  # (2.5 frames failed in linspace)
            object.__setattr__(self, name, check_int(getattr(self, name), name))
        object.__setattr__(self, "easing", check_bool(self.easing, "easing"))  # "no" eased
        # (NaN was taken: a NaN ambient rendered NaN frames, a NaN pose a clip whose labels were NaN)
        for name, interval in (("distance_mm", "(0, inf)"), ("ambient", "[0, inf)"), ("light_intensity", "[0, inf)")):
            object.__setattr__(self, name, check_number(getattr(self, name), name, interval))
        if self.num_frames < 2:
            raise ValueError(f"num_frames must be >= 2 (a neutral first frame and a target), got {self.num_frames}")
        if self.width < 16 or self.height < 16:
            raise ValueError(f"frames must be at least 16x16, got {self.width}x{self.height}")
        if not isinstance(self.anim, Tensor) or self.anim.dim() != 1:
            raise ValueError(f"anim must be a (A,) tensor, got {getattr(self.anim, 'shape', type(self.anim).__name__)}")
        for name in ("ypr_deg", "translation_mm", "light_direction"):
            value = getattr(self, name)
            try:
                triple = tuple(float(v) for v in check_reals(value, name))  # (b"111": three 49s)
            except TypeError:
                raise TypeError(f"{name} must be three numbers, got {value!r}") from None
            if len(triple) != 3 or not all(math.isfinite(v) for v in triple):
                raise ValueError(f"{name} must be three finite numbers, got {value!r}")
        if not any(float(v) != 0 for v in self.light_direction):
            raise ValueError(f"light_direction must be a non-zero direction, got {self.light_direction!r}")
        if not bool(torch.isfinite(self.anim).all()):
            raise ValueError("anim must be finite, got NaN or infinite values")


#: Frame 0's light: ambient 0.45 plus a key light from the upper left (as the standard scenarios).
_DEFAULT_DIRECTION = (-0.35, -0.45, -0.82)


def _clip_motion(subject: Subject, spec: ClipSpec) -> tuple[Tensor, Tensor, Tensor, LightState]:
    """Per-frame rotation ``(T, 3, 3)``, translation ``(T, 3)``, animation units ``(T, A)`` (float64) and light."""
    if spec.anim.shape[0] != subject.num_animation:
        raise ValueError(
            f"spec.anim must have A = {subject.num_animation} values for this subject, got {spec.anim.shape[0]}"
        )
    T = spec.num_frames
    s = torch.linspace(0.0, 1.0, T, dtype=torch.float64)
    ease = (s * s * (3.0 - 2.0 * s) if spec.easing else s).unsqueeze(-1)  # (T, 1)
    R = euler_to_matrix(ease * torch.tensor(spec.ypr_deg, dtype=torch.float64))
    t = torch.tensor([0.0, 0.0, spec.distance_mm], dtype=torch.float64) + ease * torch.tensor(
        spec.translation_mm, dtype=torch.float64
    )
    anim = ease * spec.anim.to(torch.float64)
    d0 = torch.tensor(_DEFAULT_DIRECTION, dtype=torch.float64)
    d1 = torch.tensor(spec.light_direction, dtype=torch.float64)
    d0, d1 = d0 / d0.norm(), d1 / d1.norm().clamp_min(1e-12)
    directions = torch.nn.functional.normalize((1 - ease) * d0 + ease * d1, dim=-1)
    light = LightState(
        (0.45 + ease[:, 0] * (spec.ambient - 0.45)).float(),
        directions.unsqueeze(1).float(),
        (0.55 + ease * (spec.light_intensity - 0.55)).float(),
    )
    return R, t, anim, light


def clip_landmarks(subject: Subject, spec: ClipSpec) -> Tensor:
    """``(T, 68, 2)`` float64 ground-truth iBUG landmarks (pixels) of the clip :func:`render_clip` renders."""
    R, t, anim, _ = _clip_motion(subject, spec)
    shape = subject.shape_coeffs.to(torch.float64).expand(spec.num_frames, -1)
    verts = subject.deform(shape, anim, spec.num_frames)
    cam = Intrinsics.default(spec.width, spec.height)
    return project_points(transform_points(R, t, subject.landmarks_3d(verts)), cam)


def render_clip(subject: Subject, spec: ClipSpec) -> tuple[Tensor, Tensor]:
    """Render one clip of ``subject`` (module docstring).

    Args:
        subject: a :class:`~torchface.synth.subjects.Subject` with ``A`` animation units (``spec.anim`` matches).
        spec: :class:`ClipSpec`.

    Returns:
        ``frames (T, 3, H, W)`` float32 RGB in ``[0, 1]`` and ``landmarks_px (T, 68, 2)`` float64, the subject's
        ground-truth iBUG landmarks in pixels (:func:`clip_landmarks`).

    Example:
        >>> from torchface.synth.subjects import candide_subject
        >>> s = candide_subject("james")
        >>> spec = ClipSpec(3, 64, 64, 300.0, (20.0, 0.0, 0.0), (0.0, 0.0, 0.0),
        ...                 expression_coeffs(s.animation_names, "smile"), 0.4, (0.3, -0.2, -0.9), 0.6)
        >>> frames, landmarks = render_clip(s, spec)
        >>> frames.shape, landmarks.shape
        (torch.Size([3, 3, 64, 64]), torch.Size([3, 68, 2]))
    """
    R, t, anim, light = _clip_motion(subject, spec)
    T = spec.num_frames
    cam = Intrinsics.default(spec.width, spec.height)
    shape = subject.shape_coeffs.to(torch.float32).expand(T, -1)
    verts = subject.deform(shape, anim.float(), T)
    verts_cam = transform_points(R.float(), t.float(), verts)
    normals_cam = subject.vertex_normals(verts) @ R.float().transpose(-1, -2)
    bg = background_frames(BackgroundSpec(seed=spec.background_seed), torch.arange(T, dtype=torch.float32),
                           spec.height, spec.width)  # fmt: skip
    image, _, _ = render(verts_cam, subject.faces, subject.uv, subject.texture, normals_cam, light, cam, bg)
    return image.clamp(0.0, 1.0), clip_landmarks(subject, spec)
