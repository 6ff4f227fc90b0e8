"""Prediction maps as files other tools read: 16-bit depth PNG with its scale beside it, semantic PNG.

* ``write_depth_png16(path, depth)`` writes ``path`` (uint16 PNG, 0 = invalid) and ``<path minus .png>.json``
  ``{"scale": s, "unit": "m", "invalid": 0, ...}``: ``depth_m = png_value * scale``. The scale is 1 mm
  unless the largest depth would overflow 16 bits, then ``max_depth / 65535``.
* ``write_semantic_png(path, labels)`` writes the class ids as an 8-bit PNG (value = class id of
  :data:`omnidl.classes.CLASS_NAMES`) and, with ``color=True``, ``<stem>_color.png`` with the palette.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from torch import Tensor

from omnidl.classes import CLASS_NAMES
from omnidl.utils.io import atomic_imwrite, atomic_write_json

from .colormap import semantic_to_color

MM = 1e-3


def depth_scale_path(path: str | Path) -> Path:
    """The scale file written next to a 16-bit depth PNG: ``x_depth.png`` -> ``x_depth.json``."""
    return Path(path).with_suffix(".json")


def write_depth_png16(path: str | Path, depth: Tensor | np.ndarray, scale: float | None = None) -> tuple[Path, float]:
    """Depth ``(H, W)`` or ``(1, H, W)`` metres -> uint16 PNG + scale JSON (see the module docstring).

    Non-finite or non-positive depths become 0 (invalid). Returns ``(png path, scale)``.
    """
    d = depth.detach().float().cpu().numpy() if isinstance(depth, Tensor) else np.asarray(depth, np.float32)
    d = d.reshape(d.shape[-2:]).astype(np.float64)
    valid = np.isfinite(d) & (d > 0)
    dmax = float(d[valid].max()) if valid.any() else 0.0
    if scale is None:
        scale = MM if dmax <= 65535 * MM else dmax / 65535
    if not scale > 0:
        raise ValueError(f"write_depth_png16: scale must be > 0 metres per unit, got {scale}")
    q = np.where(valid, np.clip(np.round(d / scale), 1, 65535), 0).astype(np.uint16)
    path = Path(path)
    atomic_imwrite(path, q)
    atomic_write_json(depth_scale_path(path), {
        "file": path.name, "scale": scale, "unit": "m", "invalid": 0,
        "meaning": "depth_m = png_value * scale; depth is the range along each pixel's ray (metres)",
        "max_depth": dmax})
    return path, float(scale)


def read_depth_png16(path: str | Path) -> np.ndarray:
    """Read a PNG written by :func:`write_depth_png16` with its scale file: ``(H, W)`` float32 metres
    (0 = invalid)."""
    import cv2
    path = Path(path)
    side = depth_scale_path(path)
    if not side.is_file():
        raise FileNotFoundError(f"{path}: its scale file {side.name} is missing (depth_m = png_value * scale)")
    scale = float(json.loads(side.read_text())["scale"])
    q = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if q is None or q.dtype != np.uint16:
        raise ValueError(f"{path}: expected a 16-bit PNG, got {None if q is None else q.dtype}")
    return q.astype(np.float32) * np.float32(scale)


def write_semantic_png(path: str | Path, labels: Tensor, color: bool = True) -> list[Path]:
    """Class ids ``(H, W)`` (or logits ``(C, H, W)``, arg-maxed) -> 8-bit PNG of ids (+ ``<stem>_color.png``).

    Returns the written paths."""
    if labels.is_floating_point() and labels.dim() == 3:
        labels = labels.argmax(0)
    lab = labels.detach().long().reshape(labels.shape[-2:]).cpu()
    if lab.numel() and (int(lab.min()) < 0 or int(lab.max()) > 255):
        raise ValueError(f"write_semantic_png: class ids must be in [0, 255], got [{int(lab.min())}, {int(lab.max())}]"
                         f" ({len(CLASS_NAMES)} classes: {', '.join(CLASS_NAMES)})")
    path = Path(path)
    out = [atomic_imwrite(path, lab.numpy().astype(np.uint8))]
    if color:
        rgb = semantic_to_color(lab)
        bgr = (rgb.permute(1, 2, 0).numpy()[..., ::-1] * 255).round().astype(np.uint8)
        out.append(atomic_imwrite(path.with_name(path.stem + "_color.png"), np.ascontiguousarray(bgr)))
    return out


def write_rgb_png(path: str | Path, image: Tensor) -> Path:
    """``(3, H, W)`` RGB in [0, 1] -> 8-bit PNG (atomic)."""
    arr = (image.detach().float().clamp(0, 1).cpu().permute(1, 2, 0).numpy()[..., ::-1] * 255).round()
    return atomic_imwrite(path, np.ascontiguousarray(arr.astype(np.uint8)))

