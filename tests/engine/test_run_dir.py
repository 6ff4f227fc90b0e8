"""The output policy of train/evaluate (omnidl/engine/run_dir.py, omnidl.utils.outputs): issue 48's examples.

Each test is the regression test of one example of the issue; on the code before the policy they fail (the
second run silently replaces the first one's files, the resume restarts, evaluate replaces metrics.json ...).
"""
import hashlib
import json
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import open_dict

from omnidl.engine import evaluate, train

QUICK = ["trainer.max_steps=2", "trainer.tensorboard=false"]


def _digest(folder: Path) -> dict[str, str]:
    """sha1 of every file under ``folder`` (relative path -> hash)."""
    return {p.relative_to(folder).as_posix(): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _overwrite(cfg, value=True):
    """``trainer.overwrite=true`` (set after composition while the schema has no such key)."""
    with open_dict(cfg.trainer):
        cfg.trainer.overwrite = value
    return cfg


@pytest.fixture
def finished(cfg_factory):
    """A finished run in ``<tmp>/run`` and the hashes of its files."""
    cfg = cfg_factory(QUICK, sub="run")
    train(cfg)
    out = Path(cfg.paths.output_dir)
    return out, _digest(out)


def test_training_again_into_a_finished_run_is_refused_and_changes_nothing(cfg_factory, finished):
    out, before = finished
    with pytest.raises(Exception, match=r"already holds a training run .*checkpoints/last\.pt.*trainer\.resume=true.*"
                                        r"trainer\.overwrite=true"):
        train(cfg_factory(QUICK + ["trainer.seed=3"], sub="run"))
    assert _digest(out) == before


def test_overwrite_replaces_a_finished_run(cfg_factory, finished):
    out, before = finished
    summary = train(_overwrite(cfg_factory(QUICK + ["trainer.seed=3"], sub="run")))
    after = _digest(out)
    assert summary["step"] == 2 and after["checkpoints/last.pt"] != before["checkpoints/last.pt"]
    steps = [json.loads(x)["step"] for x in (out / "train_log.jsonl").read_text().splitlines()]
    assert steps == sorted(set(steps))        # one run's log, not two appended


def test_resume_without_last_pt_in_a_used_folder_stops(cfg_factory, finished):
    out, _ = finished
    (out / "checkpoints" / "last.pt").unlink()
    before = _digest(out)
    with pytest.raises(Exception, match=r"trainer\.resume=true but .* has no checkpoints/last\.pt.*previous run's files"):
        train(cfg_factory(QUICK + ["trainer.resume=true"], sub="run"))
    assert _digest(out) == before


def test_resume_in_an_empty_chosen_folder_still_starts_from_scratch(cfg_factory):
    assert train(cfg_factory(QUICK + ["trainer.resume=true"], sub="fresh"))["step"] == 2


def test_starting_from_another_checkpoint_into_a_used_folder_is_refused(cfg_factory, finished, tmp_path):
    out, before = finished
    other = tmp_path / "other.pt"
    torch.save(torch.load(out / "checkpoints" / "best.pt", weights_only=True), other)
    with pytest.raises(Exception, match=r"starting from checkpoint=.*other\.pt here would overwrite"):
        train(cfg_factory(QUICK + [f"checkpoint={other}"], sub="run"))
    assert _digest(out) == before


def test_evaluate_into_a_training_folder_keeps_its_metrics_and_config(cfg_factory, finished):
    out, _ = finished
    (out / ".hydra").mkdir()
    (out / ".hydra" / "config.yaml").write_text("trainer: {max_steps: 2}\n")
    before = _digest(out)
    cfg = cfg_factory([f"checkpoint={out / 'checkpoints' / 'best.pt'}", "eval.save_images=1"],
                      config_name="evaluate", sub="run")
    res = evaluate(cfg)
    after = _digest(out)
    assert {k: after[k] for k in before} == before           # nothing of the training run changed
    assert Path(res["output_dir"]) == out / "eval_best_test" and (out / "eval_best_test" / "metrics.json").is_file()


def test_evaluate_again_into_the_same_folder_needs_overwrite(cfg_factory, finished):
    out, _ = finished
    ck = out / "checkpoints" / "best.pt"
    cfg = cfg_factory([f"checkpoint={ck}", "eval.save_images=1"], config_name="evaluate", sub="ev")
    evaluate(cfg)
    before = _digest(Path(cfg.paths.output_dir))
    with pytest.raises(Exception, match=r"already holds an evaluation \(metrics\.json.*trainer\.overwrite=true"):
        evaluate(cfg)
    assert _digest(Path(cfg.paths.output_dir)) == before
    assert evaluate(_overwrite(cfg))["num_images"] == 3


def test_evaluation_pictures_never_replace_a_file_of_the_data_folder(cfg_factory, finished, tmp_path):
    """paths.output_dir = data.root: a ground truth named like a prediction is kept (not even with overwrite)."""
    out, _ = finished
    data = tmp_path / "data"
    (data / "predictions").mkdir(parents=True)
    gt = data / "predictions" / "sample_000_depth.png"
    gt.write_bytes(b"ground truth")
    cfg = _overwrite(cfg_factory([f"checkpoint={out / 'checkpoints' / 'best.pt'}", "eval.save_images=1"],
                                 config_name="evaluate", sub="data"))
    with open_dict(cfg):
        cfg.data.root = str(data)
    with pytest.raises(Exception, match=r"sample_000_depth\.png already exists inside the input folder"):
        evaluate(cfg)
    assert gt.read_bytes() == b"ground truth"


def test_val_max_batches_0_is_refused_up_front(cfg_factory):
    cfg = cfg_factory(QUICK + ["trainer.val_max_batches=0"], sub="v")
    with pytest.raises(ValueError, match=r"trainer\.val_max_batches=0: expected -1 .* or a positive number"):
        train(cfg)
    assert not (Path(cfg.paths.output_dir) / "checkpoints").exists()   # refused before any training


def test_a_second_process_on_the_same_folder_stops(cfg_factory):
    from omnidl.utils.outputs import RunLock
    cfg = cfg_factory(QUICK, sub="busy")
    with RunLock(cfg.paths.output_dir, "training run"):
        with pytest.raises(RuntimeError, match=r"is in use by another training run: pid \d+ on host"):
            train(cfg)
    assert train(cfg)["step"] == 2        # released: the folder is free again


def test_a_live_trainers_temp_files_are_not_deleted_by_another_start(cfg_factory, tmp_path):
    """Two trainers in one folder: the starting one removed `.last.pt.*.tmp` of the other's write in progress."""
    cfg = cfg_factory(QUICK, sub="t")
    ck = Path(cfg.paths.output_dir) / "checkpoints"
    ck.mkdir(parents=True)
    host = re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())     # as omnidl.utils.io.this_host writes it
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        other = ck / f".last.pt.{sleeper.pid}@{host}.abc123.tmp"   # a write of a live process
        other.write_bytes(b"in progress")
        dead = ck / f".best.pt.{2**22 + 17}@{host}.abc123.tmp"     # a dead writer's orphan
        dead.write_bytes(b"orphan")
        train(cfg)
        assert other.read_bytes() == b"in progress" and not dead.exists()
    finally:
        sleeper.kill()
        sleeper.wait()


def test_temp_names_are_unique_per_process(tmp_path, monkeypatch):
    from omnidl.utils.io import atomic_write

    names = []
    atomic_write(tmp_path / "last.pt", lambda tmp: (names.append(Path(tmp).name), Path(tmp).write_bytes(b"x")))
    assert names[0].startswith(f".last.pt.{os.getpid()}@")


def test_a_checkpoint_of_another_layout_names_the_file_and_its_keys(cfg_factory, tmp_path):
    from engine_standins import TinyNet
    foreign = tmp_path / "foreign.pt"
    torch.save({"model": TinyNet().state_dict(), "optimizer": {"state": {}, "param_groups": []}, "epoch": 4}, foreign)
    with pytest.raises(RuntimeError, match=r"foreign\.pt: has an 'optimizer' but not .*missing \['scheduler', 'step'.*"
                                           r"keys found: \['epoch', 'model', 'optimizer'\]"):
        train(cfg_factory(QUICK + [f"checkpoint={foreign}"], sub="f"))
    config_only = tmp_path / "config_only.pt"
    torch.save({"config": {"model": {"name": "x"}}, "weights": TinyNet().state_dict()}, config_only)
    with pytest.raises(RuntimeError, match=r"config_only\.pt: no 'model' entry \(keys found: \['config', 'weights'\]\)"):
        evaluate(cfg_factory([f"checkpoint={config_only}"], config_name="evaluate", sub="e"))


def test_prepare_argv_keeps_an_existing_runs_hydra_files(tmp_path, monkeypatch):
    from omnidl.engine.launch import prepare_argv
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    run = tmp_path / "run"
    assert prepare_argv(["evaluate.py", f"hydra.run.dir={run}"], task="evaluate") == ["evaluate.py",
                                                                                      f"hydra.run.dir={run}"]
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text("x: 1\n")
    argv = prepare_argv(["evaluate.py", f"hydra.run.dir={run}"], task="evaluate")
    assert argv[-1].startswith("hydra.output_subdir=.hydra/evaluate-") and argv[-1].endswith(f"_{os.getpid()}")
    mine = ["train.py", f"hydra.run.dir={run}", "hydra.output_subdir=mine"]
    assert prepare_argv(list(mine)) == mine
