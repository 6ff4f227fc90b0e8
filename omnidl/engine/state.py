"""Training state: the position in the run, best/last bookkeeping, checkpoints and exact resume.

:class:`TrainState` is what a checkpoint needs besides the weights: ``step`` (optimiser steps done),
``epoch``, ``batch_in_epoch`` (the sampler position inside the epoch), the best monitored value and
the early-stopping counter. :class:`Checkpointer` writes ``<output_dir>/checkpoints/{last,best}.pt``
(see :mod:`omnidl.engine.checkpoint` for the file layout) with every RNG, and restores all of it, so a
resumed run continues the loss curve bit for bit.

Write order: ``best.pt`` before ``last.pt``. ``last.pt`` records the best value and step, so it must never
be on disk before the ``best.pt`` it describes: a kill between the two writes leaves the previous ``last.pt``
(which describes the previous, still present ``best.pt``), and the resumed run redoes that validation.
On resume a missing ``best.pt`` is repaired (rewritten from ``last.pt`` when they are the same step, else
the best is forgotten with a warning so the next validation writes one).
"""
from __future__ import annotations

import logging
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from . import distributed as ddp
from omnidl.utils.io import remove_stale_temps, temp_tag

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
    ``save_optimizer``: also keep the optimiser/scheduler/RNG state in ``best.pt`` (``last.pt`` always has it).
    """

    #: keys only a resumable checkpoint needs (left out of a weights-only best.pt)
    RESUME_KEYS = ("optimizer", "scheduler", "scaler", "rng")

    def __init__(self, ckpt_dir: Path, cfg: DictConfig, raw_model: torch.nn.Module, opt: Optimisation,
                 dist: ddp.DistInfo, save_optimizer: bool = False):
        self.dir = Path(ckpt_dir)
        self.cfg = cfg
        self.raw_model = raw_model
        self.opt = opt
        self.dist = dist
        self.save_optimizer = save_optimizer
        if dist.is_main:  # temp files a kill -9 left behind (atomic writes never leave a half file as last/best);
            # only those of dead processes on this host (temp names carry pid@host), never a live writer's
            for p in remove_stale_temps(self.dir, ["last.pt", "best.pt"]):
                log.info("removed %s, left by an interrupted checkpoint write", p)
            for p in remove_stale_temps(self.dir.parent, ["metrics.json", "train_log.jsonl"]):
                log.info("removed %s, left by an interrupted write", p)
            self._check_writable()

    def _check_writable(self) -> None:
        """Fail at start-up, not after the first training steps, when checkpoints cannot be written."""
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            fd, probe = tempfile.mkstemp(prefix=".write-test.", suffix=".tmp", dir=self.dir)
            os.close(fd)
            os.unlink(probe)
        except OSError as e:
            raise OSError(e.errno, f"cannot write checkpoints to {self.dir}: {e.strerror or e}") from e

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
        """Write ``best.pt`` (when ``best``) and then ``last.pt`` on rank 0; every rank must call it (RNG gather).

        ``best.pt`` first: ``last.pt`` says which step is best, so it must not exist before that ``best.pt``."""
        ck = self.state_dict(state)
        if self.dist.is_main:
            if best:
                save_checkpoint(self.best, self.best_dict(ck))
            save_checkpoint(self.last, ck)

    def finish(self, state: TrainState) -> None:
        """At the normal end of a run (every rank calls it): unless ``save_optimizer``, rewrite ``last.pt``
        without the optimiser/RNG state (a finished run needs only its weights; that is 2/3 of an Adam
        checkpoint). When the last step is also the best one, ``last.pt`` becomes a hard link to ``best.pt``
        (the same bytes on disk once; a copy where links are not supported)."""
        if self.save_optimizer:
            return
        ck = self.best_dict(self.state_dict(state))
        if not self.dist.is_main:
            return
        if state.best_step == state.step and self.best.is_file():
            tmp = self.dir / f".last.pt.{temp_tag()}.link.tmp"   # remove_stale_temps finds it (if this process dies)
            try:
                if self.last.is_file() and os.path.samefile(self.best, self.last):
                    return                               # already one file (a resumed finished run)
                tmp.unlink(missing_ok=True)
                os.link(self.best, tmp)
                os.replace(tmp, self.last)               # a no-op when both are links of one file...
                tmp.unlink(missing_ok=True)              # ... so never leave the temp link behind
                return
            except OSError:
                tmp.unlink(missing_ok=True)
        save_checkpoint(self.last, ck)

    def best_dict(self, ck: dict[str, Any]) -> dict[str, Any]:
        """``ck`` as written to ``best.pt``: weights-only unless ``save_optimizer``."""
        if self.save_optimizer:
            return ck
        return {k: v for k, v in ck.items() if k not in self.RESUME_KEYS}

    def repair_best(self, state: TrainState, ck: dict[str, Any]) -> None:
        """After resuming from ``last.pt``: make sure the ``best.pt`` it describes exists.

        Same step as ``last.pt``: rewrite ``best.pt`` from it. An older best whose file is gone (deleted by
        hand; omnidl's write order never loses it): forget it with a warning, so the next validation that
        gives a number writes a new ``best.pt``."""
        if state.best is None or state.best_step < 0 or self.best.is_file() or not self.dist.is_main:
            return
        if state.best_step == state.step:
            save_checkpoint(self.best, self.best_dict(ck))
            log.warning("%s was missing; rewrote it from %s (both are step %d)", self.best, self.last, state.step)
            return
        log.warning("%s is missing although %s records its best %s at step %d; that checkpoint cannot be "
                    "recovered, so the best is reset and the next validation writes a new best.pt",
                    self.best, self.last, state.best, state.best_step)
        state.best, state.best_step, state.bad_validations = None, -1, 0

    def resume_path(self, resume: bool) -> str | None:
        """``cfg.checkpoint`` if given, else ``last.pt`` when ``trainer.resume`` and it exists."""
        path = self.cfg.get("checkpoint")
        if not path and resume and self.last.is_file():
            path = str(self.last)
        if resume and not path and self.dist.is_main:
            log.info("trainer.resume=true but %s does not exist yet: starting from scratch", self.last)
        return path

    def restore(self, path: str | None, device: torch.device, ck: dict[str, Any] | None = None,
                total_steps: int | None = None) -> TrainState:
        """Load ``path`` (weights only for a bare state dict or a weights-only ``best.pt``; everything for a
        full checkpoint). ``ck``: the already loaded checkpoint of ``path``. The weights-only ``last.pt`` of a
        finished run restores its position (nothing is left to train; ``total_steps`` checks that)."""
        state = TrainState()
        if not path:
            return state
        ck = load_checkpoint(path, map_location=device) if ck is None else ck
        load_model_weights(self.raw_model, ck, path)
        own_last = Path(path).resolve() == self.last.resolve()
        if "optimizer" not in ck and own_last and "step" in ck:
            state = TrainState.from_checkpoint(ck)
            if total_steps is not None and state.step < total_steps:
                raise ValueError(f"{path} is the weights-only last.pt of a finished run (step {state.step}); it has "
                                 f"no optimiser state to continue to step {total_steps}. Start a new run from its "
                                 f"weights with checkpoint={path} in another run folder (or train with "
                                 "trainer.save_optimizer=true to keep that state)")
            return state
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
            if own_last:
                self.repair_best(state, ck)
        if self.dist.is_main:
            log.info("resumed from %s at step %d (epoch %d, batch %d)", path, state.step, state.epoch,
                     state.batch_in_epoch)
        return state
