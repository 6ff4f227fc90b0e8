"""The full geometric pipeline of thesis §5.4.4 (Fig. 5.5): boundaries + corners -> metric layout.

``estimate_layout(rays, corner_prob, world="manhattan"|"atlanta")`` orchestrates:

1. corner columns = peaks of the corner probability; the columns between consecutive corners
   (minus a margin) form the walls (:mod:`.corners`);
2. per-wall RANSAC with the single-wall solver (batched hypotheses) and an inlier refit
   (:mod:`.ransac`); the shared heights are the per-wall candidate that explains the boundaries of
   all walls best, and every wall gets its top-view direction at those heights (:mod:`.walls`);
3. the world's branch: :mod:`.manhattan` (Manhattan solver, Eq. 5.8) or :mod:`.atlanta` (Atlanta
   solver, Eq. 5.9), each ending in the corner assembly of :mod:`.assemble` (corners on the corner
   rays, occluded walls, the adjustment problem);
4. final bounded least-squares adjustment (:mod:`.adjust`) and plausibility checks (heights, range,
   a simple polygon around the camera);
5. trust checks (:mod:`.checks`): the Manhattan branch first checks that the fitted walls are Manhattan,
   and every layout must explain the boundaries (fit residual in pixel rows). A layout that fails
   them has ``ok=False`` and ``info["assumptions_ok"] = False`` (the hooks then fall back to Atlanta);
   the residual statistics are in ``info`` (``residual_px``, ``residual_p90_px``, ``residual_outliers``).

Scale comes from the rig radius through the ray moments. With a central camera (``Rc`` below
``min_rc``) the pipeline refuses metric scale unless ``camera_height`` is given (the central
baseline of Table 5.3, which fixes ``h_f = -camera_height``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ...geometry.polygon import is_simple, points_in_polygon
from ...utils.blas import single_thread_blas
from .adjust import adjust_layout
from .assemble import pixel_angles
from .atlanta import atlanta_layout
from .checks import assess, manhattan_check, manhattan_deviation
from ...metrics.layout import find_peaks
from .corners import wall_column_ranges
from .directions import manhattan_orientation
from .layout import Layout
from .manhattan import manhattan_layout
from .ransac import ransac_walls
from .rays import ColumnRays
from .walls import shared_heights, topview_wall_line, weighted_median


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
    check_assumptions: bool = True       # residual + world-assumption checks (:mod:`.checks`); False: off
    manhattan_tolerance_deg: float = 10.0  # fitted walls farther than this from the Manhattan axes are oblique
    max_non_manhattan: float = 0.15      # more than this fraction of fitted wall columns oblique: not Manhattan
    residual_outlier_px: float = 3.0     # boundary points off by more than this (pixel rows) are outliers
    max_residual_outliers: float = 0.2   # ... and more than this fraction of them: the layout is not trusted


def _fail(reason, world, t0, **info):
    return Layout.failed(reason, world=world, time_s=time.perf_counter() - t0, **info)


def estimate_layout(rays: ColumnRays, corner_prob: np.ndarray, world: str = "atlanta",
                    camera_height: float | None = None, options: LayoutOptions | None = None,
                    **overrides) -> Layout:
    """Recover a layout; see :func:`_estimate_layout` (run with single-threaded BLAS)."""
    with single_thread_blas():
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
    thr = opt.ransac_threshold * pixel_angles(rays)[0]
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
    h_c0, h_f0 = shared_heights(rays, np.r_[fit.h_c[gi], weighted_median(fit.h_c[gi], wts)],
                                 np.r_[fit.h_f[gi], weighted_median(fit.h_f[gi], wts)],
                                 [cols[long_idx[j]] for j in gi], thr)
    theta_tls = np.array([topview_wall_line(rays, cols[k], h_c0, h_f0)[0] for k in range(n_w)])
    if opt.directions == "tls":
        theta = np.where(np.isfinite(theta_tls), theta_tls, theta)
    elif opt.directions != "ransac":
        raise ValueError(f"directions must be 'tls' or 'ransac', got {opt.directions!r}")
    if world == "manhattan" and opt.check_assumptions:   # the walls' own directions must be Manhattan
        weight = np.array([len(c) if g else 0 for c, g in zip(cols, good)], float)
        checks, why = manhattan_check(manhattan_deviation(theta, weight, manhattan_orientation(theta, weight),
                                                          opt.manhattan_tolerance_deg), opt)
        info.update(checks)
        if why is not None:
            return _fail(why, world, t0, **info)
    try:
        if world == "manhattan":
            res = manhattan_layout(rays, corners_u, theta, good, cols, opt, camera_height)
        else:
            res = atlanta_layout(rays, corners_u, theta, good, cols, opt, camera_height)
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
    if opt.check_assumptions:
        checks, why = assess(rays, verts, h_c, h_f, opt)
        info.update(checks)
        if why is not None:
            return _fail(why, world, t0, **info)
    info["time_s"] = time.perf_counter() - t0
    return Layout(ok=True, corners=verts, h_ceiling=float(h_c), h_floor=float(h_f), occluded=occl, world=world,
                  scale="camera_height" if central else "metric", info=info)


def _check(verts: np.ndarray, h_c: float, h_f: float, opt: LayoutOptions) -> str | None:
    """None if the layout is plausible, else the reason."""
    if not (np.isfinite(h_c) and np.isfinite(h_f) and h_c > 0 > h_f):
        return f"implausible heights h_c = {h_c:.3g}, h_f = {h_f:.3g} (need h_c > 0 > h_f)"
    if len(verts) < 3 or not np.all(np.isfinite(verts)):
        return "fewer than 3 finite corners"
    if np.max(np.linalg.norm(verts, axis=1)) > opt.max_range:
        return f"a corner lies farther than {opt.max_range} m (ill-conditioned solve)"
    step = np.linalg.norm(verts - np.roll(verts, 1, axis=0), axis=1)
    if np.any(step <= 1e-9 * max(1.0, float(np.abs(verts).max()))):
        return "the recovered polygon has two coincident corners"
    if not is_simple(verts, eps=0.0):
        return "the recovered polygon self-intersects"
    if not points_in_polygon(np.zeros((1, 2)), verts)[0]:
        return "the recovered polygon does not contain the camera"
    return None
