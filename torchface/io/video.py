"""Reading frames for tracking, with validation (OpenCV at the boundary).

Three kinds of input are accepted:

- a video file that OpenCV can decode (``.mp4``, ``.avi``, ``.mpg``, ...);
- a folder of images (``.png``, ``.jpg``, ``.jpeg``, ``.bmp``, ``.tif``, ``.tiff``), read in name order (runs of
  digits compared as numbers, hidden files left out: :func:`image_files`) with ``cv2.IMREAD_UNCHANGED`` so that 8-
  and 16-bit, gray, BGR and BGRA images keep what they store;
- a ``.npy`` array ``(T, H, W)`` (gray) or ``(T, H, W, C)`` with ``C`` in 1, 3 (RGB), 4 (RGBA), memory-mapped and
  read a frame at a time as the other inputs are (a clip larger than the memory can be tracked).

The tracker takes 8-bit colour frames of even width and height (or float frames in ``[0, 1]``). By default a
grayscale, RGBA (4-channel) or 16-bit frame, or an odd width or height, raises
:class:`~torchface.io.errors.InputError` with a one-line message that names the problem and says how to
proceed (:data:`CONVERT_HINT`). With ``convert=True`` such frames are converted instead: gray is replicated to
three channels, alpha is dropped, 16-bit is scaled to ``[0, 1]`` (divided by 65535; a video file is decoded to
8 bits by OpenCV) and an odd-sized frame loses its last row and/or column.

A video file's stored format is read from OpenCV's pixel-format FourCC and the undecoded first frame
(``CAP_PROP_CONVERT_RGB`` off): gray FourCCs (``Y800``, ``GREY``, 16-bit gray) are grayscale, an undecoded
uint16 colour frame is 16-bit, and four channels whose alpha is not fully opaque are RGBA (an opaque alpha,
as in OpenCV's own FFV1 colour videos, is colour padding and accepted).

A video file is read as a viewer shows it: a display rotation in its container (a phone video's ``rotate`` tag or
display matrix) turns its frames (:func:`open_capture`), and ``width`` and ``height`` are the turned frames'.

Every frame becomes a ``(3, H, W)`` float32 RGB tensor in ``[0, 1]`` (:mod:`torchface.conventions`), 8-bit
values divided by 255. Anything else (another dtype, float values outside ``[0, 1]`` or non-finite, a frame
smaller than :data:`MIN_SIZE` on a side, a frame whose size differs from the first frame's) raises
:class:`~torchface.io.errors.InputError` with a one-line message naming the file and the frame.
"""

from __future__ import annotations

import math
import os
import re
import shlex
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from types import TracebackType
from typing import cast

import cv2
import numpy as np
import torch
from torch import Tensor

from torchface._frame_values import value_scale, value_scale_hint
from torchface._paths import missing_path_hint
from torchface._words import counted
from torchface.geometry._checks import check_bool, check_number
from torchface.io.errors import InputError

__all__ = [
    "CONVERT_HINT",
    "CONVERT_OPTION",
    "IMAGE_SUFFIXES",
    "VIDEO_SUFFIXES",
    "folder_of_videos_hint",
    "image_files",
    "MIN_SIZE",
    "ASSUMED_FPS",
    "PLAUSIBLE_FPS",
    "FrameReader",
    "VideoInfo",
    "array_convert_hint",
    "format_problems",
    "frame_to_tensor",
    "open_capture",
    "open_frames",
]

#: Image file suffixes read from a folder input.
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: Suffixes of video files and frame arrays, each one input of its own: a folder holding them is not an image-folder
#: input (:func:`folder_of_videos_hint`).
VIDEO_SUFFIXES: tuple[str, ...] = (
    ".mp4", ".avi", ".mov", ".mkv", ".mpg", ".mpeg", ".m4v", ".webm", ".wmv", ".flv", ".mts", ".ts", ".npy",
)
#: Smallest accepted frame side in pixels (the tracker's coarsest pyramid level needs a few pixels).
MIN_SIZE: int = 32
#: The frame rates (frames per second, open interval) a video container may declare as its own: outside it a rate is
#: taken as none (:class:`VideoInfo`'s ``fps_assumed``, its ``declared_fps`` the rate declared): from 1000 frames/s up
#: the CSV's millisecond timestamps of two rows could coincide, and at 0.001 or less (a frame every 1000 s: a broken
#: header, or a time-lapse's) OpenCV's ``mp4v`` writer cannot write the overlay and normalised videos at it.
PLAUSIBLE_FPS: tuple[float, float] = (0.001, 1000.0)
#: The frame rate of an input that has none of its own (an image folder, an array, a single image, a container without
#: a plausible rate; :class:`VideoInfo`'s ``fps_assumed``), frames per second, unless :func:`open_frames` is given one.
ASSUMED_FPS: float = 25.0
#: How to proceed when a frame is grayscale, RGBA, 16-bit or odd-sized (ends every such error message).
CONVERT_HINT: str = (
    'convert it first, e.g. ffmpeg -i in.mp4 -pix_fmt rgb24 -vf "crop=trunc(iw/2)*2:trunc(ih/2)*2" out.mp4, '
    "or pass --convert to let torchface convert the frames itself"  # (CONVERT_OPTION)
)
#: How :data:`CONVERT_HINT` and :func:`array_convert_hint` end: the command line's own conversion (a front end with
#: another way to ask for it, ``DatasetConfig(convert=True)``, puts its own in place of this).
CONVERT_OPTION: str = "pass --convert to let torchface convert the frames itself"
#: How a ``.npy`` frame array is saved as the reader takes it, per problem :func:`format_problems` names (``a``: the
#: ``(T, H, W[, C])`` array): an array's fix, where :data:`CONVERT_HINT`'s ffmpeg command suits a video file.
_ARRAY_FIXES: tuple[tuple[str, str], ...] = (
    ("grayscale", "np.repeat(a[..., None], 3, -1) for gray (T, H, W) frames (np.repeat(a, 3, -1) of (T, H, W, 1))"),
    ("RGBA", "a[..., :3] for RGBA"),
    ("16-bit", "(a / 65535).astype(np.float32) for 16-bit"),
    ("odd size", "a[:, : a.shape[1] // 2 * 2, : a.shape[2] // 2 * 2] for an odd size"),
)


def array_convert_hint(problems: str) -> str:
    """The end of the message of a ``.npy`` array whose frames are ``problems`` (:func:`format_problems` joined,
    e.g. ``"grayscale, odd size 31x20"``): how to save it as 8-bit RGB ``(T, H, W, 3)`` frames, or
    :data:`CONVERT_OPTION` (:data:`CONVERT_HINT`'s counterpart for an array, whose ffmpeg command suits a file)."""
    fixes = ", then ".join(f"a = {fix}" for word, fix in _ARRAY_FIXES if word in problems)
    return (f"save the array as (T, H, W, 3) RGB frames of even height and width, uint8 or float in [0, 1]: "
            f"np.save(path, a) after {fixes}; or {CONVERT_OPTION}")  # fmt: skip


#: OpenCV pixel-format FourCCs of grayscale video (8-bit ``Y800``/``GREY``/``Y8``, 16-bit ``Y1[0][16]``).
_GRAY_FOURCCS: frozenset[str] = frozenset({"Y800", "GREY", "Y8  ", "Y8\x00\x00", "Y1\x00\x10", "\x10\x001Y", "Y16 "})
#: FourCCs of packed RGB(A) video (8- and 16-bit) whose undecoded first frame shows alpha and bit depth.
_RGB_FOURCCS: frozenset[str] = frozenset(
    {"BGRA", "RGBA", "ARGB", "ABGR", "BGR\x00", "RGB\x00", "RBA@", "BRA@", "@ABR", "@ARB", "RGB0", "BGR0"}
    | {"0BGR", "0RGB"}
)


@dataclass(frozen=True)
class VideoInfo:
    """What is known about an input before it is read through.

    Attributes:
        path: the input path.
        kind: ``"video"``, ``"images"`` or ``"array"``.
        width: W of the first frame.
        height: H of the first frame.
        fps: frame rate (the container's, else :func:`open_frames`' ``fps``, else :data:`ASSUMED_FPS`, 25: see
            ``fps_assumed``).
        num_frames: frame count if the input states it (a container's count can be approximate; a stream's
            unknown count, which OpenCV gives as -1 or a huge negative number, is None), else None.
        source_format: what the first frame stored, e.g. ``"uint8 BGR"``, ``"uint16 gray"``.
        conversion: what ``convert=True`` did to it, e.g. ``"uint16 gray -> uint8-range RGB; cropped 159x119 to
            158x118"``; empty when the frames are used as stored.
        fps_assumed: True when ``fps`` is the default 25, not the input's: image folders, arrays, a single image
            file, and videos whose container gives no frame rate or one outside :data:`PLAUSIBLE_FPS`, (0.001, 1000)
            frames/s; False where :func:`open_frames`' ``fps`` gave their rate (``fps_given``).
        fps_given: True when ``fps`` is the rate :func:`open_frames` was given for such an input (``torchface track
            --fps``), False where it is the input's own or the default 25.
        declared_fps: the rate a video's container declares where it is not taken, being outside
            :data:`PLAUSIBLE_FPS` (e.g. ``0.0005``: ``fps`` is then 25 or the one given); None where the container
            declares none, where its rate is taken, and for image folders and arrays.
    """

    path: Path
    kind: str
    width: int
    height: int
    fps: float
    num_frames: int | None
    source_format: str
    conversion: str = ""
    fps_assumed: bool = False
    fps_given: bool = False
    declared_fps: float | None = None


def _layout(array: np.ndarray, where: str) -> np.ndarray:
    """``(H, W)`` -> ``(H, W, 1)``; anything but ``(H, W, 1|3|4)`` raises."""
    if not isinstance(array, np.ndarray):
        raise InputError(f"{where}: expected an image array, got {type(array).__name__}")
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[2] not in (1, 3, 4):
        raise InputError(f"{where}: expected an (H, W) or (H, W, 1|3|4) image, got shape {array.shape}")
    return array


def format_problems(array: np.ndarray) -> list[str]:
    """What the tracker does not take as stored: grayscale, RGBA, 16-bit, odd width or height.

    Args:
        array: ``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` or ``(H, W, 4)`` image.

    Returns:
        Short descriptions, e.g. ``["grayscale", "16-bit", "odd size 159x119"]``; empty when the frame is
        8-bit (or float) colour with even width and height.
    """
    problems = []
    channels = 1 if array.ndim == 2 else array.shape[2]
    if channels == 1:
        problems.append("grayscale")
    elif channels == 4:
        problems.append("RGBA (4 channels)")
    if array.dtype == np.uint16:
        problems.append("16-bit")
    h, w = array.shape[:2]
    if h % 2 or w % 2:
        problems.append(f"odd size {w}x{h}")
    return problems


def _problem_message(where: str, problems: list[str]) -> str:
    what = ", ".join(problems)
    return f"{where}: frames are {what} (torchface takes 8-bit colour frames of even width and height): {CONVERT_HINT}"


#: Why a frame file's NaN pixels are refused (the start of :data:`NAN_PIXELS_HINT`; a dataset's message follows it
#: with what a dataset's user can do).
NAN_PIXELS_WHY: str = (
    "a frame file's pixels must be values; NaN marks a missing pixel only in the Python API's frame tensors "
    "(FaceTracker, NormaliseFaces, NormalisedFaceLayer), which leave it out of the fit"
)

#: What a frame file's NaN pixels are told (:func:`frame_to_tensor`): why they are refused and what to do.
NAN_PIXELS_HINT: str = NAN_PIXELS_WHY + ": fill them, np.nan_to_num(frames, nan=0.0), or track the frames as a tensor"


def _float_range_problem(array: np.ndarray) -> str:
    """What a float frame outside [0, 1] holds, and what to do (:func:`frame_to_tensor`'s message; a clip of 0-255
    floats, ``frames.astype(np.float32)`` of 8-bit ones, was told only "float frames must be finite and in [0, 1]",
    and frames normalised for a network, ImageNet's mean and standard deviation giving about -2.1 to 2.6, only their
    range): NaN or infinite values named, the finite ones' range, and what they look like by the rule that the
    tracker's checks of a tensor's frames share (:func:`torchface._frame_values.value_scale`: the same values are told
    the same), with NumPy's remedies."""
    finite = array[np.isfinite(array)]
    parts = []
    nan = bool(np.isnan(array).any())
    if finite.size < array.size:
        parts.append("NaN" if nan else "infinite")
    hint = ""
    if finite.size:
        lo, hi = float(finite.min()), float(finite.max())
        parts.append(f"values from {lo:.4g} to {hi:.4g}")
        scale = value_scale(lo, hi, int(np.count_nonzero(finite < 0.0)), int(finite.size))
        hint = value_scale_hint(scale, "np.clip(frames, 0, 1)", "divide by 255, or save them as uint8")
    if nan:  # (deliberate: the tensor API's NaN pixels are missing ones, left out of the fit; a file's frames feed
        # the 8-bit overlay and face videos too, and a NaN saved in one is more often damage than a mark; the bare
        # refusal did not say that the tensor API takes them)
        hint += f" ({NAN_PIXELS_HINT})"
    return "got " + " and ".join(parts) + hint


def frame_to_tensor(array: np.ndarray, bgr: bool, where: str, convert: bool = False) -> tuple[Tensor, str]:
    """One image array -> ``(3, H', W')`` float32 RGB in ``[0, 1]`` and a description of its stored format.

    Args:
        array: ``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` or ``(H, W, 4)``; uint8, uint16 or float (16, 32 or 64 bits)
            in [0, 1].
        bgr: the colour channels are in OpenCV's BGR(A) order (else RGB(A)).
        where: names the frame in error messages.
        convert: convert gray (replicated), RGBA (alpha dropped), 16-bit (divided by 65535) and odd sizes
            (last row / column cropped, so ``H' = H - H % 2``, ``W' = W - W % 2``) instead of raising.

    Raises:
        InputError: unsupported layout, dtype or value range; with ``convert=False`` also a grayscale, RGBA,
            16-bit or odd-sized frame (:func:`format_problems`), the message ending in :data:`CONVERT_HINT`.

    Example:
        >>> frame_to_tensor(np.zeros((40, 50, 3), np.uint8), bgr=True, where="x")[0].shape
        torch.Size([3, 40, 50])
    """
    convert = check_bool(convert, "convert")  # (as open_frames': convert="no" converted)
    array = _layout(array, where)
    if array.dtype not in (np.uint8, np.uint16, np.float16, np.float32, np.float64):  # (float16: a half .npy clip)
        hint = ""
        if array.dtype.kind in "iu" and array.size and int(array.min()) >= 0 and int(array.max()) <= 65535:
            # (an array of Python ints, np.array(rows), is int64: told the type alone)
            small = int(array.max()) <= 255
            hint = f"; its values are {'0-255' if small else '0-65535'}: a.astype(np.{'uint8' if small else 'uint16'})"
        raise InputError(f"{where}: unsupported pixel type {array.dtype} (expected uint8, uint16 or float in [0, 1]"
                         f"{hint})")  # fmt: skip
    if array.dtype.kind == "f" and not (np.isfinite(array).all() and array.min() >= 0.0 and array.max() <= 1.0):
        raise InputError(f"{where}: float frames must be finite and in [0, 1], {_float_range_problem(array)}")
    problems = format_problems(array)
    if problems and not convert:
        raise InputError(_problem_message(where, problems))
    channels = {1: "gray", 3: "BGR" if bgr else "RGB", 4: "BGRA" if bgr else "RGBA"}[array.shape[2]]
    h, w = array.shape[:2]
    array = array[: h - h % 2, : w - w % 2]
    fmt = f"{array.dtype} {channels}"
    if array.dtype == np.uint8 and array.shape[2] == 3:
        # (a video's frames: the planes split and stacked in RGB order, then converted, gives the same values three
        # times faster than converting (H, W, 3) and flipping and permuting the floats: 11.5 -> 3.7 ms at 1080p), and
        # divided in place, the same values (no second 25 MB float frame: about 6 -> 4.4 ms of CPU a 1080p frame)
        planes = cv2.split(array)
        chw = np.stack(planes[::-1] if bgr else planes)
        return torch.from_numpy(chw).to(torch.float32).div_(255.0), fmt
    if array.dtype == np.uint8:
        # a read-only array (np.frombuffer's, of an ffmpeg pipe's bytes) is copied: torch warned that it "does not
        # support non-writable tensors" for a tensor converted to float32 right away
        data = torch.from_numpy(np.ascontiguousarray(array) if array.flags.writeable else array.copy())
        data = data.to(torch.float32).div_(255.0)
    elif array.dtype == np.uint16:
        data = torch.from_numpy(array.astype(np.float32)).div_(65535.0)
    else:
        data = torch.from_numpy(array.astype(np.float32))
    if data.shape[2] == 1:
        data = data.expand(-1, -1, 3)
    elif data.shape[2] == 4:
        data = data[:, :, :3]
    if bgr:
        data = data.flip(2)
    return data.permute(2, 0, 1).contiguous(), fmt


def _bgr_image(array: np.ndarray, bgr: bool) -> np.ndarray | None:
    """The ``(H, W, 3)`` uint8 BGR image whose :func:`frame_to_tensor` frame ``f`` gives it back exactly as
    ``round(clamp(f, 0, 1) * 255)`` (in float32 or float64: ``k / 255`` rounds back to ``k`` for every 8-bit ``k``),
    so that what draws on the frame need not convert it back: ``array`` itself where it is such an image of even
    width and height (a video's decoded frames, an image folder's colour images), else None (another format, RGB
    order, or a frame that ``convert`` crops)."""
    ok = isinstance(array, np.ndarray) and array.dtype == np.uint8 and array.ndim == 3 and array.shape[2] == 3
    return array if ok and bgr and array.shape[0] % 2 == 0 and array.shape[1] % 2 == 0 else None


def _conversion(array: np.ndarray, fmt: str, problems: list[str]) -> str:
    """Describe what ``convert=True`` did to a frame with these problems (empty if nothing)."""
    if not problems:
        return ""
    done = []
    if any(not q.startswith("odd size") for q in problems):
        done.append(f"{fmt} -> RGB")
    h, w = array.shape[:2]
    if h % 2 or w % 2:
        done.append(f"cropped {w}x{h} to {w - w % 2}x{h - h % 2}")
    return "; ".join(done)


class FrameReader:
    """Iterate the frames of one input as ``(3, H, W)`` float32 RGB tensors; use :func:`open_frames`.

    Validation happens as frames are read: a frame of another stored size than the first, or (without
    ``convert``) a grayscale, RGBA, 16-bit or odd-sized frame, raises :class:`InputError` naming its index.
    :attr:`frames_read` counts the frames returned so far; :attr:`image` is the 8-bit BGR image the last one was
    converted from (:func:`_bgr_image`); :attr:`timestamp` is the time of the last one in seconds:
    the container's (``clock``, milliseconds of the frame just read: ``CAP_PROP_POS_MSEC``) where it is a number,
    at least 0 and later than the previous frame's, else the last such time plus ``1 / fps`` per frame since (the
    first frame: 0). So a variable-frame-rate video's frames get their own times, and the frames of an image
    folder, an array, or a container that gives no times, ``frame / fps``.
    """

    def __init__(
        self,
        info: VideoInfo,
        first: Tensor,
        rest: Iterator[tuple[np.ndarray, bool]],
        closer=None,
        stored_size: tuple[int, int] | None = None,
        convert: bool = False,
        files: list[Path] | None = None,
        clock: Callable[[], float] | None = None,
        first_image: np.ndarray | None = None,
    ) -> None:
        self.info = info
        self.image: np.ndarray | None = None  # (_bgr_image of the last frame returned)
        self._first_image = first_image
        self.clock = clock
        self.timestamp: float | None = None  # (seconds) of the last frame returned; None before the first
        self._timed = (0, 0.0)  # (frame, seconds) of the last frame timed by the container
        self._files = files
        self.stored_size = stored_size or (info.height, info.width)
        self.convert = convert
        self._first: Tensor | None = first
        self._rest = rest
        self._closer = closer
        self.frames_read = 0

    def __iter__(self) -> "FrameReader":
        return self

    def __next__(self) -> Tensor:
        if self._first is not None:
            frame, self._first = self._first, None
            self.image, self._first_image = self._first_image, None
            self.frames_read = 1
            self._stamp()
            return frame
        array, bgr = next(self._rest)
        where = f"{self.info.path}: frame {self.frames_read}"
        if self._files is not None:  # an image folder: name the file too
            where += f" ({self._files[self.frames_read].name})"
        if isinstance(array, np.ndarray) and array.ndim >= 2 and tuple(array.shape[:2]) != self.stored_size:
            raise InputError(
                f"{where} is {array.shape[1]}x{array.shape[0]} but the video started at "
                f"{self.stored_size[1]}x{self.stored_size[0]} (the frame size must not change)"
            )
        frame, _ = frame_to_tensor(array, bgr, where, self.convert)
        self.image = _bgr_image(array, bgr)
        self.frames_read += 1
        self._stamp()
        return frame

    def _stamp(self) -> None:
        """Set :attr:`timestamp` of the frame just returned (frame ``frames_read - 1``)."""
        k = self.frames_read - 1
        ms = math.nan
        if self.clock is not None:
            try:
                ms = float(self.clock())
            except (TypeError, ValueError):
                ms = math.nan
        seconds = ms / 1000.0
        if math.isfinite(seconds) and seconds >= 0 and (self.timestamp is None or seconds > self.timestamp):
            self._timed = (k, seconds)
            self.timestamp = seconds
        else:  # (no time, or one that does not go forward: the container's last plus 1 / fps per frame)
            at, when = self._timed
            self.timestamp = when + (k - at) / self.info.fps

    def close(self) -> None:
        """Release the underlying decoder, and the frames not read (a ``.npy`` array's mapping: it held the file
        open after ``close``); the reader returns no more frames."""
        if self._closer is not None:
            self._closer()
            self._closer = None
        self._first, self._rest = None, iter(())
        self.image = self._first_image = None

    def __enter__(self) -> "FrameReader":
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _given_rate(info: VideoInfo, fps: float | None) -> VideoInfo:
    """``info`` with the rate ``fps`` (:func:`open_frames`' ``fps``) where its own is assumed (``fps_assumed``) and
    ``fps`` is given; else ``info`` as it is."""
    if fps is None or not info.fps_assumed:
        return info
    return replace(info, fps=float(fps), fps_assumed=False, fps_given=True)


def _video_frames(cap: cv2.VideoCapture) -> Iterator[tuple[np.ndarray, bool]]:
    while True:
        ok, img = cap.read()
        if not ok:
            return
        yield img, True


def _natural_key(name: str) -> tuple:
    """Sort key that compares runs of digits as numbers: ``2.png`` before ``10.png``."""
    parts = re.split(r"([0-9]+)", name)  # ASCII digits only ('²' is a digit to str.isdigit but no number)
    return tuple((0, int(x), "") if x.isascii() and x.isdecimal() else (1, 0, x) for x in parts if x), name


def image_files(folder: str | os.PathLike[str]) -> list[Path]:
    """The frames of an image folder in playing order: files with a suffix of :data:`IMAGE_SUFFIXES` (any case),
    hidden files (names starting with ``.``, e.g. macOS's ``._0001.png``) left out, sorted by name with runs of
    digits compared as numbers (``1.png, 2.png, ..., 10.png``, as ``ffmpeg -i clip.mp4 %d.png`` names them;
    zero-padded names sort as they read).

    Example:
        >>> # image_files("frames") -> [frames/1.png, frames/2.png, frames/10.png]
    """
    files = [
        f for f in Path(folder).iterdir()
        if f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith(".") and f.is_file()
    ]
    return sorted(files, key=lambda f: _natural_key(f.name))


def folder_of_videos_hint(folder: str | os.PathLike[str], usage: str = "give each file as an input") -> str:
    """What to say of a folder given as one input that holds video files or ``.npy`` arrays (``VIDEO_SUFFIXES``,
    hidden files left out) rather than frames: ``" but 11 videos (bbaf2n.mpg, brbk7n.mpg, ...): ..."`` ending in
    ``usage``, with the glob that names them; ``""`` where it holds none. A folder is one input, its images the
    frames of one video (a folder of videos was told only that it "holds no images").

    Example:
        >>> # folder_of_videos_hint("clips") -> " but 2 videos (a.mp4, b.mp4): ... (clips/*.mp4)"
    """
    p = Path(folder)
    try:
        found = [f for f in p.iterdir() if f.suffix.lower() in VIDEO_SUFFIXES and not f.name.startswith(".")
                 and f.is_file()]  # fmt: skip
    except OSError:
        return ""
    if not found:
        return ""
    found.sort(key=lambda f: _natural_key(f.name))
    names = ", ".join(f.name for f in found[:3]) + (", ..." if len(found) > 3 else "")
    # one glob per suffix (.mp4 and .MP4 each: '*' named the folder's other files too), the folder quoted as a shell
    # needs it ('my clips'/*.mp4: my clips/*.mp4 was two words)
    folder = shlex.quote(str(p)) + os.sep
    glob = " ".join(f"{folder}*{suffix}" for suffix in sorted({f.suffix for f in found}))
    return f" but {counted(len(found), 'video')} ({names}): a folder is one video of image frames; {usage} ({glob})"


def opencv_path(path: str | os.PathLike[str], error: type[Exception] = InputError) -> str:
    """``path`` as the ``str`` OpenCV takes, refused with ``error`` where its name is not valid UTF-8 (bytes that
    Python keeps as lone surrogates, ``'clip\\udcff.avi'``): OpenCV crashed the process on such a name (a
    segmentation fault), whatever the locale."""
    text = os.fspath(path)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise error(f"{text!r}: the name is not valid UTF-8, and OpenCV cannot open such a file: rename it "
                    "(e.g. convmv -f latin1 -t utf8)") from None  # fmt: skip
    return text


def open_capture(path: str | os.PathLike[str], error: type[Exception] = InputError) -> cv2.VideoCapture:
    """A ``cv2.VideoCapture`` of a video file whose frames come out as a viewer shows them: turned by the
    container's display rotation (a phone video's ``rotate`` tag or display matrix, 90, 180 or 270 degrees), so a
    portrait video stored landscape reads as portrait frames (``CAP_PROP_ORIENTATION_AUTO`` set on: OpenCV 4.11
    left it off by default, where 4.10 and 4.12 turn the frames, so the orientation depended on the OpenCV
    installed). A name that is not valid UTF-8 is refused with ``error`` (:func:`opencv_path`); whether the file
    opened is for the caller to check (``isOpened``).

    Example:
        >>> # cap = open_capture("portrait.mp4"); ok, bgr = cap.read()   # bgr: (H, W, 3) as displayed
    """
    cap = cv2.VideoCapture(opencv_path(path, error))
    cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)  # before the first read (a backend without it returns False)
    return cap


def _image_frames(files: list[Path]) -> Iterator[tuple[np.ndarray, bool]]:
    for f in files:
        img = cv2.imread(opencv_path(f), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"{f}: cannot decode this image")
        yield img, True


def _array_frames(array: np.ndarray) -> Iterator[tuple[np.ndarray, bool]]:
    for frame in array:
        yield np.array(frame), False  # read from the mapped file one frame at a time


def _check_size(path: Path, frame: Tensor) -> None:
    h, w = frame.shape[-2:]
    if h < MIN_SIZE or w < MIN_SIZE:
        raise InputError(f"{path}: frames are {w}x{h}; at least {MIN_SIZE}x{MIN_SIZE} pixels are needed")


def _fourcc(cap: cv2.VideoCapture) -> str:
    code = int(cap.get(cv2.CAP_PROP_CODEC_PIXEL_FORMAT) or 0) & 0xFFFFFFFF
    return "".join(chr((code >> (8 * k)) & 0xFF) for k in range(4))


def _stored_layout(p: Path, cap: cv2.VideoCapture, decoded: np.ndarray) -> np.ndarray:
    """An array with the stored layout (size, channels, dtype) of a video's first frame; values unused.

    Grayscale comes from the pixel-format FourCC; RGBA and 16-bit colour from the undecoded first frame,
    read through a second capture only for RGB-type FourCCs (OpenCV warns on undecoded YUV frames).
    """
    h, w = decoded.shape[:2]
    tag = _fourcc(cap)
    if tag in _GRAY_FOURCCS:
        deep = tag in ("Y1\x00\x10", "\x10\x001Y", "Y16 ")
        return np.empty((h, w), np.uint16 if deep else np.uint8)
    if tag not in _RGB_FOURCCS:
        return decoded
    probe = open_capture(p)  # turned as the frames are (else a rotated video's probe did not match them)
    try:
        probe.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        ok, raw = probe.read()
    finally:
        probe.release()
    if not ok or raw is None or raw.ndim != 3 or tuple(raw.shape[:2]) != (h, w) or raw.shape[2] not in (3, 4):
        return decoded
    if raw.shape[2] == 4 and int(raw[..., 3].min()) == np.iinfo(cast("np.dtype[np.integer]", raw.dtype)).max:
        raw = raw[..., :3]  # opaque alpha: colour padding (OpenCV writes FFV1 colour as BGRA)
    return raw


def open_frames(path: str | os.PathLike[str], convert: bool = False, fps: float | None = None) -> FrameReader:
    """Open a video file, an image folder or a ``.npy`` array and read its first frame.

    Args:
        path: the input.
        convert: convert grayscale, RGBA, 16-bit and odd-sized frames (:func:`frame_to_tensor`) instead of
            rejecting them.
        fps: the frame rate (a finite number > 0, frames per second) of an input that has none of its own (an
            image folder, an array, a single image file, a video whose container gives no plausible rate: those
            whose :class:`VideoInfo` ``fps_assumed`` would be True), used instead of the default 25: the frames'
            :attr:`~FrameReader.timestamp` are ``frame / fps`` (a container's own times are still taken where it
            gives them), ``info.fps`` is it, ``fps_assumed`` False and ``fps_given`` True. A video's own rate is
            kept (``fps_given`` False: compare ``info.fps_given`` to tell). None (the default): 25 for them.

    Returns:
        A :class:`FrameReader` whose :attr:`~FrameReader.info` describes the input (its ``width`` and
        ``height`` are those of the returned frames, after any crop).

    Raises:
        InputError: missing path, nothing decodable, zero frames, an unsupported frame format, a frame
            smaller than :data:`MIN_SIZE`, or (without ``convert``) a grayscale, RGBA, 16-bit or odd-sized
            first frame.
        TypeError: ``convert`` not a bool (``"no"`` was taken as true), ``fps`` not a real number.
        ValueError: ``fps`` not finite and > 0.

    Example:
        >>> # with open_frames("clip.mp4") as frames: first = next(frames)   # (3, H, W)
    """
    fps = check_number(fps, "fps", "(0, inf)", True, "frames per second")  # (before the input is opened)
    convert = check_bool(convert, "convert")  # (open_frames(path, "no") converted: any truthy value did)
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file or folder{missing_path_hint(path)}")
    if p.is_dir():
        files = image_files(p)
        if not files:
            videos = folder_of_videos_hint(p)
            if videos:
                raise InputError(f"{p}: folder holds no images ({', '.join(IMAGE_SUFFIXES)}){videos}")
            raise InputError(f"{p}: folder holds no images ({', '.join(IMAGE_SUFFIXES)}): zero frames")
        for f in files:  # before the first frame, not when the run reaches that one
            opencv_path(f)
        rest = _image_frames(files)
        first_arr, _ = next(rest)
        first, fmt = frame_to_tensor(first_arr, True, f"{files[0]}", convert)
        first_image = _bgr_image(first_arr, True)
        _check_size(p, first)
        conv = _conversion(first_arr, fmt, format_problems(first_arr))
        info = VideoInfo(p, "images", first.shape[-1], first.shape[-2], ASSUMED_FPS, len(files), fmt, conv, True)
        info = _given_rate(info, fps)
        return FrameReader(info, first, rest, stored_size=first_arr.shape[:2], convert=convert, files=files,
                           first_image=first_image)  # fmt: skip
    if p.suffix.lower() == ".npy":
        try:
            # Mapped, not read: frames are read as they are tracked, so that a long clip does not have to fit in
            # memory (it used to be loaded whole before the first frame was tracked).
            array = np.load(p, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:  # EOFError: an empty file (np.save interrupted)
            raise InputError(f"{p}: not a readable .npy array ({exc})") from None
        if not isinstance(array, np.ndarray):  # an .npz archive under an .npy name (np.savez): AttributeError 'ndim'
            array.close()
            raise InputError(f"{p}: an .npz archive of arrays ({', '.join(array.files)[:60]}), not one .npy array: "
                             "save the frames with np.save")  # fmt: skip
        if array.ndim not in (3, 4):
            raise InputError(f"{p}: expected a (T, H, W) or (T, H, W, C) array, got shape {array.shape}")
        if array.shape[0] == 0:
            raise InputError(f"{p}: zero frames")
        if array.ndim == 3 and array.shape[2] in (3, 4) and min(array.shape[:2]) > 4:
            # (H, W, C): one colour image, not a clip of W-pixel-high gray frames
            raise InputError(f"{p}: shape {array.shape} looks like one colour image; a clip is (T, H, W, C): save "
                             "it as array[None] (or (T, H, W) for gray frames)")  # fmt: skip
        if array.ndim == 4 and array.shape[1] in (1, 3, 4) and array.shape[3] not in (1, 3, 4):
            # (T, C, H, W): frames as PyTorch holds them (a tensor's .numpy()); it said "frame 0: expected an (H, W)
            # or (H, W, 1|3|4) image, got shape (3, H, W)"
            raise InputError(f"{p}: shape {array.shape} looks like channels-first frames (T, C, H, W), as PyTorch "
                             "holds them; a clip is (T, H, W, C): save it as array.transpose(0, 2, 3, 1)")  # fmt: skip
        rest = _array_frames(array[1:])
        try:
            first, fmt = frame_to_tensor(np.array(array[0]), False, f"{p}: frame 0", convert)
        except InputError as exc:  # (an array is told how to save it, not the ffmpeg command of a video file)
            text = str(exc)
            if not text.endswith(CONVERT_HINT):
                raise
            head = text[: -len(CONVERT_HINT)]
            raise InputError(head + array_convert_hint(head.rsplit(": frames are ", 1)[-1])) from None
        _check_size(p, first)
        conv = _conversion(array[0], fmt, format_problems(array[0]))
        info = VideoInfo(p, "array", first.shape[-1], first.shape[-2], ASSUMED_FPS, int(array.shape[0]), fmt, conv,
                         True)  # fmt: skip
        info = _given_rate(info, fps)
        return FrameReader(info, first, rest, stored_size=array.shape[1:3], convert=convert)
    if not os.access(p, os.R_OK):
        raise InputError(f"{p}: permission denied")
    cap = open_capture(p)
    if not cap.isOpened():
        cap.release()
        raise InputError(f"{p}: not a video OpenCV can open (unreadable, corrupt or an unknown format)")
    ok, img = cap.read()
    if not ok or img is None:
        cap.release()
        raise InputError(f"{p}: no frame could be decoded (zero frames, or a corrupt video)")
    try:
        stored = _stored_layout(p, cap, img)
        problems = format_problems(stored)
        if problems and not convert:
            raise InputError(_problem_message(f"{p}", problems))
        first, _ = frame_to_tensor(img, True, f"{p}: frame 0", convert)
        first_image = _bgr_image(img, True)
        _check_size(p, first)
    except BaseException:  # any failure: the decoder was kept open by the traceback for as long as it was held
        cap.release()
        raise
    channels = 1 if stored.ndim == 2 else stored.shape[2]
    fmt = f"{stored.dtype} {({1: 'gray', 3: 'BGR', 4: 'BGRA'})[channels]}"
    conv = _conversion(stored, fmt, problems)
    rate = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    count = float(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0.0)  # -1 or garbage (-1.9e14: a raw .mjpeg) when unknown
    assumed = not (math.isfinite(rate) and PLAUSIBLE_FPS[0] < rate < PLAUSIBLE_FPS[1])
    implausible = rate if assumed and math.isfinite(rate) and rate > 0 else None  # (0 or -1: none declared)
    declared = int(count) if math.isfinite(count) and count >= 1 else None
    if p.suffix.lower() in IMAGE_SUFFIXES:  # one image, read as a video of one frame: FFmpeg's image demuxer gave
        assumed, declared, implausible = True, 1, None  # 25 frames/s as the input's own (the JSON's fps_assumed
        # false) and no count
    rate = ASSUMED_FPS if assumed else rate
    info = _given_rate(VideoInfo(p, "video", first.shape[-1], first.shape[-2], rate, declared, fmt, conv, assumed,
                                 declared_fps=implausible), fps)  # fmt: skip
    return FrameReader(info, first, _video_frames(cap), cap.release, stored_size=img.shape[:2], convert=convert,
                       clock=lambda: cap.get(cv2.CAP_PROP_POS_MSEC), first_image=first_image)  # fmt: skip
