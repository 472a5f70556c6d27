"""Topology helpers: consistent winding by propagation, outward orientation, unused vertices."""

from __future__ import annotations

import numpy as np
import pytest

from torchface.model.topology import (
    edge_use_counts,
    inconsistent_edges,
    make_winding_consistent,
    orient_outward,
    unused_vertices,
)

# A cube's 12 triangles, wound outward.
CUBE_V = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
CUBE_F = np.array([
    [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
    [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],
])


def signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    t = v[f]
    return float(np.einsum("fi,fi->f", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def test_cube_fixture_is_outward():
    assert inconsistent_edges(CUBE_F) == []
    assert signed_volume(CUBE_V, CUBE_F) == pytest.approx(1.0)
    assert set(edge_use_counts(CUBE_F).values()) == {2}


def test_scrambled_winding_is_repaired_and_oriented():
    rng = np.random.default_rng(0)
    scrambled = CUBE_F.copy()
    flip = rng.random(len(CUBE_F)) < 0.5
    flip[0] = True  # the seed face is wrong too, so the whole component must be flipped back
    scrambled[flip] = scrambled[flip][:, [0, 2, 1]]
    assert inconsistent_edges(scrambled) != []
    fixed, labels = make_winding_consistent(scrambled)
    assert inconsistent_edges(fixed) == [] and set(labels.tolist()) == {0}
    assert signed_volume(CUBE_V, fixed) == pytest.approx(-1.0)  # consistent, but inward (seed was flipped)
    out = orient_outward(CUBE_V, fixed, labels, np.array([0.5, 0.5, 0.5]))
    assert signed_volume(CUBE_V, out) == pytest.approx(1.0)
    # Same triangles, only the winding changed.
    assert sorted(map(sorted, out.tolist())) == sorted(map(sorted, CUBE_F.tolist()))


def test_components_are_oriented_independently():
    faces = np.vstack([CUBE_F, CUBE_F[:, [0, 2, 1]] + 8])  # second cube wound inward
    verts = np.vstack([CUBE_V, CUBE_V + 3.0])
    fixed, labels = make_winding_consistent(faces)
    assert set(labels.tolist()) == {0, 1}
    out0 = orient_outward(verts, fixed[labels == 0], labels[labels == 0], np.array([0.5, 0.5, 0.5]))
    out1 = orient_outward(verts, fixed[labels == 1], labels[labels == 1], np.array([3.5, 3.5, 3.5]))
    assert signed_volume(verts, out0) == pytest.approx(1.0) and signed_volume(verts, out1) == pytest.approx(1.0)


def test_nonmanifold_and_unused():
    fan = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]])  # edge 0-1 shared by three triangles
    with pytest.raises(ValueError, match=r"shared by 3 triangles \(0 \[0, 1, 2\], 1 \[0, 1, 3\], 2 \[0, 1, 4\]\); "
                                         r"expected a manifold \(at most 2\)$"):
        make_winding_consistent(fan)
    # a triangle with a repeated vertex, or one given twice (both of which load_mesh_model's winding check passes, and
    # whose message names this function): "edge (0, 1) is shared by 4 triangles" of 3, and by 3 of 2, said no more
    square = np.array([[0, 1, 2], [0, 3, 1]])
    with pytest.raises(ValueError, match=r"edge \(0, 1\) is used 4 times, by triangles 0 \[0, 1, 2\], 1 \[0, 3, 1\], "
                                         r"2 \[0, 0, 1\]: triangle 2 repeats a vertex, which uses the edge twice"):
        make_winding_consistent(np.concatenate([square, [[0, 0, 1]]]))
    with pytest.raises(ValueError, match=r"shared by 3 triangles \(0 \[0, 1, 2\], 1 \[0, 3, 1\], 2 \[2, 1, 0\]\); "
                                         r"expected a manifold \(at most 2\); a triangle is given more than once"):
        make_winding_consistent(np.concatenate([square, [[2, 1, 0]]]))
    assert unused_vertices(7, fan).tolist() == [5, 6]
    with pytest.raises(ValueError, match=r"\(F, 3\)"):
        edge_use_counts(np.zeros((2, 4), dtype=int))
