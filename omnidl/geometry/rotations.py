"""Rotations, the single home of rotation maths in omnidl: conversions (kornia), elementary rotations,
roll/pitch/yaw, up vector <-> tilt, random rotations, angles, upright camera <-> world.

Conventions:

* Matrices act on column vectors: ``X' = R @ X``; batches are ``(..., 3, 3)``.
* Quaternions are ``(w, x, y, z)`` (kornia's order); axis-angle vectors are ``axis * angle``.
* **Roll/pitch/yaw** are defined in the OpenCV camera frame (x right, y down, z forward), all
  right-handed rotations about the camera axes, applied as ``R = R_y(yaw) @ R_x(pitch) @ R_z(roll)``:

  ========  ===========  ==============================================================
  angle     axis         positive value
  ========  ===========  ==============================================================
  yaw       camera ``y``   the optical axis turns to the right (``+z`` towards ``+x``)
  pitch     camera ``x``   the optical axis tilts up (``+z`` towards ``-y``)
  roll      camera ``z``   the camera ``x`` axis turns towards ``+y`` (clockwise in the image)
  ========  ===========  ==============================================================

  Used as ``R_src_dst`` of :func:`omnidl.geometry.reproject`, ``euler_to_matrix(0, 0.3, 0)``
  renders a camera looking 0.3 rad above the source camera's optical axis.
* **Up vector**: the up direction of an upright camera is :data:`UP` ``= (0, -1, 0)``. A camera of
  orientation ``R = R_up_cam`` (a direction ``d`` of the camera is ``R @ d`` in the upright frame) has
  the up vector (horizon-plane normal) ``n = R.T @ UP`` in its own frame (:func:`up_from_rotation`);
  :func:`tilt_from_up` gives the roll and pitch of ``n`` (every ``n`` has one with pitch in
  ``[-pi/2, pi/2]`` and roll in ``(-pi, pi]``: tilts beyond 90° are ``|roll| > pi/2``).
* **World frame** (``docs/design.md#conventions``): gravity-aligned, ``z`` up; poses map ``X_world = R @ X_cam + t``.
  An upright camera maps camera ``-y`` to world ``+z``; at yaw 0 camera ``x`` -> world ``+x`` and
  camera ``z`` -> world ``+y`` (:data:`UPRIGHT_TO_WORLD`, the convention of ``omnidl.synth`` too).
"""
from __future__ import annotations

import math

import torch
from kornia.geometry import conversions as _kc
from torch import Tensor

from omnidl.cameras.base import safe_norm

#: ``R_world_cam`` of an upright camera at yaw 0: columns are the camera x, y, z axes in the world
UPRIGHT_TO_WORLD = ((1.0, 0.0, 0.0),
                    (0.0, 0.0, 1.0),
                    (0.0, -1.0, 0.0))

#: up direction of an upright camera in its own (OpenCV, y down) frame
UP = (0.0, -1.0, 0.0)


def _check_matrix(R: Tensor, name: str = "R") -> None:
    if R.dim() < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got {tuple(R.shape)}")


# -- conversions (kornia) --------------------------------------------------------------------
def axis_angle_to_matrix(axis_angle: Tensor) -> Tensor:
    """``(..., 3)`` axis * angle -> ``(..., 3, 3)`` (kornia; finite gradients at zero)."""
    if axis_angle.shape[-1] != 3:
        raise ValueError(f"axis_angle must have shape (..., 3), got {tuple(axis_angle.shape)}")
    return _kc.axis_angle_to_rotation_matrix(axis_angle)


def skew(v: Tensor) -> Tensor:
    """``(..., 3)`` -> ``(..., 3, 3)`` cross-product matrix ``[v]x`` (``[v]x @ w = v x w``; kornia)."""
    if v.shape[-1] != 3:
        raise ValueError(f"v must have shape (..., 3), got {tuple(v.shape)}")
    return _kc.vector_to_skew_symmetric_matrix(v.reshape(-1, 3)).reshape(*v.shape, 3)


def matrix_to_axis_angle(R: Tensor) -> Tensor:
    """``(..., 3, 3)`` -> ``(..., 3)`` axis * angle, angle in ``[0, pi]`` (kornia)."""
    _check_matrix(R)
    return _kc.rotation_matrix_to_axis_angle(R)


def quaternion_to_matrix(q: Tensor) -> Tensor:
    """``(..., 4)`` quaternion ``(w, x, y, z)`` (normalised here) -> ``(..., 3, 3)`` (kornia)."""
    if q.shape[-1] != 4:
        raise ValueError(f"quaternion must have shape (..., 4) = (w, x, y, z), got {tuple(q.shape)}")
    q = q / safe_norm(q, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny)
    return _kc.quaternion_to_rotation_matrix(q)


def matrix_to_quaternion(R: Tensor) -> Tensor:
    """``(..., 3, 3)`` -> unit quaternion ``(..., 4)`` ``(w, x, y, z)`` with ``w >= 0`` (kornia)."""
    _check_matrix(R)
    q = _kc.rotation_matrix_to_quaternion(R)
    return torch.where(q[..., :1] < 0, -q, q)


# -- elementary rotations and roll/pitch/yaw ----------------------------------------------------
def _as_tensor(x, like: Tensor | None = None) -> Tensor:
    if isinstance(x, Tensor):
        return x
    if like is not None:
        return torch.as_tensor(x, dtype=like.dtype, device=like.device)
    return torch.as_tensor(x, dtype=torch.get_default_dtype())


def rotation_x(angle: Tensor | float) -> Tensor:
    """Right-handed rotation about ``x``: ``(...)`` -> ``(..., 3, 3)``."""
    a = _as_tensor(angle)
    c, s, o, z = torch.cos(a), torch.sin(a), torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([o, z, z, z, c, -s, z, s, c], -1).reshape(*a.shape, 3, 3)


def rotation_y(angle: Tensor | float) -> Tensor:
    """Right-handed rotation about ``y``: ``(...)`` -> ``(..., 3, 3)``."""
    a = _as_tensor(angle)
    c, s, o, z = torch.cos(a), torch.sin(a), torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([c, z, s, z, o, z, -s, z, c], -1).reshape(*a.shape, 3, 3)


def rotation_z(angle: Tensor | float) -> Tensor:
    """Right-handed rotation about ``z``: ``(...)`` -> ``(..., 3, 3)``."""
    a = _as_tensor(angle)
    c, s, o, z = torch.cos(a), torch.sin(a), torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([c, -s, z, s, c, z, z, z, o], -1).reshape(*a.shape, 3, 3)


def euler_to_matrix(roll: Tensor | float, pitch: Tensor | float, yaw: Tensor | float) -> Tensor:
    """``R = R_y(yaw) @ R_x(pitch) @ R_z(roll)`` (radians, camera frame; see the module docstring).

    The angles broadcast; floats give a ``(3, 3)`` tensor of the default dtype.
    """
    ref = next((x for x in (roll, pitch, yaw) if isinstance(x, Tensor)), None)
    r, p, y = (_as_tensor(x, ref) for x in (roll, pitch, yaw))
    r, p, y = torch.broadcast_tensors(r, p, y)
    return rotation_y(y) @ rotation_x(p) @ rotation_z(r)


def matrix_to_euler(R: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Inverse of :func:`euler_to_matrix`: ``(..., 3, 3)`` -> ``(roll, pitch, yaw)``, each ``(...)``.

    Pitch is in ``[-pi/2, pi/2]``, roll and yaw in ``(-pi, pi]``. At gimbal lock
    (``|pitch| = pi/2``) roll is set to 0 and the whole rotation about the vertical goes to yaw.
    """
    _check_matrix(R)
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    cp = torch.hypot(r10, r11)
    pitch = torch.atan2(-r12, cp)
    lock = cp < 1e-6 if R.dtype == torch.float32 else cp < 1e-12
    roll = torch.where(lock, torch.zeros_like(cp), torch.atan2(r10, torch.where(lock, torch.ones_like(r11), r11)))
    yaw_n = torch.atan2(R[..., 0, 2], R[..., 2, 2])
    yaw_l = torch.atan2(-R[..., 2, 0], R[..., 0, 0])
    yaw = torch.where(lock, yaw_l, yaw_n)
    return roll, pitch, yaw


# -- angles -------------------------------------------------------------------------------------
def rotation_angle(R1: Tensor, R2: Tensor | None = None) -> Tensor:
    """Geodesic angle ``(...)`` in ``[0, pi]`` of ``R1^T R2`` (of ``R1`` alone if ``R2`` is None).

    Computed as ``atan2(|vee(M - M^T)| / 2, (tr M - 1) / 2)``: accurate for small and large angles.
    """
    _check_matrix(R1)
    M = R1 if R2 is None else R1.transpose(-1, -2) @ R2
    v = torch.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)
    s = 0.5 * safe_norm(v)
    c = 0.5 * (M[..., 0, 0] + M[..., 1, 1] + M[..., 2, 2] - 1)
    return torch.atan2(s, c)


def tilt_angle(R: Tensor) -> Tensor:
    """Angle ``(...)`` between the camera's up axis after ``R`` (``R @ (0, -1, 0)``) and the vertical."""
    _check_matrix(R)
    up = -R[..., :, 1]
    vert = torch.zeros_like(up)
    vert[..., 1] = -1
    return torch.atan2(safe_norm(torch.linalg.cross(up, vert, dim=-1)), (up * vert).sum(-1))


# -- up vector <-> tilt ----------------------------------------------------------------------------
def up_vector(like: Tensor) -> Tensor:
    """``(3,)`` :data:`UP` in the dtype and device of ``like``."""
    return torch.tensor(UP, dtype=like.dtype, device=like.device)


def up_from_rotation(R: Tensor) -> Tensor:
    """Up vector (horizon normal) ``R.T @ UP`` ``(..., 3)`` of orientations ``R = R_up_cam (..., 3, 3)``."""
    _check_matrix(R)
    return -R[..., 1, :]


def tilt_from_up(n: Tensor) -> tuple[Tensor, Tensor]:
    """Roll and pitch ``(...)`` of the camera whose up vector is ``n (..., 3)`` (any length).

    With ``R = R_x(pitch) @ R_z(roll)``, ``R.T @ UP = (-sin r cos p, -cos r cos p, sin p)``, so
    ``pitch = asin(n_z)`` and ``roll = atan2(-n_x, -n_y)`` (the full tilt range: zenith != nadir).
    """
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    pitch = torch.asin(n[..., 2].clamp(-1.0, 1.0))
    roll = torch.atan2(-n[..., 0], -n[..., 1])
    return roll, pitch


def tilt_rotation(n: Tensor) -> Tensor:
    """``(..., 3, 3)`` ``R_x(pitch) @ R_z(roll)`` of :func:`tilt_from_up`: the zero-yaw orientation
    whose up vector is ``n``, i.e. it maps ``n`` to :data:`UP`."""
    roll, pitch = tilt_from_up(n)
    return rotation_x(pitch) @ rotation_z(roll)


# -- random rotations ---------------------------------------------------------------------------
def random_rotation(n: int, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float32,
                    device: torch.device | str | None = None) -> Tensor:
    """``(n, 3, 3)`` rotations uniform over SO(3) (normalised Gaussian quaternions)."""
    q = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    return quaternion_to_matrix(q).to(dtype=dtype, device=device)


def random_tilt_rotation(n: int, max_tilt: float, max_yaw: float = math.pi,
                         generator: torch.Generator | None = None, dtype: torch.dtype = torch.float32,
                         device: torch.device | str | None = None) -> Tensor:
    """``(n, 3, 3)`` orientations ``R_up_cam`` whose tilt (:func:`tilt_angle`) is at most ``max_tilt``.

    The up vector is uniform over the spherical cap of angle ``max_tilt`` around :data:`UP`
    (``cos(tilt)`` uniform in ``[cos(max_tilt), 1]``, uniform heading; ``max_tilt = pi`` gives any
    up vector, and with ``max_yaw = pi`` rotations uniform over SO(3)), the yaw is uniform in
    ``[-max_yaw, max_yaw]``: ``R = R_y(yaw) @ tilt_rotation(n_up)``. The draws are one
    ``rand(n, 3)`` in float64 (tilt, heading, yaw), so a seeded generator gives the same rotations
    in every dtype; radians.
    """
    if not 0 <= max_tilt <= math.pi:
        raise ValueError(f"max_tilt must be in [0, pi] radians, got {max_tilt}")
    u = torch.rand(n, 3, generator=generator, dtype=torch.float64)
    tilt = torch.acos((1 - u[:, 0] * (1 - math.cos(max_tilt))).clamp(-1, 1))
    heading = (2 * u[:, 1] - 1) * math.pi
    yaw = (2 * u[:, 2] - 1) * max_yaw
    n_up = torch.stack([torch.sin(tilt) * torch.cos(heading), -torch.cos(tilt),
                        torch.sin(tilt) * torch.sin(heading)], -1)
    R = rotation_y(yaw) @ tilt_rotation(n_up)
    return R.to(dtype=dtype, device=device)


# -- upright camera <-> world ---------------------------------------------------------------------
def upright_to_world(dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """``(3, 3)`` ``R_world_cam`` of an upright camera at yaw 0 (:data:`UPRIGHT_TO_WORLD`)."""
    return torch.tensor(UPRIGHT_TO_WORLD, dtype=dtype, device=device)


def camera_to_world_rotation(R_up_cam: Tensor | None = None, yaw: Tensor | float = 0.0,
                             dtype: torch.dtype | None = None, device=None) -> Tensor:
    """``R_world_cam = UPRIGHT_TO_WORLD @ R_y(yaw) @ R_up_cam``.

    Args:
        R_up_cam: ``(..., 3, 3)`` camera frame -> the gravity-aligned (upright) camera frame with
            the same heading (identity for an upright camera).
        yaw: heading of the upright camera (camera-frame yaw: positive turns right, i.e.
            clockwise seen from above in the world).
    """
    like = R_up_cam if R_up_cam is not None else (yaw if isinstance(yaw, Tensor) else None)
    dtype = dtype or (like.dtype if like is not None else torch.float32)
    device = device or (like.device if like is not None else None)
    R = upright_to_world(dtype, device) @ rotation_y(_as_tensor(yaw).to(dtype=dtype, device=device))
    return R if R_up_cam is None else R @ R_up_cam


def upright_rotation(R_world_cam: Tensor) -> Tensor:
    """``R_up_cam (..., 3, 3)`` of camera-to-world rotations ``R_world_cam (..., 3, 3)``.

    Splits a pose rotation into heading and tilt, ``R_world_cam = R_z(h) @ UPRIGHT_TO_WORLD @ R_up_cam``,
    with ``h`` the world heading of the camera's forward axis ``z`` (of its ``x`` axis when it looks
    straight up or down): ``R_up_cam`` is the rotation from the camera frame to the upright camera frame
    with the same heading (the ground-truth orientation of the synthetic data). For a tilt that keeps
    the forward heading (e.g. a pure pitch) it inverts :func:`camera_to_world_rotation`.
    """
    _check_matrix(R_world_cam, "R_world_cam")
    f, x = R_world_cam[..., :, 2], R_world_cam[..., :, 0]
    vertical = torch.hypot(f[..., 0], f[..., 1]) < 1e-6
    heading = torch.where(vertical, torch.atan2(x[..., 1], x[..., 0]), torch.atan2(-f[..., 0], f[..., 1]))
    R_world_up = rotation_z(heading) @ upright_to_world(R_world_cam.dtype, R_world_cam.device)
    return R_world_up.transpose(-1, -2) @ R_world_cam


def camera_to_world(points: Tensor, R: Tensor, t: Tensor | None = None) -> Tensor:
    """``X_world = R @ X_cam + t`` for ``points (..., 3)``, ``R (..., 3, 3)``, ``t (..., 3)``."""
    X = torch.einsum("...ij,...j->...i", R, points)
    return X if t is None else X + t


def world_to_camera(points: Tensor, R: Tensor, t: Tensor | None = None) -> Tensor:
    """``X_cam = R^T @ (X_world - t)`` (inverse of :func:`camera_to_world`)."""
    if t is not None:
        points = points - t
    return torch.einsum("...ji,...j->...i", R, points)
