"""The full geometric pipeline of thesis §5.4.4 (Fig. 5.5): boundaries + corners -> metric layout.

``estimate_layout(rays, corner_prob, world="manhattan"|"atlanta")``:

1. corner columns = peaks of the corner probability; the columns between consecutive corners
   (minus a margin) form the walls;
2. per-wall RANSAC with the single-wall solver (batched hypotheses) and an inlier refit; the shared
   heights are the per-wall candidate that explains the boundaries of all walls best;
3. Manhattan: the room orientation is estimated (4-fold circular mean), walls labelled, coplanar
   neighbours merged, the Manhattan layout solver (Eq. 5.8) gives one direction, the shared
   heights and every wall offset; two consecutive walls with the same label reveal an occluded
   wall, inserted perpendicular through the nearer corner-ray point (exact: the hidden wall goes
   through the visible occluding corner); two perpendicular walls whose intersection is off their
   corner ray hide two or more walls, closed by the smallest consistent room (unobservable).
   Atlanta: wall directions from RANSAC, the Atlanta solver (Eq. 5.9) gives the heights and the
   offsets; short walls get their line from the top-view boundary points at the solved heights;
   corners are the closest points between the wall lines and the corner rays, and two distinct
   points on one corner ray reveal an occluded wall coplanar with that ray (Fig. 5.6);
4. final bounded least-squares adjustment (:mod:`.adjust`).

Scale comes from the rig radius through the ray moments. With a central camera (``Rc`` below
``min_rc``) the pipeline refuses metric scale unless ``camera_height`` is given (the central
baseline of Table 5.3, which fixes ``h_f = -camera_height``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from .adjust import AdjustProblem, adjust_layout
from .corners import (azimuth, column_ray, find_peaks, line_intersection, ray_line_range, wall_column_ranges,
                      wrap_angle)
from .directions import manhattan_labels, manhattan_orientation
from .layout import Layout
from .rays import ColumnRays
from .ransac import ransac_walls, reprojection_errors
from .solvers import atlanta_rows, manhattan_rows, solve_atlanta, solve_manhattan


@dataclass
class LayoutOptions:
    """Options of :func:`estimate_layout` (thresholds in pixels unless stated)."""

    corner_threshold: float = 0.5        # corner probability peak threshold
    corner_radius: int | None = None     # peak NMS radius (columns), default W/200
    wall_margin: float = 2.0             # columns skipped next to each corner
    min_wall_columns: int = 6            # fewer columns: the wall is "short" (no own RANSAC)
    ransac_threshold: float = 2.0        # inlier threshold (pixels of latitude)
    ransac_p: float = 0.9999             # P of the n_hyp formula
    ransac_outliers: float = 0.3         # eps of the n_hyp formula
    ransac_sample: int = 3               # columns per hypothesis
    merge_distance: float = 0.10         # coplanar neighbours closer than this (metres) are merged
    merge_angle_deg: float = 8.0         # ... and within this angle (Atlanta)
    occlusion_distance: float = 0.20     # metres between corner-ray points that reveal an occlusion
    occlusion_relative: float = 0.05     # ... or this fraction of the corner range
    min_rc: float = 1e-3                 # rig radius (m) below which scale is refused
    refine: str | bool = True            # final adjustment: True, False, "auto" (Atlanta or occlusion)
    side_weight: float = 0.0             # weight of the Plücker side residuals in the adjustment
    directions: str = "tls"              # wall directions: "tls" (top view at shared heights) or "ransac"
    occlusion_azimuth: float = 6.0       # px: a line intersection this far from its corner ray is suspicious
    corner_weight: float = 0.1
    occluded_weight: float = 10.0
    manhattan_weight: float = 50.0
    max_nfev: int = 30
    adjust_max_columns: int = 384        # columns used by the final adjustment (uniform subsample)
    seed: int = 0
    max_range: float = 50.0              # corners farther than this (m) mean a failed solve


def _fail(reason, world, t0, **info):
    return Layout.failed(reason, world=world, time_s=time.perf_counter() - t0, **info)


_CONTROLLER: list = []


def _single_thread_blas():
    """Tiny matrices: BLAS threads only add overhead (and stall badly on a loaded machine)."""
    import contextlib
    try:
        if not _CONTROLLER:
            from threadpoolctl import ThreadpoolController
            _CONTROLLER.append(ThreadpoolController())
        if _CONTROLLER[0] is None:
            return contextlib.nullcontext()
        return _CONTROLLER[0].limit(limits=1, user_api="blas")
    except Exception:  # noqa: BLE001  (optional dependency)
        if not _CONTROLLER:
            _CONTROLLER.append(None)
        return contextlib.nullcontext()


def estimate_layout(rays: ColumnRays, corner_prob: np.ndarray, world: str = "atlanta",
                    camera_height: float | None = None, options: LayoutOptions | None = None,
                    **overrides) -> Layout:
    """Recover a layout; see :func:`_estimate_layout` (run with single-threaded BLAS)."""
    with _single_thread_blas():
        return _estimate_layout(rays, corner_prob, world, camera_height, options, **overrides)


def _estimate_layout(rays: ColumnRays, corner_prob: np.ndarray, world: str = "atlanta",
                     camera_height: float | None = None, options: LayoutOptions | None = None,
                     **overrides) -> Layout:
    """Recover a layout from per-column boundary rays and corner probabilities (never raises on data).

    Args:
        rays: per-column rays (:func:`~.rays.column_rays_from_boundary` / ``..._from_angles``).
        corner_prob: ``(W,)`` wall-wall corner probability per column (after the sigmoid).
        world: ``"manhattan"`` or ``"atlanta"``.
        camera_height: for central panoramas only: camera height above the floor (metres), which
            fixes the scale (``h_f = -camera_height``). Ignored when ``None``.
        options: :class:`LayoutOptions`; ``overrides`` replace single fields.
    """
    t0 = time.perf_counter()
    opt = options or LayoutOptions()
    if overrides:
        opt = LayoutOptions(**{**opt.__dict__, **overrides})
    if world not in ("manhattan", "atlanta"):
        raise ValueError(f"world must be 'manhattan' or 'atlanta', got {world!r}")
    W = rays.width
    prob = np.asarray(corner_prob, float).reshape(-1)
    if prob.shape[0] != W:
        raise ValueError(f"corner probability has {prob.shape[0]} columns, boundaries have {W}")
    if not np.isfinite(prob).any():
        return _fail("corner probabilities are all NaN", world, t0)
    valid = rays.valid.copy()
    if valid.mean() < 0.25:
        return _fail(f"only {int(valid.sum())}/{W} columns have finite boundaries with the ceiling above the floor",
                     world, t0)
    central = camera_height is not None
    if not central:
        rc_eff = float(np.max(np.hypot(rays.origin[:, 0], rays.origin[:, 1]))) if len(rays.origin) else 0.0
        if not rc_eff >= opt.min_rc:
            return _fail(f"rig radius Rc = {rc_eff:.3g} m is below min_rc = {opt.min_rc} m: the panorama is "
                         "(nearly) central and metric scale is unobservable; give camera_height for the central "
                         "pipeline", world, t0)
    elif not camera_height > 0:
        return _fail(f"camera_height must be > 0, got {camera_height}", world, t0)

    corners_u = find_peaks(prob, opt.corner_threshold, opt.corner_radius)
    if len(corners_u) < 3:
        return _fail(f"{len(corners_u)} corner(s) detected (max corner probability {np.nanmax(prob):.3f} vs threshold "
                     f"{opt.corner_threshold}); a room needs at least 3 walls", world, t0)
    walls = wall_column_ranges(corners_u, W, valid, opt.wall_margin)
    thr = opt.ransac_threshold * math.pi / rays.height
    rng = np.random.default_rng(opt.seed)
    long_idx = [k for k, c in enumerate(walls) if len(c) >= max(opt.min_wall_columns, opt.ransac_sample)]
    if len(long_idx) < 2:
        return _fail(f"only {len(long_idx)} wall(s) with at least {opt.min_wall_columns} valid columns", world, t0)
    fit, inliers = ransac_walls(rays, [walls[k] for k in long_idx], thr, rng, opt.ransac_p, opt.ransac_outliers,
                                opt.ransac_sample, camera_height if central else None)
    n_w = len(walls)
    theta = np.full(n_w, np.nan)
    cols = [np.zeros(0, int) for _ in range(n_w)]
    good = np.zeros(n_w, bool)
    for j, k in enumerate(long_idx):
        if fit.ok[j] and np.isfinite(fit.theta[j]):
            theta[k], cols[k], good[k] = fit.theta[j], inliers[j], True
    for k in range(n_w):
        if not good[k]:
            cols[k] = walls[k]
    if good.sum() < 2:
        return _fail("fewer than 2 walls could be fitted (degenerate or inconsistent boundaries, e.g. walls "
                     "parallel to the rays)", world, t0)
    info = {"n_corner_peaks": int(len(corners_u)), "n_walls_fitted": int(good.sum()),
            "ransac_inliers": int(sum(len(cols[k]) for k in range(n_w) if good[k]))}
    # robust shared heights from the per-wall fits, then top-view directions of every wall at those
    # heights (total least squares): nearly scale-independent, much steadier than per-wall directions
    gi = [j for j, k in enumerate(long_idx) if good[k]]
    wts = np.array([len(inliers[j]) for j in gi], float)
    h_c0, h_f0 = _shared_heights(rays, np.r_[fit.h_c[gi], _weighted_median(fit.h_c[gi], wts)],
                                 np.r_[fit.h_f[gi], _weighted_median(fit.h_f[gi], wts)],
                                 [cols[long_idx[j]] for j in gi], thr)
    theta_tls = np.array([_short_wall_line(rays, cols[k], h_c0, h_f0)[0] for k in range(n_w)])
    if opt.directions == "tls":
        theta = np.where(np.isfinite(theta_tls), theta_tls, theta)
    elif opt.directions != "ransac":
        raise ValueError(f"directions must be 'tls' or 'ransac', got {opt.directions!r}")
    try:
        if world == "manhattan":
            res = _manhattan(rays, corners_u, theta, good, cols, opt, camera_height)
        else:
            res = _atlanta(rays, corners_u, theta, good, cols, opt, camera_height)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as e:  # numerical breakdown
        return _fail(f"solver failed: {e}", world, t0, **info)
    if isinstance(res, str):
        return _fail(res, world, t0, **info)
    verts, occl, h_c, h_f, problem, extra = res
    info.update(extra)
    do_refine = opt.refine if isinstance(opt.refine, bool) else (world == "atlanta" or bool(occl.any()))
    if do_refine and problem is not None:
        problem.fix_h_f = -float(camera_height) if central else None
        check = _check(verts, h_c, h_f, opt)
        try:
            h_c2, h_f2, verts2, cost = adjust_layout(h_c, h_f, verts, problem, max_nfev=opt.max_nfev)
        except (ValueError, np.linalg.LinAlgError) as e:
            h_c2, h_f2, verts2, cost = h_c, h_f, verts, math.nan
            info["adjust_error"] = str(e)
        if _check(verts2, h_c2, h_f2, opt) is None or check is not None:
            h_c, h_f, verts = h_c2, h_f2, verts2
            info["adjust_cost"] = cost
    bad = _check(verts, h_c, h_f, opt)
    if bad is not None:
        return _fail(bad, world, t0, **info)
    info["time_s"] = time.perf_counter() - t0
    return Layout(ok=True, corners=verts, h_ceiling=float(h_c), h_floor=float(h_f), occluded=occl, world=world,
                  scale="camera_height" if central else "metric", info=info)


# ------------------------------------------------------------------------------------------------

def _weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    x, w = np.asarray(x, float), np.asarray(w, float)
    ok = np.isfinite(x) & (w > 0)
    if not ok.any():
        return math.nan
    o = np.argsort(x[ok])
    cw = np.cumsum(w[ok][o])
    return float(x[ok][o][np.searchsorted(cw, 0.5 * cw[-1])])


def _shared_heights(rays: ColumnRays, cand_c: np.ndarray, cand_f: np.ndarray, wall_cols: list[np.ndarray],
                    thr: float) -> tuple[float, float]:
    """The candidate heights ``(h_c, h_f)`` that explain the boundaries of *all* walls best.

    A single wall constrains the scale weakly (a wall close to the rig circle seen through rounded
    boundaries can fit a collapsed, much smaller room almost as well), so the per-wall RANSAC heights
    are only candidates. For each candidate every wall gets its top-view total-least-squares line at
    those heights (as :func:`_short_wall_line`), and the candidate with the smallest truncated
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
    nx, ny = -np.sin(th), np.cos(th)
    d = nx * mx + ny * my                                           # (K, n_w)
    # re-projection of every column on its wall's line at the candidate heights
    nxw, nyw, dw = nx[:, wall], ny[:, wall], d[:, wall]              # (K, n)
    nb = nxw * b[None, :, 0] + nyw * b[None, :, 1]
    no = nxw * o[None, :, 0] + nyw * o[None, :, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        rng_ = (dw - no) / nb
        ec = np.abs(np.arctan2(cand_c[:, None], rng_) - lat_c[idx][None])
        ef = np.abs(np.arctan2(cand_f[:, None], rng_) - lat_f[idx][None])
    e2 = np.where(np.isfinite(ec) & (rng_ > 0), np.minimum(ec, thr) ** 2, thr ** 2) + \
        np.where(np.isfinite(ef) & (rng_ > 0), np.minimum(ef, thr) ** 2, thr ** 2)
    k = int(np.argmin(e2.sum(1)))
    return float(cand_c[k]), float(cand_f[k])


def _check(verts: np.ndarray, h_c: float, h_f: float, opt: LayoutOptions) -> str | None:
    """None if the layout is plausible, else the reason."""
    if not (np.isfinite(h_c) and np.isfinite(h_f) and h_c > 0 > h_f):
        return f"implausible heights h_c = {h_c:.3g}, h_f = {h_f:.3g} (need h_c > 0 > h_f)"
    if len(verts) < 3 or not np.all(np.isfinite(verts)):
        return "fewer than 3 finite corners"
    if np.max(np.linalg.norm(verts, axis=1)) > opt.max_range:
        return f"a corner lies farther than {opt.max_range} m (ill-conditioned solve)"
    if not _is_simple(verts):
        return "the recovered polygon self-intersects"
    if not _contains_origin(verts):
        return "the recovered polygon does not contain the camera"
    return None


def _is_simple(P: np.ndarray) -> bool:
    n = len(P)
    A, B = P, np.roll(P, -1, 0)
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue
            if _seg_cross(A[i], B[i], A[j], B[j]):
                return False
    return True


def _seg_cross(p1, p2, q1, q2) -> bool:
    def orient(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    d1, d2 = orient(q1, q2, p1), orient(q1, q2, p2)
    d3, d4 = orient(p1, p2, q1), orient(p1, p2, q2)
    return (d1 * d2 < 0) and (d3 * d4 < 0)


def _contains_origin(P: np.ndarray) -> bool:
    x, y = P[:, 0], P[:, 1]
    x2, y2 = np.roll(x, -1), np.roll(y, -1)
    cond = (y > 0) != (y2 > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = x + (0 - y) * (x2 - x) / (y2 - y)
    return bool(np.sum(cond & (xi > 0)) % 2 == 1)


def _corner_points(rays: ColumnRays, u: float, th1, d1, th2, d2):
    """Closest points of two wall lines to the corner ray of column ``u`` (top view)."""
    o, b = column_ray(u, rays.width, rays.rc)
    s1 = ray_line_range(th1, d1, o, b)
    s2 = ray_line_range(th2, d2, o, b)
    return o + s1 * b, o + s2 * b, s1, s2


def _far_from_ray(X, P1, P2, s1, s2, u, rays, opt) -> bool:
    """True when the wall lines' intersection is not where the corner ray says (an occlusion)."""
    if not np.all(np.isfinite(X)):
        return True
    if not (np.isfinite(s1) and np.isfinite(s2)):
        return False
    sep = float(np.linalg.norm(P1 - P2))
    az_gap = abs(float(wrap_angle(azimuth(X) - (2 * math.pi * u / rays.width - math.pi))))
    return sep > max(opt.occlusion_distance, opt.occlusion_relative * min(s1, s2)) \
        and az_gap > opt.occlusion_azimuth * 2 * math.pi / rays.width


def _problem(rays: ColumnRays, seg_cols: list[np.ndarray | None], corner_az: np.ndarray, corner_w: np.ndarray,
             opt: LayoutOptions, manhattan: bool, s_init: list[np.ndarray | None]) -> AdjustProblem:
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
    return AdjustProblem(seg=seg, origin2=rays.origin[idx, :2], b=rays.horizontal[idx], lat_c=lat_c[idx],
                         lat_f=lat_f[idx], dir_c=rays.ceiling[idx], mom_c=rays.moments("ceiling")[idx],
                         dir_f=rays.floor[idx], mom_f=rays.moments("floor")[idx], corner_az=corner_az,
                         corner_w=corner_w, n_corners=len(seg_cols), pix_lat=math.pi / rays.height,
                         pix_az=2 * math.pi / rays.width, side_weight=opt.side_weight,
                         manhattan_weight=opt.manhattan_weight if manhattan else 0.0,
                         s0=np.concatenate(s0))


def _assemble(rays, corners_u, th, d, cols, transitions, opt, manhattan):
    """Vertices, occlusion flags and the adjustment problem from per-wall lines and transitions.

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
        u = corners_u[(t + 1) % n]
        az = 2 * math.pi * u / rays.width - math.pi
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
    lat_c, _ = rays.elevations()
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
    problem = _problem(rays, seg_cols, np.array(vaz), w, opt, manhattan, s_init)
    return verts, occl, problem


def _short_wall_line(rays: ColumnRays, c: np.ndarray, h_c: float, h_f: float):
    """Top-view line through the boundary points of columns ``c`` at known heights (total least squares)."""
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
    return (th + math.pi) % (2 * math.pi) - math.pi, d


def _keep_walls(keep: np.ndarray, cols: list[np.ndarray], *per_wall: np.ndarray) -> tuple:
    """``(cols, *per_wall)`` restricted to the walls where ``keep`` is true (each wall with its starting corner)."""
    idx = np.flatnonzero(keep)
    return ([cols[k] for k in idx], *(a[idx] for a in per_wall))


def _merge(cols, theta, keep_mask, corners_u, merge_pairs):
    """Merge walls ``k`` and ``k+1`` for every ``k`` in ``merge_pairs`` (drop corner ``k+1``)."""
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


def _manhattan(rays, corners_u, theta, good, cols, opt, camera_height):
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
        cols, corners_u, theta, good, label = _keep_walls(keep, cols, corners_u, theta, good, label)
        n = len(cols)
    for _ in range(n):
        if n < 3:
            return f"only {n} walls remain after removing unfittable short walls"
        A = manhattan_rows(*_rays4(rays, np.concatenate(cols)), label, np.concatenate(
            [np.full(len(c), k) for k, c in enumerate(cols)]), n)
        if camera_height is not None:
            th0, d, h_c, h_f, ok = _solve_manhattan_central(A, camera_height)
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
        cols, th_tmp, corners_u, good = _merge(cols, th, good, corners_u, pairs[:1])
        label = np.array([label[k] for k in range(n) if k != (pairs[0] + 1) % n])
        n = len(cols)
    transitions = []
    n_occ = 0
    for k in range(n):
        j = (k + 1) % n
        if label[k] != label[j]:
            X = line_intersection(th[k], d[k], th[j], d[j])
            P1, P2, s1, s2 = _corner_points(rays, corners_u[j], th[k], d[k], th[j], d[j])
            if not _far_from_ray(X, P1, P2, s1, s2, corners_u[j], rays, opt):
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
        P1, P2, s1, s2 = _corner_points(rays, corners_u[j], th[k], d[k], th[j], d[j])
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
    verts, occl, problem = _assemble(rays, corners_u, th, d, cols, transitions, opt, manhattan=True)
    return verts, occl, h_c, h_f, problem, {"n_occlusions": n_occ, "orientation_deg": math.degrees(th0)}


def _solve_manhattan_central(A, camera_height):
    """Manhattan solver without moments (central camera): unknown (v, w, d_i), scale from the camera height."""
    B = A[:, 2:]
    used = np.sqrt((B * B).sum(0)) > 0
    _, _, Vh = np.linalg.svd(B[:, used])
    X = np.zeros(B.shape[1])
    X[used] = Vh[-1]
    v, w, d = X[0:2], X[2:4], X[4:]
    u = v - w
    nu = np.linalg.norm(u)
    if nu < 1e-12:
        return 0.0, d, math.nan, math.nan, False
    u = u / nu
    h_c, h_f = float(u @ v), float(u @ w)
    if not h_f < 0:
        return 0.0, d, math.nan, math.nan, False
    s = -camera_height / h_f
    return math.atan2(u[1], u[0]), d * s, h_c * s, h_f * s, h_c * s > 0


def _rays4(rays, idx):
    return rays.ceiling[idx], rays.moments("ceiling")[idx], rays.floor[idx], rays.moments("floor")[idx]


def _atlanta(rays, corners_u, theta, good, cols, opt, camera_height):
    n = len(theta)
    use = np.flatnonzero(good)

    def solve(th, walls_idx, c):
        idx = np.concatenate([c[k] for k in walls_idx])
        wall = np.concatenate([np.full(len(c[k]), j) for j, k in enumerate(walls_idx)])
        A = atlanta_rows(*_rays4(rays, idx), th[walls_idx], wall, len(walls_idx))
        return solve_atlanta(A, fix_h_f=None if camera_height is None else -camera_height)

    h_c, h_f, d_use, ok = solve(theta, use, cols)
    if not ok:
        return "the Atlanta layout solver found no solution with the ceiling above the floor"
    d = np.full(n, np.nan)
    d[use] = d_use
    for k in np.flatnonzero(~good):
        theta[k], d[k] = _short_wall_line(rays, cols[k], h_c, h_f)
    keep = np.isfinite(theta) & np.isfinite(d)
    if keep.sum() < 3:
        return f"only {int(keep.sum())} walls could be located"
    if (~keep).any():
        cols, corners_u, theta, d, good = _keep_walls(keep, cols, corners_u, theta, d, good)
        n = len(cols)
    # merge coplanar neighbours (spurious corners)
    for _ in range(n):
        pairs = []
        for k in range(n):
            j = (k + 1) % n
            dth = abs((theta[k] - theta[j] + math.pi) % (2 * math.pi) - math.pi)
            if dth < math.radians(opt.merge_angle_deg) and abs(d[k] - d[j]) < opt.merge_distance:
                pairs.append(k)
        if not pairs or n <= 3:
            break
        k = pairs[0]
        cols, theta, corners_u, good = _merge(cols, theta, good, corners_u, [k])
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
        P1, P2, s1, s2 = _corner_points(rays, corners_u[j], theta[k], d[k], theta[j], d[j])
        X = line_intersection(theta[k], d[k], theta[j], d[j])
        occluded = _far_from_ray(X, P1, P2, s1, s2, corners_u[j], rays, opt)
        if not occluded:
            transitions.append([(X, False)])
            continue
        if not (np.isfinite(s1) and np.isfinite(s2) and s1 > 0 and s2 > 0):
            return "an occluded corner ray does not meet its walls in front of the camera"
        # Fig. 5.6: the hidden wall lies in the plane of the corner rays; the visible one of the
        # two points is the nearer, the other is a corner of the partially occluded wall
        transitions.append([(P1, s1 > s2), (P2, s2 > s1)])
        n_occ += 1
    verts, occl, problem = _assemble(rays, corners_u, theta, d, cols, transitions, opt, manhattan=False)
    return verts, occl, h_c, h_f, problem, {"n_occlusions": n_occ}
