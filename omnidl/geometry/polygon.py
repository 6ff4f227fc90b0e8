"""2-D polygons and rays in the plane (NumPy, float64): areas, predicates, clipping and ray hits.

The one home of the top-view geometry used by the floor-plan generator (:mod:`omnidl.synth`), the
layout pipeline (:mod:`omnidl.postprocess.layout`), its ground truth (:mod:`omnidl.data`) and the
layout metrics (:mod:`omnidl.metrics.layout`).

Conventions:

- A polygon is an ``(N, 2)`` vertex array without a repeated last vertex; edge ``k`` goes from
  vertex ``k`` to vertex ``k + 1`` (mod ``N``). Counter-clockwise (seen from above, z up) has a
  positive signed area. Functions that need an orientation say so; the others accept both.
- A 2-D ray is ``origin + s * direction`` with ``s > 0``; ``direction`` need not be unit, ranges
  ``s`` are then in units of its length.
- A line in normal form ``(theta, d)`` is ``{p : n . p = d}`` with ``n = (-sin theta, cos theta)``,
  the left normal of the direction ``(cos theta, sin theta)``; this is the wall-line form of the
  layout solvers (``d > 0``: the normal points from the camera to the wall).

Intersections of general simple polygons use the signed fan decomposition:
``area(P ∩ Q) = sum_e sum_f s_e s_f area(T_e ∩ T_f)``, ``T_e`` the triangle (common origin, edge
``e``) with orientation sign ``s_e``, every convex ``T_e ∩ T_f`` clipped with Sutherland–Hodgman.
"""
from __future__ import annotations

import numpy as np

# ---------------------------------------------------------------------------------------------
# edges and area
# ---------------------------------------------------------------------------------------------


def cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z-component of the cross product of 2-D vectors ``a, b (..., 2)`` (broadcast): ``(...)``."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def polygon_area(poly: np.ndarray) -> float:
    """Signed area of ``poly (N, 2)`` by the shoelace formula: positive counter-clockwise, 0 if ``N < 3``."""
    p = np.asarray(poly, dtype=np.float64)
    if len(p) < 3:
        return 0.0
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def edge_vectors(poly: np.ndarray) -> np.ndarray:
    """``(N, 2)`` edge vectors ``p[k+1] - p[k]``."""
    return np.roll(poly, -1, axis=0) - poly


def edge_lengths(poly: np.ndarray) -> np.ndarray:
    """``(N,)`` edge lengths."""
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


def remove_collinear(poly: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Drop vertices where the boundary goes straight on (relative turn below ``tol``)."""
    keep = []
    n = len(poly)
    for k in range(n):
        a, b, c = poly[k - 1], poly[k], poly[(k + 1) % n]
        if abs(cross2(b - a, c - b)) > tol * max(1.0, np.linalg.norm(b - a) * np.linalg.norm(c - b)):
            keep.append(k)
    return poly[keep]


def rect_corners(center: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
    """``(4, 2)`` counter-clockwise corners of a rectangle (centre, half sizes along its local x/y, yaw)."""
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * half[None]
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + center[None]


# ---------------------------------------------------------------------------------------------
# predicates
# ---------------------------------------------------------------------------------------------

def segments_intersect(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray,
                       eps: float = 1e-9) -> np.ndarray:
    """Whether segments ``p1-p2`` and ``q1-q2`` (``(..., 2)``, broadcast) properly cross: ``(...)`` bool.

    Proper crossing: each segment's end points lie strictly on both sides of the other's line,
    by more than ``eps`` in the orientation determinant. Touching, collinear overlap and shared
    end points do not count (``eps = 0`` gives the exact sign test).
    """
    d1 = cross2(q2 - q1, p1 - q1)
    d2 = cross2(q2 - q1, p2 - q1)
    d3 = cross2(p2 - p1, q1 - p1)
    d4 = cross2(p2 - p1, q2 - p1)
    return (((d1 > eps) & (d2 < -eps)) | ((d1 < -eps) & (d2 > eps))) & \
        (((d3 > eps) & (d4 < -eps)) | ((d3 < -eps) & (d4 > eps)))


def is_simple(poly: np.ndarray, eps: float = 1e-9) -> bool:
    """True when ``N >= 3``, no edge is shorter than ``eps`` and no two non-adjacent edges cross.

    Crossings are proper crossings as in :func:`segments_intersect` with the same ``eps``
    (``eps = 0``: exact signs, zero-length edges allowed).
    """
    n = len(poly)
    if n < 3 or np.any(edge_lengths(poly) < eps):
        return False
    a, b = poly, np.roll(poly, -1, axis=0)
    hit = segments_intersect(a[:, None], b[:, None], a[None], b[None], eps)
    idx = np.arange(n)
    gap = np.abs(idx[:, None] - idx[None])
    adjacent = (gap <= 1) | (gap == n - 1)
    return not bool(np.any(hit & ~adjacent))


def points_in_polygon(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """``(K,)`` bool: ``points (K, 2)`` inside ``poly`` by the even–odd rule (crossings to the right)."""
    points = np.asarray(points, dtype=np.float64)
    x, y = points[:, None, 0], points[:, None, 1]
    a, b = poly[None], np.roll(poly, -1, axis=0)[None]
    cond = (a[..., 1] > y) != (b[..., 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = a[..., 0] + (y - a[..., 1]) * (b[..., 0] - a[..., 0]) / (b[..., 1] - a[..., 1])
    crossings = cond & (x < xint)
    return (np.sum(crossings, axis=1) % 2) == 1


def distance_to_edges(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """``(K,)`` smallest Euclidean distance from each of ``points (K, 2)`` to the polygon's edges."""
    a = poly[None]
    e = edge_vectors(poly)[None]
    p = points[:, None]
    s = np.clip(np.sum((p - a) * e, -1) / np.maximum(np.sum(e * e, -1), 1e-12), 0.0, 1.0)
    closest = a + s[..., None] * e
    return np.min(np.linalg.norm(p - closest, axis=-1), axis=1)


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


# ---------------------------------------------------------------------------------------------
# intersection area (exact, simple polygons of any orientation)
# ---------------------------------------------------------------------------------------------

def _ring_area(ring: list[tuple[float, float]]) -> float:
    """Signed shoelace area of a short vertex list (the clipper's scalar form of :func:`polygon_area`)."""
    n = len(ring)
    if n < 3:
        return 0.0
    s = 0.0
    for i in range(n):
        x1, y1 = ring[i]
        x2, y2 = ring[(i + 1) % n]
        s += x1 * y2 - x2 * y1
    return 0.5 * s


def clip_convex(subject: list[tuple[float, float]], clip: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Sutherland–Hodgman: the part of polygon ``subject`` inside the convex counter-clockwise ``clip``.

    Both are vertex lists ``[(x, y), ...]``; returns the clipped vertex list (empty if disjoint).
    """
    out = subject
    n = len(clip)
    for i in range(n):
        if not out:
            break
        a, b = clip[i], clip[(i + 1) % n]
        ex, ey = b[0] - a[0], b[1] - a[1]
        inp = out
        out = []
        m = len(inp)
        for j in range(m):
            p, q = inp[j], inp[(j + 1) % m]
            sp = ex * (p[1] - a[1]) - ey * (p[0] - a[0])
            sq = ex * (q[1] - a[1]) - ey * (q[0] - a[0])
            if sp >= 0:
                out.append(p)
            if (sp >= 0) != (sq >= 0):
                t = sp / (sp - sq)
                out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def _fan(poly: np.ndarray) -> list[tuple[float, list[tuple[float, float]]]]:
    """Non-degenerate fan triangles (origin, edge ``k``) as ``(sign, counter-clockwise vertex list)``."""
    pts = poly.tolist()
    out = []
    for i in range(len(pts)):
        tri = [(0.0, 0.0), tuple(pts[i]), tuple(pts[(i + 1) % len(pts)])]
        a = _ring_area(tri)
        if a != 0:
            out.append((1.0, tri) if a > 0 else (-1.0, tri[::-1]))
    return out


def polygon_intersection_area(p: np.ndarray, q: np.ndarray) -> float:
    """Exact area of the intersection of two simple polygons ``(N, 2)``, ``(M, 2)`` (any orientation)."""
    p, q = np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64)
    if len(p) < 3 or len(q) < 3:
        return 0.0
    c = p.mean(0)                         # fan origin at a common point keeps the triangles small
    p, q = p - c, q - c
    fq = _fan(q)
    total = 0.0
    for sp, tp in _fan(p):
        for sq, tq in fq:
            total += sp * sq * _ring_area(clip_convex(tp, tq))
    sign = np.sign(polygon_area(p)) * np.sign(polygon_area(q))
    return float(abs(total) if sign != 0 else 0.0)


# ---------------------------------------------------------------------------------------------
# 2-D rays against lines and polygon edges
# ---------------------------------------------------------------------------------------------

def ray_line_range(theta, d, origin: np.ndarray, direction: np.ndarray, eps: float = 1e-12,
                   facing: bool = False) -> np.ndarray:
    """Range ``s`` at which rays ``origin + s * direction`` (``(..., 2)``) meet the line ``(theta, d)``.

    ``theta, d`` broadcast against the rays' batch shape. NaN where the ray is parallel to the
    line (``|n . direction| <= eps``). With ``facing=True`` NaN also unless the ray runs towards
    the line along its normal (``n . direction > eps``) and meets it ahead (``s > 0``): a camera
    column that sees the front of a wall.
    """
    nx, ny = -np.sin(theta), np.cos(theta)
    nb = nx * direction[..., 0] + ny * direction[..., 1]
    no = nx * origin[..., 0] + ny * origin[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (d - no) / nb
    if facing:
        return np.where((nb > eps) & (s > 0), s, np.nan)
    return np.where(np.abs(nb) > eps, s, np.nan)


def ray_polygon_hit(poly: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First edge of ``poly (N, 2)`` hit by each ray ``origin + s * direction`` (``(M, 2)`` each, ``s > 0``).

    Returns the range ``s (M,)`` (``inf`` where the ray hits nothing) and the edge index ``(M,)``
    (0 where nothing is hit). Edges include their end points (to ``1e-12`` of the edge parameter).
    """
    a = poly
    e = np.roll(poly, -1, 0) - poly                     # (N, 2)
    # origin + s b = a + t e  ->  s b - t e = a - origin, solved by Cramer's rule
    den = direction[:, None, 0] * (-e[None, :, 1]) - direction[:, None, 1] * (-e[None, :, 0])
    r = a[None] - origin[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (r[..., 0] * (-e[None, :, 1]) - r[..., 1] * (-e[None, :, 0])) / den
        t = (direction[:, None, 0] * r[..., 1] - direction[:, None, 1] * r[..., 0]) / den
    ok = (np.abs(den) > 1e-12) & (s > 1e-9) & (t >= -1e-12) & (t <= 1 + 1e-12)
    s = np.where(ok, s, np.inf)
    k = np.argmin(s, 1)
    return s[np.arange(len(s)), k], k
