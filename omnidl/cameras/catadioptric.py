"""Central catadioptric cameras: the unified sphere model (thesis Eq. 2.7–2.8, Table 2.3) and Mei's model.

Unified / Mei model (``unified``), exactly as OpenCV's ``cv2.omnidir.projectPoints``::

    X_s = X / |X|                                     # point on the unit sphere
    (x, y) = (X_s,x, X_s,y) / (X_s,z + xi)            # projection from (0, 0, -xi)
    r2 = x^2 + y^2
    x_d = x (1 + k1 r2 + k2 r2^2) + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y (1 + k1 r2 + k2 r2^2) + p1 (r2 + 2 y^2) + 2 p2 x y
    u = fx x_d + s y_d + cx,     v = fy y_d + cy

A point is visible when ``X_s,z > -min(xi, 1/xi)`` (the lifting below is then the inverse)
and the distortion is locally invertible (positive Jacobian). ``unproject`` undistorts
with Newton's method (to the dtype's rounding level) and lifts to the sphere (Eq. 2.8)::

    X = ((xi + sqrt(1 + (1 - xi^2) r2)) / (1 + r2)) * (x, y, 1) - (0, 0, xi)

Sphere model of central mirrors (``catadioptric``): Table 2.3 gives ``xi`` and ``eta`` from the
mirror's ``d`` (camera–mirror distance) and ``p`` (``2p`` = semi-latus rectum):
para ``xi = 1, eta = -2p``; hyper ``xi = d / sqrt(d^2 + 4p^2), eta = -2p / sqrt(d^2 + 4p^2)``.
With ``H_c = K_c M_c``, ``M_c = diag(-eta, eta, 1)`` (Eq. 2.7) the camera is the unified model
with focal lengths ``(-eta fx, -eta fy)`` and no distortion, written in omnidl's frame (x right,
y down, z along the mirror axis towards the scene in the image centre). The thesis' sign of
``eta`` in the second row of ``M_c`` flips ``y`` (its ray is ``diag(1, -1, 1)`` times ours).
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
from .validate import NONNEGATIVE, POSITIVE, Domain


def _distort(x: Tensor, y: Tensor, k1: float, k2: float, p1: float, p2: float) -> tuple[Tensor, Tensor]:
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def _distort_jacobian(x: Tensor, y: Tensor, k1: float, k2: float, p1: float, p2: float):
    """Entries ``(a, b, c, d)`` of ``d(x_d, y_d) / d(x, y) = [[a, b], [c, d]]``."""
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    dradial = k1 + 2 * k2 * r2  # d radial / d r2
    a = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
    b = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    c = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    d = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
    return a, b, c, d


@dataclass(frozen=True)
class Unified(Camera):
    """Unified (Mei) omnidirectional model with radial–tangential distortion, as ``cv2.omnidir``.

    Fields: ``xi`` (mirror parameter), ``fx, fy, s (skew), cx, cy`` (pixels),
    ``k1, k2, p1, p2`` (OpenCV's ``D``).
    """

    domains: ClassVar[Mapping[str, Domain]] = {"fx": POSITIVE, "fy": POSITIVE, "xi": NONNEGATIVE}
    xi: float = 1.0
    fx: float = 1.0
    fy: float = 1.0
    s: float = 0.0
    cx: float = 0.0
    cy: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"{self.name or 'unified'} camera: fx, fy must be > 0, got fx={self.fx}, fy={self.fy}")
        if not self.xi >= 0:
            raise ValueError(f"{self.name or 'unified'} camera: xi must be >= 0, got {self.xi}")

    # -- model parts -----------------------------------------------------------------------
    @property
    def _z_limit(self) -> float:
        """Visible iff ``X_s,z > -_z_limit``."""
        if self.xi == 0:
            return 0.0
        return min(self.xi, 1 / self.xi)

    @property
    def _dist(self) -> tuple[float, float, float, float]:
        return self.k1, self.k2, self.p1, self.p2

    def _lift(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        """Eq. 2.8: normalised image point -> unit ray; returns ``(direction, ok)``."""
        r2 = x * x + y * y
        disc = 1 + (1 - self.xi ** 2) * r2
        ok = disc >= 0
        root = torch.sqrt(torch.where(ok, disc, torch.ones_like(disc)))
        fac = (self.xi + root) / (1 + r2)
        d = torch.stack([fac * x, fac * y, fac - self.xi], -1)
        ok = ok & (d[..., 2] > -self._z_limit)
        return d, ok

    def _undistort(self, xd: Tensor, yd: Tensor, iters: int = 50) -> tuple[Tensor, Tensor, Tensor]:
        """Newton on ``distort(x, y) = (x_d, y_d)``; returns ``(x, y, converged & det > 0)`` with implicit grads."""
        dist = self._dist
        if not any(dist):
            return xd, yd, torch.ones_like(xd, dtype=torch.bool)
        tol = 8 * torch.finfo(xd.dtype).eps
        with torch.no_grad():
            x, y = xd.detach().clone(), yd.detach().clone()
            for _ in range(iters):
                fx_, fy_ = _distort(x, y, *dist)
                ex, ey = fx_ - xd.detach(), fy_ - yd.detach()
                if bool((torch.maximum(ex.abs(), ey.abs()) <= tol * (1 + xd.detach().abs() + yd.detach().abs())).all()):
                    break
                a, b, c, d = _distort_jacobian(x, y, *dist)
                det = a * d - b * c
                det = torch.where(det.abs() > 1e-300, det, torch.ones_like(det))
                x = x - (d * ex - b * ey) / det
                y = y - (-c * ex + a * ey) / det
                big = ~(torch.isfinite(x) & torch.isfinite(y)) | (x.abs() > 1e6) | (y.abs() > 1e6)
                x = torch.where(big, torch.zeros_like(x), x)
                y = torch.where(big, torch.zeros_like(y), y)
            fx_, fy_ = _distort(x, y, *dist)
            res = torch.maximum((fx_ - xd).abs(), (fy_ - yd).abs())
            a, b, c, d = _distort_jacobian(x, y, *dist)
            det = a * d - b * c
            ok = (res <= 1e3 * tol * (1 + xd.abs() + yd.abs())) & (det > 0)
            det = torch.where(det > 0, det, torch.ones_like(det))
        # differentiable Newton polish: (x, y) - J^{-1} (distort(x, y) - (x_d, y_d)), J detached
        fx_, fy_ = _distort(x, y, *dist)
        ex, ey = fx_ - xd, fy_ - yd
        x = x - (d * ex - b * ey) / det
        y = y - (-c * ex + a * ey) / det
        return x, y, ok

    # -- interface ---------------------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        norm = safe_norm(points)
        nz = norm > 0
        ps = torch.where(nz.unsqueeze(-1), points, torch.ones_like(points)) / torch.where(nz, norm, torch.ones_like(norm)).unsqueeze(-1)
        den = ps[..., 2] + self.xi
        ok = nz & (ps[..., 2] > -self._z_limit) & (den > 0)
        den = torch.where(ok, den, torch.ones_like(den))
        x = torch.where(ok, ps[..., 0] / den, torch.zeros_like(den))
        y = torch.where(ok, ps[..., 1] / den, torch.zeros_like(den))
        if any(self._dist):
            a, b, c, d = _distort_jacobian(x, y, *self._dist)
            ok = ok & (a * d - b * c > 0)
        xd, yd = _distort(x, y, *self._dist)
        uv = torch.stack([self.fx * xd + self.s * yd + self.cx, self.fy * yd + self.cy], -1)
        return uv, ok & in_image(uv, self.width, self.height)

    def unproject(self, uv: Tensor) -> Rays:
        inside = in_image(uv, self.width, self.height)
        yd = (uv[..., 1] - self.cy) / self.fy
        xd = (uv[..., 0] - self.cx - self.s * yd) / self.fx
        yd = torch.where(inside, yd, torch.zeros_like(yd))
        xd = torch.where(inside, xd, torch.zeros_like(xd))
        x, y, ok = self._undistort(xd, yd)
        d, ok_lift = self._lift(x, y)
        ok = inside & ok & ok_lift
        d = torch.where(ok.unsqueeze(-1), d, torch.tensor([0.0, 0.0, 1.0], dtype=d.dtype, device=d.device))
        return Rays(torch.zeros_like(d), d, ok)

    @classmethod
    def example(cls) -> "Unified":
        return cls(width=64, height=48, xi=0.9, fx=22.0, fy=21.0, s=0.3, cx=31.0, cy=24.5,
                   k1=-0.02, k2=0.002, p1=0.001, p2=-0.0015)


MIRRORS = ("para", "hyper")


def mirror_xi_eta(mirror: str, d: float, p: float) -> tuple[float, float]:
    """Table 2.3: ``(xi, eta)`` of a para-/hyper-catadioptric mirror (``d``, ``p`` in metres)."""
    if mirror == "para":
        return 1.0, -2.0 * p
    if mirror == "hyper":
        n = math.sqrt(d * d + 4 * p * p)
        return d / n, -2.0 * p / n
    raise ValueError(f"catadioptric camera: unknown mirror {mirror!r}; expected one of {MIRRORS}")


@dataclass(frozen=True)
class Catadioptric(Camera):
    """Central catadioptric camera from the mirror geometry (sphere model, Table 2.3, Eq. 2.7–2.8).

    Fields: ``mirror`` (``"para"`` or ``"hyper"``), ``d`` (camera–mirror distance, metres; unused
    by ``para``), ``p`` (``2p`` is the mirror's semi-latus rectum, metres), ``fx, fy, cx, cy``
    (the perspective camera's ``K_c`` in pixels). Equivalent to :class:`Unified` with
    ``xi`` and focal lengths ``-eta * (fx, fy)`` (see :attr:`as_unified`).
    """

    domains: ClassVar[Mapping[str, Domain]] = {"fx": POSITIVE, "fy": POSITIVE, "p": POSITIVE, "d": NONNEGATIVE}
    mirror: str = "para"
    d: float = 0.0
    p: float = 0.05
    fx: float = 1.0
    fy: float = 1.0
    cx: float = 0.0
    cy: float = 0.0

    def __post_init__(self) -> None:
        if self.mirror not in MIRRORS:
            raise ValueError(f"catadioptric camera: unknown mirror {self.mirror!r}; expected one of {MIRRORS}")
        if not self.p > 0:
            raise ValueError(f"catadioptric camera: p must be > 0 metres, got {self.p}")
        if self.mirror == "hyper" and not self.d > 0:
            raise ValueError(f"catadioptric camera: a hyperbolic mirror needs d > 0 metres, got {self.d}")

    @property
    def xi_eta(self) -> tuple[float, float]:
        return mirror_xi_eta(self.mirror, self.d, self.p)

    @property
    def as_unified(self) -> Unified:
        xi, eta = self.xi_eta
        return Unified(width=self.width, height=self.height, xi=xi, fx=-eta * self.fx, fy=-eta * self.fy,
                       cx=self.cx, cy=self.cy)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        return self.as_unified.project(points)

    def unproject(self, uv: Tensor) -> Rays:
        return self.as_unified.unproject(uv)

    @classmethod
    def example(cls) -> "Catadioptric":
        return cls(width=64, height=64, mirror="para", p=0.05, fx=150.0, fy=150.0, cx=32.0, cy=32.0)

    @classmethod
    def examples(cls) -> list["Catadioptric"]:
        return [cls.example(),
                cls(width=64, height=48, mirror="hyper", d=0.1, p=0.025, fx=40.0, fy=40.0, cx=32.5, cy=23.0)]


register_camera("unified", Unified)
register_camera("catadioptric", Catadioptric)
