"""Tests for torchface.geometry.projection: pinhole projection, unprojection and analytic Jacobians."""

from __future__ import annotations

import pytest
import torch
from torch.autograd.functional import jacobian

from torchface.geometry import Intrinsics
from torchface.geometry.projection import (
    in_front,
    pose_projection_jacobian,
    project_points,
    project_points_jacobian,
    twist_projection_jacobian,
    unproject,
)
from torchface.geometry.so3 import axis_angle_to_matrix
from torchface.geometry.transforms import transform_points

F64 = torch.float64
CAM = Intrinsics(width=640, height=480, fx=610.0, fy=590.0, cx=322.5, cy=236.0)


def face_points(B: int, N: int, seed: int, dtype: torch.dtype = F64) -> torch.Tensor:
    """``(B, N, 3)`` camera-frame points of a face-sized cloud 400-800 mm in front of the camera."""
    g = torch.Generator().manual_seed(seed)
    pts = 80.0 * torch.randn(B, N, 3, generator=g, dtype=F64)
    pts[..., 2] = 400.0 + 400.0 * torch.rand(B, N, generator=g, dtype=F64)
    return pts.to(dtype)


def block_diagonal(full: torch.Tensor, B: int) -> torch.Tensor:
    """Per-sample blocks ``full[b, ..., b, ...]`` of a batched autograd Jacobian ``(B, N, o, B, ...)``."""
    return torch.stack([full[b, :, :, b] for b in range(B)])


def test_project_points_known_answer() -> None:
    pts = torch.tensor([[[0.0, 0.0, 500.0], [100.0, -50.0, 1000.0]]], dtype=F64)
    uv = project_points(pts, CAM)
    expected = torch.tensor([[[322.5, 236.0], [322.5 + 61.0, 236.0 - 29.5]]], dtype=F64)
    torch.testing.assert_close(uv, expected)
    # Projection through the calibration matrix agrees: K X / Z.
    hom = pts @ CAM.matrix(dtype=F64).T
    torch.testing.assert_close(uv, hom[..., :2] / hom[..., 2:])


def test_project_points_follows_dtype_and_shape() -> None:
    pts = face_points(2, 7, seed=1, dtype=torch.float32)
    uv = project_points(pts, CAM)
    assert uv.shape == (2, 7, 2) and uv.dtype == torch.float32
    assert project_points_jacobian(pts, CAM).dtype == torch.float32


def test_project_unproject_round_trips() -> None:
    pts = face_points(3, 20, seed=2)
    uv = project_points(pts, CAM)
    torch.testing.assert_close(unproject(uv, pts[..., 2], CAM), pts, atol=1e-10, rtol=0)
    g = torch.Generator().manual_seed(3)
    uv2 = torch.rand(3, 20, 2, generator=g, dtype=F64) * torch.tensor([639.0, 479.0], dtype=F64)
    depth = 300.0 + 500.0 * torch.rand(3, 20, generator=g, dtype=F64)
    back = unproject(uv2, depth, CAM)
    torch.testing.assert_close(back[..., 2], depth)
    torch.testing.assert_close(project_points(back, CAM), uv2, atol=1e-10, rtol=0)


def test_depth_near_zero_and_behind_is_finite_and_masked() -> None:
    pts = torch.tensor(
        [[[10.0, -5.0, 0.0], [10.0, 5.0, -1e-30], [3.0, 4.0, -200.0], [1.0, 1.0, 1e-20], [0.0, 0.0, 500.0]]],
        dtype=F64,
    ).requires_grad_(True)
    for dtype in (torch.float32, F64):
        p = pts.detach().to(dtype).requires_grad_(True)
        uv = project_points(p, CAM)
        assert torch.isfinite(uv).all()
        (g,) = torch.autograd.grad(uv.sum(), p)
        assert torch.isfinite(g).all()
        assert torch.isfinite(project_points_jacobian(p.detach(), CAM)).all()
        assert torch.isfinite(twist_projection_jacobian(p.detach(), CAM)).all()
    assert in_front(pts).tolist() == [[False, False, False, False, True]]
    assert in_front(pts, near=600.0).tolist() == [[False] * 5]


def test_project_points_gradcheck() -> None:
    pts = face_points(2, 4, seed=4).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: project_points(x, CAM), (pts,))


def test_project_points_jacobian_matches_autograd() -> None:
    B, N = 2, 5
    pts = face_points(B, N, seed=5)
    pts[0, 0, 2] = -3.0  # clamped depth: the Z column vanishes in both
    J = project_points_jacobian(pts, CAM)
    assert J.shape == (B, N, 2, 3)
    full = jacobian(lambda x: project_points(x, CAM), pts)  # (B, N, 2, B, N, 3)
    expected = torch.stack([torch.stack([full[b, n, :, b, n] for n in range(N)]) for b in range(B)])
    torch.testing.assert_close(J, expected, atol=1e-12, rtol=1e-12)
    assert (J[0, 0, :, 2] == 0).all() and (J[0, 1, :, 2] != 0).all()


@pytest.mark.parametrize("points_batch", ["per_sample", "shared_1", "shared_2d"])
@pytest.mark.parametrize("angle", [0.0, 0.8])
def test_pose_projection_jacobian_matches_autograd(points_batch: str, angle: float) -> None:
    B, N = 3, 6
    g = torch.Generator().manual_seed(6)
    aa = angle * torch.nn.functional.normalize(torch.randn(B, 3, generator=g, dtype=F64), dim=-1)
    t = torch.tensor([[5.0, -10.0, 600.0], [-20.0, 15.0, 550.0], [0.0, 0.0, 700.0]], dtype=F64)
    X = 70.0 * torch.randn(B, N, 3, generator=g, dtype=F64)
    X_arg = {"per_sample": X, "shared_1": X[:1], "shared_2d": X[0]}[points_batch]
    X_full = X if points_batch == "per_sample" else X[:1].expand(B, N, 3)
    d_aa, d_t = pose_projection_jacobian(aa, t, X_arg, CAM)
    assert d_aa.shape == (B, N, 2, 3) and d_t.shape == (B, N, 2, 3)

    def uv_of(w: torch.Tensor, tr: torch.Tensor) -> torch.Tensor:
        return project_points(transform_points(axis_angle_to_matrix(w), tr, X_full), CAM)

    full_aa, full_t = jacobian(uv_of, (aa, t))
    torch.testing.assert_close(d_aa, block_diagonal(full_aa, B), atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(d_t, block_diagonal(full_t, B), atol=1e-12, rtol=1e-12)


def test_twist_projection_jacobian_matches_autograd() -> None:
    B, N = 2, 5
    pts = face_points(B, N, seed=7)
    J = twist_projection_jacobian(pts, CAM)
    assert J.shape == (B, N, 2, 6)

    def uv_of(xi: torch.Tensor) -> torch.Tensor:
        moved = transform_points(axis_angle_to_matrix(xi[:, :3]), xi[:, 3:], pts)
        return project_points(moved, CAM)

    expected = block_diagonal(jacobian(uv_of, torch.zeros(B, 6, dtype=F64)), B)
    torch.testing.assert_close(J, expected, atol=1e-12, rtol=1e-12)
    # It predicts the image motion of a small left twist to first order.
    xi = 1e-7 * torch.tensor([[1.0, -2.0, 0.5, 300.0, -100.0, 200.0]] * B, dtype=F64)
    moved = uv_of(xi) - project_points(pts, CAM)
    torch.testing.assert_close(moved, (J @ xi[:, None, :, None]).squeeze(-1), atol=1e-10, rtol=0)


def test_twist_jacobian_equals_pose_jacobian_at_the_identity_pose() -> None:
    # With R = I and t = 0 the model and camera frames coincide and a left twist is a pose increment.
    B, N = 2, 4
    X = face_points(B, N, seed=8)
    d_aa, d_t = pose_projection_jacobian(torch.zeros(B, 3, dtype=F64), torch.zeros(B, 3, dtype=F64), X, CAM)
    torch.testing.assert_close(twist_projection_jacobian(X, CAM), torch.cat((d_aa, d_t), dim=-1))


def test_batched_calls_equal_per_sample_calls() -> None:
    B, N = 3, 5
    pts = face_points(B, N, seed=9)
    aa = 0.4 * torch.randn(B, 3, dtype=F64, generator=torch.Generator().manual_seed(10))
    t = torch.tensor([[0.0, 0.0, 600.0]] * B, dtype=F64)
    uv, Jp, Jt = project_points(pts, CAM), project_points_jacobian(pts, CAM), twist_projection_jacobian(pts, CAM)
    d_aa, d_t = pose_projection_jacobian(aa, t, pts, CAM)
    for b in range(B):
        s = slice(b, b + 1)
        torch.testing.assert_close(uv[s], project_points(pts[s], CAM))
        torch.testing.assert_close(Jp[s], project_points_jacobian(pts[s], CAM))
        torch.testing.assert_close(Jt[s], twist_projection_jacobian(pts[s], CAM))
        one_aa, one_t = pose_projection_jacobian(aa[s], t[s], pts[s], CAM)
        torch.testing.assert_close(d_aa[s], one_aa)
        torch.testing.assert_close(d_t[s], one_t)
        torch.testing.assert_close(unproject(uv[s], pts[s, :, 2], CAM), unproject(uv, pts[..., 2], CAM)[s])


def test_bad_inputs_raise() -> None:
    pts = face_points(1, 3, seed=11)
    with pytest.raises(ValueError, match=r"\(B, N, 3\)"):
        project_points(pts[0], CAM)
    with pytest.raises(ValueError, match="must have shape"):
        project_points(pts[..., :2], CAM)
    with pytest.raises(TypeError, match="Intrinsics"):
        project_points(pts, CAM.matrix())
    with pytest.raises(TypeError, match="floating-point"):
        twist_projection_jacobian(pts.long(), CAM)
    with pytest.raises(ValueError, match="depth must be"):
        unproject(torch.zeros(1, 3, 2), torch.ones(1, 4), CAM)
    with pytest.raises(TypeError, match="depth"):
        unproject(torch.zeros(1, 3, 2), [1.0, 2.0, 3.0], CAM)
    with pytest.raises(ValueError, match="batch sizes"):
        pose_projection_jacobian(torch.zeros(2, 3), torch.zeros(3, 3), torch.zeros(4, 3), CAM)


def test_in_front_checks_near():
    """in_front's near was not looked at: a string was torch's "'>' not supported between instances of 'Tensor' and
    'str'", NaN made every point "behind" without a word; now check_number's errors, as the rasterizer's near."""
    points = torch.tensor([[[0.0, 0.0, 500.0], [0.0, 0.0, 0.5]]])
    with pytest.raises(TypeError, match=r"^near must be a real number, got str '1'"):
        in_front(points, near="1")  # type: ignore[arg-type]
    for near in (float("nan"), 0.0, -5.0, float("inf")):
        with pytest.raises(ValueError, match=r"^near must be a finite number > 0 \(millimetres\), got"):
            in_front(points, near=near)
    assert in_front(points, near=1).tolist() == [[True, False]]
    assert in_front(points, near=torch.tensor(0.25)).tolist() == [[True, True]]
