"""Synthetic face sequences with exact ground truth: specification, rendering, files.

A :class:`SequenceSpec` fixes, per frame, the head pose (``X_cam = R X_model + t``, see
:mod:`torchface.conventions`), the animation-unit values, the light (:class:`LightState`, camera
frame) and the occluder, and per sequence the subject, its shape coefficients, the camera and the
background. :func:`render_sequence` renders it in memory (frames ``(T, 3, H, W)`` + :class:`GroundTruth`);
:func:`write_sequence` streams it to a lossless video plus ``<name>.gt.npz`` / ``<name>.gt.json``.

Image formation per frame (all batched over frames):

1. vertices ``g = g_bar + S sigma + A alpha_t`` (paper Eq. 1), moved to the camera frame (on one thread,
   :func:`~torchface.synth.textures.serial`, so that the frames do not depend on the core count);
2. textured Lambertian shading (:mod:`torchface.rendering.shading`) over the panning background;
3. the occluder (if present) composited in front of everything.

Ground-truth landmarks are the subject's 68 iBUG landmarks (fixed barycentric combinations of
vertices, so they follow the expression), projected with the ground-truth pose. Visibility is exact,
not pixel-sampled (:func:`landmark_visibility`): a landmark is visible when it projects inside the
image, it faces the camera (its triangle does, or its smooth interpolated normal does up to ~6
degrees past grazing), no triangle crosses the segment from the camera centre to it
before ``(1 - 1e-2)`` of its depth (the tolerance of
:func:`~torchface.rendering.visibility.points_visible`), and the occluder does not cover its pixel.
"""

from __future__ import annotations

import json
import numbers
import os
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchface._atomic import folder_locked, remove_dead_partials, written_whole
from torchface.geometry._checks import check_int, check_number, rotation_defects
from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import project_points
from torchface.geometry.so3 import matrix_to_axis_angle, matrix_to_euler
from torchface.geometry.transforms import transform_points
from torchface.rendering.shading import LightState, render
from torchface.synth.background import BackgroundSpec, OccluderSpec, background_frames, place_occluder
from torchface.synth.io import WRITTEN_SUFFIXES, VideoSink
from torchface.synth.subjects import Subject, get_subject
from torchface.synth.textures import serial

__all__ = [
    "SequenceSpec",
    "GroundTruth",
    "SequenceFiles",
    "render_sequence",
    "iter_sequence",
    "write_sequence",
    "save_ground_truth",
    "load_ground_truth",
    "landmark_visibility",
]

#: Number of landmarks in the ground truth (iBUG-68).
NUM_LANDMARKS: int = 68


#: How far ``R^T R`` may be from the identity (largest entry) for :class:`SequenceSpec` to take ``R`` as a rotation:
#: float32 rotations are within 1e-6; a scaled matrix or one that is not a rotation is far outside.
ROTATION_TOLERANCE: float = 1e-3


def _check_spec_tensor(x: object, name: str) -> None:
    """Refuse what :class:`SequenceSpec` cannot render from its field ``name`` (``shape_coeffs`` may be None): not a
    tensor, a complex one, one off the CPU (the renderer's), or NaN or infinite values (they rendered a frame of
    background and NaN landmarks without a word)."""
    if x is None and name == "shape_coeffs":
        return
    if not isinstance(x, Tensor):
        hint = f" (torch.from_numpy({name}))" if isinstance(x, np.ndarray) else ""
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}{hint}")
    if x.is_complex():
        raise TypeError(f"{name} must be a real tensor, got {x.dtype}")
    if x.device.type != "cpu":
        raise ValueError(f"{name} must be on the CPU, where the sequence is rendered, got {x.device} ({name}.cpu())")
    if x.is_floating_point() and not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} must be finite, got NaN or infinite values")


def _check_rotations(R: Tensor) -> None:
    """Refuse ``(T, 3, 3)`` matrices that are not rotations (a scale, a shear, a reflection: they rendered a scaled or
    mirrored head, and its ground truth ``ypr_deg`` and ``axis_angle`` of no rotation at all)."""
    off, det = rotation_defects(R.detach().to(torch.float64).numpy())  # (on the CPU: _check_spec_tensor)
    bad = np.flatnonzero((off > ROTATION_TOLERANCE) | (det <= 0))
    if bad.size:
        k = int(bad[0])
        raise ValueError(
            f"rotation must hold rotation matrices (R^T R = I, det R = +1), frame {k}'s is off by {float(off[k]):.3g} "
            f"with det {float(det[k]):.4g}; make them with torchface.geometry.so3.euler_to_matrix(ypr_deg) or "
            "axis_angle_to_matrix"
        )


def _check_light(light: LightState) -> None:
    """Refuse a light that renders NaN frames (a NaN ambient or intensity did) or a light of no direction or a
    negative strength."""
    for name in ("ambient", "directions", "intensities"):
        value = getattr(light, name)
        if value.device.type != "cpu":
            raise ValueError(f"light.{name} must be on the CPU, where the sequence is rendered, got {value.device}")
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"light.{name} must be finite, got NaN or infinite values")
    if bool((light.ambient < 0).any()) or bool((light.intensities < 0).any()):
        raise ValueError("light.ambient and light.intensities must be >= 0")
    if bool(((light.directions.norm(dim=-1) == 0) & (light.intensities > 0)).any()):
        raise ValueError("light.directions must not be zero where a light is on (intensity > 0)")


@dataclass(frozen=True, eq=False)
class SequenceSpec:
    """Everything that determines a synthetic sequence.

    Attributes:
        name: sequence name (file stem).
        subject: ``"candide3"`` or ``"james"``.
        intrinsics: camera (the frames are ``intrinsics.height x intrinsics.width``).
        rotation: ``(T, 3, 3)`` head-to-camera rotations.
        translation: ``(T, 3)`` millimetres.
        anim: ``(T, A)`` animation-unit values in the subject's unit order (``A = 0`` for a scan).
        light: light state with batch ``T``.
        shape_coeffs: ``(S,)`` shape coefficients; ``None`` uses the subject's own (fitted to its photo).
        photo: photograph CANDIDE-3 is textured from (``"james"`` or ``"astronaut"``).
        background: panning backdrop.
        occluder: optional occluding object.
        fps: frame rate written to the video.
        events: ``(label, frame)`` pairs worth knowing (e.g. when a light switches on).
        description: one line for humans.
        occluders: further occluding objects; the frame ranges of ``occluder`` and these must not overlap.

    Checked when made: the tensors are finite and on the CPU (where the sequence is rendered), ``rotation`` holds
    rotation matrices (within :data:`ROTATION_TOLERANCE`; make them with
    :func:`~torchface.geometry.so3.euler_to_matrix`), the head is in front of the camera (``translation[:, 2] > 0``),
    the light's ambient and intensities are ``>= 0``, ``name`` is a file stem and each event's frame lies in
    ``0 .. T``. Rendering warns where ``anim`` leaves the subject's ``animation_ranges`` (the tracker clamps its
    estimate to them) and where no frame shows the face.

    Example:
        >>> from torchface.geometry.so3 import euler_to_matrix
        >>> from torchface.synth.scenarios import default_light
        >>> T, ypr = 3, torch.tensor([[0.0, 0, 0], [10.0, 0, 0], [20.0, 0, 0]], dtype=torch.float64)
        >>> spec = SequenceSpec("turn", "candide3", Intrinsics.default(80, 60), euler_to_matrix(ypr),
        ...                     torch.tensor([[0.0, 0.0, 450.0]] * T), torch.zeros(T, 11), default_light(T))
        >>> frames, gt = render_sequence(spec)
        >>> frames.shape, gt.ypr_deg[-1, 0].item()
        (torch.Size([3, 3, 60, 80]), 20.0)
    """

    name: str
    subject: str
    intrinsics: Intrinsics
    rotation: Tensor
    translation: Tensor
    anim: Tensor
    light: LightState
    shape_coeffs: Tensor | None = None
    photo: str = "james"
    background: BackgroundSpec = field(default_factory=BackgroundSpec)
    occluder: OccluderSpec | None = None
    fps: float = 25.0
    events: tuple[tuple[str, int], ...] = ()
    description: str = ""
    occluders: tuple[OccluderSpec, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name or self.name in (".", "..") or any(
            c in self.name for c in "/\\\0"
        ):  # (a name with a "/" wrote into a subfolder, or failed as "no folder"; "" wrote a hidden ".avi")
            raise ValueError(f"name must be a file stem, without a folder or a '/', got {self.name!r}")
        if not isinstance(self.intrinsics, Intrinsics):
            raise TypeError(f"intrinsics must be an Intrinsics, got {type(self.intrinsics).__name__}")
        for name in ("rotation", "translation", "anim", "shape_coeffs"):
            _check_spec_tensor(getattr(self, name), name)
        if self.rotation.ndim != 3 or self.rotation.shape[1:] != (3, 3):
            raise ValueError(f"rotation must be a (T, 3, 3) tensor, got {getattr(self.rotation, 'shape', self.rotation)}")
        t = self.rotation.shape[0]
        if t < 1:
            raise ValueError("a sequence needs at least one frame")
        if tuple(self.translation.shape) != (t, 3):
            raise ValueError(f"translation must be ({t}, 3), got {getattr(self.translation, 'shape', self.translation)}")
        if self.anim.ndim != 2 or self.anim.shape[0] != t:
            raise ValueError(f"anim must be ({t}, A), got {getattr(self.anim, 'shape', self.anim)}")
        if not isinstance(self.light, LightState) or self.light.batch_size != t:
            raise ValueError(f"light must be a LightState with batch {t}")
        if self.shape_coeffs is not None and self.shape_coeffs.ndim != 1:
            raise ValueError("shape_coeffs must be a (S,) tensor or None")
        _check_rotations(self.rotation)
        z = self.translation[:, 2].detach().to(torch.float64)
        if not bool((z > 0).all()):  # (the face rendered nowhere, its landmarks behind the camera)
            k = int((z <= 0).nonzero()[0])
            raise ValueError(
                f"translation[:, 2] must be > 0, the head in front of the camera (millimetres, X_cam = R X_model + t; "
                f"the scenarios' FACE_DISTANCE_MM is 450), got {float(z[k]):.6g} at frame {k}"
            )
        _check_light(self.light)
        events = tuple(self.events) if isinstance(self.events, (tuple, list)) else self.events
        if not isinstance(events, tuple) or not all(
            isinstance(e, (tuple, list)) and len(e) == 2 and isinstance(e[0], str)
            and isinstance(e[1], numbers.Integral) and not isinstance(e[1], bool) and 0 <= e[1] <= t
            for e in events
        ):  # (a frame past the end, or a list, was taken as it was)
            raise ValueError(
                f"events must be (label, frame) pairs, a str and an int frame in 0 .. {t}, got {self.events!r}"
            )
        object.__setattr__(self, "events", tuple((str(lbl), int(f)) for lbl, f in events))
        if not isinstance(self.occluders, tuple) or not all(isinstance(o, OccluderSpec) for o in self.occluders):
            raise TypeError("occluders must be a tuple of OccluderSpec")
        spans = sorted((o.first_frame, o.last_frame) for o in self.all_occluders)
        for o in self.all_occluders:
            if o.first_frame >= t:
                raise ValueError(f"occluder starts at frame {o.first_frame} of a {t}-frame sequence")
        for (_, end), (start, _) in zip(spans[:-1], spans[1:]):
            if start < end:
                raise ValueError(f"occluder frame ranges must not overlap, got {spans}")
        object.__setattr__(self, "fps", check_number(self.fps, "fps", "(0, inf)"))  # (inf and NaN were taken)

    @property
    def num_frames(self) -> int:
        """``T``."""
        return int(self.rotation.shape[0])

    @property
    def all_occluders(self) -> tuple[OccluderSpec, ...]:
        """``occluder`` (if any) followed by ``occluders``."""
        return ((self.occluder,) if self.occluder is not None else ()) + self.occluders


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Per-frame ground truth of a synthetic sequence (float64 CPU tensors).

    Attributes:
        name: sequence name.
        model: subject name (``"candide3"`` or ``"james"``).
        photo: photograph the CANDIDE-3 texture came from.
        intrinsics: camera.
        fps: frame rate.
        rotation: ``(T, 3, 3)`` head-to-camera rotations (``X_cam = R X_model + t``).
        axis_angle: ``(T, 3)`` the same rotations as axis-angle vectors (radians).
        translation: ``(T, 3)`` millimetres.
        ypr_deg: ``(T, 3)`` yaw, pitch, roll in degrees (``R = R_y R_x R_z``).
        au: ``(T, A)`` animation-unit values.
        au_names: ``A`` names (the model's, e.g. ``"AUV11 Jaw drop"``).
        shape_coeffs: ``(S,)`` shape coefficients of the subject.
        light_ambient: ``(T,)``.
        light_directions: ``(T, L, 3)`` camera frame, toward the lights.
        light_intensities: ``(T, L)``.
        occluder_on: ``(T,)`` bool.
        occluded_fraction: ``(T,)`` fraction of the face's visible pixels hidden by the occluder.
        face_pixels: ``(T,)`` number of pixels showing the face (before the occluder).
        landmarks_3d: ``(T, 68, 3)`` landmarks in the head frame (expression applied).
        landmarks_px: ``(T, 68, 2)`` pixel positions (``(u, v)``, pixel centres at integers).
        landmarks_visible: ``(T, 68)`` bool.
        events: ``(label, frame)`` pairs.
        description: one line for humans.
    """

    name: str
    model: str
    photo: str
    intrinsics: Intrinsics
    fps: float
    rotation: Tensor
    axis_angle: Tensor
    translation: Tensor
    ypr_deg: Tensor
    au: Tensor
    au_names: tuple[str, ...]
    shape_coeffs: Tensor
    light_ambient: Tensor
    light_directions: Tensor
    light_intensities: Tensor
    occluder_on: Tensor
    occluded_fraction: Tensor
    face_pixels: Tensor
    landmarks_3d: Tensor
    landmarks_px: Tensor
    landmarks_visible: Tensor
    events: tuple[tuple[str, int], ...] = ()
    description: str = ""

    @property
    def num_frames(self) -> int:
        """``T``."""
        return int(self.rotation.shape[0])

    @property
    def light(self) -> LightState:
        """The per-frame light as a :class:`LightState` with batch ``T``."""
        return LightState(self.light_ambient, self.light_directions, self.light_intensities)

    @property
    def landmarks_in_image(self) -> Tensor:
        """``(T, 68)`` bool: the landmark projects inside the image ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``
        (whether or not it is hidden by the head itself or an occluder)."""
        u, v = self.landmarks_px[..., 0], self.landmarks_px[..., 1]
        w, h = self.intrinsics.width, self.intrinsics.height
        return (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)

    @property
    def face_in_view(self) -> Tensor:
        """``(T,)`` float64: fraction of the 68 landmarks that project inside the image."""
        return self.landmarks_in_image.to(torch.float64).mean(-1)

    @property
    def face_visible(self) -> Tensor:
        """``(T,)`` bool: the whole face is in view (every landmark projects inside the image) and rendered.

        A face partly out of the image counts as not visible: when a face comes back into view, the clock of
        "frames until tracking recovers" starts at its first frame that is entirely inside the image.
        """
        return self.landmarks_in_image.all(-1) & (self.face_pixels > 0)


@dataclass(frozen=True)
class SequenceFiles:
    """Paths written by :func:`write_sequence`.

    Attributes:
        video: the video file.
        ground_truth: the ``.gt.npz`` file.
        metadata: the ``.gt.json`` file.
        codec: FourCC code of the video.
        num_frames: frames written.
    """

    video: Path
    ground_truth: Path
    metadata: Path
    codec: str
    num_frames: int


_TENSOR_FIELDS = (
    "rotation",
    "axis_angle",
    "translation",
    "ypr_deg",
    "au",
    "shape_coeffs",
    "light_ambient",
    "light_directions",
    "light_intensities",
    "occluder_on",
    "occluded_fraction",
    "face_pixels",
    "landmarks_3d",
    "landmarks_px",
    "landmarks_visible",
)


def landmark_visibility(
    verts_cam: Tensor,
    faces: Tensor,
    points_cam: Tensor,
    point_faces: Tensor,
    intrinsics: Intrinsics,
    depth_tolerance: float = 1e-2,
    point_normals: Tensor | None = None,
    grazing_tolerance: float = 0.1,
) -> Tensor:
    """Exact self-occlusion test of surface points by ray casting against every triangle.

    Point ``X`` (on triangle ``point_faces[k]``) is visible iff its projection lies in the image
    ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``, it faces the camera, and no triangle meets the ray ``s X``
    at ``s < 1 - depth_tolerance``. Facing: its triangle's outward normal gives ``n . v0 < 0``, or, with
    ``point_normals`` (smooth outward normals at the points), ``n . X / |X| < grazing_tolerance`` (a
    silhouette point on a noisy scan stays visible up to ~6 degrees past grazing). (Moller-Trumbore
    intersection with the ray from the camera centre through ``X``; the point's own and adjacent
    triangles meet it at ``s = 1``). Vectorised over samples, points and the (point, triangle) pairs
    that survive a projected bounding-box and depth test.

    Args:
        verts_cam: ``(B, V, 3)`` vertices in the camera frame (millimetres).
        faces: ``(F, 3)`` int64 triangles.
        points_cam: ``(B, K, 3)`` points on the surface.
        point_faces: ``(K,)`` triangle of each point.
        intrinsics: the camera.
        depth_tolerance: relative depth below which an intersection does not hide the point.
        point_normals: ``(B, K, 3)`` unit outward normals at the points (camera frame), optional.
        grazing_tolerance: cosine past grazing still counted as facing (with ``point_normals``).

    Returns:
        ``(B, K)`` bool.
    """
    b = verts_cam.shape[0]
    dt = torch.float64
    cam = intrinsics
    pts = points_cam.to(dt)
    z = pts[..., 2]
    u = cam.fx * pts[..., 0] / z.clamp(min=1e-9) + cam.cx
    v = cam.fy * pts[..., 1] / z.clamp(min=1e-9) + cam.cy
    inside = (z > 1.0) & (u >= -0.5) & (u <= cam.width - 0.5) & (v >= -0.5) & (v <= cam.height - 0.5)
    tri = verts_cam.to(dt)[:, faces]  # (B, F, 3, 3)
    v0, e1, e2 = tri[:, :, 0], tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0]
    n = torch.linalg.cross(e1, e2, dim=-1)
    front = (n[:, point_faces] * v0[:, point_faces]).sum(-1) < 0  # (B, K)
    if point_normals is not None:
        view = pts / pts.norm(dim=-1, keepdim=True).clamp(min=1e-9)
        front = front | ((point_normals.to(dt) * view).sum(-1) < grazing_tolerance)
    # Candidate pairs: triangles partly nearer than the point whose projected box contains it
    # (triangles reaching behind the camera plane have unbounded boxes and are always candidates).
    tz = tri[..., 2]
    tu = cam.fx * tri[..., 0] / tz.clamp(min=1e-6) + cam.cx
    tv = cam.fy * tri[..., 1] / tz.clamp(min=1e-6) + cam.cy
    unbounded = (tz <= 1e-6).any(-1).unsqueeze(1)  # (B, 1, F)
    uu, vv = u.unsqueeze(-1), v.unsqueeze(-1)  # (B, K, 1)
    in_box = (
        (tu.amin(-1).unsqueeze(1) <= uu + 1e-6)
        & (tu.amax(-1).unsqueeze(1) >= uu - 1e-6)
        & (tv.amin(-1).unsqueeze(1) <= vv + 1e-6)
        & (tv.amax(-1).unsqueeze(1) >= vv - 1e-6)
    )
    nearer = tz.amin(-1).unsqueeze(1) < z.unsqueeze(-1) * (1.0 - depth_tolerance)
    b_idx, k_idx, f_idx = torch.nonzero(nearer & (in_box | unbounded), as_tuple=True)
    # Moller-Trumbore on the candidate pairs; the ray is s * X, the point itself at s = 1.
    d = pts[b_idx, k_idx]
    a0, a1, a2 = v0[b_idx, f_idx], e1[b_idx, f_idx], e2[b_idx, f_idx]
    h = torch.linalg.cross(d, a2, dim=-1)
    a = (a1 * h).sum(-1)
    ok = a.abs() > 1e-12
    f = 1.0 / torch.where(ok, a, torch.ones_like(a))
    s_vec = -a0  # ray origin (camera centre) minus v0
    bu = f * (s_vec * h).sum(-1)
    q = torch.linalg.cross(s_vec, a1, dim=-1)
    bv = f * (d * q).sum(-1)
    s = f * (a2 * q).sum(-1)
    hit = ok & (bu >= 0) & (bv >= 0) & (bu + bv <= 1) & (s > 1e-6) & (s < 1.0 - depth_tolerance)
    hidden = torch.zeros(b, pts.shape[1], dtype=torch.bool, device=pts.device)
    hidden[b_idx[hit], k_idx[hit]] = True
    return inside & front & ~hidden


def _resolve(spec: SequenceSpec) -> tuple[Subject, Tensor]:
    subject = get_subject(spec.subject, spec.photo)
    if spec.anim.shape[1] != subject.num_animation:
        raise ValueError(
            f"anim must have A={subject.num_animation} columns for subject {spec.subject!r}, got {spec.anim.shape[1]}"
        )
    shape = subject.shape_coeffs if spec.shape_coeffs is None else spec.shape_coeffs
    if shape.shape != (subject.num_shape,):
        raise ValueError(f"shape_coeffs must be ({subject.num_shape},) for {spec.subject!r}, got {tuple(shape.shape)}")
    return subject, shape


def _warn_out_of_range(spec: SequenceSpec, subject: Subject) -> None:
    """Warn where ``spec.anim`` leaves the subject's ``animation_ranges``: rendered as asked, but the tracker clamps
    its estimate to them, so that no estimate can match it."""
    if not subject.num_animation:
        return
    anim = spec.anim.detach().to(torch.float64)
    ranges = subject.animation_ranges.to(torch.float64)
    outside = (anim < ranges[:, 0]) | (anim > ranges[:, 1])
    if bool(outside.any()):
        j = int(outside.any(0).nonzero()[0])
        lo, hi = (float(v) for v in ranges[j])
        warnings.warn(
            f"anim's {subject.animation_names[j]!r} goes to {float(anim[:, j].min()):.4g} .. "
            f"{float(anim[:, j].max()):.4g}, outside its range [{lo:.4g}, {hi:.4g}] (the subject's animation_ranges), "
            "to which the tracker clamps its estimate: its error cannot reach 0 there",
            UserWarning,
            stacklevel=3,
        )


def iter_sequence(spec: SequenceSpec, batch_size: int = 8) -> Iterator[tuple[Tensor, dict[str, Tensor]]]:
    """Render ``spec`` in chunks of at most ``batch_size`` frames.

    Yields:
        ``frames (b, 3, H, W)`` float32 in ``[0, 1]`` and a dict of the chunk's per-frame ground truth
        (``landmarks_3d``, ``landmarks_px``, ``landmarks_visible``, ``occluded_fraction``,
        ``face_pixels``, ``occluder_on``).
    """
    subject, shape = _resolve(spec)
    _warn_out_of_range(spec, subject)
    yield from _render_chunks(spec, subject, shape, batch_size)


def _render_chunks(
    spec: SequenceSpec, subject: Subject, shape: Tensor, batch_size: int
) -> Iterator[tuple[Tensor, dict[str, Tensor]]]:
    """:func:`iter_sequence` of the subject and shape coefficients :func:`_resolve` gave."""
    batch_size = check_int(batch_size, "batch_size", 1)  # (2.5 failed in range(): "'float' object cannot be ...")
    cam = spec.intrinsics
    h, w = cam.height, cam.width
    t_all = spec.num_frames
    for start in range(0, t_all, batch_size):
        idx = torch.arange(start, min(start + batch_size, t_all))
        b = idx.shape[0]
        R = spec.rotation[idx].to(torch.float32)
        t = spec.translation[idx].to(torch.float32)
        with serial():  # the same frames whatever the core count: the (b, S) @ (S, 3V) deformation rounds
            # differently on 2 threads than on 1 for some chunk sizes (5-7, 9-11 frames: MKL's sgemm)
            verts = subject.deform(shape.to(torch.float32).expand(b, -1), spec.anim[idx].to(torch.float32), b)
            verts_cam = transform_points(R, t, verts)
            normals_cam = subject.vertex_normals(verts) @ R.transpose(-1, -2)
        light = spec.light.select(idx).to(dtype=torch.float32)
        bg = background_frames(spec.background, idx.to(torch.float32), h, w)
        image, mask, frags = render(verts_cam, subject.faces, subject.uv, subject.texture, normals_cam, light, cam, bg)
        face_pixels = (mask[:, 0] > 0.5).flatten(1).sum(1)
        # Ground-truth geometry in float64 from the same parameters.
        verts64 = subject.deform(shape.to(torch.float64).expand(b, -1), spec.anim[idx].to(torch.float64), b)
        lm3d = subject.landmarks_3d(verts64)
        R64, t64 = spec.rotation[idx].to(torch.float64), spec.translation[idx].to(torch.float64)
        lm_cam = transform_points(R64, t64, lm3d)
        lm_px = project_points(lm_cam, cam)
        lm_normals = subject.landmarks_3d(normals_cam.to(torch.float64))
        lm_normals = lm_normals / lm_normals.norm(dim=-1, keepdim=True).clamp(min=1e-12)
        visible = landmark_visibility(verts_cam, subject.faces, lm_cam, subject.landmark_faces, cam, point_normals=lm_normals)
        occ_on = torch.zeros(b, dtype=torch.bool)
        occ_frac = torch.zeros(b, dtype=torch.float64)
        for occluder in spec.all_occluders:
            if not bool(occluder.active(idx).any()):
                continue
            # Occluder ranges do not overlap: each frame gets at most one, so the fractions add up.
            alpha, colour, frac = place_occluder(occluder, idx, mask)
            image = image * (1.0 - alpha) + colour * alpha
            occ_on = occ_on | (occluder.active(idx) & (face_pixels > 0))
            occ_frac = occ_frac + frac.to(torch.float64)
            col = lm_px[..., 0].round().clamp(0, w - 1).long()
            row = lm_px[..., 1].round().clamp(0, h - 1).long()
            covered = alpha[torch.arange(b).unsqueeze(-1), 0, row, col] > 0.5
            visible = visible & ~covered
        yield image.clamp(0.0, 1.0), {
            "landmarks_3d": lm3d,
            "landmarks_px": lm_px,
            "landmarks_visible": visible,
            "occluded_fraction": occ_frac,
            "occluder_on": occ_on,
            "face_pixels": face_pixels,
        }


class _Rows:
    """Per-frame tensors of a sequence, copied chunk by chunk into tensors of ``T`` rows allocated once.

    Keeping every chunk's small tensors alive between the renderer's large temporaries fragments the heap: a
    3000-frame 640x480 sequence grew the process by ~2.7 MB per frame that way; with these buffers memory stays
    flat.
    """

    def __init__(self, num_frames: int) -> None:
        self.num_frames = num_frames
        self.filled = 0
        self.data: dict[str, Tensor] = {}

    def add(self, chunk: dict[str, Tensor]) -> None:
        n = next(iter(chunk.values())).shape[0]
        if not self.data:
            self.data = {k: v.new_empty((self.num_frames, *v.shape[1:])) for k, v in chunk.items()}
        for k, v in chunk.items():
            self.data[k][self.filled : self.filled + n] = v
        self.filled += n


def _ground_truth(spec: SequenceSpec, subject: Subject, shape: Tensor, rows: _Rows) -> GroundTruth:
    if rows.filled != spec.num_frames:
        raise RuntimeError(f"rendered {rows.filled} of {spec.num_frames} frames")
    cat = rows.data
    if not bool((cat["face_pixels"] > 0).any()):
        warnings.warn(
            f"no frame of {spec.name!r} shows the face (face_pixels is 0 in all {spec.num_frames}): is translation in "
            "millimetres, the head in front of the camera and inside its view?",
            RuntimeWarning,
            stacklevel=3,
        )
    R = spec.rotation.to(torch.float64)
    return GroundTruth(
        name=spec.name,
        model=subject.name,
        photo=spec.photo if subject.name == "candide3" else "",
        intrinsics=spec.intrinsics,
        fps=float(spec.fps),
        rotation=R,
        axis_angle=matrix_to_axis_angle(R),
        translation=spec.translation.to(torch.float64),
        ypr_deg=matrix_to_euler(R),
        au=spec.anim.to(torch.float64),
        au_names=tuple(subject.animation_names),
        shape_coeffs=shape.to(torch.float64),
        light_ambient=spec.light.ambient.to(torch.float64),
        light_directions=spec.light.directions.to(torch.float64),
        light_intensities=spec.light.intensities.to(torch.float64),
        occluder_on=cat["occluder_on"],
        occluded_fraction=cat["occluded_fraction"],
        face_pixels=cat["face_pixels"].to(torch.int64),
        landmarks_3d=cat["landmarks_3d"],
        landmarks_px=cat["landmarks_px"],
        landmarks_visible=cat["landmarks_visible"],
        events=tuple(spec.events),
        description=spec.description,
    )


def render_sequence(spec: SequenceSpec, batch_size: int = 8) -> tuple[Tensor, GroundTruth]:
    """Render a whole sequence in memory (for tests and small sequences; no files).

    Args:
        spec: the sequence.
        batch_size: frames rendered at once.

    Returns:
        ``frames (T, 3, H, W)`` float32 RGB in ``[0, 1]`` and the :class:`GroundTruth`.

    Example:
        >>> from torchface.synth.scenarios import make_scenario
        >>> frames, gt = render_sequence(make_scenario("pose_sweep", 4, 80, 60))
        >>> frames.shape, gt.landmarks_px.shape
        (torch.Size([4, 3, 60, 80]), torch.Size([4, 68, 2]))
    """
    subject, shape = _resolve(spec)
    _warn_out_of_range(spec, subject)
    frames, rows = _Rows(spec.num_frames), _Rows(spec.num_frames)
    for img, gt in _render_chunks(spec, subject, shape, batch_size):
        frames.add({"frames": img})
        rows.add(gt)
    return frames.data["frames"], _ground_truth(spec, subject, shape, rows)


def _metadata(gt: GroundTruth) -> dict[str, object]:
    cam = gt.intrinsics
    on = gt.occluder_on
    return {
        "name": gt.name,
        "model": gt.model,
        "photo": gt.photo,
        "description": gt.description,
        "num_frames": gt.num_frames,
        "fps": gt.fps,
        "intrinsics": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width, "height": cam.height},
        "au_names": list(gt.au_names),
        "shape_coeffs": [round(float(x), 6) for x in gt.shape_coeffs],
        "num_lights": int(gt.light_directions.shape[1]),
        "events": [[label, int(frame)] for label, frame in gt.events],
        "ypr_deg_min": [round(float(x), 3) for x in gt.ypr_deg.detach().amin(0)],
        "ypr_deg_max": [round(float(x), 3) for x in gt.ypr_deg.detach().amax(0)],
        "occluder_frames": int(on.sum()),
        "face_not_visible_frames": int((~gt.face_visible).sum()),
        "occluded_fraction_range": (
            [round(float(gt.occluded_fraction[on].min()), 4), round(float(gt.occluded_fraction[on].max()), 4)] if on.any() else []
        ),
        "conventions": "torchface.conventions: X_cam = R X_model + t (mm), OpenCV camera, R = Ry(yaw) Rx(pitch) Rz(roll)",
    }


def save_ground_truth(
    gt: GroundTruth, stem: str | os.PathLike[str], extra_metadata: dict[str, object] | None = None
) -> tuple[Path, Path]:
    """Write ``<stem>.gt.npz`` (all arrays) and ``<stem>.gt.json`` (metadata); returns both paths.

    Both are written to temporary names of this process's own (``<stem>.gt.partial-<pid>-<hex>.npz``,
    :func:`torchface._atomic.written_whole`: two processes writing the same pair each write their own, and one that
    fails removes its own alone) and renamed when complete, the ``.gt.json`` first: the ``.gt.npz``, which
    :func:`load_ground_truth` reads, appears last, so that its presence means the pair is whole.
    ``extra_metadata`` (JSON-able) is merged into the ``.gt.json``.
    """
    stem = Path(stem)
    npz_path = stem.with_name(stem.name + ".gt.npz")
    json_path = stem.with_name(stem.name + ".gt.json")
    if not stem.parent.is_dir():  # (said "No such file or directory: '<stem>.gt.partial-<pid>-<hex>.json'")
        raise FileNotFoundError(f"{stem}: no folder {stem.parent} to write the ground truth in")
    arrays = {k: getattr(gt, k).detach().numpy() for k in _TENSOR_FIELDS}  # (a spec's tensor that required grad:
    # "Can't call numpy() on Tensor that requires grad", and write_sequence left its video without a ground truth)
    cam = gt.intrinsics
    arrays["intrinsics"] = np.array([cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height], dtype=np.float64)
    arrays["au_names"] = np.array(gt.au_names, dtype=np.str_)
    arrays["event_labels"] = np.array([e[0] for e in gt.events], dtype=np.str_)
    arrays["event_frames"] = np.array([e[1] for e in gt.events], dtype=np.int64)
    arrays["strings"] = np.array([gt.name, gt.model, gt.photo, gt.description], dtype=np.str_)
    arrays["fps"] = np.array(gt.fps, dtype=np.float64)
    meta = _metadata(gt)
    meta.update(extra_metadata or {})
    with written_whole(json_path) as tmp:
        tmp.write_text(json.dumps(meta, indent=1) + "\n")
    with written_whole(npz_path) as tmp:  # (its name ends in .npz: numpy keeps it)
        np.savez_compressed(tmp, **arrays)
    return npz_path, json_path


def load_ground_truth(path: str | os.PathLike[str]) -> GroundTruth:
    """Read a ground truth written by :func:`save_ground_truth`.

    Args:
        path: the ``.gt.npz`` file, its ``.gt.json`` sibling, the video, or the common stem (the stem
            :func:`save_ground_truth` was given: a video's name given there as the stem, ``clip.avi``, is read back
            from ``clip.avi.gt.npz`` too).

    Example:
        >>> # gt = load_ground_truth("out/pose_sweep.gt.npz"); gt.ypr_deg.shape  -> (T, 3)
    """
    p = Path(path)
    name = p.name
    for suffix in (".gt.npz", ".gt.json", *WRITTEN_SUFFIXES):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
            break
    npz_path = p.with_name(name + ".gt.npz")
    if not npz_path.is_file() and name != p.name and p.with_name(p.name + ".gt.npz").is_file():
        # (save_ground_truth(gt, "d/clip.avi") writes d/clip.avi.gt.npz: a stem given with the video's suffix)
        npz_path = p.with_name(p.name + ".gt.npz")
    if not npz_path.is_file():
        raise FileNotFoundError(f"no ground truth at {npz_path}")
    with np.load(npz_path) as z:
        a = {k: z[k] for k in z.files}
    missing = [k for k in ("intrinsics", "strings", "fps", "au_names", "event_labels", "event_frames", *_TENSOR_FIELDS)
               if k not in a]  # fmt: skip
    if missing:  # (a KeyError of the first, e.g. 'intrinsics')
        raise ValueError(f"{npz_path}: not a ground truth of save_ground_truth, it lacks {', '.join(missing)}")
    fx, fy, cx, cy, width, height = (float(x) for x in a["intrinsics"])
    strings = [str(s) for s in a["strings"]]
    tensors = {k: torch.from_numpy(a[k]) for k in _TENSOR_FIELDS}
    return GroundTruth(
        name=strings[0],
        model=strings[1],
        photo=strings[2],
        intrinsics=Intrinsics(int(width), int(height), fx, fy, cx, cy),
        fps=float(a["fps"]),
        au_names=tuple(str(s) for s in a["au_names"]),
        events=tuple((str(lbl), int(f)) for lbl, f in zip(a["event_labels"], a["event_frames"])),
        description=strings[3],
        **tensors,
    )


def write_sequence(
    spec: SequenceSpec,
    out_dir: str | os.PathLike[str],
    batch_size: int = 8,
    progress: Callable[[int, int], None] | None = None,
) -> SequenceFiles:
    """Render ``spec`` into ``out_dir/<name>.avi`` (lossless) plus its ground truth files.

    Frames are streamed to the video chunk by chunk, so memory does not grow with ``T``. The video is renamed into
    place once whole (:class:`VideoSink`), after the ground truth of an earlier sequence of the same name in
    ``out_dir`` is removed, and the new ground truth is written after it (:func:`save_ground_truth`, its ``.gt.npz``
    last): a run stopped partway (Ctrl-C, a full disk) leaves the earlier pair as it was (stopped while rendering) or
    a video without a ``.gt.npz``, never a new video beside an older ground truth, which a reader would take for its
    pair. Each file is written under a temporary name of this process's own (:mod:`torchface._atomic`), so that two
    runs rendering the same sequence into one folder (two evaluations sharing a ``--cache``) do not write into, or
    remove, each other's; the temporary files of this sequence left in ``out_dir`` by a run killed outright (``kill
    -9``: no cleanup) are removed first where their process is no longer running
    (:func:`torchface._atomic.remove_dead_partials`). The files of one run go into place together: removing the
    older ground truth, the video's rename and the new ground truth hold a lock on ``out_dir``
    (:func:`torchface._atomic.folder_locked`), so that two runs finishing together leave one run's video and ground
    truth, never one's video beside the other's ground truth (which differ where the two specs of one name do).

    Args:
        spec: the sequence.
        out_dir: destination folder (created if needed).
        batch_size: frames rendered at once.
        progress: called with ``(frames_done, total)`` after each chunk.

    Returns:
        :class:`SequenceFiles`.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    subject, shape = _resolve(spec)
    rows = _Rows(spec.num_frames)
    video_path = out / f"{spec.name}.avi"
    remove_dead_partials(out, {video_path.name, f"{spec.name}.gt.npz", f"{spec.name}.gt.json"})
    with VideoSink(video_path, spec.intrinsics.width, spec.intrinsics.height, spec.fps) as sink:
        for img, frame_truth in iter_sequence(spec, batch_size):
            sink.write(img)
            rows.add(frame_truth)
            if progress is not None:
                progress(sink.frames_written, spec.num_frames)
        codec = sink.codec
        gt = _ground_truth(spec, subject, shape, rows)
        with folder_locked(out):  # (another writer of this folder puts its files in place before or after ours)
            for stale in (out / f"{spec.name}.gt.npz", out / f"{spec.name}.gt.json"):  # before the video's rename
                stale.unlink(missing_ok=True)
            sink.close()
            extra: dict[str, object] = {"video": video_path.name, "codec": codec.strip()}
            npz_path, json_path = save_ground_truth(gt, out / spec.name, extra)
    return SequenceFiles(video_path, npz_path, json_path, codec, spec.num_frames)
