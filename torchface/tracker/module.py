"""``FaceTracker``: the stateful ``nn.Module`` around :func:`initialise_managed` and :func:`managed_step`."""

from __future__ import annotations

import copy
import dataclasses
import warnings
import weakref
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from torchface._device import DeviceCheckedModule, check_to_device
from torchface.geometry.camera import Intrinsics
from torchface.model.candide import load_candide3
from torchface.model.face_model import FaceModel
from torchface.normalise.face import apply_to_tensor_fields
from torchface.tracker.fit import LandmarkFit, widen_half_landmarks
from torchface.tracker.lookahead import LookaheadConfig, check_refine_first
from torchface.tracker.managed import (
    LandmarkDetector, check_detector, check_detector_callable, initialise_managed, managed_step,
)  # fmt: skip
from torchface.tracker.step import (
    TrackerConfig, TrackerState, TrackResult, add_coarser_levels, check_frames, check_initialise_inputs,
    check_model_precision, pyramid_for_faces,
)  # fmt: skip


_SETTINGS = frozenset({"config", "model", "detector", "refine_first", "pyramid"})

#: :class:`FaceTracker`'s ``pyramid`` settings: ``"auto"`` adds coarser levels for large faces at
#: :meth:`~FaceTracker.initialise` (:func:`~torchface.tracker.step.pyramid_for_faces`), ``"config"`` keeps
#: ``config.num_levels``.
PYRAMID_CHOICES: tuple[str, ...] = ("auto", "config")


#: The settings a tracked sequence keeps from its :meth:`~FaceTracker.initialise`: its first templates and mosaic
#: slots (``max_points``), the normalised face its confidence is measured on (``template.normalised_size``) and its
#: reference's fiducial patches (``template.dissimilarity``) are made with them. A config set mid-sequence that
#: changes one is tracked with the sequence's own, with a warning, until the next ``initialise`` (a changed
#: ``normalised_size`` or ``max_points`` was ignored without a word, a changed ``patch_size`` or ``num_patches`` failed
#: at the next mosaic entry with a RuntimeError of tensor shapes).
INITIALISE_SETTINGS: tuple[str, ...] = ("max_points", "template.normalised_size", "template.dissimilarity")


def initialise_settings_changed(started: TrackerConfig, config: TrackerConfig) -> list[str]:
    """Which of :data:`INITIALISE_SETTINGS` ``config`` changes from ``started`` (the config a sequence was started
    with), each as ``"name (old -> new)"`` (a field of ``template.dissimilarity`` by its own name)."""
    changed = []
    if config.max_points != started.max_points:
        changed.append(f"max_points ({started.max_points} -> {config.max_points})")
    if config.template.normalised_size != started.template.normalised_size:
        changed.append(f"template.normalised_size ({started.template.normalised_size} -> "
                       f"{config.template.normalised_size})")  # fmt: skip
    old, new = started.template.dissimilarity, config.template.dissimilarity
    for f in dataclasses.fields(old):
        if getattr(old, f.name) != getattr(new, f.name):
            changed.append(f"template.dissimilarity.{f.name} ({getattr(old, f.name)!r} -> {getattr(new, f.name)!r})")
    return changed


def keep_initialise_settings(started: TrackerConfig, config: TrackerConfig) -> TrackerConfig:
    """``config`` with the :data:`INITIALISE_SETTINGS` of ``started`` (``config`` itself where they are the same)."""
    if not initialise_settings_changed(started, config):
        return config
    try:
        template = dataclasses.replace(config.template, normalised_size=started.template.normalised_size,
                                       dissimilarity=started.template.dissimilarity)  # fmt: skip
        return dataclasses.replace(config, max_points=started.max_points, template=template)
    except ValueError as exc:  # (min_points above the kept max_points was told a max_points the caller never set)
        kept = ", ".join(initialise_settings_changed(started, config))
        raise ValueError(f"the config cannot go on with what the tracked sequence keeps from its initialise ({kept}): "
                         f"{exc}; start a sequence with it (initialise), or set it after one") from None


def check_pyramid(pyramid: object) -> None:
    """Refuse a ``pyramid`` setting (:class:`FaceTracker`'s, training_hooks' configs') not in
    :data:`PYRAMID_CHOICES`."""
    if not isinstance(pyramid, str):
        raise TypeError(f"pyramid must be one of {PYRAMID_CHOICES}, got {type(pyramid).__name__}")
    if pyramid not in PYRAMID_CHOICES:
        raise ValueError(f"pyramid must be one of {PYRAMID_CHOICES}, got {pyramid!r}")


#: The coarser levels ``pyramid="auto"`` added at the start of the sequence a state continues, by the state (the
#: state itself does not say how many of its levels are the config's): noted by :class:`FaceTracker` and
#: training_hooks' tracking for the states they make (:func:`note_auto_levels`), read by :func:`continuing_config`.
#: A copy of a state (``copy.deepcopy``, ``torch.load``, ``select``) is not noted: its added levels are unknown.
_AUTO_LEVELS: weakref.WeakKeyDictionary[TrackerState, int] = weakref.WeakKeyDictionary()


def note_auto_levels(state: TrackerState, added: int | None) -> None:
    """Note that ``pyramid="auto"`` added ``added`` coarser levels at the start of the sequence ``state`` continues
    (None: unknown, nothing noted), for :func:`continuing_config`."""
    if added is not None:
        _AUTO_LEVELS[state] = added


def auto_levels(state: TrackerState) -> int | None:
    """The coarser levels ``pyramid="auto"`` added at the start of the sequence ``state`` continues, as noted
    (:func:`note_auto_levels`); None where unknown."""
    return _AUTO_LEVELS.get(state)


def continuing_config(
    config: TrackerConfig, state: TrackerState, pyramid: str, added: int | None = None
) -> TrackerConfig:
    """The settings a sequence goes on with from ``state``, given ``config`` (set mid-sequence, or the one it started
    with): with ``pyramid="auto"``, ``config`` with the coarser levels the state holds beyond its ``num_levels``, at
    most ``added``, those ``"auto"`` added at the sequence's start (None: :func:`auto_levels` of ``state``, and any
    number where that is unknown); ``config`` itself with ``"config"``. :class:`FaceTracker`'s and training_hooks'
    continuations (``NormalisedFaceLayer.forward``, ``track_sequence`` from a state) read the levels so; a config
    of other levels than the state's is refused by :func:`check_continuing_levels`."""
    extra = state.num_levels - config.num_levels if pyramid == "auto" else 0
    added = auto_levels(state) if added is None else added
    if added is not None:  # only those the start added (a config of fewer levels is not made up to the state's)
        extra = min(extra, added)
    return add_coarser_levels(config, max(0, extra))


def check_continuing_levels(config: TrackerConfig, run: TrackerConfig, state: TrackerState) -> None:
    """Refuse to continue ``state`` with ``run`` (:func:`continuing_config` of ``config``) where ``pyramid="auto"``
    added levels to ``config`` and ``run`` still has other levels than the state: the message names the config's
    levels and those added, which the user did not set (:func:`~torchface.tracker.step.check_state_levels`, at the
    step, refuses the rest)."""
    levels, added = state.num_levels, run.num_levels - config.num_levels
    if added and run.num_levels != levels:
        raise ValueError(
            f"the state holds templates for {levels} pyramid levels, the config has num_levels = "
            f"{config.num_levels} and pyramid='auto' adds the {added} coarser level(s) initialise added for "
            f"large faces: set a config of {levels - added} levels (or a changed copy of tracking_config), or "
            "initialise again"
        )


def _check_setting(name: str, value: Any) -> None:
    """Raise TypeError where ``value`` cannot be the :class:`FaceTracker` setting ``name``."""
    if name == "config" and not isinstance(value, TrackerConfig):
        # (a model given first, as the model comes first in kornia's and torchvision's constructors, was told no more)
        hint = ": the model is the second argument, FaceTracker(TrackerConfig(), model) or FaceTracker(model=model)" \
            if isinstance(value, FaceModel) else ""
        raise TypeError(f"config must be a TrackerConfig, got {type(value).__name__}{hint}")
    if name == "model" and not isinstance(value, FaceModel):
        raise TypeError(f"model must be a FaceModel, got {type(value).__name__}")
    if name == "model":  # a float16 model failed at initialise: '"cholesky_cpu" not implemented for 'Half''
        check_model_precision(value)
    if name == "pyramid":
        check_pyramid(value)
    if name == "refine_first":
        check_refine_first(value)
    if name == "detector" and value is not None:  # (not called: what it answers, FaceTracker.check_detector)
        check_detector_callable(value)


class FaceTracker(DeviceCheckedModule):
    """Track B face streams at once; a thin loop over the functional :func:`managed_step`.

    The per-sequence state (:class:`TrackerState`) is explicit: :attr:`state` after each call, and
    :meth:`reset` clears it. The model defaults to CANDIDE-3 with its 11 AUVs; any :class:`FaceModel` with at
    least four landmarks across the face tracks (docs/python-api.md, "Other face models": your own mesh through
    :func:`~torchface.model.load_mesh_model`, the ICT Face Model). Template management
    (dissimilarity confidence, mosaic, loss and recovery) follows ``config.template``; ``detector`` (a
    :data:`~torchface.tracker.managed.LandmarkDetector`, ``frames (B, 3, H, W) -> landmarks (B, K, 2)`` with NaN
    rows where no face was found) re-initialises lost streams, else they are searched for in the mosaic; it is
    first called at the first loss, so :meth:`check_detector` tests what it answers before a long run (the
    constructor refuses, without calling it, one that cannot be called with the frames alone).
    ``refine_first`` (a :class:`~torchface.tracker.lookahead.LookaheadConfig`, on by default; None: off; used with
    template management) is the online look-ahead start of :func:`~torchface.tracker.managed.initialise_managed`:
    once a stream's head has turned 10 degrees, its first pose, starting expression and the shape units the
    landmark fit held are re-estimated from that view (a one-off stall of about 0.4 s on a 2-core CPU) and the rest
    of the stream is tracked from it. It is read at :meth:`initialise`, whose state holds it: assigned mid-sequence
    (``tracker.refine_first = None``), it applies from the next :meth:`initialise`, and a stream still waiting to
    turn re-anchors as it was started to. Measured with ``scripts/evaluate.py --noise-seeds 0,1,2,3``:
    ``pose_sweep``'s mean error 0.14-0.19 degrees, ``scan_motion``'s max 2.7-3.3 (5.4-7.6 without the start,
    from the held landmark fit).

    ``pyramid``: ``"auto"`` (the default) tracks each sequence with the pyramid ``torchface track`` gives it:
    :meth:`initialise` adds a coarser level per doubling of the first frames' face over the size the default
    pyramid is made for (:func:`~torchface.tracker.step.pyramid_for_faces`: faces under 254.5 pixels, such as the
    640x480 scenarios', keep ``config``; a 1280x720 face at 450 mm gets a fourth level, without which a fast
    sideways motion was lost). ``"config"`` tracks with ``config.num_levels`` as given. :attr:`tracking_config`
    (and the state's :attr:`~torchface.tracker.TrackerState.num_levels`) says which pyramid a sequence runs with.

    Saving: the tracker has no learnable parameters, so ``state_dict()`` is empty (it holds a detector's weights
    where the detector is an ``nn.Module``) and holds no tracked sequence; ``load_state_dict`` therefore forgets the
    tracker's sequence, as :meth:`reset` does (the next step says so), so that a loaded checkpoint never continues
    the sequence the tracker held before; a load that fails leaves the tracker as it was. To checkpoint a tracker
    mid-stream, ``torch.save(tracker, path)`` (or pickle it) and load it with ``torch.load(path,
    weights_only=False)`` (trusted files only);
    ``copy.deepcopy(tracker)`` forks a stream, and so does ``copy.copy(tracker)``, which shares the model, config
    and detector but not the tracked state. Each continues exactly as the original would, independently of it.
    :meth:`select` keeps some of the streams (e.g. drops those whose videos have ended).

    Example:
        >>> tracker = FaceTracker()                                          # doctest: +SKIP
        >>> first = tracker.initialise(frames[:, 0], landmarks)              # doctest: +SKIP
        >>> for t in range(1, T):                                            # doctest: +SKIP
        ...     result = tracker(frames[:, t])                               # (B, 3, H, W) -> TrackResult
    """

    #: (class defaults: for trackers pickled before these attributes existed)
    pyramid: str = "auto"
    _tracking: "tuple[TrackerConfig, TrackerConfig] | None" = None
    _added_levels: int | None = None
    _started: TrackerConfig | None = None

    def __init__(
        self, config: TrackerConfig | None = None, model: FaceModel | None = None,
        detector: LandmarkDetector | None = None, refine_first: LookaheadConfig | None = LookaheadConfig(),
        pyramid: str = "auto",
    ) -> None:
        super().__init__()
        if model is not None and not isinstance(model, FaceModel):
            raise TypeError(f"model must be a FaceModel or None (CANDIDE-3), got {type(model).__name__}")
        # (each assignment is checked: __setattr__)
        self.config = TrackerConfig() if config is None else config
        self.detector = detector
        self.model = load_candide3() if model is None else model
        self.refine_first = refine_first
        self.pyramid = pyramid
        self._state: TrackerState | None = None
        # (config, the config the sequence is tracked with): the levels pyramid="auto" added at initialise
        self._tracking: tuple[TrackerConfig, TrackerConfig] | None = None
        self._added_levels: int | None = None  # the coarser levels pyramid="auto" added at initialise (None: unknown)
        self._started: TrackerConfig | None = None  # the config the sequence was initialised with (None: unknown)
        self._dropped: str | None = None  # why the state was forgotten (a move, a load), for the next step's error

    def __setattr__(self, name: str, value: Any) -> None:
        """Attribute assignment, ``config``, ``model``, ``detector``, ``refine_first`` and ``pyramid`` checked as the
        constructor checks them (set after construction they were not: a per-image dlib detector failed at the first
        loss, with a shape error, a dict config at the next step with an AttributeError)."""
        if name in _SETTINGS:
            _check_setting(name, value)
        started = self.__dict__.get("_started")
        if name == "config" and started is not None and self.__dict__.get("_state") is not None:
            changed = initialise_settings_changed(started, value)
            if changed:  # (its templates, mosaic and normalised faces are made with them)
                keep_initialise_settings(started, value)  # (refused here, the tracker unchanged, where it cannot)
                warnings.warn(
                    f"FaceTracker: the config set mid-sequence changes {', '.join(changed)}: settings the tracked "
                    "sequence keeps from its initialise (its templates and normalised faces are made with them), so "
                    "it goes on with the old values until the next initialise (tracking_config holds them)",
                    UserWarning, stacklevel=2,
                )  # fmt: skip
        super().__setattr__(name, value)

    def to(self, *args, **kwargs) -> "FaceTracker":  # type: ignore[override]
        """Move the face model like ``nn.Module.to``: device and/or float dtype (a move that changes either
        forgets the tracked state: :meth:`_apply`).

        Example:
            >>> tracker = FaceTracker().to(torch.float64)
            >>> tracker.model.dtype
            torch.float64
        """
        check_to_device(*args, **kwargs)  # (a device this machine lacks: one ValueError listing those it has)
        device, dtype, _, _ = torch._C._nn._parse_to(*args, **kwargs)
        if dtype is not None and not dtype.is_floating_point:
            raise TypeError(f"FaceTracker.to only accepts floating point dtypes, got {dtype}")
        return super().to(*args, **kwargs)

    def _apply(self, fn, recurse: bool = True) -> "FaceTracker":
        """What ``.to``, ``.double()``, ``.float()``, ``.cuda()`` and ``.cpu()`` do: move the face model (a plain
        attribute, not a parameter); a call that changes its dtype or device forgets the tracked state (its tensors
        are the old dtype's and device's; the next step says so), one that changes neither (``.cpu()`` on the CPU,
        ``share_memory()``, a parent module's ``.to`` to where the tracker already is) keeps it."""
        target = fn(torch.zeros(1, dtype=self.model.dtype)).dtype  # the floating dtype this call converts to
        if target not in (torch.float32, torch.float64):
            raise TypeError(f"FaceTracker tracks in float32 or float64, not {target} (its solver factorises matrices)")
        before = (self.model.dtype, self.model.device)
        self.model = apply_to_tensor_fields(fn, self.model)
        after = (self.model.dtype, self.model.device)
        if after != before and self._state is not None:
            self._state = None
            self._dropped = (
                f"the tracker was moved from {before[0]} on {before[1]} to {after[0]} on {after[1]}, which forgets the "
                "tracked state"
            )
        return super()._apply(fn, recurse)

    @property
    def state(self) -> TrackerState | None:
        """The tracking state after the last call (None before :meth:`initialise`). The next call hands it to
        :func:`~torchface.tracker.managed.managed_step` with ``donate=True``, which may write into its template
        tensors: keep a ``copy.deepcopy`` of a state you want to use again. The coarser levels ``pyramid="auto"``
        added at :meth:`initialise` are noted for it, so that training_hooks continuing it reads its levels as the
        tracker does (:func:`continuing_config`; a copy of it is not noted)."""
        if self._state is not None:
            note_auto_levels(self._state, self._added_levels)
        return self._state

    @property
    def tracking_config(self) -> TrackerConfig | None:
        """The settings the tracked sequence runs with: :attr:`config`, with the coarser pyramid levels that
        ``pyramid="auto"`` added at :meth:`initialise` for large faces (its ``num_levels`` is the state's
        :attr:`~torchface.tracker.TrackerState.num_levels`); None before :meth:`initialise`. A config set
        mid-sequence gets the levels the state holds beyond it with ``pyramid="auto"`` (so a changed copy of this
        one is taken as it is), at most as many as :meth:`initialise` added for large faces, none with
        ``"config"``: one of other levels (``num_levels=2`` on a 3-level sequence that ``"auto"`` added none to) is
        refused at the next step, as with ``"config"`` (it was tracked with the state's 3 levels, the coarsest's
        iterations repeated, without a word). It keeps the sequence's :data:`INITIALISE_SETTINGS` until the next
        :meth:`initialise` (the assignment warns where it changes them).

        Example:
            >>> tracker.initialise(frames, landmarks)        # 1280x720, a 380-pixel face  # doctest: +SKIP
            >>> tracker.tracking_config.num_levels                                        # doctest: +SKIP
            4
        """
        if self._state is None or self._tracking is None:
            return None if self._state is None else self.config
        base, run = self._tracking
        if self.config is not base:  # a config set mid-sequence: with the state's levels beyond its own ("auto",
            # as training_hooks continues a state; counted from the state: a config of the state's levels, e.g. a
            # changed tracking_config, got the added levels again, 5 for a 4-level state, and every step failed)
            # (only those initialise added; unknown: a tracker pickled before, any)
            run = continuing_config(self.config, self._state, self.pyramid, self._added_levels)
            if self._started is not None:  # (INITIALISE_SETTINGS: the sequence's own, as the state is made with them)
                run = keep_initialise_settings(self._started, run)
            self._tracking = (self.config, run)
        return run

    def reset(self) -> None:
        """Forget the tracked sequence."""
        self._state = None
        self._dropped = None
        self._tracking = None
        self._added_levels = None
        self._started = None

    def select(self, index: Sequence[int] | Tensor) -> "FaceTracker":
        """Keep only streams ``index`` (``(B',)`` stream indices, int64 or a list, in the order wanted; or a ``(B,)``
        bool mask) and go on tracking them as a smaller batch: :meth:`TrackerState.select
        <torchface.tracker.TrackerState.select>` of :attr:`state`, in place (as ``.to`` is); returns the tracker.
        The next call takes the kept streams' frames, ``(B', 3, H, W)`` in that order, and they track as they would
        have in the whole batch, to float rounding (``torchface track`` drops a video that has ended this way).

        Example:
            >>> tracker.select([0, 2])                                           # doctest: +SKIP
            >>> result = tracker(frames[[0, 2], t])                              # doctest: +SKIP
        """
        if self._state is None:
            raise RuntimeError(f"call initialise(frames, landmarks) before selecting streams{self._why_none()}")
        self._state = self._state.select(index)
        return self

    def __copy__(self) -> "FaceTracker":
        """``copy.copy(tracker)``: a tracker of the same config, model and detector (shared, as a shallow copy's
        are) with its own copy of the tracked state. A shared state was corrupted: a step hands the state over to
        :func:`managed_step` (``donate=True``), which writes new templates into its tensors, so the copy's steps
        changed the original's templates (0.33 degrees on the original's next frame in a test) and vice versa. The
        module's own tables (submodules, hooks) are copied too, so that a detector set on one is not set on both."""
        new = self.__class__.__new__(self.__class__)
        new.__dict__.update({k: v.copy() if isinstance(v, (dict, set)) else v for k, v in self.__dict__.items()})
        new._state = copy.deepcopy(self._state)
        return new

    def load_state_dict(  # type: ignore[override]
        self, state_dict: Mapping[str, Any], strict: bool = True, assign: bool = False
    ) -> Any:
        """``nn.Module.load_state_dict``, which forgets the tracked sequence (a state_dict holds none:
        :meth:`_load_from_state_dict`), checked before anything changes: a load that fails (keys missing or
        unexpected, a detector weight of another size) raises torch's ``RuntimeError`` and leaves the tracker as it
        was, its tracked sequence and a detector network's weights unchanged (it forgot the sequence, and torch had
        copied the weights that matched, before raising). The check loads into a stand-in whose tensors are empty
        ``meta`` ones (no data copied). Loaded by a module that holds it, the tracker forgets its sequence as torch
        reaches it, whatever else that load refuses: torch loads a module's children one by one and raises once it has
        loaded them all, and no child is told whether the load it is part of failed (keep ``copy.copy(tracker)``,
        which copies the tracked sequence, to put it back after a failed load). Load hooks registered on the tracker
        or its detector (``register_load_state_dict_post_hook``) run once, on the tracker: the check runs none (they
        ran on the stand-in too, which they were handed as the module); where the check refuses a load that hooks
        may make good (e.g. by renaming keys), the load itself decides, with a copy of the detector's weights to put
        back if it fails."""
        checked = self._check_loads(state_dict, strict, assign)
        kept = (self._state, self._dropped, self._tracking)
        weights = [] if checked else self._weights_kept()
        try:
            return super().load_state_dict(state_dict, strict, assign)
        except BaseException:
            self._state, self._dropped, self._tracking = kept
            with torch.no_grad():  # (assign=True put other tensors in the tables; assign=False copied into these)
                for table, name, tensor, data in weights:
                    table[name] = tensor
                    tensor.copy_(data)
            raise

    def _weights_kept(self) -> list[tuple[dict[str, Any], str, Tensor, Tensor]]:
        """``(table, name, tensor, copy of its data)`` of each parameter and buffer of the tracker's submodules (a
        detector network's), for :meth:`load_state_dict` to put back after a load that fails unchecked (uninitialised
        lazy ones left out: a load makes them)."""
        kept = []
        for module in self.modules():
            for table in (module._parameters, module._buffers):
                for name, tensor in table.items():
                    if tensor is not None and not torch.nn.parameter.is_lazy(tensor):
                        kept.append((table, name, tensor, tensor.detach().clone()))
        return kept

    def _check_loads(self, state_dict: Mapping[str, Any], strict: bool, assign: bool) -> bool:
        """Raise what ``load_state_dict(state_dict, strict, assign)`` would raise, changing nothing: the load made
        into a stand-in, the tracker's settings with no tracked state, whose submodules (a detector network) are
        copies with empty ``meta`` tensors of their parameters' and buffers' shapes and dtypes. The stand-in runs no
        load hooks (a hook with effects, a counter or a hook acting on the tracker, ran twice, the first time during
        the check, even for a load then refused); where the tracker or a submodule has some and the check fails, the
        load is left to torch (a hook may rename keys or clear missing ones: the check cannot tell), and it returns
        False (True otherwise)."""
        if not isinstance(state_dict, Mapping):
            return True  # (torch's own TypeError, before anything changes)
        memo: dict[int, Any] = {}
        hooked = False
        for module in self.modules():  # (the stand-in's copies get empty hook tables: memo, nothing of them copied)
            for table in (module._load_state_dict_pre_hooks, module._load_state_dict_post_hooks):
                hooked = hooked or bool(table)
                memo[id(table)] = type(table)()
        probe = self.__class__.__new__(self.__class__)
        probe.__dict__.update(self.__dict__)
        probe.__dict__.update(_load_state_dict_pre_hooks=type(self._load_state_dict_pre_hooks)(),
                              _load_state_dict_post_hooks=type(self._load_state_dict_post_hooks)())  # fmt: skip
        try:  # (an uninitialised lazy parameter has no meta twin: empty_like's ValueError refused a load torch takes)
            for t in [*self.parameters(), *self.buffers()]:
                empty = torch.empty_like(t, device="meta")
                memo[id(t)] = torch.nn.Parameter(empty, t.requires_grad) if isinstance(t, torch.nn.Parameter) else empty
            probe.__dict__.update(
                {name: copy.deepcopy(self.__dict__[name], memo) for name in ("_modules", "_parameters", "_buffers")}
            )
        except Exception:  # (a detector network holding what cannot be copied: loaded unchecked, the sequence kept)
            return True
        probe.__dict__.update(_state=None, _dropped=None, _tracking=None)
        with warnings.catch_warnings():  # ("copying from a non-meta parameter ... to a meta parameter ... a no-op")
            warnings.simplefilter("ignore")
            try:
                torch.nn.Module.load_state_dict(probe, state_dict, strict, assign)
            except Exception:
                if not hooked:
                    raise
                return False
        return True

    def _load_from_state_dict(
        self, state_dict: Mapping[str, Any], prefix: str, local_metadata: dict[str, Any], strict: bool,
        missing_keys: list[str], unexpected_keys: list[str], error_msgs: list[str],
    ) -> None:  # fmt: skip
        """``load_state_dict`` (of the tracker or of a module holding it): a state_dict holds no tracked sequence,
        so loading one forgets the tracker's (it went on tracking the sequence it held before, whatever the
        checkpoint's tracker was tracking); the next step says why."""
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        self._state = None
        self._dropped = (
            "a state_dict was loaded: it holds no tracked sequence (to checkpoint one, torch.save the tracker)"
        )

    def initialise(
        self,
        frames: Tensor,
        landmarks_px: Tensor,
        intrinsics: Intrinsics | None = None,
        weights: Tensor | None = None,
        *,
        fit: LandmarkFit | None = None,
    ) -> TrackResult:
        """Start tracking from the first frames and their landmarks.

        Args:
            frames: ``(B, 3, H, W)`` RGB or ``(B, 1, H, W)`` gray, float in [0, 1] (values outside
                :data:`~torchface.tracker.step.FRAME_VALUE_RANGE` are refused: divide 0-255 frames by 255).
            landmarks_px: ``(B, K, 2)`` the model's K landmarks (68 iBUG points for CANDIDE-3) in pixels; a NaN row:
                missing; an infinite coordinate and a row with one coordinate NaN alone are refused
                (:func:`~torchface.tracker.fit.check_landmark_values`). A stream whose start fails (fewer than 4: no
                face found in its frame; landmarks that hold no pose, a face too small, a black frame:
                :func:`~torchface.tracker.initialise`) starts FAILED and holds its finite estimate at confidence 0,
                LOST until the ``detector`` finds its face (FAILED at every frame without template management); the
                others track as without it. The result's
                ``start_failure`` says why each stream failed (:class:`~torchface.tracker.step.StartFailure`; in
                words: ``start_failure_reasons``).
            intrinsics: camera; default :meth:`Intrinsics.default` of the frame size.
            weights: ``(B, K)`` landmark confidences ``>= 0`` (0 = ignore; their scale weighs the landmarks against
                the fit's priors, 1 as they are set for: :func:`~torchface.tracker.fit.fit_landmarks`) or None; NaN,
                infinite and negative ones are refused.
            fit: the first frames' fit when already made (e.g. by
                :func:`~torchface.tracker.lookahead.lookahead_fit`); None fits the landmarks. The online start
                (``refine_first``) still re-anchors from it once the head turns: ``torchface track --lookahead``
                tracks from its look-ahead fit alone, as ``FaceTracker(refine_first=None)`` does.
        """
        if intrinsics is None:
            check_frames(frames)  # a numpy array was "must be (B, 3, H, W), got (B, 3, H, W)"
            intrinsics = Intrinsics.default(frames.shape[-1], frames.shape[-2])
        # The tracker steps without gradients and its state is fixed data: inputs that carry a graph (a network's
        # frames or landmarks) are detached, else the state held that graph alive and copy.deepcopy(tracker) failed.
        frames, landmarks_px = (x.detach() if isinstance(x, Tensor) else x for x in (frames, landmarks_px))
        landmarks_px = widen_half_landmarks(landmarks_px)  # (float16 / bfloat16: warned of once, here)
        weights = weights.detach() if isinstance(weights, Tensor) else weights
        if isinstance(fit, LandmarkFit):
            fit = apply_to_tensor_fields(Tensor.detach, fit)
        refine = self.refine_first if self.config.template.enabled else None  # the online start needs management
        self.reset()  # a failed initialisation must not leave the previous video's state to track on
        config = self.config
        if self.pyramid == "auto":  # (the inputs checked first: their errors stay those of initialise_managed)
            check_initialise_inputs(self.model, config, frames, landmarks_px, intrinsics, weights)
            config = pyramid_for_faces(config, landmarks_px, (intrinsics.height, intrinsics.width), weights)
        self._state, result = initialise_managed(
            self.model, config, frames, landmarks_px, intrinsics, weights, fit=fit, refine_first=refine
        )
        self._tracking = (self.config, config)
        self._added_levels = config.num_levels - self.config.num_levels
        self._started = config
        return result

    @torch.no_grad()
    def forward(self, frames: Tensor, *misplaced: object) -> TrackResult:
        """Track the next frame of every stream: ``(B, 3, H, W)`` RGB or ``(B, 1, H, W)`` gray ->
        :class:`TrackResult`. ``misplaced``: nothing (landmarks given here, ``tracker(frames, landmarks)``, are
        refused saying that :meth:`initialise` takes them: it was "forward() takes 2 positional arguments but 3 were
        given")."""
        if misplaced:
            raise TypeError(
                f"FaceTracker's call takes the frames alone, got {1 + len(misplaced)} arguments: start the streams "
                "with tracker.initialise(frames, landmarks_px), then track each next frame with tracker(frames)"
            )
        if self._state is None:
            raise RuntimeError(f"call initialise(frames, landmarks) before tracking{self._why_none()}")
        config = self.tracking_config
        assert config is not None
        # (check_state_levels would name the config's levels with those pyramid="auto" added, not set by the user)
        check_continuing_levels(self.config, config, self._state)
        self._state, result = managed_step(self.model, config, self._state, frames, self.detector, donate=True)
        return result

    def step(self, frames: Tensor) -> TrackResult:
        """``tracker(frames)`` by name: :meth:`forward` through the module's call, so that its hooks run (``step =
        forward`` skipped the forward hooks and pre-hooks registered on the tracker)."""
        return self(frames)

    def check_detector(self, frames: Tensor) -> Tensor:
        """Ask the tracker's ``detector`` about ``frames`` once, as a lost stream's re-initialisation asks it, and
        check its answer as that does (:func:`~torchface.tracker.managed.check_detector`, with the tracker's model):
        a detector's mistake (an answer of the wrong type, shape or dtype, NumPy for a tensor, one image's ``(K, 2)``
        for ``(B, K, 2)``, an exception) was found only at the first loss, perhaps far into a long video. The
        tracker's state is left as it is; the detector's own sees the call. The constructor already refused a
        detector that cannot be called with the frames alone.

        Args:
            frames: ``(B, 3, H, W)`` RGB or ``(B, 1, H, W)`` gray, float in [0, 1] (a frame with a face and one
                without test both answers).

        Returns:
            ``(B, K, 2)`` the landmarks as a restart takes them (NaN rows: no face).

        Raises:
            ValueError: the tracker has no detector; bad frames; an answer not ``(B, K, 2)``.
            TypeError: an answer that is not a real tensor (the message says how to make one).
        """
        if self.detector is None:
            raise ValueError("this tracker has no detector to check (detector=None: lost streams are searched for "
                             "in their mosaic); FaceTracker(detector=...) sets one")  # fmt: skip
        return check_detector(self.detector, frames, self.model)

    def _why_none(self) -> str:
        """Why the tracker holds no state, for an error message: `` (the tracker was moved ...)`` or empty."""
        return f" ({self._dropped})" if self._dropped else ""
