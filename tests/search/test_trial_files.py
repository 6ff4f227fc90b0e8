"""What a finished trial keeps (search.keep_checkpoints): metrics always, a weights-only best.pt by default."""
import json
import math
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from omnidl.engine.checkpoint import load_checkpoint, save_checkpoint
from omnidl.search import SearchConfigError, run_search_from_config
from omnidl.search.trial_files import KEEP_CHOICES, check_keep, prune_trial


def _engine_run(out: Path, value: float = 1.0) -> None:
    """What omnidl.engine.train leaves: metrics.json and full last.pt / best.pt (with optimiser state)."""
    ck = out / "checkpoints"
    ck.mkdir(parents=True, exist_ok=True)
    full = {"model": {"w": torch.full((64, 64), value)}, "optimizer": {"state": {0: torch.zeros(64, 64)}},
            "scheduler": {}, "scaler": None, "rng": {"torch": torch.zeros(8)}, "step": 4, "epoch": 0,
            "batch_in_epoch": 4, "best": value, "best_step": 4, "config": {"model": {"name": "toy"}}}
    save_checkpoint(ck / "last.pt", full)
    save_checkpoint(ck / "best.pt", full)
    (ck / ".last.pt.abc.tmp").write_bytes(b"orphan")
    (out / "metrics.json").write_text(json.dumps({"final": {"val/err": value}}))


@pytest.mark.parametrize("keep", KEEP_CHOICES)
def test_prune_trial(tmp_path, keep):
    _engine_run(tmp_path)
    prune_trial(tmp_path, keep)
    files = sorted(p.name for p in (tmp_path / "checkpoints").iterdir())
    assert (tmp_path / "metrics.json").exists()
    if keep == "all":
        assert files == [".last.pt.abc.tmp", "best.pt", "last.pt"]
        return
    if keep == "none":
        assert files == []
        return
    assert files == ["best.pt"]
    ck = load_checkpoint(tmp_path / "checkpoints" / "best.pt")
    assert "optimizer" not in ck and "rng" not in ck and ck["step"] == 4 and ck["config"]["model"]["name"] == "toy"
    assert torch.equal(ck["model"]["w"], torch.ones(64, 64))


def test_bad_keep_value_names_the_field():
    with pytest.raises(ValueError, match=r"search\.keep_checkpoints: expected one of .*'weights'.*got 'some'"):
        check_keep("some")


def _cfg(tmp_path, **search):
    return OmegaConf.create({
        "loss": {"alpha_a": 1.0}, "paths": {"output_dir": "unused"},
        "search": {"name": "toy", "trials": 3, "sobol_trials": 3, "dir": str(tmp_path / "s"),
                   "config_dir": str(tmp_path / "configs"), "objective": {"metrics": {"err": 1.0}, "minimize": True},
                   "parameters": {"loss.alpha_a": {"bounds": [0.01, 100], "log": True}}, **search}})


def fake_train(cfg):
    err = math.log10(cfg.loss.alpha_a) ** 2
    _engine_run(Path(cfg.paths.output_dir), err)
    return {"err": err}


@pytest.mark.slow
@pytest.mark.parametrize("keep, bests", [("best_trial", 1), ("weights", 3)])
def test_search_keeps_metrics_and_weights_only_best(tmp_path, keep, bests):
    res = run_search_from_config(_cfg(tmp_path, keep_checkpoints=keep), train_fn=fake_train)
    trials = sorted((tmp_path / "s").glob("trial_*"))
    assert len(trials) == 3 and all((t / "metrics.json").exists() for t in trials)
    assert not list((tmp_path / "s").rglob("last.pt")) and not list((tmp_path / "s").rglob("*.tmp"))
    kept = list((tmp_path / "s").rglob("best.pt"))
    assert len(kept) == bests
    assert (tmp_path / "s" / f"trial_{res.best_trial:03d}" / "checkpoints" / "best.pt") in kept
    assert all("optimizer" not in load_checkpoint(p) for p in kept)


def test_bad_keep_value_fails_before_training(tmp_path):
    calls = []
    with pytest.raises(SearchConfigError, match="keep_checkpoints"):
        run_search_from_config(_cfg(tmp_path, keep_checkpoints="most"), train_fn=lambda c: calls.append(c))
    assert not calls
