"""The protocol's stages on the engine: compose an experiment config, train it, evaluate a model.

Every stage is one Hydra experiment of ``configs/experiment/`` (``fisheye_pers``, ``fisheye_f165_std`` ...)
composed with the protocol's small-CPU overrides (:func:`compose_experiment`): the image size, the views
of the in-memory panorama banks (:mod:`omnidl.apps.fisheye.banks`), the model size, Adam with a cosine
schedule to 0 and the step budget. Training is :func:`omnidl.engine.train`; evaluation runs the engine's
validation loop (:func:`omnidl.engine.validation.run_validation`) with depth, segmentation, radial and
coverage metrics, whose per-bin tables the protocol writes.
"""
from __future__ import annotations

import copy
import json
import logging
import shutil
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from torch.utils.data import DataLoader

from omnidl.data.collate import collate_samples
from omnidl.engine import register_configs, train
from omnidl.engine.build import MetricCollection, build_model
from omnidl.engine.checkpoint import load_checkpoint, save_checkpoint
from omnidl.engine.config import config_root
from omnidl.engine.validation import run_validation
from omnidl.metrics.depth import DEPTH_METRICS, DepthMetrics
from omnidl.metrics.radial import RadialMetrics
from omnidl.metrics.segmentation import SegmentationMetrics

from .banks import bank_node
from .tables import SEG_KEYS

log = logging.getLogger("omnidl.apps.fisheye")
#: the Hydra config tree shipped in the package (omnidl/configs; importlib.resources)
CONFIG_DIR = config_root()


def compose_experiment(experiment: str, pcfg: DictConfig, overrides: list[str] = ()) -> DictConfig:
    """``train.yaml`` + ``model=<pcfg.experiments.model>`` + ``experiment=<experiment>`` with the protocol's
    overrides; the datasets view the held panorama banks (no validation split, as in the thesis protocol)."""
    from hydra import compose, initialize_config_dir
    register_configs()
    angles = dict(pcfg.get("orientation", {}))
    args = [f"model={pcfg.experiments.get('model', 'unet')}", f"experiment={experiment}",
            f"data.width={int(pcfg.image.width)}", f"data.height={int(pcfg.image.height)}",
            f"data.views_per_panorama={int(pcfg.get('views_per_panorama', 1))}",
            *(f"data.{k}={float(v)}" for k, v in angles.items()),
            f"trainer.device={pcfg.get('device', 'cpu')}", f"trainer.seed={int(pcfg.get('seed', 0))}",
            f"trainer.num_threads={int(pcfg.get('threads', 0))}", f"trainer.batch_size={int(pcfg.train.batch_size)}",
            "trainer.num_workers=0", "trainer.tensorboard=false", "trainer.log_every_steps=1",
            "trainer.val_every_steps=0", "optim.name=adam", "optim.weight_decay=0.0", "sched.name=cosine",
            "sched.warmup_steps=0", "sched.min_lr_ratio=0.0", *overrides]
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("train", overrides=args)
    with open_dict(cfg):
        cfg.model = OmegaConf.merge(cfg.model, pcfg.model)
        cfg.loss = OmegaConf.merge(cfg.loss, pcfg.loss)
        cfg.data.val = None
        for split in ("train", "test"):
            cfg.data[split].panoramas = bank_node(split)
            cfg.data[split].seed = int(pcfg.get("seed", 0))
    return cfg


def training_config(cfg: DictConfig, run_dir: Path, steps: int, lr: float, init: Path | None = None,
                    rectify_fov: float | None = None) -> DictConfig:
    """A copy of ``cfg`` that trains ``steps`` steps at ``lr`` into ``run_dir``, starting from the weights file
    ``init``; with ``rectify_fov`` the model is wrapped by :func:`~omnidl.apps.fisheye.rectified.rectified_model`."""
    cfg = copy.deepcopy(cfg)
    with open_dict(cfg):
        cfg.paths.output_dir = str(run_dir)
        cfg.trainer.max_steps = int(steps)
        cfg.optim.lr = float(lr)
        cfg.model.pretrained = str(init) if init is not None else None
        if rectify_fov is not None:
            cfg.model = rectified_node(cfg, rectify_fov)
    return cfg


def rectified_node(cfg: DictConfig, fov_deg: float) -> DictConfig:
    """The model node of ``cfg`` wrapped for the rectification baseline (§7.4.3)."""
    return OmegaConf.create({"_target_": "omnidl.apps.fisheye.rectified.rectified_model", "model": cfg.model,
                             "camera": cfg.camera, "width": cfg.data.width, "height": cfg.data.height,
                             "fov_deg": fov_deg})


def train_stage(name: str, cfg: DictConfig, ckdir: Path, fresh: bool) -> dict[str, torch.Tensor]:
    """Train ``cfg`` with :func:`omnidl.engine.train` unless ``ckdir/<name>.pt`` exists (and not ``fresh``);
    returns the final model state dict. The stage file holds ``model``, ``losses`` (per step) and ``seconds``."""
    path = ckdir / f"{name}.pt"
    if path.is_file() and not fresh:
        log.info("%s: loaded %s (delete it or pass --fresh to retrain)", name, path)
        return load_checkpoint(path)["model"]
    run_dir = Path(cfg.paths.output_dir)
    shutil.rmtree(run_dir, ignore_errors=True)  # a retrain starts a fresh engine run (and a fresh loss log)
    summary = train(cfg)
    state = load_checkpoint(summary["checkpoint_last"])["model"]
    log_file = run_dir / "train_log.jsonl"
    losses = [json.loads(line)["loss"] for line in log_file.read_text().splitlines()] if log_file.is_file() else []
    save_checkpoint(path, {"model": state, "losses": losses, "seconds": summary["wall_time_s"],
                           "run_dir": str(run_dir)})
    log.info("%s: %d steps in %.0f s, loss %s -> %s", name, summary["step"], summary["wall_time_s"],
             f"{losses[0]:.3f}" if losses else "-", f"{losses[-1]:.3f}" if losses else "-")
    return state


def model_with(cfg: DictConfig, state: dict[str, torch.Tensor] | None = None, rectify_fov: float | None = None
               ) -> torch.nn.Module:
    """The model of ``cfg`` (no ``pretrained`` file; with ``rectify_fov`` wrapped for the rectification
    baseline) with ``state`` loaded strictly."""
    cfg = copy.deepcopy(cfg)
    with open_dict(cfg):
        cfg.model.pretrained = None
        if rectify_fov is not None:
            cfg.model = rectified_node(cfg, rectify_fov)
    model = build_model(cfg)
    if state is not None:
        model.load_state_dict(state)
    return model


class CoveredFraction:
    """Fraction of the valid pixels that a rectified model covers (``outputs["rectified"] & batch["valid"]``);
    empty for models without a ``rectified`` output (engine metrics contract)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.covered, self.total = 0.0, 0.0

    def update(self, outputs: dict, batch: dict) -> None:
        if "rectified" in outputs:
            v = batch["valid"]
            self.covered += float((outputs["rectified"][:, 0] & v).sum())
            self.total += float(v.sum())

    def compute(self) -> dict[str, float]:
        return {"covered_fraction": self.covered / self.total} if self.total else {}


def evaluate_stage(model: torch.nn.Module, dataset, tasks, batch_size: int, device: torch.device,
                   edges: list[float] | None) -> tuple[dict[str, float], list[dict], dict[str, float]]:
    """``(scalars, radial rows, extra)`` of ``model`` on ``dataset`` through the engine's validation loop:
    depth metrics, segmentation scores (fractions in [0, 1], like every omnidl metric), the per-radius table
    and, for rectified models, the covered fraction."""
    parts: dict[str, Any] = {"coverage": CoveredFraction()}
    if "depth" in tasks:
        parts["depth"] = DepthMetrics()
    if "semantic" in tasks:
        parts["semantic"] = SegmentationMetrics(num_classes=14)
    if edges is not None:
        parts["radial"] = RadialMetrics(edges=edges, tasks=tasks)
    loader = DataLoader(dataset, batch_size=batch_size, shuffle=False, num_workers=0, collate_fn=collate_samples)
    run_validation(model.to(device), loader, None, MetricCollection(parts), device, amp=False)
    scalars: dict[str, float] = {}
    if "depth" in parts:
        scalars.update({k: v for k, v in parts["depth"].compute().items() if k in DEPTH_METRICS})
    if "semantic" in parts:
        scalars.update({k: v for k, v in parts["semantic"].compute().items() if k in SEG_KEYS})
    table = parts["radial"].table() if "radial" in parts else []
    return scalars, table, parts["coverage"].compute()
