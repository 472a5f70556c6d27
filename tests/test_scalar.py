"""Tests for torchface._scalar: cached constants give Python numbers' results bit for bit."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import pytest
import torch

from torchface._scalar import isfinite, scalar


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_constants_give_the_python_numbers_results(dtype):
    """Products, quotients, differences and comparisons with the cached 0-dim tensor equal those with the number."""
    x = torch.randn(4000, generator=torch.Generator().manual_seed(0), dtype=dtype) * 10
    for v in (0.5, 1 / 3, 1e-6, math.pi, 4.6851**2 / 6.0, 1.4826, 3.0):
        c = scalar(v, x)
        assert c.dim() == 0 and c.dtype == dtype
        assert torch.equal(x * c, x * v) and torch.equal(c * x, v * x)
        assert torch.equal(x / c, x / v) and torch.equal(c - x, v - x)
        assert torch.equal(x < c, x < v) and torch.equal(x <= c, x <= v) and torch.equal(x > c, x > v)
    assert torch.equal(torch.where(x > 0, x, scalar(0.0, x)), torch.where(x > 0, x, 0.0))


def test_constants_are_cached_and_typed():
    x32, x64, i32 = torch.zeros(2), torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.int32)
    assert scalar(0.5, x32) is scalar(0.5, x32)
    assert scalar(0.5, x64) is not scalar(0.5, x32) and scalar(0.5, x64).dtype == torch.float64
    assert scalar(0, i32).dtype == torch.int32 and bool(scalar(0, i32) == 0)
    nan = scalar(float("nan"), x32)
    assert nan is scalar(float("nan"), x32) and bool(torch.isnan(nan))  # NaN too (it is not equal to itself)


def test_constant_first_made_in_inference_mode_works_with_autograd():
    """A constant first asked for inside inference mode still takes part in a differentiable computation."""
    with torch.inference_mode():
        scalar(0.123, torch.zeros(1, dtype=torch.float64))
    x = torch.rand(5, dtype=torch.float64, requires_grad=True)
    (x * scalar(0.123, x)).sum().backward()
    torch.testing.assert_close(x.grad, torch.full_like(x, 0.123))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_isfinite_equals_torch(dtype):
    x = torch.tensor([0.0, -0.0, 1.0, -2.5, float("inf"), -float("inf"), float("nan"), 3e38], dtype=dtype)
    assert torch.equal(isfinite(x), torch.isfinite(x))
    assert isfinite(x).tolist() == [True, True, True, True, False, False, False, True]  # 3e38 fits float32


def test_torch_compile_traces_the_constants_without_a_warning():
    """Dynamo traced through the constants' ``lru_cache`` (``scalar``, the rotation's generators) with a
    ``UserWarning`` ("Dynamo detected a call to a `functools.lru_cache`-wrapped function at 'so3.py:168'") that every
    compiled normalised face printed; while traced they are made in the graph, with the same values. In a child
    process: Dynamo warns once per process."""
    code = textwrap.dedent("""
        import warnings
        warnings.simplefilter("error")
        import torch
        from torchface._scalar import isfinite, scalar
        from torchface.geometry.so3 import axis_angle_to_matrix

        def f(aa):
            return axis_angle_to_matrix(aa) * scalar(0.5, aa), isfinite(aa / scalar(0.0, aa))

        aa = torch.tensor([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0]])
        got, ref = torch.compile(f, backend="eager")(aa), f(aa)
        assert all(torch.equal(g, r) for g, r in zip(got, ref))
        print("ok")
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "ok", (run.returncode, run.stderr[-2000:])
