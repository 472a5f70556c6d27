"""Tiny rendered videos for the training_hooks tests (written once per session).

Three 6-frame 128x128 sequences of CANDIDE-3 (textured from the James render and from the astronaut photo)
with gentle head motion (about 3 degrees per frame) and animation units ramping up, written as lossless
videos with their ground truth; first-frame landmarks are the exact ground-truth ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from th_data import TRACKING, gentle
from torchface.synth.sequence import GroundTruth, load_ground_truth, write_sequence
from training_hooks import DatasetConfig

@dataclass(frozen=True)
class Clip:
    video: Path
    landmarks: np.ndarray  # (68, 2) float64
    gt: GroundTruth


@pytest.fixture(scope="session")
def clips(tmp_path_factory: pytest.TempPathFactory) -> list[Clip]:
    root = tmp_path_factory.mktemp("th_videos")
    specs = [
        gentle("a", "james", (15.0, -6.0, 4.0), (4.0, -2.0, 8.0), {"AUV11 Jaw drop": 0.6}, seed=3),
        gentle("b", "astronaut", (-12.0, 5.0, -3.0), (-5.0, 3.0, -6.0), {"AUV5 Outer brow raiser": 0.6}, seed=7),
        gentle("c", "james", (8.0, 8.0, 0.0), (3.0, 3.0, 0.0), {"AUV2 Lip stretcher": 0.5}, seed=11),
    ]
    out = []
    for spec in specs:
        files = write_sequence(spec, root)
        gt = load_ground_truth(files.ground_truth)
        out.append(Clip(files.video, gt.landmarks_px[0].numpy().astype(np.float64), gt))
    return out


@pytest.fixture
def config(tmp_path: Path) -> DatasetConfig:
    """Frame items, the small tracker, a fresh cache folder."""
    return DatasetConfig(tracking=TRACKING, cache_dir=tmp_path / "cache")
