"""A reference-style MPP yaw solver: the baseline of the gyroscope benchmark (issue 17, item 1).

Written the way the published MPP gyroscope evaluates its cost (Caron & Morbidi 2018; libPeR): one start, and
in every Gauss-Newton iteration the Gaussian mixture of the current image and its gradient are re-summed over
all ``N x N`` (rotated centre, sample) pairs — no tabulation, no caching across iterations. The image
sampling/normalisation is omnidl's :func:`~omnidl.postprocess.gyroscope.mpp.mpp_samples` (identical inputs for
both solvers), the stop rule the same as :func:`~omnidl.postprocess.gyroscope.mpp.mpp_yaw` (every step below
``tol`` or ``max_iter`` iterations), so the measured ratio is the cost of the evaluation strategy only.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from omnidl.postprocess.gyroscope.mpp import mpp_samples


def _rot_y(theta: float, dtype) -> Tensor:
    c, s = math.cos(theta), math.sin(theta)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=dtype)


def _mixture(X: Tensor, I: Tensor, P: Tensor, lam: float) -> tuple[Tensor, Tensor]:
    """G (M,) and ambient gradient (M, 3) of the mixture of samples ``I (N,)`` at ``X (N, 3)``, at ``P (M, 3)``."""
    c = 1.0 / (lam ** 3 * (2 * math.pi) ** 1.5)
    dot = (P @ X.T).clamp(-1.0, 1.0)
    d = torch.acos(dot)
    w = c * torch.exp(-d * d / (2 * lam * lam)) * I
    sin = torch.sqrt((1 - dot * dot).clamp_min(0))
    ratio = torch.where(sin > 1e-7, d / sin.clamp_min(1e-7), torch.ones_like(d))
    return w.sum(-1), (w * ratio / (lam * lam)) @ X


def reference_mpp_yaw(current: Tensor, reference: Tensor, level: int = 3, lambda_g: float = 0.325,
                      max_iter: int = 30, tol: float = 1e-6) -> tuple[float, int]:
    """Yaw (rad) about the vertical of single images ``(1, C, H, W)`` from identity; returns ``(yaw, iterations)``."""
    X, Ic = mpp_samples(current, level)
    _, Ir = mpp_samples(reference, level)
    Ic, Ir = Ic[0], Ir[0]
    G_ref, _ = _mixture(X, Ir, X, lambda_g)
    a = torch.tensor([0.0, 1.0, 0.0], dtype=X.dtype)
    theta, it = 0.0, 0
    for it in range(1, max_iter + 1):
        R = _rot_y(theta, X.dtype)
        P = X @ R  # R.T s_g
        G, grad = _mixture(X, Ic, P, lambda_g)  # all N x N pairs, every iteration
        e = G - G_ref
        J = torch.linalg.cross(grad @ R.T, X, dim=-1) @ a
        step = float(-(J @ e) / (J @ J).clamp_min(1e-30))
        step = max(-0.5, min(0.5, step))
        theta += step
        if abs(step) < tol:
            break
    return math.remainder(theta, 2 * math.pi), it
