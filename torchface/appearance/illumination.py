"""Illumination basis for a Lambertian face under distant lights (paper Eq. 10-11 and 19).

A Lambertian point with albedo rho and unit normal n under an ambient term a and distant lights has intensity
``I = rho (a + sum_k s_k max(0, n . l_k))``. Away from shadow boundaries this is linear in the normal,
``I ~ rho (c0 + c . n)``: first-order spherical harmonics, which contain the paper's basis built from three
fixed light directions (any three independent directions span the same space). The template intensity
``T`` stands in for the albedo, so the appearance of a template point under new light is

    ``T(x) + sum_i lambda_i B_i(x)`` with ``B = [T, 1, T n_x, T n_y, T n_z]``

(gain, bias, three directional terms; normals in the camera frame). ``lambda = 0`` reproduces the template.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchface.geometry._checks import check_number, promoted

#: Names of the illumination parameters, in basis order.
ILLUMINATION_TERM_NAMES: tuple[str, ...] = ("gain", "bias", "light_x", "light_y", "light_z")
#: L, the number of illumination terms.
NUM_ILLUMINATION_TERMS: int = len(ILLUMINATION_TERM_NAMES)


def _check_tensors(*named: tuple[str, object]) -> None:
    """A ``TypeError`` naming the first of ``named`` that is not a floating-point tensor (a numpy array was "'numpy.
    ndarray' object has no attribute 'dim'")."""
    for name, x in named:
        if not isinstance(x, Tensor) or not x.is_floating_point():
            got = f"dtype {x.dtype}" if isinstance(x, Tensor) else type(x).__name__
            raise TypeError(f"{name} must be a floating-point torch.Tensor, got {got}")


def illumination_basis(template: Tensor, normals_cam: Tensor, *, out: Tensor | None = None) -> Tensor:
    """The illumination basis images ``B_i(x)`` of Eq. 11 at template points.

    Args:
        template: ``(B, N)`` template intensities ``T``.
        normals_cam: ``(B, N, 3)`` unit surface normals in the camera frame.
        out: a ``(B, N, L)`` tensor of their dtype (any strides: the transpose of a point-last ``(B, L, N)`` buffer,
            a large batch's step) that the same values are written into and returned as (without autograd:
            ``out=`` arguments do not support it); None: a new tensor.

    Returns:
        ``(B, N, L)`` with ``L = 5``: ``[T, 1, T n_x, T n_y, T n_z]``.
    """
    _check_tensors(("template", template), ("normals_cam", normals_cam))
    if template.dim() != 2 or normals_cam.shape != template.shape + (3,):
        raise ValueError(
            f"template must be (B, N) and normals_cam (B, N, 3), got {tuple(template.shape)} and "
            f"{tuple(normals_cam.shape)}"
        )
    t = template.unsqueeze(-1)
    if out is None:
        return torch.cat([t, torch.ones_like(t), t * normals_cam], dim=-1)
    dtype = torch.promote_types(template.dtype, normals_cam.dtype)
    if (tuple(out.shape) != (*template.shape, NUM_ILLUMINATION_TERMS) or out.dtype != dtype
            or out.device != template.device):  # (another dtype was written into, rounded, as to_gray's refuses)
        raise ValueError(f"out must be (B, N, {NUM_ILLUMINATION_TERMS}) = {(*template.shape, NUM_ILLUMINATION_TERMS)} "
                         f"{dtype} on {template.device}, got {tuple(out.shape)} {out.dtype} on {out.device}")
    out[..., 0] = template
    out[..., 1] = 1.0
    torch.mul(t, normals_cam, out=out[..., 2:])
    return out


def apply_illumination(template: Tensor, basis: Tensor, params: Tensor) -> Tensor:
    """Template under new light, ``T + sum_i lambda_i B_i`` (Eq. 19).

    Args:
        template: ``(B, N)``; basis: ``(B, N, L)``; params: ``(B, L)`` (mixed float dtypes are promoted, float32
            against float64: float64, as :func:`~torchface.geometry.transform_points` does).

    Returns:
        ``(B, N)``.
    """
    if not all(isinstance(x, Tensor) for x in (template, basis, params)):
        got = ", ".join(type(x).__name__ for x in (template, basis, params))
        raise TypeError(f"template, basis and params must be tensors, got {got}")
    if not template.dtype == basis.dtype == params.dtype:  # (einsum's "expected scalar type Double but found Float")
        template, basis, params = promoted(template, basis, params)
    if template.dim() != 2 or basis.shape[:2] != template.shape or basis.dim() != 3 or params.shape != (
        template.shape[0], basis.shape[2]
    ):  # (einsum's "subscript l has size 4 for operand 1 which does not broadcast ...")
        raise ValueError(f"template must be (B, N), basis (B, N, L) and params (B, L), got {tuple(template.shape)}, "
                         f"{tuple(basis.shape)} and {tuple(params.shape)}")  # fmt: skip
    return template + torch.einsum("bnl,bl->bn", basis, params)


def remove_illumination(observed: Tensor, normals_cam: Tensor, params: Tensor, min_gain: float = 0.05) -> Tensor:
    """Invert the illumination model: the intensity the point would have under the reference light.

    From ``I = T (1 + g + lambda_d . n) + b`` it returns ``T = (I - b) / (1 + g + lambda_d . n)``, with the
    denominator clamped to at least ``min_gain`` so the result is always finite.

    Args:
        observed: ``(B, N)`` or ``(B, C, N)`` observed intensities.
        normals_cam: ``(B, N, 3)`` unit normals in the camera frame.
        params: ``(B, L)`` illumination parameters ``[gain, bias, lx, ly, lz]``.
        min_gain: the denominator's floor, positive and finite.

    Returns:
        Same shape as ``observed``.

    Mixed float dtypes are promoted (float32 against float64: float64), as :func:`apply_illumination` and
    :func:`~torchface.geometry.transform_points` do.

    Raises:
        TypeError: a non-tensor argument, or ``min_gain`` not a real number.
        ValueError: ``min_gain`` not positive and finite (0 divided by zero: inf and NaN), or a shape mismatch.
    """
    if type(min_gain) is not float or not 0 < min_gain < math.inf:  # (the default's: no parse of the interval)
        # (a string or None was float()'s or clamp_min's own TypeError, "0.5" taken)
        min_gain = check_number(min_gain, "min_gain", "(0, inf)")
    if not all(isinstance(x, Tensor) for x in (observed, normals_cam, params)):
        got = ", ".join(type(x).__name__ for x in (observed, normals_cam, params))
        raise TypeError(f"observed, normals_cam and params must be tensors, got {got}")
    B, N = normals_cam.shape[:2] if normals_cam.dim() == 3 else (-1, -1)
    if (
        normals_cam.dim() != 3 or normals_cam.shape[2] != 3 or observed.dim() not in (2, 3)
        or observed.shape[0] != B or observed.shape[-1] != N or tuple(params.shape) != (B, NUM_ILLUMINATION_TERMS)
    ):  # (einsum's "subscript b has size 3 for operand 1 which does not broadcast ...", or a 6th term ignored)
        raise ValueError(
            f"observed must be (B, N) or (B, C, N), normals_cam (B, N, 3) and params (B, {NUM_ILLUMINATION_TERMS}), "
            f"got {tuple(observed.shape)}, {tuple(normals_cam.shape)} and {tuple(params.shape)}"
        )
    if not observed.dtype == normals_cam.dtype == params.dtype:  # (einsum's "expected scalar type Double ...")
        observed, normals_cam, params = promoted(observed, normals_cam, params)
    gain = 1.0 + params[:, 0:1] + torch.einsum("bnk,bk->bn", normals_cam, params[:, 2:5])  # (B, N)
    gain = gain.clamp_min(min_gain)
    bias = params[:, 1:2]
    if observed.dim() == 3:
        return (observed - bias.unsqueeze(1)) / gain.unsqueeze(1)
    return (observed - bias) / gain
