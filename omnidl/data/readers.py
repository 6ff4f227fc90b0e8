"""Image readers with clear errors (OpenCV underneath). Every function names the file it failed on."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from .validate import check_size, read_image, read_raw

__all__ = ["read_raw", "read_rgb", "rgb_to_tensor", "read_depth_png", "resize_labels"]


def read_rgb(path: str | Path, size: tuple[int, int] | None = None) -> torch.Tensor:
    """RGB image -> ``(3, H, W)`` float32 in ``[0, 1]``; ``size=(W, H)`` resizes (area/linear)."""
    return rgb_to_tensor(read_raw(path, cv2.IMREAD_COLOR), size)


def rgb_to_tensor(img: np.ndarray, size: tuple[int, int] | None = None) -> torch.Tensor:
    """A BGR array from OpenCV -> ``(3, H, W)`` float32 RGB in ``[0, 1]``, optionally resized to ``size=(W, H)``."""
    if img.dtype == np.uint16:
        img = (img / 257.0).astype(np.uint8)
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        shrink = img.shape[1] > size[0]
        img = cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).float().div_(255.0)


def read_depth_png(path: str | Path, scale: float, invalid: int | None = None,
                   size: tuple[int, int] | None = None, expect: tuple[int, int] | None = None) -> torch.Tensor:
    """16-bit depth PNG -> ``(1, H, W)`` float32 metres (``value / scale``; ``invalid`` and 0 -> 0).

    Only 16-bit files are accepted: an 8-bit PNG cannot hold the range (it would load as centimetres), so it is
    a :class:`~omnidl.data.validate.DataValidationError` naming the file.

    ``expect=(W, H)`` checks the stored size first (a depth map of the wrong size is an error naming both
    sizes); ``size=(W, H)`` then resizes with nearest neighbour (never blends valid and invalid depth).
    """
    raw = read_image(path, "depth map", channels=None, dtypes=(np.uint16,))     # an 8-bit depth PNG is refused
    if raw.ndim == 3:
        raw = raw[..., 0]
    if expect is not None:
        check_size(raw, expect, path, "depth map")
    depth = raw.astype(np.float32)
    bad = depth <= 0
    if invalid is not None:
        bad |= raw == invalid
    depth = np.where(bad, 0.0, depth / scale).astype(np.float32)
    if size is not None and (depth.shape[1], depth.shape[0]) != tuple(size):
        depth = cv2.resize(depth, tuple(size), interpolation=cv2.INTER_NEAREST)
    return torch.from_numpy(np.ascontiguousarray(depth))[None]


def resize_labels(labels: np.ndarray, size: tuple[int, int] | None) -> np.ndarray:
    """Nearest-neighbour resize of an integer label map to ``size=(W, H)``."""
    if size is None or (labels.shape[1], labels.shape[0]) == tuple(size):
        return labels
    return cv2.resize(labels.astype(np.int32), tuple(size), interpolation=cv2.INTER_NEAREST).astype(labels.dtype)
