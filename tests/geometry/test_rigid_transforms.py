"""Tests for torchface.geometry.transforms: rigid maps, composition, inversion, relative rotation."""

from __future__ import annotations

import pytest
import torch

from torchface.geometry.so3 import axis_angle_to_matrix, geodesic_angle_deg
from torchface.geometry.transforms import compose, invert, relative_rotation, transform_points

F64 = torch.float64


def random_pose(B: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    R = axis_angle_to_matrix(torch.randn(B, 3, generator=g, dtype=F64))
    t = 100.0 * torch.randn(B, 3, generator=g, dtype=F64)
    return R, t


def test_transform_points_known_answer_and_broadcast() -> None:
    R = torch.tensor([[[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]], dtype=F64)  # 90 deg about z
    t = torch.tensor([[1.0, 2.0, 500.0]], dtype=F64)
    X = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 3.0]], dtype=F64)
    expected = torch.tensor([[[1.0, 3.0, 500.0], [0.0, 2.0, 503.0]]], dtype=F64)
    torch.testing.assert_close(transform_points(R, t, X), expected)
    torch.testing.assert_close(transform_points(R, t, X[None]), expected)
    R2, t2 = random_pose(4, seed=1)
    shared = transform_points(R2, t2, X)
    assert shared.shape == (4, 2, 3)
    torch.testing.assert_close(shared, transform_points(R2, t2, X[None].expand(4, 2, 3)))
    for b in range(4):
        torch.testing.assert_close(shared[b], X @ R2[b].T + t2[b])


def test_compose_matches_sequential_application() -> None:
    R1, t1 = random_pose(3, seed=2)
    R2, t2 = random_pose(3, seed=3)
    X = torch.randn(3, 7, 3, dtype=F64, generator=torch.Generator().manual_seed(4))
    R, t = compose(R1, t1, R2, t2)
    torch.testing.assert_close(transform_points(R, t, X), transform_points(R1, t1, transform_points(R2, t2, X)))


def test_invert_gives_identity_both_ways() -> None:
    R, t = random_pose(5, seed=5)
    Ri, ti = invert(R, t)
    eye = torch.eye(3, dtype=F64).expand(5, 3, 3)
    for Ra, ta, Rb, tb in ((R, t, Ri, ti), (Ri, ti, R, t)):
        Rc, tc = compose(Ra, ta, Rb, tb)
        torch.testing.assert_close(Rc, eye)
        torch.testing.assert_close(tc, torch.zeros(5, 3, dtype=F64), atol=1e-12, rtol=0)


def test_relative_rotation() -> None:
    R0, _ = random_pose(4, seed=6)
    Rt, _ = random_pose(4, seed=7)
    rel = relative_rotation(Rt, R0)
    torch.testing.assert_close(rel @ R0, Rt)
    torch.testing.assert_close(geodesic_angle_deg(rel, torch.eye(3, dtype=F64)), geodesic_angle_deg(Rt, R0))


def test_transforms_are_differentiable() -> None:
    R, t = random_pose(2, seed=8)
    X = torch.randn(2, 3, 3, dtype=F64, generator=torch.Generator().manual_seed(9))
    args = (R.requires_grad_(True), t.requires_grad_(True), X.requires_grad_(True))
    assert torch.autograd.gradcheck(transform_points, args)


def test_bad_inputs_raise() -> None:
    R, t = random_pose(2, seed=10)
    with pytest.raises(ValueError, match=r"\(B, 3, 3\)"):
        transform_points(R[0], t, torch.zeros(4, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"\(B, 3\)"):
        transform_points(R, t[0], torch.zeros(4, 3, dtype=F64))
    with pytest.raises(ValueError, match="batch sizes"):
        transform_points(R, t, torch.zeros(3, 4, 3, dtype=F64))
    with pytest.raises(ValueError, match="must have shape"):
        transform_points(R, t, torch.zeros(4, 2, dtype=F64))
    with pytest.raises(ValueError, match="batch sizes"):
        compose(R, t, R[:1].expand(3, 3, 3), t[:1].expand(3, 3))
    with pytest.raises(TypeError, match="floating-point"):
        invert(R, t.long())


def test_mixed_float_dtypes_are_promoted_and_batch_mismatches_named() -> None:
    """transform_points, compose, invert, rotate_points_jacobian and pose_projection_jacobian raised torch's
    RuntimeError "expected scalar type Float but found Double" on float32 against float64, where
    geodesic_angle_deg, relative_rotation and unproject promote (commit 45db6bb said "as transform_points does");
    relative_rotation and geodesic_angle_deg raised torch's RuntimeError "The size of tensor a (2) must match ..." on
    batches that do not broadcast, where compose says "batch sizes ... must match" (ValueError);
    pose_projection_jacobian's message for points of another batch named transform_points' R."""
    from torchface.geometry import Intrinsics, pose_projection_jacobian, rotate_points_jacobian

    R, t = random_pose(2, seed=11)
    X = torch.randn(2, 5, 3, dtype=F64, generator=torch.Generator().manual_seed(12))
    want = transform_points(R, t, X.float().double())
    for args in ((R.float(), t, X.float()), (R, t.float(), X.float()), (R.float(), t.float(), X)):
        got = transform_points(*args)
        assert got.dtype == F64
        torch.testing.assert_close(got, transform_points(*(a.double() for a in args)), rtol=0, atol=0)
    assert torch.allclose(transform_points(R.float(), t.float(), X), want, atol=1e-3)
    Rc, tc = compose(R.float(), t, R, t.float())
    assert Rc.dtype == tc.dtype == F64
    torch.testing.assert_close(Rc, compose(R.float().double(), t, R, t.float().double())[0], rtol=0, atol=0)
    Ri, ti = invert(R.float(), t)
    assert Ri.dtype == ti.dtype == F64
    aa = torch.tensor([[0.1, -0.2, 0.3], [0.0, 0.4, 0.0]], dtype=F64)
    assert rotate_points_jacobian(aa.float(), X).dtype == F64
    cam = Intrinsics.default(320, 240)
    d_aa, d_t = pose_projection_jacobian(aa, t.float(), X.float(), cam)
    assert d_aa.dtype == d_t.dtype == F64
    torch.testing.assert_close(d_aa, pose_projection_jacobian(aa, t.float().double(), X.float().double(), cam)[0])
    with pytest.raises(ValueError, match=r"batch sizes of aa \(2\) and points_model \(3\)"):
        pose_projection_jacobian(aa, t, torch.zeros(3, 5, 3, dtype=F64), cam)
    R3 = random_pose(3, seed=13)[0]
    with pytest.raises(ValueError, match=r"batch shapes of R_t \(2,\) and R_0 \(3,\) must broadcast"):
        relative_rotation(R, R3)
    with pytest.raises(ValueError, match=r"batch shapes of R1 \(2,\) and R2 \(3,\) must broadcast"):
        geodesic_angle_deg(R, R3)
    assert geodesic_angle_deg(R, R[:1]).shape == (2,)  # broadcasting stays


def test_batch_shape_check_imports_nothing_more() -> None:
    """The batch-shape check of geodesic_angle_deg and relative_rotation used torch.broadcast_shapes, whose first
    call imports sympy (0.4 s of CPU): a stall of a tracker's first recovery attempt (managed_step compares a
    candidate's rotation with the track's). It now compares the shapes itself, with the same answers."""
    import subprocess
    import sys

    code = (
        "import sys, torch\n"
        "from torchface.geometry.so3 import geodesic_angle_deg\n"
        "from torchface.geometry.transforms import relative_rotation\n"
        "before = 'sympy' in sys.modules\n"
        "R = torch.eye(3, dtype=torch.float64).expand(2, 4, 3, 3)\n"
        "assert geodesic_angle_deg(R, R[:1]).shape == (2, 4)\n"
        "assert relative_rotation(R[0], torch.eye(3, dtype=torch.float64)).shape == (4, 3, 3)\n"
        "print(before, 'sympy' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "False"], out.stdout
    R = random_pose(1, seed=3)[0].expand(2, 3, 3, 3)
    for good in ((3,), (1, 3), (2, 1), (2, 3), (), (5, 2, 3)):
        want = torch.broadcast_shapes((2, 3), good)
        assert geodesic_angle_deg(R, torch.eye(3, dtype=F64).expand(*good, 3, 3)).shape == want
    for bad in ((2,), (4, 3), (3, 3, 3)):
        with pytest.raises(ValueError, match="must broadcast"):
            geodesic_angle_deg(R, torch.eye(3, dtype=F64).expand(*bad, 3, 3))


def test_three_batched_arguments_are_checked_together() -> None:
    """transform_points checked R against t and R against points, compose R1 against t1, R2 against t2 and R1
    against R2: a size-1 argument let the other two disagree (R (1), t (2), points (3)), and torch's RuntimeError
    "The size of tensor a (3) must match the size of tensor b (2)" came from the arithmetic; pose_projection_jacobian
    likewise for t against points_model. Each is now the ValueError naming the pair."""
    from torchface.geometry import Intrinsics, pose_projection_jacobian

    eye = torch.eye(3, dtype=F64)
    with pytest.raises(ValueError, match=r"batch sizes of t \(2\) and points \(3\) must match or be 1"):
        transform_points(eye[None], torch.zeros(2, 3, dtype=F64), torch.zeros(3, 5, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"batch sizes of R1 \(2\) and t2 \(3\) must match or be 1"):
        compose(eye.expand(2, 3, 3), torch.zeros(1, 3, dtype=F64), eye[None], torch.zeros(3, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"batch sizes of t1 \(2\) and t2 \(3\) must match or be 1"):
        compose(eye[None], torch.zeros(2, 3, dtype=F64), eye[None], torch.zeros(3, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"batch sizes of t \(2\) and points_model \(3\) must match or be 1"):
        pose_projection_jacobian(torch.zeros(1, 3, dtype=F64), torch.zeros(2, 3, dtype=F64) + 500.0,
                                 torch.zeros(3, 5, 3, dtype=F64), Intrinsics.default(32, 24))  # fmt: skip
    # size 1 against any one size still broadcasts
    assert transform_points(eye[None], torch.zeros(3, 3, dtype=F64), torch.zeros(1, 5, 3, dtype=F64)).shape == (3, 5, 3)
    R, t = compose(eye[None], torch.zeros(1, 3, dtype=F64), eye[None], torch.zeros(4, 3, dtype=F64))
    assert R.shape == (1, 3, 3) and t.shape == (4, 3)
