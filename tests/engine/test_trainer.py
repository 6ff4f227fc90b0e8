import json
import logging
from pathlib import Path

import pytest
import torch
from omegaconf import open_dict

from engine_standins import SimulatedKill
from omnidl.engine import train
from omnidl.engine.checkpoint import load_checkpoint


def _losses(out_dir: Path) -> dict[int, float]:
    """step -> loss from train_log.jsonl (a re-run step overrides the earlier record)."""
    recs = [json.loads(line) for line in (out_dir / "train_log.jsonl").read_text().splitlines()]
    return {r["step"]: r["loss"] for r in recs}


BASE = ["trainer.batch_size=4", "trainer.log_every_steps=1", "trainer.val_every_steps=4", "trainer.ckpt_every_steps=2",
        "trainer.max_steps=8", "trainer.tensorboard=false", "sched.warmup_steps=2", "trainer.random_rotation_deg=10"]


def test_kill_mid_epoch_and_resume_continues_the_loss_curve_exactly(cfg_factory):
    ref_cfg = cfg_factory(BASE, sub="uninterrupted")
    ref = train(ref_cfg)
    ref_losses = _losses(Path(ref["output_dir"]))
    assert sorted(ref_losses) == list(range(1, 9))

    cfg = cfg_factory(BASE, sub="killed")
    with open_dict(cfg):
        cfg.loss.kill_at = 7  # dies during step 7 (first batch of epoch 2); last.pt is from step 6
    with pytest.raises(SimulatedKill):
        train(cfg)
    out = Path(cfg.paths.output_dir)
    ck = load_checkpoint(out / "checkpoints" / "last.pt")
    assert (ck["step"], ck["epoch"], ck["batch_in_epoch"]) == (6, 1, 3)  # end of epoch 1 (0-based)
    resumed_cfg = cfg_factory(BASE + ["trainer.resume=true"], sub="killed")
    resumed = train(resumed_cfg)
    assert resumed["step"] == 8
    assert _losses(out) == ref_losses  # bit-identical continuation
    assert resumed["best"] == ref["best"]


def test_resume_from_mid_epoch_checkpoint_file(cfg_factory):
    over = [o for o in BASE if "random_rotation" not in o] + ["trainer.ckpt_every_steps=1"]
    ref = train(cfg_factory(over, sub="ref"))
    cfg = cfg_factory(over, sub="a")
    with open_dict(cfg):
        cfg.loss.kill_at = 6  # last.pt at step 5 = epoch 1, batch 2 of 3: a mid-epoch sampler position
    with pytest.raises(SimulatedKill):
        train(cfg)
    ck_path = Path(cfg.paths.output_dir) / "checkpoints" / "last.pt"
    assert load_checkpoint(ck_path)["batch_in_epoch"] == 2
    resumed = train(cfg_factory(over + [f"checkpoint={ck_path}"], sub="b"))
    losses = _losses(Path(resumed["output_dir"]))
    ref_losses = _losses(Path(ref["output_dir"]))
    assert {s: losses[s] for s in range(6, 9)} == {s: ref_losses[s] for s in range(6, 9)}


def test_outputs_metrics_json_tensorboard_and_best(cfg_factory):
    cfg = cfg_factory(["trainer.max_epochs=2", "trainer.monitor=val/acc", "trainer.monitor_mode=max",
                       "sched=step", "sched.step_size=2", "optim=sgd", "optim.lr=0.05", "trainer.grad_clip=1.0"])
    summary = train(cfg)
    out = Path(cfg.paths.output_dir)
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk["best"] == summary["best"] and summary["monitor"] == "val/acc"
    assert {"val/loss", "val/mae", "val/acc"} <= set(summary["final"])
    assert summary["step"] == 6 and summary["epoch"] == 2
    assert (out / "checkpoints" / "best.pt").is_file() and (out / "checkpoints" / "last.pt").is_file()
    events = list((out / "tb").glob("events.out.tfevents.*"))
    assert events
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    acc = EventAccumulator(str(out / "tb"), size_guidance={"images": 0})
    acc.Reload()
    assert "train/loss" in acc.Tags()["scalars"] and "val/acc" in acc.Tags()["scalars"]
    assert "val/prediction_vs_truth" in acc.Tags()["images"]
    best = load_checkpoint(out / "checkpoints" / "best.pt")
    assert best["best"] == summary["best"] and best["step"] == summary["best_step"]


def test_early_stopping(cfg_factory):
    cfg = cfg_factory(["trainer.max_epochs=10", "optim.lr=0.0", "trainer.early_stopping.patience=2"])
    summary = train(cfg)
    assert summary["stopped_early"] and summary["step"] == 9  # 3 validations: best, then 2 without improvement


def test_nan_batch_skipped_with_warning_or_error(cfg_factory, caplog):
    over = ["trainer.max_steps=4", "trainer.batch_size=1", "trainer.tensorboard=false"]
    cfg = cfg_factory(over)
    with open_dict(cfg):
        cfg.data.train.length = 4
        cfg.data.train.nan_index = 2
    with caplog.at_level(logging.WARNING, logger="omnidl.engine"):
        summary = train(cfg)
    assert summary["step"] == 4  # 4 samples, one poisoned: the 5th batch completes step 4
    assert "non-finite values in ['image']" in caplog.text and "sample_002" in caplog.text
    cfg = cfg_factory(over + ["trainer.skip_nonfinite=false"], sub="strict")
    with open_dict(cfg):
        cfg.data.train.length = 4
        cfg.data.train.nan_index = 2
    with pytest.raises(FloatingPointError, match="sample_002"):
        train(cfg)


def test_amp_cpu_runs(cfg_factory):
    summary = train(cfg_factory(["trainer.max_steps=2", "trainer.amp=true", "trainer.tensorboard=false"]))
    assert summary["step"] == 2 and torch.isfinite(torch.tensor(summary["best"]))


def test_multirun_style_jobs_reset_seed_and_threads(cfg_factory):
    torch.manual_seed(123)
    a = train(cfg_factory(["trainer.max_steps=2", "trainer.tensorboard=false"], sub="j1"))
    torch.rand(5)  # a previous job leaves the RNG somewhere else
    torch.set_num_threads(2)
    b = train(cfg_factory(["trainer.max_steps=2", "trainer.tensorboard=false"], sub="j2"))
    assert a["best"] == b["best"] and torch.get_num_threads() == 1


def test_missing_model_or_data_is_a_clear_error(cfg_factory):
    cfg = cfg_factory(["trainer.max_steps=1"], standin=False)
    with pytest.raises(ValueError, match="model=<name>"):
        train(cfg)


def test_missing_search_result_is_announced(cfg_factory, caplog):
    cfg = cfg_factory(["trainer.max_steps=1", "trainer.tensorboard=false", "+loss_search.name=my_search"])
    with caplog.at_level(logging.WARNING, logger="omnidl.engine"):
        train(cfg)
    assert "'my_search' search were not found" in caplog.text and "+search=my_search" in caplog.text
