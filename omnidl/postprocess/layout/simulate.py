"""Exact synthetic rooms for tests, the acceptance study, benchmarks and the noise study.

A room is a simple polygon (layout frame, metres, counter-clockwise seen from above) extruded
between ``z = h_floor < 0`` and ``z = h_ceiling > 0`` (the camera circle is at ``z = 0``). Its
per-column boundaries are computed by casting every column's radial ray (start ``Rc * b``,
horizontal direction ``b``) against the walls: this is exactly the circular non-central panorama
(or the equirectangular one for ``Rc = 0``), an independent ground truth for the solvers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .rays import ColumnRays, column_azimuths, column_rays_from_angles


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


def polygon_area(poly: np.ndarray) -> float:
    """Signed area (positive for counter-clockwise) of a ``(N, 2)`` polygon."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _segments_hit(poly: np.ndarray, origin: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First wall hit by 2-D rays ``origin + s b`` (s > 0): range ``s (M,)`` and wall index ``(M,)``."""
    a = poly
    e = np.roll(poly, -1, 0) - poly                     # (N, 2)
    # solve origin + s b = a + t e  ->  s b - t e = a - origin
    den = b[:, None, 0] * (-e[None, :, 1]) - b[:, None, 1] * (-e[None, :, 0])      # cross(b, -e)
    r = a[None] - origin[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (r[..., 0] * (-e[None, :, 1]) - r[..., 1] * (-e[None, :, 0])) / den
        t = (b[:, None, 0] * r[..., 1] - b[:, None, 1] * r[..., 0]) / den
    ok = (np.abs(den) > 1e-12) & (s > 1e-9) & (t >= -1e-12) & (t <= 1 + 1e-12)
    s = np.where(ok, s, np.inf)
    k = np.argmin(s, 1)
    return s[np.arange(len(s)), k], k


def render_boundaries(room: Room, width: int = 1024, rc: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact per-column boundary latitudes of ``room`` seen by a circular panorama of radius ``rc``.

    Returns ``lat_ceiling (W,)``, ``lat_floor (W,)`` (radians, up positive; NaN where the ray hits
    nothing) and ``wall (W,)`` the index of the wall each column sees.
    """
    lon = column_azimuths(width)
    b = np.stack([np.sin(lon), np.cos(lon)], -1)
    s, k = _segments_hit(np.asarray(room.polygon, float), rc * b, b)
    lat_c = np.arctan2(room.h_ceiling, s)
    lat_f = np.arctan2(room.h_floor, s)
    bad = ~np.isfinite(s)
    lat_c[bad] = np.nan
    lat_f[bad] = np.nan
    return lat_c, lat_f, k


def corner_columns(room: Room, width: int) -> np.ndarray:
    """Continuous column coordinate ``u`` (pixels, ``[0, W)``) of every corner's vertical edge."""
    lon = np.arctan2(room.polygon[:, 0], room.polygon[:, 1])
    return np.mod((lon + math.pi) / (2 * math.pi) * width, width)


def visible_corners(room: Room, rc: float = 1.0, tol: float = 1e-6) -> np.ndarray:
    """``(N,)`` bool: the vertical edge of each corner is seen (not hidden behind another wall)."""
    poly = np.asarray(room.polygon, float)
    b = poly / np.linalg.norm(poly, axis=1, keepdims=True)
    s, _ = _segments_hit(poly, rc * b, b)
    dist = np.linalg.norm(poly, axis=1) - rc
    return s >= dist - 1e-6 - tol * dist


def corner_probability(columns: np.ndarray, width: int, base: float = 0.96) -> np.ndarray:
    """HorizonNet corner target: ``base ** d``, ``d`` the circular distance (columns) to the nearest corner."""
    u = np.arange(width) + 0.5
    if len(columns) == 0:
        return np.zeros(width)
    d = np.abs(u[:, None] - np.asarray(columns)[None])
    d = np.minimum(d, width - d).min(1)
    return base ** d


def quantise_rows(lat: np.ndarray, height: int) -> np.ndarray:
    """Round latitudes to whole pixel rows (pixel centres), as a network reading integer rows would."""
    v = (math.pi / 2 - lat) * height / math.pi
    v = np.floor(v) + 0.5
    return math.pi / 2 - v * math.pi / height


def simulate_columns(room: Room, width: int = 1024, height: int = 512, rc: float = 1.0,
                     quantise: bool = False, noise_px: float = 0.0,
                     rng: np.random.Generator | None = None) -> tuple[ColumnRays, np.ndarray]:
    """Per-column rays and corner probability ``(W,)`` for ``room`` (optionally row-quantised/noisy)."""
    lat_c, lat_f, _ = render_boundaries(room, width, rc)
    if noise_px > 0:
        rng = rng or np.random.default_rng(0)
        step = math.pi / height
        lat_c = lat_c + rng.normal(0, noise_px * step, lat_c.shape)
        lat_f = lat_f + rng.normal(0, noise_px * step, lat_f.shape)
    if quantise:
        lat_c, lat_f = quantise_rows(lat_c, height), quantise_rows(lat_f, height)
    vis = visible_corners(room, rc)
    prob = corner_probability(corner_columns(room, width)[vis], width)
    return column_rays_from_angles(lat_c, lat_f, rc, height=height), prob


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
                        rc: float = 1.0) -> Room:
    """A Manhattan room whose convex corners are clipped by oblique walls (thesis §5.5), 5 to 14 walls."""
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
        if not visible_corners(r2, rc).all():
            continue
        return r2
    raise RuntimeError("could not sample an Atlanta room")
