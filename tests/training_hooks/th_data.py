"""Shared settings and sequence builder of the training_hooks tests (fixtures in conftest.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import euler_to_matrix
from torchface.model.candide import load_candide3
from torchface.synth.background import BackgroundSpec
from torchface.synth.scenarios import default_light
from torchface.synth.sequence import SequenceSpec
from torchface.tracker import FitConfig, TrackerConfig
from training_hooks import FaceTrackingConfig

# The HD clip shared with tests/tracker/test_module.py (tests/_helpers.py; the tests folder on sys.path, whatever
# pytest's import mode), imported from here by this folder's tests.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _helpers import sideways_clip  # noqa: E402,F401

SIZE = 128
FRAMES = 6
D = torch.float64
#: Small tracker and face: keeps each test file to a few seconds on 2 cores.
TRACKING = FaceTrackingConfig(
    tracker=TrackerConfig(num_levels=2, max_points=500, iterations=(6, 4), robust_scale_floor=(0.045, 0.02),
                          fit=FitConfig(fit_expression=True, expression_prior_precision=2.0)),
    face_size=32,
)  # fmt: skip


def gentle(name: str, photo: str, ypr_end: tuple[float, float, float], t_move: tuple[float, float, float],
           aus: dict[str, float], seed: int, num_frames: int = FRAMES) -> SequenceSpec:  # fmt: skip
    """Linear motion from frontal to ``ypr_end`` degrees at ~330 mm (face ~60 px wide); AUs ramp from 0."""
    s = torch.linspace(0.0, 1.0, num_frames, dtype=D)[:, None]
    model = load_candide3()
    anim = torch.zeros(num_frames, model.num_animation, dtype=D)
    for au, peak in aus.items():
        anim[:, model.animation_names.index(au)] = peak * s[:, 0]
    return SequenceSpec(
        name=name, subject="candide3", photo=photo, intrinsics=Intrinsics.default(SIZE, SIZE),
        rotation=euler_to_matrix(s * torch.tensor(ypr_end, dtype=D)),
        translation=torch.tensor([0.0, 0.0, 330.0], dtype=D) + s * torch.tensor(t_move, dtype=D),
        anim=anim, light=default_light(num_frames), background=BackgroundSpec(seed=seed),
    )  # fmt: skip
