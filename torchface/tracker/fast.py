"""The fast per-frame solver: Levenberg-Marquardt on a local twist, over a face crop (paper Eq. 14-20).

The paper linearises the rigid motion in twist form around the current estimate (Eq. 14-17). Here each
iteration solves for a left increment ``(d_omega, d_t)`` of the camera-frame pose,
``X_cam <- exp(hat(d_omega)) X_cam + d_t``, together with additive increments of the animation units and
the illumination parameters; the rotation is then updated as ``R <- exp(hat(d_omega)) R`` and
``t <- exp(hat(d_omega)) t + d_t``. With ``g = dI/dX_cam`` the Jacobian columns are

    ``dI/d(d_omega) = X_cam x g``,  ``dI/d(d_t) = g``,  ``dI/d(alpha_j) = g . (R B_j)``,  ``-B^light_i``,

which avoid the Jacobian of the exponential map at a general rotation (used by the reference path,
:func:`torchface.tracker.objective.frame_residuals`, which :mod:`tests` check against this one).
Weighted normal equations with Tukey/Huber/... IRLS weights (robust scale: MAD of the current residuals,
floored), a Gaussian prior on the animation units, box bounds by projection, and Levenberg-Marquardt step
acceptance (a step that raises the robust cost is undone and retried with more damping). Everything is
batched over streams; the host synchronises only for the early-exit and step-rejection tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from torchface.conventions import NEAR_PLANE_MM
from torchface.solver.robust import MAD_TO_SIGMA, RobustLoss
from torchface.template.points import Template


@dataclass(frozen=True)
class LevelCamera:
    """Pinhole camera of one pyramid level of a per-stream crop.

    Attributes:
        fx, fy, cx, cy: the level's intrinsics in full-image coordinates of that level.
        offset: ``(B, 2)`` the crop's top-left pixel (level coordinates), subtracted after projection.
        height, width: size of the crop at this level.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    offset: Tensor
    height: int
    width: int


def exp_so3(w: Tensor) -> Tensor:
    """Rodrigues' formula for ``(B, 3)`` rotation vectors (exact, finite at zero) -> ``(B, 3, 3)``."""
    theta2 = (w * w).sum(-1, keepdim=True).unsqueeze(-1)  # (B, 1, 1)
    small = theta2 < 1e-8
    theta = theta2.clamp_min(1e-8).sqrt()
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-8))
    zero = torch.zeros_like(w[:, 0])
    K = torch.stack(
        [zero, -w[:, 2], w[:, 1], w[:, 2], zero, -w[:, 0], -w[:, 1], w[:, 0], zero], dim=-1
    ).reshape(-1, 3, 3)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a * K + b * (K @ K)


def _masked_median_abs(r: Tensor, valid: Tensor) -> Tensor:
    """``(B,)`` median of ``|r|`` over valid entries (1 where a row has none)."""
    x = torch.where(valid, r.abs(), torch.full_like(r, float("nan")))
    med = torch.nanmedian(x, dim=-1).values
    return torch.nan_to_num(med, nan=1.0)


@dataclass(frozen=True)
class LevelOutcome:
    """Diagnostics of :func:`solve_level` at its final estimate."""

    residual: Tensor  # (B, N)
    valid: Tensor  # (B, N)
    sampled: Tensor  # (B, N) frame intensities at the points
    iterations: Tensor  # (B,) int64
    converged: Tensor  # (B,) bool
    finite: Tensor  # (B,) bool


def linearise(
    tpl: Template,
    image: Tensor,
    cam: LevelCamera,
    R: Tensor,
    t: Tensor,
    alpha: Tensor,
    light: Tensor,
    light_basis: Tensor,
    mask: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Residuals ``r (B, N)``, local Jacobian ``J (B, N, P)``, validity ``(B, N)`` and sampled intensities.

    Columns of ``J``: ``d_omega (3)``, ``d_t (3)``, ``alpha (A)``, ``light (L)`` (see the module docstring).
    ``image`` is ``(B, 3, h, w)``: gray level, ``d/du``, ``d/dv`` of the crop at this level.
    """
    B, N = tpl.valid.shape
    Xm = tpl.points + torch.bmm(tpl.basis.reshape(B, N * 3, -1), alpha.unsqueeze(-1)).reshape(B, N, 3)
    Xc = torch.matmul(Xm, R.transpose(1, 2)) + t.unsqueeze(1)
    X, Y, Z = Xc.unbind(-1)
    front = Z > NEAR_PLANE_MM
    iz = 1.0 / Z.clamp_min(NEAR_PLANE_MM)
    u = cam.fx * X * iz + (cam.cx - cam.offset[:, 0:1])
    v = cam.fy * Y * iz + (cam.cy - cam.offset[:, 1:2])
    h, w = cam.height, cam.width
    grid = torch.stack([u * (2.0 / max(w - 1, 1)) - 1.0, v * (2.0 / max(h - 1, 1)) - 1.0], dim=-1)
    vals = F.grid_sample(image, grid.unsqueeze(1), mode="bilinear", padding_mode="border", align_corners=True)
    vals = vals.squeeze(2)  # (B, 3, N)
    intensity, gu, gv = vals[:, 0], vals[:, 1], vals[:, 2]
    r = intensity - tpl.intensity - torch.matmul(light_basis, light.unsqueeze(-1)).squeeze(-1)
    gX = cam.fx * gu * iz
    gY = cam.fy * gv * iz
    gZ = -(gX * X + gY * Y) * iz
    g = torch.stack([gX, gY, gZ], dim=-1)  # dI/dX_cam (B, N, 3)
    j_rot = torch.linalg.cross(Xc, g, dim=-1)
    g_model = torch.matmul(g, R)  # (B, N, 3)
    j_anim = (g_model.unsqueeze(-1) * tpl.basis).sum(-2)
    J = torch.cat([j_rot, g, j_anim, -light_basis], dim=-1)
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    n_cam = torch.matmul(tpl.normals, R.transpose(1, 2))
    facing = (n_cam * Xc).sum(-1) < 0
    valid = mask & front & inside & facing
    return r, J, valid, intensity


def _weights(r: Tensor, valid: Tensor, robust: RobustLoss | None, scale_floor: float) -> tuple[Tensor, Tensor]:
    """IRLS weights ``(B, N)`` (zero where invalid) and the robust scale ``(B, 1)``."""
    s = (MAD_TO_SIGMA * _masked_median_abs(r, valid)).clamp_min(scale_floor).unsqueeze(-1)
    w = valid.to(r.dtype)
    if robust is not None:
        w = w * robust.weight(r, s)
    return w, s


def _cost(r: Tensor, valid: Tensor, robust: RobustLoss | None, s: Tensor) -> Tensor:
    """``(B,)`` robust cost ``sum rho(r; s)`` over valid points (``r**2 / 2`` without a robust loss)."""
    rho = 0.5 * r * r if robust is None else robust.rho(r, s)
    return torch.where(valid, rho, torch.zeros_like(rho)).sum(-1)


def _select(keep: Tensor, new: tuple[Tensor, ...], old: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
    """Per sample, ``new`` where ``keep (B,)`` else ``old`` (tensors of any shape with leading ``B``)."""
    return tuple(torch.where(keep.view(-1, *([1] * (n.dim() - 1))), n, o) for n, o in zip(new, old))


def solve_level(
    tpl: Template,
    image: Tensor,
    cam: LevelCamera,
    R: Tensor,
    t: Tensor,
    alpha: Tensor,
    light: Tensor,
    light_basis: Tensor,
    mask: Tensor,
    *,
    iterations: int,
    free: Tensor,
    alpha_lower: Tensor,
    alpha_upper: Tensor,
    alpha_prior: float,
    robust: RobustLoss | None,
    scale_floor: float = 0.02,
    damping: float = 1e-3,
    final_check: bool = True,
    step_tolerance: float | tuple[float, float, float] = (2e-4, 0.05, 2e-3),
) -> tuple[Tensor, Tensor, Tensor, Tensor, LevelOutcome]:
    """Levenberg-Marquardt iterations at one pyramid level for every stream at once.

    Each iteration linearises at the current estimate; a step that raised the robust cost (compared at the
    scale of the last accepted estimate) is undone and retried from the last accepted linearisation with ten
    times the damping, an accepted one divides the damping by three. The damping is relative to ``diag(H)``
    with an absolute floor, so a parameter that no point constrains (an animation unit moving no visible
    point) stays put instead of making the system singular.

    Args:
        tpl: the level's template (``N`` points); image: ``(B, 3, h, w)`` gray + gradients of the crop.
        cam: the level camera; R ``(B, 3, 3)``, t ``(B, 3)``, alpha ``(B, A)``, light ``(B, L)``: the start.
        light_basis: ``(B, N, L)``; mask: ``(B, N)`` usable points (template validity, visibility).
        iterations: the most linearisations; free: ``(P,)`` bool, the parameters that may change (ablations).
        alpha_lower, alpha_upper: ``(A,)`` bounds; alpha_prior: precision of a zero-mean prior on alpha.
        robust: IRLS loss or None; scale_floor: lower bound of the robust scale (intensity units), so that
            on clean frames legitimate appearance change (expression) is not rejected as an outlier.
        damping: initial Levenberg damping relative to ``diag(H)``.
        final_check: linearise once more after the last step, to undo it where it raised the cost and to
            report the outcome there; without it (an intermediate pyramid level, whose result the next level
            checks) the outcome describes the last linearisation.
        step_tolerance: converged when every increment is below these: rotation (radians), translation
            (millimetres), animation and illumination coefficients (units); one float applies to all.

    Returns:
        The new ``R, t, alpha, light`` and a :class:`LevelOutcome`.
    """
    B, N = mask.shape
    A = alpha.shape[1]
    P = 6 + A + light.shape[1]
    dtype, device = R.dtype, R.device
    freef = free.to(dtype)
    prior = torch.zeros(P, dtype=dtype, device=device)
    prior[6 : 6 + A] = alpha_prior
    prior = prior * freef
    fixed_diag = torch.diag(1.0 - freef)
    iters = torch.zeros(B, dtype=torch.int64, device=device)
    active = torch.ones(B, dtype=torch.bool, device=device)
    finite = torch.ones(B, dtype=torch.bool, device=device)
    lam = torch.full((B, 1, 1), damping, dtype=dtype, device=device)
    if isinstance(step_tolerance, (int, float)):
        step_tolerance = (float(step_tolerance),) * 3
    tol = torch.cat([
        torch.full((3,), step_tolerance[0], dtype=dtype, device=device),
        torch.full((3,), step_tolerance[1], dtype=dtype, device=device),
        torch.full((P - 6,), step_tolerance[2], dtype=dtype, device=device),
    ])
    best = None  # (R, t, alpha, light, H, grad, cost, s) of the last accepted estimate
    for _ in range(iterations):
        r, J, valid, _ = linearise(tpl, image, cam, R, t, alpha, light, light_basis, mask)
        # A non-finite frame makes r non-finite; a non-finite J without r (impossible by construction) would
        # make the system non-finite and the sample fail below rather than corrupt another sample.
        valid = valid & torch.isfinite(r)
        r = torch.where(valid, r, torch.zeros_like(r))
        J = torch.where(valid.unsqueeze(-1), J, torch.zeros_like(J)) * freef
        if best is None:
            wgt, s = _weights(r, valid, robust, scale_floor)
            cost = _cost(r, valid, robust, s) + 0.5 * (prior[6 : 6 + A] * alpha * alpha).sum(-1)
            accept = torch.ones(B, dtype=torch.bool, device=device)
        else:
            cost = _cost(r, valid, robust, best[7]) + 0.5 * (prior[6 : 6 + A] * alpha * alpha).sum(-1)
            accept = (cost <= best[6]) & torch.isfinite(cost)
            wgt, s = _weights(r, valid, robust, scale_floor)
            cost = _cost(r, valid, robust, s) + 0.5 * (prior[6 : 6 + A] * alpha * alpha).sum(-1)
        Jw = J * wgt.unsqueeze(-1)
        H = torch.matmul(Jw.transpose(1, 2), J)
        grad = torch.matmul((wgt * r).unsqueeze(1), J).squeeze(1)
        grad = grad + torch.cat([grad.new_zeros(B, 6), prior[6 : 6 + A] * alpha, grad.new_zeros(B, P - 6 - A)], -1)
        H = H + torch.diag(prior)
        if best is not None:
            a3 = accept.view(B, 1, 1)
            if not bool(accept.all()):  # undo rejected steps (one host sync; most steps are accepted)
                R, t, alpha, light, H, grad, cost, s = _select(accept, (R, t, alpha, light, H, grad, cost, s), best)
            lam = torch.where(a3, (lam / 3.0).clamp_min(1e-6), lam * 10.0)
        best = (R, t, alpha, light, H, grad, cost, s)
        diag = torch.diagonal(H, dim1=1, dim2=2)
        floor = 1e-6 * diag.amax(-1, keepdim=True).clamp_min(1e-12)
        Hd = H + lam * torch.diag_embed(diag + floor) + fixed_diag
        L, info = torch.linalg.cholesky_ex(Hd)
        delta = -torch.cholesky_solve(grad.unsqueeze(-1), L).squeeze(-1)
        good = (info == 0) & torch.isfinite(delta).all(-1) & (valid.sum(-1) >= P)
        finite = finite & (good | ~active)
        step = active & good
        delta = torch.where(step.unsqueeze(-1), delta * freef, torch.zeros_like(delta))
        dR = exp_so3(delta[:, 0:3])
        R = torch.matmul(dR, R)
        t = torch.matmul(dR, t.unsqueeze(-1)).squeeze(-1) + delta[:, 3:6]
        alpha = torch.minimum(torch.maximum(alpha + delta[:, 6 : 6 + A], alpha_lower), alpha_upper)
        light = light + delta[:, 6 + A :]
        iters = iters + active.to(torch.int64)
        small = (delta.abs() < tol).all(-1) & step
        active = active & ~small & good
        if not bool(active.any()):
            break
    if not final_check:
        outcome = LevelOutcome(r, valid, torch.zeros_like(r), iters, ~active & finite, finite)
        return R, t, alpha, light, outcome
    r, _, valid, sampled = linearise(tpl, image, cam, R, t, alpha, light, light_basis, mask)
    if best is not None:
        # The last step is kept only where it did not raise the cost.
        cost = _cost(torch.where(valid, r, torch.zeros_like(r)), valid, robust, best[7])
        cost = cost + 0.5 * (prior[6 : 6 + A] * alpha * alpha).sum(-1)
        accept = (cost <= best[6]) & torch.isfinite(cost)
        if not bool(accept.all()):
            R, t, alpha, light = _select(accept, (R, t, alpha, light), best[:4])
            r, _, valid, sampled = linearise(tpl, image, cam, R, t, alpha, light, light_basis, mask)
    outcome = LevelOutcome(r, valid & torch.isfinite(r), sampled, iters, ~active & finite, finite)
    return R, t, alpha, light, outcome
