"""Geometry: camera intrinsics, SO(3) maps, rigid transforms and perspective projection.

Conventions (frames, units, Euler order, pixel centres) are in :mod:`torchface.conventions`.
"""

from __future__ import annotations

from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import (
    in_front,
    pose_projection_jacobian,
    project_points,
    project_points_jacobian,
    twist_projection_jacobian,
    unproject,
)
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
from torchface.geometry.transforms import compose, invert, relative_rotation, transform_points

__all__ = [
    "Intrinsics",
    "axis_angle_to_matrix",
    "compose",
    "euler_to_matrix",
    "geodesic_angle_deg",
    "hat",
    "in_front",
    "invert",
    "left_jacobian",
    "matrix_to_axis_angle",
    "matrix_to_euler",
    "pose_projection_jacobian",
    "project_points",
    "project_points_jacobian",
    "relative_rotation",
    "rotate_points_jacobian",
    "transform_points",
    "twist_projection_jacobian",
    "unproject",
    "vee",
]
