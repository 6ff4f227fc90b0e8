"""PVG, the photometric visual gyroscope (André & Caron 2022; thesis §6.2.3): 3-DoF rotation refinement.

Raw grey levels (no normalisation) of the reference at the vertices ``X_i`` of an icosahedron subdivided
``n`` times (default 5, 10242 vertices) are compared with the current image read at ``p_i = R.T X_i``:

    C(R) = sum_i (I_cur(R.T X_i) - I_ref(X_i))^2

Gauss-Newton on the three rotation angles, ``R <- exp([w]x) R``, with the analytic Jacobian
``(R grad I_cur(p_i)) x X_i``. The spherical image gradient ``grad I_cur(p)`` is taken in the image
(bilinear reads of the equirectangular image at ``p`` moved by +-h along two tangent directions,
``h`` = one pixel of latitude), so it has no singularity at the poles. The convergence domain is narrow
(~±12.5° in the thesis): start from HoLiNet + MPP. A coarse-to-fine schedule of Gaussian blurs
(``blur_px``) widens it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from omnidl.geometry.panorama import sample_panorama

from .icosahedron import icosahedron_vertices
from .photometric import SphereImage, apply_update, blur, gauss_newton_step, rodrigues, rotation_jacobian, to_gray


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


def spherical_gradient_fast(image: SphereImage, p: Tensor, h: float | None = None) -> tuple[Tensor, Tensor]:
    """:func:`spherical_gradient` of a prepared :class:`SphereImage` (same tangent basis, same five reads;
    the offset points are not re-normalised since the reads only depend on the direction)."""
    h = math.pi / image.H if h is None else h
    px, py, pz = p.unbind(-1)
    use_x = px.abs() < 0.9  # a = e_x: a x p = (0, -pz, py); a = e_y: a x p = (pz, 0, -px)
    zero = torch.zeros_like(px)
    t1 = torch.stack([torch.where(use_x, zero, pz), torch.where(use_x, -pz, zero), torch.where(use_x, py, -px)], -1)
    t1 = t1 / t1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    t2 = torch.linalg.cross(p, t1, dim=-1)
    ht1, ht2 = h * t1, h * t2
    pts = torch.stack([p, p + ht1, p - ht1, p + ht2, p - ht2], 1)  # (B, 5, N, 3)
    B, _, N, _ = pts.shape
    v = image.read(pts.view(B, 5 * N, 3))[:, 0].view(B, 5, N)
    step = 2 * math.atan(h)
    grad = ((v[:, 1] - v[:, 2]) / step)[..., None] * t1 + ((v[:, 3] - v[:, 4]) / step)[..., None] * t2
    return v[:, 0], grad


@dataclass
class PVGResult:
    rotation: Tensor  # (B, 3, 3) refined R_ref_cur
    cost: Tensor      # (B,) final mean squared residual
    iterations: int


def pvg_refine(current: Tensor, reference: Tensor, R_init: Tensor | None = None, level: int = 5,
               max_iter: int = 30, tol: float = 1e-6, blur_px: Sequence[float] = (4.0, 1.5, 0.5),
               dofs: Sequence[bool] = (True, True, True), impl: str = "fast") -> PVGResult:
    """Refine ``R_ref_cur`` so that ``current`` read at ``R.T X`` matches ``reference`` at ``X``.

    Args:
        current, reference: ``(B, 3|1, H, W)`` equirect images (``reference`` may have batch 1).
        R_init: ``(B, 3, 3)`` start (identity default). ``level``: icosahedron subdivision (thesis n = 5).
        max_iter, tol: per blur stage; stop when every update is below ``tol`` rad.
        blur_px: coarse-to-fine Gaussian blurs (pixels) of both images; ``(0,)`` = raw images only.
        dofs: which rotation axes (reference frame x, y, z) are optimised.
        impl: ``"fast"`` (images prepared once per blur stage, fused direction -> pixel reads, ~half the
            ops per iteration) or ``"reference"`` (the original per-iteration :func:`sample_panorama` path);
            equal up to float rounding.
    Returns:
        :class:`PVGResult`.
    """
    if impl not in ("fast", "reference"):
        raise ValueError(f"pvg_refine: impl must be 'fast' or 'reference', got {impl!r}")
    dtype = current.dtype if current.dtype == torch.float64 else torch.float32
    cur = to_gray(current.to(dtype))
    ref = to_gray(reference.to(dtype))
    B = cur.shape[0]
    if ref.shape[0] == 1 and B > 1:
        ref = ref.expand(B, -1, -1, -1)
    X = icosahedron_vertices(level, dtype, cur.device)
    R = (torch.eye(3, dtype=dtype, device=cur.device) if R_init is None else R_init.to(dtype)).expand(B, 3, 3).clone()
    mask = torch.tensor([bool(d) for d in dofs], device=cur.device)
    it_total = 0
    cost = torch.zeros(B, dtype=dtype, device=cur.device)
    if impl == "fast":
        return _pvg_fast(cur, ref, X, R, mask, max_iter, tol, blur_px)
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


def _pvg_fast(cur: Tensor, ref: Tensor, X: Tensor, R: Tensor, mask: Tensor, max_iter: int, tol: float,
              blur_px: Sequence[float]) -> PVGResult:
    """The Gauss-Newton loop of :func:`pvg_refine` with prepared images and matrix products instead of
    einsum/expand (same arithmetic up to rounding)."""
    B, dtype, dev = cur.shape[0], cur.dtype, cur.device
    all_dofs = bool(mask.all())
    it_total = 0
    cost = torch.zeros(B, dtype=dtype, device=dev)
    for sigma in blur_px:
        c_img = SphereImage(blur(cur, sigma))
        I_ref = SphereImage(blur(ref, sigma)).read(X.unsqueeze(0))[:, 0]  # (B, N)
        for _ in range(max_iter):
            it_total += 1
            p = X @ R  # (B, N, 3): rows R.T X_n
            I_cur, grad = spherical_gradient_fast(c_img, p)
            e = I_cur - I_ref
            cost = (e * e).mean(-1)
            J = torch.linalg.cross(grad @ R.transpose(-1, -2), X.expand_as(grad), dim=-1)  # (R grad) x X
            if not all_dofs:
                J = J[..., mask]
            dx = gauss_newton_step(J, e)
            if all_dofs:
                w = dx
            else:
                w = torch.zeros(B, 3, dtype=dtype, device=dev)
                w[:, mask] = dx
            n = w.norm(dim=-1, keepdim=True)
            w = w * (0.35 / n).clamp(max=1.0)  # trust region: at most 20° per step
            R = rodrigues(w) @ R
            if bool((n < tol).all()):
                break
    return PVGResult(R, cost, it_total)
