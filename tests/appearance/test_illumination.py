"""Tests for torchface.appearance.illumination: basis layout, apply/remove round trip, Lambertian known answer."""

from __future__ import annotations

import pytest
import torch

from torchface.appearance import (
    ILLUMINATION_TERM_NAMES,
    NUM_ILLUMINATION_TERMS,
    apply_illumination,
    illumination_basis,
    remove_illumination,
)

D = torch.float64


def _normals(b: int, n: int, gen: torch.Generator) -> torch.Tensor:
    """Unit normals roughly facing the camera (``n_z < 0``), spread over a hemisphere cap."""
    v = torch.randn(b, n, 3, generator=gen, dtype=D) * 0.5
    v[..., 2] = -1.0
    return torch.nn.functional.normalize(v, dim=-1)


def test_basis_shape_and_columns():
    gen = torch.Generator().manual_seed(0)
    tpl = torch.rand(2, 7, generator=gen, dtype=D)
    n = _normals(2, 7, gen)
    basis = illumination_basis(tpl, n)
    assert basis.shape == (2, 7, NUM_ILLUMINATION_TERMS) and NUM_ILLUMINATION_TERMS == 5
    assert ILLUMINATION_TERM_NAMES == ("gain", "bias", "light_x", "light_y", "light_z")
    torch.testing.assert_close(basis[..., 0], tpl)
    torch.testing.assert_close(basis[..., 1], torch.ones_like(tpl))
    torch.testing.assert_close(basis[..., 2:], tpl.unsqueeze(-1) * n)
    # out=: the same values written into a given tensor, here a point-last buffer's transpose, and returned as it
    buffer = torch.full((2, NUM_ILLUMINATION_TERMS, 7), float("nan"), dtype=D)
    written = illumination_basis(tpl, n, out=buffer.transpose(1, 2))
    assert written.data_ptr() == buffer.data_ptr() and torch.equal(written, basis)
    with pytest.raises(ValueError, match=r"out must be \(B, N, 5\) = \(2, 7, 5\) torch.float64 on cpu, "
                                         r"got \(2, 5, 7\)"):  # fmt: skip
        illumination_basis(tpl, n, out=buffer)


def test_zero_params_reproduce_the_template():
    gen = torch.Generator().manual_seed(1)
    tpl = torch.rand(3, 11, generator=gen, dtype=D)
    basis = illumination_basis(tpl, _normals(3, 11, gen))
    out = apply_illumination(tpl, basis, torch.zeros(3, 5, dtype=D))
    torch.testing.assert_close(out, tpl, rtol=0, atol=0)


def test_apply_is_linear_in_params():
    gen = torch.Generator().manual_seed(2)
    tpl = torch.rand(2, 9, generator=gen, dtype=D)
    basis = illumination_basis(tpl, _normals(2, 9, gen))
    p, q = torch.randn(2, 5, generator=gen, dtype=D), torch.randn(2, 5, generator=gen, dtype=D)
    lhs = apply_illumination(tpl, basis, p + q) - tpl
    rhs = (apply_illumination(tpl, basis, p) - tpl) + (apply_illumination(tpl, basis, q) - tpl)
    torch.testing.assert_close(lhs, rhs)


def test_lambertian_known_answer():
    """Reference frame lit by ambient ``a0`` only: ``T = rho a0``. New light: ambient ``a1`` plus a distant light
    ``s l`` (no shadow) plus a camera offset ``b``: ``I = rho (a1 + s n.l) + b``. That is exactly the model with
    ``gain = a1 / a0 - 1``, ``bias = b``, ``(lx, ly, lz) = s l / a0``."""
    gen = torch.Generator().manual_seed(3)
    B, N = 2, 50
    rho = 0.2 + 0.7 * torch.rand(B, N, generator=gen, dtype=D)
    n = _normals(B, N, gen)
    a0 = torch.tensor([0.6, 0.8], dtype=D)
    a1 = torch.tensor([0.3, 0.9], dtype=D)
    s = torch.tensor([0.5, 0.2], dtype=D)
    light = torch.nn.functional.normalize(torch.tensor([[-0.3, -0.2, -1.0], [0.4, 0.1, -1.0]], dtype=D), dim=-1)
    bias = torch.tensor([0.05, -0.02], dtype=D)
    ndotl = (n * light.unsqueeze(1)).sum(-1)
    assert bool((ndotl > 0).all()), "the known answer needs every point lit (no attached shadow)"
    tpl = rho * a0[:, None]
    observed = rho * (a1[:, None] + s[:, None] * ndotl) + bias[:, None]
    params = torch.cat([(a1 / a0 - 1)[:, None], bias[:, None], s[:, None] * light / a0[:, None]], dim=1)
    predicted = apply_illumination(tpl, illumination_basis(tpl, n), params)
    torch.testing.assert_close(predicted, observed, rtol=0, atol=1e-12)
    torch.testing.assert_close(remove_illumination(observed, n, params), tpl, rtol=0, atol=1e-12)


def test_remove_inverts_apply_random_and_channels():
    gen = torch.Generator().manual_seed(4)
    tpl = torch.rand(2, 20, generator=gen, dtype=D)
    n = _normals(2, 20, gen)
    params = 0.2 * torch.randn(2, 5, generator=gen, dtype=D)
    observed = apply_illumination(tpl, illumination_basis(tpl, n), params)
    torch.testing.assert_close(remove_illumination(observed, n, params), tpl)
    # (B, C, N) observations: each channel undone with the same gain and bias
    colour = torch.rand(2, 3, 20, generator=gen, dtype=D)
    gain = 1 + params[:, 0:1] + torch.einsum("bnk,bk->bn", n, params[:, 2:5])
    observed_c = colour * gain.unsqueeze(1) + params[:, 1].view(2, 1, 1)
    torch.testing.assert_close(remove_illumination(observed_c, n, params), colour)


def test_remove_is_finite_when_gain_vanishes():
    n = torch.tensor([[[0.0, 0.0, -1.0]]], dtype=D)
    params = torch.tensor([[-1.0, 0.0, 0.0, 0.0, 0.0]], dtype=D)  # gain 1 + g = 0
    out = remove_illumination(torch.tensor([[0.5]], dtype=D), n, params, min_gain=0.05)
    torch.testing.assert_close(out, torch.tensor([[10.0]], dtype=D))


@pytest.mark.parametrize("min_gain", [0.0, -0.05, float("nan"), float("inf")])
def test_remove_refuses_a_floor_that_is_not_positive(min_gain):
    """The floor is what keeps the result finite: 0 gave inf (NaN for a zero numerator) at a vanishing gain, NaN
    gave NaN everywhere; now a clear error."""
    n = torch.tensor([[[0.0, 0.0, -1.0]]], dtype=D)
    params = torch.tensor([[-1.0, 0.0, 0.0, 0.0, 0.0]], dtype=D)  # gain 1 + (-1) = 0
    with pytest.raises(ValueError, match="min_gain must be a finite number > 0"):
        remove_illumination(torch.tensor([[0.5]], dtype=D), n, params, min_gain=min_gain)


@pytest.mark.parametrize("min_gain", ["0.05", None, True])
def test_remove_refuses_a_floor_that_is_not_a_number(min_gain):
    """check_number's rule: "0.05" was taken (float() of it), None was float()'s TypeError; now a TypeError naming
    min_gain."""
    n = torch.tensor([[[0.0, 0.0, -1.0]]], dtype=D)
    with pytest.raises(TypeError, match="min_gain must be a real number"):
        remove_illumination(torch.tensor([[0.5]], dtype=D), n, torch.zeros(1, 5, dtype=D), min_gain=min_gain)


def test_illumination_mixed_dtypes_are_promoted_and_non_tensors_named():
    """apply_illumination and remove_illumination raised einsum's "expected scalar type Double but found Float" on
    float32 against float64 (the geometry functions promote); illumination_basis met a numpy array with "no
    attribute 'dim'", and wrote into an ``out`` of another dtype (rounded), where to_gray's and pyr_down's refuse."""
    g = torch.Generator().manual_seed(3)
    template, normals = torch.rand(2, 4, dtype=D, generator=g), torch.randn(2, 4, 3, dtype=D, generator=g)
    basis = illumination_basis(template, normals)
    params = torch.randn(2, 5, dtype=D, generator=g) * 0.1
    got = apply_illumination(template.float(), basis, params.float())
    assert got.dtype == D
    torch.testing.assert_close(got, apply_illumination(template.float().double(), basis, params.float().double()),
                               rtol=0, atol=0)  # fmt: skip
    got = remove_illumination(template.float(), normals, params)
    assert got.dtype == D
    torch.testing.assert_close(got, remove_illumination(template.float().double(), normals, params), rtol=0, atol=0)
    with pytest.raises(TypeError, match="template must be a floating-point torch.Tensor, got ndarray"):
        illumination_basis(template.numpy(), normals)
    with pytest.raises(TypeError, match="normals_cam must be a floating-point torch.Tensor, got dtype torch.int64"):
        illumination_basis(template, normals.long())
    with pytest.raises(ValueError, match=r"out must be \(B, N, 5\) = \(2, 4, 5\) torch.float64 on cpu, got .*32"):
        illumination_basis(template, normals, out=torch.empty(2, 4, 5))
    out = torch.empty(2, 4, 5, dtype=D)
    assert illumination_basis(template, normals, out=out) is out
    torch.testing.assert_close(out, basis, rtol=0, atol=0)


def test_gradcheck_apply():
    gen = torch.Generator().manual_seed(5)
    tpl = torch.rand(1, 4, generator=gen, dtype=D, requires_grad=True)
    n = _normals(1, 4, gen).requires_grad_()
    params = torch.randn(1, 5, generator=gen, dtype=D, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t, nn, p: apply_illumination(t, illumination_basis(t, nn), p), (tpl, n, params))


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"\(B, N\)"):
        illumination_basis(torch.rand(5), torch.rand(5, 3))
    with pytest.raises(ValueError, match=r"\(B, N, 3\)"):
        illumination_basis(torch.rand(1, 5), torch.rand(1, 4, 3))


def test_apply_and_remove_illumination_name_bad_shapes_and_types():
    """Params or batches that do not match were einsum's RuntimeError ("subscript l has size 4 for operand 1 which
    does not broadcast with previously seen size 5"); six light terms were taken, the sixth ignored."""
    from torchface.appearance import apply_illumination, remove_illumination

    T, normals = torch.rand(2, 7), torch.nn.functional.normalize(torch.rand(2, 7, 3), dim=-1)
    basis = illumination_basis(T, normals)
    for params in (torch.rand(2, 4), torch.rand(3, 5), torch.rand(5)):
        with pytest.raises(ValueError, match=r"template must be \(B, N\), basis \(B, N, L\) and params \(B, L\)"):
            apply_illumination(T, basis, params)
    for observed, params in ((T, torch.rand(3, 5)), (T, torch.rand(2, 6)), (T[:, :6], torch.rand(2, 5)),
                             (torch.rand(7), torch.rand(2, 5))):  # fmt: skip
        with pytest.raises(ValueError, match=r"observed must be \(B, N\) or \(B, C, N\)"):
            remove_illumination(observed, normals, params)
    with pytest.raises(TypeError, match="must be tensors, got ndarray"):
        apply_illumination(T.numpy(), basis, torch.rand(2, 5))  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="must be tensors"):
        remove_illumination(T, normals, torch.rand(2, 5).numpy())  # type: ignore[arg-type]
    light = torch.rand(2, 5) * 0.1
    assert remove_illumination(apply_illumination(T, basis, light), normals, light).shape == (2, 7)
    assert remove_illumination(T[:, None].expand(2, 3, 7), normals, light).shape == (2, 3, 7)
