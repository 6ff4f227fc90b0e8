"""The Ax driver: finds a known optimum, records failures, resumes after a crash at the interrupted trial."""
import math

import pytest

from omnidl.search.driver import load_records, run_search
from omnidl.search.space import parse_search_spec


def _spec(trials, sobol=4, minimize=True):
    return parse_search_spec({
        "name": "toy", "trials": trials, "sobol_trials": sobol, "seed": 0,
        "objective": {"metrics": {"loss": 1.0}, "minimize": minimize},
        "parameters": {"loss.a": {"bounds": [1e-2, 1e2], "log": True}, "loss.b": {"bounds": [0.0, 1.0]}},
        "fixed": {"loss.c": 0.5},
    })


def quadratic(params, idx):
    # optimum at a = 1 (log10 a = 0), b = 0.3
    return {"loss": math.log10(params["loss.a"]) ** 2 + 4 * (params["loss.b"] - 0.3) ** 2}


@pytest.mark.slow
def test_finds_known_optimum(tmp_path):
    res = run_search(_spec(14), quadratic, tmp_path / "s.json", progress=False)
    assert len(res.completed) == 14
    assert abs(math.log10(res.best_params["loss.a"])) < 0.35
    assert abs(res.best_params["loss.b"] - 0.3) < 0.15
    assert res.best_objective < 0.15
    assert res.best_params["loss.c"] == 0.5


def test_failed_trial_is_recorded_not_fatal(tmp_path):
    calls = []

    def flaky(params, idx):
        calls.append(idx)
        if len(calls) == 2:
            raise RuntimeError("training diverged")
        return quadratic(params, idx)

    res = run_search(_spec(3), flaky, tmp_path / "s.json", progress=False)
    assert len(res.completed) == 3
    failed = [t for t in res.trials if t.status == "FAILED"]
    assert len(failed) == 1 and "diverged" in failed[0].reason


class Crash(BaseException):
    pass


@pytest.mark.slow
def test_resume_after_crash_continues_at_interrupted_trial(tmp_path):
    state = tmp_path / "s.json"
    seen = []

    def crashing(params, idx):
        seen.append(dict(params))
        if len(seen) == 4:
            raise Crash()
        return quadratic(params, idx)

    with pytest.raises(Crash):
        run_search(_spec(6), crashing, state, progress=False)
    assert sum(r["status"] == "COMPLETED" for r in load_records(state)) == 3
    resumed = []

    def normal(params, idx):
        resumed.append(dict(params))
        return quadratic(params, idx)

    res = run_search(_spec(6), normal, state, progress=False)
    assert resumed[0] == seen[3]          # the interrupted trial runs again first
    assert len(res.completed) == 6 and len(resumed) == 3
