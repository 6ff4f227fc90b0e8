"""Depth losses of FreDSNet (thesis §4.3.5, Eq. 4.4–4.6), masked on invalid depth (``0``).

* :func:`berhu` — reverse Huber ``B_c(e)``: ``|e|`` for ``|e| <= c``, ``(e^2 + c^2) / (2c)`` above (Eq. 4.4).
* :func:`adaptive_berhu_loss` — mean ``B_c`` over valid pixels with ``c = ratio * max |e|`` of the batch
  (ratio 0.2; ``c`` carries no gradient).
* :func:`sobel_gradients` — 3x3 Sobel ``d/dx``, ``d/dy``; the horizontal derivative wraps around for
  360° panoramas, the vertical one replicates the border rows.
* :func:`depth_loss` — ``B_c1(e) + B_c2(∇x e) + B_c2(∇y e)`` (Eq. 4.5); a gradient is valid where the
  whole 3x3 neighbourhood is valid; ``c2`` = ratio × the largest gradient error (both directions).
* :func:`margin_loss` — ``((max_gt - max_pred)^2 + (min_gt - min_pred)^2) / 2`` over valid pixels (Eq. 4.6).

Shapes: ``pred``, ``target``: ``(B, 1, H, W)`` (or ``(B, H, W)``) range in metres; ``mask``: same shape, bool.
Every function returns a 0-dim tensor; with no valid pixel it returns ``0`` (connected to ``pred``'s graph).

Bad numbers: a target pixel that is ``0``, negative, NaN or inf is invalid (masked out, also when an explicit
``mask`` covers it); :class:`DepthLoss` counts the NaN/inf ones in the term ``nonfinite_depth``. NaN/inf in the
*prediction* propagate to a non-finite loss (the engine's ``trainer.skip_nonfinite`` guard then skips the batch).
``pred`` and ``target`` of different shapes are an error (never broadcast).
"""
from __future__ import annotations

import warnings

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from omnidl.nn.padding import pad_panorama

from .checks import DepthUnitCheck, require_float, require_nonempty_maps, require_same_shape, sample_names


def valid_depth_mask(target: Tensor) -> Tensor:
    """``target > 0`` and finite: the pixels with ground-truth depth."""
    return (target > 0) & torch.isfinite(target)


def berhu(e: Tensor, c: Tensor | float) -> Tensor:
    """Reverse Huber of the (signed or absolute) error ``e``, elementwise; ``c > 0`` (Eq. 4.4)."""
    a = e.abs()
    c = torch.as_tensor(c, dtype=a.dtype, device=a.device)
    c_safe = torch.clamp(c, min=torch.finfo(a.dtype).tiny)
    return torch.where(a <= c, a, (a * a + c * c) / (2 * c_safe))


def _item(x: Tensor) -> float:
    """A loss value for logging (detached, ``-0.0`` shown as ``0.0``)."""
    return float(x.detach()) + 0.0


def _zero(ref: Tensor) -> Tensor:
    return ref.sum() * 0.0


def adaptive_berhu_loss(pred: Tensor, target: Tensor, mask: Tensor | None = None, ratio: float = 0.2) -> Tensor:
    """Mean reverse Huber over ``mask`` (and finite ``target``) with ``c = ratio * max |pred - target|`` over the
    masked batch."""
    require_same_shape(pred, target, "pred", "target", "adaptive_berhu_loss")
    mask = valid_depth_mask(target) if mask is None else mask & torch.isfinite(target)
    if not mask.any():
        return _zero(pred)
    e = (pred - torch.where(mask, target, pred))[mask]
    c = ratio * e.detach().abs().max()
    return berhu(e, c).mean()


_SOBEL_X = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]])


def sobel_gradients(x: Tensor, wrap: bool = True) -> tuple[Tensor, Tensor]:
    """Sobel derivatives of ``x (B, C, H, W)``: ``(d/dx, d/dy)``, each ``(B, C, H, W)``.

    Kernels ``[[-1,0,1],[-2,0,2],[-1,0,1]]`` (x, towards +u) and its transpose (y, towards +v), not
    normalised. ``wrap=True`` pads columns circularly (longitude), rows by replication.
    """
    b, c, h, w = x.shape
    k = _SOBEL_X.to(dtype=x.dtype, device=x.device)
    kernels = torch.stack([k, k.t()]).unsqueeze(1)                          # (2, 1, 3, 3)
    xx = x.reshape(b * c, 1, h, w)
    xx = F.pad(xx, (0, 0, 1, 1), mode="replicate")
    xx = pad_panorama(xx, 1) if wrap else F.pad(xx, (1, 1, 0, 0), mode="replicate")
    g = F.conv2d(xx, kernels).reshape(b, c, 2, h, w)
    return g[:, :, 0], g[:, :, 1]


def neighbourhood_mask(mask: Tensor, wrap: bool = True) -> Tensor:
    """``(B, C, H, W)`` bool: True where every pixel of the 3x3 neighbourhood is in ``mask``
    (same borders as :func:`sobel_gradients`)."""
    m = (~mask).to(torch.float32)
    m = F.pad(m, (0, 0, 1, 1), mode="replicate")
    m = pad_panorama(m, 1) if wrap else F.pad(m, (1, 1, 0, 0), mode="replicate")
    return F.max_pool2d(m, 3, stride=1) == 0


def _as_4d(x: Tensor) -> Tensor:
    return x.unsqueeze(1) if x.dim() == 3 else x


def depth_loss(pred: Tensor, target: Tensor, mask: Tensor | None = None, ratio: float = 0.2,
               wrap: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    """Eq. 4.5: returns ``(total, B_c1(e), B_c2(∇x) + B_c2(∇y))``.

    ``∇x``, ``∇y`` are the differences of the Sobel derivatives of prediction and ground truth,
    kept where the full 3x3 neighbourhood is valid; ``c2`` = ``ratio`` x their largest magnitude.
    """
    pred, target = _as_4d(pred), _as_4d(target)
    require_same_shape(pred, target, "pred", "target", "depth_loss")
    mask = valid_depth_mask(target) if mask is None else _as_4d(mask) & torch.isfinite(target)
    abs_term = adaptive_berhu_loss(pred, target, mask, ratio)
    gmask = neighbourhood_mask(mask, wrap)
    if not gmask.any():
        grad_term = _zero(pred)
    else:
        tgt = torch.where(mask, target, torch.zeros_like(target))
        pgx, pgy = sobel_gradients(pred, wrap)
        tgx, tgy = sobel_gradients(tgt, wrap)
        ex, ey = (pgx - tgx)[gmask], (pgy - tgy)[gmask]
        c2 = ratio * torch.maximum(ex.detach().abs().max(), ey.detach().abs().max())
        grad_term = berhu(ex, c2).mean() + berhu(ey, c2).mean()
    return abs_term + grad_term, abs_term, grad_term


def margin_loss(pred: Tensor, target: Tensor, mask: Tensor | None = None, per_image: bool = False) -> Tensor:
    """Eq. 4.6 over the valid pixels of the batch (``per_image=True``: per image, then averaged)."""
    pred, target = _as_4d(pred), _as_4d(target)
    require_same_shape(pred, target, "pred", "target", "margin_loss")
    mask = valid_depth_mask(target) if mask is None else _as_4d(mask) & torch.isfinite(target)
    if not per_image:
        if not mask.any():
            return _zero(pred)
        p, t = pred[mask], target[mask]
        return ((t.max() - p.max()) ** 2 + (t.min() - p.min()) ** 2) / 2
    terms = [margin_loss(pred[i:i + 1], target[i:i + 1], mask[i:i + 1]) for i in range(pred.shape[0])
             if mask[i].any()]
    return torch.stack(terms).mean() if terms else _zero(pred)


def prepare_depth(outputs: dict[str, Tensor], batch: dict, where: str,
                  unit_check: DepthUnitCheck | None = None) -> tuple[Tensor, Tensor, Tensor, dict[str, float]]:
    """``outputs["depth"]``, ``batch["depth"]`` checked -> ``(pred, target, mask, flags)``, all ``(B, 1, H, W)``.

    Errors: a non-float prediction, a zero-size map, different shapes. ``flags``: ``nonfinite_depth`` (number of
    NaN/inf target pixels, masked out) and ``no_valid_depth`` (1.0, with a warning naming the samples, when no
    pixel is valid). ``unit_check`` warns once when the depth does not look like metres."""
    require_float(outputs["depth"], "outputs['depth']", where)
    pred = _as_4d(outputs["depth"])
    target = _as_4d(batch["depth"]).to(pred.dtype)
    require_nonempty_maps(pred, "outputs['depth']", where)
    require_same_shape(pred, target, "outputs['depth']", "batch['depth']", where)
    finite = torch.isfinite(target)
    mask = (target > 0) & finite
    flags: dict[str, float] = {}
    if not bool(finite.all()):
        flags["nonfinite_depth"] = float((~finite).sum())
    if not bool(mask.any()):
        names = sample_names(batch)
        warnings.warn(f"{where}: no valid depth pixel in the batch (all 0, negative or NaN/inf)"
                      f"{' in samples ' + ', '.join(names[:8]) if names else ''}; depth loss set to 0", stacklevel=3)
        flags["no_valid_depth"] = 1.0
    elif unit_check is not None:
        unit_check(pred, target, mask)
    return pred, target, mask, flags


class DepthLoss(nn.Module):
    """``L_Dep`` (Eq. 4.5) as an engine loss: ``loss(outputs, batch) -> (total, terms)``.

    Reads ``outputs["depth"]`` and ``batch["depth"]`` (``(B, 1, H, W)``, 0 = invalid). With
    ``alpha_margin > 0`` adds the margin loss (Eq. 4.6). Terms: ``depth``, ``depth_abs``,
    ``depth_grad``, ``margin``, ``no_valid_depth`` (1.0 when the batch has no valid pixel) and
    ``nonfinite_depth`` (the number of NaN/inf target pixels, treated as invalid). Errors: non-float
    prediction, zero-size map, shapes that differ. Warns once when the depth does not look like metres
    (see :class:`omnidl.losses.checks.DepthUnitCheck`).
    """

    def __init__(self, ratio: float = 0.2, wrap: bool = True, alpha_margin: float = 0.0) -> None:
        super().__init__()
        self.ratio, self.wrap, self.alpha_margin = ratio, wrap, alpha_margin
        self.unit_check = DepthUnitCheck("DepthLoss")

    def forward(self, outputs: dict[str, Tensor], batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        pred, target, mask, flags = prepare_depth(outputs, batch, "DepthLoss", self.unit_check)
        total, a, g = depth_loss(pred, target, mask, self.ratio, self.wrap)
        terms = {"depth": _item(total), "depth_abs": _item(a), "depth_grad": _item(g)}
        if self.alpha_margin:
            m = margin_loss(pred, target, mask)
            total = total + self.alpha_margin * m
            terms["margin"] = _item(m)
        terms.update(flags)
        return total, terms
