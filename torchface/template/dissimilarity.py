"""Dissimilarity between the normalised face and its reference (paper Section 4, "dissimilarity").

With the estimated pose, expression and light, the frame is resampled into the normalised view of the face
(frontal, neutral expression, neutral light; :mod:`torchface.normalise`). If the estimate is right this view
matches the reference view built from the first frame; if it is wrong, the face's features appear displaced.
The paper measures this by tracking a set of fiducial patches of the reference on the current normalised
view with a 2D inverse-compositional Lucas-Kanade, and reads a large displacement as low confidence.

Inverse-compositional Lucas-Kanade (Baker and Matthews, "Lucas-Kanade 20 years on", 2004)
-------------------------------------------------------------------------------------------
Each patch ``k`` is the square ``h x h`` grid of offsets ``x`` around its centre ``c_k`` in the reference
``T``; the warp is a translation, ``W(x; p) = c_k + x + p``. Each iteration solves

    ``min_dp sum_x w(x) [T(c_k + x + dp) - I(c_k + x + p)]^2``

by linearising ``T`` (whose gradient is fixed, so the steepest-descent images ``grad T(x)`` are computed once),

    ``dp = H^-1 sum_x w(x) grad T(x)^T [I(c_k + x + p) - T(c_k + x)]``,  ``H = sum_x w(x) grad T(x)^T grad T(x)``,

and composes the inverse increment, ``p <- p - dp``. The weights ``w`` are the reference patch's mask times
the current image's mask (and its inside-image indicator) at the warped grid, so ``H`` is re-summed each
iteration from the precomputed steepest-descent images (the robust/weighted variant of the same paper,
Part 2); it is a 2 x 2 sum per patch. A constant intensity offset between the patches (a bias left by the
illumination estimate) is projected out: the steepest-descent images and the error are taken relative to
their weighted patch means ("project out" of the bias basis image ``1``).

Dissimilarity and confidence
----------------------------
:func:`build_dissimilarity_reference` picks ``K`` fiducial patches on the reference normalised face: the
positions of highest texture (the smaller eigenvalue of the structure tensor summed over the patch, as in
Shi and Tomasi's "good features to track"), whose patch lies entirely inside the reference mask, kept apart
by non-maximum suppression. :func:`dissimilarity` tracks them on the current normalised face, and

    ``d = mean_k min(|p_k|, d_max)``   over the patches present,     ``confidence = exp(-(d / d0)^2)``,

the mean leaving out the largest ``trim_fraction`` (a quarter) of the present patches' displacements.

A patch is missing when less than ``min_support`` of its reference pixels are inside the current mask at its
final position (or when the reference had no patch in that slot); a patch whose solve fails (singular
Hessian, non-finite) or leaves the search range counts as displaced by ``d_max``. When fewer than
``min_patches`` patches, or fewer than ``min_present_fraction`` of the reference's patches, are present the
dissimilarity is ``d_max`` and the confidence 0: a face seen from a view the reference does not cover keeps
only a few of its patches, and a mean over one or two of them says nothing.

Pixel coordinates are ``(u, v)`` = (column, row) with pixel centres at integers; sampling uses ``grid_sample``
with ``align_corners=True`` (see :mod:`torchface.conventions`).

Shapes: ``B`` batch, ``C`` channels, ``K`` patches, ``h`` patch size, ``H x W`` images, ``G x G`` the normalised
face.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from torchface._autocast import full_precision
from torchface import _native
from torchface._scalar import isfinite, scalar
from torchface.backend import Backend, use_native
from torchface.geometry._checks import check_bool, check_int, check_number, check_optional_int

__all__ = [
    "LKResult",
    "LKTemplate",
    "lk_template",
    "DissimilarityConfig",
    "DissimilarityReference",
    "DissimilarityResult",
    "inverse_compositional_lk",
    "build_dissimilarity_reference",
    "trimmed_mean",
    "dissimilarity",
]


class LKResult(NamedTuple):
    """What :func:`inverse_compositional_lk` returns (per patch).

    Attributes:
        displacement: ``(B, K, 2)`` pixels ``(du, dv)``: the reference patch at ``c_k`` matches the image
            at ``c_k + displacement``.
        converged: ``(B, K)`` bool, the last update was below the tolerance.
        valid: ``(B, K)`` bool, the solve stayed well-posed (finite, non-singular Hessian) and within
            ``max_displacement``.
        support: ``(B, K)`` fraction of the reference patch's weight that is inside the image (and its mask)
            at the final position, in ``[0, 1]``.
        residual: ``(B, K)`` weighted RMS intensity error at the final position (bias projected out when
            requested); None when not asked for (``with_residual=False``).
    """

    displacement: Tensor
    converged: Tensor
    valid: Tensor
    support: Tensor
    residual: Tensor | None


class LKTemplate(NamedTuple):
    """The reference side of :func:`inverse_compositional_lk`, computed once per reference (:func:`lk_template`).

    Attributes:
        grid: ``(B, K, n, 2)`` the patches' pixel positions ``c_k + x`` (``n = h * h``).
        template: ``(B, K, n, C)`` ``T`` at those positions.
        sd: ``(B, K, n, C, 2)`` the steepest-descent images ``grad T`` (central differences).
        weight: ``(B, K, n)`` reference weights (inside the reference and its mask).
        total: ``(B, K)`` their sum per patch.
    """

    grid: Tensor
    template: Tensor
    sd: Tensor
    weight: Tensor
    total: Tensor

    def select(self, index: Tensor | tuple[Tensor, Tensor]) -> "LKTemplate":
        """The rows ``index`` (a ``(B',)`` int64 or bool tensor, or a pair of ``(B',)`` int64 tensors that index the
        first two dimensions) of every field."""
        return LKTemplate(*(x[index] for x in self))


def _check_image(x: object, name: str) -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape (B, C, H, W), got {type(x).__name__}")
    if x.dim() != 4 or not x.is_floating_point():
        raise ValueError(f"{name} must be (B, C, H, W) float, got {tuple(x.shape)} {x.dtype}")
    return x


def _check_mask(mask: object, name: str, image: Tensor) -> Tensor:
    if not isinstance(mask, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape (B, 1, H, W), got {type(mask).__name__}")
    want = (image.shape[0], 1, image.shape[2], image.shape[3])
    if tuple(mask.shape) != want:
        raise ValueError(f"{name} must be {want} like its image, got {tuple(mask.shape)}")
    return mask.to(dtype=image.dtype, device=image.device)


#: :func:`inverse_compositional_lk` goes on with its last active patches alone (a batch of one patch each) from
#: this many patches in all (fewer: the whole batch iterates to the end).
_COMPACT_MIN_PATCHES = 64


def _patch_offsets(patch_size: int, like: Tensor) -> Tensor:
    """``(h * h, 2)`` offsets ``(u, v)`` of a centred ``h x h`` grid, row-major."""
    r = torch.arange(patch_size, dtype=like.dtype, device=like.device) - (patch_size - 1) / 2.0
    v, u = torch.meshgrid(r, r, indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1)


def _sample(image: Tensor, points_px: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinear samples of ``(B, C, H, W)`` at ``(B, K, n, 2)`` pixel positions.

    Returns:
        ``(B, K, n, C)`` values (0 outside) and ``(B, K, n)`` inside-image indicator (float).
    """
    H, W = image.shape[-2:]
    u, v = points_px[..., 0], points_px[..., 1]
    sx = 2.0 / max(W - 1, 1)
    sy = 2.0 / max(H - 1, 1)
    grid = torch.stack([u * sx - 1.0, v * sy - 1.0], dim=-1)  # (B, K, n, 2)
    out = F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=True)  # (B, C, K, n)
    inside = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    return out.permute(0, 2, 3, 1), inside.to(image.dtype)


def _weighted_mean(x: Tensor, w: Tensor, total: Tensor) -> Tensor:
    """Mean of ``x (B, K, n, ...)`` over ``n`` with weights ``w (B, K, n)`` summing to ``total (B, K)``."""
    ww = w.reshape(w.shape + (1,) * (x.dim() - w.dim()))
    tt = total.reshape(total.shape + (1,) * (x.dim() - total.dim() - 1))
    return (x * ww).sum(2) / tt


def inverse_compositional_lk(
    reference: Tensor,
    images: Tensor,
    centres: Tensor,
    patch_size: int,
    iterations: int = 20,
    *,
    reference_mask: Tensor | None = None,
    image_mask: Tensor | None = None,
    tolerance: float = 1e-3,
    max_displacement: float | None = None,
    project_out_bias: bool = True,
    precomputed: LKTemplate | None = None,
    with_residual: bool = True,
) -> LKResult:
    """Track ``K`` square patches of ``reference`` into ``images`` by inverse-compositional Lucas-Kanade.

    Translation-only warp, all patches and samples at once (module docstring). Patch ``k`` of sample ``b`` is
    the ``h x h`` grid centred on ``centres[b, k]`` in ``reference[b]``; the search starts at the same position
    in ``images[b]`` (zero displacement).

    Args:
        reference: ``(B, C, h_r, w_r)`` reference images (the template ``T``).
        images: ``(B, C, H, W)`` current images (``I``), same ``B`` and ``C``.
        centres: ``(B, K, 2)`` patch centres ``(u, v)`` in reference pixels (and initial positions in ``images``).
        patch_size: ``h``, an int >= 3.
        iterations: maximum Gauss-Newton iterations, >= 1 (patches stop once converged).
        reference_mask: ``(B, 1, h_r, w_r)`` or None; reference pixels with mask <= 0.5 get weight 0.
        image_mask: ``(B, 1, H, W)`` or None; multiplies the weights at the warped grid (bilinear).
        tolerance: convergence threshold on ``|dp|`` (pixels).
        max_displacement: ``|p|`` above which a patch is not valid (and stops); None for no limit.
        project_out_bias: remove the weighted patch mean from the error and steepest-descent images.
        precomputed: :func:`lk_template` of the same ``reference``, ``centres``, ``patch_size`` and
            ``reference_mask`` (in the working dtype), to skip recomputing it; None computes it.
        with_residual: compute :attr:`LKResult.residual` (False: None, some 16 tensor operations fewer for a
            caller that does not read it, as :func:`dissimilarity`).

    Returns:
        :class:`LKResult`.

    Raises:
        TypeError: an argument is not a tensor / has the wrong dtype, or ``patch_size`` / ``iterations`` is not an int.
        ValueError: shapes do not match or a setting is out of range.

    Example:
        >>> ref = torch.rand(2, 1, 32, 32)
        >>> out = inverse_compositional_lk(ref, ref, torch.full((2, 3, 2), 15.0), patch_size=9)
        >>> out.displacement.shape, bool(out.displacement.abs().max() < 1e-4)
        (torch.Size([2, 3, 2]), True)
    """
    reference = _check_image(reference, "reference")
    images = _check_image(images, "images")
    if images.shape[:2] != reference.shape[:2]:
        raise ValueError(
            f"images must have the reference's batch and channels {tuple(reference.shape[:2])}, got "
            f"{tuple(images.shape[:2])}"
        )
    if not isinstance(centres, Tensor):
        raise TypeError(f"centres must be a torch.Tensor of shape (B, K, 2), got {type(centres).__name__}")
    if centres.dim() != 3 or centres.shape[0] != reference.shape[0] or centres.shape[-1] != 2:
        raise ValueError(f"centres must be (B, K, 2) with B={reference.shape[0]}, got {tuple(centres.shape)}")
    patch_size = check_int(patch_size, "patch_size", 3)
    iterations = check_int(iterations, "iterations", 1)
    if not 0 < tolerance < math.inf:  # (inf passed "> 0": every patch converged at its first update, as the config's)
        raise ValueError(f"tolerance must be a finite number > 0 (pixels), got {tolerance}")
    if max_displacement is not None and not max_displacement > 0:
        raise ValueError(f"max_displacement must be positive or None, got {max_displacement}")
    dtype = torch.promote_types(reference.dtype, images.dtype)
    reference = reference.to(dtype)
    images = images.to(dtype=dtype, device=reference.device)
    centres = centres.to(dtype=dtype, device=reference.device)
    if reference_mask is not None:
        reference_mask = _check_mask(reference_mask, "reference_mask", reference)
    if image_mask is not None:
        image_mask = _check_mask(image_mask, "image_mask", images)
    B, K = centres.shape[:2]
    eps = torch.finfo(dtype).eps

    if precomputed is None:
        precomputed = _lk_template(reference, centres, patch_size, reference_mask)
    grid, template, sd, ref_weight, ref_total = precomputed

    p = torch.zeros(B, K, 2, dtype=dtype, device=reference.device)
    active = torch.ones(B, K, dtype=torch.bool, device=reference.device)
    converged = torch.zeros_like(active)

    # The image and its mask are sampled together (one grid_sample per iteration), at the patch grid in
    # grid_sample's [-1, 1] coordinates (converted once; the displacement is scaled each iteration).
    stacked = images if image_mask is None else torch.cat([images, image_mask], dim=1)
    C = images.shape[1]
    H, W = images.shape[-2:]
    to_grid = grid.new_tensor([2.0 / max(W - 1, 1), 2.0 / max(H - 1, 1)])
    grid_n = grid * to_grid - 1.0  # (B, K, n, 2)
    n = grid.shape[2]
    # Per point, the features [grad T (C x 2, flattened), error (C), 1]: their weighted second moments give
    # H, the gradient and (with the constant) the patch means of the bias projection in one matmul:
    # sum w (s - s_bar)(e - e_bar) = sum w s e - W s_bar e_bar, and the same for H. grad T and the constant are
    # written once; each iteration writes its error into the buffer.
    F3 = 3 * C
    feats = torch.empty(B, K, n, F3 + 1, dtype=dtype, device=reference.device)
    feats[..., : 2 * C] = sd.reshape(B, K, n, 2 * C)
    feats[..., F3] = 1.0

    def weights_at(stacked: Tensor, grid_n: Tensor, ref_weight: Tensor, p_: Tensor) -> tuple[Tensor, Tensor]:
        g = torch.addcmul(grid_n, p_.unsqueeze(2), to_grid)
        out = F.grid_sample(stacked, g, mode="bilinear", padding_mode="zeros", align_corners=True)  # (B, C', K, n)
        values = out.permute(0, 2, 3, 1)
        inside = g.abs().amax(-1) <= scalar(1.0, g)
        w = ref_weight if image_mask is None else values[..., C].clamp(0.0, 1.0) * ref_weight
        return values[..., :C], torch.where(inside, w, scalar(0.0, w))

    def normal_equations(feats: Tensor, w: Tensor) -> tuple[Tensor, ...]:
        """``a, b, c, g0, g1`` ``(B, K)`` each: ``H = [[a, b], [b, c]]`` and the gradient ``sum w grad T^T e``
        (bias projected out), with the error in the features' buffer."""
        Bs, Ks = w.shape[:2]
        moments = torch.matmul((feats * w.unsqueeze(-1)).transpose(-1, -2), feats)  # (B, K, F + 1, F + 1)
        if C == 1:  # gray images (the dissimilarity's): rows [grad T], columns [grad T, e], read in one go
            m = moments[..., :2, :3]
            if project_out_bias:  # m_ij - m_i1 m_1j / m_11 (the constant's row and column are not used)
                m = m - moments[..., :2, 3:] * (moments[..., 3:, :3] / moments[..., 3:, 3:].clamp_min(eps))
            a, b, g0, _, c, g1 = m.reshape(Bs, Ks, 6).unbind(-1)
            return a, b, c, g0, g1
        if project_out_bias:
            moments = moments - moments[..., :, F3:] * (moments[..., F3:, :] / moments[..., F3:, F3:].clamp_min(eps))
        s_s = moments[..., : 2 * C, : 2 * C].reshape(Bs, Ks, C, 2, C, 2)
        s_e = moments[..., : 2 * C, 2 * C : F3].reshape(Bs, Ks, C, 2, C)
        hess = torch.diagonal(s_s, dim1=2, dim2=4).sum(-1)  # sum over channels: (B, K, 2, 2)
        grad = torch.diagonal(s_e, dim1=2, dim2=4).sum(-1)  # (B, K, 2)
        return hess[..., 0, 0], hess[..., 0, 1], hess[..., 1, 1], grad[..., 0], grad[..., 1]

    def iterate(
        stacked: Tensor, grid_n: Tensor, feats: Tensor, template: Tensor, ref_weight: Tensor, p: Tensor,
        active: Tensor, converged: Tensor, budget: int, few: int,
    ) -> tuple[Tensor, Tensor, Tensor, int]:
        """Up to ``budget`` iterations of the patches laid out ``(B', K')`` in these tensors (``stacked``
        ``(B', C', H, W)``), until none is active or (``few`` > 0) at most ``few`` are: ``p``, ``active``,
        ``converged`` and the iterations made. Each patch iterates until its update is below the tolerance
        (converged), its system is ill-posed or it moves beyond max_displacement (both end it as not valid,
        found from its final state); a patch that stopped no longer changes, so only the active ones matter."""
        err_slot = feats[..., 2 * C : F3]
        made = 0
        while made < budget:
            warped, w = weights_at(stacked, grid_n, ref_weight, p)
            torch.sub(warped, template, out=err_slot)
            a, b, c, g0, g1 = normal_equations(feats, w)
            det = a * c - b * b
            # Well-posed: det above a relative floor (det <= trace^2 / 4) and everything finite (NaN fails the
            # first test, an infinite H or gradient the second).
            ok = (det > scalar(1e3 * eps, det) * (a + c).square()) & isfinite(det + g0 + g1)
            dp = torch.stack([c * g0 - b * g1, a * g1 - b * g0], -1) / det.unsqueeze(-1)  # H^-1 g; used where ok
            step = active & ok
            p = torch.where(step.unsqueeze(-1), p - dp, p)  # compose with the inverse increment
            small = dp.norm(dim=-1) < scalar(tolerance, dp)
            converged = converged | (step & small)
            active = step & ~small
            if max_displacement is not None:
                # p is finite: a step needs a finite dp
                active = active & (p.norm(dim=-1) <= scalar(max_displacement, p))
            made += 1
            if made == budget:  # (no read of the active count: it would wait for the device, for nothing)
                break
            left = int(active.sum())
            if left == 0 or left <= few:
                break
        return p, active, converged, made

    p = torch.zeros(B, K, 2, dtype=dtype, device=reference.device)
    active = torch.ones(B, K, dtype=torch.bool, device=reference.device)
    converged = torch.zeros_like(active)
    # Most patches converge in a few iterations and a few take many: once at most a quarter of a large batch's
    # patches are still active, those go on alone, each as a batch of one patch (the same arithmetic per patch).
    few = (B * K) // 4 if B * K >= _COMPACT_MIN_PATCHES else 0
    p, active, converged, made = iterate(stacked, grid_n, feats, template, ref_weight, p, active, converged,
                                         iterations, few)  # fmt: skip
    if made < iterations and bool(active.any()):
        at = active.reshape(-1).nonzero().squeeze(-1)  # (M,) over B * K

        def rows(x: Tensor) -> Tensor:  # (B, K, ...) -> the active patches' (M, 1, ...)
            return x.reshape(B * K, *x.shape[2:]).index_select(0, at).unsqueeze(1)

        sub = iterate(
            stacked.index_select(0, torch.div(at, K, rounding_mode="floor")), rows(grid_n), rows(feats),
            rows(template), rows(ref_weight), rows(p), rows(active), rows(converged), iterations - made, 0,
        )  # fmt: skip
        p = p.reshape(B * K, 2).index_copy(0, at, sub[0].reshape(-1, 2)).view(B, K, 2)
        active = active.reshape(-1).index_copy(0, at, sub[1].reshape(-1)).view(B, K)
        converged = converged.reshape(-1).index_copy(0, at, sub[2].reshape(-1)).view(B, K)

    # Valid: converged or still iterating (not stopped by an ill-posed system), within max_displacement (p no
    # longer changes once a patch stops, so its final norm is the one that stopped it).
    valid = active | converged
    if max_displacement is not None:
        valid = valid & (p.norm(dim=-1) <= max_displacement)
    warped, w = weights_at(stacked, grid_n, ref_weight, p)
    total = w.sum(-1)
    residual = None
    if with_residual:
        err = warped - template
        if project_out_bias:
            err = err - _weighted_mean(err, w, total.clamp_min(eps)).unsqueeze(2)
        residual = ((err.square().sum(-1) * w).sum(-1) / (total.clamp_min(eps) * err.shape[-1])).sqrt()
    support = torch.where(ref_total > 0, total / ref_total.clamp_min(eps), torch.zeros_like(total))
    valid = valid & torch.isfinite(p).all(-1) & (ref_total > 0)
    return LKResult(p, converged, valid, support.clamp(0.0, 1.0), residual)


def _lk_template(reference: Tensor, centres: Tensor, patch_size: int, reference_mask: Tensor | None) -> LKTemplate:
    dtype = reference.dtype
    offsets = _patch_offsets(patch_size, reference)  # (n, 2)
    grid = centres.unsqueeze(2) + offsets  # (B, K, n, 2)
    unit_u = offsets.new_tensor([1.0, 0.0])
    unit_v = offsets.new_tensor([0.0, 1.0])
    # The patch grid and its four neighbours (central differences), image and mask, in one sampling: every sample
    # is computed alone, so the values are those of five separate calls (a reference took 1 ms less per entry).
    C = reference.shape[1]
    stacked = reference if reference_mask is None else torch.cat([reference, reference_mask.to(dtype)], 1)
    grids = torch.cat([grid, grid + unit_u, grid - unit_u, grid + unit_v, grid - unit_v], 1)  # (B, 5 K, n, 2)
    values, inside = _sample(stacked, grids)
    at, right, left, down, up = values.chunk(5, dim=1)  # (B, K, n, C [+ 1]) each
    template, inside_r = at[..., :C], inside.chunk(5, dim=1)[0]  # (B, K, n, C), (B, K, n)
    gu = 0.5 * (right[..., :C] - left[..., :C])
    gv = 0.5 * (down[..., :C] - up[..., :C])
    sd = torch.stack([gu, gv], dim=-1)  # (B, K, n, C, 2) steepest-descent images grad T
    weight = inside_r
    if reference_mask is not None:
        weight = weight * (at[..., C] > 0.5).to(dtype)
    return LKTemplate(grid, template.contiguous(), sd, weight, weight.sum(-1))


def lk_template(
    reference: Tensor, centres: Tensor, patch_size: int, reference_mask: Tensor | None = None
) -> LKTemplate:
    """The reference side of :func:`inverse_compositional_lk` (template patches, ``grad T``, weights).

    Args:
        reference: ``(B, C, h_r, w_r)``; centres: ``(B, K, 2)`` pixels; patch_size: ``h``;
        reference_mask: ``(B, 1, h_r, w_r)`` or None.

    Returns:
        :class:`LKTemplate` in ``reference``'s dtype.
    """
    reference = _check_image(reference, "reference")
    if reference_mask is not None:
        reference_mask = _check_mask(reference_mask, "reference_mask", reference)
    return _lk_template(reference, centres.to(reference), patch_size, reference_mask)


@dataclass(frozen=True)
class DissimilarityConfig:
    """Settings of the dissimilarity measure (module docstring).

    Attributes:
        patch_size: ``h``, side of the square fiducial patches (pixels of the normalised face), odd, >= 3.
        num_patches: ``K``, fiducial patches picked on the reference.
        min_separation: minimum distance (pixels, per axis) between patch centres (non-maximum suppression
            window half-width); None means ``patch_size``.
        border: patch centres stay this far (pixels) from the image border, beyond half a patch.
        iterations: maximum inverse-compositional Lucas-Kanade iterations.
        tolerance: convergence threshold on the update (pixels).
        max_displacement: ``d_max``, search range (pixels); a patch further away or failing counts as ``d_max``.
        d0: displacement scale (pixels) of the confidence ``exp(-(d / d0)^2)``.
        min_support: fraction of a patch's reference pixels that must be inside the current mask.
        min_patches: fewer present patches than this give confidence 0.
        min_present_fraction: fewer present patches than this fraction of the reference's valid ones give
            confidence 0 (0: off; template management keeps it off, and its default settings say why).
        smoothing_sigma: Gaussian pre-smoothing (pixels) of both normalised faces (0 for none); it widens
            Lucas-Kanade's basin of convergence.
        project_out_bias: remove each patch's mean intensity offset (a light-normalisation residual).
        trim_fraction: the largest this fraction of the present patches' displacements (rounded down, at
            least one patch kept) is left out of the mean ``d``. A few patches that a cast shadow or a view's
            edge displaces then no longer decide the confidence alone: on the James long run, with the key
            light drifted 40 degrees to the side, two of eight patches moved 2.3 and 2.9 px at frontal while
            the others moved 0.2-1.0, and the mean of all eight (confidence 0.15) declared a right track lost.
    """

    patch_size: int = 11
    num_patches: int = 16
    min_separation: int | None = None
    border: int = 2
    iterations: int = 20
    tolerance: float = 1e-3
    max_displacement: float = 6.0
    d0: float = 1.5
    min_support: float = 0.8
    min_patches: int = 1
    min_present_fraction: float = 0.0
    smoothing_sigma: float = 1.0
    project_out_bias: bool = True
    trim_fraction: float = 0.25

    def __post_init__(self) -> None:
        for name, low in (("patch_size", 3), ("num_patches", 1), ("iterations", 1), ("min_patches", 1), ("border", 0)):
            object.__setattr__(self, name, check_int(getattr(self, name), name, low))
        object.__setattr__(self, "min_separation", check_optional_int(self.min_separation, "min_separation", 1))
        object.__setattr__(self, "project_out_bias", check_bool(self.project_out_bias, "project_out_bias"))
        # Each number's range, stated once (inf passed "> 0": a tolerance met at once, a d0 that scored every
        # displacement 1, an infinite search range or smoothing)
        for name, interval in (("tolerance", "(0, inf)"), ("max_displacement", "(0, inf)"), ("d0", "(0, inf)"),
                               ("min_support", "(0, 1]"), ("min_present_fraction", "[0, 1]"),
                               ("smoothing_sigma", "[0, inf)"), ("trim_fraction", "[0, 1)")):  # fmt: skip
            object.__setattr__(self, name, check_number(getattr(self, name), name, interval))
        if self.patch_size % 2 == 0:
            raise ValueError(f"patch_size must be an odd int >= 3, got {self.patch_size}")

    @property
    def separation(self) -> int:
        """The non-maximum suppression half-width actually used."""
        return self.patch_size if self.min_separation is None else self.min_separation


@dataclass(frozen=True, eq=False)
class DissimilarityReference:
    """The reference normalised face prepared for :func:`dissimilarity`.

    Attributes:
        image: ``(B, 1, G, G)`` gray, masked and smoothed reference (the Lucas-Kanade template).
        mask: ``(B, 1, G, G)`` float reference mask.
        centres: ``(B, K, 2)`` fiducial patch centres ``(u, v)`` in pixels.
        patch_valid: ``(B, K)`` bool; False where the reference had fewer than ``K`` textured places.
        score: ``(B, K)`` texture score (smaller structure-tensor eigenvalue, summed over the patch).
        config: the :class:`DissimilarityConfig` used.
        lk: the Lucas-Kanade reference side (:func:`lk_template` of ``image``, ``centres`` and ``mask``),
            computed once here so that :func:`dissimilarity` does not redo it every frame; None to compute it
            on each call.
    """

    image: Tensor
    mask: Tensor
    centres: Tensor
    patch_valid: Tensor
    score: Tensor
    config: DissimilarityConfig
    lk: LKTemplate | None = None

    def select(self, index: Tensor | tuple[Tensor, Tensor]) -> "DissimilarityReference":
        """The reference of the samples ``index`` (a ``(B',)`` int64 or bool tensor, or a pair of ``(B',)`` int64
        tensors that index the first two dimensions: ``(streams, entries)`` of a mosaic's references)."""
        return DissimilarityReference(
            self.image[index], self.mask[index], self.centres[index], self.patch_valid[index], self.score[index],
            self.config, None if self.lk is None else self.lk.select(index),
        )  # fmt: skip

    @property
    def num_patches(self) -> Tensor:
        """``(B,)`` number of valid patches per sample."""
        return self.patch_valid.sum(-1)


class DissimilarityResult(NamedTuple):
    """What :func:`dissimilarity` returns (unpacks as ``dissimilarity, confidence`` plus details).

    Attributes:
        dissimilarity: ``(B,)`` mean patch displacement (pixels of the normalised face), ``d_max`` when no
            patch is present.
        confidence: ``(B,)`` in ``[0, 1]``.
        displacement: ``(B, K, 2)`` per-patch displacement.
        present: ``(B, K)`` bool, the patch counted.
    """

    dissimilarity: Tensor
    confidence: Tensor
    displacement: Tensor
    present: Tensor


def trimmed_mean(dist: Tensor, present: Tensor, count: Tensor, trim_fraction: float) -> Tensor:
    """``(B,)`` the mean of ``dist`` ``(B, K)`` over the ``present`` patches after leaving out the largest
    ``floor(trim_fraction * count)`` of them (``count`` ``(B,)`` present per row; at least one kept)."""
    keep = torch.clamp(count - torch.floor(count.to(dist.dtype) * trim_fraction).to(count.dtype), min=1)
    ordered = torch.where(present, dist, torch.full_like(dist, float("inf"))).sort(-1).values
    used = torch.arange(dist.shape[-1], device=dist.device) < keep.unsqueeze(-1)
    return torch.where(used, ordered, torch.zeros_like(ordered)).sum(-1) / keep.to(dist.dtype)


@functools.lru_cache(maxsize=16)
def _gaussian_kernels(sigma: float, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """The normalised 1D Gaussian of ``sigma`` (radius ``round(3 sigma)``, at least 1) as ``(1, 1, 1, k)`` and
    ``(1, 1, k, 1)`` convolution weights along rows and columns: cached constants (never modify them), made
    outside inference mode."""
    with torch.inference_mode(False):
        radius = max(1, int(round(3.0 * sigma)))
        x = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
        k = torch.exp(-0.5 * (x / sigma) ** 2)
        k = k / k.sum()
        return k.reshape(1, 1, 1, -1), k.reshape(1, 1, -1, 1)


def _masked_gray(image: Tensor, mask: Tensor, sigma: float) -> Tensor:
    """``(B, 1, G, G)`` channel mean, Gaussian-smoothed by normalised convolution inside ``mask``, 0 outside.

    The gray image and the mask are blurred by separate single-channel convolutions: one two-group convolution
    (or the two as a batch of two) took several times longer on the CPU (64 x 64: 50 against 7 microseconds)."""
    gray = image.mean(1, keepdim=True) * mask
    if sigma <= 0:
        return gray
    kx, ky = _gaussian_kernels(float(sigma), image.dtype, image.device)
    r = kx.shape[-1] // 2

    def blur(x: Tensor) -> Tensor:
        x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), kx)
        return F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), ky)

    num = blur(gray)
    den = blur(mask)
    eps = torch.finfo(image.dtype).eps
    return torch.where(den > 1e3 * eps, num / den.clamp_min(1e3 * eps), 0.0) * mask


def _check_face(image: object, mask: object, name: str) -> tuple[Tensor, Tensor]:
    image = _check_image(image, name)
    if image.shape[-1] != image.shape[-2]:
        raise ValueError(f"{name} must be square (B, C, G, G), got {tuple(image.shape)}")
    mask = _check_mask(mask, f"{name}'s mask", image)
    return image, (mask > 0.5).to(image.dtype)


@full_precision
@torch.no_grad()
def build_dissimilarity_reference(
    image: Tensor, mask: Tensor, config: DissimilarityConfig | None = None, backend: Backend = Backend.AUTO
) -> DissimilarityReference:
    """Pick the fiducial patches of a reference normalised face (no gradient: the reference is fixed data).

    The texture score at each pixel is the smaller eigenvalue of the structure tensor ``sum grad g grad g^T``
    of the smoothed gray image summed over the patch (Shi-Tomasi). Candidates are pixels whose whole patch
    (plus one pixel for the gradient) is inside ``mask`` and at least ``border`` pixels beyond half a patch from
    the image border. Greedy non-maximum suppression keeps the ``K`` best (highest score first), each more than
    ``s = config.separation`` pixels (along ``u`` or ``v``) from every better one.

    Args:
        image: ``(B, C, G, G)`` reference normalised face (:class:`torchface.normalise.NormalisedFace`).
        mask: ``(B, 1, G, G)`` its mask.
        config: :class:`DissimilarityConfig` (defaults when None).
        backend: :class:`~torchface.backend.Backend` of the smoothing, the texture score and the suppression
            (``torchface/_native/dissimilarity.h``, the same steps; the scores agree to rounding).

    Returns:
        :class:`DissimilarityReference`.

    Raises:
        TypeError, ValueError: bad arguments (the message says what was expected).

    Example:
        >>> ref = build_dissimilarity_reference(torch.rand(1, 3, 96, 96), torch.ones(1, 1, 96, 96))
        >>> ref.centres.shape, int(ref.num_patches[0])
        (torch.Size([1, 16, 2]), 16)
    """
    config = DissimilarityConfig() if config is None else config
    if not isinstance(config, DissimilarityConfig):
        raise TypeError(f"config must be a DissimilarityConfig, got {type(config).__name__}")
    image, mask = _check_face(image, mask, "image")
    B, _, G, _ = image.shape
    h = config.patch_size
    r = h // 2
    K = min(config.num_patches, G * G)
    if use_native(backend, (image, mask), "dissimilarity reference"):
        gray, index, best = _native_patches(image, mask, config, K)
        return _reference(image, gray, mask, index, best, config, K)
    gray = _masked_gray(image, mask, config.smoothing_sigma)

    # Structure tensor (central differences), summed over the patch window.
    gu = torch.zeros_like(gray)
    gv = torch.zeros_like(gray)
    gu[..., :, 1:-1] = 0.5 * (gray[..., :, 2:] - gray[..., :, :-2])
    gv[..., 1:-1, :] = 0.5 * (gray[..., 2:, :] - gray[..., :-2, :])
    st = torch.cat([gu * gu, gu * gv, gv * gv], dim=1)
    st = F.avg_pool2d(st, h, stride=1, padding=r, count_include_pad=True) * (h * h)
    a, b, c = st[:, 0], st[:, 1], st[:, 2]
    min_eig = 0.5 * (a + c) - torch.sqrt((0.5 * (a - c)).square() + b.square())

    # Eligible centres: the whole patch (plus one pixel for the gradient) inside the mask and the image.
    full = F.avg_pool2d(mask, h + 2, stride=1, padding=r + 1, count_include_pad=True)[:, 0]
    eligible = full > 1.0 - 1e-6
    edge = r + 1 + config.border
    inner = torch.zeros(G, G, dtype=torch.bool, device=image.device)
    if G - 2 * edge > 0:
        inner[edge : G - edge, edge : G - edge] = True
    eligible = eligible & inner
    score = torch.where(eligible, min_eig.clamp_min(0.0), torch.full_like(min_eig, -1.0))

    # Greedy non-maximum suppression, all samples at once: take the best remaining candidate, then remove
    # every candidate within s pixels (per axis) of it, once per reference. The neighbourhood of a pick is the
    # (2 s + 1)^2 cells around it, clamped into the image (a clamped cell is still one of them).
    s = config.separation
    around = torch.arange(-s, s + 1, device=image.device)
    ranked = score.reshape(B, G * G).clone()
    picks, bests = [], []
    for _ in range(K):
        best, index = ranked.max(dim=-1)  # (B,)
        picks.append(index)
        bests.append(best)
        v = torch.div(index, G, rounding_mode="floor")
        rows = (v.unsqueeze(-1) + around).clamp(0, G - 1)
        cols = (index - v * G).unsqueeze(-1).add(around).clamp(0, G - 1)
        ranked.scatter_(1, (rows.unsqueeze(-1) * G + cols.unsqueeze(-2)).view(B, (2 * s + 1) ** 2), -1.0)  # (B = 0)
    return _reference(image, gray, mask, torch.stack(picks, -1), torch.stack(bests, -1), config, K)


def _reference(image: Tensor, gray: Tensor, mask: Tensor, index: Tensor, best: Tensor, config: DissimilarityConfig,
               K: int) -> DissimilarityReference:  # fmt: skip
    """The :class:`DissimilarityReference` of ``K`` picks: flat pixel ``index (B, K)`` int64 and score
    ``best (B, K)`` (-1: no textured place left), on the smoothed ``gray (B, 1, G, G)``."""
    B, G, h = image.shape[0], image.shape[-1], config.patch_size
    centres = torch.stack([(index % G).to(image.dtype), (index // G).to(image.dtype)], dim=-1)
    if K < config.num_patches:
        pad = config.num_patches - K
        centres = torch.cat([centres, centres.new_zeros(B, pad, 2)], 1)
        best = torch.cat([best, best.new_full((B, pad), -1.0)], 1)
    patch_valid = best > 0
    lk = _lk_template(gray, centres, h, mask)
    return DissimilarityReference(gray, mask, centres, patch_valid, best.clamp_min(0.0), config, lk)


@full_precision
@torch.no_grad()
def dissimilarity(
    reference: DissimilarityReference, normalised: Tensor, mask: Tensor, backend: Backend = Backend.AUTO
) -> DissimilarityResult:
    """Dissimilarity (pixels) and confidence in ``[0, 1]`` of normalised faces against the reference.

    A decision measure: it runs without autograd (faces that require grad are read, the results carry no
    gradient; the patch search is iterative and its displacements are clamped, so it has no useful one).

    Each of the reference's patches is tracked on ``normalised`` by :func:`inverse_compositional_lk` (both
    images gray, masked and smoothed alike), and ``d = mean_k min(|p_k|, d_max)`` over the present patches
    less the largest ``trim_fraction`` of them (:func:`trimmed_mean`), ``confidence = exp(-(d / d0)^2)``
    (module docstring). No patch present gives ``d = d_max`` and
    confidence 0, never NaN.

    Args:
        reference: from :func:`build_dissimilarity_reference`, batch ``B`` (or 1, broadcast).
        normalised: ``(B, C, G, G)`` current normalised faces (same ``G`` as the reference).
        mask: ``(B, 1, G, G)`` their masks.
        backend: :class:`~torchface.backend.Backend` of the smoothing and the patch tracking: the native kernel
            (``torchface/_native/dissimilarity.h``, each patch on its own) needs the reference's precomputed
            patches (:attr:`DissimilarityReference.lk`, as built) in the working dtype.

    Returns:
        :class:`DissimilarityResult` ``(dissimilarity (B,), confidence (B,), displacement (B, K, 2),
        present (B, K))``.

    Raises:
        TypeError, ValueError: bad arguments (the message says what was expected and what arrived).

    Example:
        >>> face, m = torch.rand(2, 3, 64, 64), torch.ones(2, 1, 64, 64)
        >>> ref = build_dissimilarity_reference(face, m)
        >>> d, conf = dissimilarity(ref, face, m)[:2]
        >>> bool((d < 1e-3).all()), bool((conf > 0.99).all())
        (True, True)
    """
    if not isinstance(reference, DissimilarityReference):
        raise TypeError(f"reference must be a DissimilarityReference, got {type(reference).__name__}")
    normalised, mask = _check_face(normalised, mask, "normalised")
    cfg = reference.config
    B = normalised.shape[0]
    Br, _, G, _ = reference.image.shape
    if normalised.shape[-1] != G:
        raise ValueError(f"normalised must be {G}x{G} like the reference, got {tuple(normalised.shape[-2:])}")
    if Br not in (1, B):
        raise ValueError(f"the reference's batch must be 1 or B={B}, got {Br}")
    dtype = torch.promote_types(reference.image.dtype, normalised.dtype)
    ref_image = reference.image.to(dtype=dtype, device=normalised.device).expand(B, -1, -1, -1)
    ref_mask = reference.mask.to(dtype=dtype, device=normalised.device).expand(B, -1, -1, -1)
    centres = reference.centres.to(dtype=dtype, device=normalised.device).expand(B, -1, -1)
    patch_valid = reference.patch_valid.to(normalised.device).expand(B, -1)
    normalised, mask = normalised.to(dtype), mask.to(dtype)
    pre = reference.lk
    if pre is not None and (Br != B or pre.template.dtype != dtype or pre.template.device != normalised.device):
        pre = None
    native = pre is not None and pre.template.shape[-1] == 1 and use_native(
        backend, (normalised, mask, *pre), "dissimilarity"
    )
    if backend is Backend.NATIVE and not native:
        raise RuntimeError("the native dissimilarity needs the reference's gray patches (DissimilarityReference.lk) "
                           "in the faces' dtype and batch")  # fmt: skip
    if native and pre is not None:  # (native implies pre)
        lk = _native_lk(normalised, mask, pre, cfg)
    else:
        gray = _masked_gray(normalised, mask, cfg.smoothing_sigma)
        lk = inverse_compositional_lk(
            ref_image, gray, centres, cfg.patch_size, cfg.iterations,
            reference_mask=ref_mask, image_mask=mask, tolerance=cfg.tolerance,
            max_displacement=cfg.max_displacement, project_out_bias=cfg.project_out_bias, precomputed=pre,
            with_residual=False,
        )  # fmt: skip
    d_max = cfg.max_displacement
    present = patch_valid & (lk.support >= cfg.min_support)
    dist = lk.displacement.norm(dim=-1).nan_to_num(nan=d_max, posinf=d_max).clamp(max=d_max)
    dist = torch.where(lk.valid, dist, torch.full_like(dist, d_max))
    count = present.sum(-1)
    mean = trimmed_mean(dist, present, count, cfg.trim_fraction)
    enough = (count >= cfg.min_patches) & (count >= cfg.min_present_fraction * patch_valid.sum(-1))
    d = torch.where(enough, mean, torch.full_like(mean, d_max))
    conf = torch.exp(-(d / cfg.d0).square()) * enough
    return DissimilarityResult(d, conf, lk.displacement, present)


def _native_lk(normalised: Tensor, mask: Tensor, pre: LKTemplate, cfg: DissimilarityConfig) -> LKResult:
    """:func:`dissimilarity`'s smoothing and patch tracking by the native kernel (``_masked_gray`` and
    :func:`inverse_compositional_lk` of one gray channel, each patch on its own): the :class:`LKResult` without
    its residual. ``normalised`` ``(B, C, G, G)`` and ``mask`` ``(B, 1, G, G)`` of 0 / 1 in the working dtype."""
    B, C, G, _ = normalised.shape
    dtype = normalised.dtype
    grid, template, sd, ref_weight, ref_total = pre
    K, n = grid.shape[1], grid.shape[2]
    if cfg.smoothing_sigma > 0:
        kernel = _gaussian_kernels(float(cfg.smoothing_sigma), dtype, normalised.device)[0].reshape(-1).contiguous()
    else:
        kernel = torch.ones(1, dtype=dtype)
    inputs = [x.contiguous() for x in (normalised, mask, grid, template.reshape(B, K, n), sd.reshape(B, K, n, 2),
                                       ref_weight, ref_total)]  # fmt: skip
    gray = torch.empty(B, 1, G, G, dtype=dtype)
    p = torch.empty(B, K, 2, dtype=dtype)
    support = torch.empty(B, K, dtype=dtype)
    converged = torch.empty(B, K, dtype=torch.bool)
    valid = torch.empty(B, K, dtype=torch.bool)
    prob = _native.LKProblem(
        B=B, C=C, G=G, K=K, n=n, radius=kernel.numel() // 2, iterations=cfg.iterations,
        project_out_bias=int(cfg.project_out_bias), has_max_displacement=int(cfg.max_displacement is not None),
        eps=torch.finfo(dtype).eps, tolerance=float(cfg.tolerance),
        max_displacement=float(cfg.max_displacement) if cfg.max_displacement is not None else 0.0,
        normalised=inputs[0].data_ptr(), mask=inputs[1].data_ptr(), kernel=kernel.data_ptr(),
        grid=inputs[2].data_ptr(), templ=inputs[3].data_ptr(), sd=inputs[4].data_ptr(),
        ref_weight=inputs[5].data_ptr(), ref_total=inputs[6].data_ptr(), out_gray=gray.data_ptr(),
        out_p=p.data_ptr(), out_support=support.data_ptr(), out_converged=converged.data_ptr(),
        out_valid=valid.data_ptr(),
    )  # fmt: skip
    _native.run("dissimilarity", dtype == torch.float64, prob, B, torch.get_num_threads())
    return LKResult(p, converged, valid, support, None)


def _native_patches(image: Tensor, mask: Tensor, config: DissimilarityConfig, K: int) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`build_dissimilarity_reference`'s smoothing, texture score and suppression by the native kernel:
    ``gray (B, 1, G, G)``, the picks' flat pixel index ``(B, K)`` int64 and their scores ``(B, K)``."""
    B, C, G, _ = image.shape
    dtype = image.dtype
    sigma = float(config.smoothing_sigma)
    kernel = (_gaussian_kernels(sigma, dtype, image.device)[0].reshape(-1) if sigma > 0
              else torch.ones(1, dtype=dtype)).contiguous()  # fmt: skip
    image_c, mask_c = image.contiguous(), mask.contiguous()
    gray = torch.empty(B, 1, G, G, dtype=dtype)
    index = torch.empty(B, K, dtype=dtype)
    best = torch.empty(B, K, dtype=dtype)
    prob = _native.LKProblem(
        B=B, C=C, G=G, K=K, n=config.patch_size, radius=kernel.numel() // 2 if sigma > 0 else 0,
        iterations=config.separation, eps=torch.finfo(dtype).eps, normalised=image_c.data_ptr(),
        mask=mask_c.data_ptr(), kernel=kernel.data_ptr(), out_gray=gray.data_ptr(), out_p=index.data_ptr(),
        out_support=best.data_ptr(), radius_border=config.border,
    )  # fmt: skip
    _native.run("reference_patches", dtype == torch.float64, prob, B, torch.get_num_threads())
    return gray, index.round().long(), best
