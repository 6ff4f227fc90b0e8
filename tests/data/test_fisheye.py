"""Fisheye/perspective views rendered from panoramas (thesis §7.4): closed-form panorama, valid circle,
calibration files, size checks, radius map."""
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from omnidl.cameras import resolve_camera
from omnidl.cameras.kannala_brandt import KannalaBrandt
from omnidl.data.fisheye import (FisheyeFromPanoramas, PerspectiveFromPanoramas, principal_point,
                                 radius_map)
from omnidl.geometry import euler_to_matrix

_spec = importlib.util.spec_from_file_location(
    "fisheye_panorama_standin", Path(__file__).resolve().parent / "panorama_standin.py")
standin = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(standin)

F195_VALUES = [540, 480, 287, 287, 1080, 960, 195, 3.37012024344156e-19, -3.543830680552053e-05,
               9.999999999924497e-08, -6.883696004705416e-11]


@pytest.fixture(autouse=True)
def _one_thread(single_thread):
    yield


@pytest.fixture(scope="module")
def panos():
    return standin.StandInPanoramas(n=2, width=256, height=128)


def write_calib(path, values):
    path.write_text("\n".join(repr(float(v)) for v in values) + "\n")
    return path


def test_reference_calibration_file_loads_directly(tmp_path):
    path = write_calib(tmp_path / "fisheye_calibration_FOV195.txt", F195_VALUES)
    cam = resolve_camera(str(path))
    ref = resolve_camera("kb_f195")
    assert cam == ref
    small = resolve_camera(str(path), 72, 64, check_aspect=True)
    assert (small.width, small.height) == (72, 64)


def test_calibration_errors_are_clear(tmp_path, panos):
    bad = write_calib(tmp_path / "short.txt", F195_VALUES[:10])
    with pytest.raises(ValueError, match=r"short\.txt.*expected 11 values"):
        FisheyeFromPanoramas(str(bad), panoramas=panos)
    nonmono = write_calib(tmp_path / "nonmono.txt", F195_VALUES[:7] + [-0.5, 0, 0, 0])
    with pytest.raises(ValueError, match="not increasing"):
        FisheyeFromPanoramas(str(nonmono), panoramas=panos)
    good = write_calib(tmp_path / "good.txt", F195_VALUES)
    with pytest.raises(ValueError, match="64x64.*disagrees with the calibration.*1080x960"):
        FisheyeFromPanoramas(str(good), width=64, height=64, panoramas=panos)
    with pytest.raises(FileNotFoundError, match="missing.txt"):
        resolve_camera(str(tmp_path / "missing.txt"))


def test_fisheye_views_match_the_closed_form_scene(panos):
    ds = FisheyeFromPanoramas("kb_f195", width=72, height=64, panoramas=panos, views_per_panorama=3, seed=3,
                              split="test", max_pitch_deg=60)
    assert len(ds) == 6
    cam = ds.camera
    rays = cam.unproject_grid(dtype=torch.float64)
    for i in (0, 4):
        s = ds[i]
        assert s["image"].shape == (3, 64, 72) and s["depth"].shape == (1, 64, 72) and s["semantic"].shape == (64, 72)
        R = euler_to_matrix(s["meta"]["roll"], s["meta"]["pitch"], s["meta"]["yaw"]).double()
        torch.testing.assert_close(s["rotation"].double(), R, atol=1e-6, rtol=0)
        d = rays.direction @ R.T          # ray in the panorama frame
        lat = standin.lat_of(d)
        inside = rays.valid & (lat < standin.CAP_LAT - 0.05)
        outside = ~rays.valid | (lat > standin.CAP_LAT + 0.05)
        v = s["valid"]
        assert bool(v[inside].all()) and not bool(v[outside].any())
        assert bool((s["depth"][0][~v] == 0).all()) and bool((s["semantic"][~v] == 0).all())
        # depth is the range of the ray (nearest panorama pixel: error < |grad| * half a pixel)
        err = (s["depth"][0].double() - standin.depth_of(d))[v].abs()
        assert float(err.max()) < 0.04
        agree = (s["semantic"] == standin.label_of(d))[v].double().mean()
        assert float(agree) > 0.95
        # pixels outside the image circle are black
        assert float(s["image"][:, ~rays.valid].abs().max()) == 0.0


def test_views_are_deterministic_and_differ(panos):
    a = FisheyeFromPanoramas("kb_f165", width=36, height=32, panoramas=panos, views_per_panorama=2, seed=1)
    b = FisheyeFromPanoramas("kb_f165", width=36, height=32, panoramas=panos, views_per_panorama=2, seed=1)
    torch.testing.assert_close(a[1]["depth"], b[1]["depth"])
    assert not torch.equal(a[0]["depth"], a[1]["depth"])
    with pytest.raises(IndexError):
        a[4]


def test_bilinear_depth_is_invalid_next_to_missing_depth(panos):
    ds = FisheyeFromPanoramas("kb_f195", width=36, height=32, panoramas=panos, depth_mode="bilinear", seed=3,
                              max_pitch_deg=60)
    s = ds[0]
    d = s["depth"][0][s["valid"]]
    assert bool((d > 0.45).all())      # no blending with the 0 of the cap (true depth >= 2 - 1.12)


def test_perspective_crops(panos):
    ds = PerspectiveFromPanoramas(width=32, height=24, fov_deg=90, panoramas=panos, max_pitch_deg=0,
                                  max_roll_deg=0)
    s = ds[0]
    assert s["valid"].all()                       # 90° pinhole, horizon level: never reaches the 75° cap
    assert ds.camera.fx == pytest.approx(16.0)
    r = s["radius"][0]
    assert float(r.min()) == pytest.approx(math.hypot(0.5, 0.5))


def test_radius_map_in_calibrated_pixels():
    cam = resolve_camera("kb_f195", 72, 64, check_aspect=True)
    r = radius_map(cam).double()
    uv = cam.pixel_grid(torch.float64)
    expect = torch.hypot(uv[..., 0] * 15 - 540, uv[..., 1] * 15 - 480)
    torch.testing.assert_close(r, expect, atol=1e-3, rtol=0)
    assert principal_point(resolve_camera("kb_f195")) == pytest.approx((540.0, 480.0))


def test_panorama_shape_checked():
    bad = [{"image": torch.rand(3, 64, 64), "depth": torch.ones(1, 64, 64), "semantic": torch.ones(64, 64)}]
    ds = FisheyeFromPanoramas(KannalaBrandt.example(), panoramas=bad)
    with pytest.raises(ValueError, match="twice as wide"):
        ds[0]


def test_stanford2d3ds_panoramas_through_the_existing_loader(tmp_path):
    from data_fixtures import write_stanford
    truth = write_stanford(tmp_path, areas=("1", "5a", "5b"), per_area=1, w=64, h=32)
    ds = FisheyeFromPanoramas("kb_f165", width=36, height=32, split="test", views_per_panorama=2,
                              panoramas={"type": "stanford2d3ds", "root": str(tmp_path), "height": 32, "width": 64})
    assert len(ds) == 4                                    # fold 1: area 5 (5a + 5b) is the test set
    s = ds[0]
    depths = torch.tensor(np.concatenate([t[1].ravel() for k, t in truth.items() if "area_5" in k]))
    got = s["depth"][0][s["valid"]]
    assert got.numel() > 100 and bool((got > 0).all())
    # nearest sampling keeps the panorama's depth values exactly (1/512 m units)
    assert bool(torch.isin((got.double() * 512).round(), (depths * 512).round()).all())
