"""torchface._compiling: the ``torch.compile`` check, and the features of this torch under ``torch.func``'s transforms,
probed rather than read from its version (``torch>=2.5.1``)."""

from __future__ import annotations

import functools
import re
import subprocess
import sys
import textwrap

import pytest
import torch
import torch.nn.functional as F

from torchface import _compiling, _deterministic
from torchface._compiling import check_reverse_mode, feature_probe, host_values, is_compiling


def test_is_compiling_is_false_in_eager_code_and_true_while_traced():
    seen = []

    def f(x):
        seen.append(is_compiling())
        return x + 1

    f(torch.zeros(1))
    torch.compile(f, backend="eager")(torch.zeros(1))
    assert seen[0] is False and seen[-1] is True


def _release() -> tuple[int, int] | None:
    """This torch's (major, minor) where it is a release (``2.13.0``, ``2.11.0+cu130``), None for a pre-release."""
    found = re.fullmatch(r"(\d+)\.(\d+)\.\d+(\+\S*)?", torch.__version__)
    return (int(found[1]), int(found[2])) if found else None


def _probes() -> tuple[bool, bool]:
    """Both probes run afresh (not their cached answers)."""
    reads = _compiling.transforms_read_values.__wrapped__()
    return reads, _deterministic._grid_sample_vmap_backward_broken.__wrapped__()


def test_the_probes_give_what_this_torch_does():
    """The probes' answers: the releases' (torch 2.10 reads a transform's values, 2.12 mended grid_sample's vmap
    backward: checked on 2.5.1, 2.11 and 2.13), and what the operations the tracker runs (a float64 ``.tolist()``
    under ``grad``, ``jacrev`` of a (2, 3, 7, 9) frame's samples with respect to the grid) do on this torch. A
    pre-release's version took a nightly for the older torch; the probes do not read it."""
    reads, broken = _probes()
    release = _release()
    if release is not None:
        assert (reads, broken) == (release >= (2, 10), release < (2, 12)), torch.__version__

    def values(x: torch.Tensor) -> torch.Tensor:
        assert x.tolist() == [0.25, -1.5, 3.0]
        return x.sum()

    x = torch.tensor([0.25, -1.5, 3.0], dtype=torch.float64)
    if reads:
        torch.func.grad(values)(x)
    else:
        with pytest.raises(RuntimeError, match="Cannot access data pointer of Tensor that doesn't have storage"):
            torch.func.grad(values)(x)
    gen = torch.Generator().manual_seed(0)
    images = torch.rand(2, 3, 7, 9, generator=gen, dtype=torch.float64)
    grid = torch.rand(2, 3, 4, 2, generator=gen, dtype=torch.float64) * 1.8 - 0.9

    def sample(g: torch.Tensor) -> torch.Tensor:
        return F.grid_sample(images, g, "bilinear", "border", align_corners=True)

    if broken:
        with pytest.raises(RuntimeError, match="Expected a proper Tensor but got None"):
            torch.func.jacrev(sample)(grid)
    else:
        want = torch.autograd.functional.jacobian(sample, grid)
        torch.testing.assert_close(torch.func.jacrev(sample)(grid), want, rtol=0, atol=1e-12)
    with pytest.MonkeyPatch.context() as patch:
        for version in ("2.10.0a0+git5e8f3c1", "2.12.0.dev20261101", "2.9.1"):
            patch.setattr(torch, "__version__", version)
            assert _probes() == (reads, broken), version


def test_the_probes_leave_the_callers_modes_alone_and_answer_the_same_under_them():
    """Asked under a caller's ``no_grad``, ``inference_mode`` (where ``jacrev`` of ``grid_sample`` passed on torch
    2.5.1, which raises outside it), CPU autocast, float64 and meta defaults, and inside a transform of the
    caller's (as they are: their first call comes under one): the same answers, and the modes as they were."""
    want = _probes()
    seen = []

    def modes() -> tuple:
        return (torch.is_grad_enabled(), torch.is_inference_mode_enabled(), torch.get_default_dtype(),
                torch.is_autocast_enabled("cpu"), torch.zeros(()).device.type)  # fmt: skip

    def under(context) -> None:
        with context:
            before = modes()
            seen.append(_probes())
            assert modes() == before

    under(torch.no_grad())
    under(torch.inference_mode())
    under(torch.autocast("cpu", dtype=torch.bfloat16))
    under(torch.device("meta"))
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        seen.append(_probes())
        assert torch.get_default_dtype() == torch.float64
    finally:
        torch.set_default_dtype(previous)

    def transformed(x: torch.Tensor) -> torch.Tensor:
        seen.append(_probes())
        return x.sum()

    torch.func.grad(transformed)(torch.zeros(2))
    torch.func.vmap(transformed)(torch.zeros(2, 3))
    torch.func.jacrev(transformed)(torch.zeros(2))
    assert seen == [want] * 8


def test_feature_probe_is_false_for_a_runtime_error_alone():
    """A torch error (what an unsupported operation under a transform raises) answers no; any other error is a
    fault of the probe, raised."""

    def not_a_torch_error() -> None:
        raise ValueError("not a torch error")

    assert feature_probe(lambda: None) is True
    assert feature_probe(lambda: torch.zeros(2) + torch.zeros(3)) is False  # (a RuntimeError)
    with pytest.raises(ValueError, match="not a torch error"):
        feature_probe(not_a_torch_error)


def test_the_probes_run_once_when_a_transform_first_asks_not_at_import(monkeypatch):
    """Import time matters, and eager code never asks: importing torchface and training_hooks (in a fresh process)
    runs neither probe, nor do reading, refusing and sampling outside a transform; the first call under a transform
    runs each once, and later calls read the kept answer (fresh caches here: this process's may be filled)."""
    code = textwrap.dedent("""
        import torchface, torchface.tracker, training_hooks.layer
        from torchface import _compiling, _deterministic
        probes = (_compiling.transforms_read_values, _deterministic._grid_sample_vmap_backward_broken)
        print([p.cache_info().misses for p in probes])
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "[0, 0]", (run.returncode, run.stdout, run.stderr[-2000:])

    fresh = [functools.cache(_compiling.transforms_read_values.__wrapped__),
             functools.cache(_deterministic._grid_sample_vmap_backward_broken.__wrapped__)]  # fmt: skip
    monkeypatch.setattr(_compiling, "transforms_read_values", fresh[0])
    monkeypatch.setattr(_deterministic, "_grid_sample_vmap_backward_broken", fresh[1])
    images, grid = torch.rand(1, 1, 3, 3), torch.zeros(1, 2, 2, 2)
    host_values(torch.tensor([1.0, 2.0]))
    check_reverse_mode("a step", images, grid)
    _deterministic.grid_sample_border(images, grid.requires_grad_()).sum().backward()
    assert [p.cache_info().misses for p in fresh] == [0, 0]

    def f(g: torch.Tensor) -> torch.Tensor:
        host_values(g.flatten())
        return _deterministic.grid_sample_border(images, g).sum()

    for _ in range(2):
        torch.func.grad(f)(torch.zeros(1, 2, 2, 2))
    assert [(p.cache_info().misses, p.cache_info().hits) for p in fresh] == [(1, 1), (1, 1)]


def test_an_older_torchs_transforms_are_read_value_by_value_and_refused_by_a_step(monkeypatch):
    """torch 2.5 to 2.9 could not ``.tolist()`` a ``torch.func`` transform's tensor ("Cannot access data pointer of
    Tensor that doesn't have storage"; ``.item()`` worked): the frames' and faces' checks read one value at a time
    there, and a tracking step, which reads values in many places, is refused in one line. Simulated on this torch:
    its ``.tolist()`` of a transform's tensor raises as theirs did, and the probe (run afresh) sees it. The refusal
    names the feature this build lacks, as a 2.10 nightly without it reads it too (it said "needs torch 2.10 or
    later (torch 2.10.0a0+git5e8f3c1 ...)")."""
    real = torch.Tensor.tolist
    monkeypatch.setattr(torch, "__version__", "2.10.0a0+git5e8f3c1")  # (a nightly of 2.10 before the feature)
    refused = (r"^a step cannot run under a torch\.func transform on this torch \(2\.10\.0a0\+git5e8f3c1\): it cannot "
               r"read the values of a transform's tensors \(\.tolist\(\) under torch\.func\.grad\), which a step "
               r"reads per stream; torch releases 2\.10 and later can: use torch\.autograd\.grad, or such a torch$")

    def old_tolist(self: torch.Tensor):
        if torch._C._functorch.is_functorch_wrapped_tensor(self):
            raise RuntimeError("Cannot access data pointer of Tensor that doesn't have storage")
        return real(self)

    monkeypatch.setattr(torch.Tensor, "tolist", old_tolist)
    fresh = functools.cache(_compiling.transforms_read_values.__wrapped__)  # (not this process's kept answer)
    monkeypatch.setattr(_compiling, "transforms_read_values", fresh)
    seen = []

    def f(x: torch.Tensor) -> torch.Tensor:
        values = torch.stack([x.amin(), x.amax()])
        seen.append(host_values(values))
        with pytest.raises(RuntimeError, match=refused):
            check_reverse_mode("a step", x)
        return x.sum()

    x = torch.tensor([0.25, -1.5, 3.0], dtype=torch.float64)
    torch.func.grad(f)(x)
    assert seen == [[-1.5, 3.0]]
    assert _compiling.transforms_read_values() is False
    check_reverse_mode("a step", x)  # outside a transform: nothing to refuse
    assert host_values(torch.tensor([1, 2])) == [1, 2]
