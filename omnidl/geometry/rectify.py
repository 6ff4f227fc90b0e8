"""Fisheye -> perspective rectification and back (thesis ch. 7 §7.4.3).

A perspective (pinhole) image only holds rays in front of the camera (``z > 0``), and its
deformation grows without bound towards 90° off-axis. So a fisheye with a field of view of
180° or more cannot be rectified completely: :func:`rectification_coverage` reports which
fraction of the fisheye image a perspective image can hold at all (rays with ``z > 0``) and
which fraction a given perspective camera actually holds.

The perspective camera shares the fisheye's optical centre and axis (no rotation); by
default (:func:`perspective_camera`) it has the fisheye's image size and the same
resolution (pixels per radian) at the principal point.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from omnidl.cameras.base import Camera
from omnidl.cameras.pinhole import Pinhole

from .warp import reproject


def _axis_focal(camera: Camera, delta: float = 1e-4) -> tuple[float, float, float, float]:
    """Principal point and local focal lengths of a central camera on its optical axis (``+z``)."""
    dirs = torch.tensor([[0, 0, 1], [math.sin(delta), 0, math.cos(delta)], [-math.sin(delta), 0, math.cos(delta)],
                         [0, math.sin(delta), math.cos(delta)], [0, -math.sin(delta), math.cos(delta)]],
                        dtype=torch.float64)
    uv, valid = camera.project(dirs)
    if not bool(valid.all()):
        raise ValueError(f"{type(camera).__name__}: the optical axis (+z) is not inside the image, cannot derive a "
                         "perspective camera; pass one explicitly")
    t = 2 * math.tan(delta)
    fx = float((uv[1, 0] - uv[2, 0]) / t)
    fy = float((uv[3, 1] - uv[4, 1]) / t)
    return float(uv[0, 0]), float(uv[0, 1]), fx, fy


def perspective_camera(fisheye: Camera, width: int | None = None, height: int | None = None,
                       fov_deg: float | None = None) -> Pinhole:
    """The perspective target of :func:`rectify`.

    Args:
        fisheye: central camera looking along ``+z``.
        width, height: output size (default: the fisheye's).
        fov_deg: horizontal field of view; default: keep the fisheye's resolution at the
            principal point (focal = the fisheye's local focal length on the axis).
    """
    if not fisheye.central:
        raise ValueError(f"rectification needs a central camera; {type(fisheye).__name__} is non-central")
    width = int(width or fisheye.width)
    height = int(height or fisheye.height)
    if fov_deg is not None:
        if not 0 < fov_deg < 180:
            raise ValueError(f"fov_deg must be in (0, 180) for a perspective image, got {fov_deg}")
        return Pinhole.from_fov(width, height, math.radians(fov_deg))
    _, _, fx, fy = _axis_focal(fisheye)
    sx, sy = width / fisheye.width, height / fisheye.height
    return Pinhole(width=width, height=height, fx=abs(fx) * sx, fy=abs(fy) * sy, cx=width / 2, cy=height / 2)


def rectify(image: Tensor, fisheye: Camera, pinhole: Camera | None = None, mode: str = "bilinear"
            ) -> tuple[Tensor, Tensor]:
    """Perspective image of a fisheye image: ``reproject(image, fisheye, pinhole)``.

    Returns ``(image (B, C, Hp, Wp), valid (B, 1, Hp, Wp))``; pixels outside the fisheye's field of
    view are 0 / invalid.
    """
    pinhole = pinhole or perspective_camera(fisheye)
    return reproject(image, fisheye, pinhole, mode=mode)


def unrectify(image: Tensor, pinhole: Camera, fisheye: Camera, mode: str = "bilinear") -> tuple[Tensor, Tensor]:
    """Back to the fisheye: ``reproject(image, pinhole, fisheye)``.

    Fisheye pixels whose ray misses the perspective image (in particular every ray 90° or more
    off-axis) are 0 / invalid.
    """
    return reproject(image, pinhole, fisheye, mode=mode)


@dataclass(frozen=True)
class RectificationCoverage:
    """Fractions of the fisheye's *valid* pixels.

    Attributes:
        rectifiable: rays in front of the camera (``z > 0``): the most any perspective image can hold.
        unrectifiable: ``1 - rectifiable`` (rays 90° or more off-axis).
        covered: rays that the given perspective camera holds (``<= rectifiable``).
        valid_pixels: number of valid fisheye pixels counted.
    """

    rectifiable: float
    unrectifiable: float
    covered: float
    valid_pixels: int


def rectification_coverage(fisheye: Camera, pinhole: Camera | None = None) -> RectificationCoverage:
    """How much of ``fisheye``'s image survives rectification (evaluated at every pixel centre)."""
    pinhole = pinhole or perspective_camera(fisheye)
    rays = fisheye.unproject_grid(dtype=torch.float64)
    valid = rays.valid
    n = int(valid.sum())
    if n == 0:
        raise ValueError(f"{type(fisheye).__name__}: no valid pixel")
    front = valid & (rays.direction[..., 2] > 0)
    _, seen = pinhole.project(rays.direction)
    covered = front & seen
    rect = float(front.sum()) / n
    return RectificationCoverage(rectifiable=rect, unrectifiable=1.0 - rect, covered=float(covered.sum()) / n,
                                 valid_pixels=n)
