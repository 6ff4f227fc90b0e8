"""The renderer as it was before the issue 17 (item 5) speed work: the test oracle of :func:`omnidl.synth.render`.

Kept verbatim (one module; the helpers that did not change are imported from the live modules) so that tests
can compare every output key of the renderer with it (``tests/synth/test_render_reference.py``); the library does
not call it. Its imports are the only change since it left ``omnidl/synth``.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from omnidl.geometry.rotations import upright_rotation
from omnidl.utils.threads import limit_threads

from omnidl.synth import materials as M
from omnidl.synth.materials import CHECKER, NOISE, PANEL, PLAIN, STRIPES
from omnidl.synth.scene import Scene
# helpers the speed work left unchanged (identical source, and everything they call is unchanged too)
from omnidl.synth.layout import (CORNER_BASE, N_MAX, _ROUNDS, _SUBDIV, corner_visibility,  # noqa: F401
                                 corners_world, plucker)
from omnidl.synth.raycast import _EPS, RoomHit, _walls_2d  # noqa: F401
from omnidl.synth.render import _box_groups, _surface_tables
from omnidl.ops.surface_shade import _hash  # noqa: F401

CEILING, WALL, FLOOR = 1, 2, 3


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


def texture_mix(texture: Tensor, scale: Tensor, su: Tensor, sv: Tensor, kinds: list[int] | None = None) -> Tensor:
    """Blend weight in ``[0, 1]`` between colour1 (0) and colour2 (1) per point.

    ``texture``, ``scale``: per point material fields ``(P,)``; ``su``, ``sv``: surface coordinates
    in metres (horizontal along the surface, and vertical / second axis; ``[0, 1]`` box coordinates
    for ``PANEL``). Each texture kind is evaluated only on its own points.
    """
    w = torch.zeros_like(su)
    for kind in (torch.unique(texture).tolist() if kinds is None else kinds):
        if kind == PLAIN:
            continue
        idx = (texture == kind).nonzero()[:, 0]
        u, v, s = su[idx], sv[idx], scale[idx].clamp_min(1e-3)
        if kind == PANEL:
            val = ((u < 0.08) | (u > 0.92) | (v < 0.06) | (v > 0.94) | ((v > 0.48) & (v < 0.52))).to(su.dtype)
        else:
            iu = torch.floor(u / s).to(torch.int64)
            iv = torch.floor(v / s).to(torch.int64)
            if kind == STRIPES:
                val = torch.remainder(iu, 2).to(su.dtype)
            elif kind == CHECKER:
                val = torch.remainder(iu + iv, 2).to(su.dtype)
            elif kind == NOISE:
                val = _hash(iu, iv).to(su.dtype)
            else:  # PLANKS: rows of staggered planks 4 x scale long with dark seams
                off = _hash(iv, iv + 7).to(su.dtype) * 4 * s
                x = (u + off) / (4 * s)
                col = torch.floor(x)
                seam = (v / s - iv.to(su.dtype) < 0.05) | (x - col < 0.012)
                val = 0.6 * _hash(iv, col.to(torch.int64)).to(su.dtype)
                val = torch.where(seam, torch.ones_like(val), val)
        w[idx] = val
    return w


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


def camera_rays(camera, dtype=torch.float32, device=None):
    """Camera-frame rays of every pixel (no cache: the reference recomputes them)."""
    r = camera.unproject_grid(dtype=torch.float64, device=device)
    return r.origin.reshape(-1, 3).to(dtype), r.direction.reshape(-1, 3).to(dtype), r.valid.reshape(-1)


def world_rays(camera, pose: np.ndarray, dtype=torch.float32, device=None):
    """Camera rays of every pixel in the world frame: ``origin (P or 1, 3)``, ``direction (P, 3)``, ``valid (P,)``."""
    o_c, d_c, valid = camera_rays(camera, dtype, device)
    R = torch.as_tensor(pose[:3, :3], dtype=dtype, device=device)
    t = torch.as_tensor(pose[:3, 3], dtype=dtype, device=device)
    d = d_c @ R.T
    if getattr(camera, "central", True):
        o = t[None]
    else:
        o = torch.addmm(t[None], o_c, R.T)
    return o, d, valid


def render_reference(scene: Scene, camera, pose: np.ndarray, layout: bool = True, dtype: torch.dtype = torch.float32,
           device=None, shadows: bool = False, threads: int | str | None = "auto") -> dict:
    """Ray-cast ``scene`` for ``camera`` at ``pose`` (``(4, 4)`` camera-to-world).

    Returns the sample dict of ``docs/synth.md`` (``image``, ``depth``, ``semantic``, ``instance``,
    ``normal``, ``valid`` and, with ``layout=True``, the layout ground truth). ``meta`` holds
    ``camera``, ``manhattan``, ``num_walls``, ``rig_radius`` and the scene seed. ``shadows`` adds
    box shadows from the point lights (slower). ``threads``: intra-op threads of the render (many small
    ops): ``"auto"`` = the process setting while every thread has a free CPU, 1 when the CPUs are
    oversubscribed (:func:`omnidl.utils.threads.auto_threads`; multi-threaded small ops collapse there);
    an int caps it; ``None`` leaves it. The result does not depend on it.
    """
    with limit_threads(threads):
        return _render(scene, camera, pose, layout, dtype, device, shadows)


def _render(scene: Scene, camera, pose: np.ndarray, layout: bool, dtype: torch.dtype, device, shadows: bool) -> dict:
    pose = np.asarray(pose, np.float64)
    W, H = camera.width, camera.height
    o, d, valid = world_rays(camera, pose, dtype, device)
    centre = torch.as_tensor(pose[:3, 3], dtype=dtype, device=device)
    rig = 0.0 if o.shape[0] == 1 else float((o - centre).norm(dim=-1)[valid].max()) if valid.any() else 0.0

    n, n_dec = scene.num_walls, len(scene.decals)
    poly = torch.as_tensor(scene.polygon, dtype=dtype, device=device)
    room = cast_room(o, d, poly, scene.height, grid=(H, W))
    boxes = torch.as_tensor(scene.boxes, dtype=dtype, device=device)
    groups = _box_groups(scene.boxes)
    t, box_id = cast_boxes(o, d, boxes, groups, room.t, centre, rig)
    hit = valid & torch.isfinite(t)
    t = torch.where(hit, t, torch.zeros_like(t))
    is_box = box_id >= 0
    point = torch.addcmul(o, t[:, None], d)

    # surface id per pixel
    surf = torch.where(room.kind == WALL, room.wall, torch.where(room.kind == FLOOR, n, n + 1))
    tex_u = torch.where(room.kind == WALL, room.s, point[:, 0])
    tex_v = torch.where(room.kind == WALL, point[:, 2], point[:, 1])
    on_wall = (room.kind == WALL) & ~is_box
    if n_dec:
        widx = on_wall.nonzero()[:, 0]
        w_wall, w_s, w_z = room.wall[widx], room.s[widx], point[widx, 2]
        w_surf = surf[widx]
        w_u, w_v = tex_u[widx], tex_v[widx]
        for k, row in enumerate(scene.decals):
            wl, s0, s1, z0, z1 = row[:5]
            m = (w_wall == int(wl)) & (w_s >= s0) & (w_s <= s1) & (w_z >= z0) & (w_z <= z1)
            w_surf = torch.where(m, n + 2 + k, w_surf)
            if scene.materials["texture"][scene.decal_material[k]] == M.PANEL:
                w_u = torch.where(m, (w_s - s0) / (s1 - s0), w_u)
                w_v = torch.where(m, (w_z - z0) / (z1 - z0), w_v)
        surf[widx], tex_u[widx], tex_v[widx] = w_surf, w_u, w_v
    sem_t, inst_t, mat_t, nrm_t = _surface_tables(scene, dtype, device)
    normal = nrm_t[surf]
    bidx = is_box.nonzero()[:, 0]
    if bidx.numel():
        bi = box_id[bidx]
        nb, uvb = box_normals(point[bidx], boxes, bi)
        normal[bidx] = nb
        surf[bidx] = n + 2 + n_dec + bi
        tex_u[bidx] = uvb[:, 0]
        tex_v[bidx] = uvb[:, 1]
    sem, inst, mat = sem_t[surf], inst_t[surf], mat_t[surf]
    # normals face the ray
    flip = (normal * d).sum(-1) > 0
    normal = torch.where(flip[:, None], -normal, normal)
    normal = normal * hit[:, None]

    mats = {k: torch.as_tensor(v, device=device) for k, v in scene.materials.items()}
    image = _shade(scene, mats, mat, tex_u, tex_v, point, normal, hit, dtype, device, boxes, groups, shadows)

    R = torch.as_tensor(pose[:3, :3], dtype=dtype, device=device)
    normal_cam = normal @ R                      # R^T n for row vectors
    sem = sem * hit
    inst = inst * hit
    out = {
        "image": image.T.reshape(3, H, W).to(torch.float32),
        "depth": t.reshape(1, H, W).to(torch.float32),
        "semantic": sem.reshape(H, W),
        "instance": inst.reshape(H, W),
        "normal": normal_cam.T.reshape(3, H, W).to(torch.float32),
        "valid": hit.reshape(H, W),
    }
    meta = {"camera": camera.to_config(), "manhattan": bool(scene.manhattan), "num_walls": int(n),
            "rig_radius": float(rig), "scene_seed": int(scene.seed)}
    if layout:
        kind_map = (room.kind * hit).reshape(H, W)
        out["layout_seg"] = kind_map
        out.update(layout_ground_truth(scene, camera, pose, kind_map, room.wall.reshape(H, W)))
        r_up = upright_rotation(torch.as_tensor(pose[:3, :3], dtype=torch.float64))
        out["pose"] = torch.as_tensor(pose, dtype=torch.float32)
        out["rotation"] = torch.as_tensor(r_up, dtype=torch.float32)
        out["horizon_normal"] = torch.as_tensor(pose[:3, :3].T @ np.array([0.0, 0.0, 1.0]), dtype=torch.float32)
        out["camera_height"] = torch.tensor(float(pose[2, 3]), dtype=torch.float32)
        out["ceiling_height"] = torch.tensor(float(scene.height), dtype=torch.float32)
    out["meta"] = meta
    return out


def _shade(scene: Scene, mats: dict, mat: Tensor, tu: Tensor, tv: Tensor, point: Tensor, normal: Tensor, hit: Tensor,
           dtype, device, boxes: Tensor, groups, shadows: bool) -> Tensor:
    """Lambertian shading ``(P, 3)``: albedo (procedural texture) x (ambient + point lights)."""
    c1 = mats["c1"].to(dtype)[mat]
    c2 = mats["c2"].to(dtype)[mat]
    kinds = sorted(set(np.asarray(scene.materials["texture"]).tolist()))
    w = texture_mix(mats["texture"][mat], mats["scale"].to(dtype)[mat], tu, tv, kinds)[:, None]
    albedo = c1 * (1 - w) + c2 * w
    everything = bool(hit.all())
    hits = slice(None) if everything else hit.nonzero()[:, 0]
    p, n = point[hits], normal[hits]
    lights = torch.as_tensor(scene.lights, dtype=dtype, device=device)             # (L, 4)
    lp, power = lights[:, :3], lights[:, 3]
    # all lights at once: n.(l - p) and |l - p|^2 from (P, L) products
    n_dot_l = n @ lp.T - (n * p).sum(-1, keepdim=True)
    dist2 = ((p * p).sum(-1, keepdim=True) - 2 * p @ lp.T + (lp * lp).sum(-1)).clamp_min(1e-12)
    lam = (n_dot_l * dist2.rsqrt()).clamp_min(0.0)
    contrib = power * lam / (1.0 + 0.25 * dist2)                                    # (P, L)
    if shadows and len(scene.boxes):
        for j in range(len(lp)):
            v = lp[j] - p
            dist = v.norm(dim=-1).clamp_min(1e-6)
            contrib[:, j] *= _shadow(p, lp[j], v, dist, boxes, groups)
    light = scene.ambient + contrib.sum(-1)
    light = 1.25 * light / (1.0 + 0.25 * light)      # soft highlight roll-off
    emissive = mats["emissive"][mat[hits]]
    a = albedo[hits]
    shaded = torch.where(emissive[:, None], a, a * light[:, None]).clamp_(0.0, 1.0)
    if everything:
        return shaded
    colour = torch.zeros_like(albedo)
    colour[hits] = shaded
    return colour


def _shadow(p: Tensor, lp: Tensor, v: Tensor, dist: Tensor, boxes: Tensor, groups) -> Tensor:
    """1 where the segment from ``p`` to the light is free of boxes, else 0.35 (soft-ish shadow)."""
    # rays from the light towards the points: a central "camera" at the light position
    d = -v / dist[:, None]
    t, bid = cast_boxes(lp[None], d, boxes, groups, dist - 1e-3, lp, 0.0)
    blocked = bid >= 0
    return torch.where(blocked, torch.full_like(dist, 0.35), torch.ones_like(dist))
