"""``torchface track --fps F`` (``JobConfig.fps``, OpenFace's ``-fps``): the frame rate of the inputs that have none
(image folders, ``.npy`` arrays), which were timed at the assumed 25 frames/s: their CSV ``timestamp``, their overlay
and normalised videos and their sidecar follow it, a video's own rate is kept with a warning, a bad rate is a usage
error, and ``--resume`` refuses another rate than the interrupted run's."""

from __future__ import annotations

import json
import math
import struct
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchface.cli import main
from torchface.io import open_frames, read_track_csv
from torchface.job import JobConfig, track_videos

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/_helpers.py
from _helpers import lossless_scenario_clip  # noqa: E402

T, W, H = 8, 160, 120


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """The ``expressions`` scenario's first frames as an ``.npy`` array (no rate of its own), the same frames as the
    rendered video (its own rate, 25 frames/s), and the first frame's landmarks."""
    root = tmp_path_factory.mktemp("clip")
    array, lm = lossless_scenario_clip(root, "expressions", T, W, H)
    (video,) = [p for p in root.iterdir() if p.suffix in (".avi", ".mp4")]
    return array, video, lm


@pytest.fixture(scope="module")
def runs(clip, tmp_path_factory):
    """The array tracked without ``--fps`` and with ``--fps 10``."""
    array, _, lm = clip
    out = {}
    for name, extra in (("plain", []), ("f10", ["--fps", "10"])):
        out[name] = tmp_path_factory.mktemp(name)
        assert main(["track", str(array), "--out", str(out[name]), "--landmarks", str(lm), "--quiet", *extra]) == 0
    return out


def _video_rate(path: Path) -> float:
    cap = cv2.VideoCapture(str(path))
    try:
        return float(cap.get(cv2.CAP_PROP_FPS))
    finally:
        cap.release()


def test_fps_times_an_array_and_changes_nothing_else(runs) -> None:
    cols, plain = read_track_csv(runs["plain"] / "clip.csv")
    cols10, given = read_track_csv(runs["f10"] / "clip.csv")
    at = cols.index("timestamp")
    assert cols10 == cols and len(given) == T
    np.testing.assert_allclose(plain[:, at], np.arange(T) / 25.0, rtol=0, atol=5e-4)  # (written to the millisecond)
    np.testing.assert_allclose(given[:, at], np.arange(T) / 10.0, rtol=0, atol=5e-4)
    # every other column as without it (the tracking does not depend on the clock)
    assert np.array_equal(np.delete(given, at, axis=1), np.delete(plain, at, axis=1), equal_nan=True)
    for name, fps, assumed, given_ in (("plain", 25.0, True, False), ("f10", 10.0, False, True)):
        side = json.loads((runs[name] / "clip.json").read_text())
        assert (side["input"]["fps"], side["input"]["fps_assumed"], side["input"]["fps_given"]) == (fps, assumed, given_)
        assert side["config"]["fps"] == (None if name == "plain" else 10.0)
        assert side["videos"]["overlay"]["fps"] == side["videos"]["normalised"]["fps"] == fps
        for video in ("clip_overlay.mp4", "clip_normalised.mp4"):
            assert _video_rate(runs[name] / video) == pytest.approx(fps, abs=1e-3), (name, video)


def test_fps_times_an_image_folder(clip, tmp_path) -> None:
    """A folder's frames at a rate that is not a whole number (NTSC's 30000/1001), as OpenFace's ``-fps`` gives it."""
    array, _, lm = clip
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, frame in enumerate(np.load(array)[:3]):
        cv2.imwrite(str(folder / f"{i:03d}.png"), frame[..., ::-1])
    rate = 30000 / 1001
    assert main(["track", str(folder), "--out", str(tmp_path / "out"), "--landmarks", str(lm), "--quiet",
                 "--fps", repr(rate)]) == 0  # fmt: skip
    cols, rows = read_track_csv(tmp_path / "out" / "frames.csv")
    np.testing.assert_allclose(rows[:, cols.index("timestamp")], np.arange(3) / rate, rtol=0, atol=5e-4)
    side = json.loads((tmp_path / "out" / "frames.json").read_text())
    assert side["input"]["kind"] == "images" and side["input"]["fps"] == rate and side["input"]["fps_given"] is True


def test_a_video_keeps_its_own_rate_with_a_warning(clip, tmp_path, capsys) -> None:
    _, video, lm = clip
    outs = {}
    for name, extra in (("own", []), ("fps", ["--fps", "10"])):
        outs[name] = tmp_path / name
        assert main(["track", str(video), "--out", str(outs[name]), "--landmarks", str(lm), "--quiet", *extra]) == 0
    err = capsys.readouterr().err
    assert (f"torchface: warning: {video}: --fps 10 not used for it: the video gives its own frame rate, 25 frames/s, "
            "which its timestamps and overlay follow") in err.splitlines(), err  # fmt: skip
    csv = f"{video.stem}.csv"
    assert (outs["fps"] / csv).read_bytes() == (outs["own"] / csv).read_bytes()
    side = json.loads((outs["fps"] / f"{video.stem}.json").read_text())
    assert side["input"]["fps"] == 25.0 and not side["input"]["fps_assumed"] and not side["input"]["fps_given"]
    # its complete outputs are resumed whatever --fps says (it was not used for it)
    assert main(["track", str(video), "--out", str(outs["own"]), "--landmarks", str(lm), "--quiet", "--resume",
                 "--fps", "12"]) == 0  # fmt: skip
    assert "already complete" in capsys.readouterr().out
    with open_frames(video, fps=10) as reader:  # (the reader keeps it too)
        assert (reader.info.fps, reader.info.fps_given) == (25.0, False)


@pytest.mark.parametrize("text", ["0", "-5", "nan", "inf", "x", "0.001", "1000.5", ""])
def test_a_bad_rate_is_a_usage_error(clip, tmp_path, capsys, text) -> None:
    array, _, lm = clip
    with pytest.raises(SystemExit) as info:
        main(["track", str(array), "--out", str(tmp_path / "out"), "--landmarks", str(lm), "--fps", text])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.splitlines()[-1] == (
        f"torchface track: error: argument --fps: must be a number of frames per second in (0.001, 1000], got {text!r}"
    ), err  # fmt: skip
    assert not (tmp_path / "out").exists()


def test_job_fps_setting_is_checked(tmp_path) -> None:
    """``JobConfig.fps`` takes the rates the command line takes (``torchface.job.FPS_RANGE``), as a float."""
    from torchface.cli import _frame_rate

    for rate in (0.0011, 1, 29.97, 1000):
        assert JobConfig(out_dir=tmp_path, fps=rate).fps == _frame_rate(str(rate)) == float(rate)
        assert type(JobConfig(out_dir=tmp_path, fps=rate).fps) is float
    for rate in (0, 0.001, -1, 1000.5, math.inf, math.nan):
        with pytest.raises(ValueError, match=r"fps must be in \(0.001, 1000\] \(frames per second\) or None"):
            JobConfig(out_dir=tmp_path, fps=rate)
    with pytest.raises(TypeError, match="fps must be a real number or None"):
        JobConfig(out_dir=tmp_path, fps="30")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="fps must be a finite number > 0"):
        open_frames(tmp_path / "missing.npy", fps=0)  # (checked before the input is opened)


def test_resume_refuses_another_rate(clip, runs, tmp_path, capsys) -> None:
    """A partial run, and complete outputs, resumed with another ``--fps`` (or none) are refused, naming both rates:
    their rows would hold two clocks, or their complete outputs another rate than asked for. With the same rate (or
    ``--fps 25`` for a run without it: the same times), resumed: the uninterrupted run's CSV."""
    array, _, lm = clip
    args = ["track", str(array), "--landmarks", str(lm), "--quiet", "--resume"]

    def interrupt(p):
        if p.done == 4:
            raise KeyboardInterrupt

    for name, fps in (("p10", 10.0), ("pnone", None)):
        with pytest.raises(KeyboardInterrupt):
            track_videos([array], JobConfig(out_dir=tmp_path / name, landmarks=(lm,), fps=fps), progress=interrupt)
    for name, extra, said in (("p10", [], "--fps 10.0 then, none (25 assumed) now"),
                              ("p10", ["--fps", "12"], "--fps 10.0 then, 12.0 now"),
                              ("pnone", ["--fps", "12"], "--fps none (25 assumed) then, 12.0 now")):  # fmt: skip
        assert main([*args, "--out", str(tmp_path / name), *extra]) == 2
        err = capsys.readouterr().err
        assert "clip.record.partial: cannot resume, the partial results were made with other settings" in err, err
        assert said in err, err
    assert main([*args, "--out", str(tmp_path / "p10"), "--fps", "10"]) == 0
    assert main([*args, "--out", str(tmp_path / "pnone"), "--fps", "25"]) == 0
    for name, run in (("p10", "f10"), ("pnone", "plain")):
        assert (tmp_path / name / "clip.csv").read_bytes() == (runs[run] / "clip.csv").read_bytes(), name
    capsys.readouterr()
    # complete outputs (skipped as complete, they would have kept the other rate's times)
    for run, extra, said in (("f10", [], "--fps 10.0 then, none (25 assumed) now"),
                             ("plain", ["--fps", "10"], "--fps none (25 assumed) then, 10.0 now")):  # fmt: skip
        assert main([*args, "--out", str(runs[run]), *extra]) == 2
        err = capsys.readouterr().err
        assert "clip.json: cannot resume, these complete outputs were made with other settings" in err and said in err
    for run, extra in (("f10", ["--fps", "10"]), ("plain", []), ("plain", ["--fps", "25"])):
        assert main([*args, "--out", str(runs[run]), *extra]) == 0
        assert "already complete" in capsys.readouterr().out


def _slow_video(array: Path, path: Path, scale: int) -> Path:
    """``array``'s frames as an MJPG AVI whose stream header declares ``1 / scale`` frames/s (OpenCV writes no rate
    under 1 through MJPG, nor at 0.001 or less through FFmpeg: written at 0.5, then ``strh``'s ``dwScale`` set)."""
    frames = np.load(array)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 0.5, (W, H))
    assert writer.isOpened()
    for frame in frames:
        writer.write(np.ascontiguousarray(frame[..., ::-1]))
    writer.release()
    data = bytearray(path.read_bytes())
    at = data.find(b"strh") + 8  # (AVISTREAMHEADER: fccType, fccHandler, dwFlags, wPriority, wLanguage,
    assert data[at : at + 4] == b"vids"  # dwInitialFrames, dwScale, dwRate)
    assert struct.unpack("<II", data[at + 20 : at + 28]) == (2, 1)
    data[at + 20 : at + 24] = struct.pack("<I", scale)
    path.write_bytes(bytes(data))
    return path


def test_a_video_of_a_tiny_declared_rate_is_taken_as_rateless(clip, tmp_path, capsys) -> None:
    """A container that declares 0.0005 frames/s (at most 0.001: its mp4v overlay could not be written at it, and
    the run stopped with an error after its first rows) is taken as one with no plausible rate, as one over 1000 is:
    25 frames/s (or ``--fps``'s) for its overlay and normalised videos, with a warning; its frames' own times are
    still the rows' timestamps. A rate just over 0.001 is the video's own."""
    array, _, lm = clip
    slow = _slow_video(array, tmp_path / "slow.avi", 2000)
    for name, extra, fps in (("plain", [], 25.0), ("f2", ["--fps", "2"], 2.0)):
        out = tmp_path / name
        assert main(["track", str(slow), "--out", str(out), "--landmarks", str(lm), "--quiet", *extra]) == 0
        err = capsys.readouterr().err
        other = "" if extra else " (--fps gives another)"
        assert (f"torchface: warning: {slow}: its container declares 0.0005 frames/s, not a plausible frame rate "
                f"(one in (0.001, 1000)): taken as none, its overlay and normalised videos at {fps:g} frames/s{other}; "
                "the container's own frame times are still the rows' timestamps") in err.splitlines(), err  # fmt: skip
        side = json.loads((out / "slow.json").read_text())
        assert (side["input"]["fps"], side["input"]["fps_assumed"], side["input"]["fps_given"]) == (
            fps, not extra, bool(extra))
        assert side["videos"]["overlay"]["frames"] == side["videos"]["normalised"]["frames"] == T
        for video in ("slow_overlay.mp4", "slow_normalised.mp4"):
            assert _video_rate(out / video) == pytest.approx(fps, abs=1e-3), (name, video)
        cols, rows = read_track_csv(out / "slow.csv")
        np.testing.assert_allclose(rows[:, cols.index("timestamp")], np.arange(T) * 2000.0, rtol=0, atol=5e-4)
    with open_frames(slow) as reader:  # (OpenCV reads the rate from it)
        assert (reader.info.fps, reader.info.fps_assumed, reader.info.declared_fps) == (25.0, True, 0.0005)
    with open_frames(slow, fps=2) as reader:  # (the reader's fps for it, and its declared rate kept)
        assert (reader.info.fps, reader.info.fps_assumed, reader.info.fps_given) == (2.0, False, True)
    with open_frames(_slow_video(array, tmp_path / "slow2.avi", 999)) as reader:  # (1.001e-3 frames/s: its own)
        assert (reader.info.fps, reader.info.fps_assumed, reader.info.declared_fps) == (pytest.approx(1 / 999), False,
                                                                                         None)  # fmt: skip
