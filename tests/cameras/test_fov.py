"""FOV (Devernay-Faugeras): pycolmap's FOV model as oracle, the closed-form inverse, the omega -> 0 limit."""
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from omnidl.cameras import build
from omnidl.cameras.fov import FOVCamera
from omnidl.cameras.pinhole import Pinhole

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "camera" / "fov.yaml"


def _front_points(n, seed, max_deg=89.0):
    g = np.random.default_rng(seed)
    theta = np.radians(max_deg) * np.sqrt(g.random(n))
    psi = g.uniform(-np.pi, np.pi, n)
    d = np.stack([np.sin(theta) * np.cos(psi), np.sin(theta) * np.sin(psi), np.cos(theta)], -1)
    return torch.from_numpy(d * g.uniform(0.5, 5, (n, 1)))


def _closed_form(cam, pts):
    """numpy reference: r_d = atan(2 r tan(omega / 2)) / omega on the normalised radius r."""
    x, y = pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2]
    r = np.hypot(x, y)
    rd = np.arctan(2 * r * math.tan(cam.omega / 2)) / cam.omega
    return np.stack([cam.fx * x * rd / r + cam.cx, cam.fy * y * rd / r + cam.cy], -1)


@pytest.mark.parametrize("omega", [0.3, 0.93, 1.6, 2.5])
def test_agrees_with_pycolmap(omega):
    pycolmap = pytest.importorskip("pycolmap")
    big = 10 ** 6
    cam = FOVCamera(width=big, height=big, fx=300.0, fy=310.0, cx=big / 2 + 0.3, cy=big / 2 - 0.2, omega=omega)
    ref = pycolmap.Camera(model="FOV", width=big, height=big, params=[300.0, 310.0, cam.cx, cam.cy, omega])
    pts = _front_points(2000, 0)
    uv, valid = cam.project(pts)
    assert valid.all()
    assert np.abs(uv.numpy() - ref.img_from_cam(pts.numpy())).max() < 1e-6
    xy = ref.cam_from_img(uv.numpy())
    d_ref = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    d_ref /= np.linalg.norm(d_ref, axis=1, keepdims=True)
    rays = cam.unproject(uv)
    assert rays.valid.all() and np.abs(rays.direction.numpy() - d_ref).max() < 1e-9


@pytest.mark.parametrize("omega", [1e-6, 0.005, 0.5, 3.0])
def test_closed_form_and_inverse(omega):
    # small omega: COLMAP switches to a series for omega^2 < 1e-4 (see the module doc); the closed form is exact
    cam = FOVCamera(width=10 ** 6, height=10 ** 6, fx=300.0, fy=310.0, cx=5e5, cy=5e5, omega=omega)
    pts = _front_points(2000, 1, max_deg=80.0)
    uv, valid = cam.project(pts)
    assert valid.all()
    assert np.abs(uv.numpy() - _closed_form(cam, pts.numpy())).max() < 1e-8
    rd = torch.linspace(0, 0.999 * cam.rd_max if omega > 0.01 else 5.0, 200, dtype=torch.float64)
    r = cam.undistortion(rd)
    assert (r - torch.tan(rd * omega) / (2 * math.tan(omega / 2))).abs().max() < 1e-12 * (1 + r.abs().max())
    assert (cam.distortion(r) - rd).abs().max() < 1e-12


def test_omega_to_zero_is_the_pinhole():
    pin = Pinhole(width=640, height=480, fx=300.0, fy=310.0, cx=320.5, cy=240.5)
    pts = _front_points(500, 2, max_deg=40.0)
    uv_pin, _ = pin.project(pts)
    for omega, tol in [(0.0, 1e-12), (1e-9, 1e-9)]:
        cam = FOVCamera(width=640, height=480, fx=300.0, fy=310.0, cx=320.5, cy=240.5, omega=omega)
        uv, valid = cam.project(pts)
        assert (uv - uv_pin)[valid].abs().max() < tol
        rays = cam.unproject(uv_pin[valid])
        assert (rays.direction - pin.unproject(uv_pin[valid]).direction).abs().max() < tol


def test_front_half_only_and_the_rim():
    cam = FOVCamera(width=10 ** 5, height=10 ** 5, fx=100.0, fy=100.0, cx=5e4, cy=5e4, omega=1.2)
    _, valid = cam.project(torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, -1e-9], [1.0, 0.0, 1e-9]], dtype=torch.float64))
    assert valid.tolist() == [False, False, True]
    # z -> 0+: r_d -> pi / (2 omega); pixels at or beyond that radius are invalid
    uv, _ = cam.project(torch.tensor([1.0, 0.0, 1e-12], dtype=torch.float64))
    assert float(uv[0]) - 5e4 == pytest.approx(100 * math.pi / 2.4, abs=1e-6)
    rim = 100 * cam.rd_max
    rays = cam.unproject(torch.tensor([[5e4 + rim * (1 - 1e-9), 5e4], [5e4 + rim, 5e4]], dtype=torch.float64))
    assert rays.valid.tolist() == [True, False]
    assert 0 < float(rays.direction[0, 2]) < 1e-6


def test_config_and_errors():
    cam = build(OmegaConf.load(CONFIG))
    assert isinstance(cam, FOVCamera) and cam.omega == 0.93
    with pytest.raises(ValueError, match="omega must be in"):
        FOVCamera(width=8, height=8, fx=1.0, fy=1.0, omega=-0.1)
    with pytest.raises(ValueError, match="omega must be in"):
        FOVCamera(width=8, height=8, fx=1.0, fy=1.0, omega=math.pi)
