"""Every registered camera works everywhere at once, with no per-model code: the data engine renders a room
through it, a ProjectedConv2d built from it runs, and a panorama is re-projected into it.

Parametrised over ``list_cameras()`` and each family's ``examples()`` (tiny images: the examples are <= 64 px).
"""
import pytest
import torch

from omnidl.cameras import Equirectangular, get_camera_class, list_cameras
from omnidl.geometry import reproject
from omnidl.nn import ProjectedConv2d
from omnidl.synth import place_camera, render, sample_room

CASES = [pytest.param(cam, id=f"{name}-{i}") for name in list_cameras()
         for i, cam in enumerate(get_camera_class(name).examples())]


@pytest.fixture(scope="module")
def room():
    return sample_room(3)


@pytest.mark.parametrize("camera", CASES)
def test_render_a_synthetic_room(camera, room):
    pose = place_camera(room, camera, 0)
    out = render(room, camera, pose, layout=False)
    H, W = camera.height, camera.width
    assert out["image"].shape == (3, H, W) and out["depth"].shape == (1, H, W)
    valid = out["valid"].reshape(H, W)
    seen = camera.unproject_grid(torch.float64).valid
    assert seen.any() and not (valid & ~seen).any()
    assert valid[seen].float().mean() > 0.99              # a closed room: every ray the camera has hits it
    assert torch.isfinite(out["image"]).all() and (out["depth"][0][valid] > 0).all()


@pytest.mark.parametrize("camera", CASES)
def test_projected_conv(camera):
    torch.manual_seed(0)
    conv = ProjectedConv2d(2, 3, 3, stride=2, padding=1, camera=camera)
    x = torch.rand(1, 2, camera.height, camera.width, requires_grad=True)
    y = conv(x)
    assert y.shape == (1, 3, (camera.height + 1) // 2, (camera.width + 1) // 2) and torch.isfinite(y).all()
    y.sum().backward()
    assert torch.isfinite(x.grad).all()


@pytest.mark.parametrize("camera", CASES)
def test_reproject_a_panorama(camera):
    pano_cam = Equirectangular(width=64, height=32)
    v = torch.linspace(0, 1, 32)[:, None].expand(32, 64)
    u = torch.linspace(0, 1, 64)[None, :].expand(32, 64)
    pano = torch.stack([u, v, u * v])[None]
    out, valid = reproject(pano, pano_cam, camera)
    assert out.shape == (1, 3, camera.height, camera.width) and torch.isfinite(out).all()
    seen = camera.unproject_grid(torch.float64).valid
    assert valid[0, 0][seen].float().mean() > 0.99        # every pixel the camera sees samples the panorama
    assert (out[0][:, ~valid[0, 0]] == 0).all()
