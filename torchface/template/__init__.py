"""Template management: template points from a frame (paper Eq. 3-9, Section 4)."""

from torchface.template.points import Template, build_template, gather_face_attributes

__all__ = ["Template", "build_template", "gather_face_attributes"]
