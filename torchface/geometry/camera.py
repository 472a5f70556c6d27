"""Pinhole camera intrinsics and perspective projection (see :mod:`torchface.conventions`)."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics shared by every sample of a batch.

    Attributes:
        width: image width W in pixels.
        height: image height H in pixels.
        fx: focal length along x in pixels.
        fy: focal length along y in pixels.
        cx: principal point column (pixel centres are integers, so the centre is ``(W - 1) / 2``).
        cy: principal point row.

    Example:
        >>> cam = Intrinsics.default(640, 480)
        >>> cam.fx, cam.cx
        (640.0, 319.5)
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, torch.Tensor) and value.numel() == 1 and not value.is_floating_point():
                value = int(value)  # a 0-d integer tensor
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                if isinstance(value, bool) or not (isinstance(value, numbers.Real) and float(value).is_integer()):
                    raise TypeError(f"{name} must be a whole number of pixels, got {value!r}")
            object.__setattr__(self, name, int(value))  # 32.0 -> 32, numpy integers -> int: sizes index tensors
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if isinstance(value, torch.Tensor):  # a 0-d tensor is kept as it is (a focal length may carry a gradient)
                if value.numel() != 1 or not value.is_floating_point():
                    raise TypeError(f"{name} must be a number or a one-element float tensor, got {value!r}")
                finite = bool(torch.isfinite(value.detach()).all())
            elif isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise TypeError(f"{name} must be a number, got {value!r}")
            else:
                finite = math.isfinite(value)
                object.__setattr__(self, name, float(value))
            if not finite:
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def default(cls, width: int, height: int, focal: float | None = None) -> "Intrinsics":
        """Intrinsics for a ``width x height`` image: ``f = max(W, H)`` unless given, centred.

        Raises:
            TypeError, ValueError: as the constructor, for a size that is not whole positive pixels (``int()`` took
                320.5 as 320 with the centre of 320.5, and ``"320"`` failed in ``max``) or a focal length that is
                not a positive finite number.
        """
        size = cls(width, height, 1.0, 1.0, 0.0, 0.0)  # the constructor's checks of the size
        w, h = size.width, size.height
        if focal is not None and (isinstance(focal, bool) or not isinstance(focal, (numbers.Real, torch.Tensor))):
            raise TypeError(f"focal must be a number or None, got {focal!r}")
        f = float(max(w, h)) if focal is None else float(focal)
        return cls(w, h, f, f, (w - 1) / 2.0, (h - 1) / 2.0)

    @property
    def size(self) -> tuple[int, int]:
        """``(H, W)``."""
        return (self.height, self.width)

    def matrix(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> torch.Tensor:
        """The 3x3 calibration matrix ``K`` (differentiable in the entries that are tensors)."""
        entries = (self.fx, self.cx, self.fy, self.cy)
        if any(isinstance(v, torch.Tensor) for v in entries):  # torch.tensor() would copy them without their graph
            fx, cx, fy, cy = (torch.as_tensor(v, dtype=dtype, device=device).reshape(()) for v in entries)
            zero, one = fx.new_zeros(()), fx.new_ones(())
            return torch.stack([fx, zero, cx, zero, fy, cy, zero, zero, one]).reshape(3, 3)
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=dtype, device=device
        )

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics of the image resized by ``factor`` (pixel-centre convention preserved).

        Raises:
            ValueError: ``factor`` not a positive finite number (a negative one gave a 1x1 camera).
        """
        if isinstance(factor, bool) or not 0 < float(factor) < math.inf:
            raise ValueError(f"factor must be a positive finite number, got {factor!r}")
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        sx, sy = w / self.width, h / self.height
        return Intrinsics(w, h, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5)
