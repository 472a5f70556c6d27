"""Known-answer tests of torchface.synth.metrics (tracking accuracy against ground truth)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchface.geometry.so3 import axis_angle_to_matrix, euler_to_matrix
from torchface.synth.metrics import (
    Recovery,
    active_units,
    auroc,
    long_run_metrics,
    pearson,
    relative_rotation_error_deg,
    relative_rotations,
    relative_ypr_error_deg,
    rotation_jitter_deg,
    sequence_metrics,
    translation_errors_mm,
    true_runs,
    unit_rmse,
)
from torchface.tracker.step import TrackStatus

F64 = torch.float64


def _ypr(rows: list[list[float]]) -> torch.Tensor:
    return euler_to_matrix(torch.tensor(rows, dtype=F64))


# --- relative rotations ---------------------------------------------------------------------------


def test_relative_rotations_identity_at_frame_zero_and_batched_shape() -> None:
    R = axis_angle_to_matrix(torch.randn(2, 5, 3, dtype=F64, generator=torch.Generator().manual_seed(0)))
    rel = relative_rotations(R)
    assert rel.shape == (2, 5, 3, 3)
    torch.testing.assert_close(rel[:, 0], torch.eye(3, dtype=F64).expand(2, 3, 3))
    torch.testing.assert_close(rel[:, 3] @ R[:, 0], R[:, 3])


def test_rotation_error_known_answer_yaw() -> None:
    gt = _ypr([[0, 0, 0], [20, 0, 0], [-10, 0, 0]])
    est = _ypr([[5, 0, 0], [30, 0, 0], [-5, 0, 0]])
    err = relative_rotation_error_deg(est, gt)
    torch.testing.assert_close(err, torch.tensor([0.0, 5.0, 0.0], dtype=F64), atol=1e-9, rtol=0)
    ypr = relative_ypr_error_deg(est, gt)
    torch.testing.assert_close(ypr, torch.tensor([[0, 0, 0], [5, 0, 0], [0, 0, 0]], dtype=F64), atol=1e-9, rtol=0)


def test_rotation_error_per_axis_signs() -> None:
    gt = _ypr([[0, 0, 0], [10, 5, -3]])
    est = _ypr([[0, 0, 0], [12, 2, -4]])
    ypr = relative_ypr_error_deg(est, gt)
    torch.testing.assert_close(ypr[1], torch.tensor([2.0, -3.0, -1.0], dtype=F64), atol=1e-9, rtol=0)


def test_rotation_error_ignores_a_constant_model_frame_offset() -> None:
    # est_t = gt_t D (a differently oriented head frame): relative rotations are identical.
    g = torch.Generator().manual_seed(1)
    gt = axis_angle_to_matrix(0.5 * torch.randn(6, 3, dtype=F64, generator=g))
    D = axis_angle_to_matrix(torch.tensor([0.3, -0.2, 0.1], dtype=F64))
    err = relative_rotation_error_deg(gt @ D, gt)
    assert float(err.abs().max()) < 1e-6
    ypr = relative_ypr_error_deg(gt @ D, gt)
    assert float(ypr.abs().max()) < 1e-6


def test_per_axis_error_wraps_around_180() -> None:
    gt = _ypr([[0, 0, 0], [179, 0, 0]])
    est = _ypr([[0, 0, 0], [-179, 0, 0]])
    ypr = relative_ypr_error_deg(est, gt)
    torch.testing.assert_close(ypr[1, 0].abs(), torch.tensor(2.0, dtype=F64), atol=1e-9, rtol=0)
    torch.testing.assert_close(relative_rotation_error_deg(est, gt)[1], torch.tensor(2.0, dtype=F64), atol=1e-9, rtol=0)
    half = relative_ypr_error_deg(_ypr([[0, 0, 0], [90, 0, 0]]), _ypr([[0, 0, 0], [-90, 0, 0]]))
    assert float(half[1, 0]) == 180.0  # (-180, 180] as documented: +180, not -180


def test_rotation_error_float32_against_float64_truth() -> None:
    gt = _ypr([[0, 0, 0], [0, 0, 10]])
    est = gt.to(torch.float32)
    err = relative_rotation_error_deg(est, gt)
    assert err.dtype == F64 and float(err.max()) < 1e-3


def test_rotation_jitter_ignores_bias_and_drift_and_measures_a_spike() -> None:
    T = 12
    yaw = torch.linspace(0, 33, T, dtype=F64)
    gt = _ypr([[float(y), 5.0, 0.0] for y in yaw])
    drifting = _ypr([[float(y) + 2.0 + 0.5 * t, 5.0, 0.0] for t, y in enumerate(yaw)])  # bias plus steady drift
    assert float(rotation_jitter_deg(drifting, gt)) < 1e-9
    spiked = _ypr([[float(y) + (4.0 if t == 6 else 0.0), 5.0, 0.0] for t, y in enumerate(yaw)])
    # second differences 4, -8, 4 at frames 5-7: sqrt(96 / (T - 2) / 6) = 4 / sqrt(T - 2)
    assert math.isclose(float(rotation_jitter_deg(spiked, gt)), 4.0 / math.sqrt(T - 2), rel_tol=1e-9)


def test_rotation_jitter_is_the_rms_angle_of_white_noise() -> None:
    g = torch.Generator().manual_seed(3)
    T, sigma = 4000, 0.2  # per-axis standard deviation in degrees
    gt = axis_angle_to_matrix(torch.linspace(0, 1, T, dtype=F64)[:, None] * torch.tensor([0.2, 0.9, 0.1], dtype=F64))
    noise = axis_angle_to_matrix(torch.deg2rad(sigma * torch.randn(T, 3, dtype=F64, generator=g)))
    est = noise @ gt  # camera-frame noise on a smooth turn
    assert abs(float(rotation_jitter_deg(est, gt)) - math.sqrt(3) * sigma) < 0.03 * math.sqrt(3) * sigma
    both = rotation_jitter_deg(torch.stack([est, gt]), torch.stack([gt, gt]))  # batched: (2,)
    assert both.shape == (2,) and float(both[1]) < 1e-9
    with pytest.raises(ValueError, match="T >= 3"):
        rotation_jitter_deg(gt[:2], gt[:2])


# --- translation -----------------------------------------------------------------------------------


def test_translation_errors_known_answer_and_constant_offset() -> None:
    gt = torch.tensor([[0.0, 0, 450], [10, 0, 450], [10, 5, 460]], dtype=F64)
    est = gt + torch.tensor([3.0, 4.0, 0.0], dtype=F64)
    absolute, relative = translation_errors_mm(est, gt)
    torch.testing.assert_close(absolute, torch.full((3,), 5.0, dtype=F64))
    torch.testing.assert_close(relative, torch.zeros(3, dtype=F64))
    est2 = est.clone()
    est2[2, 2] += 12.0
    absolute2, relative2 = translation_errors_mm(est2, gt)
    torch.testing.assert_close(absolute2[2], torch.tensor(13.0, dtype=F64))
    torch.testing.assert_close(relative2[2], torch.tensor(12.0, dtype=F64))


# --- animation units -------------------------------------------------------------------------------


def test_active_units() -> None:
    gt = torch.zeros(4, 3, dtype=F64)
    gt[2, 1] = 0.3
    assert active_units(gt).tolist() == [False, True, False]


def test_unit_rmse_known_answer_and_batch() -> None:
    gt = torch.zeros(4, 2, dtype=F64)
    est = torch.tensor([[0.3, 1.0], [-0.3, -1.0], [0.3, 1.0], [-0.3, -1.0]], dtype=F64)
    ranges = torch.tensor([[0.0, 1.5], [-1.0, 1.0]])
    torch.testing.assert_close(unit_rmse(est, gt, ranges), torch.tensor([0.2, 0.5], dtype=F64))
    batched = unit_rmse(torch.stack([est, gt]), torch.stack([gt, gt]), ranges)
    torch.testing.assert_close(batched, torch.tensor([[0.2, 0.5], [0.0, 0.0]], dtype=F64))


def test_pearson_matches_numpy_and_is_nan_for_constant() -> None:
    g = torch.Generator().manual_seed(2)
    x = torch.randn(50, 3, dtype=F64, generator=g)
    y = 0.7 * x + 0.5 * torch.randn(50, 3, dtype=F64, generator=g)
    y[:, 2] = 1.25
    rho = pearson(x, y)
    for a in range(2):
        ref = np.corrcoef(x[:, a].numpy(), y[:, a].numpy())[0, 1]
        assert math.isclose(float(rho[a]), float(ref), rel_tol=1e-10)
    assert math.isnan(float(rho[2]))
    torch.testing.assert_close(pearson(x[:, :1], -3.0 * x[:, :1] + 2.0), torch.tensor([-1.0], dtype=F64))


def test_pearson_float32_roundoff_constant_is_nan() -> None:
    x = torch.linspace(0, 1, 20).unsqueeze(-1)
    y = torch.full((20, 1), 0.1) + torch.zeros(20, 1)
    assert math.isnan(float(pearson(x, y)[0]))
    big = torch.full((20, 1), 450.0) + torch.zeros(20, 1)  # a large constant: its centring residue is not a swing
    assert math.isnan(float(pearson(x, big)[0]))


def test_pearson_float32_small_swing_on_a_large_offset() -> None:
    """A real swing of std/|mean| ~ 1.6e-4 (below sqrt(float32 eps)) is correlated as float64 correlates it (it
    used to count as constant: NaN)."""
    t = torch.arange(100.0)
    x = (450 + 0.1 * torch.sin(t / 5))[:, None]
    y = x + 0.01 * torch.cos(t)[:, None]
    ref = pearson(y.double(), x.double())
    torch.testing.assert_close(pearson(y, x).double(), ref, atol=2e-3, rtol=0)


# --- whole-sequence summary --------------------------------------------------------------------------


def _synthetic_run(T: int = 11):
    ypr_gt = torch.zeros(T, 3, dtype=F64)
    ypr_gt[:, 0] = torch.linspace(0, 40, T, dtype=F64)
    R_gt = euler_to_matrix(ypr_gt)
    t_gt = torch.zeros(T, 3, dtype=F64)
    t_gt[:, 2] = 450.0
    ypr_est = ypr_gt.clone()
    ypr_est[:, 1] += 2.0  # constant pitch offset: cancels in the relative error
    ypr_est[4, 0] += 15.0  # one lost frame
    ypr_est[7, 0] += 3.0
    R_est = euler_to_matrix(ypr_est)
    t_est = t_gt + torch.tensor([0.0, 0.0, 6.0], dtype=F64)
    status = torch.full((T,), int(TrackStatus.CONVERGED))
    status[2] = int(TrackStatus.MAX_ITERATIONS)
    status[5] = int(TrackStatus.FAILED)
    status[6] = int(TrackStatus.LOST)
    au_gt = torch.zeros(T, 3, dtype=F64)
    au_gt[:, 1] = torch.linspace(0, 1, T, dtype=F64)
    au_est = au_gt.clone()
    au_est[:, 1] += 0.1
    ranges = torch.tensor([[-1.0, 1.0], [0.0, 2.0], [-1.0, 1.0]])
    return R_est, t_est, R_gt, t_gt, status, au_est, au_gt, ranges


def test_sequence_metrics_known_answers() -> None:
    R_est, t_est, R_gt, t_gt, status, au_est, au_gt, ranges = _synthetic_run()
    m = sequence_metrics(
        R_est, t_est, R_gt, t_gt, status, anim_est=au_est, anim_gt=au_gt, anim_ranges=ranges,
        anim_names=("a", "b", "c"),
    )
    assert m.frames == 10
    # With zero roll the pitch offset is R_gt @ R_x(2): a head-frame offset, which cancels exactly.
    assert m.lost_frames == 1 and math.isclose(m.lost_fraction, 0.1)
    assert math.isclose(m.rot_err_max_deg, 15.0, rel_tol=1e-9)
    assert math.isclose(m.rot_err_mean_deg, 1.8, rel_tol=1e-9)
    assert m.rot_err_median_deg < 1e-6
    assert math.isclose(m.yaw_err_deg, 1.8, rel_tol=1e-9) and m.pitch_err_deg < 1e-9 and m.roll_err_deg < 1e-9
    assert math.isclose(m.trans_err_mm, 6.0) and math.isclose(m.trans_rel_err_mm, 0.0, abs_tol=1e-12)
    assert math.isclose(m.init_trans_err_mm, 6.0)
    assert math.isclose(m.init_rot_err_deg, 2.0, rel_tol=1e-9)
    assert math.isclose(m.converged, 0.7) and math.isclose(m.success, 0.8)
    assert m.au_names == ("b",)
    assert math.isclose(m.au_rmse, 0.05, rel_tol=1e-9)
    assert math.isclose(m.au_corr, 1.0, rel_tol=1e-9)
    d = m.as_dict()
    assert d["au_rmse/b"] == m.au_rmse and "au_names" not in d
    assert m.au_inactive_rmse == 0.0 and m.au_inactive_max == 0.0  # units a and c are estimated at rest
    # The yaw errors 0,0,0,0,15,0,0,3,0,0,0: second differences 15,-30,15 and 3,-6,3 over 9 frames.
    assert math.isclose(m.rot_jitter_deg, math.sqrt((2 * 225 + 900 + 2 * 9 + 36) / 9 / 6), rel_tol=1e-9)
    assert d["rot_jitter_deg"] == m.rot_jitter_deg


def test_sequence_metrics_inactive_units() -> None:
    """Motion reported on units the truth leaves at rest: pooled RMSE and worst error, as fractions of range."""
    R_est, t_est, R_gt, t_gt, status, au_est, au_gt, ranges = _synthetic_run()
    au_est = au_est.clone()
    au_est[1:, 0] = 0.2  # unit a (range 2): 0.1 of its range on every scored frame
    au_est[3, 2] = -0.8  # unit c (range 2): 0.4 of its range on one of the 10 scored frames
    au_est[0, 2] = 5.0  # frame 0 (the initial fit) is not scored
    m = sequence_metrics(
        R_est, t_est, R_gt, t_gt, status, anim_est=au_est, anim_gt=au_gt, anim_ranges=ranges,
        anim_names=("a", "b", "c"),
    )
    rmse_a, rmse_c = 0.1, math.sqrt(0.4**2 / 10)
    assert math.isclose(m.au_inactive_rmse, math.sqrt((rmse_a**2 + rmse_c**2) / 2), rel_tol=1e-9)
    assert math.isclose(m.au_inactive_max, 0.4, rel_tol=1e-9)
    assert m.au_names == ("b",) and math.isclose(m.au_rmse, 0.05, rel_tol=1e-9)  # the active unit is unchanged
    everything = au_gt.clone()
    everything[:, [0, 2]] = torch.linspace(0, 1, au_gt.shape[0], dtype=F64)[:, None]
    m_all = sequence_metrics(
        R_est, t_est, R_gt, t_gt, status, anim_est=everything, anim_gt=everything, anim_ranges=ranges,
        anim_names=("a", "b", "c"),
    )
    assert math.isnan(m_all.au_inactive_rmse) and math.isnan(m_all.au_inactive_max)


def test_sequence_metrics_exact_rotation_errors_without_offset() -> None:
    T = 6
    ypr_gt = torch.zeros(T, 3, dtype=F64)
    ypr_gt[:, 2] = torch.linspace(-10, 10, T, dtype=F64)
    ypr_est = ypr_gt.clone()
    ypr_est[1:, 2] += torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0], dtype=F64)
    t = torch.zeros(T, 3, dtype=F64)
    m = sequence_metrics(euler_to_matrix(ypr_est), t, euler_to_matrix(ypr_gt), t, torch.zeros(T, dtype=torch.int64))
    assert math.isclose(m.rot_err_mean_deg, 3.0, rel_tol=1e-9)
    assert math.isclose(m.rot_err_median_deg, 3.0, rel_tol=1e-9)
    assert math.isclose(m.rot_err_max_deg, 5.0, rel_tol=1e-9)
    assert math.isclose(m.roll_err_deg, 3.0, rel_tol=1e-9)
    assert m.yaw_err_deg < 1e-9 and m.pitch_err_deg < 1e-9
    assert math.isnan(m.au_rmse) and m.au_names == ()
    assert m.converged == 1.0 and m.lost_frames == 0


def test_sequence_metrics_constant_estimate_gives_nan_correlation() -> None:
    R_est, t_est, R_gt, t_gt, status, _, au_gt, ranges = _synthetic_run()
    m = sequence_metrics(
        R_est, t_est, R_gt, t_gt, status, anim_est=torch.zeros_like(au_gt), anim_gt=au_gt, anim_ranges=ranges,
        anim_names=("a", "b", "c"),
    )
    assert math.isnan(m.au_corr) and m.au_rmse > 0.2


def test_validation_errors() -> None:
    R = torch.eye(3, dtype=F64).expand(4, 3, 3)
    with pytest.raises(ValueError, match="same shape"):
        relative_rotation_error_deg(R, R[:3])
    with pytest.raises(ValueError, match="rotations"):
        relative_rotations(torch.zeros(4, 3))
    with pytest.raises(TypeError, match="torch.Tensor"):
        translation_errors_mm(np.zeros((4, 3)), torch.zeros(4, 3))
    with pytest.raises(ValueError, match="ranges"):
        unit_rmse(torch.zeros(4, 2), torch.zeros(4, 2), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="hi > lo"):
        unit_rmse(torch.zeros(4, 2), torch.zeros(4, 2), torch.zeros(2, 2))
    with pytest.raises(ValueError, match="status"):
        sequence_metrics(R, torch.zeros(4, 3), R, torch.zeros(4, 3), torch.zeros(3))
    with pytest.raises(ValueError, match="anim_ranges"):
        sequence_metrics(
            R, torch.zeros(4, 3), R, torch.zeros(4, 3), torch.zeros(4, dtype=torch.int64), anim_est=torch.ones(4, 1),
            anim_gt=torch.linspace(0, 1, 4).unsqueeze(-1), anim_names=("a",),
        )



def test_sequence_metrics_names_its_own_arguments_and_refuses_what_it_misread() -> None:
    """A shape mismatch was told of R_gt or t_est (the helpers' names); result.success given as the status (True read
    as 1, False as 0, CONVERGED: failed frames counted usable) and float codes were taken; anim_est without anim_gt
    scored no unit without a word; a NaN lost threshold lost no frame."""
    T = 4
    R = torch.eye(3, dtype=torch.float64).expand(T, 3, 3)
    t = torch.zeros(T, 3, dtype=torch.float64)
    st = torch.zeros(T, dtype=torch.int64)
    for args, kwargs, error, match in [
        ((R, t, R[:3], t, st), {}, ValueError, r"^rotation_gt must be \(4, 3, 3\) like rotation_est's T = 4"),
        ((R, t[:3], R, t, st), {}, ValueError, r"^translation_est must be \(4, 3\)"),
        ((R, t, R, t.numpy(), st), {}, TypeError, r"^translation_gt must be a torch.Tensor, got ndarray"),
        ((R, t, R, t, [0] * T), {}, TypeError, r"^status must be a \(4,\) integer tensor .*got list"),
        ((R, t, R, t, st.bool()), {}, TypeError,
         r"got torch.bool \(result.success is a bool flag: give result.status\)"),
        ((R, t, R, t, st.float()), {}, TypeError, r"^status must hold the integer TrackStatus codes"),
        ((R, t, R, t, st), {"anim_est": torch.zeros(T, 2)}, ValueError, "^anim_est was given without anim_gt"),
        ((R, t, R, t, st), {"anim_gt": torch.zeros(T, 2)}, ValueError, "^anim_gt was given without anim_est"),
        ((R, t, R, t, st), {"anim_est": torch.zeros(T - 1, 2), "anim_gt": torch.zeros(T, 2)}, ValueError,
         r"^anim_est must be a \(4, A\) tensor"),
        ((R, t, R, t, st), {"anim_est": torch.zeros(T, 3), "anim_gt": torch.zeros(T, 2)}, ValueError,
         "^anim_est and anim_gt must have the same units"),
        ((R, t, R, t, st), {"lost_threshold_deg": float("nan")}, ValueError, "^lost_threshold_deg must be a finite"),
    ]:
        with pytest.raises(error, match=match):
            sequence_metrics(*args, **kwargs)
    ok = torch.ones(T, dtype=torch.bool)
    with pytest.raises(ValueError, match="^lost_threshold_deg must be a finite number > 0, got -1"):
        long_run_metrics(torch.zeros(T), ok, ok, [1], lost_threshold_deg=-1)
    assert sequence_metrics(R, t, R, t, st.to(torch.int32)).success == 1.0  # (any integer dtype)
    scan = sequence_metrics(R, t, R, t, st, anim_est=torch.zeros(T, 11), anim_gt=torch.zeros(T, 0))  # (no unit)
    assert math.isnan(scan.au_rmse) and scan.au_names == ()

# --- long runs: returns to frontal, recovery ---------------------------------------------------------


def test_true_runs_known_answers() -> None:
    t, f = True, False
    assert true_runs(torch.tensor([t, t, f, t, f, f, t])) == ((0, 2), (3, 4), (6, 7))
    assert true_runs(torch.tensor([f, f])) == ()
    assert true_runs(torch.tensor([t, t, t])) == ((0, 3),)
    assert true_runs(torch.zeros(0, dtype=torch.bool)) == ()
    with pytest.raises(ValueError, match="bool"):
        true_runs(torch.tensor([1, 0]))


def _long_errors(T: int = 40) -> torch.Tensor:
    """Rotation errors of a made-up run: 0.3 deg everywhere, 0.4 and 0.7 at the returns (frames 19, 30)."""
    err = torch.full((T,), 0.3, dtype=F64)
    err[0] = 0.0
    err[19] = 0.4
    err[30] = 0.7
    return err


def test_long_run_metrics_returns_recovery_and_losses() -> None:
    T = 40
    err = _long_errors(T)
    err[10:13] = 15.0  # lost (error) while in view
    visible = torch.ones(T, dtype=torch.bool)
    visible[22:25] = False  # out of view: frames 22-24, back at 25
    success = torch.ones(T, dtype=torch.bool)
    success[22:28] = False  # lost until frame 27: recovered 3 frames after the face is back
    success[23] = True  # a (bogus) success while out of view
    m = long_run_metrics(err, success, visible, [19, 30], hold=3)
    assert m.return_errors_deg == (0.4, 0.7) and m.return_frames == (19, 30)
    assert m.recoveries == (Recovery(22, 25, 3, "out of view"),)
    assert m.worst_recovery() == 3 and m.worst_recovery("occluded") == 0
    assert m.success_out_of_view == 1
    assert m.lost_frames == 3 and m.unsuccessful_frames == 3  # frames 10-12; frames 25-27
    # The loss at 10-12 is one in view; the bad frames 25-27 are the recovery, not a loss in view.
    assert m.losses_in_view == ((10, 13),) and m.longest_loss_in_view == 3 and m.longest_error_loss_in_view == 3
    # Mean / max over in-view frames 1 .. T-1; and over the successful ones among them.
    keep = visible.clone()
    keep[0] = False
    assert m.rot_err_mean_deg == pytest.approx(float(err[keep].mean())) and m.rot_err_max_deg == 15.0
    assert m.rot_err_mean_success_deg == pytest.approx(float(err[keep & success].mean()))


def test_long_run_metrics_occlusion_is_a_hidden_stretch() -> None:
    T = 40
    err = _long_errors(T)
    visible = torch.ones(T, dtype=torch.bool)
    occluded = torch.zeros(T, dtype=torch.bool)
    occluded[5:15] = True
    success = torch.ones(T, dtype=torch.bool)
    success[8:17] = False  # unsuccessful under the occluder and 2 frames after it
    m = long_run_metrics(err, success, visible, [19], occluded=occluded, hold=2)
    assert m.recoveries == (Recovery(5, 15, 2, "occluded"),)
    assert m.losses_in_view == () and m.unsuccessful_frames == 9 and m.unsuccessful_occluded == 7
    # Without the occluder flags the same frames are a loss in view.
    m = long_run_metrics(err, success, visible, [19], hold=2)
    assert m.recoveries == () and m.losses_in_view == ((8, 17),) and m.longest_loss_in_view == 9
    assert m.longest_error_loss_in_view == 0  # marked unsuccessful, but the error stayed small
    err[20:24] = 11.0
    assert long_run_metrics(err, success, visible, [19], hold=2).longest_error_loss_in_view == 4


def test_long_run_metrics_never_recovered_and_hold() -> None:
    T = 40
    err = _long_errors(T)
    visible = torch.ones(T, dtype=torch.bool)
    visible[5:8] = False
    visible[30:33] = False
    success = torch.ones(T, dtype=torch.bool)
    success[5:] = False  # never again
    m = long_run_metrics(err, success, visible, [19], hold=1)
    assert m.recoveries == (Recovery(5, 8, None), Recovery(30, 33, None)) and m.worst_recovery() is None
    # A good run shorter than `hold` does not count; one of `hold` frames does, from its first frame.
    success = torch.ones(T, dtype=torch.bool)
    success[5:20] = False
    success[10:12] = True
    m3 = long_run_metrics(err, success, visible, [19], hold=3)
    assert m3.recoveries[0] == Recovery(5, 8, 12)  # frames 20, 21, 22 are the first 3 good in a row
    m2 = long_run_metrics(err, success, visible, [19], hold=2)
    assert m2.recoveries[0] == Recovery(5, 8, 2)  # frames 10, 11
    # The recovery is looked for only before the next stretch out of view.
    success[8:30] = False
    assert long_run_metrics(err, success, visible, [19]).recoveries[0].frames_to_recover is None
    # A sequence ending out of view: the stretch ends at T.
    visible[35:] = False
    assert long_run_metrics(err, success, visible, [19]).recoveries[-1] == Recovery(35, 40, None)


def test_long_run_metrics_validation() -> None:
    err = _long_errors()
    ok = torch.ones(40, dtype=torch.bool)
    with pytest.raises(ValueError, match="return_frames"):
        long_run_metrics(err, ok, ok, [40])
    with pytest.raises(ValueError, match="return_frames"):
        long_run_metrics(err, ok, ok, [0])
    with pytest.raises(ValueError, match="success"):
        long_run_metrics(err, ok[:5], ok, [1])
    with pytest.raises(ValueError, match="visible"):
        long_run_metrics(err, ok, ok.float(), [1])
    with pytest.raises(ValueError, match="occluded"):
        long_run_metrics(err, ok, ok, [1], occluded=ok[:3])
    with pytest.raises(ValueError, match="hold"):
        long_run_metrics(err, ok, ok, [1], hold=0)
    with pytest.raises(ValueError, match="NaN"):
        long_run_metrics(torch.full((40,), float("nan"), dtype=F64), ok, ok, [1])


# --- AUROC -------------------------------------------------------------------------------------------


def test_auroc_known_answers() -> None:
    assert auroc(torch.tensor([0.9, 0.8]), torch.tensor([0.1, 0.2])) == 1.0
    assert auroc(torch.tensor([0.1, 0.2]), torch.tensor([0.9, 0.8])) == 0.0
    assert auroc(torch.tensor([0.5, 0.5]), torch.tensor([0.5])) == 0.5
    assert auroc(torch.tensor([0.9, 0.8]), torch.tensor([0.1, 0.8])) == 0.875
    assert math.isnan(auroc(torch.tensor([0.9]), torch.tensor([])))
    with pytest.raises(ValueError, match="NaN"):
        auroc(torch.tensor([float("nan")]), torch.tensor([0.1]))


def test_auroc_matches_pairwise_count() -> None:
    g = torch.Generator().manual_seed(3)
    pos = torch.randint(0, 6, (37,), generator=g).double() / 5  # many ties
    neg = torch.randint(0, 6, (23,), generator=g).double() / 5 - 0.2
    pairs = (pos[:, None] > neg[None, :]).double() + 0.5 * (pos[:, None] == neg[None, :]).double()
    assert auroc(pos, neg) == pytest.approx(float(pairs.mean()), abs=1e-12)


# --- independent re-implementations (numpy, float64) of the definitions ---------------------------------------


def _np_angle_deg(M: np.ndarray) -> float:
    """Geodesic angle of a rotation matrix from its axis-angle (scipy-free): ``atan2(|vee|, (tr - 1) / 2)``."""
    vee = 0.5 * np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    return math.degrees(math.atan2(float(np.linalg.norm(vee)), (np.trace(M) - 1.0) / 2.0))


def _np_ypr(R: np.ndarray) -> np.ndarray:
    """Yaw, pitch, roll (degrees) of ``R = R_y R_x R_z`` away from gimbal lock."""
    return np.degrees([math.atan2(R[0, 2], R[2, 2]), math.asin(-R[1, 2]), math.atan2(R[1, 0], R[1, 1])])


def test_rotation_error_is_of_R_t_R_0T_not_R_0T_R_t() -> None:
    """The issue's convention, ``R_t R_0^T``: a camera-side offset of the first fit does count (a head-frame one
    does not, test above); ``R_0^T R_t`` would score this run as perfect."""
    est = _ypr([[10, 0, 0], [0, 0, 0]])
    est[1] = est[0] @ _ypr([[0, 20, 0]])[0]  # est_1 = est_0 R_x(20): R_0^T R_t equals the truth's
    gt = _ypr([[0, 0, 0], [0, 20, 0]])
    e, g = est.numpy(), gt.numpy()
    assert _np_angle_deg((e[0].T @ e[1]) @ (g[0].T @ g[1]).T) < 1e-9  # the other convention: no error
    want = _np_angle_deg((e[1] @ e[0].T) @ (g[1] @ g[0].T).T)
    assert want > 3.0
    assert math.isclose(float(relative_rotation_error_deg(est, gt)[1]), want, rel_tol=1e-12)


def test_rotation_error_180_degrees_and_sign_flip() -> None:
    gt = _ypr([[0, 0, 0], [0, 0, 0], [15, 0, 0]])
    est = _ypr([[0, 0, 0], [180, 0, 0], [-15, 0, 0]])  # half a turn; then the yaw's sign flipped
    err = relative_rotation_error_deg(est, gt)
    torch.testing.assert_close(err, torch.tensor([0.0, 180.0, 30.0], dtype=F64), atol=1e-9, rtol=0)
    ypr = relative_ypr_error_deg(est, gt)
    torch.testing.assert_close(ypr[1:], torch.tensor([[180.0, 0, 0], [-30.0, 0, 0]], dtype=F64), atol=1e-9, rtol=0)


def test_sequence_metrics_match_a_numpy_reimplementation_on_a_float32_estimate() -> None:
    """Random turns, a float32 estimate (not exactly orthonormal): every rotation figure against numpy on the
    SVD-projected matrices, and frame 0's own status and error kept out of the statistics."""
    g = torch.Generator().manual_seed(7)
    T = 40
    gt = euler_to_matrix(torch.cat([torch.zeros(1, 3, dtype=F64), 25 * torch.randn(T - 1, 3, dtype=F64, generator=g)]))
    noise = axis_angle_to_matrix(torch.deg2rad(1.5 * torch.randn(T, 3, dtype=F64, generator=g)))
    est = (noise @ gt).to(torch.float32)
    t = torch.zeros(T, 3, dtype=F64)
    status = torch.full((T,), int(TrackStatus.CONVERGED))
    status[0] = int(TrackStatus.FAILED)
    status[[3, 9]] = int(TrackStatus.MAX_ITERATIONS)
    m = sequence_metrics(est, t, gt, t, status)

    def project(R: np.ndarray) -> np.ndarray:
        u, _, vt = np.linalg.svd(R)
        return u @ vt

    e = np.stack([project(r) for r in est.double().numpy()])
    G = gt.numpy()
    rel_e, rel_g = e @ e[0].T, G @ G[0].T
    err = np.array([_np_angle_deg(rel_e[i] @ rel_g[i].T) for i in range(1, T)])
    assert m.frames == T - 1
    assert m.rot_err_mean_deg == pytest.approx(err.mean(), abs=1e-5)
    assert m.rot_err_median_deg == pytest.approx(np.median(err), abs=1e-5)  # T - 1 odd: one middle value
    assert m.rot_err_max_deg == pytest.approx(err.max(), abs=1e-5)
    d = np.array([_np_ypr(rel_e[i]) - _np_ypr(rel_g[i]) for i in range(1, T)])
    d = (d + 180.0) % 360.0 - 180.0
    assert [m.yaw_err_deg, m.pitch_err_deg, m.roll_err_deg] == pytest.approx(np.abs(d).mean(0), abs=1e-4)
    assert m.init_rot_err_deg == pytest.approx(_np_angle_deg(e[0] @ G[0].T), abs=1e-5)
    assert m.converged == pytest.approx((T - 3) / (T - 1)) and m.success == 1.0  # frame 0's FAILED not counted
    assert m.lost_frames == int((err > 10.0).sum())


def test_long_run_metrics_match_a_brute_force_reading_of_the_definitions() -> None:
    """Recoveries, lost and unsuccessful frames on random short runs against a frame-by-frame loop."""
    rng = np.random.default_rng(0)

    def brute(err, ok, vis, occ, hold):
        T = len(err)
        good = ok & (err <= 10.0)
        hidden = ~(vis & ~occ)
        hidden[0] = False
        gaps, f = [], 1
        while f < T:
            if hidden[f]:
                s = f
                while f < T and hidden[f]:
                    f += 1
                gaps.append((s, f))
            else:
                f += 1
        out = []
        for i, (s, e) in enumerate(gaps):
            limit = gaps[i + 1][0] if i + 1 < len(gaps) else T
            hit = next((f - e for f in range(e, limit - hold + 1) if good[f : f + hold].all()), None)
            out.append(Recovery(s, e, hit, "out of view" if not vis[s:e].all() else "occluded"))
        return tuple(out), int((vis & (err > 10.0))[1:].sum()), int((vis & ~ok)[1:].sum())

    for _ in range(300):
        T, hold = int(rng.integers(2, 30)), int(rng.integers(1, 5))
        err = rng.choice([0.5, 20.0], T, p=[0.7, 0.3])
        ok, vis, occ = rng.random(T) < 0.8, rng.random(T) < 0.8, rng.random(T) < 0.15
        m = long_run_metrics(
            torch.from_numpy(err), torch.from_numpy(ok), torch.from_numpy(vis), [1], occluded=torch.from_numpy(occ),
            hold=hold,
        )
        assert (m.recoveries, m.lost_frames, m.unsuccessful_frames) == brute(err, ok, vis, occ, hold)


def test_a_nan_pose_counts_as_lost() -> None:
    """A frame whose estimated rotation is NaN is lost (``NaN > threshold`` is False: it counted 0 lost frames
    while the mean and max were NaN)."""
    T = 5
    gt = torch.eye(3, dtype=F64).expand(T, 3, 3).clone()
    est = gt.clone()
    est[3] = float("nan")
    t = torch.zeros(T, 3, dtype=F64)
    m = sequence_metrics(est, t, gt, t, torch.zeros(T, dtype=torch.int64))
    assert m.lost_frames == 1 and math.isnan(m.rot_err_max_deg)


def test_matrices_that_are_not_rotations_are_refused_naming_the_frame() -> None:
    """A scaled, sheared or mirrored matrix is refused with its index (it was scored as the angle of no rotation: a
    yaw of 20 degrees scaled by 2 read 0 degrees off a 20-degree truth), while rows with NaN stay lost poses and a
    float32 tracker's or a float16 rotation's rounding passes."""
    gt = euler_to_matrix(torch.tensor([[0.0, 0, 0], [20.0, 0, 0], [40.0, 10, 0]], dtype=F64))
    for bad, what in ((gt[1] * 2.0, "scaled"), (gt[1] @ torch.diag(torch.tensor([1.0, 1, -1], dtype=F64)), "mirror"),
                      (gt[1] + 0.01 * torch.ones(3, 3, dtype=F64), "sheared")):  # fmt: skip
        est = gt.clone()
        est[1] = bad
        with pytest.raises(ValueError, match=r"R_est must hold rotation matrices .*R_est\[1\]"):
            relative_rotation_error_deg(est, gt)
        with pytest.raises(ValueError, match=r"rotation_gt must hold rotation matrices .*rotation_gt\[1\]"):
            sequence_metrics(gt, torch.zeros(3, 3), est, torch.zeros(3, 3), torch.zeros(3, dtype=torch.int64))
        with pytest.raises(ValueError, match=r"R_gt must hold .*R_gt\[1, 1\]"):  # (a batch: its full index)
            rotation_jitter_deg(gt.expand(2, 3, 3, 3), torch.stack([gt, est]))
    nan = gt.clone()
    nan[2] = float("nan")
    assert torch.isnan(relative_rotation_error_deg(nan, gt)[2])
    for dtype in (torch.float32, torch.float16, torch.bfloat16):
        relative_rotations(gt.to(dtype))


def test_the_worst_seed_of_a_seed_table_is_nan_when_a_seed_broke() -> None:
    """``evaluate.seed_table``'s "worst over N seeds" line: Python's ``max`` skipped a NaN after the first value
    (seeds 0.2 and NaN printed "worst ... rot mean 0.20")."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/_helpers.py
    from _helpers import load_script

    evaluate = load_script("evaluate")
    keys = ("rot_err_median_deg", "yaw_err_deg", "pitch_err_deg", "roll_err_deg", "trans_err_mm", "trans_rel_err_mm",
            "au_rmse", "au_corr", "converged", "success", "ms_per_frame", "rot_jitter_deg", "au_inactive_rmse")
    ok = dict.fromkeys(keys, 0.1) | {"rot_err_mean_deg": 0.2, "rot_err_max_deg": 0.9, "lost_frames": 0}
    broke = ok | {"rot_err_mean_deg": float("nan"), "rot_err_max_deg": float("nan"), "lost_frames": 3}
    text = evaluate.seed_table("x", {"0": ok, "1": broke}, "")
    assert text.splitlines()[-1].strip() == "worst over 2 seeds: rot mean - deg, max - deg, lost 3", text
    text = evaluate.seed_table("x", {"0": ok, "1": dict(ok, rot_err_mean_deg=0.3)}, "")
    assert text.splitlines()[-1].strip() == "worst over 2 seeds: rot mean 0.30 deg, max 0.90 deg, lost 0", text
