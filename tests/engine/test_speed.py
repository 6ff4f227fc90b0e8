"""PyTorch's own speed tools in the engine: ``trainer.num_threads`` (``auto`` from the machine's load, or an
int) and ``trainer.compile`` (torch.compile/Inductor for the training step; checkpoints stay plain)."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf, open_dict

import omnidl.engine.seed as seed_mod
import omnidl.utils.threads as threads
from engine_standins import SimulatedKill
from omnidl.engine import evaluate, train
from omnidl.engine.checkpoint import load_checkpoint
from omnidl.engine.compile import CompileTimer, CompileUnavailable, inductor_problem
from omnidl.engine.config import check_num_threads, check_trainer_config

from .engine_helpers import STANDIN, make_cfg


@pytest.fixture
def keep_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def _load(monkeypatch, runnable: float, cpus: int = 2, default: int = 2):
    monkeypatch.setattr(threads, "runnable_tasks", lambda: runnable)
    monkeypatch.setattr(threads, "usable_cpus", lambda: cpus)
    monkeypatch.setattr(seed_mod, "_INITIAL_THREADS", default)


# ----------------------------------------------------------------------------------------------- threads
def test_auto_threads_use_every_thread_on_an_idle_machine(monkeypatch, caplog, keep_threads):
    _load(monkeypatch, runnable=1.0)                     # only this process's own thread is running
    with caplog.at_level(logging.INFO, logger="omnidl.engine"):
        n = seed_mod.seed_everything(0, "auto")
    assert n == 2 and torch.get_num_threads() == 2
    assert "trainer.num_threads=auto: 2 intra-op threads (load: 1 runnable tasks" in caplog.text


def test_auto_threads_fall_back_on_a_busy_machine(monkeypatch, caplog, keep_threads):
    _load(monkeypatch, runnable=4.0)                     # the 2-core machine at load ~4 of issue 47
    with caplog.at_level(logging.INFO, logger="omnidl.engine"):
        assert seed_mod.resolve_num_threads("auto") == 1
    assert "1 intra-op thread (load: 4 runnable tasks, so 3 besides this process, on 2 usable CPUs" in caplog.text
    _load(monkeypatch, runnable=2.0)                     # one other task: one CPU left for this process
    assert seed_mod.resolve_num_threads("auto") == 1
    _load(monkeypatch, runnable=4.0, cpus=8, default=8)  # a bigger machine, partly busy: one per free CPU
    assert seed_mod.resolve_num_threads("auto") == 5
    _load(monkeypatch, runnable=30.0, cpus=8, default=8)
    assert seed_mod.resolve_num_threads("auto") == 1


def test_auto_threads_on_this_machine_is_a_positive_count(keep_threads):
    n, basis = seed_mod.auto_num_threads(samples=2, interval_s=0.01)
    assert isinstance(n, int) and 1 <= n <= max(1, seed_mod._INITIAL_THREADS)
    assert basis["runnable"] >= 0 and basis["cpus"] >= 1


def test_int_threads_keep_working(keep_threads):
    assert seed_mod.resolve_num_threads(2) == 2 and seed_mod.resolve_num_threads("3") == 3
    assert seed_mod.resolve_num_threads(0) == seed_mod._INITIAL_THREADS
    seed_mod.seed_everything(0, 1)
    assert torch.get_num_threads() == 1


@pytest.mark.parametrize("bad", ["many", -1, 1.5, True, "", None])
def test_bad_thread_values_are_refused_naming_the_field(bad):
    with pytest.raises(ValueError, match=r"trainer\.num_threads=.*expected 'auto'.*0 \(torch's default\)"):
        check_num_threads(bad)
    with pytest.raises(ValueError, match=r"trainer\.num_threads="):
        check_trainer_config(OmegaConf.create({**_trainer_defaults(), "num_threads": bad}))


def _trainer_defaults() -> dict:
    from omnidl.engine.config import TrainerConfig
    return OmegaConf.to_container(OmegaConf.structured(TrainerConfig))


def test_the_schema_takes_auto_and_ints(tmp_path):
    from hydra import compose, initialize_config_dir

    from omnidl.engine.config import register_configs

    from .engine_helpers import ROOT
    register_configs()
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "configs"), job_name="t"):
        default = compose(config_name="train", overrides=[f"paths.output_dir={tmp_path}"])
        small = compose(config_name="train", overrides=[f"paths.output_dir={tmp_path}", "experiment=fredsnet_small"])
        ev = compose(config_name="evaluate", overrides=[f"paths.output_dir={tmp_path}", "trainer.num_threads=2"])
    assert default.trainer.num_threads == "auto" and default.trainer.compile is False
    assert small.trainer.num_threads == 2 and ev.trainer.num_threads == 2
    for cfg in (default, small, ev):
        check_trainer_config(cfg.trainer, cfg.optim)
    for value, expected in (("auto", "auto"), ("0", 0), ("3", 3)):
        assert make_cfg(tmp_path, [f"trainer.num_threads={value}"]).trainer.num_threads == expected


def test_train_and_evaluate_refuse_a_bad_thread_count(cfg_factory):
    with pytest.raises(ValueError, match=r"trainer\.num_threads='fast': expected"):
        train(cfg_factory(["trainer.max_steps=1", "trainer.num_threads=fast"]))
    with pytest.raises(ValueError, match=r"trainer\.num_threads=-2: expected"):
        evaluate(cfg_factory(["trainer.num_threads=-2"], config_name="evaluate", sub="ev"))


def test_training_with_auto_threads_logs_the_choice(cfg_factory, caplog, monkeypatch, keep_threads):
    _load(monkeypatch, runnable=3.5)
    with caplog.at_level(logging.INFO, logger="omnidl.engine"):
        train(cfg_factory(["trainer.max_steps=1", "trainer.tensorboard=false", "trainer.num_threads=auto"]))
    assert "trainer.num_threads=auto: 1 intra-op thread" in caplog.text and torch.get_num_threads() == 1


# ----------------------------------------------------------------------------------------------- compile
def test_compile_is_refused_where_inductor_cannot_run(cfg_factory, monkeypatch):
    import omnidl.engine.compile as comp
    monkeypatch.setattr(comp, "inductor_problem", lambda device: "Python 3.99 not yet supported")
    with pytest.raises(CompileUnavailable, match=r"trainer\.compile=true: torch\.compile with Inductor is not "
                       r"available .*Python 3\.99 not yet supported\. Set trainer\.compile=false"):
        train(cfg_factory(["trainer.max_steps=1", "trainer.compile=true"]))


def test_a_missing_cpp_compiler_is_found(monkeypatch):
    import torch._inductor.cpp_builder as cpp_builder

    def no_compiler():
        raise RuntimeError("Could not find a C++ compiler")
    monkeypatch.setattr(cpp_builder, "get_cpp_compiler", no_compiler)
    assert "C++ compiler" in inductor_problem("cpu")


def test_compile_timer_reports_the_first_steps_extra_time(caplog, monkeypatch):
    clock = iter([0.0, 12.7, 20.0, 20.4])               # step 1: 12.7 s, step 2: 0.4 s
    monkeypatch.setattr("omnidl.engine.compile.time.perf_counter", lambda: next(clock))
    timer = CompileTimer(torch.device("cpu"))
    with caplog.at_level(logging.INFO, logger="omnidl.engine"):
        for _ in range(2):
            timer.start()
            timer.stop(ran=True)
        timer.finish()
    assert timer.compile_s == pytest.approx(12.3) and not timer.enabled
    assert caplog.text.count("compiled the model in 12.3 s") == 1 and "first training step took 12.7 s" in caplog.text
    caplog.clear()
    clock = iter([0.0, 0.02, 1.0, 1.02])                # already compiled in this process: nothing to report
    timer = CompileTimer(torch.device("cpu"))
    with caplog.at_level(logging.INFO, logger="omnidl.engine"):
        for _ in range(2):
            timer.start()
            timer.stop(ran=True)
    assert "no compile time to report" in caplog.text and "compiled the model in" not in caplog.text
    caplog.clear()
    clock = iter([0.0, 9.0])                            # a one-step run: an upper bound
    timer = CompileTimer(torch.device("cpu"))
    with caplog.at_level(logging.INFO, logger="omnidl.engine"):
        timer.start()
        timer.stop(ran=True)
        timer.finish()
    assert "compiled the model in at most 9.0 s" in caplog.text


#: a tiny registered model (one-level U-Net) on the built-in synthetic panoramas, 32x16
UNET = ["model=unet", "model.base_channels=4", "model.levels=1", "data=synthetic_pano", "camera=equirect",
        "data.width=32", "data.height=16", "data.train_length=6", "data.val_length=2", "data.test_length=2",
        "trainer.batch_size=2", "trainer.tensorboard=false", "viz=none", "trainer.log_every_steps=1"]

needs_inductor = pytest.mark.skipif(inductor_problem("cpu") is not None, reason="torch.compile/Inductor unavailable")


@pytest.mark.slow
@needs_inductor
def test_compiled_training_keeps_plain_checkpoints(tmp_path, caplog):
    from omnidl.engine.build import build_model
    cfg = make_cfg(tmp_path / "c", UNET + ["trainer.max_steps=3", "trainer.compile=true"], standin=False)
    with caplog.at_level(logging.INFO, logger="omnidl.engine"):
        summary = train(cfg)
    assert summary["step"] == 3 and torch.isfinite(torch.tensor(summary["best"]))
    assert "the training step runs torch.compile(model)" in caplog.text
    assert "compiled the model in " in caplog.text or "no compile time to report" in caplog.text
    ck = load_checkpoint(summary["checkpoint_last"])
    plain = build_model(cfg)
    assert list(ck["model"]) == list(plain.state_dict())               # same keys, no _orig_mod. prefix
    plain.load_state_dict(ck["model"])                                  # strict
    best = load_checkpoint(summary["checkpoint_best"])["model"]
    assert all(torch.equal(best[k], v) for k, v in plain.state_dict().items())


@pytest.mark.slow
@needs_inductor
def test_compiled_training_resumes_exactly(tmp_path):
    """Killed during step 5 (last.pt from step 4, mid-epoch), resumed with compile: the loss curve of an
    uninterrupted compiled run, bit for bit."""
    # the model and batch shapes of the test above (32x16, batch 2): run after it, the compiled graphs are reused
    over = ["model=unet", "model.base_channels=4", "model.levels=1", "viz=none", "trainer.batch_size=2",
            "trainer.max_steps=6", "trainer.tensorboard=false", "trainer.log_every_steps=1",
            "trainer.ckpt_every_steps=2", "trainer.val_every_steps=3", "trainer.compile=true"]

    def cfg(sub, extra=(), kill=0):
        c = make_cfg(tmp_path / sub, over + list(extra), standin=False)
        with open_dict(c):
            for k in ("data", "loss", "metrics"):                       # stand-in data, loss with kill_at
                c[k] = OmegaConf.create(STANDIN[k])
            c.loss.kill_at = kill
        return c

    def losses(out: str) -> dict[int, float]:
        return {r["step"]: r["loss"] for r in map(json.loads, (Path(out) / "train_log.jsonl").read_text().splitlines())}

    ref = train(cfg("ref"))
    with pytest.raises(SimulatedKill):
        train(cfg("killed", kill=5))
    ck = load_checkpoint(tmp_path / "killed" / "checkpoints" / "last.pt")
    assert (ck["step"], ck["batch_in_epoch"]) == (4, 4) and not any("_orig_mod" in k for k in ck["model"])
    resumed = train(cfg("killed", ["trainer.resume=true"]))
    assert resumed["step"] == 6 and losses(resumed["output_dir"]) == losses(ref["output_dir"])
