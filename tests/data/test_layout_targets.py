"""Layout targets through the camera model (vs an independent closed-form caster) and augmentations."""
import math

import numpy as np
import pytest
import torch

from omnidl.cameras import build
from omnidl.data.layout_targets import (LayoutAugment, boundary_targets, corner_heat, corner_probability, flip_sample,
                                        pano_stretch_sample, roll_sample)
from omnidl.geometry.polygon import ray_polygon_hit
from omnidl.geometry.rotations import UPRIGHT_TO_WORLD
from omnidl.apps.layout.simulate import Room, corner_columns

R_UP = np.asarray(UPRIGHT_TO_WORLD)          # camera -> layout frame

ROOM = Room(np.array([[3.0, -2.5], [3.5, 2.0], [-0.5, 3.5], [-2.0, 2.0], [-2.0, -2.5]]), 1.25, -1.45)


def render_boundaries(room, width, rc):
    """Closed-form boundary latitudes of the circular panorama of radius ``rc`` (independent of the cameras)."""
    lon = 2 * math.pi * (np.arange(width) + 0.5) / width - math.pi
    b = np.stack([np.sin(lon), np.cos(lon)], -1)
    s, k = ray_polygon_hit(np.asarray(room.polygon, float), rc * b, b)
    return np.arctan2(room.h_ceiling, s), np.arctan2(room.h_floor, s), k


def _corners_cam(room):
    n = len(room.polygon)
    c = np.zeros((n, 2, 3))
    c[:, :, :2] = room.polygon[:, None]
    c[:, 0, 2], c[:, 1, 2] = room.h_ceiling, room.h_floor
    return c @ R_UP               # layout -> camera frame (R^T)


@pytest.mark.parametrize("cam_cfg", [{"type": "noncentral_pano", "rc": 1.0}, {"type": "noncentral_pano", "rc": 0.5},
                                     {"type": "equirect"}])
def test_boundary_targets_match_analytic_caster(cam_cfg):
    cam = build({**cam_cfg, "width": 128, "height": 64})
    rows, valid = boundary_targets(_corners_cam(ROOM), cam)
    lat_c, lat_f, _ = render_boundaries(ROOM, 128, cam_cfg.get("rc", 0.0))
    ref = np.stack([(math.pi / 2 - lat_c) / math.pi * 64, (math.pi / 2 - lat_f) / math.pi * 64])
    assert valid.all()
    assert np.allclose(rows.numpy(), ref, atol=1e-3)


def test_noncentral_boundaries_differ_from_central():
    a, _ = boundary_targets(_corners_cam(ROOM), build({"type": "noncentral_pano", "width": 128, "height": 64, "rc": 1.0}))
    b, _ = boundary_targets(_corners_cam(ROOM), build({"type": "equirect", "width": 128, "height": 64}))
    assert (a - b).abs().max() > 1.0                     # pixels


def test_corner_heat_is_horizonnet_target():
    cam = build({"type": "equirect", "width": 64, "height": 32})
    h = corner_heat(corner_columns(ROOM, cam), 64)
    assert torch.allclose(h[0].double(), torch.from_numpy(corner_probability(corner_columns(ROOM, cam), 64)))


def _sample(cam):
    rows, valid = boundary_targets(_corners_cam(ROOM), cam)
    img = torch.rand(3, cam.height, cam.width)
    return {"image": img, "boundary": rows, "boundary_valid": valid,
            "corner_heat": corner_heat(corner_columns(ROOM, cam), cam.width),
            "corners_cam": torch.from_numpy(_corners_cam(ROOM)).float(), "num_walls": torch.tensor(5)}


@pytest.mark.parametrize("shift", [0, 7, 64])
def test_roll_and_flip_keep_targets_consistent_with_corners(shift):
    cam = build({"type": "noncentral_pano", "width": 128, "height": 64, "rc": 1.0})
    s = _sample(cam)
    for aug in (lambda x: roll_sample(x, shift), flip_sample, lambda x: flip_sample(roll_sample(x, shift))):
        t = aug(s)
        rows, _ = boundary_targets(t["corners_cam"].double().numpy(), cam)
        assert torch.allclose(rows, t["boundary"], atol=2e-3)
    assert torch.equal(roll_sample(s, shift)["image"], torch.roll(s["image"], shift, -1))


def test_pano_stretch_central_only():
    eq = build({"type": "equirect", "width": 128, "height": 64})
    s = _sample(eq)
    t = pano_stretch_sample(s, eq, 1.5, 0.8)
    c = t["corners_cam"].double().numpy() @ R_UP.T
    assert np.allclose(c[:, 0, 0], ROOM.polygon[:, 0] * 1.5, atol=1e-5)
    assert t["image"].shape == s["image"].shape and t["boundary_valid"].all()
    nc = build({"type": "noncentral_pano", "width": 128, "height": 64, "rc": 1.0})
    with pytest.raises(ValueError, match="non-central"):
        pano_stretch_sample(_sample(nc), nc, 1.5, 1.0)
    with pytest.raises(ValueError):
        LayoutAugment(nc, stretch=2.0)
    out = LayoutAugment(eq, stretch=2.0)(s, np.random.default_rng(0))
    assert out["boundary"].shape == (2, 128)
