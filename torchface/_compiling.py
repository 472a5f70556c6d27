"""Whether ``torch.compile`` (or ``torch.export``) is tracing the running code, on every torch pyproject.toml accepts.

``torch.compiler.is_compiling`` came with torch 2.3; torch 2.1 and 2.2 (which pyproject.toml accepted before it asked
for 2.5.1) have the same flag as
``torch._utils.is_compiling``: Dynamo folds either to True while it traces, and either is False in eager code. The
later torches deprecate the second with a warning at each call, so it is only the fallback. (The tracker's kernel
dispatch, :func:`torchface.backend.use_native`, asks at each call: ``torch.compiler.is_compiling`` alone raised
``AttributeError`` there on torch 2.1 and 2.2, at the first frame.)

Likewise whether ``torch.func``'s transforms or forward-mode AD run on given tensors (:func:`is_transformed`, the
native kernels and inference mode are left out for them) and the refusal of those a tracking step cannot support
(:func:`check_reverse_mode`).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.autograd.forward_ad as forward_ad
import torch.compiler
from torch import Tensor

__all__ = ["TRANSFORMS_READ_VALUES", "check_reverse_mode", "is_compiling", "host_values", "is_transformed"]

#: ``() -> bool``: whether torch.compile (or torch.export) is tracing the caller.
is_compiling: Callable[[], bool] = getattr(torch.compiler, "is_compiling", None) or torch._utils.is_compiling

_peek_interpreter_stack = torch._C._functorch.peek_interpreter_stack  # None when no torch.func transform runs
_is_wrapped = torch._C._functorch.is_functorch_wrapped_tensor

#: Whether this torch reads a ``torch.func`` transform's tensors' values with ``.tolist()`` (torch 2.10 and later;
#: 2.5 to 2.9 raised "Cannot access data pointer of Tensor that doesn't have storage"; ``bool``, ``int`` and
#: ``.item()`` worked). A tracking step reads values so in many places: on an older torch it is refused under the
#: transforms (:func:`check_reverse_mode`); the frames' and faces' checks read through :func:`host_values`.
TRANSFORMS_READ_VALUES: bool = torch.torch_version.TorchVersion(torch.__version__) >= "2.10"


def host_values(x: Tensor) -> list:
    """``x.tolist()`` of a 1-D tensor, also for a ``torch.func`` transform's tensor on a torch before 2.10
    (:data:`TRANSFORMS_READ_VALUES`; there one ``.item()`` per value, which those read)."""
    if TRANSFORMS_READ_VALUES or not _is_wrapped(x):
        return x.tolist()
    return [v.item() for v in x.unbind()]


def is_transformed(*tensors: object) -> bool:
    """Whether one of ``tensors`` (other values are skipped) is wrapped by a ``torch.func`` transform (``grad``,
    ``vmap``, ``jacrev``, ``jvp``, ...) or is a forward-AD dual tensor (``torch.autograd.forward_ad``).

    The native kernels read the tensors' memory, which wrapped tensors do not have ("Cannot access data pointer of
    Tensor that doesn't have storage", a ``.detach()`` of one too), and would drop a dual tensor's tangent without a
    sign; inference mode drops tangents too. Two cheap looks (about half a microsecond) when neither is active."""
    if _peek_interpreter_stack() is not None and any(isinstance(x, Tensor) and _is_wrapped(x) for x in tensors):
        return True
    if forward_ad._current_level >= 0:
        return any(isinstance(x, Tensor) and forward_ad.unpack_dual(x).tangent is not None for x in tensors)
    return False


def _vmapped(x: Tensor) -> bool:
    """Whether ``x`` is batched by ``torch.func.vmap`` at some level of its ``torch.func`` wrappers."""
    while _is_wrapped(x):
        if torch._C._functorch.is_batchedtensor(x):
            return True
        x = torch._C._functorch.get_unwrapped(x)
    return False


def check_reverse_mode(what: str, *tensors: object) -> None:
    """Refuse ``tensors`` (other values are skipped) batched by ``torch.func.vmap`` or carrying forward-mode tangents
    (``torch.func.jvp``, ``jacfwd``, ``torch.autograd.forward_ad``), with one line saying what works instead.

    ``what`` (a tracking step, ...) decides per stream from the values (``if`` on tensors, ``.tolist()``: vmap's
    "data-dependent control flow" errors) and samples the frames with ``grid_sample``, which has no forward-mode
    derivative in torch; reverse mode (``torch.autograd``, ``torch.func.grad``, ``vjp``, ``jacrev``) works.

    Raises:
        RuntimeError: under ``vmap`` or forward-mode AD, or under any ``torch.func`` transform on a torch before 2.10
            (:data:`TRANSFORMS_READ_VALUES`).
    """
    if _peek_interpreter_stack() is not None and any(isinstance(x, Tensor) and _vmapped(x) for x in tensors):
        raise RuntimeError(
            f"{what} cannot run under torch.func.vmap (its decisions read the values of each stream): track the "
            "streams as one batch, (B, ...) tensors, instead"
        )
    if forward_ad._current_level >= 0 and any(
        isinstance(x, Tensor) and forward_ad.unpack_dual(x).tangent is not None for x in tensors
    ):
        raise RuntimeError(
            f"{what} has no forward-mode derivative (torch.func.jvp, jacfwd, forward_ad: torch's grid_sample has "
            "none): use reverse mode (torch.autograd.grad, torch.func.grad, vjp or jacrev)"
        )
    if (
        not TRANSFORMS_READ_VALUES
        and _peek_interpreter_stack() is not None
        and any(isinstance(x, Tensor) and _is_wrapped(x) for x in tensors)
    ):
        raise RuntimeError(
            f"{what} under a torch.func transform needs torch 2.10 or later (torch {torch.__version__} cannot read the "
            f"values of a transform's tensors, which {what} reads per stream): use torch.autograd.grad, or a newer "
            "torch"
        )
