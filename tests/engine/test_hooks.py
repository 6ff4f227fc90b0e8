"""The configured post-processing hooks run before the metrics, in validation as in evaluation."""
import csv
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf, open_dict

import engine_standins
from omnidl.engine import evaluate, train
from omnidl.engine.hooks import ConfiguredHooks

HOOK = "engine_test_scaled_depth"


@pytest.fixture
def hook():
    from omnidl.postprocess.registry import _HOOKS, register_hook
    if HOOK not in _HOOKS:
        register_hook(HOOK)(engine_standins.scaled_depth_hook)
    engine_standins.HOOK_CALLS.clear()
    return engine_standins.HOOK_CALLS


def _with_hook_metrics(cfg):
    with open_dict(cfg):
        cfg.metrics = OmegaConf.create({"tiny": {"_target_": "engine_standins.TinyMetrics"},
                                        "hooked": {"_target_": "engine_standins.HookMetrics"}})
    return cfg


def test_configured_hooks_from_config():
    cfg = OmegaConf.create({"postprocess": "a, b", "postprocess_options": {"a": {"x": 1, "export_dir": "/o"}}})
    hooks = ConfiguredHooks.from_config(cfg)
    assert hooks.names == ("a", "b") and hooks.options == {"a": {"x": 1, "export_dir": "/o"}}
    assert not ConfiguredHooks.from_config(OmegaConf.create({})) and bool(hooks)
    out = {"depth": torch.ones(1)}
    assert ConfiguredHooks().run(out, {}) == (out, {})


def test_validation_runs_the_hooks_before_the_metrics(cfg_factory, hook, tmp_path):
    cfg = _with_hook_metrics(cfg_factory(["trainer.max_steps=2", "trainer.batch_size=2", "trainer.tensorboard=false",
                                          f"postprocess=[{HOOK}]",
                                          f"+postprocess_options.{HOOK}.scale=3.0",
                                          f"+postprocess_options.{HOOK}.export_dir={tmp_path / 'exports'}"]))
    summary = train(cfg)
    final = summary["final"]
    assert final["val/scaled_depth"] > 0 and {"val/mae", "val/acc"} <= set(final)
    # one validation (at the last step) of 4 samples in batches of 2: the options, but no file exports
    assert hook == [{"scale": 3.0, "export_dir": None}] * 2


def test_evaluation_metrics_read_hook_results(cfg_factory, hook, tmp_path):
    trained = train(cfg_factory(["trainer.max_steps=1", "trainer.tensorboard=false"], sub="train"))["checkpoint_best"]
    hook.clear()
    exports = str(tmp_path / "exports")
    cfg = _with_hook_metrics(cfg_factory([f"checkpoint={trained}", f"postprocess={HOOK}",
                                          f"+postprocess_options.{HOOK}.scale=2.0",
                                          f"+postprocess_options.{HOOK}.export_dir={exports}",
                                          "eval.rotation_deg=[0,10]", "eval.save_images=0",
                                          "eval.save_pointclouds=0"], config_name="evaluate", sub="eval"))
    res = evaluate(cfg)
    assert res["metrics"]["scaled_depth"] > 0 and res["rotation"]["10"]["scaled_depth"] > 0
    # 3 test images, batch size 1: the unrotated pass exports, the rotated pass does not
    assert [c["export_dir"] for c in hook] == [exports] * 3 + [None] * 3
    rows = list(csv.DictReader(open(Path(cfg.paths.output_dir) / "per_image.csv")))
    # per-image metrics see the hook results of their own image
    assert sum(float(r["scaled_depth"]) for r in rows) / 3 == pytest.approx(res["metrics"]["scaled_depth"])
