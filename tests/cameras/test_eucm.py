"""EUCM: pycolmap's EUCM model as oracle, the paper's closed forms and special cases, validity bounds."""
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from omnidl.cameras import build
from omnidl.cameras.catadioptric import Unified
from omnidl.cameras.eucm import EUCM

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "camera" / "eucm.yaml"
PARAMS = [(0.6291060881178562, 1.0418067381860868), (0.45, 2.5), (0.8, 0.7), (0.0, 1.0), (1.0, 1.3)]


def _sphere_dirs(n, seed):
    d = torch.randn(n, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return d / d.norm(dim=-1, keepdim=True)


def test_hand_computed_projection():
    # rho = sqrt(1.2 * 1.25 + 4) = 2.3452078799117148, den = 0.6 rho + 0.4 * 2 = 2.2071247279470289 (mpmath)
    cam = EUCM(width=200, height=100, fx=100.0, fy=110.0, cx=50.5, cy=40.5, alpha=0.6, beta=1.2)
    uv, valid = cam.project(torch.tensor([1.0, -0.5, 2.0], dtype=torch.float64))
    assert valid
    assert abs(float(uv[0]) - 95.80781551843499003) < 1e-12
    assert abs(float(uv[1]) - 15.58070146486075548) < 1e-12
    ray = cam.unproject(uv)
    assert torch.allclose(ray.direction, torch.tensor([1.0, -0.5, 2.0], dtype=torch.float64) / math.sqrt(5.25),
                          atol=1e-14)


@pytest.mark.parametrize("alpha,beta", PARAMS)
def test_agrees_with_pycolmap(alpha, beta):
    pycolmap = pytest.importorskip("pycolmap")
    big = 10 ** 6  # COLMAP does not clip to the image; keep every point inside ours
    cam = EUCM(width=big, height=big, fx=300.0, fy=310.0, cx=big / 2 + 0.3, cy=big / 2 - 0.2, alpha=alpha, beta=beta)
    ref = pycolmap.Camera(model="EUCM", width=big, height=big, params=[300.0, 310.0, cam.cx, cam.cy, alpha, beta])
    dirs = _sphere_dirs(4000, 0)
    pts = dirs * (0.5 + torch.rand(len(dirs), 1, dtype=torch.float64, generator=torch.Generator().manual_seed(1)))
    uv, valid = cam.project(pts)
    assert valid.sum() > 500
    # beyond 90 deg too (COLMAP's cheirality check would reject z <= 0)
    ref_uv = ref.img_from_cam(pts[valid].numpy(), check_cheirality=False)
    assert np.abs(uv[valid].numpy() - ref_uv).max() < 1e-6
    # unprojection: COLMAP returns (x/z, y/z), defined for rays in front of the camera
    front = valid & (dirs[:, 2] > 0.05)
    xy = ref.cam_from_img(uv[front].numpy())
    d_ref = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    d_ref /= np.linalg.norm(d_ref, axis=1, keepdims=True)
    rays = cam.unproject(uv[front])
    assert rays.valid.all() and np.abs(rays.direction.numpy() - d_ref).max() < 1e-9


def test_beta_one_is_unified():
    a = 0.6
    e = EUCM(width=640, height=480, fx=120.0, fy=130.0, cx=320.5, cy=240.5, alpha=a, beta=1.0)
    u = Unified(width=640, height=480, xi=a / (1 - a), fx=120.0 / (1 - a), fy=130.0 / (1 - a), cx=320.5, cy=240.5)
    dirs = _sphere_dirs(3000, 2)
    uv_e, ok_e = e.project(dirs)
    uv_u, ok_u = u.project(dirs)
    both = ok_e & ok_u
    assert both.sum() > 1000
    assert (uv_e - uv_u)[both].abs().max() < 1e-9


def test_alpha_half_beta_one_is_stereographic_and_alpha_zero_is_pinhole():
    cam = EUCM(width=5000, height=5000, fx=100.0, fy=100.0, cx=2500.0, cy=2500.0, alpha=0.5, beta=1.0)
    theta = torch.linspace(0.0, math.radians(170), 50, dtype=torch.float64)
    d = torch.stack([torch.sin(theta), torch.zeros_like(theta), torch.cos(theta)], -1)
    uv, valid = cam.project(d)
    assert valid.all() and (uv[:, 0] - 2500 - 200 * torch.tan(theta / 2)).abs().max() < 1e-10
    pin = EUCM(width=640, height=480, fx=100.0, fy=100.0, cx=320.0, cy=240.0, alpha=0.0, beta=3.0)
    uv, valid = pin.project(torch.tensor([[0.3, -0.2, 1.5], [0.3, 0.0, -1.0]], dtype=torch.float64))
    assert valid.tolist() == [True, False] and torch.allclose(uv[0], torch.tensor([340.0, 240 - 40 / 3],
                                                                                 dtype=torch.float64))


def test_validity_bounds():
    a, b = 0.8, 0.7
    big = EUCM(width=10 ** 5, height=10 ** 5, fx=100.0, fy=100.0, cx=5e4, cy=5e4, alpha=a, beta=b)
    w = (1 - a) / a
    assert big.w == pytest.approx(w)
    # z = -w rho on the x-z plane: z = -w sqrt(b x^2 + z^2), with x = sin t, z = cos t
    t_max = math.pi / 2 + math.atan(w * math.sqrt(b) / math.sqrt(1 - w * w))
    for t, expect in [(t_max - 1e-6, True), (t_max + 1e-6, False)]:
        _, valid = big.project(torch.tensor([math.sin(t), 0.0, math.cos(t)], dtype=torch.float64))
        assert bool(valid) == expect
    r_max = 100 / math.sqrt(b * (2 * a - 1))
    rays = big.unproject(torch.tensor([[5e4 + r_max * (1 - 1e-6), 5e4], [5e4 + r_max * (1 + 1e-9), 5e4]],
                                      dtype=torch.float64))
    assert rays.valid.tolist() == [True, False] and torch.isfinite(rays.direction).all()


def test_every_valid_point_round_trips_over_the_sphere():
    for cam in EUCM.examples() + [build(OmegaConf.load(CONFIG))]:
        dirs = _sphere_dirs(20000, 3)
        uv, valid = cam.project(3 * dirs)
        rays = cam.unproject(uv[valid])
        assert valid.sum() > 1000 and rays.valid.all()
        assert (rays.direction - dirs[valid]).abs().max() < 1e-11


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="beta must be"):
        EUCM(width=8, height=8, fx=1.0, fy=1.0, beta=0.0)
    with pytest.raises(ValueError, match="alpha must be in"):
        EUCM(width=8, height=8, fx=1.0, fy=1.0, alpha=-0.1)
