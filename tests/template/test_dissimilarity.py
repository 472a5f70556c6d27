"""Tests of torchface.template.dissimilarity (IC Lucas-Kanade, dissimilarity, confidence) and the AUROC helper."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from torchface import _native
from torchface.backend import Backend
from torchface.template.dissimilarity import (
    DissimilarityConfig,
    build_dissimilarity_reference,
    dissimilarity,
    inverse_compositional_lk,
    lk_template,
    trimmed_mean,
)


TORCH, NATIVE = Backend.TORCH, Backend.NATIVE
requires_native = pytest.mark.skipif(
    _native.library() is None, reason=f"native kernels unavailable: {_native.unavailable_reason()}"
)


def _texture(batch: int, size: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    """Smooth random texture ``(B, 1, size, size)`` in [0, 1] (band-limited: bilinear shifts are near exact)."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(batch, 1, size // 4, size // 4, generator=g, dtype=dtype)
    img = F.interpolate(coarse, size=(size, size), mode="bicubic", align_corners=True)
    k = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], dtype=dtype)
    k = (k / k.sum()).reshape(1, 1, 1, -1)
    img = F.conv2d(F.pad(img, (2, 2, 0, 0), mode="replicate"), k)
    img = F.conv2d(F.pad(img, (0, 0, 2, 2), mode="replicate"), k.transpose(-1, -2))
    return (img - img.amin()) / (img.amax() - img.amin())


def _shift(img: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """``out(x) = img(x - shift[b])`` (content moves by ``+shift``), bilinear, ``shift (B, 2)`` in pixels."""
    B, _, H, W = img.shape
    v, u = torch.meshgrid(
        torch.arange(H, dtype=img.dtype), torch.arange(W, dtype=img.dtype), indexing="ij"
    )
    src_u = u - shift[:, 0, None, None]
    src_v = v - shift[:, 1, None, None]
    grid = torch.stack([2 * src_u / (W - 1) - 1, 2 * src_v / (H - 1) - 1], -1)
    return F.grid_sample(img, grid, mode="bicubic", padding_mode="border", align_corners=True)


# ---------------------------------------------------------------- inverse-compositional Lucas-Kanade


def _waves(shift: torch.Tensor, size: int) -> torch.Tensor:
    """``(B, 1, size, size)`` sum of smooth plane waves evaluated exactly at ``x - shift[b]``."""
    v, u = torch.meshgrid(torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64),
                          indexing="ij")  # fmt: skip
    u = u - shift[:, 0, None, None]
    v = v - shift[:, 1, None, None]
    img = (torch.sin(0.31 * u + 0.17 * v) + torch.cos(0.23 * u - 0.29 * v + 1.0) + 0.5 * torch.sin(0.41 * v + 0.2))
    return (0.5 + 0.15 * img).unsqueeze(1)


def test_lk_recovers_known_subpixel_translations():
    shift = torch.tensor([[0.4, -0.7], [1.3, 0.25], [-0.9, -1.6]], dtype=torch.float64)
    ref = _waves(torch.zeros_like(shift), 64)
    img = _waves(shift, 64)
    centres = torch.tensor([[20.0, 20.0], [40.0, 22.0], [30.0, 42.0], [44.0, 44.0]], dtype=torch.float64)
    centres = centres.expand(3, -1, -1)
    out = inverse_compositional_lk(ref, img, centres, patch_size=15, iterations=50, tolerance=1e-6)
    assert out.displacement.shape == (3, 4, 2)
    assert out.converged.all() and out.valid.all()
    err = (out.displacement - shift[:, None, :]).abs().max()
    assert err < 0.03, f"max displacement error {float(err):.4f} px"
    assert torch.allclose(out.support, torch.ones_like(out.support))


def test_lk_identity_and_bias_projection():
    ref = _texture(2, 48, seed=1)
    centres = torch.tensor([[[16.0, 16.0], [30.0, 25.0]]], dtype=torch.float64).expand(2, -1, -1)
    out = inverse_compositional_lk(ref, ref + 0.2, centres, patch_size=11)
    assert out.displacement.abs().max() < 1e-8
    assert out.residual.max() < 1e-8  # the bias is projected out
    biased = inverse_compositional_lk(ref, ref + 0.2, centres, patch_size=11, project_out_bias=False)
    assert biased.displacement.abs().max() > 0.1  # without the projection the bias misleads the solve


def test_lk_batch_equals_per_sample():
    ref = _texture(3, 48, seed=2)
    img = _shift(ref, torch.tensor([[0.5, 0.2], [-0.3, 0.8], [1.0, -1.0]], dtype=torch.float64))
    centres = torch.tensor([[[15.0, 15.0], [30.0, 30.0]], [[20.0, 25.0], [33.0, 14.0]], [[24.0, 24.0], [14.0, 33.0]]],
                           dtype=torch.float64)  # fmt: skip
    batch = inverse_compositional_lk(ref, img, centres, patch_size=9, iterations=30)
    for b in range(3):
        one = inverse_compositional_lk(ref[b : b + 1], img[b : b + 1], centres[b : b + 1], 9, 30)
        torch.testing.assert_close(batch.displacement[b], one.displacement[0], atol=1e-10, rtol=0)
        assert torch.equal(batch.converged[b], one.converged[0])


@pytest.mark.parametrize("channels", [1, 3])
def test_lk_last_active_patches_going_on_alone_is_the_same_solve(monkeypatch, channels):
    """Once at most a quarter of a large batch's patches are active they iterate alone (one patch per batch
    row): bit for bit the solve of the whole batch to the end (the slow reference)."""
    D = sys.modules["torchface.template.dissimilarity"]  # the package re-exports a function of that name
    g = torch.Generator().manual_seed(0)
    B, K, d = 8, 16, torch.float64
    ref = F.avg_pool2d(torch.rand(B, channels, 64, 64, generator=g, dtype=d), 5, 1, 2)  # rough texture
    img = torch.roll(ref, shifts=(1, 1), dims=(2, 3)) + 0.01 * torch.rand(ref.shape, generator=g, dtype=d)
    centres = 12 + 40 * torch.rand(B, K, 2, generator=g, dtype=d)
    mask = (torch.rand(B, 1, 64, 64, generator=g) > 0.01).to(d)
    kw = dict(reference_mask=mask, image_mask=mask, max_displacement=6.0)
    assert B * K >= D._COMPACT_MIN_PATCHES
    # The first iteration count i that leaves at most a quarter of the patches active (where they go on alone)
    # leaves some; with one more iteration allowed, some are still active at the end (the budget counts).
    for i in range(1, 20):
        part = inverse_compositional_lk(ref, img, centres, 11, i, **kw)
        left = int((part.valid & ~part.converged).sum())
        if left <= B * K // 4:
            break
    assert 0 < left <= B * K // 4, (i, left)
    out = inverse_compositional_lk(ref, img, centres, 11, i + 1, **kw)
    monkeypatch.setattr(D, "_COMPACT_MIN_PATCHES", 10**9)
    slow = inverse_compositional_lk(ref, img, centres, 11, i + 1, **kw)
    assert bool((slow.valid & ~slow.converged).any())
    for name in ("displacement", "converged", "valid", "support", "residual"):
        assert torch.equal(getattr(out, name), getattr(slow, name)), name


def test_lk_without_residual_is_the_same_solve():
    """with_residual=False (what dissimilarity asks for) leaves the residual out and changes nothing else."""
    ref = _texture(3, 48, seed=2)
    img = _shift(ref, torch.tensor([[0.5, 0.2], [-0.3, 0.8], [1.0, -1.0]], dtype=torch.float64))
    centres = torch.tensor([[[15.0, 15.0], [30.0, 30.0]]], dtype=torch.float64).expand(3, -1, -1)
    mask = torch.ones(3, 1, 48, 48, dtype=torch.float64)
    mask[..., 30:, 30:] = 0.0
    full = inverse_compositional_lk(ref, img, centres, 9, 10, image_mask=mask)
    lean = inverse_compositional_lk(ref, img, centres, 9, 10, image_mask=mask, with_residual=False)
    assert lean.residual is None and full.residual is not None
    for name in ("displacement", "converged", "valid", "support"):
        assert torch.equal(getattr(lean, name), getattr(full, name)), name


def test_lk_masked_out_patch_has_no_support_and_is_finite():
    ref = _texture(1, 48, seed=3)
    centres = torch.tensor([[[12.0, 12.0], [34.0, 34.0]]], dtype=torch.float64)
    mask = torch.ones(1, 1, 48, 48, dtype=torch.float64)
    mask[..., 24:, 24:] = 0.0
    out = inverse_compositional_lk(ref, ref * mask, centres, 11, image_mask=mask)
    assert torch.isfinite(out.displacement).all() and torch.isfinite(out.residual).all()
    assert out.support[0, 0] == 1.0 and out.support[0, 1] == 0.0
    assert not out.valid[0, 1]  # no weight: singular Hessian


def test_lk_flat_patch_is_not_valid_and_finite():
    ref = torch.full((1, 1, 32, 32), 0.5, dtype=torch.float64)
    out = inverse_compositional_lk(ref, ref, torch.tensor([[[16.0, 16.0]]], dtype=torch.float64), 9)
    assert not out.valid.any() and torch.isfinite(out.displacement).all()


def test_lk_bad_shapes_raise():
    ref = torch.rand(2, 1, 32, 32)
    centres = torch.full((2, 3, 2), 16.0)
    with pytest.raises(ValueError, match="reference must be"):
        inverse_compositional_lk(ref[0], ref, centres, 9)
    with pytest.raises(ValueError, match="batch and channels"):
        inverse_compositional_lk(ref, ref[:1], centres, 9)
    with pytest.raises(ValueError, match="centres must be"):
        inverse_compositional_lk(ref, ref, centres[..., :1], 9)
    with pytest.raises(ValueError, match="patch_size"):
        inverse_compositional_lk(ref, ref, centres, 2)
    with pytest.raises(ValueError, match="image_mask"):
        inverse_compositional_lk(ref, ref, centres, 9, image_mask=torch.ones(2, 1, 16, 16))
    with pytest.raises(TypeError, match="centres"):
        inverse_compositional_lk(ref, ref, [[1.0, 2.0]], 9)
    for tolerance in (0.0, float("inf"), float("nan")):  # (inf passed "> 0": every patch converged at once)
        with pytest.raises(ValueError, match=r"^tolerance must be a finite number > 0 \(pixels\), got"):
            inverse_compositional_lk(ref, ref, centres, 9, tolerance=tolerance)


# ---------------------------------------------------------------- dissimilarity and confidence


def _face(batch: int = 2, size: int = 96, seed: int = 4):
    img = _texture(batch, size, seed).expand(-1, 3, -1, -1).clone()
    v, u = torch.meshgrid(torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64),
                          indexing="ij")  # fmt: skip
    c = (size - 1) / 2
    mask = (((u - c) / (0.45 * size)) ** 2 + ((v - c) / (0.48 * size)) ** 2 <= 1.0).to(torch.float64)
    mask = mask.expand(batch, 1, -1, -1).clone()
    return img * mask, mask


def test_reference_patches_inside_mask_and_separated():
    face, mask = _face()
    cfg = DissimilarityConfig()
    ref = build_dissimilarity_reference(face, mask, cfg)
    assert ref.centres.shape == (2, cfg.num_patches, 2) and ref.patch_valid.all()
    r = cfg.patch_size // 2
    for b in range(2):
        for u, v in ref.centres[b].long().tolist():
            assert mask[b, 0, v - r : v + r + 1, u - r : u + r + 1].min() == 1.0
        diff = (ref.centres[b, :, None] - ref.centres[b, None]).abs().amax(-1)
        diff = diff + torch.eye(cfg.num_patches, dtype=diff.dtype) * 1e9
        assert diff.min() > cfg.separation
    assert (ref.score[:, :-1] >= ref.score[:, 1:]).all()  # best first


def test_identical_faces_give_zero_dissimilarity_and_full_confidence():
    face, mask = _face()
    ref = build_dissimilarity_reference(face, mask)
    d, conf, disp, present = dissimilarity(ref, face, mask)
    assert d.shape == (2,) and conf.shape == (2,) and disp.shape == (2, 16, 2)
    assert present.all()
    assert d.max() < 1e-6 and conf.min() > 1 - 1e-9


def test_shift_and_corruption_lower_confidence():
    face, mask = _face(batch=1)
    ref = build_dissimilarity_reference(face, mask)
    shifts = torch.tensor([[0.3, 0.0], [1.0, 0.5], [2.0, -1.5]], dtype=torch.float64)
    moved = _shift(face.expand(3, -1, -1, -1), shifts) * mask
    d, conf = dissimilarity(ref, moved, mask.expand(3, -1, -1, -1))[:2]
    expected = shifts.norm(dim=-1)
    assert torch.allclose(d, expected, atol=0.1), (d, expected)
    assert (conf[1:] < conf[:-1]).all()
    g = torch.Generator().manual_seed(9)
    noisy = (face + 0.5 * torch.rand(face.shape, generator=g, dtype=torch.float64)) * mask
    other = _face(batch=1, seed=11)[0]
    d2, conf2 = dissimilarity(ref, torch.cat([face, noisy, other]), mask.expand(3, -1, -1, -1))[:2]
    assert d2[0] < 1e-6 and d2[1] > 0.05 and d2[2] > 1.0
    assert conf2[0] > conf2[1] > conf2[2]


def test_trimmed_mean_known_answers():
    """The largest floor(trim * count) present displacements are left out; absent patches never count; at least
    one patch is kept; trim 0 is the plain mean."""
    dist = torch.tensor([[0.2, 2.9, 0.5, 0.2, 1.0, 0.9, 0.4, 2.3], [5.0, 1.0, 3.0, 9.0, 2.0, 0.0, 0.0, 0.0],
                         [4.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)  # fmt: skip
    present = torch.tensor([[True] * 8, [True, True, True, False, True, False, False, False],
                            [True] + [False] * 7])  # fmt: skip
    count = present.sum(-1)
    got = trimmed_mean(dist, present, count, 0.25)
    # 8 present: the two largest (2.9, 2.3) out; 4 present: floor(1) = the 5.0 out; 1 present: kept.
    expected = torch.tensor([(0.2 + 0.5 + 0.2 + 1.0 + 0.9 + 0.4) / 6, (1.0 + 3.0 + 2.0) / 3, 4.0], dtype=torch.float64)
    torch.testing.assert_close(got, expected)
    plain = (dist * present).sum(-1) / count
    torch.testing.assert_close(trimmed_mean(dist, present, count, 0.0), plain)
    with pytest.raises(ValueError, match="trim_fraction"):
        DissimilarityConfig(trim_fraction=1.0)


def test_gaussian_kernels_are_cached_and_trimmed_mean_is_not():
    """The smoothing kernels are cached constants (one build per sigma, dtype, device); the trimmed mean, whose
    arguments are per-frame tensors, is a plain function."""
    from torchface.template.dissimilarity import _gaussian_kernels

    a = _gaussian_kernels(1.0, torch.float64, torch.device("cpu"))
    assert _gaussian_kernels(1.0, torch.float64, torch.device("cpu")) is a
    assert not hasattr(trimmed_mean, "cache_info")


def test_trimming_keeps_a_few_displaced_patches_from_deciding():
    """A quarter of the patches of an otherwise matching face replaced by another texture: with the default trim
    (0.25) the confidence stays at the clean face's; without it, it falls."""
    face, mask = _face(batch=1)
    ref = build_dissimilarity_reference(face, mask)
    centres = ref.centres[0]
    K = int(centres.shape[0])
    other = _face(batch=1, seed=11)[0]
    spoiled = face.clone()
    for cx, cy in centres[: K // 4].round().long().tolist():
        spoiled[..., cy - 6 : cy + 7, cx - 6 : cx + 7] = other[..., cy - 6 : cy + 7, cx - 6 : cx + 7]
    spoiled = spoiled * mask
    trimmed = dissimilarity(ref, spoiled, mask)
    plain = dissimilarity(build_dissimilarity_reference(face, mask, DissimilarityConfig(trim_fraction=0.0)), spoiled, mask)
    assert float(plain.dissimilarity[0]) > float(trimmed.dissimilarity[0])
    assert float(trimmed.confidence[0]) > 0.9 and float(plain.confidence[0]) < 0.8, (trimmed, plain)


def test_dissimilarity_batch_equals_per_sample_and_broadcast_reference():
    face, mask = _face(batch=1)
    ref = build_dissimilarity_reference(face, mask)
    shifts = torch.tensor([[0.5, 0.5], [-1.2, 0.3]], dtype=torch.float64)
    moved = _shift(face.expand(2, -1, -1, -1), shifts) * mask
    masks = mask.expand(2, -1, -1, -1)
    both = dissimilarity(ref, moved, masks)
    for b in range(2):
        one = dissimilarity(ref, moved[b : b + 1], masks[b : b + 1])
        torch.testing.assert_close(both.dissimilarity[b], one.dissimilarity[0], atol=1e-10, rtol=0)
        torch.testing.assert_close(both.confidence[b], one.confidence[0], atol=1e-10, rtol=0)


def test_masked_or_empty_gives_zero_confidence_and_finite():
    face, mask = _face()
    ref = build_dissimilarity_reference(face, mask)
    empty = torch.zeros_like(mask)
    half = mask.clone()
    half[..., :, 48:] = 0.0
    d, conf, _, present = dissimilarity(ref, torch.cat([face[:1] * 0, face[1:] * half[1:]]),
                                        torch.cat([empty[:1], half[1:]]))  # fmt: skip
    assert torch.isfinite(d).all() and torch.isfinite(conf).all()
    assert conf[0] == 0.0 and d[0] == ref.config.max_displacement and not present[0].any()
    # Half the face visible: the patches on the visible half still count and match.
    assert 0 < int(present[1].sum()) < 16 and conf[1] > 0.99
    # A reference without any texture has no patch: confidence 0, never NaN.
    flat = build_dissimilarity_reference(torch.full_like(face, 0.5) * mask, mask)
    assert not flat.patch_valid.any()
    d3, conf3 = dissimilarity(flat, face, mask)[:2]
    assert torch.isfinite(d3).all() and (conf3 == 0).all()


def test_too_few_present_patches_give_zero_confidence():
    """``min_present_fraction``: a face keeping only a corner of its reference's patches scores 0 however well
    that corner matches; the same face with enough patches present keeps its confidence."""
    face, mask = _face(batch=1)
    corner = mask.clone()
    corner[..., 40:, :] = 0.0
    corner[..., :, 40:] = 0.0
    most = mask.clone()
    most[..., :, 72:] = 0.0  # three quarters of the face
    for fraction, want_corner_zero in ((0.0, False), (0.5, True)):
        cfg = DissimilarityConfig(min_present_fraction=fraction)
        ref = build_dissimilarity_reference(face, mask, cfg)
        valid = int(ref.patch_valid.sum())
        _, conf_c, _, present_c = dissimilarity(ref, face * corner, corner)
        _, conf_m, _, present_m = dissimilarity(ref, face * most, most)
        assert 0 < int(present_c.sum()) < fraction * valid or fraction == 0.0
        assert int(present_m.sum()) >= 0.5 * valid and float(conf_m) > 0.99
        assert (float(conf_c) == 0.0) == want_corner_zero, (fraction, int(present_c.sum()), valid, float(conf_c))
    with pytest.raises(ValueError, match="min_present_fraction"):
        DissimilarityConfig(min_present_fraction=1.5)


def test_dissimilarity_bad_inputs_raise():
    face, mask = _face()
    ref = build_dissimilarity_reference(face, mask)
    with pytest.raises(ValueError, match="square"):
        build_dissimilarity_reference(face[..., :90], mask[..., :90])
    with pytest.raises(ValueError, match="mask"):
        dissimilarity(ref, face, mask[:, :, :50, :50])
    with pytest.raises(ValueError, match="like the reference"):
        dissimilarity(ref, face[..., :64, :64], mask[..., :64, :64])
    with pytest.raises(ValueError, match="batch must be 1 or B"):
        dissimilarity(ref, face[:1].expand(3, -1, -1, -1), mask[:1].expand(3, -1, -1, -1))
    with pytest.raises(TypeError, match="DissimilarityReference"):
        dissimilarity(face, face, mask)
    with pytest.raises(ValueError, match="odd"):
        DissimilarityConfig(patch_size=10)
    with pytest.raises(ValueError, match=r"^d0 must be a finite number > 0, got 0.0"):
        DissimilarityConfig(d0=0.0)
    with pytest.raises(ValueError, match="min_support"):
        DissimilarityConfig(min_support=0.0)


def test_float32_runs():
    face, mask = _face(batch=1)
    ref = build_dissimilarity_reference(face.float(), mask.float())
    d, conf = dissimilarity(ref, face.float(), mask.float())[:2]
    assert d.dtype == torch.float32 and float(d[0]) < 1e-3 and float(conf[0]) > 0.99


# ---------------------------------------------------------------- AUROC of scripts/confidence_auroc.py


def _auroc():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/_helpers.py
    from _helpers import SCRIPTS, load_script

    if not (SCRIPTS / "confidence_auroc.py").is_file():
        pytest.skip("scripts/confidence_auroc.py not present")
    return load_script("confidence_auroc").auroc


def test_auroc_known_answers():
    auroc = _auroc()
    assert auroc(torch.tensor([3.0, 4.0]), torch.tensor([1.0, 2.0])) == 1.0
    assert auroc(torch.tensor([1.0, 2.0]), torch.tensor([3.0, 4.0])) == 0.0
    # Ties count one half: pairs (0.9>0.1) (0.9>0.8) (0.8>0.1) (0.8=0.8) -> 3.5 / 4.
    assert auroc(torch.tensor([0.9, 0.8]), torch.tensor([0.1, 0.8])) == 0.875
    assert auroc(torch.ones(3), torch.ones(5)) == 0.5
    assert math.isnan(auroc(torch.tensor([]), torch.tensor([1.0])))
    g = torch.Generator().manual_seed(0)
    pos, neg = torch.rand(40, generator=g), torch.rand(30, generator=g).round(decimals=1)
    brute = ((pos[:, None] > neg[None]).double() + 0.5 * (pos[:, None] == neg[None]).double()).mean()
    assert abs(auroc(pos, neg) - float(brute)) < 1e-12


def test_precomputed_reference_side_gives_the_same_answer():
    """The reference side computed once (DissimilarityReference.lk / lk_template) equals computing it per call."""
    ref_img = _texture(2, 48, seed=4)
    img = _shift(ref_img, torch.tensor([[0.6, -0.3], [-1.1, 0.8]], dtype=torch.float64))
    mask = torch.ones(2, 1, 48, 48, dtype=torch.float64)
    mask[:, :, :, :6] = 0
    centres = torch.tensor([[[16.0, 16.0], [30.0, 25.0], [24.0, 34.0]]], dtype=torch.float64).expand(2, -1, -1)
    plain = inverse_compositional_lk(ref_img, img, centres, 9, reference_mask=mask, image_mask=mask)
    pre = lk_template(ref_img, centres, 9, mask)
    fast = inverse_compositional_lk(ref_img, img, centres, 9, reference_mask=mask, image_mask=mask, precomputed=pre)
    for a, b in zip(plain, fast):
        assert torch.equal(a, b)
    ref = build_dissimilarity_reference(ref_img, mask)
    assert ref.lk is not None
    without = type(ref)(ref.image, ref.mask, ref.centres, ref.patch_valid, ref.score, ref.config)
    for a, b in zip(dissimilarity(ref, img, mask, TORCH), dissimilarity(without, img, mask, TORCH)):
        assert torch.equal(a, b)
    one = ref.select(torch.tensor([1]))
    for a, b in zip(dissimilarity(one, img[1:], mask[1:], TORCH), dissimilarity(ref, img, mask, TORCH)):
        assert torch.equal(a[0], b[1])


# ---------------------------------------------------------------- the native kernel against the torch code


def _native_cases():
    """Faces against one reference per stream: moved by sub-pixel to 2.5 pixel shifts, noisy, half masked, a
    different face, flat (ill-posed patches), empty, NaN, and moved beyond ``max_displacement``."""
    face, mask = _face(batch=1)
    shifts = torch.tensor([[0.3, 0.0], [1.0, 0.5], [2.0, -1.5], [-2.5, 0.7]], dtype=torch.float64)
    faces = [_shift(face.expand(4, -1, -1, -1), shifts) * mask]
    masks = [mask.expand(4, -1, -1, -1)]
    g = torch.Generator().manual_seed(9)
    faces.append((face + 0.3 * torch.rand(face.shape, generator=g, dtype=torch.float64)) * mask)
    masks.append(mask)
    half = mask.clone()
    half[..., :, 48:] = 0.0
    faces += [face * half, _face(batch=1, seed=11)[0], torch.full_like(face, 0.5) * mask, face * 0,
              torch.full_like(face, float("nan")), _shift(face, torch.tensor([[6.0, 4.0]], dtype=torch.float64)) * mask]
    masks += [half, mask, mask, torch.zeros_like(mask), mask, mask]
    faces, masks = torch.cat(faces), torch.cat(masks)
    ref = build_dissimilarity_reference(face.expand(faces.shape[0], -1, -1, -1), mask.expand(faces.shape[0], -1, -1, -1))
    return ref, faces, masks


@requires_native
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_native_dissimilarity_equals_the_torch_code(dtype):
    """The native smoothing and patch tracking (each patch on its own) give the torch code's displacements,
    flags and supports, so the same dissimilarity and confidence: to rounding in float64, to float tolerance in
    float32; the cases include ill-posed, empty, NaN and runaway patches."""
    ref, faces, masks = _native_cases()
    if dtype == torch.float32:
        face0, mask0 = _face(batch=1)
        ref = build_dissimilarity_reference(face0.expand(faces.shape[0], -1, -1, -1).float(),
                                            mask0.expand(faces.shape[0], -1, -1, -1).float())  # fmt: skip
        faces, masks = faces.float(), masks.float()
    nat = dissimilarity(ref, faces, masks, NATIVE)
    tor = dissimilarity(ref, faces, masks, TORCH)
    tol, rtol = (1e-9, 0.0) if dtype == torch.float64 else (2e-4, 1e-4)
    assert torch.equal(nat.present, tor.present)
    both = torch.isfinite(tor.displacement)
    assert torch.equal(both, torch.isfinite(nat.displacement))
    torch.testing.assert_close(nat.displacement[both], tor.displacement[both], rtol=rtol, atol=tol)
    torch.testing.assert_close(nat.dissimilarity, tor.dissimilarity, rtol=0, atol=tol)
    torch.testing.assert_close(nat.confidence, tor.confidence, rtol=0, atol=tol)
    assert bool(torch.isfinite(nat.confidence).all())
    # the cases do what they are for: small shifts found, runaway and empty faces at zero confidence
    assert float(nat.confidence[0]) > 0.9 and float(nat.confidence[-1]) < 0.05 and float(nat.confidence[-3]) == 0.0


@requires_native
def test_native_dissimilarity_is_each_stream_alone_and_independent_of_threads():
    ref, faces, masks = _native_cases()
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = dissimilarity(ref, faces, masks, NATIVE)
        torch.set_num_threads(3)
        three = dissimilarity(ref, faces, masks, NATIVE)
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(one, three):
        assert torch.equal(a.nan_to_num(), b.nan_to_num())
    for b in (0, 5):
        alone = dissimilarity(ref.select(torch.tensor([b])), faces[b : b + 1], masks[b : b + 1], NATIVE)
        for x, y in zip(alone, one):
            assert torch.equal(x[0].nan_to_num(), y[b].nan_to_num())


def test_backend_native_without_precomputed_patches_is_an_error():
    face, mask = _face(batch=1)
    ref = build_dissimilarity_reference(face, mask)
    without = type(ref)(ref.image, ref.mask, ref.centres, ref.patch_valid, ref.score, ref.config)
    with pytest.raises(RuntimeError, match="native"):
        dissimilarity(without, face, mask, NATIVE)


@requires_native
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_native_reference_picks_the_torch_codes_patches(dtype):
    """The native smoothing, texture score and suppression pick the torch code's patches (the same centres and
    validity, scores and template to rounding): textured faces, half-masked ones, a flat one (no patch) and one
    with few textured places (fewer patches than asked for)."""
    face, mask = _face(batch=2)
    half = mask.clone()
    half[1, :, :, 48:] = 0.0
    flat = torch.full_like(face[:1], 0.5) * mask[:1]
    small = mask[:1].clone()
    small[..., :30, :] = 0.0
    small[..., 60:, :] = 0.0
    faces = torch.cat([face, face[1:] * half[1:], flat, face[:1] * small]).to(dtype)
    masks = torch.cat([mask, half[1:], mask[:1], small]).to(dtype)
    for cfg in (DissimilarityConfig(), DissimilarityConfig(patch_size=9, num_patches=24, border=1)):
        nat = build_dissimilarity_reference(faces, masks, cfg, NATIVE)
        ref = build_dissimilarity_reference(faces, masks, cfg, TORCH)
        assert torch.equal(nat.centres, ref.centres) and torch.equal(nat.patch_valid, ref.patch_valid)
        tol = 1e-10 if dtype == torch.float64 else 2e-5
        torch.testing.assert_close(nat.image, ref.image, rtol=0, atol=tol)
        torch.testing.assert_close(nat.score, ref.score, rtol=1e-4, atol=tol)
        for a, b in zip(nat.lk, ref.lk):
            torch.testing.assert_close(a, b, rtol=0, atol=tol)
        valid = nat.patch_valid.sum(-1)
        assert int(valid[0]) == cfg.num_patches and int(valid[3]) == 0 and 0 < int(valid[4]) < cfg.num_patches


@pytest.mark.parametrize("backend", [Backend.AUTO, Backend.TORCH])
def test_an_empty_batch_gives_empty_results(backend):
    """B = 0 faces: an empty reference and empty results with either implementation (the torch code's patch
    suppression raised "cannot reshape tensor of 0 elements into shape [0, -1]"; the native kernel's did not)."""
    faces, masks = torch.rand(0, 3, 64, 64), torch.ones(0, 1, 64, 64)
    ref = build_dissimilarity_reference(faces, masks, backend=backend)
    K = ref.config.num_patches
    assert ref.centres.shape == (0, K, 2) and ref.patch_valid.shape == (0, K)
    d, conf, displacement, present = dissimilarity(ref, faces, masks, backend=backend)
    assert d.shape == conf.shape == (0,) and displacement.shape == (0, K, 2) and present.shape == (0, K)
