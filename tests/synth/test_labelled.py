"""Tests of torchface.synth.labelled: expression prototypes, the GRID photograph, the animated James scan,
identity variants and one-clip rendering (known answers from the ground-truth geometry)."""

from __future__ import annotations

import pytest
import torch

from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import project_points
from torchface.model import load_candide3
from torchface.synth.labelled import (
    EXPRESSION_AUS,
    EXPRESSION_CLASSES,
    ClipSpec,
    animated_scan_subject,
    expression_coeffs,
    grid_photo,
    identity_variant,
    render_clip,
)
from torchface.synth.subjects import candide_subject, james_subject

NAMES = load_candide3().animation_names


def test_expression_coeffs_known_answer():
    a = expression_coeffs(NAMES, "surprise", 0.5)
    assert a.shape == (len(NAMES),)
    assert float(a[NAMES.index("AUV5 Outer brow raiser")]) == 0.5
    assert float(a[NAMES.index("AUV11 Jaw drop")]) == pytest.approx(0.3)
    assert int((a != 0).sum()) == len(EXPRESSION_AUS["surprise"])
    assert float(expression_coeffs(NAMES, "neutral").abs().sum()) == 0.0
    assert set(EXPRESSION_CLASSES) == set(EXPRESSION_AUS)
    with pytest.raises(ValueError, match="expression must be one of"):
        expression_coeffs(NAMES, "boredom")
    with pytest.raises(ValueError, match="animation unit"):
        expression_coeffs(("AUV0 Upper lip raiser",), "mouth_open")


def test_grid_photo():
    photo = grid_photo()
    assert photo.image.shape == (3, 288, 360) and photo.landmarks_px.shape == (68, 2)
    lm = photo.landmarks_px
    assert bool(((lm >= 0) & (lm[:, :1] < 360) & (lm[:, 1:] < 288)).all())
    # iBUG order: the nose tip (30) lies between the eye corners (36, 45) and above the chin (8).
    assert lm[36, 0] < lm[30, 0] < lm[45, 0] and lm[30, 1] < lm[8, 1]


def test_animated_scan_moves_like_candide():
    """Jaw drop moves the scan's chin landmark like CANDIDE-3's (same direction, similar size) and leaves the
    back of the head (far from the CANDIDE-3 surface) still."""
    scan = animated_scan_subject()
    rigid = james_subject()
    assert scan.num_animation == len(NAMES) and scan.animation_names == NAMES
    torch.testing.assert_close(scan.mean, rigid.mean)
    jaw = torch.zeros(1, scan.num_animation)
    jaw[0, NAMES.index("AUV11 Jaw drop")] = 1.0
    move_scan = scan.landmarks_3d(scan.deform(None, jaw, 1)) - scan.landmarks_3d(scan.deform(None, None, 1))
    cand = candide_subject("james")
    shape = cand.shape_coeffs.unsqueeze(0)
    move_cand = cand.landmarks_3d(cand.deform(shape, jaw, 1)) - cand.landmarks_3d(cand.deform(shape, None, 1))
    chin_scan, chin_cand = move_scan[0, 8], move_cand[0, 8]
    assert chin_cand.norm() > 5.0  # mm: a real jaw drop
    cos = torch.dot(chin_scan, chin_cand) / (chin_scan.norm() * chin_cand.norm())
    assert cos > 0.9 and 0.6 < float(chin_scan.norm() / chin_cand.norm()) < 1.4
    assert float(move_scan[0, 36:48].norm(dim=-1).max()) < 0.5  # the eyes do not move with the jaw
    back = scan.mean[:, 2] > scan.mean[:, 2].max() - 20.0  # the back of the head (+z away from the viewer)
    assert int(back.sum()) > 0 and float(scan.animation_units[:, back].abs().max()) == 0.0


def test_identity_variant():
    base = candide_subject("james")
    offset = torch.full((base.num_shape,), 0.2)
    gain = torch.tensor([1.1, 1.0, 0.8])
    v = identity_variant(base, offset, gain)
    torch.testing.assert_close(v.shape_coeffs, base.shape_coeffs + 0.2)
    torch.testing.assert_close(v.texture[2], (base.texture[2] * 0.8).clamp(0, 1))
    assert identity_variant(base).texture is base.texture
    with pytest.raises(ValueError, match="shape_offset"):
        identity_variant(base, torch.zeros(3))
    with pytest.raises(ValueError, match="colour_gain"):
        identity_variant(base, None, torch.ones(4))


def test_render_clip_known_geometry():
    """Frame 0 is frontal and neutral; the last frame shows the target pose (landmarks = projection of the
    subject's landmarks at that pose); equal steps without easing."""
    s = candide_subject("astronaut")
    anim = expression_coeffs(s.animation_names, "mouth_open")
    spec = ClipSpec(4, 96, 80, 300.0, (30.0, 0.0, 0.0), (10.0, 0.0, 0.0), anim, 0.3, (0.5, -0.3, -0.8), 0.7,
                    background_seed=5, easing=False)  # fmt: skip
    frames, lm = render_clip(s, spec)
    assert frames.shape == (4, 3, 80, 96) and lm.shape == (4, 68, 2)
    assert float(frames.min()) >= 0 and float(frames.max()) <= 1
    cam = Intrinsics.default(96, 80)
    shape = s.shape_coeffs.to(torch.float64).unsqueeze(0)
    lm3d = s.landmarks_3d(s.deform(shape, None, 1)) + torch.tensor([0.0, 0.0, 300.0], dtype=torch.float64)
    front = project_points(lm3d, cam)
    torch.testing.assert_close(lm[0], front[0])
    # +yaw turns the nose toward image left: the nose tip moves left of the eye-corner midpoint.
    mid = 0.5 * (lm[:, 36, 0] + lm[:, 45, 0])
    assert float(lm[-1, 30, 0] - mid[-1]) < float(lm[0, 30, 0] - mid[0]) - 3.0
    # Equal steps: the x shift of the landmarks' centroid per frame is nearly constant (10 mm in 3 steps).
    steps = lm.mean(1)[1:, 0] - lm.mean(1)[:-1, 0]
    assert float(steps.max() - steps.min()) < 0.25 * float(steps.abs().mean())
    # The mouth opened: the lower lip (57) moved away from the upper lip (51).
    assert float((lm[-1, 57] - lm[-1, 51]).norm()) > float((lm[0, 57] - lm[0, 51]).norm()) + 3.0


def test_clip_spec_and_render_errors():
    s = candide_subject("james")
    anim = expression_coeffs(s.animation_names, "smile")
    with pytest.raises(ValueError, match="num_frames"):
        ClipSpec(1, 64, 64, 300.0, (0, 0, 0), (0, 0, 0), anim, 0.4, (0, 0, -1), 0.5)
    with pytest.raises(ValueError, match="anim"):
        ClipSpec(2, 64, 64, 300.0, (0, 0, 0), (0, 0, 0), anim[None], 0.4, (0, 0, -1), 0.5)
    spec = ClipSpec(2, 64, 64, 300.0, (0, 0, 0), (0, 0, 0), anim[:3], 0.4, (0, 0, -1), 0.5)
    with pytest.raises(ValueError, match="A = 11"):
        render_clip(s, spec)


def test_clip_spec_refuses_values_that_render_nan_or_nothing():
    """A NaN ambient rendered NaN frames, a NaN pose a clip whose labels were NaN, and a zero light direction or
    an infinite distance were taken: a ValueError naming the field now."""
    anim = torch.zeros(11)
    ok = dict(num_frames=2, width=64, height=64, distance_mm=300.0, ypr_deg=(0, 0, 0), translation_mm=(0, 0, 0),
              anim=anim, ambient=0.4, light_direction=(0, 0, -1), light_intensity=0.5)  # fmt: skip
    nan = float("nan")
    for name, bad, match in [
        ("ambient", nan, "^ambient must be a finite number >= 0, got nan$"),
        ("light_intensity", -1.0, "^light_intensity must be a finite number >= 0, got -1.0$"),
        ("distance_mm", float("inf"), "^distance_mm must be a finite number > 0, got inf$"),
        ("ypr_deg", (nan, 0.0, 0.0), r"ypr_deg must be three finite numbers"),
        ("translation_mm", (0.0, 0.0), r"translation_mm must be three finite numbers"),
        ("light_direction", (0, 0, 0), "light_direction must be a non-zero direction"),
        ("anim", torch.full((11,), nan), "anim must be finite"),
    ]:
        with pytest.raises(ValueError, match=match):
            ClipSpec(**{**ok, name: bad})
    with pytest.raises(TypeError, match="ypr_deg must be"):
        ClipSpec(**{**ok, "ypr_deg": 30.0})
    ClipSpec(**ok)  # (ints taken, as before)
