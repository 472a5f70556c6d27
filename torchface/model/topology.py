"""Triangle-mesh topology helpers used when loading face models: edge use, consistent and outward winding.

These run once at load time on NumPy arrays (``V`` vertices, ``F`` triangles). A triangle ``(a, b, c)``
uses the directed edges ``a->b``, ``b->c``, ``c->a``; two triangles that share an edge are wound
consistently when they traverse it in opposite directions. Its normal is ``(v_b - v_a) x (v_c - v_a)``.
"""

from __future__ import annotations

from collections import deque

import numpy as np

__all__ = [
    "directed_edges",
    "edge_use_counts",
    "inconsistent_edges",
    "make_winding_consistent",
    "orient_outward",
    "unused_vertices",
]


def _check_faces(faces: np.ndarray) -> np.ndarray:
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces must be an integer (F, 3) array, got {faces.shape} {faces.dtype}")
    return faces.astype(np.int64, copy=False)


def directed_edges(faces: np.ndarray) -> np.ndarray:
    """``(F, 3)`` triangles -> ``(3F, 2)`` directed edges ``a->b, b->c, c->a`` (face ``f`` owns rows ``3f..3f+2``)."""
    faces = _check_faces(faces)
    return np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)


def edge_use_counts(faces: np.ndarray) -> dict[tuple[int, int], int]:
    """How many triangles use each undirected edge ``(min, max)``: 1 on a boundary, 2 inside a manifold."""
    counts: dict[tuple[int, int], int] = {}
    for a, b in np.sort(directed_edges(faces), axis=1).tolist():
        counts[(a, b)] = counts.get((a, b), 0) + 1
    return counts


def inconsistent_edges(faces: np.ndarray) -> list[tuple[int, int]]:
    """Directed edges used more than once in the same direction (empty when the winding is consistent)."""
    seen: dict[tuple[int, int], int] = {}
    for a, b in directed_edges(faces).tolist():
        seen[(a, b)] = seen.get((a, b), 0) + 1
    return sorted(edge for edge, n in seen.items() if n > 1)


def make_winding_consistent(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flip triangles so that neighbours across every shared edge traverse it in opposite directions.

    Breadth-first propagation over the face adjacency graph: the first triangle of each connected
    component keeps its winding and every neighbour is flipped or kept to agree with it. Vertices are
    never welded: adjacency is by vertex index only, so coincident but distinct vertices stay apart.

    Args:
        faces: ``(F, 3)`` triangles.

    Returns:
        ``(F, 3)`` re-wound triangles and ``(F,)`` int64 connected-component labels.

    Raises:
        ValueError: the surface is not orientable (a Moebius-like cycle of neighbours), or an edge is
            used more than twice (shared by more than two triangles, or used by a triangle with a repeated vertex,
            or by a triangle given twice, which the message says).
    """
    faces = _check_faces(faces).copy()
    num_f = faces.shape[0]
    edge_faces: dict[tuple[int, int], list[int]] = {}
    for row, (a, b) in enumerate(np.sort(directed_edges(faces), axis=1).tolist()):
        edge_faces.setdefault((a, b), []).append(row // 3)
    for edge, owners in edge_faces.items():
        if len(owners) > 2:
            # (which triangles, and why where one repeats a vertex, and so uses an edge twice, or a triangle is given
            # twice: load_mesh_model's check passes both, and its message sends a mesh here)
            tris = sorted(set(owners))
            named = ", ".join(f"{f} {faces[f].tolist()}" for f in tris)
            repeated_vertex = [f for f in tris if len(set(faces[f].tolist())) < 3]
            if repeated_vertex:
                raise ValueError(f"edge {edge} is used {len(owners)} times, by triangles {named}: triangle "
                                 f"{repeated_vertex[0]} repeats a vertex, which uses the edge twice; leave such "
                                 "triangles out (they have no area)")  # fmt: skip
            corners = [tuple(sorted(faces[f].tolist())) for f in tris]
            twice = "; a triangle is given more than once: keep one copy" if len(set(corners)) < len(corners) else ""
            raise ValueError(f"edge {edge} is shared by {len(tris)} triangles ({named}); expected a manifold (at "
                             f"most 2){twice}")  # fmt: skip

    def uses(face: np.ndarray, a: int, b: int) -> bool:
        """Whether ``face`` traverses ``a->b``."""
        return any(face[i] == a and face[(i + 1) % 3] == b for i in range(3))

    labels = np.full(num_f, -1, dtype=np.int64)
    component = 0
    for seed in range(num_f):
        if labels[seed] >= 0:
            continue
        labels[seed] = component
        queue = deque([seed])
        while queue:
            f = queue.popleft()
            tri = faces[f]
            for i in range(3):
                a, b = int(tri[i]), int(tri[(i + 1) % 3])
                for g in edge_faces[(min(a, b), max(a, b))]:
                    if g == f:
                        continue
                    same_direction = uses(faces[g], a, b)
                    if labels[g] < 0:
                        if same_direction:
                            faces[g] = faces[g][[0, 2, 1]]
                        labels[g] = component
                        queue.append(g)
                    elif same_direction:
                        raise ValueError(
                            f"the surface is not orientable: triangles {f} and {g} cannot agree on edge {a}-{b}"
                        )
        component += 1
    return faces, labels


def orient_outward(
    vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, interior_point: np.ndarray
) -> np.ndarray:
    """Flip whole consistently-wound components whose normals point, on balance, toward ``interior_point``.

    For each component, the flux ``sum_f (c_f - p) . n_f`` (``c_f`` centroid, ``n_f`` area-weighted
    normal, ``p`` the interior point) is the volume-like measure that is positive when the surface faces
    away from ``p``; components with negative flux are flipped.

    Args:
        vertices: ``(V, 3)`` positions.
        faces: ``(F, 3)`` consistently wound triangles (see :func:`make_winding_consistent`).
        labels: ``(F,)`` component labels.
        interior_point: ``(3,)`` a point inside the head, behind the surface.

    Returns:
        ``(F, 3)`` triangles with every component wound outward.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = _check_faces(faces).copy()
    tri = vertices[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flux = np.einsum("fi,fi->f", tri.mean(axis=1) - np.asarray(interior_point, dtype=np.float64), normals)
    for comp in np.unique(labels):
        sel = labels == comp
        if flux[sel].sum() < 0:
            faces[sel] = faces[sel][:, [0, 2, 1]]
    return faces


def unused_vertices(num_vertices: int, faces: np.ndarray) -> np.ndarray:
    """Sorted int64 indices of the vertices that no triangle references."""
    used = np.zeros(num_vertices, dtype=bool)
    used[_check_faces(faces).ravel()] = True
    return np.flatnonzero(~used).astype(np.int64)
