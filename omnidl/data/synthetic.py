"""Torch datasets over the built-in data engine (:mod:`omnidl.synth`), rendered on the fly.

Sample ``i`` of split ``s`` is :func:`omnidl.synth.render_sample` ``(camera, seed, s, i)``: splits never
share a room, and the same ``(seed, split, index)`` gives a bit-identical sample. The returned dict is
documented in ``docs/synth.md``.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from omnidl.cameras.resolve import resolve_camera
from omnidl.synth import SPLITS, RoomLimits, render_sample
from omnidl.utils.io import atomic_torch_save


class SyntheticCameraDataset(Dataset):
    """Procedural rooms rendered for any camera (fisheye, Kannala–Brandt, pinhole, panoramas, ...).

    Args:
        camera: a ``Camera``, a config mapping, a ``configs/camera`` name, a YAML path, or a registered
            type (then give ``width``/``height``); ``width``/``height`` resize a configured camera.
        length: number of samples in the split.
        seed: base seed; split: ``"train"``, ``"val"`` or ``"test"``.
        rotation: ``"upright"``, ``"random"`` (tilt up to ``max_tilt_deg``) or a ``(3, 3)`` ``R_up_cam``.
        cache_dir: optional folder for rendered samples (``.pt``, written atomically).
        manhattan_ratio, furniture, limits: room sampling options; layout: include layout ground truth.
    """

    def __init__(self, camera: Any = "equirect", length: int = 1000, seed: int = 0, split: str = "train",
                 rotation: Any = "upright", max_tilt_deg: float = 30.0, cache_dir: str | Path | None = None,
                 manhattan_ratio: float = 0.7, furniture: bool = True, layout: bool = True,
                 limits: RoomLimits | None = None, width: int | None = None, height: int | None = None,
                 shadows: bool = False, **camera_fields: Any) -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {sorted(SPLITS)}, got {split!r}")
        if length < 0:
            raise ValueError(f"length must be >= 0, got {length}")
        self.camera = resolve_camera(camera, width, height, **camera_fields)
        self.length = int(length)
        self.seed = int(seed)
        self.split = split
        self.rotation = rotation if isinstance(rotation, str) else np.asarray(rotation, np.float64)
        self.max_tilt_deg = float(max_tilt_deg)
        self.manhattan_ratio = float(manhattan_ratio)
        self.furniture = bool(furniture)
        self.layout = bool(layout)
        self.limits = limits or RoomLimits()
        self.shadows = bool(shadows)
        self.cache_dir = None if cache_dir is None else Path(cache_dir) / self._cache_key()

    def _cache_key(self) -> str:
        opts = {"camera": self.camera.to_config(), "seed": self.seed,
                "rotation": self.rotation if isinstance(self.rotation, str) else self.rotation.tolist(),
                "tilt": self.max_tilt_deg, "ratio": self.manhattan_ratio, "furniture": self.furniture,
                "layout": self.layout, "limits": repr(self.limits), "shadows": self.shadows, "version": 1}
        return hashlib.sha1(json.dumps(opts, sort_keys=True, default=str).encode()).hexdigest()[:16]

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> dict:
        if not 0 <= index < self.length:
            raise IndexError(f"index {index} out of range for a dataset of length {self.length}")
        path = None
        if self.cache_dir is not None:
            path = self.cache_dir / f"{self.split}_{index:07d}.pt"
            if path.exists():
                try:
                    return torch.load(path, weights_only=True)   # a cache file never runs code
                except Exception:  # noqa: BLE001 - a corrupt cache file is re-rendered
                    pass
        out = render_sample(self.camera, self.seed, self.split, index, rotation=self.rotation,
                            max_tilt_deg=self.max_tilt_deg, manhattan_ratio=self.manhattan_ratio,
                            furniture=self.furniture, layout=self.layout, limits=self.limits, shadows=self.shadows)
        if path is not None:
            atomic_torch_save(path, out)
        return out


class SyntheticPanoramaDataset(SyntheticCameraDataset):
    """Procedural rooms as equirectangular (``camera="equirect"``) or non-central (``"noncentral_pano"``,
    circle radius ``rc`` metres) panoramas of any ``width x height``."""

    def __init__(self, camera: str = "equirect", width: int = 1024, height: int = 512, rc: float = 1.0,
                 **kwargs: Any) -> None:
        if camera not in ("equirect", "noncentral_pano"):
            raise ValueError(f"SyntheticPanoramaDataset camera must be 'equirect' or 'noncentral_pano', got "
                             f"{camera!r} (use SyntheticCameraDataset for other cameras)")
        cfg = {"type": camera, "width": int(width), "height": int(height)}
        if camera == "noncentral_pano":
            cfg["rc"] = float(rc)
        super().__init__(camera=cfg, **kwargs)
