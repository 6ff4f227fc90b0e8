"""Corner assembly (thesis §5.4.4): wall lines + corner rays -> polygon, occlusions, adjustment problem.

Both branches of :mod:`.pipeline` end here. Wall ``k`` (line ``(theta_k, d_k)``, columns
``cols[k]``) runs from corner column ``corners_u[k]`` to ``corners_u[k+1]``. The corner ray of a
continuous column ``u`` is, in top view, the 2-D ray ``o + s b`` (optical centre, horizontal
direction of the column); a corner of a wall line is where that ray meets the line. When the two
walls' lines meet far from their corner ray, a wall is hidden there (an occlusion).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ...geometry.polygon import ray_line_range
from .adjust import AdjustProblem
from .corners import azimuth, wrap_angle
from .rays import ColumnRays

if TYPE_CHECKING:
    from .pipeline import LayoutOptions


def pixel_angles(rays: ColumnRays) -> tuple[float, float]:
    """Radians per pixel of the panorama: ``(latitude per row, azimuth per column)``."""
    return math.pi / rays.height, 2 * math.pi / rays.width


def corner_ray(rays: ColumnRays, u: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Top-view corner ray of continuous column ``u``: optical centre ``(2,)``, direction ``(2,)``, azimuth."""
    o, b = rays.column(u)
    return o, b, float(azimuth(b))


def corner_points(rays: ColumnRays, u: float, th1, d1, th2, d2):
    """Closest points of two wall lines to the corner ray of column ``u`` (top view) and their ranges.

    Returns ``(P1 (2,), P2 (2,), s1, s2)``: the points of lines 1 and 2 on the ray and the ranges
    along it (NaN where a line is parallel to the ray).
    """
    o, b, _ = corner_ray(rays, u)
    s1 = ray_line_range(th1, d1, o, b)
    s2 = ray_line_range(th2, d2, o, b)
    return o + s1 * b, o + s2 * b, s1, s2


def far_from_ray(X, P1, P2, s1, s2, u: float, rays: ColumnRays, opt: LayoutOptions) -> bool:
    """True when the wall lines' intersection ``X`` is not where the corner ray of ``u`` says (an occlusion)."""
    if not np.all(np.isfinite(X)):
        return True
    if not (np.isfinite(s1) and np.isfinite(s2)):
        return False
    sep = float(np.linalg.norm(P1 - P2))
    az_gap = abs(float(wrap_angle(azimuth(X) - corner_ray(rays, u)[2])))
    return sep > max(opt.occlusion_distance, opt.occlusion_relative * min(s1, s2)) \
        and az_gap > opt.occlusion_azimuth * pixel_angles(rays)[1]


def adjust_problem(rays: ColumnRays, seg_cols: list[np.ndarray | None], corner_az: np.ndarray,
                   corner_w: np.ndarray, opt: LayoutOptions, manhattan: bool,
                   s_init: list[np.ndarray | None]) -> AdjustProblem:
    """The final adjustment's problem (:mod:`.adjust`): segment ``m`` observed by columns ``seg_cols[m]``.

    ``None`` segments are hidden walls. Columns are subsampled uniformly to at most about
    ``opt.adjust_max_columns``; ``corner_az``/``corner_w`` are each vertex's corner-ray azimuth
    (NaN: off any ray) and weight, ``s_init`` the initial ranges of each segment's columns.
    """
    seg, idx, s0 = [], [], []
    total = sum(len(c) for c in seg_cols if c is not None)
    stride = max(1, int(math.ceil(total / max(opt.adjust_max_columns, 1))))
    for m, c in enumerate(seg_cols):
        if c is None or len(c) == 0:
            continue
        keep = slice(None, None, stride) if len(c) >= 4 * stride else slice(None)
        c = c[keep]
        if s_init[m] is not None:
            s_init[m] = s_init[m][keep]
        seg.append(np.full(len(c), m))
        idx.append(c)
        s0.append(s_init[m] if s_init[m] is not None else np.ones(len(c)))
    seg = np.concatenate(seg)
    idx = np.concatenate(idx)
    lat_c, lat_f = rays.elevations()
    pix_lat, pix_az = pixel_angles(rays)
    return AdjustProblem(seg=seg, origin2=rays.origin[idx, :2], b=rays.horizontal[idx], lat_c=lat_c[idx],
                         lat_f=lat_f[idx], dir_c=rays.ceiling[idx], mom_c=rays.moments("ceiling")[idx],
                         dir_f=rays.floor[idx], mom_f=rays.moments("floor")[idx], corner_az=corner_az,
                         corner_w=corner_w, n_corners=len(seg_cols), pix_lat=pix_lat, pix_az=pix_az,
                         side_weight=opt.side_weight, manhattan_weight=opt.manhattan_weight if manhattan else 0.0,
                         s0=np.concatenate(s0))


def assemble(rays: ColumnRays, corners_u: np.ndarray, th: np.ndarray, d: np.ndarray, cols: list[np.ndarray],
             transitions: list[list[tuple]], opt: LayoutOptions,
             manhattan: bool) -> tuple[np.ndarray, np.ndarray, AdjustProblem]:
    """Vertices ``(M, 2)``, occlusion flags ``(M,)`` and the adjustment problem from wall lines and transitions.

    ``transitions[k]`` describes the corner between wall ``k`` and ``k+1``: a list of
    ``(point (2,), occluded[, on_ray])`` tuples (one normal corner, or the points of an occlusion);
    ``on_ray=False`` marks a hidden corner that is not on the corner ray (no out-of-plane penalty).
    The corner between wall ``k`` and ``k+1`` is corner column ``corners_u[k+1]``.
    """
    n = len(th)
    verts, occl, vaz, seg_cols, s_init = [], [], [], [], []
    # vertex order: start with the transition (n-1 -> 0), so wall 0 starts at vertex 0
    order = [n - 1] + list(range(n - 1))
    wall_of_seg = []
    for t in order:
        pts = transitions[t]
        az = corner_ray(rays, corners_u[(t + 1) % n])[2]
        for j, item in enumerate(pts):
            p, oc = item[0], item[1]
            on_ray = item[2] if len(item) > 2 else True
            verts.append(p)
            occl.append(oc)
            vaz.append(az if on_ray else math.nan)
            if j + 1 < len(pts):            # segment inside an occlusion: inserted wall, unobserved
                wall_of_seg.append(None)
        wall_of_seg.append((t + 1) % n)
    # segment m joins vertex m and m+1; the last appended segment (after the final transition) is
    # wall (order[-1] + 1) % n, which closes the loop back to vertex 0
    M = len(verts)
    assert len(wall_of_seg) == M
    for m in range(M):
        k = wall_of_seg[m]
        if k is None:
            seg_cols.append(None)
            s_init.append(None)
            continue
        c = cols[k]
        seg_cols.append(c)
        s = ray_line_range(th[k], d[k], rays.origin[c, :2], rays.horizontal[c])
        s_init.append(np.where(np.isfinite(s), s, 1.0))
    verts = np.array(verts, float)
    occl = np.array(occl, bool)
    w = np.where(occl, opt.occluded_weight, opt.corner_weight)
    problem = adjust_problem(rays, seg_cols, np.array(vaz), w, opt, manhattan, s_init)
    return verts, occl, problem
