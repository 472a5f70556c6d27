"""The value check of float frames that the tracker's steps, the normalised face and the detectors' images share,
and the rule saying what frames outside [0, 1] look like (:func:`value_scale`) that it shares with
:func:`torchface.io.open_frames`' float arrays.

Kept apart from :mod:`torchface.tracker.step` (which re-exports it) so that :func:`torchface.detect.detector_image`
does not import the tracker (1.3 s) to check an image.
"""

from __future__ import annotations

import enum
import math

import torch
from torch import Tensor

from torchface._compiling import host_values

__all__ = [
    "FRAME_VALUE_RANGE", "STEP_VALUE_ROW_STRIDE", "TENSOR_CLIP", "ValueScale", "check_frame_values",
    "divided_twice_hint", "value_scale", "value_scale_hint",
]

#: :func:`~torchface.tracker.step.check_frames` with ``values=True`` refuses frames with values outside this interval:
#: [0, 1] frames, with room for a resampling's overshoot (a bicubic resize can pass 1 by a few percent).
FRAME_VALUE_RANGE: tuple[float, float] = (-0.5, 1.5)

#: :func:`~torchface.tracker.step.track_step` and :func:`~torchface.tracker.managed.managed_step` check the values of
#: every 16th row of their frames against :data:`FRAME_VALUE_RANGE` (0.01-0.03 ms at one 640x480 stream, against a
#: step's 5-6 ms): 0-255 frames handed to a tracker started on [0, 1] ones were tracked without a word.
STEP_VALUE_ROW_STRIDE: int = 16


class ValueScale(enum.Enum):
    """What float frames with values outside [0, 1] look like, from their finite values (:func:`value_scale`).

    The rule that the tensors given to the Python API (:func:`check_frame_values`) and the float arrays read by
    :func:`torchface.io.open_frames` (``.npy`` clips) share, so that the same values are told the same; each words
    it with its own remedy (:func:`value_scale_hint`)."""

    #: Just below 0 and at most 2: a resampling's, sharpening's or brightness' overshoot.
    OVERSHOOT = "overshoot"
    #: Below 0 to at most 3: normalised with a mean and standard deviation (ImageNet's: about -2.1 to 2.6).
    NORMALISED = "normalised"
    #: Below -0.5 (to -255) and past 3 (to 255): a 0-255 frame less its mean (undone: 0-255 values; from -0.5 and
    #: past 3 is :attr:`SCALE_255`, a 0-255 frame resampled).
    NORMALISED_0_255 = "normalised 0-255"
    #: From about 0 to past 2: 0-255 values.
    SCALE_255 = "0-255"
    #: From under 1 to at most 2: a brightness past 1.
    BRIGHTENED = "brightened"


def value_scale(lo: float, hi: float, below_zero: int, finite: int) -> ValueScale | None:
    """What frames outside [0, 1] look like (:class:`ValueScale`), from their finite values: the smallest ``lo``, the
    largest ``hi``, how many are below 0 (``below_zero``) of how many (``finite``); None where nothing is likely.

    Just below 0 (to -0.5) and none past 2, with values past 1 too or under a tenth of them below 0: an overshoot (a
    bicubic resize of [0, 1] frames: measured to -0.36 and 1.43 for OpenCV's of binary noise; such frames were told of
    mean/std normalisation, whose frames reach further below 0 unless no pixel is darker than a quarter). From 0, or
    from -0.5 and past 3, past 2 to 255: 0-255 values (from -0.5: a 0-255 frame resampled; a 0-255 frame less its mean
    reaches far below 0, a normalised [0, 1] frame not past 3). Else below 0 (to -255, none past 255): mean/std
    normalisation (ImageNet's, -1 to 1's ``(x - 0.5) / 0.5``; past 3, a 0-255 frame less its mean). From under 1 to at
    most 2: a brightness past 1. Others (a frame all 1.8, values past 255): None.

    Example:
        >>> value_scale(0.0, 255.0, 0, 100)
        <ValueScale.SCALE_255: '0-255'>
    """
    if -0.5 <= lo < 0.0 and hi <= 2.0 and (hi > 1.0 or below_zero < 0.1 * finite):
        return ValueScale.OVERSHOOT
    if -0.5 <= lo and 2.0 < hi <= 255.0 and (lo >= 0.0 or hi > 3.0):
        return ValueScale.SCALE_255
    if -255.0 <= lo < 0.0 and hi <= 255.0:
        return ValueScale.NORMALISED if hi <= 3.0 else ValueScale.NORMALISED_0_255
    if 0.0 <= lo < 1.0 < hi <= 2.0:
        return ValueScale.BRIGHTENED
    return None


def value_scale_hint(scale: ValueScale | None, clip: str, to_unit: str = "divide by 255") -> str:
    """The words of ``scale`` (:func:`value_scale`) in an error message, ``" (...)"`` ("" for None): ``clip`` is
    the code that clips the frames to [0, 1] (``"frames.clamp(0, 1)"``), ``to_unit`` what makes 0-255 ones [0, 1].

    Example:
        >>> value_scale_hint(ValueScale.BRIGHTENED, "frames.clamp(0, 1)")
        ' (brightened past 1? frames.clamp(0, 1))'
    """
    if scale is None:
        return ""
    if scale is ValueScale.OVERSHOOT:
        return f" (a little outside [0, 1]: resampled, sharpened or brightened? {clip})"
    if scale is ValueScale.SCALE_255:
        return f" (0-255 values? {to_unit})"
    if scale is ValueScale.BRIGHTENED:
        return f" (brightened past 1? {clip})"
    back = "values in [0, 1]" if scale is ValueScale.NORMALISED else "0-255 values, then divide by 255"
    return (" (values below 0: normalised with a mean and standard deviation, as for an ImageNet network? undo it, "
            f"x * std + mean per channel, to get {back})")  # fmt: skip


#: :func:`value_scale_hint`'s ``clip`` for a tensor's frames.
TENSOR_CLIP: str = "frames.clamp(0, 1)"


def check_frame_values(frames: Tensor, row_stride: int = 1) -> None:
    """Refuse float ``(..., H, W)`` frames with values outside :data:`FRAME_VALUE_RANGE`
    (:func:`~torchface.tracker.step.check_frames`' ``values``; also :func:`~torchface.normalise.normalised_face`'s and
    :func:`~torchface.detect.detector_image`'s, with :data:`STEP_VALUE_ROW_STRIDE`). NaN pixels are in range;
    infinite ones too when ``row_stride`` is not 1. The message says what the values look like
    (:func:`value_scale`, as :func:`torchface.io.open_frames` says it of a ``.npy`` clip's)."""
    if frames.numel():
        seen = frames.detach() if row_stride == 1 else frames.detach()[..., ::row_stride, :]
        lo, hi = host_values(torch.stack([seen.amin(), seen.amax()]))
        if not (math.isfinite(lo) and math.isfinite(hi)):  # NaN pixels: inside the range (the steps': non-finite)
            pos, neg = (math.inf, -math.inf) if row_stride == 1 else (0.5, 0.5)
            lo, hi = (float(v) for v in torch.aminmax(seen.nan_to_num(nan=0.5, posinf=pos, neginf=neg)))
        if lo < FRAME_VALUE_RANGE[0] or hi > FRAME_VALUE_RANGE[1]:
            raise ValueError(f"frames must be float in [0, 1], got {_values_refused(seen, lo, hi)}")


def _values_refused(seen: Tensor, lo: float, hi: float) -> str:
    """What :func:`check_frame_values` says of the ``seen`` values it refuses (``lo`` to ``hi``, NaN read as 0.5):
    their finite values' range and :func:`value_scale`, or that some are infinite (counted only on this error path:
    a second look at the values, which the check of accepted frames does not take)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):  # (an infinite pixel was "0-255 values? divide by 255")
        return f"values from {lo:.4g} to {hi:.4g} (infinite pixels: mark missing ones NaN)"
    # (NaN pixels read as 0.5 said "values from 0.5" of frames whose values were all past 1, and told them so)
    finite = torch.isfinite(seen)
    lo, hi = host_values(torch.stack([seen.where(finite, math.inf).amin(), seen.where(finite, -math.inf).amax()]))
    below_zero, count = host_values(torch.stack([(seen < 0.0).logical_and(finite).sum(), finite.sum()]))
    return f"values from {lo:.4g} to {hi:.4g}{value_scale_hint(value_scale(lo, hi, below_zero, count), TENSOR_CLIP)}"


#: :func:`divided_twice_hint` says that a frame looks divided by 255 twice where its face started at least this many
#: times brighter than the frame's brightest value (255 for the same light: a face's brightest template point is
#: darker than a bright background's, down to 255 / 8 for a face at a quarter of the background's brightness).
DIVIDED_TWICE_MIN_RATIO: float = 255.0 / 8.0


def divided_twice_hint(frame: Tensor, start_hi: float) -> str:
    """What is said of a ``(C, H, W)`` float frame at which a stream was lost, where it looks divided by 255 twice (a
    preprocessing bug: values in [0, 1 / 255], which :func:`check_frame_values` takes, and the stream was LOST
    without a word, as at a black frame): its finite values reach at most ``FRAME_VALUE_RANGE[1] / 255``, above 0,
    and at least :data:`DIVIDED_TWICE_MIN_RATIO` times less than ``start_hi`` (the brightest value the stream's face
    started with, at most 8 * 255 times more), and are not all multiples of 1/255 (an 8-bit black frame, a fade's,
    whose brightest is 1/255, is a black frame). ``""`` otherwise. Read on a loss only: a second look at the frame
    that the steps' check (:data:`STEP_VALUE_ROW_STRIDE`) does not take.

    Example:
        >>> frame = torch.linspace(0.1, 0.9, 12).reshape(1, 3, 4)
        >>> divided_twice_hint(frame / 255, 0.8)  # doctest: +ELLIPSIS
        "its frame's values reach 0.00353, about 227 times less than its face's when it started (up to 0.8): ..."
    """
    seen = frame.detach()
    seen = seen[torch.isfinite(seen)]
    if not seen.numel():
        return ""
    hi = float(seen.amax())
    if not (0.0 < hi <= FRAME_VALUE_RANGE[1] / 255.0) or not (
        DIVIDED_TWICE_MIN_RATIO * hi <= start_hi <= 8.0 * 255.0 * hi
    ):
        return ""
    levels = seen.double() * 255.0
    if bool(((levels - levels.round()).abs() < 1e-3).all()):  # (8-bit values: a black frame's)
        return ""
    return (f"its frame's values reach {hi:.3g}, about {start_hi / hi:.0f} times less than its face's when it started "
            f"(up to {start_hi:.3g}): divided by 255 twice? Frames are float in [0, 1], 8-bit ones divided by 255 once")
