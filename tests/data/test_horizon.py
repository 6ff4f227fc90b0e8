import math

import pytest
import torch

from omnidl.data.horizon import heatmaps_from_up, horizon_heatmaps
from omnidl.postprocess.gyroscope.angles import euler_to_matrix, random_rotations
from omnidl.postprocess.gyroscope.sampling import rotate_equirect


def _lonlat_grid(H, W):
    v = (torch.arange(H, dtype=torch.float64) + 0.5)
    u = (torch.arange(W, dtype=torch.float64) + 0.5)
    lat = math.pi / 2 - math.pi * v / H
    lon = 2 * math.pi * u / W - math.pi
    return lon, lat


def test_upright_maps_closed_form():
    H, W, s = 32, 64, 4.0
    hl, vp = horizon_heatmaps(torch.eye(3, dtype=torch.float64)[None], H, W, sigma_deg=s, nadir_weight=0.5)
    assert hl.shape == vp.shape == (1, 1, H, W)
    _, lat = _lonlat_grid(H, W)
    sr = math.radians(s)
    # horizon = equator: a function of latitude only
    expect = torch.exp(-lat ** 2 / (2 * sr * sr))
    assert torch.allclose(hl[0, 0], expect[:, None].expand(H, W), atol=1e-12)
    # zenith peak (north, top rows) height 1, nadir 0.5
    z = torch.exp(-(math.pi / 2 - lat) ** 2 / (2 * sr * sr)) + 0.5 * torch.exp(-(math.pi / 2 + lat) ** 2 / (2 * sr * sr))
    assert torch.allclose(vp[0, 0], z[:, None].expand(H, W).clamp(max=1), atol=1e-12)
    assert vp[0, 0, 0].mean() > 1.9 * vp[0, 0, -1].mean()


def test_maps_follow_the_rotated_panorama():
    R = euler_to_matrix(torch.tensor(0.5, dtype=torch.float64), torch.tensor(-0.4, dtype=torch.float64),
                        torch.tensor(1.2, dtype=torch.float64))
    hl0, vp0 = horizon_heatmaps(torch.eye(3, dtype=torch.float64)[None], 128, 256, sigma_deg=6)
    hl, vp = horizon_heatmaps(R[None], 128, 256, sigma_deg=6)
    hl_r = rotate_equirect(hl0, R)
    vp_r = rotate_equirect(vp0, R)
    assert (hl - hl_r).abs().mean() < 3e-3 and (vp - vp_r).abs().mean() < 3e-3


@pytest.mark.parametrize("size", [(16, 32), (64, 128), (50, 100)])
def test_any_resolution_and_up_vectors(size):
    R = random_rotations(3, generator=torch.Generator().manual_seed(0))
    hl, vp = horizon_heatmaps(R, *size)
    hl2, vp2 = heatmaps_from_up(-R[:, 1, :], *size)  # same from the up vectors
    assert torch.allclose(hl, hl2) and torch.allclose(vp, vp2)
    assert hl.shape == (3, 1, *size) and (hl >= 0).all() and (hl <= 1).all() and (vp <= 1).all()


def test_bad_arguments():
    with pytest.raises(ValueError, match="nadir_weight"):
        horizon_heatmaps(torch.eye(3)[None], 8, 16, nadir_weight=0)
    with pytest.raises(ValueError, match="rotations"):
        horizon_heatmaps(torch.zeros(2, 4), 8, 16)
    with pytest.raises(ValueError, match="up vectors"):
        heatmaps_from_up(torch.zeros(4), 8, 16)
