"""Non-central panorama (thesis Eq. 2.14–2.16).

Same angles per pixel as the equirectangular camera (:class:`~omnidl.cameras.Equirectangular`,
longitude ``lon``, latitude ``lat``), but the optical centre of column ``u`` lies on the
horizontal circle of radius ``rc`` (metres)::

    origin(u)    = rc * (sin lon, 0, cos lon)
    direction(u, v) = (cos lat sin lon, -sin lat, cos lat cos lon)      # leaves the circle radially

so every ray meets the vertical axis (``y``) and the circle. Rays are Plücker lines
``(d, m = o x d)`` (Eq. 2.16 in omnidl's frame). Forward projection of a point ``X`` is closed
form: ``lon = atan2(x, z)`` and, with the horizontal distance ``rho = |(x, z)|``,
``lat = atan2(-y, rho - rc)`` (Eq. 2.14). Points with ``rho <= rc`` (inside the circle, not seen
by any outward ray) are invalid. ``rc = 0`` is allowed (all rays through the origin: the
``equirect`` geometry, still flagged non-central so sweeps over ``rc`` need no special case).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from .base import Camera, Rays, in_image, safe_norm
from .equirectangular import Equirectangular, lonlat_to_direction
from .registry import register_camera
from .validate import NONNEGATIVE, Domain


@dataclass(frozen=True)
class NonCentralPanorama(Camera):
    """Non-central panorama (``central = False``); angular range fields as :class:`Equirectangular`."""

    central = False

    domains: ClassVar[Mapping[str, Domain]] = {"rc": NONNEGATIVE}
    rc: float = 1.0
    lon_min: float = -math.pi
    lon_max: float = math.pi
    lat_min: float = -math.pi / 2
    lat_max: float = math.pi / 2

    def __post_init__(self) -> None:
        if not self.rc >= 0:
            raise ValueError(f"noncentral_pano camera: rc must be >= 0 metres, got {self.rc}")
        self.angles  # validates the angular range

    @property
    def angles(self) -> Equirectangular:
        """The central panorama with the same pixel -> angle map."""
        return Equirectangular(width=self.width, height=self.height, lon_min=self.lon_min, lon_max=self.lon_max,
                               lat_min=self.lat_min, lat_max=self.lat_max)

    @property
    def panoramic(self) -> bool:  # type: ignore[override]
        """Always: columns are longitudes and rows latitudes (see :attr:`Camera.panoramic`)."""
        return True

    @property
    def wraps_horizontally(self) -> bool:
        return self.angles.wraps_horizontally

    def optical_centre(self, lon: Tensor) -> Tensor:
        """``(..., 3)`` optical centre of the column at longitude ``lon``."""
        return torch.stack([self.rc * torch.sin(lon), torch.zeros_like(lon), self.rc * torch.cos(lon)], -1)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z = points.unbind(-1)
        rho = safe_norm(torch.stack([x, z], -1))
        ok = rho > self.rc
        rho_s = torch.where(ok, rho, torch.full_like(rho, self.rc + 1.0))
        xs = torch.where(ok, x, torch.zeros_like(x))
        zs = torch.where(ok, z, torch.ones_like(z))
        lon = torch.atan2(xs, zs)
        lat = torch.atan2(-torch.where(ok, y, torch.zeros_like(y)), rho_s - self.rc)
        ang = self.angles
        if ang.wraps_horizontally:
            lon = self.lon_min + torch.remainder(lon - self.lon_min, 2 * math.pi)
        uv = ang.lonlat_to_uv(lon, lat)
        if ang.wraps_horizontally:
            valid = ok & (uv[..., 1] >= 0) & (uv[..., 1] <= self.height)
        else:
            valid = ok & in_image(uv, self.width, self.height)
        return uv, valid

    def unproject(self, uv: Tensor) -> Rays:
        lon, lat = self.angles.uv_to_lonlat(uv)
        d = lonlat_to_direction(lon, lat)
        return Rays(self.optical_centre(lon), d, in_image(uv, self.width, self.height))

    @classmethod
    def example(cls) -> "NonCentralPanorama":
        return cls(width=64, height=32, rc=0.5)


register_camera("noncentral_pano", NonCentralPanorama)
