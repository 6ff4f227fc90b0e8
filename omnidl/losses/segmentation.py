"""Semantic segmentation losses of FreDSNet (thesis §4.3.5), ignoring the unknown label ``0``.

* :func:`class_weights_from_frequencies` — class weights from label counts/frequencies
  (``"inverse_log"``: ENet's ``1 / ln(1.02 + p_c)``, ``"inverse"``: ``1 / p_c``, ``"median"``:
  median frequency balancing ``median(p) / p_c``); the ignored class gets weight 0, classes never
  seen get the largest weight of the seen ones; weights are normalised to mean 1 over seen classes.
* :func:`label_counts` — per-class pixel counts of a label tensor (accumulate over a dataset).
* :func:`weighted_cross_entropy` — mean weighted cross entropy over known pixels.
* :func:`recall_loss` — Recall loss (Tian et al. 2022, thesis Eq. 4.3):
  ``-(1/N) sum_c (FN_c / (FN_c + TP_c)) sum_{i: y_i = c} log p_i(c)``, with the per-class
  ``1 - recall`` measured on the current batch (argmax, no gradient), ``N`` = known pixels.

Shapes: ``logits (B, C, H, W)``, ``labels (B, H, W)`` int64 (``0`` = unknown).

Bad inputs: a label outside ``[0, C)`` that is not the ignore index is a ``ValueError`` naming the values, the
class count and (for :class:`SegmentationLoss`, from ``batch["meta"]``) the samples; float labels must hold whole
numbers (NaN or fractions are errors); logits must be floating point, with no zero-size map. An empty batch or one
without a labelled pixel gives 0 (flag ``no_valid_semantic``). NaN/inf *logits* propagate to a non-finite loss
(skipped by the engine's ``trainer.skip_nonfinite`` guard).
"""
from __future__ import annotations

import warnings
from typing import Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from .checks import as_class_ids, require_float, require_nonempty_maps
from .depth import _item

IGNORE_INDEX = 0


def label_counts(labels: Tensor, num_classes: int) -> Tensor:
    """``(num_classes,)`` int64 pixel counts of ``labels`` (values outside ``[0, num_classes)`` are dropped)."""
    lab = labels.reshape(-1)
    lab = lab[(lab >= 0) & (lab < num_classes)]
    return torch.bincount(lab, minlength=num_classes)


def class_weights_from_frequencies(counts: Sequence[float] | Tensor, method: str = "inverse_log",
                                   ignore_index: int | None = IGNORE_INDEX) -> Tensor:
    """Class weights ``(C,)`` float32 from per-class pixel counts or frequencies (see the module docstring)."""
    c = torch.as_tensor(counts, dtype=torch.float64).clone()
    if c.dim() != 1 or (c < 0).any():
        raise ValueError(f"class counts must be a 1-D non-negative sequence, got {counts}")
    if ignore_index is not None and 0 <= ignore_index < len(c):   # an ignore index outside [0, C) has no weight
        c[ignore_index] = 0
    total = c.sum()
    if total <= 0:
        raise ValueError("class_weights_from_frequencies: every count is zero")
    p = c / total
    seen = p > 0
    w = torch.zeros_like(p)
    if method == "inverse_log":
        w[seen] = 1.0 / torch.log(1.02 + p[seen])
    elif method == "inverse":
        w[seen] = 1.0 / p[seen]
    elif method == "median":
        w[seen] = p[seen].median() / p[seen]
    else:
        raise ValueError(f"class weighting method must be 'inverse_log', 'inverse' or 'median', got {method!r}")
    w = w / w[seen].mean()
    w[~seen] = w[seen].max()
    if ignore_index is not None and 0 <= ignore_index < len(c):
        w[ignore_index] = 0
    return w.float()


def _zero(ref: Tensor) -> Tensor:
    return ref.sum() * 0.0


def check_segmentation_inputs(logits: Tensor, labels: Tensor, ignore_index: int = IGNORE_INDEX,
                              where: str = "segmentation loss", batch: dict | None = None,
                              keys: tuple[str, str] = ("logits", "labels")) -> Tensor:
    """Check ``logits (B, C, H, W)`` and ``labels (B, H, W)``; returns the labels as int64 class ids.

    ``keys`` name the two tensors in messages; ``batch`` (with ``meta``) lets an error name the samples."""
    require_float(logits, keys[0], where)
    if logits.dim() != 4 or labels.shape != (logits.shape[0], *logits.shape[2:]):
        raise ValueError(f"{where}: expected logits (B, C, H, W) in {keys[0]} and labels (B, H, W) in {keys[1]}, "
                         f"got {tuple(logits.shape)} and {tuple(labels.shape)}")
    require_nonempty_maps(logits, keys[0], where)
    return as_class_ids(labels, logits.shape[1], ignore_index, where, keys[1], batch)


def _check(logits: Tensor, labels: Tensor, ignore_index: int, where: str) -> Tensor:
    return check_segmentation_inputs(logits, labels, ignore_index, where)


def weighted_cross_entropy(logits: Tensor, labels: Tensor, weight: Tensor | None = None,
                           ignore_index: int = IGNORE_INDEX) -> Tensor:
    """``sum_i w_{y_i} (-log p_i(y_i)) / sum_i w_{y_i}`` over pixels with ``y_i != ignore_index``;
    0 when there is no such pixel (or all their weights are 0)."""
    labels = _check(logits, labels, ignore_index, "weighted_cross_entropy")
    return _weighted_cross_entropy(logits, labels, weight, ignore_index)


def _weighted_cross_entropy(logits: Tensor, labels: Tensor, weight: Tensor | None, ignore_index: int) -> Tensor:
    valid = labels != ignore_index
    if weight is not None:
        weight = weight.to(dtype=logits.dtype, device=logits.device)
        if weight.numel() != logits.shape[1]:
            raise ValueError(f"cross entropy: {weight.numel()} class weights for {logits.shape[1]} classes")
        if not (weight[labels.clamp(0, logits.shape[1] - 1)][valid] > 0).any():
            return _zero(logits)
    elif not valid.any():
        return _zero(logits)
    return F.cross_entropy(logits, labels, weight=weight, ignore_index=ignore_index)


def recall_loss(logits: Tensor, labels: Tensor, ignore_index: int = IGNORE_INDEX, eps: float = 1e-12) -> Tensor:
    """Recall loss (Eq. 4.3), normalised by the number of known pixels; 0 without known pixels."""
    labels = _check(logits, labels, ignore_index, "recall_loss")
    return _recall_loss(logits, labels, ignore_index, eps)


def _recall_loss(logits: Tensor, labels: Tensor, ignore_index: int, eps: float = 1e-12) -> Tensor:
    valid = labels != ignore_index
    if not valid.any():
        return _zero(logits)
    num_classes = logits.shape[1]
    with torch.no_grad():
        pred = logits.argmax(1)
        y = labels[valid]
        tp = torch.bincount(y[pred[valid] == y], minlength=num_classes).to(logits.dtype)
        n = torch.bincount(y, minlength=num_classes).to(logits.dtype)
        fn = n - tp
        w = fn / (fn + tp).clamp_min(eps)                   # 1 - recall; 0 for absent classes
    logp = F.log_softmax(logits, dim=1)
    nll = -logp.gather(1, labels.clamp(0, num_classes - 1).unsqueeze(1)).squeeze(1)
    return (w[labels[valid]] * nll[valid]).sum() / valid.sum()


def _count_of(counts: Tensor, index: int) -> Tensor | int:
    """``counts[index]``, or 0 for an index outside the classes (an ignore index such as 255 or -1)."""
    return counts[index] if 0 <= index < counts.numel() else 0


class SegmentationLoss(nn.Module):
    """``L_Seg`` as an engine loss: ``loss(outputs, batch) -> (total, terms)``.

    Args:
        kind: ``"ce"`` (weighted cross entropy) or ``"recall"`` (Recall loss) — ablation codes CE / RL.
        class_weights: ``None`` (uniform), a list of ``num_classes`` weights, or ``"batch"`` (weights
            from the current batch's label frequencies with ``weighting``).
        class_frequencies: per-class pixel counts/frequencies of the training set → weights with
            ``weighting`` (used when ``class_weights`` is ``None``).
        weighting: ``"inverse_log"`` | ``"inverse"`` | ``"median"``.
    Reads ``outputs["semantic"]`` (logits) and ``batch["semantic"]``.
    """

    def __init__(self, kind: str = "ce", class_weights: Sequence[float] | str | None = None,
                 class_frequencies: Sequence[float] | None = None, weighting: str = "inverse_log",
                 ignore_index: int = IGNORE_INDEX) -> None:
        super().__init__()
        if kind not in ("ce", "recall"):
            raise ValueError(f"SegmentationLoss: kind must be 'ce' or 'recall', got {kind!r}")
        self.kind, self.weighting, self.ignore_index = kind, weighting, ignore_index
        self.batch_weights = class_weights == "batch"
        if isinstance(class_weights, str) and not self.batch_weights:
            raise ValueError(f"SegmentationLoss: class_weights must be null, a list or 'batch', got {class_weights!r}")
        w = None
        if class_weights is not None and not self.batch_weights:
            w = torch.as_tensor(list(class_weights), dtype=torch.float32)
        elif class_frequencies is not None:
            w = class_weights_from_frequencies(list(class_frequencies), weighting, ignore_index)
        self.register_buffer("weight", w, persistent=False)

    def segmentation_term(self, logits: Tensor, labels: Tensor, checked: bool = False) -> Tensor:
        """The loss value; ``checked=True``: ``labels`` already passed :func:`check_segmentation_inputs`."""
        if not checked:
            labels = _check(logits, labels, self.ignore_index, type(self).__name__)
        if self.kind == "recall":
            return _recall_loss(logits, labels, self.ignore_index)
        weight = self.weight
        if self.batch_weights:
            counts = label_counts(labels, logits.shape[1])
            weight = class_weights_from_frequencies(counts, self.weighting, self.ignore_index) \
                if counts.sum() - _count_of(counts, self.ignore_index) > 0 else None
        return _weighted_cross_entropy(logits, labels, weight, self.ignore_index)

    def forward(self, outputs: dict[str, Tensor], batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        logits, labels = outputs["semantic"], batch["semantic"]
        if labels.dim() == 4 and labels.shape[1] == 1:
            labels = labels[:, 0]
        labels = check_segmentation_inputs(logits, labels, self.ignore_index, "SegmentationLoss", batch,
                                           ("outputs['semantic']", "batch['semantic']"))
        loss = self.segmentation_term(logits, labels, checked=True)
        terms = {"semantic": _item(loss)}
        if not (labels != self.ignore_index).any():
            warnings.warn("SegmentationLoss: batch without any labelled pixel; semantic loss set to 0", stacklevel=2)
            terms["no_valid_semantic"] = 1.0
        return loss, terms
