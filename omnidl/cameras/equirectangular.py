"""Equirectangular (longitude/latitude) panorama, thesis Eq. 2.2–2.4.

Pixel ``(u, v)`` of a ``W x H`` image with longitude range ``[lon_min, lon_max]`` and
latitude range ``[lat_min, lat_max]`` (radians) has::

    lon = lon_min + (lon_max - lon_min) * u / W
    lat = lat_max - (lat_max - lat_min) * v / H
    direction = (cos(lat) sin(lon), -sin(lat), cos(lat) cos(lon))     # OpenCV frame

With the defaults (full sphere) column ``W/2`` looks along ``+z`` and the top row
looks up (``-y``). A narrower range gives a partial panorama (configurable FOV).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .base import Camera, Rays, in_image, safe_norm
from .registry import register_camera


def direction_to_lonlat(d: Tensor) -> tuple[Tensor, Tensor]:
    """``d (..., 3)`` (any length) -> longitude, latitude ``(...)`` in radians.

    Longitude is ``atan2(x, z)`` in ``(-pi, pi]``, latitude ``atan2(-y, hypot(x, z))``.
    Gradients are finite everywhere (the poles and the origin use safe substitutes).
    """
    x, y, z = d.unbind(-1)
    horiz = safe_norm(torch.stack([x, z], -1))
    pole = horiz <= 0
    lon = torch.atan2(torch.where(pole, torch.zeros_like(x), x), torch.where(pole, torch.ones_like(z), z))
    lat = torch.atan2(-y, horiz)
    origin = pole & (y == 0)
    lat = torch.where(origin, torch.zeros_like(lat), lat)
    return lon, lat


def lonlat_to_direction(lon: Tensor, lat: Tensor) -> Tensor:
    """Longitude/latitude ``(...)`` -> unit directions ``(..., 3)`` in the camera frame."""
    c = torch.cos(lat)
    return torch.stack([c * torch.sin(lon), -torch.sin(lat), c * torch.cos(lon)], -1)


@dataclass(frozen=True)
class Equirectangular(Camera):
    """Equirectangular panorama (central, optionally partial field of view)."""

    lon_min: float = -math.pi
    lon_max: float = math.pi
    lat_min: float = -math.pi / 2
    lat_max: float = math.pi / 2

    def __post_init__(self) -> None:
        if not (self.lon_max > self.lon_min and self.lat_max > self.lat_min):
            raise ValueError(f"equirectangular camera: empty angular range lon=[{self.lon_min}, {self.lon_max}], "
                             f"lat=[{self.lat_min}, {self.lat_max}]")
        if self.lon_max - self.lon_min > 2 * math.pi + 1e-9 or self.lat_min < -math.pi / 2 - 1e-9 \
                or self.lat_max > math.pi / 2 + 1e-9:
            raise ValueError("equirectangular camera: longitude range must span at most 2*pi and latitudes lie "
                             "in [-pi/2, pi/2]")

    @property
    def panoramic(self) -> bool:  # type: ignore[override]
        """Always: columns are longitudes and rows latitudes (see :attr:`Camera.panoramic`)."""
        return True

    @property
    def wraps_horizontally(self) -> bool:
        return abs(self.lon_max - self.lon_min - 2 * math.pi) < 1e-9

    def uv_to_lonlat(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        """Pixels ``(..., 2)`` -> longitude, latitude ``(...)`` (Eq. 2.3)."""
        lon = self.lon_min + (self.lon_max - self.lon_min) * uv[..., 0] / self.width
        lat = self.lat_max - (self.lat_max - self.lat_min) * uv[..., 1] / self.height
        return lon, lat

    def lonlat_to_uv(self, lon: Tensor, lat: Tensor) -> Tensor:
        """Longitude, latitude ``(...)`` -> pixels ``(..., 2)`` (Eq. 2.2)."""
        u = (lon - self.lon_min) / (self.lon_max - self.lon_min) * self.width
        v = (self.lat_max - lat) / (self.lat_max - self.lat_min) * self.height
        return torch.stack([u, v], -1)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        lon, lat = direction_to_lonlat(points)
        if self.wraps_horizontally:
            # bring longitude into [lon_min, lon_min + 2 pi)
            lon = self.lon_min + torch.remainder(lon - self.lon_min, 2 * math.pi)
        uv = self.lonlat_to_uv(lon, lat)
        nonzero = safe_norm(points) > 0
        valid = nonzero & in_image(uv, self.width, self.height)
        if self.wraps_horizontally:  # u == W after rounding is column 0 again
            valid = nonzero & (uv[..., 1] >= 0) & (uv[..., 1] <= self.height)
        return uv, valid

    def unproject(self, uv: Tensor) -> Rays:
        lon, lat = self.uv_to_lonlat(uv)
        d = lonlat_to_direction(lon, lat)
        valid = in_image(uv, self.width, self.height)
        return Rays(torch.zeros_like(d), d, valid)

    @classmethod
    def example(cls) -> "Equirectangular":
        return cls(width=64, height=32)


register_camera("equirect", Equirectangular)
