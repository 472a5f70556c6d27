"""Rigid transforms ``X' = R X + t`` on batches of point sets (see :mod:`torchface.conventions`).

A pose maps the head (model) frame to the camera frame, ``X_cam = R @ X_model + t`` with ``R`` in
SO(3) and ``t`` in millimetres; this is the rigid part ``M`` of the paper's Eq. 14.
"""

from __future__ import annotations

import torch

from torchface.geometry._checks import check_batches, check_broadcast, check_exact_dim, check_tensor, promoted

__all__ = ["transform_points", "compose", "invert", "relative_rotation"]


def _check_pose(R: torch.Tensor, t: torch.Tensor, r_name: str = "R", t_name: str = "t") -> None:
    check_tensor(R, r_name, (3, 3))
    check_exact_dim(R, r_name, (3,), "(B, 3, 3)")
    check_tensor(t, t_name, (3,))
    check_exact_dim(t, t_name, (2,), "(B, 3)")
    check_batches((r_name, R.shape[0]), (t_name, t.shape[0]))


def transform_points(R: torch.Tensor, t: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply ``X' = R X + t`` to every point.

    Args:
        R: ``(B, 3, 3)`` rotations.
        t: ``(B, 3)`` translations.
        points: ``(B, N, 3)``, ``(1, N, 3)`` or ``(N, 3)`` points (a shared point set broadcasts).

    Returns:
        ``(B, N, 3)`` transformed points.

    Example:
        >>> R = torch.eye(3)[None]
        >>> transform_points(R, torch.tensor([[0.0, 0.0, 500.0]]), torch.zeros(2, 3))
        tensor([[[  0.,   0., 500.],
                 [  0.,   0., 500.]]])
    """
    _check_pose(R, t)
    check_tensor(points, "points", (3,))
    check_exact_dim(points, "points", (2, 3), "(B, N, 3) or (N, 3)")
    pts = points if points.dim() == 3 else points.unsqueeze(0)
    check_batches(("R", R.shape[0]), ("t", t.shape[0]), ("points", pts.shape[0]))
    R, t, pts = promoted(R, t, pts)
    return pts @ R.transpose(-1, -2) + t[:, None, :]


def compose(
    R1: torch.Tensor, t1: torch.Tensor, R2: torch.Tensor, t2: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composition ``T1 o T2`` (apply ``T2`` first): ``(R1 R2, R1 t2 + t1)``.

    Args:
        R1: ``(B, 3, 3)`` rotation of the outer transform.
        t1: ``(B, 3)`` translation of the outer transform.
        R2: ``(B, 3, 3)`` rotation of the inner transform.
        t2: ``(B, 3)`` translation of the inner transform.

    Returns:
        ``(R, t)``: ``(B, 3, 3)`` and ``(B, 3)``, with
        ``transform_points(R, t, X) == transform_points(R1, t1, transform_points(R2, t2, X))``.

    Example:
        >>> R, t = compose(torch.eye(3)[None], torch.ones(1, 3), torch.eye(3)[None], torch.ones(1, 3))
        >>> t
        tensor([[2., 2., 2.]])
    """
    _check_pose(R1, t1, "R1", "t1")
    _check_pose(R2, t2, "R2", "t2")
    check_batches(("R1", R1.shape[0]), ("t1", t1.shape[0]), ("R2", R2.shape[0]), ("t2", t2.shape[0]))
    R1, t1, R2, t2 = promoted(R1, t1, R2, t2)
    R = R1 @ R2
    t = (R1 @ t2[..., None]).squeeze(-1) + t1
    return R, t


def invert(R: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse rigid transform: ``(R^T, -R^T t)``.

    Args:
        R: ``(B, 3, 3)`` rotations.
        t: ``(B, 3)`` translations.

    Returns:
        ``(R_inv, t_inv)``: ``(B, 3, 3)`` and ``(B, 3)``.

    Example:
        >>> invert(torch.eye(3)[None], torch.tensor([[1.0, 2.0, 3.0]]))[1]
        tensor([[-1., -2., -3.]])
    """
    _check_pose(R, t)
    R, t = promoted(R, t)
    R_inv = R.transpose(-1, -2)
    t_inv = -(R_inv @ t[..., None]).squeeze(-1)
    return R_inv, t_inv


def relative_rotation(R_t: torch.Tensor, R_0: torch.Tensor) -> torch.Tensor:
    """Rotation taking pose ``R_0`` to pose ``R_t``: ``R_t R_0^T`` (so ``R_t = rel @ R_0``).

    Args:
        R_t: ``(..., 3, 3)`` current rotations.
        R_0: ``(..., 3, 3)`` reference rotations (broadcast against ``R_t``).

    Returns:
        ``(..., 3, 3)`` relative rotations.

    Example:
        >>> relative_rotation(torch.eye(3)[None], torch.eye(3)[None]).shape
        torch.Size([1, 3, 3])
    """
    check_tensor(R_t, "R_t", (3, 3))
    check_tensor(R_0, "R_0", (3, 3))
    check_broadcast(R_t, R_0, "R_t", "R_0", 2)
    dtype = torch.promote_types(R_t.dtype, R_0.dtype)  # mixed float32 / float64: promoted, as transform_points
    return R_t.to(dtype) @ R_0.to(dtype).transpose(-1, -2)
