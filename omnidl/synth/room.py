"""Random floor plans following thesis appendix A, Table A.2.

A Manhattan floor plan is drawn first (a rectangle cut into a grid whose border cells are removed:
L, T, U, ... shaped rooms), then, following the Manhattan ratio, vertical planes clip convex
corners with oblique walls (Atlanta rooms). Layouts that break a limit are rejected and redrawn.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.polygon import edge_lengths, is_simple, polygon_area, remove_collinear, turn_angles_deg, cross2


@dataclass(frozen=True)
class RoomLimits:
    """Structural limits of Table A.2 (min, max)."""

    area: tuple[float, float] = (25.0, 110.0)          # m^2
    walls: tuple[int, int] = (4, 14)
    wall_length: tuple[float, float] = (0.5, 8.0)      # m
    wall_angle: tuple[float, float] = (25.0, 100.0)    # degrees between consecutive wall directions
    height: tuple[float, float] = (2.5, 4.25)          # m


def check_room(poly: np.ndarray, height: float, limits: RoomLimits = RoomLimits()) -> list[str]:
    """Violations of ``limits`` by a floor polygon ``(N, 2)`` (counter-clockwise) and room height; [] if fine."""
    bad = []
    n = len(poly)
    if not (limits.walls[0] <= n <= limits.walls[1]):
        bad.append(f"walls {n} not in {limits.walls}")
    if n < 3 or not is_simple(poly):
        return bad + ["polygon is not simple"]
    area = polygon_area(poly)
    if area <= 0:
        bad.append("polygon is not counter-clockwise")
    if not (limits.area[0] <= abs(area) <= limits.area[1]):
        bad.append(f"area {abs(area):.2f} not in {limits.area}")
    lengths = edge_lengths(poly)
    if lengths.min() < limits.wall_length[0] - 1e-9 or lengths.max() > limits.wall_length[1] + 1e-9:
        bad.append(f"wall lengths [{lengths.min():.3f}, {lengths.max():.3f}] not in {limits.wall_length}")
    ang = turn_angles_deg(poly)
    if ang.min() < limits.wall_angle[0] - 1e-6 or ang.max() > limits.wall_angle[1] + 1e-6:
        bad.append(f"wall angles [{ang.min():.1f}, {ang.max():.1f}] not in {limits.wall_angle}")
    if not (limits.height[0] <= height <= limits.height[1]):
        bad.append(f"height {height:.3f} not in {limits.height}")
    return bad


def is_manhattan(poly: np.ndarray, tol_deg: float = 1e-6) -> bool:
    """Every wall is parallel to the x or y axis."""
    e = np.roll(poly, -1, axis=0) - poly
    ang = np.degrees(np.arctan2(e[:, 1], e[:, 0])) % 90.0
    return bool(np.all((ang < tol_deg) | (ang > 90.0 - tol_deg)))


# ------------------------------------------------------------------------------------------------
def _grid_outline(filled: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray | None:
    """Counter-clockwise outline of the filled cells ``filled[i, j]`` (x index i, y index j); None if not one loop."""
    nx, ny = filled.shape
    pad = np.zeros((nx + 2, ny + 2), bool)
    pad[1:-1, 1:-1] = filled
    nxt: dict[tuple[int, int], tuple[int, int]] = {}
    for i in range(nx):
        for j in range(ny):
            if not filled[i, j]:
                continue
            if not pad[i + 1, j]:      # below empty: bottom edge, +x
                nxt[(i, j)] = (i + 1, j)
            if not pad[i + 2, j + 1]:  # right empty: +y
                nxt[(i + 1, j)] = (i + 1, j + 1)
            if not pad[i + 1, j + 2]:  # top empty: -x
                nxt[(i + 1, j + 1)] = (i, j + 1)
            if not pad[i, j + 1]:      # left empty: -y
                nxt[(i, j + 1)] = (i, j)
    if not nxt:
        return None
    start = min(nxt)
    loop = [start]
    cur = nxt[start]
    while cur != start:
        loop.append(cur)
        cur = nxt.get(cur)
        if cur is None or len(loop) > len(nxt):
            return None
    if len(loop) != len(nxt):  # holes or several pieces
        return None
    poly = np.array([[xs[i], ys[j]] for i, j in loop], dtype=np.float64)
    return remove_collinear(poly)


def _connected(filled: np.ndarray) -> bool:
    cells = list(zip(*np.nonzero(filled)))
    if not cells:
        return False
    seen = {cells[0]}
    stack = [cells[0]]
    while stack:
        i, j = stack.pop()
        for a, b in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
            if 0 <= a < filled.shape[0] and 0 <= b < filled.shape[1] and filled[a, b] and (a, b) not in seen:
                seen.add((a, b))
                stack.append((a, b))
    return len(seen) == len(cells)


def _diagonal_touch(filled: np.ndarray) -> bool:
    a, b = filled[:-1, :-1], filled[1:, 1:]
    c, d = filled[1:, :-1], filled[:-1, 1:]
    return bool(np.any((a & b & ~c & ~d) | (c & d & ~a & ~b)))


def sample_manhattan_polygon(rng: np.random.Generator, limits: RoomLimits = RoomLimits(),
                             max_tries: int = 1000) -> np.ndarray:
    """A rectilinear counter-clockwise floor polygon satisfying ``limits`` (area, walls, lengths)."""
    for _ in range(max_tries):
        width, depth = rng.uniform(4.0, 12.0, size=2)
        nx, ny = int(rng.integers(1, 4)), int(rng.integers(1, 4))
        xs = np.concatenate([[0.0], np.sort(rng.uniform(0.15, 0.85, nx - 1)) * width, [width]])
        ys = np.concatenate([[0.0], np.sort(rng.uniform(0.15, 0.85, ny - 1)) * depth, [depth]])
        xs, ys = np.round(xs, 2), np.round(ys, 2)
        filled = np.ones((nx, ny), bool)
        removals = int(rng.integers(0, min(nx * ny - 1, 4) + 1)) if nx * ny > 1 else 0
        for _r in range(removals):
            # a filled cell touching the outside (grid border or an already removed cell)
            pad = np.zeros((nx + 2, ny + 2), bool)
            pad[1:-1, 1:-1] = filled
            outside = ~pad
            border = [(i, j) for i in range(nx) for j in range(ny) if filled[i, j] and
                      (outside[i, j + 1] or outside[i + 2, j + 1] or outside[i + 1, j] or outside[i + 1, j + 2])]
            if not border:
                break
            i, j = border[int(rng.integers(len(border)))]
            filled[i, j] = False
            if not _connected(filled) or _diagonal_touch(filled):
                filled[i, j] = True
        poly = _grid_outline(filled, xs, ys)
        if poly is None:
            continue
        poly = poly - poly.mean(axis=0, keepdims=True)
        if not check_room(poly, limits.height[0], limits):
            return poly
    raise RuntimeError("could not draw a Manhattan floor plan within the limits; are RoomLimits consistent?")


def clip_corners(poly: np.ndarray, rng: np.random.Generator, manhattan_ratio: float,
                 limits: RoomLimits = RoomLimits()) -> np.ndarray:
    """Clip convex corners with oblique walls (each corner kept with probability ``manhattan_ratio``).

    A clipped corner ``V`` (neighbours ``A``, ``B``) becomes ``P = V + a (A-V)/|A-V|`` and
    ``Q = V + b (B-V)/|B-V|`` with the oblique wall ``PQ`` at an angle ``alpha`` to wall ``AV``
    (``b = a tan(alpha)``), so both new corners turn by ``alpha`` and ``90 - alpha`` degrees.
    """
    n = len(poly)
    e = np.roll(poly, -1, axis=0) - poly
    convex = cross2(np.roll(e, 1, axis=0), e) > 0
    lo_ang = max(limits.wall_angle[0], 90.0 - limits.wall_angle[1])
    hi_ang = 90.0 - lo_ang
    out = []
    for k in range(n):
        v = poly[k]
        if not convex[k] or rng.random() < manhattan_ratio:
            out.append(v)
            continue
        a_vec, b_vec = poly[k - 1] - v, poly[(k + 1) % n] - v
        la, lb = np.linalg.norm(a_vec), np.linalg.norm(b_vec)
        alpha = np.radians(rng.uniform(lo_ang, hi_ang))
        a = rng.uniform(0.5, max(0.5, min(3.5, 0.5 * la)))
        b = a * np.tan(alpha)
        if b > 0.5 * lb:  # keep room for the neighbouring corner's clip
            b = 0.5 * lb
            a = b / np.tan(alpha)
        if a < 0.4 or b < 0.4:
            out.append(v)
            continue
        out.append(v + a * a_vec / la)
        out.append(v + b * b_vec / lb)
    return np.array(out)


def sample_floor_plan(rng: np.random.Generator, limits: RoomLimits = RoomLimits(), manhattan_ratio: float = 0.7,
                      max_tries: int = 1000) -> np.ndarray:
    """Counter-clockwise floor polygon ``(N, 2)`` (metres, centred near the origin) within ``limits``.

    ``manhattan_ratio`` is the probability that each convex Manhattan corner is kept; the others
    are clipped by an oblique wall (Atlanta room). Clipped layouts that break a limit are redrawn
    (the clip first, then the whole plan).
    """
    if not 0.0 <= manhattan_ratio <= 1.0:
        raise ValueError(f"manhattan_ratio must be in [0, 1], got {manhattan_ratio}")
    for _ in range(max_tries):
        base = sample_manhattan_polygon(rng, limits)
        for _clip in range(10):
            poly = clip_corners(base, rng, manhattan_ratio, limits)
            if not check_room(poly, limits.height[0], limits):
                return poly
    raise RuntimeError("could not draw a floor plan within the limits")
