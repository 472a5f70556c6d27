"""A :class:`FaceModel` as one file: :func:`save_face_model` writes it, :func:`load_face_model` reads it back.

The file is a numpy ``.npz`` archive (read with ``allow_pickle=False``: nothing in it is executed) holding

- ``format``: the text :data:`FORMAT` and ``format_version``: an integer, :data:`FORMAT_VERSION` when written by this
  version (a file of a later version is refused: its fields may mean something else);
- ``name``: the model's name;
- every tensor of the :class:`FaceModel` under its field's name (``mean``, ``faces``, ``shape_units``,
  ``animation_units``, ``animation_ranges``, ``landmark_vertices``, ``landmark_weights``, ``facs_matrix``,
  ``surface_vertex_mask``), floating ones in the model's dtype (``bfloat16``, which numpy lacks, as ``float32``: every
  value exact), and every name tuple (``shape_names``, ``animation_names``, ``landmark_names``, ``facs_names``) as a
  1-D array of text.

So a model saved and loaded in its own dtype is the same to the bit, and one saved in ``float64`` and loaded in
``float32`` is rounded once, as :func:`~torchface.model.load_candide3` and :func:`~torchface.model.load_mesh_model`
round their ``float64`` arithmetic: ``load_face_model(p)`` of ``save_face_model(load_candide3(dtype=torch.float64),
p)`` equals ``load_candide3()`` to the bit. ``torchface track --model FILE`` (:class:`torchface.job.JobConfig`'s
``model``) tracks with such a file.

Entries of other names are left unread (a later version that adds one without changing what these mean keeps the
format version).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchface._device import check_device
from torchface.io.errors import InputError, OutputError
from torchface.model.face_model import FaceModel
from torchface.model.mesh_loader import _check_blendshape_size, _check_displacements, _check_surface

__all__ = ["FORMAT", "FORMAT_VERSION", "face_model_digest", "load_face_model", "save_face_model"]

#: What the ``format`` entry of a face model file says.
FORMAT: str = "torchface FaceModel"

#: The format version this version writes, and the latest it reads.
FORMAT_VERSION: int = 1

#: The name-tuple fields of :class:`FaceModel`.
_NAMES = ("shape_names", "animation_names", "landmark_names", "facs_names")

#: The tensor fields of :class:`FaceModel` and the numpy kinds the file may hold them in (``f`` floating,
#: ``iu`` integer, signed or not: a mesh's indices are often ``uint32``; ``b`` bool).
_TENSORS = {
    "mean": "f", "faces": "iu", "shape_units": "f", "animation_units": "f", "animation_ranges": "f",
    "landmark_vertices": "iu", "landmark_weights": "f", "facs_matrix": "f", "surface_vertex_mask": "b",
}  # fmt: skip


#: The entries this version reads (those it writes); an entry of another name is left unread, as the module says (an
#: entry a later version adds, of any kind, does not refuse the file: an object array did, "cannot be loaded when
#: allow_pickle=False").
_ENTRIES = frozenset({"format", "format_version", "name", *_NAMES, *_TENSORS})


def _check_arrays(
    arrays: dict[str, np.ndarray], names: dict[str, tuple[str, ...]], name: str, said: str, ask: str
) -> None:
    """The checks :func:`load_face_model` makes of a file's ``arrays`` (``names``: its name tuples) beyond
    :class:`FaceModel`'s own, and :func:`save_face_model` of the arrays it will write: no basis entry a whole mesh
    (:func:`~torchface.model.mesh_loader._check_displacements`), the blendshapes' size for the mesh's span (a
    warning), and the surface (the winding, the span, the iBUG-68 layout: ``name``, ``said`` and ``ask`` word its
    messages, :func:`~torchface.model.mesh_loader._check_surface`). Warnings name the caller of the function that
    calls this."""
    mean = np.asarray(arrays["mean"], dtype=np.float64)
    faces = arrays["faces"].astype(np.int64)
    for key, named in (("animation_units", "animation_names"), ("shape_units", "shape_names")):
        _check_displacements(np.asarray(arrays[key], dtype=np.float64), names[named], mean, key)
    _check_blendshape_size(np.asarray(arrays["animation_units"], dtype=np.float64),
                           np.asarray(arrays["animation_ranges"], dtype=np.float64), names["animation_names"], mean,
                           faces, "mm", stacklevel=4)  # fmt: skip
    _check_surface(mean, faces, arrays["landmark_vertices"].astype(np.int64),
                   np.asarray(arrays["landmark_weights"], dtype=np.float64), name, said, ask, stacklevel=4)


def _array(value: torch.Tensor) -> np.ndarray:
    """A tensor as the file holds it: on the CPU, ``bfloat16`` as ``float32`` (exact)."""
    value = value.detach().cpu()
    return (value.float() if value.dtype == torch.bfloat16 else value).numpy()


def save_face_model(model: FaceModel, path: str | os.PathLike[str]) -> None:
    """Write ``model`` to ``path`` (the file format of this module; the name is used as given, ``.npz`` is not added).

    The model is first checked as :func:`load_face_model` checks the file's (no basis entry a whole mesh, the
    triangles wound consistently and outward with the face toward ``-z``; warnings for a span outside 50 mm - 2 m,
    blendshapes of an implausible size for it and 68 landmarks not laid out as the iBUG-68 points), so a model it
    would refuse is not written (it was, and was refused only by ``torchface track --model``). The file is written
    under a temporary name beside ``path`` and renamed when complete.

    Args:
        model: the :class:`FaceModel`, of any dtype and device.
        path: the file to write (replaced if there).

    Raises:
        TypeError: ``model`` is not a :class:`FaceModel`.
        ValueError: a name ends in a NUL character (numpy's text arrays drop it: it would not read back), or the
            model fails a check above (:func:`load_face_model` would refuse the file); nothing is written.
        OutputError: the file cannot be written.

    Warns:
        UserWarning: as :func:`load_face_model` warns when the file is read.

    Example:
        >>> import tempfile
        >>> from torchface.model import load_candide3
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     path = Path(folder) / "candide3.npz"
        ...     save_face_model(load_candide3(dtype=torch.float64), path)
        ...     torch.equal(load_face_model(path).mean, load_candide3().mean)
        True
    """
    if not isinstance(model, FaceModel):
        raise TypeError(f"model must be a FaceModel, got {type(model).__name__}")
    arrays: dict[str, Any] = {"format": np.array(FORMAT), "format_version": np.array(FORMAT_VERSION)}  # (Any: savez)
    for f in fields(model):
        value = getattr(model, f.name)
        if isinstance(value, torch.Tensor):
            arrays[f.name] = _array(value)
        else:
            texts = (value,) if f.name == "name" else value
            bad = [t for t in texts if t.endswith("\0")]
            if bad:  # (which one: a model has dozens of names)
                raise ValueError(f"{f.name}: {bad[0]!r} ends in a NUL character, which the file cannot keep (numpy's "
                                 "text arrays drop it)")  # fmt: skip
            arrays[f.name] = np.array(value) if f.name == "name" else np.array(list(value), dtype=np.str_)
    # load_face_model's checks, on the values the file will hold, before anything is written (a model wound inward
    # was written, and refused only when torchface track read it)
    try:
        _check_arrays(arrays, {key: getattr(model, key) for key in _NAMES}, model.name, "in the model",
                      "is the model in millimetres (torchface.conventions)?")  # fmt: skip
    except ValueError as exc:
        raise ValueError(f"the model {model.name!r} is not saved: load_face_model would refuse it: {exc}") from None
    target = Path(path)
    tmp = target.with_name(target.name + ".partial")
    try:
        with open(tmp, "wb") as out:  # (a file object: np.savez would add .npz to a name without it)
            np.savez(out, **arrays)
        os.replace(tmp, target)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"{target}: cannot write the face model ({exc.strerror or exc})") from None


def _read(p: Path) -> dict[str, np.ndarray]:
    """The arrays of face model file ``p``, checked for its format, version, entries and their kinds and ranks."""
    if not p.is_file():
        raise InputError(f"{p}: {'a folder, not a face model file' if p.is_dir() else 'no such face model file'}")
    not_one = f"{p}: not a torchface face model file (torchface.model.save_face_model writes one)"
    try:
        with open(p, "rb") as f:  # (np.load of a path left it open when the archive was damaged)
            magic = f.read(6)
            f.seek(0)
            if magic == b"\x93NUMPY":
                raise InputError(f"{not_one}: one .npy array")
            if not magic.startswith(b"PK"):  # (np.load took any other file for a pickle, and said so)
                raise InputError(f"{not_one}: not an .npz archive")
            with np.load(f, allow_pickle=False) as data:  # (this version's entries: a later one's are left unread)
                arrays = {k: data[k] for k in data.files if k in _ENTRIES}
    except (InputError, MemoryError):
        raise
    # (a damaged archive: BadZipFile, EOFError, ValueError; a damaged compressed one, np.savez_compressed's, also
    # zlib.error, NotImplementedError or tokenize's TokenError: they came out bare)
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{not_one}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    # (an array of the other byte order, as a big-endian machine writes it: torch refused it, a bare ValueError)
    arrays = {k: v.astype(v.dtype.newbyteorder("="), copy=False) for k, v in arrays.items()}
    fmt = arrays.get("format")
    if fmt is None or fmt.dtype.kind != "U" or fmt.shape != () or str(fmt) != FORMAT:
        raise InputError(f"{not_one}: its format entry is missing or not {FORMAT!r}")
    version = arrays.get("format_version")
    if version is None or version.shape != () or version.dtype.kind not in "iu":
        raise InputError(f"{p}: a damaged face model file: its format_version is missing or not an integer")
    if int(version) > FORMAT_VERSION:
        raise InputError(f"{p}: a face model file of format version {int(version)}, written by a later torchface; "
                         f"this one reads up to version {FORMAT_VERSION}: upgrade torchface")  # fmt: skip
    if int(version) < 1:
        raise InputError(f"{p}: a damaged face model file: format_version {int(version)}")
    missing = sorted({"name", *_NAMES, *_TENSORS} - set(arrays))
    if missing:
        raise InputError(f"{p}: a damaged face model file: it lacks {', '.join(missing)}")
    for key in ("name", *_NAMES):
        rank = 0 if key == "name" else 1
        if arrays[key].ndim != rank or (arrays[key].dtype.kind != "U" and arrays[key].size):
            raise InputError(f"{p}: a damaged face model file: {key} is not {'a text' if rank == 0 else 'texts'}")
    for key, kind in _TENSORS.items():
        if arrays[key].dtype.kind not in kind:
            raise InputError(f"{p}: a damaged face model file: {key} holds {arrays[key].dtype}, not "
                             f"{ {'f': 'floating', 'iu': 'integer', 'b': 'bool'}[kind]} values")  # fmt: skip
    return arrays


def load_face_model(
    path: str | os.PathLike[str],
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> FaceModel:
    """Read a :class:`FaceModel` that :func:`save_face_model` wrote.

    The model is checked as :func:`~torchface.model.load_mesh_model` checks one: :class:`FaceModel`'s own checks
    (shapes, finite values, landmark weights, indices), no basis entry a whole mesh rather than a displacement, the
    triangles wound consistently and outward with the face toward ``-z``, and (warnings) a span of 50 mm - 2 m,
    blendshapes of a plausible size for it and, for 68 landmarks, the iBUG-68 layout.

    Args:
        path: the file.
        dtype: floating dtype of the model tensors (the file's values rounded to it once; index and mask tensors are
            ``int64`` and ``bool``).
        device: device of the model tensors.

    Returns:
        The model, with the file's name.

    Raises:
        TypeError: ``dtype`` is not a floating ``torch.dtype``.
        ValueError: ``device`` is not a device this machine has (the message lists those it has).
        InputError: (a ``ValueError``) the file is missing, is not a face model file, is one of a later format
            version, is damaged (an entry missing or of the wrong kind), or its model fails a check above.

    Warns:
        UserWarning: as :func:`~torchface.model.load_mesh_model`: a span outside 50 mm - 2 m, blendshapes that move
            the mesh implausibly little or much for its span, or 68 landmarks not laid out as the iBUG-68 points.
    """
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise TypeError(f"dtype must be a floating torch.dtype, got {dtype}")
    device = check_device(device)  # (before the file is read; "cuda" without CUDA was an AssertionError)
    p = Path(path)
    arrays = _read(p)
    names = {key: tuple(str(n) for n in arrays[key]) for key in _NAMES}
    values: dict[str, object] = {"name": str(arrays["name"]), **names}
    for key, kind in _TENSORS.items():
        as_type = {"f": dtype, "iu": torch.int64, "b": torch.bool}[kind]
        values[key] = torch.as_tensor(np.ascontiguousarray(arrays[key]), dtype=as_type, device=device)
    try:
        model = FaceModel(**values)  # type: ignore[arg-type]
        _check_arrays(arrays, names, f"{p} ({model.name})", "in the model file",
                      "was the model saved in millimetres (torchface.conventions)?")  # fmt: skip
    except (ValueError, TypeError) as exc:
        raise InputError(f"{p}: {exc}") from None
    return model


def face_model_digest(model: FaceModel) -> str:
    """A SHA-256 hex digest of ``model``'s content: its name, name tuples and tensors (shapes and values; floating
    values as ``float64``, so the same model in ``float32`` on the CPU or a GPU has one digest, and a model of other
    values, or its ``float64`` original, another). ``torchface track`` records it (the sidecar's ``model.sha256``) and
    refuses to resume a video's rows made with another model.

    Example:
        >>> from torchface.model import load_candide3
        >>> face_model_digest(load_candide3()) == face_model_digest(load_candide3())
        True
    """
    digest = hashlib.sha256(FORMAT.encode())
    for f in fields(model):
        value = getattr(model, f.name)
        if isinstance(value, torch.Tensor):
            array = value.detach().cpu()
            array = array.double() if array.is_floating_point() else array.long()
            digest.update(f"{f.name}{tuple(array.shape)}".encode())
            digest.update(np.ascontiguousarray(array.numpy()).tobytes())
        else:
            digest.update(f"{f.name}{json.dumps(value)}".encode())
    return digest.hexdigest()
