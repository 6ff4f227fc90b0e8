"""WoodScape radial polynomial fisheye (Yogamani et al., "WoodScape: A multi-task, multi-camera fisheye
dataset for autonomous driving", ICCV 2019; the dataset's ``calibration/*.json`` files and its reference
``scripts/calibration/projection.py``).

A ray at angle ``theta = atan2(|(x, y)|, z)`` from the optical axis (ray-based: works beyond 90 deg)
lands at the distance ``rho`` from the principal point::

    rho(theta) = k1 theta + k2 theta^2 + k3 theta^3 + k4 theta^4          (pixels)
    u = rho x / |(x, y)| + cx,       v = rho y / |(x, y)| * aspect_ratio + cy

WoodScape's calibration JSON gives ``k1..k4``, ``cx_offset``, ``cy_offset``, ``aspect_ratio``,
``width``, ``height`` ("intrinsic" block, ``model: radial_poly``). Its loader puts the principal
point at ``width / 2 + cx_offset - 0.5`` (and likewise ``v``) in a frame whose origin is the
*centre* of the upper-left pixel; in omnidl's frame (that centre is at ``(0.5, 0.5)``) this is::

    cx = width / 2 + cx_offset,      cy = height / 2 + cy_offset

The calibration has no field of view: ``max_fov`` (full angle, radians; default 190 deg, the
dataset's lenses) bounds the valid rays, and ``rho`` must increase on ``[0, max_fov / 2]``
(checked). ``unproject`` inverts ``rho`` with a safeguarded Newton iteration and one
differentiable Newton step (implicit gradients; see :mod:`omnidl.cameras.solvers`).

Calibration files: ``from_config({"calib_file": path})`` reads a WoodScape JSON (see
:func:`read_woodscape_json`).
"""
from __future__ import annotations

import json
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

WOODSCAPE_FIELDS = ("k1", "k2", "k3", "k4", "cx_offset", "cy_offset", "aspect_ratio", "width", "height")


def read_woodscape_json(path: str | Path) -> dict[str, Any]:
    """Camera fields of a WoodScape calibration JSON (its ``intrinsic`` block; extrinsics are ignored).

    Raises ``ValueError`` naming the file and the field when the block is missing, the model is not
    ``radial_poly`` with ``poly_order`` 4, or a field is missing or not a number.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"WoodScape calibration file {str(path)!r} cannot be read as JSON: {e}") from e
    intr = data.get("intrinsic") if isinstance(data, dict) else None
    if not isinstance(intr, dict):
        raise ValueError(f"WoodScape calibration file {str(path)!r}: no 'intrinsic' object")
    if intr.get("model", "radial_poly") != "radial_poly" or int(intr.get("poly_order", 4)) != 4:
        raise ValueError(f"WoodScape calibration file {str(path)!r}: model {intr.get('model')!r} with poly_order "
                         f"{intr.get('poly_order')!r}; expected 'radial_poly' with poly_order 4")
    out: dict[str, Any] = {}
    for key in WOODSCAPE_FIELDS:
        val = intr.get(key)
        if isinstance(val, bool) or not isinstance(val, (int, float)):
            raise ValueError(f"WoodScape calibration file {str(path)!r}: intrinsic.{key} must be a number, got {val!r}")
        out[key] = float(val)
    for key in ("width", "height"):
        if out[key] != int(out[key]) or out[key] <= 0:
            raise ValueError(f"WoodScape calibration file {str(path)!r}: intrinsic.{key} must be a positive integer, "
                             f"got {out[key]}")
        out[key] = int(out[key])
    return out


@dataclass(frozen=True)
class WoodScape(Camera):
    """WoodScape radial-polynomial fisheye (central); fields as the calibration JSON plus ``max_fov``."""

    domains: ClassVar[Mapping[str, Domain]] = {"k1": POSITIVE, "aspect_ratio": POSITIVE, "max_fov": between(0.0, 2 * math.pi, "(]", "in (0, 2*pi] radians")}
    k1: float = 1.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    cx_offset: float = 0.0
    cy_offset: float = 0.0
    aspect_ratio: float = 1.0
    max_fov: float = math.radians(190)

    def __post_init__(self) -> None:
        if not self.k1 > 0:
            raise ValueError(f"woodscape camera: k1 must be > 0 pixels/radian, got {self.k1}")
        if not self.aspect_ratio > 0:
            raise ValueError(f"woodscape camera: aspect_ratio must be > 0, got {self.aspect_ratio}")
        if not 0 < self.max_fov < 2 * math.pi:
            raise ValueError(f"woodscape camera: max_fov must be in (0, 2*pi) radians, got {self.max_fov}")
        t = torch.linspace(0, self.theta_max, 4097, dtype=torch.float64)
        dr = self.rho_derivative(t)
        if not bool((dr > 0).all()):
            bad = float(t[~(dr > 0)][0])
            raise ValueError(f"woodscape camera: rho(theta) with k=({self.k1}, {self.k2}, {self.k3}, {self.k4}) is not "
                             f"increasing on [0, max_fov/2 = {self.theta_max:.6f}] (rho'(theta) <= 0 at theta = "
                             f"{bad:.6f} rad); reduce max_fov or fix the coefficients")

    # -- geometry -----------------------------------------------------------------------------
    @property
    def cx(self) -> float:
        """Principal point ``u`` in omnidl's pixel frame: ``width / 2 + cx_offset``."""
        return self.width / 2 + self.cx_offset

    @property
    def cy(self) -> float:
        """Principal point ``v`` in omnidl's pixel frame: ``height / 2 + cy_offset``."""
        return self.height / 2 + self.cy_offset

    @property
    def theta_max(self) -> float:
        return self.max_fov / 2

    @property
    def rho_max(self) -> float:
        return float(self.rho(torch.tensor(self.theta_max, dtype=torch.float64)))

    def rho(self, theta: Tensor) -> Tensor:
        """``rho(theta)`` in pixels."""
        return theta * polyval((self.k1, self.k2, self.k3, self.k4), theta)

    def rho_derivative(self, theta: Tensor) -> Tensor:
        return polyval((self.k1, 2 * self.k2, 3 * self.k3, 4 * self.k4), theta)

    def _rho_over_sin(self, theta: Tensor) -> Tensor:
        """``rho(theta) / sin(theta)``, smooth at 0 (``theta < pi``)."""
        small = theta < 1e-4
        ts = torch.where(small, torch.ones_like(theta), theta)
        series = self.k1 + self.k2 * theta + (self.k3 + self.k1 / 6) * theta * theta
        return torch.where(small, series, self.rho(ts) / torch.sin(ts))

    def inverse_rho(self, rho: Tensor) -> Tensor:
        """``theta = rho^{-1}(rho)`` on ``[0, theta_max]`` (differentiable; larger ``rho`` clamps)."""
        theta = solve_increasing(self.rho, self.rho_derivative, rho, torch.zeros_like(rho),
                                 torch.full_like(rho, self.theta_max), x0=rho / self.k1)
        return newton_polish(theta, lambda t: self.rho(t) - rho, self.rho_derivative(theta))

    # -- interface ---------------------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        norm = safe_norm(points)
        theta = torch.atan2(safe_norm(points[..., :2]), points[..., 2])
        ok = (norm > 0) & (theta <= self.theta_max)
        theta = torch.where(ok, theta, torch.zeros_like(theta))
        scale = self._rho_over_sin(theta) / torch.where(ok, norm, torch.ones_like(norm))
        u = torch.where(ok, scale * points[..., 0] + self.cx, torch.full_like(theta, self.cx))
        v = torch.where(ok, scale * points[..., 1] * self.aspect_ratio + self.cy, torch.full_like(theta, self.cy))
        uv = torch.stack([u, v], -1)
        return uv, ok & in_image(uv, self.width, self.height)

    def unproject(self, uv: Tensor) -> Rays:
        m = torch.stack([uv[..., 0] - self.cx, (uv[..., 1] - self.cy) / self.aspect_ratio], -1)
        r = safe_norm(m)
        ok = in_image(uv, self.width, self.height) & (r <= self.rho_max)
        m = torch.where(ok.unsqueeze(-1), m, torch.zeros_like(m))
        theta = self.inverse_rho(safe_norm(m))
        # sin(theta) / rho(theta) scales the lens point to the ray's (x, y)
        d = torch.cat([m / self._rho_over_sin(theta).unsqueeze(-1), torch.cos(theta).unsqueeze(-1)], -1)
        d = torch.where(ok.unsqueeze(-1), d, torch.tensor([0.0, 0.0, 1.0], dtype=d.dtype, device=d.device))
        return Rays(torch.zeros_like(d), d, ok)

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def from_config(cls, params: Mapping[str, Any]) -> "WoodScape":
        """Fields, or ``calib_file`` (a WoodScape calibration JSON) plus optional field overrides."""
        params = dict(params)
        path = params.pop("calib_file", None)
        if path is None:
            return construct(cls, params)
        params = {**read_woodscape_json(path), **params}
        try:
            return construct(cls, params)
        except (TypeError, ValueError) as e:
            raise ValueError(f"WoodScape calibration file {str(path)!r}: {e}") from e

    @classmethod
    def from_file(cls, path: str | Path) -> "WoodScape":
        """Camera of a WoodScape calibration JSON."""
        return cls.from_config({"calib_file": path})

    @classmethod
    def example(cls) -> "WoodScape":
        # WoodScape's front camera (scripts/calibration/front.json, 1280 x 966) scaled by 1/20 to 64 x 48
        # (the principal point kept: cx = (640 + 3.942) / 20, cy = (483 - 3.093) / 20)
        s = 20.0
        return cls(width=64, height=48, k1=339.749 / s, k2=-31.988 / s, k3=48.275 / s, k4=-7.201 / s,
                   cx_offset=(640 + 3.942) / s - 32, cy_offset=(483 - 3.093) / s - 24, aspect_ratio=1.0,
                   max_fov=math.radians(190))

    @classmethod
    def examples(cls) -> list["WoodScape"]:
        # the front camera, then a lens with a non-square pixel aspect and a 220 deg field of view
        return [cls.example(),
                cls(width=64, height=64, k1=17.0, k2=-0.8, k3=0.9, k4=-0.2, cx_offset=0.4, cy_offset=-0.7,
                    aspect_ratio=1.05, max_fov=math.radians(220))]


register_camera("woodscape", WoodScape)
