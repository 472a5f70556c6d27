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
