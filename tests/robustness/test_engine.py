"""Robustness table of the training engine: bad trainer/optim configs, bad checkpoint files, resume and kill
paths, disk problems. Each row is one bad input with the verdict it must get (tests/robustness/verdicts.py)."""
from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import sys
from pathlib import Path

import pytest
import torch
import yaml
from omegaconf import OmegaConf, open_dict

from tests.robustness.verdicts import ERROR, OK, expect, row

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "engine"))
from engine_helpers import make_cfg  # noqa: E402
from engine_standins import SimulatedKill, TinyNet  # noqa: E402

from omnidl.engine import train  # noqa: E402
from omnidl.engine.checkpoint import load_checkpoint, load_model_weights  # noqa: E402

QUICK = ["trainer.max_steps=2", "trainer.tensorboard=false", "trainer.batch_size=4"]

# ---------------------------------------------------------------- bad trainer / optim configs

CONFIG_ROWS = [
    row("batch_size-0", ["trainer.batch_size=0"], verdict=ERROR, match=r"trainer\.batch_size=0: expected a positive"),
    row("batch_size-negative", ["trainer.batch_size=-2"], verdict=ERROR, match=r"trainer\.batch_size=-2: expected"),
    row("max_steps-0", ["trainer.max_steps=0"], verdict=ERROR, match=r"trainer\.max_steps=0: expected a positive.*-1"),
    row("max_steps-minus5", ["trainer.max_steps=-5"], verdict=ERROR, match=r"trainer\.max_steps=-5"),
    row("max_epochs-0", ["trainer.max_steps=-1", "trainer.max_epochs=0"], verdict=ERROR,
        match=r"trainer\.max_epochs=0: expected at least 1"),
    row("lr-nan", ["optim.lr=nan"], verdict=ERROR, match=r"optim\.lr=nan: expected a finite number"),
    row("lr-inf", ["optim.lr=inf"], verdict=ERROR, match=r"optim\.lr=inf: expected a finite number"),
    row("lr-negative", ["optim.lr=-1"], verdict=ERROR, match=r"optim\.lr=-1\.0: expected a finite number >= 0"),
    row("weight_decay-negative", ["optim.weight_decay=-0.1"], verdict=ERROR, match=r"optim\.weight_decay=-0\.1"),
    row("grad_clip-negative", ["trainer.grad_clip=-1"], verdict=ERROR, match=r"trainer\.grad_clip=-1\.0: expected"),
    row("grad_clip-nan", ["trainer.grad_clip=nan"], verdict=ERROR, match=r"trainer\.grad_clip=nan"),
    row("num_workers-negative", ["trainer.num_workers=-1"], verdict=ERROR, match=r"trainer\.num_workers=-1: expected 0"),
    row("val_every_steps-negative", ["trainer.val_every_steps=-3"], verdict=ERROR, match=r"trainer\.val_every_steps=-3"),
    row("log_every_steps-0", ["trainer.log_every_steps=0"], verdict=ERROR, match=r"trainer\.log_every_steps=0: expected 1"),
    row("val_every_minutes-negative", ["trainer.val_every_minutes=-1"], verdict=ERROR,
        match=r"trainer\.val_every_minutes=-1\.0"),
    row("ckpt_every_minutes-inf", ["trainer.ckpt_every_minutes=inf"], verdict=ERROR, match=r"trainer\.ckpt_every_minutes=inf"),
    row("max_skipped-negative", ["trainer.max_skipped=-1"], verdict=ERROR, match=r"trainer\.max_skipped=-1"),
    row("monitor_mode-typo", ["trainer.monitor_mode=maximum"], verdict=ERROR, match=r"monitor_mode='maximum'.*'min' or 'max'"),
    row("monitor-unknown", ["trainer.monitor=val/foo", "trainer.val_every_steps=1"], verdict=ERROR,
        match=r"trainer\.monitor='val/foo'.*val/loss"),
    row("device-cuda-without-gpu", ["trainer.device=cuda"], verdict=ERROR, match=r"CUDA is not available",
        marks=pytest.mark.skipif(torch.cuda.is_available(), reason="has a GPU")),
    row("unknown-trainer-key", ["trainer.max_stpes=3"], verdict=ERROR, match=r"max_stpes"),
    row("batch_size-not-a-number", ["trainer.batch_size=abc"], verdict=ERROR, match=r"abc"),
    row("lr-zero-is-allowed", ["optim.lr=0"], verdict=OK),
    row("val_max_batches-0", ["trainer.val_max_batches=0"], verdict=ERROR,
        match=r"trainer\.val_max_batches=0: expected -1 \(the whole validation set\) or a positive number"),
    row("val_max_batches-minus2", ["trainer.val_max_batches=-2"], verdict=ERROR, match=r"trainer\.val_max_batches=-2"),
]


@pytest.mark.parametrize("overrides, verdict, match", CONFIG_ROWS)
def test_bad_trainer_configs(tmp_path, overrides, verdict, match):
    out = expect(lambda: train(make_cfg(tmp_path, QUICK + overrides)), verdict, match)
    if verdict == OK:
        assert out["step"] == 2


# ---------------------------------------------------------------- bad checkpoint files


def _good(tmp: Path) -> Path:
    path = tmp / "good.pt"
    torch.save({"model": TinyNet(width=8).state_dict(), "step": 3}, path)
    return path


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def _write(name: str, make):
    def f(tmp: Path) -> Path:
        path = tmp / name
        make(path, tmp)
        return path
    return f


CKPT_ROWS = [
    row("missing", _write("none.pt", lambda p, t: None), verdict=ERROR, match=r"checkpoint .*none\.pt does not exist"),
    row("zero-byte", _write("empty.pt", lambda p, t: p.write_bytes(b"")), verdict=ERROR,
        match=r"could not read checkpoint .*empty\.pt"),
    row("truncated", _write("cut.pt", lambda p, t: p.write_bytes(_good(t).read_bytes()[:700])), verdict=ERROR,
        match=r"could not read checkpoint .*cut\.pt.*truncated"),
    row("text-file", _write("notes.pt", lambda p, t: p.write_text("not a checkpoint\n")), verdict=ERROR,
        match=r"could not read checkpoint .*notes\.pt"),
    row("pickled-list", _write("list.pt", lambda p, t: torch.save([1, 2], p)), verdict=ERROR,
        match=r"list\.pt: expected a dict, got list"),
    row("no-model-key", _write("nomodel.pt", lambda p, t: torch.save({"foo": 1}, p)), verdict=ERROR,
        match=r"nomodel\.pt: no 'model' entry"),
    row("empty-dict", _write("emptydict.pt", lambda p, t: torch.save({}, p)), verdict=ERROR,
        match=r"emptydict\.pt: an empty dict"),
    row("code-in-pickle", _write("evil.pt", lambda p, t: torch.save({"model": {}, "x": _Evil()}, p)), verdict=ERROR,
        match=r"evil\.pt: it holds Python objects.*refuses to unpickle"),
    row("model-not-a-dict", _write("modelint.pt", lambda p, t: torch.save({"model": 3}, p)), verdict=ERROR,
        match=r"modelint\.pt: 'model' is a int, expected a state dict"),
    row("other-width", _write("wide.pt", lambda p, t: torch.save({"model": TinyNet(width=16).state_dict()}, p)),
        verdict=ERROR, match=r"wide\.pt does not fit the model \(TinyNet\).*size mismatch"),
    row("foreign-model", _write("linear.pt", lambda p, t: torch.save(torch.nn.Linear(3, 2).state_dict(), p)),
        verdict=ERROR, match=r"linear\.pt does not fit the model \(TinyNet\): missing keys"),
    row("bare-state-dict", _write("bare.pt", lambda p, t: torch.save(TinyNet(width=8).state_dict(), p)), verdict=OK),
    row("lightning-style-state_dict", _write("sd.pt", lambda p, t: torch.save({"state_dict": TinyNet(width=8).state_dict()},
                                                                         p)), verdict=OK),
    row("ddp-module-prefix", _write("ddp.pt", lambda p, t: torch.save(
        {"model": {f"module.{k}": v for k, v in TinyNet(width=8).state_dict().items()}}, p)), verdict=OK),
    row("other-programs-resume-layout", _write("other.pt", lambda p, t: torch.save(
        {"model": TinyNet(width=8).state_dict(), "optimizer": {}, "epoch": 3}, p)), verdict=ERROR,
        match=r"other\.pt: has an 'optimizer' but not .*missing \['scheduler', 'step', 'batch_in_epoch'\].*keys found"),
    row("config-without-weights-entry", _write("cfgonly.pt", lambda p, t: torch.save(
        {"config": {"model": {"name": "x"}}, "net": TinyNet(width=8).state_dict()}, p)), verdict=ERROR,
        match=r"cfgonly\.pt: no 'model' entry \(keys found: \['config', 'net'\]\)"),
]


@pytest.mark.parametrize("make, verdict, match", CKPT_ROWS)
def test_bad_checkpoint_files(tmp_path, make, verdict, match):
    path = make(tmp_path)

    def load():
        model = TinyNet(width=8)
        load_model_weights(model, load_checkpoint(path), path)
        return model
    expect(load, verdict, match)


def test_a_bad_checkpoint_given_to_train_names_the_file(tmp_path):
    bad = tmp_path / "half.pt"
    bad.write_bytes(b"PK\x03\x04 not really")
    expect(lambda: train(make_cfg(tmp_path / "run", QUICK + [f"checkpoint={bad}"])), ERROR,
           r"could not read checkpoint .*half\.pt")


# ---------------------------------------------------------------- resume and kill paths

RESUME = ["trainer.batch_size=4", "trainer.log_every_steps=1", "trainer.val_every_steps=4",
          "trainer.ckpt_every_steps=2", "trainer.max_steps=8", "trainer.tensorboard=false"]


@pytest.fixture(scope="module")
def killed_run(tmp_path_factory):
    """A run killed in step 6 (last.pt from step 4, best.pt from step 4)."""
    out = tmp_path_factory.mktemp("killed") / "run"
    cfg = make_cfg(out, RESUME)
    with open_dict(cfg):
        cfg.loss.kill_at = 6
    with pytest.raises(SimulatedKill):
        train(cfg)
    return out


def _resume(killed_run: Path, tmp_path: Path, extra: list[str], prepare=None):
    """Resume a copy of ``killed_run`` with ``extra`` overrides (``@key=value``: set on the stand-in nodes after
    composition)."""
    run = tmp_path / "run"
    shutil.copytree(killed_run, run)
    if prepare:
        prepare(run)

    def go():
        cfg = make_cfg(run, RESUME + ["trainer.resume=true", *[e for e in extra if not e.startswith("@")]])
        with open_dict(cfg):
            for e in extra:
                if e.startswith("@"):
                    key, value = e[1:].split("=", 1)
                    OmegaConf.update(cfg, key, yaml.safe_load(value), force_add=True)
        return train(cfg)
    return go


def _no_best(run: Path):
    (run / "checkpoints" / "best.pt").unlink()


def _orphan_tmp(run: Path):
    (run / "checkpoints" / ".last.pt.abcd.tmp").write_bytes(b"half")


RESUME_ROWS = [
    row("changed-lr", ["optim.lr=0.5"], None, verdict=ERROR, match=r"optim\.lr: checkpoint 0\.001, now 0\.5"),
    row("changed-batch_size", ["trainer.batch_size=2"], None, verdict=ERROR,
        match=r"trainer\.batch_size: checkpoint 4, now 2.*resume_override"),
    row("changed-optimizer", ["optim=sgd"], None, verdict=ERROR, match=r"optim\.name: checkpoint 'adamw', now 'sgd'"),
    row("changed-schedule", ["sched.warmup_steps=3"], None, verdict=ERROR, match=r"sched\.warmup_steps: checkpoint 0, now 3"),
    row("changed-max_steps", ["trainer.max_steps=12"], None, verdict=ERROR, match=r"trainer\.max_steps: checkpoint 8, now 12"),
    row("changed-seed", ["trainer.seed=5"], None, verdict=ERROR, match=r"trainer\.seed: checkpoint 0, now 5"),
    row("changed-data", ["@data.train.length=20"], None, verdict=ERROR, match=r"data\.train\.length: checkpoint 12, now 20"),
    row("changed-model", ["@model.dropout=0.3"], None, verdict=ERROR, match=r"model\.dropout: checkpoint '<unset>', now 0\.3"),
    row("override-lr", ["optim.lr=0.5", "trainer.resume_override=true"], None, verdict=OK),
    row("override-batch_size", ["trainer.batch_size=2", "trainer.resume_override=true"], None, verdict=OK),
    row("unchanged-but-logging", ["trainer.log_every_steps=2", "trainer.num_workers=0", "trainer.progress=false"], None,
        verdict=OK),
    row("missing-best-same-step", [], _no_best, verdict=OK),
    row("orphan-temp-file", [], _orphan_tmp, verdict=OK),
]


@pytest.mark.parametrize("extra, prepare, verdict, match", RESUME_ROWS)
def test_resume_paths(killed_run, tmp_path, extra, prepare, verdict, match):
    out = expect(_resume(killed_run, tmp_path, extra, prepare), verdict, match, error=ValueError)
    if verdict == OK:
        ck_dir = tmp_path / "run" / "checkpoints"
        assert out["step"] == 8 and sorted(p.name for p in ck_dir.iterdir()) == ["best.pt", "last.pt"]
        steps = [json.loads(x)["step"] for x in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
        assert steps == sorted(set(steps))  # the log was cut back: no repeated steps


def test_resume_of_a_finished_lean_run_past_its_end_is_a_clear_error(tmp_path):
    train(make_cfg(tmp_path / "run", RESUME))
    expect(lambda: train(make_cfg(tmp_path / "run", RESUME + ["trainer.resume=true", "trainer.max_steps=12",
                                                               "trainer.resume_override=true"])),
           ERROR, r"last\.pt is the weights-only last\.pt of a finished run \(step 8\).*save_optimizer=true")


def test_all_corrupt_training_data_stops(tmp_path):
    cfg = make_cfg(tmp_path, QUICK + ["trainer.max_skipped=2"])
    with open_dict(cfg):
        cfg.data.train = {"_target_": "engine_standins.CorruptPanoramas", "length": 100}
    expect(lambda: train(cfg), ERROR, r"3 batches in a row skipped.*unreadable.*max_skipped=2")


# ---------------------------------------------------------------- disk and permissions

def test_full_disk_during_a_checkpoint_names_the_file(tmp_path, monkeypatch):
    import omnidl.utils.io as io

    def full(obj, f, *a, **k):
        f.write(b"x" * 10)
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(torch, "save", full)
    expect(lambda: train(make_cfg(tmp_path, QUICK)), ERROR, r"could not write .*checkpoints/(best|last)\.pt: the disk is full",
           error=OSError)
    assert not [p for p in (tmp_path / "checkpoints").iterdir() if p.name.endswith(".tmp")]
    assert io  # the module whose writes are checked


def test_checkpoint_folder_that_is_a_file(tmp_path):
    (tmp_path / "checkpoints").write_text("oops")
    expect(lambda: train(make_cfg(tmp_path, QUICK)), ERROR, r"checkpoints", error=OSError)


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600)])
def test_run_files_follow_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        train(make_cfg(tmp_path, QUICK))
    finally:
        os.umask(old)
    for name in ("checkpoints/best.pt", "checkpoints/last.pt", "metrics.json"):
        assert (tmp_path / name).stat().st_mode & 0o777 == mode, name


def test_signal_handlers_are_restored_after_training(tmp_path):
    import signal
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    train(make_cfg(tmp_path, QUICK))
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_repaired_best_is_logged(killed_run, tmp_path, caplog):
    run = _resume(killed_run, tmp_path, [], _no_best)
    with caplog.at_level(logging.WARNING, logger="omnidl.engine"):
        run()
    assert "best.pt was missing; rewrote it from" in caplog.text


# ---------------------------------------------------------------- the run folder (output policy, issue 48)

@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("finished") / "run"
    train(make_cfg(out, QUICK))
    return out


def _no_last(run: Path):
    (run / "checkpoints" / "last.pt").unlink()


def _hashes(run: Path) -> dict:
    return {p.relative_to(run).as_posix(): p.read_bytes() for p in run.rglob("*") if p.is_file()}


FOLDER_ROWS = [
    row("retrain-into-a-finished-run", [], None, verdict=ERROR,
        match=r"already holds a training run .*trainer\.resume=true.*trainer\.overwrite=true"),
    row("retrain-other-seed", ["trainer.seed=4"], None, verdict=ERROR, match=r"already holds a training run"),
    row("resume-without-last-pt", ["trainer.resume=true"], _no_last, verdict=ERROR,
        match=r"trainer\.resume=true but .* has no checkpoints/last\.pt.*trainer\.overwrite=true"),
    row("overwrite", ["@trainer.overwrite=true"], None, verdict=OK),
    row("resume-without-last-pt-overwrite", ["trainer.resume=true", "@trainer.overwrite=true"], _no_last, verdict=OK),
    row("resume-a-finished-run", ["trainer.resume=true"], None, verdict=OK),
]


@pytest.mark.parametrize("extra, prepare, verdict, match", FOLDER_ROWS)
def test_run_folder_rules(finished_run, tmp_path, extra, prepare, verdict, match):
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    if prepare:
        prepare(run)
    before = _hashes(run)
    cfg = make_cfg(run, QUICK + [e for e in extra if not e.startswith("@")])
    for e in extra:
        if e.startswith("@"):
            key, value = e[1:].split("=", 1)
            node, leaf = key.rsplit(".", 1)
            with open_dict(OmegaConf.select(cfg, node)):
                OmegaConf.update(cfg, key, yaml.safe_load(value), force_add=True)
    out = expect(lambda: train(cfg), verdict, match)
    if verdict == ERROR:
        assert _hashes(run) == before           # a refused run changes nothing
    else:
        assert out["step"] == 2 and (run / "checkpoints" / "last.pt").is_file()
