"""Compose the real configs/ tree with the stand-in model/data/loss/metrics of engine_standins.py."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf, open_dict

from omnidl.engine.config import register_configs

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).resolve().parent))

STANDIN = {
    "model": {"_target_": "engine_standins.TinyNet", "width": 8},
    "data": {"train": {"_target_": "engine_standins.RandomPanoramas", "length": 12, "seed": 0},
             "val": {"_target_": "engine_standins.RandomPanoramas", "length": 4, "seed": 1},
             "test": {"_target_": "engine_standins.RandomPanoramas", "length": 3, "seed": 2}},
    "loss": {"_target_": "engine_standins.TinyLoss"},
    "metrics": {"_target_": "engine_standins.TinyMetrics"},
}


def make_cfg(tmp_path: Path, overrides: list[str] = (), config_name: str = "train", standin: bool = True):
    """Compose ``configs/<config_name>.yaml`` with ``overrides``; output dir ``tmp_path``; stand-ins plugged in."""
    register_configs()
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "configs"), job_name="test"):
        cfg = compose(config_name=config_name, overrides=[f"paths.output_dir={tmp_path}", "trainer.progress=false",
                                                          "trainer.num_threads=1", *overrides])
    if standin:
        with open_dict(cfg):
            for k, v in STANDIN.items():
                if cfg.get(k) is None:
                    cfg[k] = OmegaConf.create(v)
    return cfg


@pytest.fixture
def cfg_factory(tmp_path):
    def f(overrides=(), config_name="train", sub="run", standin=True):
        return make_cfg(tmp_path / sub, list(overrides), config_name, standin)
    return f
