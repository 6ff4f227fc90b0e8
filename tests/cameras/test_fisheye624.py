"""Fisheye624 (RAD_TAN_THIN_PRISM_FISHEYE): pycolmap agreement, closed forms beyond 90 deg, KB special case."""
import math

import numpy as np
import pytest
import torch

from omnidl.cameras import KannalaBrandt
from omnidl.cameras.fisheye624 import Fisheye624

# a 640 x 480 SLAM-style fisheye (the configs/camera/fisheye624.yaml lens)
ARIA = dict(width=640, height=480, fx=241.2, fy=241.5, cx=316.6, cy=237.8, k0=-0.0255, k1=0.0996, k2=-0.0658,
            k3=0.0187, k4=-0.0018, k5=0.0, p0=-2.1e-4, p1=8.7e-5, s0=4.3e-4, s1=-1.6e-4, s2=-5.1e-4, s3=1e-4,
            max_fov=math.radians(200))


def _dirs(n, theta_max, seed):
    g = np.random.default_rng(seed)
    theta = g.uniform(0, theta_max, n)
    psi = g.uniform(-math.pi, math.pi, n)
    return np.stack([np.sin(theta) * np.cos(psi), np.sin(theta) * np.sin(psi), np.cos(theta)], -1), theta, psi


def _reference(cam, theta, psi):
    """The model written out from the COLMAP / Aria description (numpy, independent of the module)."""
    k = [cam.k0, cam.k1, cam.k2, cam.k3, cam.k4, cam.k5]
    theta_d = theta + sum(c * theta ** (2 * i + 3) for i, c in enumerate(k))
    x, y = theta_d * np.cos(psi), theta_d * np.sin(psi)
    r2 = x * x + y * y
    xd = x + 2 * cam.p1 * x * y + cam.p0 * (r2 + 2 * x * x) + cam.s0 * r2 + cam.s1 * r2 * r2
    yd = y + 2 * cam.p0 * x * y + cam.p1 * (r2 + 2 * y * y) + cam.s2 * r2 + cam.s3 * r2 * r2
    return np.stack([cam.fx * xd + cam.cx, cam.fy * yd + cam.cy], -1)


def test_agrees_with_pycolmap():
    pycolmap = pytest.importorskip("pycolmap")
    cam = Fisheye624(**ARIA)
    ref_cam = pycolmap.Camera(model="RAD_TAN_THIN_PRISM_FISHEYE", width=cam.width, height=cam.height,
                              params=list(cam.colmap_params))
    dirs, _, _ = _dirs(2000, math.radians(89), 0)
    pts = dirs * np.random.default_rng(1).uniform(0.5, 4, (len(dirs), 1))
    uv, valid = cam.project(torch.from_numpy(pts))
    ref = np.asarray(ref_cam.img_from_cam(pts))
    v = valid.numpy()
    assert v.mean() > 0.7
    assert np.abs(uv.numpy() - ref)[v].max() < 1e-6
    # inverse: COLMAP's iterative undistortion stops at ~1e-8 (normalised units); ours is at rounding level
    rays = cam.unproject(uv)
    ok = v & rays.valid.numpy()
    x = (rays.direction[:, :2] / rays.direction[:, 2:]).numpy()
    ref_x = np.asarray(ref_cam.cam_from_img(uv.numpy()))
    assert np.abs(x - ref_x)[ok].max() < 1e-7
    assert np.abs(x - pts[:, :2] / pts[:, 2:])[ok].max() < 1e-12


def test_closed_form_beyond_90_degrees():
    cam = Fisheye624.example()  # 200 deg
    dirs, theta, psi = _dirs(500, cam.theta_max, 2)
    uv, valid = cam.project(torch.from_numpy(3 * dirs))
    ref = _reference(cam, theta, psi)
    inside = (ref[:, 0] >= 0) & (ref[:, 0] < cam.width) & (ref[:, 1] >= 0) & (ref[:, 1] < cam.height)
    assert np.array_equal(valid.numpy(), inside) and (theta[inside] > math.pi / 2).any()
    assert np.abs(uv.numpy() - ref)[inside].max() < 1e-9
    # by hand, on the +x axis at theta = 100 deg: x = theta_d, y = 0, r2 = theta_d^2
    t = math.radians(100)
    td = t + cam.k0 * t ** 3 + cam.k1 * t ** 5 + cam.k2 * t ** 7 + cam.k3 * t ** 9 + cam.k4 * t ** 11 + cam.k5 * t ** 13
    u = cam.fx * (td + 3 * cam.p0 * td ** 2 + cam.s0 * td ** 2 + cam.s1 * td ** 4) + cam.cx
    v = cam.fy * (cam.p1 * td ** 2 + cam.s2 * td ** 2 + cam.s3 * td ** 4) + cam.cy
    got, ok = cam.project(torch.tensor([math.sin(t), 0.0, math.cos(t)], dtype=torch.float64))
    assert ok and abs(float(got[0]) - u) < 1e-12 and abs(float(got[1]) - v) < 1e-12


def test_round_trip_up_to_max_fov_and_invalid_beyond():
    cam = Fisheye624(**dict(ARIA, width=1200, height=1200, cx=600.0, cy=600.0, max_fov=math.radians(220)))
    dirs, _, _ = _dirs(1000, cam.theta_max, 3)
    d = torch.from_numpy(dirs)
    uv, valid = cam.project(2 * d)
    assert valid.all()
    rays = cam.unproject(uv)
    assert rays.valid.all() and (rays.direction - d).abs().max() < 1e-12
    beyond = torch.tensor([math.sin(math.radians(111)), 0, math.cos(math.radians(111))], dtype=torch.float64)
    uv, ok = cam.project(beyond)
    assert not ok and torch.isfinite(uv).all()
    # a pixel whose undistorted radius exceeds theta_d(max_fov / 2) is invalid
    far = torch.tensor([[cam.cx + 1.05 * cam.fx * cam.rho_max, cam.cy]], dtype=torch.float64)
    rays = cam.unproject(far)
    assert not rays.valid.any() and torch.isfinite(rays.direction).all()


def test_without_tangential_and_prism_terms_it_is_kannala_brandt():
    f = Fisheye624(width=64, height=64, fx=17.0, fy=17.5, cx=32.0, cy=31.5, k0=-0.01, k1=0.002, k2=-1e-4,
                   k3=1e-6, max_fov=math.radians(195))
    kb = KannalaBrandt.example()  # k0 = 1, (k1..k4) = (-0.01, 0.002, -1e-4, 1e-6): the same lens
    assert (kb.k0, kb.k1, kb.k2, kb.k3, kb.k4, kb.max_fov) == (1.0, f.k0, f.k1, f.k2, f.k3, f.max_fov)
    dirs, _, _ = _dirs(500, f.theta_max, 4)
    pts = torch.from_numpy(dirs)
    uv_f, v_f = f.project(pts)
    uv_k, v_k = kb.project(pts)
    assert torch.equal(v_f, v_k) and (uv_f - uv_k).abs().max() < 1e-12
    uv = kb.pixel_grid(torch.float64).reshape(-1, 2)
    rf, rk = f.unproject(uv), kb.unproject(uv)
    assert torch.equal(rf.valid, rk.valid) and (rf.direction - rk.direction)[rk.valid].abs().max() < 1e-12


def test_float32_unproject_matches_float64():
    cam = Fisheye624.example()
    uv = cam.sample_points(300, generator=torch.Generator().manual_seed(5))
    d64 = cam.unproject(uv).direction
    rays32 = cam.unproject(uv.float())
    assert rays32.valid.all() and (rays32.direction.double() - d64).abs().max() < 1e-5


def test_bad_parameters_are_rejected():
    with pytest.raises(ValueError, match="not increasing"):
        Fisheye624(width=8, height=8, fx=4.0, fy=4.0, k0=-0.3, max_fov=math.radians(200))
    with pytest.raises(ValueError, match="fx, fy must be > 0"):
        Fisheye624(width=8, height=8, fx=-1.0)
    with pytest.raises(ValueError, match="max_fov"):
        Fisheye624(width=8, height=8, max_fov=7.0)
