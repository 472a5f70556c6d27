"""torchface._frame_values: frames outside [0, 1] are told what they look like by one rule, as tensors given to the
tracker and as float ``.npy`` clips read by :func:`torchface.io.open_frames` (the two had a rule each, and told the
same values different things)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchface._frame_values import TENSOR_CLIP, ValueScale, check_frame_values, value_scale, value_scale_hint
from torchface.io import InputError, open_frames
from torchface.io.video import NAN_PIXELS_HINT

#: ImageNet networks' per-channel (R, G, B) mean and standard deviation.
IMAGENET_MEAN, IMAGENET_STD = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])
#: open_frames' words for a float array's remedies.
ARRAY_WORDS = ("np.clip(frames, 0, 1)", "divide by 255, or save them as uint8")


def _ramp(lo: float, hi: float) -> np.ndarray:
    """A ``(32, 32, 3)`` float32 frame of values from ``lo`` to ``hi`` (the smallest frame open_frames reads)."""
    return np.linspace(lo, hi, 32 * 32 * 3, dtype=np.float32).reshape(32, 32, 3)


def _holed(frame: np.ndarray) -> np.ndarray:
    """``frame`` with a NaN pixel every 7th of every row: missing pixels, which a tensor's check takes."""
    frame = frame.copy()
    frame[:, ::7] = np.nan
    return frame


@pytest.mark.parametrize(
    "frame, scale",
    [
        (_ramp(0.0, 255.0), ValueScale.SCALE_255),
        (((_ramp(0.0, 1.0) - IMAGENET_MEAN) / IMAGENET_STD).astype(np.float32), ValueScale.NORMALISED),
        (_ramp(-128.0, 127.0), ValueScale.NORMALISED_0_255),
        (_ramp(0.0, 1.8), ValueScale.BRIGHTENED),
        (_ramp(-0.6, 1.0), ValueScale.NORMALISED),  # (past -0.5: further than an overshoot)
        # each path told these otherwise before: a tensor "brightened past 1" (-0.2 to 1.8, all 1.8, and values all
        # past 1 beside NaN pixels, read as 0.5) and "normalised" (-1000 to 1000); an array "a 0-255 frame less its
        # mean" (a 0-255 frame resampled, a little below 0)
        (_ramp(-0.2, 1.8), ValueScale.OVERSHOOT),
        (np.full((32, 32, 3), 1.8, np.float32), None),
        (_holed(_ramp(1.6, 1.9)), None),
        (_ramp(-1000.0, 1000.0), None),
        (_ramp(-0.3, 255.0), ValueScale.SCALE_255),
        (_holed(_ramp(0.0, 255.0)), ValueScale.SCALE_255),
    ],
)
def test_a_tensor_and_an_array_of_the_same_values_are_told_the_same(tmp_path, frame, scale):
    """Frames that both refuse (outside the tensors' -0.5 to 1.5): the same finite range and the same
    :class:`ValueScale`, each in its own words (``frames.clamp`` / ``np.clip``)."""
    finite = frame[np.isfinite(frame)]
    lo, hi = float(finite.min()), float(finite.max())
    assert value_scale(lo, hi, int(np.count_nonzero(finite < 0)), finite.size) is scale
    said = f"values from {lo:.4g} to {hi:.4g}"
    with pytest.raises(ValueError) as info:
        check_frame_values(torch.from_numpy(frame).permute(2, 0, 1)[None])
    assert str(info.value) == f"frames must be float in [0, 1], got {said}{value_scale_hint(scale, TENSOR_CLIP)}"
    np.save(tmp_path / "f.npy", np.stack([frame, frame]))
    with pytest.raises(InputError) as info:
        open_frames(tmp_path / "f.npy")
    nan = "NaN and " if np.isnan(frame).any() else ""  # (a file's NaN pixels: why they are refused, after the scale)
    why = f" ({NAN_PIXELS_HINT})" if nan else ""
    assert str(info.value).endswith(f"got {nan}{said}{value_scale_hint(scale, *ARRAY_WORDS)}{why}"), str(info.value)


def test_the_tensor_message_is_the_same_under_a_torch_func_transform():
    """The counts behind the hint are read only when the frames are refused, through ``host_values`` (a
    ``torch.func`` transform's tensors), in the frames' dtype (float16: counts past its largest value, 65504)."""
    frame = torch.linspace(-0.2, 1.8, 256, dtype=torch.float16).expand(1, 3, 256, 256)  # (each row: -0.2 to 1.8)
    assert frame.numel() > 65504
    with pytest.raises(ValueError) as plain:
        check_frame_values(frame)
    assert "a little outside [0, 1]" in str(plain.value)
    with pytest.raises(ValueError) as transformed:
        torch.func.grad(lambda f: (check_frame_values(f), f.float().sum())[1])(frame)
    assert str(transformed.value) == str(plain.value)
    strided, holed = frame.clone(), frame[..., ::16, :].clone()
    strided[..., ::16, 5], holed[..., 5] = math.inf, math.nan  # (in the rows a step looks at: missing, as NaN ones)
    with pytest.raises(ValueError) as step:
        check_frame_values(strided, row_stride=16)
    with pytest.raises(ValueError) as every_row:
        check_frame_values(holed)
    assert str(step.value) == str(every_row.value)
