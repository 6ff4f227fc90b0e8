"""Depth metrics (Zioulis et al. 2018, thesis §4.5), computed per image on valid pixels, then averaged
over images — the protocol of the FreDSNet author's metric code (``DepthMetric``).

Per image, on ``mask = gt > min_depth`` (and ``gt <= max_depth`` when ``max_depth`` is set; the
prediction is then clamped to ``[0, max_depth]``):

* ``mre``  = mean ``|p - g| / g`` (mean relative error, a.k.a. MARE / AbsRel)
* ``mae``  = mean ``|p - g|``
* ``rmse`` = ``sqrt(mean (p - g)^2)`` (a mean of per-image RMSEs, not a global RMSE)
* ``rmse_log`` = ``sqrt(mean (ln p - ln g)^2)`` on the pixels where also ``p > min_depth`` (an image
  without any such pixel uses ``p`` clamped to ``min_depth`` instead: a large, finite value)
* ``delta1/2/3`` = fraction of pixels with ``max(p/g, g/p) < 1.25^n``

:func:`depth_errors` is the functional core (one image); :class:`DepthMetrics` follows the metrics
contract ``reset() / update(outputs, batch) / compute()``. Images without any valid pixel are skipped
(counted in ``skipped_images`` of :meth:`DepthMetrics.compute` when non-zero).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

DEPTH_METRICS = ("mre", "mae", "rmse", "rmse_log", "delta1", "delta2", "delta3")


def depth_errors(pred: Tensor, gt: Tensor, min_depth: float = 1e-7, max_depth: float | None = None
                 ) -> dict[str, float] | None:
    """Metrics of one image (``pred``, ``gt``: any equal shapes, metres); ``None`` without valid pixels."""
    if pred.shape != gt.shape:
        raise ValueError(f"depth_errors: prediction {tuple(pred.shape)} and ground truth {tuple(gt.shape)} differ")
    p, g = pred.detach().double().reshape(-1), gt.detach().double().reshape(-1)
    mask = (g > min_depth) & torch.isfinite(g)
    if max_depth is not None:
        mask &= g <= max_depth
        p = p.clamp(0.0, max_depth)
    if not mask.any():
        return None
    p, g = p[mask], g[mask]
    if not torch.isfinite(p).all():
        raise ValueError("depth_errors: the prediction has non-finite values on valid pixels")
    err = p - g
    out = {"mre": (err.abs() / g).mean().item(), "mae": err.abs().mean().item(),
           "rmse": err.pow(2).mean().sqrt().item()}
    lm = p > min_depth
    if lm.any():
        out["rmse_log"] = (p[lm].log() - g[lm].log()).pow(2).mean().sqrt().item()
    else:   # no positive prediction at all: clamp to min_depth (large but finite, never NaN)
        out["rmse_log"] = (p.clamp_min(min_depth).log() - g.log()).pow(2).mean().sqrt().item()
    ratio = torch.maximum(p / g, g / p.clamp_min(torch.finfo(p.dtype).tiny))
    for n in (1, 2, 3):
        out[f"delta{n}"] = (ratio < 1.25 ** n).double().mean().item()
    return out


class DepthMetrics:
    """Per-image depth metrics averaged over the dataset.

    Reads ``outputs["depth"]`` and ``batch["depth"]`` (``(B, 1, H, W)`` or ``(B, H, W)``, 0 = invalid).

    Args:
        min_depth: ground truth at or below this is invalid (author's code: 1e-7).
        max_depth: optional evaluation cap (author's protocol: 10 m NYU / 16 m generic): ground
            truth above it is invalid and predictions are clamped to it. ``None``: no cap.
        prefix: prepended to every key of :meth:`compute` (e.g. ``"depth/"``).
    """

    def __init__(self, min_depth: float = 1e-7, max_depth: float | None = None, prefix: str = "") -> None:
        self.min_depth, self.max_depth, self.prefix = min_depth, max_depth, prefix
        self.reset()

    def reset(self) -> None:
        self.sums = {k: 0.0 for k in DEPTH_METRICS}
        self.counts = {k: 0 for k in DEPTH_METRICS}
        self.images = 0
        self.skipped = 0

    def update(self, outputs: dict[str, Tensor], batch: dict[str, Tensor]) -> None:
        pred, gt = outputs["depth"], batch["depth"]
        if pred.dim() == 3:
            pred = pred.unsqueeze(1)
        if gt.dim() == 3:
            gt = gt.unsqueeze(1)
        if pred.shape != gt.shape:
            raise ValueError(f"DepthMetrics: outputs['depth'] {tuple(pred.shape)} and batch['depth'] "
                             f"{tuple(gt.shape)} differ")
        for i in range(pred.shape[0]):
            res = depth_errors(pred[i], gt[i], self.min_depth, self.max_depth)
            if res is None:
                self.skipped += 1
                continue
            self.images += 1
            for k, v in res.items():
                if not math.isnan(v):
                    self.sums[k] += v
                    self.counts[k] += 1

    def compute(self) -> dict[str, float]:
        out = {self.prefix + k: (self.sums[k] / self.counts[k] if self.counts[k] else math.nan) for k in DEPTH_METRICS}
        if self.skipped:
            out[self.prefix + "skipped_images"] = float(self.skipped)
        return out
