"""Double Sphere camera (Usenko, Demmel, Cremers, "The Double Sphere Camera Model", 3DV 2018, arXiv:1807.08957).

A point ``p = (x, y, z)`` is projected through two unit spheres whose centres are ``xi``
apart, then onto the image plane by a pinhole shifted by ``alpha / (1 - alpha)`` (the paper's
projection function, as coded in Basalt's ``DoubleSphereCamera``)::

    d1 = |(x, y, z)|
    d2 = |(x, y, xi d1 + z)|
    u  = fx x / (alpha d2 + (1 - alpha) (xi d1 + z)) + cx
    v  = fy y / (alpha d2 + (1 - alpha) (xi d1 + z)) + cy

Valid points (the paper's set Omega): ``z > -w2 d1`` with
``w1 = alpha / (1 - alpha)`` if ``alpha <= 0.5`` else ``(1 - alpha) / alpha`` and
``w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1)``.

Closed-form unprojection (the paper's inverse), ``mx = (u - cx) / fx``, ``my = (v - cy) / fy``,
``r^2 = mx^2 + my^2``::

    mz = (1 - alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) r^2) + 1 - alpha)
    X  = (mz xi + sqrt(mz^2 + (1 - xi^2) r^2)) / (mz^2 + r^2) * (mx, my, mz) - (0, 0, xi)

defined for ``r^2 < 1 / (2 alpha - 1)`` when ``alpha > 0.5`` (strict, as Basalt, so
the gradient stays finite), for every ``r`` otherwise. ``X`` lies on the unit sphere. A
pixel is also marked invalid where the square root's argument is negative or the lifted
ray breaks the projection's validity condition, so valid pixels and valid points are
exactly each other's images (for ``alpha > 0.5`` the circle ``r^2 = 1 / (2 alpha - 1)`` is where
``r(theta)`` folds back, slightly beyond the image of the ray limit ``z = -w2 d1``: ~0.06 px for
TUM-VI's lens; Basalt unprojects that thin ring, omnidl does not). ``alpha = 0`` is the unified
(Mei) model, ``alpha = 0.5, xi = 0`` the stereographic fisheye.

Pixel convention: omnidl's (centre of pixel ``j`` at ``j + 0.5``); Basalt/Kalibr calibrations
put the centre of pixel 0 at 0, so their ``cx, cy`` gain ``+0.5`` here.
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
class DoubleSphere(Camera):
    """Double Sphere camera (central). Fields ``fx, fy, cx, cy`` (pixels), ``xi``, ``alpha`` in ``[0, 1]``."""

    domains: ClassVar[Mapping[str, Domain]] = {"fx": POSITIVE, "fy": POSITIVE, "alpha": between(0.0, 1.0)}
    fx: float = 1.0
    fy: float = 1.0
    cx: float = 0.0
    cy: float = 0.0
    xi: float = 0.0
    alpha: float = 0.5

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"double_sphere camera: fx, fy must be > 0, got fx={self.fx}, fy={self.fy}")
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"double_sphere camera: alpha must be in [0, 1], got {self.alpha}")
        if not math.isfinite(self.xi):
            raise ValueError(f"double_sphere camera: xi must be finite, got {self.xi}")

    # -- validity constants ---------------------------------------------------------------
    @property
    def w1(self) -> float:
        a = self.alpha
        return a / (1 - a) if a <= 0.5 else (1 - a) / a

    @property
    def w2(self) -> float:
        """Points with ``z > -w2 |p|`` project (``cos`` of the largest ray angle is ``-w2``)."""
        w1, xi = self.w1, self.xi
        return (w1 + xi) / math.sqrt(2 * w1 * xi + xi * xi + 1)

    @property
    def r2_max(self) -> float:
        """Unprojection needs ``r^2 < r2_max`` (``inf`` for ``alpha <= 0.5``)."""
        return 1 / (2 * self.alpha - 1) if self.alpha > 0.5 else math.inf

    # -- interface ---------------------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        d1 = safe_norm(points)
        ok = (d1 > 0) & (points[..., 2] > -self.w2 * d1)
        axis = torch.tensor([0.0, 0.0, 1.0], dtype=points.dtype, device=points.device)
        p = torch.where(ok.unsqueeze(-1), points, axis)
        x, y, z = p.unbind(-1)
        d1 = safe_norm(p)
        zeta = self.xi * d1 + z
        d2 = safe_norm(torch.stack([x, y, zeta], -1))
        den = self.alpha * d2 + (1 - self.alpha) * zeta
        ok = ok & (den > 0)
        den = torch.where(ok, den, torch.ones_like(den))
        u = torch.where(ok, self.fx * x / den + self.cx, torch.full_like(den, self.cx))
        v = torch.where(ok, self.fy * y / den + self.cy, torch.full_like(den, self.cy))
        uv = torch.stack([u, v], -1)
        return uv, ok & in_image(uv, self.width, self.height)

    def unproject(self, uv: Tensor) -> Rays:
        a, xi = self.alpha, self.xi
        mx = (uv[..., 0] - self.cx) / self.fx
        my = (uv[..., 1] - self.cy) / self.fy
        r2 = mx * mx + my * my
        ok = in_image(uv, self.width, self.height) & (r2 < self.r2_max)
        mx = torch.where(ok, mx, torch.zeros_like(mx))
        my = torch.where(ok, my, torch.zeros_like(my))
        r2 = mx * mx + my * my
        mz = (1 - a * a * r2) / (a * torch.sqrt(1 - (2 * a - 1) * r2) + 1 - a)
        disc = mz * mz + (1 - xi * xi) * r2
        ok = ok & (disc > 0)
        disc = torch.where(ok, disc, torch.ones_like(disc))
        k = (mz * xi + torch.sqrt(disc)) / (mz * mz + r2)
        d = torch.stack([k * mx, k * my, k * mz - xi], -1)
        d = d / safe_norm(d, keepdim=True).clamp_min(torch.finfo(d.dtype).tiny)
        ok = ok & (d[..., 2] > -self.w2)
        d = torch.where(ok.unsqueeze(-1), d, torch.tensor([0.0, 0.0, 1.0], dtype=d.dtype, device=d.device))
        return Rays(torch.zeros_like(d), d, ok)

    @classmethod
    def example(cls) -> "DoubleSphere":
        # Basalt's TUM-VI 512x512 calibration (cam0) scaled to 64 x 64: a 195 deg-class lens
        return cls(width=64, height=64, fx=158.28600034966977 / 8, fy=158.2743455478755 / 8,
                   cx=255.46116578191653 / 8, cy=257.3894394501779 / 8, xi=-0.17213086034353243,
                   alpha=0.5931177593944744)

    @classmethod
    def examples(cls) -> list["DoubleSphere"]:
        # the TUM-VI lens, then alpha < 0.5 with xi > 0 (the image is cut by z > -w2 d1, not by r2_max)
        return [cls.example(),
                cls(width=64, height=48, fx=14.0, fy=14.5, cx=32.5, cy=23.5, xi=0.6, alpha=0.3)]


register_camera("double_sphere", DoubleSphere)
