"""Sample-level transforms: panorama rotation about a horizontal axis (evaluation under rotation and the
``-r`` training variants), resizing.

Rotation uses :func:`omnidl.geometry.rotate_panorama`: bilinear for the image, nearest for depth (ranges do
not change under a rotation about the centre; nearest never blends valid and invalid pixels) and for the labels.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

#: keys rotate_sample knows how to move; any other tensor key of a sample is refused (its geometry would be wrong)
ROTATABLE = {"image": "bilinear", "depth": "nearest", "semantic": "nearest", "valid": "nearest"}


def axis_angle_matrix(axis, angle_rad: float, dtype=torch.float64) -> torch.Tensor:
    """Rodrigues: ``(3, 3)`` rotation by ``angle_rad`` about the unit vector ``axis`` (right-handed)."""
    a = torch.as_tensor(axis, dtype=dtype)
    a = a / a.norm()
    k = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=dtype)
    return torch.eye(3, dtype=dtype) + math.sin(angle_rad) * k + (1 - math.cos(angle_rad)) * (k @ k)


def horizontal_rotation(angle_deg: float, axis: str | float = "x") -> torch.Tensor:
    """Rotation about a horizontal camera axis: ``"x"`` (pitch), ``"z"`` (roll) or an azimuth in degrees
    (axis ``(cos a, 0, sin a)`` in the OpenCV camera frame, y down)."""
    if axis == "x":
        vec = (1.0, 0.0, 0.0)
    elif axis == "z":
        vec = (0.0, 0.0, 1.0)
    else:
        az = math.radians(float(axis))
        vec = (math.cos(az), 0.0, math.sin(az))
    return axis_angle_matrix(vec, math.radians(angle_deg))


def rotate_sample(sample: dict[str, Any], R: torch.Tensor) -> dict[str, Any]:
    """Rotate a panorama sample (``R`` = ``R_old_new``, see :func:`omnidl.geometry.rotate_panorama`).

    Handles ``image`` (bilinear), ``depth``, ``semantic`` and ``valid`` (nearest); ``meta`` gets ``rotation``.
    Any other tensor key raises a ``ValueError`` (e.g. layout boundaries need their own rotation).
    """
    from omnidl.geometry import rotate_panorama
    other = [k for k, v in sample.items() if isinstance(v, torch.Tensor) and k not in ROTATABLE]
    if other:
        raise ValueError(f"rotate_sample cannot rotate sample keys {other}; only {sorted(ROTATABLE)}")
    out = dict(sample)
    for key, mode in ROTATABLE.items():
        v = sample.get(key)
        if not isinstance(v, torch.Tensor):
            continue
        src = v.to(torch.float32) if not v.is_floating_point() else v
        rot, _ = rotate_panorama(src, R.to(torch.float32), mode=mode)
        out[key] = rot.round().to(v.dtype) if not v.is_floating_point() else rot.to(v.dtype)
    meta = dict(sample.get("meta") or {})
    meta["rotation"] = R.tolist()
    out["meta"] = meta
    return out


class RandomRotation(Dataset):
    """Rotate every sample by ``U(-max_deg, max_deg)`` about a random horizontal axis (the thesis' ``-r`` variants).

    The angle and axis come from a generator seeded by ``(seed, epoch, index)``: the same sample in the same
    epoch is always rotated the same way (exact resume; any number of workers). Call :meth:`set_epoch`.
    """

    def __init__(self, dataset, max_deg: float = 10.0, seed: int = 0):
        self.dataset, self.max_deg, self.seed, self.epoch = dataset, float(max_deg), int(seed), 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)
        if hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.dataset)

    def angles(self, index: int) -> tuple[float, float]:
        """``(angle_deg, axis_azimuth_deg)`` used for ``index`` in the current epoch."""
        rng = np.random.default_rng([self.seed, self.epoch, int(index)])
        return float(rng.uniform(-self.max_deg, self.max_deg)), float(rng.uniform(0.0, 360.0))

    def __getitem__(self, index: int):
        sample = self.dataset[index]
        if sample is None:
            return None
        angle, az = self.angles(index)
        return rotate_sample(sample, horizontal_rotation(angle, az))
