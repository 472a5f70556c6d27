"""The linear face model ``g = g_bar + S sigma + A alpha`` (paper Eq. 1) as a frozen data holder.

:class:`FaceModel` holds the mean shape, topology, shape units, animation units, a landmark table and the
animation-unit -> FACS link table of any linear face model (CANDIDE-3, ICT-FaceKit, ...), in the head frame
and in millimetres of :mod:`torchface.conventions`. The computations are the stateless functions of this
module (:func:`deform_vertices`, :func:`interpolate_landmarks`, :func:`face_normals`,
:func:`vertex_normals`); the methods of :class:`FaceModel` call them with the model's tensors.

Shapes: ``B`` batch, ``V`` vertices, ``F`` triangles, ``S`` shape units, ``A`` animation units, ``K`` landmarks.
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchface._compiling import is_compiling, is_transformed
from torchface._device import tensor_mover
from torchface.geometry.mesh import face_normals, vertex_normals

__all__ = [
    "FaceModel",
    "deform_vertices",
    "interpolate_landmarks",
    "face_normals",
    "vertex_normals",
]


def _check_coeffs(coeffs: Tensor | None, count: int, what: str, units: Tensor) -> None:
    """Validate a ``(B, count)`` coefficient tensor against the bases it multiplies."""
    if coeffs is None:
        return
    if not isinstance(coeffs, Tensor):
        got = type(coeffs).__name__
        raise TypeError(f"{what} coefficients must be a torch.Tensor of shape (B, {count}), got {got}")
    if coeffs.ndim != 2 or coeffs.shape[1] != count:
        raise ValueError(f"{what} coefficients must have shape (B, {count}), got {tuple(coeffs.shape)}")
    if coeffs.dtype != units.dtype:
        raise TypeError(
            f"{what} coefficients must have the model's dtype {units.dtype}, got {coeffs.dtype} "
            "(convert the model with FaceModel.to(dtype=...))"
        )
    if coeffs.device != units.device:
        raise ValueError(
            f"{what} coefficients must be on the model's device {units.device}, got {coeffs.device} "
            "(move the model with FaceModel.to(device=...))"
        )


#: Elements per row of :func:`_rowwise_product`'s padded product: 16 float32 (64 bytes), the CPU allocator's
#: alignment, so that each output row is aligned as a batch of one's is.
_ROW_ALIGN = 16

#: The padded bases :func:`_padded_basis` made last (at most :data:`_PADDED_KEPT`), each with the basis it was made
#: from, held so that its memory is not another tensor's while the entry is kept, and that basis's version counter.
_PADDED: OrderedDict[tuple[object, ...], tuple[Tensor, int, Tensor]] = OrderedDict()
_PADDED_KEPT = 4
_PADDED_LOCK = threading.Lock()


def _padded_basis(basis: Tensor) -> Tensor:
    """``(K, D)`` ``basis`` with zero columns to a multiple of :data:`_ROW_ALIGN` (:func:`_rowwise_product`), the
    same padded tensor again while ``basis`` is unchanged (its memory and version counter): a model's basis is
    padded once, not at every call (the copy took about 1 ms a call on the ICT Face Model's 29538 columns and 6
    microseconds on CANDIDE-3's 339). Made afresh, not kept, where a gradient or a transform may flow through it
    (``basis`` requires grad, ``torch.compile`` traces, a ``torch.func`` transform or forward-mode AD wraps it) or in
    inference mode (an inference tensor kept would refuse a later call's backward)."""
    pad = -basis.shape[1] % _ROW_ALIGN
    if not pad:
        return basis
    if basis.requires_grad or torch.is_inference_mode_enabled() or is_compiling() or is_transformed(basis):
        return torch.nn.functional.pad(basis, (0, pad))
    key = (basis.data_ptr(), basis.storage_offset(), tuple(basis.shape), basis.stride(), basis.dtype, basis.device)
    with _PADDED_LOCK:
        kept = _PADDED.get(key)
        if kept is not None and kept[1] == basis._version:
            _PADDED.move_to_end(key)
            return kept[2]
    padded = torch.nn.functional.pad(basis, (0, pad))
    with _PADDED_LOCK:
        _PADDED[key] = (basis, basis._version, padded)
        _PADDED.move_to_end(key)
        while len(_PADDED) > _PADDED_KEPT:
            _PADDED.popitem(last=False)
    return padded


def _rowwise_product(coeffs: Tensor, basis: Tensor) -> Tensor:
    """``(B, K) @ (K, D)`` -> ``(B, D)``, each row computed as a ``(1, K) @ (K, D)`` product of its own.

    A batched product with the basis expanded (``bmm``), not one ``(B, K) @ (K, D)`` matrix product: a BLAS library
    blocks a matrix product by its number of rows, so a row's rounding depended on the batch size (float32: an ICT
    Face Model stream's vertices 1.5e-5 mm apart alone and among 5, which a LOST track on the background grew), and a
    stream in a batch was not the same stream alone to the bit. Each row here is a product of its own; at 128
    streams it costs about as much as the matrix product on CANDIDE-3 (0.04 ms) and 4 times as much on the ICT Face
    Model's 9846 vertices. The coefficients are made contiguous first: column-major ones (an ``(A, B)`` tensor
    transposed) went to ``bmm`` as they were, which computed most rows otherwise than alone.

    The basis is padded with zero columns to a multiple of :data:`_ROW_ALIGN` elements, so that every row of the
    product starts on a 64-byte boundary (the allocator's), and the padding is sliced off (the padded basis is kept
    while the basis is unchanged: :func:`_padded_basis`). A kernel may take another path for an output row that is
    not so aligned: on an AMD EPYC (AVX-512, MKL 2024.2) the rows at an odd multiple of 8 bytes were computed
    otherwise than alone (CANDIDE-3's 339 columns: 119 of 195 rows for B = 1 to 8, 31 and 128; the ICT Face Model's:
    82).

    A single row (``B = 1``) is computed as the first of a batch of two (the row twice): ``bmm`` of one matrix is a
    plain matrix product, and on an Intel Xeon with AVX-512 FP16 (MKL 2024.2; session 65) that product rounded
    otherwise than the batched one, so that 2 to 8 of the rows of batches of 2 to 8 differed from the same rows
    alone (CANDIDE-3's and the ICT Face Model's sizes alike), while every batch of two or more computed each row
    alike. On the AMD EPYC above the batch of two gives the single row's bits, as before.
    """
    coeffs = coeffs.contiguous()  # (no copy of contiguous coefficients: the same product, to the bit)
    num_b, num_d = coeffs.shape[0], basis.shape[1]
    if num_b == 1:  # (the batched kernel's rounding, the row's as in any batch: see above)
        coeffs = coeffs.expand(2, -1).contiguous()
    basis = _padded_basis(basis)
    out = torch.bmm(coeffs.unsqueeze(1), basis.unsqueeze(0).expand(coeffs.shape[0], -1, -1)).squeeze(1)
    return out[:num_b, :num_d]


def deform_vertices(
    mean: Tensor,
    shape_units: Tensor,
    animation_units: Tensor,
    shape_coeffs: Tensor | None = None,
    anim_coeffs: Tensor | None = None,
) -> Tensor:
    """Vertices of the linear model, ``g = g_bar + S sigma + A alpha`` (paper Eq. 1).

    Args:
        mean: ``(V, 3)`` mean shape ``g_bar``.
        shape_units: ``(S, V, 3)`` shape basis ``S`` (displacement per unit coefficient).
        animation_units: ``(A, V, 3)`` animation basis ``A``.
        shape_coeffs: ``(B, S)`` shape coefficients ``sigma``, or ``None`` for zeros.
        anim_coeffs: ``(B, A)`` animation coefficients ``alpha``, or ``None`` for zeros.

    Returns:
        ``(B, V, 3)`` vertices; ``B`` is taken from the coefficients (1 when both are ``None``).

    Raises:
        ValueError: a coefficient tensor is not ``(B, S)`` / ``(B, A)``, the two batch sizes differ, or a
            tensor is on another device than the bases.
        TypeError: a coefficient tensor is not a tensor or its dtype differs from the bases'.

    Example:
        >>> mean = torch.zeros(4, 3); su = torch.zeros(0, 4, 3); au = torch.ones(2, 4, 3)
        >>> deform_vertices(mean, su, au, None, torch.tensor([[1.0, 2.0]]))[0, 0]
        tensor([3., 3., 3.])
    """
    num_v = mean.shape[0]
    _check_coeffs(shape_coeffs, shape_units.shape[0], "shape", shape_units)
    _check_coeffs(anim_coeffs, animation_units.shape[0], "animation", animation_units)
    if shape_coeffs is not None and anim_coeffs is not None and shape_coeffs.shape[0] != anim_coeffs.shape[0]:
        raise ValueError(
            f"shape and animation coefficients must share the batch size B, got {shape_coeffs.shape[0]} "
            f"and {anim_coeffs.shape[0]}"
        )
    verts = mean.unsqueeze(0)
    if shape_coeffs is not None:
        verts = verts + _rowwise_product(shape_coeffs, shape_units.reshape(shape_units.shape[0], num_v * 3)).view(
            -1, num_v, 3
        )
    if anim_coeffs is not None:
        verts = verts + _rowwise_product(
            anim_coeffs, animation_units.reshape(animation_units.shape[0], num_v * 3)
        ).view(-1, num_v, 3)
    if shape_coeffs is None and anim_coeffs is None:
        verts = verts.clone()
    return verts


#: How far from one a row of landmark weights may sum, and how far below zero a weight may be
#: (:func:`check_landmark_weights`): a model cast to half or bfloat16 and back (``.to(dtype)``) keeps its weights
#: rounded (sums of 1.002), a table written with three decimals sums to 0.999, and barycentric coordinates computed
#: for a point on a triangle's edge come out a rounding error below zero (-1e-17 in float64, -6e-8 in float32, more
#: from float32 landmark positions); ``load_mesh_model`` clamps those to zero and scales each row to sum to one.
LANDMARK_WEIGHT_SUM_TOLERANCE = 1e-2


def check_landmark_weights(weights: Tensor, names: tuple[str, ...] | None = None) -> None:
    """Refuse ``(K, J)`` landmark weights that do not place each landmark on the mesh's surface: weights that are not
    finite, a negative one (a landmark is a point of a triangle or of its edge, barycentric weights in ``[0, 1]``:
    a negative weight puts it off the triangle, in front of or behind the surface; ``(1.5, -0.5, 0)`` was taken;
    one within :data:`LANDMARK_WEIGHT_SUM_TOLERANCE` below zero, a rounding error, passes), or a row that does not
    sum to one within :data:`LANDMARK_WEIGHT_SUM_TOLERANCE` (a row of 0.9 moves its landmark a tenth of the way to
    the head frame's origin). ``names`` (``K``) name the landmark in the message.

    Example:
        >>> check_landmark_weights(torch.tensor([[0.5, 0.5, 0.0], [1.5, -0.5, 0.0]]), ("a", "b"))
        Traceback (most recent call last):
            ...
        ValueError: landmark_weights must be non-negative (barycentric in a triangle: a landmark on the surface), got -0.5 for landmark 1 ('b')
    """
    if not weights.numel():
        return
    w = weights.detach().to(torch.float64)

    def named(k: int) -> str:
        return f"landmark {k}" + (f" ({names[k]!r})" if names is not None and k < len(names) else "")

    finite = torch.isfinite(w).all(dim=1)
    if not bool(finite.all()):
        k = int((~finite).nonzero()[0, 0])
        raise ValueError(f"landmark_weights must be finite, got {w[k].tolist()} for {named(k)}")
    rows = w.min(dim=1).values
    k = int(rows.argmin())
    if float(rows[k]) < -LANDMARK_WEIGHT_SUM_TOLERANCE:
        raise ValueError(f"landmark_weights must be non-negative (barycentric in a triangle: a landmark on the "
                         f"surface), got {float(rows[k]):.6g} for {named(k)}")  # fmt: skip
    sums = w.sum(dim=1)
    k = int((sums - 1.0).abs().argmax())
    if abs(float(sums[k]) - 1.0) > LANDMARK_WEIGHT_SUM_TOLERANCE:
        raise ValueError(f"landmark_weights rows must sum to one (within {LANDMARK_WEIGHT_SUM_TOLERANCE:g}), got "
                         f"{float(sums[k]):.6g} for {named(k)} (sums in [{float(sums.min()):.6g}, "
                         f"{float(sums.max()):.6g}])")  # fmt: skip


def check_landmarks_on_surface(
    faces: Tensor,
    landmark_vertices: Tensor,
    landmark_weights: Tensor,
    surface_vertex_mask: Tensor,
    names: tuple[str, ...] | None = None,
) -> None:
    """Refuse ``(K, J)`` landmarks that do not lie on the surface of the ``(F, 3)`` ``faces``: one with a non-zero
    weight on a vertex no face uses (``surface_vertex_mask`` ``(V,)`` False: it moves with no triangle, and the
    tracker's view of the surface never holds it), or one whose vertices of non-zero weight, two or three of them,
    are not those of one triangle (an edge's two, a triangle's three): its weights are then no barycentric
    coordinates, and the landmark lies off the surface (``[0, 60, 100]`` of CANDIDE-3, across the face, was taken).
    ``names`` (``K``) name the landmark in the message.

    Example:
        >>> faces = torch.tensor([[0, 1, 2], [1, 3, 2]])
        >>> mask = torch.tensor([True, True, True, True, False])
        >>> check_landmarks_on_surface(faces, torch.tensor([[1, 2, 3]]), torch.full((1, 3), 1 / 3), mask)
        >>> check_landmarks_on_surface(faces, torch.tensor([[0, 3, 0]]), torch.tensor([[0.5, 0.5, 0.0]]), mask)
        Traceback (most recent call last):
            ...
        ValueError: landmark 0 has non-zero weights on vertices [0, 3], which no triangle of faces holds (landmark weights are barycentric in a triangle: a landmark on the surface); give the vertices of the triangle it lies in (or of the edge it lies on)
    """
    if not landmark_vertices.numel():
        return

    def named(k: int) -> str:
        return f"landmark {k}" + (f" ({names[k]!r})" if names is not None and k < len(names) else "")

    idx = landmark_vertices.detach().cpu().numpy()
    on = (landmark_weights.detach() != 0).cpu().numpy()
    unused = on & ~surface_vertex_mask.detach().cpu().numpy()[idx]
    if unused.any():
        k, j = (int(i) for i in np.argwhere(unused)[0])
        raise ValueError(
            f"{named(k)} lies on vertex {int(idx[k, j])} (weight {float(landmark_weights[k, j]):.6g}), which no "
            f"face uses ({int(unused.any(axis=1).sum())} landmarks do): it is not on the surface; put it on a "
            "vertex of the mesh's triangles"
        )
    # each landmark's distinct vertices of non-zero weight, sorted, padded with -1: (K, 3)
    sets = np.sort(np.where(on, idx, -1), axis=1)
    sets[:, 1:][sets[:, 1:] == sets[:, :-1]] = -1
    sets = np.sort(sets, axis=1)
    count = (sets >= 0).sum(axis=1)
    several = np.flatnonzero(count > 1)
    if not several.size:
        return
    tri = np.sort(faces.detach().cpu().numpy(), axis=1)
    num_v = int(surface_vertex_mask.shape[0])

    wide = np.int64 if num_v < 2**21 else object  # (a triangle's key, num_v**3, within int64; else Python ints)

    def key(a: np.ndarray, b: np.ndarray, c: np.ndarray | None = None) -> np.ndarray:
        out = a.astype(wide) * num_v + b.astype(wide)
        return out if c is None else out * num_v + c.astype(wide)

    edges = np.concatenate([key(tri[:, 0], tri[:, 1]), key(tri[:, 1], tri[:, 2]), key(tri[:, 0], tri[:, 2])])
    held = np.zeros(sets.shape[0], dtype=bool)
    two, three = several[count[several] == 2], several[count[several] == 3]
    held[two] = np.isin(key(sets[two, 1], sets[two, 2]), edges)
    held[three] = np.isin(key(sets[three, 0], sets[three, 1], sets[three, 2]), key(tri[:, 0], tri[:, 1], tri[:, 2]))
    off = several[~held[several]]
    if off.size:
        k = int(off[0])
        raise ValueError(
            f"{named(k)} has non-zero weights on vertices {sets[k][sets[k] >= 0].tolist()}, which no triangle of "
            f"faces holds{f' ({off.size} landmarks do)' if off.size > 1 else ''} (landmark weights are barycentric "
            "in a triangle: a landmark on the surface); give the vertices of the triangle it lies in (or of the edge "
            "it lies on)"
        )


def interpolate_landmarks(verts: Tensor, landmark_vertices: Tensor, landmark_weights: Tensor) -> Tensor:
    """Landmarks as weighted vertex combinations, ``l_k = sum_j w[k, j] * verts[idx[k, j]]``.

    Args:
        verts: ``(B, V, 3)`` vertices.
        landmark_vertices: ``(K, J)`` int64 vertex indices (``J = 3`` for the models here).
        landmark_weights: ``(K, J)`` weights (rows sum to one; a landmark on a vertex is ``(1, 0, 0)``).

    Returns:
        ``(B, K, 3)`` landmark positions.

    Example:
        >>> v = torch.tensor([[[0.0, 0, 0], [2.0, 0, 0]]])
        >>> interpolate_landmarks(v, torch.tensor([[0, 1, 0]]), torch.tensor([[0.5, 0.5, 0.0]]))
        tensor([[[1., 0., 0.]]])
    """
    picked = verts[:, landmark_vertices]  # (B, K, J, 3)
    return (picked * landmark_weights.unsqueeze(-1)).sum(dim=2)


@dataclass(frozen=True, eq=False)
class FaceModel:
    """A linear 3D face model in the head frame and in millimetres (see :mod:`torchface.conventions`).

    Vertices are ``g = mean + sum_s sigma_s shape_units[s] + sum_a alpha_a animation_units[a]`` (paper
    Eq. 1). Topology and bases are unbatched; coefficients and vertices are batch-first.

    Attributes:
        name: model name, e.g. ``"CANDIDE-3 v3.1.6"``.
        mean: ``(V, 3)`` mean shape ``g_bar``, millimetres, head frame.
        faces: ``(F, 3)`` int64 triangles, wound consistently and outward:
            ``(v1 - v0) x (v2 - v0)`` points out of the head. Unused vertices are never referenced.
        shape_units: ``(S, V, 3)`` displacement (mm) per unit shape coefficient.
        shape_names: ``S`` names.
        animation_units: ``(A, V, 3)`` displacement (mm) per unit animation coefficient.
        animation_names: ``A`` names.
        animation_ranges: ``(A, 2)`` plausible ``[lo, hi]`` range of each animation coefficient, holding 0.
        landmark_vertices: ``(K, 3)`` int64 vertex indices of each landmark.
        landmark_weights: ``(K, 3)`` non-negative weights (within 1e-2), ``l_k = sum_j w[k, j] verts[idx[k, j]]``;
            rows sum to one (within 1e-2).
        landmark_names: ``K`` names (iBUG-68 order when ``K = 68``).
        facs_names: FACS action unit names, e.g. ``("AU2", "AU4", ...)``.
        facs_matrix: ``(n_facs, A)`` link table, ``facs_values = anim_coeffs @ facs_matrix.T``.
        surface_vertex_mask: ``(V,)`` bool, ``True`` for exactly the vertices used by a face.

    Construction checks the shapes, dtypes and devices above, that the shape, animation and FACS names are
    distinct within each tuple, that the floating tensors are finite, that each animation range has
    ``lo <= 0 <= hi`` (0, the mean mesh, is where the tracker starts each unit and centres its prior), that the
    landmark weights are non-negative with rows that sum to one (within 1e-2: :func:`check_landmark_weights`), that
    the indices index vertices, that ``surface_vertex_mask`` marks those of the faces and that each landmark lies on
    the surface (its vertices of non-zero weight used by a face, and two or three of them an edge's or a
    triangle's: :func:`check_landmarks_on_surface`), and raises ``ValueError`` (``TypeError`` for a field of the
    wrong type) otherwise.

    Example:
        >>> from torchface.model import load_candide3
        >>> model = load_candide3()
        >>> verts = model.deform(None, torch.zeros(2, model.num_animation))
        >>> verts.shape, model.landmarks_3d(verts).shape
        (torch.Size([2, 113, 3]), torch.Size([2, 68, 3]))
    """

    name: str
    mean: Tensor
    faces: Tensor
    shape_units: Tensor
    shape_names: tuple[str, ...]
    animation_units: Tensor
    animation_names: tuple[str, ...]
    animation_ranges: Tensor
    landmark_vertices: Tensor
    landmark_weights: Tensor
    landmark_names: tuple[str, ...]
    facs_names: tuple[str, ...]
    facs_matrix: Tensor
    surface_vertex_mask: Tensor

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "name":
                if not isinstance(value, str):
                    raise TypeError(f"name must be a str, got {type(value).__name__}")
            elif f.name.endswith("_names"):
                if not isinstance(value, tuple) or not all(isinstance(n, str) for n in value):
                    raise TypeError(f"{f.name} must be a tuple of str, got {type(value).__name__}")
            elif not isinstance(value, Tensor):
                raise TypeError(f"{f.name} must be a torch.Tensor, got {type(value).__name__}")
        for key in ("shape_names", "animation_names", "facs_names"):
            names = getattr(self, key)
            repeated = sorted(n for n, count in Counter(names).items() if count > 1)
            if repeated:
                raise ValueError(f"{key} must be distinct (units are looked up by name), repeated: {repeated}")
        mean = self.mean
        if mean.ndim != 2 or mean.shape[1] != 3 or not mean.is_floating_point():
            raise ValueError(f"mean must be a float (V, 3) tensor, got {tuple(mean.shape)} {mean.dtype}")
        num_v = mean.shape[0]
        expected = {
            "shape_units": (len(self.shape_names), num_v, 3),
            "animation_units": (len(self.animation_names), num_v, 3),
            "animation_ranges": (len(self.animation_names), 2),
            "landmark_vertices": (len(self.landmark_names), 3),
            "landmark_weights": (len(self.landmark_names), 3),
            "facs_matrix": (len(self.facs_names), len(self.animation_names)),
            "surface_vertex_mask": (num_v,),
        }
        for key, shape in expected.items():
            got = tuple(getattr(self, key).shape)
            if got != shape:
                raise ValueError(f"{key} must have shape {shape} (from mean and the name tuples), got {got}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or self.faces.dtype != torch.int64:
            raise ValueError(f"faces must be an int64 (F, 3) tensor, got {tuple(self.faces.shape)} {self.faces.dtype}")
        if self.landmark_vertices.dtype != torch.int64:
            raise ValueError(f"landmark_vertices must be int64, got {self.landmark_vertices.dtype}")
        if self.surface_vertex_mask.dtype != torch.bool:
            raise ValueError(f"surface_vertex_mask must be bool, got {self.surface_vertex_mask.dtype}")
        for key in ("shape_units", "animation_units", "animation_ranges", "landmark_weights", "facs_matrix"):
            value = getattr(self, key)
            if value.dtype != mean.dtype or value.device != mean.device:
                raise ValueError(
                    f"{key} must share mean's dtype and device ({mean.dtype}, {mean.device}), "
                    f"got ({value.dtype}, {value.device})"
                )
        for key in ("faces", "landmark_vertices", "surface_vertex_mask"):
            if getattr(self, key).device != mean.device:
                raise ValueError(f"{key} must be on mean's device {mean.device}, got {getattr(self, key).device}")
        for key in ("mean", "shape_units", "animation_units", "animation_ranges", "landmark_weights", "facs_matrix"):
            value = getattr(self, key)
            if value.numel() and not bool(torch.isfinite(value).all()):
                raise ValueError(f"{key} holds non-finite values (NaN or inf)")
        reversed_ranges = (self.animation_ranges[:, 0] > self.animation_ranges[:, 1]).nonzero().flatten().tolist()
        if reversed_ranges:
            names = [self.animation_names[a] for a in reversed_ranges]
            raise ValueError(f"animation_ranges must be [lo, hi] with lo <= hi, reversed for {names}")
        # (a range that excludes 0 was taken: the first frame's fit starts each unit at 0 and the expression prior is
        # centred there, outside the range, and the tracking drifted)
        without_zero = ((self.animation_ranges[:, 0] > 0) | (self.animation_ranges[:, 1] < 0)).nonzero().flatten()
        if without_zero.numel():
            a = int(without_zero[0])
            lo, hi = (float(v) for v in self.animation_ranges[a])
            raise ValueError(
                f"animation_ranges must hold 0 (lo <= 0 <= hi: a coefficient of 0 is the mean mesh, where the first "
                f"frame's fit starts and the expression prior is centred), got [{lo:g}, {hi:g}] for "
                f"{self.animation_names[a]!r} ({without_zero.numel()} of the {self.num_animation} units): make the "
                "mean a face inside the ranges (add lo times each unit to it and subtract lo from its range)"
            )
        check_landmark_weights(self.landmark_weights, self.landmark_names)
        if self.faces.numel() and (int(self.faces.min()) < 0 or int(self.faces.max()) >= num_v):
            got = (int(self.faces.min()), int(self.faces.max()))
            raise ValueError(f"faces index vertices outside [0, {num_v}): min/max {got}")
        # (a mask of its own, from a file or a dataclasses.replace of the faces, was taken: an all-False one made the
        # tracker's start a bare RuntimeError, "amax(): Expected reduction dim to be specified ...", and a wrong one
        # sizes the normalised face's and the templates' crops from other vertices)
        used = torch.zeros(num_v, dtype=torch.bool, device=mean.device)
        used[self.faces.reshape(-1)] = True
        differ = (used != self.surface_vertex_mask).nonzero().flatten()
        if differ.numel():
            v = int(differ[0])
            raise ValueError(
                f"surface_vertex_mask must be True for exactly the vertices that faces use, got {bool(~used[v])} for "
                f"vertex {v}, which {'a' if bool(used[v]) else 'no'} face uses ({differ.numel()} vertices differ): "
                "make it from the faces (mask[faces.flatten()] = True), as torchface's loaders do"
            )
        if self.landmark_vertices.numel() and (
            int(self.landmark_vertices.min()) < 0 or int(self.landmark_vertices.max()) >= num_v
        ):
            raise ValueError(f"landmark_vertices index vertices outside [0, {num_v})")
        check_landmarks_on_surface(self.faces, self.landmark_vertices, self.landmark_weights, self.surface_vertex_mask,
                                   self.landmark_names)  # fmt: skip

    # ----------------------------------------------------------------------------------------- sizes
    @property
    def num_vertices(self) -> int:
        """``V``."""
        return self.mean.shape[0]

    @property
    def num_faces(self) -> int:
        """``F``."""
        return self.faces.shape[0]

    @property
    def num_shape(self) -> int:
        """``S``."""
        return self.shape_units.shape[0]

    @property
    def num_animation(self) -> int:
        """``A``."""
        return self.animation_units.shape[0]

    @property
    def num_landmarks(self) -> int:
        """``K``."""
        return self.landmark_vertices.shape[0]

    V = num_vertices
    F = num_faces
    S = num_shape
    A = num_animation
    K = num_landmarks

    @property
    def device(self) -> torch.device:
        """Device of every tensor of the model."""
        return self.mean.device

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the geometry and bases."""
        return self.mean.dtype

    # ------------------------------------------------------------------------------------ functions
    def deform(self, shape_coeffs: Tensor | None = None, anim_coeffs: Tensor | None = None) -> Tensor:
        """``(B, S)``, ``(B, A)`` coefficients (``None`` = zeros) -> ``(B, V, 3)`` vertices (Eq. 1).

        See :func:`deform_vertices` for the errors raised on bad coefficient shapes, dtypes and devices.
        """
        return deform_vertices(self.mean, self.shape_units, self.animation_units, shape_coeffs, anim_coeffs)

    def landmarks_3d(self, verts: Tensor) -> Tensor:
        """``(B, V, 3)`` vertices -> ``(B, K, 3)`` landmarks (see :func:`interpolate_landmarks`)."""
        if not isinstance(verts, Tensor) or verts.ndim != 3 or verts.shape[1:] != (self.num_vertices, 3):
            got = tuple(verts.shape) if isinstance(verts, Tensor) else type(verts).__name__
            raise ValueError(f"verts must have shape (B, {self.num_vertices}, 3), got {got}")
        return interpolate_landmarks(verts, self.landmark_vertices, self.landmark_weights.to(verts.dtype))

    def vertex_normals(self, verts: Tensor) -> Tensor:
        """``(B, V, 3)`` vertices -> ``(B, V, 3)`` outward unit vertex normals (zero on unused vertices)."""
        if not isinstance(verts, Tensor) or verts.ndim != 3 or verts.shape[1:] != (self.num_vertices, 3):
            got = tuple(verts.shape) if isinstance(verts, Tensor) else type(verts).__name__
            raise ValueError(f"verts must have shape (B, {self.num_vertices}, 3), got {got}")
        return vertex_normals(verts, self.faces)

    def face_normals(self, verts: Tensor) -> Tensor:
        """``(B, V, 3)`` vertices -> ``(B, F, 3)`` outward unit face normals."""
        if not isinstance(verts, Tensor) or verts.ndim != 3 or verts.shape[1:] != (self.num_vertices, 3):
            got = tuple(verts.shape) if isinstance(verts, Tensor) else type(verts).__name__
            raise ValueError(f"verts must have shape (B, {self.num_vertices}, 3), got {got}")
        return face_normals(verts, self.faces)

    def facs_values(self, anim_coeffs: Tensor) -> Tensor:
        """``(B, A)`` animation coefficients -> ``(B, n_facs)`` linked FACS values (``alpha @ M.T``)."""
        _check_coeffs(anim_coeffs, self.num_animation, "animation", self.facs_matrix)
        return anim_coeffs @ self.facs_matrix.T

    def to(
        self, device: torch.device | str | int | torch.dtype | None = None, dtype: torch.dtype | None = None,
        non_blocking: bool = False, copy: bool = False,
    ) -> "FaceModel":
        """A copy on ``device`` with floating tensors in ``dtype`` (index and mask tensors keep theirs).
        ``model.to(torch.float64)`` (a dtype first, as ``nn.Module.to`` takes it) converts the dtype alone; the
        arguments, ``non_blocking`` and ``copy`` included, are read as ``TrackResult.to`` reads them
        (:func:`~torchface._device.tensor_mover`: ``copy=True`` shares no tensor with ``self``; without it a tensor
        already there is shared, as ``Tensor.to`` returns it)."""
        move = tensor_mover(device, dtype, non_blocking, copy)  # (a device not here: a ValueError naming those here)
        changes: dict[str, Any] = {}  # field name -> value, of each field's own type
        for f in fields(self):
            value = getattr(self, f.name)
            changes[f.name] = move(value) if isinstance(value, Tensor) else value
        return FaceModel(**changes)

    def __repr__(self) -> str:
        return (
            f"FaceModel(name={self.name!r}, V={self.num_vertices}, F={self.num_faces}, S={self.num_shape}, "
            f"A={self.num_animation}, K={self.num_landmarks}, dtype={self.dtype}, device={self.device})"
        )
