"""Semantic segmentation metrics accumulated over a dataset through a confusion matrix (thesis §4.5).

``confusion[t, p]`` counts pixels of true class ``t`` predicted as ``p``; pixels whose true label is
``ignore_index`` (0 = unknown) are not counted at all. For every class ``c != ignore_index``:

* ``IoU_c = TP_c / (TP_c + FP_c + FN_c)`` (FP: known pixels of another class predicted as ``c``;
  a known pixel predicted as "unknown" is a false negative of its true class);
* ``Acc_c = TP_c / (TP_c + FN_c)`` (per-class recall).

``miou`` / ``macc`` average them over the classes present in the ground truth seen so far
(classes that never occur are left out, as they have no defined accuracy); ``pixel_acc`` is the
fraction of known pixels labelled correctly. :class:`SegmentationMetrics` follows the metrics
contract ``reset() / update(outputs, batch) / compute()``.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor


def confusion_matrix(pred: Tensor, labels: Tensor, num_classes: int, ignore_index: int | None = 0) -> Tensor:
    """``(num_classes, num_classes)`` int64 confusion matrix (rows: truth, columns: prediction).

    ``pred``, ``labels``: integer tensors of the same shape; labels equal to ``ignore_index`` or
    outside ``[0, num_classes)`` are dropped; predictions outside the range raise ``ValueError``.
    """
    if pred.shape != labels.shape:
        raise ValueError(f"confusion_matrix: prediction {tuple(pred.shape)} and labels {tuple(labels.shape)} differ")
    p, t = pred.reshape(-1).long(), labels.reshape(-1).long()
    keep = (t >= 0) & (t < num_classes)
    if ignore_index is not None:
        keep &= t != ignore_index
    p, t = p[keep], t[keep]
    if p.numel() and (p.min() < 0 or p.max() >= num_classes):
        raise ValueError(f"confusion_matrix: predicted classes must lie in [0, {num_classes}), "
                         f"got [{int(p.min())}, {int(p.max())}]")
    return torch.bincount(t * num_classes + p, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def scores_from_confusion(conf: Tensor, ignore_index: int | None = 0) -> dict[str, Tensor | float]:
    """Per-class ``iou``/``acc`` (``NaN`` for absent classes) and ``miou``/``macc``/``pixel_acc``."""
    conf = conf.double()
    tp = conf.diag()
    gt = conf.sum(1)
    predicted = conf.sum(0)
    union = gt + predicted - tp
    present = gt > 0
    if ignore_index is not None and 0 <= ignore_index < conf.shape[0]:
        present[ignore_index] = False
    nan = torch.full_like(tp, math.nan)
    iou = torch.where(present, tp / union.clamp_min(1), nan)
    acc = torch.where(present, tp / gt.clamp_min(1), nan)
    total = gt.sum()
    return {"iou": iou, "acc": acc,
            "miou": iou[present].mean().item() if present.any() else math.nan,
            "macc": acc[present].mean().item() if present.any() else math.nan,
            "pixel_acc": (tp.sum() / total).item() if total > 0 else math.nan}


class SegmentationMetrics:
    """mIoU / mAcc / pixel accuracy over a dataset, excluding the unknown class.

    Reads ``outputs["semantic"]`` (``(B, C, H, W)`` logits/probabilities, or ``(B, H, W)`` class ids)
    and ``batch["semantic"]`` (``(B, H, W)`` int, 0 = unknown).

    Args:
        num_classes: including unknown (14).
        ignore_index: the unknown label (0).
        class_names: when given, :meth:`compute` also returns ``iou/<name>`` per present class.
        prefix: prepended to every key.
    """

    def __init__(self, num_classes: int = 14, ignore_index: int | None = 0,
                 class_names: Sequence[str] | None = None, prefix: str = "") -> None:
        if class_names is not None and len(class_names) != num_classes:
            raise ValueError(f"SegmentationMetrics: {len(class_names)} class names for {num_classes} classes")
        self.num_classes, self.ignore_index = num_classes, ignore_index
        self.class_names, self.prefix = class_names, prefix
        self.reset()

    def reset(self) -> None:
        self.confusion = torch.zeros(self.num_classes, self.num_classes, dtype=torch.int64)

    def update(self, outputs: dict[str, Tensor], batch: dict[str, Tensor]) -> None:
        pred, labels = outputs["semantic"], batch["semantic"]
        if labels.dim() == 4 and labels.shape[1] == 1:
            labels = labels[:, 0]
        if pred.dim() == 4:
            if pred.shape[1] != self.num_classes:
                raise ValueError(f"SegmentationMetrics: outputs['semantic'] has {pred.shape[1]} channels, "
                                 f"expected num_classes={self.num_classes}")
            pred = pred.argmax(1)
        self.confusion += confusion_matrix(pred.detach().cpu(), labels.detach().cpu(), self.num_classes,
                                           self.ignore_index)

    def compute(self) -> dict[str, float]:
        s = scores_from_confusion(self.confusion, self.ignore_index)
        out = {self.prefix + k: float(s[k]) for k in ("miou", "macc", "pixel_acc")}
        if self.class_names is not None:
            for name, v in zip(self.class_names, s["iou"].tolist()):
                if not math.isnan(v):
                    out[f"{self.prefix}iou/{name}"] = v
        return out
