"""Geometry on top of the camera models: re-projection between cameras, panorama rotation."""
from .panorama import rotate_panorama
from .warp import Reprojector, WarpGrid, clear_warp_cache, reproject, sample_grid, warp_grid

__all__ = ["reproject", "warp_grid", "sample_grid", "clear_warp_cache", "WarpGrid", "Reprojector",
           "rotate_panorama"]
