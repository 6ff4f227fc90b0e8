"""Search-space specification for loss-weight searches, validated before any training starts.

A search config (``configs/search/*.yaml``) looks like::

    name: fredsnet_loss_weights
    trials: 20                 # completed trials wanted
    sobol_trials: 5            # quasi-random warm-up before Bayesian optimisation
    seed: 0
    objective:
      metrics: {delta1: 1.0, miou: 1.0}   # scalarisation: sum of weight * metric
      minimize: false
    parameters:                # dotted keys of the training config
      loss.alpha_semantic: {bounds: [0.1, 100.0], log: true}
      loss.alpha_depth: {bounds: [0.1, 100.0], log: true}
    fixed: {loss.alpha_margin: 0.001}   # set on every trial, not searched
    constraints: []            # Ax constraint strings over the parameter keys
    overrides: [trainer.max_steps=100] # applied to every trial's training config
"""
from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any


class SearchConfigError(ValueError):
    """A search config is malformed; the message names the offending key."""


@dataclass(frozen=True)
class Parameter:
    """One searched parameter: a dotted config key with bounds and scaling."""

    key: str
    low: float
    high: float
    log: bool = False
    integer: bool = False

    @property
    def ax_name(self) -> str:
        """Name used inside Ax (dots are not allowed in constraint expressions)."""
        return ax_name(self.key)


@dataclass
class SearchSpec:
    """A validated search specification (see module docstring)."""

    name: str
    parameters: list[Parameter]
    objective_metrics: dict[str, float]
    minimize: bool
    trials: int = 20
    sobol_trials: int = 5
    seed: int = 0
    fixed: dict[str, Any] = field(default_factory=dict)
    constraints: list[str] = field(default_factory=list)
    overrides: list[str] = field(default_factory=list)
    max_failures: int | None = None

    def scalarise(self, metrics: Mapping[str, float]) -> float:
        """The objective value: ``sum(weight * metrics[name])``; a missing or non-finite metric raises."""
        total = 0.0
        for name, w in self.objective_metrics.items():
            if name not in metrics:
                raise KeyError(f"objective metric {name!r} not among the trial's metrics {sorted(metrics)}")
            v = float(metrics[name])
            if not math.isfinite(v):
                raise ValueError(f"objective metric {name!r} is not finite ({v})")
            total += w * v
        return total

    def signature(self) -> dict[str, Any]:
        """What makes two runs the same search: the objective (metrics, weights, direction), the searched
        parameters, the fixed values, the constraints and the per-trial overrides. A search may only be
        resumed under the same signature (``trials``, ``sobol_trials`` and ``seed`` may change)."""
        return {"objective": {"metrics": {k: float(v) for k, v in sorted(self.objective_metrics.items())},
                              "minimize": bool(self.minimize)},
                "parameters": {p.key: {"bounds": [p.low, p.high], "log": p.log, "int": p.integer}
                               for p in self.parameters},
                "fixed": {str(k): v for k, v in sorted(self.fixed.items())},
                "constraints": list(self.constraints), "overrides": list(self.overrides)}

    def ax_constraints(self) -> list[str]:
        out = []
        for c in self.constraints:
            for p in sorted(self.parameters, key=lambda p: -len(p.key)):
                c = c.replace(p.key, p.ax_name)
            out.append(c)
        return out


def ax_name(key: str) -> str:
    return re.sub(r"[^0-9A-Za-z_]", "__", key)


def parse_search_spec(cfg: Mapping[str, Any], train_cfg: Any | None = None) -> SearchSpec:
    """Validate a search config mapping and return a :class:`SearchSpec`.

    If ``train_cfg`` (an OmegaConf config) is given, every parameter and fixed key must exist in it,
    so a typo fails here, before any training starts.
    """
    try:
        from omegaconf import DictConfig, OmegaConf
        if isinstance(cfg, DictConfig):
            cfg = OmegaConf.to_container(cfg, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    known = {"name", "trials", "sobol_trials", "seed", "objective", "parameters", "fixed", "constraints",
             "overrides", "max_failures", "dir", "restart", "config_dir", "resume_override", "keep_checkpoints"}
    unknown = sorted(set(cfg) - known)
    if unknown:
        raise SearchConfigError(f"search: unknown key(s) {unknown}; expected some of {sorted(known)}")
    params_cfg = cfg.get("parameters") or {}
    if not isinstance(params_cfg, Mapping) or not params_cfg:
        raise SearchConfigError("search.parameters: expected a non-empty mapping of config key -> {bounds: [lo, hi]}")
    params = []
    for key, spec in params_cfg.items():
        where = f"search.parameters.{key}"
        if not isinstance(spec, Mapping) or "bounds" not in spec:
            raise SearchConfigError(f"{where}: expected a mapping with 'bounds: [low, high]' (and optional log, int)")
        extra = sorted(set(spec) - {"bounds", "log", "int"})
        if extra:
            raise SearchConfigError(f"{where}: unknown field(s) {extra}; expected bounds, log, int")
        b = spec["bounds"]
        if not isinstance(b, Sequence) or len(b) != 2:
            raise SearchConfigError(f"{where}.bounds: expected [low, high], got {b!r}")
        lo, hi = float(b[0]), float(b[1])
        if not (math.isfinite(lo) and math.isfinite(hi)) or not lo < hi:
            raise SearchConfigError(f"{where}.bounds: empty or invalid range [{lo}, {hi}] (need low < high)")
        log = bool(spec.get("log", False))
        if log and lo <= 0:
            raise SearchConfigError(f"{where}.bounds: log scale needs a positive lower bound, got {lo}")
        params.append(Parameter(key=str(key), low=lo, high=hi, log=log, integer=bool(spec.get("int", False))))
    obj = cfg.get("objective") or {}
    if not isinstance(obj, Mapping):
        raise SearchConfigError(f"search.objective: expected a mapping with 'metrics' and 'minimize', got {obj!r}")
    extra = sorted(set(obj) - {"metrics", "minimize"})
    if extra:
        raise SearchConfigError(f"search.objective: unknown field(s) {extra}; expected metrics, minimize")
    metrics = obj.get("metrics")
    if isinstance(metrics, str):
        metrics = {metrics: 1.0}
    if not metrics or not isinstance(metrics, Mapping):
        raise SearchConfigError("search.objective.metrics: name at least one validation metric (or a mapping "
                                f"metric -> weight), got {metrics!r}")
    for k, w in metrics.items():
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w):
            raise SearchConfigError(f"search.objective.metrics.{k}: expected a finite number (the metric's weight), "
                                    f"got {w!r}")
    if not isinstance(obj.get("minimize", False), bool):
        raise SearchConfigError(f"search.objective.minimize: expected true or false, got {obj.get('minimize')!r}")
    spec = SearchSpec(
        name=str(cfg.get("name") or "search"), parameters=params,
        objective_metrics={str(k): float(v) for k, v in dict(metrics).items()},
        minimize=bool(obj.get("minimize", False)), trials=_int(cfg, "trials", 20),
        sobol_trials=_int(cfg, "sobol_trials", 5), seed=_int(cfg, "seed", 0),
        fixed=dict(cfg.get("fixed") or {}), constraints=list(cfg.get("constraints") or []),
        overrides=[str(o) for o in (cfg.get("overrides") or [])],
        max_failures=None if cfg.get("max_failures") is None else _int(cfg, "max_failures", 0))
    if spec.trials < 1:
        raise SearchConfigError(f"search.trials: must be >= 1, got {spec.trials}")
    if spec.sobol_trials < 0:
        raise SearchConfigError(f"search.sobol_trials: must be >= 0, got {spec.sobol_trials}")
    if spec.max_failures is not None and spec.max_failures < 1:
        raise SearchConfigError(f"search.max_failures: must be >= 1 (or null), got {spec.max_failures}")
    names = [p.key for p in params]
    for c in spec.constraints:
        if not any(n in c for n in names):
            raise SearchConfigError(f"search.constraints: {c!r} names no searched parameter ({names})")
    if train_cfg is not None:
        check_keys_exist(train_cfg, names + list(spec.fixed))
    return spec


def _int(cfg: Mapping[str, Any], key: str, default: int) -> int:
    v = cfg.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v != int(v):
        raise SearchConfigError(f"search.{key}: expected an integer, got {v!r}")
    return int(v)


def check_keys_exist(train_cfg: Any, keys: Sequence[str]) -> None:
    """Raise :class:`SearchConfigError` naming the first key missing from the training config."""
    from omegaconf import OmegaConf
    for key in keys:
        if OmegaConf.select(train_cfg, key, default="__missing__", throw_on_missing=False) == "__missing__":
            parent = key.rsplit(".", 1)[0] if "." in key else ""
            node = OmegaConf.select(train_cfg, parent) if parent else train_cfg
            hint = f"; keys under {parent!r}: {sorted(node.keys())}" if hasattr(node, "keys") else ""
            raise SearchConfigError(f"search parameter {key!r} does not exist in the training config{hint}")
