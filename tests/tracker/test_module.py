"""Tests of torchface.tracker.module, the ``FaceTracker`` nn.Module around the managed step: what it does with its
tracked state besides stepping (keeping some streams, shallow copies, ``load_state_dict``, pickling). Small
rendered sequences (320x240, two pyramid levels), as in tests/tracker/test_step.py; the module's tracking itself
is tested there and in tests/tracker/test_managed.py.
"""

from __future__ import annotations

import copy
import dataclasses
import io
import sys
from pathlib import Path

import pytest
import torch

from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import euler_to_matrix
from torchface.model.candide import load_candide3
from torchface.synth.background import BackgroundSpec
from torchface.synth.scenarios import default_light
from torchface.synth.sequence import SequenceSpec, render_sequence
from torchface.tracker import FaceTracker, FitConfig, TrackerConfig, managed_step

# The clips shared with other folders' tests (tests/_helpers.py; the tests folder on sys.path, whatever pytest's
# import mode).
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _helpers import sideways_clip  # noqa: E402

W, H = 320, 240
D = torch.float64
CFG = TrackerConfig(
    num_levels=2, max_points=600, iterations=(6, 4), fit=FitConfig(shape_prior_precision=0.0, held_shape_units=()),
    robust_scale_floor=(0.045, 0.02),
)
FIELDS = ("rotation", "translation", "anim_coeffs", "illumination", "status", "confidence", "mosaic_entry")


@pytest.fixture(scope="module")
def model():
    return load_candide3()


def render(name: str, ypr: list[list[float]], txyz: list[list[float]], seed: int = 3):
    """``frames (T, 3, H, W)`` of CANDIDE-3 at poses ``ypr`` (degrees) and ``txyz`` (mm); first landmarks
    ``(68, 2)``."""
    T = len(ypr)
    spec = SequenceSpec(
        name=name, subject="candide3", intrinsics=Intrinsics.default(W, H),
        rotation=euler_to_matrix(torch.tensor(ypr, dtype=D)), translation=torch.tensor(txyz, dtype=D),
        anim=torch.zeros(T, load_candide3().num_animation, dtype=D), light=default_light(T),
        background=BackgroundSpec(seed=seed), photo="james",
    )  # fmt: skip
    frames, gt = render_sequence(spec)
    return frames, gt.landmarks_px[0].float()


@pytest.fixture(scope="module")
def three_streams():
    """Three different 6-frame streams with small motion: ``frames (3, 6, 3, H, W)``, landmarks ``(3, 68, 2)``."""
    s = [i / 5 for i in range(6)]
    a = render("a", [[7 * u, -4 * u, 3 * u] for u in s], [[8 * u, -4 * u, 450 + 10 * u] for u in s])
    b = render("b", [[-6 * u, 3 * u, -2 * u] for u in s], [[-15 + 4 * u, 5.0, 480 - 8 * u] for u in s], seed=7)
    c = render("c", [[2 * u, 5 * u, 0.0] for u in s], [[10.0, -6 * u, 430.0] for u in s], seed=11)
    return torch.stack([a[0], b[0], c[0]]), torch.stack([a[1], b[1], c[1]])


@pytest.fixture(scope="module")
def turn_and_still():
    """Stream 0 turns its head 0 -> 30 degrees of yaw in 3 degree steps (a mosaic entry is added at 30 and aligned
    against on the step after), stream 1 holds still: ``frames (2, 11, 3, H, W)``, landmarks ``(2, 68, 2)``."""
    yaw = [3.0 * i for i in range(11)]
    frames, lm = render("turn", [[y, 0.0, 0.0] for y in yaw], [[0.0, 0.0, 450.0]] * len(yaw))
    return torch.stack([frames, frames[:1].expand_as(frames)]), torch.stack([lm, lm])


def assert_same(a, b, index=None, atol: float = 0.0):
    """Results ``a`` (its streams ``index``, all by default) and ``b`` agree to ``atol``."""
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        x = x if index is None else x[index]
        if name in ("status", "mosaic_entry"):
            assert torch.equal(x, y), name
        else:
            torch.testing.assert_close(y, x, rtol=0, atol=atol, msg=lambda m: f"{name}: {m}")


# ----------------------------------------------------------------------------------------------- select


def test_select_keeps_streams_that_track_on_as_in_the_whole_batch(model, three_streams):
    """``FaceTracker.select``: the streams kept (here reordered) track on as they would have in the whole batch (to
    float rounding, as ``TrackerState.select`` documents) and exactly as the functional ``state.select`` +
    ``managed_step`` do; a bool mask is the same as its indices; a bad index leaves the state as it was. There was
    no public way to drop streams from a FaceTracker's batch."""
    frames, lm = three_streams
    whole = FaceTracker(CFG, model)
    whole.initialise(frames[:, 0], lm)
    whole(frames[:, 1])
    part, masked = copy.deepcopy(whole), copy.deepcopy(whole)
    state = copy.deepcopy(whole.state)
    keep = [2, 0]
    assert part.select(keep) is part
    assert part.state.params.shape[0] == 2 and part.state.frame_index == whole.state.frame_index
    with pytest.raises(ValueError, match="one per stream"):  # the next call takes the kept streams' frames only
        part(frames[:, 2])
    masked.select(torch.tensor([True, False, True]))
    state = state.select(keep)
    for t in range(2, frames.shape[1]):
        full, kept, plain = whole(frames[:, t]), part(frames[keep, t]), masked(frames[[0, 2], t])
        state, functional = managed_step(model, CFG, state, frames[keep, t])
        assert_same(full, kept, keep, atol=1e-4)
        assert_same(functional, kept)
        assert_same(full, plain, [0, 2], atol=1e-4)
    before = part.state
    with pytest.raises(IndexError, match="out of range"):
        part.select([2])
    assert part.state is before
    part.select([])  # no stream left (an empty list was "stream indices must be integers, got torch.float32")
    assert part.state.params.shape[0] == 0
    with pytest.raises(RuntimeError, match="initialise"):
        FaceTracker(CFG, model).select([0])


def test_select_names_an_index_of_the_wrong_type(model, three_streams):
    """``select(None)`` or a slice raised torch's RuntimeError "Could not infer dtype of NoneType" (from
    torch.as_tensor), a string a TypeError "new(): invalid data type 'str'": a TypeError naming the index now, as a
    float index already was; the state is left as it was."""
    frames, lm = three_streams
    tracker = FaceTracker(CFG, model, refine_first=None)
    tracker.initialise(frames[:, 0], lm)
    before = tracker.state
    for bad in (None, slice(0, 2), "0", {0, 2}):  # (a set: torch's RuntimeError "Could not infer dtype of set")
        with pytest.raises(TypeError, match=r"index must be stream indices .* or a \(3,\) bool mask, got"):
            tracker.select(bad)  # type: ignore[arg-type]
        with pytest.raises(TypeError, match="index must be stream indices"):
            before.select(bad)  # type: ignore[arg-type]
    assert tracker.state is before


def test_select_refuses_a_uint8_index_torch_takes_for_a_mask(model, three_streams):
    """A uint8 tensor (``mask.to(torch.uint8)``, a NumPy uint8 array) is a mask to torch's indexing (deprecated) but
    was taken for stream indices: ``[1, 0, 1]`` kept streams 1, 0 and 1 of the tracker, its state and a result, without
    a word. It is a TypeError saying ``.bool()`` or ``.long()``; the state is left as it was."""
    frames, lm = three_streams
    tracker = FaceTracker(CFG, model, refine_first=None)
    result = tracker.initialise(frames[:, 0], lm)
    before = tracker.state
    for bad in (torch.tensor([1, 0, 1], dtype=torch.uint8), torch.tensor([1, 0, 1]).numpy().astype("uint8")):
        with pytest.raises(TypeError, match=r"uint8 .* index\.bool\(\), or stream indices, index\.long\(\)"):
            tracker.select(bad)  # type: ignore[arg-type]
        with pytest.raises(TypeError, match="uint8"):
            result.select(bad)  # type: ignore[arg-type]
    assert tracker.state is before
    assert tracker.select(torch.tensor([1, 0, 1]).bool()).state.params.shape[0] == 2


def test_result_select_is_each_fields_rows(model, three_streams):
    """``TrackResult.select``: a result could not be split per stream (``result[0]``: a TypeError; the Python-API
    audit of session 63), only field by field. Its rows are each tensor field's, in the order asked (a bool mask as its
    indices, negative indices from the end); names and None fields as they are; bad indices refused as
    ``TrackerState.select`` refuses them."""
    frames, lm = three_streams
    tracker = FaceTracker(CFG, model, refine_first=None)
    tracker.initialise(frames[:, 0], lm)
    result = tracker(frames[:, 1])
    tensors = [f.name for f in dataclasses.fields(result) if isinstance(getattr(result, f.name), torch.Tensor)]
    assert {"rotation", "ypr_deg", "expression", "facs", "status", "confidence"} <= set(tensors)
    for index, rows in (([2, 0], [2, 0]), (torch.tensor([False, True, True]), [1, 2]), ([-1], [2]), ([], [])):
        part = result.select(index)
        for name in tensors:
            assert torch.equal(getattr(part, name), getattr(result, name)[rows]), name
        for f in dataclasses.fields(result):
            if not isinstance(getattr(result, f.name), torch.Tensor):
                assert getattr(part, f.name) == getattr(result, f.name), f.name
    assert result.select([1]).success.shape == (1,) and result.select([1]).start_failure_reasons == (None,)
    with pytest.raises(IndexError, match="out of range for 3 streams"):
        result.select([3])
    with pytest.raises(IndexError, match="must have 3 values"):
        result.select(torch.tensor([True, False]))
    with pytest.raises(TypeError, match="index must be stream indices"):
        result.select(slice(0, 2))  # type: ignore[arg-type]


# ----------------------------------------------------------------------------------------------- copies


class _NoFaces(torch.nn.Module):
    """A detector network that finds no face: ``frames (B, 3, H, W) -> (B, 68, 2)`` NaN."""

    def __init__(self) -> None:
        super().__init__()
        self.scale = torch.nn.Parameter(torch.ones(()))

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        return torch.full((frames.shape[0], 68, 2), float("nan")) * self.scale.detach()


def test_a_shallow_copy_tracks_on_apart_from_the_original(model, turn_and_still):
    """``copy.copy(tracker)`` forks the stream as ``copy.deepcopy`` does: neither one's steps change what the other
    tracks. The copy shared the tracked state, whose template tensors a step writes into (``donate=True``) where a
    stream changes mosaic entry: after the copy's stream 0 moved to the 30 degree entry, the original's next frame
    was aligned against that entry's template under its own reference entry's number (0.33 degrees off). The copy
    also shared the module's submodule table: setting its detector set the original's."""
    frames, lm = turn_and_still
    tracker = FaceTracker(CFG, model, detector=_NoFaces(), refine_first=None)
    tracker.initialise(frames[:, 0], lm)
    for t in range(1, 10):
        tracker(frames[:, t])
    fork, shallow = copy.deepcopy(tracker), copy.copy(tracker)
    entries = [shallow(frames[:, 10]).mosaic_entry.tolist() for _ in range(2)]
    assert entries == [[0, 0], [2, 0]], entries  # the copy's stream 0 changed entry alone: in place, were it shared
    want, got = fork(frames[:, 10]), tracker(frames[:, 10])
    assert_same(want, got)
    assert shallow.model is tracker.model and shallow.config is tracker.config and shallow.state is not tracker.state
    shallow.detector = None
    assert isinstance(tracker.detector, _NoFaces) and "detector" in dict(tracker.named_children())


# ----------------------------------------------------------------------------------------------- saving


def test_load_state_dict_forgets_the_tracked_sequence(model, three_streams):
    """A state_dict holds no tracked sequence, so loading one (into the tracker, or into a module holding it) leaves
    the tracker with none, and the next step says why: the tracker went on with the sequence it held before, as if
    the checkpoint had been of it. Initialised again, it tracks as a new tracker does."""
    frames, lm = three_streams
    saved = FaceTracker(CFG, model)
    saved.initialise(frames[:, 0], lm)
    checkpoint = saved.state_dict()
    assert len(checkpoint) == 0
    tracker = FaceTracker(CFG, model)
    tracker.initialise(frames[:2, 0], lm[:2])  # another sequence (two streams)
    tracker.load_state_dict(checkpoint)
    assert tracker.state is None
    with pytest.raises(RuntimeError, match=r"initialise.*a state_dict was loaded: it holds no tracked sequence"):
        tracker(frames[:, 1])
    with pytest.raises(RuntimeError, match="a state_dict was loaded"):
        tracker.select([0])
    parent = torch.nn.Sequential(tracker)
    tracker.initialise(frames[:, 0], lm)
    parent.load_state_dict(torch.nn.Sequential(FaceTracker(CFG, model)).state_dict())
    assert tracker.state is None
    tracker.initialise(frames[:, 0], lm)
    assert_same(saved(frames[:, 1]), tracker(frames[:, 1]))
    with_net = FaceTracker(CFG, model, detector=_NoFaces())  # a detector network's weights are the state_dict
    assert list(with_net.state_dict()) == ["detector.scale"]
    FaceTracker(CFG, model, detector=_NoFaces()).load_state_dict(with_net.state_dict())


def test_a_failed_load_state_dict_leaves_the_tracker_as_it_was(model, three_streams):
    """``load_state_dict`` that fails (an unexpected key, a missing or resized detector weight) raises torch's
    RuntimeError and changes nothing: the tracker forgot its sequence before torch raised (the next step said "a
    state_dict was loaded"), and torch had copied the detector weights that matched. The tracker tracks on exactly as
    a copy made before the failed load; ``strict=False`` still loads and forgets."""
    frames, lm = three_streams
    tracker = FaceTracker(CFG, model, detector=_NoFaces(), refine_first=None)
    tracker.initialise(frames[:, 0], lm)
    tracker(frames[:, 1])
    fork, state = copy.deepcopy(tracker), tracker.state
    good = {"detector.scale": torch.full((), 2.0)}
    for bad, message in (
        ({**good, "x": torch.zeros(1)}, 'Unexpected key.*"x"'),
        ({"detector.scale": torch.ones(2)}, "size mismatch for detector.scale"),
        ({}, 'Missing key.*"detector.scale"'),
    ):
        with pytest.raises(RuntimeError, match=message):
            tracker.load_state_dict(bad)
        assert tracker.state is state and float(tracker.detector.scale.detach()) == 1.0
    plain = FaceTracker(CFG, model, refine_first=None)  # (no weights at all)
    plain.initialise(frames[:, 0], lm)
    before = plain.state
    with pytest.raises(RuntimeError, match='Unexpected key.*"x"'):
        plain.load_state_dict({"x": torch.zeros(1)})
    assert plain.state is before
    assert_same(fork(frames[:, 2]), tracker(frames[:, 2]))
    tracker.load_state_dict({**good, "x": torch.zeros(1)}, strict=False)
    assert tracker.state is None and float(tracker.detector.scale.detach()) == 2.0


def test_load_hooks_run_once_on_the_tracker_and_a_failed_load_with_hooks_changes_nothing(model, three_streams):
    """Load hooks registered on the tracker or its detector ran twice per ``load_state_dict``, the first time on the
    check's stand-in (handed it as the module), even for a load the check then refused. They run once, on the
    tracker's own modules; a pre-hook that renames an old checkpoint's key (a load the check alone refuses) loads;
    a load with hooks that fails leaves the sequence and the detector's weights as they were. A parent's failed load
    still makes the tracker forget its sequence (torch tells no child that the load failed): a ``copy.copy`` kept
    before puts it back."""
    frames, lm = three_streams
    tracker = FaceTracker(CFG, model, detector=_NoFaces(), refine_first=None)
    tracker.initialise(frames[:, 0], lm)
    state, calls = tracker.state, []
    tracker.register_load_state_dict_post_hook(lambda module, keys: calls.append(module is tracker))
    tracker.detector.register_load_state_dict_post_hook(lambda module, keys: calls.append(module is tracker.detector))
    for bad, message in (({"detector.scale": torch.full((), 2.0), "x": torch.zeros(1)}, 'Unexpected key.*"x"'),
                         ({"detector.scale": torch.ones(2)}, "size mismatch")):  # fmt: skip
        with pytest.raises(RuntimeError, match=message):
            tracker.load_state_dict(bad)
        assert calls == [True, True] and tracker.state is state and float(tracker.detector.scale.detach()) == 1.0
        calls.clear()

    def renamed(state_dict, prefix, *args):  # (an old checkpoint's name of the weight)
        if prefix + "detector.gain" in state_dict:
            state_dict[prefix + "detector.scale"] = state_dict.pop(prefix + "detector.gain")

    tracker._register_load_state_dict_pre_hook(renamed)
    for assign in (False, True):
        with pytest.raises(RuntimeError, match='Unexpected key.*"x"'):
            tracker.load_state_dict({"detector.gain": torch.full((), 2.0), "x": torch.zeros(1)}, assign=assign)
        assert tracker.state is state and float(tracker.detector.scale.detach()) == 1.0
    calls.clear()
    tracker.load_state_dict({"detector.gain": torch.full((), 3.0)})
    assert calls == [True, True] and tracker.state is None and float(tracker.detector.scale.detach()) == 3.0
    tracker.initialise(frames[:, 0], lm)
    parent = torch.nn.Sequential(tracker, torch.nn.Linear(2, 2))
    kept, reference = copy.copy(tracker), copy.copy(tracker)
    with pytest.raises(RuntimeError, match='Missing key.*"1.bias"'):
        parent.load_state_dict({"0.detector.scale": torch.ones(()), "1.weight": torch.zeros(2, 2)})
    assert tracker.state is None and kept.state is not None
    parent[0] = kept
    assert_same(reference(frames[:, 1]), parent[0](frames[:, 1]))


class _LazyNoFaces(_NoFaces):
    """:class:`_NoFaces` holding a lazy layer, its weights made at the first call or load."""

    def __init__(self) -> None:
        super().__init__()
        self.head = torch.nn.LazyLinear(2)


def test_load_state_dict_materialises_a_lazy_detector_as_torch_does(model):
    """A detector network with lazy layers not yet called (``nn.LazyLinear``) loads a checkpoint's weights, as
    ``nn.Module.load_state_dict`` loads them: the check made before the load (on a stand-in of empty ``meta``
    tensors) refused it with a ValueError, "Attempted to use an uninitialized parameter", an uninitialised parameter
    having no meta twin."""
    source = _LazyNoFaces()
    source.head(torch.zeros(1, 3))  # (its weights made: (2, 3))
    saved = FaceTracker(CFG, model, detector=source, refine_first=None).state_dict()
    tracker = FaceTracker(CFG, model, detector=_LazyNoFaces(), refine_first=None)
    tracker.load_state_dict(saved)
    assert torch.equal(tracker.detector.head.weight, source.head.weight)


def test_a_saved_tracker_goes_on_as_the_original(model, three_streams):
    """The module's documented checkpoint, ``torch.save(tracker)`` mid-stream and ``torch.load(...,
    weights_only=False)``, continues exactly as the original does; the original is not changed by saving."""
    frames, lm = three_streams
    tracker = FaceTracker(CFG, model)
    tracker.initialise(frames[:, 0], lm)
    tracker(frames[:, 1])
    buffer = io.BytesIO()
    torch.save(tracker, buffer)
    buffer.seek(0)
    loaded = torch.load(buffer, weights_only=False)
    for t in range(2, 4):
        assert_same(tracker(frames[:, t]), loaded(frames[:, t]))


def test_step_runs_the_module_hooks(model, three_streams):
    """``tracker.step(frames)`` is ``tracker(frames)``: the forward pre-hooks and hooks registered on the tracker
    see it (``step = forward`` called forward directly, past them)."""
    frames, lm = three_streams
    tracker = FaceTracker(CFG, model)
    seen = []
    tracker.register_forward_pre_hook(lambda module, args: seen.append("pre"))
    tracker.register_forward_hook(lambda module, args, result: seen.append(int(result.status.shape[0])))
    tracker.initialise(frames[:, 0], lm)
    tracker.step(frames[:, 1])
    tracker(frames[:, 2])
    assert seen == ["pre", 3, "pre", 3]


def test_settings_set_after_construction_are_checked(model, three_streams):
    """``config``, ``model``, ``detector`` and ``refine_first`` assigned to a tracker are checked as the
    constructor's arguments are, and a refused one leaves the setting as it was: set later, a per-image dlib
    detector failed only at the first loss (with a shape error), a dict config at the next step."""
    from torchface.detect import _DlibDetector
    from torchface.tracker import LookaheadConfig

    frames, lm = three_streams
    tracker = FaceTracker(CFG, model)
    tracker.initialise(frames[:, 0], lm)
    per_image = _DlibDetector.__new__(_DlibDetector)  # (not loaded: dlib is an optional extra)
    for name, bad, message in (
        ("detector", per_image, r"torchface.detect.batched"),
        ("detector", "dlib", r"detector must be callable"),
        ("config", {"num_levels": 2}, r"config must be a TrackerConfig, got dict"),
        ("model", None, r"model must be a FaceModel, got NoneType"),
        ("refine_first", True, r"refine_first must be a LookaheadConfig or None, got bool"),
    ):
        before = getattr(tracker, name)
        with pytest.raises(TypeError, match=message):
            setattr(tracker, name, bad)
        assert getattr(tracker, name) is before, name
    tracker.detector, tracker.refine_first = _NoFaces(), LookaheadConfig(yaw_deg=12.0)  # good ones are taken
    assert isinstance(tracker.detector, _NoFaces) and tracker.refine_first.yaw_deg == 12.0
    assert bool(tracker(frames[:, 1]).success.all())


def test_a_tracker_adds_coarser_levels_for_a_large_face_unless_told_not_to(model):
    """FaceTracker took its config as given, so an HD video lost a fast motion that ``torchface track`` followed
    (frames 1 and 2 of this 1280x720 clip 23 and 28 degrees off with the default three levels). By default
    (``pyramid="auto"``) it now adds levels at initialise as the job does (pyramid_for_faces: four here), says so
    (``tracking_config``, the state's ``num_levels``) and follows the motion; ``pyramid="config"`` keeps the
    config's levels; a face under 255 pixels (the 640x360 copy, 190) keeps the config itself."""
    from dataclasses import replace

    from torchface.geometry.so3 import geodesic_angle_deg

    frames, lm, truth = sideways_clip(1280, 720)
    errors = {}
    for name, tracker in (("auto", FaceTracker(model=model, refine_first=None)),
                          ("config", FaceTracker(model=model, refine_first=None, pyramid="config"))):  # fmt: skip
        assert tracker.tracking_config is None
        tracker.initialise(frames[:1], lm[None])
        rotations = [tracker(frames[t : t + 1]).rotation for t in (1, 2)]
        errors[name] = geodesic_angle_deg(torch.cat(rotations).double(), truth[1:3])
        assert tracker.state.num_levels == tracker.tracking_config.num_levels == {"auto": 4, "config": 3}[name]
        assert tracker.config == TrackerConfig()  # the user's settings are not changed
    assert float(errors["auto"].max()) < 2.0, errors
    assert float(errors["config"].max()) > 10.0, errors  # (the default pyramid is lost: the motion is fast)
    # a config set mid-sequence keeps the levels added at initialise; reset forgets them
    tracker = FaceTracker(model=model, refine_first=None)
    tracker.initialise(frames[:1], lm[None])
    tracker.config = replace(TrackerConfig(), robust_c=5.0)
    assert bool(tracker(frames[1:2]).success.all()) and tracker.tracking_config.robust_c == 5.0
    assert tracker.tracking_config.num_levels == tracker.state.num_levels == 4
    tracker.reset()
    assert tracker.tracking_config is None
    # the 640x360 copy's face keeps the config (the same object: the same numbers)
    small, lm_small, _ = sideways_clip(640, 360, n=1)
    tracker.initialise(small, lm_small[None])
    assert tracker.tracking_config is tracker.config and tracker.state.num_levels == 3
    with pytest.raises(ValueError, match=r"pyramid must be one of \('auto', 'config'\), got 'none'"):
        FaceTracker(model=model, pyramid="none")
    with pytest.raises(TypeError, match=r"pyramid must be one of \('auto', 'config'\), got bool"):
        tracker.pyramid = True


def test_landmarks_of_weight_zero_do_not_choose_the_pyramid(model):
    """``weights`` 0 means "ignore" (the fit leaves such a point out), but ``pyramid="auto"`` measured the face with
    every finite landmark: two points of weight 0 in the corners of the 640x360 frame gave its 190-pixel face five
    pyramid levels instead of three. They are now left out, as NaN points are."""
    frames, lm, _ = sideways_clip(640, 360, n=1)
    stray = lm.clone()
    stray[0], stray[8] = torch.tensor([639.0, 359.0]), torch.tensor([0.0, 0.0])
    weights = torch.ones(1, 68)
    weights[0, [0, 8]] = 0.0
    tracker = FaceTracker(model=model, refine_first=None)
    tracker.initialise(frames, stray[None], weights=weights)
    assert tracker.state.num_levels == tracker.tracking_config.num_levels == 3
    assert tracker.tracking_config is tracker.config


def test_a_changed_copy_of_the_tracking_config_set_mid_sequence_is_taken_as_it_is(model):
    """``tracker.config = replace(tracker.tracking_config, ...)`` (the settings the sequence runs with, one changed)
    mid-sequence on an HD face: the levels initialise added were added to it once more (the state's 4 levels became
    a 5-level config) and every step failed ("the state holds templates for 4 pyramid levels, the config has
    num_levels = 5"). A config set mid-sequence now gets the levels the state holds beyond its own."""
    from dataclasses import replace

    frames, lm, _ = sideways_clip(1280, 720)
    tracker = FaceTracker(model=model, refine_first=None)
    tracker.initialise(frames[:1], lm[None])
    assert tracker.state.num_levels == 4
    tracker.config = replace(tracker.tracking_config, robust_c=5.0)
    assert tracker.tracking_config is tracker.config and tracker.tracking_config.num_levels == 4
    assert bool(tracker(frames[1:2]).success.all())
    tracker.config = replace(TrackerConfig(), robust_c=4.0)  # the user's 3 levels: the added one kept
    assert tracker.tracking_config.num_levels == 4 and tracker.tracking_config.robust_c == 4.0
    assert bool(tracker(frames[2:3]).success.all())
    # fewer levels than that: the one added is all "auto" adds (two were added, without a word)
    before = tracker.state
    tracker.config = replace(TrackerConfig(), num_levels=2, iterations=(6, 5))
    with pytest.raises(ValueError, match=r"4 pyramid levels, the config has num_levels = 2 and pyramid='auto' adds "
                                         r"the 1 coarser level\(s\) initialise added .* a config of 3 levels"):
        tracker(frames[3:4])
    assert tracker.state is before
    # where initialise added none, a config of other levels is refused as before
    tracker = FaceTracker(model=model, refine_first=None, pyramid="config")
    tracker.initialise(frames[:1], lm[None])
    tracker.config = replace(TrackerConfig(), num_levels=2, iterations=(6, 5))
    assert tracker.tracking_config is tracker.config
    with pytest.raises(ValueError, match="the state holds templates for 3 pyramid levels"):
        tracker(frames[1:2])


def test_a_config_of_fewer_levels_set_mid_sequence_is_refused_with_pyramid_auto_too(model, three_streams):
    """``pyramid="auto"`` re-adds to a config set mid-sequence the coarser levels initialise added for large faces,
    and no more: a 1-level config on a 2-level sequence (small faces: none added) was tracked with 2 levels, the
    coarsest's iterations repeated (``(4, 4)``), without a word. It is refused as with ``pyramid="config"``, and the
    sequence goes on as before once a config of its levels is set again."""
    from dataclasses import replace

    frames, lm = three_streams
    tracker = FaceTracker(CFG, model, refine_first=None)
    tracker.initialise(frames[:, 0], lm)
    fork = copy.deepcopy(tracker)
    assert tracker.state.num_levels == 2 and tracker.tracking_config is CFG
    tracker.config = replace(CFG, num_levels=1, iterations=(4,))
    assert tracker.tracking_config.num_levels == 1
    with pytest.raises(ValueError, match="the state holds templates for 2 pyramid levels, the config has num_levels = "
                                         "1"):  # fmt: skip
        tracker(frames[:, 1])
    tracker.config = replace(CFG, robust_c=CFG.robust_c)  # (another object, the same settings)
    assert_same(fork(frames[:, 1]), tracker(frames[:, 1]))


def test_settings_fixed_at_initialise_set_mid_sequence_warn_and_wait_for_the_next_initialise(model, turn_and_still):
    """``max_points``, ``template.normalised_size`` and ``template.dissimilarity`` are what the state's templates,
    mosaic slots, normalised faces and reference patches are made with (INITIALISE_SETTINGS). Changed mid-sequence,
    the first two were ignored without a word, and a changed ``num_patches`` failed at the next mosaic entry (a
    RuntimeError of tensor shapes, the 30 degree entry here). The assignment warns, naming them, and the sequence
    goes on exactly as with its own settings (``tracking_config`` holds them), until the next initialise takes the
    new ones; other settings take effect at once, without a warning."""
    import warnings
    from dataclasses import replace

    frames, lm = turn_and_still
    tracker = FaceTracker(CFG, model, refine_first=None)
    tracker.initialise(frames[:, 0], lm)
    fork = copy.deepcopy(tracker)
    tc = CFG.template
    changed = replace(CFG, max_points=300, template=replace(
        tc, normalised_size=96, dissimilarity=replace(tc.dissimilarity, num_patches=8)))  # fmt: skip
    with pytest.warns(UserWarning, match=r"changes max_points \(600 -> 300\), template.normalised_size \(64 -> 96\), "
                                         r"template.dissimilarity.num_patches \(16 -> 8\): settings the tracked "
                                         r"sequence keeps from its initialise"):  # fmt: skip
        tracker.config = changed
    run = tracker.tracking_config
    assert run.max_points == 600 and run.template.normalised_size == 64 and run.template.dissimilarity.num_patches == 16
    entries = []
    for t in [*range(1, frames.shape[1]), frames.shape[1] - 1]:  # (the last frame twice: its entry is aligned on)
        want, got = fork(frames[:, t]), tracker(frames[:, t])
        assert_same(want, got)
        entries.append(int(got.mosaic_entry[0]))
    assert entries[-1] > 0  # (a mosaic entry was added, and aligned against: made with the sequence's patches)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tracker.initialise(frames[:, 0], lm)  # the new settings from here
        assert tracker.tracking_config is tracker.config
        assert tracker.state.management.layout.size == 96 and tracker.state.templates[0].points.shape[1] == 300
        tracker.config = replace(changed, robust_c=5.0)  # (those settings as initialised: no warning)
        assert tracker.tracking_config.robust_c == 5.0
    # A config that cannot go on with the kept max_points (min_points above it) is refused when set, saying why, and
    # the tracker keeps its config (the next step failed, naming a max_points = 300 the caller never set there).
    before = tracker.config
    with pytest.raises(ValueError, match=r"^the config cannot go on with what the tracked sequence keeps from its "
                                         r"initialise \(max_points \(300 -> 1000\)\): min_points must be in \[0, "
                                         r"max_points = 300\]"):  # fmt: skip
        tracker.config = replace(changed, max_points=1000, min_points=700)
    assert tracker.config is before and tracker.tracking_config is before


# ----------------------------------------------------------------------------------------------- missing landmarks


def _assert_finite(result) -> None:
    """The result's values are finite (``dissimilarity`` too where measured: NaN without template management)."""
    for name in ("rotation", "axis_angle", "translation", "ypr_deg", "anim_coeffs", "expression", "facs",
                 "illumination", "confidence", "residual_confidence", "dissimilarity", "cost"):  # fmt: skip
        if name != "dissimilarity" or not bool(result.dissimilarity.isnan().all()):
            assert bool(torch.isfinite(getattr(result, name)).all()), name


@pytest.mark.parametrize("managed", [True, False])
def test_a_stream_without_landmarks_starts_failed_and_the_others_track_as_without_it(model, three_streams, managed):
    """One video of a batch whose first frame had no face found (all its landmarks NaN) made ``initialise`` raise
    "every sample needs at least 4 finite landmarks with positive weight" for the whole batch. That stream now
    starts FAILED (confidence 0) at a finite placeholder pose, which it keeps: LOST with template management, FAILED
    without (the bare step tracked the frame's middle from it, CONVERGED at confidence 0.99), with a finite
    normalised face; the other streams track as they do without it. A batch where no stream has landmarks starts
    every stream FAILED rather than raising."""
    from dataclasses import replace

    from torchface.normalise import NormalisedFace
    from torchface.template.management import TemplateConfig

    config = CFG if managed else replace(CFG, template=TemplateConfig(enabled=False))
    lost = 3 if managed else 2
    frames, lm = three_streams
    missing = lm.clone()
    missing[1] = float("nan")
    tracker, others = FaceTracker(config, model), FaceTracker(config, model)
    first, other = tracker.initialise(frames[:, 0], missing), others.initialise(frames[[0, 2], 0], lm[[0, 2]])
    assert first.status.tolist() == [0, 2, 0] and float(first.confidence[1]) == 0.0 and not bool(first.success[1])
    assert_same(first, other, [0, 2], atol=1e-4)
    _assert_finite(first)
    normalise = NormalisedFace(model)
    for t in range(1, frames.shape[1]):
        result, other = tracker(frames[:, t]), others(frames[[0, 2], t])
        assert_same(result, other, [0, 2], atol=1e-4)
        assert int(result.status[1]) == lost and float(result.confidence[1]) == 0.0 and not bool(result.success[1])
        assert torch.equal(result.translation[1], first.translation[1]), t  # the placeholder, held
        assert torch.equal(result.rotation[1], first.rotation[1]), t
        _assert_finite(result)
        face = normalise(frames[:, t], tracker.state)
        assert bool(torch.isfinite(face.image).all()) and bool(torch.isfinite(face.mask).all())
    none = FaceTracker(config, model)
    first = none.initialise(frames[:, 0], torch.full_like(lm, float("nan")))
    assert first.status.tolist() == [2, 2, 2]
    _assert_finite(first)
    result = none(frames[:, 1])
    assert result.status.tolist() == [lost] * 3 and float(result.confidence.abs().max()) == 0.0
    _assert_finite(result)


def _failed_start(cause: str, frames: torch.Tensor, lm: torch.Tensor, config: TrackerConfig):
    """One stream of ``frames (3, T, 3, H, W)`` and ``lm (3, 68, 2)`` made to fail at initialise by ``cause``: its
    index, and the frames, landmarks, landmark weights and config to start the batch with."""
    from dataclasses import replace

    frames, lm, weights = frames.clone(), lm.clone(), None
    bad = 0 if cause == "collinear" else 1
    b = lm[bad]
    if cause == "collinear":  # every point on one row: the face edge-on (FAILED with the fit of CFG)
        lm[bad] = torch.stack([b[:, 0], torch.full_like(b[:, 1], float(b[:, 1].mean()))], -1)
    elif cause == "mirrored":  # left and right swapped (tests/tracker/test_fit.py)
        m = list(range(68))
        pairs = [(i, 16 - i) for i in range(8)] + [(17 + i, 26 - i) for i in range(5)] + [(31, 35), (32, 34)]
        pairs += [(36, 45), (37, 44), (38, 43), (39, 42), (40, 47), (41, 46), (48, 54), (49, 53), (50, 52)]
        pairs += [(55, 59), (56, 58), (60, 64), (61, 63), (65, 67)]
        for i, j in pairs:
            m[i], m[j] = j, i
        lm[bad] = b[m]
    elif cause == "too_small":  # a face 15 px wide (min_face_width_px 20)
        centre = b.mean(0)
        lm[bad] = centre + 0.15 * (b - centre)
    elif cause == "black":  # a black first frame: too few template points
        frames[bad, 0] = 0.0
    elif cause == "stalled":  # weights swamped by the default fit's priors: the fit stopped at its start
        weights = torch.ones(3, 68)
        weights[bad] = 1e-20
        config = replace(config, fit=TrackerConfig().fit)
    return bad, frames, lm, weights, config


@pytest.mark.parametrize("managed", [True, False])
@pytest.mark.parametrize("cause", ["collinear", "mirrored", "too_small", "black", "stalled"])
def test_a_stream_whose_start_failed_is_never_reported_tracked(model, three_streams, cause, managed):
    """A stream whose initialisation FAILED (a fit that holds no pose, a face too small, too few template points)
    was tracked on from that start without template management: collinear landmarks FAILED at initialise, then
    CONVERGED at confidence 0.96-0.99 on the later frames, 620 mm away and drifting; a face too small CONVERGED at
    confidence 0; a stalled fit MAX_ITERATIONS (success). With template management such streams were LOST but
    tracked on, drifting from the failed start. Every later step is now FAILED (LOST with management) at confidence
    0, holding the start's finite estimate, until initialised again; the other streams track as they do without it."""
    from dataclasses import replace

    from torchface.template.management import TemplateConfig
    from torchface.tracker import TrackStatus

    frames, lm = three_streams
    config = CFG if managed else replace(CFG, template=TemplateConfig(enabled=False))
    bad, frames, lm, weights, config = _failed_start(cause, frames, lm, config)
    good = [b for b in range(3) if b != bad]
    lost = int(TrackStatus.LOST if managed else TrackStatus.FAILED)
    tracker, others = FaceTracker(config, model), FaceTracker(config, model)
    first = tracker.initialise(frames[:, 0], lm, weights=weights)
    others.initialise(frames[good, 0], lm[good], weights=None if weights is None else weights[good])
    assert int(first.status[bad]) == int(TrackStatus.FAILED) and float(first.confidence[bad]) == 0.0
    assert bool(first.success[good].all())
    assert int(first.num_points[bad]) == 0  # no template points: nothing to track from
    for t in range(1, 4):
        result, expected = tracker(frames[:, t]), others(frames[good, t])
        assert int(result.status[bad]) == lost and float(result.confidence[bad]) == 0.0, (t, result.status.tolist())
        assert not bool(result.success[bad])
        assert torch.equal(result.translation[bad], first.translation[bad]), t  # the start's estimate, held
        assert torch.equal(result.rotation[bad], first.rotation[bad]), t
        assert bool(torch.isfinite(result.translation).all()) and bool(torch.isfinite(result.rotation).all())
        assert_same(result, expected, good, atol=1e-4)
    # Initialised again (from good landmarks), the stream tracks.
    tracker.initialise(frames[:, 3], three_streams[1])
    assert bool(tracker(frames[:, 4]).success.all())


# ----------------------------------------------------------------------------------------------- detector


@pytest.mark.parametrize(
    "answer, error, message",
    [
        (lambda lm: lm.numpy(), TypeError, r"must return a \(1, 68, 2\) tensor of pixel landmarks .*got ndarray"),
        (lambda lm: [lm[0]], TypeError, r"must return a \(1, 68, 2\) tensor of pixel landmarks .*got list"),
        (lambda lm: lm > 0, TypeError, r"must return real pixel coordinates .*got torch.bool"),
        (lambda lm: lm[0], ValueError, r"must return \(1, 68, 2\) landmarks \(NaN rows: no face\), got \(68, 2\)"),
    ],
    ids=["numpy", "list", "bool", "unbatched"],
)
def test_a_detector_that_breaks_its_contract_is_named(model, three_streams, answer, error, message):
    """A detector must answer ``(B', K, 2)`` pixel landmarks. Bool ones were fitted as pixels 0 and 1 (a fit that
    failed, the stream silently left LOST); a numpy array or a list said "must return (1, 68, 2) landmarks ...,
    got ndarray", as if its shape were wrong."""
    frames, lm = three_streams
    missing = lm[:1].clone()
    missing[0] = float("nan")  # the stream starts FAILED: the detector is asked at its first recovery attempt
    tracker = FaceTracker(CFG, model, detector=lambda batch: answer(lm[:1].expand(batch.shape[0], -1, -1)))
    tracker.initialise(frames[:1, 0], missing)
    with pytest.raises(error, match=message):
        for t in range(1, frames.shape[1]):
            tracker(frames[:1, t])


class _Counted:
    """A detector that counts its calls and answers ``answer(frames)``."""

    def __init__(self, answer) -> None:
        self.answer, self.calls = answer, 0

    def __call__(self, frames: torch.Tensor) -> object:
        self.calls += 1
        return self.answer(frames)


def _two_arguments(frames, model):
    return frames


@pytest.mark.parametrize(
    "bad, message",
    [
        (_two_arguments, r"but _two_arguments\(frames, model\) cannot be \(missing a required argument: 'model'\): "
                         r"give its other arguments with functools.partial"),
        (lambda: None, r"but <lambda>\(\) cannot be \(too many positional arguments\)"),
        (lambda frames, *, k: None, r"<lambda>\(frames, \*, k\) cannot be"),
        (_NoFaces, r"got the class _NoFaces: an instance of it, detector=_NoFaces\(\.\.\.\)"),
    ],
    ids=["two-arguments", "none", "keyword-only", "class"],
)
def test_a_detector_that_cannot_take_the_frames_is_refused_at_construction(model, bad, message):
    """A detector is first called at the first loss, perhaps far into a long video: one whose signature cannot take
    the frames alone (the call ``detector(frames)``) failed there. The constructor, and an assignment, now refuse it
    from its signature, without calling it; detectors that can take the frames are taken, uncalled."""
    with pytest.raises(TypeError, match=message):
        FaceTracker(CFG, model, detector=bad)
    tracker = FaceTracker(CFG, model)
    with pytest.raises(TypeError, match=message):
        tracker.detector = bad
    assert tracker.detector is None
    import functools

    from torchface.detect import batched

    counted = _Counted(lambda frames: None)
    good = [counted, _NoFaces(), functools.partial(_two_arguments, model=model), lambda *frames: None,
            lambda frames, near=None: None, batched(lambda image: None), None]  # fmt: skip
    for detector in good:
        assert FaceTracker(CFG, model, detector=detector).detector is detector
    assert counted.calls == 0


class _Detectors:
    """Holders of detectors as methods: bound, of the class, static."""

    def bound(self, frames: torch.Tensor) -> torch.Tensor:
        return torch.full((frames.shape[0], 68, 2), float("nan"))

    @classmethod
    def of_class(cls, frames: torch.Tensor) -> torch.Tensor:
        return torch.full((frames.shape[0], 68, 2), float("nan"))

    @staticmethod
    def static(frames: torch.Tensor) -> torch.Tensor:
        return torch.full((frames.shape[0], 68, 2), float("nan"))


class _StarArgs:
    """A callable instance taking ``*args``."""

    def __call__(self, *args: torch.Tensor) -> torch.Tensor:
        return torch.full((args[0].shape[0], 68, 2), float("nan"))


def test_the_detector_signature_check_takes_every_callable_that_can_take_the_frames(model):
    """The constructor's signature check (check_detector_callable) reads a callable's signature: bound, class and
    static methods, an instance whose __call__ takes *args, a functools.partial of a two-argument function with its
    first argument bound, a torch.jit.script function and a callable implemented in C (no signature to read) can
    all be called as detector(frames), and are taken, uncalled; check_detector calls the Python ones once."""
    import functools

    from torchface.tracker import check_detector

    def two(first, frames):
        return torch.full((frames.shape[0], 68, 2), float("nan"))

    @torch.jit.script
    def scripted(frames: torch.Tensor) -> torch.Tensor:
        return torch.full([frames.shape[0], 68, 2], float("nan"))

    holder = _Detectors()
    python = [holder.bound, _Detectors.of_class, _Detectors.static, _StarArgs(), functools.partial(two, None), scripted]
    for detector in [*python, torch.sigmoid, torch.nn.Sigmoid()]:
        assert FaceTracker(CFG, model, detector=detector).detector is detector
    frames = torch.rand(2, 3, 48, 64)
    for detector in python:
        assert bool(check_detector(detector, frames).isnan().all())


_K_ANSWERS = [
    (lambda lm: lm.numpy(), TypeError, r"must return a \(3, 68, 2\) tensor .*got ndarray \(a NumPy array: "
                                       r"torch.from_numpy\(landmarks\)\)"),
    (lambda lm: list(lm), TypeError, r"got list .*torch.stack\(\[torch.as_tensor\(x\) for x in answers\]\)"),
    (lambda lm: None, TypeError, r"got NoneType \(one image's answer\? .*torchface.detect.batched\(detector\)\)"),
    (lambda lm: lm > 0, TypeError, r"must return real pixel coordinates .*got torch.bool"),
    (lambda lm: lm[0], ValueError, r"must return \(3, 68, 2\) landmarks \(NaN rows: no face\), got \(68, 2\) "
                                   r"\(one image's answer\?"),
    (lambda lm: lm[:, :5], ValueError, r"must return \(3, 68, 2\) landmarks .*got \(3, 5, 2\)"),
]


@pytest.mark.parametrize("answer, error, message", _K_ANSWERS, ids=["numpy", "list", "none", "bool", "unbatched", "k"])
def test_check_detector_finds_a_wrong_answer_before_any_loss(model, three_streams, answer, error, message):
    """``FaceTracker.check_detector(frames)`` (and the functional ``check_detector``) ask the detector once, as a
    restart does, and refuse its answer with the message a restart gives (which names the fix), before anything is
    tracked: without it a wrong answer was found at the first loss. The tracker's state is left as it was."""
    from torchface.tracker import check_detector

    frames, lm = three_streams
    detector = _Counted(lambda batch: answer(lm[: batch.shape[0]].clone()))
    tracker = FaceTracker(CFG, model, detector=detector)
    with pytest.raises(error, match=message):
        tracker.check_detector(frames[:, 0])
    with pytest.raises(error, match=message):
        check_detector(detector, frames[:, 0], model)
    assert detector.calls == 2 and tracker.state is None


def test_check_detector_passes_a_good_detector_and_changes_nothing_of_the_tracker(model, three_streams):
    """A good detector's answer comes back as a restart takes it, ``(B, K, 2)``: NaN rows for no face (a per-image
    detector's None, through ``batched``), a normalised stream made no face with the restart's warning. Asked about
    the gray or RGB frames the tracker hands it. Checked mid-stream, the tracker tracks on exactly as an untouched
    copy. A detector's exception comes through as it is; a tracker without one says so."""
    from torchface.detect import batched
    from torchface.tracker import check_detector

    frames, lm = three_streams
    seen = []
    tracker = FaceTracker(CFG, model, detector=lambda batch: seen.append(batch) or lm[: batch.shape[0]].clone())
    tracker.initialise(frames[:, 0], lm)
    twin = copy.deepcopy(tracker)
    state = tracker.state
    out = tracker.check_detector(frames[:, 1, :1])  # (gray frames: RGB for the detector, as at a restart)
    assert torch.equal(out, lm) and not out.is_inference()
    # (a copy of them in inference mode, as a restart hands them)
    assert seen[0].shape == (3, 3, H, W) and seen[0].is_inference() and tracker.state is state
    assert_same(twin(frames[:, 1]), tracker(frames[:, 1]))
    no_face = check_detector(batched(lambda image: None), frames[:2, 0])
    assert no_face.shape == (2, 68, 2) and bool(no_face.isnan().all())
    normalised = lm.clone()
    normalised[1] /= torch.tensor([W, H])
    with pytest.warns(RuntimeWarning, match=r"normalised coordinates .*NORMALISED_LANDMARKS"):
        out = check_detector(lambda batch: normalised, frames[:, 0], model)
    assert bool(out[1].isnan().all()) and torch.equal(out[[0, 2]], lm[[0, 2]])

    def broken(batch):
        raise RuntimeError("the network's weights are not loaded")

    with pytest.raises(RuntimeError, match="weights are not loaded"):
        FaceTracker(CFG, model, detector=broken).check_detector(frames[:, 0])
    with pytest.raises(ValueError, match=r"this tracker has no detector to check \(detector=None"):
        FaceTracker(CFG, model).check_detector(frames[:, 0])


def test_a_face_upside_down_in_the_frame_starts_and_tracks(model):
    """A face rolled 135-225 degrees in the frame (a camera mounted upside down, a person lying down) failed its start:
    the landmark fit began frontal, without roll, and FAILED (42 px RMS at 180). It now starts from the landmarks' roll
    and tracks: every step succeeds within a few degrees of the truth."""
    from torchface.geometry.so3 import geodesic_angle_deg

    s = [i / 3 for i in range(4)]
    streams = [render(f"roll{r}", [[6 * u, -3 * u, r + 4 * u] for u in s], [[5 * u, 0.0, 450.0] for u in s], seed=r)
               for r in (135, 180, 225)]  # fmt: skip
    frames, lm = torch.stack([f for f, _ in streams]), torch.stack([m for _, m in streams])
    truth = euler_to_matrix(torch.tensor([[[6 * u, -3 * u, r + 4 * u] for u in s] for r in (135, 180, 225)], dtype=D))
    tracker = FaceTracker(CFG, model)
    results = [tracker.initialise(frames[:, 0], lm)] + [tracker(frames[:, t]) for t in range(1, len(s))]
    for t, result in enumerate(results):
        assert bool(result.success.all()), (t, result.status.tolist())
        assert float(geodesic_angle_deg(result.rotation.double(), truth[:, t]).max()) < 3.0, t
