"""Tests for sequence files: ground-truth round trip, lossless video round trip, write_sequence."""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import torch

from torchface.synth.io import VideoSink, frames_to_uint8, iter_video_uint8, read_video, read_video_uint8, write_video
from torchface.synth.scenarios import make_scenario
from torchface.synth.sequence import (
    GroundTruth,
    load_ground_truth,
    render_sequence,
    save_ground_truth,
    write_sequence,
)

_CACHE: dict[str, tuple] = {}


def _light_switch_small():
    if "ls" not in _CACHE:
        spec = make_scenario("light_switch", 6, 64, 48)
        _CACHE["ls"] = (spec, *render_sequence(spec, batch_size=4))
    return _CACHE["ls"]


def _assert_gt_equal(a: GroundTruth, b: GroundTruth) -> None:
    for f in fields(GroundTruth):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, torch.Tensor):
            assert x.dtype == y.dtype, f.name
            torch.testing.assert_close(x, y, rtol=0, atol=0, msg=f.name)
        else:
            assert x == y, f.name


def test_ground_truth_round_trip(tmp_path):
    _, _, gt = _light_switch_small()
    npz, js = save_ground_truth(gt, tmp_path / "seq", {"note": "x"})
    assert npz.name == "seq.gt.npz" and js.name == "seq.gt.json"
    for path in (npz, js, tmp_path / "seq", tmp_path / "seq.avi"):
        _assert_gt_equal(load_ground_truth(path), gt)
    meta = json.loads(js.read_text())
    assert meta["note"] == "x" and meta["num_frames"] == 6 and meta["model"] == "candide3"
    assert meta["intrinsics"]["width"] == 64 and meta["events"] == [["side_light_on", 2], ["side_light_off", 4]]
    assert len(meta["au_names"]) == gt.au.shape[1]
    assert not list(tmp_path.glob("*.partial*"))


def test_a_ground_truth_saved_under_the_videos_name_is_read_back_by_it(tmp_path):
    """save_ground_truth(gt, "clip.avi") writes clip.avi.gt.npz; load_ground_truth("clip.avi") looked for
    clip.gt.npz alone (the video's stem) and said 'no ground truth'."""
    _, _, gt = _light_switch_small()
    npz, _ = save_ground_truth(gt, tmp_path / "clip.avi")
    assert npz.name == "clip.avi.gt.npz"
    for path in (tmp_path / "clip.avi", npz):
        _assert_gt_equal(load_ground_truth(path), gt)
    save_ground_truth(gt, tmp_path / "clip")  # (both: the stem's own is read first)
    assert load_ground_truth(tmp_path / "clip.avi").name == gt.name
    with pytest.raises(FileNotFoundError, match="other.gt.npz"):
        load_ground_truth(tmp_path / "other.avi")


def test_load_ground_truth_missing(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_ground_truth(tmp_path / "nothing.gt.npz")


def test_video_round_trip_is_lossless(tmp_path):
    gen = torch.Generator().manual_seed(0)
    frames = torch.rand(5, 3, 24, 32, generator=gen)
    codec = write_video(tmp_path / "v.avi", frames, fps=10)
    assert codec.strip() in ("FFV1", "png", "HFYU")  # a lossless codec is available here
    back = read_video(tmp_path / "v.avi")
    assert back.shape == (5, 3, 24, 32)
    expected = torch.from_numpy(frames_to_uint8(frames)).flip(-1).permute(0, 3, 1, 2).float() / 255
    torch.testing.assert_close(back, expected, rtol=0, atol=0)
    # Channel order: a pure red frame stays red (RGB in memory, BGR only on disk).
    red = torch.zeros(1, 3, 8, 8)
    red[:, 0] = 1.0
    write_video(tmp_path / "r.avi", red)
    torch.testing.assert_close(read_video(tmp_path / "r.avi"), red, rtol=0, atol=0)


def test_videos_are_read_from_any_path_like(tmp_path):
    # str() of an os.PathLike that is not a Path is its repr (an os.DirEntry's is "<DirEntry 'v.avi'>"): given to
    # OpenCV, read_video raised "could not read any frame" and iter_video_uint8 yielded no frame, without an error.
    frames = torch.rand(3, 3, 16, 24, generator=torch.Generator().manual_seed(0))
    write_video(tmp_path / "v.avi", frames)
    (entry,) = [e for e in os.scandir(tmp_path) if e.name == "v.avi"]
    torch.testing.assert_close(read_video(entry), read_video(tmp_path / "v.avi"), rtol=0, atol=0)
    assert read_video_uint8(entry, max_frames=2).shape == (2, 3, 16, 24)
    assert len(list(iter_video_uint8(entry))) == 3


def test_video_sink_is_atomic(tmp_path):
    path = tmp_path / "a.avi"
    sink = VideoSink(path, 16, 8)
    sink.write(torch.zeros(2, 3, 8, 16))
    assert not path.exists()  # still being written under a temporary name
    sink.close()
    assert path.exists() and not list(tmp_path.glob("*.partial*"))
    with pytest.raises(ValueError, match="frames"):
        with VideoSink(tmp_path / "b.avi", 16, 8) as s2:
            s2.write(torch.zeros(1, 3, 9, 16))
    assert not (tmp_path / "b.avi").exists() and not list(tmp_path.glob("*.partial*"))


def test_video_sink_names_a_missing_folder_or_a_folder_given_as_the_file(tmp_path):
    """A missing folder, or a folder as the file name, was "no OpenCV video codec among (...) could open ..." (and
    OpenCV's assertion text on stderr for a name without a suffix): each is named, nothing written."""
    VideoSink(tmp_path / "a.avi", 16, 8).close()
    with pytest.raises(FileNotFoundError, match=r"no folder .*nodir to write the video in"):
        VideoSink(tmp_path / "nodir" / "c.avi", 16, 8)
    with pytest.raises(IsADirectoryError, match=r"a folder, not a video file name"):
        write_video(tmp_path, torch.zeros(1, 3, 8, 16))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.avi"]


def test_write_sequence_matches_in_memory_render(tmp_path):
    spec, frames, gt = _light_switch_small()
    seen = []
    files = write_sequence(spec, tmp_path, batch_size=4, progress=lambda d, t: seen.append((d, t)))
    assert seen == [(4, 6), (6, 6)]
    assert files.num_frames == 6 and files.video.name == "light_switch.avi"
    video = read_video(files.video)
    assert video.shape == (6, 3, 48, 64)
    # Lossless: the file holds exactly the 8-bit quantised in-memory frames.
    expected = torch.from_numpy(frames_to_uint8(frames)).flip(-1).permute(0, 3, 1, 2).float() / 255
    torch.testing.assert_close(video, expected, rtol=0, atol=0)
    _assert_gt_equal(load_ground_truth(files.ground_truth), gt)
    meta = json.loads(files.metadata.read_text())
    assert meta["video"] == "light_switch.avi" and meta["codec"] == files.codec.strip()


def test_frames_to_uint8_validation():
    with pytest.raises(ValueError, match="frames"):
        frames_to_uint8(torch.zeros(2, 4, 4))
    out = frames_to_uint8(torch.full((1, 3, 2, 2), 0.5))
    assert out.dtype == np.uint8 and out.shape == (1, 2, 2, 3) and int(out[0, 0, 0, 0]) == 128


def test_landmark_visibility_known_answers():
    from torchface.geometry.camera import Intrinsics
    from torchface.synth.sequence import landmark_visibility

    cam = Intrinsics(320, 240, 100.0, 100.0, 159.5, 119.5)
    tri = torch.tensor([[-50.0, -50, 1], [0, 50, 1], [50, -50, 1]])  # faces the camera (n . v0 < 0)
    # A front triangle at depth 100 and a three times wider one at depth 150 behind it.
    verts = torch.cat([tri * torch.tensor([1.0, 1, 100]), tri * torch.tensor([3.0, 3, 150])])[None]
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [3, 5, 4]])  # front, behind, behind reversed (back-facing)
    pts = torch.tensor([[[0.0, 0.0, 100.0], [0.0, 0.0, 150.0], [0.0, 0.0, 150.0], [120.0, -140.0, 150.0], [0.0, 0.0, 100.5]]])
    pf = torch.tensor([0, 1, 2, 1, 0])
    vis = landmark_visibility(verts, faces, pts, pf, cam)
    # front: visible; behind: hidden; back-facing: not visible; outside the front triangle's shadow
    # (but inside the image): visible; 0.5 % behind the front surface: within the 1 % tolerance.
    assert vis.tolist() == [[True, False, False, True, True]]
    far = torch.tensor([[[200.0, 0.0, 100.0]]])  # projects outside the image
    assert not landmark_visibility(verts, faces, far, torch.tensor([0]), cam).any()
    # Batched == per sample.
    both = landmark_visibility(torch.cat([verts, verts.flip(1)]), faces, pts.expand(2, -1, -1), pf, cam)
    assert both[0].tolist() == vis[0].tolist()


@pytest.mark.parametrize("opencv_default", ["installed", "4.11"])
def test_video_readers_turn_a_phone_video_as_the_trackers_input_reader_does(tmp_path, monkeypatch, opencv_default):
    """``read_video_uint8`` / ``iter_video_uint8`` opened a video with a plain ``cv2.VideoCapture``: under OpenCV
    4.11's default (display rotation not applied) a phone's portrait video came out landscape, 64x48, where the
    tracker's reader (``torchface.io.open_frames``) gives 48x64 as displayed. They open it the same way now; a file
    that is no video is a ValueError (``iter_video_uint8`` yielded no frame without a word)."""
    import sys
    from pathlib import Path

    import cv2

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from _helpers import opencv_411_capture, write_rotated_mp4

    from torchface.io import open_frames

    stored = np.kron(np.random.default_rng(0).integers(0, 256, (2, 6, 8, 3)), np.ones((1, 8, 8, 1))).astype(np.uint8)
    write_rotated_mp4(tmp_path / "phone.mp4", stored, 90)
    with open_frames(tmp_path / "phone.mp4") as reader:
        want = torch.stack([(frame * 255).round().to(torch.uint8) for frame in reader])  # (2, 3, 64, 48)
    if opencv_default == "4.11":
        monkeypatch.setattr(cv2, "VideoCapture", opencv_411_capture)
    assert want.shape == (2, 3, 64, 48)
    torch.testing.assert_close(read_video_uint8(tmp_path / "phone.mp4"), want, rtol=0, atol=0)
    torch.testing.assert_close(torch.cat(list(iter_video_uint8(tmp_path / "phone.mp4"))), want, rtol=0, atol=0)
    (tmp_path / "notes.avi").write_text("not a video\n")
    for read in (read_video_uint8, lambda p: list(iter_video_uint8(p))):
        with pytest.raises(ValueError, match=r"notes\.avi: OpenCV cannot open this file as a video"):
            read(tmp_path / "notes.avi")


def test_video_sink_that_cannot_write_its_file_says_why(tmp_path, monkeypatch):
    """Where the file cannot be written (a read-only folder; its temporary name taken by a folder) OpenCV's writer
    fails without a word: "no OpenCV video codec among (...) could open ...", a RuntimeError that ``render-demo``
    printed as a traceback. Now the OSError of the file system, naming the file (``render-demo``: one line)."""
    import torchface.synth.io as synth_io

    taken = tmp_path / "b.partial-1-0123abcd.avi"  # (its name is the process's own: taken by a folder here)
    taken.mkdir()
    monkeypatch.setattr(synth_io, "partial_path", lambda path: taken)
    with pytest.raises(IsADirectoryError) as info:
        VideoSink(tmp_path / "b.avi", 16, 8)
    assert info.value.filename == str(taken)
    monkeypatch.undo()
    if os.geteuid() != 0:  # (root writes in a read-only folder)
        folder = tmp_path / "read_only"
        folder.mkdir()
        folder.chmod(0o500)
        try:
            with pytest.raises(PermissionError):
                VideoSink(folder / "c.avi", 16, 8)
            assert list(folder.iterdir()) == []
        finally:
            folder.chmod(0o700)


def test_write_sequence_stopped_partway_never_leaves_a_new_video_beside_an_older_ground_truth(tmp_path, monkeypatch):
    """write_sequence renamed the new video onto the old one and only then saved the ground truth: a Ctrl-C between
    the two left a 4-frame video beside the 6-frame sequence's ``.gt.npz``, which a reader takes for its pair. Now the
    older ground truth goes before the video's rename and the new ``.gt.npz`` comes last: stopped while rendering,
    the older pair stays whole; stopped after the video, no ``.gt.npz`` is left."""
    import torchface.synth.sequence as sequence

    write_sequence(make_scenario("light_switch", 6, 64, 48), tmp_path)
    shorter = make_scenario("light_switch", 4, 64, 48)

    real = sequence.iter_sequence

    def stopped_while_rendering(spec, batch_size):
        yield next(real(spec, batch_size))  # a chunk written to the partial video, then Ctrl-C
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(sequence, "iter_sequence", stopped_while_rendering)
        with pytest.raises(KeyboardInterrupt):
            write_sequence(shorter, tmp_path)
    assert read_video(tmp_path / "light_switch.avi").shape[0] == 6 == load_ground_truth(tmp_path / "light_switch").num_frames

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(np, "savez_compressed", interrupted)
        with pytest.raises(KeyboardInterrupt):
            write_sequence(shorter, tmp_path)
    assert read_video(tmp_path / "light_switch.avi").shape[0] == 4
    with pytest.raises(FileNotFoundError):
        load_ground_truth(tmp_path / "light_switch")
    assert not list(tmp_path.glob("*.partial*"))
    files = write_sequence(shorter, tmp_path)  # a run again makes the pair whole
    assert load_ground_truth(files.ground_truth).num_frames == 4 == read_video(files.video).shape[0]


def _interleaved(monkeypatch, other):
    """Run ``other()`` (a second writer of the same files) while this process's ``write_sequence`` renders: after its
    first chunk has gone to the temporary video."""
    import torchface.synth.sequence as sequence

    real, calls = sequence.iter_sequence, []

    def with_another_writer(spec, batch_size):
        chunks = real(spec, batch_size)
        yield next(chunks)
        if not calls:
            calls.append(1)
            other()
        yield from chunks

    monkeypatch.setattr(sequence, "iter_sequence", with_another_writer)
    return calls


def test_two_writers_of_one_sequence_each_write_their_own_temporary_files(tmp_path, monkeypatch):
    """write_sequence wrote every run's video to ``<name>.avi.partial.avi`` and its ground truth to
    ``<name>.gt.npz.partial.npz`` / ``.gt.json.partial``: two runs rendering one sequence into one folder (evaluate.py
    and confidence_auroc.py sharing a ``--cache``) wrote into the same temporary file, the first to finish renamed it
    away and the other's rename failed (FileNotFoundError), and a failing run's cleanup deleted the other's file. Now
    each writer's temporary names are its own: both finish, the pair is whole, nothing temporary is left."""
    spec, frames, gt = _light_switch_small()
    calls = _interleaved(monkeypatch, lambda: write_sequence(spec, tmp_path, batch_size=4))
    files = write_sequence(spec, tmp_path, batch_size=4)
    assert calls == [1]
    expected = torch.from_numpy(frames_to_uint8(frames)).flip(-1).permute(0, 3, 1, 2).float() / 255
    torch.testing.assert_close(read_video(files.video), expected, rtol=0, atol=0)
    _assert_gt_equal(load_ground_truth(files.ground_truth), gt)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"light_switch{s}" for s in (".avi", ".gt.json", ".gt.npz")]


def test_a_failing_writer_of_one_sequence_leaves_the_other_writers_files(tmp_path, monkeypatch):
    """The other writer stopped while rendering (Ctrl-C): its cleanup removed the shared ``.partial.avi`` that this
    run was still writing, whose rename then failed. Now it removes its own alone."""
    import torchface.synth.sequence as sequence

    spec, frames, gt = _light_switch_small()
    real = sequence.iter_sequence

    def stopped():
        def stopped_while_rendering(spec, batch_size):
            yield next(real(spec, batch_size))
            raise KeyboardInterrupt

        with monkeypatch.context() as m:
            m.setattr(sequence, "iter_sequence", stopped_while_rendering)
            with pytest.raises(KeyboardInterrupt):
                write_sequence(spec, tmp_path, batch_size=4)

    _interleaved(monkeypatch, stopped)
    files = write_sequence(spec, tmp_path, batch_size=4)
    assert read_video(files.video).shape[0] == 6
    _assert_gt_equal(load_ground_truth(files.ground_truth), gt)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"light_switch{s}" for s in (".avi", ".gt.json", ".gt.npz")]


_WRITER = """
import sys, time
from pathlib import Path
import torchface.synth.io as synth_io
import torchface.synth.sequence as sequence
from torchface.synth.scenarios import make_scenario

folder, frames, before_video, before_truth = Path(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
real_iter, real_close, real_save = sequence.iter_sequence, synth_io.VideoSink.close, sequence.save_ground_truth

def rendered_then_both(spec, batch_size):  # both writers put their files in place at once
    yield from real_iter(spec, batch_size)
    (folder.parent / f"ready-{frames}").touch()
    while len(list(folder.parent.glob("ready-*"))) < 2:
        time.sleep(0.005)

def close(self):
    time.sleep(before_video)
    return real_close(self)

def save(*args, **kwargs):
    time.sleep(before_truth)
    return real_save(*args, **kwargs)

sequence.iter_sequence, synth_io.VideoSink.close, sequence.save_ground_truth = rendered_then_both, close, save
sequence.write_sequence(make_scenario("light_switch", frames, 32, 24), folder)
"""


def test_two_writers_finishing_together_leave_one_writers_video_and_ground_truth(tmp_path):
    """Two processes write one sequence name (2 and 3 frames) into one folder and finish together: the first renames
    its video and is slow to save its ground truth, the second renames its video later and saves at once. Without a
    lock the folder held the second's 3-frame video beside the first's 2-frame ground truth; now whichever goes first
    puts both its files in place before the other begins (:func:`torchface._atomic.folder_locked`): the video and
    the ground truth are one writer's, and nothing else is left in the folder."""
    import subprocess
    import sys

    folder = tmp_path / "seq"
    folder.mkdir()
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    writers = [subprocess.Popen([sys.executable, "-c", _WRITER, str(folder), *args], env=env)
               for args in (("2", "0", "0.8"), ("3", "0.3", "0"))]  # fmt: skip
    assert [w.wait(timeout=120) for w in writers] == [0, 0]
    truth = load_ground_truth(folder / "light_switch")
    assert read_video(folder / "light_switch.avi").shape[0] == truth.num_frames
    assert json.loads((folder / "light_switch.gt.json").read_text())["num_frames"] == truth.num_frames
    assert sorted(p.name for p in folder.iterdir()) == [f"light_switch{s}" for s in (".avi", ".gt.json", ".gt.npz")]


@pytest.mark.skipif(os.name != "posix", reason="fcntl")
def test_a_folder_that_cannot_be_flocked_is_locked_by_a_file_in_it(tmp_path, monkeypatch):
    """NFS's flock is a record lock, which wants a file open for writing: on a folder it is EBADF (and a folder
    without read permission cannot be opened): folder_locked raised, and write_sequence into such a folder failed.
    Now it locks a file in the folder, and another process, or another thread of this one, waits for it."""
    import errno
    import fcntl
    import subprocess
    import sys
    import threading

    from torchface._atomic import LOCK_FILE, folder_locked

    def nfs_flock(fd, op):
        raise OSError(errno.EBADF, "Bad file descriptor")

    monkeypatch.setattr(fcntl, "flock", nfs_flock)
    other = "import fcntl, os, sys; fcntl.lockf(os.open(sys.argv[1], os.O_RDWR), fcntl.LOCK_EX | fcntl.LOCK_NB)"
    entered = threading.Event()

    def second() -> None:
        with folder_locked(tmp_path):
            entered.set()

    with folder_locked(tmp_path):
        held = subprocess.run([sys.executable, "-c", other, str(tmp_path / LOCK_FILE)], capture_output=True, text=True)
        thread = threading.Thread(target=second)
        thread.start()
        assert not entered.wait(0.2)  # (another thread of this process waits too: a record lock is the process's)
    thread.join(10)
    assert entered.is_set()
    assert held.returncode != 0 and "BlockingIOError" in held.stderr  # (held while in the block)
    assert subprocess.run([sys.executable, "-c", other, str(tmp_path / LOCK_FILE)]).returncode == 0  # (then free)
    files = write_sequence(make_scenario("light_switch", 2, 32, 24), tmp_path / "seq")
    assert load_ground_truth(files.ground_truth).num_frames == 2


def test_a_lock_file_that_cannot_be_locked_on_windows_says_so(tmp_path, monkeypatch):
    """Where there is no fcntl, msvcrt's LK_LOCK raises EDEADLOCK after 10 s of waiting and is asked again; any
    other error (a bad descriptor, a share without locks) was asked again too, for ever: now it is raised."""
    import errno
    import sys
    import types

    from torchface._atomic import folder_locked

    calls = []

    def locking(fd, mode, n):
        calls.append(mode)
        if len(calls) == 1:
            raise OSError(errno.EBADF, "Bad file descriptor")

    monkeypatch.setitem(sys.modules, "fcntl", None)  # (import fcntl: ImportError)
    monkeypatch.setitem(sys.modules, "msvcrt", types.SimpleNamespace(LK_LOCK=1, LK_UNLCK=0, locking=locking))
    with pytest.raises(OSError, match="Bad file descriptor"), folder_locked(tmp_path):
        pass
    assert calls == [1]


def test_two_writers_of_one_ground_truth_each_write_their_own(tmp_path, monkeypatch):
    """save_ground_truth's temporary ``.gt.npz.partial.npz`` was every writer's: another writer's save between this
    one's write and rename took this one's file (its rename: FileNotFoundError); another writer failing partway left
    its half-written file where this one renamed it into place (a truncated ``.gt.npz``). Now each has its own, and a
    failed one's is removed."""
    _, _, gt = _light_switch_small()
    real = np.savez_compressed

    def other_writer_between(fail):
        def savez(file, **arrays):
            real(file, **arrays)
            if savez.nested:
                return
            savez.nested = True
            if fail:
                def half(file, **arrays):
                    open(file, "wb").write(b"PK\x03\x04 half")
                    raise KeyboardInterrupt

                with monkeypatch.context() as m:
                    m.setattr(np, "savez_compressed", half)
                    with pytest.raises(KeyboardInterrupt):
                        save_ground_truth(gt, tmp_path / "seq")
            else:
                save_ground_truth(gt, tmp_path / "seq")

        savez.nested = False
        return savez

    for fail in (False, True):
        with monkeypatch.context() as m:
            m.setattr(np, "savez_compressed", other_writer_between(fail))
            npz, js = save_ground_truth(gt, tmp_path / "seq")
        _assert_gt_equal(load_ground_truth(npz), gt)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["seq.gt.json", "seq.gt.npz"], fail


def _dead_pid() -> int:
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()  # (reaped: its pid names no process)
    return child.pid


def test_write_sequence_removes_its_temporary_files_left_by_a_killed_run(tmp_path):
    """A run killed outright (kill -9) leaves its temporary files, a new one each time now that the names are each
    process's own: write_sequence removes those of its own sequence whose process is gone, and nothing else (a running
    process's, another sequence's, a file that only looks alike)."""
    import subprocess
    import sys

    spec, _, gt = _light_switch_small()
    dead, alive = _dead_pid(), os.getppid()
    code = ("import time; from torchface.synth.io import VideoSink\n"
            f"s = VideoSink({str(tmp_path / 'light_switch.avi')!r}, 16, 8); print(s._tmp, flush=True); time.sleep(60)")
    root = str(Path(__file__).resolve().parents[2])  # (this checkout's torchface)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")])}
    killed = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=env)
    left = Path(killed.stdout.readline().strip())
    killed.kill()  # (SIGKILL: kill -9)
    killed.wait()
    assert left.is_file() and left.parent == tmp_path
    gone = [left, tmp_path / f"light_switch.gt.partial-{dead}-0123abcd.npz",
            tmp_path / f"light_switch.gt.partial-{dead}-89abcdef.json"]
    kept = [tmp_path / f"light_switch.partial-{alive}-0123abcd.avi",  # a running process's
            tmp_path / f"light_switch.partial-{os.getpid()}-0123abcd.avi",
            tmp_path / f"pose_sweep.partial-{dead}-0123abcd.avi",  # another sequence's
            tmp_path / f"light_switch.partial-{dead}-0123abcdx.avi",  # not such a name
            tmp_path / f"light_switch.avi.partial-{dead}-0123abcd"]
    for p in gone[1:] + kept:
        p.write_bytes(b"")
    (tmp_path / f"light_switch.partial-{dead}-deadbeef.avi").mkdir()  # a folder: not touched
    write_sequence(spec, tmp_path, batch_size=4)
    assert not any(p.exists() for p in gone) and all(p.exists() for p in kept)
    assert (tmp_path / f"light_switch.partial-{dead}-deadbeef.avi").is_dir()
    _assert_gt_equal(load_ground_truth(tmp_path / "light_switch"), gt)


def _spec_fields(spec):
    return {f.name: getattr(spec, f.name) for f in fields(spec)}


def test_sequence_spec_refuses_what_renders_nan_nothing_or_no_rotation():
    """A NaN pose, expression, shape or light rendered frames of background (or NaN frames, for the light) with NaN
    landmarks; a scaled or mirrored matrix a scaled or mirrored head whose ground truth was no rotation; a head
    behind the camera nothing; tensors off the CPU failed deep in the renderer; a name with a "/" or an event past the
    end were taken: each is refused, naming the field."""
    from torchface.rendering.shading import LightState

    from torchface.synth.sequence import SequenceSpec

    good = _spec_fields(make_scenario("pose_sweep", 2, 32, 24))
    R, t, light = good["rotation"], good["translation"], good["light"]
    nan = float("nan")
    for change, error, match in [
        ({"rotation": torch.full_like(R, nan)}, ValueError, "^rotation must be finite"),
        ({"rotation": 2.0 * R}, ValueError, r"^rotation must hold rotation .*frame 0's is off by 3 with det 8"),
        ({"rotation": -R}, ValueError, r"^rotation must hold rotation matrices .* det -1"),
        ({"rotation": R.numpy()}, TypeError, r"^rotation must be a torch.Tensor, got ndarray \(torch.from_numpy"),
        ({"rotation": R.to("meta")}, ValueError, r"^rotation must be on the CPU"),
        ({"translation": t.clone().index_fill_(1, torch.tensor([2]), float("inf"))}, ValueError,
         "^translation must be finite"),
        ({"translation": -t}, ValueError, r"^translation\[:, 2\] must be > 0, .*millimetres.*got -4\d\d.* at frame 0"),
        ({"anim": torch.full_like(good["anim"], nan)}, ValueError, "^anim must be finite"),
        ({"shape_coeffs": torch.full((14,), nan)}, ValueError, "^shape_coeffs must be finite"),
        ({"light": LightState(torch.full((2,), nan), light.directions, light.intensities)}, ValueError,
         "^light.ambient must be finite"),
        ({"light": LightState(light.ambient, light.directions, -light.intensities)}, ValueError, "must be >= 0"),
        ({"light": LightState(light.ambient, 0 * light.directions, light.intensities)}, ValueError,
         "^light.directions must not be zero"),
        ({"name": "a/b"}, ValueError, "^name must be a file stem"),
        ({"name": ""}, ValueError, "^name must be a file stem"),
        ({"events": (("on", 3),)}, ValueError, r"^events must be \(label, frame\) pairs.* 0 \.\. 2"),
    ]:
        with pytest.raises(error, match=match):
            SequenceSpec(**{**good, **change})
    ok = SequenceSpec(**{**good, "events": [("on", np.int64(1))], "rotation": R.float()})  # (float32 rotations taken)
    assert ok.events == (("on", 1),) and type(ok.events[0][1]) is int


def test_render_warns_of_units_outside_their_range_and_of_a_face_in_no_frame(tmp_path):
    """Animation units beyond the subject's ranges (which the tracker clamps its estimate to) and a sequence whose
    face shows in no frame (a translation in metres) rendered without a word."""
    from torchface.synth.sequence import SequenceSpec

    good = _spec_fields(make_scenario("pose_sweep", 2, 32, 24))
    anim = good["anim"].clone()
    anim[:, 1] = 3.0  # Jaw drop: [0, 1.5]
    with pytest.warns(UserWarning, match=r"'AUV11 Jaw drop' goes to 3 \.\. 3, outside its range \[0, 1.5\]") as seen:
        render_sequence(SequenceSpec(**{**good, "anim": anim}))
    assert len([w for w in seen if "outside its range" in str(w.message)]) == 1  # (said once, not per chunk)
    with pytest.warns(UserWarning, match="outside its range") as seen:
        write_sequence(SequenceSpec(**{**good, "anim": anim}), tmp_path, batch_size=1)
    assert len([w for w in seen if "outside its range" in str(w.message)]) == 1
    with pytest.warns(RuntimeWarning, match=r"no frame of 'pose_sweep' shows the face .*millimetres"):
        render_sequence(SequenceSpec(**{**good, "translation": good["translation"] / 1000.0}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        render_sequence(SequenceSpec(**good))


def test_write_video_refuses_frames_it_would_write_as_something_else(tmp_path):
    """0-255 float frames were clipped to a white video, NaN ones written black, no frame written as a video that
    read_video could not read, a numpy array failed with "no attribute 'detach'", fps 0 or NaN and a .npy or .mpg name
    as "no OpenCV video codec ... could open" (.mpg: written, then unreadable); nothing is written now."""
    frames = torch.rand(2, 3, 8, 16)
    for call, error, match in [
        (lambda: write_video(tmp_path / "a.avi", frames * 255), ValueError,
         r"^frames must be float in \[0, 1\], got values from .* \(0-255 values\? divide by 255\)"),
        (lambda: write_video(tmp_path / "a.avi", frames.index_fill(0, torch.tensor([1]), float("nan"))), ValueError,
         "^frames must be finite"),
        (lambda: write_video(tmp_path / "a.avi", frames[:0]), ValueError, "^frames must hold at least one frame"),
        (lambda: write_video(tmp_path / "a.avi", frames.numpy()), TypeError, r"got ndarray \(torch.from_numpy"),
        (lambda: write_video(tmp_path / "a.avi", frames.double().to(torch.int64)), TypeError, "float in .* or uint8"),
        (lambda: write_video(tmp_path / "a.avi", frames, fps=0), ValueError, "^fps must be a finite number > 0, got 0"),
        (lambda: write_video(tmp_path / "a.npy", frames), ValueError, r"\.avi, .*got '\.npy' \(a \.npy clip: np"),
        (lambda: write_video(tmp_path / "a.mpg", frames), ValueError, r"got '\.mpg'"),
        (lambda: write_video(tmp_path / "a", frames), ValueError, "got 'no suffix'"),
    ]:
        with pytest.raises(error, match=match):
            call()
    assert list(tmp_path.iterdir()) == []
    write_video(tmp_path / "b.mkv", (frames * 255).round().to(torch.uint8))  # (uint8 taken, .mkv too)
    torch.testing.assert_close(read_video(tmp_path / "b.mkv"), (frames * 255).round() / 255, rtol=0, atol=0)
    for bad in (0, -1):  # ("could not read any frame" of a good video)
        with pytest.raises(ValueError, match=f"^max_frames must be an int >= 1, got {bad}$"):
            read_video(tmp_path / "b.mkv", max_frames=bad)
    assert read_video(tmp_path / "b.mkv", max_frames=1).shape == (1, 3, 8, 16)


def test_ground_truth_files_name_a_missing_folder_a_foreign_npz_and_a_fractional_batch(tmp_path):
    """save_ground_truth into a missing folder named a temporary file; load_ground_truth of another .npz raised
    KeyError('intrinsics'); batch_size=2.5 failed in range()."""
    spec, _, gt = _light_switch_small()
    with pytest.raises(FileNotFoundError, match=r"no folder .*nodir to write the ground truth in$"):
        save_ground_truth(gt, tmp_path / "nodir" / "seq")
    np.savez(tmp_path / "other.gt.npz", a=np.zeros(2))
    with pytest.raises(ValueError, match=r"other.gt.npz: not a ground truth of save_ground_truth, it lacks intrinsics"):
        load_ground_truth(tmp_path / "other.mov")  # (a .mov video's stem, as .avi's)
    with pytest.raises(TypeError, match="^batch_size must be an int >= 1, got float 2.5$"):
        render_sequence(spec, batch_size=2.5)


def test_a_spec_whose_tensors_require_grad_is_written_whole(tmp_path):
    """A rotation that required grad gave a ground truth that did too: save_ground_truth failed ("Can't call numpy()
    on Tensor that requires grad") and write_sequence left the video without its ground truth."""
    from dataclasses import replace

    import warnings

    spec = make_scenario("pose_sweep", 2, 32, 24)
    with warnings.catch_warnings():  # (nor torch's "Converting a tensor with requires_grad=True to a scalar")
        warnings.filterwarnings("error", message=".*requires_grad")
        files = write_sequence(replace(spec, rotation=spec.rotation.clone().requires_grad_()), tmp_path)
    torch.testing.assert_close(load_ground_truth(files.video).rotation, spec.rotation, rtol=0, atol=0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pose_sweep.avi", "pose_sweep.gt.json", "pose_sweep.gt.npz"]
