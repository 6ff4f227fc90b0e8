"""Per-wall bookkeeping shared by the Manhattan and Atlanta branches of :mod:`.pipeline`.

A wall is the set of columns between two consecutive corner columns (``cols[k]``, column indices
into :class:`~.rays.ColumnRays`); its line in top view is ``(theta, d)`` as in :mod:`.solvers`
(``{p : (-sin theta, cos theta) . p = d}``). Heights ``h_c > 0 > h_f`` are relative to the camera
circle. Here: the shared heights of all walls, the top-view line of a wall at known heights, the
ray arrays of a set of columns, and merging/dropping walls with their starting corners.
"""
from __future__ import annotations

import math

import numpy as np

from ...geometry.polygon import ray_line_range
from .corners import wrap_angle
from .rays import ColumnRays


def weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    """Weighted median of ``x (n,)`` with weights ``w (n,)`` (non-finite ``x`` and ``w <= 0`` ignored; NaN if none)."""
    x, w = np.asarray(x, float), np.asarray(w, float)
    ok = np.isfinite(x) & (w > 0)
    if not ok.any():
        return math.nan
    o = np.argsort(x[ok])
    cw = np.cumsum(w[ok][o])
    return float(x[ok][o][np.searchsorted(cw, 0.5 * cw[-1])])


def shared_heights(rays: ColumnRays, cand_c: np.ndarray, cand_f: np.ndarray, wall_cols: list[np.ndarray],
                   thr: float) -> tuple[float, float]:
    """The candidate heights ``(h_c, h_f)`` that explain the boundaries of *all* walls best.

    A single wall constrains the scale weakly (a wall close to the rig circle seen through rounded
    boundaries can fit a collapsed, much smaller room almost as well), so the per-wall RANSAC heights
    are only candidates. For each candidate every wall gets its top-view total-least-squares line at
    those heights (as :func:`topview_wall_line`), and the candidate with the smallest truncated
    quadratic re-projection cost over all walls' columns (MSAC, threshold ``thr`` radians) wins.
    """
    ok = np.isfinite(cand_c) & np.isfinite(cand_f) & (cand_c > 0) & (cand_f < 0)
    cand_c, cand_f = np.asarray(cand_c, float)[ok], np.asarray(cand_f, float)[ok]
    if len(cand_c) <= 1:
        return (float(cand_c[0]), float(cand_f[0])) if len(cand_c) else (math.nan, math.nan)
    idx = np.concatenate(wall_cols)
    wall = np.concatenate([np.full(len(c), k) for k, c in enumerate(wall_cols)])
    n_w = len(wall_cols)
    lat_c, lat_f = rays.elevations()
    o, b = rays.origin[idx, :2], rays.horizontal[idx]
    tc, tf = np.tan(lat_c[idx]), np.tan(lat_f[idx])
    K = len(cand_c)
    # top-view points of every column at every candidate's heights: (K, 2n, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.concatenate([cand_c[:, None] / tc[None], cand_f[:, None] / tf[None]], 1)
    use = np.isfinite(s) & (s > 0)
    oo, bb, ww = np.concatenate([o, o]), np.concatenate([b, b]), np.concatenate([wall, wall])
    P = oo[None] + np.where(use, s, 0.0)[..., None] * bb[None]
    wgt = use.astype(float)
    key = (np.arange(K)[:, None] * n_w + ww[None]).ravel()

    def wsum(v):
        return np.bincount(key, (wgt * v).ravel(), minlength=K * n_w).reshape(K, n_w)
    cnt = np.maximum(wsum(np.ones_like(wgt)), 1e-12)
    mx, my = wsum(P[..., 0]) / cnt, wsum(P[..., 1]) / cnt
    sxx = wsum(P[..., 0] ** 2) / cnt - mx ** 2
    syy = wsum(P[..., 1] ** 2) / cnt - my ** 2
    sxy = wsum(P[..., 0] * P[..., 1]) / cnt - mx * my
    th = 0.5 * np.arctan2(2 * sxy, sxx - syy)                       # principal direction of each wall
    d = -np.sin(th) * mx + np.cos(th) * my                          # (K, n_w)
    # re-projection of every column on its wall's line at the candidate heights
    rng_ = ray_line_range(th[:, wall], d[:, wall], o[None], b[None], eps=0.0)    # (K, n)
    with np.errstate(invalid="ignore"):
        ec = np.abs(np.arctan2(cand_c[:, None], rng_) - lat_c[idx][None])
        ef = np.abs(np.arctan2(cand_f[:, None], rng_) - lat_f[idx][None])
    e2 = np.where(np.isfinite(ec) & (rng_ > 0), np.minimum(ec, thr) ** 2, thr ** 2) + \
        np.where(np.isfinite(ef) & (rng_ > 0), np.minimum(ef, thr) ** 2, thr ** 2)
    k = int(np.argmin(e2.sum(1)))
    return float(cand_c[k]), float(cand_f[k])


def topview_wall_line(rays: ColumnRays, c: np.ndarray, h_c: float, h_f: float) -> tuple[float, float]:
    """Top-view line ``(theta, d)`` through the boundary points of columns ``c`` at known heights.

    Total least squares on the ceiling and floor boundary points placed at heights ``h_c``/``h_f``;
    ``d >= 0``. NaNs when fewer than two columns or points.
    """
    if len(c) < 2:
        return math.nan, math.nan
    lat_c, lat_f = rays.elevations()
    o, b = rays.origin[c, :2], rays.horizontal[c]
    pts = []
    for h, lat in ((h_c, lat_c[c]), (h_f, lat_f[c])):
        with np.errstate(divide="ignore", invalid="ignore"):
            s = h / np.tan(lat)
        ok = np.isfinite(s) & (s > 0)
        pts.append(o[ok] + s[ok, None] * b[ok])
    P = np.concatenate(pts)
    if len(P) < 2:
        return math.nan, math.nan
    mu = P.mean(0)
    Q = P - mu
    _, V = np.linalg.eigh(Q.T @ Q)                   # 2x2 scatter: principal direction = largest eigenvector
    u = V[:, 1]
    th = math.atan2(u[1], u[0])
    n = np.array([-u[1], u[0]])
    d = float(n @ mu)
    if d < 0:
        th, d = th + math.pi, -d
    return float(wrap_angle(th)), d


def ray_arrays(rays: ColumnRays, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ceiling directions, ceiling moments, floor directions, floor moments ``(n, 3)`` of columns ``idx``."""
    return rays.ceiling[idx], rays.moments("ceiling")[idx], rays.floor[idx], rays.moments("floor")[idx]


def keep_walls(keep: np.ndarray, cols: list[np.ndarray], *per_wall: np.ndarray) -> tuple:
    """``(cols, *per_wall)`` restricted to the walls where ``keep`` is true (each wall with its starting corner)."""
    idx = np.flatnonzero(keep)
    return ([cols[k] for k in idx], *(a[idx] for a in per_wall))


def merge_walls(cols: list[np.ndarray], theta: np.ndarray, keep_mask: np.ndarray, corners_u: np.ndarray,
                merge_pairs: list[int]) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """Merge walls ``k`` and ``k+1`` for every ``k`` in ``merge_pairs`` (drop corner ``k+1``).

    Returns the merged ``(cols, theta, corners_u, keep_mask)``; a merged wall keeps the direction,
    starting corner and flag of its first part.
    """
    n = len(cols)
    drop = set((k + 1) % n for k in merge_pairs)
    new_cols, new_theta, new_u, new_good = [], [], [], []
    for k in range(n):
        if k in drop:
            continue
        c = [cols[k]]
        j = (k + 1) % n
        while j in drop and j != k:
            c.append(cols[j])
            j = (j + 1) % n
        new_cols.append(np.concatenate(c))
        new_theta.append(theta[k])
        new_u.append(corners_u[k])
        new_good.append(keep_mask[k])
    return new_cols, np.array(new_theta), np.array(new_u), np.array(new_good, bool)
