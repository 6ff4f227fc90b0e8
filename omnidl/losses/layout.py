"""HorizonNet loss (``../shared/reference/layout.md`` §1.2): L1 on the boundary angles + BCE on the corner logits.

Predictions: ``outputs["boundary"] (B, 2, W)`` radians below the horizon, ``outputs["corner"] (B, 1, W)``
logits. Targets (data-engine keys, ``docs/synth.md``): ``batch["boundary"] (B, 2, W)`` continuous pixel
rows (``target_units="rows"``, converted with the image height by
:func:`omnidl.geometry.boundary.rows_to_angles`) or radians
(``target_units="radians"``), optional ``batch["boundary_valid"] (B, 2, W)``, and
``batch["corner_heat"]`` (or ``batch["corner"]``) ``(B, 1, W)`` in ``[0, 1]`` (``0.96^d``).

``total = boundary_weight * L1 + corner_weight * BCE``; terms are returned as floats.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from ..geometry.boundary import rows_to_angles


class LayoutLoss(nn.Module):
    """``loss(outputs, batch) -> (total, {"boundary": float, "corner": float})``."""

    def __init__(self, boundary_weight: float = 1.0, corner_weight: float = 1.0, target_units: str = "rows") -> None:
        super().__init__()
        if target_units not in ("rows", "radians"):
            raise ValueError(f"target_units must be 'rows' or 'radians', got {target_units!r}")
        self.boundary_weight = float(boundary_weight)
        self.corner_weight = float(corner_weight)
        self.target_units = target_units

    def forward(self, outputs: dict, batch: dict) -> tuple[Tensor, dict[str, float]]:
        for k in ("boundary", "corner"):
            if k not in outputs:
                raise KeyError(f"LayoutLoss needs outputs[{k!r}] (HorizonNet-style model)")
        pred_b, pred_c = outputs["boundary"], outputs["corner"]
        if "boundary" not in batch:
            raise KeyError("LayoutLoss needs batch['boundary'] (B, 2, W) boundary targets")
        tgt = batch["boundary"].to(pred_b)
        if tgt.shape != pred_b.shape:
            raise ValueError(f"batch['boundary'] has shape {tuple(tgt.shape)}, predictions {tuple(pred_b.shape)}")
        if self.target_units == "rows":
            H = int(batch["image"].shape[-2]) if "image" in batch else pred_b.shape[-1] // 2
            tgt = rows_to_angles(tgt, H)
        valid = batch.get("boundary_valid")
        valid = torch.ones_like(tgt, dtype=torch.bool) if valid is None else valid.to(pred_b.device).bool()
        valid = valid & torch.isfinite(tgt)
        diff = (pred_b - torch.where(valid, tgt, pred_b.detach())).abs()
        l1 = diff[valid].mean() if valid.any() else pred_b.sum() * 0
        heat = batch.get("corner_heat", batch.get("corner"))
        if heat is None:
            raise KeyError("LayoutLoss needs batch['corner_heat'] (B, 1, W) corner targets")
        heat = heat.to(pred_c).reshape(pred_c.shape)
        bce = F.binary_cross_entropy_with_logits(pred_c, heat)
        total = self.boundary_weight * l1 + self.corner_weight * bce
        return total, {"boundary": float(l1.detach()), "corner": float(bce.detach())}
