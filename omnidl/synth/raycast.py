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

CEILING, WALL, FLOOR = 1, 2, 3
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
              grid: tuple[int, int] | None = None) -> RoomHit:
    """First hit of rays with the room prism (floor polygon ``(N, 2)`` CCW, ceiling at ``height``).

    With ``grid = (H, W)`` (rays in image order) and rays whose horizontal direction and origin are the
    same down every column (upright panoramas, central or non-central), the wall test runs once per
    column and the range is scaled by ``1 / |d_xy|`` per pixel: exact, and ``H`` times less work.
    """
    ox, oy, oz = origin[..., 0], origin[..., 1], origin[..., 2]
    dx, dy, dz = direction[..., 0], direction[..., 1], direction[..., 2]
    inf = torch.full_like(dz, math.inf)
    up = dz > _EPS
    down = dz < -_EPS
    safe_dz = torch.where(up | down, dz, torch.ones_like(dz))
    t_ceil = torch.where(up, (height - oz) / safe_dz, inf)
    t_floor = torch.where(down, -oz / safe_dz, inf)
    t_plane = torch.minimum(t_ceil, t_floor)
    kind_plane = torch.where(t_ceil <= t_floor, torch.full_like(dz, CEILING, dtype=torch.int64),
                             torch.full_like(dz, FLOOR, dtype=torch.int64))

    col = _column_rays(origin, direction, grid)
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
    kind = torch.where(is_wall, torch.full_like(kind_plane, WALL), kind_plane)
    kind = torch.where(torch.isfinite(t_out), kind, torch.zeros_like(kind))
    wall = torch.where(is_wall, wall, torch.full_like(wall, -1))
    return RoomHit(t_out, kind, wall, torch.where(is_wall, s_hit, torch.zeros_like(s_hit)))


def _column_rays(origin: Tensor, direction: Tensor, grid):
    """Per-column horizontal rays if every column shares one horizontal direction and origin, else None."""
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
    if float((d[..., :2] - ref * hnorm[..., None]).abs().amax()) > 4e-6:  # absolute direction error
        return None
    if origin.shape[0] == 1:
        ox, oy = origin[:, 0], origin[:, 1]
    else:
        o = origin.reshape(H, W, 3)[..., :2]
        if float((o - o[H // 2]).abs().amax()) > 1e-6:
            return None
        ox, oy = o[H // 2, :, 0], o[H // 2, :, 1]
    return (ox, oy, ref[:, 0], ref[:, 1]), hnorm, W


def _slab(o: Tensor, d: Tensor, boxes: Tensor) -> Tensor:
    """Entry range ``(K, nb)`` of rays ``o, d (K, 3)`` into yaw-rotated boxes ``(nb, 9)``; ``inf`` where missed."""
    c, s = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])               # (nb,)
    px = o[:, None, 0] - boxes[:, 0]                                     # (K, nb)
    py = o[:, None, 1] - boxes[:, 1]
    lo = torch.stack([c * px + s * py, -s * px + c * py, (o[:, None, 2] - boxes[:, 2]).expand_as(px)], -1)
    dx, dy = d[:, None, 0], d[:, None, 1]
    ld = torch.stack([c * dx + s * dy, -s * dx + c * dy, d[:, None, 2].expand_as(px)], -1)
    tiny = torch.where(ld >= 0, 1e-12, -1e-12).to(ld.dtype)
    ld = torch.where(ld.abs() < 1e-12, tiny, ld)
    inv = ld.reciprocal_()
    half = boxes[:, 3:6]
    t1 = (-half - lo) * inv
    t2 = (half - lo).mul_(inv)
    t_near = torch.minimum(t1, t2).amax(-1)
    t_far = torch.maximum(t1, t2).amin(-1)
    hit = (t_far >= t_near) & (t_near > _EPS)
    return t_near.masked_fill_(~hit, math.inf)


def cast_boxes(origin: Tensor, direction: Tensor, boxes: Tensor, groups: list[Tensor], t_best: Tensor,
               centre: Tensor, rig_radius: float, cull: bool = True) -> tuple[Tensor, Tensor]:
    """Nearest box hits closer than ``t_best``.

    Args:
        origin: ``(P, 3)`` or ``(1, 3)``; direction: ``(P, 3)`` unit; boxes: ``(B, 9)`` scene box rows.
        groups: box indices per object (culled together by one bounding sphere).
        t_best: ``(P,)`` current nearest range (e.g. the room hit); centre: ``(3,)`` camera centre;
        rig_radius: largest distance of a ray origin from ``centre``.
        cull: skip rays that miss an object's bounding sphere (``False``: test every ray, for benchmarks).
    Returns:
        ``t (P,)`` updated nearest range and ``box (P,)`` int64 index of the hit box (``-1`` = none).
    """
    t_best = t_best.clone()
    box_id = torch.full(t_best.shape, -1, dtype=torch.int64, device=t_best.device)
    if len(boxes) == 0:
        return t_best, box_id
    central = origin.shape[0] == 1
    boxes_cpu = boxes.detach().to("cpu", torch.float64)
    # bounding spheres of each object
    spheres = []
    for g in groups:
        b = boxes_cpu[g]
        corners = []
        for sx in (-1, 1):
            for sy in (-1, 1):
                c, s = torch.cos(b[:, 6]), torch.sin(b[:, 6])
                x = b[:, 0] + c * sx * b[:, 3] - s * sy * b[:, 4]
                y = b[:, 1] + s * sx * b[:, 3] + c * sy * b[:, 4]
                corners.append(torch.stack([x, y], -1))
        corners = torch.cat(corners)
        lo_xy, hi_xy = corners.min(0).values, corners.max(0).values
        lo_z, hi_z = (b[:, 2] - b[:, 5]).min(), (b[:, 2] + b[:, 5]).max()
        mid = torch.cat([(lo_xy + hi_xy) / 2, ((lo_z + hi_z) / 2)[None]])
        rad = torch.cat([(hi_xy - lo_xy) / 2, ((hi_z - lo_z) / 2)[None]]).norm()
        spheres.append((mid, float(rad)))
    mids = torch.stack([m for m, _ in spheres]).to(direction)
    radius = torch.tensor([r for _, r in spheres], dtype=direction.dtype, device=direction.device)
    if not cull:
        cand_all = None
        always = torch.ones(len(groups), dtype=torch.bool)
    elif central or rig_radius <= 0:
        # cone from the camera centre tangent to each bounding sphere (exact for central rays)
        v = mids - centre.to(direction)
        dist = v.norm(dim=-1)
        rads = radius + rig_radius + 1e-3
        always = dist <= rads
        cos_thr = torch.sqrt((1 - (rads / dist.clamp_min(1e-9)) ** 2).clamp_min(0.0)) - 1e-4
        cand_all = direction @ (v / dist.clamp_min(1e-9)[:, None]).T >= cos_thr[None]      # (P, G)
    else:
        # each ray's own line against each sphere: |c - o|^2 - ((c - o).d)^2 <= r^2 and (c - o).d >= -r
        r = radius + 1e-2
        proj = direction @ mids.T - (origin * direction).sum(-1, keepdim=True)            # (P, G)
        dist2 = (mids * mids).sum(-1) - 2 * origin @ mids.T + (origin * origin).sum(-1, keepdim=True)
        cand_all = (dist2 - proj * proj <= r * r) & (proj >= -r)
        always = torch.zeros(len(groups), dtype=torch.bool)
    for gi, g in enumerate(groups):
        if bool(always[gi]):
            idx = torch.arange(direction.shape[0], device=direction.device)
        else:
            idx = cand_all[:, gi].nonzero()[:, 0]
        if idx.numel() == 0:
            continue
        d = direction[idx]
        o = origin.expand(1, 3) if central else origin[idx]
        if central:
            o = o.expand(len(idx), 3)
        tg, kg = _slab(o, d, boxes[g.to(boxes.device)]).min(dim=1)         # (K,)
        closer = tg < t_best[idx]
        sel = idx[closer]
        t_best[sel] = tg[closer]
        box_id[sel] = g.to(box_id.device)[kg[closer]]
    return t_best, box_id


def box_normals(points: Tensor, boxes: Tensor, box_id: Tensor) -> tuple[Tensor, Tensor]:
    """Outward world normals ``(K, 3)`` of box hits and local surface coordinates ``(K, 2)``.

    ``points (K, 3)`` lie on the boxes ``box_id (K,)`` (rows of ``boxes``).
    """
    b = boxes[box_id]
    c, s = torch.cos(b[:, 6]), torch.sin(b[:, 6])
    px, py = points[:, 0] - b[:, 0], points[:, 1] - b[:, 1]
    local = torch.stack([c * px + s * py, -s * px + c * py, points[:, 2] - b[:, 2]], -1)
    ratio = local.abs() / b[:, 3:6].clamp_min(1e-9)
    axis = ratio.argmax(-1)
    sign = torch.sign(local.gather(1, axis[:, None])[:, 0])
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    n_local = torch.zeros_like(local)
    n_local.scatter_(1, axis[:, None], sign[:, None])
    normal = torch.stack([c * n_local[:, 0] - s * n_local[:, 1], s * n_local[:, 0] + c * n_local[:, 1],
                          n_local[:, 2]], -1)
    # texture coordinates on the face: the two local axes other than the normal axis
    uv = torch.where((axis == 2)[:, None], local[:, :2],
                     torch.where((axis == 0)[:, None], local[:, [1, 2]], local[:, [0, 2]]))
    return normal, uv
