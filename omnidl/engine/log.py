"""Training logs (rank 0 only): TensorBoard scalars and images under ``tb/``, ``train_log.jsonl``, the progress bar.

``train_log.jsonl`` holds one JSON record per logged step: ``{"step", "epoch", "loss", "lr", "loss_<term>"...}``;
a resumed run first drops the records after the step it resumes from, then appends. TensorBoard gets ``train/loss``, ``train/lr``,
``train/loss_<term>``, every validation scalar (``val/...``) and the ``val/prediction_vs_truth`` image.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import torch

from omnidl.utils.io import atomic_write_text

log = logging.getLogger("omnidl.engine")


class JsonlLog:
    """Append-only JSON-lines log of training scalars; ``path=None`` writes nothing (non-zero ranks)."""

    def __init__(self, path: Path | None):
        self.path = path

    def truncate(self, step: int) -> int:
        """Drop the records after ``step`` (a resumed run redoes those steps); returns how many were dropped.
        Unreadable lines (a kill mid-line) are dropped too."""
        if self.path is None or not self.path.is_file():
            return 0
        keep, dropped = [], 0
        for line in self.path.read_text().splitlines():
            try:
                ok = int(json.loads(line)["step"]) <= step
            except (ValueError, KeyError, TypeError):
                ok = False
            if ok:
                keep.append(line)
            else:
                dropped += 1
        if dropped:
            atomic_write_text(self.path, "".join(x + "\n" for x in keep))
        return dropped

    def write(self, record: dict[str, Any]) -> None:
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")


class TrainLogger:
    """All logging of one run.

    ``main``: rank 0 (the others log nothing); ``start_step``: the step a resumed run starts at (TensorBoard
    purges later events, the bar starts there); ``log_every``: steps between records (the running mean of
    the loss is shown); ``progress``: a tqdm bar, else a log line per record.
    """

    def __init__(self, out_dir: Path, main: bool, tensorboard: bool, progress: bool, log_every: int,
                 start_step: int, total_steps: int):
        self.main = main
        self.progress = progress
        self.log_every = max(1, log_every)
        self.total_steps = total_steps
        self.writer = None
        if main and tensorboard:
            from torch.utils.tensorboard import SummaryWriter
            self.writer = SummaryWriter(log_dir=str(out_dir / "tb"), purge_step=start_step if start_step > 0 else None)
        self.jsonl = JsonlLog(out_dir / "train_log.jsonl" if main else None)
        if dropped := self.jsonl.truncate(start_step):
            log.info("train_log.jsonl: dropped %d records after step %d (the resumed run redoes them)", dropped,
                     start_step)
        self.start_step = start_step
        self.bar = None
        self._running, self._running_n = 0.0, 0

    def start(self) -> None:
        """Open the progress bar (disabled off rank 0 or with ``progress=False``)."""
        from tqdm.auto import tqdm
        self.bar = tqdm(total=self.total_steps, initial=self.start_step, desc="train",
                        disable=not (self.main and self.progress), dynamic_ncols=True)

    def train_step(self, step: int, epoch: int, loss: float, terms: dict[str, Any], lr: float) -> None:
        """Account one optimiser step; every ``log_every`` steps (and at the last) write a record."""
        self._running += loss
        self._running_n += 1
        self.bar.update(1)
        if not self.main or not (step % self.log_every == 0 or step == self.total_steps):
            return
        self.jsonl.write({"step": step, "epoch": epoch, "loss": loss, "lr": lr,
                          **{f"loss_{k}": float(v) for k, v in terms.items()}})
        if self.writer is not None:
            self.writer.add_scalar("train/loss", loss, step)
            self.writer.add_scalar("train/lr", lr, step)
            for k, v in terms.items():
                self.writer.add_scalar(f"train/loss_{k}", float(v), step)
        mean = self._running / self._running_n
        self.bar.set_postfix(loss=f"{mean:.4g}", lr=f"{lr:.2e}")
        if not self.progress:  # no bar: a log line instead
            log.info("step %d/%d epoch %d: loss %.4g, lr %.2e", step, self.total_steps, epoch, mean, lr)
        self._running, self._running_n = 0.0, 0

    def validation(self, step: int, epoch: int, result: dict[str, float], image: torch.Tensor | None) -> None:
        """Validation scalars (and the first batch's picture ``(3, h, w)`` in [0, 1], when given)."""
        if self.writer is not None:
            for k, v in result.items():
                self.writer.add_scalar(k, v, step)
            if image is not None:
                self.writer.add_image("val/prediction_vs_truth", image.clamp(0, 1).cpu(), step)
        msg = ", ".join(f"{k}={v:.4g}" for k, v in result.items())
        log.info("step %d epoch %d validation: %s", step, epoch, msg)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        if self.writer is not None:
            self.writer.flush()
            self.writer.close()
