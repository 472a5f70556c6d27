"""Tests for torchface.template.points: template points built from a render with a known pose lie on their own
triangles at pixel centres, carry the frame's intensities, respect the gradient threshold, and the identity warp
reproduces the template (paper Eq. 3-9, Section 4)."""

from __future__ import annotations

import pytest
import torch

from torchface.appearance import illumination_basis, image_with_gradients, to_gray
from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import project_points
from torchface.geometry.so3 import euler_to_matrix, matrix_to_axis_angle
from torchface.model.candide import load_candide3
from torchface.rendering.rasterizer import rasterize
from torchface.synth.background import BackgroundSpec
from torchface.synth.scenarios import default_light
from torchface.synth.sequence import SequenceSpec, render_sequence
from torchface.template import (
    Template,
    build_template,
    gather_face_attributes,
    point_normals,
    select_template_pixels,
)
from torchface.template.points import (
    _selection_keys,
    interpolated_normals,
    posed_mesh,
    rasterize_windows,
    select_pixels_posed,
    strided_window,
    template_at,
    top_scores,
)
from torchface import _native
from torchface.backend import Backend
from torchface.tracker.step import level_intrinsics
from torchface.rendering.visibility import vertex_normals
from torchface.tracker import ParamLayout, frame_residuals

W, H = 160, 120
D = torch.float64


@pytest.fixture(scope="module")
def scene():
    """Two rendered frames (different poses and expressions) with their exact parameters, in the model's dtype."""
    model = load_candide3()
    ypr = torch.tensor([[15.0, -5.0, 3.0], [-10.0, 8.0, -4.0]], dtype=D)
    anim = torch.zeros(2, model.num_animation, dtype=D)
    anim[0, model.animation_names.index("AUV11 Jaw drop")] = 0.5
    anim[1, model.animation_names.index("AUV2 Lip stretcher")] = 0.6
    spec = SequenceSpec(
        name="tpl",
        subject="candide3",
        intrinsics=Intrinsics.default(W, H),
        rotation=euler_to_matrix(ypr),
        translation=torch.tensor([[5.0, -3.0, 430.0], [-8.0, 4.0, 470.0]], dtype=D),
        anim=anim,
        light=default_light(2),
        background=BackgroundSpec(seed=5),
    )
    frames, gt = render_sequence(spec)
    f32 = torch.float32
    return {
        "model": model,
        "gray": to_gray(frames),
        "R": gt.rotation.to(f32),
        "t": gt.translation.to(f32),
        "anim": gt.au.to(f32),
        "shape": gt.shape_coeffs.to(f32).expand(2, -1).contiguous(),
        "cam": gt.intrinsics,
    }


def build(scene, max_points=H * W, gradient_threshold=0.0, **kw) -> Template:
    s = scene
    return build_template(
        s["model"], s["shape"], s["anim"], s["R"], s["t"], s["gray"], s["cam"],
        max_points=max_points, gradient_threshold=gradient_threshold, **kw,
    )


def pixels_of(scene, tpl: Template) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Projection ``(B, N, 2)`` of the template points with the true pose and expression, and its rounding."""
    s = scene
    X = tpl.points + torch.matmul(tpl.basis, s["anim"][:, None, :, None]).squeeze(-1)
    uv = project_points(X @ s["R"].mT + s["t"][:, None], s["cam"])
    return uv, uv.round().long(), X


def test_cardinality(scene):
    tpl = build(scene, max_points=500)
    A = scene["model"].num_animation
    assert tpl.face_index.shape == (2, 500) and tpl.bary.shape == (2, 500, 3) and tpl.points.shape == (2, 500, 3)
    assert tpl.basis.shape == (2, 500, 3, A) and tpl.normals.shape == (2, 500, 3)
    assert tpl.intensity.shape == (2, 500) and tpl.valid.shape == (2, 500) and tpl.valid.dtype == torch.bool
    assert tpl.num_points.tolist() == [500, 500], "a face of ~50x60 px has more than 500 usable pixels"
    one = tpl.select(torch.tensor([1]))
    assert one.points.shape == (1, 500, 3)
    torch.testing.assert_close(one.points[0], tpl.points[1])


def test_points_project_to_pixel_centres_on_their_own_triangle(scene):
    """With the true pose, each template point lands on a pixel centre whose rasterized triangle is its own, with
    the same barycentric coordinates."""
    tpl = build(scene)
    uv, pix, _ = pixels_of(scene, tpl)
    v = tpl.valid
    assert int(v.sum()) > 1000
    assert float((uv - pix)[v].abs().max()) < 1e-3
    s = scene
    verts = s["model"].deform(s["shape"], s["anim"]) @ s["R"].mT + s["t"][:, None]
    frags = rasterize(verts, s["model"].faces, s["cam"], cull_backfaces=True)
    b = torch.arange(2)[:, None].expand_as(tpl.face_index)
    seen = frags.pix_to_face[b, pix[..., 1], pix[..., 0]]
    assert bool((seen[v] == tpl.face_index[v]).all())
    torch.testing.assert_close(frags.bary[b, pix[..., 1], pix[..., 0]][v], tpl.bary[v], rtol=0, atol=1e-4)
    # Against the renderer's raster (no culling): CANDIDE-3 has a few back-facing triangles nearest the camera
    # (e.g. faces 172 and 180 on the frontal mean face, 4 pixels per frame here), where the frame shows that
    # back face; all other points agree.
    shown = rasterize(verts, s["model"].faces, s["cam"]).pix_to_face[b, pix[..., 1], pix[..., 0]]
    mismatch = (shown != tpl.face_index) & v
    assert int(mismatch.sum()) <= 0.005 * int(v.sum()), int(mismatch.sum())
    # points on distinct pixels
    for k in range(2):
        keys = pix[k][v[k]][:, 1] * W + pix[k][v[k]][:, 0]
        assert keys.unique().numel() == keys.numel()


def test_intensities_are_the_frame_pixels(scene):
    tpl = build(scene)
    _, pix, _ = pixels_of(scene, tpl)
    b = torch.arange(2)[:, None].expand_as(tpl.face_index)
    frame = scene["gray"][b, 0, pix[..., 1], pix[..., 0]]
    torch.testing.assert_close(tpl.intensity[tpl.valid], frame[tpl.valid], rtol=0, atol=0)


def test_points_basis_normals_interpolate_the_model(scene):
    """Points, expression basis and normals are the barycentric interpolations of the triangle's vertices."""
    tpl = build(scene, max_points=300)
    model, s = scene["model"], scene
    neutral = model.deform(s["shape"], None)
    corners = model.faces[tpl.face_index]  # (B, N, 3)
    b = torch.arange(2)[:, None, None]
    expected = (neutral[b, corners] * tpl.bary[..., None]).sum(2)
    torch.testing.assert_close(tpl.points, expected)
    au = model.animation_units.permute(1, 2, 0)  # (V, 3, A)
    torch.testing.assert_close(tpl.basis, (au[corners] * tpl.bary[..., None, None]).sum(2))
    torch.testing.assert_close(tpl.normals.norm(dim=-1)[tpl.valid], torch.ones(int(tpl.valid.sum())))
    # front-facing at the frame's pose (expression aside, the neutral normals still face the camera)
    _, _, X = pixels_of(scene, tpl)
    cam_pts = X @ s["R"].mT + s["t"][:, None]
    facing = ((tpl.normals @ s["R"].mT) * cam_pts).sum(-1)
    assert bool((facing[tpl.valid] < 0).all())


def test_compact_selection_and_normals_are_the_templates(scene):
    """select_template_pixels gives exactly build_template's stored fields (what a mosaic entry keeps), and
    point_normals its normals: a new mosaic entry is made from these alone."""
    s = scene
    tpl = build(scene, max_points=400, gradient_threshold=0.01, expression_quota=20)
    px = select_template_pixels(
        s["model"], s["shape"], s["anim"], s["R"], s["t"], s["gray"], s["cam"], max_points=400,
        gradient_threshold=0.01, expression_quota=20,
    )
    for name in ("face_index", "bary", "intensity", "valid"):
        assert torch.equal(getattr(px, name), getattr(tpl, name)), name
    assert bool(tpl.valid.all())  # 400 points found on each face
    # the same normals (to rounding: build_template's may come from the native interpolation)
    torch.testing.assert_close(point_normals(s["model"], s["shape"], px.face_index, px.bary), tpl.normals,
                               rtol=0, atol=1e-6)


def test_template_at_with_the_persons_neutral_mesh_given(scene):
    """template_at with the neutral vertices and vertex normals handed in (as a mosaic entry's levels share them)
    is template_at computing them."""
    s = scene
    px = select_template_pixels(s["model"], s["shape"], s["anim"], s["R"], s["t"], s["gray"], s["cam"],
                                max_points=300, gradient_threshold=0.01)  # fmt: skip
    args = (s["model"], s["shape"], px.face_index, px.bary, px.intensity, px.valid)
    verts = s["model"].deform(s["shape"], None)
    given = template_at(*args, neutral=(verts, vertex_normals(verts, s["model"].faces)))
    alone = template_at(*args)
    for name in ("points", "basis", "normals"):
        assert torch.equal(getattr(given, name), getattr(alone, name)), name
    other = template_at(*args, neutral=(verts * 1.1, vertex_normals(verts, s["model"].faces)))
    assert not torch.equal(other.points, alone.points)  # the handed-in vertices are the ones used
    with pytest.raises(ValueError, match="neutral must be two"):
        template_at(*args, neutral=(verts[:1], vertex_normals(verts, s["model"].faces)))


def test_selected_barycentrics_carry_the_poses_gradient_by_default(scene):
    """A pose that requires grad gives the chosen pixels' barycentric coordinates the torch code's gradient with
    the default backend (the native pick, taken where the detached coefficients allowed it, dropped it: no grad;
    Backend.NATIVE refuses such a pose, as its candidate tests always did)."""
    if _native.library() is None:
        pytest.skip(f"native kernels unavailable: {_native.unavailable_reason()}")
    s = scene
    grads = []
    for b in (Backend.TORCH, Backend.AUTO):
        t = s["t"].clone().requires_grad_(True)
        px = select_template_pixels(s["model"], s["shape"], s["anim"], s["R"], t, s["gray"], s["cam"],
                                    max_points=300, gradient_threshold=0.01, min_facing_cos=-1.0, backend=b)
        assert px.bary.requires_grad and bool(px.valid.any())
        bary = px.bary[px.valid]
        grads.append(torch.autograd.grad((bary * torch.arange(3.0)).sum() + bary.pow(2).sum(), t)[0])
    assert bool(grads[0].abs().sum() > 0)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-5, atol=1e-6)


def test_posed_selection_and_interpolated_normals_are_the_same(scene):
    """What a pyramid's levels share (the posed mesh, the person's vertex normals) computed once gives exactly
    select_template_pixels and point_normals."""
    s = scene
    posed = posed_mesh(s["model"], s["shape"], s["anim"], s["R"], s["t"])
    px = select_pixels_posed(s["model"], posed, s["gray"], s["cam"], None, max_points=400, gradient_threshold=0.01,
                             expression_quota=20)  # fmt: skip
    ref = select_template_pixels(
        s["model"], s["shape"], s["anim"], s["R"], s["t"], s["gray"], s["cam"], max_points=400,
        gradient_threshold=0.01, expression_quota=20,
    )
    for name in ("face_index", "bary", "intensity", "valid"):
        assert torch.equal(getattr(px, name), getattr(ref, name)), name
    normals = vertex_normals(s["model"].deform(s["shape"], None), s["model"].faces)
    assert torch.equal(interpolated_normals(normals, s["model"].faces, px.face_index, px.bary),
                       point_normals(s["model"], s["shape"], px.face_index, px.bary))  # fmt: skip


def test_selection_seed_draws_another_subset_of_the_same_candidates(scene):
    """seed 0 is the default draw; another seed picks another max_points of the same candidate pixels (every
    pick of either draw is a candidate of the full selection, with the same triangle, coordinates and
    intensity); a bad seed is refused."""
    s = scene
    args = (s["model"], s["shape"], s["anim"], s["R"], s["t"], s["gray"], s["cam"])
    kw = dict(gradient_threshold=0.01)
    default = select_template_pixels(*args, max_points=300, **kw)
    zero = select_template_pixels(*args, max_points=300, seed=0, **kw)
    other = select_template_pixels(*args, max_points=300, seed=3, **kw)
    every = select_template_pixels(*args, max_points=H * W, **kw)
    for name in ("face_index", "bary", "intensity", "valid"):
        assert torch.equal(getattr(zero, name), getattr(default, name)), name
    assert int(other.valid.sum()) == int(default.valid.sum()) == 600
    for b in range(2):
        a_keys = {(f, round(float(x), 4), round(float(y), 4)) for f, (x, y, _) in
                  zip(default.face_index[b].tolist(), default.bary[b])}  # fmt: skip
        o_keys = {(f, round(float(x), 4), round(float(y), 4)) for f, (x, y, _) in
                  zip(other.face_index[b].tolist(), other.bary[b])}  # fmt: skip
        all_keys = {(f, round(float(x), 4), round(float(y), 4)) for f, (x, y, _), v in
                    zip(every.face_index[b].tolist(), every.bary[b], every.valid[b]) if v}  # fmt: skip
        assert a_keys <= all_keys and o_keys <= all_keys
        assert len(a_keys & o_keys) < 0.5 * len(a_keys)  # mostly other points
    with pytest.raises(ValueError, match="seed"):
        select_template_pixels(*args, max_points=300, seed=-1, **kw)


def test_gather_face_attributes_matches_the_definition(scene):
    """Shared (non-batched) and per-sample attributes: sum_i bary_i * attributes[faces[face, i]]."""
    s = scene
    faces = s["model"].faces
    gen = torch.Generator().manual_seed(0)
    face_index = torch.randint(0, faces.shape[0], (2, 7), generator=gen)
    bary = torch.rand(2, 7, 3, generator=gen)
    shared = torch.randn(s["model"].num_vertices, 3, 4, generator=gen).permute(0, 2, 1)  # not contiguous
    per_sample = torch.randn(2, s["model"].num_vertices, 3, generator=gen)
    for attributes, batched in ((shared, False), (per_sample, True)):
        got = gather_face_attributes(attributes, faces, face_index, bary, batched=batched)
        for b in range(2):
            for n in range(7):
                rows = attributes[b] if batched else attributes
                want = sum(bary[b, n, i] * rows[faces[face_index[b, n], i]] for i in range(3))
                torch.testing.assert_close(got[b, n], want, rtol=1e-6, atol=1e-6)


def test_points_stay_off_the_silhouette(scene):
    """After the one-pixel erosion every template pixel has face pixels all around it."""
    tpl = build(scene)
    _, pix, _ = pixels_of(scene, tpl)
    s = scene
    verts = s["model"].deform(s["shape"], s["anim"]) @ s["R"].mT + s["t"][:, None]
    fg = rasterize(verts, s["model"].faces, s["cam"]).foreground
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            b = torch.arange(2)[:, None].expand_as(tpl.face_index)
            ok = fg[b, (pix[..., 1] + dy).clamp(0, H - 1), (pix[..., 0] + dx).clamp(0, W - 1)]
            assert bool(ok[tpl.valid].all())


def test_gradient_threshold_keeps_exactly_the_informative_points(scene):
    """The threshold removes points and keeps exactly those whose gradient magnitude reaches it (Section 4)."""
    thr = 0.03
    all_pts = build(scene, gradient_threshold=0.0)
    strong = build(scene, gradient_threshold=thr)
    grads = image_with_gradients(scene["gray"])[:, 1:]
    gmag = grads.pow(2).sum(1).sqrt()  # (B, H, W)
    for k in range(2):
        _, pix_all, _ = pixels_of(scene, all_pts)
        _, pix_strong, _ = pixels_of(scene, strong)
        keys_all = pix_all[k][all_pts.valid[k]]
        keys_strong = pix_strong[k][strong.valid[k]]
        g_all = gmag[k, keys_all[:, 1], keys_all[:, 0]]
        expected = set((keys_all[g_all >= thr] @ torch.tensor([1, W])).tolist())
        got = set((keys_strong @ torch.tensor([1, W])).tolist())
        assert got == expected
        assert 0 < len(got) < 0.9 * keys_all.shape[0]
        assert bool((gmag[k, keys_strong[:, 1], keys_strong[:, 0]] >= thr).all())


def test_facing_threshold_keeps_exactly_the_points_that_face_their_ray(scene):
    """``min_facing_cos`` keeps exactly the pixels whose interpolated normal (at the frame's expression) makes a
    cosine of at least that with the reversed viewing ray: a slow per-pixel reference against the build, which
    interpolates normals only at the candidate pixels."""
    from torchface.rendering.visibility import vertex_normals

    loose, strict = build(scene, min_facing_cos=0.0), build(scene, min_facing_cos=0.6)
    s, model = scene, scene["model"]
    normals = vertex_normals(model.deform(s["shape"], s["anim"]), model.faces) @ s["R"].mT  # (B, V, 3) camera frame
    for k in range(2):
        v = loose.valid[k]
        n = gather_face_attributes(normals, model.faces, loose.face_index, loose.bary, batched=True)[k][v]
        _, pix, _ = pixels_of(scene, loose)
        px = pix[k][v].to(n.dtype)
        cam = s["cam"]
        ray = torch.stack([(px[:, 0] - cam.cx) / cam.fx, (px[:, 1] - cam.cy) / cam.fy, torch.ones_like(px[:, 0])], -1)
        cos = -(torch.nn.functional.normalize(n, dim=-1) * torch.nn.functional.normalize(ray, dim=-1)).sum(-1)
        expected = set((pix[k][v][cos >= 0.6] @ torch.tensor([1, W])).tolist())
        _, pix_s, _ = pixels_of(scene, strict)
        got = set((pix_s[k][strict.valid[k]] @ torch.tensor([1, W])).tolist())
        assert got == expected
        assert 0 < len(got) < 0.95 * int(v.sum())  # the threshold removed some points, not all


def test_facing_bound_of_a_triangle_holds_at_its_points(scene):
    """The bound select_pixels_posed passes whole triangles on: at every point of a triangle, the cosine of the
    interpolated normal with the reversed ray is at least the smallest cosine of a corner normal with a corner's
    direction (where that is >= 0). Both kinds of triangle occur here at min_facing_cos = 0.6."""
    from torchface.rendering.visibility import vertex_normals

    s, model = scene, scene["model"]
    tpl = build(scene, min_facing_cos=0.0)
    posed = posed_mesh(model, s["shape"], s["anim"], s["R"], s["t"])
    normals = vertex_normals(model.deform(s["shape"], s["anim"]), model.faces) @ s["R"].mT  # (B, V, 3)
    corner_rays = torch.nn.functional.normalize(posed.verts_cam[:, model.faces], dim=-1)  # (B, F, 3, 3)
    bound = -(normals[:, model.faces] @ corner_rays.mT).flatten(-2).amax(-1)  # (B, F)
    n = gather_face_attributes(normals, model.faces, tpl.face_index, tpl.bary, batched=True)
    _, _, X = pixels_of(scene, tpl)
    X = X @ s["R"].mT + s["t"][:, None]  # camera frame
    cos = -(torch.nn.functional.normalize(n, dim=-1) * torch.nn.functional.normalize(X, dim=-1)).sum(-1)
    at = torch.gather(bound, 1, tpl.face_index)
    use = tpl.valid & (at >= 0)
    assert bool((cos[use] >= at[use] - 1e-5).all())
    assert int((use & (at >= 0.61)).sum()) > 100 and int((tpl.valid & (at < 0.61)).sum()) > 100


@pytest.mark.parametrize("min_facing_cos", [-0.3, 0.15, 0.6])
def test_facing_tested_per_point_only_near_the_threshold_is_the_same_selection(scene, monkeypatch, min_facing_cos):
    """select_pixels_posed tests the facing point by point only on triangles whose bound is within
    _FACING_MARGIN of the threshold: the same selection, bit for bit, as testing every candidate (the margin
    made too large to skip any: the slow reference). A negative threshold is bounded by 0 (below it the bound
    does not hold)."""
    import torchface.template.points as P

    s = scene
    posed = posed_mesh(s["model"], s["shape"], s["anim"], s["R"], s["t"])
    for n in (300, H * W):
        kw = dict(max_points=n, gradient_threshold=0.01, min_facing_cos=min_facing_cos)
        fast = select_pixels_posed(s["model"], posed, s["gray"], s["cam"], None, **kw)
        monkeypatch.setattr(P, "_FACING_MARGIN", 10.0)
        slow = select_pixels_posed(s["model"], posed, s["gray"], s["cam"], None, **kw)
        monkeypatch.undo()
        for f in ("face_index", "bary", "intensity", "valid"):
            assert torch.equal(getattr(fast, f), getattr(slow, f)), (n, f)


def test_subsampling_is_a_deterministic_subset(scene):
    full = build(scene)
    few = build(scene, max_points=200)
    again = build(scene, max_points=200)
    assert few.num_points.tolist() == [200, 200]
    torch.testing.assert_close(few.points, again.points, rtol=0, atol=0)
    _, pix_full, _ = pixels_of(scene, full)
    _, pix_few, _ = pixels_of(scene, few)
    for k in range(2):
        keys_full = set((pix_full[k][full.valid[k]] @ torch.tensor([1, W])).tolist())
        keys_few = set((pix_few[k][few.valid[k]] @ torch.tensor([1, W])).tolist())
        assert keys_few <= keys_full
    # a stream gets the same template alone as in a batch
    s = scene
    alone = build_template(
        s["model"], s["shape"][1:], s["anim"][1:], s["R"][1:], s["t"][1:], s["gray"][1:], s["cam"],
        max_points=200, gradient_threshold=0.0,
    )
    torch.testing.assert_close(alone.points[0], few.points[1], rtol=0, atol=0)
    torch.testing.assert_close(alone.intensity[0], few.intensity[1], rtol=0, atol=0)


def test_more_slots_than_candidates_marks_the_rest_invalid(scene):
    tpl = build(scene, gradient_threshold=0.2)
    n = tpl.num_points
    assert bool((n > 0).all()) and bool((n < H * W).all())
    assert bool(torch.isfinite(tpl.points).all()), "unused slots must still hold finite values"


def test_identity_warp_reproduces_the_template(scene):
    """At the template frame's own parameters (zero light), every valid residual of Eq. 20 is ~0."""
    s = scene
    model = s["model"]
    tpl = build(s)
    layout = ParamLayout(model.num_animation, 5)
    x = torch.zeros(2, layout.size)
    x[:, layout.rotation] = matrix_to_axis_angle(s["R"])
    x[:, layout.translation] = s["t"]
    x[:, layout.animation] = s["anim"]
    basis = illumination_basis(tpl.intensity, tpl.normals @ s["R"].mT)
    r, _, valid = frame_residuals(x, layout, tpl, image_with_gradients(s["gray"]), s["cam"], basis, tpl.valid)
    assert bool((valid == tpl.valid).all()), "every template point is usable in its own frame"
    # float32 projection lands within ~1e-4 px of the pixel centre: |r| <= |grad I| * 1e-4 + sampling round-off
    assert float(r[valid].abs().max()) < 1e-3
    # and the residual is not trivially zero elsewhere: a 1-pixel shift gives large residuals
    x_shift = x.clone()
    x_shift[:, 3] += s["t"][:, 2] / s["cam"].fx
    r_shift, _, v_shift = frame_residuals(x_shift, layout, tpl, image_with_gradients(s["gray"]), s["cam"], basis, tpl.valid)
    assert float(r_shift[v_shift].abs().mean()) > 20 * float(r[valid].abs().mean())


def test_gather_face_attributes_known_answer():
    faces = torch.tensor([[0, 1, 2], [1, 3, 2]])
    attrs = torch.tensor([[0.0, 0.0], [2.0, 0.0], [0.0, 4.0], [6.0, 6.0]])
    face_index = torch.tensor([[0, 1, -1]])
    bary = torch.tensor([[[0.2, 0.3, 0.5], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
    out = gather_face_attributes(attrs, faces, face_index, bary, batched=False)
    expected = torch.tensor([[[0.6, 2.0], [2.0, 0.0], [2.0, 0.0]]])  # face -1 is clamped to face 0
    torch.testing.assert_close(out, expected)
    batched = gather_face_attributes(attrs.expand(1, -1, -1), faces, face_index, bary, batched=True)
    torch.testing.assert_close(batched, expected)


def test_bad_inputs_raise(scene):
    s = scene
    with pytest.raises(ValueError, match=r"gray must be \(B, 1, 120, 160\)"):
        build_template(s["model"], s["shape"], s["anim"], s["R"], s["t"], s["gray"][:, :, :60], s["cam"],
                       max_points=10, gradient_threshold=0.0)
    with pytest.raises(ValueError, match="max_points"):
        build(scene, max_points=0)
    with pytest.raises(ValueError, match="max_points"):
        build(scene, max_points=H * W + 1)
    # a numpy array ("no attribute 'dim'"), uint8 gray ("result type Float can't be cast ... Byte"), bool gray
    args = (s["model"], s["shape"], s["anim"], s["R"], s["t"])
    with pytest.raises(TypeError, match=r"gray must be a torch.Tensor \(B, 1, H, W\) float in \[0, 1\], got ndarray"):
        build_template(*args, s["gray"].numpy(), s["cam"], max_points=10, gradient_threshold=0.0)
    with pytest.raises(ValueError, match=r"gray must be \(B, 1, H, W\) float .*uint8: pass gray.float\(\) / 255"):
        build_template(*args, (s["gray"] * 255).round().to(torch.uint8), s["cam"], max_points=10, gradient_threshold=0.0)
    with pytest.raises(ValueError, match=r"gray must be \(B, 1, H, W\) float in \[0, 1\], got torch.bool"):
        build_template(*args, s["gray"] > 0.5, s["cam"], max_points=10, gradient_threshold=0.0)


def test_expression_priority_keeps_points_that_animation_units_move():
    """With ``expression_priority`` the template favours pixels an animation unit moves (>= 1 px per unit)."""
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import render_sequence

    model = load_candide3()
    frames, gt = render_sequence(make_scenario("expressions", 1, 320, 240))
    gray = frames.mean(1, keepdim=True)
    R, t = gt.rotation.float(), gt.translation.float()
    shape = gt.shape_coeffs.float().unsqueeze(0)
    anim = gt.au.float()
    cam = Intrinsics.default(320, 240)

    def moving_points(priority: float) -> int:
        tpl = build_template(model, shape, anim, R, t, gray, cam, max_points=150, gradient_threshold=0.01,
                             expression_priority=priority)
        px = tpl.basis.norm(dim=2).amax(-1) * cam.fx / 450.0  # pixels per unit coefficient, roughly
        return int(((px >= 1.0) & tpl.valid).sum())

    plain, favoured = moving_points(0.0), moving_points(1.0)
    assert favoured > plain, (plain, favoured)
    assert favoured >= 140  # nearly every slot goes to a point an animation unit moves


def test_expression_quota_gives_every_animation_unit_points():
    """With ``expression_quota`` q, every animation unit keeps at least min(q, what it had) template points that it
    moves (>= 1 px per unit) and the eyelid unit, which the uniform draw nearly misses, gains."""
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import render_sequence

    model = load_candide3()
    frames, gt = render_sequence(make_scenario("expressions", 1, 320, 240))
    gray = frames.mean(1, keepdim=True)
    R, t = gt.rotation.float(), gt.translation.float()
    shape, anim = gt.shape_coeffs.float().unsqueeze(0), gt.au.float()
    cam = Intrinsics.default(320, 240)

    def per_unit(quota: int) -> torch.Tensor:
        tpl = build_template(model, shape, anim, R, t, gray, cam, max_points=400, gradient_threshold=0.01,
                             expression_quota=quota)
        # the selection's measure: per-vertex displacement norms interpolated at the point, over its depth
        au_mm = gather_face_attributes(model.animation_units.norm(dim=-1).T, model.faces, tpl.face_index, tpl.bary,
                                       batched=False)
        posed = tpl.points + (tpl.basis * anim[:, None, None]).sum(-1)
        z = (posed @ R.mT + t[:, None])[..., 2:]  # (1, N, 1) depth, mm
        return ((au_mm * cam.fx / z >= 0.999) & tpl.valid[..., None]).sum(1)[0]  # (A,)

    q = 20
    plain, quota = per_unit(0), per_unit(q)
    eyes = model.animation_names.index("AUV6 Eyes closed")
    # At 320x240 the eyelids have fewer than q candidates: the quota takes them (measured 2 -> 8 points).
    assert int(quota[eyes]) >= int(plain[eyes]) + 4, (plain.tolist(), quota.tolist())
    assert bool((quota >= torch.clamp(plain, max=q)).all()), (plain.tolist(), quota.tolist())


def test_quota_lift_at_the_candidates_is_the_whole_windows_fragments(scene):
    """The expression quota's lift, evaluated at the candidate pixels alone, is the one computed from the whole
    window's fragments (every pixel's barycentric coordinates and depth: the slow reference written here)."""
    from torchface.template.points import _quota_lift, rasterize_windows

    s = scene
    model = s["model"]
    posed = posed_mesh(model, s["shape"], s["anim"], s["R"], s["t"])
    frags = rasterize_windows(model, posed.verts_cam, [s["cam"]], [torch.zeros(2, 2, dtype=torch.int64)])[0]
    B, H, W = frags.pix_to_face.shape
    gen = torch.Generator().manual_seed(3)
    keys = torch.rand(B, H * W, generator=gen)
    candidate = (frags.pix_to_face >= 0) & (torch.rand(B, H, W, generator=gen) < 0.5)
    flat = candidate.reshape(-1).nonzero().squeeze(-1)
    for q in (1, 20, 10_000):
        got = _quota_lift(model, frags, flat, keys, s["cam"].fx, q)
        # the reference: fragments of every pixel; per sample and unit, the q highest keys of the moved candidates
        full = frags.fragments()
        au_mm = model.animation_units.norm(dim=-1).T  # (V, A)
        sens = gather_face_attributes(au_mm, model.faces, frags.pix_to_face.reshape(B, -1),
                                      full.bary.reshape(B, -1, 3), batched=False)  # fmt: skip
        moved = (sens * (s["cam"].fx / full.zbuf.reshape(B, -1, 1).clamp(1.0, 1e30)) >= 1.0)
        moved &= candidate.reshape(B, -1, 1)
        want = torch.zeros(B, H * W)
        for b in range(B):
            for a in range(model.num_animation):
                idx = moved[b, :, a].nonzero().squeeze(-1)
                top = idx[torch.argsort(keys[b, idx], descending=True)[:q]]
                want[b, top] = 1.0
        assert torch.equal(got, want), q
        assert 0 < int(got.sum()) <= min(q, H * W) * B * model.num_animation


@pytest.mark.parametrize(("priority", "quota"), [(0.0, 0), (1.0, 0), (0.0, 30)])
def test_window_build_equals_the_whole_image_build(scene, priority, quota):
    """Per-sample windows around the faces (offsets) give the whole image's template: same pixels, same slots."""
    s = scene
    whole = build(scene, max_points=1500, gradient_threshold=0.02, expression_priority=priority, expression_quota=quota)
    uv, _, _ = pixels_of(scene, whole)
    # Windows 64x56 placed around each face (different offsets per sample), inside the 160x120 image.
    lo = torch.where(whole.valid[..., None], uv, torch.full_like(uv, 1e9)).amin(1).floor().long() - 3
    offsets = lo.clamp(min=0)
    h, w = 56 + 34, 64 + 20
    offsets[:, 0] = offsets[:, 0].clamp(max=W - w)
    offsets[:, 1] = offsets[:, 1].clamp(max=H - h)
    assert not torch.equal(offsets[0], offsets[1])
    rows = offsets[:, 1:2, None] + torch.arange(h)[None, :, None]
    cols = offsets[:, 0:1, None] + torch.arange(w)[None, None, :]
    crops = torch.stack([s["gray"][b, :, rows[b], cols[b]] for b in range(2)])
    windowed = build_template(
        s["model"], s["shape"], s["anim"], s["R"], s["t"], crops, s["cam"], max_points=1500,
        gradient_threshold=0.02, expression_priority=priority, expression_quota=quota, offsets=offsets,
    )
    assert int(whole.valid.sum()) > 500
    assert torch.equal(windowed.valid, whole.valid)
    assert torch.equal(windowed.face_index[whole.valid], whole.face_index[whole.valid])
    torch.testing.assert_close(windowed.bary, whole.bary, atol=1e-4, rtol=0)
    torch.testing.assert_close(windowed.intensity, whole.intensity)


def test_windows_rasterized_together_are_the_windows_rasterized_alone(scene):
    """rasterize_windows (a pyramid's levels, each sample's window, one call) gives each window's back-face-culled
    fragments as rasterizing it alone: the same triangles (bar pixel centres on a shared edge, where rounding
    may pick either neighbour), barycentric coordinates and depths to rounding."""
    s = scene
    posed = posed_mesh(s["model"], s["shape"], s["anim"], s["R"], s["t"])
    offsets = [torch.tensor([[40, 20], [30, 28]]), torch.tensor([[20, 10], [15, 14]]), None]
    cams, windows = [], []
    for level, (off, (h, w)) in enumerate(zip(offsets, [(70, 80), (35, 40), (H // 4, W // 4)])):
        full = level_intrinsics(s["cam"], level, H >> level, W >> level)
        cams.append(Intrinsics(w, h, full.fx, full.fy, full.cx, full.cy))
        windows.append(off)
    together = rasterize_windows(s["model"], posed.verts_cam, cams, windows)
    for cam, off, coverage in zip(cams, windows, together):
        frags = coverage.fragments()
        shift = torch.zeros(2, 3) if off is None else torch.cat([off / torch.tensor([cam.fx, cam.fy]),
                                                                   torch.zeros(2, 1)], -1)  # fmt: skip
        alone = rasterize(posed.verts_cam - posed.verts_cam[..., 2:3] * shift[:, None], s["model"].faces, cam,
                          cull_backfaces=True)  # fmt: skip
        assert frags.pix_to_face.shape == (2, cam.height, cam.width)
        same = frags.pix_to_face == alone.pix_to_face
        assert int((alone.pix_to_face >= 0).sum()) > 200
        assert float(same.float().mean()) > 0.995
        both = same & (alone.pix_to_face >= 0)
        torch.testing.assert_close(frags.bary[both], alone.bary[both], atol=1e-4, rtol=0)
        torch.testing.assert_close(frags.zbuf[both], alone.zbuf[both], atol=1e-3, rtol=0)
        assert torch.equal(frags.facing[same], alone.facing[same])


@pytest.mark.parametrize("windowed", [False, True])
def test_strided_window_rasterizes_every_other_pixel(scene, windowed):
    """strided_window's camera sees at its pixel (i, j) what the window's camera sees at (2i, 2j): the same
    triangles (bar pixel centres on a shared edge), barycentric coordinates and depths, for whole images and
    for windows (offsets, odd ones too: they become fractional)."""
    s = scene
    posed = posed_mesh(s["model"], s["shape"], s["anim"], s["R"], s["t"])
    off = torch.tensor([[41, 20], [30, 27]]) if windowed else None
    h, w = (70, 81) if windowed else (H, W)
    cam = Intrinsics(w, h, s["cam"].fx, s["cam"].fy, s["cam"].cx, s["cam"].cy)
    full = rasterize_windows(s["model"], posed.verts_cam, [cam], [off])[0].fragments()
    grid_cam, grid_off = strided_window(cam, off, 2)
    assert (grid_cam.width, grid_cam.height) == (-(-w // 2), -(-h // 2))
    strided = rasterize_windows(s["model"], posed.verts_cam, [grid_cam], [grid_off])[0].fragments()
    sub = full.pix_to_face[:, ::2, ::2]
    same = strided.pix_to_face == sub
    assert int((sub >= 0).sum()) > 100
    assert float(same.float().mean()) > 0.99
    both = same & (sub >= 0)
    torch.testing.assert_close(strided.bary[both], full.bary[:, ::2, ::2][both], atol=1e-4, rtol=0)
    torch.testing.assert_close(strided.zbuf[both], full.zbuf[:, ::2, ::2][both], atol=1e-3, rtol=0)
    assert strided_window(cam, off, 1) == (cam, off)


def _pixel_of(s, posed, px, b):
    """Integer (x, y) image pixels of sample ``b``'s valid points (projected surface points: pixel centres)."""
    corners = posed.verts_cam[b][s["model"].faces[px.face_index[b][px.valid[b]]]]  # (n, 3, 3)
    point = (corners * px.bary[b][px.valid[b]].unsqueeze(-1)).sum(1)
    uv = project_points(point[None], s["cam"])[0]
    assert float((uv - uv.round()).abs().max()) < 1e-2
    return uv.round().long()


@pytest.mark.parametrize("windowed", [False, True])
def test_strided_selection_picks_among_the_window_pixels_of_its_grid(scene, windowed):
    """select_pixels_posed(stride=2) against a slow reference (no erosion, whose radius counts in grid steps):
    its candidates are the full-resolution candidates at the window's even rows and columns, with their
    triangle, barycentric coordinates and intensity, and it picks the n with the highest selection keys."""
    s = scene
    posed = posed_mesh(s["model"], s["shape"], s["anim"], s["R"], s["t"])
    off = torch.tensor([[40, 20], [30, 28]]) if windowed else None
    gray = s["gray"] if off is None else torch.stack([s["gray"][b, :, y:y + 70, x:x + 80]
                                                     for b, (x, y) in enumerate(off.tolist())])  # fmt: skip
    kw = dict(gradient_threshold=0.01, erode_pixels=0)
    every = select_pixels_posed(s["model"], posed, gray, s["cam"], off, max_points=gray.shape[-1] * gray.shape[-2],
                                **kw)  # fmt: skip
    grid_pixels = -(-gray.shape[-1] // 2) * -(-gray.shape[-2] // 2)
    all_grid = select_pixels_posed(s["model"], posed, gray, s["cam"], off, max_points=grid_pixels, stride=2, **kw)
    n = 300
    strided = select_pixels_posed(s["model"], posed, gray, s["cam"], off, max_points=n, stride=2, **kw)
    assert int(strided.valid.sum()) == 2 * n
    keys = _selection_keys(H, W, torch.device("cpu")).view(H, W)
    for b in range(2):
        origin = torch.zeros(2, dtype=torch.long) if off is None else off[b]
        pix_every = _pixel_of(s, posed, every, b)
        on_grid = ((pix_every - origin) % 2 == 0).all(-1)
        pix_grid = _pixel_of(s, posed, all_grid, b)
        # The same pixels, and at each the same triangle, barycentric coordinates and intensity.
        order_e = torch.argsort(pix_every[on_grid, 1] * W + pix_every[on_grid, 0])
        order_g = torch.argsort(pix_grid[:, 1] * W + pix_grid[:, 0])
        assert torch.equal(pix_every[on_grid][order_e], pix_grid[order_g])
        assert torch.equal(every.face_index[b][every.valid[b]][on_grid][order_e],
                           all_grid.face_index[b][all_grid.valid[b]][order_g])  # fmt: skip
        torch.testing.assert_close(every.bary[b][every.valid[b]][on_grid][order_e],
                                   all_grid.bary[b][all_grid.valid[b]][order_g], atol=1e-4, rtol=0)  # fmt: skip
        assert torch.equal(every.intensity[b][every.valid[b]][on_grid][order_e],
                           all_grid.intensity[b][all_grid.valid[b]][order_g])  # fmt: skip
        # The n picks are the n grid candidates with the highest keys.
        grid_keys = keys[pix_grid[:, 1], pix_grid[:, 0]]
        want = set(map(tuple, pix_grid[torch.topk(grid_keys, n).indices].tolist()))
        assert set(map(tuple, _pixel_of(s, posed, strided, b).tolist())) == want


def test_window_build_bad_offsets_raise(scene):
    s = scene
    crops = s["gray"][:, :, :50, :60]
    kw = dict(max_points=10, gradient_threshold=0.0)
    with pytest.raises(ValueError, match="offsets must be"):
        build_template(s["model"], s["shape"], s["anim"], s["R"], s["t"], crops, s["cam"],
                       offsets=torch.zeros(2, 2), **kw)
    with pytest.raises(ValueError, match="inside the 160x120 image"):
        build_template(s["model"], s["shape"], s["anim"], s["R"], s["t"], crops, s["cam"],
                       offsets=torch.tensor([[0, 0], [101, 0]]), **kw)


def test_point_last_copies_are_kept_normal_and_not_kept_with_a_gradient():
    """The fast solver's point-last copies: equal to the fields, made once per template even when first asked for
    under inference mode (and then normal tensors, so a later differentiable call can save them), made again on
    each use when a template tensor requires grad (the gradient must reach it), and not carried into a copy."""
    from torchface.template import Template
    from torchface.tracker.inference import normal_tensors

    gen = torch.Generator().manual_seed(0)
    B, N, A = 2, 5, 3

    def make(requires_grad: bool = False) -> Template:
        pts = torch.randn(B, N, 3, generator=gen, requires_grad=requires_grad)
        return Template(torch.zeros(B, N, dtype=torch.int64), torch.rand(B, N, 3, generator=gen), pts,
                        torch.randn(B, N, 3, A, generator=gen), torch.randn(B, N, 3, generator=gen),
                        torch.rand(B, N, generator=gen), torch.ones(B, N, dtype=torch.bool))  # fmt: skip

    tpl = make()
    with torch.inference_mode():
        first = tpl.point_last
    assert not any(t.is_inference() for t in first) and tpl.point_last is first
    points_t, normals_t, basis_t = first
    assert torch.equal(points_t, tpl.points.transpose(1, 2)) and torch.equal(normals_t, tpl.normals.transpose(1, 2))
    assert torch.equal(basis_t, tpl.basis.permute(0, 3, 2, 1)) and basis_t.is_contiguous()
    live = make(requires_grad=True)
    assert live.point_last is not live.point_last and live.point_last[0].requires_grad
    with torch.inference_mode():
        inner = Template(*(getattr(tpl, f) * 1 for f in tpl.__dataclass_fields__))
        inner.point_last
    copy = normal_tensors(inner)
    assert copy is not inner and "_point_last" not in copy.__dict__


@pytest.mark.parametrize("radius", [1, 2])
def test_erode_equals_the_square_minimum_filter(radius):
    """The separable erosion keeps exactly the pixels whose (2 r + 1)^2 square is set, outside the image counting
    as set (the minimum filter written out, at the borders too)."""
    from torchface.template.points import _erode

    gen = torch.Generator().manual_seed(radius)
    mask = torch.rand(2, 17, 23, generator=gen) > 0.15
    pad = torch.nn.functional.pad(mask, (radius, radius, radius, radius), value=True)
    k = 2 * radius + 1
    want = torch.ones_like(mask)
    for dy in range(k):
        for dx in range(k):
            want &= pad[:, dy : dy + 17, dx : dx + 23]
    assert torch.equal(_erode(mask, radius), want)
    assert torch.equal(_erode(mask, 0), mask)


@pytest.mark.parametrize(("min_facing_cos", "quota"), [(-0.3, 0), (0.15, 0), (0.6, 0), (0.15, 20)])
def test_native_candidates_give_the_torch_codes_selection(scene, min_facing_cos, quota):
    """The native kernel's candidate tests and scores (``torchface/_native/select_pixels.h``) give the torch
    code's selection bit for bit: whole images and per-sample windows, at several thresholds (the facing test on
    many triangles at 0.6), with few and with many slots, and with the expression quota."""
    from torchface import _native
    from torchface.backend import Backend
    from torchface.template.points import rasterize_windows

    if _native.library() is None:
        pytest.skip(f"native kernels unavailable: {_native.unavailable_reason()}")
    s = scene
    posed = posed_mesh(s["model"], s["shape"], s["anim"], s["R"], s["t"])
    offsets = torch.tensor([[40, 20], [30, 25]])
    h, w = 80, 90
    rows = offsets[:, 1:2, None] + torch.arange(h)[None, :, None]
    cols = offsets[:, 0:1, None] + torch.arange(w)[None, None, :]
    crops = torch.stack([s["gray"][b, :, rows[b], cols[b]] for b in range(2)])
    window = Intrinsics(w, h, s["cam"].fx, s["cam"].fy, s["cam"].cx, s["cam"].cy)
    frags = rasterize_windows(s["model"], posed.verts_cam, [window], [offsets])[0]
    chosen = 0
    for gray, off, fr in ((s["gray"], None, None), (crops, offsets, frags)):
        for n, threshold in ((300, 0.01), (gray.shape[-1] * gray.shape[-2], 0.0), (800, 0.03)):
            kw = dict(max_points=n, gradient_threshold=threshold, min_facing_cos=min_facing_cos, frags=fr,
                      expression_quota=quota)
            nat = select_pixels_posed(s["model"], posed, gray, s["cam"], off, backend=Backend.NATIVE, **kw)
            ref = select_pixels_posed(s["model"], posed, gray, s["cam"], off, backend=Backend.TORCH, **kw)
            for f in ("face_index", "bary", "intensity", "valid"):
                assert torch.equal(getattr(nat, f), getattr(ref, f)), (n, threshold, f)
            chosen += int(nat.valid.sum())
    assert chosen > 1000


def test_non_finite_pixels_are_no_template_points_torch_and_native(scene):
    """A float frame's inf or NaN pixels on the face (a mosaic entry made from such a frame) gave template points
    with an infinite intensity or gradient, dead points of every solve: neither backend selects them or their
    neighbours now, and the finite pixels' selection is unchanged."""
    from torchface import _native
    from torchface.backend import Backend

    s = scene
    posed = posed_mesh(s["model"], s["shape"], s["anim"], s["R"], s["t"])
    gray = s["gray"].clone()
    gray[0, 0, 50:53, 70:73] = float("inf")
    gray[0, 0, 60, 90] = float("-inf")
    gray[1, 0, 55:57, 80:82] = float("nan")
    backends = [Backend.TORCH] + ([Backend.NATIVE] if _native.library() is not None else [])
    kw = dict(max_points=H * W, gradient_threshold=0.0)
    for backend in backends:
        px = select_pixels_posed(s["model"], posed, gray, s["cam"], None, backend=backend, **kw)
        clean = select_pixels_posed(s["model"], posed, s["gray"], s["cam"], None, backend=backend, **kw)
        assert bool(torch.isfinite(px.intensity[px.valid]).all()), backend
        assert 0 < int(px.valid.sum()) < int(clean.valid.sum()), backend  # the face was there: only they went
    if len(backends) == 2:
        nat, ref = (select_pixels_posed(s["model"], posed, gray, s["cam"], None, backend=b, **kw) for b in backends)
        for f in ("face_index", "bary", "valid"):
            assert torch.equal(getattr(nat, f), getattr(ref, f)), f


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_native_template_at_is_the_torch_codes_with_its_point_last_copies(scene, dtype):
    """The native interpolation (``torchface/_native/template_at.h``) gives the torch code's template (positions and
    basis bit for bit, normals to rounding) and the point-last copies the solver reads, made in the same pass."""
    from torchface import _native
    from torchface.backend import Backend
    from torchface.template.points import template_at

    if _native.library() is None:
        pytest.skip(f"native kernels unavailable: {_native.unavailable_reason()}")
    s = scene
    model = load_candide3(dtype=dtype)
    px = select_pixels_posed(s["model"], posed_mesh(s["model"], s["shape"], s["anim"], s["R"], s["t"]), s["gray"],
                             s["cam"], None, max_points=700, gradient_threshold=0.01)  # fmt: skip
    face_index = px.face_index.clone()
    face_index[0, -5:] = -1  # unused slots
    args = (model, s["shape"].to(dtype), face_index, px.bary.to(dtype), px.intensity.to(dtype), px.valid)
    nat = template_at(*args, backend=Backend.NATIVE)
    ref = template_at(*args, backend=Backend.TORCH)
    for f in ("face_index", "bary", "points", "basis", "intensity", "valid"):
        assert torch.equal(getattr(nat, f), getattr(ref, f)), f
    torch.testing.assert_close(nat.normals, ref.normals, rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-14)
    cached = nat.__dict__.get("_point_last")
    assert cached is not None
    for got, want in zip(cached, (ref.points.transpose(1, 2), ref.normals.transpose(1, 2),
                                  ref.basis.permute(0, 3, 2, 1))):  # fmt: skip
        torch.testing.assert_close(got, want, rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-14)


@pytest.mark.parametrize("backend", [Backend.TORCH, Backend.NATIVE])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_top_scores_is_a_stable_descending_sort(backend, dtype):
    """The k highest scores in a stable descending sort's order (equal scores by index), with many ties, negative
    non-candidates of several values, and k beyond the candidates' count; the values are torch.topk's."""
    if backend is Backend.NATIVE and _native.library() is None:
        pytest.skip(f"native kernels unavailable: {_native.unavailable_reason()}")
    g = torch.Generator().manual_seed(5)
    for n, k, frac in ((20000, 1500, 0.3), (3000, 400, 0.05), (300, 290, 0.5), (40, 40, 0.0), (9, 4, 1.0)):
        score = (torch.randint(0, 150, (3, n), generator=g).to(dtype) / 150)  # about n / 150 equal copies of each
        drop = torch.rand(3, n, generator=g) > frac
        score[drop] = -1.0 - torch.randint(0, 3, (3, n), generator=g).to(dtype)[drop]
        value, index = top_scores(score, k, backend)
        assert value.shape == index.shape == (3, k) and index.dtype == torch.int64
        for b in range(3):  # the reference: Python's stable sort on (-score, index)
            order = sorted(range(n), key=lambda j: (-float(score[b, j]), j))[:k]
            assert index[b].tolist() == order
            torch.testing.assert_close(value[b], score[b, order], rtol=0, atol=0)
        torch.testing.assert_close(value, torch.topk(score, k, dim=1).values, rtol=0, atol=0)
    # Signed zeros (equal: by index) and values over the whole range (the native kernel sorts their bit patterns).
    score = torch.tensor([[0.0, -0.0, 3e38, -0.0, 0.0, -3e38, 1e-40, -1e-40, 0.0, 2.0, -1.0, 2.0]], dtype=dtype)
    order = sorted(range(score.shape[1]), key=lambda j: (-float(score[0, j]), j))
    for k in (1, 5, score.shape[1]):
        assert top_scores(score, k, backend)[1][0].tolist() == order[:k]
    with pytest.raises(ValueError, match="k must be"):
        top_scores(torch.zeros(1, 5), 6, backend)
    with pytest.raises(ValueError, match="score must be"):
        top_scores(torch.zeros(5), 2, backend)


@pytest.mark.parametrize("backend", [Backend.AUTO, Backend.TORCH])
def test_an_empty_batch_gives_an_empty_template(scene, backend):
    """B = 0 streams: an empty template of the slots asked for (the pixel selection and the interpolation raised
    "cannot reshape tensor of 0 elements into shape [0, -1]", as a state of no streams, ``state.select([])``, steps
    without error)."""
    s = {k: (v[:0] if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    tpl = build(s, max_points=50, gradient_threshold=0.01, backend=backend)
    A = scene["model"].num_animation
    assert tpl.points.shape == (0, 50, 3) and tpl.basis.shape == (0, 50, 3, A) and tpl.intensity.shape == (0, 50)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_native_template_pixels_at_the_chosen_candidates_are_the_torch_codes(scene, dtype):
    """_top_pixels' native pass over the chosen pixels (``torchface/_native/top_pixels.h``: triangle, barycentric
    coordinates, gray value, candidate or not) gives the torch code's TemplatePixels bit for bit: pyramid levels
    rasterized together (windows after the first sit further into the coefficient table), whole images and
    windows, with more slots than candidates (background and non-candidate pixels chosen)."""
    from torchface.template.points import _top_pixels, rasterize_windows

    if _native.library() is None:
        pytest.skip(f"native kernels unavailable: {_native.unavailable_reason()}")
    s = scene
    model = load_candide3(dtype=dtype)
    posed = posed_mesh(model, s["shape"].to(dtype), s["anim"].to(dtype), s["R"].to(dtype), s["t"].to(dtype))
    offsets = [torch.tensor([[40, 20], [30, 28]]), torch.tensor([[20, 10], [15, 14]]), None]
    cams = []
    for level, (h, w) in enumerate([(70, 80), (35, 40), (H // 4, W // 4)]):
        full = level_intrinsics(s["cam"], level, H >> level, W >> level)
        cams.append(Intrinsics(w, h, full.fx, full.fy, full.cx, full.cy))
    g = torch.Generator().manual_seed(4)
    picked = 0
    for cam, frags in zip(cams, rasterize_windows(model, posed.verts_cam, cams, offsets)):
        gray = torch.rand(2, 1, cam.height, cam.width, generator=g, dtype=dtype)
        face_flat = frags.pix_to_face.flatten(1)
        score = torch.rand(2, cam.height * cam.width, generator=g)  # float32, as the selection's keys
        score[torch.rand(score.shape, generator=g) < 0.5] = -1.0
        for k in (7, cam.height * cam.width // 3, cam.height * cam.width):
            nat = _top_pixels(score, face_flat, frags, gray, k, dtype, Backend.NATIVE)
            ref = _top_pixels(score, face_flat, frags, gray, k, dtype, Backend.TORCH)
            for f in ("face_index", "bary", "intensity", "valid"):
                assert getattr(nat, f).dtype == getattr(ref, f).dtype, f
                assert torch.equal(getattr(nat, f), getattr(ref, f)), (cam, k, f)
            picked += int(((face_flat.gather(1, torch.topk(score, k, dim=1).indices) >= 0)).sum())
        assert not bool(nat.valid.all()) and bool((nat.bary == 0).all(-1).any())  # non-candidates, background
    assert picked > 1000


def test_selection_keys_do_not_follow_torchs_default_dtype():
    """The template-point keys were ``torch.rand`` in torch's default dtype: under ``torch.set_default_dtype(
    torch.float64)`` (common in scientific code) the same seed drew other keys, so a float32 tracker took another
    subset of template points and its poses moved (0.24 degrees within 10 frames of a GRID clip, 3 streams). They
    are float32, the same draw, whatever the default."""
    from torchface.template.points import _cpu_selection_keys

    previous = torch.get_default_dtype()
    _cpu_selection_keys.cache_clear()  # (drawn once per size: a draw cached before would hide the default's effect)
    try:
        torch.set_default_dtype(torch.float64)
        under_float64 = _selection_keys(37, 41, torch.device("cpu")).clone()
    finally:
        torch.set_default_dtype(previous)
        _cpu_selection_keys.cache_clear()
    keys = _selection_keys(37, 41, torch.device("cpu"))
    assert keys.dtype == torch.float32 and torch.equal(under_float64, keys)
