"""Tracker states as plain data, and joined back into one batch: what ``torchface track`` keeps of each video's
tracking loop (``<stem>.state.partial``, :mod:`torchface.job`) so that ``--resume`` goes on exactly where the
interrupted run stopped.

:func:`to_plain` turns a state tree (:class:`~torchface.tracker.TrackerState`, its template management and mosaic,
:class:`~torchface.tracker.smoothing.SmoothingState`, ...: frozen dataclasses, named tuples, tuples, tensors, numbers)
into nested dicts, lists, strings, numbers and tensors, which ``torch.save`` writes and ``torch.load(...,
weights_only=True)`` reads without running any code from the file; :func:`from_plain` builds the tree again, the
classes named in it looked up among torchface's own (any other name is refused). Objects held twice (the state's
parameters also held by the management's cached angles; the templates also held by the visibility) are held twice
again: the tree's identities are kept, not only its values.

:func:`join` is the inverse of ``select``: ``join([state.select([0, 1]), state.select([2])])`` is ``state`` (every
tensor equal, bit for bit: :func:`same_tree`), so that videos resumed together from their own checkpoints track as
the batch they were tracked in.
"""

from __future__ import annotations

import dataclasses
import enum
import importlib
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

#: Fields left out of the plain data (scratch memory, :class:`~torchface.tracker.step.StepWorkspace`: a state
#: built again makes its own at its next step).
SKIPPED_FIELDS: frozenset[str] = frozenset({"workspace"})


def _name(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


def _class(name: object) -> type:
    """The torchface class ``name`` (``module:qualname``); anything else is refused (ValueError)."""
    if not isinstance(name, str) or ":" not in name:
        raise ValueError(f"not a class name: {name!r}")
    module, qualname = name.split(":", 1)
    if module != "torchface" and not module.startswith("torchface."):
        raise ValueError(f"{name}: not a torchface class")
    obj: Any = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    if not isinstance(obj, type) or not (dataclasses.is_dataclass(obj) or issubclass(obj, (tuple, enum.Enum))):
        raise ValueError(f"{name}: not a dataclass, named tuple or enum")
    if _name(obj) != name:  # (another module's class reached through a torchface module: torchface.job:os.stat_result)
        raise ValueError(f"{name}: not a torchface class (it is {_name(obj)})")
    return obj


def to_plain(tree: object) -> Any:
    """``tree`` as plain data (dicts, lists, str, int, float, bool, None and tensors) for ``torch.save``; an object
    met again (by identity: a tensor, a dataclass) is written as a reference to its first place."""
    seen: dict[int, int] = {}
    keep: list[object] = []  # (alive while walking: ids stay unique)

    def walk(x: object) -> Any:
        if x is None or isinstance(x, (bool, int, float, str)):
            return x
        if isinstance(x, (Tensor,)) or dataclasses.is_dataclass(x):
            if id(x) in seen:
                return {"ref": seen[id(x)]}
            seen[id(x)] = len(seen)
            keep.append(x)
            if isinstance(x, Tensor):
                t = x.detach()
                if t.untyped_storage().nbytes() != t.numel() * t.element_size():  # a view: torch.save would write
                    t = t.clone()  # its whole storage (a state's views of its buffers: 2.5 MB where 1.15 were its own)
                return {"tensor": t, "id": seen[id(x)]}
            assert not isinstance(x, type)
            values = {f.name: walk(getattr(x, f.name)) for f in dataclasses.fields(x) if f.name not in SKIPPED_FIELDS}
            return {"dataclass": _name(type(x)), "id": seen[id(x)], "fields": values}
        if isinstance(x, enum.Enum):
            return {"enum": _name(type(x)), "value": walk(x.value)}
        if isinstance(x, torch.dtype):
            return {"dtype": str(x).removeprefix("torch.")}
        if isinstance(x, torch.device):
            return {"device": str(x)}
        if isinstance(x, tuple):
            items = [walk(v) for v in x]
            return {"tuple": _name(type(x)) if type(x) is not tuple else None, "items": items}
        if isinstance(x, list):
            return {"list": [walk(v) for v in x]}
        if isinstance(x, dict) and all(isinstance(k, str) for k in x):
            return {"dict": {k: walk(v) for k, v in x.items()}}
        raise TypeError(f"cannot keep a {type(x).__name__} as plain data")

    return walk(tree)


def from_plain(plain: object, device: torch.device | str | None = None) -> Any:
    """The tree :func:`to_plain` made ``plain`` from (its tensors moved to ``device`` where given). Raises
    ValueError on data it did not make (an unknown class, a reference before its object, a missing field)."""
    made: dict[int, object] = {}

    def walk(x: object) -> Any:
        if x is None or isinstance(x, (bool, int, float, str)):
            return x
        if not isinstance(x, dict):
            raise ValueError(f"not plain tree data: {type(x).__name__}")
        if "ref" in x:
            if x["ref"] not in made:
                raise ValueError(f"a reference to object {x['ref']} before it")
            return made[x["ref"]]
        if "tensor" in x:
            t = x["tensor"]
            if not isinstance(t, Tensor):
                raise ValueError("a tensor entry without a tensor")
            made[x["id"]] = t = t if device is None else t.to(device)
            return t
        if "dataclass" in x:
            cls = _class(x["dataclass"])
            if not dataclasses.is_dataclass(cls):
                raise ValueError(f"{x['dataclass']}: not a dataclass")
            obj = object.__new__(cls)
            made[x["id"]] = obj
            names = {f.name for f in dataclasses.fields(cls)}
            given = x["fields"]
            if not isinstance(given, dict) or set(given) != names - SKIPPED_FIELDS:
                raise ValueError(f"{x['dataclass']}: fields {sorted(given) if isinstance(given, dict) else given} "
                                 f"are not its {sorted(names - SKIPPED_FIELDS)}")  # fmt: skip
            for f in dataclasses.fields(cls):
                object.__setattr__(obj, f.name, walk(given[f.name]) if f.name in given else None)
            return obj
        if "enum" in x:
            return _class(x["enum"])(walk(x["value"]))
        if "dtype" in x:
            dtype = getattr(torch, str(x["dtype"]), None)
            if not isinstance(dtype, torch.dtype):
                raise ValueError(f"not a dtype: {x['dtype']!r}")
            return dtype
        if "device" in x:
            return torch.device(str(x["device"]))
        if "tuple" in x:
            items = [walk(v) for v in x["items"]]
            return tuple(items) if x["tuple"] is None else _class(x["tuple"])(*items)
        if "list" in x:
            return [walk(v) for v in x["list"]]
        if "dict" in x:
            return {k: walk(v) for k, v in x["dict"].items()}
        raise ValueError(f"not plain tree data: keys {sorted(x)}")

    return walk(plain)


def join(parts: Sequence[Any], select: Callable[[Any, list[int]], Any] | None = None) -> Any:
    """One batch of the streams of ``parts`` (states of one kind, e.g. :class:`~torchface.tracker.TrackerState`s
    or :class:`~torchface.tracker.smoothing.SmoothingState`s, of ``B_i`` streams each), in order: the inverse of
    their ``select``, ``join([s.select(a), s.select(b)])`` equal to ``s.select(a + b)`` (:func:`same_tree`).

    Which tensors and tuples are per stream is told by ``select`` itself (default ``part.select(index)``): those
    whose length changes when the first part's streams are selected ``B_0 + 1`` times; they are concatenated, and
    the others (shared: intrinsics, configs, frame counts) must be the same in every part. Objects held twice in the
    first part (by identity) are held twice in the result.

    Raises:
        ValueError: parts of other kinds, or of other structure (an online-start watch in one and not in another),
            or whose shared values differ.
    """
    if not parts:
        raise ValueError("nothing to join")
    pick = select if select is not None else (lambda s, index: s.select(index))
    first = parts[0]
    n0 = _streams(first)
    probe = pick(first, [0] * (n0 + 1)) if n0 else None
    if probe is None:
        raise ValueError("cannot join a state of no streams")
    made: dict[int, object] = {}

    def walk(xs: list[Any], p: Any, at: str) -> Any:
        x0 = xs[0]
        key = id(x0)
        if (isinstance(x0, Tensor) or dataclasses.is_dataclass(x0)) and key in made:
            return made[key]
        if x0 is None or p is None:
            if any(x is not None for x in xs):
                raise ValueError(f"{at}: None in one part, not in another")
            return None
        if any(type(x) is not type(x0) for x in xs):
            raise ValueError(f"{at}: parts of other kinds ({sorted({type(x).__name__ for x in xs})})")
        if isinstance(x0, Tensor):
            if p.shape != x0.shape:  # per stream
                if p.dim() != x0.dim() or p.shape[1:] != x0.shape[1:]:
                    raise ValueError(f"{at}: per stream along another dimension than its first ({tuple(x0.shape)} "
                                     f"of {n0} streams, {tuple(p.shape)} of {n0 + 1})")  # fmt: skip
                out: object = torch.cat([x.to(x0.device) for x in xs])
            else:
                if any(x.shape != x0.shape or not torch.equal(x.to(x0.device), x0) for x in xs[1:]):
                    raise ValueError(f"{at}: a shared tensor differs between the parts")
                out = x0
            made[key] = out
            return out
        if dataclasses.is_dataclass(x0):
            values = {f.name: walk([getattr(x, f.name) for x in xs], getattr(p, f.name), f"{at}.{f.name}")
                      for f in dataclasses.fields(x0)}  # fmt: skip
            obj = object.__new__(type(x0))
            for name, v in values.items():
                object.__setattr__(obj, name, v)
            made[key] = obj
            return obj
        if isinstance(x0, tuple):
            if len(p) != len(x0):  # per stream (one item each)
                items = [v for x in xs for v in x]
            else:
                if any(len(x) != len(x0) for x in xs):
                    raise ValueError(f"{at}: tuples of other lengths")
                items = [walk([x[i] for x in xs], p[i], f"{at}[{i}]") for i in range(len(x0))]
            return tuple(items) if type(x0) is tuple else type(x0)(*items)
        if any(x != x0 for x in xs[1:]):
            raise ValueError(f"{at}: a shared value differs between the parts")
        return x0

    return walk(list(parts), probe, type(first).__name__)


def _streams(state: Any) -> int:
    """The streams of a state: the first dimension of its first per-stream tensor (``params``, ``time``)."""
    for name in ("params", "time"):
        value = getattr(state, name, None)
        if isinstance(value, Tensor):
            return int(value.shape[0])
    raise ValueError(f"cannot tell the streams of a {type(state).__name__}")


def same_tree(a: object, b: object) -> bool:
    """Whether two state trees are the same: of the same classes and structure, every tensor equal (dtype, shape,
    values bit for bit, NaN where NaN) and every other value equal; the objects ``a`` holds twice held twice in
    ``b`` too. Fields in :data:`SKIPPED_FIELDS` are not compared, nor those a dataclass leaves out of its value
    (``field(compare=False)``: a mosaic's ``claimed`` bookkeeping, None in a state after a detector's restart and
    made again by ``select``, which changes no value the state's next steps compute)."""
    pairs: dict[int, int] = {}

    def walk(x: object, y: object) -> bool:
        if type(x) is not type(y):
            return False
        if isinstance(x, Tensor) or dataclasses.is_dataclass(x):
            if id(x) in pairs:
                return pairs[id(x)] == id(y)
            pairs[id(x)] = id(y)
        if isinstance(x, Tensor):
            assert isinstance(y, Tensor)
            return (x.dtype == y.dtype and x.shape == y.shape and x.device == y.device
                    and bool(torch.equal(_bits(x), _bits(y))))
        if dataclasses.is_dataclass(x):
            return all(walk(getattr(x, f.name), getattr(y, f.name)) for f in dataclasses.fields(x)
                       if f.name not in SKIPPED_FIELDS and f.compare)  # fmt: skip
        if isinstance(x, (tuple, list)):
            assert isinstance(y, (tuple, list))
            return len(x) == len(y) and all(walk(u, v) for u, v in zip(x, y))
        if isinstance(x, float) and isinstance(y, float) and x != x and y != y:
            return True
        return bool(x == y)

    return walk(a, b)


def _bits(x: Tensor) -> Tensor:
    """``x``'s values as raw bytes (floating point: NaN equal to the same NaN, -0.0 not equal to 0.0)."""
    if not x.dtype.is_floating_point and not x.dtype.is_complex:
        return x
    return x.reshape(-1).contiguous().view(torch.uint8)
