"""Is a recovered layout trustworthy? Its fit residual against the boundaries and the world assumption.

* :func:`boundary_residual`: every valid column's ceiling and floor ray is cast (top view) against the
  layout polygon; the elevation the layout predicts there is compared with the observed one, in pixel
  rows. A layout that explains the boundaries has sub-pixel to pixel residuals; a wrong world (a
  Manhattan layout of a room with oblique walls) leaves whole walls pixels or metres off.
* :func:`manhattan_deviation`: how far the fitted walls' own directions are from the nearest
  Manhattan axis (degrees); a Manhattan room gives a few degrees at most.

:func:`manhattan_check` and :func:`assess` turn them into ``(info, reason)``: ``reason`` is ``None`` when
the layout can be trusted, and ``info["assumptions_ok"]`` is False when it cannot.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ...geometry.polygon import ray_polygon_hit
from .assemble import pixel_angles
from .directions import direction_spread
from .rays import ColumnRays

if TYPE_CHECKING:
    from .pipeline import LayoutOptions


def boundary_residual(rays: ColumnRays, verts: np.ndarray, h_c: float, h_f: float) -> np.ndarray:
    """``(2, V)`` absolute ceiling/floor residuals (pixel rows) of the ``V`` valid columns of ``rays``.

    ``verts (N, 2)`` is the layout polygon, ``h_c``/``h_f`` its heights; a ray whose top view leaves the
    polygon without hitting a wall gets ``inf``."""
    idx = np.flatnonzero(rays.valid)
    if len(idx) == 0 or len(verts) < 3:
        return np.zeros((2, 0))
    o = rays.origin[idx]
    lat_c, lat_f = rays.elevations()
    # a column is a vertical half-plane: its ceiling and floor rays share the top-view ray
    s, _ = ray_polygon_hit(np.asarray(verts, float), o[:, :2], rays.horizontal[idx])
    out = []
    for lat, h in ((lat_c[idx], h_c), (lat_f[idx], h_f)):
        pred = np.arctan2(h - o[:, 2], s)                   # s = inf -> 0 (then flagged below)
        out.append(np.where(np.isfinite(s), np.abs(pred - lat), np.inf))
    return np.stack(out) / pixel_angles(rays)[0]


def boundary_noise(rays: ColumnRays) -> float:
    """Robust noise level (pixel rows) of the observed boundaries: the MAD of the second differences of the
    ceiling and floor elevations along consecutive valid columns (``sigma = 1.4826 MAD / sqrt(6)``; corners
    touch few columns and do not move the median). 0 when fewer than 8 triples exist."""
    v = rays.valid
    triple = v & np.roll(v, 1) & np.roll(v, -1)
    if triple.sum() < 8:
        return 0.0
    d2 = [np.roll(e, 1)[triple] - 2 * e[triple] + np.roll(e, -1)[triple] for e in rays.elevations()]
    mad = float(np.median(np.abs(np.concatenate(d2))))
    return 1.4826 * mad / math.sqrt(6.0) / pixel_angles(rays)[0]


def manhattan_deviation(theta: np.ndarray, weight: np.ndarray, theta0: float,
                        tolerance_deg: float) -> tuple[float, float]:
    """How far fitted walls are from the Manhattan axes at ``theta0``.

    Returns ``(max_deg, fraction)``: the largest deviation (degrees) of a wall direction ``theta (N,)``
    from its nearest Manhattan axis, and the ``weight``-weighted fraction (``weight``: columns per wall,
    0 for unfitted walls) of walls deviating more than ``tolerance_deg``. NaN directions are ignored."""
    w = np.asarray(weight, float)
    ok = np.isfinite(theta) & (w > 0)
    if not ok.any():
        return 0.0, 0.0
    dev = np.degrees(direction_spread(np.asarray(theta, float)[ok], theta0))
    return float(dev.max()), float(np.sum(w[ok] * (dev > tolerance_deg)) / np.sum(w[ok]))


def manhattan_check(deviation: tuple[float, float], opt: LayoutOptions) -> tuple[dict, str | None]:
    """``(info, reason or None)`` of the Manhattan assumption from :func:`manhattan_deviation`'s result."""
    info = {"manhattan_deviation_deg": deviation[0], "non_manhattan_fraction": deviation[1]}
    if deviation[1] <= opt.max_non_manhattan:
        return info, None
    info["assumptions_ok"] = False
    return info, (f"the Manhattan assumption does not hold: {100 * deviation[1]:.0f}% of the fitted wall columns lie "
                  f"on walls more than {opt.manhattan_tolerance_deg} deg off the Manhattan axes (up to "
                  f"{deviation[0]:.1f} deg; allowed {100 * opt.max_non_manhattan:.0f}%); use world='atlanta'")


def assess(rays: ColumnRays, verts: np.ndarray, h_c: float, h_f: float, opt: LayoutOptions) -> tuple[dict, str | None]:
    """Residual statistics of a layout -> ``(info, reason or None)``.

    ``info``: ``residual_px`` (median over both boundaries), ``residual_p90_px``, ``boundary_noise_px``
    (:func:`boundary_noise`), ``residual_outliers`` (fraction of boundary points off by more than
    ``max(opt.residual_outlier_px, 3 * boundary_noise_px)``: noisy boundaries are not a misfit) and
    ``assumptions_ok``.
    ``reason`` says why the layout is not trusted (``None``: it is).

    The residual alone cannot reject a wrong Manhattan layout of an oblique room: a zig-zag polygon of
    axis-aligned walls, scaled up with its heights, reprojects close to the boundaries of a non-central
    panorama (the scale is weakly observable); :func:`manhattan_check` of the wall directions fitted
    before the Manhattan snap can."""
    res = boundary_residual(rays, verts, h_c, h_f).ravel()
    if res.size == 0:
        return {"residual_px": math.nan, "assumptions_ok": False}, "no valid column to check the layout against"
    finite = np.where(np.isfinite(res), res, 1e9)
    noise = boundary_noise(rays)
    limit = max(opt.residual_outlier_px, 3.0 * noise)
    info = {"residual_px": float(np.median(finite)), "residual_p90_px": float(np.percentile(finite, 90)),
            "boundary_noise_px": noise, "residual_outliers": float(np.mean(finite > limit))}
    reason = None
    if info["residual_outliers"] > opt.max_residual_outliers:
        reason = (f"the layout does not explain the boundaries: {100 * info['residual_outliers']:.0f}% of the "
                  f"boundary points are more than {limit:.2f} px off (noise {noise:.2f} px; allowed "
                  f"{100 * opt.max_residual_outliers:.0f}%; median {info['residual_px']:.2f} px)")
    info["assumptions_ok"] = reason is None
    return info, reason
