"""One optimisation step: finite checks, forward under AMP, backward, gradient clipping, optimiser step.

A batch with NaN/Inf inputs or a non-finite loss is skipped (a warning names the files) or is an error
(``trainer.skip_nonfinite=false``); too many skipped batches in a row are an error. Under DDP all ranks
agree on every skip, or the gradient all-reduce would hang.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import torch

from omnidl.data.collate import batch_files, nonfinite_keys

from . import distributed as ddp
from .forward import forward, to_device

log = logging.getLogger("omnidl.engine")


def make_grad_scaler(amp: bool, device: torch.device) -> torch.amp.GradScaler | None:
    """A float16 gradient scaler for AMP on CUDA; None otherwise (bfloat16 on CPU needs none)."""
    if amp and device.type == "cuda":
        return torch.amp.GradScaler("cuda", enabled=True)
    return None


class SkipGuard:
    """Counts batches skipped in a row and decides between a warning and an error.

    ``skip_nonfinite``: skip (True) or raise ``FloatingPointError`` (False); ``max_skipped``: the most
    batches skipped in a row before giving up.
    """

    def __init__(self, skip_nonfinite: bool, max_skipped: int):
        self.skip_nonfinite = skip_nonfinite
        self.max_skipped = max_skipped
        self.in_row = 0

    def skip(self, why: str, batch: dict[str, Any] | None) -> None:
        """Record one skipped batch; raises when not allowed. ``None``: every sample of the batch was unreadable
        (each already named in a warning by :class:`~omnidl.data.robust.SkipCorrupt`); such batches count
        towards ``max_skipped`` too, so a dataset whose samples are all corrupt stops instead of looping."""
        if batch is None:
            if self.in_row + 1 > self.max_skipped:
                raise RuntimeError(f"{self.in_row + 1} batches in a row skipped, the last ones because every sample "
                                   "in them was unreadable (see the warnings above for the files); "
                                   f"trainer.max_skipped={self.max_skipped}: check the data")
        if batch is not None:
            files = batch_files(batch)
            if not self.skip_nonfinite:
                raise FloatingPointError(f"{why} in the batch of {files}; set trainer.skip_nonfinite=true to skip "
                                         "such batches")
            if self.in_row + 1 > self.max_skipped:
                raise FloatingPointError(f"{self.in_row + 1} batches in a row skipped (last: {why} in {files}); "
                                         "lower the learning rate or check the data")
            log.warning("skipping a batch: %s (samples %s)", why, files)
        self.in_row += 1

    def reset(self) -> None:
        self.in_row = 0


def input_problems(batch: dict[str, Any] | None, dist: ddp.DistInfo) -> list[str]:
    """Why a batch cannot be used (empty when it can): unreadable, NaN/Inf inputs, or another rank's problem."""
    bad = ["<all samples unreadable>"] if batch is None else nonfinite_keys(batch)
    if dist.enabled:  # every rank must skip together, or DDP's gradient all-reduce would hang
        if ddp.all_reduce_sum(torch.tensor([float(bool(bad))])).item() > 0 and not bad:
            bad = ["<another rank's batch>"]
    return bad


def loss_is_finite(loss: torch.Tensor, dist: ddp.DistInfo) -> bool:
    """``isfinite(loss)``, agreed by all ranks under DDP."""
    finite = torch.isfinite(loss.detach())
    if dist.enabled:
        return ddp.all_reduce_sum(finite.float().reshape(1).cpu()).item() == dist.world_size
    return bool(finite)


@dataclass
class Optimisation:
    """What a step updates: the (possibly DDP-wrapped) model and its optimiser, schedule and scaler."""

    model: torch.nn.Module
    optimizer: torch.optim.Optimizer
    scheduler: Any
    scaler: torch.amp.GradScaler | None
    grad_clip: float = 0.0

    def apply(self, loss: torch.Tensor) -> None:
        """Backward (scaled under AMP on CUDA), clip the gradient norm, optimiser and scheduler step."""
        opt, scaler = self.optimizer, self.scaler
        opt.zero_grad(set_to_none=True)
        if scaler is not None:
            scaler.scale(loss).backward()
            scaler.unscale_(opt)
        else:
            loss.backward()
        if self.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.grad_clip)
        if scaler is not None:
            scaler.step(opt)
            scaler.update()
        else:
            opt.step()
        self.scheduler.step()


def train_step(opt: Optimisation, batch: dict[str, Any] | None, loss_fn, device: torch.device, amp: bool,
               dist: ddp.DistInfo, guard: SkipGuard) -> tuple[float, dict[str, Any]] | None:
    """One optimisation step on ``batch``; returns ``(loss, loss terms)``, or None when the batch was skipped."""
    bad = input_problems(batch, dist)
    if bad:
        guard.skip(f"non-finite values in {bad}", batch)
        return None
    batch = to_device(batch, device)
    loss, terms = loss_fn(forward(opt.model, batch, device, amp), batch)
    if not loss_is_finite(loss, dist):
        opt.optimizer.zero_grad(set_to_none=True)
        guard.skip(f"non-finite loss {float(loss)} (terms {terms})", batch)
        return None
    guard.reset()
    opt.apply(loss)
    return float(loss.detach()), terms
