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


def cast_room(origin: Tensor, direction: Tensor, polygon: Tensor, height: float) -> RoomHit:
    """First hit of rays with the room prism (floor polygon ``(N, 2)`` CCW, ceiling at ``height``)."""
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

    a = polygon                                     # (N, 2)
    e = torch.roll(polygon, -1, 0) - polygon        # (N, 2)
    length = e.norm(dim=-1)
    rx = a[:, 0] - ox.reshape(-1, 1)                # (P or 1, N)
    ry = a[:, 1] - oy.reshape(-1, 1)
    dxx, dyy = dx.reshape(-1, 1), dy.reshape(-1, 1)
    denom = dxx * e[:, 1] - dyy * e[:, 0]           # (P, N)
    bad = denom.abs() <= 1e-12
    denom.masked_fill_(bad, 1.0)
    t = (rx * e[:, 1] - ry * e[:, 0]) / denom       # (P, N) (broadcast from (1, N) for central rays)
    s = (rx * dyy - ry * dxx).div_(denom)
    miss = bad | (t <= _EPS) | (s < 0) | (s > 1)
    t = t.masked_fill(miss, math.inf)
    t_wall, wall = t.min(dim=1)
    s_hit = s.gather(1, wall[:, None])[:, 0].clamp(0, 1) * length[wall]
    t_wall, s_hit = t_wall.reshape(dz.shape), s_hit.reshape(dz.shape)
    wall = wall.reshape(dz.shape)

    is_wall = t_wall < t_plane
    t_out = torch.where(is_wall, t_wall, t_plane)
    kind = torch.where(is_wall, torch.full_like(kind_plane, WALL), kind_plane)
    kind = torch.where(torch.isfinite(t_out), kind, torch.zeros_like(kind))
    wall = torch.where(is_wall, wall, torch.full_like(wall, -1))
    return RoomHit(t_out, kind, wall, torch.where(is_wall, s_hit, torch.zeros_like(s_hit)))


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
               centre: Tensor, rig_radius: float) -> tuple[Tensor, Tensor]:
    """Nearest box hits closer than ``t_best``.

    Args:
        origin: ``(P, 3)`` or ``(1, 3)``; direction: ``(P, 3)`` unit; boxes: ``(B, 9)`` scene box rows.
        groups: box indices per object (culled together by one bounding sphere).
        t_best: ``(P,)`` current nearest range (e.g. the room hit); centre: ``(3,)`` camera centre;
        rig_radius: largest distance of a ray origin from ``centre``.
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
    v = mids - centre.to(direction)
    dist = v.norm(dim=-1)
    rads = torch.tensor([r for _, r in spheres], dtype=direction.dtype, device=direction.device) + rig_radius + 1e-3
    always = dist <= rads
    cos_thr = torch.sqrt((1 - (rads / dist.clamp_min(1e-9)) ** 2).clamp_min(0.0)) - 1e-4
    cosang = direction @ (v / dist.clamp_min(1e-9)[:, None]).T          # (P, G)
    cand_all = cosang >= cos_thr[None]
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
