"""Pinhole camera intrinsics and perspective projection (see :mod:`torchface.conventions`)."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import torch

from torchface._device import check_device


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
                    raise TypeError(f"{name} must be a whole number of pixels, got {value!r} (Intrinsics takes "
                                    "width, height, fx, fy, cx, cy in this order; from a 3x3 calibration matrix: "
                                    "Intrinsics.from_matrix(K, width, height))")
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

    @classmethod
    def from_matrix(cls, matrix: object, width: int, height: int) -> "Intrinsics":
        """Intrinsics of a ``width x height`` frame from its 3x3 calibration matrix
        ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (OpenCV's ``cameraMatrix``, row by row), given as a tensor, a
        NumPy array or nested lists. The constructor takes ``fx, fy, cx, cy``, not the matrix's order
        ``fx, cx, fy, cy``: read from here, the entries cannot be mixed up. Entries of a tensor that requires grad
        are kept as 0-d tensors (differentiable), as the constructor keeps them.

        Raises:
            TypeError, ValueError: not a 3x3 matrix of real numbers (a 3x4 projection matrix ``K [R | t]`` is
                told so), entries not finite, a last row other than ``(0, 0, 1)`` (a transposed matrix, its last
                row ``(cx, cy, 1)``, is told to pass ``K.T``; a matrix scaled by ``K[2, 2]`` to divide by it), a skew
                ``K[0, 1]`` or a ``K[1, 0]`` that is not 0 (the tracker's pinhole camera has none), a size or focal
                lengths the constructor refuses.

        Example:
            >>> K = [[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]]
            >>> cam = Intrinsics.from_matrix(K, 640, 480)
            >>> (cam.fx, cam.fy, cam.cx, cam.cy)
            (600.0, 600.0, 320.0, 240.0)
        """
        grad = isinstance(matrix, torch.Tensor) and matrix.requires_grad
        if isinstance(matrix, torch.Tensor):
            if matrix.dtype == torch.bool or matrix.is_complex():
                raise TypeError(f"matrix must hold real numbers, got {matrix.dtype}")
            K = matrix if grad else matrix.detach().to("cpu", torch.float64)
        else:
            if isinstance(matrix, np.ndarray) and (matrix.dtype == np.bool_ or np.iscomplexobj(matrix)):
                raise TypeError(f"matrix must hold real numbers, got {matrix.dtype}")
            try:
                K = torch.as_tensor(matrix, dtype=torch.float64)
            except (TypeError, ValueError, RuntimeError):
                raise TypeError(f"matrix must be a 3x3 calibration matrix (a tensor, an array or nested lists), "
                                f"got {type(matrix).__name__}") from None  # fmt: skip
        if tuple(K.shape) != (3, 3):
            hint = (" (a 3x4 projection matrix K [R | t]? Its left 3x3 block is K R, not K: decompose it, e.g. "
                    "cv2.decomposeProjectionMatrix)" if tuple(K.shape) == (3, 4) else "")  # fmt: skip
            if K.dim() == 3 and tuple(K.shape[1:]) == (3, 3):  # (a batch's: one Intrinsics is one camera)
                hint = (" (a batch of matrices? An Intrinsics is one camera, which the tracker's whole batch shares: "
                        "from_matrix(K[b], ...) for a stream's)")  # fmt: skip
            raise ValueError(f"matrix must be 3x3, got shape {tuple(K.shape)}{hint}")
        v = K.detach().to("cpu", torch.float64)
        if not bool(torch.isfinite(v).all()):
            raise ValueError(f"matrix must be finite, got {v.tolist()}")
        last = v[2].tolist()
        if abs(last[0]) <= 1e-9 and abs(last[1]) <= 1e-9 and abs(last[2] - 1.0) <= 1e-6:  # (float rounding: K from
            last = [0.0, 0.0, 1.0]  # float32 arithmetic, K[2, 2] = 0.99999994, is the calibration it rounds)
        if last[:2] != [0.0, 0.0] or last[2] != 1.0:
            if last[2] == 1.0 and v[0, 2] == 0 and v[1, 2] == 0 and v[1, 0] == 0 and v[0, 1] == 0:
                hint = (f": the transpose of a calibration matrix (cx, cy = {last[0]:g}, {last[1]:g} in its last "
                        "row)? Pass K.T")
            elif last[:2] == [0.0, 0.0] and last[2] != 0:
                hint = f": a matrix scaled by {last[2]:g}? Pass K / K[2, 2]"
            else:
                hint = ""
            raise ValueError(f"matrix's last row must be (0, 0, 1), got ({last[0]:g}, {last[1]:g}, {last[2]:g}){hint}")
        if abs(float(v[0, 1])) > 1e-6 * abs(float(v[0, 0])) or abs(float(v[1, 0])) > 1e-6 * abs(float(v[1, 1])):
            raise ValueError(f"matrix must have no skew (K[0, 1] = K[1, 0] = 0: the tracker's pinhole camera has "
                             f"square axes), got K[0, 1] = {float(v[0, 1]):g}, K[1, 0] = {float(v[1, 0]):g}")
        if grad:  # 0-d tensors, which the constructor keeps (its fields are typed as the numbers they usually are)
            fx, fy, cx, cy = cast("tuple[float, float, float, float]", (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
            return cls(width, height, fx, fy, cx, cy)
        return cls(width, height, float(v[0, 0]), float(v[1, 1]), float(v[0, 2]), float(v[1, 2]))

    @property
    def size(self) -> tuple[int, int]:
        """``(H, W)``."""
        return (self.height, self.width)

    def matrix(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> torch.Tensor:
        """The 3x3 calibration matrix ``K`` (differentiable in the entries that are tensors).

        Raises:
            ValueError: ``device`` is not a device this machine has (``check_device``'s rule: torch's "Invalid
                device string" for a misspelt one, a matrix without values for ``"meta"``).
        """
        device = check_device(device)
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


#: The most ``fx`` may exceed ``fy`` (their ratio) before :func:`mixed_up_intrinsics` looks for a mix-up: pixels
#: taller than wide are rare (NTSC 4:3 DV's, 10/11 wide: 1.1), and OpenCV's order read as the constructor's puts
#: ``cx`` as ``fy``, under ``fx`` but for a field of view over 90 degrees.
PLAUSIBLE_ASPECT: float = 1.25
#: The most ``fy`` may exceed ``fx``: pixels wider than tall, as anamorphic video stores them (HDV's 1440x1080
#: frames shown 16:9: 4/3; PAL 16:9 DV's 64/45: 1.42; a 2x anamorphic lens: 2), were told "implausible" at 1.25.
PLAUSIBLE_WIDE_PIXELS: float = 2.0


#: The farthest the frame's centre may lie from the principal point, in focal lengths along x or y (63 degrees off
#: the optical axis), before :func:`mixed_up_intrinsics` calls a camera implausible. A principal point outside the
#: frame alone is not: a crop of a larger frame keeps that frame's principal point, off the crop (many crop widths
#: off for a small crop of a telephoto frame); a pinhole camera that sees the crop's centre 63 degrees off its axis
#: is none real. (Every principal point outside the frame was "implausible" until session 60.)
PLAUSIBLE_OFF_AXIS: float = 2.0


def _fits(w: int, h: int, fx: float, fy: float, cx: float, cy: float, tight: bool) -> bool:
    """Whether ``fx, fy, cx, cy`` are a plausible camera of a ``w x h`` frame: ``fx / fy`` at most
    :data:`PLAUSIBLE_ASPECT` and ``fy / fx`` at most :data:`PLAUSIBLE_WIDE_PIXELS`, both at least 5 % of the
    frame's larger side (a field of view under 175 degrees), the principal point inside the frame; ``tight``: as a
    frame's camera nearly always is, focal lengths within 10 % of each other and at least 5 % of the frame's larger
    side, the principal point within 15 % of the frame's size from its centre."""
    if tight:
        return max(fx, fy) / min(fx, fy) <= 1.1 and min(fx, fy) >= 0.05 * max(w, h) \
            and abs(cx - (w - 1) / 2) <= 0.15 * w and abs(cy - (h - 1) / 2) <= 0.15 * h
    return _focal_lengths_fit(w, h, fx, fy) and -0.5 <= cx <= w - 0.5 and -0.5 <= cy <= h - 0.5


def _focal_lengths_fit(w: int, h: int, fx: float, fy: float) -> bool:
    """:func:`_fits`' loose test of the focal lengths alone."""
    return fx / fy <= PLAUSIBLE_ASPECT and fy / fx <= PLAUSIBLE_WIDE_PIXELS and min(fx, fy) >= 0.05 * max(w, h)


def _crop_fits(w: int, h: int, fx: float, fy: float, cx: float, cy: float) -> bool:
    """Whether ``fx, fy, cx, cy`` are a plausible camera of a ``w x h`` crop of a larger frame: focal lengths as
    :func:`_fits` takes them, the frame's centre at most :data:`PLAUSIBLE_OFF_AXIS` focal lengths from the principal
    point along each axis (wherever the principal point lies)."""
    return _focal_lengths_fit(w, h, fx, fy) and abs(cx - (w - 1) / 2) <= PLAUSIBLE_OFF_AXIS * fx \
        and abs(cy - (h - 1) / 2) <= PLAUSIBLE_OFF_AXIS * fy


def _unscaled_hint(w: int, h: int, fx: float, fy: float, cx: float, cy: float, given: str) -> str | None:
    """:func:`mixed_up_intrinsics`' hint where ``fx, fy, cx, cy`` look like the camera of a frame at least twice
    as large, not scaled with these ``w x h`` frames: the principal point that frame's centre (the same scale along x
    and y, to 3 %; at twice the size exactly, a centred camera's, it is the edge of this frame's bottom-right pixel,
    inside the frame) and that frame's camera scaled to these frames a plausible one; None otherwise."""
    scale, scale_y = (2 * cx + 1) / w, (2 * cy + 1) / h
    if not (scale >= 2 and abs(scale_y / scale - 1) <= 0.03):  # (scale is 0 where cx = -0.5: tested first)
        return None
    a, b, d = fx / scale, fy / scale, (cy + 0.5) / scale - 0.5  # (that frame's camera scaled to these frames)
    if not (min(a, b) > 0 and _fits(w, h, a, b, (w - 1) / 2, d, tight=True)):  # (a subnormal focal length: 0 here)
        return None
    return (f"intrinsics {given} look like the camera of a {w * scale:.0f}x{h * scale:.0f} frame (its centre the "
            f"principal point), not scaled with these frames? Likely meant: Intrinsics({w}, {h}, fx={a:.6g}, "
            f"fy={b:.6g}, cx={(w - 1) / 2:g}, cy={d:.6g}), intrinsics.scaled({1 / scale:.6g}); the camera of a "
            "crop of a larger frame (its principal point) is right as given")


#: Frame sizes ``(W, H)`` of video and photo cameras (landscape; portrait ones are these transposed) whose centred
#: camera, given unchanged for frames of another shape (a 1920x1080 calibration, or ``Intrinsics.default(1920,
#: 1080)``, for 640x480 frames), :func:`mixed_up_intrinsics` recognises by its principal point: exactly that frame's
#: centre, ``((W - 1) / 2, (H - 1) / 2)`` or ``(W / 2, H / 2)``. A list, not any larger frame's centre: a crop's
#: principal point is often a half-integer pair too (a centred camera's, less the crop's corner).
COMMON_FRAME_SIZES: tuple[tuple[int, int], ...] = (
    (640, 360), (640, 480), (720, 480), (720, 576), (800, 600), (854, 480), (960, 540), (960, 720), (1024, 576),
    (1024, 768), (1280, 720), (1280, 960), (1280, 1024), (1440, 1080), (1600, 1200), (1920, 1080), (1920, 1200),
    (1920, 1440), (2048, 1080), (2048, 1536), (2560, 1440), (2592, 1944), (2704, 1520), (2704, 2028), (3264, 2448),
    (3840, 2160), (4000, 3000), (4032, 3024), (4096, 2160),
)


def _reshaped_hint(w: int, h: int, fx: float, fy: float, cx: float, cy: float, given: str) -> str | None:
    """:func:`mixed_up_intrinsics`' hint where ``fx, fy, cx, cy`` look like the centred camera of a frame of
    :data:`COMMON_FRAME_SIZES` of another shape than these ``w x h`` frames, at least twice as large along one side
    and as large along the other, not adapted to them (:func:`_unscaled_hint` tells a larger frame of the same
    shape): its principal point exactly that frame's centre and its focal lengths a plausible camera's of it. The
    hint gives the two cameras such frames have: cut from the larger frame's middle to their shape, then resized
    (square pixels), or resized to their size as a whole (squeezed: pixels of another shape, offered where those are
    a plausible camera's); None otherwise."""
    for big_w, big_h in COMMON_FRAME_SIZES + tuple((b, a) for a, b in COMMON_FRAME_SIZES):
        if big_w * h == big_h * w or big_w < w or big_h < h or max(big_w / w, big_h / h) < 2:
            continue  # (the same shape: _unscaled_hint's; smaller along a side, or under twice the size)
        half = (big_w - 1) / 2, (big_h - 1) / 2
        if ((cx, cy) == half or (cx, cy) == (big_w / 2, big_h / 2)) and _fits(big_w, big_h, fx, fy, cx, cy, True):
            s = min(big_w / w, big_h / h)  # (the middle cut to these frames' shape, then resized by 1 / s)
            x0, y0 = (big_w - s * w) / 2, (big_h - s * h) / 2
            cut = (fx / s, fy / s, (cx + 0.5 - x0) / s - 0.5, (cy + 0.5 - y0) / s - 0.5)
            squeezed = (fx * w / big_w, fy * h / big_h, (cx + 0.5) * w / big_w - 0.5, (cy + 0.5) * h / big_h - 0.5)
            a, b = (", ".join(f"{n}={v:.6g}" for n, v in zip(("fx", "fy", "cx", "cy"), c)) for c in (cut, squeezed))
            whole = (f"; resized whole (squeezed), Intrinsics({w}, {h}, {b})" if _focal_lengths_fit(w, h, *squeezed[:2])
                     else "")  # (squeezed to tall pixels: itself implausible, not offered)
            return (f"intrinsics {given} look like the camera of a {big_w}x{big_h} frame (its centre the principal "
                    f"point), not adapted to these frames of another shape? Cut from its middle and resized, they "
                    f"have Intrinsics({w}, {h}, {a}){whole}; the camera of a crop of a larger frame (its principal "
                    "point) is right as given")
    return None


class MixedUpIntrinsics(UserWarning):
    """The warning :func:`~torchface.tracker.step.initialise` gives with :func:`mixed_up_intrinsics`' hint (a
    ``UserWarning``); ``intrinsics`` is the camera it is of, for a front end that speaks of its own options
    (``torchface track --focal``) rather than of :class:`Intrinsics`' arguments."""

    def __init__(self, message: str, intrinsics: Intrinsics) -> None:
        super().__init__(message)
        self.intrinsics = intrinsics

    def __reduce__(self) -> tuple[type["MixedUpIntrinsics"], tuple[str, Intrinsics], dict[str, Any]]:
        """Pickled and copied with its camera (``args`` holds the message alone, so the default pickle called
        ``MixedUpIntrinsics(message)``, a ``TypeError``: a warning raised as an error, ``-W error``, in a
        ``multiprocessing`` worker could not be sent back), and its other attributes as the default keeps them
        (``add_note``'s ``__notes__``)."""
        return type(self), (str(self), self.intrinsics), self.__dict__


def mixed_up_intrinsics(intrinsics: Intrinsics) -> str | None:
    """A hint, as one line, where a frame's camera looks like a mix-up of the constructor's arguments, with the
    likely fix; None for a plausible camera (and for entries that are tensors: a calibration being optimised).

    Nothing here is impossible (a principal point off the frame's centre, or outside a crop of a larger frame, and
    non-square pixels exist), so :func:`~torchface.tracker.step.initialise` warns with it and tracks on
    (:func:`~torchface.tracker.step.check_initialise_inputs`). A camera is looked at where it is implausible: ``fx``
    more than :data:`PLAUSIBLE_ASPECT` times ``fy``, or ``fy`` more than :data:`PLAUSIBLE_WIDE_PIXELS` times ``fx``
    (anamorphic video's wide pixels), one under 5 % of the frame's larger side, or the principal point outside the
    frame. Recognised, where the mix-up's reading is a frame's usual camera (focal lengths within
    10 %, the principal point near the centre):

    - OpenCV's matrix order ``fx, cx, fy, cy`` (``K``'s entries row by row) given as ``fx, fy, cx, cy``;
    - the principal point and the focal lengths swapped (``cx, cy, fx, fy``);
    - normalised intrinsics (``fx / W``, ``cx / W``: a focal length of about one pixel);
    - the camera of a frame at least twice as large, not scaled with the frames (its principal point the larger
      frame's centre: a calibration at 1920x1440 used for 640x480 frames, ``Intrinsics.default(3840, 2160)`` for
      1920x1080 ones), or of a common frame size of another shape (:data:`COMMON_FRAME_SIZES`: a 1920x1080
      calibration for 640x480 frames), with the cameras of its middle cut to the frames' shape and of it squeezed;
    - a principal point at ``(0, 0)``, the top-left pixel (a transposed ``K`` read, or a camera whose image
      coordinates are centred; torchface's pixel centres are at integers from the top-left, the centre at
      ``((W - 1) / 2, (H - 1) / 2)``), or at ``(W, H)``, the frame's size.

    A principal point outside the frame that none of these explains is a crop's camera (its larger frame's principal
    point), plausible unless the frame's centre lies more than :data:`PLAUSIBLE_OFF_AXIS` focal lengths from it.

    A camera in centred coordinates whose principal point is near ``(0, 0)`` but not on it (a calibration's offset
    from the centre, e.g. ``(10, -5)`` for a 640x480 frame) is not told: its numbers are those of a genuine crop, the
    crop whose top-left corner lies near the larger frame's principal point. The bottom-right quadrant of a frame
    twice as large is such a crop: ``(-0.5, -0.5)`` with the larger frame's default camera, and with a calibrated one
    its principal point's offset from the centre, ``(5.2, -7.2)`` for a 1280x960 calibration at ``(645.2, 472.8)``.
    The focal length does not tell them apart either (that quadrant's ``fx`` is the larger frame's, ``fx / W`` 1 for a
    wide lens, as a centred 640x480 camera's can be), so any region around ``(0, 0)`` warned of would warn such crops
    at every start; ``(0, 0)`` exactly is told (a crop starting exactly on the larger frame's principal point is no
    quadrant of a default camera, whose centre is not a pixel corner).

    Example:
        >>> mixed_up_intrinsics(Intrinsics(640, 480, 600.0, 319.5, 600.0, 239.5))  # doctest: +ELLIPSIS
        "...OpenCV's matrix order (fx, cx, fy, cy)...: Intrinsics(640, 480, fx=600, fy=600, cx=319.5, cy=239.5)..."
        >>> mixed_up_intrinsics(Intrinsics(640, 480, 900.0, 900.0, 100.0, 400.0)) is None  # off-centre: plausible
        True
    """
    entries = (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
    if any(isinstance(v, torch.Tensor) for v in entries):
        return None
    w, h = intrinsics.width, intrinsics.height
    fx, fy, cx, cy = (float(v) for v in entries)
    given = f"fx={fx:g}, fy={fy:g}, cx={cx:g}, cy={cy:g} for a {w}x{h} frame"
    if cx == 0 and cy == 0 and min(w, h) > 1:
        return (f"intrinsics {given} put the principal point at the top-left pixel: a transposed K read (K[0, 2], "
                f"K[1, 2] are cx, cy), or a camera in centred coordinates? torchface's pixel centres are at integers "
                f"from the top-left, a centred camera's principal point ({(w - 1) / 2:g}, {(h - 1) / 2:g})")
    if _fits(w, h, fx, fy, cx, cy, tight=False):  # (but a 2x larger frame's centre: its bottom-right corner's edge;
        # a 1280x720 frame's for 640x480 frames: their right edge)
        return _unscaled_hint(w, h, fx, fy, cx, cy, given) or _reshaped_hint(w, h, fx, fy, cx, cy, given)
    if abs(cx - w) <= 1 and abs(cy - h) <= 1 and _focal_lengths_fit(w, h, fx, fy):
        return (f"intrinsics {given} put the principal point at ({w}, {h}), the frame's size: a centred camera's "
                f"principal point is ({(w - 1) / 2:g}, {(h - 1) / 2:g}), pixel centres at integers from the top-left")
    readings = (
        ("OpenCV's matrix order (fx, cx, fy, cy), K's entries row by row, given as (fx, fy, cx, cy)?",
         (fx, cx, fy, cy)),
        ("the focal lengths and the principal point swapped (cx, cy, fx, fy)?", (cx, cy, fx, fy)),
        ("normalised intrinsics (fx / W, fy / H, cx / W, cy / H)?", (fx * w, fy * h, cx * w - 0.5, cy * h - 0.5)),
    )
    for what, (a, b, c, d) in readings:
        if min(a, b) > 0 and _fits(w, h, a, b, c, d, tight=True):
            return (f"intrinsics {given} look mixed up: {what} Likely meant: Intrinsics({w}, {h}, fx={a:g}, fy={b:g}, "
                    f"cx={c:g}, cy={d:g}), or Intrinsics.from_matrix(K, {w}, {h}) from a 3x3 calibration matrix")
    unscaled = _unscaled_hint(w, h, fx, fy, cx, cy, given) or _reshaped_hint(w, h, fx, fy, cx, cy, given)
    if unscaled is not None:
        return unscaled
    if _crop_fits(w, h, fx, fy, cx, cy):  # (a principal point outside the frame alone: a crop of a larger frame)
        return None
    return (f"intrinsics {given} are implausible (fx more than {PLAUSIBLE_ASPECT:g} times fy or fy more than "
            f"{PLAUSIBLE_WIDE_PIXELS:g} times fx, under 5 % of the frame's size, or the frame's centre more than "
            f"{PLAUSIBLE_OFF_AXIS:g} focal lengths from the principal point): check the order, Intrinsics(width, "
            f"height, fx, fy, cx, cy), or use Intrinsics.from_matrix(K, {w}, {h})")
