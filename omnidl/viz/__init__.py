"""Visualisation: depth/semantic colour maps, overlays, image grids, full-resolution titled figures with a
depth colour bar and a class legend, 16-bit depth / semantic PNGs, PLY point clouds (gravity-aligned y-up
frame, see :mod:`omnidl.viz.ply`), textured meshes as glTF binary / OBJ + MTL (:mod:`omnidl.viz.mesh`), 3-D
wireframes over images, plots."""
from .colormap import depth_to_color, overlay, palette, semantic_to_color
from .figure import class_legend, depth_colorbar, figure_key, prediction_figure, titled_row
from .grid import make_grid, to_uint8_bgr
from .mesh import TexturedMesh, read_glb, write_glb, write_obj
from .maps import depth_scale_path, read_depth_png16, write_depth_png16, write_rgb_png, write_semantic_png
from .panorama import FigureVisualizer, PanoramaVisualizer, sample_panels
from .plots import plot_curve_panels, plot_curves
from .ply import depth_to_points, ply_frame, read_ply, to_gravity_y_up, write_ply
from .wireframe import box_edges, draw_segments_3d

__all__ = ["depth_to_color", "overlay", "palette", "semantic_to_color", "make_grid", "to_uint8_bgr",
           "PanoramaVisualizer", "sample_panels", "depth_to_points", "read_ply", "write_ply", "plot_curves",
           "prediction_figure", "titled_row", "depth_colorbar", "class_legend", "figure_key",
           "write_depth_png16", "read_depth_png16", "depth_scale_path", "write_semantic_png", "write_rgb_png",
           "to_gravity_y_up", "ply_frame", "draw_segments_3d", "box_edges", "plot_curve_panels", "FigureVisualizer",
           "TexturedMesh", "read_glb", "write_glb", "write_obj"]
