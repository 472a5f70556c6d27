"""Frames to normalised faces: the tracking core shared by the datasets and the :class:`NormaliseFaces` transform.

A sequence of frames is tracked from its first frame's 68 iBUG landmarks (NaN rows: missing points), or continued
from a :class:`~torchface.tracker.TrackerState`, with the functional tracker as :class:`~torchface.tracker.FaceTracker`
runs it (:func:`~torchface.tracker.managed.initialise_managed`, :func:`~torchface.tracker.managed.managed_step`:
template management as ``TrackerConfig.template`` says; lost streams recover by the mosaic search, no
detector), one stream at a time (``B = 1``), and every frame is resampled into the normalised face
(:func:`~torchface.normalise.normalised_face`: frontal, neutral expression, reference light) with the state
of that frame. The result, :class:`TrackedSequence`, holds per frame the normalised face
and its mask, the tracked parameters, the confidence and the status: what the disk cache stores
(:mod:`training_hooks.cache`) and what dataset items are cut from.

Determinism: tracking runs with a fixed number of torch threads (:attr:`FaceTrackingConfig.num_threads`, set
for the duration of the tracking and restored afterwards), so a sequence gives bit-identical results in the
main process and in any ``DataLoader`` worker (workers run with one thread by default, the main process with
as many as there are cores, and float reductions depend on the split).

Storage: faces are kept as :class:`FaceStorage` (uint8 by default: clamped to ``[0, 1]`` and rounded to
``1 / 255``; items are float32 again), so freshly tracked items equal the cached ones bit for bit.

Shapes: ``T`` frames, ``C`` channels (3, or 1 for gray frames), ``S`` the normalised-face side
(:attr:`FaceTrackingConfig.face_size`), ``A`` animation units, ``L`` illumination terms, ``H x W`` frames; conventions
of :mod:`torchface.conventions`.
"""

from __future__ import annotations

import enum
import numbers
import os
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchface.appearance.illumination import NUM_ILLUMINATION_TERMS
from torchface.extending import check_bool, check_choice, check_int, check_no_tilde, check_number
from torchface.geometry.camera import Intrinsics
from torchface.io.landmarks import landmarks_shape_hint as _landmarks_shape_hint
from torchface.io.landmarks import missing_points_problem, planar_layout_problem
from torchface.model.candide import load_candide3
from torchface.model.face_model import FaceModel
from torchface.model.model_file import load_face_model
from torchface.normalise.face import NormalisedFace
from torchface.tracker.lookahead import LookaheadConfig, check_refine_first
from torchface.tracker.params import ParamLayout
from torchface.tracker.managed import initialise_managed, managed_step
from torchface.tracker.module import (
    auto_levels, check_continuing_levels, check_pyramid, continuing_config, note_auto_levels,
)
from torchface.tracker.step import (
    TrackerConfig, TrackerState, check_frames, not_tensor_hint, pyramid_for_faces, usable_status,
)  # fmt: skip

__all__ = [
    "FaceStorage",
    "FaceTrackingConfig",
    "NormaliseFaces",
    "PER_FRAME_KEYS",
    "TrackedSequence",
    "torch_threads",
    "track_sequence",
]

#: Item keys that carry one value per frame (a leading ``T`` in clip items); see :meth:`TrackedSequence.item`.
PER_FRAME_KEYS: tuple[str, ...] = (
    "face", "mask", "rotation", "axis_angle", "translation", "ypr_deg", "anim_coeffs", "expression", "facs",
    "illumination", "confidence", "success", "status", "frame",
)  # fmt: skip


class FaceStorage(enum.Enum):
    """How normalised faces are stored (in :class:`TrackedSequence` and in the disk cache)."""

    #: Clamped to ``[0, 1]`` and rounded to multiples of ``1 / 255``: a quarter of float32's size, the fastest
    #: to read back. The default.
    UINT8 = "uint8"
    #: Half precision, not clamped (light removal can exceed 1 where the light model does not fit).
    FLOAT16 = "float16"
    #: Full precision, not clamped.
    FLOAT32 = "float32"

    @property
    def dtype(self) -> torch.dtype:
        """The torch dtype of stored faces."""
        return {"uint8": torch.uint8, "float16": torch.float16, "float32": torch.float32}[self.value]


@dataclass(frozen=True)
class FaceTrackingConfig:
    """How a sequence of frames becomes normalised faces (part of the disk cache's key: change any field and
    cached results are not reused).

    Attributes:
        tracker: the tracker's settings (:class:`~torchface.tracker.TrackerConfig`; CANDIDE-3 with its 11
            animation units, float32).
        face_size: ``S``, the normalised face is ``S x S`` (at least 16; 128, as
            :attr:`LayerConfig.size <training_hooks.layer.LayerConfig.size>` and
            :class:`~torchface.normalise.NormalisedFace`'s ``size`` by default).
        face_margin: fraction of ``S`` left around the face (:func:`~torchface.normalise.build_normalised_layout`).
        face_storage: :class:`FaceStorage` of the faces (``UINT8``: clamped to ``[0, 1]``; the float faces of
            :class:`~training_hooks.layer.NormalisedFaceLayer` and :class:`~torchface.normalise.NormalisedFace` are
            not clamped, to keep their gradient: ``image.clamp(0, 1)`` gives them this range).
        focal: focal length in pixels of the frames' camera; ``None`` is ``max(W, H)``
            (:meth:`~torchface.geometry.camera.Intrinsics.default`).
        num_threads: torch threads while tracking (restored afterwards). A fixed count makes the results
            independent of the process that tracks (module docstring); 1 suits ``DataLoader`` workers.
        keep_expression: resample at the person's neutral expression (the first frame's fitted coefficients,
            ``TrackerState.neutral_anim_coeffs``) instead of the tracked one, so the face keeps its expression
            (pose and light still undone): the input an expression classifier needs. False (the default) undoes
            the expression too.
        refine_first: the online look-ahead start of a sequence tracked from landmarks
            (:func:`~torchface.tracker.managed.initialise_managed`, as :class:`~torchface.tracker.FaceTracker`
            starts by default: the first pose and the shape units the landmark fit held are re-estimated once the
            head has turned), or None. Used with template management on.
        pyramid: ``"auto"`` (the default) tracks a sequence started from landmarks with the pyramid
            ``torchface track`` and :class:`~torchface.tracker.FaceTracker` give it: a coarser level added per
            doubling of its first face over the default pyramid's (:func:`~torchface.tracker.pyramid_for_faces`;
            HD video, where the default three levels lost fast motion; faces under 254.5 pixels keep ``tracker``),
            and a :class:`~torchface.tracker.TrackerState` continued with the levels it holds beyond
            ``tracker``'s. ``"config"``: ``tracker.num_levels`` as given. The state :func:`track_sequence` returns
            says which (:attr:`~torchface.tracker.TrackerState.num_levels`).
        model: a face model file (:func:`torchface.model.save_face_model` writes one, as for ``torchface track
            --model``) that :class:`NormaliseFaces` and the datasets track with, loaded in float32 with
            :func:`torchface.model.load_face_model`, or None for CANDIDE-3. The first-frame landmarks are then the
            model's ``K``, in its order (a detector's 68 iBUG points need a model of those). In the ``repr`` only
            when given (a config without one has the ``repr`` it had before this field); the cache key hashes the
            ``repr`` without it and the file's content instead (:func:`~training_hooks.cache.cache_key`: the same
            file moved keeps its sequences). Kept as an absolute ``Path``, as :attr:`DatasetConfig.cache_dir
            <training_hooks.datasets.DatasetConfig.cache_dir>` is: a relative one is taken against the working folder
            when the config is made, so a model loaded after an ``os.chdir`` (Lightning, Hydra) or in a
            ``DataLoader`` worker is the file it named; one that starts with a ``~`` that expands is refused (give
            ``os.path.expanduser(path)``), as :attr:`DatasetConfig.cache_dir
            <training_hooks.datasets.DatasetConfig.cache_dir>` refuses it.
    """

    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    face_size: int = 128
    face_margin: float = 0.05
    face_storage: FaceStorage = FaceStorage.UINT8
    focal: float | None = None
    num_threads: int = 1
    keep_expression: bool = False
    refine_first: LookaheadConfig | None = field(default_factory=LookaheadConfig)
    pyramid: str = "auto"
    model: str | os.PathLike[str] | None = field(default=None, repr=False)  # stored as an absolute Path

    def __post_init__(self) -> None:
        if self.model is not None and not isinstance(self.model, (str, os.PathLike)):
            raise TypeError(f"model must be a path to a face model file or None, got {type(self.model).__name__}")
        if self.model is not None:  # (a relative one was read against the working folder when first loaded)
            if isinstance(self.model, str) and not self.model:  # (Path("") is the working folder)
                raise ValueError("model is empty: give a face model file, or None for CANDIDE-3")
            check_no_tilde(self.model, "model")  # (made absolute as <cwd>/~/...: "no such file" at the first load)
            object.__setattr__(self, "model", Path(self.model).absolute())
        if not isinstance(self.tracker, TrackerConfig):
            raise TypeError(f"tracker must be a TrackerConfig, got {type(self.tracker).__name__}")
        check_pyramid(self.pyramid)
        check_refine_first(self.refine_first)
        object.__setattr__(self, "face_size", check_int(self.face_size, "face_size", 16))
        object.__setattr__(self, "keep_expression", check_bool(self.keep_expression, "keep_expression"))
        # ("0.05" and focal="300" were taken, strs; focal=inf passed "> 0")
        object.__setattr__(self, "face_margin", check_number(self.face_margin, "face_margin", "[0, 0.45]", unit="a fraction of the image size"))
        object.__setattr__(self, "focal", check_number(self.focal, "focal", "(0, inf)", True, "pixels"))
        check_choice(self.face_storage, "face_storage", FaceStorage)
        object.__setattr__(self, "num_threads", check_int(self.num_threads, "num_threads", 1))

    def __repr__(self) -> str:
        """The dataclass ``repr``, with ``model`` last when it is given (a printed config hid the model); without
        it, the ``repr`` of before the field, which :func:`~training_hooks.cache.cache_key` hashes."""
        shown = [f"{f.name}={getattr(self, f.name)!r}" for f in fields(self) if f.repr]
        shown += [] if self.model is None else [f"model={self.model!r}"]
        return f"{type(self).__qualname__}({', '.join(shown)})"


@contextmanager
def torch_threads(num_threads: int) -> Iterator[None]:
    """Run the block with ``torch.set_num_threads(num_threads)`` and restore the previous count afterwards.

    Example:
        >>> with torch_threads(1):
        ...     torch.get_num_threads()
        1
    """
    previous = torch.get_num_threads()
    if previous != num_threads:
        torch.set_num_threads(num_threads)
    try:
        yield
    finally:
        if torch.get_num_threads() != previous:
            torch.set_num_threads(previous)


def decode_faces(faces: Tensor) -> Tensor:
    """Stored faces (any :class:`FaceStorage`) -> float32 in the image range (uint8 divided by 255).

    Converted with NumPy on one thread: a per-item conversion must not wake torch's intra-op thread pool in a
    busy main process (measured 20x slower per face there than in a single-threaded worker).
    """
    if faces.dtype == torch.uint8:
        return torch.from_numpy(np.divide(faces.numpy(), np.float32(255.0), dtype=np.float32))
    return faces.to(torch.float32)


def encode_faces(faces: Tensor, storage: FaceStorage) -> Tensor:
    """Float faces -> :class:`FaceStorage` (uint8: clamped to ``[0, 1]``, rounded to ``1 / 255``)."""
    if storage is FaceStorage.UINT8:
        return (faces.detach().clamp(0.0, 1.0) * 255.0).round_().to(torch.uint8)
    return faces.detach().to(storage.dtype)


@dataclass(frozen=True, eq=False)
class TrackedSequence:
    """Per-frame tracking results and normalised faces of one sequence (CPU tensors, ``T >= 1`` frames).

    Attributes:
        faces: ``(T, C, S, S)`` normalised faces in :class:`FaceStorage` dtype (:func:`decode_faces` for float).
        masks: ``(T, 1, S, S)`` bool, True where the canonical point is visible in the frame.
        rotation: ``(T, 3, 3)`` float32 head -> camera rotation (OpenCV camera frame).
        axis_angle: ``(T, 3)`` float32 the same as axis-angle vectors (radians).
        translation: ``(T, 3)`` float32 head origin in the camera frame (mm).
        ypr_deg: ``(T, 3)`` float32 yaw, pitch, roll in degrees (:mod:`torchface.conventions`).
        anim_coeffs: ``(T, A)`` float32 the model's animation-unit coefficients (they place the mesh).
        expression: ``(T, A)`` float32 the animation units measured from the person's neutral, the first frame's
            fitted coefficients (``TrackResult.expression``: 0 on the first frame).
        facs: ``(T, F)`` float32 linked FACS action-unit values (of ``expression``).
        illumination: ``(T, L)`` float32 illumination parameters (gain, bias, light x/y/z; paper Eq. 19).
        confidence: ``(T,)`` float32 in ``[0, 1]`` (``TrackResult.confidence``: the dissimilarity confidence with
            template management, else the solver's residual confidence).
        status: ``(T,)`` int64 :class:`~torchface.tracker.TrackStatus` (2 = FAILED: parameters held, 3 = LOST).
        shape_coeffs: ``(S_u,)`` float32 the person's shape units after the last frame: the first frame's landmark
            fit's, unless the online look-ahead start (:attr:`FaceTrackingConfig.refine_first`, the default)
            re-estimated them once the head had turned (by up to 0.21 on a rendered 30-degree turn); the frames before
            were normalised with the fit's. The per-frame pose is then reported in the head frame of the first result
            (``TrackResult.rotation``), so that it stays continuous: with these units it places the mesh near, not
            exactly on, the one the faces were resampled from.
        landmarks: ``(K, 2)`` float64 landmarks of the frame the tracking started from (:attr:`first_frame`;
            pixels; the model's ``K``, 68 for CANDIDE-3; a NaN row for a missing point), or ``(0, 2)`` when it
            continued from a :class:`~torchface.tracker.TrackerState`.
        frame_size: ``(H, W)`` of the frames.
        first_frame: index of the first frame in the tracked sequence: 0 when the tracking started here from
            landmarks, the state's :attr:`~torchface.tracker.TrackerState.frame_index` (frames it had seen) when
            it continued a :class:`~torchface.tracker.TrackerState`, the video's frame where a dataset's detector
            found the first face (:meth:`VideoDataset.sequence <training_hooks.datasets.VideoDataset.sequence>`);
            items' ``frame`` counts from it.
    """

    faces: Tensor
    masks: Tensor
    rotation: Tensor
    axis_angle: Tensor
    translation: Tensor
    ypr_deg: Tensor
    anim_coeffs: Tensor
    expression: Tensor
    facs: Tensor
    illumination: Tensor
    confidence: Tensor
    status: Tensor
    shape_coeffs: Tensor
    landmarks: Tensor
    frame_size: tuple[int, int]
    first_frame: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name not in ("frame_size", "first_frame") and not isinstance(getattr(self, f.name), Tensor):
                got = type(getattr(self, f.name)).__name__
                raise TypeError(f"TrackedSequence.{f.name} must be a torch.Tensor, got {got}")
        faces = self.faces
        if faces.dim() != 4 or faces.shape[0] < 1 or faces.shape[-1] != faces.shape[-2]:
            raise ValueError(f"faces must be (T, C, S, S) with T >= 1, got {tuple(faces.shape)}")
        if faces.dtype not in (torch.uint8, torch.float16, torch.float32):
            raise ValueError(f"faces must be uint8, float16 or float32, got {faces.dtype}")
        T, _, S, _ = faces.shape
        expected = {
            "masks": ((T, 1, S, S), torch.bool), "rotation": ((T, 3, 3), torch.float32),
            "axis_angle": ((T, 3), torch.float32), "translation": ((T, 3), torch.float32),
            "ypr_deg": ((T, 3), torch.float32), "anim_coeffs": ((T, self.anim_coeffs.shape[-1]), torch.float32),
            "expression": ((T, self.anim_coeffs.shape[-1]), torch.float32),
            "facs": ((T, self.facs.shape[-1]), torch.float32),
            "illumination": ((T, NUM_ILLUMINATION_TERMS), torch.float32), "confidence": ((T,), torch.float32),
            "status": ((T,), torch.int64), "shape_coeffs": ((self.shape_coeffs.shape[-1],), torch.float32),
            "landmarks": ((self.landmarks.shape[0], 2), torch.float64),
        }  # fmt: skip
        for name, (shape, dtype) in expected.items():
            x = getattr(self, name)
            if tuple(x.shape) != shape or x.dtype != dtype:
                raise ValueError(f"{name} must be {shape} {dtype} (T = {T}, S = {S}), got {tuple(x.shape)} {x.dtype}")
        if len(self.frame_size) != 2 or any(int(v) < 1 for v in self.frame_size):
            raise ValueError(f"frame_size must be (H, W), got {self.frame_size}")
        object.__setattr__(self, "first_frame", check_int(self.first_frame, "first_frame", 0))
        finite = [self.confidence, self.axis_angle, self.translation, self.anim_coeffs, self.expression,
                  self.illumination]
        if not all(bool(torch.isfinite(x).all()) for x in finite):
            raise ValueError("tracked parameters and confidence must be finite")

    @property
    def num_frames(self) -> int:
        """``T``."""
        return int(self.faces.shape[0])

    @property
    def success(self) -> Tensor:
        """``(T,)`` bool: the frame's estimate is usable (status neither FAILED nor LOST)."""
        return usable_status(self.status)

    def item(self, frames: int | slice) -> dict[str, Tensor]:
        """The dataset item of one frame (``frames`` an int) or of a clip (a slice, step 1).

        Keys (a clip item has a leading ``T'`` on each): ``face`` ``(C, S, S)`` float32, ``mask`` ``(1, S, S)``
        float32, ``rotation`` ``(3, 3)``, ``axis_angle`` ``(3,)``, ``translation`` ``(3,)``, ``ypr_deg`` ``(3,)``,
        ``anim_coeffs`` ``(A,)``, ``expression`` ``(A,)`` (the units measured from the person's neutral, which
        ``facs`` ``(F,)`` is linked to), ``illumination`` ``(L,)``, ``confidence`` ``()`` float32,
        ``success`` ``()`` bool, ``status`` ``()`` int64, ``frame`` ``()`` int64 (index in the tracked sequence:
        :attr:`first_frame` plus the position ``frames`` selects); per sequence: ``shape_coeffs`` ``(S_u,)``. Each
        tensor is the item's own (no view of the sequence's: changing it in place changes no other item, and a
        ``DataLoader`` worker sends the item's frames, not the sequence's).
        """
        if isinstance(frames, slice):
            start, stop, step = frames.indices(self.num_frames)
            if step != 1 or stop <= start:
                raise ValueError(f"a clip is a non-empty slice with step 1, got {frames}")
            index: int | slice = slice(start, stop)
            frame = torch.arange(start, stop, dtype=torch.int64) + self.first_frame
        else:
            if isinstance(frames, bool) or not isinstance(frames, numbers.Integral) and not (
                isinstance(frames, Tensor) and frames.numel() == 1 and not frames.is_floating_point()
            ):  # (int(1.7) took frame 1 without a word)
                raise TypeError(f"frames must be an int (one frame) or a slice (a clip), got {frames!r}")
            index = int(frames)
            if not 0 <= index < self.num_frames:
                raise IndexError(f"frame {frames} out of range for a {self.num_frames}-frame sequence")
            frame = torch.tensor(index + self.first_frame, dtype=torch.int64)
        status = self.status[index]
        face = decode_faces(self.faces[index])
        if self.faces.dtype == torch.float32:  # (decode_faces hands float32 faces back as they are: a view)
            face = face.clone()
        return {
            "face": face,
            "mask": self.masks[index].to(torch.float32),
            "rotation": self.rotation[index].clone(),
            "axis_angle": self.axis_angle[index].clone(),
            "translation": self.translation[index].clone(),
            "ypr_deg": self.ypr_deg[index].clone(),
            "anim_coeffs": self.anim_coeffs[index].clone(),
            "expression": self.expression[index].clone(),
            "facs": self.facs[index].clone(),
            "illumination": self.illumination[index].clone(),
            "confidence": self.confidence[index].clone(),
            # (from this item's statuses: self.success[index] was a view of the whole sequence's T flags, computed
            # again for every item, and sent whole with each item from a DataLoader worker)
            "success": usable_status(status),
            "status": status.clone(),
            "frame": frame,
            "shape_coeffs": self.shape_coeffs.clone(),
        }


def _frame_tensor(frame: object, index: int, shape: tuple[int, int, int] | None) -> Tensor:
    """One frame ``(3, H, W)`` RGB or ``(1, H, W)`` gray, float in [0, 1] or uint8 -> ``(1, C, H, W)`` float32,
    validated; ``shape``: the first frame's ``(C, H, W)`` (None for the first), which every later one must have."""
    # (frames streamed from OpenCV, (H, W, 3) BGR arrays or tensors of them: the messages named the layout alone)
    if isinstance(frame, np.ndarray):
        hint = not_tensor_hint(frame, to_float=False, layout="(3, H, W)", one_frame=True)
        raise TypeError(f"frame {index}: frames must be torch tensors (3, H, W), got a numpy array{hint}")
    if not isinstance(frame, Tensor):
        raise TypeError(f"frame {index}: expected a (3, H, W) tensor, got {type(frame).__name__}")
    if frame.dim() != 3 or frame.shape[0] not in (1, 3):
        hint = ""
        if frame.dim() == 3 and frame.shape[-1] == 3:  # (the permute alone, of an OpenCV image, tracked BGR)
            hint = (" (channels last (H, W, 3): frame.permute(2, 0, 1); BGR as OpenCV reads it: "
                    "frame.flip(-1).permute(2, 0, 1))")
        elif frame.dim() == 3 and frame.shape[-1] == 1:  # (gray, channels last: it was told (H, W, 3) and BGR)
            hint = " (a gray frame channels last (H, W, 1): frame.permute(2, 0, 1))"
        elif frame.dim() == 3 and frame.shape[0] == 4:
            hint = " (RGBA: drop the alpha, frame[:3])"
        elif frame.dim() == 2:
            hint = " (a gray frame (H, W): frame[None])"
        raise ValueError(f"frame {index}: frames must be (3, H, W) RGB or (1, H, W) gray, got {tuple(frame.shape)}"
                         f"{hint}")  # fmt: skip
    if frame.dtype == torch.uint8:
        frame = frame.to(torch.float32) / 255.0
    elif not frame.is_floating_point():
        raise ValueError(f"frame {index}: frames must be float in [0, 1] or uint8, got {frame.dtype}")
    else:  # every frame, not only the first: a clip continued from a TrackerState has no initialisation
        try:
            check_frames(frame.unsqueeze(0), values=True)
        except ValueError as exc:
            raise ValueError(f"frame {index}: {exc}") from None
    if shape is not None and tuple(frame.shape[-2:]) != shape[1:]:
        raise ValueError(
            f"frame {index} is {frame.shape[-1]}x{frame.shape[-2]} but the sequence started at {shape[2]}x{shape[1]}"
        )
    if shape is not None and frame.shape[0] != shape[0]:  # (the faces of one sequence stack: one channel count)
        kinds = {1: "gray (1, H, W)", 3: "RGB (3, H, W)"}
        raise ValueError(f"frame {index} is {kinds[frame.shape[0]]} but the sequence started {kinds[shape[0]]}: "
                         "give one kind (a gray frame as RGB: frame.expand(3, -1, -1))")  # fmt: skip
    return frame.to(torch.float32).unsqueeze(0)


def _layout_hint(frames: Tensor) -> str:
    """How to make refused ``frames`` a ``(T, 3, H, W)`` clip (:meth:`NormaliseFaces.__call__`'s message; empty where
    nothing is to say): frames read by OpenCV or NumPy are channels last, gray or RGBA (the message named the shape
    alone)."""
    shape = tuple(frames.shape)
    if frames.dim() == 4 and shape[1] not in (1, 3, 4) and shape[-1] in (1, 3, 4):
        return " (channels last (T, H, W, C): frames.permute(0, 3, 1, 2))"
    if frames.dim() == 4 and shape[1] == 4:
        return " (RGBA: drop the alpha, frames[:, :3])"
    if frames.dim() == 3:
        return " (one frame (3, H, W): frames[None]; gray frames (T, H, W): frames[:, None])"
    if frames.dim() == 5 and shape[2] in (1, 3):  # (a batch of clips was told its shape alone)
        return (" (a batch of clips (B, T, C, H, W)? NormaliseFaces takes one clip: frames[i] with its landmarks; "
                "NormalisedFaceLayer.forward_clip takes a batch)")
    return ""


def _landmarks_tensor(landmarks: object, count: int = 68) -> Tensor:
    """``(count, 2)`` first-frame landmarks (the model's ``K``) -> float64 tensor, validated.

    ``(1, count, 2)`` (a batch of one) and ``(2 * count,)`` (``x0, y0, x1, ...``) are taken as ``(count, 2)``, as a
    dataset's entry and a landmarks file (:func:`torchface.io.check_landmarks`) are; a flat vector that is evidently
    all x then all y is refused (:func:`torchface.io.landmarks.planar_layout_problem`).

    A missing point is a NaN row, which the landmark fit gives weight 0 (as :class:`~torchface.tracker.FaceTracker`
    takes it); the rules of a landmarks file (:func:`torchface.io.landmarks.missing_points_problem`): at least
    :data:`~torchface.tracker.fit.MIN_FIT_LANDMARKS` points given, no row with one coordinate NaN, nothing infinite.
    """
    if isinstance(landmarks, np.ndarray):  # copied: a read-only array (np.load's mmap) made torch warn; and
        # contiguous: a view with a negative stride (yx[:, ::-1]) was torch's "At least one stride ... is negative"
        landmarks = torch.tensor(np.ascontiguousarray(landmarks, dtype=np.float64))
    if not isinstance(landmarks, Tensor):
        got = type(landmarks).__name__
        raise TypeError(f"landmarks must be a ({count}, 2) array or tensor, or a TrackerState, got {got}")
    if tuple(landmarks.shape) == (2 * count,):  # (x0, y0, x1, ...: all x then all y refused, as check_landmarks does)
        problem = planar_layout_problem(landmarks.detach().to(device="cpu", dtype=torch.float64).numpy(), count)
        if problem is not None:
            raise ValueError(f"landmarks: {problem}")
    if tuple(landmarks.shape) in ((1, count, 2), (2 * count,)):  # the layouts a dataset's entry, a landmarks file
        landmarks = landmarks.reshape(count, 2)  # and torchface.io.check_landmarks take: one rule (this refused them)
    if tuple(landmarks.shape) != (count, 2):
        what = "iBUG points" if count == 68 else "points, the model's landmarks,"
        shape = tuple(landmarks.shape)
        hint = _landmarks_shape_hint(shape, count)
        raise ValueError(f"landmarks must be ({count}, 2) {what} in pixels, got {shape}{hint}")
    # (too few points given: the Python API starts such a stream FAILED; a dataset's item would be junk)
    points = landmarks.detach().to(device="cpu", dtype=torch.float64).numpy()
    problem = missing_points_problem(points, "iBUG points" if count == 68 else "points")
    if problem is not None:
        raise ValueError(f"landmarks: {problem}")
    # The sequence's own CPU copy, out of any graph: the caller's float64 tensor itself was kept (a buffer refilled
    # for the next video changed the sequence's landmarks), and one that required grad failed TrackCache.store.
    return landmarks.detach().to(device="cpu", dtype=torch.float64, copy=True)


def track_sequence(
    frames: Iterable[Tensor],
    start: Tensor | np.ndarray | TrackerState,
    config: FaceTrackingConfig,
    model: FaceModel,
    normaliser: NormalisedFace,
    progress: Callable[[int], None] | None = None,
) -> tuple[TrackedSequence, TrackerState]:
    """Track a sequence frame by frame and normalise every frame (module docstring).

    Args:
        frames: ``(3, H, W)`` RGB or ``(1, H, W)`` gray frames, one kind throughout (float in ``[0, 1]`` or
            uint8), e.g. a ``(T, 3, H, W)`` tensor or a :class:`~torchface.io.FrameReader`; consumed one at a time.
            Gray frames are tracked as :class:`~torchface.tracker.FaceTracker` tracks them (the tracker works on
            gray levels either way) and give gray faces ``(T, 1, S, S)``.
        start: ``(K, 2)`` the model's ``K`` landmarks of the first frame in pixels (the 68 iBUG points for
            CANDIDE-3; tracking starts with :func:`~torchface.tracker.managed.initialise_managed`, as
            :meth:`FaceTracker.initialise <torchface.tracker.FaceTracker.initialise>` starts it; a missing point is
            a NaN row, left out of the landmark fit: at least :data:`~torchface.tracker.fit.MIN_FIT_LANDMARKS` (4)
            given, no row with one coordinate NaN, nothing infinite, as ``torchface track`` takes a file's; also
            ``(1, K, 2)`` or ``(2K,)``, as a dataset's entry and a landmarks file's NPY are taken), or a
            :class:`~torchface.tracker.TrackerState` with ``B = 1`` (from this function or from the same tracker
            settings) whose tracking the frames continue (every frame goes through
            :func:`~torchface.tracker.managed.managed_step`); the state is left as it was, so the same frames
            from it give the same sequence again.
        config: :class:`FaceTrackingConfig` (tracker settings, face size and storage, threads).
        model: the face model (float32, CPU; normally CANDIDE-3 from :func:`~torchface.model.load_candide3`).
        normaliser: a :class:`~torchface.normalise.NormalisedFace` of ``model`` with ``config``'s size and margin.
        progress: called with the number of frames done after each frame.

    Returns:
        The :class:`TrackedSequence` and the tracker state after the last frame. Continuing a state, the
        sequence's :attr:`~TrackedSequence.first_frame` is the state's ``frame_index`` (so its items' ``frame``
        numbers the frames as one tracking of the whole sequence does).

    Raises:
        TypeError, ValueError: bad frames (shape, dtype, a size change, gray after RGB or back), landmarks (shape, an
            infinite value, a row with one coordinate NaN, fewer than 4 points given) or state; no frame at all.
    """
    if not isinstance(config, FaceTrackingConfig):
        raise TypeError(f"config must be a FaceTrackingConfig, got {type(config).__name__}")
    if normaliser.layout.size != config.face_size:
        raise ValueError(f"normaliser is {normaliser.layout.size}px, config.face_size is {config.face_size}")
    state: TrackerState | None = None
    landmarks = torch.zeros(0, 2, dtype=torch.float64)
    first_frame = 0
    tracker = config.tracker  # the settings tracked with: with config.pyramid's levels (set at the first frame)
    own_state = not isinstance(start, TrackerState)  # (made here from landmarks: donated to managed_step)
    if isinstance(start, TrackerState):
        if start.params.shape[0] != 1:
            B = start.params.shape[0]
            raise ValueError(f"a TrackerState to continue must hold one stream (B = 1), got B = {B}")
        kept = (start.params.dtype, start.params.device)
        if kept != (model.dtype, model.device):  # (was managed_step's "track a state with the model in the dtype
            # ... it was initialised with", a model NormaliseFaces holds: float32 CANDIDE-3 on the CPU)
            raise TypeError(
                f"the TrackerState to continue is {kept[0]} on {kept[1]}, but the frames are tracked by a "
                f"{model.dtype} model on {model.device} (NormaliseFaces' and the datasets' CANDIDE-3): continue a "
                f"state tracked so (a FaceTracker left in {model.dtype} on {model.device}), or start from landmarks"
            )
        state = start
        first_frame = int(start.frame_index)
        # the coarser levels pyramid="auto" added at its initialisation, as FaceTracker reads them (at most those
        # added, where noted: a FaceTracker's state, this function's; a config of fewer levels was made up to them)
        tracker = continuing_config(tracker, state, config.pyramid)
        check_continuing_levels(config.tracker, tracker, state)  # (else: managed_step's error)
    else:
        landmarks = _landmarks_tensor(start, model.num_landmarks)
    layout = ParamLayout(model.num_animation, NUM_ILLUMINATION_TERMS)
    per_frame: dict[str, list[Tensor]] = {k: [] for k in (
        "faces", "masks", "rotation", "axis_angle", "translation", "ypr_deg", "anim_coeffs", "expression", "facs",
        "illumination", "confidence", "status",
    )}  # fmt: skip
    size: tuple[int, int] | None = None
    first_shape: tuple[int, int, int] | None = None  # (C, H, W) of the first frame
    with torch_threads(config.num_threads), torch.no_grad():
        for t, raw in enumerate(frames):
            frame = _frame_tensor(raw, t, first_shape).to(dtype=model.dtype, device=model.device)
            if size is None:
                size = (int(frame.shape[-2]), int(frame.shape[-1]))
                first_shape = (int(frame.shape[1]), *size)
            neutral: Tensor | None = None  # (the neutral before this frame's step; None: the frame starts)
            if state is None:
                intrinsics = Intrinsics.default(size[1], size[0], config.focal)
                lm = landmarks.to(dtype=model.dtype, device=model.device).unsqueeze(0)
                refine = config.refine_first if config.tracker.template.enabled else None
                if config.pyramid == "auto":
                    tracker = pyramid_for_faces(config.tracker, lm, size)
                state, result = initialise_managed(model, tracker, frame, lm, intrinsics, refine_first=refine)
            else:
                if t == 0 and state.intrinsics.size != size:
                    raise ValueError(
                        f"the TrackerState tracks {state.intrinsics.width}x{state.intrinsics.height} frames, "
                        f"got {size[1]}x{size[0]}"
                    )
                # Donated (templates written in place at a mosaic entry change) only where the state is this
                # function's own: a caller's state, and those that share its template tensors, are left as
                # they were (a second call from it was 1.5 degrees off the first on a 55-degree turn).
                neutral = state.neutral_anim_coeffs(state.params[:, layout.animation]).clone()
                state, result = managed_step(model, tracker, state, frame, donate=own_state)
            aa, trans, alpha, light = layout.split(state.params)
            if config.keep_expression:  # the person's neutral: the first frame's fitted coefficients
                # that this frame's expression (its facs) is measured from: the neutral before the step. (The online
                # start's re-anchoring, at the end of its frame's step, re-estimates the neutral after that frame's
                # result was measured: its face was resampled at the new one, 1.05 off its labels, as
                # torchface track --keep-expression's rows up to the re-anchoring frame keep the first fit's.)
                alpha = state.neutral_anim_coeffs(alpha) if neutral is None else neutral.to(alpha)
            face = normaliser.from_params(frame, state.shape_coeffs, alpha, aa, trans, light, state.intrinsics)
            per_frame["faces"].append(encode_faces(face.image[0], config.face_storage))
            per_frame["masks"].append(face.mask[0] > 0.5)
            for name in ("rotation", "axis_angle", "translation", "ypr_deg", "anim_coeffs", "expression", "facs",
                         "illumination", "confidence"):  # fmt: skip
                per_frame[name].append(getattr(result, name)[0].detach().to("cpu", torch.float32))
            per_frame["status"].append(result.status[0].to("cpu", torch.int64))
            if progress is not None:
                progress(t + 1)
    if state is None or size is None:
        raise ValueError("no frames to track: the sequence is empty")
    sequence = TrackedSequence(
        **{k: torch.stack(v) for k, v in per_frame.items()},
        shape_coeffs=state.shape_coeffs[0].detach().to("cpu", torch.float32),
        landmarks=landmarks,
        frame_size=size,
        first_frame=first_frame,
    )
    # (for a continuation from it: the levels pyramid="auto" added at the start, as FaceTracker notes its state's)
    note_auto_levels(state, auto_levels(start) if isinstance(start, TrackerState)
                     else tracker.num_levels - config.tracker.num_levels)  # fmt: skip
    return sequence, state


class NormaliseFaces:
    """Transform: ``(frames (T, 3, H, W), landmarks (68, 2) | TrackerState)`` -> normalised faces and parameters
    (NaN rows of the landmarks: missing points, :func:`track_sequence`).

    Gray frames ``(T, 1, H, W)`` are taken as :class:`~torchface.tracker.FaceTracker` takes them and give gray faces
    ``face (T, 1, S, S)``; their parameters are those of the same frames made RGB (``frames.expand(-1, 3, -1, -1)``,
    whose faces are the gray face in each channel) to float rounding (the tracker's luminance of three equal
    channels is the gray level to 1 ulp). A video file of gray frames is :class:`~training_hooks.datasets.
    VideoDataset`'s with ``DatasetConfig(convert=True)``, which makes it RGB as ``torchface track --convert`` does.

    A torchvision-style callable for pipelines that already hold frames: it tracks the frames with
    :func:`track_sequence` and returns the clip item of :meth:`TrackedSequence.item` (``face (T, C, S, S)``
    float32, ``mask (T, 1, S, S)``, the parameters, ``confidence``, ``success``, ``status``, ``frame``), exactly
    what :class:`~training_hooks.datasets.VideoDataset` yields for the same frames as one clip: data, without
    gradients (frames that require grad are refused; :class:`~training_hooks.layer.NormalisedFaceLayer` makes faces
    differentiable w.r.t. the frames). Frames that continue
    a :class:`~torchface.tracker.TrackerState` are numbered on from it (``frame`` starts at its ``frame_index``); the
    state is left as it was (a :class:`~torchface.tracker.FaceTracker`'s ``state`` too), so it can be continued again.
    The face model and the canonical layout are built on first use.

    Args:
        config: :class:`FaceTrackingConfig` (default settings when None).

    Example:
        >>> normalise = NormaliseFaces(FaceTrackingConfig(face_size=64))
        >>> # item = normalise(frames, landmarks)   # frames (T, 3, H, W), landmarks (68, 2) of frames[0]
        >>> # item["face"].shape -> (T, 3, 64, 64)
    """

    def __init__(self, config: FaceTrackingConfig | None = None) -> None:
        self.config = FaceTrackingConfig() if config is None else config
        if not isinstance(self.config, FaceTrackingConfig):
            raise TypeError(f"config must be a FaceTrackingConfig, got {type(self.config).__name__}")
        self._model: FaceModel | None = None
        self._normaliser: NormalisedFace | None = None

    @property
    def model(self) -> FaceModel:
        """The face model (float32): CANDIDE-3, or the file of :attr:`FaceTrackingConfig.model`, loaded on first
        use."""
        if self._model is None:
            path = self.config.model
            self._model = load_candide3() if path is None else load_face_model(path)
        return self._model

    @property
    def normaliser(self) -> NormalisedFace:
        """The :class:`~torchface.normalise.NormalisedFace` of :attr:`model`, built on first use."""
        if self._normaliser is None:
            self._normaliser = NormalisedFace(self.model, size=self.config.face_size, margin=self.config.face_margin)
        return self._normaliser

    def track(
        self, frames: Iterable[Tensor], start: Tensor | np.ndarray | TrackerState
    ) -> tuple[TrackedSequence, TrackerState]:
        """:func:`track_sequence` with this transform's settings: the sequence and the final tracker state."""
        return track_sequence(frames, start, self.config, self.model, self.normaliser)

    def __call__(self, frames: Tensor, start: Tensor | np.ndarray | TrackerState) -> dict[str, Tensor]:
        """Normalised faces of ``frames (T, 3, H, W)`` RGB or ``(T, 1, H, W)`` gray (float in [0, 1] or uint8) as a
        clip item (class docstring)."""
        if not isinstance(frames, Tensor):  # (a ValueError, where track_sequence's numpy frames are a TypeError)
            hint = not_tensor_hint(frames, per="(T, 3, H, W)", to_float=False, layout="(T, 3, H, W)")
            raise TypeError(f"frames must be a (T, 3, H, W) torch.Tensor, got {type(frames).__name__}{hint}")
        if frames.dim() != 4 or frames.shape[1] not in (1, 3):
            raise ValueError(f"frames must be a (T, 3, H, W) RGB or (T, 1, H, W) gray tensor, got "
                             f"{tuple(frames.shape)}{_layout_hint(frames)}")  # fmt: skip
        if torch.is_grad_enabled() and frames.requires_grad:  # (its faces were detached without a word)
            raise ValueError(
                "frames require grad, but NormaliseFaces makes data items (stored faces, no gradient): for faces "
                "differentiable w.r.t. the frames use training_hooks.NormalisedFaceLayer, else pass frames.detach()"
            )
        sequence, _ = self.track(frames, start)
        return sequence.item(slice(0, sequence.num_frames))
