"""Kannala–Brandt fisheye, ray-based (thesis Eq. 2.9–2.11, 7.1–7.2).

A ray at angle ``theta = atan2(|(x, y)|, z)`` from the optical axis and azimuth
``psi = atan2(y, x)`` projects to::

    d(theta) = k0 theta + k1 theta^3 + k2 theta^5 + k3 theta^7 + k4 theta^9
    u = fx d(theta) cos(psi) + cx,    v = fy d(theta) sin(psi) + cy

OpenCV's ``cv2.fisheye`` is the case ``k0 = 1`` (its ``D = (k1, k2, k3, k4)``). Because
``theta`` comes from the ray (not from ``x/z``), points behind the image plane
(``theta > 90 deg``) project as long as ``theta <= max_fov / 2`` — OpenCV and kornia
cannot do this. ``unproject`` solves ``d(theta) = r`` with a safeguarded Newton iteration
(to the dtype's rounding level) and returns ``(sin theta cos psi, sin theta sin psi, cos theta)``.

``d`` must be increasing on ``[0, max_fov / 2]`` (checked at construction).

Calibration files (``from_config({"calib_file": path})``): the CalibratedConvolutions text
format, eleven numbers separated by white space/new lines —
``cx, cy, fx, fy, W, H, FOV (degrees), k1, k2, k3, k4`` — read with ``k0 = 1``.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import Tensor

from .base import Camera, Rays, in_image, safe_norm
from .registry import construct, register_camera
from .solvers import newton_polish, polyval, solve_increasing
from .validate import POSITIVE, Domain, between

KB_FILE_FIELDS = ("cx", "cy", "fx", "fy", "width", "height", "fov_deg", "k1", "k2", "k3", "k4")


def read_kb_calibration(path: str | Path) -> dict[str, Any]:
    """Read a KB calibration text file (``cx cy fx fy W H FOV k1 k2 k3 k4``) into camera fields.

    Raises ``ValueError`` naming the file when it does not hold exactly 11 numbers, or when the FOV (degrees) is
    under 10 deg (probably written in radians).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"Kannala-Brandt calibration file {str(path)!r} cannot be read as text: {e}") from e
    try:
        vals = [float(t) for t in text.replace(",", " ").split()]
    except ValueError as e:
        raise ValueError(f"Kannala-Brandt calibration file {str(path)!r}: not all entries are numbers ({e})") from e
    if len(vals) != len(KB_FILE_FIELDS):
        raise ValueError(f"Kannala-Brandt calibration file {str(path)!r}: expected {len(KB_FILE_FIELDS)} values "
                         f"({', '.join(KB_FILE_FIELDS)}), found {len(vals)}")
    v = dict(zip(KB_FILE_FIELDS, vals))
    for key in ("width", "height"):
        if v[key] != int(v[key]) or v[key] <= 0:
            raise ValueError(f"Kannala-Brandt calibration file {str(path)!r}: {key} must be a positive integer, "
                             f"got {v[key]}")
    from .io._common import MIN_FOV_DEG
    fov = v["fov_deg"]
    if 0 < fov < MIN_FOV_DEG:
        raise ValueError(f"Kannala-Brandt calibration file {str(path)!r}: FOV (7th value) = {fov:g} deg is under "
                         f"{MIN_FOV_DEG:g} deg; the file gives the field of view in degrees (was it written in "
                         f"radians? {fov:g} rad = {math.degrees(fov):.4g} deg)")
    return dict(width=int(v["width"]), height=int(v["height"]), fx=v["fx"], fy=v["fy"], cx=v["cx"], cy=v["cy"],
                k0=1.0, k1=v["k1"], k2=v["k2"], k3=v["k3"], k4=v["k4"], max_fov=math.radians(v["fov_deg"]))


@dataclass(frozen=True)
class KannalaBrandt(Camera):
    """Kannala–Brandt camera (central). ``max_fov`` is the full field of view in radians."""

    domains: ClassVar[Mapping[str, Domain]] = {"fx": POSITIVE, "fy": POSITIVE, "max_fov": between(0.0, 2 * math.pi, "(]", "in (0, 2*pi] radians")}
    fx: float = 1.0
    fy: float = 1.0
    cx: float = 0.0
    cy: float = 0.0
    k0: float = 1.0
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    max_fov: float = math.pi

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"kannala_brandt camera: fx, fy must be > 0, got fx={self.fx}, fy={self.fy}")
        if not 0 < self.max_fov < 2 * math.pi:
            raise ValueError(f"kannala_brandt camera: max_fov must be in (0, 2*pi) radians, got {self.max_fov}")
        # d'(theta) > 0 on [0, theta_max]: dense check (the derivative is a polynomial in theta^2)
        t = torch.linspace(0, self.theta_max, 4097, dtype=torch.float64)
        dd = self.distortion_derivative(t)
        if not bool((dd > 0).all()):
            bad = float(t[~(dd > 0)][0])
            raise ValueError(f"kannala_brandt camera: d(theta) = k0 theta + ... + k4 theta^9 with k=({self.k0}, "
                             f"{self.k1}, {self.k2}, {self.k3}, {self.k4}) is not increasing on [0, max_fov/2 = "
                             f"{self.theta_max:.6f}] (d'(theta) <= 0 at theta = {bad:.6f} rad); reduce max_fov or "
                             "fix the coefficients")

    # -- polynomial ------------------------------------------------------------------------
    @property
    def theta_max(self) -> float:
        return self.max_fov / 2

    @property
    def coeffs(self) -> tuple[float, ...]:
        """``d`` as a polynomial in ``theta`` (increasing degree, 0..9)."""
        return (0.0, self.k0, 0.0, self.k1, 0.0, self.k2, 0.0, self.k3, 0.0, self.k4)

    def distortion(self, theta: Tensor) -> Tensor:
        """``d(theta)`` (evaluated as ``theta * P(theta^2)``)."""
        return theta * polyval((self.k0, self.k1, self.k2, self.k3, self.k4), theta * theta)

    def distortion_derivative(self, theta: Tensor) -> Tensor:
        """``d'(theta)``."""
        return polyval((self.k0, 3 * self.k1, 5 * self.k2, 7 * self.k3, 9 * self.k4), theta * theta)

    def _d_over_sin(self, theta: Tensor) -> Tensor:
        """``d(theta) / sin(theta)``, smooth at 0 (``theta`` must stay below ``pi``)."""
        small = theta < 1e-4
        ts = torch.where(small, torch.ones_like(theta), theta)
        series = self.k0 + (self.k0 / 6 + self.k1) * theta * theta
        return torch.where(small, series, self.distortion(ts) / torch.sin(ts))

    def inverse_distortion(self, r: Tensor) -> Tensor:
        """``theta = d^{-1}(r)`` on ``[0, theta_max]`` (differentiable; ``r`` beyond ``d(theta_max)`` clamps)."""
        lo = torch.zeros_like(r)
        hi = torch.full_like(r, self.theta_max)
        theta = solve_increasing(self.distortion, self.distortion_derivative, r, lo, hi, x0=r / self.k0)
        return newton_polish(theta, lambda t: self.distortion(t) - r, self.distortion_derivative(theta))

    # -- interface ---------------------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        norm = safe_norm(points)
        theta = torch.atan2(safe_norm(points[..., :2]), points[..., 2])
        ok = (norm > 0) & (theta <= self.theta_max)
        theta_s = torch.where(ok, theta, torch.zeros_like(theta))
        scale = self._d_over_sin(theta_s) / torch.where(ok, norm, torch.ones_like(norm))
        u = self.fx * scale * points[..., 0] + self.cx
        v = self.fy * scale * points[..., 1] + self.cy
        uv = torch.stack([torch.where(ok, u, torch.full_like(u, self.cx)),
                          torch.where(ok, v, torch.full_like(v, self.cy))], -1)
        return uv, ok & in_image(uv, self.width, self.height)

    def unproject(self, uv: Tensor) -> Rays:
        m = torch.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], -1)
        r = safe_norm(m)
        r_max = float(self.distortion(torch.tensor(self.theta_max, dtype=torch.float64)))
        ok = (r <= r_max) & in_image(uv, self.width, self.height)
        r_s = torch.where(ok, r, torch.zeros_like(r))
        m = torch.where(ok.unsqueeze(-1), m, torch.zeros_like(m))
        theta = self.inverse_distortion(r_s)
        # sin(theta) / r = sin(theta) / d(theta)
        d = torch.cat([m / self._d_over_sin(theta).unsqueeze(-1), torch.cos(theta).unsqueeze(-1)], -1)
        return Rays(torch.zeros_like(d), d, ok)

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def from_config(cls, params: Mapping[str, Any]) -> "KannalaBrandt":
        """Fields, or ``calib_file`` (KB text format, see module doc) plus optional field overrides."""
        params = dict(params)
        path = params.pop("calib_file", None)
        if path is None:
            return construct(cls, params)
        params = {**read_kb_calibration(path), **params}
        try:
            return construct(cls, params)
        except (TypeError, ValueError) as e:
            raise ValueError(f"Kannala-Brandt calibration file {str(path)!r}: {e}") from e

    @classmethod
    def from_file(cls, path: str | Path) -> "KannalaBrandt":
        """Camera of a KB calibration text file."""
        return cls.from_config({"calib_file": path})

    @classmethod
    def example(cls) -> "KannalaBrandt":
        # a 195 deg lens on a 64 x 64 image (like the F195 camera of ch. 7, scaled)
        return cls(width=64, height=64, fx=17.0, fy=17.5, cx=32.0, cy=31.5, k0=1.0, k1=-0.01, k2=0.002,
                   k3=-1e-4, k4=1e-6, max_fov=math.radians(195))


register_camera("kannala_brandt", KannalaBrandt)
