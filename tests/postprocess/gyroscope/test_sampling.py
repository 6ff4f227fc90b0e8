import math

import pytest
import torch

from omnidl.cameras.equirectangular import Equirectangular
from omnidl.geometry import rotate_panorama
from omnidl.postprocess.gyroscope.angles import euler_to_matrix, rot_y
from omnidl.postprocess.gyroscope.sampling import direction_to_uv, equirect_directions, rotate_equirect, sample_equirect
from omnidl.postprocess.gyroscope.scene import procedural_panorama


def test_direction_to_uv_matches_camera_project():
    cam = Equirectangular(width=64, height=32)
    g = torch.Generator().manual_seed(0)
    d = torch.randn(500, 3, generator=g, dtype=torch.float64)
    uv, _ = cam.project(d)
    assert torch.allclose(direction_to_uv(d, 64, 32), uv, atol=1e-9)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sampling_pixel_centres_is_exact(dtype):
    img = torch.rand(2, 3, 16, 32, dtype=dtype)
    d = equirect_directions(16, 32, dtype).reshape(-1, 3)
    out = sample_equirect(img, d)
    assert torch.allclose(out, img.reshape(2, 3, -1), atol=1e-5)


def test_longitude_wraps():
    img = torch.zeros(1, 1, 8, 16, dtype=torch.float64)
    img[..., 0] = 1.0  # first column
    # exactly at longitude -pi (the seam between last and first column): half of each
    d = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    assert abs(float(sample_equirect(img, d)) - 0.5) < 1e-9


def test_yaw_by_whole_columns_is_a_roll_and_matches_geometry_rotate_panorama():
    img = procedural_panorama(None, 32, 64, seed=3, dtype=torch.float64)
    k = 5
    R = rot_y(torch.tensor(2 * math.pi * k / 64, dtype=torch.float64))
    out = rotate_equirect(img, R)
    assert torch.allclose(out, torch.roll(img, shifts=-k, dims=-1), atol=1e-9)
    R2 = euler_to_matrix(torch.tensor(0.2, dtype=torch.float64), torch.tensor(-0.3, dtype=torch.float64),
                         torch.tensor(1.0, dtype=torch.float64))
    ours = rotate_equirect(img, R2)
    theirs, _ = rotate_panorama(img, R2)
    # identical away from the two pole rows (border handling may differ there)
    assert torch.allclose(ours[..., 2:-2, :], theirs[..., 2:-2, :], atol=1e-6)


def test_procedural_scene_renders_exact_rotations():
    R = euler_to_matrix(torch.tensor(0.3, dtype=torch.float64), torch.tensor(0.2, dtype=torch.float64),
                        torch.tensor(-0.7, dtype=torch.float64))
    hi = procedural_panorama(None, 256, 512, seed=1, dtype=torch.float64)
    rendered = procedural_panorama(R, 32, 64, seed=1, dtype=torch.float64)
    resampled = sample_equirect(hi, torch.einsum("ij,hwj->hwi", R, equirect_directions(32, 64, torch.float64))
                                .reshape(-1, 3)).reshape(1, 3, 32, 64)
    assert (rendered - resampled).abs().mean() < 2e-3
