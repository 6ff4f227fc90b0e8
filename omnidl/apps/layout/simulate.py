"""Exact synthetic rooms for tests, the acceptance study, benchmarks and the noise study.

A room is a simple polygon (layout frame, metres, counter-clockwise seen from above) extruded
between ``z = h_floor < 0`` and ``z = h_ceiling > 0`` (the camera is at ``z = 0``). Its per-column
boundaries are exact for the given camera: every column's top-view ray (``camera.unproject``) is cast
against the walls and the ceiling/floor points there are projected back with ``camera.project``
(:func:`omnidl.data.layout_targets.room_boundary_rows`, the data engine's layout targets). The study's
default camera is the circular non-central panorama (:func:`ring_camera`; radius 0 = equirectangular).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from omnidl.cameras import Camera, resolve_camera
from omnidl.data.layout_targets import corner_probability, room_boundary_rows
from omnidl.geometry.polygon import polygon_area, ray_polygon_hit
from omnidl.postprocess.layout.rays import ColumnRays, camera_rays, column_rays, project_layout_points


@dataclass
class Room:
    """A ground-truth room: ``polygon (N, 2)`` CCW corners, heights relative to the camera circle."""

    polygon: np.ndarray
    h_ceiling: float
    h_floor: float

    @property
    def corners_3d(self) -> np.ndarray:
        """``(2N, 3)``: N ceiling corners then N floor corners (metres)."""
        n = len(self.polygon)
        c = np.concatenate([self.polygon, np.full((n, 1), self.h_ceiling)], 1)
        f = np.concatenate([self.polygon, np.full((n, 1), self.h_floor)], 1)
        return np.concatenate([c, f], 0)


def ring_camera(rc: float = 1.0, width: int = 1024, height: int | None = None) -> Camera:
    """The studies' camera: the circular non-central panorama of radius ``rc`` metres (``width x height``,
    default ``height = width / 2``); ``rc = 0`` has the geometry of the equirectangular panorama."""
    return resolve_camera("noncentral_pano", width, width // 2 if height is None else height, rc=float(rc))


def render_boundaries(room: Room, camera: Any) -> tuple[np.ndarray, np.ndarray]:
    """Exact per-column boundary rows of ``room`` seen by ``camera`` (any camera spec).

    Returns ``rows (2, W)`` (continuous pixel rows of the ceiling and the floor boundary; NaN where the
    column sees no wall) and ``wall (W,)`` the index of the wall each column sees.
    """
    return room_boundary_rows(room.polygon, room.h_ceiling, room.h_floor, camera)


def corner_columns(room: Room, camera: Any) -> np.ndarray:
    """Continuous column coordinate ``u`` (pixels, ``[0, W)``) of every corner's vertical edge."""
    cam = resolve_camera(camera)
    n = len(room.polygon)
    mid = np.c_[room.polygon, np.full(n, 0.5 * (room.h_ceiling + room.h_floor))]
    uv, _ = project_layout_points(cam, mid)
    return np.mod(uv[:, 0], cam.width)


def visible_corners(room: Room, camera: Any, tol: float = 1e-6) -> np.ndarray:
    """``(N,)`` bool: the vertical edge of each corner is seen (not hidden behind another wall).

    The corner's column ray (``camera.unproject`` of its column) must reach the corner before any wall.
    """
    cam = resolve_camera(camera)
    poly = np.asarray(room.polygon, float)
    u = corner_columns(room, cam)
    o, d, _ = camera_rays(cam, np.stack([u, np.full_like(u, cam.height / 2.0)], -1))
    o, b = o[:, :2], d[:, :2] / np.linalg.norm(d[:, :2], axis=1, keepdims=True)
    s, _ = ray_polygon_hit(poly, o, b)
    dist = np.linalg.norm(poly - o, axis=1)
    return s >= dist - 1e-6 - tol * dist


def quantise_rows(rows: np.ndarray) -> np.ndarray:
    """Round continuous pixel rows to whole rows (pixel centres), as a network reading integer rows would."""
    return np.floor(rows) + 0.5


def simulate_columns(room: Room, camera: Any, quantise: bool = False, noise_px: float = 0.0,
                     rng: np.random.Generator | None = None) -> tuple[ColumnRays, np.ndarray]:
    """Per-column rays and corner probability ``(W,)`` for ``room`` seen by ``camera`` (optionally
    row-quantised, or with Gaussian noise of ``noise_px`` pixel rows)."""
    cam = resolve_camera(camera)
    rows, _ = render_boundaries(room, cam)
    if noise_px > 0:
        rng = rng or np.random.default_rng(0)
        rows = rows - rng.normal(0, noise_px, rows.shape)
    if quantise:
        rows = quantise_rows(rows)
    vis = visible_corners(room, cam)
    prob = corner_probability(corner_columns(room, cam)[vis], cam.width)
    return column_rays(rows, cam), prob


# ---------------------------------------------------------------------------------------------
# random rooms
# ---------------------------------------------------------------------------------------------

def random_manhattan_room(rng: np.random.Generator, n_notches: int | None = None, min_wall: float = 0.5,
                          rc: float = 1.0, rotation: float | None = None) -> Room:
    """A random rectilinear room (4 to 12 walls) seen without occlusion from the origin.

    A rectangle with rectangular notches cut at some of its corners; the camera (origin) lies in the
    central cross, at least ``rc + 0.5`` m from every wall, so that every wall is visible. The whole
    room is rotated by ``rotation`` (random by default) about the vertical axis.
    """
    margin = rc + 0.6
    for _ in range(1000):
        x0, x1 = -rng.uniform(margin + 0.3, 5.0), rng.uniform(margin + 0.3, 5.0)
        y0, y1 = -rng.uniform(margin + 0.3, 5.0), rng.uniform(margin + 0.3, 5.0)
        k = int(rng.integers(0, 5)) if n_notches is None else n_notches
        which = rng.permutation(4)[:k]
        pts = []
        corners = [(x1, y0, -1, 1), (x1, y1, -1, -1), (x0, y1, 1, -1), (x0, y0, 1, 1)]   # CCW from bottom-right
        ok = True
        for ci, (cx, cy, sx, sy) in enumerate(corners):
            if ci in which:
                wmax_x = abs(cx) - margin
                wmax_y = abs(cy) - margin
                if wmax_x < min_wall or wmax_y < min_wall:
                    ok = False
                    break
                wx = rng.uniform(min_wall, wmax_x)
                wy = rng.uniform(min_wall, wmax_y)
                # notch: corner replaced by three vertices (order depends on corner, CCW polygon)
                if ci == 0:
                    pts += [(cx + sx * wx, cy), (cx + sx * wx, cy + sy * wy), (cx, cy + sy * wy)]
                elif ci == 1:
                    pts += [(cx, cy + sy * wy), (cx + sx * wx, cy + sy * wy), (cx + sx * wx, cy)]
                elif ci == 2:
                    pts += [(cx + sx * wx, cy), (cx + sx * wx, cy + sy * wy), (cx, cy + sy * wy)]
                else:
                    pts += [(cx, cy + sy * wy), (cx + sx * wx, cy + sy * wy), (cx + sx * wx, cy)]
            else:
                pts.append((cx, cy))
        if not ok:
            continue
        poly = np.array(pts, float)
        if polygon_area(poly) <= 0:
            poly = poly[::-1]
        ang = rng.uniform(-math.pi, math.pi) if rotation is None else rotation
        c, s = math.cos(ang), math.sin(ang)
        poly = poly @ np.array([[c, s], [-s, c]])
        h_c = float(rng.uniform(0.8, 1.6))
        h_f = -float(rng.uniform(1.0, 1.8))
        return Room(poly, h_c, h_f)
    raise RuntimeError("could not sample a Manhattan room")


def random_atlanta_room(rng: np.random.Generator, n_clips: int | None = None, min_wall: float = 0.5,
                        rc: float = 1.0, camera: Any = None) -> Room:
    """A Manhattan room whose convex corners are clipped by oblique walls (thesis §5.5), 5 to 14 walls.

    Every corner is visible from ``camera`` (default :func:`ring_camera` of radius ``rc``); the walls
    stay ``rc + 0.4`` m away from the camera.
    """
    camera = ring_camera(rc) if camera is None else resolve_camera(camera)
    for _ in range(1000):
        room = random_manhattan_room(rng, min_wall=min_wall, rc=rc)
        poly = room.polygon
        n = len(poly)
        # convex corners of a CCW polygon: positive turn
        prev, nxt = np.roll(poly, 1, 0), np.roll(poly, -1, 0)
        a_, b_ = poly - prev, nxt - poly
        turn = a_[:, 0] * b_[:, 1] - a_[:, 1] * b_[:, 0]
        convex = np.flatnonzero(turn > 0)
        k = int(rng.integers(1, len(convex) + 1)) if n_clips is None else min(n_clips, len(convex))
        chosen = set(rng.permutation(convex)[:k].tolist())
        out = []
        for i in range(n):
            if i not in chosen:
                out.append(poly[i])
                continue
            a, p, c = prev[i], poly[i], nxt[i]
            la, lc = np.linalg.norm(a - p), np.linalg.norm(c - p)
            ta = rng.uniform(min_wall, max(min_wall, 0.45 * la))
            tc = rng.uniform(min_wall, max(min_wall, 0.45 * lc))
            if ta >= 0.5 * la or tc >= 0.5 * lc:
                out.append(p)
                continue
            out.append(p + (a - p) / la * ta)
            out.append(p + (c - p) / lc * tc)
        poly2 = np.array(out)
        # camera circle must stay inside with a margin, and every corner visible
        e = np.roll(poly2, -1, 0) - poly2
        dist = np.abs(e[:, 0] * -poly2[:, 1] + e[:, 1] * poly2[:, 0]) / np.linalg.norm(e, axis=1)
        if dist.min() < rc + 0.4:
            continue
        r2 = Room(poly2, room.h_ceiling, room.h_floor)
        if not visible_corners(r2, camera).all():
            continue
        return r2
    raise RuntimeError("could not sample an Atlanta room")
