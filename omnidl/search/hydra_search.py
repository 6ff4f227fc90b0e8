"""Loss-weight search from the training app: ``python train.py +search=fredsnet_loss_weights search.trials=20``.

Each trial is a short training run whose config is composed with Hydra's compose API from the same
command line (minus the ``search`` options) plus the search's ``overrides`` and the trial's parameters,
and trained in-process with :func:`omnidl.engine.train`. The search lives in ``search.dir``
(default ``outputs/search/<name>``): running the same command again resumes it (``search.restart=true``
starts over). At the end it writes

* ``configs/loss/<name>_best.yaml`` — the loss config with the best weights, ready for
  ``python train.py loss=<name>_best`` (also copied into the search folder);
* ``trials.csv`` / ``trials.md`` — every trial with its parameters, status and objective;
* ``objective.png`` — the objective per trial and the best so far.

Each trial folder (``trial_NNN``) keeps its ``metrics.json`` and logs; ``search.keep_checkpoints`` says which
weights stay (default ``best_trial``: a weights-only ``best.pt`` of the best trial; see
:mod:`omnidl.search.trial_files`). Resuming with another objective, parameter range, fixed value or per-trial
override is an error (``search.resume_override=true`` resumes anyway; ``search.restart=true`` starts over).

Output policy (:mod:`omnidl.utils.outputs`): the search folder is locked while the search runs (a second search
in it stops with a message naming the first); a trial folder is cleared before its trial trains (it can only
hold an interrupted attempt of that trial, or a trial of the search that ``search.restart=true`` replaces);
``configs/loss/<name>_best.yaml`` is written only when new or written by a search before (checked before the
first trial), never over a hand-written loss config.
"""
from __future__ import annotations

import copy
import csv
import io
import logging
import math
from pathlib import Path
from typing import Any, Callable

from omegaconf import DictConfig, OmegaConf, open_dict

from omnidl.engine.run_dir import clear_train_results
from omnidl.utils.io import atomic_write, atomic_write_text
from omnidl.utils.outputs import OutputExistsError, RunLock, RunLockedError

from .driver import SearchResult, TrialRecord, run_search
from .space import SearchConfigError, SearchSpec, parse_search_spec
from .trial_files import check_keep, drop_other_bests, prune_trial

log = logging.getLogger(__name__)


def training_config_without_search(cfg: DictConfig) -> DictConfig:
    """A copy of ``cfg`` without the ``search`` node."""
    c = copy.deepcopy(cfg)
    with open_dict(c):
        c.pop("search", None)
    return c


def _format(v: Any) -> str:
    if isinstance(v, float):
        return repr(v)
    return str(v)


def _task_overrides() -> tuple[str | None, list[str]]:
    """The running Hydra app's config name and command-line overrides, minus the search ones."""
    try:
        from hydra.core.hydra_config import HydraConfig
        hc = HydraConfig.get()
    except Exception:
        return None, []
    keep = [o for o in hc.overrides.task
            if not o.lstrip("+~").startswith("search") and not o.startswith("hydra.")]
    # the group choices of this run (including those the search config itself selected, e.g. its model),
    # so that composing without the search still gives the same model/data/loss
    explicit = {o.lstrip("+~").split("=", 1)[0] for o in keep}
    choices = [f"{g}={c}" for g, c in hc.runtime.choices.items()
               if c is not None and "/" not in g and not g.startswith("hydra") and g != "search"
               and g not in explicit]
    return hc.job.config_name, choices + keep


def trial_dir(search_dir: Path, idx: int) -> Path:
    """The output folder of trial ``idx``."""
    return Path(search_dir) / f"trial_{idx:03d}"


def make_trial_config_fn(base: DictConfig, spec: SearchSpec, search_dir: Path) -> Callable[[dict, int], DictConfig]:
    """Return ``fn(params, idx) -> DictConfig`` building one trial's training config from ``base`` (the
    training config without its ``search`` node), through Hydra's compose API inside a Hydra app."""
    config_name, task = _task_overrides()

    def trial_overrides(params: dict, idx: int) -> list[str]:
        out = list(spec.overrides) + [f"{k}={_format(v)}" for k, v in params.items()]
        out.append(f"paths.output_dir={trial_dir(search_dir, idx).as_posix()}")
        return out

    def compose_fn(params: dict, idx: int) -> DictConfig:
        from hydra import compose
        from hydra.core.global_hydra import GlobalHydra
        if config_name and GlobalHydra.instance().is_initialized():
            c = compose(config_name=config_name, overrides=task + trial_overrides(params, idx))
            return training_config_without_search(c)
        # outside a Hydra app (library use, tests): apply the overrides to a copy
        c = copy.deepcopy(base)
        with open_dict(c):
            for o in trial_overrides(params, idx):
                key, val = o.split("=", 1)
                OmegaConf.update(c, key.lstrip("+"), _parse(val),
                                 force_add=True)
        return c

    return compose_fn


def _parse(val: str) -> Any:
    import yaml
    try:
        return yaml.safe_load(val)
    except Exception:
        return val


def trial_metrics(summary: dict) -> dict[str, float]:
    """Metrics of one training run for the objective: the final validation metrics (``summary["final"]``,
    e.g. ``val/delta1``), ``best`` (the monitored value) and any other top-level numbers."""
    out: dict[str, float] = {}
    for k, v in summary.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            out[k] = float(v)
    for k, v in (summary.get("final") or {}).items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            out[k] = float(v)
    return out


def run_search_from_config(cfg: DictConfig, train_fn: Callable[[DictConfig], dict] | None = None) -> SearchResult:
    """Entry point used by ``train.py`` when the config has a ``search`` node."""
    train_cfg = training_config_without_search(cfg)
    spec = parse_search_spec(cfg.search, train_cfg)  # fails here, before any training, on a bad key/range
    search_dir = Path(cfg.search.get("dir") or f"outputs/search/{spec.name}")
    restart = bool(cfg.search.get("restart", False))
    resume_override = bool(cfg.search.get("resume_override", False))
    try:
        keep = check_keep(cfg.search.get("keep_checkpoints", "best_trial"))
    except ValueError as exc:
        raise SearchConfigError(str(exc)) from None
    if train_fn is None:
        from omnidl.engine import train as train_fn  # type: ignore[no-redef]
    build = make_trial_config_fn(train_cfg, spec, search_dir)
    best_so_far: dict[str, Any] = {}
    if keep == "best_trial" and not restart:  # a resumed search: the best of the trials already done
        from .driver import load_records
        done = [r for r in load_records(search_dir / "experiment.json")
                if r.get("status") == "COMPLETED" and r.get("objective") is not None]
        if done:
            b = (min if spec.minimize else max)(done, key=lambda r: r["objective"])
            best_so_far.update(value=b["objective"], index=b["index"])

    def evaluate(params: dict, idx: int) -> dict:
        trial_cfg = build(params, idx)
        log.info("search %s: trial %d with %s", spec.name, idx, params)
        # a trial folder holding files is left by an interrupted attempt of this trial index or by the search that
        # search.restart=true replaces: it belongs to this search (whose folder is locked), so it is cleared
        clear_train_results(trial_dir(search_dir, idx), f"search {spec.name}: trial {idx} starts again")
        try:
            return trial_metrics(train_fn(trial_cfg))
        finally:
            prune_trial(trial_dir(search_dir, idx), keep)

    def on_end(rec: TrialRecord) -> None:
        if keep == "best_trial" and rec.status == "COMPLETED":
            old = best_so_far.get("value")
            if old is None or (rec.objective < old if spec.minimize else rec.objective > old):
                best_so_far.update(value=rec.objective, index=rec.index)
            drop_other_bests(search_dir, trial_dir(search_dir, best_so_far["index"]))
        write_reports(spec, None, search_dir, extra=rec)

    best_dir = Path(cfg.search.get("config_dir") or config_dir())
    check_best_config_path(best_dir / "loss" / f"{spec.name}_best.yaml")  # before any trial, not after the search
    try:
        lock = RunLock(search_dir, "search").acquire()
    except RunLockedError as exc:
        raise SearchConfigError(str(exc)) from None
    try:
        result = run_search(spec, evaluate, search_dir / "experiment.json", restart=restart, on_trial_end=on_end,
                            resume_override=resume_override)
        if keep == "best_trial":
            drop_other_bests(search_dir, trial_dir(search_dir, result.best_trial))
        write_reports(spec, result, search_dir)
        best_cfg = build(result.best_params, result.best_trial)  # the best trial's own config (with search overrides)
        best_path = write_best_loss_config(spec, result, best_cfg, search_dir, best_dir)
    finally:
        lock.release()
    print(f"search {spec.name}: best objective {result.best_objective:.5g} at trial {result.best_trial} "
          f"with {result.best_params}\n  best loss config: {best_path}\n  trials: {search_dir / 'trials.md'}")
    return result


def config_dir() -> Path:
    """The primary config folder of the running Hydra app (the package's ``omnidl/configs``)."""
    try:
        from hydra.core.hydra_config import HydraConfig
        for src in HydraConfig.get().runtime.config_sources:
            if src.provider == "main" and src.schema == "file":
                return Path(src.path)
    except Exception:
        pass
    from omnidl.engine.config import config_root
    return config_root()


#: the first line of every ``<name>_best.yaml`` a search writes (:func:`write_best_loss_config`)
BEST_HEADER = "# Best loss weights found by the "


def check_best_config_path(path: Path) -> None:
    """``configs/loss/<name>_best.yaml`` may be (re)written only if it is new or was written by a search: a
    hand-written loss config of that name is never replaced (:class:`~omnidl.utils.outputs.OutputExistsError`)."""
    if path.is_dir():
        raise OutputExistsError(f"{path} is a folder; the search writes its best loss config to that file name")
    if not path.exists():
        return
    try:
        first = path.read_text(encoding="utf-8", errors="replace").splitlines()[:1]
    except OSError as exc:
        raise OutputExistsError(f"{path} exists and cannot be read ({exc}); the search would replace it") from exc
    if not first or not first[0].startswith(BEST_HEADER):
        raise OutputExistsError(f"{path} exists and was not written by a search (its first line is not "
                                f"{BEST_HEADER!r}...): it is never replaced. Rename it, or give the search another "
                                "name or search.config_dir")


def write_best_loss_config(spec: SearchSpec, result: SearchResult, train_cfg: DictConfig, search_dir: Path,
                           configs: Path) -> Path:
    """Write the best trial's loss config (``train_cfg.loss`` updated with the best ``loss.*`` values) as
    ``configs/loss/<name>_best.yaml``."""
    loss = copy.deepcopy(train_cfg.get("loss"))
    if loss is None:
        raise ValueError("search: the training config has no 'loss' node to write the best weights into")
    with open_dict(loss):
        for key, val in result.best_params.items():
            if key.startswith("loss."):
                OmegaConf.update(loss, key[len("loss."):], val, force_add=True)
    objective = " ".join(f"{'+' if w >= 0 else '-'} {abs(w):g}*{m}" for m, w in spec.objective_metrics.items())
    check_best_config_path(configs / "loss" / f"{spec.name}_best.yaml")
    header = (f"{BEST_HEADER}'{spec.name}' search (trial {result.best_trial}, objective "
              f"{result.best_objective:.6g}). Use: python train.py loss={spec.name}_best\n"
              f"# objective ({'minimised' if spec.minimize else 'maximised'}, metrics as fractions): "
              f"{objective.lstrip('+ ')}\n")
    text = header + OmegaConf.to_yaml(loss, resolve=True)
    atomic_write_text(search_dir / f"{spec.name}_best.yaml", text)
    path = configs / "loss" / f"{spec.name}_best.yaml"
    atomic_write_text(path, text)
    return path


def write_reports(spec: SearchSpec, result: SearchResult | None, search_dir: Path,
                  extra: TrialRecord | None = None) -> None:
    """``trials.csv``, ``trials.md`` and ``objective.png`` in ``search_dir`` (atomic)."""
    from .driver import load_records
    records = load_records(search_dir / "experiment.json")
    if not records:
        return
    keys = [p.key for p in spec.parameters]
    metric_names = sorted({m for r in records for m in (r.get("metrics") or {})})
    header = ["trial", "status", "objective"] + keys + metric_names
    rows = []
    for r in records:
        obj = r.get("objective")
        rows.append([r["index"], r["status"], "" if obj is None else f"{obj:.6g}"]
                    + [f"{r['params'].get(k, float('nan')):.6g}" for k in keys]
                    + [f"{(r.get('metrics') or {}).get(m, float('nan')):.6g}" for m in metric_names])
    buf = io.StringIO()
    csv.writer(buf).writerows([header] + rows)
    atomic_write_text(search_dir / "trials.csv", buf.getvalue())
    md = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    md += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    atomic_write_text(search_dir / "trials.md", "\n".join(md) + "\n")
    plot_objective(records, spec.minimize, search_dir / "objective.png", title=spec.name)


def plot_objective(records: list[dict], minimize: bool, path: Path, title: str = "") -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    done = [(r["index"], r["objective"]) for r in records if r["status"] == "COMPLETED" and r.get("objective") is not None]
    if not done:
        return
    idx, val = zip(*done)
    best, cur = [], math.inf if minimize else -math.inf
    for v in val:
        cur = min(cur, v) if minimize else max(cur, v)
        best.append(cur)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(idx, val, "o", label="trial")
    ax.plot(idx, best, "-", label="best so far")
    ax.set_xlabel("trial")
    ax.set_ylabel("objective (" + ("min" if minimize else "max") + ")")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=100))
    plt.close(fig)
