"""OpenCV FileStorage, Kalibr camchain and ORB-SLAM3 settings: fields, the half-pixel convention, round trips.

Fixtures are written here in each tool's own layout (cv2.FileStorage as the OpenCV sample apps call it; Kalibr's
camchain and ORB-SLAM3's settings as text). OpenCV-convention pixels are omnidl pixels - 0.5.
"""
import math

import cv2
import numpy as np
import pytest
import torch

from omnidl.cameras import KannalaBrandt, Pinhole, Unified, list_cameras
from omnidl.cameras.io import UnsupportedModelError, detect_format, load, load_all, save

K = np.array([[300.0, 0.0, 319.25], [0.0, 310.0, 239.75], [0.0, 0.0, 1.0]])
W, H = 640, 480


def _need(family):
    if family not in list_cameras():
        pytest.skip(f"omnidl family {family!r} is not registered yet")


def _dirs(n, theta_max, seed):
    g = np.random.default_rng(seed)
    theta = theta_max * np.sqrt(g.random(n))
    psi = g.uniform(-np.pi, np.pi, n)
    return np.stack([np.sin(theta) * np.cos(psi), np.sin(theta) * np.sin(psi), np.cos(theta)], -1) \
        * g.uniform(0.5, 5, (n, 1))


def _storage(path, nodes):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in nodes.items():
        fs.write(k, v)
    fs.release()


def _project(cam, pts):
    return cam.project(torch.from_numpy(pts))[0].numpy() - 0.5  # omnidl -> OpenCV pixel convention


@pytest.mark.parametrize("suffix", [".yaml", ".xml"])
def test_calibrate_camera_file_agrees_with_cv2_project_points(tmp_path, suffix):
    _need("opencv")
    D = np.array([[-0.2, 0.05, 0.001, -0.002, 0.01]])
    path = tmp_path / f"calib{suffix}"
    _storage(path, {"image_width": W, "image_height": H, "camera_matrix": K, "distortion_coefficients": D})
    assert detect_format(path) == "opencv"
    cam = load(path)
    assert type(cam).name == "opencv" and (cam.cx, cam.cy) == (319.75, 240.25)
    pts = _dirs(500, math.radians(45), 0)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, D)
    assert np.abs(_project(cam, pts) - ref.reshape(-1, 2)).max() < 1e-6
    out = save(cam, tmp_path / f"out{suffix}", format="opencv")
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    assert np.array_equal(fs.getNode("camera_matrix").mat(), K)
    assert np.array_equal(fs.getNode("distortion_coefficients").mat().ravel(), D.ravel())
    assert int(fs.getNode("image_width").real()) == W
    assert load(out) == cam


def test_fisheye_file_agrees_with_cv2_fisheye(tmp_path):
    D = np.array([0.05, -0.01, 0.002, -1e-4])
    path = tmp_path / "fisheye.yml"
    _storage(path, {"K": K, "D": D, "image_width": W, "image_height": H})  # cv2.fisheye sample names
    cam = load(path)
    assert isinstance(cam, KannalaBrandt) and cam.k0 == 1 and cam.max_fov == math.pi
    pts = _dirs(500, math.radians(85), 1)
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros((3, 1)), np.zeros((3, 1)), K, D)
    assert np.abs(_project(cam, pts) - ref.reshape(-1, 2)).max() < 1e-6
    out = save(cam, tmp_path / "out.yaml", format="opencv")
    assert load(out) == cam


def test_omnidir_file_agrees_with_cv2_omnidir(tmp_path):
    Ks = K.copy()
    Ks[0, 1] = 0.4
    D = np.array([[-0.02, 0.002, 0.001, -0.0015]])
    path = tmp_path / "omni.xml"
    _storage(path, {"calibration_time": "now", "image_width": W, "image_height": H, "flags": 0,
                    "camera_matrix": Ks, "distortion_coefficients": D, "xi": np.array([[0.9]])})
    cam = load(path)
    assert isinstance(cam, Unified) and (cam.xi, cam.s) == (0.9, 0.4)
    pts = _dirs(500, math.radians(80), 2)
    ref, _ = cv2.omnidir.projectPoints(pts.reshape(1, -1, 3), np.zeros(3), np.zeros(3), Ks, 0.9, D)
    assert np.abs(_project(cam, pts) - ref.reshape(-1, 2)).max() < 1e-6
    assert load(save(cam, tmp_path / "out.xml")) == cam


def test_opencv_errors(tmp_path):
    path = tmp_path / "nosize.yaml"
    _storage(path, {"camera_matrix": K, "distortion_coefficients": np.zeros((1, 5))})
    with pytest.raises(ValueError, match="no image size"):
        load(path)
    assert load(path, file_image_size=(W, H)) == Pinhole(width=W, height=H, fx=300.0, fy=310.0, cx=319.75, cy=240.25)
    tilt = tmp_path / "tilt.yaml"
    _storage(tilt, {"camera_matrix": K, "distortion_coefficients": np.r_[np.zeros(12), 0.01, 0.0][None],
                    "image_width": W, "image_height": H})
    with pytest.raises(ValueError, match="tau_x"):
        load(tilt)
    with pytest.raises(UnsupportedModelError, match="'opencv'.*'scaramuzza'"):
        from omnidl.cameras import Scaramuzza
        save(Scaramuzza.example(), tmp_path / "s.xml")


CAMCHAIN = """cam0:
  cam_overlaps: [1]
  camera_model: pinhole
  distortion_coeffs: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
  distortion_model: radtan
  intrinsics: [458.654, 457.296, 367.215, 248.375]
  resolution: [752, 480]
  rostopic: /cam0/image_raw
cam1:
  T_cn_cnm1:
  - [0.9999, -0.0023, -0.0003, -0.1101]
  - [0.0023, 0.9999, -0.0140, 0.0004]
  - [0.0004, 0.0140, 0.9999, -0.0008]
  - [0.0, 0.0, 0.0, 1.0]
  camera_model: pinhole
  distortion_coeffs: [0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202, 0.00020293673591811182]
  distortion_model: equidistant
  intrinsics: [190.97847715128717, 190.9733070521226, 254.93170605935475, 256.8974428996504]
  resolution: [512, 512]
  rostopic: /cam1/image_raw
cam2:
  camera_model: omni
  distortion_coeffs: [-0.02, 0.002, 0.001, -0.0015]
  distortion_model: radtan
  intrinsics: [0.9, 300.0, 310.0, 319.25, 239.75]
  resolution: [640, 480]
cam3:
  camera_model: ds
  distortion_coeffs: []
  distortion_model: none
  intrinsics: [-0.2, 0.6, 156.0, 157.0, 319.25, 239.75]
  resolution: [640, 480]
cam4:
  camera_model: eucm
  distortion_coeffs: []
  distortion_model: none
  intrinsics: [0.6, 1.1, 200.0, 205.0, 319.25, 239.75]
  resolution: [640, 480]
cam5:
  camera_model: pinhole
  distortion_coeffs: [0.9]
  distortion_model: fov
  intrinsics: [200.0, 205.0, 319.25, 239.75]
  resolution: [640, 480]
"""


def _ds(p, fx, fy, cx, cy, xi, alpha):
    """Double Sphere projection (Usenko et al. 2018, Eq. 40-45)."""
    x, y, z = p.T
    d1 = np.sqrt(x * x + y * y + z * z)
    d2 = np.sqrt(x * x + y * y + (xi * d1 + z) ** 2)
    den = alpha * d2 + (1 - alpha) * (xi * d1 + z)
    return np.stack([fx * x / den + cx, fy * y / den + cy], -1)


def _eucm(p, fx, fy, cx, cy, alpha, beta):
    """EUCM projection (Khomutenko et al. 2016, Eq. 2-3)."""
    x, y, z = p.T
    den = alpha * np.sqrt(beta * (x * x + y * y) + z * z) + (1 - alpha) * z
    return np.stack([fx * x / den + cx, fy * y / den + cy], -1)


def test_kalibr_camchain_models_and_round_trip(tmp_path):
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text(CAMCHAIN)
    assert detect_format(path) == "kalibr"
    cams = {}
    for name in ["cam0", "cam1", "cam2", "cam3", "cam4", "cam5"]:
        fam = {"cam0": "opencv", "cam1": "kannala_brandt", "cam2": "unified", "cam3": "double_sphere",
               "cam4": "eucm", "cam5": "fov"}[name]
        if fam in list_cameras():
            cams[name] = load(path, camera=name)
            assert type(cams[name]).name == fam
    assert load(path) == load(path, camera=0) == load(path, camera="cam0") if "opencv" in list_cameras() else True
    kb = load(path, camera=1)
    assert (kb.cx, kb.cy, kb.width) == (254.93170605935475 + 0.5, 256.8974428996504 + 0.5, 512)
    pts = _dirs(500, math.radians(85), 3)
    Kk = np.array([[kb.fx, 0, kb.cx - 0.5], [0, kb.fy, kb.cy - 0.5], [0, 0, 1]])
    D = np.array([kb.k1, kb.k2, kb.k3, kb.k4])
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros((3, 1)), np.zeros((3, 1)), Kk, D)
    assert np.abs(_project(kb, pts) - ref.reshape(-1, 2)).max() < 1e-6
    if "double_sphere" in cams:
        ref = _ds(pts, 156.0, 157.0, 319.25, 239.75, -0.2, 0.6)
        assert np.abs(_project(cams["cam3"], pts) - ref).max() < 1e-6
    if "eucm" in cams:
        ref = _eucm(pts, 200.0, 205.0, 319.25, 239.75, 0.6, 1.1)
        assert np.abs(_project(cams["cam4"], pts) - ref).max() < 1e-6
    out = save(cams, tmp_path / "camchain.yaml")
    back = load_all(out)
    assert back == cams


ORB_KB8 = """%YAML:1.0

File.version: "1.0"

Camera.type: "KannalaBrandt8"

Camera1.fx: 190.978477
Camera1.fy: 190.973307
Camera1.cx: 254.931706
Camera1.cy: 256.897442

Camera1.k1: 0.003482389402
Camera1.k2: 0.000715034845
Camera1.k3: -0.002053236141
Camera1.k4: 0.000202936736

Camera2.fx: 190.44236969414825
Camera2.fy: 190.4344384721956
Camera2.cx: 252.59949716835982
Camera2.cy: 254.91723064636983

Camera2.k1: 0.0034003170790442797
Camera2.k2: 0.001766278153469831
Camera2.k3: -0.00266312569781606
Camera2.k4: 0.0003299517423931039

Camera.width: 512
Camera.height: 512

Camera.fps: 20
Camera.RGB: 1
"""

ORB_OLD_PINHOLE = """%YAML:1.0

Camera.type: "PinHole"

Camera.fx: 458.654
Camera.fy: 457.296
Camera.cx: 367.215
Camera.cy: 248.375

Camera.k1: -0.28340811
Camera.k2: 0.07395907
Camera.p1: 0.00019359
Camera.p2: 1.76187114e-05

Camera.width: 752
Camera.height: 480
"""


def test_orbslam3_settings(tmp_path):
    path = tmp_path / "TUM-VI.yaml"
    path.write_text(ORB_KB8)
    assert detect_format(path) == "orbslam3"
    cam = load(path)
    assert isinstance(cam, KannalaBrandt) and (cam.fx, cam.cx, cam.k4) == (190.978477, 255.431706, 0.000202936736)
    assert load(path, camera=2).fx == 190.44236969414825
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)  # the fixture is what ORB-SLAM3's reader reads
    assert fs.getNode("Camera1.k3").real() == -0.002053236141
    out = save(cam, tmp_path / "out.yaml", format="orbslam3")
    assert load(out) == cam
    assert cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ).getNode("Camera.type").string() == "KannalaBrandt8"
    old = tmp_path / "EuRoC.yaml"
    old.write_text(ORB_OLD_PINHOLE)
    if "opencv" in list_cameras():
        cam = load(old)
        assert (type(cam).name, cam.cx, cam.p2) == ("opencv", 367.715, 1.76187114e-05)
        assert load(save(cam, tmp_path / "o2.yaml", format="orbslam3")) == cam
    with pytest.raises(UnsupportedModelError, match="'orbslam3'.*'unified'"):
        save(Unified.example(), tmp_path / "u.yaml", format="orbslam3")
