"""Tests for torchface.rendering.visibility: normals, back-face test, point visibility."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from torchface import _native
from torchface.backend import Backend
from torchface.geometry.camera import Intrinsics
from torchface.rendering import backfacing, face_normals, points_visible, rasterize, vertex_normals
from torchface.rendering.rasterizer import rasterize_coverage

CAM = Intrinsics.default(64, 48)


def sphere(radius: float, centre: tuple[float, float, float], subdivisions: int = 2, dtype=torch.float64):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    verts = torch.tensor(mesh.vertices, dtype=dtype) + torch.tensor(centre, dtype=dtype)
    return verts[None], torch.tensor(mesh.faces, dtype=torch.int64), mesh


def centroids(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    return verts[:, faces].mean(-2)


# ------------------------------------------------------------------------------------------------- normals


def test_face_normals_known_values_and_zero_safe():
    verts = torch.tensor(
        [[[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 5.0], [4.0, 0.0, 0.0]]],
        dtype=torch.float64,
        requires_grad=True,
    )
    faces = torch.tensor([[0, 1, 2], [0, 2, 1], [0, 3, 1], [0, 1, 4]])  # the last one is collinear
    n = face_normals(verts, faces)
    expected = torch.tensor([[[0.0, 0, 1], [0, 0, -1], [0, 1, 0], [0, 0, 0]]], dtype=torch.float64)
    torch.testing.assert_close(n, expected)
    n.sum().backward()
    assert torch.isfinite(verts.grad).all()


def test_face_normals_match_trimesh_and_gradcheck():
    verts, faces, mesh = sphere(1.0, (0.0, 0.0, 0.0), subdivisions=1)
    torch.testing.assert_close(face_normals(verts, faces)[0], torch.tensor(mesh.face_normals))
    g = torch.Generator().manual_seed(0)
    v = torch.randn(2, 5, 3, generator=g, dtype=torch.float64, requires_grad=True)
    f = torch.tensor([[0, 1, 2], [1, 3, 4], [4, 2, 0]])
    assert torch.autograd.gradcheck(lambda x: face_normals(x, f), (v,))
    assert torch.autograd.gradcheck(lambda x: vertex_normals(x, f), (v,))


def test_vertex_normals_sphere_radial_and_unused_zero():
    verts, faces, _ = sphere(10.0, (0.0, 0.0, 0.0), subdivisions=3)
    extra = torch.tensor([[[100.0, 100.0, 100.0]]], dtype=torch.float64)
    normals = vertex_normals(torch.cat([verts, extra], 1), faces)
    radial = verts[0] / verts[0].norm(dim=-1, keepdim=True)
    cos = (normals[0, :-1] * radial).sum(-1)
    assert cos.min() > 0.999
    torch.testing.assert_close(normals[0, :-1].norm(dim=-1), torch.ones(verts.shape[1], dtype=torch.float64))
    assert (normals[0, -1] == 0).all()
    # Area weighting: a big and a small triangle sharing vertex 0 at right angles.
    v = torch.tensor([[[0.0, 0, 0], [3, 0, 0], [0, 3, 0], [0, 0, 1], [0, 1, 0]]])
    n0 = vertex_normals(v, torch.tensor([[0, 1, 2], [0, 3, 4]]))[0, 0]
    expected = torch.tensor([-1.0, 0.0, 9.0]) / math.sqrt(82.0)
    torch.testing.assert_close(n0, expected)


def test_normals_batched_and_exceptions():
    verts, faces, _ = sphere(10.0, (0.0, 0.0, 50.0), subdivisions=1)
    batch = torch.cat([verts, verts * 2.0, verts.flip(-1)])
    for fn in (face_normals, vertex_normals, backfacing):
        out = fn(batch, faces)
        for b in range(3):
            assert torch.equal(out[b], fn(batch[b : b + 1], faces)[0])
        with pytest.raises(ValueError):
            fn(verts[0], faces)
        with pytest.raises(TypeError):
            fn(verts, faces.double())


def test_posed_normals_and_backfacing_are_the_separate_computations():
    """vertex_normals_and_backfacing of a rotated, translated mesh: the rotated head-frame vertex normals and
    backfacing of the posed mesh; float64 gradcheck (the normalised face's gradients go through it)."""
    from torchface.geometry.mesh import vertex_normals_and_backfacing
    from torchface.geometry.so3 import axis_angle_to_matrix

    verts, faces, _ = sphere(40.0, (0.0, 0.0, 0.0), subdivisions=2)
    verts = verts * torch.tensor([1.0, 1.3, 0.8], dtype=verts.dtype)  # an ellipsoid: normals not radial
    R = axis_angle_to_matrix(torch.tensor([[0.3, -0.5, 0.2], [0.0, 1.2, 0.0]], dtype=verts.dtype))
    t = torch.tensor([[10.0, -5.0, 300.0], [0.0, 0.0, 250.0]], dtype=verts.dtype)
    posed = verts @ R.mT + t[:, None]
    normals, back = vertex_normals_and_backfacing(posed, faces)
    torch.testing.assert_close(normals, vertex_normals(verts.expand(2, -1, -1), faces) @ R.mT, atol=1e-12, rtol=0)
    assert torch.equal(back, backfacing(posed, faces))
    assert 0 < int(back.sum()) < back.numel()
    small, small_faces, _ = sphere(30.0, (0.0, 0.0, 200.0), subdivisions=0)
    x = small.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: vertex_normals_and_backfacing(v, small_faces)[0], (x,))


# ------------------------------------------------------------------------------------------------- backfacing


def test_backfacing_closed_mesh():
    centre, radius = (5.0, -3.0, 200.0), 50.0
    verts, faces, mesh = sphere(radius, centre, subdivisions=3)
    back = backfacing(verts, faces)[0]
    # Exactly the faces whose outward normal (trimesh's own) points away from the camera at the origin.
    v0 = torch.tensor(mesh.vertices[mesh.faces[:, 0]]) + torch.tensor(centre)
    away = (torch.tensor(mesh.face_normals) * v0).sum(-1) >= 0
    assert torch.equal(back, away)
    # From distance d a sphere shows the cap of area fraction (1 - r / d) / 2: about 0.375 here.
    front_fraction = 1.0 - back.double().mean().item()
    d = math.sqrt(sum(c * c for c in centre))
    assert abs(front_fraction - 0.5 * (1.0 - radius / d)) < 0.02
    # Reversing the winding swaps front and back.
    assert torch.equal(backfacing(verts, faces.flip(-1))[0], ~back)


# ---------------------------------------------------------------------------------------------- points_visible


def test_points_visible_sphere():
    verts, faces, _ = sphere(40.0, (0.0, 0.0, 200.0), subdivisions=3)
    frag = rasterize(verts, faces, CAM)
    pts = centroids(verts, faces)
    face_ids = torch.arange(faces.shape[0])
    visible = points_visible(pts, face_ids, frag, CAM)
    back = backfacing(verts, faces)
    assert not (visible & back).any()
    # Nearest and farthest face to the camera.
    nearest, farthest = pts[0, :, 2].argmin(), pts[0, :, 2].argmax()
    assert visible[0, nearest] and not visible[0, farthest]
    # Faces turned toward the camera are all visible; near the silhouette, the nearest pixel centre
    # may show background or a steep neighbour more than the tolerance nearer, so some drop out.
    ray = pts[0] / pts[0].norm(dim=-1, keepdim=True)
    cos = -(face_normals(verts, faces)[0] * ray).sum(-1)
    assert visible[0, cos > 0.5].all()
    assert visible[~back].double().mean() > 0.7
    # The same answer with per-sample face ids and in float32.
    assert torch.equal(points_visible(pts, face_ids[None], frag, CAM), visible)
    frag32 = rasterize(verts.float(), faces, CAM)
    agree = points_visible(pts.float(), face_ids, frag32, CAM) == visible
    assert agree.double().mean() > 0.98


def test_points_visible_occlusion_and_image_bounds():
    # Sphere B sits behind sphere A and half of it peeks out on the right; sphere C is partly outside the image (right).
    va, fa, _ = sphere(30.0, (0.0, 0.0, 150.0))
    vb, fb, _ = sphere(60.0, (60.0, 0.0, 300.0))
    vc, fc, _ = sphere(30.0, (148.0, 0.0, 300.0))
    n = va.shape[1]
    verts = torch.cat([va, vb, vc], 1)
    faces = torch.cat([fa, fb + n, fc + 2 * n])
    frag = rasterize(verts, faces, CAM)
    pts = centroids(verts, faces)
    face_ids = torch.arange(faces.shape[0])
    # A pixel here is ~4.7 mm wide at B and C: allow for the depth change across half a pixel.
    visible = points_visible(pts, face_ids, frag, CAM, depth_tolerance=0.03)
    front = ~backfacing(verts, faces)[0]
    nf = fa.shape[0]
    in_a, in_b, in_c = face_ids < nf, (face_ids >= nf) & (face_ids < 2 * nf), face_ids >= 2 * nf
    ray = pts[0] / pts[0].norm(dim=-1, keepdim=True)
    toward = -(face_normals(verts, faces)[0] * ray).sum(-1) > 0.5
    u = pts[0, :, 0] / pts[0, :, 2] * CAM.fx + CAM.cx
    v = pts[0, :, 1] / pts[0, :, 2] * CAM.fy + CAM.cy
    r_px = torch.hypot(u - CAM.cx, v - CAM.cy)
    a_radius_px = CAM.fx * 30.0 / math.sqrt(150.0**2 - 30.0**2)
    # B's faces turned toward the camera behind A's centre are hidden (by the z-buffer, not culling).
    b_hidden = in_b & toward & (r_px < a_radius_px - 2)
    assert b_hidden.sum() > 3 and not visible[0, b_hidden].any()
    # Those whose ray misses A are visible.
    assert (in_b & toward & (r_px > a_radius_px + 2)).sum() > 10
    assert visible[0, in_b & toward & (r_px > a_radius_px + 2)].all()
    assert not visible[0, in_b & (r_px < a_radius_px - 2)].any()
    # C straddles the right border: front faces projecting outside are never visible, inside mostly are.
    outside = (u > CAM.width - 0.5) | (v > CAM.height - 0.5) | (u < -0.5) | (v < -0.5)
    assert (in_c & front & outside).any() and not visible[0, in_c & outside].any()
    assert (in_c & toward & ~outside).sum() > 5
    assert visible[0, in_c & toward & ~outside & (u < CAM.width - 1)].all()
    # A point behind the camera and one off-screen with a (wrong) face id are not visible either.
    extra = torch.tensor([[[0.0, 0.0, -150.0], [1e4, 0.0, 150.0]]], dtype=torch.float64)
    assert not points_visible(extra, torch.tensor([0, 0]), frag, CAM).any()
    # A point on A's nearest face, pushed 10% deeper, is hidden; within the tolerance it is visible.
    a_nearest = torch.where(in_a, pts[0, :, 2], torch.inf).argmin()
    p = pts[:, a_nearest : a_nearest + 1]
    other = torch.tensor([nf + 1])  # claims to lie on another face, so only the depth test can pass it
    assert not points_visible(p * 1.1, other, frag, CAM).any()
    assert points_visible(p * 1.005, other, frag, CAM).all()
    assert not points_visible(p * 1.005, other, frag, CAM, depth_tolerance=1e-3).any()


@pytest.mark.skipif(_native.library() is None, reason="native kernels unavailable")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_points_visible_native_equals_the_torch_code(dtype):
    """Against a coverage, the native test (visible.h) gives the torch code's answer point for point: a scene with
    occlusion and a sphere cut by the image border, points on their faces, pushed off them (so that the depth test
    decides), behind the camera, off-screen, NaN and infinite, per-sample and shared face ids, several tolerances,
    a batch of two; and the fragments' answer. A coverage that is a view into a larger one (Coverage.part) takes
    the torch code."""
    va, fa, _ = sphere(30.0, (0.0, 0.0, 150.0), dtype=dtype)
    vb, fb, _ = sphere(60.0, (60.0, 0.0, 300.0), dtype=dtype)
    vc, fc, _ = sphere(30.0, (148.0, 0.0, 300.0), dtype=dtype)
    n = va.shape[1]
    verts = torch.cat([va, vb, vc], 1)
    verts = torch.cat([verts, verts + torch.tensor([8.0, -5.0, 20.0], dtype=dtype)])  # two samples
    faces = torch.cat([fa, fb + n, fc + 2 * n])
    coverage, frags = rasterize_coverage(verts, faces, CAM), rasterize(verts, faces, CAM)
    gen = torch.Generator().manual_seed(3)
    pts = centroids(verts, faces)
    pts = torch.cat([pts, pts * 1.004, pts + torch.randn(pts.shape, generator=gen, dtype=dtype)], 1)
    pts[:, :3] = torch.tensor([[0.0, 0.0, -150.0], [1e4, 0.0, 150.0], [0.0, 0.0, 0.5]], dtype=dtype)
    pts[:, 3, 0], pts[:, 4, 2] = float("nan"), float("inf")
    ids = torch.arange(faces.shape[0]).repeat(3)
    per_sample = torch.stack([ids, ids.roll(1)])
    for face_ids in (ids, per_sample):
        for tol in (0.0, 0.01, 0.03):
            got = points_visible(pts, face_ids, coverage, CAM, depth_tolerance=tol, backend=Backend.NATIVE)
            want = points_visible(pts, face_ids, coverage, CAM, depth_tolerance=tol, backend=Backend.TORCH)
            assert torch.equal(got, want), (face_ids.dim(), tol)
            assert torch.equal(got, points_visible(pts, face_ids, frags, CAM, depth_tolerance=tol))
            assert 0 < int(got.sum()) < got.numel()
    part = coverage.part(slice(1, 2), 40, 50)
    cam = Intrinsics(50, 40, CAM.fx, CAM.fy, CAM.cx, CAM.cy)
    got = points_visible(pts[1:], ids, part, cam, backend=Backend.AUTO)
    assert torch.equal(got, points_visible(pts[1:], ids, part, cam, backend=Backend.TORCH))


def test_points_visible_exceptions():
    verts, faces, _ = sphere(30.0, (0.0, 0.0, 150.0), subdivisions=1)
    frag = rasterize(verts, faces, CAM)
    pts = centroids(verts, faces)
    ids = torch.arange(faces.shape[0])
    with pytest.raises(ValueError):
        points_visible(pts[0], ids, frag, CAM)
    with pytest.raises(ValueError):
        points_visible(pts, ids[:-1], frag, CAM)
    with pytest.raises(TypeError):
        points_visible(pts, ids.double(), frag, CAM)
    with pytest.raises(ValueError):
        points_visible(pts, ids, frag, Intrinsics.default(32, 24))
    for tolerance in (-0.1, float("inf"), float("nan")):  # (inf passed ">= 0")
        with pytest.raises(ValueError, match=r"^depth_tolerance must be a finite number >= 0 \(a fraction of"):
            points_visible(pts, ids, frag, CAM, depth_tolerance=tolerance)


def test_points_visible_option_types_and_near():
    """depth_tolerance="0.1" was "'<=' not supported between instances"; near was not looked at (a string was
    "'>' not supported between instances of 'Tensor' and 'str'", a NaN near made every point invisible without a
    word, a negative one let points behind the camera through the near test)."""
    verts, faces, _ = sphere(30.0, (0.0, 0.0, 150.0), subdivisions=1)
    frag = rasterize(verts, faces, CAM)
    pts = centroids(verts, faces)
    ids = torch.arange(faces.shape[0])
    with pytest.raises(TypeError, match=r"^depth_tolerance must be a real number, got str"):
        points_visible(pts, ids, frag, CAM, depth_tolerance="0.1")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"^near must be a real number, got str"):
        points_visible(pts, ids, frag, CAM, near="1")  # type: ignore[arg-type]
    for near in (float("nan"), -1.0, 0.0, float("inf")):
        with pytest.raises(ValueError, match=r"^near must be a finite number > 0 \(millimetres\), got"):
            points_visible(pts, ids, frag, CAM, near=near)
    want = points_visible(pts, ids, frag, CAM)
    assert want.any() and torch.equal(points_visible(pts, ids, frag, CAM, near=1, depth_tolerance=0), want)
