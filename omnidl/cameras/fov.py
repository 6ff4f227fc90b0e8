"""FOV camera (Devernay, Faugeras, "Straight lines have to be straight", MVA 2001; COLMAP's ``FOV`` model).

The radius ``r = |(x / z, y / z)|`` of the normalised pinhole image is distorted to::

    r_d = atan(2 r tan(omega / 2)) / omega,        u = fx r_d / r x / z + cx,   v = fy r_d / r y / z + cy

(``omega`` is the field of view of the ideal fisheye lens; ``omega -> 0`` is the pinhole,
``r_d = r``). Closed-form inverse: ``r = tan(r_d omega) / (2 tan(omega / 2))``.

Only ``z > 0`` projects (the model lives on the pinhole plane); as ``z -> 0+`` the radius tends
to ``r_d = pi / (2 omega)``, so pixels with ``r_d omega >= pi / 2`` are invalid. Written with the
ray angle ``theta`` (``tan theta = r``) the projection is ``r_d = atan2(2 tan(omega/2) sin theta,
cos theta) / omega`` and the ray of a pixel ``(sin(phi) / r_d * m, 2 tan(omega / 2) cos(phi) / omega)``
normalised, with ``phi = omega r_d`` and ``m = ((u - cx) / fx, (v - cy) / fy)`` — both finite
and smooth down to the optical axis and up to 90 degrees.

COLMAP's convention (centre of the first pixel at ``(0.5, 0.5)``) is omnidl's: its ``cx, cy``
are used as they are. Note: COLMAP evaluates ``omega^2 < 1e-4`` with a series whose
``omega^2`` terms have the wrong sign (it is the series of the *inverse*), so for
``omega < 0.01`` it differs from the formula above by up to ``~1e-5 fx r`` pixels; omnidl
evaluates the closed form, which is accurate for every ``omega > 0``.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from .base import Camera, Rays, in_image, safe_norm
from .registry import register_camera
from .validate import POSITIVE, Domain, between


@dataclass(frozen=True)
class FOVCamera(Camera):
    """FOV camera (central). Fields ``fx, fy, cx, cy`` (pixels) and ``omega`` in ``[0, pi)`` radians."""

    domains: ClassVar[Mapping[str, Domain]] = {"fx": POSITIVE, "fy": POSITIVE, "omega": between(0.0, math.pi, "[)", "in [0, pi) radians")}
    fx: float = 1.0
    fy: float = 1.0
    cx: float = 0.0
    cy: float = 0.0
    omega: float = 0.0

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"fov camera: fx, fy must be > 0, got fx={self.fx}, fy={self.fy}")
        if not 0.0 <= self.omega < math.pi:
            raise ValueError(f"fov camera: omega must be in [0, pi) radians, got {self.omega}")

    @property
    def _c(self) -> float:
        """``2 tan(omega / 2) / omega`` (1 for the pinhole limit)."""
        w = self.omega
        return 1.0 if w == 0 else 2 * math.tan(w / 2) / w

    @property
    def rd_max(self) -> float:
        """Largest distorted radius, reached as ``z -> 0+`` (``inf`` for the pinhole)."""
        return math.inf if self.omega == 0 else math.pi / (2 * self.omega)

    def distortion(self, r: Tensor) -> Tensor:
        """``r_d(r)`` for normalised radii ``r >= 0``."""
        if self.omega == 0:
            return r
        return torch.atan(self._c * self.omega * r) / self.omega

    def undistortion(self, rd: Tensor) -> Tensor:
        """``r(r_d) = tan(r_d omega) / (2 tan(omega / 2))`` for ``0 <= r_d < rd_max``."""
        if self.omega == 0:
            return rd
        return torch.tan(rd * self.omega) / (self._c * self.omega)

    # -- interface ---------------------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        ok = points[..., 2] > 0
        axis = torch.tensor([0.0, 0.0, 1.0], dtype=points.dtype, device=points.device)
        p = torch.where(ok.unsqueeze(-1), points, axis)
        x, y, z = p.unbind(-1)
        chi = safe_norm(p[..., :2])
        w, c = self.omega, self._c
        if w == 0:
            scale = 1 / z
        else:
            # r_d / chi = atan2(c w chi, z) / (w chi); series in t = c w chi / z near the axis
            t = c * w * chi / z
            small = t < 1e-4
            chi_s = torch.where(small, torch.ones_like(chi), chi)
            scale = torch.where(small, c / z * (1 - t * t / 3), torch.atan2(c * w * chi_s, z) / (w * chi_s))
        u = torch.where(ok, self.fx * scale * x + self.cx, torch.full_like(z, self.cx))
        v = torch.where(ok, self.fy * scale * y + self.cy, torch.full_like(z, self.cy))
        uv = torch.stack([u, v], -1)
        return uv, ok & in_image(uv, self.width, self.height)

    def unproject(self, uv: Tensor) -> Rays:
        m = torch.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], -1)
        rd = safe_norm(m)
        ok = in_image(uv, self.width, self.height) & (rd < self.rd_max)
        m = torch.where(ok.unsqueeze(-1), m, torch.zeros_like(m))
        rd = safe_norm(m)
        w = self.omega
        if w == 0:
            d = torch.cat([m, torch.ones_like(rd).unsqueeze(-1)], -1)
        else:
            phi = w * rd
            small = phi < 1e-4
            phi_s = torch.where(small, torch.ones_like(phi), phi)
            sinc = torch.where(small, 1 - phi * phi / 6, torch.sin(phi_s) / phi_s)  # sin(phi) / phi
            d = torch.cat([m * sinc.unsqueeze(-1), (self._c * torch.cos(phi)).unsqueeze(-1)], -1)
        d = d / safe_norm(d, keepdim=True)
        d = torch.where(ok.unsqueeze(-1), d, torch.tensor([0.0, 0.0, 1.0], dtype=d.dtype, device=d.device))
        return Rays(torch.zeros_like(d), d, ok)

    @classmethod
    def example(cls) -> "FOVCamera":
        # a wide-angle lens (omega = 0.9 rad, like PTAM/COLMAP FOV calibrations) on 64 x 48
        return cls(width=64, height=48, fx=28.0, fy=28.5, cx=32.5, cy=23.5, omega=0.9)

    @classmethod
    def examples(cls) -> list["FOVCamera"]:
        # wide angle; a strong one whose image corners lie beyond r_d = pi / (2 omega) (invalid there)
        return [cls.example(), cls(width=64, height=64, fx=14.0, fy=14.0, cx=31.5, cy=32.5, omega=1.6)]


register_camera("fov", FOVCamera)
