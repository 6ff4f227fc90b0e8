"""Fisheye624: Kannala–Brandt theta polynomial + tangential + thin prism (Project Aria glasses).

Project Aria's ``FisheyeRadTanThinPrism`` ("Fisheye624": 6 radial, 2 tangential, 4 thin-prism
coefficients; projectaria_tools docs, "Camera intrinsic models"), the same as COLMAP's
``RAD_TAN_THIN_PRISM_FISHEYE`` (src/colmap/sensor/models.h, ``RadTanThinPrismFisheyeModel``;
parameters ``fx, fy, cx, cy, k0..k5, p0, p1, s0..s3``). A point ``X`` at angle
``theta = atan2(|(X, Y)|, Z)`` from the optical axis and azimuth ``psi`` goes to::

    theta_d = theta + k0 theta^3 + k1 theta^5 + k2 theta^7 + k3 theta^9 + k4 theta^11 + k5 theta^13
    (x, y)  = theta_d (cos psi, sin psi)
    r2 = x^2 + y^2
    x' = x + 2 p1 x y + p0 (r2 + 2 x^2) + s0 r2 + s1 r2^2
    y' = y + 2 p0 x y + p1 (r2 + 2 y^2) + s2 r2 + s3 r2^2
    u  = fx x' + cx,   v = fy y' + cy

Note the tangential pair is ``p0`` with ``r2 + 2 x^2`` (OpenCV's ``p2`` position) and ``p1`` with
``r2 + 2 y^2``. COLMAP's pixel convention is omnidl's (first pixel centre at ``(0.5, 0.5)``), so its
parameters are used unchanged. Because ``theta`` comes from the ray, points behind the image plane
project as long as ``theta <= max_fov / 2`` (COLMAP and Aria's tools stop at 90 deg).

Validity: ``theta_d`` must increase on ``[0, max_fov / 2]`` (checked at construction) and the
tangential/prism map ``(x, y) -> (x', y')`` must be locally invertible (positive Jacobian
determinant) at the point. ``unproject`` inverts that map with a damped 2-D Newton iteration from
``(x', y')`` (:func:`~omnidl.cameras.solvers.solve_2d`), then ``theta_d(theta) = |(x, y)|`` with the
safeguarded 1-D Newton of :func:`~omnidl.cameras.solvers.solve_increasing`; both carry
implicit-function gradients. With ``p = s = 0`` and ``k4 = k5 = 0`` this is
:class:`~omnidl.cameras.KannalaBrandt` with ``(k0, k1..k4) = (1, k0..k3)``.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from .base import Camera, Rays, safe_norm
from .registry import register_camera
from .distortion import (pixels_to_plane, plane_to_pixels, tangential_prism, tangential_prism_jacobian,
                         undistort_plane)
from .solvers import newton_polish, polyval, solve_increasing
from .validate import POSITIVE, Domain, between


@dataclass(frozen=True)
class Fisheye624(Camera):
    """Fisheye624 / RAD_TAN_THIN_PRISM_FISHEYE camera (central). ``max_fov`` is the full field of view in radians."""

    domains: ClassVar[Mapping[str, Domain]] = {"fx": POSITIVE, "fy": POSITIVE, "max_fov": between(0.0, 2 * math.pi, "(]", "in (0, 2*pi] radians")}
    fx: float = 1.0
    fy: float = 1.0
    cx: float = 0.0
    cy: float = 0.0
    k0: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    p0: float = 0.0
    p1: float = 0.0
    s0: float = 0.0
    s1: float = 0.0
    s2: float = 0.0
    s3: float = 0.0
    max_fov: float = math.pi

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"fisheye624 camera: fx, fy must be > 0, got fx={self.fx}, fy={self.fy}")
        if not 0 < self.max_fov < 2 * math.pi:
            raise ValueError(f"fisheye624 camera: max_fov must be in (0, 2*pi) radians, got {self.max_fov}")
        t = torch.linspace(0, self.theta_max, 4097, dtype=torch.float64)
        dd = self.theta_d_derivative(t)
        if not bool((dd > 0).all()):
            bad = float(t[~(dd > 0)][0])
            raise ValueError(f"fisheye624 camera: theta_d = theta + k0 theta^3 + ... + k5 theta^13 with k=("
                             f"{self.k0}, {self.k1}, {self.k2}, {self.k3}, {self.k4}, {self.k5}) is not increasing on "
                             f"[0, max_fov/2 = {self.theta_max:.6f}] (derivative <= 0 at theta = {bad:.6f} rad); "
                             "reduce max_fov or fix the coefficients")

    # -- radial part (theta polynomial) ------------------------------------------------------------
    @property
    def theta_max(self) -> float:
        return self.max_fov / 2

    @property
    def _even(self) -> tuple[float, ...]:
        """``theta_d / theta`` as a polynomial in ``theta^2``."""
        return (1.0, self.k0, self.k1, self.k2, self.k3, self.k4, self.k5)

    def theta_d(self, theta: Tensor) -> Tensor:
        """``theta_d(theta)``."""
        return theta * polyval(self._even, theta * theta)

    def theta_d_derivative(self, theta: Tensor) -> Tensor:
        """``d theta_d / d theta``."""
        return polyval(tuple((2 * i + 1) * c for i, c in enumerate(self._even)), theta * theta)

    def _td_over_sin(self, theta: Tensor) -> Tensor:
        """``theta_d(theta) / sin(theta)``, smooth at 0 (``theta < pi``)."""
        small = theta < 1e-4
        ts = torch.where(small, torch.ones_like(theta), theta)
        series = 1 + (1 / 6 + self.k0) * theta * theta
        return torch.where(small, series, self.theta_d(ts) / torch.sin(ts))

    def inverse_theta_d(self, rho: Tensor) -> Tensor:
        """``theta`` with ``theta_d(theta) = rho`` on ``[0, theta_max]`` (differentiable; clamps beyond)."""
        lo = torch.zeros_like(rho)
        hi = torch.full_like(rho, self.theta_max)
        theta = solve_increasing(self.theta_d, self.theta_d_derivative, rho, lo, hi, x0=rho)
        return newton_polish(theta, lambda t: self.theta_d(t) - rho, self.theta_d_derivative(theta))

    @property
    def rho_max(self) -> float:
        """``theta_d(max_fov / 2)``: radius of the valid disk on the (undistorted) fisheye plane."""
        return float(self.theta_d(torch.tensor(self.theta_max, dtype=torch.float64)))

    # -- tangential + thin prism part -----------------------------------------------------------------
    @property
    def _has_tangential(self) -> bool:
        return any((self.p0, self.p1, self.s0, self.s1, self.s2, self.s3))

    def distort(self, xy: Tensor) -> Tensor:
        """``(..., 2)`` fisheye-plane ``(x, y)`` -> ``(x', y')`` (tangential and thin prism terms)."""
        dx, dy = tangential_prism(xy, self.p1, self.p0, (self.s0, self.s1, self.s2, self.s3))
        return torch.stack([xy[..., 0] + dx, xy[..., 1] + dy], -1)

    def distort_jacobian(self, xy: Tensor) -> Tensor:
        """``(..., 2, 2)`` Jacobian ``d(x', y') / d(x, y)``."""
        a, b, c, d = tangential_prism_jacobian(xy, self.p1, self.p0, (self.s0, self.s1, self.s2, self.s3))
        return torch.stack([torch.stack([1 + a, b], -1), torch.stack([c, 1 + d], -1)], -2)

    def _regular(self, xy: Tensor) -> Tensor:
        """``(...)`` bool: the tangential/prism map is locally invertible at ``xy`` (``det J > 0``)."""
        if not self._has_tangential:
            return torch.ones_like(xy[..., 0], dtype=torch.bool)
        j = self.distort_jacobian(xy.detach())
        return j[..., 0, 0] * j[..., 1, 1] - j[..., 0, 1] * j[..., 1, 0] > 0

    def undistort(self, xy_d: Tensor) -> tuple[Tensor, Tensor]:
        """Invert :meth:`distort` (``(..., 2)`` -> ``(..., 2)``, ``ok (...)``); implicit-function gradient."""
        if not self._has_tangential:
            return xy_d, torch.isfinite(xy_d).all(-1)
        return undistort_plane(self, xy_d, self.rho_max)

    # -- interface -------------------------------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        norm = safe_norm(points)
        theta = torch.atan2(safe_norm(points[..., :2]), points[..., 2])
        ok = (norm > 0) & (theta <= self.theta_max)
        theta_s = torch.where(ok, theta, torch.zeros_like(theta))
        scale = self._td_over_sin(theta_s) / torch.where(ok, norm, torch.ones_like(norm))
        xy = scale.unsqueeze(-1) * torch.where(ok.unsqueeze(-1), points[..., :2], torch.zeros_like(points[..., :2]))
        return plane_to_pixels(self, xy, ok)

    def unproject(self, uv: Tensor) -> Rays:
        xy, ok = pixels_to_plane(self, uv)
        rho = safe_norm(xy)
        ok = ok & (rho <= self.rho_max)
        rho = torch.where(ok, rho, torch.zeros_like(rho))
        xy = torch.where(ok.unsqueeze(-1), xy, torch.zeros_like(xy))
        theta = self.inverse_theta_d(rho)
        # sin(theta) / rho = sin(theta) / theta_d(theta)
        d = torch.cat([xy / self._td_over_sin(theta).unsqueeze(-1), torch.cos(theta).unsqueeze(-1)], -1)
        return Rays(torch.zeros_like(d), d, ok)

    @property
    def colmap_params(self) -> tuple[float, ...]:
        """COLMAP's RAD_TAN_THIN_PRISM_FISHEYE parameter list ``fx, fy, cx, cy, k0..k5, p0, p1, s0..s3``."""
        return (self.fx, self.fy, self.cx, self.cy, self.k0, self.k1, self.k2, self.k3, self.k4, self.k5,
                self.p0, self.p1, self.s0, self.s1, self.s2, self.s3)

    @classmethod
    def example(cls) -> "Fisheye624":
        # a 200 deg lens on 64 x 64 (Aria-like coefficients, tangential/prism terms enlarged to ~0.5 px)
        return cls(width=64, height=64, fx=17.5, fy=17.8, cx=32.2, cy=31.6, k0=0.02, k1=-0.012, k2=0.004,
                   k3=-6e-4, k4=4e-5, k5=-1e-6, p0=2e-3, p1=-1.5e-3, s0=2.5e-3, s1=-4e-4, s2=-2e-3, s3=3e-4,
                   max_fov=math.radians(200))


register_camera("fisheye624", Fisheye624)
