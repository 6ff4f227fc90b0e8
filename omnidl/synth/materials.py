"""Surface materials: colour pools and cheap procedural textures.

A material is ``(colour1 (3,), colour2 (3,), texture, scale, emissive)``; textures are functions of
2D surface coordinates and an integer hash (no image look-ups), evaluated per hit point by the renderer's
shading op (:func:`omnidl.ops.surface_shade.texture_mix`).
"""
from __future__ import annotations

import numpy as np

from omnidl.ops.surface_shade import CHECKER, NOISE, PANEL, PLAIN, PLANKS, STRIPES  # noqa: F401 - texture kinds

# colour pools (linear-ish RGB in [0, 1])
WALL_COLOURS = [(0.92, 0.90, 0.85), (0.85, 0.82, 0.74), (0.80, 0.84, 0.86), (0.78, 0.85, 0.76),
                (0.93, 0.87, 0.80), (0.88, 0.88, 0.88), (0.86, 0.78, 0.70), (0.72, 0.78, 0.85),
                (0.95, 0.93, 0.88), (0.82, 0.80, 0.86)]
FLOOR_COLOURS = [(0.55, 0.38, 0.22), (0.66, 0.50, 0.34), (0.42, 0.30, 0.20), (0.70, 0.68, 0.64),
                 (0.50, 0.50, 0.52), (0.78, 0.72, 0.62), (0.35, 0.36, 0.42), (0.60, 0.45, 0.40)]
CEILING_COLOURS = [(0.95, 0.95, 0.94), (0.92, 0.91, 0.88), (0.90, 0.92, 0.93)]
WOOD_COLOURS = [(0.50, 0.33, 0.18), (0.62, 0.45, 0.28), (0.35, 0.23, 0.14), (0.75, 0.60, 0.42),
                (0.28, 0.20, 0.15)]
PAINT_COLOURS = [(0.93, 0.93, 0.92), (0.20, 0.20, 0.22), (0.55, 0.57, 0.60), (0.80, 0.76, 0.68),
                 (0.25, 0.35, 0.50)]
FABRIC_COLOURS = [(0.55, 0.15, 0.15), (0.20, 0.30, 0.55), (0.35, 0.45, 0.30), (0.60, 0.58, 0.55),
                  (0.30, 0.30, 0.32), (0.75, 0.65, 0.45), (0.45, 0.28, 0.45)]
CLUTTER_COLOURS = [(0.85, 0.20, 0.15), (0.15, 0.45, 0.75), (0.95, 0.80, 0.20), (0.20, 0.60, 0.30),
                   (0.90, 0.90, 0.90), (0.10, 0.10, 0.10), (0.85, 0.45, 0.10)]


class MaterialTable:
    """Growing list of materials; ``add`` returns the material (surface) index."""

    def __init__(self) -> None:
        self.c1: list[tuple[float, float, float]] = []
        self.c2: list[tuple[float, float, float]] = []
        self.texture: list[int] = []
        self.scale: list[float] = []
        self.emissive: list[bool] = []

    def add(self, c1, c2=None, texture: int = PLAIN, scale: float = 1.0, emissive: bool = False) -> int:
        c1 = tuple(float(np.clip(c, 0, 1)) for c in c1)
        c2 = c1 if c2 is None else tuple(float(np.clip(c, 0, 1)) for c in c2)
        self.c1.append(c1)
        self.c2.append(c2)
        self.texture.append(int(texture))
        self.scale.append(float(scale))
        self.emissive.append(bool(emissive))
        return len(self.c1) - 1

    def arrays(self) -> dict[str, np.ndarray]:
        return {"c1": np.array(self.c1, np.float64).reshape(-1, 3), "c2": np.array(self.c2, np.float64).reshape(-1, 3),
                "texture": np.array(self.texture, np.int64), "scale": np.array(self.scale, np.float64),
                "emissive": np.array(self.emissive, bool)}


def jitter(rng: np.random.Generator, colour, amount: float = 0.05):
    return tuple(np.clip(np.asarray(colour) * (1 + rng.uniform(-amount, amount)) + rng.uniform(-amount, amount, 3) * 0.5,
                         0, 1))


def pick(rng: np.random.Generator, pool):
    return pool[int(rng.integers(len(pool)))]


def darker(colour, f: float = 0.75):
    return tuple(np.asarray(colour) * f)


def wall_material(rng, table: MaterialTable) -> int:
    c = jitter(rng, pick(rng, WALL_COLOURS))
    tex = [PLAIN, PLAIN, PLAIN, STRIPES, NOISE][int(rng.integers(5))]
    return table.add(c, darker(c, 0.88 if tex == STRIPES else 0.93), tex, rng.uniform(0.08, 0.3))


def floor_material(rng, table: MaterialTable) -> int:
    c = jitter(rng, pick(rng, FLOOR_COLOURS))
    tex = [PLANKS, PLANKS, CHECKER, NOISE][int(rng.integers(4))]
    scale = {PLANKS: rng.uniform(0.12, 0.22), CHECKER: rng.uniform(0.3, 0.6), NOISE: rng.uniform(0.05, 0.2)}[tex]
    return table.add(c, darker(c, 0.7 if tex != NOISE else 0.85), tex, scale)


def ceiling_material(rng, table: MaterialTable) -> int:
    c = jitter(rng, pick(rng, CEILING_COLOURS), 0.02)
    tex = [PLAIN, PLAIN, CHECKER][int(rng.integers(3))]
    return table.add(c, darker(c, 0.95), tex, rng.uniform(0.5, 0.7))


def wood_material(rng, table: MaterialTable) -> int:
    c = jitter(rng, pick(rng, WOOD_COLOURS))
    return table.add(c, darker(c, 0.8), STRIPES, rng.uniform(0.01, 0.03))


def paint_material(rng, table: MaterialTable) -> int:
    return table.add(jitter(rng, pick(rng, PAINT_COLOURS)))


def fabric_material(rng, table: MaterialTable) -> int:
    c = jitter(rng, pick(rng, FABRIC_COLOURS))
    return table.add(c, darker(c, 0.85), NOISE, 0.03)


def clutter_material(rng, table: MaterialTable) -> int:
    return table.add(jitter(rng, pick(rng, CLUTTER_COLOURS), 0.1))
