"""Tests for torchface.geometry.so3: exp/log maps, Euler angles, geodesic distance, Jacobians."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation
from torch.autograd.functional import jacobian

from torchface.geometry import Intrinsics, project_points, transform_points
from torchface.geometry.so3 import (
    axis_angle_to_matrix,
    euler_to_matrix,
    geodesic_angle_deg,
    hat,
    left_jacobian,
    matrix_to_axis_angle,
    matrix_to_euler,
    rotate_points_jacobian,
    vee,
)

F64 = torch.float64


def random_axis_angle(n: int, lo: float, hi: float, seed: int = 0, dtype: torch.dtype = F64) -> torch.Tensor:
    """``(n, 3)`` axis-angle vectors with random axes and angles uniform in ``[lo, hi]``."""
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(n, 3, generator=g, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = lo + (hi - lo) * torch.rand(n, 1, generator=g, dtype=F64)
    return (axis * angle).to(dtype)


def assert_rotation(R: torch.Tensor, atol: float) -> None:
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, atol=atol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(R.shape[:-2], dtype=R.dtype), atol=atol, rtol=0)


# ----------------------------------------------------------------------------------------------- hat / vee
def test_hat_is_cross_product_and_vee_inverts_it() -> None:
    g = torch.Generator().manual_seed(1)
    v, x = torch.randn(4, 5, 3, generator=g, dtype=F64), torch.randn(4, 5, 3, generator=g, dtype=F64)
    K = hat(v)
    assert K.shape == (4, 5, 3, 3)
    torch.testing.assert_close((K @ x[..., None]).squeeze(-1), torch.linalg.cross(v, x))
    torch.testing.assert_close(K.transpose(-1, -2), -K)
    torch.testing.assert_close(vee(K), v)


@pytest.mark.parametrize(
    "fn, arg",
    [
        (hat, torch.zeros(2, 4)),
        (vee, torch.zeros(3, 2)),
        (axis_angle_to_matrix, torch.zeros(5)),
        (matrix_to_axis_angle, torch.zeros(2, 3, 4)),
        (euler_to_matrix, torch.zeros(2, 2)),
        (matrix_to_euler, torch.zeros(3)),
        (left_jacobian, torch.zeros(1, 2)),
    ],
)
def test_bad_shapes_raise_value_error(fn, arg) -> None:
    with pytest.raises(ValueError, match="must have shape"):
        fn(arg)


def test_bad_types_raise_type_error() -> None:
    with pytest.raises(TypeError, match="floating-point"):
        axis_angle_to_matrix(torch.zeros(1, 3, dtype=torch.int64))
    with pytest.raises(TypeError, match="torch.Tensor"):
        axis_angle_to_matrix([0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"\(B, 3\)"):
        rotate_points_jacobian(torch.zeros(3), torch.zeros(4, 3))
    with pytest.raises(ValueError, match="batch sizes"):
        rotate_points_jacobian(torch.zeros(2, 3), torch.zeros(3, 4, 3))


# ------------------------------------------------------------------------------------------- exp map
def test_axis_angle_to_matrix_matches_scipy_and_is_a_rotation() -> None:
    aa = torch.cat((random_axis_angle(64, 0.0, math.pi), random_axis_angle(16, 0.0, 0.6, seed=3)))
    R = axis_angle_to_matrix(aa)
    assert R.shape == (80, 3, 3) and R.dtype == F64
    expected = torch.from_numpy(Rotation.from_rotvec(aa.numpy()).as_matrix())
    torch.testing.assert_close(R, expected, atol=1e-14, rtol=0)
    assert_rotation(R, 1e-14)


def test_axis_angle_to_matrix_known_answers_and_dtype() -> None:
    aa = torch.tensor([[0.0, 0.0, math.pi / 2], [0.0, 0.0, 0.0]])
    R = axis_angle_to_matrix(aa)
    assert R.dtype == torch.float32
    expected = torch.tensor([[[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], torch.eye(3).tolist()])
    torch.testing.assert_close(R, expected, atol=1e-6, rtol=0)
    # Leading dims are free.
    assert axis_angle_to_matrix(torch.zeros(2, 3, 4, 3)).shape == (2, 3, 4, 3, 3)


def test_axis_angle_to_matrix_series_and_closed_form_agree_at_the_switch() -> None:
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=F64)
    axis = axis / axis.norm()
    below, above = axis * (0.5 - 1e-12), axis * (0.5 + 1e-12)
    aa = torch.stack((below, above)).requires_grad_(True)
    R = axis_angle_to_matrix(aa)
    torch.testing.assert_close(R[0], R[1], atol=1e-11, rtol=0)
    w = torch.randn(3, 3, dtype=F64, generator=torch.Generator().manual_seed(2))
    (g,) = torch.autograd.grad((R * w).sum(), aa)
    torch.testing.assert_close(g[0], g[1], atol=1e-10, rtol=0)
    # float32 agrees with float64 on both sides of the switch.
    R32 = axis_angle_to_matrix(aa.detach().float())
    torch.testing.assert_close(R32.double(), R.detach(), atol=3e-7, rtol=0)


def test_axis_angle_to_matrix_backward_at_exact_zero_matches_finite_differences() -> None:
    weights = torch.randn(3, 3, dtype=F64, generator=torch.Generator().manual_seed(4))
    aa = torch.zeros(1, 3, dtype=F64, requires_grad=True)
    (grad,) = torch.autograd.grad((axis_angle_to_matrix(aa) * weights).sum(), aa)
    assert torch.isfinite(grad).all()
    h = 1e-6
    fd = torch.zeros(3, dtype=F64)
    for j in range(3):
        step = torch.zeros(1, 3, dtype=F64)
        step[0, j] = h
        fd[j] = ((axis_angle_to_matrix(step) - axis_angle_to_matrix(-step)) * weights).sum() / (2 * h)
    torch.testing.assert_close(grad[0], fd, atol=1e-9, rtol=0)
    # The derivative of exp at zero is hat: d R / d w_j = hat(e_j), so grad_j = <weights, hat(e_j)>.
    expected = torch.stack([(hat(torch.eye(3, dtype=F64)[j]) * weights).sum() for j in range(3)])
    torch.testing.assert_close(grad[0], expected, atol=1e-14, rtol=0)


def test_axis_angle_to_matrix_matches_the_matrix_exponential_near_zero() -> None:
    """Against ``torch.linalg.matrix_exp`` of the skew matrix, at small, tiny and zero angles."""
    gen = torch.Generator().manual_seed(0)
    w = torch.cat([torch.randn(4, 3, generator=gen, dtype=F64), 1e-5 * torch.randn(2, 3, generator=gen, dtype=F64),
                   1e-12 * torch.randn(2, 3, generator=gen, dtype=F64), torch.zeros(1, 3, dtype=F64)])
    torch.testing.assert_close(axis_angle_to_matrix(w), torch.linalg.matrix_exp(hat(w)), rtol=0, atol=1e-12)


def test_cached_generators_survive_inference_mode() -> None:
    """The generators and identity are cached per dtype and device; made first under inference mode (a tracker
    run in a dataloader), they must still serve a later differentiable call, and never be modified by one."""
    from torchface.geometry.so3 import _so3_generators

    _so3_generators.cache_clear()
    w = torch.tensor([[0.1, -0.2, 0.3]], dtype=F64)
    with torch.inference_mode():
        axis_angle_to_matrix(w)
    g, eye = _so3_generators(F64, w.device)
    assert not g.is_inference() and not eye.is_inference()
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (w.clone().requires_grad_(True),))
    torch.testing.assert_close(eye, torch.eye(3, dtype=F64), rtol=0, atol=0)
    assert axis_angle_to_matrix(w).data_ptr() != eye.data_ptr()


@pytest.mark.parametrize("case", ["zero", "tiny", "small", "switch", "general"])
def test_axis_angle_to_matrix_gradcheck(case: str) -> None:
    aa = {
        "zero": torch.zeros(2, 3, dtype=F64),
        "tiny": random_axis_angle(2, 1e-9, 1e-7, seed=5),
        "small": random_axis_angle(2, 1e-3, 1e-2, seed=6),
        "switch": random_axis_angle(2, 0.499, 0.501, seed=7),
        "general": random_axis_angle(3, 0.6, 3.0, seed=8),
    }[case].requires_grad_(True)
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (aa,))


# ------------------------------------------------------------------------------------------- log map
@pytest.mark.parametrize(
    "lo, hi, atol",
    [(0.0, 0.0, 0.0), (1e-9, 1e-7, 1e-22), (1e-4, 1e-2, 1e-17), (0.01, 3.0, 2e-15), (math.pi - 1e-3, math.pi - 1e-7, 1e-9)],
)
def test_log_exp_round_trip_float64(lo: float, hi: float, atol: float) -> None:
    aa = random_axis_angle(32, lo, hi, seed=9)
    back = matrix_to_axis_angle(axis_angle_to_matrix(aa))
    torch.testing.assert_close(back, aa, atol=max(atol, 1e-300), rtol=1e-12)


def test_log_exp_round_trip_float32() -> None:
    aa = torch.cat(
        (random_axis_angle(32, 0.0, 0.01, seed=10), random_axis_angle(32, 0.01, math.pi - 1e-2, seed=11),
         random_axis_angle(32, math.pi - 1e-2, math.pi - 1e-5, seed=12))
    )
    back = matrix_to_axis_angle(axis_angle_to_matrix(aa.float()))
    assert back.dtype == torch.float32
    # Compare rotations (the log is ill-conditioned right at pi): angle between them in float32.
    err = geodesic_angle_deg(axis_angle_to_matrix(back.double()), axis_angle_to_matrix(aa))
    assert err.max() < 1e-3
    torch.testing.assert_close(back[:64].double(), aa[:64], atol=2e-6, rtol=0)


def test_log_at_exactly_pi_returns_a_valid_axis() -> None:
    axes = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 0.0], [1.0, -2.0, 3.0]], dtype=F64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    R = axis_angle_to_matrix(axes * math.pi)
    aa = matrix_to_axis_angle(R)
    torch.testing.assert_close(aa.norm(dim=-1), torch.full((5,), math.pi, dtype=F64))
    torch.testing.assert_close(axis_angle_to_matrix(aa), R, atol=1e-14, rtol=0)


def test_log_matches_scipy() -> None:
    aa = random_axis_angle(64, 0.0, math.pi - 1e-3, seed=13)
    R = axis_angle_to_matrix(aa)
    expected = torch.from_numpy(Rotation.from_matrix(R.numpy()).as_rotvec())
    torch.testing.assert_close(matrix_to_axis_angle(R), expected, atol=1e-12, rtol=0)


@pytest.mark.parametrize("case", ["identity", "small", "general", "near_pi"])
def test_matrix_to_axis_angle_gradcheck(case: str) -> None:
    aa = {
        "identity": torch.zeros(2, 3, dtype=F64),
        "small": random_axis_angle(2, 1e-4, 1e-3, seed=14),
        "general": random_axis_angle(3, 0.1, 2.0, seed=15),
        "near_pi": random_axis_angle(2, 2.3, 2.9, seed=16),
    }[case]
    R = axis_angle_to_matrix(aa).requires_grad_(True)
    assert torch.autograd.gradcheck(matrix_to_axis_angle, (R,))


@pytest.mark.parametrize("lo, hi", [(0.0, 0.0), (1e-6, 1e-4), (0.2, 2.0), (2.5, 3.1)])
def test_log_of_exp_has_identity_jacobian(lo: float, hi: float) -> None:
    aa = random_axis_angle(3, lo, hi, seed=17)
    J = jacobian(lambda x: matrix_to_axis_angle(axis_angle_to_matrix(x)), aa)  # (3, 3, 3, 3)
    blocks = torch.stack([J[i, :, i, :] for i in range(3)])
    torch.testing.assert_close(blocks, torch.eye(3, dtype=F64).expand(3, 3, 3), atol=1e-9, rtol=0)


# ------------------------------------------------------------------------------------------- Euler
def random_ypr(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=g, dtype=F64)
    return torch.stack((360 * u[:, 0] - 180, 178 * u[:, 1] - 89, 360 * u[:, 2] - 180), dim=-1)


def test_euler_to_matrix_matches_intrinsic_yxz() -> None:
    ypr = random_ypr(50, seed=18)
    expected = torch.from_numpy(Rotation.from_euler("YXZ", ypr.numpy(), degrees=True).as_matrix())
    torch.testing.assert_close(euler_to_matrix(ypr), expected, atol=1e-14, rtol=0)


def test_euler_round_trips() -> None:
    ypr = random_ypr(200, seed=19)
    torch.testing.assert_close(matrix_to_euler(euler_to_matrix(ypr)), ypr, atol=1e-10, rtol=0)
    R = axis_angle_to_matrix(random_axis_angle(100, 0.0, math.pi, seed=20))
    torch.testing.assert_close(euler_to_matrix(matrix_to_euler(R)), R, atol=1e-12, rtol=0)
    pitch = matrix_to_euler(R)[:, 1]
    assert (pitch.abs() <= 90).all()


@pytest.mark.parametrize("pitch", [90.0, -90.0])
def test_euler_gimbal_lock_reconstructs_the_rotation_with_finite_gradients(pitch: float) -> None:
    ypr = torch.tensor([[35.0, pitch, 0.0], [10.0, pitch, -25.0]], dtype=F64)
    R = euler_to_matrix(ypr).requires_grad_(True)
    out = matrix_to_euler(R)
    torch.testing.assert_close(out[:, 1], ypr[:, 1])
    torch.testing.assert_close(out[:, 2], torch.zeros(2, dtype=F64))
    torch.testing.assert_close(euler_to_matrix(out), R.detach(), atol=1e-12, rtol=0)
    (g,) = torch.autograd.grad(out.sum(), R)
    assert torch.isfinite(g).all()


def test_euler_signs_follow_the_conventions() -> None:
    nose = torch.tensor([0.0, 0.0, -1.0], dtype=F64)  # the nose is at -z in the head frame
    cam = Intrinsics.default(640, 480)
    t = torch.tensor([[0.0, 0.0, 600.0]], dtype=F64)
    # Face centre, nose tip, a point on the subject's left cheek (image right) and on the forehead (up).
    head = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, -40.0], [50.0, 0.0, 0.0], [0.0, -50.0, 0.0]], dtype=F64)

    def image(ypr: list[float]) -> torch.Tensor:
        R = euler_to_matrix(torch.tensor([ypr], dtype=F64))
        return project_points(transform_points(R, t, head), cam)[0]

    frontal = image([0.0, 0.0, 0.0])
    # Positive yaw: the nose moves toward image left.
    assert (euler_to_matrix(torch.tensor([20.0, 0, 0], dtype=F64)) @ nose)[0] < 0
    assert image([20.0, 0.0, 0.0])[1, 0] < frontal[1, 0] - 5
    # Positive pitch: the nose tips down (image v increases).
    assert (euler_to_matrix(torch.tensor([0, 20.0, 0], dtype=F64)) @ nose)[1] > 0
    assert image([0.0, 20.0, 0.0])[1, 1] > frontal[1, 1] + 5
    # Positive roll: clockwise in the image (y down): the right point moves down, the top point right.
    rolled = image([0.0, 0.0, 20.0])
    assert rolled[2, 1] > frontal[2, 1] + 5 and rolled[3, 0] > frontal[3, 0] + 5
    # Reading back the angles keeps their signs.
    torch.testing.assert_close(
        matrix_to_euler(euler_to_matrix(torch.tensor([20.0, -10.0, 5.0], dtype=F64))),
        torch.tensor([20.0, -10.0, 5.0], dtype=F64),
    )


# ------------------------------------------------------------------------------------------- geodesic
def test_geodesic_angle_known_values_and_symmetry() -> None:
    aa = random_axis_angle(40, 0.0, math.pi, seed=21)
    R = axis_angle_to_matrix(aa)
    eye = torch.eye(3, dtype=F64)
    torch.testing.assert_close(geodesic_angle_deg(R, eye), torch.rad2deg(aa.norm(dim=-1)), atol=1e-10, rtol=0)
    R2 = axis_angle_to_matrix(random_axis_angle(40, 0.0, math.pi, seed=22))
    torch.testing.assert_close(geodesic_angle_deg(R, R2), geodesic_angle_deg(R2, R))
    # Left-invariance: d(Q R, Q R2) = d(R, R2).
    Q = axis_angle_to_matrix(random_axis_angle(1, 0.5, 2.5, seed=23))
    torch.testing.assert_close(geodesic_angle_deg(Q @ R, Q @ R2), geodesic_angle_deg(R, R2))
    # Accurate at both ends, where acos would lose precision.
    tiny = axis_angle_to_matrix(torch.tensor([1e-9, 0.0, 0.0], dtype=F64))
    torch.testing.assert_close(geodesic_angle_deg(tiny, eye), torch.tensor(math.degrees(1e-9), dtype=F64), rtol=1e-6, atol=0)
    flip = axis_angle_to_matrix(torch.tensor([0.0, math.pi - 1e-9, 0.0], dtype=F64))
    torch.testing.assert_close(
        geodesic_angle_deg(flip, eye), torch.tensor(math.degrees(math.pi - 1e-9), dtype=F64), rtol=1e-12, atol=0
    )


def test_geodesic_angle_gradients() -> None:
    R1 = axis_angle_to_matrix(random_axis_angle(3, 0.2, 2.5, seed=24)).requires_grad_(True)
    R2 = axis_angle_to_matrix(random_axis_angle(3, 0.2, 2.5, seed=25)).requires_grad_(True)
    assert torch.autograd.gradcheck(geodesic_angle_deg, (R1, R2))
    same = torch.eye(3, dtype=F64)[None].repeat(2, 1, 1).requires_grad_(True)
    (g,) = torch.autograd.grad(geodesic_angle_deg(same, torch.eye(3, dtype=F64)).sum(), same)
    assert torch.isfinite(g).all()


# ------------------------------------------------------------------------------------------- Jacobians
@pytest.mark.parametrize("lo, hi", [(0.0, 0.0), (1e-8, 1e-6), (0.45, 0.55), (0.6, 3.1)])
def test_rotate_points_jacobian_matches_autograd(lo: float, hi: float) -> None:
    B, N = 3, 5
    aa = random_axis_angle(B, lo, hi, seed=26)
    X = 80.0 * torch.randn(B, N, 3, dtype=F64, generator=torch.Generator().manual_seed(27))
    J = rotate_points_jacobian(aa, X)
    assert J.shape == (B, N, 3, 3) and torch.isfinite(J).all()
    full = jacobian(lambda w: X @ axis_angle_to_matrix(w).transpose(-1, -2), aa)  # (B, N, 3, B, 3)
    expected = torch.stack([full[b, :, :, b, :] for b in range(B)])
    torch.testing.assert_close(J, expected, atol=1e-10, rtol=1e-10)
    # A shared (N, 3) point set broadcasts over the batch.
    torch.testing.assert_close(rotate_points_jacobian(aa, X[0]), rotate_points_jacobian(aa, X[:1].expand(B, N, 3)))


def test_left_jacobian_maps_perturbations_to_left_increments() -> None:
    aa = random_axis_angle(4, 0.3, 2.8, seed=28)
    d = 1e-7 * torch.randn(4, 3, dtype=F64, generator=torch.Generator().manual_seed(29))
    lhs = axis_angle_to_matrix(aa + d)
    inc = (left_jacobian(aa) @ d[..., None]).squeeze(-1)
    rhs = axis_angle_to_matrix(inc) @ axis_angle_to_matrix(aa)
    torch.testing.assert_close(lhs, rhs, atol=1e-13, rtol=0)
    torch.testing.assert_close(left_jacobian(torch.zeros(2, 3)), torch.eye(3).expand(2, 3, 3))


def test_batched_calls_equal_per_sample_calls() -> None:
    aa = random_axis_angle(4, 0.0, 3.0, seed=30)
    X = torch.randn(4, 6, 3, dtype=F64, generator=torch.Generator().manual_seed(31))
    R = axis_angle_to_matrix(aa)
    J = rotate_points_jacobian(aa, X)
    for b in range(4):
        torch.testing.assert_close(R[b : b + 1], axis_angle_to_matrix(aa[b : b + 1]), atol=0, rtol=0)
        torch.testing.assert_close(J[b : b + 1], rotate_points_jacobian(aa[b : b + 1], X[b : b + 1]))
        torch.testing.assert_close(matrix_to_axis_angle(R)[b], matrix_to_axis_angle(R[b]))
        torch.testing.assert_close(matrix_to_euler(R)[b], matrix_to_euler(R[b]))


def test_geodesic_angle_and_relative_rotation_promote_mixed_dtypes() -> None:
    """float32 against float64 rotations give a float64 answer, as transform_points does (a matmul dtype error
    before)."""
    from torchface.geometry.transforms import relative_rotation

    R64 = euler_to_matrix(torch.tensor([[10.0, 0.0, 0.0]], dtype=torch.float64))
    R32 = torch.eye(3)[None]
    angle = geodesic_angle_deg(R64, R32)
    assert angle.dtype == torch.float64 and abs(float(angle[0]) - 10.0) < 1e-9
    assert relative_rotation(R32, R64).dtype == torch.float64


def test_euler_yaw_and_roll_are_never_minus_180() -> None:
    """``atan2`` of a -0.0 or rounding-level negative sine gives -180: reported as +180, as documented
    ((-180, 180]); the rotation is the same."""
    for dtype in (torch.float32, F64):
        for ypr in ([180.0, 0.0, 0.0], [0.0, 89.0, 180.0], [-180.0, 10.0, -180.0], [0.0, 90.0, 180.0]):
            R = euler_to_matrix(torch.tensor(ypr, dtype=dtype))
            out = matrix_to_euler(R)
            assert bool((out[[0, 2]] > -180.0).all()) and bool((out[[0, 2]] <= 180.0).all()), (ypr, out)
            tol = 1e-5 if dtype == torch.float32 else 1e-12
            torch.testing.assert_close(euler_to_matrix(out), R, atol=tol, rtol=0)
    R = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=F64))  # yaw 180 with signed zeros
    R[0, 2], R[2, 0] = -0.0, -0.0
    assert float(matrix_to_euler(R)[0]) == 180.0


def test_euler_round_trip_near_the_lock_keeps_the_rotation() -> None:
    """Near +-90 pitch the free formulas divide the matrix's rounding error by cos(pitch): with the lock narrowed to
    cos(pitch) < eps, a float32 rotation built by axis_angle_to_matrix at 89.99999 degrees came back 6 degrees off.
    The lock at sqrt(eps) keeps every round trip within about sqrt(eps) of rotation."""
    gen = torch.Generator().manual_seed(0)
    for dtype, tol in ((torch.float32, 0.1), (F64, 1e-5)):
        n = 2000
        ypr = torch.empty(n, 3, dtype=F64)
        ypr[:, 0] = torch.rand(n, generator=gen, dtype=F64) * 360 - 180
        ypr[:, 2] = torch.rand(n, generator=gen, dtype=F64) * 360 - 180
        side = torch.where(torch.rand(n, generator=gen) < 0.5, 1.0, -1.0).to(F64)
        ypr[:, 1] = side * (90.0 - 10.0 ** (-6 * torch.rand(n, generator=gen, dtype=F64) - 1))  # 0.1 to 1e-7 deg off
        # A matrix with ordinary rounding error: through the axis-angle map in the working dtype.
        R = axis_angle_to_matrix(matrix_to_axis_angle(euler_to_matrix(ypr)).to(dtype))
        err = geodesic_angle_deg(euler_to_matrix(matrix_to_euler(R)).double(), R.double())
        assert float(err.max()) < tol, (dtype, float(err.max()))


def _reference_log(R: torch.Tensor) -> torch.Tensor:
    """matrix_to_axis_angle as first written (element by element; session 59's code): the oracle of the fast one."""
    finfo = torch.finfo(R.dtype)
    w = 0.5 * torch.stack((R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]), -1)
    cos = (0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0)).clamp(-1.0, 1.0)
    s2 = (w * w).sum(-1)
    sin = s2.clamp(min=finfo.tiny).sqrt()
    theta = torch.atan2(sin, cos)
    series = torch.full_like(s2, 5.0 / 112.0)
    for c in (3.0 / 40.0, 1.0 / 6.0, 1.0):  # asin(s) / s in s^2
        series = series * s2 + c
    ratio = torch.where((s2 < finfo.eps ** (1.0 / 3.0)) & (cos > 0), series, theta / sin)
    sym = 0.5 * (R + R.transpose(-1, -2)) - cos[..., None, None] * torch.eye(3, dtype=R.dtype)
    col = sym.diagonal(dim1=-2, dim2=-1).argmax(-1)
    axis = torch.gather(sym, -1, col[..., None, None].expand(*col.shape, 3, 1)).squeeze(-1)
    axis = axis / (axis * axis).sum(-1, keepdim=True).clamp(min=finfo.tiny).sqrt()
    sign = torch.where((axis * w).sum(-1, keepdim=True) < 0, -torch.ones_like(cos)[..., None], 1.0)
    return torch.where((cos < -0.5)[..., None], axis * (sign * theta[..., None]), w * ratio[..., None])


def _reference_euler(R: torch.Tensor) -> torch.Tensor:
    """matrix_to_euler as first written (both branches' atan2 evaluated, then chosen): the oracle of the fast one."""
    finfo = torch.finfo(R.dtype)
    r00, r01, r02, r10, r11, r12, r22 = (
        R[..., i, j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2), (2, 2))
    )
    cos_p2 = r10 * r10 + r11 * r11
    pitch = torch.atan2(-r12, cos_p2.clamp(min=finfo.tiny).sqrt())
    locked = cos_p2 < finfo.eps
    one = torch.ones_like(r00)
    yaw_free = torch.atan2(torch.where(locked, 0.0 * one, r02), torch.where(locked, one, r22))
    roll_free = torch.atan2(torch.where(locked, 0.0 * one, r10), torch.where(locked, one, r11))
    sign_p = torch.where(-r12 < 0, -one, one)
    yaw_locked = torch.atan2(torch.where(locked, sign_p * r01, 0.0 * one), torch.where(locked, r00, one))
    yaw = torch.where(locked, yaw_locked, yaw_free)
    roll = torch.where(locked, 0.0 * one, roll_free)
    ypr = torch.rad2deg(torch.stack((yaw, pitch, roll), dim=-1))
    return torch.where(ypr <= -180.0, ypr + 360.0, ypr)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_log_and_euler_equal_their_element_by_element_reference_bit_for_bit(dtype: torch.dtype) -> None:
    """The logarithm map, Euler angles and vee are written with few operations (one stream's tracking step takes a
    logarithm and Euler angles per frame, and its time there is the operations' dispatch): they must give the values
    and gradients of the formulas written element by element, bit for bit, in every regime (near zero, general,
    near pi, exactly pi, gimbal lock and near it, yaw and roll at 180), at batch sizes below and above the
    vectorised kernels' block (16 float32 values: atan2's SIMD and scalar code round differently), for
    non-contiguous and unbatched matrices, with and without a matrix near pi in the batch."""
    g = torch.Generator().manual_seed(3)
    B = 20
    ax = torch.nn.functional.normalize(torch.randn(B, 3, generator=g, dtype=dtype), dim=-1)
    Rs = [axis_angle_to_matrix(torch.randn(B, 3, generator=g, dtype=dtype) * 1.2)]
    Rs += [axis_angle_to_matrix(ax * a) for a in (0.0, 1e-7, 1e-2, 2.0, 2.1, math.pi - 1e-4, math.pi)]
    ypr = (torch.rand(B, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor([360.0, 180.0, 360.0], dtype=dtype)
    for pitch in (None, 90.0, -90.0, 89.99999, -89.999):
        y = ypr.clone()
        if pitch is not None:
            y[:, 1] = pitch
        Rs.append(euler_to_matrix(y))
    Rs.append(euler_to_matrix(torch.tensor([180.0, 0.0, -180.0], dtype=dtype).expand(B, 3)))
    Rs.append(torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=dtype)).expand(B, 3, 3))
    R = torch.cat(Rs)
    for inference in (False, True):
        with torch.inference_mode(inference):
            # (R[B : 5 B]: no angle near pi, where the logarithm leaves that branch out; R: both)
            for M in (R[:1], R[:3], R[B : 5 * B], R, R.transpose(-1, -2), R.reshape(-1, 4, 3, 3), R[5]):
                assert torch.equal(matrix_to_axis_angle(M), _reference_log(M))
                assert torch.equal(matrix_to_euler(M), _reference_euler(M))
                assert torch.equal(vee(M), 0.5 * torch.stack((M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0],
                                                              M[..., 1, 0] - M[..., 0, 1]), -1))  # fmt: skip
    if dtype == torch.float64:  # gradients: the same where each formula's branch is chosen
        for fn, ref in ((matrix_to_axis_angle, _reference_log), (matrix_to_euler, _reference_euler)):
            for M in (R[::B], R[B + 3 :: B]):
                assert torch.equal(jacobian(fn, M), jacobian(ref, M))
