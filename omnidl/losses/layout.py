"""HorizonNet loss (``docs/design.md#horizonnet-targets-and-loss``): L1 on boundary angles + BCE on corner logits.

Predictions: ``outputs["boundary"] (B, 2, W)`` radians below the horizon, ``outputs["corner"] (B, 1, W)``
logits. Targets (data-engine keys, ``docs/synth.md``): ``batch["boundary"] (B, 2, W)`` continuous pixel
rows (``target_units="rows"``, converted with the image height by
:func:`omnidl.geometry.boundary.rows_to_angles`) or radians
(``target_units="radians"``), optional ``batch["boundary_valid"] (B, 2, W)``, and
``batch["corner_heat"]`` (or ``batch["corner"]``) ``(B, 1, W)`` in ``[0, 1]`` (``0.96^d``).

``total = boundary_weight * L1 + corner_weight * BCE``; terms are returned as floats.

Bad inputs: boundary targets are masked, so a NaN/inf angle only drops its column (counted in the flag term
``nonfinite_boundary``); with no valid column the L1 term is 0 (flag ``no_valid_boundary``, with a warning). The
corner heat is dense: a NaN/inf or a value outside ``[0, 1]`` is a ``ValueError`` naming the values and the samples
(from ``batch["meta"]``), as are non-float predictions and target/mask shapes that differ from the predictions'.
An empty batch gives 0 (flags ``no_valid_boundary``, ``no_valid_corner``). NaN/inf *predictions* propagate to a
non-finite loss (skipped by the engine's ``trainer.skip_nonfinite`` guard).
"""
from __future__ import annotations

import warnings

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from ..geometry.boundary import rows_to_angles
from .checks import require_float, require_same_shape, require_unit_interval, sample_names


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
        require_float(pred_b, "outputs['boundary']", "LayoutLoss")
        require_float(pred_c, "outputs['corner']", "LayoutLoss")
        if "boundary" not in batch:
            raise KeyError("LayoutLoss needs batch['boundary'] (B, 2, W) boundary targets")
        tgt = batch["boundary"].to(pred_b)
        require_same_shape(tgt, pred_b, "batch['boundary']", "outputs['boundary']", "LayoutLoss")
        if self.target_units == "rows":
            H = int(batch["image"].shape[-2]) if "image" in batch else pred_b.shape[-1] // 2
            tgt = rows_to_angles(tgt, H)
        valid = batch.get("boundary_valid")
        if valid is not None:
            require_same_shape(valid, tgt, "batch['boundary_valid']", "batch['boundary']", "LayoutLoss")
        valid = torch.ones_like(tgt, dtype=torch.bool) if valid is None else valid.to(pred_b.device).bool()
        finite = torch.isfinite(tgt)
        valid = valid & finite
        flags: dict[str, float] = {}
        if not bool(finite.all()):
            flags["nonfinite_boundary"] = float((~finite).sum())
        diff = (pred_b - torch.where(valid, tgt, pred_b.detach())).abs()
        if bool(valid.any()):
            l1 = diff[valid].mean()
        else:
            l1 = pred_b.sum() * 0
            flags["no_valid_boundary"] = 1.0
            names = sample_names(batch)
            warnings.warn(f"LayoutLoss: no valid boundary column in the batch"
                          f"{' of ' + ', '.join(names[:8]) if names else ''}; boundary loss set to 0", stacklevel=2)
        heat_key = "corner_heat" if "corner_heat" in batch else "corner"
        heat = batch.get(heat_key)
        if heat is None:
            raise KeyError("LayoutLoss needs batch['corner_heat'] (B, 1, W) corner targets")
        if heat.numel() != pred_c.numel() or heat.shape[0] != pred_c.shape[0]:
            raise ValueError(f"LayoutLoss: batch[{heat_key!r}] has shape {tuple(heat.shape)} but outputs['corner'] "
                             f"{tuple(pred_c.shape)}; expected (B, 1, W) like the prediction")
        require_unit_interval(heat, "LayoutLoss", f"batch[{heat_key!r}]", batch)
        heat = heat.to(pred_c).reshape(pred_c.shape)
        if heat.numel():
            bce = F.binary_cross_entropy_with_logits(pred_c, heat)
        else:
            bce = pred_c.sum() * 0
            flags["no_valid_corner"] = 1.0
        total = self.boundary_weight * l1 + self.corner_weight * bce
        return total, {"boundary": float(l1.detach()), "corner": float(bce.detach()), **flags}
