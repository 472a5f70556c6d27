"""Rotations: the SO(3) exponential and logarithm maps, Euler angles for reporting, and Jacobians.

Rotations are parameterised by axis-angle vectors (direction = axis, norm = angle in radians) and
mapped to matrices with the exponential map (Rodrigues' formula); Euler angles (yaw, pitch, roll) in
degrees are for reporting only, with ``R = R_y(yaw) @ R_x(pitch) @ R_z(roll)`` -- see
:mod:`torchface.conventions`. The rigid motion of the paper's Eq. 14-16 uses the exponential map of a
twist; :func:`rotate_points_jacobian` and :func:`left_jacobian` give its derivatives (Eq. 17).

Every function takes any number of leading dimensions ``...`` unless it says otherwise, and is
differentiable with finite values and gradients at the singular points (zero rotation, rotation by pi).

Numerics: the exponential map writes ``sin(t)/t`` and ``(1 - cos t)/t^2`` with ``torch.sinc`` (exact at zero;
the second as a squared half-angle sinc, free of cancellation). The left Jacobian's ``(1 - cos t)/t^2`` and
``(t - sin t)/t^3`` use a Taylor series for ``t < 0.5`` rad (eight terms; truncation error below 1e-19, smaller
than float64 resolution) and the closed form above it (where cancellation costs at most about 8 ulp). Values and
gradients are accurate in every dtype and finite at exactly zero.
"""

from __future__ import annotations

import functools
import math

import torch

from torchface._compiling import is_compiling, is_transformed
from torchface._scalar import scalar
from torchface.geometry._checks import check_batch, check_broadcast, check_exact_dim, check_tensor, promoted

__all__ = [
    "hat",
    "vee",
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "left_jacobian",
    "euler_to_matrix",
    "matrix_to_euler",
    "geodesic_angle_deg",
    "rotate_points_jacobian",
]

# Rotation angles below this (radians, squared) use the Taylor series of the coefficient functions.
_SERIES_THETA2 = 0.25
_SERIES_TERMS = 8
# Taylor coefficients (-1)^k / (2k + 1)!, (-1)^k / (2k + 2)!, (-1)^k / (2k + 3)!, k = 0 .. 7.
_SIN_OVER_T = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(_SERIES_TERMS))
_ONE_MINUS_COS_OVER_T2 = tuple((-1) ** k / math.factorial(2 * k + 2) for k in range(_SERIES_TERMS))
_T_MINUS_SIN_OVER_T3 = tuple((-1) ** k / math.factorial(2 * k + 3) for k in range(_SERIES_TERMS))
# Taylor coefficients of asin(s) / s in s^2: (2k)! / (4^k (k!)^2 (2k + 1)), k = 0 .. 3.
_ASIN_OVER_S = tuple(
    math.factorial(2 * k) / (4**k * math.factorial(k) ** 2 * (2 * k + 1)) for k in range(4)
)


def _horner(t: torch.Tensor, coeffs: tuple[float, ...]) -> torch.Tensor:
    """Evaluate ``sum_k coeffs[k] * t^k`` by Horner's rule (at least two coefficients). The first product is
    ``t * coeffs[-1]`` (the same value as a tensor full of ``coeffs[-1]`` times ``t``, one operation fewer) and the
    constants are :func:`~torchface._scalar.scalar`'s."""
    out = t * scalar(coeffs[-1], t) + scalar(coeffs[-2], t)
    for c in reversed(coeffs[:-2]):
        out = out * t + scalar(c, t)
    return out


def _rotation_coefficients(theta2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``sin t / t``, ``(1 - cos t) / t^2`` and ``(t - sin t) / t^3`` for ``t = sqrt(theta2)``.

    Args:
        theta2: ``(...)`` squared rotation angles.

    Returns:
        Three ``(...)`` tensors, finite with finite gradients everywhere including ``theta2 = 0``.
    """
    small = theta2 < _SERIES_THETA2
    # Clamp before torch.where: the closed-form branch never sees the angles it would divide by zero at.
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    sin, cos = torch.sin(theta), torch.cos(theta)
    a = torch.where(small, _horner(theta2, _SIN_OVER_T), sin / theta)
    b = torch.where(small, _horner(theta2, _ONE_MINUS_COS_OVER_T2), (1.0 - cos) / theta2_safe)
    c = torch.where(small, _horner(theta2, _T_MINUS_SIN_OVER_T3), (theta - sin) / (theta2_safe * theta))
    return a, b, c


def hat(v: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric cross-product matrix: ``hat(v) @ x == cross(v, x)``.

    Args:
        v: ``(..., 3)`` vectors.

    Returns:
        ``(..., 3, 3)`` skew-symmetric matrices.

    Example:
        >>> hat(torch.tensor([1.0, 2.0, 3.0]))
        tensor([[ 0., -3.,  2.],
                [ 3.,  0., -1.],
                [-2.,  1.,  0.]])
    """
    check_tensor(v, "v", (3,))
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    rows = (
        torch.stack((zero, -z, y), dim=-1),
        torch.stack((z, zero, -x), dim=-1),
        torch.stack((-y, x, zero), dim=-1),
    )
    return torch.stack(rows, dim=-2)


def vee(m: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat`: the vector of the skew-symmetric part of ``m``.

    Args:
        m: ``(..., 3, 3)`` matrices.

    Returns:
        ``(..., 3)``: ``vee(m) = ((m21 - m12), (m02 - m20), (m10 - m01)) / 2``.

    Example:
        >>> vee(hat(torch.tensor([1.0, 2.0, 3.0])))
        tensor([1., 2., 3.])
    """
    check_tensor(m, "m", (3, 3))
    return _vee_of_difference(m - m.transpose(-1, -2))


def _vee_of_difference(d: torch.Tensor) -> torch.Tensor:
    """:func:`vee` of ``m`` from ``d = m - m^T`` ``(..., 3, 3)``: its entries (2, 1), (0, 2) and (1, 0), halved.

    The same differences, in the same (contiguous ``(..., 3)``) layout as three differences stacked, in four
    operations instead of eleven (one stream's tracking step takes a logarithm map per frame)."""
    index = (_vee_index.__wrapped__ if is_compiling() else _vee_index)(d.device)
    return d.flatten(-2).index_select(-1, index) * scalar(0.5, d)


@functools.lru_cache(maxsize=16)
def _vee_index(device: torch.device) -> torch.Tensor:
    """The flat indices ``(3,)`` of entries (2, 1), (0, 2) and (1, 0) of a ``3 x 3`` matrix: a cached constant (never
    modify it), made outside inference mode."""
    with torch.inference_mode(False):
        return torch.tensor([7, 2, 3], device=device)


@functools.lru_cache(maxsize=16)
def _so3_generators(dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The SO(3) generators ``(3, 9)`` (row ``i`` is the flattened ``hat(e_i)``, so ``hat(w) = (w @ G)`` viewed as
    ``(..., 3, 3)``) and the identity ``(3, 3)``: cached constants (never modify them), built once per dtype and
    device. Made outside inference mode even when first asked for inside it, so that a later differentiable call
    may save them for backward."""
    with torch.inference_mode(False):
        g = torch.zeros(3, 3, 3, dtype=dtype, device=device)
        g[0, 2, 1], g[0, 1, 2] = 1.0, -1.0
        g[1, 0, 2], g[1, 2, 0] = 1.0, -1.0
        g[2, 1, 0], g[2, 0, 1] = 1.0, -1.0
        return g.reshape(3, 9), torch.eye(3, dtype=dtype, device=device)


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Exponential map of SO(3) (Rodrigues): ``R = I + A hat(w) + B hat(w)^2``.

    With ``t = |w|``, ``A = sin t / t = sinc(t / pi)`` and ``B = (1 - cos t) / t^2 = sinc(t / 2 pi)^2 / 2``:
    ``torch.sinc`` is exact at zero and the half-angle form has no cancellation, so values are accurate in every
    dtype; the angle is taken from ``t^2`` clamped to a tiny floor, so gradients are finite (and exact) at
    ``w = 0`` too. About a dozen tensor operations (the rotation part of the paper's twist motion, Eq. 14-16,
    evaluated several times per tracked frame).

    Args:
        aa: ``(..., 3)`` axis-angle vectors (radians).

    Returns:
        ``(..., 3, 3)`` rotation matrices.

    Example:
        >>> R = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, math.pi / 2]]))
        >>> R.round(decimals=4) + 0.0  # (+ 0.0 turns a -0. into 0.)
        tensor([[[ 0., -1.,  0.],
                 [ 1.,  0.,  0.],
                 [ 0.,  0.,  1.]]])
    """
    check_tensor(aa, "aa", (3,))
    half = scalar(0.5, aa)  # cached constants (torchface._scalar): the same values, cheaper operations
    x = (aa * aa).sum(-1, keepdim=True).clamp_min(torch.finfo(aa.dtype).tiny).sqrt().unsqueeze(-1) / scalar(math.pi, aa)
    a = torch.sinc(x)  # (..., 1, 1)
    b = torch.sinc(half * x).square() * half
    # (made in the graph while torch.compile traces: torchface._scalar)
    G, eye = (_so3_generators.__wrapped__ if is_compiling() else _so3_generators)(aa.dtype, aa.device)
    k = torch.matmul(aa, G).view(*aa.shape[:-1], 3, 3)
    return torch.addcmul(torch.addcmul(eye, a, k), b, torch.matmul(k, k))


def left_jacobian(aa: torch.Tensor) -> torch.Tensor:
    """Left Jacobian of SO(3): ``J_l(w) = I + B hat(w) + C hat(w)^2``.

    With ``t = |w|``, ``B = (1 - cos t) / t^2`` and ``C = (t - sin t) / t^3``. It maps a small
    perturbation ``d`` of the axis-angle vector to the equivalent left increment:
    ``exp(w + d) ~= exp(hat(J_l(w) d)) exp(w)``.

    Args:
        aa: ``(..., 3)`` axis-angle vectors (radians).

    Returns:
        ``(..., 3, 3)`` Jacobians (identity at ``w = 0``).

    Example:
        >>> left_jacobian(torch.zeros(3))
        tensor([[1., 0., 0.],
                [0., 1., 0.],
                [0., 0., 1.]])
    """
    check_tensor(aa, "aa", (3,))
    theta2 = (aa * aa).sum(-1)
    _, b, c = _rotation_coefficients(theta2)
    k = hat(aa)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(k)
    return eye + b[..., None, None] * k + c[..., None, None] * (k @ k)


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """Logarithm map of SO(3): the axis-angle vector ``w`` with ``exp(hat(w)) = R``, angle in ``[0, pi]``.

    ``cos t = (tr R - 1) / 2`` and ``sin t * axis = vee(R)``. Three regimes, each accurate and
    finite where it is used:

    * near zero (``sin^2 t < eps^(1/3)`` and ``cos t > 0``): ``w = vee(R) * asin(s)/s`` with the
      Taylor series of ``asin(s)/s`` in ``s^2``, so the gradient at ``R = I`` is finite;
    * general: ``w = vee(R) * atan2(s, cos t) / s``;
    * near pi (``cos t < -1/2``): the axis is read from the symmetric part
      ``(R + R^T)/2 - cos t I = (1 - cos t) axis axis^T`` (its largest column), with the sign of
      ``vee(R)``, since ``vee(R)`` vanishes at pi.

    At exactly pi both ``w`` and ``-w`` are valid; one of them is returned.

    Args:
        R: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 3)`` axis-angle vectors (radians).

    Example:
        >>> R = axis_angle_to_matrix(torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64))
        >>> matrix_to_axis_angle(R)
        tensor([ 0.1000, -0.2000,  0.3000], dtype=torch.float64)
    """
    check_tensor(R, "R", (3, 3))
    finfo = torch.finfo(R.dtype)
    half = scalar(0.5, R)
    Rt = R.transpose(-1, -2)
    w = _vee_of_difference(R - Rt)
    r00, _, _, _, r11, _, _, _, r22 = R.flatten(-2).unbind(-1)
    cos = (half * ((r00 + r11 + r22) - scalar(1.0, R))).clamp(-1.0, 1.0)
    s2 = (w * w).sum(-1)
    sin = s2.clamp(min=finfo.tiny).sqrt()
    theta = torch.atan2(sin, cos)

    small = (s2 < scalar(finfo.eps ** (1.0 / 3.0), R)) & (cos > scalar(0.0, R))
    near_pi = cos < scalar(-0.5, R)
    ratio_general = theta / sin
    ratio_small = _horner(s2, _ASIN_OVER_S)
    ratio = torch.where(small, ratio_small, ratio_general)
    aa_regular = w * ratio.unsqueeze(-1)
    if not (R.requires_grad or not R.is_cpu or is_compiling() or is_transformed(R)) and not bool(
        near_pi.any()
    ):  # no angle above 120 degrees (a tracked face's): the near-pi branch would be computed to be dropped
        return aa_regular  # (the values the torch.where below would copy; 25 operations, the host read is free here)

    # Near pi: axis from the symmetric part; its largest diagonal entry picks a well-scaled column.
    eye = (_so3_generators.__wrapped__ if is_compiling() else _so3_generators)(R.dtype, R.device)[1]
    sym = half * (R + Rt) - cos[..., None, None] * eye
    col = sym.diagonal(dim1=-2, dim2=-1).argmax(-1)
    index = col[..., None, None].expand(*col.shape, 3, 1)
    axis = torch.gather(sym, -1, index).squeeze(-1)
    axis = axis / (axis * axis).sum(-1, keepdim=True).clamp(min=finfo.tiny).sqrt()
    sign = torch.where((axis * w).sum(-1, keepdim=True) < scalar(0.0, R), scalar(-1.0, R), scalar(1.0, R))
    aa_pi = axis * (sign * theta.unsqueeze(-1))

    return torch.where(near_pi.unsqueeze(-1), aa_pi, aa_regular)


def _axis_rotation(angle: torch.Tensor, axis: int) -> torch.Tensor:
    """``(..., 3, 3)`` right-handed rotation by ``angle`` (radians, ``(...)``) about camera axis 0, 1 or 2."""
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(angle), torch.zeros_like(angle)
    if axis == 0:
        rows = ((one, zero, zero), (zero, c, -s), (zero, s, c))
    elif axis == 1:
        rows = ((c, zero, s), (zero, one, zero), (-s, zero, c))
    else:
        rows = ((c, -s, zero), (s, c, zero), (zero, zero, one))
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def euler_to_matrix(ypr_deg: torch.Tensor) -> torch.Tensor:
    """Rotation from yaw, pitch, roll in degrees: ``R = R_y(yaw) @ R_x(pitch) @ R_z(roll)``.

    See :mod:`torchface.conventions`: positive yaw turns the nose toward image left, positive pitch
    tips it down, positive roll turns the face clockwise in the image.

    Args:
        ypr_deg: ``(..., 3)`` yaw, pitch, roll in degrees.

    Returns:
        ``(..., 3, 3)`` rotation matrices.

    Example:
        >>> R = euler_to_matrix(torch.tensor([90.0, 0.0, 0.0]))
        >>> (R @ torch.tensor([0.0, 0.0, -1.0])).round(decimals=4) + 0.0  # nose turns to image left
        tensor([-1.,  0.,  0.])
    """
    check_tensor(ypr_deg, "ypr_deg", (3,))
    yaw, pitch, roll = torch.deg2rad(ypr_deg).unbind(-1)
    return _axis_rotation(yaw, 1) @ _axis_rotation(pitch, 0) @ _axis_rotation(roll, 2)


def matrix_to_euler(R: torch.Tensor) -> torch.Tensor:
    """Yaw, pitch, roll in degrees with ``R = R_y(yaw) @ R_x(pitch) @ R_z(roll)``, pitch in ``[-90, 90]``.

    From the product, ``R[1] = (cos p sin r, cos p cos r, -sin p)`` and
    ``R[:, 2] = (sin y cos p, -sin p, cos y cos p)``, so
    ``pitch = atan2(-R12, hypot(R10, R11))``, ``yaw = atan2(R02, R22)``, ``roll = atan2(R10, R11)``.
    At gimbal lock (``cos p`` below ``sqrt(eps)``) roll is set to 0 and yaw absorbs it:
    ``yaw = atan2(sign(sin p) R01, R00)``. Nearer the lock the free formulas would divide a matrix's rounding error
    by ``cos p`` (a float32 rotation from :func:`axis_angle_to_matrix` at 89.99999 degrees of pitch came back 6
    degrees off); the lock's roll of 0 costs at most about ``sqrt(eps)`` of rotation instead (0.06 degrees in
    float32). Yaw and roll of -180 degrees (``atan2`` of a -0.0 or a rounding-level negative sine) are reported as
    +180. See :mod:`torchface.conventions`.

    Args:
        R: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 3)`` yaw, pitch, roll in degrees; yaw and roll in ``(-180, 180]``.

    Example:
        >>> matrix_to_euler(euler_to_matrix(torch.tensor([30.0, -20.0, 10.0]))).round(decimals=3)
        tensor([ 30., -20.,  10.])
    """
    check_tensor(R, "R", (3, 3))
    finfo = torch.finfo(R.dtype)
    zero, one = scalar(0.0, R), scalar(1.0, R)
    r00, r01, r02, r10, r11, r12, _, _, r22 = R.flatten(-2).unbind(-1)
    cos_p2 = r10 * r10 + r11 * r11
    cos_p = cos_p2.clamp(min=finfo.tiny).sqrt()
    pitch = torch.atan2(-r12, cos_p)
    locked = cos_p2 < scalar(finfo.eps, R)
    # Each atan2 is given its own branch's arguments (the free or the locked one's), chosen before it: both are
    # away from (0, 0) where they are used, so values and gradients are finite. The locked roll is atan2(0, 1) = 0.
    yaw = torch.atan2(
        torch.where(locked, torch.where(r12 > zero, -r01, r01), r02), torch.where(locked, r00, r22)
    )  # locked: atan2(sign(sin p) R01, R00)
    roll = torch.atan2(torch.where(locked, zero, r10), torch.where(locked, one, r11))
    ypr = torch.rad2deg(torch.stack((yaw, pitch, roll), dim=-1))
    return torch.where(ypr <= scalar(-180.0, R), ypr + scalar(360.0, R), ypr)  # -180 -> +180 (pitch is in [-90, 90])


def geodesic_angle_deg(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Geodesic distance between rotations: the angle of ``R1 @ R2^T`` in degrees, in ``[0, 180]``.

    Computed as ``atan2(|vee(M)|, (tr M - 1) / 2)`` with ``M = R1 R2^T`` and the cosine clamped to
    ``[-1, 1]``, which is accurate at both ends (``acos`` is not) and has finite gradients
    (zero at ``R1 = R2``, where the distance is not differentiable).

    Args:
        R1: ``(..., 3, 3)`` rotation matrices.
        R2: ``(..., 3, 3)`` rotation matrices (broadcast against ``R1``).

    Returns:
        ``(...)`` angles in degrees.

    Example:
        >>> R = euler_to_matrix(torch.tensor([10.0, 0.0, 0.0]))
        >>> geodesic_angle_deg(R, torch.eye(3)).round(decimals=4)
        tensor(10.)
    """
    check_tensor(R1, "R1", (3, 3))
    check_tensor(R2, "R2", (3, 3))
    check_broadcast(R1, R2, "R1", "R2", 2)
    dtype = torch.promote_types(R1.dtype, R2.dtype)  # float32 against float64: in float64, as transform_points
    m = R1.to(dtype) @ R2.to(dtype).transpose(-1, -2)
    finfo = torch.finfo(m.dtype)
    cos = (0.5 * (m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2] - 1.0)).clamp(-1.0, 1.0)
    w = vee(m)
    sin = (w * w).sum(-1).clamp(min=finfo.tiny).sqrt()
    return torch.rad2deg(torch.atan2(sin, cos))


def rotate_points_jacobian(aa: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Jacobian of rotated points with respect to the axis-angle vector, at a general rotation.

    ``d(R(w) X) / dw = -hat(R(w) X) @ J_l(w)`` (:func:`left_jacobian`), finite and exact at ``w = 0``
    where it reduces to ``-hat(X)``. This is the rotational block of the paper's Eq. 17 away from
    the linearisation point.

    Args:
        aa: ``(B, 3)`` axis-angle vectors (radians).
        points: ``(B, N, 3)``, ``(1, N, 3)`` or ``(N, 3)`` points ``X`` (any unit).

    Returns:
        ``(B, N, 3, 3)``: entry ``[b, n, i, j] = d (R X)_i / d w_j``.

    Example:
        >>> J = rotate_points_jacobian(torch.zeros(1, 3), torch.tensor([[1.0, 0.0, 0.0]]))
        >>> J[0, 0] + 0.0  # -hat(X) at the identity
        tensor([[ 0.,  0.,  0.],
                [ 0.,  0.,  1.],
                [ 0., -1.,  0.]])
    """
    check_tensor(aa, "aa", (3,))
    check_exact_dim(aa, "aa", (2,), "(B, 3)")
    check_tensor(points, "points", (3,))
    check_exact_dim(points, "points", (2, 3), "(B, N, 3) or (N, 3)")
    pts = points if points.dim() == 3 else points.unsqueeze(0)
    check_batch(aa.shape[0], pts.shape[0], "aa", "points")
    aa, pts = promoted(aa, pts)
    R = axis_angle_to_matrix(aa)
    rotated = pts @ R.transpose(-1, -2)
    return -hat(rotated) @ left_jacobian(aa)[:, None]
