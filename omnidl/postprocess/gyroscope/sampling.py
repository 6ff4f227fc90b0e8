"""Sampling a full 360° equirectangular image at arbitrary directions (bilinear, longitude wraps).

Geometry comes from :class:`omnidl.cameras.Equirectangular` (``project``/``unproject_grid``), so the pixel
convention is the project's (pixel centres at ``j + 0.5``). Used by the MPP/PVG solvers (vertices of a
subdivided icosahedron) and to rotate panoramas (:func:`rotate_equirect`).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from omnidl.cameras.equirectangular import Equirectangular


def _check_image(image: Tensor) -> None:
    if image.ndim != 4:
        raise ValueError(f"expected an image batch (B, C, H, W), got shape {tuple(image.shape)}")
    if image.shape[-1] != 2 * image.shape[-2]:
        raise ValueError(f"a full equirectangular panorama has W = 2 H, got H x W = {image.shape[-2]} x "
                         f"{image.shape[-1]}")


def sample_equirect(image: Tensor, directions: Tensor, mode: str = "bilinear") -> Tensor:
    """Sample ``image (B, C, H, W)`` at unit ``directions`` (``(N, 3)`` shared or ``(B, N, 3)``).

    Returns ``(B, C, N)``. Longitude wraps around (column ``W`` is column 0), latitude is clamped at the
    poles (border rows). Works for float32/float64 on any device; differentiable w.r.t. the image.
    """
    _check_image(image)
    B, C, H, W = image.shape
    if directions.ndim == 2:
        directions = directions.unsqueeze(0).expand(B, -1, -1)
    uv = direction_to_uv(directions.to(image.dtype), W, H)
    padded = torch.cat([image[..., -1:], image, image[..., :1]], dim=-1)  # one wrapped column each side
    gx = 2 * (uv[..., 0] + 1) / (W + 2) - 1
    gy = 2 * uv[..., 1] / H - 1
    grid = torch.stack([gx, gy], -1).unsqueeze(1)  # (B, 1, N, 2)
    out = F.grid_sample(padded, grid, mode=mode, padding_mode="border", align_corners=False)
    return out[:, :, 0, :]


def direction_to_uv(d: Tensor, width: int, height: int) -> Tensor:
    """Pixels ``(..., 2)`` of directions ``d (..., 3)`` on a full ``width x height`` panorama.

    The formulas of :meth:`Equirectangular.project` (``lon = atan2(x, z)``, ``lat = atan2(-y, hypot(x, z))``)
    without its validity bookkeeping: the hot path of the solvers (tests check both agree).
    """
    x, y, z = d.unbind(-1)
    lon = torch.atan2(x, z)
    lat = torch.atan2(-y, torch.hypot(x, z))
    return torch.stack([(lon + math.pi) * (width / (2 * math.pi)), (math.pi / 2 - lat) * (height / math.pi)], -1)


def equirect_directions(height: int, width: int, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """``(H, W, 3)`` unit viewing directions of the pixel centres of an ``H x W`` panorama."""
    return Equirectangular(width=width, height=height).unproject_grid(dtype, device).direction


def rotate_equirect(image: Tensor, R: Tensor, mode: str = "bilinear") -> Tensor:
    """Render the panorama seen by a rotated camera: pixel direction ``d`` reads the source at ``R @ d``.

    ``R``: ``(3, 3)`` or ``(B, 3, 3)`` = ``R_src_dst`` (the convention of ``omnidl.geometry.reproject``).
    With an orientation ``R = R_ref_cur``, ``rotate_equirect(reference, R)`` is the current view and
    ``rotate_equirect(current, R.transpose(-1, -2))`` the stabilised one. Returns ``(B, C, H, W)``.
    """
    _check_image(image)
    B, C, H, W = image.shape
    d = equirect_directions(H, W, image.dtype, image.device).reshape(-1, 3)
    R = R.to(image.dtype)
    if R.ndim == 2:
        R = R.expand(B, 3, 3)
    src = torch.einsum("bij,nj->bni", R, d)
    return sample_equirect(image, src, mode=mode).reshape(B, C, H, W)
