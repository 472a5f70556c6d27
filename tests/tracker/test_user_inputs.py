"""Tests of what a Python user hands ``FaceTracker`` (and the functional pieces and ``NormalisedFace`` behind it) by
mistake, from session 52's audit of the Python API: inputs on the ``meta`` device, landmarks in MediaPipe's
normalised coordinates instead of pixels (from the caller and from a detector), and landmarks as NumPy arrays, as
``torchface.io.read_landmarks`` returns them. Each was an error from deep inside torch, a silent FAILED status, or a
``TypeError`` that did not say how to make a tensor. A small rendered clip (tests/_helpers.py's, 160x120).
"""

from __future__ import annotations

import copy
import re
import sys
import warnings
from pathlib import Path

import pytest
import torch

from torchface.normalise import NormalisedFace
from torchface.tracker import FaceTracker, FitConfig, StartFailure, TrackerConfig, TrackStatus

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _helpers import sideways_clip  # noqa: E402

W, H = 160, 120
CFG = TrackerConfig(
    num_levels=2, max_points=400, iterations=(6, 4), fit=FitConfig(shape_prior_precision=0.0, held_shape_units=()),
)
CONVERGED, FAILED, LOST = int(TrackStatus.CONVERGED), int(TrackStatus.FAILED), int(TrackStatus.LOST)


@pytest.fixture(scope="module")
def clip():
    """``frames (3, 3, H, W)`` and the first frame's landmarks ``(68, 2)`` in pixels."""
    frames, landmarks, _ = sideways_clip(W, H, 3)
    return frames, landmarks


def normalised(landmarks: torch.Tensor) -> torch.Tensor:
    """``landmarks`` ``(..., 2)`` in pixels (centres at integers) as MediaPipe gives them: x / W, y / H, in [0, 1]
    (MediaPipe's convention, measured: torchface.detect.facemesh.MediaPipeDetector)."""
    return landmarks / torch.tensor([float(W), float(H)])


def test_inputs_on_the_meta_device_are_named(clip):
    """Inputs on another device are moved to the model's (docs/python-api.md, "Devices and dtypes"); ``meta`` tensors
    hold no values to move. They failed deep inside torch: frames with "Cannot copy out of meta tensor; no data!"
    (a NotImplementedError, at ``initialise``, at a step and in ``NormalisedFace``), landmarks with a
    NotImplementedError about ``torch.nonzero``'s meta registration."""
    frames, lm = clip
    tracker = FaceTracker(CFG)
    message = r"^{} are on device 'meta', which holds no values: pass them on a device that computes"
    with pytest.raises(ValueError, match=message.format("frames")):
        tracker.initialise(frames[:1].to("meta"), lm[None])
    with pytest.raises(ValueError, match=message.format("landmarks_px")):
        tracker.initialise(frames[:1], lm[None].to("meta"))
    with pytest.raises(ValueError, match=message.format("weights")):
        tracker.initialise(frames[:1], lm[None], weights=torch.ones(1, 68, device="meta"))
    tracker.initialise(frames[:1], lm[None])
    with pytest.raises(ValueError, match=message.format("frames")):
        tracker(frames[1:2].to("meta"))
    assert bool(tracker(frames[1:2]).success)  # (the refused step left the state as it was)
    with pytest.raises(ValueError, match=message.format("frames")):
        NormalisedFace(tracker.model)(frames[1:2].to("meta"), tracker.state)


def test_landmarks_in_normalised_coordinates_are_told_how_to_make_pixels(clip):
    """Landmarks in [0, 1] (MediaPipe's face landmarker: x / W, y / H) were taken as pixels: a face less than a pixel
    wide, which the landmark fit FAILED, and ``initialise`` returned status 2 without a word of why. They are refused
    with how to make pixels of them, and the pixels made so start the stream as the landmarks in pixels do."""
    frames, lm = clip
    with pytest.raises(ValueError, match=r"^landmarks_px lie within \[-0.5, 1.5\] x \[-0.5, 1.5\]: normalised "
                                         r"coordinates .*landmarks \* torch.tensor\(\[160.0, 120.0\]\) "
                                         r"for these 160x120"):
        FaceTracker(CFG).initialise(frames[:1], normalised(lm)[None])
    tracker = FaceTracker(CFG)
    converted = tracker.initialise(frames[:1], (normalised(lm) * torch.tensor([160.0, 120.0]))[None])
    reference = FaceTracker(CFG).initialise(frames[:1], lm[None])
    assert int(converted.status) == CONVERGED
    assert torch.allclose(converted.translation, reference.translation, atol=1e-3)
    # Streams without a face (NaN rows) or with weight 0 on the points outside [0, 1] leave the others' say.
    nan = torch.full_like(lm, float("nan"))
    with pytest.raises(ValueError, match=r"^landmarks_px lie within \[-0.5, 1.5\]"):
        FaceTracker(CFG).initialise(frames[:2], torch.stack([normalised(lm), nan]))
    # A face partly out of the frame: MediaPipe's points a little outside [0, 1] (they failed without a word too).
    partly_out = normalised(lm) - torch.stack([normalised(lm)[:, 0].min() + 0.05, torch.tensor(0.0)])
    assert bool((partly_out[:, 0] < 0).any())
    with pytest.raises(ValueError, match=r"^landmarks_px lie within \[-0.5, 1.5\]"):
        FaceTracker(CFG).initialise(frames[:1], partly_out[None])
    # Centred coordinates, in [-1, 1], are told their own recipe too (the [0, 1] one alone put them at negative
    # pixels), and the pixels made so start the stream.
    centred = normalised(lm) * 2 - 1
    with pytest.raises(ValueError, match=r"if they are centred, in \[-1, 1\] \(some are below 0\): \(landmarks \+ 1\) "
                                         r"\* torch.tensor\(\[80, 60\]\)"):  # fmt: skip
        FaceTracker(CFG).initialise(frames[:1], centred[None])
    assert int(FaceTracker(CFG).initialise(frames[:1], ((centred + 1) * torch.tensor([80, 60]))[None]).status) == 0
    with pytest.raises(ValueError, match=r"for these 160x120 frames \(a fit to them failed"):  # (all >= 0: not said)
        FaceTracker(CFG).initialise(frames[:1], normalised(lm)[None])
    half = torch.cat([normalised(lm[:40]), lm[40:]])
    weights = torch.cat([torch.ones(40), torch.zeros(28)])[None]
    with pytest.raises(ValueError, match=r"^landmarks_px lie within \[-0.5, 1.5\]"):
        FaceTracker(CFG).initialise(frames[:1], half[None], weights=weights)


@pytest.mark.parametrize(
    "landmarks, status",
    [
        # a stream in pixels: the other fails alone
        (lambda lm: torch.stack([normalised(lm), lm]), [FAILED, CONVERGED]),
        (lambda lm: torch.zeros(2, 68, 2), [FAILED, FAILED]),  # zeros for "no face": at one point, as before
        (lambda lm: normalised(lm).where(torch.arange(68)[:, None] < 3, float("nan"))[None].expand(2, -1, -1),
         [FAILED, FAILED]),  # fewer than 4 landmarks: no face found, as before
    ],
    ids=["one-stream-in-pixels", "zeros", "three-points"],
)
def test_landmarks_that_fail_alone_as_before(clip, landmarks, status):
    """What is not taken for normalised coordinates fails the stream alone, as before the check: a batch where one
    stream's landmarks are in pixels, zeros (at one point), too few points."""
    frames, lm = clip
    result = FaceTracker(CFG).initialise(frames[:2], landmarks(lm))
    assert result.status.tolist() == status


def test_a_landmark_row_with_one_coordinate_alone_is_refused_by_every_entry_point(clip):
    """A row with one coordinate NaN (or infinite) and the other finite, and a row of infinite coordinates, were taken
    as a missing point by ``FaceTracker.initialise`` (and ``fit_landmarks``, ``pyramid_for_faces``) and refused by
    ``torchface track``, ``NormaliseFaces`` and ``track_sequence``. One rule now, in one function that all of them
    call (landmark_rows_problem): refused, naming the row (and the stream of a batch), saying how a missing point is
    marked. A NaN row stays a missing point."""
    from torchface.io.landmarks import missing_points_problem
    from torchface.tracker import fit_landmarks, pyramid_for_faces
    from training_hooks.transforms import FaceTrackingConfig, NormaliseFaces

    frames, lm = clip
    tracker = FaceTracker(CFG)
    half = lm.clone()
    half[5, 0] = float("nan")
    said = (r"^landmarks_px: landmark\(s\) \[5\] have one coordinate NaN \(a missing point has neither\): mark a "
            r"missing point with both coordinates NaN \(a NaN row\), or give a point you do not trust weight 0; one "
            r"coordinate alone is most likely a bug upstream")
    with pytest.raises(ValueError, match=said) as refused:
        tracker.initialise(frames[:1], half[None])
    with pytest.raises(ValueError, match=said):
        fit_landmarks(tracker.model, half[None], _camera())
    with pytest.raises(ValueError, match=said):
        pyramid_for_faces(CFG, half[None], (H, W))
    # a landmarks file's rule (torchface track) and NormaliseFaces' and track_sequence's is this one, word for word
    rule = str(refused.value).removeprefix("landmarks_px: ").replace(", or give a point you do not trust weight 0", "")
    assert missing_points_problem(half.double().numpy()) == rule
    with pytest.raises(ValueError, match=f"^landmarks: {re.escape(rule)}$"):
        NormaliseFaces(FaceTrackingConfig(face_size=32))(frames[:1], half)
    inf = lm.clone()
    inf[7, 1] = float("inf")
    infinite = (r"^landmarks_px: landmark\(s\) \[7\] of stream 1 are infinite \(a missing point is a NaN row\): most "
                r"likely a bug upstream \(a division by zero, an overflow\); give a point you do not trust weight 0$")
    with pytest.raises(ValueError, match=infinite):
        tracker.initialise(frames[:2], torch.stack([lm, inf]))
    # a row of infinite coordinates too (it was taken as a missing point here, and refused by torchface track,
    # NormaliseFaces and track_sequence): every entry point refuses it, in the same words
    inf[7] = float("-inf")
    with pytest.raises(ValueError, match=infinite) as refused:
        tracker.initialise(frames[:2], torch.stack([lm, inf]))
    with pytest.raises(ValueError, match=infinite):
        fit_landmarks(tracker.model, torch.stack([lm, inf]), _camera())
    with pytest.raises(ValueError, match=infinite):
        pyramid_for_faces(CFG, torch.stack([lm, inf]), (H, W))
    rule = str(refused.value).removeprefix("landmarks_px: ").replace(" of stream 1", "").replace(
        "; give a point you do not trust weight 0", "")
    assert missing_points_problem(inf.double().numpy()) == rule
    with pytest.raises(ValueError, match=f"^landmarks: {re.escape(rule)}$"):
        NormaliseFaces(FaceTrackingConfig(face_size=32))(frames[:1], inf)
    missing = lm.clone()
    missing[5] = float("nan")  # both coordinates: a missing point, as before
    assert int(tracker.initialise(frames[:1], missing[None]).status) == CONVERGED


def _camera():
    from torchface.geometry import Intrinsics

    return Intrinsics.default(W, H)


@pytest.mark.parametrize(
    "bad, said",
    [(-0.5, r"^weights must be >= 0 \(0 ignores a point; 1 is what the fit's priors are set for\), got -0.5 for "
            r"landmark\(s\) \[3\]$"),
     (float("nan"), r"^weights must be numbers >= 0, got NaN for landmark\(s\) \[3\]: give a point you do not "
                    r"trust weight 0"),
     (float("inf"), r"^weights must be finite, got inf for landmark\(s\) \[3\]")],
    ids=["negative", "nan", "inf"],
)
def test_negative_nan_or_infinite_landmark_weights_are_refused(clip, bad, said):
    """Negative, NaN and infinite landmark weights were read as weight 0 (the point ignored) without a word; they are
    refused by ``FaceTracker.initialise`` (and the functional ``initialise``), ``fit_landmarks`` and
    ``pyramid_for_faces``, naming the point; weight 0 still ignores a point."""
    from torchface.tracker import fit_landmarks, initialise, pyramid_for_faces

    frames, lm = clip
    weights = torch.ones(1, 68)
    weights[0, 3] = bad
    tracker = FaceTracker(CFG)
    with pytest.raises(ValueError, match=said):
        tracker.initialise(frames[:1], lm[None], weights=weights)
    with pytest.raises(ValueError, match=said):
        initialise(tracker.model, CFG, frames[:1], lm[None], _camera(), weights)
    with pytest.raises(ValueError, match=said):
        fit_landmarks(tracker.model, lm[None], _camera(), weights)
    with pytest.raises(ValueError, match=said):
        pyramid_for_faces(CFG, lm[None], (H, W), weights)
    weights[0, 3] = 0.0
    assert int(tracker.initialise(frames[:1], lm[None], weights=weights).status) == CONVERGED


def test_landmark_weights_of_one_stream_or_with_a_trailing_axis_are_told_how_to_make_them(clip):
    """Weights ``(K,)`` (one per landmark, as a (68, 2) landmarks file's rows) or ``(B, K, 1)`` given to ``initialise``
    or ``fit_landmarks`` (session 63's Python-API audit) were told "weights must be (1, 68), got (68,)" alone, where
    landmarks of one stream are told ``landmarks_px[None]``; the hint given makes weights that start the streams."""
    from torchface.model import load_candide3
    from torchface.geometry import Intrinsics
    from torchface.tracker import fit_landmarks

    frames, lm = clip
    w = torch.ones(68)
    with pytest.raises(ValueError, match=r"^weights must be a \(B, K\) = \(1, 68\) tensor or None, got shape \(68,\) "
                                        r"\(one per landmark: weights\[None\]\)$"):
        FaceTracker(CFG).initialise(frames[:1], lm[None], weights=w)
    with pytest.raises(ValueError, match=r"^weights must be a \(B, K\) = \(2, 68\) tensor or None, got shape \(68,\) "
                                        r"\(one per landmark: weights\[None\].expand\(2, -1\) for every stream\)$"):
        FaceTracker(CFG).initialise(frames[:2], torch.stack([lm, lm]), weights=w)
    with pytest.raises(ValueError, match=r"^weights must be a \(B, K\) = \(1, 68\) tensor or None, got shape "
                                        r"\(1, 68, 1\) \(a trailing axis: weights\[..., 0\]\)$"):
        FaceTracker(CFG).initialise(frames[:1], lm[None], weights=w[None, :, None])
    with pytest.raises(ValueError, match=r"^weights must be a \(B, K\) = \(1, 68\) tensor or None, got shape "
                                        r"\(68,\) \(one per"):
        fit_landmarks(load_candide3(), lm[None], Intrinsics.default(W, H), weights=w)
    result = FaceTracker(CFG).initialise(frames[:2], torch.stack([lm, lm]), weights=w[None].expand(2, -1))
    assert result.status.tolist() == [CONVERGED, CONVERGED]
    assert int(FaceTracker(CFG).initialise(frames[:1], lm[None], weights=w[None, :, None][..., 0]).status) == CONVERGED


def test_landmark_weights_of_another_shape_are_refused_alike_by_each_entry_point(clip):
    """``initialise``, ``fit_landmarks`` and ``pyramid_for_faces`` check the landmark weights' shape with one function
    (``torchface.tracker.fit.check_weights_shape``), so that the same weights are told the same thing: each had worded
    the shape its own way ("weights must be (1, 68)", "(B, K) = (1, 68)", "(1, 68) (B, K)", the last without the
    hint of how to make them)."""
    from torchface.geometry import Intrinsics
    from torchface.model import load_candide3
    from torchface.tracker import fit_landmarks, pyramid_for_faces

    frames, lm = clip
    calls = (
        lambda w: FaceTracker(CFG).initialise(frames[:1], lm[None], weights=w),
        lambda w: fit_landmarks(load_candide3(), lm[None], Intrinsics.default(W, H), weights=w),
        lambda w: pyramid_for_faces(CFG, lm[None], (H, W), w),
    )
    for bad, error in ((torch.ones(68), ValueError), (torch.ones(1, 68, 1), ValueError), ([[1.0] * 68], TypeError)):
        said = set()
        for call in calls:
            with pytest.raises(error, match=r"^weights must be a \(B, K\) = \(1, 68\) tensor or None, got ") as info:
                call(bad)
            said.add(str(info.value))
        assert len(said) == 1, said


def test_landmark_weights_that_are_not_a_tensor_are_told_how_to_make_one(clip):
    """NumPy or list weights were told "weights must be a (1, 68) tensor or None, got ndarray" alone, where landmarks
    of those types are told how to make a tensor (docs/python-api.md); by ``initialise``, ``fit_landmarks`` and
    ``pyramid_for_faces``. The way named starts the streams."""
    import numpy as np

    from torchface.geometry import Intrinsics
    from torchface.model import load_candide3
    from torchface.tracker import fit_landmarks, pyramid_for_faces

    frames, lm = clip
    w = np.ones(68)
    with pytest.raises(TypeError, match=r"^weights must be a \(B, K\) = \(1, 68\) tensor or None, got ndarray \(a "
                                        r"NumPy array: torch\.from_numpy\(weights\)\[None\]\)$"):
        FaceTracker(CFG).initialise(frames[:1], lm[None], weights=w)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"got ndarray \(a NumPy array: torch\.from_numpy\(weights\)\[None\]\.expand"
                                        r"\(2, -1\)\)$"):
        FaceTracker(CFG).initialise(frames[:2], torch.stack([lm, lm]), weights=w)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"got list \(a list: torch\.tensor\(weights\), laid out \(1, 68\)\)$"):
        fit_landmarks(load_candide3(), lm[None], Intrinsics.default(W, H),
                      weights=[[1.0] * 68])  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"got ndarray \(a NumPy array: torch\.from_numpy\(weights\)\)$"):
        pyramid_for_faces(CFG, lm[None], (H, W), w[None])  # type: ignore[arg-type]
    made = torch.from_numpy(w)[None]
    assert int(FaceTracker(CFG).initialise(frames[:1], lm[None], weights=made).status) == CONVERGED


def test_intrinsics_that_look_mixed_up_are_named_and_tracked(clip):
    """Intrinsics in OpenCV's matrix order (``fx, cx, fy, cy`` for ``fx, fy, cx, cy``) were tracked without a word
    (a camera that sees the face 2x stretched); a size swapped or given among the other numbers was told the size
    alone. ``initialise`` names a likely mix-up with the fix in a ``UserWarning`` and tracks (nothing there is
    impossible), and the size check says which mix-up its numbers show; a plausible camera has no word."""
    from torchface.geometry import Intrinsics

    frames, lm = clip
    from torchface.geometry.camera import MixedUpIntrinsics

    given = Intrinsics(160, 120, 160.0, 79.5, 160.0, 59.5)
    with pytest.warns(UserWarning, match=r"^intrinsics fx=160, fy=79.5, cx=160, cy=59.5 for a 160x120 frame look "
                                         r"mixed up: OpenCV's matrix order .*Intrinsics\(160, 120, fx=160, fy=160, "
                                         r"cx=79.5, cy=59.5\)") as warned:
        result = FaceTracker(CFG).initialise(frames[:1], lm[None], given)
    assert result.status.shape == (1,)
    # (a MixedUpIntrinsics, holding the camera: torchface track tells its --focal from it)
    assert isinstance(warned[0].message, MixedUpIntrinsics) and warned[0].message.intrinsics == given
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        FaceTracker(CFG).initialise(frames[:1], lm[None], Intrinsics(160, 120, 170.0, 160.0, 70.0, 50.0))
    with pytest.raises(ValueError, match=r"^frames must be 120x160 \(W x H, the intrinsics' size\), got 160x120 "
                                         r"\(width and height swapped\? Intrinsics\(160, 120, fx, fy, cx, cy\)"):
        FaceTracker(CFG).initialise(frames[:1], lm[None], Intrinsics(120, 160, 160.0, 160.0, 79.5, 59.5))
    with pytest.raises(ValueError, match=r"^frames must be 200x200 .*got 160x120 \(the size given among fx, fy, cx, "
                                         r"cy\? Intrinsics takes \(width, height, fx, fy, cx, cy\)"):
        FaceTracker(CFG).initialise(frames[:1], lm[None], Intrinsics(200, 200, 79.5, 59.5, 160, 120))


def test_a_detector_answering_normalised_coordinates_is_named(clip):
    """A detector (``FaceTracker(detector=...)``) that answers MediaPipe's normalised coordinates failed every fit at
    each recovery attempt: the stream stayed LOST without a word. It was then refused with a ``ValueError`` at the
    restart, which a detector answering pixels for other streams (two detectors behind one) raised too whenever the
    normalised streams restarted alone. Now such a stream fails its restart alone: LOST, its result's
    ``start_failure`` says NORMALISED_LANDMARKS, and a ``RuntimeWarning`` says how to make pixels. One answering
    pixels starts it (even with a row of one coordinate alone or an infinite one, taken as missing with a
    ``RuntimeWarning``)."""
    frames, lm = clip
    nan = torch.full((1, 68, 2), float("nan"))
    tracker = FaceTracker(CFG, detector=lambda batch: normalised(lm)[None].expand(batch.shape[0], -1, -1).clone())
    tracker.initialise(frames[:1], nan)  # starts FAILED: the detector is asked at its recovery attempts
    reasons = []
    with pytest.warns(RuntimeWarning, match=r"^the detector's landmarks of some streams lie within \[-0.5, 1.5\] x "
                                            r"\[-0.5, 1.5\]: normalised .*landmarks \* torch.tensor\(\[160.0, "
                                            r"120.0\]\) for these 160x120 frames"):
        for t in (1, 2, 1, 2, 1, 2):
            result = tracker(frames[t : t + 1])
            assert int(result.status) == LOST
            if result.start_failure is not None:  # (a frame where the restart was tried)
                reasons.append(int(result.start_failure))
    assert reasons and set(reasons) == {int(StartFailure.NORMALISED_LANDMARKS)}
    assert result.start_failure_reasons[0] is None or "normalised" in result.start_failure_reasons[0]
    # (a detector's row with one coordinate alone, refused where a user gives it, is a missing point with a word:
    # a restart never raises)
    half = lm.clone()
    half[5, 1] = float("nan")
    half[9] = float("inf")  # (an infinite row too: refused where a user gives it, missing here)
    tracker = FaceTracker(CFG, detector=lambda batch: half[None].expand(batch.shape[0], -1, -1).clone())
    tracker.initialise(frames[:1], nan)
    with pytest.warns(RuntimeWarning, match=r"^the detector's landmark\(s\) \[9\] are infinite \(a missing point is a "
                                            r"NaN row\).*; landmark\(s\) \[5\] have one coordinate NaN .*: those "
                                            r"points are taken as missing$"):
        statuses = [int(tracker(frames[t : t + 1]).status) for t in (1, 2, 1, 2, 1, 2)]
    assert statuses[0] == LOST and CONVERGED in statuses


#: The value of the pixel (0, 0, 0) that marks the frames a mixed detector answers in normalised coordinates.
_MARK = 0.123


def _mixed_detector(lm: torch.Tensor):
    """A detector answering ``lm`` in pixels for a frame, normalised for one marked with :data:`_MARK` (MediaPipe
    behind one, dlib behind the other)."""
    def detect(batch: torch.Tensor) -> torch.Tensor:
        return torch.stack([normalised(lm) if abs(float(b[0, 0, 0]) - _MARK) < 1e-6 else lm.clone() for b in batch])

    return detect


@pytest.mark.parametrize("order", ["pixels-first", "normalised-first"])
def test_a_detector_mixing_pixels_and_normalised_points_fails_those_streams_alone(clip, order):
    """A detector that answers pixels for one stream and normalised [0, 1] points for another (each stream's first
    landmarks missing, so both restart from the detector): the normalised stream fails its restart with the reason
    NORMALISED_LANDMARKS and stays LOST, the other restarts and tracks as it does alone with a pixel detector; a
    restart asked of the normalised stream alone (its partner already started) is no error either (it raised a
    ``ValueError`` for the batch)."""
    frames, lm = clip
    marked = frames.clone()
    marked[:, 0, 0, 0] = _MARK
    good, bad = (0, 1) if order == "pixels-first" else (1, 0)
    batch = torch.stack([frames, marked] if good == 0 else [marked, frames], 1)  # (T, 2, 3, H, W)
    nan = torch.full((2, 68, 2), float("nan"))
    tracker = FaceTracker(CFG, detector=_mixed_detector(lm))
    alone = FaceTracker(CFG, detector=lambda b: lm[None].expand(b.shape[0], -1, -1).clone())
    first = tracker.initialise(batch[0], nan)
    alone.initialise(frames[:1], nan[:1])
    assert first.start_failure.tolist() == [int(StartFailure.NO_LANDMARKS)] * 2
    tried = 0
    with pytest.warns(RuntimeWarning, match="normalised coordinates"):
        for t in (1, 2) * 5:  # (restarts tried at the 5th and 10th frames)
            result, reference = tracker(batch[t]), alone(frames[t : t + 1])
            assert int(result.status[bad]) == LOST
            if result.start_failure is not None:
                tried += 1
                assert int(result.start_failure[bad]) == int(StartFailure.NORMALISED_LANDMARKS)
                assert int(result.start_failure[good]) == int(StartFailure.NONE)
                assert result.start_failure_reasons[good] is None and "normalised" in result.start_failure_reasons[bad]
            assert int(result.status[good]) == int(reference.status[0])
            torch.testing.assert_close(result.rotation[good], reference.rotation[0], rtol=0, atol=1e-5)
            torch.testing.assert_close(result.translation[good], reference.translation[0], rtol=0, atol=1e-3)
    assert tried == 2  # (the first with both streams, the second with the normalised stream alone)
    assert int(result.status[good]) != LOST


@pytest.mark.parametrize(
    "answer, error, hint",
    [
        (lambda lm, b: lm.numpy(), TypeError, r"got ndarray \(one image's answer\? .*torchface.detect.batched"),
        (lambda lm, b: None, TypeError, r"got NoneType \(one image's answer\? .*torchface.detect.batched"),
        (lambda lm, b: lm, ValueError, r"got \(68, 2\) \(one image's answer\? .*torchface.detect.batched"),
        (lambda lm, b: lm[None].expand(b, -1, -1).numpy(), TypeError, r"got ndarray \(a NumPy array: "
                                                                       r"torch.from_numpy\(landmarks\)\)$"),
        (lambda lm, b: [lm.numpy()] * b, TypeError, r"got list \(a list, one answer per stream: torch.stack\(\[torch"
                                                     r"\.as_tensor\(x\) for x in answers\]\), NaN rows for no face; "
                                                     r"or wrap a per-image detector in torchface\.detect\.batched"),
    ],
    ids=["per-image-array", "per-image-none", "one-frame-tensor", "numpy-batch", "list"],
)
def test_a_detector_answering_one_images_points_or_numpy_is_told_what_to_return(clip, answer, error, hint):
    """A user's own detector given to ``FaceTracker(detector=...)`` that answers as a per-image detector does (one
    image's ``(68, 2)`` array, or None for no face), or a batch as NumPy or a list (session 63's Python-API audit),
    was told "the detector must return a (1, 68, 2) tensor ..., got ndarray" alone, at the first recovery attempt;
    it is told ``torchface.detect.batched`` or how to make the tensor, and the detector so made re-initialises."""
    from torchface.detect import batched

    frames, lm = clip
    tracker = FaceTracker(CFG, detector=lambda batch: answer(lm, batch.shape[0]))
    tracker.initialise(frames[:1], torch.full((1, 68, 2), float("nan")))  # FAILED: the detector is asked next
    with pytest.raises(error, match=r"^the detector must return .*" + hint):
        for t in (1, 2, 1, 2, 1, 2):  # (to the first recovery attempt)
            tracker(frames[t : t + 1])
    tracker = FaceTracker(CFG, detector=batched(lambda image: lm.numpy()))
    tracker.initialise(frames[:1], torch.full((1, 68, 2), float("nan")))
    statuses = [int(tracker(frames[t : t + 1]).status) for t in (1, 2, 1, 2, 1, 2)]
    assert statuses[-1] != LOST, statuses


@pytest.mark.parametrize(
    "make, hint",
    [
        (lambda lm: lm.numpy(), r"got ndarray \(a NumPy array of one stream's \(K, 2\) points, as read_landmarks gives "
                                r"them: torch.from_numpy\(points\)\[None\]\)$"),
        (lambda lm: lm[None].numpy(), r"got ndarray \(a NumPy array: torch.from_numpy\(points\)\)$"),
        (lambda lm: lm[None].tolist(), r"got list \(a list: torch.tensor\(points\), laid out \(1, 68, 2\)\)$"),
    ],
    ids=["numpy-one-stream", "numpy-batch", "list"],
)
def test_landmarks_that_are_not_a_tensor_are_told_how_to_make_one(clip, make, hint):
    """``read_landmarks`` returns a ``(68, 2)`` NumPy array; handed to ``initialise`` it was told "got ndarray"
    alone (frames in NumPy are told how to make a tensor). The hint given makes landmarks that start the stream."""
    frames, lm = clip
    with pytest.raises(TypeError, match=r"^landmarks_px must be a torch.Tensor \(1, 68, 2\) of pixel coordinates, "
                                        + hint):  # fmt: skip
        FaceTracker(CFG).initialise(frames[:1], make(lm))
    assert int(FaceTracker(CFG).initialise(frames[:1], torch.from_numpy(lm.numpy())[None]).status) == CONVERGED


def test_frames_of_another_batch_size_are_told_how_the_streams_change(clip):
    """A step given more or fewer frames than the streams initialised (a person entering or leaving a multi-stream
    run) was told "expected 2 frames (one per stream), got 1" alone; it names ``select`` and ``initialise``, and the
    ``select`` it names then takes the frame."""
    frames, lm = clip
    tracker = FaceTracker(CFG)
    tracker.initialise(frames[:2], lm[None].expand(2, -1, -1))
    with pytest.raises(ValueError, match=r"^expected 2 frames \(one per stream\), got 1: the streams are those "
                                         r"initialised \(select\(index\) keeps some of them, initialise starts"):
        tracker(frames[1:2])
    assert bool(tracker.select([0])(frames[1:2]).success)


def test_a_landmarks_file_of_normalised_coordinates_is_refused_naming_it(tmp_path):
    """``read_landmarks`` (``torchface track --landmarks``, ``training_hooks``' landmark files) read a file of
    MediaPipe's normalised points as pixels: ``torchface track`` then tracked the video as a face under a pixel wide,
    every row unsuccessful, exit status 0. It names the file and the pixels to give; a file of pixels, and one whose
    missing points are NaN beside points in pixels, read as before."""
    from torchface.io import InputError, read_landmarks

    _, lm, _ = sideways_clip(W, H, 1)
    path = tmp_path / "mediapipe.csv"
    rows = normalised(lm).double().tolist()
    path.write_text("x,y\n" + "".join(f"{x!r},{y!r}\n" for x, y in rows))
    with pytest.raises(InputError, match=r"mediapipe.csv: every point lies within \[-0.5, 1.5\] x \[-0.5, 1.5\]: "
                                         r"normalised coordinates .* Give pixels, centres at integers: x \* 160, "
                                         r"y \* 120$"):  # fmt: skip
        read_landmarks(path, W, H)
    x0 = min(x for x, _ in rows) + 0.05  # a face partly out of the frame: MediaPipe's points a little outside [0, 1]
    path.write_text("x,y\n" + "".join(f"{x - x0!r},{y!r}\n" for x, y in rows))
    with pytest.raises(InputError, match=r"mediapipe.csv: every point lies within \[-0.5, 1.5\]"):
        read_landmarks(path, W, H)
    pixels = [[x * W, y * H] for x, y in rows]
    path.write_text("x,y\n" + "".join(f"{x!r},{y!r}\n" for x, y in pixels))
    assert torch.allclose(torch.from_numpy(read_landmarks(path, W, H)), lm.double(), atol=1e-4)
    path.write_text("x,y\n" + "".join("nan,nan\n" if k < 60 else f"{x!r},{y!r}\n" for k, (x, y) in enumerate(pixels)))
    assert int(torch.isfinite(torch.from_numpy(read_landmarks(path, W, H))).all(-1).sum()) == 8


def test_landmarks_checked_before_the_frame_size_is_known_are_told_the_rule(clip):
    """``training_hooks`` checks a video's landmark array before it reads the video, with a size of 2**30: the
    refusal of normalised points gives the rule then, not ``x * 1073741824``."""
    from torchface.io import InputError, check_landmarks

    _, lm = clip
    with pytest.raises(InputError, match=r"^a.avi: landmarks: every point .* x \* W, y \* H$"):
        check_landmarks(normalised(lm).numpy(), 1 << 30, 1 << 30, "a.avi: landmarks", missing=True)


def test_saved_results_load_with_torchs_weights_only_load_as_the_docs_say(clip, tmp_path):
    """docs/python-api.md, "Selecting, copying and saving": results saved with ``torch.save`` load with torch's
    weights-only ``torch.load`` once ``TrackResult`` is named (``safe_globals``), every field as it was."""
    from torchface.tracker import TrackResult

    frames, lm = clip
    tracker = FaceTracker(CFG)
    results = [tracker.initialise(frames[:1], lm[None]), tracker(frames[1:2])]
    torch.save(results, tmp_path / "results.pt")
    with torch.serialization.safe_globals([TrackResult]):
        loaded = torch.load(tmp_path / "results.pt", weights_only=True)
    for a, b in zip(loaded, results):
        assert type(a) is TrackResult and a.anim_names == b.anim_names
        for name in ("rotation", "translation", "status", "confidence"):
            assert torch.equal(getattr(a, name), getattr(b, name))


def test_a_model_given_as_the_first_argument_is_told_where_it_goes():
    """``FaceTracker(model)`` (the model first, as other libraries' modules take it) said "config must be a
    TrackerConfig, got FaceModel" alone."""
    from torchface.model import load_candide3

    model = load_candide3()
    with pytest.raises(TypeError, match=r"^config must be a TrackerConfig, got FaceModel: the model is the second "
                                        r"argument, FaceTracker\(TrackerConfig\(\), model\) or "
                                        r"FaceTracker\(model=model\)$"):
        FaceTracker(model)  # type: ignore[arg-type]
    assert FaceTracker(model=model).model is model


def test_frames_of_another_size_mid_stream_are_told_to_initialise_again(clip):
    """A step given frames of another size than the stream's (the next video in a loop) said the size alone; it says
    how to track them, and the ``initialise`` it names does."""
    frames, lm = clip
    tracker = FaceTracker(CFG)
    tracker.initialise(frames[:1], lm[None])
    smaller = frames[1:2, :, : H - 20, : W - 20]
    with pytest.raises(ValueError, match=r"^frames must be 160x120 \(W x H, the tracked size\), got 140x100: a stream "
                                         r"keeps its size, initialise again to track frames of another$"):
        tracker(smaller)
    assert bool(tracker.initialise(smaller, lm[None]).success)


def test_the_packaged_grid_clip_tracks_from_python_as_the_docs_say():
    """docs/python-api.md, "Frames and landmarks": ``open_frames`` and ``read_landmarks`` give what ``FaceTracker``
    takes, RGB frames in [0, 1] (the BGR recipe for an OpenCV image gives the same values) and pixel landmarks, and
    the packaged GRID clip tracks from them, step by step as the page writes it."""
    import cv2
    import numpy as np

    from torchface.io import open_frames, read_landmarks

    root = Path(__file__).resolve().parents[2] / "torchface" / "data" / "grid"
    with open_frames(root / "bbaf2n.mpg") as reader:
        first = next(reader)
        landmarks = torch.from_numpy(read_landmarks(root / "bbaf2n_landmarks68.csv", reader.info.width,
                                                    reader.info.height))[None]  # fmt: skip
        tracker = FaceTracker(CFG)
        results = [tracker.initialise(first[None], landmarks)]
        for _, frame in zip(range(3), reader):
            results.append(tracker(frame[None]))
    assert first.shape == (3, 288, 360) and first.dtype == torch.float32
    capture = cv2.VideoCapture(str(root / "bbaf2n.mpg"))
    ok, image = capture.read()
    capture.release()
    assert ok
    recipe = torch.from_numpy(np.ascontiguousarray(image[..., ::-1])).permute(2, 0, 1)[None].float() / 255
    assert torch.equal(recipe[0], first)
    assert all(bool(r.success) for r in results) and len(results) == 4


def test_a_first_call_with_landmarks_or_a_clip_is_told_what_to_pass(clip):
    """Session 58's audit: ``tracker(frames0, landmarks0)`` (the start given to the call, as other trackers' modules
    take it) was "forward() takes 2 positional arguments but 3 were given", and a clip ``(B, T, C, H, W)`` (a video
    dataset's batch) was told its shape alone. Each names what to pass, and what it names tracks."""
    frames, lm = clip
    tracker = FaceTracker(CFG)
    with pytest.raises(TypeError, match=r"^FaceTracker's call takes the frames alone, got 2 arguments: start the "
                                        r"streams with tracker.initialise\(frames, landmarks_px\), then"):
        tracker(frames[:1], lm[None])
    with pytest.raises(ValueError, match=r"got \(1, 3, 3, 120, 160\) torch.float32 \(a clip \(B, T, C, H, W\)\? one "
                                         r"frame per stream per call: frames\[:, t\]\)$"):
        tracker.initialise(frames[None], lm[None])
    tracker.initialise(frames[None][:, 0], lm[None])
    assert bool(tracker(frames[None][:, 1]).success)


def test_landmarks_of_every_frame_of_a_clip_are_told_to_take_the_first_frames(clip):
    """The landmarks of a clip, ``(T, K, 2)`` for one stream (``GroundTruth.landmarks_px``, a detector run over every
    frame) or ``(T, B, K, 2)`` for ``B``, were told the shape alone, where ``torchface track`` tells such a file to
    take the first frame's set; ``(N, K, 2)`` may also be N faces of the one frame given, a stream each. The message
    names them, and what it names starts the streams."""
    frames, lm = clip
    per_frame = torch.stack([lm, lm + 1.0, lm + 2.0])  # (T, K, 2)
    with pytest.raises(ValueError, match=r"^landmarks_px must be \(B, K, 2\) with B = 1 \(one set per frame\), got "
                                         r"\(3, 68, 2\): a set per frame of a clip\? the first frame's, "
                                         r"landmarks_px\[:1\]; 3 faces in this frame\? a stream each, "
                                         r"frames\.expand\(3, -1, -1, -1\)$"):
        FaceTracker(CFG).initialise(frames[:1], per_frame)
    assert bool(FaceTracker(CFG).initialise(frames[:1], per_frame[:1]).success)
    assert FaceTracker(CFG).initialise(frames[:1].expand(3, -1, -1, -1), per_frame).success.all()
    two = per_frame[:, None].expand(-1, 2, -1, -1)  # (T, B, K, 2)
    with pytest.raises(ValueError, match=r"with B = 2 \(one set per frame\), got \(3, 2, 68, 2\): a set per frame\? "
                                         r"the first frame's, landmarks_px\[0\]$"):
        FaceTracker(CFG).initialise(frames[:1].expand(2, -1, -1, -1), two)
    assert FaceTracker(CFG).initialise(frames[:1].expand(2, -1, -1, -1), two[0]).success.all()
    # the frames of a clip given as the batch with the first frame's landmarks: "one set per frame" read as if a set
    # for each frame were wanted (each frame then a stream of its own, started afresh)
    with pytest.raises(ValueError, match=r"with B = 3 \(one set per frame\), got \(1, 68, 2\): the frames of one "
                                         r"video\? initialise takes its first, frames\[:1\], and each later frame is a "
                                         r"call of its own, tracker\(frames\[t : t \+ 1\]\); 3 streams of this face: "
                                         r"landmarks_px\.expand\(3, -1, -1\)$"):
        FaceTracker(CFG).initialise(frames, lm[None])
    tracker = FaceTracker(CFG)
    assert bool(tracker.initialise(frames[:1], lm[None]).success) and bool(tracker(frames[1:2]).success)


def test_another_landmark_set_is_named_and_openposes_70_told_to_keep_its_first_68(clip):
    """``initialise`` given OpenPose's ``(B, 70, 3)`` face keypoints (x, y, confidence; the 68 iBUG points, then the
    pupils) or WFLW's ``(B, 98, 2)`` said the shape alone. Each is named; what it names for OpenPose's starts."""
    frames, lm = clip
    openpose = torch.cat([torch.cat([lm, lm[36:38]]), torch.ones(70, 1)], -1)[None]  # (1, 70, 3)
    with pytest.raises(ValueError, match=r"got \(1, 70, 3\) \(OpenPose's 70 face points\? Its first 68 are the iBUG "
                                         r"points, in their order \(then the pupils\): landmarks_px\[:, :68, :2\]\)$"):
        FaceTracker(CFG).initialise(frames[:1], openpose)
    assert bool(FaceTracker(CFG).initialise(frames[:1], openpose[:, :68, :2]).success)
    with pytest.raises(ValueError, match=r"got \(1, 98, 2\) \(WFLW's 98 points\? The 68 iBUG / 300-W landmarks"):
        FaceTracker(CFG).initialise(frames[:1], torch.rand(1, 98, 2) * 100)


def test_an_iterator_of_frames_is_told_to_give_one_frame_per_call(clip, tmp_path):
    """A generator of frames, or ``open_frames``' reader itself, given to ``initialise`` or a step was told "got
    generator" (``FrameReader``) alone, where a list is told to stack it. It is told to give one frame per call (and
    what stacking them makes), and what it names tracks."""
    import numpy as np

    from torchface.io import open_frames

    frames, lm = clip
    np.save(tmp_path / "clip.npy", frames.permute(0, 2, 3, 1).numpy())
    said = (r"got {} \(an iterator of frames: one per call, next\(frames\)\[None\] of \(3, H, W\) frames; or "
            r"torch\.stack\(list\(frames\)\), one frame per stream\)$")
    tracker = FaceTracker(CFG)
    with pytest.raises(TypeError, match=said.format("generator")):
        tracker.initialise((f for f in frames[:1]), lm[None])  # type: ignore[arg-type]
    with open_frames(tmp_path / "clip.npy") as reader:
        with pytest.raises(TypeError, match=said.format("FrameReader")):
            tracker.initialise(reader, lm[None])  # type: ignore[arg-type]
        assert bool(tracker.initialise(next(reader)[None], lm[None]).success)
        with pytest.raises(TypeError, match=said.format("FrameReader")):
            tracker(reader)  # type: ignore[arg-type]
        assert bool(tracker(next(reader)[None]).success)


def test_a_choice_given_as_a_string_is_told_the_member_to_pass():
    """``TrackerConfig(solver="fast")`` was "solver must be a TrackSolver, got 'fast'" (``robust="huber"``: "got str"),
    and ``TrackSolver`` and ``TemplateConfig``, which docs/python-api.md names among the settings, did not import from
    ``torchface.tracker``. The member named is the one to pass, and it imports from where the message says."""
    from torchface.solver import RobustKind
    from torchface.tracker import Backend, TemplateConfig, TrackSolver

    for name, value, member in (("solver", "fast", "TrackSolver.FAST"), ("robust", "Huber", "RobustKind.HUBER"),
                                ("backend", "native", "Backend.NATIVE")):  # fmt: skip
        with pytest.raises(TypeError, match=rf"^{name} must be a \w+, got str '{value}' \(pass {member}, from "):
            TrackerConfig(**{name: value})
    with pytest.raises(TypeError, match=r"\(pass TrackSolver.FAST or TrackSolver.REFERENCE, from torchface.tracker\)"):
        TrackerConfig(solver="gauss-newton")
    config = TrackerConfig(solver=TrackSolver.FAST, robust=RobustKind.HUBER, backend=Backend.NATIVE,
                           template=TemplateConfig(enabled=False))  # fmt: skip
    assert config.robust is RobustKind.HUBER and not config.template.enabled


def test_results_become_the_csvs_rows_as_the_docs_say(clip):
    """docs/python-api.md, "Results and settings": ``result_rows`` and ``track_columns`` give a result's table in the
    CSV's columns, a failed stream's row finite with ``success`` 0; a list of results, or frame numbers of another
    count than the streams, were an AttributeError and torch.cat's "Sizes of tensors must match"."""
    import numpy as np

    from torchface.io import result_rows, track_columns

    frames, lm = clip
    tracker = FaceTracker(CFG)
    both = lm[None].repeat(2, 1, 1)
    both[1] = float("nan")  # stream 1 without a face: its start fails
    results = [tracker.initialise(frames[:1].expand(2, -1, -1, -1), both), tracker(frames[1:2].expand(2, -1, -1, -1))]
    r = results[-1]
    columns = track_columns(r.anim_names, r.facs_names, r.illumination_names)
    rows = np.concatenate([result_rows(r, [t] * 2, 25.0) for t, r in enumerate(results)])
    assert rows.shape == (4, len(columns)) and np.isfinite(rows[:, :-3]).all()
    table = dict(zip(columns, rows.T))
    assert table["success"].tolist() == [1, 0, 1, 0] and table["timestamp"].tolist() == [0, 0, 0.04, 0.04]
    assert table["pose_Tz"][2] == float(r.translation[0, 2]) and table["yaw_deg"][2] == float(r.ypr_deg[0, 0])
    with pytest.raises(TypeError, match=r"^result must be one step's TrackResult, got list"):
        result_rows(results, [0, 1], 25.0)
    with pytest.raises(ValueError, match=r"^frame_indices must give one frame index per stream \(2\), got 1$"):
        result_rows(r, [1], 25.0)
    for frame in (1.5, -1, float("nan")):  # (written as the row's frame and time without a word)
        with pytest.raises(ValueError, match=r"^frame_indices must be whole frame numbers >= 0, got "):
            result_rows(r, [0, frame], 25.0)
    assert result_rows(r, np.array([2.0, 3.0]), 25.0)[:, 0].tolist() == [2, 3]  # (whole floats, as the job's)
    for fps in (0.0, float("inf"), float("nan")):  # (inf passed "> 0": every timestamp 0)
        with pytest.raises(ValueError, match=r"^fps must be a finite number > 0 \(frames per second\), got"):
            result_rows(r, [0, 1], fps)
    with pytest.raises(TypeError, match=r"^fps must be a real number, got str '25'$"):
        result_rows(r, [0, 1], "25")


def test_landmarks_as_row_and_column_fail_saying_to_give_x_and_y(clip):
    """``(row, col)`` landmarks (a NumPy image's index order) cannot be told from a mirrored face before the fit:
    the stream fails for no pose, and its reason said "mirrored or seen from behind" alone. It names the order and
    the flip, and the flipped landmarks start."""
    frames, lm = clip
    result = FaceTracker(CFG).initialise(frames[:1], lm.flip(-1)[None])
    assert int(result.status) == FAILED and int(result.start_failure) == int(StartFailure.NO_POSE)
    reason = result.start_failure_reasons[0]
    assert reason is not None and "(row, col) ones give a mirrored face: landmarks.flip(-1)" in reason
    assert int(FaceTracker(CFG).initialise(frames[:1], lm.flip(-1).flip(-1)[None]).status) == CONVERGED


def test_normalised_face_mistakes_are_told_what_to_pass(clip):
    """The README's ``NormalisedFace(tracker.model)(frames1, tracker.state)`` given the tracker for its model, the
    state before ``initialise`` (None) or its arguments swapped was told the type alone; each says what to pass, and
    what it says gives the face."""
    frames, lm = clip
    tracker = FaceTracker(CFG)
    with pytest.raises(TypeError, match=r"^model must be a FaceModel, got FaceTracker: pass its model, tracker.model$"):
        NormalisedFace(tracker)  # type: ignore[arg-type]
    normaliser = NormalisedFace(tracker.model)
    with pytest.raises(TypeError, match=r"got NoneType: tracker.state is None until tracker.initialise\(...\)$"):
        normaliser(frames[:1], tracker.state)  # type: ignore[arg-type]
    tracker.initialise(frames[:1], lm[None])
    with pytest.raises(TypeError, match=r"got Tensor: the frames come first, normaliser\(frames, tracker.state\)$"):
        normaliser(tracker.state, frames[:1])  # type: ignore[arg-type]
    assert normaliser(frames[:1], tracker.state).image.shape == (1, 3, 128, 128)


def test_normalised_face_given_the_tracker_for_its_state_is_told_to_pass_the_state(clip):
    """``NormalisedFace(model)(frames, tracker)``, the tracker where its state goes (session 63's Python-API audit),
    was told "estimate must be a TrackResult or a TrackerState, got FaceTracker" alone, before ``initialise`` and
    after; it names ``tracker.state``, which gives the face."""
    frames, lm = clip
    tracker = FaceTracker(CFG)
    normaliser = NormalisedFace(tracker.model)
    message = r"^estimate must be a TrackResult or a TrackerState, got FaceTracker: pass its state, " \
              r"normaliser\(frames, tracker.state\)$"  # fmt: skip
    with pytest.raises(TypeError, match=message):
        normaliser(frames[:1], tracker)  # type: ignore[arg-type]
    tracker.initialise(frames[:1], lm[None])
    with pytest.raises(TypeError, match=message):
        normaliser(frames[:1], tracker)  # type: ignore[arg-type]
    assert normaliser(frames[:1], tracker.state).image.shape == (1, 3, 128, 128)


def test_landmarks_far_too_large_fail_the_start_and_the_next_step_runs(clip):
    """Landmarks in the wrong unit, 255 times too large (a 0-255 scale taken for pixels), gave the automatic pyramid
    7 levels on 160x120 frames, more than the step's least crop (64 pixels) can make: the start failed as it should
    (OUTSIDE_FRAME), and the next step failed deep inside ("images must be (B, C, H, W) with H, W >= 3, got (1, 1, 2,
    2)"). The pyramid stops where that crop does; the stream is LOST as any failed start is."""
    from torchface.tracker import pyramid_for_faces
    from torchface.tracker.step import MIN_CROP_PX

    frames, lm = clip
    tracker = FaceTracker(CFG)
    first = tracker.initialise(frames[:1], lm[None] * 255)
    assert int(first.status) == FAILED and int(first.start_failure) == int(StartFailure.OUTSIDE_FRAME)
    levels = tracker.state.num_levels
    assert levels == 6 and MIN_CROP_PX >= 3 * 2 ** (levels - 2)
    assert int(tracker(frames[1:2]).status) == LOST
    big = torch.tensor([[[0.0, 0.0], [3000.0, 3000.0]]])  # (a face that large in 8K frames still gets its levels)
    assert pyramid_for_faces(CFG, big, (4320, 7680)).num_levels == 6


def test_many_levels_asked_for_a_tiny_face_fail_its_start_without_a_crash():
    """``TrackerConfig(num_levels=8)`` asked for (not the automatic pyramid, which stops at 6) with a face a tenth of
    its size: the start's crop was 128 pixels, whose 7th halving left 1 pixel, and ``initialise`` raised inside the
    pyramid ("H, W >= 3, got (1, 1, 2, 2)"). The crop now keeps 3 pixels at the last halving: the start fails as
    for any face that small (FAILED, narrower than ``min_face_width_px``) and the next step is LOST."""
    frames, lm, _ = sideways_clip(640, 480, 2)
    tiny = (lm - lm.mean(0)) * 0.1 + lm.mean(0)
    tracker = FaceTracker(TrackerConfig(num_levels=8, iterations=(3,) * 8), refine_first=None, pyramid="config")
    first = tracker.initialise(frames[:1], tiny[None])
    assert int(first.status) == FAILED and int(first.start_failure) == int(StartFailure.FACE_TOO_SMALL)
    assert tracker.state.num_levels == 8 and int(tracker(frames[1:2]).status) == LOST


def test_a_stream_may_take_gray_and_rgb_frames_at_its_online_start():
    """Frames are ``(B, 3, H, W)`` RGB or ``(B, 1, H, W)`` gray at every call (docs/python-api.md; a stream keeps its
    size and batch, nothing more). A stream started on RGB frames and stepped on gray ones (or the other way round)
    crashed at the online start's re-anchoring, where its first frame and its keyframe were stacked: torch.stack's
    "expects each tensor to be equal size". Both are made gray there, as the refinement makes them: the run
    re-anchors and follows the turn as the same frames all given gray do."""
    from torchface.appearance.sampling import to_gray
    from torchface.geometry.so3 import geodesic_angle_deg
    from torchface.synth import render_sequence
    from torchface.tracker.lookahead import LookaheadConfig

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from _helpers import candide_spec

    yaw = [0.0, 6.0, 12.0, 12.0]
    rgb, gt = render_sequence(candide_spec("turn", [[y, 0.0, 0.0] for y in yaw], [[0.0, 0.0, 450.0]] * 4, W, H))
    gray, lm = to_gray(rgb), gt.landmarks_px[:1].float()
    la = LookaheadConfig(iterations=(4, 3), max_points=800)

    def run(first: torch.Tensor, rest: torch.Tensor) -> tuple[FaceTracker, list]:
        tracker = FaceTracker(CFG, refine_first=la)
        results = [tracker.initialise(first[:1], lm)] + [tracker(rest[i : i + 1]) for i in range(1, len(yaw))]
        return tracker, results

    _, same = run(gray, gray)
    for first, rest in ((rgb, gray), (gray, rgb)):
        tracker, results = run(first, rest)
        ms = tracker.state.management
        assert ms.first is None and ms.head_rotation is not None  # (re-anchored: the wait is over)
        assert all(bool(r.success) for r in results)
        for r, s in zip(results, same):
            assert float(geodesic_angle_deg(r.rotation, s.rotation)) < 0.05


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_half_precision_landmarks_are_warned_of_once_per_call_and_fitted_as_given(clip, dtype):
    """Landmarks in bfloat16 (a network's under ``torch.autocast``) or float16 are rounded to their few significant
    bits (bfloat16: 0.5 px steps from 64 px, 1 px from 128, 2 px from 256) before torchface sees them, and were fitted
    1-2 px off without a word by ``initialise``, the landmark fit and the look-ahead. Each warns, once per call
    (``FaceTracker.initialise`` checks them in several places), saying to pass float32, and fits them as given: the
    result is that of their exact float32 values. float32 landmarks are not warned of."""
    from torchface.geometry import Intrinsics
    from torchface.tracker import fit_landmarks, initialise

    frames, lm = clip
    half = lm[None].to(dtype)
    assert not torch.equal(half.float(), lm[None])  # (rounded: the clip's points are not all on its grid)
    said = rf"^landmarks_px are {re.escape(str(dtype))}, which rounds pixel coordinates to steps of 0\.5 px from "
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = FaceTracker(CFG, refine_first=None).initialise(frames[:1], half)
    assert len(caught) == 1 and re.match(said, str(caught[0].message)), [str(w.message) for w in caught]
    assert "pass float32 landmarks" in str(caught[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (float32: not warned of)
        want = FaceTracker(CFG, refine_first=None).initialise(frames[:1], half.float())
    assert torch.equal(got.rotation, want.rotation) and torch.equal(got.translation, want.translation)
    model = FaceTracker(CFG).model
    for call in (lambda: fit_landmarks(model, half, Intrinsics.default(W, H)),
                 lambda: initialise(model, CFG, frames[:1], half, Intrinsics.default(W, H))):  # fmt: skip
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            call()
        assert len(caught) == 1 and re.match(said, str(caught[0].message))


def test_a_frame_divided_by_255_twice_mid_stream_is_told_where_its_stream_is_lost(clip):
    """A frame divided by 255 twice (a preprocessing bug: values in [0, 1 / 255], inside the range the steps check)
    made the stream LOST without a word, as a black frame does. Where a stream is lost at such a frame, a warning
    (naming the caller's line) says that its values are about 255 times less than its face's when it started and asks
    whether it was divided by 255 twice. A black frame, an 8-bit black frame (values multiples of 1/255), a dark
    frame and a frame like the others are not told so; the tracking is the same with or without the warning."""
    frames, lm = clip
    tracker = FaceTracker(CFG, refine_first=None)
    tracker.initialise(frames[:1], lm[None])
    for frame in (torch.zeros_like(frames[1:2]), torch.full_like(frames[1:2], 1 / 255), frames[1:2] * 0.02,
                  frames[1:2]):  # fmt: skip
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            copy.deepcopy(tracker)(frame)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        quiet = copy.deepcopy(tracker)(frames[1:2] / 255)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = tracker(frames[1:2] / 255)
    assert int(result.status) == LOST and torch.equal(result.rotation, quiet.rotation)
    said = [w for w in caught if "divided by 255 twice" in str(w.message)]
    assert len(said) == 1 and said[0].filename == __file__, [str(w.message) for w in caught]
    assert re.match(r"^stream 0 is lost at this frame: its frame's values reach 0\.00\d+, about \d+ times less than "
                    r"its face's when it started \(up to 0\.\d+\): divided by 255 twice\? Frames are float in \[0, 1\], 8-bit ones "
                    r"divided by 255 once$", str(said[0].message)), str(said[0].message)  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:  # (lost already: said once, at the loss)
        warnings.simplefilter("always")
        tracker(frames[2:3] / 255)
    assert not [w for w in caught if "divided by 255 twice" in str(w.message)]
