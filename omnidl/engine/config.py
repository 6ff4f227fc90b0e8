"""Structured-config schemas of the engine (Hydra ConfigStore), where the config tree is, and what a
composed config may hold.

The Hydra config tree ships inside the package, ``omnidl/configs/`` (:func:`config_root`, read with
``importlib.resources``, so an installed wheel trains as a checkout does; the checkout's ``configs/`` is a link
to it). The YAML files in ``configs/{optim,sched,trainer}/`` and the two entry configs start from these
schemas (``defaults: [schema, _self_]``), so a misspelt override such as
``trainer.max_stpes=3`` or ``optim.lr=fast`` fails at composition time with the key and the schema named.
Model, data, loss, metrics, camera and viz nodes stay free-form (each is a ``_target_`` node), so
:func:`check_finite_config` refuses a ``nan``/``inf`` in any of their numbers where the config is read.

:func:`register_configs` must run before Hydra composes (``train.py``/``evaluate.py`` and the tests call it).
YAML is read by OmegaConf's loader only (a ``yaml.SafeLoader``: no ``!!python/...`` tags).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from datetime import datetime
from importlib import resources
from pathlib import Path
from typing import Any, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, ListConfig, OmegaConf


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
    # torch intra-op threads, decided once at the start of a run (omnidl.engine.seed.resolve_num_threads):
    # auto: torch's default count when every one of those threads has a free CPU, else as many as there are
    # free CPUs (at least 1), from the runnable tasks in /proc/loadavg; N > 0: N threads; 0: torch's default
    num_threads: Any = "auto"          # auto | 0 | N (Any: the schema takes both; check_num_threads validates)
    deterministic: bool = False        # torch.use_deterministic_algorithms
    # torch.compile(model) (Inductor, default mode) for the training step; checkpoints keep the plain model's
    # state dict, validation runs the plain model; the compile time (the first step's extra time) is logged
    compile: bool = False
    log_every_steps: int = 10
    image_every_steps: int = 0         # TensorBoard image grids on validation (0: at every validation)
    val_every_steps: int = 0           # validate every N steps (0: at the end of every epoch)
    val_every_minutes: float = 0.0     # ...and when this much wall time has passed since the last one (0: off)
    val_max_batches: int = -1          # -1: the whole validation set
    ckpt_every_steps: int = 0          # also write last.pt every N steps (0: only at validation/epoch end)
    ckpt_every_minutes: float = 0.0    # ...and when this much wall time has passed since the last write (0: off)
    save_optimizer: bool = False       # keep optimiser/RNG state in best.pt too (last.pt always has it)
    monitor: str = "val/loss"          # metric for best.pt and early stopping
    monitor_mode: str = "min"          # min | max
    early_stopping: EarlyStoppingConfig = field(default_factory=EarlyStoppingConfig)
    resume: bool = False               # continue from <output_dir>/checkpoints/last.pt (needs hydra.run.dir=<run>)
    overwrite: bool = False            # replace a previous run's results in the run folder (omnidl.engine.run_dir); evaluate: an earlier evaluation
    resume_override: bool = False      # resume although optim/sched/data/... settings differ from the checkpoint
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
    expected: Any = None               # expected final metrics of the default run (omnidl.engine.expected)
    notes: Any = None


@dataclass
class EvaluateConfig(TrainConfig):
    """Root schema of ``configs/evaluate.yaml``."""

    task: str = "evaluate"


def config_root() -> Path:
    """The folder of the Hydra config tree shipped with the package (``omnidl/configs``, holding ``train.yaml``,
    ``evaluate.yaml`` and the groups), found with ``importlib.resources`` so it is the installed package's in a
    wheel install and the checkout's in an editable one. Hydra composes from a directory on disk: a package
    imported from a zip file is refused with that said."""
    root = resources.files("omnidl").joinpath("configs")
    if not isinstance(root, Path) or not (root / "train.yaml").is_file():
        raise FileNotFoundError(f"omnidl's Hydra configs were not found at {root} (expected "
                                "omnidl/configs/train.yaml inside the installed package; Hydra needs them on disk, "
                                "not in a zip file): reinstall omnidl with pip install")
    return root


_REGISTERED = False
_RUN_STAMP: dict[str, str] = {}


def run_stamp(pattern: str = "%H-%M-%S") -> str:
    """``${run_stamp:%H-%M-%S}`` in a config: the process start time with ``pattern``, then milliseconds and
    the process id (``23-59-59.123_4567``), so two commands started in the same second never share a run dir.
    The same value for the whole process (every resolution of the run dir agrees)."""
    if pattern not in _RUN_STAMP:
        now = datetime.now()
        _RUN_STAMP[pattern] = f"{now.strftime(pattern)}.{now.microsecond // 1000:03d}_{os.getpid()}"
    return _RUN_STAMP[pattern]


def register_configs() -> None:
    """Put the schemas into Hydra's ConfigStore and register the ``run_stamp`` resolver (idempotent)."""
    global _REGISTERED
    if _REGISTERED:
        return
    if not OmegaConf.has_resolver("run_stamp"):
        OmegaConf.register_new_resolver("run_stamp", run_stamp)
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


def check_trainer_config(tc: Any, optim: Any = None) -> None:
    """Refuse trainer/optim values that would crash later with an unclear error (or train on garbage):
    ``ValueError`` naming the key, the value and what is expected."""
    def bad(key: str, value: Any, expected: str) -> ValueError:
        return ValueError(f"trainer.{key}={value!r}: expected {expected}")

    if int(tc.batch_size) < 1:
        raise bad("batch_size", tc.batch_size, "a positive number of samples per batch (e.g. 4)")
    if int(tc.max_steps) == 0 or int(tc.max_steps) < -1:
        raise bad("max_steps", tc.max_steps, "a positive number of optimiser steps, or -1 to train "
                  "trainer.max_epochs epochs")
    if int(tc.max_steps) == -1 and int(tc.max_epochs) < 1:
        raise bad("max_epochs", tc.max_epochs, "at least 1 (or set trainer.max_steps > 0)")
    for key in ("num_workers", "val_every_steps", "ckpt_every_steps", "max_skipped", "image_every_steps"):
        if int(tc[key]) < 0:
            raise bad(key, tc[key], "0 or more")
    if int(tc.log_every_steps) < 1:
        raise bad("log_every_steps", tc.log_every_steps, "1 or more")
    for key in ("grad_clip", "val_every_minutes", "ckpt_every_minutes", "random_rotation_deg"):
        v = float(tc[key])
        if not math.isfinite(v) or v < 0:
            raise bad(key, tc[key], "a finite number >= 0 (0: off)")
    if str(tc.monitor_mode) not in ("min", "max"):
        raise bad("monitor_mode", tc.monitor_mode, "'min' or 'max'")
    check_num_threads(tc.get("num_threads", "auto"))
    if not isinstance(tc.get("compile", False), bool):
        raise bad("compile", tc.compile, "true or false")
    if optim is not None:
        for key in ("lr", "weight_decay"):
            v = float(optim[key])
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"optim.{key}={optim[key]!r}: expected a finite number >= 0")


def check_num_threads(value: Any, key: str = "trainer.num_threads") -> int | str:
    """``value`` of ``trainer.num_threads`` as ``"auto"`` or an int >= 0 (a string of digits counts as that
    int); anything else is a ``ValueError`` naming ``key``, the value and what is expected."""
    if isinstance(value, str):
        v = value.strip()
        if v.lower() == "auto":
            return "auto"
        if v.isdigit():
            return int(v)
    elif isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        return int(value)
    raise ValueError(f"{key}={value!r}: expected 'auto' (pick from the machine's load), 0 (torch's default) "
                     "or a positive number of intra-op threads")


def _leaves(node: Any, prefix: str) -> list[tuple[str, Any]]:
    """``(dotted key, value)`` of every leaf of an omegaconf container; a value whose interpolation cannot be
    resolved here (``${hydra:...}`` outside a Hydra run, a ``???``) is left out: it is not a number yet."""
    out: list[tuple[str, Any]] = []
    keys = list(node.keys()) if isinstance(node, DictConfig) else list(range(len(node)))
    for key in keys:
        name = f"{prefix}{key}" if isinstance(node, DictConfig) else f"{prefix[:-1]}[{key}]"
        if OmegaConf.is_missing(node, key):
            continue
        try:
            value = node[key]
        except Exception:  # noqa: BLE001 (an interpolation that only Hydra's runtime or a later merge resolves)
            continue
        if isinstance(value, (DictConfig, ListConfig)):
            out += _leaves(value, f"{name}.")
        else:
            out.append((name, value))
    return out


def check_finite_config(cfg: Any, what: str = "config") -> None:
    """Refuse a composed config holding a non-finite number (``nan``, ``inf``, ``-inf``) in any field, e.g.
    ``loss.alpha_depth=nan`` (a NaN weight would train without that loss term, a NaN learning rate on garbage):
    ``ValueError`` naming every such key with its value. Interpolations count with their resolved value.

    Numbers are floats here (Hydra's override grammar and YAML read ``nan``/``.inf`` as floats); a *string*
    ``"nan"`` is not a number and is left to the field's own check. No shipped config holds a non-finite value:
    a bound that is "none" is ``null`` (or a documented sentinel such as ``-1``), never ``inf``.
    """
    if not isinstance(cfg, (DictConfig, ListConfig)):
        cfg = OmegaConf.create(cfg)
    bad = [(k, v) for k, v in _leaves(cfg, "") if isinstance(v, float) and not math.isfinite(v)]
    if bad:
        listed = ", ".join(f"{k}={v!r}" for k, v in bad)
        raise ValueError(f"{what}: non-finite value(s) {listed}: every number of a config must be finite (a NaN "
                         "or an infinite weight, rate or size would train or evaluate on garbage); give a finite "
                         "number, or null where the field accepts 'none'")
