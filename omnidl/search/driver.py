"""The Ax ask/tell loop: Sobol warm-up then Bayesian optimisation, saved after every trial, resumable.

``run_search(spec, evaluate, state_path)`` drives ``ax.Client`` (ax-platform 1.x; the hydra-ax-sweeper
plugin does not work with it). ``evaluate(params, trial_index) -> dict[str, float]`` runs one trial
(a short training run) and returns its metrics; the driver scalarises them with the spec.

Crash safety:
* the experiment is written atomically to ``state_path`` (JSON) after every state change, including
  right after a trial is suggested (so a crash leaves it RUNNING);
* on resume, a trial found RUNNING is marked failed and its parameters are attached again as a new
  trial, which runs first — the search resumes *at* the interrupted trial;
* a resume must be the same search: the spec's :meth:`~SearchSpec.signature` (objective, parameters, fixed
  values, constraints, overrides) is saved beside the state (``<stem>_spec.json``) and compared, and the Ax
  experiment's direction is checked; an unreadable state file is a :class:`SearchStateError` naming it;
* an exception raised by ``evaluate`` marks that trial failed (reason recorded) and the search goes on;
  ``KeyboardInterrupt``/``SystemExit`` propagate (that is a crash, not a failed trial).
"""
from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omnidl.utils.io import atomic_write, atomic_write_json

from .space import SearchSpec

log = logging.getLogger(__name__)

OBJECTIVE = "objective"


class SearchStateError(ValueError):
    """A saved search cannot be resumed: its state file is unreadable, or the search config changed."""


_RESTART_HINT = "run with search.restart=true to start the search over (or set another search.dir)"


@dataclass
class TrialRecord:
    index: int
    params: dict[str, float]
    status: str
    objective: float | None = None
    metrics: dict[str, float] = field(default_factory=dict)
    reason: str = ""


@dataclass
class SearchResult:
    best_params: dict[str, float]
    best_objective: float
    best_trial: int
    trials: list[TrialRecord]

    @property
    def completed(self) -> list[TrialRecord]:
        return [t for t in self.trials if t.status == "COMPLETED"]


def _quiet_ax() -> None:
    try:
        from ax.utils.common.logger import set_ax_logger_levels
        set_ax_logger_levels(logging.WARNING)
    except Exception:  # pragma: no cover - best effort
        pass
    for name in ("ax", "botorch", "gpytorch", "linear_operator"):
        logging.getLogger(name).setLevel(logging.WARNING)


def _save(client, path: Path) -> None:
    """Write the Ax experiment to ``path`` atomically."""
    atomic_write(path, client.save_to_json_file)


def _new_client(spec: SearchSpec):
    from ax import Client, RangeParameterConfig

    client = Client(random_seed=spec.seed)
    params = [RangeParameterConfig(name=p.ax_name, bounds=(p.low, p.high),
                                   parameter_type="int" if p.integer else "float",
                                   scaling="log" if p.log else "linear") for p in spec.parameters]
    client.configure_experiment(parameters=params, parameter_constraints=spec.ax_constraints() or None,
                                name=spec.name)
    client.configure_optimization(objective=("-" if spec.minimize else "") + OBJECTIVE)
    client.configure_generation_strategy(initialization_budget=max(1, spec.sobol_trials),
                                         initialization_random_seed=spec.seed)
    return client


def _trials(client) -> dict:
    return client._experiment.trials  # Ax 1.x keeps them here; the public API has no listing


def _status(trial) -> str:
    return trial.status.name


def _params_of(trial) -> dict[str, float]:
    return dict(trial.arm.parameters)


def _to_keys(spec: SearchSpec, ax_params: Mapping[str, Any]) -> dict[str, float]:
    return {p.key: ax_params[p.ax_name] for p in spec.parameters}


def run_search(spec: SearchSpec, evaluate: Callable[[dict[str, float], int], Mapping[str, float]],
               state_path: str | os.PathLike, restart: bool = False, progress: bool = True,
               on_trial_end: Callable[[TrialRecord], None] | None = None,
               resume_override: bool = False) -> SearchResult:
    """Run (or resume) a search until ``spec.trials`` trials have completed.

    Args:
        spec: validated search specification.
        evaluate: ``evaluate(params, trial_index) -> metrics``; ``params`` maps dotted config keys
            (and ``spec.fixed``) to values.
        state_path: JSON file holding the Ax experiment; resumed from if it exists (unless ``restart``).
        on_trial_end: called with each finished (completed or failed) trial record.
        resume_override: resume even if the search config (objective, parameters, fixed values,
            constraints, per-trial overrides) differs from the saved one (a warning instead of an error).

    Raises:
        SearchStateError: the state file (or its side files) cannot be read, or the saved search was run
            with another objective / parameters (unless ``resume_override``).
    """
    _quiet_ax()
    state_path = Path(state_path)
    records: dict[int, TrialRecord] = {}
    pending: list[dict[str, float]] = []
    resuming = state_path.exists() and not restart
    if resuming:
        check_same_search(spec, state_path, resume_override)
        client = _load_client(state_path)
        client._random_seed = spec.seed  # not restored by load_from_json_file
        _check_direction(client, spec, state_path, resume_override)
        for idx, trial in sorted(_trials(client).items()):
            if _status(trial) == "RUNNING":
                log.warning("search: trial %d was running when the last process stopped; marking it failed and "
                            "running its parameters again", idx)
                client.mark_trial_failed(idx, failed_reason="interrupted (process stopped while running)")
                pending.append(_params_of(trial))
        _save(client, state_path)
    else:
        client = _new_client(spec)
        _save(client, state_path)
    atomic_write_json(_spec_path(state_path), spec.signature())
    _load_records(client, spec, records, state_path, use_saved=resuming)

    def n_completed() -> int:
        return sum(1 for t in _trials(client).values() if _status(t) == "COMPLETED")

    max_failures = spec.max_failures if spec.max_failures is not None else max(3, spec.trials)
    failures = 0
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=spec.trials, initial=n_completed(), desc=f"search {spec.name}", unit="trial")
    try:
        while n_completed() < spec.trials:
            if pending:
                idx = client.attach_trial(parameters=pending.pop(0))
                ax_params = _params_of(_trials(client)[idx])
            else:
                (idx, ax_params), = client.get_next_trials(max_trials=1).items()
            _save(client, state_path)  # a crash from here on leaves the trial RUNNING
            params = {**_to_keys(spec, ax_params), **spec.fixed}
            rec = TrialRecord(index=idx, params=params, status="RUNNING")
            try:
                metrics = {k: float(v) for k, v in dict(evaluate(params, idx)).items()}
                value = spec.scalarise(metrics)
            except (KeyboardInterrupt, SystemExit):
                raise
            except Exception as exc:  # a failed trial is recorded, not fatal
                log.warning("search: trial %d failed: %r", idx, exc)
                client.mark_trial_failed(idx, failed_reason=repr(exc)[:500])
                rec.status, rec.reason = "FAILED", repr(exc)[:500]
                failures += 1
                _save(client, state_path)
                records[idx] = rec
                _save_records(records, state_path)
                if on_trial_end:
                    on_trial_end(rec)
                if failures >= max_failures:
                    raise RuntimeError(f"search {spec.name}: {failures} trials failed (last: {exc!r}); stopping. "
                                       f"State kept in {state_path}") from exc
                continue
            client.complete_trial(trial_index=idx, raw_data={OBJECTIVE: value})
            rec.status, rec.objective, rec.metrics = "COMPLETED", value, metrics
            records[idx] = rec
            _save(client, state_path)
            _save_records(records, state_path)
            if on_trial_end:
                on_trial_end(rec)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(objective=f"{value:.4g}")
    finally:
        if bar is not None:
            bar.close()
    _save_records(records, state_path)
    return _result(spec, records)


def _records_path(state_path: Path) -> Path:
    return state_path.with_name(state_path.stem + "_trials.json")


def _spec_path(state_path: Path) -> Path:
    return state_path.with_name(state_path.stem + "_spec.json")


def _read_json(path: Path, what: str) -> Any:
    import json
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SearchStateError(f"search state file {path} ({what}) is not valid JSON ({exc}); it was probably "
                               f"cut short by a crash or edited by hand: restore it, or {_RESTART_HINT}") from exc


def _load_client(state_path: Path):
    """The Ax client saved in ``state_path``; a :class:`SearchStateError` naming the file if it is unreadable."""
    from ax import Client
    _read_json(state_path, "the Ax experiment")
    try:
        return Client.load_from_json_file(str(state_path))
    except Exception as exc:  # valid JSON, but not an Ax experiment
        raise SearchStateError(f"search state file {state_path} is not a saved Ax experiment "
                               f"({type(exc).__name__}: {str(exc)[:200]}); {_RESTART_HINT}") from exc


def _differences(old: Any, new: Any, prefix: str = "search") -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new), key=str):
            out += _differences(old.get(k, "<absent>"), new.get(k, "<absent>"), f"{prefix}.{k}")
        return out
    return [] if old == new else [f"{prefix}: saved {old!r}, now {new!r}"]


def check_same_search(spec: SearchSpec, state_path: str | os.PathLike, resume_override: bool = False) -> None:
    """Compare ``spec`` with the signature saved beside ``state_path`` (``<stem>_spec.json``).

    A changed objective (metrics, weights, direction), parameter range, fixed value, constraint or
    per-trial override would mix trials of two different searches and pick the best by the new rule:
    :class:`SearchStateError` listing the changes, or only a warning with ``resume_override``."""
    path = _spec_path(Path(state_path))
    if not path.exists():
        return  # a search saved before signatures existed: only the Ax direction can be checked
    saved = _read_json(path, "the search config it was started with")
    diff = _differences(saved, spec.signature())
    if not diff:
        return
    msg = (f"search {spec.name}: the saved search in {Path(state_path).parent} was run with another config: "
           + "; ".join(diff))
    if resume_override:
        log.warning("%s (resuming anyway: search.resume_override=true)", msg)
        return
    raise SearchStateError(f"{msg}. Resuming would mix trials of two searches; {_RESTART_HINT}, or pass "
                           "search.resume_override=true to resume anyway")


def _check_direction(client, spec: SearchSpec, state_path: Path, resume_override: bool) -> None:
    """The saved Ax experiment's optimisation direction must be the config's."""
    try:
        saved_min = bool(client._experiment.optimization_config.objective.minimize)
    except AttributeError:  # pragma: no cover - an Ax without this attribute: nothing to compare
        return
    if saved_min == spec.minimize:
        return
    msg = (f"search {spec.name}: the experiment in {state_path} {'minimises' if saved_min else 'maximises'} the "
           f"objective but search.objective.minimize={str(spec.minimize).lower()}")
    if resume_override:
        log.warning("%s (resuming anyway: search.resume_override=true)", msg)
        return
    raise SearchStateError(f"{msg}; {_RESTART_HINT}")


def _save_records(records: dict[int, TrialRecord], state_path: Path) -> None:
    atomic_write_json(_records_path(state_path), [vars(r) for r in sorted(records.values(), key=lambda r: r.index)])


def _load_records(client, spec: SearchSpec, records: dict[int, TrialRecord], state_path: Path,
                  use_saved: bool = True) -> None:
    """Rebuild trial records from the Ax experiment, with metrics from the side file when present."""
    saved = {r["index"]: r for r in load_records(state_path)} if use_saved else {}
    values = {}
    data = client._experiment.lookup_data().df
    for _, row in data.iterrows():
        if row["metric_name"] == OBJECTIVE:
            values[int(row["trial_index"])] = float(row["mean"])
    for idx, trial in _trials(client).items():
        params = {**_to_keys(spec, _params_of(trial)), **spec.fixed}
        records[idx] = TrialRecord(index=idx, params=params, status=_status(trial), objective=values.get(idx),
                                   metrics=dict(saved.get(idx, {}).get("metrics", {})),
                                   reason=str(getattr(trial, "failed_reason", "") or saved.get(idx, {}).get("reason", "")))


def load_records(state_path: str | os.PathLike) -> list[dict]:
    """The per-trial records (params, status, objective, metrics) saved beside the state file."""
    p = _records_path(Path(state_path))
    if not p.exists():
        return []
    records = _read_json(p, "the per-trial records")
    if not isinstance(records, list) or not all(isinstance(r, dict) and "index" in r for r in records):
        raise SearchStateError(f"search state file {p} (the per-trial records) should hold a list of trial "
                               f"records with an 'index'; got {str(records)[:80]!r}: restore it, or {_RESTART_HINT}")
    return records


def _result(spec: SearchSpec, records: dict[int, TrialRecord]) -> SearchResult:
    done = [r for r in records.values() if r.status == "COMPLETED" and r.objective is not None
            and math.isfinite(r.objective)]
    if not done:
        raise RuntimeError(f"search {spec.name}: no trial completed")
    best = (min if spec.minimize else max)(done, key=lambda r: r.objective)
    return SearchResult(best_params=dict(best.params), best_objective=float(best.objective),
                        best_trial=best.index, trials=sorted(records.values(), key=lambda r: r.index))
