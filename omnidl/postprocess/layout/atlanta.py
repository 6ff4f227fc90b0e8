"""Atlanta branch of the layout pipeline (thesis §5.4.3 and §5.4.4, Fig. 5.6).

Wall directions come from RANSAC (or the top view at the shared heights); the Atlanta solver
(Eq. 5.9) gives the heights and every offset; short walls get their line from the top-view boundary
points at the solved heights; coplanar neighbours are merged and every wall re-solved jointly.
Corners are the closest points between the wall lines and the corner rays; two distinct points on
one corner ray reveal an occluded wall coplanar with that ray (Fig. 5.6).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from .assemble import assemble, corner_points, far_from_ray
from .corners import line_intersection, wrap_angle
from .rays import ColumnRays
from .solvers import atlanta_rows, solve_atlanta
from .walls import keep_walls, merge_walls, ray_arrays, topview_wall_line

if TYPE_CHECKING:
    from .pipeline import LayoutOptions


def atlanta_layout(rays: ColumnRays, corners_u: np.ndarray, theta: np.ndarray, good: np.ndarray,
                   cols: list[np.ndarray], opt: LayoutOptions, camera_height: float | None) -> tuple | str:
    """The Atlanta branch: the Atlanta solver (Eq. 5.9), short walls, merges, occlusions, corners.

    Arguments and result as :func:`~.manhattan.manhattan_layout` (``theta`` is updated in place for
    the short walls).
    """
    n = len(theta)
    use = np.flatnonzero(good)

    def solve(th, walls_idx, c):
        idx = np.concatenate([c[k] for k in walls_idx])
        wall = np.concatenate([np.full(len(c[k]), j) for j, k in enumerate(walls_idx)])
        A = atlanta_rows(*ray_arrays(rays, idx), th[walls_idx], wall, len(walls_idx))
        return solve_atlanta(A, fix_h_f=None if camera_height is None else -camera_height)

    h_c, h_f, d_use, ok = solve(theta, use, cols)
    if not ok:
        return "the Atlanta layout solver found no solution with the ceiling above the floor"
    d = np.full(n, np.nan)
    d[use] = d_use
    for k in np.flatnonzero(~good):
        theta[k], d[k] = topview_wall_line(rays, cols[k], h_c, h_f)
    keep = np.isfinite(theta) & np.isfinite(d)
    if keep.sum() < 3:
        return f"only {int(keep.sum())} walls could be located"
    if (~keep).any():
        cols, corners_u, theta, d, good = keep_walls(keep, cols, corners_u, theta, d, good)
        n = len(cols)
    # merge coplanar neighbours (spurious corners)
    for _ in range(n):
        pairs = []
        for k in range(n):
            j = (k + 1) % n
            dth = abs(wrap_angle(theta[k] - theta[j]))
            if dth < math.radians(opt.merge_angle_deg) and abs(d[k] - d[j]) < opt.merge_distance:
                pairs.append(k)
        if not pairs or n <= 3:
            break
        k = pairs[0]
        cols, theta, corners_u, good = merge_walls(cols, theta, good, corners_u, [k])
        d = np.delete(d, (k + 1) % n)
        n = len(cols)
    # re-solve every wall jointly with the directions fixed
    h_c, h_f, d_all, ok = solve(theta, np.arange(n), cols)
    if ok:
        d = d_all
    transitions = []
    n_occ = 0
    for k in range(n):
        j = (k + 1) % n
        P1, P2, s1, s2 = corner_points(rays, corners_u[j], theta[k], d[k], theta[j], d[j])
        X = line_intersection(theta[k], d[k], theta[j], d[j])
        occluded = far_from_ray(X, P1, P2, s1, s2, corners_u[j], rays, opt)
        if not occluded:
            transitions.append([(X, False)])
            continue
        if not (np.isfinite(s1) and np.isfinite(s2) and s1 > 0 and s2 > 0):
            return "an occluded corner ray does not meet its walls in front of the camera"
        # Fig. 5.6: the hidden wall lies in the plane of the corner rays; the visible one of the
        # two points is the nearer, the other is a corner of the partially occluded wall
        transitions.append([(P1, s1 > s2), (P2, s2 > s1)])
        n_occ += 1
    verts, occl, problem = assemble(rays, corners_u, theta, d, cols, transitions, opt, manhattan=False)
    return verts, occl, h_c, h_f, problem, {"n_occlusions": n_occ}
