"""Depth metrics under the protocols of 360° depth papers, selected by name (``metrics.protocol=...``).

The protocols differ in four choices, each a field of :class:`DepthProtocol`:

* **averaging**: ``image`` (metrics per image on its valid pixels, then the mean over images) or ``pixel``
  (every valid pixel of the dataset pooled; RMSE is then the root of the dataset-wide mean squared error);
* **depth cap**: ground truth above ``max_depth`` either ``mask``-ed out (and the prediction clamped to the
  cap) or ``clamp``-ed to it;
* **median scaling**: off, or the prediction multiplied by ``median(gt) / median(pred)`` per image;
* **log base** of ``rmse_log`` / ``log10``.

Presets (how each follows the peer's published script as documented):

``fredsnet``
    The FreDSNet author's ``DepthMetric`` (also :class:`omnidl.metrics.depth.DepthMetrics`): valid ``gt > 1e-7``,
    no cap, per-image averaging, natural-log ``rmse_log``, no median scaling.
``unifuse`` / ``unifuse_median``
    UniFuse's ``metrics.py`` with its 3D60 loader's mask: valid ``0 < gt <= 10`` m (the loader sets deeper gt
    to 11 and masks it out); gt and prediction clamped below at 0.1 m; the script then writes
    ``gt[pred > 10] = 10`` and never clamps the prediction above: reproduced (``unifuse_gt_quirk``); optional
    median alignment (after the clamps, as there); ``log10`` for ``rmse_log``; metrics per batch weighted by
    batch size, i.e. per-image averaging at batch size 1.
``pixel``
    Pooled over all valid pixels (``0 < gt <= 10`` m, prediction clamped to the cap), natural log.

Keys: ``abs_rel`` (= MRE), ``sq_rel``, ``mae``, ``rmse``, ``rmse_log``, ``log10``, ``delta1..3``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

KEYS = ("abs_rel", "sq_rel", "mae", "rmse", "rmse_log", "log10", "delta1", "delta2", "delta3")


@dataclass(frozen=True)
class DepthProtocol:
    name: str
    averaging: str = "image"             # image | pixel
    min_depth: float = 1e-7              # gt <= min_depth is invalid
    max_depth: float | None = None       # cap (metres) or None
    cap: str = "mask"                    # mask | clamp
    clamp_min: float | None = None       # clamp gt and prediction below (UniFuse: 0.1)
    median_scaling: bool = False
    log_base: float = math.e
    unifuse_gt_quirk: bool = False


DEPTH_PROTOCOLS: dict[str, DepthProtocol] = {
    "fredsnet": DepthProtocol("fredsnet"),
    "unifuse": DepthProtocol("unifuse", min_depth=0.0, max_depth=10.0, cap="mask", clamp_min=0.1, log_base=10.0,
                             unifuse_gt_quirk=True),
    "unifuse_median": DepthProtocol("unifuse_median", min_depth=0.0, max_depth=10.0, cap="mask", clamp_min=0.1,
                                    log_base=10.0, unifuse_gt_quirk=True, median_scaling=True),
    "pixel": DepthProtocol("pixel", averaging="pixel", min_depth=0.0, max_depth=10.0),
}


def get_depth_protocol(name: str, **overrides: Any) -> DepthProtocol:
    if name not in DEPTH_PROTOCOLS:
        raise ValueError(f"unknown depth protocol {name!r}; expected one of {', '.join(DEPTH_PROTOCOLS)}")
    p = replace(DEPTH_PROTOCOLS[name], **{k: v for k, v in overrides.items() if v is not None})
    if p.averaging not in ("image", "pixel"):
        raise ValueError(f"depth protocol averaging={p.averaging!r}; expected 'image' or 'pixel'")
    if p.cap not in ("mask", "clamp"):
        raise ValueError(f"depth protocol cap={p.cap!r}; expected 'mask' or 'clamp'")
    return p


def valid_pairs(pred: Tensor, gt: Tensor, proto: DepthProtocol) -> tuple[Tensor, Tensor]:
    """Flattened float64 ``(pred, gt)`` on the valid pixels of one image, after the protocol's cap, clamps and
    median scaling."""
    if pred.shape != gt.shape:
        raise ValueError(f"depth protocol {proto.name}: prediction {tuple(pred.shape)} and ground truth "
                         f"{tuple(gt.shape)} differ")
    p, g = pred.detach().double().reshape(-1), gt.detach().double().reshape(-1)
    mask = torch.isfinite(g) & (g > proto.min_depth)
    if proto.max_depth is not None and proto.cap == "mask":
        mask &= g <= proto.max_depth
    p, g = p[mask], g[mask]
    if not torch.isfinite(p).all():
        raise ValueError(f"depth protocol {proto.name}: the prediction has non-finite values on valid pixels")
    if proto.clamp_min is not None:
        g, p = g.clamp_min(proto.clamp_min), p.clamp_min(proto.clamp_min)
    if proto.max_depth is not None:
        if proto.unifuse_gt_quirk:        # the script's `gt[pred > 10] = 10`; the prediction is not clamped above
            g = torch.where(p > proto.max_depth, torch.full_like(g, proto.max_depth), g)
        elif proto.cap == "clamp":
            g, p = g.clamp_max(proto.max_depth), p.clamp_max(proto.max_depth)
        else:
            p = p.clamp(0.0, proto.max_depth)
    if proto.median_scaling and len(p):
        mp = p.median()
        if not mp > 0:
            raise ValueError(f"depth protocol {proto.name}: median scaling needs a positive median prediction, got "
                             f"{float(mp)}")
        p = p * (g.median() / mp)
    return p, g


def _sums(p: Tensor, g: Tensor, log_base: float) -> dict[str, float]:
    """Per-pixel sums (and the count) from which every metric follows."""
    tiny = torch.finfo(p.dtype).tiny
    pl = p.clamp_min(tiny)
    lg = math.log(log_base)
    ratio = torch.maximum(pl / g, g / pl)
    e = p - g
    return {"n": float(len(p)), "abs_rel": float((e.abs() / g).sum()), "sq_rel": float((e ** 2 / g).sum()),
            "mae": float(e.abs().sum()), "se": float((e ** 2).sum()),
            "sle": float(((pl.log() - g.log()) / lg).pow(2).sum()),
            "log10": float((pl.log10() - g.log10()).abs().sum()),
            **{f"delta{n}": float((ratio < 1.25 ** n).double().sum()) for n in (1, 2, 3)}}


def _finish(s: dict[str, float]) -> dict[str, float]:
    n = s["n"]
    return {"abs_rel": s["abs_rel"] / n, "sq_rel": s["sq_rel"] / n, "mae": s["mae"] / n, "rmse": math.sqrt(s["se"] / n),
            "rmse_log": math.sqrt(s["sle"] / n), "log10": s["log10"] / n,
            **{f"delta{k}": s[f"delta{k}"] / n for k in (1, 2, 3)}}


def protocol_depth_errors(pred: Tensor, gt: Tensor, protocol: str | DepthProtocol = "fredsnet") -> dict[str, float] | None:
    """Metrics of one image under ``protocol``; ``None`` without valid pixels."""
    proto = get_depth_protocol(protocol) if isinstance(protocol, str) else protocol
    p, g = valid_pairs(pred, gt, proto)
    return _finish(_sums(p, g, proto.log_base)) if len(p) else None


class DepthProtocolMetrics:
    """Engine metric over ``outputs["depth"]`` / ``batch["depth"]`` (``(B, 1, H, W)`` or ``(B, H, W)``, 0 = invalid).

    Args:
        protocol: a name of :data:`DEPTH_PROTOCOLS`; max_depth, median_scaling, averaging: override its fields.
        prefix: prepended to every key.
    """

    def __init__(self, protocol: str = "fredsnet", max_depth: float | None = None, median_scaling: bool | None = None,
                 averaging: str | None = None, prefix: str = "") -> None:
        self.protocol = get_depth_protocol(protocol, max_depth=max_depth, median_scaling=median_scaling,
                                           averaging=averaging)
        self.prefix = prefix
        self.reset()

    def reset(self) -> None:
        self.images = 0
        self.skipped = 0
        self._image_sums = {k: 0.0 for k in KEYS}
        self._pixel_sums: dict[str, float] = {}

    def update(self, outputs: dict[str, Tensor], batch: dict[str, Tensor]) -> None:
        pred, gt = outputs["depth"], batch["depth"]
        pred = pred.unsqueeze(1) if pred.dim() == 3 else pred
        gt = gt.unsqueeze(1) if gt.dim() == 3 else gt
        if pred.shape != gt.shape:
            raise ValueError(f"DepthProtocolMetrics: outputs['depth'] {tuple(pred.shape)} and batch['depth'] "
                             f"{tuple(gt.shape)} differ")
        for i in range(pred.shape[0]):
            p, g = valid_pairs(pred[i], gt[i], self.protocol)
            if not len(p):
                self.skipped += 1
                continue
            s = _sums(p, g, self.protocol.log_base)
            self.images += 1
            for k, v in _finish(s).items():
                self._image_sums[k] += v
            for k, v in s.items():
                self._pixel_sums[k] = self._pixel_sums.get(k, 0.0) + v

    def compute(self) -> dict[str, float]:
        if not self.images:
            out = {k: math.nan for k in KEYS}
        elif self.protocol.averaging == "image":
            out = {k: v / self.images for k, v in self._image_sums.items()}
        else:
            out = _finish(self._pixel_sums)
        out = {self.prefix + k: v for k, v in out.items()}
        if self.skipped:
            out[self.prefix + "skipped_images"] = float(self.skipped)
        return out
