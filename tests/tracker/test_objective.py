"""Tests for torchface.tracker.objective: the analytic Jacobian of Eq. 20 against autograd, residual values
against an independent implementation, and the validity mask.

The image is given as analytic channels ``[I, dI/du, dI/dv]``. Two images are used:

* a *bilinear* image ``I = c0 + a u + b v + c u v``: bilinear sampling reproduces it exactly and its gradient
  channels are exact everywhere, so the analytic Jacobian must equal autograd through ``frame_residuals``
  itself (through ``grid_sample``) to round-off;
* a smooth ``sin``/``cos`` pattern, evaluated analytically by an independent reference residual (matrix
  exponential, own projection); the analytic Jacobian (which bilinearly interpolates the gradient channels)
  must match autograd of the reference up to the interpolation error of a slowly varying gradient.
"""

from __future__ import annotations

import platform

import pytest
import torch

from torchface.appearance import illumination_basis
from torchface.geometry.camera import Intrinsics
from torchface.template import Template
from torchface.tracker import ParamLayout, frame_residuals, warp_points

D = torch.float64
A = 4
LAYOUT = ParamLayout(A, 5)
CAM = Intrinsics.default(160, 120)
GROUPS = {"rotation": LAYOUT.rotation, "translation": LAYOUT.translation, "expression": LAYOUT.animation,
          "illumination": LAYOUT.illumination}


def make_template(B: int = 2, N: int = 40, seed: int = 0) -> Template:
    """A small synthetic template: points on a bumpy patch facing the camera, random expression basis."""
    gen = torch.Generator().manual_seed(seed)
    xy = (torch.rand(B, N, 2, generator=gen, dtype=D) - 0.5) * 80.0
    z = 8.0 * torch.sin(xy[..., :1] / 20.0) * torch.cos(xy[..., 1:] / 25.0)
    points = torch.cat([xy, z], -1)
    normals = torch.nn.functional.normalize(
        torch.cat([0.2 * torch.randn(B, N, 2, generator=gen, dtype=D), -torch.ones(B, N, 1, dtype=D)], -1), dim=-1
    )
    basis = 4.0 * torch.randn(B, N, 3, A, generator=gen, dtype=D)
    intensity = 0.2 + 0.6 * torch.rand(B, N, generator=gen, dtype=D)
    bary = torch.softmax(torch.randn(B, N, 3, generator=gen, dtype=D), -1)
    face_index = torch.randint(0, 10, (B, N), generator=gen)
    return Template(face_index, bary, points, basis, normals, intensity, torch.ones(B, N, dtype=torch.bool))


def params(kind: str, B: int = 2) -> torch.Tensor:
    """Packed ``(B, P)`` parameters: identity rotation / neutral / reference light, or a general state."""
    x = torch.zeros(B, LAYOUT.size, dtype=D)
    x[:, LAYOUT.translation] = torch.tensor([[4.0, -3.0, 420.0], [-6.0, 2.0, 380.0]], dtype=D)[:B]
    if kind == "nonzero":
        x[:, LAYOUT.rotation] = torch.tensor([[0.12, -0.2, 0.07], [-0.25, 0.1, -0.15]], dtype=D)[:B]
        x[:, LAYOUT.animation] = torch.tensor([[0.3, -0.2, 0.5, 0.1], [-0.4, 0.25, 0.0, 0.35]], dtype=D)[:B]
        x[:, LAYOUT.illumination] = torch.tensor(
            [[0.1, -0.05, 0.2, -0.1, 0.05], [-0.2, 0.03, -0.1, 0.15, 0.1]], dtype=D
        )[:B]
    return x


def bilinear_image(B: int = 2) -> torch.Tensor:
    """``(B, 3, H, W)`` channels of ``I = c0 + a u + b v + c u v`` and its exact derivatives."""
    vv, uu = torch.meshgrid(torch.arange(CAM.height, dtype=D), torch.arange(CAM.width, dtype=D), indexing="ij")
    coef = torch.tensor([[0.3, 2e-3, -1.5e-3, 4e-5], [0.6, -1e-3, 3e-3, -6e-5]], dtype=D)[:B].view(B, 4, 1, 1)
    c0, a, b, c = coef.unbind(1)
    img = c0 + a * uu + b * vv + c * uu * vv
    return torch.stack([img, (a + c * vv).expand_as(img), (b + c * uu).expand_as(img)], 1)


def smooth_intensity(uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``I(u, v) = 0.5 + 0.2 sin(u / 9 + 0.3) cos(v / 11 - 0.2)`` and its exact partial derivatives."""
    u, v = uv[..., 0], uv[..., 1]
    su, cu = torch.sin(u / 9.0 + 0.3), torch.cos(u / 9.0 + 0.3)
    sv, cv = torch.sin(v / 11.0 - 0.2), torch.cos(v / 11.0 - 0.2)
    return 0.5 + 0.2 * su * cv, 0.2 / 9.0 * cu * cv, -0.2 / 11.0 * su * sv


def smooth_image(B: int = 2) -> torch.Tensor:
    vv, uu = torch.meshgrid(torch.arange(CAM.height, dtype=D), torch.arange(CAM.width, dtype=D), indexing="ij")
    i, du, dv = smooth_intensity(torch.stack([uu, vv], -1))
    return torch.stack([i, du, dv], 0).unsqueeze(0).expand(B, -1, -1, -1).contiguous()


def rotation_reference(w: torch.Tensor) -> torch.Tensor:
    """Independent exponential map ``(B, 3) -> (B, 3, 3)``: ``torch.linalg.matrix_exp`` of the skew matrix."""
    K = torch.zeros(w.shape[0], 3, 3, dtype=w.dtype)
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 0] = -w[:, 2], w[:, 1], w[:, 2]
    K[:, 1, 2], K[:, 2, 0], K[:, 2, 1] = -w[:, 0], -w[:, 1], w[:, 0]
    return torch.linalg.matrix_exp(K)


def reference_residual(x: torch.Tensor, tpl: Template, light_basis: torch.Tensor) -> torch.Tensor:
    """Eq. 20 written out independently with the analytic smooth image: ``I(pi(R X(alpha) + t)) - T - B lambda``."""
    w, t = x[:, 0:3], x[:, 3:6]
    alpha, lam = x[:, 6 : 6 + A], x[:, 6 + A :]
    X = tpl.points + torch.einsum("bnka,ba->bnk", tpl.basis, alpha)
    R = rotation_reference(w)
    Xc = torch.einsum("bij,bnj->bni", R, X) + t[:, None]
    uv = torch.stack([CAM.fx * Xc[..., 0] / Xc[..., 2] + CAM.cx, CAM.fy * Xc[..., 1] / Xc[..., 2] + CAM.cy], -1)
    return smooth_intensity(uv)[0] - tpl.intensity - torch.einsum("bnl,bl->bn", light_basis, lam)


def _light_basis(tpl: Template, x: torch.Tensor) -> torch.Tensor:
    _, _, R = warp_points(tpl, LAYOUT, x)
    return illumination_basis(tpl.intensity, tpl.normals @ R.transpose(1, 2))


def _autograd_jacobian(fn, x: torch.Tensor) -> torch.Tensor:
    """``(B, N, P)`` per-sample Jacobian of a batched residual ``(B, P) -> (B, N)``."""
    full = torch.autograd.functional.jacobian(fn, x, vectorize=True)  # (B, N, B, P)
    return torch.stack([full[b, :, b] for b in range(x.shape[0])])


@pytest.mark.parametrize("kind", ["zero", "nonzero"])
def test_jacobian_equals_autograd_bilinear_image(kind):
    """Exact agreement, column group by column group, including zero rotation (the exp map's singular point)."""
    tpl, x, image = make_template(), params(kind), bilinear_image()
    light_basis = _light_basis(tpl, params("nonzero"))
    mask = tpl.valid

    def fn(p):
        return frame_residuals(p, LAYOUT, tpl, image, CAM, light_basis, mask)[0]

    r, J, valid = frame_residuals(x, LAYOUT, tpl, image, CAM, light_basis, mask)
    assert r.shape == (2, 40) and J.shape == (2, 40, LAYOUT.size) and valid.shape == (2, 40)
    assert bool(valid.all()), "the synthetic template should be fully visible"
    J_auto = _autograd_jacobian(fn, x)
    for name, cols in GROUPS.items():
        scale = J_auto[..., cols].abs().max()
        assert scale > 0, f"{name} columns vanish: the test would be vacuous"
        torch.testing.assert_close(J[..., cols], J_auto[..., cols], rtol=1e-9, atol=1e-12 * float(scale),
                                   msg=lambda m, name=name: f"{name} columns: {m}")


@pytest.mark.parametrize("kind", ["zero", "nonzero"])
def test_jacobian_and_residual_against_independent_reference_smooth_image(kind):
    tpl, x, image = make_template(seed=1), params(kind), smooth_image()
    light_basis = _light_basis(tpl, params("nonzero"))
    r, J, valid = frame_residuals(x, LAYOUT, tpl, image, CAM, light_basis, tpl.valid)
    assert bool(valid.all())
    # residual values: bilinear interpolation error <= (|I_uu| + |I_vv|) / 8 ~ 5e-4 for this pattern
    torch.testing.assert_close(r, reference_residual(x, tpl, light_basis), rtol=0, atol=1e-3)
    J_ref = _autograd_jacobian(lambda p: reference_residual(p, tpl, light_basis), x)
    for name, cols in GROUPS.items():
        scale = float(J_ref[..., cols].abs().max())
        # interpolated gradient channels: error <= h^2/8 |grad I''| ~ 4e-5 against |grad I| ~ 2e-2
        torch.testing.assert_close(J[..., cols], J_ref[..., cols], rtol=0, atol=1e-2 * scale,
                                   msg=lambda m, name=name: f"{name} columns: {m}")
        # and not by accident: the typical error is far below the tolerance
        assert float((J[..., cols] - J_ref[..., cols]).abs().mean()) < 2e-3 * scale


def test_light_columns_are_minus_the_basis():
    tpl, x, image = make_template(), params("nonzero"), bilinear_image()
    light_basis = _light_basis(tpl, x)
    _, J, _ = frame_residuals(x, LAYOUT, tpl, image, CAM, light_basis, tpl.valid)
    torch.testing.assert_close(J[..., LAYOUT.illumination], -light_basis, rtol=0, atol=0)


def test_rotation_jacobian_matches_finite_differences_near_zero():
    """Central differences straddling ``w = 0`` agree with the analytic rotation columns at 0."""
    tpl, image = make_template(), bilinear_image()
    x = params("zero")
    light_basis = _light_basis(tpl, x)
    _, J, _ = frame_residuals(x, LAYOUT, tpl, image, CAM, light_basis, tpl.valid)
    h = 1e-6
    for j in range(3):
        e = torch.zeros_like(x)
        e[:, j] = h
        rp = frame_residuals(x + e, LAYOUT, tpl, image, CAM, light_basis, tpl.valid)[0]
        rm = frame_residuals(x - e, LAYOUT, tpl, image, CAM, light_basis, tpl.valid)[0]
        torch.testing.assert_close(J[..., j], (rp - rm) / (2 * h), rtol=1e-5, atol=1e-8)


def test_warp_points_matches_independent_formula():
    tpl, x = make_template(), params("nonzero")
    pm, pc, R = warp_points(tpl, LAYOUT, x)
    X = tpl.points + torch.einsum("bnka,ba->bnk", tpl.basis, x[:, LAYOUT.animation])
    torch.testing.assert_close(pm, X)
    torch.testing.assert_close(R, rotation_reference(x[:, :3]))
    torch.testing.assert_close(pc, torch.einsum("bij,bnj->bni", R, X) + x[:, None, 3:6])


def _as_the_matmul(a: torch.Tensor, b: torch.Tensor, scale: torch.Tensor) -> bool:
    """``a`` equals the matmul's ``b`` bit for bit on x86-64 (measured: torch 2.5.1, 2.11 and 2.13, whose small-matrix
    kernel there sums without fused multiply-adds); elsewhere (an ARM build may fuse them) within 16 roundings of
    ``scale``, the sum of the products' magnitudes."""
    if platform.machine().lower() in ("x86_64", "amd64"):
        return torch.equal(a, b)
    return bool(((a - b).abs() <= 16 * torch.finfo(a.dtype).eps * scale).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_warp_points_expression_loop_equals_the_broadcast_matmul(dtype, monkeypatch):
    """The chunked loop over the point-last basis (many streams' points, no gradient) gives the broadcast matmul's
    values bit for bit: the same products summed in the same order with the same roundings (a fused multiply-add,
    or a reduction in another order, changes the last bit of some of these sums). Chunks of two streams here
    (the last one shorter); where a gradient is asked for, the matmul runs itself (None). ``out=`` takes
    ``points_cam`` into a view of a larger tensor (the visibility test's points of every level), the same values."""
    import torchface.tracker.objective as objective

    monkeypatch.setattr(objective, "_OFFSET_LOOP_MIN_POINTS", 0)
    monkeypatch.setattr(objective, "_OFFSET_CHUNK_VALUES", 2 * 3 * 50)
    gen = torch.Generator().manual_seed(3)
    B, N, A11 = 5, 50, 11
    layout = ParamLayout(A11, 5)
    basis = (torch.randn(B, N, 3, A11, generator=gen, dtype=D) * 10.0 ** torch.randint(-3, 3, (B, N, 3, A11),
             generator=gen)).to(dtype)  # fmt: skip
    scale = torch.tensor([100.0, 1.0], dtype=D).view(2, 1, 1, 1)  # the points (mm) and the normals
    points, normals = (torch.randn(2, B, N, 3, generator=gen, dtype=D) * scale).to(dtype)
    intensity = torch.rand(B, N, generator=gen, dtype=D).to(dtype)
    tpl = Template(torch.zeros(B, N, dtype=torch.long), torch.full((B, N, 3), 1 / 3, dtype=dtype), points, basis,
                   normals, intensity, torch.ones(B, N, dtype=torch.bool))  # fmt: skip
    x = torch.randn(B, layout.size, generator=gen, dtype=D).to(dtype)
    x[:, 5] += 400.0
    alpha = x[:, layout.animation]
    offsets = objective._expression_offsets(tpl, alpha)
    assert offsets is not None and offsets.shape == (B, 3, N)
    magnitude = torch.matmul(tpl.basis.abs(), alpha.abs()[:, None, :, None]).squeeze(-1)
    assert _as_the_matmul(offsets.transpose(1, 2), torch.matmul(tpl.basis, alpha[:, None, :, None]).squeeze(-1),
                          magnitude)  # fmt: skip
    pm, pc, R = warp_points(tpl, layout, x)
    monkeypatch.setattr(objective, "_OFFSET_LOOP_MIN_POINTS", B * N + 1)  # the matmul
    pm0, pc0, R0 = warp_points(tpl, layout, x)
    assert _as_the_matmul(pm, pm0, tpl.points.abs() + magnitude) and torch.equal(R, R0)
    assert _as_the_matmul(pc, pc0, torch.matmul(tpl.points.abs() + magnitude, R.abs().transpose(1, 2)) + 400.0)
    into = torch.zeros(B, N + 7, 3, dtype=dtype)  # points_cam written into a view of a larger tensor
    pc1 = warp_points(tpl, layout, x, out=into[:, 3 : 3 + N])[1]
    assert torch.equal(pc1, pc) and torch.equal(into[:, 3 : 3 + N], pc) and not into[:, :3].any()
    assert objective._expression_offsets(tpl, alpha) is None
    monkeypatch.setattr(objective, "_OFFSET_LOOP_MIN_POINTS", 0)
    assert objective._expression_offsets(tpl, alpha.clone().requires_grad_()) is None
    # the matmul's cases: a tangent, a torch.func transform, half precision, one template broadcast over the streams
    import torch.autograd.forward_ad as fwAD

    with fwAD.dual_level():
        assert objective._expression_offsets(tpl, fwAD.make_dual(alpha, torch.ones_like(alpha))) is None
    seen = []
    torch.func.vmap(lambda a: seen.append(objective._expression_offsets(tpl, a[None])) or a)(alpha)
    assert seen == [None]
    half = Template(*(f.to(torch.bfloat16) if f.is_floating_point() else f for f in (tpl.face_index, tpl.bary,
                    tpl.points, tpl.basis, tpl.normals, tpl.intensity, tpl.valid)))  # fmt: skip
    assert objective._expression_offsets(half, alpha.to(torch.bfloat16)) is None
    one = Template(*(f[:1] for f in (tpl.face_index, tpl.bary, tpl.points, tpl.basis, tpl.normals, tpl.intensity,
                                      tpl.valid)))  # fmt: skip
    pc_one = warp_points(one, layout, x)[1]  # (the loop raised: alpha (5, A) is not the template's (1, A))
    assert torch.equal(pc_one, torch.matmul(one.points + torch.matmul(one.basis, alpha[:, None, :, None]).squeeze(-1),
                                            R.transpose(1, 2)) + x[:, None, 3:6])  # fmt: skip


def test_validity_mask():
    tpl, image = make_template(B=1, N=6), bilinear_image(B=1)
    x = params("zero", B=1)
    pts, normals = tpl.points.clone(), tpl.normals.clone()
    pts[0, 1] = torch.tensor([400.0, 0.0, 0.0], dtype=D)  # projects right of the image
    pts[0, 2] = torch.tensor([0.0, 0.0, -430.0], dtype=D)  # behind the camera (Z = -10 mm)
    normals[0, 3] = torch.tensor([0.0, 0.0, 1.0], dtype=D)  # faces away from the camera
    tpl = Template(tpl.face_index, tpl.bary, pts, tpl.basis, normals, tpl.intensity, tpl.valid)
    mask = torch.tensor([[True, True, True, True, False, True]])
    r, J, valid = frame_residuals(x, LAYOUT, tpl, image, CAM, _light_basis(tpl, x), mask)
    assert valid[0].tolist() == [True, False, False, False, False, True]
    assert bool(torch.isfinite(r).all() and torch.isfinite(J).all()), "invalid points must still be finite"
