import sys
from pathlib import Path

import numpy as np
import pytest

from omnidl.classes import CLASS_ID
from omnidl.data.collate import collate_samples
from omnidl.data.structured3d import Structured3D, nyu40_lut
from omnidl.metrics.layout import corners_to_layout

sys.path.insert(0, str(Path(__file__).resolve().parent))
from adapter_fixtures import ROOMS, write_structured3d  # noqa: E402


def test_splits_depth_and_semantics(tmp_path):
    truth = write_structured3d(tmp_path)
    for split, scene in (("train", "scene_00000"), ("val", "scene_03000"), ("test", "scene_03250")):
        ds = Structured3D(tmp_path, split=split, height=None, width=None)
        assert len(ds) == 1 and ds[0]["meta"]["name"].startswith(scene)
    ds = Structured3D(tmp_path, split="train", height=None, width=None)
    s = ds[0]
    rgb, mm, sem = truth[s["meta"]["name"]]
    assert np.allclose(s["depth"][0].numpy(), mm / 1000.0, atol=1e-6)
    assert np.array_equal(s["semantic"].numpy(), nyu40_lut()[sem])
    assert np.allclose(s["image"].permute(1, 2, 0).numpy() * 255, rgb, atol=0.5)


def test_nyu40_mapping():
    lut = nyu40_lut()
    assert lut[0] == 0 and lut[1] == CLASS_ID["wall"] and lut[22] == CLASS_ID["ceiling"]
    assert lut[14] == CLASS_ID["table"] and lut[40] == CLASS_ID["clutter"] and lut[30] == CLASS_ID["board"]


def test_layout_targets(tmp_path):
    write_structured3d(tmp_path)
    ds = Structured3D(tmp_path, split="train", layout=True, depth=False, semantic=False, height=32, width=64)
    s = ds[0]
    assert "depth" not in s and s["boundary"].shape == (2, 64) and s["boundary_valid"].all()
    n = int(s["num_walls"])
    poly, h_c, h_f = corners_to_layout(s["corners_cam"][:n].double().numpy())
    k = 1.6 / -h_f                                    # layout.txt fixes the shape; the camera height the scale
    dist = np.linalg.norm((poly * k)[:, None] - ROOMS["box"][None], axis=-1).min(0)   # each true corner is found
    assert dist.max() < 0.05 and len(poly) == 4 and h_c == pytest.approx(1.2, abs=0.05)
    assert collate_samples([s, s])["corners_cam"].shape[0] == 2


@pytest.mark.parametrize("kw, match", [({"variant": "furnished"}, "variant='furnished'"),
                                       ({"light": "blue"}, "light='blue'"),
                                       ({"split": "dev"}, "unknown split 'dev'")])
def test_bad_options(tmp_path, kw, match):
    write_structured3d(tmp_path)
    with pytest.raises(ValueError, match=match):
        Structured3D(tmp_path, **kw)


def test_config(tmp_path):
    from adapter_fixtures import instantiate_split
    write_structured3d(tmp_path / "d")
    ds = instantiate_split(tmp_path, "structured3d", tmp_path / "d", "val", ["data.height=16", "data.width=32"])
    assert len(ds) == 1 and ds[0]["image"].shape == (3, 16, 32)
