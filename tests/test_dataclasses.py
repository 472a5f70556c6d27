"""A package-wide convention: the dataclasses that hold tensors (results, states, model data, specs) compare by
identity (``eq=False``, as :class:`torchface.model.FaceModel`), since a field-wise ``==`` on tensors raised
"Boolean value of Tensor with more than one value is ambiguous"."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil

import torch

import torchface
import training_hooks
from torchface.solver.least_squares import SolveResult


def _tensor_dataclasses() -> list[type]:
    """The dataclasses of ``torchface`` and ``training_hooks`` with a tensor field."""
    found = []
    packages = [(torchface.__path__, "torchface."), (training_hooks.__path__, "training_hooks.")]
    for info in (i for path, prefix in packages for i in pkgutil.walk_packages(path, prefix)):
        module = importlib.import_module(info.name)
        for obj in vars(module).values():
            if inspect.isclass(obj) and dataclasses.is_dataclass(obj) and obj.__module__ == module.__name__:
                if any("Tensor" in str(f.type) for f in dataclasses.fields(obj)):
                    found.append(obj)
    return found


def test_every_dataclass_holding_tensors_compares_by_identity():
    classes = _tensor_dataclasses()
    assert len(classes) > 20  # TrackerState, TrackResult, Template, Fragments, SolveResult, ...
    names = {c.__qualname__ for c in classes}
    assert {"LayerResult", "TrackedSequence"} <= names  # training_hooks' (their == raised as torchface's did)
    field_wise = [c.__qualname__ for c in classes if c.__dataclass_params__.eq]
    assert field_wise == []
    assert all(c.__hash__ is object.__hash__ for c in classes)  # hash agrees with ==


def test_a_result_compares_and_hashes_without_error():
    r = SolveResult(torch.zeros(2, 3), torch.ones(2), torch.ones(2), torch.zeros(2, dtype=torch.long),
                    torch.zeros(2, dtype=torch.long))  # fmt: skip
    same_tensors = dataclasses.replace(r)
    assert r == r and r != same_tensors and same_tensors in [r, same_tensors]
    assert len({r, same_tensors}) == 2
