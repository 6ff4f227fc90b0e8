"""Tangential (decentering) and thin-prism distortion terms shared by the OpenCV pinhole and Fisheye624.

On a normalised plane point ``(x, y)`` with ``r2 = x^2 + y^2`` (Brown 1966; Weng et al. 1992; OpenCV's
``projectPoints`` order)::

    dx = 2 p1 x y + p2 (r2 + 2 x^2) + s1 r2 + s2 r2^2
    dy = p1 (r2 + 2 y^2) + 2 p2 x y + s3 r2 + s4 r2^2

OpenCV adds these to the radially scaled point; Fisheye624 (COLMAP's RAD_TAN_THIN_PRISM_FISHEYE) adds them
to the fisheye-plane point, with its ``(p0, p1)`` in the slots of OpenCV's ``(p2, p1)``.
"""
from __future__ import annotations

from torch import Tensor


def tangential_prism(xy: Tensor, p1: float, p2: float, s: tuple[float, float, float, float]) -> tuple[Tensor, Tensor]:
    """``(dx, dy)``, each ``(...)``, of plane points ``xy (..., 2)`` (module formula)."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + r2 * (s[0] + s[1] * r2)
    dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + r2 * (s[2] + s[3] * r2)
    return dx, dy


def tangential_prism_jacobian(xy: Tensor, p1: float, p2: float,
                              s: tuple[float, float, float, float]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Entries ``(d dx/dx, d dx/dy, d dy/dx, d dy/dy)``, each ``(...)``, of :func:`tangential_prism`."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    tx = 2 * (s[0] + 2 * s[1] * r2)  # d(s1 r2 + s2 r2^2) / d r2, times 2 (d r2 / dx = 2 x)
    ty = 2 * (s[2] + 2 * s[3] * r2)
    return (2 * p1 * y + 6 * p2 * x + tx * x, 2 * p1 * x + 2 * p2 * y + tx * y,
            2 * p1 * x + 2 * p2 * y + ty * x, 6 * p1 * y + 2 * p2 * x + ty * y)
