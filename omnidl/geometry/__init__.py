"""Geometry on top of the camera models (thesis ch. 2): Plücker lines, the 3D line through rays,
rotations, re-projection between cameras, panorama sampling and rotation, cube maps, fisheye
rectification, the horizon plane of a panorama's heat maps.

Conventions and the API are documented in ``docs/geometry.md``.
"""
from .cubemap import (FACE_NAMES, cube_face_camera, cube_face_rotations, cubemap_to_camera, cubemap_to_equirect,
                      equirect_to_cubemap)
from .horizon import HorizonFitOptions, fit_horizon
from .line_from_rays import Y_AXIS, Z_AXIS, LineFit, LineStatus, camera_axis, line_from_rays
from .panorama import rotate_panorama, sample_panorama
from .plucker import (ClosestPoints, closest_points_line_ray, closest_points_lines, line_distance,
                      line_from_point_direction, line_from_points, lines_from_rays, normalize_line,
                      plucker_identity, point_line_distance, point_on_line, project_point, side, transform_line)
from .rectify import RectificationCoverage, perspective_camera, rectification_coverage, rectify, unrectify
from .rotations import (UP, UPRIGHT_TO_WORLD, axis_angle_to_matrix, camera_to_world, camera_to_world_rotation,
                        euler_to_matrix, matrix_to_axis_angle, matrix_to_euler, matrix_to_quaternion,
                        quaternion_to_matrix, random_rotation, random_tilt_rotation, rotation_angle, rotation_x,
                        rotation_y, rotation_z, skew, tilt_angle, tilt_from_up, tilt_rotation, up_from_rotation,
                        up_vector, upright_rotation, upright_to_world, world_to_camera)
from .warp import Reprojector, WarpGrid, clear_warp_cache, reproject, sample_grid, warp_grid

__all__ = [
    # re-projection
    "reproject", "warp_grid", "sample_grid", "clear_warp_cache", "WarpGrid", "Reprojector", "rotate_panorama",
    "sample_panorama",
    "FACE_NAMES", "cube_face_camera", "cube_face_rotations", "equirect_to_cubemap", "cubemap_to_camera",
    "cubemap_to_equirect", "perspective_camera", "rectify", "unrectify", "rectification_coverage",
    "RectificationCoverage",
    # Plücker lines
    "line_from_points", "line_from_point_direction", "lines_from_rays", "normalize_line", "plucker_identity",
    "side", "point_on_line", "point_line_distance", "project_point", "line_distance", "closest_points_lines",
    "closest_points_line_ray", "ClosestPoints", "transform_line", "line_from_rays", "LineFit", "LineStatus", "camera_axis", "Y_AXIS", "Z_AXIS",
    # horizon plane from heat maps
    "fit_horizon", "HorizonFitOptions",
    # rotations
    "axis_angle_to_matrix", "matrix_to_axis_angle", "quaternion_to_matrix", "matrix_to_quaternion", "skew",
    "rotation_x", "rotation_y", "rotation_z", "euler_to_matrix", "matrix_to_euler", "rotation_angle",
    "tilt_angle", "UP", "up_vector", "up_from_rotation", "tilt_from_up", "tilt_rotation", "random_rotation",
    "random_tilt_rotation", "UPRIGHT_TO_WORLD", "upright_to_world", "upright_rotation",
    "camera_to_world_rotation", "camera_to_world", "world_to_camera",
]
