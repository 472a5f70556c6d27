"""Standard synthetic scenarios: each a deterministic function of ``(num_frames, width, height)``.

The face sits about :data:`FACE_DISTANCE_MM` from a camera with the default intrinsics
(``f = max(W, H)``), so it spans the same fraction of the image at any size.

================  ==========================================================================
``pose_sweep``    CANDIDE-3, neutral face: yaw to +-45, pitch to +-25, roll to +-20 degrees,
                  then a combined turn; small lateral drift; static background.
``expressions``   CANDIDE-3 with moderate head motion: jaw drop, outer brow raise, brow
                  lowering, eyes closed, lip stretch, then a combination; panning background.
``light_switch``  CANDIDE-3, moderate head motion, a slowly circling light plus a strong side
                  light that switches on abruptly at ``T/3`` and off at ``2T/3``.
``occlusion``     CANDIDE-3, moderate motion; a textured ellipse covers ~32 % (25-40 %) of the
                  visible face during ``min(40, T/2)`` frames in the middle.
``scan_motion``   the James scan over the pose range of ``pose_sweep``.
================  ==========================================================================

Sizes: :data:`SIZES` ``"small"`` (160x120, 20 frames, for tests) and ``"full"`` (640x480, with
per-scenario lengths in :data:`FULL_FRAMES`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from torchface.geometry._checks import check_int
from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import euler_to_matrix
from torchface.rendering.shading import LightState
from torchface.synth.background import BackgroundSpec, OccluderSpec
from torchface.synth.sequence import SequenceSpec
from torchface.synth.subjects import get_subject

__all__ = [
    "FACE_DISTANCE_MM",
    "SCENARIOS",
    "SIZES",
    "FULL_FRAMES",
    "keyframe_path",
    "default_light",
    "pose_sweep",
    "expressions",
    "light_switch",
    "occlusion",
    "scan_motion",
    "LONG_RUN_FRAMES",
    "LONG_RUN_MIN_FRAMES",
    "LONG_SCENARIOS",
    "ALL_SCENARIOS",
    "LongRunTimeline",
    "long_run_timeline",
    "long_run",
    "long_run_scan",
    "make_scenario",
    "scenario_size",
]

#: Distance from the camera to the head-frame origin (millimetres).
FACE_DISTANCE_MM: float = 450.0

#: Named sizes: ``(width, height, frames)``; ``frames = None`` means the scenario's full length.
SIZES: dict[str, tuple[int, int, int | None]] = {"small": (160, 120, 20), "full": (640, 480, None)}

#: Frame counts of the full-size scenarios.
FULL_FRAMES: dict[str, int] = {
    "pose_sweep": 240,
    "expressions": 200,
    "light_switch": 180,
    "occlusion": 160,
    "scan_motion": 240,
    "long_run": 3000,
    "long_run_scan": 3000,
}

# Pose keyframes (yaw, pitch, roll in degrees) of the sweep, shared by pose_sweep and scan_motion.
_SWEEP_KEYS: tuple[tuple[float, float, float], ...] = (
    (0, 0, 0), (45, 0, 0), (-45, 0, 0), (0, 0, 0),
    (0, 25, 0), (0, -25, 0), (0, 0, 0),
    (0, 0, 20), (0, 0, -20), (0, 0, 0),
    (30, 15, 10), (-30, -15, -10), (0, 0, 0),
)


def keyframe_path(keys: Tensor, num_frames: int) -> Tensor:
    """Smooth path through keyframes, time per segment proportional to its largest change.

    Keys are placed on whole frames, so each key with a frame of its own is reached exactly
    (a short sequence may skip keys). Each segment is eased with ``s^2 (3 - 2 s)`` so the motion starts and stops smoothly at keys.

    Args:
        keys: ``(n, D)`` keyframe values (``n >= 1``).
        num_frames: ``T``.

    Returns:
        ``(T, D)`` float64 values; frame 0 is ``keys[0]`` and frame ``T - 1`` is ``keys[-1]``.

    Example:
        >>> keyframe_path(torch.tensor([[0.0], [10.0]]), 3).flatten()
        tensor([ 0.,  5., 10.], dtype=torch.float64)
    """
    if not isinstance(keys, Tensor):  # (a list failed on "no attribute 'to'")
        raise TypeError(f"keys must be a (n, D) tensor, got {type(keys).__name__} (torch.tensor(keys))")
    keys = keys.to(torch.float64)
    if keys.ndim != 2 or keys.shape[0] < 1:
        raise ValueError(f"keys must be (n, D) with n >= 1, got {tuple(keys.shape)}")
    if not bool(torch.isfinite(keys).all()):  # (a NaN key made every frame of its segments NaN)
        raise ValueError("keys must be finite, got NaN or infinite values")
    num_frames = check_int(num_frames, "num_frames")
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    if keys.shape[0] == 1 or num_frames == 1:
        return keys[:1].expand(num_frames, -1).clone()
    seg = (keys[1:] - keys[:-1]).abs().amax(dim=1).clamp(min=1e-9)
    # Keys sit on whole frames (rounded), so every key that gets a frame is reached exactly.
    knots = (torch.cat([seg.new_zeros(1), seg.cumsum(0)]) / seg.sum() * (num_frames - 1)).round()
    f = torch.arange(num_frames, dtype=torch.float64)
    i = (torch.searchsorted(knots, f, right=True) - 1).clamp(0, keys.shape[0] - 2)
    local = ((f - knots[i]) / (knots[i + 1] - knots[i]).clamp(min=1.0)).clamp(0.0, 1.0)
    ease = local * local * (3.0 - 2.0 * local)
    out = keys[i] + ease.unsqueeze(-1) * (keys[i + 1] - keys[i])
    out[-1] = keys[-1]
    return out


def _unit(v: list[float]) -> Tensor:
    t = torch.tensor(v, dtype=torch.float64)
    return t / t.norm()


def default_light(num_frames: int) -> LightState:
    """Ambient 0.45 plus a key light from the upper left of the camera (intensity 0.55)."""
    d = _unit([-0.35, -0.45, -0.82])
    return LightState(
        torch.full((num_frames,), 0.45, dtype=torch.float64),
        d.view(1, 1, 3).expand(num_frames, 1, 3).clone(),
        torch.full((num_frames, 1), 0.55, dtype=torch.float64),
    )


def _pose(ypr: Tensor, num_frames: int, drift_mm: tuple[float, float, float]) -> tuple[Tensor, Tensor]:
    """Rotations from yaw/pitch/roll and a translation drifting around ``(0, 0, FACE_DISTANCE_MM)``."""
    s = torch.linspace(0.0, 1.0, num_frames, dtype=torch.float64)
    t = torch.stack(
        [
            drift_mm[0] * torch.sin(2 * math.pi * s),
            drift_mm[1] * torch.sin(4 * math.pi * s + 0.5),
            FACE_DISTANCE_MM + drift_mm[2] * torch.sin(2 * math.pi * s + 1.0),
        ],
        dim=-1,
    )
    return euler_to_matrix(ypr), t


def _sweep_pose(num_frames: int) -> tuple[Tensor, Tensor]:
    """The pose of :func:`pose_sweep` and :func:`scan_motion`: the sweep through ``_SWEEP_KEYS`` (yaw, pitch, roll),
    the translation drifting by (12, 6, 10) mm."""
    return _pose(keyframe_path(torch.tensor(_SWEEP_KEYS), num_frames), num_frames, (12.0, 6.0, 10.0))


def _moderate_motion(num_frames: int, phase: float = 0.0) -> Tensor:
    """Gentle head motion: yaw +-15, pitch +-8, roll +-5 degrees (sums of sines)."""
    s = torch.linspace(0.0, 1.0, num_frames, dtype=torch.float64)
    yaw = 15.0 * torch.sin(2 * math.pi * (s + phase))
    pitch = 8.0 * torch.sin(2 * math.pi * (1.5 * s + phase) + 0.7)
    roll = 5.0 * torch.sin(2 * math.pi * (0.75 * s + phase) + 1.9)
    return torch.stack([yaw, pitch, roll], dim=-1)


def _bump(num_frames: int, start: float, end: float) -> Tensor:
    """Raised cosine from 0 up to 1 and back over the fraction ``[start, end]`` of the sequence."""
    s = torch.linspace(0.0, 1.0, num_frames, dtype=torch.float64)
    x = ((s - start) / (end - start)).clamp(0.0, 1.0)
    return 0.5 - 0.5 * torch.cos(2 * math.pi * x)


def _au_index(names: tuple[str, ...], needle: str) -> int:
    hits = [i for i, n in enumerate(names) if needle.lower() in n.lower()]
    if len(hits) != 1:
        raise ValueError(f"expected exactly one animation unit named like {needle!r} in {names}, got {len(hits)}")
    return hits[0]


def _camera(width: int, height: int) -> Intrinsics:
    return Intrinsics.default(width, height)


def _check(num_frames: int, width: int, height: int) -> None:
    """Refuse sizes a scenario cannot be built at: not ints (2.5 frames failed deep inside torch when a builder was
    called directly, as :func:`make_scenario` checks), under one frame or under 8x8 pixels."""
    for value, name in ((num_frames, "num_frames"), (width, "width"), (height, "height")):
        check_int(value, name)
    if num_frames < 1 or width < 8 or height < 8:
        raise ValueError(f"need num_frames >= 1 and an image of at least 8x8, got {num_frames}, {width}x{height}")


def pose_sweep(num_frames: int, width: int, height: int) -> SequenceSpec:
    """CANDIDE-3, neutral face, sweeping yaw (+-45), pitch (+-25) and roll (+-20), static background."""
    _check(num_frames, width, height)
    R, t = _sweep_pose(num_frames)
    subject = get_subject("candide3")
    return SequenceSpec(
        name="pose_sweep",
        subject="candide3",
        intrinsics=_camera(width, height),
        rotation=R,
        translation=t,
        anim=torch.zeros(num_frames, subject.num_animation, dtype=torch.float64),
        light=default_light(num_frames),
        background=BackgroundSpec(seed=11),
        description="CANDIDE-3 neutral: yaw to +-45, pitch to +-25, roll to +-20 deg, then combined",
    )


def expressions(num_frames: int, width: int, height: int) -> SequenceSpec:
    """CANDIDE-3 with moderate head motion and one expression after another, then a mix."""
    _check(num_frames, width, height)
    subject = get_subject("candide3")
    names = subject.animation_names
    anim = torch.zeros(num_frames, subject.num_animation, dtype=torch.float64)
    schedule = (
        ("Jaw drop", 0.02, 0.18, 1.0),
        ("Outer brow raiser", 0.16, 0.32, 1.0),
        ("Brow lowerer", 0.30, 0.46, 1.0),
        ("Eyes closed", 0.44, 0.60, 1.0),
        ("Lip stretcher", 0.58, 0.74, 1.0),
        ("Jaw drop", 0.76, 0.98, 0.7),
        ("Outer brow raiser", 0.76, 0.98, 0.8),
        ("Lip stretcher", 0.80, 0.96, 0.5),
    )
    for needle, start, end, peak in schedule:
        j = _au_index(names, needle)
        anim[:, j] = anim[:, j] + peak * _bump(num_frames, start, end)
    R, t = _pose(_moderate_motion(num_frames), num_frames, (10.0, 5.0, 8.0))
    return SequenceSpec(
        name="expressions",
        subject="candide3",
        intrinsics=_camera(width, height),
        rotation=R,
        translation=t,
        anim=anim,
        light=default_light(num_frames),
        background=BackgroundSpec(seed=23, pan_px_per_frame=(0.4 * width / 640.0, 0.15 * height / 480.0)),
        description="CANDIDE-3, moderate motion: jaw drop, brow raise, brow lower, eyes closed, lip stretch, mix",
    )


def light_switch(num_frames: int, width: int, height: int) -> SequenceSpec:
    """CANDIDE-3 under a slowly circling light plus a strong side light switched on at T/3, off at 2T/3."""
    _check(num_frames, width, height)
    subject = get_subject("candide3")
    s = torch.linspace(0.0, 1.0, num_frames, dtype=torch.float64)
    azimuth = math.radians(60.0) * torch.sin(2 * math.pi * s)
    elevation = math.radians(25.0)
    moving = torch.stack(
        [
            torch.sin(azimuth) * math.cos(elevation),
            torch.full_like(s, -math.sin(elevation)),
            -torch.cos(azimuth) * math.cos(elevation),
        ],
        dim=-1,
    )
    side = _unit([0.95, -0.05, -0.3]).expand(num_frames, 3)
    on, off = num_frames // 3, (2 * num_frames) // 3
    side_on = ((torch.arange(num_frames) >= on) & (torch.arange(num_frames) < off)).to(torch.float64)
    light = LightState(
        torch.full((num_frames,), 0.3, dtype=torch.float64),
        torch.stack([moving, side], dim=1),
        torch.stack([torch.full_like(s, 0.45), 0.75 * side_on], dim=1),
    )
    R, t = _pose(_moderate_motion(num_frames, phase=0.2), num_frames, (10.0, 5.0, 8.0))
    return SequenceSpec(
        name="light_switch",
        subject="candide3",
        intrinsics=_camera(width, height),
        rotation=R,
        translation=t,
        anim=torch.zeros(num_frames, subject.num_animation, dtype=torch.float64),
        light=light,
        background=BackgroundSpec(seed=37),
        events=(("side_light_on", on), ("side_light_off", off)),
        description="CANDIDE-3, slowly circling light + strong side light on at T/3, off at 2T/3",
    )


def occlusion(num_frames: int, width: int, height: int) -> SequenceSpec:
    """CANDIDE-3 with a textured ellipse covering 25-40 % of the face for ``min(40, T/2)`` frames."""
    _check(num_frames, width, height)
    subject = get_subject("candide3")
    n_on = max(1, min(40, num_frames // 2))
    first = (num_frames - n_on) // 2
    R, t = _pose(_moderate_motion(num_frames, phase=0.45), num_frames, (8.0, 4.0, 6.0))
    return SequenceSpec(
        name="occlusion",
        subject="candide3",
        intrinsics=_camera(width, height),
        rotation=R,
        translation=t,
        anim=torch.zeros(num_frames, subject.num_animation, dtype=torch.float64),
        light=default_light(num_frames),
        background=BackgroundSpec(seed=41, pan_px_per_frame=(0.25 * width / 640.0, 0.0)),
        occluder=OccluderSpec(first_frame=first, last_frame=first + n_on, target_fraction=0.32),
        events=(("occluder_on", first), ("occluder_off", first + n_on)),
        description="CANDIDE-3, moderate motion; textured ellipse over ~32 % of the face in the middle frames",
    )


def scan_motion(num_frames: int, width: int, height: int) -> SequenceSpec:
    """The James scan over the pose range of :func:`pose_sweep` (rigid: no animation units)."""
    _check(num_frames, width, height)
    R, t = _sweep_pose(num_frames)
    return SequenceSpec(
        name="scan_motion",
        subject="james",
        intrinsics=_camera(width, height),
        rotation=R,
        translation=t,
        anim=torch.zeros(num_frames, 0, dtype=torch.float64),
        light=default_light(num_frames),
        background=BackgroundSpec(seed=53, pan_px_per_frame=(0.3 * width / 640.0, 0.1 * height / 480.0)),
        description="James scan: yaw to +-45, pitch to +-25, roll to +-20 deg, then combined",
    )


#: Scenario name -> builder ``(num_frames, width, height) -> SequenceSpec``.
SCENARIOS: dict[str, Callable[[int, int, int], SequenceSpec]] = {
    "pose_sweep": pose_sweep,
    "expressions": expressions,
    "light_switch": light_switch,
    "occlusion": occlusion,
    "scan_motion": scan_motion,
}


# --------------------------------------------------------------------------------------------- long scenarios

#: Nominal length of the long scenarios; their timeline is written in frames of this length and scaled.
LONG_RUN_FRAMES: int = 3000

#: Fewest frames a long scenario can be rendered with (every turn, return and exit still has frames).
LONG_RUN_MIN_FRAMES: int = 100

#: Head translation (mm, camera x) that puts either subject's whole head outside a default camera's image:
#: the image edge is at ``x = 225`` mm at the head's distance and no vertex is farther than ~170 mm from the
#: head origin.
EXIT_OFFSET_MM: float = 460.0

# Pose keys of the long timeline: (nominal frame, yaw, pitch, roll [deg], dx, dy [mm], return to frontal?).
# Turns: yaw +-60 and pitch +-30 alone and combined, each held briefly and undone; frames are at 25 fps.
_X = EXIT_OFFSET_MM
_LONG_KEYS: tuple[tuple[float, float, float, float, float, float, bool], ...] = (
    (0, 0, 0, 0, 0, 0, False), (50, 0, 0, 0, 0, 0, False),
    (125, 60, 0, 0, 0, 0, False), (140, 60, 0, 0, 0, 0, False), (215, 0, 0, 0, 0, 0, True),
    (240, 0, 0, 0, 0, 0, False), (315, -60, 0, 0, 0, 0, False), (330, -60, 0, 0, 0, 0, False),
    (405, 0, 0, 0, 0, 0, True),
    (430, 0, 0, 0, 0, 0, False), (490, 0, 30, 0, 0, 0, False), (500, 0, 30, 0, 0, 0, False),
    (560, 0, 0, 0, 0, 0, True),
    (580, 0, 0, 0, 0, 0, False), (640, 0, -30, 0, 0, 0, False), (650, 0, -30, 0, 0, 0, False),
    (710, 0, 0, 0, 0, 0, True),
    (730, 0, 0, 0, 0, 0, False), (800, 45, 20, 10, 0, 0, False), (900, -45, -20, -10, 0, 0, False),
    (970, 0, 0, 0, 0, 0, True),
    # Gentle motion under the first occluder.
    (1000, 0, 0, 0, 0, 0, False), (1040, -12, 6, 0, 0, 0, False), (1080, 0, 0, 0, 0, 0, False),
    # First exit: to the right; the head turns while out of view and comes back turned.
    (1100, 0, 0, 0, 0, 0, False), (1160, 0, 0, 0, _X, 0, False), (1260, -15, 5, 0, _X, 0, False),
    (1320, -15, 5, 0, 0, 0, False), (1370, 0, 0, 0, 0, 0, True),
    (1400, 0, 0, 0, 0, 0, False), (1475, 60, 0, 0, 0, 0, False), (1490, 60, 0, 0, 0, 0, False),
    (1570, 0, 0, 0, 0, 0, True),
    (1600, 0, 0, 0, 0, 0, False), (1680, -40, -30, 0, 0, 0, False), (1695, -40, -30, 0, 0, 0, False),
    (1770, 0, 0, 0, 0, 0, True),
    (1800, 0, 0, 0, 0, 0, False), (1875, -60, 0, 0, 0, 0, False), (1890, -60, 0, 0, 0, 0, False),
    (1965, 0, 0, 0, 0, 0, True),
    (1990, 0, 0, 0, 0, 0, False), (2050, 0, 30, 0, 0, 0, False), (2060, 0, 30, 0, 0, 0, False),
    (2120, 0, 0, 0, 0, 0, True),
    # Gentle motion under the second occluder.
    (2150, 0, 0, 0, 0, 0, False), (2195, 15, -8, 5, 0, 0, False), (2240, 0, 0, 0, 0, 0, False),
    # Second exit: to the left and down.
    (2270, 0, 0, 0, 0, 0, False), (2320, 0, 0, 0, -_X, 60, False), (2400, 10, 0, 0, -_X, 60, False),
    (2460, 10, 0, 0, 0, 0, False), (2500, 0, 0, 0, 0, 0, True),
    # The third occluder passes during this turn.
    (2530, 0, 0, 0, 0, 0, False), (2610, 50, 15, 0, 0, 0, False), (2625, 50, 15, 0, 0, 0, False),
    (2700, 0, 0, 0, 0, 0, True),
    (2730, 0, 0, 0, 0, 0, False), (2810, -50, -15, -10, 0, 0, False), (2825, -50, -15, -10, 0, 0, False),
    (2900, 0, 0, 0, 0, 0, True),
    (2999, 0, 0, 0, 0, 0, False),
)
del _X

# Exits: (nominal frame the head starts leaving, frame it starts coming back).
_LONG_EXITS: tuple[tuple[int, int], ...] = ((1100, 1260), (2270, 2400))
# Sudden light switches, [on, off) in nominal frames: a strong side light (twice), the key light dimmed (once).
_LONG_SIDE_LIGHT: tuple[tuple[int, int], ...] = ((300, 520), (1500, 1700))
_LONG_KEY_DIM: tuple[int, int] = (2630, 2780)
# Occluders: (first, last) nominal frames and the fraction of the face they cover.
_LONG_OCCLUDERS: tuple[tuple[int, int, float], ...] = ((1000, 1080, 0.32), (2150, 2240, 0.35), (2560, 2620, 0.25))
# Expressions (CANDIDE-3): (unit, nominal first, last frame, peak).
_LONG_EXPRESSIONS: tuple[tuple[str, int, int, float], ...] = (
    ("Jaw drop", 60, 200, 1.0), ("Outer brow raiser", 440, 560, 1.0), ("Lip stretcher", 740, 880, 0.8),
    ("Brow lowerer", 1000, 1090, 1.0), ("Eyes closed", 1380, 1395, 1.0), ("Jaw drop", 1420, 1560, 0.8),
    ("Brow lowerer", 1590, 1700, 0.8), ("Outer brow raiser", 1820, 1960, 0.8), ("Jaw drop", 2130, 2250, 0.7),
    ("Eyes closed", 2510, 2525, 1.0), ("Lip stretcher", 2540, 2700, 1.0), ("Outer brow raiser", 2740, 2900, 0.7),
)


@dataclass(frozen=True, eq=False)
class LongRunTimeline:
    """The motion of the long scenarios at a given length (nominal frames scaled to ``T``).

    Attributes:
        ypr_deg: ``(T, 3)`` yaw, pitch, roll (degrees, :mod:`torchface.conventions`).
        offset_mm: ``(T, 3)`` translation added to the resting head position (the exits), millimetres.
        returns: frames at which the head is exactly frontal again after a turn.
        exits: ``(leave, reenter)`` per exit: the frame the head starts translating out, the frame it starts
            coming back.
        events: ``(label, frame)`` pairs sorted by frame: ``frontal_return``, ``face_leaves``,
            ``face_reenters``, ``side_light_on/off``, ``key_light_dim/restore``, ``occluder_on/off``.
    """

    ypr_deg: Tensor
    offset_mm: Tensor
    returns: tuple[int, ...]
    exits: tuple[tuple[int, int], ...]
    events: tuple[tuple[str, int], ...]


def _scaled(nominal: float, num_frames: int) -> int:
    """Frame of nominal frame ``nominal`` (of :data:`LONG_RUN_FRAMES`) in a ``num_frames`` sequence."""
    return int(round(nominal * (num_frames - 1) / (LONG_RUN_FRAMES - 1)))


def _knot_path(knots: Tensor, values: Tensor, num_frames: int) -> Tensor:
    """Eased path through ``values (n, D)`` placed at whole frames ``knots (n,)`` (non-decreasing).

    Keys sharing a frame: the last one holds there. Each segment is eased with ``s^2 (3 - 2 s)``.
    """
    f = torch.arange(num_frames, dtype=torch.float64)
    kn = knots.to(torch.float64)
    i = (torch.searchsorted(kn, f, right=True) - 1).clamp(0, kn.shape[0] - 2)
    local = ((f - kn[i]) / (kn[i + 1] - kn[i]).clamp(min=1.0)).clamp(0.0, 1.0)
    ease = local * local * (3.0 - 2.0 * local)
    return values[i] + ease.unsqueeze(-1) * (values[i + 1] - values[i])


def long_run_timeline(num_frames: int) -> LongRunTimeline:
    """The long scenarios' timeline at ``num_frames`` frames (>= :data:`LONG_RUN_MIN_FRAMES`).

    Keys sit on whole frames, so every return to frontal is exactly frontal at its frame.

    Example:
        >>> tl = long_run_timeline(3000)
        >>> len(tl.returns), tl.returns[0], tl.ypr_deg[tl.returns[0]].abs().max().item()
        (13, 215, 0.0)
    """
    if num_frames < LONG_RUN_MIN_FRAMES:
        raise ValueError(f"the long scenarios need at least {LONG_RUN_MIN_FRAMES} frames, got {num_frames}")
    keys = torch.tensor([k[:6] for k in _LONG_KEYS], dtype=torch.float64)
    knots = torch.tensor([_scaled(k[0], num_frames) for k in _LONG_KEYS], dtype=torch.float64)
    path = _knot_path(knots, keys[:, 1:], num_frames)
    offset = torch.cat([path[:, 3:5], torch.zeros(num_frames, 1, dtype=torch.float64)], dim=-1)
    returns = tuple(sorted({_scaled(k[0], num_frames) for k in _LONG_KEYS if k[6]}))
    exits = tuple((_scaled(a, num_frames), _scaled(b, num_frames)) for a, b in _LONG_EXITS)
    events: list[tuple[str, int]] = [("frontal_return", r) for r in returns]
    for leave, back in exits:
        events += [("face_leaves", leave), ("face_reenters", back)]
    for on, off in _LONG_SIDE_LIGHT:
        events += [("side_light_on", _scaled(on, num_frames)), ("side_light_off", _scaled(off, num_frames))]
    events += [("key_light_dim", _scaled(_LONG_KEY_DIM[0], num_frames)),
               ("key_light_restore", _scaled(_LONG_KEY_DIM[1], num_frames))]  # fmt: skip
    for first, last, _ in _LONG_OCCLUDERS:
        events += [("occluder_on", _scaled(first, num_frames)), ("occluder_off", _scaled(last, num_frames))]
    events.sort(key=lambda e: (e[1], e[0]))
    return LongRunTimeline(path[:, :3].clone(), offset, returns, exits, tuple(events))


def _window(num_frames: int, first: int, last: int) -> Tensor:
    """``(T,)`` float64 indicator of the frames ``[first, last)`` (nominal frames scaled)."""
    f = torch.arange(num_frames)
    return ((f >= _scaled(first, num_frames)) & (f < _scaled(last, num_frames))).to(torch.float64)


def _long_light(num_frames: int) -> LightState:
    """Slowly circling key light of slowly drifting strength, plus the sudden switches of the timeline."""
    s = torch.linspace(0.0, 1.0, num_frames, dtype=torch.float64)
    azimuth = math.radians(50.0) * torch.sin(2 * math.pi * 2.0 * s)
    elevation = math.radians(25.0) + math.radians(10.0) * torch.sin(2 * math.pi * 3.0 * s + 0.4)
    key = torch.stack(
        [torch.sin(azimuth) * torch.cos(elevation), -torch.sin(elevation), -torch.cos(azimuth) * torch.cos(elevation)],
        dim=-1,
    )
    side = _unit([0.95, -0.05, -0.3]).expand(num_frames, 3)
    no_light = torch.zeros(num_frames, dtype=torch.float64)
    side_on = sum((_window(num_frames, a, b) for a, b in _LONG_SIDE_LIGHT), no_light)
    dim = _window(num_frames, *_LONG_KEY_DIM)
    key_intensity = (0.55 + 0.15 * torch.sin(2 * math.pi * 1.5 * s + 1.1)) * (1.0 - 0.6 * dim)
    ambient = 0.4 + 0.08 * torch.sin(2 * math.pi * 2.5 * s + 0.3) + 0.1 * dim
    return LightState(ambient, torch.stack([key, side], dim=1), torch.stack([key_intensity, 0.7 * side_on], dim=1))


def _long_spec(name: str, subject_name: str, num_frames: int, width: int, height: int, seed: int) -> SequenceSpec:
    _check(num_frames, width, height)
    tl = long_run_timeline(num_frames)
    subject = get_subject(subject_name)
    anim = torch.zeros(num_frames, subject.num_animation, dtype=torch.float64)
    if subject.num_animation:
        for needle, first, last, peak in _LONG_EXPRESSIONS:
            j = _au_index(subject.animation_names, needle)
            a, b = first / (LONG_RUN_FRAMES - 1), last / (LONG_RUN_FRAMES - 1)
            anim[:, j] = anim[:, j] + peak * _bump(num_frames, a, b)
    R, t = _pose(tl.ypr_deg, num_frames, (12.0, 6.0, 10.0))
    occluders = tuple(
        OccluderSpec(
            first_frame=_scaled(a, num_frames), last_frame=_scaled(b, num_frames), target_fraction=q, seed=5 + i
        )
        for i, (a, b, q) in enumerate(_LONG_OCCLUDERS)
    )
    return SequenceSpec(
        name=name,
        subject=subject_name,
        intrinsics=_camera(width, height),
        rotation=R,
        translation=t + tl.offset_mm,
        anim=anim,
        light=_long_light(num_frames),
        background=BackgroundSpec(seed=seed, pan_px_per_frame=(0.3 * width / 640.0, 0.1 * height / 480.0)),
        occluders=occluders,
        events=tl.events,
        description=(
            f"{subject_name}, {len(tl.returns)} large turns (yaw +-60, pitch +-30) each back to frontal, light "
            f"drifts and switches, {len(occluders)} occluders, {len(tl.exits)} exits out of the image"
        ),
    )


def long_run(num_frames: int, width: int, height: int) -> SequenceSpec:
    """CANDIDE-3 (textured, with expressions) on the long timeline (:func:`long_run_timeline`)."""
    return _long_spec("long_run", "candide3", num_frames, width, height, seed=61)


def long_run_scan(num_frames: int, width: int, height: int) -> SequenceSpec:
    """The James scan on the long timeline (:func:`long_run_timeline`; rigid: no animation units)."""
    return _long_spec("long_run_scan", "james", num_frames, width, height, seed=67)


#: Long scenario name -> builder; not in :data:`SCENARIOS` (the standard set), in :data:`ALL_SCENARIOS`.
LONG_SCENARIOS: dict[str, Callable[[int, int, int], SequenceSpec]] = {
    "long_run": long_run,
    "long_run_scan": long_run_scan,
}

#: Every scenario :func:`make_scenario` builds.
ALL_SCENARIOS: dict[str, Callable[[int, int, int], SequenceSpec]] = {**SCENARIOS, **LONG_SCENARIOS}


def scenario_size(name: str, size: str) -> tuple[int, int, int]:
    """``(width, height, frames)`` of scenario ``name`` at named size ``"small"`` or ``"full"``.

    A long scenario's small size has :data:`LONG_RUN_MIN_FRAMES` frames (its timeline needs them).
    """
    if size not in SIZES:
        raise ValueError(f"size must be one of {tuple(SIZES)}, got {size!r}")
    if name not in ALL_SCENARIOS:
        raise ValueError(f"scenario must be one of {tuple(ALL_SCENARIOS)}, got {name!r}")
    w, h, frames = SIZES[size]
    if frames is None:
        return w, h, FULL_FRAMES[name]
    return w, h, max(frames, LONG_RUN_MIN_FRAMES) if name in LONG_SCENARIOS else frames


def make_scenario(name: str, num_frames: int, width: int, height: int) -> SequenceSpec:
    """Build scenario ``name`` (one of :data:`ALL_SCENARIOS`).

    Example:
        >>> make_scenario("light_switch", 30, 160, 120).events
        (('side_light_on', 10), ('side_light_off', 20))
    """
    if name not in ALL_SCENARIOS:
        raise ValueError(f"scenario must be one of {tuple(ALL_SCENARIOS)}, got {name!r}")
    # (int() took 2.5 frames as 2, a width of 639.9 as 639, "20" and True without a word)
    sizes = (check_int(v, n) for v, n in ((num_frames, "num_frames"), (width, "width"), (height, "height")))
    return ALL_SCENARIOS[name](*sizes)
