"""Final adjustment (thesis §5.4.4): bounded least squares on the heights and the 2-D corners.

Parameters ``x = (h_c, h_f, x_1, y_1, ..., x_M, y_M)``; the polygon's segment ``m`` joins corners
``m`` and ``m+1``. Residuals (all roughly in pixels):

* reprojection: for each observed column of a segment, the latitude at which the column sees the
  segment's ceiling (floor) line minus the observed boundary latitude, divided by ``pi / H``;
* side: the Plücker side product of the column's ceiling (floor) ray with the segment's 3-D line,
  divided by ``(pi / H) * s`` (``s`` the initial horizontal range), weight ``side_weight``;
* out-of-plane penalty: the azimuth of each corner minus the azimuth of its corner ray, divided by
  ``2 pi / W`` (weight ``corner_weight``, ``occluded_weight`` for corners created by occlusion
  handling on a corner ray, which are only defined by that ray's plane; a hidden corner off every
  corner ray, e.g. the far end of an inserted Manhattan wall, has no penalty (NaN azimuth) and is
  held by the Manhattan term);
* Manhattan: ``manhattan_weight * cos`` of the angle between consecutive segments.

Solved with :func:`scipy.optimize.least_squares` (TRF, bounds ``0 < h_c``, ``h_f < 0``, corners
within ``+-max_extent``) with an analytic Jacobian.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .corners import wrap_angle


@dataclass
class AdjustProblem:
    """Observations of the final adjustment (see module docstring). ``seg`` indexes segments."""

    seg: np.ndarray          # (n,) segment of each observed column
    origin2: np.ndarray      # (n, 2) column optical centres (top view)
    b: np.ndarray            # (n, 2) column horizontal directions
    lat_c: np.ndarray        # (n,) observed ceiling latitude
    lat_f: np.ndarray        # (n,) observed floor latitude
    dir_c: np.ndarray        # (n, 3) ceiling ray directions
    mom_c: np.ndarray        # (n, 3) ceiling ray moments
    dir_f: np.ndarray
    mom_f: np.ndarray
    corner_az: np.ndarray    # (M,) azimuth of each corner's corner ray (NaN = no penalty)
    corner_w: np.ndarray     # (M,) weight of each corner penalty
    n_corners: int
    pix_lat: float           # radians per pixel row
    pix_az: float            # radians per pixel column
    side_weight: float = 0.5
    manhattan_weight: float = 0.0
    s0: np.ndarray | None = None
    fix_h_f: float | None = None  # central cameras: the floor height is given (scale is not observable)


def _cross(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def residuals_and_jacobian(x: np.ndarray, P: AdjustProblem, want_jac: bool = True):
    """Residual vector and dense Jacobian at ``x`` (see module docstring)."""
    M = P.n_corners
    hc, hf = x[0], x[1]
    C = x[2:].reshape(M, 2)
    i0 = P.seg
    i1 = (P.seg + 1) % M
    A, B = C[i0], C[i1]
    n = len(i0)
    a = A - P.origin2
    c = B - P.origin2
    E = B - A
    N = _cross(a, c)
    D = _cross(P.b, E)
    Dsafe = np.where(np.abs(D) > 1e-12, D, 1e-12)
    s = N / Dsafe
    blocks, jac_blocks = [], []
    nvar = 2 + 2 * M

    # d s / d A, d s / d B   (n, 2)
    if want_jac:
        dN_dA = np.stack([c[:, 1], -c[:, 0]], -1)
        dN_dB = np.stack([-a[:, 1], a[:, 0]], -1)
        dD_dA = np.stack([P.b[:, 1], -P.b[:, 0]], -1)
        dD_dB = -dD_dA
        ds_dA = (dN_dA - s[:, None] * dD_dA) / Dsafe[:, None]
        ds_dB = (dN_dB - s[:, None] * dD_dB) / Dsafe[:, None]
    rows = np.arange(n)
    for h, lat, hidx in ((hc, P.lat_c, 0), (hf, P.lat_f, 1)):
        r = (np.arctan2(h, s) - lat) / P.pix_lat
        blocks.append(r)
        if want_jac:
            J = np.zeros((n, nvar))
            q = h * h + s * s
            J[rows, hidx] = s / q / P.pix_lat
            dl_ds = (-h / q / P.pix_lat)[:, None]
            np.add.at(J, (rows[:, None], 2 + 2 * i0[:, None] + np.arange(2)[None]), dl_ds * ds_dA)
            np.add.at(J, (rows[:, None], 2 + 2 * i1[:, None] + np.arange(2)[None]), dl_ds * ds_dB)
            jac_blocks.append(J)

    if P.side_weight > 0:
        L = np.linalg.norm(E, axis=-1)
        Ls = np.where(L > 1e-12, L, 1e-12)
        ehat = E / Ls[:, None]
        s0 = P.s0 if P.s0 is not None else np.ones(n)
        wgt = P.side_weight / (P.pix_lat * np.maximum(s0, 0.1))
        crossAB = _cross(A, B)
        for h, xi, xib, hidx in ((hc, P.dir_c, P.mom_c, 0), (hf, P.dir_f, P.mom_f, 1)):
            g = np.stack([h * xi[:, 1] + xib[:, 0], -h * xi[:, 0] + xib[:, 1]], -1)
            Nn = (g * E).sum(-1) + xi[:, 2] * crossAB
            r = wgt * Nn / Ls
            blocks.append(r)
            if want_jac:
                J = np.zeros((n, nvar))
                dN_dh = xi[:, 1] * E[:, 0] - xi[:, 0] * E[:, 1]
                J[rows, hidx] = wgt * dN_dh / Ls
                dNdB = g + xi[:, 2:3] * np.stack([-A[:, 1], A[:, 0]], -1)
                dNdA = -g + xi[:, 2:3] * np.stack([B[:, 1], -B[:, 0]], -1)
                dA = (dNdA / Ls[:, None] + (Nn / Ls ** 2)[:, None] * ehat) * wgt[:, None]
                dB = (dNdB / Ls[:, None] - (Nn / Ls ** 2)[:, None] * ehat) * wgt[:, None]
                np.add.at(J, (rows[:, None], 2 + 2 * i0[:, None] + np.arange(2)[None]), dA)
                np.add.at(J, (rows[:, None], 2 + 2 * i1[:, None] + np.arange(2)[None]), dB)
                jac_blocks.append(J)

    has = np.isfinite(P.corner_az) & (P.corner_w > 0)
    if has.any():
        idx = np.flatnonzero(has)
        Cm = C[idx]
        az = np.arctan2(Cm[:, 0], Cm[:, 1])
        diff = wrap_angle(az - P.corner_az[idx])
        w = P.corner_w[idx] / P.pix_az
        blocks.append(w * diff)
        if want_jac:
            J = np.zeros((len(idx), nvar))
            q = np.maximum((Cm * Cm).sum(-1), 1e-12)
            J[np.arange(len(idx)), 2 + 2 * idx] = w * Cm[:, 1] / q
            J[np.arange(len(idx)), 3 + 2 * idx] = -w * Cm[:, 0] / q
            jac_blocks.append(J)

    if P.manhattan_weight > 0 and M >= 3:
        E_all = np.roll(C, -1, 0) - C                     # segment m: C[m] -> C[m+1]
        Ln = np.maximum(np.linalg.norm(E_all, axis=-1), 1e-12)
        eh = E_all / Ln[:, None]
        e_next = np.roll(eh, -1, 0)
        f = (eh * e_next).sum(-1)
        blocks.append(P.manhattan_weight * f)
        if want_jac:
            J = np.zeros((M, nvar))
            m = np.arange(M)
            # d f / d E_m = (I - e e^T) e_next / |E_m|;  d f / d E_{m+1} = (I - e' e'^T) e / |E_{m+1}|
            g1 = (e_next - f[:, None] * eh) / Ln[:, None]
            Ln_next = np.roll(Ln, -1)
            g2 = (eh - f[:, None] * e_next) / Ln_next[:, None]
            w = P.manhattan_weight
            # E_m = C[m+1] - C[m];  E_{m+1} = C[m+2] - C[m+1]
            for k, sign, g in ((m, -1.0, g1), ((m + 1) % M, 1.0, g1), ((m + 1) % M, -1.0, g2), ((m + 2) % M, 1.0, g2)):
                np.add.at(J, (m[:, None], 2 + 2 * k[:, None] + np.arange(2)[None]), w * sign * g)
            jac_blocks.append(J)

    if P.fix_h_f is not None:
        blocks.append(np.array([1e4 * (hf - P.fix_h_f)]))
        if want_jac:
            J = np.zeros((1, nvar))
            J[0, 1] = 1e4
            jac_blocks.append(J)

    r = np.concatenate(blocks)
    r = np.where(np.isfinite(r), r, 1e3)
    if not want_jac:
        return r, None
    J = np.concatenate(jac_blocks, 0)
    return r, np.where(np.isfinite(J), J, 0.0)


def adjust_layout(h_c: float, h_f: float, corners: np.ndarray, P: AdjustProblem, max_nfev: int = 50,
                  max_extent: float = 100.0) -> tuple[float, float, np.ndarray, float]:
    """Run the bounded least squares; returns refined ``(h_c, h_f, corners (M, 2), cost)``."""
    x0 = np.concatenate([[h_c, h_f], np.asarray(corners, float).reshape(-1)])
    lo = np.concatenate([[1e-3, -50.0], np.full(2 * P.n_corners, -max_extent)])
    hi = np.concatenate([[50.0, -1e-3], np.full(2 * P.n_corners, max_extent)])
    x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)
    cache: dict = {}

    def fun(x):
        r, J = residuals_and_jacobian(x, P, True)
        cache["x"], cache["J"] = x.copy(), J
        return r

    def jac(x):
        if "x" in cache and np.array_equal(cache["x"], x):
            return cache["J"]
        return residuals_and_jacobian(x, P, True)[1]

    res = least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf", max_nfev=max_nfev, x_scale="jac")
    x = res.x
    return float(x[0]), float(x[1]), x[2:].reshape(-1, 2), float(res.cost)
