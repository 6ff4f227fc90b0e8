"""Corner columns from the corner probability, wall column ranges, and corner geometry.

Corner rays. For an upright panorama the vertical edge of a room corner projects to one column;
the rays of that column span the vertical half-plane through the column's optical centre ``o``
with horizontal direction ``b``. The corner of a wall line is the point of the line closest to
that ray (thesis §5.4.4): in top view, the intersection of the 2-D ray ``o + s b`` with the line.
"""
from __future__ import annotations

import math

import numpy as np


def find_peaks(prob: np.ndarray, threshold: float = 0.5, radius: int | None = None) -> np.ndarray:
    """Sub-pixel columns (continuous ``u``) of local maxima of a circular ``(W,)`` probability.

    A column is a peak when it is the maximum within ``radius`` columns (circularly; default
    ``W/200``, at least 2) and above ``threshold``. The position is refined by a parabola through the peak and
    its neighbours. Returns sorted ``u`` values in ``[0, W)``.
    """
    p = np.nan_to_num(np.asarray(prob, float).reshape(-1), nan=0.0)
    W = p.shape[0]
    r = max(2, int(round(W / 200))) if radius is None else max(1, int(radius))
    idx = np.arange(W)
    win = np.stack([np.roll(p, k) for k in range(-r, r + 1)], 0)
    is_max = (p >= win.max(0)) & (p > threshold)
    # plateaus: keep the first column of equal maxima
    is_max &= ~((np.roll(p, 1) == p) & np.roll(is_max, 1))
    peaks = idx[is_max]
    if len(peaks) == 0:
        return np.zeros(0)
    l, c, rr = p[(peaks - 1) % W], p[peaks], p[(peaks + 1) % W]
    den = l - 2 * c + rr
    off = np.where(np.abs(den) > 1e-12, 0.5 * (l - rr) / np.where(np.abs(den) > 1e-12, den, 1.0), 0.0)
    off = np.clip(off, -0.5, 0.5)
    return np.sort(np.mod(peaks + 0.5 + off, W))


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


def ray_line_range(theta, d, origin2: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Range ``s`` along the 2-D ray ``origin2 + s b`` where it meets the wall line ``(theta, d)`` (NaN if never)."""
    nx, ny = -np.sin(theta), np.cos(theta)
    nb = nx * b[..., 0] + ny * b[..., 1]
    no = nx * origin2[..., 0] + ny * origin2[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (d - no) / nb
    return np.where(np.abs(nb) > 1e-12, s, np.nan)


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


def column_ray(u: float | np.ndarray, width: int, rc: float) -> tuple[np.ndarray, np.ndarray]:
    """Optical centre ``(..., 2)`` and horizontal direction ``(..., 2)`` of continuous column ``u``."""
    lon = 2 * math.pi * np.asarray(u, float) / width - math.pi
    b = np.stack([np.sin(lon), np.cos(lon)], -1)
    return rc * b, b


def azimuth(points2: np.ndarray) -> np.ndarray:
    """Longitude of top-view points ``(..., 2)`` in our convention (``b = (sin lon, cos lon)``)."""
    return np.arctan2(points2[..., 0], points2[..., 1])


def wrap_angle(a):
    """Wrap to ``(-pi, pi]``."""
    return np.mod(np.asarray(a) + math.pi, 2 * math.pi) - math.pi
