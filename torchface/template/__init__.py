"""Template management: template points from a frame (paper Eq. 3-9, Section 4)."""

from torchface.template.points import (
    Template,
    TemplatePixels,
    build_template,
    gather_face_attributes,
    point_normals,
    select_template_pixels,
    template_at,
)

__all__ = [
    "Template",
    "TemplatePixels",
    "build_template",
    "gather_face_attributes",
    "point_normals",
    "select_template_pixels",
    "template_at",
]
from torchface.template.dissimilarity import (  # noqa: E402
    DissimilarityConfig,
    DissimilarityReference,
    DissimilarityResult,
    LKResult,
    build_dissimilarity_reference,
    dissimilarity,
    inverse_compositional_lk,
)

__all__ += [
    "DissimilarityConfig",
    "DissimilarityReference",
    "DissimilarityResult",
    "LKResult",
    "build_dissimilarity_reference",
    "dissimilarity",
    "inverse_compositional_lk",
]
from torchface.template.management import Mosaic, MosaicLevel, TemplateConfig  # noqa: E402

__all__ += ["Mosaic", "MosaicLevel", "TemplateConfig"]
