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


# -- resuming a saved search: the same search only, and a clear error on an unreadable state file --------
@pytest.fixture(scope="module")
def saved_search(tmp_path_factory):
    """A finished 2-trial search (Sobol only): its state files."""
    d = tmp_path_factory.mktemp("saved")
    run_search(_spec(2, sobol=2), quadratic, d / "experiment.json", progress=False)
    return {p.name: p.read_bytes() for p in d.iterdir()}


def _restore(saved, folder):
    for name, data in saved.items():
        (folder / name).write_bytes(data)
    return folder / "experiment.json"


def _never(params, idx):
    raise AssertionError("no trial may run")


def test_resume_with_flipped_direction_is_an_error(saved_search, tmp_path):
    from omnidl.search import SearchStateError
    state = _restore(saved_search, tmp_path)
    with pytest.raises(SearchStateError, match=r"objective\.minimize: saved True, now False.*search\.restart=true"):
        run_search(_spec(3, sobol=2, minimize=False), _never, state, progress=False)


def test_resume_with_flipped_direction_of_an_old_search_is_an_error(saved_search, tmp_path):
    """A search saved before the signature file existed: the Ax experiment's own direction is checked."""
    from omnidl.search import SearchStateError
    state = _restore(saved_search, tmp_path)
    (tmp_path / "experiment_spec.json").unlink()
    with pytest.raises(SearchStateError, match=r"minimises the objective but search\.objective\.minimize=false"):
        run_search(_spec(3, sobol=2, minimize=False), _never, state, progress=False)


def test_resume_with_changed_weights_or_bounds_is_an_error(saved_search, tmp_path):
    from omnidl.search import SearchStateError
    state = _restore(saved_search, tmp_path)
    spec = _spec(3, sobol=2)
    spec.objective_metrics = {"loss": 0.01}
    with pytest.raises(SearchStateError, match=r"objective\.metrics\.loss: saved 1\.0, now 0\.01"):
        run_search(spec, _never, state, progress=False)
    spec = _spec(3, sobol=2)
    spec.overrides = ["trainer.max_steps=8"]
    with pytest.raises(SearchStateError, match=r"search\.overrides"):
        run_search(spec, _never, state, progress=False)


@pytest.mark.slow
def test_resume_override_and_more_trials_are_allowed(saved_search, tmp_path, caplog):
    state = _restore(saved_search, tmp_path)
    res = run_search(_spec(3, sobol=2), quadratic, state, progress=False)   # more trials: same search
    assert len(res.completed) == 3
    spec = _spec(4, sobol=2)
    spec.objective_metrics = {"loss": 2.0}
    with caplog.at_level("WARNING"):
        res = run_search(spec, quadratic, state, progress=False, resume_override=True)
    assert len(res.completed) == 4 and "resuming anyway" in caplog.text


@pytest.mark.parametrize("name, content", [
    ("experiment.json", "half"), ("experiment.json", b"hello"), ("experiment.json", b""),
    ("experiment.json", b'{"a": 1}'), ("experiment_trials.json", "half"), ("experiment_trials.json", b'{"x": 2}'),
    ("experiment_spec.json", "half")])
def test_corrupt_state_file_is_named(saved_search, tmp_path, name, content):
    from omnidl.search import SearchStateError
    state = _restore(saved_search, tmp_path)
    data = saved_search[name]
    (tmp_path / name).write_bytes(data[: len(data) // 2] if content == "half" else content)
    with pytest.raises(SearchStateError, match=rf"search state file .*{name}.*search\.restart=true"):
        run_search(_spec(3, sobol=2), _never, state, progress=False)
    # restart=true starts over whatever the old files hold
    res = run_search(_spec(1, sobol=1), quadratic, state, restart=True, progress=False)
    assert len(res.completed) == 1
