"""Tests for torchface.synth.background's settings."""

from __future__ import annotations

import pytest
import torch

from torchface.synth.background import BackgroundSpec, OccluderSpec, background_frames


def test_seeds_beyond_the_generators_range_are_refused_when_made():
    """A seed of 2**70 was taken and failed when rendering ("Overflow when unpacking long long")."""
    refused = r"^seed must be an int in \[-2\*\*62, 2\*\*62\], got 1180591620717411303424$"
    for make in (lambda s: BackgroundSpec(seed=s), lambda s: OccluderSpec(0, 2, seed=s)):
        with pytest.raises(ValueError, match=refused):
            make(2**70)
        assert make(-(2**62)).seed == -(2**62) and make(2**62).seed == 2**62
    assert background_frames(BackgroundSpec(seed=2**62), torch.arange(1.0), 8, 8).isfinite().all()
    assert background_frames(BackgroundSpec(seed=-(2**62)), torch.arange(1.0), 8, 8).isfinite().all()
