"""Scaled room layout from panoramas (thesis chapter 5): solvers, pipeline, hooks, exports.

Public API::

    from omnidl.postprocess.layout import (estimate_layout, LayoutOptions, Layout,
        column_rays, column_rays_from_boundary, solve_walls, solve_manhattan, solve_atlanta)

    rays = column_rays_from_boundary(outputs["boundary"][0], camera)      # (2, W) radians, any Camera
    layout = estimate_layout(rays, torch.sigmoid(outputs["corner"][0, 0]).numpy(), world="atlanta")
    layout.save_json("room.json"); layout.save_obj("room.obj")

Hooks ``layout_manhattan``, ``layout_atlanta``, ``layout_manhattan_central`` and
``layout_atlanta_central`` are registered on import.
"""
from .layout import Layout
from .pipeline import LayoutOptions, estimate_layout
from .rays import ColumnRays, column_rays, column_rays_from_boundary
from .solvers import (WallFit, atlanta_rows, manhattan_rows, ransac_iterations, solve_atlanta, solve_manhattan,
                      solve_walls, solve_walls_central, wall_rows)
from . import hooks  # noqa: F401  (registers the hooks)
from .hooks import layouts_from_outputs

__all__ = ["Layout", "LayoutOptions", "estimate_layout", "ColumnRays",
           "column_rays", "column_rays_from_boundary", "WallFit", "atlanta_rows", "manhattan_rows",
           "ransac_iterations", "solve_atlanta", "solve_manhattan", "solve_walls", "solve_walls_central",
           "wall_rows", "layouts_from_outputs"]
