"""``torchface track``'s faster paths give what the plain ones gave: the frame conversions, the videos encoded in a
thread of their own (:class:`torchface.job._Encoder`) and the inputs read in one (:class:`torchface.job._ReadAhead`),
with their errors and interrupts."""

from __future__ import annotations

import json
import threading
import time

import cv2
import numpy as np
import pytest
import torch

import torchface.job
from torchface.cli import main
from torchface.detect import detector_image
from torchface.job import _Encoder, _ReadAhead, _to_uint8_bgr, _VideoOut
from torchface.synth.scenarios import make_scenario
from torchface.synth.sequence import load_ground_truth, write_sequence


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    root = tmp_path_factory.mktemp("clip")
    files = write_sequence(make_scenario("expressions", 8, 160, 120), root)
    lm = root / "first_frame.csv"
    np.savetxt(lm, load_ground_truth(files.ground_truth).landmarks_px[0].numpy(), delimiter=",")
    return files.video, lm


@pytest.fixture(autouse=True)
def _threads_before():
    """The encoding threads running before the test (another module's video left open): not the test's."""
    global _BEFORE
    _BEFORE = set(threading.enumerate())
    yield


_BEFORE: set[threading.Thread] = set()


def _encoders() -> list[threading.Thread]:
    """The encoding and reading threads the test started that are still running."""
    return [t for t in threading.enumerate()
            if t.name.startswith(("torchface encoder", "torchface reader")) and t not in _BEFORE]  # fmt: skip


def _decoded(path):
    capture, frames = cv2.VideoCapture(str(path)), []
    while (got := capture.read())[0]:
        frames.append(got[1])
    capture.release()
    return frames


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_uint8_images_are_the_previous_formulas(dtype):
    """The overlay's and normalised face's BGR frames and a detector's RGB image, made by planes, are what the
    conversion of the whole image gave (values outside [0, 1] and halves included)."""
    g = torch.Generator().manual_seed(0)
    frame = (torch.rand(3, 30, 40, generator=g, dtype=dtype) * 1.2 - 0.1)
    frame[0, 0, :4] = torch.tensor([0.5, 1.5, 2.5, 254.5], dtype=dtype) / 255
    old_rgb = (frame.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    bgr = _to_uint8_bgr(frame)
    assert bgr.flags.c_contiguous and bgr.shape == (30, 40, 3) and bgr.dtype == np.uint8
    np.testing.assert_array_equal(bgr, cv2.cvtColor(old_rgb, cv2.COLOR_RGB2BGR))
    np.testing.assert_array_equal(detector_image(frame), old_rgb)
    assert frame[0, 0, 1] == 1.5 / 255  # (the frame itself is left as it was)


@pytest.mark.parametrize("options", [[], ["--lookahead"], ["images"]])
def test_outputs_are_the_same_with_and_without_the_faster_paths(clip, tmp_path, monkeypatch, options):
    """The CSV byte for byte, the JSON but its timings and every frame of both videos, with the videos encoded in
    their threads, the inputs read in theirs and the overlay drawn on the frames as read (the defaults), and with all
    in the tracking's thread (``ENCODE_QUEUE = 0``, ``READ_AHEAD = 0``) and the overlay drawn on the frames converted
    back to 8 bits; a video, with the look-ahead start (frames read ahead), an image folder. No encoding or reading
    thread outlives a run."""
    video, lm = clip
    name = video.stem
    if options == ["images"]:  # (the clip's frames as PNG files, named as the video)
        video, options = tmp_path / name, []
        video.mkdir()
        for k, f in enumerate(_decoded(clip[0])):
            cv2.imwrite(str(video / f"{k:03d}.png"), f)
    outs = {}
    for fast in (False, True):
        with monkeypatch.context() as m:
            if not fast:
                m.setattr(torchface.job, "ENCODE_QUEUE", 0)
                m.setattr(torchface.job, "READ_AHEAD", 0)
                m.setattr(torchface.job, "_frame_bgr", lambda frame, image: _to_uint8_bgr(frame))
            outs[fast] = tmp_path / f"fast{fast}"
            args = ["track", str(video), "--landmarks", str(lm), "--out", str(outs[fast]), "--quiet", *options]
            assert main(args) == 0
            assert not _encoders()
    a, b = outs.values()
    assert (a / f"{name}.csv").read_bytes() == (b / f"{name}.csv").read_bytes()

    def sidecar(path):
        return {k: v for k, v in json.loads(path.read_text()).items() if k not in ("timings_s", "outputs")}

    assert sidecar(a / f"{name}.json") == sidecar(b / f"{name}.json")
    for kind in ("overlay", "normalised"):
        fa, fb = _decoded(a / f"{name}_{kind}.mp4"), _decoded(b / f"{name}_{kind}.mp4")
        assert len(fa) == len(fb) == 8
        for x, y in zip(fa, fb):
            np.testing.assert_array_equal(x, y)


class _FailingWriter:
    """A ``cv2.VideoWriter`` stand-in whose ``fail_at``-th write raises (frames counted in ``written``)."""

    def __init__(self, fail_at: int, delay: float = 0.0) -> None:
        self.fail_at, self.delay, self.written = fail_at, delay, 0

    def write(self, image):
        time.sleep(self.delay)
        if self.written == self.fail_at:
            raise cv2.error("the encoder failed")
        self.written += 1


def test_an_error_in_the_encoding_thread_is_raised_to_the_caller():
    """An error while encoding frame k is raised by a later write or by finish, and the thread ends (it took and
    dropped the frames after it: the caller never waits on a thread that has stopped writing)."""
    encoder = _Encoder(_FailingWriter(2), "x.mp4")
    image = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(cv2.error, match="the encoder failed"):
        for _ in range(50):
            encoder.write(image)
            time.sleep(0.001)
    with pytest.raises(cv2.error, match="the encoder failed"):
        encoder.finish()
    assert encoder.writer.written == 2 and not encoder._thread.is_alive()


def test_a_video_stopped_with_frames_queued_is_removed_and_its_thread_ended(tmp_path):
    """abort() with frames still queued (an interrupted run): they are dropped, the thread joined, the partial
    file removed; close() of a video whose encoder failed removes it too and raises the error."""
    out = _VideoOut(tmp_path / "a.mp4", 64, 48, 25.0)
    out._encoder.writer = _FailingWriter(10**6, delay=0.05)  # (a slow encoder: the queue fills)
    for _ in range(6):
        out.write(np.zeros((48, 64, 3), np.uint8))
    out.abort()
    assert not out._encoder._thread.is_alive() and not out.tmp.exists() and out._encoder.writer.written < 6
    bad = _VideoOut(tmp_path / "b.mp4", 64, 48, 25.0)
    real = bad.writer
    bad._encoder.writer = _FailingWriter(1)
    bad.write(np.zeros((48, 64, 3), np.uint8))
    bad.write(np.zeros((48, 64, 3), np.uint8))
    with pytest.raises(cv2.error):
        bad.close()
    real.release()
    assert not bad._encoder._thread.is_alive() and not bad.tmp.exists() and not bad.path.exists()


def test_interrupted_while_encoding_leaves_no_video_and_no_thread(clip, tmp_path, monkeypatch, capsys):
    """Ctrl-C while the frames are being encoded in their threads: exit status 130, the rows kept for --resume, no
    partial or complete video left, no encoding thread running; the resumed run completes."""
    video, lm = clip
    real = _Encoder.write
    calls = []

    def interrupted(self, image):
        calls.append(1)
        if len(calls) == 7:  # (frame 3's overlay: its normalised face and the frames after it not written)
            raise KeyboardInterrupt
        return real(self, image)

    monkeypatch.setattr(_Encoder, "write", interrupted)
    out = tmp_path / "out"
    args = ["track", str(video), "--landmarks", str(lm), "--out", str(out), "--quiet"]
    assert main(args) == 130
    assert "torchface: interrupted; rows kept in" in capsys.readouterr().err
    assert not list(out.glob("*.mp4")) and not _encoders()
    monkeypatch.undo()
    assert main([*args, "--resume"]) == 0 and len(_decoded(out / f"{video.stem}_overlay.mp4")) == 8


@pytest.mark.parametrize("step_delay", [0.0, 0.6])
def test_sigterm_while_waiting_on_a_full_encoding_queue_stops_cleanly(clip, tmp_path, monkeypatch, capsys,
                                                                      step_delay):  # fmt: skip
    """SIGTERM arriving while the tracking waits for a slow encoder (its queue full): status 143 as before, once
    the frame under way is written (the signal waits for the step's end), the rows kept for --resume, no video left, the encoding threads joined (none outlives the run). Also with each
    tracking step made 0.6 s slower (a loaded machine: the test used to fail there, SIGTERM coming while it
    tracked)."""
    import os
    import signal

    video, lm = clip
    real_init, real_put = _Encoder.__init__, _Encoder.write
    waiting, stalled = [], []

    class Stalled:
        """The overlay's writer: its first frame is held until the tracking waits on the encoder's full queue (a
        later frame's ``put`` blocked in it), then SIGTERM comes. (It slept 1 s, taken as long enough for the
        tracking to fill the queue: under load the tracking of the next frames took longer, and SIGTERM came while
        it tracked, not while it waited.)"""

        def __init__(self, writer):
            self.real, self.calls, self.encoder, self.saw_waiter = writer, 0, None, False

        def write(self, image):
            self.calls += 1
            if self.calls == 1:
                q, deadline = self.encoder._queue, time.monotonic() + 120.0
                while not self.saw_waiter and time.monotonic() < deadline:
                    with q.mutex:  # (the tracking thread waits in q.not_full.wait(): a waiter of that condition)
                        self.saw_waiter = q._qsize() >= q.maxsize and len(q.not_full._waiters) > 0
                    time.sleep(0.005)
                os.kill(os.getpid(), signal.SIGTERM)
            self.real.write(image)

    def stalled_init(self, writer, name):
        real_init(self, Stalled(writer) if "overlay" in name else writer, name)
        if isinstance(self.writer, Stalled):
            self.writer.encoder = self
            stalled.append(self.writer)

    def put(self, image):
        waiting.append(self._queue.full())
        real_put(self, image)

    real_step = torchface.job.managed_step

    def slow_step(*args, **kwargs):
        time.sleep(step_delay)
        return real_step(*args, **kwargs)

    monkeypatch.setattr(_Encoder, "__init__", stalled_init)
    monkeypatch.setattr(_Encoder, "write", put)
    monkeypatch.setattr(torchface.job, "managed_step", slow_step)
    out = tmp_path / "out"
    rc = main(["track", str(video), "--landmarks", str(lm), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 143 and "torchface: terminated; rows kept in" in err and "not finalised" not in err, err
    assert len(stalled) == 1 and stalled[0].saw_waiter, "SIGTERM came while the tracking waited on the full queue"
    # (the signal waits for the step's end: the blocked put goes through once the encoder drains, so the frame under
    # way is written whole before the run stops)
    assert any(waiting) and not list(out.glob("*.mp4")) and not _encoders()


def test_a_reader_keeps_the_8bit_image_each_frame_was_read_from(clip, tmp_path):
    """``FrameReader.image``: the decoded BGR image of the frame just read, which the frame converted back to 8 bits
    gives exactly; None where the frame is not one converted as is (an RGB array, a frame ``convert`` crops)."""
    from torchface.io import open_frames

    video, _ = clip
    with open_frames(video) as reader:
        for frame in reader:
            assert reader.image is not None and reader.image.dtype == np.uint8
            np.testing.assert_array_equal(reader.image, _to_uint8_bgr(frame))
            np.testing.assert_array_equal(reader.image, _to_uint8_bgr(frame.double()))
        assert reader.frames_read == 8
    assert reader.image is None  # (closed: not kept)
    rgb = np.zeros((2, 40, 50, 3), np.uint8)
    np.save(tmp_path / "rgb.npy", rgb)
    np.save(tmp_path / "odd.npy", np.zeros((2, 41, 50, 3), np.uint8))
    for name, convert in (("rgb.npy", False), ("odd.npy", True)):
        with open_frames(tmp_path / name, convert=convert) as reader:
            assert [reader.image for _ in reader] == [None, None]


def test_a_read_ahead_reader_gives_the_readers_frames_times_images_and_errors_at_their_frame(clip, tmp_path):
    """:class:`_ReadAhead` gives the frames, times and 8-bit images the reader gives, in order; an image folder whose
    frame 3 has another size: frames 0-2, then the reader's InputError at frame 3, again at the next call; the
    thread ends after it, and ``close`` closes the reader."""
    from torchface.io import InputError, open_frames

    video, _ = clip
    with open_frames(video) as plain:
        want = [(f, plain.timestamp, plain.image) for f in plain]
    ahead = _ReadAhead(open_frames(video))
    got = [(f, ahead.timestamp, ahead.image) for f in ahead]
    assert len(got) == len(want) == 8
    for (f, t, im), (g, u, jm) in zip(want, got):
        assert torch.equal(f, g) and t == u
        np.testing.assert_array_equal(im, jm)
    with pytest.raises(StopIteration):  # (the end, again)
        next(ahead)
    ahead.close()
    assert not ahead._thread.is_alive() and ahead.reader.image is None
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, f in enumerate(_decoded(video)[:5]):
        cv2.imwrite(str(folder / f"{k:03d}.png"), f if k != 3 else f[:-2])
    ahead = _ReadAhead(open_frames(folder))
    assert len([next(ahead) for _ in range(3)]) == 3
    for _ in range(2):
        with pytest.raises(InputError, match="frame 3"):
            next(ahead)
    ahead._thread.join(10)  # (it ends once it has handed the error over)
    assert not ahead._thread.is_alive()
    ahead.close()


def test_a_read_ahead_reader_closed_with_frames_queued_ends_its_thread(clip):
    """``close`` while the thread waits on a full queue (the tracking stopped: an error, Ctrl-C): the frames read
    ahead are dropped, the thread ends, the reader is closed, and the reader gives no more frames."""
    from torchface.io import open_frames

    video, _ = clip
    ahead = _ReadAhead(open_frames(video))
    next(ahead)
    deadline = time.monotonic() + 10
    while not ahead._queue.full() and time.monotonic() < deadline:  # (the thread has read ahead and waits)
        time.sleep(0.01)
    assert ahead._queue.full()
    ahead.close()
    assert not ahead._thread.is_alive() and ahead._queue.empty() and ahead.image is None
    with pytest.raises(StopIteration):
        next(ahead)


@pytest.mark.parametrize("ahead", [1, 2])
def test_a_read_ahead_reader_holds_at_most_read_ahead_frames_ahead(clip, monkeypatch, ahead):
    """``READ_AHEAD`` frames ahead of the tracking at most, as documented: the thread reads a frame only into a free
    place of its queue (it read the next one while it waited on a full queue: READ_AHEAD + 1 frames ahead, 2 x 31 MB
    per 1080p video at the default); the frames still in order, the next ones read once the tracking takes one."""
    from torchface.io import open_frames

    video, _ = clip
    monkeypatch.setattr(torchface.job, "READ_AHEAD", ahead)
    ahead_reader = _ReadAhead(open_frames(video))
    try:
        with open_frames(video) as plain:
            want = list(plain)
        for k in range(3):
            assert torch.equal(next(ahead_reader), want[k])
            deadline = time.monotonic() + 10
            while not ahead_reader._queue.full() and time.monotonic() < deadline:  # (the thread has read ahead)
                time.sleep(0.01)
            time.sleep(0.3)  # (time for one more frame of 160x120: well under a millisecond)
            assert ahead_reader.reader.frames_read == k + 1 + ahead
    finally:
        ahead_reader.close()
    assert not ahead_reader._thread.is_alive()


def test_a_batch_of_more_videos_than_read_ahead_streams_is_read_in_the_tracking_thread(clip, tmp_path, monkeypatch):
    """``READ_AHEAD_STREAMS``: the videos of a larger batch are read by the tracking's thread (no reading thread
    started), those of a batch within it each by its own; the same outputs."""
    video, lm = clip
    started = []
    real = _ReadAhead.__init__

    def counted(self, reader):
        started.append(reader.info.path)
        real(self, reader)

    monkeypatch.setattr(_ReadAhead, "__init__", counted)
    copy = tmp_path / "b.avi"
    copy.write_bytes(video.read_bytes())
    outs = []
    for limit in (1, 2):
        monkeypatch.setattr(torchface.job, "READ_AHEAD_STREAMS", limit)
        started.clear()
        out = tmp_path / f"limit{limit}"
        args = ["track", str(video), "--landmarks", str(lm), str(copy), "--landmarks", str(lm), "--out", str(out),
                "--quiet"]
        assert main(args) == 0 and not _encoders()
        assert len(started) == (0 if limit == 1 else 2)
        outs.append(out)
    for name in (video.stem, "b"):
        assert (outs[0] / f"{name}.csv").read_bytes() == (outs[1] / f"{name}.csv").read_bytes()
