"""Enhanced (extended) unified camera model, EUCM (Khomutenko, Garcia, Martinet, "An Enhanced Unified
Camera Model", IEEE RA-L 2016; formulas as coded in Basalt's ``ExtendedUnifiedCamera`` and COLMAP's
``EUCM`` model).

The unified model's sphere becomes an ellipsoid of revolution (``beta``)::

    rho = sqrt(beta (x^2 + y^2) + z^2)
    u   = fx x / (alpha rho + (1 - alpha) z) + cx
    v   = fy y / (alpha rho + (1 - alpha) z) + cy

Valid points: ``z > -w rho`` with ``w = (1 - alpha) / alpha`` if ``alpha > 0.5`` else
``alpha / (1 - alpha)`` (for ``alpha <= 0.5`` this is exactly "denominator > 0"; for
``alpha > 0.5`` it also keeps the projection one-to-one).

Closed-form unprojection, ``mx = (u - cx) / fx``, ``my = (v - cy) / fy``, ``r^2 = mx^2 + my^2``::

    mz = (1 - beta alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) beta r^2) + 1 - alpha)
    d  = (mx, my, mz) / |(mx, my, mz)|

defined for ``r^2 < 1 / (beta (2 alpha - 1))`` when ``alpha > 0.5`` (strict, as Basalt), for
every ``r`` otherwise; a pixel whose lifted ray breaks ``z > -w rho`` is invalid too, so valid
pixels and valid points are exactly each other's images. ``beta = 1`` is the unified model
with ``xi = alpha / (1 - alpha)`` and focal lengths ``f / (1 - alpha)``; ``alpha = 0`` the pinhole.

Pixel convention: omnidl's (centre of pixel ``j`` at ``j + 0.5``, as COLMAP); Basalt/Kalibr
calibrations put the centre of pixel 0 at 0, so their ``cx, cy`` gain ``+0.5`` here.
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
class EUCM(Camera):
    """EUCM camera (central). Fields ``fx, fy, cx, cy`` (pixels), ``alpha`` in ``[0, 1]``, ``beta > 0``."""

    domains: ClassVar[Mapping[str, Domain]] = {"fx": POSITIVE, "fy": POSITIVE, "alpha": between(0.0, 1.0), "beta": POSITIVE}
    fx: float = 1.0
    fy: float = 1.0
    cx: float = 0.0
    cy: float = 0.0
    alpha: float = 0.5
    beta: float = 1.0

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"eucm camera: fx, fy must be > 0, got fx={self.fx}, fy={self.fy}")
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"eucm camera: alpha must be in [0, 1], got {self.alpha}")
        if not (self.beta > 0 and math.isfinite(self.beta)):
            raise ValueError(f"eucm camera: beta must be a finite number > 0, got {self.beta}")

    @property
    def w(self) -> float:
        """Points with ``z > -w rho`` project."""
        a = self.alpha
        return (1 - a) / a if a > 0.5 else a / (1 - a)

    @property
    def r2_max(self) -> float:
        """Unprojection needs ``r^2 < r2_max`` (``inf`` for ``alpha <= 0.5``)."""
        return 1 / (self.beta * (2 * self.alpha - 1)) if self.alpha > 0.5 else math.inf

    def _rho(self, x: Tensor, y: Tensor, z: Tensor) -> Tensor:
        return safe_norm(torch.stack([math.sqrt(self.beta) * x, math.sqrt(self.beta) * y, z], -1))

    # -- interface ---------------------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z = points.unbind(-1)
        rho = self._rho(x, y, z)
        ok = (rho > 0) & (z > -self.w * rho)
        axis = torch.tensor([0.0, 0.0, 1.0], dtype=points.dtype, device=points.device)
        x, y, z = torch.where(ok.unsqueeze(-1), points, axis).unbind(-1)
        den = self.alpha * self._rho(x, y, z) + (1 - self.alpha) * z
        ok = ok & (den > 0)
        den = torch.where(ok, den, torch.ones_like(den))
        u = torch.where(ok, self.fx * x / den + self.cx, torch.full_like(den, self.cx))
        v = torch.where(ok, self.fy * y / den + self.cy, torch.full_like(den, self.cy))
        uv = torch.stack([u, v], -1)
        return uv, ok & in_image(uv, self.width, self.height)

    def unproject(self, uv: Tensor) -> Rays:
        a, b = self.alpha, self.beta
        mx = (uv[..., 0] - self.cx) / self.fx
        my = (uv[..., 1] - self.cy) / self.fy
        r2 = mx * mx + my * my
        ok = in_image(uv, self.width, self.height) & (r2 < self.r2_max)
        mx = torch.where(ok, mx, torch.zeros_like(mx))
        my = torch.where(ok, my, torch.zeros_like(my))
        r2 = mx * mx + my * my
        mz = (1 - b * a * a * r2) / (a * torch.sqrt(1 - (2 * a - 1) * b * r2) + 1 - a)
        d = torch.stack([mx, my, mz], -1)
        d = d / safe_norm(d, keepdim=True)  # never 0: mz = 1 at r = 0
        ok = ok & (d[..., 2] > -self.w * self._rho(*d.unbind(-1)))
        d = torch.where(ok.unsqueeze(-1), d, torch.tensor([0.0, 0.0, 1.0], dtype=d.dtype, device=d.device))
        return Rays(torch.zeros_like(d), d, ok)

    @classmethod
    def example(cls) -> "EUCM":
        # Basalt's TUM-VI 512x512 EUCM calibration (cam0) scaled to 64 x 64: a 195 deg-class lens
        return cls(width=64, height=64, fx=191.14799836282189 / 8, fy=191.13150963902818 / 8,
                   cx=255.4585771534443 / 8, cy=257.38154645599448 / 8, alpha=0.6291060881178562,
                   beta=1.0418067381860868)

    @classmethod
    def examples(cls) -> list["EUCM"]:
        # the TUM-VI lens, then alpha < 0.5 with an elongated ellipsoid (cut by the denominator, not r2_max)
        return [cls.example(),
                cls(width=64, height=48, fx=20.0, fy=19.0, cx=31.5, cy=24.5, alpha=0.45, beta=2.5)]


register_camera("eucm", EUCM)
