"""Fisheye lenses of thesis Tables 2.1/2.2 against closed forms and OmniSCV's reference rays."""
import math

import pytest
import torch

from omnidl.cameras import Fisheye, build
from omnidl.cameras.fisheye import LENS_DOMAIN

LENS_H = {  # independent closed forms, standard focal length f
    "equiangular": lambda f, p: f * p,
    "stereographic": lambda f, p: 2 * f * math.tan(p / 2),
    "orthogonal": lambda f, p: f * math.sin(p),
    "equisolid": lambda f, p: 2 * f * math.sin(p / 2),
}


@pytest.mark.parametrize("lens", sorted(LENS_H))
def test_projection_matches_table_2_1(lens):
    cam = Fisheye(width=400, height=400, f=80.0, cx=200.0, cy=200.0, lens=lens, max_fov=math.radians(180))
    for phi in (0.05, 0.4, 1.0, 1.5):
        for psi in (0.3, 2.0, -2.5):
            d = torch.tensor([math.sin(phi) * math.cos(psi), math.sin(phi) * math.sin(psi), math.cos(phi)],
                             dtype=torch.float64)
            uv, valid = cam.project(5 * d)
            r = LENS_H[lens](80.0, phi)
            assert valid
            assert abs(uv[0] - (200 + r * math.cos(psi))) < 1e-9 and abs(uv[1] - (200 + r * math.sin(psi))) < 1e-9
            ray = cam.unproject(uv)
            assert torch.allclose(ray.direction, d, atol=1e-12)


def test_equisolid_thesis_focal_is_twice_standard():
    # thesis Table 2.1 / OmniSCV: r = f_t sin(phi/2); standard: r = 2 f sin(phi/2) -> f = f_t / 2
    f_t = 625.036589
    cam = Fisheye(width=1024, height=1024, f=f_t / 2, cx=512.0, cy=512.0, lens="equisolid", max_fov=math.radians(220))
    phi = 1.2
    uv, _ = cam.project(torch.tensor([math.sin(phi), 0.0, math.cos(phi)], dtype=torch.float64))
    assert abs(float(uv[0]) - 512 - f_t * math.sin(phi / 2)) < 1e-9


# OmniSCV-36 reference rays (docs/design.md#omniscv-reference-rays): 1024 x 1024, centre (512, 512)
OMNISCV = {
    ("equiangular", 266.685810, 220): {(612, 512): (0.366247, 0, 0.930517), (512, 300): (0, -0.713824, 0.700326),
                                       (900, 900): (0.624986, 0.624986, -0.467744),
                                       (1000, 512): (0.966628, 0, -0.256184)},
    ("stereographic", 179.253130, 220): {(612, 512): (0.517599, 0, 0.855624), (512, 300): (0, -0.876267, 0.481826),
                                         (900, 900): (0.647559, 0.647559, -0.401665),
                                         (1000, 512): (0.954268, 0, -0.298953)},
    ("orthogonal", 512.0, 180): {(612, 512): (0.195312, 0, 0.980741), (512, 300): (0, -0.414062, 0.910248),
                                 (1000, 512): (0.953125, 0, 0.302577)},
    ("equisolid", 625.036589 / 2, 220): {(612, 512): (0.315859, 0, 0.948806), (512, 300): (0, -0.638148, 0.769914),
                                         (900, 900): (0.594515, 0.594515, -0.541390),
                                         (1000, 512): (0.975690, 0, -0.219155)},
}


@pytest.mark.parametrize("key", list(OMNISCV), ids=lambda k: k[0])
def test_matches_omniscv_rays(key):
    lens, f, _ = key  # OmniSCV's table gives the unmasked maths: use the lens' whole domain
    cam = Fisheye(width=2048, height=2048, f=f, cx=512.0, cy=512.0, lens=lens,
                  max_fov=2 * LENS_DOMAIN[lens] - (1e-6 if lens != "orthogonal" else 0))
    pix = torch.tensor(list(OMNISCV[key]), dtype=torch.float64)
    want = torch.tensor(list(OMNISCV[key].values()), dtype=torch.float64)
    rays = cam.unproject(pix)
    assert rays.valid.all()
    assert (rays.direction - want).abs().max() < 2e-6


def test_invalid_beyond_fov_and_domain():
    cam = Fisheye(width=200, height=200, f=30.0, cx=100.0, cy=100.0, lens="equiangular", max_fov=math.radians(190))
    ang = torch.tensor([math.radians(94.9), math.radians(95.1)], dtype=torch.float64)
    pts = torch.stack([torch.sin(ang), torch.zeros_like(ang), torch.cos(ang)], -1)
    _, valid = cam.project(pts)
    assert valid.tolist() == [True, False]
    ortho = Fisheye(width=200, height=200, f=60.0, cx=100.0, cy=100.0, lens="orthogonal", max_fov=math.pi)
    uv, valid = ortho.project(torch.tensor([[1.0, 0.0, -0.1], [0.0, 0.0, -1.0]], dtype=torch.float64))
    assert not valid.any() and torch.isfinite(uv).all()
    # a pixel beyond the image circle is invalid
    assert not ortho.unproject(torch.tensor([[100.0 + 61, 100.0]], dtype=torch.float64)).valid.any()


def test_bad_config_errors():
    with pytest.raises(ValueError, match="lens"):
        Fisheye(width=10, height=10, f=5.0, lens="fishy")
    with pytest.raises(ValueError, match="max_fov"):
        Fisheye(width=10, height=10, f=5.0, lens="orthogonal", max_fov=4.0)
    with pytest.raises(ValueError, match="unknown field"):
        build({"type": "fisheye", "width": 10, "height": 10, "focal": 3.0})
