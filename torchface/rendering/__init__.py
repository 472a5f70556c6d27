"""Rendering: rasterization (which triangle each pixel sees), visibility and normals."""

from torchface.rendering.rasterizer import Fragments, rasterize
from torchface.rendering.reference import rasterize_reference
from torchface.rendering.visibility import backfacing, face_normals, points_visible, vertex_normals
