"""``FaceTrackingConfig(model=FILE)``: NormaliseFaces and the datasets track with a face model file (as ``torchface
track --model``): CANDIDE-3 through the file gives the default's items to the bit; another model takes its own
landmarks and keys its cache entries apart; a detector with a model of other landmarks is refused when the dataset is
made. The default config's cache key and repr are those of before the field; a config with a model shows it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from th_data import TRACKING
from torchface.io import InputError
from torchface.synth.io import read_video
from torchface.model import load_candide3, save_face_model
from training_hooks import DatasetConfig, FaceTrackingConfig, NormaliseFaces, VideoDataset, cache_key

#: The other model's landmarks: 26 of CANDIDE-3's iBUG points, in this order.
SUBSET = list(range(17, 68, 2))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    save_face_model(load_candide3(dtype=torch.float64), root / "candide3.npz")
    c = load_candide3(dtype=torch.float64)
    other = replace(c, name="other", animation_units=c.animation_units[:6], animation_names=c.animation_names[:6],
                    animation_ranges=c.animation_ranges[:6], facs_matrix=c.facs_matrix[:, :6],
                    landmark_vertices=c.landmark_vertices[SUBSET], landmark_weights=c.landmark_weights[SUBSET],
                    landmark_names=tuple(c.landmark_names[k] for k in SUBSET))  # fmt: skip
    save_face_model(other, root / "other.npz")
    return root / "candide3.npz", root / "other.npz"


def test_candide3_through_a_file_normalises_as_the_default(clips, files):
    frames = read_video(clips[0].video)[:3]
    a = NormaliseFaces(TRACKING)(frames, clips[0].landmarks)
    b = NormaliseFaces(replace(TRACKING, model=files[0]))(frames, clips[0].landmarks)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_another_model_tracks_from_its_landmarks_with_its_own_cache_entries(clips, files, tmp_path):
    other = replace(TRACKING, model=files[1])
    lm = clips[0].landmarks[SUBSET]
    config = DatasetConfig(tracking=other, cache_dir=tmp_path / "cache", clip_length=3)
    items = list(VideoDataset([clips[0].video], [lm], config))
    assert items and items[0]["anim_coeffs"].shape[-1] == 6 and bool(items[0]["success"].all())
    with pytest.raises(Exception, match=r"expected 26 landmarks \(the face model's\), got 68"):
        list(VideoDataset([clips[0].video], [clips[0].landmarks], replace(config, cache_dir=None)))
    content = "0" * 64
    assert cache_key(content, other, lm) != cache_key(content, replace(other, model=files[0]), lm)
    assert "model" not in repr(TRACKING)  # (the default repr and key are those of before the field)


def test_a_printed_config_names_its_model_and_the_key_holds_its_content_not_its_path(files, tmp_path, monkeypatch):
    """``repr`` shows ``model`` when given (it was left out: a printed config hid the model); the cache key hashes
    the repr without it and the file's content, so the same file at another path keys the same sequences. A relative
    ``model`` was kept relative and loaded against the working folder of the moment (a DataLoader worker, an epoch
    after Lightning's or Hydra's os.chdir): it is made absolute when the config is made, its key unchanged."""
    other = replace(TRACKING, model=files[1])
    assert repr(other) == repr(TRACKING)[:-1] + f", model={files[1]!r})"
    monkeypatch.chdir(files[1].parent)
    relative = replace(TRACKING, model=files[1].name)
    monkeypatch.chdir(tmp_path)
    assert relative.model == files[1] and relative == other
    with pytest.raises(ValueError, match="model is empty"):
        replace(TRACKING, model="")
    with pytest.raises(ValueError, match=r"model '~/m.npz' starts with '~', which is not expanded .*: give os.path.expanduser"):
        replace(TRACKING, model="~/m.npz")  # (was <cwd>/~/m.npz: "no such file" only when first loaded)
    moved = tmp_path / "moved.npz"
    moved.write_bytes(files[1].read_bytes())
    lm = np.zeros((len(SUBSET), 2))
    assert cache_key("0" * 64, other, lm) == cache_key("0" * 64, replace(TRACKING, model=moved), lm)


def test_a_detector_with_a_model_of_other_landmarks_is_refused_when_made(clips, files):
    with pytest.raises(ValueError, match="has 26 landmarks, and a detector gives the 68 iBUG points"):
        VideoDataset([clips[0].video], lambda image: None,
                     DatasetConfig(tracking=replace(TRACKING, model=files[1])))  # fmt: skip
    with pytest.raises(TypeError, match="model must be a path"):
        FaceTrackingConfig(model=load_candide3())  # type: ignore[arg-type]


def test_the_landmarks_messages_name_the_models_count(clips, files, tmp_path):
    """With a model of 26 landmarks, a landmarks argument of the wrong type and a landmarks file of the wrong form
    are told the model's (26, 2) points (they were told "(68, 2)", the iBUG points the model does not take)."""
    config = DatasetConfig(tracking=replace(TRACKING, model=files[1]))
    with pytest.raises(TypeError, match=r"one \(26, 2\) array/tensor .* an \(N, 26, 2\) stack"):
        VideoDataset([clips[0].video], "first.csv", config)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"must be a \(26, 2\) array or tensor"):
        VideoDataset([clips[0].video], [clips[0].landmarks[SUBSET].tolist()], config)  # type: ignore[list-item]
    (tmp_path / "first.json").write_text('{"frame": 0}')
    with pytest.raises(InputError, match=r"expected a list of 26 \[x, y\] pairs"):
        list(VideoDataset([clips[0].video], [tmp_path / "first.json"], config))
    with open(tmp_path / "first.npy", "wb") as f:  # (an .npz archive under an .npy name)
        np.savez(f, points=clips[0].landmarks[SUBSET])
    with pytest.raises(InputError, match=r"save the \(26, 2\) points with np.save"):
        list(VideoDataset([clips[0].video], [tmp_path / "first.npy"], config))


def test_a_bad_model_file_is_refused_when_the_dataset_is_made(clips, tmp_path):
    """A missing or damaged model file with landmarks given: refused by VideoDataset(...) itself, as with a detector
    (it was found only when the first video was tracked, in each DataLoader worker)."""
    (tmp_path / "bad.npz").write_text("not a model\n")
    for path, said in ((tmp_path / "nope.npz", "no such face model file"), (tmp_path / "bad.npz", "not a torchface")):
        with pytest.raises(InputError, match=said):
            VideoDataset([clips[0].video], [clips[0].landmarks], DatasetConfig(tracking=replace(TRACKING, model=path)))


def test_a_model_file_saved_again_does_not_take_the_sequences_of_the_model_read_before(clips, files, tmp_path):
    """A dataset tracks with the model it read when made; the file saved again (another model) before it tracks:
    its cache entries are keyed by the content it read, so a dataset made after, of the new file, tracks with the new
    model (the entries were keyed by the file's content when stored: the new model's key held the old model's
    sequence, and the new dataset's items came from it)."""
    path = tmp_path / "model.npz"
    path.write_bytes(files[1].read_bytes())  # (the 26-landmark model of 6 animation units)
    lm = clips[0].landmarks[SUBSET]
    config = DatasetConfig(tracking=replace(TRACKING, model=path), cache_dir=tmp_path / "cache", clip_length=3)
    first = VideoDataset([clips[0].video], [lm], config)
    c = load_candide3(dtype=torch.float64)
    five = replace(c, name="five", animation_units=c.animation_units[:5], animation_names=c.animation_names[:5],
                   animation_ranges=c.animation_ranges[:5], facs_matrix=c.facs_matrix[:, :5],
                   landmark_vertices=c.landmark_vertices[SUBSET], landmark_weights=c.landmark_weights[SUBSET],
                   landmark_names=tuple(c.landmark_names[k] for k in SUBSET))  # fmt: skip
    save_face_model(five, path)
    assert next(iter(first))["anim_coeffs"].shape[-1] == 6  # (the model it read)
    item = next(iter(VideoDataset([clips[0].video], [lm], config)))
    assert item["anim_coeffs"].shape[-1] == 5
    content = "0" * 64
    assert cache_key(content, config.tracking, lm, model_content="1" * 64) != cache_key(content, config.tracking, lm)
    with pytest.raises(ValueError, match="config has no model"):
        cache_key(content, TRACKING, clips[0].landmarks, model_content="1" * 64)
