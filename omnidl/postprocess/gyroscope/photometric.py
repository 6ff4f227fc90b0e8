"""Shared pieces of the photometric gyroscopes: grey levels, blur, the rotation update, the damped solve, reads of
an equirectangular image at directions.

Rotation parametrisation of both solvers: the orientation ``R = R_ref_cur`` (see the package docstring) is
updated on the left, ``R <- exp([w]x) R`` (``w`` in the reference frame, :func:`rodrigues`). A reference-frame
direction ``s`` is seen in the current frame at ``p = R.T s``; for a function ``f`` on the current sphere with
ambient gradient ``grad f(p)``, ``d f(R(w).T s) / dw = (R grad f(p)) x s`` (row vector), which is the
Jacobian both MPP and PVG use (no autograd).
"""
from __future__ import annotations

import math
from functools import lru_cache

import torch
import torch.nn.functional as F
from torch import Tensor


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


def _gaussian_taps(sigma_px: float, dtype: torch.dtype, device=None) -> tuple[int, Tensor]:
    """Radius ``r = ceil(3 sigma)`` (at least 1) and the normalised 1-D Gaussian taps ``(2r + 1,)`` of
    :func:`blur_fast`."""
    r = max(1, int(math.ceil(3 * sigma_px)))
    x = torch.arange(-r, r + 1, dtype=dtype, device=device)
    k = torch.exp(-x * x / (2 * sigma_px * sigma_px))
    return r, k / k.sum()


@lru_cache(maxsize=32)
def _blur_matrix(n: int, sigma_px: float, wrap: bool, dtype: torch.dtype, device: str) -> Tensor:
    """``(n, n)`` matrix ``K`` of the 1-D Gaussian of :func:`_gaussian_taps` along an axis of length ``n``
    (``out = K @ x``): ``wrap`` = circular (longitude; a kernel wider than the axis wraps around it more than
    once), else replicated borders (latitude). Built in float64, cached."""
    r, k = _gaussian_taps(sigma_px, torch.float64)
    idx = torch.arange(n)[:, None] + torch.arange(-r, r + 1)[None]  # (n, 2r + 1) source of each tap
    idx = idx.remainder(n) if wrap else idx.clamp(0, n - 1)
    K = torch.zeros(n, n, dtype=torch.float64).scatter_add_(1, idx, k.expand(n, -1).contiguous())
    return K.to(dtype=dtype, device=device)


def blur_fast(image: Tensor, sigma_px: float) -> Tensor:
    """Separable Gaussian blur of ``image (B, C, H, W)`` (``sigma_px`` pixels, taps to ``ceil(3 sigma)``), wrapping
    horizontally and replicating vertically, as two matrix products with cached Gaussian matrices
    (``K_v @ image @ K_h.T``): one GEMM per axis instead of pads and single-channel convolutions (2.5x faster at
    256 x 128 than ``tests/reference/gyroscope.py``'s ``blur``, the same values up to float rounding)."""
    if sigma_px <= 0:
        return image
    H, W = int(image.shape[-2]), int(image.shape[-1])
    dev = str(image.device)
    Kh = _blur_matrix(W, float(sigma_px), True, image.dtype, dev)
    Kv = _blur_matrix(H, float(sigma_px), False, image.dtype, dev)
    return Kv @ (image @ Kh.T)


def rodrigues(w: Tensor) -> Tensor:
    """``exp([w]x)`` ``(..., 3, 3)`` of axis-angle ``w (..., 3)`` by Rodrigues' formula in ~12 ops (the kornia
    conversion :func:`~omnidl.geometry.rotations.axis_angle_to_matrix` takes ~200 for a 3x3 matrix):
    ``I + a K + b K^2`` with ``K = [w]x`` (one product with a constant generator matrix),
    ``a = sin t / t = sinc(t / pi)`` and ``b = (1 - cos t) / t^2 = sinc(t / 2 pi)^2 / 2`` (``torch.sinc`` is 1 at 0:
    no branch for small angles); equal up to rounding, exact at 0."""
    gen = _skew_generator(w.dtype, w.device)
    K = (w @ gen).view(*w.shape[:-1], 3, 3)
    t = (w * w).sum(-1, keepdim=True).sqrt()  # (..., 1)
    ab = torch.sinc(t * _SINC_SCALE.to(dtype=w.dtype, device=w.device))  # (..., 2): sinc(t/pi), sinc(t/2pi)
    a = ab[..., :1, None]
    b = 0.5 * ab[..., 1:, None].square()
    return torch.eye(3, dtype=w.dtype, device=w.device) + a * K + b * (K @ K)


_SINC_SCALE = torch.tensor([1 / math.pi, 0.5 / math.pi], dtype=torch.float64)


@lru_cache(maxsize=8)
def _skew_generator(dtype: torch.dtype, device) -> Tensor:
    """``(3, 9)`` matrix ``S`` with ``(w @ S).view(3, 3) = [w]x``."""
    S = torch.zeros(3, 9, dtype=dtype, device=device)
    for (i, j), (k, sign) in {(0, 1): (2, -1), (0, 2): (1, 1), (1, 0): (2, 1), (1, 2): (0, -1), (2, 0): (1, -1),
                              (2, 1): (0, 1)}.items():
        S[k, 3 * i + j] = sign
    return S


def damped_step(A: Tensor, b: Tensor, damping: float = 1e-9) -> Tensor:
    """``dx = -(A + damping * mean(diag A) I)^-1 b`` for normal equations ``A (..., D, D)``, ``b (..., D)``
    (the Gauss-Newton step of ``min |J dx + e|^2`` for ``A = J^T J``, ``b = J^T e``)."""
    scale = torch.diagonal(A, dim1=-2, dim2=-1).mean(-1, keepdim=True).clamp_min(1e-30)
    A = A + damping * scale[..., None] * torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
    return -torch.linalg.solve(A, b)


class SphereImage:
    """An equirectangular ``image (B, C, H, W)`` prepared once for many bilinear reads at directions.

    Same values as :func:`omnidl.geometry.panorama.sample_panorama` (pixel centres at ``j + 0.5``, longitude
    wrapping across the seam, latitude clamped at the pole rows, longitude 0 exactly at the poles) up to
    float rounding, but the wrap columns are added once here instead of on every call and the
    direction -> grid conversion is a handful of fused ops: the solvers read the same image tens of times.
    """

    def __init__(self, image: Tensor) -> None:
        if image.dim() != 4:
            raise ValueError(f"SphereImage: image must have shape (B, C, H, W), got {tuple(image.shape)}")
        self.H, self.W = int(image.shape[-2]), int(image.shape[-1])
        self.padded = torch.cat([image[..., -1:], image, image[..., :1]], dim=-1)
        # grid x = 2 (u + 1) / (W + 2) - 1 with u = (lon + pi) / (2 pi) W; grid y = 2 v / H - 1 = -2 lat / pi
        self._sx = self.W / (math.pi * (self.W + 2))
        self._ox = math.pi * self._sx + 2.0 / (self.W + 2) - 1.0

    def read_xyz(self, x: Tensor, y: Tensor, z: Tensor) -> Tensor:
        """Values ``(B, C, M)`` at directions (any positive length) given by their components ``x, y, z (B|1, ...)``
        (``M`` = the product of the trailing sizes; e.g. rows of a ``(B, 3, M)`` tensor: no strided component
        reads). The grid of ``sample_panorama`` up to rounding, in few ops: ``lat`` from ``atan2(y, .)`` (odd in
        ``y``) with the sign folded into the scale, the pole longitude set after the ``atan2``, the affine maps in
        place on contiguous rows."""
        return self.read_grid(x, y, z)[:, :, 0]

    def read_grid(self, x: Tensor, y: Tensor, z: Tensor) -> Tensor:
        """:meth:`read_xyz` as ``(B, C, 1, M)`` (the ``grid_sample`` output, one view less)."""
        sq = torch.addcmul(x * x, z, z)
        lon = torch.atan2(x, z)
        # longitude 0 at the poles, = atan2(0, 1) as sample_panorama; on many points a check first (a point at a pole is
        # rare: one reduction instead of two mask passes), on few the mask (fewer ops)
        if sq.numel() < 16384 or bool(sq.min() <= 1e-30):
            lon.masked_fill_(sq <= 1e-30, 0.0)
        lat = torch.atan2(y, sq.sqrt_())
        g = torch.stack([lon.mul_(self._sx).add_(self._ox), lat.mul_(2.0 / math.pi)], -1)  # (B|1, ..., 2)
        g = g.view(g.shape[0], 1, -1, 2)
        src = self.padded
        B = max(src.shape[0], g.shape[0])
        if src.shape[0] != B:
            src = src.expand(B, -1, -1, -1)
        if g.shape[0] != B:
            g = g.expand(B, -1, -1, -1)
        return F.grid_sample(src, g, mode="bilinear", padding_mode="border", align_corners=False)
