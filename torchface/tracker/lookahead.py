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
from torchface._words import switch_hint
from torchface.appearance.sampling import image_with_gradients, sample_at_pixels
from torchface.backend import Backend
from torchface.geometry._checks import check_bool, check_int, check_ints, check_names, check_number, check_real
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
    FitConfig, LandmarkFit, check_landmark_type, check_landmark_values, check_precisions, check_shape_prior_count,
    fit_landmarks, held_shape_indices, landmark_targets, prior_scale, shape_precisions, shape_prior_vector,
    sparse_samples,
)
from torchface.tracker.step import (
    TrackerConfig, check_api_types, gray_pyramid, level_intrinsics, min_frame_side, pixel_type_hint,
)  # fmt: skip

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
            closed needs (docs/limitations.md, "Eyes closed"): with the tracker's ``expression_quota=0.06``
            and ``expression_sparsity=0.03`` on the 640x480 ``expressions`` scenario from exact first-frame
            landmarks, eyes closed RMSE 0.031 / r 0.99 (0.090 with this start's defaults, 0.105 keeping the eyes'
            position but re-estimating the expression, 0.150 the other way round; 0.034 without the online start).
        fit_expression: re-estimate the starting expression (the first frame's; each keyframe's points add the
            expression change the tracker measured there, ``key_expression`` of :func:`refine_first_fit`).
        photometric_weight: weight of the photometric term (squared landmark pixels per squared gray level);
            1e3 and 1e5 tracked worse than 1e4 on the James scan.
        iterations: Levenberg-Marquardt iterations per pyramid level, coarsest first (levels 2, 1, 0); 0 skips a
            level, and at least one level must have some (all 0 is refused: nothing would be refined). The
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
            0.83 -> 0.97) while their translation errors hardly changed (docs/limitations.md), and the
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
        # Each number's range, stated once (check_number: a wrong type a TypeError, NaN or an infinite value a
        # ValueError; a NaN gradient_threshold passed "< 0", and no point passes it: the refinement had none).
        for name, interval in (("yaw_deg", "(0, 90)"), ("min_confidence", "[0, 1]"), ("photometric_weight", "(0, inf)"),
                               ("gradient_threshold", "[0, inf)"), ("huber_k", "(0, inf)"),
                               ("min_facing_cos", "[0, 1)")):  # fmt: skip
            object.__setattr__(self, name, check_number(getattr(self, name), name, interval))
        object.__setattr__(self, "fit_expression", check_bool(self.fit_expression, "fit_expression"))
        for name, low in (("max_frames", 2), ("min_keyframes", 1), ("max_points", 1), ("silhouette_margin", 0)):
            object.__setattr__(self, name, check_int(getattr(self, name), name, low))
        object.__setattr__(self, "iterations", check_ints(self.iterations, "iterations", 0))
        if self.shape_units is not None:
            object.__setattr__(self, "shape_units", check_ints(self.shape_units, "shape_units", 0))
        # (a list was a ValueError, as was a wrong type: the other tuple settings take a list, and say TypeError)
        kept = check_names(self.kept_shape_units, "kept_shape_units")
        object.__setattr__(self, "kept_shape_units", kept)
        if kept and self.shape_units is not None:  # (they were ignored: shape_units names every unit re-estimated)
            raise ValueError(f"kept_shape_units {kept} applies with shape_units=None (the held units); with "
                             f"shape_units={self.shape_units} given, leave the kept units out of it")  # fmt: skip
        if self.min_keyframes not in (1, 2):
            raise ValueError(f"min_keyframes must be 1 or 2 (one keyframe per side), got {self.min_keyframes!r}")
        if not self.iterations:
            raise ValueError(f"iterations must be a non-empty tuple of ints >= 0, got {self.iterations!r}")
        if not any(self.iterations):  # (the start was re-anchored from the fit it had, refined by nothing)
            raise ValueError(f"iterations must give at least one level a positive count, got {self.iterations!r}: "
                             "with none the fit is not refined, and the online start re-anchors the stream at the "
                             "pose it had (refine_first=None, torchface track --no-online-refine, turns it "
                             "off)")  # fmt: skip
        units = self.shape_units
        if units is not None and len(set(units)) != len(units):
            raise ValueError(f"shape_units must be distinct non-negative indices, got {self.shape_units!r}")
        if self.shape_prior_precision is not None:  # (FitConfig's rule)
            object.__setattr__(self, "shape_prior_precision", check_precisions(self.shape_prior_precision,
                                                                               "shape_prior_precision"))  # fmt: skip


def check_refine_first(refine_first: object) -> None:
    """Refuse a ``refine_first`` setting (:func:`~torchface.tracker.managed.initialise_managed`, ``FaceTracker``,
    ``TrackJob``, training_hooks' ``FaceTrackingConfig``) that is neither a :class:`LookaheadConfig` nor None."""
    if refine_first is not None and not isinstance(refine_first, LookaheadConfig):
        raise TypeError(f"refine_first must be a LookaheadConfig or None, got {type(refine_first).__name__}"
                        f"{switch_hint(refine_first, 'LookaheadConfig')}")  # (refine_first=False: None turns it off)


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


def check_model_units(config: LookaheadConfig, model: FaceModel, name: str = "refine_first") -> None:
    """Refuse ``config``'s settings that name or count the model's shape units where ``model`` has no such units:
    ``kept_shape_units`` (:func:`kept_shape_indices`), ``shape_units`` indices ``>= model.num_shape`` and a
    ``shape_prior_precision`` tuple not one per shape unit; each named ``name.<setting>``. The online start
    (:func:`~torchface.tracker.managed.initialise_managed`) calls it at the start: :func:`refine_first_fit` refuses
    them too, but only once the head has turned, perhaps far into a video (frame 149 of the default
    ``max_frames``) or never.

    Raises:
        ValueError: the first such setting, what the model has.
    """
    kept_shape_indices(config, model.shape_names, f"{name}.kept_shape_units")
    S = model.num_shape
    if config.shape_units is not None and any(s >= S for s in config.shape_units):
        raise ValueError(f"{name}.shape_units must be < {S} (the model's shape units), got {config.shape_units}")
    check_shape_prior_count(config.shape_prior_precision, S, f"{name}.shape_prior_precision")


def levels_of(config: LookaheadConfig, num_levels: int, name: str = "iterations") -> LookaheadConfig:
    """``config`` refining on at most ``num_levels`` pyramid levels (a tracker's
    :attr:`~torchface.tracker.step.TrackerConfig.num_levels`): its finest ones, ``iterations[-num_levels:]``.

    The tracker checks that its frames hold ``num_levels`` levels (at least ``3 * 2 ** (num_levels - 2)`` pixels a
    side); the default three of the refinement needed 6, and a tracker of 1 or 2 levels on smaller frames failed at
    its re-anchoring, in the middle of the stream (``images must be (B, C, H, W) with H, W >= 3``).

    Raises:
        ValueError: ``iterations`` give those levels none (``(5, 0, 0)`` for a tracker of 2 levels): nothing would be
            refined, as with all 0 (refused by :class:`LookaheadConfig`). :func:`initialise_managed
            <torchface.tracker.managed.initialise_managed>`, :func:`lookahead_fit` and ``JobConfig`` ask at the start,
            not at the re-anchoring. ``name``: the setting's name in the message.
    """
    if len(config.iterations) <= num_levels:
        return config
    kept = config.iterations[-num_levels:]
    if not any(kept):
        raise ValueError(
            f"{name} {config.iterations} give none of the tracker's {num_levels} pyramid levels an iteration (the "
            f"look-ahead refines on its finest {num_levels}: {kept}): nothing would be refined; give them some, e.g. "
            f"iterations={config.iterations[:-num_levels] + (1,) * num_levels}, or track with more levels"
        )
    return replace(config, iterations=kept)


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
        if landmark_weights is not None and (not isinstance(landmark_weights, Tensor)
                                             or tuple(landmark_weights.shape) != tuple(landmarks_px.shape[:1])):
            got = (tuple(landmark_weights.shape) if isinstance(landmark_weights, Tensor)
                   else type(landmark_weights).__name__)  # fmt: skip
            raise ValueError(f"landmark_weights must be ({landmarks_px.shape[0]},) or None, got {got}")
        check_landmark_values(landmarks_px, landmark_weights, weights_name="landmark_weights")
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
    start = _stream_start(
        model, frames, intrinsics, landmarks_px, fit, key_rotation, key_translation, key_expression=key_expression,
        landmark_weights=landmark_weights, shape_prior_precision=shape_prior_precision, shape_bound=shape_bound,
        expression_prior_precision=expression_prior_precision, config=config, held_shape_units=held_shape_units,
        prior_scale=prior_scale, min_shape_prior_precision=min_shape_prior_precision,
        min_expression_prior_precision=min_expression_prior_precision, backend=backend,
    )  # fmt: skip
    return _refine_starts(model, [start], intrinsics, config, backend=backend)[0]


@dataclass(frozen=True, eq=False)
class _Start:
    """One stream's refinement problem (:func:`_stream_start`), which :func:`_refine_starts` solves with others.

    ``x``, ``lo``, ``hi``, ``prior`` ``(P,)`` the packed start, bounds and prior precisions (``[aa0 (3), t0 (3), free
    shape units (nf), expression (nA), per keyframe: aa, t, light (11)]``); ``imgs`` per pyramid level the frames'
    ``(1 + K, 3, h, w)`` intensity and gradients; ``fi`` ``(N,)``, ``bary`` ``(N, 3)`` the first frame's template
    points; ``target`` ``(L, 2)``, ``lw`` ``(L,)`` the landmark targets and weights; ``X_start`` ``(N, 3)`` and
    ``L_start`` ``(L, 3)`` the points and landmarks at the starting coefficients ``x_start`` ``(C,)``, ``X_units``
    ``(N, C, 3)`` and ``L_units`` ``(L, C, 3)`` their displacements per free coefficient; ``key_alpha`` ``(K, A)``
    and ``key_delta`` ``(K, N, 3)`` the keyframes' own expression and its points' offsets; ``sig0`` ``(S,)``,
    ``al0`` ``(A,)`` the starting coefficients; ``free_units`` the re-estimated shape units; ``status`` the fit's."""

    x: Tensor
    lo: Tensor
    hi: Tensor
    prior: Tensor
    imgs: tuple[Tensor, ...]
    fi: Tensor
    bary: Tensor
    target: Tensor
    lw: Tensor
    X_start: Tensor
    L_start: Tensor
    X_units: Tensor
    L_units: Tensor
    x_start: Tensor
    key_alpha: Tensor
    key_delta: Tensor
    sig0: Tensor
    al0: Tensor
    free_units: tuple[int, ...]
    status: Tensor


def _stream_start(
    model: FaceModel,
    frames: Tensor,
    intrinsics: Intrinsics,
    landmarks_px: Tensor,
    fit: LandmarkFit,
    key_rotation: Tensor,
    key_translation: Tensor,
    *,
    key_expression: Tensor | None,
    landmark_weights: Tensor | None,
    shape_prior_precision: float | tuple[float, ...],
    shape_bound: float,
    expression_prior_precision: float,
    config: LookaheadConfig,
    held_shape_units: tuple[int, ...],
    prior_scale: float,
    min_shape_prior_precision: float,
    min_expression_prior_precision: float,
    backend: Backend,
) -> _Start:
    """One stream's arguments of :func:`refine_first_fit` checked and turned into its :class:`_Start` (its template
    points selected in the first frame, its pyramid built)."""
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
    check_landmark_values(landmarks_px, landmark_weights, weights_name="landmark_weights")
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
    levels = len(config.iterations)
    side = min_frame_side(levels)  # (as the tracker)
    if min(frames.shape[-2:]) < side:
        raise ValueError(f"frames must be at least {side}x{side} pixels for the refinement's {levels} pyramid "
                         f"levels (config.iterations), got {frames.shape[-1]}x{frames.shape[-2]}")  # fmt: skip
    pyramid = gray_pyramid(frames.to(device=dev, dtype=dt), levels)  # the tracker's levels
    gray = pyramid[0]
    imgs = tuple(image_with_gradients(g) for g in pyramid)

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
    return _Start(x, lo, hi, prior, imgs, fi[0], bary[0], target, lw, X_start, L_start, X_units, L_units, x_start,
                  key_alpha, key_delta, sig0[0], al0[0], tuple(free_units), fit.status.clone())  # fmt: skip


def _masked_median(values: Tensor, mask: Tensor) -> Tensor:
    """``(...)`` the median of ``values`` ``(..., N)`` where ``mask`` (the lower middle one of an even count, as
    :func:`torch.median`); 0 where ``mask`` holds nowhere."""
    count = mask.sum(-1, keepdim=True)
    ordered = torch.where(mask, values, torch.full_like(values, float("inf"))).sort(-1).values
    return ordered.gather(-1, ((count - 1).clamp_min(0) // 2)).squeeze(-1).where(count.squeeze(-1) > 0, 0.0)


def _dot3(g: Tensor, units: Tensor) -> Tensor:
    """``(B, N, C)`` the dot products of ``g`` ``(B, N, 3)`` with each of ``units`` ``(B, 3, N, C)`` (by coordinate),
    as three products (a batched matrix product of (1, 3) by (3, C) matrices took twice as long)."""
    return g[..., 0:1] * units[:, 0] + g[..., 1:2] * units[:, 1] + g[..., 2:3] * units[:, 2]


def _refine_starts(
    model: FaceModel, starts: Sequence[_Start], intrinsics: Intrinsics, config: LookaheadConfig, *,
    analytic: bool = True, backend: Backend = Backend.AUTO,
) -> tuple[LandmarkFit, Tensor, Tensor]:
    """The refinements of streams ``starts`` (:func:`_stream_start`; the same keyframe count, free units and frame
    size), solved together: one batched Levenberg-Marquardt over the streams, each with its own damping, steps and
    stopping as alone (a stream whose level stops, no visible point or no step lowering its cost, waits for the
    others' with its parameters as they are). Their points are padded to the most points of a stream, the padding
    masked out of every residual.

    Returns:
        The refined :class:`LandmarkFit` (batch ``B``, the model's dtype) and the keyframes' refined poses, rotation
        ``(B, K, 3, 3)`` and translation ``(B, K, 3)``.
    """
    B = len(starts)
    s0_ = starts[0]
    K = s0_.key_alpha.shape[0]
    if any(s.key_alpha.shape[0] != K or s.free_units != s0_.free_units or s.x.shape != s0_.x.shape for s in starts):
        raise ValueError("streams refined together must have the same keyframe count and re-estimated units")
    dt, dev = torch.float64, model.device
    m = model.to(dtype=dt)
    nf = len(s0_.free_units)
    free_su = torch.tensor(s0_.free_units, dtype=torch.long, device=dev)
    nA = model.num_animation if config.fit_expression else 0
    o_sig, o_al = 6, 6 + nf
    o_k = o_al + nA
    P = o_k + 11 * K
    levels = list(reversed(range(len(config.iterations))))
    imgs = [torch.stack([s.imgs[lv] for s in starts]) for lv in range(len(levels))]  # (B, 1 + K, 3, h, w)
    intrs = [level_intrinsics(intrinsics, lv, g.shape[-2], g.shape[-1]) for lv, g in enumerate(imgs)]
    N = max(s.fi.shape[0] for s in starts)

    def pad_points(t: Tensor, dim: int) -> Tensor:
        extra = N - t.shape[dim]
        if not extra:
            return t
        shape = list(t.shape)
        shape[dim] = extra
        return torch.cat([t, t.new_zeros(shape)], dim)

    valid = torch.stack([pad_points(torch.ones(s.fi.shape[0], dtype=torch.bool, device=dev), 0) for s in starts])
    fi = torch.stack([pad_points(s.fi, 0) for s in starts])  # padding: triangle 0 at its first corner
    bary = torch.stack([pad_points(s.bary, 0) for s in starts])
    bary[..., 0] = torch.where(valid, bary[..., 0], 1.0)
    X_start = torch.stack([pad_points(s.X_start, 0) for s in starts])  # (B, N, 3)
    # The units' displacements by coordinate, (B, 3, N, C) and (B, L, 3, C), for the Jacobian, and (B, C, 3 N),
    # (B, C, 3 L) for X = X_start + d XU, one vector-matrix product per stream (einsum over (B, N, C, 3) copied it to
    # such a layout at every call: a sixth of the batched refinement's time)
    XU = torch.stack([pad_points(s.X_units, 0) for s in starts]).transpose(-1, -2)  # (B, N, 3, C)
    LU = torch.stack([s.L_units for s in starts]).transpose(-1, -2).contiguous()
    XU_rows, LU_rows = XU.flatten(1, 2).transpose(1, 2).contiguous(), LU.flatten(1, 2).transpose(1, 2).contiguous()
    XU = XU.permute(0, 2, 1, 3).contiguous()
    key_delta = torch.stack([pad_points(s.key_delta, 1) for s in starts])  # (B, K, N, 3)
    L_start = torch.stack([s.L_start for s in starts])

    def pick(t: Tensor, rows: Tensor | None) -> Tensor:
        """``t``'s streams ``rows`` (a ``(B',)`` index; None: all)."""
        return t if rows is None else t[rows]

    def deformed(d: Tensor, rows: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The points ``(B, N, 3)`` and landmarks ``(B, L, 3)`` (head frame) at coefficients ``x_start + d`` (of
        streams ``rows``)."""
        X0, L0 = pick(X_start, rows), pick(L_start, rows)
        return (X0 + (d[:, None] @ pick(XU_rows, rows)).view(X0.shape),
                L0 + (d[:, None] @ pick(LU_rows, rows)).view(L0.shape))  # fmt: skip

    target, lw = torch.stack([s.target for s in starts]), torch.stack([s.lw for s in starts])  # (B, L, 2), (B, L)
    x_start, key_alpha = torch.stack([s.x_start for s in starts]), torch.stack([s.key_alpha for s in starts])
    sig0, al0 = torch.stack([s.sig0 for s in starts]), torch.stack([s.al0 for s in starts])
    x = torch.stack([s.x for s in starts])  # (B, P)
    lo, hi, prior = (torch.stack([getattr(s, n) for s in starts]) for n in ("lo", "hi", "prior"))

    def coeffs(x: Tensor) -> tuple[Tensor, Tensor]:
        """``(B, S)`` shape and ``(B, A)`` expression coefficients of ``x``."""
        if not nf:
            return sig0, (x[:, o_al:o_k] if nA else al0)
        sig = sig0.clone()
        sig[:, free_su] = x[:, o_sig:o_al]
        return sig, (x[:, o_al:o_k] if nA else al0)

    def key_poses(x: Tensor) -> tuple[Tensor, Tensor]:
        """The keyframes' rotations ``(B, K, 3, 3)`` and translations ``(B, K, 3)``."""
        key = x[:, o_k:].reshape(-1, K, 11)
        return axis_angle_to_matrix(key[..., 0:3]), key[..., 3:6]

    def geometry(x: Tensor, level: int, rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Points' pixels in frame 0 ``(B, N, 2)`` and the keyframes ``(B, K, N, 2)``, landmark pixels ``(B, L, 2)``,
        the keyframes' rotations ``(B, K, 3, 3)`` and the points ``(B, N, 3)`` (head frame); ``rows``: ``x`` holds
        those streams only."""
        X, lmk = deformed(x[:, o_sig:o_k] - pick(x_start, rows), rows)
        R0t = axis_angle_to_matrix(x[:, 0:3]).transpose(-1, -2)
        uv0 = project_points(X @ R0t + x[:, None, 3:6], intrs[level])
        uvl = project_points(lmk @ R0t + x[:, None, 3:6], intrinsics)
        Rk, tk = key_poses(x)
        Pk = (X[:, None] + pick(key_delta, rows)) @ Rk.transpose(-1, -2) + tk[:, :, None]  # (B, K, N, 3)
        uvk = project_points(Pk.flatten(0, 1), intrs[level]).unflatten(0, (-1, K))
        return uv0, uvk, uvl, Rk, X

    def visibility(x: Tensor, level: int, geo: tuple) -> tuple[Tensor, Tensor]:
        """``(B, K, N)`` bool: visible, facing and inside in frame 0 and keyframe k; the points' normals
        ``(B, N, 3)`` (``geo``: :func:`geometry` at ``x``)."""
        with torch.no_grad():
            sig, al = coeffs(x)
            uv0, uvk, _, Rk, X = geo
            normals = point_normals(m, sig, fi, bary)
            R = torch.cat([axis_angle_to_matrix(x[:, None, 0:3]), Rk], 1)  # (B, 1 + K, 3, 3)
            t = torch.cat([x[:, None, 3:6], key_poses(x)[1]], 1)  # (B, 1 + K, 3)
            alphas = torch.cat([al[:, None], al[:, None] + key_alpha], 1)  # (B, 1 + K, A)
            points = torch.cat([X[:, None], X[:, None] + key_delta], 1)  # (B, 1 + K, N, 3)
            verts = m.deform(sig[:, None].expand(-1, K + 1, -1).flatten(0, 1), alphas.flatten(0, 1))
            Rt = R.flatten(0, 1).transpose(-1, -2)
            # one rasterization of the B (1 + K) poses (each alone allocated its buffers B (1 + K) times)
            frags = rasterize_coverage(verts @ Rt + t.flatten(0, 1)[:, None], m.faces, intrinsics,
                                       cull_backfaces=True, backend=backend)  # fmt: skip
            pts = points.flatten(0, 1) @ Rt + t.flatten(0, 1)[:, None]  # (B (1 + K), N, 3)
            vis = points_visible(pts, fi.repeat_interleave(K + 1, 0), frags, intrinsics, backend=backend)
            radius = config.silhouette_margin * 2**level  # in full-resolution pixels
            if radius:
                background = frags.pix_to_face < 0
                vis = vis & ~torch.stack([_near_background(background[i], pts[i], intrinsics, radius)
                                          for i in range(pts.shape[0])])  # fmt: skip
            nrm = normals.repeat_interleave(K + 1, 0) @ Rt
            cos = -(nrm * torch.nn.functional.normalize(pts, dim=-1)).sum(-1)
            seen = (vis & (cos >= config.min_facing_cos)).unflatten(0, (B, K + 1))
            h, w = imgs[level].shape[-2:]

            def inside(uv: Tensor) -> Tensor:
                return (uv[..., 0] >= 1) & (uv[..., 0] <= w - 2) & (uv[..., 1] >= 1) & (uv[..., 1] <= h - 2)

            mask = (seen[:, :1] & seen[:, 1:] & inside(uv0)[:, None] & inside(uvk)) & valid[:, None]
            return mask, normals

    def samples(level: int, uv0: Tensor, uvk: Tensor, rows: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Intensity and gradient ``(B, N, 3)`` of frame 0 at ``uv0`` and ``(B, K, N, 3)`` of the keyframes at
        ``uvk`` (of streams ``rows``)."""
        uv = torch.cat([uv0[:, None], uvk], 1).flatten(0, 1)
        s = sample_at_pixels(pick(imgs[level], rows).flatten(0, 1), uv)[0].unflatten(0, (-1, K + 1))
        return s[:, 0], s[:, 1:]

    def residual(x: Tensor, I0: Tensor, Ik: Tensor, Rk: Tensor, normals: Tensor) -> Tensor:
        """``(B, K, N)`` keyframe intensities ``Ik`` minus frame 0's ``I0 (B, N)`` under each keyframe's light."""
        light = x[:, o_k:].reshape(-1, K, 11)[..., 6:11]  # (B, K, 5)
        shade = ((normals[:, None] @ Rk.transpose(-1, -2)) @ light[..., 2:5, None]).squeeze(-1)  # (B, K, N)
        return Ik - (I0[:, None] * (1 + light[..., 0:1] + shade) + light[..., 1:2])

    def photometric(x: Tensor, level: int, lin: tuple[Tensor, ...], normals: Tensor) -> tuple[Tensor, Tensor]:
        """``(B, K, N)`` residuals linearised in the pixel coordinates at ``lin`` and the landmark pixels."""
        uv0, uvk, uvl, Rk, _ = geometry(x, level)
        uv0s, uvks, s0, sk = lin
        I0 = s0[..., 0] + ((uv0 - uv0s) * s0[..., 1:]).sum(-1)
        Ik = sk[..., 0] + ((uvk - uvks) * sk[..., 1:]).sum(-1)
        return residual(x, I0, Ik, Rk, normals), uvl

    def exact(x: Tensor, level: int, normals: Tensor, geo: tuple | None = None,
              rows: Tensor | None = None) -> tuple[Tensor, Tensor, tuple]:  # fmt: skip
        """``(B, K, N)`` residuals with both images sampled at ``x``'s pixels, the landmark pixels and the
        samples (``rows``: ``x`` and ``normals`` hold those streams only)."""
        uv0, uvk, uvl, Rk, _ = geometry(x, level, rows) if geo is None else geo
        s0, sk = samples(level, uv0, uvk, rows)
        return residual(x, s0[..., 0], sk[..., 0], Rk, normals), uvl, (uv0, uvk, s0, sk)

    def jacobian(x: Tensor, level: int, lin: tuple[Tensor, ...], normals: Tensor, sw: Tensor) -> Tensor:
        """``(B, M, P)`` the Jacobian of ``residuals`` at ``x`` in closed form: the chain rule through the
        projections and rotations (``d(R X) / d w = -hat(R X) J_l(w)`` for axis-angle ``w``, :func:`left_jacobian`),
        the same values as forward-mode autograd (tests/tracker/test_lookahead.py) in one pass instead of one per
        parameter."""
        with torch.no_grad():
            uv0s, uvks, s0, sk = lin
            X, lmk = deformed(x[:, o_sig:o_k] - x_start)  # (B, N, 3), (B, L, 3) head frame
            intr = intrs[level]
            R0 = axis_angle_to_matrix(x[:, 0:3])
            Jl0 = left_jacobian(x[:, 0:3])
            t0 = x[:, None, 3:6]
            RX0 = X @ R0.transpose(-1, -2)
            uv0 = project_points(RX0 + t0, intr)
            gp0 = torch.einsum("bnu,bnud->bnd", s0[..., 1:], project_points_jacobian(RX0 + t0, intr))  # dI0 / dP0
            dI0 = torch.cat([
                -torch.einsum("bnd,bnde->bne", gp0, hat(RX0)) @ Jl0,  # rotation (B, N, 3)
                gp0,  # translation
                _dot3(gp0 @ R0, XU),  # shape / expression units: (R0 u) . g = u . (R0^T g)
            ], -1)  # (B, N, 6 + C)  # fmt: skip
            I0 = s0[..., 0] + ((uv0 - uv0s) * s0[..., 1:]).sum(-1)  # frame 0 linearised, as in photometric
            rows = []
            for k in range(K):
                b = o_k + 11 * k
                Rk, Jlk = axis_angle_to_matrix(x[:, b : b + 3]), left_jacobian(x[:, b : b + 3])
                light = x[:, b + 6 : b + 11]
                RXk = (X + key_delta[:, k]) @ Rk.transpose(-1, -2)
                nk = normals @ Rk.transpose(-1, -2)  # (B, N, 3)
                gpk = torch.einsum("bnu,bnud->bnd", sk[:, k, :, 1:],
                                   project_points_jacobian(RXk + x[:, None, b + 3 : b + 6], intr))  # fmt: skip
                gain = 1 + light[:, 0:1] + (nk @ light[:, 2:5, None]).squeeze(-1)  # (B, N)
                Jk = x.new_zeros(B, N, P)
                Jk[..., :o_k] = -gain[..., None] * dI0
                Jk[..., o_sig:o_k] += _dot3(gpk @ Rk, XU)
                Jk[..., b : b + 3] = -torch.einsum("bnd,bnde->bne", gpk, hat(RXk)) @ Jlk
                Jk[..., b : b + 3] -= I0[..., None] * (-(torch.einsum("bd,bnde->bne", light[:, 2:5], hat(nk)) @ Jlk))
                Jk[..., b + 3 : b + 6] = gpk
                Jk[..., b + 6] = -I0
                Jk[..., b + 7] = -1.0
                Jk[..., b + 8 : b + 11] = -I0[..., None] * nk
                rows.append(Jk * sw[:, k, :, None])
            RL = lmk @ R0.transpose(-1, -2)
            jl = project_points_jacobian(RL + t0, intrinsics)  # (B, L, 2, 3)
            Jlm = x.new_zeros(B, lmk.shape[1], 2, P)
            Jlm[..., 0:3] = -torch.einsum("blud,blde->blue", jl, hat(RL)) @ Jl0[:, None]
            Jlm[..., 3:6] = jl
            Jlm[..., o_sig:o_k] = (jl @ R0[:, None]) @ LU
            Jlm = Jlm * lw.sqrt()[..., None, None]
            return torch.cat([torch.cat(rows, 1), Jlm.flatten(1, 2), torch.diag_embed(prior.sqrt())], 1)

    def cost(x: Tensor, r: Tensor, uvl: Tensor, mask: Tensor, scale: Tensor, rows: Tensor | None = None) -> Tensor:
        """``(B,)`` the minimised cost at ``x`` from its exact residuals ``r`` and landmark pixels ``uvl`` (``rows``:
        those of these streams only)."""
        c = config.huber_k * scale[..., None]
        a = r.abs()
        hub = torch.where(a <= c, a * a, 2 * c * a - c * c)
        return (config.photometric_weight * (hub * mask).flatten(1).sum(-1)
                + (((uvl - pick(target, rows)) ** 2).sum(-1) * pick(lw, rows)).sum(-1)
                + (pick(prior, rows) * x * x).sum(-1))  # fmt: skip

    for li, level in enumerate(levels):
        mu = x.new_full((B,), 1e-3)
        going = torch.ones(B, dtype=torch.bool, device=dev)  # the streams whose iterations at this level go on
        for _ in range(config.iterations[li]):
            with torch.no_grad():
                geo = geometry(x, level)
            mask, normals = visibility(x, level, geo)
            going = going & mask.flatten(1).any(-1)
            if not bool(going.any()):
                break
            with torch.no_grad():
                r, uvl, lin = exact(x, level, normals, geo)
                med = _masked_median(r, mask)
                scale = (1.4826 * _masked_median((r - med[..., None]).abs(), mask)).clamp_min(1e-3)
                scale = scale.where(mask.any(-1), 1.0)
                c = config.huber_k * scale[..., None]
                irls = torch.where(r.abs() <= c, torch.ones_like(r), c / r.abs().clamp_min(1e-12))
                sw = (config.photometric_weight * irls * mask).sqrt()
                before = cost(x, r, uvl, mask, scale)

            def residuals(xx: Tensor) -> Tensor:
                rp, uvl = photometric(xx, level, lin, normals)
                return torch.cat([(rp * sw).flatten(1), ((uvl - target) * lw.sqrt()[..., None]).flatten(1),
                                  prior.sqrt() * xx], 1)  # fmt: skip

            if analytic:
                J = jacobian(x, level, lin, normals, sw)
            else:
                from torch.func import jacfwd  # imported here: its first use imports torch._dynamo (1.5 s)

                J = jacfwd(residuals)(x).diagonal(0, 0, 2).permute(2, 0, 1)  # each stream's own block
            res0 = residuals(x).detach()
            Jt = J.transpose(-1, -2)
            H, g = Jt @ J, (Jt @ res0[..., None]).squeeze(-1)
            # (a stream that stopped takes no step: an identity system, which no empty mask makes singular)
            H = torch.where(going[:, None, None], H, torch.eye(P, dtype=dt, device=dev))
            g = torch.where(going[:, None], g, 0.0)
            damp = torch.diag_embed(torch.diagonal(H, dim1=-2, dim2=-1).clamp_min(1e-9))
            trying = going.clone()  # the streams still looking for a step that lowers their cost
            for _ in range(8):
                step = -torch.linalg.solve(H + mu[:, None, None] * damp, g)
                x_new = torch.maximum(torch.minimum(x + step, hi), lo)
                finite = torch.isfinite(x_new).all(-1)
                x_new = torch.where(finite[:, None], x_new, x)
                with torch.no_grad():
                    if bool(trying.all()):
                        after = cost(x_new, *exact(x_new, level, normals)[:2], mask, scale)
                    else:  # (a further try is for few streams: the others are not evaluated)
                        rows = trying.nonzero().squeeze(-1)
                        xr = x_new[rows]
                        after = torch.full_like(before, float("inf")).index_put(
                            (rows,), cost(xr, *exact(xr, level, normals[rows], rows=rows)[:2], mask[rows],
                                          scale[rows], rows))  # fmt: skip
                better = trying & finite & (after < before)
                x = torch.where(better[:, None], x_new, x)
                mu = torch.where(better, (mu / 10).clamp_min(1e-9), torch.where(trying, mu * 10, mu))
                trying = trying & ~better
                if not bool(trying.any()):
                    break
            going = going & ~trying  # a stream that found no step stops at this level

    sig, al = coeffs(x)
    R0 = axis_angle_to_matrix(x[:, 0:3])
    uvl = geometry(x, 0)[2]  # landmark pixels (full resolution at every level)
    rms = ((((uvl - target) ** 2).sum(-1) * lw).sum(-1) / lw.sum(-1).clamp_min(torch.finfo(lw.dtype).tiny)).sqrt()
    out_dt = model.dtype
    refined = LandmarkFit(
        R0.to(out_dt), x[:, 0:3].to(out_dt), x[:, 3:6].to(out_dt), sig.to(out_dt), al.to(out_dt), rms.to(out_dt),
        torch.cat([s.status for s in starts]),
    )
    key_R, key_t = key_poses(x)
    return refined, key_R.to(out_dt), key_t.to(out_dt)


def _clip_hint(frames: Tensor) -> str:
    """How to make refused clips ``(B, T, 3, H, W)`` float in [0, 1] (:func:`lookahead_fit`'s message), as
    `` (...)``: one stream's ``(T, C, H, W)``, time first, channels last, RGBA, integer pixels; "" where nothing
    fits."""
    hints = []
    shape = tuple(frames.shape)
    if len(shape) == 4 and shape[1] in (1, 3):
        hints.append("one stream's clip (T, C, H, W): frames[None]")
    elif len(shape) == 5 and shape[2] not in (1, 3, 4) and shape[-1] in (1, 3, 4):
        hints.append("channels last (B, T, H, W, C): frames.permute(0, 1, 4, 2, 3)")
    elif len(shape) == 5 and shape[2] == 4:
        hints.append("RGBA: drop the alpha, frames[:, :, :3]")
    elif len(shape) == 5 and shape[1] == 1 and shape[0] >= 2:
        hints.append("time first, (T, B, C, H, W)? frames.transpose(0, 1)")
    dtype = pixel_type_hint(frames)  # (the tracker's words: uint16 clips were told to convert alone)
    hints += [dtype] if dtype else []
    return f" ({'; '.join(hints)})" if hints else ""


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
    come from the frames before the cut); a stream with at least ``config.min_keyframes`` keyframes gets
    :func:`refine_first_fit` (those streams refined in one batched solve, each as alone), the others keep
    :func:`fit_landmarks`'s fit. Start tracking from ``frames[:, 0]`` again with ``initialise(..., fit=...)`` (or
    ``FaceTracker.initialise(..., fit=...)``).

    Args:
        frames: ``(B, T, 3, H, W)`` float in [0, 1], each stream's first ``T >= 2`` frames.
        landmarks_px: ``(B, L, 2)`` the first frames' landmarks; weights ``(B, L)`` or None.

    Returns:
        The fit (batch ``B``) and each stream's keyframes.
    """
    from torchface.tracker.managed import REANCHOR_BATCH, initialise_managed, managed_step

    # (None was an AttributeError: 'NoneType' object has no attribute 'dtype'; a TrackerConfig is "tracker_config"
    # here: "config must be a TrackerConfig" named this function's LookaheadConfig)
    check_api_types(model, tracker_config, config_name="tracker_config")
    if not isinstance(config, LookaheadConfig):
        raise TypeError(f"config must be a LookaheadConfig, got {type(config).__name__}")
    check_model_units(config, model, "config")  # (refine_first_fit's checks, before the frames are tracked ahead)
    levels_of(config, tracker_config.num_levels, "config.iterations")  # (asked again once the frames are tracked)
    if not isinstance(frames, Tensor):  # a numpy array was "must be (B, T, 3, H, W) ..., got (B, T, 3, H, W)"
        raise TypeError(f"frames must be a torch.Tensor (B, T, 3, H, W) float in [0, 1], got {type(frames).__name__}")
    if frames.dim() != 5 or frames.shape[1] < 2 or frames.shape[2] not in (1, 3) or not frames.is_floating_point():
        # (uint8 went on as 0-255 floats; channels-last and RGBA clips were told the first frames' check, of (B, 3,
        # H, W), with its fix for those, which raised for the clip; the rest were told the shape alone)
        raise ValueError(f"frames must be (B, T, 3, H, W) float in [0, 1] with T >= 2, got {tuple(frames.shape)} "
                         f"{frames.dtype}{_clip_hint(frames)}")  # fmt: skip
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
    la = levels_of(config, tracker_config.num_levels)

    def problem(b: int) -> _Start:
        idx = torch.tensor([0] + keys[b], device=frames.device)
        w = None if weights is None else weights[b]
        # (priors per stream: a batch can mix dense and sparse starts)
        return _stream_start(
            model, frames[b, idx], intrinsics, landmarks_px[b], fit.select([b]), R[b, keys[b]],
            t[b, keys[b]], key_expression=expr[b, keys[b]], landmark_weights=w, config=la,
            backend=tracker_config.backend, **landmark_fit_priors(model, fc, intrinsics, landmarks_px[b], w),
        )  # fmt: skip

    # The streams with their keyframes refined together, as the online start's (one batched solve per keyframe
    # count, at most REANCHOR_BATCH streams each): each as alone
    streams = [fit.select([b]) for b in range(B)]
    groups: dict[int, list[int]] = {}
    for b in range(B):
        if len(keys[b]) >= config.min_keyframes:
            groups.setdefault(len(keys[b]), []).append(b)
    for members in groups.values():
        for c in range(0, len(members), REANCHOR_BATCH):
            chunk = members[c : c + REANCHOR_BATCH]
            refined = _refine_starts(model, [problem(b) for b in chunk], intrinsics, la,
                                     backend=tracker_config.backend)[0]  # fmt: skip
            for j, b in enumerate(chunk):
                streams[b] = refined.select([j])
    return LandmarkFit(*(torch.cat([getattr(f, n) for f in streams]) for n in LandmarkFit.__dataclass_fields__)), keys
