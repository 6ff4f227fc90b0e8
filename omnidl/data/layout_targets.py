"""Layout targets through the camera model, and layout augmentations valid for the camera.

* :func:`room_boundary_rows` / :func:`boundary_targets`: per-column ceiling/floor boundary rows
  ``(2, W)`` of a room (top-view polygon and heights in the layout frame, or 3D corners in the camera
  frame), computed *through the camera*: each column's rays (``camera.unproject``) give its vertical
  half-plane, the half-plane meets the wall polygon at a horizontal range, and the ceiling/floor point
  there is re-projected with ``camera.project``. For a non-central panorama the result differs from
  the central one (HorizonNet's ``cor_2_1d`` assumes a central camera).
* :func:`corner_probability` / :func:`corner_heat`: HorizonNet's corner target ``0.96^d`` from the
  corner columns.
* :class:`LayoutAugment` / :class:`LayoutAugmentedDataset`: horizontal roll and left-right flip (exact
  for equirectangular and non-central panoramas: the rig circle is symmetric) and, for central
  panoramas only, HorizonNet's pano stretch (which has no exact non-central counterpart: refused).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..cameras import resolve_camera
from ..geometry.polygon import ray_polygon_hit
from ..geometry.rotations import UPRIGHT_TO_WORLD, rotation_y
from ..metrics.layout import corners_to_layout

CORNER_BASE = 0.96
#: camera frame -> layout frame (float64 numpy)
_R = np.asarray(UPRIGHT_TO_WORLD, dtype=np.float64)


def room_boundary_rows(polygon: np.ndarray, h_ceiling: float, h_floor: float,
                       camera: Any) -> tuple[np.ndarray, np.ndarray]:
    """Ceiling/floor boundary rows of a room through ``camera``, and the wall each column sees.

    Args:
        polygon: ``(N, 2)`` top-view room polygon in the layout frame (metres, any orientation).
        h_ceiling, h_floor: ceiling and floor heights in the layout frame (metres).
        camera: the panorama's camera (any :func:`~omnidl.cameras.resolve_camera` spec).
    Returns:
        ``rows (2, W)`` float64 continuous pixel rows (NaN where the column's half-plane misses the
        room or the camera does not see the point) and ``wall (W,)`` the index of the polygon edge
        each column's half-plane meets first.
    """
    cam = resolve_camera(camera)
    W, H = cam.width, cam.height
    uv = torch.stack([torch.arange(W, dtype=torch.float64) + 0.5, torch.full((W,), H / 2.0, dtype=torch.float64)], -1)
    rays = cam.unproject(uv)
    o = rays.origin.numpy() @ _R.T
    d = rays.direction.numpy() @ _R.T
    b = d[:, :2] / np.maximum(np.linalg.norm(d[:, :2], axis=1, keepdims=True), 1e-12)
    s, wall = ray_polygon_hit(np.asarray(polygon, float), o[:, :2], b)
    ok = np.isfinite(s) & rays.valid.numpy()
    rows = np.full((2, W), np.nan)
    for k, h in enumerate((h_ceiling, h_floor)):
        p = np.concatenate([o[:, :2] + np.where(ok, s, 1.0)[:, None] * b, np.full((W, 1), h)], 1)
        uvp, vis = cam.project(torch.from_numpy(p @ _R))               # layout -> camera frame (R^T)
        rows[k] = np.where(ok & vis.numpy(), uvp[:, 1].numpy(), np.nan)
    return rows, wall


def boundary_targets(corners_cam: np.ndarray, camera: Any) -> tuple[Tensor, Tensor]:
    """Boundary rows ``(2, W)`` (float32, continuous pixel rows) and validity ``(2, W)`` through ``camera``.

    ``corners_cam``: ``(N, 2, 3)`` ceiling/floor corners of the room polygon in the camera frame
    (metres, any orientation of the polygon). Columns whose half-plane misses the room are invalid
    (row ``-1``). See :func:`room_boundary_rows`.
    """
    poly, h_c, h_f = corners_to_layout(corners_cam)
    rows, _ = room_boundary_rows(poly, h_c, h_f, camera)
    valid = np.isfinite(rows)
    return torch.from_numpy(np.where(valid, rows, -1.0)).float(), torch.from_numpy(valid)


def corner_probability(columns: np.ndarray, width: int, base: float = CORNER_BASE) -> np.ndarray:
    """``(W,)`` float64 HorizonNet corner target ``base ** d`` in ``(0, 1]``, ``d`` the circular column distance of
    column centre ``j + 0.5`` to the nearest corner column (zeros without corners).

    Columns are continuous ``u`` on the circle of ``width`` columns (taken modulo ``width``); a NaN/inf
    column is a ``ValueError`` (the readers refuse such labels earlier, naming the file)."""
    u = np.arange(width) + 0.5
    cols = np.asarray(columns, float).reshape(-1)
    if len(cols) == 0:
        return np.zeros(width)
    if not np.isfinite(cols).all():
        raise ValueError(f"corner_probability: corner columns must be finite, got {cols[~np.isfinite(cols)][:3]}")
    cols = np.mod(cols, width)
    dist = np.abs(u[:, None] - cols[None])
    dist = np.minimum(dist, width - dist).min(1)
    return base ** dist


def corner_heat(columns: np.ndarray, width: int, base: float = CORNER_BASE) -> Tensor:
    """``(1, W)`` float32 :func:`corner_probability` (the sample key ``corner_heat``)."""
    return torch.from_numpy(corner_probability(columns, width, base)).float()[None]


# ------------------------------------------------------------------------------------------------
# augmentations
# ------------------------------------------------------------------------------------------------

def roll_sample(sample: dict, shift: int) -> dict:
    """Rotate the panorama about the vertical axis by ``shift`` columns (exact for both panoramas)."""
    out = dict(sample)
    W = sample["image"].shape[-1]
    for k, v in sample.items():
        if isinstance(v, Tensor) and v.dim() >= 2 and v.shape[-1] == W and k not in ("corners_cam", "lines_cam"):
            out[k] = torch.roll(v, shift, -1)
    R = rotation_y(torch.tensor(2 * math.pi * shift / W, dtype=torch.float64)).float()   # longitude += delta
    if "corners_cam" in sample:
        out["corners_cam"] = sample["corners_cam"] @ R.T.to(sample["corners_cam"].dtype)
    if "lines_cam" in sample:
        L = sample["lines_cam"]
        out["lines_cam"] = torch.cat([L[..., :3] @ R.T.to(L.dtype), L[..., 3:] @ R.T.to(L.dtype)], -1)
    if "corners_uv" in sample:
        uv = sample["corners_uv"].clone()
        uv[..., 0] = torch.remainder(uv[..., 0] + shift, W)
        out["corners_uv"] = uv
    return out


def flip_sample(sample: dict) -> dict:
    """Mirror the panorama left-right (``u -> W - u``, camera ``x -> -x``; exact for both panoramas)."""
    out = dict(sample)
    W = sample["image"].shape[-1]
    for k, v in sample.items():
        if isinstance(v, Tensor) and v.dim() >= 2 and v.shape[-1] == W and k not in ("corners_cam", "lines_cam"):
            out[k] = torch.flip(v, [-1])
    S = torch.tensor([-1.0, 1.0, 1.0])
    if "corners_cam" in sample:
        out["corners_cam"] = sample["corners_cam"] * S.to(sample["corners_cam"].dtype)
    if "lines_cam" in sample:
        L = sample["lines_cam"]
        # reflection: d -> S d, m = p x d -> (S p) x (S d) = -S m
        out["lines_cam"] = torch.cat([L[..., :3] * S.to(L.dtype), -L[..., 3:] * S.to(L.dtype)], -1)
    if "corners_uv" in sample:
        uv = sample["corners_uv"].clone()
        uv[..., 0] = torch.remainder(W - uv[..., 0], W)
        out["corners_uv"] = uv
    return out


def pano_stretch_sample(sample: dict, camera: Any, kx: float, kz: float) -> dict:
    """HorizonNet's pano stretch for a *central* panorama: the room scaled by ``kx`` along camera x and
    ``kz`` along z; the image is resampled and the boundary targets are recomputed through the camera."""
    cam = resolve_camera(camera)
    if not getattr(cam, "central", True):
        raise ValueError("pano stretch has no exact counterpart for a non-central panorama (the rig circle would "
                         "have to be stretched too); use roll/flip only")
    out = dict(sample)
    img = sample["image"]
    H, W = img.shape[-2:]
    rays = cam.unproject_grid(torch.float64)
    d = rays.direction.clone()
    d[..., 0] /= kx
    d[..., 2] /= kz
    uv, _ = cam.project(d)
    gx = torch.remainder(uv[..., 0], W) / W * 2 - 1
    gy = uv[..., 1] / H * 2 - 1
    grid = torch.stack([gx, gy], -1).float()[None]
    out["image"] = torch.nn.functional.grid_sample(img[None].float(), grid, mode="bilinear", padding_mode="border",
                                                   align_corners=False)[0]
    for k in ("depth", "semantic", "edges", "layout_seg", "valid", "instance", "normal"):
        out.pop(k, None)                 # not transformed: dropped rather than wrong
    if "corners_cam" in sample:
        n = int(sample.get("num_walls", sample["corners_cam"].shape[0]))
        c = sample["corners_cam"].clone()
        c[..., 0] *= kx
        c[..., 2] *= kz
        out["corners_cam"] = c
        rows, valid = boundary_targets(c[:n].double().numpy(), cam)
        out["boundary"], out["boundary_valid"] = rows, valid
        uvc, _ = cam.project(c[:n, 0].double())
        vis = sample["corners_valid"][:n, 0].numpy() if "corners_valid" in sample else np.ones(n, bool)
        out["corner_heat"] = corner_heat(uvc[:, 0].numpy()[vis], W)
        out.pop("lines_cam", None)
        out.pop("corners_uv", None)
    return out


class LayoutAugment:
    """Random layout augmentation ``sample -> sample`` valid for ``camera`` (see module docstring).

    Args:
        camera: the panorama camera (``Camera`` or config); pano stretch is refused for non-central ones.
        roll, flip: enable a uniform random horizontal rotation / a left-right flip with p = 0.5.
        stretch: max stretch factor (HorizonNet: 2.0; ``None`` disables; central cameras only).
        seed: base seed (a generator per call keeps workers reproducible with the sample index).
    """

    def __init__(self, camera: Any = None, roll: bool = True, flip: bool = True, stretch: float | None = None,
                 seed: int = 0) -> None:
        self.camera = resolve_camera(camera, default=None)
        if stretch is not None and self.camera is not None and not self.camera.central:
            raise ValueError("LayoutAugment: stretch is only valid for central panoramas (got a non-central camera)")
        self.roll, self.flip, self.stretch, self.seed = roll, flip, stretch, seed

    def __call__(self, sample: dict, rng: np.random.Generator | None = None) -> dict:
        rng = rng or np.random.default_rng()
        W = sample["image"].shape[-1]
        if self.stretch is not None and self.camera is not None:
            kx, kz = rng.uniform(1.0, self.stretch, 2)
            kx = kx if rng.random() < 0.5 else 1 / kx
            kz = kz if rng.random() < 0.5 else 1 / kz
            sample = pano_stretch_sample(sample, self.camera, float(kx), float(kz))
        if self.flip and rng.random() < 0.5:
            sample = flip_sample(sample)
        if self.roll:
            sample = roll_sample(sample, int(rng.integers(0, W)))
        return sample


class LayoutAugmentedDataset(torch.utils.data.Dataset):
    """Wrap a map-style dataset of layout samples with :class:`LayoutAugment` (per-index seeded)."""

    def __init__(self, dataset: Any, camera: Any = None, roll: bool = True, flip: bool = True,
                 stretch: float | None = None, seed: int = 0) -> None:
        self.dataset = dataset
        cam = camera if camera is not None else getattr(dataset, "camera", None)
        self.augment = LayoutAugment(cam, roll, flip, stretch, seed)
        self.seed = seed
        self._epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self._epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int) -> dict:
        rng = np.random.default_rng([self.seed, self._epoch, int(i)])
        return self.augment(self.dataset[i], rng)
