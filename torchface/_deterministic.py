"""Substitutes for the CUDA operations that raise under ``torch.use_deterministic_algorithms(True)``.

A training run that asks torch for deterministic algorithms makes every CUDA operation without a deterministic
kernel raise ``RuntimeError: ... does not have a deterministic implementation``. Three that torchface uses are on
torch's list:

- ``torch.nanmedian(x, dim)`` (its CUDA kernel returns indices: "median CUDA with indices output"), in the robust
  scale of every tracking step: without a substitute, no frame could be tracked on a GPU in that mode;
- the backward of ``grid_sample`` with respect to the image (atomic adds), where a frame's pixels require grad:
  ``NormalisedFaceLayer``'s faces and unrolled iterations, ``NormalisedFace``;
- the backward of ``F.pad(mode="reflect")`` (``pyr_down``, the tracking pyramid of a frame that requires grad).

Where the mode is on and the tensor is on a CUDA device (and, for the two backward ones, requires grad), these
functions compute the same thing with operations that have deterministic kernels: a sort and a gather for the
median (the same values), gathered corners for the bilinear sample (the same to float rounding, gradients
included), concatenated slices for the reflected border (the same values). Elsewhere they call torch's operation,
so results off that path are unchanged bit for bit. ``tests/test_deterministic.py`` checks each substitute against
torch's operation on the CPU (forced with :data:`FORCE`).

The gathered corners serve one more case: under torch < 2.12 ``torch.func.jacrev`` with respect to the sampled
points alone (the normalised face's Jacobian with respect to the pose) raised inside torch's ``grid_sample``
backward (:func:`_grid_sample_vmap_backward_broken`, probed).
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor

from torchface._compiling import feature_probe

__all__ = ["grid_sample_border", "nanmedian_values", "reflect_pad"]

#: Tests set this to True to run the substitutes on any device (module docstring).
FORCE = False


def _jacrev_of_grid_sample_with_respect_to_the_grid() -> None:
    grid = torch.zeros(1, 1, 1, 2, dtype=torch.float32, device="cpu")
    for needs_grad in (False, True):  # (an image that requires grad outside the transform asks for none inside it)
        images = torch.zeros(1, 1, 2, 2, dtype=torch.float32, device="cpu", requires_grad=needs_grad)
        torch.func.jacrev(
            lambda g, images=images: F.grid_sample(images, g, "bilinear", "border", align_corners=True)
        )(grid)


@functools.cache
def _grid_sample_vmap_backward_broken() -> bool:
    """Whether ``torch.func.jacrev`` of ``grid_sample`` with respect to the grid alone raises: torch before 2.12
    (2.5.1 and 2.11 raise; 2.12, session 57, and 2.13 do not), whose ``vmap`` rule of ``grid_sample``'s backward
    fails where the image asks for no gradient at the transform's level and the grid does ("Expected a proper Tensor
    but got None ... argument #0 'self'"), also where the image requires grad outside the transform. The gathered
    corners run there instead.

    Probed (:func:`torchface._compiling.feature_probe`: both cases on a 2x2 image, about a millisecond) at the first
    call, which comes under such a transform (:func:`grid_sample_border` asks only there), and kept for the process.
    (On the CPU: the rule is the same on every device.)"""
    return not feature_probe(_jacrev_of_grid_sample_with_respect_to_the_grid)


def _substitute(x: Tensor, backward: bool) -> bool:
    """Whether torch's CUDA operation on ``x`` would raise (module docstring); ``backward``: only its backward
    raises, so only where ``x`` requires grad."""
    if FORCE:
        return True
    return x.is_cuda and (x.requires_grad or not backward) and torch.are_deterministic_algorithms_enabled()


def nanmedian_values(x: Tensor, dim: int = -1) -> Tensor:
    """``torch.nanmedian(x, dim).values``: the lower middle value of the non-NaN entries along ``dim`` (NaN where
    there are none), also under deterministic algorithms on CUDA (module docstring).

    Args:
        x: a floating-point tensor.
        dim: the dimension reduced.

    Returns:
        ``x``'s shape without ``dim``.
    """
    if not _substitute(x, backward=False):
        return torch.nanmedian(x, dim=dim).values
    nan = torch.isnan(x)
    ordered = torch.sort(torch.where(nan, torch.inf, x), dim=dim, stable=True).values  # NaN (as inf) last
    count = (~nan).sum(dim=dim, keepdim=True)
    middle = torch.gather(ordered, dim, ((count - 1) // 2).clamp_min(0)).squeeze(dim)
    return torch.where(count.squeeze(dim) > 0, middle, torch.nan)


def _clip(coordinate: Tensor, limit: int) -> Tensor:
    """``coordinate`` clipped to ``[0, limit]`` with grid_sample's gradient: 1 strictly inside, 0 on the border and
    outside it (``clamp``'s is 1 on the border too); a NaN one at 0, as grid_sample reads it (``clamp`` keeps NaN,
    whose gather index was out of range: "index -9223372036854775808 is out of bounds", a device-side assert on
    CUDA)."""
    inside = (coordinate > 0) & (coordinate < limit)
    return torch.where(inside, coordinate, coordinate.detach().nan_to_num(nan=0.0).clamp(0, limit))


def _grid_alone_under_a_transform(images: Tensor, grid: Tensor) -> bool:
    """Whether a ``torch.func`` transform asks for ``grid``'s gradient and not ``images``': ``grid`` is wrapped by it
    and ``images`` is not, at its level (an image that requires grad at an outer level, as a frame a network made,
    asks for none at the transform's: torch < 2.12 raised there too, :func:`_grid_sample_vmap_backward_broken`)."""
    functorch = torch._C._functorch
    if not (grid.requires_grad and functorch.is_functorch_wrapped_tensor(grid)):
        return False
    return not images.requires_grad or functorch.maybe_get_level(images) < functorch.maybe_get_level(grid)


def grid_sample_border(images: Tensor, grid: Tensor) -> Tensor:
    """``F.grid_sample(images, grid, mode="bilinear", padding_mode="border", align_corners=True)``, also where the
    image's gradient is asked for under deterministic algorithms on CUDA (module docstring), and for a grid wrapped
    by a ``torch.func`` transform that asks for the grid's gradient and not the image's, where torch's raises
    there (:func:`_grid_sample_vmap_backward_broken`, torch < 2.12).

    Args:
        images: ``(B, C, H, W)``.
        grid: ``(B, Ho, Wo, 2)`` normalised coordinates ``(x, y)`` in ``[-1, 1]`` (``align_corners=True``), of
            ``images``' dtype; outside it the border is read (an infinite one too), a NaN one reads column / row 0
            as grid_sample does (the tracker's points of a diverged or lost stream).

    Returns:
        ``(B, C, Ho, Wo)``.
    """
    old_jacrev = _grid_alone_under_a_transform(images, grid) and _grid_sample_vmap_backward_broken()
    if not old_jacrev and not _substitute(images, backward=True):
        return F.grid_sample(images, grid, mode="bilinear", padding_mode="border", align_corners=True)
    B, C, H, W = images.shape
    Ho, Wo = grid.shape[1:3]
    # As grid_sample: unnormalise (align_corners=True), clip to the border, then the four corners' weights.
    ix = _clip(((grid[..., 0] + 1) / 2 * (W - 1)).reshape(B, 1, Ho * Wo), W - 1)
    iy = _clip(((grid[..., 1] + 1) / 2 * (H - 1)).reshape(B, 1, Ho * Wo), H - 1)
    x0, y0 = torch.floor(ix), torch.floor(iy)
    x1, y1 = x0 + 1, y0 + 1
    flat = images.reshape(B, C, H * W)

    def corner(x: Tensor, y: Tensor) -> Tensor:
        # A corner past the last row or column has weight 0 (its point lies on that border): read the border. The
        # index in integers: in float32, row * W + column is exact only below 2**24 (a 16.7-megapixel frame).
        index = (y.clamp(max=H - 1).long() * W + x.clamp(max=W - 1).long()).expand(B, C, Ho * Wo)
        return torch.gather(flat, 2, index)

    out = (
        corner(x0, y0) * ((x1 - ix) * (y1 - iy))
        + corner(x1, y0) * ((ix - x0) * (y1 - iy))
        + corner(x0, y1) * ((x1 - ix) * (iy - y0))
        + corner(x1, y1) * ((ix - x0) * (iy - y0))
    )
    return out.reshape(B, C, Ho, Wo)


def reflect_pad(images: Tensor, pad: int) -> Tensor:
    """``F.pad(images, (pad,) * 4, mode="reflect")``, also where the gradient is asked for under deterministic
    algorithms on CUDA (module docstring).

    Args:
        images: ``(B, C, H, W)`` with ``H, W > pad``.
        pad: the border's width on each side.

    Returns:
        ``(B, C, H + 2 pad, W + 2 pad)``.
    """
    if not _substitute(images, backward=True):
        return F.pad(images, (pad, pad, pad, pad), mode="reflect")
    out = images
    for dim in (-2, -1):
        n = out.shape[dim]
        before = out.narrow(dim, 1, pad).flip(dim)  # rows pad .. 1, mirrored about row 0
        after = out.narrow(dim, n - 1 - pad, pad).flip(dim)  # rows n - 2 .. n - 1 - pad
        out = torch.cat([before, out, after], dim=dim)
    return out
