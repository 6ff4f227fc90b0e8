"""Panoramic stabilisation (thesis Ch. 6): HoLiNet heat maps -> horizon (roll, pitch) -> MPP (yaw) -> PVG
(3-DoF refinement), and :func:`stabilise` over a sequence. Importing registers the ``horizon`` hook.

Conventions (camera frame: OpenCV, x right, y down, z forward; rotation maths in
:mod:`omnidl.geometry.rotations`):

* The *orientation* of a frame is ``R = R_ref_cur`` (``(..., 3, 3)``): a direction ``d`` seen in the
  current camera frame is ``R @ d`` in the reference (upright) frame. So
  ``rotate_panorama(reference, R)`` renders the current frame and ``rotate_panorama(current, R.T)``
  stabilises it (:func:`omnidl.geometry.panorama.rotate_panorama`).
* The horizon-plane normal ("up vector") of a frame of orientation ``R`` is ``n = R.T @ UP`` with
  ``UP = (0, -1, 0)`` (:func:`~omnidl.geometry.rotations.up_from_rotation`); its roll and pitch are
  :func:`~omnidl.geometry.rotations.tilt_from_up`.
* Angles: ``R = R_y(yaw) @ R_x(pitch) @ R_z(roll)`` (radians,
  :func:`~omnidl.geometry.rotations.euler_to_matrix`).

The command line lives in the applications wing: ``python -m omnidl.apps.gyroscope``.
"""
from .horizon import horizon_hook
from .icosahedron import icosahedron_vertices
from .mpp import MPPResult, mpp_yaw
from .pipeline import FrameEstimate, Gyroscope, GyroscopeOptions, model_horizon_fn, stabilise
from .pvg import PVGResult, pvg_refine

__all__ = ["FrameEstimate", "Gyroscope", "GyroscopeOptions", "MPPResult", "PVGResult", "horizon_hook",
           "icosahedron_vertices", "model_horizon_fn", "mpp_yaw", "pvg_refine", "stabilise"]
