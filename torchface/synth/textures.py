"""Deterministic procedural textures for synthetic scenes (backgrounds, occluders).

Every function is a pure function of its arguments: randomness comes from a ``torch.Generator``
seeded by the caller, on the CPU, so the same seed gives the same image on every machine. The resampling
runs on one thread (:func:`serial`): PyTorch's CPU upsampling kernels round differently with other thread
counts (a 300x400 -> 600x800 bilinear upsampling changed half its values by one unit in the last place
between 1 and 2 threads), and a scene rendered on a 2-core and on an 8-core machine must be the same.
Images are ``(3, H, W)`` float RGB in ``[0, 1]`` (see :mod:`torchface.conventions`).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

import torch
import torch.nn.functional as nnf
from torch import Tensor

__all__ = ["smooth_noise", "background_texture", "occluder_texture", "serial"]


@contextlib.contextmanager
def serial() -> Iterator[None]:
    """Run the enclosed CPU operations on one thread (PyTorch's intra-op thread count is restored after),
    so that their rounding does not depend on the machine's core count (module docstring). The setting is the
    process's: torch work in other Python threads also runs on one thread meanwhile."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _check_size(height: int, width: int) -> None:
    if int(height) <= 0 or int(width) <= 0:
        raise ValueError(f"texture size must be positive, got {height}x{width}")


def smooth_noise(
    height: int, width: int, channels: int, seed: int, cell: float = 32.0, octaves: int = 4
) -> Tensor:
    """Fractal value noise: random lattices upsampled bicubically and summed over octaves.

    Args:
        height: ``H``.
        width: ``W``.
        channels: ``C``.
        seed: generator seed.
        cell: lattice spacing of the coarsest octave in pixels.
        octaves: number of octaves; octave ``k`` has spacing ``cell / 2**k`` and weight ``2**-k``.

    Returns:
        ``(C, H, W)`` noise normalised to ``[0, 1]`` per channel.

    Example:
        >>> smooth_noise(8, 12, 3, seed=0).shape
        torch.Size([3, 8, 12])
    """
    _check_size(height, width)
    if cell <= 0 or octaves < 1:
        raise ValueError(f"cell must be > 0 and octaves >= 1, got cell={cell}, octaves={octaves}")
    gen = torch.Generator().manual_seed(int(seed))
    total = torch.zeros(1, channels, height, width)
    for k in range(octaves):
        spacing = max(cell / 2**k, 1.0)
        gh = max(2, int(math.ceil(height / spacing)) + 2)
        gw = max(2, int(math.ceil(width / spacing)) + 2)
        lattice = torch.rand(1, channels, gh, gw, generator=gen)
        with serial():
            up = nnf.interpolate(lattice, size=(height, width), mode="bicubic", align_corners=True)
        total = total + up * 0.5**k
    lo = total.amin(dim=(2, 3), keepdim=True)
    hi = total.amax(dim=(2, 3), keepdim=True)
    return ((total - lo) / (hi - lo).clamp(min=1e-6))[0]


def background_texture(height: int, width: int, seed: int = 0) -> Tensor:
    """A busy but smooth scene backdrop: colour gradient, fractal noise, discs, bars and stripes.

    The mix gives image gradients everywhere (so a tracker cannot latch onto a flat background)
    without resembling skin.

    Args:
        height: ``H``.
        width: ``W``.
        seed: generator seed (shapes, colours and noise all derive from it).

    Returns:
        ``(3, H, W)`` RGB in ``[0, 1]``.

    Example:
        >>> background_texture(48, 64, seed=1).shape
        torch.Size([3, 48, 64])
    """
    _check_size(height, width)
    gen = torch.Generator().manual_seed(int(seed) + 7919)
    ys = torch.linspace(0.0, 1.0, height).view(height, 1).expand(height, width)
    xs = torch.linspace(0.0, 1.0, width).view(1, width).expand(height, width)
    c0, c1 = torch.rand(3, generator=gen) * 0.6 + 0.2, torch.rand(3, generator=gen) * 0.6 + 0.2
    t = (0.6 * xs + 0.4 * ys).unsqueeze(0)
    img = c0.view(3, 1, 1) * (1 - t) + c1.view(3, 1, 1) * t
    scale = float(max(height, width))
    noise = smooth_noise(height, width, 3, seed=int(seed) + 1, cell=scale / 6.0, octaves=5)
    img = 0.55 * img + 0.45 * noise
    n_shapes = 14
    centres = torch.rand(n_shapes, 2, generator=gen)
    radii = torch.rand(n_shapes, generator=gen) * 0.12 + 0.04
    colours = torch.rand(n_shapes, 3, generator=gen)
    kinds = torch.randint(0, 3, (n_shapes,), generator=gen)
    aspect = width / height
    for i in range(n_shapes):
        dx = (xs - centres[i, 0]) * aspect
        dy = ys - centres[i, 1]
        r = float(radii[i])
        if int(kinds[i]) == 0:  # soft-edged disc
            d = torch.sqrt(dx**2 + dy**2)
            alpha = torch.sigmoid((r - d) * scale / 3.0)
        elif int(kinds[i]) == 1:  # bar
            alpha = torch.sigmoid((r - dx.abs()) * scale / 3.0) * torch.sigmoid((2.5 * r - dy.abs()) * scale / 3.0)
        else:  # striped square
            inside = torch.sigmoid((r - dx.abs()) * scale / 3.0) * torch.sigmoid((r - dy.abs()) * scale / 3.0)
            stripes = 0.5 + 0.5 * torch.sin((dx + dy) * 2 * math.pi / (0.35 * r))
            alpha = inside * (0.35 + 0.65 * stripes)
        img = img * (1 - 0.8 * alpha) + colours[i].view(3, 1, 1) * (0.8 * alpha)
    return img.clamp(0.0, 1.0)


def occluder_texture(height: int, width: int, seed: int = 0) -> Tensor:
    """Texture of a hand-held occluding object: saturated stripes over noise (clearly not skin).

    Args:
        height: ``H``.
        width: ``W``.
        seed: generator seed.

    Returns:
        ``(3, H, W)`` RGB in ``[0, 1]``.

    Example:
        >>> occluder_texture(32, 32).shape
        torch.Size([3, 32, 32])
    """
    _check_size(height, width)
    gen = torch.Generator().manual_seed(int(seed) + 104729)
    ys = torch.linspace(0.0, 1.0, height).view(height, 1).expand(height, width)
    xs = torch.linspace(0.0, 1.0, width).view(1, width).expand(height, width)
    a = torch.tensor([0.10, 0.35, 0.75]) + 0.1 * torch.rand(3, generator=gen)
    b = torch.tensor([0.95, 0.80, 0.15]) - 0.1 * torch.rand(3, generator=gen)
    stripes = (0.5 + 0.5 * torch.sin((xs * 0.8 + ys) * 2 * math.pi * 5.0)).unsqueeze(0)
    img = a.view(3, 1, 1) * (1 - stripes) + b.view(3, 1, 1) * stripes
    noise = smooth_noise(height, width, 3, seed=int(seed) + 2, cell=max(height, width) / 4.0, octaves=3)
    return (0.8 * img + 0.2 * noise).clamp(0.0, 1.0)
