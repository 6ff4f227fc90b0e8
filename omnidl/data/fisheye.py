"""Fisheye (or perspective) views rendered from equirectangular panoramas (thesis ch. 7, §7.4).

The F165/F195 datasets of the thesis are fisheye images "randomly synthesized from the panoramic
dataset in different orientations and with known calibration"; *Pers* is a perspective dataset of
the same scenes. :class:`ViewsFromPanoramas` does both for any central camera: view ``i`` re-projects
panorama ``i // views_per_panorama`` (:func:`omnidl.geometry.reproject`) into ``camera`` turned by a
random rotation ``R_pano_cam`` (yaw uniform, pitch and roll uniform within limits):

* RGB bilinear; depth (range along the ray — the same in any central camera at the same centre, so it
  re-projects unchanged) nearest by default (no mixing of depths across object edges), ``bilinear``
  on request; semantics nearest.
* Pixels outside the camera's image circle, or whose panorama pixel has no depth, are invalid:
  ``depth = 0``, ``semantic = 0`` (unknown), ``valid = False``; RGB outside the circle is 0.

Panorama sources (``panoramas=``): the built-in synthetic engine (default,
:class:`omnidl.data.synthetic.SyntheticPanoramaDataset`), Stanford2D3DS
(:class:`omnidl.data.stanford2d3ds.Stanford2D3DS`), or any map-style dataset of equirectangular
sample dicts — given as an object or a config mapping (``{"_target_": ..., ...}`` or
``{"type": "synthetic"|"stanford2d3ds", ...}``).

Sample dict (``H x W`` = the camera's image size):
``image (3,H,W) float32``, ``depth (1,H,W) float32`` (0 = invalid), ``semantic (H,W) int64``,
``valid (H,W) bool``, ``radius (1,H,W) float32`` — distance of each pixel centre to the principal
point, **in pixels of the calibrated image** (so curves of resized datasets compare with full-size
ones), ``rotation (3,3) float32`` ``R_pano_cam``, ``meta`` (panorama index, angles, camera config).
"""
from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from omnidl.cameras.base import Camera, ResizedCamera
from omnidl.cameras.equirectangular import Equirectangular
from omnidl.cameras.resolve import resolve_camera
from omnidl.geometry import euler_to_matrix, reproject
from .readers import image_to_float

SPLITS = {"train": 0, "val": 1, "test": 2}


def principal_point(camera: Camera) -> tuple[float, float]:
    """``(u, v)`` of the optical axis ``+z`` in ``camera``'s pixels (the image centre if ``+z`` is not seen)."""
    uv, valid = camera.project(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    if bool(valid):
        return float(uv[0]), float(uv[1])
    return camera.width / 2, camera.height / 2


def radius_map(camera: Camera, dtype: torch.dtype = torch.float32) -> Tensor:
    """``(H, W)`` distance of each pixel centre to the principal point, in pixels of the calibrated image.

    For a resized camera (:class:`ResizedCamera`) distances are measured in the base (calibration)
    image: ``hypot((u - cx) / s_x, (v - cy) / s_y)``.
    """
    sx = sy = 1.0
    cam = camera
    while isinstance(cam, ResizedCamera):
        sx, sy, cam = sx * cam.scale_x, sy * cam.scale_y, cam.base
    cx, cy = principal_point(cam)
    uv = camera.pixel_grid(torch.float64)
    return torch.hypot(uv[..., 0] / sx - cx, uv[..., 1] / sy - cy).to(dtype)


def build_panoramas(spec: Any, split: str) -> Dataset:
    """A panorama dataset from an object or a config mapping (see the module docstring)."""
    if spec is None:
        spec = {"type": "synthetic"}
    is_cfg = isinstance(spec, Mapping) or type(spec).__name__ == "DictConfig"
    if not is_cfg:
        if hasattr(spec, "__getitem__") and hasattr(spec, "__len__"):
            return spec
        raise TypeError(f"panoramas must be a dataset or a config mapping, got {type(spec).__name__}")
    cfg = dict(spec)
    if "_target_" in cfg:
        from hydra.utils import instantiate
        return instantiate(cfg, _convert_="all")
    kind = cfg.pop("type", "synthetic")
    if kind == "synthetic":
        from omnidl.data.synthetic import SyntheticPanoramaDataset
        cfg.setdefault("split", split)
        cfg.setdefault("layout", False)
        cfg.setdefault("width", 512)
        cfg.setdefault("height", 256)
        return SyntheticPanoramaDataset(**cfg)
    if kind == "stanford2d3ds":
        from omnidl.data.stanford2d3ds import Stanford2D3DS
        cfg.setdefault("split", split)
        return Stanford2D3DS(**cfg)
    raise ValueError(f"panoramas.type must be 'synthetic' or 'stanford2d3ds' (or give a _target_), got {kind!r}")


class ViewsFromPanoramas(Dataset):
    """Views of any central camera rendered from equirectangular panoramas at random orientations.

    Args:
        camera: any spec of :func:`omnidl.cameras.resolve_camera` (a ``Camera``, a config mapping, a KB
            calibration file, a camera YAML or a ``configs/camera`` name).
        width, height: rendered image size (the camera is resized to it; same aspect ratio required);
            default: the camera's own size.
        panoramas: panorama source (dataset object or config mapping; default synthetic 512x256).
        split: ``train``/``val``/``test`` (passed to config-built panorama sources; seeds the views).
        views_per_panorama: views drawn from each panorama.
        length: number of views (default ``len(panoramas) * views_per_panorama``).
        max_pitch_deg, max_roll_deg: pitch/roll uniform in ``[-max, max]``; yaw uniform in ``[-180, 180)``.
        seed: base seed of the orientations (``SeedSequence([seed, split, index])``).
        depth_mode: ``"nearest"`` (default) or ``"bilinear"``.
        cache_panoramas: keep up to this many decoded panoramas in memory (consecutive views share one).
    """

    def __init__(self, camera: Any, width: int | None = None, height: int | None = None, panoramas: Any = None,
                 split: str = "train", views_per_panorama: int = 1, length: int | None = None,
                 max_pitch_deg: float = 30.0, max_roll_deg: float = 10.0, seed: int = 0,
                 depth_mode: str = "nearest", cache_panoramas: int = 8) -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {sorted(SPLITS)}, got {split!r}")
        if depth_mode not in ("nearest", "bilinear"):
            raise ValueError(f"depth_mode must be 'nearest' or 'bilinear', got {depth_mode!r}")
        if views_per_panorama < 1:
            raise ValueError(f"views_per_panorama must be >= 1, got {views_per_panorama}")
        self.camera = resolve_camera(camera, width, height, check_aspect=True)
        if not self.camera.central:
            raise ValueError(f"ViewsFromPanoramas renders central cameras only, got {type(self.camera).__name__}")
        self.panoramas = build_panoramas(panoramas, split)
        self.split, self.seed = split, int(seed)
        self.views = int(views_per_panorama)
        n = len(self.panoramas) * self.views
        self.length = n if length is None else int(length)
        if not 0 < self.length <= n:
            raise ValueError(f"length={length}: the panorama source has {len(self.panoramas)} panoramas x "
                             f"{self.views} views = {n} views")
        self.max_pitch, self.max_roll = math.radians(max_pitch_deg), math.radians(max_roll_deg)
        self.depth_mode = depth_mode
        self._cache: OrderedDict[int, dict] = OrderedDict()
        self._cache_size = int(cache_panoramas)
        self._radius = radius_map(self.camera)

    def __len__(self) -> int:
        return self.length

    def angles(self, index: int) -> tuple[float, float, float]:
        """``(roll, pitch, yaw)`` radians of view ``index`` (deterministic)."""
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, SPLITS[self.split], int(index), 7]))
        yaw = rng.uniform(-math.pi, math.pi)
        pitch = rng.uniform(-self.max_pitch, self.max_pitch)
        roll = rng.uniform(-self.max_roll, self.max_roll)
        return float(roll), float(pitch), float(yaw)

    def _panorama(self, k: int) -> dict:
        if k in self._cache:
            self._cache.move_to_end(k)
            return self._cache[k]
        pano = self.panoramas[k]
        for key in ("image", "depth", "semantic"):
            if key not in pano:
                raise KeyError(f"panorama {k} of {type(self.panoramas).__name__} has no {key!r} (keys: {sorted(pano)})")
        h, w = pano["image"].shape[-2:]
        if w != 2 * h:
            raise ValueError(f"panorama {k} of {type(self.panoramas).__name__} is {w}x{h}; an equirectangular "
                             "panorama must be twice as wide as high")
        if self._cache_size > 0:
            self._cache[k] = pano
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return pano

    def __getitem__(self, index: int) -> dict:
        if not 0 <= index < self.length:
            raise IndexError(f"index {index} out of range for a dataset of length {self.length}")
        k = index // self.views
        pano = self._panorama(k)
        h, w = pano["image"].shape[-2:]
        src = Equirectangular(width=int(w), height=int(h))
        roll, pitch, yaw = self.angles(index)
        R = euler_to_matrix(roll, pitch, yaw).to(torch.float64)
        img = image_to_float(pano["image"], f"panorama {k}").float()       # uint8: / 255 before any arithmetic
        image, valid = reproject(img, src, self.camera, R, mode="bilinear")
        depth, dvalid = reproject(pano["depth"].float().reshape(1, h, w), src, self.camera, R, mode=self.depth_mode)
        if self.depth_mode == "bilinear":  # a bilinear sample touching an invalid (0) depth is invalid
            zero, _ = reproject((pano["depth"].reshape(1, h, w) <= 0).float(), src, self.camera, R, mode="bilinear")
            dvalid = dvalid & (zero == 0)
        sem, _ = reproject(pano["semantic"].reshape(1, h, w).long(), src, self.camera, R, mode="nearest")
        ok = (valid & dvalid & (depth > 0))[0]
        depth = torch.where(ok, depth, torch.zeros_like(depth))
        sem = torch.where(ok, sem[0], torch.zeros_like(sem[0]))
        image = torch.where(valid, image, torch.zeros_like(image))
        meta = {"panorama": int(k), "view": int(index % self.views), "split": self.split,
                "roll": roll, "pitch": pitch, "yaw": yaw, "camera": self.camera.to_config()}
        if isinstance(pano.get("meta"), Mapping):
            meta["panorama_meta"] = {kk: vv for kk, vv in pano["meta"].items() if isinstance(vv, (str, int, float))}
        return {"image": image.float().clamp(0, 1), "depth": depth.float(), "semantic": sem.long(),
                "valid": ok, "radius": self._radius.unsqueeze(0).clone(), "rotation": R.float(), "meta": meta}


class FisheyeFromPanoramas(ViewsFromPanoramas):
    """:class:`ViewsFromPanoramas` for a fisheye calibration (F165, F195, or a calibration file)."""


class PerspectiveFromPanoramas(ViewsFromPanoramas):
    """Perspective crops of panoramas (the *Pers* dataset): a pinhole of horizontal FOV ``fov_deg``.

    ``camera`` may still be given (any pinhole config); otherwise a square-pixel pinhole of
    ``width x height`` pixels with the given horizontal field of view is used.
    """

    def __init__(self, width: int = 128, height: int = 128, fov_deg: float = 90.0, camera: Any = None,
                 **kwargs: Any) -> None:
        if camera is None:
            if not 0 < fov_deg < 180:
                raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg}")
            f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
            camera = {"type": "pinhole", "width": int(width), "height": int(height), "fx": f, "fy": f,
                      "cx": width / 2, "cy": height / 2}
        super().__init__(camera=camera, width=width, height=height, **kwargs)
