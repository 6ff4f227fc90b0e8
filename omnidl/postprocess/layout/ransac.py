"""Per-wall RANSAC with batched hypotheses (thesis §5.4.4).

Every wall's hypotheses are solved in one batched SVD: a hypothesis is ``sample_size`` columns of
the wall (each column gives one ceiling and one floor ray). Inliers are columns whose ceiling
*and* floor boundaries are re-projected within ``threshold`` radians. The best hypothesis of each
wall is refitted on its inliers with the full single-wall solver.
"""
from __future__ import annotations

import numpy as np

from .rays import ColumnRays
from .solvers import WallFit, ransac_iterations, solve_walls, solve_walls_central


def _gather(rays: ColumnRays, cols: np.ndarray, mask: np.ndarray):
    """Padded ray arrays for index matrix ``cols (..., n)``."""
    mc, mf = rays.moments("ceiling"), rays.moments("floor")
    return rays.ceiling[cols], mc[cols], rays.floor[cols], mf[cols], mask.astype(float)


def reprojection_errors(fit_theta, fit_d, fit_hc, fit_hf, rays: ColumnRays, cols: np.ndarray):
    """Latitude errors ``(..., n)`` (radians, first order) of ceiling and floor, walls broadcast over columns.

    ``fit_*`` have shape ``(...)`` and ``cols`` ``(..., n)``, where the leading dimensions need only
    broadcast: ``cols (n_w, 1, n)`` against hypotheses ``(n_w, n_hyp)`` gathers each column once.

    The column sees the wall line at horizontal range ``s`` and predicted ``tan(lat) = h / s``; the
    error ``|h/s - tan(lat_obs)| cos^2(lat_obs)`` is the angular error to first order (no arctan:
    this runs on every hypothesis x column).
    """
    tc, tf, wc, wf = rays._cached("tan", lambda: _tan_tables(rays))
    o2 = rays.origin[cols][..., :2]
    b = rays.horizontal[cols]
    nx, ny = -np.sin(fit_theta)[..., None], np.cos(fit_theta)[..., None]
    nb = nx * b[..., 0] + ny * b[..., 1]
    no = nx * o2[..., 0] + ny * o2[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_s = nb / (fit_d[..., None] - no)
    bad = ~((nb > 1e-9) & (inv_s > 0))
    ec = np.abs(fit_hc[..., None] * inv_s - tc[cols]) * wc[cols]
    ef = np.abs(fit_hf[..., None] * inv_s - tf[cols]) * wf[cols]
    ec[bad | ~np.isfinite(ec)] = np.inf
    ef[bad | ~np.isfinite(ef)] = np.inf
    return ec, ef


def _tan_tables(rays: ColumnRays):
    lat_c, lat_f = rays.elevations()
    return np.tan(lat_c), np.tan(lat_f), np.cos(lat_c) ** 2, np.cos(lat_f) ** 2


def ransac_walls(rays: ColumnRays, wall_columns: list[np.ndarray], threshold: float,
                 rng: np.random.Generator, p_success: float = 0.9999, outlier_rate: float = 0.3,
                 sample_size: int = 3, camera_height: float | None = None,
                 max_hypotheses: int = 200) -> tuple[WallFit, list[np.ndarray]]:
    """Fit every wall (list of column-index arrays, each with ``>= sample_size`` columns).

    Returns the refitted walls (``WallFit`` with one entry per wall) and each wall's inlier columns.
    ``camera_height`` switches to the central solver (scale from the camera height).
    """
    n_w = len(wall_columns)
    if n_w == 0:
        e = np.zeros(0)
        return WallFit(e, e, e, e, np.zeros(0, bool), e), []
    n_hyp = min(max_hypotheses, ransac_iterations(p_success, outlier_rate, sample_size))
    lens = np.array([len(c) for c in wall_columns])
    L = int(lens.max())
    cols = np.zeros((n_w, L), int)
    mask = np.zeros((n_w, L), bool)
    for i, c in enumerate(wall_columns):
        cols[i, :len(c)] = c
        mask[i, :len(c)] = True
    # sample without replacement: random keys, padded columns pushed to the end
    keys = rng.random((n_w, n_hyp, L)) + (~mask)[:, None, :] * 2.0
    pick = np.argsort(keys, -1)[..., :sample_size]                                   # (n_w, n_hyp, k)
    sel = np.take_along_axis(np.broadcast_to(cols[:, None], (n_w, n_hyp, L)), pick, -1)
    flat = sel.reshape(-1, sample_size)
    if camera_height is None:
        hyp = solve_walls(rays.ceiling[flat], rays.moments("ceiling")[flat], rays.floor[flat],
                          rays.moments("floor")[flat])
    else:
        hyp = solve_walls_central(rays.ceiling[flat], rays.floor[flat], camera_height=camera_height)
    th, d, hc, hf = (x.reshape(n_w, n_hyp) for x in (hyp.theta, hyp.d, hyp.h_c, hyp.h_f))
    ec, ef = reprojection_errors(th, d, hc, hf, rays, cols[:, None, :])              # (n_w, n_hyp, L)
    inl = (ec < threshold) & (ef < threshold) & mask[:, None, :]
    score = inl.sum(-1) - np.where(hyp.ok.reshape(n_w, n_hyp), 0, L + 1)
    best = np.argmax(score, -1)
    best_inl = inl[np.arange(n_w), best]                                              # (n_w, L)
    # walls whose best hypothesis explains too little: refit on all columns
    few = best_inl.sum(-1) < max(sample_size, 3)
    best_inl[few] = mask[few]
    w = best_inl.astype(float)
    if camera_height is None:
        fit = solve_walls(*_gather(rays, cols, mask)[:4], w, w)
    else:
        fit = solve_walls_central(rays.ceiling[cols], rays.floor[cols], w, w, camera_height=camera_height)
    # second pass: inliers of the refitted model, refit again
    ec, ef = reprojection_errors(fit.theta, fit.d, fit.h_c, fit.h_f, rays, cols)
    inl2 = (ec < threshold) & (ef < threshold) & mask
    again = inl2.sum(-1) >= max(sample_size, 3)
    w2 = np.where(again[:, None], inl2, best_inl).astype(float)
    if camera_height is None:
        fit = solve_walls(*_gather(rays, cols, mask)[:4], w2, w2)
    else:
        fit = solve_walls_central(rays.ceiling[cols], rays.floor[cols], w2, w2, camera_height=camera_height)
    inliers = [cols[i][w2[i] > 0] for i in range(n_w)]
    return fit, inliers
