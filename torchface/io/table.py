"""The per-frame CSV in OpenFace's spirit: columns, rows from a :class:`~torchface.tracker.TrackResult`, and a
writer that flushes every row and renames the file only when complete.

Columns (units; frames as in :mod:`torchface.conventions`)
---------------------------------------------------------
- ``frame`` (0-based index), ``timestamp`` (seconds: the video container's time of the frame, where it gives one
  that goes forward, as a variable-frame-rate video's; else ``frame / fps``: :class:`~torchface.io.video.FrameReader`
  ``.timestamp``), ``success`` (1/0: the frame's estimate
  is usable: not failed, stream not lost), ``confidence`` (``[0, 1]``; with template management, the default,
  the dissimilarity confidence of the normalised face, paper Section 4.1; else the residual confidence);
- ``pose_Tx, pose_Ty, pose_Tz``: the head origin in the OpenCV camera frame (x right, y down, z forward), mm;
- ``pose_Rx, pose_Ry, pose_Rz``: radians, OpenFace's definition: ``R = Rx(pose_Rx) @ Ry(pose_Ry) @ Rz(pose_Rz)``
  (:func:`openface_euler`), ``R`` the head-to-camera rotation in the OpenCV camera frame, identity = a face
  looking straight into the camera;
- ``yaw_deg, pitch_deg, roll_deg``: the same rotation as ``R = R_y(yaw) @ R_x(pitch) @ R_z(roll)``, degrees;
- ``r00 ... r22``: the rotation matrix, row-major (``X_cam = R @ X_head + t``). After the online start has
  re-anchored a stream, the pose columns of the later rows are the re-anchored estimate in the head frame of the
  first row (they stay continuous); their mesh is placed by ``R @ D^T`` and ``t - R @ D^T @ d`` with the offsets the
  job's JSON records (``start.head_rotation``, ``start.head_translation``, after ``start.reanchored_at_frame``;
  :attr:`~torchface.tracker.TrackResult.rotation`);
- ``AUxx_r`` (two digits, as OpenFace: ``AU02_r``): one column per FACS action unit linked to a CANDIDE-3
  animation unit: the expression's signed change in the animation unit's own scale, dimensionless, not OpenFace's
  0-5 intensity (:meth:`~torchface.model.FaceModel.facs_values` of :attr:`~torchface.tracker.TrackResult.expression`,
  measured from the first frame, which is taken as neutral);
- ``anim_<name>``: one column per CANDIDE-3 animation unit, the model's coefficients
  (:attr:`~torchface.tracker.TrackResult.anim_coeffs`: dimensionless, the model file's scale; with the shape units
  they place the mesh, and they include the first frame's fitted coefficients);
- ``illum_<name>``: the illumination parameters (gain, bias, three light-direction terms; paper Eq. 19);
- ``status`` (0 converged, 1 ran out of iterations, 2 failed, 3 lost), ``iterations``, ``num_points`` (template
  points used), ``cost`` (RMS residual per point, intensity units);
- ``residual_confidence`` (``[0, 1]``, from the solver's residual), ``dissimilarity`` (mean fiducial-patch
  displacement on the normalised face, its pixels; ``nan`` when not measured), ``mosaic_entry`` (the template
  mosaic entry aligned against, 0 = the first frame's; -1 when not reported);
- with ``torchface track --smooth`` (``JobConfig.smoothing``), after all of them, :data:`SMOOTH_COLUMNS`
  (``smooth_pose_Tx`` ... ``smooth_roll_deg``, ``smooth_r00`` ... ``smooth_r22``): the pose smoothed over time
  (:mod:`torchface.tracker.smoothing`), in the raw pose columns' units, frames and conventions (re-anchored rows
  too); a row where the filter starts afresh or that is unsuccessful holds its raw cells exactly (docs/cli.md,
  "Smoothing"). The other columns stay raw.

The names follow OpenFace where the quantity matches, but the file is not OpenFace's: no space after the header's
commas, no ``face_id``, ``frame`` from 0 (OpenFace's from 1), and ``AUxx_r`` is a signed animation-unit change, not
OpenFace's 0-5 intensity, with only the AUs CANDIDE-3 animates (docs/cli.md, "Differences from OpenFace's per-frame
CSV").
"""

from __future__ import annotations

import array
import codecs
import contextlib
import math
import os
import re
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, TextIO

import numpy as np
import torch
from torch import Tensor

from torchface._names import name_tuple
from torchface.geometry._checks import check_number
from torchface.geometry.so3 import matrix_to_euler
from torchface.io.errors import InputError, OutputError

if TYPE_CHECKING:  # (torchface.tracker imports torchface.io: the name only, for the annotation)
    from torchface.tracker.step import TrackResult

__all__ = [
    "POSE_COLUMNS",
    "ROTATION_COLUMNS",
    "SMOOTH_COLUMNS",
    "TrackCsvWriter",
    "column_name",
    "openface_euler",
    "partial_path",
    "pose_values",
    "read_back",
    "read_track_csv",
    "result_rows",
    "track_columns",
]

#: Pose columns, in order.
POSE_COLUMNS: tuple[str, ...] = (
    "pose_Tx", "pose_Ty", "pose_Tz", "pose_Rx", "pose_Ry", "pose_Rz", "yaw_deg", "pitch_deg", "roll_deg",
)  # fmt: skip
#: Rotation-matrix columns, row-major.
ROTATION_COLUMNS: tuple[str, ...] = tuple(f"r{i}{j}" for i in range(3) for j in range(3))
#: The columns ``torchface track --smooth`` appends after the others (``JobConfig.smoothing``): the pose smoothed
#: over time (:mod:`torchface.tracker.smoothing`), as :data:`POSE_COLUMNS` and :data:`ROTATION_COLUMNS` hold the
#: raw one, each name prefixed ``smooth_`` (:func:`pose_values` of the smoothed pose).
SMOOTH_COLUMNS: tuple[str, ...] = tuple(f"smooth_{c}" for c in POSE_COLUMNS + ROTATION_COLUMNS)
_LEAD = ("frame", "timestamp", "success", "confidence")
_TAIL = ("status", "iterations", "num_points", "cost", "residual_confidence", "dissimilarity", "mosaic_entry")
_INT_COLUMNS = frozenset({"frame", "success", "status", "iterations", "num_points", "mosaic_entry"})


def column_name(prefix: str, name: str) -> str:
    """``"AUV11 Jaw drop"`` -> ``"anim_AUV11_jaw_drop"``: a CSV-safe column name (the name's runs of letters and
    digits, any script's: ``"lächeln"`` -> ``"anim_lächeln"``, lower-cased, joined by ``_``)."""
    parts = re.findall(r"[^\W_]+", name)
    if not parts:
        raise ValueError(f"cannot make a column name from {name!r}: it has no letter or digit")
    head = parts[0] if re.match(r"^[A-Z]+\d+$", parts[0]) else parts[0].lower()
    return "_".join([prefix, head] + [p.lower() for p in parts[1:]])


def facs_column_stem(name: str) -> str:
    """OpenFace's spelling of a FACS AU in column names, two digits at least: ``"AU2"`` -> ``"AU02"``, ``"AU26"``
    unchanged; a name of another form unchanged when it is letters, digits and ``_`` only (``"AU12L"``), else its
    runs of letters and digits joined by ``_`` (``"AU 12"`` -> ``"AU_12"``: a comma or a quote in a header cell
    would break the CSV)."""
    m = re.fullmatch(r"AU(\d+)", name)
    if m:
        return f"AU{int(m.group(1)):02d}"
    if re.fullmatch(r"\w+", name):
        return name
    parts = re.findall(r"[^\W_]+", name)
    if not parts:
        raise ValueError(f"cannot make a column name from the FACS name {name!r}: it has no letter or digit")
    return "_".join(parts)


def track_columns(
    anim_names: tuple[str, ...], facs_names: tuple[str, ...], illumination_names: tuple[str, ...]
) -> tuple[str, ...]:
    """The CSV header for a model with these animation units, FACS AUs and illumination terms (any model's: the
    names become CSV-safe column names, :func:`column_name` and :func:`facs_column_stem`).

    Raises:
        TypeError: one of the three is one string (it was taken as its characters' names).
        ValueError: a name has no letter or digit, or two names give the same column (the message names them).
    """
    anim_names = name_tuple(anim_names, "anim_names")
    facs_names = name_tuple(facs_names, "facs_names")
    illumination_names = name_tuple(illumination_names, "illumination_names")
    facs = tuple(f"{facs_column_stem(n)}_r" for n in facs_names)
    anim = tuple(column_name("anim", n) for n in anim_names)
    illum = tuple(column_name("illum", n) for n in illumination_names)
    cols = _LEAD + POSE_COLUMNS + ROTATION_COLUMNS + facs + anim + illum + _TAIL
    if len(set(cols)) != len(cols):
        sources = (_LEAD + POSE_COLUMNS + ROTATION_COLUMNS + tuple(facs_names) + tuple(anim_names)
                   + tuple(illumination_names) + _TAIL)  # fmt: skip
        clashes = {c: [s for s, d in zip(sources, cols) if d == c] for c in cols if cols.count(c) > 1}
        detail = "; ".join(f"{c!r} from {names!r}" for c, names in clashes.items())
        raise ValueError(f"column names collide (rename the model's units or AUs): {detail}")
    return cols


def openface_euler(R: Tensor) -> Tensor:
    """``(B, 3, 3)`` rotations -> ``(B, 3)`` OpenFace angles ``(Rx, Ry, Rz)`` in radians with ``R = Rx Ry Rz``.

    ``R[0, 2] = sin(Ry)``, ``R[1, 2] = -sin(Rx) cos(Ry)``, ``R[2, 2] = cos(Rx) cos(Ry)``,
    ``R[0, 1] = -cos(Ry) sin(Rz)``, ``R[0, 0] = cos(Ry) cos(Rz)``; ``Ry`` is kept in ``[-pi/2, pi/2]``.
    At ``|Ry| = pi/2`` (gimbal lock) ``Rz`` is set to 0 and ``Rx`` absorbs the remaining rotation.

    Example:
        >>> openface_euler(torch.eye(3)[None]) + 0.0  # (+ 0.0 turns a -0. into 0.)
        tensor([[0., 0., 0.]])
    """
    if not isinstance(R, Tensor) or R.dim() != 3 or R.shape[-2:] != (3, 3):
        raise ValueError(f"R must be a (B, 3, 3) tensor, got {getattr(R, 'shape', type(R))}")
    s = R[:, 0, 2].clamp(-1.0, 1.0)
    ry = torch.asin(s)
    cy = torch.sqrt((R[:, 0, 0] ** 2 + R[:, 0, 1] ** 2))
    eps = torch.finfo(R.dtype).eps * 16
    locked = cy < eps
    rx = torch.where(locked, torch.atan2(R[:, 2, 1], R[:, 1, 1]), torch.atan2(-R[:, 1, 2], R[:, 2, 2]))
    rz = torch.where(locked, torch.zeros_like(ry), torch.atan2(-R[:, 0, 1], R[:, 0, 0]))
    return torch.stack([rx, ry, rz], dim=-1)


def pose_values(R: Tensor, t: Tensor) -> np.ndarray:
    """``(B, 18)`` float64, the pose's cells of a row in the order of ``POSE_COLUMNS + ROTATION_COLUMNS`` (and of
    :data:`SMOOTH_COLUMNS`): ``t`` (mm), OpenFace's angles (:func:`openface_euler`), yaw, pitch, roll in degrees
    (:func:`~torchface.geometry.so3.matrix_to_euler`) and ``R`` row-major, of ``R (B, 3, 3)`` and ``t (B, 3)``."""
    R = R.detach().to("cpu", torch.float64)
    t = t.detach().to("cpu", torch.float64).reshape(-1, 3)
    return torch.cat([t, openface_euler(R), matrix_to_euler(R), R.reshape(-1, 9)], dim=1).numpy()


def result_rows(result: TrackResult, frame_indices: Tensor | np.ndarray | Sequence[int], fps: float) -> np.ndarray:
    """``(B, C)`` float64 rows (columns of :func:`track_columns`) for one step's ``TrackResult``.

    Args:
        result: a :class:`~torchface.tracker.TrackResult` with batch B.
        frame_indices: ``(B,)`` frame index of each row, whole numbers >= 0 (a tensor, array or list: ``[t] * B``).
        fps: frames per second (``timestamp = frame / fps``; the job writes the frame's time from its reader).

    Raises:
        TypeError: ``result`` is not one step's result, or ``fps`` not a number.
        ValueError: not one frame index per stream, an index that is not a whole number >= 0, or ``fps`` <= 0.
    """
    if not isinstance(getattr(result, "rotation", None), Tensor):  # (a list of results: an AttributeError)
        raise TypeError(f"result must be one step's TrackResult, got {type(result).__name__} (rows of several: "
                        "np.concatenate([result_rows(r, ...) for r in results]))")  # fmt: skip
    fps = check_number(fps, "fps", "(0, inf)", unit="frames per second")  # (inf passed "> 0": every timestamp 0)
    frames = torch.as_tensor(np.asarray(frame_indices), dtype=torch.float64).reshape(-1, 1)
    R = result.rotation.detach().to("cpu", torch.float64)
    B = R.shape[0]
    if frames.shape[0] != B:  # (torch.cat's "Sizes of tensors must match")
        raise ValueError(f"frame_indices must give one frame index per stream ({B}), got {frames.shape[0]}")
    bad = ~(torch.isfinite(frames) & (frames >= 0) & (frames == frames.round()))
    if bool(bad.any()):  # (1.5, -1 or NaN was written as the row's frame and its time without a word)
        raise ValueError(f"frame_indices must be whole frame numbers >= 0, got {float(frames[bad][0]):g}")

    def col(x: Tensor) -> Tensor:
        return x.detach().to("cpu", torch.float64).reshape(B, -1)

    def optional(x: Tensor | None, missing: float) -> Tensor:
        return torch.full((B, 1), missing, dtype=torch.float64) if x is None else col(x)

    parts = [
        frames, frames / fps, col(result.success), col(result.confidence), col(result.translation),
        openface_euler(R), col(result.ypr_deg), R.reshape(B, 9), col(result.facs), col(result.anim_coeffs),
        col(result.illumination), col(result.status), col(result.iterations), col(result.num_points), col(result.cost),
        optional(result.residual_confidence, math.nan), optional(result.dissimilarity, math.nan),
        optional(result.mosaic_entry, -1.0),
    ]  # fmt: skip
    return torch.cat(parts, dim=1).numpy()


def _format_row(columns: tuple[str, ...], row: np.ndarray) -> str:
    cells = []
    for name, v in zip(columns, row):
        if name in _INT_COLUMNS:
            cells.append(str(int(v)))
        elif name == "timestamp":
            cells.append(f"{v:.3f}")
        else:
            cells.append("nan" if not math.isfinite(v) else f"{v:.9g}")
    return ",".join(cells)


def read_back(columns: tuple[str, ...], rows: np.ndarray) -> np.ndarray:
    """``(n, C)`` rows as :func:`read_track_csv` reads them back once :class:`TrackCsvWriter` has written them
    (each cell formatted as written, ``%.9g``, and parsed again): what a resumed run replays, so that what is drawn
    from a row is the same whether the row was just tracked or read back.

    Example:
        >>> read_back(("frame", "confidence"), np.array([[3.0, 0.1 + 1e-12]])).tolist()
        [[3.0, 0.1]]
    """
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, len(columns))
    return np.array([[float(c) for c in _format_row(columns, r).split(",")] for r in rows], dtype=np.float64)


def read_track_csv(path: str | os.PathLike[str]) -> tuple[tuple[str, ...], np.ndarray]:
    """Read a track CSV (finished or ``.partial``): ``(columns, (T, C) float64 rows)``.

    Only complete rows (ending in a newline) are returned, so a file cut off mid-row reads as its complete part.
    A complete line that is not a row (another number of cells, a cell that is not a number) is damage, not a cut:
    an :class:`~torchface.io.InputError` names it (the rows after it were dropped silently, and ``--resume`` tracked
    them again from the rows before it). Column names are stripped of surrounding spaces (OpenFace writes
    ``frame, face_id, timestamp, ...``), carriage returns (Windows line ends) and a UTF-8 byte-order mark, so
    such a file's columns are found by name. The file is read a line at a time into the array (it was read whole,
    and its rows held as lists of Python floats: about 9 times the array's size, 430 MB at the finalising of an
    hour's video at 30 frames/s).

    Raises:
        InputError: the file cannot be read (missing: where ``<path>.partial`` is there, the message says that its
            run is not complete), is not a track CSV, or is damaged, naming it.
    """
    columns, data, _ = _read_csv(path)
    return columns, data


def _read_csv(path: str | os.PathLike[str]) -> tuple[tuple[str, ...], np.ndarray, int | None]:
    """:func:`read_track_csv`'s ``(columns, rows)``, and the length in bytes of the file's part up to its last
    complete row where that part is as :class:`TrackCsvWriter` writes it (a header of the bare names, each line
    ending in a bare newline; no byte-order mark, carriage return or blank line), else None."""
    p = Path(path)
    rows = array.array("d")
    end: int | None = None  # the bytes read up to the last complete row (while the lines are the writer's)
    offset = 0
    blank = 0  # blank complete lines not yet known to be followed by a row (at the end: dropped)
    try:
        with open(p, "rb") as f:
            first = f.readline()
            offset = len(first)
            if first.startswith(codecs.BOM_UTF8):
                first = first[len(codecs.BOM_UTF8) :]
            if not first.endswith(b"\n") or first == b"\n":
                raise InputError(f"{p}: not a track CSV (no complete header line)")
            if first.lstrip()[:1] in (b"{", b"["):  # (a sidecar: "line 2 is not a row ...: the file is damaged")
                csv_name = Path(p.name.removesuffix(".partial")).with_suffix(".csv").name
                raise InputError(f"{p}: not a track CSV but JSON text (a run's sidecar? its rows are {csv_name})")
            columns = tuple(c.strip() for c in first[:-1].decode("utf-8").split(","))
            if offset == len(first) and first == (",".join(columns) + "\n").encode("utf-8"):
                end = offset
            for n, raw in enumerate(f, start=2):
                if not raw.endswith(b"\n"):  # the last line, cut off (or empty)
                    break
                offset += len(raw)
                try:
                    line = raw[:-1].decode("utf-8")
                except UnicodeDecodeError:  # (under a track CSV's header: a damaged row, not "not a track CSV")
                    raise InputError(f"{p}: line {n} is not a row of the track CSV (not UTF-8 text): the file is "
                                     "damaged") from None  # fmt: skip
                if not line:
                    blank += 1
                    continue
                if end is not None:  # (a blank line before a row is damage, below)
                    end = offset if not line.endswith("\r") else None
                if blank:  # a blank line followed by a row is damage
                    n, line, blank = n - blank, "", 0
                cells = line.split(",")
                try:
                    if len(cells) != len(columns):
                        raise ValueError(f"{len(cells)} cells, the header has {len(columns)}")
                    rows.extend(map(float, cells))
                except ValueError as exc:
                    why = f"line {n} is not a row of the track CSV ({exc}): the file is damaged"
                    raise InputError(f"{p}: {why}") from None
    except UnicodeDecodeError:
        raise InputError(f"{p}: not a track CSV (not UTF-8 text)") from None
    except OSError as exc:  # (it said the exception's class alone: "(FileNotFoundError)", "(IsADirectoryError)")
        why = exc.strerror or exc.__class__.__name__
        if isinstance(exc, FileNotFoundError) and partial_path(p).is_file():  # (a run under way or interrupted)
            why += (f"; {partial_path(p).name} holds the rows of a run not complete, under way or interrupted: "
                    "torchface track --resume completes it, read_track_csv reads its rows so far")
        raise InputError(f"{p}: cannot read the track CSV ({why})") from None
    data = np.frombuffer(rows, dtype=np.float64) if rows else np.zeros(0)
    return columns, data.reshape(-1, len(columns)), end  # (a view of the rows read: no copy of them)


def _header_start(path: Path, header: str) -> bool:
    """Whether the file ``path`` holds no more than a beginning of ``header`` (nothing, or the header cut off)."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(header.encode("utf-8")) + 1)
    except OSError:
        return False  # (read_track_csv says what is wrong with it)
    return header.encode("utf-8").startswith(head)


def partial_path(path: str | os.PathLike[str]) -> Path:
    """Where :class:`TrackCsvWriter` keeps the rows of ``path`` until it is complete: ``<path>.partial``."""
    path = Path(path)
    return path.with_name(path.name + ".partial")


class TrackCsvWriter:
    """Write track rows to ``<path>.partial``, flushing every call; :meth:`close` renames it to ``path``.

    Args:
        path: the final CSV path.
        columns: header (:func:`track_columns`).
        resume: continue an existing ``<path>.partial`` with the same header: its complete rows are kept
            (a row cut off mid-line is dropped) and :attr:`rows_done` says how many there are; the new rows are
            appended after them (the file is cut after its last complete row; one that holds what this writer
            would not write, a carriage return or a byte-order mark, is written again with its rows: it was
            always written again, 18.8 s per hour of video at 30 frames/s). A partial file
            that holds no more than a beginning of this header (empty, or cut off in it: a run killed, or its disk
            full, as it started the file) holds no rows: it is started afresh.

    Raises:
        OutputError: the folder cannot be written.
        InputError: ``resume`` and the partial file has another header.
    """

    def __init__(self, path: str | os.PathLike[str], columns: tuple[str, ...], resume: bool = False) -> None:
        self.path = Path(path)
        self.columns = name_tuple(columns, "columns")
        self.partial = partial_path(self.path)
        self.rows_done = 0
        self.previous: np.ndarray = np.zeros((0, len(self.columns)))
        self._file: TextIO | None = None  # open from here to close or stop
        tmp: Path | None = None
        header = ",".join(self.columns) + "\n"
        try:
            if resume and self.partial.is_file() and not _header_start(self.partial, header):
                cols, data, end = _read_csv(self.partial)
                if cols != self.columns:
                    raise InputError(f"{self.partial}: cannot resume, its columns differ from this run's")
                self.previous = data
                self.rows_done = int(data.shape[0])
                if end is not None:  # the writer's own lines: cut after the last complete row, and appended to
                    with open(self.partial, "r+b") as f:
                        f.truncate(end)
                else:
                    keep = "\n".join([",".join(cols)] + [_format_row(cols, r) for r in data]) + "\n"
                    tmp = self.partial.with_name(self.partial.name + ".tmp")
                    tmp.write_text(keep, encoding="utf-8")
                    os.replace(tmp, self.partial)
                    tmp = None
                self._file = open(self.partial, "a", encoding="utf-8")
            else:
                self._file = open(self.partial, "w", encoding="utf-8")
                self._file.write(header)
                self._file.flush()
        except OSError as exc:
            if tmp is not None:  # a full disk: no temporary file left behind (the partial CSV is as it was)
                tmp.unlink(missing_ok=True)
            elif self._file is not None:  # the new file's header did not fit: closed, and no file without one
                self.stop()
                self.partial.unlink(missing_ok=True)
            raise OutputError(f"{self.partial}: cannot write ({exc.strerror or exc})") from None

    def write(self, rows: np.ndarray) -> None:
        """Append ``(n, C)`` rows and flush them to the operating system."""
        rows = np.asarray(rows, dtype=np.float64).reshape(-1, len(self.columns))
        if self._file is None:
            raise RuntimeError("the CSV writer is closed")
        try:
            for r in rows:
                self._file.write(_format_row(self.columns, r) + "\n")
            self._file.flush()
        except OSError as exc:  # a full disk: say which file (the error named none)
            raise OutputError(f"{self.partial}: cannot write ({exc.strerror or exc})") from None
        self.rows_done += int(rows.shape[0])

    def close(self) -> Path:
        """Sync, close and rename to the final name; returns it.

        Raises:
            OutputError: the rows cannot be synced (a full disk, an I/O error; the file stays open for
                :meth:`stop`) or the file renamed (a folder gone read-only), naming the file (the error named none
                where the sync failed); ``<path>.partial`` stays for ``--resume``.
        """
        if self._file is not None:
            try:
                self._file.flush()
                os.fsync(self._file.fileno())
            except OSError as exc:
                raise OutputError(f"{self.partial}: cannot write ({exc.strerror or exc})") from None
            file, self._file = self._file, None
            file.close()  # (nothing left to write)
            try:
                os.replace(self.partial, self.path)
            except OSError as exc:
                why = exc.strerror or exc
                raise OutputError(f"{self.partial}: cannot rename it to {self.path.name} ({why})") from None
        return self.path

    def stop(self) -> None:
        """Close without finishing: ``<path>.partial`` stays for ``--resume``. Never raises ``OSError``: where the
        rows cannot be flushed (a full disk, the reason to stop), those that were stay (a row cut off mid-line is
        dropped on resume), and the file is closed all the same."""
        if self._file is not None:
            file, self._file = self._file, None
            with contextlib.suppress(OSError):
                file.flush()
            with contextlib.suppress(OSError):  # closed even where its flush fails again
                file.close()

    def __enter__(self) -> "TrackCsvWriter":
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.stop()
