"""Checkpoint safety: best.pt before last.pt, repair of a missing best, weights-only best.pt, a lean final
last.pt, safe loading (weights_only=True), stale temp files."""
import json
import logging
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import open_dict

from engine_standins import SimulatedKill
from omnidl.engine import train
from omnidl.engine.checkpoint import load_checkpoint

BASE = ["trainer.batch_size=4", "trainer.log_every_steps=1", "trainer.val_every_steps=2", "trainer.ckpt_every_steps=1",
        "trainer.max_steps=8", "trainer.tensorboard=false", "optim.lr=0.01"]


def _losses(out: Path) -> dict[int, float]:
    return {r["step"]: r["loss"] for r in map(json.loads, (out / "train_log.jsonl").read_text().splitlines())}


def _kill_between_best_and_last(monkeypatch, at_step: int):
    """Make the run die right after writing best.pt at ``at_step`` (before last.pt is written)."""
    import omnidl.engine.state as st
    real = st.save_checkpoint

    def save(path, ck):
        out = real(path, ck)
        if Path(path).name == "best.pt" and ck["step"] == at_step:
            raise SimulatedKill(f"killed after writing best.pt at step {at_step}")
        return out
    monkeypatch.setattr(st, "save_checkpoint", save)


def test_a_kill_between_the_best_and_last_writes_leaves_a_consistent_pair(cfg_factory, monkeypatch):
    ref = train(cfg_factory(BASE, sub="ref"))
    cfg = cfg_factory(BASE, sub="killed")
    out = Path(cfg.paths.output_dir) / "checkpoints"
    _kill_between_best_and_last(monkeypatch, 4)
    with pytest.raises(SimulatedKill):
        train(cfg)
    monkeypatch.undo()
    last, best = load_checkpoint(out / "last.pt"), load_checkpoint(out / "best.pt")
    assert last["step"] == 3 and last["best_step"] == 2  # the previous last.pt: it describes ...
    assert best["step"] == 4  # ... a best.pt that exists (here already the next one, which the resume redoes)
    resumed = train(cfg_factory(BASE + ["trainer.resume=true"], sub="killed"))
    assert _losses(out.parent) == _losses(Path(ref["output_dir"]))
    assert (resumed["best"], resumed["best_step"]) == (ref["best"], ref["best_step"])
    assert load_checkpoint(out / "best.pt")["step"] == ref["best_step"]


def test_resume_repairs_a_missing_best(cfg_factory, caplog):
    over = [o for o in BASE if "max_steps" not in o]
    cfg = cfg_factory(over + ["trainer.max_steps=4", "trainer.save_optimizer=true"], sub="r")
    train(cfg)
    ck_dir = Path(cfg.paths.output_dir) / "checkpoints"
    (ck_dir / "best.pt").unlink()  # lost by hand; last.pt (step 4) is also the best step
    with caplog.at_level(logging.WARNING, logger="omnidl.engine"):
        train(cfg_factory(over + ["trainer.max_steps=4", "trainer.save_optimizer=true", "trainer.resume=true"],
                          sub="r"))
    assert "rewrote it from" in caplog.text and load_checkpoint(ck_dir / "best.pt")["step"] == 4


def test_resume_forgets_a_best_whose_file_is_gone(cfg_factory, caplog, monkeypatch):
    cfg = cfg_factory(BASE + ["trainer.early_stopping.patience=0"], sub="f")
    with open_dict(cfg):
        cfg.loss.kill_at = 6  # last.pt at step 5; best at step 4
    with pytest.raises(SimulatedKill):
        train(cfg)
    ck_dir = Path(cfg.paths.output_dir) / "checkpoints"
    assert load_checkpoint(ck_dir / "last.pt")["best_step"] == 4
    (ck_dir / "best.pt").unlink()
    with caplog.at_level(logging.WARNING, logger="omnidl.engine"):
        summary = train(cfg_factory(BASE + ["trainer.resume=true"], sub="f"))
    assert "cannot be recovered" in caplog.text
    assert (ck_dir / "best.pt").is_file() and summary["best_step"] >= 6


def test_best_is_weights_only_by_default_and_the_final_last_is_lean(cfg_factory):
    summary = train(cfg_factory(BASE, sub="w"))
    ck_dir = Path(summary["output_dir"]) / "checkpoints"
    best, last = load_checkpoint(ck_dir / "best.pt"), load_checkpoint(ck_dir / "last.pt")
    assert "optimizer" not in best and "rng" not in best and best["step"] == summary["best_step"]
    assert "optimizer" not in last and last["step"] == 8
    if summary["best_step"] == 8:  # the same weights: one file on disk
        assert (ck_dir / "best.pt").stat().st_ino == (ck_dir / "last.pt").stat().st_ino
    full = train(cfg_factory(BASE + ["trainer.save_optimizer=true"], sub="o"))
    ck_dir = Path(full["output_dir"]) / "checkpoints"
    assert "optimizer" in load_checkpoint(ck_dir / "best.pt") and "optimizer" in load_checkpoint(ck_dir / "last.pt")


def test_resuming_a_finished_run_is_a_no_op(cfg_factory):
    first = train(cfg_factory(BASE, sub="done"))
    again = train(cfg_factory(BASE + ["trainer.resume=true"], sub="done"))
    assert again["step"] == 8 and again["best"] == first["best"]


def test_interrupted_run_keeps_the_optimizer_state_in_last(cfg_factory):
    cfg = cfg_factory(BASE, sub="k")
    with open_dict(cfg):
        cfg.loss.kill_at = 5
    with pytest.raises(SimulatedKill):
        train(cfg)
    last = load_checkpoint(Path(cfg.paths.output_dir) / "checkpoints" / "last.pt")
    assert {"optimizer", "scheduler", "rng"} <= set(last)
    assert isinstance(last["rng"]["numpy"][1], torch.Tensor)  # no numpy objects: loads with weights_only=True


class _Evil:
    def __reduce__(self):
        return (print, ("this ran code",))


def test_checkpoints_are_loaded_without_unpickling_code(tmp_path, capsys):
    torch.save({"model": {"w": torch.zeros(1)}, "x": _Evil()}, tmp_path / "evil.pt")
    with pytest.raises(RuntimeError, match=r"evil\.pt.*refuses to unpickle"):
        load_checkpoint(tmp_path / "evil.pt")
    assert "this ran code" not in capsys.readouterr().out


def test_older_checkpoints_with_a_numpy_rng_state_still_load(tmp_path):
    np.random.seed(3)
    torch.save({"model": {"w": torch.zeros(1)}, "rng": {"numpy": np.random.get_state()}}, tmp_path / "old.pt")
    ck = load_checkpoint(tmp_path / "old.pt")
    from omnidl.engine.seed import set_rng_state
    set_rng_state({"python": __import__("random").getstate(), "numpy": ck["rng"]["numpy"],
                   "torch": torch.get_rng_state()})
    a = np.random.rand()
    np.random.seed(3)
    assert a == np.random.rand()


def test_stale_temp_files_are_removed_at_start(cfg_factory):
    cfg = cfg_factory(["trainer.max_steps=1", "trainer.tensorboard=false"], sub="t")
    ck_dir = Path(cfg.paths.output_dir) / "checkpoints"
    ck_dir.mkdir(parents=True)
    (ck_dir / ".last.pt.k1l2.tmp").write_bytes(pickle.dumps("half a checkpoint"))
    train(cfg)
    assert sorted(p.name for p in ck_dir.iterdir()) == ["best.pt", "last.pt"]


def test_a_kill_while_last_is_linked_to_best_leaves_no_temp_after_restart(cfg_factory, monkeypatch):
    """finish() links last.pt to best.pt through a temp file; a kill there must not leave it behind for good
    (the kill storm found `.last.pt.<pid>.link.tmp` files the start-up clean-up did not recognise)."""
    import omnidl.engine.state as state_mod
    cfg = cfg_factory(["trainer.max_steps=1", "trainer.tensorboard=false"], sub="t")
    ck_dir = Path(cfg.paths.output_dir) / "checkpoints"

    def killed_link(src, dst):
        Path(dst).write_bytes(b"")          # the temp name exists, then the process dies
        raise KeyboardInterrupt("killed between link and replace")
    monkeypatch.setattr(state_mod.os, "link", killed_link)
    monkeypatch.setattr(state_mod.os, "getpid", lambda: 424242)     # the killed process, not this one
    with pytest.raises(KeyboardInterrupt):
        train(cfg)
    assert any(p.name.endswith(".tmp") for p in ck_dir.iterdir())
    monkeypatch.undo()
    train(cfg_factory(["trainer.max_steps=1", "trainer.tensorboard=false", "trainer.resume=true"], sub="t"))
    assert sorted(p.name for p in ck_dir.iterdir()) == ["best.pt", "last.pt"]  # the resume cleaned up at start


def test_finishing_again_when_last_is_already_the_best_link_leaves_no_temp(cfg_factory):
    """rename() between two links of one file does nothing, so linking last.pt to best.pt a second time (a resumed
    finished run, or a kill after the first link) must not leave the temp link behind (found by the kill storm)."""
    cfg = cfg_factory(["trainer.max_steps=1", "trainer.tensorboard=false"], sub="t")
    ck_dir = Path(cfg.paths.output_dir) / "checkpoints"
    train(cfg)
    assert (ck_dir / "last.pt").samefile(ck_dir / "best.pt")
    with open_dict(cfg):
        cfg.trainer.resume = True
    train(cfg)
    assert sorted(p.name for p in ck_dir.iterdir()) == ["best.pt", "last.pt"]


def test_model_config_gives_the_model_kwargs_without_weight_paths():
    """The model of a train.py checkpoint: name, create_model kwargs (no _target_, weight paths dropped: the
    weights are the checkpoint's own), the run config; clear errors without a config or a model name."""
    from omnidl.engine.checkpoint import model_config

    cfg = {"model": {"_target_": "omnidl.models.create_model", "name": "holinet", "width": 0.25,
                     "pretrained": "/nowhere/resnet18.pth"}, "data": {"height": 64}}
    name, kwargs, conf = model_config({"config": cfg}, "checkpoint ck.pt", "hint")
    assert name == "holinet" and kwargs == {"width": 0.25, "pretrained": None} and conf.data.height == 64
    del cfg["model"]["name"]
    assert model_config({"config": cfg}, "ck", "hint", default_name="holinet")[0] == "holinet"
    with pytest.raises(ValueError, match=r"checkpoint ck\.pt: config\.model has no 'name'"):
        model_config({"config": cfg}, "checkpoint ck.pt", "hint")
    with pytest.raises(ValueError, match=r"checkpoint ck\.pt: no 'config' with a 'model' entry; from train\.py"):
        model_config({"model": {}}, "checkpoint ck.pt", "from train.py")
