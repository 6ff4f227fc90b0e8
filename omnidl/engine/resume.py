"""Resume checks: the settings a checkpoint was trained with, the run folder, and the command to continue.

* :func:`check_resume_settings`: resuming with other optimisation/data settings (``optim.lr``,
  ``trainer.batch_size`` ...) is an error listing every difference, unless ``trainer.resume_override=true``
  (then a warning, and :func:`apply_new_settings` makes the new values take effect).
* :func:`check_resume_dir`: ``trainer.resume=true`` in a fresh, auto-named run folder is an error naming the
  latest run that can be resumed (every command gets its own folder, so there is nothing to resume there).
* :func:`resume_command`: the exact command that continues this run (printed on Ctrl-C/SIGTERM).
"""
from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

#: config groups compared on resume (whole subtrees) and the ``trainer`` keys that change the optimisation
#: (``loss`` is not compared: a loss change on resume is how a schedule of loss weights is run)
CHECKED_GROUPS = ("model", "data", "camera", "optim", "sched")
CHECKED_TRAINER_KEYS = ("batch_size", "seed", "max_steps", "max_epochs", "grad_clip", "amp", "random_rotation_deg")
#: keys that may change on resume (where files live, caching, backbone initialisation that the weights replace)
IGNORED = {"data.root", "data.cache_dir", "data.cache_in_memory", "data.cache_keys", "model.pretrained"}


def _flat(node: Any, prefix: str) -> dict[str, Any]:
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for k, v in node.items():
            out.update(_flat(v, f"{prefix}.{k}"))
        return out or {prefix: {}}
    return {prefix: node}


def _settings(cfg: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for g in CHECKED_GROUPS:
        if cfg.get(g) is not None:
            out.update(_flat(cfg[g], g))
    trainer = cfg.get("trainer") or {}
    out.update({f"trainer.{k}": trainer.get(k) for k in CHECKED_TRAINER_KEYS if k in trainer})
    return {k: v for k, v in out.items() if not any(k == i or k.startswith(i + ".") for i in IGNORED)}


def resume_differences(saved: dict[str, Any], cfg: DictConfig) -> list[str]:
    """``"key: checkpoint X, now Y"`` for every compared setting that differs (unresolved config values)."""
    old = _settings(saved)
    new = _settings(OmegaConf.to_container(cfg, resolve=False))
    diffs = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k, "<unset>"), new.get(k, "<unset>")
        if a != b and not (isinstance(a, (int, float)) and isinstance(b, (int, float)) and float(a) == float(b)):
            diffs.append(f"{k}: checkpoint {a!r}, now {b!r}")
    return diffs


def check_resume_settings(ck: dict[str, Any], cfg: DictConfig, path: str | Path) -> list[str]:
    """Compare the checkpoint's saved config with ``cfg``; raise ``ValueError`` listing the differences unless
    ``trainer.resume_override``. Returns the differences (empty: an exact continuation)."""
    saved = ck.get("config")
    if not isinstance(saved, dict):
        return []
    diffs = resume_differences(saved, cfg)
    if diffs and not bool(cfg.trainer.get("resume_override", False)):
        raise ValueError(f"resuming from {path} with settings that differ from the ones it was trained with:\n  "
                         + "\n  ".join(diffs) + "\nUse the checkpoint's values, or add trainer.resume_override=true to "
                         "continue with the new ones (the run is then no longer an exact continuation).")
    return diffs


def apply_new_settings(optimizer, scheduler, cfg: DictConfig, step: int, total_steps: int) -> None:
    """After loading an optimiser/scheduler state under ``resume_override``: use the configured learning rate,
    weight decay and betas/momentum instead of the checkpoint's (the schedule continues at ``step``)."""
    from .optim import lr_factor
    oc = cfg.optim
    scheduler.base_lrs = [float(oc.lr)] * len(optimizer.param_groups)
    factor = lr_factor(step, total_steps, cfg.sched)
    for g in optimizer.param_groups:
        g["initial_lr"] = float(oc.lr)
        g["lr"] = float(oc.lr) * factor
        g["weight_decay"] = float(oc.weight_decay)
        if "betas" in g:
            g["betas"] = tuple(float(b) for b in oc.betas)
        if "momentum" in g:
            g["momentum"] = float(oc.momentum)


def _hydra_overrides() -> tuple[list[str], list[str]] | None:
    """``(task overrides, hydra overrides)`` of the current ``@hydra.main`` run, or None outside one."""
    try:
        from hydra.core.hydra_config import HydraConfig
        if not HydraConfig.initialized():
            return None
        hc = HydraConfig.get()
        return list(hc.overrides.task), list(hc.overrides.hydra)
    except Exception:  # pragma: no cover - other Hydra versions
        return None


def _sets(overrides: list[str], key: str) -> bool:
    return any(o.lstrip("+~").startswith(f"{key}=") for o in overrides)


def check_resume_dir(cfg: DictConfig, last: Path) -> None:
    """``trainer.resume=true`` without ``checkpoint=`` in an auto-named (new) run folder: a ``ValueError`` that
    says which ``hydra.run.dir=`` to add (the latest run with a ``last.pt`` next to this one, if any)."""
    if not bool(cfg.trainer.resume) or cfg.get("checkpoint") or last.is_file():
        return
    ov = _hydra_overrides()
    chosen = any(_sets(ov[1], k) for k in ("hydra.run.dir", "hydra.sweep.dir")) if ov else True
    if chosen or _sets(ov[0], "paths.output_dir"):
        return  # the user chose the folder: an empty one just starts from scratch (logged by the Checkpointer)
    run_dir = last.parent.parent
    candidates = [p for p in run_dir.parent.parent.glob("*/*/checkpoints/last.pt") if p.parent.parent != run_dir]
    hint = ""
    if candidates:
        latest = max(candidates, key=lambda p: p.stat().st_mtime).parent.parent
        hint = f" The latest run with a last.pt is {latest}: add hydra.run.dir={latest}"
    raise ValueError("trainer.resume=true needs the folder of the run to continue, but this command got a new "
                     f"run folder ({run_dir}) with no checkpoints/last.pt: add hydra.run.dir=<that run's folder> "
                     f"(or checkpoint=<path>/last.pt).{hint}")


def resume_command(cfg: DictConfig, out_dir: Path) -> str:
    """The command that continues this run from its ``last.pt``: the same overrides plus
    ``hydra.run.dir=<out_dir> trainer.resume=true`` (without ``checkpoint=``, which would win over last.pt)."""
    ov = _hydra_overrides()
    script = Path(sys.argv[0]).name if sys.argv and sys.argv[0].endswith(".py") else "train.py"
    program = "omnidl train" if sys.argv and sys.argv[0] == "omnidl train" else f"python {script}"
    try:
        shown = Path(out_dir).resolve().relative_to(Path.cwd())
    except ValueError:
        shown = Path(out_dir)
    if ov is None:
        return f"{program} <the same overrides> paths.output_dir={shlex.quote(str(out_dir))} trainer.resume=true"
    keep = [o for o in ov[0] if not any(o.lstrip("+~").startswith(k + "=") for k in ("trainer.resume", "checkpoint"))]
    if not _sets(ov[0], "paths.output_dir"):
        keep.append(f"hydra.run.dir={shown}")
    keep.append("trainer.resume=true")
    return " ".join([program, *(shlex.quote(o) for o in keep)])
