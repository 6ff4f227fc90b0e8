"""Geometry of the projected kernel: zero offsets at the reference pixel, 1/cos(lat) growth, strides, fisheye."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from omnidl.cameras import Equirectangular, Pinhole, get_camera_class, list_cameras
from omnidl.nn import compute_offsets, compute_sampling
from omnidl.nn.sampling import sample_positions


def _taps(off: torch.Tensor, k: int) -> torch.Tensor:
    """(1, 2K, Ho, Wo) -> (Ho, Wo, K, 2) as (dy, dx)."""
    return off[0].permute(1, 2, 0).reshape(off.shape[2], off.shape[3], k * k, 2)


@pytest.mark.parametrize("kernel", ["grid", "tangent"])
@pytest.mark.parametrize("k,d", [(3, 1), (5, 2), (7, 1)])
def test_pinhole_centre_is_regular_grid(kernel, k, d):
    # principal point on the centre of pixel (12, 16), non-square pixels
    cam = Pinhole(width=33, height=25, fx=20.0, fy=23.0, cx=16.5, cy=12.5)
    off = compute_offsets(cam, (25, 33), k, 1, d * (k // 2), d, kernel=kernel)
    assert off.shape == (1, 2 * k * k, 25, 33)
    assert off[0, :, 12, 16].abs().max() < 1e-6
    assert off.abs().max() > 0.05  # away from the centre the kernel deforms


@pytest.mark.parametrize("k,d", [(3, 1), (5, 2), (7, 1)])
def test_equirect_equator_is_regular_grid(k, d):
    cam = Equirectangular(width=64, height=33)  # odd height: row 16 is the equator
    off = compute_offsets(cam, (33, 64), k, 1, d * (k // 2), d)
    assert off[0, :, 16, :].abs().max() < 1e-6
    # the tangent-plane lattice (EquiConv recipe) is close but not exact off the middle row/column
    off_t = compute_offsets(cam, (33, 64), k, 1, d * (k // 2), d, kernel="tangent")
    assert 1e-6 < off_t[0, :, 16, :].abs().max() < 1.0


def test_equirect_horizontal_extent_grows_as_inverse_cos_latitude():
    W, H, k = 128, 64, 3
    cam = Equirectangular(width=W, height=H)
    off = compute_offsets(cam, (H, W), k, 1, 1, 1)
    pos, _ = sample_positions(off, None, (H, W), (k, k), (1, 1), (1, 1), (1, 1))
    y, x = pos[..., 0], pos[..., 1]
    row = k // 2  # middle kernel row: taps k*row ... k*row + k-1
    extent = (x[:, 5, row * k + k - 1] - x[:, 5, row * k]) * 2 * math.pi / W  # longitude span (rad)
    lat = math.pi / 2 - math.pi * (torch.arange(H, dtype=torch.float64) + 0.5) / H
    delta = 2 * math.pi / W  # kernel pitch = one pixel on the equator
    # exact: the middle-row taps are at longitude +-atan(tan(delta) / cos(lat))
    expected = 2 * torch.atan(math.tan(delta) / torch.cos(lat))
    inner = lat.abs() < math.radians(80)
    assert torch.allclose(extent[inner], expected[inner], atol=1e-9)
    ratio = extent / (2 * delta) * torch.cos(lat)
    mid = lat.abs() < math.radians(60)
    assert (ratio[mid] - 1).abs().max() < 5e-3  # ~ 1/cos(latitude)
    # the centre tap follows the anchor: no offset anywhere
    assert _taps(off, k)[:, :, k * k // 2].abs().max() < 1e-9


@pytest.mark.parametrize("camera", ["equirect", "kannala_brandt", "catadioptric"])
def test_strided_offsets_are_computed_at_output_positions(camera):
    cam = Equirectangular(width=64, height=32) if camera == "equirect" else get_camera_class(camera).example()
    H, W = 16, (32 if camera == "equirect" else 16)
    full = compute_offsets(cam, (H, W), 3, 1, 1, 1)  # anchor of output (i, j) = input (i, j)
    strided = compute_offsets(cam, (H, W), 3, 2, 1, 1)  # anchor of output (i, j) = input (2i, 2j)
    assert strided.shape[-2:] == ((H - 1) // 2 + 1, (W - 1) // 2 + 1)
    assert torch.allclose(strided, full[..., ::2, ::2], atol=1e-9)
    assert full.abs().max() > 0.1


def test_equidistant_fisheye_centre_is_regular_grid():
    Fisheye = get_camera_class("fisheye")
    cam = Fisheye(width=41, height=41, f=13.0, cx=20.5, cy=20.5, lens="equiangular", max_fov=math.radians(190))
    for k, d in [(3, 1), (5, 1), (3, 2)]:
        off = compute_offsets(cam, (41, 41), k, 1, d * (k // 2), d)
        assert off[0, :, 20, 20].abs().max() < 1e-6


def test_equidistant_fisheye_matches_independent_construction():
    """Off-centre taps = reference kernel rotated by the smallest rotation to the anchor ray (scipy), r = f*theta."""
    f, c, n = 13.0, 20.5, 41
    cam = get_camera_class("fisheye")(width=n, height=n, f=f, cx=c, cy=c, lens="equiangular",
                                      max_fov=math.radians(190))
    off = compute_offsets(cam, (n, n), 3, 1, 1, 1)
    taps = _taps(off, 3).numpy()

    def unproject(u, v):
        mx, my = (u - c) / f, (v - c) / f
        th, ph = math.hypot(mx, my), math.atan2(my, mx)
        return np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])

    def project(p):
        th = math.acos(p[2] / np.linalg.norm(p))
        ph = math.atan2(p[1], p[0])
        return c + f * th * math.cos(ph), c + f * th * math.sin(ph)

    for oy, ox in [(5, 30), (33, 8), (20, 2), (12, 20)]:
        a = unproject(ox + 0.5, oy + 0.5)
        axis = np.cross([0.0, 0.0, 1.0], a)
        rot = Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.acos(a[2]))
        for t in range(9):
            i, j = divmod(t, 3)
            ref = unproject(c + j - 1, c + i - 1)
            u, v = project(rot.apply(ref))
            assert abs((v - 0.5) - (oy + i - 1) - taps[oy, ox, t, 0]) < 1e-9
            assert abs((u - 0.5) - (ox + j - 1) - taps[oy, ox, t, 1]) < 1e-9


def test_invalid_samples_are_masked():
    KB = get_camera_class("kannala_brandt")
    cam = KB(width=32, height=32, fx=8.0, fy=8.0, cx=16.0, cy=16.0, max_fov=math.radians(150))
    off, mask = compute_sampling(cam, (32, 32), 3, 1, 1, 1)
    assert mask[0, :, 0, 0].sum() == 0  # image corner: outside the fisheye circle
    seen = cam.unproject(cam.pixel_grid(torch.float64)).valid
    assert not seen[0, 0] and seen[16, 16]
    assert mask[0, :, 16, 16].sum() == 9
    assert torch.isfinite(off).all()
    assert off[mask.repeat_interleave(2, 1) == 0].abs().max() == 0


def test_image_padding_and_resizing():
    """The layer's camera is resized to the feature map; image padding shifts nothing left/top."""
    cam = Pinhole(width=64, height=48, fx=40.0, fy=40.0, cx=32.0, cy=24.0)
    a = compute_offsets(cam, (24, 32), 3, 1, 1, 1)
    b = compute_offsets(cam.resized(32, 24), (24, 32), 3, 1, 1, 1)
    assert torch.allclose(a, b, atol=1e-12)
    padded = compute_offsets(cam, (25, 33), 3, 1, 1, 1, image_padding=(2, 2))  # 66x50 image on a 33x25 map
    assert padded.shape[-2:] == (25, 33)


@pytest.mark.parametrize("name", list_cameras())
def test_every_registered_camera_gives_finite_offsets(name):
    for cam in get_camera_class(name).examples():
        off, mask = compute_sampling(cam, (8, 16) if cam.wraps_horizontally else (12, 12), 3, 2, 1, 1)
        assert torch.isfinite(off).all() and torch.isfinite(mask).all()
        assert mask.sum() > 0


def test_bad_configuration_errors():
    cam = Pinhole.example()
    with pytest.raises(ValueError, match="too small"):
        compute_offsets(cam, (2, 2), 7, 1, 0, 1)
    with pytest.raises(ValueError, match="wrap=True"):
        compute_offsets(cam, (8, 8), 3, 1, 1, 1, wrap=True)
    with pytest.raises(ValueError, match="kernel must be"):
        compute_offsets(cam, (8, 8), 3, 1, 1, 1, kernel="round")
