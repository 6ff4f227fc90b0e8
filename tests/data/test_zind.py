import json
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from omnidl.data.collate import collate_samples
from omnidl.data.zind import ZInD
from omnidl.metrics.layout import corners_to_layout

sys.path.insert(0, str(Path(__file__).resolve().parent))
from adapter_fixtures import ROOMS, write_zind  # noqa: E402


def _room(s):
    n = int(s["num_walls"])
    return corners_to_layout(s["corners_cam"][:n].double().numpy())


def test_reads_split_rooms_in_metres(tmp_path):
    truth = write_zind(tmp_path, metres_per_unit=1.5)
    ds = ZInD(tmp_path, split="train", height=32, width=64)
    assert len(ds) == 6
    for i in range(len(ds)):
        s = ds[i]
        poly0, ch, ceil = truth[s["meta"]["name"]]
        poly, h_c, h_f = _room(s)
        assert np.allclose(poly, poly0, atol=1e-5) and h_f == pytest.approx(-ch, abs=1e-6)
        assert h_c == pytest.approx(ceil, abs=1e-6) and s["meta"]["metric"] is True
        assert s["boundary_valid"].all() and s["meta"]["layout"] == "visible"
    assert len(ZInD(tmp_path, split="test", height=32, width=64)) == 3
    assert collate_samples([ds[0], ds[1]])["corners_cam"].shape == (2, 32, 2, 3)


def test_camera_height_scale_and_missing_floor_scale(tmp_path):
    write_zind(tmp_path, metres_per_unit=1.5, houses=("0000",))
    s = ZInD(tmp_path, split="train", scale="camera_height", camera_height=1.6, height=32, width=64)[0]
    poly, h_c, h_f = _room(s)
    assert h_f == pytest.approx(-1.6, abs=1e-6) and np.allclose(poly, ROOMS["box"] * 1.6 / 1.5, atol=1e-5)
    assert s["meta"]["metric"] is False
    data = json.loads((tmp_path / "0000" / "zind_data.json").read_text())
    data["scale_meters_per_coordinate"]["floor_01"] = None                    # allowed by the spec
    (tmp_path / "0000" / "zind_data.json").write_text(json.dumps(data))
    s = ZInD(tmp_path, split="train", height=32, width=64)[0]
    assert s["meta"]["metric"] is False and float(s["camera_height"]) == pytest.approx(1.6)


def test_axes_follow_zind_spherical_convention(tmp_path):
    """ZInD's azimuth of a local vertex is atan2(-x, y); omnidl must put the corner in that column."""
    from omnidl.cameras import Equirectangular
    write_zind(tmp_path, houses=("0000",))
    data = json.loads((tmp_path / "0000" / "zind_data.json").read_text())
    ds = ZInD(tmp_path, split="train", height=32, width=64)
    pano = data["merger"]["floor_01"]["complete_room_03"]["partial_room_03"]["pano_3"]
    v = np.asarray(pano["layout_visible"]["vertices"])
    theta = np.arctan2(-v[:, 0], v[:, 1])
    phi = np.arctan2(-1.0, np.hypot(v[:, 0], v[:, 1]))                       # floor, camera height 1
    s = ds[2]
    uv, _ = Equirectangular(width=64, height=32).project(s["corners_cam"][: len(v), 1].double())
    assert np.allclose(uv[:, 0].numpy(), (theta + math.pi) / (2 * math.pi) * 64, atol=1e-4)
    assert np.allclose(uv[:, 1].numpy(), (math.pi / 2 - phi) / math.pi * 32, atol=1e-4)


@pytest.mark.parametrize("layout", ["complete", "raw"])
def test_layout_choice(tmp_path, layout):
    write_zind(tmp_path, houses=("0000",))
    data = json.loads((tmp_path / "0000" / "zind_data.json").read_text())
    pano = data["merger"]["floor_01"]["complete_room_01"]["partial_room_01"]["pano_1"]
    pano[f"layout_{layout}"]["vertices"] = (np.asarray(pano[f"layout_{layout}"]["vertices"]) * 2).tolist()
    (tmp_path / "0000" / "zind_data.json").write_text(json.dumps(data))
    a = ZInD(tmp_path, split="train", layout="visible", height=32, width=64)[0]
    b = ZInD(tmp_path, split="train", layout=layout, height=32, width=64)[0]
    assert np.allclose(_room(b)[0], 2 * _room(a)[0], atol=1e-5)


def test_filters_and_left_out_panoramas_warn(tmp_path):
    write_zind(tmp_path, houses=("0000",))
    path = tmp_path / "0000" / "zind_data.json"
    data = json.loads(path.read_text())
    rooms = data["merger"]["floor_01"]
    rooms["complete_room_01"]["partial_room_01"]["pano_1"]["is_inside"] = False
    del rooms["complete_room_02"]["partial_room_02"]["pano_2"]["layout_visible"]
    rooms["complete_room_03"]["partial_room_03"]["pano_3"]["is_primary"] = False
    path.write_text(json.dumps(data))
    with pytest.warns(UserWarning, match=r"left out 2 panorama.*is_inside = false.*no layout_visible"):
        ds = ZInD(tmp_path, split="train", height=32, width=64)
    assert len(ds) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(FileNotFoundError, match="no usable panoramas"):
            ZInD(tmp_path, split="train", primary_only=True)
    (tmp_path / "room_shape_simplicity_labels.json").write_text(json.dumps({"0000_floor_01_partial_room_03_pano_3": True}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert len(ZInD(tmp_path, split="train", simple_only=True, height=32, width=64)) == 1


def test_all_houses_without_split(tmp_path):
    write_zind(tmp_path)
    (tmp_path / "zind_partition.json").unlink()
    assert len(ZInD(tmp_path, split=None, height=32, width=64)) == 6
    assert len(ZInD(tmp_path, houses=["0001"], height=32, width=64)) == 3


@pytest.mark.slow
def test_train_and_evaluate_end_to_end(tmp_path):
    from test_pano_annotator import train_and_evaluate
    write_zind(tmp_path / "data", w=128, h=64)
    res = train_and_evaluate("zind", tmp_path / "data", tmp_path)
    assert res["num_images"] == 3 and {"gt_skipped", "iou_2d", "layout_fail_rate"} <= set(res["metrics"])
    assert all(math.isfinite(v) for v in res["metrics"].values())


@pytest.mark.parametrize("split", ["train", "val", "test"])
def test_config(tmp_path, split):
    from adapter_fixtures import instantiate_split
    write_zind(tmp_path / "d")
    ds = instantiate_split(tmp_path, "zind", tmp_path / "d", split, ["data.height=16", "data.width=32"])
    assert len(ds) == (6 if split == "train" else 3) and ds[0]["image"].shape == (3, 16, 32)
