"""Landmark files for initialisation: 68 iBUG points of the first frame, as CSV, iBUG ``.pts`` or NPY.

Accepted layouts (pixel coordinates ``(u, v)``, pixel centres at integers, :mod:`torchface.conventions`):

- CSV: 68 rows of ``x, y`` (an optional header line and ``#`` comment lines are skipped; a header ``y, x`` says
  the columns are the other way round, as image coordinates (row, column) are written; a two-column header naming
  the y column first in other words, ``y_px, x_px`` or ``row, col``, is refused), or one row of
  136 numbers ``x0, y0, x1, y1, ...`` (in the order a header names them when it names every cell ``x<k>`` or
  ``y<k>``, e.g. ``x_0, ..., x_67, y_0, ..., y_67``); cells separated by commas, semicolons, tabs or
  spaces, optionally quoted (a spreadsheet's of a decimal-comma locale, ``12,5;40,25``: where cells are separated
  by semicolons or tabs and no number has a decimal point, a comma between digits is one); UTF-8 with or without a
  byte order mark, UTF-16 after its byte order mark (a spreadsheet's "Unicode Text"), or 8-bit (Windows-1252,
  Latin-1: the numbers are ASCII in all of them);
- OpenFace's per-frame CSV (FeatureExtraction, ``frame, face_id, timestamp, confidence, success, ...``): a header
  with ``x_0 ... x_67`` and ``y_0 ... y_67`` among other columns (OpenFace's 3D ``X_k``, gaze, AUs, ...); the points
  are the first row's (its first frame), which must have ``success`` 1 when the file has that column;
- CSV, one row per point: a header naming an ``ibug_index`` column (0-67, as torchface's arrays index the points;
  also ``index``, ``point`` or ``landmark``) and ``x``, ``y`` columns, other columns (a ``meaning``) ignored, rows
  in any order; each point once at most, a point without a row missing (the hand-marked
  ``torchface/data/photos/astronaut_landmarks.csv`` gives 22); also pandas' ``DataFrame.to_csv`` with its index
  (a header ``,x,y``, ``,y,x`` or ``,0,1``, then rows ``k, x, y``): the index is the point's; R's ``write.csv``
  with its row names (``"","x","y"``, then rows ``"1",x,y`` ... ``"68",x,y``): such an unnamed index with 0 is
  0-based, one reaching 68 without 0 is 1-based (a 0-based one has no 68), 1 subtracted; one with neither (R's 1..67
  without point 68 is pandas' 1..67 without point 0) is refused, saying to keep a missing point's row (``"68",NA,NA``)
  or name the column ``ibug_index``;
- iBUG / 300-W ``.pts`` (the layout every 68-point data set ships: ``version: 1``, ``n_points: 68``, ``{``, 68 lines
  ``x y``, ``}``), read when the name ends in ``.pts`` or the file starts with ``version:`` / ``n_points:``. Its
  coordinates are 1-based (Matlab's convention, the top-left pixel's centre at ``(1, 1)``, as menpo and the 300-W
  tools read them), so 1 is subtracted: a ``.pts`` point ``(1, 1)`` is torchface's ``(0, 0)``, the same pixel
  centre; the subtraction is exact in decimal, so ``x`` in a ``.pts`` reads as ``x - 1`` written in a CSV does.
  A file written 0-based whose points lie inside the frame as written but some left of or above it read 1-based (a
  coordinate under 0.5) is refused, saying it looks 0-based (:func:`_zero_based_pts_problem`); one whose points
  all lie at 0.5 or more cannot be told, and is read 1-based;
- NPY: an array of shape ``(68, 2)``, ``(1, 68, 2)`` or ``(136,)`` (``x0, y0, x1, y1, ...``, as every flat form is
  read; one evidently all x then all y is refused: :func:`planar_layout_problem`);
- JSON (``.json``): a list of 68 ``[x, y]`` pairs (or of 136 numbers ``x0, y0, x1, ...``; or one frame's pairs
  ``[[[x, y], ...]]``, as an NPY ``(1, 68, 2)``), or an object holding them as ``initial_landmarks_px``: a
  torchface sidecar, so a run can start from the landmarks another one started from (one whose
  ``start.first_frame`` is 0: a run its detector started later, on that frame's landmarks, is refused).

Missing points (a detector's occluded ones): a point may be left out as a NaN row, which the landmark fit gives
weight 0, as the tracker's Python API does a NaN row; the file keeps its count of 68 (its points are placed by
their order): in a CSV an ``x, y`` pair of empty cells (``,``; a separator ending every line, ``x,y,``, is not a
cell, nor is a column empty on every row of ``x, y`` rows: ``,x,y``, a spreadsheet's cells from its column B, nor
an empty column before one row's 136 values: ``,x0,y0,...``, 137 cells, where its last cell is empty too the 136
whose empty cells pair up as missing points, refused where two cuts do; but the cells of ``x, y`` rows 2 wide and of
one row 136 wide are all values, an empty one a missing coordinate: ``,y0,x1,...`` has point 0's ``x`` missing) or of
``nan``, ``NA``, ``N/A``, ``null`` or ``None``, a one-row-per-point CSV's point without a row, a ``.pts`` line
``nan nan``, NaN in an NPY, ``[null, null]`` in a JSON. At least 4 points must be given (the landmark fit's
:data:`~torchface.tracker.fit.MIN_FIT_LANDMARKS`: the pose's six parameters need as many residuals); a point with
one coordinate missing, an infinite coordinate, or a given point outside the frame is refused, as is a file of
another count (a ``.pts`` of 60 points: which are missing is not known).

A face model's ``K`` landmarks (``read_landmarks(count=K)``, ``torchface track --model``) come in the same layouts,
``K`` points in the model's order where these say 68 (one row of ``2 K`` values, indices ``0`` to ``K - 1``, R's row
names ``1`` to ``K``, ``x_0`` to ``x_{K-1}``).
"""

from __future__ import annotations

import codecs
import csv
import json
import math
import numbers
import os
import re
import warnings
from decimal import MAX_EMAX, MIN_EMIN, Context, Decimal, DecimalException
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from torchface._paths import missing_path_hint
from torchface._words import counted
from torchface.conventions import (
    IBUG68_MIRROR, MEDIAPIPE_MESH_HINT, MEDIAPIPE_MESH_POINT_COUNTS, NORMALISED_CHECK_MIN_SIDE,
    NORMALISED_LANDMARK_MAX_SPAN, NORMALISED_LANDMARK_RANGE, half_precision_rounding, other_landmark_set_hint,
)
from torchface.io.errors import InputError

__all__ = [
    "NUM_LANDMARKS", "read_landmarks", "check_landmarks", "landmarks_shape_hint", "missing_points_problem",
    "mirror_landmarks",
]

#: Points in the iBUG-68 scheme.
NUM_LANDMARKS: int = 68

if TYPE_CHECKING:
    import torch

#: Pixel points as a tensor or a NumPy array (:func:`mirror_landmarks` returns the type it is given).
_Points = TypeVar("_Points", "torch.Tensor", np.ndarray)


def _cells(line: str, decimal_comma: bool = False) -> list[str]:
    """A line's cells: separated by commas, semicolons, tabs or spaces; quotes around a cell dropped. An empty cell
    between separators is kept in its place (``1,,2``: three cells, the second ``""``, a missing value).
    ``decimal_comma`` (:func:`_decimal_comma`): semicolons and tabs alone separate cells, a comma is a decimal point."""
    for sep in (";", "\t"):
        line = line.replace(sep, "," if not decimal_comma else "\x00")
    if decimal_comma:
        line = line.replace(",", ".").replace("\x00", ",")
    if "," not in line:
        line = ",".join(line.split())
    return [c.strip().strip("\"'").strip() for c in line.split(",")]


def _decimal_comma(lines: list[str]) -> bool:
    """Whether ``lines`` (a CSV's, comments left out) are a spreadsheet's of a locale with a decimal comma: cells
    separated by semicolons or tabs, a comma between digits (``12,5;40,25``) only on lines so separated (a title
    ``Landmarks; frame 0`` over ``12,40`` rows: the commas separate), and no decimal point between digits anywhere (a
    decimal point says the commas are something else, separators: ``1,234.5;40.5`` is 3 cells)."""
    text = "\n".join(lines)
    commas = [line for line in lines if re.search(r"\d,\d", line)]
    return bool(commas) and all(";" in c or "\t" in c for c in commas) and re.search(r"\d\.\d", text) is None


def _check_not_grouped(p: Path, lines: list[str]) -> None:
    """Refuse decimal-comma ``lines`` (:func:`_decimal_comma`) where every number with a comma has three digits after
    it and one to three before (``3,402;2,536``): thousands separators of integer pixels as much as decimal commas
    (read as decimal commas, a 4K frame's points were silently 1000 times nearer its corner)."""
    cells = [c.strip().strip("\"'").strip() for line in lines for c in re.split(r"[;\t]", line)]
    with_comma = [c for c in cells if re.search(r"\d,\d", c)]
    if with_comma and all(re.fullmatch(r"[-+]?\d{1,3}(,\d{3})+", c) for c in with_comma):
        raise InputError(f"{p}: every number with a comma has 3 digits after it ({with_comma[0]}): a thousands "
                         f"separator or a decimal comma? Save the numbers without thousands separators (or with "
                         f"another number of decimals)")  # fmt: skip


def _trimmed(cells: list[str], width: int) -> list[str]:
    """``cells`` without the empty cells at their end beyond ``width`` (a separator ending every line, as some
    spreadsheets write them: ``x,y,``)."""
    end = len(cells)
    while end > width and cells[end - 1] == "":
        end -= 1
    return cells[:end]


#: Cells (lower case) that mean a missing value: an empty cell, as pandas and spreadsheets write NaN, R's ``NA``,
#: JSON's and SQL's ``null``, Python's ``None``; ``nan`` is read by ``float`` itself.
_MISSING_CELLS: frozenset[str] = frozenset({"", "na", "n/a", "null", "none"})


def _number(cell: str) -> float:
    """A cell's number; NaN for a missing value (:data:`_MISSING_CELLS`). Raises ValueError for other text."""
    return math.nan if cell.lower() in _MISSING_CELLS else float(cell)


def _number_rows(data: list[list[str]], width: int) -> list[list[float]]:
    """The rows' cells as numbers (NaN: missing), each without the empty cells at its end beyond ``width``."""
    return [[_number(c) for c in _trimmed(cells, width)] for cells in data]


def _without_empty_columns(data: list[list[str]]) -> list[list[str]] | None:
    """The rows without the columns that are empty on every row (a spreadsheet's export that starts at column B:
    ``,x,y``; a row too short to reach a column is empty there), a row of empty cells alone kept as a missing point
    ``["", ""]``; None when no column is empty on every row."""
    width = max((len(cells) for cells in data), default=0)
    keep = [j for j in range(width) if any(j < len(cells) and cells[j] != "" for cells in data)]
    if len(keep) == width:
        return None
    rows = [[cells[j] for j in keep if j < len(cells)] for cells in data]
    return [row if any(row) else ["", ""] for row in rows]


def _one_row_values(
    p: Path, cells: list[str], names: list[str], count: int = NUM_LANDMARKS
) -> tuple[list[str], list[str]]:
    """One row's ``cells`` and its header's ``names`` (``[]``: no header) cut to the row's ``2 * count`` values where it
    holds more cells, the others empty in both (and not named by the header): a spreadsheet's export with a column
    before the values left empty, ``,x0,y0,...``, as the rows-of-``x, y`` layout drops a column empty on every row
    (:func:`_without_empty_columns`), or a separator ending the line, ``x0,...,y67,``. Where both ends are empty (a
    column before the values, or a missing point 0 and a separator after them) the values are those whose empty
    cells come in ``x, y`` pairs (a missing point; a single empty coordinate is refused in any case); refused when
    more than one cut pairs them. A row of at most ``2 * count`` cells (136: the 68 iBUG points) is returned as it
    is: its empty cells are values."""
    width = 2 * count
    blank = [c == "" and (j >= len(names) or names[j] == "") for j, c in enumerate(cells)]
    starts = [s for s in range(len(cells) - width + 1) if all(blank[:s]) and all(blank[s + width :])]
    if not starts:
        return cells, names
    paired = [s for s in starts if all((cells[j] == "") == (cells[j + 1] == "") for j in range(s, s + width, 2))]
    if len(paired) > 1:
        raise InputError(f"{p}: one row of {len(cells)} cells, empty at both ends: which {width} are the x, y values "
                         f"is not known (a column before them left empty, or a missing point and a separator after "
                         f"them); remove the empty cells at one end")  # fmt: skip
    s = (paired or starts)[0]
    return cells[s : s + width], names[s : s + width]


def _named_row(names: list[str], row: list[float]) -> np.ndarray | None:
    """One row's values placed by a header's cells ``names`` naming each cell ``x<k>`` or ``y<k>`` (``x_0``, ``X 1``,
    ...; ``k`` from 0 or 1, each once): ``(K, 2)``; None when the header does not name them so."""
    keys = [m for n in names if (m := re.fullmatch(r"([xy])[_ ]?(\d+)", n.lower())) is not None]
    if len(names) != len(row) or len(row) % 2 or len(keys) != len(names):
        return None
    index = {(m.group(1), int(m.group(2))): v for m, v in zip(keys, row)}
    first = min(k for _, k in index)
    K = len(row) // 2
    wanted = [(c, first + k) for k in range(K) for c in "xy"]
    if first not in (0, 1) or set(index) != set(wanted):
        return None
    return np.asarray([index[w] for w in wanted], dtype=np.float64).reshape(K, 2)


def _openface_row(p: Path, names: list[str], rows: list[list[float]]) -> np.ndarray | None:
    """The first row's ``x_k``, ``y_k`` cells ``(K, 2)`` when the header's cells ``names`` name them (exactly so, lower
    case: OpenFace's 3D ``X_k`` are other columns) among other columns, every row as wide as the header; else None."""
    if not rows or any(len(r) != len(names) for r in rows):
        return None
    where = {n: i for i, n in enumerate(names)}
    K = sum(1 for n in names if re.fullmatch(r"x_\d+", n))
    xs, ys = [f"x_{k}" for k in range(K)], [f"y_{k}" for k in range(K)]
    if K == 0 or not all(n in where for n in xs + ys) or len(names) == 2 * K:
        return None
    if "success" in where and rows[0][where["success"]] != 1:
        raise InputError(f"{p}: the first row (OpenFace's first frame) has success 0: no landmarks to start from")
    return np.asarray([[rows[0][where[x]], rows[0][where[y]]] for x, y in zip(xs, ys)], dtype=np.float64)


#: Header names of the point-index column of a one-row-per-point CSV.
_INDEX_COLUMNS: tuple[str, ...] = ("ibug_index", "index", "point", "landmark")

#: Decimal arithmetic wide enough that ``x - 1`` of any float's digits is exact (the caller's context may be narrow),
#: and a number beyond float64's range is one (infinite as a float: refused as such), not an overflow.
_EXACT = Context(prec=64, Emax=MAX_EMAX, Emin=MIN_EMIN)


def _read_text(p: Path) -> str:
    """The file's text: UTF-8 (a byte order mark, Excel's "CSV UTF-8", is not a cell), UTF-16 after its byte order
    mark (Excel's "Unicode Text", tab-separated), else a spreadsheet's 8-bit export (Windows-1252 / Latin-1: its
    numbers read the same, its header's and comments' accents may not). A file with NUL bytes is not text."""
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputError(f"{p}: cannot read landmarks ({exc.strerror or exc.__class__.__name__})") from None
    utf16 = data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE))
    try:
        text = data.decode("utf-16" if utf16 else "utf-8-sig")
    except UnicodeDecodeError:
        if utf16:
            raise InputError(f"{p}: cannot read landmarks (a UTF-16 byte order mark, then no UTF-16 text)") from None
        text = data.decode("latin-1")
    if "\x00" in text:
        raise InputError(f"{p}: not a text file (NUL bytes): landmarks are a CSV, an iBUG .pts or a .npy file"
                         f"{_ground_truth_hint(p)}")
    return text


def _ground_truth_hint(p: Path) -> str:
    """Where a ``torchface.synth`` ground truth (``<name>.gt.json`` / ``<name>.gt.npz``, as ``torchface render-demo``
    writes them) was given as ``--landmarks``: the file beside it that is its first frame's landmarks (the natural
    choice was refused naming the format alone); ``""`` for any other file.

    Example:
        >>> _ground_truth_hint(Path("synth/pose_sweep.gt.npz")).split("; ")[1][:64]
        "its first frame's landmarks are synth/pose_sweep_first_frame.csv"
        >>> _ground_truth_hint(Path("lm.json")), _ground_truth_hint(Path(".gt.json"))
        ('', '')
    """
    for suffix in (".gt.json", ".gt.npz"):
        if p.name.endswith(suffix) and len(p.name) > len(suffix):
            first = p.with_name(p.name[: -len(suffix)] + "_first_frame.csv")
            return (f": a torchface.synth ground truth; its first frame's landmarks are {first} (torchface render-demo "
                    "writes it), or load_ground_truth(path).landmarks_px[0]")
    return ""


def _parse_json(p: Path, text: str, count: int = NUM_LANDMARKS) -> np.ndarray:
    """A JSON file's points: a list of ``[x, y]`` pairs (``null``: missing; also in a list of one, one frame's:
    ``(1, 68, 2)``) or of numbers, or an object holding such a list as ``initial_landmarks_px`` (a torchface
    sidecar's first-frame landmarks). ``count``: the points expected, as the messages name them."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{p}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
    if isinstance(value, dict):
        if value.get("initial_landmarks_px") is None:
            raise InputError(f"{p}: a JSON object without initial_landmarks_px (a torchface sidecar's): expected a "
                             f"list of {count} [x, y] pairs, or a sidecar{_ground_truth_hint(p)}")  # fmt: skip
        start = value.get("start")
        first = start.get("first_frame") if isinstance(start, dict) else None
        if isinstance(first, int) and first != 0:  # (a detector's first face: those landmarks are that frame's)
            raise InputError(f"{p}: that run started at frame {first} (where its detector first found the face): its "
                             f"initial_landmarks_px are that frame's, not the first frame's")  # fmt: skip
        value = value["initial_landmarks_px"]

    def number(c: object) -> float:
        if c is None:
            return math.nan
        if isinstance(c, bool) or not isinstance(c, (int, float)):
            raise ValueError
        return float(c)

    try:
        if not isinstance(value, list):
            raise ValueError
        if len(value) == 1 and isinstance(value[0], list) and value[0] and all(isinstance(v, list) for v in value[0]):
            value = value[0]  # one frame's points ``[[[x, y], ...]]``, (1, 68, 2), as an NPY of that shape is read
        if all(not isinstance(v, list) for v in value):  # 136 numbers x0, y0, x1, ...
            return np.asarray([number(v) for v in value], dtype=np.float64)
        if not all(isinstance(v, list) and len(v) == 2 for v in value):
            raise ValueError
        return np.asarray([[number(c) for c in v] for v in value], dtype=np.float64).reshape(-1, 2)
    except ValueError:
        raise InputError(f"{p}: expected a JSON list of {count} [x, y] pairs of numbers (null: missing), "
                         f"got {json.dumps(value)[:60]}") from None  # fmt: skip


def _is_pts(p: Path, text: str) -> bool:
    """Whether ``text`` is an iBUG ``.pts`` file: its name ends in ``.pts``, or its first line is ``version:`` or
    ``n_points:``."""
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    return p.suffix.lower() == ".pts" or re.match(r"(version|n_points)\s*:", first.lower()) is not None


def _zero_based_pts_problem(points: np.ndarray, width: int, height: int, count: int) -> str | None:
    """Why a ``.pts`` file's ``points`` (``(K, 2)``, 1 already subtracted: :func:`_parse_pts`) look written
    0-based, or None: some of its points lie left of or above a ``width x height`` frame read 1-based, as ``.pts``
    is (a coordinate under 0.5 in the file: 0, as OpenCV counts its first pixel), and every point lies in it read
    0-based, as written. Such a file was refused as points outside the frame, without a word of the convention; one
    whose points all lie at 0.5 or more cannot be told from a 1-based one, and is read 1-based. ``count``: the
    points expected (another count, or normalised coordinates, are refused as such by :func:`check_landmarks`)."""
    if points.shape != (count, 2):
        return None
    given = points[np.isfinite(points).all(axis=1)]
    low, high = NORMALISED_LANDMARK_RANGE
    written = given + 1
    if not len(given) or (((written >= low) & (written <= high)).all()
                          and np.ptp(written, axis=0).max() <= NORMALISED_LANDMARK_MAX_SPAN):  # fmt: skip
        return None
    u, v = given[:, 0], given[:, 1]
    before = (u < -0.5) | (v < -0.5)  # (read 1-based: left of or above the frame)
    as_written = (u + 1 >= -0.5) & (u + 1 <= width - 0.5) & (v + 1 >= -0.5) & (v + 1 <= height - 0.5)
    if not before.any() or not as_written.all():
        return None
    k = int(np.flatnonzero(before)[0])
    x, y = (_coordinate(c + 1, side) for c, side in ((given[k, 0], width), (given[k, 1], height)))
    return (f"{counted(int(before.sum()), 'point')} left of or above the {width}x{height} frame as a .pts is read, "
            f"1-based (the top-left pixel's centre at (1, 1): 1 is subtracted), e.g. ({x}, {y}) in the file, but "
            "every point inside it as written: is the file 0-based (the top-left pixel's centre at (0, 0), as OpenCV "
            "counts)? Add 1 to its coordinates, or save the points as a CSV (x,y), read as they are")


def _parse_pts(p: Path, text: str, count: int = NUM_LANDMARKS) -> np.ndarray:
    """An iBUG / 300-W ``.pts`` file's points ``(K, 2)``, 1 subtracted (1-based to torchface's 0-based pixel
    centres, exactly: in decimal before rounding to float64). ``K`` is checked against its ``n_points``; ``count``:
    the points expected, as the messages name them."""
    expected: tuple[int, int] | None = None  # (n_points, its line)
    points: list[list[float]] = []
    state = "header"  # -> "points" after '{' -> "end" after '}'
    number = 0
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if state == "end":
            raise InputError(f"{p}: line {number}: text after the closing '}}' of the .pts points: {line[:60]!r}")
        if state == "header":
            if line == "{":
                state = "points"
                continue
            m = re.fullmatch(r"([A-Za-z_]+)\s*:\s*(.*)", line)
            if m is None:
                raise InputError(f"{p}: line {number}: expected 'version: 1', 'n_points: {count}' or '{{' of a .pts "
                                 f"file, got {line[:60]!r}")  # fmt: skip
            key, value = m.group(1).lower(), m.group(2).strip()
            if key == "version" and value not in ("1", "1.0"):
                raise InputError(f"{p}: line {number}: .pts version {value[:20]!r}, only version 1 is read")
            if key == "n_points":
                if not value.isdigit():
                    raise InputError(f"{p}: line {number}: n_points is not a count: {value[:20]!r}")
                expected = (int(value), number)
            continue
        if line == "}":
            state = "end"
            if expected is not None and len(points) != expected[0]:
                raise InputError(f"{p}: line {number}: {counted(len(points), 'point')} before '}}', but n_points (line "
                                 f"{expected[1]}) says {expected[0]}")  # fmt: skip
            continue
        cells = line.split()
        try:
            if len(cells) != 2:
                raise ValueError
            points.append([float(_EXACT.subtract(Decimal(c), 1)) for c in cells])
        except (DecimalException, ValueError):
            raise InputError(f"{p}: line {number} is not a .pts point 'x y': {line[:60]!r}") from None
    if state == "header":
        raise InputError(f"{p}: no '{{' line: not a .pts file (version: 1, n_points: {count}, {{, {count} lines 'x y', "
                         "})")  # fmt: skip
    if state == "points":
        raise InputError(f"{p}: line {number}: the .pts points end without their closing '}}'")
    return np.asarray(points, dtype=np.float64).reshape(-1, 2)


def _delimiter(line: str, decimal_comma: bool = False) -> str | None:
    """The character that separates ``line``'s cells: a comma, semicolon or tab (``decimal_comma``,
    :func:`_decimal_comma`: a semicolon or tab, a comma being a decimal point); None: spaces."""
    return next((d for d in ((";", "\t") if decimal_comma else (",", ";", "\t")) if d in line), None)


def _long_columns(header: str, decimal_comma: bool = False) -> tuple[str | None, int, int, int] | None:
    """``(delimiter, index, x, y)`` column positions when ``header`` names a point-index column and ``x``, ``y``
    (a one-row-per-point CSV); None otherwise. ``delimiter`` None: cells separated by spaces (``decimal_comma``: see
    :func:`_delimiter`)."""
    delimiter = _delimiter(header, decimal_comma)
    names = [n.lower() for n in _split(header, delimiter)]
    index = next((names.index(n) for n in _INDEX_COLUMNS if n in names), None)
    if index is None or "x" not in names or "y" not in names:
        return None
    return delimiter, index, names.index("x"), names.index("y")


def _split(line: str, delimiter: str | None, decimal_comma: bool = False) -> list[str]:
    """A line's cells at ``delimiter`` (quotes honoured; None: spaces), stripped, quotes around a cell dropped;
    ``decimal_comma``: a comma in a cell is its decimal point (:func:`_decimal_comma`)."""
    try:
        cells = line.split() if delimiter is None else next(csv.reader([line], delimiter=delimiter))
    except csv.Error:  # (a NUL character on older Pythons): split without quoting
        cells = line.split(delimiter)
    return [c.strip().strip("\"'").strip().replace(",", "." if decimal_comma else ",") for c in cells]


def _parse_long(
    p: Path, lines: list[tuple[int, str]], columns: tuple[str | None, int, int, int], decimal_comma: bool = False,
    base: int = 0, unnamed: bool = False, count: int = NUM_LANDMARKS,
) -> np.ndarray:
    """``(count, 2)`` points of a one-row-per-point CSV (``lines``: its rows after the header, with their numbers;
    ``count``: the 68 iBUG points, or a face model's landmarks, indexed in its order); a point without a row, or with
    empty or ``nan`` ``x`` and ``y`` cells, is a NaN row (missing). ``decimal_comma``: see :func:`_decimal_comma`.
    ``base``: the index of point 0 (1: R's row names, 1..count). ``unnamed``: the index column's header cell is
    empty (pandas' index, or R's row names: an index with 0 and ``count`` is said to be neither)."""
    delimiter, index, x, y = columns
    points = np.full((count, 2), np.nan)
    what = "an iBUG index" if count == NUM_LANDMARKS else f"an index of the face model's {count} landmarks,"
    what += f" 0-{count - 1}"
    seen: dict[int, int] = {}
    for number, line in lines:
        cells = _split(line, delimiter, decimal_comma and delimiter in (";", "\t"))
        try:
            k_text, point = cells[index], [_number(cells[x]), _number(cells[y])]  # (empty: missing, NaN)
            k = int(k_text) - base
        except (IndexError, ValueError):
            raise InputError(f"{p}: line {number} is not 'index, x, y' numbers: {line[:60]!r}") from None
        if not 0 <= k < count:
            if base:  # (R's row names: 1..count)
                raise InputError(f"{p}: line {number}: row name {k + base} is not 1-{count} (an index reaching "
                                 f"{count} without 0 counts the points from 1, as R's row names do)")  # fmt: skip
            one_based = (f": the index has 0 and {count}, neither 0-based (pandas: 0-{count - 1}) nor 1-based (R's "
                         f"row names: 1-{count})" if unnamed and k == count else "")  # fmt: skip
            if not unnamed and k == count and not any(_index_cell(line, delimiter, index) == 0 for _, line in lines):
                # (a named index counted 1..68, as many annotation tools number the points: it said only that 68 is
                # not an iBUG index)
                one_based = (f": numbered from 1? The index column counts the points from 0 (0-{count - 1}): "
                             "subtract 1 from each index")
            raise InputError(f"{p}: line {number}: point index {k} is not {what}{one_based}")
        if k in seen:
            raise InputError(f"{p}: line {number}: point {k} again (first on line {seen[k]})")
        seen[k] = number
        points[k] = point
    return points  # (a point without a row stays NaN: missing)


def _index_cell(line: str, delimiter: str | None, index: int) -> int | None:
    """The index of a one-row-per-point CSV's ``line`` as :func:`_parse_long` reads it (``int``: ``"00"`` and ``"+0"``
    are 0), None where it has none or not an integer."""
    cells = _split(line, delimiter)
    try:
        return int(cells[index]) if index < len(cells) else None
    except ValueError:
        return None


def _parse_csv(p: Path, text: str, count: int = NUM_LANDMARKS) -> np.ndarray:
    """A CSV's points (:func:`_parse_csv_as`), its commas read as decimal ones where :func:`_decimal_comma` says so,
    unless only the comma-separated reading gives ``count`` points (one row of pairs ``x0,y0;x1,y1;...`` of
    integers). ``count``: the points expected (68, or a face model's landmarks), which the one-row-per-point layouts
    hold (indexed 0 to ``count - 1``)."""
    lines = [line for line in text.splitlines() if not line.strip().startswith("#")]
    if not _decimal_comma(lines):
        return _parse_csv_as(p, text, False, count)
    _check_not_grouped(p, lines)
    try:
        points: np.ndarray | None = _parse_csv_as(p, text, True, count)
    except InputError as exc:
        points, error = None, exc
    if points is None or points.size != 2 * count:
        try:
            separated = _parse_csv_as(p, text, False, count)
            if separated.size == 2 * count:
                return separated
        except InputError:
            pass
    if points is None:
        raise error
    return points


def _parse_csv_as(p: Path, text: str, comma: bool, count: int = NUM_LANDMARKS) -> np.ndarray:
    """A CSV's points; ``comma``: its commas are decimal ones (:func:`_decimal_comma`); ``count``: as
    :func:`_parse_csv`'s."""
    data: list[list[str]] = []  # the number rows' cells
    header: str | None = None
    long: tuple[str | None, int, int, int] | None = None
    long_lines: list[tuple[int, str]] = []
    lines = text.splitlines()
    # tab-separated: a tab at a line's ends separates cells, empty ones (``\t``: a missing point; ``5\t\t``)
    tabs = any("\t" in line.strip() for line in lines)
    for number, line in enumerate(lines, start=1):
        line = line.strip(" \r\n\f\v") if tabs else line.strip()
        if not line or line.lstrip().startswith("#"):
            continue
        if long is not None:  # one row per point: its other cells may be text (a point's meaning)
            long_lines.append((number, line))
            continue
        cells = _cells(line, comma)
        try:
            for c in cells:
                _number(c)
        except ValueError:
            if data or header is not None:  # one header line at most, before the numbers
                raise InputError(f"{p}: line {number} is not numbers: {line[:60]!r}") from None
            header = line
            long = _long_columns(header, comma)
            continue
        data.append(cells)
        long_lines.append((number, line))
    if long is not None:
        return _parse_long(p, long_lines, long, comma, count=count)
    # pandas' DataFrame.to_csv with its index (the point's): a header ``,x,y`` (``,0,1``: numbers), rows ``k,x,y``
    # (or ``,y,x``: the points' columns in that order, ``DataFrame(points[:, ::-1], columns=["y", "x"])``)
    first = _trimmed(_cells(header, comma), 0) if header is not None else data[0] if data else []
    if [n.lower() for n in first] in (["", "x", "y"], ["", "0", "1"], ["", "y", "x"]):
        indexed = long_lines if header is not None else long_lines[1:]
        index_rows = data[len(data) - len(indexed) :]
        if indexed and all(len(_trimmed(c, 3)) == 3 and c[0].isdigit() for c in index_rows):
            # pandas' index counts the points from 0, R's write.csv's row names (``"1",x,y``) from 1 (1..68; 1..count),
            # and either may leave a point's row out (dropna, na.omit: R keeps the others' names): an index with 0 is
            # 0-based, one reaching 68 and without 0 1-based (0-67 has no 68); one with neither (R's 1..67 without
            # point 68, pandas' 1..67 without point 0: the same file but for R's quotes, which neither always writes)
            # is refused
            indices = {int(c[0]) for c in index_rows}
            if 0 not in indices and max(indices) < count:
                raise InputError(
                    f"{p}: its index column (unnamed: pandas' index or R's row names) has neither 0 nor {count}, so "
                    f"whether it counts the points from 0 (pandas; point 0 missing) or from 1 (R's write.csv; its "
                    f"last point missing) is not known: keep a row for every point, a missing one's x and y NA or "
                    f'empty (R: "{count}",NA,NA), or name the column ibug_index, 0-based '
                    '(to_csv(index_label="ibug_index"))'
                )
            x, y = (2, 1) if first[1].lower() == "y" else (1, 2)
            columns = (_delimiter(indexed[0][1], comma), 0, x, y)
            return _parse_long(p, indexed, columns, comma, base=int(0 not in indices), unnamed=True, count=count)
    # A row's empty cells are missing values (NaN) in their places, but not those a separator ending every line
    # leaves beyond the row's width: the header's where it names the cells (OpenFace's, x_k / y_k), else one row of
    # 136 or rows of 2 (``x,y,``: x and y; under a header of other words, a title or ``x,y,note``, as without one).
    names = _trimmed(_cells(header, comma), 0) if header is not None else []
    # (``--landmarks results/clip.csv``: "got rows of [62] values"; one whose x_k, y_k columns were added to its
    # rows holds landmarks, read as OpenFace's are)
    if {"frame", "pose_Tx", "yaw_deg"} <= set(names) and "x_0" not in names:
        sidecar = Path(p.name.removesuffix(".partial")).with_suffix(".json").name
        raise InputError(f"{p}: a torchface track CSV, which holds no landmarks: give its JSON sidecar ({sidecar}), "
                         "whose initial_landmarks_px are the landmarks its run started from")  # fmt: skip
    if len(data) == 1:  # one row of 136 with a column before it left empty (``,x0,y0,...``): that column is no cell
        cells, names = _one_row_values(p, data[0], names, count)
        data = [cells]
    if header is not None:
        rows = _number_rows(data, len(names))
        openface = _openface_row(p, names, rows)
        if openface is not None:  # OpenFace's per-frame CSV: the first frame's x_k, y_k among its other columns
            return openface
        named = _named_row(names, rows[0]) if len(rows) == 1 else None
        if named is not None:  # e.g. OpenFace's x_0..x_67, y_0..y_67: not interleaved
            return named
    rows = _number_rows(data, 2 if len(data) > 1 else 2 * count)
    kept = _without_empty_columns(data) if len(rows) > 1 and {len(r) for r in rows} != {2} else None
    if kept is not None and {len(r) for r in _number_rows(kept, 2)} == {2}:  # ``,x,y``: x, y (as before the
        rows = _number_rows(kept, 2)  # missing points, which dropped every empty cell), a missing point ``,,``
    if len(rows) == 1:
        values = np.asarray(rows[0], dtype=np.float64)
        if (planar := planar_layout_problem(values, count)) is not None:
            raise InputError(f"{p}: {planar} (or name the columns: x_0, ..., x_67, y_0, ..., y_67)")
        return values.reshape(-1, 2) if len(rows[0]) % 2 == 0 else np.asarray(rows[0])
    widths = {len(r) for r in rows}
    if len(widths) > 1 or (rows and len(rows[0]) != 2):
        # (two rows of ``count``: the points transposed, ``np.savetxt(path, points.T)``, told as any other width)
        hint = (f": a row of x and a row of y, the points transposed? Write one 'x, y' row per point (np.savetxt "
                f"of the ({count}, 2) points, not of points.T)") if len(rows) == 2 and widths == {count} else ""
        raise InputError(f"{p}: expected rows of 'x, y' (or, one row per point, a header naming ibug_index, x and y "
                         f"columns), got rows of {sorted(widths)} values{hint}")  # fmt: skip
    points = np.asarray(rows, dtype=np.float64).reshape(-1, 2)
    # a header naming the columns ``y, x`` (image coordinates as (row, column): ``DataFrame(points[:, ::-1],
    # columns=["y", "x"]).to_csv(index=False)``) says which is which: they were read as x, y, the face transposed
    words = [n.lower() for n in names if n]
    if words == ["y", "x"]:
        return points[:, ::-1].copy()
    if len(words) == 2 and _names_y_first(words):  # ``y_px, x_px``, ``row, col``: read as x, y, every point swapped
        raise InputError(f"{p}: the header {', '.join(names)!r} names the y (row) column first: name the columns "
                         "exactly 'x,y' or 'y,x' (their order is then read from the header), or drop the header")
    return points


def _names_y_first(names: list[str]) -> bool:
    """Whether two header cells ``names`` (lower case) name a y (row) column before an x (column) one in words other
    than exactly ``y, x``: ``y_px, x_px``, ``lm_y, lm_x``, ``row, col``. Those were read as x, y without a word."""
    tokens = [set(re.split(r"[^a-z]+", n)) - {""} for n in names]
    return bool(tokens[0] & {"y", "row", "rows"}) and bool(tokens[1] & {"x", "col", "cols", "column", "columns"})


def missing_points_problem(points: np.ndarray, what: str = "iBUG points") -> str | None:
    """What is wrong, as one line, with ``(K, 2)`` pixel landmarks whose NaN rows are missing points (a landmarks
    file's, :func:`check_landmarks` with ``missing``; ``training_hooks``' first-frame landmarks), or None: an infinite
    coordinate or a row with one coordinate NaN (:func:`~torchface.tracker.fit.landmark_rows_problem`, the rule the
    Python API's landmarks follow too), or fewer points given than the landmark fit's
    :data:`~torchface.tracker.fit.MIN_FIT_LANDMARKS` (4). ``what`` names the points.

    Example:
        >>> points = np.full((68, 2), np.nan)
        >>> points[:3] = 10.0
        >>> missing_points_problem(points)
        '3 of the 68 iBUG points given, the others missing (NaN): the landmark fit needs at least 4'
        >>> points[3:8] = 20.0
        >>> missing_points_problem(points) is None
        True
    """
    points = np.asarray(points, dtype=np.float64)
    # (here: the tracker imports torch and the model)
    import torch

    from torchface.tracker.fit import MIN_FIT_LANDMARKS, landmark_rows_problem

    # the rule of every landmark input, the Python API's too: an infinite coordinate, or one coordinate NaN alone
    problem = landmark_rows_problem(torch.from_numpy(np.ascontiguousarray(points)), weighted=False)
    if problem is not None:
        return problem
    nan = np.isnan(points)
    given = int((~nan.any(axis=1)).sum())
    if given < MIN_FIT_LANDMARKS:
        return (f"{given} of the {len(points)} {what} given, the others missing (NaN): the landmark fit needs at "
                f"least {MIN_FIT_LANDMARKS}")  # fmt: skip
    return None


#: The 68 iBUG points of a frontal face, ``(68, 2)``, centred, unit Frobenius norm (the mean of 45 frames within 5
#: degrees of frontal of the synthetic ``pose_sweep`` sequence, CANDIDE-3; x right, y down): the shape a flat
#: vector's two readings are compared with (:func:`planar_layout_problem`), not a detector's model.
_IBUG_FRONTAL: np.ndarray = np.array([
    -0.146, -0.085, -0.139, -0.037, -0.132, 0.011, -0.118, 0.057, -0.104, 0.102, -0.085, 0.126,
    -0.066, 0.150, -0.045, 0.176, 0.000, 0.190, 0.045, 0.176, 0.066, 0.150, 0.086, 0.126,
    0.105, 0.102, 0.119, 0.057, 0.133, 0.011, 0.140, -0.037, 0.147, -0.085, -0.132, -0.120,
    -0.117, -0.134, -0.102, -0.147, -0.069, -0.136, -0.035, -0.124, 0.034, -0.124, 0.068, -0.136,
    0.102, -0.147, 0.117, -0.134, 0.132, -0.120, 0.000, -0.107, 0.000, -0.070, 0.000, -0.036,
    0.000, -0.001, -0.045, 0.012, -0.032, 0.019, 0.000, 0.019, 0.032, 0.019, 0.045, 0.012,
    -0.100, -0.092, -0.087, -0.101, -0.059, -0.104, -0.044, -0.093, -0.059, -0.087, -0.087, -0.088,
    0.044, -0.093, 0.059, -0.103, 0.087, -0.100, 0.100, -0.092, 0.087, -0.088, 0.059, -0.087,
    -0.060, 0.068, -0.030, 0.056, -0.012, 0.054, 0.000, 0.060, 0.011, 0.054, 0.030, 0.056,
    0.060, 0.068, 0.030, 0.082, 0.015, 0.085, 0.000, 0.089, -0.015, 0.085, -0.030, 0.082,
    -0.048, 0.067, -0.024, 0.069, 0.000, 0.071, 0.024, 0.069, 0.048, 0.067, 0.024, 0.069,
    0.000, 0.071, -0.024, 0.069
]).reshape(68, 2)
_IBUG_FRONTAL = (_IBUG_FRONTAL - _IBUG_FRONTAL.mean(0)) / np.linalg.norm(_IBUG_FRONTAL - _IBUG_FRONTAL.mean(0))

#: A reading of a flat vector below this Procrustes distance from :data:`_IBUG_FRONTAL` places the points as a face.
_FACE_LIKE: float = 0.5
#: ... and above this one does not (:func:`planar_layout_problem`).
_NOT_FACE_LIKE: float = 0.85


def _face_distance(points: np.ndarray) -> float:
    """The Procrustes distance of ``(68, 2)`` finite points from :data:`_IBUG_FRONTAL` (translation, scale, rotation
    and reflection removed): ``sqrt(1 - s**2)``, ``s`` the sum of the singular values of the normalised points'
    cross-covariance with it, 0 for the same shape up to a similarity, 1 for one unrelated to it (or all points at
    one place). The points are first divided by their largest magnitude (the distance does not depend on it), so
    that coordinates near float64's range neither overflow nor underflow (judged, without a RuntimeWarning)."""
    top = float(np.abs(points).max())
    if not top > 0 or not math.isfinite(top):
        return 1.0
    q = points / top
    q = q - q.mean(0)
    norm = float(np.linalg.norm(q))
    if not norm > 0 or not math.isfinite(norm):
        return 1.0
    fit = float(np.linalg.svd(_IBUG_FRONTAL.T @ (q / norm), compute_uv=False).sum())
    return math.sqrt(max(0.0, 1.0 - fit * fit))


def planar_layout_problem(values: np.ndarray, count: int = NUM_LANDMARKS) -> str | None:
    """Why a flat ``(2 * count,)`` landmark vector (read interleaved, ``x0, y0, x1, y1, ...``, as every flat form is)
    looks planar (``x0, ..., x67, y0, ..., y67``, e.g. ``points.T.reshape(-1)`` or OpenFace's column order without
    its header), or None.

    Only 68 finite iBUG points are judged: the vector is refused where its interleaved reading lies more than
    :data:`_NOT_FACE_LIKE` (0.85) from a frontal face's layout (Procrustes distance: position, size, rotation and
    mirroring removed) while its planar reading lies within :data:`_FACE_LIKE` (0.5) of it. Read interleaved, a
    planar vector pairs neighbouring points' x (or y) values, points strung along the line ``x = y``. Measured on
    14040 faces (the synthetic sequences' ground-truth landmarks, and projections of their 3D landmarks at yaw up
    to 95 degrees, pitch up to 70, any roll, mirrored, stretched up to 35 % on one axis, perspective from 0.6 to 50
    face sizes away, noise up to 3 % of their size, placed anywhere or on the image diagonal): the planar reading of
    a genuine (interleaved) vector lay at least 0.90 from the frontal layout (0.84 over 163178 more: 21 of the ICT
    model's identities with expressions and a scanned face, yaw to 100, pitch to 85, points clamped to a line,
    collapsed onto one, rounded, float32; a search over pose, shear and perspective found none nearer than 0.81),
    so none was refused; of the planar vectors 98 % of the sequences' faces and 58 % of that whole range were
    refused (the faces far from frontal fit neither reading: let through, as before).
    """
    flat = np.asarray(values, dtype=np.float64).reshape(-1)
    if count != NUM_LANDMARKS or flat.size != 2 * count or not np.isfinite(flat).all():
        return None
    interleaved, planar = flat.reshape(count, 2), flat.reshape(2, count).T
    if _face_distance(interleaved) > _NOT_FACE_LIKE and _face_distance(planar) < _FACE_LIKE:
        return (f"the {2 * count} values read as x0, y0, x1, y1, ... (a flat vector's order) do not place the "
                f"{count} iBUG points as a face, but read as all x then all y they do: pass points.reshape(2, "
                f"{count}).T, or the ({count}, 2) points")
    return None


def mirror_landmarks(landmarks_px: _Points, width: int) -> _Points:
    """The iBUG-68 pixel landmarks of frames mirrored left-right (``frames.flip(-1)``: a flip augmentation), from
    those of the frames: ``x -> width - 1 - x`` (pixel centres at integers, :mod:`torchface.conventions`) and each
    point swapped with its mirror partner (:data:`~torchface.conventions.IBUG68_MIRROR`: the jaw's 0 <-> 16, the eyes'
    outer corners 36 <-> 45, ...), so that they are iBUG-68's again, in its order. The x coordinates flipped alone
    are a mirrored face, which the tracker's landmark fit fails (``StartFailure.NO_POSE``). A NaN row (a missing
    point) moves with its point. The mirrored frames' camera is ``cx -> width - 1 - cx`` (the default intrinsics
    are centred: the same); their head pose has yaw and roll negated.

    Args:
        landmarks_px: ``(..., 68, 2)`` pixel ``(x, y)``, a tensor (differentiable; device and dtype kept) or a NumPy
            array (dtype kept, floating).
        width: the frames' width in pixels.

    Returns:
        ``(..., 68, 2)`` of the same type; ``mirror_landmarks(mirror_landmarks(p, W), W)`` is ``p`` (to float
        rounding).

    Example:
        >>> flipped = frames.flip(-1)                                         # doctest: +SKIP
        >>> result = tracker.initialise(flipped, mirror_landmarks(landmarks, frames.shape[-1]))  # doctest: +SKIP
    """
    import torch

    if isinstance(width, bool) or not isinstance(width, (int, np.integer)) or width < 1:
        raise TypeError(f"width must be the frames' width in pixels, a positive int, got {width!r}")
    if isinstance(landmarks_px, np.ndarray):
        floating = bool(np.issubdtype(landmarks_px.dtype, np.floating))
    elif isinstance(landmarks_px, torch.Tensor):
        floating = landmarks_px.is_floating_point()
    else:
        raise TypeError(f"landmarks_px must be a tensor or NumPy array (..., 68, 2), got {type(landmarks_px).__name__}")
    if tuple(landmarks_px.shape[-2:]) != (NUM_LANDMARKS, 2):
        raise ValueError(f"landmarks_px must be (..., {NUM_LANDMARKS}, 2) iBUG-68 pixel points, got "
                         f"{tuple(landmarks_px.shape)}")  # fmt: skip
    if not floating:
        raise TypeError(f"landmarks_px must be floating pixel coordinates, got {landmarks_px.dtype}")
    points = landmarks_px[..., list(IBUG68_MIRROR), :]
    x, y = (width - 1) - points[..., 0], points[..., 1]
    if isinstance(points, np.ndarray):
        return np.stack([x, y], axis=-1).astype(points.dtype, copy=False)
    return torch.stack([x, y], dim=-1)


def landmarks_shape_hint(shape: tuple[int, ...], count: int, name: str = "landmarks") -> str:
    """What to do with landmarks of ``shape`` where ``(count, 2)`` was wanted, as `` (...)`` ("" when nothing fits):
    :func:`check_landmarks`' and ``training_hooks``' words for the points transposed, 3D points or a set per frame.

    Example:
        >>> landmarks_shape_hint((2, 68), 68)
        ' (x, y rows: landmarks.T)'
    """
    if shape == (2, count):
        return f" (x, y rows: {name}.T)"
    if shape == (count, 3):
        return f" (x, y, z points, as 3D landmark detectors give them: {name}[:, :2])"
    if len(shape) == 3 and shape[1:] == (count, 2) and shape[0] > 1:
        return f" (a set per frame or per stream? one set, of the first frame: {name}[0])"
    return ""


def _check_frame_size(width: object, height: object) -> None:
    """Refuse a frame size that is not whole positive pixels (``"160"`` from a command line's text met a bare
    ``TypeError`` in the arithmetic; ``160.5`` was taken as a frame's edge at 160.5). A ``TypeError``, the
    constructor's of :class:`~torchface.geometry.Intrinsics` (a caller's mistake, not the file's)."""
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < 1:
            raise TypeError(f"{name} must be a whole positive number of pixels (an int), got {value!r}")


#: The fraction of a landmarks file's given points (and a detector's) that must lie inside the frame
#: (:func:`check_landmarks`' ``min_inside``): half. A face at the frame's edge has points just outside it (an
#: annotated chin a pixel below the frame, dlib's), which ``FaceTracker.initialise`` fits as given; a file's were
#: refused, all of them had to lie inside (``torchface track`` refused what the Python API took). More than half
#: outside is refused: most likely landmarks of another frame size (the Python API's start fails then,
#: ``StartFailure.OUTSIDE_FRAME``).
FILE_MIN_INSIDE: float = 0.5


def check_landmarks(
    points: np.ndarray, width: int, height: int, where: str, *, min_inside: float = FILE_MIN_INSIDE,
    missing: bool = False, missing_as: str = "", count: int = NUM_LANDMARKS,
) -> np.ndarray:
    """Check ``(count, 2)`` pixel landmarks (68 iBUG points by default) against a ``width x height`` frame; returns
    them as float64.

    ``min_inside``: the fraction of the points that must lie inside the frame (:data:`FILE_MIN_INSIDE`, half of
    them, as a landmarks file's and a detector's are checked: a face at the frame's edge has points just outside
    it, dlib's predictor places its chin there, and ``FaceTracker.initialise`` fits them; 1: all of them).

    ``missing``: whether a NaN row ``(nan, nan)`` is a missing point (a landmarks file's occluded points), passed on
    as NaN for the landmark fit to give weight 0, as the tracker's Python API takes it; the points given (finite
    rows) must then be at least the fit's :data:`~torchface.tracker.fit.MIN_FIT_LANDMARKS` (4), and ``min_inside``
    counts them alone. False: every point must be finite (a detector's, which gives all or none).

    ``missing_as``: how the points' source writes a missing point, for the error on a wrong count (with
    ``missing``: "a missing point stays, as a NaN row", then ``: {missing_as}`` where given; :func:`read_landmarks`
    gives its file format's way, e.g. ``"empty cells or nan"`` for a CSV; an array's caller none).

    ``count``: the number of points, a face model's ``K`` (:attr:`~torchface.model.FaceModel.num_landmarks`;
    ``torchface track --model``): its landmarks, in its order, rather than the 68 iBUG points.

    The points returned are a C-contiguous copy of ``points``.

    Float16 points are warned of (rounded: 0.5 px steps from 512 px, 1 px from 1024), and read as they are.

    Raises:
        InputError: not real numbers (bool, complex, text), wrong count, non-finite values (with ``missing``:
            infinite ones, a row with one coordinate NaN, or fewer than 4 points given), (more than
            ``1 - min_inside`` of the) points outside the frame, or, in frames of 8 pixels a side at least, points
            all within ``[-0.5, 1.5] x [-0.5, 1.5]`` spanning at most 1.5 and not all at one point (normalised
            coordinates, MediaPipe's, not pixels; a little outside ``[0, 1]`` for a face partly out of the frame).
    """
    _check_frame_size(width, height)
    dtype = np.asarray(points).dtype
    if not (np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.floating)):  # (complex: its imaginary part
        raise InputError(f"{where}: landmarks must be real numbers, got {dtype}")  # was dropped with a warning)
    if dtype == np.float16:  # (read as float64 without a word: 0.5 px steps from 512 px, 1 px from 1024)
        warnings.warn(f"{where}: landmarks are {half_precision_rounding('float16', float(np.finfo(np.float16).eps))}: "
                      "they are read as rounded (converting them back cannot restore the digits lost); save the "
                      "points as float32 or float64", UserWarning, stacklevel=2)  # fmt: skip
    # a copy, C-contiguous (a detector's view with a negative stride: torch refuses it; its reused buffer)
    points = np.array(points, dtype=np.float64, order="C")
    if points.ndim == 3 and points.shape[0] == 1:
        points = points[0]
    if points.ndim == 1 and points.size % 2 == 0:
        planar = planar_layout_problem(points, count)
        if planar is not None:
            raise InputError(f"{where}: {planar}")
        points = points.reshape(-1, 2)
    if points.ndim != 2 or points.shape[1] != 2:  # ((2, K) was told its shape alone: np.save(path, points.T))
        hint = landmarks_shape_hint(points.shape, count, "points")
        raise InputError(f"{where}: expected {count} (x, y) points, got an array of shape {points.shape}{hint}")
    if points.shape[0] != count:
        hint = f" (a missing point stays, as a NaN row{': ' + missing_as if missing_as else ''})" if missing else ""
        what = "iBUG landmarks" if count == NUM_LANDMARKS else "landmarks (the face model's)"
        if count == NUM_LANDMARKS and points.shape[0] in MEDIAPIPE_MESH_POINT_COUNTS:  # (told the count alone)
            hint = f" ({MEDIAPIPE_MESH_HINT})"
        # (a file's reader, torchface track's user, was told the Python of an array: a file keeps its first 68 rows)
        keep = "keep the file's first 68 rows" if missing_as else "points[:68]"
        other = other_landmark_set_hint(points.shape[0], keep) if count == NUM_LANDMARKS else None
        if other is not None:  # (WFLW's 98 points were told that a missing point stays as a NaN row)
            hint = f" ({other})"
        raise InputError(f"{where}: expected {count} {what}, got {points.shape[0]}{hint}")
    given = np.isfinite(points).all(axis=1)
    if not missing and not given.all():
        raise InputError(f"{where}: landmark(s) {np.flatnonzero(~given).tolist()[:8]} are NaN or infinite")
    named = "iBUG points" if count == NUM_LANDMARKS else "landmarks"
    problem = missing_points_problem(points, named) if missing else None
    if problem is not None:
        raise InputError(f"{where}: {problem}")
    u, v = points[:, 0], points[:, 1]
    outside = (u < -0.5) | (u > width - 0.5) | (v < -0.5) | (v > height - 0.5)  # (False for a missing point)
    if outside.sum() > (1.0 - min_inside) * int(given.sum()):
        k = int(np.flatnonzero(outside)[0])
        raise InputError(
            f"{where}: {int(outside.sum())} landmark(s) outside the {width}x{height} frame, e.g. point {k} at "
            f"({_coordinate(points[k, 0], width)}, {_coordinate(points[k, 1], height)}) (the frame spans x -0.5 to "
            f"{width - 0.5}, y -0.5 to {height - 0.5}: pixel centres at integers)"
            + (f"; at most {'half' if min_inside == 0.5 else f'{1.0 - min_inside:.0%}'} of the points given may lie "
               "outside it (a face at the frame's edge)" if min_inside < 1.0 else "")
            # (a point a pixel out of the frame, which initialise takes, was refused without a word of the way out)
            + (f"; a point the frame does not show is given as missing"
               f"{' (' + missing_as + ')' if missing_as else ', a NaN row'}" if missing else "")
        )  # (the point was written to 0.1: one 0.01 px outside read "at (-0.5, ...)", the frame's very edge)
    kept = points[given]
    low, high = NORMALISED_LANDMARK_RANGE
    if (len(kept) and min(width, height) >= NORMALISED_CHECK_MIN_SIDE and ((kept >= low) & (kept <= high)).all()
            and 0 < np.ptp(kept, axis=0).max() <= NORMALISED_LANDMARK_MAX_SPAN):
        # (the rule torchface.conventions writes down, as initialise checks it: check_pixel_landmarks)
        # (MediaPipe's normalised points passed as pixels: a face under a pixel wide, whose fit failed: every row
        # of the video unsuccessful; the tracker's initialise refuses them too, naming no file)
        # (training_hooks checks an array before it knows the frame size, with a size of 2**30: no numbers then)
        w, h = (str(width), str(height)) if max(width, height) < 1 << 30 else ("W", "H")
        raise InputError(
            f"{where}: every point lies within [{low}, {high}] x [{low}, {high}]: normalised coordinates (x / W, "
            f"y / H, as MediaPipe writes them)? Give pixels, centres at integers: x * {w}, y * {h}"
        )
    return points


def _coordinate(value: float, side: int) -> str:
    """A coordinate of a frame ``side`` pixels across as a message gives it: to 0.1 where that is its value, else to
    10 digits (``-0.51``, not the ``-0.5`` that reads as the frame's edge), or more where a value outside the frame
    (``-0.5 .. side - 0.5``) would read as inside it (``99.50000000001``, not ``99.5``)."""
    short = f"{value:.1f}"
    if float(short) == value:
        return short
    text = f"{value:.10g}"
    outside = not -0.5 <= value <= side - 0.5
    if outside and -0.5 <= float(text) <= side - 0.5:  # (written to 10 digits it reads as the edge: all of them)
        text = repr(float(value))
    return text


def read_landmarks(
    path: str | os.PathLike[str], width: int, height: int, *, missing: bool = True, count: int = NUM_LANDMARKS
) -> np.ndarray:
    """Read and check 68 first-frame landmarks (or ``count``) for a ``width x height`` video.

    Args:
        path: a ``.csv`` (or any text), iBUG ``.pts``, ``.npy`` or ``.json`` file, see the module docstring.
        width: frame width W.
        height: frame height H.
        missing: whether the file may leave points out (NaN rows, see the module docstring; at least 4 given, the
            landmark fit's :data:`~torchface.tracker.fit.MIN_FIT_LANDMARKS`); False: all 68 must be given.
        count: the number of points: a face model's ``K`` landmarks (``torchface track --model``) in its order,
            rather than the 68 iBUG points. Every layout holds that count: one row of ``2 * count`` values, one row
            per point with an index ``0`` to ``count - 1`` in the model's order (pandas' index; R's row names
            ``1`` to ``count``), OpenFace's ``x_k``, ``y_k`` columns, rows of ``x, y``, ``.pts``, NPY and JSON.

    Returns:
        ``(count, 2)`` float64 pixel coordinates, a NaN row for each missing point.

    Raises:
        InputError: missing or unreadable file, wrong count, infinite values, too few points given (or, without
            ``missing``, any NaN), or out-of-frame points.
        TypeError: ``width`` or ``height`` not a whole positive number (``"160"``, ``160.5``).

    Example:
        >>> # points = read_landmarks("first_frame.csv", 640, 480)   # (68, 2)
    """
    _check_frame_size(width, height)  # (before the file is read: a caller's mistake, whatever the file holds)
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: a folder, not a landmarks file" if p.is_dir()
                         else f"{p}: no such landmarks file{missing_path_hint(path)}")  # fmt: skip
    if p.suffix.lower() == ".npy":
        try:
            points = np.load(p, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:  # EOFError: an empty file (np.save interrupted)
            raise InputError(f"{p}: not a readable .npy array ({exc})") from None
        if not isinstance(points, np.ndarray):  # an .npz archive under an .npy name (np.savez): its arrays
            points.close()
            raise InputError(f"{p}: an .npz archive of arrays ({', '.join(points.files)[:60]}), not one .npy array: "
                             f"save the ({count}, 2) points with np.save")  # fmt: skip
        missing_as = ""  # (an NPY's missing point is a NaN row)
    else:
        text = _read_text(p)
        pts = _is_pts(p, text)
        if p.suffix.lower() == ".json":
            points, missing_as = _parse_json(p, text, count), "[null, null]"
        else:
            points = _parse_pts(p, text, count) if pts else _parse_csv(p, text, count)
            missing_as = "a line 'nan nan'" if pts else "empty cells or nan"
            zero_based = _zero_based_pts_problem(points, width, height, count) if pts else None
            if zero_based is not None:
                raise InputError(f"{p}: {zero_based}")
    return check_landmarks(points, width, height, str(p), missing=missing, missing_as=missing_as, count=count)
