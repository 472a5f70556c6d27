"""Disk cache of tracked sequences: a second epoch reads instead of tracking again.

Key (:func:`cache_key`): a BLAKE2b hash of

- the video's CONTENT (:func:`content_hash`: the file's bytes; for a folder of frames, every image file's bytes
  in name order), not its path or time stamp;
- the :class:`~training_hooks.transforms.FaceTrackingConfig`'s full ``repr`` (the nested
  :class:`~torchface.tracker.TrackerConfig` and its :class:`~torchface.tracker.FitConfig` included: every field,
  face size and storage, focal length, thread count);
- the first-frame landmarks (float64 bytes; a missing point, a NaN row, as one NaN whatever its bits) and the
  frame they are of, where it is not the video's first (a dataset's detector found no face before it);
- the face model file's content (:func:`content_hash`), where the config names one
  (:attr:`~training_hooks.transforms.FaceTrackingConfig.model`; a dataset's: as it read the model from it);
- any extra text the caller adds (the datasets add their frame-conversion setting);
- the torchface and torch versions, whether torchface's native kernels run (:mod:`torchface.backend`; they
  and the torch code agree to float tolerance, not bit for bit) and :data:`CACHE_FORMAT`;
- the installed code itself (:func:`code_version`: a digest of the files of the ``torchface`` and
  ``training_hooks`` packages, hidden files, editors' swap and backup files and byte-code left out), so that a change of the tracking that keeps the version (an editable install
  pulled or edited, as ``scripts/test.sh`` and ``scripts/demo.sh`` install it) keys apart the sequences the
  code tracked before.

So a changed config, video or landmark set is a different file: a stale entry is never read, it is only left
behind (delete ``cache_dir`` to reclaim the space).

Files: one uncompressed ``<key>.npz`` per sequence (NumPy ``savez``) holding every
:class:`~training_hooks.transforms.TrackedSequence` array (faces in their storage dtype, masks as bool) and a
``meta`` JSON record with the key, the format, the torchface version, a BLAKE2b digest of all arrays, the
config's repr (for people) and the source path. Writing goes to a unique temporary name in the same folder,
flushed and ``fsync``-ed, then :func:`os.replace`-d into place, so a reader sees a whole file or none. A temporary
file left by a writer that was killed (``.<key>.<pid>.<id>.partial``) is never read; the first write of a
:class:`TrackCache` deletes such files older than a day. Reading
checks the zip structure, the digest, the key and the arrays' shapes and dtypes; anything wrong (a truncated,
partial or corrupted file) is reported with a :class:`CacheWarning`, deleted and treated as a miss, so the
sequence is tracked again: a damaged file is never used (a file that another process has stored under its name
since it was read is kept, and so is one the folder does not let this process delete: the store of the sequence
tracked again replaces it); one that cannot be read now (an ``OSError``: too many open files, an I/O error; a
``MemoryError``) is no proof of damage: kept, with a :class:`CacheWarning`, and the sequence tracked. An error
writing (a full disk, a read-only folder) raises an ``OSError`` of its class and ``errno`` that names the folder
and what to do. :meth:`TrackCache.num_frames` reads the ``meta`` record alone (a dataset counts a cached video's
frames with it instead of decoding the video).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import stat
import time
import uuid
import warnings
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

import torchface
from torchface.backend import Backend, native_available
from torchface.extending import check_int, check_no_tilde
from torchface.io.video import image_files
from training_hooks.transforms import FaceTrackingConfig, TrackedSequence

if TYPE_CHECKING:  # (importlib.resources.abc: Python 3.11 on)
    from importlib.resources.abc import Traversable

__all__ = ["CACHE_FORMAT", "CacheWarning", "CacheStats", "TrackCache", "cache_key", "code_version", "content_hash"]

#: Version of the file layout; part of every key.
CACHE_FORMAT: int = 2
#: Arrays of a :class:`TrackedSequence` stored in a cache file, in digest order.
_ARRAYS: tuple[str, ...] = (
    "faces", "masks", "rotation", "axis_angle", "translation", "ypr_deg", "anim_coeffs", "expression", "facs",
    "illumination", "confidence", "status", "shape_coeffs", "landmarks",
)  # fmt: skip
_CHUNK = 1 << 20
#: Age (seconds) after which a killed writer's temporary file is deleted.
_STALE_PARTIAL_S = 24 * 3600.0
#: Resolved path -> (digest of its files' sizes, modification times and inodes, content hash), per process: an
#: unchanged file is hashed once. One entry per path, replaced when the file changes, and of a fixed size (the
#: stats themselves as the key held 46 kB for a folder of 500 images, and every changed file added an entry).
_HASH_MEMO: dict[str, tuple[bytes, str]] = {}
#: The installed code's :func:`code_version`, computed once per process.
_CODE_VERSION: list[str] = []


#: File names :func:`code_version` leaves out, besides hidden ones (``.x.swp``, ``.#x``, ``.DS_Store``, hidden
#: folders) and ``__pycache__`` folders: what editors, patch tools and Python leave beside the code, which no
#: process runs and which come and go, or change as one types, while a run goes on (a worker started later
#: digested them differently from its rank and tracked its cached videos again).
_NOT_CODE_SUFFIXES: tuple[str, ...] = ("~", ".pyc", ".pyo", ".swp", ".swo", ".swx", ".tmp", ".bak", ".orig", ".rej")


def _is_code_name(name: str) -> bool:
    """Whether a file or folder called ``name`` counts in :func:`code_version` (:data:`_NOT_CODE_SUFFIXES`)."""
    if name.startswith(".") or name == "__pycache__" or (name.startswith("#") and name.endswith("#")):
        return False  # (hidden; Python's byte-code; an Emacs auto-save)
    return not name.endswith(_NOT_CODE_SUFFIXES)


def _code_files(folder: Traversable, prefix: str) -> Iterator[tuple[str, bytes]]:
    """``(path relative to the package, bytes)`` of the files under ``folder``, in name order: a folder that is a
    symbolic link is not walked (as ``Path.rglob``), a file that cannot be read as it is listed (removed meanwhile:
    an editor's atomic save) is left out."""
    for child in sorted(folder.iterdir(), key=lambda c: c.name):
        if not _is_code_name(child.name):
            continue
        try:
            if isinstance(child, Path) and child.is_symlink() and child.is_dir():
                continue
            if child.is_dir():
                yield from _code_files(child, f"{prefix}{child.name}/")
            elif child.is_file():
                yield f"{prefix}{child.name}", child.read_bytes()
        except OSError:
            continue


def _package_digest(roots: tuple[Traversable, ...]) -> str:
    """BLAKE2b hex digest of the files under the package folders ``roots`` (path relative to its root, length and
    bytes, in name order; :func:`_is_code_name` says which count): the content of installed packages
    (:func:`code_version`). ``roots``: folders (``Path``) or ``importlib.resources.files`` of packages, which also
    reads a package imported from a zip archive (``Path(module.__file__).parent`` there is no folder: it digested
    no file, the same for every code)."""
    h = hashlib.blake2b(digest_size=32)
    for root in roots:
        h.update(root.name.encode("utf-8") + b"\0")
        for name, data in _code_files(root, ""):
            h.update(name.encode("utf-8") + b"\0" + len(data).to_bytes(8, "little"))
            h.update(data)
    return h.hexdigest()


def code_version() -> str:
    """The digest (:func:`_package_digest`) of the installed ``torchface`` and ``training_hooks`` packages: their
    source, the native kernels' C source and the model data (not hidden files, editors' swap and backup files nor
    byte-code: :func:`_is_code_name`), as they are when this process first asks (once per process: a spawned
    ``DataLoader`` worker reads them again). Part of every :func:`cache_key`: ``torchface.__version__`` stays the
    same across the commits of an editable install, whose tracking may change between them (a cache filled before
    a ``git pull`` was read after it). About 30 ms (2.9 MB).
    """
    if not _CODE_VERSION:
        _CODE_VERSION.append(_package_digest(tuple(resources.files(name) for name in ("torchface", "training_hooks"))))
    return _CODE_VERSION[0]


class CacheWarning(UserWarning):
    """A cache file was unreadable or damaged; it was deleted (where it was damaged and could be) and the sequence
    is tracked again."""


def _file_digest(path: Path, h: "hashlib.blake2b") -> None:
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)


def content_hash(path: str | os.PathLike[str]) -> str:
    """BLAKE2b hex digest of a video's content: a file's bytes, or a folder's image files' bytes in name order.

    For a folder, each image (:func:`torchface.io.video.image_files`, in the order
    :func:`torchface.io.open_frames` reads them) contributes its length and bytes; names do not count. The
    result for an unchanged file (same size, modification time and inode) is remembered per process.

    Raises:
        FileNotFoundError: ``path`` does not exist.

    Example:
        >>> # content_hash("clip.avi") -> '3f1c...' (64 hex digits)
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file or folder")
    files = image_files(p) if p.is_dir() else [p]
    stats = [f.stat() for f in files]
    signature = hashlib.blake2b(digest_size=16)
    for s in stats:
        signature.update(b"%d,%d,%d;" % (s.st_size, s.st_mtime_ns, s.st_ino))
    where, seen = str(p.resolve()), signature.digest()
    held = _HASH_MEMO.get(where)
    if held is not None and held[0] == seen:
        return held[1]
    h = hashlib.blake2b(digest_size=32)
    h.update(b"folder" if p.is_dir() else b"file")
    for f, s in zip(files, stats):
        h.update(s.st_size.to_bytes(8, "little"))
        _file_digest(f, h)
    digest = h.hexdigest()
    _HASH_MEMO[where] = (seen, digest)
    return digest


def cache_key(
    content: str, config: FaceTrackingConfig, landmarks: np.ndarray, extra: str = "", first_frame: int = 0,
    model_content: str | None = None,
) -> str:
    """The cache key of a sequence (module docstring): 64 hex digits.

    Args:
        content: :func:`content_hash` of the video.
        config: the tracking settings (their ``repr`` is hashed, that of ``model=None``: the model file's content
            is hashed instead of its path, so that the same file moved keeps its sequences).
        landmarks: ``(68, 2)`` first-frame landmarks in pixels (with the config's ``model``, its ``K``; hashed as
            float64); a NaN row (a missing point) is hashed as the same NaN whatever its bits.
        extra: anything else that changes the result (e.g. a frame-conversion setting).
        first_frame: the video's frame the landmarks are of, where the tracking starts (a dataset's detector found
            no face before it); hashed where it is not 0, so that the key of a sequence tracked from the video's
            first frame is the one it had before the frame counted.
        model_content: with the config's ``model``, the :func:`content_hash` of the model file as it was when the
            model tracked with was read from it (the datasets give theirs: a file saved again since keys apart the
            sequences of the model read before); None: the file as it is now.

    Example:
        >>> from training_hooks.transforms import FaceTrackingConfig
        >>> a = cache_key("0" * 64, FaceTrackingConfig(), np.zeros((68, 2)))
        >>> b = cache_key("0" * 64, FaceTrackingConfig(face_size=64), np.zeros((68, 2)))
        >>> len(a), a == b
        (64, False)
    """
    if not isinstance(config, FaceTrackingConfig):
        raise TypeError(f"config must be a FaceTrackingConfig, got {type(config).__name__}")
    if model_content is not None and config.model is None:
        raise ValueError("model_content is the content of config.model's file, and config has no model")
    first_frame = check_int(first_frame, "first_frame", 0)
    points = np.ascontiguousarray(np.asarray(landmarks, dtype=np.float64))
    if points.ndim != 2 or points.shape[1] != 2 or (config.model is None and points.shape[0] != 68):
        count = "68" if config.model is None else "K"  # (a model file's K is not known without reading it)
        raise ValueError(f"landmarks must be ({count}, 2), got {points.shape}")
    points = np.where(np.isnan(points), np.nan, points)  # one NaN for a missing point (x86's 0 / 0 has the sign bit)
    h = hashlib.blake2b(digest_size=32)
    native = config.tracker.backend is not Backend.TORCH and native_available()
    settings = repr(config if config.model is None else replace(config, model=None))  # (the file's content below)
    parts = (
        f"format={CACHE_FORMAT}", f"torchface={torchface.__version__}", f"torch={torch.__version__}",
        f"native={native}", f"code={code_version()}", content, settings, extra,
        *([f"first_frame={first_frame}"] if first_frame else []),
        *([f"model={model_content or content_hash(config.model)}"] if config.model is not None else []),
    )  # fmt: skip
    for part in parts:
        data = part.encode("utf-8")
        h.update(len(data).to_bytes(8, "little"))
        h.update(data)
    h.update(points.tobytes())
    return h.hexdigest()


def _arrays_digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.blake2b(digest_size=32)
    for name in _ARRAYS:
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.data if a.size else b"")
    return h.hexdigest()


@dataclass
class CacheStats:
    """Counters of one :class:`TrackCache` in this process (each ``DataLoader`` worker has its own copy).

    Attributes:
        hits: sequences read from the cache.
        misses: sequences not found (tracked, then stored).
        corrupt: damaged files found, deleted and counted as misses too.
        writes: files written.
    """

    hits: int = 0
    misses: int = 0
    corrupt: int = 0
    writes: int = 0


class TrackCache:
    """A folder of tracked sequences keyed by :func:`cache_key` (module docstring).

    Args:
        root: the folder (created on first write); a relative one is taken against the working folder when the
            cache is made (:attr:`root` is absolute: a later ``os.chdir`` does not move it). An empty string is
            refused, as :attr:`DatasetConfig.cache_dir <training_hooks.datasets.DatasetConfig.cache_dir>` refuses it
            (``Path("")`` is the working folder: say ``"."`` for it).

    Raises:
        TypeError: ``root`` is not a ``str`` or path-like.
        ValueError: ``root`` is an empty string, or starts with a ``~`` that ``os.path.expanduser``
            expands (not expanded here).

    Example:
        >>> # cache = TrackCache("cache"); seq = cache.load(key) or track(...); cache.store(key, seq)
    """

    def __init__(self, root: str | os.PathLike[str]) -> None:
        if not isinstance(root, (str, os.PathLike)):  # (was pathlib's "expected str, bytes or os.PathLike object")
            raise TypeError(f"root must be a folder (a str or path-like), got {type(root).__name__}")
        if isinstance(root, str) and not root:  # (Path("") is ".": the cache filled the working folder unasked)
            raise ValueError('root is empty (the working folder): give a folder ("." for the working folder)')
        check_no_tilde(root, "root")
        self.root = Path(root).absolute()
        self.stats = CacheStats()
        self._swept = False

    def _sweep_partials(self) -> None:
        """Delete temporary files older than a day (left by a writer killed mid-write), once per instance."""
        self._swept = True
        limit = time.time() - _STALE_PARTIAL_S
        for tmp in self.root.glob(".*.partial"):
            try:
                if tmp.stat().st_mtime < limit:
                    tmp.unlink()
            except OSError:  # another process removed or renamed it meanwhile
                pass

    def path(self, key: str) -> Path:
        """The file of ``key``."""
        if len(key) != 64 or any(c not in "0123456789abcdef" for c in key):
            raise ValueError(f"key must be 64 lowercase hex digits (cache_key), got {key!r}")
        return self.root / f"{key}.npz"

    def load(self, key: str) -> TrackedSequence | None:
        """The stored sequence of ``key``, or None when there is none or the file is damaged (then it is deleted,
        unless another process has stored a new file under its name since it was read or the folder does not let
        this process delete it, and a :class:`CacheWarning` says why) or cannot be read now (an ``OSError`` or a
        ``MemoryError``: kept, a :class:`CacheWarning` says so)."""
        path = self.path(key)
        try:
            read = _identity(path)
            if read is None:
                self.stats.misses += 1
                return None
            sequence = _read(path, key)
        except (OSError, MemoryError) as exc:  # could not be read now (too many open files, an I/O error, a long
            # video's file in a process short of memory): no proof of damage, kept
            warnings.warn(
                f"{path}: cache file unreadable now ({type(exc).__name__}: {exc}); kept, tracking again",
                CacheWarning,
                stacklevel=2,
            )
            self.stats.misses += 1
            return None
        except Exception as exc:  # any failure to read back means the file is not trustworthy
            # Deleted only if it is still the file read: another process (a DataLoader worker, a rank) that found it
            # damaged too may have tracked the sequence and stored a good file under its name meanwhile.
            what = "deleted"
            try:
                now = _identity(path)
                if now == read:
                    path.unlink(missing_ok=True)
                elif now is not None:
                    what = "a new file replaced it meanwhile, kept"
            except OSError as gone:  # (a folder that does not let this user delete: a miss all the same, not an error
                # of the video's; a store replaces the file, or says why it cannot)
                what = f"it could not be deleted ({gone.strerror or gone})"
            warnings.warn(
                f"{path}: damaged cache file ({type(exc).__name__}: {exc}); {what}, tracking again",
                CacheWarning,
                stacklevel=2,
            )
            self.stats.corrupt += 1
            self.stats.misses += 1
            return None
        self.stats.hits += 1
        return sequence

    def num_frames(self, key: str) -> int | None:
        """Frames of the sequence stored under ``key``, read from the file's ``meta`` record alone (CRC-checked; the
        arrays are neither read nor checked: a fraction of a millisecond, where :meth:`load` reads them all), or
        None when there is no file or its record is unreadable, damaged or of another key or format. The count of a
        stored sequence is the number of frames its video gave (tracking stops only at the video's end), so it
        stands for counting the video's frames without decoding it. Touches neither the file nor :attr:`stats`: a
        damaged file is reported and deleted by :meth:`load`.

        Example:
            >>> # cache.num_frames(key) -> 300 (or None: decode the video to count its frames)
        """
        path = self.path(key)
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(bytes(z["meta"]).decode("utf-8"))
            frames = meta.get("num_frames")
            if meta.get("key") != key or meta.get("format") != CACHE_FORMAT:
                return None
        except Exception:  # (no file, or any failure to read its record: count another way)
            return None
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
            return None
        return frames

    def store(
        self, key: str, sequence: TrackedSequence, source: str = "", config: FaceTrackingConfig | None = None
    ) -> Path:
        """Write ``sequence`` under ``key`` atomically (temporary file, fsync, :func:`os.replace`); returns the path.

        Args:
            key: from :func:`cache_key`.
            sequence: what to store.
            source: the video's path, recorded for people.
            config: the settings, their repr recorded for people.

        Raises:
            OSError: the file cannot be written (a full disk, a read-only folder, a folder inside a file): of the
                error's class and ``errno``, naming :attr:`root` and what to do; no file is left.
        """
        path = self.path(key)
        arrays = {name: getattr(sequence, name).numpy() for name in _ARRAYS}
        meta = {
            "key": key, "format": CACHE_FORMAT, "torchface": torchface.__version__, "code": code_version(),
            "digest": _arrays_digest(arrays),
            "frame_size": list(sequence.frame_size), "num_frames": sequence.num_frames, "source": str(source),
            "first_frame": sequence.first_frame,
            "config": repr(config) if config is not None else "",
        }  # fmt: skip
        tmp = self.root / f".{key}.{os.getpid()}.{uuid.uuid4().hex}.partial"
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            if not self._swept:
                self._sweep_partials()
            with open(tmp, "wb") as f:
                np.savez(f, meta=np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8), **arrays)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException as exc:
            try:
                tmp.unlink(missing_ok=True)
            except OSError:  # (a folder that does not let this user delete: the error below says more)
                pass
            if isinstance(exc, OSError):  # (a full disk was "[Errno 28] No space left on device", of no file)
                raise self._write_error(exc) from exc
            raise
        self.stats.writes += 1
        return path

    def _write_error(self, exc: OSError) -> OSError:
        """``exc``, raised writing a file of :attr:`root`, as an error of its class and ``errno`` that names the
        folder and what to do."""
        detail = exc.strerror if exc.errno is not None and exc.strerror else str(exc)
        if isinstance(exc, (FileExistsError, NotADirectoryError)) and exc.filename == str(self.root):
            detail = "it is a file, or inside one"  # (mkdir's "File exists" / "Not a directory" of the folder)
        elif exc.filename is not None and Path(exc.filename).parent != self.root:  # (not the temporary file)
            detail += f": {exc.filename}"
        message = (
            f"cannot store a tracked sequence in the cache folder {self.root} ({detail}): free space there, make it "
            f"writable, or give another cache folder (DatasetConfig.cache_dir; None tracks every epoch)"
        )
        return OSError(exc.errno, message) if exc.errno is not None else OSError(message)


def _identity(path: Path) -> tuple[int, int] | None:
    """``(device, inode)`` of the regular file at ``path``, or None where there is none."""
    try:
        st = path.stat()
    except OSError as exc:
        if exc.errno in (errno.ENOENT, errno.ENOTDIR, errno.EBADF, errno.ELOOP):  # (as Path.is_file takes them)
            return None
        raise
    return (st.st_dev, st.st_ino) if stat.S_ISREG(st.st_mode) else None


def _read(path: Path, key: str) -> TrackedSequence:
    """Read and verify one cache file; raises on anything unexpected."""
    # (through one handle: one file, whatever is stored under its name meanwhile; the arrays read from it, not from a
    # copy of its bytes, which held the sequence twice in memory)
    with open(path, "rb") as f:
        with zipfile.ZipFile(f) as z:
            bad = z.testzip()  # CRC of every member
            if bad is not None:
                raise ValueError(f"member {bad} fails its CRC check")
        f.seek(0)
        with np.load(f, allow_pickle=False) as z:
            names = set(z.files)
            missing = [n for n in (*_ARRAYS, "meta") if n not in names]
            if missing:
                raise ValueError(f"missing arrays {missing}")
            meta = json.loads(bytes(z["meta"]).decode("utf-8"))
            arrays = {name: z[name] for name in _ARRAYS}
    if meta.get("key") != key or meta.get("format") != CACHE_FORMAT:
        raise ValueError(f"the file holds key {meta.get('key')!r} format {meta.get('format')!r}, expected {key!r}")
    if meta.get("digest") != _arrays_digest(arrays):
        raise ValueError("the arrays do not match their recorded digest")
    tensors = {name: torch.from_numpy(np.ascontiguousarray(a)) for name, a in arrays.items()}
    size = meta.get("frame_size")
    if not isinstance(size, list) or len(size) != 2:
        raise ValueError(f"bad frame_size {size!r}")
    first = meta.get("first_frame", 0)  # files written before it was recorded hold sequences tracked from landmarks
    sequence = TrackedSequence(**tensors, frame_size=(int(size[0]), int(size[1])), first_frame=first)
    if sequence.num_frames != meta.get("num_frames"):
        raise ValueError(f"{sequence.num_frames} frames stored, {meta.get('num_frames')} recorded")
    return sequence
