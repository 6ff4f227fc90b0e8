"""Tangential (decentering) and thin-prism distortion terms shared by the OpenCV pinhole and Fisheye624.

On a normalised plane point ``(x, y)`` with ``r2 = x^2 + y^2`` (Brown 1966; Weng et al. 1992; OpenCV's
``projectPoints`` order)::

    dx = 2 p1 x y + p2 (r2 + 2 x^2) + s1 r2 + s2 r2^2
    dy = p1 (r2 + 2 y^2) + 2 p2 x y + s3 r2 + s4 r2^2

OpenCV adds these to the radially scaled point; Fisheye624 (COLMAP's RAD_TAN_THIN_PRISM_FISHEYE) adds them
to the fisheye-plane point, with its ``(p0, p1)`` in the slots of OpenCV's ``(p2, p1)``.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .base import in_image
from .solvers import newton_polish_2d, solve_2d


def tangential_prism(xy: Tensor, p1: float, p2: float, s: tuple[float, float, float, float]) -> tuple[Tensor, Tensor]:
    """``(dx, dy)``, each ``(...)``, of plane points ``xy (..., 2)`` (module formula)."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + r2 * (s[0] + s[1] * r2)
    dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + r2 * (s[2] + s[3] * r2)
    return dx, dy


def tangential_prism_jacobian(xy: Tensor, p1: float, p2: float,
                              s: tuple[float, float, float, float]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Entries ``(d dx/dx, d dx/dy, d dy/dx, d dy/dy)``, each ``(...)``, of :func:`tangential_prism`."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    tx = 2 * (s[0] + 2 * s[1] * r2)  # d(s1 r2 + s2 r2^2) / d r2, times 2 (d r2 / dx = 2 x)
    ty = 2 * (s[2] + 2 * s[3] * r2)
    return (2 * p1 * y + 6 * p2 * x + tx * x, 2 * p1 * x + 2 * p2 * y + tx * y,
            2 * p1 * x + 2 * p2 * y + ty * x, 6 * p1 * y + 2 * p2 * x + ty * y)


def plane_to_pixels(camera, xy: Tensor, ok: Tensor) -> tuple[Tensor, Tensor]:
    """Undistorted plane points ``xy (..., 2)`` of ``camera`` (fields ``fx fy cx cy``, methods ``distort`` and
    ``_regular``) -> ``(uv (..., 2), valid (...))``: distorted, through ``K``; points not ``ok`` (or where the
    distortion is not locally invertible) sit at the principal point and are invalid, as are pixels outside."""
    ok = ok & camera._regular(xy)
    xd = camera.distort(xy)
    uv = torch.stack([camera.fx * xd[..., 0] + camera.cx, camera.fy * xd[..., 1] + camera.cy], -1)
    centre = torch.tensor([camera.cx, camera.cy], dtype=uv.dtype, device=uv.device)
    uv = torch.where(ok.unsqueeze(-1), uv, centre)
    return uv, ok & in_image(uv, camera.width, camera.height)


def pixels_to_plane(camera, uv: Tensor) -> tuple[Tensor, Tensor]:
    """Pixels ``uv (..., 2)`` -> ``(undistorted plane points (..., 2), ok (...))`` through ``K^-1`` and
    ``camera.undistort``; pixels outside the image are solved at the principal point and are not ok."""
    inside = in_image(uv, camera.width, camera.height)
    xd = torch.stack([(uv[..., 0] - camera.cx) / camera.fx, (uv[..., 1] - camera.cy) / camera.fy], -1)
    xd = torch.where(inside.unsqueeze(-1), xd, torch.zeros_like(xd))
    xy, ok = camera.undistort(xd)
    return xy, ok & inside


def undistort_plane(camera, xy_d: Tensor, max_norm: float) -> tuple[Tensor, Tensor]:
    """Invert ``camera.distort`` on plane points ``xy_d (..., 2)`` -> ``(xy (..., 2), ok (...))``.

    2-D Newton (:func:`~omnidl.cameras.solvers.solve_2d`, roots within ``max_norm``), then one differentiable
    step (implicit-function gradient). ``ok`` is False where Newton did not converge or the root leaves the
    invertible region (``camera._regular``); ``xy`` stays finite there.
    """
    x, conv = solve_2d(camera.distort, camera.distort_jacobian, xy_d, max_norm=max_norm)
    ok = conv & camera._regular(x)
    x = torch.where(ok.unsqueeze(-1), x, torch.zeros_like(x))
    target = torch.where(ok.unsqueeze(-1), xy_d, torch.zeros_like(xy_d))
    x = newton_polish_2d(x, lambda z: camera.distort(z) - target, camera.distort_jacobian(x))
    return x, ok
