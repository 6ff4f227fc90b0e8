"""A procedural textured sphere rendered exactly at any orientation (tests, benchmarks, demos).

The texture is a smooth random function of the viewing direction in the *world* (upright) frame,
``f(d) = 0.5 + sum_k a_k sin(f_k (u_k . d) + phi_k)`` plus a sky/ground gradient, so a panorama of a
rotated camera is evaluated directly at ``R @ d`` with no resampling error: renders of the same scene
at two orientations differ by exactly that rotation.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from omnidl.cameras.equirectangular import Equirectangular


def procedural_panorama(rotation: Tensor | None, height: int, width: int, seed: int = 0, waves: int = 24,
                        max_frequency: float = 9.0, dtype: torch.dtype = torch.float32) -> Tensor:
    """``(B, 3, H, W)`` RGB in ``[0, 1]`` of cameras with orientation ``rotation (B, 3, 3)`` (``R_up_cam``:
    camera direction ``d`` looks at world direction ``R @ d``); ``None`` = one upright panorama."""
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(waves, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=-1, keepdim=True)
    f = 1.0 + (max_frequency - 1.0) * torch.rand(waves, generator=g, dtype=torch.float64)
    ph = 2 * math.pi * torch.rand(waves, 3, generator=g, dtype=torch.float64)
    amp = 0.5 / math.sqrt(waves) * torch.rand(waves, 3, generator=g, dtype=torch.float64) / f[:, None].sqrt()
    R = torch.eye(3, dtype=torch.float64)[None] if rotation is None else rotation.to(torch.float64)
    if R.ndim == 2:
        R = R[None]
    d = Equirectangular(width=width, height=height).unproject_grid(torch.float64).direction.reshape(-1, 3)
    w = torch.einsum("bij,nj->bni", R, d)  # world directions (B, N, 3)
    arg = torch.einsum("bnk,wk->bnw", w, u) * f  # (B, N, waves)
    img = 0.5 + (torch.sin(arg[..., None] + ph) * amp).sum(-2)  # (B, N, 3)
    img = img + 0.15 * (-w[..., 1:2])  # brighter sky (world up is -y)
    img = img.clamp(0, 1).transpose(1, 2).reshape(R.shape[0], 3, height, width)
    return img.to(dtype)
