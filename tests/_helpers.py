"""Helpers shared by tests in more than one folder. A test file imports them with this folder on ``sys.path``
(``sys.path.insert(0, str(Path(__file__).resolve().parents[1]))``, whatever pytest's import mode), as the
folders' own helper modules are imported (tests/training_hooks/th_data.py, tests/tracker/test_objective.py)."""

from __future__ import annotations

import importlib.util
import os
import struct
import sys
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np
import pytest
import torch

from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import euler_to_matrix
from torchface.model.candide import load_candide3
from torchface.synth.background import BackgroundSpec, OccluderSpec
from torchface.synth.scenarios import default_light
from torchface.synth.sequence import SequenceSpec, render_sequence

D = torch.float64

#: The shared assets beside the checkout (``../shared/assets``: the ICT Face Model, the James scan's sources; not
#: shipped), or where ``TORCHFACE_ASSETS`` says. Tests that need them skip without them.
ASSETS = Path(os.environ.get("TORCHFACE_ASSETS") or Path(__file__).resolve().parents[2] / "shared" / "assets")
ICT_NPZ = ASSETS / "ict_facekit" / "ict_face_model_light.npz"


class WriteOnlyStream:
    """A text stream with ``write`` and ``flush`` alone (no ``isatty``, as some notebook or wrapper streams), keeping
    each write in ``parts``."""

    def __init__(self) -> None:
        self.parts: list[str] = []

    def write(self, text: str) -> int:
        self.parts.append(text)
        return len(text)

    def flush(self) -> None:
        pass


#: The command-line scripts (scripts/ of the checkout).
SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def without_home(monkeypatch: pytest.MonkeyPatch) -> None:
    """No home folder for ``~`` to expand to, as in a container run as an uid without a password entry: ``HOME``
    unset and the password database without the user (``os.path.expanduser("~/x")`` gives ``"~/x"``). The test
    skips where there is no password database (``pwd``: POSIX)."""
    pwd = pytest.importorskip("pwd")

    def missing(*args: object) -> None:
        raise KeyError("no such entry")

    monkeypatch.delenv("HOME", raising=False)
    monkeypatch.setattr(pwd, "getpwuid", missing)
    monkeypatch.setattr(pwd, "getpwnam", missing)
    assert os.path.expanduser("~/x") == "~/x"


def load_script(name: str) -> ModuleType:
    """scripts/``name``.py imported afresh as module ``name`` (its module-level defaults, e.g. the assets folder,
    read from the environment now), for a test to call its ``main`` or functions."""
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


def sideways_clip(w: int, h: int, n: int = 3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The clip of tests/cli/test_cli_track.py's HD test: CANDIDE-3 at 450 mm turning 2 degrees and moving 13 mm
    sideways a frame (18 pixels at 640x360, 37 at 1280x720), ``n <= 6`` frames of ``w x h``.

    Returns:
        ``frames (n, 3, h, w)`` float32, the first frame's landmarks ``(68, 2)`` float32 and the true rotations
        ``(n, 3, 3)`` float64.
    """
    s = torch.linspace(0.0, 1.0, 6, dtype=D)[:n, None]
    spec = SequenceSpec(
        name="clip", subject="candide3", intrinsics=Intrinsics.default(w, h),
        rotation=euler_to_matrix(s * torch.tensor([10.0, 0.0, 0.0], dtype=D)),
        translation=torch.tensor([0.0, 0.0, 450.0], dtype=D) + s * torch.tensor([65.0, 0.0, 0.0], dtype=D),
        anim=torch.zeros(n, load_candide3().num_animation, dtype=D), light=default_light(n),
        background=BackgroundSpec(seed=3),
    )  # fmt: skip
    frames, gt = render_sequence(spec)
    return frames.float(), gt.landmarks_px[0].float(), gt.rotation


def write_rotated_mp4(path: str | os.PathLike[str], frames_bgr: np.ndarray, rotate: int) -> None:
    """Write ``frames_bgr`` ``(T, H, W, 3)`` uint8 as an MP4 (``mp4v``, 25 frames/s) stored as given, with the display
    rotation of a phone video: a viewer turns its frames ``rotate`` degrees clockwise (0, 90, 180 or 270; the
    ``rotate`` tag's meaning, OpenCV's ``CAP_PROP_ORIENTATION_META``). The rotation is the track header's matrix
    (ISO/IEC 14496-12 ``tkhd``: ``a b u c d v x y w``, ``a b c d`` in 16.16 fixed point), written as ffmpeg's
    ``-display_rotation -rotate`` writes it (the same bytes: checked with ffmpeg 9.0.2 and ``ffmpeg -i``'s
    "Display Matrix: rotation of ..." line), so no ffmpeg binary is needed.
    """
    t, h, w = frames_bgr.shape[:3]
    writer = cv2.VideoWriter(os.fspath(path), cv2.VideoWriter.fourcc(*"mp4v"), 25.0, (w, h))
    assert writer.isOpened(), "this OpenCV cannot write mp4v"
    for frame in frames_bgr:
        writer.write(np.ascontiguousarray(frame))
    writer.release()
    cos, sin = {0: (1, 0), 90: (0, -1), 180: (-1, 0), 270: (0, 1)}[rotate]  # of the counter-clockwise -rotate
    data = bytearray(open(path, "rb").read())

    def boxes(start: int, end: int):
        while start + 8 <= end:
            size, kind = struct.unpack(">I4s", data[start : start + 8])
            size = end - start if size == 0 else size
            yield kind, start, start + size
            start += size

    moov = next((s, e) for k, s, e in boxes(0, len(data)) if k == b"moov")
    trak = next((s, e) for k, s, e in boxes(moov[0] + 8, moov[1]) if k == b"trak")
    tkhd = next(s for k, s, e in boxes(trak[0] + 8, trak[1]) if k == b"tkhd")
    at = tkhd + 12 + (20 if data[tkhd + 8] == 0 else 32) + 16  # size, type, version+flags; times, id, ...; layer ...
    struct.pack_into(">4i", data, at, cos << 16, -sin << 16, 0, sin << 16)  # a, b, u (0), c
    struct.pack_into(">i", data, at + 16, cos << 16)  # d
    open(path, "wb").write(bytes(data))


_VideoCapture = cv2.VideoCapture  # (OpenCV's own, before a test replaces it with the one below)


def opencv_411_capture(*args) -> cv2.VideoCapture:
    """A capture as OpenCV 4.11 opened one: ``CAP_PROP_ORIENTATION_AUTO`` off by default (4.10 and 4.12 on). (Not a
    subclass of ``cv2.VideoCapture``: the garbage collector crashed the process on one's instances.)"""
    cap = _VideoCapture(*args)
    cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 0)
    return cap


def candide_spec(name: str, ypr: list[list[float]], txyz: list[list[float]], width: int, height: int, *,
                 photo: str = "james", occluder: OccluderSpec | None = None) -> SequenceSpec:
    """A rendered CANDIDE-3 sequence at rest (no expression) with the default light and background seed 3: its
    per-frame yaw/pitch/roll (degrees) and translation (mm) as lists of ``[a, b, c]``, at ``width x height``."""
    T = len(ypr)
    return SequenceSpec(
        name=name, subject="candide3", intrinsics=Intrinsics.default(width, height),
        rotation=euler_to_matrix(torch.tensor(ypr, dtype=D)), translation=torch.tensor(txyz, dtype=D),
        anim=torch.zeros(T, load_candide3().num_animation, dtype=D), light=default_light(T),
        background=BackgroundSpec(seed=3), occluder=occluder, photo=photo,
    )  # fmt: skip


def leave_and_return_streams(width: int = 320, height: int = 240, frames: int = 12, depth_mm: float = 450.0):
    """Two rendered streams ``(2, T, 3, H, W)``: a gentle turn (12, -5, 4 degrees of yaw, pitch, roll and a few mm)
    at ``depth_mm``, and a face at 450 mm that moves, leaves the frame to the right (frames 4-7) and comes back on the
    left (8 on); their first landmarks ``(2, 68, 2)`` float32 and ground truths. For tests of loss and recovery on
    any device (with a nearer turn, its face sizes the batch's crop: test_other_models.py)."""
    s = torch.linspace(0, 1, frames, dtype=D)
    ypr = (s[:, None] * torch.tensor([12.0, -5.0, 4.0], dtype=D)).tolist()
    txyz = (torch.tensor([0.0, 0.0, depth_mm], dtype=D) + s[:, None] * torch.tensor([8.0, -4.0, 10.0], dtype=D)).tolist()
    x = ([0.0, 5.0, 10.0, 15.0] + [400.0] * 4 + [-60.0] * frames)[:frames]
    fa, ga = render_sequence(candide_spec("gentle", ypr, txyz, width, height))
    still = [[0.0, 0.0, 0.0]] * frames
    fb, gb = render_sequence(candide_spec("leaves", still, [[xi, 0.0, 450.0] for xi in x], width, height))
    lm = torch.stack([ga.landmarks_px[0], gb.landmarks_px[0]]).float()
    return torch.stack([fa, fb]), lm, (ga, gb)


def managed_track(model, config, frames: torch.Tensor, landmarks: torch.Tensor) -> list:
    """``initialise_managed`` on ``frames[:, 0]`` then ``managed_step`` on each later frame of ``frames (B, T, C, H,
    W)``, inputs moved to the model's device; the list of results."""
    from torchface.tracker import initialise_managed, managed_step

    h, w = frames.shape[-2:]
    state, res = initialise_managed(model, config, frames[:, 0].to(model.device), landmarks.to(model.device),
                                    Intrinsics.default(w, h))  # fmt: skip
    results = [res]
    for i in range(1, frames.shape[1]):
        state, res = managed_step(model, config, state, frames[:, i].to(model.device))
        results.append(res)
    return results


def count_job_steps(monkeypatch) -> list[int]:
    """From now on, count ``torchface.job``'s tracking steps (``managed_step`` calls, each still made): the returned
    list gets one entry per step (``monkeypatch``: pytest's fixture, which undoes the patch)."""
    import torchface.job

    steps: list[int] = []
    real = torchface.job.managed_step

    def counted(*args, **kwargs):
        steps.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(torchface.job, "managed_step", counted)
    return steps


def lossless_scenario_clip(root: Path, scenario: str, frames: int, width: int, height: int) -> tuple[Path, Path]:
    """A standard scenario's first ``frames`` frames written into ``root`` as ``clip.npy`` (``(T, H, W, 3)`` uint8,
    lossless: a ``.npy`` video tracks without the codec's rounding) and its first frame's true landmarks as
    ``first_frame.csv`` (``x,y`` header, as ``torchface track --landmarks`` reads it). Returns ``(video, landmarks)``."""
    from torchface.synth.io import read_video
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import load_ground_truth, write_sequence

    files = write_sequence(make_scenario(scenario, frames, width, height), root)
    gt = load_ground_truth(files.ground_truth)
    lm = root / "first_frame.csv"
    np.savetxt(lm, gt.landmarks_px[0].numpy(), delimiter=",", header="x,y", comments="")
    video = root / "clip.npy"
    np.save(video, (read_video(files.video).permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8))
    return video, lm
