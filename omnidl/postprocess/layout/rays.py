"""Boundary rays of a panorama in the gravity-aligned layout frame (z up).

Frames. The camera frame is OpenCV (x right, y down, z forward). The layout frame used by every
solver of this package is the upright world frame of the project, ``X_w = R_wc X_c`` with::

    R_wc = [[1, 0, 0],      (x_w, y_w, z_w) = (x_c, z_c, -y_c)
            [0, 0, 1],
            [0, -1, 0]]

so the camera's ``-y`` is world ``+z`` (up) and column ``W/2`` looks along world ``+y``. The rig
centre is the origin; heights are measured from the (horizontal) camera circle.

Panorama columns. For an upright equirectangular or non-central circular panorama every column
``u`` is a vertical half-plane: the rays of that column start at ``o = Rc * b`` and leave radially,
``b = (sin lon, cos lon)`` being the horizontal direction of the column and ``lon = 2 pi u / W - pi``
(``Rc = 0`` for a central panorama). A pixel row ``v`` has latitude ``lat = pi/2 - pi v / H``. The
solvers only use this column structure through :class:`ColumnRays`.

HorizonNet boundary convention (``outputs["boundary"]``): the angle below the horizon, in radians,
``theta = -lat`` (negative = ceiling side), i.e. row ``v = (theta / pi + 0.5) * H``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

#: rotation from the OpenCV camera frame to the z-up layout frame
R_WORLD_FROM_CAM = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass
class ColumnRays:
    """Per-column boundary rays of one panorama, in the layout frame (float64 numpy).

    Attributes:
        azimuth: ``(W,)`` longitude of each column (radians, our convention ``lon``).
        origin: ``(W, 3)`` optical centre of each column (``Rc * (sin lon, cos lon, 0)``).
        ceiling: ``(W, 3)`` unit direction of the ray through the ceiling boundary.
        floor: ``(W, 3)`` unit direction of the ray through the floor boundary.
        valid: ``(W,)`` bool, columns with finite boundaries (ceiling above floor).
        width: panorama width in pixels (columns per 360 degrees).
        height: panorama height in pixels (only used to express thresholds in pixels).
        rc: rig radius in metres (0 for a central panorama).
    """

    azimuth: np.ndarray
    origin: np.ndarray
    ceiling: np.ndarray
    floor: np.ndarray
    valid: np.ndarray
    width: int
    height: int
    rc: float

    def _cached(self, key, fn):
        cache = self.__dict__.setdefault("_cache", {})
        if key not in cache:
            cache[key] = fn()
        return cache[key]

    @property
    def horizontal(self) -> np.ndarray:
        """``(W, 2)`` unit horizontal direction ``b`` of each column (from the ray directions)."""
        def f():
            h = self.ceiling[:, :2]
            n = np.linalg.norm(h, axis=1, keepdims=True)
            return h / np.where(n > 0, n, 1.0)
        return self._cached("b", f)

    def elevations(self) -> tuple[np.ndarray, np.ndarray]:
        """Observed ceiling and floor latitudes ``(W,)`` (radians, up positive)."""
        def el(d):
            return np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
        return self._cached("lat", lambda: (el(self.ceiling), el(self.floor)))

    def moments(self, which: str) -> np.ndarray:
        """Plücker moments ``o x d`` ``(W, 3)`` of the ``'ceiling'`` or ``'floor'`` rays."""
        return self._cached("m_" + which, lambda: np.cross(self.origin, getattr(self, which)))

    def subset(self, idx: np.ndarray) -> "ColumnRays":
        return ColumnRays(self.azimuth[idx], self.origin[idx], self.ceiling[idx], self.floor[idx],
                          self.valid[idx], self.width, self.height, self.rc)


def lonlat_dir_world(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """Unit directions ``(..., 3)`` in the layout frame for longitude/latitude (radians)."""
    c = np.cos(lat)
    return np.stack([c * np.sin(lon), c * np.cos(lon), np.sin(lat)], -1)


def column_azimuths(width: int) -> np.ndarray:
    """Longitude of every column centre ``u = j + 0.5``: ``(W,)``."""
    return 2.0 * math.pi * (np.arange(width) + 0.5) / width - math.pi


def column_rays_from_angles(lat_ceiling: np.ndarray, lat_floor: np.ndarray, rc: float,
                            height: int = 512, azimuth: np.ndarray | None = None) -> ColumnRays:
    """Build :class:`ColumnRays` from per-column latitudes (radians, up positive) and the rig radius.

    Args:
        lat_ceiling, lat_floor: ``(W,)`` latitudes of the ceiling/floor boundary of each column.
        rc: rig radius in metres (``0`` = central equirectangular panorama).
        height: image height (only for thresholds expressed in pixels).
        azimuth: ``(W,)`` column longitudes; default the column centres of a full panorama.
    """
    lat_c = np.asarray(lat_ceiling, dtype=np.float64).reshape(-1)
    lat_f = np.asarray(lat_floor, dtype=np.float64).reshape(-1)
    if lat_c.shape != lat_f.shape:
        raise ValueError(f"ceiling/floor boundaries must have the same shape, got {lat_c.shape} and {lat_f.shape}")
    width = lat_c.shape[0]
    lon = column_azimuths(width) if azimuth is None else np.asarray(azimuth, dtype=np.float64).reshape(-1)
    valid = np.isfinite(lat_c) & np.isfinite(lat_f) & (lat_c > lat_f) & (np.abs(lat_c) < math.pi / 2) \
        & (np.abs(lat_f) < math.pi / 2)
    lat_c = np.where(valid, lat_c, 0.5)
    lat_f = np.where(valid, lat_f, -0.5)
    b = np.stack([np.sin(lon), np.cos(lon), np.zeros_like(lon)], -1)
    return ColumnRays(lon, float(rc) * b, lonlat_dir_world(lon, lat_c), lonlat_dir_world(lon, lat_f), valid,
                      width, int(height), float(rc))


def column_rays_from_boundary(boundary: Any, rc: float | None = None, camera: Any = None,
                              height: int | None = None) -> ColumnRays:
    """Rays of HorizonNet-style boundaries ``(2, W)`` (angle below the horizon, radians).

    Either ``camera`` (a :class:`omnidl.cameras.Camera`: its ``unproject`` is asked for the rays of
    the boundary pixels, so any upright panoramic camera works) or ``rc`` (rig radius in metres,
    the built-in circular non-central panorama; ``0`` = equirectangular) must be given.
    """
    b = _to_numpy(boundary)
    if b.ndim != 2 or b.shape[0] != 2:
        raise ValueError(f"boundary must have shape (2, W) (ceiling, floor angles), got {tuple(b.shape)}")
    width = b.shape[1]
    if camera is None:
        if rc is None:
            raise ValueError("column_rays_from_boundary needs either camera= or rc=")
        return column_rays_from_angles(-b[0], -b[1], rc, height=height or width // 2)
    import torch
    h = int(getattr(camera, "height", height or width // 2))
    w = int(getattr(camera, "width", width))
    if w != width:
        camera = camera.resized(width, h * width // w)
        h = int(camera.height)
    u = (np.arange(width) + 0.5)
    rows = (b / math.pi + 0.5) * h
    uv = torch.from_numpy(np.stack([np.broadcast_to(u, rows.shape), np.nan_to_num(rows, nan=h / 2)], -1))
    rays = camera.unproject(uv.to(torch.float64))
    o = rays.origin.detach().cpu().numpy().astype(np.float64) @ R_WORLD_FROM_CAM.T
    d = rays.direction.detach().cpu().numpy().astype(np.float64) @ R_WORLD_FROM_CAM.T
    ok = rays.valid.detach().cpu().numpy() & np.isfinite(rows)
    lon = np.arctan2(d[0, :, 0], d[0, :, 1])
    rc_est = float(np.median(np.hypot(o[0, :, 0], o[0, :, 1]))) if o.size else 0.0
    valid = ok[0] & ok[1] & (d[0, :, 2] > d[1, :, 2])
    return ColumnRays(lon, 0.5 * (o[0] + o[1]), d[0], d[1], valid, width, h, rc_est)


def _to_numpy(x: Any) -> np.ndarray:
    try:
        import torch
        if isinstance(x, torch.Tensor):
            return x.detach().cpu().to(torch.float64).numpy()
    except ImportError:  # pragma: no cover
        pass
    return np.asarray(x, dtype=np.float64)
