"""Reference implementations of the photometric gyroscopes' solvers: the test oracles of
:mod:`omnidl.postprocess.gyroscope` (and the benchmark's baselines).

These are the plain versions the library's solvers replaced (issue 17): PVG's Gauss-Newton loop on
``sample_panorama`` reads and the kornia rotation update (:func:`pvg_refine_reference`), MPP's loop on the full
cached kernels or on the exact ``N x N`` sums (:func:`mpp_yaw_reference`; with ``tries=1, grid_height=0`` it is the
published gyroscope's evaluation, the baseline of ``benchmarks/gyroscope.py``), the padded-convolution blur and the
Jacobian helpers they use. The library's results are compared with them in ``tests/postprocess/gyroscope``;
the library does not call them.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from omnidl.cameras.equirectangular import Equirectangular
from omnidl.geometry.panorama import sample_panorama
from omnidl.geometry.rotations import axis_angle_to_matrix
from omnidl.postprocess.gyroscope.icosahedron import icosahedron_vertices
from omnidl.postprocess.gyroscope.mpp import (MPPResult, _is_icosahedron, _kernels, _level_of, mpp_field,
                                              mpp_samples)
from omnidl.postprocess.gyroscope.photometric import _gaussian_taps, damped_step, to_gray
from omnidl.postprocess.gyroscope.pvg import PVGResult


# ---- shared pieces ------------------------------------------------------------------------------------------------

def blur(image: Tensor, sigma_px: float) -> Tensor:
    """Separable Gaussian blur of ``(B, C, H, W)``; wraps horizontally, replicates vertically."""
    if sigma_px <= 0:
        return image
    r, k = _gaussian_taps(sigma_px, image.dtype, image.device)
    C = image.shape[1]
    img = F.pad(image, (r, r, 0, 0), mode="circular") if r < image.shape[-1] else image.repeat(1, 1, 1, 3)[
        ..., image.shape[-1] - r: 2 * image.shape[-1] + r]
    img = F.conv2d(img, k.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    img = F.pad(img, (0, 0, r, r), mode="replicate")
    return F.conv2d(img, k.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)


def apply_update(R: Tensor, w: Tensor) -> Tensor:
    """``exp([w]x) @ R`` for ``R (..., 3, 3)``, ``w (..., 3)``."""
    return axis_angle_to_matrix(w) @ R


def rotation_jacobian(grad_cur: Tensor, R: Tensor, s: Tensor) -> Tensor:
    """``(R grad) x s``: ``grad_cur (..., N, 3)`` ambient gradients at ``p = R.T s``, ``R (..., 3, 3)``,
    ``s (N, 3)`` reference-frame points -> ``(..., N, 3)`` Jacobian rows w.r.t. ``w``."""
    g_ref = torch.einsum("...ij,...nj->...ni", R, grad_cur)
    return torch.linalg.cross(g_ref, s.expand_as(g_ref), dim=-1)


def gauss_newton_step(J: Tensor, e: Tensor, damping: float = 1e-9) -> Tensor:
    """Solve ``min |J dx + e|^2`` per batch: ``J (..., N, D)``, ``e (..., N)`` -> ``dx (..., D)``."""
    A = J.transpose(-1, -2) @ J
    b = (J.transpose(-1, -2) @ e.unsqueeze(-1)).squeeze(-1)
    return damped_step(A, b, damping)


# ---- PVG ----------------------------------------------------------------------------------------------------------

def tangent_basis(p: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit tangent vectors ``(..., 3)`` orthogonal to unit ``p (..., 3)`` and to each other."""
    ex = torch.zeros_like(p)
    ex[..., 0] = 1
    ey = torch.zeros_like(p)
    ey[..., 1] = 1
    a = torch.where((p[..., :1].abs() < 0.9), ex, ey)
    t1 = torch.linalg.cross(a, p, dim=-1)
    t1 = t1 / t1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return t1, torch.linalg.cross(p, t1, dim=-1)


def spherical_gradient(image: Tensor, p: Tensor, h: float | None = None) -> tuple[Tensor, Tensor]:
    """Values ``(B, N)`` and ambient (tangent) gradients ``(B, N, 3)`` of ``image (B, 1, H, W)`` at unit
    directions ``p (B, N, 3)``, by central differences of bilinear reads ``h`` radians apart."""
    H = image.shape[-2]
    h = math.pi / H if h is None else h
    t1, t2 = tangent_basis(p)
    pts = torch.stack([p, p + h * t1, p - h * t1, p + h * t2, p - h * t2], 1)  # (B, 5, N, 3)
    pts = pts / pts.norm(dim=-1, keepdim=True)
    B, _, N, _ = pts.shape
    v = sample_panorama(image, pts.reshape(B, -1, 3))[:, 0].reshape(B, 5, N)
    # chord length of a tangent step of h after normalisation: 2 * sin(atan(h)) / ... ~ arc atan(h)
    step = 2 * math.atan(h)
    grad = ((v[:, 1] - v[:, 2]) / step)[..., None] * t1 + ((v[:, 3] - v[:, 4]) / step)[..., None] * t2
    return v[:, 0], grad


# ---- MPP ----------------------------------------------------------------------------------------------------------

def mpp_table_reference(X: Tensor, I: Tensor, lambda_g: float, height: int = 64) -> Tensor:
    """``(B, 4, h, 2h)`` equirect table of ``G`` and its ambient gradient (channels ``G, gx, gy, gz``).

    For icosahedron vertices ``X`` the kernels are cached per (level, lambda_g, height) and the table is two
    GEMMs (:func:`_kernels`; same values as :func:`mpp_field` at the grid up to float rounding)."""
    B = I.shape[0]
    level = _level_of(X)
    if level is not None and X.dtype in (torch.float32, torch.float64) and _is_icosahedron(X, level):
        K, Kr = _kernels(level, float(lambda_g), int(height), X.dtype, str(X.device))
        G = I @ K.T  # (B, M)
        grad = (Kr @ (I.T.unsqueeze(-1) * X.unsqueeze(1)).reshape(X.shape[0], B * 3)).view(-1, B, 3)  # (M, B, 3)
        return torch.cat([G.unsqueeze(1), grad.permute(1, 2, 0)], 1).reshape(B, 4, height, 2 * height)
    d = Equirectangular(width=2 * height, height=height).unproject_grid(X.dtype, X.device).direction.reshape(-1, 3)
    G, grad = mpp_field(X, I, d.unsqueeze(0).expand(B, -1, -1), lambda_g, with_grad=True)
    return torch.cat([G.unsqueeze(-1), grad], -1).transpose(1, 2).reshape(B, 4, height, 2 * height)


def mpp_yaw_reference(current: Tensor, reference: Tensor, R_init: Tensor | None = None, axis: Tensor | None = None,
                      level: int = 3, lambda_g: float = 0.325, tries: int = 4, max_iter: int = 30, tol: float = 1e-6,
                      prefilter: bool = True, reference_samples: Tensor | None = None,
                      grid_height: int = 32) -> MPPResult:
    """:func:`omnidl.postprocess.gyroscope.mpp.mpp_yaw` as first written (its ``impl="reference"``): per iteration
    the rotations by the kornia update, the points by ``einsum``, the field read from :func:`mpp_table_reference`
    by :func:`sample_panorama` (``grid_height=0``: the exact ``N x N`` sums of :func:`mpp_field`)."""
    B = current.shape[0]
    dtype = current.dtype if current.dtype == torch.float64 else torch.float32
    current = current.to(dtype)
    eye = torch.eye(3, dtype=dtype, device=current.device)
    R0 = eye.expand(B, 3, 3) if R_init is None else R_init.to(dtype).expand(B, 3, 3)
    a = torch.tensor([0.0, 1.0, 0.0], dtype=dtype, device=current.device) if axis is None else axis.to(dtype)
    a = (a / a.norm(dim=-1, keepdim=True)).expand(B, 3)
    X, Ic = mpp_samples(current, level, prefilter)
    if reference_samples is None:
        _, Ir = mpp_samples(reference.to(dtype), level, prefilter)
    else:
        Ir = reference_samples.to(dtype)
    if Ir.shape[0] == 1 and B > 1:
        Ir = Ir.expand(B, -1)
    G_ref, _ = mpp_field(X, Ir, X.unsqueeze(0), lambda_g)  # (B, M)
    T = max(1, int(tries))
    theta = (torch.arange(T, dtype=dtype, device=current.device) * (2 * math.pi / T)).expand(B, T).clone()
    theta = torch.remainder(theta + math.pi, 2 * math.pi) - math.pi
    best_cost = torch.full((B, T), float("inf"), dtype=dtype, device=current.device)
    best_theta = theta.clone()
    table = mpp_table_reference(X, Ic, lambda_g, grid_height) if grid_height > 0 else None
    it = 0
    for it in range(1, max_iter + 1):
        R = apply_update(R0.unsqueeze(1), theta[..., None] * a.unsqueeze(1))  # (B, T, 3, 3)
        p = torch.einsum("btji,mj->btmi", R, X)  # R.T s_g
        if table is None:
            G, grad = mpp_field(X, Ic, p, lambda_g, with_grad=True)  # (B, T, M), (B, T, M, 3)
        else:
            v = sample_panorama(table, p.reshape(B, -1, 3)).reshape(B, 4, T, -1)
            G, grad = v[:, 0], v[:, 1:].permute(0, 2, 3, 1)
        e = G - G_ref.unsqueeze(1)
        cost = (e * e).sum(-1)
        better = cost < best_cost
        best_cost = torch.where(better, cost, best_cost)
        best_theta = torch.where(better, theta, best_theta)
        J = (rotation_jacobian(grad, R, X) * a[:, None, None, :]).sum(-1)  # (B, T, M)
        step = -(J * e).sum(-1) / (J * J).sum(-1).clamp_min(1e-30)
        step = step.clamp(-0.5, 0.5)  # at most ~29° per iteration
        theta = theta + step
        if bool((step.abs() < tol).all()):
            break
    k = best_cost.argmin(-1)
    yaw = best_theta.gather(1, k[:, None])[:, 0]
    yaw = torch.remainder(yaw + math.pi, 2 * math.pi) - math.pi
    R = apply_update(R0, yaw[:, None] * a)
    return MPPResult(R, yaw, best_cost.gather(1, k[:, None])[:, 0], it)


def pvg_refine_reference(current: Tensor, reference: Tensor, R_init: Tensor | None = None, level: int = 5,
                         max_iter: int = 30, tol: float = 1e-6, blur_px: Sequence[float] = (4.0, 1.5, 0.5),
                         dofs: Sequence[bool] = (True, True, True)) -> PVGResult:
    """:func:`omnidl.postprocess.gyroscope.pvg.pvg_refine` as first written (its ``impl="reference"``): per
    iteration the five reads of :func:`spherical_gradient` by :func:`sample_panorama`, the Jacobian rows of
    :func:`rotation_jacobian`, the solve of :func:`gauss_newton_step` and the kornia update."""
    dtype = current.dtype if current.dtype == torch.float64 else torch.float32
    cur = to_gray(current.to(dtype))
    B = cur.shape[0]
    X = icosahedron_vertices(level, dtype, cur.device)
    R = (torch.eye(3, dtype=dtype, device=cur.device) if R_init is None else R_init.to(dtype)).expand(B, 3, 3).clone()
    ref = to_gray(reference.to(dtype))
    if ref.shape[0] == 1 and B > 1:
        ref = ref.expand(B, -1, -1, -1)
    mask = torch.tensor([bool(d) for d in dofs], device=cur.device)
    it_total = 0
    cost = torch.zeros(B, dtype=dtype, device=cur.device)
    for sigma in blur_px:
        c_img, r_img = blur(cur, sigma), blur(ref, sigma)
        I_ref = sample_panorama(r_img, X)[:, 0]  # (B, N)
        for _ in range(max_iter):
            it_total += 1
            p = torch.einsum("bji,nj->bni", R, X)
            I_cur, grad = spherical_gradient(c_img, p)
            e = I_cur - I_ref
            cost = (e * e).mean(-1)
            J = rotation_jacobian(grad, R, X)[..., mask]  # (B, N, D)
            dx = gauss_newton_step(J, e)
            w = torch.zeros(B, 3, dtype=dtype, device=cur.device)
            w[:, mask] = dx
            n = w.norm(dim=-1, keepdim=True)
            w = w * (0.35 / n).clamp(max=1.0)  # trust region: at most 20° per step
            R = apply_update(R, w)
            if bool((n < tol).all()):
                break
    return PVGResult(R, cost, it_total)
