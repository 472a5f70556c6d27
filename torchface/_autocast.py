"""Run torchface's numerics in the dtype of their inputs, also inside a caller's ``torch.autocast`` region.

A training step usually runs under ``torch.autocast`` (bfloat16 on the CPU, float16 on CUDA). Autocast would
run the tracker's and the normalised face's matrix products in that low precision while their outputs stay
float32: the poses, expressions and faces change without any sign (a pose 0.3 mm and a face 0.5 gray level off,
a frame's status flipped), and a track cached by ``training_hooks`` would hold the degraded result. The public
entry points of the tracker and the normalised face are therefore wrapped in :func:`full_precision`: autocast is
off inside them and back on for the caller's own modules afterwards. Their results are bit-identical with and
without an enclosing autocast region.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

import torch

F = TypeVar("F", bound=Callable)

_DEVICE_TYPES = ("cpu", "cuda", "xpu", "mps")


def _autocast_enabled(device_type: str) -> bool:
    try:
        return bool(torch.is_autocast_enabled(device_type))
    except RuntimeError:  # a device type this torch's autocast does not know (each of the four is known to 2.5.1)
        return False


def _call_without(devices: list[str], fn: Callable, args: tuple, kwargs: dict):
    """``fn(*args, **kwargs)`` inside one ``torch.autocast(..., enabled=False)`` per device type of ``devices``
    (nested ``with`` blocks, which ``torch.compile`` traces, rather than an ``ExitStack``)."""
    if not devices:
        return fn(*args, **kwargs)
    with torch.autocast(device_type=devices[0], enabled=False):
        return _call_without(devices[1:], fn, args, kwargs)


def full_precision(fn: F) -> F:
    """Decorator: run ``fn`` with every enabled autocast region turned off (nothing to do, and about a microsecond
    per call, when none is)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        enabled = [d for d in _DEVICE_TYPES if _autocast_enabled(d)]
        if not enabled:
            return fn(*args, **kwargs)
        return _call_without(enabled, fn, args, kwargs)

    return wrapper  # type: ignore[return-value]
