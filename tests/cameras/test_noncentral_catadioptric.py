"""Non-central catadioptric (conical/spherical mirror): reflection law and thesis Eq. 2.17/2.18."""
import math

import pytest
import torch

from omnidl.cameras import NonCentralCatadioptric, build

CONE = NonCentralCatadioptric.examples()[0]
SPHERE = NonCentralCatadioptric.examples()[1]


def _pixels(cam, n=200, seed=0):
    return cam.sample_points(n, generator=torch.Generator().manual_seed(seed))


def _plucker(origin, d):
    return torch.cat([d, torch.linalg.cross(origin, d, dim=-1)], -1)


@pytest.mark.parametrize("cam", [CONE, SPHERE], ids=lambda c: c.mirror)
def test_reflection_law(cam):
    uv = _pixels(cam)
    rays = cam.unproject(uv)
    assert rays.valid.all()
    a = torch.stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy, torch.ones(len(uv),
                     dtype=torch.float64)], -1)
    a = a / a.norm(dim=-1, keepdim=True)
    P = rays.origin
    assert torch.linalg.cross(P, a, dim=-1).norm(dim=-1).max() < 1e-14  # P on the pinhole ray
    rho = torch.hypot(P[:, 0], P[:, 1])
    if cam.mirror == "conical":  # implicit surface rho cos(tau) - (z - z_m) sin(tau) = 0 and its gradient
        surf = rho * math.cos(cam.tau) - (P[:, 2] - cam.z_m) * math.sin(cam.tau)
        n = torch.stack([P[:, 0] / rho * math.cos(cam.tau), P[:, 1] / rho * math.cos(cam.tau),
                         torch.full_like(rho, -math.sin(cam.tau))], -1)
    else:
        C = torch.tensor([0.0, 0.0, cam.z_m + cam.r_s], dtype=torch.float64)
        surf = (P - C).norm(dim=-1) - cam.r_s
        n = (P - C) / cam.r_s
    assert surf.abs().max() < 1e-14 and (rho <= cam.rim_radius + 1e-12).all()
    d = rays.direction
    assert torch.allclose((a * n).sum(-1), -(d * n).sum(-1), atol=1e-14)  # equal angles
    assert (torch.linalg.cross(a, n, dim=-1) * d).sum(-1).abs().max() < 1e-14  # coplanar
    assert ((d * n).sum(-1) > 0).all()  # leaves the mirror on the camera side of the surface
    # every reflected ray meets the mirror axis (z): side(ray, z-axis) = m_z = 0
    assert _plucker(P, d)[:, 5].abs().max() < 1e-14


def test_cone_is_thesis_eq_2_17():
    cam = CONE
    uv = _pixels(cam, seed=1)
    rays = cam.unproject(uv)
    x, y = (uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy
    r, theta, z = torch.hypot(x, y), torch.atan2(y, x), 1.0
    t2 = math.tan(2 * cam.tau)
    R_c, Z_c = cam.z_m * math.sin(2 * cam.tau), cam.z_m * (1 - math.cos(2 * cam.tau))
    cot_phi = (z + r * t2) / (z * t2 - r)
    phi = torch.atan2(torch.ones_like(cot_phi), cot_phi)
    Z_r = Z_c + R_c * cot_phi
    s = torch.sin(phi)
    xi = torch.stack([s * torch.cos(theta), s * torch.sin(theta), torch.cos(phi),
                      -Z_r * s * torch.sin(theta), Z_r * s * torch.cos(theta), torch.zeros_like(s)], -1)
    assert torch.allclose(_plucker(rays.origin, rays.direction), xi, atol=1e-12)


def test_sphere_is_thesis_eq_2_18():
    """Eq. 2.18 holds in the frame X' = (x, -y, Z_s - z) (origin at the sphere centre, z' towards the camera)."""
    cam = SPHERE
    uv = _pixels(cam, seed=2)
    rays = cam.unproject(uv)
    x, y = (uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy
    z = torch.ones_like(x)
    Z_s = cam.z_m + cam.r_s
    Z_rel = Z_s / cam.r_s
    r2, rho2 = x * x + y * y, x * x + y * y + z * z
    gamma = (-r2 * Z_rel ** 2 + rho2) * Z_rel ** 2
    sg = torch.sqrt(gamma)
    delta = 2 * r2 * Z_rel ** 4 - 2 * z * sg * Z_rel ** 2 - 3 * rho2 * Z_rel ** 2 + rho2
    eps = (-r2 + z * z) * Z_rel ** 2 + 2 * sg * z + rho2
    zeta = 2 * r2 * z * Z_rel ** 4 - z * rho2 * Z_rel ** 2 - 2 * sg * (-r2 * Z_rel ** 2 + rho2) - z * rho2
    xi = torch.stack([-x * delta, y * delta, -zeta, eps * y * Z_s, eps * x * Z_s, torch.zeros_like(x)], -1)
    xi = xi / xi[:, :3].norm(dim=-1, keepdim=True)
    flip = torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
    o = rays.origin * flip + torch.tensor([0.0, 0.0, Z_s], dtype=torch.float64)
    assert torch.allclose(_plucker(o, rays.direction * flip), xi, atol=1e-12)


@pytest.mark.parametrize("cam", [CONE, SPHERE], ids=lambda c: c.mirror)
def test_invisible_points_and_pixels(cam):
    uv = torch.tensor([[cam.cx + cam.fx * cam.r_rim * 1.01, cam.cy]], dtype=torch.float64)
    assert not cam.unproject(uv).valid.any()
    # on the axis beyond the mirror (hidden), at the camera, and inside the mirror's shadow
    pts = torch.tensor([[0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [1e-3, 0.0, 3.0]], dtype=torch.float64)
    uv, valid = cam.project(pts)
    assert not valid.any() and torch.isfinite(uv).all()


def test_bad_configs():
    with pytest.raises(ValueError, match="mirror"):
        NonCentralCatadioptric(width=8, height=8, mirror="parabolic")
    with pytest.raises(ValueError, match="silhouette"):
        NonCentralCatadioptric(width=8, height=8, mirror="spherical", z_m=0.3, r_s=0.5, rim_radius=0.45)
    with pytest.raises(ValueError, match="tau"):
        build({"type": "noncentral_catadioptric", "width": 8, "height": 8, "tau": 2.0})
