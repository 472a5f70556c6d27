"""Tests for torchface.solver.least_squares: normal equations, GN/LM known answers, status, bounds,
prior, IRLS and gradients through the unrolled solve."""

from __future__ import annotations

import math
import re

import pytest
import torch

from torchface.solver import (
    RobustKind,
    RobustLoss,
    SolverConfig,
    SolverMethod,
    SolveStatus,
    least_squares,
    solve_normal_equations,
)

D = torch.float64
GN = SolverConfig(method=SolverMethod.GAUSS_NEWTON, max_iterations=50)
LM = SolverConfig(method=SolverMethod.LEVENBERG_MARQUARDT, max_iterations=100)
METHODS = [pytest.param(GN, id="gn"), pytest.param(LM, id="lm")]
CONV = int(SolveStatus.CONVERGED)
FAIL = int(SolveStatus.FAILED)


# ------------------------------------------------------------------------------------------------ problems


def exp_problem(y: torch.Tensor, t: torch.Tensor):
    """``r = a exp(b t) + c - y`` with ``x = (a, b, c)``; ``y (B, N)``, ``t (N,)``."""

    def fn(x: torch.Tensor):
        a, b, c = x[:, 0:1], x[:, 1:2], x[:, 2:3]
        e = torch.exp(b * t)
        r = a * e + c - y
        J = torch.stack([e, a * t * e, torch.ones_like(e)], dim=2)
        return r, J, None

    return fn


def similarity_residual(src: torch.Tensor, dst: torch.Tensor):
    """2D similarity ``dst = exp(k) R(theta) src + t``; ``x = (k, theta, tx, ty)``; points ``(B, N, 2)``.

    Residuals are the interleaved x/y differences ``(B, 2N)``.
    """

    def fn(x: torch.Tensor):
        k, th, tx, ty = x.unbind(1)
        s = torch.exp(k)[:, None]
        c, sn = torch.cos(th)[:, None], torch.sin(th)[:, None]
        px, py = src[..., 0], src[..., 1]
        qx = s * (c * px - sn * py) + tx[:, None]
        qy = s * (sn * px + c * py) + ty[:, None]
        r = torch.stack([qx - dst[..., 0], qy - dst[..., 1]], dim=2).flatten(1)
        one, zero = torch.ones_like(px), torch.zeros_like(px)
        Jx = torch.stack([qx - tx[:, None], -(qy - ty[:, None]), one, zero], dim=2)
        Jy = torch.stack([qy - ty[:, None], qx - tx[:, None], zero, one], dim=2)
        J = torch.stack([Jx, Jy], dim=2).flatten(1, 2)
        return r, J, None

    return fn


def make_exp_data(B: int, N: int = 30, noise: float = 0.0, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0.0, 2.0, N, dtype=D)
    x_true = torch.stack(
        [
            1.0 + 2.0 * torch.rand(B, generator=g, dtype=D),
            -1.5 + torch.rand(B, generator=g, dtype=D),
            -0.5 + torch.rand(B, generator=g, dtype=D),
        ],
        dim=1,
    )
    y = x_true[:, 0:1] * torch.exp(x_true[:, 1:2] * t) + x_true[:, 2:3]
    y = y + noise * torch.randn(B, N, generator=g, dtype=D)
    return t, y, x_true


# ------------------------------------------------------------------------------------------------ normal equations


def test_solve_normal_equations_matches_dense_solve() -> None:
    g = torch.Generator().manual_seed(0)
    B, N, P = 4, 30, 5
    J = torch.randn(B, N, P, generator=g, dtype=D)
    r = torch.randn(B, N, generator=g, dtype=D)
    w = torch.rand(B, N, generator=g, dtype=D)
    lam = torch.rand(P, generator=g, dtype=D)
    off = torch.randn(B, P, generator=g, dtype=D)
    mu = torch.tensor([0.0, 0.1, 1.0, 10.0], dtype=D)
    H = J.transpose(1, 2) @ (w[..., None] * J) + torch.diag(lam)
    gr = (J.transpose(1, 2) @ (w * r)[..., None]).squeeze(2) + lam * off
    Hd = H + mu[:, None, None] * torch.diag_embed(torch.diagonal(H, dim1=1, dim2=2))
    ref = -torch.linalg.solve(Hd, gr)
    delta, ok = solve_normal_equations(J, r, w, mu, lam, prior_offset=off)
    assert ok.all()
    torch.testing.assert_close(delta, ref, rtol=1e-10, atol=1e-12)
    # Levenberg (identity) damping
    ref_i = -torch.linalg.solve(H + mu[:, None, None] * torch.eye(P, dtype=D), gr)
    delta_i, _ = solve_normal_equations(J, r, w, mu, lam, prior_offset=off, marquardt_scaling=False)
    torch.testing.assert_close(delta_i, ref_i, rtol=1e-10, atol=1e-12)


def test_solve_normal_equations_bad_samples_are_isolated() -> None:
    g = torch.Generator().manual_seed(1)
    B, N, P = 5, 20, 3
    J = torch.randn(B, N, P, generator=g, dtype=D)
    r = torch.randn(B, N, generator=g, dtype=D)
    J[1, 3, 2] = float("nan")
    r[2, 0] = float("inf")
    J[3, :, 1] = J[3, :, 0]  # duplicate columns: singular
    J[4, :, 2] = 0.0  # zero column: singular
    delta, ok = solve_normal_equations(J, r)
    assert ok.tolist() == [True, False, False, False, False]
    assert torch.isfinite(delta).all()
    assert torch.all(delta[1:] == 0)
    ref = -torch.linalg.lstsq(J[0], r[0]).solution
    torch.testing.assert_close(delta[0], ref, rtol=1e-10, atol=1e-12)
    # With Marquardt damping the zero column is harmless (its step is 0).
    delta_d, ok_d = solve_normal_equations(J, r, damping=torch.full((B,), 1e-3, dtype=D))
    assert ok_d[4] and delta_d[4, 2] == 0


def test_solve_normal_equations_exceptions() -> None:
    J = torch.randn(2, 6, 3)
    with pytest.raises(ValueError):
        solve_normal_equations(J[0], torch.randn(6))
    with pytest.raises(ValueError):
        solve_normal_equations(J, torch.randn(2, 5))
    with pytest.raises(ValueError):
        solve_normal_equations(J, torch.randn(2, 6), torch.ones(2, 6, dtype=D))
    with pytest.raises(ValueError):
        solve_normal_equations(J, torch.randn(2, 6), prior=torch.ones(4))
    with pytest.raises(TypeError):
        solve_normal_equations(J, [0.0] * 6)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------------ config


def test_config_validation() -> None:
    with pytest.raises(TypeError):
        SolverConfig(method="lm")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        SolverConfig(max_iterations=-1)
    with pytest.raises(TypeError):
        SolverConfig(max_iterations=2.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        SolverConfig(initial_damping=0.0)
    with pytest.raises(ValueError):
        SolverConfig(damping_increase_factor=1.0)
    with pytest.raises(ValueError):
        SolverConfig(step_tolerance=-1.0)


def test_least_squares_input_validation() -> None:
    t, y, _ = make_exp_data(2)
    fn = exp_problem(y, t)
    x0 = torch.zeros(2, 3, dtype=D)
    with pytest.raises(ValueError):
        least_squares(fn, x0[0])
    with pytest.raises(ValueError):
        least_squares(fn, x0.float())  # residuals are float64, x0 float32
    with pytest.raises(ValueError):
        least_squares(fn, x0, lower=torch.zeros(4, dtype=D))
    with pytest.raises(ValueError):
        least_squares(fn, x0, lower=torch.ones(3, dtype=D), upper=torch.zeros(3, dtype=D))
    with pytest.raises(ValueError):
        least_squares(fn, x0, prior_mean=torch.zeros(3, dtype=D))
    with pytest.raises(ValueError):
        least_squares(fn, x0, prior_precision=-torch.ones(3, dtype=D))
    with pytest.raises(TypeError):
        least_squares(fn, x0, robust=RobustKind.HUBER)  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        least_squares(fn, x0, config={"method": "lm"})  # type: ignore[arg-type]

    def wrong_j(x: torch.Tensor):
        r, J, _ = fn(x)
        return r, J[:, :, :2], None

    with pytest.raises(ValueError):
        least_squares(wrong_j, x0)


# ------------------------------------------------------------------------------------------------ known answers


@pytest.mark.parametrize("config", METHODS)
def test_exponential_exact_recovery(config: SolverConfig) -> None:
    t, y, x_true = make_exp_data(B=6)
    if config.method is SolverMethod.LEVENBERG_MARQUARDT:
        x0 = torch.tensor([[1.0, -0.5, 0.0]], dtype=D).repeat(6, 1)
    else:  # undamped Gauss-Newton needs a start near the answer on this problem
        x0 = x_true + torch.tensor([0.3, 0.2, -0.2], dtype=D)
    res = least_squares(exp_problem(y, t), x0, config)
    assert res.status.tolist() == [CONV] * 6
    torch.testing.assert_close(res.params, x_true, rtol=0, atol=1e-8)
    assert torch.all(res.cost < 1e-20)
    assert torch.all(res.initial_cost > 1e-2)
    assert res.iterations.dtype == torch.int64 and res.status.dtype == torch.int64
    assert torch.all(res.iterations > 0) and torch.all(res.iterations < config.max_iterations)


@pytest.mark.parametrize("config", METHODS)
def test_similarity_alignment_exact_recovery(config: SolverConfig) -> None:
    g = torch.Generator().manual_seed(3)
    B, N = 5, 12
    src = torch.randn(B, N, 2, generator=g, dtype=D) * 50
    x_true = torch.stack(
        [
            0.3 * torch.randn(B, generator=g, dtype=D),
            torch.linspace(-1.2, 1.2, B, dtype=D),  # up to 69 degrees
            10 * torch.randn(B, generator=g, dtype=D),
            10 * torch.randn(B, generator=g, dtype=D),
        ],
        dim=1,
    )
    s = torch.exp(x_true[:, 0])[:, None, None]
    c, sn = torch.cos(x_true[:, 1]), torch.sin(x_true[:, 1])
    R = torch.stack([torch.stack([c, -sn], 1), torch.stack([sn, c], 1)], 1)
    dst = s * src @ R.transpose(1, 2) + x_true[:, None, 2:]
    res = least_squares(similarity_residual(src, dst), torch.zeros(B, 4, dtype=D), config)
    assert res.status.tolist() == [CONV] * B
    torch.testing.assert_close(res.params, x_true, rtol=0, atol=1e-8)


@pytest.mark.parametrize("config", METHODS)
def test_noisy_matches_scipy(config: SolverConfig) -> None:
    scipy_opt = pytest.importorskip("scipy.optimize")
    t, y, x_true = make_exp_data(B=3, N=40, noise=0.05, seed=7)
    x0 = torch.tensor([1.0, -0.5, 0.0], dtype=D).repeat(3, 1)
    tight = SolverConfig(method=config.method, step_tolerance=1e-14, cost_tolerance=1e-15)
    res = least_squares(exp_problem(y, t), x0, tight)
    assert res.status.tolist() == [CONV] * 3
    for b in range(3):
        tb, yb = t.numpy(), y[b].numpy()

        def f(p, tb=tb, yb=yb):
            return p[0] * torch.exp(torch.as_tensor(p[1] * tb)).numpy() + p[2] - yb

        ref = scipy_opt.least_squares(f, x0[b].numpy(), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        torch.testing.assert_close(res.params[b], torch.as_tensor(ref.x), rtol=0, atol=1e-7)
        assert res.cost[b].item() == pytest.approx(ref.cost, rel=1e-9)  # scipy: 0.5 * sum r^2
    assert (res.params - x_true).abs().max() > 1e-4  # noise moved the optimum


@pytest.mark.parametrize("config", METHODS)
def test_batch_invariance(config: SolverConfig) -> None:
    t, y, _ = make_exp_data(B=5, noise=0.01, seed=11)
    x0 = torch.tensor(
        [[1.0, -0.5, 0.0], [2.0, -1.0, 0.0], [0.5, -0.2, 1.0], [1.5, -0.5, -0.2], [3.0, -2.0, 0.5]], dtype=D
    )
    fn = exp_problem(y, t)
    res = least_squares(fn, x0, config)
    assert len(set(res.iterations.tolist())) > 1  # samples really stopped at different times
    for b in range(5):
        one = least_squares(exp_problem(y[b : b + 1], t), x0[b : b + 1], config)
        torch.testing.assert_close(res.params[b : b + 1], one.params, rtol=0, atol=1e-12)
        torch.testing.assert_close(res.cost[b : b + 1], one.cost, rtol=1e-10, atol=1e-14)
        assert res.iterations[b] == one.iterations[0]
        assert res.status[b] == one.status[0]


def test_max_iterations_status() -> None:
    t, y, _ = make_exp_data(B=2)
    res = least_squares(exp_problem(y, t), torch.zeros(2, 3, dtype=D) + 1.0, SolverConfig(max_iterations=2))
    assert res.status.tolist() == [int(SolveStatus.MAX_ITERATIONS)] * 2
    assert res.iterations.tolist() == [2, 2]
    assert torch.all(res.cost < res.initial_cost)
    zero = least_squares(exp_problem(y, t), torch.ones(2, 3, dtype=D), SolverConfig(max_iterations=0))
    torch.testing.assert_close(zero.params, torch.ones(2, 3, dtype=D))
    torch.testing.assert_close(zero.cost, zero.initial_cost)


def test_reported_cost_is_half_sum_of_squares() -> None:
    t, y, _ = make_exp_data(B=2, noise=0.1)
    fn = exp_problem(y, t)
    res = least_squares(fn, torch.ones(2, 3, dtype=D), LM)
    r, _, _ = fn(res.params)
    torch.testing.assert_close(res.cost, 0.5 * (r * r).sum(1))
    r0, _, _ = fn(torch.ones(2, 3, dtype=D))
    torch.testing.assert_close(res.initial_cost, 0.5 * (r0 * r0).sum(1))


# ------------------------------------------------------------------------------------------------ failures


@pytest.mark.parametrize("config", METHODS)
def test_failed_samples_are_isolated(config: SolverConfig) -> None:
    t, y, x_true = make_exp_data(B=4)
    y = y.clone()
    y[1, 4] = float("nan")  # NaN residual at a valid entry
    valid = torch.ones(4, t.shape[0], dtype=torch.bool)
    valid[2] = False  # no valid residual at all
    valid[3, 2:] = False  # 2 valid residuals < P = 3
    y[3, 5] = float("nan")  # garbage at an invalid entry must not matter

    base = exp_problem(y, t)

    def fn(x: torch.Tensor):
        r, J, _ = base(x)
        return r, J, valid

    x0 = torch.tensor([1.0, -0.5, 0.0], dtype=D).repeat(4, 1)
    res = least_squares(fn, x0, config)
    assert res.status.tolist() == [CONV, FAIL, FAIL, FAIL]
    assert torch.isfinite(res.params).all() and torch.isfinite(res.cost).all()
    torch.testing.assert_close(res.params[0], x_true[0], rtol=0, atol=1e-8)
    torch.testing.assert_close(res.params[1:], x0[1:])
    assert res.iterations[1:].tolist() == [0, 0, 0]


def test_singular_sample_fails_with_gauss_newton() -> None:
    # Sample 1 has duplicate Jacobian columns (y = a t + b t): GN cannot solve it.
    t = torch.linspace(0, 1, 10, dtype=D)
    y = torch.stack([2 * t + 1, 3 * t], 0)

    def fn(x: torch.Tensor):
        r = x[:, 0:1] * t + x[:, 1:2] - y
        J = torch.stack([t.expand(2, -1), torch.ones(2, 10, dtype=D)], 2)
        J = torch.cat([J[:1], t[None, :, None].expand(1, 10, 2)], 0)
        r = torch.cat([r[:1], ((x[1:, 0:1] + x[1:, 1:2]) * t - y[1:])], 0)
        return r, J, None

    res = least_squares(fn, torch.zeros(2, 2, dtype=D), GN)
    assert res.status.tolist() == [CONV, FAIL]
    torch.testing.assert_close(res.params[0], torch.tensor([2.0, 1.0], dtype=D))
    assert torch.all(res.params[1] == 0)
    # LM regularises the same problem: a minimiser (a + b = 3) is found, nothing is NaN.
    res_lm = least_squares(fn, torch.zeros(2, 2, dtype=D), LM)
    assert torch.isfinite(res_lm.params).all()
    assert res_lm.params[1].sum().item() == pytest.approx(3.0, abs=1e-8)


@pytest.mark.parametrize("config", METHODS)
def test_nan_region_midway(config: SolverConfig) -> None:
    """Residuals are NaN for b > -0.2: LM steps around it, GN stops FAILED at its last good x."""
    t, y, x_true = make_exp_data(B=3)
    base = exp_problem(y, t)

    def fn(x: torch.Tensor):
        r, J, v = base(x)
        bad = (x[:, 1] > -0.2)[:, None]
        return torch.where(bad, torch.full_like(r, float("nan")), r), J, v

    x0 = torch.tensor([[1.0, -0.3, 3.0]], dtype=D).repeat(3, 1)
    res = least_squares(fn, x0, config)
    assert torch.isfinite(res.params).all() and torch.isfinite(res.cost).all()
    assert torch.all(res.params[:, 1] <= -0.2)
    if config.method is SolverMethod.LEVENBERG_MARQUARDT:
        assert res.status.tolist() == [CONV] * 3
        torch.testing.assert_close(res.params, x_true, rtol=0, atol=1e-8)
    else:
        done = res.status == CONV
        assert torch.all(done | (res.status == FAIL))
        torch.testing.assert_close(res.params[done], x_true[done], rtol=0, atol=1e-8)


# ------------------------------------------------------------------------------------------------ bounds and prior


@pytest.mark.parametrize("config", METHODS)
def test_box_bounds_active_at_constrained_optimum(config: SolverConfig) -> None:
    g = torch.Generator().manual_seed(5)
    t = torch.linspace(0, 1, 25, dtype=D)
    y = 2.0 * t + 1.0 + 0.01 * torch.randn(2, 25, generator=g, dtype=D)

    def fn(x: torch.Tensor):
        r = x[:, 0:1] * t + x[:, 1:2] - y
        J = torch.stack([t.expand(2, -1), torch.ones(2, 25, dtype=D)], 2)
        return r, J, None

    # Sample 0: slope <= 1.5 cuts the free optimum; sample 1: slope >= -10 does not.
    lower = torch.tensor([[-10.0, -10.0], [-10.0, -10.0]], dtype=D)
    upper = torch.tensor([[1.5, 10.0], [10.0, 10.0]], dtype=D)
    x0 = torch.tensor([[5.0, 0.0], [0.0, 0.0]], dtype=D)  # sample 0 starts outside: projected
    res = least_squares(fn, x0, config, lower=lower, upper=upper)
    assert res.status.tolist() == [CONV, CONV]
    assert torch.all(res.params >= lower) and torch.all(res.params <= upper)
    assert res.params[0, 0].item() == 1.5
    c_ref = (y[0] - 1.5 * t).mean()
    assert res.params[0, 1].item() == pytest.approx(c_ref.item(), abs=1e-10)
    free = torch.linalg.lstsq(torch.stack([t, torch.ones_like(t)], 1), y[1]).solution
    torch.testing.assert_close(res.params[1], free, rtol=0, atol=1e-10)


def test_bounds_on_nonlinear_problem() -> None:
    t, y, x_true = make_exp_data(B=2)
    lower = torch.tensor([-math.inf, -math.inf, 0.0], dtype=D)  # c >= 0
    x0 = torch.tensor([1.0, -0.5, 0.5], dtype=D).repeat(2, 1)
    res = least_squares(exp_problem(y, t), x0, LM, lower=lower)
    assert torch.all(res.params[:, 2] >= 0)
    for b in range(2):
        if x_true[b, 2] >= 0:
            torch.testing.assert_close(res.params[b], x_true[b], rtol=0, atol=1e-8)
        else:
            assert res.params[b, 2].item() == 0.0
            assert res.cost[b] > 0


def test_prior_matches_closed_form_and_pulls_toward_mean() -> None:
    g = torch.Generator().manual_seed(2)
    B, N, P = 3, 15, 4
    A = torch.randn(B, N, P, generator=g, dtype=D)
    b = torch.randn(B, N, generator=g, dtype=D)

    def fn(x: torch.Tensor):
        return (A @ x[..., None]).squeeze(2) - b, A, None

    mu = torch.tensor([1.0, -2.0, 0.5, 3.0], dtype=D)
    dist = []
    for scale in (0.0, 1.0, 10.0, 1e3):
        lam = torch.full((B, P), scale, dtype=D)
        res = least_squares(fn, torch.zeros(B, P, dtype=D), GN, prior_precision=lam, prior_mean=mu)
        H = A.transpose(1, 2) @ A + torch.diag_embed(lam)
        ref = torch.linalg.solve(H, (A.transpose(1, 2) @ b[..., None]).squeeze(2) + lam * mu)
        torch.testing.assert_close(res.params, ref, rtol=1e-10, atol=1e-10)
        r = (A @ ref[..., None]).squeeze(2) - b
        torch.testing.assert_close(res.cost, 0.5 * (r * r).sum(1) + 0.5 * (lam * (ref - mu) ** 2).sum(1))
        dist.append((res.params - mu).norm(dim=1))
    dist_t = torch.stack(dist)
    assert torch.all(dist_t[1:] < dist_t[:-1])
    assert torch.all(dist_t[-1] < 0.05 * dist_t[0])


# ------------------------------------------------------------------------------------------------ IRLS


@pytest.mark.parametrize("kind", [RobustKind.HUBER, RobustKind.CAUCHY, RobustKind.TUKEY, RobustKind.GEMAN_MCCLURE])
def test_irls_rejects_gross_outliers(kind: RobustKind) -> None:
    g = torch.Generator().manual_seed(9)
    B, N = 4, 100
    t = torch.linspace(-1, 1, N, dtype=D)
    x_true = torch.tensor([[2.0, 1.0], [-1.0, 0.5], [0.5, -3.0], [3.0, 2.0]], dtype=D)
    y = x_true[:, :1] * t + x_true[:, 1:] + 0.01 * torch.randn(B, N, generator=g, dtype=D)
    out = torch.rand(B, N, generator=g) < 0.3
    y = torch.where(out, y + 5.0 + 10.0 * torch.rand(B, N, generator=g, dtype=D), y)  # one-sided

    def fn(x: torch.Tensor):
        r = x[:, 0:1] * t + x[:, 1:2] - y
        return r, torch.stack([t.expand(B, -1), torch.ones(B, N, dtype=D)], 2), None

    x0 = torch.zeros(B, 2, dtype=D)
    l2 = least_squares(fn, x0, LM)
    rob = least_squares(fn, x0, LM, robust=RobustLoss(kind))
    err_l2 = (l2.params - x_true).abs().amax(1)
    err_rob = (rob.params - x_true).abs().amax(1)
    assert torch.all(err_l2 > 1.0)
    tol = 0.3 if kind is RobustKind.HUBER else 0.02  # Huber is only bounded-influence, not redescending
    assert torch.all(err_rob < tol), err_rob
    assert torch.isfinite(rob.cost).all()


def test_robust_none_equals_plain() -> None:
    t, y, _ = make_exp_data(B=2, noise=0.05)
    a = least_squares(exp_problem(y, t), torch.ones(2, 3, dtype=D), LM)
    b = least_squares(exp_problem(y, t), torch.ones(2, 3, dtype=D), LM, robust=RobustLoss(RobustKind.NONE))
    torch.testing.assert_close(a.params, b.params, rtol=0, atol=0)


# ------------------------------------------------------------------------------------------------ gradients


def test_no_grad_by_default() -> None:
    t, y, _ = make_exp_data(B=1)
    y = y.clone().requires_grad_(True)
    res = least_squares(exp_problem(y, t), torch.ones(1, 3, dtype=D), LM)
    assert not res.params.requires_grad


@pytest.mark.parametrize("method", [SolverMethod.GAUSS_NEWTON, SolverMethod.LEVENBERG_MARQUARDT])
def test_gradcheck_through_unrolled_solve(method: SolverMethod) -> None:
    """d params / d (data, x0) of the unrolled solve equals finite differences (float64)."""
    src = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.5]]], dtype=D).repeat(2, 1, 1)
    th = torch.tensor([0.3, -0.5], dtype=D)
    R = torch.stack([torch.stack([th.cos(), -th.sin()], 1), torch.stack([th.sin(), th.cos()], 1)], 1)
    noise = 0.05 * torch.tensor([[0.3, -1.0], [0.5, 0.2], [-0.7, 0.4], [0.1, 0.9]], dtype=D)
    dst = (1.3 * src @ R.transpose(1, 2) + torch.tensor([0.5, -0.2], dtype=D) + noise).requires_grad_(True)
    cfg = SolverConfig(method=method, max_iterations=6, step_tolerance=0.0, cost_tolerance=0.0, differentiable=True)
    lam = torch.tensor([0.0, 0.1, 0.0, 0.0], dtype=D)

    def solve(dst: torch.Tensor, x0: torch.Tensor) -> torch.Tensor:
        res = least_squares(similarity_residual(src, dst), x0, cfg, prior_precision=lam, robust=RobustLoss(RobustKind.CAUCHY, c=5.0))
        return res.params

    x0 = torch.tensor([[0.1, 0.2, 0.4, 0.0], [0.3, -0.3, 0.5, -0.1]], dtype=D, requires_grad=True)
    assert torch.autograd.gradcheck(solve, (dst, x0), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_differentiable_matches_implicit_gradient() -> None:
    """At convergence the unrolled gradient equals the implicit-function one: dx/dy = (J^T J)^-1 J^T."""
    t, y, x_true = make_exp_data(B=1, noise=0.02, seed=4)
    y = y.clone().requires_grad_(True)
    cfg = SolverConfig(method=SolverMethod.GAUSS_NEWTON, max_iterations=40, step_tolerance=0.0, cost_tolerance=0.0, differentiable=True)
    res = least_squares(exp_problem(y, t), x_true + 0.1, cfg)
    assert res.status.tolist() == [CONV]
    w = torch.tensor([[0.3, -1.0, 2.0]], dtype=D)
    (gy,) = torch.autograd.grad((res.params * w).sum(), y)

    # Implicit function theorem on grad_x f(x, y) = 0 with f = 1/2 |r(x, y)|^2.
    def f(x: torch.Tensor, yy: torch.Tensor) -> torch.Tensor:
        r, _, _ = exp_problem(yy, t)(x)
        return 0.5 * (r * r).sum()

    x_star = res.params.detach()
    hxx, hxy = torch.autograd.functional.hessian(f, (x_star, y.detach()))[0]
    hxx, hxy = hxx.reshape(3, 3), hxy.reshape(3, -1)
    ref = -(w[0] @ torch.linalg.solve(hxx, hxy))[None]
    torch.testing.assert_close(gy, ref, rtol=1e-6, atol=1e-9)


def test_garbage_at_invalid_entries_is_ignored() -> None:
    t, y, x_true = make_exp_data(B=2)
    valid = torch.ones(2, t.shape[0], dtype=torch.bool)
    valid[:, ::3] = False
    base = exp_problem(y, t)

    def fn(x: torch.Tensor):
        r, J, _ = base(x)
        r = torch.where(valid, r, torch.full_like(r, float("nan")))
        J = torch.where(valid[..., None], J, torch.full_like(J, float("inf")))
        return r, J, valid

    x0 = torch.tensor([1.0, -0.5, 0.0], dtype=D).repeat(2, 1)
    res = least_squares(fn, x0, LM, robust=RobustLoss(RobustKind.CAUCHY))
    assert res.status.tolist() == [CONV, CONV]
    torch.testing.assert_close(res.params, x_true, rtol=0, atol=1e-8)


@pytest.mark.parametrize("config", METHODS)
def test_float32(config: SolverConfig) -> None:
    t, y, x_true = make_exp_data(B=4)
    x0 = x_true + torch.tensor([0.3, 0.2, -0.2], dtype=D)
    res = least_squares(exp_problem(y.float(), t.float()), x0.float(), config)
    assert res.params.dtype == torch.float32
    assert res.status.tolist() == [CONV] * 4
    torch.testing.assert_close(res.params.double(), x_true, rtol=0, atol=1e-4)


def test_unrolled_gradients_stay_finite_next_to_a_failed_sample() -> None:
    t, y, _ = make_exp_data(B=3)
    y = y.clone()
    y[1, 3] = float("nan")
    y.requires_grad_(True)
    cfg = SolverConfig(differentiable=True)
    x0 = torch.tensor([1.0, -0.5, 0.0], dtype=D).repeat(3, 1)
    res = least_squares(exp_problem(y, t), x0, cfg, robust=RobustLoss(RobustKind.TUKEY))
    assert res.status.tolist() == [CONV, FAIL, CONV]
    (gy,) = torch.autograd.grad(res.params.sum(), y)
    assert torch.isfinite(gy).all()
    assert torch.all(gy[1] == 0) and torch.all(gy[[0, 2]].abs().sum(1) > 0)


def test_gradients_through_a_singular_sample_are_zero_not_nan() -> None:
    """A sample whose normal equations are singular fails with zero gradients; its neighbours keep theirs."""
    g = torch.Generator().manual_seed(2)
    B, N, P = 3, 12, 3
    J = torch.randn(B, N, P, generator=g, dtype=D)
    J[1, :, 2] = 0.0  # a parameter no residual sees: the factorisation fails (NaN gradients before the fix)
    J.requires_grad_(True)
    r = torch.randn(B, N, generator=g, dtype=D, requires_grad=True)
    delta, ok = solve_normal_equations(J, r)
    assert ok.tolist() == [True, False, True]
    gJ, gr = torch.autograd.grad(delta.sum(), (J, r))
    assert torch.isfinite(gJ).all() and torch.isfinite(gr).all()
    assert torch.all(gJ[1] == 0) and torch.all(gr[1] == 0)
    assert gJ[[0, 2]].abs().sum() > 0 and gr[[0, 2]].abs().sum() > 0


@pytest.mark.parametrize("config", METHODS)
def test_overflowing_cost_is_failed_not_converged(config: SolverConfig) -> None:
    """Finite residuals whose squares overflow (float32 residuals of 1e20): the objective is inf at every
    estimate, no step can be judged, so the sample is FAILED (LM used to stop there as CONVERGED with a cost of
    inf); its neighbour in the batch is solved as alone."""
    g = torch.Generator().manual_seed(5)
    A = torch.randn(2, 8, 2, generator=g)
    y = torch.randn(2, 8, generator=g)
    y[0] = y[0] * 1e20

    def fn(x: torch.Tensor):
        return (A @ x[..., None]).squeeze(2) - y, A, None

    res = least_squares(fn, torch.zeros(2, 2), config)
    alone = least_squares(lambda x: ((A[1:] @ x[..., None]).squeeze(2) - y[1:], A[1:], None), torch.zeros(1, 2), config)
    assert res.status.tolist() == [FAIL, CONV]
    assert bool(torch.isfinite(res.params).all())
    torch.testing.assert_close(res.params[1:], alone.params, rtol=0, atol=0)


def test_min_valid_lets_a_prior_stand_in_for_residuals() -> None:
    """Two residuals and three parameters, one of which has a prior: with ``min_valid=2`` the system is solved
    (to the closed form); by default (``P`` residuals needed) the sample is FAILED at ``x0``."""
    A = torch.tensor([[[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]], dtype=D)
    b = torch.tensor([[1.0, 2.0]], dtype=D)
    lam = torch.tensor([0.0, 0.0, 4.0], dtype=D)

    def fn(x: torch.Tensor):
        return (A @ x[..., None]).squeeze(2) - b, A, None

    x0 = torch.zeros(1, 3, dtype=D)
    assert least_squares(fn, x0, GN, prior_precision=lam).status.tolist() == [FAIL]
    res = least_squares(fn, x0, GN, prior_precision=lam, min_valid=2)
    ref = torch.linalg.solve(A[0].T @ A[0] + torch.diag(lam), A[0].T @ b[0])
    assert res.status.tolist() == [CONV]
    torch.testing.assert_close(res.params[0], ref, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="min_valid"):
        least_squares(fn, x0, GN, prior_precision=lam, min_valid=-1)
    for bad in (1.5, True):  # a wrong type is a TypeError (it was a ValueError)
        with pytest.raises(TypeError, match="min_valid"):
            least_squares(fn, x0, GN, prior_precision=lam, min_valid=bad)


def test_min_valid_per_sample() -> None:
    """A ``(B,)`` ``min_valid``: each sample's own, for per-sample priors (the landmark fit's sparse samples, whose
    raised priors leave fewer parameters to the residuals). The two residuals of the test above solve sample 0,
    which needs 2, and sample 1, which needs 3, is FAILED at ``x0``; sample 0 as alone with ``min_valid=2``."""
    A = torch.tensor([[[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]], dtype=D).expand(2, 2, 3)
    b = torch.tensor([[1.0, 2.0]], dtype=D).expand(2, 2)
    lam = torch.tensor([0.0, 0.0, 4.0], dtype=D)

    def fn(x: torch.Tensor):
        return (A[: x.shape[0]] @ x[..., None]).squeeze(2) - b[: x.shape[0]], A[: x.shape[0]], None

    x0 = torch.zeros(2, 3, dtype=D)
    res = least_squares(fn, x0, GN, prior_precision=lam, min_valid=torch.tensor([2, 3]))
    alone = least_squares(fn, x0[:1], GN, prior_precision=lam, min_valid=2)
    assert res.status.tolist() == [CONV, FAIL]
    torch.testing.assert_close(res.params[:1], alone.params, rtol=0, atol=0)
    assert torch.equal(res.params[1], x0[1])
    with pytest.raises(ValueError, match="min_valid must be >= 0"):
        least_squares(fn, x0, GN, prior_precision=lam, min_valid=torch.tensor([2, -1]))
    for bad in (torch.tensor([2.0, 3.0]), torch.tensor([2]), torch.tensor([True, False])):
        with pytest.raises(TypeError, match=r"min_valid must be an int, a \(2,\) integer tensor or None"):
            least_squares(fn, x0, GN, prior_precision=lam, min_valid=bad)


@pytest.mark.parametrize("config", METHODS)
def test_every_residual_rejected_is_failed(config: SolverConfig) -> None:
    """Sample 1's residuals share an offset of 1000 the model cannot explain, so their spread (the centred robust
    scale) is tiny against them and Tukey's weights are all 0: ``J^T W J = 0``, no information. GN called that
    unsolvable (FAILED) while LM's damping made it a system of denormals whose zero step CONVERGED at ``x0``; both
    say FAILED now, and sample 0 is solved as alone. A zero Jacobian (no prior) is the same case."""
    g = torch.Generator().manual_seed(0)
    A = torch.randn(2, 40, 2, generator=g, dtype=D)
    y = (A @ torch.tensor([1.0, -2.0], dtype=D)[:, None]).squeeze(2) + 0.01 * torch.randn(2, 40, generator=g, dtype=D)
    y[1] += 1000.0

    def fn(x: torch.Tensor):
        return (A @ x[..., None]).squeeze(2) - y, A, None

    tukey = RobustLoss(RobustKind.TUKEY)
    res = least_squares(fn, torch.zeros(2, 2, dtype=D), config, robust=tukey)
    alone = least_squares(lambda x: ((A[:1] @ x[..., None]).squeeze(2) - y[:1], A[:1], None),
                          torch.zeros(1, 2, dtype=D), config, robust=tukey)  # fmt: skip
    assert res.status.tolist() == [CONV, FAIL]
    torch.testing.assert_close(res.params[:1], alone.params, rtol=0, atol=0)
    assert bool(torch.isfinite(res.params).all() & torch.isfinite(res.cost).all())
    zero_j = least_squares(lambda x: (x[:, :1] * 0 + 1.0, torch.zeros(1, 1, 2, dtype=D), None),
                           torch.zeros(1, 2, dtype=D), config, min_valid=1)  # fmt: skip
    assert zero_j.status.tolist() == [FAIL]
    delta, ok = solve_normal_equations(torch.zeros(1, 3, 2, dtype=D), torch.ones(1, 3, dtype=D),
                                       damping=torch.tensor([1e-3], dtype=D))  # fmt: skip
    assert ok.tolist() == [False] and delta.abs().sum() == 0


@pytest.mark.parametrize(
    "lower, upper, named",
    [((math.nan, -5.0), (5.0, 5.0), "lower nan, upper 5.0 for sample 0, parameter 0"),
     ((-5.0, -5.0), (5.0, math.nan), "lower -5.0, upper nan for sample 0, parameter 1"),
     ((math.nan, -5.0), None, "lower nan for sample 0, parameter 0"),
     (None, (5.0, math.nan), "upper nan for sample 0, parameter 1"),
     ((math.inf, -5.0), None, "lower inf for sample 0, parameter 0"),
     (None, (-math.inf, 5.0), "upper -inf for sample 0, parameter 0"),
     ((-5.0, 6.0), (5.0, 5.0), "lower 6.0, upper 5.0 for sample 0, parameter 1")],
)  # fmt: skip
def test_unusable_bounds_are_refused_naming_the_parameter(lower, upper, named) -> None:
    """A NaN bound (or one at the wrong infinity) is refused like crossed bounds, naming the sample and parameter:
    it made its parameter NaN (inf) and the sample FAILED without a word."""

    def fn(x: torch.Tensor):
        return x - torch.tensor([1.0, -2.0], dtype=D), torch.eye(2, dtype=D).expand(x.shape[0], 2, 2), None

    def bound(v):
        return None if v is None else torch.tensor(v, dtype=D)

    with pytest.raises(ValueError, match=re.escape(named)):
        least_squares(fn, torch.zeros(1, 2, dtype=D), lower=bound(lower), upper=bound(upper))
    ok = least_squares(fn, torch.zeros(1, 2, dtype=D), lower=torch.full((2,), -5.0, dtype=D))
    assert ok.params.tolist() == [[1.0, -2.0]]
