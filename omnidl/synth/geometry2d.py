"""Small vectorised 2D polygon helpers (NumPy, float64) used to build and check floor plans.

Polygons are ``(N, 2)`` vertex arrays, counter-clockwise seen from above (world z up), without a
repeated last vertex. Edge ``k`` goes from vertex ``k`` to vertex ``k + 1`` (mod ``N``).
"""
from __future__ import annotations

import numpy as np


def polygon_area(poly: np.ndarray) -> float:
    """Signed area (positive for counter-clockwise) by the shoelace formula."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def edge_vectors(poly: np.ndarray) -> np.ndarray:
    """``(N, 2)`` edge vectors ``p[k+1] - p[k]``."""
    return np.roll(poly, -1, axis=0) - poly


def edge_lengths(poly: np.ndarray) -> np.ndarray:
    return np.linalg.norm(edge_vectors(poly), axis=1)


def turn_angles_deg(poly: np.ndarray) -> np.ndarray:
    """``(N,)`` unsigned angle (degrees) between the directions of edge ``k-1`` and edge ``k``.

    90 at every Manhattan corner (convex or concave); the angle between consecutive walls as
    Table A.2 ("walls angle") limits it.
    """
    e = edge_vectors(poly)
    e = e / np.linalg.norm(e, axis=1, keepdims=True)
    prev = np.roll(e, 1, axis=0)
    cosang = np.clip(np.sum(prev * e, axis=1), -1.0, 1.0)
    return np.degrees(np.arccos(cosang))


def cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def segments_intersect(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray,
                       eps: float = 1e-9) -> np.ndarray:
    """Broadcast test whether segments ``p1-p2`` and ``q1-q2`` (``(..., 2)``) properly cross or touch."""
    d1 = cross2(q2 - q1, p1 - q1)
    d2 = cross2(q2 - q1, p2 - q1)
    d3 = cross2(p2 - p1, q1 - p1)
    d4 = cross2(p2 - p1, q2 - p1)
    proper = (((d1 > eps) & (d2 < -eps)) | ((d1 < -eps) & (d2 > eps))) & \
             (((d3 > eps) & (d4 < -eps)) | ((d3 < -eps) & (d4 > eps)))
    return proper


def is_simple(poly: np.ndarray) -> bool:
    """True when no two non-adjacent edges intersect (and no edge is degenerate)."""
    n = len(poly)
    if n < 3 or np.any(edge_lengths(poly) < 1e-9):
        return False
    a, b = poly, np.roll(poly, -1, axis=0)
    hit = segments_intersect(a[:, None], b[:, None], a[None], b[None])
    idx = np.arange(n)
    adjacent = (np.abs(idx[:, None] - idx[None]) <= 1) | (np.abs(idx[:, None] - idx[None]) == n - 1)
    return not bool(np.any(hit & ~adjacent))


def points_in_polygon(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """``(K,)`` bool: even-odd rule for ``points (K, 2)``."""
    x, y = points[:, None, 0], points[:, None, 1]
    a, b = poly[None], np.roll(poly, -1, axis=0)[None]
    cond = (a[..., 1] > y) != (b[..., 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = a[..., 0] + (y - a[..., 1]) * (b[..., 0] - a[..., 0]) / (b[..., 1] - a[..., 1])
    crossings = cond & (x < xint)
    return (np.sum(crossings, axis=1) % 2) == 1


def distance_to_edges(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """``(K,)`` smallest distance from each point to the polygon's edges."""
    a = poly[None]
    e = edge_vectors(poly)[None]
    p = points[:, None]
    s = np.clip(np.sum((p - a) * e, -1) / np.maximum(np.sum(e * e, -1), 1e-12), 0.0, 1.0)
    closest = a + s[..., None] * e
    return np.min(np.linalg.norm(p - closest, axis=-1), axis=1)


def rect_corners(center: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
    """``(4, 2)`` counter-clockwise corners of a rectangle (centre, half sizes along its local x/y, yaw)."""
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * half[None]
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + center[None]


def polygons_overlap(p: np.ndarray, q: np.ndarray) -> bool:
    """Overlap test for two simple polygons (edges cross, or a vertex of one lies inside the other)."""
    pa, pb = p, np.roll(p, -1, axis=0)
    qa, qb = q, np.roll(q, -1, axis=0)
    if np.any(segments_intersect(pa[:, None], pb[:, None], qa[None], qb[None])):
        return True
    return bool(np.any(points_in_polygon(p, q)) or np.any(points_in_polygon(q, p)))


def polygon_inside(inner: np.ndarray, outer: np.ndarray) -> bool:
    """``inner`` lies inside ``outer`` (no edge crossings, its vertices inside, no outer vertex inside it)."""
    if not np.all(points_in_polygon(inner, outer)):
        return False
    ia, ib = inner, np.roll(inner, -1, axis=0)
    oa, ob = outer, np.roll(outer, -1, axis=0)
    if np.any(segments_intersect(ia[:, None], ib[:, None], oa[None], ob[None])):
        return False
    return not bool(np.any(points_in_polygon(outer, inner)))


def remove_collinear(poly: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Drop vertices where the boundary goes straight on."""
    keep = []
    n = len(poly)
    for k in range(n):
        a, b, c = poly[k - 1], poly[k], poly[(k + 1) % n]
        if abs(cross2(b - a, c - b)) > tol * max(1.0, np.linalg.norm(b - a) * np.linalg.norm(c - b)):
            keep.append(k)
    return poly[keep]
