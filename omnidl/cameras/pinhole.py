"""Pinhole (perspective) camera: cube faces, perspective crops, rectification targets."""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from .base import Camera, Rays, in_image, normalize
from .registry import register_camera
from .validate import POSITIVE, Domain


@dataclass(frozen=True)
class Pinhole(Camera):
    """``u = fx * x / z + cx``, ``v = fy * y / z + cy``; points with ``z <= 0`` are invalid."""

    domains: ClassVar[Mapping[str, Domain]] = {"fx": POSITIVE, "fy": POSITIVE}
    fx: float = 1.0
    fy: float = 1.0
    cx: float = 0.0
    cy: float = 0.0

    @classmethod
    def from_fov(cls, width: int, height: int, fov_x: float) -> "Pinhole":
        """Square-pixel pinhole with horizontal field of view ``fov_x`` (radians), centred principal point."""
        if not 0 < fov_x < math.pi:
            raise ValueError(f"pinhole camera: fov_x must be in (0, pi) radians, got {fov_x}")
        f = 0.5 * width / math.tan(0.5 * fov_x)
        return cls(width=width, height=height, fx=f, fy=f, cx=width / 2, cy=height / 2)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z = points.unbind(-1)
        front = z > 0
        zs = torch.where(front, z, torch.ones_like(z))
        uv = torch.stack([self.fx * x / zs + self.cx, self.fy * y / zs + self.cy], -1)
        return uv, front & in_image(uv, self.width, self.height)

    def unproject(self, uv: Tensor) -> Rays:
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        d = normalize(torch.stack([x, y, torch.ones_like(x)], -1))
        return Rays(torch.zeros_like(d), d, in_image(uv, self.width, self.height))

    @property
    def K(self) -> Tensor:
        """``(3, 3)`` float64 intrinsic matrix."""
        return torch.tensor([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=torch.float64)

    @classmethod
    def example(cls) -> "Pinhole":
        return cls.from_fov(48, 32, math.radians(90))


register_camera("pinhole", Pinhole)
