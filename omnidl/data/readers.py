"""Image readers with clear errors (OpenCV underneath). Every function names the file it failed on."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from .robust import CorruptSampleError


def read_raw(path: str | Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    """``cv2.imread`` that raises :class:`CorruptSampleError` for missing, empty or undecodable files."""
    path = Path(path)
    if not path.is_file():
        raise CorruptSampleError(f"missing file {path}")
    if path.stat().st_size == 0:
        raise CorruptSampleError(f"empty file {path}")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, flags)
    if img is None:
        raise CorruptSampleError(f"cannot decode image {path} (truncated or not an image?)")
    if path.suffix.lower() == ".png" and not data[-12:].tobytes().endswith(b"IEND\xaeB`\x82"):
        raise CorruptSampleError(f"truncated PNG {path} (no IEND chunk)")
    return img


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

    ``expect=(W, H)`` checks the stored size first (a depth map of the wrong size is an error naming both
    sizes); ``size=(W, H)`` then resizes with nearest neighbour (never blends valid and invalid depth).
    """
    raw = read_raw(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim == 3:
        raw = raw[..., 0]
    if raw.dtype not in (np.uint16, np.uint8, np.float32):
        raise CorruptSampleError(f"depth map {path}: unexpected pixel type {raw.dtype} (expected 16-bit PNG)")
    if expect is not None and (raw.shape[1], raw.shape[0]) != tuple(expect):
        raise CorruptSampleError(f"depth map {path} is {raw.shape[1]}x{raw.shape[0]}, expected {expect[0]}x{expect[1]} "
                                 "(the size of its RGB image)")
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
