"""Tests of torchface._deterministic: the substitutes for CUDA operations that raise under
``torch.use_deterministic_algorithms(True)``, checked against torch's operations on the CPU (forced with ``FORCE``);
the tracker and the layer through them; torch's operations everywhere else. The CUDA run itself:
tests/test_cuda.py."""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from torchface import _deterministic
from torchface._deterministic import grid_sample_border, nanmedian_values, reflect_pad
from torchface.template.management import TemplateConfig
from torchface.tracker import TrackerConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _helpers import leave_and_return_streams, managed_track  # noqa: E402

D = torch.float64


@pytest.fixture
def forced(monkeypatch):
    monkeypatch.setattr(_deterministic, "FORCE", True)


def test_nanmedian_values_equal_torchs(forced):
    """The same values as ``torch.nanmedian``: NaN entries skipped, the lower middle of an even count, ties, an
    infinite entry, a row of NaN (NaN), along the last and an inner dimension, float32 and float64."""
    gen = torch.Generator().manual_seed(0)
    for dtype in (torch.float32, D):
        x = torch.randn(6, 9, 5, generator=gen, dtype=dtype).round(decimals=1)  # (ties)
        x[torch.rand(x.shape, generator=gen) < 0.3] = torch.nan
        x[0, :, 0] = torch.nan
        x[1, 2, :] = torch.nan
        x[2, 3, 1] = torch.inf
        x[3, 4, 2] = -torch.inf
        for dim in (-1, 1, 0):
            torch.testing.assert_close(nanmedian_values(x, dim), torch.nanmedian(x, dim=dim).values, rtol=0, atol=0,
                                       equal_nan=True)  # fmt: skip
    assert bool(torch.isnan(nanmedian_values(torch.full((2, 3), torch.nan), 1)).all())


def _grid(gen: torch.Generator, B: int, H: int, W: int) -> torch.Tensor:
    """``(B, 4, 6, 2)`` points: inside, outside, on the border lines and on pixel centres."""
    g = torch.rand(B, 4, 6, 2, generator=gen, dtype=D) * 2.6 - 1.3
    g[:, 0, :, 0] = torch.tensor([-1.0, 1.0, 0.0, 1.0, -1.0, 0.5], dtype=D)  # x on the borders
    g[:, 0, :, 1] = torch.tensor([-1.0, -1.0, 1.0, 1.0, 0.25, 1.0], dtype=D)
    g[:, 1, :, 0] = torch.arange(6, dtype=D) / (W - 1) * 2 - 1  # pixel centres
    return g


def test_grid_sample_border_equals_torchs_values_and_gradients(forced):
    gen = torch.Generator().manual_seed(1)
    images = torch.rand(2, 3, 7, 9, generator=gen, dtype=D, requires_grad=True)
    grid = _grid(gen, 2, 7, 9).requires_grad_()
    weight = torch.rand(2, 3, 4, 6, generator=gen, dtype=D)
    outs = []
    for run in (grid_sample_border, lambda i, g: F.grid_sample(i, g, "bilinear", "border", align_corners=True)):
        out = run(images, grid)
        gi, gg = torch.autograd.grad((out * weight).sum(), (images, grid))
        outs.append((out, gi, gg))
    for a, b in zip(*outs):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    inner = (torch.rand(2, 3, 5, 2, generator=gen, dtype=D) * 1.8 - 0.9).requires_grad_()  # off pixel centres
    assert torch.autograd.gradcheck(grid_sample_border, (images, inner))


def test_jacrev_with_respect_to_the_grid_alone_under_an_old_torch(monkeypatch):
    """torch 2.11's ``vmap`` rule of ``grid_sample``'s backward raised where the grid asks for a gradient and the image
    does not ("Expected a proper Tensor but got None"; ``torch.func.jacrev`` of the normalised face with respect to the
    pose, session 57), and where the image requires grad outside the transform too: there the gathered corners run, and
    their Jacobian is torch's. Simulated on this torch: its sampler raises as 2.11's did where the grid is a
    transform's and the image is not at its level, the probe (run afresh) sees it, and torch's sampler's calls are
    counted; the image's own gradient and plain autograd keep torch's sampler."""
    from torch.func import grad, jacrev

    gen = torch.Generator().manual_seed(3)
    images = torch.rand(2, 3, 7, 9, generator=gen, dtype=D)
    grid = torch.rand(2, 3, 4, 2, generator=gen, dtype=D) * 1.8 - 0.9
    want = torch.autograd.functional.jacobian(lambda g: grid_sample_border(images, g), grid)
    real = F.grid_sample
    calls = []

    def as_torch_2_11(image, points, *args, **kwargs):
        if _deterministic._grid_alone_under_a_transform(image, points):
            raise RuntimeError("Expected a proper Tensor but got None (or an undefined Tensor in C++) for argument #0")
        calls.append(1)
        return real(image, points, *args, **kwargs)

    monkeypatch.setattr(_deterministic.F, "grid_sample", as_torch_2_11)
    fresh = functools.cache(_deterministic._grid_sample_vmap_backward_broken.__wrapped__)  # (not the kept answer)
    monkeypatch.setattr(_deterministic, "_grid_sample_vmap_backward_broken", fresh)
    assert fresh() is True
    calls.clear()
    got = jacrev(lambda g: grid_sample_border(images, g))(grid)
    assert not calls  # (the gathered corners)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    # an image that requires grad outside the transform (a frame a network made) asks for none inside it: torch
    # 2.11 raised there too; the Jacobian's own gradient with respect to the image is autograd's
    outer = images.clone().requires_grad_()
    got = jacrev(lambda g: grid_sample_border(outer, g))(grid)
    assert not calls
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    # (the Jacobian is linear in the image: its weighted sum's gradient G gives any image's weighted sum as <G, image>,
    # checked against torch's sampler for another image; torch 2.11 has no double backward of grid_sample)
    weights = torch.rand(got.shape, generator=gen, dtype=D)
    (image_grad,) = torch.autograd.grad((got * weights).sum(), outer)
    other = torch.rand(images.shape, generator=gen, dtype=D)
    other_jacobian = torch.autograd.functional.jacobian(
        lambda g: real(other, g, mode="bilinear", padding_mode="border", align_corners=True), grid
    )
    torch.testing.assert_close((image_grad * other).sum(), (other_jacobian * weights).sum(), rtol=1e-12, atol=0)
    grad(lambda i: grid_sample_border(i, grid).sum())(images)  # the image's gradient: torch's sampler
    grid_sample_border(images, grid.clone().requires_grad_())  # plain autograd: torch's sampler
    assert len(calls) == 2


def test_grid_sample_border_reads_non_finite_points_as_torch_does(forced):
    """A NaN coordinate (a diverged stream's point) reads column / row 0 and an infinite one the border, as
    grid_sample does; the substitute took NaN through ``clamp`` into the gather: "index -9223372036854775808 is out
    of bounds" (a device-side assert on CUDA). Its image gradient stays finite, the point's own is 0. (torch's CPU
    backward with a NaN point crashes the process: not compared.)"""
    gen = torch.Generator().manual_seed(2)
    images = torch.rand(2, 3, 4, 5, generator=gen, dtype=D)
    grid = _grid(gen, 2, 4, 5)
    grid[0, 0, :4, 0] = torch.tensor([torch.nan, torch.inf, -torch.inf, 0.3], dtype=D)
    grid[1, 1, :, 1] = torch.nan
    grid[1, 2, 0] = torch.nan
    theirs = F.grid_sample(images, grid, "bilinear", "border", align_corners=True)
    torch.testing.assert_close(grid_sample_border(images, grid), theirs, rtol=0, atol=1e-12)
    pixel = torch.rand(1, 1, 1, 1, generator=gen, dtype=D)  # (W - 1 = 0: an infinite coordinate times 0 is NaN)
    point = torch.tensor([[[[torch.inf, torch.nan]]]], dtype=D)
    assert torch.equal(grid_sample_border(pixel, point), pixel)
    images.requires_grad_(), grid.requires_grad_()
    gi, gg = torch.autograd.grad(grid_sample_border(images, grid).sum(), (images, grid))
    assert bool(gi.isfinite().all()) and not bool(gg[1, 2, 0].any()) and not bool(gg[0, 0, 0].any())


def test_grid_sample_border_reads_the_right_pixel_of_a_large_frame(forced):
    """A frame of more than 2**24 pixels (3 x 6000001 here; a 6K or 8K frame in NormalisedFace): the corners' flat
    index row * W + column was computed in the image's float32, where integers past 2**24 round to even, so a point
    in the last row read a neighbouring pixel (0.84 off torch's sample); now in integers."""
    gen = torch.Generator().manual_seed(3)
    images = torch.rand(1, 1, 3, 6_000_001, generator=gen)
    grid = torch.rand(1, 1, 500, 2, generator=gen) * 2 - 1
    grid[..., 1] = 1.0  # the last row: flat indices from 12000002 to 18000002
    theirs = F.grid_sample(images, grid, "bilinear", "border", align_corners=True)
    torch.testing.assert_close(grid_sample_border(images, grid), theirs, rtol=0, atol=1e-6)


def test_reflect_pad_equals_torchs(forced):
    images = torch.rand(2, 3, 5, 7, dtype=D, requires_grad=True)
    weight = torch.rand(2, 3, 9, 11, dtype=D)
    ours, theirs = reflect_pad(images, 2), F.pad(images, (2, 2, 2, 2), mode="reflect")
    assert torch.equal(ours, theirs)
    g1, g2 = (torch.autograd.grad((p * weight).sum(), images)[0] for p in (ours, theirs))
    torch.testing.assert_close(g1, g2, rtol=0, atol=1e-15)


def test_torchs_operations_off_cuda_even_in_deterministic_mode(monkeypatch):
    """The substitutes run only where torch's CUDA kernels would raise: on the CPU (and without the mode) torch's
    own operations run, so nothing else changes."""
    calls = []
    monkeypatch.setattr(torch, "nanmedian", lambda *a, **k: calls.append(1) or torch.sort(a[0]).values.max(-1))
    x = torch.rand(2, 4, requires_grad=True)
    previous = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        nanmedian_values(x)
        assert calls == [1]
        assert not _deterministic._substitute(x, backward=True) and not _deterministic._substitute(x, backward=False)
    finally:
        torch.use_deterministic_algorithms(previous)


def test_tracking_and_the_layer_through_the_substitutes(monkeypatch):
    """Managed tracking (the torch code) and ``NormalisedFaceLayer``'s unrolled backward with every substitute
    forced: the same statuses and estimates as torch's operations give, to float64 rounding."""
    from torchface.backend import Backend
    from torchface.model.candide import load_candide3
    from training_hooks.layer import LayerConfig, LayerMode, NormalisedFaceLayer

    frames, lm, _ = leave_and_return_streams(160, 120, 6)
    config = TrackerConfig(num_levels=2, max_points=400, iterations=(6, 4), backend=Backend.TORCH,
                           template=TemplateConfig(recovery_every=2))  # fmt: skip
    runs = []
    for force in (False, True):
        monkeypatch.setattr(_deterministic, "FORCE", force)
        results = managed_track(load_candide3(dtype=D), config, frames, lm)
        layer = NormalisedFaceLayer(LayerConfig(mode=LayerMode.UNROLLED, size=24, tracker=config)).double()
        state, _ = layer.initialise(frames[:, 0], lm)
        frame = frames[:, 1].to(D).requires_grad_()
        out = layer(frame, state)
        out.image.square().sum().backward()
        runs.append((results, out.image.detach(), frame.grad))
    (a, ia, ga), (b, ib, gb) = runs
    for ra, rb in zip(a, b):
        assert torch.equal(ra.status, rb.status)
        torch.testing.assert_close(ra.axis_angle, rb.axis_angle, rtol=0, atol=1e-9)
        torch.testing.assert_close(ra.confidence, rb.confidence, rtol=0, atol=1e-9)
    torch.testing.assert_close(ia, ib, rtol=0, atol=1e-9)
    torch.testing.assert_close(ga, gb, rtol=1e-6, atol=1e-9)

