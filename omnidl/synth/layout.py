"""Layout ground truth through the camera model: corners, Plücker lines, per-column boundaries, edges.

Per-column ceiling/floor boundaries are found where the column's own rays (``camera.unproject`` at
``u = j + 0.5``) pass from ceiling to wall (and from wall to floor) in the room without objects:
bracketed at pixel centres, then refined in float64 (7 rounds of 8 samples: 5e-7 px). This is exact for any
camera, including non-central panoramas whose rays in a column do not share an origin with other
columns.

When every column's rays lie in one vertical plane through one origin (upright panoramas, central or
not, and upright pinholes), the transition of a column is where its rays meet the wall it faces at the
ceiling (floor) height: that point is projected through the camera once, the 7 bisection rounds are
replayed against it without casting, and a single cast of the two final bracket ends per column checks
that they are on the expected sides. Outside an open interval of about 1e-12 px around a transition a
column's classes are monotone, so this check proves the replay took every decision the casts would have
taken: the result is the one of the 7 casting rounds, bit for bit. Columns whose check fails (none seen)
send the whole frame through the casting rounds.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .raycast import CEILING, FLOOR, WALL, _walls_2d, cast_room
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


_MID_RAYS: dict = {}


def _mid_column_rays(camera) -> tuple[Tensor, Tensor, Tensor]:
    """Camera-frame float64 ray of every column at the middle row ``v = H / 2``: ``origin (W, 3)``,
    ``direction (W, 3)``, ``valid (W,)`` (cached per camera)."""
    rays = _MID_RAYS.get(camera)
    if rays is None:
        W, H = camera.width, camera.height
        uv = torch.stack([torch.arange(W, dtype=torch.float64) + 0.5, torch.full((W,), H / 2.0, dtype=torch.float64)], -1)
        r = camera.unproject(uv)
        rays = (r.origin, r.direction, r.valid)
        if len(_MID_RAYS) > 8:
            _MID_RAYS.clear()
        _MID_RAYS[camera] = rays
    return rays


def _edge_rows(scene: Scene, camera, R: Tensor, t: Tensor, poly: Tensor, want: Tensor) -> Tensor | None:
    """``(2W,)`` float64 rows where each column's plane meets its wall at the ceiling (first ``W``) and the
    floor height, through ``camera.project``; None when a column's rays do not span a vertical plane or
    the edge point of a column in ``want (2W,)`` does not project back into its own column."""
    o_c, d_c, ok = _mid_column_rays(camera)
    W = camera.width
    d = d_c @ R.T
    o = o_c @ R.T + t
    hn = torch.linalg.vector_norm(d[:, :2], dim=-1)
    if not bool(ok.all()) or bool((hn <= 1e-6).any()):
        return None
    dx, dy = d[:, 0] / hn, d[:, 1] / hn
    t2, _, _ = _walls_2d(o[:, 0], o[:, 1], dx, dy, poly)
    if not bool(torch.isfinite(t2).all()):
        return None
    x, y = o[:, 0] + t2 * dx, o[:, 1] + t2 * dy
    z = torch.cat([torch.full((W,), float(scene.height), dtype=torch.float64), torch.zeros(W, dtype=torch.float64)])
    X = torch.stack([x.repeat(2), y.repeat(2), z], -1)
    uv, valid = camera.project((X - t) @ R)
    u = torch.arange(W, dtype=torch.float64).repeat(2) + 0.5
    if bool((want & ~valid).any()) or float(torch.where(want, uv[:, 0] - u, 0.0).abs().max()) > 1e-6:
        return None
    return uv[:, 1]


def _refine(lo: Tensor, hi: Tensor, same_of) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The bisection: ``_ROUNDS`` rounds of ``_SUBDIV - 1`` samples in ``[lo, hi]`` (``(M,)`` float64).

    ``same_of(v (M, S-1)) -> (M, S-1)`` int64: 1 where a sample is on the ``lo`` side. Returns the final
    ``lo, hi`` and whether each moved off its start (i.e. is a sample whose side was decided).
    """
    frac = torch.arange(1, _SUBDIV, dtype=torch.float64) / _SUBDIV            # (S-1,)
    moved_lo = torch.zeros(lo.shape, dtype=torch.bool)
    moved_hi = torch.zeros(lo.shape, dtype=torch.bool)
    for _ in range(_ROUNDS):
        v = lo[:, None] + (hi - lo)[:, None] * frac[None]                      # (M, S-1)
        # number of leading samples on the lo side (the transition is after them)
        n_same = torch.cumprod(same_of(v), dim=1).sum(1)
        new_lo = torch.where(n_same > 0, v.gather(1, (n_same - 1).clamp_min(0)[:, None])[:, 0], lo)
        new_hi = torch.where(n_same < _SUBDIV - 1, v.gather(1, n_same.clamp_max(_SUBDIV - 2)[:, None])[:, 0], hi)
        moved_lo |= n_same > 0
        moved_hi |= n_same < _SUBDIV - 1
        lo, hi = new_lo, new_hi
    return lo, hi, moved_lo, moved_hi


def _replay(lo: Tensor, hi: Tensor, edge: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`_refine` with a sample on the ``lo`` side iff it is above ``edge (M,)``, in NumPy: the same
    float64 operations in the same order (so the same bits), without the per-op cost of small tensors."""
    lo_n, hi_n, e = lo.numpy(), hi.numpy(), edge.numpy()[:, None]
    frac = (np.arange(1, _SUBDIV, dtype=np.float64) / _SUBDIV)[None]
    rows = np.arange(len(lo_n))
    moved_lo = np.zeros(len(lo_n), bool)
    moved_hi = np.zeros(len(lo_n), bool)
    for _ in range(_ROUNDS):
        v = lo_n[:, None] + (hi_n - lo_n)[:, None] * frac                      # (M, S-1), ascending
        n_same = (v < e).sum(1)
        new_lo = np.where(n_same > 0, v[rows, np.maximum(n_same - 1, 0)], lo_n)
        new_hi = np.where(n_same < _SUBDIV - 1, v[rows, np.minimum(n_same, _SUBDIV - 2)], hi_n)
        moved_lo |= n_same > 0
        moved_hi |= n_same < _SUBDIV - 1
        lo_n, hi_n = new_lo, new_hi
    return (torch.from_numpy(lo_n), torch.from_numpy(hi_n), torch.from_numpy(moved_lo),
            torch.from_numpy(moved_hi))


def _brackets(kind_map: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per column of ``kind_map (H, W)`` (CPU): the first row ``i_c`` with CEILING above WALL below, the last row
    ``i_f`` with WALL above FLOOR below (int64 ``(W,)``; 0 and ``H - 2`` where there is none) and whether each
    exists."""
    k = kind_map.to(torch.int8)              # classes 0..3: the same comparisons on 8x less memory
    ceil_t = (k[:-1] == CEILING) & (k[1:] == WALL)
    floor_t = (k[:-1] == WALL) & (k[1:] == FLOOR)
    i_c = ceil_t.to(torch.int8).argmax(0)
    i_f = (kind_map.shape[0] - 2) - floor_t.flip(0).to(torch.int8).argmax(0)
    return i_c, i_f, ceil_t.any(0), floor_t.any(0)


def column_boundaries(scene: Scene, camera, pose: np.ndarray, kind_map: Tensor,
                      vertical_columns: bool = False) -> tuple[Tensor, Tensor]:
    """Sub-pixel rows ``(2, W)`` of the ceiling–wall and wall–floor transitions of every column, and validity.

    ``kind_map (H, W)``: room-only surface class at pixel centres (``CEILING``/``WALL``/``FLOOR``).
    The ceiling boundary is the first ceiling->wall transition from the top, the floor boundary the
    last wall->floor transition. ``vertical_columns``: the caller found every column's rays in one
    vertical plane through one origin (e.g. ``raycast.column_rays``), which allows the replayed bisection
    of the module docstring; the result does not depend on it.
    """
    H, W = kind_map.shape
    i_c, i_f, has_c, has_f = _brackets(kind_map.cpu())
    lo = torch.cat([i_c, i_f]).to(torch.float64) + 0.5
    hi = lo + 1.0
    lo_kind = torch.cat([torch.full((W,), CEILING), torch.full((W,), WALL)])
    u = torch.arange(W, dtype=torch.float64).repeat(2) + 0.5
    R = torch.as_tensor(pose[:3, :3], dtype=torch.float64)
    t = torch.as_tensor(pose[:3, 3], dtype=torch.float64)
    poly = torch.as_tensor(scene.polygon, dtype=torch.float64)
    valid = torch.stack([has_c, has_f])

    def cast_same(v: Tensor) -> Tensor:
        uv = torch.stack([u[:, None].expand_as(v), v], -1)
        kind = _room_kind(camera, (R, t), uv.reshape(-1, 2), poly, scene.height).reshape(v.shape)
        return (kind == lo_kind[:, None]).to(torch.int64)

    replayed = False
    want = valid.reshape(-1)
    edge = _edge_rows(scene, camera, R, t, poly, want) if vertical_columns else None
    if edge is not None:
        lo_f, hi_f, moved_lo, moved_hi = _replay(lo, hi, edge)
        # one cast of both ends: every decided end must lie on the side the replay put it
        sides = cast_same(torch.stack([lo_f, hi_f], 1))                         # (2W, 2)
        replayed = not bool((want & moved_lo & (sides[:, 0] != 1)).any() | (want & moved_hi & (sides[:, 1] != 0)).any())
    if not replayed:
        lo_f, hi_f, _, _ = _refine(lo, hi, cast_same)
    v = (0.5 * (lo_f + hi_f)).reshape(2, W)
    v = torch.where(valid, v, torch.full_like(v, -1.0))
    return v.to(torch.float32), valid


def _edge_map(kind_map: Tensor, wall_map: Tensor, wraps: bool) -> Tensor:
    """``(H, W)`` float 1 on wall-wall (vertical) edges and, for cameras that do not wrap (no single boundary per
    column), on every vertical class change; the ceiling/floor boundary pixels are added by the caller."""
    H, W = kind_map.shape
    walls = kind_map == WALL
    key = kind_map * 64 + torch.where(walls, wall_map.clamp_min(0), 0)
    edges = torch.zeros(H, W)
    right = torch.roll(key, -1, 1) if wraps else torch.cat([key[:, 1:], key[:, -1:]], 1)
    right_wall = torch.roll(walls, -1, 1) if wraps else torch.cat([walls[:, 1:], walls[:, -1:]], 1)
    edges.masked_fill_((key != right) & walls & right_wall, 1.0)     # wall-wall (vertical) edges
    if not wraps:
        below = torch.cat([key[1:], key[-1:]], 0)
        edges.masked_fill_((key != below) & (key > 0) & (below > 0), 1.0)
    return edges


def layout_ground_truth(scene: Scene, camera, pose: np.ndarray, kind_map: Tensor, wall_map: Tensor,
                        vertical_columns: bool = False) -> dict:
    """The layout keys of the sample dict (see ``docs/synth.md``); ``vertical_columns``: see
    :func:`column_boundaries`."""
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

    boundary, b_valid = column_boundaries(scene, camera, pose, kind_map, vertical_columns)

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
    edges = _edge_map(kind_map.cpu(), wall_map.cpu(), camera.wraps_horizontally)
    rows = boundary.floor().long().clamp(0, H - 1)
    colsi = torch.arange(W).repeat(2, 1)
    edges[rows[b_valid], colsi[b_valid]] = 1.0

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
