"""Batched Gauss-Newton / Levenberg-Marquardt least squares with per-sample outcomes.

This is the engine of the per-frame minimisation of Anisetti et al. 2006 (Eq. 12, 13 and 20): pose,
animation units and illumination are found together by forward-additive Gauss-Newton, with robust
IRLS weights against external occlusion (Section 4). ``B`` independent problems are solved at once;
each sample has its own damping, acceptance, iteration count and :class:`SolveStatus`, so one sample
that fails never turns the others into NaN.

Conventions (used throughout this module):

* ``residual_fn(x)`` returns residuals ``r (B, N)`` and their Jacobian ``J = dr/dx (B, N, P)``.
* The objective is ``cost(x) = sum_n rho(r_n(x); s) + 1/2 sum_p lambda_p (x_p - mu_p)**2`` -- a **sum**,
  not a mean -- with ``rho(r; s) = r**2 / 2`` without a robust loss (see :mod:`torchface.solver.robust`)
  and the optional diagonal Gaussian prior of precision ``lambda`` and mean ``mu``.
* One step solves the normal equations of ``1/2 sum_n w_n r_n**2`` (IRLS weights ``w`` held fixed):
  ``H = J^T W J (+ diag(lambda))``, ``g = J^T W r (+ lambda (x - mu))`` and ``delta = -H^{-1} g``
  (Eq. 20: ``Delta = H^{-1} sum SD^T E`` with ``E = -r``). Levenberg-Marquardt adds ``mu_LM D`` to
  ``H``, ``D = diag(H)`` (Marquardt) or ``I`` (Levenberg).

Shape vocabulary: ``B`` batch, ``N`` residuals per sample, ``P`` packed parameters
(see :mod:`torchface.conventions`).
"""

from __future__ import annotations

import contextlib
import enum
import functools
from dataclasses import dataclass
from typing import Callable

import torch

from torchface._scalar import scalar
from torchface.geometry._checks import check_bool, check_choice, check_int, check_number, check_optional_int
from torchface.solver.robust import RobustKind, RobustLoss, SwitchedRobustLoss, robust_scale

__all__ = [
    "SolverMethod",
    "SolverConfig",
    "SolveStatus",
    "SolveResult",
    "ResidualFn",
    "solve_normal_equations",
    "least_squares",
]

#: ``residual_fn(x (B, P)) -> (r (B, N), J (B, N, P), valid (B, N) bool)``.
ResidualFn = Callable[[torch.Tensor], "tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]"]


class SolverMethod(enum.Enum):
    """Step rule: plain Gauss-Newton (every finite step accepted) or Levenberg-Marquardt."""

    GAUSS_NEWTON = "gauss_newton"
    LEVENBERG_MARQUARDT = "levenberg_marquardt"


class SolveStatus(enum.IntEnum):
    """Per-sample outcome stored in :attr:`SolveResult.status`."""

    #: The step or relative cost tolerance was met (or LM could not decrease the cost any further).
    CONVERGED = 0
    #: ``max_iterations`` ran out first; ``params`` holds the last accepted estimate.
    MAX_ITERATIONS = 1
    #: Non-finite residuals or Jacobian, fewer valid residuals than parameters (than ``min_valid`` where given),
    #: an unsolvable system, or a non-finite objective at the end (residuals whose squares overflow);
    #: ``params`` holds the last good estimate (``x0`` projected on the bounds if none).
    FAILED = 2


@dataclass(frozen=True)
class SolverConfig:
    """Settings of :func:`least_squares`.

    Attributes:
        method: Gauss-Newton or Levenberg-Marquardt (default).
        max_iterations: most steps tried per sample (a rejected LM step counts as one).
        initial_damping: LM damping ``mu_LM`` at the start of every sample.
        damping_increase_factor: ``mu_LM`` is multiplied by this after a rejected step (> 1).
        damping_decrease_factor: ``mu_LM`` is divided by this after an accepted step (> 1).
        min_damping: lower clamp of ``mu_LM``.
        max_damping: a sample whose ``mu_LM`` would exceed this stops: CONVERGED if its systems were
            solvable (no step decreases the cost: a minimum to working precision), FAILED if not.
        marquardt_scaling: damp with ``diag(H)`` (True, scale invariant) or with the identity.
        step_tolerance: converged when ``||dx|| <= tol * (||x|| + tol)`` (floored at the dtype's eps).
        cost_tolerance: converged when an accepted step changes the cost by at most ``tol * cost``
            (floored at the dtype's eps).
        differentiable: keep the autograd graph through every iteration (unrolled solver), so that
            gradients flow from the final ``params`` to ``x0`` and to tensors captured by
            ``residual_fn``; when False the loop runs under ``torch.no_grad``.

    Raises:
        TypeError, ValueError: on a field of the wrong type or out of range.
    """

    method: SolverMethod = SolverMethod.LEVENBERG_MARQUARDT
    max_iterations: int = 50
    initial_damping: float = 1e-3
    damping_increase_factor: float = 10.0
    damping_decrease_factor: float = 10.0
    min_damping: float = 1e-12
    max_damping: float = 1e12
    marquardt_scaling: bool = True
    step_tolerance: float = 1e-8
    cost_tolerance: float = 1e-10
    differentiable: bool = False

    def __post_init__(self) -> None:
        check_choice(self.method, "method", SolverMethod)
        object.__setattr__(self, "max_iterations", check_int(self.max_iterations, "max_iterations", 0))
        for name in ("marquardt_scaling", "differentiable"):  # "no" was true
            object.__setattr__(self, name, check_bool(getattr(self, name), name))
        # Each number's range, stated once ("10" or "1e-8" was taken, a str; inf passed "> 1" and ">= 0": an infinite
        # damping factor made the damping inf and the step NaN)
        for name, interval in (("initial_damping", "(0, inf)"), ("min_damping", "(0, inf)"), ("max_damping", "(0, inf)"),
                               ("damping_increase_factor", "(1, inf)"), ("damping_decrease_factor", "(1, inf)"),
                               ("step_tolerance", "[0, inf)"), ("cost_tolerance", "[0, inf)")):  # fmt: skip
            object.__setattr__(self, name, check_number(getattr(self, name), name, interval))
        if not (self.min_damping <= self.initial_damping <= self.max_damping):
            raise ValueError(
                "damping must satisfy 0 < min_damping <= initial_damping <= max_damping, got "
                f"{self.min_damping}, {self.initial_damping}, {self.max_damping}"
            )


@dataclass(frozen=True, eq=False)
class SolveResult:
    """Per-sample outcome of :func:`least_squares`.

    Attributes:
        params: ``(B, P)`` final parameters (last accepted; inside the bounds).
        cost: ``(B,)`` objective at ``params``: ``sum_n rho(r_n; s) + 1/2 sum_p lambda_p (x_p - mu_p)**2``
            (a sum over valid residuals, ``rho = r**2/2`` without robust loss, ``s`` re-estimated at
            ``params``). For a sample FAILED at ``x0`` it covers only its finite valid residuals.
        initial_cost: ``(B,)`` the same objective at the (projected) ``x0``.
        iterations: ``(B,)`` int64 steps tried by each sample.
        status: ``(B,)`` int64 :class:`SolveStatus` codes.
    """

    params: torch.Tensor
    cost: torch.Tensor
    initial_cost: torch.Tensor
    iterations: torch.Tensor
    status: torch.Tensor

    @property
    def converged(self) -> torch.Tensor:
        """``(B,)`` bool, status == CONVERGED."""
        return self.status == int(SolveStatus.CONVERGED)

    @property
    def failed(self) -> torch.Tensor:
        """``(B,)`` bool, status == FAILED."""
        return self.status == int(SolveStatus.FAILED)


# ----------------------------------------------------------------------------------------------------
# Normal equations
# ----------------------------------------------------------------------------------------------------


def _gauss_newton_system(J: torch.Tensor, r: torch.Tensor, w: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """``H = J^T W J (B, P, P)`` and ``g = J^T W r (B, P)`` with batched matmuls."""
    Jt = J.transpose(1, 2)
    wJ = J if w is None else J * w.unsqueeze(2)
    H = torch.bmm(Jt, wJ)
    wr = r if w is None else r * w
    # (r^T W) J as a row vector: reads J in memory order, several times faster than J^T (W r).
    g = torch.bmm(wr.unsqueeze(1), J).squeeze(1)
    return H, g


def _solve_spd(
    H: torch.Tensor, g: torch.Tensor, damping: torch.Tensor | None, marquardt: bool, rcond: float | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``delta = -(H + damping D)^{-1} g`` by Jacobi-scaled Cholesky, per-sample ``ok``.

    A sample is not ok when its ``H`` or ``g`` is non-finite, ``H`` is zero (before damping), the factorisation
    fails, the scaled Cholesky pivots show a reciprocal condition number below ``rcond`` (default ``P * eps``), or
    the solution is non-finite; such samples get ``delta = 0`` and never touch the others.
    """
    B, P = g.shape
    eye = torch.eye(P, dtype=H.dtype, device=H.device).expand(B, P, P)
    finite = torch.isfinite(H).flatten(1).all(1) & torch.isfinite(g).all(1)
    fin3 = finite.view(B, 1, 1)
    H = torch.where(fin3, H, eye)
    g = torch.where(finite.unsqueeze(1), g, torch.zeros_like(g))
    diag = torch.diagonal(H, dim1=1, dim2=2)
    # A zero H (no residual carries weight, no prior: e.g. every residual rejected by a redescending loss) holds no
    # information; damping would turn it into a solvable system of denormals whose zero step "converged".
    informative = diag.amax(1) > 0
    if damping is not None:
        if marquardt:
            floor = diag.amax(1, keepdim=True).clamp_min(torch.finfo(H.dtype).tiny) * 1e-6
            d = torch.maximum(diag, floor)
        else:
            d = torch.ones_like(diag)
        H = H + torch.diag_embed(damping.unsqueeze(1) * d)
        diag = torch.diagonal(H, dim1=1, dim2=2)
    # Jacobi scaling S H S with S = diag(H)^{-1/2}: better accuracy and a scale-free pivot test.
    pos = diag > 0
    # rsqrt of a safe value (not of a clamped one), so that no infinite derivative meets a zero in backward.
    sc = torch.where(pos, torch.where(pos, diag, torch.ones_like(diag)).rsqrt(), torch.ones_like(diag))
    Hs = H * sc.unsqueeze(2) * sc.unsqueeze(1)
    # Which samples are solvable is decided without autograd; the factorisation autograd records then sees
    # only well-posed systems (the identity elsewhere), so a singular sample gives zero, not NaN, gradients.
    with torch.no_grad():
        L, info = torch.linalg.cholesky_ex(Hs)
        ok = finite & (info == 0) & pos.all(1) & informative
        piv = torch.diagonal(L, dim1=1, dim2=2).abs()
        ratio = piv.amin(1) / piv.amax(1).clamp_min(torch.finfo(H.dtype).tiny)
        thresh = P * torch.finfo(H.dtype).eps if rcond is None else rcond
        ok = ok & torch.isfinite(ratio) & (ratio * ratio >= thresh)
    if Hs.requires_grad:
        L = torch.linalg.cholesky_ex(torch.where(ok.view(B, 1, 1), Hs, eye))[0]
    else:
        L = torch.where(ok.view(B, 1, 1), L, eye)
    delta = -sc * torch.cholesky_solve((sc * g).unsqueeze(2), L).squeeze(2)
    ok = ok & torch.isfinite(delta).all(1)
    delta = torch.where(ok.unsqueeze(1), delta, torch.zeros_like(delta))
    return delta, ok


def solve_normal_equations(
    J: torch.Tensor,
    r: torch.Tensor,
    w: torch.Tensor | None = None,
    damping: torch.Tensor | None = None,
    prior: torch.Tensor | None = None,
    *,
    prior_offset: torch.Tensor | None = None,
    marquardt_scaling: bool = True,
    rcond: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One (damped) Gauss-Newton step of ``min 1/2 sum_n w_n r_n**2 (+ 1/2 sum_p prior_p (x_p - mu_p)**2)``.

    Forms ``H = J^T W J + diag(prior) + damping * D`` and ``g = J^T W r + prior * prior_offset`` and
    returns ``delta = -H^{-1} g`` (Eq. 20), solved by a Jacobi-scaled Cholesky
    (``torch.linalg.cholesky_ex``). ``D = diag(J^T W J + diag(prior))`` (floored at ``1e-6`` times its
    largest entry) with ``marquardt_scaling``, else ``I``.

    Args:
        J: ``(B, N, P)`` Jacobian ``dr/dx``.
        r: ``(B, N)`` residuals.
        w: ``(B, N)`` non-negative weights, ``None`` for ones. Entries with zero weight must still be
            finite (mask them out with ``torch.where`` first): ``0 * nan`` is nan.
        damping: ``(B,)`` Levenberg-Marquardt damping ``mu_LM >= 0``, ``None`` for none.
        prior: ``(B, P)`` or ``(P,)`` diagonal precision ``lambda >= 0`` added to ``H``; ``None`` for none.
        prior_offset: ``(B, P)`` or ``(P,)`` ``x - mu`` of the prior, adding ``lambda (x - mu)`` to ``g``;
            ``None`` for zero (the prior then only penalises the step itself).
        marquardt_scaling: choose ``D`` as above.
        rcond: smallest accepted reciprocal condition number of the scaled ``H`` (estimated from the
            Cholesky pivots); ``None`` for ``P * eps``.

    Returns:
        ``delta (B, P)`` and ``ok (B,)`` bool. Where ``ok`` is False (non-finite input, a zero ``J^T W J +
        diag(prior)``, failed or ill-conditioned factorisation), ``delta`` is 0; other samples are unaffected.

    Example:
        >>> J = torch.eye(2).expand(1, 2, 2)
        >>> solve_normal_equations(J, torch.tensor([[1.0, -2.0]]))
        (tensor([[-1.,  2.]]), tensor([True]))
    """
    if not isinstance(J, torch.Tensor) or not J.is_floating_point() or J.dim() != 3:
        got = tuple(J.shape) if isinstance(J, torch.Tensor) else type(J).__name__
        raise ValueError(f"J must be a (B, N, P) floating-point tensor, got {got}")
    B, N, P = J.shape
    _check_tensor("r", r, (B, N), J.dtype)
    if w is not None:
        _check_tensor("w", w, (B, N), J.dtype)
    if damping is not None:
        _check_tensor("damping", damping, (B,), J.dtype)
    prior_b = None if prior is None else _batched_param("prior", prior, B, P, J.dtype)
    off_b = None if prior_offset is None else _batched_param("prior_offset", prior_offset, B, P, J.dtype)
    H, g = _gauss_newton_system(J, r, w)
    if prior_b is not None:
        H = H + torch.diag_embed(prior_b)
        if off_b is not None:
            g = g + prior_b * off_b
    return _solve_spd(H, g, damping, marquardt_scaling, rcond)


# ----------------------------------------------------------------------------------------------------
# Validation helpers
# ----------------------------------------------------------------------------------------------------


def _check_tensor(name: str, t: object, shape: tuple[int, ...], dtype: torch.dtype) -> None:
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a tensor of shape {shape}, got {type(t).__name__}")
    if tuple(t.shape) != tuple(shape) or t.dtype != dtype:
        raise ValueError(f"{name} must be {dtype} of shape {tuple(shape)}, got {t.dtype} {tuple(t.shape)}")


def _batched_param(name: str, t: object, B: int, P: int, dtype: torch.dtype) -> torch.Tensor:
    """Validate a ``(P,)`` or ``(B, P)`` tensor and return it as ``(B, P)`` (a broadcast view)."""
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a tensor of shape ({P},) or ({B}, {P}), got {type(t).__name__}")
    if t.dtype != dtype or tuple(t.shape) not in ((P,), (B, P)):
        raise ValueError(f"{name} must be {dtype} of shape ({P},) or ({B}, {P}), got {t.dtype} {tuple(t.shape)}")
    return t.expand(B, P)


def _usable_bounds(lo: torch.Tensor | None, hi: torch.Tensor | None) -> torch.Tensor | None:
    """Elementwise, whether lower bounds ``lo`` and upper bounds ``hi`` (broadcast; None: none on that side) can bound
    a parameter: no NaN, ``lo < inf``, ``hi > -inf`` and ``lo <= hi`` (``-inf`` / ``inf``: none on that side). None
    where both are None. No host read (``solve_level`` reads it with its first iteration's flag)."""
    checks = []  # each False at NaN
    if lo is not None:
        checks.append(lo < scalar(float("inf"), lo))
    if hi is not None:
        checks.append(hi > scalar(float("-inf"), hi))
    if lo is not None and hi is not None:
        checks.append(lo <= hi)
    return functools.reduce(torch.logical_and, checks) if checks else None


def _check_bounds(lo: torch.Tensor | None, hi: torch.Tensor | None) -> None:
    """Refuse ``(B, P)`` bounds that are not :func:`_usable_bounds`: a NaN, a lower bound at ``inf``, an upper at
    ``-inf`` or ``lo > hi``, naming the first such sample and parameter (one host read where there is none). A NaN
    bound made its parameter NaN and the sample FAILED without a word."""
    ok = _usable_bounds(lo, hi)
    if ok is None or bool(ok.all()):
        return
    b, k = (int(v) for v in (~ok).nonzero()[0])
    got = ", ".join(f"{name} {float(x[b, k])}" for name, x in (("lower", lo), ("upper", hi)) if x is not None)
    raise ValueError(
        "lower and upper must be bounds, lower <= upper, neither NaN, lower below inf and upper above -inf (-inf / "
        f"inf: none on that side), got {got} for sample {b}, parameter {k}"
    )


# ----------------------------------------------------------------------------------------------------
# The solver
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Point:
    """Everything known at one estimate ``x`` of every sample (internal)."""

    r: torch.Tensor  # (B, N) residuals, 0 where not used
    J: torch.Tensor  # (B, N, P) Jacobian, finite everywhere (rows not used may hold anything finite)
    use: torch.Tensor | None  # (B, N) bool, valid and finite; None when every residual is used
    good: torch.Tensor  # (B,) finite at every valid residual and enough valid residuals


def _where_b(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``torch.where`` with a ``(B,)`` mask broadcast over trailing dimensions."""
    return torch.where(mask.view(mask.shape + (1,) * (a.dim() - 1)), a, b)


def least_squares(
    residual_fn: ResidualFn,
    x0: torch.Tensor,
    config: SolverConfig = SolverConfig(),
    *,
    lower: torch.Tensor | None = None,
    upper: torch.Tensor | None = None,
    prior_precision: torch.Tensor | None = None,
    prior_mean: torch.Tensor | None = None,
    robust: RobustLoss | SwitchedRobustLoss | None = None,
    min_valid: int | torch.Tensor | None = None,
) -> SolveResult:
    """Minimise ``sum_n rho(r_n(x); s) + 1/2 sum_p lambda_p (x_p - mu_p)**2`` for ``B`` samples at once.

    Batched Gauss-Newton or Levenberg-Marquardt (Anisetti et al. 2006, Eq. 20) with

    * per-sample acceptance: LM accepts a step where the cost decreased and then divides that
      sample's damping by ``damping_decrease_factor``, otherwise keeps ``x`` and multiplies it by
      ``damping_increase_factor``; GN accepts every finite step. Samples that converged or failed stop
      changing (masks, no Python loop over ``B``); the loop ends when none is left running.
    * box bounds: ``x`` is projected onto ``[lower, upper]`` (``x0`` included); parameters at a bound
      whose gradient points outward are held fixed for the step (projected Newton, Bertsekas 1982),
      so the solution is the constrained minimum, with the bound active where it cuts the free one.
    * IRLS: with ``robust``, the weights ``w_n = robust.weight(r_n, s)`` are recomputed every
      iteration from the current residuals, with ``s = max(robust_scale(r, valid), robust.min_scale)``
      (Section 4 of the paper). LM compares costs at the same ``s``.
    * an optional diagonal Gaussian prior (precision ``lambda``, mean ``mu``, zero if not given).

    Status per sample (see :class:`SolveStatus`): CONVERGED when the step or relative cost tolerance is
    met, MAX_ITERATIONS, or FAILED when the residuals or Jacobian are non-finite at a valid entry, fewer
    than ``P`` residuals (or ``min_valid``) are valid, the normal equations cannot be solved (GN; LM retries with
    more damping up to ``max_damping``), or the objective at ``params`` is not finite (it overflowed: no step
    can be judged, so LM would otherwise stop there as CONVERGED). A failed sample keeps its last good estimate
    and never makes another one NaN. Without ``config.differentiable`` the loop runs under ``torch.no_grad``; with it,
    only out-of-place tensor operations are used so gradients flow through the unrolled iterations.

    Args:
        residual_fn: ``x (B, P) -> (r (B, N), J (B, N, P), valid (B, N) bool or None)`` with the
            analytic Jacobian ``J = dr/dx``; ``valid`` false marks residuals to ignore (their values
            may be anything, NaN included). It is called once before the loop and once per iteration
            on the whole batch (finished samples included; their results are ignored). Under
            ``torch.no_grad`` a function that needs autograd must enable it itself.
        x0: ``(B, P)`` floating-point initial parameters.
        config: the :class:`SolverConfig`.
        lower: ``(P,)`` or ``(B, P)`` lower bounds (``-inf`` allowed), ``None`` for none.
        upper: ``(P,)`` or ``(B, P)`` upper bounds (``+inf`` allowed), ``None`` for none. ``ValueError`` for
            ``lower > upper``, a NaN bound, a lower bound at ``inf`` or an upper at ``-inf``.
        prior_precision: ``(P,)`` or ``(B, P)`` non-negative diagonal precision ``lambda``.
        prior_mean: ``(P,)`` or ``(B, P)`` prior mean ``mu`` (needs ``prior_precision``).
        robust: the :class:`RobustLoss` (or a per-sample :class:`SwitchedRobustLoss`); ``None`` for plain
            least squares.
        min_valid: the fewest valid residuals a sample needs (FAILED with fewer); ``None`` for ``P``. Fewer than
            ``P`` can do where a prior determines the other parameters (e.g. ``P`` less the number of parameters
            with a positive ``prior_precision``). A ``(B,)`` integer tensor: each sample's own (per-sample
            ``prior_precision``).

    Returns:
        :class:`SolveResult` with ``params (B, P)``, ``cost (B,)`` and ``initial_cost (B,)`` (sums, as
        above), ``iterations (B,)`` and ``status (B,)`` (int64).

    Raises:
        TypeError, ValueError: on malformed inputs or ``residual_fn`` outputs of the wrong shape/dtype.

    Example:
        >>> t = torch.linspace(0, 1, 20, dtype=torch.float64)
        >>> y = 2.0 * torch.exp(-1.5 * t)
        >>> def fn(x):
        ...     e = torch.exp(x[:, 1:2] * t)
        ...     r = x[:, 0:1] * e - y
        ...     return r, torch.stack([e, x[:, 0:1] * t * e], dim=2), None
        >>> res = least_squares(fn, torch.tensor([[1.0, 0.0]], dtype=torch.float64))
        >>> [round(v, 6) for v in res.params[0].tolist()], SolveStatus(int(res.status[0])).name
        ([2.0, -1.5], 'CONVERGED')
    """
    if not callable(residual_fn):
        raise TypeError(f"residual_fn must be callable, got {type(residual_fn).__name__}")
    if not isinstance(config, SolverConfig):
        raise TypeError(f"config must be a SolverConfig, got {type(config).__name__}")
    if not isinstance(x0, torch.Tensor) or not x0.is_floating_point() or x0.dim() != 2:
        got = (tuple(x0.shape), x0.dtype) if isinstance(x0, torch.Tensor) else type(x0).__name__
        raise ValueError(f"x0 must be a (B, P) floating-point tensor, got {got}")
    if robust is not None and not isinstance(robust, (RobustLoss, SwitchedRobustLoss)):
        raise TypeError(f"robust must be a RobustLoss, a SwitchedRobustLoss or None, got {type(robust).__name__}")
    B, P = x0.shape
    dtype = x0.dtype
    lo = None if lower is None else _batched_param("lower", lower, B, P, dtype)
    hi = None if upper is None else _batched_param("upper", upper, B, P, dtype)
    _check_bounds(lo, hi)
    lam = None if prior_precision is None else _batched_param("prior_precision", prior_precision, B, P, dtype)
    if lam is not None and bool((lam < 0).any() | ~torch.isfinite(lam).all()):
        raise ValueError("prior_precision must be finite and non-negative")
    if prior_mean is not None and lam is None:
        raise ValueError("prior_mean needs prior_precision")
    mu = None if prior_mean is None else _batched_param("prior_mean", prior_mean, B, P, dtype)
    use_robust = robust is not None and robust.kind is not RobustKind.NONE
    if isinstance(min_valid, torch.Tensor):
        if min_valid.shape != (B,) or min_valid.dtype.is_floating_point or min_valid.dtype == torch.bool:
            raise TypeError(f"min_valid must be an int, a ({B},) integer tensor or None, got {min_valid.dtype} "
                            f"{tuple(min_valid.shape)}")  # fmt: skip
        if bool((min_valid < 0).any()):
            raise ValueError(f"min_valid must be >= 0, got {min_valid.tolist()}")
        min_valid = min_valid.to(x0.device)
    else:
        min_valid = check_optional_int(min_valid, "min_valid", 0)

    grad_ctx = contextlib.nullcontext() if config.differentiable else torch.no_grad()
    with grad_ctx:
        return _run(residual_fn, x0, config, lo, hi, lam, mu, robust if use_robust else None,
                    P if min_valid is None else min_valid)


def _run(
    residual_fn: ResidualFn,
    x0: torch.Tensor,
    config: SolverConfig,
    lo: torch.Tensor | None,
    hi: torch.Tensor | None,
    lam: torch.Tensor | None,
    mu: torch.Tensor | None,
    robust: RobustLoss | SwitchedRobustLoss | None,
    min_valid: int | torch.Tensor,
) -> SolveResult:
    B, P = x0.shape
    dtype, device = x0.dtype, x0.device
    eps = torch.finfo(dtype).eps
    step_tol = max(float(config.step_tolerance), eps)
    cost_tol = max(float(config.cost_tolerance), eps)
    lm = config.method is SolverMethod.LEVENBERG_MARQUARDT

    def project(x: torch.Tensor) -> torch.Tensor:
        if lo is not None:
            x = torch.maximum(x, lo)
        if hi is not None:
            x = torch.minimum(x, hi)
        return x

    first_call = [True]

    def evaluate(x: torch.Tensor) -> _Point:
        out = residual_fn(x)
        if not isinstance(out, tuple) or len(out) != 3:
            raise TypeError("residual_fn must return a tuple (r, J, valid)")
        r, J, valid = out
        if first_call[0]:
            if not isinstance(r, torch.Tensor) or r.dim() != 2 or r.shape[0] != B or r.dtype != dtype:
                got = (tuple(r.shape), r.dtype) if isinstance(r, torch.Tensor) else type(r).__name__
                raise ValueError(f"residual_fn must return r of shape ({B}, N) and dtype {dtype}, got {got}")
            _check_tensor("J returned by residual_fn", J, (B, r.shape[1], P), dtype)
            if valid is not None:
                _check_tensor("valid returned by residual_fn", valid, (B, r.shape[1]), torch.bool)
            first_call[0] = False
        # One reduction pass over J finds its non-finite rows (a NaN or inf anywhere makes the sum
        # non-finite); J is copied only in the rare case it holds such rows.
        finite = torch.isfinite(r) & torch.isfinite(J.detach().sum(2))
        if valid is None:
            good = finite.all(1) & (r.shape[1] >= min_valid)
            use = finite
        else:
            good = ~(valid & ~finite).any(1) & (valid.sum(1) >= min_valid)
            use = valid & finite
        if not bool(finite.all()):
            J = torch.where(finite.unsqueeze(2), J, torch.zeros_like(J))
        r = torch.where(use, r, torch.zeros_like(r))
        return _Point(r, J, None if bool(use.all()) else use, good)

    def scale_of(pt: _Point) -> torch.Tensor | None:
        if robust is None:
            return None
        return robust_scale(pt.r, pt.use).clamp_min(robust.min_scale).unsqueeze(1)

    def cost_of(pt: _Point, x: torch.Tensor, s: torch.Tensor | None) -> torch.Tensor:
        rho = 0.5 * pt.r * pt.r if robust is None or s is None else robust.rho(pt.r, s)  # s is None iff robust is
        if pt.use is not None:
            rho = torch.where(pt.use, rho, torch.zeros_like(rho))
        c = rho.sum(1)
        if lam is not None:
            d = x if mu is None else x - mu
            c = c + 0.5 * (lam * d * d).sum(1)
        return c

    def system(pt: _Point, x: torch.Tensor, s: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        if robust is None or s is None:  # s is None iff robust is
            w = None if pt.use is None else pt.use.to(dtype)
        else:
            w = robust.weight(pt.r, s)
            if pt.use is not None:
                w = torch.where(pt.use, w, torch.zeros_like(w))
        H, g = _gauss_newton_system(pt.J, pt.r, w)
        if lam is not None:
            H = H + torch.diag_embed(lam)
            g = g + lam * (x if mu is None else x - mu)
        return H, g

    x = project(x0)
    pt = evaluate(x)
    s = scale_of(pt)
    cost = cost_of(pt, x, s)
    H, g = system(pt, x, s)
    initial_cost = cost
    active = pt.good
    status = torch.where(
        active,
        torch.full((B,), int(SolveStatus.MAX_ITERATIONS), dtype=torch.int64, device=device),
        torch.full((B,), int(SolveStatus.FAILED), dtype=torch.int64, device=device),
    )
    iterations = torch.zeros(B, dtype=torch.int64, device=device)
    damping = torch.full((B,), float(config.initial_damping), dtype=dtype, device=device)
    code_conv = torch.full_like(status, int(SolveStatus.CONVERGED))
    code_fail = torch.full_like(status, int(SolveStatus.FAILED))

    for _ in range(config.max_iterations):
        if not bool(active.any()):
            break
        # Projected Newton: hold parameters at a bound whose descent direction leaves the box.
        if lo is not None or hi is not None:
            held = torch.zeros_like(x, dtype=torch.bool)
            if lo is not None:
                held = held | ((x <= lo) & (g > 0))
            if hi is not None:
                held = held | ((x >= hi) & (g < 0))
            free = (~held).to(dtype)
            Hs = H * free.unsqueeze(2) * free.unsqueeze(1) + torch.diag_embed(held.to(dtype))
            gs = g * free
        else:
            Hs, gs = H, g
        delta, ok = _solve_spd(Hs, gs, damping if lm else None, config.marquardt_scaling, None)
        ok = ok & active
        x_try = torch.where(ok.unsqueeze(1), project(x + delta), x)
        pt_try = evaluate(x_try)
        cost_try = cost_of(pt_try, x_try, s)  # same scale as `cost`, so the two compare
        try_good = ok & pt_try.good & torch.isfinite(cost_try)
        step = (x_try - x).norm(dim=1)
        small_step = ok & (step <= step_tol * (x.norm(dim=1) + step_tol))
        if lm:
            accept = try_good & (cost_try < cost)
        else:
            accept = try_good
        small_cost = accept & ((cost - cost_try).abs() <= cost_tol * cost)
        converged = active & (small_step | small_cost | (accept & (cost_try == 0)))
        iterations = iterations + active.to(torch.int64)

        # Move the accepted samples; re-estimate the IRLS scale and rebuild their system there.
        x = _where_b(accept, x_try, x)
        s_new = scale_of(pt_try)
        cost_new = cost_of(pt_try, x_try, s_new) if robust is not None else cost_try
        H_new, g_new = system(pt_try, x_try, s_new)
        cost = _where_b(accept, cost_new, cost)
        H = _where_b(accept, H_new, H)
        g = _where_b(accept, g_new, g)
        if s is not None and s_new is not None:  # both are None without a robust loss, tensors with one
            s = _where_b(accept, s_new, s)

        if lm:
            up = damping * config.damping_increase_factor
            down = (damping / config.damping_decrease_factor).clamp_min(config.min_damping)
            stuck = active & ~accept & ~converged & (up > config.max_damping)
            damping = torch.where(accept, down, torch.where(active, up.clamp_max(config.max_damping), damping))
            # Stuck: CONVERGED if the last system was solvable (no decrease possible), else FAILED.
            failed = stuck & ~ok
            converged = converged | (stuck & ok)
        else:
            failed = active & ~try_good & ~converged
        status = torch.where(converged, code_conv, torch.where(failed, code_fail, status))
        active = active & ~converged & ~failed

    # An objective that overflowed (finite residuals whose squares do not fit the dtype) cannot have been
    # minimised: LM, which no step could improve on it, would have stopped as CONVERGED at a cost of inf.
    status = torch.where(torch.isfinite(cost), status, code_fail)
    return SolveResult(params=x, cost=cost, initial_cost=initial_cost, iterations=iterations, status=status)
