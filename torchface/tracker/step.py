"""One tracking step as a function of (state, frames) -> (new state, result) (paper Sections 2-4).

Initialisation fits pose and shape to fiducial points (Eq. 2) and builds a template per pyramid level from
the first frame (Eq. 3-9). Each later frame is one joint minimisation over pose, animation units and
illumination (Eq. 20), coarse to fine over an image pyramid, with self-occlusion (back-facing and z-buffer)
and external occlusion (IRLS robust weights) handled per point.
"""

from __future__ import annotations

import ctypes
import enum
import functools
import math
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, cast

import torch
from torch import Tensor

from torchface import _native
from torchface._autocast import full_precision
from torchface._compiling import check_reverse_mode
from torchface._device import check_holds_data, tensor_mover
from torchface._frame_values import FRAME_VALUE_RANGE, STEP_VALUE_ROW_STRIDE, check_frame_values
from torchface._scalar import scalar
from torchface.appearance.illumination import ILLUMINATION_TERM_NAMES, NUM_ILLUMINATION_TERMS, illumination_basis
from torchface.appearance.sampling import image_with_gradients, pyr_down, sample_at_pixels, to_gray
from torchface.backend import Backend, use_native
from torchface.conventions import (
    MEDIAPIPE_MESH_HINT, MEDIAPIPE_MESH_POINT_COUNTS, NEAR_PLANE_MM, other_landmark_set_hint,
)
from torchface.geometry._checks import (
    check_bool, check_choice, check_int, check_intrinsics, check_ints, check_number, check_reals,
)
from torchface.geometry.camera import Intrinsics, MixedUpIntrinsics, mixed_up_intrinsics
from torchface.geometry.projection import project_points
from torchface.geometry.so3 import axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_euler
from torchface.model.face_model import FaceModel
from torchface.rendering.rasterizer import _cover, rasterize_coverage
from torchface.rendering.visibility import points_visible
from torchface.solver.least_squares import SolveResult, SolverConfig, SolveStatus, least_squares
from torchface.solver.robust import RobustKind, RobustLoss, SwitchedRobustLoss, robust_scale
from torchface.template.management import TemplateConfig
from torchface.template.points import Template, _of_dtype, build_template
from torchface.tracker.fast import FUNCTION_TOLERANCE, STEP_TOLERANCE, LevelCamera, robust_scale_of, solve_level
from torchface.tracker.fit import (
    MAX_UNIT_PRECISION, MIN_FIT_LANDMARKS, FitConfig, LandmarkFit, _landmark_width_mm, check_landmark_type,
    check_landmark_values, check_model_landmarks, check_pixel_landmarks, check_unit_precision, check_weights_shape,
    fit_landmarks, landmark_targets, normalised_streams, widen_half_landmarks,
)
from torchface.tracker.inference import without_autograd
from torchface.tracker.objective import frame_residuals, warp_points
from torchface.tracker.params import ParamLayout

if TYPE_CHECKING:
    from torchface.tracker.managed import ManagementState


class TrackSolver(enum.Enum):
    """Which per-frame solver :func:`track_step` uses."""

    #: Gauss-Newton on a local twist over a face crop (:mod:`torchface.tracker.fast`); the default.
    FAST = "fast"
    #: The generic Levenberg-Marquardt (:func:`torchface.solver.least_squares`) on the full frame with
    #: additive axis-angle parameters (:func:`~torchface.tracker.objective.frame_residuals`): slow, a reference.
    #: It runs the pyramid levels only, not the expression refinement pass (``refine_iterations``), so it
    #: matches the fast solver with ``refine_iterations=0``.
    REFERENCE = "reference"


class TrackStatus(enum.IntEnum):
    """Per-sample outcome of a step."""

    #: The minimisation converged.
    CONVERGED = 0
    #: It ran out of iterations; the estimate is usable.
    MAX_ITERATIONS = 1
    #: No usable estimate (too few points, no contrast, non-finite data); the previous one is kept.
    FAILED = 2
    #: The stream is lost (template management, :func:`torchface.tracker.managed.managed_step`): its
    #: confidence stayed low or the face left the frame, and no recovery has succeeded yet.
    LOST = 3


class StartFailure(enum.IntEnum):
    """Why a stream's start failed: :attr:`TrackResult.start_failure`, one code per stream, of a start
    (:func:`initialise`, :func:`~torchface.tracker.managed.initialise_managed`, ``FaceTracker.initialise``) or of a
    detector's restart in :func:`~torchface.tracker.managed.managed_step`. The stream's status says that it failed
    (:class:`TrackStatus` FAILED at a start; a failed restart leaves it LOST); this says why, and
    :attr:`TrackResult.start_failure_reasons` (or a code's :attr:`reason`) in words. Where several apply, the first
    in this order is given, but NORMALISED_LANDMARKS comes before NO_LANDMARKS: a detector's restart takes a stream's
    normalised landmarks as no face found (NaN rows, with a warning), so there such a stream has both, and the
    useful one is that its landmarks are normalised; at a start the two never meet (normalised landmarks are at
    least :data:`~torchface.tracker.fit.MIN_FIT_LANDMARKS`, and NO_LANDMARKS means fewer); and OUTSIDE_FRAME comes
    before NO_POSE and FACE_TOO_SMALL where the landmarks lie mostly outside the frame (its comment)."""

    #: The stream started (or no start was tried for it).
    NONE = 0
    #: Fewer than :data:`~torchface.tracker.fit.MIN_FIT_LANDMARKS` (4) finite landmarks of positive weight: no face
    #: found in its frame (NaN rows; a detector's answer with fewer than half its landmarks).
    NO_LANDMARKS = 1
    #: Landmarks in normalised image coordinates (x / W, y / H in [0, 1], MediaPipe's) beside streams in pixels
    #: (:func:`~torchface.tracker.fit.normalised_streams`): a face about a pixel wide, which no fit holds.
    NORMALISED_LANDMARKS = 2
    #: The landmark fit holds no pose (:func:`~torchface.tracker.fit.fit_landmarks`: landmarks within a pixel of one
    #: point, a fit turned away from the camera or nearly edge-on, behind it, mirrored landmarks, a stalled fit, a
    #: layout that does not determine the rotation).
    NO_POSE = 3
    #: The fitted face is narrower than :attr:`TrackerConfig.min_face_width_px`.
    FACE_TOO_SMALL = 4
    #: Template management: less than :attr:`~torchface.template.management.TemplateConfig.min_inside_fraction` of
    #: the fitted face's vertices inside the frame (landmarks that put the face mostly outside it; without template
    #: management such a face fails only for want of template points, TOO_FEW_POINTS). Also a start that failed for
    #: a later reason (NO_POSE, FACE_TOO_SMALL, ...) from landmarks less than that fraction of which lie inside the
    #: frame (:func:`~torchface.tracker.fit.landmarks_inside_fraction`; landmarks 1000 px off a 160x120 frame: the
    #: fit said NO_POSE or FACE_TOO_SMALL), whatever this order says.
    OUTSIDE_FRAME = 5
    #: Fewer than :attr:`TrackerConfig.min_points` template points in its first frame: no texture where the face
    #: is (a black or flat frame, NaN pixels).
    TOO_FEW_POINTS = 6
    #: Template management: the first normalised face shows too few of its own fiducial patches to score any frame
    #: (a face fitted nearly edge-on).
    NO_PATCHES = 7

    @property
    def reason(self) -> str | None:
        """The code in words (None for :attr:`NONE`).

        Example:
            >>> StartFailure.NO_LANDMARKS.reason
            'no face: too few finite landmarks of positive weight'
        """
        return _START_FAILURE_REASONS[self]


_START_FAILURE_REASONS: dict[StartFailure, str | None] = {
    StartFailure.NONE: None,
    StartFailure.NO_LANDMARKS: "no face: too few finite landmarks of positive weight",
    StartFailure.NORMALISED_LANDMARKS: "landmarks in normalised [0, 1] coordinates, not pixels (x * W, y * H "
                                       "makes pixels of them)",
    StartFailure.NO_POSE: "the landmark fit holds no pose (landmarks at one point: a 'no face' is NaN rows, not "
                          "zeros; collinear, mirrored or seen from behind: a fit turned away, edge-on or behind "
                          "the camera; landmarks are (x, y) pixels, (row, col) ones give a mirrored face: "
                          "landmarks.flip(-1); a flipped frame's: torchface.io.mirror_landmarks)",
    StartFailure.FACE_TOO_SMALL: "the face is narrower than TrackerConfig.min_face_width_px",
    StartFailure.OUTSIDE_FRAME: "the fitted face, or its landmarks, lie mostly outside the frame "
                                "(TemplateConfig.min_inside_fraction)",
    StartFailure.TOO_FEW_POINTS: "too few template points: no texture where the face is (a black or flat frame, NaN "
                                 "pixels)",
    StartFailure.NO_PATCHES: "the first normalised face shows too few fiducial patches to score any frame",
}  # fmt: skip


def start_failure_codes(causes: Sequence[tuple[StartFailure, Tensor]]) -> Tensor:
    """``(B,)`` int64 :class:`StartFailure` codes of ``(code, failed)`` pairs in order of precedence, each ``failed``
    ``(B,)`` bool (at least one pair): a stream takes the first code whose ``failed`` holds, :attr:`StartFailure.NONE`
    where none does.

    Example:
        >>> start_failure_codes([(StartFailure.NO_POSE, torch.tensor([True, False, False])),
        ...                      (StartFailure.FACE_TOO_SMALL, torch.tensor([True, True, False]))]).tolist()
        [3, 4, 0]
    """
    out = torch.zeros(causes[0][1].shape, dtype=torch.int64, device=causes[0][1].device)
    for code, failed in reversed(causes):
        out = torch.where(failed.to(out.device), int(code), out)
    return out


def usable_status(status: Tensor) -> Tensor:
    """``(*)`` bool of ``status (*)`` integer :class:`TrackStatus`: the estimate is usable, neither FAILED nor LOST
    (:attr:`TrackResult.success`)."""
    return (status != int(TrackStatus.FAILED)) & (status != int(TrackStatus.LOST))


#: The largest :attr:`TrackerConfig.selection_seed` (torch's generators take seeds below 2**64; the pixel keys' seed
#: adds the frame size to it).
MAX_SELECTION_SEED: int = 2**63 - 1

# (MAX_UNIT_PRECISION, the strongest prior an animation unit may be given, is torchface.tracker.fit's, which
# FitConfig's expression priors share: imported above, torchface.tracker.step.MAX_UNIT_PRECISION as before)

#: The range of :attr:`TrackerConfig.expression_sparsity`: above it the prior is the Gaussian one (``None``) for any
#: unit within 1e6 of its centre (1e39 overflowed float32: a ``RuntimeError`` at the first step); below it every
#: active unit's prior is gone already (1e-12 and 1e-30 tracked alike), and under about 1e-45 float32 holds 0 (the
#: streams LOST).
SPARSITY_RANGE = (1e-12, 1e6)

_STRONG_PRIOR = (
    "a unit's prior precision (expression_prior_precision or refine_prior_precision times its "
    "expression_prior_weights factor) is at most 1e6: at 1e6 a unit is held as firmly as use_expression=False holds "
    "it, and from about 1e12 the float32 solver stops following the pose (the first frame's reported at every frame)"
)


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of the tracker.

    Attributes:
        num_levels: pyramid levels (1 = full resolution only); coarse to fine.
        max_points: template points per level per stream (fewer where a level has fewer pixels). Fewer points
            at the coarse levels were measured to lose expression accuracy (jaw drop RMSE 0.04 -> 0.12).
        gradient_threshold: minimum gray-level gradient magnitude (per pixel, in [0, 1] units) of a template
            point (Section 4: informative points); 0 keeps all pixels.
        iterations: Levenberg-Marquardt iterations per level, coarse to fine. Measured on the 640x480 scenarios:
            (6, 5, 4) matches (8, 6, 4) within 0.01 deg of mean error (occlusion's max 6.0 -> 6.4 deg) for 3 fewer
            linearisations per frame; (5, 4, 3), with the coarse levels' final check dropped, costs occlusion
            0.66 -> 0.86 deg mean (and dropping that check alone fails the sudden-occlusion test).
        function_tolerance: a pass also stops when its step's predicted cost decrease is below this fraction of
            the cost (:func:`~torchface.tracker.fast.solve_level`; the coarser levels at ``2**level`` times it, as
            their step tolerance; 0: off). Measured on the 640x480 scenarios (evaluate.py), 3e-3 ends the passes
            after 3.1 instead of 4.0 linearisations on average with every mean error within 0.02 degree (occlusion's
            worst frame 5.1 -> 4.4 degrees), and one stream's step took 21.7 instead of 27.0 ms with the change of
            :mod:`~torchface.tracker.fast`'s rotation increment (same process, benchmark.py's frames). A looser 1e-2
            (one value at every level, measured before that change) took 2.9 linearisations per pass but moved
            scan_motion's mean from 1.89 to 1.99 degrees. With many streams the batch iterates while any stream
            does, so the saving is at small B (32 streams: 12.3 -> 12.1 ms per stream-frame).
        use_illumination: estimate the illumination terms (else held at zero: the ablation).
        use_expression: estimate the animation units (else held at the initial values: the ablation).
        robust: the robust loss for external occlusion (``RobustKind.NONE`` is the ablation).
        robust_c: its tuning constant (in robust-scale units); None: the loss's default
            (:class:`~torchface.solver.robust.RobustLoss`).
        robust_scale_floor: lower bound of the robust scale (gray levels in [0, 1]) at the coarsest and at the
            finest level (geometric in between).
            On clean frames the residual scale is tiny, and an expression change would be rejected as an
            outlier; a high floor at the coarse levels lets expression and light pull the estimate first, and
            the low floor at the fine levels then rejects what no parameter explains (external occlusion): a
            graduated non-convexity schedule.
        zbuffer_visibility: test template points against the z-buffer of the previous estimate (fast solver:
            at the coarsest level at least 16 pixels a side, :func:`visibility_level`; reference solver: at
            level 1).
        visibility_interval: the fast solver re-rasterizes that z-buffer every this many frames and reuses
            the masks in between (back-facing points are still dropped every iteration).
        expression_prior_precision: precision (per squared unit) of the Gaussian prior on the animation units.
            In [0, 1e6], and so is each unit's (times its ``expression_prior_weights`` factor;
            ``refine_prior_precision`` alike): at 1e6 a unit is held as firmly as ``use_expression=False`` holds
            it, and much stronger priors stop the float32 solver following the pose (:data:`MAX_UNIT_PRECISION`).
        expression_prior_weights: one factor per animation unit (the model's order), each in [0, 1e6], on that
            precision and on ``refine_prior_precision``: units the image can hardly tell apart can be weighted so
            that their shared motion goes to one of them (CANDIDE-3's Lid tightener and Upper lid raiser move the
            eyelid vertices nearly as Eyes closed does; docs/limitations.md). None: 1 for every unit. Refused with
            ``use_expression=False`` (no unit is solved for).
        expression_sparsity: ``delta`` > 0 turns that Gaussian prior into a reweighted L1 (Laplace) prior,
            which prefers few active units: before each pass, unit ``j``'s precision is multiplied by
            ``delta / max(|alpha_j - mu_j|, delta)`` (``alpha``: the estimate the pass starts from, i.e. the
            previous frame's for the pyramid levels and the levels' result for the refinement pass; ``mu``:
            the prior's centre). A unit at rest keeps the full precision; an active one is shrunk less, in
            proportion to its size. Units whose motions are nearly the same then settle on one of them, where
            a Gaussian prior spreads the motion over all of them (its minimum-norm split). Template management's
            lost streams and recovery candidates keep the Gaussian prior (``track_step(conservative=)``): a unit
            pushed by an occluder would otherwise lose its prior and roam (on the CANDIDE-3 long run a recovery
            after the first occluder took 27 frames instead of 2). None: Gaussian; else in [1e-12, 1e6]
            (:data:`SPARSITY_RANGE`: above it the prior is the Gaussian one already). Measured with 0.1 on the
            640x480 ``expressions`` scenario (landmark-noise seed 0, against None): rotation error 0.56 -> 0.42
            degrees mean, AU RMSE jaw drop 0.036 -> 0.007, lip stretcher 0.047 -> 0.007, brow lowerer 0.025 ->
            0.011, outer brow raiser 0.023 -> 0.012 (seeds 1 and 2 alike); eyes closed is not helped (0.231).
        expression_range_from_start: each animation unit's range (``model.animation_ranges``) bounds the expression
            measured from the first frame's fitted coefficients (:attr:`TrackResult.expression`, ``anim_coeffs -``
            :attr:`TrackerState.anim_prior_mean`) rather than the coefficients themselves, so that the whole range is
            left to the readout whatever the first fit holds (:func:`animation_bounds`). On a real face that fit
            absorbs shape CANDIDE-3's shape units cannot and can end at a bound (on the 11 GRID clips' dlib landmarks
            11 units on 7 clips: Upper lip raiser -0.5, Upper lid raiser 1, Lip presser -1, Lip stretcher 1), where
            the coefficients' bounds stopped that unit's expression for the whole video: tracked, a unit sat at such
            a bound in 427 of the clips' 825 frames x 11 units, its readout clipped; from the first fit, 44 (the
            expression at the ends of its range), the coefficients going up to 0.47 past the model's ranges.
            Measured on the rendered scenarios (``evaluate.py --scenarios standard --noise-seeds 0,1,2,3``): within
            their draw-to-draw spread (docs/limitations.md, "Expression units at their bounds from the first
            frame"). False: the coefficients in the ranges (before session 57).
        expression_prior_at_start: centre that prior on the first frame's fitted expression
            (:attr:`TrackerState.anim_prior_mean`) rather than on zero. On a face unlike CANDIDE-3 the fitted
            expression carries shape the shape units cannot, and a prior pulling it to zero tilts the pose:
            measured on the James scan's long run, a fresh tracker's error at the returns to frontal (frames
            405, 2700, 215, 970) went from 2.32/2.73/1.14/1.38 to 1.57/1.48/0.56/0.90 degrees.
        min_points: fewer valid points than this marks a sample FAILED.
        min_contrast: a sample whose sampled frame intensities have a standard deviation below this is FAILED
            (black or textureless frame).
        min_face_width_px: a face narrower than this (pixels of the full-resolution frame; :func:`face_width_px`,
            the model's frontal face's width at the estimate's depth) gets confidence 0 at each step, and
            :func:`initialise` fails its stream: its estimates are too coarse to use. Measured with the test off
            on ten rendered CANDIDE-3 clips of 30 frames per width at 320x240 (exact first-frame landmarks, head
            turning out to 15 degrees each way; ``python scripts/doc_figures.py face-width``): rotation error
            2.8 / 5.8 degrees (mean / max) at 27 px wide, 3.3 / 5.9 at 23.5 px, 3.5 / 7.5 at 20 px, 5.4 / 14.3 at
            18 px, 6.8 / 39 at 16 px (2 of the 10 clips ran off), and at 13 px 7 of the 10 ran off (errors up to
            110 degrees); the confidence stayed high as the error grew (median 0.77 at 18 px, 0.69 at 16 px).
            0 turns the test off. The standard scenarios' faces are
            about 180 px wide at 640x480 (45 px at 160x120).
        refine_iterations: after the pose is found, iterations of a second pass at the finest level that
            re-estimates only the animation units and the light with the robust scale floored at
            ``refine_scale_floor`` (0 disables it). Expression change is a large, structured residual that a
            tight robust scale rejects as an outlier; with the pose held, a loose scale lets the expression
            follow while an occluder cannot drag the pose.
        refine_scale_floor: the robust scale floor of that pass.
        refine_prior_precision: the animation units' prior precision in that pass (None: the same as
            ``expression_prior_precision``; in [0, 1e6] as it). The pose is held there, so a weak prior lets the
            expression follow without tilting the pose; measured on the 640x480 ``expressions`` scenario, 0.1 took the
            lip stretcher from 0.081 / 0.88 (RMSE fraction of range / r) to 0.045 / 0.97 and the brow lowerer from 0.041
            / 0.97 to 0.034 / 1.00; the mean rotation errors moved by at most 0.01 degree (maxima: expressions 1.16 ->
            1.27, scan_motion 5.87 -> 5.94 degrees). At first it broke recovery on the 3000-frame long runs
            (evaluate.py): after the face left the frame the CANDIDE-3 run never recovered, because a lost track with
            this weak prior fitted a pose 74 degrees wrong well enough to pass ``recover_confidence``; on the James scan
            a lost track ran to 83 degrees of yaw and 6.5 m and scored 0.58 on 1 of its reference's patches. Template
            management now solves recovery candidates and lost streams with ``expression_prior_precision`` here
            (``track_step(conservative=)``), and a lost stream goes on from a recovery candidate that beats the
            continued track, scores at least ``adopt_min_confidence`` and lies more than ``adopt_min_angle_deg`` from
            it. With those, and 0.1 as the default, every loss on both long runs is recovered within 12 frames of the
            face being in view again (CANDIDE-3 returns max 0.61 degree; James 1.54, as with None); the pooled
            confidence AUROC is 0.975.
        expression_priority: template points that an animation unit moves are picked first when positive
            (:func:`~torchface.template.points.build_template`). Off by default: measured with 1.0 on the
            640x480 scenarios it improves the AUs (lip stretcher RMSE 0.080 -> 0.063 of range, r 0.90 -> 0.95)
            but costs pose accuracy (pose_sweep mean 0.49 -> 0.63 deg, scan_motion 1.93 -> 2.66 deg).
        expression_quota: per animation unit, this fraction of the finest level's template points is reserved
            for points that the unit moves (``int(expression_quota * points)``, passed to
            :func:`~torchface.template.points.build_template`; 0: off), in the templates built at initialisation
            (and at a re-anchoring or a detector's re-initialisation). The coarser levels, which serve the pose,
            and the mosaic's entries select without it (in the entries it took management's overhead from 24-26%
            to 37-56%, benchmark.py --management-only). The uniform draw gives the eyelid unit about 7 of 1500
            points. Measured with 0.027 (40 of 1500) on the 640x480 ``expressions`` scenario: eyes closed RMSE
            0.231 -> 0.152 and r 0.45 -> 0.83 (landmark-noise draw 0; r -0.03 -> 0.67 and -0.12 -> 0.48 on
            draws 1 and 2), the other units and the five standard scenarios' rotation errors within their
            draw-to-draw spread (scan_motion 0.91 -> 0.88 degrees mean), the long runs' targets held (returns
            max 0.65 and 0.82 degrees, every loss recovered within 17 frames). Off by default: eyes closed still
            misses its targets, and the native and torch confidence paths then part on one borderline frame of
            tests/tracker/test_native.py's sweep (dissimilarity 1.34 against 1.07 on a badly tracked stream).
        fit: settings of the initial fit to landmarks. The default also fits a starting expression (weak
            prior): on a face unlike CANDIDE-3 (the James scan) the animation units absorb shape the shape units
            cannot, which lowered scan_motion's mean error from 2.7 to 1.9 degrees.
        solver: :class:`TrackSolver`.
        backend: which implementation runs the hot loops (:class:`~torchface.backend.Backend`): the fast solver's
            level solves, the rasterizer's coverage, template building, the normalised face, the dissimilarity
            confidence and template management's per-frame decisions. By default the native kernels (C compiled
            at first use, :mod:`torchface._native`) where they can run (CPU, no gradient asked for, a C compiler
            on the machine), else the torch code. The two agree to rounding (the same template points and
            management decisions); measured on benchmark.py's frames, one stream's bare step took 3.2-3.9 instead
            of about 8.5 ms per frame.
        crop_margin: the fast solver tracks inside a crop around the previous estimate's face box, enlarged
            by this fraction of the box size on each side (plus 32 pixels).
        selection_seed: which draw of the pixels' selection keys picks each template's ``max_points`` among its
            candidate pixels (the first frame's and the mosaic entries'; a function of the pixel, so batches
            and single streams agree). 0 is the default draw; any other seed draws another, equally uniform
            subset; seeds lie in ``[0, 2**63 - 1]`` (:data:`MAX_SELECTION_SEED`).
            The figures of a turn on a face unlike the model move with the draw (docs/limitations.md: ``scan_motion``'s max error 4.85, 5.49 and 5.35 degrees with seeds 0, 1 and 2), which
            ``scripts/evaluate.py --selection-seeds`` measures.
        template: template management (:class:`~torchface.template.management.TemplateConfig`): dissimilarity
            confidence, gating, the pose-keyed mosaic, loss and recovery; used by
            :func:`torchface.tracker.managed.managed_step` (:func:`track_step` alone ignores it).
        motion_prediction: ``k`` in [0, 1]: each frame's solve starts from a constant-velocity prediction of the
            pose instead of the previous frame's estimate: rotation ``(R_t R_{t-1}^T)^k R_t``, translation
            ``t_t + k (t_t - t_{t-1})`` (expression and light start where they were). Applied per stream only where
            the previous two frames were both confident with no loss, recovery, re-anchoring or restart between
            them (:func:`torchface.tracker.managed.managed_step`; it needs template management, whose confidence
            decides that). 0 (the default): off, the previous frame's estimate as before; 1: full constant
            velocity; between them damped. A predicted solve that scores below the very-low confidence (the head
            stopped or turned back) is solved again from the previous frame's estimate. It widens the motion per
            frame the solve captures (docs/limitations.md, "Fast motion").
    """

    num_levels: int = 3
    max_points: int = 1500
    gradient_threshold: float = 0.01
    iterations: tuple[int, ...] = (6, 5, 4)
    function_tolerance: float = FUNCTION_TOLERANCE
    use_illumination: bool = True
    use_expression: bool = True
    robust: RobustKind = RobustKind.TUKEY
    robust_c: float | None = 4.685
    robust_scale_floor: tuple[float, float] = (0.1, 0.02)
    refine_iterations: int = 3
    refine_scale_floor: float = 0.1
    refine_prior_precision: float | None = 0.1
    expression_priority: float = 0.0
    expression_quota: float = 0.0
    zbuffer_visibility: bool = True
    visibility_interval: int = 1
    expression_prior_precision: float = 1.0
    expression_prior_weights: tuple[float, ...] | None = None
    expression_sparsity: float | None = 0.1
    expression_prior_at_start: bool = True
    expression_range_from_start: bool = True
    min_points: int = 50
    min_contrast: float = 0.01
    min_face_width_px: float = 20.0
    fit: FitConfig = field(default_factory=lambda: FitConfig(fit_expression=True, expression_prior_precision=2.0))
    solver: TrackSolver = TrackSolver.FAST
    backend: Backend = Backend.AUTO
    crop_margin: float = 0.25
    selection_seed: int = 0
    template: TemplateConfig = field(default_factory=TemplateConfig)
    motion_prediction: float = 0.0

    def __post_init__(self) -> None:
        # Settings read only at the first frame or deep in a step were refused there with another name, or not at
        # all: fit=None or template=None an AttributeError at initialise, num_levels=2.0 a TypeError from range(),
        # gradient_threshold or refine_scale_floor NaN failed or lost every frame without a word.
        if not isinstance(self.fit, FitConfig):
            raise TypeError(f"fit must be a FitConfig, got {type(self.fit).__name__}")
        if not isinstance(self.template, TemplateConfig):
            # (template=None or False, to track without template management, was told the type alone)
            off = (" (template management off: template=TemplateConfig(enabled=False), TemplateConfig from "
                   "torchface.tracker)" if self.template is None or self.template is False else "")  # fmt: skip
            raise TypeError(f"template must be a TemplateConfig, got {type(self.template).__name__}{off}")
        for name in ("use_illumination", "use_expression", "zbuffer_visibility", "expression_prior_at_start",
                     "expression_range_from_start"):
            object.__setattr__(self, name, check_bool(getattr(self, name), name))  # "no" was true
        for name, low in (("num_levels", 1), ("max_points", 8), ("min_points", 0), ("refine_iterations", 0),
                          ("visibility_interval", 1), ("selection_seed", 0)):  # fmt: skip
            object.__setattr__(self, name, check_int(getattr(self, name), name, low))
        if self.selection_seed > MAX_SELECTION_SEED:  # (2**64 was taken, then torch's "Overflow when unpacking long
            # long" at the first frame's template)
            raise ValueError(f"selection_seed must be an integer in [0, 2**63 - 1], got {self.selection_seed}")
        object.__setattr__(self, "iterations", check_ints(self.iterations, "iterations"))  # 6.5 was taken here
        # Each number's range, stated once (check_number: a wrong type a TypeError naming it, "0.2" included; NaN or
        # an infinite value a ValueError: inf passed ">= 0" as a tolerance, a precision or a margin).
        for name, interval, optional in (
            ("gradient_threshold", "[0, inf)", False), ("function_tolerance", "[0, inf)", False),
            ("refine_scale_floor", "[0, inf)", False), ("expression_priority", "(-inf, inf)", False),
            ("expression_quota", "[0, 1]", False), ("expression_prior_precision", "[0, inf)", False),
            ("min_contrast", "[0, inf)", False), ("min_face_width_px", "[0, inf)", False),
            ("crop_margin", "[0, inf)", False), ("motion_prediction", "[0, 1]", False),
            ("robust_c", "(0, inf)", True), ("refine_prior_precision", "[0, inf)", True),
            ("expression_sparsity", "(0, inf)", True),
        ):  # fmt: skip
            object.__setattr__(self, name, check_number(getattr(self, name), name, interval, optional))
        # ((True, True) was taken as floors of 1, ("0.1", "0.02") was "'<' not supported between 'int' and 'str'")
        floors = check_reals(self.robust_scale_floor, "robust_scale_floor", "(0, inf)")
        if len(floors) != 2:
            raise ValueError(f"robust_scale_floor must be two floors (coarsest, finest), got {self.robust_scale_floor}")
        object.__setattr__(self, "robust_scale_floor", floors)
        if self.expression_prior_weights is not None:
            # (a string was taken as its characters: "1" * 11 as eleven ones, bytes as their codes)
            weights = check_reals(self.expression_prior_weights, "expression_prior_weights", "[0, inf)")
            if not weights:
                raise ValueError("expression_prior_weights must be one factor per animation unit or None, got ()")
            object.__setattr__(self, "expression_prior_weights", tuple(float(w) for w in weights))
            if not self.use_expression:  # (the units are held: their prior, weighted or not, did nothing, unsaid)
                raise ValueError("expression_prior_weights weigh the prior of animation units that "
                                 "use_expression=False never solves for (they are held at the start's values): "
                                 "leave them None, or estimate the expression (use_expression=True)")  # fmt: skip
        self._check_prior_strength()
        if len(self.iterations) != self.num_levels or any(i < 1 for i in self.iterations):
            raise ValueError(
                f"iterations must give a positive count per level ({self.num_levels}), got {self.iterations}"
            )
        if not 0 <= self.min_points <= self.max_points:
            raise ValueError(f"min_points must be in [0, max_points = {self.max_points}] (with more, every frame fails), "
                             f"got {self.min_points}")  # fmt: skip
        if self.motion_prediction > 0.0 and not self.template.enabled:
            raise ValueError("motion_prediction needs template management (template.enabled): its confidence "
                             "decides where the prediction applies")
        for name, kind in (("robust", RobustKind), ("backend", Backend), ("solver", TrackSolver)):
            check_choice(getattr(self, name), name, kind)  # (solver="fast" ran the reference solver)

    def _check_prior_strength(self) -> None:
        """Refuse priors the float32 solver cannot use (:data:`MAX_UNIT_PRECISION`, :data:`SPARSITY_RANGE`): an
        ``expression_prior_weights`` of 1e16 or ``expression_prior_precision=1e20`` held the pose at the first
        frame's while every frame reported success, ``expression_sparsity=1e39`` was a ``RuntimeError`` ("value
        cannot be converted to type float without overflow") at the first step."""
        sparsity = self.expression_sparsity
        if sparsity is not None:
            low, high = SPARSITY_RANGE
            if not low <= sparsity <= high:
                raise ValueError(
                    f"expression_sparsity must be in [{low:g}, {high:g}] or None, got {sparsity!r}: above {high:g} "
                    f"the prior is the Gaussian one already (expression_sparsity=None gives it), below {low:g} every "
                    "active unit's prior is gone already, and float32 overflows past 3e38 and holds 0 under 1e-45"
                )
        precisions = [(name, value) for name in ("expression_prior_precision", "refine_prior_precision")
                      if (value := getattr(self, name)) is not None]  # fmt: skip
        for name, value in precisions:
            check_unit_precision(value, name, _STRONG_PRIOR, optional=name == "refine_prior_precision")
        weights = self.expression_prior_weights or (1.0,)
        for i, w in enumerate(weights):
            check_unit_precision(w, f"expression_prior_weights[{i}]", _STRONG_PRIOR)
        i = max(range(len(weights)), key=lambda k: weights[k])
        for name, value in precisions:
            if value * weights[i] > MAX_UNIT_PRECISION:
                raise ValueError(
                    f"expression_prior_weights[{i}] ({weights[i]:g}) times {name} ({value:g}) is "
                    f"{value * weights[i]:g}: {_STRONG_PRIOR}; lower one of them"
                )


def face_width_px(model: FaceModel, translation: Tensor, intrinsics: Intrinsics) -> Tensor:
    """``(B,)`` the width in pixels of the model's mean face seen frontally at the estimate's depth: ``fx w / t_z``,
    ``w`` the horizontal extent of the model's landmarks on its mean shape (CANDIDE-3: 125 mm between the iBUG
    jaw's ends) and ``t_z`` the head origin's depth (``translation (B, 3)``, mm). It does not shrink as the head
    turns; a depth at or behind the near plane gives ``inf``, a NaN one NaN. :attr:`TrackerConfig.min_face_width_px`
    is compared with it.

    Example:
        >>> from torchface.model import load_candide3
        >>> w = face_width_px(load_candide3(), torch.tensor([[0.0, 0.0, 3000.0]]), Intrinsics.default(320, 240))
        >>> round(float(w), 1)
        13.4
    """
    if not isinstance(translation, Tensor) or translation.dim() != 2 or translation.shape[1] != 3:
        # (a (3,) translation raised "too many indices for tensor of dimension 1" from inside)
        got = tuple(translation.shape) if isinstance(translation, Tensor) else type(translation).__name__
        hint = ": one estimate's, translation[None]" if got == (3,) else ""
        raise ValueError(f"translation must be (B, 3) head origins in mm, got {got}{hint}")
    z = translation[:, 2]
    ahead = z > NEAR_PLANE_MM
    width = intrinsics.fx * _landmark_width_mm(model) / torch.where(ahead, z, torch.ones_like(z))
    return torch.where(ahead | z.isnan(), width, torch.full_like(width, math.inf))


def too_small(model: FaceModel, config: TrackerConfig, translation: Tensor, intrinsics: Intrinsics) -> Tensor:
    """``(B,)`` bool: the face of an estimate at ``translation (B, 3)`` is narrower than
    :attr:`TrackerConfig.min_face_width_px` (:func:`face_width_px`), i.e. farther than ``fx w / min_face_width_px``
    (one comparison; a depth at or behind the near plane or NaN is not too small: such estimates fail on their own)."""
    if config.min_face_width_px <= 0:
        return torch.zeros(translation.shape[0], dtype=torch.bool, device=translation.device)
    return translation[:, 2] > intrinsics.fx * _landmark_width_mm(model) / config.min_face_width_px


def _unit_weights(config: TrackerConfig, num_animation: int, like: Tensor) -> Tensor | None:
    """:attr:`TrackerConfig.expression_prior_weights` as an ``(A,)`` tensor of ``like``'s dtype and device (None
    without them); ``ValueError`` when their count is not the model's ``num_animation``."""
    weights = config.expression_prior_weights
    if weights is None:
        return None
    if len(weights) != num_animation:
        raise ValueError(
            f"expression_prior_weights has {len(weights)} factors for a model with {num_animation} animation units"
        )
    return torch.tensor(weights, dtype=like.dtype, device=like.device)


def expression_prior(
    config: TrackerConfig,
    precision: float | Tensor,
    alpha: Tensor,
    mean: Tensor | None = None,
    plain: Tensor | None = None,
) -> float | Tensor:
    """The animation units' prior precision for the solvers.

    Args:
        precision: a float, or ``(B,)`` per stream.
        alpha: ``(B, A)`` the estimate the pass starts from, in the solve's dtype and device.
        mean: ``(B, A)`` the prior's centre (None: zero).
        plain: optional ``(B,)`` bool, streams kept on the Gaussian prior (no sparsity reweighting).

    Returns:
        ``precision`` as it is without :attr:`TrackerConfig.expression_prior_weights` and
        :attr:`TrackerConfig.expression_sparsity`, else ``(B, A)``: each unit's weight applied, and with
        sparsity ``delta`` each unit's precision times ``delta / max(|alpha - mean|, delta)``.
    """
    B, A = alpha.shape
    w = _unit_weights(config, A, alpha)
    delta = config.expression_sparsity
    if w is None and delta is None:
        return precision
    base = precision.to(alpha.dtype).unsqueeze(-1) if isinstance(precision, Tensor) else precision
    out = torch.ones_like(alpha) * base if w is None else base * w
    if delta is not None:
        size = (alpha if mean is None else alpha - mean.to(alpha)).abs()
        factor = delta / size.clamp_min(delta)
        if plain is not None:
            factor = torch.where(plain.to(alpha.device).unsqueeze(-1), torch.ones_like(factor), factor)
        out = out * factor
    return out.expand(B, A).contiguous()


def scale_floor(config: TrackerConfig, level: int) -> float:
    """The robust scale floor at pyramid ``level`` (0 = finest): geometric from coarsest to finest."""
    coarse, fine = config.robust_scale_floor
    if config.num_levels == 1:
        return fine
    f = level / (config.num_levels - 1)
    return fine * (coarse / fine) ** f


def stream_index(index: Sequence[int] | Tensor, batch: int, device: torch.device) -> Tensor:
    """``index``, stream indices (a list or integer tensor, negative ones from the end) or a ``(batch,)`` bool mask,
    as an int64 ``(B',)`` tensor of indices in ``[0, batch)`` on ``device`` (:meth:`TrackerState.select`,
    :meth:`TrackResult.select`); a ``TypeError`` or ``IndexError`` naming what is wrong otherwise (a uint8 tensor,
    which torch indexes with as a mask, is a ``TypeError``: ``.bool()`` for a mask, ``.long()`` for indices)."""
    B = batch
    # An empty list is no streams (torch.as_tensor([]) is float32: "stream indices must be integers").
    empty = isinstance(index, (list, tuple)) and not index
    # (torch's "Could not infer dtype of NoneType", of set: a set or dict has no order to keep the streams in)
    if index is None or isinstance(index, (str, bytes, slice, set, frozenset, dict)):
        raise TypeError(f"index must be stream indices (a list or int64 tensor) or a ({B},) bool mask, "
                        f"got {type(index).__name__}")  # fmt: skip
    index = torch.as_tensor(index, device=device, dtype=torch.int64 if empty else None).reshape(-1)
    if index.dtype == torch.uint8:  # torch indexes with it as a mask (deprecated), this took it for indices: a
        # uint8 mask [1, 0, 1] kept streams 1, 0 and 1 without a word
        raise TypeError(f"a uint8 index is ambiguous (torch takes it for a mask, deprecated): pass a ({B},) bool mask, "
                        "index.bool(), or stream indices, index.long()")  # fmt: skip
    if index.dtype == torch.bool:  # a mask of the streams kept
        if index.numel() != B:
            raise IndexError(f"a stream mask must have {B} values (one per stream), got {index.numel()}")
        index = index.nonzero().squeeze(-1)
    elif index.is_floating_point() or index.is_complex():
        raise TypeError(f"stream indices must be integers, got {index.dtype}")
    index = index.to(torch.int64)
    if index.numel() and (int(index.min()) < -B or int(index.max()) >= B):
        raise IndexError(f"stream index out of range for {B} streams: {index.tolist()}")
    return index % B if B else index


@dataclass(frozen=True, eq=False)
class TrackResult:
    """What one step reports per stream (see :mod:`torchface.conventions` for frames and units).

    Attributes:
        rotation: ``(B, 3, 3)`` head -> camera rotation (OpenCV camera frame). Once the online look-ahead start
            has re-anchored a stream (:func:`~torchface.tracker.managed.initialise_managed`), the pose (rotation,
            axis-angle, translation, angles) is reported in the head frame of the stream's first result, so that
            it stays continuous; the mesh is then placed by the state's parameters (``TrackerState.params``), not
            by these: normalise or draw with the state.
        axis_angle: ``(B, 3)`` the same as an axis-angle vector (radians).
        translation: ``(B, 3)`` head origin in the camera frame, millimetres.
        ypr_deg: ``(B, 3)`` yaw, pitch, roll in degrees (conventions' order and signs).
        anim_coeffs: ``(B, A)`` the model's animation-unit coefficients: with the shape units they place the
            mesh (:meth:`~torchface.model.FaceModel.deform`). They include the first frame's fitted expression
            (:attr:`TrackerConfig.fit`), which on a face unlike the model carries shape the shape units cannot.
        anim_names: the animation units' names.
        expression: ``(B, A)`` the expression: ``anim_coeffs`` minus the first frame's fitted coefficients
            (:attr:`TrackerState.anim_prior_mean`), so 0 on the first frame. The tracker takes the first frame as
            the person's neutral face, as the paper does (Section 2.1: the template comes from a frontal,
            neutral view); the first fit's coefficients are then the person's neutral, not an expression, and
            the landmark noise in them does not become a constant expression offset. Equal to ``anim_coeffs``
            when that fit estimates no expression.
        facs: ``(B, n_facs)`` FACS AU values linked to ``expression``; facs_names: their names.
        illumination: ``(B, L)`` illumination parameters; illumination_names: their names.
        status: ``(B,)`` int64 :class:`TrackStatus`; iterations: ``(B,)`` at the finest level (0 from
        :func:`initialise`); cost: ``(B,)`` RMS residual (gray levels in [0, 1]) over the valid points at the finest
        level (0 from :func:`initialise`).
        num_points: ``(B,)`` valid template points at the finest level.
        confidence: ``(B,)`` in ``[0, 1]``. From :func:`track_step` alone: the residual confidence (fraction of
            valid points times ``exp(-(rms / 0.1)^2)``); with template management
            (:func:`~torchface.tracker.managed.managed_step`): the dissimilarity confidence of the normalised
            face (paper Section 4.1), 0 for a FAILED sample; a LOST sample's is still its frame's score, which
            can be high (a face leaving the frame is LOST once less than ``min_inside_fraction`` of it is in
            view, while its in-view part may still match): select on :attr:`success` as well. From
            :func:`initialise` (the first frame): the landmark fit's ``exp(-rms_px / 5)``
            (:attr:`~torchface.tracker.fit.LandmarkFit.rms_px`, pixels), 0 for a FAILED stream; from
            :func:`~torchface.tracker.managed.initialise_managed`: the first frame's dissimilarity confidence
            against its own reference, that fit's in ``residual_confidence``.
        residual_confidence: ``(B,)`` the residual confidence (set by template management; None otherwise; the
            first frame's: its landmark fit's, above).
        dissimilarity: ``(B,)`` mean fiducial-patch displacement on the normalised face (its pixels; set by
            template management, NaN where it was not measured; None otherwise).
        mosaic_entry: ``(B,)`` int64 the mosaic entry the frame was aligned against (0 = the reference; set by
            template management; None otherwise).
        start_failure: ``(B,)`` int64 :class:`StartFailure`: why each stream's start failed, where one was tried in
            this call (:attr:`StartFailure.NONE` where the stream started or none was tried for it): every stream's
            at :func:`initialise` and :func:`~torchface.tracker.managed.initialise_managed` (a FAILED stream's
            reason); at a :func:`~torchface.tracker.managed.managed_step` where a detector's restart was tried, that
            of the streams it did not start (they stay LOST); None for a step that tried no start.
            :attr:`start_failure_reasons` gives them in words.

    Example:
        >>> first = tracker.initialise(frames, landmarks)                         # doctest: +SKIP
        >>> first.status.tolist(), first.start_failure_reasons                    # doctest: +SKIP
        ([0, 2], (None, 'no face: too few finite landmarks of positive weight'))
        >>> first.cpu().translation.device                                        # doctest: +SKIP
        device(type='cpu')
    """

    rotation: Tensor
    axis_angle: Tensor
    translation: Tensor
    ypr_deg: Tensor
    anim_coeffs: Tensor
    anim_names: tuple[str, ...]
    expression: Tensor
    facs: Tensor
    facs_names: tuple[str, ...]
    illumination: Tensor
    illumination_names: tuple[str, ...]
    status: Tensor
    iterations: Tensor
    cost: Tensor
    num_points: Tensor
    confidence: Tensor
    residual_confidence: Tensor | None = None
    dissimilarity: Tensor | None = None
    mosaic_entry: Tensor | None = None
    start_failure: Tensor | None = None

    @property
    def start_failure_reasons(self) -> tuple[str | None, ...]:
        """Per stream, why its start failed in words (:attr:`StartFailure.reason` of :attr:`start_failure`), None
        where it did not fail or no start was tried (every stream's None where :attr:`start_failure` is None)."""
        if self.start_failure is None:
            return (None,) * int(self.status.shape[0])
        return tuple(StartFailure(code).reason for code in self.start_failure.tolist())

    def to(
        self, device: torch.device | str | int | torch.dtype | None = None, dtype: torch.dtype | None = None,
        non_blocking: bool = False, copy: bool = False,
    ) -> "TrackResult":
        """The result on ``device`` with the floating tensors in ``dtype`` (a floating dtype; the integer ones,
        ``status``, ``iterations``, ``num_points``, ``mosaic_entry`` and ``start_failure``, keep theirs); the names and
        the fields that are None as they are, ``self`` unchanged (a tensor already on that device and in that dtype is
        shared, as ``Tensor.to`` returns it, unless ``copy=True``). Called as ``Tensor.to`` is: ``.to(device)``,
        ``.to(dtype)``, ``.to(device, dtype)`` or with keywords, ``non_blocking`` and ``copy`` as ``Tensor.to`` takes
        them (:func:`~torchface._device.tensor_mover`: anything else is a ``TypeError``). A device this machine lacks,
        or ``meta`` (no values), is a ``ValueError`` naming it (docs/python-api.md, "Devices and dtypes").

        Example:
            >>> result.to(torch.float64).translation.dtype                      # doctest: +SKIP
            torch.float64
        """
        from torchface.normalise.face import apply_to_tensor_fields

        # (a device not here: a ValueError naming those here)
        return apply_to_tensor_fields(tensor_mover(device, dtype, non_blocking, copy), self)

    def cpu(self) -> "TrackResult":
        """``self.to("cpu")``: a copy with every tensor on the CPU."""
        return self.to("cpu")

    def select(self, index: Sequence[int] | Tensor) -> "TrackResult":
        """The result of streams ``index`` (``(B',)`` stream indices, int64 or a list, in the order wanted; or a
        ``(B,)`` bool mask), as :meth:`TrackerState.select` takes them: every per-stream tensor's rows, the names and
        the fields that are None as they are. ``result.select([b])`` is stream ``b``'s result as a batch of one
        (``result[b]`` is not defined: a result holds one tensor per field).

        Example:
            >>> result.select([1]).ypr_deg.shape                                # doctest: +SKIP
            torch.Size([1, 3])
        """
        from torchface.normalise.face import apply_to_tensor_fields

        index = stream_index(index, int(self.status.shape[0]), self.status.device)
        return apply_to_tensor_fields(lambda t: t[index], self)

    @property
    def success(self) -> Tensor:
        """``(B,)`` bool: the estimate is usable (neither FAILED nor LOST).

        With template management a stream is declared LOST only after a few frames of low confidence
        (:attr:`~torchface.template.management.TemplateConfig.lost_after`, ``lost_after_very_low``: 3 frames below
        0.1 by default), so the first frames of a loss are still successful, with their low ``confidence``:
        where single frames matter, threshold the confidence as well (e.g. a face turned upside down for 10
        frames read success True, confidence 0.00, 28 degrees off, on its first 2)."""
        return usable_status(self.status)


@dataclass(frozen=True, eq=False)
class TrackerState:
    """Everything a step needs from the past.

    Attributes:
        params: ``(B, P)`` packed parameters of the last frame (:class:`ParamLayout`).
        shape_coeffs: ``(B, S)`` the person's shape units (fixed after the first frame).
        templates: one :class:`Template` per pyramid level, finest first.
        intrinsics: camera of the full-resolution frames.
        frame_index: frames seen so far.
        visibility: the z-buffer visibility masks last computed (:attr:`TrackerConfig.visibility_interval`),
            with the templates they belong to (recomputed when the templates change).
        management: template management's state (:class:`~torchface.tracker.managed.ManagementState`: mosaic,
            confidence counters, last confident parameters), or None without it.
        anim_prior_mean: ``(B, A)`` the first frame's fitted expression, where the animation units' prior is
            centred when :attr:`TrackerConfig.expression_prior_at_start` (None: zero), and the person's neutral
            that :attr:`TrackResult.expression` is measured from.
        workspace: scratch memory its steps reuse (:class:`StepWorkspace`; made by the first step of a batch of
            more than :data:`_PYRAMID_CHUNK` streams and handed on to the states that step makes). Not part of
            the state's value: equality and ``repr`` ignore it, copies get an empty one.
    """

    params: Tensor
    shape_coeffs: Tensor
    templates: tuple[Template, ...]
    intrinsics: Intrinsics
    frame_index: int
    management: "ManagementState | None" = None
    visibility: "tuple[tuple[Template, ...], tuple[Tensor, ...]] | None" = None
    anim_prior_mean: Tensor | None = None
    workspace: "StepWorkspace | None" = field(default=None, compare=False, repr=False)

    @property
    def num_levels(self) -> int:
        """The pyramid levels the state is tracked with (one template each): the config's ``num_levels``, or more
        where :func:`pyramid_for_faces` added coarser ones (:class:`~torchface.tracker.FaceTracker` and
        ``torchface track`` do for large faces)."""
        return len(self.templates)

    def detach(self) -> "TrackerState":
        """The state detached from the autograd graph: its ``params``, ``shape_coeffs``, ``anim_prior_mean`` and
        templates (the same objects where they hold no graph). Template management's state is built without one.

        A step from frames that require grad (:func:`track_step`, :func:`~torchface.tracker.managed.managed_step`)
        hands back a state whose ``params`` carry that frame's graph, and the next step starts from them, so the
        graph runs on from frame to frame like an RNN's hidden state: it keeps every frame and its pyramid alive
        (0.26 MB of saved tensors per frame at 160x120 besides the frames themselves, growing without end), and a
        second frame's ``backward()`` fails with "Trying to backward through the graph a second time" (so does
        the first step's after :func:`initialise` from first frames that require grad: its templates are made from
        them). Detach the state between frames where each frame's loss stands alone (truncated back-propagation).

        Example:
            >>> state, result = track_step(model, config, state, frames.requires_grad_())  # doctest: +SKIP
            >>> loss_fn(result).backward()                                                 # doctest: +SKIP
            >>> state = state.detach()                                                     # doctest: +SKIP
        """
        from torchface.normalise.face import apply_to_tensor_fields

        templates, visibility = self.templates, self.visibility
        if any(t.requires_grad for tpl in templates for t in (tpl.points, tpl.basis, tpl.normals, tpl.intensity)):
            templates = tuple(apply_to_tensor_fields(Tensor.detach, tpl) for tpl in templates)
            if visibility is not None and visibility[0] is self.templates:  # the masks belong to these templates
                visibility = (templates, visibility[1])
        prior = None if self.anim_prior_mean is None else self.anim_prior_mean.detach()
        return replace(
            self, params=self.params.detach(), shape_coeffs=self.shape_coeffs.detach(), templates=templates,
            visibility=visibility, anim_prior_mean=prior,
        )  # fmt: skip

    def select(self, index: Sequence[int] | Tensor) -> "TrackerState":
        """The state of streams ``index`` (``(B',)`` stream indices, int64 or a list, in the order wanted; or a
        ``(B,)`` bool mask), to go on tracking them as a smaller batch: e.g. without the streams whose videos have
        ended (``torchface track``).

        Every per-stream part is selected (parameters, shape, templates and their visibility masks, the
        management's mosaic, counters, confident parameters, re-anchoring offsets and online-start watch); the
        intrinsics, frame count and management layout are shared, and so is the :class:`StepWorkspace` (scratch).
        The kept streams then track as they would have in the whole batch, to float rounding (the solver and the
        management treat each stream alone, but the face crop's size is the batch's largest). The tensors are new,
        normal ones (made outside inference mode, as a step's are); selecting every stream in order changes no
        later step's result.

        Example:
            >>> state = state.select([0, 2])                                      # doctest: +SKIP
            >>> state, result = managed_step(model, config, state, frames[[0, 2]])  # doctest: +SKIP
        """
        index = stream_index(index, self.params.shape[0], self.params.device)
        with torch.inference_mode(False):
            params = self.params[index]
            templates = tuple(t.select(index) for t in self.templates)
            visibility = self.visibility
            if visibility is not None:
                kept = templates if visibility[0] is self.templates else tuple(t.select(index) for t in visibility[0])
                visibility = (kept, tuple(m[index] for m in visibility[1]))
            ms = self.management
            if ms is not None:
                tied = ms.params_ypr is not None and ms.params_ypr[0] is self.params
                ms = ms.select(index)
                ms = replace(ms, params_ypr=(params, ms.params_ypr[1]) if tied and ms.params_ypr is not None else None)
            prior = None if self.anim_prior_mean is None else self.anim_prior_mean[index]
            return replace(
                self, params=params, shape_coeffs=self.shape_coeffs[index], templates=templates, management=ms,
                visibility=visibility, anim_prior_mean=prior,
            )  # fmt: skip

    def neutral_anim_coeffs(self, like: Tensor) -> Tensor:
        """The person's neutral animation coefficients (``anim_prior_mean``; zero where the state has none) in the
        dtype and device of ``like`` ``(B, A)`` and broadcast to its shape."""
        if self.anim_prior_mean is None:
            return torch.zeros_like(like)
        return self.anim_prior_mean.to(dtype=like.dtype, device=like.device).expand_as(like)


def anim_prior_mean(config: TrackerConfig, state: TrackerState) -> Tensor | None:
    """``(B, A)`` the centre of the animation units' prior for ``state`` under ``config`` (None: zero)."""
    return state.anim_prior_mean if config.expression_prior_at_start else None


def prior_mean_vector(config: TrackerConfig, state: TrackerState, layout: ParamLayout) -> Tensor | None:
    """``(B, P)`` the prior mean of the packed parameters (the animation part from :func:`anim_prior_mean`)."""
    mean = anim_prior_mean(config, state)
    if mean is None:
        return None
    full = torch.zeros_like(state.params)
    full[:, layout.animation] = mean.to(full)
    return full


def level_intrinsics(intrinsics: Intrinsics, level: int, height: int, width: int) -> Intrinsics:
    """Camera of pyramid level ``level`` (``>= 0``, 0 the finest; each level halves the previous with pixel-centre
    alignment). A negative level (it doubled the focal length) or a fractional one is refused."""
    check_int(level, "level", 0)
    s = 0.5**level
    return Intrinsics(
        width, height, intrinsics.fx * s, intrinsics.fy * s, (intrinsics.cx + 0.5) * s - 0.5, (intrinsics.cy + 0.5) * s - 0.5
    )


def gray_pyramid(frames: Tensor, num_levels: int) -> list[Tensor]:
    """``(B, C, H, W)`` float frames -> ``num_levels`` (``>= 1``) gray levels, finest first, each
    ``(B, 1, H_l, W_l)`` (:func:`pyr_down`). Integer frames are refused (uint8 ones gave a uint8 finest level and
    float 0-255 coarser ones), as is a ``num_levels`` below 1 (0 and -3 gave one level)."""
    check_int(num_levels, "num_levels", 1)
    if not isinstance(frames, Tensor) or frames.dim() != 4 or not frames.is_floating_point():
        got = f"{tuple(frames.shape)} {frames.dtype}" if isinstance(frames, Tensor) else type(frames).__name__
        hint = _frame_hint(frames) if isinstance(frames, Tensor) else ""
        raise ValueError(f"frames must be (B, C, H, W) float in [0, 1], got {got}{hint}")
    gray = to_gray(frames)
    levels = [gray]
    for _ in range(num_levels - 1):
        levels.append(pyr_down(levels[-1]))
    return levels


def gray_pyramid_windows(
    frames: Tensor, num_levels: int, offsets: Sequence[Tensor | None], heights: Sequence[int], widths: Sequence[int],
    rows: Tensor | None = None, backend: Backend = Backend.AUTO,
) -> list[Tensor]:
    """Windows of :func:`gray_pyramid`: level ``l``'s ``(B, 1, heights[l], widths[l])`` windows whose top-left
    pixels are ``offsets[l] (B, 2)`` int64 ``(x0, y0)`` in that level's pixels (each inside its level); where
    ``offsets[l]`` is None, the whole level. ``rows``: ``(B,)`` int64, the windows are those of
    ``frames[rows]`` (without copying those frames); None: of ``frames``.

    The values are :func:`gray_pyramid`'s exactly, computed from a crop of the frames around the windows: the
    crop's corners lie on multiples of ``2 ** (num_levels - 1)`` (the levels stay aligned) and it reaches
    ``4 * 2 ** (num_levels - 1)`` pixels beyond the windows (4 pixels at the coarsest level) unless it meets the
    image border, so that the pyramid filter's reflected border only touches pixels outside the windows. Where
    that crop would not fit (a frame size not divisible by that power of two), or a level is wanted whole, the
    whole frames are used. ``backend``: :func:`gray_crop_pyramid`'s (the crop's pyramid).
    """
    _, _, H, W = frames.shape

    def from_whole_frames() -> list[Tensor]:
        levels = gray_pyramid(frames if rows is None else frames.index_select(0, rows), num_levels)
        return [g if off is None else crop_windows(g, off, h, w) for g, off, h, w in zip(levels, offsets, heights, widths)]

    windows = [off for off in offsets if off is not None]
    if len(windows) < len(offsets):  # a level wanted whole
        return from_whole_frames()
    q = 2 ** (num_levels - 1)
    size_hw = frames.new_tensor([W, H], dtype=torch.int64)
    lo = torch.stack([off * 2**lv for lv, off in enumerate(windows)]).amin(0)  # (B, 2) level 0 (x, y)
    hi = torch.stack([(off + off.new_tensor([w, h])) * 2**lv
                      for lv, (off, h, w) in enumerate(zip(windows, heights, widths))]).amax(0)  # fmt: skip
    start = torch.div((lo - 4 * q).clamp_min(0), q, rounding_mode="floor") * q
    stop = torch.minimum(hi + 4 * q, size_hw)
    size = -torch.div(-(stop - start).amax(0), q, rounding_mode="floor") * q  # (2,) width, height
    start = torch.minimum(start, size_hw - size)
    if bool((start < 0).any() | (start % q != 0).any()):
        return from_whole_frames()
    crop = gray_crop_pyramid(frames, start, int(size[1]), int(size[0]), num_levels, rows, backend=backend)
    return [crop_windows(g, off - torch.div(start, 2**lv, rounding_mode="floor"), h, w)
            for lv, (g, off, h, w) in enumerate(zip(crop, windows, heights, widths))]  # fmt: skip


def not_tensor_hint(
    frames: object, per: str = "one frame per stream", to_float: bool = True, rgb_only: bool = False,
    layout: str = "(B, C, H, W)", *, one_frame: bool = False,
) -> str:
    """How to pass frames that are not a tensor, for a ``TypeError`` that refuses them: ``" (...)"`` to append to
    its message, empty where nothing is to say (:func:`check_frames`'; ``training_hooks.NormaliseFaces``', and
    ``training_hooks.track_sequence``'s for each streamed frame). It covers a NumPy image as OpenCV reads it,
    ``(H, W, 3)`` uint8 BGR (the common case: the message said "got ndarray" alone), NumPy frames ``(N, H, W, 3)``,
    a gray image ``(H, W)``, another NumPy array, a list of frames and an iterator of them (a generator,
    :func:`torchface.io.open_frames`' reader: for the tracker's ``per``, one frame per call too).

    Args:
        frames: what was passed.
        per: what ``torch.stack`` of a list of frames gives the caller.
        to_float: the caller takes float frames in [0, 1] only (``NormaliseFaces`` takes uint8 too).
        rgb_only: the caller takes 3 channels only (``NormaliseFaces``: a gray image's ``(1, 1, H, W)`` was refused
            again), a gray image's three channels given too.
        layout: the caller's frame layout, said for another NumPy array (``NormaliseFaces``: ``(T, 3, H, W)``; it
            was told ``(B, C, H, W)``, the tracker's).
        one_frame: the caller takes one frame ``(C, H, W)`` at a time, without a batch dimension (``track_sequence``'s
            frames: an image's recipe adds none); a list is then no list of frames, and nothing is said of it.

    Example:
        >>> import numpy as np
        >>> not_tensor_hint(np.zeros((480, 640), np.uint8))
        ' (a NumPy gray image (H, W): torch.from_numpy(image)[None, None].float() / 255)'
        >>> not_tensor_hint(np.zeros((8, 3, 4, 4), np.float32), layout="(T, 3, H, W)")
        ' (a NumPy array: torch.from_numpy(array).float(), laid out (T, 3, H, W))'
        >>> not_tensor_hint(np.zeros((480, 640), np.uint8), to_float=False, rgb_only=True, one_frame=True)
        ' (a NumPy gray image (H, W): torch.from_numpy(image)[None].expand(3, -1, -1))'
    """
    if isinstance(frames, (list, tuple)):
        return "" if one_frame else f" (a {type(frames).__name__} of frames: torch.stack(frames), {per})"
    if isinstance(frames, Iterator) and not one_frame:  # (a generator, open_frames' reader: told the type alone)
        # (the tracker's, per frame: a video's frames, one call each; stacked, they are streams)
        each = " one per call, next(frames)[None] of (3, H, W) frames; or" if per == "one frame per stream" else ""
        return f" (an iterator of frames:{each} torch.stack(list(frames)), {per})"
    shape, dtype = getattr(frames, "shape", None), str(getattr(frames, "dtype", ""))
    if type(frames).__name__ != "ndarray" or not isinstance(shape, tuple):
        return ""
    scale = {"uint8": ".float() / 255", "uint16": ".float() / 65535"}.get(dtype, ".float()")
    scale = scale if to_float or dtype != "uint8" else ""
    batch = "" if one_frame else "[None]"
    if len(shape) == 3 and shape[-1] == 3:
        return (f" (a NumPy image (H, W, 3), BGR as OpenCV reads it: torch.from_numpy(image[..., ::-1].copy())"
                f".permute(2, 0, 1){batch}{scale}; an RGB one without [..., ::-1])")
    if len(shape) == 4 and shape[-1] == 3 and not one_frame:
        return (f" (NumPy frames (N, H, W, 3), BGR as OpenCV reads them: torch.from_numpy(frames[..., ::-1].copy())"
                f".permute(0, 3, 1, 2){scale}; RGB ones without [..., ::-1])")
    if len(shape) == 2:
        rgb = (".expand(3, -1, -1)" if one_frame else ".expand(-1, 3, -1, -1)") if rgb_only else ""
        index = "[None]" if one_frame else "[None, None]"
        return f" (a NumPy gray image (H, W): torch.from_numpy(image){index}{rgb}{scale})"
    return f" (a NumPy array: torch.from_numpy(array){scale}, laid out {layout})"


def _frame_hint(frames: Tensor) -> str:
    """How to make refused frames ``(B, 3, H, W)`` / ``(B, 1, H, W)`` float in [0, 1] (:func:`check_frames`'s
    message; empty where nothing is to say): a missing batch or channel dimension, channels last, RGBA, integer
    pixels (uint16 was refused without one, uint8 had one)."""
    hints = []
    shape = tuple(frames.shape)
    if frames.dim() == 2:
        hints.append("one gray frame: frames[None, None]")
    elif frames.dim() == 3 and shape[0] not in (1, 3, 4) and shape[-1] in (1, 3, 4):
        # an image as OpenCV, PIL and numpy hold it (it was told "one frame (C, H, W): frames[None]", which gave a
        # (1, H, W, C) frame)
        hints.append("one channels-last frame (H, W, C): frames.permute(2, 0, 1)[None]")
    elif frames.dim() == 3 and shape[0] not in (1, 3, 4):
        hints.append("gray frames (B, H, W): frames[:, None]")
    elif frames.dim() == 3:
        hints.append("one frame (C, H, W): frames[None]; gray frames (B, H, W): frames[:, None]")
    elif frames.dim() == 4 and shape[1] not in (1, 3, 4) and shape[-1] in (1, 3, 4):
        hints.append("channels last (B, H, W, C): frames.permute(0, 3, 1, 2)")
    elif frames.dim() == 4 and shape[1] == 4:
        hints.append("RGBA: drop the alpha, frames[:, :3]")
    elif frames.dim() == 5:  # (a clip, as a video dataset's batch holds it, was told the shape alone)
        hints.append("a clip (B, T, C, H, W)? one frame per stream per call: frames[:, t]")
    dtype = pixel_type_hint(frames)
    hints += [dtype] if dtype else []
    return f" ({'; '.join(hints)})" if hints else ""


def pixel_type_hint(frames: Tensor) -> str:
    """How to make frames of integer pixels ``frames`` float in [0, 1] (uint8, uint16, another integer type), for
    the messages of refused frames and clips; "" for float frames."""
    if frames.dtype == torch.uint8:
        return "uint8 frames: pass frames.float() / 255"
    if frames.dtype == torch.uint16:
        return "16-bit frames: pass frames.float() / 65535"
    return "" if frames.is_floating_point() else "convert them to float in [0, 1]"


def check_frames(
    frames: Tensor, intrinsics: Intrinsics | None = None, *, values: bool = False, row_stride: int = 1,
    size_of: str = "the tracked size",
) -> None:
    """Validate ``(B, 3, H, W)`` (or ``(B, 1, H, W)``) float frames in [0, 1].

    With ``values``, also refuse values outside :data:`FRAME_VALUE_RANGE`: 0-255 frames, or frames normalised with
    a mean and standard deviation, would otherwise be tracked with every threshold (gradient, contrast, robust
    scale) 255 times too small. NaN pixels are left out of that range (they are never template points; a frame of
    them is a failed sample); infinite ones are refused. ``row_stride``: the values looked at are those of every
    ``row_stride``-th row (initialisation: 1, every pixel; the steps: :data:`STEP_VALUE_ROW_STRIDE`, a cheap look
    that a 0-255 frame does not pass, which leaves infinite pixels out too: a later frame's stray one is the robust
    loss's to reject, as a NaN one is). ``size_of``: what ``intrinsics``' size is, for the message of frames of
    another size.
    """
    if not isinstance(frames, Tensor):
        raise TypeError(f"frames must be a torch.Tensor (B, 3, H, W) RGB or (B, 1, H, W) gray, float in [0, 1], "
                        f"got {type(frames).__name__}{not_tensor_hint(frames)}")  # fmt: skip
    check_holds_data(frames, "frames")
    if frames.dim() != 4 or frames.shape[1] not in (1, 3) or not frames.is_floating_point():
        raise ValueError(
            f"frames must be (B, 3, H, W) RGB or (B, 1, H, W) gray, float in [0, 1], got {tuple(frames.shape)} "
            f"{frames.dtype}{_frame_hint(frames)}"
        )
    if intrinsics is not None and tuple(frames.shape[-2:]) != intrinsics.size:
        # W x H, as everywhere else (it said H x W: a tracker of 1920x1080 frames handed a portrait 1080x1920 frame
        # read "frames must be 1080x1920 (the tracked size), got 1920x1080")
        # (mid-stream, a new video's frames were told the size alone)
        tracked = size_of == "the tracked size"
        hint = ": a stream keeps its size, initialise again to track frames of another" if tracked else ""
        if not tracked:
            hint = _intrinsics_size_hint(intrinsics, frames.shape[-1], frames.shape[-2])
        raise ValueError(
            f"frames must be {intrinsics.width}x{intrinsics.height} (W x H, {size_of}), got "
            f"{frames.shape[-1]}x{frames.shape[-2]}{hint}"
        )
    if values:
        check_frame_values(frames, row_stride)


def _intrinsics_size_hint(intrinsics: Intrinsics, width: int, height: int) -> str:
    """Why intrinsics' size may differ from ``width x height`` frames, for :func:`check_frames`' message at the start:
    width and height swapped, or the size among the other numbers (the arguments out of order); empty otherwise."""
    if (intrinsics.width, intrinsics.height) == (height, width):
        return f" (width and height swapped? Intrinsics({width}, {height}, fx, fy, cx, cy): the width first)"
    others = [float(v) for v in (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
              if not isinstance(v, Tensor)]  # fmt: skip
    if float(width) in others and float(height) in others:
        return (" (the size given among fx, fy, cx, cy? Intrinsics takes (width, height, fx, fy, cx, cy); from a "
                "3x3 calibration matrix: Intrinsics.from_matrix(K, width, height))")
    return ""


def check_model_precision(model: FaceModel) -> None:
    """Refuse a float16 / bfloat16 model, as ``FaceTracker.to`` does: the tracker's solves (Cholesky) have no such
    kernels ('"cholesky_cpu" not implemented for 'Half'' from deep inside the landmark fit)."""
    if model.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"the tracker tracks in float32 or float64, the model is {model.dtype} (its solver factorises "
                        "matrices): convert it, model.to(dtype=torch.float32), or load it so (the loaders' dtype="
                        "torch.float32), or use torch.autocast")  # fmt: skip


def check_api_types(
    model: object, config: object, state: object = None, *, with_state: bool = False, config_name: str = "config"
) -> None:
    """Refuse a ``model`` that is not a :class:`FaceModel`, a ``config`` that is not a :class:`TrackerConfig` and
    (``with_state``) a ``state`` that is not a :class:`TrackerState`, by name: the functional entry points
    (:func:`initialise`, :func:`track_step`, :func:`~torchface.tracker.managed.managed_step`, ...) raised an
    AttributeError ('NoneType' object has no attribute 'intrinsics') where ``FaceTracker`` names them.
    ``config_name``: the caller's name for ``config`` (``lookahead_fit``'s is ``tracker_config``, its ``config`` a
    :class:`~torchface.tracker.lookahead.LookaheadConfig`)."""
    if not isinstance(model, FaceModel):
        raise TypeError(f"model must be a FaceModel, got {type(model).__name__}")
    check_model_precision(model)
    if not isinstance(config, TrackerConfig):
        raise TypeError(f"{config_name} must be a TrackerConfig, got {type(config).__name__}")
    if with_state and not isinstance(state, TrackerState):
        raise TypeError(f"state must be a TrackerState (from initialise or a previous step), got {type(state).__name__}")


def min_frame_side(num_levels: int) -> int:
    """The least side, in pixels, of frames a pyramid of ``num_levels`` levels takes: ``3 * 2 ** (num_levels - 2)``
    (its coarsest level made of a level of at least 3 pixels a side, as ``pyr_down`` needs), 1 for one level."""
    return 3 * 2 ** (num_levels - 2) if num_levels > 1 else 1


def check_initialise_inputs(
    model: FaceModel, config: TrackerConfig, frames: Tensor, landmarks_px: Tensor, intrinsics: Intrinsics,
    weights: Tensor | None,
) -> None:
    """The checks of :func:`initialise` (and of :func:`~torchface.tracker.managed.initialise_managed` before its
    landmark fit): frames (:func:`check_frames` with values), at least one stream, ``(B, K, 2)`` landmarks of the
    model's ``K`` points (NaN: missing; the online start and recovery use them all, so a subset is given as NaN
    rows), ``(B, K)`` tensor weights, ``config.expression_prior_weights`` of the model's length, and a
    ``config.num_levels`` the frames' size allows."""
    check_api_types(model, config)
    check_model_landmarks(model)  # (a model without landmarks: an IndexError from the pyramid's face size)
    check_intrinsics(intrinsics)  # (first: check_frames reads its size, an AttributeError for a tuple)
    check_frames(frames, intrinsics, values=True, size_of="the intrinsics' size")  # (nothing is tracked yet)
    mixed_up = mixed_up_intrinsics(intrinsics)
    if mixed_up is not None:  # (implausible, not impossible: tracked as given, with a word; from this line, so that
        # Python's filter shows it once, not once per entry point that checks: FaceTracker, initialise_managed, ...)
        warnings.warn(MixedUpIntrinsics(mixed_up, intrinsics), stacklevel=1)  # (a UserWarning)
    B, K = frames.shape[0], model.num_landmarks
    if B == 0:
        raise ValueError("frames must hold at least one stream (B >= 1), got B = 0")
    side = min_frame_side(config.num_levels)
    if min(frames.shape[-2:]) < side:  # was pyr_down's "images must be ... H, W >= 3, got (B, 1, 2, 2)"
        raise ValueError(f"frames must be at least {side}x{side} pixels for num_levels = {config.num_levels}, "
                         f"got {frames.shape[-1]}x{frames.shape[-2]} (W x H)")  # fmt: skip
    check_landmark_type(landmarks_px, f"({B}, {K}, 2)")
    if landmarks_px.dim() != 3 or landmarks_px.shape[0] != B:
        got = tuple(landmarks_px.shape)
        # (a (K, 2) set for one stream, as a landmark file holds it, was told no more than that)
        hint = ": one stream's, landmarks_px[None]" if B == 1 and got == (K, 2) else ""
        if B == 1 and len(got) == 3 and got[1:] == (K, 2):  # (a clip's, as GroundTruth.landmarks_px: told no more)
            n = got[0]
            hint = (f": a set per frame of a clip? the first frame's, landmarks_px[:1]; {n} faces in this frame? a "
                    f"stream each, frames.expand({n}, -1, -1, -1)")  # fmt: skip
        elif len(got) == 4 and got[1:] == (B, K, 2):  # ((T, B, K, 2): the streams' clips)
            hint = ": a set per frame? the first frame's, landmarks_px[0]"
        elif B > 1 and got == (1, K, 2):  # (a clip's frames given as the batch: "one set per frame" read as if a set
            # for each of its frames were wanted, which starts each frame as a stream of its own)
            hint = (f": the frames of one video? initialise takes its first, frames[:1], and each later frame is a "
                    f"call of its own, tracker(frames[t : t + 1]); {B} streams of this face: landmarks_px.expand({B}, "
                    "-1, -1)")  # fmt: skip
        raise ValueError(f"landmarks_px must be (B, K, 2) with B = {B} (one set per frame), got {got}{hint}")
    if tuple(landmarks_px.shape[1:]) != (K, 2):
        # ((B, 2, K): x and y rows, as some detectors give them)
        hint = (" (x, y rows: landmarks_px.transpose(1, 2))" if tuple(landmarks_px.shape[1:]) == (2, K)
                else " (x, y, z points, as 3D landmark detectors give them: landmarks_px[..., :2])"
                if tuple(landmarks_px.shape[1:]) == (K, 3) else "")  # fmt: skip
        if K == 68 and landmarks_px.shape[1] in MEDIAPIPE_MESH_POINT_COUNTS:  # (CANDIDE-3's, the iBUG points)
            hint = f" ({MEDIAPIPE_MESH_HINT})"  # (MediaPipe's (B, 478, 2 or 3) points were told the shape alone)
        other = other_landmark_set_hint(landmarks_px.shape[1], "landmarks_px[:, :68, :2]") if K == 68 else None
        if other is not None:  # (WFLW's (B, 98, 2), OpenPose's (B, 70, 3): told the shape alone)
            hint = f" ({other})"
        raise ValueError(f"landmarks_px must be (B, {K}, 2), the model's {K} landmarks (NaN rows for missing ones), "
                         f"got {tuple(landmarks_px.shape)}{hint}")  # fmt: skip
    check_weights_shape(weights, B, K)
    if weights is not None:
        check_holds_data(weights, "weights")
    check_landmark_values(landmarks_px, weights)  # (infinite or half-NaN rows; NaN, infinite, negative weights)
    check_pixel_landmarks(landmarks_px, frames.shape[-1], frames.shape[-2], weights)  # (not MediaPipe's [0, 1])
    _unit_weights(config, model.num_animation, frames)  # their count, before any work


#: The least side, in pixels, of the crop a step tracks a stream in (:func:`face_crop`: the largest face's box, its
#: margins and this many pixels; the frame where smaller): :func:`pyramid_for_faces` adds no level a crop this small
#: cannot make.
MIN_CROP_PX: int = 64

#: The face size :class:`TrackerConfig`'s pyramid is made for: the larger side, in pixels, of the first frame's
#: landmark box in the 640x480 scenarios (160-200 pixels). :func:`pyramid_for_faces` adds coarser levels for larger
#: faces.
PYRAMID_REFERENCE_FACE_PX: float = 180.0


def pyramid_for_faces(
    config: TrackerConfig, landmarks_px: Tensor, size: tuple[int, int], weights: Tensor | None = None
) -> TrackerConfig:
    """``config`` with coarser pyramid levels added where the faces are larger than the pyramid is made for.

    A frame-to-frame motion is followed when the coarsest level sees it as a few pixels, and a face's motion in
    pixels grows with its size in the image: the same clip that is tracked at 640x360 was lost after two frames
    at 1280x720 (13 mm a frame sideways at 450 mm, 37 pixels; 18 at 640x360) with the default three levels, and
    tracked with four. One level is added per doubling of the face's size over
    :data:`PYRAMID_REFERENCE_FACE_PX` (rounded: faces smaller than 180·√2 = 254.56 pixels keep ``config``; a
    1280x720 face at 450 mm, 380 pixels, gets one, 1920x1080 two, 3840x2160 three), as many as the frame's size
    (:func:`check_initialise_inputs`) and the step's least crop (:data:`MIN_CROP_PX`: 6 levels at most) allow.
    The added levels take the coarsest level's ``iterations``; the robust scale floors stay those of the coarsest
    and the finest level. ``torchface track`` does this for every video (and batches only videos of one pyramid),
    :class:`~torchface.tracker.FaceTracker` and ``training_hooks``' tracking do by default (their
    ``pyramid="auto"``); :func:`initialise` and the other functions use the config as given.

    Args:
        config: the settings to extend.
        landmarks_px: ``(B, K, 2)`` the first frames' landmarks in pixels (NaN rows: missing). The smallest face
            of the batch decides (its streams share one pyramid): none is made smaller than the reference at the
            coarsest level.
        size: ``(H, W)`` of the frames.
        weights: ``(B, K)`` the landmarks' weights (``>= 0``), or None: a point the landmark fit ignores (weight 0)
            is left out of its face's size, as a missing one is (:class:`~torchface.tracker.FaceTracker` passes its
            ``weights``: two points of weight 0 at the corners of a 640x360 frame gave a 190-pixel face five levels
            instead of three).

    Raises:
        TypeError, ValueError: landmarks or weights of the wrong type or shape, a landmark row with an infinite
            coordinate or one coordinate NaN alone, NaN, infinite or negative weights
            (:func:`~torchface.tracker.fit.check_landmark_values`).

    Returns:
        ``config`` itself, or a copy with more ``num_levels`` and ``iterations``.

    Example:
        >>> lm = torch.tensor([[[0.0, 0.0], [360.0, 380.0]]])  # a 380-pixel face (two of its landmarks)
        >>> pyramid_for_faces(TrackerConfig(), lm, (720, 1280)).iterations
        (6, 6, 5, 4)
    """
    if not isinstance(config, TrackerConfig):
        raise TypeError(f"config must be a TrackerConfig, got {type(config).__name__}")
    check_landmark_type(landmarks_px, "(B, K, 2)")
    if landmarks_px.dim() != 3 or landmarks_px.shape[-1] != 2:
        raise ValueError(f"landmarks_px must be (B, K, 2), got {tuple(landmarks_px.shape)}")
    check_weights_shape(weights, *landmarks_px.shape[:2])
    check_landmark_values(landmarks_px, weights)
    points = landmarks_px.detach().to(torch.float64)
    # (B, K, 1): the points the fit uses (finite, of positive weight: landmark_targets)
    seen = (landmark_targets(points, None if weights is None else weights.detach())[1] > 0).unsqueeze(-1)
    lo = torch.where(seen, points, math.inf).amin(1)
    hi = torch.where(seen, points, -math.inf).amax(1)
    faces = (hi - lo).amax(-1)  # (B,) the larger side of each box; -inf or NaN without two points
    faces = faces[torch.isfinite(faces) & (faces > 0)]
    if faces.numel() == 0:
        return config
    extra = max(0, math.floor(math.log2(float(faces.min()) / PYRAMID_REFERENCE_FACE_PX) + 0.5))
    # pyr_down's 3 pixels a side in the frame, and at most the levels a MIN_CROP_PX crop makes (6). The latter no
    # longer guards the step (landmarks 255 times too large on 160x120 frames once gave 7 levels, and the crop of the
    # failed start crashed in pyr_down; face_crop now enlarges its crop to 3 * 2**(L - 2) a side), but it is not
    # redundant: it is the documented ceiling, without which faces over 2036 px (a 4K close-up) get 7 levels and a
    # far too large landmark box up to the frame's limit (10 at 1080p): 462 of 990 frame x face sizes differ
    while extra > 0 and min(*size, MIN_CROP_PX) < 3 * 2 ** (config.num_levels + extra - 2):
        extra -= 1
    return add_coarser_levels(config, extra)


def add_coarser_levels(config: TrackerConfig, extra: int) -> TrackerConfig:
    """``config`` with ``extra`` coarser pyramid levels (as :func:`pyramid_for_faces` adds them: each with the
    coarsest level's ``iterations``); ``config`` itself for ``extra = 0``.

    Raises:
        TypeError: ``config`` is not a :class:`TrackerConfig`, or ``extra`` is not an int (:func:`check_int`).
        ValueError: ``extra`` is negative.

    Example:
        >>> add_coarser_levels(TrackerConfig(), 2).iterations
        (6, 6, 6, 5, 4)
    """
    if not isinstance(config, TrackerConfig):
        raise TypeError(f"config must be a TrackerConfig, got {type(config).__name__}")
    extra = check_int(extra, "extra", 0)
    if extra == 0:
        return config
    return replace(config, num_levels=config.num_levels + extra,
                   iterations=(config.iterations[0],) * extra + tuple(config.iterations))  # fmt: skip


def _layout(model: FaceModel) -> ParamLayout:
    return ParamLayout(model.num_animation, NUM_ILLUMINATION_TERMS)


def animation_bounds(model: FaceModel, config: TrackerConfig, state: TrackerState) -> tuple[Tensor, Tensor]:
    """The bounds of the animation units in a step: the model's ranges ``(A,)`` (shared by the streams), or, with
    :attr:`TrackerConfig.expression_range_from_start` and the state's :attr:`TrackerState.anim_prior_mean` (the first
    fit's coefficients, the origin of :attr:`TrackResult.expression`), those ranges about it, ``(B, A)``: the
    expression, not the coefficient, is bounded by each unit's range.

    Returns:
        ``(lower, upper)`` in the model's dtype and device: ``(A,)`` or ``(B, A)``.
    """
    lo, hi = model.animation_ranges[:, 0], model.animation_ranges[:, 1]
    origin = state.anim_prior_mean
    if not config.expression_range_from_start or origin is None:
        return lo, hi
    origin = origin.detach().to(device=lo.device, dtype=lo.dtype)  # (bounds: constants of the solve, no gradient)
    return origin + lo, origin + hi


def parameter_bounds(
    model: FaceModel, config: TrackerConfig, x_prev: Tensor, layout: ParamLayout,
    animation: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    """The box bounds of a REFERENCE step's solve (:func:`reference_levels`): the animation units in the model's
    ranges (``model.animation_ranges``), or pinned to ``x_prev``'s where ``config.use_expression`` is False; the
    illumination pinned to 0 where ``config.use_illumination`` is False; pose and the rest unbounded.

    Args:
        model: the face model (its ``animation_ranges`` ``(A, 2)``).
        config: the tracker settings (``use_expression``, ``use_illumination``).
        x_prev: ``(B, P)`` the previous estimate (``state.params``), ``P = layout.size``.
        layout: the packed parameters' :class:`~torchface.tracker.ParamLayout`.
        animation: the animation units' ``(lower, upper)``, ``(A,)`` or ``(B, A)`` (:func:`animation_bounds`); None:
            the model's ranges.

    Returns:
        ``(lower, upper)``, each ``(B, P)`` in ``x_prev``'s dtype and device (``-inf`` / ``inf`` where unbounded).

    Example:
        >>> from torchface.appearance.illumination import NUM_ILLUMINATION_TERMS
        >>> from torchface.model import load_candide3
        >>> model = load_candide3()
        >>> layout = ParamLayout(model.num_animation, NUM_ILLUMINATION_TERMS)
        >>> lower, upper = parameter_bounds(model, TrackerConfig(), torch.zeros(1, layout.size), layout)
        >>> lower.shape, bool(torch.equal(upper[0, layout.animation], model.animation_ranges[:, 1]))
        (torch.Size([1, 22]), True)
        >>> bool(torch.isinf(lower[:, layout.translation]).all())
        True
    """
    B, P = x_prev.shape
    lower = torch.full((B, P), float("-inf"), dtype=x_prev.dtype, device=x_prev.device)
    upper = torch.full((B, P), float("inf"), dtype=x_prev.dtype, device=x_prev.device)
    if config.use_expression:
        lo, hi = (model.animation_ranges[:, 0], model.animation_ranges[:, 1]) if animation is None else animation
        lower[:, layout.animation] = lo.to(x_prev.dtype)
        upper[:, layout.animation] = hi.to(x_prev.dtype)
    else:
        lower[:, layout.animation] = x_prev[:, layout.animation]
        upper[:, layout.animation] = x_prev[:, layout.animation]
    if not config.use_illumination:
        lower[:, layout.illumination] = 0.0
        upper[:, layout.illumination] = 0.0
    return lower, upper


def fail_templates(templates: Sequence[Template], failed: Tensor) -> list[Template]:
    """``templates`` (one per pyramid level) without the points of the streams ``failed`` ``(B,)`` bool, whose
    initialisation FAILED: such a stream has no valid start to track from (a fit without a pose, too few template
    points, a face too small), so that each later step FAILS for want of points and holds its estimate, instead of
    tracking from that start (collinear landmarks: CONVERGED at confidence 0.99 on the next frames, 620 mm away
    and drifting). Initialise the stream again (template management: a detector's landmarks) to start it."""
    keep = ~failed.to(templates[0].valid.device).unsqueeze(-1)
    return [replace(tpl, valid=tpl.valid & keep) for tpl in templates]


def check_given_fit(model: FaceModel, fit: LandmarkFit, batch: int) -> None:
    """Refuse a :class:`~torchface.tracker.fit.LandmarkFit` handed to :func:`initialise` that is not ``batch``
    streams' fit with ``model``: every field's shape (``rotation (B, 3, 3)``, ``shape_coeffs (B, S)``,
    ``anim_coeffs (B, A)``, ...), a ``ValueError`` naming those that differ. A fit of another batch said "got batch
    3" for one stream's fit without its batch dimension (``fit.select(b)``, its rotation's 3 rows), and one made with
    another model (other animation units) was a bare RuntimeError of tensor sizes from inside."""
    want = {
        "rotation": (batch, 3, 3), "axis_angle": (batch, 3), "translation": (batch, 3),
        "shape_coeffs": (batch, model.num_shape), "anim_coeffs": (batch, model.num_animation), "rms_px": (batch,),
        "status": (batch,),
    }  # fmt: skip
    shapes = {n: tuple(v.shape) if isinstance(v, Tensor) else type(v).__name__ for n, v in vars(fit).items()}
    wrong = [n for n in want if shapes.get(n) != want[n]]
    if not wrong:
        return
    rotation = shapes.get("rotation")
    if rotation == (3, 3):  # (its 3 rows were read as the batch: "got batch 3")
        raise ValueError(f"fit must be a LandmarkFit of batch {batch}, got one stream's fit without its batch "
                         "dimension, rotation (3, 3) (LandmarkFit.select of an int drops it; fit.select([b]) keeps "
                         "it)")  # fmt: skip
    if not isinstance(rotation, tuple) or len(rotation) != 3:
        raise ValueError(f"fit must be a LandmarkFit of batch {batch}, got rotation {rotation}: (B, 3, 3) wanted")
    if rotation[0] != batch:  # (said "got LandmarkFit", the right type)
        raise ValueError(f"fit must be a LandmarkFit of batch {batch}, got batch {rotation[0]}")
    units = all(n in ("shape_coeffs", "anim_coeffs") and shapes.get(n, ())[:1] == (batch,) for n in wrong)
    raise ValueError(
        f"fit must be a LandmarkFit of batch {batch} for this model ({model.num_shape} shape and "
        f"{model.num_animation} animation units), got " + ", ".join(f"{n} {shapes.get(n)} for {want[n]}" for n in wrong)
        + (": a fit made with another model? (fit_landmarks with the tracker's model)" if units else "")
    )


@full_precision
def initialise(
    model: FaceModel,
    config: TrackerConfig,
    frames: Tensor,
    landmarks_px: Tensor,
    intrinsics: Intrinsics,
    weights: Tensor | None = None,
    *,
    fit: LandmarkFit | None = None,
) -> tuple[TrackerState, TrackResult]:
    """Fit the first frame from landmarks (Eq. 2) and build the templates (Eq. 3-9).

    Args:
        model: the face model.
        config: :class:`TrackerConfig`.
        frames: ``(B, 3, H, W)`` (or gray ``(B, 1, H, W)``) first frames, float in [0, 1].
        landmarks_px: ``(B, K, 2)`` the model's landmarks in pixels (a NaN row = missing; an infinite coordinate or
            one NaN alone is refused: :func:`~torchface.tracker.fit.check_landmark_values`). A stream with fewer than
            :data:`~torchface.tracker.fit.MIN_FIT_LANDMARKS` (4) of positive weight (all NaN: no face found) fails
            alone, FAILED at :func:`~torchface.tracker.fit.fit_landmarks`' placeholder pose.
        intrinsics: camera of ``frames``.
        weights: ``(B, K)`` landmark confidences ``>= 0`` (0 = ignore; their scale counts against the fit's priors:
            :func:`~torchface.tracker.fit.fit_landmarks`) or None; NaN, infinite and negative ones are refused.
        fit: the first frames' fit when already made (batch ``B``; e.g. refined by
            :func:`~torchface.tracker.lookahead.lookahead_fit`); None fits the landmarks.

    Returns:
        The state and the first frame's result. A stream whose initialisation FAILED (its fit holds no pose, fewer
        than ``config.min_points`` template points, a face narrower than ``config.min_face_width_px``) keeps no
        template points (:func:`fail_templates`; ``num_points`` 0): each later :func:`track_step` FAILS and holds
        its estimate, at confidence 0, until it is initialised again (template management keeps it LOST until a
        detector starts it). The result's ``start_failure`` ``(B,)`` says why (:class:`StartFailure`: NONE where
        the stream started).
    """
    landmarks_px = widen_half_landmarks(landmarks_px)  # (float16 / bfloat16: warned of once, here)
    check_initialise_inputs(model, config, frames, landmarks_px, intrinsics, weights)
    frames = frames.to(dtype=model.dtype, device=model.device)
    if fit is None:
        fit = fit_landmarks(model, landmarks_px, intrinsics, weights, config=config.fit)
    elif not isinstance(fit, LandmarkFit):
        raise TypeError(f"fit must be a LandmarkFit of batch {frames.shape[0]} or None, got {type(fit).__name__}")
    else:  # in the model's dtype and device, as fit_landmarks returns it
        check_given_fit(model, fit, frames.shape[0])
        fit = fit.to(model.device, model.dtype)
    layout = _layout(model)
    B = frames.shape[0]
    x = torch.zeros(B, layout.size, dtype=model.dtype, device=model.device)
    x[:, layout.rotation] = fit.axis_angle
    x[:, layout.translation] = fit.translation
    x[:, layout.animation] = fit.anim_coeffs
    pyramid = gray_pyramid(frames, config.num_levels)
    templates = []
    for level, gray in enumerate(pyramid):
        intr = level_intrinsics(intrinsics, level, gray.shape[-2], gray.shape[-1])
        n = min(config.max_points, gray.shape[-2] * gray.shape[-1])
        templates.append(
            build_template(
                model, fit.shape_coeffs, fit.anim_coeffs, fit.rotation, fit.translation, gray, intr,
                max_points=n, gradient_threshold=config.gradient_threshold,
                expression_priority=config.expression_priority,
                expression_quota=int(config.expression_quota * n) if level == 0 else 0,  # the finest level's
                seed=config.selection_seed, backend=config.backend,
            )
        )
    no_pose = fit.status == int(SolveStatus.FAILED)
    lm = landmarks_px.detach().to(dtype=model.dtype, device=model.device)
    _, w = landmark_targets(lm, None if weights is None else weights.detach().to(lm))
    missing = no_pose & ((w > 0).sum(-1) < MIN_FIT_LANDMARKS)  # (no face found: _missing_fit's placeholder)
    # Landmarks that look normalised (beside streams in pixels: check_initialise_inputs refuses a batch with none)
    # fail their stream whatever the fit made of them, as a detector's restart fails them: they were given only
    # where the fit failed, and a fit that held (a fit given, e.g. lookahead_fit's) started a face about a pixel
    # wide, or failed for a later reason (FACE_TOO_SMALL, TOO_FEW_POINTS). (Never with MIN_FIT_LANDMARKS missing:
    # normalised landmarks are at least that many, so the two codes never meet here.)
    normalised = normalised_streams(lm, frames.shape[-1], frames.shape[-2], w)
    small = too_small(model, config, fit.translation, intrinsics)
    start_failure = start_failure_codes([
        (StartFailure.NO_LANDMARKS, missing), (StartFailure.NORMALISED_LANDMARKS, normalised),
        (StartFailure.NO_POSE, no_pose), (StartFailure.FACE_TOO_SMALL, small),
        (StartFailure.TOO_FEW_POINTS, templates[0].num_points < config.min_points),
    ])  # fmt: skip
    failed = start_failure != int(StartFailure.NONE)
    status = torch.where(failed, int(TrackStatus.FAILED), int(TrackStatus.CONVERGED))
    if bool(failed.any()):
        templates = fail_templates(templates, failed)
    state = TrackerState(x, fit.shape_coeffs, tuple(templates), intrinsics, 1, anim_prior_mean=fit.anim_coeffs.clone())
    n_pts = templates[0].num_points
    conf = torch.exp(-fit.rms_px / 5.0) * ~failed
    result = _result(
        model, layout, x, status, torch.zeros_like(status), torch.zeros_like(fit.rms_px), n_pts, conf, fit.anim_coeffs
    )
    return state, replace(result, start_failure=start_failure)


def _result(
    model: FaceModel, layout: ParamLayout, x: Tensor, status: Tensor, iterations: Tensor, cost: Tensor,
    num_points: Tensor, confidence: Tensor, neutral: Tensor | None,
) -> TrackResult:
    """The result of estimate ``x (B, P)``; ``neutral``: ``(B, A)`` the first frame's fitted animation
    coefficients (None: zero), which :attr:`TrackResult.expression` is measured from.

    The fields are views of a copy of ``x``, which is the new state's ``params``: a caller modifying a result in
    place (``result.translation += offset``) moved the head the next step starts from."""
    aa, t, alpha, light = layout.split(x.clone())
    R = axis_angle_to_matrix(aa)
    expression = alpha if neutral is None else alpha - neutral.to(alpha.dtype)
    return TrackResult(
        rotation=R, axis_angle=aa, translation=t, ypr_deg=matrix_to_euler(R), anim_coeffs=alpha,
        anim_names=model.animation_names, expression=expression, facs=model.facs_values(expression),
        facs_names=model.facs_names,
        illumination=light, illumination_names=ILLUMINATION_TERM_NAMES, status=_of_dtype(status, torch.int64),
        iterations=_of_dtype(iterations, torch.int64), cost=cost, num_points=num_points, confidence=confidence,
    )


def step_grad_inputs(
    model: FaceModel, config: TrackerConfig, state: TrackerState, frames: Tensor, *args: object, **kwargs: object
) -> tuple[object, ...]:
    """The tensors of a step's arguments through which a caller could want gradients (:func:`track_step`,
    :func:`~torchface.tracker.managed.managed_step`; see :mod:`torchface.tracker.inference`): the frames, the
    state's parameters and shape, and its templates' values (made from first frames that require grad)."""
    templates = getattr(state, "templates", None) or ()
    return (frames, getattr(state, "params", None), getattr(state, "shape_coeffs", None)) + tuple(
        getattr(tpl, name, None) for tpl in templates for name in ("points", "basis", "normals", "intensity")
    )


def _wants_grad(model: FaceModel, config: TrackerConfig, state: "TrackerState", frames: Tensor) -> bool:
    """Whether a step is asked for gradients: grad mode on and one of :func:`step_grad_inputs` requires grad."""
    return torch.is_grad_enabled() and any(
        isinstance(v, Tensor) and v.requires_grad for v in step_grad_inputs(model, config, state, frames)
    )


def check_state_levels(config: TrackerConfig, state: "TrackerState") -> None:
    """Refuse a config whose pyramid has another number of levels than the state's templates."""
    if len(state.templates) != config.num_levels:
        raise ValueError(
            f"the state holds templates for {len(state.templates)} pyramid levels, the config has num_levels = "
            f"{config.num_levels}: track with the config the state was initialised with (or initialise again)"
        )


def check_step_inputs(model: FaceModel, config: "TrackerConfig", state: "TrackerState", frames: Tensor) -> None:
    """The checks of a step (:func:`track_step`, :func:`~torchface.tracker.managed.managed_step`): ``frames``
    ``(B, 3, H, W)`` in [0, 1] (:func:`check_frames`, every :data:`STEP_VALUE_ROW_STRIDE`-th row's values), one
    per stream of ``state``, whose pyramid ``config`` has (:func:`check_state_levels`) and whose model ``model`` is
    (:func:`check_state_model`), and neither under ``torch.func.vmap`` nor forward-mode AD
    (:func:`~torchface._compiling.check_reverse_mode`: reverse mode works, ``torch.func.grad`` included)."""
    check_api_types(model, config, state, with_state=True)
    check_reverse_mode("a tracking step", frames, state.params, state.shape_coeffs)
    check_frames(frames, state.intrinsics, values=True, row_stride=STEP_VALUE_ROW_STRIDE)
    if frames.shape[0] != state.params.shape[0]:
        # (a stream added or dropped mid-run was told no more than the count)
        raise ValueError(f"expected {state.params.shape[0]} frames (one per stream), got {frames.shape[0]}: the "
                         "streams are those initialised (select(index) keeps some of them, initialise starts "
                         "another batch)")  # fmt: skip
    check_state_levels(config, state)
    check_state_model(model, state)


def check_state_model(model: FaceModel, state: "TrackerState") -> None:
    """Refuse a model with another number of shape or animation units than the state's (a state made with another
    model: a tensor-size RuntimeError deep in the solver, or a shape-coefficient error naming the model alone), or
    in another dtype or on another device (a model or layer moved after the state was made: the error said to
    convert the model)."""
    kept = (state.shape_coeffs.dtype, state.shape_coeffs.device)
    if kept != (model.dtype, model.device):
        raise TypeError(
            f"the state is {kept[0]} on {kept[1]}, the model {model.dtype} on {model.device}: track a state with "
            "the model in the dtype and device it was initialised with (or initialise again)"
        )
    got = (state.shape_coeffs.shape[-1], state.params.shape[-1] - 6 - NUM_ILLUMINATION_TERMS)
    if got != (model.num_shape, model.num_animation):
        raise ValueError(
            f"the state was made with a model of {got[0]} shape and {got[1]} animation units, this model has "
            f"{model.num_shape} and {model.num_animation}: track with the model the state was initialised with"
        )


@full_precision
@without_autograd(step_grad_inputs)
def track_step(
    model: FaceModel,
    config: TrackerConfig,
    state: TrackerState,
    frames: Tensor,
    *,
    conservative: Tensor | None = None,
    near_template: Tensor | None = None,
) -> tuple[TrackerState, TrackResult]:
    """Track one frame per stream: one joint minimisation over pose, expression and light (Eq. 20).

    Args:
        model: the face model used at initialisation.
        config: :class:`TrackerConfig`.
        state: from :func:`initialise` or the previous step.
        frames: ``(B, 3, H, W)`` (or gray ``(B, 1, H, W)``) the next frame of each stream, float in [0, 1].
        conservative: optional ``(B,)`` bool, streams whose refinement pass uses ``expression_prior_precision``
            instead of ``refine_prior_precision``, and whose expression prior stays Gaussian
            (no :attr:`TrackerConfig.expression_sparsity`) in both passes; template management passes its lost
            streams and recovery candidates. The reference solver ignores it.
        near_template: optional ``(B,)`` bool, streams whose pose is near the pose their templates were built at
            (template management passes those within ``config.template.clean_radius_deg`` of their mosaic
            entry's); on a clean frame (``config.template.clean_rejected_fraction``) their finest pose level uses
            a Huber loss instead of Tukey's. None: ``config.robust`` throughout.

    Returns:
        The new state and the frame's :class:`TrackResult`. A FAILED sample keeps its previous parameters
        and never produces NaN.

    Runs in inference mode (:mod:`torchface.tracker.inference`) unless ``frames`` or the state's parameters or
    templates (:func:`initialise` from first frames that require grad) require grad with grad mode on; the tensors
    handed back are normal tensors. The state's ``params`` then carry the frame's graph on to the next step
    (:meth:`TrackerState.detach` between frames whose losses stand alone).
    """
    check_step_inputs(model, config, state, frames)
    return _checked_step(model, config, state, frames, conservative, near_template)


@full_precision
@without_autograd(step_grad_inputs)
def track_checked_step(
    model: FaceModel,
    config: TrackerConfig,
    state: TrackerState,
    frames: Tensor,
    *,
    conservative: Tensor | None = None,
    near_template: Tensor | None = None,
) -> tuple[TrackerState, TrackResult]:
    """:func:`track_step` of inputs its caller has checked with :func:`check_step_inputs` (the same result):
    :func:`~torchface.tracker.managed.managed_step`, which checks them before its own work. The check reads every
    16th row of every frame (:data:`STEP_VALUE_ROW_STRIDE`), about 1.5 ms per step at 32 streams of 640x480 (one
    thread), frames that have just come from memory; checked twice, it was about 6% of template management's
    cost there."""
    return _checked_step(model, config, state, frames, conservative, near_template)


def _checked_step(
    model: FaceModel, config: TrackerConfig, state: TrackerState, frames: Tensor, conservative: Tensor | None,
    near_template: Tensor | None,
) -> tuple[TrackerState, TrackResult]:
    """:func:`track_step` after :func:`check_step_inputs`."""
    frames = frames.to(dtype=model.dtype, device=model.device)
    for name, mask in (("conservative", conservative), ("near_template", near_template)):
        if mask is not None and (
            not isinstance(mask, Tensor) or mask.dtype != torch.bool or tuple(mask.shape) != (frames.shape[0],)
        ):
            got = f"{mask.dtype} {tuple(mask.shape)}" if isinstance(mask, Tensor) else type(mask).__name__
            raise ValueError(f"{name} must be a ({frames.shape[0]},) bool tensor, got {got}")
    if config.solver is TrackSolver.FAST:
        return _track_step_fast(model, config, state, frames, conservative, near_template)
    layout = _layout(model)
    # Unrolled where a gradient is wanted, as the fast solver is (the same iterations; without it the estimates
    # were constants: no gradient reached the frames or the previous estimate).
    differentiable = _wants_grad(model, config, state, frames)
    solvers = [
        SolverConfig(max_iterations=config.iterations[config.num_levels - 1 - level], differentiable=differentiable)
        for level in reversed(range(config.num_levels))
    ]
    x, last = reference_levels(model, config, state, frames, state.params, solvers, near_template=near_template)
    # Finest-level diagnostics at the final estimate.
    r, _, valid = last.residual_fn(x)
    _, cam, _ = warp_points(last.template, layout, x)
    sampled, _ = sample_at_pixels(last.image[:, :1], project_points(cam, last.intrinsics))
    status = last.result.status
    solver_failed = status == int(SolveStatus.FAILED)
    return _finish(
        model, config, layout, state, last.template, x, r, valid, sampled[..., 0], solver_failed, status,
        last.result.iterations,
    )  # fmt: skip


@dataclass(frozen=True, eq=False)
class ReferenceLevel:
    """The finest level solved by :func:`reference_levels`: its template, gray image with gradients
    ``(B, 3, h, w)``, camera, residual function ``p -> (r, J, valid)`` (:func:`frame_residuals` of that level)
    and the solver's result there."""

    template: Template
    image: Tensor
    intrinsics: Intrinsics
    residual_fn: Callable[[Tensor], tuple[Tensor, Tensor, Tensor]]  # a ResidualFn whose valid is a tensor
    result: SolveResult


def _clean_rule(config: TrackerConfig, near_template: Tensor | None) -> bool:
    """Whether the clean-frame rule of :attr:`~torchface.template.management.TemplateConfig.clean_radius_deg`
    applies: streams near their template's pose given (and one of them is), a Tukey loss, a positive rejection
    threshold, two levels. With no stream near, no stream is clean and the rule's robust scale and rejection count
    (0.07 ms per frame at one stream) would change nothing."""
    return (
        near_template is not None and config.robust is RobustKind.TUKEY
        and config.template.clean_rejected_fraction > 0 and config.num_levels > 1 and bool(near_template.any())
    )  # fmt: skip


def _clean_streams(
    config: TrackerConfig, near_template: Tensor, robust: RobustLoss, r: Tensor, valid: Tensor, scale: Tensor
) -> Tensor:
    """``(B, 1)`` bool: the streams ``near_template (B,)`` whose residuals ``r (B, N)`` ``robust`` rejects (zero
    weight at ``scale (B, 1)``) fewer than ``config.template.clean_rejected_fraction`` of the valid ones."""
    rejected = ((robust.weight(r, scale) == 0) & valid).sum(-1)
    clean = rejected / valid.sum(-1).clamp_min(1) < config.template.clean_rejected_fraction
    return (clean & near_template.to(clean.device)).unsqueeze(-1)


def _native_clean_streams(
    config: TrackerConfig, near_template: Tensor, robust: RobustLoss, r: Tensor, valid: Tensor, floor: float
) -> Tensor | None:
    """:func:`_clean_streams` at :func:`~torchface.tracker.fast.robust_scale_of`'s scale of ``r (B, N)`` over ``valid``
    (floored at ``floor``), by the native kernel (``management.h``: the same arithmetic, so the same streams), or
    None where it cannot run (:func:`~torchface.backend.use_native`; torch's default dtype not float32 or float64,
    which the rejected share is computed in). The torch code's scale and count were about 25 operations, 40
    microseconds a call at one stream alone and about 115 inside a step, in 40% of benchmark.py's managed steps."""
    default = torch.get_default_dtype()
    if (default not in (torch.float32, torch.float64) or not near_template.is_cpu
            or not use_native(config.backend, (r,), "clean-frame rule")):  # fmt: skip
        return None
    B, N = r.shape
    if N == 0:  # (no residuals: the torch code's, whatever it does there; not met in a step, which has points)
        return None
    r, valid, near = r.contiguous(), valid.contiguous(), near_template.contiguous()  # (near: (B,) bool, checked)
    clean = torch.empty(B, 1, dtype=torch.bool)
    prob = _native.CleanProblem(
        B=B, N=N, share_double=int(default == torch.float64), scale_floor=floor,
        min_scale=torch.finfo(r.dtype).tiny ** 0.5, c=cast(float, robust.c),  # (_as_scale's floor; c: set, a float)
        fraction=config.template.clean_rejected_fraction, r=r.data_ptr(), valid=valid.data_ptr(),
        near=near.data_ptr(), out_clean=clean.data_ptr(),
    )  # fmt: skip
    _native.run("clean_streams", r.dtype == torch.float64, prob, B, torch.get_num_threads())
    return clean


def _finest_loss(robust: RobustLoss, clean: Tensor | None) -> RobustLoss | SwitchedRobustLoss:
    """The finest pose level's loss: Huber with ``robust``'s constant for the ``clean (B, 1)`` streams, ``robust``
    for the others (:attr:`~torchface.template.management.TemplateConfig.clean_radius_deg`); ``robust`` when
    ``clean`` is None."""
    if clean is None:
        return robust
    huber = RobustLoss(RobustKind.HUBER, robust.c, min_scale=robust.min_scale)
    n = int(clean.sum())
    if n == clean.shape[0]:
        return huber
    return robust if n == 0 else SwitchedRobustLoss(robust, huber, clean)


def reference_levels(
    model: FaceModel,
    config: TrackerConfig,
    state: TrackerState,
    frames: Tensor,
    start: Tensor,
    solvers: Sequence[SolverConfig],
    *,
    near_template: Tensor | None = None,
) -> tuple[Tensor, ReferenceLevel]:
    """The reference path's coarse-to-fine solve of Eq. 20 over the ``len(solvers)`` finest pyramid levels.

    Per level: :func:`frame_residuals` of the state's template on the frame's gray pyramid level, the light
    basis with the normals rotated by the previous estimate (``state.params``), z-buffer visibility at the
    previous estimate (when ``config.zbuffer_visibility``, a constant mask), the animation units boxed to the
    model's ranges (:func:`parameter_bounds`), the expression prior and IRLS weights of ``config.robust`` with the
    level's scale floor. A sample whose solve fails keeps the previous level's estimate. Shared by
    :func:`track_step` (``config.solver`` REFERENCE) and the differentiable unrolled layer of ``training_hooks``;
    everything that depends on ``frames`` and ``start`` stays in the autograd graph when the solvers are
    differentiable.

    Args:
        frames: ``(B, C, H, W)`` in ``[0, 1]`` at the state's size; start: ``(B, P)`` initial parameters.
        solvers: one :class:`SolverConfig` per level, coarsest first; ``len(solvers)`` in
            ``[1, config.num_levels]``.
        near_template: as in :func:`track_step` (the finest level's loss on clean frames); None: Tukey.

    Returns:
        ``(B, P)`` the estimate and the finest level's :class:`ReferenceLevel`.
    """
    if not 1 <= len(solvers) <= config.num_levels:
        raise ValueError(f"need 1 to {config.num_levels} level solvers, got {len(solvers)}")
    layout = _layout(model)
    pyramid = gray_pyramid(frames, config.num_levels)
    with torch.no_grad():
        previous = state.params.detach()
        if config.zbuffer_visibility:
            vis_level = min(1, config.num_levels - 1)
            g = pyramid[vis_level]
            masks = _visibility_at(model, replace(state, params=previous), layout, vis_level, g.shape[-2], g.shape[-1])
        else:
            masks = [t.valid for t in state.templates]
        R_prev = axis_angle_to_matrix(previous[:, layout.rotation])
        lower, upper = parameter_bounds(model, config, previous, layout, animation_bounds(model, config, state))
    prior = torch.zeros(layout.size, dtype=model.dtype, device=model.device)
    prior_mean = prior_mean_vector(config, state, layout)
    if config.use_expression:
        units = expression_prior(
            config, config.expression_prior_precision, previous[:, layout.animation],
            None if prior_mean is None else prior_mean[:, layout.animation],
        )  # fmt: skip
        if isinstance(units, Tensor):  # (B, A): per stream and unit
            prior = prior.expand(previous.shape[0], -1).clone()
        prior[..., layout.animation] = units
    x = start
    last = None
    clean = None  # (B, 1): the streams whose finest level uses Huber (TemplateConfig.clean_radius_deg)
    for level, solver in zip(reversed(range(len(solvers))), solvers):
        gray = pyramid[level]
        intr = level_intrinsics(state.intrinsics, level, gray.shape[-2], gray.shape[-1])
        image = image_with_gradients(gray)
        tpl = state.templates[level]
        light_basis = illumination_basis(tpl.intensity, torch.einsum("bij,bnj->bni", R_prev, tpl.normals))
        mask = masks[level]

        def residual_fn(p: Tensor, tpl=tpl, image=image, intr=intr, light_basis=light_basis, mask=mask):
            return frame_residuals(p, layout, tpl, image, intr, light_basis, mask)

        robust = None
        if config.robust is not RobustKind.NONE:
            robust = RobustLoss(config.robust, config.robust_c, min_scale=scale_floor(config, level))
        res = least_squares(
            residual_fn, x, solver, lower=lower, upper=upper, prior_precision=prior, prior_mean=prior_mean,
            robust=_finest_loss(robust, clean) if level == 0 and robust is not None else robust,
        )  # fmt: skip
        x = torch.where(res.failed.unsqueeze(-1), x, res.params)
        if level == 1 and robust is not None and near_template is not None and _clean_rule(config, near_template):
            with torch.no_grad():  # the level's residuals and robust scale at its estimate, as least_squares has them
                r, _, valid = residual_fn(x.detach())
                valid = valid & torch.isfinite(r)
                r = torch.where(valid, r, torch.zeros_like(r))
                scale = robust_scale(r, valid).clamp_min(robust.min_scale).unsqueeze(1)
                clean = _clean_streams(config, near_template, robust, r, valid, scale)
        last = ReferenceLevel(tpl, image, intr, residual_fn, res)
    assert last is not None
    return x, last


def _posed_vertices(model: FaceModel, state: TrackerState, layout: ParamLayout, R: Tensor | None = None) -> Tensor:
    """``(B, V, 3)`` camera-frame vertices of the model at the state's parameters (``R (B, 3, 3)``: their
    rotation, when the caller has it)."""
    aa, t, alpha, _ = layout.split(state.params)
    R = axis_angle_to_matrix(aa) if R is None else R
    return torch.matmul(model.deform(state.shape_coeffs, alpha), R.transpose(1, 2)) + t.unsqueeze(1)


def clamp_projection(uv: Tensor, width: int, height: int) -> Tensor:
    """Projected points ``(..., 2)`` made finite (NaN to 0) and kept within one image size of the image on each
    axis (u in ``[-W, 2W]``, v in ``[-H, 2H]``), for the boxes around a projected face."""
    uv = torch.nan_to_num(uv)
    return torch.stack([uv[..., 0].clamp(-width, 2 * width), uv[..., 1].clamp(-height, 2 * height)], dim=-1)


def _round_down(x: Tensor, q: int) -> Tensor:
    """Round int64 ``x`` down to a multiple of the power of two ``q`` (two's complement: also below zero)."""
    return x & -q


def face_crop(
    model: FaceModel, state: TrackerState, layout: ParamLayout, config: TrackerConfig, verts: Tensor | None = None
) -> tuple[Tensor, int, int]:
    """Crop around every stream's face at the previous estimate: offsets ``(B, 2)`` (x0, y0) and size (h, w).

    One size for the batch (the largest face box, enlarged by ``config.crop_margin``); offsets are multiples
    of ``2**(num_levels - 1)`` so every pyramid level of the crop is pixel-aligned with the full image's.
    ``verts``: the ``(B, V, 3)`` camera-frame vertices at that estimate, when the caller has them.
    """
    H, W = state.intrinsics.height, state.intrinsics.width
    verts = _posed_vertices(model, state, layout) if verts is None else verts
    uv = project_points(verts, state.intrinsics)
    uv = clamp_projection(uv, W, H)
    lo, hi = uv.amin(1), uv.amax(1)  # (B, 2)
    size = (hi - lo).amax(-1)  # (B,)
    q = 2 ** (config.num_levels - 1)
    side = int(torch.ceil(size.max() * (1 + 2 * config.crop_margin) + MIN_CROP_PX).item()) if size.numel() else W
    # (a level pyr_down halves has 3 pixels a side or more: a tiny face with TrackerConfig(num_levels=8) crashed)
    side = max(side, 3 * 2 ** (config.num_levels - 2))
    side = ((side + q - 1) // q) * q
    cw, ch = min(W, side), min(H, side)
    centre = 0.5 * (lo + hi)
    x0 = _round_down(torch.round(centre[:, 0] - cw / 2).long(), q).clamp(0, (W - cw) // q * q)
    y0 = _round_down(torch.round(centre[:, 1] - ch / 2).long(), q).clamp(0, (H - ch) // q * q)
    return torch.stack([x0, y0], dim=-1), ch, cw


def crop_windows(images: Tensor, offsets: Tensor, height: int, width: int) -> Tensor:
    """``(B, C, H, W)`` images -> ``(B, C, height, width)`` windows whose top-left pixels are ``offsets (B, 2)``
    int64 ``(x0, y0)`` (exact copies; every window must lie inside its image).

    One ``index_select`` of whole window rows for the batch: the images' storage is viewed (``as_strided``) as
    the ``width``-long runs starting at every element, and the ``B * C * height`` runs that are window rows are
    selected. Each row is one contiguous copy, where a flat ``gather`` of every pixel reads an int64 index per
    value: measured 4 times faster at B = 1 (0.15 against 0.64 ms for a 480x496 window of a 640x480 RGB frame,
    2 threads) and 1.7 times at B = 32 (advanced indexing was 6 times slower than the gather).
    """
    B, C, H, W = images.shape
    flat = images.contiguous().reshape(-1)
    runs = flat.as_strided((flat.numel() - width + 1, width), (1, 1))
    dev = images.device
    plane = (torch.arange(B, device=dev)[:, None] * C + torch.arange(C, device=dev)) * H  # (B, C) first row of each
    rows = plane[:, :, None] + (offsets[:, None, 1:2] + torch.arange(height, device=dev))  # (B, C, height)
    start = (rows * W + offsets[:, None, 0:1]).reshape(-1)
    return runs.index_select(0, start).reshape(B, C, height, width)


def _crop_gray(
    frames: Tensor, offsets: Tensor, ch: int, cw: int, rows: Tensor | None = None, out: Tensor | None = None
) -> Tensor:
    """``(B, C, H, W)`` frames -> ``(B, 1, ch, cw)`` gray crops at per-stream offsets ``(B, 2)`` int64 ``(x0, y0)``
    (of the frames ``rows (B,)`` int64 when given), written into ``out`` when given (without autograd).

    Each stream's window of the colour frame is converted straight into its slot of one output (:func:`to_gray`
    with ``out=``; a loop over the streams, a few operations each): only the window's pixels are read, and no
    whole-frame gray image or crop copy is made. Converting whole frames and then cropping the gray ones cost
    2.5 times the memory traffic and its fresh pages at 128 streams.
    """
    C = frames.shape[1]
    if C == 1:
        crops = crop_windows(frames if rows is None else frames.index_select(0, rows), offsets, ch, cw)
        return crops if out is None else out.copy_(crops)
    B = offsets.shape[0]
    at = range(B) if rows is None else rows.tolist()
    windows = [frames[b : b + 1, :, y0 : y0 + ch, x0 : x0 + cw] for b, (x0, y0) in zip(at, offsets.tolist())]
    if torch.is_grad_enabled() and frames.requires_grad:  # out= does not support autograd: the same values, joined
        return torch.cat([to_gray(w) for w in windows])
    if out is None:
        out = torch.empty(B, 1, ch, cw, dtype=frames.dtype, device=frames.device)
    for b, w in enumerate(windows):
        to_gray(w, out=out[b : b + 1])
    return out


#: Streams per chunk of :func:`gray_crop_pyramid`: each chunk's crop and pyramid are built before the next, so that
#: the filter's padded copies and row passes (about 4 MB for 8 streams at 480x512) stay in the cache.
_PYRAMID_CHUNK: int = 8


class StepWorkspace:
    """Scratch memory that the steps of one batch of streams reuse: the step's large tensors that do not outlive it
    (the levels of its gray crop pyramid, the visibility's coverage and points, the finest level's Jacobian and
    light basis handed to the native solver).

    At 128 streams a step's pyramid takes about 170 MB (the finest level 126 MB at a 480x512 crop), more than
    glibc's largest automatic ``mmap`` threshold (32 MB), so without reuse every step maps it afresh and faults
    its pages in: measured at B = 128, 2 threads (``benchmark.py``'s frames), 245 ms per step, of which 82 ms in
    the pyramid, against 181 and 51 ms with the workspace (521 -> 708 frames/s; glibc's
    ``MALLOC_MMAP_THRESHOLD_=268435456`` in the environment, which keeps every large block, gave 775). The others
    (about 60 MB at 128 streams, each under 32 MB) were not mapped afresh, but freed together they left more free
    memory at the top of glibc's heap than its trim threshold (twice the largest block it has ``mmap``-ed and freed,
    about 40 MB there), which it gave back to the system and faulted in again at the next step: about 11000 page
    faults per step, none with them here (docs/speed.md).

    A :class:`TrackerState` holds one (``workspace``) and the states its steps make share it. A step borrows it
    for its duration; a step that finds it borrowed (another thread stepping a state that shares it) allocates
    its own, so concurrent steps never share buffers. The buffers only grow (with 25 % headroom, as the crop
    follows the faces), are normal tensors (usable in and out of inference mode), and go with the last state
    that holds them. Copies and pickles of a workspace are empty ones.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._buffers: dict[str, Tensor] = {}

    def acquire(self) -> bool:
        """Borrow the workspace: True when it was free (then :meth:`release` it), False when in use."""
        return self._lock.acquire(blocking=False)

    def release(self) -> None:
        """End a borrowing."""
        self._lock.release()

    def buffer(self, name: str, shape: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> Tensor:
        """A contiguous tensor of ``shape`` on the workspace's memory named ``name`` (one buffer per name: the
        tensor of the last call with that name is the same memory); its values are whatever the last use left."""
        n = math.prod(shape)
        buf = self._buffers.get(name)
        if buf is None or buf.numel() < n or buf.dtype != dtype or buf.device != device:
            with torch.inference_mode(False):  # a normal tensor: written in and out of inference mode
                buf = torch.empty(n + n // 4, dtype=dtype, device=device)
            self._buffers[name] = buf
        return buf[:n].view(shape)

    def buffers(
        self, shapes: Sequence[tuple[int, ...]], dtype: torch.dtype, device: torch.device, name: str = "pyramid"
    ) -> list[Tensor]:
        """:meth:`buffer` for each of ``shapes``, in order (named ``name`` and the position)."""
        return [self.buffer(f"{name}{i}", shape, dtype, device) for i, shape in enumerate(shapes)]

    def __contains__(self, name: object) -> bool:
        """Whether the workspace holds a buffer named ``name`` (:meth:`buffer`)."""
        return name in self._buffers

    def __deepcopy__(self, memo: dict) -> "StepWorkspace":
        return StepWorkspace()

    def __reduce__(self) -> tuple:
        return (StepWorkspace, ())

    def __repr__(self) -> str:
        return f"StepWorkspace({sum(b.numel() * b.element_size() for b in self._buffers.values()) / 2**20:.0f} MB)"


def gray_crop_pyramid(
    frames: Tensor, offsets: Tensor, ch: int, cw: int, num_levels: int, rows: Tensor | None = None,
    workspace: StepWorkspace | None = None, backend: Backend = Backend.AUTO,
) -> list[Tensor]:
    """``gray_pyramid(_crop_gray(frames, offsets, ch, cw, rows), num_levels)``, the same values bit for bit.

    RGB frames are done by the native kernel where ``backend`` allows it (:func:`~torchface.backend.use_native`;
    ``torchface/_native/gray_pyramid.h``): one stream's window, gray, and its levels one after the other, with the
    torch code's arithmetic. Measured at B = 128, 480x512 crops, 1 thread: 169 against 40 ms per step (the torch
    code's many passes each streamed the whole batch's level through memory).
    Otherwise, without autograd, more than :data:`_PYRAMID_CHUNK` streams are done a chunk of streams at a time,
    every level written into its slot of one output per level: the whole batch's padded copies and row passes (at
    B = 128 and a 480x512 crop, 130 and 65 MB for the finest level) otherwise go through memory once each.
    Measured at B = 128 with 2 threads on a slow host: 197 against 285-314 ms, or 104 against 176 ms with
    glibc's ``MALLOC_MMAP_THRESHOLD_=268435456``.

    Args:
        frames: ``(T, C, H, W)``; offsets: ``(B, 2)`` int64 ``(x0, y0)`` windows of size ``(ch, cw)`` inside the
            frames; rows: ``(B,)`` int64 the frames of the streams (None: ``T == B``, stream b's is frame b).
        workspace: a borrowed :class:`StepWorkspace` whose buffers hold the levels (None: new tensors);
            the levels returned are then its memory, valid until its next use.
        backend: :class:`~torchface.backend.Backend` (the native kernel or the torch code; the same values).

    Returns:
        ``num_levels`` tensors ``(B, 1, h_l, w_l)``, finest first (``h_0, w_0 = ch, cw``, each level half the
        previous, rounded down).
    """
    B = offsets.shape[0]
    native = _native_crop_pyramid(frames, offsets, ch, cw, num_levels, rows, workspace, backend)
    if native is not None:
        return native
    if B <= _PYRAMID_CHUNK or num_levels < 1 or (torch.is_grad_enabled() and frames.requires_grad):
        return gray_pyramid(_crop_gray(frames, offsets, ch, cw, rows), num_levels)
    levels = _pyramid_levels(frames, B, ch, cw, num_levels, workspace)
    for b0 in range(0, B, _PYRAMID_CHUNK):
        b1 = min(B, b0 + _PYRAMID_CHUNK)
        if rows is None:
            _crop_gray(frames[b0:b1], offsets[b0:b1], ch, cw, out=levels[0][b0:b1])
        else:
            _crop_gray(frames, offsets[b0:b1], ch, cw, rows[b0:b1], out=levels[0][b0:b1])
        for lv in range(1, num_levels):
            pyr_down(levels[lv - 1][b0:b1], out=levels[lv][b0:b1])
    return levels


def _pyramid_levels(
    frames: Tensor, B: int, ch: int, cw: int, num_levels: int, workspace: StepWorkspace | None
) -> list[Tensor]:
    """:func:`gray_crop_pyramid`'s outputs ``(B, 1, h_l, w_l)``, contiguous: the workspace's memory, or new tensors
    where it is None."""
    shapes = [(B, 1, ch, cw)]
    for _ in range(num_levels - 1):
        h, w = shapes[-1][-2:]
        shapes.append((B, 1, h // 2, w // 2))
    if workspace is None:
        return [torch.empty(shape, dtype=frames.dtype, device=frames.device) for shape in shapes]
    return workspace.buffers(shapes, frames.dtype, frames.device)


def _native_crop_pyramid(
    frames: Tensor, offsets: Tensor, ch: int, cw: int, num_levels: int, rows: Tensor | None,
    workspace: StepWorkspace | None, backend: Backend,
) -> list[Tensor] | None:
    """:func:`gray_crop_pyramid` by the native kernel, or None where it does not run (other than RGB frames, a
    level too small for :func:`pyr_down`, a window outside its frame or a row outside the frames: the torch code
    then gives its result or its error; or where ``backend`` rules the kernel out)."""
    if frames.dim() != 4 or frames.shape[1] != 3 or num_levels < 1 or offsets.dim() != 2 or ch < 1 or cw < 1:
        return None
    if num_levels > 1 and min(ch, cw) >> (num_levels - 2) < 3:  # pyr_down's smallest input: at least 3x3
        return None
    if not use_native(backend, (frames,), "gray pyramid"):
        return None
    T, _, H, W = frames.shape
    B = offsets.shape[0]
    offsets = offsets.to(torch.int64).contiguous()
    if rows is not None:
        rows = rows.to(torch.int64).contiguous()
    within = (offsets >= 0).all() & (offsets[:, 0] <= W - cw).all() & (offsets[:, 1] <= H - ch).all()
    if rows is not None and rows.numel():
        within = within & (rows.amin() >= 0) & (rows.amax() < T)
    if (rows is None and T < B) or (rows is not None and rows.shape != (B,)) or not bool(within):
        return None
    levels = _pyramid_levels(frames, B, ch, cw, num_levels, workspace)
    out = (ctypes.c_void_p * num_levels)(*(level.data_ptr() for level in levels))
    stride = frames.stride()
    prob = _native.PyramidProblem(
        B=B, height=ch, width=cw, levels=num_levels, stride_frame=stride[0], stride_channel=stride[1],
        stride_row=stride[2], stride_col=stride[3], frames=frames.data_ptr(),
        rows=None if rows is None else rows.data_ptr(), offsets=offsets.data_ptr(),
        out=ctypes.cast(out, ctypes.c_void_p),
    )  # fmt: skip
    _native.run("gray_pyramid", frames.dtype == torch.float64, prob, B, torch.get_num_threads())
    return levels


def _track_step_fast(
    model: FaceModel,
    config: TrackerConfig,
    state: TrackerState,
    frames: Tensor,
    conservative: Tensor | None = None,
    near_template: Tensor | None = None,
) -> tuple[TrackerState, TrackResult]:
    """:func:`track_step` with the fast solver (:mod:`torchface.tracker.fast`), in the state's
    :class:`StepWorkspace` when it has one (a batch of more than :data:`_PYRAMID_CHUNK` streams gets one) and no
    other step is using it, and not where a gradient is wanted: the graph saves the step's pyramid levels (the
    sampler's backward reads them), which the next step would write over (a backward through two steps' graphs, as
    a state that carries its graph on makes, failed: "modified by an inplace operation")."""
    if _wants_grad(model, config, state, frames):
        return _fast_step(model, config, state, frames, conservative, near_template, None)
    workspace = state.workspace
    if workspace is None and state.params.shape[0] > _PYRAMID_CHUNK:
        workspace = StepWorkspace()
        state = replace(state, workspace=workspace)
    if workspace is None or not workspace.acquire():
        return _fast_step(model, config, state, frames, conservative, near_template, None)
    try:
        return _fast_step(model, config, state, frames, conservative, near_template, workspace)
    finally:
        workspace.release()


def _fast_step(
    model: FaceModel,
    config: TrackerConfig,
    state: TrackerState,
    frames: Tensor,
    conservative: Tensor | None,
    near_template: Tensor | None,
    workspace: StepWorkspace | None,
) -> tuple[TrackerState, TrackResult]:
    """:func:`_track_step_fast`'s step, its crop pyramid in ``workspace`` (borrowed) when given."""
    layout = _layout(model)
    aa, t, alpha, light = (p.clone() for p in layout.split(state.params))
    R = axis_angle_to_matrix(aa)
    verts = _posed_vertices(model, state, layout, R)
    offsets, ch, cw = face_crop(model, state, layout, config, verts)
    crop = gray_crop_pyramid(frames, offsets, ch, cw, config.num_levels, workspace=workspace, backend=config.backend)
    masks = [t.valid for t in state.templates]
    visibility = None
    if config.zbuffer_visibility:
        cached = state.visibility
        if (cached is None or cached[0] is not state.templates
                or (state.frame_index - 1) % config.visibility_interval == 0):  # fmt: skip
            H, W = state.intrinsics.height, state.intrinsics.width
            vis_level = visibility_level(config.num_levels, H, W)
            h_l, w_l = H >> vis_level, W >> vis_level
            masks = _visibility_at(model, state, layout, vis_level, h_l, w_l, R, verts, config.backend, workspace)
            visibility = (state.templates, tuple(masks))
        else:
            masks, visibility = list(cached[1]), cached
    R_prev = R
    free, only = _free_masks(layout, config.use_expression, config.use_illumination)
    robust = None if config.robust is RobustKind.NONE else RobustLoss(config.robust, config.robust_c)
    lo, hi = animation_bounds(model, config, state)
    if lo.dim() == 2 and config.use_expression:
        # The start inside the bounds about the state's neutral: after a re-anchoring the coefficients go on from where
        # they were about the old one (the solver holds a unit outside its bounds where the gradient pushes it out).
        alpha = torch.maximum(torch.minimum(alpha, hi.to(alpha.dtype)), lo.to(alpha.dtype))
    if lo.dim() == 1 and lo.dtype == hi.dtype == alpha.dtype:
        # The model's (A,) ranges as (B, A) rows once a step: the native solver reads one row per stream, and made
        # them at each of its three or four calls (the torch code broadcasts either alike).
        lo, hi = (b.expand(alpha.shape).contiguous() for b in (lo, hi))
    alpha_mean = anim_prior_mean(config, state)
    intr = state.intrinsics
    clean = None  # (B, 1): the streams whose finest level uses Huber (TemplateConfig.clean_radius_deg)
    refine = config.refine_iterations > 0 and config.use_expression
    pose_prior = expression_prior(config, config.expression_prior_precision, alpha, alpha_mean, conservative)
    for level in reversed(range(config.num_levels)):
        s = 0.5**level
        img = crop[level]
        cam = LevelCamera(
            intr.fx * s, intr.fy * s, (intr.cx + 0.5) * s - 0.5, (intr.cy + 0.5) * s - 0.5,
            (offsets >> level).to(R.dtype), img.shape[-2], img.shape[-1],
        )
        tpl = state.templates[level]
        light_basis = _level_light_basis(tpl, R_prev, level, workspace)
        R, t, alpha, light, out = solve_level(
            tpl, img, cam, R, t, alpha, light, light_basis, masks[level],
            iterations=config.iterations[config.num_levels - 1 - level], free=free,
            alpha_lower=lo, alpha_upper=hi, alpha_prior=pose_prior, alpha_mean=alpha_mean,
            robust=_finest_loss(robust, clean) if level == 0 and robust is not None else robust,
            scale_floor=scale_floor(config, level),
            # A coarser level's result is refined by the next one: its convergence tolerance is as coarse as its
            # pixels (2**level full-resolution pixels). Its last step is still checked (without the check, a
            # sudden occluder's first frame went from 1.98 to 2.15 degrees in test_step's occlusion test).
            step_tolerance=tuple(v * 2**level for v in STEP_TOLERANCE),
            function_tolerance=config.function_tolerance * 2**level,
            keep_linearisation=level == 0 and refine,  # the refinement pass starts from it
            backend=config.backend, workspace=workspace,
        )
        if level == 1 and robust is not None and near_template is not None and _clean_rule(config, near_template):
            floor = scale_floor(config, level)
            clean = _native_clean_streams(config, near_template, robust, out.residual, out.valid, floor)
            if clean is None:
                scale = robust_scale_of(out.residual, out.valid, floor)  # as the level's IRLS
                clean = _clean_streams(config, near_template, robust, out.residual, out.valid, scale)
    if refine:
        refine_prior: float | Tensor = config.expression_prior_precision
        if config.refine_prior_precision is not None:
            refine_prior = config.refine_prior_precision
            if conservative is not None and bool(conservative.any()):
                refine_prior = torch.where(
                    conservative.to(R.device), config.expression_prior_precision, config.refine_prior_precision
                ).to(R.dtype)
        R, t, alpha, light, out = solve_level(
            tpl, img, cam, R, t, alpha, light, light_basis, masks[0],
            iterations=config.refine_iterations, free=only, alpha_lower=lo, alpha_upper=hi,
            alpha_prior=expression_prior(config, refine_prior, alpha, alpha_mean, conservative),
            alpha_mean=alpha_mean, robust=robust,
            scale_floor=config.refine_scale_floor, start=out.linearisation, constants=out.constants,
            function_tolerance=config.function_tolerance, keep_linearisation=False, backend=config.backend,
            workspace=workspace,
        )
    x = torch.cat([matrix_to_axis_angle(R), t, alpha, light], dim=-1)
    status = torch.where(out.converged, int(TrackStatus.CONVERGED), int(TrackStatus.MAX_ITERATIONS))
    new_state, result = _finish(
        model, config, layout, state, tpl, x, out.residual, out.valid, out.sampled, ~out.finite, status, out.iterations
    )
    return replace(new_state, visibility=visibility), result


@functools.lru_cache(maxsize=64)
def _free_masks(layout: ParamLayout, use_expression: bool, use_illumination: bool) -> tuple[Tensor, Tensor]:
    """The fast step's free-parameter masks ``(P,)`` bool, on the host (the solvers read them there): the level
    passes' (the animation and illumination parameters fixed where ``use_expression`` / ``use_illumination`` is
    False) and the refinement pass's (the pose fixed too). Cached per setting, made outside inference mode; the
    solvers only read them."""
    with torch.inference_mode(False):
        free = torch.ones(layout.size, dtype=torch.bool)
        if not use_expression:
            free[layout.animation] = False
        if not use_illumination:
            free[layout.illumination] = False
        only = free.clone()
        only[layout.rotation] = False
        only[layout.translation] = False
        return free, only


def _level_light_basis(tpl: Template, R: Tensor, level: int, workspace: StepWorkspace | None) -> Tensor:
    """``(B, N, L)`` :func:`illumination_basis` of a level's template ``tpl`` with its normals turned by ``R``
    ``(B, 3, 3)``. With a ``workspace`` (borrowed; a step given one asks for no gradient) the same values are written
    point-last into its buffer ``light_basis<level>``, a contiguous ``(B, L, N)`` returned as its transpose (valid
    until the workspace's next step): the layout the level solvers read (their negated copy is then one contiguous
    pass). At 128 streams, 1500 points, the basis's concatenation (three new 3.8 MB tensors a step, and a 0.8 MB
    column of ones each) wrote the five columns point by point and the native solver read them back transposed."""
    normals_cam = torch.matmul(tpl.normals, R.transpose(1, 2))
    intensity = tpl.intensity
    if workspace is None or intensity.dtype != normals_cam.dtype:
        return illumination_basis(intensity, normals_cam)
    B, N = intensity.shape
    out = workspace.buffer(f"light_basis{level}", (B, NUM_ILLUMINATION_TERMS, N), intensity.dtype, intensity.device)
    return illumination_basis(intensity, normals_cam, out=out.transpose(1, 2))


def _finish(
    model: FaceModel,
    config: TrackerConfig,
    layout: ParamLayout,
    state: TrackerState,
    tpl: Template,
    x: Tensor,
    residual: Tensor,
    valid: Tensor,
    sampled: Tensor,
    solver_failed: Tensor,
    status: Tensor,
    iterations: Tensor,
) -> tuple[TrackerState, TrackResult]:
    """Failure tests, confidence and the new state, from the finest level's final residuals (both solvers).

    Args:
        x: ``(B, P)`` the estimate; residual, valid, sampled: ``(B, N)`` at the finest level (``sampled`` the
            frame's gray values at the points); solver_failed: ``(B,)``; status: ``(B,)`` status codes before
            the failure tests; iterations: ``(B,)``.

    A sample fails when its solver did, when fewer than ``config.min_points`` points are valid, when the frame
    has no contrast there (black or textureless) or when the estimate is not finite; it keeps its previous
    parameters and gets confidence 0.
    """
    n_valid = valid.sum(-1)
    count = n_valid.clamp_min(1)
    vf = valid.to(x.dtype)
    r = torch.nan_to_num(torch.where(valid, residual, scalar(0.0, residual)))
    mean_i = (sampled * vf).sum(-1) / count
    std_i = (((sampled - mean_i.unsqueeze(-1)) ** 2 * vf).sum(-1) / count).sqrt()
    rms = ((r**2 * vf).sum(-1) / count).sqrt()
    failed = solver_failed | (n_valid < config.min_points) | (std_i < config.min_contrast) | ~torch.isfinite(x).all(-1)
    x = torch.where(failed.unsqueeze(-1), state.params, x)
    status = torch.where(failed, int(TrackStatus.FAILED), status)
    frac = n_valid.to(x.dtype) / tpl.num_points.clamp_min(1).to(x.dtype)
    confidence = frac.clamp(0, 1) * torch.exp(-((rms / 0.1) ** 2)) * (~failed)
    if config.min_face_width_px > 0:  # a face too small to track well (TrackerConfig.min_face_width_px)
        t = layout.split(x)[1]
        small = too_small(model, config, t, state.intrinsics)
        confidence = torch.where(small, torch.zeros_like(confidence), confidence)
    new_state = replace(state, params=x, frame_index=state.frame_index + 1)
    return new_state, _result(model, layout, x, status, iterations, rms, n_valid, confidence, state.anim_prior_mean)


#: The fast solver rasterizes its z-buffer visibility at the coarsest pyramid level whose sides are both at least this
#: many pixels (:func:`visibility_level`). At 64x48 with five levels the coarsest level is 4x3 pixels, where every
#: template point came out hidden (every frame FAILED); at 8x6, 7-15% of them did (16x12: under 1%). The standard
#: sizes' coarsest levels (160x120, 80x60 and 40x30 with three levels) are above it and keep their level.
VISIBILITY_MIN_SIDE_PX: int = 16


def visibility_level(num_levels: int, height: int, width: int) -> int:
    """The pyramid level the fast solver rasterizes its z-buffer visibility at, for ``height x width`` frames: the
    coarsest of the ``num_levels`` whose sides are both at least :data:`VISIBILITY_MIN_SIDE_PX` (``H >> level``,
    ``W >> level``), the finest (0) where none is.

    Example:
        >>> visibility_level(3, 120, 160), visibility_level(5, 48, 64), visibility_level(4, 720, 1280)
        (2, 1, 3)
    """
    level = num_levels - 1
    while level > 0 and min(height >> level, width >> level) < VISIBILITY_MIN_SIDE_PX:
        level -= 1
    return level


def _visibility_at(
    model: FaceModel, state: TrackerState, layout: ParamLayout, level: int, height: int, width: int,
    R: Tensor | None = None, verts: Tensor | None = None, backend: Backend = Backend.AUTO,
    workspace: StepWorkspace | None = None,
) -> list[Tensor]:
    """Z-buffer visibility of every level's template points at the previous estimate (one rasterization).

    ``R (B, 3, 3)`` and ``verts (B, V, 3)``: the rotation and camera-frame vertices at that estimate, when the
    caller has them. ``workspace``: a borrowed :class:`StepWorkspace` for the z-buffer (the native kernel's) and the
    levels' points and faces taken together (None: new tensors); the masks returned are new tensors either way."""
    intr = level_intrinsics(state.intrinsics, level, height, width)
    verts = _posed_vertices(model, state, layout, R) if verts is None else verts
    # The coverage alone: points_visible evaluates the depth at the points' pixels only (the same values as the
    # fragments' z-buffer there). At B = 128 the fragments' barycentric coordinates and depths at every covered
    # pixel took about a third of the visibility's time.
    if workspace is None:
        frags = rasterize_coverage(verts, model.faces, intr, backend=backend)
    else:
        def scratch(name: str, shape: tuple[int, ...], dtype: torch.dtype) -> Tensor:
            return workspace.buffer(f"visibility_{name}", shape, dtype, verts.device)

        frags = _cover(verts, model.faces, intr, False, NEAR_PLANE_MM, backend, pixels=False, scratch=scratch)[0]
    # The levels' points are tested together (one call instead of one per level: the test is per point).
    faces = [tpl.face_index for tpl in state.templates]
    sizes = [f.shape[1] for f in faces]
    if workspace is None:
        points = torch.cat([warp_points(tpl, layout, state.params, R)[1] for tpl in state.templates], 1)
        point_faces = torch.cat(faces, 1)
    else:  # each level's points written where they go (not made apart and then copied)
        B, n, device = faces[0].shape[0], sum(sizes), verts.device
        dtype = torch.promote_types(state.templates[0].points.dtype, state.params.dtype)  # (warp_points' result's)
        points = workspace.buffer("visibility_points", (B, n, 3), dtype, device)
        for tpl, part in zip(state.templates, points.split(sizes, 1)):
            warp_points(tpl, layout, state.params, R, out=part)
        point_faces = torch.cat(faces, 1, out=workspace.buffer("visibility_faces", (B, n), faces[0].dtype, device))
    visible = points_visible(points, point_faces, frags, intr, depth_tolerance=0.02, backend=backend)
    return [v & tpl.valid for v, tpl in zip(visible.split(sizes, 1), state.templates)]
