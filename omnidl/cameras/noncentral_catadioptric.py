"""Non-central catadioptric cameras: a pinhole looking at a conical or spherical mirror (thesis Eq. 2.17–2.18).

Frame: the pinhole is at the origin looking along ``+z`` (OpenCV frame) and the mirror's axis
of revolution is the ``z`` axis. Pixel ``(u, v)`` gives the pinhole ray ``(x, y, 1)`` with
``x = (u - cx) / fx``, ``y = (v - cy) / fy``; it hits the mirror at ``P`` with outward normal
``n`` and is reflected, ``d = a - 2 (a . n) n``. ``unproject`` returns that reflected ray
(origin ``P``, direction ``d``): a non-central camera whose rays all meet the ``z`` axis.

Mirrors (metres, radians):

* ``conical``: apex at ``(0, 0, z_m)`` pointing at the camera, half-aperture ``tau``
  (angle between the surface and the axis). The reflected rays of an image direction pass
  through the mirror image of the pinhole, on the circle of radius ``R_c = z_m sin 2 tau`` at
  height ``Z_c = z_m (1 - cos 2 tau)``: thesis Eq. 2.17 with
  ``cot(phi) = (1 + r tan 2 tau) / (tan 2 tau - r)`` and ``Z_r = Z_c + R_c cot(phi)``.
* ``spherical``: sphere of radius ``r_s`` whose nearest point is at distance ``z_m``
  (centre ``Z_s = z_m + r_s``), Eq. 2.18.

The mirror ends at the horizontal radius ``rim_radius``; pixels that do not see the mirror
inside the rim are invalid (the apex of the cone is excluded: its normal is undefined).
``project`` finds, in the plane through the axis and the point, the image radius whose
reflected ray passes through the point (vectorised Illinois regula falsi to the dtype's resolution plus a
differentiable Newton step). Points not reached by any reflected ray are invalid.
Occlusion by the camera body or by the mirror itself is not modelled.
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
from .solvers import bracketed_root, newton_polish
from .validate import POSITIVE, Domain, between

MIRRORS = ("conical", "spherical")


@dataclass(frozen=True)
class NonCentralCatadioptric(Camera):
    """Pinhole ``(fx, fy, cx, cy)`` + conical/spherical mirror (``central = False``).

    Fields: ``mirror`` (``"conical"`` or ``"spherical"``), ``z_m`` (camera to apex / nearest
    mirror point, m), ``tau`` (cone half-aperture, rad; conical only), ``r_s`` (sphere
    radius, m; spherical only), ``rim_radius`` (horizontal radius where the mirror ends, m).
    """

    central = False

    domains: ClassVar[Mapping[str, Domain]] = {"fx": POSITIVE, "fy": POSITIVE, "z_m": POSITIVE, "rim_radius": POSITIVE, "r_s": POSITIVE, "tau": between(0.0, math.pi / 2, "()", "in (0, pi/2) radians")}
    fx: float = 1.0
    fy: float = 1.0
    cx: float = 0.0
    cy: float = 0.0
    mirror: str = "conical"
    z_m: float = 0.3
    tau: float = math.radians(30)
    r_s: float = 0.5
    rim_radius: float = 0.2

    def __post_init__(self) -> None:
        name = "noncentral_catadioptric camera"
        if self.mirror not in MIRRORS:
            raise ValueError(f"{name}: unknown mirror {self.mirror!r}; expected one of {MIRRORS}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"{name}: fx, fy must be > 0, got fx={self.fx}, fy={self.fy}")
        if not (self.z_m > 0 and self.rim_radius > 0):
            raise ValueError(f"{name}: z_m and rim_radius must be > 0 metres, got z_m={self.z_m}, "
                             f"rim_radius={self.rim_radius}")
        if self.mirror == "conical" and not 0 < self.tau < math.pi / 2:
            raise ValueError(f"{name}: the cone half-aperture tau must be in (0, pi/2) radians, got {self.tau}")
        if self.mirror == "spherical":
            if not self.r_s > 0:
                raise ValueError(f"{name}: sphere radius r_s must be > 0 metres, got {self.r_s}")
            zs = self.z_m + self.r_s
            rho_tan = self.r_s * math.sqrt(zs * zs - self.r_s ** 2) / zs
            if not self.rim_radius < rho_tan:
                raise ValueError(f"{name}: rim_radius={self.rim_radius} m must be smaller than the radius "
                                 f"{rho_tan:.6f} m of the sphere's silhouette seen from the camera")

    # -- mirror geometry in the plane through the axis (coordinates (rho, z)) ---------------------
    @property
    def r_rim(self) -> float:
        """Normalised image radius of the rim."""
        if self.mirror == "conical":
            return self.rim_radius / (self.z_m + self.rim_radius / math.tan(self.tau))
        zs = self.z_m + self.r_s
        return self.rim_radius / (zs - math.sqrt(self.r_s ** 2 - self.rim_radius ** 2))

    def axial_ray(self, r: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Reflection of the pinhole ray of normalised image radius ``r >= 0`` in the axial plane.

        Returns ``(p_rho, p_z, d_rho, d_z)``: the reflection point and the unit reflected direction.
        """
        if self.mirror == "conical":
            ta = math.tan(self.tau)
            t = self.z_m * ta / (ta - r)
            n_rho, n_z = math.cos(self.tau), -math.sin(self.tau)
            p_rho, p_z = t * r, t
            n_rho, n_z = torch.full_like(r, n_rho), torch.full_like(r, n_z)
        else:
            zs = self.z_m + self.r_s
            a2 = 1 + r * r
            disc = torch.clamp(zs * zs - a2 * (zs * zs - self.r_s ** 2), min=0.0)
            t = (zs - torch.sqrt(disc)) / a2
            p_rho, p_z = t * r, t
            n_rho, n_z = p_rho / self.r_s, (p_z - zs) / self.r_s
        norm_a = torch.sqrt(1 + r * r)
        a_rho, a_z = r / norm_a, 1 / norm_a
        dot = a_rho * n_rho + a_z * n_z
        return p_rho, p_z, a_rho - 2 * dot * n_rho, a_z - 2 * dot * n_z

    # -- interface ---------------------------------------------------------------------------
    def unproject(self, uv: Tensor) -> Rays:
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        r = safe_norm(torch.stack([x, y], -1))
        ok = in_image(uv, self.width, self.height) & (r <= self.r_rim)
        if self.mirror == "conical":
            ok = ok & (r > 0)
        pos = r > 0
        r_s = torch.where(ok, r, torch.full_like(r, 0.5 * self.r_rim))
        rs = torch.where(pos, r, torch.ones_like(r))
        ex = torch.where(ok & pos, x / rs, torch.ones_like(x))
        ey = torch.where(ok & pos, y / rs, torch.zeros_like(y))
        p_rho, p_z, d_rho, d_z = self.axial_ray(r_s)
        origin = torch.stack([p_rho * ex, p_rho * ey, p_z], -1)
        d = torch.stack([d_rho * ex, d_rho * ey, d_z], -1)
        return Rays(origin, d, ok)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        x, y, z = points.unbind(-1)
        rho = safe_norm(torch.stack([x, y], -1))
        pos = rho > 0
        rho_s = torch.where(pos, rho, torch.ones_like(rho))
        ex = torch.where(pos, x / rho_s, torch.ones_like(x))
        ey = torch.where(pos, y / rho_s, torch.zeros_like(y))

        def residual(r: Tensor, rho_x: Tensor = rho, z_x: Tensor = z) -> Tensor:
            p_rho, p_z, d_rho, d_z = self.axial_ray(r)
            return d_rho * (z_x - p_z) - d_z * (rho_x - p_rho)

        lo = torch.full_like(rho, 1e-9 * self.r_rim if self.mirror == "conical" else 0.0)
        hi = torch.full_like(rho, self.r_rim)
        r, ok = bracketed_root(lambda t: residual(t, rho.detach(), z.detach()), lo, hi)
        # the point must lie ahead on the reflected ray, not on its backward extension
        with torch.no_grad():
            p_rho, p_z, d_rho, d_z = self.axial_ray(r)
            ahead = (rho - p_rho) * d_rho + (z - p_z) * d_z > 0
        ok = ok & ahead & (safe_norm(points) > 0)
        r = torch.where(ok, r, torch.full_like(r, 0.5 * self.r_rim))
        r = newton_polish(r, residual)
        r = torch.where(ok, r, torch.zeros_like(r))
        uv = torch.stack([self.cx + self.fx * r * ex, self.cy + self.fy * r * ey], -1)
        return uv, ok & in_image(uv, self.width, self.height)

    @classmethod
    def example(cls) -> "NonCentralCatadioptric":
        return cls(width=64, height=64, fx=53.0, fy=53.0, cx=32.0, cy=32.0, mirror="conical", z_m=0.3,
                   tau=math.radians(60), rim_radius=0.25)

    @classmethod
    def examples(cls) -> list["NonCentralCatadioptric"]:
        return [cls.example(),
                cls(width=64, height=48, fx=30.0, fy=30.0, cx=32.0, cy=24.0, mirror="spherical", z_m=0.3,
                    r_s=0.5, rim_radius=0.3)]


register_camera("noncentral_catadioptric", NonCentralCatadioptric)
