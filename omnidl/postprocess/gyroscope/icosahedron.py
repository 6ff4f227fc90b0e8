"""Subdivided icosahedron: near-uniform samples of the unit sphere (``10 * 4**n + 2`` vertices).

Level 0 is the regular icosahedron with vertices ``(0, ±1, ±phi)`` cyclic, normalised (so one of them is
``(-0.525731, 0.850651, 0)`` as in libPeR's files). Each level splits every triangle into four at the edge
midpoints, re-projected on the sphere. Results are cached per level (float64, CPU) and converted on demand.
"""
from __future__ import annotations

import math
from functools import lru_cache

import torch
from torch import Tensor


def _base() -> tuple[list[list[float]], list[tuple[int, int, int]]]:
    p = (1 + math.sqrt(5)) / 2
    verts = [[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0],
             [0, -1, p], [0, 1, p], [0, -1, -p], [0, 1, -p],
             [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11),
             (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6), (7, 1, 8),
             (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9),
             (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    return verts, faces


@lru_cache(maxsize=None)
def _subdivided(level: int) -> tuple[Tensor, Tensor]:
    verts, faces = _base()
    v = [list(map(float, x)) for x in verts]
    for _ in range(level):
        cache: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int) -> int:
            key = (a, b) if a < b else (b, a)
            if key not in cache:
                cache[key] = len(v)
                v.append([(v[a][k] + v[b][k]) / 2 for k in range(3)])
            return cache[key]

        new_faces = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new_faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new_faces
        norm = [math.sqrt(sum(x * x for x in p)) for p in v]
        v = [[x / nn for x in p] for p, nn in zip(v, norm)]
    vt = torch.tensor(v, dtype=torch.float64)
    vt = vt / vt.norm(dim=-1, keepdim=True)
    return vt, torch.tensor(faces, dtype=torch.int64)


_CONVERTED: dict[tuple, Tensor] = {}


def icosahedron_vertices(level: int, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """``(10 * 4**level + 2, 3)`` unit vertices of the icosahedron subdivided ``level`` times.

    The tensor is cached per (level, dtype, device) and shared by every caller (the solvers ask for it on
    every call): do not modify it in place (``.clone()`` first)."""
    if level < 0 or level > 8:
        raise ValueError(f"icosahedron subdivision level must be in [0, 8], got {level}")
    key = (int(level), dtype, str(torch.device(device)) if device is not None else "cpu")
    hit = _CONVERTED.get(key)
    if hit is None:
        hit = _CONVERTED.setdefault(key, _subdivided(int(level))[0].to(dtype=dtype, device=device))
    return hit


def icosahedron_faces(level: int) -> Tensor:
    """``(20 * 4**level, 3)`` int64 triangle vertex indices (outward orientation of the base mesh)."""
    return _subdivided(int(level))[1].clone()


def mean_edge_angle(level: int) -> float:
    """Mean geodesic edge length (radians) of the level-``level`` mesh."""
    v, f = _subdivided(int(level))
    e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    cos = (v[e[:, 0]] * v[e[:, 1]]).sum(-1).clamp(-1, 1)
    return float(torch.acos(cos).mean())
