"""Batched, differentiable Gauss-Newton / Levenberg-Marquardt and robust losses (IRLS).

The numerical engine of the per-frame minimisation (Anisetti et al. 2006, Eq. 20 and Section 4):
:func:`least_squares` solves ``B`` independent problems at once with per-sample status;
:mod:`torchface.solver.robust` gives the robust losses and their IRLS weights.
"""

from __future__ import annotations

from torchface.solver.least_squares import (
    ResidualFn,
    SolveResult,
    SolverConfig,
    SolverMethod,
    SolveStatus,
    least_squares,
    solve_normal_equations,
)
from torchface.solver.robust import MAD_TO_SIGMA, RobustKind, RobustLoss, SwitchedRobustLoss, robust_scale

__all__ = [
    "MAD_TO_SIGMA",
    "ResidualFn",
    "RobustKind",
    "RobustLoss",
    "SolveResult",
    "SolveStatus",
    "SolverConfig",
    "SolverMethod",
    "SwitchedRobustLoss",
    "least_squares",
    "robust_scale",
    "solve_normal_equations",
]
