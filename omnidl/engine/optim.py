"""Optimisers and learning-rate schedules built from the ``optim``/``sched`` schemas."""
from __future__ import annotations

import math
from typing import Any, Iterable

import torch


def build_optimizer(params: Iterable[torch.nn.Parameter], cfg: Any) -> torch.optim.Optimizer:
    """``cfg``: :class:`~omnidl.engine.config.OptimConfig`-like (``name``, ``lr``, ``weight_decay`` ...)."""
    params = [p for p in params if p.requires_grad]
    if not params:
        raise ValueError("the model has no trainable parameters")
    name = str(cfg.name).lower()
    if name == "adamw":
        return torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay, betas=tuple(cfg.betas),
                                 **_fused(params))
    if name == "adam":
        return torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay, betas=tuple(cfg.betas),
                                **_fused(params))
    if name == "sgd":
        return torch.optim.SGD(params, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
    raise ValueError(f"optim.name={cfg.name!r}: expected one of adamw, adam, sgd")


def _fused(params: list[torch.nn.Parameter]) -> dict:
    """``{"fused": True}`` where PyTorch's fused Adam/AdamW applies (floating-point parameters, all on the CPU or
    all on one CUDA device): one kernel updates every parameter, against one small op per tensor (17 M parameters
    in 565 tensors: about 10x faster per step on a 2-core CPU). The same update up to float rounding."""
    devices = {p.device for p in params}
    if len(devices) == 1 and next(iter(devices)).type in ("cpu", "cuda") and all(p.is_floating_point() for p in params):
        return {"fused": True}
    return {}


def lr_factor(step: int, total_steps: int, cfg: Any) -> float:
    """Multiplier of the base learning rate before optimiser step ``step`` (0-based).

    Linear warm-up over ``warmup_steps`` (from ``1/(warmup_steps+1)`` to 1), then
    ``cosine`` (to ``min_lr_ratio`` at ``total_steps``), ``step`` (``gamma`` every ``step_size``) or ``none``.
    """
    warm = int(cfg.warmup_steps)
    if warm > 0 and step < warm:
        return (step + 1) / (warm + 1)
    name = str(cfg.name).lower()
    if name == "none":
        return 1.0
    if name == "step":
        return float(cfg.gamma) ** ((step - warm) // max(1, int(cfg.step_size)))
    if name == "cosine":
        span = max(1, total_steps - warm)
        t = min(1.0, (step - warm) / span)
        lo = float(cfg.min_lr_ratio)
        return lo + (1 - lo) * 0.5 * (1 + math.cos(math.pi * t))
    raise ValueError(f"sched.name={cfg.name!r}: expected one of cosine, step, none")


def build_scheduler(optimizer: torch.optim.Optimizer, cfg: Any, total_steps: int) -> torch.optim.lr_scheduler.LambdaLR:
    """A per-step ``LambdaLR`` following :func:`lr_factor` (its state dict is saved in checkpoints)."""
    lr_factor(0, total_steps, cfg)  # validate the name early
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: lr_factor(s, total_steps, cfg))
