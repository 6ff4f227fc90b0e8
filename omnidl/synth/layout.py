"""Layout ground truth through the camera model: corners, Plücker lines, per-column boundaries, edges.

Per-column ceiling/floor boundaries are found where the column's own rays (``camera.unproject`` at
``u = j + 0.5``) pass from ceiling to wall (and from wall to floor) in the room without objects:
bracketed at pixel centres, then refined in float64 (7 rounds of 8 samples: 5e-7 px). This is exact for any
camera, including non-central panoramas whose rays in a column do not share an origin with other
columns.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .raycast import CEILING, FLOOR, WALL, cast_room
from .scene import Scene

N_MAX = 14
CORNER_BASE = 0.96
_SUBDIV = 8
_ROUNDS = 7


def corners_world(scene: Scene) -> np.ndarray:
    """``(N, 2, 3)``: ``[ceiling, floor]`` 3D corner points in layout order (world frame)."""
    p = scene.polygon
    n = len(p)
    out = np.zeros((n, 2, 3))
    out[:, :, :2] = p[:, None]
    out[:, 0, 2] = scene.height
    return out


def plucker(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Plücker line ``(d, m = a x d)`` ``(..., 6)`` through points ``a`` and ``b`` (unit ``d``)."""
    d = b - a
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return np.concatenate([d, np.cross(a, d)], -1)


def corner_visibility(scene: Scene, centre: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: the vertical edge at each corner is not hidden (in top view) by another wall,
    seen from the camera centre (HorizonNet's occlusion notion; central approximation for rigs)."""
    p = scene.polygon
    n = len(p)
    a, b = p, np.roll(p, -1, axis=0)
    vis = np.ones(n, bool)
    c = centre[:2]
    for k in range(n):
        q = p[k]
        dvec = q - c
        e = b - a
        denom = dvec[0] * e[:, 1] - dvec[1] * e[:, 0]
        ok = np.abs(denom) > 1e-12
        denom = np.where(ok, denom, 1.0)
        r = a - c
        t = (r[:, 0] * e[:, 1] - r[:, 1] * e[:, 0]) / denom
        s = (r[:, 0] * dvec[1] - r[:, 1] * dvec[0]) / denom
        blocking = ok & (t > 1e-6) & (t < 1 - 1e-6) & (s > 1e-6) & (s < 1 - 1e-6)
        blocking[[k, (k - 1) % n]] = False
        vis[k] = not bool(blocking.any())
    return vis


def _room_kind(camera, pose_t: tuple[Tensor, Tensor], uv: Tensor, poly: Tensor, height: float) -> Tensor:
    rays = camera.unproject(uv)
    R, t = pose_t
    d = rays.direction @ R.T
    o = rays.origin @ R.T + t
    kind = cast_room(o, d, poly, height).kind
    return torch.where(rays.valid, kind, torch.zeros_like(kind))


def column_boundaries(scene: Scene, camera, pose: np.ndarray, kind_map: Tensor) -> tuple[Tensor, Tensor]:
    """Sub-pixel rows ``(2, W)`` of the ceiling–wall and wall–floor transitions of every column, and validity.

    ``kind_map (H, W)``: room-only surface class at pixel centres (``CEILING``/``WALL``/``FLOOR``).
    The ceiling boundary is the first ceiling->wall transition from the top, the floor boundary the
    last wall->floor transition.
    """
    H, W = kind_map.shape
    k = kind_map.cpu()
    ceil_t = (k[:-1] == CEILING) & (k[1:] == WALL)
    floor_t = (k[:-1] == WALL) & (k[1:] == FLOOR)
    has_c, has_f = ceil_t.any(0), floor_t.any(0)
    i_c = ceil_t.to(torch.int8).argmax(0)
    i_f = (H - 2) - floor_t.flip(0).to(torch.int8).argmax(0)
    lo = torch.cat([i_c, i_f]).to(torch.float64) + 0.5
    hi = lo + 1.0
    lo_kind = torch.cat([torch.full((W,), CEILING), torch.full((W,), WALL)])
    u = torch.arange(W, dtype=torch.float64).repeat(2) + 0.5
    R = torch.as_tensor(pose[:3, :3], dtype=torch.float64)
    t = torch.as_tensor(pose[:3, 3], dtype=torch.float64)
    poly = torch.as_tensor(scene.polygon, dtype=torch.float64)
    # refine the bracket [lo, hi] by _SUBDIV samples at once, _ROUNDS times (precision 1 / _SUBDIV ** _ROUNDS px)
    frac = torch.arange(1, _SUBDIV, dtype=torch.float64) / _SUBDIV            # (S-1,)
    for _ in range(_ROUNDS):
        v = lo[:, None] + (hi - lo)[:, None] * frac[None]                      # (2W, S-1)
        uv = torch.stack([u[:, None].expand_as(v), v], -1)
        kind = _room_kind(camera, (R, t), uv.reshape(-1, 2), poly, scene.height).reshape(v.shape)
        same = (kind == lo_kind[:, None]).to(torch.int64)
        # number of leading samples on the lo side (the transition is after them)
        n_same = torch.cumprod(same, dim=1).sum(1)
        new_lo = torch.where(n_same > 0, v.gather(1, (n_same - 1).clamp_min(0)[:, None])[:, 0], lo)
        new_hi = torch.where(n_same < _SUBDIV - 1, v.gather(1, n_same.clamp_max(_SUBDIV - 2)[:, None])[:, 0], hi)
        lo, hi = new_lo, new_hi
    v = (0.5 * (lo + hi)).reshape(2, W)
    valid = torch.stack([has_c, has_f])
    v = torch.where(valid, v, torch.full_like(v, -1.0))
    return v.to(torch.float32), valid


def layout_ground_truth(scene: Scene, camera, pose: np.ndarray, kind_map: Tensor, wall_map: Tensor) -> dict:
    """The layout keys of the sample dict (see ``docs/synth.md``)."""
    H, W = kind_map.shape
    n = scene.num_walls
    R, t = pose[:3, :3], pose[:3, 3]
    cw = corners_world(scene)                                   # (N, 2, 3)
    cc = (cw - t) @ R                                           # R^T (X - t)
    uv, ok = camera.project(torch.as_tensor(cc, dtype=torch.float64))
    vis = torch.as_tensor(corner_visibility(scene, t))
    ok = ok & vis[:, None]
    nxt = np.roll(cc, -1, axis=0)
    lines = plucker(cc, nxt)                                    # (N, 2, 6)

    def pad(x: np.ndarray | Tensor, shape, dtype=torch.float32, fill=0):
        out = torch.full((N_MAX,) + shape, fill, dtype=dtype)
        out[:n] = torch.as_tensor(np.asarray(x) if not isinstance(x, Tensor) else x).to(dtype)
        return out

    boundary, b_valid = column_boundaries(scene, camera, pose, kind_map)

    # corner heat map over columns (HorizonNet): 0.96 ** distance to the nearest visible corner column
    heat = torch.zeros(1, W)
    cols = uv[:, 1, 0][ok[:, 1]]
    if cols.numel() == 0:
        cols = uv[:, 0, 0][ok[:, 0]]
    if cols.numel():
        x = torch.arange(W, dtype=torch.float64) + 0.5
        dist = (x[:, None] - cols[None]).abs()
        if camera.wraps_horizontally:
            dist = torch.minimum(dist, W - dist)
        heat[0] = (CORNER_BASE ** dist.min(1).values).to(torch.float32)

    # structural edge map (EM_gt): the pixel holding each column's ceiling/floor boundary, wall-wall edges,
    # and for cameras that do not wrap (no single boundary per column) every vertical class change
    key = kind_map.cpu() * 64 + torch.where(kind_map.cpu() == WALL, wall_map.cpu().clamp_min(0), 0)
    edges = torch.zeros(H, W)
    right = torch.roll(key, -1, 1) if camera.wraps_horizontally else torch.cat([key[:, 1:], key[:, -1:]], 1)
    walls = kind_map.cpu() == WALL
    right_wall = torch.roll(walls, -1, 1) if camera.wraps_horizontally else torch.cat([walls[:, 1:], walls[:, -1:]], 1)
    edges[(key != right) & walls & right_wall] = 1.0     # wall-wall (vertical) edges
    rows = boundary.floor().long().clamp(0, H - 1)
    colsi = torch.arange(W).repeat(2, 1)
    edges[rows[b_valid], colsi[b_valid]] = 1.0
    if not camera.wraps_horizontally:
        below = torch.cat([key[1:], key[-1:]], 0)
        edges[(key != below) & (key > 0) & (below > 0)] = 1.0

    return {
        "boundary": boundary,
        "boundary_valid": b_valid,
        "corner_heat": heat,
        "edges": edges[None],
        "corners_world": pad(cw, (2, 3)),
        "corners_cam": pad(cc, (2, 3)),
        "corners_uv": pad(torch.where(ok[..., None], uv, torch.zeros_like(uv)), (2, 2)),
        "corners_valid": pad(ok, (2,), torch.bool, False),
        "lines_cam": pad(lines, (2, 6)),
        "num_walls": torch.tensor(n, dtype=torch.int64),
    }
