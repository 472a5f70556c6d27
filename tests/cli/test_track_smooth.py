"""``torchface track --smooth`` (``JobConfig.smoothing``): the smoothed pose columns beside the raw ones, the raw rows
as without it, the overlay drawn at the smoothed pose, the filter restored on ``--resume``, and the refusals."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import torchface.job
from torchface.cli import main
from torchface.io import read_track_csv, to_jsonable
from torchface.io.table import POSE_COLUMNS, ROTATION_COLUMNS, SMOOTH_COLUMNS
from torchface.job import JobConfig, track_videos
from torchface.tracker import OneEuroConfig, SmoothingConfig, smooth_pose_series

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/_helpers.py
from _helpers import load_script, lossless_scenario_clip  # noqa: E402

T, W, H = 10, 160, 120


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """The ``expressions`` scenario's first frames (its head turns past 10 degrees at frame 2: the online start
    re-anchors there), lossless as an ``.npy`` array, and its first landmarks."""
    return lossless_scenario_clip(tmp_path_factory.mktemp("clip"), "expressions", T, W, H)


@pytest.fixture(scope="module")
def runs(clip, tmp_path_factory):
    """The clip tracked without and with ``--smooth`` (the latter recording the head axes its overlay drew)."""
    video, lm = clip
    plain, smooth = tmp_path_factory.mktemp("plain"), tmp_path_factory.mktemp("smooth")
    assert main(["track", str(video), "--out", str(plain), "--landmarks", str(lm), "--quiet"]) == 0
    drawn = []
    original = torchface.job.axes_geometry

    def record(R, t, intr):
        drawn.append((R.detach().double().clone(), t.detach().double().clone()))
        return original(R, t, intr)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(torchface.job, "axes_geometry", record)
        assert main(["track", str(video), "--out", str(smooth), "--landmarks", str(lm), "--quiet", "--smooth"]) == 0
    return plain, smooth, drawn


def offline(cols, rows, restart_after: int | None) -> np.ndarray:
    """The smoothed pose columns of ``rows`` as the filter gives them offline (the rows' times and success, a start
    afresh after the re-anchoring frame ``restart_after``)."""
    data = torch.from_numpy(rows)
    R = data[:, [cols.index(c) for c in ROTATION_COLUMNS]].reshape(1, -1, 3, 3)
    t = data[:, [cols.index(c) for c in POSE_COLUMNS[:3]]][None]
    restart = torch.zeros(1, len(rows), dtype=torch.bool)
    if restart_after is not None:
        restart[0, restart_after + 1] = True
    R_s, t_s = smooth_pose_series(R, t, (data[:, cols.index("success")] > 0.5)[None],
                                  data[:, cols.index("timestamp")][None], SmoothingConfig(), restart)  # fmt: skip
    return np.concatenate([t_s[0].numpy(), R_s[0].reshape(-1, 9).numpy()], 1)


def smooth_cells(cols, rows) -> np.ndarray:
    """The rows' smoothed translation and rotation matrix ``(T, 12)``."""
    names = [f"smooth_{c}" for c in POSE_COLUMNS[:3] + ROTATION_COLUMNS]
    return rows[:, [cols.index(c) for c in names]]


def test_smooth_adds_columns_and_leaves_the_raw_rows_as_without_it(runs) -> None:
    plain, smooth, drawn = runs
    cols_p, rows_p = read_track_csv(plain / "clip.csv")
    cols_s, rows_s = read_track_csv(smooth / "clip.csv")
    assert not any(c.startswith("smooth_") for c in cols_p)
    assert cols_s == cols_p + SMOOTH_COLUMNS
    # off is the code without it, and the filter never feeds the tracker: every raw cell as the plain run's
    assert np.array_equal(rows_s[:, : len(cols_p)], rows_p, equal_nan=True)
    sidecar, plain_sidecar = (json.loads((d / "clip.json").read_text()) for d in (smooth, plain))
    assert sidecar["config"]["smoothing"] == to_jsonable(SmoothingConfig())
    assert plain_sidecar["config"]["smoothing"] is None
    at = sidecar["start"]["reanchored_at_frame"]
    assert at is not None and at + 1 < T  # (the clip re-anchors: a start afresh after it)
    got = smooth_cells(cols_s, rows_s)
    raw = rows_s[:, [cols_s.index(c) for c in POSE_COLUMNS[:3] + ROTATION_COLUMNS]]
    np.testing.assert_allclose(got, offline(cols_s, rows_s, at), rtol=1e-7, atol=1e-6)
    assert np.array_equal(got[0], raw[0]) and np.array_equal(got[at + 1], raw[at + 1])  # starts: the raw pose
    # every cell of a start, its angles too (recomputed from the rounded matrix they were up to 4e-6 degrees off)
    cells = [cols_s.index(c) for c in POSE_COLUMNS + ROTATION_COLUMNS]
    smooth_all = rows_s[:, [cols_s.index(c) for c in SMOOTH_COLUMNS]]
    for k in (0, at + 1):
        assert np.array_equal(smooth_all[k], rows_s[k, cells]), k
    assert np.abs(got[1:] - raw[1:]).max() > 1e-3  # and smoothed elsewhere
    # the overlay's head axes are drawn at the smoothed pose
    assert len(drawn) == T
    R_drawn = torch.cat([R for R, _ in drawn]).numpy().reshape(T, 9)
    np.testing.assert_allclose(R_drawn, got[:, 3:], rtol=0, atol=1e-6)


def test_smooth_resume_goes_on_from_the_interrupted_filter(clip, runs, tmp_path, capsys) -> None:
    """Interrupted after 5 rows and resumed with ``--smooth``: the replayed rows are kept, and the filter goes on from
    the state the replayed rows give it (the row after the resume is filtered from them, not started afresh), as
    the offline filter over the whole CSV. Resumed without ``--smooth``, or a plain partial run resumed with it:
    refused, naming the smoothing."""
    video, lm = clip
    out = tmp_path / "out"

    def interrupt(p):
        if p.done == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        track_videos([video], JobConfig(out_dir=out, landmarks=(lm,), smoothing=SmoothingConfig()), progress=interrupt)
    cols, kept = read_track_csv(out / "clip.csv.partial")
    assert kept.shape[0] == 5
    assert main(["track", str(video), "--out", str(out), "--landmarks", str(lm), "--quiet", "--resume"]) == 2
    assert "another smoothing" in capsys.readouterr().err
    assert main(["track", str(video), "--out", str(out), "--landmarks", str(lm), "--quiet", "--resume",
                 "--smooth"]) == 0  # fmt: skip
    cols, rows = read_track_csv(out / "clip.csv")
    assert rows.shape[0] == T and np.array_equal(rows[:5], kept)
    at = json.loads((out / "clip.json").read_text())["start"]["reanchored_at_frame"]
    got = smooth_cells(cols, rows)
    np.testing.assert_allclose(got, offline(cols, rows, at), rtol=1e-7, atol=1e-6)
    raw5 = rows[5, [cols.index(c) for c in POSE_COLUMNS[:3] + ROTATION_COLUMNS]]
    if at != 4:  # (row 5 is not a start afresh: it was filtered from the replayed rows' state)
        assert np.abs(got[5] - raw5).max() > 1e-4
    # a plain partial run resumed with --smooth
    plain = tmp_path / "plain"
    with pytest.raises(KeyboardInterrupt):
        track_videos([video], JobConfig(out_dir=plain, landmarks=(lm,)), progress=interrupt)
    assert main(["track", str(video), "--out", str(plain), "--landmarks", str(lm), "--quiet", "--resume",
                 "--smooth"]) == 2  # fmt: skip
    assert "another smoothing" in capsys.readouterr().err



def test_smooth_resume_rebuilds_the_uninterrupted_filter_state_bit_for_bit(clip, tmp_path, monkeypatch) -> None:
    """A real interruption (KeyboardInterrupt after 6 rows, past the re-anchoring) resumed with ``--smooth``: the
    filter state that the replayed rows rebuild is, bit for bit, the one the uninterrupted run had after the same
    rows, and so are their smoothed values; the first resumed row is filtered from that state. (The rows tracked
    after a resume are not the uninterrupted run's to the bit: they go on from the CSV's rounded values, ~1e-5,
    with or without --smooth; so the states, not the later rows, are compared.)"""
    video, lm = clip
    original = torchface.job._smooth_rows

    def recording(log: dict):
        def wrapped(config, state, written, columns, streams, live, stamps, t):
            values, new = original(config, state, written, columns, streams, live, stamps, t)
            log[t] = (values.copy(), new)
            return values, new

        return wrapped

    def tensors(s):
        parts = [getattr(f, n) for f in (s.rotation, s.translation) for n in ("value", "raw", "rate", "started")]
        return [s.time, *parts]

    whole, resumed = {}, {}
    monkeypatch.setattr(torchface.job, "_smooth_rows", recording(whole))
    track_videos([video], JobConfig(out_dir=tmp_path / "whole", landmarks=(lm,), smoothing=SmoothingConfig()))
    at = json.loads((tmp_path / "whole" / "clip.json").read_text())["start"]["reanchored_at_frame"]
    assert at is not None and at + 1 < 6  # (the replayed rows hold the start after the re-anchoring)
    out = tmp_path / "out"

    def interrupt(p):
        if p.done == 6:
            raise KeyboardInterrupt

    monkeypatch.setattr(torchface.job, "_smooth_rows", original)
    with pytest.raises(KeyboardInterrupt):
        track_videos([video], JobConfig(out_dir=out, landmarks=(lm,), smoothing=SmoothingConfig()), progress=interrupt)
    monkeypatch.setattr(torchface.job, "_smooth_rows", recording(resumed))
    track_videos([video], JobConfig(out_dir=out, landmarks=(lm,), smoothing=SmoothingConfig(), resume=True))
    assert sorted(resumed) == sorted(whole) == list(range(T))
    for t in range(6):
        assert np.array_equal(resumed[t][0], whole[t][0]), t
        assert all(torch.equal(a, b) for a, b in zip(tensors(resumed[t][1]), tensors(whole[t][1]))), t
    cols, rows = read_track_csv(out / "clip.csv")
    _, rows_whole = read_track_csv(tmp_path / "whole" / "clip.csv")
    assert np.array_equal(rows[:6], rows_whole[:6], equal_nan=True)
    raw6 = rows[6, [cols.index(c) for c in POSE_COLUMNS[:3] + ROTATION_COLUMNS]]
    assert np.abs(smooth_cells(cols, rows)[6] - raw6).max() > 1e-4  # (filtered from that state, not started afresh)

def test_complete_outputs_without_smooth_are_not_skipped_by_a_smooth_resume(clip, runs, tmp_path, capsys) -> None:
    video, lm = clip
    plain, _, _ = runs
    out = tmp_path / "out"
    out.mkdir()
    for f in plain.iterdir():
        if f.is_file():
            (out / f.name).write_bytes(f.read_bytes())
    assert main(["track", str(video), "--out", str(out), "--landmarks", str(lm), "--quiet", "--resume",
                 "--smooth"]) == 2  # fmt: skip
    assert "--smooth off then, on now" in capsys.readouterr().err


def test_job_smoothing_setting_is_checked(tmp_path) -> None:
    with pytest.raises(TypeError, match="smoothing must be a SmoothingConfig"):
        JobConfig(out_dir=tmp_path, smoothing=True)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="pose only"):
        JobConfig(out_dir=tmp_path, smoothing=SmoothingConfig(expression=OneEuroConfig()))
    # Neither filter: the smooth_* columns were written equal to the raw ones (and the sidecar said smoothed)
    with pytest.raises(ValueError, match=r"smoothing smooths nothing .*smoothing=None for no smooth_\* columns"):
        JobConfig(out_dir=tmp_path, smoothing=SmoothingConfig(rotation=None, translation=None))
    for one in (SmoothingConfig(rotation=None), SmoothingConfig(translation=None)):  # one filter is smoothing
        assert JobConfig(out_dir=tmp_path, smoothing=one).smoothing is one


def test_track_grid_smooths_offline_as_the_job_did(runs) -> None:
    """scripts/track_grid.py --smoothing filters a run's CSV rows offline: given the sidecar's
    start.reanchored_at_frame it starts afresh where ``--smooth`` did (the row after the re-anchoring frame), so its
    rotations are the job's smooth_r* cells; without it (as before) they part after the re-anchoring."""
    track_grid = load_script("track_grid")
    _, smooth, _ = runs
    cols, rows = read_track_csv(smooth / "clip.csv")
    at = json.loads((smooth / "clip.json").read_text())["start"]["reanchored_at_frame"]
    assert at is not None and at + 1 < T
    job = smooth_cells(cols, rows)[:, 3:].reshape(-1, 3, 3)
    got = track_grid.smoothed_rotations(cols, rows, SmoothingConfig(), at)
    np.testing.assert_allclose(got, job, rtol=0, atol=1e-6)
    assert np.array_equal(got[at + 1], rows[at + 1, [cols.index(c) for c in ROTATION_COLUMNS]].reshape(3, 3))
    without = track_grid.smoothed_rotations(cols, rows, SmoothingConfig())
    assert np.abs(without[at + 1] - job[at + 1]).max() > 1e-4
