"""Whether ``torch.compile`` (or ``torch.export``) is tracing the running code, on every torch pyproject.toml accepts.

``torch.compiler.is_compiling`` came with torch 2.3; torch 2.1 and 2.2 (``torch>=2.1``) have the same flag as
``torch._utils.is_compiling``: Dynamo folds either to True while it traces, and either is False in eager code. The
later torches deprecate the second with a warning at each call, so it is only the fallback. (The tracker's kernel
dispatch, :func:`torchface.backend.use_native`, asks at each call: ``torch.compiler.is_compiling`` alone raised
``AttributeError`` there on torch 2.1 and 2.2, at the first frame.)
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.compiler

__all__ = ["is_compiling"]

#: ``() -> bool``: whether torch.compile (or torch.export) is tracing the caller.
is_compiling: Callable[[], bool] = getattr(torch.compiler, "is_compiling", None) or torch._utils.is_compiling
