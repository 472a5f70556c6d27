"""Opt-in temporal smoothing of the tracker's outputs: the One-Euro filter, with rotations smoothed on SO(3).

The One-Euro filter (G. Casiraghi, N. Roussel, D. Vogel, *1€ Filter: A Simple Speed-based Low-pass Filter for
Noisy Input in Interactive Systems*, CHI 2012) is a first-order low-pass filter whose cutoff grows with the
signal's speed: at rest a low cutoff removes the jitter, in fast motion a high one keeps the lag small. Per frame,
with ``T_e`` the time since the previous frame (seconds) and ``alpha(f_c) = 1 / (1 + tau / T_e)``,
``tau = 1 / (2 pi f_c)``::

    dx_t   = (x_t - x_{t-1}) / T_e                         (the raw signal's derivative)
    dx^_t  = dx^_{t-1} + alpha(d_cutoff) (dx_t - dx^_{t-1})
    f_c    = min_cutoff + beta |dx^_t|
    x^_t   = x^_{t-1} + alpha(f_c) (x_t - x^_{t-1})

(the derivative from the raw previous value, as the authors' reference code and MediaPipe's filter take it).
Vectors (the translation, mm) take ``|dx^|`` as the Euclidean norm, so the cutoff does not depend on the axes;
the animation units are filtered one unit at a time. A rotation is filtered on SO(3), not entry by entry: its
derivative is the angular velocity ``log(R_{t-1}^T R_t) / T_e`` (rad/s), and the step towards the new rotation is
taken in the tangent space of the previous output, ``R^_t = R^_{t-1} exp(alpha delta)`` with
``delta = log(R^_{t-1}^T R_t)``, written ``R^_t = R_t exp(-(1 - alpha) delta)``: each output is the raw rotation
times an exponential, a rotation to rounding however long the stream, with no re-orthonormalisation.

Streams: every function is batch-first, one filter per stream ``b`` of ``(B, ...)``, no loop over them. A stream
starts afresh (its output the raw input, its derivative 0) at its first frame, where ``restart`` says so (a
re-anchoring, a new video in its slot), at a frame whose time step is not positive and finite, and at the first
usable frame after one that is not: a frame that is not ``valid`` (``TrackResult.success`` false: failed, lost) or
whose input is not finite passes its input through unchanged and leaves the stream to start afresh, so that the
jump of a recovery after a loss is not smeared over the frames that follow it. Non-finite input is passed through, never
raised on and never mixed into the filter's state (the tracker never reports NaN; a NaN row of a user's signal
stays that row's). Finite input gives finite output, however small a positive time step (the derivative's update is
computed as ``a_d / T_e = 2 pi d_cutoff / (1 + 2 pi d_cutoff T_e)`` times the move, never divided by ``T_e``) and
however high the cutoff (``alpha`` is 1 where ``r`` overflows), short of values whose difference overflows the
dtype; float16 and bfloat16 signals are filtered in float32 (their state too) and returned in their dtype.

Gradients: every operation is differentiable (the speed's norm is written to be finite at zero speed and the SO(3)
logarithm is finite at the identity), so the filtered signal can be back-propagated to the inputs and the
previous state; float64 gradcheck in ``tests/tracker/test_smoothing.py``. The filter never feeds the tracker: the
tracker's state holds its own estimates, and :class:`ResultSmoother` only reads results.

Defaults (:class:`SmoothingConfig`), chosen from ``scripts/evaluate.py --smoothing`` and
``scripts/track_grid.py --smoothing`` (docs/python-api.md, "Smoothing the outputs"): rotation ``min_cutoff=1.0`` Hz,
``beta=100`` Hz per rad/s, ``d_cutoff=5.0`` Hz; translation ``min_cutoff=1.0`` Hz, ``beta=1.0`` Hz per mm/s,
``d_cutoff=5.0`` Hz; expression off. In fast motion the lag tends to ``1 / (2 pi beta)`` (0.09 degrees, 0.16 mm):
the GRID clips' pose jitter 0.098 -> 0.067 degrees, the rendered scenarios' mean rotation error up 0.01-0.03
degrees.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor

from torchface._words import switch_hint
from torchface.geometry._checks import check_number
from torchface.geometry.so3 import axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_euler
from torchface.model.face_model import FaceModel
from torchface.tracker.step import TrackerState, TrackResult, stream_index

__all__ = [
    "OneEuroConfig",
    "OneEuroState",
    "ResultSmoother",
    "SmoothingConfig",
    "SmoothingState",
    "one_euro_alpha",
    "one_euro_rotation_step",
    "one_euro_step",
    "reanchored_streams",
    "smooth_pose_series",
    "smooth_result",
]


@dataclass(frozen=True)
class OneEuroConfig:
    """One signal's One-Euro filter (Casiraghi et al. 2012; module docstring).

    Attributes:
        min_cutoff: the cutoff frequency at rest, Hz (> 0): lower removes more jitter and lags more.
        beta: how fast the cutoff grows with the speed, Hz per unit of the signal per second (>= 0; the units
            are the signal's: rad/s for a rotation, mm/s for a translation, animation units per second).
            0 is a fixed low-pass at ``min_cutoff``.
        d_cutoff: the cutoff of the derivative's own low-pass, Hz (> 0).

    These defaults (a fixed 1 Hz low-pass) are not :class:`SmoothingConfig`'s filters': to change one setting of
    its default rotation filter, ``dataclasses.replace(SmoothingConfig().rotation, beta=30.0)`` (``OneEuroConfig(
    beta=30.0)`` takes ``d_cutoff`` 1 Hz, not the rotation's 5).
    """

    min_cutoff: float = 1.0
    beta: float = 0.0
    d_cutoff: float = 1.0

    def __post_init__(self) -> None:
        for name, interval, unit in (("min_cutoff", "(0, inf)", "Hz"), ("beta", "[0, inf)", "Hz per unit/s"),
                                     ("d_cutoff", "(0, inf)", "Hz")):  # fmt: skip
            object.__setattr__(self, name, check_number(getattr(self, name), name, interval, unit=unit))


@dataclass(frozen=True)
class SmoothingConfig:
    """Which of a :class:`~torchface.tracker.TrackResult`'s outputs :class:`ResultSmoother` smooths, and how.

    Attributes:
        rotation: the head rotation's filter, on SO(3) (speed: the angular velocity, rad/s), or None to leave it
            (``rotation``, ``axis_angle``, ``ypr_deg``) raw.
        translation: the translation's filter (speed: the norm of the velocity, mm/s), or None.
        expression: the animation units' filter, one per unit (``expression``; ``anim_coeffs`` and ``facs`` follow
            it), or None (the default: raw). Needs the face model (:class:`ResultSmoother`'s ``model``).

    The defaults were chosen from the measurements of docs/python-api.md, "Smoothing the outputs".
    """

    rotation: OneEuroConfig | None = field(
        default_factory=lambda: OneEuroConfig(min_cutoff=1.0, beta=100.0, d_cutoff=5.0)
    )
    translation: OneEuroConfig | None = field(
        default_factory=lambda: OneEuroConfig(min_cutoff=1.0, beta=1.0, d_cutoff=5.0)
    )
    expression: OneEuroConfig | None = None

    def __post_init__(self) -> None:
        for name in ("rotation", "translation", "expression"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, OneEuroConfig):
                raise TypeError(f"{name} must be a OneEuroConfig or None, got {type(value).__name__}"
                                f"{switch_hint(value, 'OneEuroConfig')}")  # (expression=True: its filter)


@dataclass(frozen=True, eq=False)
class OneEuroState:
    """One signal's filter state after a frame, per stream.

    Attributes:
        value: ``(B, *S)`` the last output ``x^`` (a rotation filter's: ``(B, 3, 3)`` matrices).
        raw: ``(B, *S)`` the last input ``x`` (finite: a non-finite input is not kept).
        rate: ``(B, *S')`` the filtered derivative ``dx^`` (a rotation filter's: ``(B, 3)`` rad/s).
        started: ``(B,)`` bool: the stream has a usable previous frame (False: its next frame starts afresh).
    """

    value: Tensor
    raw: Tensor
    rate: Tensor
    started: Tensor

    def select(self, index: Tensor) -> "OneEuroState":
        """The state of streams ``index`` (``(B',)`` int64 indices or a ``(B,)`` bool mask)."""
        return OneEuroState(self.value[index], self.raw[index], self.rate[index], self.started[index])


def one_euro_alpha(cutoff_hz: Tensor, dt: Tensor) -> Tensor:
    """The smoothing factor of a first-order low-pass: ``alpha = r / (1 + r)``, ``r = 2 pi f_c T_e``
    (``= 1 / (1 + tau / T_e)``, ``tau = 1 / (2 pi f_c)``; Casiraghi et al. 2012).

    Args:
        cutoff_hz: ``(*)`` cutoff frequencies, Hz.
        dt: ``(*)`` time steps, seconds (broadcast with ``cutoff_hz``).

    Returns:
        ``(*)`` in ``(0, 1)`` for positive inputs.

    Example:
        >>> one_euro_alpha(torch.tensor(1.0), torch.tensor(1 / 25))
        tensor(0.2008)
    """
    r = (2.0 * math.pi) * cutoff_hz * dt
    big = torch.isinf(r)  # (a cutoff or a step so large that r overflows: the limit, 1; inf / inf was NaN)
    r = torch.where(big, torch.ones_like(r), r)  # (both branches finite: gradients stay finite)
    return torch.where(big, torch.ones_like(r), r / (1.0 + r))


def _speed(rate: Tensor) -> Tensor:
    """``(*)`` Euclidean norm of ``(*, D)`` over its last dimension, finite in value and gradient at zero."""
    sq = (rate * rate).sum(-1)
    positive = sq > 0
    return torch.where(positive, torch.where(positive, sq, torch.ones_like(sq)).sqrt(), torch.zeros_like(sq))


def _rows(mask: Tensor, like: Tensor) -> Tensor:
    """``(B,)`` mask viewed to broadcast against ``like`` ``(B, ...)``."""
    return mask.view(mask.shape[0], *([1] * (like.dim() - 1)))


def _stream_mask(mask: Tensor | None, B: int, name: str, device: torch.device, default: bool) -> Tensor:
    if mask is None:
        return torch.full((B,), default, dtype=torch.bool, device=device)
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool or tuple(mask.shape) != (B,):
        got = f"{tuple(mask.shape)} {mask.dtype}" if isinstance(mask, Tensor) else type(mask).__name__
        raise ValueError(f"{name} must be a ({B},) bool tensor (one flag per stream), got {got}")
    return mask.to(device)


def _flag_or_complex(time: object) -> str | None:
    """How a message says ``time`` is no real seconds: a bool (taken as 0 and 1 seconds) or a bool or complex tensor;
    None for anything else."""
    if isinstance(time, bool):
        return "a bool"
    if isinstance(time, Tensor) and (time.dtype == torch.bool or time.is_complex()):
        return f"a {time.dtype} tensor"
    return None


def _seconds(time: object, B: int, name: str, device: torch.device) -> Tensor:
    """``time`` (a ``(B,)`` tensor or sequence of real seconds) as a float64 ``(B,)`` tensor on ``device``, else a
    ``TypeError`` or ``ValueError`` naming the argument ``name`` (``ResultSmoother``'s ``timestamps`` was refused as
    ``time``, and a bool one taken as 0 and 1 seconds)."""
    if (got := _flag_or_complex(time)) is not None:
        raise TypeError(f"{name} must be real seconds, a ({B},) tensor, got {got}")
    seconds = torch.as_tensor(time, dtype=torch.float64, device=device)
    if tuple(seconds.shape) != (B,):
        hint = f": one per stream, torch.full(({B},), t)" if seconds.dim() == 0 else ""
        raise ValueError(f"{name} must be a ({B},) tensor of seconds, got shape {tuple(seconds.shape)}{hint}")
    return seconds


def _time_steps(dt: Tensor | float, B: int, like: Tensor) -> Tensor:
    if isinstance(dt, bool) or not isinstance(dt, (Tensor, int, float)):
        raise TypeError(f"dt must be seconds, a number or a ({B},) tensor, got {type(dt).__name__}")
    if (got := _flag_or_complex(dt)) is not None:  # (a bool tensor: 0 and 1 seconds)
        raise TypeError(f"dt must be real seconds, a number or a ({B},) tensor, got {got}")
    dt = torch.as_tensor(dt, dtype=like.dtype, device=like.device)
    if dt.dim() == 0:
        dt = dt.expand(B)
    if tuple(dt.shape) != (B,):
        raise ValueError(f"dt must be a number or a ({B},) tensor of seconds, got shape {tuple(dt.shape)}")
    return dt


def _filter(
    x: Tensor, state: OneEuroState | None, dt: Tensor | float, config: OneEuroConfig, valid: Tensor | None,
    restart: Tensor | None, identity: Tensor,
    difference: Callable[[Tensor, Tensor], Tensor], advance: Callable[[Tensor, Tensor, Tensor, Tensor], Tensor],
) -> tuple[Tensor, OneEuroState]:
    """The One-Euro step shared by the vector and rotation filters: ``difference(x, y)`` the tangent vector from
    ``y`` to ``x`` (``(B, ..., D)``), ``advance(x, prev, delta, alpha)`` the output ``alpha`` of the way from the
    previous output ``prev`` to ``x`` (``delta = difference(x, prev)``); ``identity`` a finite value of one (what
    a non-finite first input keeps). 16-bit signals are filtered in float32 (their state too) and returned in
    their dtype: a speed's square overflowed float16 (NaN from a 100 mm/s move)."""
    if not isinstance(config, OneEuroConfig):
        raise TypeError(f"config must be a OneEuroConfig, got {type(config).__name__}")
    if not isinstance(x, Tensor) or not x.is_floating_point():
        raise TypeError(f"the signal must be a floating-point tensor, got {getattr(x, 'dtype', type(x).__name__)}")
    given, x = x, x.to(torch.promote_types(x.dtype, torch.float32))  # (16-bit: filtered in float32)
    identity = identity.to(x.dtype)
    B = x.shape[0]
    dt = _time_steps(dt, B, x)
    valid = _stream_mask(valid, B, "valid", x.device, True)
    restart = _stream_mask(restart, B, "restart", x.device, False)
    finite = torch.isfinite(x.flatten(1)).all(1)  # ((B, 0) signals: all True)
    timed = torch.isfinite(dt) & (dt > 0)
    ok = valid & finite  # a usable frame: filtered, or the start of the stream (a bad time step: the start)
    if state is None:
        prev_raw = prev_value = torch.where(_rows(finite, x), x, identity.expand_as(x))
        started = torch.zeros(B, dtype=torch.bool, device=x.device)
        prev_rate = None
    else:
        if tuple(state.value.shape) != tuple(x.shape):
            raise ValueError(f"the state is of signals {tuple(state.value.shape)}, the input {tuple(x.shape)}: "
                             "one filter state per batch of streams (select() it as the batch changes)")  # fmt: skip
        prev_raw, prev_value, prev_rate, started = state.raw, state.value, state.rate, state.started
    x_safe = torch.where(_rows(finite, x), x, prev_raw)  # (both branches finite: gradients stay finite)
    dt_safe = torch.where(timed, dt, torch.ones_like(dt))
    moved = difference(x_safe, prev_raw)  # (B, ..., D) tangent vectors
    step = _rows(dt_safe, moved)
    if prev_rate is None:
        prev_rate = torch.zeros_like(moved)
    # dx^ = dx^_prev + a_d (moved / T_e - dx^_prev), with a_d / T_e = 2 pi f_d / (1 + 2 pi f_d T_e): no division by
    # the step, which a positive step too small to divide by (1e-40 s in float32) made infinite, the state NaN for
    # good; as T_e -> 0 it tends to dx^_prev + 2 pi f_d moved, as the filter does
    r_d = (2.0 * math.pi * config.d_cutoff) * step
    a_d = r_d / (1.0 + r_d)
    rate = prev_rate + ((2.0 * math.pi * config.d_cutoff) / (1.0 + r_d) * moved - a_d * prev_rate)
    cutoff = config.min_cutoff + config.beta * _speed(rate)  # (B, ...)
    a = one_euro_alpha(cutoff, dt_safe.view(B, *([1] * (cutoff.dim() - 1)))).unsqueeze(-1)
    smoothed = advance(x_safe, prev_value, difference(x_safe, prev_value), a)
    fresh = ~started | restart | ~ok | ~timed  # the input passes through
    out = torch.where(_rows(fresh, x), given, smoothed.to(given.dtype))
    rate = torch.where(_rows(fresh, rate), torch.zeros_like(rate), rate)
    value = torch.where(_rows(fresh, x), x_safe, smoothed)
    return out, OneEuroState(value=value, raw=x_safe, rate=rate, started=ok)


def one_euro_step(
    x: Tensor, state: OneEuroState | None, dt: Tensor | float, config: OneEuroConfig, *,
    valid: Tensor | None = None, restart: Tensor | None = None,
) -> tuple[Tensor, OneEuroState]:  # fmt: skip
    """One frame of the One-Euro filter of B streams of vectors (module docstring).

    Args:
        x: ``(B, ..., D)`` this frame's values; the speed that sets the cutoff is the Euclidean norm over the last
            dimension ``D`` (one cutoff per ``(B, ...)``: give ``(B, A, 1)`` to filter A channels each alone).
        state: the state the previous frame returned, or None (the first frame: every stream starts).
        dt: seconds since the previous frame, a number or ``(B,)``.
        config: the filter's settings.
        valid: ``(B,)`` bool, the frame is usable (default all): elsewhere the input passes through and the stream
            starts afresh at its next usable frame.
        restart: ``(B,)`` bool, the stream starts afresh at this frame (default none).

    Returns:
        ``(B, ..., D)`` the filtered values (the input itself where a stream starts or the frame is not usable,
        non-finite values included), and the state for the next frame.

    Example:
        >>> x, state = one_euro_step(torch.zeros(2, 3), None, 0.04, OneEuroConfig())
        >>> y, state = one_euro_step(torch.ones(2, 3), state, 0.04, OneEuroConfig())   # alpha(1 Hz) at 25 fps
        >>> y[0]
        tensor([0.2008, 0.2008, 0.2008])
    """
    if not isinstance(x, Tensor) or x.dim() < 2:
        raise ValueError(f"x must be a (B, ..., D) tensor, got {getattr(x, 'shape', type(x).__name__)}")
    return _filter(
        x, state, dt, config, valid, restart, torch.zeros((), dtype=x.dtype, device=x.device),
        lambda u, v: u - v, lambda u, prev, delta, a: prev + a * delta,
    )


def _rotation_difference(R: Tensor, P: Tensor) -> Tensor:
    """``(B, 3)`` the rotation vector of ``P^T R``: from ``P`` to ``R`` in ``P``'s tangent space."""
    return matrix_to_axis_angle(torch.matmul(P.transpose(-1, -2), R))


def _rotation_advance(R: Tensor, prev: Tensor, delta: Tensor, a: Tensor) -> Tensor:
    """``prev exp(a delta)``, written ``R exp(-(1 - a) delta)`` (equal where ``R = prev exp(delta)``): the raw
    rotation times an exponential, orthonormal to rounding."""
    return torch.matmul(R, axis_angle_to_matrix((a - 1.0) * delta))


def one_euro_rotation_step(
    R: Tensor, state: OneEuroState | None, dt: Tensor | float, config: OneEuroConfig, *,
    valid: Tensor | None = None, restart: Tensor | None = None,
) -> tuple[Tensor, OneEuroState]:  # fmt: skip
    """One frame of the One-Euro filter of B streams of rotations, on SO(3) (module docstring): the speed is the
    angular velocity's norm (rad/s, ``beta`` in Hz per rad/s), the output moves from the previous one along the
    geodesic towards ``R``.

    Args:
        R: ``(B, 3, 3)`` rotation matrices (taken as rotations: not checked).
        state: the state the previous frame returned, or None (the first frame).
        dt: seconds since the previous frame, a number or ``(B,)``.
        config: the filter's settings.
        valid: ``(B,)`` bool, the frame is usable (default all); restart: ``(B,)`` bool, start afresh here
            (:func:`one_euro_step`).

    Returns:
        ``(B, 3, 3)`` the filtered rotations (``R`` itself where a stream starts or the frame is not usable), and
        the state for the next frame.

    Example:
        >>> from torchface.geometry import euler_to_matrix
        >>> R0, state = one_euro_rotation_step(torch.eye(3)[None], None, 0.04, OneEuroConfig())
        >>> R1 = euler_to_matrix(torch.tensor([[10.0, 0.0, 0.0]]))
        >>> R, state = one_euro_rotation_step(R1, state, 0.04, OneEuroConfig())
        >>> matrix_to_euler(R).round(decimals=2) + 0.0                    # a fifth of the way: alpha(1 Hz) at 25 fps
        tensor([[2.0100, 0.0000, 0.0000]])
    """
    if not isinstance(R, Tensor) or R.dim() != 3 or tuple(R.shape[1:]) != (3, 3):
        raise ValueError(f"R must be a (B, 3, 3) tensor, got {getattr(R, 'shape', type(R).__name__)}")
    eye = torch.eye(3, dtype=R.dtype, device=R.device) if R.is_floating_point() else torch.eye(3)
    return _filter(R, state, dt, config, valid, restart, eye, _rotation_difference, _rotation_advance)


@dataclass(frozen=True, eq=False)
class SmoothingState:
    """:func:`smooth_result`'s state after a frame.

    Attributes:
        rotation: the rotation filter's state, or None (not smoothed).
        translation: the translation filter's state, or None.
        expression: the animation units' filter state (its signal ``(B, A, 1)``), or None.
        time: ``(B,)`` the frame's time, seconds (:class:`ResultSmoother`: the timestamps given, or the frame
            count over ``fps``).
    """

    rotation: OneEuroState | None
    translation: OneEuroState | None
    expression: OneEuroState | None
    time: Tensor

    def select(self, index: Sequence[int] | Tensor) -> "SmoothingState":
        """The state of streams ``index`` (``(B',)`` stream indices, a list or int64 tensor; or a ``(B,)`` bool
        mask), as :meth:`TrackerState.select <torchface.tracker.TrackerState.select>` keeps them."""
        # (as TrackerState.select checks them: a 0-d index dropped the batch dimension, an index out of range, a
        # mask of another length, None or a slice were torch's errors, a uint8 mask was taken for indices)
        index = stream_index(index, int(self.time.shape[0]), self.time.device)

        def pick(s: OneEuroState | None) -> OneEuroState | None:
            return None if s is None else s.select(index)

        return SmoothingState(pick(self.rotation), pick(self.translation), pick(self.expression), self.time[index])


def smooth_result(
    result: TrackResult, state: SmoothingState | None, time: Tensor, config: SmoothingConfig,
    facs_matrix: Tensor | None = None, restart: Tensor | None = None,
) -> tuple[TrackResult, SmoothingState]:  # fmt: skip
    """Smooth one frame's :class:`~torchface.tracker.TrackResult` of B streams (the functional core of
    :class:`ResultSmoother`).

    The rotation (``rotation``; ``axis_angle`` and ``ypr_deg`` follow it), the translation and, with
    ``config.expression``, the animation units (``expression``; ``anim_coeffs`` moved by the same amount, ``facs``
    the smoothed expression's) are replaced by their filtered values; every other field is the result's. A stream
    starts afresh (its fields the raw ones, bit for bit) at its first frame, at ``restart`` and at the first
    successful frame after one that is not (:attr:`~torchface.tracker.TrackResult.success`); an unsuccessful frame
    is passed through raw.

    Args:
        result: the tracker's result, batch B.
        state: the state the previous frame returned, or None (the first frame).
        time: ``(B,)`` the frame's time in seconds (the step is its difference to the previous frame's; a step that
            is not positive starts the stream afresh).
        config: what to smooth, how.
        facs_matrix: ``(n_facs, A)`` the model's FACS links (:attr:`~torchface.model.FaceModel.facs_matrix`),
            needed with ``config.expression``.
        restart: ``(B,)`` bool, the streams that start afresh at this frame (e.g. at a re-anchoring), or None.

    Returns:
        The smoothed result and the state for the next frame.
    """
    if not isinstance(result, TrackResult):
        raise TypeError(f"result must be a TrackResult, got {type(result).__name__}")
    if not isinstance(config, SmoothingConfig):
        raise TypeError(f"config must be a SmoothingConfig, got {type(config).__name__}")
    B = result.rotation.shape[0]
    time = _seconds(time, B, "time", result.rotation.device)
    if state is not None and state.time.shape[0] != B:
        raise ValueError(f"the smoothing state holds {state.time.shape[0]} streams, the result {B}: select() the "
                         "state as the tracker's streams change, or reset it")  # fmt: skip
    dt = time - state.time if state is not None else torch.ones_like(time)  # (the first frame starts anyway)
    valid = result.success.to(result.rotation.device)
    changes: dict[str, Any] = {}  # (replace checks each value against every field's type)
    rot = trans = expr = None
    if config.rotation is not None:
        R, rot = one_euro_rotation_step(result.rotation, None if state is None else state.rotation,
                                        dt.to(result.rotation.dtype), config.rotation, valid=valid, restart=restart)
        kept = (R == result.rotation).flatten(1).all(1)  # (passed through: the raw fields, bit for bit)
        changes["rotation"] = R
        changes["axis_angle"] = torch.where(kept[:, None], result.axis_angle, matrix_to_axis_angle(R))
        changes["ypr_deg"] = torch.where(kept[:, None], result.ypr_deg, matrix_to_euler(R))
    if config.translation is not None:
        changes["translation"], trans = one_euro_step(
            result.translation, None if state is None else state.translation, dt.to(result.translation.dtype),
            config.translation, valid=valid, restart=restart,
        )  # fmt: skip
    if config.expression is not None:
        if facs_matrix is None:
            raise ValueError("smoothing the expression needs the model's facs_matrix (ResultSmoother's model)")
        e = result.expression
        smoothed, expr = one_euro_step(e.unsqueeze(-1), None if state is None else state.expression,
                                       dt.to(e.dtype), config.expression, valid=valid, restart=restart)  # fmt: skip
        smoothed = smoothed.squeeze(-1)
        kept = (smoothed == e).all(1, keepdim=True)
        changes["expression"] = smoothed
        changes["anim_coeffs"] = torch.where(kept, result.anim_coeffs, result.anim_coeffs + (smoothed - e))
        facs = smoothed @ facs_matrix.to(device=e.device, dtype=e.dtype).T
        changes["facs"] = torch.where(kept, result.facs, facs)
    return replace(result, **changes), SmoothingState(rot, trans, expr, time)


def smooth_pose_series(
    rotation: Tensor, translation: Tensor, success: Tensor, time: Tensor, config: SmoothingConfig,
    restart: Tensor | None = None, reanchored: Tensor | None = None,
) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Smooth whole recorded pose series offline, frame after frame, as :class:`ResultSmoother` smooths them online
    (e.g. the rows of a ``torchface track`` CSV: ``r00 .. r22``, ``pose_T*``, ``success``, ``timestamp``).

    Args:
        rotation: ``(B, T, 3, 3)`` head rotations; translation: ``(B, T, 3)`` mm.
        success: ``(B, T)`` bool, the frames' estimates are usable.
        time: ``(B, T)`` the frames' times, seconds.
        config: its ``rotation`` and ``translation`` filters (None: that series is returned as it is).
        restart: ``(B, T)`` bool, frames where a stream starts afresh, or None.
        reanchored: ``(B, T)`` bool, the frames whose tracking step the online start re-anchored the stream in
            (:func:`reanchored_streams` after each step; a ``torchface track`` sidecar's
            ``start.reanchored_at_frame``), or None: the stream starts afresh at the frame after each, the first of
            the re-anchored estimate, as :class:`ResultSmoother` given ``tracker_state`` and
            ``torchface track --smooth`` start it.

    Returns:
        ``(B, T, 3, 3)`` and ``(B, T, 3)`` the smoothed series.

    Example:
        >>> R = torch.eye(3).expand(1, 5, 3, 3)
        >>> t = torch.tensor([0.0, 0.0, 10.0, 10.0, 10.0]).view(1, 5, 1).expand(1, 5, 3)
        >>> time = torch.arange(5.0)[None] / 25
        >>> _, smooth = smooth_pose_series(R, t, torch.ones(1, 5, dtype=torch.bool), time,
        ...                                SmoothingConfig(translation=OneEuroConfig(beta=0.0)))
        >>> smooth[0, :, 0]
        tensor([0.0000, 0.0000, 2.0085, 3.6136, 4.8963])
    """
    if not isinstance(config, SmoothingConfig):
        raise TypeError(f"config must be a SmoothingConfig, got {type(config).__name__}")
    if not isinstance(rotation, Tensor) or rotation.dim() != 4 or tuple(rotation.shape[2:]) != (3, 3):
        raise ValueError(f"rotation must be (B, T, 3, 3), got {getattr(rotation, 'shape', type(rotation).__name__)}")
    B, T = rotation.shape[:2]
    masks = tuple((name, x) for name, x in (("restart", restart), ("reanchored", reanchored)) if x is not None)
    for name, x, shape in (("translation", translation, (B, T, 3)), ("success", success, (B, T)),
                           ("time", time, (B, T))) + tuple((name, x, (B, T)) for name, x in masks):
        if not isinstance(x, Tensor) or tuple(x.shape) != shape:
            raise ValueError(f"{name} must be {shape}, got {getattr(x, 'shape', type(x).__name__)}")
    if success.dtype != torch.bool or any(x.dtype != torch.bool for _, x in masks):
        raise ValueError("success, restart and reanchored must be bool tensors")
    if (got := _flag_or_complex(time)) is not None:  # (a bool series was taken as 0 and 1 seconds)
        raise TypeError(f"time must be real seconds, got {got}")
    if reanchored is not None:  # (afresh at the frame after each re-anchoring step)
        after = torch.zeros_like(reanchored)
        after[:, 1:] = reanchored[:, :-1]
        restart = after if restart is None else restart | after.to(restart.device)
    time = time.to(torch.float64)
    R_out, t_out = [], []
    rot = trans = None
    for k in range(T):
        dt = time[:, k] - time[:, k - 1] if k else torch.ones_like(time[:, 0])
        again = None if restart is None else restart[:, k]
        R, t = rotation[:, k], translation[:, k]
        if config.rotation is not None:
            R, rot = one_euro_rotation_step(R, rot, dt.to(R.dtype), config.rotation, valid=success[:, k],
                                            restart=again)  # fmt: skip
        if config.translation is not None:
            t, trans = one_euro_step(t, trans, dt.to(t.dtype), config.translation, valid=success[:, k],
                                     restart=again)  # fmt: skip
        R_out.append(R)
        t_out.append(t)
    return torch.stack(R_out, 1), torch.stack(t_out, 1)


def reanchored_streams(
    state: TrackerState, before: tuple[Tensor, Tensor] | None, num_streams: int | None = None,
) -> tuple[Tensor, tuple[Tensor, Tensor] | None]:  # fmt: skip
    """Which streams the online start has re-anchored since ``before``: those whose re-anchoring offsets
    (``ManagementState.head_rotation`` ``(B, 3, 3)`` and ``head_translation`` ``(B, 3)``, set once the online start
    re-anchors a stream) changed. :class:`ResultSmoother` asks it after each step it is given ``tracker_state`` at,
    and the stream starts afresh at its next result; offline, the frames it flags are
    :func:`smooth_pose_series`' ``reanchored``.

    Args:
        state: the tracker's state after a step (``tracker.state``).
        before: the offsets this function returned for the previous step's state, or None (none yet: a stream whose
            offset is not the identity has been re-anchored).
        num_streams: B, checked against the state's streams (None: the state's).

    Returns:
        ``(B,)`` bool on the state's device, the re-anchored streams, and the offsets to pass as ``before`` next
        time (detached copies; ``before`` itself while the state holds none).
    """
    if not isinstance(state, TrackerState):
        raise TypeError(f"tracker_state must be the tracker's TrackerState, got {type(state).__name__}")
    B = state.params.shape[0] if num_streams is None else num_streams
    ms = state.management
    if ms is None or ms.head_rotation is None or ms.head_translation is None:
        return torch.zeros(B, dtype=torch.bool, device=state.params.device), before
    D, d = ms.head_rotation.detach().clone(), ms.head_translation.detach().clone()
    if D.shape[0] != B:
        raise ValueError(f"tracker_state holds {D.shape[0]} streams, the result {B}")
    if before is None:  # (none recorded yet: a stream whose offset is not the identity was re-anchored)
        eye = torch.eye(3, dtype=D.dtype, device=D.device)
        before = (eye.expand_as(D), torch.zeros_like(d))
    changed = (D != before[0]).flatten(1).any(1) | (d != before[1]).any(1)
    return changed, (D, d)


class ResultSmoother:
    """Smooth the tracker's results over time, per stream: a thin stateful loop over :func:`smooth_result`.

    Opt-in and outside the tracker: the tracker's own results (and its state, which it tracks from) stay raw, and
    the smoother returns new :class:`~torchface.tracker.TrackResult` objects. Streams start afresh at their first
    result, at the first successful frame after an unsuccessful one (a loss and its recovery: a detector's
    re-initialisation too), where ``restart`` says and, given the tracker's state, at the first result after the
    online start re-anchors them (as ``torchface track --smooth`` starts after the re-anchoring frame); call :meth:`reset` when the tracker is initialised again, :meth:`select` when it keeps some
    streams.

    Args:
        config: what to smooth and how (:class:`SmoothingConfig`; its defaults smooth the pose).
        fps: the frame rate, Hz, for calls without ``timestamps`` (frame ``n`` at ``n / fps`` seconds).
        model: the tracker's face model; needed when ``config.expression`` is set (its FACS links map the smoothed
            expression to ``facs``).

    Example:
        >>> smoother = ResultSmoother(SmoothingConfig(), fps=25.0)                       # doctest: +SKIP
        >>> smooth = smoother(tracker.initialise(frames[:, 0], landmarks))             # doctest: +SKIP
        >>> for t in range(1, T):                                                      # doctest: +SKIP
        ...     raw = tracker(frames[:, t])                                            # the tracker's own
        ...     smooth = smoother(raw, tracker_state=tracker.state)                    # smoothed pose
    """

    #: (class default: for smoothers pickled before the attribute existed)
    _timed: bool | None = None

    def __init__(
        self, config: SmoothingConfig | None = None, fps: float | None = None, model: FaceModel | None = None
    ) -> None:
        config = SmoothingConfig() if config is None else config
        if not isinstance(config, SmoothingConfig):
            raise TypeError(f"config must be a SmoothingConfig, got {type(config).__name__}")
        fps = check_number(fps, "fps", "(0, inf)", optional=True, unit="frames per second")  # (OneEuroConfig's rule)
        if model is not None and not isinstance(model, FaceModel):
            raise TypeError(f"model must be a FaceModel or None, got {type(model).__name__}")
        if config.expression is not None and model is None:
            raise ValueError("smoothing the expression (config.expression) needs the tracker's face model: "
                             "ResultSmoother(config, fps, model=tracker.model)")  # fmt: skip
        self.config = config
        self.fps = fps
        self.facs_matrix = None if model is None else model.facs_matrix.detach()
        self._state: SmoothingState | None = None
        self._frames: Tensor | None = None  # (B,) frames counted per stream, for calls without timestamps
        self._offsets: tuple[Tensor, Tensor] | None = None  # the tracker's re-anchoring offsets at the last call
        # (B,) bool: streams re-anchored in the last call's step, whose next result is the first of the re-anchored
        # estimate (managed_step reports a frame at the offsets it was tracked under, then re-anchors)
        self._reanchoring: Tensor | None = None
        self._timed: bool | None = None  # whether the calls give timestamps (None: no call since the last reset)

    @property
    def state(self) -> SmoothingState | None:
        """The filters' state after the last call (None before the first and after :meth:`reset`)."""
        return self._state

    def reset(self) -> None:
        """Forget every stream: the next result starts them all afresh."""
        self._state = None
        self._frames = None
        self._offsets = None
        self._reanchoring = None
        self._timed = None

    def select(self, index: Sequence[int] | Tensor) -> "ResultSmoother":
        """Keep only streams ``index`` (as :meth:`FaceTracker.select <torchface.tracker.FaceTracker.select>`);
        returns the smoother."""
        if self._state is None:
            raise RuntimeError("the smoother holds no streams yet: nothing to select")
        rows = stream_index(index, int(self._state.time.shape[0]), torch.device("cpu"))  # (checked before any change)
        self._state = self._state.select(rows)
        if self._frames is not None:
            self._frames = self._frames[rows.to(self._frames.device)]
        if self._offsets is not None:
            self._offsets = (self._offsets[0][rows.to(self._offsets[0].device)],
                             self._offsets[1][rows.to(self._offsets[1].device)])  # fmt: skip
        if self._reanchoring is not None:
            self._reanchoring = self._reanchoring[rows.to(self._reanchoring.device)]
        return self

    def _reanchored(self, state: TrackerState, B: int, device: torch.device) -> Tensor:
        """``(B,)`` bool: the streams the online start re-anchored since the last call's ``state``
        (:func:`reanchored_streams`)."""
        changed, self._offsets = reanchored_streams(state, self._offsets, B)
        return changed.to(device)

    def __call__(
        self, result: TrackResult, timestamps: Tensor | None = None, restart: Tensor | None = None,
        tracker_state: TrackerState | None = None,
    ) -> TrackResult:
        """The smoothed ``result`` of the next frame of every stream.

        Args:
            result: the tracker's result, batch B (the same streams, in the same order, as the previous call's).
            timestamps: ``(B,)`` the frames' times in seconds (a video's presentation times), or None: the
                smoother's ``fps`` (each stream's frames counted from its first result). Either at every call
                until :meth:`reset`: a call without timestamps after calls with them (or the other way round) is a
                ``ValueError`` (it counted frames from 0, so that every stream's time went back and it restarted).
            restart: ``(B,)`` bool, streams that start afresh at this frame (a new video in a slot), or None.
            tracker_state: the tracker's state after this result (``tracker.state``), or None: a stream that the
                online start re-anchored in this result's step (its offsets changed since the last call's state)
                starts afresh at its next result, the first of the re-anchored estimate (the result of the
                re-anchoring frame itself is the estimate tracked before it, which the refined one may step from).
        """
        if not isinstance(result, TrackResult):
            raise TypeError(f"result must be a TrackResult, got {type(result).__name__}")
        B, device = result.rotation.shape[0], result.rotation.device
        if self._state is not None and self._state.time.shape[0] != B:
            raise ValueError(f"the smoother holds {self._state.time.shape[0]} streams, the result has {B}: select() "
                             "or reset() the smoother as the tracker's streams change")  # fmt: skip
        timed = timestamps is not None
        if self._state is not None and self._timed is not None and timed != self._timed:
            given, now = ("with", "without") if self._timed else ("without", "with")
            raise ValueError(
                f"this smoother's calls were made {given} timestamps, this one {now}: give them at every call or at "
                "none (frames counted by fps start at 0 and are no video's times: each stream would go back in time "
                "and restart), or reset() the smoother first"
            )
        if timestamps is None:
            if self.fps is None:
                raise ValueError("give the frames' timestamps, or the frame rate: ResultSmoother(config, fps=...)")
            frames = torch.zeros(B, dtype=torch.float64, device=device) if self._frames is None else self._frames + 1
            self._frames = frames
            time = frames / self.fps
        else:
            time = _seconds(timestamps, B, "timestamps", device)  # (named as given: smooth_result says "time")
        restart = None if restart is None else _stream_mask(restart, B, "restart", device, False)
        if self._reanchoring is not None:  # (re-anchored in the last call's step: this result is the new estimate's)
            restart = self._reanchoring if restart is None else restart | self._reanchoring
        self._reanchoring = None if tracker_state is None else self._reanchored(tracker_state, B, device)
        out, self._state = smooth_result(result, self._state, time, self.config, self.facs_matrix, restart)
        self._timed = timed
        return out
