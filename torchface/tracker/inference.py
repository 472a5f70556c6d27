"""The per-frame work without autograd's bookkeeping (``torch.inference_mode``), results as normal tensors.

At one stream every operation of a tracking step works on a few thousand values, so a step's time is mostly
the dispatch of its thousands of operations. Inference mode leaves out autograd's dispatch keys (``no_grad`` still
goes through them): measured on benchmark.py's frames at one stream, one thread, the bare step took 8.7-9.3
instead of 10.6-11.2 ms and the managed step 12.2-12.6 instead of 15.1-15.9 ms (at 128 streams the step is bound
by memory traffic and does not change).

Tensors made in inference mode are *inference tensors*: autograd refuses to save them for a backward pass, and
they cannot be modified in place outside inference mode. :func:`run_without_autograd` therefore hands back
normal copies of the tensors its function made (:func:`normal_tensors`); what the function passed through
unchanged (a state's templates, its mosaic) is returned as it was, the same objects.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

import torch
from torch import Tensor

from torchface._compiling import is_transformed

__all__ = ["normal_tensors", "run_without_autograd", "without_autograd"]

T = TypeVar("T")

_SCALARS = (bool, int, float, complex, str, bytes, torch.dtype, torch.device)

#: The attribute that marks a frozen dataclass instance as holding normal tensors only (:func:`normal_tensors`).
_NORMAL_MARK = "_torchface_normal_tensors"


def normal_tensors(tree: T) -> T:
    """``tree`` with each inference tensor in it replaced by a normal copy (``clone`` outside inference mode).

    Walks tensors, dataclass instances, tuples (named tuples too), lists and dicts. An object holding no inference
    tensor is returned as it is (the same object), one that does as a shallow copy with those members replaced (a
    dataclass: its fields only, so values cached on the instance are made again from the copies); an object reached
    twice is copied once (aliasing is kept). Other values are returned as they are.

    A frozen dataclass instance handed back is marked as holding normal tensors only, and a marked instance is not
    walked again: a state passes most of its parts (templates, mosaic) on unchanged from step to step, and walking
    them every step took 0.2 ms per frame at one stream with template management. Its fields cannot be rebound, and
    a tensor never becomes an inference tensor (an in-place change under inference mode leaves it a normal tensor),
    so the mark stays true.
    """
    memo: dict[int, Any] = {}

    def walk(x: Any) -> Any:
        if isinstance(x, _SCALARS) or x is None:
            return x
        key = id(x)
        if key in memo:
            return memo[key]
        out: Any  # x, or its copy holding normal tensors
        if isinstance(x, Tensor):
            out = x.clone() if x.is_inference() else x
        elif getattr(x, "__dict__", None) is not None and x.__dict__.get(_NORMAL_MARK):
            out = x
        elif dataclasses.is_dataclass(x) and not isinstance(x, type):
            changed: dict[str, Any] = {}
            for f in dataclasses.fields(x):
                value = getattr(x, f.name)
                new = walk(value)
                if new is not value:
                    changed[f.name] = new
            out = x
            if changed:  # a copy of the fields alone (no __init__ / __post_init__ to run again, no cached values)
                out = object.__new__(type(x))
                for f in dataclasses.fields(x):
                    object.__setattr__(out, f.name, changed.get(f.name, getattr(x, f.name)))
            if getattr(type(x), "__dataclass_params__").frozen and getattr(out, "__dict__", None) is not None:
                object.__setattr__(out, _NORMAL_MARK, True)
        elif isinstance(x, (tuple, list)):
            items = [walk(v) for v in x]
            out = x
            if any(a is not b for a, b in zip(items, x)):
                out = type(x)(*items) if hasattr(x, "_fields") else type(x)(items)
        elif isinstance(x, dict):
            values = {k: walk(v) for k, v in x.items()}
            out = x if all(values[k] is v for k, v in x.items()) else type(x)(values)
        else:
            out = x
        memo[key] = out
        return out

    return walk(tree)


def run_without_autograd(fn: Callable[..., T], inputs: Iterable[object], *args: Any, **kwargs: Any) -> T:
    """``fn(*args, **kwargs)`` in inference mode, unless one of ``inputs`` needs a gradient, with its result's new
    tensors made normal (:func:`normal_tensors`).

    Args:
        fn: the work; it must not need autograd when none of ``inputs`` requires grad.
        inputs: the tensors through which a caller could want gradients (other values are skipped): when grad
            mode is on and one of them requires grad, or one of them is a ``torch.func`` transform's tensor
            (``grad``, ``jvp``, ``vmap``, ...) or a forward-AD dual tensor, ``fn`` runs as it is.

    Already in inference mode (a caller's, or an outer call of this function), ``fn`` runs as it is and its result
    is not copied. Where a gradient is wanted, ``fn`` is given normal copies of the inference tensors among
    ``args`` and ``kwargs`` (:func:`normal_tensors`: a state made in a caller's inference mode).
    """
    inputs = tuple(inputs)
    if torch.is_inference_mode_enabled():
        return fn(*args, **kwargs)
    if (torch.is_grad_enabled() and any(isinstance(x, Tensor) and x.requires_grad for x in inputs)) or is_transformed(
        *inputs
    ):  # (torch.func's wrapped tensors, forward AD's tangents: inference mode would drop them)
        # A state made in a caller's inference mode (a validation pass) holds inference tensors, which autograd
        # refuses to save ("Inference tensors cannot be saved for backward"): normal copies of them.
        args, kwargs = normal_tensors((args, kwargs))
        return fn(*args, **kwargs)
    with torch.inference_mode():
        out = fn(*args, **kwargs)
    return normal_tensors(out)


def without_autograd(inputs_of: Callable[..., Iterable[object]]) -> Callable[[Callable[..., T]], Callable[..., T]]:
    """Decorator: the function runs as :func:`run_without_autograd` with ``inputs_of(*args, **kwargs)`` as the
    tensors through which a caller could want gradients.

    Example:
        >>> @without_autograd(lambda x: (x,))
        ... def double(x):
        ...     return x * 2
        >>> double(torch.ones(2)).is_inference()
        False
    """

    def decorate(fn: Callable[..., T]) -> Callable[..., T]:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> T:
            return run_without_autograd(fn, inputs_of(*args, **kwargs), *args, **kwargs)

        return wrapper

    return decorate
