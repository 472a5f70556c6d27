"""``torchface track --model FILE`` (``JobConfig.model``): CANDIDE-3 through a face model file tracks as the default
to the byte; another model writes its own columns and sidecar entry; a resume with another model, a detector with a
model of other landmarks, landmarks files of another count and bad model files are refused before tracking."""

from __future__ import annotations

import gc
import json
from dataclasses import fields, replace

import numpy as np
import pytest
import torch

import torchface.job
from torchface.cli import main
from torchface.io import InputError, read_track_csv
from torchface.job import JobConfig, output_paths, track_videos
from torchface.model import FaceModel, face_model_digest, load_candide3, save_face_model
from torchface.synth.scenarios import make_scenario
from torchface.synth.sequence import load_ground_truth, write_sequence
from torchface.tracker import FitConfig, LookaheadConfig, TrackerConfig

T, W, H, NAME = 6, 160, 120, "expressions"
#: The other model's landmarks: 26 of CANDIDE-3's 68 iBUG points (brows, nose, eyes, mouth), in this order.
SUBSET = list(range(17, 68, 2))


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    root = tmp_path_factory.mktemp("clip")
    files = write_sequence(make_scenario(NAME, T, W, H), root)
    points = load_ground_truth(files.ground_truth).landmarks_px[0].numpy()
    np.savetxt(root / "lm68.csv", points, delimiter=",")
    np.savetxt(root / "lm26.csv", points[SUBSET], delimiter=",")
    save_face_model(load_candide3(dtype=torch.float64), root / "candide3.npz")
    c = load_candide3(dtype=torch.float64)
    other = replace(c, name="CANDIDE-3, 6 AUVs, 26 landmarks", animation_units=c.animation_units[:6],
                    animation_names=c.animation_names[:6], animation_ranges=c.animation_ranges[:6],
                    facs_matrix=c.facs_matrix[:, :6], landmark_vertices=c.landmark_vertices[SUBSET],
                    landmark_weights=c.landmark_weights[SUBSET],
                    landmark_names=tuple(c.landmark_names[k] for k in SUBSET))  # fmt: skip
    save_face_model(other, root / "other.npz")
    return files.video, root


@pytest.fixture(scope="module")
def default_run(clip, tmp_path_factory):
    video, root = clip
    out = tmp_path_factory.mktemp("default")
    track_videos([video], JobConfig(out, landmarks=(root / "lm68.csv",)))
    return output_paths(out, NAME)


def test_candide3_through_a_model_file_tracks_as_the_default_to_the_byte(clip, default_run, tmp_path):
    """The CSV of --model FILE (CANDIDE-3 saved in float64) is the default run's byte for byte; the sidecar's model
    entry names the model, its file and its digest (it said "CANDIDE-3" whatever tracked)."""
    video, root = clip
    rc = main(["track", str(video), "--out", str(tmp_path), "--landmarks", str(root / "lm68.csv"), "--model",
               str(root / "candide3.npz"), "--quiet"])  # fmt: skip
    assert rc == 0
    mine = output_paths(tmp_path, NAME)
    assert mine["csv"].read_bytes() == default_run["csv"].read_bytes()
    side, ref = (json.loads(p["json"].read_text())["model"] for p in (mine, default_run))
    assert side["sha256"] == ref["sha256"] == face_model_digest(load_candide3())
    assert side["name"] == ref["name"] == "CANDIDE-3 v3.1.6" and side["landmarks"] == 68
    assert side["file"] == str(root / "candide3.npz") and ref["file"] is None
    assert side["shape_coeffs"] == ref["shape_coeffs"]
    # the same model, given or not, is one setting: the complete outputs are resumed (skipped), not refused
    assert main(["track", str(video), "--out", str(tmp_path), "--landmarks", str(root / "lm68.csv"), "--resume",
                 "--quiet"]) == 0  # fmt: skip


def test_another_model_tracks_with_its_own_landmarks_and_columns(clip, default_run, tmp_path):
    """A model of 6 animation units and 26 landmarks, from a landmarks file of its 26 points: its columns, its
    sidecar entry; resuming its complete outputs with CANDIDE-3 is refused (they were skipped as complete)."""
    video, root = clip
    track_videos([video], JobConfig(tmp_path, landmarks=(root / "lm26.csv",), model=root / "other.npz"))
    paths = output_paths(tmp_path, NAME)
    cols, rows = read_track_csv(paths["csv"])
    ref_cols, ref_rows = read_track_csv(default_run["csv"])
    anim = [c for c in cols if c.startswith("anim_")]
    assert len(anim) == 6 and anim == [c for c in ref_cols if c.startswith("anim_")][:6]
    assert rows.shape[0] == T and rows[:, cols.index("success")].all()
    yaw = cols.index("yaw_deg")
    assert np.abs(rows[:, yaw] - ref_rows[:, ref_cols.index("yaw_deg")]).max() < 3.0  # the same head
    side = json.loads(paths["json"].read_text())["model"]
    assert side["name"] == "CANDIDE-3, 6 AUVs, 26 landmarks" and side["landmarks"] == 26
    assert len(side["animation_units"]) == 6 and side["sha256"] != face_model_digest(load_candide3())
    with pytest.raises(InputError, match="made with another face model .*CANDIDE-3 v3.1.6"):
        track_videos([video], JobConfig(tmp_path, landmarks=(root / "lm68.csv",), resume=True))


def test_a_partial_run_is_not_resumed_with_another_model(clip, tmp_path):
    """Interrupted with one model, resumed with CANDIDE-3 (or the other way round): refused, naming the models,
    before the CSV's columns are compared ("its columns differ" said nothing of the model); with its own model the
    resume completes it."""
    video, root = clip
    other = JobConfig(tmp_path, landmarks=(root / "lm26.csv",), model=root / "other.npz")

    def interrupt(p):
        if p.done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        track_videos([video], other, progress=interrupt)
    partial = tmp_path / f"{NAME}.csv.partial"
    kept = partial.read_bytes()
    with pytest.raises(InputError, match=r"another face model \(model CANDIDE-3, 6 AUVs, 26 landmarks \(sha256 "
                                         r"[0-9a-f]{16}\) then, CANDIDE-3 \(no model\) now\)"):  # fmt: skip
        track_videos([video], JobConfig(tmp_path, landmarks=(root / "lm68.csv",), resume=True))
    assert partial.read_bytes() == kept
    track_videos([video], replace(other, resume=True))
    assert read_track_csv(tmp_path / f"{NAME}.csv")[1].shape[0] == T
    out = tmp_path / "second"  # made with CANDIDE-3, resumed with the other model
    with pytest.raises(KeyboardInterrupt):
        track_videos([video], JobConfig(out, landmarks=(root / "lm68.csv",)), progress=interrupt)
    with pytest.raises(InputError, match=r"another face model \(model CANDIDE-3 \(no model\) then, CANDIDE-3, 6"):
        track_videos([video], replace(other, out_dir=out, resume=True))


def test_what_a_model_cannot_track_is_refused_before_anything_is_written(clip, tmp_path, capsys):
    video, root = clip
    out = tmp_path / "out"
    with pytest.raises(InputError, match="has 26 landmarks, and the dlib detector gives the 68 iBUG points"):
        track_videos([video], JobConfig(out, detector="dlib", model=root / "other.npz"))  # (dlib need not be there)
    # (neither landmarks nor a detector: it said "give --landmarks FILE (68 iBUG points ...) or --detector NAME")
    # (the command line's "give --landmarks FILE ...": from Python, the JobConfig field)
    said = r"give landmarks=\(FILE, \.\.\.\) \(the 26 landmarks of the face model 'CANDIDE-3, 6 AUVs, 26 landmarks', "
    with pytest.raises(InputError, match=said + r"of the first frame, in its order\)$"):
        track_videos([video], JobConfig(out, model=root / "other.npz"))
    with pytest.raises(InputError, match=r"lm68.csv: expected 26 landmarks \(the face model's\), got 68"):
        track_videos([video], JobConfig(out, landmarks=(root / "lm68.csv",), model=root / "other.npz"))
    with pytest.raises(InputError, match="expected 68 iBUG landmarks, got 26"):
        track_videos([video], JobConfig(out, landmarks=(root / "lm26.csv",), model=root / "candide3.npz"))
    bad = tmp_path / "bad.npz"
    bad.write_text("not a model\n")
    rc = main(["track", str(video), "--out", str(out), "--landmarks", str(root / "lm68.csv"), "--model", str(bad),
               "--quiet"])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0 and "not a torchface face model file" in err, err
    rc = main(["track", str(video), "--out", str(out), "--landmarks", str(root / "lm68.csv"), "--model",
               str(tmp_path / "nope.npz"), "--quiet"])  # fmt: skip
    assert rc == 2 and "no such face model file" in capsys.readouterr().err
    assert not out.exists() or not list(out.iterdir())
    with pytest.raises(TypeError, match="model must be a path"):
        JobConfig(out, model=load_candide3())  # type: ignore[arg-type]


def test_a_model_path_that_names_no_file_is_refused_when_the_config_is_made(tmp_path, monkeypatch):
    """``JobConfig(model="~/m.npz")`` was taken (nothing expands the ``~``: the job then said "no such face model
    file"), and ``model=""`` too (the current folder: "a folder, not a face model file"), where ``out_dir``'s and
    training_hooks' ``FaceTrackingConfig.model`` are refused when made; a ``~name`` that no home is stays a name."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match=r"model '~/m.npz' starts with '~', which is not expanded .*expanduser"):
        JobConfig(out_dir="o", model="~/m.npz")
    with pytest.raises(ValueError, match="model is an empty path"):
        JobConfig(out_dir="o", model="")
    with pytest.raises(TypeError, match="model must be a path to a face model file or None"):
        JobConfig(out_dir="o", model=5)
    assert JobConfig(out_dir="o", model="~torchface-no-such-user.npz").model == "~torchface-no-such-user.npz"


def test_a_model_whose_landmarks_cannot_start_a_track_is_refused_up_front(clip, tmp_path):
    """Three landmarks (the first frame's pose needs four): refused naming the model file, before anything is
    written (the landmarks file's check said only "3 of the 3 landmarks given")."""
    video, root = clip
    c = load_candide3()
    save_face_model(replace(c, landmark_vertices=c.landmark_vertices[:3], landmark_weights=c.landmark_weights[:3],
                            landmark_names=c.landmark_names[:3]), tmp_path / "three.npz")  # fmt: skip
    np.savetxt(tmp_path / "lm3.csv", np.loadtxt(root / "lm68.csv", delimiter=",")[:3], delimiter=",")
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"three.npz: the model 'CANDIDE-3 v3.1.6' has 3 landmarks"):
        track_videos([video], JobConfig(out, landmarks=(tmp_path / "lm3.csv",), model=tmp_path / "three.npz"))
    assert not out.exists()


def test_settings_of_another_models_units_are_refused_before_earlier_outputs_are_touched(clip, tmp_path):
    """Settings that count or name the model's units (CANDIDE-3's 11 expression prior weights, a shape unit the
    model lacks, one shape precision per unit) given with the 6-unit model's file, over the complete outputs of an
    earlier run of it: refused before anything is touched. They were refused only once the batch had started (the
    look-ahead's, after its frames were read ahead), after the fresh run had removed those outputs: a ValueError
    left ``.csv.partial`` and ``.record.partial`` where the complete outputs had been."""
    video, root = clip
    config = JobConfig(tmp_path, landmarks=(root / "lm26.csv",), model=root / "other.npz")
    track_videos([video], config)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    S = load_candide3().num_shape
    for bad, message in (
        (dict(tracker=TrackerConfig(expression_prior_weights=(1.0,) * 11)),
         "expression_prior_weights has 11 factors for a model with 6 animation units"),
        (dict(tracker=TrackerConfig(fit=FitConfig(fit_expression=True, shape_prior_precision=(2.0,) * 6))),
         f"shape_prior_precision has 6 values; the model has {S} shape units"),
        (dict(refine_first=LookaheadConfig(shape_units=(S,))), f"refine_first.shape_units must be < {S}"),
        (dict(lookahead=LookaheadConfig(shape_prior_precision=(2.0,) * 6)),
         f"lookahead.shape_prior_precision has 6 values; the model has {S}"),
    ):  # fmt: skip
        with pytest.raises(ValueError, match=message):
            track_videos([video], replace(config, **bad))
        assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before, bad
    # the online start's settings are not checked where it does not run (with --lookahead instead)
    track_videos([video], replace(config, lookahead=LookaheadConfig(), refine_first=LookaheadConfig(shape_units=(S,))))


def test_frames_too_small_for_the_pyramid_are_refused_before_earlier_outputs_are_touched(clip, tmp_path):
    """A tracker of 8 pyramid levels needs frames of at least 192x192; on the 160x120 clip, over the complete outputs
    of an earlier run, it was refused only at the batch's start, after the fresh run had cleared those outputs: the
    ValueError left ``.csv.partial`` and ``.record.partial`` in their place. Refused before, naming the video, with
    the outputs byte for byte as they were."""
    video, root = clip
    config = JobConfig(tmp_path, landmarks=(root / "lm26.csv",), model=root / "other.npz")
    track_videos([video], config)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    deep = TrackerConfig(num_levels=8, iterations=(4,) * 8)
    said = rf"{video.name}: frames must be at least 192x192 pixels for tracker.num_levels = 8, got 160x120 \(W x H\)"
    for bad in (dict(tracker=deep), dict(tracker=deep, lookahead=LookaheadConfig())):
        with pytest.raises(ValueError, match=said):
            track_videos([video], replace(config, **bad))
        assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before, bad


def test_a_job_keeps_no_model_alive_after_it(clip, tmp_path):
    """The job's model (on its device) is not held once the job is over (an lru_cache of its digest kept the last
    job's model alive: on a GPU, its memory)."""
    video, root = clip
    track_videos([video], JobConfig(tmp_path, landmarks=(root / "lm26.csv",), model=root / "other.npz"))
    gc.collect()
    assert not [o for o in gc.get_objects() if isinstance(o, FaceModel) and o.name.endswith("26 landmarks")]


def test_the_default_model_is_loaded_once_per_process_and_left_as_loaded(clip, default_run, tmp_path, monkeypatch):
    """Each job loaded CANDIDE-3 (45 ms), and the check of its digest loaded it once more. Now the first job loads it
    and the later ones share it (a job's model is _job_model's): one load, on the CPU whatever torch's default device
    then (a GPU copy loaded there stayed alive for the process's life; under "meta" the load failed); nothing of a
    job writes into it (its tensors' version counters, which count in-place writes, even of equal values, are as
    loaded; it equals a fresh load), and the job's outputs are the default run's byte for byte."""
    video, root = clip
    loads: list[int] = []
    real = torchface.job.load_candide3
    monkeypatch.setattr(torchface.job, "load_candide3", lambda *a, **k: loads.append(1) or real(*a, **k))
    torchface.job._candide3.cache_clear()
    torchface.job._candide_digest.cache_clear()
    with torch.device("meta"):  # (the default device when the first job loads it; "cuda" where there is one)
        shared = torchface.job._job_model(JobConfig(tmp_path))
    assert shared.device == torch.device("cpu")
    tensors = {f.name: getattr(shared, f.name) for f in fields(shared) if isinstance(getattr(shared, f.name),
               torch.Tensor)}  # fmt: skip
    versions = {name: t._version for name, t in tensors.items()}
    track_videos([video], JobConfig(tmp_path, landmarks=(root / "lm68.csv",)))
    for kind in ("csv", "overlay", "normalised"):
        assert output_paths(tmp_path, NAME)[kind].read_bytes() == default_run[kind].read_bytes()
    assert torchface.job._job_model(JobConfig(tmp_path / "next")) is shared  # (the next job's)
    assert shared is torchface.job._candide3() and len(loads) == 1
    assert {name: t._version for name, t in tensors.items()} == versions
    assert not any(t.requires_grad for t in tensors.values())
    fresh = load_candide3()
    assert all(torch.equal(getattr(shared, f.name), getattr(fresh, f.name)) if isinstance(getattr(fresh, f.name),
               torch.Tensor) else getattr(shared, f.name) == getattr(fresh, f.name) for f in fields(fresh))  # fmt: skip
