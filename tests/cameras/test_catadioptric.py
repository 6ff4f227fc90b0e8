"""Unified/Mei model against cv2.omnidir; sphere model against thesis Eq. 2.7-2.8 and Table 2.3."""
import math

import cv2
import numpy as np
import pytest
import torch

from omnidl.cameras import Catadioptric, Unified


def _visible_points(cam, n, seed):
    g = np.random.default_rng(seed)
    d = g.normal(size=(4 * n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d[:, 2] > -cam._z_limit + 0.05][:n]
    return d * g.uniform(0.3, 8, (len(d), 1))


@pytest.mark.parametrize("xi", [0.0, 0.6, 1.0, 1.7])
def test_unified_agrees_with_cv2_omnidir(xi):
    cam = Unified(width=800, height=600, xi=xi, fx=210.0, fy=205.0, s=0.4, cx=402.0, cy=297.0,
                  k1=-0.03, k2=0.004, p1=0.002, p2=-0.001)
    pts = _visible_points(cam, 400, 0)
    K = np.array([[cam.fx, cam.s, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
    D = np.array([[cam.k1, cam.k2, cam.p1, cam.p2]])
    ref, _ = cv2.omnidir.projectPoints(pts.reshape(1, -1, 3), np.zeros(3), np.zeros(3), K, xi, D)
    uv, _ = cam.project(torch.from_numpy(pts))
    assert np.abs(uv.numpy() - ref.reshape(-1, 2)).max() < 1e-8


def test_unified_unproject_tight_on_full_image():
    cam = Unified.example()
    uv = cam.pixel_grid(torch.float64).reshape(-1, 2)
    rays = cam.unproject(uv)
    assert rays.valid.all()
    uv2, valid = cam.project(rays.direction)
    assert valid.all() and (uv2 - uv).abs().max() < 1e-10


def _thesis_backprojection(u, v, xi, eta, fx, fy, u0, v0):
    """Eq. 2.7-2.8 literally: v_bar = (K_c M_c)^-1 (u, v, 1), then h^-1."""
    Hc = np.array([[fx, 0, u0], [0, fy, v0], [0, 0, 1]]) @ np.diag([-eta, eta, 1.0])
    x, y, z = np.linalg.solve(Hc, np.array([u, v, 1.0]))
    n2 = x * x + y * y + z * z
    fac = (z * xi + math.sqrt(z * z + (1 - xi * xi) * (x * x + y * y))) / n2
    ray = np.array([x * fac, y * fac, z * fac - xi])
    return ray / np.linalg.norm(ray)


@pytest.mark.parametrize("cam", Catadioptric.examples(), ids=lambda c: c.mirror)
def test_sphere_model_is_thesis_eq_2_7_2_8(cam):
    xi, eta = cam.xi_eta
    uv = cam.sample_points(20, generator=torch.Generator().manual_seed(0))
    rays = cam.unproject(uv)
    for (u, v), d in zip(uv.tolist(), rays.direction):
        want = _thesis_backprojection(u, v, xi, eta, cam.fx, cam.fy, cam.cx, cam.cy)
        # the thesis' M_c = diag(-eta, eta, 1) flips y relative to omnidl's frame
        assert np.abs(d.numpy() - want * np.array([1, -1, 1])).max() < 1e-12


def test_table_2_3():
    assert Catadioptric(width=8, height=8, mirror="para", p=0.03).xi_eta == (1.0, -0.06)
    d, p = 0.1, 0.025
    xi, eta = Catadioptric(width=8, height=8, mirror="hyper", d=d, p=p).xi_eta
    assert abs(xi - d / math.sqrt(d * d + 4 * p * p)) < 1e-15 and abs(eta + 2 * p / math.sqrt(d * d + 4 * p * p)) < 1e-15
    cam = Catadioptric(width=64, height=64, mirror="hyper", d=d, p=p, fx=40.0, fy=41.0, cx=32.0, cy=32.0)
    u = cam.as_unified
    assert (u.xi, u.fx, u.fy) == (xi, -eta * 40.0, -eta * 41.0)


def test_para_point_behind_is_invalid_and_finite():
    cam = Catadioptric.example()
    uv, valid = cam.project(torch.tensor([[0.0, 0.0, -2.0], [1e-9, 0.0, -1.0]], dtype=torch.float64))
    assert not valid.any() and torch.isfinite(uv).all()


def test_bad_config_errors():
    with pytest.raises(ValueError, match="mirror"):
        Catadioptric(width=8, height=8, mirror="conical")
    with pytest.raises(ValueError, match="d > 0"):
        Catadioptric(width=8, height=8, mirror="hyper", d=0.0)
    with pytest.raises(ValueError, match="fx, fy"):
        Unified(width=8, height=8, fx=-1.0)
