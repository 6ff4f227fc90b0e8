"""MPP visual gyroscope: yaw from a Mixture of Photometric Potentials (Caron & Morbidi 2018; thesis §6.2.2).

An image becomes a function on the sphere: the grey levels ``I_i`` sampled at the vertices ``X_i`` of an
icosahedron subdivided ``n`` times, normalised as libPeR's ``toAbsZN`` (``I <- |I - mean I|``, then divided
by its mean and by its sum), weight Gaussians of geodesic width ``lambda_g`` centred at the same vertices:

    G(s) = sum_i I_i c exp(-acos(X_i . s)^2 / (2 lambda_g^2)),   c = 1 / (lambda_g^3 (2 pi)^1.5)

The cost is ``C(R) = sum_g (G_cur(R.T s_g) - G_ref(s_g))^2`` over the Gaussian centres ``s_g`` (same
vertices, reference frame), minimised by Gauss-Newton on the yaw only: ``R <- exp(theta [a]x) R`` with
``a`` the vertical of the reference frame, analytic Jacobian ``((R grad G_cur(p_g)) x s_g) . a`` where
``grad G(p) = sum_i I_i c exp(-d_i^2 / 2 lambda_g^2) (d_i / lambda_g^2) X_i / sin d_i``. Several
initial yaws (``tries``, spread over 360°) run as one batch; the lowest final cost wins.

Speed: ``G_cur`` and its gradient are smooth at the scale ``lambda_g``; with ``grid_height > 0`` they are
tabulated once per image on an equirectangular grid (``grid_height x 2 grid_height``, default 32, i.e.
5.6° spacing for a field of width 18.6°; 0.3 % max error) and read bilinearly at the rotated centres in every iteration,
instead of re-summing all ``N x N`` Gaussian pairs. ``grid_height=0`` evaluates the sums exactly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import torch
from torch import Tensor

from omnidl.cameras.equirectangular import Equirectangular
from omnidl.geometry.panorama import sample_panorama

from .icosahedron import icosahedron_vertices
from .photometric import SphereImage, blur_fast, rodrigues, to_gray


def abs_zn(I: Tensor) -> Tensor:
    """libPeR ``toAbsZN`` on ``(..., N)`` samples: zero mean, absolute value, divided by mean then sum."""
    I = (I - I.mean(-1, keepdim=True)).abs()
    I = I / I.mean(-1, keepdim=True).clamp_min(1e-12)
    return I / I.sum(-1, keepdim=True).clamp_min(1e-12)


def mpp_samples(image: Tensor, level: int = 3, prefilter: bool = True) -> tuple[Tensor, Tensor]:
    """Normalised grey levels of ``image (B, C, H, W)`` at the level-``level`` vertices.

    Returns ``(vertices (N, 3), weights (B, N))``. ``prefilter`` blurs the image to about the vertex
    spacing first (anti-aliasing; libPeR samples bilinearly without it), with :func:`blur_fast`
    (:func:`mpp_yaw` and the reference solvers of the tests and the benchmark read these samples).
    """
    gray = to_gray(image)
    X = icosahedron_vertices(level, gray.dtype, gray.device)
    if prefilter:
        spacing = 1.1 / (2 ** level)  # ~ edge angle of the subdivided mesh (rad)
        gray = blur_fast(gray, 0.5 * spacing * gray.shape[-1] / (2 * math.pi))
    return X, abs_zn(sample_panorama(gray, X)[:, 0])


def mpp_field(X: Tensor, I: Tensor, points: Tensor, lambda_g: float, with_grad: bool = False):
    """Evaluate the MPP ``G`` (and its ambient gradient) of samples ``X (N, 3)``, ``I (B, N)`` at
    ``points (B, ..., M, 3)``. Returns ``G (B, ..., M)`` and ``grad (B, ..., M, 3)`` or None."""
    c = 1.0 / (lambda_g ** 3 * (2 * math.pi) ** 1.5)
    dot = (points @ X.T).clamp(-1.0, 1.0)  # (B, ..., M, N)
    d = torch.acos(dot)
    k = c * torch.exp(-d * d / (2 * lambda_g ** 2))
    Ib = I.reshape(I.shape[0], *([1] * (points.ndim - 2)), I.shape[-1])  # (B, 1.., N)
    wk = k * Ib
    G = wk.sum(-1)
    if not with_grad:
        return G, None
    sin = torch.sqrt((1 - dot * dot).clamp_min(0))
    ratio = torch.where(sin > 1e-7, d / sin.clamp_min(1e-7), torch.ones_like(d))
    grad = (wk * ratio / lambda_g ** 2) @ X  # (B, ..., M, 3)
    return G, grad


@lru_cache(maxsize=8)
def _kernels(level: int, lambda_g: float, height: int, dtype: torch.dtype, device: str) -> tuple[Tensor, Tensor]:
    """The image-independent part of :func:`mpp_field` at fixed points: ``K (M, N)`` with ``G = K @ I`` and
    ``Kr (M, N)`` with ``grad = Kr @ (I X)``; points = the ``height x 2 height`` table grid, or the vertices
    themselves for ``height = 0``. Cached: a table is then two small GEMMs instead of ``M x N``
    transcendental evaluations per image (M = 2048, N = 642 at the defaults: 10 MiB in float32)."""
    X = icosahedron_vertices(level, torch.float64, device)
    d = X if height == 0 else Equirectangular(width=2 * height, height=height).unproject_grid(
        torch.float64, device).direction.reshape(-1, 3)
    c = 1.0 / (lambda_g ** 3 * (2 * math.pi) ** 1.5)
    dot = (d @ X.T).clamp(-1.0, 1.0)
    ang = torch.acos(dot)
    k = c * torch.exp(-ang * ang / (2 * lambda_g ** 2))
    sin = torch.sqrt((1 - dot * dot).clamp_min(0))
    ratio = torch.where(sin > 1e-7, ang / sin.clamp_min(1e-7), torch.ones_like(ang))
    return k.to(dtype), (k * ratio / lambda_g ** 2).to(dtype)


def _level_of(X: Tensor) -> int | None:
    n = X.shape[0]
    for level in range(9):
        if 10 * 4 ** level + 2 == n:
            return level
    return None


def _is_icosahedron(X: Tensor, level: int) -> bool:
    ico = icosahedron_vertices(level, X.dtype, X.device)
    return X is ico or torch.equal(X, ico)


@lru_cache(maxsize=8)
def _symmetric_kernels(level: int, lambda_g: float, height: int, dtype: torch.dtype, device: str):
    """The table kernels of :func:`_kernels` on one octant of the grid, with the maps that give the rest.

    The icosahedron vertices (``(0, +-1, +-phi)`` cyclic, subdivided by midpoints) and the equirectangular grid
    are both invariant under the 8 coordinate sign flips ``s`` (columns ``j <-> W - 1 - j`` and
    ``W/2 - 1 - j``, rows ``i <-> H - 1 - i``), so with ``X[perm_s] = s X``:
    ``G(s d) = K_o[d] . I[perm_s]`` and ``grad(s d) = s (Kr_o[d] @ (I[perm_s] X))`` for ``d`` in the octant
    ``x, y, z > 0``: the kernel rows read per table are 8x fewer (1.3 MB instead of 10 MB at the defaults:
    they stay in cache). Returns ``(K_o, Kr_o (M/8, N), perm (8, N), signs (8, 3), order (M,))`` with the
    table = ``(values per (s, octant point)).flatten()[order]``, or ``None`` when a sign flip of a vertex or
    grid point is not one (then :func:`mpp_table` uses the full kernels). The grid directions are
    mirror images to ~2e-8 only (their float64 construction), so the symmetry serves float32 tables."""
    X = icosahedron_vertices(level, torch.float64, device)
    d = Equirectangular(width=2 * height, height=height).unproject_grid(torch.float64, device).direction.reshape(-1, 3)
    signs = torch.tensor([[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)], dtype=torch.float64,
                         device=device)
    octant = torch.nonzero((d > 0).all(-1))[:, 0]
    if 8 * octant.numel() != d.shape[0]:
        return None
    perm, where = [], torch.empty(d.shape[0], dtype=torch.int64, device=device)
    for k, sg in enumerate(signs):
        dist, idx = torch.cdist(X * sg, X).min(-1)  # X[idx] = s X
        pd, pidx = torch.cdist(d[octant] * sg, d).min(-1)  # d[pidx] = s d_octant
        if float(dist.max()) > 1e-6 or float(pd.max()) > 1e-6:  # (the grid is mirror-exact to ~2e-8 only)
            return None
        perm.append(idx)
        where[pidx] = k * octant.numel() + torch.arange(octant.numel(), device=device)
    K, Kr = _kernels(level, float(lambda_g), int(height), torch.float64, device)
    return (K[octant].to(dtype), Kr[octant].to(dtype), torch.stack(perm), signs.to(dtype), where)


def mpp_table(X: Tensor, I: Tensor, lambda_g: float, height: int = 32) -> Tensor:
    """``(B, 4, h, 2h)`` equirect table of ``G`` and its ambient gradient (channels ``G, gx, gy, gz``) of samples
    ``I (B, N)`` at ``X (N, 3)``: the values of :func:`mpp_field` at the grid up to float rounding.

    For icosahedron vertices ``X`` the image-independent kernels are cached per (level, lambda_g, height)
    (:func:`_kernels`): in float32 those of one grid octant with the 8 sign-flip symmetries
    (:func:`_symmetric_kernels`: ~10 ops on in-cache data instead of two passes over 10 MB of kernels); in float64
    (or without the symmetry) ``G = I @ K.T``, ``grad.T = (I X).T @ Kr.T`` (the small operand on the left).
    Other ``X``: :func:`mpp_field` at the grid directions."""
    level = _level_of(X)
    if level is None or X.dtype not in (torch.float32, torch.float64) or not _is_icosahedron(X, level):
        B = I.shape[0]
        d = Equirectangular(width=2 * height, height=height).unproject_grid(X.dtype, X.device).direction
        G, grad = mpp_field(X, I, d.reshape(-1, 3).unsqueeze(0).expand(B, -1, -1), lambda_g, with_grad=True)
        return torch.cat([G.unsqueeze(-1), grad], -1).transpose(1, 2).reshape(B, 4, height, 2 * height)
    B, N = I.shape
    sym = None if X.dtype != torch.float32 else _symmetric_kernels(level, float(lambda_g), int(height), X.dtype,
                                                                    str(X.device))
    if sym is None:
        K, Kr = _kernels(level, float(lambda_g), int(height), X.dtype, str(X.device))
        G = I @ K.T  # (B, M)
        grad = (I.unsqueeze(1) * X.T.contiguous()).reshape(3 * B, -1) @ Kr.T  # (3B, N) row-major @ (N, M)
        return torch.cat([G.unsqueeze(1), grad.view(B, 3, -1)], 1).view(B, 4, height, 2 * height)
    Ko, Kro, perm, signs, where = sym
    Ip = I[:, perm]  # (B, 8, N): samples re-indexed by each flip
    G = Ip @ Ko.T  # (B, 8, M/8)
    grad = ((Ip.unsqueeze(2) * X.T.contiguous()).view(B, 24, N) @ Kro.T).view(B, 8, 3, -1) * signs[:, :, None]
    vals = torch.cat([G.unsqueeze(2), grad], 2)  # (B, 8, 4, M/8)
    return vals.transpose(1, 2).reshape(B, 4, -1)[:, :, where].view(B, 4, height, 2 * height)


def mpp_vertex_field(X: Tensor, I: Tensor, lambda_g: float) -> Tensor:
    """``G`` of samples ``I (B, N)`` at the vertices ``X`` themselves ``(B, N)`` (cached kernel when ``X`` is an
    icosahedron; equals ``mpp_field(X, I, X[None], lambda_g)[0]`` up to rounding)."""
    level = _level_of(X)
    if level is not None and X.dtype in (torch.float32, torch.float64) and _is_icosahedron(X, level):
        return I @ _kernels(level, float(lambda_g), 0, X.dtype, str(X.device))[0].T
    return mpp_field(X, I, X.unsqueeze(0), lambda_g)[0]


@dataclass
class MPPResult:
    rotation: Tensor   # (B, 3, 3) estimated R_ref_cur
    yaw: Tensor        # (B,) yaw correction applied to the initial rotation (radians)
    cost: Tensor       # (B,) final cost
    iterations: int


def mpp_yaw(current: Tensor, reference: Tensor, R_init: Tensor | None = None, axis: Tensor | None = None,
            level: int = 3, lambda_g: float = 0.325, tries: int = 4, max_iter: int = 30, tol: float = 1e-6,
            prefilter: bool = True, reference_samples: Tensor | None = None, grid_height: int = 32,
            reference_field: Tensor | None = None) -> MPPResult:
    """Yaw of ``current`` w.r.t. ``reference`` (both ``(B, C, H, W)`` equirect, or ``reference (1, ...)``).

    Args:
        R_init: ``(B, 3, 3)`` initial ``R_ref_cur`` (e.g. the tilt from the horizon hook); identity default.
        axis: ``(3,)`` or ``(B, 3)`` yaw axis in the reference frame (default its vertical, ``y``).
        level, lambda_g: icosahedron subdivision ``n`` and Gaussian width (rad), thesis n = 3, 0.325.
        tries: initial yaws spread evenly over 360°, solved as one batch (1 = start from ``R_init``).
        reference_samples: precomputed ``mpp_samples(reference)[1]`` to reuse over a sequence.
        grid_height: tabulate ``G_cur`` on a ``grid_height x 2 grid_height`` grid (:func:`mpp_table`, read
            bilinearly); 0 = the exact sums of :func:`mpp_field` at the rotated centres in every iteration.
        max_iter, tol: Gauss-Newton stops when every yaw step is below ``tol`` rad or after ``max_iter``.
        reference_field: ``mpp_vertex_field(X, reference_samples, lambda_g)`` ``(B|1, N)`` prepared once per
            reference (then ``reference`` and ``reference_samples`` are not read).
    Returns:
        :class:`MPPResult` with ``rotation = exp(yaw [axis]x) R_init``.
    """
    B = current.shape[0]
    dtype = current.dtype if current.dtype == torch.float64 else torch.float32
    current = current.to(dtype)
    eye = torch.eye(3, dtype=dtype, device=current.device)
    R0 = eye.expand(B, 3, 3) if R_init is None else R_init.to(dtype).expand(B, 3, 3)
    a = torch.tensor([0.0, 1.0, 0.0], dtype=dtype, device=current.device) if axis is None else axis.to(dtype)
    a = (a / a.norm(dim=-1, keepdim=True)).expand(B, 3)
    # the samples by sample_panorama of the prefiltered image: the yaw is the evaluated angle of least cost, and
    # near convergence two angles ~1e-5 apart have costs equal to rounding, so a perturbation of the samples of
    # 1e-8 (a GEMM blur) can flip the pick (the loop below perturbs the costs much less)
    X, Ic = mpp_samples(current, level, prefilter)
    if reference_field is None:
        Ir = mpp_samples(reference.to(dtype), level, prefilter)[1] if reference_samples is None else \
            reference_samples.to(dtype)
        reference_field = mpp_vertex_field(X, Ir, lambda_g)
    G_ref = reference_field.to(dtype).expand(B, X.shape[0])
    return _mpp_loop(X, Ic, G_ref, R0, a, lambda_g, tries, max_iter, tol, grid_height)


def _mpp_loop(X: Tensor, Ic: Tensor, G_ref: Tensor, R0: Tensor, a: Tensor, lambda_g: float, tries: int,
              max_iter: int, tol: float, grid_height: int) -> MPPResult:
    """The Gauss-Newton loop of :func:`mpp_yaw`, ~35 ops per iteration for all starts.

    ``R(theta) = E(theta) R0`` with ``E = I + sin K + (1 - cos) K^2`` (Rodrigues, ``K = [a]x``), so the rotated
    centres ``p = X @ R`` and the Jacobian directions ``D = (X x a) @ R`` (``J = grad . D``) are
    ``P0 + sin P1 + (1 - cos) P2`` with ``P0..P2`` computed once: per iteration one ``(B, T, 3) x (B, 3, 6N)``
    product gives all starts' points and directions as component rows (contiguous reads); ``G`` and its gradient
    are read there from the table (or summed exactly), ``J.J``, ``J.e``, ``e.e`` come from one small product, in
    buffers allocated once."""
    B, dtype, dev = Ic.shape[0], Ic.dtype, Ic.device
    T = max(1, int(tries))
    theta = (torch.arange(T, dtype=dtype, device=dev) * (2 * math.pi / T)).expand(B, T).clone()
    theta = torch.remainder(theta + math.pi, 2 * math.pi) - math.pi
    M = X.shape[0]
    zero = torch.zeros_like(a[:, 0])
    K = torch.stack([zero, -a[:, 2], a[:, 1], a[:, 2], zero, -a[:, 0], -a[:, 1], a[:, 0], zero], -1).view(B, 3, 3)
    KR0, K2R0 = K @ R0, K @ (K @ R0)
    XC = torch.cat([X.expand(B, M, 3), torch.linalg.cross(X.unsqueeze(0), a[:, None, :], dim=-1)], 1)  # (B, 2M, 3)
    # (B, 3, 6M): for each of P0, P1, P2 the x, y, z rows of p, then those of D
    basis = torch.stack([(XC @ m).view(B, 2, M, 3).permute(0, 1, 3, 2) for m in (R0, KR0, K2R0)], 1)
    basis = basis.reshape(B, 3, 6 * M)
    if grid_height > 0:
        read = SphereImage(mpp_table(X, Ic, lambda_g, grid_height)).read_grid
    else:
        def read(x: Tensor, y: Tensor, z: Tensor) -> Tensor:  # the exact sums at the points
            G, grad = mpp_field(X, Ic, torch.stack([x, y, z], -1), lambda_g, with_grad=True)  # (B, T, M), (.., 3)
            return torch.cat([G.unsqueeze(1), grad.permute(0, 3, 1, 2)], 1)
    best_cost = torch.full((B, T), float("inf"), dtype=dtype, device=dev)
    best_theta = theta.clone()
    # buffers written in place every iteration, and their views, made once (a view costs as much as a small op)
    k = torch.ones(B, T, 3, dtype=dtype, device=dev)  # [1, sin theta, 1 - cos theta] per start
    k_sin, k_cos = k[..., 1], k[..., 2]
    pd = torch.empty(B, T, 6 * M, dtype=dtype, device=dev)  # components of p (x, y, z rows), then of D
    p_xyz = pd.view(B, T, 2, 3, M)[:, :, 0].unbind(2)  # (B, T, M) each
    D = pd.view(B, T, 2, 3, M)[:, :, 1].transpose(1, 2)  # (B, 3, T, M)
    je = torch.empty(B * T, 2, M, dtype=dtype, device=dev)  # rows J, e per start
    J_out, e_out = je.view(B, T, 2, M).unbind(2)
    S = torch.empty(B * T, 2, 2, dtype=dtype, device=dev)
    JJ, Je, _, ee = S.view(B, T, 4).unbind(-1)  # J.J, J.e, e.J, e.e
    jeT = je.transpose(1, 2)
    G_ref = G_ref.unsqueeze(1)  # (B, 1, M)
    it = 0
    for it in range(1, max_iter + 1):
        torch.sin(theta, out=k_sin)
        torch.cos(theta, out=k_cos).neg_().add_(1.0)  # 1 - cos, exactly
        torch.bmm(k, basis, out=pd)
        v = read(*p_xyz).view(B, 4, T, M)
        torch.sum(v[:, 1:] * D, 1, out=J_out)  # J = grad . D
        torch.sub(v[:, 0], G_ref, out=e_out)  # e = G - G_ref
        torch.bmm(je, jeT, out=S)
        better = ee < best_cost
        best_cost = torch.where(better, ee, best_cost)
        best_theta = torch.where(better, theta, best_theta)
        q = (Je / JJ.clamp_min(1e-30)).clamp_(-0.5, 0.5)  # = -step, at most ~29°
        theta = theta - q
        if bool(q.abs().max() < tol):
            break
    k = best_cost.argmin(-1)
    yaw = best_theta.gather(1, k[:, None])[:, 0]
    yaw = torch.remainder(yaw + math.pi, 2 * math.pi) - math.pi
    R = rodrigues(yaw[:, None] * a) @ R0
    return MPPResult(R, yaw, best_cost.gather(1, k[:, None])[:, 0], it)
