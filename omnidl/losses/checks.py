"""Input checks shared by the losses: clear errors naming the key, the value, what was expected and the samples.

Every check is cheap on the normal path (one reduction such as a min/max per tensor and batch); the work of
finding *which* values and samples are wrong is only done when the check fails.

* :func:`sample_names` — the names of (some of) the samples of a batch, from ``batch["meta"]`` (a list of dicts
  with ``"name"``, ``"image"`` or ``"file"``, as :func:`omnidl.data.collate.collate_samples` makes it).
* :func:`require_float`, :func:`require_same_shape`, :func:`require_nonempty_maps` — dtype / shape checks.
* :func:`as_class_ids` — semantic labels → int64 class ids in ``[0, num_classes)`` or the ignore index.
* :func:`require_unit_interval` — a dense target (heat map, corner heat) is finite and in ``[0, 1]``.
* :class:`DepthUnitCheck` — warns once when depth does not look like metres.
"""
from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

MAX_LISTED = 8
MAX_PLAUSIBLE_DEPTH_M = 1000.0   # mean valid depth above this: not metres
PRED_TARGET_SCALE = 100.0        # mean prediction this many times the mean target: a unit mismatch


def sample_names(batch: Mapping[str, Any] | None, index: Tensor | list[int] | None = None) -> list[str]:
    """Names of the samples ``index`` (all if None) of a collated batch, or ``[]`` when it carries no ``meta``."""
    meta = batch.get("meta") if isinstance(batch, Mapping) else None
    if not isinstance(meta, (list, tuple)):
        return []
    idx = range(len(meta)) if index is None else [int(i) for i in index]
    out = []
    for i in idx:
        m = meta[i] if 0 <= i < len(meta) else None
        if isinstance(m, Mapping):
            out.append(str(m.get("name") or m.get("image") or m.get("file") or m.get("index", i)))
        else:
            out.append(f"#{i}")
    return out


def _in_samples(batch: Mapping[str, Any] | None, bad: Tensor) -> str:
    """`` in samples a, b`` for the batch entries where the per-pixel bool ``bad`` holds (or the indices)."""
    if bad.dim() == 0 or bad.numel() == 0:
        return ""
    rows = bad.reshape(bad.shape[0], -1).any(1).nonzero().flatten().tolist()
    names = sample_names(batch, rows)
    what = "sample(s)" if names else "batch item(s)"
    names = names or [str(i) for i in rows]
    more = f" and {len(names) - MAX_LISTED} more" if len(names) > MAX_LISTED else ""
    return f" in {what} " + ", ".join(names[:MAX_LISTED]) + more


def _values(x: Tensor) -> str:
    vals = torch.unique(x.detach().flatten().cpu())
    n = MAX_LISTED if not x.is_floating_point() else 4
    shown = ", ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in vals[:n].tolist())
    return f"[{shown}{', ...' if vals.numel() > n else ''}]"


def require_float(x: Tensor, what: str, where: str) -> None:
    """``x`` must be a floating-point tensor (a prediction)."""
    if not x.is_floating_point():
        raise ValueError(f"{where}: {what} must be a floating-point tensor, got {x.dtype}")


def require_same_shape(a: Tensor, b: Tensor, what_a: str, what_b: str, where: str) -> None:
    """``a`` and ``b`` must have the same shape (no silent broadcasting)."""
    if a.shape != b.shape:
        raise ValueError(f"{where}: {what_a} has shape {tuple(a.shape)} but {what_b} has shape {tuple(b.shape)}; "
                         "expected the same shape")


def require_nonempty_maps(x: Tensor, what: str, where: str) -> None:
    """With a non-empty batch, no spatial dimension (after batch and channel) may be 0."""
    if x.shape[0] > 0 and x.numel() == 0:
        raise ValueError(f"{where}: {what} has a zero-size map {tuple(x.shape)}; expected H, W >= 1 "
                         "(check the resize/crop of the data or the model's output size)")


def as_class_ids(labels: Tensor, num_classes: int, ignore_index: int, where: str, key: str = "batch['semantic']",
                 batch: Mapping[str, Any] | None = None) -> Tensor:
    """``labels`` as int64 class ids; every value must be in ``[0, num_classes)`` or equal ``ignore_index``.

    Float labels are accepted when they hold whole numbers (a NaN or a fraction, e.g. from bilinear resizing, is an
    error). The normal path costs one min/max; the error names the offending values, the class count, the ignore
    index and the samples (from ``batch["meta"]``)."""
    if labels.is_floating_point():
        if labels.numel() and not torch.isfinite(labels).all():
            bad = ~torch.isfinite(labels)
            raise ValueError(f"{where}: {key} holds {int(bad.sum())} NaN/inf value(s){_in_samples(batch, bad)}; "
                             "expected integer class ids")
        frac = labels != labels.round()
        if labels.numel() and frac.any():
            raise ValueError(f"{where}: {key} is {labels.dtype} with non-integer values {_values(labels[frac])}"
                             f"{_in_samples(batch, frac)}; expected integer class ids (resize label maps with "
                             "nearest-neighbour interpolation)")
    labels = labels.long()
    if labels.numel() == 0:
        return labels
    lo, hi = torch.aminmax(labels)
    if int(lo) >= 0 and int(hi) < num_classes:
        return labels
    bad = ((labels < 0) | (labels >= num_classes)) & (labels != ignore_index)
    if bad.any():
        raise ValueError(f"{where}: {key} holds class id(s) {_values(labels[bad])} outside [0, {num_classes}) "
                         f"({num_classes} classes in the logits, ignore index {ignore_index}){_in_samples(batch, bad)};"
                         " expected class ids below the class count: remap them in the dataset (e.g. to the ignore "
                         "index) or set the model's number of classes")
    return labels


def require_unit_interval(t: Tensor, where: str, key: str, batch: Mapping[str, Any] | None = None) -> None:
    """A dense probability target must be finite and within ``[0, 1]`` (one min/max on the normal path)."""
    if t.numel() == 0:
        return
    hint = ""
    if not t.is_floating_point():
        t, hint = t.float(), f" (an integer {t.dtype} map: scale it to [0, 1])"
    lo, hi = torch.aminmax(t.detach())
    if float(lo) >= 0.0 and float(hi) <= 1.0:   # NaN compares false: falls through
        return
    nonfinite = ~torch.isfinite(t)
    if nonfinite.any():
        raise ValueError(f"{where}: {key} holds {int(nonfinite.sum())} NaN/inf value(s){_in_samples(batch, nonfinite)};"
                         " expected finite values in [0, 1]")
    bad = (t < 0) | (t > 1)
    raise ValueError(f"{where}: {key} holds values from {float(lo):.3g} to {float(hi):.3g} "
                     f"(e.g. {_values(t[bad])}), expected values in [0, 1]{_in_samples(batch, bad)}{hint}")


class DepthUnitCheck:
    """Warns (once per instance) when depth does not look like metres.

    Two signs, both from the valid pixels of a batch: a mean target depth above ``MAX_PLAUSIBLE_DEPTH_M``
    (millimetres, or a scale applied twice), or a mean prediction ``PRED_TARGET_SCALE`` times the mean target (a
    model trained in other units). A prediction much *smaller* than the target is not reported: an untrained model
    starts near 0. Costs two masked means per batch until it has warned."""

    def __init__(self, where: str) -> None:
        self.where, self.warned = where, False

    def __call__(self, pred: Tensor, target: Tensor, mask: Tensor) -> None:
        if self.warned or not bool(mask.any()):
            return
        with torch.no_grad():
            n = mask.sum()
            t_mean = float(torch.where(mask, target, 0).sum(dtype=torch.float32) / n)   # fp16 sums overflow
            p_mean = float(torch.where(mask, pred.detach().abs(), 0).sum(dtype=torch.float32) / n)
        if t_mean > MAX_PLAUSIBLE_DEPTH_M:
            msg = (f"{self.where}: valid target depths average {t_mean:.3g} m (> {MAX_PLAUSIBLE_DEPTH_M:g} m): "
                   "the depth is probably not in metres (millimetres? a depth scale applied twice?); convert it to "
                   "metres in the dataset")
        elif p_mean > PRED_TARGET_SCALE * t_mean:
            msg = (f"{self.where}: depth scale mismatch of {p_mean / t_mean:.3g}x: the prediction averages "
                   f"{p_mean:.3g} but its target {t_mean:.3g} m; are model and data in the same unit (metres)?")
        else:
            return
        self.warned = True
        warnings.warn(msg, stacklevel=3)
