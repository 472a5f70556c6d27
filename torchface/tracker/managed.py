"""Template management around the tracking step (paper Section 4): one function of (state, frames).

:func:`managed_step` wraps :func:`~torchface.tracker.step.track_step`, which aligns each frame against stored
templates, with the policy of the paper's Section 4 (the pieces are in :mod:`torchface.template.management`):

1. **Mosaic entry.** Before the solve, each stream picks the mosaic entry nearest its pose (yaw and pitch,
   with hysteresis) and aligns against that entry's templates: near a stored pose the solve re-aligns pose
   and expression against the template seen there (Section 4.2). Entry 0 is the first frame's.
2. **Dissimilarity confidence.** After the solve, the frame's normalised face is compared with that of the
   mosaic entry nearest the estimated pose (the first frame's near it) by the fiducial patches'
   inverse-compositional Lucas-Kanade (Section 4.1); its confidence in [0, 1] is ``TrackResult.confidence``
   (the solver's residual confidence stays in ``residual_confidence``).
3. **Confidence gating.** A confident frame (confidence >= ``confidence_threshold``) updates the last
   confident parameters and may teach the mosaic: when it is confidently (>= ``add_confidence``) near the
   centre of a pose bin the mosaic lacks, next to a bin it has (``entry_reach``), its templates become a new
   entry, intensities brought back to the reference light. With ``texture_update`` it also re-samples the
   intensities of the entry in use (off by default: drift). A frame that is not confident teaches nothing and counts toward a loss; its
   estimate is still the next frame's start: every frame is aligned against stored templates, never against
   the previous frame, so a poor estimate corrupts no template, and while a head moves behind an occluder
   the last estimate is nearer the truth than the last confident one.
4. **Loss and recovery.** A stream is lost when its confidence stayed below ``confidence_threshold`` for
   ``lost_after`` frames or below ``very_low_confidence`` for ``lost_after_very_low`` frames (nothing of the
   face matches: the tracker sits on the background), when its solve FAILED (too few points, no contrast),
   or when less than ``min_inside_fraction`` of its face projects inside the frame (the face left). Lost
   frames are reported with status LOST (``success`` False). A lost stream keeps tracking from its estimate
   (back at the last confident parameters when the estimate left the frame or failed), with the
   refinement pass's prior at ``expression_prior_precision`` and a Gaussian expression prior (no
   ``expression_sparsity``; ``track_step(conservative=)``), and, when it is lost
   and then every ``recovery_every`` frames, re-initialises: from the ``detector`` callback's landmarks when
   one is given, else by searching its mosaic over the coarsest pyramid level (on small frames the coarsest
   that is at least 2 pixels a side and holds template points;
   :func:`~torchface.template.management.search_mosaic`); each candidate is refined by a normal solve. A
   candidate whose confidence beats the continued track's and reaches ``adopt_min_confidence`` replaces it
   (the stream goes on from the candidate) when it lies more than ``adopt_min_angle_deg`` from the track, in the
   frame (``min_inside_fraction``) and, when searched, within the searched depths; a continued track whose face is
   out of the frame competes with no candidate (its confidence is that of the patches still in view): any
   candidate that is itself confident (``confidence_threshold``), in the frame and, when searched, within the
   searched depths replaces it. The loss ends when the continued track or a candidate reaches
   ``recover_confidence``. A lost stream's continued track outside the searched depths scores 0 (it went astray,
   however well its patches match). With a detector and ``restart_after_unmatched`` (off by default), a stream
   whose detected face nothing of its mosaic matched at that many attempts in a row (the candidate and the
   continued track under ``adopt_min_confidence``, or the track out of the frame), the same face each time (a cut
   to another person), starts afresh from the detector's landmarks.

All per-frame work is batched over the B streams; adding an entry, switching entries and recovery touch only
the streams concerned (the recovery search loops over its lost streams).
"""

from __future__ import annotations

import functools
import inspect
import math
import os
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from types import FrameType
from typing import Any, cast

import torch
from torch import Tensor

from torchface._autocast import full_precision
from torchface._frame_values import divided_twice_hint
from torchface import _native
from torchface.appearance.illumination import NUM_ILLUMINATION_TERMS, remove_illumination
from torchface.appearance.sampling import sample_at_pixels, to_gray
from torchface.backend import Backend, use_native
from torchface.conventions import NORMALISED_LANDMARK_RANGE
from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import project_points
from torchface.geometry.so3 import axis_angle_to_matrix, geodesic_angle_deg, matrix_to_axis_angle, matrix_to_euler
from torchface.geometry.transforms import transform_points
from torchface.model.candide import load_candide3
from torchface.model.face_model import FaceModel
from torchface.normalise.face import NormalisedFaceLayout, apply_to_tensor_fields, build_normalised_layout
from torchface.rendering.visibility import vertex_normals
from torchface.solver.least_squares import SolveStatus
from torchface.template.dissimilarity import (
    DissimilarityReference, DissimilarityResult, build_dissimilarity_reference, dissimilarity,
)
from torchface.template.management import (
    Mosaic,
    MosaicLevel,
    TemplateConfig,
    _map_reference,
    _of_dtype,
    _reference_tensors,
    add_entries,
    entry_templates,
    face_inside_fraction,
    frame_dissimilarity,
    has_bin,
    light_normalised_intensity,
    native_mosaic_confidence,
    nearest_entries,
    new_mosaic,
    params_from_pose,
    pose_bins,
    reference_face,
    search_mosaic,
    select_entries,
    within_reach,
)
from torchface.template.points import (
    Template,
    TemplatePixels,
    _rows_writable,
    _template_rows_native,
    interpolated_normals,
    posed_mesh,
    rasterize_windows,
    select_pixels_posed,
    strided_window,
)
from torchface.tracker.fit import (
    LandmarkFit, fit_landmarks, landmark_rows_problem, landmarks_inside_fraction, normalised_streams,
    widen_half_landmarks,
)
from torchface.tracker.inference import without_autograd
from torchface.tracker.lookahead import (
    LookaheadConfig, _refine_starts, _Start, _stream_start, check_model_units, check_refine_first, is_keyframe_turn,
    is_video_cut, landmark_fit_priors, levels_of, view_yaw_deg,
)
from torchface.tracker.params import ParamLayout
from torchface.tracker.step import (
    STEP_VALUE_ROW_STRIDE,
    StartFailure,
    TrackerConfig,
    TrackerState,
    TrackResult,
    TrackStatus,
    check_api_types,
    check_frames,
    check_initialise_inputs,
    check_state_model,
    check_step_inputs,
    clamp_projection,
    fail_templates,
    gray_pyramid,
    gray_pyramid_windows,
    initialise,
    level_intrinsics,
    start_failure_codes,
    step_grad_inputs,
    too_small,
    track_checked_step,
    track_step,
)

__all__ = [
    "FirstPoseWatch", "LandmarkDetector", "ManagementState", "check_detector", "check_detector_callable",
    "estimate_confidence", "initialise_managed", "managed_step",
]

#: A face detector for re-initialisation: ``frames (B, 3, H, W)`` float in [0, 1] -> ``landmarks (B, K, 2)``
#: pixels of the model's K landmarks (68 iBUG points for CANDIDE-3), a row of NaN where no face was found.
LandmarkDetector = Callable[[Tensor], Tensor]

_FAILED = int(TrackStatus.FAILED)
_LOST = int(TrackStatus.LOST)


@dataclass(frozen=True, eq=False)
class ManagementState:
    """What template management keeps between frames (in :attr:`TrackerState.management`).

    Attributes:
        mosaic: the streams' :class:`~torchface.template.management.Mosaic` (templates and dissimilarity
            references per entry).
        layout: the normalised-face layout the dissimilarity is measured on (shared by the batch).
        entry: ``(B,)`` int64 the mosaic entry whose templates are ``TrackerState.templates``.
        low_count: ``(B,)`` int64 consecutive frames not confident (below the confidence threshold, or lost):
            the frames since ``confident_params``.
        very_low_count: ``(B,)`` int64 consecutive frames below the very-low confidence threshold.
        lost: ``(B,)`` bool, the stream is lost.
        confident_params: ``(B, P)`` the parameters of the last confident frame.
        since_attempt: ``(B,)`` int64 lost frames since the last recovery attempt.
        attempts: ``(B,)`` int64 recovery attempts made in the stream's current loss (0 when not lost; None:
            none yet), which sets the depths a search tries (:meth:`TemplateConfig.depth_scale`).
        adopted_scale: ``(B,)`` the depth scale of the attempt whose candidate the stream adopted in its current
            loss (1.0: none, or the base depths; None: none yet): its continued track is judged within the depths
            that attempt searched, so that the frames after it can end the loss.
        params_ypr: ``(params, ypr_deg)``: the yaw/pitch/roll ``(B, 3)`` of the parameters tensor ``params`` the
            step ended with (its result's), so that the next step does not convert them again; used only while
            ``TrackerState.params`` is that very tensor. None: not known.
        unstarted: ``(B,)`` bool, the streams whose initialisation failed (a black first frame, no face) and that
            have not started since: their templates hold no points and their dissimilarity reference no face
            (they hold their estimate, LOST, at confidence 0), so a detector's landmarks initialise them afresh
            (:func:`managed_step`) instead of recovering against them. None: every stream started.
        unmatched: ``(B,)`` int64 consecutive recovery attempts in the stream's current loss at which the detector
            found a face that no candidate matched (none adopted; :attr:`TemplateConfig.restart_after_unmatched
            <torchface.template.management.TemplateConfig.restart_after_unmatched>`), each showing the same face as the
            one before it. None: none yet.
        unmatched_face: the normalised face and mask ``((B, 3, G, G), (B, 1, G, G))`` the detector's landmarks placed
            at the last of those attempts (rows without one: zeros). None: no stream counts one.
        previous_pose: ``(B, 6)`` axis-angle and translation of the frame before the one whose estimate
            ``TrackerState.params`` holds (:attr:`~torchface.tracker.step.TrackerConfig.motion_prediction`'s
            velocity). None: not kept (the prediction off, or no step yet).
        steady: ``(B,)`` int64 consecutive confident frames ending with the one whose estimate the state holds, none
            of them lost, recovered, re-anchored or restarted (an initialisation counts 0); the motion prediction
            applies where it is at least 2. None: not kept (the prediction off, or no step yet).
    """

    mosaic: Mosaic
    layout: NormalisedFaceLayout
    entry: Tensor
    low_count: Tensor
    very_low_count: Tensor
    lost: Tensor
    confident_params: Tensor
    since_attempt: Tensor
    params_ypr: tuple[Tensor, Tensor] | None = None
    first: FirstPoseWatch | None = None
    head_rotation: Tensor | None = None
    head_translation: Tensor | None = None
    attempts: Tensor | None = None
    adopted_scale: Tensor | None = None
    unstarted: Tensor | None = None
    unmatched: Tensor | None = None
    unmatched_face: tuple[Tensor, Tensor] | None = None
    previous_pose: Tensor | None = None
    steady: Tensor | None = None

    def select(self, index: Tensor) -> "ManagementState":
        """The management of streams ``index`` (a ``(B',)`` int64 tensor: :meth:`TrackerState.select
        <torchface.tracker.step.TrackerState.select>`, which keeps ``params_ypr`` tied to the state's parameters).
        The look-ahead watch goes when none of those streams still waits for it; the layout is shared."""
        def pick(x: Tensor | None) -> Tensor | None:
            return None if x is None else x[index]

        first = self.first
        if first is not None:
            first = first.select(index)
            first = first if bool(first.pending.any()) else None
        ypr = None if self.params_ypr is None else (self.params_ypr[0][index], self.params_ypr[1][index])
        face = None if self.unmatched_face is None else (self.unmatched_face[0][index], self.unmatched_face[1][index])
        return ManagementState(
            self.mosaic.select(index), self.layout, self.entry[index], self.low_count[index],
            self.very_low_count[index], self.lost[index], self.confident_params[index], self.since_attempt[index],
            ypr, first, pick(self.head_rotation), pick(self.head_translation), pick(self.attempts),
            pick(self.adopted_scale), pick(self.unstarted), pick(self.unmatched), face, pick(self.previous_pose),
            pick(self.steady),
        )  # fmt: skip


@dataclass(frozen=True, eq=False)
class FirstPoseWatch:
    """The online look-ahead start (``initialise_managed(refine_first=...)``): what a stream keeps until its head
    has turned (``min_keyframes`` sides), when its first frame's pose is re-estimated and the stream re-anchored, or
    until a video cut (:data:`~torchface.tracker.lookahead.KEYFRAME_MAX_STEP_DEG`) ends its wait.

    Attributes:
        config: :class:`~torchface.tracker.lookahead.LookaheadConfig` (``yaw_deg``, ``min_keyframes``,
            ``min_confidence``, ``max_frames`` and the refinement's settings).
        frame0: ``(B, 3, H, W)`` the first frames (model dtype).
        landmarks: ``(B, K, 2)`` their landmarks; weights: ``(B, K)`` or None.
        fit: the first frames' :class:`~torchface.tracker.fit.LandmarkFit`.
        yaw0: ``(B,)`` the first frame's yaw (degrees).
        keys: per stream, its keyframes in the order found, each ``(frame (3, H, W), rotation (3, 3), translation
            (3,), expression (A,))``: the first confident frame whose yaw passed ``yaw_deg`` on each side, with its
            tracked pose and expression (relative to the first frame's).
        sides: ``(B, 2)`` bool, the stream has its keyframe of the yaw-up, yaw-down side.
        pending: ``(B,)`` bool, the stream still waits for its keyframes.
        frames_seen: frames of the sequence so far (the first included).
        view_yaw0: ``(B,)`` float64, the first frame's yaw seen along the camera's ray to the head
            (:func:`~torchface.tracker.lookahead.view_yaw_deg`; a keyframe's turn must also show there,
            :func:`~torchface.tracker.lookahead.is_keyframe_turn`); None: not checked.
    """

    config: LookaheadConfig
    frame0: Tensor
    landmarks: Tensor
    weights: Tensor | None
    fit: LandmarkFit
    yaw0: Tensor
    keys: tuple[tuple[tuple[Tensor, Tensor, Tensor, Tensor], ...], ...]
    sides: Tensor
    pending: Tensor
    frames_seen: int = 1
    view_yaw0: Tensor | None = None

    def select(self, index: Tensor) -> "FirstPoseWatch":
        """The watch of streams ``index`` (a ``(B',)`` int64 tensor); the config and frame count are shared."""
        return FirstPoseWatch(
            self.config, self.frame0[index], self.landmarks[index],
            None if self.weights is None else self.weights[index], self.fit.select(index), self.yaw0[index],
            tuple(self.keys[b] for b in index.tolist()), self.sides[index], self.pending[index], self.frames_seen,
            None if self.view_yaw0 is None else self.view_yaw0[index],
        )  # fmt: skip


def _layout(model: FaceModel) -> ParamLayout:
    return ParamLayout(model.num_animation, NUM_ILLUMINATION_TERMS)


def _management(state: TrackerState) -> ManagementState:
    """``state``'s template management (:func:`initialise_managed`'s states and those :func:`managed_step` makes
    have one)."""
    ms = state.management
    if not isinstance(ms, ManagementState):
        raise ValueError("the state has no template management: start with initialise_managed")
    return ms


def _plain(result: TrackResult) -> TrackResult:
    """A bare step's result with the management fields filled (no dissimilarity measured: NaN)."""
    B = result.status.shape[0]
    return replace(
        result, residual_confidence=result.confidence,
        dissimilarity=torch.full_like(result.confidence, float("nan")),
        mosaic_entry=torch.zeros(B, dtype=torch.int64, device=result.status.device),
    )  # fmt: skip


@full_precision
def initialise_managed(
    model: FaceModel,
    config: TrackerConfig,
    frames: Tensor,
    landmarks_px: Tensor,
    intrinsics: Intrinsics,
    weights: Tensor | None = None,
    *,
    fit: LandmarkFit | None = None,
    refine_first: LookaheadConfig | None = None,
) -> tuple[TrackerState, TrackResult]:
    """:func:`~torchface.tracker.step.initialise`, then the mosaic and the dissimilarity reference.

    The first frame's normalised face becomes the dissimilarity reference and its templates the mosaic's
    entry 0. Arguments and returns as :func:`~torchface.tracker.step.initialise`; with
    ``config.template.enabled`` False the state has no management (``management`` None). Besides
    :func:`~torchface.tracker.step.initialise`'s failures, a stream FAILS (confidence 0, no template points; a
    detector given to :func:`managed_step` starts it afresh) whose first normalised face shows too few of its own
    fiducial patches to score any frame, or whose fitted face has less than
    :attr:`~torchface.template.management.TemplateConfig.min_inside_fraction` of its vertices inside the frame
    (first landmarks that put the face mostly outside it: :func:`managed_step` would declare every frame LOST).

    ``refine_first``: the online look-ahead start, None for none (the default here; :class:`FaceTracker` starts with
    it by default). From one frontal view the landmark fit cannot tell the head's pitch from the face's vertical
    proportions (:mod:`~torchface.tracker.lookahead`): it holds the units that move features vertically
    (:attr:`~torchface.tracker.fit.FitConfig.held_shape_units`), so that landmark noise cannot tip the pose, and a
    face whose proportions differ then starts pitched. With a :class:`~torchface.tracker.lookahead.LookaheadConfig`,
    each stream keeps its first frame (``(3, H, W)`` in memory) until it has confidently turned ``yaw_deg`` (10) to
    one side (``min_keyframes`` 1; or to each side with 2; at most ``max_frames`` frames); then
    :func:`~torchface.tracker.lookahead.refine_first_fit` re-estimates the first frame's pose, its starting
    expression and the held shape units from those keyframes (each with its tracked expression change; a sparse
    start's units held as its fit held them: :attr:`~torchface.tracker.fit.FitConfig.sparse_landmark_count`), the
    stream's templates and mosaic are rebuilt from the first frame at that pose, and from the next frame on its
    reported pose (``rotation``, ``axis_angle``, ``translation``, ``ypr_deg``) is the re-anchored estimate expressed
    in the head frame of its first result: reported poses stay continuous and relative to the first frame's, while
    the mesh placed by the state's parameters (overlays, normalised faces) follows the refined estimate. The
    re-anchoring is a one-off stall of the stream's step (about 0.4 s on a 2-core CPU: the refinement and a new
    start); the frames before it keep the plain start's error, and a stream that never turns keeps the landmark
    fit. Measured with ``scripts/evaluate.py --noise-seeds 0,1,2,3`` (docs/limitations.md):
    ``pose_sweep``'s mean error 0.14-0.19 degrees, ``scan_motion``'s max 2.7-3.3.

    Example:
        >>> from torchface.model import load_candide3                                  # doctest: +SKIP
        >>> state, first = initialise_managed(model, TrackerConfig(), frames, lm, cam)  # doctest: +SKIP
        >>> state, result = managed_step(model, TrackerConfig(), state, next_frames)    # doctest: +SKIP
    """
    landmarks_px = widen_half_landmarks(landmarks_px)  # (float16 / bfloat16: warned of once, here)
    check_api_types(model, config)
    check_refine_first(refine_first)
    if refine_first is not None:
        if not config.template.enabled:
            raise ValueError("refine_first needs template management (config.template.enabled)")
        check_model_units(refine_first, model)  # (now, not at the turn: shape_units and shape_prior_precision were
        # refused only at the re-anchoring frame, a tracker and a torchface track run that had gone on until then)
        levels_of(refine_first, config.num_levels, "refine_first.iterations")  # (the same, at the turn)
        if fit is None:
            check_initialise_inputs(model, config, frames, landmarks_px, intrinsics, weights)
            fit = fit_landmarks(model, landmarks_px, intrinsics, weights, config=config.fit)
    if tc_enabled := config.template.enabled:
        # What the state keeps (templates, mosaic, reference, the look-ahead's first frame) is fixed data: built
        # from the frames without autograd, as managed_step reads later frames.
        check_frames(frames)  # (a numpy array was "'numpy.ndarray' object has no attribute 'detach'")
        frames = frames.detach()
    state, result = initialise(model, config, frames, landmarks_px, intrinsics, weights, fit=fit)
    tc = config.template
    if not tc_enabled:
        return state, _plain(result)
    frames = frames.to(dtype=model.dtype, device=model.device)
    layout = build_normalised_layout(model, tc.normalised_size, backend=config.backend)
    aa, t, alpha, light = _layout(model).split(state.params)
    image, mask = reference_face(frames, model, layout, state.shape_coeffs, alpha, aa, t, light, intrinsics, tc,
                                 backend=config.backend)
    reference = build_dissimilarity_reference(image, mask, tc.dissimilarity, config.backend)
    diss = frame_dissimilarity(
        frames, model, layout, reference, state.shape_coeffs, alpha, aa, t, light, intrinsics, tc,
        backend=config.backend,
    )
    failed = result.status == _FAILED
    # A first frame whose normalised face shows fewer than min_patches of its own reference's patches scores 0 against
    # itself, and so would every later frame and recovery candidate: the stream could never be confident (collinear
    # landmarks fitted the face edge-on, pitch 87 degrees, CONVERGED at confidence 0). It fails, as a fit without a
    # pose does (a detector can then start it afresh: managed_step).
    no_patches = ~failed & (diss.confidence <= 0)
    # A first fit with less than min_inside_fraction of its face inside the frame fails too: managed_step declares
    # such a frame lost at once, so the stream started, then reported every later frame LOST at the confidence of
    # the few in-view vertices against themselves (0.99-1.0: landmarks scaled x3 about the image centre, a third of
    # the face in view), and searched its mosaic of that face for good. Failed, it scores 0 and a detector restarts it.
    verts_cam = transform_points(axis_angle_to_matrix(aa), t, model.deform(state.shape_coeffs, alpha))
    away = face_inside_fraction(model, verts_cam, state.intrinsics) < tc.min_inside_fraction
    outside = ~failed & away
    blind = no_patches | outside
    # The reason: a face mostly outside the frame that also failed for want of template points is reported outside.
    code = cast(Tensor, result.start_failure)  # (initialise's)
    outside_code = outside | (away & (code == int(StartFailure.TOO_FEW_POINTS)))
    code = torch.where(outside_code, int(StartFailure.OUTSIDE_FRAME), code)
    code = torch.where(no_patches & ~outside, int(StartFailure.NO_PATCHES), code)
    # A start that failed from landmarks mostly outside the frame failed because the face is there, whatever the fit
    # made of them: landmarks 1000 px off a 160x120 frame said FACE_TOO_SMALL, off a 640x480 one NO_POSE. (Failed
    # starts only, their status and values as they were; a start that succeeded is untouched.)
    inside = landmarks_inside_fraction(landmarks_px, weights, frames.shape[-1], frames.shape[-2])
    lm_away = inside < tc.min_inside_fraction
    later = (code != int(StartFailure.NONE)) & (code != int(StartFailure.NO_LANDMARKS))
    later = later & (code != int(StartFailure.NORMALISED_LANDMARKS))
    code = torch.where(lm_away.to(code.device) & later, int(StartFailure.OUTSIDE_FRAME), code)
    if bool(blind.any()):
        failed = failed | blind
        state = replace(state, templates=tuple(fail_templates(state.templates, blind)))  # (as initialise's failures)
        result = replace(result, status=torch.where(blind, torch.full_like(result.status, _FAILED), result.status),
                         confidence=torch.where(blind, torch.zeros_like(result.confidence), result.confidence),
                         num_points=state.templates[0].num_points)  # fmt: skip
    result = replace(result, start_failure=code)
    conf = torch.where(failed, torch.zeros_like(diss.confidence), diss.confidence)
    mosaic = new_mosaic(state.templates, result.rotation, result.ypr_deg, reference, tc)
    B = state.params.shape[0]
    zeros = torch.zeros(B, dtype=torch.int64, device=state.params.device)
    management = ManagementState(
        mosaic, layout, zeros, zeros.clone(), zeros.clone(), failed.clone(), state.params, zeros.clone(),
        unstarted=failed.clone() if bool(failed.any()) else None,
    )
    if refine_first is not None and fit is not None:  # (with refine_first, fit is made above when not given)
        with torch.inference_mode(False):  # kept in the state: normal tensors, detached (as the frames are: a
            # detector network's landmarks kept its graph alive in the state until the stream re-anchored)
            watch = FirstPoseWatch(
                refine_first, frames.clone(),
                landmarks_px.detach().to(dtype=model.dtype, device=model.device).clone(),
                None if weights is None else weights.detach().to(dtype=model.dtype, device=model.device).clone(),
                apply_to_tensor_fields(Tensor.detach, fit.to(model.device, model.dtype)),
                result.ypr_deg[:, 0].clone(), ((),) * B,
                torch.zeros(B, 2, dtype=torch.bool, device=model.device), ~failed.clone(),
                view_yaw0=view_yaw_deg(result.rotation, result.translation),
            )  # fmt: skip
        management = replace(management, first=watch)
    result = replace(
        result, confidence=conf, residual_confidence=result.confidence, dissimilarity=diss.dissimilarity,
        mosaic_entry=zeros.clone(),
    )  # fmt: skip
    return replace(state, management=management), result


def _scatter_templates(
    templates: tuple[Template, ...], index: Tensor, sub: tuple[Template, ...], in_place: bool = False
) -> tuple[Template, ...]:
    """``templates`` with the samples ``index`` replaced by ``sub`` (batch ``len(index)``), made as normal tensors
    even in inference mode (they persist in the state: see :func:`~torchface.template.management.add_entries`).

    Where a template already holds its point-last copies (:attr:`~torchface.template.points.Template.point_last`,
    made by the solver on first use), the new one gets them the same way, rows ``index`` replaced by ``sub``'s:
    made again from the whole batch, they cost the solver a transposed copy of every stream's points and
    expression basis each time one stream changed entry (2 ms per step at 32 streams).

    ``in_place``: write the rows into ``templates``' own tensors (normal ones; inference tensors are copied as
    without it) instead of copies of them, for a caller that hands over the state they belong to
    (:func:`managed_step`'s ``donate``): a copy of every stream's template, to replace a few streams', cost 2 ms
    per step at 32 streams, 3% of the step."""
    B = templates[0].valid.shape[0]
    if index.shape[0] == B and bool((index == torch.arange(B, device=index.device)).all()):
        return tuple(_normal_template(s) for s in sub)  # every stream replaced, in order: the templates are sub's
    out = []
    with torch.inference_mode(False):
        for t, s in zip(templates, sub):
            reuse = in_place and not any(getattr(t, f.name).is_inference() for f in fields(Template))
            parts = []
            for f in fields(Template):
                x = getattr(t, f.name)
                x = x if reuse else x.clone()
                x[index] = getattr(s, f.name).to(x.dtype)
                parts.append(x)
            new = Template(*parts)
            cached = t.__dict__.get("_point_last")
            if cached is not None:
                lasts = []
                for x, y in zip(cached, s.point_last):
                    x = x if reuse and not x.is_inference() else x.clone()
                    x[index] = y.to(x.dtype)
                    lasts.append(x)
                object.__setattr__(new, "_point_last", tuple(lasts))
            out.append(new)
    return tuple(out)


def _entry_templates_in_place(
    model: FaceModel, shape_coeffs: Tensor, mosaic: Mosaic, streams: Tensor, entries: Tensor,
    templates: tuple[Template, ...], backend: Backend,
) -> tuple[Template, ...] | None:
    """``_scatter_templates(templates, streams, entry_templates(...), in_place=True)``: the templates of entries
    ``entries (B',)`` of streams ``streams (B',)`` (shape units ``shape_coeffs (B', S)``) written into rows
    ``streams`` of ``templates``' own tensors (those of a donated state) by the native interpolation, point-last
    copies included, without making them apart first (a fresh template per level, then copied into the state's:
    about 0.5 ms more per step at 32 streams, one thread). The same values. None (nothing written) where a level's
    tensors do not allow it (:func:`~torchface.template.points._rows_writable`) or the kernel cannot run."""
    verts = model.deform(shape_coeffs, None)
    neutral = verts, vertex_normals(verts, model.faces)
    levels = [TemplatePixels(*(getattr(lv, name)[streams, entries] for name in ("face_index", "bary", "intensity",
                                                                               "valid"))) for lv in mosaic.levels]
    if not use_native(backend, (verts, neutral[1], levels[0].bary, model.animation_units), "template") or not all(
        _rows_writable(model, t, verts.dtype) and t.face_index.shape[1] == px.face_index.shape[1]
        for t, px in zip(templates, levels)
    ):
        return None
    return tuple(_template_rows_native(model, neutral, px, t, streams) for t, px in zip(templates, levels))


def _normal_template(t: Template) -> Template:
    """``t`` with normal tensors (copies of its inference tensors, made outside inference mode), its point-last
    copies kept where they are normal tensors."""
    if not any(getattr(t, f.name).is_inference() for f in fields(Template)):
        return t
    with torch.inference_mode(False):
        new = Template(*(getattr(t, f.name).clone() for f in fields(Template)))
    cached = t.__dict__.get("_point_last")
    if cached is not None and not any(x.is_inference() for x in cached):
        object.__setattr__(new, "_point_last", cached)
    return new


def _result_rows(result: TrackResult, index: Tensor) -> TrackResult:
    """``result``'s samples ``index`` (tensor fields; the others, the names, as they are)."""
    return replace(result, **{f.name: getattr(result, f.name)[index] for f in fields(TrackResult)
                              if isinstance(getattr(result, f.name), Tensor)})  # fmt: skip


def _scatter_result(result: TrackResult, index: Tensor, sub: TrackResult) -> TrackResult:
    """``result`` with the samples ``index`` replaced by ``sub``'s (tensor fields only)."""
    changes: dict[str, Any] = {}  # field name -> its tensor (replace checks a value against every field's type)
    for f in fields(TrackResult):
        x = getattr(result, f.name)
        if isinstance(x, Tensor):
            x = x.clone()
            x[index] = getattr(sub, f.name).to(x.dtype)
            changes[f.name] = x
    return replace(result, **changes)


def _subset_state(state: TrackerState, index: Tensor, params: Tensor, templates: tuple[Template, ...]) -> TrackerState:
    mean = None if state.anim_prior_mean is None else state.anim_prior_mean[index]
    return TrackerState(
        params, state.shape_coeffs[index], templates, state.intrinsics, state.frame_index, anim_prior_mean=mean
    )


@functools.lru_cache(maxsize=64)
def _all_rows(count: int, device: torch.device) -> Tensor:
    """``torch.arange(count)`` on ``device``, int64: a batch's rows of its mosaic, as :func:`_confidence` and the
    clean radius's check read them every step (only read: a cached constant, made outside inference mode)."""
    with torch.inference_mode(False):
        return torch.arange(count, device=device)


def _confidence(
    model: FaceModel, config: TrackerConfig, ms: ManagementState, frames: Tensor, state: TrackerState,
    status: Tensor, index: Tensor | None = None, ypr_deg: Tensor | None = None, rotation: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, tuple[Tensor, Tensor]]:
    """Dissimilarity confidence ``(B,)`` (0 for FAILED samples, faces too small and streams that never started,
    :attr:`ManagementState.unstarted`), dissimilarity ``(B,)``,
    :func:`face_inside_fraction` ``(B,)`` of ``state``'s estimate, compared with the reference of the mosaic
    entry nearest it (one posing of the mesh serves both), and the normalised face and mask it was measured on
    (:func:`~torchface.template.management.reference_face`: ``(B, 3, G, G)``, ``(B, 1, G, G)``); ``index``
    selects the streams of a sub-batch (the mosaic's rows); ``ypr_deg`` ``(B, 3)`` and ``rotation``
    ``(B, 3, 3)``: the estimate's yaw/pitch/roll and rotation matrix when known."""
    aa, t, alpha, light = _layout(model).split(state.params)
    rows = _all_rows(state.params.shape[0], aa.device) if index is None else index
    ypr = None
    if ms.mosaic.capacity > 1:
        ypr = matrix_to_euler(axis_angle_to_matrix(aa)) if ypr_deg is None else ypr_deg
    R = axis_angle_to_matrix(aa) if rotation is None else rotation
    failed = status == _FAILED
    native = native_mosaic_confidence(frames, model, ms.layout, ms.mosaic, rows, ypr, state.shape_coeffs, alpha, R,
                                      t, light, state.intrinsics, config.template, config.backend)  # fmt: skip
    # A face narrower than TrackerConfig.min_face_width_px scores 0, as a FAILED sample does: its estimate is too
    # coarse to trust (it neither counts as confident nor ends a loss).
    failed = failed | too_small(model, config, t, state.intrinsics)
    if ms.unstarted is not None:
        # A stream whose initialisation failed has no reference to be confident against: its frames matched the
        # failed fit's own templates and reference (a fit 87 degrees off ended its loss at the next frame, at
        # confidence 1.0, and so did a recovery candidate searched in its mosaic without a detector). It scores 0
        # (track, recovery candidates, estimate_confidence) until it starts afresh (a detector's landmarks: _restart).
        failed = failed | ms.unstarted[rows]
    if native is not None:
        native_diss, native_conf, inside, face, _ = native
        # (in place: the kernel's own output; the same zeros as a torch.where, in one operation instead of two)
        return native_conf.masked_fill_(failed, 0.0), native_diss, inside, face
    diss, face, verts_cam = _nearest_dissimilarity(model, config, ms, frames, rows, ypr, state.shape_coeffs, aa, R,
                                                   t, alpha, light, state.intrinsics)  # fmt: skip
    conf = torch.where(failed, torch.zeros_like(diss.confidence), diss.confidence)
    return conf, diss.dissimilarity, face_inside_fraction(model, verts_cam, state.intrinsics), face


def _nearest_dissimilarity(
    model: FaceModel, config: TrackerConfig, ms: ManagementState, frames: Tensor, rows: Tensor, ypr: Tensor | None,
    shape_coeffs: Tensor, aa: Tensor, R: Tensor, t: Tensor, alpha: Tensor, light: Tensor, intrinsics: Intrinsics,
) -> tuple[DissimilarityResult, tuple[Tensor, Tensor], Tensor]:
    """The torch path of :func:`_confidence`: the dissimilarity of the streams ``rows``' estimates (``aa``, ``R``,
    ``t``, ``alpha``, ``light``, ``shape_coeffs``) against the reference of the mosaic entry nearest each (``ypr``
    ``(B', 3)``; None: entry 0), the normalised face and mask it was measured on, and the posed vertices
    ``(B', V, 3)`` (frame_dissimilarity's two halves, so that the normalised face can also serve a new entry)."""
    nearest = torch.zeros_like(rows) if ypr is None else nearest_entries(ms.mosaic, ypr, streams=rows)
    verts_cam = transform_points(R, t, model.deform(shape_coeffs, alpha))
    reference = ms.mosaic.references.select((rows, nearest))
    face = reference_face(frames, model, ms.layout, shape_coeffs, alpha, aa, t, light, intrinsics, config.template,
                          verts_cam=verts_cam, backend=config.backend)  # fmt: skip
    return dissimilarity(reference, *face, backend=config.backend), face, verts_cam


@full_precision
def estimate_confidence(
    model: FaceModel, config: TrackerConfig, state: TrackerState, frames: Tensor
) -> tuple[Tensor, Tensor]:
    """The dissimilarity confidence ``(B,)`` and dissimilarity ``(B,)`` of ``state``'s parameters on ``frames``,
    measured as :func:`managed_step` measures its result's (e.g. to score a pose that is not the tracker's).

    Args:
        state: with management (:func:`initialise_managed` / :func:`managed_step`); its ``params`` are scored.
        frames: ``(B, 3, H, W)`` the frames those parameters belong to.
    """
    check_api_types(model, config, state, with_state=True)
    ms = _management(state)
    check_state_model(model, state)  # (as the steps: another dtype said "convert the model", other units a size error)
    check_frames(frames, state.intrinsics, values=True, row_stride=STEP_VALUE_ROW_STRIDE)
    B = state.params.shape[0]
    if frames.shape[0] != B:  # the native kernel read past the state's streams (a segmentation fault)
        raise ValueError(f"expected {B} frames (one per stream of the state), got {frames.shape[0]}")
    frames = frames.to(dtype=model.dtype, device=model.device)
    status = torch.zeros(B, dtype=torch.int64, device=state.params.device)  # none failed
    return _confidence(model, config, ms, frames, state, status)[:2]


def _face_windows(model: FaceModel, verts_cam: Tensor, intrinsics: Intrinsics, q: int) -> Tensor:
    """Full-resolution pixel windows int64 ``(n, 4)`` ``(x0, y0, w, h)`` around the projected faces ``verts_cam
    (n, V, 3)``, each enlarged by 5% of its size and 8 pixels on each side, inside the image, corners on multiples
    of ``q`` (so that every pyramid level's window is pixel-aligned with that level): a corner's coordinate
    (in the vertices' dtype) truncated toward zero, then rounded outwards to ``q``. Every stream at once (one per
    stream, with four conversions of a value to a Python number each, cost about 0.1 ms a stream)."""
    uv = project_points(verts_cam[:, model.surface_vertex_mask], intrinsics)
    W, H = intrinsics.width, intrinsics.height
    uv = clamp_projection(uv, W, H)
    lo, hi = uv.amin(1), uv.amax(1)  # (n, 2) each
    pad = 0.05 * (hi - lo) + 8
    first = torch.div((lo - pad).to(torch.int64), q, rounding_mode="floor") * q  # int(): toward zero
    last = -torch.div(-(hi + pad).to(torch.int64), q, rounding_mode="floor") * q
    first = first.clamp(min=0)
    last = torch.minimum(last, torch.tensor([W, H], dtype=torch.int64, device=last.device))
    return torch.cat([first, (last - first).clamp(min=q)], -1)


def _new_entries(
    model: FaceModel, config: TrackerConfig, state: TrackerState, ms: ManagementState, frames: Tensor, index: Tensor,
    face: tuple[Tensor, Tensor] | None = None,
) -> tuple[tuple[TemplatePixels, ...], DissimilarityReference]:
    """Template pixels of streams ``index`` selected at their current estimate, intensities under the reference
    light, and the dissimilarity reference of their normalised face.

    The templates are built from a window of the frames around the faces (one size for the streams concerned,
    each placed around its face): the same templates as from the whole frames (rasterizing and gathering over
    the whole 640x480 frame made an entry cost ~110 ms). Only their compact form is made (the mosaic stores
    nothing else; :func:`~torchface.template.management.entry_templates` completes it when the entry is used):
    the positions and expression bases of a full template took a quarter of an entry's time. ``face``: the
    streams' normalised face and mask at this estimate when the caller has them (:func:`_confidence`'s).
    """
    aa, t, alpha, light = _layout(model).split(state.params[index])
    R = axis_angle_to_matrix(aa)
    shape = state.shape_coeffs[index]
    posed = posed_mesh(model, shape, alpha, R, t)  # posed once, for the reference face and the pixels
    if face is None:
        face = reference_face(_rows(frames, index), model, ms.layout, shape, alpha, aa, t, light, state.intrinsics,
                              config.template, verts_cam=posed.verts_cam, backend=config.backend)  # fmt: skip
    image, mask = face
    reference = build_dissimilarity_reference(image, mask, config.template.dissimilarity, config.backend)
    q = 2 ** (config.num_levels - 1)
    # (x0, y0, w, h) at full resolution per stream, as Python integers: the levels' windows below are a few
    # integer operations each (as tensor operations they cost 0.3 ms per entry).
    windows = _face_windows(model, posed.verts_cam, state.intrinsics, q).tolist()
    # Each level's window (one size for the streams concerned), or the whole level where it would hold fewer
    # pixels than the level's slots.
    cameras, heights, widths, offsets, strides = [], [], [], [], []
    h, w = state.intrinsics.height, state.intrinsics.width
    for level, lv in enumerate(ms.mosaic.levels):
        s = 2**level
        hl = min(-(-max(win[3] for win in windows) // s), h)
        wl = min(-(-max(win[2] for win in windows) // s), w)
        slots = lv.face_index.shape[-1]
        whole = wl * hl < slots  # fewer pixels than the level's slots
        cameras.append(level_intrinsics(state.intrinsics, level, h, w))
        heights.append(h if whole else hl)
        widths.append(w if whole else wl)
        offsets.append(None if whole else torch.tensor(
            [[min(win[0] // s, w - wl), min(win[1] // s, h - hl)] for win in windows], dtype=torch.int64,
            device=index.device,
        ))  # fmt: skip
        # The finest level's candidates on a sparser grid where it still holds 4x the slots (TemplateConfig).
        k = config.template.entry_stride if level == 0 else 1
        strides.append(k if (-(-heights[-1] // k)) * (-(-widths[-1] // k)) >= 4 * slots else 1)
        h, w = h // 2, w // 2
    grays = gray_pyramid_windows(frames, config.num_levels, offsets, heights, widths, rows=index,
                                 backend=config.backend)
    grids = [strided_window(Intrinsics(wl, hl, c.fx, c.fy, c.cx, c.cy), off, k)
             for c, hl, wl, off, k in zip(cameras, heights, widths, offsets, strides)]  # fmt: skip
    fragments = rasterize_windows(model, posed.verts_cam, [g[0] for g in grids], [g[1] for g in grids],
                                  config.backend)  # one call
    vertex_normals_neutral = vertex_normals(model.deform(shape, None), model.faces)
    pixels = []
    # Without TrackerConfig.expression_quota: it is the first template's (its finest level), where the expression
    # is refined; reserving points for every unit here took management's overhead from 24-26% to 37-56%
    # (benchmark.py --management-only), and the mosaic's entries are for the pose.
    for gray, off, cam, lv, frags, k in zip(grays, offsets, cameras, ms.mosaic.levels, fragments, strides):
        slots = lv.face_index.shape[-1]  # the slots of this level's entries
        pixels.append(select_pixels_posed(
            model, posed, gray, cam, off, max_points=slots,
            gradient_threshold=config.gradient_threshold, expression_priority=config.expression_priority,
            expression_quota=0, frags=frags, stride=k, seed=config.selection_seed,
            backend=config.backend,
        ))  # fmt: skip
    # The intensities under the reference light, every level's points at once (the work is per point).
    sizes = [px.face_index.shape[-1] for px in pixels]
    normals = interpolated_normals(vertex_normals_neutral, model.faces, torch.cat([px.face_index for px in pixels], 1),
                                   torch.cat([px.bary for px in pixels], 1))  # fmt: skip
    intensity = light_normalised_intensity(torch.cat([px.intensity for px in pixels], 1), normals, R, light)
    templates = tuple(replace(px, intensity=i.contiguous()) for px, i in zip(pixels, intensity.split(sizes, 1)))
    return templates, reference


def _rows(frames: Tensor, index: Tensor) -> Tensor:
    """``frames[index]`` for an int64 ``index (n,)``, without a copy when it lists every row in order."""
    if index.shape[0] == frames.shape[0] and bool((index == torch.arange(index.shape[0], device=index.device)).all()):
        return frames
    return frames.index_select(0, index)


def _texture_update(
    model: FaceModel, config: TrackerConfig, state: TrackerState, ms: ManagementState, frames: Tensor, mask: Tensor
) -> tuple[tuple[Template, ...], Mosaic]:
    """Re-sample the intensities of the templates in use from the frame for streams ``mask (B,)``."""
    aa, t, alpha, light = _layout(model).split(state.params)
    R = axis_angle_to_matrix(aa)
    beta = config.template.texture_blend
    B = mask.shape[0]
    rows = torch.arange(B, device=mask.device)
    templates, levels = [], []
    pyramid = gray_pyramid(frames, config.num_levels)
    for level, (tpl, gray, lv) in enumerate(zip(state.templates, pyramid, ms.mosaic.levels)):
        intr = level_intrinsics(state.intrinsics, level, gray.shape[-2], gray.shape[-1])
        pts = tpl.points + torch.einsum("bnka,ba->bnk", tpl.basis, alpha)
        cam = torch.matmul(pts, R.transpose(1, 2)) + t.unsqueeze(1)
        sampled, inside = sample_at_pixels(gray, project_points(cam, intr))
        normals_cam = torch.matmul(tpl.normals, R.transpose(1, 2))
        fresh = remove_illumination(sampled[..., 0], normals_cam, light)  # light_normalised_intensity, rotated once
        facing = (normals_cam * torch.nn.functional.normalize(cam, dim=-1)).sum(-1) < -config.template.min_facing_cos
        # Not from a NaN (missing) pixel: blended in, it would stay NaN in the template and its mosaic entry for good.
        update = mask.unsqueeze(-1) & tpl.valid & inside & facing & torch.isfinite(fresh)
        intensity = torch.where(update, (1 - beta) * tpl.intensity + beta * fresh, tpl.intensity)
        templates.append(replace(tpl, intensity=intensity))
        stored = lv.intensity.clone()
        stored[rows, ms.entry] = intensity.to(stored.dtype)
        levels.append(MosaicLevel(lv.face_index, lv.bary, stored, lv.valid))
    return tuple(templates), replace(ms.mosaic, levels=tuple(levels))


def _check_detector_output(landmarks: object, count: int, k: int, width: int, height: int) -> tuple[Tensor, Tensor]:
    """What a :data:`LandmarkDetector` answered for ``count`` frames of ``width x height``, refused unless it is
    ``(count, k, 2)`` real landmarks: bool ones were fitted as pixels 0 and 1 (the fit failed, the stream silently
    left LOST), a numpy array or a list was told its shape was wrong.

    A row with an infinite coordinate or one coordinate NaN alone (:func:`~torchface.tracker.fit.landmark_rows_problem`,
    refused where a user gives landmarks) is made a NaN row, a missing point, with a ``RuntimeWarning`` naming it: a
    restart never raises.

    Returns:
        The landmarks, with NaN rows (no face found) for the streams whose landmarks are in normalised coordinates
        (:func:`~torchface.tracker.fit.normalised_streams`: x / W, y / H in [0, 1], a MediaPipe-like detector's),
        and those streams ``(count,)`` bool, with a ``RuntimeWarning`` that says how to make pixels of them. They
        fail alone (a restart's reason :attr:`~torchface.tracker.step.StartFailure.NORMALISED_LANDMARKS`), the other
        streams of the answer going on: a detector that answers pixels for some streams and normalised points for
        others (two detectors behind one) raised at a restart of the normalised streams alone, and had those
        streams fitted as pixels (failed, LOST without a word) when asked together with the others.
    """
    # (a per-image detector's answer, one image's (K, 2) array or None, and a batch's as NumPy were told the type
    # alone, at the first recovery attempt)
    per_image = (" (one image's answer? The detector is called with the (B, 3, H, W) frames of the streams it "
                 f"re-initialises; a per-image detector, image -> ({k}, 2) points or None: "
                 "torchface.detect.batched(detector))")  # fmt: skip
    if not isinstance(landmarks, Tensor):
        shape = getattr(landmarks, "shape", None)
        hint = (per_image if landmarks is None or shape == (k, 2)
                else " (a NumPy array: torch.from_numpy(landmarks))" if shape == (count, k, 2)
                else (" (a list, one answer per stream: torch.stack([torch.as_tensor(x) for x in answers]), NaN "
                      "rows for no face; or wrap a per-image detector in torchface.detect.batched(detector))")
                if isinstance(landmarks, list) else "")  # fmt: skip
        raise TypeError(f"the detector must return a ({count}, {k}, 2) tensor of pixel landmarks (NaN rows: no "
                        f"face), got {type(landmarks).__name__}{hint}")  # fmt: skip
    if landmarks.dtype == torch.bool or landmarks.is_complex():
        raise TypeError(f"the detector must return real pixel coordinates (float or int), got {landmarks.dtype}")
    if tuple(landmarks.shape) != (count, k, 2):
        got = tuple(landmarks.shape)
        hint = per_image if got == (k, 2) else ""
        raise ValueError(f"the detector must return ({count}, {k}, 2) landmarks (NaN rows: no face), got {got}{hint}")
    problem = landmark_rows_problem(landmarks, weighted=False)
    if problem is not None:  # (refused where a user gives them; a running track is not stopped: missing, with a word)
        warnings.warn(f"the detector's {problem}: those points are taken as missing", RuntimeWarning, stacklevel=2)
        finite = torch.isfinite(landmarks).all(-1, keepdim=True)
        landmarks = torch.where(finite, landmarks, math.nan)
    normalised = normalised_streams(landmarks, width, height)
    if bool(normalised.any()):
        low, high = NORMALISED_LANDMARK_RANGE
        # (the same text each time, so that Python's warning filter shows it once, not at every recovery attempt)
        warnings.warn(
            f"the detector's landmarks of some streams lie within [{low}, {high}] x [{low}, {high}]: normalised "
            f"coordinates (x / W, y / H, as MediaPipe gives them)? The tracker takes pixels, centres at integers: "
            f"landmarks * torch.tensor([{width}.0, {height}.0]) for these {width}x{height} frames. Those streams "
            "are taken as no face found (a restart's TrackResult.start_failure: NORMALISED_LANDMARKS)",
            RuntimeWarning, stacklevel=2,
        )  # fmt: skip
        if not landmarks.is_floating_point():
            landmarks = landmarks.to(torch.get_default_dtype())
        landmarks = torch.where(normalised.to(landmarks.device)[:, None, None], math.nan, landmarks)
    return landmarks, normalised


def _as_rgb(frames: Tensor) -> Tensor:
    """``frames`` as the detector's contract has them, ``(B, 3, H, W)`` RGB (docs/python-api.md): gray
    ``(B, 1, H, W)`` frames, which the tracker tracks, expanded to three equal channels (a view); RGB frames as they
    are."""
    return frames.expand(-1, 3, -1, -1) if frames.shape[1] == 1 else frames


def _ask_detector(detector: LandmarkDetector, frames: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """``detector``'s answer about ``frames`` ``(B', 3, H, W)`` (or gray ``(B', 1, H, W)``: :func:`_as_rgb`), the
    frames of the streams it re-initialises, checked (:func:`_check_detector_output`, ``k``: the model's landmarks):
    the landmarks ``(B', k, 2)`` and the streams in normalised coordinates ``(B',)``. The one call of a detector: a
    recovery attempt's, a restart's and :func:`check_detector`'s."""
    with torch.no_grad():
        return _check_detector_output(detector(_as_rgb(frames)), frames.shape[0], k, frames.shape[-1], frames.shape[-2])


def check_detector_callable(detector: object) -> None:
    """Refuse, without calling it, a ``detector`` that cannot be the :data:`LandmarkDetector` the tracker calls as
    ``detector(frames)`` (:class:`~torchface.FaceTracker` ``detector=``, :func:`check_detector`): not callable, a
    class (not an instance of it), a per-image detector of :func:`~torchface.detect.load_detector`, or a callable
    whose signature does not take one positional argument (a second required one, none at all). What it answers is
    known only once it is called: :func:`check_detector`.

    Raises:
        TypeError: saying how to make a detector of it.
    """
    if not callable(detector):
        raise TypeError(f"detector must be callable (frames -> landmarks), got {type(detector).__name__}")
    from torchface.detect import _PerImageDetector  # (light: dlib or mediapipe is imported when one is made)

    if isinstance(detector, _PerImageDetector):  # one image at a time: it failed at the first loss, with a shape error
        raise TypeError(
            "detector takes a batch of frames (B, 3, H, W) -> (B, K, 2): wrap the per-image detector of "
            "load_detector in torchface.detect.batched(...)"
        )
    if isinstance(detector, type):  # (a class called with the frames made an instance of it, at the first loss)
        name = detector.__qualname__
        raise TypeError(f"detector must be a callable frames (B, 3, H, W) -> landmarks (B, K, 2), got the class "
                        f"{name}: an instance of it, detector={name}(...)")  # fmt: skip
    try:  # (its own signature: a wrapper's functools.wraps may name a function it calls with more arguments)
        signature = inspect.signature(detector, follow_wrapped=False)
    except (TypeError, ValueError):  # no signature to read (a builtin, some extension types): found at its call
        return
    try:
        signature.bind(None)  # the tracker's call: detector(frames)
    except TypeError as exc:
        name = getattr(detector, "__qualname__", type(detector).__qualname__)
        raise TypeError(
            f"detector is called with one argument, the frames (B, 3, H, W) of the streams it re-initialises -> "
            f"landmarks (B, K, 2), but {name}{signature} cannot be ({exc}): give its other arguments with "
            "functools.partial(detector, ...) or a lambda frames: detector(frames, ...)"
        ) from None


@without_autograd(lambda *args, **kwargs: ())
def check_detector(detector: LandmarkDetector, frames: Tensor, model: FaceModel | None = None) -> Tensor:
    """Ask ``detector`` about ``frames`` once, as the re-initialisation of lost streams asks it
    (:func:`managed_step`, :class:`~torchface.FaceTracker`), and check its answer as that does: the way to test a
    detector before a long run, whose first loss may come late (a wrong answer was found only there). Nothing else
    is called, nothing of a tracker changed; the detector's own state sees the call (a ``batched`` detector's
    warning about a face at the frame's edge is given once, a MediaPipe landmarker in video mode takes a timestamp).

    Args:
        detector: the :data:`LandmarkDetector`, first checked without a call (:func:`check_detector_callable`).
        frames: ``(B, 3, H, W)`` RGB or ``(B, 1, H, W)`` gray, float in [0, 1], as the tracker takes them: the
            first frames of the videos, say (a frame without a face tests the answer of no face, NaN rows). They
            reach the detector as the tracker hands them: RGB (gray expanded), in ``model``'s dtype and device, in
            inference mode. A restart asks about the lost streams alone, any ``B'`` of ``B``: a detector that
            answers a fixed batch shows it asked about one frame, ``frames[:1]``.
        model: the tracked model, whose ``K = model.num_landmarks`` points are asked for; None: CANDIDE-3 (68).

    Returns:
        ``(B, K, 2)`` the landmarks as a restart takes them, in the detector's dtype: NaN rows where it found no face,
        a point with an infinite coordinate or one NaN alone missing, and the streams whose landmarks lie in
        normalised coordinates made no face; each with a ``RuntimeWarning`` that says so, as at a restart.

    Raises:
        TypeError: ``detector`` refused by :func:`check_detector_callable`; an answer that is not a tensor (None, a
            NumPy array, a list: the message says how to make one) or whose values are bool or complex.
        ValueError: frames the tracker would refuse; an answer not ``(B, K, 2)`` (one image's ``(K, 2)`` named).
        Exception: whatever the detector raises, as it would at the restart.

    Example:
        >>> import torch
        >>> good = lambda frames: torch.full((frames.shape[0], 68, 2), float("nan"))  # finds no face
        >>> check_detector(good, torch.zeros(2, 3, 48, 64)).shape
        torch.Size([2, 68, 2])
        >>> check_detector(lambda frames: torch.zeros(68, 2), torch.zeros(1, 3, 48, 64))  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: the detector must return (1, 68, 2) landmarks (NaN rows: no face), got (68, 2) (one image's ...
    """
    check_detector_callable(detector)
    model = load_candide3() if model is None else model
    if not isinstance(model, FaceModel):
        raise TypeError(f"model must be a FaceModel or None (CANDIDE-3), got {type(model).__name__}")
    check_frames(frames, values=True, row_stride=STEP_VALUE_ROW_STRIDE)
    frames = frames.detach().to(dtype=model.dtype, device=model.device)  # (managed_step's frames)
    # (a copy, as a restart's frames[index] is, which the detector may change)
    return _ask_detector(detector, frames.clone(memory_format=torch.contiguous_format), model.num_landmarks)[0]


#: The fewest valid template points an entry needs at a pyramid level for the recovery search to place it there
#: (:attr:`~torchface.template.management.TemplateConfig.search_points`' least).
_SEARCH_MIN_POINTS = 8


def _search_level(mosaic: Mosaic, stream: int, height: int, width: int, num_levels: int) -> int:
    """The pyramid level the recovery search runs on for ``stream`` in frames of ``height x width``: the coarsest
    of the ``num_levels`` whose sides are both at least 2 pixels
    (:func:`~torchface.template.management.search_mosaic` halves it once more) and where one of the stream's
    entries holds at least :data:`_SEARCH_MIN_POINTS` valid points, or -1 when none is. The frame check lets the
    coarsest level be 1 pixel a side (:func:`~torchface.tracker.step.check_initialise_inputs`: 8x6 frames give a
    2x1 third level), and on small frames with many levels the coarsest levels hold no template points (every
    placement there scored 0: the face was never found). At the standard sizes it is the coarsest level."""
    level = -1
    used = mosaic.used[stream]
    for lv in range(num_levels):
        if min(height, width) < 2:
            break
        if int(mosaic.levels[lv].valid[stream][used].sum(-1).max()) >= _SEARCH_MIN_POINTS:
            level = lv
        height, width = height // 2, width // 2  # pyr_down's sizes
    return level


def _recovery_starts(
    model: FaceModel, config: TrackerConfig, state: TrackerState, ms: ManagementState, frames: Tensor, index: Tensor,
    detector: LandmarkDetector | None, depth_scales: list[float],
) -> tuple[Tensor, Tensor, Tensor]:
    """Start parameters ``(B', P)``, entries ``(B',)`` and "found" ``(B',)`` for the lost streams ``index``
    (``depth_scales``: each one's :meth:`~torchface.template.management.TemplateConfig.depth_scale`)."""
    layout = _layout(model)
    conf_params = ms.confident_params[index]
    aa_c, t_c, alpha_c, light_c = layout.split(conf_params)
    n = index.shape[0]
    found = torch.zeros(n, dtype=torch.bool, device=index.device)
    starts = conf_params.clone()
    if detector is not None:
        lm, _ = _ask_detector(detector, frames[index], model.num_landmarks)
        lm = lm.to(dtype=model.dtype, device=model.device)
        ok = torch.isfinite(lm).all(-1).sum(-1) >= max(4, model.num_landmarks // 2)
        if bool(ok.any()):
            fit = fit_landmarks(model, lm[ok], state.intrinsics, config=config.fit)
            good = fit.status != int(SolveStatus.FAILED)
            rows = ok.nonzero().squeeze(-1)[good]
            starts[rows] = params_from_pose(
                fit.rotation[good], fit.translation[good], fit.anim_coeffs[good], light_c[rows]
            )
            found[rows] = True
    else:
        H, W = frames.shape[-2:]
        levels = [_search_level(ms.mosaic, b, H, W, config.num_levels) for b in index.tolist()]
        pyramid = gray_pyramid(frames[index], max(levels) + 1) if max(levels) >= 0 else []
        R_c = axis_angle_to_matrix(aa_c)
        for i, (b, level) in enumerate(zip(index.tolist(), levels)):
            if level < 0:  # no level to search: not found
                continue
            gray = pyramid[level][i : i + 1]
            intr = level_intrinsics(state.intrinsics, level, gray.shape[-2], gray.shape[-1])
            hit = search_mosaic(
                model, state.shape_coeffs[b : b + 1], ms.mosaic, b, gray, intr, level,
                float(t_c[i, 2]), R_c[i], config.template, depth_scale=depth_scales[i], backend=config.backend,
            )  # fmt: skip
            if hit.score > 0:
                # The last confident expression: on a face unlike the model the animation units also absorb
                # shape (TrackerConfig.fit), and from zero the solve can settle in another minimum.
                starts[i] = params_from_pose(hit.rotation[None], hit.translation[None], alpha_c[i : i + 1],
                                             light_c[i : i + 1])[0]  # fmt: skip
                found[i] = True
    ypr = matrix_to_euler(axis_angle_to_matrix(layout.split(starts)[0]))
    entries = select_entries(ms.mosaic, ypr, torch.zeros_like(index), 0.0, config.template.reference_radius_deg,
                             streams=index)  # fmt: skip
    return starts, entries, found


def _recover(
    model: FaceModel, config: TrackerConfig, state: TrackerState, ms: ManagementState, frames: Tensor, index: Tensor,
    detector: LandmarkDetector | None, depth_scales: list[float],
) -> tuple[Tensor, TrackerState, TrackResult, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Re-initialise the lost streams ``index``: candidates, a normal solve from each, their confidence.

    Returns:
        found ``(B',)``, the sub-batch's solved state and result, confidence ``(B',)``, dissimilarity ``(B',)``,
        the fraction of the face inside the frame ``(B',)``, the entries ``(B',)`` used and the candidates' start
        parameters ``(B', P)``.
    """
    starts, entries, found = _recovery_starts(model, config, state, ms, frames, index, detector, depth_scales)
    templates = entry_templates(model, state.shape_coeffs[index], ms.mosaic, index, entries, config.backend)
    sub = _subset_state(state, index, starts, templates)
    # A candidate is solved conservatively: the refinement pass's weak prior would let the animation units
    # absorb a wrong candidate's residual, and the face normalised with them would then fail the confidence.
    every = torch.ones(index.shape[0], dtype=torch.bool, device=index.device)
    solved, result = track_step(model, config, sub, frames[index], conservative=every)
    conf, diss, inside, _ = _confidence(model, config, ms, frames[index], solved, result.status, index,
                                        rotation=result.rotation)  # fmt: skip
    return found, solved, result, conf, diss, inside, entries, starts


def _count_unmatched(
    model: FaceModel, config: TrackerConfig, state: TrackerState, ms: ManagementState, frames: Tensor, index: Tensor,
    starts: Tensor, blind: Tensor,
) -> tuple[Tensor, tuple[Tensor, Tensor] | None]:
    """:attr:`ManagementState.unmatched` and ``unmatched_face`` after the recovery attempt of the lost streams
    ``index`` ``(B',)``, whose detector found a face that nothing of the mosaic matched where ``blind`` ``(B',)``
    (``starts`` ``(B', P)``: its landmark fit). Such an attempt counts on from the one before only when the face
    normalised at the fit matches the one normalised then (dissimilarity confidence at least
    ``confidence_threshold`` against it): a new person in view looks the same five frames later, an occluder
    passing over the face does not (320x240, 75% of the face covered: 0.000-0.005 against 0.996 for a cut to
    another person). Any other attempt sets the count to 0, or 1 for the first blind one."""
    tc = config.template
    count = torch.zeros_like(ms.low_count) if ms.unmatched is None else ms.unmatched.clone()
    kept = ms.unmatched_face
    count[index[~blind]] = 0
    rows = index[blind]
    if not rows.numel():
        return count, kept
    aa, t, alpha, light = _layout(model).split(starts[blind])
    image, mask = reference_face(_rows(frames, rows), model, ms.layout, state.shape_coeffs[rows], alpha, aa, t, light,
                                 state.intrinsics, tc, backend=config.backend)  # fmt: skip
    same = torch.zeros_like(blind[blind])
    before = count[rows] > 0
    if kept is not None and bool(before.any()):
        at = rows[before]
        reference = build_dissimilarity_reference(kept[0][at], kept[1][at], tc.dissimilarity, config.backend)
        diss = dissimilarity(reference, image[before], mask[before], backend=config.backend)
        same[before] = diss.confidence >= tc.confidence_threshold
    count[rows] = torch.where(same, count[rows] + 1, torch.ones_like(count[rows]))
    B = count.shape[0]
    if kept is None:
        kept = (image.new_zeros((B, *image.shape[1:])), mask.new_zeros((B, *mask.shape[1:])))
    kept = (kept[0].clone(), kept[1].clone())
    kept[0][rows], kept[1][rows] = image, mask
    return count, kept


def _restart(
    model: FaceModel, config: TrackerConfig, state: TrackerState, result: TrackResult, frames: Tensor,
    restart: Tensor, detector: LandmarkDetector,
) -> tuple[TrackerState, TrackResult, Tensor]:
    """The streams ``restart`` ``(B,)`` that never started (:attr:`ManagementState.unstarted`), or whose detector found
    a face their mosaic never matched (``TemplateConfig.restart_after_unmatched``), initialised from this
    frame and the detector's landmarks, where it finds a face (half the landmarks) and the initialisation succeeds:
    their fit, templates, mosaic and reference are this frame's, their management starts afresh, and their result
    is the initialisation's (without the online look-ahead start: a stream still waiting for its keyframes stops
    waiting). Returns the state, the result and the streams that started (int64 ``(n,)``)."""
    ms = cast(ManagementState, state.management)  # managed_step's: a managed state
    index = restart.nonzero().squeeze(-1)
    lm, normalised = _ask_detector(detector, frames[index], model.num_landmarks)
    lm = lm.to(dtype=model.dtype, device=model.device)
    found = torch.isfinite(lm).all(-1).sum(-1) >= max(4, model.num_landmarks // 2)
    normalised = normalised.to(found.device)
    # why each stream asked did not start (NONE where it starts: initialise_managed's reasons below)
    codes = torch.zeros_like(result.status)
    codes[index] = start_failure_codes([(StartFailure.NORMALISED_LANDMARKS, normalised),
                                        (StartFailure.NO_LANDMARKS, ~found)])  # fmt: skip
    result = replace(result, start_failure=codes)
    rows = index[found]
    if not rows.numel():
        return state, result, rows
    sub, sub_result = initialise_managed(model, config, frames[rows], lm[found], state.intrinsics)
    ok = sub_result.status != _FAILED
    if not bool(ok.all()):  # (one host read where every found stream starts)
        codes = codes.clone()
        codes[rows] = cast(Tensor, sub_result.start_failure)
        result = replace(result, start_failure=codes)
        if not bool(ok.any()):
            return state, result, rows[:0]
        sub = sub.select(ok)
        sub_result = _result_rows(sub_result, ok)
    rows = rows[ok]
    sub_ms = cast(ManagementState, sub.management)  # initialise_managed's with template management: managed
    with torch.inference_mode(False):
        def put(x: Tensor, y: Tensor | float) -> Tensor:
            x = x.clone()
            x[rows] = torch.as_tensor(y).to(device=x.device, dtype=x.dtype)
            return x

        def put_some(x: Tensor | None, y: Tensor | float) -> Tensor | None:  # a field that may be None
            return None if x is None else put(x, y)

        unstarted = put_some(ms.unstarted, False)
        # no longer waiting for the online start's keyframes: re-anchored at them, a stream restarted after a cut
        # got its first frame's templates and mosaic back (another person's)
        first = ms.first
        if first is not None:
            first = replace(first, pending=put(first.pending, False))
            first = first if bool(first.pending.any()) else None
        eye = torch.eye(3, dtype=model.dtype, device=model.device)
        new_ms = replace(
            ms, mosaic=_reset_mosaic_rows(ms.mosaic, rows, sub_ms.mosaic), entry=put(ms.entry, 0),
            low_count=put(ms.low_count, 0), very_low_count=put(ms.very_low_count, 0), lost=put(ms.lost, False),
            confident_params=put(ms.confident_params, sub.params), since_attempt=put(ms.since_attempt, 0),
            params_ypr=None, head_rotation=put_some(ms.head_rotation, eye),
            head_translation=put_some(ms.head_translation, 0.0), attempts=put_some(ms.attempts, 0),
            adopted_scale=put_some(ms.adopted_scale, 1.0), unmatched=put_some(ms.unmatched, 0),
            unstarted=unstarted if unstarted is not None and bool(unstarted.any()) else None, first=first,
            steady=put_some(ms.steady, 0),
        )  # fmt: skip
        prior = state.anim_prior_mean
        state = replace(
            state, params=put(state.params, sub.params), shape_coeffs=put(state.shape_coeffs, sub.shape_coeffs),
            templates=_scatter_templates(state.templates, rows, sub.templates),
            anim_prior_mean=None if prior is None else put(prior, sub.neutral_anim_coeffs(prior[rows])),
            management=new_ms,
        )  # fmt: skip
    return state, _scatter_result(result, rows, sub_result), rows


def _within_searched_depths(
    params: Tensor, confident_params: Tensor, layout: ParamLayout, tc: TemplateConfig, scales: Tensor | None = None
) -> Tensor:
    """``(B,)`` bool: the depth of ``params`` ``(B, P)`` lies within the depths the recovery search tries
    (``search_depth_factors`` of the depth of ``confident_params`` ``(B, P)``, widened by 10%; with ``scales``
    ``(B,)``, those factors scaled by it too: the depths that attempt tried)."""
    ratio = params[:, layout.translation][:, 2] / confident_params[:, layout.translation][:, 2]
    lo, hi = min(tc.search_depth_factors) / 1.1, max(tc.search_depth_factors) * 1.1
    if scales is None:
        return (ratio >= lo) & (ratio <= hi)
    return (ratio >= lo * scales.clamp(max=1.0)) & (ratio <= hi * scales.clamp(min=1.0))


def _thin(
    model: FaceModel, config: TrackerConfig, ms: ManagementState, frames: Tensor, params: Tensor,
    shape_coeffs: Tensor, intrinsics: Intrinsics, rows: Tensor,
) -> Tensor:
    """``(B',)`` bool: the estimates ``params`` ``(B', P)`` of the streams ``rows`` (their ``frames``
    ``(B', C, H, W)`` and ``shape_coeffs``) whose dissimilarity, against the mosaic entry nearest each as
    :func:`_confidence` measures it, rests on fewer than ``TemplateConfig.recover_min_patches`` present fiducial
    patches (docs/limitations.md, "Fast motion": a lost track 65-72 degrees off scored 0.47-0.82 on one)."""
    aa, t, alpha, light = _layout(model).split(params)
    R = axis_angle_to_matrix(aa)
    ypr = matrix_to_euler(R) if ms.mosaic.capacity > 1 else None
    diss, _, _ = _nearest_dissimilarity(model, config, ms, frames, rows, ypr, shape_coeffs, aa, R, t, alpha, light,
                                        intrinsics)  # fmt: skip
    return diss.present.sum(-1) < config.template.recover_min_patches


def _turned_too_far(
    rotation: Tensor, confident_params: Tensor, low_count: Tensor, tc: TemplateConfig, layout: ParamLayout
) -> Tensor:
    """``(B,)`` bool: ``rotation`` ``(B, 3, 3)`` lies farther from the last confident pose (``confident_params``
    ``(B, P)``) than ``TemplateConfig.plausible_turn_deg`` lets a head turn in the ``low_count + 1`` frames since it
    (all False with the check off)."""
    if max(tc.plausible_turn_deg) <= 0:
        return torch.zeros(rotation.shape[0], dtype=torch.bool, device=rotation.device)
    turned = geodesic_angle_deg(rotation, axis_angle_to_matrix(confident_params[:, layout.rotation]).to(rotation.dtype))
    base, per_frame = tc.plausible_turn_deg
    return turned > base + per_frame * (low_count + 1).to(turned.dtype)


@full_precision
@without_autograd(step_grad_inputs)
def managed_step(
    model: FaceModel,
    config: TrackerConfig,
    state: TrackerState,
    frames: Tensor,
    detector: LandmarkDetector | None = None,
    *,
    donate: bool = False,
) -> tuple[TrackerState, TrackResult]:
    """Track one frame per stream with template management (module docstring).

    Args:
        model: the face model used at initialisation.
        config: :class:`~torchface.tracker.step.TrackerConfig`; ``config.template`` sets the management.
        state: from :func:`initialise_managed` or the previous step.
        frames: ``(B, 3, H, W)`` (or gray ``(B, 1, H, W)``) the next frame of each stream, float in [0, 1].
        detector: optional :data:`LandmarkDetector` used to re-initialise lost streams (called with the
            frames of the streams attempting a recovery only, and once more with those of the streams that start
            afresh: never started, or ``TemplateConfig.restart_after_unmatched``); None searches the mosaic instead.
        donate: the caller hands ``state`` over and will not use it again (:class:`~torchface.FaceTracker` does):
            where streams change mosaic entry, their new templates are written into ``state``'s template tensors
            instead of into copies of every stream's (which then also change). False: ``state`` is left as it was.

    Returns:
        The new state and the frame's :class:`~torchface.tracker.step.TrackResult`, whose ``confidence`` is the
        dissimilarity confidence, ``residual_confidence`` the solver's, ``dissimilarity`` the patch displacement
        and ``mosaic_entry`` the entry aligned against; lost streams have status LOST (``success`` False).
        ``start_failure`` is None, except at a step where a detector's restart was tried: there it is ``(B,)``
        int64, the :class:`~torchface.tracker.step.StartFailure` of each stream the restart did not start (they stay
        LOST; NONE for the others). With ``config.template.enabled`` False it is
        :func:`~torchface.tracker.step.track_step` (confidence = residual confidence, dissimilarity NaN, entry 0).

    Raises:
        ValueError: bad frames, a state without management while management is enabled, or management turned off
            (``config.template.enabled`` False) in a state whose online start has re-anchored streams: their results
            are in the first result's head frame only through management (:func:`_in_head_frame`), and the bare
            step's would jump by the re-anchoring's offset (initialise again to track on without it).

    Runs in inference mode (:mod:`torchface.tracker.inference`) unless ``frames`` or the state's parameters or
    templates require grad with grad mode on; the tensors handed back are normal tensors. With gradients asked for, the
    solver's estimates (pose, expression, light) carry them as :func:`~torchface.tracker.step.track_step`'s do
    (through the unrolled solve), in the streams whose estimate is the solver's; the management's decisions and
    what it keeps (confidence, mosaic entries, confident parameters) are made from detached copies. The state's
    ``params`` carry the frame's graph on to the next step (:meth:`~torchface.tracker.TrackerState.detach` between
    frames whose losses stand alone).
    """
    check_api_types(model, config, state, with_state=True)
    tc = config.template
    if not tc.enabled:
        _check_not_reanchored(state.management)
        new_state, result = track_step(model, config, state, frames)
        return new_state, _plain(result)
    ms = state.management
    if not isinstance(ms, ManagementState):
        raise ValueError(
            "template management is enabled but the state has none: start with initialise_managed (or set "
            "TrackerConfig.template = TemplateConfig(enabled=False))"
        )
    check_step_inputs(model, config, state, frames)
    frames = frames.to(dtype=model.dtype, device=model.device)
    layout = _layout(model)
    # 0. TrackerConfig.motion_prediction: the solve (and the entry, the crop, the visibility) starts from a
    # constant-velocity prediction where the last two frames were steadily confident.
    pose_now = None  # the previous frame's pose (the next step's previous_pose), kept with the prediction on
    predicted, unpredicted = None, state  # the streams that start from a prediction; the state without it
    if config.motion_prediction > 0.0:
        pose_now = state.params.detach()[:, :6].clone()
        if ms.previous_pose is not None and ms.steady is not None and bool((ms.steady >= 2).any()):
            predicted = ms.steady >= 2
            state = replace(state, params=_predicted_start(state.params, ms.previous_pose, predicted,
                                                           config.motion_prediction, layout))  # fmt: skip

    # 1. The mosaic entry nearest each stream's pose (templates rebuilt only where the entry changes).
    entry, templates = ms.entry, state.templates
    use_mosaic = tc.mosaic and ms.mosaic.capacity > 1
    if use_mosaic or tc.clean_radius_deg > 0:
        if ms.params_ypr is not None and ms.params_ypr[0] is state.params:
            ypr = ms.params_ypr[1]
        else:
            ypr = matrix_to_euler(axis_angle_to_matrix(state.params[:, layout.rotation]))
    near = None
    native = use_mosaic and use_native(config.backend, (ypr, ms.mosaic.ypr_deg), "template management")
    if native:  # the same decisions in one native call (torchface/_native/management.h)
        entry, near = _native_select_entries(ms, ypr, tc)
    elif use_mosaic:
        entry = select_entries(ms.mosaic, ypr, ms.entry, tc.switch_margin_deg, tc.reference_radius_deg)
    # (one comparison where no stream changes entry, as in most steps: the list of those that do is three operations)
    if use_mosaic and not torch.equal(entry, ms.entry):
        changed = (entry != ms.entry).nonzero().squeeze(-1)
        written = None
        if donate:  # straight into the state's templates where they allow it (_entry_templates_in_place)
            written = _entry_templates_in_place(model, state.shape_coeffs[changed], ms.mosaic, changed,
                                                entry[changed], templates, config.backend)  # fmt: skip
        if written is None:
            sub = entry_templates(model, state.shape_coeffs[changed], ms.mosaic, changed, entry[changed],
                                  config.backend)  # fmt: skip
            written = _scatter_templates(templates, changed, sub, in_place=donate)
        templates = written

    # 2. The joint minimisation (Eq. 20) against those templates, then its dissimilarity confidence.
    # Lost streams (and, with TemplateConfig.conservative_when_unconfident, those whose last frame was not confident)
    # keep the pose levels' prior in the refinement pass: with a weak one (refine_prior_precision)
    # a lost track's units fitted a wrong pose well enough to pass the recovery confidence, and the stream
    # stayed lost at that pose (measured on the CANDIDE-3 long run after the face left the frame).
    # Streams near the pose their entry was built at are solved with Huber at the finest level on a clean frame
    # (TemplateConfig.clean_radius_deg).
    conservative = ms.lost | (ms.low_count > 0) if tc.conservative_when_unconfident else ms.lost
    if tc.clean_radius_deg > 0 and near is None:
        rows = _all_rows(entry.shape[0], entry.device)
        near = (ms.mosaic.ypr_deg[rows, entry, :2] - ypr[:, :2]).norm(dim=-1) <= tc.clean_radius_deg
    # (the state as it is where no stream changed entry: a replace of it took 6-9 us a step at one stream)
    solving = state if templates is state.templates else replace(state, templates=templates)
    solved, result = track_checked_step(  # (track_step, without checking the inputs again)
        model, config, solving, frames, conservative=conservative, near_template=near
    )
    # Where the caller asked for gradients (frames or parameters that require grad, with grad mode on), the
    # solver's estimates carry them, as track_step's do; template management is a decision layer and works on
    # detached copies, so that nothing it keeps (mosaic entries, confident parameters, the look-ahead's keyframes)
    # holds a graph from frame to frame. The gradients go back into the result and the state's parameters at the
    # end, for the streams whose estimate is the solver's (not reverted, not a recovery candidate's).
    graded = _graded(solved, result)
    if graded is not None:
        frames = frames.detach()
        solved, result = replace(solved, params=solved.params.detach()), _detached(result)
    adopted = None  # the streams that go on from a recovery candidate (rows), if any
    face: tuple[Tensor, Tensor] | None  # the normalised faces of the track's estimates (None: not all the track's)
    conf, diss, inside, face = _confidence(
        model, config, ms, frames, solved, result.status, ypr_deg=result.ypr_deg, rotation=result.rotation
    )
    # A predicted start that the frame contradicts (the head stopped or turned back: a velocity reversed at 16 mm a
    # frame put the prediction 32 mm off, beyond the solve's capture range) scores very low: those streams are
    # solved again from the previous frame's estimate, and keep the better of the two (docs/limitations.md, "Fast
    # motion").
    retried = None  # the streams whose estimate is the plain start's (rows)
    if predicted is not None:
        again = predicted & ((conf < tc.very_low_confidence) | (result.status == _FAILED))
        if bool(again.any()):
            index = again.nonzero().squeeze(-1)
            plain = _subset_state(unpredicted, index, unpredicted.params.detach()[index], entry_templates(
                model, state.shape_coeffs[index], ms.mosaic, index, entry[index], config.backend))  # fmt: skip
            with torch.no_grad():  # (a management decision: its estimate carries no gradient)
                p_state, p_result = track_step(model, config, plain, frames[index], conservative=conservative[index],
                                               near_template=None if near is None else near[index])  # fmt: skip
            p_conf, p_diss, p_inside, _ = _confidence(model, config, ms, frames[index], p_state, p_result.status,
                                                      index, rotation=p_result.rotation)  # fmt: skip
            better = (p_conf > conf[index]) & (p_result.status != _FAILED)
            if bool(better.any()):
                rows, face = index[better], None
                solved = replace(solved, params=solved.params.clone())
                solved.params[rows] = p_state.params[better].to(solved.params.dtype)
                result = _scatter_result(result, rows, _result_rows(p_result, better))
                conf, diss, inside = conf.clone(), diss.clone(), inside.clone()
                conf[rows], diss[rows], inside[rows] = p_conf[better], p_diss[better], p_inside[better]
                retried = rows

    # 3. Gating and loss.
    failed = result.status == _FAILED  # (a stream that never started scores 0: _confidence)
    # A lost stream's track that has left the depths its recovery searches (search_depth_factors of its last
    # confident depth, widened by 10 %; scaled as the attempt whose candidate it adopted) went astray, whatever its
    # confidence: it scores 0, so it neither ends the loss nor counts as confident (CANDIDE-3 long run,
    # landmark-noise draw 2, with README's per-unit shape prior and early re-anchoring: lost under an occluder,
    # the track drifted to twice the true depth and 51 degrees off, scored 0.58 there and ended the loss for good).
    if bool(ms.lost.any()):
        near = _within_searched_depths(solved.params, ms.confident_params, layout, tc, ms.adopted_scale)
        conf = torch.where(ms.lost & ~near, torch.zeros_like(conf), conf)
        # With TemplateConfig.recover_min_patches, a lost stream's track whose confidence rests on too few fiducial
        # patches scores 0 as well (James long run with motion_prediction 0.5: 65-72 degrees off, 0.47-0.82 on one).
        if tc.recover_min_patches > 1:
            index = ms.lost.nonzero().squeeze(-1)
            thin = _thin(model, config, ms, frames[index], solved.params[index], solved.shape_coeffs[index],
                         solved.intrinsics, index)  # fmt: skip
            conf = conf.clone()
            conf[index[thin]] = 0.0
        # (opt-in) nor does one turned faster than a head turns
        too_far = _turned_too_far(result.rotation, ms.confident_params, ms.low_count, tc, layout)
        conf = torch.where(ms.lost & too_far, torch.zeros_like(conf), conf)
    gate = _native_gate(ms, result.ypr_deg, conf, inside, failed, tc) if native else None
    if gate is not None:
        confident, low_count, very_low_count, lost, reverted, since, attempt, add_if_kept, bins_if_kept = gate
    else:
        outside = inside < tc.min_inside_fraction
        confident = (conf >= tc.confidence_threshold) & ~failed & ~outside
        low_count = torch.where(confident, torch.zeros_like(ms.low_count), ms.low_count + 1)
        very_low = (conf < tc.very_low_confidence) | failed | outside
        very_low_count = torch.where(very_low, ms.very_low_count + 1, torch.zeros_like(ms.very_low_count))
        lost = ms.lost | failed | outside | (low_count >= tc.lost_after) | (very_low_count >= tc.lost_after_very_low)
        lost = lost & ~((conf >= tc.recover_confidence) & ~failed & ~outside)
        reverted = lost & (failed | outside)
        since = torch.where(lost, ms.since_attempt + 1, torch.zeros_like(ms.since_attempt))
        since = torch.where(lost & ~ms.lost, torch.full_like(since, tc.recovery_every), since)  # at once when lost
        attempt = lost & (since >= tc.recovery_every)
    # A lost stream's frame scoring between confidence_threshold and recover_confidence is not confident either
    # (confident_params keeps the pose before the loss): low_count counts it, so that it stays the frames since that
    # pose, which plausible_turn_deg's reach grows with (it had restarted there: James scan, landmark-noise draw 2,
    # 2-px grid, (15, 1): a right track 17-18 degrees from that pose held lost 27 frames longer). Nothing else reads
    # a lost stream's count: defaults unchanged.
    # any_lost: one host read; where no stream is lost (most steps), what follows from a loss (the counts above, the
    # reverted parameters, a recovery, the loss's attempts and depth scale, the status) is known without the dozen
    # operations that compute it (each 2-4 microseconds at one stream): the same values.
    any_lost = bool(lost.any())
    if any_lost:
        low_count = torch.where(confident & lost, ms.low_count + 1, low_count)
    # The next step starts from these parameters; while they are the solver's, their yaw/pitch/roll is the result's.
    params_ypr: Tensor | None  # None: not known (rows reverted to the confident parameters or adopted)
    params, params_ypr = solved.params, result.ypr_deg.clone()  # (a copy: the caller may modify the result's)
    if any_lost and bool(reverted.any()):
        params, params_ypr = torch.where(reverted.unsqueeze(-1), ms.confident_params, solved.params), None

    # 4. Recovery of lost streams (rare; only the streams concerned). A stream that never started (its
    # initialisation failed) has nothing to recover against: with a detector it is initialised afresh (below).
    restart = None
    if ms.unstarted is not None and detector is not None:
        restart = attempt & ms.unstarted
        attempt = attempt & ~restart
        since = torch.where(restart, torch.zeros_like(since), since)
    adopted_scale = ms.adopted_scale if ms.adopted_scale is not None else torch.ones_like(conf)
    unmatched, unmatched_face = ms.unmatched, ms.unmatched_face  # (None: no detector attempt has counted yet)
    recovery = any_lost and bool(attempt.any())
    if recovery:
        index = attempt.nonzero().squeeze(-1)
        since = torch.where(attempt, torch.zeros_like(since), since)
        made = torch.zeros_like(index) if ms.attempts is None else ms.attempts[index]
        scales = [tc.depth_scale(n) for n in made.tolist()] if detector is None else [1.0] * len(index)
        tried = torch.tensor(scales, dtype=state.params.dtype, device=state.params.device)
        found, r_state, r_result, r_conf, r_diss, r_inside, r_entry, r_starts = _recover(
            model, config, state, ms, frames, index, detector, scales
        )
        if tc.recover_min_patches > 1:  # a candidate on too few fiducial patches scores 0 (as the track above)
            thin = _thin(model, config, ms, frames[index], r_state.params, r_state.shape_coeffs, r_state.intrinsics,
                         index)  # fmt: skip
            r_conf = torch.where(thin, torch.zeros_like(r_conf), r_conf)
        # A candidate that beats the continued track and scores at least adopt_min_confidence (below it the
        # candidate's solve ran off the face: benchmark.py's streams adopted candidates 60-100 degrees off that
        # scored 0.000 beside right tracks scoring less), and disagrees with it by more than adopt_min_angle_deg, is
        # adopted: the stream goes on from it. It ends the loss only at recover_confidence; below that it stays
        # lost, but the next frames refine a candidate near the face rather than a track gone astray (James long
        # run, face back in view at 15 degrees of yaw: the candidates were 1-4 degrees off and scored 0.01-0.48
        # after one solve, the continued track 50-100 degrees off and 0, and the loss lasted 53 frames).
        # A continued track whose face is out of the frame (under min_inside_fraction inside: the rule that declared
        # it lost) competes with no candidate: its confidence is that of the few patches still in view (a face
        # half out at the edge scored 0.95-0.98), and the stream goes on from its last confident parameters anyway.
        # A candidate that passes its own checks (found, solved, in the frame, within the searched depths) and is
        # itself confident (confidence_threshold, not only adopt_min_confidence: a weak match on the background must
        # not take the stream from a face that may come back at the same edge) replaces it: a face back in view,
        # turned 30 degrees, scored 0.90 and stayed LOST while such a track outscored it (tests/tracker/
        # test_managed.py, two views of the face).
        away = inside[index] < tc.min_inside_fraction
        beats = (r_conf > conf[index]) | (away & (r_conf >= tc.confidence_threshold))
        adopt = found & (r_result.status != _FAILED) & beats & (r_conf >= tc.adopt_min_confidence)
        R_track = axis_angle_to_matrix(params[index][:, layout.rotation])
        apart = geodesic_angle_deg(r_result.rotation, R_track)
        apart = (apart > tc.adopt_min_angle_deg) | away
        adopt = adopt & (apart | (r_conf >= tc.recover_confidence))
        if detector is None:  # a searched candidate whose solve left the searched depths went astray itself
            near = _within_searched_depths(r_state.params, ms.confident_params[index], layout, tc, tried)
            adopt = adopt & (near | (r_conf >= tc.recover_confidence))
        adopt = adopt & (r_inside >= tc.min_inside_fraction)
        # (opt-in) nor one turned from the last confident pose faster than a head turns
        adopt = adopt & ~_turned_too_far(r_result.rotation, ms.confident_params[index], ms.low_count[index], tc, layout)
        ok = adopt & (r_conf >= tc.recover_confidence)
        if detector is not None and tc.restart_after_unmatched > 0:
            # The detector found a face and neither its candidate nor the continued track scores
            # adopt_min_confidence: the mosaic matches nothing there (a cut to another person: both score 0.00).
            # After restart_after_unmatched such attempts in a row, each showing the same face, the stream starts
            # afresh from the detector's landmarks (below). A continued track out of the frame matches nothing
            # whatever it scores (``away``, as for the adoption above): a cut to another person while the first
            # one's face stood half out at the edge, whose patches still in view scored 0.98, stayed LOST to the end.
            blind = found & (r_conf < tc.adopt_min_confidence) & ((conf[index] < tc.adopt_min_confidence) | away)
            unmatched, unmatched_face = _count_unmatched(model, config, state, ms, frames, index, r_starts, blind)
        if bool(adopt.any()):
            rows = index[adopt]
            params, params_ypr, face = params.clone(), None, None  # the normalised faces are the track's
            params[rows] = r_state.params[adopt]
            adopted = rows
            result = _scatter_result(result, rows, _result_rows(r_result, adopt))
            conf, diss = conf.clone(), diss.clone()
            conf[rows], diss[rows] = r_conf[adopt], r_diss[adopt]
            entry = entry.clone()
            entry[rows] = r_entry[adopt]
            adopted_scale = adopted_scale.clone()
            adopted_scale[rows] = tried[adopt]
            templates = _scatter_templates(templates, rows, entry_templates(
                model, state.shape_coeffs[rows], ms.mosaic, rows, r_entry[adopt], config.backend),
                in_place=donate or templates is not state.templates)  # fmt: skip
        if bool(ok.any()):
            rows = index[ok]
            recovered = torch.zeros_like(lost)
            recovered[rows] = True
            lost = lost & ~recovered
            low_count = torch.where(recovered, torch.zeros_like(low_count), low_count)
            very_low_count = torch.where(recovered, torch.zeros_like(very_low_count), very_low_count)
            confident = confident | recovered

    if any_lost:  # (a recovery only ends losses: with none lost above, none is now)
        confident = confident & ~lost
        _warn_divided_twice(frames, state.templates[0], lost & ~ms.lost)
    confident_params = torch.where(confident.unsqueeze(-1), params, ms.confident_params)
    # The new state is made once, at the end (with its management); what reads it before then (a new entry, the
    # texture update: rare, or opt-in) gets it as it stands (each replace of a state took 6-9 us at one stream).
    mosaic = ms.mosaic

    # 5. Learning from confident frames: a new mosaic entry, optionally the texture.
    if tc.mosaic:
        if gate is not None and not recovery:  # no recovery changed a stream: the kernel's decision stands
            add, bins = add_if_kept, bins_if_kept
        else:
            bins, near = pose_bins(result.ypr_deg, tc, origin_deg=mosaic.ypr_deg[:, 0])
            add = confident & (conf >= tc.add_confidence) & near & ~has_bin(mosaic, bins)
            add = add & within_reach(mosaic, result.ypr_deg, tc)
            add = add & (mosaic.num_entries < tc.max_entries)
        if bool(add.any()):
            index = add.nonzero().squeeze(-1)
            faces = None if face is None else (face[0][index], face[1][index])
            templates_new, reference_new = _new_entries(model, config, replace(solved, params=params,
                                                        templates=templates), ms, frames, index, faces)  # fmt: skip
            mosaic, _ = add_entries(mosaic, index, templates_new, result.rotation[index], bins[index], reference_new,
                                    max_capacity=tc.max_entries)  # fmt: skip
    if tc.texture_update and bool(confident.any()):
        # (the management as updated so far: only the texture update reads it; below, the new ManagementState is
        # made from mosaic and entry themselves: a replace of its 19 fields took 15-18 us a step at one stream)
        templates, mosaic = _texture_update(model, config, replace(solved, params=params, templates=templates),
                                            replace(ms, mosaic=mosaic, entry=entry), frames, confident)  # fmt: skip
    attempts = torch.zeros_like(ms.low_count) if ms.attempts is None else ms.attempts
    if any_lost:
        attempts = torch.where(lost, attempts + attempt, torch.zeros_like(attempts))  # in the current loss
        adopted_scale = torch.where(lost, adopted_scale, torch.ones_like(adopted_scale))
    else:  # (the zeros and ones those give where no stream is lost; the fresh ones made above stand as they are)
        attempts = attempts if ms.attempts is None else torch.zeros_like(attempts)
        adopted_scale = adopted_scale if ms.adopted_scale is None else torch.ones_like(adopted_scale)
    if unmatched is not None:
        unmatched = torch.where(lost, unmatched, torch.zeros_like(unmatched))  # in the current loss
        if not bool(unmatched.any()):
            unmatched_face = None
        if detector is not None and tc.restart_after_unmatched > 0:
            # at the attempt that reached the count (or went past it: a restart whose initialisation failed is
            # tried again at the next attempt, not at every frame between, each a detector call and a landmark fit)
            again = attempt & (unmatched >= tc.restart_after_unmatched)
            if bool(again.any()):
                restart = again if restart is None else restart | again
    steady = None
    if pose_now is not None:  # (confident excludes the lost, the reverted and the adopted that stay lost)
        run = torch.zeros_like(ms.low_count) if ms.steady is None else ms.steady
        steady = torch.where(confident, run + 1, torch.zeros_like(run))
        if adopted is not None:  # a recovery candidate's pose: no velocity across it (it starts a run when confident)
            steady[adopted] = confident[adopted].to(steady.dtype)
    ms = ManagementState(
        mosaic, ms.layout, entry, low_count, very_low_count, lost, confident_params, since,
        None if params_ypr is None else (params, params_ypr), ms.first, ms.head_rotation, ms.head_translation,
        attempts, adopted_scale, ms.unstarted, unmatched, unmatched_face, pose_now, steady,
    )
    status = torch.where(lost, torch.full_like(result.status, _LOST), result.status) if any_lost else result.status
    result = replace(
        result, status=status, confidence=conf, residual_confidence=result.confidence, dissimilarity=diss,
        mosaic_entry=entry.clone(),
    )  # fmt: skip
    new_state = replace(solved, params=params, templates=templates, management=ms)
    started = None
    if restart is not None and detector is not None and bool(restart.any()):  # (restart: only with a detector)
        new_state, result, started = _restart(model, config, new_state, result, frames, restart, detector)
        ms = cast(ManagementState, new_state.management)  # _restart's
    watched = result
    if graded is not None:  # the streams whose parameters are the solver's: not reverted, not adopted, not restarted
        own = ~reverted
        if adopted is not None:
            own[adopted] = False
        if retried is not None:
            own[retried] = False
        if started is not None:
            own[started] = False
        result = _regraded(result, graded[1], own)
    reported = _in_head_frame(result, ms)  # the offsets this frame was tracked under
    if ms.first is not None:  # the online look-ahead start (initialise_managed(refine_first=...))
        start = axis_angle_to_matrix(state.params.detach()[:, layout.rotation])  # the pose the solve started from
        new_state = _watch_first_pose(model, config, new_state, frames, watched, start)
    if graded is not None:
        new_state = replace(new_state, params=torch.where(own.unsqueeze(-1), graded[0], new_state.params))
    return new_state, reported


def _warn_divided_twice(frames: Tensor, template: Template, lost: Tensor) -> None:
    """Warn where the streams ``lost`` ``(B,)`` bool (those lost at this frame) were lost at a frame that looks
    divided by 255 twice (:func:`~torchface._frame_values.divided_twice_hint`, against the brightest gray value of
    ``template``'s valid points, the finest level's: what the stream's face started with). Such a frame, values in
    [0, 1 / 255] (a preprocessing bug), made the stream LOST without a word, as a black frame does; the steps' check
    of frame values takes it. Read only at a loss (one host read of ``lost`` while some stream is lost), not at
    every frame."""
    if not bool(lost.any()):
        return
    valid = template.valid.detach()
    start = torch.where(valid, template.intensity.detach(), torch.zeros_like(template.intensity)).amax(-1)
    said = {}
    for b in lost.nonzero().flatten().tolist():
        hint = divided_twice_hint(frames[b], float(start[b]))
        if hint:
            said[b] = hint
    if said:
        first = next(iter(said))
        more = f" (and stream(s) {list(said)[1:]})" if len(said) > 1 else ""
        warnings.warn(f"stream {first} is lost at this frame{more}: {said[first]}", RuntimeWarning,
                      stacklevel=_caller_stacklevel())  # fmt: skip


def _caller_stacklevel() -> int:
    """The ``stacklevel`` of a warning issued by the function that calls this that names the first frame outside
    torchface's tracker (:mod:`torchface.tracker`, :mod:`torchface._autocast`) and torch: the caller's line that
    stepped the tracker (``tracker(frames)``, ``managed_step``; ``torchface track``'s job, whose warnings the command
    line prints as its own), however many wrappers (the module's call, :func:`~torchface._autocast.full_precision`,
    inference mode) lie between."""
    here = os.path.dirname(os.path.abspath(__file__))
    inside = (here + os.sep, os.path.join(os.path.dirname(here), "_autocast.py"),
              os.path.dirname(os.path.abspath(torch.__file__)) + os.sep)  # fmt: skip
    frame: FrameType | None = sys._getframe(1)
    level = 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(inside):
        frame, level = frame.f_back, level + 1
    return level


def _predicted_start(params: Tensor, previous: Tensor, apply: Tensor, k: float, layout: ParamLayout) -> Tensor:
    """``params`` ``(B, P)`` whose pose, in rows ``apply`` ``(B,)``, is moved on by ``k`` times the motion from
    ``previous`` ``(B, 6)`` (axis-angle, translation) to it: rotation ``(R R_prev^T)^k R`` (the relative rotation's
    axis-angle scaled by ``k``), translation ``t + k (t - t_prev)``; the other rows and parameters as they are."""
    aa, t = params[:, layout.rotation], params[:, layout.translation]
    previous = previous.to(params.dtype)
    R = axis_angle_to_matrix(aa)
    turn = matrix_to_axis_angle(torch.matmul(R, axis_angle_to_matrix(previous[:, :3]).transpose(1, 2)))
    aa_next = matrix_to_axis_angle(torch.matmul(axis_angle_to_matrix(k * turn), R))
    t_next = t + k * (t - previous[:, 3:6])
    moved = torch.cat([aa_next, t_next, params[:, layout.translation.stop :]], dim=-1)
    return torch.where(apply.unsqueeze(-1), moved, params)


def _graded(solved: TrackerState, result: TrackResult) -> tuple[Tensor, TrackResult] | None:
    """``(params, result)`` of a solve whose estimates carry gradients (:func:`managed_step`), else None."""
    if not torch.is_grad_enabled():  # inference mode or no_grad: the usual case, nothing to look at
        return None
    if not solved.params.requires_grad and not any(
        isinstance(v, Tensor) and v.requires_grad for v in (getattr(result, f.name) for f in fields(TrackResult))
    ):
        return None
    return solved.params, result


def _detached(result: TrackResult) -> TrackResult:
    """``result`` with every tensor detached."""
    changes: dict[str, Any] = {f.name: v.detach() for f in fields(TrackResult)
                               if isinstance(v := getattr(result, f.name), Tensor)}  # fmt: skip
    return replace(result, **changes)


#: TrackResult's fields that template management sets (the solver's estimates are the others).
_DECISIONS = frozenset(
    {"status", "confidence", "residual_confidence", "dissimilarity", "mosaic_entry", "start_failure"}
)


def _regraded(result: TrackResult, graded: TrackResult, own: Tensor) -> TrackResult:
    """``result`` whose estimates that carry gradients in ``graded`` (the solver's; not the fields management sets)
    are ``graded``'s in the streams ``own`` ``(B,)`` (equal values: ``result`` is the detached solve there) and
    ``result``'s elsewhere."""
    out: dict[str, Any] = {}  # field name -> its tensor
    for f in fields(TrackResult):
        if f.name in _DECISIONS:
            continue
        g, v = getattr(graded, f.name), getattr(result, f.name)
        if isinstance(g, Tensor) and g.requires_grad and isinstance(v, Tensor) and v.shape == g.shape:
            out[f.name] = torch.where(own.reshape(-1, *([1] * (g.dim() - 1))), g, v)
    return replace(result, **out)


def _native_select_entries(ms: ManagementState, ypr: Tensor, tc: TemplateConfig) -> tuple[Tensor, Tensor | None]:
    """:func:`~torchface.template.management.select_entries` and the clean-radius test of the chosen entries
    (``(B,)`` int64, ``(B,)`` bool or None when the radius is 0) by the native kernel."""
    m = ms.mosaic
    B, E = m.used.shape
    dtype = m.ypr_deg.dtype
    inputs = [x.contiguous() for x in (m.ypr_deg, m.bins, m.used, _of_dtype(ypr, dtype), ms.entry)]
    entry = torch.empty(B, dtype=torch.int64)
    near = torch.empty(B, dtype=torch.bool) if tc.clean_radius_deg > 0 else None
    prob = _native.ManageProblem(
        B=B, E=E, switch_margin_deg=tc.switch_margin_deg, reference_radius_deg=tc.reference_radius_deg,
        clean_radius_deg=tc.clean_radius_deg, mosaic_ypr=inputs[0].data_ptr(), bins=inputs[1].data_ptr(),
        used=inputs[2].data_ptr(), ypr=inputs[3].data_ptr(), entry=inputs[4].data_ptr(), out_entry=entry.data_ptr(),
        out_near=None if near is None else near.data_ptr(),
    )  # fmt: skip
    _native.run("select_entries", dtype == torch.float64, prob, B, 1)
    return entry, near


def _native_gate(
    ms: ManagementState, ypr: Tensor, conf: Tensor, inside: Tensor, failed: Tensor, tc: TemplateConfig
) -> tuple[Tensor, ...]:
    """managed_step's gating (confident, low and very-low counts, lost, reverted, frames since the last recovery
    attempt, attempt) and, for a stream no recovery changes, whether its frame becomes a mosaic entry and its pose
    bin, by the native kernel: ``(B,)`` tensors and bins ``(B, 2)`` int64."""
    m = ms.mosaic
    B, E = m.used.shape
    dtype = m.ypr_deg.dtype
    inputs = [x.contiguous() for x in (m.ypr_deg, m.bins, m.used, _of_dtype(ypr, dtype), _of_dtype(conf, dtype),
                                       _of_dtype(inside, dtype), failed, ms.lost, ms.low_count, ms.very_low_count,
                                       ms.since_attempt)]  # fmt: skip
    flags = torch.empty(5, B, dtype=torch.bool)  # confident, lost, reverted, attempt, add
    counts = torch.empty(3, B, dtype=torch.int64)  # low, very low, since
    bins = torch.empty(B, 2, dtype=torch.int64)
    f, c = flags.data_ptr(), counts.data_ptr()  # (the rows' addresses: a bool is a byte, an int64 8)
    names = ("mosaic_ypr", "bins", "used", "ypr", "confidence", "inside", "failed", "lost", "low_count",
             "very_low_count", "since")  # fmt: skip
    prob = _native.ManageProblem(
        B=B, E=E, lost_after=tc.lost_after, lost_after_very_low=tc.lost_after_very_low,
        recovery_every=tc.recovery_every, max_entries=tc.max_entries, min_inside_fraction=tc.min_inside_fraction,
        confidence_threshold=tc.confidence_threshold, very_low_confidence=tc.very_low_confidence,
        recover_confidence=tc.recover_confidence, yaw_bin_deg=tc.yaw_bin_deg, pitch_bin_deg=tc.pitch_bin_deg,
        bin_centre_fraction=tc.bin_centre_fraction, entry_reach=tc.entry_reach, add_confidence=tc.add_confidence,
        **{n: x.data_ptr() for n, x in zip(names, inputs)}, out_confident=f, out_low_count=c,
        out_very_low_count=c + 8 * B, out_lost=f + B, out_reverted=f + 2 * B, out_since=c + 16 * B,
        out_attempt=f + 3 * B, out_bins=bins.data_ptr(), out_add=f + 4 * B,
    )  # fmt: skip
    _native.run("gate", dtype == torch.float64, prob, B, 1)
    # (each output a row of flags or counts, unbound at once: a row taken by indexing is an operation of its own)
    confident, lost, reverted, attempt, add = flags.unbind(0)
    low_count, very_low_count, since = counts.unbind(0)
    return confident, low_count, very_low_count, lost, reverted, since, attempt, add, bins


def _reanchored(ms: ManagementState) -> Tensor | None:
    """``(B,)`` bool, the streams whose online start has re-anchored them with an offset (``head_rotation``,
    ``head_translation`` other than the identity); None where no stream has been re-anchored yet."""
    D, d = ms.head_rotation, ms.head_translation  # set together, by the first re-anchoring
    if D is None or d is None:
        return None
    moved = (D - torch.eye(3, dtype=D.dtype, device=D.device)).abs()
    return (moved.flatten(1).amax(-1) > 0) | (d.abs().amax(-1) > 0)


def _check_not_reanchored(ms: object) -> None:
    """Refuse template management turned off mid-sequence (:func:`managed_step` with ``config.template.enabled``
    False) in a state whose streams the online start has re-anchored: the bare step reports the pose of the
    re-anchored head frame, not the first result's, which only management maps back (:func:`_in_head_frame`), so
    their pose jumped by the re-anchoring's offset, unsaid (1.2 degrees of pitch on a rendered 20 degree turn at
    160x120). Turning it on mid-sequence is refused too (the state has no management)."""
    if not isinstance(ms, ManagementState):
        return
    moved = _reanchored(ms)
    if moved is None or not bool(moved.any()):
        return
    streams = moved.nonzero().flatten().tolist()
    raise ValueError(
        f"template management cannot be turned off mid-sequence (config.template.enabled False) once the online start "
        f"has re-anchored streams {streams}: their pose would jump by the re-anchoring's offset (management reports "
        "it in the first result's head frame); keep TrackerConfig.template enabled for this sequence, or start it "
        "again without it (initialise, FaceTracker.initialise)"
    )


def _in_head_frame(result: TrackResult, ms: ManagementState) -> TrackResult:
    """``result`` with its pose expressed in the head frame of the stream's first result: ``R D`` and
    ``R d + t`` for the estimate ``(R, t)`` and the re-anchoring offset ``(D, d)`` (``head_rotation``,
    ``head_translation``: None until a stream is re-anchored; identity in the rows of the others, which are left
    untouched)."""
    D, d = ms.head_rotation, ms.head_translation  # set together, by the first re-anchoring
    if D is None or d is None:
        return result
    moved = (D - torch.eye(3, dtype=D.dtype, device=D.device)).abs()
    moved = (moved.flatten(1).amax(-1) > 0) | (d.abs().amax(-1) > 0)
    if not bool(moved.any()):
        return result
    D, d = D.to(result.rotation.dtype), d.to(result.translation.dtype)
    R = torch.matmul(result.rotation, D)
    t = torch.matmul(result.rotation, d.unsqueeze(-1)).squeeze(-1) + result.translation
    m3, m33 = moved[:, None], moved[:, None, None]
    return replace(
        result, rotation=torch.where(m33, R, result.rotation), translation=torch.where(m3, t, result.translation),
        axis_angle=torch.where(m3, matrix_to_axis_angle(R), result.axis_angle),
        ypr_deg=torch.where(m3, matrix_to_euler(R), result.ypr_deg),
    )  # fmt: skip


def _reset_mosaic_rows(mosaic: Mosaic, index: Tensor, sub: Mosaic) -> Mosaic:
    """``mosaic`` whose streams ``index`` hold only ``sub``'s entry 0 (``sub`` has batch ``len(index)``)."""

    def put(x: Tensor, y: Tensor, empty: bool | None = None) -> Tensor:
        x = x.clone()
        if empty is not None:
            x[index] = empty
        x[index, 0] = y[:, 0].to(x.dtype)
        return x

    with torch.inference_mode(False):
        levels = tuple(
            MosaicLevel(put(a.face_index, b.face_index), put(a.bary, b.bary), put(a.intensity, b.intensity),
                        put(a.valid, b.valid, False))  # fmt: skip
            for a, b in zip(mosaic.levels, sub.levels)
        )
        pairs = zip(_reference_tensors(mosaic.references), _reference_tensors(sub.references))
        ref = iter([put(x, y) for x, y in pairs])
        return Mosaic(
            levels, put(mosaic.rotation, sub.rotation), put(mosaic.ypr_deg, sub.ypr_deg), put(mosaic.bins, sub.bins),
            put(mosaic.used, sub.used, False), _map_reference(mosaic.references, lambda _: next(ref)),
        )  # fmt: skip


def _watch_first_pose(
    model: FaceModel, config: TrackerConfig, state: TrackerState, frames: Tensor, result: TrackResult,
    start_rotation: Tensor,
) -> TrackerState:
    """Keyframes for the streams still waiting (``result`` in the internal frame), and the re-anchoring of those
    that have them all (:func:`initialise_managed`'s ``refine_first``). ``start_rotation`` ``(B, 3, 3)``: the
    rotation each stream's step started from (the previous frame's estimate); a stream whose estimate turned more
    than :data:`~torchface.tracker.lookahead.KEYFRAME_MAX_STEP_DEG` from it (a video cut) stops waiting."""
    ms = _management(state)
    w = ms.first
    if w is None:  # no stream waits for its keyframes (managed_step calls this only while one does)
        return state
    lc = w.config
    rel = result.ypr_deg[:, 0] - w.yaw0.to(result.ypr_deg.dtype)
    view_rel = rel.to(torch.float64) if w.view_yaw0 is None else (
        view_yaw_deg(result.rotation, result.translation) - w.view_yaw0.to(torch.float64))
    # A video cut (a jump no head makes between two frames) ends the stream's wait: it keeps its landmark fit
    cut = w.pending & is_video_cut(start_rotation, result.rotation)
    ok = w.pending & ~cut & result.success & (result.confidence >= lc.min_confidence)
    keys = list(w.keys)
    with torch.inference_mode(False):
        sides = w.sides.clone()
        for side, sign in enumerate((1.0, -1.0)):
            turned = is_keyframe_turn(sign * rel.to(torch.float64), sign * view_rel, lc.yaw_deg).to(ok.device)
            for b in (ok & turned).nonzero().squeeze(-1).tolist():
                if not bool(sides[b, side]):
                    sides[b, side] = True  # the newest keyframe goes last: it is this frame
                    key = (frames[b].clone(), result.rotation[b].clone(), result.translation[b].clone(),
                           result.expression[b].clone())
                    keys[b] = keys[b] + (key,)
    ready = w.pending & (sides.sum(-1) >= lc.min_keyframes)
    seen = w.frames_seen + 1
    pending = w.pending & ~ready & ~cut & (seen < lc.max_frames)
    if bool(ready.any()):
        state = _reanchor(model, config, state, w, keys, ready.nonzero().squeeze(-1), frames)
        ms = _management(state)
    first = None if not bool(pending.any()) else replace(w, keys=tuple(keys), sides=sides, pending=pending,
                                                          frames_seen=seen)  # fmt: skip
    return replace(state, management=replace(ms, first=first))


#: The online start's re-anchoring refines at most this many streams in one batched solve (more that re-anchor on
#: one frame go in further solves): the solve holds each stream's frames' pyramids with their gradients in float64,
#: 19 MB a stream with one keyframe at 640x480 (128 streams at once would have held 2.5 GB, twice over while they were
#: stacked), and 16 already share its per-operation overhead (a stream's result does not depend on the others').
REANCHOR_BATCH: int = 16


def _reanchor(
    model: FaceModel, config: TrackerConfig, state: TrackerState, w: FirstPoseWatch,
    keys: list[tuple[tuple[Tensor, Tensor, Tensor, Tensor], ...]], index: Tensor, frames: Tensor,
) -> TrackerState:
    """Streams ``index`` re-anchored at this frame (``frames``), their newest keyframe: their first frame's fit
    refined against their keyframes, their templates and mosaic rebuilt from the first frame at the refined pose,
    this frame's pose replaced by its refined one and added to the mosaic, and the offset that keeps their
    reported poses in the head frame of their first result."""
    ms = _management(state)
    fc = config.fit
    streams = index.tolist()
    la = levels_of(w.config, config.num_levels)
    with torch.inference_mode(False):
        # Each stream's problem set up alone (its template points; its priors: a sparse start keeps the fit's sparse
        # priors), then one batched refinement of the streams re-anchoring on this frame (Levenberg-Marquardt with
        # each stream's own damping and stopping: each as alone, to 1e-5). Refined one after another, 8 streams at
        # 320x240 took this frame 2.6-3.3 s of CPU on one thread; together 1.7-1.8 (docs/speed.md): the solve's
        # arithmetic grows with the streams, its per-operation overhead no longer.
        def start(b: int) -> _Start:
            ks = keys[b]
            weights = None if w.weights is None else w.weights[b]
            seen = [w.frame0[b]] + [k[0] for k in ks]
            if len({f.shape[0] for f in seen}) > 1:  # RGB and gray frames in one stream (each step takes either): all
                # made gray as the refinement makes them, in its float64 (torch.stack's "expects each tensor to be
                # equal size" ended the step); a stream of one kind is refined as before, to the bit
                seen = [to_gray(f[None].to(torch.float64))[0] for f in seen]
            return _stream_start(
                model, torch.stack(seen), state.intrinsics, w.landmarks[b],
                w.fit.select([b]), torch.stack([k[1] for k in ks]), torch.stack([k[2] for k in ks]),
                key_expression=torch.stack([k[3] for k in ks]), landmark_weights=weights, config=la,
                backend=config.backend, **landmark_fit_priors(model, fc, state.intrinsics, w.landmarks[b], weights),
            )  # fmt: skip

        # (streams of another keyframe count, which min_keyframes=1 never gives on one frame, are solved apart; at
        # most REANCHOR_BATCH at once, each chunk's problems set up just before its solve)
        groups: dict[int, list[int]] = {}
        for i, b in enumerate(streams):
            groups.setdefault(len(keys[b]), []).append(i)
        refined: dict[int, tuple[LandmarkFit, Tensor, Tensor]] = {}  # per stream: its fit, this frame's pose
        for members in groups.values():
            for c in range(0, len(members), REANCHOR_BATCH):
                chunk = members[c : c + REANCHOR_BATCH]
                out, key_R, key_t = _refine_starts(model, [start(streams[i]) for i in chunk], state.intrinsics, la,
                                                   backend=config.backend)  # fmt: skip
                for j, i in enumerate(chunk):
                    refined[i] = out.select([j]), key_R[j, -1], key_t[j, -1]
        fits = [refined[i][0] for i in range(len(streams))]
        now_R, now_t = [refined[i][1] for i in range(len(streams))], [refined[i][2] for i in range(len(streams))]
        fit = LandmarkFit(*(torch.cat([getattr(f, n) for f in fits]) for n in LandmarkFit.__dataclass_fields__))
        fit = fit.to(model.device, model.dtype)
    weights = None if w.weights is None else w.weights[index]
    sub, sub_result = initialise_managed(model, config, w.frame0[index], w.landmarks[index], state.intrinsics, weights,
                                         fit=fit)  # fmt: skip
    started = sub_result.status != _FAILED
    if not bool(started.all()):  # a refined start that fails (a face that came out too small, ...) keeps no template
        # points (initialise): those streams go on from their plain start (they took the failed start's templates)
        keep = started.tolist()
        index, fit, sub = index[started], fit.select(started), sub.select(started)
        now_R, now_t = [r for r, k in zip(now_R, keep) if k], [t for t, k in zip(now_t, keep) if k]
        if not index.numel():
            return state
    templates = _scatter_templates(state.templates, index, sub.templates)
    with torch.inference_mode(False):
        shape = state.shape_coeffs.clone()
        shape[index] = sub.shape_coeffs
        prior = None
        if state.anim_prior_mean is not None:
            prior = state.anim_prior_mean.clone()
            prior[index] = sub.neutral_anim_coeffs(prior[index])  # sub's anim_prior_mean (initialise sets it)
        R0, t0 = w.fit.rotation[index], w.fit.translation[index]  # the first result's pose
        R0c, t0c = fit.rotation, fit.translation
        if ms.head_rotation is None or ms.head_translation is None:  # the first re-anchoring (they are set
            # together): every stream's offset starts as the identity
            B = state.params.shape[0]
            head_R = torch.eye(3, dtype=model.dtype, device=model.device).expand(B, 3, 3).clone()
            head_t = torch.zeros(B, 3, dtype=model.dtype, device=model.device)
        else:
            head_R, head_t = ms.head_rotation.clone(), ms.head_translation.clone()
        head_R[index] = torch.matmul(R0c.transpose(1, 2), R0).to(head_R.dtype)
        head_t[index] = torch.matmul(R0c.transpose(1, 2), (t0 - t0c).unsqueeze(-1)).squeeze(-1).to(head_t.dtype)
        entry = ms.entry.clone()
        entry[index] = 0
        layout = _layout(model)
        params = state.params.clone()
        R_now = torch.stack(now_R).to(params.dtype)
        params[index, layout.rotation] = matrix_to_axis_angle(R_now)
        params[index, layout.translation] = torch.stack(now_t).to(params.dtype)
        if not config.use_expression:
            # Without expression estimation the coefficients are never re-solved: they are the neutral, now the
            # refined one the templates hold (they kept the old one: a constant false expression of 0.07 from
            # here on). With it, the next solve starts from the coefficients as they are: starting it from them
            # moved about the new neutral instead took occlusion's max error from 4.53 to 6.78 degrees.
            params[index, layout.animation] = fit.anim_coeffs.to(params.dtype)
        # The frame is confident (the keyframe test asked it); its refined parameters are the ones a failure or a
        # loss from the next frame on falls back to (kept at the unrefined pose, 2 degrees and 11 mm off).
        confident_params = ms.confident_params.clone()
        confident_params[index] = params[index]
        steady = ms.steady
        if steady is not None:  # the pose moved to the refined one: no velocity across it
            steady = steady.clone()
            steady[index] = 0
    mosaic = _reset_mosaic_rows(ms.mosaic, index, _management(sub).mosaic)
    ms = replace(ms, mosaic=mosaic, entry=entry, head_rotation=head_R, head_translation=head_t, params_ypr=None,
                 confident_params=confident_params, steady=steady)  # fmt: skip
    state = replace(state, params=params, templates=templates, shape_coeffs=shape, anim_prior_mean=prior,
                    management=ms)  # fmt: skip
    # This frame, at its refined pose, becomes the stream's second mosaic entry (the head is turned: without it
    # the stream would be measured against the frontal entry alone until its mosaic grows again).
    tc = config.template
    if tc.mosaic and tc.max_entries > 1:
        bins, _ = pose_bins(matrix_to_euler(R_now), tc, origin_deg=ms.mosaic.ypr_deg[index, 0])
        fresh = ~has_bin(ms.mosaic, bins, streams=index)
        if bool(fresh.any()):
            rows = index[fresh]
            tpl, ref = _new_entries(model, config, state, ms, frames, rows, None)
            mosaic, _ = add_entries(ms.mosaic, rows, tpl, R_now[fresh], bins[fresh], ref, max_capacity=tc.max_entries)
            state = replace(state, management=replace(ms, mosaic=mosaic))
    return state
