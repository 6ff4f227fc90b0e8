"""OpenCV pinhole camera with Brown–Conrady distortion (rational radial, tangential, thin prism).

The model of ``cv2.projectPoints`` / ``cv2.calibrateCamera`` (OpenCV documentation, "Camera
Calibration and 3D Reconstruction"; Brown 1966, Conrady 1919; thin prism: Weng et al., TPAMI 1992),
without the tilted-sensor terms. A point ``(X, Y, Z)`` with ``Z > 0`` goes to::

    x = X / Z,  y = Y / Z,  r2 = x^2 + y^2
    R  = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    x' = x R + 2 p1 x y + p2 (r2 + 2 x^2) + s1 r2 + s2 r2^2
    y' = y R + p1 (r2 + 2 y^2) + 2 p2 x y + s3 r2 + s4 r2^2
    u  = fx x' + cx,   v = fy y' + cy

OpenCV's distortion vector is ``(k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4)`` (see
:meth:`OpenCVPinhole.dist_coeffs`). Pixel convention: the formula is OpenCV's with the same
numbers; OpenCV puts the centre of pixel 0 at 0 where omnidl puts it at 0.5, so a calibration from
``cv2.calibrateCamera`` is used here with ``cx + 0.5, cy + 0.5`` (readers do this; this class does not).

Validity (honest, computed at construction): the radial map ``r -> r R(r^2)`` is increasing only up
to ``r_max`` (first positive root of its derivative or of the denominator of ``R``; infinite when
there is none). A point is valid when ``Z > 0``, ``r <= r_max``, the Jacobian of the whole
distortion ``(x, y) -> (x', y')`` has a positive determinant there, and its pixel is in the image.
``unproject`` inverts the distortion with a damped 2-D Newton iteration started at the distorted
point (:func:`~omnidl.cameras.solvers.solve_2d`, to the dtype's rounding level) and is valid where it
converged inside that same region; the gradient is the implicit-function one.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from .base import Camera, Rays, normalize
from .registry import register_camera
from .distortion import (pixels_to_plane, plane_to_pixels, tangential_prism, tangential_prism_jacobian,
                         undistort_plane)
from .validate import POSITIVE, Domain

DIST_ORDER = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")


def _smallest_positive_root(coeffs_increasing: list[float]) -> float:
    """Smallest real root ``> 0`` of ``sum c_k s^k`` (``inf`` when there is none)."""
    c = np.trim_zeros(np.asarray(coeffs_increasing, dtype=np.float64), "b")
    if len(c) <= 1:
        return math.inf
    roots = np.roots(c[::-1])
    real = roots.real[(np.abs(roots.imag) <= 1e-9 * np.maximum(1.0, np.abs(roots.real))) & (roots.real > 0)]
    return float(real.min()) if len(real) else math.inf


def _polymul(a: list[float], b: list[float]) -> list[float]:
    return list(np.convolve(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)))


def _polyadd(a: list[float], b: list[float]) -> list[float]:
    n = max(len(a), len(b))
    return [(a[i] if i < len(a) else 0.0) + (b[i] if i < len(b) else 0.0) for i in range(n)]


@dataclass(frozen=True)
class OpenCVPinhole(Camera):
    """Pinhole camera with OpenCV's rational + tangential + thin-prism distortion (no tilt).

    Fields: ``fx, fy, cx, cy`` (pixels) and the distortion coefficients ``k1..k6, p1, p2, s1..s4``.
    """

    domains: ClassVar[Mapping[str, Domain]] = {"fx": POSITIVE, "fy": POSITIVE}
    fx: float = 1.0
    fy: float = 1.0
    cx: float = 0.0
    cy: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    k6: float = 0.0
    s1: float = 0.0
    s2: float = 0.0
    s3: float = 0.0
    s4: float = 0.0

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"opencv camera: fx, fy must be > 0, got fx={self.fx}, fy={self.fy}")
        for name in DIST_ORDER + ("cx", "cy"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"opencv camera: {name} must be finite, got {getattr(self, name)}")
        object.__setattr__(self, "_r_max", self._radial_limit())

    # -- distortion ----------------------------------------------------------------------------
    @property
    def dist_coeffs(self) -> tuple[float, ...]:
        """OpenCV's distortion vector ``(k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4)``."""
        return tuple(getattr(self, n) for n in DIST_ORDER)

    @property
    def r_max(self) -> float:
        """Largest undistorted radius ``|(X/Z, Y/Z)|`` up to which ``r R(r^2)`` increases (may be ``inf``)."""
        return self._r_max  # type: ignore[attr-defined]

    def _radial_limit(self) -> float:
        """First ``r > 0`` where ``d/dr [r N(s)/D(s)]`` (``s = r^2``) or ``D(s)`` vanishes.

        ``d/dr [r N/D] = [(N + 2 s N') D - 2 s N D'] / D^2`` with ``'`` = ``d/ds``.
        """
        n = [1.0, self.k1, self.k2, self.k3]
        d = [1.0, self.k4, self.k5, self.k6]
        dn = [self.k1, 2 * self.k2, 3 * self.k3]
        dd = [self.k4, 2 * self.k5, 3 * self.k6]
        n_plus = _polyadd(n, [0.0] + [2 * c for c in dn])           # N + 2 s N'
        num = _polyadd(_polymul(n_plus, d), [0.0] + [-2 * c for c in _polymul(n, dd)])
        s = min(_smallest_positive_root(num), _smallest_positive_root(d))
        return math.sqrt(s) if math.isfinite(s) else math.inf

    def _radial(self, r2: Tensor) -> tuple[Tensor, Tensor]:
        """``(N(r2), D(r2))`` of ``R = N / D``."""
        num = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        den = 1 + r2 * (self.k4 + r2 * (self.k5 + r2 * self.k6))
        return num, den

    @property
    def _prism(self) -> tuple[float, float, float, float]:
        return (self.s1, self.s2, self.s3, self.s4)

    def distort(self, xy: Tensor) -> Tensor:
        """``(..., 2)`` normalised undistorted ``(x, y)`` -> distorted ``(x', y')`` (module formula)."""
        x, y = xy[..., 0], xy[..., 1]
        num, den = self._radial(x * x + y * y)
        rad = num / den
        dx, dy = tangential_prism(xy, self.p1, self.p2, self._prism)
        return torch.stack([x * rad + dx, y * rad + dy], -1)

    def distort_jacobian(self, xy: Tensor) -> Tensor:
        """``(..., 2, 2)`` Jacobian ``d(x', y') / d(x, y)`` of :meth:`distort`."""
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        num, den = self._radial(r2)
        dnum = self.k1 + r2 * (2 * self.k2 + 3 * self.k3 * r2)
        dden = self.k4 + r2 * (2 * self.k5 + 3 * self.k6 * r2)
        rad = num / den
        drad = (dnum * den - num * dden) / (den * den)  # dR / d r2
        ta, tb, tc, td = tangential_prism_jacobian(xy, self.p1, self.p2, self._prism)
        a = rad + 2 * x * x * drad + ta
        b = 2 * x * y * drad + tb
        c = 2 * x * y * drad + tc
        d = rad + 2 * y * y * drad + td
        return torch.stack([torch.stack([a, b], -1), torch.stack([c, d], -1)], -2)

    def _regular(self, xy: Tensor) -> Tensor:
        """``(...)`` bool: ``|xy| <= r_max`` and ``det J > 0`` (the distortion is locally invertible)."""
        j = self.distort_jacobian(xy.detach())
        det = j[..., 0, 0] * j[..., 1, 1] - j[..., 0, 1] * j[..., 1, 0]
        return ((xy.detach() ** 2).sum(-1) <= self.r_max ** 2) & (det > 0)

    def undistort(self, xy_d: Tensor) -> tuple[Tensor, Tensor]:
        """Invert :meth:`distort`: ``(..., 2)`` distorted -> ``(undistorted (..., 2), ok (...))``.

        ``ok`` is False where Newton did not converge or the root leaves the invertible region;
        values stay finite there. Differentiable (implicit-function gradient).
        """
        if not any(self.dist_coeffs):
            return xy_d, torch.isfinite(xy_d).all(-1)
        return undistort_plane(self, xy_d, self.r_max)

    # -- interface -------------------------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z = points.unbind(-1)
        front = z > 0
        zs = torch.where(front, z, torch.ones_like(z))
        with torch.no_grad():
            ok = front & (((x / zs) ** 2 + (y / zs) ** 2) <= self.r_max ** 2)
        xy = torch.stack([torch.where(ok, x, torch.zeros_like(x)), torch.where(ok, y, torch.zeros_like(y))], -1)
        xy = xy / torch.where(ok, zs, torch.ones_like(zs)).unsqueeze(-1)
        return plane_to_pixels(self, xy, ok)

    def unproject(self, uv: Tensor) -> Rays:
        xy, ok = pixels_to_plane(self, uv)
        d = normalize(torch.cat([xy, torch.ones_like(xy[..., :1])], -1))
        d = torch.where(ok.unsqueeze(-1), d, torch.tensor([0.0, 0.0, 1.0], dtype=d.dtype, device=d.device))
        return Rays(torch.zeros_like(d), d, ok)

    # -- construction ------------------------------------------------------------------------------
    @property
    def K(self) -> Tensor:
        """``(3, 3)`` float64 intrinsic matrix."""
        return torch.tensor([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=torch.float64)

    @classmethod
    def example(cls) -> "OpenCVPinhole":
        # a wide-angle lens (~108 deg diagonal) on 64 x 48 (rational barrel model, tangential and thin prism terms
        # of a few pixels at the corners); the whole image lies inside the invertible region
        return cls(width=64, height=48, fx=40.0, fy=40.5, cx=32.3, cy=23.8, k1=-0.2, k2=0.05, p1=1.5e-3,
                   p2=-2e-3, k3=-0.005, k4=0.05, k5=-0.01, k6=0.002, s1=2e-3, s2=-4e-4, s3=-1.5e-3, s4=3e-4)

    @classmethod
    def examples(cls) -> list["OpenCVPinhole"]:
        # the second lens has strong barrel distortion: the image corners lie beyond the distortion's
        # invertible region (r > r_max) and are invalid
        strong = cls(width=64, height=48, fx=40.0, fy=40.0, cx=31.7, cy=24.2, k1=-0.25, p1=1e-3, p2=5e-4,
                     s1=1e-3, s3=-1e-3)
        return [cls.example(), strong]


register_camera("opencv", OpenCVPinhole)
