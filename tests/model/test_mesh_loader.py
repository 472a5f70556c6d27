"""Generic mesh loader and the ICT Face Model loader: same FaceModel API for any linear model."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from torchface.model.mesh_loader import ICT_MM_PER_UNIT, load_ict_face_model, load_mesh_model

ASSETS = Path(__file__).resolve().parents[3] / "shared" / "assets"
ICT_NPZ = ASSETS / "ict_facekit" / "ict_face_model_light.npz"
JAMES_OBJ = ASSETS / "james" / "james.obj"

# A closed tetrahedron wound outward, plus one unused vertex.
TET_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]])
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def outward_flux(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Per-face ``(c_f - centre) . n_f`` about the centroid of the used vertices (positive = outward)."""
    used = torch.unique(faces)
    centre = verts[used].mean(0)
    tri = verts[faces]
    n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    return ((tri.mean(1) - centre) * n).sum(-1)


def test_trimesh_input_with_bases():
    mesh = trimesh.Trimesh(TET_V, TET_F, process=False)
    blend = np.zeros((2, 5, 3))
    blend[0, 3] = [0.0, 0.0, 1.0]
    blend[1, 1] = [1.0, 0.0, 0.0]
    shape = np.ones((1, 5, 3))
    model = load_mesh_model(mesh, blendshapes=blend, blendshape_names=["up", "right"], shape_units=shape,
                            landmark_vertices=[3, 1], scale_to_mm=10.0, dtype=torch.float64)
    sizes = (model.num_vertices, model.num_faces, model.num_shape, model.num_animation, model.num_landmarks)
    assert sizes == (5, 4, 1, 2, 2)
    assert model.surface_vertex_mask.tolist() == [True, True, True, True, False]
    torch.testing.assert_close(model.mean, torch.as_tensor(TET_V * 10.0))
    verts = model.deform(torch.tensor([[0.5]], dtype=torch.float64), torch.tensor([[1.0, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(verts[0, 3], torch.tensor([5.0, 5.0, 25.0], dtype=torch.float64))
    torch.testing.assert_close(model.landmarks_3d(verts)[0, 0], verts[0, 3])
    assert model.animation_ranges.tolist() == [[0.0, 1.0], [0.0, 1.0]]
    assert model.facs_matrix.shape == (0, 2)
    assert (outward_flux(model.mean, model.faces) > 0).all()


def test_path_input_no_bases_and_reflection(tmp_path):
    path = tmp_path / "tet.obj"
    trimesh.Trimesh(TET_V, TET_F, process=False).export(path)
    model = load_mesh_model(path)
    assert model.name == "tet" and model.num_animation == 0 and model.num_shape == 0
    assert model.animation_units.shape == (0, 5, 3) and model.shape_units.shape == (0, 5, 3)
    assert model.deform().shape == (1, 5, 3)
    assert model.num_vertices == 5  # nothing merged or dropped
    # A reflection swaps handedness: triangles are re-wound so they still point out.
    mirror = np.diag([-1.0, 1.0, 1.0])
    reflected = load_mesh_model(path, to_head_frame=mirror, dtype=torch.float64)
    torch.testing.assert_close(reflected.mean, torch.as_tensor(TET_V @ mirror.T))
    assert (outward_flux(reflected.mean, reflected.faces) > 0).all()
    # The rotation of the head-frame conversion keeps winding.
    rot = np.diag([1.0, -1.0, -1.0])
    rotated = load_mesh_model(path, to_head_frame=rot, dtype=torch.float64)
    assert torch.equal(rotated.faces, model.faces)
    assert (outward_flux(rotated.mean, rotated.faces) > 0).all()


def test_any_path_like_is_a_path(tmp_path):
    # Only str and Path were taken as paths: an os.DirEntry (os.scandir), an os.PathLike like them, raised
    # "TypeError: mesh must be a trimesh.Trimesh or a path to a mesh file, got DirEntry".
    trimesh.Trimesh(TET_V, TET_F, process=False).export(tmp_path / "tet.obj")
    (entry,) = os.scandir(tmp_path)
    model = load_mesh_model(entry)
    assert model.name == "tet" and torch.equal(model.mean, load_mesh_model(tmp_path / "tet.obj").mean)


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        ({"blendshapes": np.zeros((2, 4, 3))}, ValueError, r"blendshapes must have shape \(n, 5, 3\)"),
        ({"blendshapes": np.zeros((2, 5, 3)), "blendshape_names": ["a"]}, ValueError, "2 names"),
        ({"landmark_vertices": [7]}, ValueError, "landmark_vertices"),
        ({"to_head_frame": np.eye(3) * 2}, ValueError, "orthogonal"),
        ({"scale_to_mm": 0.0}, ValueError, "positive"),
        ({"dtype": torch.int64}, TypeError, "floating"),
        # One string where a sequence is expected was taken character by character, silently: three units named
        # 'j', 'a', 'w'; a unit linked to the FACS AUs '1', '2', 'A' and 'U'.
        ({"blendshapes": np.zeros((3, 5, 3)), "blendshape_names": "jaw"}, TypeError, r"\('jaw',\), not one string"),
        ({"blendshapes": np.zeros((1, 5, 3)), "blendshape_names": ["smile"], "facs_links": {"smile": "AU12"}},
         TypeError, r"facs_links\['smile'\] must be a tuple"),
    ],
)
def test_bad_arguments_raise(kwargs, error, message):
    with pytest.raises(error, match=message):
        load_mesh_model(trimesh.Trimesh(TET_V, TET_F, process=False), **kwargs)
    with pytest.raises(TypeError, match="trimesh.Trimesh"):
        load_mesh_model(np.zeros((3, 3)))


@pytest.mark.skipif(not JAMES_OBJ.exists(), reason="../shared/assets/james is absent")
def test_obj_keeps_file_vertex_order():
    lines = JAMES_OBJ.read_text().splitlines()
    file_verts = np.array([[float(t) for t in line.split()[1:4]] for line in lines if line.startswith("v ")])
    model = load_mesh_model(JAMES_OBJ, dtype=torch.float64)
    assert model.num_vertices == len(file_verts) == 6393  # not split at UV seams
    torch.testing.assert_close(model.mean, torch.as_tensor(file_verts))
    assert model.num_faces == sum(1 for line in lines if line.startswith("f "))


def test_obj_keeps_unreferenced_vertices_at_its_end(tmp_path):
    """An OBJ with texture coordinates whose last vertices no face uses keeps them (trimesh's order-keeping read
    drops them, and bases sized from the file were refused)."""
    obj = tmp_path / "t.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nv 9 9 9\nvt 0 0\nvt 1 0\nvt 0 1\nvt 1 1\n"
                   "f 1/1 2/2 3/3\nf 2/2 4/4 3/3\n")  # fmt: skip
    model = load_mesh_model(obj, blendshapes=np.ones((1, 5, 3)), dtype=torch.float64)
    assert model.num_vertices == 5 and model.mean[4].tolist() == [9.0, 9.0, 9.0] and model.num_faces == 2


@pytest.mark.skipif(not ICT_NPZ.exists(), reason="../shared/assets/ict_facekit is absent")
def test_ict_face_model():
    model = load_ict_face_model(ICT_NPZ, num_expressions=3, num_identities=2, dtype=torch.float64)
    assert (model.num_vertices, model.num_faces, model.num_animation, model.num_shape, model.num_landmarks) == (
        26719, 52220, 3, 2, 68)
    with np.load(ICT_NPZ) as data:
        neutral = data["neutral"].astype(np.float64)
        delta1 = data["expression_deltas"][1].astype(np.float64)
        ident0 = data["identity_deltas"][0].astype(np.float64)
        names = [str(s) for s in data["expression_names"][:3]]
        lm_ids = data["landmarks68"]
    to_head = np.array([1.0, -1.0, -1.0]) * ICT_MM_PER_UNIT
    assert list(model.animation_names) == names
    torch.testing.assert_close(model.mean, torch.as_tensor(neutral * to_head))
    # One-hot expression = neutral + that delta (converted), identity likewise.
    onehot = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(model.deform(None, onehot)[0], torch.as_tensor((neutral + delta1) * to_head))
    verts = model.deform(torch.tensor([[1.0, 0.0]], dtype=torch.float64), None)
    torch.testing.assert_close(verts[0], torch.as_tensor((neutral + ident0) * to_head))
    lm = model.landmarks_3d(verts)[0]
    torch.testing.assert_close(lm, verts[0, torch.as_tensor(lm_ids)])
    lm = model.landmarks_3d(model.mean[None])[0]
    # Head frame in mm: chin (8) below (+y) the eyes, nose tip (30) nearest the viewer (-z),
    # the subject's right eye (36) at -x, outer eye corners about 9 cm apart.
    assert lm[8, 1] > lm[36, 1] + 50 and lm[30, 2] < lm[36, 2] - 30
    assert lm[36, 0] < 0 < lm[45, 0]
    with pytest.raises(TypeError, match="num_expressions must be an int"):
        load_ict_face_model(ICT_NPZ, num_expressions=3.7)  # type: ignore[arg-type]  # was read as 3
    assert 80.0 < float((lm[45] - lm[36]).norm()) < 100.0
    # ARKit names link to FACS: browDown_L/_R -> AU4, browInnerUp_L -> AU1.
    assert model.facs_names == ("AU1", "AU4")
    torch.testing.assert_close(model.facs_matrix, torch.tensor([[0.0, 0.0, 1.0], [1.0, 1.0, 0.0]], dtype=torch.float64))
    # Faces of the face region point outward on balance (about the head's centre).
    face_region = (model.faces < 9409).all(1)
    assert outward_flux(model.mean, model.faces[face_region]).sum() > 0
    with pytest.raises(ValueError, match="num_expressions"):
        load_ict_face_model(ICT_NPZ, num_expressions=54)
