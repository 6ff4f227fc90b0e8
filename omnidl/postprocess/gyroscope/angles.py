"""Rotation helpers of the visual gyroscope (roll / pitch / yaw, axis-angle, tilt from an up vector).

Conventions (camera frame: OpenCV, x right, y down, z forward):

* The *orientation* of a frame is ``R = R_ref_cur`` (``(..., 3, 3)``): a direction ``d`` seen in the
  current camera frame is ``R @ d`` in the reference (upright) frame. So ``rotate_equirect(reference, R)``
  renders the current frame and ``rotate_equirect(current, R.T)`` stabilises it.
* The up direction of an upright camera is ``UP = (0, -1, 0)``. The horizon-plane normal of a frame of
  orientation ``R`` is ``n = R.T @ UP`` (its "up" vector, in the frame's own camera coordinates).
* Angles: ``R = R_y(yaw) @ R_x(pitch) @ R_z(roll)`` (radians), the convention of
  :mod:`omnidl.geometry.rotations` (re-exported here); roll about the optical axis z, pitch about x,
  yaw about the vertical y. Every up vector has a representation with ``pitch`` in
  ``[-pi/2, pi/2]`` and ``roll`` in ``(-pi, pi]`` (tilts beyond 90° are ``|roll| > pi/2``).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from omnidl.geometry.rotations import euler_to_matrix, matrix_to_euler, rotation_angle, rotation_x, rotation_y, \
    rotation_z

__all__ = ["UP", "euler_to_matrix", "matrix_to_euler", "rotation_angle", "rot_x", "rot_y", "rot_z", "tilt_from_up",
           "tilt_rotation", "up_from_rotation", "skew", "axis_angle_to_matrix", "random_rotations", "up_vector"]

UP = (0.0, -1.0, 0.0)


def up_vector(like: Tensor) -> Tensor:
    """``(3,)`` upright up direction ``(0, -1, 0)`` in the dtype/device of ``like``."""
    return torch.tensor(UP, dtype=like.dtype, device=like.device)


def rot_x(angle: Tensor) -> Tensor:
    """``(..., 3, 3)`` right-handed rotation about x (:func:`omnidl.geometry.rotations.rotation_x`)."""
    return rotation_x(angle)


def rot_y(angle: Tensor) -> Tensor:
    """``(..., 3, 3)`` right-handed rotation about y (the vertical of an upright camera)."""
    return rotation_y(angle)


def rot_z(angle: Tensor) -> Tensor:
    """``(..., 3, 3)`` right-handed rotation about z (the optical axis)."""
    return rotation_z(angle)


def tilt_from_up(n: Tensor) -> tuple[Tensor, Tensor]:
    """Roll and pitch ``(...)`` of the camera whose up vector (horizon normal) is ``n (..., 3)``.

    With ``R = R_x(pitch) R_z(roll)``, ``R.T @ UP = (-sin r cos p, -cos r cos p, sin p)``, so
    ``pitch = asin(n_z)`` and ``roll = atan2(-n_x, -n_y)`` (full tilt range, zenith != nadir).
    """
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    pitch = torch.asin(n[..., 2].clamp(-1.0, 1.0))
    roll = torch.atan2(-n[..., 0], -n[..., 1])
    return roll, pitch


def tilt_rotation(n: Tensor) -> Tensor:
    """``(..., 3, 3)`` rotation ``R_x(pitch) R_z(roll)`` taking up vector ``n`` to ``UP`` (zero yaw)."""
    roll, pitch = tilt_from_up(n)
    return rot_x(pitch) @ rot_z(roll)


def up_from_rotation(R: Tensor) -> Tensor:
    """Horizon normal ``R.T @ UP`` of orientation ``R (..., 3, 3)`` -> ``(..., 3)``."""
    return -R[..., 1, :]


def skew(v: Tensor) -> Tensor:
    """``(..., 3)`` -> ``(..., 3, 3)`` cross-product matrix ``[v]x`` (``[v]x w = v x w``)."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(*v.shape[:-1], 3, 3)


def axis_angle_to_matrix(w: Tensor) -> Tensor:
    """Rodrigues: rotation vector ``w (..., 3)`` (axis * angle, radians) -> ``(..., 3, 3)``."""
    theta = w.norm(dim=-1, keepdim=True)
    small = theta < 1e-8
    safe = torch.where(small, torch.ones_like(theta), theta)
    k = skew(w / safe)
    s = torch.sin(theta)[..., None]
    c = (1 - torch.cos(theta))[..., None]
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(k.shape)
    full = eye + s * k + c * (k @ k)
    approx = eye + skew(w)
    return torch.where(small[..., None], approx, full)


def random_rotations(n: int, max_tilt: float = math.pi, generator: torch.Generator | None = None,
                     dtype: torch.dtype = torch.float64) -> Tensor:
    """``(n, 3, 3)`` random orientations: up vector uniform in the spherical cap of angle ``max_tilt``
    around upright (``pi`` = uniform over the sphere, hence uniform on SO(3)) and uniform yaw."""
    u = torch.rand(n, 3, generator=generator, dtype=dtype)
    cos_t = 1 - u[:, 0] * (1 - math.cos(max_tilt))
    tilt = torch.acos(cos_t.clamp(-1, 1))
    az = (2 * u[:, 1] - 1) * math.pi
    yaw = (2 * u[:, 2] - 1) * math.pi
    # up vector tilted by `tilt` from UP towards azimuth `az` in the x-z plane
    n_up = torch.stack([torch.sin(tilt) * torch.cos(az), -torch.cos(tilt), torch.sin(tilt) * torch.sin(az)], -1)
    return rot_y(yaw) @ tilt_rotation(n_up)
