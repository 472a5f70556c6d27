"""Tests of training_hooks.layer: the normalised-face layer with detached and unrolled tracking.

Gradients are checked in float64 against finite differences (``torch.autograd.gradcheck``) on a 32x32 frame
with an 80-point template, probing a few pixels the template samples (the full frame would be slow). The
known answers: ``K = 0`` is the detached mode exactly, and from a converged reference solve the unrolled
Gauss-Newton steps stay at the tracker's estimate (same objective, same fixed point), while their gradient
differs from the detached one (the tracking contributes).
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap
from dataclasses import replace

import pytest
import torch

from torchface._compiling import transforms_read_values
from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import project_points
from torchface.geometry.so3 import euler_to_matrix
from torchface.model.candide import load_candide3
from torchface.normalise import normalised_face
from torchface.synth.background import BackgroundSpec
from torchface.synth.scenarios import default_light
from torchface.synth.sequence import SequenceSpec, render_sequence
from torchface.tracker import FitConfig, TrackerConfig, warp_points
from training_hooks.hooks import confidence_weighted_loss, drop_low_confidence
from training_hooks.layer import LayerConfig, LayerMode, NormalisedFaceLayer, UnrollStart, unrolled_params
from training_hooks.transforms import FaceTrackingConfig, NormaliseFaces

D = torch.float64
G = 12  # canonical image size of the gradient tests
SMALL = TrackerConfig(
    num_levels=1, max_points=80, iterations=(4,), min_points=10, robust_scale_floor=(0.02, 0.02),
    fit=FitConfig(shape_prior_precision=0.0, held_shape_units=(), fit_expression=True, expression_prior_precision=2.0),
)


def _clip(size: int, num_frames: int = 2, jaw: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A short CANDIDE-3 clip, face ~``size`` px wide: a small turn and shift; jaw drop ramping to ``jaw``."""
    s = torch.linspace(0.0, 1.0, num_frames, dtype=D)[:, None]
    model = load_candide3()
    anim = torch.zeros(num_frames, model.num_animation, dtype=D)
    anim[:, model.animation_names.index("AUV11 Jaw drop")] = jaw * s[:, 0]
    spec = SequenceSpec(
        name="layer", subject="candide3", intrinsics=Intrinsics.default(size, size),
        rotation=euler_to_matrix(s * torch.tensor([6.0, 3.0, 2.0], dtype=D)),
        translation=torch.tensor([0.0, 5.0, 170.0], dtype=D) + s * torch.tensor([1.0, 0.0, 0.0], dtype=D),
        anim=anim, light=default_light(num_frames), background=BackgroundSpec(seed=3),
    )  # fmt: skip
    frames, gt = render_sequence(spec)
    return frames.to(D), gt.landmarks_px.to(D)


@pytest.fixture(scope="module")
def model():
    return load_candide3(dtype=D)


@pytest.fixture(scope="module")
def small(model):
    """32x32 clip, its state after frame 0, and pixels (x, y) that frame 1's template points sample."""
    frames, landmarks = _clip(32)
    layer = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL), model)
    state, _ = layer.initialise(frames[:1], landmarks[:1])
    _, cam, _ = warp_points(state.templates[0], layer.param_layout, state.params)
    uv = project_points(cam, state.intrinsics)[0].floor().long()
    pixels = torch.unique(uv, dim=0)
    pixels = pixels[torch.linspace(0, len(pixels) - 1, 6).round().long()]
    return frames, state, pixels


def _with_pixels(frame: torch.Tensor, pixels: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``frame (1, 3, H, W)`` with channel 0 at ``pixels (n, 2)`` (x, y) replaced by ``values (n,)``."""
    n = pixels.shape[0]
    zeros = torch.zeros(n, dtype=torch.long)
    return frame.index_put((zeros, zeros, pixels[:, 1], pixels[:, 0]), values)


# ---------------------------------------------------------------------------------------------------------
# gradcheck (float64, finite differences)
# ---------------------------------------------------------------------------------------------------------


def test_gradcheck_unrolled_params(model, small):
    frames, state, pixels = small
    frame = frames[1:2]
    layer = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL), model)
    start = layer(frame, state).params.detach()  # the tracker's estimate, held fixed
    base = frame[0, 0, pixels[:, 1], pixels[:, 0]].clone()

    def fn(values):
        return unrolled_params(model, SMALL, state, _with_pixels(frame, pixels, values), start, iterations=2)

    values = base.clone().requires_grad_(True)
    grad = torch.autograd.grad(fn(values).sum(), values)[0]
    assert bool((grad.abs() > 0).any()), "the probed pixels must influence the unrolled estimate"
    assert torch.autograd.gradcheck(fn, (values,), eps=1e-6, atol=1e-5, rtol=1e-3)


def test_gradcheck_layer_unrolled_from_previous(model, small):
    """PREVIOUS start: the whole forward (tracking + resampling) is differentiable in the pixels."""
    frames, state, pixels = small
    frame = frames[1:2]
    cfg = LayerConfig(mode=LayerMode.UNROLLED, size=G, unrolled_iterations=2, start=UnrollStart.PREVIOUS, tracker=SMALL)
    layer = NormalisedFaceLayer(cfg, model)
    weights = torch.rand(2, 3, G, G, dtype=D, generator=torch.Generator().manual_seed(0))

    def fn(values):
        out = layer(_with_pixels(frame, pixels, values), state)
        return out.params, (out.image * weights).flatten(1).sum(1)

    values = frame[0, 0, pixels[:, 1], pixels[:, 0]].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(fn, (values,), eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)


# ---------------------------------------------------------------------------------------------------------
# detached vs unrolled
# ---------------------------------------------------------------------------------------------------------


def _grad(layer: NormalisedFaceLayer, frame: torch.Tensor, state, weights: torch.Tensor):
    frame = frame.clone().requires_grad_(True)
    out = layer(frame, state)
    (out.image * weights).sum().backward()
    return out, frame.grad


def test_detached_gradient_is_the_resampling_only(model, small):
    frames, state, _ = small
    layer = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL), model)
    weights = torch.rand(1, 3, G, G, dtype=D, generator=torch.Generator().manual_seed(1))
    out, grad = _grad(layer, frames[1:2], state, weights)
    assert not out.params.requires_grad
    frame = frames[1:2].clone().requires_grad_(True)
    aa, t, alpha, light = layer.param_layout.split(out.params)
    ref = normalised_face(frame, model, layer.layout, state.shape_coeffs, alpha, aa, t, light, state.intrinsics)
    (ref.image * weights).sum().backward()
    torch.testing.assert_close(grad, frame.grad)
    assert grad.abs().sum() > 0


def test_unrolled_k0_is_detached(model, small):
    frames, state, _ = small
    weights = torch.rand(1, 3, G, G, dtype=D, generator=torch.Generator().manual_seed(2))
    det = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL), model)
    k0 = NormalisedFaceLayer(
        LayerConfig(mode=LayerMode.UNROLLED, size=G, unrolled_iterations=0, tracker=SMALL), model
    )
    a, ga = _grad(det, frames[1:2], state, weights)
    b, gb = _grad(k0, frames[1:2], state, weights)
    torch.testing.assert_close(a.params, b.params, rtol=0, atol=0)
    torch.testing.assert_close(a.image, b.image, rtol=0, atol=0)
    torch.testing.assert_close(ga, gb)


def test_unrolled_gradient_differs_from_detached(model, small):
    """The tracking contributes: one unrolled step changes the gradient, and reaches pixels the resampling
    alone does not read."""
    frames, state, _ = small
    weights = torch.rand(1, 3, G, G, dtype=D, generator=torch.Generator().manual_seed(3))
    det = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL), model)
    unr = NormalisedFaceLayer(LayerConfig(mode=LayerMode.UNROLLED, size=G, tracker=SMALL), model)
    a, ga = _grad(det, frames[1:2], state, weights)
    b, gb = _grad(unr, frames[1:2], state, weights)
    assert b.params.requires_grad
    assert (gb - ga).norm() > 0.1 * ga.norm()
    only_unrolled = (gb.abs() > 0) & (ga == 0)
    assert int(only_unrolled.sum()) > 0


def test_unrolled_at_the_exact_minimum_is_detached(model, small):
    """Frame 1 == frame 0, fitted without expression (so the expression prior is at its mean too): the
    template frame's estimate is the exact minimum of the objective (zero residuals), so the tracker stays
    there and a Gauss-Newton step of the unrolled objective does not move (same objective, same fixed point);
    its gradient still differs from the detached one."""
    frames, _, _ = small
    _, landmarks = _clip(32)
    cfg = replace(SMALL, fit=FitConfig(shape_prior_precision=0.0, held_shape_units=(), fit_expression=False))
    weights = torch.rand(1, 3, G, G, dtype=D, generator=torch.Generator().manual_seed(4))
    det = NormalisedFaceLayer(LayerConfig(size=G, tracker=cfg), model)
    state, _ = det.initialise(frames[:1], landmarks[:1])
    a, ga = _grad(det, frames[:1], state, weights)
    torch.testing.assert_close(a.params, state.params, atol=1e-9, rtol=0)
    for k in (1, 2):
        cfg_k = LayerConfig(mode=LayerMode.UNROLLED, size=G, unrolled_iterations=k, tracker=cfg)
        unr = NormalisedFaceLayer(cfg_k, model)
        b, gb = _grad(unr, frames[:1], state, weights)
        torch.testing.assert_close(b.params.detach(), a.params, atol=1e-9, rtol=0)
        torch.testing.assert_close(b.image.detach(), a.image, atol=1e-9, rtol=0)
        assert torch.isfinite(gb).all()
        assert (gb - ga).norm() > 0.1 * ga.norm()


@pytest.mark.parametrize("mode", [LayerMode.DETACHED, LayerMode.UNROLLED])
def test_torch_func_grad_of_the_layer_equals_autograd(model, small, mode):
    """``torch.func.grad`` through the layer (per-sample gradients of a network's loss): the detached tracking step
    ran the transform's wrapped frames (``.detach()`` keeps them wrapped, asking for no gradient) in inference mode,
    "Cannot set version_counter for inference tensor" (and would then have handed them to the native kernels)."""
    frames, state, _ = small
    layer = NormalisedFaceLayer(LayerConfig(mode=mode, size=G, tracker=SMALL), model)
    weights = torch.rand(1, 3, G, G, dtype=D, generator=torch.Generator().manual_seed(6))
    _, want = _grad(layer, frames[1:2], state, weights)
    if not transforms_read_values():  # (torch < 2.10: the tracking step under a transform is refused in one line)
        with pytest.raises(RuntimeError, match=r"^a tracking step cannot run under a torch.func transform on this"):
            torch.func.grad(lambda f: (layer(f, state).image * weights).sum())(frames[1:2].clone())
        return
    got = torch.func.grad(lambda f: (layer(f, state).image * weights).sum())(frames[1:2].clone())
    # (to rounding: gradients up to 5.5 apart by 8.5e-13 with the units' ranges on the coefficients, 1.55e-12 on the
    # expression from the first fit, session 57's expression_range_from_start: 3e-13 of the largest)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_unrolled_iterations_run_on_frames_with_missing_pixels(model, small):
    """Missing (NaN) pixels over part of the face: the unrolled iterations leave the points that sample them out, as
    the tracker does, and move on from their start with finite gradients that go through the tracking. Before, the
    reference objective's solve failed at the first such point and kept its start without a sign: the detached
    mode's gradient, and with ``UnrollStart.PREVIOUS`` the face resampled at the previous frame's pose."""
    frames, state, _ = small
    frame = frames[1:2].clone()
    frame[..., 20:] = float("nan")  # the right third of the 32x32 frame
    weights = torch.rand(1, 3, G, G, dtype=D, generator=torch.Generator().manual_seed(5))
    det = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL), model)
    a, ga = _grad(det, frame, state, weights)
    assert int(a.track.status[0]) in (0, 1) and torch.isfinite(ga).all()
    for start in (UnrollStart.TRACKED, UnrollStart.PREVIOUS):
        cfg = LayerConfig(mode=LayerMode.UNROLLED, size=G, unrolled_iterations=2, start=start, tracker=SMALL)
        b, gb = _grad(NormalisedFaceLayer(cfg, model), frame, state, weights)
        first = a.params if start is UnrollStart.TRACKED else state.params
        assert float((b.params.detach() - first).abs().max()) > 0.01, start
        assert torch.isfinite(gb).all() and bool((gb[..., 20:] == 0).all()), start
        assert (gb - ga).norm() > 0.1 * ga.norm(), start


# ---------------------------------------------------------------------------------------------------------
# features, cardinality, exceptions
# ---------------------------------------------------------------------------------------------------------


def test_keep_expression_keeps_the_expression_visible(model):
    """With the true parameters, undoing the expression makes an open-mouth frame match the neutral one;
    keeping it leaves the difference."""
    frames, landmarks = _clip(64, num_frames=2, jaw=1.0)
    frames_n, _ = _clip(64, num_frames=2, jaw=0.0)
    plain = NormalisedFaceLayer(LayerConfig(size=32, tracker=SMALL), model)
    keep = NormalisedFaceLayer(LayerConfig(size=32, keep_expression=True, tracker=SMALL), model)
    state, _ = plain.initialise(frames[:1], landmarks[:1])
    # Ground-truth parameters of frame 1 in the state's layout (light 0 == the template's light).
    from torchface.geometry.so3 import matrix_to_axis_angle

    s = torch.tensor([[1.0]], dtype=D)
    aa = matrix_to_axis_angle(euler_to_matrix(s * torch.tensor([6.0, 3.0, 2.0], dtype=D)))
    t = torch.tensor([[1.0, 5.0, 170.0]], dtype=D)
    alpha = torch.zeros(1, model.num_animation, dtype=D)
    alpha[0, model.animation_names.index("AUV11 Jaw drop")] = 1.0
    x = torch.cat([aa, t, alpha, torch.zeros(1, 5, dtype=D)], dim=1)
    x_n = torch.cat([aa, t, torch.zeros_like(alpha), torch.zeros(1, 5, dtype=D)], dim=1)
    ref = plain.normalise(frames_n[1:2], state, x_n)

    def diff(layer):
        out = layer.normalise(frames[1:2], state, x)
        both = (out.mask * ref.mask).bool().expand_as(out.image)
        return (out.image - ref.image)[both].abs().mean()

    assert diff(keep) > 2 * diff(plain)


def test_keep_expression_resamples_at_the_persons_neutral(model):
    """The neutral that ``keep_expression`` resamples at is the first frame's fitted coefficients (what
    ``TrackResult.expression`` is measured from), zero where the state carries none."""
    frames, landmarks = _clip(64, num_frames=2, jaw=1.0)
    plain = NormalisedFaceLayer(LayerConfig(size=32, tracker=SMALL), model)
    keep = NormalisedFaceLayer(LayerConfig(size=32, keep_expression=True, tracker=SMALL), model)
    state, _ = plain.initialise(frames[:1], landmarks[:1])
    lay = plain.param_layout
    x = state.params.clone()
    x[:, lay.animation] = 0.4  # an estimate other than the neutral
    neutral = torch.zeros_like(state.anim_prior_mean)
    neutral[0, model.animation_names.index("AUV11 Jaw drop")] = 0.3
    state = replace(state, anim_prior_mean=neutral)
    at_neutral = x.clone()
    at_neutral[:, lay.animation] = neutral
    torch.testing.assert_close(keep.normalise(frames[1:2], state, x).image,
                               plain.normalise(frames[1:2], state, at_neutral).image)  # fmt: skip
    at_zero = x.clone()
    at_zero[:, lay.animation] = 0.0
    assert not torch.allclose(keep.normalise(frames[1:2], state, x).image,
                              plain.normalise(frames[1:2], state, at_zero).image)  # fmt: skip
    torch.testing.assert_close(keep.normalise(frames[1:2], replace(state, anim_prior_mean=None), x).image,
                               plain.normalise(frames[1:2], state, at_zero).image)  # fmt: skip


def test_forward_clip_shapes_and_first_frame(model):
    """Shapes, frame 0, and the per-frame ``success`` / ``confidence`` ``(B, T)``: those of the frame-by-frame steps
    (before, only the last frame's ``track`` came back: a failed frame inside a clip could not be left out)."""
    frames, landmarks = _clip(32, num_frames=2)
    clips = torch.stack([frames, frames.roll(1, dims=-1)])  # (2, 2, 3, 32, 32); the second shifted 1 px right,
    clips[1, 1] = 0.0  # its frame 1 black (no face: FAILED)
    lms = torch.stack([landmarks[0], landmarks[0] + torch.tensor([1.0, 0.0], dtype=D)])
    layer = NormalisedFaceLayer(LayerConfig(mode=LayerMode.UNROLLED, size=G, tracker=SMALL), model)
    out = layer.forward_clip(clips, lms)
    P = layer.param_layout.size
    assert out.image.shape == (2, 2, 3, G, G) and out.mask.shape == (2, 2, 1, G, G)
    assert out.params.shape == (2, 2, P) and out.state.frame_index == 2
    assert out.success.shape == (2, 2) and out.success.dtype == torch.bool
    assert out.confidence.shape == (2, 2) and out.confidence.is_floating_point()
    assert torch.isfinite(out.image).all()
    state, first = layer.initialise(clips[:, 0], lms)
    torch.testing.assert_close(out.image[:, 0], layer.normalise(clips[:, 0], state, state.params).image)
    step = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL), model)(clips[:, 1], state)  # same tracking, cheaper
    assert step.success.shape == (2,) and torch.equal(step.success, step.track.success)
    assert torch.equal(step.confidence, step.track.confidence)
    for t, want in ((0, first), (1, step.track)):
        assert torch.equal(out.success[:, t], want.success) and torch.equal(out.confidence[:, t], want.confidence), t
    assert out.success.tolist() == [[True, True], [True, False]] and float(out.confidence[1, 1]) == 0.0
    assert bool((out.confidence[out.success] > 0).all())
    # the hooks take them as a clip batch: the failed frame weighs 0 (even at a NaN loss), the clips are kept
    loss = torch.tensor([[1.0, 2.0], [3.0, float("nan")]], dtype=D)
    want_loss = (loss * out.confidence)[out.success].sum() / out.confidence[out.success].sum()
    torch.testing.assert_close(confidence_weighted_loss(loss, out.confidence, out.success), want_loss)
    kept = drop_low_confidence({"confidence": out.confidence, "success": out.success, "face": out.image}, 0.0)
    assert kept.indices.tolist() == [0, 1]
    # 2 sets of landmarks for 1 clip of 2 frames (as a (T, B, ...) stack gives): told one set per clip and the
    # transpose (initialise's "with B = 1 (one set per frame)" suggested a set per frame)
    with pytest.raises(ValueError, match=r"one set per clip.*B = 1 clips of T = 2 frames.*clips.transpose\(0, 1\)"):
        layer.forward_clip(clips[:1], lms)
    # one clip's (K, 2) landmarks were initialise's "with B = 1 (one set per frame)"; one clip (T, C, H, W) was told
    # the shape alone
    with pytest.raises(ValueError, match=r"one set per clip, the first frame's: .* B = 1 clips, got landmarks_px "
                                         r"\(68, 2\): one clip's, landmarks_px\[None\]$"):
        layer.forward_clip(clips[:1], lms[0])
    with pytest.raises(ValueError, match=r"got \(2, 3, 32, 32\) \(one clip \(T, C, H, W\): clips\[None\]\)$"):
        layer.forward_clip(clips[0], lms[:1])


def test_double_moves_the_layer_model_and_layout(small):
    frames, state, _ = small  # float64 frames and state
    layer = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL)).double()  # CANDIDE-3, float32 until .double()
    assert layer.model.dtype == D and layer.layout.bary.dtype == D and layer.layout.translation.dtype == D
    assert layer.layout.face_index.dtype == torch.int64 and layer.model.faces.dtype == torch.int64
    out = layer(frames[1:2], state)
    assert out.image.dtype == D and out.params.dtype == D and torch.isfinite(out.image).all()
    assert out.mask.sum() > 0
    layer.to(torch.float32)
    assert layer.model.dtype == torch.float32 and layer.layout.bary.dtype == torch.float32


@pytest.mark.parametrize(
    "move, message",
    [
        pytest.param(lambda layer: layer.to("cuda"), r"^device 'cuda' is not available: ",
                     marks=pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")),
        pytest.param(lambda layer: layer.cuda(), r"^device 'cuda' is not available: ",
                     marks=pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")),
        (lambda layer: layer.to("gpu0"), r"^unknown torch device 'gpu0'"),
        (lambda layer: layer.to(device="meta", dtype=torch.float64), r"^device 'meta' holds no data"),
    ],
    ids=["to(cuda)", "cuda()", "to(gpu0)", "to(device=meta)"],
)  # fmt: skip
def test_a_device_this_machine_lacks_is_torchfaces_value_error(move, message):
    """``NormalisedFaceLayer.to`` / ``.cuda`` check the device as ``NormalisedFace``'s do (torch's own error before: an
    AssertionError 'Torch not compiled with CUDA enabled', torch's list of backends for 'gpu0'); the layer is left
    as it was."""
    layer = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL))
    with pytest.raises(ValueError, match=message) as caught:
        move(layer)
    assert "devices here: cpu" in str(caught.value)
    assert layer.model.dtype == torch.float32 and layer.layout.bary.device.type == "cpu"


def test_a_config_one_level_off_is_told_where_it_goes():
    """The datasets' FaceTrackingConfig given as LayerConfig's tracker, and a TrackerConfig as DatasetConfig's
    tracking, were told the type alone."""
    from training_hooks import DatasetConfig, FaceTrackingConfig

    with pytest.raises(TypeError, match=r"^tracker must be a TrackerConfig, got FaceTrackingConfig; LayerConfig "
                                        r"holds its tracker, size and keep_expression itself: LayerConfig\(tracker="
                                        r"c.tracker, size=c.face_size, keep_expression=c.keep_expression\)$"):
        LayerConfig(tracker=FaceTrackingConfig())  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"^tracking must be a FaceTrackingConfig, got TrackerConfig, which goes inside "
                                        r"it: FaceTrackingConfig\(tracker=TrackerConfig\(...\)\)$"):
        DatasetConfig(tracking=TrackerConfig())  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"^tracker must be a TrackerConfig, got str$"):
        LayerConfig(tracker="fast")  # type: ignore[arg-type]
    c = FaceTrackingConfig(face_size=48, keep_expression=True)  # (the way named)
    assert LayerConfig(tracker=c.tracker, size=c.face_size, keep_expression=c.keep_expression).size == 48


def test_default_size_is_the_datasets_and_the_normalisers():
    """The layer's faces are the datasets' items' size and ``NormalisedFace``'s by default (128): a network trained
    on the items and run on the layer's faces got 64x64 faces (LayerConfig.size was 64)."""
    from torchface.normalise import NormalisedFace

    layer = NormalisedFaceLayer()
    assert LayerConfig().size == FaceTrackingConfig().face_size == 128
    assert layer.layout.size == NormalisedFace(layer.model).layout.size == 128


def test_exceptions(model, small):
    frames, state, _ = small
    with pytest.raises(TypeError):
        LayerConfig(mode="unrolled")
    with pytest.raises(ValueError):
        LayerConfig(unrolled_iterations=-1)
    with pytest.raises(ValueError):
        LayerConfig(unrolled_levels=4)
    with pytest.raises(ValueError):
        LayerConfig(size=2)
    for margin in (0.9, -0.1, float("nan")):  # refused when made, as FaceTrackingConfig's face_margin (was: when the
        with pytest.raises(ValueError, match="margin must be in"):  # layer was built from the config)
            LayerConfig(margin=margin)
    layer = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL), model)
    with pytest.raises(TypeError, match="TrackerState"):
        layer(frames[1:2], None)
    with pytest.raises(ValueError, match="32x32"):
        layer(torch.zeros(1, 3, 30, 32, dtype=D), state)
    with pytest.raises(ValueError, match="one per stream"):
        layer(frames, state)
    with pytest.raises(ValueError, match="start must be"):
        unrolled_params(model, SMALL, state, frames[1:2], state.params[:, :5], iterations=1)
    with pytest.raises(ValueError, match="clips must be"):
        layer.forward_clip(frames, torch.zeros(1, 68, 2, dtype=D))
    # A clip's layout (it was told of its first frame's: channels last "frames.permute(0, 3, 1, 2)", which a clip
    # cannot take; uint8 clips "values from 0 to 255")
    clips = frames[None]
    with pytest.raises(ValueError, match=r"got \(1, 2, 32, 32, 3\) \(channels last \(B, T, H, W, C\): "
                                        r"clips\.permute\(0, 1, 4, 2, 3\)\)$"):
        layer.forward_clip(clips.permute(0, 1, 3, 4, 2), torch.zeros(1, 68, 2, dtype=D))
    rgba = torch.cat([clips, clips[:, :, :1]], 2)  # (RGBA channels last: its shape alone, NormaliseFaces' said it)
    with pytest.raises(ValueError, match=r"\(channels last \(B, T, H, W, C\): clips\.permute\(0, 1, 4, 2, 3\)\)$"):
        layer.forward_clip(rgba.permute(0, 1, 3, 4, 2), torch.zeros(1, 68, 2, dtype=D))
    with pytest.raises(ValueError, match=r"\(RGBA: drop the alpha, clips\[:, :, :3\]\)$"):
        layer.forward_clip(torch.cat([clips, clips[:, :, :1]], 2), torch.zeros(1, 68, 2, dtype=D))
    with pytest.raises(ValueError, match=r"clips must be float in \[0, 1\], got torch\.uint8 \(uint8 clips: "
                                        r"clips\.float\(\) / 255\)$"):
        layer.forward_clip((clips * 255).to(torch.uint8), torch.zeros(1, 68, 2, dtype=D))
    # Not tensors: TypeErrors as forward's numpy frames are (both were ValueErrors, as a wrong shape).
    with pytest.raises(TypeError, match="clips must be a torch.Tensor"):
        layer.forward_clip(frames[None].numpy(), torch.zeros(1, 68, 2, dtype=D))  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="start must be a"):
        unrolled_params(model, SMALL, state, frames[1:2], state.params.numpy(), iterations=1)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"frames must be a \(T, 3, H, W\) torch.Tensor, got ndarray \(a NumPy array: "
                                        r"torch.from_numpy\(array\).float\(\), laid out \(T, 3, H, W\)\)"):  # (it said
        NormaliseFaces(FaceTrackingConfig(tracker=SMALL, face_size=16))(frames.numpy(), torch.zeros(68, 2))  # (B, C, ..)
    # OpenCV's (T, H, W, 3) uint8 BGR frames: told how to make the clip (uint8 taken as it is), not "got ndarray" alone
    bgr = (frames * 255).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()[..., ::-1]
    hint = r"got ndarray \(NumPy frames \(N, H, W, 3\), BGR as OpenCV reads them: "
    hint += r"torch.from_numpy\(frames\[\.\.\., ::-1\]"
    with pytest.raises(TypeError, match=hint + r"\.copy\(\)\)\.permute\(0, 3, 1, 2\); RGB ones"):
        NormaliseFaces(FaceTrackingConfig(tracker=SMALL, face_size=16))(bgr, torch.zeros(68, 2))
    # Frames that require grad: the transform's faces are data (they were detached without a word).
    graded = frames.clone().requires_grad_(True)
    with pytest.raises(ValueError, match="NormaliseFaces makes data items.*NormalisedFaceLayer"):
        NormaliseFaces(FaceTrackingConfig(tracker=SMALL, face_size=16))(graded, torch.zeros(68, 2))
    # numpy landmarks: a one-line TypeError naming them (was AttributeError: 'numpy.ndarray' ... 'detach'), and
    # 0-255 frames after initialisation are refused by the step (they were tracked).
    _, landmarks = _clip(32)
    with pytest.raises(TypeError, match="landmarks_px must be a torch.Tensor"):
        layer.initialise(frames[:1], landmarks[:1].numpy())
    with pytest.raises(ValueError, match="divide by 255"):
        layer(frames[1:2] * 255.0, state)


def test_unrolling_zero_iterations_from_the_previous_estimate_is_refused(model, small):
    """UNROLLED from the PREVIOUS estimate with K = 0 has no tracking at all: each frame was resampled, without a
    word, at the previous frame's pose (0.054-0.064 rad and 1-2.7 mm off the detached layer's on a clip turning
    3 degrees a frame). Refused when made; K = 0 from the TRACKED estimate (the detached mode) and PREVIOUS with
    K >= 1 are taken, as is any K in the DETACHED mode (where start and K are not used)."""
    with pytest.raises(ValueError, match="unrolled_iterations=0.*PREVIOUS"):
        LayerConfig(mode=LayerMode.UNROLLED, start=UnrollStart.PREVIOUS, unrolled_iterations=0)
    LayerConfig(mode=LayerMode.UNROLLED, start=UnrollStart.TRACKED, unrolled_iterations=0)
    LayerConfig(mode=LayerMode.UNROLLED, start=UnrollStart.PREVIOUS, unrolled_iterations=1)
    LayerConfig(mode=LayerMode.DETACHED, start=UnrollStart.PREVIOUS, unrolled_iterations=0)


def test_a_half_precision_layer_says_it_needs_float32(small):
    """``.half()`` / ``.to(bfloat16)`` of a network holding the layer: calling it is a TypeError that says what to
    do (it was torch's '"cholesky_cpu" not implemented for 'Half'' from inside the landmark fit)."""
    frames, state, _ = small
    _, landmarks = _clip(32)
    for dtype in (torch.float16, torch.bfloat16):
        layer = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL)).to(dtype)
        with pytest.raises(TypeError, match="float32 or float64"):
            layer.initialise(frames[:1].to(dtype), landmarks[:1].to(dtype))
        with pytest.raises(TypeError, match="float32 or float64"):
            layer(frames[1:2].to(dtype), state)
        layer.float()  # and back: it tracks again
        assert torch.isfinite(layer(frames[1:2].float(), layer.initialise(frames[:1], landmarks[:1])[0]).image).all()


def test_layer_inside_autocast_equals_full_precision():
    """Under ``torch.autocast`` (CPU bfloat16) the float32 layer tracks, unrolls and resamples in float32: the
    same images and parameters as outside it, while the caller's own products still autocast."""
    frames, landmarks = _clip(32)
    frames, landmarks = frames.float(), landmarks.float()
    for mode in (LayerMode.DETACHED, LayerMode.UNROLLED):
        layer = NormalisedFaceLayer(LayerConfig(mode=mode, size=G, tracker=SMALL))
        state, _ = layer.initialise(frames[:1], landmarks[:1])
        ref = layer(frames[1:2], state)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            state_amp, _ = layer.initialise(frames[:1], landmarks[:1])
            out = layer(frames[1:2], state_amp)
            assert (out.image.flatten(1) @ torch.ones(G * G * 3, 1)).dtype == torch.bfloat16
        assert torch.equal(state_amp.params, state.params), mode
        assert torch.equal(out.params, ref.params) and torch.equal(out.image, ref.image), mode


def test_a_compiled_layer_tracks_eagerly_and_equals_the_eager_layer():
    """``torch.compile`` of a network holding the layer: the tracker's native kernels were traced with the pointers
    of the traced tensors and the process crashed (segmentation fault), detached and unrolled. The tracking now runs
    eagerly inside the compiled function: the same faces, parameters and gradients. In a child, so that a regression
    fails this test only."""
    code = textwrap.dedent(f"""
        import sys
        import torch
        torch.set_num_threads(1)
        sys.path.insert(0, {os.path.dirname(os.path.abspath(__file__))!r})
        from test_layer import SMALL, _clip
        from training_hooks.layer import LayerConfig, LayerMode, NormalisedFaceLayer
        frames, landmarks = _clip(32)
        for mode in (LayerMode.DETACHED, LayerMode.UNROLLED):
            layer = NormalisedFaceLayer(LayerConfig(mode=mode, size=12, tracker=SMALL)).double()
            state, _ = layer.initialise(frames[:1], landmarks[:1])
            outs = []
            for run in (layer, torch.compile(layer, backend="eager")):
                frame = frames[1:2].clone().requires_grad_(True)
                out = run(frame, state)
                out.image.sum().backward()
                outs.append((out.image, out.params, frame.grad))
            for eager, compiled in zip(*outs):
                assert torch.equal(eager, compiled), mode
            assert outs[0][2].abs().sum() > 0
        print("ok")
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=240)
    assert run.returncode == 0 and run.stdout.strip() == "ok", (run.returncode, run.stderr[-2000:])


def test_the_layer_tracks_an_hd_clip_with_the_coarser_levels_its_face_needs():
    """The layer took its tracker config as given, so the 1280x720 clip of tests/cli/test_cli_track.py's HD test
    (37 pixels a frame sideways) was lost with the default three levels (frames 1 and 2 23 and 30 degrees off, in
    both modes). ``LayerConfig.pyramid`` "auto" (the default) initialises with pyramid_for_faces's four levels,
    tracks on with the state's levels (the unrolled iterations too) and follows it; "config" keeps three."""
    from th_data import sideways_clip
    from torchface.geometry.so3 import axis_angle_to_matrix, geodesic_angle_deg

    frames, lm, truth = sideways_clip(1280, 720)
    errors = {}
    for pyramid, mode in (("auto", LayerMode.UNROLLED), ("config", LayerMode.DETACHED)):
        out = NormalisedFaceLayer(LayerConfig(size=16, mode=mode, pyramid=pyramid)).forward_clip(frames[None], lm[None])
        assert out.state.num_levels == {"auto": 4, "config": 3}[pyramid]
        rotation = axis_angle_to_matrix(out.params[0, 1:, :3].detach().double())
        errors[pyramid] = geodesic_angle_deg(rotation, truth[1:])
        if pyramid == "auto":  # a config of fewer levels gets back the one level added, no more (two were added)
            fewer = TrackerConfig(num_levels=2, iterations=(6, 4))
            with pytest.raises(ValueError, match=r"4 pyramid levels, the config has num_levels = 2 and "
                                                 r"pyramid='auto' adds the 1 coarser level\(s\) initialise added"):
                NormalisedFaceLayer(LayerConfig(size=16, tracker=fewer))(frames[-1:], out.state)
    assert float(errors["auto"].max()) < 2.0 and float(errors["config"].max()) > 10.0, errors
    with pytest.raises(ValueError, match=r"pyramid must be one of \('auto', 'config'\), got 'on'"):
        LayerConfig(pyramid="on")


def test_a_state_is_continued_with_the_levels_pyramid_auto_added_and_no_more():
    """The layer's ``pyramid="auto"`` continuation made any config up to the state's levels: a 2-level state (small
    faces: "auto" added none) forwarded by a layer of a 1-level config was tracked with 2 levels, the coarsest's
    iterations repeated, without a word. As :class:`FaceTracker` does (``torchface.tracker.module.continuing_config``,
    one function), it adds back only the levels initialise added, so a config of fewer levels is refused, naming
    them; a FaceTracker's state (its added levels noted) continues with the tracker's own config, and a layer of
    ``pyramid="config"`` refuses any config of other levels as before."""
    from torchface.tracker import FaceTracker

    frames, landmarks = _clip(32, num_frames=2)
    two = replace(SMALL, num_levels=2, iterations=(4, 4))
    state, _ = NormalisedFaceLayer(LayerConfig(size=G, tracker=two)).initialise(frames[:1], landmarks[:1])
    assert state.num_levels == 2
    for pyramid in ("auto", "config"):
        fewer = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL, pyramid=pyramid))
        with pytest.raises(ValueError, match="the state holds templates for 2 pyramid levels, the config has "
                                             "num_levels = 1"):  # fmt: skip
            fewer(frames[1:2], state)
    assert NormalisedFaceLayer(LayerConfig(size=G, tracker=two))(frames[1:2], state).state.num_levels == 2
    tracker = FaceTracker(two, load_candide3(dtype=torch.float32), refine_first=None)
    tracker.initialise(frames[:1].float(), landmarks[:1].float())
    layer = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL), tracker.model)
    with pytest.raises(ValueError, match="the state holds templates for 2 pyramid levels, the config has "
                                         "num_levels = 1"):  # fmt: skip
        layer(frames[1:2], tracker.state)


def test_initialise_names_intrinsics_that_are_not_intrinsics():
    """With ``pyramid="auto"`` (the default) the layer read the intrinsics' size before :func:`initialise` checked
    them: a ``(W, H)`` tuple was "'tuple' object has no attribute 'height'" (it was "intrinsics must be
    torchface.geometry.Intrinsics, got tuple"). Both pyramids now say what is wrong."""
    frames = torch.rand(1, 3, 48, 64)
    landmarks = torch.rand(1, 68, 2) * 40
    for pyramid in ("auto", "config"):
        layer = NormalisedFaceLayer(LayerConfig(size=16, pyramid=pyramid))
        for bad in ((64, 48), "camera"):
            with pytest.raises(TypeError, match="intrinsics must be torchface.geometry.Intrinsics"):
                layer.initialise(frames, landmarks, bad)  # type: ignore[arg-type]


def _assert_finite_and_the_others_as_alone(layer, clips, lms, grad, out) -> None:
    """``out = layer.forward_clip(grad, lms)`` of three clips whose middle one failed: finite images, parameters and
    gradients, and clips 0 and 2 as tracked without the middle one."""
    assert bool(torch.isfinite(out.image).all()) and bool(torch.isfinite(out.params).all())
    out.image.sum().backward()
    assert grad.grad is not None and bool(torch.isfinite(grad.grad).all())
    rest = layer.forward_clip(clips[[0, 2]], lms[[0, 2]])
    torch.testing.assert_close(out.image[[0, 2]].detach(), rest.image)
    torch.testing.assert_close(out.params[[0, 2]].detach(), rest.params)


@pytest.mark.parametrize("mode", [LayerMode.DETACHED, LayerMode.UNROLLED])
def test_a_clip_without_landmarks_fails_alone_and_the_others_are_as_without_it(model, mode):
    """A batch of clips, one without a face found in its first frame (landmarks all NaN): ``initialise`` raised
    "every sample needs at least 4 finite landmarks with positive weight" for the whole batch. That clip now
    tracks FAILED (confidence 0) with finite images, parameters and gradients, and the other clips' normalised faces
    are those of the batch without it."""
    frames, landmarks = _clip(32, num_frames=3)
    clips = torch.stack([frames, frames.roll(1, dims=-1), frames.roll(-1, dims=-1)])
    lms = landmarks[0] + torch.tensor([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0]], dtype=D)[:, None]
    lms[1] = float("nan")
    layer = NormalisedFaceLayer(LayerConfig(mode=mode, size=G, tracker=SMALL), model)
    grad = clips.clone().requires_grad_()
    out = layer.forward_clip(grad, lms)
    assert out.track.status.tolist()[1] == 2 and float(out.track.confidence[1]) == 0.0
    assert bool(out.track.success[[0, 2]].all())
    _assert_finite_and_the_others_as_alone(layer, clips, lms, grad, out)


def test_the_layers_outputs_share_no_memory_with_the_state_it_hands_on(model, small):
    """A caller modifying what the layer returns in place (``out.params``, the first result's pose) leaves the state
    the next frame starts from alone: in DETACHED mode ``out.params`` was ``out.state.params`` itself, and
    ``initialise``'s result's pose was a view of the state's parameters."""
    frames, state, _ = small
    layer = NormalisedFaceLayer(LayerConfig(size=G, tracker=SMALL), model)

    def storages(*trees) -> set[int]:
        found: list[torch.Tensor] = []

        def walk(x) -> None:
            if isinstance(x, torch.Tensor):
                found.append(x)
            elif dataclasses.is_dataclass(x) and not isinstance(x, type):
                for f in dataclasses.fields(x):
                    walk(getattr(x, f.name))
            elif isinstance(x, (tuple, list)):
                for v in x:
                    walk(v)

        for tree in trees:
            walk(tree)
        return {t.untyped_storage().data_ptr() for t in found if t.numel()}

    landmarks = _clip(32)[1]
    first_state, first = layer.initialise(frames[:1], landmarks[:1])
    assert not storages(first) & storages(first_state)
    out = layer(frames[1:2], state)
    assert not storages(out.image, out.mask, out.params, out.track) & storages(out.state)
    want = out.state.params.clone()
    out.params.add_(1.0)
    assert torch.equal(out.state.params, want)


@pytest.mark.parametrize("mode", [LayerMode.DETACHED, LayerMode.UNROLLED])
def test_a_clip_whose_start_failed_is_failed_at_every_frame(model, mode):
    """A clip whose first frame's landmarks hold no pose (collinear: the face edge-on, a fit that FAILED): the
    layer's tracker went on from that failed start, CONVERGED (success True) on the next frames, its parameters
    moving (the head's origin 3.8-4.8 mm over two frames). It is FAILED at every frame now, at confidence 0 and the
    start's parameters (the unrolled ones too), with finite images and gradients; the other clips are as without it."""
    frames, landmarks = _clip(32, num_frames=3)
    clips = torch.stack([frames, frames.roll(1, dims=-1), frames.roll(-1, dims=-1)])
    lms = landmarks[0] + torch.tensor([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0]], dtype=D)[:, None]
    lms[1, :, 1] = lms[1, :, 1].mean()  # every point on one row
    layer = NormalisedFaceLayer(LayerConfig(mode=mode, size=G, tracker=SMALL), model)
    state, first = layer.initialise(clips[:, 0], lms)
    assert first.status.tolist() == [0, 2, 0] and float(first.confidence[1]) == 0.0
    start = state.params[1].clone()
    for t in (1, 2):
        out = layer(clips[:, t], state)
        state = out.state
        assert int(out.track.status[1]) == 2 and float(out.track.confidence[1]) == 0.0, t
        assert torch.equal(out.params[1].detach(), start) and torch.equal(state.params[1], start), t
    grad = clips.clone().requires_grad_()
    out = layer.forward_clip(grad, lms)
    assert torch.equal(out.params[1, 2].detach(), out.params[1, 0].detach())
    _assert_finite_and_the_others_as_alone(layer, clips, lms, grad, out)
