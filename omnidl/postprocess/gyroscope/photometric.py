"""Shared pieces of the photometric gyroscopes: grey levels, blur, the rotation update, GN step.

Rotation parametrisation of both solvers: the orientation ``R = R_ref_cur`` (see the package docstring) is
updated on the left, ``R <- exp([w]x) R`` (``w`` in the reference frame). A reference-frame direction
``s`` is seen in the current frame at ``p = R.T s``; for a function ``f`` on the current sphere with
ambient gradient ``grad f(p)``, ``d f(R(w).T s) / dw = (R grad f(p)) x s`` (row vector), which is the
Jacobian both MPP and PVG use (no autograd).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from omnidl.geometry.rotations import axis_angle_to_matrix


def to_gray(image: Tensor) -> Tensor:
    """``(B, 3|1, H, W)`` (or ``(3|1, H, W)``) -> ``(B, 1, H, W)`` luma (ITU-R 601 weights)."""
    if image.ndim == 3:
        image = image.unsqueeze(0)
    if image.ndim != 4 or image.shape[1] not in (1, 3):
        raise ValueError(f"expected images (B, 3 or 1, H, W), got shape {tuple(image.shape)}")
    if image.shape[1] == 1:
        return image
    w = torch.tensor([0.299, 0.587, 0.114], dtype=image.dtype, device=image.device).view(1, 3, 1, 1)
    return (image * w).sum(1, keepdim=True)


def blur(image: Tensor, sigma_px: float) -> Tensor:
    """Separable Gaussian blur of ``(B, C, H, W)``; wraps horizontally, replicates vertically."""
    if sigma_px <= 0:
        return image
    r = max(1, int(math.ceil(3 * sigma_px)))
    x = torch.arange(-r, r + 1, dtype=image.dtype, device=image.device)
    k = torch.exp(-x * x / (2 * sigma_px * sigma_px))
    k = k / k.sum()
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
    D = A.shape[-1]
    scale = torch.diagonal(A, dim1=-2, dim2=-1).mean(-1, keepdim=True).clamp_min(1e-30)
    A = A + damping * scale[..., None] * torch.eye(D, dtype=A.dtype, device=A.device)
    return -torch.linalg.solve(A, b)
