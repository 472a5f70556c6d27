"""Whether ``torch.compile`` (or ``torch.export``) is tracing the running code (:func:`is_compiling`, torch's
``torch.compiler.is_compiling``, asked at each native kernel's dispatch, :func:`torchface.backend.use_native`).

Likewise whether ``torch.func``'s transforms or forward-mode AD run on given tensors (:func:`is_transformed`, the
native kernels and inference mode are left out for them) and the refusal of those a tracking step cannot support
(:func:`check_reverse_mode`).

What this torch can do under the transforms is probed, not read from its version (:func:`feature_probe`): a
pre-release's version (``2.10.0a0+git...``, ``2.12.0.dev20261101``) sorts before its release, so a version test
took a nightly for the older torch, and a build's fix need not come with the release a version test names.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
import torch.autograd.forward_ad as forward_ad
import torch.compiler
from torch import Tensor

__all__ = ["check_reverse_mode", "feature_probe", "host_values", "is_compiling", "is_transformed",
           "transforms_read_values"]  # fmt: skip

#: ``() -> bool``: whether torch.compile (or torch.export) is tracing the caller.
is_compiling: Callable[[], bool] = torch.compiler.is_compiling

_peek_interpreter_stack = torch._C._functorch.peek_interpreter_stack  # None when no torch.func transform runs
_is_wrapped = torch._C._functorch.is_functorch_wrapped_tensor


def feature_probe(check: Callable[[], object]) -> bool:
    """Whether ``check()`` runs without a ``RuntimeError`` (the errors an unsupported operation of a ``torch.func``
    transform raises), apart from the caller's modes: grad mode on, inference mode and CPU autocast off (a caller's
    ``torch.no_grad`` or ``torch.inference_mode`` changed what a transform does: ``jacrev`` of ``grid_sample`` passed
    in inference mode on torch 2.5.1, where it raises). ``check`` makes its own small CPU tensors (a dtype and
    device given: the caller's defaults may be any) and changes no global state; the modes are put back on return.
    A transform of the caller's around it is left alone: the probes' transforms nest inside it (their answers
    were the same nested as alone on torch 2.5.1, 2.11 and 2.13)."""
    try:
        with torch.inference_mode(False), torch.enable_grad(), torch.autocast("cpu", enabled=False):
            check()
    except RuntimeError:
        return False
    return True


def _tolist_under_grad() -> None:
    def f(x: Tensor) -> Tensor:
        x.tolist()
        return x.sum()

    torch.func.grad(f)(torch.zeros(2, dtype=torch.float32, device="cpu"))


@functools.cache
def transforms_read_values() -> bool:
    """Whether this torch reads a ``torch.func`` transform's tensors' values with ``.tolist()`` (torch 2.10 and later
    do; 2.5 to 2.9 raised "Cannot access data pointer of Tensor that doesn't have storage"; ``bool``, ``int`` and
    ``.item()`` worked). A tracking step reads values so in many places: where it cannot, a step is refused under the
    transforms (:func:`check_reverse_mode`); the frames' and faces' checks read through :func:`host_values`.

    Probed (:func:`feature_probe`: a ``.tolist()`` inside ``torch.func.grad``, under a millisecond once torch.func
    has run) at the first call, which comes under a transform (:func:`host_values`, :func:`check_reverse_mode` ask
    only there), and kept for the process."""
    return feature_probe(_tolist_under_grad)


def host_values(x: Tensor) -> list:
    """``x.tolist()`` of a 1-D tensor, also for a ``torch.func`` transform's tensor on a torch that cannot
    ``.tolist()`` it (:func:`transforms_read_values`, before 2.10; there one ``.item()`` per value, which those
    read)."""
    if not _is_wrapped(x) or transforms_read_values():
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
        RuntimeError: under ``vmap`` or forward-mode AD, or under any ``torch.func`` transform on a torch that
            cannot read its tensors' values (:func:`transforms_read_values`: releases before 2.10, or a build
            without the feature, a nightly before it).
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
        _peek_interpreter_stack() is not None
        and any(isinstance(x, Tensor) and _is_wrapped(x) for x in tensors)
        and not transforms_read_values()
    ):
        raise RuntimeError(
            f"{what} cannot run under a torch.func transform on this torch ({torch.__version__}): it cannot read the "
            f"values of a transform's tensors (.tolist() under torch.func.grad), which {what} reads per stream; torch "
            "releases 2.10 and later can: use torch.autograd.grad, or such a torch"
        )  # (probed, not read from the version: a 2.10 nightly without the feature is refused too, as this build)
