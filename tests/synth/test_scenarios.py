"""Tests for the standard scenarios and the in-memory sequence renderer (torchface.synth.sequence).

Each small scenario (160x120, 20 frames) is rendered once per module and checked for shapes,
known-answer ground truth (landmark projection, landmark pixels on the right triangle), the light
switch and the occluder coverage.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchface.geometry.camera import Intrinsics
from torchface.geometry.transforms import transform_points
from torchface.rendering.rasterizer import rasterize
from torchface.synth.scenarios import (
    FACE_DISTANCE_MM,
    SCENARIOS,
    keyframe_path,
    make_scenario,
    scenario_size,
)
from torchface.synth.sequence import SequenceSpec, render_sequence
from torchface.synth.subjects import get_subject

_CACHE: dict[str, tuple] = {}


#: The scan has 12k triangles: its test sequence is shorter to keep the suite fast.
_FRAMES = {"scan_motion": 8}


def rendered(name: str):
    """``(spec, frames, gt)`` of scenario ``name`` at the small size, rendered once."""
    if name not in _CACHE:
        w, h, t = scenario_size(name, "small")
        t = _FRAMES.get(name, t)
        spec = make_scenario(name, t, w, h)
        frames, gt = render_sequence(spec)
        _CACHE[name] = (spec, frames, gt)
    return _CACHE[name]


def _border_landmarks(subject) -> torch.Tensor:
    """``(68,)`` bool: landmarks whose vertices (with non-zero weight) all lie on the mesh border."""
    f = subject.faces
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(dim=1).values
    uniq, counts = torch.unique(edges, dim=0, return_counts=True)
    border_v = torch.zeros(int(subject.mean.shape[0]), dtype=torch.bool)
    border_v[uniq[counts == 1].flatten()] = True
    used = subject.landmark_weights > 1e-6
    return (border_v[subject.landmark_vertices] | ~used).all(dim=1)


# ----------------------------------------------------------------------------------------- smoke / cardinality
@pytest.mark.parametrize("name", list(SCENARIOS))
def test_small_scenarios_render_finite_frames(name):
    spec, frames, gt = rendered(name)
    t = _FRAMES.get(name, 20)
    assert frames.shape == (t, 3, 120, 160)
    assert frames.dtype == torch.float32 and torch.isfinite(frames).all()
    assert frames.min() >= 0 and frames.max() <= 1
    assert gt.num_frames == t
    assert gt.landmarks_px.shape == (t, 68, 2) and gt.landmarks_visible.shape == (t, 68)
    assert gt.rotation.shape == (t, 3, 3) and gt.ypr_deg.shape == (t, 3) and gt.axis_angle.shape == (t, 3)
    assert gt.au.shape == (t, len(gt.au_names))
    # The face is in view and of a sensible size in every frame (same fraction at any image size).
    assert (gt.face_pixels > 0.04 * 160 * 120).all()
    assert (gt.face_pixels < 0.5 * 160 * 120).all()
    # Frames differ from one another (motion, expression or light).
    assert (frames[1:] - frames[:-1]).abs().mean() > 1e-3


def test_face_scale_is_resolution_independent():
    small = render_sequence(make_scenario("pose_sweep", 1, 80, 60))[1].face_pixels.item() / (80 * 60)
    large = render_sequence(make_scenario("pose_sweep", 1, 240, 180))[1].face_pixels.item() / (240 * 180)
    assert abs(small - large) < 0.1 * large


def test_scenarios_are_deterministic():
    a = render_sequence(make_scenario("occlusion", 3, 64, 48))
    b = render_sequence(make_scenario("occlusion", 3, 64, 48))
    torch.testing.assert_close(a[0], b[0], rtol=0, atol=0)
    torch.testing.assert_close(a[1].landmarks_px, b[1].landmarks_px, rtol=0, atol=0)


# ----------------------------------------------------------------------------------------- feature: poses
def test_frames_do_not_depend_on_the_thread_count():
    """A scene rendered on a 2-core and on a 1-core machine is the same (torchface.synth.textures): a chunk of 6
    frames deformed CANDIDE-3 with a matrix product that rounded differently on 2 threads than on 1."""
    before = torch.get_num_threads()
    frames = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            frames.append(render_sequence(make_scenario("occlusion", 6, 64, 48))[0])
    finally:
        torch.set_num_threads(before)
    assert torch.equal(frames[0], frames[1])


def test_pose_sweep_reaches_its_range_and_ground_truth_is_consistent():
    spec, _, gt = rendered("pose_sweep")
    # Keys sit on whole frames: the extremes are reached exactly, even with 20 frames.
    for axis, limit in enumerate((45.0, 25.0, 20.0)):
        assert gt.ypr_deg[:, axis].max() == pytest.approx(limit, abs=1e-6)
        assert gt.ypr_deg[:, axis].min() == pytest.approx(-limit, abs=1e-6)
    assert (gt.au == 0).all()
    torch.testing.assert_close(gt.translation[:, 2].mean(), torch.tensor(FACE_DISTANCE_MM, dtype=torch.float64), atol=15.0, rtol=0)
    # Rotation, axis-angle and Euler angles describe the same rotations.
    from torchface.geometry.so3 import axis_angle_to_matrix, euler_to_matrix

    torch.testing.assert_close(axis_angle_to_matrix(gt.axis_angle), gt.rotation)
    torch.testing.assert_close(euler_to_matrix(gt.ypr_deg), gt.rotation)
    # The shape is a person, not the mean.
    assert gt.shape_coeffs.abs().max() > 0.05


def test_keyframe_path_known_answers():
    keys = torch.tensor([[0.0, 0.0], [10.0, -5.0], [10.0, 20.0]])
    path = keyframe_path(keys, 61)
    torch.testing.assert_close(path[0], keys[0].double())
    torch.testing.assert_close(path[-1], keys[-1].double())
    # Segment times are proportional to the largest change: 10 then 25 -> the middle key at 10/35.
    i = round(60 * 10 / 35)
    torch.testing.assert_close(path[i], keys[1].double())
    # Eased: the first step is smaller than the middle step of the segment.
    assert (path[1] - path[0]).abs().max() < (path[i // 2 + 1] - path[i // 2]).abs().max()
    with pytest.raises(ValueError):
        keyframe_path(torch.zeros(0, 3), 5)


def test_scan_motion_uses_the_scan_over_the_sweep_poses():
    spec, _, gt = rendered("scan_motion")
    ref = make_scenario("pose_sweep", gt.num_frames, 160, 120)
    assert gt.model == "james" and gt.au.shape == (gt.num_frames, 0)
    torch.testing.assert_close(gt.rotation, ref.rotation)


def test_expressions_drive_the_named_units():
    _, frames, gt = rendered("expressions")
    names = gt.au_names
    for needle in ("Jaw drop", "Outer brow raiser", "Brow lowerer", "Eyes closed", "Lip stretcher"):
        j = [i for i, n in enumerate(names) if needle in n][0]
        assert gt.au[:, j].max() > 0.5, needle
    # Jaw drop moves the lower-lip landmark (57) away from the upper lip (51) in the model frame.
    jaw = [i for i, n in enumerate(names) if "Jaw drop" in n][0]
    opening = (gt.landmarks_3d[:, 57, 1] - gt.landmarks_3d[:, 51, 1])
    assert opening[gt.au[:, jaw].argmax()] > opening[0] + 5.0


# ----------------------------------------------------------------------------------------- known answers: landmarks
@pytest.mark.parametrize("name", ["pose_sweep", "expressions", "scan_motion"])
def test_landmarks_px_are_the_projection_of_the_3d_landmarks(name):
    _, _, gt = rendered(name)
    cam = gt.intrinsics
    X = gt.landmarks_3d @ gt.rotation.transpose(-1, -2) + gt.translation.unsqueeze(1)
    u = cam.fx * X[..., 0] / X[..., 2] + cam.cx
    v = cam.fy * X[..., 1] / X[..., 2] + cam.cy
    torch.testing.assert_close(torch.stack([u, v], dim=-1), gt.landmarks_px, atol=1e-9, rtol=0)
    # And the 3D landmarks are the subject's landmark table applied to its deformed vertices.
    subject = get_subject(gt.model)
    verts = subject.deform(gt.shape_coeffs.expand(gt.num_frames, -1), gt.au, gt.num_frames)
    torch.testing.assert_close(subject.landmarks_3d(verts), gt.landmarks_3d, atol=1e-9, rtol=0)


@pytest.mark.parametrize("name", ["pose_sweep", "expressions", "scan_motion"])
def test_visible_landmark_pixels_show_the_face(name):
    spec, frames, gt = rendered(name)
    subject = get_subject(gt.model)
    verts = subject.deform(gt.shape_coeffs.float().expand(gt.num_frames, -1), gt.au.float(), gt.num_frames)
    verts_cam = transform_points(gt.rotation.float(), gt.translation.float(), verts)
    frags = rasterize(verts_cam, subject.faces, gt.intrinsics)
    vis = gt.landmarks_visible
    assert vis.float().mean() > 0.6
    t_idx, k_idx = torch.nonzero(vis, as_tuple=True)
    col = gt.landmarks_px[t_idx, k_idx, 0].round().long()
    row = gt.landmarks_px[t_idx, k_idx, 1].round().long()
    seen = frags.pix_to_face[t_idx, row, col]
    # Visibility is exact (ray cast, see the next test); the nearest pixel centre (up to 0.71 px away)
    # of a landmark on the mesh border (jaw outline, inner lips at the mouth opening) or on a
    # silhouette of the turned head can fall just off the mesh.
    on_border = _border_landmarks(subject)[k_idx]
    on_face = seen >= 0
    assert on_face[~on_border].float().mean() > 0.97, "visible landmarks' pixels must show the face"
    assert on_face[on_border].float().mean() > 0.5
    t_idx, k_idx, row, col = t_idx[on_face], k_idx[on_face], row[on_face], col[on_face]
    # The surface seen at the nearest pixel centre is at the landmark's depth (up to the slope of the
    # surface over the <= 0.71 px offset, which is large only where the surface is seen at a grazing angle).
    lm_cam = transform_points(gt.rotation, gt.translation, gt.landmarks_3d)
    z_lm = lm_cam[t_idx, k_idx, 2]
    z_seen = frags.zbuf[t_idx, row, col].double()
    rel = (z_seen - z_lm).abs() / z_lm
    assert rel.median() < 0.005 and torch.quantile(rel, 0.95) < 0.03


def _rotation_to_optical_axis(dirs: torch.Tensor) -> torch.Tensor:
    """``(N, 3)`` directions -> ``(N, 3, 3)`` rotations taking each unit direction onto ``+z`` (Rodrigues)."""
    a = dirs / dirs.norm(dim=-1, keepdim=True)
    z = torch.zeros_like(a)
    z[:, 2] = 1.0
    v = torch.linalg.cross(a, z, dim=-1)
    c = (a * z).sum(-1)
    vx = torch.zeros(a.shape[0], 3, 3, dtype=a.dtype)
    vx[:, 0, 1], vx[:, 0, 2], vx[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    vx = vx - vx.transpose(1, 2)
    return torch.eye(3, dtype=a.dtype) + vx + vx @ vx / (1.0 + c).view(-1, 1, 1)


@pytest.mark.parametrize("name", ["pose_sweep", "expressions", "scan_motion"])
def test_ray_through_a_visible_landmark_hits_its_own_triangle(name):
    """Known answer: the ray through a visible landmark's location hits the landmark's own triangle.

    Each target is the landmark nudged 2 % of the way toward its triangle's centroid (landmarks on a
    vertex or an edge belong to several triangles; the nudge makes the expected triangle unique). The
    camera is rotated about its centre so that the target lies on the optical axis (rays are
    unchanged), and a 3x3 window with the principal point on its centre pixel is rasterized: that
    pixel must show the target's triangle with the target's barycentric coordinates and depth.
    """
    _, _, gt = rendered(name)
    subject = get_subject(gt.model)
    cam = gt.intrinsics
    frames = sorted({0, gt.num_frames // 2, int(gt.ypr_deg[:, 0].argmax()), int(gt.ypr_deg[:, 0].argmin())})
    verts = subject.deform(gt.shape_coeffs.expand(gt.num_frames, -1), gt.au, gt.num_frames)
    verts_cam = transform_points(gt.rotation, gt.translation, verts)
    lm_cam = transform_points(gt.rotation, gt.translation, gt.landmarks_3d)
    t_idx, k_idx = torch.nonzero(gt.landmarks_visible[frames], as_tuple=True)
    t_idx = torch.tensor(frames)[t_idx]
    faces = subject.landmark_faces[k_idx]
    corners = subject.faces[faces]  # (N, 3)
    # Landmark weights expressed on the triangle's corners (a vertex may be listed twice with weight 0).
    w_corner = (
        (subject.landmark_vertices[k_idx].unsqueeze(-1) == corners.unsqueeze(1)).double()
        * subject.landmark_weights[k_idx].double().unsqueeze(-1)
    ).sum(1)
    tri = verts_cam[t_idx.unsqueeze(-1), corners]  # (N, 3, 3)
    torch.testing.assert_close((w_corner.unsqueeze(-1) * tri).sum(1), lm_cam[t_idx, k_idx], atol=1e-4, rtol=0)
    w_target = 0.98 * w_corner + 0.02 / 3.0
    target = (w_target.unsqueeze(-1) * tri).sum(1)
    Q = _rotation_to_optical_axis(target)
    rotated = verts_cam[t_idx] @ Q.transpose(1, 2)
    window = Intrinsics(3, 3, cam.fx, cam.fy, 1.0, 1.0)
    frag = rasterize(rotated, subject.faces, window)
    seen = frag.pix_to_face[:, 1, 1]
    depth = target.norm(dim=-1)  # on the optical axis, depth is the distance
    same = seen == faces
    # Where another triangle is seen, it may only be nearer by less than the visibility test's depth
    # tolerance (1 % of Z): CANDIDE-3's eyelid triangles lie up to ~2 mm behind the eye-socket ones.
    gap = depth - frag.zbuf[:, 1, 1]
    assert (seen[~same] >= 0).all() and ((gap[~same] > 0) & (gap[~same] < 0.01 * depth[~same])).all()
    assert same.double().mean() >= 0.85, (int(same.sum()), len(same))
    torch.testing.assert_close(frag.bary[same, 1, 1], w_target[same], atol=1e-6, rtol=0)
    torch.testing.assert_close(frag.zbuf[same, 1, 1], depth[same], atol=0, rtol=1e-6)
    assert len(same) > 100


def test_frontal_first_frame_sees_the_inner_landmarks():
    _, _, gt = rendered("pose_sweep")
    inner = gt.landmarks_visible[0, 17:]  # brows, nose, eyes, mouth
    assert inner.float().mean() > 0.85


# ----------------------------------------------------------------------------------------- feature: light and occluder
def test_light_switch_changes_abruptly_at_the_stated_frames():
    spec, frames, gt = rendered("light_switch")
    events = dict(gt.events)
    on, off = events["side_light_on"], events["side_light_off"]
    assert (on, off) == (20 // 3, 40 // 3)
    side = gt.light_intensities[:, 1]
    assert (side[on:off] > 0.5).all() and (side[:on] == 0).all() and (side[off:] == 0).all()
    # Mean face brightness from one frame to the next: the switches dwarf the changes due to motion.
    subject = get_subject(gt.model)
    verts = subject.deform(gt.shape_coeffs.float().expand(20, -1), gt.au.float(), 20)
    frags = rasterize(transform_points(gt.rotation.float(), gt.translation.float(), verts), subject.faces, gt.intrinsics)
    mask = (frags.pix_to_face >= 0).float()
    brightness = (frames.mean(1) * mask).flatten(1).sum(1) / mask.flatten(1).sum(1)
    step = (brightness[1:] - brightness[:-1]).abs()
    jumps = step[[on - 1, off - 1]]
    others = torch.cat([step[: on - 1], step[on : off - 1], step[off:]])
    assert brightness[on] > brightness[on - 1] and brightness[off] < brightness[off - 1]
    assert jumps.min() > 3.0 * others.max(), (jumps, others.max())
    # The slowly moving light does move.
    d0 = gt.light_directions[:, 0]
    assert (d0[1:] - d0[:-1]).norm(dim=-1).max() < 0.35 and (d0[5] - d0[0]).norm() > 0.3


def test_occluder_covers_25_to_40_percent_when_on():
    spec, frames, gt = rendered("occlusion")
    on = gt.occluder_on
    assert int(on.sum()) == 10  # min(40, T / 2) frames for T = 20
    events = dict(gt.events)
    assert bool(on[events["occluder_on"]]) and not bool(on[events["occluder_off"]])
    frac = gt.occluded_fraction
    assert ((frac[on] >= 0.25) & (frac[on] <= 0.40)).all(), frac[on]
    assert (frac[~on] == 0).all()
    # Landmarks under the occluder are marked hidden: visibility drops while it is on.
    assert gt.landmarks_visible[on].float().mean() < gt.landmarks_visible[~on].float().mean() - 0.15


def test_full_size_occlusion_lasts_40_frames():
    spec = make_scenario("occlusion", 160, 64, 48)
    assert spec.occluder.last_frame - spec.occluder.first_frame == 40
    w, h, t = scenario_size("pose_sweep", "full")
    assert (w, h) == (640, 480) and 150 <= t <= 300


# ----------------------------------------------------------------------------------------- exception
def test_spec_validation():
    good = make_scenario("pose_sweep", 2, 32, 24)
    with pytest.raises(ValueError, match="translation"):
        SequenceSpec(good.name, good.subject, good.intrinsics, good.rotation, good.translation[:1], good.anim, good.light)
    with pytest.raises(ValueError, match="rotation"):
        SequenceSpec(good.name, good.subject, good.intrinsics, good.rotation[:, :2], good.translation, good.anim, good.light)
    with pytest.raises(ValueError, match="light"):
        SequenceSpec(good.name, good.subject, good.intrinsics, good.rotation, good.translation, good.anim, good.light.select(0))
    bad_anim = SequenceSpec(good.name, good.subject, good.intrinsics, good.rotation, good.translation, good.anim[:, :3], good.light)
    with pytest.raises(ValueError, match="anim"):
        render_sequence(bad_anim)
    with pytest.raises(ValueError, match="scenario"):
        make_scenario("nope", 2, 32, 24)
    with pytest.raises(ValueError, match="size"):
        scenario_size("pose_sweep", "huge")


def test_make_scenario_and_keyframe_path_refuse_what_int_and_nan_passed():
    """make_scenario's int() took 2.5 frames as 2, a width of 63.9 as 63 and "20" or True as numbers; keyframe_path
    made every frame of a NaN key's segments NaN and failed on a list with "no attribute 'to'"."""
    for args, match in [
        ((2.5, 64, 48), "^num_frames must be an int, got float 2.5$"),
        (("3", 64, 48), "^num_frames must be an int, got str '3'$"),
        ((True, 64, 48), "^num_frames must be an int, got bool True$"),
        ((2, 63.9, 48), "^width must be an int, got float 63.9$"),
    ]:
        with pytest.raises(TypeError, match=match):
            make_scenario("pose_sweep", *args)
    assert make_scenario("pose_sweep", np.int64(2), 64, torch.tensor(48)).intrinsics.height == 48
    # the builders themselves, called directly, check too (2.5 frames failed deep inside torch)
    from torchface.synth import scenarios

    for build in (scenarios.pose_sweep, scenarios.expressions, scenarios.long_run):
        with pytest.raises(TypeError, match="^num_frames must be an int, got float 2.5$"):
            build(2.5, 64, 48)
    with pytest.raises(TypeError, match="^height must be an int, got float 47.5$"):
        scenarios.light_switch(3, 64, 47.5)
    with pytest.raises(ValueError, match="^keys must be finite"):
        keyframe_path(torch.tensor([[0.0], [float("nan")]]), 3)
    with pytest.raises(TypeError, match=r"^keys must be a \(n, D\) tensor, got list"):
        keyframe_path([[0.0], [1.0]], 3)
    with pytest.raises(TypeError, match="^num_frames must be an int"):
        keyframe_path(torch.zeros(2, 1), 2.5)
