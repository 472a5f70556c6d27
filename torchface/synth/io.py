"""Lossless video files for synthetic sequences (OpenCV at the boundary: BGR uint8 on disk).

Writing goes to a temporary name in the destination folder and is renamed when complete, so a
reader never sees a half-written file. The codec is the first of :data:`LOSSLESS_CODECS` that this
OpenCV build can write; FFV1 in AVI is lossless and reads back bit-exactly with ``cv2.VideoCapture``. The readers open
a video as the tracker's input is opened (:func:`torchface.io.video.open_capture`: a phone video's display rotation
applied on every OpenCV).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType

import cv2
import numpy as np
import torch
from torch import Tensor

from torchface._atomic import partial_path
from torchface._frame_values import check_frame_values
from torchface.geometry._checks import check_int, check_number
from torchface.io.video import open_capture, opencv_path

__all__ = [
    "LOSSLESS_CODECS",
    "WRITTEN_SUFFIXES",
    "VideoSink",
    "write_video",
    "read_video",
    "read_video_uint8",
    "iter_video_uint8",
    "frames_to_uint8",
]

#: FourCC codes tried in order (all lossless); ``MJPG`` (lossy) is the last resort.
LOSSLESS_CODECS: tuple[str, ...] = ("FFV1", "png ", "HFYU", "MJPG")

#: Suffixes :class:`VideoSink` writes: FFV1 in these reads back bit-exactly (others were written unreadable, ``.mpg``,
#: or failed as "no OpenCV video codec ... could open", ``.npy``).
WRITTEN_SUFFIXES: tuple[str, ...] = (".avi", ".mkv", ".mov", ".mp4")


def _check_frames(frames: object) -> Tensor:
    """Refuse frames that would be written as something else: not a tensor, NaN or infinite values (written as 0),
    values outside [0, 1] beyond a resampling's overshoot (0-255 floats were clipped to a white video)."""
    if not isinstance(frames, Tensor):
        hint = " (torch.from_numpy(frames): (T, 3, H, W) RGB)" if isinstance(frames, np.ndarray) else ""
        raise TypeError(f"frames must be a torch.Tensor, got {type(frames).__name__}{hint}")
    if frames.dtype != torch.uint8:
        if not frames.is_floating_point():
            raise TypeError(f"frames must be float in [0, 1] or uint8, got {frames.dtype}")
        if not bool(torch.isfinite(frames).all()):
            raise ValueError("frames must be finite, got NaN or infinite values")
        check_frame_values(frames)
    return frames


def frames_to_uint8(frames: Tensor) -> np.ndarray:
    """``(T, 3, H, W)`` float RGB in ``[0, 1]`` -> ``(T, H, W, 3)`` uint8 BGR for OpenCV."""
    if frames.ndim != 4 or frames.shape[1] != 3:
        raise ValueError(f"frames must be (T, 3, H, W), got shape {tuple(frames.shape)}")
    if frames.dtype == torch.uint8:
        arr = frames
    else:
        arr = (frames.detach().float().clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)
    return np.ascontiguousarray(arr.flip(1).permute(0, 2, 3, 1).cpu().numpy())


class VideoSink:
    """Streams frames into a lossless video file; use as a context manager.

    Args:
        path: destination (``.avi`` recommended); written as ``<stem>.partial-<pid>-<hex>.avi``, this process's own
            (:func:`torchface._atomic.partial_path`: two writers of one file do not write into, or remove, each
            other's), then renamed.
        width: frame width W.
        height: frame height H.
        fps: frames per second stored in the file.

    Raises:
        FileNotFoundError: ``path``'s folder does not exist.
        OSError: the file cannot be written there (a read-only folder, a full disk), naming it.
        IsADirectoryError: ``path`` is a folder.
        ValueError: an odd or too small size, a suffix not in :data:`WRITTEN_SUFFIXES`, ``fps`` not a number > 0, or a
            name that is not valid UTF-8 (OpenCV cannot write it).
        RuntimeError: no codec of :data:`LOSSLESS_CODECS` opens the file.

    Example:
        >>> # with VideoSink("seq.avi", 640, 480) as sink: sink.write(frames)  # frames (T, 3, H, W)
    """

    def __init__(self, path: str | os.PathLike[str], width: int, height: int, fps: float = 25.0) -> None:
        self.path = Path(path)
        self.width, self.height = int(width), int(height)
        fps = check_number(fps, "fps", "(0, inf)")  # (0 or NaN: "no OpenCV video codec ... could open", and noise)
        if self.width < 2 or self.height < 2 or self.width % 2 or self.height % 2:
            # FFV1 and the other 4:2:0 codecs write odd sizes cropped to even ones without a word, so the file
            # would no longer match the ground truth's intrinsics and landmarks
            raise ValueError(
                f"video frames must have an even width and height >= 2, got {self.width}x{self.height} (the lossless "
                "codecs crop odd sizes; render_sequence renders any size in memory)"
            )
        if not self.path.parent.is_dir():  # (OpenCV's writer fails without a word: "no codec could open" misled)
            raise FileNotFoundError(f"{self.path}: no folder {self.path.parent} to write the video in")
        if self.path.is_dir():
            raise IsADirectoryError(f"{self.path}: a folder, not a video file name (e.g. {self.path / 'clip.avi'})")
        if self.path.suffix.lower() not in WRITTEN_SUFFIXES:
            npy = " (a .npy clip: np.save(path, frames.permute(0, 2, 3, 1).numpy()), (T, H, W, 3) RGB)"
            raise ValueError(
                f"{self.path}: a lossless video is written as {', '.join(WRITTEN_SUFFIXES)} (.avi recommended), got "
                f"{self.path.suffix or 'no suffix'!r}" + (npy if self.path.suffix.lower() == ".npy" else "")
            )
        self._tmp = partial_path(self.path)
        tmp = opencv_path(self._tmp, ValueError)  # (a name that is not UTF-8 crashed OpenCV's writer: a segfault)
        self._writer: cv2.VideoWriter | None = None
        self.codec = ""
        self.frames_written = 0
        with open(self._tmp, "wb"):  # OSError naming the file where it cannot be written (a read-only folder): the
            pass  # writer fails without a word, and "no OpenCV video codec ... could open" misled
        for code in LOSSLESS_CODECS:
            writer = cv2.VideoWriter(tmp, cv2.VideoWriter.fourcc(*code), float(fps), (self.width, self.height))
            if writer.isOpened():
                self._writer, self.codec = writer, code
                break
            writer.release()
        if self._writer is None:
            self._tmp.unlink(missing_ok=True)
            raise RuntimeError(f"no OpenCV video codec among {LOSSLESS_CODECS} could open {self._tmp}")

    def write(self, frames: Tensor) -> None:
        """Append ``(T, 3, H, W)`` float frames in ``[0, 1]`` (or uint8); NaN, infinite or 0-255 float values are
        refused (they were written as black or white pixels)."""
        if self._writer is None:
            raise RuntimeError("video sink is closed")
        frames = _check_frames(frames)
        if frames.ndim != 4 or tuple(frames.shape[1:]) != (3, self.height, self.width):
            raise ValueError(f"frames must be (T, 3, {self.height}, {self.width}), got {tuple(frames.shape)}")
        for img in frames_to_uint8(frames):
            self._writer.write(img)
        self.frames_written += int(frames.shape[0])

    def close(self) -> Path:
        """Finish the file and move it to its final name; returns that path."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
            os.replace(self._tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Drop the partial file."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> "VideoSink":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_video(path: str | os.PathLike[str], frames: Tensor, fps: float = 25.0) -> str:
    """Write ``(T, 3, H, W)`` RGB frames, float in ``[0, 1]`` or uint8, to ``path`` (a suffix of
    :data:`WRITTEN_SUFFIXES`, ``.avi`` recommended); returns the FourCC code used.

    Example:
        >>> # write_video("clip.avi", frames); read_video("clip.avi")  # the same frames, 8-bit quantised
    """
    frames = _check_frames(frames)
    if frames.ndim != 4 or frames.shape[1] != 3:
        raise ValueError(f"frames must be (T, 3, H, W), got shape {tuple(frames.shape)}")
    if frames.shape[0] == 0:  # (a video of no frame, which read_video cannot read)
        raise ValueError("frames must hold at least one frame, got T = 0")
    with VideoSink(path, frames.shape[3], frames.shape[2], fps) as sink:
        sink.write(frames)
        return sink.codec


def _open(path: str | os.PathLike[str]) -> cv2.VideoCapture:
    """An open capture of the video file ``path``, opened as :func:`torchface.io.video.open_capture` opens the
    tracker's input (turned by the container's display rotation on every OpenCV).

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: a name that is not valid UTF-8, or a file OpenCV cannot open as a video.
    """
    if not Path(path).is_file():
        raise FileNotFoundError(f"no video at {os.fspath(path)}")
    cap = open_capture(path, ValueError)
    if not cap.isOpened():
        cap.release()
        raise ValueError(f"{os.fspath(path)}: OpenCV cannot open this file as a video")
    return cap


def read_video_uint8(path: str | os.PathLike[str], max_frames: int | None = None) -> Tensor:
    """Read a video into ``(T, 3, H, W)`` uint8 RGB (a quarter of the memory of :func:`read_video`); at most
    ``max_frames`` (an int >= 1, None: all)."""
    if max_frames is not None:  # (0 or -1 said "could not read any frame" of a good video)
        max_frames = check_int(max_frames, "max_frames", 1)
    cap = _open(path)
    frames: list[np.ndarray] = []
    try:
        while max_frames is None or len(frames) < max_frames:
            ok, img = cap.read()
            if not ok:
                break
            frames.append(img)
    finally:
        cap.release()
    if not frames:
        raise ValueError(f"could not read any frame from {path}")
    return torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2).flip(1).contiguous()


def iter_video_uint8(path: str | os.PathLike[str]) -> Iterator[Tensor]:
    """Stream a video frame by frame as ``(1, 3, H, W)`` uint8 RGB (memory independent of its length).

    Example:
        >>> # for frame in iter_video_uint8("seq.avi"): ...   # (1, 3, H, W) uint8
    """
    cap = _open(path)
    try:
        while True:
            ok, img = cap.read()
            if not ok:
                return
            yield torch.from_numpy(img).permute(2, 0, 1).flip(0).unsqueeze(0).contiguous()
    finally:
        cap.release()


def read_video(path: str | os.PathLike[str], max_frames: int | None = None) -> Tensor:
    """Read a video into ``(T, 3, H, W)`` float32 RGB in ``[0, 1]``; at most ``max_frames`` (None: all)."""
    return read_video_uint8(path, max_frames).to(torch.float32) / 255.0
