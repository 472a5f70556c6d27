"""The value check of float frames that the tracker's steps, the normalised face and the detectors' images share.

Kept apart from :mod:`torchface.tracker.step` (which re-exports it) so that :func:`torchface.detect.detector_image`
does not import the tracker (1.3 s) to check an image.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchface._compiling import host_values

__all__ = ["FRAME_VALUE_RANGE", "STEP_VALUE_ROW_STRIDE", "check_frame_values"]

#: :func:`~torchface.tracker.step.check_frames` with ``values=True`` refuses frames with values outside this interval:
#: [0, 1] frames, with room for a resampling's overshoot (a bicubic resize can pass 1 by a few percent).
FRAME_VALUE_RANGE: tuple[float, float] = (-0.5, 1.5)

#: :func:`~torchface.tracker.step.track_step` and :func:`~torchface.tracker.managed.managed_step` check the values of
#: every 16th row of their frames against :data:`FRAME_VALUE_RANGE` (0.01-0.03 ms at one 640x480 stream, against a
#: step's 5-6 ms): 0-255 frames handed to a tracker started on [0, 1] ones were tracked without a word.
STEP_VALUE_ROW_STRIDE: int = 16


def check_frame_values(frames: Tensor, row_stride: int = 1) -> None:
    """Refuse float ``(..., H, W)`` frames with values outside :data:`FRAME_VALUE_RANGE`
    (:func:`~torchface.tracker.step.check_frames`' ``values``; also :func:`~torchface.normalise.normalised_face`'s and
    :func:`~torchface.detect.detector_image`'s, with :data:`STEP_VALUE_ROW_STRIDE`). NaN pixels are in range;
    infinite ones too when ``row_stride`` is not 1."""
    if frames.numel():
        seen = frames.detach() if row_stride == 1 else frames.detach()[..., ::row_stride, :]
        lo, hi = host_values(torch.stack([seen.amin(), seen.amax()]))
        if not (math.isfinite(lo) and math.isfinite(hi)):  # NaN pixels: inside the range (the steps': non-finite)
            pos, neg = (math.inf, -math.inf) if row_stride == 1 else (0.5, 0.5)
            lo, hi = (float(v) for v in torch.aminmax(seen.nan_to_num(nan=0.5, posinf=pos, neginf=neg)))
        if lo < FRAME_VALUE_RANGE[0] or hi > FRAME_VALUE_RANGE[1]:
            # (frames of 0 to 1.8, an augmentation's brightness past 1, were told "0-255 values? divide by 255", and
            # mean/std-normalised ones, -2 to 2, nothing)
            if not (math.isfinite(lo) and math.isfinite(hi)):  # (an infinite pixel was "0-255 values? divide by 255")
                hint = " (infinite pixels: mark missing ones NaN)"
            elif lo < FRAME_VALUE_RANGE[0]:
                hint = " (normalised with a mean and standard deviation? pass the frames in [0, 1], before that)"
            elif hi > 2.0:
                hint = " (0-255 values? divide by 255)"
            else:
                hint = " (brightened past 1? frames.clamp(0, 1))"
            raise ValueError(f"frames must be float in [0, 1], got values from {lo:.4g} to {hi:.4g}{hint}")
