"""Scene backgrounds and occluders composited with the rendered face.

The background is a procedural texture larger than the frame, seen through a window that pans
slowly (sub-pixel, bilinear). The occluder is a textured ellipse drawn IN FRONT of everything,
like a hand or a card held before the face; its size is chosen per frame so that it covers a
requested fraction of the face's visible pixels.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
import torch.nn.functional as nnf
from torch import Tensor

from torchface.geometry._checks import check_int, check_number, check_reals
from torchface.synth.textures import background_texture, occluder_texture, serial

__all__ = ["BackgroundSpec", "background_frames", "OccluderSpec", "ellipse_mask", "place_occluder"]


@dataclass(frozen=True)
class BackgroundSpec:
    """A procedural backdrop panning behind the face.

    Attributes:
        seed: texture seed.
        margin: the texture is ``(1 + margin)`` times the frame size on each axis.
        pan_px_per_frame: ``(dx, dy)`` pan speed in frame pixels per frame (0 for a static scene); the
            window bounces between the texture's borders (triangle wave).
    """

    seed: int = 0
    margin: float = 0.25
    pan_px_per_frame: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "seed", _check_seed(self.seed))
        object.__setattr__(self, "margin", check_number(self.margin, "margin", "[0, 4]"))
        _set_pair(self, "pan_px_per_frame", "(-inf, inf)")  # (NaN or inf: NaN frames)


#: Texture seeds lie in ``[-SEED_LIMIT, SEED_LIMIT]``: torch's generator takes 64-bit seeds, and the textures add
#: small offsets to them (2**70 failed when rendering, "Overflow when unpacking long long").
SEED_LIMIT: int = 2**62


def _check_seed(value: object) -> int:
    seed = check_int(value, "seed")
    if abs(seed) > SEED_LIMIT:
        raise ValueError(f"seed must be an int in [-2**62, 2**62], got {seed}")
    return seed


def _set_pair(spec: object, name: str, interval: str) -> None:
    """Check ``spec``'s field ``name``, two numbers each in ``interval`` (a list or array kept as a tuple)."""
    pair = check_reals(getattr(spec, name), name, interval)
    if len(pair) != 2:
        raise ValueError(f"{name} must be two numbers (x, y), got {getattr(spec, name)!r}")
    object.__setattr__(spec, name, pair)


#: Backgrounds are generated at most this large (longest side) and upsampled: they are smooth anyway.
_MAX_GENERATED_SIDE: int = 400


@functools.lru_cache(maxsize=8)
def _cached_background(height: int, width: int, seed: int) -> Tensor:
    scale = min(1.0, _MAX_GENERATED_SIDE / max(height, width))
    if scale >= 1.0:
        return background_texture(height, width, seed=seed)
    small = background_texture(max(8, round(height * scale)), max(8, round(width * scale)), seed=seed)
    with serial():  # the same backdrop whatever the core count (torchface.synth.textures)
        return nnf.interpolate(small[None], size=(height, width), mode="bilinear", align_corners=False)[0]


@functools.lru_cache(maxsize=8)
def _cached_occluder(seed: int) -> Tensor:
    return occluder_texture(64, 64, seed=seed)


def _triangle_wave(x: Tensor, period: float) -> Tensor:
    """Goes 0 -> period -> 0 linearly with period ``2 * period``."""
    if period <= 0:
        return torch.zeros_like(x)
    m = torch.remainder(x, 2 * period)
    return torch.where(m <= period, m, 2 * period - m)


def background_frames(spec: BackgroundSpec, frame_index: Tensor, height: int, width: int) -> Tensor:
    """The background of frames ``frame_index`` (float tensor ``(B,)``), ``(B, 3, H, W)`` in ``[0, 1]``.

    Example:
        >>> background_frames(BackgroundSpec(seed=3), torch.arange(2.0), 24, 32).shape
        torch.Size([2, 3, 24, 32])
    """
    bh = int(round(height * (1 + spec.margin)))
    bw = int(round(width * (1 + spec.margin)))
    tex = _cached_background(bh, bw, spec.seed).unsqueeze(0)
    b = frame_index.shape[0]
    f = frame_index.to(torch.float32)
    ox = _triangle_wave(f * spec.pan_px_per_frame[0], float(bw - width)) if spec.pan_px_per_frame[0] else f * 0
    oy = _triangle_wave(f * spec.pan_px_per_frame[1], float(bh - height)) if spec.pan_px_per_frame[1] else f * 0
    # Start centred-left so the first frame is a deterministic window; offsets are texture pixels.
    cols = torch.arange(width, dtype=torch.float32).view(1, 1, width) + ox.view(b, 1, 1)
    rows = torch.arange(height, dtype=torch.float32).view(1, height, 1) + oy.view(b, 1, 1)
    gx = 2.0 * cols / max(bw - 1, 1) - 1.0
    gy = 2.0 * rows / max(bh - 1, 1) - 1.0
    grid = torch.stack([gx.expand(b, height, width), gy.expand(b, height, width)], dim=-1)
    return nnf.grid_sample(tex.expand(b, -1, -1, -1), grid, mode="bilinear", align_corners=True)


@dataclass(frozen=True)
class OccluderSpec:
    """An elliptical textured object passing in front of the face.

    Attributes:
        first_frame: first frame (inclusive) where the occluder is present.
        last_frame: last frame (exclusive).
        target_fraction: fraction of the face's visible pixels it covers (size adapted per frame).
        aspect: ellipse height / width.
        path_start: ``(x, y)`` start of the centre's path, in units of the face's bounding box
            (0 = left/top edge, 1 = right/bottom edge).
        path_end: end of the path (same units); the centre moves linearly between them.
        seed: texture seed.
    """

    first_frame: int
    last_frame: int
    target_fraction: float = 0.32
    aspect: float = 1.3
    path_start: tuple[float, float] = (0.15, 0.55)
    path_end: tuple[float, float] = (0.85, 0.65)
    seed: int = 5

    def __post_init__(self) -> None:
        for name in ("first_frame", "last_frame"):
            object.__setattr__(self, name, check_int(getattr(self, name), name))
        object.__setattr__(self, "seed", _check_seed(self.seed))
        if not 0 <= self.first_frame < self.last_frame:
            raise ValueError(f"need 0 <= first_frame < last_frame, got {self.first_frame}, {self.last_frame}")
        # (an aspect was not checked: 0 or inf gave NaN masks)
        for name, interval in (("target_fraction", "(0, 1)"), ("aspect", "(0, inf)")):
            object.__setattr__(self, name, check_number(getattr(self, name), name, interval))
        for name in ("path_start", "path_end"):
            _set_pair(self, name, "(-inf, inf)")

    def active(self, frame_index: Tensor) -> Tensor:
        """``(B,)`` bool: is the occluder present in these frames."""
        return (frame_index >= self.first_frame) & (frame_index < self.last_frame)


def ellipse_mask(centre: Tensor, radius_x: Tensor, aspect: float, height: int, width: int, soft: float = 0.75) -> Tensor:
    """Anti-aliased ellipse masks ``(B, 1, H, W)`` for centres ``(B, 2)`` px and x radii ``(B,)`` px."""
    b = centre.shape[0]
    cols = torch.arange(width, dtype=centre.dtype).view(1, 1, width)
    rows = torch.arange(height, dtype=centre.dtype).view(1, height, 1)
    rx = radius_x.view(b, 1, 1).clamp(min=1e-3)
    ry = rx * aspect
    dx = (cols - centre[:, 0].view(b, 1, 1)) / rx
    dy = (rows - centre[:, 1].view(b, 1, 1)) / ry
    # Signed distance approximated in pixels along x.
    d = (torch.sqrt(dx**2 + dy**2) - 1.0) * rx
    return torch.sigmoid(-d / soft).unsqueeze(1)


def place_occluder(
    spec: OccluderSpec, frame_index: Tensor, face_mask: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Occluder layer for a batch of frames, sized to cover ``spec.target_fraction`` of the face.

    Args:
        spec: the occluder.
        frame_index: ``(B,)`` frame numbers.
        face_mask: ``(B, 1, H, W)`` visible-face mask of the rendered frames.

    Returns:
        ``alpha (B, 1, H, W)`` coverage in ``[0, 1]`` (0 on frames without the occluder),
        ``colour (B, 3, H, W)`` the occluder's texture, and ``fraction (B,)`` the fraction of
        face pixels it covers (hard-thresholded alpha > 0.5 against mask > 0.5).
    """
    b, _, h, w = face_mask.shape
    dtype = face_mask.dtype
    on = spec.active(frame_index)
    face = face_mask[:, 0] > 0.5
    rows = torch.arange(h, dtype=dtype).view(1, h, 1)
    cols = torch.arange(w, dtype=dtype).view(1, 1, w)
    big = torch.tensor(float(max(h, w)), dtype=dtype)
    has = face.flatten(1).any(dim=1)
    x_min = torch.where(face, cols.expand(b, h, w), big).flatten(1).amin(1)
    x_max = torch.where(face, cols.expand(b, h, w), -big).flatten(1).amax(1)
    y_min = torch.where(face, rows.expand(b, h, w), big).flatten(1).amin(1)
    y_max = torch.where(face, rows.expand(b, h, w), -big).flatten(1).amax(1)
    span = max(spec.last_frame - spec.first_frame - 1, 1)
    s = ((frame_index.to(dtype) - spec.first_frame) / span).clamp(0.0, 1.0)
    px = spec.path_start[0] + (spec.path_end[0] - spec.path_start[0]) * s
    py = spec.path_start[1] + (spec.path_end[1] - spec.path_start[1]) * s
    centre = torch.stack([x_min + px * (x_max - x_min), y_min + py * (y_max - y_min)], dim=-1)
    face_area = face.flatten(1).sum(1).to(dtype).clamp(min=1.0)
    # The ellipse of x radius r covers exactly the pixels with elliptical radius rho <= r, so the
    # radius that covers a fraction q of the face is the q-quantile of rho over the face pixels.
    dx = cols - centre[:, 0].view(b, 1, 1)
    dy = (rows - centre[:, 1].view(b, 1, 1)) / spec.aspect
    rho = torch.sqrt(dx**2 + dy**2)
    rho = torch.where(face, rho, torch.full_like(rho, float("inf"))).flatten(1)
    k = (spec.target_fraction * face_area).ceil().long().clamp(min=1) - 1
    rho_sorted = rho.sort(dim=1).values
    radius = rho_sorted.gather(1, k.unsqueeze(1)).squeeze(1)
    radius = torch.where(torch.isfinite(radius), radius, torch.ones_like(radius)) + 1e-3
    alpha = ellipse_mask(centre, radius, spec.aspect, h, w)
    active = (on & has).to(dtype).view(b, 1, 1, 1)
    alpha = alpha * active
    fraction = ((alpha[:, 0] > 0.5) & face).flatten(1).sum(1).to(dtype) / face_area * active.view(b)
    # Texture attached to the object: sample a fixed texture in the ellipse's own frame.
    tex = _cached_occluder(spec.seed).to(dtype).unsqueeze(0).expand(b, -1, -1, -1)
    gx = (cols - centre[:, 0].view(b, 1, 1)) / radius.view(b, 1, 1).clamp(min=1.0)
    gy = (rows - centre[:, 1].view(b, 1, 1)) / (radius.view(b, 1, 1) * spec.aspect).clamp(min=1.0)
    grid = torch.stack([gx.expand(b, h, w), gy.expand(b, h, w)], dim=-1)
    colour = nnf.grid_sample(tex, grid, mode="bilinear", padding_mode="border", align_corners=True)
    # Mild shading toward the rim so the object reads as a rounded solid.
    rim = (1.0 - 0.35 * (gx**2 + gy**2).clamp(max=1.0)).unsqueeze(1)
    return alpha, colour * rim, fraction
