"""Build a :class:`FaceModel` from any triangle mesh plus optional linear bases (e.g. the ICT Face Model).

The paper notes that a denser model can replace CANDIDE-3 (Section 2); these loaders give such a model
the same :class:`FaceModel` interface. Meshes are read with ``trimesh`` (``process=False``, so nothing is
welded or reordered), mapped into the head frame with a user-given orthogonal matrix and scaled to
millimetres (see :mod:`torchface.conventions`).

Shapes: ``V`` vertices, ``F`` triangles, ``S`` shape units, ``A`` animation units (blendshapes), ``K`` landmarks.
"""

from __future__ import annotations

import numbers
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from torchface.model.face_model import FaceModel

__all__ = ["load_mesh_model", "load_ict_face_model", "ICT_TO_HEAD", "ICT_MM_PER_UNIT", "ARKIT_TO_FACS"]

#: ICT Face Model frame (+x subject's left, +y up, +z toward the viewer) to the head frame: 180 deg about x.
ICT_TO_HEAD = np.diag([1.0, -1.0, -1.0])

#: The ICT Face Model is in centimetres (outer eye corners 8.9 apart, head 24.8 wide).
ICT_MM_PER_UNIT = 10.0

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
    if isinstance(names, str):  # a str is a Sequence[str]: its characters were taken as the names
        raise TypeError(f"{what} must be a sequence of names, e.g. ({names!r},), not one string")
    names = tuple(str(n) for n in names)
    if len(names) != count:
        raise ValueError(f"{what} must hold {count} names (one per unit), got {len(names)}")
    return names


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
    already be consistent and outward.

    Args:
        mesh: a ``trimesh.Trimesh`` or a path (``str`` or any ``os.PathLike``) to any file trimesh reads (loaded
            with ``process=False``; OBJ files also with ``maintain_order=True`` so that vertices keep the file's
            order and count, which trimesh otherwise splits at texture seams and prunes when unreferenced).
        blendshapes: ``(A, V, 3)`` animation displacements per unit weight (mesh units and frame), or ``None``.
        blendshape_names: ``A`` names (default ``"blendshape{i}"``).
        shape_units: ``(S, V, 3)`` identity displacements, or ``None``.
        shape_names: ``S`` names (default ``"shape{i}"``).
        landmark_vertices: ``(K,)`` int vertex index per landmark, or ``None`` for ``K = 0``.
        landmark_names: ``K`` names (default ``"landmark{k}"``).
        animation_ranges: ``(A, 2)`` ``[lo, hi]`` per blendshape (default ``[0, 1]``, the blendshape-weight
            convention).
        facs_links: blendshape name -> FACS AUs it is linked to (names not listed link to nothing).
        scale_to_mm: millimetres per mesh unit.
        to_head_frame: ``(3, 3)`` orthogonal matrix from the mesh frame to the head frame (default identity).
        name: model name (default: the file name, or ``"mesh"``).
        dtype: floating dtype of the model tensors.
        device: device of the model tensors.

    Returns:
        The model; ``A = 0`` and ``S = 0`` give ``(0, V, 3)`` bases.

    Raises:
        TypeError: ``mesh`` is neither a Trimesh nor a path, ``dtype`` is not floating, or a name list or a
            ``facs_links`` value is one string (a sequence of names is expected).
        ValueError: a basis, name list, landmark index or range has the wrong size, the file holds no
            triangles, ``to_head_frame`` is not orthogonal, or ``scale_to_mm`` is not positive.

    Example:
        >>> import trimesh
        >>> tri = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 2, 1]], process=False)
        >>> model = load_mesh_model(tri, blendshapes=np.ones((1, 3, 3)), scale_to_mm=10.0)
        >>> model.deform(None, torch.ones(1, 1))[0, 1]
        tensor([20., 10., 10.])
    """
    import trimesh  # imported lazily: only the generic loader needs it

    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise TypeError(f"dtype must be a floating torch.dtype, got {dtype}")
    obj_vertices = None
    if isinstance(mesh, (str, os.PathLike)):  # any path-like (an os.DirEntry too), not only a Path
        default_name = Path(mesh).stem
        is_obj = Path(mesh).suffix.lower() == ".obj"
        options = {"maintain_order": True, "skip_materials": True} if is_obj else {}
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
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[0] == 0:
        raise ValueError(f"the mesh must hold triangles, got faces of shape {faces.shape}")
    num_v = vertices.shape[0]
    if not scale_to_mm > 0:
        raise ValueError(f"scale_to_mm must be positive, got {scale_to_mm}")
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
    if landmark_vertices is None:
        lm = np.zeros((0,), dtype=np.int64)
    else:
        lm = np.asarray(landmark_vertices).astype(np.int64).reshape(-1)
        if lm.size and (lm.min() < 0 or lm.max() >= num_v):
            raise ValueError(f"landmark_vertices must index vertices in [0, {num_v}), got [{lm.min()}, {lm.max()}]")
    lm_names = _as_names(landmark_names, lm.shape[0], "landmark_names", "landmark")
    if animation_ranges is None:
        ranges = np.tile(np.array([[0.0, 1.0]]), (anim.shape[0], 1))
    else:
        ranges = np.asarray(animation_ranges, dtype=np.float64)
        if ranges.shape != (anim.shape[0], 2):
            raise ValueError(f"animation_ranges must have shape ({anim.shape[0]}, 2), got {ranges.shape}")
    for unit, link in (facs_links or {}).items():
        if isinstance(link, str):  # its characters were taken as AUs: "AU12" linked the unit to 'A', 'U', '1', '2'
            raise TypeError(f"facs_links[{unit!r}] must be a tuple of FACS AU names, e.g. ({link!r},), not one string")
    links = [tuple((facs_links or {}).get(n, ())) for n in anim_names]
    facs_names = tuple(sorted({au for link in links for au in link}, key=lambda au: (len(au), au)))
    facs_matrix = np.zeros((len(facs_names), anim.shape[0]))
    for a, link in enumerate(links):
        for au in link:
            facs_matrix[facs_names.index(au), a] = 1.0
    mask = np.zeros(num_v, dtype=bool)
    mask[faces.ravel()] = True

    def tensor(array: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(array, dtype=dtype, device=device)

    return FaceModel(
        name=default_name if name is None else str(name),
        mean=tensor(vertices @ linear),
        faces=torch.as_tensor(faces, dtype=torch.int64, device=device),
        shape_units=tensor(shape @ linear),
        shape_names=shp_names,
        animation_units=tensor(anim @ linear),
        animation_names=anim_names,
        animation_ranges=tensor(ranges),
        landmark_vertices=torch.as_tensor(np.stack([lm, lm, lm], axis=1), dtype=torch.int64, device=device),
        landmark_weights=tensor(np.tile(np.array([1.0, 0.0, 0.0]), (lm.shape[0], 1))),
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
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> FaceModel:
    """The ICT Face Model Light (USC ICT-VGL, MIT licence) from its ``.npz`` repack, as a :class:`FaceModel`.

    The file is in centimetres with +y up and +z toward the viewer; it is converted with
    :data:`ICT_TO_HEAD` and :data:`ICT_MM_PER_UNIT`. Expressions (ARKit-style blendshapes, weights in
    ``[0, 1]``) become animation units linked to FACS by :data:`ARKIT_TO_FACS`; identities become shape
    units; ``landmarks68`` gives the ``K = 68`` iBUG landmarks.

    Args:
        npz_path: path to ``ict_face_model_light.npz`` (keys ``neutral, faces, expression_deltas,
            expression_names, identity_deltas, identity_names, landmarks68``).
        num_expressions: keep the first this many expressions (default all 53).
        num_identities: keep the first this many identities (default all 100).
        dtype: floating dtype of the model tensors.
        device: device of the model tensors.

    Returns:
        The model with ``V = 26719``, ``F = 52220``.

    Raises:
        ValueError: a requested count is negative or exceeds what the file holds, or a key is missing.
    """
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

        mesh = trimesh.Trimesh(data["neutral"], data["faces"], process=False)
        expr_names = tuple(str(s) for s in data["expression_names"][:n_exp])
        links = {n: ARKIT_TO_FACS.get(n.rsplit("_", 1)[0] if n.endswith(("_L", "_R")) else n, ()) for n in expr_names}
        return load_mesh_model(
            mesh,
            blendshapes=data["expression_deltas"][:n_exp],
            blendshape_names=expr_names,
            shape_units=data["identity_deltas"][:n_id],
            shape_names=tuple(str(s) for s in data["identity_names"][:n_id]),
            landmark_vertices=data["landmarks68"],
            landmark_names=tuple(f"ibug{k}" for k in range(data["landmarks68"].shape[0])),
            facs_links=links,
            scale_to_mm=ICT_MM_PER_UNIT,
            to_head_frame=ICT_TO_HEAD,
            name="ICT Face Model Light",
            dtype=dtype,
            device=device,
        )
