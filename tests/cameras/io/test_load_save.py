"""omnidl.cameras.load/save: detection, adapters (OCamCalib, KB text, omnidl YAML), image sizes, resolve_camera."""
import math

import numpy as np
import pytest
import torch

from omnidl.cameras import KannalaBrandt, Pinhole, Scaramuzza, Unified, load, resolve_camera, save
from omnidl.cameras.io import FORMATS, UnsupportedModelError, detect_format, load_all

KB_TXT = "540\n480\n287\n287\n1080\n960\n195\n3.37012024344156e-19\n-3.543830680552053e-05\n" \
         "9.999999999924497e-08\n-6.883696004705416e-11\n"


def test_kb_text_adapter_and_writer(tmp_path):
    path = tmp_path / "fisheye_calibration_FOV195.txt"
    path.write_text(KB_TXT)
    assert detect_format(path) == "kb_txt"
    cam = load(path)
    assert cam == resolve_camera(str(path))
    assert (cam.width, cam.cx, cam.k0) == (1080, 540.0, 1.0) and abs(cam.max_fov - math.radians(195)) < 1e-15
    out = save(cam, tmp_path / "kb.txt", format="kb_txt")
    again = load(out)
    assert again.replace(max_fov=cam.max_fov) == cam and abs(again.max_fov - cam.max_fov) < 1e-15


def test_ocamcalib_adapter_writes_the_centre_it_reads(tmp_path):
    cam = Scaramuzza.example()
    out = save(cam, tmp_path / "calib_results.txt")
    assert detect_format(out) == "ocamcalib"
    back = load(out)
    assert isinstance(back, Scaramuzza)
    assert (back.cx, back.cy) == (cam.cx, cam.cy)  # written 0-based (C), stated in the comment, read back exactly
    assert back.pol == cam.pol and (back.width, back.height) == (cam.width, cam.height)
    assert resolve_camera(str(out)) == back


def test_omnidl_yaml_and_default_formats(tmp_path):
    cam = Unified.example()
    out = save(cam, tmp_path / "cam.yaml")
    assert detect_format(out) == "omnidl"
    assert load(out) == cam == resolve_camera(str(out))
    with pytest.raises(ValueError, match="pass format="):
        save(cam, tmp_path / "cam.txt")
    with pytest.raises(ValueError, match="unknown calibration format"):
        save(cam, tmp_path / "cam.txt", format="nope")
    assert set(FORMATS) >= {"colmap", "kalibr", "opencv", "orbslam3", "ocamcalib", "kb_txt", "omnidl"}


def test_unrecognised_and_missing_files(tmp_path):
    bad = tmp_path / "x.yaml"
    bad.write_text("foo: 1\n")
    with pytest.raises(ValueError, match="format not recognised"):
        load(bad)
    with pytest.raises(FileNotFoundError):
        load(tmp_path / "missing.yaml")
    with pytest.raises(ValueError, match="multi-camera"):
        load(save(Pinhole.example(), tmp_path / "p.yaml"), camera=1)


def test_image_size_follows_resolve_camera_semantics(tmp_path):
    # (180 deg: COLMAP's fisheye models cannot hold a wider lens; save refuses one, see test_lossless_save)
    cam = KannalaBrandt(width=1080, height=960, fx=287.0, fy=287.0, cx=540.0, cy=480.0, max_fov=math.pi)
    path = save(cam, tmp_path / "cameras.txt")
    assert load(path, image_size=(1080, 960)) == load(path)
    half = load(path, image_size=(540, 480))  # uniform resize
    assert (half.width, half.height) == (540, 480)
    uv, _ = half.project(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    assert torch.allclose(uv, torch.tensor([[270.0, 240.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"cameras\.txt.*1088x960|1088x960.*cameras\.txt"):
        load(path, image_size=(1088, 960))
    padded = load(path, image_size=(1088, 960), size_policy="pad")
    uv, _ = padded.project(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    assert torch.allclose(uv, torch.tensor([[540.0, 480.0]], dtype=torch.float64))  # principal point stays


def test_resolve_camera_accepts_calibration_files(tmp_path):
    cam = KannalaBrandt(width=640, height=480, fx=200.0, fy=205.0, cx=320.5, cy=240.25, k1=0.05, k2=-0.01,
                        k3=0.002, k4=-1e-4, max_fov=math.pi)
    for name, fmt in [("cameras.txt", "colmap"), ("cameras.bin", "colmap"), ("camchain.yaml", "kalibr"),
                      ("calib.xml", "opencv"), ("orb.yaml", "orbslam3"), ("fs.yaml", "opencv")]:
        path = save(cam, tmp_path / name, format=fmt)
        got = resolve_camera(str(path))
        assert isinstance(got, KannalaBrandt), name
        assert abs(got.cx - cam.cx) < 1e-12 and got.k4 == cam.k4, name
        assert resolve_camera(str(path), fx=210.0).fx == 210.0
        assert resolve_camera(str(path), 320, 240).width == 320


def test_multi_camera_save_and_errors(tmp_path):
    cams = {1: Pinhole.example(), 2: KannalaBrandt(width=64, height=64, fx=17.0, fy=17.0, cx=32.0, cy=32.0)}
    out = save(cams, tmp_path / "cameras.txt")
    assert load_all(out) == {1: cams[1], 2: cams[2].replace(max_fov=math.pi)}
    with pytest.raises(ValueError, match="holds one camera"):
        save(cams, tmp_path / "a.xml")
    with pytest.raises(UnsupportedModelError, match="'kalibr'.*'scaramuzza'"):
        save(Scaramuzza.example(), tmp_path / "camchain.yaml")
    with pytest.raises(UnsupportedModelError, match="k0 = 2"):
        save(KannalaBrandt(width=64, height=64, fx=17.0, fy=17.0, cx=32.0, cy=32.0, k0=2.0), tmp_path / "cameras.bin")
    assert np.isfinite(load(out, camera=2).fx)


def test_woodscape_json_loads_through_the_entry_point(tmp_path):
    ws = pytest.importorskip("tests.cameras.test_woodscape")
    import json
    path = tmp_path / "front.json"
    path.write_text(json.dumps(ws.FRONT))
    assert detect_format(path) == "woodscape"
    cam = load(path)
    assert type(cam).name == "woodscape" and cam == resolve_camera(str(path))
    with pytest.raises(UnsupportedModelError, match="read-only"):
        save(cam, tmp_path / "w.json", format="woodscape")
