"""Shared pieces of the photometric gyroscopes: grey levels, blur, the rotation update, GN step.

Rotation parametrisation of both solvers: the orientation ``R = R_ref_cur`` (see the package docstring) is
updated on the left, ``R <- exp([w]x) R`` (``w`` in the reference frame). A reference-frame direction
``s`` is seen in the current frame at ``p = R.T s``; for a function ``f`` on the current sphere with
ambient gradient ``grad f(p)``, ``d f(R(w).T s) / dw = (R grad f(p)) x s`` (row vector), which is the
Jacobian both MPP and PVG use (no autograd).
"""
from __future__ import annotations

import math
from functools import lru_cache

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


def _gaussian_taps(sigma_px: float, dtype: torch.dtype, device=None) -> tuple[int, Tensor]:
    """Radius ``r = ceil(3 sigma)`` (at least 1) and the normalised 1-D Gaussian taps ``(2r + 1,)`` of :func:`blur`."""
    r = max(1, int(math.ceil(3 * sigma_px)))
    x = torch.arange(-r, r + 1, dtype=dtype, device=device)
    k = torch.exp(-x * x / (2 * sigma_px * sigma_px))
    return r, k / k.sum()


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


@lru_cache(maxsize=32)
def _blur_matrix(n: int, sigma_px: float, wrap: bool, dtype: torch.dtype, device: str) -> Tensor:
    """``(n, n)`` matrix ``K`` of :func:`blur`'s 1-D Gaussian along an axis of length ``n`` (``out = K @ x``):
    ``wrap`` = circular (longitude), else replicated borders (latitude). Built in float64, cached."""
    r, k = _gaussian_taps(sigma_px, torch.float64)
    idx = torch.arange(n)[:, None] + torch.arange(-r, r + 1)[None]  # (n, 2r + 1) source of each tap
    idx = idx.remainder(n) if wrap else idx.clamp(0, n - 1)
    K = torch.zeros(n, n, dtype=torch.float64).scatter_add_(1, idx, k.expand(n, -1).contiguous())
    return K.to(dtype=dtype, device=device)


def blur_fast(image: Tensor, sigma_px: float) -> Tensor:
    """:func:`blur` as two matrix products with cached Gaussian matrices (``K_v @ image @ K_h.T``): one GEMM
    per axis instead of pads and single-channel convolutions (2.5x faster at 256 x 128); same values up to
    float rounding. ``image (B, C, H, W)``; the wrap needs the kernel radius ``ceil(3 sigma) <= W``, as
    :func:`blur`."""
    if sigma_px <= 0:
        return image
    H, W = int(image.shape[-2]), int(image.shape[-1])
    if int(math.ceil(3 * sigma_px)) > W:
        return blur(image, sigma_px)
    dev = str(image.device)
    Kh = _blur_matrix(W, float(sigma_px), True, image.dtype, dev)
    Kv = _blur_matrix(H, float(sigma_px), False, image.dtype, dev)
    return Kv @ (image @ Kh.T)


def apply_update(R: Tensor, w: Tensor) -> Tensor:
    """``exp([w]x) @ R`` for ``R (..., 3, 3)``, ``w (..., 3)``."""
    return axis_angle_to_matrix(w) @ R


def rodrigues(w: Tensor) -> Tensor:
    """``exp([w]x)`` ``(..., 3, 3)`` of axis-angle ``w (..., 3)`` by Rodrigues' formula in ~12 ops (the kornia
    conversion behind :func:`apply_update` takes ~200 for a 3x3 matrix): ``I + a K + b K^2`` with ``K = [w]x``
    (one product with a constant generator matrix), ``a = sin t / t = sinc(t / pi)`` and
    ``b = (1 - cos t) / t^2 = sinc(t / 2 pi)^2 / 2`` (``torch.sinc`` is 1 at 0: no branch for small angles);
    equal up to rounding, exact at 0."""
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


def damped_step(A: Tensor, b: Tensor, damping: float = 1e-9) -> Tensor:
    """``dx = -(A + damping * mean(diag A) I)^-1 b`` for normal equations ``A (..., D, D)``, ``b (..., D)``
    (the solve of :func:`gauss_newton_step`)."""
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
        """Values ``(B, C, M)`` at directions given by their components ``x, y, z (B|1, ...)`` (``M`` = the
        product of the trailing sizes; e.g. rows of a ``(B, 3, M)`` tensor: no strided component reads).
        Same grid as :meth:`read` up to rounding, in fewer ops: ``lat`` from ``atan2(y, .)`` (odd in ``y``)
        with the sign folded into the scale, the pole longitude set after the ``atan2``, the affine maps in
        place on contiguous rows."""
        return self.read_grid(x, y, z)[:, :, 0]

    def read_grid(self, x: Tensor, y: Tensor, z: Tensor) -> Tensor:
        """:meth:`read_xyz` as ``(B, C, 1, M)`` (the ``grid_sample`` output, one view less)."""
        sq = torch.addcmul(x * x, z, z)
        lon = torch.atan2(x, z)
        # longitude 0 at the poles, = atan2(0, 1) as read(); on many points a check first (a point at a pole is
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

    def read(self, d: Tensor) -> Tensor:
        """Values ``(B, C, M)`` at directions ``d (B|1, M, 3)`` (any positive length; the scale is irrelevant)."""
        x, y, z = d.unbind(-1)
        sq = x * x + z * z
        pole = sq <= 1e-30
        lon = torch.atan2(x.masked_fill(pole, 0.0), z.masked_fill(pole, 1.0))
        lat = torch.atan2(-y, sq.sqrt())
        g = torch.stack([lon * self._sx + self._ox, lat * (-2.0 / math.pi)], -1)  # (B|1, M, 2)
        src = self.padded
        B = max(src.shape[0], g.shape[0])
        if src.shape[0] != B:
            src = src.expand(B, -1, -1, -1)
        if g.shape[0] != B:
            g = g.expand(B, -1, -1)
        out = F.grid_sample(src, g.unsqueeze(1), mode="bilinear", padding_mode="border", align_corners=False)
        return out[:, :, 0, :]


def yaw_rotations(R0: Tensor, axis: Tensor, theta: Tensor) -> Tensor:
    """``exp(theta [axis]x) @ R0`` by Rodrigues' formula: ``R0 (B, 3, 3)``, unit ``axis (B, 3)``, ``theta (B, T)``
    -> ``(B, T, 3, 3)`` (the same rotations as :func:`apply_update` with ``w = theta * axis``, fewer ops)."""
    a = axis
    zero = torch.zeros_like(a[:, 0])
    K = torch.stack([zero, -a[:, 2], a[:, 1], a[:, 2], zero, -a[:, 0], -a[:, 1], a[:, 0], zero], -1).view(-1, 3, 3)
    K2 = K @ K
    s, c = torch.sin(theta)[..., None, None], (1 - torch.cos(theta))[..., None, None]
    E = torch.eye(3, dtype=R0.dtype, device=R0.device) + s * K.unsqueeze(1) + c * K2.unsqueeze(1)
    return E @ R0.unsqueeze(1)
