"""Colour maps: depth -> RGB, semantic labels -> palette RGB, overlays. Torch in, torch out, values in [0, 1]."""
from __future__ import annotations

import numpy as np
import torch

from omnidl.classes import CLASS_COLORS


def _turbo_lut() -> torch.Tensor:
    import matplotlib
    cmap = matplotlib.colormaps["turbo"]
    return torch.tensor(cmap(np.linspace(0.0, 1.0, 256))[:, :3], dtype=torch.float32)


_LUT: torch.Tensor | None = None


def depth_to_color(depth: torch.Tensor, vmax: float | None = None, vmin: float = 0.0) -> torch.Tensor:
    """Depth ``(H, W)`` or ``(1, H, W)`` metres -> ``(3, H, W)`` turbo colours in [0, 1]; invalid (<= 0 or
    non-finite) pixels are black. ``vmax`` defaults to the 99th percentile of the valid depths."""
    global _LUT
    if _LUT is None:
        _LUT = _turbo_lut()
    d = depth.detach().float().reshape(depth.shape[-2:]).cpu()
    valid = torch.isfinite(d) & (d > 0)
    if vmax is None:
        vmax = float(torch.quantile(d[valid], 0.99)) if valid.any() else 1.0
    t = ((d - vmin) / max(vmax - vmin, 1e-6)).clamp(0, 1)
    t = torch.where(valid, t, torch.zeros_like(t))
    rgb = _LUT[(t * 255).round().long()].permute(2, 0, 1)
    return rgb * valid[None]


def palette(num_classes: int | None = None) -> torch.Tensor:
    """``(C, 3)`` float colours of :data:`omnidl.classes.CLASS_COLORS` (grey-cycled beyond them)."""
    cols = torch.tensor(CLASS_COLORS, dtype=torch.float32) / 255.0
    if num_classes is not None and num_classes > len(cols):
        extra = torch.rand(num_classes - len(cols), 3, generator=torch.Generator().manual_seed(0))
        cols = torch.cat([cols, extra])
    return cols


def semantic_to_color(labels: torch.Tensor) -> torch.Tensor:
    """Labels ``(H, W)`` int (or logits ``(C, H, W)``, arg-maxed) -> ``(3, H, W)`` palette colours."""
    if labels.is_floating_point() and labels.dim() == 3:
        labels = labels.argmax(0)
    labels = labels.detach().long().reshape(labels.shape[-2:]).cpu()
    pal = palette(int(labels.max()) + 1 if labels.numel() else None)
    return pal[labels.clamp(min=0)].permute(2, 0, 1)


def overlay(image: torch.Tensor, colors: torch.Tensor, alpha: float = 0.5) -> torch.Tensor:
    """Blend ``colors (3, H, W)`` over ``image (3, H, W)`` (both [0, 1]) with weight ``alpha``."""
    image = image.detach().float().cpu()
    colors = colors.detach().float().cpu()
    if colors.shape[-2:] != image.shape[-2:]:
        colors = torch.nn.functional.interpolate(colors[None], size=image.shape[-2:], mode="nearest")[0]
    return ((1 - alpha) * image + alpha * colors).clamp(0, 1)
