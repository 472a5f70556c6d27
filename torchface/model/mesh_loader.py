"""Build a :class:`FaceModel` from any triangle mesh plus optional linear bases (e.g. the ICT Face Model).

The paper notes that a denser model can replace CANDIDE-3 (Section 2); these loaders give such a model
the same :class:`FaceModel` interface. Meshes are read with ``trimesh`` (``process=False``, so nothing is
welded or reordered), mapped into the head frame with a user-given orthogonal matrix and scaled to
millimetres (see :mod:`torchface.conventions`).

Shapes: ``V`` vertices, ``F`` triangles, ``S`` shape units, ``A`` animation units (blendshapes), ``K`` landmarks.
"""

from __future__ import annotations

import math
import numbers
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchface._device import check_device
from torchface._names import name_tuple
from torchface.conventions import IBUG68_MIRROR
from torchface.model.face_model import FaceModel, check_landmark_weights

__all__ = ["load_mesh_model", "load_ict_face_model", "ICT_TO_HEAD", "ICT_MM_PER_UNIT", "ICT_AREAS", "ARKIT_TO_FACS"]

#: ICT Face Model frame (+x subject's left, +y up, +z toward the viewer) to the head frame: 180 deg about x.
ICT_TO_HEAD = np.diag([1.0, -1.0, -1.0])

#: The ICT Face Model is in centimetres (outer eye corners 8.9 apart, head 24.8 wide).
ICT_MM_PER_UNIT = 10.0

#: The ICT Face Model's areas (its README's "Face Model Topology" and "Face Area Details"): the ``[start, stop)``
#: vertex ranges each keeps, in this order, and the triangles on them alone. ``"head"``: every vertex (head and neck,
#: mouth and eye sockets, gums, teeth, eyeballs, eyelashes); ``"face"``: the full face area; ``"narrow"``: the
#: narrow face area; ``"narrow_eyes"``: the narrow face area and the two eyeballs, which fill its eye holes.
ICT_AREAS: dict[str, tuple[tuple[int, int], ...]] = {
    "head": ((0, 26719),),
    "face": ((0, 9409),),
    "narrow": ((0, 6706),),
    "narrow_eyes": ((0, 6706), (21451, 24591)),
}

#: The range (mm) of the largest side of a face model's bounding box that :func:`load_mesh_model` takes without a
#: warning.
_FACE_SPAN_MM = (50.0, 2000.0)

#: The range of the largest displacement the blendshapes make within their animation ranges, relative to the span of
#: the mesh's used vertices, that :func:`load_mesh_model` takes without a warning: CANDIDE-3's (every animation set)
#: is 0.22-0.32, the ICT Face Model's 0.12 (whole head) to 0.21 (``area="narrow_eyes"``). Blendshapes in metres on a
#: mesh in millimetres come out 1000 times too small (about 2e-4), in millimetres on a mesh in metres 1000 times too
#: large.
_BLENDSHAPE_REACH = (2e-3, 5.0)

#: FACS action units commonly associated with the ARKit-style blendshapes of the ICT model
#: (``_L`` / ``_R`` suffixes dropped). Eye-gaze shapes map to the FACS eye-position codes AU61-AU64.
ARKIT_TO_FACS: dict[str, tuple[str, ...]] = {
    "browDown": ("AU4",),
    "browInnerUp": ("AU1",),
    "browOuterUp": ("AU2",),
    "cheekPuff": ("AU34",),
    "cheekSquint": ("AU6",),
    "eyeBlink": ("AU45",),
    "eyeLookDown": ("AU64",),
    "eyeLookUp": ("AU63",),
    "eyeSquint": ("AU7",),
    "eyeWide": ("AU5",),
    "jawForward": ("AU29",),
    "jawLeft": ("AU30",),
    "jawRight": ("AU30",),
    "jawOpen": ("AU26", "AU27"),
    "mouthDimple": ("AU14",),
    "mouthFrown": ("AU15",),
    "mouthFunnel": ("AU22",),
    "mouthLowerDown": ("AU16",),
    "mouthPress": ("AU24",),
    "mouthPucker": ("AU18",),
    "mouthRollLower": ("AU28",),
    "mouthRollUpper": ("AU28",),
    "mouthShrugLower": ("AU17",),
    "mouthSmile": ("AU12",),
    "mouthStretch": ("AU20",),
    "mouthUpperUp": ("AU10",),
    "noseSneer": ("AU9",),
}


def _as_basis(value: object, what: str, num_v: int) -> np.ndarray:
    """``None`` -> ``(0, V, 3)``; otherwise a float64 ``(n, V, 3)`` array (checked)."""
    if value is None:
        return np.zeros((0, num_v, 3))
    array = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
    if array.ndim != 3 or array.shape[1:] != (num_v, 3):
        raise ValueError(f"{what} must have shape (n, {num_v}, 3) to match the mesh, got {array.shape}")
    return array.astype(np.float64)


def _as_names(names: Sequence[str] | None, count: int, what: str, prefix: str) -> tuple[str, ...]:
    if names is None:
        return tuple(f"{prefix}{i}" for i in range(count))
    names = tuple(str(n) for n in name_tuple(names, what))
    if len(names) != count:
        raise ValueError(f"{what} must hold {count} names (one per unit), got {len(names)}")
    return names


def _facs_link(link: object, name: str) -> tuple[str, ...]:
    """One blendshape's FACS link: a collection of AU names, or one name (a str is one AU, not its letters)."""
    if isinstance(link, str):
        return (link,)
    aus = tuple(link) if isinstance(link, (tuple, list, set, frozenset)) else None
    if aus is None or not all(isinstance(au, str) for au in aus):
        raise TypeError(f"facs_links[{name!r}] must be an AU name or a tuple of them, got {link!r}")
    return aus


def _check_displacements(basis: np.ndarray, names: tuple[str, ...], vertices: np.ndarray, what: str) -> None:
    """Raise ``ValueError`` when a ``(n, V, 3)`` basis entry is a whole mesh (a blendshape target) rather than a
    displacement: when it is within half its own size of the ``(V, 3)`` mesh (RMS over the vertices). A
    displacement is far from the mesh (about the mesh's own distance from the origin) unless it is the mesh."""
    if basis.shape[0] == 0:
        return
    size = np.sqrt((basis**2).sum(axis=2).mean(axis=1))
    off = np.sqrt(((basis - vertices[None]) ** 2).sum(axis=2).mean(axis=1))
    whole = np.flatnonzero((size > 0) & (off < 0.5 * size))
    if whole.size:
        i = int(whole[0])
        raise ValueError(
            f"{what}[{i}] ({names[i]!r}) is a whole mesh, not a displacement: it is {off[i]:.3g} (RMS, mesh units) "
            f"from the mesh and {size[i]:.3g} from zero; pass each target minus the neutral mesh"
        )


def _used_span(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The span of the ``(V, 3)`` vertices the ``(F, 3)`` faces use: the largest side of their bounding box."""
    used = vertices[np.unique(faces)]
    return float((used.max(axis=0) - used.min(axis=0)).max())


def _check_blendshape_size(
    basis: np.ndarray, ranges: np.ndarray, names: tuple[str, ...], vertices: np.ndarray, faces: np.ndarray, unit: str,
    stacklevel: int = 3,
) -> None:
    """Warn when the ``(A, V, 3)`` blendshapes, within their ``(A, 2)`` ranges, move the ``(V, 3)`` mesh by an
    implausible amount for its size (``unit``: what its numbers are, in the message): when the largest displacement
    of any vertex at either end of any unit's range is outside :data:`_BLENDSHAPE_REACH` times the span of the used
    vertices (the largest side of their bounding box). Blendshapes in another unit than the mesh are taken, scaled by
    ``scale_to_mm`` as the mesh is: a jaw that barely moves, or one that leaves the face. The warning names the frame
    ``stacklevel`` up (3: the caller of the loader that calls this)."""
    if basis.shape[0] == 0:
        return
    span = _used_span(vertices, faces)
    reach = np.sqrt((basis**2).sum(axis=2)).max(axis=1) * np.abs(ranges).max(axis=1)  # (A,)
    if not np.isfinite(reach).all():  # (a non-finite blendshape or range, which FaceModel refuses: an inf one warned
        return  # that the blendshapes "move the mesh by at most inf", the unit's question, before that error)
    a = int(reach.argmax())
    if not (span > 0 and reach[a] > 0):
        return  # (nothing moves, or a mesh of no size: nothing to judge by)
    ratio = float(reach[a]) / span
    if not _BLENDSHAPE_REACH[0] <= ratio <= _BLENDSHAPE_REACH[1]:
        warnings.warn(
            f"the blendshapes move the mesh by at most {float(reach[a]):.3g} {unit} within their animation_ranges "
            f"({names[a]!r}), {ratio:.3g} of the mesh's span of {span:.3g} {unit}; a face's expressions move it by "
            "about a tenth of its size (CANDIDE-3's jaw drop 0.22 of it): are the blendshapes in the mesh's unit "
            "(scale them to it: blendshapes in metres on a mesh in millimetres make a jaw that barely moves)?",
            UserWarning,
            stacklevel=stacklevel,
        )


def _check_winding(vertices: np.ndarray, faces: np.ndarray) -> None:
    """Raise ``ValueError`` unless the ``(F, 3)`` triangles on the ``(V, 3)`` head-frame vertices are wound
    consistently (no edge shared by two triangles is traversed by both in the same direction, and no triangle is
    given in both windings; a triangle repeated in one winding or one with a repeated vertex is no evidence either
    way) and the face looks toward ``-z``: of the
    pixels of a frontal, nearly orthographic 32 x 32 view that the mesh covers, at least half see the front of
    a triangle (:func:`~torchface.rendering.rasterizer.rasterize`'s ``facing``)."""
    from torchface.backend import Backend
    from torchface.geometry.camera import Intrinsics
    from torchface.rendering.rasterizer import rasterize

    rows = np.flatnonzero((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0]))
    proper = faces[rows]
    # a triangle given in both windings (a double-sided mesh): the same three vertices, which listed from the lowest
    # index run one way in one copy and the other way in the other. The two copies traverse each of their edges in
    # opposite directions, which the edge rule below takes for consistent; their normals cancel (zero vertex normals:
    # no shading) and the tracker's every start failed (NO_PATCHES, "too few fiducial patches").
    _, first, group = np.unique(np.sort(proper, axis=1), axis=0, return_index=True, return_inverse=True)
    group = group.reshape(-1)
    turned = np.take_along_axis(proper, (np.argmin(proper, axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    flipped = turned[:, 1] > turned[:, 2]
    count = int(group.max()) + 1 if group.size else 0
    both = np.flatnonzero((np.bincount(group[flipped], minlength=count) > 0)
                          & (np.bincount(group[~flipped], minlength=count) > 0))  # fmt: skip
    if both.size:
        i, j = sorted((int(rows[(group == both[0]) & flipped][0]), int(rows[(group == both[0]) & ~flipped][0])))
        raise ValueError(
            f"{both.size} of the mesh's triangles are given in both windings, e.g. triangles {i} and {j} (vertices "
            f"{sorted(faces[i].tolist())}): a double-sided mesh, whose two copies of a triangle face opposite ways "
            "and whose normals cancel; keep one copy of each, wound outward"
        )
    tri = proper[np.sort(first)]
    directed = np.stack([tri, np.roll(tri, -1, axis=1)], axis=-1).reshape(-1, 2)
    _, u_inv, u_counts = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True, return_counts=True)
    _, d_inv, d_counts = np.unique(directed, axis=0, return_inverse=True, return_counts=True)
    same_way = (u_counts[u_inv.reshape(-1)] == 2) & (d_counts[d_inv.reshape(-1)] == 2)
    if same_way.any():
        a, b = directed[same_way][0].tolist()
        raise ValueError(
            f"the mesh's triangles are not wound consistently: {int(same_way.sum()) // 2} edges shared by two "
            f"triangles are traversed by both in the same direction (e.g. {a}-{b}); wind them all one way, outward "
            "(torchface.model.topology.make_winding_consistent and orient_outward do it)"
        )
    used = vertices[np.unique(faces)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    extent = float(max(hi[0] - lo[0], hi[1] - lo[1]))
    if not extent > 0:
        return  # seen edge-on: nothing to judge by
    size, distance = 32, 10.0 * (extent + float(hi[2] - lo[2]))
    focal = 0.9 * size * distance / extent
    shift = np.array([-0.5 * (lo[0] + hi[0]), -0.5 * (lo[1] + hi[1]), distance - lo[2]])
    camera = Intrinsics(size, size, focal, focal, (size - 1) / 2.0, (size - 1) / 2.0)
    verts = torch.as_tensor(vertices + shift, dtype=torch.float64).unsqueeze(0)
    frags = rasterize(verts, torch.as_tensor(faces, dtype=torch.int64), camera, backend=Backend.TORCH)  # no compiling
    hit = frags.pix_to_face[0] >= 0
    if int(hit.sum()) and float((frags.facing[0][hit] > 0).double().mean()) < 0.5:
        away = 100.0 * float((frags.facing[0][hit] <= 0).double().mean())
        raise ValueError(
            f"seen from the front (the head frame's -z side, torchface.conventions) {away:.0f}% of the mesh's "
            "surface faces away from the viewer: its triangles are wound inward (reverse them: faces[:, ::-1]) or "
            "the face does not look toward -z (pass to_head_frame: torchface.model.mesh_loader.ICT_TO_HEAD for a "
            "+y up, +z toward the viewer file)"
        )


#: iBUG-68's left-right mirror (:data:`torchface.conventions.IBUG68_MIRROR`) as an index array.
_IBUG_MIRROR = np.asarray(IBUG68_MIRROR)
#: The point on the subject's right (head frame ``-x``) of each of iBUG-68's 29 left-right pairs (jaw, brows, nose
#: wings, eyes, lips), at least 8.8 mm from its partner on CANDIDE-3 and 12 mm on the ICT Face Model.
_IBUG_RIGHT = np.r_[0:8, 17:22, 31:33, 36:42, 48:51, 58:62, 67]


def _check_ibug_layout(weighted: np.ndarray, name: str, stacklevel: int = 3) -> None:
    """Warn when 68 landmarks (``(68, J, 3)`` weighted head-frame vertices, summed over ``J``) are not laid out as the
    iBUG-68 points: the subject's right (``-x``) before their left (jaw end 0 and outer eye corner 36 against 16 and
    45, and no more than one of the other left-right pairs the other way round: a part mirrored alone, the brows or
    the mouth, reverses 5 or 8), the brows (19, 24) above (``-y``) the nose tip (30) and that above the chin (8).
    (CANDIDE-3 made asymmetric, one side up to 15% wider, vertices moved by 3 mm at random and turned by up to 20
    degrees, reversed at most one pair in 500 draws.)"""
    lm = weighted.sum(axis=1)
    x, y = lm[:, 0], lm[:, 1]
    reversed_pairs = int((x[_IBUG_MIRROR[_IBUG_RIGHT]] <= x[_IBUG_RIGHT]).sum())
    if not (x[0] < x[16] and x[36] < x[45] and reversed_pairs < 2 and max(y[19], y[24]) < y[30] < y[8]):
        warnings.warn(
            f"{name}: the 68 landmarks are not laid out as the iBUG-68 points (0-16 the jaw from the subject's right, "
            "36 and 45 the outer eye corners, 8 the chin; the head frame's +x is the subject's left, +y down; "
            f"{reversed_pairs} of the 29 left-right pairs, e.g. 17 and 26, 48 and 54, are the other way round): a "
            "face detector gives those, in that order, and the first frame's fit fails or goes astray on mirrored or "
            "reordered ones",
            UserWarning,
            stacklevel=stacklevel,
        )


def _check_surface(
    vertices: np.ndarray, faces: np.ndarray, lm_idx: np.ndarray, lm_w: np.ndarray, name: str, said: str, ask: str,
    stacklevel: int = 3,
) -> None:
    """The checks of a face model's surface that :func:`load_mesh_model` and
    :func:`~torchface.model.model_file.load_face_model` both make, on ``(V, 3)`` head-frame millimetre ``vertices``,
    ``(F, 3)`` ``faces`` and ``(K, J)`` landmarks ``lm_idx`` / ``lm_w``: the winding (:func:`_check_winding`, a
    ``ValueError``), the span of the used vertices (a ``UserWarning`` outside 50 mm - 2 m; ``said`` follows the span
    in it, ``ask`` is its question about the unit) and, for 68 landmarks, their iBUG-68 layout (a ``UserWarning``,
    :func:`_check_ibug_layout`). Warnings name the frame ``stacklevel`` up (3: the caller of the loader that calls
    this)."""
    _check_winding(vertices, faces)
    span = _used_span(vertices, faces)
    if not _FACE_SPAN_MM[0] <= span <= _FACE_SPAN_MM[1]:
        warnings.warn(
            f"the mesh spans {span:.3g} mm {said}; a face is 100-300 mm: {ask} Tracked translations come out "
            "scaled by the same mistake, and a face of a few millimetres fails the landmark fit",
            UserWarning,
            stacklevel=stacklevel,
        )
    if lm_idx.shape[0] == 68:
        _check_ibug_layout(vertices[lm_idx] * lm_w[:, :, None], name, stacklevel=stacklevel + 1)


def _obj_vertices(path: Path) -> np.ndarray | None:
    """``(V, 3)`` the positions of an OBJ file's ``v`` lines, in order (None when it cannot be read as text)."""
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
        rows = [line.split()[1:4] for line in lines if line.startswith("v ") or line.startswith("v\t")]
        return np.asarray(rows, dtype=np.float64).reshape(-1, 3)
    except (OSError, ValueError):
        return None


def load_mesh_model(
    mesh: object,
    *,
    blendshapes: object = None,
    blendshape_names: Sequence[str] | None = None,
    shape_units: object = None,
    shape_names: Sequence[str] | None = None,
    landmark_vertices: object = None,
    landmark_names: Sequence[str] | None = None,
    landmark_weights: object = None,
    animation_ranges: object = None,
    facs_links: dict[str, tuple[str, ...]] | None = None,
    scale_to_mm: float = 1.0,
    to_head_frame: object = None,
    name: str | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> FaceModel:
    """A :class:`FaceModel` from a triangle mesh and optional blendshape / shape bases.

    Each position and displacement ``x`` becomes ``scale_to_mm * (to_head_frame @ x)``. When
    ``to_head_frame`` is a reflection (determinant -1) the triangles are re-wound so that their normals
    keep pointing the same way relative to the surface. The mesh's own winding is kept otherwise: it must
    already be consistent and outward, and the face must look toward ``-z`` in the head frame (the camera's side
    when the head is frontal, :mod:`torchface.conventions`). Both are checked: two triangles that traverse a
    shared edge in the same direction, or a frontal view (32 x 32 pixels, of the used vertices) in which most of
    the surface seen faces away from the viewer (a mesh wound inward, or a ``+y`` up, ``+z`` toward the viewer
    file loaded without ``to_head_frame``), raise ``ValueError``: the tracker's normalised face and templates
    are built from that view, and such a model was tracked with its head turned 180 degrees, then lost.

    Args:
        mesh: a ``trimesh.Trimesh`` or a path (``str`` or any ``os.PathLike``) to any file trimesh reads (loaded
            with ``process=False``; OBJ files also with ``maintain_order=True`` so that vertices keep the file's
            order and count, which trimesh otherwise splits at texture seams and prunes when unreferenced).
        blendshapes: ``(A, V, 3)`` animation displacements per unit weight (mesh units and frame: a target
            shape minus the neutral mesh; a whole target mesh is refused), or ``None``.
        blendshape_names: ``A`` names (default ``"blendshape{i}"``).
        shape_units: ``(S, V, 3)`` identity displacements (not whole meshes, as ``blendshapes``), or ``None``.
        shape_names: ``S`` names (default ``"shape{i}"``).
        landmark_vertices: ``(K,)`` int vertex index per landmark (floats only when whole numbers, as
            ``np.loadtxt`` reads them), ``(K, J)`` (``J <= 3``) with ``landmark_weights`` for landmarks between
            vertices, or ``None`` for ``K = 0``. Tracking needs at least four (:func:`~torchface.tracker.initialise`
            fits the first frame's pose to them); a face detector's, and ``torchface track``'s, are the 68 iBUG
            points in their order.
        landmark_names: ``K`` names (default ``"landmark{k}"``).
        landmark_weights: ``(K, J)`` non-negative weights of ``(K, J)`` ``landmark_vertices``, ``l_k = sum_j w[k, j]
            verts[idx[k, j]]`` (barycentric coordinates in a triangle, as CANDIDE-3's table holds them; rows that
            sum to one within 1e-2, a table of three decimals, are scaled to sum to one exactly, and a weight within
            1e-2 below zero, a rounding error, is made zero: the rule of
            :func:`~torchface.model.face_model.check_landmark_weights`), or ``None``: each landmark on its vertex.
        animation_ranges: ``(A, 2)`` ``[lo, hi]`` per blendshape (default ``[0, 1]``, the blendshape-weight
            convention), each holding 0 (the neutral mesh: the tracker starts each unit there and centres its
            prior there).
        facs_links: blendshape name -> the FACS AUs it is linked to, a tuple of names or one name (``"AU26"``
            is one AU, not four; blendshapes not listed link to nothing; a name that is no blendshape's is refused).
        scale_to_mm: millimetres per mesh unit (1000 for a mesh in metres, 10 in centimetres). A model whose used
            vertices then span less than 50 mm or more than 2 m (a face is 100-300 mm) is loaded with a
            ``UserWarning``: the pose is found at any scale, but translations come out scaled by the mistake, and
            a face in metres (0.2 mm) fails the tracker's landmark fit.
        to_head_frame: ``(3, 3)`` orthogonal matrix from the mesh frame to the head frame (default identity).
        name: model name (default: the file name, or ``"mesh"``).
        dtype: floating dtype of the model tensors.
        device: device of the model tensors.

    Returns:
        The model; ``A = 0`` and ``S = 0`` give ``(0, V, 3)`` bases.

    Raises:
        TypeError: ``mesh`` is neither a Trimesh nor a path, ``dtype`` is not floating, a name list is
            one string (a sequence of names is expected), ``facs_links`` is not a dict or a value of it is neither
            an AU name nor a collection of them, ``scale_to_mm`` is not a number, or ``landmark_vertices`` are not
            integers.
        ValueError: a vertex of the mesh is not finite (NaN or inf; a basis's are refused as :class:`FaceModel` refuses
            them), a basis, name list, landmark index or range has the wrong size, a basis entry is a whole mesh (close
            to the mesh itself) rather than a displacement, a range does not hold 0, ``landmark_vertices`` is not 1-D
            (2-D with ``landmark_weights`` of its shape, at most 3 columns) or holds fractions, ``landmark_weights`` are
            not finite, one is negative or a row does not sum to one (each within 1e-2), a landmark is on a vertex no
            triangle uses or weighted over vertices that are not one triangle's (or edge's), the file holds no
            triangles, they are not wound consistently (or a triangle is given in both windings, a double-sided mesh) or
            the frontal view sees mostly their back, ``to_head_frame`` is not orthogonal, ``scale_to_mm`` is not
            positive and finite, a ``facs_links`` name is not a blendshape name, or ``device`` is not a device this
            machine has (the message lists those it has).

    Warns:
        UserWarning: the mesh spans less than 50 mm or more than 2 m (``scale_to_mm``), the blendshapes move it, at
            most, by less than 0.002 or more than 5 times its span within their ranges (blendshapes in another unit
            than the mesh: CANDIDE-3's and the ICT Face Model's move it by 0.12-0.32 times), or 68 landmarks are not
            laid out as the iBUG-68 points (mirrored or in another order: a face detector's landmarks are those).

    Example:
        >>> import trimesh
        >>> tri = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 2, 1]], process=False)
        >>> model = load_mesh_model(tri, blendshapes=np.ones((1, 3, 3)), scale_to_mm=100.0)
        >>> model.deform(None, torch.ones(1, 1))[0, 1]
        tensor([200., 100., 100.])
    """
    import trimesh  # imported lazily: only the generic loader needs it

    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise TypeError(f"dtype must be a floating torch.dtype, got {dtype}")
    device = check_device(device)
    obj_vertices = None
    if isinstance(mesh, (str, os.PathLike)):  # any path-like (an os.DirEntry too), not only a Path
        default_name = Path(mesh).stem
        is_obj = Path(mesh).suffix.lower() == ".obj"
        options: dict[str, Any] = {"maintain_order": True, "skip_materials": True} if is_obj else {}
        obj_vertices = _obj_vertices(Path(mesh)) if is_obj else None
        mesh = trimesh.load(os.fspath(mesh), process=False, force="mesh", **options)
    else:
        default_name = "mesh"
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"mesh must be a trimesh.Trimesh or a path to a mesh file, got {type(mesh).__name__}")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if obj_vertices is not None and obj_vertices.shape[0] != vertices.shape[0]:
        # trimesh's maintain_order path drops unreferenced vertices at the end of an OBJ with texture
        # coordinates; bases and landmark indices count the file's vertices, so they are put back
        n = vertices.shape[0]
        if obj_vertices.shape[0] > n and np.allclose(obj_vertices[:n], vertices, rtol=0, atol=1e-9):
            vertices = obj_vertices
        else:
            raise ValueError(f"{default_name}: trimesh read {n} of the file's {obj_vertices.shape[0]} vertices, not "
                             "in the file's order: the model's vertices would not be the file's")  # fmt: skip
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if bad.size:  # (an inf was "fx must be a finite number, got nan" from the winding check's view; a NaN warned
        # that the mesh "spans nan mm" before FaceModel refused its mean)
        raise ValueError(f"the mesh's vertices must be finite, got {vertices[bad[0]].tolist()} for vertex "
                         f"{int(bad[0])} ({bad.size} of the {vertices.shape[0]} vertices are not)")  # fmt: skip
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[0] == 0:
        raise ValueError(f"the mesh must hold triangles, got faces of shape {faces.shape}")
    num_v = vertices.shape[0]
    try:
        if isinstance(scale_to_mm, (str, bytes, bool)):
            raise TypeError
        scale_to_mm = float(scale_to_mm)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise TypeError(f"scale_to_mm must be a number (millimetres per mesh unit), got {scale_to_mm!r}") from None
    if not 0 < scale_to_mm < math.inf:
        raise ValueError(f"scale_to_mm must be positive and finite, got {scale_to_mm}")
    rot = np.eye(3) if to_head_frame is None else np.asarray(to_head_frame, dtype=np.float64)
    if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6):
        raise ValueError(f"to_head_frame must be a (3, 3) orthogonal matrix, got {np.array2string(rot)}")
    if np.linalg.det(rot) < 0:
        faces = faces[:, [0, 2, 1]]
    linear = rot.T * float(scale_to_mm)  # row vectors: x_head = x @ (s R)^T

    anim = _as_basis(blendshapes, "blendshapes", num_v)
    shape = _as_basis(shape_units, "shape_units", num_v)
    anim_names = _as_names(blendshape_names, anim.shape[0], "blendshape_names", "blendshape")
    shp_names = _as_names(shape_names, shape.shape[0], "shape_names", "shape")
    _check_displacements(anim, anim_names, vertices, "blendshapes")
    _check_displacements(shape, shp_names, vertices, "shape_units")
    if landmark_vertices is None:
        if landmark_weights is not None:
            raise ValueError("landmark_weights were given without landmark_vertices")
        lm_idx, lm_w = np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3))
    else:
        raw = np.asarray(landmark_vertices)
        given = raw.shape  # (the shape named in an error: (K,) stays (K,), not the (K, 1) it is taken as)
        if landmark_weights is not None:
            if raw.ndim == 1:
                raw = raw[:, None]
            if raw.ndim != 2 or not 1 <= raw.shape[1] <= 3:
                raise ValueError(f"landmark_vertices with landmark_weights must be (K, J) vertex indices, J <= 3 "
                                 f"(a landmark in a triangle), got shape {raw.shape}")  # fmt: skip
        elif raw.ndim not in (1, 2) or (raw.ndim == 2 and raw.shape[1] != 1):
            raise ValueError(
                f"landmark_vertices must be (K,) vertex indices, one per landmark, got shape {raw.shape} (a landmark "
                "between vertices takes (K, J) indices with landmark_weights of that shape)"
            )
        if raw.dtype == bool or not (np.issubdtype(raw.dtype, np.integer) or np.issubdtype(raw.dtype, np.floating)):
            raise TypeError(f"landmark_vertices must be integer vertex indices, got dtype {raw.dtype}")
        if np.issubdtype(raw.dtype, np.floating) and not np.array_equal(raw, np.round(raw)):
            raise ValueError("landmark_vertices must be whole vertex indices, got non-integer (or non-finite) values")
        # (K, J): reshape(K, -1) raised for K = 0 ("cannot reshape array of size 0"), an empty list taken before
        lm_idx = raw.astype(np.int64).reshape(raw.shape[0], raw.shape[1] if raw.ndim == 2 else 1)
        if lm_idx.size and (lm_idx.min() < 0 or lm_idx.max() >= num_v):
            raise ValueError(
                f"landmark_vertices must index vertices in [0, {num_v}), got [{lm_idx.min()}, {lm_idx.max()}]"
            )
        lm_w = np.ones((lm_idx.shape[0], 1)) if landmark_weights is None else np.asarray(landmark_weights, np.float64)
        if landmark_weights is not None:
            weights_given = lm_w.shape
            lm_w = lm_w[:, None] if lm_w.ndim == 1 else lm_w
            if lm_w.shape != lm_idx.shape:
                raise ValueError(f"landmark_weights must have landmark_vertices' shape {given}, got {weights_given}")
            # FaceModel's rule (non-negative, rows summing to one, each within 1e-2; it was within 1e-6 here and
            # negative weights passed both), then a rounding error below zero clamped to it and each row scaled to
            # sum to one exactly (one that does, without a negative weight, is kept to the bit). (The names made a
            # tuple once: an iterator of them was used up here, and refused below as "must hold 2 names, got 0".)
            landmark_names = _as_names(landmark_names, lm_idx.shape[0], "landmark_names", "landmark")
            check_landmark_weights(torch.from_numpy(lm_w), landmark_names)
            if lm_w.size:
                lm_w = np.maximum(lm_w, 0.0)
                lm_w = lm_w / lm_w.sum(axis=1, keepdims=True)
        # FaceModel holds three (vertex, weight) pairs a landmark: the first vertex again, at weight 0, pads them
        pad = 3 - lm_idx.shape[1]
        lm_idx = np.concatenate([lm_idx, np.repeat(lm_idx[:, :1], pad, axis=1)], axis=1)
        lm_w = np.concatenate([lm_w, np.zeros((lm_w.shape[0], pad))], axis=1)
    lm_names = _as_names(landmark_names, lm_idx.shape[0], "landmark_names", "landmark")
    if animation_ranges is None:
        ranges = np.tile(np.array([[0.0, 1.0]]), (anim.shape[0], 1))
    else:
        ranges = np.asarray(animation_ranges, dtype=np.float64)
        if ranges.shape != (anim.shape[0], 2):
            raise ValueError(f"animation_ranges must have shape ({anim.shape[0]}, 2), got {ranges.shape}")
    _check_blendshape_size(anim, ranges, anim_names, vertices, faces, "mesh units")
    if facs_links is not None and not isinstance(facs_links, Mapping):
        raise TypeError(f"facs_links must be a dict of blendshape name -> AU names, got {type(facs_links).__name__}")
    unknown = sorted(str(n) for n in set(facs_links or {}) - set(anim_names))
    if unknown:  # (a misspelt name linked nothing, and result.facs lost its AUs without a word)
        raise ValueError(f"facs_links names {unknown}, which are not blendshape names {anim_names}")
    links = [_facs_link((facs_links or {}).get(n, ()), n) for n in anim_names]
    facs_names = tuple(sorted({au for link in links for au in link}, key=lambda au: (len(au), au)))
    facs_matrix = np.zeros((len(facs_names), anim.shape[0]))
    for a, link in enumerate(links):
        for au in link:
            facs_matrix[facs_names.index(au), a] = 1.0
    said = f"with scale_to_mm={scale_to_mm:g}"
    scale = "is scale_to_mm the millimetres per mesh unit (1000 for metres, 10 for centimetres)?"
    _check_surface(vertices @ linear, faces, lm_idx, lm_w, default_name if name is None else name, said, scale)
    mask = np.zeros(num_v, dtype=bool)
    mask[faces.ravel()] = True

    def tensor(array: np.ndarray) -> torch.Tensor:  # (a caller's view with a negative stride: torch refuses it)
        return torch.as_tensor(np.ascontiguousarray(array), dtype=dtype, device=device)

    return FaceModel(
        name=default_name if name is None else str(name),
        mean=tensor(vertices @ linear),
        faces=torch.as_tensor(np.ascontiguousarray(faces), dtype=torch.int64, device=device),
        shape_units=tensor(shape @ linear),
        shape_names=shp_names,
        animation_units=tensor(anim @ linear),
        animation_names=anim_names,
        animation_ranges=tensor(ranges),
        landmark_vertices=torch.as_tensor(np.ascontiguousarray(lm_idx), dtype=torch.int64, device=device),
        landmark_weights=tensor(lm_w),
        landmark_names=lm_names,
        facs_names=facs_names,
        facs_matrix=tensor(facs_matrix),
        surface_vertex_mask=torch.as_tensor(mask, device=device),
    )


def load_ict_face_model(
    npz_path: str | Path,
    num_expressions: int | None = None,
    num_identities: int | None = None,
    *,
    area: str = "head",
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> FaceModel:
    """The ICT Face Model Light (USC ICT-VGL, MIT licence) from its ``.npz`` repack, as a :class:`FaceModel`.

    The file is in centimetres with +y up and +z toward the viewer; it is converted with
    :data:`ICT_TO_HEAD` and :data:`ICT_MM_PER_UNIT`. Expressions (ARKit-style blendshapes, weights in
    ``[0, 1]``) become animation units linked to FACS by :data:`ARKIT_TO_FACS`; identities become shape
    units; ``landmarks68`` gives the ``K = 68`` iBUG landmarks. A ``_L`` / ``_R`` pair links both its shapes to
    one AU, whose value (:meth:`FaceModel.facs_values`, the CSV's ``AUxx_r``) is their sum: ``AU12`` is
    ``mouthSmile_L + mouthSmile_R``, in ``[0, 2]``, not OpenFace's 0-5 intensity nor one side's weight.

    Args:
        npz_path: path to ``ict_face_model_light.npz`` (keys ``neutral, faces, expression_deltas,
            expression_names, identity_deltas, identity_names, landmarks68``).
        num_expressions: keep the first this many expressions (default all 53).
        num_identities: keep the first this many identities (default all 100).
        area: ``"head"`` (every vertex), ``"face"`` (the face's skin, 9409 vertices), ``"narrow"`` (the narrow face
            area, 6706 vertices: forehead to chin, cheek to cheek, without ears, neck or the inside of the mouth, and
            with holes at the eyes) or ``"narrow_eyes"`` (that and the eyeballs, 9846 vertices) (:data:`ICT_AREAS`;
            a part's vertices keep their order, the parts follow one another). To track, ``"narrow_eyes"``: with the
            whole head the tracker aligns the neck and the back of the head to the frame too, and lost a rendered
            CANDIDE-3 face on 37 of 80 frames of a pose sweep (docs/python-api.md, "Other face models").
        dtype: floating dtype of the model tensors.
        device: device of the model tensors.

    Returns:
        The model with ``V = 26719``, ``F = 52220`` (``"face"``: 9409, 18461; ``"narrow"``: 6706, 13120;
        ``"narrow_eyes"``: 9846, 19384).

    Raises:
        ValueError: a requested count is negative or exceeds what the file holds, a key is missing, or ``area`` is
            none of :data:`ICT_AREAS` (or the file is not the model's 26719 vertices), or ``device`` is not a
            device this machine has.
    """
    if area not in ICT_AREAS:
        raise ValueError(f"area must be one of {list(ICT_AREAS)}, got {area!r}")
    device = check_device(device)  # (before the file is read)
    with np.load(Path(npz_path), allow_pickle=False) as data:
        missing = {"neutral", "faces", "expression_deltas", "expression_names", "identity_deltas",
                   "identity_names", "landmarks68"} - set(data.files)
        if missing:
            raise ValueError(f"{npz_path} lacks the keys {sorted(missing)}")
        counts = {}
        for what, key, n in (("num_expressions", "expression_deltas", num_expressions),
                             ("num_identities", "identity_deltas", num_identities)):
            total = data[key].shape[0]
            if n is not None and (isinstance(n, bool) or not isinstance(n, numbers.Integral)):
                raise TypeError(f"{what} must be an int or None, got {n!r}")  # 3.7 was read as 3
            if n is not None and not 0 <= int(n) <= total:
                raise ValueError(f"{what} must be in [0, {total}], got {n}")
            counts[key] = total if n is None else int(n)
        n_exp, n_id = counts["expression_deltas"], counts["identity_deltas"]
        import trimesh

        total = data["neutral"].shape[0]
        if area == "head":
            keep = np.arange(total)
        elif total != ICT_AREAS["head"][0][1]:
            raise ValueError(f"{npz_path} holds {total} vertices, not the ICT Face Model's {ICT_AREAS['head'][0][1]}: "
                             "its areas are unknown (area='head' loads it whole)")  # fmt: skip
        else:
            keep = np.concatenate([np.arange(start, stop) for start, stop in ICT_AREAS[area]])
        new_index = np.full(total, -1, dtype=np.int64)
        new_index[keep] = np.arange(keep.shape[0])
        faces = new_index[data["faces"]]
        faces = faces[(faces >= 0).all(axis=1)]
        landmarks = new_index[data["landmarks68"]]
        if (landmarks < 0).any():
            raise ValueError(f"{npz_path}'s landmarks lie outside the {area!r} area")
        part: slice | np.ndarray = slice(None) if area == "head" else keep  # (the whole model: no copies)
        mesh = trimesh.Trimesh(data["neutral"][part], faces, process=False)
        expr_names = tuple(str(s) for s in data["expression_names"][:n_exp])
        links = {n: ARKIT_TO_FACS.get(n.rsplit("_", 1)[0] if n.endswith(("_L", "_R")) else n, ()) for n in expr_names}
        return load_mesh_model(
            mesh,
            blendshapes=data["expression_deltas"][:n_exp][:, part],
            blendshape_names=expr_names,
            shape_units=data["identity_deltas"][:n_id][:, part],
            shape_names=tuple(str(s) for s in data["identity_names"][:n_id]),
            landmark_vertices=landmarks,
            landmark_names=tuple(f"ibug{k}" for k in range(data["landmarks68"].shape[0])),
            facs_links=links,
            scale_to_mm=ICT_MM_PER_UNIT,
            to_head_frame=ICT_TO_HEAD,
            name="ICT Face Model Light" if area == "head" else f"ICT Face Model Light ({area})",
            dtype=dtype,
            device=device,
        )
