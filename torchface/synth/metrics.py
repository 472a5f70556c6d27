"""Accuracy of a tracked sequence against synthetic ground truth (pose, expression, robustness).

The per-frame functions (:func:`relative_rotation_error_deg`, :func:`translation_errors_mm`, :func:`unit_rmse`, ...)
take time series with the frame axis ``T`` just before the per-frame dimensions and any leading batch dimensions
``*`` (e.g. ``(B, T, 3, 3)`` for ``B`` runs of the same sequence); reductions are over ``T``. The summaries,
:func:`sequence_metrics` and :func:`long_run_metrics`, score one sequence (no batch dimension): call them per stream.
Rotations are head -> camera (``X_cam = R X_model + t``, millimetres; see
:mod:`torchface.conventions`).

Pose is scored *relative to frame 0*, ``R_t R_0^T`` of the estimate against the same of the ground truth,
so that a constant offset of the initial fit (paper Eq. 2) -- e.g. a different head-frame origin when the
tracked model is not the rendered one -- does not count against every later frame. The absolute errors are
reported beside it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor

from torchface.geometry._checks import check_number, rotation_defects
from torchface.geometry.so3 import geodesic_angle_deg, matrix_to_axis_angle, matrix_to_euler
from torchface.synth.sequence import ROTATION_TOLERANCE
from torchface.tracker.step import TrackStatus, usable_status

__all__ = [
    "LOST_THRESHOLD_DEG",
    "relative_rotations",
    "relative_rotation_error_deg",
    "relative_ypr_error_deg",
    "rotation_jitter_deg",
    "translation_errors_mm",
    "active_units",
    "unit_rmse",
    "pearson",
    "SequenceMetrics",
    "sequence_metrics",
    "RECOVERY_TARGET_FRAMES",
    "true_runs",
    "Recovery",
    "LongRunMetrics",
    "long_run_metrics",
    "auroc",
]

#: A frame whose relative rotation error exceeds this (degrees) counts as lost.
LOST_THRESHOLD_DEG: float = 10.0

#: Issue 5's target: a track lost while the face was out of view is back within this many frames of the face
#: being entirely in view again.
RECOVERY_TARGET_FRAMES: int = 30


def _check_rotations(R: Tensor, name: str) -> None:
    if not isinstance(R, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(R).__name__}")
    if R.dim() < 3 or tuple(R.shape[-2:]) != (3, 3) or not R.is_floating_point():
        raise ValueError(f"{name} must be (*, T, 3, 3) float rotations, got {tuple(R.shape)} {R.dtype}")
    # (a scale, a shear or a reflection was scored as an angle of no rotation at all; rows with NaN or inf are left
    # to the callers, which count such a pose as lost)
    flat = R.detach().reshape(-1, 3, 3).to("cpu", torch.float64).numpy()
    finite = np.flatnonzero(np.isfinite(flat).all(axis=(1, 2)))
    off, det = rotation_defects(flat[finite])
    tol = max(ROTATION_TOLERANCE, 8.0 * torch.finfo(R.dtype).eps)  # (a sequence's; float16's, bfloat16's rounding)
    bad = np.flatnonzero((off > tol) | (det <= 0))
    if bad.size:
        k = int(finite[bad[0]])
        where = tuple(int(i) for i in np.unravel_index(k, R.shape[:-2]))
        raise ValueError(
            f"{name} must hold rotation matrices (R^T R = I, det R = +1); {name}[{', '.join(map(str, where))}] is off "
            f"by {float(off[bad[0]]):.3g} with det {float(det[bad[0]]):.4g}; make them with "
            "torchface.geometry.so3.euler_to_matrix(ypr_deg) or axis_angle_to_matrix"
        )


def _check_same(a: Tensor, b: Tensor, names: str) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{names} must have the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")


def _rotation_pair_dtype(R_est: Tensor, R_gt: Tensor) -> torch.dtype:
    """Check ``R_est`` and ``R_gt``, both ``(*, T, 3, 3)`` float rotations of the same shape; their common dtype."""
    _check_rotations(R_est, "R_est")
    _check_rotations(R_gt, "R_gt")
    _check_same(R_est, R_gt, "R_est and R_gt")
    return torch.promote_types(R_est.dtype, R_gt.dtype)


def relative_rotations(R: Tensor) -> Tensor:
    """Rotations relative to the first frame, ``R_t R_0^T``.

    Args:
        R: ``(*, T, 3, 3)`` rotations.

    Returns:
        ``(*, T, 3, 3)``; frame 0 is the identity.

    Example:
        >>> R = torch.eye(3).expand(4, 3, 3)
        >>> relative_rotations(R).shape
        torch.Size([4, 3, 3])
    """
    _check_rotations(R, "R")
    return R @ R[..., :1, :, :].transpose(-1, -2)


def relative_rotation_error_deg(R_est: Tensor, R_gt: Tensor) -> Tensor:
    """Geodesic angle between the estimated and the true rotation relative to frame 0.

    ``e_t = angle((R^est_t R^est_0^T) (R^gt_t R^gt_0^T)^T)`` in degrees (:func:`geodesic_angle_deg`).

    Args:
        R_est: ``(*, T, 3, 3)`` estimated rotations.
        R_gt: ``(*, T, 3, 3)`` true rotations.

    Returns:
        ``(*, T)`` degrees; ``e_0 = 0``.

    Example:
        >>> from torchface.geometry.so3 import euler_to_matrix
        >>> gt = euler_to_matrix(torch.tensor([[0.0, 0, 0], [20.0, 0, 0]], dtype=torch.float64))
        >>> est = euler_to_matrix(torch.tensor([[5.0, 0, 0], [30.0, 0, 0]], dtype=torch.float64))
        >>> relative_rotation_error_deg(est, gt).round(decimals=6)
        tensor([0., 5.], dtype=torch.float64)
    """
    dtype = _rotation_pair_dtype(R_est, R_gt)
    return geodesic_angle_deg(relative_rotations(R_est.to(dtype)), relative_rotations(R_gt.to(dtype)))


def relative_ypr_error_deg(R_est: Tensor, R_gt: Tensor) -> Tensor:
    """Per-axis error of the relative rotations decomposed into yaw, pitch, roll.

    Both ``R_t R_0^T`` are decomposed with :func:`matrix_to_euler` (``R = R_y R_x R_z``) and their
    difference is wrapped to ``(-180, 180]``.

    Args:
        R_est: ``(*, T, 3, 3)`` estimated rotations.
        R_gt: ``(*, T, 3, 3)`` true rotations.

    Returns:
        ``(*, T, 3)`` signed yaw, pitch, roll errors (estimate minus truth), degrees.
    """
    dtype = _rotation_pair_dtype(R_est, R_gt)
    d = matrix_to_euler(relative_rotations(R_est.to(dtype))) - matrix_to_euler(relative_rotations(R_gt.to(dtype)))
    wrapped = torch.remainder(d + 180.0, 360.0) - 180.0  # [-180, 180)
    return torch.where(wrapped == -180.0, torch.full_like(wrapped, 180.0), wrapped)  # (-180, 180] as documented


def rotation_jitter_deg(R_est: Tensor, R_gt: Tensor) -> Tensor:
    """Frame-to-frame noise of the rotation error: how much an estimate jitters around the truth.

    The error ``E_t = (R^est_t R^est_0^T) (R^gt_t R^gt_0^T)^T`` (as in :func:`relative_rotation_error_deg`) is
    taken as its rotation vector ``e_t`` (degrees), and its second differences ``e_{t+1} - 2 e_t + e_{t-1}``
    remove what varies slowly (a bias, a drift). For an error that is smooth plus independent noise ``n_t`` per
    frame, ``E |Δ² n|² = 6 E |n|²``, so the result, ``sqrt(mean |Δ² e|² / 6)``, is the RMS angle of that noise;
    a smooth error gives about 0. It measures what a user sees as jitter, apart from the error itself.

    Args:
        R_est: ``(*, T, 3, 3)`` estimated rotations, ``T >= 3``.
        R_gt: ``(*, T, 3, 3)`` true rotations.

    Returns:
        ``(*)`` degrees.

    Example:
        >>> from torchface.geometry.so3 import euler_to_matrix
        >>> gt = euler_to_matrix(torch.tensor([[2.0 * t, 0.0, 0.0] for t in range(10)], dtype=torch.float64))
        >>> est = euler_to_matrix(torch.tensor([[2.0 * t + 1.0, 0.0, 0.0] for t in range(10)], dtype=torch.float64))
        >>> float(rotation_jitter_deg(est, gt)) < 1e-9  # a constant bias is no jitter
        True
    """
    dtype = torch.promote_types(_rotation_pair_dtype(R_est, R_gt), torch.float64)
    if R_est.shape[-3] < 3:
        raise ValueError(f"jitter needs T >= 3 frames, got {R_est.shape[-3]}")
    err = relative_rotations(R_est.to(dtype)) @ relative_rotations(R_gt.to(dtype)).transpose(-1, -2)
    e = torch.rad2deg(matrix_to_axis_angle(err))  # (*, T, 3)
    d2 = e[..., 2:, :] - 2.0 * e[..., 1:-1, :] + e[..., :-2, :]
    return (d2.pow(2).sum(-1).mean(-1) / 6.0).sqrt()


def translation_errors_mm(t_est: Tensor, t_gt: Tensor) -> tuple[Tensor, Tensor]:
    """Absolute and frame-0-relative translation errors (Euclidean, millimetres).

    The relative error compares the displacements ``t_t - t_0`` of the head-frame origin, which removes
    a constant offset of the initial fit.

    Args:
        t_est: ``(*, T, 3)`` estimated translations (mm).
        t_gt: ``(*, T, 3)`` true translations (mm).

    Returns:
        ``(*, T)`` absolute errors ``|t^est_t - t^gt_t|`` and ``(*, T)`` relative errors
        ``|(t^est_t - t^est_0) - (t^gt_t - t^gt_0)|``.

    Example:
        >>> est = torch.tensor([[1.0, 0, 0], [1.0, 2, 0]])
        >>> gt = torch.tensor([[0.0, 0, 0], [0.0, 0, 0]])
        >>> translation_errors_mm(est, gt)
        (tensor([1.0000, 2.2361]), tensor([0., 2.]))
    """
    for t, name in ((t_est, "t_est"), (t_gt, "t_gt")):
        if not isinstance(t, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if t.dim() < 2 or t.shape[-1] != 3 or not t.is_floating_point():
            raise ValueError(f"{name} must be (*, T, 3) float translations, got {tuple(t.shape)} {t.dtype}")
    _check_same(t_est, t_gt, "t_est and t_gt")
    dtype = torch.promote_types(t_est.dtype, t_gt.dtype)
    d = t_est.to(dtype) - t_gt.to(dtype)
    return d.norm(dim=-1), (d - d[..., :1, :]).norm(dim=-1)


def _check_series(x: Tensor, name: str) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() < 2 or not x.is_floating_point():
        raise ValueError(f"{name} must be (*, T, A) float, got {tuple(x.shape)} {x.dtype}")


def active_units(values_gt: Tensor, tolerance: float = 1e-6) -> Tensor:
    """Units whose true value varies over the sequence (peak-to-peak above ``tolerance``).

    Args:
        values_gt: ``(*, T, A)`` true unit values.
        tolerance: smallest peak-to-peak change that counts as varying.

    Returns:
        ``(*, A)`` bool.
    """
    _check_series(values_gt, "values_gt")
    return (values_gt.amax(dim=-2) - values_gt.amin(dim=-2)) > tolerance


def unit_rmse(values_est: Tensor, values_gt: Tensor, ranges: Tensor) -> Tensor:
    """Root-mean-square error of each unit over time, as a fraction of its range.

    ``rmse_a = sqrt(mean_t (alpha^est_ta - alpha^gt_ta)^2) / (hi_a - lo_a)``.

    Args:
        values_est: ``(*, T, A)`` estimated animation-unit values.
        values_gt: ``(*, T, A)`` true values.
        ranges: ``(A, 2)`` ``[lo, hi]`` of each unit (e.g. ``FaceModel.animation_ranges``).

    Returns:
        ``(*, A)`` dimensionless.

    Example:
        >>> est = torch.tensor([[0.5, 0.0], [0.5, 0.0]])
        >>> gt = torch.zeros(2, 2)
        >>> unit_rmse(est, gt, torch.tensor([[0.0, 1.0], [-1.0, 1.0]]))
        tensor([0.5000, 0.0000])
    """
    _check_series(values_est, "values_est")
    _check_series(values_gt, "values_gt")
    _check_same(values_est, values_gt, "values_est and values_gt")
    A = values_gt.shape[-1]
    if not isinstance(ranges, Tensor) or tuple(ranges.shape) != (A, 2):
        raise ValueError(f"ranges must be ({A}, 2) [lo, hi] per unit, got {tuple(getattr(ranges, 'shape', ()))}")
    dtype = torch.promote_types(values_est.dtype, values_gt.dtype)
    ranges = ranges.to(dtype=dtype, device=values_gt.device)
    span = ranges[:, 1] - ranges[:, 0]
    if not bool((span > 0).all()):
        raise ValueError(f"every range must have hi > lo, got {ranges.tolist()}")
    d = values_est.to(dtype) - values_gt.to(dtype)
    return (d * d).mean(dim=-2).sqrt() / span


def pearson(x: Tensor, y: Tensor) -> Tensor:
    """Pearson correlation over time, per unit.

    ``rho = sum_t (x_t - x_mean)(y_t - y_mean) / sqrt(sum_t (x_t - x_mean)^2 sum_t (y_t - y_mean)^2)``;
    NaN where either series is constant (the correlation is undefined there).

    Args:
        x: ``(*, T, A)``.
        y: ``(*, T, A)``.

    Returns:
        ``(*, A)`` in ``[-1, 1]`` or NaN.

    Example:
        >>> x = torch.tensor([[0.0], [1.0], [2.0]])
        >>> pearson(x, 3.0 - 2.0 * x)
        tensor([-1.])
    """
    _check_series(x, "x")
    _check_series(y, "y")
    _check_same(x, y, "x and y")
    dtype = torch.promote_types(x.dtype, y.dtype)
    xc = x.to(dtype) - x.to(dtype).mean(dim=-2, keepdim=True)
    yc = y.to(dtype) - y.to(dtype).mean(dim=-2, keepdim=True)
    sxx, syy, sxy = (xc * xc).sum(-2), (yc * yc).sum(-2), (xc * yc).sum(-2)
    # Constant series: relative to the data's own scale, so a float round-off residue counts as constant. Centring
    # leaves each value off by a few eps |x|, so the residue of a constant series is of order eps^2 sum(x^2) (a
    # threshold of eps sum(x^2) took a real swing of std/|mean| below sqrt(eps), 3.5e-4 in float32, for constant).
    eps = torch.finfo(dtype).eps
    scale_x = (x.to(dtype) ** 2).sum(-2) * (100.0 * eps * eps)
    scale_y = (y.to(dtype) ** 2).sum(-2) * (100.0 * eps * eps)
    degenerate = (sxx <= scale_x) | (syy <= scale_y) | (sxx == 0) | (syy == 0)
    denom = torch.where(degenerate, torch.ones_like(sxx), (sxx * syy).clamp_min(torch.finfo(dtype).tiny).sqrt())
    rho = (sxy / denom).clamp(-1.0, 1.0)
    return torch.where(degenerate, torch.full_like(rho, float("nan")), rho)


@dataclass(frozen=True)
class SequenceMetrics:
    """Summary of one tracked sequence (frames ``1 .. T-1``; frame 0 is the reference).

    Attributes:
        frames: number of tracked frames ``T - 1``.
        rot_err_mean_deg, rot_err_median_deg, rot_err_max_deg: geodesic error of the rotation relative to
            frame 0 (:func:`relative_rotation_error_deg`).
        yaw_err_deg, pitch_err_deg, roll_err_deg: mean absolute per-axis error (:func:`relative_ypr_error_deg`).
        trans_err_mm: mean absolute translation error; trans_rel_err_mm: mean frame-0-relative error
            (:func:`translation_errors_mm`).
        init_rot_err_deg, init_trans_err_mm: error of the initial fit at frame 0 (absolute).
        converged: fraction of frames whose status is CONVERGED.
        success: fraction of frames neither FAILED nor LOST (``TrackResult.success``).
        lost_frames: frames whose relative rotation error exceeds the lost threshold or is not finite;
            lost_fraction: the same over ``frames``.
        au_rmse: RMSE over the active units, each as a fraction of its range, averaged (NaN if none active).
        au_corr: Pearson correlation over the active units, averaged over the defined ones (NaN if none).
        au_names: names of the active units; au_rmse_per_unit, au_corr_per_unit: per active unit.
        au_inactive_rmse: RMSE over the units the truth leaves at rest (those :func:`active_units` does not
            list), each as a fraction of its range, pooled as their quadratic mean: how much motion the tracker
            reports where there is none (NaN if every unit is active or none is scored).
        au_inactive_max: the largest ``|estimate - truth|`` of such a unit over the frames, as a fraction of its
            range (NaN likewise).
        rot_jitter_deg: :func:`rotation_jitter_deg` over the frames ``0 .. T-1`` (NaN for ``T < 3``).
    """

    frames: int
    rot_err_mean_deg: float
    rot_err_median_deg: float
    rot_err_max_deg: float
    yaw_err_deg: float
    pitch_err_deg: float
    roll_err_deg: float
    trans_err_mm: float
    trans_rel_err_mm: float
    init_rot_err_deg: float
    init_trans_err_mm: float
    converged: float
    success: float
    lost_frames: int
    lost_fraction: float
    au_rmse: float
    au_corr: float
    au_names: tuple[str, ...] = ()
    au_rmse_per_unit: tuple[float, ...] = ()
    au_corr_per_unit: tuple[float, ...] = ()
    au_inactive_rmse: float = float("nan")
    au_inactive_max: float = float("nan")
    rot_jitter_deg: float = float("nan")

    def as_dict(self) -> dict[str, float | int]:
        """Flat ``{metric: number}``; per-unit values as ``au_rmse/<name>`` and ``au_corr/<name>``."""
        d = asdict(self)
        names = d.pop("au_names")
        rmse = d.pop("au_rmse_per_unit")
        corr = d.pop("au_corr_per_unit")
        for n, r, c in zip(names, rmse, corr):
            d[f"au_rmse/{n}"] = r
            d[f"au_corr/{n}"] = c
        return d


def sequence_metrics(
    rotation_est: Tensor,
    translation_est: Tensor,
    rotation_gt: Tensor,
    translation_gt: Tensor,
    status: Tensor,
    *,
    anim_est: Tensor | None = None,
    anim_gt: Tensor | None = None,
    anim_ranges: Tensor | None = None,
    anim_names: tuple[str, ...] = (),
    lost_threshold_deg: float = LOST_THRESHOLD_DEG,
) -> SequenceMetrics:
    """Summarise one tracked sequence against its ground truth.

    Statistics are over the tracked frames ``1 .. T-1`` (frame 0 is the initial fit and the reference of
    the relative errors); the initial fit's own error is reported separately.

    Args:
        rotation_est: ``(T, 3, 3)`` estimated head -> camera rotations.
        translation_est: ``(T, 3)`` estimated translations (mm).
        rotation_gt: ``(T, 3, 3)`` true rotations.
        translation_gt: ``(T, 3)`` true translations (mm).
        status: ``(T,)`` integer per-frame :class:`~torchface.tracker.step.TrackStatus`.
        anim_est: ``(T, A)`` estimated animation units, or None (no expression metrics).
        anim_gt: ``(T, A)`` true animation units in the same order, or None.
        anim_ranges: ``(A, 2)`` ranges the RMSE is normalised by (required with ``anim_est``).
        anim_names: ``A`` names.
        lost_threshold_deg: relative rotation error above which a frame is lost.

    Returns:
        :class:`SequenceMetrics`.
    """
    _check_rotations(rotation_est, "rotation_est")
    if rotation_est.dim() != 3 or rotation_est.shape[0] < 2:
        raise ValueError(f"rotation_est must be (T, 3, 3) with T >= 2, got {tuple(rotation_est.shape)}")
    T = rotation_est.shape[0]
    _check_rotations(rotation_gt, "rotation_gt")
    for x, name, shape in (
        (rotation_gt, "rotation_gt", (T, 3, 3)),
        (translation_est, "translation_est", (T, 3)),
        (translation_gt, "translation_gt", (T, 3)),
    ):  # (named as the helpers name theirs, R_gt or t_est, where the shapes differed)
        if not isinstance(x, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
        if tuple(x.shape) != shape:
            raise ValueError(f"{name} must be {shape} like rotation_est's T = {T} frames, got {tuple(x.shape)}")
    if not isinstance(status, Tensor):
        raise TypeError(f"status must be a ({T},) integer tensor of TrackStatus codes, got {type(status).__name__}")
    if tuple(status.shape) != (T,):
        raise ValueError(f"status must be ({T},), got {tuple(status.shape)}")
    if status.is_floating_point() or status.is_complex() or status.dtype == torch.bool:
        # (result.success, True where usable, was read as status 1 and False as 0, CONVERGED: every frame usable)
        raise TypeError(
            f"status must hold the integer TrackStatus codes (TrackResult.status), got {status.dtype}"
            + (" (result.success is a bool flag: give result.status)" if status.dtype == torch.bool else "")
        )
    if (anim_est is None) != (anim_gt is None):  # (one alone scored no unit without a word)
        given, missing = ("anim_est", "anim_gt") if anim_gt is None else ("anim_gt", "anim_est")
        raise ValueError(f"{given} was given without {missing}: give both to score the animation units, or neither")
    if anim_est is not None and anim_gt is not None:
        for x, name in ((anim_est, "anim_est"), (anim_gt, "anim_gt")):
            if not isinstance(x, Tensor) or x.dim() != 2 or x.shape[0] != T:
                got = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
                raise ValueError(f"{name} must be a ({T}, A) tensor like rotation_est's T = {T} frames, got {got}")
        if anim_est.shape != anim_gt.shape and anim_gt.shape[-1] > 0:  # (a scan's truth, A = 0: nothing to score)
            raise ValueError(f"anim_est and anim_gt must have the same units, got {tuple(anim_est.shape)} and "
                             f"{tuple(anim_gt.shape)}")  # fmt: skip
    lost_threshold_deg = check_number(lost_threshold_deg, "lost_threshold_deg", "(0, inf)")  # (NaN: nothing lost)
    rot = relative_rotation_error_deg(rotation_est, rotation_gt)[1:]
    ypr = relative_ypr_error_deg(rotation_est, rotation_gt)[1:].abs().mean(0)
    t_abs, t_rel = translation_errors_mm(translation_est, translation_gt)
    init_rot = geodesic_angle_deg(rotation_est[0].to(rotation_gt.dtype), rotation_gt[0])
    st = status[1:]
    lost = int(((rot > lost_threshold_deg) | ~torch.isfinite(rot)).sum())  # a NaN pose is lost too (NaN > x: False)
    nan = float("nan")
    au_rmse, au_corr = nan, nan
    names: tuple[str, ...] = ()
    rmse_u: tuple[float, ...] = ()
    corr_u: tuple[float, ...] = ()
    inactive_rmse, inactive_max = nan, nan
    if anim_est is not None and anim_gt is not None and anim_gt.shape[-1] > 0:
        if anim_ranges is None:
            raise ValueError("anim_ranges is required to score animation units")
        if len(anim_names) != anim_gt.shape[-1]:
            raise ValueError(f"anim_names must name {anim_gt.shape[-1]} units, got {len(anim_names)}")
        est, gt = anim_est[1:], anim_gt[1:]
        active = active_units(gt)
        rmse_all = unit_rmse(est, gt, anim_ranges)  # (A,): both groups' figures come from it
        if bool(active.any()):
            r = rmse_all[active]
            c = pearson(est, gt)[active]
            names = tuple(n for n, a in zip(anim_names, active.tolist()) if a)
            rmse_u = tuple(float(v) for v in r)
            corr_u = tuple(float(v) for v in c)
            au_rmse = float(r.mean())
            defined = c[~torch.isnan(c)]
            au_corr = float(defined.mean()) if defined.numel() else nan
        if bool((~active).any()):
            span = (anim_ranges[:, 1] - anim_ranges[:, 0]).to(est)
            inactive_rmse = float(rmse_all[~active].pow(2).mean().sqrt())
            inactive_max = float(((est - gt).abs() / span)[:, ~active].max())
    return SequenceMetrics(
        frames=T - 1,
        rot_err_mean_deg=float(rot.mean()),
        rot_err_median_deg=float(rot.median()),
        rot_err_max_deg=float(rot.max()),
        yaw_err_deg=float(ypr[0]),
        pitch_err_deg=float(ypr[1]),
        roll_err_deg=float(ypr[2]),
        trans_err_mm=float(t_abs[1:].mean()),
        trans_rel_err_mm=float(t_rel[1:].mean()),
        init_rot_err_deg=float(init_rot),
        init_trans_err_mm=float(t_abs[0]),
        converged=float((st == int(TrackStatus.CONVERGED)).double().mean()),
        success=float(usable_status(st).double().mean()),
        lost_frames=lost,
        lost_fraction=lost / (T - 1),
        au_rmse=au_rmse,
        au_corr=au_corr,
        au_names=names,
        au_rmse_per_unit=rmse_u,
        au_corr_per_unit=corr_u,
        au_inactive_rmse=inactive_rmse,
        au_inactive_max=inactive_max,
        rot_jitter_deg=float(rotation_jitter_deg(rotation_est, rotation_gt)) if T >= 3 else nan,
    )


# ------------------------------------------------------------------------------------ long runs: returns, recovery


def _check_flags(x: Tensor, name: str, T: int | None = None) -> Tensor:
    if not isinstance(x, Tensor) or x.dim() != 1 or x.dtype != torch.bool:
        got = f"{tuple(getattr(x, 'shape', ()))} {getattr(x, 'dtype', type(x).__name__)}"
        raise ValueError(f"{name} must be a (T,) bool tensor, got {got}")
    if T is not None and x.shape[0] != T:
        raise ValueError(f"{name} must have T = {T} frames, got {x.shape[0]}")
    return x


def true_runs(mask: Tensor) -> tuple[tuple[int, int], ...]:
    """Maximal runs of True, as half-open frame ranges ``[start, end)``.

    Args:
        mask: ``(T,)`` bool.

    Example:
        >>> true_runs(torch.tensor([True, True, False, True, False, False, True]))
        ((0, 2), (3, 4), (6, 7))
    """
    _check_flags(mask, "mask")
    padded = torch.cat([mask.new_zeros(1), mask, mask.new_zeros(1)]).to(torch.int8)
    edges = padded[1:] - padded[:-1]
    starts = torch.nonzero(edges == 1).flatten().tolist()
    ends = torch.nonzero(edges == -1).flatten().tolist()
    return tuple(zip(starts, ends))


@dataclass(frozen=True)
class Recovery:
    """How tracking came back after one stretch where the face was hidden (out of view or occluded).

    Attributes:
        gap_start: first frame of the stretch.
        gap_end: first frame after it (the face is entirely in view and clear again); ``T`` when the sequence
            ends hidden.
        frames_to_recover: frames from ``gap_end`` to the first frame that starts ``hold`` consecutive good
            frames (0: good right away); None when that never happens before the next hidden stretch or the
            end of the sequence.
        cause: ``"out of view"`` when some frame of the stretch has the face (partly) outside the image, else
            ``"occluded"``.
    """

    gap_start: int
    gap_end: int
    frames_to_recover: int | None
    cause: str = "out of view"


@dataclass(frozen=True)
class LongRunMetrics:
    """Drift and recovery on a long sequence (issue 5). Frames ``1 .. T-1`` are scored (frame 0 is the reference).

    A frame is *good* when the tracker calls it successful and its rotation error relative to frame 0
    (:func:`relative_rotation_error_deg`) is at most the lost threshold. The face is *in view* when it is
    entirely inside the image, and *clear* when it is in view and not occluded.

    Attributes:
        return_frames: the frames at which the true head is back at the frontal pose after a turn.
        return_errors_deg: rotation error at each of them.
        rot_err_mean_deg, rot_err_max_deg: over the frames where the face is in view.
        rot_err_mean_success_deg, rot_err_max_success_deg: over the in-view frames the tracker called successful.
        lost_frames: in-view frames whose error exceeds the lost threshold.
        unsuccessful_frames: in-view frames the tracker did not call successful; unsuccessful_occluded: those of
            them that are occluded.
        success_out_of_view: frames where the face was not entirely in view but the tracker called it successful.
        recoveries: one :class:`Recovery` per hidden stretch (out of view or occluded), in order.
        losses_in_view: ``(start, end)`` runs of not-good clear frames that do not begin where a hidden stretch
            ends (those are the recoveries): losses during tracking proper.
        longest_loss_in_view: frames of the longest of those (0 when none).
        longest_error_loss_in_view: frames of the longest such run counting only the error (above the lost
            threshold, whatever the tracker says): a run of frames merely marked unsuccessful is not one.
    """

    return_frames: tuple[int, ...]
    return_errors_deg: tuple[float, ...]
    rot_err_mean_deg: float
    rot_err_max_deg: float
    rot_err_mean_success_deg: float
    rot_err_max_success_deg: float
    lost_frames: int
    unsuccessful_frames: int
    unsuccessful_occluded: int
    success_out_of_view: int
    recoveries: tuple[Recovery, ...]
    losses_in_view: tuple[tuple[int, int], ...]
    longest_loss_in_view: int
    longest_error_loss_in_view: int

    def worst_recovery(self, cause: str | None = None) -> int | None:
        """The most frames a recovery (of ``cause``, or any) took; None if one never recovered; 0 if none."""
        frames = [r.frames_to_recover for r in self.recoveries if cause is None or r.cause == cause]
        recovered = [f for f in frames if f is not None]
        return None if len(recovered) < len(frames) else max(recovered, default=0)


def long_run_metrics(
    error_deg: Tensor,
    success: Tensor,
    visible: Tensor,
    return_frames: tuple[int, ...] | list[int],
    *,
    occluded: Tensor | None = None,
    hold: int = 5,
    lost_threshold_deg: float = LOST_THRESHOLD_DEG,
) -> LongRunMetrics:
    """Errors at the returns to frontal, drift, losses and recovery of one long tracked sequence.

    Args:
        error_deg: ``(T,)`` rotation error relative to frame 0 (:func:`relative_rotation_error_deg`), degrees.
        success: ``(T,)`` bool, the tracker's own per-frame success flag.
        visible: ``(T,)`` bool, the face is entirely in view (:attr:`GroundTruth.face_visible`).
        return_frames: frames where the true head is frontal again after a turn (in ``1 .. T-1``).
        occluded: ``(T,)`` bool, an occluder covers part of the face (:attr:`GroundTruth.occluder_on`), or None.
        hold: consecutive good frames that make a recovery.
        lost_threshold_deg: rotation error above which a frame is not good.

    Returns:
        :class:`LongRunMetrics`.

    Example:
        >>> err = torch.zeros(6, dtype=torch.float64)
        >>> vis = torch.tensor([True, True, False, False, True, True])
        >>> ok = torch.tensor([True, True, False, False, False, True])
        >>> m = long_run_metrics(err, ok, vis, [1], hold=1)
        >>> m.recoveries, m.unsuccessful_frames
        ((Recovery(gap_start=2, gap_end=4, frames_to_recover=1, cause='out of view'),), 1)
    """
    if not isinstance(error_deg, Tensor) or error_deg.dim() != 1 or error_deg.shape[0] < 2:
        raise ValueError(f"error_deg must be a (T,) tensor with T >= 2, got {tuple(getattr(error_deg, 'shape', ()))}")
    T = error_deg.shape[0]
    _check_flags(success, "success", T)
    _check_flags(visible, "visible", T)
    occluded = torch.zeros(T, dtype=torch.bool) if occluded is None else _check_flags(occluded, "occluded", T)
    if hold < 1:
        raise ValueError(f"hold must be >= 1, got {hold}")
    lost_threshold_deg = check_number(lost_threshold_deg, "lost_threshold_deg", "(0, inf)")  # (NaN: every frame good)
    frames = tuple(int(f) for f in return_frames)
    if any(not 1 <= f < T for f in frames):
        raise ValueError(f"return_frames must lie in 1 .. {T - 1}, got {frames}")
    err = error_deg.detach().cpu().to(torch.float64)
    if bool(torch.isnan(err).any()):
        raise ValueError("error_deg must not be NaN")
    success, visible, occluded = success.cpu(), visible.cpu(), occluded.cpu()
    good = success & (err <= lost_threshold_deg)
    scored = visible.clone()
    scored[0] = False
    clear = scored & ~occluded
    nan = float("nan")

    def mean_max(mask: Tensor) -> tuple[float, float]:
        e = err[mask]
        return (float(e.mean()), float(e.max())) if e.numel() else (nan, nan)

    # Start of each good run of `hold` frames: good[f : f + hold] all True.
    window = good.to(torch.int64).unfold(0, hold, 1).sum(-1) == hold if T >= hold else good[:0]
    hidden = ~clear
    hidden[0] = False
    gaps = true_runs(hidden)
    recoveries = []
    for i, (start, end) in enumerate(gaps):
        limit = gaps[i + 1][0] if i + 1 < len(gaps) else T
        hits = torch.nonzero(window[end : max(end, limit - hold + 1)]).flatten()
        cause = "out of view" if not bool(visible[start:end].all()) else "occluded"
        recoveries.append(Recovery(start, end, int(hits[0]) if hits.numel() else None, cause))
    gap_ends = {end for _, end in gaps}
    losses = tuple((a, b) for a, b in true_runs(clear & ~good) if a not in gap_ends)
    error_losses = [b - a for a, b in true_runs(clear & (err > lost_threshold_deg)) if a not in gap_ends]
    mean_all, max_all = mean_max(scored)
    mean_ok, max_ok = mean_max(scored & success)
    return LongRunMetrics(
        return_frames=frames,
        return_errors_deg=tuple(float(err[f]) for f in frames),
        rot_err_mean_deg=mean_all,
        rot_err_max_deg=max_all,
        rot_err_mean_success_deg=mean_ok,
        rot_err_max_success_deg=max_ok,
        lost_frames=int((scored & (err > lost_threshold_deg)).sum()),
        unsuccessful_frames=int((scored & ~success).sum()),
        unsuccessful_occluded=int((scored & ~success & occluded).sum()),
        success_out_of_view=int((~visible & success)[1:].sum()),
        recoveries=tuple(recoveries),
        losses_in_view=losses,
        longest_loss_in_view=max((b - a for a, b in losses), default=0),
        longest_error_loss_in_view=max(error_losses, default=0),
    )


def auroc(scores_pos: Tensor, scores_neg: Tensor) -> float:
    """Area under the ROC curve: ``P(s_pos > s_neg) + P(s_pos = s_neg) / 2`` (Mann-Whitney ``U / (n_pos n_neg)``).

    Args:
        scores_pos: ``(n_pos,)`` scores of the positives (e.g. the confidence of good frames).
        scores_neg: ``(n_neg,)`` scores of the negatives.

    Returns:
        The AUROC in ``[0, 1]``; NaN when either set is empty.

    Example:
        >>> auroc(torch.tensor([0.9, 0.8]), torch.tensor([0.1, 0.8]))
        0.875
    """
    pos = torch.as_tensor(scores_pos, dtype=torch.float64).reshape(-1)
    neg = torch.as_tensor(scores_neg, dtype=torch.float64).reshape(-1)
    if bool(torch.isnan(pos).any() | torch.isnan(neg).any()):
        raise ValueError("scores must not be NaN")
    n_pos, n_neg = pos.numel(), neg.numel()
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    allv = torch.cat([pos, neg])
    order = torch.argsort(allv, stable=True)
    # Average 1-based ranks over ties.
    _, inverse, counts = torch.unique_consecutive(allv[order], return_inverse=True, return_counts=True)
    ends = torch.cumsum(counts, 0).to(torch.float64)
    avg_rank = ends - (counts.to(torch.float64) - 1.0) / 2.0
    ranks = torch.empty_like(allv)
    ranks[order] = avg_rank[inverse]
    u = float(ranks[:n_pos].sum()) - n_pos * (n_pos + 1) / 2.0
    return u / (n_pos * n_neg)
