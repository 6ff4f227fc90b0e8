"""Panoramic stabilisation (thesis Ch. 6): HoLiNet heat maps -> horizon (roll, pitch) -> MPP (yaw) -> PVG
(3-DoF refinement), and :func:`stabilise` over a sequence. Importing registers the ``horizon`` hook."""
from .angles import euler_to_matrix, matrix_to_euler, tilt_from_up, tilt_rotation
from .horizon import HorizonFitOptions, fit_horizon, horizon_hook
from .icosahedron import icosahedron_vertices
from .sampling import rotate_equirect, sample_equirect

__all__ = ["HorizonFitOptions", "euler_to_matrix", "fit_horizon", "horizon_hook", "icosahedron_vertices",
           "matrix_to_euler", "rotate_equirect", "sample_equirect", "tilt_from_up", "tilt_rotation"]
