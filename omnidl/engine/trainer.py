"""The training loop: :func:`train` (``python train.py ...`` calls it; the loss-weight search calls it in-process).

What one run does (all side effects on rank 0 only):

* resets seeds and thread counts (multirun jobs share a process; ``trainer.num_threads=auto`` picks the
  intra-op thread count from the machine's load once, at the start: :func:`.seed.resolve_num_threads`),
  joins DDP when started by ``torchrun``;
* builds model / datasets / loss / metrics / visualiser from the config, optimiser and per-step LR schedule;
  with ``trainer.compile=true`` the training step calls ``torch.compile(model)`` (Inductor; :mod:`.compile`),
  its compile time logged after the second step, while checkpoints and validation use the plain model;
* trains for ``trainer.max_steps`` optimiser steps (or ``trainer.max_epochs`` epochs), with optional AMP,
  gradient clipping and skipping of batches with non-finite inputs or loss (:mod:`.step`);
* validates every epoch (or every ``trainer.val_every_steps``, and every ``trainer.val_every_minutes`` of wall
  time; :mod:`.validation`, running the configured ``postprocess`` hooks before the metrics), keeps
  ``checkpoints/last.pt`` (also every ``trainer.ckpt_every_steps`` / ``ckpt_every_minutes``) and a weights-only
  ``checkpoints/best.pt`` (by ``trainer.monitor``; :mod:`.state`), stops early after
  ``trainer.early_stopping.patience`` validations without improvement;
* on Ctrl-C / SIGTERM finishes the step, writes ``last.pt`` and raises
  :class:`~omnidl.engine.interrupt.TrainingInterrupted` with the exact resume command (:mod:`.interrupt`);
* logs TensorBoard scalars and image grids under ``tb/``, every logged training step in ``train_log.jsonl``
  (:mod:`.log`);
* writes ``metrics.json`` and returns the same dict.

Output policy (:mod:`.run_dir`, :mod:`omnidl.utils.outputs`): the run folder is locked for the whole run
(``.omnidl.lock``: pid and host; a second process on the same folder stops with a message naming the first);
a folder with a previous run's checkpoints/metrics is refused unless ``trainer.resume=true`` continues that run
or ``trainer.overwrite=true`` replaces it; ``trainer.resume=true`` without ``last.pt`` in a used folder stops.

Resume (``trainer.resume=true`` or ``checkpoint=PATH``) restores model, optimiser, scheduler, AMP scaler,
every RNG and the sampler position, so the loss curve continues exactly as if never interrupted; other
optimisation/data settings than the checkpoint's are an error unless ``trainer.resume_override=true``
(:mod:`.resume`), and ``train_log.jsonl`` is cut back to the resumed step.
"""
from __future__ import annotations

import logging
import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from torch.utils.data import DataLoader

from omnidl.data.collate import collate_samples
from omnidl.data.robust import SkipCorrupt
from omnidl.utils.io import atomic_write_json
from omnidl.utils.outputs import RunLock

from . import distributed as ddp
from .build import build_dataset, build_loss, build_metrics, build_model, build_viz, output_dir, pick_device
from .checkpoint import load_checkpoint
from .compile import CompileTimer, compile_for_training
from .config import check_finite_config, check_trainer_config, missing_search_result
from .hooks import ConfiguredHooks
from .interrupt import StopRequest, TrainingInterrupted
from .log import TrainLogger
from .optim import build_optimizer, build_scheduler
from .resume import apply_new_settings, check_resume_dir, check_resume_settings, resume_command
from .run_dir import check_output_options, check_train_dir
from .sampler import ResumableDistributedSampler
from .seed import seed_everything
from .state import Checkpointer, TrainState, is_better
from .step import Optimisation, SkipGuard, make_grad_scaler, train_step
from .validation import run_validation

log = logging.getLogger("omnidl.engine")


def train(cfg: DictConfig) -> dict[str, Any]:
    """Train the configured model; returns (and writes to ``<output_dir>/metrics.json``) the summary:
    ``{"monitor", "best", "best_step", "final": {...val metrics...}, "step", "epoch", "stopped_early",
    "wall_time_s", "output_dir", "checkpoint_best", "checkpoint_last"}``.
    """
    t0 = time.time()
    tc = cfg.trainer
    check_trainer_config(tc, cfg.optim)
    check_finite_config(cfg)
    check_output_options(tc)
    out_dir = Path(output_dir(cfg))
    # one process per run folder (rank 0 holds the lock for all ranks; taken before DDP starts, so a refused
    # start never leaves the other ranks waiting), then the folder rules of .run_dir
    lock = RunLock(out_dir, "training run") if int(os.environ.get("RANK", "0")) == 0 else None
    if lock is not None:
        lock.acquire()
    try:
        if lock is not None:
            check_train_dir(cfg, out_dir, out_dir / "checkpoints" / "last.pt")
        return _train(cfg, out_dir, t0)
    finally:
        if lock is not None:
            lock.release()


def _train(cfg: DictConfig, out_dir: Path, t0: float) -> dict[str, Any]:
    """:func:`train` once the run folder is locked and checked."""
    tc = cfg.trainer
    seed_everything(int(tc.seed), tc.num_threads, bool(tc.deterministic))
    device = pick_device(str(tc.device), int(os.environ.get("LOCAL_RANK", 0)))
    dist = ddp.setup(device, str(tc.distributed_backend))
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if dist.is_main and (note := missing_search_result(cfg)):
        log.warning(note)
    model, raw_model = _model(cfg, device, dist)
    loss_fn = _loss(cfg, device)
    metrics = build_metrics(cfg)
    viz = build_viz(cfg) if dist.is_main else None
    train_ds, val_ds = _datasets(cfg)
    bs = int(tc.batch_size)
    sampler = ResumableDistributedSampler(len(train_ds), shuffle=True, seed=int(tc.seed), rank=dist.rank,
                                          world_size=dist.world_size)
    steps_per_epoch, total_steps = _step_budget(len(sampler), bs, tc)
    optimizer = build_optimizer(model.parameters(), cfg.optim)
    opt = Optimisation(model, optimizer, build_scheduler(optimizer, cfg.sched, total_steps),
                       make_grad_scaler(bool(tc.amp), device), float(tc.grad_clip))
    ckpt = Checkpointer(out_dir / "checkpoints", cfg, raw_model, opt, dist, bool(tc.save_optimizer))
    state = _resume(cfg, ckpt, opt, device, dist, total_steps)
    logger = TrainLogger(out_dir, dist.is_main, bool(tc.tensorboard), bool(tc.progress), int(tc.log_every_steps),
                         state.step, total_steps)
    if dist.is_main:
        out_dir.mkdir(parents=True, exist_ok=True)
        log.info("output dir: %s; %d training samples, %d steps (%d per epoch), device %s, world size %d",
                 out_dir, len(train_ds), total_steps, steps_per_epoch, device, dist.world_size)
    is_better(0.0, None, str(tc.monitor_mode))  # validates the mode string
    val_loader = None
    if val_ds is not None:
        val_gen = torch.Generator()  # its own seed generator: validation must not draw from the global RNG,
        val_gen.manual_seed(int(tc.seed))  # or a wall-time-triggered validation would change the training
        val_loader = DataLoader(val_ds, batch_size=bs, shuffle=False, num_workers=int(tc.num_workers),
                                collate_fn=collate_samples, generator=val_gen)
    loop = _Loop(cfg, device, dist, opt, loss_fn, metrics, viz, ConfiguredHooks.from_config(cfg), val_loader,
                 ckpt, logger, train_ds, sampler, steps_per_epoch, total_steps,
                 compile_timer=CompileTimer(device, enabled=dist.is_main) if bool(tc.compile) else None)
    logger.start()
    stopped_early = loop.run(state)
    if loop.compile_timer is not None:
        loop.compile_timer.finish()
    logger.close()
    ckpt.finish(state)
    summary = {"monitor": str(tc.monitor), "best": state.best, "best_step": state.best_step,
               "final": state.last_val, "step": state.step, "epoch": state.epoch,
               "stopped_early": bool(stopped_early), "wall_time_s": time.time() - t0, "output_dir": str(out_dir),
               "checkpoint_best": str(ckpt.best) if ckpt.best.is_file() else None,
               "checkpoint_last": str(ckpt.last) if ckpt.last.is_file() else None}
    if dist.is_main:
        atomic_write_json(out_dir / "metrics.json", summary)
        from .expected import summary_lines  # (lazy: the module is also a command, python -m ...expected)
        for line in summary_lines(state.last_val, cfg):
            log.info("%s", line)
        log.info("done: %d steps in %.1f s; best %s = %s (step %d); outputs in %s", state.step, summary["wall_time_s"],
                 tc.monitor, state.best, state.best_step, out_dir)
    ddp.cleanup()
    return summary


@dataclass
class _Loop:
    """The epoch/step loop of one run, with validation, checkpointing and early stopping."""

    cfg: DictConfig
    device: torch.device
    dist: ddp.DistInfo
    opt: Optimisation
    loss_fn: Any
    metrics: Any
    viz: Any
    hooks: ConfiguredHooks
    val_loader: DataLoader | None
    ckpt: Checkpointer
    logger: TrainLogger
    train_ds: Any
    sampler: ResumableDistributedSampler
    steps_per_epoch: int
    total_steps: int
    last_image_step: int = -10**9
    last_val_time: float = 0.0
    last_ckpt_time: float = 0.0
    compile_timer: CompileTimer | None = None   # trainer.compile=true: times the first two steps (rank 0)

    def run(self, state: TrainState) -> bool:
        """Train until ``total_steps`` or early stopping (then True); Ctrl-C/SIGTERM: :meth:`_interrupt`."""
        with StopRequest() as request:
            return self._run(state, request)

    def _due(self, every_steps: int, every_minutes: float, since: float, step: int) -> bool:
        """Whether a periodic validation/checkpoint is due at ``step`` (by steps, or by wall time since ``since``;
        rank 0 decides the wall-time part for all ranks)."""
        if every_steps > 0 and step % every_steps == 0:
            return True
        if every_minutes <= 0:
            return False
        due = time.monotonic() - since >= every_minutes * 60
        return bool(ddp.broadcast_object(due)) if self.dist.enabled else due

    def _run(self, state: TrainState, request: StopRequest) -> bool:
        tc = self.cfg.trainer
        guard = SkipGuard(bool(tc.skip_nonfinite), int(tc.max_skipped))
        self.opt.model.train()
        self.last_val_time = self.last_ckpt_time = time.monotonic()
        stop, stopped_early = state.step >= self.total_steps, False
        while not stop:
            epoch_done = True
            for batch in self._epoch_loader(state):
                state.batch_in_epoch += 1
                timer = self.compile_timer
                if timer is not None and timer.enabled:
                    timer.start()
                done = train_step(self.opt, batch, self.loss_fn, self.device, bool(tc.amp), self.dist, guard)
                if timer is not None and timer.enabled:
                    timer.stop(done is not None)
                if done is None:
                    if self._stop_requested(request):
                        self._interrupt(state, request, saved=False)
                    continue
                state.step += 1
                self.logger.train_step(state.step, state.epoch, done[0], done[1],
                                       self.opt.optimizer.param_groups[0]["lr"])
                saved = True
                if (self._due(int(tc.val_every_steps), float(tc.val_every_minutes), self.last_val_time, state.step)
                        or state.step >= self.total_steps):
                    stop = self.validate_and_checkpoint(state)
                elif self._due(int(tc.ckpt_every_steps), float(tc.ckpt_every_minutes), self.last_ckpt_time,
                               state.step):
                    self.save(state)
                else:
                    saved = False
                if stop or state.step >= self.total_steps:
                    stopped_early = stop and state.step < self.total_steps
                    stop = True
                    epoch_done = state.batch_in_epoch >= self.steps_per_epoch
                    break
                if self._stop_requested(request):
                    self._interrupt(state, request, saved)
            if epoch_done:
                state.epoch += 1
                state.batch_in_epoch = 0
                if not stop and int(tc.val_every_steps) <= 0:
                    stop = self.validate_and_checkpoint(state)
                    stopped_early = stop
                if not stop and self._stop_requested(request):
                    self._interrupt(state, request, saved=int(tc.val_every_steps) <= 0)
        return stopped_early

    def _stop_requested(self, request: StopRequest) -> bool:
        """A signal reached this process (under DDP: any rank; all ranks then stop at the same step)."""
        if not self.dist.enabled:
            return request.requested
        if ddp.all_reduce_sum(torch.tensor([float(request.requested)])).item() > 0:
            request.signum = request.signum or signal.SIGTERM
            return True
        return False

    def save(self, state: TrainState, best: bool = False) -> None:
        self.ckpt.save(state, best=best)
        self.last_ckpt_time = time.monotonic()

    def _interrupt(self, state: TrainState, request: StopRequest, saved: bool) -> None:
        """Write ``last.pt`` (unless this step already did) and raise :class:`TrainingInterrupted`."""
        if not saved:
            self.save(state)
        out_dir = Path(output_dir(self.cfg))
        command = resume_command(self.cfg, out_dir)
        if self.dist.is_main:
            self.logger.close()
            log.warning("stopped by %s after step %d: %s written. Resume with:\n  %s",
                        signal.Signals(request.signum).name, state.step, self.ckpt.last, command)
        raise TrainingInterrupted(request.signum, state.step, str(self.ckpt.last), command)

    def _epoch_loader(self, state: TrainState) -> DataLoader:
        """The training loader of ``state.epoch``, starting at ``state.batch_in_epoch`` (its own seeded RNG)."""
        tc = self.cfg.trainer
        bs = int(tc.batch_size)
        self.sampler.set_epoch(state.epoch)
        self.sampler.set_start(state.batch_in_epoch * bs)
        if hasattr(self.train_ds, "set_epoch"):
            self.train_ds.set_epoch(state.epoch)
        gen = torch.Generator()
        gen.manual_seed(int(tc.seed) * 1000003 + state.epoch)  # the loader must not draw from the global RNG
        return DataLoader(self.train_ds, batch_size=bs, sampler=self.sampler, num_workers=int(tc.num_workers),
                          collate_fn=collate_samples, drop_last=len(self.sampler) >= bs, generator=gen,
                          pin_memory=self.device.type == "cuda")

    def validate_and_checkpoint(self, state: TrainState) -> bool:
        """Validate (rank 0), update best/early stopping, write checkpoints; True = stop training."""
        tc = self.cfg.trainer
        stop = improved = False
        if self.dist.is_main and self.val_loader is not None:
            with_image = state.step - self.last_image_step >= int(tc.image_every_steps)
            result, image = run_validation(self.ckpt.raw_model, self.val_loader, self.loss_fn, self.metrics,
                                           self.device, bool(tc.amp), int(tc.val_max_batches),
                                           self.viz if with_image else None, self.hooks)
            if image is not None:
                self.last_image_step = state.step
            self.logger.validation(state.step, state.epoch, result, image)
            improved = state.record_validation(result, str(tc.monitor), str(tc.monitor_mode),
                                               float(tc.early_stopping.min_delta))
            patience = int(tc.early_stopping.patience)
            stop = patience > 0 and state.bad_validations >= patience
            if stop:
                log.info("early stopping: %s did not improve for %d validations (best %.4g at step %d)",
                         tc.monitor, state.bad_validations, state.best, state.best_step)
        stop = bool(ddp.broadcast_object(stop))
        self.save(state, best=improved or self.val_loader is None)
        self.last_val_time = time.monotonic()
        ddp.barrier()
        return stop


def _resume(cfg: DictConfig, ckpt: Checkpointer, opt: Optimisation, device: torch.device, dist: ddp.DistInfo,
            total_steps: int) -> TrainState:
    """The state to start from: fresh, or restored from ``checkpoint=`` / ``last.pt`` (``trainer.resume``) after
    checking the run folder and the settings (:mod:`.resume`)."""
    tc = cfg.trainer
    check_resume_dir(cfg, ckpt.last)
    path = ckpt.resume_path(bool(tc.resume))
    if not path:
        return TrainState()
    ck = load_checkpoint(path, map_location=device)
    diffs = check_resume_settings(ck, cfg, path) if "optimizer" in ck else []
    state = ckpt.restore(path, device, ck, total_steps)
    if diffs:
        if dist.is_main:
            log.warning("trainer.resume_override=true: continuing %s with changed settings (not an exact "
                        "continuation):\n  %s", path, "\n  ".join(diffs))
        apply_new_settings(opt.optimizer, opt.scheduler, cfg, state.step, total_steps)
        old_bs = int(((ck.get("config") or {}).get("trainer") or {}).get("batch_size", tc.batch_size))
        state.batch_in_epoch = state.batch_in_epoch * old_bs // int(tc.batch_size)  # same samples consumed
    return state


def _model(cfg: DictConfig, device: torch.device, dist: ddp.DistInfo) -> tuple[torch.nn.Module, torch.nn.Module]:
    """``(model to train, raw model)``: the raw model is the one without the DDP wrapper and without
    ``torch.compile`` (checkpoints: its state dict has no ``module.``/``_orig_mod.`` prefix; validation).

    Order: SyncBatchNorm conversion (CUDA DDP), then DDP, then ``torch.compile`` of the DDP module
    (``trainer.compile=true``), as PyTorch recommends for DDP + compile."""
    model = build_model(cfg).to(device)
    raw_model = model
    if dist.enabled:
        if device.type == "cuda":
            model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
            raw_model = model
        model = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None,
            find_unused_parameters=bool(cfg.trainer.find_unused_parameters))
    if bool(cfg.trainer.compile):
        model = compile_for_training(model, device)
        if dist.is_main:
            log.info("trainer.compile=true: the training step runs torch.compile(model) (Inductor, default mode), "
                     "compiled during the first step; validation and checkpoints use the plain model")
    return model, raw_model


def _loss(cfg: DictConfig, device: torch.device):
    loss_fn = build_loss(cfg)
    if loss_fn is None:
        raise ValueError("no loss configured: choose loss=<name> (configs/loss/) or a model config that sets it")
    return loss_fn.to(device) if isinstance(loss_fn, torch.nn.Module) else loss_fn


def _datasets(cfg: DictConfig):
    """``(train, val or None)``, wrapped: in-memory cache (``data.cache_in_memory``), random rotation
    (``trainer.random_rotation_deg``, train only) and :class:`~omnidl.data.robust.SkipCorrupt`."""
    tc = cfg.trainer
    train_ds = build_dataset(cfg, "train")
    train_ds = SkipCorrupt(_maybe_rotating(_maybe_cached(train_ds, cfg), float(tc.random_rotation_deg), int(tc.seed)))
    val_ds = build_dataset(cfg, "val", required=False)
    return train_ds, (SkipCorrupt(_maybe_cached(val_ds, cfg)) if val_ds is not None else None)


def _maybe_rotating(dataset, max_deg: float, seed: int):
    if max_deg and max_deg > 0:
        from omnidl.data.transforms import RandomRotation
        return RandomRotation(dataset, max_deg=max_deg, seed=seed)
    return dataset


def _maybe_cached(dataset, cfg: DictConfig):
    """``data.cache_in_memory: true`` keeps rendered samples in memory (``data.cache_keys``: which keys)."""
    data = cfg.get("data") or {}
    if bool(data.get("cache_in_memory", False)):
        from omnidl.data.cache import MemoryCache
        keys = data.get("cache_keys")
        return MemoryCache(dataset, list(keys) if keys else None)
    return dataset


def _step_budget(n_samples: int, batch_size: int, tc: DictConfig) -> tuple[int, int]:
    """``(steps per epoch, total optimiser steps)`` for this rank's ``n_samples`` (a short last batch is dropped)."""
    steps_per_epoch = n_samples // batch_size if n_samples >= batch_size else 1
    total = int(tc.max_steps) if int(tc.max_steps) > 0 else int(tc.max_epochs) * steps_per_epoch
    if total <= 0:
        raise ValueError("nothing to train: set trainer.max_steps > 0 or trainer.max_epochs > 0")
    return steps_per_epoch, total
