"""Kannala–Brandt: OpenCV agreement, > 180 deg round trips, Newton accuracy, calibration files."""
import math

import cv2
import numpy as np
import pytest
import torch

from omnidl.cameras import KannalaBrandt, build, read_kb_calibration

F195_FILE = "540\n480\n287\n287\n1080\n960\n195\n3.37012024344156e-19\n-3.543830680552053e-05\n" \
            "9.999999999924497e-08\n-6.883696004705416e-11\n"


def _random_dirs(n, theta_max, seed):
    g = np.random.default_rng(seed)
    theta = theta_max * np.sqrt(g.random(n))
    psi = g.uniform(-np.pi, np.pi, n)
    return np.stack([np.sin(theta) * np.cos(psi), np.sin(theta) * np.sin(psi), np.cos(theta)], -1), theta


def test_agrees_with_cv2_fisheye():
    cam = KannalaBrandt(width=640, height=480, fx=300.0, fy=310.0, cx=321.0, cy=239.0, k1=0.05, k2=-0.01,
                        k3=0.002, k4=-1e-4, max_fov=math.pi)
    dirs, _ = _random_dirs(500, math.radians(89.9), 0)
    pts = dirs * np.random.default_rng(1).uniform(0.5, 5, (500, 1))
    K = np.array([[300.0, 0, 321.0], [0, 310.0, 239.0], [0, 0, 1]])
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros((3, 1)), np.zeros((3, 1)), K,
                                       np.array([0.05, -0.01, 0.002, -1e-4]))
    uv, _ = cam.project(torch.from_numpy(pts))
    assert np.abs(uv.numpy() - ref.reshape(-1, 2)).max() < 1e-6


def test_f195_round_trips_rays_up_to_97_5_degrees(tmp_path):
    path = tmp_path / "fisheye_calibration_FOV195.txt"
    path.write_text(F195_FILE)
    cam = build({"type": "kannala_brandt", "calib_file": str(path)})
    assert (cam.width, cam.height, cam.fx, cam.cx, cam.k0) == (1080, 960, 287.0, 540.0, 1.0)
    assert abs(cam.max_fov - math.radians(195)) < 1e-15
    g = np.random.default_rng(2)
    theta = np.concatenate([g.uniform(0, math.radians(97.5), 400), [math.radians(97.5), math.radians(95.0)]])
    psi = g.uniform(-math.pi / 6, math.pi / 6, len(theta)) + np.where(g.random(len(theta)) < 0.5, 0, math.pi)
    d = torch.from_numpy(np.stack([np.sin(theta) * np.cos(psi), np.sin(theta) * np.sin(psi), np.cos(theta)], -1))
    uv, valid = cam.project(3 * d)
    assert valid.all()
    rays = cam.unproject(uv)
    assert rays.valid.all()
    assert (rays.direction - d).abs().max() < 1e-12
    # effectively equidistant r = 287 theta (< 1 px up to 97.5 deg)
    r = torch.hypot(uv[:, 0] - 540, uv[:, 1] - 480)
    assert (r - 287 * torch.from_numpy(theta)).abs().max() < 1.0
    # beyond 97.5 deg: invalid, finite
    out = torch.tensor([math.sin(math.radians(98)), 0, math.cos(math.radians(98))], dtype=torch.float64)
    uv, valid = cam.project(out)
    assert not valid and torch.isfinite(uv).all()


def test_inverse_matches_polynomial_roots_and_converges():
    cam = KannalaBrandt.example()
    r = torch.linspace(0, float(cam.distortion(torch.tensor(cam.theta_max, dtype=torch.float64))), 101,
                       dtype=torch.float64)
    theta = cam.inverse_distortion(r)
    assert (cam.distortion(theta) - r).abs().max() < 1e-14
    for ri, ti in zip(r[1::10].tolist(), theta[1::10].tolist()):  # independent: numpy companion-matrix roots
        c = [cam.k4, 0, cam.k3, 0, cam.k2, 0, cam.k1, 0, cam.k0, -ri]
        roots = np.roots(c)
        real = roots[(np.abs(roots.imag) < 1e-9) & (roots.real >= 0) & (roots.real <= cam.theta_max + 1e-12)].real
        assert len(real) == 1 and abs(real[0] - ti) < 1e-12


def test_unproject_is_eq_7_2():
    cam = KannalaBrandt.example()
    uv = torch.tensor([[40.0, 20.0], [12.0, 50.0]], dtype=torch.float64)
    assert cam.unproject(uv).valid.all()
    mx, my = (uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy
    phi = torch.atan2(my, mx)
    theta = cam.inverse_distortion(torch.hypot(mx, my))
    want = torch.stack([torch.cos(phi) * torch.sin(theta), torch.sin(phi) * torch.sin(theta), torch.cos(theta)], -1)
    assert torch.allclose(cam.unproject(uv).direction, want, atol=1e-14)


def test_non_monotonic_polynomial_is_rejected():
    with pytest.raises(ValueError, match="not increasing"):
        KannalaBrandt(width=10, height=10, fx=5.0, fy=5.0, k1=-0.3, max_fov=math.radians(195))


def test_calibration_file_errors(tmp_path):
    bad = tmp_path / "short_calib.txt"
    bad.write_text("540 480 287 287 1080 960 195 0 0 0\n")
    with pytest.raises(ValueError, match="short_calib.txt.*expected 11 values"):
        read_kb_calibration(bad)
    with pytest.raises(ValueError, match="missing.txt"):
        build({"type": "kannala_brandt", "calib_file": str(tmp_path / "missing.txt")})
    word = tmp_path / "word.txt"
    word.write_text(F195_FILE.replace("287", "f", 1))
    with pytest.raises(ValueError, match="word.txt"):
        read_kb_calibration(word)


def test_resized_with_padding_is_eq_7_3():
    # CalibratedConvolutions' reference values: F195 on a 541 x 480 feature map with 2 px right padding
    # gives cx' = 270, fx' = 143.5 (Eq. 7.3 with s = (1080 + 2) / 541 = 2)
    cam = build({"type": "kannala_brandt", "width": 1080, "height": 960, "fx": 287.0, "fy": 287.0, "cx": 540.0,
                 "cy": 480.0, "k1": 3.37012024344156e-19, "k2": -3.543830680552053e-05,
                 "k3": 9.999999999924497e-08, "k4": -6.883696004705416e-11, "max_fov": math.radians(195)})
    small = cam.resized(541, 480, pad_right=2)
    direct = cam.replace(width=541, height=480, fx=143.5, fy=143.5, cx=270.0, cy=240.0)
    dirs, _ = _random_dirs(300, math.radians(97), 3)
    pts = torch.from_numpy(dirs)
    uv_a, va = small.project(pts)
    uv_b, vb = direct.project(pts)
    assert torch.equal(va, vb) and (uv_a - uv_b).abs().max() < 1e-9
    uv = direct.sample_points(100, generator=torch.Generator().manual_seed(0))
    assert (small.unproject(uv).direction - direct.unproject(uv).direction).abs().max() < 1e-12
