"""The normalised face: frames resampled to a frontal, neutral, evenly lit canonical view (paper Section 4)."""

from torchface.normalise.face import (
    NormalisedFace,
    NormalisedFaceLayout,
    NormalisedFaceResult,
    build_normalised_layout,
    normalised_face,
    normalised_face_posed,
)

__all__ = [
    "NormalisedFace",
    "NormalisedFaceLayout",
    "NormalisedFaceResult",
    "build_normalised_layout",
    "normalised_face",
    "normalised_face_posed",
]
