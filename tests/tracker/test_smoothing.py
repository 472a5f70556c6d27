"""Tests of torchface.tracker.smoothing: the One-Euro filter of the tracker's outputs (vectors and SO(3) rotations),
its per-stream starts, the result wrapper and its settings. Feature tests on known signals (a constant, a ramp's lag
against the analytic steady state, white noise's variance against a first-order low-pass's), the rotation path
against a slow quaternion reference, batch against streams alone, float64 gradcheck; one small tracking run checks
that a smoother leaves the tracker's own results as they are."""

from __future__ import annotations

import copy
import math
import pickle

import numpy as np
import pytest
import torch

from torchface.geometry.so3 import axis_angle_to_matrix, euler_to_matrix, matrix_to_axis_angle, matrix_to_euler
from torchface.model.candide import load_candide3
from torchface.tracker import (
    OneEuroConfig,
    ResultSmoother,
    SmoothingConfig,
    TrackResult,
    one_euro_alpha,
    one_euro_rotation_step,
    one_euro_step,
    smooth_pose_series,
    smooth_result,
)

D = torch.float64
FPS = 25.0
DT = 1.0 / FPS


def run_vector(x: torch.Tensor, config: OneEuroConfig, valid=None, restart=None, dt: float = DT) -> torch.Tensor:
    """``(B, T, D)`` filtered frame by frame; ``valid`` / ``restart`` ``(B, T)`` bool or None."""
    out, state = [], None
    for k in range(x.shape[1]):
        y, state = one_euro_step(x[:, k], state, dt, config, valid=None if valid is None else valid[:, k],
                                 restart=None if restart is None else restart[:, k])  # fmt: skip
        out.append(y)
    return torch.stack(out, 1)


def run_rotation(R: torch.Tensor, config: OneEuroConfig, valid=None, restart=None, dt=DT) -> torch.Tensor:
    """``(B, T, 3, 3)`` filtered frame by frame; ``dt`` a number or ``(B, T)``."""
    out, state = [], None
    for k in range(R.shape[1]):
        step = dt if not isinstance(dt, torch.Tensor) else dt[:, k]
        y, state = one_euro_rotation_step(R[:, k], state, step, config, valid=None if valid is None else valid[:, k],
                                          restart=None if restart is None else restart[:, k])  # fmt: skip
        out.append(y)
    return torch.stack(out, 1)


def random_rotations(B: int, T: int, seed: int, step_deg: float = 3.0) -> torch.Tensor:
    """``(B, T, 3, 3)`` float64 random walks on SO(3) (steps of about ``step_deg``), each from a random start."""
    g = torch.Generator().manual_seed(seed)
    start = axis_angle_to_matrix(torch.randn(B, 3, generator=g, dtype=D))
    steps = axis_angle_to_matrix(math.radians(step_deg) * torch.randn(B, T, 3, generator=g, dtype=D))
    out, R = [], start
    for k in range(T):
        R = R @ steps[:, k]
        out.append(R)
    return torch.stack(out, 1)


# ------------------------------------------------------------------------------------------------------ settings


def test_config_defaults_and_validation() -> None:
    c = SmoothingConfig()
    assert c.rotation is not None and c.translation is not None and c.expression is None
    with pytest.raises(ValueError, match="min_cutoff"):
        OneEuroConfig(min_cutoff=0.0)
    with pytest.raises(ValueError, match="d_cutoff"):
        OneEuroConfig(d_cutoff=float("nan"))
    with pytest.raises(ValueError, match="beta"):
        OneEuroConfig(beta=-1.0)
    with pytest.raises(ValueError, match="beta"):
        OneEuroConfig(beta=float("inf"))
    with pytest.raises(TypeError, match="min_cutoff"):
        OneEuroConfig(min_cutoff="1")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="rotation"):
        SmoothingConfig(rotation=(1.0, 0.0))  # type: ignore[arg-type]
    with pytest.raises(Exception):  # frozen
        c.rotation = None  # type: ignore[misc]
    assert OneEuroConfig(min_cutoff=np.float32(2.0)).min_cutoff == 2.0


def test_bad_inputs_are_refused() -> None:
    cfg = OneEuroConfig()
    with pytest.raises(ValueError, match=r"R must be a \(B, 3, 3\)"):
        one_euro_rotation_step(torch.eye(3), None, DT, cfg)
    with pytest.raises(ValueError, match=r"x must be a \(B, \.\.\., D\)"):
        one_euro_step(torch.zeros(3), None, DT, cfg)
    with pytest.raises(ValueError, match=r"valid must be a \(2,\) bool"):
        one_euro_step(torch.zeros(2, 3), None, DT, cfg, valid=torch.ones(2))
    with pytest.raises(ValueError, match=r"dt must be a number or a \(2,\)"):
        one_euro_step(torch.zeros(2, 3), None, torch.ones(3), cfg)
    _, state = one_euro_step(torch.zeros(2, 3), None, DT, cfg)
    with pytest.raises(ValueError, match="select"):
        one_euro_step(torch.zeros(3, 3), state, DT, cfg)
    with pytest.raises(TypeError, match="OneEuroConfig"):
        one_euro_step(torch.zeros(2, 3), None, DT, SmoothingConfig())  # type: ignore[arg-type]
    for fps in (0.0, math.inf, math.nan):  # (refused before too: now in OneEuroConfig's words, a str a TypeError)
        with pytest.raises(ValueError, match=r"^fps must be a finite number > 0 \(frames per second\) or None, got"):
            ResultSmoother(fps=fps)
    with pytest.raises(TypeError, match=r"^fps must be a real number or None, got str '25'$"):
        ResultSmoother(fps="25")
    with pytest.raises(ValueError, match="face model"):
        ResultSmoother(SmoothingConfig(expression=OneEuroConfig()), fps=FPS)


# ------------------------------------------------------------------------------------------- known signals (vector)


def test_alpha_is_the_first_order_low_pass() -> None:
    """alpha = 1 / (1 + tau / T_e), tau = 1 / (2 pi f_c) (Casiraghi et al. 2012)."""
    fc, dt = torch.tensor([0.5, 1.0, 4.0], dtype=D), torch.tensor(DT, dtype=D)
    tau = 1.0 / (2 * math.pi * fc)
    torch.testing.assert_close(one_euro_alpha(fc, dt), 1.0 / (1.0 + tau / dt), rtol=1e-15, atol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_constant_stays_exact(dtype) -> None:
    x = torch.tensor([[1.5, -2.25, 1e3], [0.1, 0.2, 0.3]], dtype=dtype)[:, None].expand(2, 50, 3)
    out = run_vector(x, OneEuroConfig(min_cutoff=0.3, beta=2.0))
    assert out.dtype == dtype
    assert torch.equal(out, x)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_constant_rotation_stays_put(dtype) -> None:
    R = axis_angle_to_matrix(torch.tensor([[0.3, -1.2, 0.5], [2.0, 0.1, 0.0]], dtype=D)).to(dtype)
    out = run_rotation(R[:, None].expand(2, 60, 3, 3), OneEuroConfig(min_cutoff=0.3, beta=2.0))
    tol = 1e-12 if dtype == D else 2e-6
    torch.testing.assert_close(out, R[:, None].expand_as(out), rtol=0, atol=tol)
    eye = torch.eye(3, dtype=dtype)
    torch.testing.assert_close(out @ out.transpose(-1, -2), eye.expand_as(out), rtol=0, atol=tol)


@pytest.mark.parametrize("beta", [0.0, 0.05])
def test_ramp_lag_within_the_analytic_bound(beta: float) -> None:
    """A ramp ``x = v t``: the lag ``x - x^`` never exceeds ``v / (2 pi min_cutoff)`` (the fixed low-pass's steady
    lag: the cutoff is never below ``min_cutoff``) and settles at ``v / (2 pi f_c)``, ``f_c = min_cutoff + beta |v|``
    (the derivative's low-pass settles on ``v`` exactly)."""
    v, mc = 40.0, 1.0  # mm/s
    T = 300
    t = torch.arange(T, dtype=D) * DT
    x = (v * t)[None, :, None].expand(1, T, 3).contiguous()
    out = run_vector(x, OneEuroConfig(min_cutoff=mc, beta=beta))
    lag = (x - out)[0, :, 0]
    speed = v * math.sqrt(3)  # the speed is the norm of the 3-vector's velocity
    steady = v / (2 * math.pi * (mc + beta * speed))
    bound = v / (2 * math.pi * mc)
    assert float(lag.max()) <= bound * (1 + 1e-9)
    assert float(lag[0]) == 0 and bool((lag[1:] > 0).all())
    assert abs(float(lag[-1]) - steady) < 1e-9 * steady
    if beta > 0:  # faster than the fixed low-pass: the speed raised the cutoff
        assert steady < bound / 2


def test_ramp_lag_of_a_rotation() -> None:
    """A rotation turning at constant angular velocity lags by ``w / (2 pi f_c)`` radians once settled, and never
    by more than ``w / (2 pi min_cutoff)``."""
    w, mc, beta = 1.0, 1.0, 2.0  # rad/s
    T = 300
    axis = torch.tensor([0.6, 0.0, 0.8], dtype=D)
    R = axis_angle_to_matrix((torch.arange(T, dtype=D) * DT * w)[:, None] * axis)[None]
    out = run_rotation(R, OneEuroConfig(min_cutoff=mc, beta=beta))
    lag = matrix_to_axis_angle(out.transpose(-1, -2) @ R)[0].norm(dim=-1)
    steady = w / (2 * math.pi * (mc + beta * w))
    assert float(lag.max()) <= w / (2 * math.pi * mc)
    assert abs(float(lag[-1]) - steady) < 1e-9


def test_white_noise_variance_reduced_by_the_low_pass_factor() -> None:
    """White noise through a fixed low-pass (beta 0): the output's stationary variance is ``alpha / (2 - alpha)``
    of the input's (first-order recursion ``y_t = (1 - alpha) y_{t-1} + alpha x_t``)."""
    g = torch.Generator().manual_seed(0)
    B, T, skip = 64, 2000, 100
    x = torch.randn(B, T, 1, generator=g, dtype=D)
    for mc in (0.5, 2.0):
        out = run_vector(x, OneEuroConfig(min_cutoff=mc, beta=0.0))
        a = float(one_euro_alpha(torch.tensor(mc, dtype=D), torch.tensor(DT, dtype=D)))
        ratio = float(out[:, skip:].var() / x[:, skip:].var())
        assert abs(ratio / (a / (2 - a)) - 1) < 0.05, (mc, ratio, a / (2 - a))


def test_speed_raises_the_cutoff() -> None:
    """A signal moving fast is followed far more closely than by the fixed low-pass at ``min_cutoff``; one at rest
    with small noise is filtered as by that low-pass."""
    cfg, fixed = OneEuroConfig(min_cutoff=1.0, beta=0.5), OneEuroConfig(min_cutoff=1.0)
    fast = (torch.arange(20, dtype=D) * 4.0)[None, :, None]  # 100 units/s
    lag = float(fast[0, 19, 0] - run_vector(fast, cfg)[0, 19, 0])
    lag_fixed = float(fast[0, 19, 0] - run_vector(fast, fixed)[0, 19, 0])
    assert lag < lag_fixed / 5
    still = 1e-3 * torch.randn(1, 200, 1, generator=torch.Generator().manual_seed(3), dtype=D)
    a, b = run_vector(still, cfg), run_vector(still, fixed)
    assert float((a - b).abs().max()) < 0.02 * float(still.abs().max())


# ----------------------------------------------------------------------------------------------- SO(3) reference


def _quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix (Shepperd's method)."""
    t = np.trace(R)
    if t > 0:
        s = 2 * math.sqrt(1 + t)
        return np.array([s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    i = int(np.argmax(np.diag(R)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2 * math.sqrt(1 + R[i, i] - R[j, j] - R[k, k])
    q = np.zeros(4)
    q[0] = (R[k, j] - R[j, k]) / s
    q[1 + i] = s / 4
    q[1 + j] = (R[j, i] + R[i, j]) / s
    q[1 + k] = (R[k, i] + R[i, k]) / s
    return q


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])  # fmt: skip


def _qconj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1, -1, -1, -1])


def _qlog(q: np.ndarray) -> np.ndarray:
    """Rotation vector of a unit quaternion (shortest: ``w >= 0``)."""
    q = q if q[0] >= 0 else -q
    n = np.linalg.norm(q[1:])
    return np.zeros(3) if n == 0 else q[1:] / n * 2 * math.atan2(n, q[0])


def _qexp(v: np.ndarray) -> np.ndarray:
    a = np.linalg.norm(v)
    return np.array([1.0, 0, 0, 0]) if a == 0 else np.concatenate([[math.cos(a / 2)], math.sin(a / 2) * v / a])


def _slerp(p: np.ndarray, q: np.ndarray, a: float) -> np.ndarray:
    """The quaternion ``a`` of the way from ``p`` to ``q`` along the geodesic."""
    return _qmul(p, _qexp(a * _qlog(_qmul(_qconj(p), q))))


def _qmatrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])  # fmt: skip


def slow_reference(R: np.ndarray, valid: np.ndarray, dt: np.ndarray, cfg: OneEuroConfig) -> np.ndarray:
    """The One-Euro filter on unit quaternions, one stream and one frame at a time (Casiraghi et al.'s pseudocode,
    the speed the norm of the raw angular velocity's low-pass, the step a slerp)."""
    def alpha(fc: float, te: float) -> float:
        return 1.0 / (1.0 + 1.0 / (2 * math.pi * fc * te))

    B, T = R.shape[:2]
    out = np.zeros_like(R)
    for b in range(B):
        hat = raw = None
        rate = np.zeros(3)
        for t in range(T):
            q = _quat(R[b, t])
            if not valid[b, t]:
                out[b, t], hat, raw = R[b, t], None, None
                continue
            if hat is None:
                out[b, t], hat, raw, rate = R[b, t], q, q, np.zeros(3)
                continue
            w = _qlog(_qmul(_qconj(raw), q)) / dt[b, t]
            rate = rate + alpha(cfg.d_cutoff, dt[b, t]) * (w - rate)
            a = alpha(cfg.min_cutoff + cfg.beta * np.linalg.norm(rate), dt[b, t])
            hat, raw = _slerp(hat, q, a), q
            out[b, t] = _qmatrix(hat)
    return out


def test_rotation_filter_against_slow_reference() -> None:
    B, T = 3, 40
    R = random_rotations(B, T, seed=1, step_deg=4.0)
    g = torch.Generator().manual_seed(2)
    valid = torch.rand(B, T, generator=g) > 0.15
    dt = (0.03 + 0.02 * torch.rand(B, T, generator=g, dtype=D))  # uneven frame times
    cfg = OneEuroConfig(min_cutoff=0.7, beta=1.5, d_cutoff=1.3)
    out = run_rotation(R, cfg, valid=valid, dt=dt)
    ref = slow_reference(R.numpy(), valid.numpy(), dt.numpy(), cfg)
    np.testing.assert_allclose(out.numpy(), ref, rtol=0, atol=1e-10)
    # orthonormal, and not the matrices' entries filtered one by one (which leaves SO(3))
    torch.testing.assert_close(out @ out.transpose(-1, -2), torch.eye(3, dtype=D).expand_as(out), rtol=0, atol=1e-12)
    per_entry = run_vector(R.flatten(2), cfg, valid=valid).view_as(R)
    assert float((per_entry @ per_entry.transpose(-1, -2) - torch.eye(3, dtype=D)).abs().max()) > 1e-3


def test_rotation_stays_orthonormal_over_a_long_stream() -> None:
    """float32, 5000 frames of small steps: each output is a raw rotation times an exponential, so rounding does
    not accumulate."""
    R = random_rotations(2, 5000, seed=4, step_deg=0.3).float()
    out = run_rotation(R, OneEuroConfig(min_cutoff=0.5, beta=1.0))
    err = (out @ out.transpose(-1, -2) - torch.eye(3)).abs().amax(dim=(-1, -2))
    assert float(err[:, -100:].max()) < 1e-6


# --------------------------------------------------------------------------------------- batch, starts, non-finite


def test_batch_equals_each_stream_alone() -> None:
    B, T = 4, 30
    R = random_rotations(B, T, seed=5)
    g = torch.Generator().manual_seed(6)
    x = torch.cumsum(torch.randn(B, T, 3, generator=g, dtype=D), 1)
    valid = torch.rand(B, T, generator=g) > 0.2
    restart = torch.rand(B, T, generator=g) > 0.9
    cfg = OneEuroConfig(min_cutoff=0.8, beta=1.0)
    both_R, both_x = run_rotation(R, cfg, valid, restart), run_vector(x, cfg, valid, restart)
    for b in range(B):
        alone_R = run_rotation(R[b : b + 1], cfg, valid[b : b + 1], restart[b : b + 1])
        alone_x = run_vector(x[b : b + 1], cfg, valid[b : b + 1], restart[b : b + 1])
        torch.testing.assert_close(both_R[b : b + 1], alone_R, rtol=0, atol=1e-14)
        assert torch.equal(both_x[b : b + 1], alone_x)


def test_unsuccessful_frames_pass_through_and_restart_the_stream() -> None:
    """A loss (frames 10-14 not valid) and a recovery 50 mm away: the lost frames are the raw input, the recovery
    frame starts afresh (its output the raw value, not smeared from before the loss), the next is filtered from it;
    the other stream, always valid, is filtered through."""
    T = 25
    x = torch.zeros(2, T, 3, dtype=D)
    x[:, 15:] = 50.0
    x[:, :, 0] += torch.linspace(0, 1, T, dtype=D)  # (moving a little)
    valid = torch.ones(2, T, dtype=torch.bool)
    valid[0, 10:15] = False
    cfg = OneEuroConfig(min_cutoff=1.0, beta=0.0)
    out = run_vector(x, cfg, valid)
    assert torch.equal(out[0, 10:16], x[0, 10:16])  # lost frames and the recovery frame: raw
    assert not torch.equal(out[0, 16], x[0, 16])  # then filtered again
    assert float((out[0, 16] - x[0, 16]).abs().max()) < 0.1  # from the recovered value, not from before the loss
    assert float((x[1, 15] - out[1, 15]).abs().max()) > 30  # the stream without a loss smears its jump
    # the same with rotations: a 60-degree jump after a loss is not smeared
    R = euler_to_matrix(torch.where(torch.arange(T)[:, None] >= 15, torch.tensor([60.0, 0, 0], dtype=D),
                                    torch.zeros(3, dtype=D)))[None].expand(2, T, 3, 3)  # fmt: skip
    outR = run_rotation(R, cfg, valid)
    assert torch.equal(outR[0, 15], R[0, 15])
    assert float(matrix_to_euler(outR[1, 15:16])[0, 0]) < 20


def test_restart_starts_the_stream_afresh() -> None:
    x = torch.zeros(2, 10, 2, dtype=D)
    x[:, 5:] = 10.0
    restart = torch.zeros(2, 10, dtype=torch.bool)
    restart[0, 5] = True
    out = run_vector(x, OneEuroConfig(), restart=restart)
    assert torch.equal(out[0, 5:], x[0, 5:])  # fresh at 5, then constant: exact
    assert float(out[1, 5, 0]) < 5


def test_non_finite_input_passes_through_without_touching_the_filter() -> None:
    """A NaN row is returned as it came and restarts its stream; the state stays finite, the other streams are
    filtered as without it."""
    g = torch.Generator().manual_seed(7)
    x = torch.randn(2, 12, 3, generator=g, dtype=D)
    bad = x.clone()
    bad[0, 4, 1] = float("nan")
    bad[0, 7] = float("inf")
    cfg = OneEuroConfig(min_cutoff=1.0, beta=0.3)
    out = run_vector(bad, cfg)
    assert torch.isnan(out[0, 4, 1]) and torch.isinf(out[0, 7]).all()
    assert torch.isfinite(out[0, [0, 1, 2, 3, 5, 6, 8, 9, 10, 11]]).all()
    assert torch.equal(out[0, 5], x[0, 5]) and torch.equal(out[0, 8], x[0, 8])  # restarted after each
    assert torch.equal(out[1], run_vector(x[1:], cfg)[0])
    R = random_rotations(1, 6, seed=8)
    R_bad = R.clone()
    R_bad[0, 2, 0, 0] = float("nan")
    outR = run_rotation(R_bad, cfg)
    assert torch.isnan(outR[0, 2, 0, 0]) and torch.isfinite(outR[0, 3:]).all()
    assert torch.equal(outR[0, 3], R[0, 3])


def test_non_positive_time_step_restarts() -> None:
    x = torch.arange(6, dtype=D)[None, :, None].expand(1, 6, 2).contiguous()
    out, state = [], None
    for k, dt in enumerate([DT, DT, 0.0, DT, -DT, DT]):
        y, state = one_euro_step(x[:, k], state, dt, OneEuroConfig())
        out.append(y)
    # a frame without a usable time step starts the stream afresh there; the next one is filtered from it
    assert torch.equal(out[2], x[:, 2]) and torch.equal(out[4], x[:, 4])
    assert not torch.equal(out[3], x[:, 3]) and not torch.equal(out[5], x[:, 5])



@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_no_nan_from_finite_input_at_extreme_steps_and_speeds(dtype) -> None:
    """Finite input never gives NaN, nor a state that does later: a positive time step too small to divide by (a
    float32 subnormal: the derivative was infinite and the state NaN for good), a cutoff too large for alpha's
    ``r / (1 + r)`` (inf / inf: a huge beta, a jump of 1e30), a huge step. Tiny steps tend to the filter's limit:
    the output holds the previous one, the derivative ``2 pi d_cutoff`` times the move."""
    cfg = OneEuroConfig(min_cutoff=1.0, beta=100.0, d_cutoff=5.0)
    tiny = torch.finfo(dtype).tiny * 1e-3  # (subnormal, positive)
    for step in (tiny, 1e-30, 1e30):
        _, state = one_euro_step(torch.zeros(2, 3, dtype=dtype), None, DT, cfg)
        y, state = one_euro_step(torch.ones(2, 3, dtype=dtype), state, step, cfg)
        z, state = one_euro_step(torch.full((2, 3), 2.0, dtype=dtype), state, DT, cfg)
        assert torch.isfinite(y).all() and torch.isfinite(z).all() and torch.isfinite(state.rate).all(), step
    _, state = one_euro_step(torch.zeros(1, 3, dtype=dtype), None, DT, cfg)
    y, state = one_euro_step(torch.ones(1, 3, dtype=dtype), state, tiny, cfg)
    assert float(y.abs().max()) < 1e-6  # (held)
    torch.testing.assert_close(state.rate, torch.full((1, 3), 2 * math.pi * 5.0, dtype=dtype))
    for config, jump in ((OneEuroConfig(beta=1e38), 1.0), (cfg, 1e30)):
        _, state = one_euro_step(torch.zeros(1, 3, dtype=dtype), None, DT, config)
        y, state = one_euro_step(torch.full((1, 3), jump, dtype=dtype), state, DT, config)
        assert torch.isfinite(y).all() and torch.isfinite(state.rate).all()
        torch.testing.assert_close(y, torch.full((1, 3), jump, dtype=dtype))  # (alpha's limit, 1: no lag)
    R = random_rotations(1, 3, seed=3).to(dtype)
    _, rstate = one_euro_rotation_step(R[:, 0], None, DT, cfg)
    for k, step in ((1, tiny), (2, DT)):
        Q, rstate = one_euro_rotation_step(R[:, k], rstate, step, cfg)
        assert torch.isfinite(Q).all() and torch.isfinite(rstate.rate).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_16_bit_signals_are_filtered_in_float32(dtype) -> None:
    """A 16-bit signal is filtered in float32 and returned in its dtype: in float16 the square of a 100 mm/s
    move's speed overflowed (NaN out of a realistic translation)."""
    x = torch.cumsum(torch.full((2, 8, 3), 4.0, dtype=D), 1)  # 100 mm/s at 25 frames/s
    cfg = OneEuroConfig(min_cutoff=1.0, beta=1.0, d_cutoff=5.0)
    half = run_vector(x.to(dtype), cfg)
    assert half.dtype == dtype and torch.isfinite(half).all()
    torch.testing.assert_close(half.float(), run_vector(x.to(dtype).float(), cfg).to(dtype).float())
    R = random_rotations(1, 5, seed=4)
    Q = run_rotation(R.to(dtype), cfg)
    assert Q.dtype == dtype and torch.isfinite(Q).all()

# ------------------------------------------------------------------------------------------------------ gradients


def test_gradcheck_vector_and_rotation() -> None:
    """The filter is differentiable in its inputs (three frames: through the state and the speed's norm,
    including a frame at rest, where the norm is 0)."""
    cfg = OneEuroConfig(min_cutoff=0.8, beta=1.5)
    g = torch.Generator().manual_seed(9)
    x = torch.randn(2, 3, 3, generator=g, dtype=D)
    x[1, 1] = x[1, 0]  # (zero speed on stream 1's second frame)
    x.requires_grad_(True)

    def vec(x: torch.Tensor) -> torch.Tensor:
        return run_vector(x, cfg)

    assert torch.autograd.gradcheck(vec, (x,))
    w = (0.3 * torch.randn(2, 3, 3, generator=g, dtype=D))
    w[1, 1] = w[1, 0]
    w.requires_grad_(True)

    def rot(w: torch.Tensor) -> torch.Tensor:
        return run_rotation(axis_angle_to_matrix(w), cfg)

    assert torch.autograd.gradcheck(rot, (w,))
    grad = torch.autograd.grad(rot(w).sum(), w)[0]
    assert torch.isfinite(grad).all()


# ------------------------------------------------------------------------------------------- results and wrapper


def fake_result(R: torch.Tensor, t: torch.Tensor, expression: torch.Tensor, success: torch.Tensor) -> TrackResult:
    """A TrackResult of ``B`` streams with the given pose, expression and success (status 0 or 3)."""
    model = load_candide3().to(expression.dtype)
    B = R.shape[0]
    status = torch.where(success, torch.zeros(B, dtype=torch.int64), torch.full((B,), 3))
    anim = expression + 0.1
    return TrackResult(
        rotation=R, axis_angle=matrix_to_axis_angle(R), translation=t, ypr_deg=matrix_to_euler(R),
        anim_coeffs=anim, anim_names=model.animation_names, expression=expression,
        facs=model.facs_values(expression), facs_names=model.facs_names,
        illumination=torch.zeros(B, 5, dtype=R.dtype), illumination_names=tuple("abcde"), status=status,
        iterations=torch.zeros(B, dtype=torch.int64), cost=torch.zeros(B, dtype=R.dtype),
        num_points=torch.zeros(B, dtype=torch.int64), confidence=torch.ones(B, dtype=R.dtype),
    )  # fmt: skip


def test_result_smoother_matches_the_series_and_keeps_the_other_fields() -> None:
    B, T = 3, 20
    R = random_rotations(B, T, seed=10, step_deg=2.0)
    g = torch.Generator().manual_seed(11)
    t = 500 + torch.cumsum(torch.randn(B, T, 3, generator=g, dtype=D), 1)
    e = torch.rand(B, T, 11, generator=g, dtype=D)
    success = torch.rand(B, T, generator=g) > 0.2
    model = load_candide3().to(D)
    config = SmoothingConfig(expression=OneEuroConfig(min_cutoff=1.5, beta=0.5))
    smoother = ResultSmoother(config, fps=FPS, model=model)
    outs = [smoother(fake_result(R[:, k], t[:, k], e[:, k], success[:, k])) for k in range(T)]
    time = (torch.arange(T, dtype=D) / FPS)[None].expand(B, T)
    R_ref, t_ref = smooth_pose_series(R, t, success, time, config)
    got_R = torch.stack([o.rotation for o in outs], 1)
    assert torch.equal(got_R, R_ref) and torch.equal(torch.stack([o.translation for o in outs], 1), t_ref)
    e_ref = run_vector(e.unsqueeze(-1), config.expression, valid=success).squeeze(-1)
    got_e = torch.stack([o.expression for o in outs], 1)
    torch.testing.assert_close(got_e, e_ref, rtol=0, atol=1e-14)  # (time steps from differences of times)
    for k, o in enumerate(outs):
        raw = fake_result(R[:, k], t[:, k], e[:, k], success[:, k])
        torch.testing.assert_close(o.axis_angle, matrix_to_axis_angle(o.rotation), rtol=0, atol=1e-12)
        torch.testing.assert_close(o.ypr_deg, matrix_to_euler(o.rotation), rtol=0, atol=1e-9)
        torch.testing.assert_close(o.anim_coeffs - o.expression, raw.anim_coeffs - raw.expression, rtol=0,
                                   atol=1e-12)  # fmt: skip
        torch.testing.assert_close(o.facs, model.facs_values(o.expression), rtol=0, atol=1e-12)
        for name in ("illumination", "status", "confidence", "iterations"):
            assert torch.equal(getattr(o, name), getattr(raw, name))
        # passed through where the frame failed: the raw fields, bit for bit
        for name in ("rotation", "axis_angle", "ypr_deg", "translation", "expression", "anim_coeffs", "facs"):
            assert torch.equal(getattr(o, name)[~success[:, k]], getattr(raw, name)[~success[:, k]])


def test_result_smoother_timestamps_select_and_reset() -> None:
    B, T = 3, 8
    R = random_rotations(B, T, seed=12)
    t = torch.zeros(B, T, 3, dtype=D)
    e = torch.zeros(B, T, 11, dtype=D)
    ok = torch.ones(B, dtype=torch.bool)
    stamps = torch.arange(T, dtype=D) / FPS
    by_fps, by_time = ResultSmoother(fps=FPS), ResultSmoother()
    for k in range(T):
        a = by_fps(fake_result(R[:, k], t[:, k], e[:, k], ok))
        b = by_time(fake_result(R[:, k], t[:, k], e[:, k], ok), timestamps=stamps[k].expand(B))
        torch.testing.assert_close(a.rotation, b.rotation, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="timestamps, or the frame rate"):
        ResultSmoother()(fake_result(R[:, 0], t[:, 0], e[:, 0], ok))
    with pytest.raises(ValueError, match="select"):
        by_fps(fake_result(R[:2, 0], t[:2, 0], e[:2, 0], ok[:2]))
    alone = ResultSmoother(fps=FPS)
    for k in range(T):
        alone(fake_result(R[2:, k], t[2:, k], e[2:, k], ok[2:]))
    by_fps.select([2])
    a = by_fps(fake_result(R[2:, 0], t[2:, 0], e[2:, 0], ok[2:]))
    b = alone(fake_result(R[2:, 0], t[2:, 0], e[2:, 0], ok[2:]))
    torch.testing.assert_close(a.rotation, b.rotation, rtol=0, atol=1e-15)
    forked = copy.deepcopy(by_fps)
    again = pickle.loads(pickle.dumps(by_fps))
    x = fake_result(R[2:, 1], t[2:, 1], e[2:, 1], ok[2:])
    assert torch.equal(forked(x).rotation, again(x).rotation)
    by_fps.reset()
    assert by_fps.state is None and torch.equal(by_fps(x).rotation, x.rotation)  # afresh: the raw rotation
    by_fps(x)
    assert by_fps.select([]).state.time.shape == (0,) and by_fps._frames.shape == (0,)  # (an empty list: no stream)


def test_result_smoother_refuses_calls_with_and_without_timestamps_mixed() -> None:
    """A call without ``timestamps`` after calls with them counted its frames from 0 (``n / fps``), so every stream's
    time went back and it restarted without a word (and the other way round jumped from frame counts to a video's
    times). Mixing is a ValueError saying what to do, which leaves the smoother as it was; ``reset()`` switches."""
    B, T = 2, 4
    R = random_rotations(B, T, seed=21)
    t = torch.zeros(B, T, 3, dtype=D)
    e = torch.zeros(B, T, 11, dtype=D)
    ok = torch.ones(B, dtype=torch.bool)
    stamps = 10.0 + torch.arange(T, dtype=D) / FPS
    timed, counted = ResultSmoother(fps=FPS), ResultSmoother(fps=FPS)
    for k in range(T - 1):
        timed(fake_result(R[:, k], t[:, k], e[:, k], ok), timestamps=stamps[k].expand(B))
        counted(fake_result(R[:, k], t[:, k], e[:, k], ok))
    x = fake_result(R[:, -1], t[:, -1], e[:, -1], ok)
    before = timed.state
    with pytest.raises(ValueError, match=r"calls were made with timestamps, this one without: give them at every call"):
        timed(x)
    with pytest.raises(ValueError, match=r"calls were made without timestamps, this one with: .* or reset\(\)"):
        counted(x, timestamps=stamps[-1].expand(B))
    assert timed.state is before
    smooth = timed(x, timestamps=stamps[-1].expand(B))  # (given again: it goes on)
    assert not torch.equal(smooth.rotation, x.rotation)  # (filtered, not restarted)
    counted.reset()
    assert torch.equal(counted(x, timestamps=stamps[-1].expand(B)).rotation, x.rotation)  # afresh, now timed


def test_times_are_checked_under_the_name_they_were_given() -> None:
    """``ResultSmoother``'s ``timestamps`` of the wrong shape were refused as ``time`` (``smooth_result``'s name for
    them), a scalar without saying one per stream is needed; bool times, at any of the three entry points, were
    taken as 0 and 1 seconds."""
    R = random_rotations(2, 2, seed=14)
    t = torch.zeros(2, 2, 3, dtype=D)
    e = torch.zeros(2, 2, 11, dtype=D)
    ok = torch.ones(2, dtype=torch.bool)
    first = fake_result(R[:, 0], t[:, 0], e[:, 0], ok)
    with pytest.raises(ValueError, match=r"timestamps must be a \(2,\) tensor of seconds, got shape \(\): one per "
                                         r"stream, torch.full\(\(2,\), t\)"):  # fmt: skip
        ResultSmoother()(first, timestamps=0.04)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"timestamps must be a \(2,\) tensor of seconds, got shape \(2, 1\)$"):
        ResultSmoother()(first, timestamps=torch.zeros(2, 1))
    with pytest.raises(TypeError, match="timestamps must be real seconds, a \\(2,\\) tensor, got a torch.bool tensor"):
        ResultSmoother()(first, timestamps=torch.tensor([False, True]))
    with pytest.raises(TypeError, match="time must be real seconds"):
        smooth_result(first, None, torch.tensor([False, True]), SmoothingConfig())
    with pytest.raises(TypeError, match="time must be real seconds"):
        smooth_pose_series(R, t, ok[:, None].expand(2, 2), torch.ones(2, 2, dtype=torch.bool), SmoothingConfig())
    with pytest.raises(ValueError, match=r"time must be a \(2,\) tensor of seconds"):
        smooth_result(first, None, torch.zeros(3), SmoothingConfig())
    for step in (one_euro_step, one_euro_rotation_step):  # the functional filters' time steps alike
        x = R[:, 0] if step is one_euro_rotation_step else t[:, 0]
        with pytest.raises(TypeError, match="dt must be real seconds, a number or a \\(2,\\) tensor, got a torch.bool"):
            step(x, None, torch.tensor([True, True]), OneEuroConfig())
    # real seconds of any real dtype, and a list, are taken as before
    a = ResultSmoother()(first, timestamps=torch.tensor([0, 1]))
    b = ResultSmoother()(first, timestamps=[0.0, 1.0])
    assert torch.equal(a.rotation, b.rotation) and torch.equal(a.rotation, first.rotation)


def test_result_smoother_select_checks_its_index_as_the_tracker_does() -> None:
    """``ResultSmoother.select`` (and ``SmoothingState.select``) take stream indices as ``FaceTracker.select`` does:
    a 0-d index kept the stream without its batch dimension (the next call failed with "tuple index out of range"
    where the tracker's own select kept a batch of one), a uint8 mask was taken as a mask where the tracker took it for
    indices, and an index out of range, a mask of another length, None or a slice were torch's errors. A bad index
    leaves the smoother as it was."""
    B, T = 3, 3
    R = random_rotations(B, T, seed=15)
    t = torch.zeros(B, T, 3, dtype=D)
    e = torch.zeros(B, T, 11, dtype=D)
    ok = torch.ones(B, dtype=torch.bool)
    smoother, alone = ResultSmoother(fps=FPS), ResultSmoother(fps=FPS)
    for k in range(T - 1):
        smoother(fake_result(R[:, k], t[:, k], e[:, k], ok))
        alone(fake_result(R[1:2, k], t[1:2, k], e[1:2, k], ok[1:2]))
    before = smoother.state
    for bad, error, match in (
        ([3], IndexError, "out of range for 3 streams"),
        (torch.tensor([True, False]), IndexError, "must have 3 values"),
        (None, TypeError, "index must be stream indices"), (slice(0, 1), TypeError, "index must be stream indices"),
        (torch.tensor([0, 1, 0], dtype=torch.uint8), TypeError, "uint8"),
    ):  # fmt: skip
        with pytest.raises(error, match=match):
            smoother.select(bad)  # type: ignore[arg-type]
        with pytest.raises(error, match=match):
            before.select(bad)  # type: ignore[arg-type]
    assert smoother.state is before and smoother._frames.shape == (3,)
    assert before.select(torch.tensor(1)).time.shape == (1,)
    smoother.select(torch.tensor(1))  # a 0-d index: a batch of one, as FaceTracker.select keeps it
    assert smoother.state.time.shape == (1,) and smoother._frames.shape == (1,)
    x = fake_result(R[1:2, -1], t[1:2, -1], e[1:2, -1], ok[1:2])
    assert torch.equal(smoother(x).rotation, alone(x).rotation)


def test_smooth_result_restart_and_checks() -> None:
    R = random_rotations(2, 2, seed=13)
    t = torch.zeros(2, 2, 3, dtype=D)
    e = torch.zeros(2, 2, 11, dtype=D)
    ok = torch.ones(2, dtype=torch.bool)
    _, state = smooth_result(fake_result(R[:, 0], t[:, 0], e[:, 0], ok), None, torch.zeros(2), SmoothingConfig())
    out, _ = smooth_result(fake_result(R[:, 1], t[:, 1], e[:, 1], ok), state, torch.full((2,), DT),
                           SmoothingConfig(), restart=torch.tensor([True, False]))  # fmt: skip
    assert torch.equal(out.rotation[0], R[0, 1]) and not torch.equal(out.rotation[1], R[1, 1])
    with pytest.raises(ValueError, match="facs_matrix"):
        smooth_result(fake_result(R[:, 0], t[:, 0], e[:, 0], ok), None, torch.zeros(2),
                      SmoothingConfig(expression=OneEuroConfig()))  # fmt: skip
    with pytest.raises(TypeError, match="TrackResult"):
        smooth_result(R, None, torch.zeros(2), SmoothingConfig())  # type: ignore[arg-type]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_on_cuda_as_on_the_cpu() -> None:
    R = random_rotations(2, 20, seed=14)
    cfg = OneEuroConfig(min_cutoff=0.8, beta=1.0)
    cpu = run_rotation(R, cfg)
    gpu = run_rotation(R.cuda(), cfg)
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=0, atol=1e-12)


def test_a_smoother_leaves_the_tracker_as_it_is() -> None:
    """Off is the code without it: tracking a small rendered clip with a smoother reading every result gives the
    tracker's results (and state) bit for bit as tracking without one, and the smoothed pose differs from them.
    Given the tracker's state, the stream the online start re-anchors starts afresh at its first re-anchored result
    (the frame after the re-anchoring one); the other (a still head) goes on as without the state."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from _helpers import sideways_clip

    from torchface.tracker import FaceTracker, FitConfig, LookaheadConfig, TrackerConfig

    frames, landmarks, _ = sideways_clip(320, 240, n=6)
    frames = torch.stack([frames, frames[:1].expand_as(frames)], 1)  # (T, 2, 3, H, W): turning, still
    lm = torch.stack([landmarks, landmarks])
    config = TrackerConfig(num_levels=2, max_points=400, iterations=(4, 3), fit=FitConfig(held_shape_units=()))
    fields = ("rotation", "axis_angle", "translation", "ypr_deg", "anim_coeffs", "expression", "confidence", "status")

    def track(smoother: ResultSmoother | None):
        tracker = FaceTracker(config, refine_first=LookaheadConfig(yaw_deg=5.0))
        raw, smooth, offsets = [tracker.initialise(frames[0], lm)], [], []
        for k in range(1, frames.shape[0]):
            raw.append(tracker(frames[k]))
            ms = tracker.state.management
            offsets.append(None if ms.head_rotation is None else ms.head_rotation.clone())
            if smoother is not None:  # (online, given the tracker's state, as a user calls it)
                smooth.append(smoother(raw[-1], tracker_state=tracker.state))
        return raw, smooth, offsets, tracker

    base, _, _, tracker = track(None)
    raw, smooth, offsets, tracker_s = track(ResultSmoother(fps=FPS, model=load_candide3()))
    for a, b in zip(base, raw):
        for name in fields:
            assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert torch.equal(tracker.state.params, tracker_s.state.params)
    assert bool(torch.stack([r.success for r in raw]).all())
    assert torch.equal(smooth[0].rotation, raw[1].rotation)  # the first frame the smoother sees: raw
    assert not torch.equal(smooth[-1].rotation[0], raw[-1].rotation[0])
    # the re-anchoring of stream 0 (at 5 degrees of yaw)
    eye = torch.eye(3)
    at = next(k for k, D in enumerate(offsets) if D is not None and not torch.equal(D[0], eye))
    assert torch.equal(offsets[at][1], eye)  # (the still stream: not re-anchored)
    plain = ResultSmoother(fps=FPS)
    without = [plain(r) for r in raw[1:]]
    # managed_step reports the re-anchoring frame (raw[at + 1]) at the estimate tracked before it, and the refined,
    # re-anchored estimate from the next frame on (here a step of ~18 degrees): afresh at that next result, as
    # torchface track --smooth starts after the re-anchoring frame, not at the frame itself (which smeared the step)
    assert at + 1 < len(smooth)
    assert torch.equal(smooth[at + 1].rotation[0], raw[at + 2].rotation[0])
    assert torch.equal(smooth[at + 1].translation[0], raw[at + 2].translation[0])
    assert not torch.equal(smooth[at].rotation[0], raw[at + 1].rotation[0])  # (the re-anchoring frame: filtered)
    assert not torch.equal(without[at + 1].rotation[0], raw[at + 2].rotation[0])
    for a, b in zip(smooth, without):  # the still stream as without the state
        assert torch.equal(a.rotation[1], b.rotation[1]) and torch.equal(a.translation[1], b.translation[1])
    with pytest.raises(TypeError, match="tracker_state"):
        ResultSmoother(fps=FPS)(raw[-1], tracker_state=tracker.state.management)  # type: ignore[arg-type]


def test_docs_smoothing_block_runs_as_written() -> None:
    """docs/python-api.md's "Smoothing the outputs" block, its placeholders a small rendered clip (one stream): the
    smoothed result is a TrackResult whose pose differs from the tracker's raw one, and the first one is raw."""
    import re
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    sys.path.insert(0, str(root / "tests"))
    from _helpers import sideways_clip

    text = (root / "docs" / "python-api.md").read_text(encoding="utf-8")
    section = text.split("## Smoothing the outputs\n", 1)[1].split("\n## ", 1)[0]
    (code,) = re.findall(r"^```python\n(.*?)^```", section, flags=re.S | re.M)
    frames, landmarks, _ = sideways_clip(320, 240, n=4)
    scope = {"frames0": frames[:1], "landmarks0": landmarks[None], "later_frames": [f[None] for f in frames[1:]]}
    exec(compile(code, "docs/python-api.md", "exec"), scope)  # noqa: S102 (the docs' own block)
    smooth, raw = scope["smooth"], scope["raw"]
    assert isinstance(smooth, TrackResult) and smooth.rotation.shape == (1, 3, 3)
    assert not torch.equal(smooth.rotation, raw.rotation) and not torch.equal(smooth.translation, raw.translation)


def test_offline_series_restarts_where_the_online_smoother_does() -> None:
    """smooth_pose_series given the frames whose step re-anchored a stream (reanchored_streams after each step, what
    ResultSmoother reads from tracker_state) smooths a tracked pose series as the online smoother did, bit for bit,
    on a small rendered clip (two streams: one turning, which the online start re-anchors, one still); without them
    (the offline path of scripts/evaluate.py --smoothing before) it smears the re-anchored estimate's step."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from _helpers import sideways_clip

    from torchface.tracker import FaceTracker, FitConfig, LookaheadConfig, TrackerConfig, reanchored_streams

    frames, landmarks, _ = sideways_clip(320, 240, n=6)
    frames = torch.stack([frames, frames[:1].expand_as(frames)], 1)  # (T, 2, 3, H, W): turning, still
    config = TrackerConfig(num_levels=2, max_points=400, iterations=(4, 3), fit=FitConfig(held_shape_units=()))
    tracker = FaceTracker(config, refine_first=LookaheadConfig(yaw_deg=5.0))
    smoother = ResultSmoother(fps=FPS)
    raw = [tracker.initialise(frames[0], torch.stack([landmarks, landmarks]))]
    smooth = [smoother(raw[0], tracker_state=tracker.state)]
    flags, offsets = [], None
    for k in range(frames.shape[0]):
        if k:
            raw.append(tracker(frames[k]))
            smooth.append(smoother(raw[-1], tracker_state=tracker.state))
        changed, offsets = reanchored_streams(tracker.state, offsets)
        flags.append(changed)
    reanchored = torch.stack(flags, 1)  # (B, T)
    assert reanchored[0].sum() == 1 and not reanchored[1].any()  # (the turning stream re-anchors once, mid-clip)
    at = int(reanchored[0].nonzero()[0, 0])
    assert 0 < at < len(raw) - 1
    R = torch.stack([r.rotation for r in raw], 1)
    t = torch.stack([r.translation for r in raw], 1)
    ok = torch.stack([r.success for r in raw], 1)
    time = torch.arange(len(raw), dtype=D).expand(2, -1) / FPS
    R_s, t_s = smooth_pose_series(R, t, ok, time, SmoothingConfig(), reanchored=reanchored)
    assert torch.equal(R_s, torch.stack([s.rotation for s in smooth], 1))
    assert torch.equal(t_s, torch.stack([s.translation for s in smooth], 1))
    assert torch.equal(R_s[0, at + 1], R[0, at + 1])  # afresh at the first re-anchored estimate
    R_old, _ = smooth_pose_series(R, t, ok, time, SmoothingConfig())
    assert not torch.equal(R_old[0, at + 1], R[0, at + 1])
    assert torch.equal(R_old[1], R_s[1])  # (the still stream: as without the flags)
    # the same as restart= one frame later; the masks are checked as the other series
    after = torch.zeros_like(reanchored)
    after[:, 1:] = reanchored[:, :-1]
    assert torch.equal(smooth_pose_series(R, t, ok, time, SmoothingConfig(), restart=after)[0], R_s)
    with pytest.raises(ValueError, match="reanchored must be"):
        smooth_pose_series(R, t, ok, time, SmoothingConfig(), reanchored=reanchored[:, 1:])
    with pytest.raises(ValueError, match="bool"):
        smooth_pose_series(R, t, ok, time, SmoothingConfig(), reanchored=reanchored.float())
    with pytest.raises(TypeError, match="tracker_state"):
        reanchored_streams(tracker.state.management, None)  # type: ignore[arg-type]
