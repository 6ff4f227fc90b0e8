"""Panoramic stabilisation (thesis Ch. 6): HoLiNet heat maps -> horizon (roll, pitch) -> MPP (yaw) -> PVG
(3-DoF refinement), and :func:`stabilise` over a sequence. Importing registers the ``horizon`` hook.

Conventions are in :mod:`.angles`; the CLI is ``python -m omnidl.postprocess.gyroscope`` (:mod:`.cli`).
"""
from .angles import euler_to_matrix, matrix_to_euler, tilt_from_up, tilt_rotation
from .horizon import HorizonFitOptions, fit_horizon, horizon_hook
from .icosahedron import icosahedron_vertices
from .mpp import MPPResult, mpp_yaw
from .pipeline import FrameEstimate, Gyroscope, GyroscopeOptions, model_horizon_fn, stabilise
from .pvg import PVGResult, pvg_refine
from .sampling import rotate_equirect, sample_equirect

__all__ = ["FrameEstimate", "Gyroscope", "GyroscopeOptions", "HorizonFitOptions", "MPPResult", "PVGResult",
           "euler_to_matrix", "fit_horizon", "horizon_hook", "icosahedron_vertices", "matrix_to_euler",
           "model_horizon_fn", "mpp_yaw", "pvg_refine", "rotate_equirect", "sample_equirect", "stabilise",
           "tilt_from_up", "tilt_rotation"]
