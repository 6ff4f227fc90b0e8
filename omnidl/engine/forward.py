"""One forward pass of a model on a batch, shared by training, validation and evaluation.

A batch is the dict of :func:`omnidl.data.collate.collate_samples` (``image (B, 3, H, W)`` plus
targets and ``meta``); a model returns a dict of named outputs. Under AMP the outputs come back in
bfloat16/float16; losses, metrics and hooks always see float32 (:func:`float_outputs`).
"""
from __future__ import annotations

from contextlib import nullcontext
from typing import Any

import torch


def to_device(batch: dict[str, Any], device: torch.device) -> dict[str, Any]:
    """Move the tensors of a batch to ``device`` (``meta`` and other values are kept)."""
    return {k: (v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}


def autocast_context(device: torch.device, enabled: bool):
    """bfloat16 autocast on CPU, float16 on CUDA; a null context when disabled."""
    if not enabled:
        return nullcontext()
    dtype = torch.float16 if device.type == "cuda" else torch.bfloat16
    return torch.autocast(device_type=device.type, dtype=dtype)


def float_outputs(outputs: dict[str, Any]) -> dict[str, Any]:
    """The model outputs with every floating-point tensor cast to float32 (other values kept)."""
    return {k: (v.float() if isinstance(v, torch.Tensor) and v.is_floating_point() else v) for k, v in outputs.items()}


def forward(model: torch.nn.Module, batch: dict[str, Any], device: torch.device, amp: bool) -> dict[str, Any]:
    """``model(batch["image"])`` under :func:`autocast_context`, outputs cast by :func:`float_outputs`.

    ``batch`` must already be on ``device`` (:func:`to_device`).
    """
    with autocast_context(device, amp):
        outputs = model(batch["image"])
    return float_outputs(outputs)
