"""Training state: the position in the run, best/last bookkeeping, checkpoints and exact resume.

:class:`TrainState` is what a checkpoint needs besides the weights: ``step`` (optimiser steps done),
``epoch``, ``batch_in_epoch`` (the sampler position inside the epoch), the best monitored value and
the early-stopping counter. :class:`Checkpointer` writes ``<output_dir>/checkpoints/{last,best}.pt``
(see :mod:`omnidl.engine.checkpoint` for the file layout) with every RNG, and restores all of it, so a
resumed run continues the loss curve bit for bit.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from . import distributed as ddp
from .checkpoint import load_checkpoint, load_model_weights, save_checkpoint
from .seed import rng_state, set_rng_state
from .step import Optimisation

log = logging.getLogger("omnidl.engine")


def is_better(value: float, best: float | None, mode: str, min_delta: float = 0.0) -> bool:
    """Whether ``value`` improves on ``best`` (``mode`` ``min``/``max``; None or NaN best: any number)."""
    if mode not in ("min", "max"):
        raise ValueError(f"trainer.monitor_mode={mode!r}: expected 'min' or 'max'")
    if best is None or math.isnan(best):
        return not math.isnan(value)
    return value < best - min_delta if mode == "min" else value > best + min_delta


@dataclass
class TrainState:
    """Where a run is and how it went; saved in every checkpoint."""

    step: int = 0
    epoch: int = 0
    batch_in_epoch: int = 0
    best: float | None = None
    best_step: int = -1
    bad_validations: int = 0
    last_val: dict[str, float] = field(default_factory=dict)

    def record_validation(self, result: dict[str, float], monitor: str, mode: str, min_delta: float) -> bool:
        """Keep ``result`` as the last validation and update best/early-stopping; True if it improved."""
        self.last_val = result
        if monitor not in result:
            raise KeyError(f"trainer.monitor={monitor!r} is not among the validation results {sorted(result)}")
        value = float(result[monitor])
        if is_better(value, self.best, mode, min_delta):
            self.best, self.best_step, self.bad_validations = value, self.step, 0
            return True
        self.bad_validations += 1
        return False

    def as_dict(self) -> dict[str, Any]:
        return {"step": self.step, "epoch": self.epoch, "batch_in_epoch": self.batch_in_epoch, "best": self.best,
                "best_step": self.best_step, "bad_validations": self.bad_validations, "last_val": self.last_val}

    @classmethod
    def from_checkpoint(cls, ck: dict[str, Any]) -> "TrainState":
        return cls(step=int(ck["step"]), epoch=int(ck["epoch"]), batch_in_epoch=int(ck["batch_in_epoch"]),
                   best=ck.get("best"), best_step=int(ck.get("best_step", -1)),
                   bad_validations=int(ck.get("bad_validations", 0)), last_val=ck.get("last_val", {}))


class Checkpointer:
    """Writes and restores checkpoints of one run (rank 0 writes; every rank's RNG is gathered).

    ``raw_model``: the model without its DDP wrapper (its state dict has no ``module.`` prefix).
    """

    def __init__(self, ckpt_dir: Path, cfg: DictConfig, raw_model: torch.nn.Module, opt: Optimisation,
                 dist: ddp.DistInfo):
        self.dir = Path(ckpt_dir)
        self.cfg = cfg
        self.raw_model = raw_model
        self.opt = opt
        self.dist = dist

    @property
    def last(self) -> Path:
        return self.dir / "last.pt"

    @property
    def best(self) -> Path:
        return self.dir / "best.pt"

    def state_dict(self, state: TrainState) -> dict[str, Any]:
        """Everything needed to resume: weights, optimiser/scheduler/scaler, RNGs (all ranks), ``state``."""
        rng = rng_state()
        if self.dist.enabled:  # every rank's RNG (dropout streams differ per rank)
            gathered = [None] * self.dist.world_size
            torch.distributed.all_gather_object(gathered, rng)
            rng = gathered
        scaler = self.opt.scaler
        return {"model": self.raw_model.state_dict(), "optimizer": self.opt.optimizer.state_dict(),
                "scheduler": self.opt.scheduler.state_dict(), "scaler": scaler.state_dict() if scaler else None,
                "rng": rng, **state.as_dict(), "config": OmegaConf.to_container(self.cfg, resolve=False)}

    def save(self, state: TrainState, best: bool = False) -> None:
        """Write ``last.pt`` (and ``best.pt`` when ``best``) on rank 0; every rank must call it (RNG gather)."""
        ck = self.state_dict(state)
        if self.dist.is_main:
            save_checkpoint(self.last, ck)
            if best:
                save_checkpoint(self.best, ck)

    def resume_path(self, resume: bool) -> str | None:
        """``cfg.checkpoint`` if given, else ``last.pt`` when ``trainer.resume`` and it exists."""
        path = self.cfg.get("checkpoint")
        if not path and resume and self.last.is_file():
            path = str(self.last)
        if resume and not path and self.dist.is_main:
            log.info("trainer.resume=true but %s does not exist yet: starting from scratch", self.last)
        return path

    def restore(self, path: str | None, device: torch.device) -> TrainState:
        """Load ``path`` (weights only for a bare state dict; everything for a full checkpoint)."""
        state = TrainState()
        if not path:
            return state
        ck = load_checkpoint(path, map_location=device)
        load_model_weights(self.raw_model, ck, path)
        if "optimizer" in ck:
            self.opt.optimizer.load_state_dict(ck["optimizer"])
            self.opt.scheduler.load_state_dict(ck["scheduler"])
            if self.opt.scaler is not None and ck.get("scaler") is not None:
                self.opt.scaler.load_state_dict(ck["scaler"])
            state = TrainState.from_checkpoint(ck)
            rng = ck.get("rng")
            if rng is not None:
                if isinstance(rng, list):
                    rng = rng[self.dist.rank] if self.dist.rank < len(rng) else rng[0]
                set_rng_state(rng)
        if self.dist.is_main:
            log.info("resumed from %s at step %d (epoch %d, batch %d)", path, state.step, state.epoch,
                     state.batch_in_epoch)
        return state
