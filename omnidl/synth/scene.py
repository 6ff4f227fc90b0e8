"""A procedural room: floor plan, openings, furniture boxes, materials and lights, all from one seed.

World frame: z up, floor at ``z = 0``, ceiling at ``z = height``. Everything is NumPy float64 and
deterministic given the seed (``numpy.random.Generator``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from omnidl.classes import CLASS_ID

from . import materials as M
from ..geometry.polygon import edge_vectors, polygon_inside, polygons_overlap, rect_corners, points_in_polygon
from .room import RoomLimits, is_manhattan, sample_floor_plan


@dataclass
class Scene:
    """Everything the ray caster needs.

    Attributes:
        polygon: ``(N, 2)`` floor polygon, counter-clockwise from above; wall ``k`` joins vertex k and k+1.
        height: ceiling height (m).
        manhattan: every wall is axis-aligned.
        wall_material, floor_material, ceiling_material: material ids (``(N,)`` for walls).
        boxes: ``(B, 9)`` rows ``[cx, cy, cz, hx, hy, hz, yaw, class, instance]`` (centre, half sizes in
            the box frame, yaw about z), with ``box_material (B,)``.
        decals: ``(K, 7)`` rows ``[wall, s0, s1, z0, z1, class, instance]``: flat rectangles on a wall
            (doors, windows, boards; ``s`` = metres along the wall from its first vertex), ``decal_material (K,)``.
        lights: ``(L, 4)`` rows ``[x, y, z, intensity]``; ``ambient`` scalar.
        materials: :meth:`MaterialTable.arrays` dict.
        footprints: floor-standing obstacle rectangles ``(F, 4, 2)`` (for camera placement).
    """

    polygon: np.ndarray
    height: float
    manhattan: bool
    wall_material: np.ndarray
    floor_material: int
    ceiling_material: int
    boxes: np.ndarray
    box_material: np.ndarray
    decals: np.ndarray
    decal_material: np.ndarray
    lights: np.ndarray
    ambient: float
    materials: dict
    footprints: np.ndarray
    seed: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def num_walls(self) -> int:
        return len(self.polygon)

    def wall_instance(self, k: int) -> int:
        return 1 + k

    @property
    def floor_instance(self) -> int:
        return 1 + self.num_walls

    @property
    def ceiling_instance(self) -> int:
        return 2 + self.num_walls

    @property
    def num_primitives(self) -> int:
        """Walls + floor + ceiling + boxes + decals."""
        return self.num_walls + 2 + len(self.boxes) + len(self.decals)


# ------------------------------------------------------------------------------------------------
class _Builder:
    def __init__(self, rng: np.random.Generator, poly: np.ndarray, height: float):
        self.rng = rng
        self.poly = poly
        self.height = height
        self.table = M.MaterialTable()
        self.boxes: list[list[float]] = []
        self.box_mat: list[int] = []
        self.decals: list[list[float]] = []
        self.decal_mat: list[int] = []
        self.footprints: list[np.ndarray] = []   # floor obstacles for furniture and the camera
        self.keepout: list[np.ndarray] = []      # door clearances (furniture only)
        self.openings: dict[int, list[tuple[float, float, float, float]]] = {}
        self.next_instance = len(poly) + 3
        n = len(poly)
        e = edge_vectors(poly)
        self.length = np.linalg.norm(e, axis=1)
        self.tangent = e / self.length[:, None]
        self.inward = np.stack([-self.tangent[:, 1], self.tangent[:, 0]], 1)  # left of a CCW edge
        self.n = n

    def instance(self) -> int:
        self.next_instance += 1
        return self.next_instance - 1

    def box(self, centre, half, yaw, cls: str, inst: int, mat: int) -> None:
        self.boxes.append([*centre, *half, yaw, CLASS_ID[cls], inst])
        self.box_mat.append(mat)

    # -- openings --------------------------------------------------------------------------------
    def add_opening(self, wall: int, width: float, z0: float, z1: float, cls: str, mat: int) -> bool:
        length = self.length[wall]
        if length < width + 0.3:
            return False
        for _ in range(5):
            s0 = self.rng.uniform(0.15, length - width - 0.15)
            s1 = s0 + width
            if all(s1 + 0.1 < a or s0 - 0.1 > b for a, b, _, _ in self.openings.get(wall, [])):
                self.openings.setdefault(wall, []).append((s0, s1, z0, z1))
                self.decals.append([wall, s0, s1, z0, z1, CLASS_ID[cls], self.instance()])
                self.decal_mat.append(mat)
                return True
        return False

    def wall_rect(self, wall: int, s0: float, s1: float, depth: float) -> np.ndarray:
        a = self.poly[wall]
        t, n = self.tangent[wall], self.inward[wall]
        return np.array([a + s0 * t, a + s1 * t, a + s1 * t + depth * n, a + s0 * t + depth * n])

    # -- furniture ----------------------------------------------------------------------------------
    def free(self, rect: np.ndarray) -> bool:
        """``rect (4, 2)`` lies inside the room and overlaps no obstacle or door clearance."""
        if not polygon_inside(rect, self.poly):
            return False
        for other in self.footprints + self.keepout:
            if polygons_overlap(rect, other):
                return False
        return True

    def place_against_wall(self, width: float, depth: float, height: float, windows_ok: bool):
        """A free footprint against a random wall: returns (centre xy, yaw) or None."""
        for _ in range(12):
            wall = int(self.rng.integers(self.n))
            length = self.length[wall]
            if length < width + 0.2:
                continue
            s0 = self.rng.uniform(0.05, length - width - 0.05)
            s1 = s0 + width
            blocked = False
            for a, b, z0, _z1 in self.openings.get(wall, []):
                overlaps = not (s1 < a - 0.05 or s0 > b + 0.05)
                if overlaps and (z0 < 0.05 or height > z0 - 0.05 or not windows_ok):
                    blocked = True
            if blocked:
                continue
            rect = self.wall_rect(wall, s0, s1, depth)
            # shrink a hair off the wall so the footprint test is strict
            rect_test = self.wall_rect(wall, s0, s1, depth) + 0.01 * self.inward[wall]
            if not self.free(rect_test):
                continue
            centre = rect.mean(axis=0)
            yaw = float(np.arctan2(self.tangent[wall, 1], self.tangent[wall, 0]))
            return centre, yaw, rect
        return None

    def place_free(self, width: float, depth: float, margin: float = 0.35):
        lo, hi = self.poly.min(axis=0), self.poly.max(axis=0)
        for _ in range(15):
            centre = self.rng.uniform(lo, hi)
            if self.rng.random() < 0.7:
                ref = float(np.arctan2(self.tangent[0, 1], self.tangent[0, 0]))
                yaw = ref + 0.5 * np.pi * int(self.rng.integers(4))
            else:
                yaw = self.rng.uniform(-np.pi, np.pi)
            rect = rect_corners(centre, np.array([width / 2, depth / 2]), yaw)
            big = rect_corners(centre, np.array([width / 2 + margin, depth / 2 + margin]), yaw)
            if self.free(big):
                return centre, yaw, rect
        return None


def _local_to_world(centre_xy, yaw, local):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([centre_xy[0] + c * local[0] - s * local[1], centre_xy[1] + s * local[0] + c * local[1]])


def _add_parts(b: _Builder, centre_xy, yaw, parts, cls, inst, mats):
    """parts: list of (local centre (x, y, z_bottom), size (w, d, h), material index into mats)."""
    for (lx, ly, z0), (w, d, h), mi in parts:
        xy = _local_to_world(centre_xy, yaw, (lx, ly))
        b.box((xy[0], xy[1], z0 + h / 2), (w / 2, d / 2, h / 2), yaw, cls, inst, mats[mi])


def _table_parts(w, d, h, leg=0.05, top=0.04):
    parts = [((0, 0, h - top), (w, d, top), 0)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(((sx * (w / 2 - leg), sy * (d / 2 - leg), 0.0), (leg, leg, h - top), 0))
    return parts


def _clutter_on(b: _Builder, centre_xy, yaw, w, d, top_z, count):
    rng = b.rng
    for _ in range(count):
        cw, cd, ch = rng.uniform(0.08, 0.35), rng.uniform(0.08, 0.3), rng.uniform(0.05, 0.35)
        ch = min(ch, b.height - 0.05 - top_z)
        if cw > w - 0.05 or cd > d - 0.05 or ch < 0.03:
            continue
        lx = rng.uniform(-(w - cw) / 2, (w - cw) / 2)
        ly = rng.uniform(-(d - cd) / 2, (d - cd) / 2)
        mat = M.clutter_material(rng, b.table)
        xy = _local_to_world(centre_xy, yaw, (lx, ly))
        b.box((xy[0], xy[1], top_z + ch / 2), (cw / 2, cd / 2, ch / 2), yaw + rng.uniform(-0.4, 0.4), "clutter",
              b.instance(), mat)


def _furnish(b: _Builder) -> None:
    rng = b.rng
    h = b.height
    # openings: doors (1-2), windows (0-4), boards (0-1)
    for _ in range(int(rng.integers(1, 3))):
        door_h = rng.uniform(2.0, min(2.3, h - 0.2))
        mat = b.table.add(M.jitter(rng, M.pick(rng, M.WOOD_COLOURS + M.PAINT_COLOURS)), None, M.PANEL)
        wall = int(rng.integers(b.n))
        width = rng.uniform(0.8, 1.0)
        if b.add_opening(wall, width, 0.0, door_h, "door", mat):
            s0, s1 = b.openings[wall][-1][:2]
            b.keepout.append(b.wall_rect(wall, s0 - 0.1, s1 + 0.1, 1.0))
    for _ in range(int(rng.integers(0, 5))):
        sill = rng.uniform(0.7, 1.2)
        top = min(h - 0.25, sill + rng.uniform(0.8, 1.6))
        mat = b.table.add(M.jitter(rng, (0.75, 0.85, 0.97), 0.05), (0.95, 0.95, 0.95), M.PANEL, emissive=True)
        b.add_opening(int(rng.integers(b.n)), rng.uniform(0.6, 2.0), sill, top, "window", mat)
    if rng.random() < 0.3:
        z0 = rng.uniform(0.85, 1.1)
        mat = b.table.add((0.96, 0.96, 0.96), (0.5, 0.5, 0.52), M.PANEL)
        b.add_opening(int(rng.integers(b.n)), rng.uniform(1.0, 2.4), z0, z0 + rng.uniform(0.8, 1.2), "board", mat)

    # columns against walls (sometimes)
    if rng.random() < 0.25:
        for _ in range(int(rng.integers(1, 3))):
            size = rng.uniform(0.3, 0.6)
            spot = b.place_against_wall(size, size, h, windows_ok=False)
            if spot is None:
                continue
            centre, yaw, rect = spot
            mat = b.table.add(M.jitter(rng, M.pick(rng, M.WALL_COLOURS)))
            b.box((*centre, h / 2), (size / 2, size / 2, h / 2), yaw, "column", b.instance(), mat)
            b.footprints.append(rect)

    # wall furniture: bed, wardrobe, desk, bookcase, sofa
    kinds = ["bed", "wardrobe", "desk", "bookcase", "sofa", "bookcase", "desk"]
    for _ in range(int(rng.integers(3, 8))):
        kind = kinds[int(rng.integers(len(kinds)))]
        if kind == "bed":
            w, d, hh = rng.uniform(0.9, 1.8), rng.uniform(1.9, 2.1), rng.uniform(0.45, 0.6)
        elif kind == "wardrobe":
            w, d, hh = rng.uniform(0.8, 2.0), rng.uniform(0.5, 0.65), min(h - 0.2, rng.uniform(1.8, 2.3))
        elif kind == "desk":
            w, d, hh = rng.uniform(1.0, 1.6), rng.uniform(0.6, 0.8), rng.uniform(0.72, 0.78)
        elif kind == "bookcase":
            w, d, hh = rng.uniform(0.6, 1.2), rng.uniform(0.3, 0.4), min(h - 0.2, rng.uniform(1.2, 2.2))
        else:
            w, d, hh = rng.uniform(1.6, 2.4), rng.uniform(0.8, 1.0), rng.uniform(0.7, 0.9)
        spot = b.place_against_wall(w, d, hh, windows_ok=hh < 0.95)
        if spot is None:
            continue
        centre, yaw, rect = spot
        inst = b.instance()
        b.footprints.append(rect)
        # local frame: x along the wall, y away from the wall (y = -d/2 is at the wall)
        if kind == "bed":
            frame = M.wood_material(rng, b.table)
            sheet = M.fabric_material(rng, b.table)
            parts = [((0, 0, 0), (w, d, hh - 0.15), 0), ((0, 0.03, hh - 0.15), (w - 0.04, d - 0.1, 0.15), 1),
                     ((0, -d / 2 + 0.03, 0), (w, 0.06, hh + 0.5), 0)]
            _add_parts(b, centre, yaw, parts, "clutter", inst, [frame, sheet])
        elif kind == "wardrobe":
            mat = M.wood_material(rng, b.table) if rng.random() < 0.6 else M.paint_material(rng, b.table)
            _add_parts(b, centre, yaw, [((0, 0, 0), (w, d, hh), 0)], "bookcase", inst, [mat])
            _clutter_on(b, centre, yaw, w, d, hh, int(rng.integers(0, 3)))
        elif kind == "desk":
            mat = M.wood_material(rng, b.table)
            _add_parts(b, centre, yaw, _table_parts(w, d, hh), "table", inst, [mat])
            _clutter_on(b, centre, yaw, w, d, hh, int(rng.integers(1, 4)))
        elif kind == "bookcase":
            mat = M.wood_material(rng, b.table)
            books = M.clutter_material(rng, b.table)
            n_shelves = max(2, int(hh / 0.4))
            parts = [((0, -d / 2 + 0.01, 0), (w, 0.02, hh), 0), ((-w / 2 + 0.02, 0, 0), (0.04, d, hh), 0),
                     ((w / 2 - 0.02, 0, 0), (0.04, d, hh), 0), ((0, 0, hh - 0.03), (w, d, 0.03), 0)]
            for k in range(n_shelves):
                z = k * hh / n_shelves
                parts.append(((0, 0, z), (w - 0.08, d, 0.03), 0))
                fill = rng.uniform(0.3, 0.95)
                parts.append(((-(w - 0.08) * (1 - fill) / 2, -0.02, z + 0.03),
                              ((w - 0.08) * fill, d - 0.08, min(0.3, hh / n_shelves - 0.08)), 1))
            _add_parts(b, centre, yaw, parts, "bookcase", inst, [mat, books])
        else:
            mat = M.fabric_material(rng, b.table)
            parts = [((0, 0.05, 0), (w, d - 0.1, 0.42), 0), ((0, -d / 2 + 0.1, 0), (w, 0.2, hh), 0),
                     ((-w / 2 + 0.1, 0, 0), (0.2, d, 0.6), 0), ((w / 2 - 0.1, 0, 0), (0.2, d, 0.6), 0)]
            _add_parts(b, centre, yaw, parts, "sofa", inst, [mat])

    # free-standing: tables with chairs, single chairs, sofas
    for _ in range(int(rng.integers(1, 5))):
        kind = ["table", "table", "chair", "sofa"][int(rng.integers(4))]
        if kind == "table":
            w, d, hh = rng.uniform(0.8, 1.8), rng.uniform(0.6, 1.0), rng.uniform(0.72, 0.78)
            spot = b.place_free(w + 1.0, d + 1.0)
            if spot is None:
                continue
            centre, yaw, rect = spot
            b.footprints.append(rect)
            mat = M.wood_material(rng, b.table) if rng.random() < 0.7 else M.paint_material(rng, b.table)
            _add_parts(b, centre, yaw, _table_parts(w, d, hh), "table", b.instance(), [mat])
            _clutter_on(b, centre, yaw, w, d, hh, int(rng.integers(0, 4)))
            chair_mat = M.paint_material(rng, b.table)
            for side in (-1, 1):
                if rng.random() < 0.8:
                    cx = rng.uniform(-w / 4, w / 4)
                    _chair(b, _local_to_world(centre, yaw, (cx, side * (d / 2 + 0.25))), yaw + (np.pi if side > 0
                           else 0.0), chair_mat)
        elif kind == "chair":
            spot = b.place_free(0.5, 0.5)
            if spot is None:
                continue
            centre, yaw, rect = spot
            b.footprints.append(rect)
            _chair(b, centre, yaw, M.paint_material(rng, b.table))
        else:
            w, d, hh = rng.uniform(1.6, 2.2), rng.uniform(0.8, 0.95), rng.uniform(0.7, 0.9)
            spot = b.place_free(w, d)
            if spot is None:
                continue
            centre, yaw, rect = spot
            b.footprints.append(rect)
            mat = M.fabric_material(rng, b.table)
            parts = [((0, 0.05, 0), (w, d - 0.1, 0.42), 0), ((0, -d / 2 + 0.1, 0), (w, 0.2, hh), 0),
                     ((-w / 2 + 0.1, 0, 0), (0.2, d, 0.6), 0), ((w / 2 - 0.1, 0, 0), (0.2, d, 0.6), 0)]
            _add_parts(b, centre, yaw, parts, "sofa", b.instance(), [mat])

    # beams along the first wall's direction (sometimes)
    if rng.random() < 0.2:
        t = b.tangent[0]
        yaw = float(np.arctan2(t[1], t[0]))
        nrm = b.inward[0]
        proj = b.poly @ nrm
        span = b.poly @ t
        for _ in range(int(rng.integers(1, 3))):
            off = rng.uniform(proj.min() + 0.8, max(proj.min() + 0.81, proj.max() - 0.8))
            bw, bh = rng.uniform(0.2, 0.4), rng.uniform(0.2, 0.45)
            centre = t * 0.5 * (span.min() + span.max()) + nrm * off
            length = span.max() - span.min() + 0.2
            mat = b.table.add(M.jitter(rng, M.pick(rng, M.CEILING_COLOURS + M.WOOD_COLOURS)))
            b.box((*centre, h - bh / 2), (length / 2, bw / 2, bh / 2), yaw, "beam", b.instance(), mat)
            b.extra_beam_bottom = min(getattr(b, "extra_beam_bottom", h), h - bh)


def _chair(b: _Builder, centre_xy, yaw, mat):
    inst = b.instance()
    s = 0.45
    parts = [((0, 0, 0.42), (s, s, 0.05), 0), ((0, s / 2 - 0.03, 0.47), (s, 0.05, 0.45), 0)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(((sx * (s / 2 - 0.03), sy * (s / 2 - 0.03), 0.0), (0.04, 0.04, 0.42), 0))
    _add_parts(b, centre_xy, yaw, parts, "chair", inst, [mat])


def sample_room(seed: int | np.random.Generator, limits: RoomLimits = RoomLimits(), manhattan_ratio: float = 0.7,
                furniture: bool = True) -> Scene:
    """A random furnished room (Table A.2 limits), deterministic for a given seed."""
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    poly = sample_floor_plan(rng, limits, manhattan_ratio)
    height = float(rng.uniform(*limits.height))
    b = _Builder(rng, poly, height)
    wall_mat_main = M.wall_material(rng, b.table)
    wall_mats = np.full(len(poly), wall_mat_main, np.int64)
    if rng.random() < 0.3:  # an accent wall
        wall_mats[int(rng.integers(len(poly)))] = M.wall_material(rng, b.table)
    floor_mat = M.floor_material(rng, b.table)
    ceil_mat = M.ceiling_material(rng, b.table)
    if furniture:
        _furnish(b)
    # lights: 1-3 point lights under the ceiling inside the room
    lights = []
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    n_lights = int(rng.integers(1, 4))
    while len(lights) < n_lights:
        p = rng.uniform(lo, hi)
        if points_in_polygon(p[None], poly)[0]:
            lights.append([p[0], p[1], height - 0.3, rng.uniform(0.8, 1.4) / n_lights ** 0.5])
    ambient = float([0.25, 0.35, 0.45][int(rng.integers(3))])
    boxes = np.array(b.boxes, np.float64).reshape(-1, 9)
    decals = np.array(b.decals, np.float64).reshape(-1, 7)
    fps = np.array(b.footprints, np.float64).reshape(-1, 4, 2)
    extra = {"beam_bottom": float(getattr(b, "extra_beam_bottom", height))}
    return Scene(polygon=poly, height=height, manhattan=is_manhattan(poly), wall_material=wall_mats,
                 floor_material=floor_mat, ceiling_material=ceil_mat, boxes=boxes,
                 box_material=np.array(b.box_mat, np.int64), decals=decals,
                 decal_material=np.array(b.decal_mat, np.int64), lights=np.array(lights, np.float64),
                 ambient=ambient, materials=b.table.arrays(), footprints=fps,
                 seed=int(seed) if not isinstance(seed, np.random.Generator) else -1, extra=extra)
