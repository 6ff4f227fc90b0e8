"""Linear wall and layout solvers of thesis §5.4 (batched, float64 numpy).

A vertical wall is two horizontal lines in a vertical plane (Fig. 5.4). With the wall direction
``u = (ux, uy)``, ``e2 = (-uy, ux)`` and ``e3 = z``, the ceiling line has direction ``(u, 0)`` and
moment ``h_c e2 - d e3``; the floor line has moment ``h_f e2 - d e3``. ``d`` is the signed distance
of the wall plane along ``e2`` and ``h_c``/``h_f`` are the heights of the ceiling/floor planes
relative to the camera circle. A ray ``(xi, xi_bar)`` (direction, moment ``o x xi``) meets the
ceiling line when (Eq. 5.1/5.3)::

    xi_bar_1 ux + xi_bar_2 uy + xi_2 vx - xi_1 vy - xi_3 d = 0,      v = h_c u

which is linear in ``W = (u, v, w, d)`` (Eq. 5.4, ``w = h_f u`` for floor rays).

Canonical wall parameters returned by every solver: ``theta`` (direction angle of ``u``),
``d > 0`` (``e2`` points from the camera to the wall), ``h_c``, ``h_f``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...geometry.polygon import ray_line_range
from .corners import wrap_angle


@dataclass
class WallFit:
    """Batched wall estimates (arrays of shape ``(B,)``)."""

    theta: np.ndarray
    d: np.ndarray
    h_c: np.ndarray
    h_f: np.ndarray
    ok: np.ndarray
    cost: np.ndarray

    @property
    def u(self) -> np.ndarray:
        return np.stack([np.cos(self.theta), np.sin(self.theta)], -1)

    @property
    def normal(self) -> np.ndarray:
        """``e2 = (-uy, ux)``: ``(B, 2)``, pointing from the camera to the wall."""
        return np.stack([-np.sin(self.theta), np.cos(self.theta)], -1)


def ransac_iterations(p_success: float = 0.9999, outlier_rate: float = 0.3, sample_size: int = 3) -> int:
    """``n_hyp = log(1 - P) / log(1 - (1 - eps)^k)`` (thesis §5.4.4), rounded up."""
    if not (0 < p_success < 1) or not (0 <= outlier_rate < 1):
        raise ValueError(f"ransac: need 0 < P < 1 and 0 <= eps < 1, got P={p_success}, eps={outlier_rate}")
    good = (1.0 - outlier_rate) ** sample_size
    if good >= 1.0:
        return 1
    return max(1, int(math.ceil(math.log(1.0 - p_success) / math.log(1.0 - good))))


def wall_rows(dir_c: np.ndarray, mom_c: np.ndarray, dir_f: np.ndarray, mom_f: np.ndarray,
              w_c: np.ndarray | None = None, w_f: np.ndarray | None = None) -> np.ndarray:
    """The DLT-like system of Eq. 5.4: ``(..., n_c + n_f, 7)`` rows on ``W = (ux, uy, vx, vy, wx, wy, d)``.

    ``dir_*``/``mom_*``: ``(..., n, 3)`` ray directions and moments; ``w_*``: ``(..., n)`` row
    weights (0 removes a row, e.g. padding).
    """
    zc = np.zeros(dir_c.shape[:-1])
    zf = np.zeros(dir_f.shape[:-1])
    rc = np.stack([mom_c[..., 0], mom_c[..., 1], dir_c[..., 1], -dir_c[..., 0], zc, zc, -dir_c[..., 2]], -1)
    rf = np.stack([mom_f[..., 0], mom_f[..., 1], zf, zf, dir_f[..., 1], -dir_f[..., 0], -dir_f[..., 2]], -1)
    if w_c is not None:
        rc = rc * w_c[..., None]
    if w_f is not None:
        rf = rf * w_f[..., None]
    return np.concatenate([rc, rf], -2)


def _right_singular_vectors(A: np.ndarray) -> np.ndarray:
    """``Vh (..., k, k)`` of ``A (..., n, k)`` with rows sorted by decreasing singular value.

    Tall systems use the eigenvectors of the ``k x k`` Gram matrix (far cheaper than an SVD of the
    ``n x k`` matrix; rows are normalised by the caller so the squared conditioning is harmless in
    float64); short ones (minimal samples) use the full SVD.
    """
    n, k = A.shape[-2], A.shape[-1]
    if n <= 3 * k:
        return np.linalg.svd(A, full_matrices=n < k)[2]
    G = np.swapaxes(A, -1, -2) @ A
    _, V = np.linalg.eigh(G)                      # ascending eigenvalues
    return np.swapaxes(V[..., ::-1], -1, -2)


def _quadratic_roots(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Real roots of ``a x^2 + b x + c`` ``(..., 2)`` (NaN where none; linear case handled)."""
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
    # numerically stable form
    q = -0.5 * (b + np.where(b >= 0, 1.0, -1.0) * sq)
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(np.abs(a) > 1e-300, q / a, np.nan)
        r2 = np.where(np.abs(q) > 1e-300, c / q, np.nan)
        lin = np.abs(a) <= 1e-14 * (np.abs(b) + np.abs(c) + 1e-300)
        r_lin = np.where(np.abs(b) > 1e-300, -c / b, np.nan)
    r1 = np.where(lin, r_lin, r1)
    r2 = np.where(lin, np.nan, r2)
    return np.stack([r1, r2], -1)


def _parallel_quadratic(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray):
    """Coefficients of ``cross(p0 + l p1, q0 + l q1) = 0`` in ``l`` (Eq. 5.6/5.7)."""
    def cr(a, b):
        return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return cr(p1, q1), cr(p0, q1) + cr(p1, q0), cr(p0, q0)


def _consistent(W: np.ndarray):
    """Parallel-consistent wall ``(theta, d, h_c, h_f)`` from a (possibly non-parallel) ``W (..., 7)``."""
    u, v, w, d = W[..., 0:2], W[..., 2:4], W[..., 4:6], W[..., 6]
    n2 = (u * u).sum(-1)
    n = np.sqrt(n2)
    safe = np.where(n2 > 0, n2, 1.0)
    h_c = (u * v).sum(-1) / safe
    h_f = (u * w).sum(-1) / safe
    dd = d / np.where(n > 0, n, 1.0)
    theta = np.arctan2(u[..., 1], u[..., 0])
    flip = dd < 0
    theta = np.where(flip, theta + math.pi, theta)
    dd = np.abs(dd)
    theta = wrap_angle(theta)
    return theta, dd, h_c, h_f, n


def wall_vector(theta, d, h_c, h_f) -> np.ndarray:
    """``W (..., 7)`` of a canonical wall (unit ``u``)."""
    u = np.stack([np.cos(theta), np.sin(theta)], -1)
    return np.concatenate([u, u * np.asarray(h_c)[..., None], u * np.asarray(h_f)[..., None],
                           np.asarray(d)[..., None]], -1)


def solve_walls_from_rows(A: np.ndarray) -> WallFit:
    """Single-wall solver (§5.4.1) on stacked rows ``A (B, n, 7)`` (zero rows are ignored).

    SVD -> the two smallest right singular vectors ``W0, W1`` span the solution space
    ``W = W0 + l W1``; parallelism ``u || v`` and ``u || w`` gives two quadratics in ``l``
    (Eq. 5.6/5.7). Every real root (and ``W0`` itself) is made consistent (``v = h_c u``,
    ``w = h_f u``) and the candidate with ``h_c > h_f`` and the smallest algebraic residual wins.
    """
    A = np.asarray(A, dtype=np.float64)
    B = A.shape[0]
    scale = np.sqrt((A * A).sum((-1, -2)) / np.maximum((np.abs(A).sum(-1) > 0).sum(-1), 1))
    scale = np.where(scale > 0, scale, 1.0)
    An = A / scale[:, None, None]
    try:
        Vh = _right_singular_vectors(An)
    except np.linalg.LinAlgError:
        nan = np.full(B, np.nan)
        return WallFit(nan, nan, nan, nan, np.zeros(B, bool), np.full(B, np.inf))
    W0, W1 = Vh[:, -1], Vh[:, -2]
    a1, b1, c1 = _parallel_quadratic(W0[:, 0:2], W1[:, 0:2], W0[:, 2:4], W1[:, 2:4])
    a2, b2, c2 = _parallel_quadratic(W0[:, 0:2], W1[:, 0:2], W0[:, 4:6], W1[:, 4:6])
    lam = np.concatenate([np.zeros((B, 1)), _quadratic_roots(a1, b1, c1), _quadratic_roots(a2, b2, c2)], -1)
    cand = W0[:, None] + np.nan_to_num(lam)[..., None] * W1[:, None]          # (B, 5, 7)
    theta, d, h_c, h_f, n = _consistent(cand)
    Wc = wall_vector(theta, d, h_c, h_f)                                          # (B, 5, 7)
    res = np.einsum("bnk,bck->bcn", An, Wc)
    cost = (res * res).sum(-1)
    good = np.isfinite(lam) & (h_c > h_f) & (n > 1e-9) & np.isfinite(cost)
    cost_sel = np.where(good, cost, np.inf)
    k = np.argmin(cost_sel, -1)
    idx = np.arange(B)
    ok = np.isfinite(cost_sel[idx, k])
    return WallFit(theta[idx, k], d[idx, k], h_c[idx, k], h_f[idx, k], ok, cost_sel[idx, k])


def solve_walls(dir_c, mom_c, dir_f, mom_f, w_c=None, w_f=None) -> WallFit:
    """Single-wall solver on batched rays ``(B, n, 3)`` (see :func:`solve_walls_from_rows`)."""
    return solve_walls_from_rows(wall_rows(dir_c, mom_c, dir_f, mom_f, w_c, w_f))


def predicted_elevation(theta, d, h, origin2: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Latitude at which each column sees a horizontal wall line, and the horizontal range.

    ``theta, d, h`` broadcast against ``origin2 (..., 2)`` (column optical centre, horizontal part)
    and ``b (..., 2)`` (unit horizontal direction of the column). Returns ``(lat, s)``; ``s <= 0``
    (the column does not face the wall) gives ``lat = NaN``.
    """
    s = ray_line_range(theta, d, origin2, b, eps=1e-9, facing=True)
    return np.arctan2(h, s), s


def manhattan_rows(dir_c, mom_c, dir_f, mom_f, label: np.ndarray, wall: np.ndarray, n_walls: int) -> np.ndarray:
    """Rows of the Manhattan layout solver (Eq. 5.4 for label 0, Eq. 5.8 for label 1).

    Unknown ``L_M = (ux, uy, vx, vy, wx, wy, d_1..d_N)``; ``label (N,)`` in {0, 1} is the Manhattan
    direction of each wall (``u`` or ``u_perp = (-uy, ux)``), ``wall (n,)`` the wall index of each
    column. Returns ``A (2n, 6 + N)``.
    """
    base = wall_rows(dir_c, mom_c, dir_f, mom_f)                       # (2n, 7)
    n = dir_c.shape[0]
    lab = np.concatenate([label[wall], label[wall]])
    rot = base.copy()
    # u -> u_perp = (-uy, ux): coefficient (a, b) on (ux, uy) becomes (b, -a)
    for s in (0, 2, 4):
        rot[:, s], rot[:, s + 1] = base[:, s + 1], -base[:, s]
    rows = np.where(lab[:, None] == 1, rot, base)
    A = np.zeros((2 * n, 6 + n_walls))
    A[:, :6] = rows[:, :6]
    wi = np.concatenate([wall, wall])
    A[np.arange(2 * n), 6 + wi] = rows[:, 6]
    return A


def solve_manhattan(A: np.ndarray, label: np.ndarray):
    """Manhattan layout solver (§5.4.2) on rows from :func:`manhattan_rows`.

    Returns ``(theta0, d (N,), h_c, h_f, ok)``: ``theta0`` the direction of label-0 walls (label-1
    walls have ``theta0 + pi/2``), ``d`` signed offsets along each wall's ``e2``.
    """
    A = np.asarray(A, float)
    col = np.sqrt((A * A).sum(0))
    used = col > 0
    n_walls = A.shape[1] - 6
    scale = np.sqrt((A * A).sum() / max(A.shape[0], 1)) or 1.0
    An = A[:, used] / scale
    try:
        Vh = _right_singular_vectors(An)
    except np.linalg.LinAlgError:
        return 0.0, np.zeros(n_walls), np.nan, np.nan, False
    W0 = np.zeros(A.shape[1])
    W1 = np.zeros(A.shape[1])
    W0[used], W1[used] = Vh[-1], Vh[-2]
    a1, b1, c1 = _parallel_quadratic(W0[0:2], W1[0:2], W0[2:4], W1[2:4])
    a2, b2, c2 = _parallel_quadratic(W0[0:2], W1[0:2], W0[4:6], W1[4:6])
    lam = np.concatenate([[0.0], _quadratic_roots(np.array(a1), np.array(b1), np.array(c1)),
                          _quadratic_roots(np.array(a2), np.array(b2), np.array(c2))])
    best = None
    for l in lam[np.isfinite(lam)]:
        W = W0 + l * W1
        u, v, w = W[0:2], W[2:4], W[4:6]
        n2 = float(u @ u)
        if n2 < 1e-18:
            continue
        h_c, h_f = float(u @ v) / n2, float(u @ w) / n2
        if not h_c > h_f:
            continue
        un = u / math.sqrt(n2)
        Wc = np.concatenate([un, h_c * un, h_f * un, W[6:] / math.sqrt(n2)])
        cost = float(np.sum((An @ Wc[used]) ** 2))
        if best is None or cost < best[0]:
            best = (cost, math.atan2(un[1], un[0]), Wc[6:], h_c, h_f)
    if best is None:
        return 0.0, np.zeros(n_walls), np.nan, np.nan, False
    _, theta0, d, h_c, h_f = best
    return theta0, d, h_c, h_f, True


def solve_manhattan_central(A: np.ndarray, camera_height: float):
    """Manhattan layout solver without moments (central panorama) on rows from :func:`manhattan_rows`.

    Unknown ``(v, w, d_1..d_N)`` (the moment columns of ``A`` vanish); the smallest singular vector
    gives the layout up to scale, ``u ∝ v - w``, and the floor is put at ``h_f = -camera_height``.
    Returns ``(theta0, d (N,), h_c, h_f, ok)`` as :func:`solve_manhattan`.
    """
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


def atlanta_rows(dir_c, mom_c, dir_f, mom_f, theta: np.ndarray, wall: np.ndarray, n_walls: int):
    """Rows of the Atlanta layout solver (Eq. 5.9): unknown ``(1, h_c, h_f, d_1..d_N)``.

    Rays are expressed in each wall's frame ``{e1 = u, e2, e3}`` (``theta (N,)`` known wall
    directions): ``xi_bar'_1 + h_c xi'_2 - d xi'_3 = 0``. Returns ``A (2n, 3 + N)``.
    """
    th = theta[wall]
    e1 = np.stack([np.cos(th), np.sin(th)], -1)
    e2 = np.stack([-np.sin(th), np.cos(th)], -1)
    n = dir_c.shape[0]
    A = np.zeros((2 * n, 3 + n_walls))
    r = np.arange(n)
    A[r, 0] = (mom_c[:, :2] * e1).sum(-1)
    A[r, 1] = (dir_c[:, :2] * e2).sum(-1)
    A[r, 3 + wall] = -dir_c[:, 2]
    A[n + r, 0] = (mom_f[:, :2] * e1).sum(-1)
    A[n + r, 2] = (dir_f[:, :2] * e2).sum(-1)
    A[n + r, 3 + wall] = -dir_f[:, 2]
    return A


def solve_atlanta(A: np.ndarray, fix_h_f: float | None = None):
    """Atlanta layout solver (§5.4.3): least squares with the first unknown fixed to 1.

    With ``fix_h_f`` (central panoramas: ``-camera_height``) the floor height is fixed instead and
    the homogeneous part is solved for the rest. Returns ``(h_c, h_f, d (N,), ok)``.
    """
    A = np.asarray(A, float)
    n_walls = A.shape[1] - 3
    used = np.sqrt((A * A).sum(0)) > 0
    if fix_h_f is None:
        cols = np.flatnonzero(used[1:]) + 1
        M, rhs = A[:, cols], -A[:, 0]
    else:
        cols = np.array([c for c in np.flatnonzero(used) if c not in (0, 2)], int)
        M, rhs = A[:, cols], -A[:, 2] * fix_h_f - A[:, 0]
    if len(cols) == 0 or M.shape[0] < len(cols):
        return math.nan, math.nan, np.zeros(n_walls), False
    try:
        # normal equations on column-scaled unknowns (tiny systems, many rows)
        cs = np.sqrt((M * M).sum(0))
        cs = np.where(cs > 0, cs, 1.0)
        Ms = M / cs
        x = np.linalg.solve(Ms.T @ Ms, Ms.T @ rhs) / cs
    except np.linalg.LinAlgError:
        return math.nan, math.nan, np.zeros(n_walls), False
    full = np.zeros(A.shape[1])
    full[cols] = x
    if fix_h_f is not None:
        full[2] = fix_h_f
    h_c, h_f, d = full[1], full[2], full[3:]
    ok = bool(np.all(np.isfinite(full)) and h_c > h_f)
    return float(h_c), float(h_f), d, ok


def solve_walls_central(dir_c: np.ndarray, dir_f: np.ndarray, w_c=None, w_f=None,
                        camera_height: float = 1.6) -> WallFit:
    """Single-wall solver for a central panorama (moments vanish): scale from the camera height.

    Unknown ``(vx, vy, wx, wy, d)``; the smallest singular vector gives the wall up to scale,
    ``u ∝ v - w`` (``h_c > 0 > h_f``), and the floor is put at ``h_f = -camera_height``.
    """
    zc = np.zeros(dir_c.shape[:-1])
    zf = np.zeros(dir_f.shape[:-1])
    rc = np.stack([dir_c[..., 1], -dir_c[..., 0], zc, zc, -dir_c[..., 2]], -1)
    rf = np.stack([zf, zf, dir_f[..., 1], -dir_f[..., 0], -dir_f[..., 2]], -1)
    if w_c is not None:
        rc = rc * w_c[..., None]
    if w_f is not None:
        rf = rf * w_f[..., None]
    A = np.concatenate([rc, rf], -2)
    B = A.shape[0]
    try:
        _, _, Vh = np.linalg.svd(A, full_matrices=A.shape[-2] < A.shape[-1])
    except np.linalg.LinAlgError:
        nan = np.full(B, np.nan)
        return WallFit(nan, nan, nan, nan, np.zeros(B, bool), np.full(B, np.inf))
    X = Vh[:, -1]
    v, w, d = X[:, 0:2], X[:, 2:4], X[:, 4]
    u = v - w
    nu = np.linalg.norm(u, axis=-1)
    u = u / np.where(nu > 0, nu, 1.0)[:, None]
    h_c, h_f = (u * v).sum(-1), (u * w).sum(-1)
    s = -camera_height / np.where(h_f != 0, h_f, np.nan)
    h_c, h_f, d = h_c * s, h_f * s, d * s
    theta = np.arctan2(u[:, 1], u[:, 0])
    theta = np.where(d < 0, theta + math.pi, theta)
    theta = wrap_angle(theta)
    d = np.abs(d)
    Wc = wall_vector(theta, d, h_c, h_f)
    ok = np.isfinite(h_c) & (h_c > 0) & (h_f < 0) & (nu > 1e-12)
    full = np.concatenate([np.zeros(A.shape[:-1] + (2,)), A], -1)
    res = np.einsum("bnk,bk->bn", full, Wc)
    return WallFit(theta, d, h_c, h_f, ok, np.where(ok, (res ** 2).sum(-1), np.inf))
