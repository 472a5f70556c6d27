"""Tests for torchface.solver.robust: rho, IRLS weights and the batched robust scale."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchface.solver.robust import MAD_TO_SIGMA, RobustKind, RobustLoss, robust_scale

KINDS = [RobustKind.NONE, RobustKind.HUBER, RobustKind.CAUCHY, RobustKind.TUKEY, RobustKind.GEMAN_MCCLURE]


# ------------------------------------------------------------------------------------------------ smoke


def test_l2_is_alias_of_none_and_defaults() -> None:
    assert RobustKind.L2 is RobustKind.NONE
    assert RobustLoss(RobustKind.HUBER).c == pytest.approx(1.345)
    assert RobustLoss(RobustKind.TUKEY).c == pytest.approx(4.6851)
    assert RobustLoss(RobustKind.CAUCHY, c=3).c == 3.0


@pytest.mark.parametrize("kind", KINDS)
def test_cardinality(kind: RobustKind) -> None:
    loss = RobustLoss(kind)
    r = torch.randn(3, 7)
    s = torch.rand(3, 1) + 0.5
    assert loss.rho(r, s).shape == (3, 7)
    assert loss.weight(r, s).shape == (3, 7)
    assert loss.rho(r).dtype == r.dtype


# ------------------------------------------------------------------------------------------------ exceptions


def test_exceptions() -> None:
    with pytest.raises(TypeError):
        RobustLoss("huber")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        RobustLoss(RobustKind.HUBER, c=0.0)
    with pytest.raises(ValueError):
        RobustLoss(RobustKind.HUBER, min_scale=-1.0)
    with pytest.raises(TypeError):
        RobustLoss(RobustKind.HUBER).weight(torch.arange(3))
    with pytest.raises(ValueError):
        robust_scale(torch.randn(5))
    with pytest.raises(ValueError):
        robust_scale(torch.randn(2, 5), torch.ones(2, 5))  # not bool


# ------------------------------------------------------------------------------------------------ features


@pytest.mark.parametrize("kind", KINDS)
def test_weight_at_zero_and_range(kind: RobustKind) -> None:
    loss = RobustLoss(kind)
    r = torch.linspace(-50, 50, 2001, dtype=torch.float64)
    w = loss.weight(r, 1.7)
    assert torch.all(w >= 0) and torch.all(w <= 1)
    assert loss.weight(torch.zeros(1, dtype=torch.float64), 1.7).item() == 1.0
    # w -> 1 as r -> 0
    assert loss.weight(torch.tensor([1e-4], dtype=torch.float64), 1.7).item() == pytest.approx(1.0, abs=1e-7)
    # rho ~ r^2 / 2 near 0, and rho(0) = 0
    assert loss.rho(torch.zeros(1, dtype=torch.float64), 1.7).item() == 0.0
    r_small = torch.tensor([1e-3], dtype=torch.float64)
    assert loss.rho(r_small, 1.7).item() == pytest.approx(0.5e-6, rel=1e-5)


@pytest.mark.parametrize("kind", KINDS)
def test_weight_equals_rho_prime_over_r(kind: RobustKind) -> None:
    loss = RobustLoss(kind)
    r = (torch.linspace(-9, 9, 37, dtype=torch.float64) + 0.013).requires_grad_(True)
    scale = 1.3
    (d,) = torch.autograd.grad(loss.rho(r, scale).sum(), r)
    w = loss.weight(r.detach(), scale)
    torch.testing.assert_close(d / r.detach(), w, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("kind", KINDS)
def test_gradient_safe_at_zero(kind: RobustKind) -> None:
    loss = RobustLoss(kind)
    r = torch.zeros(4, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad((loss.rho(r, 1.0) + loss.weight(r, 1.0)).sum(), r)
    assert torch.isfinite(g).all() and torch.all(g == 0)
    x = torch.tensor([0.0, 0.3, -2.0, 7.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: loss.rho(t, 1.1), (x,))


@pytest.mark.parametrize("kind", list(RobustKind))
def test_rho_and_weight_equal_the_two_methods(kind: RobustKind) -> None:
    """The one-pass pair the IRLS loop uses is exactly ``(rho, weight)`` (same scale, per-sample scales too)."""
    g = torch.Generator().manual_seed(4)
    r = 3.0 * torch.randn(3, 50, generator=g)
    s = 0.5 + torch.rand(3, 1, generator=g)
    loss = RobustLoss(kind)
    rho, w = loss.rho_and_weight(r, s)
    assert torch.equal(rho, loss.rho(r, s)) and torch.equal(w, loss.weight(r, s))


def test_limits() -> None:
    big = torch.tensor([1e6], dtype=torch.float64)
    assert RobustLoss(RobustKind.NONE).weight(big).item() == 1.0
    assert RobustLoss(RobustKind.HUBER, c=2.0).weight(big).item() == pytest.approx(2e-6)
    assert RobustLoss(RobustKind.CAUCHY).weight(big).item() < 1e-10
    assert RobustLoss(RobustKind.GEMAN_MCCLURE).weight(big).item() < 1e-20
    # Huber is linear beyond c: rho = c (|r| - c/2)
    assert RobustLoss(RobustKind.HUBER, c=2.0).rho(big).item() == pytest.approx(2.0 * (1e6 - 1.0))
    # Tukey and Geman-McClure saturate at c^2/6 and c^2/2
    assert RobustLoss(RobustKind.TUKEY, c=3.0).rho(big).item() == pytest.approx(1.5)
    assert RobustLoss(RobustKind.GEMAN_MCCLURE, c=2.0).rho(big).item() == pytest.approx(2.0, rel=1e-9)


def test_tukey_zero_weight_beyond_c() -> None:
    loss = RobustLoss(RobustKind.TUKEY, c=2.0)
    scale = 1.5  # cut-off at c * scale = 3
    r = torch.tensor([-10.0, -3.0, 3.0, 3.01, 100.0, 2.99], dtype=torch.float64)
    w = loss.weight(r, scale)
    assert torch.all(w[:5] == 0)
    assert w[5] > 0
    rho = loss.rho(r, scale)
    torch.testing.assert_close(rho[:5], torch.full((5,), scale**2 * 4.0 / 6.0, dtype=torch.float64))


def test_scale_invariance() -> None:
    # rho(k r; k s) = k^2 rho(r; s), w(k r; k s) = w(r; s)
    r = torch.randn(50, dtype=torch.float64) * 3
    for kind in KINDS:
        loss = RobustLoss(kind)
        torch.testing.assert_close(loss.rho(4 * r, 4 * 0.7), 16 * loss.rho(r, 0.7))
        torch.testing.assert_close(loss.weight(4 * r, 4 * 0.7), loss.weight(r, 0.7))


def test_robust_scale_matches_numpy_mad() -> None:
    g = torch.Generator().manual_seed(0)
    B, N = 6, 41
    r = torch.randn(B, N, generator=g, dtype=torch.float64) * torch.arange(1, B + 1, dtype=torch.float64)[:, None]
    r[:, :5] += 40.0  # outliers
    mask = torch.rand(B, N, generator=g) > 0.3
    mask[1, :] = True  # odd count
    mask[2, :] = torch.arange(N) < 10  # even count
    r[3, 7] = float("nan")  # a NaN where valid is ignored
    r[4, ~mask[4]] = float("inf")  # garbage where invalid is ignored
    for centered in (True, False):
        got = robust_scale(r, mask, centered=centered)
        for b in range(B):
            v = r[b][mask[b]].numpy()
            v = v[np.isfinite(v)]
            ref = MAD_TO_SIGMA * np.median(np.abs(v - np.median(v)) if centered else np.abs(v))
            assert got[b].item() == pytest.approx(ref, rel=1e-12)


def test_robust_scale_gaussian_consistency() -> None:
    g = torch.Generator().manual_seed(1)
    r = 2.5 * torch.randn(2, 200000, generator=g, dtype=torch.float64)
    torch.testing.assert_close(robust_scale(r), torch.full((2,), 2.5, dtype=torch.float64), rtol=0.02, atol=0)


def test_robust_scale_empty_row_fallback() -> None:
    r = torch.tensor([[1.0, 2.0, 3.0], [float("nan"), 5.0, 1.0], [float("nan")] * 3])
    mask = torch.tensor([[False] * 3, [True, False, False], [True] * 3])
    s = robust_scale(r, mask)
    assert torch.isfinite(s).all()
    torch.testing.assert_close(s, torch.ones(3))
    assert robust_scale(torch.zeros(1, 0)).item() == 1.0


def test_switched_loss_gives_each_row_its_loss() -> None:
    from torchface.solver.robust import SwitchedRobustLoss

    tukey, huber = RobustLoss(RobustKind.TUKEY, 4.685), RobustLoss(RobustKind.HUBER, 4.685)
    r = torch.linspace(-9.0, 9.0, 37, dtype=torch.float64).expand(3, -1)
    s = torch.tensor([[1.0], [1.5], [0.5]], dtype=torch.float64)
    loss = SwitchedRobustLoss(tukey, huber, torch.tensor([[True], [False], [True]]))
    rho, w = loss.rho_and_weight(r, s)
    for b, chosen in enumerate((huber, tukey, huber)):
        torch.testing.assert_close(rho[b], chosen.rho(r[b], s[b]), rtol=0, atol=0)
        torch.testing.assert_close(w[b], chosen.weight(r[b], s[b]), rtol=0, atol=0)
    torch.testing.assert_close(loss.rho(r, s), rho, rtol=0, atol=0)
    torch.testing.assert_close(loss.weight(r, s), w, rtol=0, atol=0)
    assert loss.kind is RobustKind.TUKEY and loss.min_scale == tukey.min_scale
    assert float(w[1].min()) == 0.0 and float(w[0].min()) > 0.0  # Tukey rejects the far residuals, Huber keeps them
    with pytest.raises(ValueError, match="switch"):
        SwitchedRobustLoss(tukey, huber, torch.tensor([True, False]))
    with pytest.raises(ValueError, match="switch"):
        SwitchedRobustLoss(tukey, huber, torch.ones(2, 1))
    with pytest.raises(ValueError, match="min_scale"):
        SwitchedRobustLoss(tukey, RobustLoss(RobustKind.HUBER, min_scale=0.1), torch.ones(2, 1, dtype=torch.bool))
    with pytest.raises(TypeError, match="RobustLoss"):
        SwitchedRobustLoss(tukey, RobustKind.HUBER, torch.ones(2, 1, dtype=torch.bool))  # type: ignore[arg-type]


def test_least_squares_with_a_switched_loss_solves_each_row_with_its_loss() -> None:
    """A line fit with one gross outlier: Tukey rejects it, Huber is pulled by it; a switched loss gives each row
    the solution of its own loss."""
    from torchface.solver.least_squares import SolverConfig, least_squares
    from torchface.solver.robust import SwitchedRobustLoss

    x = torch.linspace(0.0, 1.0, 40, dtype=torch.float64)
    y = 2.0 * x + 1.0 + 0.01 * torch.sin(37.0 * x)
    y[5] += 5.0

    def residual_fn(p: torch.Tensor):
        r = p[:, :1] * x + p[:, 1:] - y
        J = torch.stack([x.expand_as(r), torch.ones_like(r)], -1)
        return r, J, torch.ones_like(r, dtype=torch.bool)

    cfg = SolverConfig(max_iterations=50)
    x0 = torch.zeros(2, 2, dtype=torch.float64)
    tukey, huber = RobustLoss(RobustKind.TUKEY, 4.685), RobustLoss(RobustKind.HUBER, 4.685)
    a = least_squares(residual_fn, x0, cfg, robust=tukey).params
    b = least_squares(residual_fn, x0, cfg, robust=huber).params
    assert float((a - b).abs().max()) > 1e-3  # the losses disagree here
    mixed = least_squares(residual_fn, x0, cfg, robust=SwitchedRobustLoss(tukey, huber, torch.tensor([[False], [True]])))
    torch.testing.assert_close(mixed.params[0], a[0], rtol=0, atol=1e-8)
    torch.testing.assert_close(mixed.params[1], b[1], rtol=0, atol=1e-8)


@pytest.mark.parametrize("kind", [RobustKind.CAUCHY, RobustKind.GEMAN_MCCLURE])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rho_stays_finite_far_beyond_the_scale(kind: RobustKind, dtype: torch.dtype) -> None:
    """A residual far beyond the scale (a zero scale is floored at sqrt(tiny)) made (r/s)^2 overflow: Cauchy's rho
    was inf and Geman-McClure's NaN, their gradients too. Both saturate there: finite, and equal to rho at the
    largest |r / s| the dtype squares safely."""
    loss = RobustLoss(kind)
    r = torch.tensor([1e-20, 3.0, -3.0, 1e30], dtype=dtype, requires_grad=True)
    for scale in (0.0, 1e-30):
        rho = loss.rho(r, scale)
        (g,) = torch.autograd.grad(rho.sum(), r)
        assert bool(torch.isfinite(rho).all()) and bool(torch.isfinite(g).all()), (rho, g)
        rho2, w = loss.rho_and_weight(r.detach(), scale)
        torch.testing.assert_close(rho2, rho.detach())
        assert bool(torch.isfinite(w).all())
    # an ordinary residual is untouched
    x = torch.linspace(-5, 5, 11, dtype=dtype)
    c = loss.c
    if kind is RobustKind.CAUCHY:
        expected = 0.5 * c * c * torch.log1p(x * x / (c * c))
    else:
        expected = 0.5 * x * x / (1 + x * x / (c * c))
    torch.testing.assert_close(loss.rho(x, 1.0), expected)


@pytest.mark.parametrize("kind", [RobustKind.HUBER, RobustKind.CAUCHY, RobustKind.TUKEY, RobustKind.GEMAN_MCCLURE])
def test_infinite_constants_are_refused(kind) -> None:
    """An infinite ``c`` or ``min_scale`` was accepted and gave NaN losses or weights (Huber's weight inf / inf, the
    others' loss inf * 0), and ``TrackerConfig(robust_c=...)`` took it (or a negative one, refused only at the first
    tracking step)."""
    from torchface.tracker import TrackerConfig

    with pytest.raises(ValueError, match=r"^c must be a finite number > 0 or None, got inf"):
        RobustLoss(kind, c=float("inf"))
    with pytest.raises(ValueError, match=r"^min_scale must be a finite number > 0, got inf"):
        RobustLoss(kind, min_scale=float("inf"))
    for c in (float("inf"), -1.0):
        with pytest.raises(ValueError, match=r"robust_c must be a finite number > 0 or None"):
            TrackerConfig(robust=kind, robust_c=c)


def test_the_tracker_config_and_the_loss_take_the_same_constants() -> None:
    """``TrackerConfig.robust_c`` and ``RobustLoss.c`` disagreed: a numpy float32 (a ``numbers.Real``) passed the
    config and was refused by the loss at the first frame ("c must be a finite positive number, got
    np.float32(4.685)"), and ``True`` passed the config (a bool is a Real) and was refused by the loss. Now a numpy
    float is taken by both, as the float it is, and a bool by neither."""
    import numpy as np

    from torchface.tracker import TrackerConfig

    c = np.float32(4.685)
    config = TrackerConfig(robust_c=c)
    loss = RobustLoss(config.robust, config.robust_c)
    assert type(loss.c) is float and loss.c == float(c)
    r = torch.linspace(-20.0, 20.0, 41)
    torch.testing.assert_close(loss.weight(r, 1.0), RobustLoss(config.robust, float(c)).weight(r, 1.0), rtol=0, atol=0)
    with pytest.raises(TypeError, match="robust_c must be a real number or None"):  # (was a ValueError)
        TrackerConfig(robust_c=True)
    with pytest.raises(TypeError, match=r"^c must be a real number or None, got bool True"):  # (was a ValueError)
        RobustLoss(RobustKind.TUKEY, c=True)


def test_min_scale_of_another_type_is_a_type_error() -> None:
    """``RobustLoss(min_scale="0.5")`` was taken (``float()`` of the string passed the range check) and failed in
    the solver's ``clamp_min``; a numpy float is kept as a Python float (the settings' rule, docs/python-api.md)."""
    import numpy as np

    for bad in ("0.5", True, None):
        with pytest.raises(TypeError, match="min_scale must be a real number"):
            RobustLoss(RobustKind.HUBER, min_scale=bad)  # type: ignore[arg-type]
    assert type(RobustLoss(RobustKind.HUBER, min_scale=np.float32(0.5)).min_scale) is float
