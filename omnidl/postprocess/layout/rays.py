"""Boundary rays of a panorama in the gravity-aligned layout frame (z up), asked of the camera model.

Frames. The camera frame is OpenCV (x right, y down, z forward). The layout frame used by every
solver of this package is the upright world frame of the project,
``X_w = UPRIGHT_TO_WORLD @ X_c`` (:data:`omnidl.geometry.rotations.UPRIGHT_TO_WORLD`), so the
camera's ``-y`` is world ``+z`` (up). The rig centre is the origin; heights are measured from the
horizontal plane of the camera.

Panorama columns. The solvers assume an upright panorama: every column ``u`` is a vertical
half-plane whose rays start at one optical centre ``o`` (the origin for a central camera, a point of
the rig circle for the non-central panorama) and leave along the horizontal direction ``b`` of the
column. Everything about the rays (where the column looks, where its rays start, the ray of a pixel
row) comes from ``camera.unproject``; this module never re-derives a projection, so any camera with
this column structure works. The solvers only use it through :class:`ColumnRays`.

HorizonNet boundaries (``outputs["boundary"]``) are angles below the horizon, turned into pixel
rows by :func:`omnidl.geometry.boundary.angles_to_rows` before the camera is asked.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ...cameras import Camera, resolve_camera
from ...geometry.boundary import angles_to_rows
from ...geometry.rotations import UPRIGHT_TO_WORLD

#: ``UPRIGHT_TO_WORLD`` as a float64 numpy matrix (camera frame -> layout frame)
_R = np.asarray(UPRIGHT_TO_WORLD, dtype=np.float64)


def camera_rays(camera: Camera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays of pixels ``uv (..., 2)`` in the layout frame (float64 numpy).

    Returns ``origin (..., 3)``, unit ``direction (..., 3)`` and ``valid (...)`` (``camera.unproject``
    rotated by ``UPRIGHT_TO_WORLD``).
    """
    rays = camera.unproject(torch.from_numpy(np.asarray(uv, dtype=np.float64)))
    o = rays.origin.detach().cpu().numpy().astype(np.float64) @ _R.T
    d = rays.direction.detach().cpu().numpy().astype(np.float64) @ _R.T
    return o, d, rays.valid.detach().cpu().numpy()


def project_layout_points(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(..., 2)`` and validity ``(...)`` of layout-frame points ``(..., 3)`` (``camera.project``)."""
    pc = torch.from_numpy(np.asarray(points, dtype=np.float64) @ _R)      # R^T on the right: layout -> camera
    uv, valid = camera.project(pc)
    return uv.detach().cpu().numpy().astype(np.float64), valid.detach().cpu().numpy()


def _horizontal(d: np.ndarray) -> np.ndarray:
    """Unit horizontal part ``(..., 2)`` of directions ``(..., 3)``."""
    h = d[..., :2]
    n = np.linalg.norm(h, axis=-1, keepdims=True)
    return h / np.where(n > 0, n, 1.0)


@dataclass
class ColumnRays:
    """Per-column boundary rays of one panorama, in the layout frame (float64 numpy).

    Attributes:
        azimuth: ``(W,)`` azimuth ``atan2(b_x, b_y)`` of each column's rays (radians).
        origin: ``(W, 3)`` optical centre of each column.
        ceiling: ``(W, 3)`` unit direction of the ray through the ceiling boundary.
        floor: ``(W, 3)`` unit direction of the ray through the floor boundary.
        valid: ``(W,)`` bool, columns with finite boundaries (ceiling above floor).
        width: panorama width in pixels (columns per 360 degrees).
        height: panorama height in pixels (only used to express thresholds in pixels).
        camera: the camera of the panorama at ``width`` columns; :meth:`column` asks it for the ray
            of a continuous column.
    """

    azimuth: np.ndarray
    origin: np.ndarray
    ceiling: np.ndarray
    floor: np.ndarray
    valid: np.ndarray
    width: int
    height: int
    camera: Camera

    def _cached(self, key, fn):
        cache = self.__dict__.setdefault("_cache", {})
        if key not in cache:
            cache[key] = fn()
        return cache[key]

    @property
    def rc(self) -> float:
        """Median horizontal distance (metres) of the optical centres from the rig axis (0: central)."""
        return self._cached("rc", lambda: float(np.median(np.hypot(self.origin[:, 0], self.origin[:, 1])))
                            if len(self.origin) else 0.0)

    @property
    def horizontal(self) -> np.ndarray:
        """``(W, 2)`` unit horizontal direction ``b`` of each column (from the ray directions)."""
        return self._cached("b", lambda: _horizontal(self.ceiling))

    def elevations(self) -> tuple[np.ndarray, np.ndarray]:
        """Observed ceiling and floor elevations ``(W,)`` of the rays (radians, up positive)."""
        def el(d):
            return np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
        return self._cached("lat", lambda: (el(self.ceiling), el(self.floor)))

    def moments(self, which: str) -> np.ndarray:
        """Plücker moments ``o x d`` ``(W, 3)`` of the ``'ceiling'`` or ``'floor'`` rays."""
        return self._cached("m_" + which, lambda: np.cross(self.origin, getattr(self, which)))

    def column(self, u: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Top-view ray of continuous column(s) ``u``: optical centre ``(..., 2)`` and unit direction ``(..., 2)``.

        Asked of the camera at the middle row (every row of a column gives the same half-plane); the
        rays of single columns are cached (the corner assembly asks for the same corner columns again).
        """
        u = np.asarray(u, dtype=np.float64)

        def ask():
            uv = np.stack([u, np.full_like(u, self.camera.height / 2.0)], -1)
            o, d, _ = camera_rays(self.camera, uv)
            return o[..., :2], _horizontal(d)
        return self._cached(("column", float(u)), ask) if u.ndim == 0 else ask()

    def column_azimuth(self, u: float | np.ndarray) -> np.ndarray:
        """Azimuth ``atan2(b_x, b_y)`` (radians) of continuous column(s) ``u``."""
        _, b = self.column(u)
        return np.arctan2(b[..., 0], b[..., 1])

    def subset(self, idx: np.ndarray) -> "ColumnRays":
        return ColumnRays(self.azimuth[idx], self.origin[idx], self.ceiling[idx], self.floor[idx],
                          self.valid[idx], self.width, self.height, self.camera)


def column_camera(camera: Any, width: int) -> Camera:
    """``camera`` (any :func:`~omnidl.cameras.resolve_camera` spec) resized to ``width`` columns (same aspect)."""
    cam = resolve_camera(camera)
    if cam.width != width:
        cam = cam.resized(width, cam.height * width // cam.width)
    return cam


def column_rays(rows: Any, camera: Any) -> ColumnRays:
    """:class:`ColumnRays` of ceiling/floor boundary pixel rows ``(2, W)`` (continuous ``v``; NaN = missing).

    Args:
        rows: ``(2, W)`` rows of the ceiling and the floor boundary of every column ``u = j + 0.5``.
        camera: the panorama's camera (a :class:`~omnidl.cameras.Camera` or any spec of
            :func:`~omnidl.cameras.resolve_camera`); resized to ``W`` columns if needed.
    """
    r = _to_numpy(rows)
    if r.ndim != 2 or r.shape[0] != 2:
        raise ValueError(f"boundary rows must have shape (2, W) (ceiling, floor), got {tuple(r.shape)}")
    width = r.shape[1]
    cam = column_camera(camera, width)
    h = int(cam.height)
    u = np.arange(width) + 0.5
    uv = np.stack([np.broadcast_to(u, r.shape), np.nan_to_num(r, nan=h / 2)], -1)
    o, d, ok = camera_rays(cam, uv)
    ok = ok & np.isfinite(r)
    lon = np.arctan2(d[0, :, 0], d[0, :, 1])
    valid = ok[0] & ok[1] & (d[0, :, 2] > d[1, :, 2])
    return ColumnRays(lon, 0.5 * (o[0] + o[1]), d[0], d[1], valid, width, h, cam)


def column_rays_from_boundary(boundary: Any, camera: Any) -> ColumnRays:
    """:class:`ColumnRays` of HorizonNet boundaries ``(2, W)`` (angles below the horizon, radians).

    The angles become pixel rows of the camera (:func:`~omnidl.geometry.boundary.angles_to_rows`)
    and the camera's ``unproject`` gives the rays, so any upright panoramic camera works.
    """
    b = _to_numpy(boundary)
    if b.ndim != 2 or b.shape[0] != 2:
        raise ValueError(f"boundary must have shape (2, W) (ceiling, floor angles), got {tuple(b.shape)}")
    cam = column_camera(camera, b.shape[1])
    return column_rays(angles_to_rows(b, cam.height), cam)


def _to_numpy(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().to(torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)
