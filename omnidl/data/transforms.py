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

from omnidl.geometry.panorama import rotate_panorama
from omnidl.geometry.rotations import axis_angle_to_matrix

#: keys rotate_sample knows how to move (and how); ``normal`` vectors are also rotated into the new frame
ROTATABLE = {"image": "bilinear", "depth": "nearest", "semantic": "nearest", "valid": "nearest",
             "instance": "nearest", "normal": "nearest", "layout_seg": "nearest", "edges": "bilinear"}


def horizontal_rotation(angle_deg: float, axis: str | float = "x") -> torch.Tensor:
    """``(3, 3)`` float64 right-handed rotation by ``angle_deg`` about a horizontal camera axis: ``"x"``
    (pitch), ``"z"`` (roll) or an azimuth in degrees (axis ``(cos a, 0, sin a)`` in the OpenCV camera
    frame, y down)."""
    if axis == "x":
        vec = (1.0, 0.0, 0.0)
    elif axis == "z":
        vec = (0.0, 0.0, 1.0)
    else:
        az = math.radians(float(axis))
        vec = (math.cos(az), 0.0, math.sin(az))
    return axis_angle_to_matrix(torch.tensor(vec, dtype=torch.float64) * math.radians(angle_deg))


def rotate_tensors(data: dict[str, Any], R: torch.Tensor, batched: bool, drop_unknown: bool = False
                   ) -> dict[str, Any]:
    """Rotate the image-like tensors of a sample (``batched=False``) or batch (``batched=True``).

    ``R`` is ``R_old_new`` (see :func:`omnidl.geometry.rotate_panorama`). Keys of :data:`ROTATABLE` are
    resampled (integer/bool maps with nearest, keeping their dtype; ``normal`` vectors become ``R^T n``).
    Any other tensor key raises a ``ValueError`` naming it -- its geometry (e.g. layout boundaries) would
    be wrong -- unless ``drop_unknown`` removes it. Non-tensor values are kept.
    """
    other = [k for k, v in data.items() if isinstance(v, torch.Tensor) and k not in ROTATABLE]
    if other and not drop_unknown:
        raise ValueError(f"cannot rotate the panorama keys {other}: only {sorted(ROTATABLE)} are supported "
                         "(drop the others, e.g. layout=False for synthetic data)")
    out = {k: v for k, v in data.items() if k not in other}
    for key, mode in ROTATABLE.items():
        v = data.get(key)
        if not isinstance(v, torch.Tensor):
            continue
        src = v if v.is_floating_point() else v.to(torch.float32)
        plane = src.dim() == (3 if batched else 2)  # (B,H,W) / (H,W) maps get a channel axis
        if plane:
            src = src.unsqueeze(-3)
        rot, _ = rotate_panorama(src, R.to(device=src.device, dtype=src.dtype), mode=mode)
        if key == "normal":  # the same surface seen from the new frame: n_new = R^T n_old
            rot = torch.einsum("ji,...jhw->...ihw", R.to(rot), rot)
        if plane:
            rot = rot.squeeze(-3)
        out[key] = rot.to(v.dtype) if v.is_floating_point() else rot.round().to(v.dtype)
    return out


def rotate_sample(sample: dict[str, Any], R: torch.Tensor, drop_unknown: bool = False) -> dict[str, Any]:
    """Rotate one sample (see :func:`rotate_tensors`); ``meta["rotation"]`` records ``R``."""
    out = rotate_tensors(sample, R, batched=False, drop_unknown=drop_unknown)
    meta = dict(sample.get("meta") or {})
    meta["rotation"] = R.tolist()
    out["meta"] = meta
    return out


class RandomRotation(Dataset):
    """Rotate every sample by ``U(-max_deg, max_deg)`` about a random horizontal axis (the thesis' ``-r`` variants).

    The angle and axis come from a generator seeded by ``(seed, epoch, index)``: the same sample in the same
    epoch is always rotated the same way (exact resume; any number of workers). Call :meth:`set_epoch`.
    Keys that cannot be rotated (layout annotations) are dropped unless ``drop_unknown=False``.
    """

    def __init__(self, dataset, max_deg: float = 10.0, seed: int = 0, drop_unknown: bool = True):
        self.dataset, self.max_deg, self.seed, self.epoch = dataset, float(max_deg), int(seed), 0
        self.drop_unknown = drop_unknown

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
        return rotate_sample(sample, horizontal_rotation(angle, az), drop_unknown=self.drop_unknown)
