"""``torchface track --resume`` of a video interrupted within the online look-ahead start's frames (fewer rows than
``LookaheadConfig.max_frames``), before or after the start re-anchored it: its written rows are tracked again from its
first frame (``torchface.job._Stream.retrack``), so that it re-anchors where the uninterrupted run did, builds its
template mosaic again, and its CSV is the uninterrupted run's."""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from torchface.io import read_track_csv
from torchface.job import JobConfig, track_videos
from torchface.synth.io import read_video
from torchface.synth.scenarios import make_scenario
from torchface.synth.sequence import load_ground_truth, write_sequence
from torchface.tracker.lookahead import LookaheadConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _helpers import count_job_steps  # noqa: E402

#: The first N frames of ``pose_sweep`` rendered over 120 frames at 160x120: the head turns past 10 degrees of yaw
#: at frame REANCHOR, where the online start re-anchors the stream (asserted below).
N, REANCHOR = 8, 4


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    files = write_sequence(make_scenario("pose_sweep", 120, 160, 120), root)
    lm = root / "first_frame.csv"
    np.savetxt(lm, load_ground_truth(files.ground_truth).landmarks_px[0].numpy(), delimiter=",", header="x,y",
               comments="")  # fmt: skip
    frames = read_video(files.video, max_frames=N)
    video = root / "sweep.npy"
    np.save(video, (frames.permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8))
    return video, lm


@pytest.fixture(scope="module")
def reference(clip, tmp_path_factory):
    """The uninterrupted run's rows and sidecar."""
    video, lm = clip
    out = tmp_path_factory.mktemp("ref")
    track_videos([video], JobConfig(out_dir=out, landmarks=(lm,)))
    side = json.loads((out / "sweep.json").read_text())
    assert side["start"]["method"] == "online" and side["start"]["reanchored_at_frame"] == REANCHOR
    return read_track_csv(out / "sweep.csv")[1], side


def _interrupted(video, out, lm, stop_at, **kwargs):
    def interrupt(p):
        if p.done == stop_at:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        track_videos([video], JobConfig(out_dir=out, landmarks=(lm,), **kwargs), progress=interrupt)
    assert read_track_csv(out / f"{video.stem}.csv.partial")[1].shape[0] == stop_at


@pytest.mark.parametrize("stop_at", [1, 3, REANCHOR, REANCHOR + 1, REANCHOR + 3])
def test_resume_within_the_online_starts_frames_goes_on_as_the_uninterrupted_run(clip, reference, tmp_path, stop_at):
    """Interrupted before the online start re-anchored the stream (after 1, 3 or 4 rows: the re-anchoring comes at
    frame 4's step) or after (5 or 7 rows: its record holds the re-anchoring), the resumed run re-anchors at the same
    frame and its rows are the uninterrupted run's. (Resumed without the online start, before the re-anchoring, they
    went on up to 20 mm, 2.1 degrees and 0.25 of confidence off; resumed from the record after it, without the
    template mosaic built before the interruption, 7 rows of a 20-frame clip went on 8.1 mm, 0.64 degrees and 0.30 of
    confidence off.)"""
    video, lm = clip
    rows_ref, side_ref = reference
    out = tmp_path / "out"
    _interrupted(video, out, lm, stop_at)
    anchor = json.loads((out / "sweep.record.partial").read_text())["anchor"]
    assert (anchor is None) == (stop_at <= REANCHOR)  # re-anchored before the interruption, or not yet
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # the rows tracked again met the CSV's: no warning
        track_videos([video], JobConfig(out_dir=out, landmarks=(lm,), resume=True))
    _, rows = read_track_csv(out / "sweep.csv")
    assert rows.shape == rows_ref.shape
    np.testing.assert_allclose(rows, rows_ref, rtol=0, atol=1e-6)
    side = json.loads((out / "sweep.json").read_text())
    assert side["start"] == side_ref["start"]
    np.testing.assert_allclose(side["model"]["shape_coeffs"], side_ref["model"]["shape_coeffs"], rtol=0, atol=1e-9)
    assert not (out / "sweep.record.partial").exists()


@pytest.mark.parametrize("max_frames", [None, REANCHOR + 2])
def test_resumes_tracked_again_beside_other_videos_go_on_as_the_uninterrupted_run(clip, reference, tmp_path,
                                                                                 max_frames):  # fmt: skip
    """The stream tracked again goes on as the uninterrupted run beside a new video of its batch and beside a resumed
    one that the interrupted run had re-anchored: tracked again too, within the online start's frames (its rows went
    on from the record, their confidence off where the mosaic was used); with ``max_frames`` 6, it has as many rows
    as the start watched, and its rows are put into the state from its CSV and record."""
    video, lm = clip
    rows_ref, side_ref = reference
    kwargs = {} if max_frames is None else {"refine_first": LookaheadConfig(max_frames=max_frames)}
    if max_frames is not None:  # (the same re-anchoring with fewer frames watched)
        track_videos([video], JobConfig(out_dir=tmp_path / "ref", landmarks=(lm,), **kwargs))
        rows_ref = read_track_csv(tmp_path / "ref" / "sweep.csv")[1]
        assert json.loads((tmp_path / "ref" / "sweep.json").read_text())["start"] == side_ref["start"]
    out = tmp_path / "out"
    later = tmp_path / "later.npy"
    later.write_bytes(video.read_bytes())
    fresh = tmp_path / "fresh.npy"
    fresh.write_bytes(video.read_bytes())
    _interrupted(video, out, lm, 2, **kwargs)
    _interrupted(later, out, lm, REANCHOR + 2, **kwargs)
    assert json.loads((out / "later.record.partial").read_text())["anchor"] is not None
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        track_videos([video, later, fresh], JobConfig(out_dir=out, landmarks=(lm,) * 3, resume=True, **kwargs))
    names = ("sweep", "later", "fresh") if max_frames is None else ("sweep", "fresh")
    for name in names:  # (from its record, later's confidence parts where its template mosaic is used: not restored)
        _, rows = read_track_csv(out / f"{name}.csv")
        assert rows.shape == rows_ref.shape, name
        np.testing.assert_allclose(rows, rows_ref, rtol=0, atol=1e-4, err_msg=name)


def _shift_row_1(partial: Path) -> int:
    """Move row 1's ``pose_Tx`` in the partial CSV ``partial`` by 0.5 mm (a row tracking again will not meet);
    returns the column's index."""
    columns, _ = read_track_csv(partial)
    lines = partial.read_text().splitlines(keepends=True)
    cells = lines[2].rstrip("\n").split(",")  # (line 0: the header)
    tx = columns.index("pose_Tx")
    cells[tx] = repr(float(cells[tx]) + 0.5)
    lines[2] = ",".join(cells) + "\n"
    partial.write_text("".join(lines))
    return tx


def test_rows_not_met_again_are_warned_about_and_kept(clip, reference, tmp_path):
    """A written row that tracking its frame again does not give (another version or machine; here an edited row)
    is warned about, naming the gap, and kept as the CSV holds it; the next rows go on from the frames tracked
    again."""
    video, lm = clip
    rows_ref, _ = reference
    out = tmp_path / "out"
    _interrupted(video, out, lm, 3)
    _, kept = read_track_csv(out / "sweep.csv.partial")
    tx = _shift_row_1(out / "sweep.csv.partial")
    with pytest.warns(RuntimeWarning, match=r"3 rows .* not met again: up to 0\.5 mm \(frame 1\)"):
        track_videos([video], JobConfig(out_dir=out, landmarks=(lm,), resume=True))
    _, rows = read_track_csv(out / "sweep.csv")
    assert rows.shape == rows_ref.shape
    assert rows[1, tx] == pytest.approx(kept[1, tx] + 0.5, abs=1e-6)
    np.testing.assert_allclose(rows[2:], rows_ref[2:], rtol=0, atol=1e-6)


def test_rows_not_met_again_are_said_by_the_sidecar_and_the_summary(clip, tmp_path, capsys):
    """Rows not met again are recorded in the sidecar's ``resumed`` (how many, the largest gap) and said by the
    summary, not only by the warning line that scrolls by above the progress bars; the video is complete, so the
    exit status stays 0. (Only the warning said it: a script that checked status 0 and read the sidecar missed
    it.)"""
    from torchface.cli import main

    video, lm = clip
    out = tmp_path / "out"
    _interrupted(video, out, lm, 3)
    tx = _shift_row_1(out / "sweep.csv.partial")
    assert main(["track", str(video), "--out", str(out), "--landmarks", str(lm), "--resume", "--quiet"]) == 0
    said = capsys.readouterr()
    assert "3 rows written before the interruption" in said.err  # (the warning, as before)
    assert "sweep: 8 frames" in said.out
    assert "warning: 1 row written before the interruption was not met again when tracked again" in said.out, said.out
    resumed = json.loads((out / "sweep.json").read_text())["resumed"]
    gap = resumed.pop("largest_gap")
    assert resumed == {"rows": 3, "tracked_again": 3, "not_met_again": 1, "checkpoint": False, "threads": None}
    assert gap["mm"] == pytest.approx(0.5, abs=1e-6) and gap["frame"] == 1 and gap["other_status_from_frame"] is None
    assert gap["degrees"] < 1e-3 and gap["confidence"] < 1e-4


@pytest.mark.parametrize("max_frames, tracked_again", [(3, 0), (None, 3)])
def test_the_sidecar_says_what_was_resumed_and_fps_counts_the_frames_tracked_again(clip, tmp_path, max_frames,
                                                                                  tracked_again):  # fmt: skip
    """A resumed video's sidecar says how many of its rows the interrupted run wrote and how many of them were tracked
    again (every one met again here); its ``timings_s.fps`` counts the frames it tracked again as tracked frames,
    their time being in ``timings_s.track`` (it counted only the new rows: 5 of these 8 frames; a 40-frame sweep resumed
    after 20 rows gave 16-17 frames/s where the uninterrupted run gave 28-32), not the rows put into the state from
    the CSV, nor the time spent redrawing those (``timings_s.replay``, left out of its time). A video tracked afresh
    has ``resumed`` null and ``replay`` 0."""
    video, lm = clip
    out = tmp_path / "out"
    kwargs = {} if max_frames is None else {"refine_first": LookaheadConfig(max_frames=max_frames)}
    track_videos([video], JobConfig(out_dir=tmp_path / "fresh", landmarks=(lm,), **kwargs))
    fresh = json.loads((tmp_path / "fresh" / "sweep.json").read_text())
    assert fresh["resumed"] is None
    assert fresh["timings_s"]["fps"] * fresh["timings_s"]["track"] == pytest.approx(N)
    assert fresh["timings_s"]["replay"] == 0.0
    _interrupted(video, out, lm, 3, **kwargs)
    (summary,) = track_videos([video], JobConfig(out_dir=out, landmarks=(lm,), resume=True, **kwargs))
    side = json.loads((out / "sweep.json").read_text())
    gap = side["resumed"].pop("largest_gap")
    assert side["resumed"] == {"rows": 3, "tracked_again": tracked_again, "not_met_again": 0, "checkpoint": False,
                               "threads": None}
    if tracked_again:  # (met again: within RETRACK_TOLERANCE)
        assert gap["mm"] <= 1e-3 and gap["degrees"] <= 1e-3 and gap["confidence"] <= 1e-4, gap
        assert gap["other_status_from_frame"] is None
    else:
        assert gap is None
    timings = side["timings_s"]
    # (the rows put into the state from the CSV are not tracked frames, and the time spent redrawing them, replay,
    # is not tracking time: counted, fps was that of the new rows over the whole loop)
    assert (timings["replay"] > 0) == (not tracked_again) and timings["replay"] < timings["track"]
    assert timings["fps"] * (timings["track"] - timings["replay"]) == pytest.approx(N - 3 + tracked_again)
    assert timings["batch_fps"] == timings["fps"] == summary.fps


@pytest.mark.parametrize("max_frames, tracked_again", [(3, False), (4, True)])
def test_only_rows_within_the_online_starts_frames_are_tracked_again(clip, tmp_path, monkeypatch, max_frames,
                                                                    tracked_again):  # fmt: skip
    """The rows are tracked again only while the online start may still have waited: fewer rows than its
    ``max_frames`` (3 rows with ``max_frames=4``: frame 3 is still watched; with 3, the watch had ended and the rows
    are put into the state from the CSV): the extra tracking is bounded by ``max_frames``."""
    video, lm = clip
    out = tmp_path / "out"
    online = LookaheadConfig(max_frames=max_frames)
    _interrupted(video, out, lm, 3, refine_first=online)
    steps = count_job_steps(monkeypatch)
    track_videos([video], JobConfig(out_dir=out, landmarks=(lm,), refine_first=online, resume=True))
    assert len(steps) == (N - 1 if tracked_again else N - 3)
    method = json.loads((out / "sweep.json").read_text())["start"]["method"]
    assert method == ("online" if tracked_again else "landmark fit")


def test_a_stream_tracked_again_without_its_reanchoring_records_none(clip, tmp_path, monkeypatch):
    """A stream tracked again that does not re-anchor where the interrupted run did (here its head's turn is not
    taken as one; elsewhere another machine's rounding at the turn's threshold: the rows up to the re-anchoring
    frame, made before it, are met again, so no warning) has its record say so once it is tracked again: a second
    interruption after the online start's frames resumes its rows as they were tracked, not re-anchored. (The record
    kept the first run's re-anchoring: the resumed rows were taken as re-anchored ones, and the sidecar named a
    re-anchoring frame that its rows after it were not tracked with.)"""
    import torch

    import torchface.tracker.managed

    video, lm = clip
    online = LookaheadConfig(max_frames=REANCHOR + 2)
    out = tmp_path / "out"
    _interrupted(video, out, lm, REANCHOR + 1, refine_first=online)
    assert json.loads((out / "sweep.record.partial").read_text())["anchor"]["frame"] == REANCHOR
    with monkeypatch.context() as m:  # (no turn is one: the stream does not re-anchor)
        m.setattr(torchface.tracker.managed, "is_keyframe_turn", lambda rel, *_: torch.zeros_like(rel, dtype=bool))
        track_videos([video], JobConfig(out_dir=tmp_path / "plain", landmarks=(lm,), refine_first=online))
        assert json.loads((tmp_path / "plain" / "sweep.json").read_text())["start"]["reanchored_at_frame"] is None

        def interrupt(p):
            if p.done == REANCHOR + 3:
                raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt), warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # (its rows met again)
            track_videos([video], JobConfig(out_dir=out, landmarks=(lm,), refine_first=online, resume=True),
                         progress=interrupt)  # fmt: skip
    assert json.loads((out / "sweep.record.partial").read_text())["anchor"] is None
    track_videos([video], JobConfig(out_dir=out, landmarks=(lm,), refine_first=online, resume=True))
    assert json.loads((out / "sweep.json").read_text())["start"]["reanchored_at_frame"] is None
    _, rows = read_track_csv(out / "sweep.csv")
    _, plain = read_track_csv(tmp_path / "plain" / "sweep.csv")
    np.testing.assert_allclose(rows[: REANCHOR + 3], plain[: REANCHOR + 3], rtol=0, atol=1e-6)
    # (the next row from the rows without the mosaic: 0.045 off at most, in any column; 12.3 taken as re-anchored)
    np.testing.assert_allclose(rows, plain, rtol=0, atol=0.1)


def test_a_lookahead_runs_resume_is_not_refused_over_the_online_start_it_does_not_use(clip, tmp_path):
    """A partial ``--lookahead`` run (which starts without the online start) resumed with ``--no-online-refine``, or
    one without it resumed with it, was refused over the unused setting ("online start on then, off now"), as its
    complete outputs were before (``test_resume_refuses_to_skip_complete_outputs_made_with_other_settings``): its
    record now says no online start, and an earlier version's record, which held one, is read so. A partial run of
    the online start resumed without it is still refused."""
    import torchface.job as job
    from torchface.io import InputError
    from torchface.io.sidecar import to_jsonable

    video, lm = clip
    out = tmp_path / "out"
    ahead = LookaheadConfig(max_frames=3)
    _interrupted(video, out, lm, 2, lookahead=ahead)
    record = out / "sweep.record.partial"
    made = json.loads(record.read_text())
    assert made["settings"]["online start"] is None and job._setting_values(
        JobConfig(out_dir=out, lookahead=ahead))["online start"] is None  # fmt: skip
    made["settings"]["online start"] = json.loads(json.dumps(to_jsonable(LookaheadConfig())))  # (as written before)
    record.write_text(json.dumps(made))
    track_videos([video], JobConfig(out_dir=out, landmarks=(lm,), lookahead=ahead, refine_first=None, resume=True))
    assert read_track_csv(out / "sweep.csv")[1].shape[0] == N
    _interrupted(video, tmp_path / "online", lm, 2)  # the online start's partial run: its setting is used
    with pytest.raises(InputError, match=r"\(online start on then, off now\)"):
        track_videos([video], JobConfig(out_dir=tmp_path / "online", landmarks=(lm,), refine_first=None, resume=True))
