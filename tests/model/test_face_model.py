"""FaceModel: deform (Eq. 1), landmarks, normals, validation, dtype/device handling."""

from __future__ import annotations

import dataclasses
import re

import pytest
import torch

from torchface.model import (
    FaceModel,
    deform_vertices,
    face_normals,
    interpolate_landmarks,
    load_candide3,
    vertex_normals,
)


@pytest.fixture(scope="module")
def model():
    return load_candide3(dtype=torch.float64)


def test_zero_coefficients_give_the_mean(model):
    torch.testing.assert_close(model.deform()[0], model.mean)
    sigma0 = torch.zeros(3, model.num_shape, dtype=torch.float64)
    zeros = model.deform(sigma0, torch.zeros(3, model.num_animation, dtype=torch.float64))
    assert zeros.shape == (3, model.num_vertices, 3)
    torch.testing.assert_close(zeros, model.mean.expand(3, -1, -1))
    # None for one term, B inferred from the other.
    assert model.deform(None, torch.zeros(5, model.num_animation, dtype=torch.float64)).shape[0] == 5
    assert model.deform(torch.zeros(4, model.num_shape, dtype=torch.float64), None).shape[0] == 4
    # The output never aliases the model's mean.
    out = model.deform()
    out += 1.0
    assert not torch.equal(out[0], model.mean)


def test_deform_matches_explicit_sum(model):
    gen = torch.Generator().manual_seed(0)
    sigma = torch.randn(4, model.num_shape, generator=gen, dtype=torch.float64)
    alpha = torch.randn(4, model.num_animation, generator=gen, dtype=torch.float64)
    out = model.deform(sigma, alpha)
    for b in range(4):  # slow reference, one sample and one unit at a time
        ref = model.mean.clone()
        for s in range(model.num_shape):
            ref = ref + sigma[b, s] * model.shape_units[s]
        for a in range(model.num_animation):
            ref = ref + alpha[b, a] * model.animation_units[a]
        torch.testing.assert_close(out[b], ref)
        torch.testing.assert_close(model.deform(sigma[b : b + 1], alpha[b : b + 1])[0], out[b])


def test_deform_is_linear_with_exact_jacobian(model):
    alpha = torch.randn(1, model.num_animation, dtype=torch.float64)
    jac = torch.autograd.functional.jacobian(lambda a: model.deform(None, a)[:, ::8], alpha)
    expected = model.animation_units[:, ::8].permute(1, 2, 0)  # (V/8, 3, A)
    torch.testing.assert_close(jac[0, :, :, 0, :], expected)
    sigma = torch.randn(2, model.num_shape, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s: model.deform(s, alpha.expand(2, -1)), (sigma,), fast_mode=True)


@pytest.mark.parametrize(
    "shape, anim, error, message",
    [
        ("vec", None, ValueError, r"shape coefficients must have shape \(B, 14\), got \(14,\)"),
        (None, "wrong_width", ValueError, r"animation coefficients must have shape \(B, 11\), got \(2, 10\)"),
        ("batch3", "batch2", ValueError, "share the batch size"),
        (None, "float32", TypeError, "dtype"),
        (None, "list", TypeError, "torch.Tensor"),
    ],
)
def test_bad_coefficients_raise(model, shape, anim, error, message):
    values = {
        None: None,
        "vec": torch.zeros(14, dtype=torch.float64),
        "wrong_width": torch.zeros(2, 10, dtype=torch.float64),
        "batch3": torch.zeros(3, 14, dtype=torch.float64),
        "batch2": torch.zeros(2, 11, dtype=torch.float64),
        "float32": torch.zeros(1, 11, dtype=torch.float32),
        "list": [[0.0] * 11],
    }
    with pytest.raises(error, match=message):
        model.deform(values[shape], values[anim])


def test_landmarks_follow_deformation(model):
    alpha = torch.zeros(2, model.num_animation, dtype=torch.float64)
    alpha[1, model.animation_names.index("AUV11 Jaw drop")] = 1.0
    verts = model.deform(None, alpha)
    lm = model.landmarks_3d(verts)
    assert lm.shape == (2, 68, 3)
    # Chin (iBUG 8 = vertex 10) and lower lip (57 = vertex 8) move down (+y); upper lip (51 = 7) stays.
    delta = lm[1] - lm[0]
    assert delta[8, 1] > 10.0 and delta[57, 1] > 20.0
    torch.testing.assert_close(delta[51], torch.zeros(3, dtype=torch.float64))
    # Derived landmark = weighted vertices, by hand.
    k = 5
    ref = sum(model.landmark_weights[k, j] * verts[:, model.landmark_vertices[k, j]] for j in range(3))
    torch.testing.assert_close(lm[:, k], ref)
    with pytest.raises(ValueError, match=r"verts must have shape \(B, 113, 3\)"):
        model.landmarks_3d(verts[0])


def test_dtype_and_device_follow():
    m32 = load_candide3()
    assert m32.dtype == torch.float32 and m32.device.type == "cpu"
    assert m32.deform(None, torch.zeros(1, 11)).dtype == torch.float32
    m64 = m32.to(dtype=torch.float64)
    assert m64.dtype == torch.float64 and m64.faces.dtype == torch.int64
    assert m64.surface_vertex_mask.dtype == torch.bool and m64.landmark_vertices.dtype == torch.int64
    assert all(t.dtype == torch.float64 for t in (m64.shape_units, m64.animation_units, m64.animation_ranges,
                                                    m64.landmark_weights, m64.facs_matrix))
    torch.testing.assert_close(m64.mean.float(), m32.mean)
    assert m32.to("cpu").device == torch.device("cpu")
    assert m32.to(torch.float64).dtype == torch.float64  # a dtype first, as nn.Module.to takes it
    with pytest.raises(TypeError, match="two dtypes"):
        m32.to(torch.float64, torch.float32)
    with pytest.raises(TypeError, match="floating"):
        m32.to(dtype=torch.int32)
    if torch.cuda.is_available():
        mg = m32.to("cuda")
        assert mg.deform(None, torch.zeros(1, 11, device="cuda")).device.type == "cuda"


def test_construction_validates_shapes(model):
    fields = {f: getattr(model, f) for f in model.__dataclass_fields__}
    bad = dict(fields, shape_units=model.shape_units[:, :-1])
    with pytest.raises(ValueError, match=r"shape_units must have shape \(14, 113, 3\)"):
        FaceModel(**bad)
    with pytest.raises(ValueError, match="faces must be an int64"):
        FaceModel(**dict(fields, faces=model.faces.int()))
    with pytest.raises(TypeError, match="tuple of str"):
        FaceModel(**dict(fields, shape_names=list(model.shape_names)))
    with pytest.raises(ValueError, match="faces index vertices outside"):
        FaceModel(**dict(fields, faces=model.faces + 200))
    # a mask that is not the faces' (from a file, or a replace of the faces) was taken: an all-False one made the
    # tracker's start a bare RuntimeError of amax
    none = torch.zeros_like(model.surface_vertex_mask)
    used = int(model.surface_vertex_mask.sum())  # (104 of the 113)
    with pytest.raises(ValueError, match=r"surface_vertex_mask must be True for exactly the vertices that faces use, "
                                         rf"got False for vertex 0, which a face uses \({used} vertices differ\)"):
        FaceModel(**dict(fields, surface_vertex_mask=none))
    unused = int((~model.surface_vertex_mask).nonzero()[0, 0])
    extra = model.surface_vertex_mask.clone()
    extra[unused] = True
    with pytest.raises(ValueError, match=rf"got True for vertex {unused}, which no face uses \(1 vertices differ\)"):
        FaceModel(**dict(fields, surface_vertex_mask=extra))


def test_vertex_normals_known_answer_and_zero_safe():
    # A unit square in the z = 0 plane, wound so that (v1 - v0) x (v2 - v0) is -z, plus an unused vertex.
    verts = torch.tensor([[[0.0, 0, 0], [0, 1, 0], [1, 1, 0], [1, 0, 0], [3, 3, 3]]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    vn = vertex_normals(verts, faces)
    torch.testing.assert_close(vn[0, :4], torch.tensor([0.0, 0, -1]).expand(4, 3).double())
    torch.testing.assert_close(vn[0, 4], torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(face_normals(verts, faces)[0], torch.tensor([[0.0, 0, -1], [0, 0, -1]]).double())
    # Area weighting: a tent; the shared vertex normal leans toward the bigger face's normal.
    tent = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 0, 1], [0, 3, 0]]], dtype=torch.float64)
    tf = torch.tensor([[0, 1, 2], [0, 2, 3]])  # normals -y (area 0.5) and -x (area 1.5)
    n0 = vertex_normals(tent, tf)[0, 0]
    expected = torch.tensor([-3.0, -1.0, 0.0], dtype=torch.float64) / 10 ** 0.5
    torch.testing.assert_close(n0, expected)
    # Gradients stay finite through an unused vertex and a degenerate (zero-area) triangle.
    deg = verts.clone().requires_grad_(True)
    out = vertex_normals(deg, torch.tensor([[0, 1, 2], [4, 4, 4]])).sum()
    out = out + face_normals(deg, torch.tensor([[4, 4, 4]])).sum()
    out.backward()
    assert torch.isfinite(deg.grad).all()


def test_normals_gradcheck():
    gen = torch.Generator().manual_seed(1)
    verts = torch.randn(2, 5, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [1, 3, 4]])
    assert torch.autograd.gradcheck(lambda v: vertex_normals(v, faces), (verts,))
    assert torch.autograd.gradcheck(lambda v: face_normals(v, faces), (verts,))


def test_candide_vertex_normals_point_out(model):
    vn = model.vertex_normals(model.mean[None])[0]
    mask = model.surface_vertex_mask
    torch.testing.assert_close(vn[mask].norm(dim=-1), torch.ones(int(mask.sum()), dtype=torch.float64))
    assert (vn[~mask] == 0).all()
    # Nose tip (5) faces the viewer (-z in the head frame); the left temple (14) faces +x.
    assert vn[5, 2] < -0.9 and vn[14, 0] > 0.5


def test_functional_core_examples():
    v = torch.tensor([[[0.0, 0, 0], [2.0, 0, 0]]])
    out = interpolate_landmarks(v, torch.tensor([[0, 1, 0]]), torch.tensor([[0.25, 0.75, 0.0]]))
    torch.testing.assert_close(out, torch.tensor([[[1.5, 0.0, 0.0]]]))
    mean, su, au = torch.zeros(2, 3), torch.zeros(0, 2, 3), torch.ones(1, 2, 3)
    torch.testing.assert_close(deform_vertices(mean, su, au, None, torch.tensor([[2.0]])), torch.full((1, 2, 3), 2.0))
    # S = 0 shape coefficients are (B, 0).
    assert deform_vertices(mean, su, au, torch.zeros(3, 0), None).shape == (3, 2, 3)


def test_construction_refuses_non_finite_values_reversed_ranges_and_unnormalised_landmark_weights(model):
    """A NaN or inf in the model, or a range with lo > hi, was accepted: an inf blendshape tracked until the stream
    was lost without a word, a reversed range failed deep in the landmark fit's solver, a NaN mean in the normalised
    face's distance check."""
    fields = {f: getattr(model, f) for f in model.__dataclass_fields__}
    mean = model.mean.clone()
    mean[100, 1] = float("nan")
    with pytest.raises(ValueError, match="mean holds non-finite values"):
        FaceModel(**dict(fields, mean=mean))
    units = model.animation_units.clone()
    units[0, 5, 2] = float("inf")
    with pytest.raises(ValueError, match="animation_units holds non-finite values"):
        FaceModel(**dict(fields, animation_units=units))
    ranges = model.animation_ranges.clone()
    ranges[1] = ranges[1].flip(0)
    with pytest.raises(ValueError, match=r"lo <= hi, reversed for \['AUV11 Jaw drop'\]"):
        FaceModel(**dict(fields, animation_ranges=ranges))
    with pytest.raises(ValueError, match="landmark_weights rows must sum to one"):
        FaceModel(**dict(fields, landmark_weights=model.landmark_weights * 2.0))
    ranges = model.animation_ranges.clone()
    ranges[3] = torch.tensor([0.2, 1.0])  # (0 outside: the fit's start and the prior's centre; the tracking drifted)
    with pytest.raises(ValueError, match=r"must hold 0 .* got \[0.2, 1\] for 'AUV3 Brow lowerer'"):
        FaceModel(**dict(fields, animation_ranges=ranges))
    assert FaceModel(**fields).to(torch.float64).num_animation == 11  # the model itself passes, in any dtype


def test_construction_refuses_repeated_unit_names(model):
    """Two units of one name were accepted: held_shape_units held the first of them only, and the CSV's columns
    collided after the tracking, when the writer was made."""
    fields = {f: getattr(model, f) for f in model.__dataclass_fields__}
    names = list(model.shape_names)
    names[3] = names[2]
    with pytest.raises(ValueError, match=r"shape_names must be distinct .* repeated: \['Eyes vertical position'\]"):
        FaceModel(**dict(fields, shape_names=tuple(names)))
    names = list(model.animation_names)
    names[0] = names[1]
    with pytest.raises(ValueError, match=r"animation_names must be distinct .* repeated: \['AUV11 Jaw drop'\]"):
        FaceModel(**dict(fields, animation_names=tuple(names)))
    with pytest.raises(ValueError, match="facs_names must be distinct"):
        FaceModel(**dict(fields, facs_names=("AU2",) * model.facs_matrix.shape[0]))


def test_construction_refuses_negative_landmark_weights(model):
    """A landmark weight below zero puts the landmark off its triangle (``(1.5, -0.5, 0)`` sums to one and was taken);
    FaceModel and load_mesh_model now share one rule (``check_landmark_weights``): non-negative, rows within 1e-2 of
    one, the landmark named in the message."""
    fields = {f.name: getattr(model, f.name) for f in dataclasses.fields(model)}
    off = model.landmark_weights.clone()
    off[5] = torch.tensor([1.5, -0.5, 0.0])
    with pytest.raises(ValueError, match=r"must be non-negative .* got -0\.5 for landmark 5 \('jaw5: one third"):
        FaceModel(**dict(fields, landmark_weights=off))
    rounded = model.to(torch.bfloat16).to(torch.float32)  # rounded weights (sums of 1.002) still pass
    assert rounded.landmark_weights.min() >= 0


def test_construction_takes_a_rounding_error_below_zero_in_landmark_weights(model):
    """A landmark on a triangle's edge has a barycentric weight of zero, computed as a rounding error below it
    (-6e-8 in float32): it was refused as "must be non-negative"; a weight within 1e-2 below zero passes, as a row
    sum within 1e-2 of one does."""
    fields = {f.name: getattr(model, f.name) for f in dataclasses.fields(model)}
    edge = model.landmark_weights.clone()
    edge[5] = torch.tensor([0.4, 0.6 + 6e-8, -6e-8], dtype=edge.dtype)
    assert FaceModel(**dict(fields, landmark_weights=edge)).landmark_weights[5, 2] == -6e-8
    edge[5] = torch.tensor([0.4, 0.62, -0.02], dtype=edge.dtype)  # (2e-2 below zero: off the triangle)
    with pytest.raises(ValueError, match=r"must be non-negative .* got -0\.02 for landmark 5"):
        FaceModel(**dict(fields, landmark_weights=edge))


@pytest.mark.parametrize("size", [(53, 9846), (14, 113)], ids=["ict", "candide3"])
@pytest.mark.parametrize("layout", ["rows", "row_slice", "expanded", "columns"])
def test_each_stream_deforms_as_it_does_alone_whatever_the_layout(layout, size):
    """Each row of a batch of coefficients gives the vertices that row gives alone (a contiguous batch of one), to
    the bit, in float32 with a basis the size of the ICT Face Model's (53 units, 9846 vertices), whatever the
    coefficients' memory layout: rows (contiguous), a slice of a wider state vector, one row expanded, and
    column-major (an ``(A, B)`` tensor transposed). Column-major coefficients went to ``bmm`` as they were, which
    computed 28 of 36 such rows otherwise than alone (B = 1 to 8); they are made contiguous first. And CANDIDE-3's
    size (14 units, 113 vertices): on an AMD EPYC (AVX-512, MKL 2024.2) the rows whose output was not 64-byte aligned
    were computed otherwise than alone in every layout (9-14 of 36 rows with the ICT basis); each row of the product
    is now aligned. On an Intel Xeon with AVX-512 FP16 (session 65) a row alone, a plain matrix product, rounded
    otherwise than the batched product (29-35 of 36 rows differed, either size); a row alone is now the first of a
    batch of two. A batch of none gives ``(0, V, 3)``."""
    g = torch.Generator().manual_seed(0)
    A, V = size
    mean = torch.randn(V, 3, generator=g)
    su, au = torch.randn(0, V, 3, generator=g), torch.randn(A, V, 3, generator=g)
    rows = differ = 0
    for B in range(1, 9):
        if layout == "rows":
            x = torch.rand(B, A, generator=g)
        elif layout == "row_slice":
            x = torch.rand(B, A + 7, generator=g)[:, 3 : 3 + A]
        elif layout == "expanded":
            x = torch.rand(1, A, generator=g).expand(B, -1)
        else:
            x = torch.rand(A, B, generator=g).T
        full = deform_vertices(mean, su, au, None, x)
        for b in range(B):
            rows += 1
            differ += not torch.equal(full[b : b + 1], deform_vertices(mean, su, au, None, x[b : b + 1].contiguous()))
    assert (rows, differ) == (36, 0)
    assert deform_vertices(mean, su, au, None, torch.zeros(0, A)).shape == (0, V, 3)


def test_the_padded_basis_is_kept_while_the_basis_is_unchanged():
    """``deform_vertices`` pads the basis to aligned rows (``_rowwise_product``); the padded copy, made at every call
    (about 1 ms on the ICT Face Model's basis), is kept while the basis is unchanged. A basis changed in place is
    padded again; one that requires grad, or a call in inference mode, keeps nothing (a gradient reaches the basis,
    and an inference tensor kept would refuse a later call's backward)."""
    from torchface.model import face_model as fm

    g = torch.Generator().manual_seed(3)
    mean, su = torch.randn(37, 3, generator=g), torch.zeros(0, 37, 3)
    au, x = torch.randn(5, 37, 3, generator=g), torch.rand(3, 5, generator=g)
    fm._PADDED.clear()
    first = deform_vertices(mean, su, au, None, x)
    kept = [entry[2] for entry in fm._PADDED.values()]
    assert len(kept) == 1 and kept[0].shape == (5, 112)  # (111 columns padded to 112)
    torch.testing.assert_close(first, mean + torch.einsum("ba,avc->bvc", x, au), rtol=1e-6, atol=1e-6)
    assert torch.equal(deform_vertices(mean, su, au, None, x), first)
    assert [entry[2] for entry in fm._PADDED.values()][0] is kept[0]  # (the same padded tensor)
    au.mul_(2.0)  # (in place: the version counter moves, the padded basis is made again)
    torch.testing.assert_close(deform_vertices(mean, su, au, None, x) - mean, 2 * (first - mean), rtol=1e-6, atol=1e-6)
    fm._PADDED.clear()
    with torch.inference_mode():
        deform_vertices(mean, su, au, None, x)
    assert not fm._PADDED
    alpha = x[:1].clone().requires_grad_()
    deform_vertices(mean, su, au, None, alpha).sum().backward()  # (no inference tensor kept to refuse it)
    assert alpha.grad is not None and torch.isfinite(alpha.grad).all()
    learnt = au.clone().requires_grad_()
    deform_vertices(mean, su, learnt, None, x).sum().backward()
    torch.testing.assert_close(learnt.grad, x.sum(0)[:, None, None].expand(5, 37, 3))
    assert all(not entry[2].requires_grad for entry in fm._PADDED.values())
    for _ in range(fm._PADDED_KEPT + 3):  # (at most _PADDED_KEPT bases kept)
        deform_vertices(mean, su, torch.randn(5, 37, 3, generator=g), None, x)
    assert len(fm._PADDED) == fm._PADDED_KEPT


def test_construction_refuses_landmarks_off_the_surface(model):
    """Landmark weights over vertices that no triangle holds (``[0, 60, 100]``, across the face; two vertices of no
    edge) put the landmark off the surface, though each row sums to one: they were taken. So was a landmark on a
    vertex that no face uses. Both refused, naming the landmark; a triangle's three, an edge's two (the third
    weight 0) and one vertex (padded at weight 0) pass."""
    fields = {f: getattr(model, f) for f in model.__dataclass_fields__}
    name = model.landmark_names[5]
    for vertices, weights, said in (
        ([0, 60, 100], [0.4, 0.3, 0.3], r"vertices \[0, 60, 100\], which no triangle of faces holds"),
        ([0, 60, 0], [0.5, 0.5, 0.0], r"vertices \[0, 60\], which no triangle"),
    ):
        lv, lw = model.landmark_vertices.clone(), model.landmark_weights.clone()
        lv[5], lw[5] = torch.tensor(vertices), torch.tensor(weights)
        with pytest.raises(ValueError, match=rf"landmark 5 \({re.escape(repr(name))}\) has non-zero weights on {said}"):
            FaceModel(**dict(fields, landmark_vertices=lv, landmark_weights=lw))
    a, b, c = model.faces[7].tolist()
    for vertices, weights in (([a, b, c], [0.2, 0.3, 0.5]), ([c, a, c], [0.5, 0.5, 0.0]), ([b, b, b], [1.0, 0, 0])):
        lv, lw = model.landmark_vertices.clone(), model.landmark_weights.clone()
        lv[5], lw[5] = torch.tensor(vertices), torch.tensor(weights)
        FaceModel(**dict(fields, landmark_vertices=lv, landmark_weights=lw))
    # a vertex no face uses: CANDIDE-3's faces without those of vertex 3
    faces = model.faces[~(model.faces == 3).any(dim=1)]
    mask = torch.zeros_like(model.surface_vertex_mask)
    mask[faces.flatten()] = True
    lv, lw = model.landmark_vertices.clone(), model.landmark_weights.clone()
    lv[2], lw[2] = torch.tensor([3, 3, 3]), torch.tensor([1.0, 0.0, 0.0])
    base = dict(fields, faces=faces, surface_vertex_mask=mask)
    with pytest.raises(ValueError, match=r"landmark 2 \(.*\) lies on vertex 3 \(weight 1\), which no face uses"):
        FaceModel(**dict(base, landmark_vertices=lv, landmark_weights=lw))
    lv[2], lw[2] = torch.tensor([0, 3, 0]), torch.tensor([1.0, 0.0, 0.0])  # (at weight 0: not used)
    FaceModel(**dict(base, landmark_vertices=lv, landmark_weights=lw))
