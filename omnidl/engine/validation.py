"""Validation during training: mean loss and metrics over the validation loader (``val/...`` scalars).

Per batch: forward (AMP as in training) → loss → the configured post-processing hooks
(:class:`~omnidl.engine.hooks.ConfiguredHooks`, without file exports) → ``metrics.update`` on the
outputs merged with the hook results, exactly as :func:`omnidl.engine.evaluator.evaluate` does.
"""
from __future__ import annotations

from typing import Any

import torch

from .forward import forward, to_device
from .hooks import ConfiguredHooks


@torch.no_grad()
def run_validation(model, loader, loss_fn, metrics, device, amp: bool, max_batches: int = -1,
                   viz=None, hooks: ConfiguredHooks | None = None) -> tuple[dict[str, float], Any]:
    """Mean loss (weighted by batch size) and ``metrics.compute()`` over ``loader``; prefixed ``val/``.

    Returns ``(scalars, image)`` where ``image`` is the visualiser's picture of the first batch (or None).
    ``max_batches >= 0`` stops after that many batches.
    """
    was_training = model.training
    model.eval()
    if metrics is not None:
        metrics.reset()
    total, count, terms_sum, image = 0.0, 0, {}, None
    for i, batch in enumerate(loader):
        if 0 <= max_batches <= i:
            break
        if batch is None:
            continue
        batch = to_device(batch, device)
        out = forward(model, batch, device, amp)
        n = batch["image"].shape[0]
        if loss_fn is not None:
            loss, terms = loss_fn(out, batch)
            if torch.isfinite(loss):
                total += float(loss) * n
                count += n
                for k, v in terms.items():
                    terms_sum[k] = terms_sum.get(k, 0.0) + float(v) * n
        if metrics is not None:
            merged, _ = hooks.run(out, batch, exports=False) if hooks else (out, {})
            metrics.update(merged, batch)
        if image is None and viz is not None:
            image = viz(out, batch)
    model.train(was_training)
    result: dict[str, float] = {}
    if count:
        result["val/loss"] = total / count
        result.update({f"val/loss_{k}": v / count for k, v in terms_sum.items()})
    if metrics is not None:
        result.update({f"val/{k}": float(v) for k, v in metrics.compute().items()})
    return result, image
