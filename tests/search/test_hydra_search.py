"""The search driven from a training config (outside a Hydra app: overrides applied to a copy)."""
import math

import pytest
from omegaconf import OmegaConf

from omnidl.search import SearchConfigError, run_search_from_config


def _cfg(tmp_path, **search):
    return OmegaConf.create({
        "loss": {"alpha_a": 1.0, "alpha_b": 1.0, "kind": "toy"},
        "paths": {"output_dir": "unused"},
        "search": {"name": "toy", "trials": 4, "sobol_trials": 3, "dir": str(tmp_path / "s"),
                   "config_dir": str(tmp_path / "configs"),
                   "objective": {"metrics": {"err": 1.0}, "minimize": True},
                   "parameters": {"loss.alpha_a": {"bounds": [0.01, 100], "log": True}},
                   **search}})


def fake_train(cfg):
    assert "search" not in cfg
    return {"err": math.log10(cfg.loss.alpha_a) ** 2, "other": 1.0}


@pytest.mark.slow
def test_search_writes_best_config_table_and_plot(tmp_path):
    res = run_search_from_config(_cfg(tmp_path), train_fn=fake_train)
    assert len(res.completed) == 4
    best = OmegaConf.load(tmp_path / "configs" / "loss" / "toy_best.yaml")
    assert best.alpha_a == pytest.approx(res.best_params["loss.alpha_a"])
    assert best.kind == "toy" and best.alpha_b == 1.0
    for f in ("trials.csv", "trials.md", "objective.png", "experiment.json"):
        assert (tmp_path / "s" / f).exists()
    assert (tmp_path / "s" / "trials.md").read_text().count("COMPLETED") == 4


def test_unknown_parameter_fails_before_training(tmp_path):
    calls = []
    cfg = _cfg(tmp_path, parameters={"loss.alpha_typo": {"bounds": [0.1, 1]}})
    with pytest.raises(SearchConfigError, match="loss.alpha_typo"):
        run_search_from_config(cfg, train_fn=lambda c: calls.append(c))
    assert not calls


def test_a_hand_written_best_config_is_never_replaced_and_is_checked_before_any_trial(tmp_path):
    mine = tmp_path / "configs" / "loss" / "toy_best.yaml"
    mine.parent.mkdir(parents=True)
    mine.write_text("alpha_a: 3.0  # tuned by hand\n")
    calls = []
    with pytest.raises(FileExistsError, match=r"toy_best\.yaml exists and was not written by a search"):
        run_search_from_config(_cfg(tmp_path), train_fn=lambda c: calls.append(c))
    assert not calls and mine.read_text() == "alpha_a: 3.0  # tuned by hand\n"


def test_a_second_search_in_the_same_folder_stops(tmp_path):
    from omnidl.utils.outputs import RunLock
    calls = []
    with RunLock(tmp_path / "s", "search"):
        with pytest.raises(SearchConfigError, match=r"is in use by another search: pid \d+"):
            run_search_from_config(_cfg(tmp_path), train_fn=lambda c: calls.append(c))
    assert not calls
