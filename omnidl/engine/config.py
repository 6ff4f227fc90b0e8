"""Structured-config schemas of the engine (Hydra ConfigStore).

The YAML files in ``configs/{optim,sched,trainer}/`` and the two entry configs start from these
schemas (``defaults: [schema, _self_]``), so a misspelt override such as
``trainer.max_stpes=3`` or ``optim.lr=fast`` fails at composition time with the key and the schema named.
Model, data, loss, metrics, camera and viz nodes stay free-form (each is a ``_target_`` node).

:func:`register_configs` must run before Hydra composes (``train.py``/``evaluate.py`` and the tests call it).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from hydra.core.config_store import ConfigStore


@dataclass
class OptimConfig:
    """Optimiser: ``adamw`` | ``adam`` | ``sgd``."""

    name: str = "adamw"
    lr: float = 1e-3
    weight_decay: float = 0.0
    momentum: float = 0.9              # sgd only
    betas: list[float] = field(default_factory=lambda: [0.9, 0.999])  # adam/adamw only


@dataclass
class SchedConfig:
    """Learning-rate schedule per optimiser step: ``cosine`` | ``step`` | ``none``, with linear warm-up."""

    name: str = "cosine"
    warmup_steps: int = 0
    min_lr_ratio: float = 0.01         # cosine: final lr = lr * min_lr_ratio
    step_size: int = 1000              # step: multiply by gamma every step_size steps
    gamma: float = 0.1


@dataclass
class EarlyStoppingConfig:
    """Stop when ``monitor`` has not improved for ``patience`` validations (0 disables)."""

    patience: int = 0
    min_delta: float = 0.0


@dataclass
class TrainerConfig:
    """The training loop. Steps are optimiser steps; ``max_steps`` wins over ``max_epochs`` when > 0."""

    max_epochs: int = 1
    max_steps: int = -1
    batch_size: int = 4
    num_workers: int = 0
    device: str = "auto"               # auto | cpu | cuda | cuda:1 ...
    amp: bool = False                  # autocast (bfloat16 on CPU, float16 + GradScaler on CUDA)
    grad_clip: float = 0.0             # max gradient norm (0: off)
    seed: int = 0
    num_threads: int = 0               # torch intra-op threads (0: leave torch's default)
    deterministic: bool = False        # torch.use_deterministic_algorithms
    log_every_steps: int = 10
    image_every_steps: int = 0         # TensorBoard image grids on validation (0: at every validation)
    val_every_steps: int = 0           # validate every N steps (0: at the end of every epoch)
    val_max_batches: int = -1          # -1: the whole validation set
    ckpt_every_steps: int = 0          # also write last.pt every N steps (0: only at validation/epoch end)
    monitor: str = "val/loss"          # metric for best.pt and early stopping
    monitor_mode: str = "min"          # min | max
    early_stopping: EarlyStoppingConfig = field(default_factory=EarlyStoppingConfig)
    resume: bool = False               # continue from <output_dir>/checkpoints/last.pt if present
    random_rotation_deg: float = 0.0   # train-time rotation about a random horizontal axis, U(-a, a) ("-r" variants)
    skip_nonfinite: bool = True        # skip (with a warning) batches with NaN/Inf inputs or loss
    max_skipped: int = 20              # ...but fail after this many consecutive skips
    progress: bool = True              # tqdm progress bar
    tensorboard: bool = True
    distributed_backend: str = "auto"  # auto: nccl on CUDA, gloo on CPU
    find_unused_parameters: bool = False


@dataclass
class PathsConfig:
    output_dir: str = "${hydra:runtime.output_dir}"


@dataclass
class EvalConfig:
    """``evaluate.py`` options."""

    split: str = "test"
    batch_size: int = 1
    max_images: Optional[int] = None
    save_images: int = 16
    save_pointclouds: int = 4
    rotation_deg: list[float] = field(default_factory=list)
    rotation_axis: str = "x"
    depth_max: Optional[float] = None


@dataclass
class TrainConfig:
    """Root schema of ``configs/train.yaml``."""

    task: str = "train"
    model: Any = None
    data: Any = None
    camera: Any = None
    loss: Any = None
    metrics: Any = None
    optim: OptimConfig = field(default_factory=OptimConfig)
    sched: SchedConfig = field(default_factory=SchedConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    viz: Any = None
    paths: PathsConfig = field(default_factory=PathsConfig)
    checkpoint: Optional[str] = None
    postprocess: Any = field(default_factory=list)   # hook names: [a, b] or a single name
    postprocess_options: Any = field(default_factory=dict)
    eval: EvalConfig = field(default_factory=EvalConfig)  # evaluate.py options (here too: experiments set both)
    search: Any = None                 # filled by +search=... (loss-weight search)
    # an experiment that trains with a search's loss weights: {name: <search>, result: <its best loss config,
    # loaded by an optional default when the search has written it>} (see configs/experiment/*-B*.yaml)
    loss_search: Any = None
    name: str = "run"                  # free label (experiments set it)
    notes: Any = None


@dataclass
class EvaluateConfig(TrainConfig):
    """Root schema of ``configs/evaluate.yaml``."""

    task: str = "evaluate"


_REGISTERED = False


def register_configs() -> None:
    """Put the schemas into Hydra's ConfigStore (idempotent)."""
    global _REGISTERED
    if _REGISTERED:
        return
    cs = ConfigStore.instance()
    cs.store(name="schema_train", node=TrainConfig)
    cs.store(name="schema_evaluate", node=EvaluateConfig)
    cs.store(group="optim", name="schema", node=OptimConfig)
    cs.store(group="sched", name="schema", node=SchedConfig)
    cs.store(group="trainer", name="schema", node=TrainerConfig)
    _REGISTERED = True


def missing_search_result(cfg) -> str | None:
    """The warning for a run whose experiment wants a search's loss weights (``loss_search``) that the search
    has not written yet (the experiment then falls back to the weights it names); None otherwise."""
    spec = cfg.get("loss_search")
    if not spec or spec.get("result") is not None:
        return None
    name = spec.get("name", "?")
    loss = cfg.get("loss") or {}
    return (f"the loss weights of the '{name}' search were not found (configs/loss/{name}_best.yaml does not exist): "
            f"training with the experiment's fallback weights loss.alpha_* = "
            f"{[loss.get(k) for k in ('alpha_semantic', 'alpha_depth', 'alpha_margin', 'alpha_object')]}. "
            f"Run python train.py +search={name} first to train with the searched weights.")
