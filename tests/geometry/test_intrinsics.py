"""Tests for torchface.geometry.camera.Intrinsics."""

from __future__ import annotations

import dataclasses
import re
import warnings

import numpy as np
import pytest
import torch

from torchface.geometry import Intrinsics, project_points, unproject


def test_default_intrinsics_follow_the_conventions() -> None:
    cam = Intrinsics.default(640, 480)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (640.0, 640.0, 319.5, 239.5)
    assert cam.size == (480, 640)
    assert Intrinsics.default(480, 640).fx == 640.0
    K = cam.matrix(dtype=torch.float64)
    assert K.dtype == torch.float64
    torch.testing.assert_close(K, torch.tensor([[640.0, 0, 319.5], [0, 640.0, 239.5], [0, 0, 1]], dtype=torch.float64))


def test_scaled_intrinsics_keep_pixel_centres() -> None:
    cam = Intrinsics.default(640, 480)
    half = cam.scaled(0.5)
    assert (half.width, half.height, half.fx, half.cx, half.cy) == (320, 240, 320.0, 159.5, 119.5)
    # A 3D point lands on the same place of the image in both resolutions (pixel edges scale).
    pts = torch.tensor([[[40.0, -25.0, 500.0]]], dtype=torch.float64)
    uv, uv_half = project_points(pts, cam), project_points(pts, half)
    torch.testing.assert_close((uv_half + 0.5) * 2.0 - 0.5, uv)
    torch.testing.assert_close(unproject(uv_half, pts[..., 2], half), pts)


@pytest.mark.parametrize("factor", [-1.0, 0.0, float("nan"), float("inf")])
def test_scaled_refuses_a_factor_that_is_not_a_positive_size(factor: float) -> None:
    """A negative or zero factor gave a 1x1 camera without a word; NaN and inf an int conversion's error."""
    with pytest.raises(ValueError, match="factor must be a positive finite number"):
        Intrinsics.default(640, 480).scaled(factor)


def test_intrinsics_validation_and_frozen() -> None:
    with pytest.raises(ValueError, match="image size"):
        Intrinsics(0, 480, 500.0, 500.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="focal"):
        Intrinsics(640, 480, -1.0, 500.0, 0.0, 0.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        Intrinsics.default(640, 480).fx = 1.0  # type: ignore[misc]
    # Sizes are stored as ints (32.0 used to be kept and failed later inside the rasterizer); the rest must be
    # finite numbers (a NaN centre made every projection NaN and the rasterizer silently empty).
    cam = Intrinsics(32.0, 24, 32, 32.0, 15.5, 11.5)
    assert type(cam.width) is int and cam.width == 32 and type(cam.fx) is float
    for bad in ("32", 32.5, True):
        with pytest.raises(TypeError, match="whole number"):
            Intrinsics(bad, 24, 32.0, 32.0, 15.5, 11.5)
    for k, bad in ((2, float("inf")), (4, float("nan")), (5, torch.tensor(float("nan")))):
        args = [32, 24, 32.0, 32.0, 15.5, 11.5]
        args[k] = bad
        with pytest.raises(ValueError, match="finite number"):
            Intrinsics(*args)
    with pytest.raises(TypeError, match="cy must be a number"):
        Intrinsics(32, 24, 32.0, 32.0, 15.5, "11.5")
    # Entries of a calibration tensor work as before (a focal length that requires grad keeps it).
    K = torch.tensor([[50.0, 0.0, 15.5], [0.0, 50.0, 11.5], [0.0, 0.0, 1.0]], requires_grad=True)
    cam = Intrinsics(torch.tensor(32), 24, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    assert cam.width == 32 and cam.fx.requires_grad
    # ... and so does the matrix made from them: it was rebuilt with torch.tensor(), detached (with only a warning).
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = cam.matrix(torch.float64)
    assert back.dtype == torch.float64 and back.requires_grad
    torch.testing.assert_close(back, K.detach().double(), rtol=0, atol=0)
    back.sum().backward()
    torch.testing.assert_close(K.grad, torch.tensor([[1.0, 0, 1], [0, 1, 1], [0, 0, 0]]), rtol=0, atol=0)


def test_default_checks_the_size_as_the_constructor_does() -> None:
    """``Intrinsics.default(320.5, 240)`` took int(320.5) = 320 pixels with the centre of a 320.5-pixel image
    (159.75), where the constructor refuses 320.5; ``default("320", 240)`` failed in max() ("'>' not supported
    between instances of 'int' and 'str'")."""
    for bad in (320.5, "320", True):
        with pytest.raises(TypeError, match="width must be a whole number"):
            Intrinsics.default(bad, 240)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="image size"):
        Intrinsics.default(320, 0)
    with pytest.raises(TypeError, match="focal must be a number"):
        Intrinsics.default(320, 240, "500")  # type: ignore[arg-type]
    cam = Intrinsics.default(320.0, np.int64(240), 400)
    assert (cam.width, cam.height, cam.fx, cam.cx, cam.cy) == (320, 240, 400.0, 159.5, 119.5)
    assert type(cam.width) is int and Intrinsics.default(640, 480) == Intrinsics(640, 480, 640.0, 640.0, 319.5, 239.5)


def test_from_matrix_reads_opencvs_calibration_matrix_and_refuses_what_no_camera_is() -> None:
    """``Intrinsics`` takes ``fx, fy, cx, cy``; OpenCV's matrix reads ``fx, cx`` / ``fy, cy`` row by row, and passing
    its entries in that order was caught only by chance (a size check). ``from_matrix`` reads the matrix (a list, an
    array, a tensor; a tensor's graph kept) and refuses what is no calibration matrix, saying what it likely is."""
    K = [[600.0, 0.0, 321.0], [0.0, 590.0, 239.0], [0.0, 0.0, 1.0]]
    expected = Intrinsics(640, 480, 600.0, 590.0, 321.0, 239.0)
    assert Intrinsics.from_matrix(K, 640, 480) == expected
    assert Intrinsics.from_matrix(np.array(K), 640, 480) == expected
    assert Intrinsics.from_matrix(torch.tensor(K, dtype=torch.float32), 640, 480) == expected
    Kt = torch.tensor(K, requires_grad=True)
    cam = Intrinsics.from_matrix(Kt, 640, 480)
    cam.matrix(torch.float32).sum().backward()
    torch.testing.assert_close(Kt.grad, torch.tensor([[1.0, 0, 1], [0, 1, 1], [0, 0, 0]]), rtol=0, atol=0)
    cases = [
        (np.array(K).T, r"^matrix's last row must be \(0, 0, 1\), got \(321, 239, 1\): the transpose of a "
                        r"calibration matrix \(cx, cy = 321, 239 in its last row\)\? Pass K.T$"),
        (np.array(K) * 2, r"^matrix's last row .*got \(0, 0, 2\): a matrix scaled by 2\? Pass K / K\[2, 2\]$"),
        (np.hstack([K, [[0.0], [0.0], [0.0]]]), r"^matrix must be 3x3, got shape \(3, 4\) \(a 3x4 projection matrix"),
        (torch.tensor(K)[None], r"^matrix must be 3x3, got shape \(1, 3, 3\) \(a batch of matrices\? An Intrinsics is "
                                r"one camera"),
        ([[600.0, 2.0, 321.0], [0.0, 590.0, 239.0], [0.0, 0.0, 1.0]], r"^matrix must have no skew .*got K\[0, 1\] = 2"),
        ([[600.0, 0.0, float("nan")], [0.0, 590.0, 239.0], [0.0, 0.0, 1.0]], "^matrix must be finite"),
    ]
    for bad, message in cases:
        with pytest.raises(ValueError, match=message):
            Intrinsics.from_matrix(bad, 640, 480)
    with pytest.raises(TypeError, match="matrix must be a 3x3 calibration matrix"):
        Intrinsics.from_matrix("K", 640, 480)
    with pytest.raises(TypeError, match="matrix must hold real numbers, got bool"):  # (was read as 0 / 1)
        Intrinsics.from_matrix(np.array(K) > 1, 640, 480)
    # float32 arithmetic's rounding of the last row (K / K[2, 2] computed in float32) is the calibration it rounds
    rounded = np.array(K, dtype=np.float64)
    rounded[2] = [1e-10, -1e-10, np.float32(1) - np.finfo(np.float32).eps / 2]
    assert Intrinsics.from_matrix(rounded, 640, 480) == expected
    with pytest.raises(TypeError, match=r"width must be a whole number of pixels, got 600.5 \(Intrinsics takes width, "
                                        r"height, fx, fy, cx, cy in this order; from a 3x3 calibration matrix"):
        Intrinsics(600.5, 590.5, 321.0, 239.0, 640, 480)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "given, said",
    [
        ((600.0, 319.5, 600.0, 239.5), r"OpenCV's matrix order \(fx, cx, fy, cy\).*Likely meant: Intrinsics\(640, 480, "
                                       r"fx=600, fy=600, cx=319.5, cy=239.5\)"),
        ((319.5, 239.5, 600.0, 600.0), r"focal lengths and the principal point swapped.*Likely meant: Intrinsics\(640, "
                                       r"480, fx=600, fy=600, cx=319.5, cy=239.5\)"),
        ((0.9, 1.2, 0.5, 0.5), r"normalised intrinsics.*Likely meant: Intrinsics\(640, 480, fx=576, fy=576, "
                               r"cx=319.5, cy=239.5\)"),
        ((600.0, 600.0, 0.0, 0.0), r"principal point at the top-left pixel: a transposed K read .* a centred camera's "
                                   r"principal point \(319.5, 239.5\)"),
        ((1000.0, 400.0, 319.5, 239.5), r"are implausible \(fx more than 1.25 times fy or fy more than 2 times fx"),
        ((400.0, 900.0, 319.5, 239.5), r"are implausible \(fx more than 1.25 times fy"),  # wide pixels: over 2
        ((300.0, 300.0, 1300.0, 240.0), r"are implausible .*or the frame's centre more than 2 focal lengths from the "
                                         r"principal point\)"),  # (980 pixels off the centre: 73 degrees)
        ((600.0, 600.0, 640.0, 480.0), r"put the principal point at \(640, 480\), the frame's size: a centred camera's "
                                       r"principal point is \(319.5, 239.5\)"),
        ((1500.0, 1500.0, 959.5, 719.5), r"the camera of a 1920x1440 frame \(its centre the principal point\), not "
                                         r"scaled with these frames\? Likely meant: Intrinsics\(640, 480, fx=500, "
                                         r"fy=500, cx=319.5, cy=239.5\), intrinsics.scaled\(0.333333\)"),
        ((1200.0, 1200.0, 639.5, 479.5), r"the camera of a 1280x960 frame .* Likely meant: Intrinsics\(640, 480, "
                                         r"fx=600, fy=600, cx=319.5, cy=239.5\), intrinsics.scaled\(0.5\)"),  # (2x)
        ((600.0, 600.0, 319.5, 239.5), None),
        ((300.0, 300.0, 900.0, 240.0), None),  # a crop of a larger frame: its principal point off the crop (62 deg.)
        ((5000.0, 5000.0, -3000.0, 3500.0), None),  # a telephoto frame's crop, many crop widths off its centre
        ((1500.0, 1500.0, 1200.0, 719.5), None),  # off the frame, not a larger frame's centre (scales 3.75 and 3)
        ((900.0, 880.0, 100.0, 400.0), None),  # off-centre, inside the frame: plausible (crops of a sensor exist)
        ((300.0, 300.0, -0.5, 479.5), None),  # at the frame's corner pixel's edge
        ((1000.0, 850.0, 319.5, 239.5), None),  # pixels 1.18 from square: within PLAUSIBLE_ASPECT
        ((600.0 / 1.42, 600.0, 319.5, 239.5), None),  # PAL 16:9 DV's wide pixels (HDV's 4/3 too): were "implausible"
    ],
    ids=["opencv-order", "swapped", "normalised", "corner", "aspect", "wide-pixels-2", "far-outside", "size",
         "not-scaled", "not-scaled-2x", "centred", "crop", "telephoto-crop", "off-frame", "off-centre", "edge",
         "non-square", "anamorphic"],
)
def test_mixed_up_intrinsics_are_named_with_the_likely_fix(given, said) -> None:
    """A camera whose numbers read as a mix-up of the constructor's arguments (OpenCV's matrix order, the principal
    point and focal lengths swapped, normalised units, a transposed matrix's zeros) is named with the likely fix;
    implausible ones are named; plausible ones, off-centre principal points included, are not (nothing here is
    impossible: the tracker warns and tracks, test_user_inputs)."""
    from torchface.geometry.camera import mixed_up_intrinsics

    hint = mixed_up_intrinsics(Intrinsics(640, 480, *given))
    if said is None:
        assert hint is None
    else:
        assert hint is not None and re.search(said, hint), hint
    K = torch.tensor(float(given[0]), requires_grad=True)  # (a calibration being optimised: no word)
    assert mixed_up_intrinsics(Intrinsics(640, 480, K, *given[1:])) is None  # type: ignore[arg-type]


def test_a_principal_point_outside_the_frame_alone_is_a_crop_not_a_mix_up() -> None:
    """Every principal point outside the frame was "implausible": a crop of a larger frame, which keeps that frame's
    principal point, was warned of at each start. It is plausible unless the frame's centre lies more than
    PLAUSIBLE_OFF_AXIS (2) focal lengths from it; the mix-ups it told still are told (a square frame's focal
    lengths and principal point swapped: the principal point outside alone showed it)."""
    from torchface.geometry.camera import PLAUSIBLE_OFF_AXIS, mixed_up_intrinsics

    assert PLAUSIBLE_OFF_AXIS == 2.0
    hint = mixed_up_intrinsics(Intrinsics(480, 480, 239.5, 239.5, 600.0, 600.0))
    assert hint is not None and "swapped (cx, cy, fx, fy)? Likely meant: Intrinsics(480, 480, fx=600, fy=600, " \
        "cx=239.5, cy=239.5)" in hint, hint
    for cx, cy in ((-250.0, 100.0), (500.0, 400.0), (127.5 - 400.0, 127.5)):  # (the last: 2 focal lengths off)
        assert mixed_up_intrinsics(Intrinsics(256, 256, 200.0, 200.0, cx, cy)) is None, (cx, cy)
    assert "are implausible" in str(mixed_up_intrinsics(Intrinsics(256, 256, 200.0, 200.0, 127.5 - 401.0, 127.5)))
    # a principal point at cx = -0.5 (a crop's left edge at it) with cy outside: a ZeroDivisionError (the larger
    # frame's scale, 2 cx + 1 over W, divided by before it was tested)
    assert mixed_up_intrinsics(Intrinsics(640, 480, 600.0, 600.0, -0.5, -100.0)) is None
    assert "are implausible" in str(mixed_up_intrinsics(Intrinsics(640, 480, 600.0, 600.0, -0.5, 1500.0)))
    assert "are implausible" in str(mixed_up_intrinsics(Intrinsics(640, 480, 1.0, 1.0, -0.5, -0.5)))
    # the bottom-right quadrant of a calibrated 1280x960 camera (principal point (645.2, 472.8), a wide lens): its
    # principal point (5.2, -7.2) is a centred camera's near (0, 0) too, so that is not warned of (the docstring)
    assert mixed_up_intrinsics(Intrinsics(640, 480, 640.0, 640.0, 645.2 - 640, 472.8 - 480)) is None
    # a subnormal focal length, scaled to that larger frame's, is 0 (divided by: a ZeroDivisionError)
    assert "are implausible" in str(mixed_up_intrinsics(Intrinsics(1, 1, 5e-324, 1.0, 0.5, 0.5)))


def test_a_common_larger_frames_camera_of_another_shape_is_named_with_both_adaptations() -> None:
    """A 1920x1080 calibration (or ``Intrinsics.default(1920, 1080)``) given unchanged for 640x480 frames was not
    told: its principal point, that frame's centre, lies outside these frames, as a crop's camera's does, and the
    same-shape rule (a larger frame's centre at one scale along x and y) does not read 3 and 2.25. A common frame
    size's exact centre, with that frame's plausible focal lengths, is told with the cameras of its middle cut to
    4:3 and of it squeezed; a crop's principal point that is no common frame's centre still is not."""
    from torchface.geometry.camera import COMMON_FRAME_SIZES, mixed_up_intrinsics

    assert (1920, 1080) in COMMON_FRAME_SIZES and (1280, 720) in COMMON_FRAME_SIZES
    hint = mixed_up_intrinsics(Intrinsics(640, 480, 1920.0, 1920.0, 959.5, 539.5))  # (Intrinsics.default(1920, 1080))
    assert hint is not None and "the camera of a 1920x1080 frame (its centre the principal point), not adapted to " \
        "these frames of another shape? Cut from its middle and resized, they have Intrinsics(640, 480, fx=853.333, " \
        "fy=853.333, cx=319.5, cy=239.5); resized whole (squeezed), Intrinsics(640, 480, fx=640, fy=853.333, " \
        "cx=319.5, cy=239.5)" in hint, hint
    # the middle cut's camera is the one a centred cut and resize make of the larger frame's (scaled() agrees)
    cut = Intrinsics(1440, 1080, 1920.0, 1920.0, 959.5 - 240, 539.5).scaled(1 / 2.25)
    assert (cut.width, cut.height, round(cut.fx, 3), cut.cx, cut.cy) == (640, 480, 853.333, 319.5, 239.5)
    # the W / 2 convention's centre; a 1280x720 frame's, inside these frames (their right edge); portrait frames,
    # whose squeezed camera (pixels 1.33 times taller than wide) is itself implausible and not offered
    hint = str(mixed_up_intrinsics(Intrinsics(640, 480, 1800.0, 1800.0, 960.0, 540.0)))
    assert "the camera of a 1920x1080 frame" in hint and "cx=319.722, cy=239.722" in hint, hint
    hint = str(mixed_up_intrinsics(Intrinsics(640, 480, 1280.0, 1280.0, 639.5, 359.5)))
    assert "the camera of a 1280x720 frame" in hint and "fx=853.333, fy=853.333, cx=319.5, cy=239.5" in hint, hint
    hint = str(mixed_up_intrinsics(Intrinsics(480, 640, 1920.0, 1920.0, 539.5, 959.5)))
    assert "the camera of a 1080x1920 frame" in hint and "Intrinsics(480, 640, fx=853.333, fy=853.333, cx=239.5, " \
        "cy=319.5)" in hint and "squeezed" not in hint, hint
    for cx, cy in ((959.5, 539.6), (1199.5, 539.5), (959.5 - 100, 539.5 - 100)):  # no common frame's exact centre
        assert mixed_up_intrinsics(Intrinsics(640, 480, 1920.0, 1920.0, cx, cy)) is None, (cx, cy)
    # under twice the size (a 720x480 frame's centre: 40 pixels right of these frames'), or focal lengths no camera
    # of that frame has, are not told; the same shape is the unscaled rule's (test above)
    assert mixed_up_intrinsics(Intrinsics(640, 480, 700.0, 700.0, 359.5, 239.5)) is None
    assert "are implausible" in str(mixed_up_intrinsics(Intrinsics(640, 480, 1920.0, 1000.0, 959.5, 539.5)))
    hint = str(mixed_up_intrinsics(Intrinsics(640, 360, 1280.0, 1280.0, 639.5, 359.5)))
    assert "not scaled with these frames" in hint and "another shape" not in hint, hint


def test_the_mixed_up_warning_pickles_and_copies_with_its_camera() -> None:
    """``MixedUpIntrinsics`` holds its camera beside the message (``args``: the message alone), so the default pickle
    called ``MixedUpIntrinsics(message)``, a TypeError: a warning raised as an error (``-W error``) in a
    ``multiprocessing`` worker could not be sent back, nor could the warning be deep-copied."""
    import copy
    import pickle

    from torchface.geometry.camera import MixedUpIntrinsics

    camera = Intrinsics(640, 480, 600.0, 319.5, 600.0, 239.5)
    warning = MixedUpIntrinsics("intrinsics ... look mixed up", camera)
    warning.add_note("while initialising stream 3")  # (kept, as the default pickle keeps an exception's notes)
    for copied in (pickle.loads(pickle.dumps(warning)), copy.deepcopy(warning), copy.copy(warning)):
        assert type(copied) is MixedUpIntrinsics and str(copied) == str(warning) and copied.intrinsics == camera
        assert copied.args == warning.args and copied.__notes__ == ["while initialising stream 3"]


@pytest.mark.parametrize(
    "given, said",
    [
        (torch.tensor([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]]), r"Intrinsics.from_matrix\(K, width, height\)"),
        (np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]]), r"Intrinsics.from_matrix\(K, width, height\)"),
        ([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]], r"Intrinsics.from_matrix\(K, width, height\)"),
        ((600.0, 600.0, 319.5, 239.5), r"Intrinsics\(width, height, fx, fy, cx, cy\), in pixels"),
        ([640, 480, 600.0, 600.0, 319.5, 239.5], r"Intrinsics\(width, height, fx, fy, cx, cy\), in pixels"),
    ],
    ids=["tensor-K", "numpy-K", "list-K", "fx-fy-cx-cy", "size-and-numbers"],
)
def test_a_camera_given_as_a_matrix_or_numbers_is_told_how_to_make_intrinsics(given, said) -> None:
    """``initialise(frames, landmarks, intrinsics)`` given OpenCV's 3x3 ``cameraMatrix`` or a tuple of the camera's
    numbers (session 63's Python-API audit) was told "intrinsics must be torchface.geometry.Intrinsics, got Tensor"
    alone; it names the constructor that makes one of them, and that constructor makes the camera."""
    from torchface.geometry._checks import check_intrinsics

    with pytest.raises(TypeError, match=r"^intrinsics must be torchface.geometry.Intrinsics, got \w+ \(.*" + said):
        check_intrinsics(given)
    if np.shape(np.asarray(given)) == (3, 3):
        cam = Intrinsics.from_matrix(given, 640, 480)
    else:
        cam = Intrinsics(640, 480, *[float(v) for v in list(given)[-4:]])
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (600.0, 600.0, 319.5, 239.5)
    with pytest.raises(TypeError, match=r"^intrinsics must be torchface.geometry.Intrinsics, got NoneType$"):
        check_intrinsics(None)  # (nothing to say of another type)


def test_matrix_device_is_checked_as_every_device_torchface_takes():
    """Intrinsics.matrix(device="gpu0") was torch's RuntimeError "Invalid device string", and device="meta" a
    matrix without values; check_device's ValueError names the device and the devices here."""
    K = Intrinsics.default(64, 48)
    for device in ("gpu0", "meta"):
        with pytest.raises(ValueError, match=f"'{device}'.*devices here: cpu"):
            K.matrix(device=device)
    assert torch.equal(K.matrix(device="cpu"), K.matrix())
    assert K.matrix(torch.float64, torch.device("cpu")).dtype == torch.float64
