"""Pictures of a track: overlay frames (wireframe, head axes, confidence) and a summary plot."""

from torchface.visualise.overlay import AXIS_LENGTH_MM, axes_geometry, draw_overlay, mesh_edges, overlay_geometry
from torchface.visualise.plot import au_groups, plot_track

__all__ = [
    "AXIS_LENGTH_MM", "au_groups", "axes_geometry", "draw_overlay", "mesh_edges", "overlay_geometry", "plot_track",
]
