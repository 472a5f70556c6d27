"""Why a stream's start failed (``TrackResult.start_failure``, :class:`~torchface.tracker.StartFailure`), and
``TrackResult.to`` / ``.cpu``. Session 52's reviewers: a user with B streams learnt from ``initialise`` that some
failed (status FAILED) but not which reason, and a result could not be moved as a tensor can. A small rendered clip
(tests/_helpers.py's, 160x120).
"""

from __future__ import annotations

import ast
import re
import sys
from dataclasses import fields, replace
from pathlib import Path

import pytest
import torch

from torchface.geometry.camera import Intrinsics
from torchface.template.management import TemplateConfig
from torchface.tracker import (
    FaceTracker, FitConfig, LandmarkFit, StartFailure, TrackerConfig, TrackResult, TrackStatus, fit_landmarks,
    initialise,
)  # fmt: skip

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _helpers import sideways_clip  # noqa: E402

W, H = 160, 120
CFG = TrackerConfig(
    num_levels=2, max_points=400, iterations=(6, 4), fit=FitConfig(shape_prior_precision=0.0, held_shape_units=()),
)
CONVERGED, FAILED = int(TrackStatus.CONVERGED), int(TrackStatus.FAILED)


@pytest.fixture(scope="module")
def clip():
    """``frames (3, 3, H, W)`` and the first frame's landmarks ``(68, 2)`` in pixels."""
    frames, landmarks, _ = sideways_clip(W, H, 3)
    return frames, landmarks


def _shrunk(lm: torch.Tensor, scale: float) -> torch.Tensor:
    """``lm`` ``(68, 2)`` scaled by ``scale`` about their centroid."""
    c = lm.mean(0)
    return (lm - c) * scale + c


def _mirrored(lm: torch.Tensor) -> torch.Tensor:
    """``lm`` ``(68, 2)`` mirrored left-right about their mean x, the jaw line's points in their own order."""
    return torch.stack([2 * lm[:, 0].mean() - lm[:, 0], lm[:, 1]], -1)[
        torch.tensor([16 - i for i in range(17)] + list(range(17, 68)))]


# (what makes the second stream's start fail: its frame, its landmarks) -> the reason
KINDS = {
    "no-face-found": (lambda f: f, lambda lm: torch.full_like(lm, float("nan")), StartFailure.NO_LANDMARKS),
    "three-landmarks": (lambda f: f, lambda lm: lm.where(torch.arange(68)[:, None] < 3, float("nan")),
                        StartFailure.NO_LANDMARKS),
    "normalised-landmarks": (lambda f: f, lambda lm: (lm + 0.5) / torch.tensor([float(W), float(H)]),
                             StartFailure.NORMALISED_LANDMARKS),
    "landmarks-at-one-point": (lambda f: f, lambda lm: torch.full_like(lm, 50.0), StartFailure.NO_POSE),
    "mirrored-landmarks": (lambda f: f, lambda lm: _mirrored(lm), StartFailure.NO_POSE),
    "face-too-small": (lambda f: f, lambda lm: _shrunk(lm, 0.1), StartFailure.FACE_TOO_SMALL),
    "black-frame": (lambda f: torch.zeros_like(f), lambda lm: lm, StartFailure.TOO_FEW_POINTS),
    "nan-frame": (lambda f: torch.full_like(f, float("nan")), lambda lm: lm, StartFailure.TOO_FEW_POINTS),
    "face-mostly-outside": (lambda f: f, lambda lm: lm + torch.tensor([120.0, 0.0]), StartFailure.OUTSIDE_FRAME),
}


@pytest.mark.parametrize("kind", list(KINDS))
def test_a_failed_start_says_which_stream_and_why(clip, kind):
    """A batch of one good stream and one whose start fails: the failed one is FAILED with its reason (code and
    words), the good one CONVERGED with NONE, and the good stream's first result and next step are those it has
    tracked alone. Either order in the batch."""
    frames, lm = clip
    make_frame, make_landmarks, reason = KINDS[kind]
    bad_frame, bad_lm = make_frame(frames[0]), make_landmarks(lm)
    alone = FaceTracker(CFG)
    first_alone = alone.initialise(frames[:1], lm[None])
    next_alone = alone(frames[1:2])
    assert first_alone.start_failure.tolist() == [0] and first_alone.start_failure_reasons == (None,)
    for good in (0, 1):
        pair = [frames[0], bad_frame] if good == 0 else [bad_frame, frames[0]]
        pair_lm = [lm, bad_lm] if good == 0 else [bad_lm, lm]
        tracker = FaceTracker(CFG)
        first = tracker.initialise(torch.stack(pair), torch.stack(pair_lm))
        bad = 1 - good
        assert first.status[good] == CONVERGED and first.status[bad] == FAILED
        assert first.start_failure.dtype == torch.int64
        assert first.start_failure.tolist()[bad] == int(reason) and first.start_failure.tolist()[good] == 0
        assert first.start_failure_reasons[good] is None
        assert first.start_failure_reasons[bad] == reason.reason and isinstance(reason.reason, str)
        for name in ("rotation", "translation", "anim_coeffs", "confidence", "num_points"):
            assert torch.equal(getattr(first, name)[good], getattr(first_alone, name)[0]), name
        step = tracker(torch.stack([frames[1], make_frame(frames[1])][:: 1 if good == 0 else -1]))
        assert step.start_failure is None  # (no start tried at this step)
        assert step.start_failure_reasons == (None, None)
        assert int(step.status[good]) == int(next_alone.status[0]) and not bool(step.success[bad])
        torch.testing.assert_close(step.rotation[good], next_alone.rotation[0], rtol=0, atol=1e-6)
        torch.testing.assert_close(step.translation[good], next_alone.translation[0], rtol=0, atol=1e-4)


def test_landmarks_far_outside_the_frame_say_so(clip):
    """Landmarks 1000 px off the frame, and mirrored ones there: the fit fails them for a reason of its own (it said
    FACE_TOO_SMALL and NO_POSE), but the reason is that the face lies outside the frame (OUTSIDE_FRAME); the stream
    beside them starts. (A start that succeeds is untouched: the outside check only renames a failure.)"""
    frames, lm = clip
    far = torch.tensor([1000.0, 0.0])
    lms = torch.stack([lm, lm + far, _mirrored(lm) + far])
    first = FaceTracker(CFG).initialise(frames[:1].expand(3, -1, -1, -1), lms)
    assert first.status.tolist() == [CONVERGED, FAILED, FAILED]
    assert first.start_failure.tolist() == [0, int(StartFailure.OUTSIDE_FRAME), int(StartFailure.OUTSIDE_FRAME)]


def test_a_start_whose_normalised_face_shows_too_few_patches_says_so(clip):
    """Collinear landmarks (every point on one row), with the fit's checks that fail them off
    (``max_facing_deg=None``, ``max_rotation_std_deg=None``): the fit converges edge-on (pitch 87 degrees), and
    template management fails the start, its normalised face showing too few fiducial patches (NO_PATCHES); the
    good stream beside it is as alone."""
    frames, lm = clip
    config = replace(CFG, fit=FitConfig(max_facing_deg=None, max_rotation_std_deg=None))
    line = torch.stack([lm[:, 0], torch.full_like(lm[:, 1], float(lm[:, 1].mean()))], -1)
    first = FaceTracker(config).initialise(frames[:1].expand(2, -1, -1, -1), torch.stack([lm, line]))
    alone = FaceTracker(config).initialise(frames[:1], lm[None])
    assert first.status.tolist() == [CONVERGED, FAILED]
    assert first.start_failure.tolist() == [0, int(StartFailure.NO_PATCHES)]
    assert "fiducial patches" in first.start_failure_reasons[1]
    for name in ("rotation", "translation", "confidence", "num_points"):
        assert torch.equal(getattr(first, name)[0], getattr(alone, name)[0]), name


#: A detector's answer per stream at a restart (its frame marked by the value of pixel (0, 0, 0), as
#: test_user_inputs' mixed detector): the landmarks (of the first frame's ``lm``) and the restart's reason.
RESTART_KINDS = {
    0.11: (lambda lm: lm, StartFailure.NONE),
    0.12: (KINDS["no-face-found"][1], StartFailure.NO_LANDMARKS),
    0.13: (KINDS["mirrored-landmarks"][1], StartFailure.NO_POSE),
    0.14: (KINDS["face-too-small"][1], StartFailure.FACE_TOO_SMALL),
    0.15: (KINDS["face-mostly-outside"][1], StartFailure.OUTSIDE_FRAME),
}


def _restart_reasons(frames: torch.Tensor, lm: torch.Tensor, marks: list[float]) -> list[tuple[list[int], list[int]]]:
    """``(start_failure, status)`` of each step of ``frames`` 1, 2, 1, 2, ... (10 steps) that tried a restart, for
    streams whose first landmarks are missing (each restarts from the detector) and whose frames carry ``marks``."""
    batch = frames[:, None].repeat(1, len(marks), 1, 1, 1)
    for j, mark in enumerate(marks):
        batch[:, j, 0, 0, 0] = mark

    def detect(images: torch.Tensor) -> torch.Tensor:
        return torch.stack([RESTART_KINDS[round(float(b[0, 0, 0]), 2)][0](lm).clone() for b in images])

    tracker = FaceTracker(CFG, detector=detect)
    tracker.initialise(batch[0], torch.full((len(marks), 68, 2), float("nan")))
    tried = []
    for t in (1, 2) * 5:
        result = tracker(batch[t])
        if result.start_failure is not None:
            tried.append((result.start_failure.tolist(), result.status.tolist()))
    return tried


def test_a_failed_restart_gives_each_stream_its_own_reason(clip):
    """A detector's restart of five streams, one it starts and four it cannot (no face found; landmarks without a
    pose, a face too small, mostly outside the frame: the initialisation of the found streams fails them): each
    stream's ``start_failure`` is its own reason at every step that tried a restart (NONE for the started one, and
    for it at the later restart too, which is not its), the failed streams stay LOST, and each reason is the one
    that stream gets restarted alone (batch-consistent)."""
    frames, lm = clip
    marks = list(RESTART_KINDS)
    tried = _restart_reasons(frames, lm, marks)
    assert len(tried) == 2  # (the restarts at the recovery attempts: the 5th and 10th steps)
    expected = [int(RESTART_KINDS[m][1]) for m in marks]
    for codes, status in tried:
        assert codes == expected
        assert [s == int(TrackStatus.LOST) for s in status] == [c != 0 for c in expected]
    for mark in marks[1:]:
        alone = _restart_reasons(frames, lm, [mark])
        assert [codes for codes, _ in alone] == [[int(RESTART_KINDS[mark][1])]] * 2, mark


def test_functional_initialise_gives_the_reasons_too(clip):
    """The bare :func:`~torchface.tracker.initialise` (no template management) reports the same codes; a face mostly
    outside the frame fails there only for want of template points (TOO_FEW_POINTS), management's OUTSIDE_FRAME."""
    frames, lm = clip
    model = FaceTracker(CFG).model
    config = TrackerConfig(num_levels=2, max_points=400, iterations=(6, 4), template=TemplateConfig(enabled=False))
    lms = torch.stack([lm, torch.full_like(lm, float("nan")), _shrunk(lm, 0.1), lm + torch.tensor([120.0, 0.0])])
    _, first = initialise(model, config, frames[:1].expand(4, -1, -1, -1), lms, Intrinsics.default(W, H))
    assert first.status.tolist() == [CONVERGED, FAILED, FAILED, FAILED]
    assert first.start_failure.tolist() == [0, int(StartFailure.NO_LANDMARKS), int(StartFailure.FACE_TOO_SMALL),
                                            int(StartFailure.TOO_FEW_POINTS)]


@pytest.mark.parametrize("fit_kind", ["the-good-streams-fit", "its-own-fit-held"])
def test_normalised_landmarks_fail_their_stream_whatever_the_fit(clip, fit_kind):
    """A stream whose landmarks are normalised, beside one in pixels, fails with NORMALISED_LANDMARKS whatever its
    landmark fit made of it: given a fit that holds a pose (``initialise``'s ``fit=``, as ``lookahead_fit``'s is
    given), it was started at the pixel face's fit (NONE, CONVERGED), or failed for a later reason (its own fit held
    with CONVERGED status: a face about a pixel wide, FACE_TOO_SMALL), as a detector's restart never leaves it. The
    stream in pixels starts as with its own landmarks alone."""
    frames, lm = clip
    model = FaceTracker(CFG).model
    config = TrackerConfig(num_levels=2, max_points=400, iterations=(6, 4), template=TemplateConfig(enabled=False))
    intrinsics = Intrinsics.default(W, H)
    lms = torch.stack([lm, KINDS["normalised-landmarks"][1](lm)])
    if fit_kind == "the-good-streams-fit":
        fit = fit_landmarks(model, lm[None].expand(2, -1, -1), intrinsics, config=config.fit)
    else:
        own = fit_landmarks(model, lms, intrinsics, config=config.fit)
        fit = LandmarkFit(*(getattr(own, f.name) for f in fields(LandmarkFit)[:-1]), torch.zeros_like(own.status))
    assert fit.status.tolist() == [CONVERGED, CONVERGED]
    both = frames[:1].expand(2, -1, -1, -1)
    state, first = initialise(model, config, both, lms, intrinsics, fit=fit)
    _, alone = initialise(model, config, frames[:1], lm[None], intrinsics)
    assert first.status.tolist() == [CONVERGED, FAILED]
    assert first.start_failure.tolist() == [0, int(StartFailure.NORMALISED_LANDMARKS)]
    assert int(first.num_points[1]) == 0 and float(first.confidence[1]) == 0.0
    for name in ("rotation", "translation", "confidence", "num_points"):
        assert torch.equal(getattr(first, name)[0], getattr(alone, name)[0]), name


def test_docs_start_failure_block_runs_and_gives_what_it_states(clip):
    """docs/python-api.md's "When `initialise` fails a stream" block, run as written on two streams (the second's
    landmarks NaN rows): each line's value is what its comment states (the literal before any ``:`` gloss)."""
    frames, lm = clip
    text = (Path(__file__).resolve().parents[2] / "docs" / "python-api.md").read_text(encoding="utf-8")
    start = text.index("### When `initialise` fails a stream")
    (code,) = re.findall(r"^```python\n(.*?)^```", text[start : text.index("\n### ", start + 1)], flags=re.S | re.M)
    scope = {"tracker": FaceTracker(CFG), "frames": frames[:1].expand(2, -1, -1, -1).clone(),
             "landmarks": torch.stack([lm, torch.full_like(lm, float("nan"))])}  # fmt: skip
    checked = 0
    for line in code.splitlines():
        statement, _, comment = line.partition("  # ")
        if "=" in statement.split("(")[0]:
            exec(statement, scope)
            continue
        try:
            stated = ast.literal_eval(comment)
        except (ValueError, SyntaxError):
            stated = ast.literal_eval(comment.split(": ")[0])
        assert eval(statement, scope) == stated, line
        checked += 1
    assert checked == 3


def test_landmarks_at_one_point_are_told_that_no_face_is_nan_rows(clip):
    """All-zero landmarks (a detector's "no face" written as zeros) failed as a fit that holds no pose, the reason
    not saying that NaN rows are how a stream is given no face (the Python-API audit of session 63)."""
    frames, lm = clip
    first = FaceTracker(CFG).initialise(frames[:1], torch.zeros_like(lm)[None])
    assert first.start_failure.tolist() == [int(StartFailure.NO_POSE)]
    assert "NaN rows, not zeros" in first.start_failure_reasons[0]


def test_start_failure_codes_and_words():
    """Every code but NONE has its words; the codes are the enum's ints (what ``start_failure`` holds)."""
    assert StartFailure.NONE.reason is None
    assert all(isinstance(code.reason, str) and code.reason for code in StartFailure if code is not StartFailure.NONE)
    assert len({code.reason for code in StartFailure}) == len(StartFailure)
    assert [int(code) for code in StartFailure] == list(range(len(StartFailure)))


@pytest.fixture(scope="module")
def result(clip):
    """A managed step's :class:`TrackResult` (every optional field set) of two streams, float32."""
    frames, lm = clip
    tracker = FaceTracker(CFG)
    tracker.initialise(frames[:1].expand(2, -1, -1, -1), lm[None].expand(2, -1, -1))
    return tracker(frames[1:2].expand(2, -1, -1, -1))


def test_result_to_converts_floating_fields_only(result):
    """``TrackResult.to(dtype=...)`` casts the floating tensors, keeps the integer ones' dtype and every value, keeps
    the names (the same objects) and leaves the original as it was."""
    before = {f.name: getattr(result, f.name) for f in fields(TrackResult)}
    copies = {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in before.items()}
    moved = result.to(dtype=torch.float64)
    assert isinstance(moved, TrackResult) and moved is not result
    tensors = 0
    for f in fields(TrackResult):
        old, new = getattr(result, f.name), getattr(moved, f.name)
        if not isinstance(old, torch.Tensor):
            assert new is old, f.name  # names, None
            continue
        tensors += 1
        if old.is_floating_point():
            assert new.dtype == torch.float64, f.name
            assert torch.equal(new, old.double()), f.name
        else:
            assert new.dtype == old.dtype and torch.equal(new, old), f.name
        assert getattr(result, f.name) is before[f.name] and torch.equal(before[f.name], copies[f.name])
        assert old.dtype != torch.float64  # (the original's dtype: the step's, float32)
    assert tensors == len(fields(TrackResult)) - 4  # all but the three name tuples and start_failure (None here)
    assert moved.anim_names is result.anim_names and moved.start_failure is None
    assert torch.equal(moved.success, result.success)
    with pytest.raises(TypeError, match="dtype must be a floating torch.dtype"):
        result.to(dtype=torch.int32)


def test_result_to_takes_what_tensor_to_takes(result):
    """``TrackResult.to`` and ``LandmarkFit.to`` read their arguments as ``Tensor.to`` does: a dtype first
    (``.to(torch.float64)``, a ``TypeError`` from the device check before), a device (``torch.device``, str),
    both, keywords, each giving what the keyword call gives; anything else is a ``TypeError`` saying what ``.to``
    takes."""
    reference = result.to(dtype=torch.float64)
    fit = fit_landmarks(FaceTracker(CFG).model, torch.full((1, 68, 2), float("nan")), Intrinsics.default(W, H))
    for moved in (result.to(torch.float64), result.to("cpu", torch.float64),
                  result.to(torch.device("cpu"), dtype=torch.float64), result.to(device="cpu", dtype=torch.float64)):
        for f in fields(TrackResult):
            old, new = getattr(reference, f.name), getattr(moved, f.name)
            if isinstance(old, torch.Tensor):
                assert new.dtype == old.dtype and new.device == old.device and torch.equal(new, old), f.name
            else:
                assert new is old, f.name
    for moved_fit in (fit.to(torch.float64), fit.to("cpu", torch.float64), fit.to(dtype=torch.float64)):
        assert moved_fit.rotation.dtype == torch.float64 and moved_fit.status.dtype == torch.int64
        assert torch.equal(moved_fit.translation, fit.translation.double())
    for target in (result, fit):
        with pytest.raises(TypeError, match="got two dtypes"):
            target.to(torch.float64, torch.float32)
        with pytest.raises(TypeError, match="not a tensor"):
            target.to(torch.zeros(1, dtype=torch.float64))
        with pytest.raises(TypeError, match=r"^.to takes a device .* got float 1.5"):
            target.to(1.5)
        with pytest.raises(TypeError, match="dtype must be a floating torch.dtype"):
            target.to("cpu", torch.int64)
        with pytest.raises(TypeError, match="dtype must be a floating torch.dtype"):
            target.to(torch.int32)


def _tensors(obj) -> dict[str, torch.Tensor]:
    return {f.name: getattr(obj, f.name) for f in fields(obj) if isinstance(getattr(obj, f.name), torch.Tensor)}


def test_the_to_of_results_and_pieces_takes_non_blocking_and_copy(result):
    """The ``.to`` of ``TrackResult``, ``LandmarkFit``, ``NormalisedFaceLayout``, ``TexturedMesh``, ``LightState`` and
    ``FaceModel`` take ``non_blocking`` and ``copy`` as ``Tensor.to`` does (by keyword, or after the device and dtype): they were
    refused ("got an unexpected keyword argument 'non_blocking'"), though the docs say they take their arguments
    as ``Tensor.to`` takes them. ``copy=True`` shares no tensor with the original; without it a tensor already there
    is shared. The last three also take a dtype first, as the first two did (a TypeError from the device check), and
    refuse one that is not floating (``LightState.to(dtype=torch.int64)`` truncated the light). ``FaceModel.to``
    shares their helper (it took neither flag: "unexpected keyword argument 'non_blocking'")."""
    from torchface.normalise import build_normalised_layout
    from torchface.rendering import LightState, TexturedMesh

    fit = fit_landmarks(FaceTracker(CFG).model, torch.full((1, 68, 2), float("nan")), Intrinsics.default(W, H))
    layout = build_normalised_layout(FaceTracker(CFG).model, 16, 0.1)
    mesh = TexturedMesh(torch.zeros(3, 3), torch.tensor([[0, 1, 2]]), torch.zeros(3, 2), torch.ones(3, 4, 4))
    light = LightState.ambient_only(torch.ones(2))
    for obj in (result, fit, layout, mesh, light, FaceTracker(CFG).model):
        name = type(obj).__name__
        before = _tensors(obj)
        for moved, shared in (
            (obj.to("cpu", non_blocking=True), True), (obj.to(device="cpu", copy=True), False),
            (obj.to("cpu", None, False, True), False), (obj.to(dtype=torch.float32, non_blocking=False), True),
        ):
            for key, old in before.items():
                new = getattr(moved, key)
                assert new.dtype == old.dtype and torch.equal(new, old), (name, key)
                if shared:  # (a tensor already there, as Tensor.to returns it)
                    assert new is old, (name, key)
                else:
                    assert new is not old and (not old.numel() or new.data_ptr() != old.data_ptr()), (name, key)
        doubled = obj.to(torch.float64, copy=True)
        assert all(getattr(doubled, k).dtype == (torch.float64 if v.is_floating_point() else v.dtype)
                   for k, v in before.items()), name  # fmt: skip
        with pytest.raises(TypeError, match="non_blocking must be a bool, as Tensor.to takes it, got int 1"):
            obj.to("cpu", non_blocking=1)
        with pytest.raises(TypeError, match="copy must be a bool"):
            obj.to("cpu", copy="yes")
        with pytest.raises(TypeError, match=r"got True for the dtype \(non_blocking= and copy= by keyword\)"):
            obj.to(torch.float64, True)
        with pytest.raises(TypeError, match="dtype must be a floating torch.dtype"):  # (a light truncated to ints)
            obj.to(dtype=torch.int64)
        assert all(v is before[k] for k, v in _tensors(obj).items()), name  # the original unchanged


def test_result_to_moves_start_failure_as_an_integer_field(clip):
    """An ``initialise`` result with a ``start_failure`` tensor (one stream started, one without landmarks): ``.to``
    a dtype keeps its int64 codes (and ``status``, ``num_points``) as they are, and a device moves them with the
    rest (on a GPU where there is one)."""
    frames, lm = clip
    no_face = torch.full_like(lm, float("nan"))
    first = FaceTracker(CFG).initialise(frames[:1].expand(2, -1, -1, -1), torch.stack([lm, no_face]))
    assert first.start_failure.tolist() == [0, int(StartFailure.NO_LANDMARKS)]
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for device in devices:
        calls = (first.to(device, torch.float64), first.to(device), first.to(device=device, dtype=torch.float64))
        for moved in calls + ((first.to(torch.float64),) if device == "cpu" else ()):
            assert moved.start_failure.dtype == torch.int64 and moved.start_failure.device.type == device
            assert moved.start_failure.tolist() == first.start_failure.tolist()
            assert moved.start_failure_reasons == first.start_failure_reasons
            assert moved.rotation.device == moved.start_failure.device
            for name in ("status", "num_points", "iterations"):
                assert getattr(moved, name).dtype == getattr(first, name).dtype, name
        assert first.start_failure.device.type == "cpu"  # (the original as it was)


def test_result_to_device_and_cpu(result):
    """``.to("cpu")`` and ``.cpu()`` give the CPU's result (here: the same values); ``meta`` (no values to hold) and a
    device this machine lacks are a ``ValueError`` naming it, as everywhere torchface takes a device; with a GPU,
    the round trip to it and back keeps every value."""
    for moved in (result.to("cpu"), result.cpu(), result.to(torch.device("cpu"), torch.float32)):
        for f in fields(TrackResult):
            old, new = getattr(result, f.name), getattr(moved, f.name)
            if isinstance(old, torch.Tensor):
                assert new.device.type == "cpu" and new.dtype == old.dtype and torch.equal(new, old), f.name
    with pytest.raises(ValueError, match="device 'meta' holds no data"):
        result.to("meta")
    with pytest.raises(ValueError, match="devices here"):
        result.to("gpu0")
    if torch.cuda.is_available():
        there = result.to("cuda", torch.float64)
        assert there.rotation.device.type == "cuda" and there.status.device.type == "cuda"
        assert there.status.dtype == torch.int64 and there.rotation.dtype == torch.float64
        back = there.cpu()
        for f in fields(TrackResult):
            old, new = getattr(result, f.name), getattr(back, f.name)
            if isinstance(old, torch.Tensor):
                assert new.device.type == "cpu" and torch.equal(new, old.double() if old.is_floating_point() else old)
