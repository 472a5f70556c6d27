"""Pinhole projection, its inverse, and the projection Jacobians of the paper's Eq. 15-17.

``u = fx X / Z + cx``, ``v = fy Y / Z + cy`` in the OpenCV camera frame with pixel centres at integer
coordinates (see :mod:`torchface.conventions` and :class:`torchface.geometry.camera.Intrinsics`).

Depth safety: :func:`project_points` and the Jacobians divide by ``max(Z, eps)`` with ``eps`` the
machine epsilon of the input dtype, so no input produces ``inf`` or ``NaN``. Points at or behind the
near plane (``Z <= NEAR_PLANE_MM``) have no meaningful projection; callers mask them with
:func:`in_front`.
"""

from __future__ import annotations

import math

import torch

from torchface.conventions import NEAR_PLANE_MM
from torchface.geometry._checks import (
    check_batch, check_batches, check_exact_dim, check_intrinsics, check_number, check_tensor, promoted,
)
from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import axis_angle_to_matrix, hat, rotate_points_jacobian
from torchface.geometry.transforms import transform_points

__all__ = [
    "in_front",
    "project_points",
    "project_points_jacobian",
    "pose_projection_jacobian",
    "twist_projection_jacobian",
    "unproject",
]


def _check_points_cam(points_cam: torch.Tensor, name: str = "points_cam") -> None:
    check_tensor(points_cam, name, (3,))
    check_exact_dim(points_cam, name, (3,), "(B, N, 3)")


def _safe_depth(z: torch.Tensor) -> torch.Tensor:
    """Depth clamped to the dtype's machine epsilon (millimetres) so that ``1 / Z`` stays finite."""
    return z.clamp(min=torch.finfo(z.dtype).eps)


def in_front(points_cam: torch.Tensor, near: float = NEAR_PLANE_MM) -> torch.Tensor:
    """Mask of points in front of the near plane, whose projection is meaningful.

    Args:
        points_cam: ``(B, N, 3)`` points in the camera frame (millimetres).
        near: near-plane depth in millimetres, a finite number > 0 (as the rasterizer's).

    Returns:
        ``(B, N)`` bool, ``Z > near``.

    Raises:
        TypeError: ``near`` is not a real number (a string was torch's "'>' not supported").
        ValueError: ``near`` is not finite and > 0 (NaN made every point "behind" without a word).

    Example:
        >>> in_front(torch.tensor([[[0.0, 0.0, 500.0], [0.0, 0.0, -5.0]]]))
        tensor([[ True, False]])
    """
    _check_points_cam(points_cam)
    if type(near) is not float or not 0 < near < math.inf:  # (the default's: no parse of the interval)
        near = check_number(near, "near", "(0, inf)", unit="millimetres")
    return points_cam[..., 2] > near


def project_points(points_cam: torch.Tensor, intrinsics: Intrinsics) -> torch.Tensor:
    """Perspective projection to pixel coordinates (the paper's Eq. 15).

    Depth is clamped to the dtype's machine epsilon, so the result is always finite in float32 and float64 (not
    in float16, whose range a focal length times millimetres exceeds); it is only meaningful where
    :func:`in_front` holds.

    Args:
        points_cam: ``(B, N, 3)`` points in the camera frame (millimetres).
        intrinsics: the camera.

    Returns:
        ``(B, N, 2)`` pixel coordinates ``(u, v)``.

    Example:
        >>> cam = Intrinsics.default(640, 480)
        >>> project_points(torch.tensor([[[0.0, 0.0, 500.0], [100.0, 50.0, 640.0]]]), cam)
        tensor([[[319.5000, 239.5000],
                 [419.5000, 289.5000]]])
    """
    _check_points_cam(points_cam)
    cam = check_intrinsics(intrinsics)
    z = _safe_depth(points_cam[..., 2])
    u = cam.fx * points_cam[..., 0] / z + cam.cx
    v = cam.fy * points_cam[..., 1] / z + cam.cy
    return torch.stack((u, v), dim=-1)


def project_points_jacobian(points_cam: torch.Tensor, intrinsics: Intrinsics) -> torch.Tensor:
    """Analytic Jacobian of :func:`project_points` with respect to the camera-frame point.

    ``d(u, v)/d(X, Y, Z) = [[fx/Z, 0, -fx X/Z^2], [0, fy/Z, -fy Y/Z^2]]`` (the projection factor of the
    paper's Eq. 17). Where the depth is clamped the ``Z`` column is zero, as for the clamped
    projection itself.

    Args:
        points_cam: ``(B, N, 3)`` points in the camera frame (millimetres).
        intrinsics: the camera.

    Returns:
        ``(B, N, 2, 3)`` Jacobians.

    Example:
        >>> J = project_points_jacobian(torch.tensor([[[0.0, 0.0, 100.0]]]), Intrinsics.default(4, 3, focal=100.0))
        >>> J[0, 0]
        tensor([[1., 0., -0.],
                [0., 1., -0.]])
    """
    _check_points_cam(points_cam)
    cam = check_intrinsics(intrinsics)
    x, y, z_raw = points_cam.unbind(-1)
    z = _safe_depth(z_raw)
    inv_z = 1.0 / z
    live = (z_raw >= torch.finfo(z_raw.dtype).eps).to(z.dtype)
    zero = torch.zeros_like(z)
    row_u = torch.stack((cam.fx * inv_z, zero, -cam.fx * x * inv_z * inv_z * live), dim=-1)
    row_v = torch.stack((zero, cam.fy * inv_z, -cam.fy * y * inv_z * inv_z * live), dim=-1)
    return torch.stack((row_u, row_v), dim=-2)


def pose_projection_jacobian(
    aa: torch.Tensor, t: torch.Tensor, points_model: torch.Tensor, intrinsics: Intrinsics
) -> tuple[torch.Tensor, torch.Tensor]:
    """Jacobians of ``project(R(aa) X + t)`` with respect to ``aa`` and ``t`` at a general pose.

    By the chain rule, ``d uv / d aa = J_proj(X_cam) @ (-hat(R X) J_l(aa))`` and
    ``d uv / d t = J_proj(X_cam)`` (see :func:`torchface.geometry.so3.rotate_points_jacobian`).

    Args:
        aa: ``(B, 3)`` axis-angle rotations (radians).
        t: ``(B, 3)`` translations (millimetres).
        points_model: ``(B, N, 3)``, ``(1, N, 3)`` or ``(N, 3)`` model-frame points (millimetres).
        intrinsics: the camera.

    Returns:
        ``(d_aa, d_t)``, each ``(B, N, 2, 3)``.

    Example:
        >>> cam = Intrinsics.default(640, 480)
        >>> d_aa, d_t = pose_projection_jacobian(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 500.0]]),
        ...                                      torch.zeros(5, 3), cam)
        >>> d_aa.shape, d_t.shape
        (torch.Size([1, 5, 2, 3]), torch.Size([1, 5, 2, 3]))
    """
    check_tensor(aa, "aa", (3,))
    check_exact_dim(aa, "aa", (2,), "(B, 3)")
    check_tensor(t, "t", (3,))
    check_exact_dim(t, "t", (2,), "(B, 3)")
    check_batch(aa.shape[0], t.shape[0], "aa", "t")
    check_tensor(points_model, "points_model", (3,))
    check_exact_dim(points_model, "points_model", (2, 3), "(B, N, 3) or (N, 3)")
    if points_model.dim() == 3:  # (named here: transform_points' message named its R)
        check_batches(("aa", aa.shape[0]), ("t", t.shape[0]), ("points_model", points_model.shape[0]))
    cam = check_intrinsics(intrinsics)
    aa, t, points_model = promoted(aa, t, points_model)
    R = axis_angle_to_matrix(aa)
    points_cam = transform_points(R, t, points_model)
    j_proj = project_points_jacobian(points_cam, cam)
    j_rot = rotate_points_jacobian(aa, points_model)
    return j_proj @ j_rot, j_proj


def twist_projection_jacobian(points_cam: torch.Tensor, intrinsics: Intrinsics) -> torch.Tensor:
    """Jacobian of the projection under a left twist perturbation, at zero (the paper's Eq. 17).

    The perturbed point is ``X' = exp(hat(dw)) X_cam + dt``; at ``dw = dt = 0``,
    ``dX'/d(dw) = -hat(X_cam)`` and ``dX'/d(dt) = I``, so the result is
    ``[J_proj @ -hat(X_cam), J_proj]``. A Lucas-Kanade tracker uses it once per iteration.

    Args:
        points_cam: ``(B, N, 3)`` points in the camera frame (millimetres).
        intrinsics: the camera.

    Returns:
        ``(B, N, 2, 6)``: columns ``(dw_x, dw_y, dw_z, dt_x, dt_y, dt_z)``.

    Example:
        >>> cam = Intrinsics.default(640, 480)
        >>> twist_projection_jacobian(torch.tensor([[[0.0, 0.0, 500.0]]]), cam).shape
        torch.Size([1, 1, 2, 6])
    """
    _check_points_cam(points_cam)
    cam = check_intrinsics(intrinsics)
    j_proj = project_points_jacobian(points_cam, cam)
    j_rot = j_proj @ (-hat(points_cam))
    return torch.cat((j_rot, j_proj), dim=-1)


def unproject(uv: torch.Tensor, depth: torch.Tensor, intrinsics: Intrinsics) -> torch.Tensor:
    """Back-project pixels with known depth: ``X = (u - cx) Z / fx``, ``Y = (v - cy) Z / fy``.

    Args:
        uv: ``(B, N, 2)`` pixel coordinates ``(u, v)``.
        depth: ``(B, N)`` depths ``Z`` (millimetres).
        intrinsics: the camera.

    Returns:
        ``(B, N, 3)`` camera-frame points; ``project_points(unproject(uv, Z)) == uv`` for ``Z > 0``.

    Example:
        >>> cam = Intrinsics.default(640, 480)
        >>> unproject(torch.tensor([[[419.5, 289.5]]]), torch.tensor([[640.0]]), cam)
        tensor([[[100.,  50., 640.]]])
    """
    check_tensor(uv, "uv", (2,))
    check_exact_dim(uv, "uv", (3,), "(B, N, 2)")
    if not isinstance(depth, torch.Tensor):
        raise TypeError(f"depth must be a torch.Tensor, got {type(depth).__name__}")
    if not depth.is_floating_point():
        raise TypeError(f"depth must be a floating-point tensor, got dtype {depth.dtype}")
    if tuple(depth.shape) != tuple(uv.shape[:-1]):
        raise ValueError(f"depth must be (B, N) = {tuple(uv.shape[:-1])} to match uv, got {tuple(depth.shape)}")
    cam = check_intrinsics(intrinsics)
    x = (uv[..., 0] - cam.cx) * depth / cam.fx
    y = (uv[..., 1] - cam.cy) * depth / cam.fy
    return torch.stack((x, y, depth), dim=-1)
