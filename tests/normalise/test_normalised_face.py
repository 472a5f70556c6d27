"""Tests of torchface.normalise.face: canonical layout, normalised face (pose, expression and light undone)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import axis_angle_to_matrix, euler_to_matrix, matrix_to_axis_angle
from torchface.model import load_candide3
from torchface.normalise import (
    NormalisedFace,
    NormalisedFaceLayout,
    build_normalised_layout,
    normalised_face,
    normalised_face_posed,
)
from torchface.rendering.shading import LightState, render
from torchface.synth.subjects import candide_subject

G = 64  # canonical image size of the feature tests
CAM = Intrinsics.default(320, 240)
T_FRONT = torch.tensor([[0.0, 0.0, 450.0]])


@pytest.fixture(scope="module")
def model():
    return load_candide3()


@pytest.fixture(scope="module")
def subject():
    return candide_subject("james")


@pytest.fixture(scope="module")
def layout(model):
    return build_normalised_layout(model, G, 0.05)


def _zeros(model, B=1):
    return torch.zeros(B, model.num_shape), torch.zeros(B, model.num_animation)


def _render(subject, shape, alpha, aa, t, cam=CAM, ambient=1.0, dirs=None, inten=None, bg=0.5):
    """Textured Lambertian render of the CANDIDE-3 subject (same vertex order as the model)."""
    B = alpha.shape[0]
    R = axis_angle_to_matrix(aa)
    v = subject.deform(shape.expand(B, -1), alpha, B)
    verts_cam = v @ R.transpose(-1, -2) + t[:, None]
    normals_cam = subject.vertex_normals(v) @ R.transpose(-1, -2)
    amb = torch.full((B,), ambient)
    light = LightState.ambient_only(amb) if dirs is None else LightState(amb, dirs, inten)
    background = torch.full((B, 3, cam.height, cam.width), bg)
    return render(verts_cam, subject.faces, subject.uv, subject.texture, normals_cam, light, cam, background)


@pytest.fixture(scope="module")
def layout_render(model, subject, layout):
    """The textured mean shape rendered directly into the layout camera (ambient light 1)."""
    t = layout.translation[None]
    return _render(subject, torch.zeros(1, model.num_shape), torch.zeros(1, model.num_animation),
                   torch.zeros(1, 3), t, cam=layout.intrinsics, bg=0.0)  # fmt: skip


@pytest.fixture(scope="module")
def frontal(model, subject, layout):
    """A frontal, neutral, evenly lit frame of the subject and its normalised face."""
    sigma = subject.shape_coeffs[None]
    alpha = torch.zeros(1, model.num_animation)
    frame = _render(subject, sigma, alpha, torch.zeros(1, 3), T_FRONT).image
    out = normalised_face(frame, model, layout, sigma, alpha, torch.zeros(1, 3), T_FRONT, None, CAM)
    return frame, out


def _mad(a, b, mask):
    """Mean over ``mask (G, G)`` of the channel-mean absolute difference of ``(C, G, G)`` images."""
    return float((a - b).abs().mean(0)[mask].mean())


# ------------------------------------------------------------------------------------------- layout
def test_layout_cardinality_and_framing(layout):
    assert layout.mask.shape == (G, G) and layout.mask.dtype == torch.bool
    M = layout.num_pixels
    assert layout.face_index.shape == (M,) and layout.bary.shape == (M, 3) and layout.pixel_index.shape == (M,)
    assert int(layout.mask.sum()) == M
    assert torch.equal(layout.mask.reshape(-1).nonzero().squeeze(-1), layout.pixel_index)
    torch.testing.assert_close(layout.bary.sum(-1), torch.ones(M), atol=1e-5, rtol=0)
    assert bool((layout.bary >= -1e-6).all())
    # The face's bounding box fills (1 - 2 margin) G along its longer side, centred.
    rows = layout.mask.any(1).nonzero().squeeze(-1)
    cols = layout.mask.any(0).nonzero().squeeze(-1)
    span = max(int(rows[-1] - rows[0]) + 1, int(cols[-1] - cols[0]) + 1)
    assert abs(span - 0.9 * G) <= 2
    assert abs(float(rows[0] + rows[-1]) / 2 - (G - 1) / 2) <= 1.0
    assert abs(float(cols[0] + cols[-1]) / 2 - (G - 1) / 2) <= 1.0
    # The model is left-right symmetric and the layout centres its symmetry plane.
    agree = (layout.mask == layout.mask.flip(-1)).float().mean()
    assert agree > 0.99


def test_layout_follows_model_dtype(model):
    lay = build_normalised_layout(model.to(dtype=torch.float64), 16)
    assert lay.bary.dtype == torch.float64 and lay.translation.dtype == torch.float64
    assert lay.to(dtype=torch.float32).bary.dtype == torch.float32


def test_identity_round_trip_is_exact(model, layout, layout_render):
    """Normalising the layout's own render with the layout pose reproduces it pixel for pixel."""
    image = layout_render.image
    shape, alpha = _zeros(model)
    out = normalised_face(
        image, model, layout, shape, alpha, torch.zeros(1, 3), layout.translation[None], None, layout.intrinsics
    )
    assert torch.equal(out.mask[0, 0] > 0, layout.mask)
    torch.testing.assert_close(out.image, image * out.mask, atol=1e-5, rtol=0)


# ------------------------------------------------------------------------------------- cardinality
@pytest.mark.parametrize("channels", [1, 3])
def test_cardinality(model, channels):
    lay = build_normalised_layout(model, 24)
    B = 2
    shape, alpha = _zeros(model, B)
    frames = torch.rand(B, channels, CAM.height, CAM.width)
    out = normalised_face(frames, model, lay, shape, alpha, torch.zeros(B, 3), T_FRONT.expand(B, 3),
                          torch.zeros(B, 5), CAM)  # fmt: skip
    image, mask = out
    assert image.shape == (B, channels, 24, 24) and mask.shape == (B, 1, 24, 24)
    assert image.dtype == mask.dtype == torch.float32
    assert set(mask.unique().tolist()) <= {0.0, 1.0}
    assert bool((image * (1 - mask) == 0).all())
    assert bool((mask[:, 0] <= lay.mask).all())


# ----------------------------------------------------------------------------------------- features
def test_frontal_matches_direct_layout_render(layout, layout_render, frontal):
    """The normalised face of a frontal, neutral, evenly lit frame equals the model rendered into the layout."""
    _, out = frontal
    mask = out.mask[0, 0] > 0
    assert mask.sum() >= 0.95 * layout.num_pixels
    assert _mad(out.image[0], layout_render.image[0], mask) < 0.03


def _moving_region(model, layout, unit, *faces):
    """The triangles ``(F,)`` that animation unit ``unit`` moves, and the canonical pixels ``(G, G)`` on them that
    every one of ``faces`` (normalised face results) sees: the mouth region of the jaw drop."""
    moving_faces = (model.animation_units[unit].norm(dim=-1) > 0)[model.faces].any(-1)  # (F,)
    region = torch.zeros(G * G, dtype=torch.bool)
    region[layout.pixel_index[moving_faces[layout.face_index]]] = True
    region = region.reshape(G, G)
    for face in faces:
        region = region & (face.mask[0, 0] > 0)
    return moving_faces, region


def test_expression_is_undone(model, subject, layout, frontal):
    """A jaw-drop frame sampled at its own expression matches the neutral normalised face in the mouth."""
    _, neutral = frontal
    sigma = subject.shape_coeffs[None]
    jaw = model.animation_names.index("AUV11 Jaw drop")
    alpha = torch.zeros(1, model.num_animation)
    alpha[0, jaw] = 1.0
    rendered = _render(subject, sigma, alpha, torch.zeros(1, 3), T_FRONT)
    aa = torch.zeros(1, 3)
    right = normalised_face(rendered.image, model, layout, sigma, alpha, aa, T_FRONT, None, CAM)
    wrong = normalised_face(rendered.image, model, layout, sigma, torch.zeros_like(alpha), aa, T_FRONT, None, CAM)
    moving_faces, region = _moving_region(model, layout, jaw, neutral, right, wrong)
    assert region.sum() > 100
    err_right = _mad(right.image[0], neutral.image[0], region)
    err_wrong = _mad(wrong.image[0], neutral.image[0], region)
    # The raw frames, over the frame pixels showing those triangles in either frame.
    neutral_frame = _render(subject, sigma, torch.zeros_like(alpha), aa, T_FRONT)
    shown = lambda r: moving_faces[r.fragments.pix_to_face[0].clamp_min(0)] & (r.fragments.pix_to_face[0] >= 0)
    raw_region = shown(rendered) | shown(neutral_frame)
    err_raw = _mad(rendered.image[0], neutral_frame.image[0], raw_region)
    assert err_right < 0.03
    assert err_right < 0.3 * err_wrong
    assert err_right < 0.3 * err_raw


def test_keep_expression_resamples_a_state_at_the_persons_neutral(model, subject, layout, frontal):
    """``NormalisedFace(keep_expression=True)`` resamples a TrackerState's frame at the person's neutral
    (``state.neutral_anim_coeffs``), as ``LayerConfig(keep_expression=True)`` and ``torchface track
    --keep-expression`` do: a jaw-drop frame's face keeps the open jaw where the expression-free face shows the
    neutral frame's mouth. It had no such option: a user split ``state.params`` by hand (``ParamLayout(A, 5)``)."""
    from torchface.tracker.step import TrackerState, TrackResult
    from training_hooks import LayerConfig, NormalisedFaceLayer

    _, neutral_face = frontal
    sigma, aa = subject.shape_coeffs[None], torch.zeros(1, 3)
    jaw = model.animation_names.index("AUV11 Jaw drop")
    alpha = torch.zeros(1, model.num_animation)
    alpha[0, jaw] = 1.0
    frame = _render(subject, sigma, alpha, aa, T_FRONT).image
    person = torch.zeros(1, model.num_animation)  # the person's neutral (the first frame's fit): not zero
    person[0, model.animation_names.index("AUV5 Outer brow raiser")] = 0.05
    light = torch.zeros(1, 5)
    state = TrackerState(torch.cat([aa, T_FRONT, alpha, light], -1), sigma, (), CAM, 1, anim_prior_mean=person)
    kept = NormalisedFace(model, size=G, keep_expression=True)(frame, state)
    plain = NormalisedFace(model, size=G)(frame, state)
    assert torch.equal(kept.image, normalised_face(frame, model, layout, sigma, person, aa, T_FRONT, light, CAM).image)
    layer = NormalisedFaceLayer(LayerConfig(size=G, keep_expression=True), model)
    assert torch.equal(kept.image, layer.normalise(frame, state, state.params).image)  # the layer's path, to the bit
    _, region = _moving_region(model, layout, jaw, neutral_face, kept, plain)
    assert region.sum() > 100
    assert _mad(plain.image[0], neutral_face.image[0], region) < 0.03  # the expression undone
    assert _mad(kept.image[0], neutral_face.image[0], region) > 0.06  # the open jaw kept
    zeros = torch.zeros(1)
    result = TrackResult(
        rotation=axis_angle_to_matrix(aa), axis_angle=aa, translation=T_FRONT, ypr_deg=torch.zeros(1, 3),
        anim_coeffs=alpha, anim_names=model.animation_names, expression=alpha - person,
        facs=model.facs_values(alpha), facs_names=model.facs_names, illumination=light,
        illumination_names=("g", "b", "x", "y", "z"), status=zeros.long(), iterations=zeros.long(), cost=zeros,
        num_points=zeros.long(), confidence=zeros,
    )  # fmt: skip
    with pytest.raises(ValueError, match=r"a TrackResult does not hold: pass the tracker's state"):
        NormalisedFace(model, size=G, keep_expression=True)(frame, result, sigma, CAM)
    with pytest.raises(TypeError, match="keep_expression"):
        NormalisedFace(model, size=G, keep_expression="no")  # type: ignore[arg-type]


def test_light_is_undone(model, subject, layout, frontal):
    """Gain, bias and a directional light (inside the Eq. 19 model) normalise back to the reference light."""
    _, reference = frontal
    sigma = subject.shape_coeffs[None]
    alpha = torch.zeros(1, model.num_animation)
    aa = torch.zeros(1, 3)
    d = torch.tensor([[[0.3, -0.3, -0.9]]])
    d = d / d.norm(dim=-1, keepdim=True)
    ambient, strength, bias = 0.6, 0.3, 0.05
    frame = _render(subject, sigma, alpha, aa, T_FRONT, ambient=ambient, dirs=d, inten=torch.tensor([[strength]]))
    frame = frame.image + bias
    # I = albedo (a + s n.d) + b = T (1 + (a - 1) + (s d) . n) + b with T = albedo (the reference light is a = 1).
    light = torch.cat([torch.tensor([[ambient - 1.0, bias]]), strength * d[0]], dim=-1)
    fixed = normalised_face(frame, model, layout, sigma, alpha, aa, T_FRONT, light, CAM)
    kept = normalised_face(frame, model, layout, sigma, alpha, aa, T_FRONT, None, CAM)
    mask = (fixed.mask[0, 0] > 0) & (reference.mask[0, 0] > 0)
    assert mask.sum() >= 0.95 * layout.num_pixels
    err_fixed = _mad(fixed.image[0], reference.image[0], mask)
    err_kept = _mad(kept.image[0], reference.image[0], mask)
    assert err_fixed < 0.005
    assert err_fixed < 0.1 * err_kept


def test_pose_is_undone_and_self_occlusion_masked(model, subject, layout, frontal):
    _, reference = frontal
    sigma = subject.shape_coeffs[None]
    alpha = torch.zeros(1, model.num_animation)
    aa = matrix_to_axis_angle(euler_to_matrix(torch.tensor([[35.0, 10.0, 8.0]])))
    t = torch.tensor([[20.0, -10.0, 480.0]])
    frame = _render(subject, sigma, alpha, aa, t).image
    out = normalised_face(frame, model, layout, sigma, alpha, aa, t, None, CAM)
    seen = out.mask[0, 0] > 0
    common = seen & (reference.mask[0, 0] > 0)
    assert common.sum() > 0.6 * layout.num_pixels
    assert _mad(out.image[0], reference.image[0], common) < 0.03
    # The side turned away loses pixels (self-occlusion behind the nose, grazing cheek).
    assert seen.sum() < 0.95 * reference.mask.sum()
    # Seen from behind nothing is visible.
    back = matrix_to_axis_angle(euler_to_matrix(torch.tensor([[180.0, 0.0, 0.0]])))
    out_back = normalised_face(frame, model, layout, sigma, alpha, back, t, None, CAM)
    assert out_back.mask.sum() == 0 and out_back.image.abs().sum() == 0


def test_outside_and_behind_camera_are_masked_and_finite(model, layout):
    shape, alpha = _zeros(model, 3)
    frames = torch.rand(3, 3, CAM.height, CAM.width)
    t = torch.tensor([[0.0, 0.0, 450.0], [5000.0, 0.0, 450.0], [0.0, 0.0, 20.0]], requires_grad=True)
    light = torch.zeros(3, 5, requires_grad=True)
    out = normalised_face(frames, model, layout, shape, alpha, torch.zeros(3, 3), t, light, CAM)
    assert out.mask[0].sum() > 0 and out.mask[1].sum() == 0
    assert torch.isfinite(out.image).all()
    (out.image.sum() + out.mask.sum()).backward()
    assert torch.isfinite(t.grad).all() and torch.isfinite(light.grad).all()


def test_batch_equals_per_sample(model, subject, layout):
    B = 3
    sigma = subject.shape_coeffs[None].expand(B, -1).contiguous()
    gen = torch.Generator().manual_seed(3)
    alpha = 0.3 * torch.rand(B, model.num_animation, generator=gen)
    aa = matrix_to_axis_angle(euler_to_matrix(torch.tensor([[0.0, 0.0, 0.0], [20.0, -5.0, 3.0], [-25.0, 8.0, -4.0]])))
    t = torch.tensor([[0.0, 0.0, 450.0], [15.0, 5.0, 500.0], [-10.0, 0.0, 420.0]])
    light = 0.1 * torch.randn(B, 5, generator=gen)
    frames = _render(subject, sigma[:1], alpha, aa, t).image
    batched = normalised_face(frames, model, layout, sigma, alpha, aa, t, light, CAM)
    for b in range(B):
        sl = slice(b, b + 1)
        single = normalised_face(frames[sl], model, layout, sigma[sl], alpha[sl], aa[sl], t[sl], light[sl], CAM)
        torch.testing.assert_close(batched.image[sl], single.image, atol=1e-5, rtol=1e-5)
        assert torch.equal(batched.mask[sl], single.mask)


def test_given_rotation_is_the_computed_one(model, subject, layout):
    """A caller's rotation matrix (the tracker passes its result's) gives exactly the face computed from the
    axis-angle; a wrong shape is refused."""
    B = 2
    sigma = subject.shape_coeffs[None].expand(B, -1).contiguous()
    alpha = torch.zeros(B, model.num_animation)
    aa = matrix_to_axis_angle(euler_to_matrix(torch.tensor([[10.0, -5.0, 2.0], [-30.0, 8.0, -4.0]])))
    t = torch.tensor([[0.0, 0.0, 450.0], [15.0, 5.0, 500.0]])
    light = torch.tensor([[1.1, 0.02, 0.1, -0.05, 0.0], [0.9, -0.03, 0.0, 0.1, 0.05]])
    frames = _render(subject, sigma[:1], alpha, aa, t).image
    computed = normalised_face(frames, model, layout, sigma, alpha, aa, t, light, CAM)
    given = normalised_face(frames, model, layout, sigma, alpha, aa, t, light, CAM, rotation=axis_angle_to_matrix(aa))
    assert torch.equal(given.image, computed.image) and torch.equal(given.mask, computed.mask)
    with pytest.raises(ValueError, match="rotation must be"):
        normalised_face(frames, model, layout, sigma, alpha, aa, t, light, CAM, rotation=torch.eye(3))


# ----------------------------------------------------------------------------------------- gradcheck
@pytest.fixture(scope="module")
def tiny():
    """A float64 model, an 8 x 8 layout and a 24 x 20 camera seeing the face."""
    m64 = load_candide3(dtype=torch.float64)
    lay = build_normalised_layout(m64, 8, 0.1)
    cam = Intrinsics.default(24, 20)
    t = torch.tensor([[0.5, 1.0, 260.0]], dtype=torch.float64)
    return m64, lay, cam, t


def test_gradcheck_frames(tiny):
    m64, lay, cam, t = tiny
    shape = torch.zeros(1, m64.num_shape, dtype=torch.float64)
    alpha = torch.zeros(1, m64.num_animation, dtype=torch.float64)
    aa = torch.tensor([[0.05, -0.1, 0.02]], dtype=torch.float64)
    light = torch.tensor([[0.1, 0.05, 0.1, -0.05, 0.2]], dtype=torch.float64)
    frames = torch.rand(1, 2, 20, 24, dtype=torch.float64, requires_grad=True)

    def fn(f):
        return normalised_face(f, m64, lay, shape, alpha, aa, t, light, cam).image

    assert normalised_face(frames, m64, lay, shape, alpha, aa, t, light, cam).mask.sum() > 10
    # The output is linear in the pixels: the fast (random-projection) mode checks the whole Jacobian's action.
    assert torch.autograd.gradcheck(fn, (frames,), eps=1e-6, atol=1e-8, fast_mode=True)


def test_gradcheck_parameters(tiny):
    m64, lay, cam, t = tiny
    gen = torch.Generator().manual_seed(1)
    # A smooth frame, so bilinear sampling is differentiable at every sample point.
    yy, xx = torch.meshgrid(torch.arange(20.0), torch.arange(24.0), indexing="ij")
    frames = (0.5 + 0.3 * torch.sin(0.4 * xx + 0.3 * yy) * torch.cos(0.25 * yy)).to(torch.float64)[None, None]
    shape = 0.1 * torch.randn(1, m64.num_shape, generator=gen, dtype=torch.float64)

    def fn(alpha, aa, tr, light):
        return normalised_face(frames, m64, lay, shape, alpha, aa, tr, light, cam).image

    alpha = (0.2 * torch.rand(1, m64.num_animation, generator=gen, dtype=torch.float64)).requires_grad_()
    aa = torch.tensor([[0.05, -0.1, 0.02]], dtype=torch.float64, requires_grad=True)
    tr = t.clone().requires_grad_()
    light = torch.tensor([[0.1, 0.05, 0.1, -0.05, 0.2]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(fn, (alpha, aa, tr, light), eps=1e-6, atol=1e-6)


# -------------------------------------------------------------------------------------------- module
def test_module_with_track_result_and_state(model, subject, layout):
    from torchface.tracker.step import TrackerState, TrackResult

    normaliser = NormalisedFace(model, size=G, margin=0.05)
    sigma = subject.shape_coeffs[None]
    alpha = torch.zeros(1, model.num_animation)
    alpha[0, 1] = 0.5
    aa = torch.tensor([[0.0, 0.2, 0.0]])
    light = torch.tensor([[0.1, 0.02, 0.0, 0.0, 0.1]])
    frame = _render(subject, sigma, alpha, aa, T_FRONT).image
    want = normalised_face(frame, model, layout, sigma, alpha, aa, T_FRONT, light, CAM)
    zeros = torch.zeros(1)
    result = TrackResult(
        rotation=axis_angle_to_matrix(aa), axis_angle=aa, translation=T_FRONT, ypr_deg=torch.zeros(1, 3),
        anim_coeffs=alpha, anim_names=model.animation_names, expression=alpha, facs=model.facs_values(alpha),
        facs_names=model.facs_names, illumination=light, illumination_names=("g", "b", "x", "y", "z"),
        status=zeros.long(), iterations=zeros.long(), cost=zeros, num_points=zeros.long(), confidence=zeros,
    )  # fmt: skip
    got = normaliser(frame, result, sigma, CAM)
    torch.testing.assert_close(got.image, want.image)
    # Default intrinsics are Intrinsics.default of the frame size, as in FaceTracker.
    torch.testing.assert_close(normaliser(frame, result, sigma).image, want.image)
    state = TrackerState(torch.cat([aa, T_FRONT, alpha, light], -1), sigma, (), CAM, 1)
    torch.testing.assert_close(normaliser(frame, state).image, want.image)
    with pytest.raises(ValueError, match="shape_coeffs"):
        normaliser(frame, result)
    with pytest.raises(ValueError, match="from the state"):
        normaliser(frame, state, sigma)
    with pytest.raises(TypeError, match="TrackResult or a TrackerState"):
        normaliser(frame, {"axis_angle": aa})
    # A numpy frame with a result (default intrinsics) is named as one: it was "frames must be (B, C, H, W), got
    # (1, 3, H, W)", the shape it had.
    with pytest.raises(TypeError, match="torch.Tensor"):
        normaliser(frame.numpy(), result, sigma)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"got \(3, "):
        normaliser(frame[0], result, sigma)
    # Frames of another batch than the state's streams were "shape_coeffs must be (B, 14) with B=2 like frames, got
    # (1, 14)", a tensor the caller never passed; depth_tolerance / min_facing_cos out of range were accepted by the
    # constructor and refused only at the first call.
    with pytest.raises(ValueError, match=r"expected 1 frames \(one per stream of the state\), got 2"):
        normaliser(frame.expand(2, -1, -1, -1), state)
    with pytest.raises(TypeError, match="the state is torch.float32 on cpu, this normaliser's model torch.float64"):
        NormalisedFace(model.to(dtype=torch.float64), size=G)(frame, state)  # (named the state's shape_coeffs)
    for bad in (-1.0, float("inf"), float("nan")):  # (inf passed ">= 0")
        with pytest.raises(ValueError, match=r"^depth_tolerance must be a finite number >= 0 \(a fraction of the depth\), got"):
            NormalisedFace(model, size=G, depth_tolerance=bad)
    for name in ("depth_tolerance", "min_facing_cos"):  # ("5" was taken by float(), "x" a ValueError)
        with pytest.raises(TypeError, match=rf"^{name} must be a real number, got str '0.5'"):
            NormalisedFace(model, size=G, **{name: "0.5"})
    for bad in (1.0, -0.5, float("nan")):
        with pytest.raises(ValueError, match="min_facing_cos"):
            NormalisedFace(model, size=G, min_facing_cos=bad)


def test_module_moves_model_and_layout_with_to(model):
    normaliser = NormalisedFace(model, size=16).double()
    assert normaliser.model.dtype == torch.float64 and normaliser.layout.bary.dtype == torch.float64
    assert normaliser.layout.translation.dtype == torch.float64
    assert normaliser.model.faces.dtype == torch.int64 and normaliser.layout.pixel_index.dtype == torch.int64
    assert normaliser.layout.mask.dtype == torch.bool
    D = torch.float64
    out = normaliser.from_params(
        torch.rand(1, 3, CAM.height, CAM.width, dtype=D), torch.zeros(1, model.num_shape, dtype=D),
        torch.zeros(1, model.num_animation, dtype=D), torch.zeros(1, 3, dtype=D), T_FRONT.to(D), None, CAM,
    )  # fmt: skip
    assert out.image.dtype == D and out.mask.dtype == D and out.mask.sum() > 0
    assert normaliser.float().model.dtype == torch.float32 and normaliser.layout.bary.dtype == torch.float32
    assert normaliser.to(torch.float64).model.dtype == torch.float64
    assert normaliser.to(device="cpu", dtype=torch.float32).layout.translation.dtype == torch.float32
    assert model.dtype == torch.float32  # the model passed in is not changed in place


def test_nan_geometry_backward_does_not_crash_and_gradients_are_finite():
    """A NaN pose used to crash the process in grid_sample's backward: run it in a child so that a regression
    fails this test instead of the whole session. A sample with non-finite geometry is masked out whole, its
    parameters get gradient 0, and the other samples are unaffected."""
    code = textwrap.dedent("""
        import torch
        torch.set_num_threads(1)
        from torchface.geometry.camera import Intrinsics
        from torchface.model import load_candide3
        from torchface.normalise import build_normalised_layout, normalised_face
        m = load_candide3()
        lay = build_normalised_layout(m, 16)
        cam = Intrinsics.default(80, 60)
        nan = float("nan")
        for zbuffer in (True, False):
            for light in (None, torch.tensor([[0.1, 0.05, 0.1, 0.0, 0.2]]).expand(3, 5).clone()):
                aa = torch.tensor([[nan, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, 0.0]], requires_grad=True)
                t = torch.tensor([[0.0, 0.0, 450.0], [0.0, 0.0, 450.0], [0.0, float("inf"), 450.0]],
                                 requires_grad=True)
                shape = torch.zeros(3, m.num_shape, requires_grad=True)
                frames = torch.rand(3, 3, 60, 80, requires_grad=True)
                if light is not None:
                    light.requires_grad_()
                out = normalised_face(frames, m, lay, shape, torch.zeros(3, m.num_animation), aa, t, light, cam,
                                      zbuffer=zbuffer)
                (out.image * out.mask).sum().backward()
                assert out.mask.flatten(1).sum(1).tolist()[::2] == [0.0, 0.0] and out.mask[1].sum() > 0
                assert torch.isfinite(out.image).all() and out.image[0::2].abs().sum() == 0
                for x in (aa, t, shape, frames) + (() if light is None else (light,)):
                    assert torch.isfinite(x.grad).all(), x.grad
                    assert x.grad[0::2].abs().sum() == 0
                one = normalised_face(frames[1:2], m, lay, shape[1:2], torch.zeros(1, m.num_animation), aa[1:2],
                                      t[1:2], None if light is None else light[1:2], cam, zbuffer=zbuffer)
                assert torch.equal(one.mask[0], out.mask[1])
                torch.testing.assert_close(one.image[0], out.image[1])
        print("ok")
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "ok", (run.returncode, run.stderr[-2000:])


@pytest.mark.parametrize("zbuffer", [True, False])
def test_empty_batch_gives_empty_result(model, layout, zbuffer):
    shape, alpha = _zeros(model, 0)
    out = normalised_face(torch.rand(0, 3, CAM.height, CAM.width), model, layout, shape, alpha, torch.zeros(0, 3),
                          torch.zeros(0, 3), None, CAM, zbuffer=zbuffer)  # fmt: skip
    assert out.image.shape == (0, 3, G, G) and out.mask.shape == (0, 1, G, G)


# -------------------------------------------------------------------------------------------- errors
def test_errors(model, layout):
    shape, alpha = _zeros(model, 2)
    aa, t = torch.zeros(2, 3), T_FRONT.expand(2, 3)
    frames = torch.rand(2, 3, CAM.height, CAM.width)

    def call(**kw):
        args = dict(frames=frames, model=model, layout=layout, shape_coeffs=shape, anim_coeffs=alpha,
                    axis_angle=aa, translation=t, illumination=None, intrinsics=CAM)  # fmt: skip
        args.update(kw)
        return normalised_face(**args)

    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        call(frames=frames[0])
    # what to do, as the tracker says it (the message gave the shape or dtype alone)
    with pytest.raises(ValueError, match=r"got \(3, 240, 320\) torch.float32 \(one frame \(C, H, W\): frames\[None\]"):
        call(frames=frames[0])
    with pytest.raises(ValueError, match=r"torch.uint8 \(uint8 frames: pass frames.float\(\) / 255\)"):
        call(frames=(frames * 255).to(torch.uint8))
    with pytest.raises(ValueError, match="intrinsics' size"):
        call(frames=torch.rand(2, 3, 100, 100))
    # channels-last frames were told "must be 320x240 (W x H, the intrinsics' size), got 3x320", no way out
    with pytest.raises(ValueError, match=r"got 3x320 \(channels last \(B, H, W, C\): frames.permute\(0, 3, 1, 2\)\)"):
        call(frames=frames.permute(0, 2, 3, 1))
    with pytest.raises(TypeError, match="frames must be a torch.Tensor"):
        call(frames=frames.numpy())
    with pytest.raises(ValueError, match=r"shape_coeffs must be \(B, 14\)"):
        call(shape_coeffs=torch.zeros(2, 3))
    with pytest.raises(ValueError, match="B=2 like frames"):
        call(anim_coeffs=torch.zeros(1, model.num_animation))
    with pytest.raises(ValueError, match="axis_angle"):
        call(axis_angle=torch.zeros(2, 3, 3))
    with pytest.raises(TypeError, match="model's dtype"):
        call(translation=t.double())
    with pytest.raises(ValueError, match=r"illumination must be \(B, 5\)"):
        call(illumination=torch.zeros(2, 4))
    with pytest.raises(TypeError, match="intrinsics"):
        call(intrinsics=(320, 240))
    with pytest.raises(TypeError, match="layout must be"):
        call(layout=None)
    with pytest.raises(ValueError, match="triangles"):
        call(layout=dataclasses.replace(layout, num_faces=model.num_faces + 1))
    with pytest.raises(ValueError, match="min_facing_cos"):
        normalised_face(frames, model, layout, shape, alpha, aa, t, None, CAM, min_facing_cos=1.0)
    with pytest.raises(ValueError, match="size must be"):
        build_normalised_layout(model, 2)
    for bad in (32.0, "32", True):  # a wrong type is a TypeError (it was a ValueError)
        with pytest.raises(TypeError, match="size must be an int"):
            build_normalised_layout(model, bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="margin"):
        build_normalised_layout(model, 32, margin=0.6)
    with pytest.raises(ValueError, match="distance_mm"):
        build_normalised_layout(model, 32, distance_mm=10.0)
    with pytest.raises(ValueError, match=r"^distance_mm must be a finite number > 0 \(mm\), got inf"):
        build_normalised_layout(model, 32, distance_mm=float("inf"))
    with pytest.raises(TypeError, match=r"^margin must be a real number, got str '0.05'"):  # (was taken)
        build_normalised_layout(model, 32, margin="0.05")  # type: ignore[arg-type]
    # 0-d real tensors are numbers, as before session 59's checks ("must be a real number, got Tensor"): the same
    # layout and face as their Python numbers; NaN, out of range, bool and complex still refused
    zero_d = build_normalised_layout(model, 12, margin=torch.tensor(0.25), distance_mm=torch.tensor(2000))
    plain = build_normalised_layout(model, 12, margin=0.25, distance_mm=2000)
    assert zero_d.margin == plain.margin and torch.equal(zero_d.pixel_index, plain.pixel_index)
    assert torch.equal(zero_d.translation, plain.translation)
    settings = {"depth_tolerance": 0.125, "min_facing_cos": 0.25}  # (exact in float32)
    want = call(**settings)
    got = call(**{k: torch.tensor(v) for k, v in settings.items()})
    assert torch.equal(got.image, want.image) and torch.equal(got.mask, want.mask)
    assert NormalisedFace(model, size=G, depth_tolerance=torch.tensor(0.1)).depth_tolerance == float(torch.tensor(0.1))
    with pytest.raises(ValueError, match=r"^min_facing_cos must be in \[0, 1\), got nan$"):
        call(min_facing_cos=torch.tensor(float("nan")))
    with pytest.raises(ValueError, match=r"^margin must be in \[0, 0.45\] \(a fraction of the image size\), got 0.5$"):
        build_normalised_layout(model, 12, margin=torch.tensor(0.5, dtype=torch.float64))
    for bad in (torch.tensor(True), torch.tensor(0.1 + 0j), torch.tensor([0.1])):
        with pytest.raises(TypeError, match=r"^depth_tolerance must be a real number, got Tensor tensor\("):
            call(depth_tolerance=bad)
    with pytest.raises(TypeError, match="FaceModel"):
        build_normalised_layout("candide", 32)
    with pytest.raises(ValueError, match="mask must be"):
        NormalisedFaceLayout(8, 0.0, Intrinsics.default(8, 8), torch.zeros(3), 1, torch.zeros(1, dtype=torch.long),
                             torch.zeros(1, dtype=torch.long), torch.zeros(1, 3), torch.zeros(8, 8))  # fmt: skip


def test_a_numpy_integer_size_is_taken_as_an_int(model):
    """``NormalisedFace(size=np.int64(32))`` was refused ("size must be an int >= 4, got np.int64(32)") while
    :class:`Intrinsics` takes numpy integers."""
    face = NormalisedFace(model, size=np.int64(32), margin=0.1)  # type: ignore[arg-type]
    assert type(face.layout.size) is int and face.layout.size == 32
    assert face.layout.mask.shape == (32, 32)


def _posed_scene(model, subject):
    """The posed entry point's scene: the subject rendered turned 20 degrees, a light, and the camera-frame mesh
    ``normalised_face`` poses for it: ``(frame, light, verts_cam, (sigma, alpha, aa, t))``."""
    from torchface.geometry.transforms import transform_points

    sigma = subject.shape_coeffs[None]
    alpha = torch.zeros(1, model.num_animation)
    aa = matrix_to_axis_angle(euler_to_matrix(torch.tensor([[20.0, -5.0, 3.0]])))
    t = torch.tensor([[5.0, -4.0, 470.0]])
    frame = _render(subject, sigma, alpha, aa, t).image
    light = torch.tensor([[0.1, 0.02, 0.05, -0.05, 0.1]])
    verts_cam = transform_points(axis_angle_to_matrix(aa), t, model.deform(sigma, alpha))
    return frame, light, verts_cam, (sigma, alpha, aa, t)


def test_posed_entry_point_is_normalised_face_and_checks_its_mesh(model, subject, layout):
    """normalised_face_posed on the mesh normalised_face poses gives its output exactly; a mesh of the wrong
    shape or batch is a clear ValueError."""
    frame, light, verts_cam, (sigma, alpha, aa, t) = _posed_scene(model, subject)
    for zbuffer in (True, False):
        want = normalised_face(frame, model, layout, sigma, alpha, aa, t, light, CAM, zbuffer=zbuffer)
        got = normalised_face_posed(frame, model, layout, verts_cam, light, CAM, zbuffer=zbuffer)
        assert want.mask.sum() > 0.5 * layout.num_pixels
        assert torch.equal(got.image, want.image) and torch.equal(got.mask, want.mask)
    with pytest.raises(ValueError, match="verts_cam"):
        normalised_face_posed(frame, model, layout, verts_cam[:, :-1], light, CAM)
    with pytest.raises(ValueError, match="verts_cam"):
        normalised_face_posed(frame.expand(2, -1, -1, -1), model, layout, verts_cam, light, CAM)
    with pytest.raises(ValueError, match="frames"):
        normalised_face_posed(frame[0], model, layout, verts_cam, light, CAM)
    # (a numpy frame was a ValueError naming its shape, the right one, as the wrong one)
    with pytest.raises(TypeError, match=r"frames must be a torch.Tensor \(B, C, H, W\), got ndarray"):
        normalised_face_posed(frame.numpy(), model, layout, verts_cam, light, CAM)  # type: ignore[arg-type]


def test_posed_entry_point_casts_half_frames_and_names_a_light_of_another_dtype(model, subject, layout):
    """normalised_face_posed casts float16 / bfloat16 frames to the mesh's dtype, as normalised_face casts them to
    the model's: it sampled them in their own precision (images off by 6e4 without the z-buffer, 3e38 with it,
    against the same values in float32). A light of another dtype than the mesh is a TypeError naming it (was
    "expected scalar type Double but found Float" from inside the sampling), and a float64 mesh with a float64 light
    keeps working."""
    frame, light, verts_cam, _ = _posed_scene(model, subject)
    for zbuffer in (True, False):
        for dtype in (torch.float16, torch.bfloat16):
            half = frame.to(dtype)
            want = normalised_face_posed(half.float(), model, layout, verts_cam, light, CAM, zbuffer=zbuffer)
            got = normalised_face_posed(half, model, layout, verts_cam, light, CAM, zbuffer=zbuffer)
            assert want.mask.sum() > 0.5 * layout.num_pixels
            assert torch.equal(got.image, want.image) and torch.equal(got.mask, want.mask), (zbuffer, dtype)
    with pytest.raises(TypeError, match="illumination must have verts_cam's dtype"):
        normalised_face_posed(frame, model, layout, verts_cam.double(), light, CAM)
    double = normalised_face_posed(frame, model, layout, verts_cam.double(), light.double(), CAM, zbuffer=False)
    assert double.image.dtype == torch.float64 and double.mask.sum() > 0.5 * layout.num_pixels


def test_layout_vertex_weights_interpolate_like_the_barycentric_gather(model, layout):
    """The layout's (M, V) weights times per-vertex values equal the barycentric sum over each face pixel's
    triangle corners (the slow reference); they are made once per faces tensor and dtype; an empty batch gives
    an empty normalised face."""
    X = torch.randn(model.num_vertices, 5, dtype=torch.float64)
    w = layout.vertex_weights(model.faces, model.num_vertices, torch.float64)
    corners = model.faces[layout.face_index]  # (M, 3)
    want = (X[corners] * layout.bary.to(torch.float64).unsqueeze(-1)).sum(1)
    torch.testing.assert_close(w @ X, want, rtol=0, atol=1e-12)
    assert layout.vertex_weights(model.faces, model.num_vertices, torch.float64) is w
    assert layout.vertex_weights(model.faces.clone(), model.num_vertices, torch.float64) is not w
    assert layout.vertex_weights(model.faces, model.num_vertices, torch.float32).dtype == torch.float32
    empty = normalised_face_posed(torch.rand(0, 3, CAM.height, CAM.width), model, layout,
                                  torch.zeros(0, model.num_vertices, 3), None, CAM, zbuffer=False)  # fmt: skip
    assert empty.image.shape == (0, 3, G, G) and empty.mask.shape == (0, 1, G, G)


# ---------------------------------------------------------------- the native kernel against the torch code


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_native_normalised_face_without_zbuffer_equals_the_torch_code(model, subject, layout, dtype):
    """``zbuffer=False`` (template management's): the native kernel gives the torch code's image and mask, to
    rounding, with and without illumination, over poses that turn away, leave the frame and go behind the
    camera; the batch equals each stream alone."""
    from torchface import _native
    from torchface.backend import Backend
    from torchface.geometry.transforms import transform_points

    if _native.library() is None:
        pytest.skip(f"native kernels unavailable: {_native.unavailable_reason()}")
    m = load_candide3(dtype=dtype)
    lay = build_normalised_layout(m, G, 0.05)
    B = 5
    sigma = subject.shape_coeffs[None].expand(B, -1).to(dtype)
    gen = torch.Generator().manual_seed(5)
    alpha = (0.3 * torch.rand(B, m.num_animation, generator=gen)).to(dtype)
    ypr = torch.tensor([[0.0, 0.0, 0.0], [35.0, -10.0, 6.0], [-60.0, 8.0, -4.0], [10.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    aa = matrix_to_axis_angle(euler_to_matrix(ypr)).to(dtype)
    t = torch.tensor([[0.0, 0.0, 450.0], [15.0, 5.0, 500.0], [-10.0, 0.0, 420.0], [260.0, 0.0, 450.0],
                      [0.0, 0.0, -200.0]], dtype=dtype)  # fmt: skip
    frames = _render(subject, subject.shape_coeffs[None], alpha.float(), aa.float(), t.float()).image.to(dtype)
    verts = transform_points(axis_angle_to_matrix(aa), t, m.deform(sigma, alpha))
    light = (0.1 * torch.randn(B, 5, generator=gen)).to(dtype)
    for illum in (None, light):
        nat = normalised_face_posed(frames, m, lay, verts, illum, CAM, zbuffer=False, min_facing_cos=0.6,
                                    backend=Backend.NATIVE)  # fmt: skip
        ref = normalised_face_posed(frames, m, lay, verts, illum, CAM, zbuffer=False, min_facing_cos=0.6,
                                    backend=Backend.TORCH)  # fmt: skip
        assert torch.equal(nat.mask, ref.mask)
        tol = 1e-10 if dtype == torch.float64 else 1e-5
        torch.testing.assert_close(nat.image, ref.image, rtol=0, atol=tol)
        counts = nat.mask.sum((1, 2, 3))
        assert float(counts[0]) > 0.6 * lay.num_pixels and 0 < float(counts[2]) < float(counts[0])
        assert float(counts[4]) == 0.0 and float(counts[3]) < float(counts[0])  # behind the camera; half out
        for b in (1, 3):
            one = normalised_face_posed(frames[b : b + 1], m, lay, verts[b : b + 1], None if illum is None else
                                        illum[b : b + 1], CAM, zbuffer=False, min_facing_cos=0.6,
                                        backend=Backend.NATIVE)  # fmt: skip
            assert torch.equal(one.image[0], nat.image[b]) and torch.equal(one.mask[0], nat.mask[b])
    with pytest.raises(RuntimeError, match="z-buffer"):
        normalised_face_posed(frames, m, lay, verts, None, CAM, backend=Backend.NATIVE)


def test_image_is_zero_where_mask_is_zero_on_nan_input_torch_and_native(model, layout):
    """NaN frame pixels and NaN parameters: image 0 wherever mask is 0, the same in the torch and native paths."""
    from torchface import _native
    from torchface.backend import Backend

    shape, alpha = _zeros(model, 3)
    frames = torch.rand(3, 3, CAM.height, CAM.width)
    frames[0] = float("nan")  # a NaN frame seen at a large yaw (turned-away pixels are masked)
    frames[1, :, :, : CAM.width // 2] = float("nan")  # half a frame
    aa = torch.tensor([[0.0, 0.9, 0.0], [0.0, 0.3, 0.0], [float("nan"), 0.0, 0.0]])
    t = T_FRONT.expand(3, 3)
    backends = [Backend.TORCH] + ([Backend.NATIVE] if _native.library() is not None else [])
    outs = [normalised_face(frames, model, layout, shape, alpha, aa, t, None, CAM, zbuffer=False, backend=b)
            for b in backends]  # fmt: skip
    for out in outs:
        off = out.mask.expand_as(out.image) == 0
        assert off.any() and out.image[off].eq(0).all()  # 0 exactly, not NaN
        assert out.mask[2].sum() == 0 and out.mask[0].sum() == 0  # NaN frame pixels are not seen
        assert 0 < out.mask[1].sum() < out.mask.shape[-1] ** 2
    if len(outs) == 2:
        assert torch.equal(outs[0].mask, outs[1].mask)
        torch.testing.assert_close(outs[0].image, outs[1].image, rtol=0, atol=1e-4, equal_nan=True)


@pytest.mark.parametrize("illumination", [False, True])
def test_nan_frame_pixels_are_masked_as_not_seen_torch_and_native(model, layout, illumination):
    """A NaN block of frame pixels on the face is missing data (the tracker takes NaN pixels so): the normalised
    face has mask 0 there and no NaN anywhere; elsewhere it is the face of the same frame with the block filled.
    It used to carry the NaN with mask 1, which template management's dissimilarity read as displaced patches: a
    30-pixel NaN block on a rightly tracked face gave confidence 0.02, and the stream was declared lost."""
    from torchface import _native
    from torchface.backend import Backend

    shape, alpha = _zeros(model, 2)
    filled = torch.rand(2, 3, CAM.height, CAM.width, generator=torch.Generator().manual_seed(0))
    frames = filled.clone()
    frames[0, :, 105:135, 145:175] = float("nan")  # on the face of stream 0; stream 1 is finite
    aa, t = torch.tensor([[0.0, 0.2, 0.0], [0.0, 0.2, 0.0]]), T_FRONT.expand(2, 3)
    light = torch.tensor([[0.1, -0.05, 0.1, 0.0, 0.2]]).expand(2, 5) if illumination else None
    backends = [Backend.TORCH] + ([Backend.NATIVE] if _native.library() is not None else [])
    for backend in backends:
        out = normalised_face(frames, model, layout, shape, alpha, aa, t, light, CAM, zbuffer=False, backend=backend)
        ref = normalised_face(filled, model, layout, shape, alpha, aa, t, light, CAM, zbuffer=False, backend=backend)
        assert bool(torch.isfinite(out.image).all()), backend
        lost = (ref.mask > 0) & (out.mask == 0)
        assert lost[0].sum() > 100 and lost[1].sum() == 0, backend  # the block's pixels, in stream 0 only
        assert bool((out.mask <= ref.mask).all())
        seen = out.mask.expand_as(out.image) > 0
        assert torch.equal(out.image[seen], ref.image[seen]) and out.image[~seen].eq(0).all()


def test_a_model_wound_inward_is_told_what_the_canonical_view_needs():
    """A FaceModel built directly (not through load_mesh_model, which checks it) with its triangles wound inward:
    the error said "degenerate model?"; it says what the canonical view needs."""
    from torchface.normalise.face import build_normalised_layout

    model = load_candide3()
    inward = dataclasses.replace(model, faces=model.faces.flip(-1).contiguous())
    with pytest.raises(ValueError, match="wound outward"):
        build_normalised_layout(inward, size=32)
    assert build_normalised_layout(model, size=32) is not None


def _nan_block_face(backend, nan: bool):
    from torchface.normalise.face import build_normalised_layout, normalised_face

    model = load_candide3()
    layout = build_normalised_layout(model, 32, backend=backend)
    cam = Intrinsics.default(160, 160)
    frames = torch.rand(1, 3, 160, 160, generator=torch.Generator().manual_seed(0))
    if nan:
        frames[:, :, 70:90, 70:90] = float("nan")
    aa = torch.zeros(1, 3, requires_grad=True)
    t = torch.tensor([[0.0, 0.0, 600.0]], requires_grad=True)
    out = normalised_face(frames, model, layout, torch.zeros(1, model.num_shape), torch.zeros(1, model.num_animation),
                          aa, t, None, cam, backend=backend)  # fmt: skip
    return out, aa, t


def test_nan_frame_pixels_give_finite_gradients():
    """NaN (missing) frame pixels were masked in the output but still sampled: the backward pass gave 0 * NaN = NaN
    for the pose (and shape) gradients. They are finite now, and the output is the one the NaN-free part of the
    frame gives."""
    from torchface.backend import Backend

    out, aa, t = _nan_block_face(Backend.TORCH, nan=True)
    clean, _, _ = _nan_block_face(Backend.TORCH, nan=False)
    assert 0 < int((out.mask == 0).sum()) and int(out.mask.sum()) < int(clean.mask.sum())  # the block is not seen
    seen = out.mask.bool().expand_as(out.image)
    torch.testing.assert_close(out.image[seen], clean.image[seen], rtol=0, atol=0)
    out.image.sum().backward()
    assert bool(torch.isfinite(aa.grad).all()) and bool(torch.isfinite(t.grad).all()), (aa.grad, t.grad)


def test_torch_backend_z_buffer_runs_no_native_kernel(monkeypatch):
    """``normalised_face(backend=Backend.TORCH)`` with its default z-buffer ran the native coverage kernel."""
    from torchface import _native
    from torchface.backend import Backend

    ran = []
    real = _native.run
    monkeypatch.setattr(_native, "run", lambda kernel, *args: (ran.append(kernel), real(kernel, *args))[1])
    _nan_block_face(Backend.TORCH, nan=False)
    assert ran == []


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_a_half_precision_normaliser_says_it_needs_float32(model, dtype):
    """``.half()`` of a network holding a NormalisedFace: the float16 resampling lost the face without a sign (a
    frontal face gave mask 0 everywhere, image all 0). Now the module, the functions and the layout builder raise a
    TypeError that names the fix, as NormalisedFaceLayer does."""
    from torchface.normalise.face import normalised_face_posed

    normaliser = NormalisedFace(model, size=16).to(dtype)
    shape, alpha = (x.to(dtype) for x in _zeros(model, 1))
    frames = torch.rand(1, 3, CAM.height, CAM.width, dtype=dtype, requires_grad=True)
    aa, t = torch.zeros(1, 3, dtype=dtype), T_FRONT.to(dtype)
    with pytest.raises(TypeError, match="float32 or float64.*module.float"):
        normaliser.from_params(frames, shape, alpha, aa, t, None, CAM)
    verts = torch.zeros(1, model.num_vertices, 3, dtype=dtype)
    with pytest.raises(TypeError, match="float32 or float64"):
        normalised_face_posed(frames, normaliser.model, normaliser.layout, verts, None, CAM)
    with pytest.raises(TypeError, match="float32 or float64"):
        build_normalised_layout(normaliser.model, size=16)
    out = normaliser.float().from_params(frames.float(), shape.float(), alpha.float(), aa.float(), t.float(), None, CAM)
    assert out.mask.sum() > 100  # the float32 module sees the face


def test_under_torch_compile_the_normalised_face_is_the_torch_codes():
    """Under ``torch.compile`` without gradients the native kernels (the face's sampling without the z-buffer, the
    rasterizer's z-buffer) were traced with the traced tensors' pointers: wrong faces without a sign (0.37 off) and,
    with the z-buffer, a crash of the process. Run in a child so that a regression fails this test only; the compiled
    face is now the eager torch code's, bit for bit (no native kernel runs while torch.compile traces)."""
    code = textwrap.dedent("""
        import torch
        torch.set_num_threads(1)
        from torchface.backend import Backend
        from torchface.geometry.camera import Intrinsics
        from torchface.model import load_candide3
        from torchface.normalise import build_normalised_layout, normalised_face
        m = load_candide3()
        lay = build_normalised_layout(m, 16)
        cam = Intrinsics.default(64, 48)
        frames = torch.rand(2, 3, 48, 64, generator=torch.Generator().manual_seed(0))
        shape, alpha = torch.zeros(2, m.num_shape), torch.zeros(2, m.num_animation)
        aa = torch.tensor([[0.05, 0.1, 0.0], [0.0, -0.1, 0.02]])
        t = torch.tensor([[0.0, 0.0, 400.0]]).expand(2, 3)
        light = torch.tensor([[0.1, 0.05, 0.1, 0.2, -0.1]]).expand(2, 5)
        for zbuffer in (False, True):
            def face(fr, backend=Backend.AUTO):
                return normalised_face(fr, m, lay, shape, alpha, aa, t, light, cam, zbuffer=zbuffer, backend=backend)
            with torch.no_grad():
                ref = face(frames, Backend.TORCH)
                torch._dynamo.reset()
                out = torch.compile(face, backend="eager")(frames)  # the torch code (use_native: not under compile)
                assert torch.equal(out.image, ref.image) and torch.equal(out.mask, ref.mask)
                assert out.mask.sum() > 100
        print("ok")
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=240)
    assert run.returncode == 0 and run.stdout.strip() == "ok", (run.returncode, run.stderr[-2000:])


def test_torch_func_grad_and_jacrev_equal_autograd():
    """``torch.func.grad`` / ``jacrev`` (per-sample gradients, Jacobians) of the face with its default z-buffer
    raised "Cannot access data pointer of Tensor that doesn't have storage" from the native rasterizer, which was
    given torch.func's wrapped tensors: the torch z-buffer (the same fragments) serves them now. Under torch 2.11
    ``jacrev`` raised inside torch's ``grid_sample`` backward (session 57): gathered corners serve it there."""
    from torch.func import grad, jacrev

    D = torch.float64
    model = load_candide3(dtype=D)
    layout = build_normalised_layout(model, 12)
    cam = Intrinsics.default(64, 48)
    frames = torch.rand(2, 3, 48, 64, dtype=D, generator=torch.Generator().manual_seed(0))
    shape, alpha = torch.zeros(2, model.num_shape, dtype=D), torch.zeros(2, model.num_animation, dtype=D)
    aa = torch.tensor([[0.05, 0.1, 0.0], [0.0, -0.1, 0.02]], dtype=D)
    t = torch.tensor([[0.0, 0.0, 400.0]], dtype=D).expand(2, 3)
    light = torch.tensor([[0.1, 0.05, 0.1, 0.2, -0.1]], dtype=D).expand(2, 5)

    def face(fr, a):
        return normalised_face(fr, model, layout, shape, alpha, a, t, light, cam).image

    fr, a = frames.clone().requires_grad_(), aa.clone().requires_grad_()
    ref_fr, ref_a = torch.autograd.grad(face(fr, a).sum(), (fr, a))
    got_fr, got_a = grad(lambda x, y: face(x, y).sum(), argnums=(0, 1))(frames, aa)
    assert torch.equal(got_a, ref_a) and torch.equal(got_fr, ref_fr) and ref_a.abs().sum() > 0
    jac = jacrev(lambda y: face(frames, y))(aa)
    torch.testing.assert_close(jac, torch.autograd.functional.jacobian(lambda y: face(frames, y), aa))


def test_vmap_over_frames_and_light_equals_the_batch_and_forward_mode_is_refused():
    """What the module docstring says of the other ``torch.func`` transforms: ``vmap`` over the frames or the light
    gives the batched call's faces; forward mode (``jvp``) raises torch's error for ``grid_sample``."""
    from torch.func import jvp, vmap

    D = torch.float64
    model = load_candide3(dtype=D)
    layout = build_normalised_layout(model, 12)
    cam = Intrinsics.default(64, 48)
    frames = torch.rand(3, 3, 48, 64, dtype=D, generator=torch.Generator().manual_seed(1))
    shape, alpha = torch.zeros(1, model.num_shape, dtype=D), torch.zeros(1, model.num_animation, dtype=D)
    aa, t = torch.tensor([[0.05, 0.1, 0.0]], dtype=D), torch.tensor([[0.0, 0.0, 400.0]], dtype=D)
    light = torch.tensor([[0.1, 0.05, 0.1, 0.2, -0.1], [0.0, 0.0, 0.0, 0.0, 0.0], [-0.2, 0.1, 0.0, 0.1, 0.1]], dtype=D)

    def face(fr, li):
        return normalised_face(fr, model, layout, shape.expand(fr.shape[0], -1), alpha.expand(fr.shape[0], -1),
                               aa.expand(fr.shape[0], -1), t.expand(fr.shape[0], -1), li, cam).image  # fmt: skip

    want = face(frames, light)
    assert want.abs().sum() > 0
    torch.testing.assert_close(vmap(lambda f, li: face(f[None], li[None])[0])(frames, light), want, rtol=0, atol=1e-12)
    with pytest.raises(NotImplementedError, match="grid_sampler"):
        jvp(lambda f: face(f, light), (frames,), (torch.ones_like(frames),))


def test_a_compiled_face_does_not_recompile_at_each_pose():
    """Under ``torch.compile`` the z-buffer window fitted to the face (its size and offset read from the data) made
    dynamo recompile at nearly every new pose, up to its recompile limit; the compiled face uses the whole frame
    (the same visibility) and settles after the first calls."""
    import torch._dynamo
    from torch._dynamo.utils import counters

    shape, alpha = _zeros(model := load_candide3(), 2)
    layout = build_normalised_layout(model, 12)
    cam = Intrinsics.default(64, 48)

    def face(frames, aa, t):
        return normalised_face(frames, model, layout, shape, alpha, aa, t, None, cam)

    torch._dynamo.reset()
    counters.clear()
    compiled = torch.compile(face, backend="aot_eager")  # (the "eager" backend did settle)
    gen = torch.Generator().manual_seed(0)
    graphs = []
    for _ in range(7):
        frames = torch.rand(2, 3, 48, 64, generator=gen)
        aa = ((torch.rand(2, 3, generator=gen) - 0.5) * 0.4).requires_grad_()
        t = torch.tensor([[0.0, 0.0, 300.0]]) + torch.rand(2, 3, generator=gen) * torch.tensor([20.0, 20.0, 200.0])
        out, ref = compiled(frames, aa, t), face(frames, aa, t)
        assert torch.equal(out.mask, ref.mask) and torch.equal(out.image, ref.image) and ref.mask.sum() > 0
        graphs.append(counters["stats"]["unique_graphs"])
    torch._dynamo.reset()
    assert graphs[-1] == graphs[2], graphs  # no new graph after the third call


def test_a_first_call_in_inference_mode_does_not_break_later_gradients(model):
    """A validation pass first (Lightning's sanity check runs under ``torch.inference_mode``) cached the layout's
    vertex weights as an inference tensor: every later differentiable call with respect to the pose then raised
    "Inference tensors cannot be saved for backward". The cache is made as a normal tensor."""
    normaliser = NormalisedFace(model, size=16)
    shape, alpha = _zeros(model, 1)
    frames = torch.rand(1, 3, CAM.height, CAM.width, generator=torch.Generator().manual_seed(0))
    aa = torch.tensor([[0.05, 0.1, 0.0]])
    with torch.inference_mode():
        first = normaliser.from_params(frames, shape, alpha, aa, T_FRONT, None, CAM)
    pose = aa.clone().requires_grad_()
    out = normaliser.from_params(frames, shape, alpha, pose, T_FRONT, None, CAM)
    (grad,) = torch.autograd.grad(out.image.sum(), pose)
    assert torch.equal(out.image, first.image) and bool(torch.isfinite(grad).all()) and grad.abs().sum() > 0


@pytest.mark.parametrize("zbuffer", [True, False])
def test_missing_frame_pixels_give_finite_pose_and_light_gradients(model, zbuffer):
    """NaN (missing) frame pixels on the face are masked out, as documented, but the pose and light gradients were
    NaN (the sampling's backward multiplied the masked pixels' zero gradient by the NaN): one missing patch made a
    training step's whole update NaN. The gradients are finite and the face and mask unchanged."""
    from torchface.backend import Backend

    shape, alpha = _zeros(model, 2)
    frames = torch.rand(2, 3, CAM.height, CAM.width, generator=torch.Generator().manual_seed(0))
    frames[0, :, 105:135, 145:175] = float("nan")  # on the face of stream 0
    aa = torch.tensor([[0.0, 0.2, 0.0], [0.05, -0.1, 0.0]], requires_grad=True)
    light = torch.tensor([[0.1, -0.05, 0.1, 0.0, 0.2]]).repeat(2, 1).requires_grad_()
    out = normalised_face(frames, model, layout_of(model), shape, alpha, aa, T_FRONT.expand(2, 3), light, CAM,
                          zbuffer=zbuffer)  # fmt: skip
    grads = torch.autograd.grad(out.image.sum(), (aa, light))
    assert all(bool(torch.isfinite(g).all()) and g.abs().sum() > 0 for g in grads), grads
    with torch.no_grad():
        ref = normalised_face(frames, model, layout_of(model), shape, alpha, aa, T_FRONT.expand(2, 3), light, CAM,
                              zbuffer=zbuffer, backend=Backend.TORCH)  # fmt: skip
    assert torch.equal(out.mask, ref.mask) and torch.equal(out.image, ref.image)
    full = normalised_face(frames.nan_to_num(0.5), model, layout_of(model), shape, alpha, aa.detach(),
                           T_FRONT.expand(2, 3), light.detach(), CAM, zbuffer=zbuffer)  # fmt: skip
    assert 0 < float(out.mask[0].sum()) < float(full.mask[0].sum())  # the patch is masked out, the rest seen


def layout_of(model, size=16):
    return build_normalised_layout(model, size)


def test_the_normalised_face_is_frontal_upright_and_not_mirrored(model, layout):
    """Known answers for the canonical view's orientation, from the frame's pixels, not from the layout's own camera:
    a frame whose image-left half is dark (the subject's right side, facing the camera) gives a face dark on its
    left; one dark above the eyes gives a face dark at its top. The subject's right eye (iBUG 37-42) is then on
    the image's left and the brows above the eyes above the mouth."""
    shape, alpha = _zeros(model)
    aa, t = torch.zeros(1, 3), T_FRONT
    u = torch.arange(CAM.width, dtype=torch.float32)
    v = torch.arange(CAM.height, dtype=torch.float32)
    split_u = torch.where(u < CAM.cx, 0.2, 0.8).expand(1, 3, CAM.height, CAM.width)
    eyes_v = CAM.cy + CAM.fy * float(model.landmarks_3d(model.deform())[0, 36:48, 1].mean()) / float(t[0, 2])
    split_v = torch.where(v < eyes_v, 0.2, 0.8)[:, None].expand(1, 3, CAM.height, CAM.width)
    half, every = G // 2, slice(None)
    left, right = (every, slice(0, half)), (every, slice(half, None))
    top, low = (slice(0, half // 2), every), (slice(half + 8, None), every)  # above the eyes; below them
    for frame, near, far in ((split_u, left, right), (split_v, top, low)):
        out = normalised_face(frame, model, layout, shape, alpha, aa, t, None, CAM)
        face, mask = out.image[0, 0], out.mask[0, 0] > 0
        assert bool(mask[near].any()) and bool(mask[far].any())
        assert torch.allclose(face[near][mask[near]], torch.tensor(0.2)), "mirrored or upside down"
        assert torch.allclose(face[far][mask[far]], torch.tensor(0.8)), "mirrored or upside down"
    lm = model.landmarks_3d(model.deform())[0] + layout.translation  # the canonical view's camera frame
    px = layout.intrinsics.fx * lm[:, :2] / lm[:, 2:] + torch.tensor([layout.intrinsics.cx, layout.intrinsics.cy])
    assert (px[36:42, 0] < half).all() and (px[42:48, 0] > half).all()  # subject's right eye on the image's left
    assert px[17:27, 1].max() < px[36:48, 1].min() and px[36:48, 1].max() < px[48:68, 1].min()  # brows, eyes, mouth


def test_frames_outside_0_1_are_refused_like_the_tracker_steps_refuse_them(model, subject, layout):
    """0-255 frames were normalised without a word (the light's bias, in [0, 1] units, then undone 255 times too
    weakly) where the tracker's steps refuse them: the module, ``normalised_face`` and ``normalised_face_posed``
    now say so, with the steps' message; NaN and infinite pixels (missing data) are still masked, not refused."""
    from torchface.tracker.step import TrackerState

    sigma = subject.shape_coeffs[None]
    alpha = torch.zeros(1, model.num_animation)
    light = torch.tensor([[0.1, 0.02, 0.0, 0.0, 0.1]])
    frame = _render(subject, sigma, alpha, torch.zeros(1, 3), T_FRONT).image
    state = TrackerState(torch.cat([torch.zeros(1, 3), T_FRONT, alpha, light], -1), sigma, (), CAM, 1)
    normaliser = NormalisedFace(model, size=G, margin=0.05)
    for bad in (frame * 255, frame - 1.0):
        with pytest.raises(ValueError, match=r"frames must be float in \[0, 1\], got values from"):
            normaliser(bad, state)
        with pytest.raises(ValueError, match=r"in \[0, 1\]"):
            normalised_face(bad, model, layout, sigma, alpha, torch.zeros(1, 3), T_FRONT, light, CAM)
        verts_cam = model.deform(sigma, alpha) + T_FRONT[:, None]
        with pytest.raises(ValueError, match=r"in \[0, 1\]"):
            normalised_face_posed(bad, model, layout, verts_cam, light, CAM)
    with pytest.raises(ValueError, match="divide by 255"):
        normaliser(frame * 255, state)
    # Template management passes frames its step checked: check_values=False looks at nothing.
    out = normalised_face(frame * 255, model, layout, sigma, alpha, torch.zeros(1, 3), T_FRONT, None, CAM,
                          check_values=False)  # fmt: skip
    torch.testing.assert_close(out.image, 255 * normalised_face(frame, model, layout, sigma, alpha, torch.zeros(1, 3),
                                                                T_FRONT, None, CAM).image)  # fmt: skip
    holed = frame.clone()
    holed[..., 100:140, 140:180] = float("nan")
    holed[..., 0, 0] = float("inf")
    out = normaliser(holed, state)
    assert bool(torch.isfinite(out.image).all()) and 0 < float(out.mask.sum()) < float(normaliser(frame, state).mask.sum())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_z_buffered_face_from_the_coverage_equals_every_pixels_fragments(model, subject, dtype, monkeypatch):
    """With the native kernels (``Backend.AUTO``) the z-buffer test takes the coverage alone and evaluates the depth at
    the layout's points' pixels (``rasterize_coverage``, the native visibility test), not the fragments of every
    covered pixel of the face's window (``rasterize``; 3.5 -> 1.1 ms a 640x480 frame in ``torchface track``): the
    same image and mask, bit for bit, as the torch code's fragments, over poses whose far side the nose and cheek
    hide, one that leaves the frame and one behind the camera, with and without illumination; so does the torch
    code's coverage and test at the points (where no native kernel is built)."""
    import torchface.normalise.face as face_module
    import torchface.rendering.visibility as visibility
    from torchface import _native
    from torchface.backend import Backend

    if _native.library() is None:
        pytest.skip(f"native kernels unavailable: {_native.unavailable_reason()}")
    m = load_candide3(dtype=dtype)
    lay = build_normalised_layout(m, 96, 0.05)
    B = 5
    sigma = subject.shape_coeffs[None].expand(B, -1).to(dtype)
    gen = torch.Generator().manual_seed(7)
    alpha = (0.3 * torch.rand(B, m.num_animation, generator=gen)).to(dtype)
    ypr = torch.tensor([[0.0, 0.0, 0.0], [55.0, -10.0, 6.0], [-70.0, 8.0, -4.0], [10.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    aa = matrix_to_axis_angle(euler_to_matrix(ypr)).to(dtype)
    t = torch.tensor([[0.0, 0.0, 450.0], [15.0, 5.0, 500.0], [-10.0, 0.0, 420.0], [260.0, 0.0, 450.0],
                      [0.0, 0.0, -200.0]], dtype=dtype)  # fmt: skip
    frames = _render(subject, subject.shape_coeffs[None], alpha.float(), aa.float(), t.float()).image.to(dtype)
    light = (0.1 * torch.randn(B, 5, generator=gen)).to(dtype)
    for illum in (None, light):
        ref = normalised_face(frames, m, lay, sigma, alpha, aa, t, illum, CAM, backend=Backend.TORCH)
        with monkeypatch.context() as mp:  # (the fragments of every covered pixel are not evaluated)
            mp.setattr(face_module, "rasterize", lambda *a, **k: pytest.fail("rasterize called"))
            out = normalised_face(frames, m, lay, sigma, alpha, aa, t, illum, CAM)
        assert torch.equal(out.mask, ref.mask) and torch.equal(out.image, ref.image)
        with monkeypatch.context() as mp:  # the coverage and the test at the points by the torch code (no compiler)
            mp.setattr(face_module, "rasterize", lambda *a, **k: pytest.fail("rasterize called"))
            cover = face_module.rasterize_coverage
            mp.setattr(face_module, "rasterize_coverage", lambda *a, **k: cover(*a, **{**k, "backend": Backend.TORCH}))
            mp.setattr(visibility, "_native_visible", lambda *a, **k: None)
            out = normalised_face(frames, m, lay, sigma, alpha, aa, t, illum, CAM)
        assert torch.equal(out.mask, ref.mask) and torch.equal(out.image, ref.image)
        counts = ref.mask.sum((1, 2, 3))
        full = float(counts[0])
        assert full > 0.6 * lay.num_pixels and 0 < float(counts[1]) < full and 0 < float(counts[2]) < full
        assert 0 < float(counts[3]) < full and float(counts[4]) == 0.0
        # The far side is hidden by the z-buffer itself, not only by the facing tests.
        facing = normalised_face(frames, m, lay, sigma, alpha, aa, t, illum, CAM, zbuffer=False)
        assert float(facing.mask[1:3].sum()) > float(ref.mask[1:3].sum())


def test_settings_assigned_after_construction_are_checked(model):
    """``keep_expression``, ``depth_tolerance`` and ``min_facing_cos`` assigned to a ``NormalisedFace`` are checked
    as the constructor checks them (as ``FaceTracker`` checks its settings): ``keep_expression = "no"`` was taken as
    given, and kept the expression (a non-empty string is true). A refused value leaves the setting as it was; a good
    one is taken (a NumPy bool as a bool)."""
    normaliser = NormalisedFace(model, size=32)
    for name, bad, error, message in (
        ("keep_expression", "no", TypeError, "keep_expression must be a bool, got str 'no'"),
        ("keep_expression", 1, TypeError, "keep_expression must be a bool, got int 1"),
        ("depth_tolerance", "5", TypeError, "depth_tolerance must be a real number"),
        ("depth_tolerance", -0.1, ValueError, "depth_tolerance"),
        ("min_facing_cos", 1.0, ValueError, r"min_facing_cos must be in \[0, 1\)"),
    ):
        before = getattr(normaliser, name)
        with pytest.raises(error, match=message):
            setattr(normaliser, name, bad)
        assert getattr(normaliser, name) == before, name
    normaliser.keep_expression, normaliser.depth_tolerance, normaliser.min_facing_cos = np.bool_(True), 0.1, 0.3
    assert normaliser.keep_expression is True and normaliser.depth_tolerance == 0.1 and normaliser.min_facing_cos == 0.3


def test_flags_must_be_bools(model, layout):
    """normalised_face and normalised_face_posed took zbuffer and check_values by truth: zbuffer="no" ran the
    z-buffer test, check_values="no" checked the frames (0 skipped the check). check_bool's rule, as the settings'."""
    frames = torch.rand(1, 3, 240, 320)
    S, A = _zeros(model)
    verts_cam = model.deform(S, A) + T_FRONT[:, None]
    for flag in ("zbuffer", "check_values"):
        for value in ("no", 0, None):
            with pytest.raises(TypeError, match=f"^{flag} must be a bool, got"):
                normalised_face(frames, model, layout, S, A, torch.zeros(1, 3), T_FRONT, None, CAM, **{flag: value})
            with pytest.raises(TypeError, match=f"^{flag} must be a bool, got"):
                normalised_face_posed(frames, model, layout, verts_cam, None, CAM, **{flag: value})
    got = normalised_face(frames, model, layout, S, A, torch.zeros(1, 3), T_FRONT, None, CAM, zbuffer=np.bool_(False))
    want = normalised_face(frames, model, layout, S, A, torch.zeros(1, 3), T_FRONT, None, CAM, zbuffer=False)
    assert torch.equal(got.image, want.image)


def test_normalised_face_keeps_a_callers_cpu_autocast_out(model, layout):
    """normalised_face is @full_precision: under a caller's CPU autocast (bfloat16) it gives the float32 face of full
    precision, the same as without it (a helper defined between the decorator and the function once took the
    decorator away, and no test said so)."""
    frames = torch.rand(1, 3, 240, 320, generator=torch.Generator().manual_seed(0))
    S, A = _zeros(model)
    args = (frames, model, layout, S, A, torch.tensor([[0.05, -0.1, 0.02]]), T_FRONT, None, CAM)
    want = normalised_face(*args).image
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = normalised_face(*args).image
    assert got.dtype == torch.float32 and torch.equal(got, want)
