"""Plausibility of a loaded calibration: values that construct a valid camera but are probably wrong.

Run by :func:`omnidl.cameras.io.load` on every camera it reads (any format). Hard errors (non-finite values,
image sizes <= 0, focal lengths <= 0, a FOV outside (0, 360] deg) come from the camera's own validation
(:mod:`omnidl.cameras.validate`) and the readers; the checks here are the ones a valid camera can fail:

* a principal point outside the image ``[0, W] x [0, H]`` (a swapped width/height, a crop, a wrong unit):
  :class:`ImplausibleCalibrationWarning`;
* a ``max_fov`` under :data:`MIN_FOV_DEG` degrees on a fisheye family (a FOV typed in radians where degrees
  were meant, or vice versa): :class:`ImplausibleCalibrationWarning`. Formats that store the FOV in
  degrees (the ``kb_txt`` file) raise ``ValueError`` instead (see :mod:`omnidl.cameras.io.kb_txt`).
"""
from __future__ import annotations

import math
import warnings

from ..base import Camera
from ._common import MIN_FOV_DEG, ImplausibleCalibrationWarning, family_of


def principal_point(camera: Camera) -> tuple[float, float] | None:
    """``(cx, cy)`` in omnidl pixels, ``None`` for families without one (panoramas)."""
    if hasattr(camera, "cx") and hasattr(camera, "cy"):
        return float(camera.cx), float(camera.cy)
    if hasattr(camera, "cx_offset") and hasattr(camera, "cy_offset"):  # WoodScape: offsets from the centre
        return camera.width / 2 + float(camera.cx_offset), camera.height / 2 + float(camera.cy_offset)
    return None


def check_plausible(camera: Camera, where: str) -> None:
    """Warn (:class:`ImplausibleCalibrationWarning`) about the implausible values of ``camera`` read from ``where``."""
    pp = principal_point(camera)
    if pp is not None:
        cx, cy = pp
        if not (0 <= cx <= camera.width and 0 <= cy <= camera.height):
            warnings.warn(f"{where}: the principal point (cx, cy) = ({cx:g}, {cy:g}) lies outside the "
                          f"{camera.width}x{camera.height} image (expected 0 <= cx <= {camera.width}, 0 <= cy <= "
                          f"{camera.height}); are width and height swapped, or is the image cropped?",
                          ImplausibleCalibrationWarning, stacklevel=3)
    fov = getattr(camera, "max_fov", None)
    if isinstance(fov, float) and math.degrees(fov) < MIN_FOV_DEG:
        warnings.warn(f"{where}: {family_of(camera)} max_fov = {fov:g} rad ({math.degrees(fov):.3g} deg) is under "
                      f"{MIN_FOV_DEG:g} deg, implausible for this model; max_fov is in radians (195 deg = "
                      f"{math.radians(195):.4f} rad)", ImplausibleCalibrationWarning, stacklevel=3)
