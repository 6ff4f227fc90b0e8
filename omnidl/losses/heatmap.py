"""Heat-map loss of HoLiNet: binary cross-entropy on the final and intermediate horizon/VP maps.

Targets ``batch["horizon_map"]`` and ``batch["vp_map"]`` (``(B, 1, H, W)`` in ``[0, 1]``, see
:mod:`omnidl.data.horizon`) are area-resampled to the resolution of every prediction. Predictions are
logits: ``outputs["horizon"]``, ``outputs["vp"]`` ``(B, 1, h, w)`` and the intermediate decoder maps
``outputs["aux_<k>"]`` ``(B, 2, h_k, w_k)`` (channel 0 = horizon, 1 = VP).

``total = sum_maps w_map * [BCE(final) + aux_weight * mean_k BCE(aux_k)]`` with
``pos_weight`` up-weighting the (sparse) positive pixels (``BCEWithLogits``' ``pos_weight``).

Bad inputs: the targets are dense, so a NaN/inf or a value outside ``[0, 1]`` (e.g. an 8-bit ``0..255`` map) is a
``ValueError`` naming the key, the values and the samples (from ``batch["meta"]``); so are non-float logits, a
zero-size map and a batch size or channel count that differ between a prediction and its target. An empty batch
gives 0 with the flag ``no_valid_heatmap``. NaN/inf *logits* propagate to a non-finite loss (skipped by the
engine's ``trainer.skip_nonfinite`` guard).
"""
from __future__ import annotations

import warnings

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from .checks import require_float, require_nonempty_maps, require_unit_interval


def resize_target(target: Tensor, size: tuple[int, int]) -> Tensor:
    """Area-resample (down) or bilinear (up) a ``(B, C, H, W)`` target to ``size = (h, w)``."""
    if tuple(target.shape[-2:]) == tuple(size):
        return target
    if size[0] <= target.shape[-2]:
        return F.adaptive_avg_pool2d(target, size)
    return F.interpolate(target, size=size, mode="bilinear", align_corners=False)


def heatmap_bce(logits: Tensor, target: Tensor, pos_weight: float = 1.0) -> Tensor:
    """Mean BCE-with-logits of ``logits (B, C, h, w)`` against ``target`` resized to ``(h, w)``."""
    _check_pair(logits, target, "logits", "target", "heatmap_bce")
    t = resize_target(target.to(logits.dtype), tuple(logits.shape[-2:]))
    pw = torch.tensor(pos_weight, dtype=logits.dtype, device=logits.device) if pos_weight != 1.0 else None
    return F.binary_cross_entropy_with_logits(logits, t, pos_weight=pw)


def _check_pair(logits: Tensor, target: Tensor, what_l: str, what_t: str, where: str) -> None:
    """A prediction and its target: float logits, no zero-size map, same batch size and channels, both 4-D."""
    require_float(logits, what_l, where)
    if logits.dim() != 4 or target.dim() != 4 or logits.shape[:2] != target.shape[:2]:
        raise ValueError(f"{where}: {what_l} has shape {tuple(logits.shape)} and {what_t} {tuple(target.shape)}; "
                         "expected (B, C, h, w) and (B, C, H, W) with the same B and C")
    require_nonempty_maps(logits, what_l, where)
    require_nonempty_maps(target, what_t, where)


class HeatmapLoss(nn.Module):
    """BCE on HoLiNet's final and intermediate heat maps (loss contract: ``(total, terms)``).

    Args:
        horizon_weight, vp_weight: weights of the two maps.
        aux_weight: weight of the mean intermediate-map loss relative to the final one.
        pos_weight: BCE weight of positive targets (>1 helps the sparse lines/peaks).
    """

    def __init__(self, horizon_weight: float = 1.0, vp_weight: float = 1.0, aux_weight: float = 1.0,
                 pos_weight: float = 5.0) -> None:
        super().__init__()
        self.horizon_weight = float(horizon_weight)
        self.vp_weight = float(vp_weight)
        self.aux_weight = float(aux_weight)
        self.pos_weight = float(pos_weight)

    def forward(self, outputs: dict, batch: dict) -> tuple[Tensor, dict[str, float]]:
        for key in ("horizon_map", "vp_map"):
            if key not in batch:
                raise KeyError(f"HeatmapLoss: the batch has no {key!r} target (keys: {sorted(batch)}); use "
                               "omnidl.data.horizon.RotatedPanoramas")
        for key in ("horizon", "vp"):
            if key not in outputs:
                raise KeyError(f"HeatmapLoss: the model outputs lack {key!r} (have {sorted(outputs)})")
        hl_t, vp_t = batch["horizon_map"], batch["vp_map"]
        for key, out_key in (("horizon_map", "horizon"), ("vp_map", "vp")):
            _check_pair(outputs[out_key], batch[key], f"outputs[{out_key!r}]", f"batch[{key!r}]", "HeatmapLoss")
            require_unit_interval(batch[key], "HeatmapLoss", f"batch[{key!r}]", batch)
        if hl_t.shape[0] == 0:
            warnings.warn("HeatmapLoss: empty batch; heat-map loss set to 0", stacklevel=2)
            zero = sum(v.sum() for k, v in outputs.items() if k in ("horizon", "vp") or k.startswith("aux_")) * 0.0
            return zero, {"bce_horizon": 0.0, "bce_vp": 0.0, "no_valid_heatmap": 1.0, "total": 0.0}
        hl = heatmap_bce(outputs["horizon"], hl_t, self.pos_weight)
        vp = heatmap_bce(outputs["vp"], vp_t, self.pos_weight)
        total = self.horizon_weight * hl + self.vp_weight * vp
        terms = {"bce_horizon": float(hl.detach()), "bce_vp": float(vp.detach())}
        aux_keys = sorted(k for k in outputs if k.startswith("aux_"))
        if aux_keys and self.aux_weight > 0:
            both = torch.cat([hl_t, vp_t], 1)
            w = torch.tensor([self.horizon_weight, self.vp_weight], dtype=hl.dtype, device=hl.device).view(1, 2, 1, 1)
            aux = 0
            for k in aux_keys:
                a = outputs[k]
                _check_pair(a, both, f"outputs[{k!r}]", "the horizon and VP targets", "HeatmapLoss")
                t = resize_target(both.to(a.dtype), tuple(a.shape[-2:]))
                pw = torch.tensor(self.pos_weight, dtype=a.dtype, device=a.device)
                l = F.binary_cross_entropy_with_logits(a, t, pos_weight=pw, reduction="none")
                lk = (l * w).mean(dim=(0, 2, 3)).sum()  # w_h BCE_h + w_v BCE_v at this scale
                aux = aux + lk
                terms[f"bce_{k}"] = float(lk.detach())
            total = total + self.aux_weight * aux / len(aux_keys)
        terms["total"] = float(total.detach())
        return total, terms
