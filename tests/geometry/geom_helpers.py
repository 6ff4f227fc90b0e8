"""Helpers of the geometry tests: a smooth texture on the sphere, a stand-in fisheye,
and rays of a non-central panorama written from docs/design.md#conventions (independent of omnidl)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from omnidl.cameras.base import Camera, Rays, in_image


def texture(d: torch.Tensor) -> torch.Tensor:
    """A smooth grey-level function of the direction ``d (..., 3)`` (unit), values in about [8, 247]."""
    x, y, z = d.unbind(-1)
    return 127.5 + 60 * torch.sin(3 * x + 1) * torch.cos(2 * y) + 60 * torch.sin(2.5 * z + y)


def render(camera: Camera, fn=texture, dtype=torch.float64) -> torch.Tensor:
    """``(1, 1, H, W)`` image of ``fn`` seen by a central ``camera`` (0 where invalid)."""
    rays = camera.unproject_grid(dtype=dtype)
    img = torch.where(rays.valid, fn(rays.direction), torch.zeros((), dtype=dtype))
    return img[None, None]


@dataclass(frozen=True)
class EquiangularFisheye(Camera):
    """Test stand-in: equiangular fisheye ``r = f * theta`` with a field of view up to ``max_fov``."""

    f: float = 10.0
    cx: float = 0.0
    cy: float = 0.0
    max_fov: float = math.radians(195)

    def project(self, points):
        x, y, z = points.unbind(-1)
        rxy = torch.sqrt(x * x + y * y + 1e-300)
        theta = torch.atan2(rxy, z)
        r = self.f * theta
        uv = torch.stack([self.cx + r * x / rxy, self.cy + r * y / rxy], -1)
        return uv, (theta <= self.max_fov / 2) & in_image(uv, self.width, self.height)

    def unproject(self, uv):
        dx, dy = uv[..., 0] - self.cx, uv[..., 1] - self.cy
        r = torch.sqrt(dx * dx + dy * dy + 1e-300)
        theta = r / self.f
        d = torch.stack([torch.sin(theta) * dx / r, torch.sin(theta) * dy / r, torch.cos(theta)], -1)
        valid = (theta <= self.max_fov / 2) & in_image(uv, self.width, self.height)
        return Rays(torch.zeros_like(d), d, valid)


def fisheye_195(size: int = 64) -> EquiangularFisheye:
    """A 195° equiangular fisheye whose image circle touches the image borders."""
    fov = math.radians(195)
    return EquiangularFisheye(width=size, height=size, f=(size / 2) / (fov / 2), cx=size / 2, cy=size / 2, max_fov=fov)


def noncentral_panorama_rays(points: torch.Tensor, rc: float = 1.0) -> torch.Tensor:
    """Plücker rays ``(..., 6)`` of a non-central panorama (radius ``rc``) seeing ``points (..., 3)``.

    docs/design.md#conventions: the optical centre of longitude ``lon`` is ``rc (sin lon, 0, cos lon)``; the ray
    leaves radially, so the ray of a point lies in the half plane of the point's longitude.
    """
    lon = torch.atan2(points[..., 0], points[..., 2])
    o = rc * torch.stack([torch.sin(lon), torch.zeros_like(lon), torch.cos(lon)], -1)
    d = points - o
    d = d / d.norm(dim=-1, keepdim=True)
    return torch.cat([d, torch.linalg.cross(o, d, dim=-1)], -1)

