"""Bilinear sampling of images at pixel coordinates (pixel centres at integers, see torchface.conventions)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from torchface._deterministic import grid_sample_border, reflect_pad
from torchface.geometry._checks import check_int, check_tensor


#: ITU-R BT.601 luma weights of R, G and B (kornia's ``rgb_to_grayscale`` defaults).
_BT601: tuple[float, float, float] = (0.299, 0.587, 0.114)


def to_gray(images: Tensor, out: Tensor | None = None) -> Tensor:
    """Luminance of RGB images.

    Args:
        images: ``(B, 3, H, W)`` RGB or ``(B, 1, H, W)`` gray, float in ``[0, 1]``.
        out: optional ``(B, 1, H, W)`` tensor of ``images``' dtype (float RGB input only) to write the result into.

    Returns:
        ``(B, 1, H, W)`` gray images (ITU-R BT.601 weights, as ``kornia.color.rgb_to_grayscale``).
    """
    if not isinstance(images, Tensor):  # (a numpy array: "'numpy.ndarray' object has no attribute 'dim'")
        raise TypeError(f"images must be a torch.Tensor (B, 1 or 3, H, W), got {type(images).__name__}")
    if images.dim() != 4 or images.shape[1] not in (1, 3):
        raise ValueError(f"images must be (B, 1 or 3, H, W), got {tuple(images.shape)}")
    if out is not None and (images.shape[1] != 3 or not images.is_floating_point()):
        raise ValueError("out= needs float RGB images")
    want = (images.shape[0], 1, *images.shape[2:])
    if out is not None and (tuple(out.shape) != want or out.dtype != images.dtype or out.device != images.device):
        # (an IndexError "too many indices for tensor of dimension 1", or a broadcast into the wrong shape)
        raise ValueError(f"out must be {want} {images.dtype} on {images.device}, "
                         f"got {tuple(out.shape)} {out.dtype} on {out.device}")  # fmt: skip
    if images.shape[1] == 1:
        return images
    if not images.is_floating_point():
        import kornia  # (here only: its import took 0.23 s of every run of the tracker, which never comes here)

        return kornia.color.rgb_to_grayscale(images)
    # kornia's arithmetic (r * w_r, then addcmul of g and b by 0-dim weights of the image's dtype), so the values are
    # kornia's bit for bit, accumulated in place into one new tensor: per 640x480 frame, 2 threads, 0.08 against
    # 1.0 ms at B = 1 and 0.56 against 1.33 ms at B = 32.
    r, g, b = images.unbind(dim=1)
    w_r, w_g, w_b = (torch.full((), w, dtype=images.dtype, device=images.device) for w in _BT601)
    gray = torch.mul(r, w_r, out=None if out is None else out[:, 0])
    gray.addcmul_(g, w_g).addcmul_(b, w_b)
    return gray.unsqueeze(1) if out is None else out


def pixels_to_grid(points_px: Tensor, height: int, width: int) -> Tensor:
    """Map pixel coordinates ``(u, v)`` to ``grid_sample``'s normalised coordinates (``align_corners=True``).

    Args:
        points_px: ``(B, N, 2)`` (or any ``(..., 2)``) float pixel coordinates (column, row).
        height, width: the image's size in pixels, ints ``>= 1``.

    Returns:
        ``(B, N, 2)`` coordinates in ``[-1, 1]`` for points inside the image.

    Raises:
        TypeError: ``points_px`` is not a floating-point tensor, or a size is not an int.
        ValueError: ``points_px`` does not end in 2 coordinates, or a size is below 1.
    """
    check_tensor(points_px, "points_px", (2,))
    height, width = check_int(height, "height", 1), check_int(width, "width", 1)
    return _pixels_to_grid(points_px, height, width)


def _pixels_to_grid(points_px: Tensor, height: int, width: int) -> Tensor:
    """:func:`pixels_to_grid` without its checks (:func:`sample_at_pixels`' size is its images')."""
    scale = points_px.new_tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)])
    return points_px * scale - 1.0


def sample_at_pixels(images: Tensor, points_px: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinearly sample images at pixel coordinates.

    Args:
        images: ``(B, C, H, W)``.
        points_px: ``(B, N, 2)`` pixel coordinates ``(u, v)``.

    Returns:
        ``values (B, N, C)`` (border values outside the image) and ``inside (B, N)`` bool, True where the
        point lies within ``[0, W - 1] x [0, H - 1]`` (where all four bilinear neighbours exist). A non-finite
        point (NaN or inf coordinate) is not inside; it is sampled at pixel ``(0, 0)`` instead, so its values
        and every gradient stay finite (its own gradient is 0).

    Differentiable with respect to ``images`` and ``points_px``.
    """
    for name, x in (("images", images), ("points_px", points_px)):
        if not isinstance(x, Tensor) or not x.is_floating_point():  # (a numpy array: "no attribute 'dim'"; uint8
            # images: grid_sample's "not implemented for 'Byte'")
            got = f"dtype {x.dtype}" if isinstance(x, Tensor) else type(x).__name__
            hint = " (uint8 frames: images.float() / 255)" if isinstance(x, Tensor) and x.dtype == torch.uint8 else ""
            raise TypeError(f"{name} must be a floating-point torch.Tensor, got {got}{hint}")
    if images.dim() != 4:
        raise ValueError(f"images must be (B, C, H, W), got {tuple(images.shape)}")
    if points_px.dim() != 3 or points_px.shape[-1] != 2 or points_px.shape[0] != images.shape[0]:
        raise ValueError(f"points_px must be (B, N, 2) with B={images.shape[0]}, got {tuple(points_px.shape)}")
    h, w = images.shape[-2:]
    finite = torch.isfinite(points_px).all(-1, keepdim=True)  # (B, N, 1)
    # grid_sample's CPU backward with border padding crashes the process on a NaN grid point (PyTorch bug):
    # non-finite points go to pixel (0, 0), a torch.where so that their gradient is 0, not NaN.
    points_px = torch.where(finite, points_px, 0.0)
    grid = _pixels_to_grid(points_px, h, w).unsqueeze(1)  # (B, 1, N, 2)
    values = grid_sample_border(images, grid.to(images.dtype))
    u, v = points_px[..., 0], points_px[..., 1]
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1) & finite.squeeze(-1)
    return values.squeeze(2).transpose(1, 2), inside


def image_with_gradients(gray: Tensor) -> Tensor:
    """Stack a gray image with its spatial derivatives for one-call sampling in Lucas-Kanade.

    Args:
        gray: ``(B, 1, H, W)``.

    Returns:
        ``(B, 3, H, W)``: intensity, d/du and d/dv (central differences, per pixel, replicate border), so that
        sampling at a point gives ``I`` and ``grad I`` there.
    """
    # Central differences with replicated borders (kornia's "diff" spatial gradient halved), by slicing
    # straight into the output: several times faster than a convolution on the CPU.
    if not isinstance(gray, Tensor):
        raise TypeError(f"gray must be a torch.Tensor (B, 1, H, W), got {type(gray).__name__}")
    if gray.dim() != 4 or gray.shape[1] != 1 or gray.shape[-1] < 2 or gray.shape[-2] < 2:
        raise ValueError(f"gray must be (B, 1, H, W) with H, W >= 2, got {tuple(gray.shape)}")
    if not gray.is_floating_point():  # (uint8, as to_gray gives of uint8 RGB: "result type Float can't be cast to
        # the desired output type Byte" from the halving)
        raise TypeError(f"gray must be a floating-point tensor, got dtype {gray.dtype} (uint8 images: .float() / 255)")
    if gray.requires_grad:  # the differentiable path: plain out-of-place ops
        p = F.pad(gray, (1, 1, 1, 1), mode="replicate")
        gu = 0.5 * (p[:, :, 1:-1, 2:] - p[:, :, 1:-1, :-2])
        gv = 0.5 * (p[:, :, 2:, 1:-1] - p[:, :, :-2, 1:-1])
        return torch.cat([gray, gu, gv], dim=1)
    g = gray[:, 0]
    out = torch.empty((gray.shape[0], 3, *g.shape[-2:]), dtype=gray.dtype, device=gray.device)
    out[:, 0] = g
    torch.sub(g[:, :, 2:], g[:, :, :-2], out=out[:, 1, :, 1:-1])
    torch.sub(g[:, :, 1:2], g[:, :, 0:1], out=out[:, 1, :, 0:1])
    torch.sub(g[:, :, -1:], g[:, :, -2:-1], out=out[:, 1, :, -1:])
    torch.sub(g[:, 2:], g[:, :-2], out=out[:, 2, 1:-1])
    torch.sub(g[:, 1:2], g[:, 0:1], out=out[:, 2, 0:1])
    torch.sub(g[:, -1:], g[:, -2:-1], out=out[:, 2, -1:])
    out[:, 1:].mul_(0.5)
    return out


#: Binomial 5-tap Gaussian ``[1, 4, 6, 4, 1] / 16`` convolved with the 2-tap box ``[1, 1] / 2`` of the 2x
#: decimation: one pyramid step is this 6-tap filter applied at stride 2 along each axis.
_PYR_TAPS: tuple[float, ...] = (1 / 32, 5 / 32, 10 / 32, 10 / 32, 5 / 32, 1 / 32)


def pyr_down(images: Tensor, out: Tensor | None = None) -> Tensor:
    """One Gaussian-pyramid step: blur with ``[1, 4, 6, 4, 1] / 16`` (reflect border), halve by 2x2 averaging.

    Equal to ``kornia.geometry.transform.pyrdown`` (Gaussian blur, then bilinear resize by 1/2 with
    ``align_corners=False``) for even sizes, to float rounding, computed with strided slices instead of a
    convolution, which is several times faster on the CPU for single-channel images. Output pixel ``j`` is
    centred on input coordinate ``2 j + 0.5``, the pixel-centre convention of :mod:`torchface.conventions`; odd
    sizes drop the last row/column.

    The rows are filtered first (the taps then read whole contiguous rows), and each pass accumulates its six taps
    in place into one output: a sum of products made twelve temporaries per pass, and on large batches their
    fresh memory cost more than the arithmetic (B = 128, 480x520: 333 -> 51 ms; B = 1: 0.55 -> 0.32 ms).
    Differentiable.

    Args:
        images: ``(B, C, H, W)`` with ``H, W >= 3``.
        out: optional ``(B, C, H // 2, W // 2)`` tensor of ``images``' dtype and device to write the result into
            (not differentiable, like every ``out=``).

    Returns:
        ``(B, C, H // 2, W // 2)`` (``out`` when given).
    """
    if not isinstance(images, Tensor):
        raise TypeError(f"images must be a torch.Tensor (B, C, H, W), got {type(images).__name__}")
    if images.dim() != 4 or images.shape[-1] < 3 or images.shape[-2] < 3:
        raise ValueError(f"images must be (B, C, H, W) with H, W >= 3, got {tuple(images.shape)}")
    h2, w2 = images.shape[-2] // 2, images.shape[-1] // 2
    if out is not None and (
        out.shape != (*images.shape[:2], h2, w2) or out.dtype != images.dtype or out.device != images.device
    ):
        raise ValueError(
            f"out must be {(*images.shape[:2], h2, w2)} {images.dtype} on {images.device}, "
            f"got {tuple(out.shape)} {out.dtype} on {out.device}"
        )
    p = reflect_pad(images, 2)
    rows = torch.mul(p[..., 0 : 2 * h2 : 2, :], _PYR_TAPS[0])
    for k in range(1, len(_PYR_TAPS)):
        rows.add_(p[..., k : k + 2 * h2 : 2, :], alpha=_PYR_TAPS[k])
    out = torch.mul(rows[..., 0 : 2 * w2 : 2], _PYR_TAPS[0], out=out)
    for k in range(1, len(_PYR_TAPS)):
        out.add_(rows[..., k : k + 2 * w2 : 2], alpha=_PYR_TAPS[k])
    return out
