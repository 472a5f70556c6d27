"""The track CSV's template-management columns (residual_confidence, dissimilarity, mosaic_entry) and the lost
status: values from a managed result, NaN / -1 from a bare one, and the per-image detector adapter of the job."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from torchface.io.table import result_rows, track_columns
from torchface.tracker.step import TrackResult, TrackStatus


def _result(B: int = 2) -> TrackResult:
    A, F, L = 3, 2, 5
    return TrackResult(
        rotation=torch.eye(3).expand(B, 3, 3), axis_angle=torch.zeros(B, 3), translation=torch.zeros(B, 3),
        ypr_deg=torch.zeros(B, 3), anim_coeffs=torch.zeros(B, A), anim_names=("a b", "c d", "e f"),
        expression=torch.zeros(B, A),
        facs=torch.zeros(B, F), facs_names=("AU1", "AU2"), illumination=torch.zeros(B, L),
        illumination_names=("gain", "bias", "light_x", "light_y", "light_z"),
        status=torch.tensor([int(TrackStatus.CONVERGED), int(TrackStatus.LOST)])[:B],
        iterations=torch.zeros(B, dtype=torch.int64), cost=torch.zeros(B), num_points=torch.zeros(B, dtype=torch.int64),
        confidence=torch.tensor([0.9, 0.05])[:B],
    )  # fmt: skip


def test_management_columns_from_a_managed_and_a_bare_result():
    res = _result()
    cols = track_columns(res.anim_names, res.facs_names, res.illumination_names)
    assert cols[-3:] == ("residual_confidence", "dissimilarity", "mosaic_entry")
    bare = result_rows(res, np.arange(2), 25.0)
    idx = {c: i for i, c in enumerate(cols)}
    assert bare.shape == (2, len(cols))
    assert all(math.isnan(v) for v in bare[:, idx["residual_confidence"]])
    assert all(math.isnan(v) for v in bare[:, idx["dissimilarity"]])
    assert bare[:, idx["mosaic_entry"]].tolist() == [-1.0, -1.0]
    managed = replace(res, residual_confidence=torch.tensor([0.8, 0.7]), dissimilarity=torch.tensor([0.2, 2.5]),
                      mosaic_entry=torch.tensor([0, 3]))  # fmt: skip
    rows = result_rows(managed, np.arange(2), 25.0)
    np.testing.assert_allclose(rows[:, idx["residual_confidence"]], [0.8, 0.7], rtol=1e-6)
    np.testing.assert_allclose(rows[:, idx["dissimilarity"]], [0.2, 2.5], rtol=1e-6)
    assert rows[:, idx["mosaic_entry"]].tolist() == [0.0, 3.0]
    # A lost frame is not successful; its status column says 3.
    assert rows[:, idx["success"]].tolist() == [1.0, 0.0]
    assert rows[:, idx["status"]].tolist() == [0.0, 3.0]
