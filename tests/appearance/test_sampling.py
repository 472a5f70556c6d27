"""Tests for torchface.appearance.sampling: pixel-centre bilinear sampling, gradient images, gray."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import pytest
import torch

from torchface.appearance import image_with_gradients, pixels_to_grid, sample_at_pixels, to_gray

D = torch.float64


def _bilinear_reference(img: torch.Tensor, u: float, v: float) -> torch.Tensor:
    """Textbook bilinear interpolation of ``img (C, H, W)`` at pixel ``(u, v)`` (centres at integers), clamped."""
    _, h, w = img.shape
    u = min(max(u, 0.0), w - 1.0)
    v = min(max(v, 0.0), h - 1.0)
    u0, v0 = min(int(math.floor(u)), w - 2), min(int(math.floor(v)), h - 2)
    a, b = u - u0, v - v0
    return (
        (1 - a) * (1 - b) * img[:, v0, u0]
        + a * (1 - b) * img[:, v0, u0 + 1]
        + (1 - a) * b * img[:, v0 + 1, u0]
        + a * b * img[:, v0 + 1, u0 + 1]
    )


# ------------------------------------------------------------------------------------------- cardinality


def test_sample_shapes():
    img = torch.rand(2, 3, 7, 9)
    pts = torch.rand(2, 5, 2) * 6
    values, inside = sample_at_pixels(img, pts)
    assert values.shape == (2, 5, 3) and inside.shape == (2, 5) and inside.dtype == torch.bool


def test_image_with_gradients_shape():
    out = image_with_gradients(torch.rand(3, 1, 6, 8))
    assert out.shape == (3, 3, 6, 8)


# ----------------------------------------------------------------------------------------------- feature


def test_integer_coordinates_return_pixel_values_exactly():
    gen = torch.Generator().manual_seed(0)
    img = torch.rand(2, 3, 11, 13, generator=gen, dtype=D)
    u = torch.randint(0, 13, (2, 40), generator=gen)
    v = torch.randint(0, 11, (2, 40), generator=gen)
    pts = torch.stack([u, v], -1).to(D)
    values, inside = sample_at_pixels(img, pts)
    expected = img[torch.arange(2)[:, None], :, v, u]  # (B, N, C): pixel (u, v) is column u, row v
    torch.testing.assert_close(values, expected, rtol=0, atol=1e-12)
    assert bool(inside.all())


def test_float32_integer_coordinates_are_exact_enough():
    """In float32 the normalise/unnormalise round trip of grid_sample costs ~1e-6 px, so values agree to ~1e-4."""
    img = torch.rand(1, 1, 120, 160)
    uu, vv = torch.meshgrid(torch.arange(160), torch.arange(120), indexing="xy")
    pts = torch.stack([uu.flatten(), vv.flatten()], -1).float().unsqueeze(0)
    values, _ = sample_at_pixels(img, pts)
    torch.testing.assert_close(values[0, :, 0], img.flatten(), rtol=0, atol=1e-4)


def test_matches_manual_bilinear_interpolation():
    gen = torch.Generator().manual_seed(1)
    img = torch.rand(2, 2, 8, 10, generator=gen, dtype=D)
    pts = torch.stack(
        [torch.rand(2, 30, generator=gen, dtype=D) * 9, torch.rand(2, 30, generator=gen, dtype=D) * 7], -1
    )
    values, inside = sample_at_pixels(img, pts)
    for b in range(2):
        for n in range(30):
            ref = _bilinear_reference(img[b], float(pts[b, n, 0]), float(pts[b, n, 1]))
            torch.testing.assert_close(values[b, n], ref, rtol=0, atol=1e-12)
    assert bool(inside.all())


def test_row_column_order():
    """``(u, v)`` is (column, row): moving u walks along a row."""
    img = torch.arange(12, dtype=D).reshape(1, 1, 3, 4)  # value = 4 * row + col
    values, _ = sample_at_pixels(img, torch.tensor([[[2.5, 1.0], [0.0, 1.5], [3.0, 2.0]]], dtype=D))
    torch.testing.assert_close(values[0, :, 0], torch.tensor([6.5, 6.0, 11.0], dtype=D))


def test_outside_points_flagged_and_clamped_to_border():
    img = torch.arange(12, dtype=D).reshape(1, 1, 3, 4)
    pts = torch.tensor([[[-0.5, 1.0], [3.2, 0.0], [1.0, -1.0], [1.0, 2.5], [3.0, 2.0], [0.0, 0.0]]], dtype=D)
    values, inside = sample_at_pixels(img, pts)
    assert inside[0].tolist() == [False, False, False, False, True, True]
    # border padding: outside points take the nearest edge value
    torch.testing.assert_close(values[0, :4, 0], torch.tensor([4.0, 3.0, 1.0, 9.0], dtype=D))


def test_nan_points_are_not_inside():
    img = torch.rand(1, 1, 5, 5, dtype=D)
    _, inside = sample_at_pixels(img, torch.tensor([[[float("nan"), 1.0], [1.0, 1.0]]], dtype=D))
    assert inside[0].tolist() == [False, True]


def test_nan_points_backward_does_not_crash_and_gradients_are_finite():
    """grid_sample's CPU backward (border padding) kills the process on a NaN grid point: run it in a child so
    that a regression fails this test instead of the whole session."""
    code = textwrap.dedent("""
        import torch
        torch.set_num_threads(1)
        from torchface.appearance import sample_at_pixels
        img = torch.rand(2, 3, 6, 7, dtype=torch.float64, requires_grad=True)
        pts = torch.tensor([[[float("nan"), 1.0], [2.5, 3.0]], [[float("inf"), 2.0], [1.0, float("-inf")]]],
                           dtype=torch.float64, requires_grad=True)
        values, inside = sample_at_pixels(img, pts)
        assert inside.tolist() == [[False, True], [False, False]], inside
        assert torch.isfinite(values).all()
        (values * inside.unsqueeze(-1)).sum().backward()
        assert torch.isfinite(img.grad).all() and torch.isfinite(pts.grad).all()
        assert torch.equal(pts.grad[0, 0], torch.zeros(2, dtype=torch.float64)) and bool(pts.grad[0, 1].ne(0).any())
        print("ok")
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "ok", (run.returncode, run.stderr[-2000:])


def test_pixels_to_grid_align_corners():
    g = pixels_to_grid(torch.tensor([[[0.0, 0.0], [9.0, 5.0], [4.5, 2.5]]], dtype=D), 6, 10)
    torch.testing.assert_close(g[0], torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0]], dtype=D))


def test_image_with_gradients_equals_central_differences():
    gen = torch.Generator().manual_seed(2)
    gray = torch.rand(2, 1, 9, 12, generator=gen, dtype=D)
    out = image_with_gradients(gray)
    torch.testing.assert_close(out[:, :1], gray)
    g = gray[:, 0]
    du = torch.empty_like(g)
    dv = torch.empty_like(g)
    du[:, :, 1:-1] = 0.5 * (g[:, :, 2:] - g[:, :, :-2])
    dv[:, 1:-1, :] = 0.5 * (g[:, 2:, :] - g[:, :-2, :])
    # replicate border: the missing neighbour is the pixel itself
    du[:, :, 0] = 0.5 * (g[:, :, 1] - g[:, :, 0])
    du[:, :, -1] = 0.5 * (g[:, :, -1] - g[:, :, -2])
    dv[:, 0, :] = 0.5 * (g[:, 1, :] - g[:, 0, :])
    dv[:, -1, :] = 0.5 * (g[:, -1, :] - g[:, -2, :])
    torch.testing.assert_close(out[:, 1], du, rtol=0, atol=1e-12)
    torch.testing.assert_close(out[:, 2], dv, rtol=0, atol=1e-12)


def test_image_gradients_exact_for_quadratic_image():
    """Central differences are exact for quadratics: d/du (a u^2 + b u v) = 2 a u + b v."""
    vv, uu = torch.meshgrid(torch.arange(10, dtype=D), torch.arange(14, dtype=D), indexing="ij")
    gray = (0.01 * uu**2 + 0.02 * uu * vv - 0.03 * vv**2).view(1, 1, 10, 14)
    out = image_with_gradients(gray)[0]
    inner = (slice(1, -1), slice(1, -1))
    torch.testing.assert_close(out[1][inner], (0.02 * uu + 0.02 * vv)[inner], rtol=0, atol=1e-12)
    torch.testing.assert_close(out[2][inner], (0.02 * uu - 0.06 * vv)[inner], rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_to_gray_is_kornias_bit_for_bit(dtype):
    import kornia

    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(2, 3, 17, 23, generator=g, dtype=dtype)
    assert torch.equal(to_gray(rgb), kornia.color.rgb_to_grayscale(rgb))
    u8 = (rgb * 255).to(torch.uint8)
    assert torch.equal(to_gray(u8), kornia.color.rgb_to_grayscale(u8))
    # out=: written into a slot of a bigger tensor, from a strided window, the same values
    out = torch.full((3, 1, 9, 11), -1.0, dtype=dtype)
    window = rgb[1:2, :, 4:13, 5:16]
    assert to_gray(window, out=out[2:3]) is not None and torch.equal(out[2:3], kornia.color.rgb_to_grayscale(window))
    assert bool((out[:2] == -1).all())
    with pytest.raises(ValueError, match="out="):
        to_gray(u8, out=out[:2])


def test_to_gray_bt601_and_passthrough():
    rgb = torch.tensor([1.0, 0.0, 0.0]).view(1, 3, 1, 1).expand(1, 3, 2, 2)
    torch.testing.assert_close(to_gray(rgb), torch.full((1, 1, 2, 2), 0.299), rtol=0, atol=1e-6)
    g = torch.rand(1, 1, 3, 3)
    assert to_gray(g) is g


# -------------------------------------------------------------------------------------------- gradcheck


def test_gradcheck_points_and_image():
    gen = torch.Generator().manual_seed(3)
    img = torch.rand(1, 2, 5, 6, generator=gen, dtype=D, requires_grad=True)
    # keep away from integer coordinates where bilinear sampling has kinks
    pts = (torch.rand(1, 4, 2, generator=gen, dtype=D) * 0.8 + 0.1 + torch.tensor([[1.0, 1.0], [2.0, 3.0], [4.0, 2.0], [3.0, 1.0]], dtype=D)).requires_grad_()
    assert torch.autograd.gradcheck(lambda i, p: sample_at_pixels(i, p)[0], (img, pts))


# -------------------------------------------------------------------------------------------- exception


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        sample_at_pixels(torch.rand(3, 4, 5), torch.rand(1, 2, 2))
    with pytest.raises(ValueError, match=r"\(B, N, 2\)"):
        sample_at_pixels(torch.rand(1, 1, 4, 5), torch.rand(1, 2, 3))
    with pytest.raises(ValueError, match=r"B=2"):
        sample_at_pixels(torch.rand(2, 1, 4, 5), torch.rand(1, 2, 2))
    with pytest.raises(ValueError, match="1 or 3"):
        to_gray(torch.rand(1, 2, 4, 4))
    # numpy images were AttributeErrors ('numpy.ndarray' object has no attribute 'dim'); a to_gray out= of the wrong
    # shape an IndexError ("too many indices for tensor of dimension 1"), as pyr_down's is a ValueError.
    from torchface.appearance.sampling import pyr_down

    for fn, name in ((to_gray, "images"), (pyr_down, "images"), (image_with_gradients, "gray")):
        with pytest.raises(TypeError, match=f"{name} must be a torch.Tensor"):
            fn(torch.rand(1, 1, 4, 4).numpy())  # type: ignore[arg-type]
    for out in (torch.zeros(1), torch.zeros(2, 1, 4, 4), torch.zeros(1, 1, 4, 4, dtype=torch.float64)):
        with pytest.raises(ValueError, match=r"out must be \(1, 1, 4, 4\) torch.float32"):
            to_gray(torch.rand(1, 3, 4, 4), out=out)


@pytest.mark.parametrize("shape", [(2, 1, 40, 60), (1, 3, 24, 32), (1, 1, 41, 33)])
def test_pyr_down_equals_kornia_pyrdown(shape):
    """The strided-slice pyramid step equals kornia's pyrdown (blur + half-size bilinear) on even sizes; on odd
    sizes it keeps the pixel-centre alignment (output j centred on input 2 j + 0.5) and drops the last row."""
    import kornia

    from torchface.appearance.sampling import pyr_down

    x = torch.rand(shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ours = pyr_down(x)
    assert ours.shape == (*shape[:2], shape[2] // 2, shape[3] // 2)
    if shape[2] % 2 == 0 and shape[3] % 2 == 0:
        torch.testing.assert_close(ours, kornia.geometry.transform.pyrdown(x), rtol=0, atol=1e-12)
    else:
        even = x[..., : shape[2] // 2 * 2 + 2, : shape[3] // 2 * 2 + 2]
        # away from the dropped border the odd-size result equals the even-size one of a slightly larger crop
        torch.testing.assert_close(ours[..., :-2, :-2], pyr_down(even)[..., :-2, :-2], rtol=0, atol=1e-12)


def test_pyr_down_out_is_the_same_step():
    """``out=`` writes the same values bit for bit, also into a strided slot of a larger tensor, and returns it;
    an ``out`` of the wrong shape or dtype is refused."""
    from torchface.appearance.sampling import pyr_down

    x = torch.rand(3, 1, 30, 44, generator=torch.Generator().manual_seed(4))
    big = torch.full((5, 1, 15, 22), -1.0)
    got = pyr_down(x, out=big[1:4])
    assert got.data_ptr() == big[1:4].data_ptr() and torch.equal(got, pyr_down(x))
    assert bool((big[0] == -1).all()) and bool((big[4] == -1).all())
    with pytest.raises(ValueError, match="out must be"):
        pyr_down(x, out=torch.empty(3, 1, 15, 21))
    with pytest.raises(ValueError, match="out must be"):
        pyr_down(x, out=torch.empty(3, 1, 15, 22, dtype=torch.float64))


def test_pyr_down_gradcheck():
    """The in-place accumulation of the taps keeps the pyramid step differentiable (float64 gradcheck)."""
    from torchface.appearance.sampling import pyr_down

    x = torch.rand(1, 1, 7, 8, generator=torch.Generator().manual_seed(3), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(pyr_down, (x,))


def test_sampling_refuses_what_torch_would_fail_deep_inside():
    """sample_at_pixels met a numpy array with "'numpy.ndarray' object has no attribute 'dim'" and uint8 images
    with grid_sample's "not implemented for 'Byte'"; image_with_gradients of to_gray's uint8 gray with "result type
    Float can't be cast to the desired output type Byte"; pixels_to_grid had no check (a size of 0 or -3 taken, a
    (B, N, 3) tensor torch's "The size of tensor a (3) must match"). Each is now an error naming the argument."""
    images = torch.rand(1, 3, 8, 10, dtype=D)
    points = torch.tensor([[[1.0, 2.0]]], dtype=D)
    with pytest.raises(TypeError, match="images must be a floating-point torch.Tensor, got ndarray"):
        sample_at_pixels(images.numpy(), points)
    with pytest.raises(TypeError, match="points_px must be a floating-point torch.Tensor, got ndarray"):
        sample_at_pixels(images, points.numpy())
    with pytest.raises(TypeError, match=r"images must be a floating-point torch.Tensor, got dtype torch.uint8 "
                                        r"\(uint8 frames: images.float\(\) / 255\)"):  # fmt: skip
        sample_at_pixels((images * 255).to(torch.uint8), points)
    gray_u8 = to_gray((images * 255).to(torch.uint8))
    with pytest.raises(TypeError, match="gray must be a floating-point tensor, got dtype torch.uint8"):
        image_with_gradients(gray_u8)
    with pytest.raises(ValueError, match=r"points_px must have shape \(\.\.\., 2\)"):
        pixels_to_grid(torch.zeros(1, 3, 3), 8, 10)
    with pytest.raises(ValueError, match="height must be an int >= 1, got 0"):
        pixels_to_grid(points, 0, 10)
    with pytest.raises(TypeError, match="width must be an int >= 1, got float 10.5"):
        pixels_to_grid(points, 8, 10.5)
    # the checked function gives what sample_at_pixels uses
    want = torch.tensor([[[-1 + 2 / 9, -1 + 4 / 7]]], dtype=D)
    torch.testing.assert_close(pixels_to_grid(points, 8, 10), want)
