"""Look-ahead initialisation: the first frame's pose re-estimated photometrically from later frames.

From one frontal view the landmark fit (Eq. 2) cannot separate the head's pitch from the face's vertical
proportions: on a face unlike the model's mean (the James scan) it comes out pitched by 4-8 degrees with every
shape unit free, and further with the vertical ones held (:attr:`~torchface.tracker.fit.FitConfig.held_shape_units`),
and because every later pose is measured against the first frame's template, that pitch becomes pose error of
several degrees at +-45 degrees of yaw. Frames where the head has turned see the face from another side, and
what the first frame's texture must look like there fixes the pitch.

:func:`lookahead_fit` tracks a stream's first frames as usual until the head has turned by
``LookaheadConfig.yaw_deg`` to each side (the *keyframes*, :func:`select_keyframes`; with one side only, the
stream is refined from that one when ``min_keyframes`` is 1, the default), then :func:`refine_first_fit`
minimises jointly over the first frame's pose, its starting expression, the shape units the landmark fit held
(:attr:`~torchface.tracker.fit.FitConfig.held_shape_units`, or those listed) and each keyframe's pose and
illumination (gain, bias, three directional terms)::

    sum_k sum_p w * 2 huber( I_k(pi(P_k X_p)) - I_0(pi(P_0 X_p)) (1 + g_k + n_p^k . l_k) - b_k )
      + sum_landmarks |pi(P_0 L) - l|^2 + priors                      (the landmark fit's own terms, Eq. 2)

over the first frame's template points ``X_p`` (fixed triangle and barycentric coordinates), each used where
it is visible (z-buffer) and facing the camera in both frames. Both images are resampled at every
iteration; Levenberg-Marquardt with Jacobians by forward-mode autograd, coarse to fine, in float64. The
caller then starts tracking at the first frame again from the refined fit
(``initialise(..., fit=...)``): a two-pass start for a video whose frames are all at hand (files,
dataloaders, evaluation), not for a live stream.

Measured with ``evaluate.py --lookahead --noise-seeds 0,1,2,3`` (max rotation error relative to frame 0, seeds
0 / 1 / 2 / 3, degrees): ``scan_motion`` 2.04 / 2.11 / 1.86 / 2.06 (mean 0.50 / 0.68 / 0.51 / 0.50), against
7.19 / 7.58 / 5.41 / 5.75 without any refinement; ``pose_sweep`` 0.41 / 0.77 / 0.61 / 0.71. With the earlier
defaults (no held shape units, two keyframes at 20 degrees) the first frame's own rotation error on the James
scan went from 4.0-7.8 to 1.2-1.7 degrees, and its depth could move by several millimetres (``pose_sweep`` seed
3: first-frame translation error 0.6 -> 9.5 mm). Scenarios without a turn in their first frames keep the
landmark fit.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from torchface._autocast import full_precision
from torchface.appearance.sampling import image_with_gradients, sample_at_pixels
from torchface.backend import Backend
from torchface.geometry._checks import check_bool, check_int, check_ints, check_real
from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import project_points, project_points_jacobian
from torchface.geometry.so3 import (
    axis_angle_to_matrix, geodesic_angle_deg, hat, left_jacobian, matrix_to_axis_angle, matrix_to_euler,
)
from torchface.model.face_model import FaceModel
from torchface.rendering.rasterizer import rasterize_coverage
from torchface.rendering.visibility import points_visible
from torchface.template.points import gather_face_attributes, point_normals, select_template_pixels
from torchface.tracker.fit import (
    FitConfig, LandmarkFit, check_landmark_type, fit_landmarks, held_shape_indices, landmark_targets, prior_scale,
    shape_precisions, shape_prior_vector, sparse_samples,
)
from torchface.tracker.step import TrackerConfig, check_api_types, gray_pyramid, level_intrinsics

__all__ = ["LookaheadConfig", "select_keyframes", "view_yaw_deg", "refine_first_fit", "lookahead_fit"]

_NUM_LIGHT = 5  # gain, bias, three directional terms (Eq. 19)


@dataclass(frozen=True)
class LookaheadConfig:
    """Settings of the look-ahead initialisation (module docstring).

    Attributes:
        yaw_deg: a keyframe is the first frame whose tracked yaw, relative to the first frame's, reaches this on
            one side; one keyframe per side. 10: with the landmark fit's vertical units held
            (:attr:`~torchface.tracker.fit.FitConfig.held_shape_units`), the James scan's first frame is pitched
            and its first turn drifts before the head has turned 20 degrees (``scan_motion`` max 5.4-7.6 degrees
            over landmark-noise draws 0-3 without the re-anchoring); re-anchored at 10 degrees, 2.7-3.3.
        max_frames: frames tracked at most while looking for the keyframes (the first frame included).
        min_keyframes: a stream with fewer keyframes keeps the landmark fit. One (the first side the head turns
            to) by default, so that the re-anchoring comes early; 2 waits for a turn to each side.
        min_confidence: a frame is a keyframe candidate only with at least this tracking confidence. 0.3: on the
            James scan with noise draw 1 the first frame's pitch is so far off that the confidence falls below
            0.5 before the head has turned 20 degrees, so at 0.5 that stream never had its first keyframe and was
            never re-anchored (``scan_motion`` mean 2.30 degrees; 1.13 at 0.3). The other draws and scenarios,
            and both long runs, track the same at 0.3 as at 0.5.
        shape_units: indices of the shape units re-estimated (the others keep the landmark fit's values); empty:
            none; None: the units the landmark fit held (:attr:`~torchface.tracker.fit.FitConfig.held_shape_units`,
            the ``held_shape_units`` argument of :func:`refine_first_fit`) but those named in
            ``kept_shape_units``. A keyframe sees the face from the
            side, which separates the pitch from the vertical proportions that the frontal view confounds.
        shape_prior_precision: prior precision of the re-estimated shape units (one value, or one per unit of
            the model as :attr:`~torchface.tracker.fit.FitConfig.shape_prior_precision`); None: the landmark
            fit's. 2 (the landmark fit's default for the units it does not hold) lets the held units go (a sparse
            start's at least :attr:`~torchface.tracker.fit.FitConfig.sparse_shape_prior_precision`, as its fit held
            them: :func:`landmark_fit_priors`). Given, as
            the landmark fit's, at its ``reference_focal_px`` (scaled with them: ``prior_scale`` of
            :func:`refine_first_fit`).
        kept_shape_units: names of held units that ``shape_units=None`` leaves at the landmark fit's values
            (each must be one of the model's shape units: :func:`refine_first_fit` checks; refused with
            ``shape_units`` given); empty by default. ``("Eyes vertical position",)`` with
            ``fit_expression=False`` leaves the eyelids where the first frame's landmarks placed them, which eyes
            closed needs (README, Known limitations, "Eyes closed"): with the tracker's ``expression_quota=0.06``
            and ``expression_sparsity=0.03`` on the 640x480 ``expressions`` scenario from exact first-frame
            landmarks, eyes closed RMSE 0.031 / r 0.99 (0.090 with this start's defaults, 0.105 keeping the eyes'
            position but re-estimating the expression, 0.150 the other way round; 0.034 without the online start).
        fit_expression: re-estimate the starting expression (the first frame's; each keyframe's points add the
            expression change the tracker measured there, ``key_expression`` of :func:`refine_first_fit`).
        photometric_weight: weight of the photometric term (squared landmark pixels per squared gray level);
            1e3 and 1e5 tracked worse than 1e4 on the James scan.
        iterations: Levenberg-Marquardt iterations per pyramid level, coarsest first (levels 2, 1, 0). The
            online start and :func:`lookahead_fit` refine on at most the tracker's
            :attr:`~torchface.tracker.step.TrackerConfig.num_levels` levels, the finest ones
            (:func:`levels_of`): a tracker of fewer levels takes frames too small for this pyramid.
        max_points: first-frame template points used.
        gradient_threshold: minimum gradient magnitude of a point (as the tracker's templates).
        huber_k: Huber constant, in robust standard deviations (MAD) of each keyframe's residual.
        min_facing_cos: a point is used where its normal faces the viewing ray at least this much in both frames.
        silhouette_margin: a point is used only where it lies at least this many pixels of the pyramid level
            being refined inside the mesh's outline (and its holes) in both frames; 0: anywhere on the mesh. The
            pyramid's blur mixes the background into the face near the outline, and the background does not
            turn with the head: those points pull the mesh smaller in the image, i.e. deeper. On a rendered 18
            degree turn at 600 mm (CANDIDE-3, 1 degree a frame, exact first-frame landmarks, the default
            :class:`~torchface.tracker.FaceTracker`) the re-anchored mesh ends 4.3 / 25.4 / 33.2 mm too deep at
            640x480 / 320x240 / 160x120 without the margin (17.8-25.4 mm at 320x240 for turns of 0.5-2 degrees a
            frame), 0.3 / 5.6 / -0.3 mm with 2. Not the default: those points carry yaw and pitch, and with 2 the
            standard scenarios' rotation errors grew (``expressions`` 0.20 -> 0.46 degrees mean, ``scan_motion``
            0.83 -> 0.97) while their translation errors hardly changed (README, Known limitations), and the
            refinement took 2.9 s instead of 1.3 at 640x480.
    """

    yaw_deg: float = 10.0
    max_frames: int = 150
    min_keyframes: int = 1
    min_confidence: float = 0.3
    shape_units: tuple[int, ...] | None = None
    kept_shape_units: tuple[str, ...] = ()
    shape_prior_precision: float | tuple[float, ...] | None = 2.0
    fit_expression: bool = True
    photometric_weight: float = 1e4
    iterations: tuple[int, ...] = (10, 8, 6)
    max_points: int = 3000
    gradient_threshold: float = 0.01
    huber_k: float = 1.345
    min_facing_cos: float = 0.15
    silhouette_margin: int = 0

    def __post_init__(self) -> None:
        for name in ("yaw_deg", "min_confidence", "photometric_weight", "gradient_threshold", "huber_k",
                     "min_facing_cos"):  # fmt: skip
            object.__setattr__(self, name, check_real(getattr(self, name), name))  # "10": "'<' not supported"
        if not 0.0 < self.yaw_deg < 90.0:
            raise ValueError(f"yaw_deg must be in (0, 90), got {self.yaw_deg}")
        object.__setattr__(self, "fit_expression", check_bool(self.fit_expression, "fit_expression"))
        for name, low in (("max_frames", 2), ("min_keyframes", 1), ("max_points", 1), ("silhouette_margin", 0)):
            object.__setattr__(self, name, check_int(getattr(self, name), name, low))
        object.__setattr__(self, "iterations", check_ints(self.iterations, "iterations", 0))
        if self.shape_units is not None:
            object.__setattr__(self, "shape_units", check_ints(self.shape_units, "shape_units", 0))
        kept = self.kept_shape_units
        if not isinstance(kept, tuple) or not all(isinstance(n, str) for n in kept) or len(set(kept)) != len(kept):
            raise ValueError(f"kept_shape_units must be a tuple of distinct unit names, got {kept!r}")
        if kept and self.shape_units is not None:  # (they were ignored: shape_units names every unit re-estimated)
            raise ValueError(f"kept_shape_units {kept} applies with shape_units=None (the held units); with "
                             f"shape_units={self.shape_units} given, leave the kept units out of it")  # fmt: skip
        if self.min_keyframes not in (1, 2):
            raise ValueError(f"min_keyframes must be 1 or 2 (one keyframe per side), got {self.min_keyframes!r}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be in [0, 1], got {self.min_confidence}")
        if not self.photometric_weight > 0 or not self.huber_k > 0 or not 0.0 <= self.min_facing_cos < 1.0:
            raise ValueError(
                "photometric_weight and huber_k must be positive and min_facing_cos in [0, 1), got "
                f"{self.photometric_weight}, {self.huber_k}, {self.min_facing_cos}"
            )
        if not self.iterations:
            raise ValueError(f"iterations must be a non-empty tuple of ints >= 0, got {self.iterations!r}")
        if self.gradient_threshold < 0:
            raise ValueError(f"gradient_threshold must be >= 0, got {self.gradient_threshold}")
        units = self.shape_units
        if units is not None and len(set(units)) != len(units):
            raise ValueError(f"shape_units must be distinct non-negative indices, got {self.shape_units!r}")
        if self.shape_prior_precision is not None:
            FitConfig(shape_prior_precision=self.shape_prior_precision)  # the same validation


def kept_shape_indices(
    config: LookaheadConfig, shape_names: Sequence[str], name: str = "kept_shape_units"
) -> set[int]:
    """Indices (into ``shape_names``, the model's) of :attr:`LookaheadConfig.kept_shape_units`.

    Raises:
        ValueError: a name that is not the model's (a misspelt one would otherwise keep nothing, without a word),
            the message naming the setting as ``name``.
    """
    missing = [n for n in config.kept_shape_units if n not in shape_names]
    if missing:
        raise ValueError(f"{name} {missing} are not among the model's shape units {tuple(shape_names)}")
    return {i for i, n in enumerate(shape_names) if n in config.kept_shape_units}


def levels_of(config: LookaheadConfig, num_levels: int) -> LookaheadConfig:
    """``config`` refining on at most ``num_levels`` pyramid levels (a tracker's
    :attr:`~torchface.tracker.step.TrackerConfig.num_levels`): its finest ones, ``iterations[-num_levels:]``.

    The tracker checks that its frames hold ``num_levels`` levels (at least ``3 * 2 ** (num_levels - 2)`` pixels a
    side); the default three of the refinement needed 6, and a tracker of 1 or 2 levels on smaller frames failed at
    its re-anchoring, in the middle of the stream (``images must be (B, C, H, W) with H, W >= 3``).
    """
    if len(config.iterations) <= num_levels:
        return config
    return replace(config, iterations=config.iterations[-num_levels:])


def view_yaw_deg(rotation: Tensor, translation: Tensor | None = None) -> Tensor:
    """``(...)`` the yaw (degrees) of the head seen along the camera's ray to it: that of ``R_ray^T R``, where
    ``R_ray`` is the smallest rotation taking the optical axis to the direction of ``translation``.

    A camera pan, a shake or a moving crop turns the head in the camera frame (its yaw changes by the pan's angle)
    but not about the ray the camera sees it along: the view, what a look-ahead keyframe must add, is the same.
    This yaw changes only with the view. Without ``translation``, the yaw of ``rotation``.

    Args:
        rotation: ``(..., 3, 3)`` head rotations (OpenCV camera frame).
        translation: ``(..., 3)`` head translations (mm), or None.
    """
    R = rotation.to(torch.float64)
    if translation is not None:
        d = torch.nn.functional.normalize(translation.to(torch.float64), dim=-1)
        axis = torch.stack([-d[..., 1], d[..., 0], torch.zeros_like(d[..., 0])], -1)  # e_z x d
        s = axis.norm(dim=-1, keepdim=True)
        angle = torch.atan2(s, d[..., 2:3])
        aa = torch.where(s > 1e-12, axis / s.clamp_min(1e-12) * angle, torch.zeros_like(axis))
        R = axis_angle_to_matrix(aa).transpose(-1, -2) @ R
    return matrix_to_euler(R)[..., 0]


#: A keyframe's turn must also be at least this fraction of ``LookaheadConfig.yaw_deg`` seen along the camera's ray
#: (:func:`view_yaw_deg`), so that a camera pan, shake or moving crop, which turns the head in the camera frame but
#: shows no new side of it, is no keyframe: on GRID clip bbaf2n with frames 30-39 shifted 120 px to the left (about
#: 20 degrees of yaw in the camera frame, 2.5 seen along the camera's ray), the re-anchoring at that view left the
#: rest of the clip (frames 40-74) 0.61 degrees mean off the clean run, 0.01 with this check as without the online
#: start (``python scripts/doc_figures.py grid-pan``; shifted to the right, and the other ten clips shifted either
#: way, re-anchored no view even without the check). Half: a real turn of an off-centre head still counts at the
#: frame it would without the check (the five standard scenarios track as before).
VIEW_TURN_FRACTION: float = 0.5

#: The online start (:func:`~torchface.tracker.managed.initialise_managed`'s ``refine_first``) stops waiting for a
#: stream's keyframe, which then keeps its landmark fit, when the stream's estimate turns more than this (degrees)
#: from the pose its step started from (the previous frame's): a jump no head makes between two frames (a head
#: turning 400 degrees a second at 25 fps turns 16 a frame), which a video cut gives. A 160x120 cut to the same face
#: 20 mm across, 60 mm nearer and turned 12 degrees was tracked 54.5 degrees off at confidence 0.74 on the cut's
#: frame; that frame became the keyframe, and the stream re-anchored on it scored 0.02 from then on and stayed LOST
#: to the end, with a detector too (without the online start it was right, 0.4 degrees, from the next frame). The
#: look-ahead relates the first frame to a later view of the same shot; after a cut even a right keyframe misleads it
#: (cut 8 mm across, 60 nearer, turned -30 degrees: re-anchored on the cut's frame, 2.7 degrees off, or on the next,
#: 1.2 off, the stream went on 15 mm aside at confidence 0.01-0.19; 0.93-0.97 with this). Never reached in the
#: evaluation's scenarios: at full size each waits until its re-anchoring (frames 7-70) with steps of at most 2.6
#: degrees (long runs 0.95), so they track as before. :func:`lookahead_fit` ends a stream's look-ahead at such a
#: turn too (no keyframe from the cut's frame on): refined against the cut's frame and the next (its keyframes),
#: the first frame of that 160x120 clip came out 4.2 degrees and 35 mm off, against the landmark fit's 1.0 degree
#: and 0.9 mm. The standard scenarios' look-ahead windows turn at most 5.4 degrees a step (640x480, landmark-noise
#: draws 0-3), so their keyframes and ``evaluate.py --lookahead`` figures are as before.
KEYFRAME_MAX_STEP_DEG: float = 20.0


def is_video_cut(start_rotation: Tensor, rotation: Tensor) -> Tensor:
    """``(B,)`` bool: whether a step from ``start_rotation`` to ``rotation`` (both ``(B, 3, 3)``) turned more than
    :data:`KEYFRAME_MAX_STEP_DEG`, a jump no head makes between two frames (a video cut): it ends a stream's wait
    for keyframes, online and in :func:`lookahead_fit`."""
    return geodesic_angle_deg(rotation, start_rotation.to(rotation.dtype)) > KEYFRAME_MAX_STEP_DEG


def is_keyframe_turn(rel_yaw: Tensor, rel_view_yaw: Tensor, yaw_deg: float) -> Tensor:
    """Whether a yaw change (degrees, towards the side looked for: positive) is a keyframe's turn: ``yaw_deg`` in
    the camera frame and :data:`VIEW_TURN_FRACTION` of it seen along the camera's ray (:func:`view_yaw_deg`)."""
    return (rel_yaw >= yaw_deg) & (rel_view_yaw >= VIEW_TURN_FRACTION * yaw_deg)


def select_keyframes(
    rotation: Tensor, yaw_deg: float, confident: Tensor | None = None, translation: Tensor | None = None
) -> list[int]:
    """The first frame whose yaw relative to frame 0 reaches ``+yaw_deg``, and the first reaching ``-yaw_deg`` (with
    ``translation``: whose turn also shows along the camera's ray, :func:`is_keyframe_turn`).

    Args:
        rotation: ``(T, 3, 3)`` one stream's rotations, frame 0 first.
        yaw_deg: positive threshold (degrees).
        confident: ``(T,)`` bool, frames that may be chosen (None: all).
        translation: ``(T, 3)`` the translations, or None: with them a keyframe's turn must also be seen along
            the camera's ray (:func:`is_keyframe_turn`), so that a camera pan is no turn.

    Returns:
        Sorted frame indices (0, 1 or 2 of them: a side the head never reaches has none).
    """
    if not isinstance(rotation, Tensor) or rotation.dim() != 3 or rotation.shape[1:] != (3, 3):
        raise ValueError(f"rotation must be (T, 3, 3), got {getattr(rotation, 'shape', type(rotation))}")
    if translation is not None and tuple(translation.shape) != (rotation.shape[0], 3):
        raise ValueError(f"translation must be ({rotation.shape[0]}, 3), got {tuple(translation.shape)}")
    if not 0.0 < yaw_deg < 180.0:  # 0 or less chose frame 0 itself, twice, as the keyframe of both sides
        raise ValueError(f"yaw_deg must be a positive angle (degrees, below 180), got {yaw_deg}")
    if confident is not None and (not isinstance(confident, Tensor) or confident.dtype != torch.bool
                                  or tuple(confident.shape) != (rotation.shape[0],)):  # fmt: skip
        # (one value was broadcast to every frame; float confidences were read as True wherever not 0)
        got = (f"{confident.dtype} {tuple(confident.shape)}" if isinstance(confident, Tensor)
               else type(confident).__name__)  # fmt: skip
        raise ValueError(f"confident must be a ({rotation.shape[0]},) bool tensor or None, got {got}")
    yaw = matrix_to_euler(rotation.to(torch.float64))[:, 0]
    rel = (yaw - yaw[0]).cpu()
    view = view_yaw_deg(rotation, translation)
    view_rel = (view - view[0]).cpu()
    ok = torch.ones_like(rel, dtype=torch.bool) if confident is None else confident.to(torch.bool).cpu()
    out = []
    for side in (1.0, -1.0):
        hit = torch.nonzero(is_keyframe_turn(side * rel, side * view_rel, yaw_deg) & ok).flatten()
        if hit.numel():
            out.append(int(hit[0]))
    return sorted(out)


def _near_background(background: Tensor, points: Tensor, intrinsics: Intrinsics, radius: int) -> Tensor:
    """``(N,)`` bool: whether ``points`` ``(N, 3)`` (camera frame) project within ``radius`` pixels (a square) of
    a ``background`` ``(H, W)`` bool pixel, by their nearest pixel centre (clamped into the image)."""
    x = background.to(points.dtype)[None, None]
    k = 2 * radius + 1
    pool = torch.nn.functional.max_pool2d
    near = pool(pool(x, (k, 1), 1, (radius, 0)), (1, k), 1, (0, radius))[0, 0] > 0  # separable: the square's max
    uv = project_points(points[None], intrinsics)[0].round().long()
    return near[uv[:, 1].clamp(0, near.shape[0] - 1), uv[:, 0].clamp(0, near.shape[1] - 1)]


def landmark_fit_priors(
    model: FaceModel, fit_config: FitConfig, intrinsics: Intrinsics, landmarks_px: Tensor | None = None,
    landmark_weights: Tensor | None = None,
) -> dict:
    """The landmark fit's settings as :func:`refine_first_fit` takes them (keyword arguments): its shape
    precisions per unit, bounds, expression precision and held units, for ``model``, the factor on the
    precisions for the camera ``intrinsics`` that :func:`~torchface.tracker.fit.fit_landmarks` applies
    (:func:`~torchface.tracker.fit.prior_scale`: exactly 1 at the reference focal length, 640 px), and the least
    precisions of a sparse start.

    Args:
        landmarks_px: ``(L, 2)`` one stream's first-frame landmarks and landmark_weights ``(L,)`` (or None), as given
            to the fit: a stream the fit found sparse (:func:`~torchface.tracker.fit.sparse_samples`) is refined with
            its shape and expression precisions at least
            :attr:`~torchface.tracker.fit.FitConfig.sparse_shape_prior_precision` and
            :attr:`~torchface.tracker.fit.FitConfig.sparse_expression_prior_precision` (``min_shape_prior_precision``,
            ``min_expression_prior_precision``; 0 for a dense one, and without ``landmarks_px``).
    """
    precision = shape_precisions(fit_config, model.shape_names, torch.float64, "cpu")
    sparse = False
    if landmarks_px is not None:
        check_landmark_type(landmarks_px, "(L, 2)")
        if landmarks_px.dim() != 2 or landmarks_px.shape[-1] != 2:  # (a batch's (B, L, 2) was "Boolean value of
            # Tensor with more than one value is ambiguous")
            raise ValueError(f"landmarks_px must be one stream's (L, 2) landmarks, got {tuple(landmarks_px.shape)}")
        lm = landmarks_px.detach().to(dtype=model.dtype)  # (positive in the model's dtype, as the fit counts them)
        count = (landmark_targets(lm, landmark_weights)[1] > 0).sum(-1)
        sparse = bool(sparse_samples(fit_config, count, model.num_shape, model.num_animation))
    return dict(
        shape_prior_precision=tuple(precision.tolist()), shape_bound=fit_config.shape_bound,
        expression_prior_precision=fit_config.expression_prior_precision,
        held_shape_units=held_shape_indices(fit_config, model.shape_names),
        prior_scale=prior_scale(fit_config, intrinsics),
        min_shape_prior_precision=fit_config.sparse_shape_prior_precision if sparse else 0.0,
        min_expression_prior_precision=fit_config.sparse_expression_prior_precision if sparse else 0.0,
    )


@full_precision
def refine_first_fit(
    model: FaceModel,
    frames: Tensor,
    intrinsics: Intrinsics,
    landmarks_px: Tensor,
    fit: LandmarkFit,
    key_rotation: Tensor,
    key_translation: Tensor,
    *,
    key_expression: Tensor | None = None,
    landmark_weights: Tensor | None = None,
    shape_prior_precision: float | tuple[float, ...] = 2.0,
    shape_bound: float = 1.0,
    expression_prior_precision: float = 2.0,
    held_shape_units: tuple[int, ...] = (),
    prior_scale: float = 1.0,
    min_shape_prior_precision: float = 0.0,
    min_expression_prior_precision: float = 0.0,
    config: LookaheadConfig = LookaheadConfig(),
    backend: Backend = Backend.AUTO,
) -> LandmarkFit:
    """One stream's first-frame fit refined against keyframes (module docstring).

    Args:
        model: the face model.
        frames: ``(1 + K, 3, H, W)`` float in [0, 1]: the first frame, then the ``K >= 1`` keyframes.
        intrinsics: their camera.
        landmarks_px: ``(L, 2)`` the first frame's landmarks (NaN = missing), as given to :func:`fit_landmarks`.
        fit: the first frame's :class:`LandmarkFit` (batch 1): the start, and the shape units kept.
        key_rotation: ``(K, 3, 3)`` and key_translation ``(K, 3)``: the keyframes' tracked poses (the start).
        key_expression: ``(K, A)`` the keyframes' tracked expressions relative to the first frame's
            (:attr:`~torchface.tracker.step.TrackResult.expression`): each keyframe's points are placed with the
            refined starting expression plus its own. None: zeros, the first frame's expression in every keyframe.
            A face whose expression changed between the first frame and a keyframe otherwise pulls that change
            into the starting expression.
        landmark_weights: ``(L,)`` or None, as given to :func:`fit_landmarks`.
        shape_prior_precision, shape_bound, expression_prior_precision: the landmark fit's
            (:class:`~torchface.tracker.fit.FitConfig`; the shape precisions as
            :func:`~torchface.tracker.fit.shape_precisions` gives them).
        held_shape_units: the shape units the landmark fit held
            (:func:`~torchface.tracker.fit.held_shape_indices`): those re-estimated when ``config.shape_units``
            is None (but ``config.kept_shape_units``).
        prior_scale: the factor on every prior precision (those above and ``config.shape_prior_precision``), so
            that the landmark terms and the priors weigh against each other as in the fit refined:
            :func:`~torchface.tracker.fit.prior_scale` of its config for the camera, which
            :func:`landmark_fit_priors` gives and :func:`lookahead_fit` and the online start pass (they passed the
            precisions unscaled: at 160 x 120, whose fit scales them by 1/16, the refinement held the shape units 16
            times as hard as the fit did; with the photometric term negligible, a frame's refinement came out 0.03
            degrees (320 x 240) and 0.22 (160 x 120) from that of the same scene at 640 x 480, now the same). 1: as
            given, in the camera's squared pixels. The photometric term is not scaled (``photometric_weight`` was
            tuned at 640 x 480).
        min_shape_prior_precision, min_expression_prior_precision: the least precisions of the re-estimated shape
            units and expression (before ``prior_scale``, as the others), whatever the ones above and
            ``config.shape_prior_precision``: those of a sparse start (:func:`landmark_fit_priors`, as the fit held
            them; 0 for a dense one). The dense precisions let a 5-point start's units absorb the pose again.
        config: :class:`LookaheadConfig`.
        backend: :class:`~torchface.backend.Backend` of the first frame's template points (the tracker's
            :attr:`~torchface.tracker.step.TrackerConfig.backend`).

    Returns:
        The refined :class:`LandmarkFit` (batch 1, the model's dtype); ``rms_px`` is its landmark RMS.
    """
    return _refine_first_fit(
        model, frames, intrinsics, landmarks_px, fit, key_rotation, key_translation, key_expression=key_expression,
        landmark_weights=landmark_weights,
        shape_prior_precision=shape_prior_precision, shape_bound=shape_bound,
        expression_prior_precision=expression_prior_precision, held_shape_units=held_shape_units,
        prior_scale=prior_scale, min_shape_prior_precision=min_shape_prior_precision,
        min_expression_prior_precision=min_expression_prior_precision, config=config, backend=backend,
    )[0]  # fmt: skip


def _refine_first_fit(
    model: FaceModel,
    frames: Tensor,
    intrinsics: Intrinsics,
    landmarks_px: Tensor,
    fit: LandmarkFit,
    key_rotation: Tensor,
    key_translation: Tensor,
    *,
    key_expression: Tensor | None = None,
    landmark_weights: Tensor | None,
    shape_prior_precision: float | tuple[float, ...],
    shape_bound: float,
    expression_prior_precision: float,
    config: LookaheadConfig,
    held_shape_units: tuple[int, ...] = (),
    prior_scale: float = 1.0,
    min_shape_prior_precision: float = 0.0,
    min_expression_prior_precision: float = 0.0,
    analytic: bool = True,
    backend: Backend = Backend.AUTO,
) -> tuple[LandmarkFit, Tensor, Tensor]:
    """:func:`refine_first_fit`, also returning the keyframes' refined poses: rotation ``(K, 3, 3)`` and
    translation ``(K, 3)`` (the model's dtype), in the frame of the refined first pose. ``analytic``: the
    Jacobian in closed form (False: by forward-mode autograd, the reference the tests compare it with)."""
    K = frames.shape[0] - 1
    if frames.dim() != 4 or K < 1 or frames.shape[1] not in (1, 3):  # gray frames too, as the tracker takes them
        raise ValueError(f"frames must be (1 + K, 3 or 1, H, W) with K >= 1 keyframes, got {tuple(frames.shape)}")
    if key_rotation.shape != (K, 3, 3) or key_translation.shape != (K, 3):
        raise ValueError(f"key poses must be ({K}, 3, 3) and ({K}, 3), got {tuple(key_rotation.shape)}, "
                         f"{tuple(key_translation.shape)}")  # fmt: skip
    if key_expression is not None and key_expression.shape != (K, model.num_animation):
        raise ValueError(f"key_expression must be ({K}, {model.num_animation}), got {tuple(key_expression.shape)}")
    if key_expression is not None and not bool(torch.isfinite(key_expression).all()):
        raise ValueError("key_expression must be finite")
    if fit.rotation.shape[0] != 1:
        raise ValueError(f"fit must be one stream's (batch 1), got batch {fit.rotation.shape[0]}")
    L = model.num_landmarks  # (a batched (1, L, 2), as fit_landmarks takes, was a RuntimeError about sizes)
    check_landmark_type(landmarks_px, f"({L}, 2)")
    if tuple(landmarks_px.shape) != (L, 2):
        raise ValueError(f"landmarks_px must be ({L}, 2), one stream's, got {tuple(landmarks_px.shape)}")
    if landmark_weights is not None and (not isinstance(landmark_weights, Tensor)
                                         or tuple(landmark_weights.shape) != (L,)):  # fmt: skip
        got = tuple(landmark_weights.shape) if isinstance(landmark_weights, Tensor) else type(landmark_weights).__name__
        raise ValueError(f"landmark_weights must be ({L},) or None, got {got}")
    pscale = check_real(prior_scale, "prior_scale")
    if not (math.isfinite(pscale) and pscale > 0):  # (NaN, infinite or negative precisions would reach the solve)
        raise ValueError(f"prior_scale must be a positive finite number, got {prior_scale!r}")
    least = {}
    for name, value in (("min_shape_prior_precision", min_shape_prior_precision),
                        ("min_expression_prior_precision", min_expression_prior_precision)):  # fmt: skip
        least[name] = check_real(value, name)
        if not (math.isfinite(least[name]) and least[name] >= 0):
            raise ValueError(f"{name} must be finite and non-negative, got {value!r}")
    S, A = model.num_shape, model.num_animation
    if config.shape_units is None:
        kept = kept_shape_indices(config, model.shape_names)
        free_units = tuple(i for i in held_shape_units if i not in kept)
    else:
        free_units = config.shape_units
    if any(s >= S for s in free_units):
        raise ValueError(f"shape_units must be < {S} (the model's shape units), got {free_units}")
    dt, dev = torch.float64, model.device
    m = model.to(dtype=dt)
    free_su = torch.tensor(free_units, dtype=torch.long, device=dev)
    nf = len(free_units)
    nA = A if config.fit_expression else 0
    levels = list(reversed(range(len(config.iterations))))
    side = 3 * 2 ** (len(levels) - 2) if len(levels) > 1 else 1  # pyr_down needs 3 pixels a side (as the tracker)
    if min(frames.shape[-2:]) < side:
        raise ValueError(f"frames must be at least {side}x{side} pixels for the refinement's {len(levels)} pyramid "
                         f"levels (config.iterations), got {frames.shape[-1]}x{frames.shape[-2]}")  # fmt: skip
    pyramid = gray_pyramid(frames.to(device=dev, dtype=dt), len(levels))  # the tracker's levels
    gray = pyramid[0]
    imgs = [image_with_gradients(g) for g in pyramid]
    intrs = [level_intrinsics(intrinsics, lv, g.shape[-2], g.shape[-1]) for lv, g in enumerate(pyramid)]

    sig0, al0 = fit.shape_coeffs.to(dt), fit.anim_coeffs.to(dt)
    px = select_template_pixels(
        m, sig0, al0, fit.rotation.to(dt), fit.translation.to(dt), gray[:1], intrinsics,
        max_points=min(config.max_points, gray.shape[-2] * gray.shape[-1]),
        gradient_threshold=config.gradient_threshold, backend=backend,
    )  # fmt: skip
    keep = px.valid[0]
    fi, bary = px.face_index[:, keep], px.bary[:, keep]
    target, lw = landmark_targets(landmarks_px.to(device=dev, dtype=dt).contiguous(),  # as fit_landmarks
                                  None if landmark_weights is None else landmark_weights.to(dt).contiguous())
    # x = [aa0 (3), t0 (3), free shape units (nf), expression (nA), per keyframe: aa, t, light (11)]
    o_sig, o_al = 6, 6 + nf
    o_k = o_al + nA
    P = o_k + 11 * K
    x = torch.zeros(P, dtype=dt, device=dev)
    x[0:3], x[3:6] = fit.axis_angle[0].to(dt), fit.translation[0].to(dt)
    x[o_sig:o_al] = sig0[0, free_su]
    if nA:
        x[o_al:o_k] = al0[0]
    key_aa = matrix_to_axis_angle(key_rotation.to(device=dev, dtype=dt))
    for k in range(K):
        x[o_k + 11 * k : o_k + 11 * k + 3] = key_aa[k]
        x[o_k + 11 * k + 3 : o_k + 11 * k + 6] = key_translation[k].to(device=dev, dtype=dt)
    lo = torch.full((P,), -float("inf"), dtype=dt, device=dev)
    hi = -lo
    prior = torch.zeros(P, dtype=dt, device=dev)
    lo[o_sig:o_al], hi[o_sig:o_al] = -shape_bound, shape_bound
    if config.shape_prior_precision is not None:
        shape_prior_precision = config.shape_prior_precision
    prior[o_sig:o_al] = shape_prior_vector(shape_prior_precision, S, dt, dev)[free_su] * pscale
    if nA:
        lo[o_al:o_k], hi[o_al:o_k] = m.animation_ranges[:, 0], m.animation_ranges[:, 1]
        prior[o_al:o_k] = expression_prior_precision * pscale
    if least["min_shape_prior_precision"] > 0:  # a sparse start (0: dense, its precisions as they are, to the bit)
        prior[o_sig:o_al] = prior[o_sig:o_al].clamp_min(least["min_shape_prior_precision"] * pscale)
    if least["min_expression_prior_precision"] > 0:
        prior[o_al:o_k] = prior[o_al:o_k].clamp_min(least["min_expression_prior_precision"] * pscale)
    x = torch.maximum(torch.minimum(x, hi), lo)

    def coeffs(x: Tensor) -> tuple[Tensor, Tensor]:
        sig = sig0[0].index_put((free_su,), x[o_sig:o_al]) if nf else sig0[0]
        return sig, (x[o_al:o_k] if nA else al0[0])

    # The points and landmarks are linear in the free units (Eq. 1): the starting ones plus the units' gathered
    # displacements times the change of the coefficients. Gathered once, so that jacfwd's tangents go through
    # (N, 3) sums instead of deforming the whole mesh (2.3 -> 1.8 s per refinement on one thread, benchmark.py's
    # frames, with the same results to the bit).
    units = torch.cat([m.shape_units[free_su], m.animation_units[:nA]]).permute(1, 0, 2)  # (V, nf + nA, 3)
    start = m.deform(sig0[:1], al0[:1])  # (1, V, 3) at the starting coefficients
    X_start = gather_face_attributes(start, m.faces, fi, bary, batched=True)[0]  # (N, 3)
    L_start = m.landmarks_3d(start)[0]
    if units.shape[1]:
        X_units = gather_face_attributes(units, m.faces, fi, bary, batched=False)[0]  # (N, nf + nA, 3)
        L_units = m.landmarks_3d(units.permute(1, 0, 2)).permute(1, 0, 2)  # (L, nf + nA, 3)
    else:  # nothing free but the poses
        X_units, L_units = X_start.new_zeros(X_start.shape[0], 0, 3), L_start.new_zeros(L_start.shape[0], 0, 3)
    x_start = torch.cat([sig0[0, free_su], al0[0, :nA]])
    # Each keyframe's own expression change (key_expression): a fixed offset of its points, ``(K, N, 3)``.
    key_alpha = X_start.new_zeros(K, A) if key_expression is None else key_expression.to(device=dev, dtype=dt)
    if bool((key_alpha != 0).any()):
        X_anim = gather_face_attributes(m.animation_units.permute(1, 0, 2), m.faces, fi, bary, batched=False)[0]
        key_delta = torch.einsum("ka,nad->knd", key_alpha, X_anim)
    else:
        key_delta = X_start.new_zeros(K, X_start.shape[0], 3)

    def geometry(x: Tensor, level: int) -> tuple[Tensor, Tensor, Tensor, list[Tensor], Tensor]:
        """Points' pixels in frame 0 ``(N, 2)`` and the keyframes ``(K, N, 2)``, landmark pixels, rotations and
        the points ``(N, 3)`` (head frame)."""
        d = x[o_sig:o_k] - x_start
        X = X_start + torch.einsum("c,ncd->nd", d, X_units)
        lmk = L_start + torch.einsum("c,lcd->ld", d, L_units)
        R0 = axis_angle_to_matrix(x[0:3])
        uv0 = project_points((X @ R0.T + x[3:6])[None], intrs[level])[0]
        uvl = project_points((lmk @ R0.T + x[3:6])[None], intrinsics)[0]
        uvk, Rk = [], []
        for k in range(K):
            b = o_k + 11 * k
            R = axis_angle_to_matrix(x[b : b + 3])
            uvk.append(project_points(((X + key_delta[k]) @ R.T + x[b + 3 : b + 6])[None], intrs[level])[0])
            Rk.append(R)
        return uv0, torch.stack(uvk), uvl, Rk, X

    def visibility(x: Tensor, level: int, geo: tuple) -> tuple[Tensor, Tensor]:
        """``(K, N)`` bool: visible, facing and inside in frame 0 and keyframe k; the points' normals
        (``geo``: :func:`geometry` at ``x``)."""
        with torch.no_grad():
            sig, al = coeffs(x)
            uv0, uvk, _, Rk, X = geo
            normals = point_normals(m, sig[None], fi, bary)[0]
            poses = [(axis_angle_to_matrix(x[0:3]), x[3:6])] + [(Rk[k], x[o_k + 11 * k + 3 : o_k + 11 * k + 6])
                                                                 for k in range(K)]  # fmt: skip
            alphas = [al] + [al + key_alpha[k] for k in range(K)]
            points = [X] + [X + key_delta[k] for k in range(K)]
            seen = []
            radius = config.silhouette_margin * 2**level  # in full-resolution pixels
            for (R, t), a, Xf in zip(poses, alphas, points):  # one rasterization each: stacked, the (1 + K)-frame
                verts = m.deform(sig[None], a[None])[0]  # buffers cost more to allocate
                frags = rasterize_coverage((verts @ R.T + t)[None], m.faces, intrinsics, cull_backfaces=True,
                                           backend=backend)
                pts = Xf @ R.T + t
                vis = points_visible(pts[None], fi, frags, intrinsics, backend=backend)[0]
                if radius:
                    vis = vis & ~_near_background(frags.pix_to_face[0] < 0, pts, intrinsics, radius)
                cos = -((normals @ R.T) * torch.nn.functional.normalize(pts, dim=-1)).sum(-1)
                seen.append(vis & (cos >= config.min_facing_cos))
            h, w = imgs[level].shape[-2:]

            def inside(uv: Tensor) -> Tensor:
                return (uv[..., 0] >= 1) & (uv[..., 0] <= w - 2) & (uv[..., 1] >= 1) & (uv[..., 1] <= h - 2)

            mask = torch.stack([seen[0] & seen[k + 1] & inside(uv0) & inside(uvk[k]) for k in range(K)])
            return mask, normals

    def samples(level: int, uv0: Tensor, uvk: Tensor) -> tuple[Tensor, Tensor]:
        """Intensity and gradient ``(N, 3)`` of frame 0 at ``uv0`` and ``(K, N, 3)`` of the keyframes at ``uvk``."""
        return sample_at_pixels(imgs[level][:1], uv0[None])[0][0], sample_at_pixels(imgs[level][1:], uvk)[0]

    def residual(x: Tensor, I0: Tensor, Ik: Tensor, Rk: list[Tensor], normals: Tensor) -> Tensor:
        """``(K, N)`` keyframe intensities ``Ik`` minus frame 0's ``I0 (N,)`` under each keyframe's light."""
        res = []
        for k in range(K):
            light = x[o_k + 11 * k + 6 : o_k + 11 * k + 11]
            res.append(Ik[k] - (I0 * (1 + light[0] + (normals @ Rk[k].T) @ light[2:5]) + light[1]))
        return torch.stack(res)

    def photometric(x: Tensor, level: int, lin: tuple[Tensor, ...], normals: Tensor) -> tuple[Tensor, Tensor]:
        """``(K, N)`` residuals linearised in the pixel coordinates at ``lin`` and the landmark pixels."""
        uv0, uvk, uvl, Rk, _ = geometry(x, level)
        uv0s, uvks, s0, sk = lin
        I0 = s0[:, 0] + ((uv0 - uv0s) * s0[:, 1:]).sum(-1)
        Ik = sk[..., 0] + ((uvk - uvks) * sk[..., 1:]).sum(-1)
        return residual(x, I0, Ik, Rk, normals), uvl

    def exact(x: Tensor, level: int, normals: Tensor, geo: tuple | None = None) -> tuple[Tensor, Tensor, tuple]:
        """``(K, N)`` residuals with both images sampled at ``x``'s pixels, the landmark pixels and the samples."""
        uv0, uvk, uvl, Rk, _ = geometry(x, level) if geo is None else geo
        s0, sk = samples(level, uv0, uvk)
        return residual(x, s0[:, 0], sk[..., 0], Rk, normals), uvl, (uv0, uvk, s0, sk)

    def jacobian(x: Tensor, level: int, lin: tuple[Tensor, ...], normals: Tensor, sw: Tensor) -> Tensor:
        """The Jacobian of ``residuals`` at ``x`` in closed form: the chain rule through the projections and
        rotations (``d(R X) / d w = -hat(R X) J_l(w)`` for axis-angle ``w``, :func:`left_jacobian`), the same
        values as forward-mode autograd (tests/tracker/test_lookahead.py) in one pass instead of one per
        parameter."""
        with torch.no_grad():
            uv0s, uvks, s0, sk = lin
            d = x[o_sig:o_k] - x_start
            X = X_start + torch.einsum("c,ncd->nd", d, X_units)  # (N, 3) head frame
            lmk = L_start + torch.einsum("c,lcd->ld", d, L_units)  # (L, 3)
            intr = intrs[level]
            R0 = axis_angle_to_matrix(x[0:3])
            Jl0 = left_jacobian(x[0:3])

            def proj_jac(Pc: Tensor, cam: Intrinsics) -> Tensor:
                """``(M, 2, 3)`` d(u, v) / d(camera point) of ``(M, 3)`` points."""
                return project_points_jacobian(Pc[None], cam)[0]

            RX0 = X @ R0.T
            uv0 = project_points((RX0 + x[3:6])[None], intr)[0]
            gp0 = torch.einsum("nu,nud->nd", s0[:, 1:], proj_jac(RX0 + x[3:6], intr))  # (N, 3) dI0 / dP0
            units_cam0 = torch.einsum("ij,ncj->nci", R0, X_units)  # (N, C, 3)
            dI0 = torch.cat([
                -torch.einsum("nd,nde->ne", gp0, hat(RX0)) @ Jl0,  # rotation (N, 3)
                gp0,  # translation
                torch.einsum("nd,ncd->nc", gp0, units_cam0),  # shape / expression units
            ], 1)  # (N, 6 + C)  # fmt: skip
            rows = []
            for k in range(K):
                b = o_k + 11 * k
                Rk, Jlk = axis_angle_to_matrix(x[b : b + 3]), left_jacobian(x[b : b + 3])
                light = x[b + 6 : b + 11]
                RXk = (X + key_delta[k]) @ Rk.T
                nk = normals @ Rk.T  # (N, 3)
                gpk = torch.einsum("nu,nud->nd", sk[k, :, 1:], proj_jac(RXk + x[b + 3 : b + 6], intr))
                I0 = s0[:, 0] + ((uv0 - uv0s) * s0[:, 1:]).sum(-1)  # frame 0 linearised, as in photometric
                gain = 1 + light[0] + nk @ light[2:5]  # (N,)
                Jk = x.new_zeros(X.shape[0], P)
                Jk[:, : o_k] = -gain[:, None] * dI0
                Jk[:, o_sig:o_k] += torch.einsum("nd,ncd->nc", gpk, torch.einsum("ij,ncj->nci", Rk, X_units))
                Jk[:, b : b + 3] = -torch.einsum("nd,nde->ne", gpk, hat(RXk)) @ Jlk
                Jk[:, b : b + 3] -= I0[:, None] * (-(torch.einsum("d,nde->ne", light[2:5], hat(nk)) @ Jlk))
                Jk[:, b + 3 : b + 6] = gpk
                Jk[:, b + 6] = -I0
                Jk[:, b + 7] = -1.0
                Jk[:, b + 8 : b + 11] = -I0[:, None] * nk
                rows.append(Jk * sw[k][:, None])
            PL = lmk @ R0.T + x[3:6]
            jl = proj_jac(PL, intrinsics)  # (L, 2, 3)
            Jlm = x.new_zeros(lmk.shape[0], 2, P)
            Jlm[:, :, 0:3] = -torch.einsum("lud,lde->lue", jl, hat(lmk @ R0.T)) @ Jl0
            Jlm[:, :, 3:6] = jl
            Jlm[:, :, o_sig:o_k] = torch.einsum("lud,lcd->luc", jl, torch.einsum("ij,lcj->lci", R0, L_units))
            Jlm = Jlm * lw.sqrt()[:, None, None]
            return torch.cat([torch.cat(rows), Jlm.reshape(-1, P), torch.diag(prior.sqrt())])

    def cost(x: Tensor, r: Tensor, uvl: Tensor, mask: Tensor, scale: Tensor) -> float:
        """The minimised cost at ``x`` from its exact residuals ``r`` and landmark pixels ``uvl``."""
        c = config.huber_k * scale[:, None]
        a = r.abs()
        hub = torch.where(a <= c, a * a, 2 * c * a - c * c)
        return float(config.photometric_weight * (hub * mask).sum() + (((uvl - target) ** 2).sum(-1) * lw).sum()
                     + (prior * x * x).sum())  # fmt: skip

    for li, level in enumerate(levels):
        mu = 1e-3
        for _ in range(config.iterations[li]):
            with torch.no_grad():
                geo = geometry(x, level)
            mask, normals = visibility(x, level, geo)
            if not bool(mask.any()):
                break
            with torch.no_grad():
                r, uvl, lin = exact(x, level, normals, geo)
                scale = torch.stack([
                    (1.4826 * (r[k][mask[k]] - r[k][mask[k]].median()).abs().median()).clamp_min(1e-3)
                    if bool(mask[k].any()) else r.new_tensor(1.0) for k in range(K)
                ])  # fmt: skip
                c = config.huber_k * scale[:, None]
                irls = torch.where(r.abs() <= c, torch.ones_like(r), c / r.abs().clamp_min(1e-12))
                sw = (config.photometric_weight * irls * mask).sqrt()
                before = cost(x, r, uvl, mask, scale)

            def residuals(xx: Tensor) -> Tensor:
                rp, uvl = photometric(xx, level, lin, normals)
                return torch.cat([(rp * sw).reshape(-1), ((uvl - target) * lw.sqrt()[:, None]).reshape(-1),
                                  prior.sqrt() * xx])  # fmt: skip

            if analytic:
                J = jacobian(x, level, lin, normals, sw)
            else:
                from torch.func import jacfwd  # imported here: its first use imports torch._dynamo (1.5 s)

                J = jacfwd(residuals)(x)
            res0 = residuals(x).detach()
            H, g = J.T @ J, J.T @ res0
            accepted = False
            for _ in range(8):
                step = -torch.linalg.solve(H + mu * torch.diag(torch.diag(H).clamp_min(1e-9)), g)
                x_new = torch.maximum(torch.minimum(x + step, hi), lo)
                if not bool(torch.isfinite(x_new).all()):
                    mu *= 10
                    continue
                with torch.no_grad():
                    after = cost(x_new, *exact(x_new, level, normals)[:2], mask, scale)
                if after < before:
                    x, mu, accepted = x_new, max(mu / 10, 1e-9), True
                    break
                mu *= 10
            if not accepted:
                break

    sig, al = coeffs(x)
    R0 = axis_angle_to_matrix(x[0:3])[None]
    uvl = geometry(x, 0)[2]  # landmark pixels (full resolution at every level)
    rms = ((((uvl - target) ** 2).sum(-1) * lw).sum() / lw.sum().clamp_min(torch.finfo(lw.dtype).tiny)).sqrt()
    out_dt = model.dtype
    refined = LandmarkFit(
        R0.to(out_dt), x[0:3][None].to(out_dt), x[3:6][None].to(out_dt), sig[None].to(out_dt), al[None].to(out_dt),
        rms[None].to(out_dt), fit.status.clone(),
    )
    key = x[o_k:].reshape(K, 11)
    return refined, axis_angle_to_matrix(key[:, 0:3]).to(out_dt), key[:, 3:6].to(out_dt)


@full_precision
def lookahead_fit(
    model: FaceModel,
    tracker_config: TrackerConfig,
    frames: Tensor,
    landmarks_px: Tensor,
    intrinsics: Intrinsics,
    weights: Tensor | None = None,
    config: LookaheadConfig = LookaheadConfig(),
) -> tuple[LandmarkFit, list[list[int]]]:
    """The first frames' landmark fit, refined per stream against keyframes found by tracking ahead.

    Each stream is tracked (template management as ``tracker_config``) over ``frames[:, 1:]`` until its head has
    turned ``config.yaw_deg`` to both sides, ``config.max_frames`` frames are used or a video cut ends its
    look-ahead (a turn of more than :data:`KEYFRAME_MAX_STEP_DEG` in one step, as the online start: its keyframes
    come from the frames before the cut); a stream with at least
    ``config.min_keyframes`` keyframes gets :func:`refine_first_fit`, the others keep :func:`fit_landmarks`'s
    fit. Start tracking from ``frames[:, 0]`` again with ``initialise(..., fit=...)`` (or
    ``FaceTracker.initialise(..., fit=...)``).

    Args:
        frames: ``(B, T, 3, H, W)`` float in [0, 1], each stream's first ``T >= 2`` frames.
        landmarks_px: ``(B, L, 2)`` the first frames' landmarks; weights ``(B, L)`` or None.

    Returns:
        The fit (batch ``B``) and each stream's keyframes.
    """
    from torchface.tracker.managed import initialise_managed, managed_step

    # (None was an AttributeError: 'NoneType' object has no attribute 'dtype'; a TrackerConfig is "tracker_config"
    # here: "config must be a TrackerConfig" named this function's LookaheadConfig)
    check_api_types(model, tracker_config, config_name="tracker_config")
    if not isinstance(config, LookaheadConfig):
        raise TypeError(f"config must be a LookaheadConfig, got {type(config).__name__}")
    if not isinstance(frames, Tensor):  # a numpy array was "must be (B, T, 3, H, W) ..., got (B, T, 3, H, W)"
        raise TypeError(f"frames must be a torch.Tensor (B, T, 3, H, W) float in [0, 1], got {type(frames).__name__}")
    if frames.dim() != 5 or frames.shape[1] < 2 or not frames.is_floating_point():  # uint8 went on as 0-255 floats
        raise ValueError(f"frames must be (B, T, 3, H, W) float in [0, 1] with T >= 2, got {tuple(frames.shape)} "
                         f"{frames.dtype}")  # fmt: skip
    B = frames.shape[0]
    frames = frames.to(dtype=model.dtype, device=model.device)
    fc = tracker_config.fit
    fit = fit_landmarks(model, landmarks_px, intrinsics, weights, config=fc)
    state, first = initialise_managed(model, tracker_config, frames[:, 0], landmarks_px, intrinsics, weights, fit=fit)
    rotations, translations, confident = [first.rotation], [first.translation], [first.success]
    expressions = [first.expression]
    T = min(frames.shape[1], config.max_frames)
    keys: list[list[int]] = [[] for _ in range(B)]
    # The streams whose look-ahead goes on, as the online start's that wait: started (a failed start, a LOST stream
    # with no reference to be confident against, finds no keyframe: the others were tracked up to max_frames for it)
    # and no video cut yet
    uncut = first.success.detach().clone()
    for i in range(1, T):
        start = axis_angle_to_matrix(state.params.detach()[:, 0:3])  # the pose the step starts from
        state, res = managed_step(model, tracker_config, state, frames[:, i])
        # A video cut (a turn of more than KEYFRAME_MAX_STEP_DEG in one step) ends a stream's look-ahead: the frames
        # from it on show another shot, and no keyframe may come from there
        uncut = uncut & ~is_video_cut(start, res.rotation)
        rotations.append(res.rotation)
        translations.append(res.translation)
        expressions.append(res.expression)
        confident.append(res.success & (res.confidence >= config.min_confidence) & uncut)
        R, ok, tr = torch.stack(rotations, 1), torch.stack(confident, 1), torch.stack(translations, 1)
        keys = [select_keyframes(R[b], config.yaw_deg, ok[b], tr[b]) for b in range(B)]
        if all(len(k) == 2 or not going for k, going in zip(keys, uncut.tolist())):
            break
    R, t, expr = torch.stack(rotations, 1), torch.stack(translations, 1), torch.stack(expressions, 1)
    streams = []
    for b in range(B):
        one = fit.select(slice(b, b + 1))
        if len(keys[b]) >= config.min_keyframes:
            idx = torch.tensor([0] + keys[b], device=frames.device)
            # (per stream: a batch can mix dense and sparse starts)
            priors = landmark_fit_priors(model, fc, intrinsics, landmarks_px[b],
                                         None if weights is None else weights[b])  # fmt: skip
            one = refine_first_fit(
                model, frames[b, idx], intrinsics, landmarks_px[b], one, R[b, keys[b]], t[b, keys[b]],
                key_expression=expr[b, keys[b]],
                landmark_weights=None if weights is None else weights[b],
                config=levels_of(config, tracker_config.num_levels), backend=tracker_config.backend, **priors,
            )  # fmt: skip
        streams.append(one)
    return LandmarkFit(*(torch.cat([getattr(f, n) for f in streams]) for n in LandmarkFit.__dataclass_fields__)), keys
