"""Textured Lambertian shading of rasterized meshes (the appearance stage after the rasterizer).

The rasterizer (:func:`torchface.rendering.rasterizer.rasterize`) decides, once per pixel, which
triangle is nearest and where inside it the pixel centre lies (perspective-correct barycentrics).
This module consumes those :class:`~torchface.rendering.rasterizer.Fragments`: it interpolates
per-vertex texture coordinates and normals, samples the texture bilinearly and applies the
Lambertian light model

    ``colour(x) = albedo(x) * (a + sum_l s_l * max(0, n(x) . d_l))``

with ``a`` the ambient level, ``d_l`` unit directions in the CAMERA frame pointing from the surface
toward distant light ``l``, ``s_l`` their intensities and ``n(x)`` the barycentrically interpolated,
renormalised unit vertex normal in the camera frame. The colour is clamped to ``[0, 1]``.

This is the image formation that the tracker's illumination basis is built to model (Anisetti et
al. 2006, Eq. 10-11 and 19): for a Lambertian surface under distant lights the observed template
is ``T(x) + sum_i lambda_i B_i(x)`` with a gain term ``B_1 = T`` (a change of ``a``), a bias term
``B_2 = 1`` and normal-based directional terms ``B_3..B_5`` (``n . d`` against fixed directions:
any directional light is a linear combination of three independent ones while ``n . d_l > 0``).
Sequences rendered with this module therefore have an exact answer in the tracker's model family
except where a light grazes the surface (the ``max(0, .)`` clamp) or the colour saturates.

Texture coordinates (see :mod:`torchface.conventions` for the image side): ``uv[..., 0]`` runs
along the texture width and ``uv[..., 1]`` along its height, both in ``[0, 1]``, with ``(0, 0)``
the TOP-LEFT corner of the top-left texel and ``(1, 1)`` the bottom-right corner of the
bottom-right texel (so OBJ's bottom-up ``v`` must be flipped on load: ``v_img = 1 - v_obj``).
Sampling uses ``grid_sample`` with ``align_corners=False``, for which normalised ``-1`` and ``+1``
are exactly those outer texel edges: ``x_norm = 2 u - 1``, ``y_norm = 2 v - 1``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as nnf
from torch import Tensor, nn

from torchface._device import tensor_mover
from torchface.geometry._checks import check_bool, check_intrinsics
from torchface.geometry.camera import Intrinsics
from torchface.rendering.rasterizer import Fragments, rasterize

__all__ = [
    "LightState",
    "TexturedMesh",
    "RenderResult",
    "interpolate_vertex_attributes",
    "sample_texture",
    "lambertian_irradiance",
    "shade",
    "render",
    "TexturedRenderer",
]


def _check_tensor(name: str, x: object, ndim: int, last: int | None = None) -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim != ndim or (last is not None and x.shape[-1] != last):
        want = f"{ndim}-d" + (f" with last dimension {last}" if last is not None else "")
        raise ValueError(f"{name} must be {want}, got shape {tuple(x.shape)}")
    return x


@dataclass(frozen=True, eq=False)
class TexturedMesh:
    """A triangle mesh with per-vertex texture coordinates and an RGB texture image.

    Attributes:
        verts: ``(V, 3)`` float vertex positions in the model (head) frame, millimetres
            (see :mod:`torchface.conventions`).
        faces: ``(F, 3)`` int64 vertex indices, counter-clockwise seen from outside (outward normals).
        uv: ``(V, 2)`` float texture coordinates in ``[0, 1]`` (module docstring: ``(0, 0)`` is the
            top-left texture corner). Coordinates are per vertex, so texture seams must already be
            split into duplicated vertices.
        texture: ``(3, Ht, Wt)`` float RGB in ``[0, 1]``.

    Example:
        >>> mesh = TexturedMesh(torch.zeros(3, 3), torch.tensor([[0, 1, 2]]), torch.zeros(3, 2),
        ...                     torch.ones(3, 4, 4))
        >>> mesh.num_verts, mesh.num_faces
        (3, 1)
    """

    verts: Tensor
    faces: Tensor
    uv: Tensor
    texture: Tensor

    def __post_init__(self) -> None:
        verts = _check_tensor("verts", self.verts, 2, 3)
        faces = _check_tensor("faces", self.faces, 2, 3)
        uv = _check_tensor("uv", self.uv, 2, 2)
        tex = _check_tensor("texture", self.texture, 3)
        if tex.shape[0] != 3:
            raise ValueError(f"texture must be (3, Ht, Wt) RGB, got shape {tuple(tex.shape)}")
        if uv.shape[0] != verts.shape[0]:
            raise ValueError(f"uv must be (V, 2) with V={verts.shape[0]} like verts, got {tuple(uv.shape)}")
        if faces.dtype not in (torch.int64, torch.int32):
            raise TypeError(f"faces must be an integer tensor, got {faces.dtype}")
        if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= verts.shape[0]):
            raise ValueError(f"faces index vertices outside [0, {verts.shape[0]})")

    @property
    def num_verts(self) -> int:
        """``V``."""
        return int(self.verts.shape[0])

    @property
    def num_faces(self) -> int:
        """``F``."""
        return int(self.faces.shape[0])

    def to(
        self, device: torch.device | str | int | torch.dtype | None = None, dtype: torch.dtype | None = None,
        non_blocking: bool = False, copy: bool = False,
    ) -> "TexturedMesh":
        """A copy on ``device`` with float tensors cast to ``dtype`` (faces int64), called as ``Tensor.to`` is
        (``.to(device)``, ``.to(dtype)``, ``.to(device, dtype)``, keywords, ``non_blocking`` and ``copy``:
        :func:`~torchface._device.tensor_mover`, as ``TrackResult.to``). The faces are moved blocking whatever
        ``non_blocking`` says: the mesh's check reads their values."""
        move = tensor_mover(device, dtype, non_blocking, copy)  # (a device this machine lacks: a ValueError)
        faces = tensor_mover(device, None, False, copy)(self.faces).to(torch.int64)
        return TexturedMesh(move(self.verts), faces, move(self.uv), move(self.texture))


@dataclass(frozen=True, eq=False)
class LightState:
    """Ambient plus ``L`` distant directional lights, one state per batch sample.

    Attributes:
        ambient: ``(B,)`` ambient level ``a``.
        directions: ``(B, L, 3)`` unit vectors in the CAMERA frame pointing FROM the surface TOWARD
            each light (a light behind the camera, shining at a frontal face, is ``(0, 0, -1)``).
            Directions are renormalised when used.
        intensities: ``(B, L)`` intensities ``s_l`` (0 switches a light off; ``L = 0`` is allowed).

    Example:
        >>> light = LightState.ambient_only(torch.ones(2))
        >>> light.batch_size, light.num_lights
        (2, 0)
    """

    ambient: Tensor
    directions: Tensor
    intensities: Tensor

    def __post_init__(self) -> None:
        amb = _check_tensor("ambient", self.ambient, 1)
        dirs = _check_tensor("directions", self.directions, 3, 3)
        inten = _check_tensor("intensities", self.intensities, 2)
        b = amb.shape[0]
        if dirs.shape[0] != b or inten.shape != (b, dirs.shape[1]):
            raise ValueError(
                "light state must be ambient (B,), directions (B, L, 3), intensities (B, L) with one B and L, "
                f"got {tuple(amb.shape)}, {tuple(dirs.shape)}, {tuple(inten.shape)}"
            )

    @property
    def batch_size(self) -> int:
        """``B``."""
        return int(self.ambient.shape[0])

    @property
    def num_lights(self) -> int:
        """``L``, the number of directional lights."""
        return int(self.directions.shape[1])

    @classmethod
    def ambient_only(cls, ambient: Tensor) -> "LightState":
        """Ambient light ``(B,)`` and no directional light."""
        amb = _check_tensor("ambient", ambient, 1)
        b = amb.shape[0]
        return cls(amb, amb.new_zeros(b, 0, 3), amb.new_zeros(b, 0))

    def select(self, index: Tensor | slice | int | list[int]) -> "LightState":
        """The states of the samples ``index`` (a slice, index list or tensor; an int keeps ``B = 1``)."""
        if isinstance(index, int):
            index = slice(index, index + 1) if index != -1 else slice(-1, None)
        return LightState(self.ambient[index], self.directions[index], self.intensities[index])

    def to(
        self, device: torch.device | str | int | torch.dtype | None = None, dtype: torch.dtype | None = None,
        non_blocking: bool = False, copy: bool = False,
    ) -> "LightState":
        """A copy on ``device`` cast to ``dtype`` (a floating dtype), called as ``Tensor.to`` is (``.to(device)``,
        ``.to(dtype)``, ``.to(device, dtype)``, keywords, ``non_blocking`` and ``copy``:
        :func:`~torchface._device.tensor_mover`, as ``TrackResult.to``)."""
        move = tensor_mover(device, dtype, non_blocking, copy)  # (a device this machine lacks: a ValueError)
        return LightState(move(self.ambient), move(self.directions), move(self.intensities))


class RenderResult(NamedTuple):
    """What :func:`render` returns (unpacks as ``image, mask, fragments``).

    Attributes:
        image: ``(B, 3, H, W)`` RGB in ``[0, 1]``: shaded mesh over the background.
        mask: ``(B, 1, H, W)`` float, 1 where a triangle covers the pixel centre, else 0.
        fragments: the rasterizer's per-pixel triangle ids, barycentrics and depth.
    """

    image: Tensor
    mask: Tensor
    fragments: Fragments


def interpolate_vertex_attributes(fragments: Fragments, faces: Tensor, attributes: Tensor) -> Tensor:
    """Barycentric interpolation of per-vertex attributes at every pixel.

    Args:
        fragments: rasterizer output with ``pix_to_face (B, H, W)`` (-1 = background) and
            perspective-correct ``bary (B, H, W, 3)``.
        faces: ``(F, 3)`` int64 vertex indices.
        attributes: ``(B, V, C)`` or unbatched ``(V, C)`` per-vertex values.

    Returns:
        ``(B, H, W, C)`` interpolated values, exactly 0 at background pixels.

    Example:
        >>> # colours (1, V, 3) -> image-shaped (1, H, W, 3)
        >>> # interpolate_vertex_attributes(frags, faces, colours)
    """
    p2f = fragments.pix_to_face
    b, h, w = p2f.shape
    if attributes.ndim == 2:
        attributes = attributes.unsqueeze(0).expand(b, -1, -1)
    _check_tensor("attributes", attributes, 3)
    if attributes.shape[0] != b:
        raise ValueError(f"attributes must be (B, V, C) with B={b}, got {tuple(attributes.shape)}")
    v, c = attributes.shape[1], attributes.shape[2]
    # Work on covered pixels only (the face is a fraction of the image), then scatter back.
    flat_p2f = p2f.reshape(-1)
    pix = torch.nonzero(flat_p2f >= 0).squeeze(1)
    face_idx = flat_p2f[pix]
    batch_idx = torch.div(pix, h * w, rounding_mode="floor")
    corner = faces.to(device=p2f.device, dtype=torch.int64)[face_idx] + (batch_idx * v).unsqueeze(1)  # (n, 3)
    corner_vals = attributes.reshape(b * v, c)[corner]  # (n, 3, C)
    bary = fragments.bary.reshape(-1, 3)[pix].to(attributes.dtype)
    vals = (bary.unsqueeze(-1) * corner_vals).sum(dim=1)
    out = attributes.new_zeros(b * h * w, c).index_put((pix,), vals)
    return out.reshape(b, h, w, c)


def sample_texture(texture: Tensor, uv: Tensor) -> Tensor:
    """Bilinear texture look-up at continuous texture coordinates.

    Args:
        texture: ``(3, Ht, Wt)`` or ``(B, 3, Ht, Wt)`` RGB texture (any channel count ``C`` works).
        uv: ``(B, H, W, 2)`` coordinates in ``[0, 1]`` (module docstring for the convention);
            outside values clamp to the border texels.

    Returns:
        ``(B, C, H, W)`` sampled colours.

    Example:
        >>> tex = torch.rand(3, 8, 8)
        >>> sample_texture(tex, torch.full((1, 2, 2, 2), 0.5)).shape
        torch.Size([1, 3, 2, 2])
    """
    _check_tensor("uv", uv, 4, 2)
    b = uv.shape[0]
    if texture.ndim == 3:
        texture = texture.unsqueeze(0)
    _check_tensor("texture", texture, 4)
    if texture.shape[0] not in (1, b):
        raise ValueError(f"texture batch must be 1 or B={b}, got shape {tuple(texture.shape)}")
    texture = texture.to(uv.dtype).expand(b, -1, -1, -1)
    grid = uv * 2.0 - 1.0
    return nnf.grid_sample(texture, grid, mode="bilinear", padding_mode="border", align_corners=False)


def lambertian_irradiance(normals: Tensor, light: LightState) -> Tensor:
    """Lambertian shading factor ``a + sum_l s_l max(0, n . d_l)`` (Anisetti et al. Eq. 10).

    Args:
        normals: ``(B, ..., 3)`` unit normals in the camera frame (any middle shape, e.g. ``H, W``).
        light: light state with batch size ``B``.

    Returns:
        ``(B, ...)`` irradiance factor that multiplies the albedo.

    Example:
        >>> light = LightState(torch.zeros(1), torch.tensor([[[0.0, 0.0, -1.0]]]), torch.ones(1, 1))
        >>> lambertian_irradiance(torch.tensor([[0.0, 0.0, -1.0]]), light)
        tensor([1.])
    """
    if normals.shape[-1] != 3 or normals.shape[0] != light.batch_size:
        raise ValueError(
            f"normals must be (B, ..., 3) with B={light.batch_size} like the light, got {tuple(normals.shape)}"
        )
    b = normals.shape[0]
    middle = normals.shape[1:-1]
    n = normals.reshape(b, math.prod(middle), 3)  # (not -1: B = 0 has no size to infer)
    dirs = light.directions.to(n)
    eps = torch.finfo(n.dtype).eps
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp(min=eps)
    cosines = torch.einsum("bnc,blc->bnl", n, dirs).clamp(min=0.0)
    direct = (cosines * light.intensities.to(n).unsqueeze(1)).sum(dim=-1)
    out = light.ambient.to(n).unsqueeze(1) + direct
    return out.reshape(b, *middle)


def shade(
    fragments: Fragments,
    faces: Tensor,
    uv: Tensor,
    texture: Tensor,
    normals_cam: Tensor,
    light: LightState,
) -> tuple[Tensor, Tensor]:
    """Textured Lambertian colour of every covered pixel (module docstring for the model).

    Args:
        fragments: rasterizer output for a batch of ``B`` images of ``H x W``.
        faces: ``(F, 3)`` int64 triangles.
        uv: ``(V, 2)`` or ``(B, V, 2)`` texture coordinates.
        texture: ``(3, Ht, Wt)`` or ``(B, 3, Ht, Wt)`` RGB albedo in ``[0, 1]``.
        normals_cam: ``(B, V, 3)`` vertex normals in the camera frame (renormalised after interpolation).
        light: light state with batch size ``B``.

    Returns:
        ``colour (B, 3, H, W)`` clamped to ``[0, 1]`` (0 on background) and ``mask (B, 1, H, W)``.
    """
    covered = (fragments.pix_to_face >= 0).unsqueeze(1)
    dtype = normals_cam.dtype
    b = normals_cam.shape[0]
    uv_b = uv.to(dtype).unsqueeze(0).expand(b, -1, -1) if uv.ndim == 2 else uv.to(dtype)
    # One gather for both attributes: texture coordinates (2) and normals (3).
    both = interpolate_vertex_attributes(fragments, faces, torch.cat([uv_b, normals_cam], dim=-1))
    uv_px, n_px = both[..., :2], both[..., 2:]
    albedo = sample_texture(texture, uv_px)
    eps = torch.finfo(dtype).eps
    n_px = n_px / n_px.norm(dim=-1, keepdim=True).clamp(min=eps)
    irradiance = lambertian_irradiance(n_px, light).unsqueeze(1)
    colour = (albedo * irradiance).clamp(0.0, 1.0)
    mask = covered.to(dtype)
    return colour * mask, mask


def render(
    verts_cam: Tensor,
    faces: Tensor,
    uv: Tensor,
    texture: Tensor,
    normals_cam: Tensor,
    light: LightState,
    intrinsics: Intrinsics,
    background: Tensor | None = None,
    cull_backfaces: bool = False,
) -> RenderResult:
    """Rasterize and shade a textured mesh, composited over a background.

    Args:
        verts_cam: ``(B, V, 3)`` vertices in the camera frame, millimetres.
        faces: ``(F, 3)`` int64 triangles (outward, counter-clockwise seen from outside).
        uv: ``(V, 2)`` or ``(B, V, 2)`` texture coordinates in ``[0, 1]``.
        texture: ``(3, Ht, Wt)`` or ``(B, 3, Ht, Wt)`` RGB albedo in ``[0, 1]``.
        normals_cam: ``(B, V, 3)`` unit vertex normals in the camera frame.
        light: light state with batch size ``B``.
        intrinsics: camera; the output is ``intrinsics.height x intrinsics.width``.
        background: ``(B, 3, H, W)`` (or ``(1, 3, H, W)``) image behind the mesh; black when ``None``.
        cull_backfaces: passed to the rasterizer.

    Returns:
        :class:`RenderResult` ``(image (B, 3, H, W), mask (B, 1, H, W), fragments)``, on ``verts_cam``'s device,
        ``image`` and ``mask`` in ``normals_cam``'s dtype.

    Raises:
        TypeError: an argument of the wrong type (a numpy array, a uint8 texture: ``.float() / 255``, a
            ``cull_backfaces`` that is not a bool).
        ValueError: a shape that does not match ``verts_cam``'s ``B`` and ``V`` or the camera's size, or a tensor on
            another device than ``verts_cam``'s.

    Gradients: ``image`` is differentiable with respect to ``verts_cam`` (through the covered pixels' barycentric
    coordinates, as :func:`~torchface.rendering.rasterizer.rasterize`'s ``bary``: not through which triangle a pixel
    sees, so not at silhouettes and occlusion edges), ``normals_cam``, ``uv``, ``texture``, the light's tensors and
    ``background``; ``mask`` and the fragments' ``pix_to_face`` and ``facing`` carry none. An input that requires
    grad makes the image hold its graph: render under ``torch.no_grad()`` where no gradient is wanted.

    Devices: there is no ``device=`` argument, as for every function of :mod:`torchface.geometry`,
    :mod:`torchface.appearance` and :mod:`torchface.rendering`: it computes where its inputs are (``device=`` is for
    what makes tensors from nothing, ``load_candide3(device=...)``). Move them together (``TexturedMesh.to``,
    ``LightState.to``).

    Example:
        >>> # image, mask, frags = render(verts_cam, faces, uv, tex, normals_cam, light, Intrinsics.default(64, 48))
    """
    _check_tensor("verts_cam", verts_cam, 3, 3)
    _check_tensor("normals_cam", normals_cam, 3, 3)
    if normals_cam.shape != verts_cam.shape:
        raise ValueError(
            f"normals_cam must match verts_cam {tuple(verts_cam.shape)}, got {tuple(normals_cam.shape)}"
        )
    b, v = verts_cam.shape[:2]
    if not isinstance(light, LightState):
        raise TypeError(f"light must be a LightState, got {type(light).__name__}")
    if light.batch_size != b:
        raise ValueError(f"light batch size must be B={b}, got {light.batch_size}")
    h, w = check_intrinsics(intrinsics).height, intrinsics.width
    cull_backfaces = check_bool(cull_backfaces, "cull_backfaces")  # ("no" was taken as true, and culled)
    # (uv: torch.cat's "Sizes of tensors must match", or a (V, 3) told as normals (B, H, W, 4); a numpy uv or texture
    # "no attribute 'to'"; a uint8 texture taken as 0-255 albedo, every pixel clamped to white)
    for name, x in (("uv", uv), ("texture", texture)):
        if not isinstance(x, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if uv.ndim not in (2, 3) or uv.shape[-2:] != (v, 2) or uv.ndim == 3 and uv.shape[0] != b:
        raise ValueError(f"uv must be (V, 2) or (B, V, 2) with V={v} and B={b} like verts_cam, got {tuple(uv.shape)}")
    if texture.ndim not in (3, 4):
        raise ValueError(f"texture must be (3, Ht, Wt) or (B, 3, Ht, Wt), got {tuple(texture.shape)}")
    tensors: tuple[tuple[str, Tensor | None], ...] = (
        ("verts_cam", verts_cam), ("normals_cam", normals_cam), ("uv", uv), ("texture", texture),
        ("background", background),
    )  # fmt: skip
    for name, value in tensors:
        if value is not None and not value.is_floating_point():
            hint = " (uint8: .float() / 255)" if value.dtype == torch.uint8 else ""
            raise TypeError(f"{name} must be a floating-point tensor, got {value.dtype}{hint}")
    for name, value in (*tensors[1:], ("light", light.ambient)):
        if value is not None and value.device != verts_cam.device:  # (torch's "Expected all tensors to be on the
            # same device")
            raise ValueError(f"{name} must be on verts_cam's device {verts_cam.device}, got {value.device}")
    if background is not None:
        _check_tensor("background", background, 4)
        if background.shape[1:] != (3, h, w) or background.shape[0] not in (1, b):
            raise ValueError(f"background must be (B, 3, {h}, {w}) with B={b} or 1, got {tuple(background.shape)}")
    fragments = rasterize(verts_cam, faces, intrinsics, cull_backfaces=cull_backfaces)
    colour, mask = shade(fragments, faces, uv, texture, normals_cam, light)
    if background is not None:
        colour = colour + (1.0 - mask) * background.to(colour)
    return RenderResult(colour, mask, fragments)


class TexturedRenderer(nn.Module):
    """Thin module holding a mesh's topology, texture coordinates and texture; calls :func:`render`.

    Args:
        faces: ``(F, 3)`` int64 triangles.
        uv: ``(V, 2)`` texture coordinates.
        texture: ``(3, Ht, Wt)`` RGB albedo.
        intrinsics: camera of the rendered images.

    Example:
        >>> # renderer = TexturedRenderer(mesh.faces, mesh.uv, mesh.texture, Intrinsics.default(640, 480))
        >>> # image, mask, frags = renderer(verts_cam, normals_cam, light)
    """

    faces: Tensor  # buffers (registered in __init__)
    uv: Tensor
    texture: Tensor

    def __init__(self, faces: Tensor, uv: Tensor, texture: Tensor, intrinsics: Intrinsics) -> None:
        super().__init__()
        self.register_buffer("faces", faces.to(torch.int64))
        self.register_buffer("uv", uv)
        self.register_buffer("texture", texture)
        self.intrinsics = intrinsics

    def forward(
        self, verts_cam: Tensor, normals_cam: Tensor, light: LightState, background: Tensor | None = None
    ) -> RenderResult:
        """Render ``(B, V, 3)`` camera-frame vertices and normals under ``light``."""
        return render(
            verts_cam, self.faces, self.uv, self.texture, normals_cam, light, self.intrinsics, background
        )
