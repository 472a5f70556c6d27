"""Rendering: rasterization (which triangle each pixel sees), visibility, normals and Lambertian shading."""

from torchface.rendering.rasterizer import Coverage, Fragments, rasterize, rasterize_coverage
from torchface.rendering.reference import rasterize_reference
from torchface.rendering.shading import LightState, TexturedMesh, render
from torchface.rendering.visibility import backfacing, face_normals, points_visible, vertex_normals

__all__ = [
    "Coverage",
    "Fragments",
    "LightState",
    "TexturedMesh",
    "backfacing",
    "face_normals",
    "points_visible",
    "rasterize",
    "rasterize_coverage",
    "rasterize_reference",
    "render",
    "vertex_normals",
]
