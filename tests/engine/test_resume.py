"""Resume checks: changed settings, the log cut back to the resumed step, all-corrupt data, run folders."""
import json
import logging
from pathlib import Path

import pytest
from omegaconf import open_dict

from engine_standins import SimulatedKill
from omnidl.engine import train
from omnidl.engine.config import run_stamp

BASE = ["trainer.batch_size=4", "trainer.log_every_steps=1", "trainer.val_every_steps=4", "trainer.ckpt_every_steps=2",
        "trainer.max_steps=8", "trainer.tensorboard=false"]


def _records(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]


def _killed_run(cfg_factory, sub: str, kill_at: int = 6):
    cfg = cfg_factory(BASE, sub=sub)
    with open_dict(cfg):
        cfg.loss.kill_at = kill_at  # last.pt from step 4
    with pytest.raises(SimulatedKill):
        train(cfg)
    return Path(cfg.paths.output_dir)


def test_changed_settings_on_resume_are_an_error_listing_them(cfg_factory):
    _killed_run(cfg_factory, "a")
    with pytest.raises(ValueError, match=r"(?s)optim\.lr: checkpoint 0\.001, now 0\.5.*trainer\.batch_size: "
                                         r"checkpoint 4, now 2.*trainer\.resume_override=true"):
        train(cfg_factory(BASE + ["trainer.resume=true", "optim.lr=0.5", "trainer.batch_size=2"], sub="a"))


def test_resume_override_uses_the_new_settings(cfg_factory, caplog):
    out = _killed_run(cfg_factory, "b")
    with caplog.at_level(logging.WARNING, logger="omnidl.engine"):
        summary = train(cfg_factory(BASE + ["trainer.resume=true", "optim.lr=0.5", "trainer.resume_override=true",
                                            "sched=none"], sub="b"))
    assert "resume_override=true" in caplog.text and "optim.lr" in caplog.text
    lrs = {r["step"]: r["lr"] for r in _records(out)}
    assert lrs[5] == pytest.approx(0.5) and summary["step"] == 8


def test_the_log_is_cut_back_to_the_resumed_step(cfg_factory):
    out = _killed_run(cfg_factory, "c", kill_at=7)  # dies in step 7: steps 1..6 logged, last.pt from step 6
    steps_before = [r["step"] for r in _records(out)]
    assert steps_before == [1, 2, 3, 4, 5, 6]
    cfg = cfg_factory(BASE, sub="c2")
    with open_dict(cfg):
        cfg.loss.kill_at = 6  # dies in step 6: last.pt from step 4, log has 1..5
    with pytest.raises(SimulatedKill):
        train(cfg)
    out2 = Path(cfg.paths.output_dir)
    assert [r["step"] for r in _records(out2)] == [1, 2, 3, 4, 5]
    train(cfg_factory(BASE + ["trainer.resume=true"], sub="c2"))
    assert [r["step"] for r in _records(out2)] == list(range(1, 9))  # 5 is not repeated


def test_batches_of_only_skipped_samples_count_towards_max_skipped(cfg_factory):
    cfg = cfg_factory(["trainer.max_steps=2", "trainer.tensorboard=false", "trainer.max_skipped=3"], sub="bad")
    with open_dict(cfg):
        cfg.data.train = {"_target_": "engine_standins.CorruptPanoramas", "length": 400}
    with pytest.raises(RuntimeError, match=r"4 batches in a row skipped.*every sample.*unreadable.*max_skipped=3"):
        train(cfg)


def test_run_stamp_is_unique_per_process_and_stable():
    a, b = run_stamp("%H-%M-%S"), run_stamp("%H-%M-%S")
    assert a == b and a.rsplit("_", 1)[1] == str(__import__("os").getpid()) and "." in a
