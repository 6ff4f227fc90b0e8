"""Kalibr camchain files as Kalibr writes and reads them (ConfigReader.py is the truth).

The fixtures below follow the layout of Kalibr's wiki page "Yaml formats" (camchain.yaml: ``camera_model``,
``intrinsics``, ``distortion_model``, ``distortion_coeffs``, ``T_cam_imu``, ``timeshift_cam_imu``,
``rostopic``, ``resolution``; ``T_cn_cnm1`` from the second camera on) with the distortion model names of
its "Supported models" page (``equidistant``, not ``equi``).
"""
import math

import cv2
import numpy as np
import pytest
import torch
import yaml

from omnidl.cameras import KannalaBrandt, Unified
from omnidl.cameras.io import UnsupportedModelError, detect_format, kalibr, load, load_all, save

#: a stereo camchain as on the Kalibr wiki, with the equidistant (Kannala-Brandt) model of "Supported models"
CAMCHAIN_EQUIDISTANT = """cam0:
  camera_model: pinhole
  intrinsics: [461.629, 460.152, 362.680, 246.049]
  distortion_model: equidistant
  distortion_coeffs: [-0.01316, 0.05008, -0.04506, 0.01241]
  T_cam_imu:
  - [0.01779318, 0.99967549,-0.01822936, 0.07008565]
  - [-0.9998017, 0.01795239, 0.00860714,-0.01771023]
  - [0.00893160, 0.01807260, 0.99979678, 0.00399246]
  - [0.0, 0.0, 0.0, 1.0]
  timeshift_cam_imu: -8.121e-05
  rostopic: /cam0/image_raw
  resolution: [752, 480]
cam1:
  camera_model: omni
  intrinsics: [0.80065662, 833.006, 830.345, 373.850, 253.749]
  distortion_model: radtan
  distortion_coeffs: [-0.33518750, 0.13211436, 0.00055967, 0.00057686]
  T_cn_cnm1:
  - [ 0.99998854, 0.00216014, 0.00427195,-0.11003785]
  - [-0.00221074, 0.99992702, 0.01187697, 0.00045792]
  - [-0.00424598,-0.01188627, 0.99992034,-0.00064487]
  - [0.0, 0.0, 0.0, 1.0]
  T_cam_imu:
  - [ 0.01567142, 0.99978002,-0.01393948,-0.03997419]
  - [-0.99966203, 0.01595569, 0.02052137,-0.01735854]
  - [ 0.02073927, 0.01361317, 0.99969223, 0.00326019]
  - [0.0, 0.0, 0.0, 1.0]
  timeshift_cam_imu: -8.681e-05
  rostopic: /cam1/image_raw
  resolution: [752, 480]
"""


def _dirs(n, theta_max, seed):
    g = np.random.default_rng(seed)
    theta = theta_max * np.sqrt(g.random(n))
    psi = g.uniform(-np.pi, np.pi, n)
    return np.stack([np.sin(theta) * np.cos(psi), np.sin(theta) * np.sin(psi), np.cos(theta)], -1)


def test_equidistant_camchain_as_documented_loads_and_round_trips(tmp_path):
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text(CAMCHAIN_EQUIDISTANT)
    assert detect_format(path) == "kalibr"
    cams = load_all(path)
    kb, omni = cams["cam0"], cams["cam1"]
    assert isinstance(kb, KannalaBrandt) and (kb.k0, kb.k1, kb.k4) == (1.0, -0.01316, 0.01241)
    assert (kb.cx, kb.cy) == (362.680 + 0.5, 246.049 + 0.5) and (kb.width, kb.height) == (752, 480)
    assert isinstance(omni, Unified) and (omni.xi, omni.p2) == (0.80065662, 0.00057686)
    # the equidistant model is cv2.fisheye's (Kalibr's EquidistantDistortion): same pixels (OpenCV convention)
    pts = _dirs(400, math.radians(80), 0)
    K = np.array([[461.629, 0, 362.680], [0, 460.152, 246.049], [0, 0, 1.0]])
    D = np.array([-0.01316, 0.05008, -0.04506, 0.01241])
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros((3, 1)), np.zeros((3, 1)), K, D)
    uv, _ = kb.project(torch.from_numpy(pts))
    assert np.abs(uv.numpy() - 0.5 - ref.reshape(-1, 2)).max() < 1e-6
    # round trip: written with Kalibr's own names, read back identical
    out = save(cams, tmp_path / "camchain.yaml")
    assert load_all(out) == cams
    nodes = yaml.safe_load(out.read_text())
    assert nodes["cam0"]["distortion_model"] == "equidistant" and nodes["cam1"]["camera_model"] == "omni"
    assert "equi\n" not in out.read_text()


def test_written_nodes_pass_kalibrs_own_checks(tmp_path):
    out = save(load_all(_write(tmp_path, CAMCHAIN_EQUIDISTANT)), tmp_path / "camchain.yaml")
    for name, node in yaml.safe_load(out.read_text()).items():
        # CameraParameters.checkIntrinsics / checkDistortion / checkResolution of ConfigReader.py
        n_intr = {"pinhole": 4, "omni": 5, "ds": 6, "eucm": 6}[node["camera_model"]]
        assert len(node["intrinsics"]) == n_intr and all(isinstance(v, float) for v in node["intrinsics"])
        n_dist = {"radtan": 4, "equidistant": 4, "fov": 1, "none": 0}[node["distortion_model"]]
        assert len(node["distortion_coeffs"]) == n_dist
        assert all(isinstance(v, int) for v in node["resolution"]) and len(node["resolution"]) == 2
        assert min(node["intrinsics"][-4:]) >= 0


def _write(tmp_path, text, name="camchain.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_equidistant_was_refused_before_and_is_read_now(tmp_path):
    # regression: "distortion_model 'equidistant' is not one of ['equi', 'fov', 'none', 'radtan']"
    cam = load(_write(tmp_path, CAMCHAIN_EQUIDISTANT))
    assert isinstance(cam, KannalaBrandt)


def test_omnidl_legacy_equi_is_read_but_never_written(tmp_path):
    legacy = CAMCHAIN_EQUIDISTANT.replace("distortion_model: equidistant", "distortion_model: equi")
    cam = load(_write(tmp_path, legacy, "old.yaml"))
    assert cam == load(_write(tmp_path, CAMCHAIN_EQUIDISTANT))
    assert "distortion_model: equidistant" in save(cam, tmp_path / "camchain.yaml").read_text()


@pytest.mark.parametrize("header", ["%YAML:1.0\n---\n", "%YAML:1.0\n", "# calibrated with Kalibr\n%YAML:1.0\n---\n"])
def test_opencv_yaml_header_parses(tmp_path, header):
    # VIO datasets ship camchains with cv::FileStorage's directive; PyYAML alone refuses '%YAML:1.0'
    path = _write(tmp_path, header + CAMCHAIN_EQUIDISTANT)
    assert detect_format(path) == "kalibr"
    assert load_all(path) == load_all(_write(tmp_path, CAMCHAIN_EQUIDISTANT, "plain.yaml"))


def test_combinations_kalibr_does_not_build_are_refused(tmp_path):
    bad = CAMCHAIN_EQUIDISTANT.replace("distortion_model: radtan", "distortion_model: equidistant")
    with pytest.raises(ValueError, match=r"node 'cam1'.*'omni' with distortion_model 'equidistant'.*Kalibr builds"):
        load(_write(tmp_path, bad), camera=1)
    with pytest.raises(ValueError, match=r"distortion_model 'kb4' is not one of Kalibr's"):
        load(_write(tmp_path, CAMCHAIN_EQUIDISTANT.replace("equidistant", "kb4"), "b.yaml"))


def test_writer_refuses_what_kalibrs_reader_rejects(tmp_path):
    ds = pytest.importorskip("omnidl.cameras").DoubleSphere
    cam = ds(width=64, height=64, fx=20.0, fy=20.0, cx=32.0, cy=32.0, xi=-0.2, alpha=1.0)
    with pytest.raises(UnsupportedModelError, match=r"'kalibr'.*requires ds alpha in \[0, 1\), got 1.0"):
        save(cam, tmp_path / "camchain.yaml")
    off = KannalaBrandt(width=64, height=64, fx=20.0, fy=20.0, cx=0.25, cy=32.0, max_fov=math.pi)
    with pytest.raises(UnsupportedModelError, match=r"'kalibr'.*requires pinhole pu >= 0"):
        kalibr.from_camera(off)
