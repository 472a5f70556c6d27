"""Tests of torchface.template.management: settings, pose bins, the mosaic's book-keeping, rebuilding stored
templates, light normalisation, the face-inside test, the dissimilarity confidence of a rendered frame and
the mosaic search (known answers on a rendered 160x120 frame)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from torchface.appearance.illumination import apply_illumination, illumination_basis
from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import euler_to_matrix, matrix_to_axis_angle, matrix_to_euler
from torchface.model.candide import load_candide3
from torchface.normalise.face import build_normalised_layout
from torchface.synth.background import BackgroundSpec
from torchface.synth.scenarios import default_light
from torchface.synth.sequence import SequenceSpec, render_sequence
from torchface.template.dissimilarity import build_dissimilarity_reference
from torchface.template.management import (
    TemplateConfig,
    add_entries,
    entry_templates,
    face_inside_fraction,
    frame_dissimilarity,
    has_bin,
    within_reach,
    light_normalised_intensity,
    new_mosaic,
    pose_bins,
    reference_face,
    search_mosaic,
    nearest_entries,
    select_entries,
)
from torchface.template.points import build_template
from torchface.tracker.fit import FitConfig, fit_landmarks

W, H = 320, 240
D = torch.float64


@pytest.fixture(scope="module")
def model():
    return load_candide3(dtype=D)


@pytest.fixture(scope="module")
def scene(model):
    """Two rendered frames (frontal; yaw 20 deg, moved) with their ground truth and the first frame's templates."""
    ypr = torch.tensor([[0.0, 0.0, 0.0], [20.0, -5.0, 3.0]], dtype=D)
    spec = SequenceSpec(
        name="m", subject="candide3", intrinsics=Intrinsics.default(W, H), rotation=euler_to_matrix(ypr),
        translation=torch.tensor([[0.0, 0.0, 450.0], [-40.0, 15.0, 470.0]], dtype=D),
        anim=torch.zeros(2, model.num_animation, dtype=D), light=default_light(2), background=BackgroundSpec(seed=3),
    )  # fmt: skip
    frames, gt = render_sequence(spec)
    frames = frames.to(D)
    # exact landmarks: nothing to hold against noise (FitConfig.held_shape_units), so the shape fits the render's
    fit = fit_landmarks(model, gt.landmarks_px[:1].to(D), gt.intrinsics, config=FitConfig(held_shape_units=()))
    gray = frames[:1].mean(1, keepdim=True)
    tpl = build_template(model, fit.shape_coeffs, fit.anim_coeffs, fit.rotation, fit.translation, gray, gt.intrinsics,
                         max_points=800, gradient_threshold=0.01)  # fmt: skip
    return frames, gt, fit, tpl


# ---------------------------------------------------------------- settings and pose bins


def test_config_defaults_and_validation():
    cfg = TemplateConfig()
    assert cfg.enabled and cfg.mosaic and not cfg.texture_update
    with pytest.raises(ValueError):
        TemplateConfig(lost_after=0)
    with pytest.raises(ValueError):
        TemplateConfig(confidence_threshold=1.5)
    with pytest.raises(ValueError):
        TemplateConfig(yaw_bin_deg=0.0)
    with pytest.raises(ValueError):
        TemplateConfig(search_depth_factors=())
    with pytest.raises(ValueError, match="adopt_min_angle_deg"):
        TemplateConfig(adopt_min_angle_deg=-1.0)
    with pytest.raises(ValueError, match="adopt_min_confidence"):
        TemplateConfig(adopt_min_confidence=1.5)
    with pytest.raises(TypeError):
        TemplateConfig(enabled=1)  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        TemplateConfig(dissimilarity=None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="entry_stride"):
        TemplateConfig(entry_stride=0)
    with pytest.raises(TypeError, match="entry_stride"):
        TemplateConfig(entry_stride=2.0)  # type: ignore[arg-type]
    for small in (16, 47):  # 16 used to pass: no fiducial patch fitted, so every frame's confidence was 0
        with pytest.raises(ValueError, match="too few fiducial patches"):
            TemplateConfig(normalised_size=small)
    assert TemplateConfig(normalised_size=48).normalised_size == 48
    assert TemplateConfig().restart_after_unmatched == 0  # off: a face-borne occluder also restarts (README)
    with pytest.raises(ValueError, match="restart_after_unmatched"):
        TemplateConfig(restart_after_unmatched=-1)
    # An infinite (or NaN) grid step passed as positive: the first recovery's search raised a RuntimeError ("cannot
    # reshape tensor of 0 elements"; its coarse grid was empty and its fine one int(inf) wide)
    for step in (float("inf"), float("nan")):
        with pytest.raises(ValueError, match="search_step_px"):
            TemplateConfig(search_step_px=step)
    # NaN margins passed "< 0" (every comparison with NaN is False: the tracker never changed entry, or never
    # aligned against the first frame's near it)
    for name in ("switch_margin_deg", "reference_radius_deg", "adopt_min_angle_deg"):
        with pytest.raises(ValueError, match=rf"^{name} must be a finite number >= 0, got nan"):
            TemplateConfig(**{name: float("nan")})


def test_confidence_threshold_above_recover_confidence_is_refused():
    """A stream is lost after ``lost_after`` frames below ``confidence_threshold`` and the loss ends at a frame reaching
    ``recover_confidence``: with the threshold above it, a frame between the two counted toward a loss and ended it at
    once, so ``lost_after`` did nothing (``confidence_threshold=0.99, lost_after=1`` reported status 0 at confidence
    0.56 on every frame). Refused, saying to raise both; equal ones and the defaults are taken."""
    with pytest.raises(ValueError, match=r"confidence_threshold \(0\.99\) must not exceed recover_confidence "
                                         r"\(0\.35\).*TemplateConfig\(confidence_threshold=0\.99, "
                                         r"recover_confidence=0\.99\)"):  # fmt: skip
        TemplateConfig(confidence_threshold=0.99, lost_after=1)
    with pytest.raises(ValueError, match="must not exceed recover_confidence"):
        replace(TemplateConfig(), recover_confidence=0.2)
    assert TemplateConfig(confidence_threshold=0.99, recover_confidence=0.99).lost_after == 15
    assert TemplateConfig(confidence_threshold=0.35).recover_confidence == 0.35
    default = TemplateConfig()
    assert (default.confidence_threshold, default.recover_confidence) == (0.3, 0.35)


def test_pose_bins_known_answers():
    cfg = TemplateConfig(yaw_bin_deg=15.0, pitch_bin_deg=10.0, bin_centre_fraction=0.25)
    ypr = torch.tensor([[0.0, 0.0, 40.0], [16.0, -9.0, 0.0], [7.4, 2.4, 0.0], [7.6, 0.0, 0.0], [-31.0, 21.0, 0.0]])
    bins, near = pose_bins(ypr, cfg)
    assert bins.tolist() == [[0, 0], [1, -1], [0, 0], [1, 0], [-2, 2]]
    # within 0.25 bin widths of the centre on both axes (roll ignored)
    assert near.tolist() == [True, True, False, False, True]


def test_pose_bins_relative_to_an_origin():
    """With an origin, the bins are those of the angles less the origin's (the mosaic's reference pose)."""
    cfg = TemplateConfig(yaw_bin_deg=15.0, pitch_bin_deg=10.0, bin_centre_fraction=0.25)
    ypr = torch.tensor([[0.0, 0.0, 40.0], [16.0, -9.0, 0.0], [7.4, 2.4, 0.0], [7.6, 0.0, 0.0], [-35.0, 16.0, 0.0]])
    origin = torch.tensor([[-5.0, 6.0, 30.0]]).expand(5, 3)
    bins, near = pose_bins(ypr, cfg, origin_deg=origin)
    want_bins, want_near = pose_bins(ypr - origin, cfg)
    assert torch.equal(bins, want_bins) and torch.equal(near, want_near)
    assert bins.tolist() == [[0, -1], [1, -1], [1, 0], [1, -1], [-2, 1]]
    assert near.tolist() == [False, False, False, False, True]
    # A pose is in bin (0, 0), at its centre, against itself.
    bins, near = pose_bins(ypr, cfg, origin_deg=ypr)
    assert bins.eq(0).all() and near.all()


# ---------------------------------------------------------------- the mosaic


def _fake_templates(B: int, N: int, seed: int, levels: int = 2):
    from torchface.template.points import Template

    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(levels):
        out.append(Template(
            torch.randint(0, 100, (B, N), generator=g), torch.rand(B, N, 3, generator=g, dtype=D),
            torch.randn(B, N, 3, generator=g, dtype=D), torch.randn(B, N, 3, 2, generator=g, dtype=D),
            torch.randn(B, N, 3, generator=g, dtype=D), torch.rand(B, N, generator=g, dtype=D),
            torch.rand(B, N, generator=g) > 0.2,
        ))  # fmt: skip
    return tuple(out)


def _fake_reference(B: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    return build_dissimilarity_reference(torch.rand(B, 1, 32, 32, generator=g, dtype=D), torch.ones(B, 1, 32, 32, dtype=D))


def test_mosaic_add_select_and_grow():
    cfg = TemplateConfig()
    B, N = 3, 10
    ref = _fake_reference(B, seed=0)
    ypr0 = torch.zeros(B, 3, dtype=D)
    m = new_mosaic(_fake_templates(B, N, 0), euler_to_matrix(ypr0), ypr0, ref, cfg)
    assert m.capacity == 1 and m.num_entries.tolist() == [1, 1, 1]
    # Stream 1 and 2 get an entry at yaw 30; stream 2 another at yaw -30: the storage grows to 2 slots, then 4.
    ypr = torch.tensor([[30.0, 0.0, 0.0], [30.0, 0.0, 0.0]], dtype=D)
    bins, _ = pose_bins(ypr, cfg)
    new = _fake_templates(2, N, 1)
    new_ref = _fake_reference(2, seed=1)
    m, slots = add_entries(m, torch.tensor([1, 2]), new, euler_to_matrix(ypr), bins, new_ref)
    assert slots.tolist() == [1, 1] and m.capacity == 2 and m.num_entries.tolist() == [1, 2, 2]
    assert torch.equal(m.levels[1].intensity[2, 1], new[1].intensity[1])
    assert not m.levels[0].valid[0, 1].any()  # stream 0's unused slot holds nothing
    # Each entry keeps its own dissimilarity reference (Lucas-Kanade side included).
    got = m.references.select((torch.tensor([0, 2, 2]), torch.tensor([0, 0, 1])))
    assert torch.equal(got.image[0], ref.image[0]) and torch.equal(got.image[1], ref.image[2])
    assert torch.equal(got.image[2], new_ref.image[1]) and torch.equal(got.lk.sd[2], new_ref.lk.sd[1])
    assert not m.references.patch_valid[0, 1].any()
    ypr2 = torch.tensor([[-30.0, 0.0, 0.0]], dtype=D)
    bins2 = pose_bins(ypr2, cfg)[0]
    m, slots = add_entries(m, torch.tensor([2]), _fake_templates(1, N, 2), euler_to_matrix(ypr2), bins2,
                           _fake_reference(1, seed=2))  # fmt: skip
    assert slots.tolist() == [2] and m.capacity == 4 and m.num_entries.tolist() == [1, 2, 3]
    assert not m.used[:, 3].any() and not m.levels[0].valid[:, 3].any()  # the slot grown ahead holds nothing
    assert has_bin(m, torch.tensor([[2, 0], [2, 0], [-2, 0]])).tolist() == [False, True, True]
    # a subset of the streams, in any order: the same answers as their rows of the whole batch
    assert has_bin(m, torch.tensor([[-2, 0], [2, 0]]), streams=torch.tensor([2, 0])).tolist() == [True, False]
    # Selection: nearest entry in yaw/pitch among the used ones, with hysteresis.
    now = torch.tensor([[25.0, 0.0, 0.0], [25.0, 0.0, 0.0], [-20.0, 0.0, 0.0]], dtype=D)
    cur = torch.zeros(B, dtype=torch.int64)
    assert select_entries(m, now, cur, 2.0).tolist() == [0, 1, 2]
    mid = torch.tensor([[0.0, 0.0, 0.0], [15.5, 0.0, 0.0], [13.0, 0.0, 0.0]], dtype=D)
    # 15.5 deg: entry 1 (30) is 14.5 away, entry 0 15.5: within the 2 deg margin, keep the current one (0);
    # 13 deg from entry 1 (17 away): entry 0 (13 away) is nearer by more than the margin.
    assert select_entries(m, mid, torch.tensor([0, 0, 1]), 2.0).tolist() == [0, 0, 0]
    assert select_entries(m, mid, torch.tensor([0, 0, 1]), 0.0).tolist() == [0, 1, 0]
    sub = select_entries(m, now[1:], torch.zeros(2, dtype=torch.int64), 0.0, streams=torch.tensor([1, 2]))
    assert sub.tolist() == [1, 2]
    # nearest_entries: select_entries with no margin or radius from entry 0 (halfway between entries 0 and 1,
    # 15 deg of yaw, either may be nearer by rounding: both pick the same).
    half = torch.tensor([[15.0, 0.0, 0.0], [15.0, 0.0, 0.0], [-15.0, 5.0, 0.0]], dtype=D)
    for poses in (now, mid, half, now + torch.tensor([0.0, 9.0, 0.0], dtype=D)):
        assert torch.equal(nearest_entries(m, poses), select_entries(m, poses, cur, 0.0))
    assert nearest_entries(m, now).tolist() == [0, 1, 2]
    assert torch.equal(nearest_entries(m, now[1:], streams=torch.tensor([1, 2])), sub)
    # Within the reference radius (20) the reference is used although entry 1 is nearer; a stream on entry 1
    # comes back once the margin (2) inside; beyond the radius the nearest entry.
    near = torch.tensor([[25.0, 0.0, 0.0], [19.0, 0.0, 0.0], [17.0, 0.0, 0.0]], dtype=D)
    got = select_entries(m, near, torch.tensor([0, 1, 1]), 2.0, reference_radius_deg=20.0)
    assert got.tolist() == [0, 1, 0]
    # A new entry must be within 1.5 bins (22.5 deg of yaw or pitch) of one the stream has.
    reach = within_reach(m, torch.tensor([[30.0, 0.0, 0.0], [50.0, 10.0, 0.0], [-45.0, -20.0, 0.0]], dtype=D), cfg)
    assert reach.tolist() == [False, True, True]
    far = torch.tensor([[25.0, 0.0, 0.0], [25.0, 0.0, 0.0], [-25.0, 0.0, 0.0]], dtype=D)
    assert select_entries(m, far, cur, 2.0, reference_radius_deg=20.0).tolist() == [0, 1, 2]
    # The stored yaw/pitch/roll of every used entry is its rotation's, through adding and growing.
    assert torch.equal(m.ypr_deg[m.used], matrix_to_euler(m.rotation[m.used]))


def test_mosaic_storage_grows_by_doubling_in_chunks_of_at_most_four_up_to_max_capacity():
    """add_entries grows the mosaic's storage by several slots at once (it grew one slot at a time: every per-entry
    tensor copied at each new entry beyond the last), so most entries are written in place into slots grown
    before; never beyond ``max_capacity`` unless the entries need more. The entries' values are those added."""
    cfg = TemplateConfig()
    B, N = 2, 10
    ypr0 = torch.zeros(B, 3, dtype=D)
    stream = torch.tensor([1])

    def grow(limit, additions):
        m = new_mosaic(_fake_templates(B, N, 0), euler_to_matrix(ypr0), ypr0, _fake_reference(B, seed=0), cfg)
        capacities, copies, added, rotations = [], 0, [], []
        for k in range(1, additions + 1):
            ypr = torch.tensor([[5.0 * k, 0.0, 0.0]], dtype=D)
            t, r = _fake_templates(1, N, k), _fake_reference(1, seed=k)
            rotations.append(euler_to_matrix(ypr)[0])
            new, slot = add_entries(m, stream, t, rotations[-1][None], pose_bins(ypr, cfg)[0], r, max_capacity=limit)
            assert slot.tolist() == [k]
            copies += new.levels[0].intensity is not m.levels[0].intensity
            m = new
            capacities.append(m.capacity)
            added.append((t, r))
        return m, capacities, copies, added, rotations

    m, capacities, copies, added, rotations = grow(16, 17)
    assert capacities == [2, 4, 4, 8, 8, 8, 8, 12, 12, 12, 12, 16, 16, 16, 16, 17, 18]  # the limit: then as needed
    assert copies == 7  # one per growth (it was 17)
    assert m.num_entries.tolist() == [1, 18] and not m.used[0, 1:].any()
    for k, (t, r) in enumerate(added, start=1):
        assert torch.equal(m.levels[1].intensity[1, k], t[1].intensity[0])
        assert torch.equal(m.references.image[1, k], r.image[0]) and torch.equal(m.rotation[1, k], rotations[k - 1])
    assert grow(None, 17)[1][11:] == [16, 16, 16, 16, 20, 20]  # no limit: chunks of 4 on
    assert grow(5, 6)[1] == [2, 4, 4, 5, 6, 7] and grow(3, 3)[1] == [2, 3, 4]
    assert grow(1, 2)[1] == [2, 3]  # a limit below what the entries need: what they need
    # a count or None: "16" was "'<' not supported between 'str' and 'int'" from inside the growth, 0 or True taken
    m = new_mosaic(_fake_templates(B, N, 0), euler_to_matrix(ypr0), ypr0, _fake_reference(B, seed=0), cfg)
    args = (m, stream, _fake_templates(1, N, 1), euler_to_matrix(ypr0[:1]), pose_bins(ypr0[:1], cfg)[0],
            _fake_reference(1, seed=1))  # fmt: skip
    for bad, error in (("16", TypeError), (2.0, TypeError), (True, TypeError), (0, ValueError)):
        with pytest.raises(error, match=r"max_capacity must be an int >= 1 or None, got"):
            add_entries(*args, max_capacity=bad)


def test_add_entries_shares_storage_only_where_no_other_mosaic_wrote():
    """add_entries writes in place into storage it shares with the mosaic it was given only at slots never
    written there: the given mosaic keeps its value, and a second entry added from it (a branch) is copied rather
    than overwrite the first branch's entry; with a gradient involved it always copies."""
    cfg = TemplateConfig()
    B, N = 3, 10
    ypr0 = torch.zeros(B, 3, dtype=D)
    m0 = new_mosaic(_fake_templates(B, N, 0), euler_to_matrix(ypr0), ypr0, _fake_reference(B, seed=0), cfg)
    ypr = torch.tensor([[30.0, 0.0, 0.0]], dtype=D)
    bins, one = pose_bins(ypr, cfg)[0], torch.tensor([0])

    def add(m, seed, stream=one):
        t, r = _fake_templates(1, N, seed), _fake_reference(1, seed=seed)
        return add_entries(m, stream, t, euler_to_matrix(ypr), bins, r)[0], t, r

    m1, t1, _ = add(m0, 1)  # grows: new storage
    assert m1.levels[0].intensity is not m0.levels[0].intensity
    snapshot = [x.clone() for lv in m1.levels for x in (lv.face_index, lv.bary, lv.intensity, lv.valid)]
    m2, t2, r2 = add(m1, 2, torch.tensor([1]))  # stream 1's slot 1 was never written: in place
    assert m2.levels[0].intensity is m1.levels[0].intensity and m2.references.image is m1.references.image
    assert m1.num_entries.tolist() == [2, 1, 1] and m2.num_entries.tolist() == [2, 2, 1]
    for x, y in zip((x for lv in m1.levels for x in (lv.face_index, lv.bary, lv.intensity, lv.valid)), snapshot):
        assert torch.equal(x[0], y[0]) and torch.equal(x[1, 0], y[1, 0])  # m1's used entries unchanged
    # A branch from m1 writing stream 1's slot 1 again copies: m2's entry survives.
    m3, t3, r3 = add(m1, 3, torch.tensor([1]))
    assert m3.levels[0].intensity is not m1.levels[0].intensity
    assert torch.equal(m2.levels[1].intensity[1, 1], t2[1].intensity[0])
    assert torch.equal(m3.levels[1].intensity[1, 1], t3[1].intensity[0])
    assert torch.equal(m2.references.image[1, 1], r2.image[0]) and torch.equal(m3.references.image[1, 1], r3.image[0])
    # m3 owns its copy: its next entry goes in place, and m2 is not touched by it.
    m4, t4, _ = add(m3, 4, torch.tensor([2]))
    assert m4.levels[0].intensity is m3.levels[0].intensity
    assert torch.equal(m4.levels[0].intensity[2, 1], t4[0].intensity[0])
    assert torch.equal(m2.levels[1].intensity[1, 1], t2[1].intensity[0]) and m2.num_entries.tolist() == [2, 2, 1]
    # Templates that require grad: copied, and the gradient reaches them.
    t = _fake_templates(1, N, 5)
    t = tuple(replace(x, intensity=x.intensity.clone().requires_grad_()) for x in t)
    m5, _ = add_entries(m2, torch.tensor([2]), t, euler_to_matrix(ypr), bins, _fake_reference(1, seed=5))
    assert m5.levels[0].intensity is not m2.levels[0].intensity
    m5.levels[0].intensity[2, 1].sum().backward()
    assert torch.equal(t[0].intensity.grad, torch.ones(1, N, dtype=D))


def test_entry_templates_rebuild_the_stored_template(model, scene):
    frames, gt, fit, tpl = scene
    cfg = TemplateConfig()
    ref = build_dissimilarity_reference(torch.rand(1, 1, 32, 32, dtype=D), torch.ones(1, 1, 32, 32, dtype=D))
    m = new_mosaic((tpl,), fit.rotation, matrix_to_euler(fit.rotation), ref, cfg)
    (again,) = entry_templates(model, fit.shape_coeffs, m, torch.tensor([0]), torch.tensor([0]))
    for name in ("face_index", "bary", "points", "basis", "normals", "intensity", "valid"):
        assert torch.equal(getattr(again, name), getattr(tpl, name)), name


def test_light_normalised_intensity_inverts_eq19(scene):
    *_, tpl = scene
    R = euler_to_matrix(torch.tensor([[10.0, 5.0, 0.0]], dtype=D))
    light = torch.tensor([[0.3, 0.05, 0.1, -0.2, 0.15]], dtype=D)
    basis = illumination_basis(tpl.intensity, torch.matmul(tpl.normals, R.transpose(1, 2)))
    seen = apply_illumination(tpl.intensity, basis, light)
    back = light_normalised_intensity(seen, tpl.normals, R, light)
    assert torch.allclose(back, tpl.intensity, atol=1e-10)


def test_face_inside_fraction(model, scene):
    _, gt, fit, _ = scene
    verts = torch.matmul(model.deform(fit.shape_coeffs, None), fit.rotation.transpose(1, 2)) + fit.translation[:, None]
    assert float(face_inside_fraction(model, verts, gt.intrinsics)[0]) == 1.0
    shifted = verts + torch.tensor([400.0, 0.0, 0.0], dtype=D)  # far to the right of the frame
    behind = verts * torch.tensor([1.0, 1.0, -1.0], dtype=D)
    out = face_inside_fraction(model, torch.cat([shifted, behind]), gt.intrinsics)
    assert out.tolist() == [0.0, 0.0]
    half = verts + torch.tensor([verts[0, :, 2].mean() * (W / 2 - 0.5) / gt.intrinsics.fx - verts[0, :, 0].mean(), 0.0,
                                 0.0], dtype=D)  # fmt: skip
    assert 0.3 < float(face_inside_fraction(model, half, gt.intrinsics)[0]) < 0.7


# ---------------------------------------------------------------- dissimilarity confidence and search


def test_frame_dissimilarity_high_at_truth_low_when_wrong(model, scene):
    frames, gt, fit, _ = scene
    cfg = TemplateConfig()
    layout = build_normalised_layout(model, cfg.normalised_size)
    alpha = torch.zeros(1, model.num_animation, dtype=D)
    light = torch.zeros(1, 5, dtype=D)
    aa0 = matrix_to_axis_angle(gt.rotation[:1].to(D))
    t0 = gt.translation[:1].to(D)
    image, mask = reference_face(frames[:1], model, layout, fit.shape_coeffs, alpha, aa0, t0, light, gt.intrinsics, cfg)
    ref = build_dissimilarity_reference(image, mask, cfg.dissimilarity)
    # Frame 1 at its true pose, and frame 1 with the pose off by 6 degrees of yaw and 8 mm.
    aa1 = matrix_to_axis_angle(gt.rotation[1:].to(D))
    t1 = gt.translation[1:].to(D)
    R_bad = euler_to_matrix(torch.tensor([[6.0, 0.0, 0.0]], dtype=D)) @ gt.rotation[1:].to(D)
    aa = torch.cat([aa1, matrix_to_axis_angle(R_bad)])
    t = torch.cat([t1, t1 + torch.tensor([[8.0, 0.0, 0.0]], dtype=D)])
    shape = fit.shape_coeffs.expand(2, -1)
    out = frame_dissimilarity(frames[1:].expand(2, -1, -1, -1), model, layout, ref, shape, alpha.expand(2, -1), aa, t,
                              light.expand(2, -1), gt.intrinsics, cfg)  # fmt: skip
    assert out.confidence[0] > 0.5, out.confidence  # the fitted shape is not the rendered one: not exactly 1
    assert out.confidence[1] < 0.05 and out.dissimilarity[1] > 2 * out.dissimilarity[0], out
    assert torch.isfinite(out.dissimilarity).all()


def _half_size_mosaic(model, scene, cfg):
    """One pyramid level at half size: its camera, frame 0's gray image and a mosaic of frame 0's template."""
    frames, gt, fit, _ = scene
    ref = build_dissimilarity_reference(torch.rand(1, 1, 32, 32, dtype=D), torch.ones(1, 1, 32, 32, dtype=D))
    gray0 = torch.nn.functional.avg_pool2d(frames[:1].mean(1, keepdim=True), 2)
    intr = Intrinsics(W // 2, H // 2, gt.intrinsics.fx / 2, gt.intrinsics.fy / 2, (gt.intrinsics.cx + 0.5) / 2 - 0.5,
                      (gt.intrinsics.cy + 0.5) / 2 - 0.5)  # fmt: skip
    tpl0 = build_template(model, fit.shape_coeffs, fit.anim_coeffs, fit.rotation, fit.translation, gray0, intr,
                          max_points=600, gradient_threshold=0.01)  # fmt: skip
    return intr, gray0, ref, new_mosaic((tpl0,), fit.rotation, matrix_to_euler(fit.rotation), ref, cfg)


def test_search_mosaic_finds_the_moved_face(model, scene):
    frames, gt, fit, tpl = scene
    cfg = TemplateConfig(search_step_px=2.0)
    intr, _, ref, m = _half_size_mosaic(model, scene, cfg)
    # A second entry at yaw 20 (the frame-1 pose) so that the right hypothesis exists.
    R1 = gt.rotation[1:].to(D)
    tpl1 = build_template(model, fit.shape_coeffs, fit.anim_coeffs, R1, gt.translation[1:].to(D),
                          torch.nn.functional.avg_pool2d(frames[1:].mean(1, keepdim=True), 2), intr, max_points=600,
                          gradient_threshold=0.01)  # fmt: skip
    m, _ = add_entries(m, torch.tensor([0]), (tpl1,), R1, torch.tensor([[1, 0]]), ref)
    gray1 = torch.nn.functional.avg_pool2d(frames[1:].mean(1, keepdim=True), 2)
    hit = search_mosaic(model, fit.shape_coeffs, m, 0, gray1, intr, 0, float(fit.translation[0, 2]), None, cfg)
    assert hit.entry == 1 and hit.score > 0.5
    # The head origin projects within a few (half-size) pixels of the truth.
    def origin_px(t):
        return torch.stack([intr.fx * t[0] / t[2] + intr.cx, intr.fy * t[1] / t[2] + intr.cy])

    err = (origin_px(hit.translation) - origin_px(gt.translation[1].to(D))).norm()
    assert float(err) < 4.0, float(err)
    assert math.isfinite(hit.score)


def test_search_mosaic_refuses_an_image_it_cannot_halve(model, scene):
    """The search's first stage runs on ``gray`` halved once more: a 1-pixel-high image was avg_pool2d's "Output
    size is too small" RuntimeError (the coarsest level of 8x6 frames with three levels); now a clear ValueError."""
    _, _, fit, _ = scene
    cfg = TemplateConfig()
    intr, gray0, _, m = _half_size_mosaic(model, scene, cfg)
    depth = float(fit.translation[0, 2])
    for bad in (gray0[..., :1, :], gray0[..., :, :1], gray0[0]):
        with pytest.raises(ValueError, match=r"gray must be \(1, 1, h, w\) with h, w >= 2"):
            search_mosaic(model, fit.shape_coeffs, m, 0, bad, intr, 0, depth, None, cfg)
    assert search_mosaic(model, fit.shape_coeffs, m, 0, gray0[..., :2, :2], intr, 0, depth, None, cfg).score <= 1.0


def test_search_mosaic_places_nothing_from_an_entry_without_points(model, scene):
    """An entry with no valid points at the searched level (the coarsest levels of small frames) was "placed"
    with score 0 everywhere (no points inside counted as enough of them), a score that outranked every real
    placement below 0; now nothing is placed (-1, as the docstring says)."""
    _, _, fit, _ = scene
    cfg = TemplateConfig()
    intr, gray0, _, m = _half_size_mosaic(model, scene, cfg)
    depth = float(fit.translation[0, 2])
    assert search_mosaic(model, fit.shape_coeffs, m, 0, gray0, intr, 0, depth, None, cfg).score > 0.5
    lv = m.levels[0]
    empty = replace(m, levels=(replace(lv, valid=torch.zeros_like(lv.valid)),))
    assert search_mosaic(model, fit.shape_coeffs, empty, 0, gray0, intr, 0, depth, None, cfg).score == -1.0


def test_search_mosaic_leaves_out_nan_pixels(model, scene):
    """NaN frame pixels are missing data: the search finds the face as in the same frame without them. A NaN
    sample made its placement's score NaN, which topk ranked first and no comparison accepted, so one NaN row far
    from the face left the search empty (score -1) and a lost stream without a detector was never recovered."""
    frames, gt, fit, _ = scene
    cfg = TemplateConfig(search_step_px=2.0)
    intr, gray0, _, m = _half_size_mosaic(model, scene, cfg)
    depth = float(fit.translation[0, 2])
    clean = search_mosaic(model, fit.shape_coeffs, m, 0, gray0, intr, 0, depth, None, cfg)
    holed = gray0.clone()
    holed[..., :1, :] = float("nan")  # the top row
    holed[..., 50:53, 70:73] = float("nan")  # and a few pixels on the face
    hit = search_mosaic(model, fit.shape_coeffs, m, 0, holed, intr, 0, depth, None, cfg)
    assert clean.score > 0.5 and hit.score > 0.5 and hit.entry == clean.entry, (clean.score, hit.score)
    assert float((hit.translation - clean.translation).norm()) < 3.0


def test_search_mosaic_leaves_out_non_finite_template_intensities(model, scene):
    """An entry point with an infinite intensity (an entry built from a frame with infinite pixels: only the first
    frames are range-checked) is left out of the correlation; it made every placement of that entry NaN, and the
    search came back empty."""
    from dataclasses import replace

    frames, gt, fit, _ = scene
    cfg = TemplateConfig(search_step_px=2.0)
    intr, gray0, _, m = _half_size_mosaic(model, scene, cfg)
    depth = float(fit.translation[0, 2])
    clean = search_mosaic(model, fit.shape_coeffs, m, 0, gray0, intr, 0, depth, None, cfg)
    lv = m.levels[0]
    bad = lv.intensity.clone()
    bad[0, 0, :3] = float("inf")
    m = replace(m, levels=(replace(lv, intensity=bad),) + m.levels[1:])
    hit = search_mosaic(model, fit.shape_coeffs, m, 0, gray0, intr, 0, depth, None, cfg)
    assert clean.score > 0.5 and hit.score > 0.5, (clean.score, hit.score)
    assert float((hit.translation - clean.translation).norm()) < 3.0


def test_search_mosaic_widened_depths_find_a_face_that_came_back_farther(model, scene):
    """A lost face back at 1.6 times its last confident depth lies outside the searched depths (0.85-1.2 of it):
    the later attempts' widened depths (``search_depth_widening``, here 1.45) find it where it is."""
    _, _, fit, _ = scene
    cfg = TemplateConfig(search_step_px=2.0)
    intr, gray0, _, m = _half_size_mosaic(model, scene, cfg)
    true_depth = float(fit.translation[0, 2])
    last = true_depth / 1.6  # the depth the stream was confident at before it was lost
    plain = search_mosaic(model, fit.shape_coeffs, m, 0, gray0, intr, 0, last, None, cfg)
    wide = search_mosaic(model, fit.shape_coeffs, m, 0, gray0, intr, 0, last, None, cfg, depth_scale=1.45)
    assert float(plain.translation[2]) <= 1.2 * last + 1e-6  # it cannot look farther
    assert abs(float(wide.translation[2]) / true_depth - 1) < 0.1 and wide.score > plain.score
    assert [cfg.depth_scale(n) for n in range(7)] == [1.0, 0.7, 1.45, 0.5, 2.0, 0.7, 1.45]
    assert TemplateConfig(search_depth_widening=()).depth_scale(20) == 1.0
    with pytest.raises(ValueError, match="search_depth_widening"):
        TemplateConfig(search_depth_widening=(0.0,))


def _ncc_by_projection(gray, intr, X, T, w, t, min_inside):
    """The search's correlation of the placed points projected with project_points and sampled with sample_at_pixels
    on the (.., 3) points (as it was): the reference :func:`~torchface.template.management._ncc` must equal to the
    bit. The correlation of the samples is the package's (:func:`~torchface.template.management._sampled_ncc`): the
    projection and the sampling are what the search writes out coordinate by coordinate."""
    from torchface.appearance.sampling import sample_at_pixels
    from torchface.geometry.projection import project_points
    from torchface.template.management import _sampled_ncc

    H, P = t.shape[:2]
    cam = X.unsqueeze(1) + t.unsqueeze(2)
    vals, inside = sample_at_pixels(gray, project_points(cam.reshape(1, -1, 3), intr))
    return _sampled_ncc(vals[..., 0].reshape(H, P, -1), inside.reshape(H, P, -1), T, w, min_inside)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_search_correlation_equals_projecting_and_sampling_the_placed_points(model, scene, dtype, monkeypatch):
    """The search's correlation projects and samples the placed points coordinate by coordinate (its (.., 3) and
    (.., 2) forms made the search about 1.5 times as slow): the same scores to the bit as project_points and
    sample_at_pixels, with NaN pixels, a non-finite intensity, a non-finite placement, placements behind the
    camera and partly outside the image; and the same split into a few hypotheses at a time."""
    import torchface.template.management as management
    from torchface.template.management import _ncc, _placements

    frames, gt, fit, tpl = scene
    intr = gt.intrinsics
    gray = frames[:1].mean(1, keepdim=True).to(dtype)
    X = torch.matmul(tpl.points[:, :200], fit.rotation.transpose(1, 2)).to(dtype).expand(3, -1, -1).clone()
    X[2] = X[2].flip(0)
    T = tpl.intensity[:, :200].to(dtype).expand(3, -1).clone()
    w = tpl.valid[:, :200].to(dtype).expand(3, -1).clone()
    T[1, 5] = float("inf")
    vv, uu = torch.meshgrid(torch.arange(0.0, H, 7, dtype=dtype), torch.arange(0.0, W, 7, dtype=dtype), indexing="ij")
    grid = torch.stack([uu.reshape(-1), vv.reshape(-1)], -1)
    depth = float(fit.translation[0, 2]) * torch.tensor([1.0, 0.9, 1.3], dtype=dtype)
    t = _placements(grid, depth, intr)
    t[0, :3] = float("nan")
    t[1, 3:6, 2] = -50.0  # behind the camera
    clean = _ncc(gray, intr, X, T, w, t, 0.8)
    assert torch.equal(clean, _ncc_by_projection(gray, intr, X, T, w, t, 0.8))
    assert float(clean.max()) > 0.5 and bool((clean[0, :3] == -1).all())
    holed = gray.clone()
    holed[..., :1, :] = float("nan")
    holed[..., 100:110, 150:160] = float("nan")
    assert torch.equal(_ncc(holed, intr, X, T, w, t, 0.8), _ncc_by_projection(holed, intr, X, T, w, t, 0.8))
    monkeypatch.setattr(management, "_NCC_CHUNK_BYTES", t.shape[1] * X.shape[1] * X.element_size())  # one row
    assert torch.equal(_ncc(gray, intr, X, T, w, t, 0.8), clean)
