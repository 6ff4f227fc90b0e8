"""Non-central panorama: Eq. 2.14-2.16 in omnidl's frame, Plücker rays, 3D line from four rays."""
import math

import pytest
import torch

from omnidl.cameras import Equirectangular, NonCentralPanorama, build


def test_same_angles_as_equirect_and_centres_on_circle():
    cam = NonCentralPanorama(width=128, height=64, rc=0.7)
    eq = Equirectangular(width=128, height=64)
    uv = cam.pixel_grid(torch.float64).reshape(-1, 2)
    rays, rays_eq = cam.unproject(uv), eq.unproject(uv)
    assert torch.allclose(rays.direction, rays_eq.direction, atol=1e-15)
    o = rays.origin
    assert torch.allclose(torch.hypot(o[:, 0], o[:, 2]), torch.full_like(o[:, 0], 0.7)) and (o[:, 1] == 0).all()
    # the ray leaves the circle radially: its horizontal part is parallel to the centre's position
    assert torch.allclose(o[:, 0] * rays.direction[:, 2] - o[:, 2] * rays.direction[:, 0],
                          torch.zeros_like(o[:, 0]), atol=1e-15)
    assert cam.wraps_horizontally and not cam.central


def test_forward_projection_is_eq_2_14():
    cam = NonCentralPanorama(width=256, height=128, rc=1.3)
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(300, 3, dtype=torch.float64, generator=g) * 4
    uv, valid = cam.project(pts)
    x, y, z = pts.unbind(-1)
    rho = torch.hypot(x, z)
    assert valid.tolist() == (rho > 1.3).tolist()
    # Eq. 2.14 written in omnidl's frame (vertical axis -y): theta = atan2(x, z), phi = atan(-y / (rho - w Rc))
    lon = torch.atan2(x, z)
    lat = torch.atan(-y / (rho - 1.3))
    u = (lon + math.pi) / (2 * math.pi) * 256
    v = (math.pi / 2 - lat) / math.pi * 128
    assert torch.allclose(uv[valid], torch.stack([u, v], -1)[valid], atol=1e-9)
    assert torch.isfinite(uv).all()


def test_plucker_rays_meet_the_axis_and_eq_2_16():
    cam = NonCentralPanorama.example()
    uv = cam.sample_points(100, generator=torch.Generator().manual_seed(1))
    L = cam.unproject(uv).plucker()
    d, m = L[:, :3], L[:, 3:]
    # side(ray, y-axis) = d . 0 + m . (0, 1, 0) = 0 and the Plücker identity
    assert m[:, 1].abs().max() < 1e-15 and (d * m).sum(-1).abs().max() < 1e-15
    # Eq. 2.16 in omnidl's frame: m = Rc (cos lat) * (0 x ...) -> |m| = Rc |sin lat|
    lon, lat = cam.angles.uv_to_lonlat(uv)
    assert torch.allclose(m.norm(dim=-1), cam.rc * lat.sin().abs(), atol=1e-15)


def test_line_from_four_rays_is_recovered():
    from omnidl.geometry.line_from_rays import line_from_rays
    cam = NonCentralPanorama(width=1024, height=512, rc=1.0)
    # a synthetic horizontal line 1.2 m below the camera (y down), 3 m away
    p0 = torch.tensor([-2.0, 1.2, 3.0], dtype=torch.float64)
    dirn = torch.tensor([1.0, 0.0, 0.3], dtype=torch.float64)
    pts = p0 + torch.tensor([0.0, 1.0, 2.5, 4.0], dtype=torch.float64)[:, None] * dirn
    uv, valid = cam.project(pts)
    assert valid.all()
    fit = line_from_rays(cam.unproject(uv))
    assert bool(fit.ok)
    line = fit.line
    # every point of the true line lies on the recovered line (< 1e-6 m)
    d, m = line[:3], line[3:]
    dist = torch.linalg.cross(pts, d.expand_as(pts), dim=-1) - m
    assert dist.norm(dim=-1).max() < 1e-6
    # a central camera's rays are reported as degenerate
    eq = Equirectangular(width=1024, height=512)
    uv, _ = eq.project(pts)
    assert not bool(line_from_rays(eq.unproject(uv)).ok)


def test_inside_circle_invalid_and_config():
    cam = build({"type": "noncentral_pano", "width": 64, "height": 32, "rc": 1.0})
    uv, valid = cam.project(torch.tensor([[0.5, 0.0, 0.5], [0.0, 3.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64))
    assert not valid.any() and torch.isfinite(uv).all()
    with pytest.raises(ValueError, match="rc"):
        NonCentralPanorama(width=64, height=32, rc=-0.1)
    # rc = 0 degenerates to the equirect geometry
    zero, eq = NonCentralPanorama(width=64, height=32, rc=0.0), Equirectangular(width=64, height=32)
    pts = torch.randn(50, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    (uv0, v0), (uv1, v1) = zero.project(pts), eq.project(pts)
    assert torch.equal(v0, v1) and torch.allclose(uv0, uv1, atol=1e-12)
