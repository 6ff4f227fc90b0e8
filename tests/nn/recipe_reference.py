"""Test reference: the calibrated-convolution offset recipe of the public CalibratedConvolutions code,
re-written from its description (``docs/design.md#calibrated-convolution-offsets``), numpy float64.

As coded there: kernel angular size from the field of view and the feature-map width
(``alpha = k / img_W * FOV``, ``d = k / (2 tan(alpha / 2))``), kernel rays ``normalize([j/d, i/d, 1])``,
Eq. 7.3 calibration scaling with a right/bottom pad (``pad_W = 2``), pixel centres at INTEGER
coordinates, ``theta = KB^-1(r)`` by 100 Newton steps from ``x0 = r``, the smallest rotation taking
``+z`` to the anchor ray (identity on the axis), and offsets ``(v_k - (i + v), u_k - (j + u))``.

``pitch`` (optional) replaces the tap spacing ``1/d`` on the tangent plane, so the same recipe can be
run with omnidl's kernel-pitch rule.
"""
from __future__ import annotations

import math

import numpy as np

#: fisheye_calibration_FOV195.txt of the reference code
F195 = (540.0, 480.0, 287.0, 287.0, 1080.0, 960.0, 195.0, 3.37012024344156e-19, -3.543830680552053e-05,
        9.999999999924497e-08, -6.883696004705416e-11)


def kb(theta: np.ndarray, k: tuple[float, float, float, float]) -> np.ndarray:
    return theta + k[0] * theta ** 3 + k[1] * theta ** 5 + k[2] * theta ** 7 + k[3] * theta ** 9


def kb_inv(r: float, k: tuple[float, float, float, float], iters: int = 100) -> float:
    x = r
    for _ in range(iters):
        f = kb(np.float64(x), k) - r
        df = 1 + 3 * k[0] * x ** 2 + 5 * k[1] * x ** 4 + 7 * k[2] * x ** 6 + 9 * k[3] * x ** 8
        x = x - f / df
    return float(x)


def rotation_z_to(vec: np.ndarray) -> np.ndarray:
    """Rodrigues rotation about ``vec x z`` by ``-theta``: takes ``+z`` to the unit ``vec``."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(vec, z)
    n = np.linalg.norm(axis)
    if n == 0:
        return np.eye(3)
    axis = axis / n
    theta = math.acos(np.clip(vec @ z, -1, 1))
    a = -theta
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def scaled_calibration(calib, img_W: int, img_H: int, pad_W: int = 2, pad_H: int = 0):
    """``(cx', cy', fx', fy')`` of the recipe's Eq. 7.3 on an ``img_W x img_H`` map (integer-centred pixels)."""
    cx, cy, fx, fy, W, H = calib[:6]
    scale = (W + pad_W) / img_W
    sx = (img_W - pad_W / scale) / W
    sy = (img_H - pad_H / scale) / H
    return cx * sx, cy * sy, fx * sx, fy * sy


def recipe_offsets(calib, img_W: int, img_H: int, u: int, v: int, k: int = 3, pad_W: int = 2, pad_H: int = 0,
                   pitch: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(off_y (k, k), off_x (k, k))`` of the kernel anchored at integer pixel ``(u, v)``."""
    fov = math.radians(calib[6])
    kk = tuple(calib[7:11])
    alpha = k / img_W * fov
    d = k / (2 * math.tan(alpha / 2))
    t = 1.0 / d if pitch is None else pitch
    h_grid, w_grid = np.meshgrid(np.arange(k) - k // 2, np.arange(k) - k // 2, indexing="ij")
    rays = np.stack([w_grid * t, h_grid * t, np.ones_like(h_grid, dtype=float)], 0).reshape(3, -1)
    rays = rays / np.linalg.norm(rays, axis=0, keepdims=True)
    cx, cy, fx, fy = scaled_calibration(calib, img_W, img_H, pad_W, pad_H)
    mx, my = (u - cx) / fx, (v - cy) / fy
    r, phi = math.hypot(mx, my), math.atan2(my, mx)
    theta = kb_inv(r, kk)
    vec = np.array([math.cos(phi) * math.sin(theta), math.sin(phi) * math.sin(theta), math.cos(theta)])
    rk = rotation_z_to(vec) @ rays
    phi_k = np.arctan2(rk[1], rk[0])
    theta_k = np.arccos(np.clip(rk[2], -1, 1))
    r_k = kb(theta_k, kk)
    u_k = (fx * r_k * np.cos(phi_k) + cx).reshape(k, k)
    v_k = (fy * r_k * np.sin(phi_k) + cy).reshape(k, k)
    return v_k - (h_grid + v), u_k - (w_grid + u)
