"""Batch collation for sample dicts: stacks tensors, keeps ``meta`` as a list, drops skipped samples."""
from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch.utils.data import default_collate

log = logging.getLogger("omnidl.data")


def collate_samples(samples: Sequence[Mapping[str, Any] | None]) -> dict[str, Any] | None:
    """Collate dataset items (see docs/extending.md "Data samples and batches").

    ``None`` items (samples a robust dataset skipped, see :class:`omnidl.data.robust.SkipCorrupt`) are
    dropped; if nothing is left the batch is ``None`` and the engine skips it. Tensors are stacked with
    ``default_collate``; ``meta`` and any non-tensor values become lists. Samples must share keys and shapes:
    a mismatch raises a ``ValueError`` that names the key, the shapes and the files (from ``meta``).
    """
    kept = [s for s in samples if s is not None]
    if len(kept) < len(samples):
        log.warning("dropped %d unreadable sample(s) from a batch", len(samples) - len(kept))
    if not kept:
        return None
    keys = list(kept[0].keys())
    for s in kept[1:]:
        if list(s.keys()) != keys and set(s.keys()) != set(keys):
            raise ValueError(f"samples in one batch have different keys: {sorted(keys)} vs {sorted(s.keys())} "
                             f"({_files(kept)})")
    batch: dict[str, Any] = {}
    for k in keys:
        vals = [s[k] for s in kept]
        if k == "meta" or not isinstance(vals[0], torch.Tensor):
            batch[k] = vals if k == "meta" or not isinstance(vals[0], (int, float)) else default_collate(vals)
            continue
        shapes = {tuple(v.shape) for v in vals}
        if len(shapes) > 1:
            raise ValueError(f"samples of one batch have different '{k}' shapes {sorted(shapes)} ({_files(kept)}); "
                             "resize them in the dataset or use batch size 1")
        batch[k] = torch.stack(vals, 0)
    return batch


def _files(samples: Sequence[Mapping[str, Any]]) -> str:
    names = []
    for s in samples:
        m = s.get("meta") or {}
        names.append(str(m.get("name") or m.get("image") or m.get("index", "?")))
    return "samples " + ", ".join(names)


def nonfinite_keys(batch: Mapping[str, Any]) -> list[str]:
    """Keys of floating-point tensors in ``batch`` that hold NaN or Inf."""
    return [k for k, v in batch.items()
            if isinstance(v, torch.Tensor) and v.is_floating_point() and not torch.isfinite(v).all()]


def batch_files(batch: Mapping[str, Any]) -> list[str]:
    """The file names (or indices) of the samples of a batch, from ``meta``, for warnings."""
    out = []
    for m in batch.get("meta") or []:
        if isinstance(m, Mapping):
            out.append(str(m.get("image") or m.get("name") or m.get("index", "?")))
    return out
