"""Which implementation runs torchface's hot loops: the torch code or the native kernels (:mod:`torchface._native`).

The per-frame work of a tracking step is mostly small operations: at one stream their dispatch, not their
arithmetic, is most of the time, and at many streams every intermediate goes through memory. The native kernels
(C, compiled at first use by the machine's C compiler; listed in :mod:`torchface._native`) run the same
algorithms one stream (or patch) at a time: the fast solver's level solves, a step's gray crop pyramid, the
rasterizer's coverage and the z-buffer test of points against it, a template's candidate pixels and points, the normalised face, the dissimilarity confidence and its references,
and template management's per-frame decisions. Each is tested against its torch code
(``tests/tracker/test_native.py`` and the tests of each module).

:attr:`Backend.AUTO` (the default of :class:`~torchface.tracker.TrackerConfig`) takes the native kernels where
they can run: CPU tensors of float32 or float64 that ask for no gradient (nor tangent: ``torch.func``, forward
AD), on a machine with a C compiler;
elsewhere, and whenever the environment sets ``TORCHFACE_NATIVE=0``, the torch code runs. :func:`native_available`
says whether the kernels can run on this machine (for a package built on torchface that records it, such as
``training_hooks``' cache key), :func:`native_unavailable_reason` why not.
"""

from __future__ import annotations

import enum

import torch
from torch import Tensor

from torchface import _native
from torchface._compiling import is_compiling, is_transformed
from torchface.geometry._checks import check_choice

__all__ = ["Backend", "native_available", "native_unavailable_reason", "use_native"]


class Backend(enum.Enum):
    """Which implementation runs a kernel (module docstring)."""

    #: The native kernel where it can run (CPU, float32 or float64, no gradient asked for, a C compiler on the
    #: machine), else the torch code.
    AUTO = "auto"
    #: Always the torch code (differentiable, any device).
    TORCH = "torch"
    #: Always the native kernel: an error where it cannot run.
    NATIVE = "native"


def native_available() -> bool:
    """Whether the native kernels can run on this machine: their library is built (at the first call, a few seconds
    once, then cached) and loaded, and the environment does not turn them off (``TORCHFACE_NATIVE=0``). Where it is
    False, :attr:`Backend.AUTO` runs the torch code and :attr:`Backend.NATIVE` raises (:func:`use_native`).

    Example:
        >>> native_available() in (True, False)
        True
    """
    return _native.library() is not None


def native_unavailable_reason() -> str | None:
    """Why :func:`native_available` is False (no C compiler, a failed build, ``TORCHFACE_NATIVE=0``); None where the
    kernels are available or were not asked for yet.

    Example:
        >>> native_available() or native_unavailable_reason() is not None
        True
    """
    return _native.unavailable_reason()


def use_native(backend: Backend, tensors: tuple[Tensor | float | None, ...], what: str, max_params: int = 0,
               num_params: int = 0) -> bool:  # fmt: skip
    """Whether ``what`` (a kernel's name, for messages) runs natively: ``backend`` allows it and the inputs suit it
    (CPU, one dtype of float32 or float64, no gradient asked for, no ``torch.func`` transform's or forward-AD dual
    tensor, not being traced by ``torch.compile``; with
    ``max_params``, at most that many parameters). With :attr:`Backend.NATIVE`, inputs that do not suit it raise ``RuntimeError``."""
    if backend is Backend.TORCH:
        return False
    check_choice(backend, "backend", Backend)
    arrays = [x for x in tensors if isinstance(x, Tensor)]
    dtype = arrays[0].dtype if arrays else torch.float32
    why = None
    if dtype not in (torch.float32, torch.float64) or any(x.dtype != dtype for x in arrays):
        why = f"needs tensors of one dtype, float32 or float64 (got {sorted({str(x.dtype) for x in arrays})})"
    elif not all(x.is_cpu for x in arrays):  # (is_cpu: x.device made a torch.device per tensor, 1-2 us each)
        why = "runs on the CPU only"
    elif torch.is_grad_enabled() and any(x.requires_grad for x in arrays):
        why = "does not propagate gradients (use Backend.TORCH)"
    elif is_compiling():  # traced ctypes calls were handed other tensors' memory: the process died
        why = "cannot be traced by torch.compile (the torch code runs under it)"
    elif is_transformed(*arrays):  # wrapped tensors have no memory to read; a dual tensor's tangent would be dropped
        why = "does not run under torch.func transforms or forward AD (use Backend.TORCH)"
    elif max_params and num_params > max_params:
        why = f"supports at most {max_params} parameters, got {num_params}"
    elif not native_available():
        why = f"is unavailable: {native_unavailable_reason()}"
    if why is None:
        return True
    if backend is Backend.NATIVE:
        raise RuntimeError(f"the native {what} {why}")
    return False
