"""The fast per-frame solver: Levenberg-Marquardt on a local twist, over a face crop (paper Eq. 14-20).

The paper linearises the rigid motion in twist form around the current estimate (Eq. 14-17). Here each
iteration solves for an increment ``(d_omega, d_t)`` of the pose that turns the head about its own origin,
``X_cam <- exp(hat(d_omega)) R X + t + d_t`` (``X`` in the head frame), together with additive increments of the
animation units and the illumination parameters; the pose is then updated as ``R <- exp(hat(d_omega)) R`` and
``t <- t + d_t``. With ``g = dI/dX_cam`` the Jacobian columns are

    ``dI/d(d_omega) = (R X) x g``,  ``dI/d(d_t) = g``,  ``dI/d(alpha_j) = g . (R B_j)``,  ``-B^light_i``,

which avoid the Jacobian of the exponential map at a general rotation (used by the reference path,
:func:`torchface.tracker.objective.frame_residuals`, which :mod:`tests` check against this one). Turning about the
head rather than the camera keeps rotation and translation nearly decoupled: a turn about the camera centre moves
the head sideways by ``d_omega x t`` (``|t|`` is half a metre), which the translation had to undo in the same
step; measured on the 640x480 scenarios (evaluate.py) it took 5% fewer iterations and the occlusion scenario's
worst frame went from 6.4 to 5.1 degrees.
Weighted normal equations with Tukey/Huber/... IRLS weights (robust scale: MAD of the current residuals,
floored), a Gaussian prior on the animation units, box bounds on them (an active set: a unit at a bound that the
data push outward is held out of the step; the step is then clipped to the bounds), and Levenberg-Marquardt step
acceptance (a step that raises the robust cost is undone and retried with more damping). Everything is
batched over streams; the host synchronises only for the early-exit and step-rejection tests.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import torch
from torch import Tensor

from torchface import _native
from torchface._deterministic import grid_sample_border, nanmedian_values
from torchface._scalar import isfinite, scalar
from torchface.backend import Backend, use_native
from torchface.conventions import NEAR_PLANE_MM
from torchface.geometry.so3 import axis_angle_to_matrix
from torchface.solver.least_squares import _usable_bounds
from torchface.solver.robust import MAD_TO_SIGMA, RobustLoss, SwitchedRobustLoss
from torchface.template.points import Template

if TYPE_CHECKING:
    from torchface.tracker.step import StepWorkspace


#: Default convergence test of :func:`solve_level`: every increment below these, rotation (radians), translation
#: (millimetres), animation and illumination coefficients (units), at full resolution.
STEP_TOLERANCE: tuple[float, float, float] = (2e-4, 0.05, 2e-3)

#: Where :func:`solve_level` takes an animation unit to be at a bound, as a fraction of its range: within
#: ``BOUND_MARGIN * (upper - lower)`` of it (the native solver's ``TF_BOUND_MARGIN``).
BOUND_MARGIN: float = 1e-6

#: Default second convergence test of :func:`solve_level`: the step's predicted cost decrease (of the
#: linearised, reweighted problem) below this fraction of the cost.
FUNCTION_TOLERANCE: float = 3e-3


@dataclass(frozen=True, eq=False)
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


def _masked_median_abs(r: Tensor, valid: Tensor) -> Tensor:
    """``(B,)`` median of ``|r|`` over valid entries (1 where a row has none)."""
    x = torch.where(valid, r.abs(), scalar(float("nan"), r))
    med = nanmedian_values(x, dim=-1)
    return torch.nan_to_num(med, nan=1.0)


@dataclass(frozen=True, eq=False)
class LevelOutcome:
    """Diagnostics of :func:`solve_level` at its final estimate."""

    residual: Tensor  # (B, N)
    valid: Tensor  # (B, N)
    sampled: Tensor  # (B, N) frame intensities at the points
    iterations: Tensor  # (B,) int64
    converged: Tensor  # (B,) bool
    finite: Tensor  # (B,) bool
    #: :func:`linearise`'s output ``(r, J, valid, sampled)`` at the final estimate (with ``final_check`` and
    #: ``keep_linearisation``), for a following pass at the same level to start from (``solve_level(start=...)``).
    linearisation: tuple[Tensor, Tensor, Tensor, Tensor] | None = None
    #: The level's :class:`_LevelConstants`, for such a pass to reuse (``solve_level(constants=...)``): the torch
    #: code's; the native solver, which reads the template alone, hands on those it was given (None: none made).
    constants: _LevelConstants | None = None


@dataclass(frozen=True, eq=False)
class _LevelConstants:
    """What :func:`linearise` needs from the camera and the template, computed once per level (not per iteration).

    ``grid = xy * grid_scale + grid_shift`` maps normalised image coordinates ``xy = (X/Z, Y/Z)`` to
    ``grid_sample``'s ``[-1, 1]`` coordinates of the crop, for each point and its four neighbours one pixel away
    (:data:`_STENCIL`: ``grid_shift`` holds the five offsets); ``half_focal`` turns the neighbours' differences
    ``I(u + 1) - I(u - 1), I(v + 1) - I(v - 1)`` into ``d/dx, d/dy``.
    The template's points, normals and expression basis are kept point-last (``(B, 3, N)``, ``(B, A, 3, N)``), the
    layout of the Jacobian :func:`linearise` builds (``(B, P, N)``): every per-point product then runs along
    contiguous rows of ``N`` values. Point-first (``(B, N, P)``), each row is one point's 11 animation or 22
    parameter columns and a broadcast factor repeats per row: measured at one stream, 1500 points, the animation
    columns' multiply-adds took 26 instead of 3 microseconds each, and the IRLS masking and weighting of ``J``
    25 and 8 microseconds.
    """

    half_focal: Tensor  # (1, 2, 1)
    grid_scale: Tensor  # (1, 2, 1, 1)
    grid_shift: Tensor  # (B, 2, 5, 1)
    points_t: Tensor  # (B, 3, N)
    normals_t: Tensor  # (B, 3, N)
    basis_t: Tensor  # (B, A, 3, N)
    # Views of the above in the shapes linearise uses, made once per level rather than at every linearisation
    # (each view is one more dispatched operation: on a GPU at one stream, the dispatches are the step's time).
    point_shift: Tensor  # (B, 2, 1, 1) grid_shift's first column: the points alone, without the stencil
    points_flat: Tensor  # (B, 1, 3 N)
    basis_flat: Tensor  # (B, A, 3 N)
    basis_xyz: tuple[Tensor, Tensor, Tensor]  # basis_t's x, y and z rows, (B, A, N) each


#: Where :func:`linearise` samples the image, in pixels from each point: the point, then ``+u``, ``+v``, ``-u``,
#: ``-v`` (``(2, 5)``: rows u and v).
_STENCIL: tuple[tuple[float, ...], tuple[float, ...]] = ((0.0, 1.0, 0.0, -1.0, 0.0), (0.0, 0.0, 1.0, 0.0, -1.0))


@functools.lru_cache(maxsize=64)
def _camera_constants(
    fx: float, fy: float, cx: float, cy: float, width: int, height: int, dtype: torch.dtype, device: torch.device
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """What :func:`_level_constants` takes from a level camera's intrinsics alone (not its per-stream offsets):
    ``centre (2,)``, ``to_grid (2,)``, ``stencil (2, 5)``, ``half_focal`` and ``grid_scale``. Cached per camera
    (a tracked video's levels keep theirs), made outside inference mode as :mod:`torchface._scalar`'s constants
    are; never modified in place."""
    with torch.inference_mode(False):
        focal = torch.tensor([fx, fy], dtype=dtype, device=device)
        to_grid = torch.tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)], dtype=dtype, device=device)
        centre = torch.tensor([cx, cy], dtype=dtype, device=device)
        stencil = torch.tensor(_STENCIL, dtype=dtype, device=device) * to_grid.unsqueeze(-1)  # (2, 5)
        return centre, to_grid, stencil, (0.5 * focal).view(1, 2, 1), (focal * to_grid).view(1, 2, 1, 1)


def _level_constants(cam: LevelCamera, like: Tensor, tpl: Template) -> _LevelConstants:
    dtype, device = like.dtype, like.device
    centre, to_grid, stencil, half_focal, grid_scale = _camera_constants(
        cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, dtype, device
    )
    shift = (centre - cam.offset.to(dtype)) * to_grid - 1.0  # (B, 2)
    grid_shift = (shift.unsqueeze(-1) + stencil).unsqueeze(-1)
    points_t, normals_t, basis_t = tpl.point_last
    B, A, _, N = basis_t.shape
    return _LevelConstants(
        half_focal, grid_scale, grid_shift, points_t, normals_t, basis_t, grid_shift[:, :, :1],
        points_t.view(B, 1, 3 * N), basis_t.view(B, A, 3 * N), cast("tuple[Tensor, Tensor, Tensor]", basis_t.unbind(2)),
    )  # fmt: skip


@functools.lru_cache(maxsize=64)
def _solver_constants(
    free: tuple[bool, ...], num_animation: int, alpha_prior: float, step_tolerance: tuple[float, float, float],
    dtype: torch.dtype, device: torch.device,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`solve_level`'s constants for a float prior precision (one for every stream), in this order: the
    prior's animation part and half of it ``(A,)``, the prior's Hessian term ``(P, P)``, the fixed parameters'
    unit diagonal ``(P, P)``, the free mask as a ``(P, 1)`` bool column and as ``(P,)``, and the step tolerances
    ``(P,)``. Cached per setting, made outside inference mode; never modified in place."""
    P, A = len(free), num_animation
    with torch.inference_mode(False):
        free_mask = torch.tensor(free, dtype=torch.bool, device=device)
        freef = free_mask.to(dtype)
        prior = torch.zeros(P, dtype=dtype, device=device)
        prior[6 : 6 + A] = alpha_prior
        prior = prior * freef
        prior_alpha = prior[..., 6 : 6 + A]
        tol = torch.cat([
            torch.full((3,), step_tolerance[0], dtype=dtype, device=device),
            torch.full((3,), step_tolerance[1], dtype=dtype, device=device),
            torch.full((P - 6,), step_tolerance[2], dtype=dtype, device=device),
        ])  # fmt: skip
        return (prior_alpha, 0.5 * prior_alpha, torch.diag_embed(prior), torch.diag(1.0 - freef),
                free_mask.unsqueeze(-1), free_mask, tol)  # fmt: skip


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
    constants: _LevelConstants | None = None,
    neg_light_basis_t: Tensor | None = None,
    jacobian: bool = True,
    holes: Tensor | None = None,
) -> tuple[Tensor, Tensor | None, Tensor, Tensor]:
    """Residuals ``r (B, N)``, local Jacobian ``J (B, N, P)``, validity ``(B, N)`` and sampled intensities.

    Columns of ``J``: ``d_omega (3)``, ``d_t (3)``, ``alpha (A)``, ``light (L)`` (see the module docstring).
    ``J`` is the transpose of a contiguous ``(B, P, N)`` tensor (``J.transpose(1, 2)`` is that tensor).
    ``image`` is ``(B, 1, h, w)``, the gray crop at this level. The image gradient at a point is the central
    difference of the bilinearly interpolated image one pixel either side, ``(I(u + 1) - I(u - 1)) / 2``: the
    same value as bilinear interpolation of the central-difference gradient image
    (:func:`~torchface.appearance.sampling.image_with_gradients`, the reference path's), by the linearity of the
    interpolation, and at the crop's border too (the sampler clamps as that image replicates). Sampling five
    points of the gray crop instead of one point of a three-channel image spares building the gradient images:
    at B = 128 and a 480x520 crop that took about 1 ms per stream-frame. ``constants`` and ``neg_light_basis_t``
    (``-light_basis`` as a contiguous ``(B, L, N)``) may be passed to reuse them across iterations. With
    ``jacobian`` False only the points themselves are sampled and ``J`` is None (a step's cost check).
    ``holes``: the level's image with its non-finite (missing) pixels, when ``image`` is that image with 0 there
    (:func:`solve_level` under autograd): the points whose samples touch a hole are left out as they are without
    it, and the sampled ``intensity`` is NaN there as it is without it, while everything autograd goes through is
    finite.
    """
    B, N = tpl.valid.shape
    if image.shape[1] != 1:
        raise ValueError(f"image must be the (B, 1, h, w) gray crop, got {tuple(image.shape)}")
    k = _level_constants(cam, R, tpl) if constants is None else constants
    nlb = -light_basis.transpose(1, 2) if neg_light_basis_t is None else neg_light_basis_t  # (B, L, N)
    A, L = k.basis_t.shape[1], nlb.shape[1]
    Xm = torch.baddbmm(k.points_flat, alpha.unsqueeze(1), k.basis_flat).view(B, 3, N)
    Xr = torch.bmm(R, Xm)  # turned about the head's origin, (B, 3, N)
    Xc = Xr + t.unsqueeze(-1)
    Z = Xc[:, 2]
    front = Z > scalar(NEAR_PLANE_MM, Z)
    iz = Z.clamp_min(NEAR_PLANE_MM).reciprocal().unsqueeze(1)  # (B, 1, N)
    xy = Xc[:, :2] * iz  # (B, 2, N)
    shift = k.grid_shift if jacobian else k.point_shift  # the stencil, or the points alone
    grid = torch.addcmul(shift, xy.unsqueeze(2), k.grid_scale)  # (B, 2, 5 or 1, N) in [-1, 1] inside the crop
    vals = grid_sample_border(image, grid.permute(0, 2, 3, 1)).view(B, -1, N)
    intensity = vals[:, 0]
    r = torch.baddbmm((intensity - tpl.intensity).unsqueeze(1), light.unsqueeze(1), nlb).view(B, N)
    inside = (grid[:, :, 0].abs() <= scalar(1.0, grid)).all(1)
    facing = (torch.bmm(R, k.normals_t) * Xc).sum(1) < scalar(0.0, Xc)
    valid = mask & front & inside & facing
    if holes is not None:  # the samples the image with its holes gives, for the masks and the reported intensity
        with torch.no_grad():
            seen = grid_sample_border(holes, grid.detach().permute(0, 2, 3, 1)).view(B, -1, N)
        valid = valid & isfinite(seen.sum(1))  # (without holes: r is not finite there, or the stencil, below)
        intensity = torch.where(isfinite(seen[:, 0]), intensity, seen[:, 0])
    if not jacobian:
        return r, None, valid, intensity
    # A point whose gradient stencil touches a non-finite pixel (r itself may be finite) is left out: its Jacobian
    # row would make the sample's normal equations non-finite (one NaN pixel failed the whole frame).
    valid = valid & isfinite(vals.sum(1))  # the sum: one test per point (as the native solver's)
    # Without autograd each row block is written into one (B, P, N) tensor where it is computed; out= arguments do
    # not support autograd, so a differentiable call (an input requires grad) computes the same blocks and
    # concatenates them.
    differentiable = torch.is_grad_enabled() and any(
        x.requires_grad for x in (image, R, t, alpha, light, light_basis, nlb, tpl.points, tpl.basis, tpl.intensity)
    )
    Jt = None if differentiable else torch.empty(B, 6 + A + L, N, dtype=r.dtype, device=r.device)

    def block(first: int, stop: int) -> Tensor | None:
        return None if Jt is None else Jt[:, first:stop]

    gxy = torch.mul((vals[:, 1:3] - vals[:, 3:5]).mul_(k.half_focal), iz, out=block(3, 5))  # dI/dX, dI/dY (B, 2, N)
    gz = torch.sum(gxy * xy, 1, keepdim=True, out=block(5, 6)).neg_()
    g = torch.cat([gxy, gz], dim=1) if Jt is None else Jt[:, 3:6]  # dI/dX_cam (B, 3, N)
    j_rot = torch.linalg.cross(Xr, g, dim=1, out=block(0, 3))
    # dI/dX_cam turned into the head frame: its x, y and z rows, (B, 1, N) each
    mx, my, mz = torch.bmm(R.transpose(1, 2), g).unsqueeze(2).unbind(1)
    bx, by, bz = k.basis_xyz
    j_anim = torch.mul(bx, mx, out=block(6, 6 + A))
    if Jt is None:
        j_anim = torch.addcmul(torch.addcmul(j_anim, by, my), bz, mz)
        Jt = torch.cat([j_rot, g, j_anim, nlb], dim=1)
    else:
        j_anim.addcmul_(by, my).addcmul_(bz, mz)
        Jt[:, 6 + A :] = nlb
    return r, Jt.transpose(1, 2), valid, intensity


def robust_scale_of(r: Tensor, valid: Tensor, scale_floor: float) -> Tensor:
    """``(B, 1)`` the IRLS robust scale of residuals ``r (B, N)``: ``1.4826 * median |r|`` over ``valid (B, N)``,
    floored at ``scale_floor``."""
    med = _masked_median_abs(r, valid)
    return (scalar(MAD_TO_SIGMA, med) * med).clamp_min(scale_floor).unsqueeze(-1)


def _weights(
    r: Tensor, valid: Tensor, robust: RobustLoss | SwitchedRobustLoss | None, scale_floor: float,
    judge_scale: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """IRLS weights ``(B, N)`` (zero where invalid), the robust scale ``(B, 1)`` (:func:`robust_scale_of`), the
    cost ``(B,)`` at that scale (:func:`_cost`) and, with ``judge_scale`` ``(B, 1)``, the cost at that scale (else
    None). The two costs are one pass over ``(2, B, N)``: the same values as two, in fewer (dispatched)
    operations."""
    s = robust_scale_of(r, valid, scale_floor)
    w = valid.to(r.dtype)
    if robust is None:
        return w, s, _cost(r, None, s), None if judge_scale is None else _cost(r, None, judge_scale)
    if judge_scale is None:
        rho, rw = robust.rho_and_weight(r, s)
        return w * rw, s, rho.sum(-1), None
    rho, rw = robust.rho_and_weight(r.expand(2, *r.shape), torch.stack((judge_scale, s)))
    judged, cost = rho.sum(-1).unbind(0)
    return w * rw[1], s, cost, judged


def _cost(r: Tensor, robust: RobustLoss | SwitchedRobustLoss | None, s: Tensor) -> Tensor:
    """``(B,)`` robust cost ``sum rho(r; s)`` (``r**2 / 2`` without a robust loss); ``r`` is 0 where invalid
    (``rho(0) = 0``, so invalid points add nothing)."""
    rho = scalar(0.5, r) * r * r if robust is None else robust.rho(r, s)
    return rho.sum(-1)


def _select(keep: Tensor, new: tuple[Tensor, ...], old: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
    """Per sample, ``new`` where ``keep (B,)`` else ``old`` (tensors of any shape with leading ``B``)."""
    return tuple(torch.where(keep.view(-1, *([1] * (n.dim() - 1))), n, o) for n, o in zip(new, old))


def _bounds_valid(lower: Tensor, upper: Tensor) -> Tensor:
    """``()`` bool on the bounds' device, without a host read: every animation bound pair ``(A,)`` is usable
    (``torchface.solver.least_squares._usable_bounds``: no NaN, ``lower <= upper``, ``lower < inf`` and
    ``upper > -inf``)."""
    return cast(Tensor, _usable_bounds(lower, upper)).all()


#: The most bound values (lower and upper together) :func:`_check_bounds` reads as lists on the host; more are
#: checked elementwise first.
_LIST_CHECK_VALUES: int = 64


def _check_bounds(lower: Tensor, upper: Tensor) -> None:
    """Raise ``ValueError`` naming the first animation unit whose bounds ``(A,)`` or ``(B, A)`` are not usable (one
    host read where they are; more to name it where not). A model's ``(A,)`` bounds on the host are read as lists at
    once (a few microseconds; the elementwise check costs about 15 per call, and the native solver checks at every
    call); per-stream bounds with more than :data:`_LIST_CHECK_VALUES` values elementwise first (at 128 streams, 11
    units, the lists' loop took 0.3-0.7 ms per call, four calls a step)."""
    if (
        not lower.is_cpu or not upper.is_cpu or lower.numel() + upper.numel() > _LIST_CHECK_VALUES
    ) and bool(_bounds_valid(lower, upper)):
        return
    A = lower.shape[-1]
    lo, hi = lower.reshape(-1).tolist(), upper.reshape(-1).tolist()  # (from any device; tolist ignores autograd)
    inf = float("inf")
    for i, (a, b) in enumerate(zip(lo, hi)):
        if not (a <= b and a < inf and b > -inf):
            j = i % A  # (per-stream bounds (B, A): the unit of row-major index i)
            raise ValueError(
                "alpha_lower and alpha_upper must be bounds, lower <= upper, neither NaN, a lower bound below inf and "
                f"an upper above -inf (-inf / inf: none on that side), got [{a}, {b}] for animation unit {j}"
            )


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
    alpha_prior: float | Tensor,
    robust: RobustLoss | SwitchedRobustLoss | None,
    alpha_mean: Tensor | None = None,
    scale_floor: float = 0.02,
    damping: float = 1e-3,
    final_check: bool = True,
    step_tolerance: float | tuple[float, float, float] = STEP_TOLERANCE,
    function_tolerance: float = FUNCTION_TOLERANCE,
    start: tuple[Tensor, Tensor, Tensor, Tensor] | None = None,
    constants: _LevelConstants | None = None,
    keep_linearisation: bool = True,
    backend: Backend = Backend.AUTO,
    workspace: StepWorkspace | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, LevelOutcome]:
    """Levenberg-Marquardt iterations at one pyramid level for every stream at once.

    Each iteration linearises at the current estimate; a step that raised the robust cost (compared at the
    scale of the last accepted estimate) is undone and retried from the last accepted linearisation with ten
    times the damping, an accepted one divides the damping by three. The damping is relative to ``diag(H)``
    with an absolute floor, so a parameter that no point constrains (an animation unit moving no visible
    point) stays put instead of making the system singular.

    The animation units' bounds are kept by an active set: before each solve, a unit at a bound (within
    :data:`BOUND_MARGIN` of its range; exactly at it where the range is infinite) that the gradient pushes outward
    (at the lower bound ``grad > 0``, at the upper ``grad < 0``) is held there: its row and column of the damped
    matrix become the identity's and its right-hand side 0, so its step is 0 and the other parameters' step is the
    one with it fixed (as for a parameter that is not ``free``). A unit the step then takes past a bound is clipped
    to it. Clipping the free step alone moved the others as if a unit on its bound had gone past it: with coupled
    units (CANDIDE-3's three eyelid units move the lid's points nearly alike) a wrong step, and a level that ended
    away from the constrained optimum. Measured on the 640x480 standard scenarios (evaluate.py; CANDIDE-3's lid
    tightener is held at its lower bound in about a third of the iterations of ``expressions``): the rotation means
    moved by -0.07 to +0.004 degree (occlusion 0.50 -> 0.42, its worst frame 5.57 -> 3.09; scan_motion 0.83 -> 0.76,
    its worst 3.00 -> 3.12), the iterations per frame by +0.1% to +1.2%.

    Args:
        tpl: the level's template (``N`` points); image: ``(B, 1, h, w)`` the gray crop at this level.
        cam: the level camera; R ``(B, 3, 3)``, t ``(B, 3)``, alpha ``(B, A)``, light ``(B, L)``: the start.
        light_basis: ``(B, N, L)``; mask: ``(B, N)`` usable points (template validity, visibility).
        iterations: the most linearisations; free: ``(P,)`` bool, the parameters that may change (ablations).
        alpha_lower, alpha_upper: ``(A,)`` bounds, or ``(B, A)`` per stream (``-inf`` / ``inf``: none on that side),
            ``lower <= upper`` (``ValueError`` for another shape, a NaN, ``lower > upper`` or a lower bound at ``inf``,
            an upper at ``-inf``; the torch code finds the values' errors at its first host read, after the first
            linearisation, so that checking them costs no synchronisation of its own); alpha_prior: precision of a
            Gaussian prior on alpha, centred on ``alpha_mean`` ``(B, A)`` (None: zero); a float, ``(B,)`` for one
            precision per stream, or ``(B, A)`` for one per stream and unit.
        robust: IRLS loss or None; scale_floor: lower bound of the robust scale (intensity units), so that
            on clean frames legitimate appearance change (expression) is not rejected as an outlier.
        damping: initial Levenberg damping relative to ``diag(H)``.
        final_check: linearise once more after the last step, to undo it where it raised the cost and to
            report the outcome there; without it (an intermediate pyramid level, whose result the next level
            checks) the outcome describes the last linearisation.
        step_tolerance: converged when every increment is below these: rotation (radians), translation
            (millimetres), animation and illumination coefficients (units); one float applies to all. An
            animation unit's increment, here and in ``function_tolerance``'s test, is its change after the
            bounds' clip: a unit held at its bound moves by 0 instead of keeping the level to its iteration cap.
        function_tolerance: also converged when the step's predicted decrease of the cost,
            ``-(grad . delta + delta^T H delta / 2)`` of the reweighted linear model, is at least 0 and below this
            fraction of the cost (0: off). The parameter test alone is slow to pass along directions the images
            hardly constrain (a small pitch against a vertical shift): the steps there stay above the tolerance
            while changing the cost by a fraction of a percent, and the levels ran to their iteration caps.
            Measured on the 640x480 scenarios (evaluate.py, with the coarse levels at ``2**level`` times this),
            3e-3 took the iterations per pass from 4.0 to 3.1 with every mean error within 0.02 degree
            (occlusion's worst frame 5.1 -> 4.4 degrees). A negative prediction (the bounds' clip took a unit's
            step away from the model's minimum, and with coupled units the others' step with it) does not stop
            the level: it stopped there, and the final check then undid the step.
        start: :func:`linearise`'s output at the start estimate with these ``tpl``, ``image``, ``cam``,
            ``light_basis`` and ``mask`` (:attr:`LevelOutcome.linearisation` of a pass that ended there), used
            for the first iteration instead of linearising again.
        constants: :attr:`LevelOutcome.constants` of a pass with the same ``tpl`` and ``cam``, to reuse; None
            computes them.
        keep_linearisation: the final check linearises in full and hands it on
            (:attr:`LevelOutcome.linearisation`, for a following pass at this level); False: residuals only there
            (no Jacobian, one sample per point) and ``linearisation`` None.
        backend: :class:`~torchface.backend.Backend`: the native solver (each stream iterated on its own, in parallel over
            ``torch.get_num_threads()`` threads) or this torch code, whose batch iterates while any stream does
            (a stream that has stopped keeps its estimate; only where the loop goes on for others can its last
            step still be undone in the loop rather than by the final check, which gives the same estimate with
            ``final_check``).
        workspace: a borrowed :class:`~torchface.tracker.step.StepWorkspace` in which the native solver keeps
            its copy of the light basis and the Jacobian it hands on (:attr:`LevelOutcome.linearisation`, then valid
            until the workspace's next use); None: new tensors. The torch code does not use it.

    Returns:
        The new ``R, t, alpha, light`` and a :class:`LevelOutcome`.
    """
    B, N = mask.shape
    A = alpha.shape[1]
    P = 6 + A + light.shape[1]
    dtype, device = R.dtype, R.device
    if isinstance(step_tolerance, (int, float)):
        step_tolerance = (float(step_tolerance),) * 3
    for name, bound in (("alpha_lower", alpha_lower), ("alpha_upper", alpha_upper)):
        if tuple(bound.shape) not in ((A,), (B, A)):
            raise ValueError(f"{name} must be ({A},) or ({B}, {A}), one bound per animation unit (per stream), got "
                             f"{tuple(bound.shape)}")
    if use_native(backend, (tpl.points, tpl.basis, tpl.normals, tpl.intensity, image, R, t, alpha, light, light_basis,
                            alpha_lower, alpha_upper, alpha_mean, alpha_prior, cam.offset), "level solver", 64, P):
        _check_bounds(alpha_lower, alpha_upper)  # (host tensors: a read without a synchronisation)
        return _solve_level_native(
            tpl, image, cam, R, t, alpha, light, light_basis, mask, iterations=iterations, free=free,
            alpha_lower=alpha_lower, alpha_upper=alpha_upper, alpha_prior=alpha_prior, robust=robust,
            alpha_mean=alpha_mean, scale_floor=scale_floor, damping=damping, final_check=final_check,
            step_tolerance=step_tolerance, function_tolerance=function_tolerance, start=start, constants=constants,
            keep_linearisation=keep_linearisation, workspace=workspace,
        )
    # Everything that does not change across iterations is computed once here (what depends on the settings alone
    # once per setting: _solver_constants).
    # (free is read on the host: a mask on a GPU costs a synchronisation here; the tracker's is a CPU tensor)
    free_key = tuple(bool(v) for v in free.tolist())
    all_free = all(free_key)
    if isinstance(alpha_prior, Tensor):  # one precision per stream: (B, P) priors, (B, P, P) Hessian terms
        _, _, _, fixed_diag, free_rows, free_mask, tol = _solver_constants(
            free_key, A, 0.0, tuple(step_tolerance), dtype, device
        )
        freef = free_mask.to(dtype)
        prior = torch.zeros(B, P, dtype=dtype, device=device)
        ap = alpha_prior.to(dtype)
        prior[:, 6 : 6 + A] = ap.unsqueeze(-1) if ap.dim() == 1 else ap.expand(B, A)
        prior = prior * freef
        prior_alpha = prior[..., 6 : 6 + A]
        half_prior_alpha = 0.5 * prior_alpha
        prior_H = torch.diag_embed(prior)
    else:
        prior_alpha, half_prior_alpha, prior_H, fixed_diag, free_rows, free_mask, tol = _solver_constants(
            free_key, A, float(alpha_prior), tuple(step_tolerance), dtype, device
        )
    constants = _level_constants(cam, R, tpl) if constants is None else constants
    holes = None
    if torch.is_grad_enabled() and any(
        v.requires_grad for v in (image, R, t, alpha, light, light_basis, tpl.points, tpl.basis, tpl.intensity)
    ) and not bool(isfinite(image).all()):
        # Missing (NaN) pixels: the points whose samples touch one are left out, but the sampler's backward
        # multiplies their zero incoming gradient by the pixels (NaN), and so do the Jacobian's products: every
        # gradient of the step was NaN. Sample a copy with 0 there, the holes kept for the masks (linearise).
        holes = image.detach()
        image = torch.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0)
    # (B, L, N) in (B, N, L)'s memory order (the negation keeps its input's): a point-last basis (a large batch's
    # step: torchface.tracker.step._level_light_basis) is laid out as the other first, as the products below round
    # by the layout (batched products of the other order changed the estimates' last bits)
    neg_light_basis_t = light_basis.contiguous().transpose(1, 2).neg()
    # Where an animation unit counts as at its bound (the active set, below): within BOUND_MARGIN of its range
    # (in the dtype, as the native solver computes it); the pose and light columns of the held mask are never set.
    # An infinite range (a bound at -inf or inf: none on that side) has no margin: an infinite one put the other
    # bound's inner edge at -inf or inf (every unit the gradient pushed towards it held, wherever it was).
    lower, upper = alpha_lower.to(dtype), alpha_upper.to(dtype)
    span = upper - lower
    margin = torch.where(isfinite(span), span * BOUND_MARGIN, torch.zeros_like(span))
    lower_in, upper_in = lower + margin, upper - margin
    # The bounds' check is read with the first iteration's flag (no read of its own); without an iteration, alone.
    bounds_valid = _bounds_valid(lower, upper)
    if iterations < 1:
        _check_bounds(lower, upper)
    no_pose = torch.zeros(B, 6, dtype=torch.bool, device=device)
    no_light = torch.zeros(B, P - 6 - A, dtype=torch.bool, device=device)
    iters = torch.zeros(B, dtype=torch.int64, device=device)
    active = torch.ones(B, dtype=torch.bool, device=device)
    finite = torch.ones(B, dtype=torch.bool, device=device)
    lam = torch.full((B, 1, 1), damping, dtype=dtype, device=device)

    def lin(R: Tensor, t: Tensor, alpha: Tensor, light: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        out = linearise(tpl, image, cam, R, t, alpha, light, light_basis, mask, constants, neg_light_basis_t,
                        holes=holes)  # fmt: skip
        return cast("tuple[Tensor, Tensor, Tensor, Tensor]", out)  # with its Jacobian: J is a tensor

    def lin_last(R: Tensor, t: Tensor, alpha: Tensor, light: Tensor) -> tuple[Tensor, Tensor | None, Tensor, Tensor]:
        return linearise(tpl, image, cam, R, t, alpha, light, light_basis, mask, constants, neg_light_basis_t,
                         keep_linearisation, holes)  # fmt: skip

    best = None  # (R, t, alpha, light, H, grad, cost, s) of the last accepted estimate
    for it in range(iterations):
        r, J, valid, _ = lin(R, t, alpha, light) if it > 0 or start is None else start
        # A non-finite frame makes r non-finite there: those points are left out.
        valid = valid & isfinite(r)
        r = torch.where(valid, r, scalar(0.0, r))
        Jt = J.transpose(1, 2)  # (B, P, N), contiguous: see _LevelConstants
        if not all_free:
            Jt = torch.where(free_rows, Jt, scalar(0.0, Jt))
        d_alpha = alpha if alpha_mean is None else alpha - alpha_mean
        prior_grad = prior_alpha * d_alpha
        prior_cost = (prior_grad * d_alpha).sum(-1) * scalar(0.5, d_alpha)  # (halving is exact: = sum(p/2 d^2))
        # The step is judged at the scale of the last accepted estimate; the new cost, at the new scale, is
        # compared against at the next iteration.
        wgt, s, cost, judged = _weights(r, valid, robust, scale_floor, None if best is None else best[7])
        cost = cost + prior_cost
        if best is not None and judged is not None:  # (judged is given exactly when best is)
            judged = judged + prior_cost
            accept = (judged <= best[6]) & isfinite(judged)
        # The weights are zero at invalid points, which so add nothing: J is not masked (a select over J cost 28
        # microseconds against 3 for the product at one stream, 1500 points). Unless J is not finite there (a
        # gradient next to a non-finite pixel is already left out by linearise; a non-finite start handed on, or
        # template): then the points whose J rows are not finite are left out too and the system built again,
        # instead of failing the sample.
        Jw = Jt * wgt.unsqueeze(1)
        H = torch.baddbmm(prior_H, Jw, Jt.transpose(1, 2))
        # The common case, H finite and (past the first iteration) every stream's step accepted, is one host read:
        # each read waits for the device (on a GPU, a synchronisation).
        H_finite = isfinite(H).all()
        all_accepted = bool(H_finite & bounds_valid if best is None else H_finite & accept.all())
        if best is None and not all_accepted:
            _check_bounds(lower, upper)
        if not all_accepted and not bool(H_finite):
            valid = valid & isfinite(Jt).all(1)
            r = torch.where(valid, r, scalar(0.0, r))
            Jt = torch.where(valid.unsqueeze(1), Jt, scalar(0.0, Jt))
            wgt, s, cost, judged = _weights(r, valid, robust, scale_floor, None if best is None else best[7])
            cost = cost + prior_cost
            if best is not None and judged is not None:  # (judged is given exactly when best is)
                judged = judged + prior_cost
                accept = (judged <= best[6]) & isfinite(judged)
                all_accepted = bool(accept.all())
            Jw = Jt * wgt.unsqueeze(1)
            H = torch.baddbmm(prior_H, Jw, Jt.transpose(1, 2))
        grad = torch.bmm(Jw, r.unsqueeze(-1)).squeeze(-1)
        grad[:, 6 : 6 + A].add_(prior_grad)
        if best is not None:
            if all_accepted:  # the common case: no selection
                lam = (lam / scalar(3.0, lam)).clamp_min(1e-6)
            else:  # undo rejected steps
                R, t, alpha, light, H, grad, cost, s = _select(accept, (R, t, alpha, light, H, grad, cost, s), best)
                lam = torch.where(
                    accept.view(B, 1, 1), (lam / scalar(3.0, lam)).clamp_min(1e-6), lam * scalar(10.0, lam)
                )
        best = (R, t, alpha, light, H, grad, cost, s)
        diag = torch.diagonal(H, dim1=1, dim2=2)
        floor = scalar(1e-6, diag) * diag.amax(-1, keepdim=True).clamp_min(1e-12)
        Hd = torch.diag_embed(diag + floor).mul_(lam).add_(H)
        if not all_free:
            Hd = Hd + fixed_diag
        # The active set: an animation unit at a bound that the gradient pushes outward is held there, out of the
        # system (its row and column of Hd zero, 1 on the diagonal, 0 on the right-hand side: its step is 0), so
        # that the other parameters' step is the one with that unit fixed.
        g_alpha = grad[:, 6 : 6 + A]
        zero = scalar(0.0, g_alpha)
        outward = ((alpha <= lower_in) & (g_alpha > zero)) | ((alpha >= upper_in) & (g_alpha < zero))
        held = torch.cat((no_pose, outward, no_light), -1)  # (B, P)
        if not all_free:
            held = held & free_mask
        kept = ~held
        Hd = torch.where(kept.unsqueeze(-1) & kept.unsqueeze(-2), Hd, torch.diag_embed(held.to(dtype)))
        rhs = torch.where(held, scalar(0.0, grad), grad)
        L, info = torch.linalg.cholesky_ex(Hd)
        delta = torch.cholesky_solve(rhs.unsqueeze(-1), L).squeeze(-1).neg()  # not in place: autograd keeps the output
        n_valid = valid.sum(-1)
        good = (info == scalar(0, info)) & isfinite(delta.sum(-1)) & (n_valid >= scalar(P, n_valid))
        finite = finite & (good | ~active)
        step = active & good
        moves = step.unsqueeze(-1) & kept if all_free else step.unsqueeze(-1) & kept & free_mask
        delta = torch.where(moves, delta, scalar(0.0, delta))
        dR = axis_angle_to_matrix(delta[:, 0:3])
        R = torch.bmm(dR, R)
        t = t + delta[:, 3:6]
        moved = torch.clamp(alpha + delta[:, 6 : 6 + A], alpha_lower, alpha_upper)
        # The convergence tests read the change made: a held unit moves by 0, and a unit the step takes past a
        # bound by as far as the clip lets it.
        taken = torch.cat((delta[:, :6], moved - alpha, delta[:, 6 + A :]), -1).detach()
        alpha = moved
        light = light + delta[:, 6 + A :]
        iters = iters + active
        stop = (taken.abs() < tol).all(-1)
        if function_tolerance > 0:  # 0 is off
            # Predicted decrease of the (undamped) model, -(g.d + d^T H d / 2), in [0, tolerance times the cost
            # where it was built): g.d + d^T H d / 2 in (minus that, 0] (negation is exact: the same test). A
            # negative prediction (a step that the bounds' clip took away from the model's minimum, or rounding on
            # a tiny step, which the step test stops) does not stop the level: the model is not trusted there.
            change = (taken * (grad + scalar(0.5, H) * torch.bmm(H, taken.unsqueeze(-1)).squeeze(-1))).sum(-1)
            stop = stop | ((change <= scalar(0.0, change)) & (change > scalar(-function_tolerance, cost) * cost))
        active = step & ~stop
        if it + 1 < iterations and not bool(active.any()):  # (after the last iteration: no read, no wait)
            break
    if not final_check:
        if iterations < 1:  # no linearisation to report: none of the points, as the native solver reports
            r, valid = torch.zeros(B, N, dtype=dtype, device=device), torch.zeros(B, N, dtype=torch.bool, device=device)
        outcome = LevelOutcome(r, valid, torch.zeros_like(r), iters, ~active & finite, finite, constants=constants)
        return R, t, alpha, light, outcome
    last = lin_last(R, t, alpha, light)
    if best is not None:
        # The last step is kept only where it did not raise the cost.
        r, _, valid, _ = last
        cost = _cost(torch.where(valid, r, scalar(0.0, r)), robust, best[7])
        d_alpha = alpha if alpha_mean is None else alpha - alpha_mean
        cost = cost + (half_prior_alpha * d_alpha * d_alpha).sum(-1)
        accept = (cost <= best[6]) & isfinite(cost)
        if not bool(accept.all()):
            R, t, alpha, light = _select(accept, (R, t, alpha, light), best[:4])
            last = lin_last(R, t, alpha, light)
    r, J_last, valid, sampled = last
    outcome = LevelOutcome(
        r, valid & isfinite(r), sampled, iters, ~active & finite, finite,
        (r, J_last, valid, sampled) if J_last is not None else None, constants,  # J is None unless keep_linearisation
    )  # fmt: skip
    return R, t, alpha, light, outcome


@functools.lru_cache(maxsize=64)
def _shared_loss_codes(code: int, c: float, B: int) -> tuple[Tensor, Tensor]:
    """:func:`_loss_codes` of one loss for every stream: ``(B,)`` int32 codes and ``(B,)`` float64 constants. Cached
    (a tracked video's levels keep theirs), made outside inference mode; the kernel only reads them."""
    with torch.inference_mode(False):
        return torch.full((B,), code, dtype=torch.int32), torch.full((B,), c, dtype=torch.float64)


@functools.lru_cache(maxsize=64)
def _tolerance_row(step_tolerance: tuple[float, float, float], P: int, dtype: torch.dtype) -> Tensor:
    """``(P,)`` float64: the native solver's step tolerances (rotation, translation, the rest) rounded to ``dtype``,
    as the torch code compares them. Cached per setting, made outside inference mode; the kernel only reads it."""
    with torch.inference_mode(False):
        return torch.tensor(
            [step_tolerance[0]] * 3 + [step_tolerance[1]] * 3 + [step_tolerance[2]] * (P - 6), dtype=dtype
        ).to(torch.float64)


def _loss_codes(robust: RobustLoss | SwitchedRobustLoss | None, B: int) -> tuple[Tensor, Tensor]:
    """Per stream, the native solver's loss code ``(B,)`` int32 and tuning constant ``(B,)`` float64 (not to be
    written: one loss's are shared, :func:`_shared_loss_codes`)."""
    if robust is None:
        return _shared_loss_codes(0, 1.0, B)
    if not isinstance(robust, SwitchedRobustLoss):
        return _shared_loss_codes(_native.LOSS_CODES[robust.kind.value], cast(float, robust.c), B)  # (set: a float)
    kinds = [robust.base, robust.alternative]
    switch = robust.switch.reshape(B).cpu()
    code = torch.tensor([_native.LOSS_CODES[k.kind.value] for k in kinds], dtype=torch.int32)
    c = torch.tensor([k.c for k in kinds], dtype=torch.float64)
    which = switch.long()
    return code[which].contiguous(), c[which].contiguous()


def _solve_level_native(
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
    alpha_prior: float | Tensor,
    robust: RobustLoss | SwitchedRobustLoss | None,
    alpha_mean: Tensor | None,
    scale_floor: float,
    damping: float,
    final_check: bool,
    step_tolerance: tuple[float, float, float],
    function_tolerance: float,
    start: tuple[Tensor, Tensor, Tensor, Tensor] | None,
    constants: _LevelConstants | None,
    keep_linearisation: bool,
    workspace: StepWorkspace | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, LevelOutcome]:
    """:func:`solve_level` by the native solver (:mod:`torchface._native`); the same arguments and results."""
    B, N = mask.shape
    A, L = alpha.shape[1], light.shape[1]
    P = 6 + A + L
    dtype = R.dtype
    if image.shape[1] != 1:
        raise ValueError(f"image must be the (B, 1, h, w) gray crop, got {tuple(image.shape)}")
    image = image.contiguous()
    h, w = image.shape[-2:]
    # The kernel reads the template point-last alone: the rest of _LevelConstants (the torch code's sampling grid,
    # 11 dispatched operations a level) is not made here, and the outcome hands on the constants it was given.
    point_last = tpl.point_last if constants is None else (constants.points_t, constants.normals_t, constants.basis_t)
    points_t, normals_t, basis_t = (x.contiguous() for x in point_last)
    intensity = tpl.intensity.contiguous()
    # (B, L, N), negated straight into contiguous memory (the negation of the transposed view kept its layout, and
    # .contiguous() copied it again: two 3.7 MB tensors per pass at 128 streams)
    nlb_shape = (B, L, N)
    nlb = torch.empty(nlb_shape, dtype=light_basis.dtype) if workspace is None else workspace.buffer(
        "neg_light_basis", nlb_shape, light_basis.dtype, light_basis.device)
    torch.neg(light_basis.transpose(1, 2), out=nlb)
    offsets = _rows(cam.offset, dtype, cam.offset.shape)
    mask_c = mask.contiguous()
    free_u8 = _free_row(tuple(free.tolist()))
    # (use_native let no gradient through: the copies need no detach)
    R_out, t_out, alpha_out, light_out = (x.clone(memory_format=torch.contiguous_format) for x in (R, t, alpha, light))
    # (B, A) for the kernel, one row per stream (shared (A,) bounds repeated)
    lower = _rows(alpha_lower, dtype, (B, A))
    upper = _rows(alpha_upper, dtype, (B, A))
    mean = None if alpha_mean is None else _rows(alpha_mean, dtype, (B, A))
    if isinstance(alpha_prior, Tensor):  # (B, A) for the kernel
        ap = alpha_prior.to(torch.float64)
        prior = (ap.unsqueeze(-1) if ap.dim() == 1 else ap).expand(B, A).contiguous()
    else:
        prior = _shared_prior(float(alpha_prior).hex(), B, A)  # (hex: -0.0 and 0.0 apart)
    loss_kind, loss_c = _loss_codes(robust, B)
    tol = _tolerance_row(tuple(step_tolerance), P, dtype)  # as the torch code compares them: rounded to the dtype
    if start is not None:
        start_r = start[0].to(dtype).contiguous()
        start_J = start[1].transpose(1, 2).to(dtype).contiguous()  # (B, P, N)
        start_valid = start[2].contiguous()
    residual = torch.empty(B, N, dtype=dtype)
    sampled = torch.empty(B, N, dtype=dtype)
    valid = torch.empty(B, N, dtype=torch.bool)
    converged = torch.empty(B, dtype=torch.bool)
    finite = torch.empty(B, dtype=torch.bool)
    iters = torch.empty(B, dtype=torch.int64)
    keep = final_check and keep_linearisation
    J_out = None
    if keep:
        J_out = torch.empty(B, P, N, dtype=dtype) if workspace is None else workspace.buffer(
            "jacobian", (B, P, N), dtype, R.device)

    def ptr(x: Tensor | None) -> int | None:
        return None if x is None else x.data_ptr()

    prob = _native.LevelProblem(
        B=B, N=N, A=A, L=L, P=P, height=h, width=w, iterations=int(iterations), final_check=int(final_check),
        fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, scale_floor=float(scale_floor), damping=float(damping),
        function_tolerance=float(function_tolerance),
        image=ptr(image), points=ptr(points_t), normals=ptr(normals_t), basis=ptr(basis_t), intensity=ptr(intensity),
        neg_light_basis=ptr(nlb), offsets=ptr(offsets), mask=ptr(mask_c), free=ptr(free_u8), R=ptr(R_out),
        t=ptr(t_out), alpha=ptr(alpha_out), light=ptr(light_out), alpha_lower=ptr(lower), alpha_upper=ptr(upper),
        alpha_mean=ptr(mean), alpha_prior=ptr(prior), loss_c=ptr(loss_c), step_tolerance=ptr(tol),
        loss_kind=ptr(loss_kind),
        start_r=ptr(start_r) if start is not None else None,
        start_J=ptr(start_J) if start is not None else None,
        start_valid=ptr(start_valid) if start is not None else None,
        out_residual=ptr(residual), out_sampled=ptr(sampled), out_J=ptr(J_out), out_valid=ptr(valid),
        out_converged=ptr(converged), out_finite=ptr(finite), out_iterations=ptr(iters),
    )  # fmt: skip
    _native.run("solve_level", dtype == torch.float64, prob, B, torch.get_num_threads())
    linearisation = (residual, J_out.transpose(1, 2), valid, sampled) if J_out is not None else None  # (keep)
    outcome = LevelOutcome(
        residual, valid & isfinite(residual), sampled, iters, converged, finite, linearisation, constants
    )  # fmt: skip
    return R_out, t_out, alpha_out, light_out, outcome


def _rows(x: Tensor, dtype: torch.dtype, shape: tuple[int, ...]) -> Tensor:
    """``x`` as a contiguous ``shape`` tensor of ``dtype`` for a native kernel to read (never written): ``x`` itself
    where it is one already, else ``x.to(dtype).expand(shape).contiguous()`` (each of those a dispatched operation,
    about 3 microseconds, even where it changes nothing)."""
    if x.dtype == dtype and x.shape == shape and x.is_contiguous():
        return x
    return x.to(dtype).expand(shape).contiguous()


@functools.lru_cache(maxsize=64)
def _free_row(free: tuple[bool | int | float, ...]) -> Tensor:
    """The native solver's free-parameter mask ``(P,)`` uint8 of ``free`` (a mask's values, as ``.to(torch.uint8)``
    converts them). Cached per mask, made outside inference mode; the kernel only reads it."""
    with torch.inference_mode(False):
        return torch.tensor(free, dtype=torch.uint8)


@functools.lru_cache(maxsize=64)
def _shared_prior(precision: str, B: int, A: int) -> Tensor:
    """The native solver's ``(B, A)`` float64 prior precisions of one float (``precision``: its ``float.hex()``) for
    every stream and unit. Cached per setting, made outside inference mode; the kernel only reads it."""
    with torch.inference_mode(False):
        return torch.full((B, A), float.fromhex(precision), dtype=torch.float64)
