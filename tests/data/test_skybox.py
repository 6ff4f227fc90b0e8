import math

import cv2
import numpy as np
import pytest
import torch

from omnidl.data.skybox import Matterport3DSkybox, SKYBOX_VIEWS, skybox_rotations, stitch_skybox


def colour(lon, lat):
    """A smooth colour of the viewing direction (continuous over the whole sphere)."""
    return np.stack([0.5 + 0.4 * np.sin(lon) * np.cos(lat), 0.5 + 0.4 * np.cos(lon) * np.cos(lat),
                     0.5 + 0.4 * np.sin(lat)], -1)


def render_face(yaw_deg, pitch_deg, F):
    """A skybox face by the stitching scripts' description: the forward view pitched up by ``pitch`` then
    turned right by ``yaw`` (90° field of view), written out longhand."""
    a = (np.arange(F) + 0.5 - F / 2) / (F / 2)
    x, y = np.meshgrid(a, a)                       # image right, image down
    z = np.ones_like(x)
    p, yw = math.radians(pitch_deg), math.radians(yaw_deg)
    y1, z1 = y * math.cos(p) - z * math.sin(p), y * math.sin(p) + z * math.cos(p)      # pitch up
    x2, z2 = x * math.cos(yw) + z1 * math.sin(yw), -x * math.sin(yw) + z1 * math.cos(yw)  # turn right
    lon, lat = np.arctan2(x2, z2), np.arctan2(-y1, np.hypot(x2, z2))
    return colour(lon, lat)


def faces(F):
    return torch.from_numpy(np.stack([render_face(y, p, F) for y, p in SKYBOX_VIEWS])).permute(0, 3, 1, 2).float()


def test_rotations_match_the_face_views():
    R = skybox_rotations()
    fwd = R[:, :, 2]
    assert torch.allclose(fwd[0], torch.tensor([0.0, -1, 0], dtype=torch.float64))      # top looks up
    assert torch.allclose(fwd[2], torch.tensor([0.0, 0, 1], dtype=torch.float64))       # face 2: longitude 0
    assert torch.allclose(fwd[3], torch.tensor([1.0, 0, 0], dtype=torch.float64))       # face 3: +90° (right)
    assert torch.allclose(R[0][:, 1], torch.tensor([-1.0, 0, 0], dtype=torch.float64))  # top's image-down -> face 1


def test_stitched_panorama_matches_the_scene():
    W, H = 128, 64
    pano = stitch_skybox(faces(48), W, H).permute(1, 2, 0).numpy()
    lon = 2 * math.pi * (np.arange(W) + 0.5) / W - math.pi
    lat = math.pi / 2 - math.pi * (np.arange(H) + 0.5) / H
    truth = colour(*np.meshgrid(lon, lat))
    err = np.abs(pano - truth)
    assert np.median(err) < 2e-3 and err.max() < 0.03


def test_dataset_reads_skybox_files(tmp_path):
    d = tmp_path / "scA" / "matterport_skybox_images"
    d.mkdir(parents=True)
    fc = (faces(32).permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8)
    for k in range(6):
        cv2.imwrite(str(d / f"abc123_skybox{k}_sami.jpg"), fc[k][..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])
    ds = Matterport3DSkybox(tmp_path, height=32, width=64)
    s = ds[0]
    assert len(ds) == 1 and s["image"].shape == (3, 32, 64) and s["meta"]["name"] == "scA_abc123"
    lon = 2 * math.pi * (np.arange(64) + 0.5) / 64 - math.pi
    lat = math.pi / 2 - math.pi * (np.arange(32) + 0.5) / 32
    assert np.abs(s["image"].permute(1, 2, 0).numpy() - colour(*np.meshgrid(lon, lat))).max() < 0.05


def test_bad_faces():
    with pytest.raises(ValueError, match=r"expected faces \(6, C, F, F\), got \(5, 3, 8, 8\)"):
        stitch_skybox(torch.zeros(5, 3, 8, 8), 16, 8)


def test_config(tmp_path):
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from adapter_fixtures import instantiate_split
    d = tmp_path / "d" / "scA" / "matterport_skybox_images"
    d.mkdir(parents=True)
    for k in range(6):
        cv2.imwrite(str(d / f"p_skybox{k}_sami.jpg"), np.full((8, 8, 3), 40 * k, np.uint8))
    ds = instantiate_split(tmp_path, "matterport3d_skybox", tmp_path / "d", "predict", ["data.height=8", "data.width=16"])
    assert ds[0]["image"].shape == (3, 8, 16)
