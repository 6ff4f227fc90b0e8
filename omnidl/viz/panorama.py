"""The default visualiser: per sample a row ``RGB | depth pred | depth GT | semantic pred | semantic GT``.

Panels are present only where the outputs/batch have them; semantics are drawn over the RGB image.
"""
from __future__ import annotations

from typing import Any

import torch

from .colormap import depth_to_color, overlay, semantic_to_color
from .grid import make_grid


def sample_panels(outputs: dict[str, Any], batch: dict[str, Any], i: int, depth_max: float | None = None,
                  alpha: float = 0.6) -> list[torch.Tensor]:
    """The panels of sample ``i`` (see module docstring); each ``(3, H, W)`` in [0, 1]."""
    rgb = batch["image"][i].detach().float().cpu().clamp(0, 1)
    panels = [rgb]
    gt_depth = batch.get("depth")
    vmax = depth_max
    if vmax is None and isinstance(gt_depth, torch.Tensor):
        valid = gt_depth[i] > 0
        vmax = float(gt_depth[i][valid].max()) if valid.any() else None
    if isinstance(outputs.get("depth"), torch.Tensor):
        panels.append(depth_to_color(outputs["depth"][i], vmax=vmax))
        if isinstance(gt_depth, torch.Tensor):
            panels.append(depth_to_color(gt_depth[i], vmax=vmax))
    if isinstance(outputs.get("semantic"), torch.Tensor):
        panels.append(overlay(rgb, semantic_to_color(outputs["semantic"][i]), alpha))
        if isinstance(batch.get("semantic"), torch.Tensor):
            panels.append(overlay(rgb, semantic_to_color(batch["semantic"][i]), alpha))
    return panels


class PanoramaVisualizer:
    """``viz(outputs, batch) -> (3, h, w)``: one row of panels per sample for the first ``max_images`` samples."""

    def __init__(self, max_images: int = 2, depth_max: float | None = None, alpha: float = 0.6):
        self.max_images, self.depth_max, self.alpha = max_images, depth_max, alpha

    def __call__(self, outputs: dict[str, Any], batch: dict[str, Any]) -> torch.Tensor:
        n = min(self.max_images, batch["image"].shape[0])
        return make_grid([sample_panels(outputs, batch, i, self.depth_max, self.alpha) for i in range(n)])


class FigureVisualizer:
    """``viz(outputs, batch) -> (3, h, w)``: the full-resolution titled figure of
    :func:`omnidl.viz.figure.prediction_figure` (input | depth | GT depth | semantics | GT semantics, depth
    colour bar in metres, class legend) for each of the first ``max_images`` samples, stacked vertically.

    A drop-in for :class:`PanoramaVisualizer` in a ``viz:`` config (``_target_: omnidl.viz.FigureVisualizer``).
    """

    def __init__(self, max_images: int = 1, depth_max: float | None = None, alpha: float = 0.6):
        self.max_images, self.depth_max, self.alpha = max_images, depth_max, alpha

    def __call__(self, outputs: dict[str, Any], batch: dict[str, Any]) -> torch.Tensor:
        from .figure import prediction_figure

        def pick(d: dict, key: str, i: int):
            v = d.get(key)
            return v[i] if isinstance(v, torch.Tensor) else None
        n = min(self.max_images, batch["image"].shape[0])
        figs = [prediction_figure(batch["image"][i], pick(outputs, "depth", i), pick(outputs, "semantic", i),
                                  pick(batch, "depth", i), pick(batch, "semantic", i), depth_max=self.depth_max,
                                  alpha=self.alpha) for i in range(n)]
        w = max(f.shape[-1] for f in figs)
        return torch.cat([torch.nn.functional.pad(f, (0, w - f.shape[-1]), value=1.0) for f in figs], dim=1)
