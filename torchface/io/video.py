"""Reading frames for tracking, with validation (OpenCV at the boundary).

Three kinds of input are accepted:

- a video file that OpenCV can decode (``.mp4``, ``.avi``, ``.mpg``, ...);
- a folder of images (``.png``, ``.jpg``, ``.jpeg``, ``.bmp``, ``.tif``, ``.tiff``), read in name order with
  ``cv2.IMREAD_UNCHANGED`` so that 8- and 16-bit, gray, BGR and BGRA images keep what they store;
- a ``.npy`` array ``(T, H, W)`` (gray) or ``(T, H, W, C)`` with ``C`` in 1, 3 (RGB), 4 (RGBA).

Every frame becomes a ``(3, H, W)`` float32 RGB tensor in ``[0, 1]`` (:mod:`torchface.conventions`):
gray is replicated to three channels, alpha is dropped, 8-bit is divided by 255 and 16-bit by 65535.
Anything else (another dtype, float values outside ``[0, 1]`` or non-finite, a frame smaller than
:data:`MIN_SIZE` on a side, a frame whose size differs from the first frame's) raises
:class:`~torchface.io.errors.InputError` with a one-line message naming the file and the frame.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import cv2
import numpy as np
import torch
from torch import Tensor

from torchface.io.errors import InputError

__all__ = ["IMAGE_SUFFIXES", "MIN_SIZE", "FrameReader", "VideoInfo", "open_frames", "frame_to_tensor"]

#: Image file suffixes read from a folder input.
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: Smallest accepted frame side in pixels (the tracker's coarsest pyramid level needs a few pixels).
MIN_SIZE: int = 32


@dataclass(frozen=True)
class VideoInfo:
    """What is known about an input before it is read through.

    Attributes:
        path: the input path.
        kind: ``"video"``, ``"images"`` or ``"array"``.
        width: W of the first frame.
        height: H of the first frame.
        fps: frame rate (the container's, else 25).
        num_frames: frame count if the input states it (a container's count can be approximate), else None.
        source_format: what the first frame stored, e.g. ``"uint8 BGR"``, ``"uint16 gray"``.
    """

    path: Path
    kind: str
    width: int
    height: int
    fps: float
    num_frames: int | None
    source_format: str


def frame_to_tensor(array: np.ndarray, bgr: bool, where: str) -> tuple[Tensor, str]:
    """One image array -> ``(3, H, W)`` float32 RGB in ``[0, 1]`` and a description of its format.

    Args:
        array: ``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` or ``(H, W, 4)``; uint8, uint16 or float in [0, 1].
        bgr: the colour channels are in OpenCV's BGR(A) order (else RGB(A)).
        where: names the frame in error messages.

    Raises:
        InputError: unsupported layout, dtype or value range.
    """
    if not isinstance(array, np.ndarray):
        raise InputError(f"{where}: expected an image array, got {type(array).__name__}")
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[2] not in (1, 3, 4):
        raise InputError(f"{where}: expected an (H, W) or (H, W, 1|3|4) image, got shape {array.shape}")
    channels = {1: "gray", 3: "BGR" if bgr else "RGB", 4: "BGRA" if bgr else "RGBA"}[array.shape[2]]
    if array.dtype == np.uint8:
        data = torch.from_numpy(np.ascontiguousarray(array)).to(torch.float32) / 255.0
    elif array.dtype == np.uint16:
        data = torch.from_numpy(array.astype(np.float32)) / 65535.0
    elif array.dtype in (np.float32, np.float64):
        data = torch.from_numpy(array.astype(np.float32))
        if not bool(torch.isfinite(data).all()) or float(data.min()) < 0.0 or float(data.max()) > 1.0:
            raise InputError(f"{where}: float frames must be finite and in [0, 1]")
    else:
        raise InputError(f"{where}: unsupported pixel type {array.dtype} (expected uint8, uint16 or float in [0, 1])")
    fmt = f"{array.dtype} {channels}"
    if data.shape[2] == 1:
        data = data.expand(-1, -1, 3)
    elif data.shape[2] == 4:
        data = data[:, :, :3]
    if bgr:
        data = data.flip(2)
    return data.permute(2, 0, 1).contiguous(), fmt


class FrameReader:
    """Iterate the frames of one input as ``(3, H, W)`` float32 RGB tensors; use :func:`open_frames`.

    Validation happens as frames are read: a frame of another size than the first raises
    :class:`InputError` naming its index. :attr:`frames_read` counts the frames returned so far.
    """

    def __init__(self, info: VideoInfo, first: Tensor, rest: Iterator[tuple[np.ndarray, bool]], closer=None) -> None:
        self.info = info
        self._first: Tensor | None = first
        self._rest = rest
        self._closer = closer
        self.frames_read = 0

    def __iter__(self) -> "FrameReader":
        return self

    def __next__(self) -> Tensor:
        if self._first is not None:
            frame, self._first = self._first, None
            self.frames_read = 1
            return frame
        array, bgr = next(self._rest)
        where = f"{self.info.path}: frame {self.frames_read}"
        frame, _ = frame_to_tensor(array, bgr, where)
        if tuple(frame.shape[-2:]) != (self.info.height, self.info.width):
            raise InputError(
                f"{where} is {frame.shape[-1]}x{frame.shape[-2]} but the video started at "
                f"{self.info.width}x{self.info.height} (the frame size must not change)"
            )
        self.frames_read += 1
        return frame

    def close(self) -> None:
        """Release the underlying decoder."""
        if self._closer is not None:
            self._closer()
            self._closer = None

    def __enter__(self) -> "FrameReader":
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _video_frames(cap: cv2.VideoCapture) -> Iterator[tuple[np.ndarray, bool]]:
    while True:
        ok, img = cap.read()
        if not ok:
            return
        yield img, True


def _image_frames(files: list[Path]) -> Iterator[tuple[np.ndarray, bool]]:
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"{f}: cannot decode this image")
        yield img, True


def _array_frames(array: np.ndarray) -> Iterator[tuple[np.ndarray, bool]]:
    for frame in array:
        yield frame, False


def _check_size(path: Path, frame: Tensor) -> None:
    h, w = frame.shape[-2:]
    if h < MIN_SIZE or w < MIN_SIZE:
        raise InputError(f"{path}: frames are {w}x{h}; at least {MIN_SIZE}x{MIN_SIZE} pixels are needed")


def open_frames(path: str | os.PathLike[str]) -> FrameReader:
    """Open a video file, an image folder or a ``.npy`` array and read its first frame.

    Args:
        path: the input.

    Returns:
        A :class:`FrameReader` whose :attr:`~FrameReader.info` describes the input.

    Raises:
        InputError: missing path, nothing decodable, zero frames, an unsupported frame format or a frame
            smaller than :data:`MIN_SIZE`.

    Example:
        >>> # with open_frames("clip.mp4") as frames: first = next(frames)   # (3, H, W)
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file or folder")
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES and f.is_file())
        if not files:
            raise InputError(f"{p}: folder holds no images ({', '.join(IMAGE_SUFFIXES)}): zero frames")
        rest = _image_frames(files)
        first_arr, _ = next(rest)
        first, fmt = frame_to_tensor(first_arr, True, f"{files[0]}")
        _check_size(p, first)
        info = VideoInfo(p, "images", first.shape[-1], first.shape[-2], 25.0, len(files), fmt)
        return FrameReader(info, first, rest)
    if p.suffix.lower() == ".npy":
        try:
            array = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError(f"{p}: not a readable .npy array ({exc})") from None
        if array.ndim not in (3, 4):
            raise InputError(f"{p}: expected a (T, H, W) or (T, H, W, C) array, got shape {array.shape}")
        if array.shape[0] == 0:
            raise InputError(f"{p}: zero frames")
        rest = _array_frames(array[1:])
        first, fmt = frame_to_tensor(array[0], False, f"{p}: frame 0")
        _check_size(p, first)
        info = VideoInfo(p, "array", first.shape[-1], first.shape[-2], 25.0, int(array.shape[0]), fmt)
        return FrameReader(info, first, rest)
    if not os.access(p, os.R_OK):
        raise InputError(f"{p}: permission denied")
    cap = cv2.VideoCapture(str(p))
    if not cap.isOpened():
        cap.release()
        raise InputError(f"{p}: not a video OpenCV can open (unreadable, corrupt or an unknown format)")
    ok, img = cap.read()
    if not ok or img is None:
        cap.release()
        raise InputError(f"{p}: no frame could be decoded (zero frames, or a corrupt video)")
    first, fmt = frame_to_tensor(img, True, f"{p}: frame 0")
    try:
        _check_size(p, first)
    except InputError:
        cap.release()
        raise
    fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    info = VideoInfo(p, "video", first.shape[-1], first.shape[-2], fps if 0 < fps < 1000 else 25.0, count or None, fmt)
    return FrameReader(info, first, _video_frames(cap), cap.release)
