"""Appearance: sampling images at projected points, and the illumination basis (paper Eq. 10-11, 19)."""

from torchface.appearance.illumination import (
    ILLUMINATION_TERM_NAMES,
    NUM_ILLUMINATION_TERMS,
    apply_illumination,
    illumination_basis,
    remove_illumination,
)
from torchface.appearance.sampling import image_with_gradients, pixels_to_grid, pyr_down, sample_at_pixels, to_gray

__all__ = [
    "ILLUMINATION_TERM_NAMES",
    "NUM_ILLUMINATION_TERMS",
    "apply_illumination",
    "illumination_basis",
    "remove_illumination",
    "image_with_gradients",
    "pixels_to_grid",
    "pyr_down",
    "sample_at_pixels",
    "to_gray",
]
