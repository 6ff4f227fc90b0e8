"""Manhattan branch of the layout pipeline (thesis §5.4.2 and §5.4.4, Fig. 5.5).

The room orientation is estimated (4-fold circular mean of the wall directions), every wall gets a
Manhattan label (0: along ``u``, 1: along ``u_perp``), runs of short walls between fitted walls get
alternating labels when consistent, the Manhattan layout solver (Eq. 5.8; without moments for a
central panorama) gives one direction, the shared heights and every wall offset, and coplanar
neighbours are merged. Two consecutive walls with the same label reveal an occluded wall, inserted
perpendicular through the nearer corner-ray point (exact: the hidden wall goes through the visible
occluding corner); two perpendicular walls whose intersection is off their corner ray hide two or
more walls, closed by the smallest consistent room (unobservable).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from .assemble import assemble, corner_points, far_from_ray
from .corners import line_intersection
from .directions import manhattan_labels, manhattan_orientation
from .rays import ColumnRays
from .solvers import manhattan_rows, solve_manhattan, solve_manhattan_central
from .walls import keep_walls, merge_walls, ray_arrays

if TYPE_CHECKING:
    from .pipeline import LayoutOptions


def manhattan_layout(rays: ColumnRays, corners_u: np.ndarray, theta: np.ndarray, good: np.ndarray,
                     cols: list[np.ndarray], opt: LayoutOptions, camera_height: float | None) -> tuple | str:
    """The Manhattan branch: labels, the Manhattan solver (Eq. 5.8), merges, occlusions, corners.

    Args:
        rays: the panorama's column rays.
        corners_u: ``(N,)`` corner columns; wall ``k`` starts at ``corners_u[k]``.
        theta: ``(N,)`` wall directions (NaN where unknown), ``good``: ``(N,)`` walls fitted by RANSAC.
        cols: each wall's column indices; ``opt``: :class:`~.pipeline.LayoutOptions`.
        camera_height: central panoramas only (scale from ``h_f = -camera_height``), else ``None``.
    Returns:
        ``(verts (M, 2), occluded (M,), h_c, h_f, problem, info)`` or the reason of a failure (str).
    """
    n = len(theta)
    weight = np.array([len(c) if g else 0 for c, g in zip(cols, good)], float)
    theta0 = manhattan_orientation(theta, weight)
    own = np.where(np.isfinite(theta), manhattan_labels(np.nan_to_num(theta), theta0), -1)
    label = np.where(good, own, -1)
    # runs of short walls between two fitted walls: alternating labels when the run's length is
    # consistent with its neighbours, otherwise each short wall's own top-view direction decides
    keep = np.ones(n, bool)
    k0 = int(np.flatnonzero(good)[0])
    k = 0
    while k < n:
        i = (k0 + k) % n
        if label[i] >= 0:
            k += 1
            continue
        run = []
        while label[(k0 + k) % n] < 0 and k < n:
            run.append((k0 + k) % n)
            k += 1
        lp, ln = label[(run[0] - 1) % n], label[(run[-1] + 1) % n]
        alt = [(1 - lp) if j % 2 == 0 else lp for j in range(len(run))]
        if alt[-1] != ln:
            for r in run:
                label[r] = alt[run.index(r)]
        else:
            for r in run:
                label[r] = own[r]
        for r in run:
            if label[r] < 0 or len(cols[r]) < 2:
                keep[r] = False
    if (~keep).any():
        # dropping wall k merges its columns into nothing: remove it and its starting corner
        cols, corners_u, theta, good, label = keep_walls(keep, cols, corners_u, theta, good, label)
        n = len(cols)
    for _ in range(n):
        if n < 3:
            return f"only {n} walls remain after removing unfittable short walls"
        A = manhattan_rows(*ray_arrays(rays, np.concatenate(cols)), label, np.concatenate(
            [np.full(len(c), k) for k, c in enumerate(cols)]), n)
        if camera_height is not None:
            th0, d, h_c, h_f, ok = solve_manhattan_central(A, camera_height)
        else:
            th0, d, h_c, h_f, ok = solve_manhattan(A, label)
        if not ok:
            return "the Manhattan layout solver found no solution with the ceiling above the floor"
        th = np.where(label == 0, th0, th0 + math.pi / 2)
        # coplanar consecutive walls (same label and offset): a spurious corner -> merge
        pairs = [k for k in range(n) if label[k] == label[(k + 1) % n]
                 and abs(d[k] - d[(k + 1) % n]) < opt.merge_distance]
        if not pairs:
            break
        cols, th_tmp, corners_u, good = merge_walls(cols, th, good, corners_u, pairs[:1])
        label = np.array([label[k] for k in range(n) if k != (pairs[0] + 1) % n])
        n = len(cols)
    transitions = []
    n_occ = 0
    for k in range(n):
        j = (k + 1) % n
        if label[k] != label[j]:
            X = line_intersection(th[k], d[k], th[j], d[j])
            P1, P2, s1, s2 = corner_points(rays, corners_u[j], th[k], d[k], th[j], d[j])
            if not far_from_ray(X, P1, P2, s1, s2, corners_u[j], rays, opt):
                transitions.append([(X, False)])
                continue
            # two hidden walls behind the corner ray: one parallel to wall j through wall k's ray point
            # and one parallel to wall k through wall j's ray point (the smallest room that fits)
            dk = -math.sin(th[j]) * P1[0] + math.cos(th[j]) * P1[1]
            dj = -math.sin(th[k]) * P2[0] + math.cos(th[k]) * P2[1]
            Q = line_intersection(th[j], dk, th[k], dj)
            transitions.append([(P1, bool(s1 > s2)), (Q, True, False), (P2, bool(s2 > s1))])
            n_occ += 1
            continue
        # occlusion: insert a perpendicular wall through the nearer corner-ray point
        P1, P2, s1, s2 = corner_points(rays, corners_u[j], th[k], d[k], th[j], d[j])
        if not (np.isfinite(s1) and np.isfinite(s2)):
            return "an occluded corner ray does not meet its walls"
        th_perp = th[k] + math.pi / 2
        if s1 < s2:   # wall k is in front: its end is seen, the hidden wall starts there
            near, far_th, far_d = P1, th[j], d[j]
            dp = -math.sin(th_perp) * near[0] + math.cos(th_perp) * near[1]
            Q = line_intersection(th_perp, dp, far_th, far_d)
            transitions.append([(P1, False), (Q, True, False)])   # Q: hidden, off the corner ray
        else:
            near = P2
            dp = -math.sin(th_perp) * near[0] + math.cos(th_perp) * near[1]
            Q = line_intersection(th_perp, dp, th[k], d[k])
            transitions.append([(Q, True, False), (P2, False)])
        n_occ += 1
    verts, occl, problem = assemble(rays, corners_u, th, d, cols, transitions, opt, manhattan=True)
    return verts, occl, h_c, h_f, problem, {"n_occlusions": n_occ, "orientation_deg": math.degrees(th0)}
