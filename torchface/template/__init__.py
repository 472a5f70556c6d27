"""Templates and their management: template points from a frame (paper Eq. 3-9), the dissimilarity confidence
of the normalised face (Section 4.1) and the pose-keyed mosaic with its settings, :class:`TemplateConfig`
(Section 4)."""

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
