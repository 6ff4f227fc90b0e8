"""Every configs/camera/*.yaml builds (with build() and hydra's instantiate) and is self-consistent."""
from pathlib import Path

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from omnidl.cameras import Camera, build

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs" / "camera"
CONFIGS = sorted(CONFIG_DIR.glob("*.yaml"))


def test_configs_exist():
    names = {p.stem for p in CONFIGS}
    for want in ["equirect", "equirect_256", "pinhole", "fisheye_equiangular", "fisheye_stereographic",
                 "fisheye_orthogonal", "fisheye_equisolid", "catadioptric_para", "catadioptric_hyper", "unified",
                 "kb_opencv", "kb_f165", "kb_f195", "scaramuzza"]:
        assert want in names


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_config_builds_and_round_trips(path):
    cfg = OmegaConf.load(path)
    cam = build(cfg)
    assert isinstance(cam, Camera) and cam.name == cfg.type
    assert instantiate(cfg) == cam
    assert build(cam.to_config()) == cam
    uv = cam.pixel_grid(torch.float64)[::17, ::23].reshape(-1, 2)
    rays = cam.unproject(uv)
    assert rays.valid.any()
    uv = uv[rays.valid]
    pts = rays.at(torch.full(rays.valid.shape, 2.5, dtype=torch.float64))[rays.valid]
    uv2, valid = cam.project(pts)
    assert valid.all() and (uv2 - uv).abs().max() < 1e-8
