"""Revolution-symmetric fisheye with the four classic lenses (thesis Tables 2.1/2.2, Eq. 2.5–2.6).

A ray making the angle ``phi`` with the optical axis (``+z``) lands at the distance
``r = h(phi)`` pixels from the principal point ``(cx, cy)``, in the direction of its
``(x, y)`` components (OpenCV frame: x right, y down, so the image is not mirrored)::

    equiangular     r = f * phi                 phi = r / f
    stereographic   r = 2 f tan(phi / 2)        phi = 2 atan(r / (2 f))
    orthogonal      r = f sin(phi)              phi = asin(r / f)          (phi <= 90 deg)
    equisolid       r = 2 f sin(phi / 2)        phi = 2 asin(r / (2 f))    (standard form)

Equisolid is the *standard* form. The thesis' Table 2.1 writes ``r = f sin(phi/2)`` (and
OmniSCV codes that), i.e. its ``f`` is **twice** the standard focal length used here:
``f_here = f_thesis / 2``.

Points beyond ``max_fov / 2`` from the axis (``max_fov`` is the full field of view in
radians) or outside the lens' domain are invalid, and so are pixels beyond the image
circle ``h(max_fov / 2)``.
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

LENSES = ("equiangular", "stereographic", "orthogonal", "equisolid")
#: largest angle from the axis each lens can represent (radians)
LENS_DOMAIN = {"equiangular": math.pi, "stereographic": math.pi, "orthogonal": math.pi / 2, "equisolid": math.pi}


def lens_radius(lens: str, phi: Tensor | float) -> Tensor | float:
    """``h(phi) / f``: normalised image radius of a ray at ``phi`` radians from the axis."""
    t = torch if isinstance(phi, Tensor) else math
    if lens == "equiangular":
        return phi
    if lens == "stereographic":
        return 2 * t.tan(phi / 2)
    if lens == "orthogonal":
        return t.sin(phi)
    if lens == "equisolid":
        return 2 * t.sin(phi / 2)
    raise ValueError(f"fisheye camera: unknown lens {lens!r}; expected one of {LENSES}")


def _radius_over_sin(lens: str, phi: Tensor) -> Tensor:
    """``h(phi) / (f sin(phi))``, smooth at ``phi = 0`` (callers keep ``phi`` away from ``pi``)."""
    if lens == "equiangular":
        small = phi.abs() < 1e-4
        ps = torch.where(small, torch.ones_like(phi), phi)
        return torch.where(small, 1 + phi * phi / 6, ps / torch.sin(ps))
    if lens == "stereographic":
        return 1 / torch.cos(phi / 2) ** 2
    if lens == "orthogonal":
        return torch.ones_like(phi)
    return 1 / torch.cos(phi / 2)  # equisolid


def _sin_and_cos_from_radius(lens: str, r: Tensor) -> tuple[Tensor, Tensor]:
    """For normalised radius ``r = h(phi)/f``: ``(sin(phi) / r, cos(phi))``, smooth at ``r = 0``."""
    if lens == "equiangular":
        small = r < 1e-4
        rs = torch.where(small, torch.ones_like(r), r)
        return torch.where(small, 1 - r * r / 6, torch.sin(rs) / rs), torch.cos(r)
    if lens == "stereographic":
        q = r * r / 4
        return 1 / (1 + q), (1 - q) / (1 + q)
    if lens == "orthogonal":
        return torch.ones_like(r), torch.sqrt(torch.clamp(1 - r * r, min=0.0))
    q = r * r / 4  # equisolid: sin(phi) = r sqrt(1 - r^2/4), cos(phi) = 1 - r^2/2
    return torch.sqrt(torch.clamp(1 - q, min=0.0)), 1 - 2 * q


@dataclass(frozen=True)
class Fisheye(Camera):
    """Revolution-symmetric fisheye (central).

    Fields: ``width``, ``height`` (pixels), ``f`` (focal length in pixels, standard form for
    every lens), ``cx``, ``cy`` (principal point, pixels), ``lens`` (one of :data:`LENSES`),
    ``max_fov`` (full field of view in radians; rays with ``phi > max_fov/2`` are invalid).
    """

    domains: ClassVar[Mapping[str, Domain]] = {"f": POSITIVE, "max_fov": between(0.0, 2 * math.pi, "(]", "in (0, 2*pi] radians")}
    f: float = 100.0
    cx: float = 0.0
    cy: float = 0.0
    lens: str = "equiangular"
    max_fov: float = math.pi

    def __post_init__(self) -> None:
        if self.lens not in LENSES:
            raise ValueError(f"fisheye camera: unknown lens {self.lens!r}; expected one of {LENSES}")
        if not self.f > 0:
            raise ValueError(f"fisheye camera: focal length f must be > 0 pixels, got {self.f}")
        if not 0 < self.max_fov <= 2 * LENS_DOMAIN[self.lens]:
            raise ValueError(f"fisheye camera: max_fov={self.max_fov} rad is outside (0, "
                             f"{2 * LENS_DOMAIN[self.lens]:.6f}] for the {self.lens} lens")
        if self.lens in ("equiangular", "stereographic") and self.max_fov >= 2 * math.pi:
            raise ValueError(f"fisheye camera: the {self.lens} lens needs max_fov < 2*pi (the ray straight "
                             "behind the camera has no image point)")

    @property
    def max_radius(self) -> float:
        """Radius of the image circle in pixels, ``h(max_fov / 2)``."""
        return self.f * float(lens_radius(self.lens, self.max_fov / 2))

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        norm = safe_norm(points)
        phi = torch.atan2(safe_norm(points[..., :2]), points[..., 2])
        ok = (norm > 0) & (phi <= self.max_fov / 2)
        phi_s = torch.where(ok, phi, torch.zeros_like(phi))
        scale = self.f * _radius_over_sin(self.lens, phi_s) / torch.where(ok, norm, torch.ones_like(norm))
        u = self.cx + scale * points[..., 0]
        v = self.cy + scale * points[..., 1]
        uv = torch.stack([torch.where(ok, u, torch.full_like(u, self.cx)),
                          torch.where(ok, v, torch.full_like(v, self.cy))], -1)
        return uv, ok & in_image(uv, self.width, self.height)

    def unproject(self, uv: Tensor) -> Rays:
        m = torch.stack([uv[..., 0] - self.cx, uv[..., 1] - self.cy], -1) / self.f
        r = safe_norm(m)
        r_max = float(lens_radius(self.lens, self.max_fov / 2))
        ok = (r <= r_max) & in_image(uv, self.width, self.height)
        r_s = torch.where(ok, r, torch.zeros_like(r))
        m = torch.where(ok.unsqueeze(-1), m, torch.zeros_like(m))
        sin_over_r, cos_phi = _sin_and_cos_from_radius(self.lens, r_s)
        d = torch.cat([m * sin_over_r.unsqueeze(-1), cos_phi.unsqueeze(-1)], -1)
        return Rays(torch.zeros_like(d), d, ok)

    @classmethod
    def example(cls) -> "Fisheye":
        return cls(width=64, height=64, f=18.0, cx=32.0, cy=32.0, lens="equiangular", max_fov=math.radians(190))

    @classmethod
    def examples(cls) -> list["Fisheye"]:
        return [cls.example(),
                cls(width=64, height=48, f=9.0, cx=33.0, cy=23.5, lens="stereographic", max_fov=math.radians(200)),
                cls(width=64, height=64, f=30.0, cx=32.0, cy=32.0, lens="orthogonal", max_fov=math.radians(170)),
                cls(width=64, height=64, f=15.0, cx=32.0, cy=32.0, lens="equisolid", max_fov=math.radians(220))]


register_camera("fisheye", Fisheye)
