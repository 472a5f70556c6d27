"""CANDIDE-3 (J. Ahlberg, 2001): parse the ``.wfm`` file and build a :class:`FaceModel` from it.

The paper's model (Eq. 1) is CANDIDE-3: ``g = g_bar + S sigma + A alpha`` with 14 shape units and, for
tracking, the 11 animation unit vectors (AUVs) that the file links to FACS action units. The file also
holds 54 MPEG-4 facial animation parameters (FAPs) whose rows are unit directions scaled by a facial
animation parameter unit (FAPU):

    displacement = value * FAPU / 1024 * direction.

Loading converts the file frame (+x subject's left, +y up, +z toward the viewer, normalised units) to the
head frame of :mod:`torchface.conventions` (+y down, +z away from the viewer, millimetres): a 180 degree
rotation about x followed by the scale :data:`~torchface.conventions.MM_PER_CANDIDE_UNIT`. Triangles are
re-wound consistently and outward, vertices are never welded, and the package's own data files
(``torchface/data``) supply the iBUG-68 landmark table and the AUV -> FACS table with coefficient ranges.

Shapes: ``V`` vertices, ``F`` triangles, ``S`` shape units, ``A`` animation units, ``K`` landmarks.
"""

from __future__ import annotations

import csv
import enum
import io
import os
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import torch

from torchface._device import check_device
from torchface.conventions import MM_PER_CANDIDE_UNIT
from torchface.geometry._checks import check_choice
from torchface.model.face_model import FaceModel
from torchface.model.topology import make_winding_consistent, orient_outward, unused_vertices

__all__ = [
    "AnimationSet",
    "WfmUnit",
    "WfmFile",
    "parse_wfm",
    "candide3_fapu",
    "load_candide3",
    "read_landmark_table",
    "read_auv_facs_table",
    "FILE_TO_HEAD",
    "FAP_EYEBALL_FAPU",
]

#: Rotation taking CANDIDE-3 file coordinates to the head frame (180 degrees about x), before scaling.
FILE_TO_HEAD = np.diag([1.0, -1.0, -1.0])

#: FAPU used for FAPs 23-30 (eyeball yaw/pitch/thrust, pupil dilation), which carry no FAPU comment in
#: the file. MPEG-4 measures 23-26 in angle units, which a linear vertex displacement cannot represent;
#: the iris diameter makes a value of 1024 move the iris/pupil vertices by one iris diameter (about
#: 8.7 mm, an eyeball rotation of roughly 40 degrees), which keeps all eight on the scale of the eye.
FAP_EYEBALL_FAPU = "IRISD"

#: Interior point of the head in file coordinates (behind the mask), used to orient the triangles outward.
_HEAD_CENTRE_FILE = np.array([0.0, 0.0, -0.6])

#: CANDIDE-3 vertices that realise the MPEG-4 feature points each FAPU is measured between.
_PUPIL_LEFT = (67, 68, 71, 72)  # iris corners of the subject's left eye (feature point 3.5 = their centre)
_PUPIL_RIGHT = (69, 70, 73, 74)  # iris corners of the subject's right eye (feature point 3.6)
_IRIS_TOP_BOTTOM = ((67, 68), (69, 70))  # upper/lower iris vertices of each eye (3.1-3.3, 3.2-3.4)
_NOSE_BOTTOM = 6  # subnasale (feature point 9.15)
_MOUTH_MIDDLE = 87  # inner upper lip middle, on the mouth line (2.2)
_MOUTH_CORNERS = (31, 64)  # outer lip corners (8.3, 8.4)

#: FAP range (in FAP units) used for every FAP: one FAPU either way.
_FAP_RANGE = (-1024.0, 1024.0)

_SECTION_RE = re.compile(r"^#\s*([A-Z][A-Z ]*[A-Z])\s*:\s*$")
_AUV_RE = re.compile(r"^AUV\s*(\d+)\s+(.*?)\s*(?:\(([^)]*)\))?\s*$")
_FAP_RE = re.compile(r"^FAP\s*(\d+)\s+(\S.*?)\s*$")
_FAPU_RE = re.compile(r"^[A-Z]{2,6}$")


class AnimationSet(enum.Enum):
    """Which CANDIDE-3 animation units a loaded model exposes (in file order)."""

    #: The 11 animation unit vectors linked to FACS (the tracking set of the paper).
    AUV = "auv"
    #: The 11 AUVs followed by the 54 MPEG-4 FAPs (65 units).
    AUV_AND_FAP = "auv_and_fap"
    #: The 54 MPEG-4 FAPs only.
    FAP = "fap"


@dataclass(frozen=True)
class WfmUnit:
    """One animation or shape unit of a ``.wfm`` file.

    Attributes:
        comments: comment lines that precede the unit, ``#`` stripped: its name first (e.g.
            ``"AUV11 Jaw drop (AU26/27)"``, ``"FAP 3 open_jaw"``), then for FAPs the FAPU (``"MNS"``).
        vertex_indices: ``(n,)`` int64 vertices the unit moves.
        vectors: ``(n, 3)`` float64 rows in file coordinates: displacements for AUVs and shape units,
            directions for FAPs.
    """

    comments: tuple[str, ...]
    vertex_indices: np.ndarray
    vectors: np.ndarray

    @property
    def name(self) -> str:
        """The first comment line (empty when the unit has none)."""
        return self.comments[0] if self.comments else ""

    @property
    def fapu(self) -> str | None:
        """The FAPU comment (``"MNS"``, ``"MW"``, ``"ENS"``, ``"ES"``, ``"IRISD"``) or ``None``."""
        for comment in self.comments[1:]:
            if _FAPU_RE.match(comment):
                return comment
        return None

    @property
    def is_fap(self) -> bool:
        """Whether the unit is an MPEG-4 FAP (its name starts with ``FAP``)."""
        return bool(_FAP_RE.match(self.name))


@dataclass(frozen=True)
class WfmFile:
    """The content of a CANDIDE ``.wfm`` file, in file coordinates and units.

    Attributes:
        header: comment lines before the first section, ``#`` stripped.
        vertices: ``(V, 3)`` float64 vertex positions.
        faces: ``(F, 3)`` int64 triangles as written (winding not fixed).
        animation_units: the units of ``ANIMATION UNITS LIST`` in file order.
        shape_units: the units of ``SHAPE UNITS LIST`` in file order.
        animation_parameters: ``(n, 2)`` float64 rows ``(unit index, value)`` of ``ANIMATION PARAMETERS``.
        shape_parameters: ``(n, 2)`` float64 rows of ``SHAPE PARAMETERS``.
        texture: raw data lines of ``TEXTURE`` after its count.
        global_motion: ``(n, 3)`` float64 rows of ``GLOBAL MOTION`` (rotation, scale, translation).
    """

    header: tuple[str, ...]
    vertices: np.ndarray
    faces: np.ndarray
    animation_units: tuple[WfmUnit, ...]
    shape_units: tuple[WfmUnit, ...]
    animation_parameters: np.ndarray
    shape_parameters: np.ndarray
    texture: tuple[str, ...]
    global_motion: np.ndarray


class _Lines:
    """A cursor over the lines of a ``.wfm`` text (1-based line numbers in errors)."""

    def __init__(self, text: str) -> None:
        self.lines = [line.strip() for line in text.splitlines()]
        self.pos = 0

    def at_end(self) -> bool:
        return self.pos >= len(self.lines)

    def peek(self) -> str:
        return self.lines[self.pos]

    def error(self, message: str) -> ValueError:
        line = min(self.pos, len(self.lines) - 1) + 1
        return ValueError(f"malformed .wfm file at line {line}: {message}")

    def skip_blank(self) -> None:
        while not self.at_end() and not self.peek():
            self.pos += 1

    def comments(self) -> list[str]:
        """Consume blank and comment lines (stopping before a section header); return the comments."""
        out: list[str] = []
        while not self.at_end():
            line = self.peek()
            if not line:
                self.pos += 1
            elif line.startswith("#") and not _SECTION_RE.match(line):
                out.append(line.lstrip("#").strip())
                self.pos += 1
            else:
                break
        return out

    def data(self, what: str) -> list[str]:
        """The whitespace-separated tokens of the next data line (comments and blanks skipped)."""
        self.comments()
        if self.at_end() or self.peek().startswith("#"):
            raise self.error(f"expected {what}, found {'end of file' if self.at_end() else repr(self.peek())}")
        tokens = self.peek().split()
        self.pos += 1
        return tokens

    def count(self, section: str) -> int:
        tokens = self.data(f"the item count of {section}")
        try:
            value = int(tokens[0])
        except ValueError:
            raise self.error(f"expected an integer count for {section}, got {tokens[0]!r}") from None
        if value < 0:
            raise self.error(f"negative count {value} for {section}")
        return value

    def rows(self, count: int, width: int, section: str, kind: type) -> np.ndarray:
        out = np.zeros((count, width), dtype=np.int64 if kind is int else np.float64)
        for i in range(count):
            tokens = self.data(f"row {i + 1} of {count} of {section}")
            if len(tokens) < width:
                raise self.error(f"{section} rows need {width} numbers, got {len(tokens)}")
            try:
                out[i] = [kind(t) for t in tokens[:width]]
            except ValueError:
                raise self.error(f"could not read {width} numbers from {' '.join(tokens)!r} in {section}") from None
        return out


def _read_units(cur: _Lines, section: str) -> tuple[WfmUnit, ...]:
    """Units: a count, then per unit its comment lines, a row count and ``index dx dy dz`` rows."""
    num_units = cur.count(section)
    units: list[WfmUnit] = []
    for _ in range(num_units):
        comments = tuple(cur.comments())
        n = cur.count(f"{section} unit {len(units)} ({comments[0] if comments else 'unnamed'})")
        rows = cur.rows(n, 4, section, float)
        if n and np.any(rows[:, 0] != np.round(rows[:, 0])):
            raise cur.error(f"vertex indices of {section} rows must be integers")
        units.append(WfmUnit(comments, rows[:, 0].astype(np.int64), rows[:, 1:4].copy()))
    return tuple(units)


def _raw_lines(cur: _Lines) -> list[str]:
    """The data lines up to the next comment or section header."""
    raw: list[str] = []
    cur.skip_blank()
    while not cur.at_end() and not cur.peek().startswith("#"):
        raw.append(cur.peek())
        cur.pos += 1
        cur.skip_blank()
    return raw


def _read_text(path_or_text: str | os.PathLike[str] | bytes) -> str:
    if isinstance(path_or_text, bytes):
        return path_or_text.decode("latin-1")
    if isinstance(path_or_text, os.PathLike):  # any path-like (an os.DirEntry too), not only a Path
        return Path(path_or_text).read_bytes().decode("latin-1")
    if isinstance(path_or_text, str):
        if "\n" in path_or_text:
            return path_or_text
        return Path(path_or_text).read_bytes().decode("latin-1")
    raise TypeError(f"path_or_text must be a path, the file's text or its bytes, got {type(path_or_text).__name__}")


def parse_wfm(path_or_text: str | os.PathLike[str] | bytes) -> WfmFile:
    """Parse a CANDIDE ``.wfm`` file (Latin-1). Every section's size is read from its count line.

    Args:
        path_or_text: a path (a ``str`` without a newline or any ``os.PathLike``), the file's text (anything
            containing a newline), or its raw bytes.

    Returns:
        The file content in file coordinates (see :class:`WfmFile`).

    Raises:
        ValueError: a section is malformed, truncated or missing (``VERTEX LIST`` and ``FACE LIST`` are
            required), or a triangle or unit references a vertex that does not exist.

    Example:
        >>> wfm = parse_wfm("# VERTEX LIST:\\n3\\n0 0 0\\n1 0 0\\n0 1 0\\n# FACE LIST:\\n1\\n0 1 2\\n")
        >>> wfm.vertices.shape, wfm.faces.tolist()
        ((3, 3), [[0, 1, 2]])
    """
    cur = _Lines(_read_text(path_or_text))
    header = tuple(cur.comments())
    arrays: dict[str, np.ndarray] = {}  # VERTEX LIST, FACE LIST, the PARAMETERS, GLOBAL MOTION
    units: dict[str, tuple[WfmUnit, ...]] = {}  # ANIMATION UNITS LIST, SHAPE UNITS LIST
    texts: dict[str, tuple[str, ...]] = {}  # TEXTURE and unknown sections
    while not cur.at_end():
        match = _SECTION_RE.match(cur.peek())
        if match is None:
            raise cur.error(f"expected a section header such as '# VERTEX LIST:', got {cur.peek()!r}")
        section = match.group(1)
        cur.pos += 1
        if section == "END OF FILE":
            break
        if section in arrays or section in units or section in texts:
            raise cur.error(f"section {section} appears twice")
        if section == "VERTEX LIST":
            arrays[section] = cur.rows(cur.count(section), 3, section, float)
        elif section == "FACE LIST":
            arrays[section] = cur.rows(cur.count(section), 3, section, int)
        elif section in ("ANIMATION UNITS LIST", "SHAPE UNITS LIST"):
            units[section] = _read_units(cur, section)
        elif section in ("ANIMATION PARAMETERS", "SHAPE PARAMETERS"):
            arrays[section] = cur.rows(cur.count(section), 2, section, float)
        elif section == "GLOBAL MOTION":
            raw = _raw_lines(cur)
            try:
                arrays[section] = np.array([[float(t) for t in line.split()[:3]] for line in raw]).reshape(-1, 3)
            except ValueError:
                raise cur.error(f"{section} rows must hold three numbers, got {raw}") from None
        else:  # TEXTURE and unknown sections: keep the data lines after the count
            texts[section] = tuple(_raw_lines(cur)[1:])
        cur.comments()
    for required in ("VERTEX LIST", "FACE LIST"):
        if required not in arrays:
            raise ValueError(f"malformed .wfm file: missing section '# {required}:'")
    vertices = arrays["VERTEX LIST"]
    faces = arrays["FACE LIST"]
    num_v = len(vertices)
    if faces.size and (faces.min() < 0 or faces.max() >= num_v):
        raise ValueError(f"malformed .wfm file: triangles reference vertices outside [0, {num_v})")
    anim = units.get("ANIMATION UNITS LIST", ())
    shape = units.get("SHAPE UNITS LIST", ())
    for unit in (*anim, *shape):
        if unit.vertex_indices.size and (unit.vertex_indices.min() < 0 or unit.vertex_indices.max() >= num_v):
            raise ValueError(f"malformed .wfm file: unit {unit.name!r} moves vertices outside [0, {num_v})")
    empty2 = np.zeros((0, 2))
    return WfmFile(
        header=header,
        vertices=vertices,
        faces=faces,
        animation_units=anim,
        shape_units=shape,
        animation_parameters=arrays.get("ANIMATION PARAMETERS", empty2),
        shape_parameters=arrays.get("SHAPE PARAMETERS", empty2),
        texture=texts.get("TEXTURE", ()),
        global_motion=arrays.get("GLOBAL MOTION", np.zeros((0, 3))),
    )


def candide3_fapu(vertices: np.ndarray) -> dict[str, float]:
    """MPEG-4 FAPUs of the CANDIDE-3 mean shape, in model units, measured between its feature vertices.

    ``ES`` pupil-to-pupil distance; ``IRISD`` iris diameter; ``ENS`` eye line to nose bottom; ``MNS``
    nose bottom to mouth line; ``MW`` mouth width (outer corners). For CANDIDE-3 v3.1.6 these are
    0.613, 0.085, 0.4225, 0.196 and 0.492.

    Args:
        vertices: ``(V, 3)`` CANDIDE-3 vertices in file coordinates.

    Returns:
        ``{"ES": ..., "IRISD": ..., "ENS": ..., "MNS": ..., "MW": ...}``.
    """
    v = np.asarray(vertices, dtype=np.float64)
    pupil_l = v[list(_PUPIL_LEFT)].mean(axis=0)
    pupil_r = v[list(_PUPIL_RIGHT)].mean(axis=0)
    eye_y = 0.5 * (pupil_l[1] + pupil_r[1])
    irisd = float(np.mean([abs(v[a, 1] - v[b, 1]) for a, b in _IRIS_TOP_BOTTOM]))
    return {
        "ES": float(abs(pupil_l[0] - pupil_r[0])),
        "IRISD": irisd,
        "ENS": float(eye_y - v[_NOSE_BOTTOM, 1]),
        "MNS": float(v[_NOSE_BOTTOM, 1] - v[_MOUTH_MIDDLE, 1]),
        "MW": float(abs(v[_MOUTH_CORNERS[0], 0] - v[_MOUTH_CORNERS[1], 0])),
    }


def _data_text(name: str, encoding: str = "utf-8") -> str:
    """The text of a file shipped in ``torchface/data`` (never read from outside the package)."""
    return resources.files("torchface").joinpath("data").joinpath(name).read_bytes().decode(encoding)


def read_landmark_table(text: str | None = None) -> tuple[np.ndarray, np.ndarray, tuple[str, ...], tuple[str, ...]]:
    """Read ``candide3_landmarks68.csv``: each iBUG-68 point as a weighted combination of three vertices.

    Args:
        text: CSV text; ``None`` reads the package's copy.

    Returns:
        ``(K, 3)`` int64 vertex indices, ``(K, 3)`` float64 weights, ``K`` names and ``K`` sources
        (``"FaceSwap"`` for published pairs, ``"derived"`` for points placed along contours).

    Raises:
        ValueError: rows are missing, out of order, or a row's weights do not sum to one.
    """
    rows = list(csv.DictReader(io.StringIO(_data_text("candide3_landmarks68.csv") if text is None else text)))
    idx = np.zeros((len(rows), 3), dtype=np.int64)
    wts = np.zeros((len(rows), 3), dtype=np.float64)
    names, sources = [], []
    for k, row in enumerate(rows):
        if int(row["ibug_index"]) != k:
            raise ValueError(f"landmark table rows must be ordered 0..K-1, row {k} has ibug_index {row['ibug_index']}")
        idx[k] = [int(row[f"v{j}"]) for j in range(3)]
        wts[k] = [float(row[f"w{j}"]) for j in range(3)]
        if abs(wts[k].sum() - 1.0) > 1e-9:
            raise ValueError(f"landmark {k} weights must sum to 1, got {wts[k].tolist()}")
        names.append(row["meaning"])
        sources.append(row["source"])
    return idx, wts, tuple(names), tuple(sources)


@dataclass(frozen=True)
class _AuvRow:
    file_position: int
    auv: int
    name: str
    facs: tuple[str, ...]
    range_lo: float
    range_hi: float


def read_auv_facs_table(text: str | None = None) -> tuple[_AuvRow, ...]:
    """Read ``candide3_auv_facs.csv``: per AUV its file position, number, name, linked FACS AUs and range.

    Args:
        text: CSV text; ``None`` reads the package's copy.

    Returns:
        One record per row with fields ``file_position, auv, name, facs, range_lo, range_hi``.

    Raises:
        ValueError: a range is empty (``range_lo >= range_hi``).
    """
    rows = csv.DictReader(io.StringIO(_data_text("candide3_auv_facs.csv") if text is None else text))
    out = []
    for row in rows:
        rec = _AuvRow(
            file_position=int(row["file_position"]),
            auv=int(row["auv"]),
            name=row["name"].strip(),
            facs=tuple(a.strip() for a in row["facs"].split(";") if a.strip()),
            range_lo=float(row["range_lo"]),
            range_hi=float(row["range_hi"]),
        )
        if not rec.range_lo < rec.range_hi:
            raise ValueError(f"AUV{rec.auv} range must satisfy lo < hi, got [{rec.range_lo}, {rec.range_hi}]")
        out.append(rec)
    return tuple(out)


def _facs_from_comment(text: str | None) -> tuple[str, ...]:
    """``"AU26/27"`` -> ``("AU26", "AU27")``."""
    if not text:
        return ()
    return tuple(f"AU{n}" for n in re.findall(r"\d+", text))


def _unit_basis(unit: WfmUnit, num_v: int, scale: float) -> np.ndarray:
    """``(V, 3)`` displacement per unit coefficient in head-frame millimetres."""
    basis = np.zeros((num_v, 3), dtype=np.float64)
    np.add.at(basis, unit.vertex_indices, unit.vectors * scale)
    return basis @ FILE_TO_HEAD.T * MM_PER_CANDIDE_UNIT


def load_candide3(
    animation: AnimationSet = AnimationSet.AUV,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> FaceModel:
    """Load the package's CANDIDE-3 v3.1.6 as a :class:`FaceModel` (head frame, millimetres).

    AUV rows are displacements per unit coefficient. A FAP's basis is ``direction * FAPU / 1024`` so that
    its coefficient is the MPEG-4 FAP value; FAPUs come from :func:`candide3_fapu` and FAPs 23-30 use
    :data:`FAP_EYEBALL_FAPU`. Animation ranges come from ``candide3_auv_facs.csv`` for AUVs and are
    ``[-1024, 1024]`` (one FAPU either way) for FAPs; only AUVs link to FACS.

    Args:
        animation: which animation units to expose (default: the 11 AUVs, in file order).
        dtype: floating dtype of the model tensors.
        device: device of the model tensors.

    Returns:
        The model: ``V = 113`` (legacy vertices 4, 35-39, 41-43 kept but unused), ``F = 184``, ``S = 14``,
        ``A = 11`` / ``65`` / ``54``, ``K = 68`` iBUG landmarks.

    Raises:
        TypeError: ``animation`` is not an :class:`AnimationSet` or ``dtype`` is not floating.
        ValueError: ``device`` is not a device this machine has (``"cuda"`` without CUDA, ``"mps"`` off Apple
            silicon, ``"meta"``; the message lists those it has), or the packaged data files disagree with each other.

    Example:
        >>> model = load_candide3()
        >>> model.num_vertices, model.num_faces, model.num_shape, model.num_animation
        (113, 184, 14, 11)
        >>> model.animation_names[1]
        'AUV11 Jaw drop'
    """
    check_choice(animation, "animation", AnimationSet)
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise TypeError(f"dtype must be a floating torch.dtype, got {dtype}")
    device = check_device(device)
    wfm = parse_wfm(_data_text("candide3.wfm", encoding="latin-1"))
    num_v = wfm.vertices.shape[0]

    faces, labels = make_winding_consistent(wfm.faces)
    faces = orient_outward(wfm.vertices, faces, labels, _HEAD_CENTRE_FILE)
    mask = np.ones(num_v, dtype=bool)
    mask[unused_vertices(num_v, faces)] = False

    auvs = [u for u in wfm.animation_units if not u.is_fap]
    faps = [(u, m) for u in wfm.animation_units if (m := _FAP_RE.match(u.name)) is not None]  # u.is_fap
    table = read_auv_facs_table()
    if len(table) != len(auvs):
        raise ValueError(f"candide3_auv_facs.csv has {len(table)} rows but the .wfm file has {len(auvs)} AUVs")

    names: list[str] = []
    bases: list[np.ndarray] = []
    ranges: list[tuple[float, float]] = []
    links: list[tuple[str, ...]] = []
    if animation in (AnimationSet.AUV, AnimationSet.AUV_AND_FAP):
        for pos, (unit, rec) in enumerate(zip(auvs, table)):
            match = _AUV_RE.match(unit.name)
            parsed = (pos, int(match.group(1)), match.group(2)) if match else None
            agrees = (rec.file_position, rec.auv, rec.name) == parsed
            if not agrees:
                raise ValueError(f"candide3_auv_facs.csv row {pos} ({rec}) does not describe the file's {unit.name!r}")
            names.append(f"AUV{rec.auv} {rec.name}")
            bases.append(_unit_basis(unit, num_v, 1.0))
            ranges.append((rec.range_lo, rec.range_hi))
            links.append(rec.facs)
    if animation in (AnimationSet.FAP, AnimationSet.AUV_AND_FAP):
        fapu = candide3_fapu(wfm.vertices)
        for unit, match in faps:
            unit_name = unit.fapu or FAP_EYEBALL_FAPU
            if unit_name not in fapu:
                raise ValueError(f"FAP {unit.name!r} names an unknown FAPU {unit_name!r}")
            names.append(f"FAP{int(match.group(1))} {match.group(2)}")
            bases.append(_unit_basis(unit, num_v, fapu[unit_name] / 1024.0))
            ranges.append(_FAP_RANGE)
            links.append(())

    facs_names = tuple(sorted({au for link in links for au in link}, key=lambda au: int(au[2:])))
    facs_matrix = np.zeros((len(facs_names), len(names)))
    for a, link in enumerate(links):
        for au in link:
            facs_matrix[facs_names.index(au), a] = 1.0

    shape_names = tuple(u.name for u in wfm.shape_units)
    shape_bases = [_unit_basis(u, num_v, 1.0) for u in wfm.shape_units]
    lm_idx, lm_w, lm_names, _ = read_landmark_table()

    def tensor(array: np.ndarray, shape: tuple[int, ...]) -> torch.Tensor:
        return torch.as_tensor(np.asarray(array, dtype=np.float64).reshape(shape), dtype=dtype, device=device)

    return FaceModel(
        name="CANDIDE-3 v3.1.6",
        mean=tensor(wfm.vertices @ FILE_TO_HEAD.T * MM_PER_CANDIDE_UNIT, (num_v, 3)),
        faces=torch.as_tensor(faces, dtype=torch.int64, device=device),
        shape_units=tensor(np.stack(shape_bases) if shape_bases else np.zeros(0), (len(shape_names), num_v, 3)),
        shape_names=shape_names,
        animation_units=tensor(np.stack(bases) if bases else np.zeros(0), (len(names), num_v, 3)),
        animation_names=tuple(names),
        animation_ranges=tensor(np.array(ranges), (len(names), 2)),
        landmark_vertices=torch.as_tensor(lm_idx, dtype=torch.int64, device=device),
        landmark_weights=tensor(lm_w, lm_w.shape),
        landmark_names=lm_names,
        facs_names=facs_names,
        facs_matrix=tensor(facs_matrix, facs_matrix.shape),
        surface_vertex_mask=torch.as_tensor(mask, device=device),
    )
