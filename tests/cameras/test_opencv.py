"""OpenCV pinhole + distortion against cv2.projectPoints / cv2.undistortPoints; the 2-D Newton solver."""
import math

import cv2
import numpy as np
import pytest
import torch

from omnidl.cameras.opencv import OpenCVPinhole
from omnidl.cameras.pinhole import Pinhole
from omnidl.cameras.solvers import newton_polish_2d, solve_2d

FULL = dict(width=1280, height=800, fx=620.0, fy=622.0, cx=641.3, cy=399.1, k1=0.41, k2=-0.08, p1=4e-4,
            p2=-7e-4, k3=0.003, k4=0.75, k5=0.02, k6=0.001, s1=1e-3, s2=-2e-4, s3=-8e-4, s4=1e-4)
MILD = dict(FULL, k1=-0.12, k2=0.03, k3=-0.003, k4=0.05, k5=0.002, k6=1e-4)
PLAIN = dict(width=640, height=480, fx=500.0, fy=505.0, cx=320.5, cy=240.5, k1=-0.28, k2=0.09, p1=1e-3, p2=-5e-4,
             k3=-0.01)  # the common 5-coefficient calibration


def _points(n, seed, half_w=1.2, half_h=0.8):
    g = np.random.default_rng(seed)
    xy = np.stack([g.uniform(-half_w, half_w, n), g.uniform(-half_h, half_h, n), np.ones(n)], -1)
    return xy * g.uniform(0.5, 5, (n, 1))


def _cv2_project(cam, pts, shift=0.0):
    K = cam.K.numpy().copy()
    K[:2, 2] += shift
    ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.array(cam.dist_coeffs))
    return ref.reshape(-1, 2)


@pytest.mark.parametrize("params", [FULL, MILD, PLAIN], ids=["rational_prism", "mild", "five_coeffs"])
def test_agrees_with_cv2_project_points(params):
    cam = OpenCVPinhole(**params)
    pts = _points(2000, 0, 0.6 * cam.width / cam.fx, 0.6 * cam.height / cam.fy)
    uv, valid = cam.project(torch.from_numpy(pts))
    ref = _cv2_project(cam, pts)
    v = valid.numpy()
    assert v.mean() > 0.7
    assert np.abs(uv.numpy() - ref)[v].max() < 1e-6
    # pixel convention: OpenCV puts pixel 0's centre at 0, omnidl at 0.5 -- the same lens has cx_cv = cx - 0.5
    ref_cv = _cv2_project(cam, pts, shift=-0.5)
    assert np.abs((uv.numpy() - 0.5) - ref_cv)[v].max() < 1e-6


def test_dist_coeffs_are_in_opencv_order():
    cam = OpenCVPinhole(**FULL)
    assert cam.dist_coeffs == (0.41, -0.08, 4e-4, -7e-4, 0.003, 0.75, 0.02, 0.001, 1e-3, -2e-4, -8e-4, 1e-4)


@pytest.mark.parametrize("params", [MILD, PLAIN], ids=["mild", "five_coeffs"])
def test_unproject_agrees_with_cv2_undistort_points(params):
    cam = OpenCVPinhole(**params)
    uv = cam.sample_points(1000, generator=torch.Generator().manual_seed(0))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-16)
    ref = cv2.undistortPoints(uv.numpy().reshape(-1, 1, 2), cam.K.numpy(), np.array(cam.dist_coeffs),
                              criteria=crit).reshape(-1, 2)
    d = cam.unproject(uv).direction
    assert np.abs((d[:, :2] / d[:, 2:]).numpy() - ref).max() < 1e-10


def test_unproject_exact_where_cv2_fixed_point_iteration_is_not():
    # strong rational distortion: cv2.undistortPoints' fixed-point iteration stays ~1e-3 off, Newton is exact
    cam = OpenCVPinhole(**FULL)
    pts = _points(2000, 1)
    uv, valid = cam.project(torch.from_numpy(pts))
    rays = cam.unproject(uv)
    ok = (valid & rays.valid).numpy()
    assert ok.mean() > 0.8
    x = (rays.direction[:, :2] / rays.direction[:, 2:]).numpy()
    assert np.abs(x - pts[:, :2] / pts[:, 2:])[ok].max() < 1e-12


def test_radial_limit_closed_form_and_invalid_beyond():
    # R = 1 + k1 r^2: d/dr (r + k1 r^3) = 0 at r = 1 / sqrt(-3 k1)
    cam = OpenCVPinhole(width=64, height=48, fx=40.0, fy=40.0, cx=31.7, cy=24.2, k1=-0.25)
    assert abs(cam.r_max - 1 / math.sqrt(0.75)) < 1e-12
    # rational: R = 1 / (1 + k4 r^2) -> r / (1 + k4 r^2) peaks at r = 1 / sqrt(k4)
    assert abs(OpenCVPinhole(width=8, height=8, k4=0.5).r_max - math.sqrt(2)) < 1e-12
    # a denominator root limits too: 1 + k4 r^2 = 0 at r = 1 / sqrt(-k4)
    assert abs(OpenCVPinhole(width=8, height=8, k4=-0.25).r_max - 2.0) < 1e-9
    assert OpenCVPinhole(width=8, height=8, k1=0.1, k2=0.01).r_max == math.inf
    r = cam.r_max
    pts = torch.tensor([[0.999 * r, 0, 1], [1.001 * r, 0, 1], [0, 1.2 * r, 1.0]], dtype=torch.float64)
    uv, valid = cam.project(pts)
    assert valid.tolist() == [True, False, False] and torch.isfinite(uv).all()
    # pixels beyond the image of the invertible disk (the corners of this image) are invalid and finite
    corners = torch.tensor([[0.5, 0.5], [63.5, 47.5]], dtype=torch.float64, requires_grad=True)
    rays = cam.unproject(corners)
    assert not rays.valid.any() and torch.isfinite(rays.direction).all()
    (g,) = torch.autograd.grad(rays.direction.sum(), corners)
    assert torch.isfinite(g).all()


def test_no_distortion_is_pinhole():
    a = OpenCVPinhole(width=48, height=32, fx=24.0, fy=25.0, cx=24.0, cy=16.5)
    b = Pinhole(width=48, height=32, fx=24.0, fy=25.0, cx=24.0, cy=16.5)
    uv = b.pixel_grid(torch.float64).reshape(-1, 2)
    assert torch.allclose(a.unproject(uv).direction, b.unproject(uv).direction, atol=1e-15)
    pts = b.unproject(uv).direction
    assert torch.allclose(a.project(pts)[0], b.project(pts)[0], atol=1e-12)


def test_float32_unproject_matches_float64():
    cam = OpenCVPinhole.example()
    uv = cam.sample_points(300, generator=torch.Generator().manual_seed(4))
    d64 = cam.unproject(uv).direction
    rays32 = cam.unproject(uv.float())
    assert rays32.valid.all() and (rays32.direction.double() - d64).abs().max() < 1e-6


def test_bad_parameters_are_rejected():
    with pytest.raises(ValueError, match="fx, fy must be > 0"):
        OpenCVPinhole(width=8, height=8, fx=0.0)
    with pytest.raises(ValueError, match="k2 must be finite"):
        OpenCVPinhole(width=8, height=8, k2=float("nan"))


# -- the 2-D Newton solver (omnidl.cameras.solvers.solve_2d / newton_polish_2d) ----------------------------
def _map(z):
    """A smooth invertible map of the plane near the origin (distortion-like)."""
    x, y = z[..., 0], z[..., 1]
    return torch.stack([x + 0.1 * x * y + 0.05 * y ** 3, y - 0.08 * x * x + 0.02 * torch.sin(3 * x)], -1)


def _map_jac(z):
    x, y = z[..., 0], z[..., 1]
    row0 = torch.stack([1 + 0.1 * y, 0.1 * x + 0.15 * y * y], -1)
    row1 = torch.stack([-0.16 * x + 0.06 * torch.cos(3 * x), torch.ones_like(y)], -1)
    return torch.stack([row0, row1], -2)


def test_solve_2d_converges_to_rounding_and_polish_gives_implicit_gradient():
    g = torch.Generator().manual_seed(0)
    x_true = torch.rand(200, 2, dtype=torch.float64, generator=g) * 1.6 - 0.8
    y = _map(x_true).requires_grad_(True)
    x, conv = solve_2d(_map, _map_jac, y)
    assert conv.all() and (x - x_true).abs().max() < 1e-14
    assert (_map(x) - y.detach()).abs().max() <= 4 * torch.finfo(torch.float64).eps * 2
    xp = newton_polish_2d(x, lambda z: _map(z) - y, _map_jac(x))
    assert (xp - x).abs().max() < 1e-14
    # dx/dy = J^{-1} at the root
    jac_inv = torch.linalg.inv(_map_jac(x_true))
    for k in range(2):
        (gk,) = torch.autograd.grad(xp[:, k].sum(), y, retain_graph=True)
        assert torch.allclose(gk, jac_inv[:, k, :], atol=1e-13)
    yy = y.detach()[:5].clone().requires_grad_(True)

    def inverse(t):
        root, _ = solve_2d(_map, _map_jac, t)
        return newton_polish_2d(root, lambda z: _map(z) - t, _map_jac(root))

    assert torch.autograd.gradcheck(inverse, (yy,))


def test_solve_2d_flags_targets_outside_the_disk_and_non_finite_input():
    # identity map restricted to |x| <= 1: targets outside cannot be reached
    ident = (lambda z: z, lambda z: torch.eye(2, dtype=z.dtype).expand(*z.shape[:-1], 2, 2))
    y = torch.tensor([[0.3, 0.4], [3.0, 0.0], [float("nan"), 0.0], [float("inf"), 1.0]], dtype=torch.float64)
    x, conv = solve_2d(*ident, y, max_norm=1.0)
    assert conv.tolist() == [True, False, False, False]
    assert torch.isfinite(x).all() and torch.equal(x[0], y[0])
    x32, conv32 = solve_2d(_map, _map_jac, _map(torch.tensor([[0.5, -0.3]])))
    assert conv32.all() and (x32 - torch.tensor([[0.5, -0.3]])).abs().max() < 1e-6
