"""CANDIDE-3 parser and loader: counts, encoding, frame, winding, symmetry, FAP scaling, data tables."""

from __future__ import annotations

import csv
import io
import os
from importlib import resources

import numpy as np
import pytest
import torch

from torchface.conventions import MM_PER_CANDIDE_UNIT
from torchface.model import AnimationSet, candide3_fapu, load_candide3, parse_wfm
from torchface.model.candide import FAP_EYEBALL_FAPU, read_auv_facs_table, read_landmark_table
from torchface.model.topology import edge_use_counts, inconsistent_edges

DATA = resources.files("torchface").joinpath("data")
WFM_BYTES = DATA.joinpath("candide3.wfm").read_bytes()
LEGACY = [4, 35, 36, 37, 38, 39, 41, 42, 43]
MOUTH_PAIRS = [(40, 87), (81, 83), (82, 84)]
# iBUG-68 left/right flip (0-based).
IBUG_FLIP = (
    list(range(16, -1, -1))
    + list(range(26, 16, -1))
    + [27, 28, 29, 30, 35, 34, 33, 32, 31]
    + [45, 44, 43, 42, 47, 46, 39, 38, 37, 36, 41, 40]
    + [54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55]
    + [64, 63, 62, 61, 60, 67, 66, 65]
)


@pytest.fixture(scope="module")
def wfm():
    return parse_wfm(WFM_BYTES)


@pytest.fixture(scope="module")
def model64():
    return load_candide3(AnimationSet.AUV_AND_FAP, dtype=torch.float64)


def mirror_map(verts: np.ndarray) -> np.ndarray:
    """Vertex -> its mirror image in x; coincident vertices are paired by rank (never welded)."""
    key = {tuple(np.round(v, 6)): [] for v in verts}
    for i, v in enumerate(verts):
        key[tuple(np.round(v, 6))].append(i)
    out = np.full(len(verts), -1)
    for pos, group in key.items():
        partner = key[(round(-pos[0], 6) + 0.0, pos[1], pos[2])]
        assert len(partner) == len(group), pos
        out[group] = partner
    return out


def outside_parity(verts: np.ndarray, faces: np.ndarray, points: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Number of triangles hit by the rays ``points + t * direction`` (t > 0), Moller-Trumbore, vectorised."""
    tri = verts[faces]  # (F, 3, 3)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(direction, e2)  # (F, 3)
    det = np.einsum("fi,fi->f", e1, p)
    inv = 1.0 / det
    s = points[:, None, :] - tri[None, :, 0]  # (Q, F, 3)
    u = np.einsum("qfi,fi->qf", s, p) * inv
    q = np.cross(s, e1[None])
    v = np.einsum("qfi,i->qf", q, direction) * inv
    t = np.einsum("qfi,fi->qf", q, e2) * inv
    hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return hit.sum(axis=1)


def faces_pointing_outward(verts: np.ndarray, faces: np.ndarray, toward_viewer: np.ndarray) -> np.ndarray:
    """Per face: does its normal point out of the head?

    The mask is open, so "inside the head" is decided by ray parity toward the viewer: a point is inside
    when a ray toward the viewer crosses the surface an odd number of times. A face points outward when
    the point a small step along its normal is outside and the point a step against it is inside. This
    holds for folded faces (eyelid to iris) too, where the normal points away from the viewer.
    """
    tri = verts[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = tri.mean(axis=1)
    eps = 1e-3
    front = outside_parity(verts, faces, c + eps * n, toward_viewer) % 2 == 0
    back = outside_parity(verts, faces, c - eps * n, toward_viewer) % 2 == 1
    return front & back


# ------------------------------------------------------------------------------------------------ parser
def test_counts_read_from_file(wfm):
    assert wfm.vertices.shape == (113, 3)
    assert wfm.faces.shape == (184, 3)
    assert len(wfm.shape_units) == 14
    auvs = [u for u in wfm.animation_units if not u.is_fap]
    faps = [u for u in wfm.animation_units if u.is_fap]
    assert (len(auvs), len(faps)) == (11, 54)
    assert wfm.global_motion.shape == (3, 3)
    assert wfm.animation_parameters.shape == (0, 2)


def test_counts_follow_the_file_not_constants():
    text = WFM_BYTES.decode("latin-1")
    # Drop the last triangle and lower the face count: the parser must follow the count.
    lines = text.splitlines()
    i = lines.index("# FACE LIST:")
    lines[i + 1] = "183"
    del lines[i + 2 + 183]
    assert parse_wfm("\n".join(lines)).faces.shape == (183, 3)


def test_latin1_required_and_accepted(tmp_path):
    with pytest.raises(UnicodeDecodeError):
        WFM_BYTES.decode("utf-8")
    path = tmp_path / "c.wfm"
    path.write_bytes(WFM_BYTES)
    from_path = parse_wfm(path)
    from_str_path = parse_wfm(str(path))
    assert any("Link\xf6ping" in h for h in from_path.header)
    np.testing.assert_array_equal(from_path.vertices, from_str_path.vertices)
    # Any os.PathLike is a path: an os.DirEntry raised "path_or_text must be a path, the file's text or its bytes".
    (entry,) = os.scandir(tmp_path)
    np.testing.assert_array_equal(parse_wfm(entry).vertices, from_path.vertices)


def test_unit_rows_and_fapu_comments(wfm):
    jaw = wfm.animation_units[1]
    assert jaw.name.startswith("AUV11 Jaw drop")
    assert jaw.vertex_indices.shape == (12,) and jaw.vectors.shape == (12, 3)
    np.testing.assert_allclose(jaw.vectors[0], [0.0, -0.26, -0.05])
    faps = [u for u in wfm.animation_units if u.is_fap]
    assert faps[0].name == "FAP 3 open_jaw" and faps[0].fapu == "MNS"
    no_fapu = [u.name for u in faps if u.fapu is None]
    assert len(no_fapu) == 8 and all(f"FAP{n}" in name for n, name in zip(range(23, 31), no_fapu))


@pytest.mark.parametrize(
    "text, message",
    [
        ("# VERTEX LIST:\n3\n0 0 0\n1 0 0\n", "row 3 of 3"),
        ("# VERTEX LIST:\n1\n0 0 0\n", "missing section"),
        ("# VERTEX LIST:\n1\n0 0 0\n# FACE LIST:\n1\n0 1 2\n", "outside"),
        ("# VERTEX LIST:\nthree\n", "integer count"),
        ("# VERTEX LIST:\n1\n0 zero 0\n", "could not read"),
    ],
)
def test_malformed_files_raise(text, message):
    with pytest.raises(ValueError, match=message):
        parse_wfm(text)


def test_fapu_values(wfm):
    fapu = candide3_fapu(wfm.vertices)
    expected = {"ES": 0.613, "IRISD": 0.085, "ENS": 0.4225, "MNS": 0.196, "MW": 0.492}
    for key, value in expected.items():
        assert fapu[key] == pytest.approx(value, abs=1e-9), key
    # The millimetre scale of the conventions maps ES to 63 mm.
    assert fapu["ES"] * MM_PER_CANDIDE_UNIT == pytest.approx(63.0)


# --------------------------------------------------------------------------------------- frame, counts
def test_model_sizes_and_names():
    model = load_candide3()
    assert (model.num_vertices, model.num_faces, model.num_shape, model.num_animation) == (113, 184, 14, 11)
    assert model.animation_names[:3] == ("AUV0 Upper lip raiser", "AUV11 Jaw drop", "AUV2 Lip stretcher")
    assert model.shape_names[0] == "Head height" and model.shape_names[-1] == "Chin width"
    both = load_candide3(AnimationSet.AUV_AND_FAP)
    faps = load_candide3(AnimationSet.FAP)
    assert both.num_animation == 65 and faps.num_animation == 54
    assert both.animation_names[11] == "FAP3 open_jaw" and faps.animation_names[-1] == "FAP64 bend_nose"
    with pytest.raises(TypeError, match="AnimationSet"):
        load_candide3("auv")


def test_head_frame_and_millimetres(wfm, model64):
    expected = wfm.vertices * np.array([1.0, -1.0, -1.0]) * MM_PER_CANDIDE_UNIT
    np.testing.assert_allclose(model64.mean.numpy(), expected, atol=1e-9)
    mean = model64.mean.numpy()
    # Nose tip (vertex 5) is the point closest to the viewer (smallest z); the chin (10) is lowest (+y).
    used = model64.surface_vertex_mask.numpy()
    assert np.argmin(np.where(used, mean[:, 2], np.inf)) == 5
    assert np.argmax(mean[:, 1]) == 10
    # Subject's left eye outer corner (vertex 20) is at +x.
    assert mean[20, 0] > 0
    # Interpupillary distance 63 mm.
    left = mean[[67, 68, 71, 72]].mean(0)
    right = mean[[69, 70, 73, 74]].mean(0)
    assert np.linalg.norm(left - right) == pytest.approx(63.0)


# ----------------------------------------------------------------------------------------------- winding
TOWARD_VIEWER = np.array([0.013, 0.029, -1.0]) / np.linalg.norm([0.013, 0.029, -1.0])  # head frame, skewed


def test_winding_consistent(model64):
    faces = model64.faces.numpy()
    assert inconsistent_edges(faces) == []
    counts = edge_use_counts(faces)
    assert set(counts.values()) <= {1, 2}
    directed = {tuple(e) for e in np.stack([faces, np.roll(faces, -1, axis=1)], -1).reshape(-1, 2).tolist()}
    for (a, b), n in counts.items():
        if n == 2:  # interior edge: once in each direction
            assert (a, b) in directed and (b, a) in directed
    # The file's own winding is not consistent.
    assert inconsistent_edges(parse_wfm(WFM_BYTES).faces) != []


def test_every_face_points_out_of_the_head(model64, wfm):
    verts = model64.mean.numpy()
    faces = model64.faces.numpy()
    outward = faces_pointing_outward(verts, faces, TOWARD_VIEWER)
    # Two sliver triangles join each lower lid to the iris corner below it (vertices 55-70-100 and
    # 22-68-99). The iris corner sits below the lid line and in front of the lid, so each sliver folds
    # over its neighbour across the shared lid edge and shows its back to the viewer: no consistent
    # winding can make it face out there. Every other face passes.
    flaps = [i for i, f in enumerate(faces.tolist()) if set(f) in ({55, 70, 100}, {22, 68, 99})]
    assert len(flaps) == 2
    assert np.flatnonzero(~outward).tolist() == flaps
    # The file's own winding fails on most faces: the loader keeps 24 of its triangles as written, and
    # the criterion passes exactly those plus the two flaps (wound the other way in the file).
    rotations = [lambda t: t, lambda t: t[1:] + t[:1], lambda t: t[2:] + t[:2]]
    kept = [i for i, (a, b) in enumerate(zip(wfm.faces.tolist(), faces.tolist())) if any(a == r(b) for r in rotations)]
    assert len(kept) == 24
    raw = faces_pointing_outward(verts, wfm.faces, TOWARD_VIEWER)
    assert np.flatnonzero(raw).tolist() == sorted(kept + flaps)
    # Flipping single faces (a front face, a folded eyelid-to-iris face) is detected, and only those.
    tri = verts[faces]
    nz = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2]
    folded = int(next(i for i in np.flatnonzero(nz > 0) if i not in flaps))  # normal away from the viewer
    flipped = faces.copy()
    flipped[[0, folded]] = flipped[[0, folded]][:, [0, 2, 1]]
    bad = np.flatnonzero(~faces_pointing_outward(verts, flipped, TOWARD_VIEWER))
    assert bad.tolist() == sorted({0, folded, *flaps})


def test_unused_vertices_kept_and_not_welded(model64, wfm):
    mask = model64.surface_vertex_mask.numpy()
    assert np.flatnonzero(~mask).tolist() == LEGACY
    faces = model64.faces.numpy()
    assert not np.isin(faces, LEGACY).any()
    assert model64.num_vertices == wfm.vertices.shape[0]
    jaw = model64.animation_names.index("AUV11 Jaw drop")
    verts = model64.deform(None, torch.eye(model64.num_animation, dtype=torch.float64)[jaw : jaw + 1])[0].numpy()
    for a, b in MOUTH_PAIRS:
        assert np.isin([a, b], faces).all()
        np.testing.assert_allclose(model64.mean[a].numpy(), model64.mean[b].numpy())
        # Jaw drop pulls each pair apart, the lower one (40, 83, 84) downward (+y).
        assert verts[b if b != 87 else a, 1] - verts[a if b != 87 else b, 1] > 10.0


# ---------------------------------------------------------------------------------------------- symmetry
def test_mirror_map_is_an_involution(model64):
    mirror = mirror_map(model64.mean.numpy())
    np.testing.assert_array_equal(mirror[mirror], np.arange(model64.num_vertices))
    assert mirror[81] == 82 and mirror[83] == 84 and mirror[40] == 40 and mirror[87] == 87


def test_auvs_move_mirrored_vertices_symmetrically(model64):
    mirror = mirror_map(model64.mean.numpy())
    flip = np.array([-1.0, 1.0, 1.0])
    for a, name in enumerate(model64.animation_names[:11]):
        disp = model64.animation_units[a].numpy()
        np.testing.assert_allclose(disp[mirror], disp * flip, atol=1e-12, err_msg=name)
        assert np.abs(disp).max() > 1.0, name


def test_shape_units_symmetry(model64):
    mirror = mirror_map(model64.mean.numpy())
    flip = np.array([-1.0, 1.0, 1.0])
    for s, name in enumerate(model64.shape_names):
        disp = model64.shape_units[s].numpy()
        if name == "Eyes vertical difference":  # moves one eye up and the other down
            np.testing.assert_allclose(disp[mirror], -disp * flip, atol=1e-12)
        else:
            np.testing.assert_allclose(disp[mirror], disp * flip, atol=1e-12, err_msg=name)


@pytest.mark.parametrize(
    "left, right",
    [("stretch_l_cornerlip", "stretch_r_cornerlip"), ("close_t_l_eyelid", "close_t_r_eyelid"),
     ("raise_l_o_eyebrow", "raise_r_o_eyebrow"), ("squeeze_l_eyebrow", "squeeze_r_eyebrow"),
     ("lower_t_lip_lm", "lower_t_lip_rm"), ("strecth_l_nose", "strecth_r_nose"), ("puff_l_cheek", "puff_r_cheek")],
)
def test_left_right_faps_mirror_each_other(model64, left, right):
    mirror = mirror_map(model64.mean.numpy())
    names = [n.split(" ", 1)[1] for n in model64.animation_names]
    dl = model64.animation_units[names.index(left)].numpy()
    dr = model64.animation_units[names.index(right)].numpy()
    np.testing.assert_allclose(dr[mirror], dl * np.array([-1.0, 1.0, 1.0]), atol=1e-12)


# ----------------------------------------------------------------------------------------- FAP scaling
def test_fap_scaling(model64, wfm):
    fapu = candide3_fapu(wfm.vertices)
    names = list(model64.animation_names)
    coeffs = torch.zeros(1, model64.num_animation, dtype=torch.float64)
    coeffs[0, names.index("FAP3 open_jaw")] = 1024.0
    moved = model64.deform(None, coeffs)[0] - model64.mean
    # open_jaw: direction (0, -1, 0) in the file -> +y (down) in the head frame, one MNS for 1024.
    for v in (10, 32, 65):
        np.testing.assert_allclose(moved[v].numpy(), [0.0, fapu["MNS"] * MM_PER_CANDIDE_UNIT, 0.0], atol=1e-9)
    assert moved.abs().sum() == pytest.approx(3 * fapu["MNS"] * MM_PER_CANDIDE_UNIT)
    # close_t_l_eyelid: row (0, -1, 0.1) per IRISD; 1024 closes the lid by one iris diameter (8.74 mm).
    a = names.index("FAP19 close_t_l_eyelid")
    np.testing.assert_allclose(
        model64.animation_units[a, 21].numpy() * 1024.0,
        np.array([0.0, 1.0, -0.1]) * fapu["IRISD"] * MM_PER_CANDIDE_UNIT,
        atol=1e-9,
    )
    # Eyeball FAPs (no FAPU in the file) use the documented FAPU.
    a = names.index("FAP23 yaw_l_eyeball")
    assert FAP_EYEBALL_FAPU == "IRISD"
    np.testing.assert_allclose(
        model64.animation_units[a, 67].numpy() * 1024.0, [fapu["IRISD"] * MM_PER_CANDIDE_UNIT, 0.0, 0.0], atol=1e-9
    )
    # AUVs are plain displacements: jaw drop 1 moves vertex 40 by (0, 0.26, 0.05) units (head frame).
    jaw = names.index("AUV11 Jaw drop")
    np.testing.assert_allclose(
        model64.animation_units[jaw, 40].numpy(), np.array([0.0, 0.26, 0.05]) * MM_PER_CANDIDE_UNIT, atol=1e-9
    )


def test_animation_ranges_and_facs(model64, wfm):
    table = read_auv_facs_table()
    ranges = model64.animation_ranges.numpy()
    for a, rec in enumerate(table):
        assert tuple(ranges[a]) == (rec.range_lo, rec.range_hi)
        assert rec.range_lo < rec.range_hi and rec.range_lo <= 0.0 < rec.range_hi
        # FACS links in the table are those named in the file comment, e.g. "(AU26/27)".
        comment = wfm.animation_units[a].name
        numbers = comment[comment.index("(AU") + 3 : comment.rindex(")")].split("/")
        assert rec.facs == tuple(f"AU{n}" for n in numbers), comment
    assert tuple(ranges[11]) == (-1024.0, 1024.0)
    # facs_values = alpha @ M.T: jaw drop 0.7 gives AU26 = AU27 = 0.7 and nothing else.
    alpha = torch.zeros(1, model64.num_animation, dtype=torch.float64)
    alpha[0, 1] = 0.7
    facs = dict(zip(model64.facs_names, model64.facs_values(alpha)[0].tolist()))
    assert facs.pop("AU26") == 0.7 and facs.pop("AU27") == 0.7
    assert all(v == 0.0 for v in facs.values())
    assert model64.facs_matrix[:, 11:].abs().sum() == 0  # FAPs link to no AU
    assert len(model64.facs_names) == 17


# ---------------------------------------------------------------------------------------------- landmarks
def test_landmark_table_complete(model64):
    idx, wts, names, sources = read_landmark_table()
    assert idx.shape == (68, 3) and wts.shape == (68, 3) and len(names) == 68
    np.testing.assert_allclose(wts.sum(axis=1), 1.0, atol=1e-12)
    assert (wts >= 0).all()
    assert sources.count("FaceSwap") == 46 and sources.count("derived") == 22
    pairs = {int(r["ibug68_index"]): int(r["candide3_vertex"])
             for r in csv.DictReader(io.StringIO(DATA.joinpath("ibug68_to_candide3.csv").read_text()))}
    lm = model64.landmarks_3d(model64.mean[None])[0].numpy()
    mean = model64.mean.numpy()
    for k, v in pairs.items():
        assert sources[k] == "FaceSwap"
        np.testing.assert_allclose(lm[k], mean[v], atol=1e-12)
    assert model64.landmark_vertices.dtype == torch.int64


def test_derived_landmarks_sit_on_the_surface_between_neighbours(model64):
    idx, wts, _, sources = read_landmark_table()
    faces = model64.faces.numpy()
    edges = set(edge_use_counts(faces))
    tris = {tuple(sorted(f)) for f in faces.tolist()}
    lm = model64.landmarks_3d(model64.mean[None])[0].numpy()
    for k in np.flatnonzero(np.array(sources) == "derived"):
        support = tuple(sorted({int(v) for v, w in zip(idx[k], wts[k]) if w > 0}))
        assert model64.surface_vertex_mask[list(support)].all()
        assert len(support) == 1 or (len(support) == 2 and support in edges) or support in tris, (k, support)
        if k in (27, 29):
            continue
        # Contour points: between their iBUG neighbours k-1 and k+1 (the inner lip 60-67 is closed).
        a, b = lm[k - 1], lm[60 if k == 67 else k + 1]
        t = np.dot(lm[k] - a, b - a) / np.dot(b - a, b - a)
        dist = np.linalg.norm(lm[k] - (a + t * (b - a)))
        assert 0.2 < t < 0.8 and dist < 0.25 * np.linalg.norm(b - a), (k, t, dist)
    # Nose bridge 27..30 on the midline, evenly spaced top to tip, 27 below the inner brows.
    nose = lm[27:31]
    np.testing.assert_allclose(nose[:, 0], 0.0, atol=1e-9)
    steps = np.diff(nose[:, 1])
    assert (steps > 0).all() and steps.max() / steps.min() < 2.1
    assert lm[27, 1] > max(lm[21, 1], lm[22, 1])


def test_landmarks_mirror_symmetric(model64):
    lm = model64.landmarks_3d(model64.mean[None])[0].numpy()
    np.testing.assert_allclose(lm[IBUG_FLIP], lm * np.array([-1.0, 1.0, 1.0]), atol=1e-9)
    # iBUG 0-7 and the right eye (36-41) are on the subject's right (-x).
    assert (lm[0:8, 0] < 0).all() and (lm[36:42, 0] < 0).all() and (lm[42:48, 0] > 0).all()


def test_data_table_validation():
    bad_weights = "ibug_index,v0,w0,v1,w1,v2,w2,source,meaning\n0,1,0.5,2,0.4,3,0,derived,x\n"
    with pytest.raises(ValueError, match="sum to 1"):
        read_landmark_table(bad_weights)
    bad_order = "ibug_index,v0,w0,v1,w1,v2,w2,source,meaning\n1,1,1,1,0,1,0,derived,x\n"
    with pytest.raises(ValueError, match="ordered"):
        read_landmark_table(bad_order)
    with pytest.raises(ValueError, match="lo < hi"):
        read_auv_facs_table("file_position,auv,name,facs,range_lo,range_hi\n0,0,x,AU10,1,0\n")


def test_landmark_contours_run_in_the_ibug_order():
    """Each iBUG-68 contour runs as the annotation does, seen frontally (head frame = camera frame at the identity:
    +x image right, +y down): the jaw from the subject's right (image left) to the left; each brow, the nostrils and
    each lip from image left to right; each eye from its image-left corner along the upper lid, then back along the
    lower lid; the lower lips are those the jaw drop moves. Mirror symmetry and the sides alone let a swap within a
    contour through (upper and lower lid, a lip's upper and lower points, a brow's ends)."""
    model = load_candide3(dtype=torch.float64)
    lm = model.landmarks_3d(model.deform())[0].numpy()
    x, y = lm[:, 0], lm[:, 1]

    def rising(idx):
        return bool((np.diff(x[idx]) > 0).all())

    assert rising(range(0, 17)) and int(np.argmax(y[:17])) == 8  # jaw: right to left, chin lowest
    assert rising(range(17, 22)) and rising(range(22, 27)) and (y[17:27] < y[36:48].min()).all()  # brows over eyes
    assert rising(range(31, 36))  # nostrils
    for outer, upper, inner, lower in (([36], [37, 38], [39], [40, 41]), ([42], [43, 44], [45], [46, 47])):
        ring = outer + upper + inner + lower
        assert x[outer[0]] == x[ring].min() and x[inner[0]] == x[ring].max()  # image-left corner first
        assert rising(upper) and rising(lower[::-1])  # upper lid left to right, lower lid back
        assert (y[upper] < y[lower[::-1]]).all()  # the upper lid above the lower, point by point
    assert x[48] == x[48:60].min() and x[54] == x[48:60].max() and rising(range(48, 55)) and rising(range(59, 53, -1))
    assert (y[49:54] < y[55:60][::-1]).all()  # outer lip: upper above lower
    assert x[60] == x[60:68].min() and x[64] == x[60:68].max()
    assert rising(range(60, 65)) and rising([60, 67, 66, 65, 64])  # inner lip
    jaw = torch.zeros(1, model.num_animation, dtype=torch.float64)
    jaw[0, model.animation_names.index("AUV11 Jaw drop")] = 1.0
    down = (model.landmarks_3d(model.deform(None, jaw))[0].numpy() - lm)[:, 1]
    assert (down[55:60] > 10).all() and (down[65:68] > 10).all()  # lower lips (outer, inner) follow the jaw
    assert (np.abs(down[49:54]) < 1e-9).all() and (np.abs(down[61:64]) < 1e-9).all()  # upper lips stay
