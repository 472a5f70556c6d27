"""``torchface track --resume`` of a video interrupted after the online start's frames, from the checkpoint the
interrupted run wrote (``<stem>.state.partial``, ``torchface.job._write_checkpoints``): its tracker state with the
templates and the mosaic, pose filter and bookkeeping, so that the resumed CSV and videos are the uninterrupted
run's, byte for byte (from the CSV's last row alone, without the mosaic, they were not)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import torchface.job
from torchface.io import read_track_csv
from torchface.job import JobConfig, track_videos
from torchface.synth.io import read_video
from torchface.synth.scenarios import make_scenario
from torchface.synth.sequence import load_ground_truth, write_sequence
from torchface.tracker.lookahead import LookaheadConfig
from torchface.tracker.smoothing import SmoothingConfig

#: Frames of the clips; the online start watches MAX_FRAMES of them, a checkpoint every EVERY frames (at 4 and 8
#: rows), and the runs are interrupted after STOP rows: resumed from the checkpoint at 8 rows, rows 9-10 again.
N, MAX_FRAMES, EVERY, STOP = 12, 4, 4, 10
ONLINE = LookaheadConfig(max_frames=MAX_FRAMES)
OUTPUTS = (".csv", "_overlay.mp4", "_normalised.mp4")


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    """Two clips of ``pose_sweep`` (160x120, its head turning), from its frames 0 and 3, with their first
    frames' landmarks."""
    root = tmp_path_factory.mktemp("sweep")
    files = write_sequence(make_scenario("pose_sweep", 40, 160, 120), root)
    gt = load_ground_truth(files.ground_truth)
    frames = read_video(files.video, max_frames=N + 3)
    out = []
    for name, start in (("a", 0), ("b", 3)):
        lm = root / f"{name}.csv"
        np.savetxt(lm, gt.landmarks_px[start].numpy(), delimiter=",", header="x,y", comments="")
        video = root / f"{name}.npy"
        np.save(video, (frames[start : start + N].permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8))
        out.append((video, lm))
    return out


@pytest.fixture(scope="module")
def batch_ref(clips, tmp_path_factory) -> Path:
    """The folder of both clips' outputs, tracked uninterrupted as one batch (read only: shared by the tests that
    compare a resumed batch with it)."""
    ref = tmp_path_factory.mktemp("ref")
    with pytest.MonkeyPatch.context() as m:  # (as every test here tracks: the checkpoints change no output)
        m.setattr(torchface.job, "CHECKPOINT_EVERY", EVERY)
        track_videos([v for v, _ in clips], _config(ref, clips))
    return ref


@pytest.fixture(autouse=True)
def every(monkeypatch):
    monkeypatch.setattr(torchface.job, "CHECKPOINT_EVERY", EVERY)


def _config(out: Path, clips, **kwargs) -> JobConfig:
    kwargs.setdefault("refine_first", ONLINE)
    return JobConfig(out_dir=out, landmarks=tuple(lm for _, lm in clips), **kwargs)


def _interrupted(clips, out: Path, **kwargs) -> None:
    def interrupt(p):
        if p.done == STOP and p.index == len(clips) - 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        track_videos([v for v, _ in clips], _config(out, clips, **kwargs), progress=interrupt)
    for v, _ in clips:
        assert read_track_csv(out / f"{v.stem}.csv.partial")[1].shape[0] == STOP
        assert (out / f"{v.stem}.state.partial").is_file()


def _resumed_without_its_checkpoint(clips, out: Path, said_first: str) -> dict:
    """Resume the first clip in ``out``: one warning about its checkpoint, starting ``said_first``, and the video
    complete from its CSV's rows (``resumed.checkpoint`` False, N rows). The sidecar's ``resumed``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        track_videos([clips[0][0]], _config(out, clips, resume=True))
    said = [str(w.message) for w in caught if "state.partial" in str(w.message)]
    assert len(said) == 1 and said[0].startswith(said_first), said
    assert "\n" not in said[0]
    resumed = json.loads((out / "a.json").read_text())["resumed"]
    assert resumed["checkpoint"] is False
    assert read_track_csv(out / "a.csv")[1].shape[0] == N
    return resumed


def _same_outputs(a: Path, b: Path, names) -> list[str]:
    """The outputs of ``names`` whose bytes differ between folders ``a`` and ``b``."""
    return [n + s for n in names for s in OUTPUTS if (a / (n + s)).read_bytes() != (b / (n + s)).read_bytes()]


@pytest.mark.parametrize("count, smoothing, detector, turn", [
    (1, None, False, 10.0), (2, SmoothingConfig(), False, 10.0), (1, None, True, 10.0), (1, None, False, 80.0),
], ids=["alone", "batch-smooth", "detector", "not-reanchored"])  # fmt: skip
def test_resume_from_a_checkpoint_is_the_uninterrupted_run(clips, tmp_path, monkeypatch, count, smoothing, detector,
                                                          turn):  # fmt: skip
    """Interrupted after STOP rows (and its last row cut off, as a SIGKILL may leave it), alone or beside another
    video of its batch (alone: with ``--meshes``, its meshes compared too), with or without ``--smooth``, or with a
    detector re-detecting every other frame (one made after the checkpoint's row): resumed from the checkpoint at 8
    rows (rows 9 and 10 cut off and tracked again) on another CPU thread count than the interrupted run's, the CSVs,
    overlays and normalised videos are the uninterrupted run's, byte for byte; the sidecar says so (and both thread
    counts) (``resumed.checkpoint``) and no checkpoint is left; its detector counts (``detector_calls``,
    ``redetections``, ``restart_failures``) are the whole video's, the uninterrupted run's (they were this run's
    alone: those of the rows after the checkpoint). (From the CSV's
    last row, without the template mosaic, the pose filter's state and the rest, the resumed rows parted from the
    uninterrupted ones: byte-identical before this change only where rows < max_frames were tracked again. The
    detector's re-fit left the state's cached angles untied from its parameters, which the join refused, and the
    checkpoint was not used; a video the online start had not re-anchored (its head not turning ``turn`` degrees)
    had its sidecar say ``landmark fit`` where the uninterrupted run said ``online``.)"""
    clips = clips[:count]
    names = [v.stem for v, _ in clips]
    kwargs: dict = {"smoothing": smoothing, "meshes": count == 1 and not detector and turn == 10.0,
                    "refine_first": LookaheadConfig(max_frames=MAX_FRAMES, yaw_deg=turn)}
    if detector:
        import torchface.detect

        first = np.loadtxt(clips[0][1], delimiter=",", skiprows=1)
        monkeypatch.setitem(torchface.detect.DETECTORS, "first", lambda: lambda image_rgb: first.copy())
        kwargs.update(detector="first", redetect_after=2, redetect_below=1.01)  # (every frame low)
    track_videos([v for v, _ in clips], _config(tmp_path / "ref", clips, **kwargs))
    if detector:
        assert json.loads((tmp_path / "ref" / "a.json").read_text())["redetections"] > 0
    out = tmp_path / "out"
    _interrupted(clips, out, **kwargs)
    with open(out / f"{names[0]}.csv.partial", "a") as f:  # (a row cut off by a SIGKILL)
        f.write(f"{STOP},0.4,1")
    data = torch.load(out / f"{names[0]}.state.partial", weights_only=True)  # (tensors and plain data only)
    threads = torch.get_num_threads()
    assert data["rows"] == 8 and data["batch"] == names and data["threads"] == threads
    other = 1 if threads > 1 else 2  # resumed on another thread count: the same rows (it changes no result)
    try:
        torch.set_num_threads(other)
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # (the checkpoints matched: no warning)
            track_videos([v for v, _ in clips], _config(out, clips, resume=True, **kwargs))
    finally:
        torch.set_num_threads(threads)
    assert _same_outputs(tmp_path / "ref", out, names) == []
    if kwargs["meshes"]:  # (the meshes of the rows cut off written again)
        ref, got = sorted((tmp_path / "ref" / "a_meshes").iterdir()), sorted((out / "a_meshes").iterdir())
        assert [p.name for p in got] == [p.name for p in ref] and len(ref) == N
        assert all(p.read_bytes() == q.read_bytes() for p, q in zip(ref, got))
    for n in names:
        side, ref = (json.loads((d / f"{n}.json").read_text()) for d in (out, tmp_path / "ref"))
        assert side["resumed"]["checkpoint"] == "exact"
        assert side["resumed"]["threads"] == {"checkpoint": threads, "now": other}
        assert not (out / f"{n}.state.partial").exists()
        for d in (side, ref):  # (the rest of the sidecar, its start and final shape included, is the same too)
            for key in ("resumed", "timings_s", "outputs"):  # (the detector's counts: the whole video's)
                del d[key]
            del d["config"]["resume"]
        assert side == ref
        assert side["start"]["method"] == "online"
        assert turn == 10.0 or side["start"]["reanchored_at_frame"] is None


def test_without_its_checkpoint_the_resumed_rows_part(clips, tmp_path):
    """What the checkpoint is for: the same interruption resumed without it (removed) goes on from the CSV's last
    row, and its rows part from the uninterrupted run's."""
    clips = clips[:1]
    track_videos([clips[0][0]], _config(tmp_path / "ref", clips))
    out = tmp_path / "out"
    _interrupted(clips, out)
    (out / "a.state.partial").unlink()
    track_videos([clips[0][0]], _config(out, clips, resume=True))
    assert json.loads((out / "a.json").read_text())["resumed"]["checkpoint"] is False
    assert _same_outputs(tmp_path / "ref", out, ["a"])[:1] == ["a.csv"]


@pytest.mark.parametrize("damage", ["row", "file", "truncated"])
def test_a_checkpoint_that_does_not_match_is_refused_with_a_warning(clips, tmp_path, damage):
    """A checkpoint whose last row is not the CSV's (a row edited) or that cannot be read (damaged) is not used:
    one warning line naming it, and the video goes on from its CSV's rows, as before (none cut off)."""
    clips = clips[:1]
    out = tmp_path / "out"
    _interrupted(clips, out)
    ck = out / "a.state.partial"
    if damage == "file":
        ck.write_bytes(b"not a checkpoint")
    elif damage == "truncated":  # (its first half: a file cut off)
        ck.write_bytes(ck.read_bytes()[: ck.stat().st_size // 2])
    else:
        partial = out / "a.csv.partial"
        lines = partial.read_text().splitlines(keepends=True)
        cells = lines[8].split(",")  # (row 8: the checkpoint's last)
        cells[2] = "0.5" if cells[2] != "0.5" else "0.25"
        lines[8] = ",".join(cells)
        partial.write_text("".join(lines))
    assert _resumed_without_its_checkpoint(clips, out, f"{ck}: not used (")["rows"] == STOP


def test_a_batch_resumed_in_smaller_batches_goes_on_from_its_checkpoints(clips, batch_ref, tmp_path):
    """A batch's videos resumed with a smaller ``max_batch`` are tracked in parts of their batch, each part's states
    joined alone: every video goes on from its checkpoint, without a warning, its rows those of the uninterrupted
    run to float rounding (the batch's composition: not to the byte)."""
    out = tmp_path / "out"
    _interrupted(clips, out)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        track_videos([v for v, _ in clips], _config(out, clips, resume=True, max_batch=1))
    for v, _ in clips:
        assert json.loads((out / f"{v.stem}.json").read_text())["resumed"]["checkpoint"] == "split"
        ref, got = (read_track_csv(d / f"{v.stem}.csv")[1] for d in (batch_ref, out))
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-4, err_msg=v.stem)


def test_a_state_that_cannot_be_kept_tracks_on_without_checkpoints(clips, tmp_path, monkeypatch):
    """A state holding what plain data cannot (here: ``to_plain`` refusing it, as it would a value of a kind added
    to the state that it does not know) does not stop the tracking: one warning, no checkpoint, the outputs those
    of a run with checkpoints."""
    import torchface._checkpoint

    clips = clips[:1]
    track_videos([clips[0][0]], _config(tmp_path / "ref", clips))

    def refuse(tree):
        raise TypeError("cannot keep a Thing as plain data")

    monkeypatch.setattr(torchface._checkpoint, "to_plain", refuse)
    out = tmp_path / "out"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        track_videos([clips[0][0]], _config(out, clips))
    said = [str(w.message) for w in caught if "checkpoint" in str(w.message)]
    assert said == ["no checkpoints written (cannot keep a Thing as plain data): an interrupted run resumes from its "
                    "CSV's rows"]  # fmt: skip
    assert _same_outputs(tmp_path / "ref", out, ["a"]) == []


@pytest.mark.parametrize("other", ["version", "device", "dtype"])
def test_a_checkpoint_of_another_version_device_or_dtype_is_not_used(clips, tmp_path, monkeypatch, other):
    """A checkpoint made by another torchface version, on another device or in another dtype (which the settings,
    compared for a resume from the CSV's rows, do not hold) is not restored: one warning line saying which, and the
    video goes on from its CSV's rows (``resumed.checkpoint`` false). (Before, it was restored, its tensors moved to
    this run's device, and the sidecar said the rows were the uninterrupted run's.) This machine has one device and
    the job one dtype: the checkpoint is told it was made on another."""
    import torchface

    clips = clips[:1]
    out = tmp_path / "out"
    _interrupted(clips, out)
    ck = out / "a.state.partial"
    if other == "version":
        monkeypatch.setattr(torchface, "__version__", "0.0.9")
        said_other = "torchface 0.1.0, now 0.0.9"
    else:
        data = torch.load(ck, weights_only=True)
        value = {"device": "cuda:0", "dtype": "float64"}[other]
        data["origin"] = {**data.get("origin", {}), other: value}
        torch.save(data, ck)
        said_other = f"{other} {value}, now {'cpu' if other == 'device' else 'float32'}"
    resumed = _resumed_without_its_checkpoint(clips, out, f"{ck}: not used (made with another {said_other})")
    assert resumed["rows"] == STOP
    assert not ck.exists()


def test_a_temporary_checkpoint_cut_off_is_removed_with_the_video_complete(clips, tmp_path, monkeypatch):
    """A temporary checkpoint (``<stem>.state.partial.tmp``) left by a SIGKILL while it was written is not read,
    and is removed once the resumed video is complete, as its checkpoint is, where the resumed run wrote no
    checkpoint of its own (here: none due in the rows it tracked). It stayed beside the complete outputs."""
    clips = clips[:1]
    out = tmp_path / "out"
    _interrupted(clips, out)
    tmp = out / "a.state.partial.tmp"
    tmp.write_bytes(b"\x80\x02cut off")
    monkeypatch.setattr(torchface.job, "CHECKPOINT_EVERY", 100)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        track_videos([clips[0][0]], _config(out, clips, resume=True))
    assert json.loads((out / "a.json").read_text())["resumed"]["checkpoint"] == "exact"
    assert not tmp.exists() and not (out / "a.state.partial").exists()


@pytest.mark.parametrize("mode", ["lookahead", "no-templates"])
def test_resume_from_a_checkpoint_without_the_online_start(clips, tmp_path, mode):
    """Without the online start (``--lookahead``, or no template management) checkpoints are written from frame
    EVERY on (not from the online start's MAX_FRAMES): resumed from the one at 8 rows, the outputs are the
    uninterrupted run's, byte for byte, and the sidecar's start is too."""
    from torchface.template.management import TemplateConfig
    from torchface.tracker import TrackerConfig

    clips = clips[:1]
    kwargs: dict = ({"lookahead": LookaheadConfig(max_frames=MAX_FRAMES)} if mode == "lookahead"
                    else {"tracker": TrackerConfig(template=TemplateConfig(enabled=False))})  # fmt: skip
    track_videos([clips[0][0]], _config(tmp_path / "ref", clips, **kwargs))
    out = tmp_path / "out"
    _interrupted(clips, out, **kwargs)
    assert torch.load(out / "a.state.partial", weights_only=True)["rows"] == 8
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        track_videos([clips[0][0]], _config(out, clips, resume=True, **kwargs))
    assert _same_outputs(tmp_path / "ref", out, ["a"]) == []
    side, ref = (json.loads((d / "a.json").read_text()) for d in (out, tmp_path / "ref"))
    assert side["resumed"]["checkpoint"] == "exact" and side["start"] == ref["start"]


@pytest.mark.parametrize("stop", [7, STOP])
def test_a_video_that_ended_before_its_batch_is_complete_as_it_ends(clips, tmp_path, stop):
    """A batch of two videos, the second of 6 frames: it ends after the checkpoint at 4 rows, and its outputs are
    final as it ends, the first going on alone (its checkpoint at 6 rows, then 8, of a batch of itself).
    Interrupted after ``stop`` rows of the first (before or after its checkpoint at 8), the second is complete, its
    outputs those of the uninterrupted run, byte for byte, and no partial file of it is left; resumed, it is
    skipped, and the first goes on from its checkpoint of itself, as the uninterrupted run went on (``exact``),
    every output the uninterrupted run's. (Before, the second stayed partial until the first ended: interrupted, it
    kept its rows alone, replayed by the resume; and a resume from the first's checkpoint of both, at 4 rows, went
    on from it split.)"""
    short = tmp_path / "c.npy"
    np.save(short, np.load(clips[1][0])[:6])
    both = [clips[0], (short, clips[1][1])]
    track_videos([v for v, _ in both], _config(tmp_path / "ref", both))
    out = tmp_path / "out"

    def interrupt(p):
        if p.done == stop and p.index == 0:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt) as caught:
        track_videos([v for v, _ in both], _config(out, both), progress=interrupt)
    assert "complete: c" in caught.value.kept, caught.value.kept
    assert _same_outputs(tmp_path / "ref", out, ["c"]) == []
    assert (out / "c.json").is_file() and (out / "c_plot.png").is_file()
    assert sorted(f.name for f in out.iterdir() if f.name.startswith("c") and "partial" in f.name) == []
    ck = torch.load(out / "a.state.partial", weights_only=True)
    assert ck["batch"] == ["a"] and ck["rows"] == (6 if stop < 8 else 8)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        summaries = track_videos([v for v, _ in both], _config(out, both, resume=True))
    assert [x.skipped for x in summaries] == [False, True]
    assert _same_outputs(tmp_path / "ref", out, ["a", "c"]) == []
    assert json.loads((out / "a.json").read_text())["resumed"]["checkpoint"] == "exact"  # (its batch: a alone)
    assert [f.name for f in out.iterdir() if "partial" in f.name] == []


def test_a_fresh_run_removes_an_earlier_runs_checkpoints(clips, tmp_path):
    """A run without ``--resume`` removes an earlier run's checkpoint and temporary checkpoint of its videos before
    it tracks: interrupted before its own first checkpoint, none is there (an earlier one would be another run's)."""
    clips = clips[:1]
    out = tmp_path / "out"
    _interrupted(clips, out)
    (out / "a.state.partial.tmp").write_bytes(b"cut off")

    def interrupt(p):
        if p.done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        track_videos([clips[0][0]], _config(out, clips), progress=interrupt)
    assert read_track_csv(out / "a.csv.partial")[1].shape[0] == 2
    assert not (out / "a.state.partial").exists() and not (out / "a.state.partial.tmp").exists()


def test_a_video_that_stops_while_its_rows_are_replayed_leaves_its_batchs_state(clips, batch_ref, tmp_path,
                                                                              monkeypatch):  # fmt: skip
    """Two videos resumed from their checkpoints of one batch, the first of which cannot be read on (an
    ``InputError`` at its 4th frame, while its rows are replayed: the others go on): the second goes on from its own
    part of the batch's state, its rows those of the uninterrupted run to float rounding (tracked alone). (The
    batch's whole state was put back after the checkpoint's row, the first video's stream included: the second
    went on from the first's state.)"""
    from torchface.io import InputError

    out = tmp_path / "out"
    _interrupted(clips, out)
    read = torchface.job._next_frame

    def flaky(s):
        if s.name == "a" and s.frames == 3:
            raise InputError(f"{s.reader.info.path}: cannot read frame 3")
        return read(s)

    monkeypatch.setattr(torchface.job, "_next_frame", flaky)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            track_videos([v for v, _ in clips], _config(out, clips, resume=True, keep_going=True))
        except InputError:
            pass
    assert not (out / "a.json").exists()
    assert json.loads((out / "b.json").read_text())["resumed"]["checkpoint"] == "split"
    ref, got = (read_track_csv(d / "b.csv")[1] for d in (batch_ref, out))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-4)


@pytest.mark.parametrize("damage", ["batch", "stream", "index", "layout 2"])
def test_a_checkpoint_lacking_part_of_its_layout_is_refused_with_a_warning(clips, tmp_path, damage):
    """A checkpoint of this version's number that lacks an entry the resume reads after the check (its batch, its
    bookkeeping) or whose place is not in its batch is not used: one warning line, the video goes on from its CSV's
    rows. (It stopped the run with a KeyError.) One of the layout before (2: without the detector counts) is not
    used either, the line saying whose it is (it said "not a checkpoint of this version (3)", as if of torchface
    3)."""
    clips = clips[:1]
    out = tmp_path / "out"
    _interrupted(clips, out)
    ck = out / "a.state.partial"
    data = torch.load(ck, weights_only=True)
    said = f"{ck}: not used ("
    if damage == "index":
        data["index"] = 3
    elif damage == "layout 2":
        data["version"] = 2
        for key in ("detector_calls", "redetections", "restart_failures"):
            del data["stream"][key]
        said += "written by another torchface, its layout 2, this one's 3): the video goes on from its CSV's rows"
    else:
        del data[damage]
    torch.save(data, ck)
    _resumed_without_its_checkpoint(clips, out, said)


@pytest.mark.parametrize("damage", ["rows", "record"])
def test_a_resume_refused_after_its_checkpoint_matched_keeps_every_row(clips, tmp_path, damage):
    """A checkpoint that matches its CSV (at 8 rows of STOP) whose resume is then refused, by a damaged row before
    it (row 5 says another frame) or a record that cannot be read: the run stops with the InputError, and the
    partial CSV keeps its STOP rows, byte for byte (its rows after the checkpoint were cut off before the checks:
    2 rows lost, up to CHECKPOINT_EVERY - 1 in a real run). Mended, the resume goes on from the checkpoint."""
    from torchface.io import InputError

    clips = clips[:1]
    out = tmp_path / "out"
    _interrupted(clips, out)
    partial = out / "a.csv.partial"
    if damage == "rows":
        lines = partial.read_text().splitlines(keepends=True)
        cells = lines[5].split(",")
        cells[0] = "99"
        lines[5] = ",".join(cells)
        partial.write_text("".join(lines))
    else:
        record = out / "a.record.partial"
        assert record.is_file()
        kept_record = record.read_bytes()
        record.write_text("{not json")
    before = partial.read_bytes()
    with pytest.raises(InputError, match="cannot resume"):
        track_videos([clips[0][0]], _config(out, clips, resume=True))
    assert partial.read_bytes() == before and read_track_csv(partial)[1].shape[0] == STOP
    if damage == "record":
        record.write_bytes(kept_record)
        track_videos([clips[0][0]], _config(out, clips, resume=True))
        side = json.loads((out / "a.json").read_text())
        assert side["resumed"]["checkpoint"] == "exact" and side["resumed"]["rows"] == 8


@pytest.mark.parametrize("change", ["written-otherwise", "refused"])
def test_a_checkpoint_of_other_settings_is_refused_with_a_warning_where_the_record_accepts_them(clips, tmp_path,
                                                                                               change):  # fmt: skip
    """A checkpoint whose settings are not this run's text but the same settings (``visibility_interval`` 1.0 for 1,
    as another version may write them), which the record accepts: not used, with one warning line, the video goes on
    from its CSV's rows (it was dropped without a word). Other settings (``--focal 300``): no warning of
    the checkpoint, the record's check refuses the resume and says why."""
    from torchface.io import InputError

    clips = clips[:1]
    out = tmp_path / "out"
    _interrupted(clips, out)
    ck = out / "a.state.partial"
    if change == "written-otherwise":
        data = torch.load(ck, weights_only=True)
        assert '"visibility_interval": 1,' in data["settings"]
        data["settings"] = data["settings"].replace('"visibility_interval": 1,', '"visibility_interval": 1.0,')
        torch.save(data, ck)
    kwargs = {"focal": 300.0} if change == "refused" else {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if change == "refused":
            with pytest.raises(InputError, match="other settings"):
                track_videos([clips[0][0]], _config(out, clips, resume=True, **kwargs))
        else:
            track_videos([clips[0][0]], _config(out, clips, resume=True))
    said = [str(w.message) for w in caught if "state.partial" in str(w.message)]
    if change == "refused":
        assert said == []
        return
    assert len(said) == 1 and said[0].startswith(f"{ck}: not used (its settings"), said
    side = json.loads((out / "a.json").read_text())
    assert side["resumed"]["checkpoint"] is False and side["resumed"]["rows"] == STOP


def test_cut_rows_keeps_the_header_and_first_rows_reading_line_by_line(tmp_path, monkeypatch):
    """``_cut_rows`` cuts a partial CSV after its header and ``rows`` rows, the bytes before the cut as they were,
    reading it line by line (it read the whole file into memory: an hour's CSV at 30 frames/s, some 100 MB); too
    few complete rows: ValueError, the file as it was."""
    csv = tmp_path / "a.csv"
    partial = tmp_path / "a.csv.partial"
    lines = [b"frame,x\n"] + [f"{i},{i * 0.5:.9g}\n".encode() for i in range(10)]
    opened = []

    class NoWholeRead:
        def __init__(self, f):
            self.f = f

        def read(self, *size):
            if not size or size[0] is None or size[0] < 0:
                raise AssertionError("the whole file read")
            return self.f.read(*size)

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    def watched(path, *args, **kwargs):
        opened.append(path)
        return NoWholeRead(open(path, *args, **kwargs))

    monkeypatch.setattr(torchface.job, "open", watched, raising=False)
    for rows in (0, 3, 10):
        partial.write_bytes(b"".join(lines) + b"10,0.2")  # (a row cut off)
        torchface.job._cut_rows(csv, rows)
        assert partial.read_bytes() == b"".join(lines[: rows + 1])
    assert opened == [partial] * 3
    partial.write_bytes(b"".join(lines[:4]) + b"3,1.5")
    with pytest.raises(ValueError, match="fewer than 4"):
        torchface.job._cut_rows(csv, 4)
    assert partial.read_bytes() == b"".join(lines[:4]) + b"3,1.5"


def test_a_checkpoint_of_more_rows_than_the_csv_holds_as_it_opens_is_not_used(clips, tmp_path, monkeypatch):
    """A checkpoint that matched its CSV as the run started, whose CSV holds fewer rows as its outputs open (changed
    in between; here its row count said 99): not used, with one warning line, the video goes on from its CSV's STOP
    rows (the cut raised a bare ValueError from ``bytes.index`` and stopped the run)."""
    clips = clips[:1]
    out = tmp_path / "out"
    _interrupted(clips, out)
    load = torchface.job._load_checkpoint

    def more(*args, **kwargs):
        found = load(*args, **kwargs)
        return None if found is None else found | {"rows": 99}

    monkeypatch.setattr(torchface.job, "_load_checkpoint", more)
    resumed = _resumed_without_its_checkpoint(clips, out, f"{out / 'a.state.partial'}: not used (it is of row 99")
    assert resumed["rows"] == STOP


def _signalling_step(monkeypatch, at: int, signals: list[int]) -> list[int]:
    """Make ``torchface.job.managed_step`` send this process ``signals`` at its call for row ``at`` (mid-step, before
    that step's work), as Ctrl-C or ``kill`` would; returns the list of the rows it is called for."""
    import os

    real, calls = torchface.job.managed_step, []

    def step(*args, **kwargs):
        calls.append(len(calls) + 1)
        if calls[-1] == at:
            for signum in signals:
                os.kill(os.getpid(), signum)
        return real(*args, **kwargs)

    monkeypatch.setattr(torchface.job, "managed_step", step)
    return calls


@pytest.mark.filterwarnings("ignore:SIGINT. stopping once:RuntimeWarning")
def test_ctrl_c_writes_a_checkpoint_at_the_step_boundary_and_resumes_tracking_nothing_again(
    clips, batch_ref, tmp_path, monkeypatch
):
    """Ctrl-C (SIGINT) mid-step, in a batch of 2: the step goes on to its rows (STOP + 1), the checkpoint of that
    consistent state is written after them, then KeyboardInterrupt as before (SIGINT's handler given back). The
    resume tracks no row again (one step: the last row's; it tracked those after the last periodic checkpoint
    again, here 3 of them) and its outputs are the uninterrupted run's, byte for byte. A second Ctrl-C while the
    first waits interrupts at once (a video alone, at its row 5): that step's row not written, the last periodic
    checkpoint (4 rows) kept."""
    import signal

    names = [v.stem for v, _ in clips]
    for twice, videos, at in ((False, clips, STOP), (True, clips[:1], 5)):
        out = tmp_path / f"out{int(twice)}"
        _signalling_step(monkeypatch, at, [signal.SIGINT] * (2 if twice else 1))
        with pytest.raises(KeyboardInterrupt):
            track_videos([v for v, _ in videos], _config(out, videos))
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        rows = at if twice else at + 1
        for v, _ in videos:
            assert read_track_csv(out / f"{v.stem}.csv.partial")[1].shape[0] == rows
            assert torch.load(out / f"{v.stem}.state.partial", weights_only=True)["rows"] == (4 if twice else rows)
    calls = _signalling_step(monkeypatch, 0, [])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        track_videos([v for v, _ in clips], _config(tmp_path / "out0", clips, resume=True))
    assert len(calls) == N - (STOP + 1)  # (the step of its last row alone)
    assert _same_outputs(batch_ref, tmp_path / "out0", names) == []
    for n in names:
        assert json.loads((tmp_path / "out0" / f"{n}.json").read_text())["resumed"]["checkpoint"] == "exact"


def test_sigterm_in_the_command_line_writes_its_checkpoint_and_exits_143(clips, tmp_path, monkeypatch, capsys):
    """``torchface track`` (without the online start: checkpoints from its first row) sent SIGTERM mid-step: its
    SIGTERM handler runs at the step boundary, after the checkpoint of that step's rows; status 143, the rows kept;
    ``--resume`` tracks none of them again, and its CSV is the uninterrupted run's, byte for byte."""
    import signal

    from torchface.cli import main

    video, lm = clips[0]
    stop = 5

    def args(out: Path, *more: str) -> list[str]:
        return ["track", str(video), "--landmarks", str(lm), "--out", str(out), "--no-online-refine", "--quiet", *more]

    assert main(args(tmp_path / "ref")) == 0
    before = signal.getsignal(signal.SIGTERM)
    _signalling_step(monkeypatch, stop, [signal.SIGTERM])
    assert main(args(tmp_path / "out")) == 143
    assert signal.getsignal(signal.SIGTERM) is before
    err = capsys.readouterr().err
    assert "terminated" in err
    assert "torchface: warning: SIGTERM: stopping once the frame under way is written, after its checkpoint; a second " \
           "signal stops at once" in err, err
    assert read_track_csv(tmp_path / "out" / "a.csv.partial")[1].shape[0] == stop + 1
    assert torch.load(tmp_path / "out" / "a.state.partial", weights_only=True)["rows"] == stop + 1
    calls = _signalling_step(monkeypatch, 0, [])
    assert main(args(tmp_path / "out", "--resume")) == 0
    assert len(calls) == N - (stop + 1)
    assert (tmp_path / "out" / "a.csv").read_bytes() == (tmp_path / "ref" / "a.csv").read_bytes()


def test_sigterm_after_a_shorter_video_ended_leaves_it_complete(clips, tmp_path, monkeypatch, capsys):
    """``torchface track`` of a batch of two, the second of 6 frames, sent SIGTERM once the first has 9 rows: the
    second's outputs are complete (every file, under its final name, none partial; the line says so), and
    ``--resume`` skips it, tracking the first alone from its checkpoint; both CSVs are the uninterrupted run's, byte
    for byte. (Before, the second's outputs waited for the first's end: it stayed ``c.csv.partial``, and the resume
    replayed it.)"""
    import signal

    from torchface.cli import main

    short = tmp_path / "c.npy"
    np.save(short, np.load(clips[1][0])[:6])
    (video, lm), stop = clips[0], 8

    def args(out: Path, *more: str) -> list[str]:
        return ["track", str(video), "--landmarks", str(lm), str(short), "--landmarks", str(clips[1][1]), "--out",
                str(out), "--no-online-refine", "--quiet", *more]  # fmt: skip

    assert main(args(tmp_path / "ref")) == 0
    _signalling_step(monkeypatch, stop, [signal.SIGTERM])
    assert main(args(tmp_path / "out")) == 143
    err = capsys.readouterr().err
    assert "rows kept in " in err and "a.csv.partial (9 rows); complete: c: run the same command with --resume" in err
    out = tmp_path / "out"
    assert sorted(f.name for f in out.iterdir() if f.name.startswith("c")) == [
        "c.csv", "c.json", "c_normalised.mp4", "c_overlay.mp4", "c_plot.png"]  # fmt: skip
    assert (out / "c.csv").read_bytes() == (tmp_path / "ref" / "c.csv").read_bytes()
    calls = _signalling_step(monkeypatch, 0, [])
    assert main(args(out, "--resume")) == 0
    assert len(calls) == N - (stop + 1)  # (the first's steps after its checkpoint; none of the second's)
    for n in ("a", "c"):
        assert (out / f"{n}.csv").read_bytes() == (tmp_path / "ref" / f"{n}.csv").read_bytes()
    assert json.loads((out / "a.json").read_text())["resumed"]["checkpoint"] == "exact"


@pytest.mark.filterwarnings("ignore:SIGINT. stopping once:RuntimeWarning")
def test_the_step_boundary_defers_python_handlers_in_the_main_thread_alone(monkeypatch):
    """``_AtStepBoundary``: SIGINT's Python handler waits for ``check`` (no KeyboardInterrupt where the signal
    arrives), a second signal runs it at once, the handlers are given back as the block ends (a signal that waited
    runs then), a caller's own handler is what runs (with the boundary's frame), ``SIG_IGN`` is left as it
    is, a nested block runs the handler itself and puts the outer block's deferral back as it ends, an error passed
    to ``check`` or ending the block is the interruption's ``error``, a block interrupted as it begins leaves no
    handler of its own, and nothing changes outside the main thread (where ``signal.signal`` raises)."""
    import os
    import signal
    import threading

    from torchface.job import _AtStepBoundary

    with _AtStepBoundary() as boundary:
        assert signal.getsignal(signal.SIGINT) is not signal.default_int_handler
        with pytest.warns(RuntimeWarning, match="^SIGINT: stopping once the frame under way is written, after its "
                                                "checkpoint; Ctrl-C again stops at once$"):  # (said: it can take seconds)
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(100):
                pass
        assert boundary.pending == signal.SIGINT
        with pytest.raises(KeyboardInterrupt):
            boundary.check()
        boundary.check()  # (nothing waits)
        with pytest.raises(KeyboardInterrupt):  # a second one: at once
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(100):  # (the handler runs between bytecodes: well before this ends)
                pass
        assert boundary.pending is None
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with pytest.raises(KeyboardInterrupt):  # one that waits as the block ends: run then, the handler given back
        with _AtStepBoundary():
            os.kill(os.getpid(), signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    ran = []

    def own(signum, frame):
        ran.append(signum)

    def own_frame(signum, frame):
        ran.append((signum, frame.f_code.co_name))

    def mid_step():
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(100):  # (the deferring handler runs here, in this frame)
            pass

    def boundary_check(boundary):
        boundary.check()

    before = signal.signal(signal.SIGINT, own)
    try:
        with _AtStepBoundary() as boundary:
            os.kill(os.getpid(), signal.SIGINT)
            assert ran == [] and boundary.pending == signal.SIGINT
            boundary.check()
            assert ran == [signal.SIGINT]
        assert signal.getsignal(signal.SIGINT) is own
        signal.signal(signal.SIGINT, own_frame)
        with _AtStepBoundary() as boundary:  # its handler gets the frame it runs from (check's caller's), not the
            mid_step()  # one the signal arrived in (its locals, a step's tensors, are not held until the boundary)
            boundary_check(boundary)
        assert ran[1:] == [(signal.SIGINT, "boundary_check")]
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with _AtStepBoundary():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)
    # a track_videos within another's loop (its progress callback): a signal ends the inner one at its boundary
    # (the outer loop's deferral had only marked the outer loop: the inner one tracked on to its end)
    with _AtStepBoundary() as outer:
        with _AtStepBoundary() as inner:
            os.kill(os.getpid(), signal.SIGINT)
            with pytest.raises(KeyboardInterrupt):
                inner.check()
            assert outer.pending is None
        # and the outer loop defers again once the inner one has ended (Python's own handler was put back: a Ctrl-C
        # stopped the outer loop mid-step, no checkpoint of that state)
        assert signal.getsignal(signal.SIGINT) == outer._defer
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    # an error that stopped the loop while a signal waited is kept by the interruption that replaces it
    error = OSError(28, "No space left on device")
    with pytest.raises(KeyboardInterrupt) as caught, _AtStepBoundary() as boundary:
        os.kill(os.getpid(), signal.SIGINT)
        boundary.check(error)
    assert caught.value.error is error
    # the block ended by that error (the loop's `with`): the signal that waited runs as it ends, over the error
    with pytest.raises(KeyboardInterrupt) as caught, _AtStepBoundary():
        os.kill(os.getpid(), signal.SIGINT)
        raise error
    assert caught.value.error is error and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    # a signal whose handler raises while the block begins (SIGTERM's, between the two handlers set): none is left
    set_handler = signal.signal

    def interrupted_at(signum, handler):
        if signum == signal.SIGTERM:
            raise KeyboardInterrupt
        return set_handler(signum, handler)

    before = signal.signal(signal.SIGTERM, own)  # (a Python handler: torchface track's)
    try:
        monkeypatch.setattr(signal, "signal", interrupted_at)
        with pytest.raises(KeyboardInterrupt), _AtStepBoundary():
            pass
        monkeypatch.undo()
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler and signal.getsignal(signal.SIGTERM) is own
    finally:
        signal.signal(signal.SIGTERM, before)
    seen, failed = [], []

    def in_a_thread():
        try:
            with _AtStepBoundary() as b:
                seen.append((signal.getsignal(signal.SIGINT), b.pending))
        except BaseException as exc:  # (signal.signal outside the main thread: ValueError)
            failed.append(exc)

    thread = threading.Thread(target=in_a_thread)
    thread.start()
    thread.join()
    assert failed == [] and seen == [(signal.default_int_handler, None)]


def test_a_checkpoints_detector_counts_are_checked_with_its_layout():
    """The detector counts a checkpoint carries (``stream``'s ``detector_calls``, ``redetections``,
    ``restart_failures``, which a resume goes on counting from) are part of its layout: missing, or not whole
    numbers by name, the checkpoint is refused (not used, with a warning) before the resume reads them."""
    from torchface.job import _check_checkpoint_layout

    stream = {"low_count": 0, "smooth_restart": False, "detection_warned": False, "near": None, "detector_calls": 3,
              "redetections": 1, "restart_failures": {"OUTSIDE_FRAME": 2}}  # fmt: skip
    data = {"version": 3, "t": 7, "rows": 8, "start": 0, "row": None, "settings": "{}", "origin": {}, "batch": ["a"],
            "index": 0, "state": {}, "smooth": None, "first_R": torch.eye(3)[None], "first_t": torch.zeros(1, 3),
            "stream": stream}  # fmt: skip
    _check_checkpoint_layout(data)
    for key, value in (("detector_calls", "3"), ("redetections", None), ("restart_failures", {"OUTSIDE_FRAME": 2.0}),
                       ("restart_failures", [2]), ("detector_calls", True),
                       ("restart_failures", {"OUTSIDE_FRAME": True})):  # fmt: skip
        with pytest.raises(ValueError, match="its detector counts are not of their layout"):
            _check_checkpoint_layout(data | {"stream": stream | {key: value}})
    with pytest.raises(ValueError, match="its place True is not in its batch of 1"):  # (a bool is no place)
        _check_checkpoint_layout(data | {"index": True})
    with pytest.raises(ValueError, match=r"it lacks stream\.restart_failures"):
        _check_checkpoint_layout(data | {"stream": {k: v for k, v in stream.items() if k != "restart_failures"}})
