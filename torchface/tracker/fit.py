"""Individual shape and pose from 2D fiducial points (paper Eq. 2).

Minimises ``sum_k w_k || pi(R (g_k + S_k sigma + A_k alpha) + t) - p_k ||^2`` over the rotation
(axis-angle), the translation, the shape units ``sigma`` (Gaussian prior, bounded) and optionally a starting
expression ``alpha``, by batched Levenberg-Marquardt, where ``g_k``, ``S_k``, ``A_k`` are the landmark
positions and bases interpolated from the model's landmark table.
"""

from __future__ import annotations

import math
import warnings
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TypeVar, cast

import numpy as np
import torch
from torch import Tensor

from torchface._autocast import full_precision
from torchface._compiling import is_compiling
from torchface._device import check_holds_data, tensor_mover
from torchface.conventions import (
    NORMALISED_CHECK_MIN_SIDE, NORMALISED_LANDMARK_MAX_SPAN, NORMALISED_LANDMARK_RANGE, half_precision_rounding,
)
from torchface.geometry._checks import (
    check_bool, check_int, check_intrinsics, check_names, check_number, check_optional_int, check_reals,
)
from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import pose_projection_jacobian, project_points, project_points_jacobian
from torchface.geometry.so3 import axis_angle_to_matrix
from torchface.model.face_model import FaceModel, interpolate_landmarks
from torchface.solver.least_squares import SolveStatus, SolverConfig, least_squares, solve_normal_equations

#: The strongest prior an animation unit may be given: :attr:`~torchface.tracker.step.TrackerConfig`'s
#: ``expression_prior_precision`` and ``refine_prior_precision``, each times the unit's ``expression_prior_weights``
#: factor, and :attr:`FitConfig.expression_prior_precision` and ``sparse_expression_prior_precision``, are at most
#: this (:func:`check_unit_precision`). Measured on a rendered 160x120 head turning 20 degrees (16 frames, every
#: unit's precision the same): at 1e4-1e6 the units are held as firmly as ``use_expression=False`` holds them (the
#: pose within 0.02 degree of that ablation's), at 1e8-1e10 within 0.09-0.14 degree, at 1e12 3 degrees off, and from
#: 1e14 on the pose stayed the first frame's while every frame reported success: the float32 solver's damping is
#: relative to the largest diagonal entry of its Hessian, which the prior then is, and it swamps the pose's. The
#: landmark fit (the same clip's first frame, 68 landmarks) held the units within 3e-5 of 0 at 1e6, as
#: ``fit_expression=False`` (the pose within 1e-6 rad of its), and from 1e19 on was FAILED with no rotation.
MAX_UNIT_PRECISION = 1e6


def check_unit_precision(value: float | None, name: str, why: str, optional: bool = False) -> None:
    """Refuse a prior precision of animation units (``name``, a setting already checked finite and >= 0; None
    passes) above :data:`MAX_UNIT_PRECISION` with a ``ValueError`` naming the setting, its range (``[0, 1e6]``, ``or
    None`` when ``optional``) and ``why`` (what such a prior does to the solver that takes it)."""
    if value is not None and value > MAX_UNIT_PRECISION:
        none = " or None" if optional else ""
        raise ValueError(f"{name} must be in [0, 1e6]{none}, got {value!r}: {why}")


_FIT_STRONG_PRIOR = (
    "at 1e6 the animation units are held at 0 as firmly as fit_expression=False holds them, and from about 1e19 the "
    "fit fails (FAILED, no rotation)"
)


@dataclass(frozen=True)
class FitConfig:
    """Settings of :func:`fit_landmarks`.

    The prior precisions weigh the coefficients against the landmark terms' squared pixels, and a face spans
    more pixels, its landmarks' residuals and Jacobians in proportion, the longer the focal length: they are
    given for a camera of focal length ``reference_focal_px`` and scaled by ``fx fy / reference_focal_px**2``
    for the camera at hand (:func:`prior_scale`), so that the balance between the landmarks and the priors, and
    with it the fit, is the same at any image size (a camera of ``Intrinsics.default(W, H)`` has ``f = max(W,
    H)``). Unscaled, exact landmarks of the ``pose_sweep`` scenario's first frame fitted the rotation 1.06 degrees
    off at 640x480, 0.92 at 960x540, 0.58 at 1920x1080 and 0.24 at 3840x2160 (the weaker the priors, the closer
    to the person's shape), but noise of 2 px at 640 wide, scaled to the image (a detector's error grows with
    the face), tipped the pose by up to 3.07 / 3.22 / 4.42 / 6.24 degrees (32 draws; 1.54 / 1.57 / 1.76 / 2.16
    mean): the priors' strength was tuned at 640x480. Scaled, every size fits as 640x480 does.

    Attributes:
        shape_prior_precision: precision of the zero-mean Gaussian prior on each shape coefficient, in units of
            squared pixels of landmark error (at ``reference_focal_px``) per unit coefficient squared: one value
            for every unit, or a tuple of one per unit (its length the model's ``S``; :func:`fit_landmarks` checks
            it). Weak (2) so that the shape fits faces unlike the mean.
        held_shape_units: names (a tuple or list) of the shape units whose precision is ``held_shape_precision``
            instead. From one frontal view the units that move features vertically trade with the head's pitch, and
            2 px of landmark noise then tips the pose by up to 2.75 degrees (8 draws; 6.41 with a starting
            expression); held, 1.42 (1.46). None: :data:`CANDIDE3_VERTICAL_UNITS`, those of them the model has
            (none for a model without those names); ``()``: none. Names given must be the model's
            (:func:`fit_landmarks` checks). The online look-ahead start lets these units go again once the head has
            turned (:class:`~torchface.tracker.lookahead.LookaheadConfig`), since a side view separates them from
            the pitch.
        held_shape_precision: the precision of ``held_shape_units`` (at ``reference_focal_px``, as every
            precision here).
        shape_bound: shape coefficients are kept in ``[-shape_bound, shape_bound]``.
        fit_expression: also estimate a starting expression (animation units, bounded by the model's ranges).
        expression_prior_precision: prior precision on the animation units when ``fit_expression``: in [0, 1e6]
            (:data:`MAX_UNIT_PRECISION`, as the tracker's expression priors): at 1e6 the units are held at 0 as
            ``fit_expression=False`` holds them, and from about 1e19 the fit was FAILED.
        max_iterations: Levenberg-Marquardt iterations.
        refine_shape_prior_precision: when set, a second solve re-estimates the shape alone (pose and expression
            held at the first solve's values) with this weaker prior. The first, strongly regularised solve gives
            a pose that noisy points cannot tip; the second lets the shape move away from the mean where the
            points ask for it, so the template's depth matches a face unlike the mean face.
        max_rotation_std_deg: a fit whose landmarks' layout determines the rotation only to more than this standard
            deviation (degrees, in its least determined direction) is FAILED; None: no such check. The standard
            deviation is that of the pose alone (shape and expression held at the fit's) for a noise of 1% of the
            face's width on each landmark coordinate (1.8 px on the mean face at 450 mm in 640 x 480), so it measures
            the layout whatever the face's size: :func:`rotation_std_deg`. Layouts that cannot hold the pose were
            CONVERGED tens of degrees off: the nose bridge alone (4 nearly collinear points; 2 px of noise, 53-146
            degrees off) gives 33 and more, the base of the nose alone 6-19, one eye alone 7-50 (CANDIDE-3 and the
            James scan rendered frontal, at yaw +-40, pitch +-20 and a mixed pose, at 450 and 900 mm); the 68
            landmarks 0.5-0.9, the 51 inner ones up to 1.7, 5-point subsets (eye corners, nose, mouth corners) up to
            6.6, and every fit within 3 degrees of the truth from 2 px noisy landmarks up to 12.1. It does not see the
            shape and expression units trading with the pose (a sparse subset's main error, which
            ``sparse_landmark_count`` holds: docs/limitations.md).
        max_facing_deg: a fit that turned the face more than this many degrees from facing the camera (the angle
            between its forward axis and the ray to its landmarks' centroid) is FAILED; None: only a face turned away
            (90 degrees and more) is. A face seen edge-on hides half its landmarks, yet projects them onto a line,
            and that is how the fit explained (nearly) collinear landmarks that the layout check
            (``max_rotation_std_deg``) passes, since the face's depth relief determines the edge-on pose well
            (CANDIDE-3 frontal, at yaw +-40, pitch +-20 and a mixed pose, at 450 and 900 mm, 0-2 px of noise; this
            and the tracker's fit): the 68 landmarks moved onto one row or a slanted line CONVERGED 85-90 degrees
            from facing the camera, 64-113 degrees off (rotation standard deviation 0.24-0.28); the 17 jaw points
            moved onto a line 75-90 degrees (0.40-0.57); subsets of 4-12 points (eye corners, one eye, both eyes,
            nose, upper lip, the 5-point one) so moved 75-90 degrees, 36-147 off; and the 8 inner lip points as
            they are (2 px of noise, 900 mm) 89 degrees, 76 off. 75: the evaluation's scenarios face the camera
            within 46 degrees (the long runs within 61), and no good fit (within 10 degrees of the truth) above
            faced it beyond 50; the model's own 68 landmarks fit to within 1.5 degrees up to 85 degrees of yaw or
            pitch (FAILED now above 75), but no detector sees a face's landmarks there. Landmarks on a line that a
            face facing the camera within 75 degrees explains are not caught (of the 2808 line cases above, 795
            still CONVERGED more than 30 degrees off), nor can be by the fit's geometry alone.
        reference_focal_px: the focal length (pixels) at which the precisions above hold as given: 640, that of
            ``Intrinsics.default(640, 480)`` (the standard scenarios' camera, where they were tuned), whose fits
            the scaling leaves as they were, to the bit (a factor of exactly 1). None: no scaling, the precisions
            in the squared pixels of whatever camera is given (the fit before session 43).
        sparse_landmark_count: a sample fitted from fewer landmarks than this (finite, of positive weight: a subset
            given by ``landmark_indices``, or NaN or zero-weight rows) is sparse: its shape units' precisions are
            raised to at least ``sparse_shape_prior_precision`` and, with ``fit_expression``, its animation units'
            to at least ``sparse_expression_prior_precision``. None: the fit's unknowns, ``6 + S`` (``+ A`` with
            ``fit_expression``): CANDIDE-3's 20, 31 for the tracker's fit; fewer landmarks give fewer than two
            residuals per unknown. 0: no sample is sparse. Few points cannot separate the pose from the units that
            move them, and the weak dense priors let those units absorb what is pose: the 5 points of a detector
            (outer eye corners, nose tip, mouth corners), 2 px of noise, the mean face frontal, at yaw 20 and -30
            and a mixed pose (80 draws) were fitted 4.8 / 12.6 degrees off (mean / worst; the tracker's fit,
            expression precision 2, 6.1 / 18.7), dlib's 5 (eye corners, nose base) 7.7 / 21.8, 10 points (eye
            corners, nose, mouth corners) 4.8 / 10.6; held, 3.4 / 7.5 (3.5 / 7.7), 6.5 / 16.7 and 3.7 / 8.5.
            Random subsets (the mean face, a CANDIDE-3 person and the James scan, yaw to 40 and pitch to 20 degrees,
            450 and 900 mm) gained most below the unknowns' count (12 points: 6.7 to 5.8 degrees mean, the
            tracker's fit 8.9 to 5.9; 20 and 26, the tracker's fit: 4.8 to 4.4, 4.3 to 4.0), little above it (32,
            the tracker's fit: 4.3 to 4.0; means within 0.1 degree from 40 points on). A denser sample keeps the
            dense priors, its fit the same to the bit (the 68 landmarks, as the evaluation and the tracker's start
            fit them, unless the model has more than 68 unknowns: the ICT Face Model has 106, 159 with the
            expression). The look-ahead refinements hold a sparse start's re-estimated units at these precisions too
            (:func:`~torchface.tracker.lookahead.landmark_fit_priors`).
        sparse_shape_prior_precision: a sparse sample's least shape precision (at ``reference_focal_px``): 64, the
            prior of a population whose shape coefficients spread about 0.25 about the mean, for landmarks of 2 px
            of noise. Stronger priors fit the mean face better still but bias a face unlike it (the subjects'
            CANDIDE-3 shapes, coefficients up to 0.72), weaker ones let the units trade with the pose again.
        sparse_expression_prior_precision: a sparse sample's least expression precision (with ``fit_expression``;
            at ``reference_focal_px``): 200, ``FitConfig()``'s ``expression_prior_precision``; in [0, 1e6] as it.
    """

    shape_prior_precision: float | tuple[float, ...] = 2.0
    held_shape_units: tuple[str, ...] | None = None
    held_shape_precision: float = 256.0
    shape_bound: float = 1.0
    fit_expression: bool = False
    expression_prior_precision: float = 200.0
    max_iterations: int = 50
    refine_shape_prior_precision: float | None = None
    max_rotation_std_deg: float | None = 15.0
    max_facing_deg: float | None = 75.0
    reference_focal_px: float | None = 640.0
    sparse_landmark_count: int | None = None
    sparse_shape_prior_precision: float = 64.0
    sparse_expression_prior_precision: float = 200.0

    def __post_init__(self) -> None:
        # Each number's range, stated once (check_number: a wrong type a TypeError naming it, NaN or an infinite
        # value a ValueError: inf passed "> 0" as a bound, a layout check or a focal length). A precision's NaN failed
        # in the solver; max_rotation_std_deg NaN would fail nothing, 0 everything; max_facing_deg 90 and more: the
        # turned-away check does it.
        for name, interval, optional in (
            ("held_shape_precision", "[0, inf)", False), ("shape_bound", "(0, inf)", False),
            ("expression_prior_precision", "[0, inf)", False), ("refine_shape_prior_precision", "[0, inf)", True),
            ("max_rotation_std_deg", "(0, inf)", True), ("max_facing_deg", "(0, 90)", True),
            ("reference_focal_px", "(0, inf)", True), ("sparse_shape_prior_precision", "[0, inf)", False),
            ("sparse_expression_prior_precision", "[0, inf)", False),
        ):  # fmt: skip
            object.__setattr__(self, name, check_number(getattr(self, name), name, interval, optional))
        for name in ("expression_prior_precision", "sparse_expression_prior_precision"):  # (1e20 was FAILED)
            check_unit_precision(getattr(self, name), name, _FIT_STRONG_PRIOR)
        object.__setattr__(self, "shape_prior_precision", check_precisions(self.shape_prior_precision,
                                                                           "shape_prior_precision"))  # fmt: skip
        object.__setattr__(self, "fit_expression", check_bool(self.fit_expression, "fit_expression"))  # "no" was true
        object.__setattr__(self, "max_iterations", check_int(self.max_iterations, "max_iterations", 1))  # 2.5: at the fit
        count = check_optional_int(self.sparse_landmark_count, "sparse_landmark_count", 0)
        object.__setattr__(self, "sparse_landmark_count", count)
        # (a list was a ValueError, as was a wrong type: the other tuple settings take a list, and say TypeError)
        object.__setattr__(self, "held_shape_units", check_names(self.held_shape_units, "held_shape_units", True))


def check_precisions(value: object, name: str) -> float | tuple[float, ...]:
    """A shape prior setting of one precision for every unit, or one per unit (:attr:`FitConfig.shape_prior_precision`,
    :attr:`~torchface.tracker.lookahead.LookaheadConfig.shape_prior_precision`): a number, or a non-empty tuple, list
    or 1-D array of numbers (kept as a tuple), each finite and >= 0.

    Raises:
        TypeError: ``value`` is neither a number nor a sequence of numbers (it was a ``ValueError``, the settings'
            only one for a wrong type).
        ValueError: it is empty, or a precision is negative, NaN or infinite.
    """
    if isinstance(value, (tuple, list)) or (isinstance(value, (np.ndarray, Tensor)) and value.ndim == 1):
        precisions = check_reals(value, name, "[0, inf)")
        if not precisions:
            raise ValueError(f"{name} must be a number or a non-empty tuple of numbers (one per shape unit), got ()")
        return precisions
    try:
        return check_number(value, name, "[0, inf)")
    except TypeError:
        raise TypeError(f"{name} must be a real number or a tuple of them (one per shape unit), got "
                        f"{type(value).__name__} {value!r}") from None


@dataclass(frozen=True, eq=False)
class LandmarkFit:
    """Result of :func:`fit_landmarks`.

    Attributes:
        rotation: ``(B, 3, 3)`` head -> camera; axis_angle: ``(B, 3)``; translation: ``(B, 3)`` mm.
        shape_coeffs: ``(B, S)``; anim_coeffs: ``(B, A)`` (zeros unless fitted).
        rms_px: ``(B,)`` weighted RMS landmark reprojection error in pixels.
        status: ``(B,)`` int64 :class:`~torchface.solver.SolveStatus`: the solver's, or FAILED for a sample whose
            landmarks hold no pose (or that has fewer than 4 of them), or whose fit put a used landmark behind the
            camera or turned the face away from it or nearly edge-on (:func:`fit_landmarks`).
    """

    rotation: Tensor
    axis_angle: Tensor
    translation: Tensor
    shape_coeffs: Tensor
    anim_coeffs: Tensor
    rms_px: Tensor
    status: Tensor

    def select(self, index: int | Sequence[int] | Tensor) -> "LandmarkFit":
        """The fit of streams ``index``: an int (or a 0-d integer tensor; negative from the end) is one stream's fit
        without the batch dimension (``rotation (3, 3)``); stream indices (a list or int64 tensor, in the order
        wanted) or a ``(B,)`` bool mask keep it, ``fit.select([b])`` being stream ``b``'s fit as a batch of one. The
        indices are read as ``TrackResult.select`` reads them (:func:`~torchface.tracker.step.stream_index`): None, a
        slice, a set, a uint8 tensor and an index out of range are refused (None added a dimension, a slice was
        taken, an index out of range was torch's bare IndexError).

        Example:
            >>> fit.select([1]).rotation.shape, fit.select(1).rotation.shape     # doctest: +SKIP
            (torch.Size([1, 3, 3]), torch.Size([3, 3]))
        """
        from torchface.tracker.step import stream_index

        if self.status.ndim != 1:  # (its fields' first dimension is no batch: rotation's rows were taken for one)
            raise ValueError("this LandmarkFit is one stream's, without its batch dimension (select of an int): "
                             "select streams from the batched fit")  # fmt: skip
        one = (isinstance(index, (int, np.integer)) and not isinstance(index, (bool, np.bool_))) or (
            isinstance(index, Tensor) and index.ndim == 0 and index.dtype not in (torch.bool, torch.uint8)
        )  # fmt: skip
        rows = stream_index(index, int(self.status.shape[0]), self.status.device)  # type: ignore[arg-type]
        return LandmarkFit(*(getattr(self, f)[rows[0] if one else rows] for f in self.__dataclass_fields__))

    def to(
        self, device: torch.device | str | int | torch.dtype | None = None, dtype: torch.dtype | None = None,
        non_blocking: bool = False, copy: bool = False,
    ) -> "LandmarkFit":
        """A copy on ``device`` with the floating tensors in ``dtype`` (a floating dtype; ``status`` keeps its integer
        dtype), called as ``Tensor.to`` is (``.to(device)``, ``.to(dtype)``, ``.to(device, dtype)``, keywords,
        ``non_blocking`` and ``copy``: :func:`~torchface._device.tensor_mover`, as ``TrackResult.to``)."""
        move = tensor_mover(device, dtype, non_blocking, copy)  # (a device this machine lacks: a ValueError)
        return LandmarkFit(*(move(getattr(self, f)) for f in self.__dataclass_fields__))


#: The shape units :class:`FitConfig` holds by default (``held_shape_units=None``): CANDIDE-3's units that move
#: features vertically, which one frontal view cannot tell from the head's pitch.
CANDIDE3_VERTICAL_UNITS: tuple[str, ...] = (
    "Eyebrows vertical position", "Eyes vertical position", "Nose vertical position", "Mouth vertical position",
)


def held_shape_indices(config: FitConfig, shape_names: Sequence[str]) -> tuple[int, ...]:
    """Indices (into ``shape_names``, the model's) of :attr:`FitConfig.held_shape_units`, ascending.

    Raises:
        ValueError: an explicitly given name that is not the model's.
    """
    names = list(shape_names)
    if config.held_shape_units is None:
        return tuple(i for i, n in enumerate(names) if n in CANDIDE3_VERTICAL_UNITS)
    missing = [n for n in config.held_shape_units if n not in names]
    if missing:
        raise ValueError(f"held_shape_units {missing} are not among the model's shape units {tuple(names)}")
    return tuple(sorted(names.index(n) for n in config.held_shape_units))


def shape_precisions(
    config: FitConfig, shape_names: Sequence[str], dtype: torch.dtype, device: torch.device | str | None
) -> Tensor:
    """``(S,)`` the landmark fit's shape prior precisions: :attr:`FitConfig.shape_prior_precision`, with
    :attr:`FitConfig.held_shape_precision` on the held units (:func:`held_shape_indices`)."""
    precision = shape_prior_vector(config.shape_prior_precision, len(shape_names), dtype, device)
    held = held_shape_indices(config, shape_names)
    if held:
        precision[list(held)] = config.held_shape_precision
    return precision


def prior_scale(config: FitConfig, intrinsics: Intrinsics) -> float:
    """The factor on :class:`FitConfig`'s prior precisions for a camera: ``fx fy / reference_focal_px**2`` (1 when
    ``reference_focal_px`` is None).

    A face at a given distance spans ``fx / reference_focal_px`` times the pixels it spans at the reference focal
    length (``fy / ...`` vertically), and the landmark terms' squared residuals and Jacobians grow with the
    product; the precisions, scaled by it, keep their weight against them. Exactly 1.0 for the reference camera.

    Raises:
        ValueError: a factor beyond the float range (focal lengths of 1e154 pixels and more).

    Example:
        >>> [prior_scale(FitConfig(), Intrinsics.default(w, h)) for w, h in ((640, 480), (1920, 1080), (320, 240))]
        [1.0, 9.0, 0.25]
    """
    if config.reference_focal_px is None:
        return 1.0
    # (a focal length that carries a gradient read detached: float() of it warned at each fit)
    fx, fy = (float(f.detach()) if isinstance(f, Tensor) else float(f) for f in (intrinsics.fx, intrinsics.fy))
    scale = fx * fy / float(config.reference_focal_px) ** 2
    if not math.isfinite(scale):  # the priors would be infinite, and 0 * inf NaN
        raise ValueError(f"the prior scale fx fy / reference_focal_px**2 is {scale}: focal lengths too large")
    return scale


def check_shape_prior_count(
    precision: float | tuple[float, ...] | None, num_shape: int, name: str = "shape_prior_precision"
) -> None:
    """Refuse a shape prior setting ``name`` (:attr:`FitConfig.shape_prior_precision`,
    :attr:`~torchface.tracker.lookahead.LookaheadConfig.shape_prior_precision`) that is a tuple of other than one
    value per shape unit of a model of ``num_shape`` (one number passes: it is every unit's; so does None, the
    look-ahead's "the landmark fit's").

    Raises:
        ValueError: a tuple whose length is not ``num_shape``, naming both.
    """
    if isinstance(precision, tuple) and len(precision) != num_shape:
        raise ValueError(f"{name} has {len(precision)} values; the model has {num_shape} shape units (one value for "
                         "all of them, or one per unit)")  # fmt: skip


def shape_prior_vector(
    precision: float | tuple[float, ...], num_shape: int, dtype: torch.dtype, device: torch.device | str | None
) -> Tensor:
    """``(S,)`` the shape units' prior precisions from :attr:`FitConfig.shape_prior_precision` (one value for all,
    or one per unit).

    Raises:
        ValueError: a tuple whose length is not ``num_shape`` (:func:`check_shape_prior_count`).
    """
    if isinstance(precision, tuple):
        check_shape_prior_count(precision, num_shape)
        return torch.tensor(precision, dtype=dtype, device=device)
    return torch.full((num_shape,), float(precision), dtype=dtype, device=device)


def landmark_targets(landmarks_px: Tensor, weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """What the landmark terms fit (:func:`fit_landmarks`, the look-ahead refinement): ``(targets, weights)``.

    Args:
        landmarks_px: ``(..., K, 2)`` pixels; a point with a NaN or infinite coordinate is missing (the entry points
            refuse infinite ones: :func:`check_landmark_values`; a detector's are made NaN rows).
        weights: ``(..., K)`` confidences, or None for ones.

    Returns:
        ``targets (..., K, 2)``: the landmarks, non-finite coordinates set to 0 (they weigh 0, and a product of 0
        with an infinite target's square would be NaN); ``weights (..., K)``: 0 for a missing point and for a NaN,
        infinite or negative weight, the weight elsewhere; both in ``landmarks_px``' dtype and device. (The entry
        points refuse rows with one coordinate NaN alone or an infinite one, and NaN, infinite or negative weights:
        :func:`check_landmark_values`; this reads what they let through, and a detector's answer.)
    """
    finite = torch.isfinite(landmarks_px)
    w = torch.ones_like(landmarks_px[..., 0]) if weights is None else weights.to(landmarks_px)
    w = torch.where(finite.all(-1) & torch.isfinite(w), w.clamp_min(0), torch.zeros_like(w))
    return torch.where(finite, landmarks_px, torch.zeros_like(landmarks_px)), w


def landmarks_inside_fraction(landmarks_px: Tensor, weights: Tensor | None, width: int, height: int) -> Tensor:
    """``(B,)`` the fraction of each stream's landmarks ``(B, K, 2)`` (those that count: finite, of finite positive
    ``weights`` ``(B, K)`` where given, as :func:`landmark_targets` says) that lie inside ``width x height`` frames
    (pixel centres ``[0, W - 1] x [0, H - 1]``, as
    :func:`~torchface.template.management.face_inside_fraction` counts the face's vertices); 0 where none counts.
    Read by :func:`~torchface.tracker.managed.initialise_managed` to say that a start failed because the face is
    outside the frame (:attr:`~torchface.tracker.step.StartFailure.OUTSIDE_FRAME`).

    Example:
        >>> lm = torch.tensor([[[10.0, 10.0], [20.0, 20.0]], [[10.0, 10.0], [900.0, 20.0]]])
        >>> landmarks_inside_fraction(lm, None, 64, 48).tolist()
        [1.0, 0.5]
    """
    lm = landmarks_px.detach()
    _, w = landmark_targets(lm, None if weights is None else weights.detach())
    counted = w > 0
    x, y = lm[..., 0], lm[..., 1]
    inside = counted & (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    return inside.sum(-1) / counted.sum(-1).clamp_min(1)  # (float: true division of the counts)


def _landmarks_hint(landmarks_px: object, shape: str) -> str:
    """How to pass landmarks that are not a tensor as the ``shape`` wanted (``"(B, 68, 2)"``, ``"(L, 2)"``), for
    :func:`check_landmark_type`'s message: a NumPy array (what :func:`torchface.io.read_landmarks` returns, ``(K, 2)``
    float64: it said "got ndarray" alone), a list or tuple of points; empty for anything else."""
    wanted = shape.count(",") + 1
    ndim = getattr(landmarks_px, "ndim", None)
    if type(landmarks_px).__name__ == "ndarray" and isinstance(ndim, int):
        if wanted == 3 and ndim == 2:
            return " (a NumPy array of one stream's (K, 2) points, as read_landmarks gives them: " \
                "torch.from_numpy(points)[None])"
        return " (a NumPy array: torch.from_numpy(points))"
    if isinstance(landmarks_px, (list, tuple)):
        return f" (a {type(landmarks_px).__name__}: torch.tensor(points), laid out {shape})"
    return ""


def check_landmark_type(landmarks_px: object, shape: str) -> None:
    """Refuse ``landmarks_px`` that is not a tensor of real pixel coordinates (a TypeError naming ``shape``, the
    shape expected, e.g. ``"(B, 68, 2)"``): a numpy array failed later with an AttributeError, and bool ones were
    fitted as pixels 0 and 1."""
    if not isinstance(landmarks_px, Tensor):
        raise TypeError(f"landmarks_px must be a torch.Tensor {shape} of pixel coordinates, "
                        f"got {type(landmarks_px).__name__}{_landmarks_hint(landmarks_px, shape)}")  # fmt: skip
    check_holds_data(landmarks_px, "landmarks_px")
    if landmarks_px.dtype == torch.bool or landmarks_px.is_complex():
        raise TypeError(f"landmarks_px must be real pixel coordinates (float or int), got {landmarks_px.dtype}")
    if landmarks_px.dtype in (torch.float16, torch.bfloat16):
        warn_half_precision_landmarks(landmarks_px.dtype)


_L = TypeVar("_L")


def half_precision_landmarks_warning(dtype: torch.dtype) -> str:
    """What :func:`warn_half_precision_landmarks` says of ``dtype`` (float16 or bfloat16) landmarks: the steps its
    significant bits round pixel coordinates to, and what to pass instead.

    Example:
        >>> half_precision_landmarks_warning(torch.bfloat16)  # doctest: +ELLIPSIS
        'landmarks_px are torch.bfloat16, which rounds pixel coordinates to steps of 0.5 px from 64, 1 px from 128...'
    """
    eps = torch.finfo(dtype).eps  # (the step from 1 to 2: 2**-7 for bfloat16, 2**-10 for float16)
    return (f"landmarks_px are {half_precision_rounding(str(dtype), eps)}: they are fitted as given, rounded "
            "(converting them back cannot restore the digits lost); pass float32 landmarks (those before the cast, "
            "or made outside torch.autocast) for sub-pixel ones")  # fmt: skip


def warn_half_precision_landmarks(dtype: torch.dtype) -> None:
    """Warn that float16 / bfloat16 landmarks are rounded (:func:`half_precision_landmarks_warning`): a network's
    landmarks under ``torch.autocast``, or a ``.half()``, reached the fit 1-2 px off (bfloat16 at 128-512 px) without
    a word. Warned, not refused, as float16 / bfloat16 frames are taken (converted to the model's dtype) and a
    ``torch.autocast`` region is left as the caller's (:mod:`torchface._autocast`): the coordinates are what the
    caller has. One warning per dtype, from here: Python's default warning filter shows it once (each entry point
    of ``initialise`` checks the landmarks again)."""
    warnings.warn(half_precision_landmarks_warning(dtype), UserWarning, stacklevel=1)


def widen_half_landmarks(landmarks_px: _L) -> _L:
    """``landmarks_px`` as float32 where they are a float16 or bfloat16 tensor (exact: the same values the fit would
    convert them to), warned of once (:func:`warn_half_precision_landmarks`), so that the checks an entry point's
    callees make again do not warn again; anything else as it is (the checks refuse what is not landmarks)."""
    if isinstance(landmarks_px, Tensor) and landmarks_px.dtype in (torch.float16, torch.bfloat16):
        warn_half_precision_landmarks(landmarks_px.dtype)
        return cast(_L, landmarks_px.float())
    return landmarks_px


def _points_named(bad: Tensor) -> str:
    """``landmark(s) [3, 7]`` for the True entries of a ``(K,)`` or ``(B, K)`` bool mask (at most 8 listed), with
    ``of stream b`` and the other streams' numbers where a batch of more than one stream holds them."""
    bad = bad.detach().cpu()

    def listed(indices: list[int]) -> str:  # (more than 8 were listed as the first 8 alone: all 68 read as 8)
        return str(indices) if len(indices) <= 8 else f"{str(indices[:8])[:-1]}, ...] ({len(indices)} in all)"

    if bad.dim() < 2 or bad.shape[0] == 1:
        return f"landmark(s) {listed(bad.reshape(-1, bad.shape[-1]).any(0).nonzero().flatten().tolist())}"
    flat = bad.reshape(-1, bad.shape[-1])
    streams = flat.any(-1).nonzero().flatten().tolist()
    more = f" (and in stream(s) {listed(streams[1:])})" if len(streams) > 1 else ""
    return f"landmark(s) {listed(flat[streams[0]].nonzero().flatten().tolist())} of stream {streams[0]}{more}"


def landmark_rows_problem(landmarks_px: Tensor, *, weighted: bool = True) -> str | None:
    """One line naming the rows of ``(K, 2)`` or ``(B, K, 2)`` landmarks that are neither a point (both coordinates
    finite) nor a missing point (both NaN), or None: the one rule every landmark input follows (the Python API's
    :func:`check_landmark_values`; a landmarks file's and ``training_hooks``' arrays,
    :func:`torchface.io.landmarks.missing_points_problem`). A missing point is a NaN row. Refused:

    - a row with an infinite coordinate: most likely a bug upstream (a division by zero, an overflow), not a way to
      leave a point out (it used to be taken as missing by :class:`~torchface.tracker.FaceTracker` and refused by
      the command line);
    - a row with one coordinate NaN and the other finite: most likely a bug upstream too (a column lost or shifted,
      one coordinate of a point masked).

    ``weighted``: the input takes weights (the message then says that weight 0 ignores a point). A detector's
    answer mid-stream is not refused: such rows are missing points, with a warning
    (:func:`~torchface.tracker.managed.initialise_managed`'s restarts).

    Example:
        >>> lm = torch.tensor([[1.0, 2.0], [float("nan"), 3.0]])
        >>> landmark_rows_problem(lm, weighted=False)  # doctest: +ELLIPSIS
        'landmark(s) [1] have one coordinate NaN (a missing point has neither): mark a missing point with both ...'
        >>> landmark_rows_problem(torch.tensor([[1.0, 2.0], [float("inf"), float("inf")]]))  # doctest: +ELLIPSIS
        'landmark(s) [1] are infinite (a missing point is a NaN row): most likely a bug upstream (a division by ...'
    """
    lm = landmarks_px.detach()
    if not lm.is_floating_point() or lm.dim() < 2 or lm.shape[-1] != 2:  # (integers are finite; shapes: callers')
        return None
    finite = torch.isfinite(lm)
    if bool(finite.all()):
        return None
    zero = "give a point you do not trust weight 0" if weighted else ""
    infinite = torch.isinf(lm).any(-1)
    partly = finite.any(-1) & ~finite.all(-1) & ~infinite  # (one coordinate NaN, the other finite)
    problems: list[str] = []
    if bool(infinite.any()):
        problems.append(f"{_points_named(infinite)} are infinite (a missing point is a NaN row): most likely a bug "
                        f"upstream (a division by zero, an overflow){'; ' + zero if zero else ''}")  # fmt: skip
    if bool(partly.any()):
        problems.append(f"{_points_named(partly)} have one coordinate NaN (a missing point has neither): mark a "
                        f"missing point with both coordinates NaN (a NaN row){', or ' + zero if zero else ''}; one "
                        "coordinate alone is most likely a bug upstream (a column lost or shifted)")  # fmt: skip
    return "; ".join(problems) or None


def _weights_shape_hint(got: tuple[int, ...], batch: int, count: int) -> str:
    """How to make ``(batch, count)`` landmark weights of weights shaped ``got``, for a message refusing them: one
    weight per landmark for every stream ``(K,)``, or a trailing axis ``(B, K, 1)``, as landmarks' ``(B, K, 2)``
    suggests (both were told the shapes alone); empty otherwise."""
    if got == (count,):
        return " (one per landmark: weights[None]" + (")" if batch == 1 else f".expand({batch}, -1) for every stream)")
    if got == (batch, count, 1):
        return " (a trailing axis: weights[..., 0])"
    return ""


def _weights_type_hint(weights: object, batch: int, count: int) -> str:
    """How to make ``(batch, count)`` tensor weights of ``weights`` that are not a tensor, for the ``TypeError`` that
    refuses them, as `` (...)``: a NumPy array (``(K,)``: one stream's) or a list, as landmarks are told (they were
    told the type alone); empty otherwise."""
    shape = getattr(weights, "shape", None)
    if type(weights).__name__ == "ndarray" and isinstance(shape, tuple):
        each = "" if shape != (count,) else "[None]" if batch == 1 else f"[None].expand({batch}, -1)"
        return f" (a NumPy array: torch.from_numpy(weights){each})"
    if isinstance(weights, (list, tuple)):
        return f" (a {type(weights).__name__}: torch.tensor(weights), laid out ({batch}, {count}))"
    return ""


def check_weights_shape(weights: object, batch: int, count: int) -> None:
    """Refuse landmark weights that are not a ``(batch, count)`` tensor (None passes): one ``TypeError`` or
    ``ValueError`` and one message, with how to make them where it can tell (:func:`fit_landmarks`,
    :func:`~torchface.tracker.step.check_initialise_inputs` and
    :func:`~torchface.tracker.step.pyramid_for_faces` call it; each had worded the shape its own way).

    Example:
        >>> check_weights_shape(torch.ones(68), 1, 68)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
            ...
        ValueError: weights must be a (B, K) = (1, 68) tensor or None, got shape (68,) (one per landmark: ...
    """
    if weights is None:
        return
    if not isinstance(weights, Tensor):  # (a list or a NumPy array: an AttributeError)
        raise TypeError(f"weights must be a (B, K) = ({batch}, {count}) tensor or None, got {type(weights).__name__}"
                        f"{_weights_type_hint(weights, batch, count)}")  # fmt: skip
    got = tuple(weights.shape)
    if got != (batch, count):
        raise ValueError(f"weights must be a (B, K) = ({batch}, {count}) tensor or None, got shape {got}"
                         f"{_weights_shape_hint(got, batch, count)}")  # fmt: skip


def check_landmark_values(
    landmarks_px: Tensor, weights: Tensor | None = None, *, name: str = "landmarks_px", weights_name: str = "weights"
) -> None:
    """Refuse, with a ``ValueError`` naming the points, ``(..., K, 2)`` landmarks with a row that is neither a point
    nor a missing point (an infinite coordinate, or one coordinate NaN alone: :func:`landmark_rows_problem`) and
    ``(..., K)`` ``weights`` (checked for shape by the caller) that are NaN, infinite or negative: they were taken
    as weight 0 without a word (:func:`landmark_targets`), where they are almost surely a bug (a confidence of NaN
    from a failed detection, a log-probability given as a weight). Weights are ``>= 0``: 0 ignores a point (as a
    NaN row does), 1 is what the fit's priors are set for. The checks of :func:`fit_landmarks`,
    :func:`~torchface.tracker.step.initialise` (and so :class:`~torchface.tracker.FaceTracker`),
    :func:`~torchface.tracker.step.pyramid_for_faces` and the look-ahead's refinement."""
    problem = landmark_rows_problem(landmarks_px)
    if problem is not None:
        raise ValueError(f"{name}: {problem}")
    if weights is None or weights.dtype == torch.bool:
        return
    if weights.is_complex():  # (torch's NotImplementedError '"lt_cpu" not implemented for 'ComplexFloat'')
        raise TypeError(f"{weights_name} must be real numbers >= 0 (landmark confidences), got {weights.dtype}")
    w = weights.detach()
    bad = w < 0
    if w.is_floating_point():
        bad = bad | ~torch.isfinite(w)
    if not bool(bad.any()):
        return
    nan = torch.isnan(w) if w.is_floating_point() else torch.zeros_like(bad)
    if bool(nan.any()):
        raise ValueError(f"{weights_name} must be numbers >= 0, got NaN for {_points_named(nan)}: give a point you do "
                         "not trust weight 0 (or a NaN row in the landmarks for a missing one)")  # fmt: skip
    inf = torch.isinf(w) if w.is_floating_point() else torch.zeros_like(bad)
    if bool(inf.any()):
        raise ValueError(f"{weights_name} must be finite, got {float(w[inf][0]):g} for {_points_named(inf)}: a "
                         "weight scales its landmark's squared error (1 is what the fit's priors are set for; 0 "
                         "ignores the point)")  # fmt: skip
    raise ValueError(f"{weights_name} must be >= 0 (0 ignores a point; 1 is what the fit's priors are set for), got "
                     f"{float(w[bad][0]):g} for {_points_named(bad)}")  # fmt: skip


def _check_landmark_indices(idx: object, num_landmarks: int) -> None:
    """Refuse ``landmark_indices`` that are not a ``(K,)`` integer tensor of rows in ``[0, num_landmarks)``: a
    negative index fitted a landmark counted from the table's end, a list failed with an AttributeError."""
    if not isinstance(idx, Tensor) or idx.dim() != 1 or idx.dtype not in (torch.int64, torch.int32):
        got = f"{idx.dtype} {tuple(idx.shape)}" if isinstance(idx, Tensor) else type(idx).__name__
        raise TypeError(f"landmark_indices must be a (K,) int64 tensor or None, got {got}")
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= num_landmarks):
        raise ValueError(f"landmark_indices must be in [0, {num_landmarks}) (the model's landmark rows), "
                         f"got {int(idx.min())}..{int(idx.max())}")  # fmt: skip


#: The fewest landmarks (finite, of positive weight) a sample's :func:`fit_landmarks` needs: the pose's six
#: parameters need as many residuals. A sample with fewer (a frame where no face was found: NaN rows) is FAILED.
MIN_FIT_LANDMARKS: int = 4


def normalised_streams(
    landmarks_px: Tensor, width: int, height: int, weights: Tensor | None = None
) -> Tensor:
    """``(B,)`` bool: the streams whose ``(B, K, 2)`` landmarks look like normalised image coordinates (x / W, y / H
    in [0, 1], MediaPipe's) for ``width x height`` frames, by :func:`check_pixel_landmarks`' rule for one stream: at
    least :data:`MIN_FIT_LANDMARKS` of them (finite, of finite positive ``weights`` ``(B, K)`` where given), all in
    :data:`~torchface.conventions.NORMALISED_LANDMARK_RANGE` along each axis, spanning at most
    :data:`~torchface.conventions.NORMALISED_LANDMARK_MAX_SPAN` and not all at one point: a face about a pixel wide
    in pixels, which the landmark fit fails. All False for frames with a side under
    :data:`~torchface.conventions.NORMALISED_CHECK_MIN_SIDE` pixels, landmarks not ``(B, K, 2)`` and under
    ``torch.compile``. :func:`~torchface.tracker.step.initialise` fails such a stream alone (reason
    :attr:`~torchface.tracker.step.StartFailure.NORMALISED_LANDMARKS`), and so does a detector's restart.

    Example:
        >>> normalised_streams(torch.stack([torch.rand(68, 2), torch.rand(68, 2) * 200]), 640, 480).tolist()
        [True, False]
    """
    return _normalised_and_pixels(landmarks_px, width, height, weights)[0]


def _normalised_and_pixels(
    landmarks_px: Tensor, width: int, height: int, weights: Tensor | None
) -> tuple[Tensor, Tensor]:
    """``(B,)`` bool each: the streams whose landmarks look normalised (:func:`normalised_streams`) and those with
    enough landmarks, some outside the normalised range (in pixels)."""
    none = torch.zeros(landmarks_px.shape[0] if landmarks_px.dim() else 0, dtype=torch.bool,
                       device=landmarks_px.device)  # fmt: skip
    if landmarks_px.dim() != 3 or landmarks_px.shape[-1] != 2 or landmarks_px.numel() == 0 or is_compiling():
        return none, none
    if min(width, height) < NORMALISED_CHECK_MIN_SIDE:  # (frames so small that a face in pixels spans a pixel too)
        return none, none
    lm = landmarks_px.detach().to(torch.promote_types(landmarks_px.dtype, torch.float32))  # (MPS has no float64)
    given = torch.isfinite(lm).all(-1)  # (B, K)
    if weights is not None and tuple(weights.shape) == tuple(given.shape):
        w = weights.detach().to(lm)
        given = given & torch.isfinite(w) & (w > 0)  # (the points landmark_targets weighs)
    usable = given.sum(-1) >= MIN_FIT_LANDMARKS  # (B,)
    low, high = NORMALISED_LANDMARK_RANGE
    inside = (((lm >= low) & (lm <= high)).all(-1) | ~given).all(-1)
    points = given.unsqueeze(-1)
    lo = torch.where(points, lm, math.inf).amin(1)
    hi = torch.where(points, lm, -math.inf).amax(1)
    span = (hi - lo).amax(-1)  # (B,)
    inside = inside & (span <= NORMALISED_LANDMARK_MAX_SPAN)
    spread = (span > 0) & usable
    return usable & inside & spread, usable & ~inside


def check_pixel_landmarks(
    landmarks_px: Tensor, width: int, height: int, weights: Tensor | None = None, *, name: str = "landmarks_px"
) -> None:
    """Refuse ``(B, K, 2)`` landmarks given in normalised image coordinates (x / W, y / H in [0, 1], as MediaPipe's
    face landmarker gives them) instead of pixels, with a ``ValueError`` that says how to make pixels of them.

    They are refused where every stream with at least :data:`MIN_FIT_LANDMARKS` landmarks (finite, of finite positive
    ``weights`` ``(B, K)`` where given) has all of them in ``[-0.5, 1.5] x [-0.5, 1.5]`` (MediaPipe's points of a face
    partly out of the frame lie a little outside ``[0, 1]``) spanning at most 1.5 along each axis, not all at one
    point, and none lies outside: such landmarks spread about a pixel at most, so the landmark fit FAILED every stream
    (:func:`fit_landmarks`) and the tracker reported status 2 with no word of why. A batch where
    some stream has landmarks in pixels fails such a stream alone, as before, and so does an answer of zeros for no
    face (all at one point), or any landmarks in frames with a side under
    :data:`~torchface.conventions.NORMALISED_CHECK_MIN_SIDE` pixels (the ranges: :mod:`torchface.conventions`).

    Args:
        landmarks_px: ``(B, K, 2)`` landmarks, a tensor (checked by the caller).
        width: ``W`` of the frames, in pixels.
        height: ``H`` of the frames, in pixels.
        weights: ``(B, K)`` landmark weights or None.
        name: what the message calls the landmarks (the argument's name, ``landmarks_px`` as ``initialise`` takes
            them; a detector's answer is not checked here: :func:`normalised_streams` fails its streams alone).

    Example:
        >>> check_pixel_landmarks(torch.rand(1, 68, 2), 640, 480)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
            ...
        ValueError: landmarks_px lie within [-0.5, 1.5] x [-0.5, 1.5]: normalised coordinates (x / W, y / H, as ...
    """
    normalised, in_pixels = _normalised_and_pixels(landmarks_px, width, height, weights)
    low, high = NORMALISED_LANDMARK_RANGE
    if bool(normalised.any()) and not bool(in_pixels.any()):
        lm = landmarks_px.detach()[normalised]
        # (centred coordinates, in [-1, 1] as some toolkits give them, were told the [0, 1] recipe alone, which put
        # their points at negative pixels)
        centred = bool((lm[torch.isfinite(lm)] < 0).any())
        raise ValueError(
            f"{name} lie within [{low}, {high}] x [{low}, {high}]: normalised coordinates (x / W, y / H, as MediaPipe "
            f"gives them)? The tracker takes pixels, centres at integers: landmarks * torch.tensor([{width}.0, {height}.0]) "
            f"for these {width}x{height} frames"
            + (f"; if they are centred, in [-1, 1] (some are below 0): (landmarks + 1) * torch.tensor([{width / 2:g}, "
               f"{height / 2:g}])" if centred else "")
            + " (a fit to them failed: they span about a pixel at most)"
        )


#: The least horizontal extent of a model's landmarks on its mean shape, as a fraction of its surface's width, that
#: :func:`check_model_landmarks` takes. The tracker measures a face's size by its landmarks' extent
#: (:func:`~torchface.tracker.step.face_width_px`, :attr:`~torchface.tracker.step.TrackerConfig.min_face_width_px`,
#: the landmark fit's rotation check): landmarks on the face's midline span none, and every stream FAILED.
MIN_LANDMARK_WIDTH_FRACTION: float = 0.1


def check_model_landmarks(model: FaceModel) -> None:
    """Refuse a model with fewer than :data:`MIN_FIT_LANDMARKS` landmarks: the first frame's pose is fitted to them,
    and such a model failed every stream (fewer than four) or raised an IndexError from inside (none). Refuse one
    whose landmarks span, across the face, less than :data:`MIN_LANDMARK_WIDTH_FRACTION` of its surface's width
    (all on the midline: every face was too small, :func:`~torchface.tracker.step.too_small`, and every stream
    FAILED without a word)."""
    if model.num_landmarks < MIN_FIT_LANDMARKS:
        raise ValueError(
            f"the model {model.name!r} has {model.num_landmarks} landmarks: the first frame's pose is fitted to the "
            f"model's landmarks, at least {MIN_FIT_LANDMARKS} of them (load_mesh_model's landmark_vertices; a face "
            "detector gives the 68 iBUG points, in their order)"
        )
    width, surface = _landmark_width_mm(model), _surface_width_mm(model)
    if not width >= MIN_LANDMARK_WIDTH_FRACTION * surface:
        raise ValueError(
            f"the model {model.name!r}'s landmarks span {width:.3g} mm across its mean face, which is {surface:.3g} mm "
            "wide: the tracker takes a face's size in the frame from its landmarks' width (face_width_px, "
            "TrackerConfig.min_face_width_px), so every face was too small and every stream FAILED; give landmarks "
            f"that span at least {MIN_LANDMARK_WIDTH_FRACTION:g} of the face's width (not all on its midline)"
        )


def _check_landmarks(
    landmarks_px: Tensor, weights: Tensor | None, k: int, dtype: torch.dtype, device: torch.device
) -> tuple[Tensor, Tensor]:
    """:func:`landmark_targets` of ``(B, k, 2)`` landmarks and ``(B, k)`` weights in ``dtype`` on ``device``, after
    checking their shapes and the weights of the samples that have :data:`MIN_FIT_LANDMARKS` usable points (fewer:
    missing, which :func:`fit_landmarks` reports as FAILED)."""
    check_landmark_type(landmarks_px, f"(B, {k}, 2)")
    if landmarks_px.dim() != 3 or landmarks_px.shape[1:] != (k, 2):
        got = tuple(landmarks_px.shape)
        hint = (": one sample's, landmarks_px[None]" if got == (k, 2)
                else " (x, y rows: landmarks_px.transpose(1, 2))" if got[1:] == (2, k)
                else " (x, y, z points, as 3D landmark detectors give them: landmarks_px[..., :2])"
                if got[1:] == (k, 3) else "")  # fmt: skip
        raise ValueError(f"landmarks_px must be (B, {k}, 2) pixel coordinates, got {got}{hint}")
    B = landmarks_px.shape[0]
    check_weights_shape(weights, B, k)
    check_landmark_values(landmarks_px, weights)
    # contiguous: the fit's sums over the points follow the memory order (a transposed view's fit was 5e-4 mm off)
    lm = landmarks_px.to(dtype=dtype, device=device).contiguous()
    target, w = landmark_targets(lm, None if weights is None else weights.to(lm).contiguous())
    used = w[(w > 0).sum(-1) >= MIN_FIT_LANDMARKS]  # (a sample with fewer is missing, not malformed)
    if not bool(torch.isfinite(used.sum(-1)).all()):  # the start's weighted centroid would be 0 / 0
        raise ValueError(f"the landmark weights of a sample sum beyond {dtype}'s range; scale them down")
    if used.numel() and bool((used.amax(-1) < torch.finfo(dtype).tiny).any()):  # subnormal: squares underflow
        raise ValueError(f"the landmark weights of a sample are all below {dtype}'s smallest normal number "
                         f"({torch.finfo(dtype).tiny:.3g}); scale them up")  # fmt: skip
    return target, w


#: A fit whose undamped Gauss-Newton step would still lower its objective by more than this fraction of the
#: objective (floored at that of a 1 px RMS landmark error) stopped short of a minimum (:func:`_stalled`).
_STALL_FRACTION: float = 1e-3

#: A :data:`~torchface.solver.least_squares.ResidualFn` whose ``valid`` is a tensor (never None): the landmark fit's.
_MaskedResidualFn = Callable[[Tensor], tuple[Tensor, Tensor, Tensor]]


def _stalled(
    residual_fn: _MaskedResidualFn, x: Tensor, lower: Tensor, upper: Tensor, prior: Tensor, weight_sum: Tensor
) -> Tensor:
    """``(B,)`` bool: the solve stopped away from a minimum of ``1/2 |r(x)|^2 + 1/2 sum_p prior_p x_p^2``.

    Levenberg-Marquardt damps each parameter by at least ``1e-6`` of the largest diagonal of its normal matrix;
    where the landmark terms weigh that little against the priors (equal weights of 1e-15 and less against the
    default shape prior), the pose's steps are swamped by the damping, become tiny, and meet the step tolerance as
    CONVERGED near the start's pose (at 1e-20, 11.7 and 21.6 degrees off). The criterion is scale-free: the decrease
    ``1/2 g^T H^-1 g`` that the undamped step (bound-held parameters fixed, as the solver holds them) predicts,
    against the objective floored at ``1/2 weight_sum`` (a 1 px RMS error), above :data:`_STALL_FRACTION`; converged
    fits predict 1e-6 of it or less (float32; about 1e-7 in float64). A sample whose system cannot be solved is not
    called stalled here.

    Args:
        x: ``(B, P)`` the solver's estimate; lower, upper, prior: ``(P,)`` or ``(B, P)`` its bounds and precisions
            (zero prior mean); weight_sum: ``(B,)`` the landmark weights' sums.
    """
    with torch.no_grad():
        return _predicts_decrease(residual_fn, x, lower, upper, prior, weight_sum)


def _predicts_decrease(
    residual_fn: _MaskedResidualFn, x: Tensor, lower: Tensor, upper: Tensor, prior: Tensor, weight_sum: Tensor
) -> Tensor:
    """:func:`_stalled`'s test (without autograd around it)."""
    r, J, valid = residual_fn(x)
    use = torch.isfinite(r) & torch.isfinite(J).all(-1)
    if valid is not None:  # ResidualFn may leave validity out (all valid), as the solver reads it
        use = use & valid
    r = torch.where(use, r, torch.zeros_like(r))
    J = torch.where(use.unsqueeze(-1), J, torch.zeros_like(J))
    g = torch.bmm(r.unsqueeze(1), J).squeeze(1) + prior * x
    held = ((x <= lower) & (g > 0)) | ((x >= upper) & (g < 0))  # the solver's projected Newton holds these
    J = torch.where(held.unsqueeze(1), torch.zeros_like(J), J)
    prior_held = torch.where(held, torch.ones_like(x), prior.expand_as(x))
    offset = torch.where(held, torch.zeros_like(x), x)
    delta, ok = solve_normal_equations(J, r, prior=prior_held, prior_offset=offset)
    decrease = -0.5 * (delta * torch.where(held, torch.zeros_like(g), g)).sum(-1)
    cost = 0.5 * (r.pow(2).sum(-1) + (prior * x * x).sum(-1))
    return ok & (decrease > _STALL_FRACTION * torch.maximum(cost, 0.5 * weight_sum))


#: Landmarks closer than this to their weighted centroid (RMS, pixels) hold no pose: a face seen as a point, whose
#: fit drifts to tens of kilometres away at any rotation. Such a sample is FAILED.
_MIN_SPREAD_PX: float = 1.0

#: A fit whose weighted RMS landmark error is at least this fraction of the landmarks' weighted RMS spread about
#: their centroid explains less than half their layout: FAILED. Mirrored landmarks (left and right swapped: a
#: wrong point order) that the solver cannot turn to a face seen from behind collapse to a far face, every point
#: near the centroid (0.94-1.0); fits of the model's landmarks stay below 0.42 even with 5 px of noise on a face
#: 17 px in spread, and below 0.07 at 2 px on one of 46 px.
_MAX_RMS_SPREAD: float = 0.7


#: :func:`rotation_std_deg`'s landmark noise: this fraction of the face's width in pixels (the model's landmarks'
#: horizontal extent on its mean shape seen frontally at the fitted depth), on each coordinate.
ROTATION_NOISE_FACE_FRACTION: float = 0.01


def rotation_std_deg(J_pose: Tensor, valid: Tensor, weights: Tensor, noise_px: Tensor) -> Tensor:
    """``(B,)`` the standard deviation in degrees of a rotation fitted to landmarks, in its least determined direction:
    the largest eigenvalue's square root of the axis-angle block of ``noise_px^2 (J^T J)^-1`` over the pose alone
    (the translation marginalised, the shape and expression taken as known), for landmarks of the largest weight
    with noise ``noise_px`` on each coordinate (a landmark of weight ``w`` has ``noise_px / sqrt(w / max w)``).

    The pose's Gauss-Newton information at the solution: its inverse is the covariance the landmark noise leaves in
    the rotation, so this is how well the landmarks' layout determines the rotation ("to +-X degrees"); it grows
    without bound as the layout degenerates (collinear points) and is ``inf`` where the pose is not determined at
    all. Computed in float64 from a Jacobi-scaled eigendecomposition (eigenvalues floored at 1e-12 of the largest:
    an undetermined direction gives a very large value); for tensors on an ``mps`` device, which has no float64
    (the fit solves there in the model's dtype, :func:`fit_landmarks`), on the CPU, the result handed back in
    float32.

    Args:
        J_pose: ``(B, N, 6)`` the weighted residuals' Jacobian with respect to the axis-angle and the translation.
        valid: ``(B, N)`` bool, the residuals that count.
        weights: ``(B, K)`` the landmark weights (``N = 2K``), whose largest is the reference.
        noise_px: ``(B,)`` the noise in pixels.
    """
    home, there = J_pose.device, _float64_device(J_pose.device)
    if there != home:  # (.double() on mps: "the MPS framework doesn't support float64", at every default fit)
        J_pose, valid, weights, noise_px = J_pose.to(there), valid.to(there), weights.to(there), noise_px.to(there)
    J = torch.where(valid.unsqueeze(-1) & torch.isfinite(J_pose), J_pose, torch.zeros_like(J_pose)).double()
    H = J.transpose(1, 2) @ J / weights.amax(-1).double().clamp_min(torch.finfo(torch.float64).tiny)[:, None, None]
    d = torch.diagonal(H, dim1=1, dim2=2)
    s = torch.where(d > 0, d.rsqrt(), torch.zeros_like(d))
    lam, V = torch.linalg.eigh(s.unsqueeze(-1) * H * s.unsqueeze(-2))  # ascending
    lam = lam.clamp_min(1e-12 * lam[:, -1:].clamp_min(torch.finfo(torch.float64).tiny))  # undetermined: 1e12 x
    Vr = V[:, :3] * s[:, :3].unsqueeze(-1)  # the axis-angle's rows of H^-1's eigenvectors
    cov = (Vr / lam.unsqueeze(1)) @ Vr.transpose(1, 2)  # (B, 3, 3) rad^2 per px^2
    std = torch.linalg.eigvalsh(cov)[:, -1].clamp_min(0).sqrt() * noise_px.double() * (180.0 / math.pi)
    std = torch.where((d[:, :3] > 0).all(-1), std, torch.full_like(std, math.inf))  # no information: inf
    return std if there == home else std.to(home, torch.float32)


@full_precision
def fit_landmarks(
    model: FaceModel,
    landmarks_px: Tensor,
    intrinsics: Intrinsics,
    weights: Tensor | None = None,
    *,
    landmark_indices: Tensor | None = None,
    config: FitConfig = FitConfig(),
) -> LandmarkFit:
    """Fit pose, shape (and optionally expression) to 2D landmarks by weighted least squares (Eq. 2).

    Solved in float64 whatever the model's dtype (on an ``mps`` device, which has no float64, in the model's dtype),
    the :class:`LandmarkFit` cast to the model's: the weak priors leave flat directions in which float32's rounding
    moved the fit by up to 2.6e-3 degrees, 1.7e-3 mm and 1e-3 in the coefficients, and a stream fitted in a batch
    came out that far from itself fitted alone (now equal to float32 rounding: to the bit on the CPU).

    The fit starts frontal, without roll, at the depth and place of the landmarks' spread and centroid; a sample
    that fails from there (below) is fitted again, in a batch of such samples, from a start turned about the optical
    axis by its landmarks' roll in the image (:func:`_image_roll`), and that fit is kept where it does not fail: a face
    upside down in the frame (roll 150-210 degrees) failed from the frontal start at 50-60 px RMS error. The samples
    that do not fail from the frontal start are fitted as before, to the bit.

    Args:
        model: the face model; its landmark table gives the 3D points.
        landmarks_px: ``(B, K, 2)`` pixel positions of the model's landmarks (all of them, or those listed in
            ``landmark_indices``). A NaN row marks a missing point; a row with an infinite coordinate, or with one
            coordinate NaN alone, is refused (:func:`check_landmark_values`).
        intrinsics: the camera.
        weights: ``(B, K)`` non-negative confidences ``w_k`` (0 = ignore), or None for all ones; NaN, infinite and
            negative ones are refused (:func:`check_landmark_values`). They multiply
            each landmark's squared pixel error against the priors, so their scale counts: 1 is what the priors
            (:class:`FitConfig`) are set for, and weights all halved make the priors count twice as much (2 px
            noisy landmarks on a 320x240 face: 0.03-0.08 degrees and 0.2-0.3 mm from the fit with ones; all 0.01:
            0.4-0.6 degrees and 3-4 mm).
        landmark_indices: ``(K,)`` int64 rows of the model's landmark table, or None for all.
        config: :class:`FitConfig`.

    Returns:
        :class:`LandmarkFit`. A sample is FAILED (its fields then hold the solver's last estimate, which means
        nothing) when the solver failed, when its landmarks spread less than a pixel about their centroid (all at
        one point: no pose to find), when the fit put a landmark of positive weight behind the camera, where
        its residual no longer counts (far-off landmarks, thousands of image widths out, can end so), or when it
        turned the face away from the camera (more than 90 degrees from facing it), where its landmarks could not
        be seen (the landmarks of a face seen from behind, or mirrored ones, can fit such a pose), or nearly so
        (more than :attr:`FitConfig.max_facing_deg`, 75: seen edge-on, as collinear landmarks were fitted), when
        its RMS error is at least 0.7 of the landmarks' RMS spread about their centroid (it explains less than half
        their layout: mirrored landmarks that did not turn the face away end so, collapsed to a far face), or when
        the solver stopped short of a minimum (weights so small against the priors, about 1e-15 or less with the
        default ones, that the solver's damping swamps the pose's steps: it stopped near the start's pose), or when
        the landmarks' layout does not determine the rotation (:attr:`FitConfig.max_rotation_std_deg`: e.g. the nose
        bridge alone, 4 nearly collinear points: from 2 px noisy landmarks 53-146 degrees off, some CONVERGED).
        Four landmarks suffice: the solver needs as many residuals as the parameters without a prior (the pose's
        six; the shape units and the expression have priors, unless given a precision of 0). A sample with fewer
        finite landmarks of positive weight (all NaN: no face found in its frame) is FAILED, at a placeholder
        estimate (:func:`_missing_fit`: frontal, centred on the principal point, a quarter of the frame wide,
        mean shape, ``rms_px`` 0); the others are fitted as they are alone (it raised a ValueError for the batch).
        Not differentiable: the solve runs without autograd, so no gradient reaches ``landmarks_px`` or
        ``weights`` (the fit's tensors do not require grad).
    """
    if not isinstance(model, FaceModel):  # None was an AttributeError ('NoneType' ... 'num_landmarks')
        raise TypeError(f"model must be a FaceModel, got {type(model).__name__}")
    if not isinstance(config, FitConfig):  # None was an AttributeError ('NoneType' ... 'fit_expression')
        raise TypeError(f"config must be a FitConfig, got {type(config).__name__}")
    check_model_landmarks(model)
    idx = torch.arange(model.num_landmarks, device=model.device) if landmark_indices is None else landmark_indices
    _check_landmark_indices(idx, model.num_landmarks)
    k = int(idx.numel())
    model_dtype, device = model.dtype, model.device
    check_intrinsics(intrinsics)  # None was an AttributeError ('NoneType' object has no attribute 'fx')
    target, w = _check_landmarks(landmarks_px, weights, k, model_dtype, device)
    enough = (w > 0).sum(-1) >= MIN_FIT_LANDMARKS
    if not bool(enough.all()):  # samples without landmarks (no face found): FAILED; the others fitted alone
        return _fit_with_missing(model, landmarks_px, intrinsics, weights, idx, config, enough)
    return _fit(model, target, w, idx, intrinsics, config)


def _fit(
    model: FaceModel, target: Tensor, w: Tensor, idx: Tensor, intrinsics: Intrinsics, config: FitConfig,
    roll: Tensor | None = None,
) -> LandmarkFit:
    """:func:`fit_landmarks` of checked landmarks (``(B, K, 2)`` ``target`` and ``(B, K)`` weights ``w``, from
    :func:`_check_landmarks`, every sample with enough of them) from a frontal start turned by ``roll`` ``(B,)``
    radians about the optical axis (clockwise in the image); None: no roll, and a FAILED sample is fitted again
    from its landmarks' roll (:func:`_image_roll`), the retry kept where it did not fail (a face upside down, roll
    150-210 degrees, failed from the frontal start at 50-60 px RMS error; the samples that did not fail are left
    as they are, to the bit)."""
    model_dtype, device = model.dtype, model.device
    k, B = int(idx.numel()), target.shape[0]
    checked_target, checked_w, checked_intrinsics = target, w, intrinsics
    # Solved in float64 (_fit_dtype; MPS: the model's dtype) and cast back at the end (see the docstring).
    dtype = _fit_dtype(model_dtype, device)
    target, w = target.to(dtype), w.to(dtype)
    intrinsics = _intrinsics_in(intrinsics, dtype)
    lv, lw = model.landmark_vertices[idx], model.landmark_weights[idx].to(dtype)
    mean_l = interpolate_landmarks(model.mean.to(dtype).unsqueeze(0), lv, lw)[0]  # (K, 3)
    shape_l = interpolate_landmarks(model.shape_units.to(dtype), lv, lw)  # (S, K, 3)
    anim_l = interpolate_landmarks(model.animation_units.to(dtype), lv, lw)  # (A, K, 3)
    S, A = shape_l.shape[0], anim_l.shape[0] if config.fit_expression else 0
    sqrt_w = w.sqrt().repeat_interleave(2, dim=1)  # (B, 2K)

    def residual_fn(x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        aa, t, sigma = x[:, :3], x[:, 3:6], x[:, 6 : 6 + S]
        pts = mean_l.unsqueeze(0) + torch.einsum("bs,skj->bkj", sigma, shape_l)
        if A:
            pts = pts + torch.einsum("ba,akj->bkj", x[:, 6 + S :], anim_l)
        R = axis_angle_to_matrix(aa)
        cam = torch.einsum("bij,bkj->bki", R, pts) + t.unsqueeze(1)
        uv = project_points(cam, intrinsics)
        d_aa, d_t = pose_projection_jacobian(aa, t, pts, intrinsics)  # (B, K, 2, 3)
        d_cam = project_points_jacobian(cam, intrinsics)  # (B, K, 2, 3)
        d_dir = torch.einsum("bkuj,bji->bkui", d_cam, R)  # d uv / d X_model (B, K, 2, 3)
        cols = [d_aa, d_t, torch.einsum("bkuj,skj->bkus", d_dir, shape_l)]
        if A:
            cols.append(torch.einsum("bkuj,akj->bkua", d_dir, anim_l))
        J = torch.cat(cols, dim=-1).reshape(B, 2 * k, 6 + S + A) * sqrt_w.unsqueeze(-1)
        r = (uv - target).reshape(B, 2 * k) * sqrt_w
        valid = (w > 0).repeat_interleave(2, dim=1) & (cam[..., 2] > 0).repeat_interleave(2, dim=1)
        return r, J, valid

    # Start: frontal, distance from the landmarks' spread, centred on their centroid.
    wk = w / w.sum(-1, keepdim=True)
    centroid = (target * wk.unsqueeze(-1)).sum(1)
    spread_px = ((target - centroid.unsqueeze(1)).pow(2).sum(-1) * wk).sum(-1).sqrt()
    model_c = (mean_l.unsqueeze(0) * wk.unsqueeze(-1)).sum(1)
    spread_mm = ((mean_l.unsqueeze(0)[..., :2] - model_c.unsqueeze(1)[..., :2]).pow(2).sum(-1) * wk).sum(-1).sqrt()
    z = intrinsics.fx * spread_mm / spread_px.clamp_min(1e-3)
    tx = (centroid[:, 0] - intrinsics.cx) * z / intrinsics.fx - model_c[:, 0]
    ty = (centroid[:, 1] - intrinsics.cy) * z / intrinsics.fy - model_c[:, 1]
    x0 = torch.zeros(B, 6 + S + A, dtype=dtype, device=device)
    x0[:, 3], x0[:, 4], x0[:, 5] = tx, ty, z - model_c[:, 2]
    if roll is not None:  # turned about the optical axis, the landmarks' centroid kept where it was
        x0[:, 2] = roll.to(dtype)
        turned = torch.einsum("bij,bj->bi", axis_angle_to_matrix(x0[:, :3]), model_c)
        x0[:, 3:6] = x0[:, 3:6] + model_c - turned

    inf = torch.full((6,), float("inf"), dtype=dtype, device=device)
    lower = [-inf, torch.full((S,), -config.shape_bound, dtype=dtype, device=device)]
    upper = [inf, torch.full((S,), config.shape_bound, dtype=dtype, device=device)]
    # The priors in the camera's squared pixels (FitConfig: given at its reference focal length).
    scale = prior_scale(config, intrinsics)
    prior = [torch.zeros(6, dtype=dtype, device=device),
             shape_precisions(config, model.shape_names, dtype, device) * scale]  # fmt: skip
    if A:
        lower.append(model.animation_ranges[:, 0].to(dtype))
        upper.append(model.animation_ranges[:, 1].to(dtype))
        prior.append(torch.full((A,), config.expression_prior_precision * scale, dtype=dtype, device=device))
    lower_all, upper_all = torch.cat(lower), torch.cat(upper)
    sparse = sparse_samples(config, (w > 0).sum(-1), S, model.num_animation)
    prior_all = _sparse_priors(torch.cat(prior), sparse, S, A, config, scale)  # (P,), or (B, P): sparse
    res = least_squares(
        residual_fn,
        x0,
        SolverConfig(max_iterations=config.max_iterations),
        lower=lower_all,
        upper=upper_all,
        prior_precision=prior_all,
        min_valid=_unregularised(prior_all),
    )
    x = res.params
    stalled = _stalled(residual_fn, x, lower_all, upper_all, prior_all, w.sum(-1))
    if config.refine_shape_prior_precision is not None and S > 0:
        hold = torch.ones(x.shape[1], dtype=torch.bool, device=device)
        hold[6 : 6 + S] = False
        lo2 = torch.where(hold, x, lower_all.expand_as(x))
        hi2 = torch.where(hold, x, upper_all.expand_as(x))
        prior2 = prior_all.clone()
        prior2[..., 6 : 6 + S] = config.refine_shape_prior_precision * scale
        prior2 = _sparse_priors(prior2, sparse, S, A, config, scale)  # a sparse sample's shape still held
        res2 = least_squares(
            residual_fn, x, SolverConfig(max_iterations=config.max_iterations), lower=lo2, upper=hi2,
            prior_precision=prior2, min_valid=_unregularised(torch.where(hold, 1.0, prior2)),  # (held: no unknowns)
        )
        failed2 = res2.failed | _stalled(residual_fn, res2.params, lo2, hi2, prior2, w.sum(-1))
        x = torch.where(failed2.unsqueeze(-1), x, res2.params)
    r, J, valid = residual_fn(x)
    # The floor only keeps a division by 0 away (never here: 4 positive weights): a floor of 1e-12 inflated small
    # weights' sums, and their RMS error came out in units of sqrt(weight), 0.004 px for a fit 1.4 px off at 1e-20.
    rms = (r.pow(2) * valid).sum(-1).div(w.sum(-1).clamp_min(torch.finfo(dtype).tiny)).sqrt()
    anim = x[:, 6 + S :] if A else torch.zeros(B, model.num_animation, dtype=dtype, device=device)
    # A landmark of positive weight behind the camera (not valid) was dropped from the fit, not fitted.
    dropped = ((w > 0).repeat_interleave(2, dim=1) & ~valid).any(1)
    # The face turned away from the camera (its forward axis, head -z, points away from the line of sight to the
    # landmarks' centroid): its landmarks would be hidden. A face's landmarks seen from behind fit it exactly so.
    R = axis_angle_to_matrix(x[:, :3])
    centre = torch.einsum("bij,bj->bi", R, model_c) + x[:, 3:6]
    away = (R[:, :, 2] * centre).sum(-1) <= 0
    if config.max_facing_deg is not None:  # nearly edge-on: how (nearly) collinear landmarks were explained
        cos = (R[:, :, 2] * centre).sum(-1) / centre.norm(dim=-1).clamp_min(torch.finfo(dtype).tiny)
        away = away | ~(cos >= math.cos(math.radians(config.max_facing_deg)))
    # A fit that explains less than half the landmarks' layout is no face's (mirrored landmarks collapse so).
    unexplained = rms >= _MAX_RMS_SPREAD * spread_px
    failed = (spread_px < _MIN_SPREAD_PX) | dropped | away | stalled | unexplained
    if config.max_rotation_std_deg is not None:  # a layout that does not determine the rotation (collinear points)
        z = x[:, 5]  # (a landmark behind the camera, as at z <= 0, is failed above)
        noise = ROTATION_NOISE_FACE_FRACTION * intrinsics.fx * _landmark_width_mm(model) / z
        noise = torch.where(z > 0, noise, torch.full_like(noise, math.inf))
        failed = failed | ~(rotation_std_deg(J[..., :6], valid, w, noise) <= config.max_rotation_std_deg)
    status = torch.where(failed, int(SolveStatus.FAILED), res.status)
    fit = LandmarkFit(R, x[:, :3], x[:, 3:6], x[:, 6 : 6 + S], anim, rms, status).to(dtype=model_dtype)
    again = failed & (spread_px >= _MIN_SPREAD_PX)  # (landmarks at one point have no roll either)
    if roll is not None or not bool(again.any()):
        return fit
    rows = again.nonzero().squeeze(-1)
    start = _image_roll(target[rows], w[rows], mean_l)
    retry = _fit(model, checked_target[rows], checked_w[rows], idx, checked_intrinsics, config, start)
    keep = retry.status != int(SolveStatus.FAILED)
    if not bool(keep.any()):
        return fit
    rows, retry = rows[keep], retry.select(keep)
    parts = []
    for name in LandmarkFit.__dataclass_fields__:
        v = getattr(fit, name).clone()
        v[rows] = getattr(retry, name)
        parts.append(v)
    return LandmarkFit(*parts)


def _image_roll(target: Tensor, w: Tensor, mean_l: Tensor) -> Tensor:
    """``(B,)`` radians: the rotation in the image (clockwise, about the optical axis) that best turns the model's
    frontal landmarks onto ``target`` (weighted 2D Procrustes about the weighted centroids: every landmark of positive
    weight counts, so missing points, the eyes' among them, need no fallback).

    Args:
        target: ``(B, K, 2)`` pixels; w: ``(B, K)`` weights (0: missing); mean_l: ``(K, 3)`` the model's landmarks (mm).
    """
    wk = w / w.sum(-1, keepdim=True)
    b = target - (target * wk.unsqueeze(-1)).sum(1, keepdim=True)
    a = mean_l[:, :2].unsqueeze(0)
    a = a - (a * wk.unsqueeze(-1)).sum(1, keepdim=True)
    cross = (wk * (a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])).sum(-1)
    dot = (wk * (a * b).sum(-1)).sum(-1)
    return torch.atan2(cross, dot)


def sparse_samples(config: FitConfig, count: Tensor, num_shape: int, num_animation: int) -> Tensor:
    """``(B,)`` bool: the samples :func:`fit_landmarks` fits with the sparse priors, those with fewer landmarks of
    positive weight than :attr:`FitConfig.sparse_landmark_count` (None: the fit's unknowns, ``6 + S``, ``+ A`` with
    ``fit_expression``). The look-ahead refinements hold a sparse start's units as the fit did
    (:func:`~torchface.tracker.lookahead.landmark_fit_priors`).

    Args:
        count: ``(B,)`` the samples' landmarks of positive weight (finite ones: :func:`landmark_targets`).
        num_shape, num_animation: the model's ``S`` and ``A`` (``A`` counted with ``fit_expression`` only).
    """
    unknowns = 6 + num_shape + (num_animation if config.fit_expression else 0)
    return count < (unknowns if config.sparse_landmark_count is None else config.sparse_landmark_count)


def _unregularised(prior: Tensor) -> int | Tensor:
    """The residuals a sample's solve needs (``min_valid``): as many as its parameters without a prior, ``prior``'s
    zeros (``(P,)``: an int; ``(B, P)``: per sample, a sparse sample's raised priors counted). The shape units' and
    the expression's priors determine theirs: 4 landmarks, 8 residuals, fit the pose (asking for ``P`` residuals
    failed every fit from fewer than 10 points). Counted on the dense priors, a 5-point sample with a precision set to
    0 by hand needed 16 residuals or more, had 10, and was FAILED, though its sparse priors held those units."""
    zeros = (prior == 0).sum(-1)
    return int(zeros) if prior.dim() == 1 else zeros


def _sparse_priors(prior: Tensor, sparse: Tensor, S: int, A: int, config: FitConfig, scale: float) -> Tensor:
    """The landmark fit's prior precisions, a sparse sample's (:func:`sparse_samples`) shape and expression ones raised
    to at least :attr:`FitConfig.sparse_shape_prior_precision` and :attr:`FitConfig.sparse_expression_prior_precision`
    (times ``scale``, :func:`prior_scale`). ``A``: the animation units fitted (0 without ``fit_expression``).

    Args:
        prior: ``(P,)`` or ``(B, P)`` the dense precisions, ``P = 6 + S + A`` (the pose's six first, 0).
        sparse: ``(B,)`` bool, the sparse samples.

    Returns:
        ``prior`` itself when no sample is sparse (the fit is then the dense one, to the bit), else ``(B, P)``.
    """
    if not bool(sparse.any()):
        return prior
    floor = torch.zeros_like(prior)
    floor[..., 6 : 6 + S] = config.sparse_shape_prior_precision * scale
    floor[..., 6 + S : 6 + S + A] = config.sparse_expression_prior_precision * scale
    return torch.where(sparse.unsqueeze(-1), torch.maximum(prior, floor), prior)


def _landmark_width_mm(model: FaceModel) -> float:
    """The horizontal extent (mm) of the model's landmarks on its mean shape (CANDIDE-3: 125 mm, the iBUG jaw's ends),
    computed once per model."""
    width = _LANDMARK_WIDTH.get(model)
    if width is None:
        lm = model.landmarks_3d(model.mean[None].detach())[0]
        width = _LANDMARK_WIDTH[model] = float(lm[:, 0].amax() - lm[:, 0].amin())
    return width


_LANDMARK_WIDTH: "weakref.WeakKeyDictionary[FaceModel, float]" = weakref.WeakKeyDictionary()


def _surface_width_mm(model: FaceModel) -> float:
    """The horizontal extent (mm) of the model's surface (the vertices its triangles use; all of them for a model
    without triangles) on its mean shape, computed once per model."""
    width = _SURFACE_WIDTH.get(model)
    if width is None:
        x, used = model.mean.detach()[:, 0], model.surface_vertex_mask
        x = x[used] if bool(used.any()) else x
        width = _SURFACE_WIDTH[model] = float(x.amax() - x.amin())
    return width


_SURFACE_WIDTH: "weakref.WeakKeyDictionary[FaceModel, float]" = weakref.WeakKeyDictionary()


def _fit_dtype(model_dtype: torch.dtype, device: torch.device) -> torch.dtype:
    """The dtype :func:`fit_landmarks` solves in: float64, except on Apple's MPS devices, which have no float64
    (there the model's dtype, as before: a float32 fit, precise to about 1e-3 in its weakly held coefficients)."""
    return model_dtype if torch.device(device).type == "mps" else torch.float64


def _float64_device(device: torch.device) -> torch.device:
    """Where float64 work on ``device``'s tensors runs (:func:`rotation_std_deg`): there, except on Apple's MPS
    devices, which have no float64 (:func:`_fit_dtype`): on the CPU."""
    return torch.device("cpu") if torch.device(device).type == "mps" else torch.device(device)


def _intrinsics_in(intrinsics: Intrinsics, dtype: torch.dtype) -> Intrinsics:
    """``intrinsics`` with its tensor entries (a focal length that carries a gradient) in ``dtype``; numbers as
    they are."""
    fields = ("fx", "fy", "cx", "cy")
    if not any(isinstance(getattr(intrinsics, f), Tensor) for f in fields):
        return intrinsics
    return replace(intrinsics, **{f: getattr(intrinsics, f).to(dtype) for f in fields
                                  if isinstance(getattr(intrinsics, f), Tensor)})  # fmt: skip


def _missing_fit(model: FaceModel, intrinsics: Intrinsics, count: int) -> LandmarkFit:
    """The FAILED fit of ``count`` samples without landmarks: a placeholder, finite, estimate (it means nothing):
    frontal, the model's landmark centroid on the optical axis at the depth where its mean face (the extent of its
    landmarks) is a quarter of the frame wide, mean shape and neutral expression, ``rms_px`` 0."""
    dtype, device = model.dtype, model.device
    mean_l = model.landmarks_3d(model.mean[None].detach())[0]  # (K, 3)
    centre = mean_l.mean(0)
    z = intrinsics.fx * _landmark_width_mm(model) / (intrinsics.width / 4.0)
    t = torch.stack([-centre[0], -centre[1], z - centre[2]]).to(dtype=dtype, device=device)
    eye = torch.eye(3, dtype=dtype, device=device)
    zeros = torch.zeros(count, dtype=dtype, device=device)
    return LandmarkFit(
        eye.expand(count, 3, 3).clone(), torch.zeros(count, 3, dtype=dtype, device=device), t.expand(count, 3).clone(),
        torch.zeros(count, model.num_shape, dtype=dtype, device=device),
        torch.zeros(count, model.num_animation, dtype=dtype, device=device), zeros,
        torch.full((count,), int(SolveStatus.FAILED), dtype=torch.int64, device=device),
    )  # fmt: skip


def _fit_with_missing(
    model: FaceModel, landmarks_px: Tensor, intrinsics: Intrinsics, weights: Tensor | None, idx: Tensor,
    config: FitConfig, enough: Tensor,
) -> LandmarkFit:
    """:func:`fit_landmarks` of a batch where the samples not ``enough`` ``(B,)`` lack the landmarks a fit needs:
    the others fitted as a batch of their own (as they are alone), these :func:`_missing_fit`."""
    enough = enough.to(landmarks_px.device)
    fit = _missing_fit(model, intrinsics, int(enough.shape[0]))
    if not bool(enough.any()):
        return fit
    some = fit_landmarks(model, landmarks_px[enough], intrinsics,
                         None if weights is None else weights[enough.to(weights.device)],
                         landmark_indices=idx, config=config)  # fmt: skip
    rows = enough.nonzero().squeeze(-1).to(model.device)
    parts = []
    for name in LandmarkFit.__dataclass_fields__:
        x = getattr(fit, name)
        x[rows] = getattr(some, name).to(x.dtype)
        parts.append(x)
    return LandmarkFit(*parts)
