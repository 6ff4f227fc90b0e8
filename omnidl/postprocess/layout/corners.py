"""Wall column ranges between corner columns, and top-view corner geometry.

Corner columns are the peaks of the corner probability (:func:`omnidl.metrics.layout.find_peaks`).

Corner rays. For an upright panorama the vertical edge of a room corner projects to one column;
the rays of that column span the vertical half-plane through the column's optical centre ``o``
with horizontal direction ``b``. The corner of a wall line is the point of the line closest to
that ray (thesis §5.4.4): in top view, the intersection of the 2-D ray ``o + s b`` with the line
(``o``, ``b`` from :meth:`~.rays.ColumnRays.column`, i.e. from the camera).
"""
from __future__ import annotations

import math

import numpy as np


def wall_column_ranges(corners_u: np.ndarray, width: int, valid: np.ndarray, margin: float = 2.0) -> list[np.ndarray]:
    """Column indices of each wall: between consecutive corners (circular), ``margin`` px away from them.

    Wall ``k`` spans from corner ``k`` to corner ``k+1`` (the last wraps around to corner 0).
    """
    u = np.arange(width) + 0.5
    out = []
    n = len(corners_u)
    for k in range(n):
        a, b = corners_u[k], corners_u[(k + 1) % n]
        span = (b - a) % width if n > 1 else width
        rel = (u - a) % width
        sel = (rel > margin) & (rel < span - margin) & valid
        out.append(np.flatnonzero(sel))
    return out


def line_intersection(theta1, d1, theta2, d2) -> np.ndarray:
    """Intersection ``(..., 2)`` of two wall lines ``{p : e2(theta) . p = d}`` (NaN if parallel)."""
    n1 = np.stack([-np.sin(theta1), np.cos(theta1)], -1)
    n2 = np.stack([-np.sin(theta2), np.cos(theta2)], -1)
    det = n1[..., 0] * n2[..., 1] - n1[..., 1] * n2[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (d1 * n2[..., 1] - d2 * n1[..., 1]) / det
        y = (n1[..., 0] * d2 - n2[..., 0] * d1) / det
    bad = np.abs(det) < 1e-9
    return np.where(bad[..., None], np.nan, np.stack([x, y], -1))


def azimuth(points2: np.ndarray) -> np.ndarray:
    """Longitude of top-view points ``(..., 2)`` in our convention (``b = (sin lon, cos lon)``)."""
    return np.arctan2(points2[..., 0], points2[..., 1])


def wrap_angle(a):
    """Wrap to ``(-pi, pi]``."""
    return np.mod(np.asarray(a) + math.pi, 2 * math.pi) - math.pi
