"""Image grids: rows of equally sized ``(3, H, W)`` panels with a thin separator."""
from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F


def _fit(img: torch.Tensor, h: int, w: int) -> torch.Tensor:
    img = img.detach().float().cpu()
    if img.dim() == 2:
        img = img[None]
    if img.shape[0] == 1:
        img = img.expand(3, -1, -1)
    if img.shape[-2:] != (h, w):
        img = F.interpolate(img[None], size=(h, w), mode="nearest")[0]
    return img.clamp(0, 1)


def make_grid(rows: Sequence[Sequence[torch.Tensor]], pad: int = 2, value: float = 1.0) -> torch.Tensor:
    """Panels ``rows[r][c]`` (``(3, H, W)``, ``(1, H, W)`` or ``(H, W)`` in [0, 1]) -> one ``(3, h, w)`` image.

    Every panel is resized (nearest) to the size of the first one; ``pad`` pixels of ``value`` separate them.
    """
    if not rows or not rows[0]:
        raise ValueError("make_grid needs at least one panel")
    h, w = rows[0][0].shape[-2:]
    ncol = max(len(r) for r in rows)
    out = torch.full((3, len(rows) * (h + pad) - pad, ncol * (w + pad) - pad), value)
    for i, row in enumerate(rows):
        for j, panel in enumerate(row):
            y, x = i * (h + pad), j * (w + pad)
            out[:, y:y + h, x:x + w] = _fit(panel, h, w)
    return out


def to_uint8_bgr(image: torch.Tensor):
    """``(3, H, W)`` [0, 1] RGB tensor -> ``(H, W, 3)`` uint8 BGR array for OpenCV writers."""
    import numpy as np
    arr = (image.detach().float().clamp(0, 1).cpu().permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    return arr[..., ::-1].copy()
