"""The normalised face as a differentiable ``nn.Module`` layer, with detached or unrolled tracking.

:class:`NormalisedFaceLayer` turns frames and a tracker state into normalised faces
(:func:`torchface.normalise.normalised_face`: frontal, neutral, evenly lit, ``(B, C, G, G)`` plus a mask) for
use inside a network. The face parameters ``x = (omega, t, alpha, lambda)`` of each frame come from the
tracker (paper Eq. 20); how gradients reach the frame pixels ``I`` depends on :class:`LayerMode`:

``DETACHED`` (default, fast)
    ``x`` is estimated by :func:`torchface.tracker.track_step` under ``torch.no_grad`` and treated as a
    constant. The normalised face is linear in the pixels (bilinear resampling, then the inverse of Eq. 19),
    so ``d face / d I`` is the resampling alone.

``UNROLLED``
    ``K`` Gauss-Newton iterations of the tracker's reference objective (Eq. 20,
    :func:`torchface.tracker.frame_residuals`, the same robust weights, bounds and prior as the REFERENCE
    path of :func:`~torchface.tracker.track_step`) run with autograd on
    (:func:`torchface.solver.least_squares` with ``differentiable=True``), so ``x_K`` is a function of the
    pixels and ``d face / d I`` also holds ``d face / d x_K . d x_K / d I``: the gradient reaches the frames
    through the tracking. Where the iterations start is :class:`UnrollStart`:

    * ``TRACKED``: from the detached tracker's estimate ``x*`` (held constant). ``K = 0`` is exactly the
      detached mode; one step from a converged ``x*``, ``x_1 = x* - H^-1 g(x*, I)``, has
      ``d x_1 / d I = -H^-1 d g / d I`` (``g(x*) = 0``), the implicit-function gradient of the minimiser with
      the Gauss-Newton Hessian ``H = J^T W J``.
    * ``PREVIOUS``: from the state's previous-frame estimate, which does not depend on the frame: the
      ``K`` iterations on each unrolled pyramid level are the whole tracking and the gradient is exact for
      the output computed.

The mask (visibility) and the tracker state carried to the next frame are not differentiable. The state
passed in may come from :meth:`NormalisedFaceLayer.initialise` (first frame and its landmarks) or from a
:class:`~torchface.tracker.FaceTracker`; the layer never stores per-sequence state.

Shapes: ``B`` batch, ``T`` frames, ``C`` channels, ``H x W`` frames, ``K`` landmarks, ``P`` packed parameters
(:class:`~torchface.tracker.ParamLayout`), ``G x G`` the normalised image; see :mod:`torchface.conventions`.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import torch
from torch import Tensor

from torchface.appearance.illumination import NUM_ILLUMINATION_TERMS
from torchface.extending import (
    DeviceCheckedModule,
    check_bool,
    check_choice,
    check_int,
    check_intrinsics,
    check_number,
    full_precision,
    is_compiling,
)
from torchface.geometry.camera import Intrinsics
from torchface.model.candide import load_candide3
from torchface.model.face_model import FaceModel
from torchface.normalise.face import (
    NormalisedFaceLayout,
    NormalisedFaceResult,
    apply_to_model_and_layout,
    build_normalised_layout,
    normalised_face,
)
from torchface.solver.least_squares import SolverConfig, SolverMethod
from torchface.tracker.fit import check_landmark_type
from torchface.tracker.module import (
    auto_levels, check_continuing_levels, check_pyramid, continuing_config, note_auto_levels,
)
from torchface.tracker.params import ParamLayout
from torchface.tracker.step import (
    TrackerConfig,
    TrackerState,
    TrackResult,
    check_frames,
    initialise,
    parameter_bounds,
    pyramid_for_faces,
    reference_levels,
    track_step,
)
from training_hooks.transforms import FaceTrackingConfig

__all__ = [
    "LayerMode",
    "UnrollStart",
    "LayerConfig",
    "LayerResult",
    "unrolled_params",
    "NormalisedFaceLayer",
]


class LayerMode(enum.Enum):
    """How the face parameters enter the autograd graph (module docstring)."""

    #: Parameters from the tracker under ``no_grad``; gradients reach the pixels through the resampling only.
    DETACHED = "detached"
    #: ``K`` differentiable Gauss-Newton iterations of the reference objective; gradients also go through them.
    UNROLLED = "unrolled"


class UnrollStart(enum.Enum):
    """Where the unrolled iterations start (module docstring)."""

    #: The detached tracker's estimate of this frame (``K = 0`` is the detached mode).
    TRACKED = "tracked"
    #: The state's previous-frame estimate (the iterations are the whole tracking; exact gradient).
    PREVIOUS = "previous"


@dataclass(frozen=True)
class LayerConfig:
    """Settings of :class:`NormalisedFaceLayer`.

    Attributes:
        mode: :class:`LayerMode`.
        size: ``G``, the normalised face is ``G x G``: 128 by default, the size of the datasets' items
            (:attr:`FaceTrackingConfig.face_size <training_hooks.transforms.FaceTrackingConfig.face_size>`) and of
            :class:`~torchface.normalise.NormalisedFace`'s, so that a network trained on one takes the others' faces
            (the default was 64 before, half the datasets').
        margin: empty fraction around the face in the canonical view
            (:func:`~torchface.normalise.build_normalised_layout`).
        keep_expression: resample at the person's neutral expression (the first frame's fitted coefficients,
            :meth:`~torchface.tracker.TrackerState.neutral_anim_coeffs`) instead of the estimated one, so the
            canonical image keeps the expression (texture displaced where the face moved) with pose and
            light undone: what an expression classifier needs. False undoes the expression too (paper Section 4).
        normalise_light: undo the estimated light (inverse of Eq. 19); False keeps the frame's light.
        unrolled_iterations: ``K``, Gauss-Newton iterations per unrolled pyramid level (``UNROLLED`` only; at
            least 1 from :attr:`UnrollStart.PREVIOUS`, where ``K = 0`` would not track at all).
        unrolled_levels: how many of the finest pyramid levels are unrolled, coarse to fine (``UNROLLED``).
        start: :class:`UnrollStart` (``UNROLLED`` only).
        tracker: the tracker's settings (the detached estimate, and the objective of the unrolled iterations).
        pyramid: ``"auto"`` (the default): :meth:`NormalisedFaceLayer.initialise` adds coarser pyramid levels for
            large faces as :class:`~torchface.tracker.FaceTracker` does
            (:func:`~torchface.tracker.pyramid_for_faces`: HD video, where the default three levels lost fast
            motion; faces under 254.5 pixels keep ``tracker``), and a state is tracked on with the levels it holds
            (:attr:`~torchface.tracker.TrackerState.num_levels`). ``"config"``: ``tracker.num_levels`` as given.
    """

    mode: LayerMode = LayerMode.DETACHED
    size: int = 128
    margin: float = 0.05
    keep_expression: bool = False
    normalise_light: bool = True
    unrolled_iterations: int = 1
    unrolled_levels: int = 1
    start: UnrollStart = UnrollStart.TRACKED
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    pyramid: str = "auto"

    def __post_init__(self) -> None:
        check_pyramid(self.pyramid)
        check_choice(self.mode, "mode", LayerMode)
        check_choice(self.start, "start", UnrollStart)
        if not isinstance(self.tracker, TrackerConfig):
            # (the datasets' FaceTrackingConfig, whose face size and expression setting are LayerConfig's own here,
            # was told the type alone)
            hint = ("; LayerConfig holds its tracker, size and keep_expression itself: LayerConfig(tracker=c.tracker, "
                    "size=c.face_size, keep_expression=c.keep_expression)"
                    if isinstance(self.tracker, FaceTrackingConfig) else "")  # fmt: skip
            raise TypeError(f"tracker must be a TrackerConfig, got {type(self.tracker).__name__}{hint}")
        for name, low in (("size", 4), ("unrolled_iterations", 0), ("unrolled_levels", None)):
            object.__setattr__(self, name, check_int(getattr(self, name), name, low))
        for name in ("keep_expression", "normalise_light"):  # "no" was true
            object.__setattr__(self, name, check_bool(getattr(self, name), name))
        # ("0.05" was taken, a str; out of range was found only when a layer was built from it)
        object.__setattr__(self, "margin", check_number(self.margin, "margin", "[0, 0.45]", unit="a fraction of the image size"))
        if self.mode is LayerMode.UNROLLED and self.start is UnrollStart.PREVIOUS and self.unrolled_iterations == 0:
            # (each frame was resampled at the previous frame's estimate: no tracking at all, a frame's motion off)
            raise ValueError(
                "unrolled_iterations=0 from UnrollStart.PREVIOUS does no tracking (each frame would be resampled at "
                "the previous frame's estimate): use unrolled_iterations >= 1, or UnrollStart.TRACKED (K = 0 is the "
                "detached mode)"
            )
        if not 1 <= self.unrolled_levels <= self.tracker.num_levels:
            raise ValueError(
                f"unrolled_levels must be in [1, tracker.num_levels = {self.tracker.num_levels}], "
                f"got {self.unrolled_levels}"
            )


@dataclass(frozen=True, eq=False)
class LayerResult:
    """What :class:`NormalisedFaceLayer` returns.

    Attributes:
        image: ``(B, C, G, G)`` the normalised faces (0 where ``mask`` is 0); differentiable w.r.t. the frames, so
            not clamped (the light normalisation can put a few values a little outside ``[0, 1]``, where a clamp would
            zero the gradient): the datasets' items are clamped to ``[0, 1]`` and rounded to ``1 / 255`` by default
            (``FaceStorage.UINT8``); ``image.clamp(0, 1)`` gives a network trained on them the range it saw.
        mask: ``(B, 1, G, G)`` float, 1 where the canonical point is visible (not differentiable).
        params: ``(B, P)`` the parameters the faces were resampled with (in the graph in ``UNROLLED`` mode).
        state: the detached tracker state after this frame (pass it with the next frame).
        track: the detached tracker's :class:`~torchface.tracker.TrackResult` of this frame (confidence,
            status, pose, ... of the estimate carried in ``state``); of a clip
            (:meth:`NormalisedFaceLayer.forward_clip`), the last frame's.
        success: ``(B,)`` bool, ``track.success`` (the estimate is usable); of a clip ``(B, T)``, one per frame
            (frame 0: the initialisation's), to leave failed frames out of a loss (e.g. as the ``mask`` of
            :func:`~training_hooks.hooks.confidence_weighted_loss`).
        confidence: ``(B,)`` float, ``track.confidence`` in ``[0, 1]``; of a clip ``(B, T)``, one per frame (frame 0:
            the landmark fit's, :func:`~torchface.tracker.initialise`). Not differentiable.

    Per frame, a clip's ``success`` and ``confidence`` are those of the frame-by-frame steps (``initialise``, then
    ``forward``): ``{"confidence": out.confidence, "success": out.success}`` is a clip batch for
    :func:`~training_hooks.hooks.drop_low_confidence` and :func:`~training_hooks.hooks.sample_confidence`.
    """

    image: Tensor
    mask: Tensor
    params: Tensor
    state: TrackerState
    track: TrackResult
    success: Tensor
    confidence: Tensor


_F = TypeVar("_F", bound=Callable)


def _tracked(fn: _F) -> _F:
    """``fn`` (the tracking, detached or unrolled), run eagerly where ``torch.compile`` traces the layer (autograd
    goes through it as in eager mode): traced, the tracker's native kernels got the pointers of the traced tensors
    instead of the call's and crashed the process. Outside a compiled region ``fn`` itself (nothing changes)."""
    return torch.compiler.disable(fn) if is_compiling() else fn


def _unrolled_solver(iterations: int) -> SolverConfig:
    # Plain Gauss-Newton: every finite step is taken, so the graph is the same for nearby inputs (an LM
    # accept/reject decision would flip under a finite-difference probe near convergence). No tolerances:
    # exactly ``iterations`` steps (a sample stops early only if its cost is unchanged to working precision).
    return SolverConfig(
        method=SolverMethod.GAUSS_NEWTON, max_iterations=iterations, step_tolerance=0.0, cost_tolerance=0.0,
        differentiable=True,
    )


@full_precision
def unrolled_params(
    model: FaceModel,
    config: TrackerConfig,
    state: TrackerState,
    frames: Tensor,
    start: Tensor,
    iterations: int,
    levels: int = 1,
) -> Tensor:
    """``iterations`` differentiable Gauss-Newton steps per pyramid level of the reference objective (Eq. 20).

    The objective of each level is the REFERENCE path's of :func:`~torchface.tracker.track_step`, solved by
    the same level loop (:func:`~torchface.tracker.step.reference_levels`): residuals
    :func:`~torchface.tracker.frame_residuals` of the state's template on the frame's gray pyramid, the light
    basis with the normals rotated by the previous estimate, z-buffer visibility at the previous estimate
    (when ``config.zbuffer_visibility``), the animation units boxed to the model's ranges, the expression
    prior, and IRLS weights of ``config.robust`` with that level's scale floor. Levels run coarse to fine over
    the ``levels`` finest ones. Everything that depends on the frame (image, its gradients, the residuals,
    the Jacobian, the robust weights) stays in the autograd graph; visibility is a constant mask.

    Args:
        model: the face model of the state.
        config: the tracker settings the state was built with.
        state: from :func:`~torchface.tracker.initialise` or a previous step (its template and previous
            estimate).
        frames: ``(B, C, H, W)`` float in ``[0, 1]`` at the state's size, in the model's dtype (may require grad).
        start: ``(B, P)`` initial parameters (may require grad).
        iterations: ``K >= 0`` steps per level (``0`` returns ``start`` projected on the bounds).
        levels: number of finest pyramid levels unrolled, in ``[1, config.num_levels]``.

    Returns:
        ``(B, P)`` the parameters after the iterations; a sample whose solve failed keeps its last good value.

    Raises:
        TypeError, ValueError: on frames or parameters of the wrong shape, dtype or size.

    Example:
        >>> # x = unrolled_params(model, config, state, frames.requires_grad_(), state.params, iterations=2)
        >>> # x.sum().backward()   # frames.grad now holds d(sum x)/d(frames) through the tracking
    """
    check_frames(frames, state.intrinsics)
    layout = ParamLayout(model.num_animation, NUM_ILLUMINATION_TERMS)
    B = state.params.shape[0]
    if frames.shape[0] != B:
        raise ValueError(f"expected {B} frames (one per stream of the state), got {frames.shape[0]}")
    if frames.dtype != model.dtype:
        raise TypeError(f"frames must be in the model's dtype {model.dtype}, got {frames.dtype}")
    if not isinstance(start, Tensor):
        raise TypeError(f"start must be a ({B}, {layout.size}) {model.dtype} tensor, got {type(start).__name__}")
    if tuple(start.shape) != (B, layout.size) or start.dtype != model.dtype:
        raise ValueError(f"start must be ({B}, {layout.size}) {model.dtype}, got {(tuple(start.shape), start.dtype)}")
    iterations = check_int(iterations, "iterations", 0)
    levels = check_int(levels, "levels")
    if not 1 <= levels <= config.num_levels:
        raise ValueError(f"levels must be in [1, {config.num_levels}], got {levels}")
    if len(state.templates) != config.num_levels:
        raise ValueError(
            f"the state has {len(state.templates)} template levels, config.num_levels is {config.num_levels}"
        )

    if iterations == 0:
        with torch.no_grad():
            lower, upper = parameter_bounds(model, config, state.params.detach(), layout)  # the reference path's
        return torch.minimum(torch.maximum(start, lower), upper)
    x, _ = reference_levels(model, config, state, frames, start, [_unrolled_solver(iterations)] * levels)
    return x


class NormalisedFaceLayer(DeviceCheckedModule):
    """Normalised faces of tracked frames as a layer: ``(frames, state) -> LayerResult`` (module docstring).

    Holds the face model, the canonical layout and the settings; the per-sequence tracker state is passed in
    and returned, never stored.

    Args:
        config: :class:`LayerConfig`.
        model: the face model (CANDIDE-3 when ``None``); its dtype and device are the layer's, and move with
            ``.to(...)``, ``.double()``, ``.float()``, ``.cuda()``. Tracking needs float32 or float64: a layer
            cast to float16 or bfloat16 (``.half()`` of the network) raises a TypeError when called.

    Under ``torch.compile`` the tracking (:meth:`initialise`, the detached step and the unrolled iterations) runs
    eagerly, a graph break (its native kernels cannot be traced; the gradient goes through it as in eager mode); the
    resampling and the rest of the network are compiled.

    Example:
        >>> layer = NormalisedFaceLayer(LayerConfig(mode=LayerMode.UNROLLED, size=48))   # doctest: +SKIP
        >>> state, _ = layer.initialise(frames0, landmarks0)               # (B, 3, H, W), (B, 68, 2)  # doctest: +SKIP
        >>> out = layer(frames1.requires_grad_(), state)                   # doctest: +SKIP
        >>> loss(net(out.image)).backward()       # frames1.grad through resampling and tracking  # doctest: +SKIP
    """

    def __init__(self, config: LayerConfig | None = None, model: FaceModel | None = None) -> None:
        super().__init__()
        self.config = LayerConfig() if config is None else config
        if not isinstance(self.config, LayerConfig):
            raise TypeError(f"config must be a LayerConfig, got {type(self.config).__name__}")
        self.model = load_candide3() if model is None else model
        if not isinstance(self.model, FaceModel):
            raise TypeError(f"model must be a FaceModel, got {type(self.model).__name__}")
        self.layout: NormalisedFaceLayout = build_normalised_layout(self.model, self.config.size, self.config.margin)

    def _apply(self, fn: Callable[[Tensor], Tensor], recurse: bool = True) -> "NormalisedFaceLayer":
        """Move the face model and the layout with the module (``.to``, ``.double``, ``.float``, ``.cuda``, ...)."""
        self.model, self.layout = apply_to_model_and_layout(fn, self.model, self.layout)
        return super()._apply(fn, recurse)

    def _check_precision(self) -> None:
        # The tracker's solves (Cholesky) have no float16 / bfloat16 kernels: say so instead of torch's
        # '"cholesky_cpu" not implemented for 'Half'' from deep inside the landmark fit or the step.
        if self.model.dtype not in (torch.float32, torch.float64):
            raise TypeError(
                f"NormalisedFaceLayer tracks in float32 or float64, it is {self.model.dtype} (a .half() or "
                ".to(bfloat16) of the network?): keep the layer in float32 (layer.float()) and cast its image, "
                "or run the network under torch.autocast, which leaves the layer in full precision"
            )

    @property
    def param_layout(self) -> ParamLayout:
        """The packing of :attr:`LayerResult.params`."""
        return ParamLayout(self.model.num_animation, NUM_ILLUMINATION_TERMS)

    @torch.no_grad()
    def initialise(
        self, frames: Tensor, landmarks_px: Tensor, intrinsics: Intrinsics | None = None
    ) -> tuple[TrackerState, TrackResult]:
        """Fit the first frames from their landmarks (Eq. 2) and build the templates (detached).

        Args:
            frames: ``(B, 3, H, W)`` RGB or ``(B, 1, H, W)`` gray, float in ``[0, 1]``.
            landmarks_px: ``(B, K, 2)`` the model's landmarks (68 iBUG points for CANDIDE-3), pixels; NaN rows:
                missing. A stream whose start fails (fewer than 4 landmarks: no face found; landmarks that hold no
                pose, a face too small: :func:`~torchface.tracker.initialise`) is FAILED here and at every later
                frame, at confidence 0 and its first parameters, with finite images and gradients; the others are
                as without it.
            intrinsics: camera of the frames; default :meth:`Intrinsics.default` of their size.

        Returns:
            The tracker state and the first frame's result.

        Raises:
            TypeError: the layer is not float32 or float64 (e.g. after ``.half()``).
        """
        self._check_precision()
        check_frames(frames)
        if intrinsics is None:
            intrinsics = Intrinsics.default(frames.shape[-1], frames.shape[-2])
        check_intrinsics(intrinsics)  # (pyramid="auto" reads its size before initialise checks it: an AttributeError)
        check_landmark_type(landmarks_px, "(B, K, 2)")  # (numpy ones: an AttributeError, no attribute detach)
        frames = frames.detach().to(dtype=self.model.dtype, device=self.model.device)
        landmarks_px = landmarks_px.detach().to(dtype=self.model.dtype, device=self.model.device)
        config = self.config.tracker
        if self.config.pyramid == "auto" and landmarks_px.dim() == 3 and landmarks_px.shape[-1] == 2:
            config = pyramid_for_faces(config, landmarks_px, (intrinsics.height, intrinsics.width))
        state, result = _tracked(initialise)(self.model, config, frames, landmarks_px, intrinsics)
        note_auto_levels(state, config.num_levels - self.config.tracker.num_levels)  # (for forward: continuing_config)
        return state, result

    def normalise(self, frames: Tensor, state: TrackerState, params: Tensor) -> NormalisedFaceResult:
        """Resample ``(B, C, H, W)`` frames with ``(B, P)`` parameters and the state's shape and camera.

        Frame by frame, frame 0's face is ``layer.normalise(frames0, state, state.params)`` with the state of
        :meth:`initialise` (which returns a ``TrackResult``, no face): what :meth:`forward_clip` gives at ``t = 0``.

        Args:
            frames: ``(B, C, H, W)`` float in ``[0, 1]`` (may require grad: the gradient reaches them through the
                resampling).
            state: the tracker state whose shape coefficients, neutral expression and camera are used.
            params: ``(B, P)`` packed pose, expression and light (``state.params``, or an unrolled step's).

        Returns:
            :class:`~torchface.normalise.NormalisedFaceResult`: ``image (B, C, G, G)``, ``mask (B, 1, G, G)``, with
            ``G`` = :attr:`LayerConfig.size`.
        """
        aa, t, alpha, light = self.param_layout.split(params)
        if self.config.keep_expression:  # the person's neutral: the first frame's fitted coefficients
            alpha = state.neutral_anim_coeffs(alpha).detach()
        return normalised_face(
            frames, self.model, self.layout, state.shape_coeffs.detach(), alpha, aa, t,
            light if self.config.normalise_light else None, state.intrinsics,
        )  # fmt: skip

    def forward(self, frames: Tensor, state: TrackerState) -> LayerResult:
        """Track ``(B, C, H, W)`` frames from ``state`` and return their normalised faces.

        Args:
            frames: ``(B, 3, H, W)`` RGB or ``(B, 1, H, W)`` gray (as :meth:`initialise`'s), float in ``[0, 1]``, the
                next frame of each stream (may require grad).
            state: the tracker state after the previous frame (:meth:`initialise` or an earlier call).

        Returns:
            :class:`LayerResult`; ``result.state`` continues the sequence.

        Raises:
            TypeError: a state of another kind, or the layer is not float32 or float64 (e.g. after ``.half()``).
        """
        self._check_precision()
        if not isinstance(state, TrackerState):
            raise TypeError(f"state must be a TrackerState (from initialise), got {type(state).__name__}")
        check_frames(frames, state.intrinsics)
        if frames.shape[0] != state.params.shape[0]:
            raise ValueError(f"expected {state.params.shape[0]} frames (one per stream), got {frames.shape[0]}")
        frames = frames.to(dtype=self.model.dtype, device=self.model.device)
        cfg = self.config
        # the coarser levels pyramid="auto" added at initialise, as FaceTracker reads them (at most those added: a
        # config of fewer levels was made up to the state's; unknown for a copied state: the state's)
        tracker = continuing_config(cfg.tracker, state, cfg.pyramid)
        check_continuing_levels(cfg.tracker, tracker, state)  # (else: track_step's error)
        with torch.no_grad():
            new_state, track = _tracked(track_step)(self.model, tracker, state, frames.detach())
        note_auto_levels(new_state, auto_levels(state))
        params = new_state.params.clone()  # the result's own: a caller's in-place change must not move the state
        if cfg.mode is LayerMode.UNROLLED:
            start = params if cfg.start is UnrollStart.TRACKED else state.params.detach()
            params = _tracked(unrolled_params)(
                self.model, tracker, state, frames, start, cfg.unrolled_iterations, cfg.unrolled_levels
            )
        image, mask = self.normalise(frames, state, params)
        return LayerResult(image, mask, params, new_state, track, track.success, track.confidence.detach())

    def forward_clip(self, clips: Tensor, landmarks_px: Tensor, intrinsics: Intrinsics | None = None) -> LayerResult:
        """Normalised faces of whole clips, initialised from their first frames' landmarks.

        Frame 0 is resampled with the landmark fit (its template is built from it; detached); frames
        ``1 .. T-1`` go through :meth:`forward` one after another.

        Args:
            clips: ``(B, T, 3, H, W)`` RGB or ``(B, T, 1, H, W)`` gray, float in ``[0, 1]`` (may require grad).
            landmarks_px: ``(B, K, 2)`` landmarks of frame 0, pixels.
            intrinsics: camera; default :meth:`Intrinsics.default` of the frame size.

        Returns:
            :class:`LayerResult` with ``image (B, T, C, G, G)``, ``mask (B, T, 1, G, G)``, ``params (B, T, P)``,
            ``success (B, T)`` bool and ``confidence (B, T)`` per frame (frame 0: the initialisation's result), the
            state after the last frame and the last frame's ``track``.

        Example:
            >>> out = layer.forward_clip(clips, landmarks)                       # doctest: +SKIP
            >>> loss = confidence_weighted_loss(per_frame_loss, out.confidence, out.success)  # doctest: +SKIP
        """
        if not isinstance(clips, Tensor):  # (a numpy clip was a ValueError, as a wrong shape; forward's a TypeError)
            raise TypeError(f"clips must be a torch.Tensor (B, T, 3, H, W), got {type(clips).__name__}")
        if clips.dim() != 5 or clips.shape[1] < 1:
            # (one clip's (T, C, H, W) was told the shape alone)
            hint = " (one clip (T, C, H, W): clips[None])" if clips.dim() == 4 and clips.shape[1] in (1, 3) else ""
            raise ValueError(f"clips must be (B, T, 3, H, W) with T >= 1, got {tuple(clips.shape)}{hint}")
        if isinstance(landmarks_px, Tensor) and landmarks_px.dim() == 2:
            # (initialise's "with B = 1 (one set per frame)": a clip takes one set, its first frame's)
            hint = ": one clip's, landmarks_px[None]" if clips.shape[0] == 1 else ""
            raise ValueError(
                f"landmarks_px must be (B, K, 2), one set per clip, the first frame's: clips {tuple(clips.shape)} are "
                f"B = {clips.shape[0]} clips, got landmarks_px {tuple(landmarks_px.shape)}{hint}"
            )
        # (told of a frame's layout, clips[:, 0]'s: channels last was "frames.permute(0, 3, 1, 2)", which a clip
        # cannot take; uint8 clips, cast to the model's dtype first, were "values from 0 to 255")
        hint = ""
        if clips.shape[2] not in (1, 3, 4) and clips.shape[-1] in (1, 3, 4):  # (RGBA too, as NormaliseFaces says)
            hint = " (channels last (B, T, H, W, C): clips.permute(0, 1, 4, 2, 3))"
        elif clips.shape[2] == 4:
            hint = " (RGBA: drop the alpha, clips[:, :, :3])"
        if clips.shape[2] not in (1, 3):
            raise ValueError(f"clips must be (B, T, 3, H, W) RGB or (B, T, 1, H, W) gray, got {tuple(clips.shape)}"
                             f"{hint}")  # fmt: skip
        if not clips.is_floating_point():
            hint = " (uint8 clips: clips.float() / 255)" if clips.dtype == torch.uint8 else ""
            raise ValueError(f"clips must be float in [0, 1], got {clips.dtype}{hint}")
        if isinstance(landmarks_px, Tensor) and landmarks_px.dim() == 3 and landmarks_px.shape[0] != clips.shape[0]:
            # (initialise's "with B = T (one set per frame)" read as if T landmark sets were wanted)
            B, T = clips.shape[:2]
            hint = ": frames first, (T, B, C, H, W)? clips.transpose(0, 1)" if landmarks_px.shape[0] == T else ""
            raise ValueError(
                f"landmarks_px must be (B, K, 2), one set per clip, the first frame's: clips {tuple(clips.shape)} "
                f"are B = {B} clips of T = {T} frames, got landmarks_px {tuple(landmarks_px.shape)}{hint}"
            )
        clips = clips.to(dtype=self.model.dtype, device=self.model.device)
        state, track = self.initialise(clips[:, 0], landmarks_px, intrinsics)
        image, mask = self.normalise(clips[:, 0], state, state.params)
        images, masks, params = [image], [mask], [state.params]
        success, confidence = [track.success], [track.confidence.detach()]
        for t in range(1, clips.shape[1]):
            out = self(clips[:, t], state)
            state, track = out.state, out.track
            images.append(out.image)
            masks.append(out.mask)
            params.append(out.params)
            success.append(out.success)
            confidence.append(out.confidence)
        return LayerResult(
            torch.stack(images, 1), torch.stack(masks, 1), torch.stack(params, 1), state, track,
            torch.stack(success, 1), torch.stack(confidence, 1),
        )  # fmt: skip
