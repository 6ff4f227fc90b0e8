"""Vectorised torch ray casting of a :class:`~omnidl.synth.scene.Scene`.

Rays are world-frame ``origin (P, 3)`` (or ``(1, 3)`` for a central camera) and unit ``direction (P, 3)``.
The room is a vertical prism: floor plane ``z = 0``, ceiling plane ``z = height`` and one vertical
quad per polygon edge. Because the ray starts inside the prism, the first hit is the nearest of the
first plane crossing and the nearest wall segment crossing in top view (no height test needed: a wall
crossed above the ceiling is farther than the ceiling crossing). Furniture boxes (yaw-rotated) are slab
tests, culled per object with a bounding cone from the camera centre.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from omnidl.ops.surface_shade import CEILING, FLOOR, WALL  # the room hit's kinds, as the shading op reads them

_EPS = 1e-6


class RoomHit(NamedTuple):
    t: Tensor       # (P,) range along the ray
    kind: Tensor    # (P,) int64: CEILING / WALL / FLOOR, 0 = no hit
    wall: Tensor    # (P,) int64 wall index (valid where kind == WALL, else -1)
    s: Tensor       # (P,) metres along the wall from its first vertex (WALL hits)


def _walls_2d(ox: Tensor, oy: Tensor, dx: Tensor, dy: Tensor, polygon: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Nearest wall crossing of 2D rays (top view): range in units of ``|(dx, dy)|``, wall index, metres along it.

    ``ox, oy``: ``(R,)`` or ``(1,)``; ``dx, dy``: ``(R,)``. A ray leaving a counter-clockwise room from the
    inside crosses a wall from its front (``d . inward < 0``, i.e. ``cross(d, e) > 0``), which lets the
    segment test run without divisions: ``0 <= cross(a - o, d) <= cross(d, e)``.
    """
    a = polygon                                     # (N, 2)
    e = torch.roll(polygon, -1, 0) - polygon        # (N, 2)
    length = e.norm(dim=-1)
    rx = a[:, 0] - ox.reshape(-1, 1)                # (R or 1, N)
    ry = a[:, 1] - oy.reshape(-1, 1)
    dxx, dyy = dx.reshape(-1, 1), dy.reshape(-1, 1)
    denom = dxx * e[:, 1] - dyy * e[:, 0]           # (R, N) = cross(d, e)
    num_s = rx * dyy - ry * dxx                     # cross(a - o, d)
    front = (denom > 1e-12) & (num_s >= 0) & (num_s <= denom)
    t = (rx * e[:, 1] - ry * e[:, 0]) / torch.where(front, denom, torch.ones_like(denom))
    t = t.masked_fill_(~front | (t <= _EPS), math.inf)
    t_wall, wall = t.min(dim=1)
    s_hit = (num_s.gather(1, wall[:, None])[:, 0] / denom.gather(1, wall[:, None])[:, 0].clamp_min(1e-12))
    return t_wall, wall, s_hit.clamp(0, 1) * length[wall]


def cast_room(origin: Tensor, direction: Tensor, polygon: Tensor, height: float,
              grid: tuple[int, int] | None = None, columns=False,
              components: tuple[Tensor, Tensor] | None = None) -> RoomHit:
    """First hit of rays with the room prism (floor polygon ``(N, 2)`` CCW, ceiling at ``height``).

    With ``grid = (H, W)`` (rays in image order) and rays whose horizontal direction and origin are the
    same down every column (upright panoramas, central or non-central), the wall test runs once per
    column and the range is scaled by ``1 / |d_xy|`` per pixel: exact, and ``H`` times less work.
    ``columns``: the result of :func:`column_rays` for these rays and ``grid`` when the caller has it;
    ``components``: the same rays component-major, ``origin (3, P or 1)`` and ``direction (3, P)``
    (contiguous rows: faster, the same values).
    """
    if components is None:
        ox, oy, oz = origin[..., 0], origin[..., 1], origin[..., 2]
        dx, dy, dz = direction[..., 0], direction[..., 1], direction[..., 2]
    else:
        (ox, oy, oz), (dx, dy, dz) = components[0], components[1]
    up = dz > _EPS
    down = dz < -_EPS
    safe_dz = torch.where(up | down, dz, 1.0)
    t_ceil = torch.where(up, (height - oz) / safe_dz, math.inf)
    t_floor = torch.where(down, -oz / safe_dz, math.inf)
    t_plane = torch.minimum(t_ceil, t_floor)
    kind_plane = torch.where(t_ceil <= t_floor, CEILING, FLOOR)

    col = column_rays(origin, direction, grid, components) if columns is False else columns
    if col is not None:
        (cox, coy, cdx, cdy), hnorm, W = col
        t2, wall, s_hit = _walls_2d(cox, coy, cdx, cdy, polygon)       # per column, unit horizontal direction
        H = dz.numel() // W
        t_wall = (t2[None] / hnorm.reshape(H, W)).reshape(-1)
        wall = wall.repeat(H)
        s_hit = s_hit.repeat(H)
    else:
        t_wall, wall, s_hit = _walls_2d(ox, oy, dx, dy, polygon)
        t_wall, s_hit, wall = t_wall.reshape(dz.shape), s_hit.reshape(dz.shape), wall.reshape(dz.shape)

    is_wall = t_wall < t_plane
    t_out = torch.where(is_wall, t_wall, t_plane)
    kind = torch.where(is_wall, WALL, kind_plane)
    kind = torch.where(torch.isfinite(t_out), kind, 0)
    wall = torch.where(is_wall, wall, -1)
    return RoomHit(t_out, kind, wall, torch.where(is_wall, s_hit, 0.0))


def column_rays(origin: Tensor, direction: Tensor, grid, components: tuple[Tensor, Tensor] | None = None):
    """Per-column horizontal rays if every column shares one horizontal direction and origin, else None.

    Returns ``((ox, oy, dx, dy) (W,) each, |d_xy| (H, W), W)``: origin and unit horizontal direction per
    column, and the horizontal norm of every ray (``grid = (H, W)``, rays in image order).
    ``components``: as in :func:`cast_room` (the test runs on contiguous rows: the same decision).
    """
    if grid is None:
        return None
    H, W = grid
    if direction.shape[0] != H * W or H < 2:
        return None
    d = direction.reshape(H, W, 3)
    hnorm = torch.linalg.vector_norm(d[..., :2], dim=-1)                  # (H, W)
    if bool((hnorm <= 1e-6).any()):
        return None
    ref = d[H // 2, :, :2] / hnorm[H // 2, :, None]                      # the most accurate row
    if components is None:
        err = float((d[..., :2] - ref * hnorm[..., None]).abs().amax())   # absolute direction error
    else:   # the same elementwise values, one component at a time
        d_t = components[1]
        err = max(float((d_t[k].reshape(H, W) - ref[:, k] * hnorm).abs().amax()) for k in (0, 1))
    if err > 4e-6:
        return None
    if origin.shape[0] == 1:
        ox, oy = origin[:, 0], origin[:, 1]
    else:
        o = origin.reshape(H, W, 3)[..., :2]
        if float((o - o[H // 2]).abs().amax()) > 1e-6:
            return None
        ox, oy = o[H // 2, :, 0], o[H // 2, :, 1]
    return (ox, oy, ref[:, 0], ref[:, 1]), hnorm, W


def _safe_inverse(g: Tensor) -> Tensor:
    """``1 / g`` with ``|g| < 1e-12`` replaced by ``+-1e-12`` (sign of ``g``, ``+`` for zeros)."""
    if g.dtype == torch.float32:   # the same values in fewer ops (threshold and substitute are one float32)
        return torch.where(g >= 0, g.clamp_min(1e-12), g.clamp_max(-1e-12)).reciprocal_()
    tiny = torch.where(g >= 0, 1e-12, -1e-12).to(g.dtype)
    return torch.where(g.abs() < 1e-12, tiny, g).reciprocal_()


def _box_frames(o: Tensor, boxes: Tensor) -> Tensor:
    """``(10, K or 1, nb)``: rows ``cos, -sin`` | ``sin, cos`` (yaw; the x and y rows of the rotation into
    the box frames), ``-half - l`` for x, y | ``half - l`` for x, y | ``-half - l``, ``half - l`` for z,
    where ``l`` are the origins ``o (K or 1, 3)`` in the frames of ``boxes (nb, 9)``."""
    c, s = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])               # (nb,)
    px = o[:, None, 0] - boxes[:, 0]                                     # (K or 1, nb)
    py = o[:, None, 1] - boxes[:, 1]
    lx, ly, lz = c * px + s * py, -s * px + c * py, o[:, None, 2] - boxes[:, 2]
    hx, hy, hz = boxes[:, 3], boxes[:, 4], boxes[:, 5]
    rows = [c, -s, s, c]
    return torch.stack([r.expand_as(px) for r in rows] + [-hx - lx, -hy - ly, hx - lx, hy - ly, -hz - lz, hz - lz])


def _slab(o: Tensor, d: Tensor, boxes: Tensor, frames: Tensor | None = None, inv_z: Tensor | None = None) -> Tensor:
    """Entry range ``(K, nb)`` of rays ``o (K or 1, 3)``, ``d (K, 3)`` into yaw-rotated boxes ``(nb, 9)``;
    ``inf`` where missed. ``frames``: :func:`_box_frames` of ``o, boxes`` and ``inv_z (K, 1)``: the safe
    inverse of ``d[:, 2:]``, when the caller has them (a central camera's origin is shared by every box
    group, its frames are computed once per frame). The x and y axes run stacked (the same operations per
    element, half the tensor calls)."""
    f = _box_frames(o, boxes) if frames is None else frames
    g = f[0:2] * d[:, None, 0] + f[2:4] * d[:, None, 1]                  # (2, K, nb) ray direction in box x, y
    inv = _safe_inverse(g)
    t1, t2 = f[4:6] * inv, f[6:8] * inv
    near, far = torch.minimum(t1, t2), torch.maximum(t1, t2)
    inv_z = _safe_inverse(d[:, None, 2]) if inv_z is None else inv_z
    z1, z2 = f[8] * inv_z, f[9] * inv_z
    t_near = torch.maximum(torch.maximum(near[0], near[1]), torch.minimum(z1, z2))
    t_far = torch.minimum(torch.minimum(far[0], far[1]), torch.maximum(z1, z2))
    hit = (t_far >= t_near) & (t_near > _EPS)
    return t_near.masked_fill_(~hit, math.inf)


def group_spheres(boxes: Tensor, groups: list[Tensor]) -> tuple[Tensor, Tensor]:
    """Bounding spheres of box groups: centres ``(G, 3)`` and radii ``(G,)`` (float64, CPU), from the
    axis-aligned bounds of each group's yawed box corners."""
    b = boxes.detach().to("cpu", torch.float64)
    gid = torch.empty(len(b), dtype=torch.int64)
    for gi, g in enumerate(groups):
        gid[g] = gi
    c, s = torch.cos(b[:, 6:7]), torch.sin(b[:, 6:7])
    sx = torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=torch.float64)
    sy = torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=torch.float64)
    x = b[:, 0:1] + c * sx * b[:, 3:4] - s * sy * b[:, 4:5]              # (B, 4) corners
    y = b[:, 1:2] + s * sx * b[:, 3:4] + c * sy * b[:, 4:5]
    lo = torch.stack([x.amin(1), y.amin(1), b[:, 2] - b[:, 5]], -1)      # (B, 3)
    hi = torch.stack([x.amax(1), y.amax(1), b[:, 2] + b[:, 5]], -1)
    G = len(groups)
    idx = gid[:, None].expand(-1, 3)
    g_lo = torch.full((G, 3), math.inf, dtype=torch.float64).scatter_reduce_(0, idx, lo, "amin")
    g_hi = torch.full((G, 3), -math.inf, dtype=torch.float64).scatter_reduce_(0, idx, hi, "amax")
    return (g_lo + g_hi) / 2, ((g_hi - g_lo) / 2).norm(dim=-1)


def cast_boxes(origin: Tensor, direction: Tensor, boxes: Tensor, groups: list[Tensor], t_best: Tensor,
               centre: Tensor, rig_radius: float, cull: bool = True, candidates: list[Tensor] | None = None,
               spheres: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Nearest box hits closer than ``t_best``.

    Args:
        origin: ``(P, 3)`` or ``(1, 3)``; direction: ``(P, 3)`` unit; boxes: ``(B, 9)`` scene box rows.
        groups: box indices per object (culled together by one bounding sphere).
        t_best: ``(P,)`` current nearest range (e.g. the room hit); centre: ``(3,)`` camera centre;
        rig_radius: largest distance of a ray origin from ``centre``.
        cull: skip rays that miss an object's bounding sphere (``False``: test every ray, for benchmarks).
        candidates: per group, the indices of the rays to test (a superset of the rays that can hit it,
            e.g. from :mod:`omnidl.synth.tiles`); replaces the per-ray culling.
        spheres: :func:`group_spheres` of ``boxes, groups`` when the caller has them.
    Returns:
        ``t (P,)`` updated nearest range and ``box (P,)`` int64 index of the hit box (``-1`` = none).
        Ties go to the earlier group, then to the lower index inside a group; the result does not
        depend on the culling (any superset of the hitting rays gives the same bits).
    """
    t_best = t_best.clone()
    box_id = torch.full(t_best.shape, -1, dtype=torch.int64, device=t_best.device)
    if len(boxes) == 0:
        return t_best, box_id
    central = origin.shape[0] == 1
    P = direction.shape[0]
    cand_all = None
    if candidates is None and cull:
        mids, radius = group_spheres(boxes, groups) if spheres is None else spheres
        mids, radius = mids.to(direction), radius.to(direction)
        if central or rig_radius <= 0:
            # cone from the camera centre tangent to each bounding sphere (exact for central rays)
            v = mids - centre.to(direction)
            dist = v.norm(dim=-1)
            rads = radius + rig_radius + 1e-3
            cos_thr = torch.sqrt((1 - (rads / dist.clamp_min(1e-9)) ** 2).clamp_min(0.0)) - 1e-4
            cand_all = (v / dist.clamp_min(1e-9)[:, None]) @ direction.T >= cos_thr[:, None]      # (G, P)
            cand_all[dist <= rads] = True
        else:
            # each ray's own line against each sphere: |c - o|^2 - ((c - o).d)^2 <= r^2 and (c - o).d >= -r
            r = radius + 1e-2
            proj = mids @ direction.T - (origin * direction).sum(-1)[None]                      # (G, P)
            dist2 = (mids * mids).sum(-1)[:, None] - 2 * mids @ origin.T + (origin * origin).sum(-1)[None]
            cand_all = (dist2 - proj * proj <= (r * r)[:, None]) & (proj >= -r[:, None])
    everyone = torch.arange(P, device=direction.device)
    rays = []
    for gi in range(len(groups)):
        if candidates is not None:
            rays.append(candidates[gi])
        elif cand_all is None:
            rays.append(everyone)
        else:
            rays.append(cand_all[gi].nonzero()[:, 0])
    frames = _box_frames(origin, boxes) if central else None                 # (10, 1, B)
    inv_z = _safe_inverse(direction[:, 2:])                                  # (P, 1)
    for g, idx in zip(groups, rays):
        if idx.numel() == 0 or g.numel() == 0:
            continue
        g = g.to(boxes.device)
        # index_select / index_copy_: the same gathers and scatters as x[idx], several times faster
        d = direction.index_select(0, idx)
        if central:
            t_slab = _slab(origin, d, None, frames.index_select(2, g), inv_z.index_select(0, idx))
        else:
            t_slab = _slab(origin.index_select(0, idx), d, boxes[g], inv_z=inv_z.index_select(0, idx))
        tg, kg = t_slab.min(dim=1)                                           # (K,)
        closer = (tg < t_best.index_select(0, idx)).nonzero()[:, 0]
        sel = idx.index_select(0, closer)
        t_best.index_copy_(0, sel, tg.index_select(0, closer))
        box_id.index_copy_(0, sel, g.to(box_id.device).index_select(0, kg.index_select(0, closer)))
    return t_best, box_id
