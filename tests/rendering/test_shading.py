"""Tests for torchface.rendering.shading: texture look-up, Lambertian light, batching, validation."""

from __future__ import annotations

import math

import pytest
import torch

from torchface.geometry.camera import Intrinsics
from torchface.rendering.rasterizer import rasterize
from torchface.rendering.shading import (
    LightState,
    TexturedMesh,
    TexturedRenderer,
    interpolate_vertex_attributes,
    lambertian_irradiance,
    render,
    sample_texture,
)
from torchface.rendering.visibility import vertex_normals

CAM = Intrinsics.default(64, 48)


def _plane(depth: float = 500.0, half: float = 100.0, dtype: torch.dtype = torch.float32):
    """A square facing the camera (outward normal -z), uv spanning the texture."""
    v = torch.tensor(
        [[-half, -half, depth], [half, -half, depth], [half, half, depth], [-half, half, depth]], dtype=dtype
    )
    faces = torch.tensor([[0, 2, 1], [0, 3, 2]])
    uv = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=dtype)
    return v.unsqueeze(0), faces, uv


def _rotation_y(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def _no_lights(b: int, ambient: float = 1.0) -> LightState:
    return LightState.ambient_only(torch.full((b,), ambient))


# ----------------------------------------------------------------------------------------- smoke
def test_smoke_render_shapes():
    v, f, uv = _plane()
    n = vertex_normals(v, f)
    out = render(v, f, uv, torch.rand(3, 8, 8), n, _no_lights(1), CAM)
    image, mask, frags = out
    assert image.shape == (1, 3, 48, 64) and mask.shape == (1, 1, 48, 64)
    assert frags.pix_to_face.shape == (1, 48, 64)
    assert torch.isfinite(image).all() and image.min() >= 0 and image.max() <= 1


# ----------------------------------------------------------------------------------------- feature
def test_flat_texture_ambient_only_gives_albedo():
    v, f, uv = _plane()
    albedo = torch.tensor([0.2, 0.5, 0.7])
    tex = albedo.view(3, 1, 1).expand(3, 5, 7).contiguous()
    n = vertex_normals(v, f)
    bg = torch.full((1, 3, 48, 64), 0.9)
    for ambient in (1.0, 0.6):
        image, mask, _ = render(v, f, uv, tex, n, _no_lights(1, ambient), CAM, background=bg)
        inside = mask[0, 0] > 0
        assert inside.sum() > 100
        expected = (albedo * ambient).view(3, 1)
        torch.testing.assert_close(image[0][:, inside], expected.expand(3, int(inside.sum())), atol=1e-6, rtol=0)
        # Background pixels keep the background.
        torch.testing.assert_close(image[0][:, ~inside], torch.full((3, int((~inside).sum())), 0.9))


@pytest.mark.parametrize("tilt_deg, light_deg", [(0.0, 0.0), (30.0, 0.0), (30.0, -25.0), (-40.0, 60.0), (20.0, 70.0)])
def test_lambert_cosine_law_on_tilted_plane(tilt_deg, light_deg):
    v, f, uv = _plane()
    centre = torch.tensor([0.0, 0.0, 500.0])
    R = _rotation_y(tilt_deg)
    v = (v - centre) @ R.T + centre
    n = vertex_normals(v, f)
    normal = n[0, 0]
    d = _rotation_y(light_deg) @ torch.tensor([0.0, 0.0, -1.0])
    light = LightState(torch.tensor([0.1]), d.view(1, 1, 3), torch.tensor([[0.8]]))
    albedo = torch.tensor([0.9, 0.6, 0.3])
    tex = albedo.view(3, 1, 1).expand(3, 4, 4).contiguous()
    image, mask, _ = render(v, f, uv, tex, n, light, CAM)
    inside = mask[0, 0] > 0
    cosine = max(0.0, float(normal @ d))
    assert abs(cosine - max(0.0, math.cos(math.radians(tilt_deg - light_deg)))) < 1e-5
    expected = albedo * (0.1 + 0.8 * cosine)
    torch.testing.assert_close(image[0][:, inside], expected.view(3, 1).expand(3, int(inside.sum())), atol=1e-5, rtol=0)


def test_light_from_behind_gives_ambient_only():
    n = torch.tensor([[[0.0, 0.0, -1.0]]])
    light = LightState(torch.tensor([0.3]), torch.tensor([[[0.0, 0.0, 1.0]]]), torch.tensor([[5.0]]))
    torch.testing.assert_close(lambertian_irradiance(n, light), torch.tensor([[0.3]]))


def test_sample_texture_hits_texel_centres_and_edges():
    tex = torch.rand(3, 5, 7, dtype=torch.float64)
    i, j = torch.meshgrid(torch.arange(5), torch.arange(7), indexing="ij")
    uv = torch.stack([(j + 0.5) / 7, (i + 0.5) / 5], dim=-1).to(torch.float64).unsqueeze(0)
    torch.testing.assert_close(sample_texture(tex, uv)[0], tex, atol=1e-6, rtol=0)
    # Corner (0, 0) is the outer edge of the top-left texel: border padding returns that texel.
    corner = sample_texture(tex, torch.zeros(1, 1, 1, 2, dtype=torch.float64))
    torch.testing.assert_close(corner[0, :, 0, 0], tex[:, 0, 0])


def test_texture_orientation_top_left():
    """Texture top-left lands on the image top-left of a frontal plane with uv (0, 0) at its top-left corner."""
    v, f, uv = _plane()
    tex = torch.zeros(3, 2, 2)
    tex[0, 0, 0] = 1.0  # red top-left
    tex[2, 1, 1] = 1.0  # blue bottom-right
    n = vertex_normals(v, f)
    image, mask, _ = render(v, f, uv, tex, n, _no_lights(1), CAM)
    ys, xs = torch.nonzero(mask[0, 0] > 0, as_tuple=True)
    tl = image[0, :, ys.min() + 1, xs.min() + 1]
    br = image[0, :, ys.max() - 1, xs.max() - 1]
    assert tl[0] > 0.8 and tl[2] < 0.2
    assert br[2] > 0.8 and br[0] < 0.2


def test_interpolation_matches_per_pixel_reference():
    torch.manual_seed(0)
    v, f, uv = _plane()
    v = v + torch.randn(1, 4, 3) * torch.tensor([5.0, 5.0, 20.0])
    frags = rasterize(v, f, CAM)
    attrs = torch.randn(1, 4, 2)
    fast = interpolate_vertex_attributes(frags, f, attrs)
    slow = torch.zeros_like(fast)
    for y in range(CAM.height):
        for x in range(CAM.width):
            face = int(frags.pix_to_face[0, y, x])
            if face < 0:
                continue
            corners = attrs[0, f[face]]
            slow[0, y, x] = (frags.bary[0, y, x].unsqueeze(-1) * corners).sum(0)
    torch.testing.assert_close(fast, slow)


def test_batched_equals_per_sample():
    torch.manual_seed(1)
    v, f, uv = _plane()
    b = 3
    angles = [0.0, 25.0, -35.0]
    centre = torch.tensor([0.0, 0.0, 500.0])
    verts = torch.cat([(v - centre) @ _rotation_y(a).T + centre + torch.tensor([10.0 * i, -5.0, 0]) for i, a in enumerate(angles)])
    normals = vertex_normals(verts, f)
    tex = torch.rand(b, 3, 6, 6)
    dirs = torch.nn.functional.normalize(torch.randn(b, 2, 3) - torch.tensor([0.0, 0.0, 2.0]), dim=-1)
    light = LightState(torch.rand(b) * 0.5, dirs, torch.rand(b, 2))
    bg = torch.rand(b, 3, 48, 64)
    image, mask, _ = render(verts, f, uv, tex, normals, light, CAM, background=bg)
    for i in range(b):
        img_i, mask_i, _ = render(
            verts[i : i + 1], f, uv, tex[i], normals[i : i + 1], light.select(i), CAM, background=bg[i : i + 1]
        )
        torch.testing.assert_close(image[i : i + 1], img_i)
        torch.testing.assert_close(mask[i : i + 1], mask_i)


def test_module_matches_function():
    v, f, uv = _plane()
    tex = torch.rand(3, 4, 4)
    n = vertex_normals(v, f)
    light = _no_lights(1, 0.7)
    renderer = TexturedRenderer(f, uv, tex, CAM)
    torch.testing.assert_close(renderer(v, n, light).image, render(v, f, uv, tex, n, light, CAM).image)


# ----------------------------------------------------------------------------------------- gradcheck
def test_gradcheck_irradiance_and_texture_sampling():
    torch.manual_seed(2)
    amb = torch.rand(2, dtype=torch.float64, requires_grad=True)
    # Normals and lights facing each other, well away from grazing, so the max(0, .) kink is not crossed.
    dirs = torch.tensor([[[0.0, 0.0, -1.0]], [[0.3, -0.2, -1.0]]], dtype=torch.float64)
    inten = torch.rand(2, 1, dtype=torch.float64, requires_grad=True)
    raw = torch.randn(2, 5, 3, dtype=torch.float64) * torch.tensor([0.2, 0.2, 1.0], dtype=torch.float64)
    raw[..., 2] = -raw[..., 2].abs() - 0.5
    n_front = torch.nn.functional.normalize(raw, dim=-1).requires_grad_()
    torch.autograd.gradcheck(
        lambda nn_, a, s: lambertian_irradiance(nn_, LightState(a, dirs, s)), (n_front, amb, inten)
    )
    tex = torch.rand(3, 4, 5, dtype=torch.float64, requires_grad=True)
    uv = (torch.rand(1, 3, 3, 2, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    torch.autograd.gradcheck(sample_texture, (tex, uv))


def test_render_backpropagates_to_vertices_and_light():
    v, f, uv = _plane(dtype=torch.float64)
    v = v.clone().requires_grad_()
    tex = torch.rand(3, 4, 4, dtype=torch.float64)
    n = vertex_normals(v, f)
    amb = torch.tensor([0.5], dtype=torch.float64, requires_grad=True)
    light = LightState(amb, torch.tensor([[[0.0, 0.0, -1.0]]], dtype=torch.float64), torch.tensor([[0.3]], dtype=torch.float64))
    image, _, _ = render(v, f, uv, tex, n, light, CAM)
    image.sum().backward()
    assert torch.isfinite(v.grad).all() and v.grad.abs().sum() > 0
    assert amb.grad is not None and amb.grad.item() > 0


# ----------------------------------------------------------------------------------------- exception
def test_validation_errors():
    with pytest.raises(ValueError, match="directions"):
        LightState(torch.ones(2), torch.zeros(3, 1, 3), torch.zeros(2, 1))
    with pytest.raises(TypeError, match="ambient"):
        LightState([1.0], torch.zeros(1, 1, 3), torch.zeros(1, 1))
    with pytest.raises(ValueError, match="texture"):
        TexturedMesh(torch.zeros(3, 3), torch.tensor([[0, 1, 2]]), torch.zeros(3, 2), torch.zeros(4, 2, 2))
    with pytest.raises(ValueError, match="outside"):
        TexturedMesh(torch.zeros(3, 3), torch.tensor([[0, 1, 3]]), torch.zeros(3, 2), torch.zeros(3, 2, 2))
    v, f, uv = _plane()
    n = vertex_normals(v, f)
    with pytest.raises(ValueError, match="light batch"):
        render(v, f, uv, torch.rand(3, 2, 2), n, _no_lights(2), CAM)
    with pytest.raises(ValueError, match="background"):
        render(v, f, uv, torch.rand(3, 2, 2), n, _no_lights(1), CAM, background=torch.zeros(1, 3, 10, 10))
    with pytest.raises(ValueError, match="normals_cam"):
        render(v, f, uv, torch.rand(3, 2, 2), n[:, :2], _no_lights(1), CAM)


def test_render_names_each_bad_argument():
    """render checked its vertices, normals, light size and background alone: a uv of another V was torch.cat's
    "Sizes of tensors must match", a (V, 3) uv a message about normals (B, H, W, 4), a numpy uv or texture "no
    attribute", a light or camera of another type "no attribute 'batch_size'" / "'height'", a uint8 texture was
    taken as 0-255 albedo (every pixel clamped to white), cull_backfaces="no" culled, a tensor on another device
    was torch's own error from inside, and B = 0 failed in a reshape."""
    v, f, uv = _plane()
    n = vertex_normals(v, f)
    tex = torch.rand(3, 2, 2)
    light = _no_lights(1)
    with pytest.raises(ValueError, match=r"uv must be \(V, 2\) or \(B, V, 2\) with V=4 and B=1 like verts_cam, "
                                         r"got \(3, 2\)"):  # fmt: skip
        render(v, f, uv[:3], tex, n, light, CAM)
    with pytest.raises(ValueError, match=r"uv must be .* got \(4, 3\)"):
        render(v, f, torch.rand(4, 3), tex, n, light, CAM)
    with pytest.raises(ValueError, match=r"uv must be .* got \(3, 4, 2\)"):
        render(v, f, uv.expand(3, -1, -1), tex, n, light, CAM)
    with pytest.raises(TypeError, match="uv must be a torch.Tensor, got ndarray"):
        render(v, f, uv.numpy(), tex, n, light, CAM)
    with pytest.raises(TypeError, match="texture must be a torch.Tensor, got ndarray"):
        render(v, f, uv, tex.numpy(), n, light, CAM)
    with pytest.raises(ValueError, match=r"texture must be \(3, Ht, Wt\) or \(B, 3, Ht, Wt\), got \(2, 2\)"):
        render(v, f, uv, tex[0], n, light, CAM)
    with pytest.raises(TypeError, match=r"texture must be a floating-point tensor, got torch.uint8 \(uint8: "):
        render(v, f, uv, (tex * 255).to(torch.uint8), n, light, CAM)
    with pytest.raises(TypeError, match="light must be a LightState, got str"):
        render(v, f, uv, tex, n, "ambient", CAM)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="intrinsics must be torchface.geometry.Intrinsics, got NoneType"):
        render(v, f, uv, tex, n, light, None)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="cull_backfaces must be a bool, got str 'no'"):
        render(v, f, uv, tex, n, light, CAM, cull_backfaces="no")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="texture must be on verts_cam's device cpu, got meta"):
        render(v, f, uv, tex.to("meta"), n, light, CAM)
    with pytest.raises(ValueError, match="light must be on verts_cam's device cpu, got meta"):
        meta_light = LightState(*(x.to("meta") for x in (light.ambient, light.directions, light.intensities)))
        render(v, f, uv, tex, n, meta_light, CAM)
    image, mask, _ = render(v[:0], f, uv, tex, n[:0], _no_lights(0), CAM)
    assert image.shape == (0, 3, 48, 64) and mask.shape == (0, 1, 48, 64)


def test_render_gradients_reach_every_input_but_the_mask():
    """render's gradients, documented in its docstring: the image is differentiable with respect to the vertices,
    normals, texture coordinates, texture, light and background; the mask is not."""
    D = torch.float64
    v, f, uv = _plane(dtype=D)
    n = vertex_normals(v, f)
    light = LightState(torch.tensor([0.4], dtype=D), torch.tensor([[[0.3, 0.0, -1.0]]], dtype=D),
                       torch.tensor([[0.5]], dtype=D))  # fmt: skip
    tex = torch.rand(3, 4, 4, dtype=D, generator=torch.Generator().manual_seed(0)) * 0.5
    inputs = [x.clone().requires_grad_() for x in (v, n, uv, tex, light.ambient, light.directions, light.intensities,
                                                   torch.rand(1, 3, 48, 64, dtype=D))]  # fmt: skip
    vv, nn, uu, tt, amb, dirs, inten, bg = inputs
    image, mask, frags = render(vv, f, uu, tt, nn, LightState(amb, dirs, inten), CAM, background=bg)
    assert not mask.requires_grad and not frags.pix_to_face.requires_grad
    weights = torch.rand(image.shape, dtype=D, generator=torch.Generator().manual_seed(1))
    grads = torch.autograd.grad((image * weights).sum(), inputs)
    for name, g in zip(("verts_cam", "normals_cam", "uv", "texture", "ambient", "directions", "intensities",
                        "background"), grads):  # fmt: skip
        assert torch.isfinite(g).all() and g.abs().sum() > 0, name
