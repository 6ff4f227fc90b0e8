"""reproject / warp_grid: py360convert e2p oracle, analytic depth/labels, seamless wrap, every camera."""
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import py360convert
import pytest
import torch

from .geom_helpers import fisheye_195, render, texture
from omnidl.cameras import Equirectangular, Pinhole, get_camera_class, list_cameras
from omnidl.geometry import clear_warp_cache, euler_to_matrix, reproject, warp_grid
from omnidl.geometry.rotations import axis_angle_to_matrix

D = torch.float64
PANO = Equirectangular(width=256, height=128)


@pytest.fixture(scope="module")
def pano():
    return render(PANO)  # (1, 1, 128, 256) float64 grey levels


def deg(*a):
    return [torch.tensor(math.radians(x), dtype=D) for x in a]


# -- oracle: py360convert.e2p -------------------------------------------------------------------
@pytest.mark.parametrize("fov,u_deg,v_deg,hw", [(90, 0, 0, (48, 64)), (100, 40, 25, (60, 80)),
                                                 (70, -120, -50, (50, 50)), (60, 180, 10, (40, 40))])
def test_e2p_matches_py360convert(pano, fov, u_deg, v_deg, hw):
    """py360convert's e2p samples ``linspace(-tan, tan, n)``: pixel centres on the FOV edges, so its
    pinhole is ``f = (n - 1) / (2 tan(fov/2))``, centre ``n/2``; its ``u_deg``/``v_deg`` are our
    yaw/pitch (``R = R_y(u) R_x(v)``); its equirect pixel centres are ours."""
    ref = py360convert.e2p(pano[0, 0].float().numpy(), fov_deg=fov, u_deg=u_deg, v_deg=v_deg, out_hw=hw)
    h, w = hw
    t = math.tan(math.radians(fov) / 2)
    cam = Pinhole(width=w, height=h, fx=(w - 1) / (2 * t), fy=(h - 1) / (2 * t), cx=w / 2, cy=h / 2)
    R = euler_to_matrix(*deg(0, v_deg, u_deg))
    out, valid = reproject(pano.float(), PANO, cam, R)
    assert valid.all()
    mad = np.abs(out[0, 0].numpy() - ref).mean()
    assert mad < 1.2, mad


# -- identity, labels, depth ----------------------------------------------------------------------
def test_identity_is_exact(pano):
    for mode in ("bilinear", "nearest"):
        out, valid = reproject(pano, PANO, PANO, mode=mode)
        assert valid.all() and torch.allclose(out, pano, atol=1e-10)
    out, valid = reproject(pano[0, 0], PANO, PANO)  # (H, W) in, (H, W) out
    assert out.shape == (128, 256) and valid.shape == (128, 256)


BOX_LO = torch.tensor([-2.2, -1.5, -2.5], dtype=D)
BOX_HI = torch.tensor([1.8, 1.3, 3.1], dtype=D)


def box_range_and_face(d):
    """Range from the origin to the inside of an axis-aligned box, and the face hit (0..5)."""
    bound = torch.where(d > 0, BOX_HI, BOX_LO)
    t = torch.where(d.abs() > 1e-12, bound / torch.where(d.abs() > 1e-12, d, torch.ones_like(d)),
                    torch.full_like(d, 1e9))
    rng, axis = t.min(-1)
    face = 2 * axis + (d.gather(-1, axis[..., None])[..., 0] > 0).long()
    return rng, face


def test_depth_and_labels_reproject(pano):
    pano_cam = Equirectangular(width=256, height=128)
    d = pano_cam.unproject_grid(dtype=D).direction
    depth, labels = box_range_and_face(d)
    cam = Pinhole.from_fov(40, 32, math.radians(80))
    R = euler_to_matrix(*deg(5, 20, -60))
    dd = cam.unproject_grid(dtype=D).direction
    true_depth, true_labels = box_range_and_face(torch.einsum("ij,hwj->hwi", R, dd))  # src frame rays
    for mode in ("nearest", "bilinear"):
        out, valid = reproject(depth[None, None].float(), pano_cam, cam, R.float(), mode=mode)
        rel = ((out[0, 0].double() - true_depth) / true_depth).abs()
        assert valid.all() and rel.median() < 0.01 and (rel < 0.05).double().mean() > 0.95
    lab, valid = reproject(labels[None, None], pano_cam, cam, R, mode="nearest")
    assert lab.dtype == torch.int64 and set(lab.unique().tolist()) <= set(labels.unique().tolist())
    assert (lab[0, 0] == true_labels).double().mean() > 0.97
    with pytest.raises(TypeError, match="nearest"):
        reproject(labels[None, None], pano_cam, cam, R, mode="bilinear")


def test_rotation_keeps_range():
    """Range is invariant to rotation: depth seen through any rotation equals the rotated scene's range."""
    cam = Equirectangular(width=128, height=64)
    d = cam.unproject_grid(dtype=D).direction
    depth, _ = box_range_and_face(d)
    R = euler_to_matrix(*deg(10, -15, 40))
    out, _ = reproject(depth[None, None], cam, cam, R, mode="nearest")
    true, _ = box_range_and_face(torch.einsum("ij,hwj->hwi", R, d))
    assert ((out[0, 0] - true).abs() / true < 0.03).double().mean() > 0.95


# -- wrap -----------------------------------------------------------------------------------------
def test_horizontal_wrap_is_seamless():
    cam = Equirectangular(width=64, height=32)
    img = render(cam)
    half_px = 0.5 * 2 * math.pi / 64
    R = euler_to_matrix(torch.zeros((), dtype=D), torch.zeros((), dtype=D), torch.tensor(half_px, dtype=D))
    out, valid = reproject(img, cam, cam, R)
    assert valid.all()
    true = texture(torch.einsum("ij,hwj->hwi", R, cam.unproject_grid(dtype=D).direction))
    err = (out[0, 0] - true).abs()[4:-4]  # away from the poles
    seam = err[:, [0, -1]].max()
    inner = err[:, 2:-2].max()
    assert seam <= 1.5 * inner + 1e-9, (float(seam), float(inner))
    # the last column really samples across the seam, between the centres of columns W-1 and 0
    u_last = warp_grid(cam, cam, R, dtype=D).uv[0, :, -1, 0]
    assert ((u_last > 63.5) | (u_last < 0.5)).all()


# -- batching, caching, gradients, errors -------------------------------------------------------------
def test_batches_broadcast(pano, gen):
    cam = Pinhole.from_fov(16, 12, math.radians(70))
    R = axis_angle_to_matrix(0.5 * torch.randn(3, 3, generator=gen, dtype=D))
    out, valid = reproject(pano, PANO, cam, R)
    assert out.shape == (3, 1, 12, 16) and valid.shape == (3, 1, 12, 16)
    for i in range(3):
        single, _ = reproject(pano, PANO, cam, R[i])
        assert torch.allclose(out[i], single[0])
    two = torch.cat([pano, 2 * pano])
    out2, _ = reproject(two, PANO, cam, R[:2])
    assert torch.allclose(out2[1], 2 * out[1])
    with pytest.raises(ValueError, match="broadcast"):
        reproject(two, PANO, cam, R)


def test_grid_cache():
    clear_warp_cache()
    cam = Pinhole.from_fov(8, 8, math.radians(60))
    R = euler_to_matrix(*deg(0, 10, 20))
    g1 = warp_grid(PANO, cam, R)
    assert warp_grid(PANO, cam, R.clone()) is g1
    assert warp_grid(PANO, cam, euler_to_matrix(*deg(0, 10, 21))) is not g1
    assert warp_grid(PANO, cam, R, cache=False) is not g1
    Rg = R.clone().requires_grad_()
    assert warp_grid(PANO, cam, Rg) is not warp_grid(PANO, cam, Rg)


def test_gradcheck_image_and_rotation():
    src = Equirectangular(width=16, height=8)
    cam = Pinhole.from_fov(5, 4, math.radians(60))
    img = torch.rand(1, 2, 8, 16, dtype=D, requires_grad=True)
    R = euler_to_matrix(*deg(3, 20, 30))
    assert torch.autograd.gradcheck(lambda x: reproject(x, src, cam, R)[0], (img,))
    w = torch.tensor([0.05, 0.3, -0.1], dtype=D, requires_grad=True)
    smooth = render(src)
    assert torch.autograd.gradcheck(lambda v: reproject(smooth, src, cam, axis_angle_to_matrix(v))[0], (w,),
                                    atol=1e-5)


@dataclass(frozen=True)
class _NonCentral(Equirectangular):
    central: ClassVar[bool] = False


def test_errors(pano):
    cam = Pinhole.from_fov(8, 8, math.radians(60))
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        reproject(pano, PANO, cam, torch.eye(2))
    with pytest.raises(ValueError, match="256x128"):
        reproject(pano[..., :100], PANO, cam)
    with pytest.raises(ValueError, match="non-central"):
        reproject(pano, _NonCentral(width=256, height=128), cam)
    with pytest.raises(ValueError, match="mode"):
        reproject(pano, PANO, cam, mode="cubic")
    with pytest.raises(ValueError, match="NaN"):
        reproject(pano, PANO, cam, torch.full((3, 3), float("nan")))


# -- every registered camera (and a fisheye stand-in) can be rendered from a panorama -----------------
def _examples():
    cams = [("fisheye195_standin", fisheye_195(48))]
    for name in list_cameras():
        try:
            cams.append((name, get_camera_class(name).example()))
        except NotImplementedError:
            pass
    return cams


@pytest.mark.parametrize("name,cam", _examples(), ids=lambda x: x if isinstance(x, str) else "")
def test_render_every_camera_from_panorama(pano, name, cam):
    out, valid = reproject(pano.float(), PANO, cam)
    rays = cam.unproject_grid(dtype=D)
    true = texture(rays.direction)
    v = valid[0, 0] & rays.valid
    assert v.sum() > 0.2 * v.numel()
    assert (out[0, 0][~valid[0, 0]] == 0).all()
    mad = (out[0, 0].double() - true)[v].abs().mean()
    assert mad < 1.2, (name, float(mad))


def test_module_wrapper_and_dtypes(pano):
    from omnidl.geometry import Reprojector
    cam = Pinhole.from_fov(12, 10, math.radians(60))
    R = euler_to_matrix(*deg(0, 10, 30))
    m = Reprojector(PANO, cam)
    out32, _ = m(pano.float(), R.float())
    out64, _ = reproject(pano, PANO, cam, R)
    assert out32.dtype == torch.float32 and out64.dtype == torch.float64
    assert (out32.double() - out64).abs().max() < 1e-3
    with pytest.raises(ValueError, match="mode"):
        Reprojector(PANO, cam, mode="area")


def test_masked_equals_bilinear_without_holes_and_is_differentiable(pano):
    """``mode="masked"`` is plain bilinear on a map without invalid values (any camera, seam included),
    and differentiable w.r.t. the image and the rotation."""
    depth = 1.0 + pano                                        # no zeros
    cam = fisheye_195(32)
    R = euler_to_matrix(*deg(5, -20, 170))
    a, va = reproject(depth, PANO, cam, R, mode="bilinear", cache=False)
    b, vb = reproject(depth, PANO, cam, R, mode="masked", cache=False)
    assert torch.equal(va, vb) and torch.allclose(a, b, atol=1e-12)
    small = Equirectangular(width=16, height=8)
    img = (1.0 + torch.rand(1, 1, 8, 16, dtype=D)).requires_grad_()
    angles = torch.tensor([0.1, 0.2, 0.3], dtype=D, requires_grad=True)
    torch.autograd.gradcheck(lambda im, ang: reproject(im, small, Pinhole.from_fov(6, 5, 1.0),
                                                       euler_to_matrix(*ang), mode="masked", cache=False)[0],
                             (img, angles))


def test_masked_sampling_of_a_wrong_mode_or_integer_image_is_an_error(pano):
    cam = Pinhole.from_fov(8, 8, math.radians(60))
    with pytest.raises(ValueError, match="mode must be one of"):
        reproject(pano, PANO, cam, mode="masked_bilinear")
    with pytest.raises(TypeError, match="masked sampling needs a floating image"):
        reproject((pano * 100).long(), PANO, cam, mode="masked")
