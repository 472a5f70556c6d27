"""Tests for the renderable subjects (James scan, textured CANDIDE-3), the landmark fit and scene layers."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torchface.geometry.projection import project_points
from torchface.geometry.so3 import euler_to_matrix
from torchface.geometry.transforms import transform_points
from torchface.synth.background import BackgroundSpec, OccluderSpec, background_frames, place_occluder
from torchface.synth.james import LJSON_TO_IBUG, closest_points_on_triangles, load_james
from torchface.synth.subjects import (
    astronaut_photo,
    candide_photo_mapping,
    candide_subject,
    fit_landmarks,
    get_subject,
    james_subject,
)
from torchface.synth.textures import background_texture, occluder_texture, smooth_noise

SHARED = Path(__file__).resolve().parents[3] / "shared" / "assets"


# ----------------------------------------------------------------------------------------- James
def test_ljson_reordering_is_a_permutation():
    assert sorted(LJSON_TO_IBUG) == list(range(68))


def test_james_is_in_the_head_frame():
    subject = james_subject()
    lm = subject.landmarks_3d(subject.mean[None])[0]
    # +x toward the subject's left (image right when frontal), +y down, +z away from the viewer.
    assert lm[36, 0] < lm[39, 0] < lm[42, 0] < lm[45, 0]  # eye corners left to right in the image
    assert lm[0, 0] < lm[8, 0] < lm[16, 0]
    assert lm[8, 1] > lm[57, 1] > lm[33, 1] > lm[27, 1] > lm[19, 1]  # chin below mouth below nose below brows
    inner = lm[17:]
    assert int(inner[:, 2].argmin()) + 17 == 30  # the nose tip is nearest to a frontal camera
    # Frontal: the face is nearly symmetric about x = 0 (outer eye corners, mouth corners).
    assert abs(float(lm[36, 0] + lm[45, 0])) < 8.0 and abs(float(lm[48, 0] + lm[54, 0])) < 8.0
    assert abs(float(lm[36, 2] - lm[45, 2])) < 8.0
    # Millimetres: outer eye corners about 9-10 cm apart.
    assert 80.0 < float(lm[45, 0] - lm[36, 0]) < 110.0


def test_james_landmarks_lie_on_their_triangles_and_normals_weld_seams():
    scan = load_james()
    assert scan.verts.shape == (6680, 3) and scan.faces.shape == (12228, 3)
    torch.testing.assert_close(scan.landmark_bary.sum(-1), torch.ones(68), atol=1e-5, rtol=0)
    assert (scan.landmark_bary >= -1e-6).all()
    subject = james_subject()
    normals = subject.vertex_normals(subject.mean[None])[0]
    torch.testing.assert_close(normals.norm(dim=-1), torch.ones(6680), atol=1e-5, rtol=0)
    dup = scan.weld.bincount()
    assert (dup > 1).any()  # the scan has seams
    seam_id = int(torch.nonzero(dup > 1)[0, 0])
    members = torch.nonzero(scan.weld == seam_id).flatten()
    torch.testing.assert_close(normals[members], normals[members[:1]].expand(len(members), 3))
    # Normals point out of the face: toward a frontal camera (negative z) at the nose tip.
    nose = scan.faces[scan.landmark_faces[30]]
    assert (normals[nose, 2] < -0.5).all()


@pytest.mark.skipif(not (SHARED / "james" / "james.obj").is_file(), reason="../shared/assets not available")
def test_packaged_james_matches_a_fresh_conversion(tmp_path):
    from torchface.synth.james import build_james_data

    figures = build_james_data(SHARED / "james", tmp_path)
    assert figures["snap_max_mm"] < 0.5 and figures["align_rms_mm"] < 12.0
    fresh = np.load(tmp_path / "james.npz")
    scan = load_james()
    np.testing.assert_allclose(fresh["verts"], scan.verts.numpy(), atol=1e-4)
    np.testing.assert_array_equal(fresh["landmark_faces"], scan.landmark_faces.numpy())


def test_james_conversion_without_its_texture_says_so_and_writes_nothing(tmp_path):
    # The texture was read last: a missing james.jpg gave "'NoneType' object has no attribute 'shape'" after
    # james.npz had been written into out_dir.
    from torchface.synth.james import build_james_data

    assets = tmp_path / "assets"
    assets.mkdir()
    (assets / "james.obj").write_text("v 0 0 0\nv 100 0 0\nv 0 100 0\nv 0 0 100\n"
                                      "vt 0 0\nvt 1 0\nvt 0 1\nvt 1 1\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")  # fmt: skip
    points = np.random.default_rng(0).normal(size=(68, 3)) * 30
    (assets / "james.ljson").write_text(json.dumps({"groups": {"LJSON": {"landmarks": {"points": points.tolist()}}}}))
    (assets / "LICENSE.txt").write_text("licence")
    with pytest.raises(FileNotFoundError, match="james.jpg"):
        build_james_data(assets, tmp_path / "out")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_closest_points_known_answers():
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    pts = np.array([[0.2, 0.3, 2.0], [2.0, -1.0, 0.0], [-1.0, 0.5, 0.0], [0.6, 0.6, -1.0]])
    face, bary, dist = closest_points_on_triangles(pts, tri)
    np.testing.assert_allclose(bary[0], [0.5, 0.2, 0.3], atol=1e-12)  # above the interior
    np.testing.assert_allclose(dist[0], 2.0)
    np.testing.assert_allclose(bary[1], [0.0, 1.0, 0.0], atol=1e-12)  # vertex region of (1, 0, 0)
    np.testing.assert_allclose(bary[2], [0.5, 0.0, 0.5], atol=1e-12)  # edge x = 0
    np.testing.assert_allclose(bary[3], [0.0, 0.5, 0.5], atol=1e-12)  # hypotenuse
    np.testing.assert_allclose(dist[3], math.sqrt(0.1**2 * 2 + 1.0))
    # Brute force over a dense sampling of random triangles agrees (never closer than the answer).
    rng = np.random.default_rng(0)
    tris = rng.normal(size=(6, 3, 3))
    q = rng.normal(size=(20, 3)) * 2
    _, _, d = closest_points_on_triangles(q, tris)
    g = np.linspace(0, 1, 60)
    a, b = np.meshgrid(g, g)
    keep = a + b <= 1
    w = np.stack([1 - a[keep] - b[keep], a[keep], b[keep]], -1)
    samples = np.einsum("sk,fkc->fsc", w, tris).reshape(-1, 3)
    brute = np.linalg.norm(q[:, None] - samples[None], axis=-1).min(1)
    assert (d <= brute + 1e-9).all() and (brute - d).max() < 0.05


# ----------------------------------------------------------------------------------------- CANDIDE
def test_candide_subject_is_textured_and_personalised():
    subject = candide_subject("james")
    assert subject.uv.shape == (subject.mean.shape[0], 2)
    assert (subject.uv >= 0).all() and (subject.uv <= 1).all()
    assert subject.shape_coeffs.abs().max() > 0.05  # a person, not the mean face
    assert subject.texture.shape[0] == 3 and subject.texture.shape[1] >= 256
    assert get_subject("candide3") is subject
    with pytest.raises(ValueError, match="subject"):
        get_subject("nobody")
    # Every landmark lies on its recorded triangle.
    for k in range(68):
        used = {int(i) for i, w in zip(subject.landmark_vertices[k], subject.landmark_weights[k]) if w > 0}
        assert used <= set(subject.faces[subject.landmark_faces[k]].tolist())


def test_packaged_astronaut_mapping_matches_a_fresh_fit():
    photo = astronaut_photo()
    assert photo.landmarks_px.shape[0] == photo.landmark_ids.shape[0] >= 15
    uv, shape, rms = candide_photo_mapping(photo)
    packaged = candide_subject("astronaut")
    torch.testing.assert_close(uv.float(), packaged.uv, atol=1e-4, rtol=0)
    torch.testing.assert_close(shape.float(), packaged.shape_coeffs, atol=1e-3, rtol=0)
    assert rms < 5.0  # hand marks on a 160 px crop


def test_fit_landmarks_recovers_a_known_pose_and_shape():
    from torchface.geometry.camera import Intrinsics
    from torchface.model import load_candide3

    model = load_candide3(dtype=torch.float64)
    cam = Intrinsics.default(320, 240)
    sigma = torch.zeros(model.num_shape, dtype=torch.float64)
    sigma[[0, 3, 11]] = torch.tensor([0.4, -0.3, 0.5], dtype=torch.float64)
    R = euler_to_matrix(torch.tensor([[8.0, -5.0, 3.0]], dtype=torch.float64))
    t = torch.tensor([[5.0, -3.0, 450.0]], dtype=torch.float64)
    verts = model.mean + torch.einsum("s,svc->vc", sigma, model.shape_units)
    px = project_points(transform_points(R, t, model.landmarks_3d(verts[None])), cam)[0]
    fit = fit_landmarks(model.mean, model.shape_units, model.landmarks_3d, px, torch.arange(68), cam, shape_prior=1e-8)
    assert fit.rms_px < 1e-2
    torch.testing.assert_close(fit.rotation, R[0], atol=2e-3, rtol=0)
    torch.testing.assert_close(fit.translation, t[0], atol=2.0, rtol=0)


# ----------------------------------------------------------------------------------------- scene layers
def test_backdrop_does_not_depend_on_the_thread_count():
    # The full-size scenarios' backdrop (600x800, upsampled from 300x400): with PyTorch's own thread count the
    # upsampling changed half of its values by one unit in the last place between 1 and 2 threads, and 1089
    # values of the rendered pose_sweep video by one gray level. Needs 2 cores to fail without the fix.
    from torchface.synth.background import _cached_background

    threads = torch.get_num_threads()
    try:
        out = []
        for n in (1, 2):
            torch.set_num_threads(n)
            out.append(_cached_background.__wrapped__(600, 800, 11))
            out.append(smooth_noise(150, 203, 3, seed=1, cell=40.0, octaves=5))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(out[0], out[2]) and torch.equal(out[1], out[3])
    assert torch.get_num_threads() == threads


def test_textures_are_deterministic_and_in_range():
    for fn in (lambda: background_texture(30, 40, seed=3), lambda: occluder_texture(16, 16, seed=1)):
        a, b = fn(), fn()
        torch.testing.assert_close(a, b, rtol=0, atol=0)
        assert a.min() >= 0 and a.max() <= 1 and a.std() > 0.02
    assert not torch.equal(background_texture(30, 40, seed=3), background_texture(30, 40, seed=4))
    n = smooth_noise(20, 30, 2, seed=0)
    assert n.shape == (2, 20, 30) and float(n.min()) == 0.0 and float(n.max()) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        smooth_noise(0, 5, 1, seed=0)


def test_background_pans_by_whole_pixels():
    spec = BackgroundSpec(seed=2, margin=0.5, pan_px_per_frame=(1.0, 0.0))
    frames = background_frames(spec, torch.tensor([0.0, 1.0, 3.0]), 20, 30)
    torch.testing.assert_close(frames[1, :, :, :-1], frames[0, :, :, 1:], atol=1e-5, rtol=0)
    torch.testing.assert_close(frames[2, :, :, :-3], frames[0, :, :, 3:], atol=1e-5, rtol=0)
    static = background_frames(BackgroundSpec(seed=2), torch.tensor([0.0, 7.0]), 20, 30)
    torch.testing.assert_close(static[0], static[1], rtol=0, atol=0)


def test_occluder_covers_the_target_fraction_of_any_face_mask():
    h, w = 60, 80
    rows = torch.arange(h).view(h, 1).float()
    cols = torch.arange(w).view(1, w).float()
    disc = (((rows - 30) / 22) ** 2 + ((cols - 35) / 16) ** 2 <= 1).float()
    square = ((rows - 20).abs() <= 12) & ((cols - 50).abs() <= 15)
    mask = torch.stack([disc, square.float(), torch.zeros(h, w)]).unsqueeze(1)
    spec = OccluderSpec(first_frame=0, last_frame=5, target_fraction=0.3)
    alpha, colour, frac = place_occluder(spec, torch.tensor([0, 2, 4]), mask)
    assert alpha.shape == (3, 1, h, w) and colour.shape == (3, 3, h, w)
    assert abs(float(frac[0]) - 0.3) < 0.02 and abs(float(frac[1]) - 0.3) < 0.02
    assert float(frac[2]) == 0.0 and float(alpha[2].max()) == 0.0  # no face, nothing to occlude
    off = place_occluder(spec, torch.tensor([5, 9]), mask[:2])
    assert float(off[0].max()) == 0.0 and (off[2] == 0).all()
    with pytest.raises(ValueError):
        OccluderSpec(first_frame=3, last_frame=3)
