"""Horizon-line and vertical-vanishing-point heat maps from a rotation (HoLiNet ground truth, thesis §6.2.1).

Given the orientation ``R = R_up_cam`` of a panorama (a direction ``d`` of the rotated camera is ``R @ d``
in the upright camera frame, so the rotated image is ``rotate_equirect(upright, R)``), the horizon normal
in the camera frame is ``n = R.T @ (0, -1, 0)`` and, for every pixel direction ``p`` of the output
equirectangular grid (pixel centres, exactly through :class:`~omnidl.cameras.Equirectangular`):

* horizon map ``HL(p) = exp(-asin(|n . p|)^2 / (2 s_h^2))`` (geodesic distance to the great circle);
* vanishing-point map ``VP(p) = exp(-acos(n . p)^2 / (2 s_v^2)) + w * exp(-acos(-n . p)^2 / (2 s_v^2))``:
  the zenith peak has height 1 and the nadir peak height ``w = nadir_weight`` (default 0.5), so the map
  tells zenith from nadir and the horizon hook recovers tilts beyond 90°. ``w = 1`` gives the symmetric
  maps of the reference code.

The module also holds the training data pipeline: :class:`RotatedPanoramas` wraps any dataset of
gravity-aligned panoramas and rotates them on the fly (random roll/pitch/yaw) with the augmentations of
§6.2.1 (horizontal flip, colour permutation, colour jitter, random crop), and :class:`PanoramaFolder`
reads a folder of upright panoramas.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import Dataset

from omnidl.cameras.equirectangular import Equirectangular


def horizon_heatmaps(rotation: Tensor, height: int, width: int, sigma_deg: float = 3.0,
                     vp_sigma_deg: float | None = None, nadir_weight: float = 0.5) -> tuple[Tensor, Tensor]:
    """Ground-truth heat maps of orientations ``rotation`` (``(B, 3, 3)`` or ``(3, 3)``, ``R_up_cam``).

    The maps depend on the up vector ``n = R.T @ (0, -1, 0)`` only; see :func:`heatmaps_from_up`.
    """
    if rotation.shape[-2:] != (3, 3) or rotation.ndim not in (2, 3):
        raise ValueError(f"horizon_heatmaps: expected rotations (B, 3, 3) or (3, 3), got shape {tuple(rotation.shape)}")
    R = rotation if rotation.ndim == 3 else rotation[None]
    return heatmaps_from_up(-R[:, 1, :], height, width, sigma_deg, vp_sigma_deg, nadir_weight)


def heatmaps_from_up(up: Tensor, height: int, width: int, sigma_deg: float = 3.0,
                     vp_sigma_deg: float | None = None, nadir_weight: float = 0.5) -> tuple[Tensor, Tensor]:
    """Ground-truth heat maps of a batch of up vectors at any output resolution.

    Args:
        up: ``(B, 3)`` horizon normals (zenith direction) in the camera frame (normalised here).
        height, width: output grid (a full panorama, any size).
        sigma_deg: angular width (Gaussian sigma, degrees) of the horizon line.
        vp_sigma_deg: width of the vanishing-point peaks (default: ``sigma_deg``).
        nadir_weight: height of the nadir peak (zenith = 1); in ``(0, 1]``.
    Returns:
        ``horizon (B, 1, H, W)``, ``vp (B, 1, H, W)`` in ``[0, 1]``, dtype/device of ``rotation``.
    """
    if not 0 < nadir_weight <= 1:
        raise ValueError(f"nadir_weight must be in (0, 1], got {nadir_weight}")
    if sigma_deg <= 0 or (vp_sigma_deg is not None and vp_sigma_deg <= 0):
        raise ValueError("heat-map widths sigma_deg / vp_sigma_deg must be positive")
    if up.ndim != 2 or up.shape[-1] != 3:
        raise ValueError(f"heatmaps_from_up: expected up vectors (B, 3), got shape {tuple(up.shape)}")
    n = up / up.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    dtype = n.dtype if n.is_floating_point() else torch.float32
    d = Equirectangular(width=width, height=height).unproject_grid(dtype, n.device).direction  # (H, W, 3)
    dot = torch.einsum("bk,hwk->bhw", n.to(dtype), d).clamp(-1.0, 1.0)
    sh = math.radians(sigma_deg)
    sv = math.radians(vp_sigma_deg if vp_sigma_deg is not None else sigma_deg)
    hl = torch.exp(-torch.asin(dot.abs()) ** 2 / (2 * sh * sh))
    vp = torch.exp(-torch.acos(dot) ** 2 / (2 * sv * sv)) + nadir_weight * torch.exp(-torch.acos(-dot) ** 2 / (2 * sv * sv))
    return hl.unsqueeze(1), vp.clamp(max=1.0).unsqueeze(1)
