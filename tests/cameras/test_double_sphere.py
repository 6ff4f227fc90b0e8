"""Double Sphere: the paper's closed forms, special cases, validity bounds, Basalt's TUM-VI calibration."""
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from omnidl.cameras import build
from omnidl.cameras.catadioptric import Unified
from omnidl.cameras.double_sphere import DoubleSphere
from omnidl.cameras.eucm import EUCM

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "camera" / "double_sphere.yaml"
# Basalt's TUM-VI 512 calibrations of cam0 (data/tumvi_512_{ds,eucm}_calib.json), + 0.5 px for omnidl's centres
TUMVI_DS = dict(width=512, height=512, fx=158.28600034966977, fy=158.2743455478755, cx=255.46116578191653,
                cy=257.3894394501779, xi=-0.17213086034353243, alpha=0.5931177593944744)
TUMVI_EUCM = dict(width=512, height=512, fx=191.14799836282189, fy=191.13150963902818, cx=255.4585771534443,
                  cy=257.38154645599448, alpha=0.6291060881178562, beta=1.0418067381860868)


def _sphere_dirs(n, seed):
    d = torch.randn(n, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return d / d.norm(dim=-1, keepdim=True)


def test_hand_computed_projection():
    # d1 = sqrt(5.25) = 2.2912878474779200, zeta = 0.5 d1 + 2 = 3.1456439237389600,
    # d2 = |(1, -0.5, zeta)| = 3.3384241334731332, den = 0.6 d2 + 0.4 zeta = 3.2613120495794639 (30-digit mpmath)
    cam = DoubleSphere(width=200, height=100, fx=100.0, fy=110.0, cx=50.5, cy=40.5, xi=0.5, alpha=0.6)
    uv, valid = cam.project(torch.tensor([1.0, -0.5, 2.0], dtype=torch.float64))
    assert valid
    assert abs(float(uv[0]) - 81.16250591166052042) < 1e-12
    assert abs(float(uv[1]) - 23.63562174858671377) < 1e-12
    ray = cam.unproject(uv)
    assert torch.allclose(ray.direction, torch.tensor([1.0, -0.5, 2.0], dtype=torch.float64) / math.sqrt(5.25),
                          atol=1e-14)


def test_alpha_zero_is_unified_and_cv2_omnidir():
    ds = DoubleSphere(width=640, height=480, fx=300.0, fy=310.0, cx=321.0, cy=239.0, xi=0.8, alpha=0.0)
    uni = Unified(width=640, height=480, xi=0.8, fx=300.0, fy=310.0, cx=321.0, cy=239.0)
    dirs = _sphere_dirs(2000, 0)
    dirs = dirs[dirs[:, 2] > -0.7]
    uv_ds, ok_ds = ds.project(2 * dirs)
    uv_u, ok_u = uni.project(2 * dirs)
    assert torch.equal(ok_ds, ok_u) and ok_ds.sum() > 100
    assert (uv_ds - uv_u)[ok_ds].abs().max() < 1e-9
    K = np.array([[300.0, 0, 321.0], [0, 310.0, 239.0], [0, 0, 1]])
    pts = (2 * dirs[dirs[:, 2] > -0.5]).numpy()
    ref, _ = cv2.omnidir.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, 0.8, np.zeros((1, 4)))
    uv, _ = ds.project(torch.from_numpy(pts))
    assert np.abs(uv.numpy() - ref.reshape(-1, 2)).max() < 1e-9
    rays = ds.unproject(uv_ds[ok_ds])
    assert rays.valid.all() and (rays.direction - dirs[ok_ds]).abs().max() < 1e-12


def test_xi_zero_alpha_half_is_stereographic():
    cam = DoubleSphere(width=5000, height=5000, fx=100.0, fy=100.0, cx=2500.0, cy=2500.0, xi=0.0, alpha=0.5)
    theta = torch.linspace(0.0, math.radians(170), 50, dtype=torch.float64)
    d = torch.stack([torch.sin(theta), torch.zeros_like(theta), torch.cos(theta)], -1)
    uv, valid = cam.project(d)
    assert valid.all()
    assert (uv[:, 0] - 2500 - 200 * torch.tan(theta / 2)).abs().max() < 1e-10


def test_validity_bounds_match_the_paper():
    cam = DoubleSphere(**TUMVI_DS)
    w1 = (1 - cam.alpha) / cam.alpha
    w2 = (w1 + cam.xi) / math.sqrt(2 * w1 * cam.xi + cam.xi ** 2 + 1)
    assert cam.w1 == pytest.approx(w1, abs=1e-15) and cam.w2 == pytest.approx(w2, abs=1e-15)
    big = DoubleSphere(width=10 ** 5, height=10 ** 5, fx=100.0, fy=100.0, cx=5e4, cy=5e4, xi=cam.xi, alpha=cam.alpha)
    t_max = math.acos(-w2)
    for t, expect in [(t_max - 1e-6, True), (t_max + 1e-6, False)]:
        _, valid = big.project(torch.tensor([math.sin(t), 0.0, math.cos(t)], dtype=torch.float64))
        assert bool(valid) == expect
    # unprojection needs r^2 < 1 / (2 alpha - 1); that circle is where r(theta) folds back, slightly beyond the
    # image r_b of the ray limit z = -w2 d1, and the band r_b <= r < r_max (rays the projection rejects) is invalid
    r_max = 100 * math.sqrt(1 / (2 * cam.alpha - 1))
    uv_b, _ = big.project(torch.tensor([math.sin(t_max - 1e-9), 0.0, math.cos(t_max - 1e-9)], dtype=torch.float64))
    r_b = float(uv_b[0]) - 5e4
    assert r_max - 0.05 < r_b < r_max
    r = torch.tensor([r_b - 1e-3, r_b + 1e-3, r_max * (1 - 1e-9), r_max * (1 + 1e-9)], dtype=torch.float64)
    rays = big.unproject(torch.stack([5e4 + r, torch.full_like(r, 5e4)], -1))
    assert rays.valid.tolist() == [True, False, False, False]
    assert torch.isfinite(rays.direction).all()


def test_every_valid_point_round_trips_over_the_sphere():
    for cam in DoubleSphere.examples() + [DoubleSphere(**TUMVI_DS)]:
        dirs = _sphere_dirs(20000, 1)
        uv, valid = cam.project(3 * dirs)
        rays = cam.unproject(uv[valid])
        assert valid.sum() > 1000 and rays.valid.all()
        assert (rays.direction - dirs[valid]).abs().max() < 1e-11


def test_tumvi_calibration_is_a_195_degree_lens_and_agrees_with_eucm():
    ds, eucm = DoubleSphere(**TUMVI_DS), EUCM(**TUMVI_EUCM)
    r = torch.linspace(0.0, 350.0, 71, dtype=torch.float64)
    # along the image diagonal (the image is 512 x 512, its centre ~256 px from the sides)
    uv = torch.stack([ds.cx + r / math.sqrt(2), ds.cy + r / math.sqrt(2)], -1)
    theta_ds = torch.rad2deg(torch.acos(ds.unproject(uv).direction[:, 2]))
    uv = torch.stack([eucm.cx + r / math.sqrt(2), eucm.cy + r / math.sqrt(2)], -1)
    theta_eucm = torch.rad2deg(torch.acos(eucm.unproject(uv).direction[:, 2]))
    # 97.5 deg (half of 195) at ~318 px from the centre, inside the image diagonal (362 px)
    assert theta_ds[r == 320.0].item() == pytest.approx(97.80, abs=0.01)
    corner = ds.unproject(torch.tensor([2.0, 2.0], dtype=torch.float64))
    assert corner.valid and math.degrees(math.acos(corner.direction[2])) > 97.5
    # two independent calibrations (DS, EUCM) of the same lens: rays within 1 deg out to 350 px
    assert (theta_ds - theta_eucm).abs().max() < 1.0


def test_config_file_is_the_tumvi_calibration():
    cam = build(OmegaConf.load(CONFIG))
    assert cam == DoubleSphere(**TUMVI_DS)


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="alpha must be in"):
        DoubleSphere(width=8, height=8, fx=1.0, fy=1.0, alpha=1.2)
    with pytest.raises(ValueError, match="fx, fy must be > 0"):
        DoubleSphere(width=8, height=8, fx=0.0, fy=1.0)
