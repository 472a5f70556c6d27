"""Robust losses for iteratively re-weighted least squares (IRLS) and a batched robust scale.

The tracker down-weights pixels hit by external occlusion with weights drawn from robust statistics of
the residual (Anisetti et al. 2006, Section 4, after Xiao, Kanade and Cohn 2002). Every loss here is
written in the scaled form

    ``rho(r; s) = s**2 * rho_hat(r / s)``,   with ``rho_hat(u) ~ u**2 / 2`` near ``u = 0``,

so that ``NONE`` gives the plain least-squares cost ``r**2 / 2`` whatever the scale, and the IRLS weight

    ``w(r; s) = rho'(r; s) / r = rho_hat'(u) / u``,   ``u = r / s``,

lies in ``[0, 1]`` with ``w -> 1`` as ``r -> 0``. Minimising ``sum_n rho(r_n; s)`` by Gauss-Newton with
the weights held fixed at the current residuals is IRLS (see :func:`torchface.solver.least_squares`).

Shape vocabulary: ``B`` batch, ``N`` residuals per sample (see :mod:`torchface.conventions`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import cast

import torch

from torchface._deterministic import nanmedian_values
from torchface._scalar import scalar
from torchface.geometry._checks import check_choice, check_number

__all__ = ["RobustKind", "RobustLoss", "SwitchedRobustLoss", "robust_scale", "MAD_TO_SIGMA"]

#: ``1 / Phi^{-1}(3/4)``: makes the median absolute deviation a consistent estimate of a Gaussian sigma.
MAD_TO_SIGMA: float = 1.482602218505602


class RobustKind(enum.Enum):
    """Which ``rho_hat`` a :class:`RobustLoss` uses (``u = r / s``, tuning constant ``c``).

    ============== ============================================== =============================
    kind           ``rho_hat(u)``                                 weight ``rho_hat'(u) / u``
    ============== ============================================== =============================
    NONE (= L2)    ``u**2 / 2``                                   ``1``
    HUBER          ``u**2/2`` if ``|u| <= c`` else ``c(|u|-c/2)`` ``min(1, c / |u|)``
    CAUCHY         ``c**2/2 log(1 + (u/c)**2)``                   ``1 / (1 + (u/c)**2)``
    TUKEY          ``c**2/6 (1 - (1 - (u/c)**2)**3)``, ``|u|<=c`` ``(1 - (u/c)**2)**2``, 0 beyond
    GEMAN_MCCLURE  ``(u**2/2) / (1 + (u/c)**2)``                  ``1 / (1 + (u/c)**2)**2``
    ============== ============================================== =============================

    Tukey's biweight is constant ``c**2/6`` beyond ``|u| = c`` (zero weight: full rejection).
    """

    NONE = "none"
    L2 = "none"  # alias of NONE
    HUBER = "huber"
    CAUCHY = "cauchy"
    TUKEY = "tukey"
    GEMAN_MCCLURE = "geman_mcclure"


#: Tuning constants giving 95% asymptotic efficiency on Gaussian data (Geman-McClure: unit constant).
_DEFAULT_C: dict[RobustKind, float] = {
    RobustKind.NONE: 1.0,
    RobustKind.HUBER: 1.345,
    RobustKind.CAUCHY: 2.3849,
    RobustKind.TUKEY: 4.6851,
    RobustKind.GEMAN_MCCLURE: 1.0,
}


def _as_scale(scale: torch.Tensor | float, r: torch.Tensor) -> torch.Tensor:
    """``scale`` as a tensor on ``r``'s device and dtype, clamped to a dtype-tied positive floor."""
    s = scale if isinstance(scale, torch.Tensor) and scale.dtype == r.dtype and scale.device == r.device else (
        torch.as_tensor(scale, dtype=r.dtype, device=r.device))  # (as_tensor of such a tensor: one more operation)
    return s.clamp_min(torch.finfo(r.dtype).tiny ** 0.5)


def _bounded_square_over_c(u: torch.Tensor, c: float) -> torch.Tensor:
    """``(u / c)**2`` with ``|u / c|`` clamped below ``sqrt(max) / 2`` of its dtype, where Cauchy's and
    Geman-McClure's ``rho_hat`` (functions of ``(u / c)**2``) have long saturated: a residual far beyond the scale (a
    zero scale is floored at ``sqrt(tiny)``) made ``u**2`` overflow, and ``rho`` inf (Cauchy) or NaN (Geman-McClure,
    inf / inf), gradients too. Relative to ``c``, so that float16 keeps its range (|u / c| up to 128). In float32
    and float64 the square stays below ``max / 256`` (``|u / c|`` at most 1.1e18 and 8.4e152): torch 2.5's ``log1p``
    gave inf above about ``max / 64`` (Cauchy's ``rho`` of a residual 1e30 beyond a zero scale, float64)."""
    root = torch.finfo(u.dtype).max ** 0.5
    bound = min(root / 2, max(root / 16, 128.0))
    v = (u / c).clamp(-bound, bound)
    return v * v


@dataclass(frozen=True)
class RobustLoss:
    """A robust loss ``rho(r; s) = s**2 rho_hat(r / s)`` and its IRLS weight.

    Attributes:
        kind: which ``rho_hat`` (see :class:`RobustKind`).
        c: tuning constant in units of the scale ``s``; ``None`` picks the usual 95%-efficiency value
            (Huber 1.345, Cauchy 2.3849, Tukey 4.6851, Geman-McClure 1.0). Ignored by ``NONE``.
        min_scale: floor on the scale used by :func:`torchface.solver.least_squares` when it estimates
            ``s`` with :func:`robust_scale` (in residual units); keeps the weights defined on exact data.

    Example:
        >>> loss = RobustLoss(RobustKind.HUBER)
        >>> loss.weight(torch.tensor([0.0, 1.0, 2.69]), 1.0)
        tensor([1.0000, 1.0000, 0.5000])
    """

    kind: RobustKind = RobustKind.NONE
    c: float | None = None
    min_scale: float = 1e-6

    def __post_init__(self) -> None:
        check_choice(self.kind, "kind", RobustKind)
        # Infinite constants gave NaN losses or weights (Huber's weight inf / inf, the others' rho inf * 0); a numpy
        # float is taken as TrackerConfig.robust_c takes it (a numpy float32 passed the config and was refused here),
        # a bool or a string is a TypeError (was a ValueError).
        c = check_number(self.c, "c", "(0, inf)", optional=True)
        object.__setattr__(self, "c", _DEFAULT_C[self.kind] if c is None else float(c))
        object.__setattr__(self, "min_scale", check_number(self.min_scale, "min_scale", "(0, inf)"))

    @property
    def _c(self) -> float:
        """``c`` as ``__post_init__`` left it: a float (``None`` became the kind's default)."""
        return cast(float, self.c)

    def _check(self, r: torch.Tensor) -> None:
        if not isinstance(r, torch.Tensor) or not r.is_floating_point():
            got = r.dtype if isinstance(r, torch.Tensor) else type(r).__name__
            raise TypeError(f"r must be a floating-point tensor, got {got}")

    def rho(self, r: torch.Tensor, scale: torch.Tensor | float = 1.0) -> torch.Tensor:
        """The loss ``rho(r; s) = s**2 rho_hat(r / s)``.

        Args:
            r: residuals, any shape ``(*)`` (e.g. ``(B, N)``).
            scale: ``s > 0``, a float or a tensor broadcastable against ``r`` (``(B, 1)`` for a
                per-sample scale).

        Returns:
            ``(*)`` losses, ``r**2 / 2`` for ``NONE``; finite and differentiable at ``r = 0``.
        """
        self._check(r)
        if self.kind is RobustKind.NONE:
            return 0.5 * r * r
        s = _as_scale(scale, r)
        c = self._c
        u = r / s
        u2 = u * u
        if self.kind is RobustKind.HUBER:
            a = u.abs()
            # Clamp before the branch so both sides stay finite with finite gradients.
            lin = c * (a.clamp_min(c) - 0.5 * c)
            out = torch.where(a <= c, 0.5 * u2, lin)
        elif self.kind is RobustKind.CAUCHY:
            out = 0.5 * c * c * torch.log1p(_bounded_square_over_c(u, c))
        elif self.kind is RobustKind.TUKEY:  # the tracker's default: its constants as cached tensors (_scalar)
            one = scalar(1.0, u2)
            t = (u2 / scalar(c * c, u2)).clamp(max=1.0)
            out = scalar(c * c / 6.0, u2) * (one - (one - t) ** 3)
        else:  # GEMAN_MCCLURE
            v2 = _bounded_square_over_c(u, c)
            out = 0.5 * c * c * v2 / (1.0 + v2)
        return s * s * out

    def weight(self, r: torch.Tensor, scale: torch.Tensor | float = 1.0) -> torch.Tensor:
        """The IRLS weight ``w = rho'(r; s) / r`` in ``[0, 1]``, equal to 1 at ``r = 0``.

        Args:
            r: residuals, any shape ``(*)``.
            scale: ``s > 0``, a float or a tensor broadcastable against ``r``.

        Returns:
            ``(*)`` weights (Tukey: exactly 0 for ``|r| >= c s``).
        """
        self._check(r)
        if self.kind is RobustKind.NONE:
            return torch.ones_like(r)
        s = _as_scale(scale, r)
        c = self._c
        u = r / s
        u2 = u * u
        if self.kind is RobustKind.HUBER:
            return c / u.abs().clamp_min(c)
        if self.kind is RobustKind.CAUCHY:
            return 1.0 / (1.0 + u2 / (c * c))
        if self.kind is RobustKind.TUKEY:
            t = (u2 / (c * c)).clamp(max=1.0)
            return (1.0 - t) ** 2
        d = 1.0 + u2 / (c * c)  # GEMAN_MCCLURE
        return 1.0 / (d * d)

    def rho_and_weight(self, r: torch.Tensor, scale: torch.Tensor | float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
        """``(rho(r; s), weight(r; s))`` in one pass: the same values as the two methods, sharing ``r / s``.

        Args:
            r: residuals, any shape ``(*)``; scale: ``s > 0``, a float or a tensor broadcastable against ``r``.

        Returns:
            Two ``(*)`` tensors, equal to :meth:`rho` and :meth:`weight` (the IRLS loop needs both at the same
            scale every iteration).
        """
        if self.kind is not RobustKind.TUKEY:
            return self.rho(r, scale), self.weight(r, scale)
        self._check(r)
        s = _as_scale(scale, r)
        c = self._c
        u = r / s
        one = scalar(1.0, u)
        t = ((u * u) / scalar(c * c, u)).clamp(max=1.0)
        one_minus_t = one - t
        return s * s * (scalar(c * c / 6.0, u) * (one - one_minus_t**3)), one_minus_t**2


@dataclass(frozen=True, eq=False)
class SwitchedRobustLoss:
    """Per sample, one of two robust losses: ``alternative`` for the samples (rows) where ``switch`` is True,
    ``base`` for the others. It has :class:`RobustLoss`'s interface (``rho``, ``weight``, ``rho_and_weight``,
    ``kind`` and ``min_scale`` of ``base``) for :func:`torchface.solver.least_squares` and the tracker's solver.

    Attributes:
        base: the loss of the rows not switched; alternative: the loss of the switched rows (same ``min_scale``).
        switch: ``(B, 1)`` bool, broadcast against residuals ``(B, N)``.

    Example:
        >>> loss = SwitchedRobustLoss(RobustLoss(RobustKind.TUKEY, 4.685), RobustLoss(RobustKind.HUBER, 4.685),
        ...                           torch.tensor([[False], [True]]))
        >>> loss.weight(torch.full((2, 1), 6.0))  # beyond Tukey's c: rejected by Tukey, kept by Huber
        tensor([[0.0000],
                [0.7808]])
    """

    base: RobustLoss
    alternative: RobustLoss
    switch: torch.Tensor

    def __post_init__(self) -> None:
        if not isinstance(self.base, RobustLoss) or not isinstance(self.alternative, RobustLoss):
            raise TypeError("base and alternative must be RobustLoss instances")
        if self.base.min_scale != self.alternative.min_scale:
            raise ValueError(f"base and alternative need one min_scale, got {self.base.min_scale} and "
                             f"{self.alternative.min_scale}")  # fmt: skip
        sw = self.switch
        if not isinstance(sw, torch.Tensor) or sw.dtype != torch.bool or sw.dim() != 2 or sw.shape[1] != 1:
            got = (tuple(sw.shape), sw.dtype) if isinstance(sw, torch.Tensor) else type(sw).__name__
            raise ValueError(f"switch must be a (B, 1) bool tensor, got {got}")

    @property
    def kind(self) -> RobustKind:
        """``base``'s kind."""
        return self.base.kind

    @property
    def min_scale(self) -> float:
        """The losses' common scale floor."""
        return self.base.min_scale

    def rho(self, r: torch.Tensor, scale: torch.Tensor | float = 1.0) -> torch.Tensor:
        """:meth:`RobustLoss.rho` of each row's loss; ``r`` ``(B, N)``."""
        return torch.where(self.switch, self.alternative.rho(r, scale), self.base.rho(r, scale))

    def weight(self, r: torch.Tensor, scale: torch.Tensor | float = 1.0) -> torch.Tensor:
        """:meth:`RobustLoss.weight` of each row's loss; ``r`` ``(B, N)``."""
        return torch.where(self.switch, self.alternative.weight(r, scale), self.base.weight(r, scale))

    def rho_and_weight(self, r: torch.Tensor, scale: torch.Tensor | float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
        """``(rho, weight)`` of each row's loss."""
        rho_a, w_a = self.alternative.rho_and_weight(r, scale)
        rho_b, w_b = self.base.rho_and_weight(r, scale)
        return torch.where(self.switch, rho_a, rho_b), torch.where(self.switch, w_a, w_b)


def _masked_median(x: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Row-wise median of the entries of ``x (B, N)`` where ``mask (B, N)``; returns (median, count).

    Even counts average the two middle values (as ``numpy.median``). ``nanmedian`` (a selection, not a
    full sort) gives the lower middle value ``s[(k - 1) // 2]`` of the ``k`` sorted valid values; the
    upper one ``s[k // 2]`` is the same value when more than ``k // 2`` values are <= it, else the
    smallest value above it. Empty rows give 0.
    """
    xm = torch.where(mask, x, torch.full_like(x, torch.nan))
    lo = nanmedian_values(xm, dim=1)
    count = mask.sum(dim=1)
    lo = torch.where(count > 0, lo, torch.zeros_like(lo))
    n_le = (mask & (x <= lo.unsqueeze(1))).sum(dim=1)
    above = torch.where(mask & (x > lo.unsqueeze(1)), x, torch.full_like(x, torch.inf)).amin(dim=1)
    same = (count % 2 == 1) | (n_le > count // 2)
    hi = torch.where(same, lo, above.clamp(max=torch.finfo(x.dtype).max))
    return 0.5 * (lo + hi), count


def robust_scale(r: torch.Tensor, mask: torch.Tensor | None = None, *, centered: bool = True) -> torch.Tensor:
    """Per-sample robust scale ``1.4826 * MAD`` of the valid residuals.

    ``MAD = median_n |r_n - median_m r_m|`` over the entries where ``mask`` is true (``centered=True``),
    or ``median_n |r_n|`` (``centered=False``, for residuals known to be centred on zero). Non-finite
    residuals are ignored. A row without any valid finite residual gets the fallback scale 1.

    Args:
        r: ``(B, N)`` residuals.
        mask: ``(B, N)`` bool, true where a residual counts; ``None`` means all.
        centered: subtract the per-sample median before taking absolute values.

    Returns:
        ``(B,)`` scales, finite and non-negative (0 when more than half the residuals are identical;
        callers floor it, see :attr:`RobustLoss.min_scale`).

    Example:
        >>> robust_scale(torch.tensor([[1.0, -1.0, 2.0, -2.0, 100.0]]))
        tensor([2.9652])
    """
    if not isinstance(r, torch.Tensor) or not r.is_floating_point() or r.dim() != 2:
        got = tuple(r.shape) if isinstance(r, torch.Tensor) else type(r).__name__
        raise ValueError(f"r must be a (B, N) floating-point tensor, got {got}")
    if mask is None:
        mask = torch.ones_like(r, dtype=torch.bool)
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.shape != r.shape:
        got_mask = (tuple(mask.shape), mask.dtype) if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ValueError(f"mask must be a bool tensor of shape {tuple(r.shape)}, got {got_mask}")
    if r.shape[1] == 0:
        return torch.ones(r.shape[0], dtype=r.dtype, device=r.device)
    mask = mask & torch.isfinite(r)
    if centered:
        med, _ = _masked_median(r, mask)
        dev = (r - med.unsqueeze(1)).abs()
    else:
        dev = r.abs()
    mad, count = _masked_median(dev, mask)
    scale = MAD_TO_SIGMA * mad
    return torch.where(count > 0, scale, torch.ones_like(scale))
