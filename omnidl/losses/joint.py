"""FreDSNet's joint loss (thesis §4.3.5, Eq. 4.7–4.8).

``L_total = alpha_semantic L_Seg + alpha_depth L_Dep + alpha_margin L_mar + alpha_object L_obj``
with the thesis' hand-set ``alpha = [8, 12, 0.001, 4]``.

:func:`object_loss` (Eq. 4.7): per-class depth maps ``y^i = depth * m^i`` for the ground truth
(``m^i`` = one-hot label) and the prediction (``m^i`` = softmax probability of class ``i`` by default,
so the loss reaches the semantic branch too; ``"hard"``: argmax one-hot; ``"gt"``: the true label),
the MSE of each class map over the pixels with valid depth and a known label, averaged over the
known classes (``1 .. C-1``).

Bad inputs are handled as in :mod:`omnidl.losses.depth` and :mod:`omnidl.losses.segmentation`: NaN/inf depth
targets are masked (flag ``nonfinite_depth``), labels outside ``[0, C)`` other than the ignore index are an error
naming the values, the class count and the samples, predictions with NaN/inf give a non-finite loss.
"""
from __future__ import annotations

import warnings
from typing import Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from .checks import DepthUnitCheck, require_same_shape
from .depth import _as_4d, _item, depth_loss, margin_loss, prepare_depth, valid_depth_mask
from .segmentation import IGNORE_INDEX, SegmentationLoss, check_segmentation_inputs

TASKS = ("depth", "semantic")


def object_loss(depth: Tensor, target: Tensor, logits: Tensor, labels: Tensor, mode: str = "soft",
                ignore_index: int = IGNORE_INDEX) -> Tensor:
    """Eq. 4.7. ``depth``, ``target``: ``(B, 1, H, W)``; ``logits``: ``(B, C, H, W)``; ``labels``: ``(B, H, W)``.

    Returns 0 (connected to the graph) when no pixel has both valid depth and a known label. Errors: shapes that
    differ, labels outside ``[0, C)`` other than ``ignore_index``.
    """
    depth, target = _as_4d(depth), _as_4d(target)
    require_same_shape(depth, target, "depth", "target", "object_loss")
    labels = check_segmentation_inputs(logits, labels, ignore_index, "object_loss")
    return _object_loss(depth, target, logits, labels, mode, ignore_index)


def _object_loss(depth: Tensor, target: Tensor, logits: Tensor, labels: Tensor, mode: str, ignore_index: int) -> Tensor:
    num_classes = logits.shape[1]
    valid = (valid_depth_mask(target)[:, 0] & (labels != ignore_index))       # (B, H, W)
    if not valid.any():
        return (depth.sum() + logits.sum()) * 0.0
    lab = labels.clamp(0, num_classes - 1)
    gt_masks = F.one_hot(lab, num_classes).permute(0, 3, 1, 2).to(depth.dtype)  # (B, C, H, W)
    if mode == "soft":
        pred_masks = logits.softmax(1)
    elif mode == "hard":
        pred_masks = F.one_hot(logits.argmax(1), num_classes).permute(0, 3, 1, 2).to(depth.dtype)
    elif mode == "gt":
        pred_masks = gt_masks
    else:
        raise ValueError(f"object_loss: mode must be 'soft', 'hard' or 'gt', got {mode!r}")
    tgt = torch.where(valid.unsqueeze(1), target, torch.zeros_like(target))
    diff = tgt * gt_masks - depth * pred_masks.to(depth.dtype)                   # (B, C, H, W)
    v = valid.unsqueeze(1).expand_as(diff)
    per_class = (diff.pow(2) * v).sum(dim=(0, 2, 3)) / valid.sum()
    keep = torch.ones(num_classes, dtype=torch.bool, device=depth.device)
    if 0 <= ignore_index < num_classes:
        keep[ignore_index] = False
    return per_class[keep].mean()


class JointLoss(nn.Module):
    """Eq. 4.8 as an engine loss: ``loss(outputs, batch) -> (total, terms)``.

    Args:
        alpha_semantic, alpha_depth, alpha_margin, alpha_object: the weights α (plain config fields:
            ``loss.alpha_depth=...`` on the command line or in a search space). A zero weight skips
            the term (and the outputs it needs).
        tasks: the tasks being trained: ``["depth", "semantic"]`` (joint), ``["depth"]`` or
            ``["semantic"]`` (single-task, Table 4.2). Terms needing a task not listed are dropped:
            ``semantic`` needs semantics, ``depth``/``margin`` need depth, ``object`` needs both.
        semantic_loss: ``"ce"`` or ``"recall"`` (ablation codes CE / RL).
        class_weights, class_frequencies, weighting: see :class:`omnidl.losses.segmentation.SegmentationLoss`.
        berhu_ratio: ``c = berhu_ratio * max error`` (0.2). wrap: horizontal wrap of the Sobel gradients.
        object_mode: prediction masks of the object loss (``"soft"`` | ``"hard"`` | ``"gt"``).
        margin_per_image: margin loss per image then averaged (default: over the whole batch, as Eq. 4.6).

    ``terms`` holds every computed raw loss (``semantic``, ``depth``, ``depth_abs``, ``depth_grad``,
    ``margin``, ``object``) and ``no_valid_depth`` / ``no_valid_semantic`` = 1.0 when a batch has no
    usable pixel for that task (its terms are then 0).
    """

    def __init__(self, alpha_semantic: float = 8.0, alpha_depth: float = 12.0, alpha_margin: float = 0.001,
                 alpha_object: float = 4.0, tasks: Sequence[str] = TASKS, semantic_loss: str = "ce",
                 class_weights: Sequence[float] | str | None = None, class_frequencies: Sequence[float] | None = None,
                 weighting: str = "inverse_log", berhu_ratio: float = 0.2, wrap: bool = True,
                 object_mode: str = "soft", margin_per_image: bool = False,
                 ignore_index: int = IGNORE_INDEX) -> None:
        super().__init__()
        tasks = tuple(tasks)
        if not tasks or set(tasks) - set(TASKS):
            raise ValueError(f"JointLoss: tasks must be a non-empty subset of {TASKS}, got {tasks}")
        self.alpha = {"semantic": float(alpha_semantic), "depth": float(alpha_depth),
                      "margin": float(alpha_margin), "object": float(alpha_object)}
        if any(a < 0 for a in self.alpha.values()):
            raise ValueError(f"JointLoss: loss weights must be >= 0, got {self.alpha}")
        needs = {"semantic": {"semantic"}, "depth": {"depth"}, "margin": {"depth"}, "object": {"depth", "semantic"}}
        self.active = [k for k, a in self.alpha.items() if a > 0 and needs[k] <= set(tasks)]
        if not self.active:
            raise ValueError(f"JointLoss: no active term for tasks {tasks} and weights {self.alpha}")
        self.tasks = tasks
        self.seg = SegmentationLoss(semantic_loss, class_weights, class_frequencies, weighting, ignore_index)
        self.berhu_ratio, self.wrap, self.object_mode = berhu_ratio, wrap, object_mode
        self.margin_per_image, self.ignore_index = margin_per_image, ignore_index
        self.unit_check = DepthUnitCheck("JointLoss")

    @staticmethod
    def _get(d: dict, key: str, where: str) -> Tensor:
        if key not in d:
            raise KeyError(f"JointLoss: {where}[{key!r}] is missing (have {sorted(d)}); "
                           f"set loss.tasks or the alpha of the terms that need it to 0")
        return d[key]

    def forward(self, outputs: dict[str, Tensor], batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        terms: dict[str, float] = {}
        parts: list[Tensor] = []
        need_depth = any(k in self.active for k in ("depth", "margin", "object"))
        need_sem = any(k in self.active for k in ("semantic", "object"))
        if need_depth:
            self._get(outputs, "depth", "outputs")
            self._get(batch, "depth", "batch")
            pred, target, mask, flags = prepare_depth(outputs, batch, "JointLoss", self.unit_check)
            terms.update(flags)
        if need_sem:
            logits = self._get(outputs, "semantic", "outputs")
            labels = self._get(batch, "semantic", "batch")
            if labels.dim() == 4 and labels.shape[1] == 1:
                labels = labels[:, 0]
            labels = check_segmentation_inputs(logits, labels, self.ignore_index, "JointLoss", batch,
                                               ("outputs['semantic']", "batch['semantic']"))
            if not (labels != self.ignore_index).any():
                warnings.warn("JointLoss: batch without labelled pixels; semantic terms set to 0", stacklevel=2)
                terms["no_valid_semantic"] = 1.0
        if "semantic" in self.active:
            l_seg = self.seg.segmentation_term(logits, labels, checked=True)
            terms["semantic"] = _item(l_seg)
            parts.append(self.alpha["semantic"] * l_seg)
        if "depth" in self.active:
            l_dep, l_abs, l_grad = depth_loss(pred, target, mask, self.berhu_ratio, self.wrap)
            terms.update(depth=_item(l_dep), depth_abs=_item(l_abs), depth_grad=_item(l_grad))
            parts.append(self.alpha["depth"] * l_dep)
        if "margin" in self.active:
            l_mar = margin_loss(pred, target, mask, self.margin_per_image)
            terms["margin"] = _item(l_mar)
            parts.append(self.alpha["margin"] * l_mar)
        if "object" in self.active:
            if logits.shape[-2:] != pred.shape[-2:] or logits.shape[0] != pred.shape[0]:
                raise ValueError(f"JointLoss: outputs['semantic'] {tuple(logits.shape)} and outputs['depth'] "
                                 f"{tuple(pred.shape)} differ in batch size or map size; expected the same")
            l_obj = _object_loss(pred, target, logits, labels, self.object_mode, self.ignore_index)
            terms["object"] = _item(l_obj)
            parts.append(self.alpha["object"] * l_obj)
        total = torch.stack(parts).sum() if len(parts) > 1 else parts[0]
        terms["total"] = _item(total)
        return total, terms
