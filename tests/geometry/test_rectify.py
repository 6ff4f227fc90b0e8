"""Fisheye -> perspective rectification and back; the unrectifiable fraction of a 195° fisheye."""
import math

import pytest
import torch

from .geom_helpers import fisheye_195, render
from omnidl.geometry import perspective_camera, rectification_coverage, rectify, unrectify

D = torch.float64


def test_coverage_of_a_195_degree_fisheye():
    fish = fisheye_195(96)
    cov = rectification_coverage(fish)
    # equiangular image circle of 97.5°: the disc within 90° holds (90 / 97.5)^2 of its pixels
    assert abs(cov.rectifiable - (90 / 97.5) ** 2) < 0.01, cov
    assert abs(cov.unrectifiable + cov.rectifiable - 1) < 1e-12
    assert 0 < cov.covered <= cov.rectifiable
    wide = perspective_camera(fish, fov_deg=170)
    assert rectification_coverage(fish, wide).covered > cov.covered


def test_default_perspective_keeps_central_resolution():
    fish = fisheye_195(64)
    pin = perspective_camera(fish)
    assert abs(pin.fx - fish.f) < 1e-5 * fish.f and abs(pin.fy - fish.f) < 1e-5 * fish.f
    assert (pin.width, pin.height) == (64, 64)
    with pytest.raises(ValueError, match="fov_deg"):
        perspective_camera(fish, fov_deg=180)


def test_rectify_and_back():
    fish = fisheye_195(96)
    img = render(fish)
    pin = perspective_camera(fish, fov_deg=120)
    rect, valid = rectify(img, fish, pin)
    true = render(pin)
    assert valid.all()
    assert (rect - true).abs().mean() < 1.2
    back, bvalid = unrectify(rect, pin, fish)
    rays = fish.unproject_grid(dtype=D)
    theta = torch.acos(rays.direction[..., 2].clamp(-1, 1))
    bv = bvalid[0, 0]
    assert not bv[rays.valid & (theta >= math.pi / 2)].any()  # nothing beyond 90° comes back
    assert (back[0, 0][~bv] == 0).all()
    inner = bv & (theta < math.radians(50))
    assert inner.sum() > 100 and (back[0, 0] - img[0, 0])[inner].abs().mean() < 1.0
