"""The training loop: :func:`train` (``python train.py ...`` calls it; the loss-weight search calls it in-process).

What one run does (all side effects on rank 0 only):

* resets seeds and thread counts (multirun jobs share a process), joins DDP when started by ``torchrun``;
* builds model / datasets / loss / metrics / visualiser from the config, optimiser and per-step LR schedule;
* trains for ``trainer.max_steps`` optimiser steps (or ``trainer.max_epochs`` epochs), with optional AMP,
  gradient clipping and skipping of batches with non-finite inputs or loss (a warning names the files);
* validates every epoch (or every ``trainer.val_every_steps``), keeps ``checkpoints/last.pt`` and
  ``checkpoints/best.pt`` (by ``trainer.monitor``), stops early after ``trainer.early_stopping.patience``
  validations without improvement;
* logs TensorBoard scalars and image grids under ``tb/``, every logged training step in ``train_log.jsonl``;
* writes ``metrics.json`` and returns the same dict.

Resume (``trainer.resume=true`` or ``checkpoint=PATH``) restores model, optimiser, scheduler, AMP scaler,
every RNG and the sampler position, so the loss curve continues exactly as if never interrupted.
"""
from __future__ import annotations

import json
import os
import logging
import math
import time
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader

from omnidl.data.collate import batch_files, collate_samples, nonfinite_keys
from omnidl.data.robust import SkipCorrupt
from omnidl.utils.io import atomic_write_json

from . import distributed as ddp
from .build import build_dataset, build_loss, build_metrics, build_model, build_viz, output_dir, pick_device
from .checkpoint import load_checkpoint, load_model_weights, save_checkpoint
from .optim import build_optimizer, build_scheduler
from .seed import rng_state, seed_everything, set_rng_state

log = logging.getLogger("omnidl.engine")


def to_device(batch: dict[str, Any], device: torch.device) -> dict[str, Any]:
    """Move the tensors of a batch to ``device`` (``meta`` and other values are kept)."""
    return {k: (v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}


def autocast_context(device: torch.device, enabled: bool):
    """bfloat16 autocast on CPU, float16 on CUDA; a null context when disabled."""
    if not enabled:
        return nullcontext()
    dtype = torch.float16 if device.type == "cuda" else torch.bfloat16
    return torch.autocast(device_type=device.type, dtype=dtype)


def is_better(value: float, best: float | None, mode: str, min_delta: float = 0.0) -> bool:
    if best is None or math.isnan(best):
        return not math.isnan(value)
    if mode == "min":
        return value < best - min_delta
    if mode == "max":
        return value > best + min_delta
    raise ValueError(f"trainer.monitor_mode={mode!r}: expected 'min' or 'max'")


class _JsonlLog:
    """Append-only JSON-lines log of training scalars (``train_log.jsonl``), rank 0 only."""

    def __init__(self, path: Path | None):
        self.path = path

    def write(self, record: dict[str, Any]) -> None:
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")


@torch.no_grad()
def run_validation(model, loader, loss_fn, metrics, device, amp: bool, max_batches: int = -1,
                   viz=None) -> tuple[dict[str, float], Any]:
    """Mean loss (weighted by batch size) and ``metrics.compute()`` over ``loader``; prefixed ``val/``.

    Returns ``(scalars, image)`` where ``image`` is the visualiser's picture of the first batch (or None).
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
        with autocast_context(device, amp):
            out = model(batch["image"])
        out = {k: (v.float() if isinstance(v, torch.Tensor) and v.is_floating_point() else v) for k, v in out.items()}
        n = batch["image"].shape[0]
        if loss_fn is not None:
            loss, terms = loss_fn(out, batch)
            if torch.isfinite(loss):
                total += float(loss) * n
                count += n
                for k, v in terms.items():
                    terms_sum[k] = terms_sum.get(k, 0.0) + float(v) * n
        if metrics is not None:
            metrics.update(out, batch)
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


def train(cfg: DictConfig) -> dict[str, Any]:
    """Train the configured model; returns (and writes to ``<output_dir>/metrics.json``) the summary:
    ``{"monitor", "best", "best_step", "final": {...val metrics...}, "step", "epoch", "stopped_early",
    "wall_time_s", "output_dir", "checkpoint_best", "checkpoint_last"}``.
    """
    t0 = time.time()
    tc = cfg.trainer
    out_dir = Path(output_dir(cfg))
    seed_everything(int(tc.seed), int(tc.num_threads), bool(tc.deterministic))
    device = pick_device(str(tc.device), int(os.environ.get("LOCAL_RANK", 0)))
    dist = ddp.setup(device, str(tc.distributed_backend))
    main = dist.is_main
    if device.type == "cuda":
        torch.cuda.set_device(device)

    model = build_model(cfg).to(device)
    raw_model = model
    if dist.enabled:
        if device.type == "cuda":
            model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
            raw_model = model
        model = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None,
            find_unused_parameters=bool(tc.find_unused_parameters))
    loss_fn = build_loss(cfg)
    if loss_fn is None:
        raise ValueError("no loss configured: choose loss=<name> (configs/loss/) or a model config that sets it")
    if isinstance(loss_fn, torch.nn.Module):
        loss_fn = loss_fn.to(device)
    metrics = build_metrics(cfg)
    viz = build_viz(cfg) if main else None

    train_ds = SkipCorrupt(_maybe_rotating(_maybe_cached(build_dataset(cfg, "train"), cfg), float(tc.random_rotation_deg),
                                           int(tc.seed)))
    val_ds = build_dataset(cfg, "val", required=False)
    if val_ds is not None:
        val_ds = SkipCorrupt(_maybe_cached(val_ds, cfg))
    bs = int(tc.batch_size)
    sampler = _sampler(len(train_ds), int(tc.seed), dist)
    steps_per_epoch = len(sampler) // bs if len(sampler) >= bs else 1
    drop_last = len(sampler) >= bs
    if int(tc.max_steps) > 0:
        total_steps = int(tc.max_steps)
    else:
        total_steps = int(tc.max_epochs) * steps_per_epoch
    if total_steps <= 0:
        raise ValueError("nothing to train: set trainer.max_steps > 0 or trainer.max_epochs > 0")

    optimizer = build_optimizer(model.parameters(), cfg.optim)
    scheduler = build_scheduler(optimizer, cfg.sched, total_steps)
    use_scaler = bool(tc.amp) and device.type == "cuda"
    scaler = torch.amp.GradScaler("cuda", enabled=use_scaler) if use_scaler else None

    step, epoch, batch_in_epoch = 0, 0, 0
    best, best_step, bad_vals, last_val = None, -1, 0, {}
    ckpt_dir = out_dir / "checkpoints"
    resume_from = cfg.get("checkpoint")
    if not resume_from and bool(tc.resume) and (ckpt_dir / "last.pt").is_file():
        resume_from = str(ckpt_dir / "last.pt")
    if bool(tc.resume) and not resume_from and main:
        log.info("trainer.resume=true but %s does not exist yet: starting from scratch", ckpt_dir / "last.pt")
    if resume_from:
        ck = load_checkpoint(resume_from, map_location=device)
        load_model_weights(raw_model, ck, resume_from)
        if "optimizer" in ck:
            optimizer.load_state_dict(ck["optimizer"])
            scheduler.load_state_dict(ck["scheduler"])
            if scaler is not None and ck.get("scaler") is not None:
                scaler.load_state_dict(ck["scaler"])
            step, epoch, batch_in_epoch = int(ck["step"]), int(ck["epoch"]), int(ck["batch_in_epoch"])
            best, best_step, bad_vals = ck.get("best"), int(ck.get("best_step", -1)), int(ck.get("bad_validations", 0))
            last_val = ck.get("last_val", {})
            rng = ck.get("rng")
            if rng is not None:
                if isinstance(rng, list):
                    rng = rng[dist.rank] if dist.rank < len(rng) else rng[0]
                set_rng_state(rng)
        if main:
            log.info("resumed from %s at step %d (epoch %d, batch %d)", resume_from, step, epoch, batch_in_epoch)

    writer = None
    if main and bool(tc.tensorboard):
        from torch.utils.tensorboard import SummaryWriter
        writer = SummaryWriter(log_dir=str(out_dir / "tb"), purge_step=step if step > 0 else None)
    jlog = _JsonlLog(out_dir / "train_log.jsonl" if main else None)
    if main:
        out_dir.mkdir(parents=True, exist_ok=True)
        log.info("output dir: %s; %d training samples, %d steps (%d per epoch), device %s, world size %d",
                 out_dir, len(train_ds), total_steps, steps_per_epoch, device, dist.world_size)

    monitor, mode = str(tc.monitor), str(tc.monitor_mode)
    is_better(0.0, None, mode)  # validates the mode string
    val_loader = None
    if val_ds is not None:
        val_loader = DataLoader(val_ds, batch_size=bs, shuffle=False, num_workers=int(tc.num_workers),
                                collate_fn=collate_samples)
    image_every = int(tc.image_every_steps)
    last_image_step = -10**9

    def checkpoint_state() -> dict[str, Any]:
        rng = rng_state()
        if dist.enabled:  # every rank's RNG (dropout streams differ per rank)
            gathered = [None] * dist.world_size
            torch.distributed.all_gather_object(gathered, rng)
            rng = gathered
        return {"model": raw_model.state_dict(), "optimizer": optimizer.state_dict(),
                "scheduler": scheduler.state_dict(), "scaler": scaler.state_dict() if scaler else None,
                "rng": rng, "step": step, "epoch": epoch, "batch_in_epoch": batch_in_epoch, "best": best,
                "best_step": best_step, "bad_validations": bad_vals, "last_val": last_val,
                "config": OmegaConf.to_container(cfg, resolve=False)}

    def validate_and_checkpoint() -> bool:
        """Validate (rank 0), update best/early stopping, write checkpoints; True = stop training."""
        nonlocal best, best_step, bad_vals, last_val, last_image_step
        stop = False
        improved = False
        if main and val_loader is not None:
            result, image = run_validation(raw_model, val_loader, loss_fn, metrics, device, bool(tc.amp),
                                           int(tc.val_max_batches),
                                           viz if step - last_image_step >= image_every else None)
            last_val = result
            for k, v in result.items():
                if writer is not None:
                    writer.add_scalar(k, v, step)
            if image is not None:
                last_image_step = step
                if writer is not None:
                    writer.add_image("val/prediction_vs_truth", image.clamp(0, 1).cpu(), step)
            msg = ", ".join(f"{k}={v:.4g}" for k, v in result.items())
            log.info("step %d epoch %d validation: %s", step, epoch, msg)
            if monitor not in result:
                raise KeyError(f"trainer.monitor={monitor!r} is not among the validation results {sorted(result)}")
            value = float(result[monitor])
            if is_better(value, best, mode, float(tc.early_stopping.min_delta)):
                best, best_step, bad_vals, improved = value, step, 0, True
            else:
                bad_vals += 1
            patience = int(tc.early_stopping.patience)
            stop = patience > 0 and bad_vals >= patience
            if stop:
                log.info("early stopping: %s did not improve for %d validations (best %.4g at step %d)",
                         monitor, bad_vals, best, best_step)
        stop = bool(ddp.broadcast_object(stop))
        state = checkpoint_state()
        if main:
            save_checkpoint(ckpt_dir / "last.pt", state)
            if improved or (val_loader is None):
                save_checkpoint(ckpt_dir / "best.pt", state)
        ddp.barrier()
        return stop

    from tqdm.auto import tqdm
    bar = tqdm(total=total_steps, initial=step, desc="train", disable=not (main and bool(tc.progress)),
               dynamic_ncols=True)
    model.train()
    stop, skipped_in_row, stopped_early = step >= total_steps, 0, False
    running, running_n = 0.0, 0
    while not stop:
        sampler.set_epoch(epoch)
        sampler.set_start(batch_in_epoch * bs)
        if hasattr(train_ds, "set_epoch"):
            train_ds.set_epoch(epoch)
        gen = torch.Generator()
        gen.manual_seed(int(tc.seed) * 1000003 + epoch)  # the loader must not draw from the global RNG
        loader = DataLoader(train_ds, batch_size=bs, sampler=sampler, num_workers=int(tc.num_workers),
                            collate_fn=collate_samples, drop_last=drop_last, generator=gen,
                            pin_memory=device.type == "cuda")
        epoch_done = True
        for batch in loader:
            batch_in_epoch += 1
            bad = ["<all samples unreadable>"] if batch is None else nonfinite_keys(batch)
            if dist.enabled:  # every rank must skip together, or DDP's gradient all-reduce would hang
                if ddp.all_reduce_sum(torch.tensor([float(bool(bad))])).item() > 0 and not bad:
                    bad = ["<another rank's batch>"]
            if bad:
                if batch is not None:
                    _skip_or_raise(tc, f"non-finite values in {bad}", batch, skipped_in_row)
                skipped_in_row += 1
                continue
            batch = to_device(batch, device)
            with autocast_context(device, bool(tc.amp)):
                out = model(batch["image"])
            out = {k: (v.float() if isinstance(v, torch.Tensor) and v.is_floating_point() else v)
                   for k, v in out.items()}
            loss, terms = loss_fn(out, batch)
            finite = torch.isfinite(loss.detach())
            if dist.enabled:  # all ranks must agree to skip, or DDP would hang
                finite = ddp.all_reduce_sum(finite.float().reshape(1).cpu()).item() == dist.world_size
            else:
                finite = bool(finite)
            if not finite:
                optimizer.zero_grad(set_to_none=True)
                _skip_or_raise(tc, f"non-finite loss {float(loss)} (terms {terms})", batch, skipped_in_row)
                skipped_in_row += 1
                continue
            skipped_in_row = 0
            optimizer.zero_grad(set_to_none=True)
            if scaler is not None:
                scaler.scale(loss).backward()
                scaler.unscale_(optimizer)
            else:
                loss.backward()
            if float(tc.grad_clip) > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), float(tc.grad_clip))
            if scaler is not None:
                scaler.step(optimizer)
                scaler.update()
            else:
                optimizer.step()
            scheduler.step()
            step += 1
            lval = float(loss.detach())
            running += lval
            running_n += 1
            bar.update(1)
            if main and (step % max(1, int(tc.log_every_steps)) == 0 or step == total_steps):
                lr = optimizer.param_groups[0]["lr"]
                rec = {"step": step, "epoch": epoch, "loss": lval, "lr": lr,
                       **{f"loss_{k}": float(v) for k, v in terms.items()}}
                jlog.write(rec)
                if writer is not None:
                    writer.add_scalar("train/loss", lval, step)
                    writer.add_scalar("train/lr", lr, step)
                    for k, v in terms.items():
                        writer.add_scalar(f"train/loss_{k}", float(v), step)
                bar.set_postfix(loss=f"{running / running_n:.4g}", lr=f"{lr:.2e}")
                if not bool(tc.progress):  # no bar: a log line instead
                    log.info("step %d/%d epoch %d: loss %.4g, lr %.2e", step, total_steps, epoch,
                             running / running_n, lr)
                running, running_n = 0.0, 0
            vstep = int(tc.val_every_steps)
            if (vstep > 0 and step % vstep == 0) or step >= total_steps:
                stop = validate_and_checkpoint()
            elif int(tc.ckpt_every_steps) > 0 and step % int(tc.ckpt_every_steps) == 0:
                state = checkpoint_state()
                if main:
                    save_checkpoint(ckpt_dir / "last.pt", state)
            if stop or step >= total_steps:
                stopped_early = stop and step < total_steps
                stop = True
                epoch_done = batch_in_epoch >= steps_per_epoch
                break
        if epoch_done:
            epoch += 1
            batch_in_epoch = 0
            if not stop and int(tc.val_every_steps) <= 0:
                stop = validate_and_checkpoint()
                stopped_early = stop
    bar.close()
    if writer is not None:
        writer.flush()
        writer.close()
    summary = {"monitor": monitor, "best": best, "best_step": best_step, "final": last_val, "step": step,
               "epoch": epoch, "stopped_early": bool(stopped_early), "wall_time_s": time.time() - t0,
               "output_dir": str(out_dir), "checkpoint_best": str(ckpt_dir / "best.pt"),
               "checkpoint_last": str(ckpt_dir / "last.pt")}
    if main:
        atomic_write_json(out_dir / "metrics.json", summary)
        log.info("done: %d steps in %.1f s; best %s = %s (step %d); outputs in %s", step, summary["wall_time_s"],
                 monitor, best, best_step, out_dir)
    ddp.cleanup()
    return summary


def _sampler(length: int, seed: int, dist: ddp.DistInfo):
    from .sampler import ResumableDistributedSampler
    return ResumableDistributedSampler(length, shuffle=True, seed=seed, rank=dist.rank, world_size=dist.world_size)


def _skip_or_raise(tc, why: str, batch, skipped_in_row: int) -> None:
    files = batch_files(batch)
    if not bool(tc.skip_nonfinite):
        raise FloatingPointError(f"{why} in the batch of {files}; set trainer.skip_nonfinite=true to skip such batches")
    if skipped_in_row + 1 > int(tc.max_skipped):
        raise FloatingPointError(f"{skipped_in_row + 1} batches in a row skipped (last: {why} in {files}); "
                                 "lower the learning rate or check the data")
    log.warning("skipping a batch: %s (samples %s)", why, files)
