"""``torchface._checkpoint``: a tracker state as plain data (``torch.load(weights_only=True)``) and states of some
streams joined back into one batch, the inverse of ``select``, bit for bit."""

from __future__ import annotations

import io
import warnings
from dataclasses import dataclass, replace

import pytest
import torch

from torchface import _checkpoint
from torchface.geometry.camera import Intrinsics
from torchface.model.candide import load_candide3
from torchface.synth.io import read_video
from torchface.synth.scenarios import make_scenario
from torchface.synth.sequence import load_ground_truth, write_sequence
from torchface.tracker import TrackerConfig, initialise_managed, managed_step
from torchface.tracker.lookahead import LookaheadConfig
from torchface.tracker.smoothing import SmoothingConfig, SmoothingState, one_euro_step

T = 8  # frames tracked: the online start (max_frames 4) has ended, the mosaic holds entries


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A 3-stream state after T frames of ``pose_sweep`` (160x120), the streams' clips shifted by 0, 2 and 4
    frames (so that their states differ), the model, config and the next frames."""
    files = write_sequence(make_scenario("pose_sweep", 60, 160, 120), tmp_path_factory.mktemp("sweep"))
    gt = load_ground_truth(files.ground_truth)
    frames = read_video(files.video, max_frames=T + 5)
    clips = torch.stack([frames[o : o + T + 1] for o in (0, 2, 4)])  # (3, T + 1, 3, H, W)
    lm = torch.stack([gt.landmarks_px[o] for o in (0, 2, 4)])
    model, config = load_candide3(), TrackerConfig()
    state, _ = initialise_managed(model, config, clips[:, 0], lm, Intrinsics.default(160, 120),
                                  refine_first=LookaheadConfig(max_frames=4))  # fmt: skip
    for i in range(1, T):
        state, _ = managed_step(model, config, state, clips[:, i])
    return model, config, state, clips[:, T]


def test_join_of_selected_streams_is_the_state_bit_for_bit(tracked):
    """``join([s.select([0]), s.select([1, 2])])`` is ``s`` (every tensor, templates and mosaic included, bit for
    bit; the parameters still held twice, by the state and the management's cached angles) and the next step from
    it gives the same state and result as from ``s``. Streams joined in another order are the select of that
    order."""
    model, config, state, nxt = tracked
    assert state.management is not None and state.management.mosaic is not None
    assert state.management.first is None and bool((state.management.mosaic.used.sum(1) > 1).any())
    joined = _checkpoint.join([state.select([0]), state.select([1, 2])])
    assert _checkpoint.same_tree(joined, state)
    ypr = joined.management.params_ypr
    assert (ypr is not None and ypr[0] is joined.params) == (state.management.params_ypr is not None
                                                             and state.management.params_ypr[0] is state.params)
    assert _checkpoint.same_tree(_checkpoint.join([state.select([2]), state.select([0])]), state.select([2, 0]))
    a, ra = managed_step(model, config, state.select([0, 1, 2]), nxt)
    b, rb = managed_step(model, config, joined, nxt)
    assert _checkpoint.same_tree(a, b)
    assert torch.equal(ra.rotation, rb.rotation) and torch.equal(ra.confidence, rb.confidence)


def test_a_different_state_is_not_the_same_tree(tracked):
    """``same_tree`` tells states apart (so that the test above can fail): another stream's state, or one value
    changed in the mosaic."""
    _, _, state, _ = tracked
    assert not _checkpoint.same_tree(state.select([0]), state.select([1]))
    ms = state.management
    level = ms.mosaic.levels[0]
    changed = level.bary.clone()
    changed.view(-1)[0] += 1e-6
    other = replace(level, bary=changed)
    assert not _checkpoint.same_tree(level, other)


def test_plain_data_round_trips_through_torch_save_weights_only(tracked):
    """``to_plain`` then ``torch.save`` / ``torch.load(weights_only=True)`` then ``from_plain`` gives the state back,
    bit for bit, and one of a smoother's pose filter."""
    _, _, state, _ = tracked
    part = state.select([1])
    buffer = io.BytesIO()
    torch.save(_checkpoint.to_plain(part), buffer)
    buffer.seek(0)
    back = _checkpoint.from_plain(torch.load(buffer, weights_only=True))
    assert _checkpoint.same_tree(back, part)
    config = SmoothingConfig()
    x0, x1 = torch.zeros(2, 3, dtype=torch.float64), torch.ones(2, 3, dtype=torch.float64)
    _, trans = one_euro_step(x0, None, 0.04, config.translation)
    _, trans = one_euro_step(x1, trans, 0.04, config.translation)
    smooth = SmoothingState(None, trans, None, torch.tensor([0.04, 0.04], dtype=torch.float64))
    assert isinstance(smooth, SmoothingState)
    buffer = io.BytesIO()
    torch.save(_checkpoint.to_plain(smooth), buffer)
    buffer.seek(0)
    again = _checkpoint.from_plain(torch.load(buffer, weights_only=True))
    assert _checkpoint.same_tree(again, smooth)
    assert _checkpoint.same_tree(_checkpoint.join([smooth.select([0]), smooth.select([1])]), smooth)


def test_states_that_do_not_go_together_are_refused(tracked):
    """Parts of other kinds, or whose shared values differ (another intrinsics), are refused with a ValueError; so
    is plain data naming a class that is not torchface's."""
    _, _, state, _ = tracked
    with pytest.raises(ValueError, match="other kinds"):
        _checkpoint.join([state.select([0]), state.select([1]).management])
    moved = replace(state.select([1]), intrinsics=Intrinsics.default(320, 240))
    with pytest.raises(ValueError, match="shared value differs"):
        _checkpoint.join([state.select([0]), moved])
    plain = _checkpoint.to_plain(state.select([0]))
    plain["dataclass"] = "subprocess:Popen"
    with pytest.raises(ValueError, match="not a torchface class"):
        _checkpoint.from_plain(plain)


def test_a_state_after_a_restart_that_failed_a_stream_round_trips(tmp_path):
    """Two streams without first landmarks, restarted from a detector that answers pixels for one and normalised
    [0, 1] points for the other (a restart's ``start_failure`` NORMALISED_LANDMARKS: that stream stays LOST, session
    53's h2): after the restarts, each stream's state written as plain data (``torch.save``, ``weights_only``), read
    back and joined is the batch's state bit for bit, and the next frames from it (restarts tried again) give the
    same states and results as from the state itself, ``start_failure`` included."""
    import sys
    from pathlib import Path

    from torchface.tracker import FitConfig, StartFailure, TrackStatus

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from _helpers import sideways_clip

    W, H = 160, 120
    config = TrackerConfig(num_levels=2, max_points=400, iterations=(6, 4),
                           fit=FitConfig(shape_prior_precision=0.0, held_shape_units=()))  # fmt: skip
    frames, lm, _ = sideways_clip(W, H, 3)
    mark = 0.123  # (pixel (0, 0, 0) of the frames answered in normalised coordinates)
    marked = frames.clone()
    marked[:, 0, 0, 0] = mark
    batch = torch.stack([frames, marked], 1)  # (T, 2, 3, H, W)

    def detect(images: torch.Tensor) -> torch.Tensor:
        return torch.stack([(lm + 0.5) / torch.tensor([float(W), float(H)]) if abs(float(b[0, 0, 0]) - mark) < 1e-6
                            else lm.clone() for b in images])  # fmt: skip

    model = load_candide3()
    state, _ = initialise_managed(model, config, batch[0], torch.full((2, 68, 2), float("nan")),
                                  Intrinsics.default(W, H))  # fmt: skip
    failures = []
    with pytest.warns(RuntimeWarning, match="normalised coordinates"):
        for t in (1, 2) * 5:  # (restarts tried at the 5th and 10th frames)
            state, result = managed_step(model, config, state, batch[t], detect)
            if result.start_failure is not None:
                failures.append(result.start_failure.tolist())
    assert failures and failures[-1][1] == int(StartFailure.NORMALISED_LANDMARKS), failures
    assert int(result.status[1]) == int(TrackStatus.LOST) and int(result.status[0]) != int(TrackStatus.LOST)

    parts = []
    for k in range(2):
        path = tmp_path / f"{k}.pt"
        torch.save(_checkpoint.to_plain(state.select([k])), path)
        parts.append(_checkpoint.from_plain(torch.load(path, weights_only=True)))
    joined = _checkpoint.join(parts)
    # (the state's mosaic's ``claimed`` bookkeeping None after the restart, the join's made again by select: not
    # compared, field(compare=False); same_tree compared it, and told these states apart)
    assert state.management.mosaic.claimed is None and joined.management.mosaic.claimed is not None
    assert _checkpoint.same_tree(joined, state)
    a, b = state, joined
    tried = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (the detector's normalised points, said above)
        for t in (1, 2) * 5:  # (a restart tried again)
            a, ra = managed_step(model, config, a, batch[t], detect)
            b, rb = managed_step(model, config, b, batch[t], detect)
            assert _checkpoint.same_tree(a, b)
            assert torch.equal(ra.status, rb.status) and torch.equal(ra.rotation, rb.rotation)
            assert (ra.start_failure is None) == (rb.start_failure is None)
            if ra.start_failure is not None:
                tried += 1
                assert torch.equal(ra.start_failure, rb.start_failure)
                assert int(ra.start_failure[1]) == int(StartFailure.NORMALISED_LANDMARKS)
    assert tried > 0


def test_plain_data_naming_another_modules_class_through_torchface_is_refused(tracked):
    """A class of another module reached through a torchface module's names (``torchface.job:os.stat_result``, a
    named tuple of the standard library) is refused as not torchface's, as the module docstring says: it was built
    (the name's module was checked, not the class's)."""
    plain = {"tuple": "torchface.job:os.stat_result", "items": list(range(10))}
    with pytest.raises(ValueError, match="not a torchface class"):
        _checkpoint.from_plain(plain)
    _, _, state, _ = tracked
    assert _checkpoint.same_tree(_checkpoint.from_plain(_checkpoint.to_plain(state.select([0]))), state.select([0]))


@dataclass(frozen=True)
class _Columns:
    """A state whose ``other`` ``(3, B)`` is per stream along its second dimension (``params`` ``(B, 2)``)."""

    params: torch.Tensor
    other: torch.Tensor

    def select(self, index: list[int]) -> "_Columns":
        return _Columns(self.params[index], self.other[:, index])


def test_a_tensor_per_stream_along_another_dimension_is_refused():
    """``join`` concatenates per-stream tensors along their first dimension: one whose streams lie along another
    is refused (ValueError) rather than joined wrong (``(3, 1)`` and ``(3, 1)`` made ``(6, 1)``)."""
    state = _Columns(torch.arange(4.0).reshape(2, 2), torch.arange(6.0).reshape(3, 2))
    with pytest.raises(ValueError, match="per stream along another dimension"):
        _checkpoint.join([state.select([0]), state.select([1])])
