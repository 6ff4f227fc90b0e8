"""The shipped search configs (configs/search/*.yaml) as train.py composes them: the objective computed from
fixed trial metrics must equal the hand-computed value, with every metric a fraction (issue 14)."""
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from omnidl.engine.config import register_configs
from omnidl.search import parse_search_spec

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
SEARCHES = sorted(p.stem for p in (CONFIGS / "search").glob("*.yaml"))
# the final validation metrics of one trial, as omnidl reports them: all fractions
TRIAL = {"val/delta1": 0.62, "val/miou": 0.31, "val/mre": 0.27, "val/mae": 0.55, "val/loss": 3.0}


def _search(name):
    register_configs()
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"+search={name}"])
    return parse_search_spec(cfg.search)


def test_every_search_config_is_listed():
    assert {"fredsnet_loss_weights", "fredsnet_loss_weights_recall", "fredsnet_tiny"} <= set(SEARCHES)


@pytest.mark.parametrize("name", SEARCHES)
def test_objective_from_fixed_trial_metrics(name):
    spec = _search(name)
    assert not spec.minimize
    # delta1 + mIoU - MRE, by hand: 0.62 + 0.31 - 0.27
    assert spec.scalarise(TRIAL) == pytest.approx(0.66, abs=1e-12)


@pytest.mark.parametrize("name", SEARCHES)
def test_miou_moves_the_objective_as_much_as_delta1(name):
    spec = _search(name)
    base = spec.scalarise(TRIAL)
    d_miou = spec.scalarise({**TRIAL, "val/miou": TRIAL["val/miou"] + 0.1}) - base
    d_delta = spec.scalarise({**TRIAL, "val/delta1": TRIAL["val/delta1"] + 0.1}) - base
    assert d_miou == pytest.approx(0.1) and d_delta == pytest.approx(0.1)


@pytest.mark.parametrize("name", SEARCHES)
def test_search_keeps_a_weights_only_best_by_default(name):
    register_configs()
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"+search={name}"])
    assert OmegaConf.select(cfg, "search.keep_checkpoints") == "best_trial"
    assert OmegaConf.select(cfg, "search.resume_override") is False
