"""Tests of the long scenarios (issue 5): their timeline, ground truth of visibility, several occluders.

Rendering all of a long scenario is slow even when short, so the rendered checks take a handful of its frames
(:func:`_subset`: the same poses, expressions and light, the occluders left out) at a small size.
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from torchface.geometry.so3 import euler_to_matrix
from torchface.synth.background import OccluderSpec, background_frames
from torchface.synth.scenarios import (
    ALL_SCENARIOS,
    LONG_RUN_FRAMES,
    LONG_RUN_MIN_FRAMES,
    LONG_SCENARIOS,
    SCENARIOS,
    long_run_timeline,
    make_scenario,
    scenario_size,
)
from torchface.synth.sequence import SequenceSpec, render_sequence, save_ground_truth

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/_helpers.py
from _helpers import load_script  # noqa: E402

F64 = torch.float64
W, H = 80, 60


def _subset(spec: SequenceSpec, frames: list[int]) -> SequenceSpec:
    """The frames ``frames`` of ``spec`` as a sequence of their own (occluders and events dropped)."""
    idx = torch.tensor(frames)
    return replace(
        spec, rotation=spec.rotation[idx], translation=spec.translation[idx], anim=spec.anim[idx],
        light=spec.light.select(idx), occluder=None, occluders=(), events=(),
    )


def _frames_of_interest(num_frames: int) -> tuple[list[int], dict[str, list[int]]]:
    """Frames to render from a ``num_frames`` long scenario, grouped by what the timeline says of them."""
    tl = long_run_timeline(num_frames)
    out_of_view = (tl.offset_mm[:, 0].abs() == tl.offset_mm[:, 0].abs().max()).nonzero().flatten().tolist()
    leave, back = tl.exits[0]
    entering = [f for f in range(back, back + 12) if f not in out_of_view][:6]
    groups = {"returns": list(tl.returns[:3]), "out": out_of_view[:4], "entering": entering, "start": [0]}
    frames = sorted({f for g in groups.values() for f in g})
    return frames, groups


_RENDERED: dict[str, tuple] = {}


def _rendered(name: str, num_frames: int = LONG_RUN_MIN_FRAMES):
    if name not in _RENDERED:
        spec = make_scenario(name, num_frames, W, H)
        frames, groups = _frames_of_interest(num_frames)
        images, gt = render_sequence(_subset(spec, frames))
        _RENDERED[name] = (spec, frames, groups, images, gt)
    return _RENDERED[name]


# ----------------------------------------------------------------------------------------- timeline
@pytest.mark.parametrize("num_frames", [LONG_RUN_MIN_FRAMES, 457, LONG_RUN_FRAMES])
def test_timeline_returns_are_exactly_frontal_after_large_turns(num_frames):
    tl = long_run_timeline(num_frames)
    assert tl.ypr_deg.shape == (num_frames, 3) and tl.offset_mm.shape == (num_frames, 3)
    assert len(tl.returns) == 13 and list(tl.returns) == sorted(set(tl.returns))
    assert (tl.ypr_deg[list(tl.returns)] == 0).all() and (tl.offset_mm[list(tl.returns)] == 0).all()
    # Reaches yaw +-60 and pitch +-30, several times each.
    assert tl.ypr_deg[:, 0].max() == 60 and tl.ypr_deg[:, 0].min() == -60
    assert tl.ypr_deg[:, 1].max() == 30 and tl.ypr_deg[:, 1].min() == -30
    peaks, previous = [], 0
    for r in tl.returns:
        peaks.append(float(tl.ypr_deg[previous:r].abs().amax()))
        previous = r
    assert sum(p >= 45 for p in peaks) >= 7 and sum(p >= 30 for p in peaks) >= 10 and min(peaks) >= 10, peaks
    # Both exits move the head out by the full offset for some frames, turned or not, then back.
    for leave, back in tl.exits:
        assert tl.offset_mm[leave].abs().max() == 0 and tl.offset_mm[back].abs().max() > 400
        assert tl.offset_mm[back:].abs().amax(-1).min() == 0  # it does come back
    events = dict((label, f) for label, f in tl.events if label != "frontal_return")
    assert {"face_leaves", "face_reenters", "side_light_on", "occluder_on", "key_light_dim"} <= set(events)
    assert [f for label, f in tl.events if label == "frontal_return"] == list(tl.returns)


def test_timeline_scales_with_length():
    full, short = long_run_timeline(LONG_RUN_FRAMES), long_run_timeline(300)
    assert full.returns[0] == 215
    # Nominal frame k of the 3000 lands on round(k * 299 / 2999) of 300.
    assert short.returns == tuple(round(r * 299 / 2999) for r in full.returns)
    with pytest.raises(ValueError, match="at least"):
        long_run_timeline(LONG_RUN_MIN_FRAMES - 1)


def test_long_scenarios_are_registered_apart_from_the_standard_ones():
    assert set(LONG_SCENARIOS).isdisjoint(SCENARIOS) and set(ALL_SCENARIOS) == set(SCENARIOS) | set(LONG_SCENARIOS)
    assert scenario_size("long_run", "full") == (640, 480, LONG_RUN_FRAMES)
    assert scenario_size("long_run_scan", "small")[2] == LONG_RUN_MIN_FRAMES
    a, b = make_scenario("long_run", 120, W, H), make_scenario("long_run_scan", 120, W, H)
    assert (a.subject, b.subject) == ("candide3", "james")
    torch.testing.assert_close(a.rotation, b.rotation, rtol=0, atol=0)
    torch.testing.assert_close(a.translation, b.translation, rtol=0, atol=0)
    assert a.anim.abs().amax(0).gt(0.5).sum() >= 4 and b.anim.shape == (120, 0)
    assert len(a.occluders) == 3 and a.occluder is None
    # The light switches: the side light is on between its events, off elsewhere.
    events = [(label, f) for label, f in a.events if label.startswith("side_light")]
    on = torch.zeros(120, dtype=torch.bool)
    for (l1, f1), (l2, f2) in zip(events[::2], events[1::2]):
        assert (l1, l2) == ("side_light_on", "side_light_off")
        on[f1:f2] = True
    assert (a.light.intensities[on, 1] > 0.5).all() and (a.light.intensities[~on, 1] == 0).all()


# ----------------------------------------------------------------------------------------- rendered ground truth
@pytest.mark.parametrize("name", list(LONG_SCENARIOS))
def test_rendered_returns_are_frontal_and_visible(name):
    spec, frames, groups, images, gt = _rendered(name)
    rows = [frames.index(f) for f in groups["returns"] + groups["start"]]
    torch.testing.assert_close(gt.ypr_deg[rows], torch.zeros(len(rows), 3, dtype=F64), atol=1e-9, rtol=0)
    torch.testing.assert_close(gt.rotation[rows], euler_to_matrix(torch.zeros(len(rows), 3, dtype=F64)))
    assert gt.face_visible[rows].all() and (gt.face_in_view[rows] == 1).all()
    assert (gt.face_pixels[rows] > 0.04 * W * H).all()
    # Frontal: the inner landmarks (brows, nose, eyes, mouth) are seen.
    assert gt.landmarks_visible[rows][:, 17:].float().mean() > 0.85


@pytest.mark.parametrize("name", list(LONG_SCENARIOS))
def test_rendered_out_of_view_stretch_projects_outside_the_image(name):
    spec, frames, groups, images, gt = _rendered(name)
    rows = [frames.index(f) for f in groups["out"]]
    assert rows and not gt.face_visible[rows].any()
    # Every landmark projects outside the image, no pixel shows the face, none is visible ...
    assert not gt.landmarks_in_image[rows].any() and (gt.face_in_view[rows] == 0).all()
    assert (gt.face_pixels[rows] == 0).all() and not gt.landmarks_visible[rows].any()
    # ... and the frame is the bare background (known answer).
    bg = background_frames(spec.background, torch.tensor(rows, dtype=torch.float32), H, W)
    torch.testing.assert_close(images[rows], bg.clamp(0, 1), atol=1e-6, rtol=0)


@pytest.mark.parametrize("name", list(LONG_SCENARIOS))
def test_rendered_visibility_flags_match_the_landmarks_while_the_face_comes_back(name):
    spec, frames, groups, images, gt = _rendered(name)
    rows = [frames.index(f) for f in groups["entering"]]
    inside = gt.landmarks_in_image[rows]
    # The flag is exactly "every landmark inside the image and some face pixels".
    assert torch.equal(gt.face_visible[rows], inside.all(-1) & (gt.face_pixels[rows] > 0))
    torch.testing.assert_close(gt.face_in_view[rows], inside.double().mean(-1))
    # The face comes in over these frames: partly (not visible, yet rendered), then whole.
    partial = (gt.face_pixels[rows] > 0) & ~gt.face_visible[rows]
    assert partial.any() and gt.face_visible[rows].any()
    first_visible = int(gt.face_visible[rows].nonzero()[0])
    assert gt.face_visible[rows][first_visible:].all()
    # A landmark seen by the camera always projects inside the image.
    assert not (gt.landmarks_visible & ~gt.landmarks_in_image).any()


# ----------------------------------------------------------------------------------------- several occluders
def test_several_occluders_each_cover_their_frames():
    spec = make_scenario("pose_sweep", 10, 64, 48)
    occ = (OccluderSpec(1, 3, target_fraction=0.3), OccluderSpec(6, 8, target_fraction=0.3, seed=6))
    frames, gt = render_sequence(replace(spec, occluders=occ))
    on = gt.occluder_on
    assert on.tolist() == [False, True, True, False, False, False, True, True, False, False]
    assert ((gt.occluded_fraction[on] > 0.2) & (gt.occluded_fraction[on] < 0.45)).all()
    assert (gt.occluded_fraction[~on] == 0).all()
    # One occluder given as `occluder` or as `occluders` renders the same frames.
    a = render_sequence(replace(spec, occluder=occ[0]))[0]
    b = render_sequence(replace(spec, occluders=occ[:1]))[0]
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    clean = render_sequence(spec)[0]
    assert (frames[~on] == clean[~on]).all() and (frames[on] != clean[on]).any()


def test_overlapping_or_late_occluders_are_rejected():
    spec = make_scenario("pose_sweep", 10, 64, 48)
    with pytest.raises(ValueError, match="overlap"):
        replace(spec, occluder=OccluderSpec(1, 5), occluders=(OccluderSpec(4, 6),))
    with pytest.raises(ValueError, match="starts at frame"):
        replace(spec, occluders=(OccluderSpec(12, 14),))
    with pytest.raises(TypeError, match="occluders"):
        replace(spec, occluders=[OccluderSpec(1, 2)])


# ----------------------------------------------------------------------------------------- evaluate.py sections
def _load_evaluate():
    return load_script("evaluate")


def test_evaluate_sections_on_made_up_runs(tmp_path):
    """Section (a)'s table and section (b)'s AUROC from runs whose errors and confidences are known."""
    ev = _load_evaluate()
    spec, frames, groups, images, gt = _rendered("long_run")
    returns = [frames.index(f) for f in groups["returns"]]
    gt = replace(gt, events=tuple(("frontal_return", r) for r in returns))
    T = gt.num_frames
    in_view = gt.face_visible

    def run(yaw_err: torch.Tensor, success: torch.Tensor, confidence: torch.Tensor):
        offset = euler_to_matrix(torch.stack([yaw_err, torch.zeros(T, dtype=F64), torch.zeros(T, dtype=F64)], -1))
        return ev.RunOutput(
            rotation=offset @ gt.rotation, translation=gt.translation, anim=torch.zeros(T, 0, dtype=F64),
            status=torch.zeros(T, dtype=torch.int64), ms_per_frame=10.0, init_ms=1.0, success=success,
            confidence=confidence, reanchored=torch.zeros(T, dtype=torch.bool),
        )

    good_err = torch.full((T,), 0.5, dtype=F64)
    good_err[0] = 0.0
    good = run(good_err, in_view.clone(), torch.where(in_view, 0.9, 0.0).to(F64))
    drift = torch.linspace(0.0, 12.0, T, dtype=F64)
    bad = run(drift, torch.ones(T, dtype=torch.bool), (1.0 - drift / 12.0))
    series = [
        ev.frame_series("long_run", "mosaic", True, gt, good), ev.frame_series("long_run", "bare", False, gt, bad)
    ]
    runs = {s.config: (ev.long_metrics(gt, s.error, s.success, 1), s.ms_per_frame) for s in series}
    m = runs["mosaic"][0]
    torch.testing.assert_close(torch.tensor(m.return_errors_deg, dtype=F64), torch.full((3,), 0.5, dtype=F64))
    assert [r.frames_to_recover for r in m.recoveries] == [0]
    table = ev.long_table("long_run", "made up", gt, runs, hold=1)
    assert table.count("return ") >= 3 and "mosaic" in table and "bare" in table
    assert "error at every return <= 1 deg: PASS (max 0.50)" in table
    assert "again: PASS (worst 0)" in table
    ev.write_json(tmp_path / "long.json", {"long_run/mosaic": ev.long_json(m, good.ms_per_frame, W, H, T)})
    json.loads((tmp_path / "long.json").read_text(), parse_constant=lambda c: pytest.fail(f"not strict JSON: {c}"))
    # Section (b): the made-up confidence falls as the error grows, so it separates them perfectly.
    text, figures = ev.auroc_section(series)
    pooled = figures["POOLED all configurations"]
    assert pooled["auroc"] == 1.0 and pooled["negatives"] > 0 and pooled["positives"] > 0
    assert "n/a" in text  # the default runs alone have no frame above 5 degrees
    flipped = [replace(s, confidence=1.0 - s.confidence) for s in series]
    assert ev.auroc_section(flipped)[1]["POOLED all configurations"]["auroc"] == 0.0
    # The per-frame figures survive a round trip through a file (for pooling runs of several processes).
    ev.save_series(tmp_path / "s.npz", series)
    back = ev.load_series(tmp_path / "s.npz")
    assert [(b.scenario, b.config, b.default) for b in back] == [(s.scenario, s.config, s.default) for s in series]
    for b, s in zip(back, series):
        for f in ("error", "confidence", "success", "in_view"):
            assert torch.equal(getattr(b, f), getattr(s, f))
        assert (b.ms_per_frame, b.width, b.height) == (s.ms_per_frame, W, H)
    # ... and section (a)'s table is printed again from them, with the ground truth from the cache.
    folder = tmp_path / f"long_run_{W}x{H}_{T}f"
    folder.mkdir()
    save_ground_truth(gt, folder / "long_run")
    tables, figures = ev.long_tables_from_series(back, tmp_path, hold=1)
    assert len(tables) == 1 and tables[0].splitlines()[1:] == table.splitlines()[1:]
    assert figures["long_run/mosaic"]["return_errors_deg"] == m.return_errors_deg


def test_evaluate_table_reports_units_at_rest():
    """A scenario's table adds the units the truth leaves at rest (pooled RMSE / worst error) when scored."""
    ev = _load_evaluate()
    base = dict(rot_err_mean_deg=0.4, rot_err_median_deg=0.4, rot_err_max_deg=0.9, yaw_err_deg=0.1,
                pitch_err_deg=0.1, roll_err_deg=0.1, trans_err_mm=1.0, trans_rel_err_mm=1.0, au_rmse=0.05,
                au_corr=0.9, converged=1.0, success=1.0, lost_frames=0, ms_per_frame=5.0)  # fmt: skip
    rows = {"full": dict(base, au_inactive_rmse=0.0123, au_inactive_max=0.3456)}
    text = ev.table("expressions", rows, "made up")
    assert "AUs the truth leaves at rest" in text and "0.012 / 0.346" in text
    plain = ev.table("pose_sweep", {"full": dict(base, au_inactive_rmse=float("nan"))}, "made up")
    assert "at rest" not in plain


def test_evaluate_noise_seeds_track_each_seed_again(tmp_path, capsys):
    """--noise-seeds: one full-configuration run per seed (the main seed's run reused), a table of them with the
    worst seed's figures, and one JSON entry per extra seed whose figures come from its own initial landmarks."""
    ev = _load_evaluate()
    out = tmp_path / "e.json"
    argv = ["--scenarios", "pose_sweep", "--frames", "3", "--size", "160x120", "--ablations", "none", "--cache",
            "none", "--no-auroc", "--progress-every", "0", "--noise-seeds", "0,1", "--json", str(out)]  # fmt: skip
    assert ev.main(argv) == 0
    text = capsys.readouterr().out
    assert "pose_sweep across landmark-noise seeds" in text and "worst over 2 seeds" in text
    figures = json.loads(out.read_text())
    assert set(figures) == {"pose_sweep", "pose_sweep/seed1"}
    assert figures["pose_sweep"]["rot_err_max_deg"] != figures["pose_sweep/seed1"]["rot_err_max_deg"]
    worst = max(figures["pose_sweep"]["rot_err_max_deg"], figures["pose_sweep/seed1"]["rot_err_max_deg"])
    assert f"max {worst:.2f} deg" in text
    with pytest.raises(SystemExit):
        ev.main(["--scenarios", "pose_sweep", "--noise-seeds", "1,x"])


def _spy_track_sequence(ev, monkeypatch, field: str) -> list:
    """Replace ``ev.track_sequence`` by a spy recording ``(label, getattr(config, field))`` of every run."""
    seen = []
    real = ev.track_sequence

    def spy(model, config, seq, landmarks, label, every):
        seen.append((label, getattr(config, field)))
        return real(model, config, seq, landmarks, label, every)

    monkeypatch.setattr(ev, "track_sequence", spy)
    return seen


def test_evaluate_selection_seeds_track_each_draw_again(tmp_path, capsys, monkeypatch):
    """--selection-seeds: one full-configuration run per draw of the template points (the default draw's run
    reused), each with that TrackerConfig.selection_seed and the default landmarks, and a table of them."""
    ev = _load_evaluate()
    seen = _spy_track_sequence(ev, monkeypatch, "selection_seed")
    out = tmp_path / "e.json"
    argv = ["--scenarios", "pose_sweep", "--frames", "3", "--size", "160x120", "--ablations", "none", "--cache",
            "none", "--no-auroc", "--progress-every", "0", "--selection-seeds", "0,2", "--json", str(out)]  # fmt: skip
    assert ev.main(argv) == 0
    text = capsys.readouterr().out
    assert "pose_sweep across template selection seeds" in text and "worst over 2 seeds" in text
    assert seen == [("pose_sweep/full", 0), ("pose_sweep/draw2", 2)]
    figures = json.loads(out.read_text())
    assert set(figures) == {"pose_sweep", "pose_sweep/draw2"}
    for bad in ("1,x", "-1"):
        with pytest.raises(SystemExit):
            ev.main(["--scenarios", "pose_sweep", "--selection-seeds", bad])


def test_evaluate_lookahead_hands_the_frames_read_ahead_to_the_tracking_pass(tmp_path, monkeypatch):
    """--lookahead: the first --lookahead-frames frames go to lookahead_fit, then every frame is tracked in order
    from the fit it returns; with that fit replaced by the plain landmark fit (a spy) the figures equal the run
    without look-ahead."""
    from torchface.tracker import fit_landmarks

    ev = _load_evaluate()
    seen = []

    def spy(model, tracker_config, frames, landmarks_px, intrinsics, weights=None, config=None):
        seen.append((tuple(frames.shape), config.max_frames))
        return fit_landmarks(model, landmarks_px, intrinsics, weights, config=tracker_config.fit), [[]]

    monkeypatch.setattr(ev, "lookahead_fit", spy)
    base = ["--scenarios", "pose_sweep", "--frames", "6", "--size", "160x120", "--ablations", "none", "--cache",
            "none", "--no-auroc", "--progress-every", "0"]  # fmt: skip
    plain, ahead = tmp_path / "p.json", tmp_path / "a.json"
    # (--lookahead runs without the online start; so does the plain run, which otherwise re-anchors wherever the head
    # turns 10 degrees in these 6 frames: a 160x120 face with 2 px of landmark noise loses the track and turns)
    assert ev.main(base + ["--json", str(plain), "--no-online-refine"]) == 0
    assert ev.main(base + ["--json", str(ahead), "--lookahead", "--lookahead-frames", "4"]) == 0
    assert seen == [((1, 4, 3, 120, 160), 4)]
    assert json.loads(ahead.read_text())["pose_sweep"] | {"ms_per_frame": 0, "init_ms": 0} == json.loads(
        plain.read_text())["pose_sweep"] | {"ms_per_frame": 0, "init_ms": 0}  # fmt: skip
    assert ev.LOOKAHEAD is not None
    ev.main(base + ["--json", str(plain)])
    assert ev.LOOKAHEAD is None  # reset by a run without --lookahead


def test_evaluate_gives_the_managed_runs_the_online_start_unless_told_not_to(monkeypatch):
    """The online start is the default: every tracker with template management is built with refine_first (its
    max_frames from --lookahead-frames), the no_management ablation without; --no-online-refine and --lookahead
    (the other way to refine the first pose) run without it, and the setting is reset by the next run."""
    from torchface.tracker.lookahead import LookaheadConfig

    ev = _load_evaluate()
    seen = []
    real = ev.FaceTracker

    def spy(config, model=None, refine_first=None, **kwargs):
        seen.append((config.template.enabled, refine_first))
        return real(config, model=model, refine_first=refine_first, **kwargs)

    monkeypatch.setattr(ev, "FaceTracker", spy)
    base = ["--scenarios", "pose_sweep", "--frames", "3", "--size", "160x120", "--cache", "none", "--no-auroc",
            "--progress-every", "0", "--ablations", "no_management"]  # fmt: skip
    assert ev.main(base + ["--lookahead-frames", "7"]) == 0
    assert seen == [(True, LookaheadConfig(max_frames=7)), (False, None)]
    seen.clear()
    assert ev.main(base + ["--no-online-refine"]) == 0
    assert seen == [(True, None), (False, None)]
    seen.clear()
    assert ev.main(base) == 0
    assert seen == [(True, LookaheadConfig()), (False, None)]
    seen.clear()
    assert ev.main(base + ["--lookahead"]) == 0
    assert seen == [(True, None), (False, None)]


def test_evaluate_expression_quota_sets_every_runs_config(monkeypatch):
    """--expression-quota: every run (each ablation, each noise seed) gets that TrackerConfig.expression_quota;
    without it the default's; out of [0, 1] is refused."""
    ev = _load_evaluate()
    seen = _spy_track_sequence(ev, monkeypatch, "expression_quota")
    base = ["--scenarios", "pose_sweep", "--frames", "3", "--size", "160x120", "--cache", "none", "--no-auroc",
            "--progress-every", "0", "--ablations", "no_robust", "--noise-seeds", "0,1"]  # fmt: skip
    assert ev.main(base + ["--expression-quota", "0.05"]) == 0
    assert seen == [("pose_sweep/full", 0.05), ("pose_sweep/no_robust", 0.05), ("pose_sweep/seed1", 0.05)]
    seen.clear()
    assert ev.main(base) == 0
    assert [q for _, q in seen] == [ev.TrackerConfig().expression_quota] * 3
    with pytest.raises(SystemExit):
        ev.main(base + ["--expression-quota", "1.5"])


def test_evaluate_motion_prediction_sets_every_runs_config(monkeypatch):
    """--motion-prediction: every run gets that TrackerConfig.motion_prediction but the one without template
    management (no_management: the prediction needs it), which runs off; without it 0; out of [0, 1] is refused."""
    ev = _load_evaluate()
    seen = _spy_track_sequence(ev, monkeypatch, "motion_prediction")
    base = ["--scenarios", "pose_sweep", "--frames", "3", "--size", "160x120", "--cache", "none", "--no-auroc",
            "--progress-every", "0", "--ablations", "no_robust,no_management"]  # fmt: skip
    assert ev.main(base + ["--motion-prediction", "0.5"]) == 0
    assert seen == [("pose_sweep/full", 0.5), ("pose_sweep/no_robust", 0.5), ("pose_sweep/no_management", 0.0)]
    seen.clear()
    assert ev.main(base) == 0
    assert [k for _, k in seen] == [0.0] * 3
    with pytest.raises(SystemExit):
        ev.main(base + ["--motion-prediction", "1.5"])


def test_evaluate_expression_sparsity_sets_every_runs_config(monkeypatch):
    """--expression-sparsity: every run gets that TrackerConfig.expression_sparsity, 'none' the Gaussian prior;
    without it the default's; a delta that is not a number > 0 is refused."""
    ev = _load_evaluate()
    seen = _spy_track_sequence(ev, monkeypatch, "expression_sparsity")
    base = ["--scenarios", "pose_sweep", "--frames", "3", "--size", "160x120", "--cache", "none", "--no-auroc",
            "--progress-every", "0", "--ablations", "no_robust", "--noise-seeds", "0,1"]  # fmt: skip
    assert ev.main(base + ["--expression-sparsity", "0.03"]) == 0
    assert [d for _, d in seen] == [0.03] * 3
    seen.clear()
    assert ev.main(base + ["--expression-sparsity", "none"]) == 0
    assert [d for _, d in seen] == [None] * 3
    seen.clear()
    assert ev.main(base) == 0
    assert [d for _, d in seen] == [ev.TrackerConfig().expression_sparsity] * 3
    for bad in ("0", "-1", "abc", "nan"):
        with pytest.raises(SystemExit):
            ev.main(base + ["--expression-sparsity", bad])
