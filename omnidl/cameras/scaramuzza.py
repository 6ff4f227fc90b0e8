"""Scaramuzza / OCamCalib omnidirectional model (thesis Eq. 2.12–2.13).

Back-projection (``cam2world``): a pixel is mapped to sensor coordinates by the inverse
of the affine transform, and the ray is ``(x_s, y_s, f(rho))`` with the polynomial
``f(rho) = a0 + a1 rho + ... + aN rho^N`` (``pol``, ``a0 < 0``) of the sensor radius
``rho = |(x_s, y_s)|``. Projection (``world2cam``) uses the inverse polynomial ``invpol``
``rho = b0 + b1 t + ...`` of the elevation ``t = atan(z_o / |(x_o, y_o)|)``; here it only gives
the start of a safeguarded Newton solve of the exact inverse of ``pol`` (so that
``project(unproject(uv)) == uv`` to rounding). When ``invpol`` is empty it is fitted by least
squares (:func:`fit_invpol`).

Conventions — OCamCalib vs omnidl. OCamCalib's first image coordinate is the **row** and the
second the **column** (``point2D = (row, col)``, centre ``(xc, yc) = (row, col)``), its 3-D frame is
``(x_o, y_o, z_o) = (down, right, backward)`` and the camera looks along ``-z_o``
(``f(0) = a0 < 0``). Its affine model is ``row = c x_o + d y_o + xc``, ``col = e x_o + y_o + yc``.
omnidl uses ``(u, v) = (col, row)`` and the OpenCV frame, so with ``x_s`` along ``u`` and
``y_s`` along ``v``::

    u = x_s + e y_s + cx,      v = d x_s + c y_s + cy,      ray = (x_s, y_s, -f(rho))

The fields ``cx, cy`` are the centre in omnidl pixels. :func:`read_ocamcalib` converts a
``calib_results.txt``. The toolbox's exporter writes the centre for its C code, where pixel coordinates
start from 0 (it writes ``xc - 1, yc - 1`` of MATLAB's 1-based values) and says so in the comment above
the centre line; the reader follows that comment: 0-based (``cx = yc + 0.5``, ``cy = xc + 0.5``) when
it says the coordinates start from 0, 1-based MATLAB values (``cx = yc - 0.5``, ``cy = xc - 0.5``) when
it names no convention (files written by hand or by older exporters), unless ``one_based`` is given.
"""
from __future__ import annotations

import functools
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .base import Camera, Rays, in_image, safe_norm
from .registry import construct, register_camera
from .solvers import newton_polish, polyder, polyval, solve_increasing


#: phrases of the centre line's comment that state 0-based (C) pixel coordinates
_ZERO_BASED = re.compile(r"start(?:s|ing)?\s+(?:from|at)\s+(?:0|zero)\b|\b(?:0|zero)[- ]based\b", re.IGNORECASE)
#: phrases that state 1-based (MATLAB) pixel coordinates
_ONE_BASED = re.compile(r"start(?:s|ing)?\s+(?:from|at)\s+(?:1|one)\b|\b(?:1|one)[- ]based\b", re.IGNORECASE)


def centre_convention(comment: str) -> bool | None:
    """``True`` (1-based), ``False`` (0-based) or ``None`` (not stated) from the centre line's comment."""
    if _ZERO_BASED.search(comment):
        return False
    if _ONE_BASED.search(comment):
        return True
    return None


def read_ocamcalib(path: str | Path, one_based: bool | None = None) -> dict[str, Any]:
    """Read OCamCalib's ``calib_results.txt`` into :class:`Scaramuzza` fields.

    The file has five data lines (``#`` lines are comments): ``N a0 .. a{N-1}`` (pol),
    ``M b0 .. b{M-1}`` (invpol), ``xc yc`` (row, column of the centre), ``c d e`` and
    ``height width``. ``one_based``: ``None`` (default) reads the convention of the centre from the
    comment above it (the toolbox writes "In C the coordinates start from 0" and ``xc - 1, yc - 1``:
    0-based pixel centres, converted with ``+0.5``); a comment that names no convention means 1-based
    MATLAB pixel centres (``-0.5``). ``True``/``False`` force 1-based/0-based.
    """
    path = Path(path)
    try:
        lines = [ln.strip() for ln in path.read_text().splitlines()]
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"OCamCalib file {str(path)!r} cannot be read as text: {e}") from e
    rows, comments, pending = [], [], []
    for ln in lines:
        if ln.startswith("#"):
            pending.append(ln)
        elif ln:
            rows.append(ln)
            comments.append(" ".join(pending))
            pending = []
    names = ["pol", "invpol", "centre (xc yc)", "affine (c d e)", "image size (height width)"]
    if len(rows) < 5:
        raise ValueError(f"OCamCalib file {str(path)!r}: expected 5 data lines ({', '.join(names)}), "
                         f"found {len(rows)}")
    try:
        vals = [[float(t) for t in r.split()] for r in rows[:5]]
    except ValueError as e:
        raise ValueError(f"OCamCalib file {str(path)!r}: non-numeric entry ({e})") from e
    polys = []
    for name, v in zip(names[:2], vals[:2]):
        if not v or v[0] != int(v[0]) or int(v[0]) != len(v) - 1:
            raise ValueError(f"OCamCalib file {str(path)!r}: the {name} line must start with its number of "
                             f"coefficients followed by that many values, got {v}")
        polys.append(tuple(v[1:]))
    for name, v, n in zip(names[2:], vals[2:], (2, 3, 2)):
        if len(v) != n:
            raise ValueError(f"OCamCalib file {str(path)!r}: the {name} line needs {n} values, got {len(v)}")
    xc, yc = vals[2]
    c, d, e = vals[3]
    height, width = vals[4]
    for key, val in (("height", height), ("width", width)):
        if not math.isfinite(val) or val != int(val) or val < 1:
            raise ValueError(f"OCamCalib file {str(path)!r}: image size line: {key} must be a positive integer, "
                             f"got {val:g}")
    if one_based is None:
        stated = centre_convention(comments[2])
        one_based = True if stated is None else stated
    shift = -0.5 if one_based else 0.5
    return dict(width=int(width), height=int(height), pol=polys[0], invpol=polys[1], cx=yc + shift, cy=xc + shift,
                c=c, d=d, e=e)


def _angle(pol: tuple[float, ...], rho: Tensor) -> Tensor:
    """Angle from the optical axis of the ray at sensor radius ``rho``: ``atan2(rho, -f(rho))``."""
    return torch.atan2(rho, -polyval(pol, rho))


def _angle_deriv(pol: tuple[float, ...], dpol: tuple[float, ...], rho: Tensor) -> Tensor:
    p = polyval(pol, rho)
    return (-p + rho * polyval(dpol, rho)) / (rho * rho + p * p)


@functools.lru_cache(maxsize=64)
def _rho_limit(pol: tuple[float, ...], rho_needed: float) -> float:
    """Largest sensor radius ``<= rho_needed`` up to which the ray angle increases with ``rho``."""
    rho = torch.linspace(0, rho_needed, 8193, dtype=torch.float64)
    ok = _angle_deriv(pol, polyder(pol), rho) > 0
    if bool(ok.all()):
        return rho_needed
    return float(rho[int((~ok).nonzero()[0])] * 0.999) if int((~ok).nonzero()[0]) > 0 else 0.0


@functools.lru_cache(maxsize=64)
def fit_invpol(pol: tuple[float, ...], rho_max: float, degree: int = 12) -> tuple[float, ...]:
    """Least-squares ``invpol``: ``rho`` as a polynomial of OCamCalib's elevation ``t = angle - pi/2``."""
    rho = torch.linspace(0, rho_max, 400, dtype=torch.float64)
    t = (_angle(pol, rho) - math.pi / 2).numpy()
    coef = np.polynomial.polynomial.polyfit(t, rho.numpy(), degree)
    return tuple(float(c) for c in coef)


@dataclass(frozen=True)
class Scaramuzza(Camera):
    """OCamCalib camera (central).

    Fields: ``pol`` (``a0..aN``, ``a0 < 0``), ``invpol`` (``b0..bM``; empty = fitted),
    ``cx, cy`` (distortion centre in omnidl pixels), ``c, d, e`` (OCamCalib's affine terms).
    """

    pol: tuple[float, ...] = (-1.0,)
    invpol: tuple[float, ...] = ()
    cx: float = 0.0
    cy: float = 0.0
    c: float = 1.0
    d: float = 0.0
    e: float = 0.0

    def __post_init__(self) -> None:
        if not self.pol or not self.pol[0] < 0:
            raise ValueError(f"scaramuzza camera: pol must start with a0 < 0 (OCamCalib convention), got {self.pol}")
        if abs(self.c - self.d * self.e) < 1e-12:
            raise ValueError(f"scaramuzza camera: singular affine matrix (c - d*e = 0) with c={self.c}, d={self.d}, "
                             f"e={self.e}")
        object.__setattr__(self, "pol", tuple(float(a) for a in self.pol))
        object.__setattr__(self, "invpol", tuple(float(b) for b in self.invpol))

    # -- geometry helpers ------------------------------------------------------------------------
    def pixel_to_sensor(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        """Inverse affine: pixels ``(..., 2)`` -> sensor ``(x_s, y_s)``."""
        du, dv = uv[..., 0] - self.cx, uv[..., 1] - self.cy
        det = self.c - self.d * self.e
        return (self.c * du - self.e * dv) / det, (dv - self.d * du) / det

    def sensor_to_pixel(self, xs: Tensor, ys: Tensor) -> Tensor:
        return torch.stack([xs + self.e * ys + self.cx, self.d * xs + self.c * ys + self.cy], -1)

    @property
    def rho_limit(self) -> float:
        """Largest valid sensor radius: covers the image, stops where the ray angle stops increasing."""
        corners = torch.tensor([[0, 0], [self.width, 0], [0, self.height], [self.width, self.height]],
                               dtype=torch.float64)
        xs, ys = self.pixel_to_sensor(corners)
        return _rho_limit(self.pol, float(torch.hypot(xs, ys).max()) * 1.05)

    @property
    def inverse_polynomial(self) -> tuple[float, ...]:
        """``invpol`` from the config, or its least-squares fit."""
        return self.invpol or fit_invpol(self.pol, self.rho_limit)

    # -- interface ---------------------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        pol, dpol = self.pol, polyder(self.pol)
        rho_lim = self.rho_limit
        alpha_max = float(_angle(pol, torch.tensor(rho_lim, dtype=torch.float64)))
        norm = safe_norm(points)
        rxy = safe_norm(points[..., :2])
        alpha = torch.atan2(rxy, points[..., 2])
        ok = (norm > 0) & (alpha <= alpha_max)
        alpha = torch.where(ok, alpha, torch.zeros_like(alpha))
        rho0 = polyval(self.inverse_polynomial, alpha.detach() - math.pi / 2)
        rho = solve_increasing(lambda r: _angle(pol, r), lambda r: _angle_deriv(pol, dpol, r), alpha,
                               torch.zeros_like(alpha), torch.full_like(alpha, rho_lim), x0=rho0)
        rho = newton_polish(rho, lambda r: _angle(pol, r) - alpha, _angle_deriv(pol, dpol, rho))
        # rho / rxy = (rho / sin(alpha)) / |X|, smooth at the axis (limit 1 / angle'(0) = -a0)
        small = alpha < 1e-6
        ratio = torch.where(small, torch.full_like(rho, -pol[0]),
                            rho / torch.sin(torch.where(small, torch.ones_like(alpha), alpha)))
        scale = ratio / torch.where(ok, norm, torch.ones_like(norm))
        uv = self.sensor_to_pixel(scale * points[..., 0], scale * points[..., 1])
        uv = torch.where(ok.unsqueeze(-1), uv, torch.zeros_like(uv) + torch.tensor(
            [self.cx, self.cy], dtype=uv.dtype, device=uv.device))
        return uv, ok & in_image(uv, self.width, self.height)

    def unproject(self, uv: Tensor) -> Rays:
        xs, ys = self.pixel_to_sensor(uv)
        rho = safe_norm(torch.stack([xs, ys], -1))
        ok = (rho <= self.rho_limit) & in_image(uv, self.width, self.height)
        xs = torch.where(ok, xs, torch.zeros_like(xs))
        ys = torch.where(ok, ys, torch.zeros_like(ys))
        rho = torch.where(ok, rho, torch.zeros_like(rho))
        d = torch.stack([xs, ys, -polyval(self.pol, rho)], -1)
        d = d / safe_norm(d, keepdim=True)
        return Rays(torch.zeros_like(d), d, ok)

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def from_config(cls, params: Mapping[str, Any]) -> "Scaramuzza":
        """Fields, or ``calib_file`` (OCamCalib ``calib_results.txt``) + overrides.

        ``one_based``: the centre's convention (default ``None``: as the file's comment states, see
        :func:`read_ocamcalib`).
        """
        params = dict(params)
        path = params.pop("calib_file", None)
        one_based = params.pop("one_based", None)
        if path is None:
            return construct(cls, params)
        params = {**read_ocamcalib(path, one_based=None if one_based is None else bool(one_based)), **params}
        try:
            return construct(cls, params)
        except (TypeError, ValueError) as e:
            raise ValueError(f"OCamCalib file {str(path)!r}: {e}") from e

    @classmethod
    def from_file(cls, path: str | Path, one_based: bool | None = None) -> "Scaramuzza":
        return cls.from_config({"calib_file": path, "one_based": one_based})

    @classmethod
    def example(cls) -> "Scaramuzza":
        # OmniSCV's default 1024-px polynomial scaled to a 64 x 64 image (a_k -> a_k * 16^(k-1)), mild affine
        s = 16.0
        pol = (-2.736690e+02, 0.0, 1.491215e-03, -1.810410e-06, 6.614668e-09)
        return cls(width=64, height=64, pol=tuple(a * s ** (k - 1) for k, a in enumerate(pol)),
                   cx=31.7, cy=32.4, c=1.002, d=0.003, e=-0.002)


register_camera("scaramuzza", Scaramuzza)
