import math

import pytest
import torch

from omnidl.data.horizon import heatmaps_from_up, horizon_heatmaps
from omnidl.geometry.panorama import rotate_panorama
from omnidl.geometry.rotations import euler_to_matrix, random_tilt_rotation


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
    hl_r, _ = rotate_panorama(hl0, R)
    vp_r, _ = rotate_panorama(vp0, R)
    assert (hl - hl_r).abs().mean() < 3e-3 and (vp - vp_r).abs().mean() < 3e-3


@pytest.mark.parametrize("size", [(16, 32), (64, 128), (50, 100)])
def test_any_resolution_and_up_vectors(size):
    R = random_tilt_rotation(3, math.pi, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
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


class _Upright(torch.utils.data.Dataset):
    def __init__(self, n=3):
        from omnidl.postprocess.gyroscope.scene import procedural_panorama
        self.imgs = [procedural_panorama(None, 32, 64, seed=i)[0] for i in range(n)]

    def __len__(self):
        return len(self.imgs)

    def __getitem__(self, i):
        return {"image": self.imgs[i], "meta": {"name": f"p{i}"}}


def test_rotated_dataset_matches_exact_renders_and_targets():
    from omnidl.data.horizon import RotatedPanoramas
    from omnidl.postprocess.gyroscope.scene import procedural_panorama
    base = _Upright()
    ds = RotatedPanoramas(base, height=32, width=64, augment=False, deterministic=True, seed=3)
    s = ds[1]
    R = s["rotation"].double()
    exact = procedural_panorama(R[None], 32, 64, seed=1)[0]
    assert (s["image"] - exact)[:, 2:-2].abs().mean() < 0.02
    hl, vp = horizon_heatmaps(R[None], 16, 32)
    assert torch.allclose(s["horizon_map"], hl[0].float(), atol=1e-5) and s["vp_map"].shape == (1, 16, 32)
    assert torch.allclose(s["up"].double(), -R[1], atol=1e-6) and bool(s["geometry_valid"])
    again = ds[1]
    assert torch.equal(again["image"], s["image"])  # deterministic per index


def test_augmentations_and_crop_flag():
    from omnidl.data.horizon import RotatedPanoramas, colour_jitter
    base = _Upright(2)
    ds = RotatedPanoramas(base, height=32, width=64, flip_p=1.0, permute_p=1.0, jitter=0.3, crop_p=1.0,
                          deterministic=True, length=5)
    s = ds[4]
    assert s["meta"]["flip"] and sorted(s["meta"]["permutation"]) == [0, 1, 2]
    assert not bool(s["geometry_valid"]) and s["image"].shape == (3, 32, 64)
    assert s["image"].min() >= 0 and s["image"].max() <= 1
    img = torch.rand(3, 8, 16)
    assert torch.equal(colour_jitter(img, 0.0, torch.Generator()), img)
    with pytest.raises(ValueError, match="width = 2 height"):
        RotatedPanoramas(base, height=32, width=32)
    with pytest.raises(IndexError):
        ds[5]


def test_panorama_folder(tmp_path):
    import cv2
    import numpy as np
    from omnidl.data.horizon import PanoramaFolder
    cv2.imwrite(str(tmp_path / "e_000002.png"), np.full((16, 32, 3), 255, np.uint8))
    cv2.imwrite(str(tmp_path / "e_000001.png"), np.zeros((16, 32, 3), np.uint8))
    ds = PanoramaFolder(str(tmp_path), height=8, width=16)
    assert len(ds) == 2 and ds[0]["meta"]["name"] == "e_000001.png" and ds[1]["image"].shape == (3, 8, 16)
    assert float(ds[1]["image"].min()) == 1.0
    with pytest.raises(FileNotFoundError):
        PanoramaFolder(str(tmp_path / "missing"))
