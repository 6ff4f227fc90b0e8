"""Visualisation: depth/semantic colour maps, overlays, image grids, PLY point clouds, plots."""
from .colormap import depth_to_color, overlay, palette, semantic_to_color
from .grid import make_grid, to_uint8_bgr
from .panorama import PanoramaVisualizer, sample_panels
from .ply import depth_to_points, read_ply, write_ply
from .plots import plot_curves

__all__ = ["depth_to_color", "overlay", "palette", "semantic_to_color", "make_grid", "to_uint8_bgr",
           "PanoramaVisualizer", "sample_panels", "depth_to_points", "read_ply", "write_ply", "plot_curves"]
