"""What a package built on torchface (as ``training_hooks`` is) uses of its internals, under public names.

A package outside ``torchface`` imports public names only (none that starts with ``_``, from no module whose name
does): a private one may be renamed or changed without a word. This module names those such a package needs to
follow torchface's own rules:

- the settings' argument checks (docs/python-api.md, "Results and settings"): :func:`check_bool` for flags,
  :func:`check_int` / :func:`check_optional_int` for counts, :func:`check_real` / :func:`check_optional_real` for
  numbers, :func:`check_number` for a number and its range (``"[0, 1]"``, ``"(0, inf)"``: finite unless the
  interval closes on ``inf``), :func:`check_choice` for an enum member, :func:`check_intrinsics`, and :func:`check_no_tilde` for paths (a ``~`` nothing expanded), each a
  ``TypeError`` or ``ValueError`` that names the setting; :func:`unexpanded_home`, the rule of that ``~``, and
  :func:`no_home_reason`, why nothing here expands it, for messages of its own, and :func:`missing_path_hint`, the
  hint torchface gives for a missing path that starts with such a ``~``;
- :func:`full_precision`, the decorator that runs torchface's public entry points in the dtype of their inputs
  inside a caller's ``torch.autocast`` region;
- :func:`is_compiling`, whether ``torch.compile`` (or ``torch.export``) traces the running code, on every torch
  torchface supports (the native kernels must not be traced: :mod:`torchface.backend`);
- the device check (docs/python-api.md, "Devices and dtypes"): :func:`check_device` of a device argument,
  :func:`check_to_device` of an ``nn.Module.to`` call's arguments and :func:`check_cuda_device` of ``.cuda``'s, each
  one ``ValueError`` that names a device this machine lacks and the devices it has, and
  :class:`DeviceCheckedModule`, an ``nn.Module`` whose ``.to`` and ``.cuda`` run them.

Whether the native kernels can run is :func:`torchface.backend.native_available`; the tracker's own pieces (a
step's bounds, its level loop) are public in :mod:`torchface.tracker.step`.

Example:
    >>> import numpy as np
    >>> check_int(np.int64(3), "clip_length", 1), check_optional_real(None, "focal")
    (3, None)
    >>> check_bool("no", "keep_short_clips")
    Traceback (most recent call last):
        ...
    TypeError: keep_short_clips must be a bool, got str 'no'
    >>> is_compiling()
    False
"""

from __future__ import annotations

from torchface._autocast import full_precision
from torchface._compiling import is_compiling
from torchface._device import DeviceCheckedModule, check_cuda_device, check_device, check_to_device
from torchface._paths import check_no_tilde, missing_path_hint, no_home_reason, unexpanded_home
from torchface.geometry._checks import (
    check_bool,
    check_choice,
    check_int,
    check_intrinsics,
    check_number,
    check_optional_int,
    check_optional_real,
    check_real,
)

__all__ = [
    "DeviceCheckedModule",
    "check_bool",
    "check_choice",
    "check_cuda_device",
    "check_device",
    "check_int",
    "check_intrinsics",
    "check_no_tilde",
    "check_number",
    "check_optional_int",
    "check_optional_real",
    "check_real",
    "check_to_device",
    "full_precision",
    "is_compiling",
    "missing_path_hint",
    "no_home_reason",
    "unexpanded_home",
]
