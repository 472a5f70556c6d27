"""Helpers shared by tests in more than one folder. A test file imports them with this folder on ``sys.path``
(``sys.path.insert(0, str(Path(__file__).resolve().parents[1]))``, whatever pytest's import mode), as the
folders' own helper modules are imported (tests/training_hooks/th_data.py, tests/tracker/test_objective.py)."""

from __future__ import annotations

import torch

from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import euler_to_matrix
from torchface.model.candide import load_candide3
from torchface.synth.background import BackgroundSpec
from torchface.synth.scenarios import default_light
from torchface.synth.sequence import SequenceSpec, render_sequence

D = torch.float64


def sideways_clip(w: int, h: int, n: int = 3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The clip of tests/cli/test_cli_track.py's HD test: CANDIDE-3 at 450 mm turning 2 degrees and moving 13 mm
    sideways a frame (18 pixels at 640x360, 37 at 1280x720), ``n <= 6`` frames of ``w x h``.

    Returns:
        ``frames (n, 3, h, w)`` float32, the first frame's landmarks ``(68, 2)`` float32 and the true rotations
        ``(n, 3, 3)`` float64.
    """
    s = torch.linspace(0.0, 1.0, 6, dtype=D)[:n, None]
    spec = SequenceSpec(
        name="clip", subject="candide3", intrinsics=Intrinsics.default(w, h),
        rotation=euler_to_matrix(s * torch.tensor([10.0, 0.0, 0.0], dtype=D)),
        translation=torch.tensor([0.0, 0.0, 450.0], dtype=D) + s * torch.tensor([65.0, 0.0, 0.0], dtype=D),
        anim=torch.zeros(n, load_candide3().num_animation, dtype=D), light=default_light(n),
        background=BackgroundSpec(seed=3),
    )  # fmt: skip
    frames, gt = render_sequence(spec)
    return frames.float(), gt.landmarks_px[0].float(), gt.rotation
