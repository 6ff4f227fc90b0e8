"""Render a :class:`Scene` through any camera: RGB, range depth, semantics, instances, normals (+ layout).

See ``docs/synth.md`` for the returned dict.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from omnidl.classes import CLASS_ID
from omnidl.geometry.rotations import upright_rotation
from omnidl.ops.surface_shade import PANEL, SurfaceTables, surface_shade
from omnidl.utils.threads import limit_threads

from .layout import layout_ground_truth
from .raycast import cast_boxes, cast_room, column_rays, group_spheres
from .scene import Scene
from .tiles import ray_tiles, tile_batches, tile_mask


_RAY_CACHE: dict = {}


def camera_rays(camera, dtype=torch.float32, device=None):
    """Camera-frame rays of every pixel (cached per camera/dtype/device: cameras are hashable values):
    ``origin (P, 3)``, ``direction (P, 3)``, ``valid (P,)``."""
    o, valid, d_t = _camera_rays(camera, dtype, device)
    return o, d_t.T.contiguous(), valid


def _camera_rays(camera, dtype, device):
    """``origin (P, 3)``, ``valid (P,)`` and the component-major ``direction (3, P)`` (cached)."""
    key = (camera, dtype, str(device))
    rays = _RAY_CACHE.get(key)
    if rays is None:
        r = camera.unproject_grid(dtype=torch.float64, device=device)
        d = r.direction.reshape(-1, 3).to(dtype)
        rays = (r.origin.reshape(-1, 3).to(dtype), r.valid.reshape(-1), d.T.contiguous())
        if len(_RAY_CACHE) > 8:
            _RAY_CACHE.clear()
        _RAY_CACHE[key] = rays
    return rays


def world_rays(camera, pose: np.ndarray, dtype=torch.float32, device=None):
    """Camera rays of every pixel in the world frame: ``origin (P or 1, 3)``, ``direction (P, 3)``, ``valid (P,)``."""
    return _world_rays(camera, pose, dtype, device)[:3]


def _world_rays(camera, pose: np.ndarray, dtype, device):
    """:func:`world_rays` plus the component-major ``origin (3, P or 1)`` and ``direction (3, P)``.

    ``R @ d_c^T`` on component-major rays gives the same bits as ``d_c @ R^T``, several times faster."""
    o_c, valid, d_ct = _camera_rays(camera, dtype, device)
    R = torch.as_tensor(pose[:3, :3], dtype=dtype, device=device)
    t = torch.as_tensor(pose[:3, 3], dtype=dtype, device=device)
    d_t = R @ d_ct
    if getattr(camera, "central", True):
        o = t[None]
    else:
        o = torch.addmm(t[None], o_c, R.T)     # (kept row-major: addmm's rounding depends on the layout)
    return o, d_t.T.contiguous(), valid, o.T, d_t


def _box_groups(boxes: np.ndarray) -> list[Tensor]:
    if len(boxes) == 0:
        return []
    inst = boxes[:, 8].astype(np.int64)
    groups = []
    for i in np.unique(inst):
        groups.append(torch.as_tensor(np.nonzero(inst == i)[0], dtype=torch.int64))
    return groups


def _surface_tables(scene: Scene, dtype, device):
    """Per-surface class, instance, material and (structural) normal tables.

    Surface ids: walls ``0..N-1``, floor ``N``, ceiling ``N+1``, decals ``N+2..N+1+K``, boxes after that.
    """
    n, k = scene.num_walls, len(scene.decals)
    poly = scene.polygon
    e = np.roll(poly, -1, axis=0) - poly
    inward = np.stack([-e[:, 1], e[:, 0], np.zeros(n)], 1) / np.linalg.norm(e, axis=1)[:, None]
    normals = np.concatenate([inward, [[0, 0, 1.0], [0, 0, -1.0]],
                              inward[scene.decals[:, 0].astype(np.int64)] if k else np.zeros((0, 3))])
    sem = np.concatenate([np.full(n, CLASS_ID["wall"]), [CLASS_ID["floor"], CLASS_ID["ceiling"]],
                          scene.decals[:, 5], scene.boxes[:, 7]]).astype(np.int64)
    inst = np.concatenate([np.arange(1, n + 1), [scene.floor_instance, scene.ceiling_instance],
                           scene.decals[:, 6], scene.boxes[:, 8]]).astype(np.int64)
    mat = np.concatenate([scene.wall_material, [scene.floor_material, scene.ceiling_material],
                          scene.decal_material, scene.box_material]).astype(np.int64)
    as_t = lambda x, dt=torch.int64: torch.as_tensor(x, dtype=dt, device=device)  # noqa: E731
    return as_t(sem), as_t(inst), as_t(mat), as_t(normals, dtype)


def render(scene: Scene, camera, pose: np.ndarray, layout: bool = True, dtype: torch.dtype = torch.float32,
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
    o, d, valid, o_t, d_t = _world_rays(camera, pose, dtype, device)
    centre = torch.as_tensor(pose[:3, 3], dtype=dtype, device=device)
    rig = 0.0 if o.shape[0] == 1 or not bool(valid.any()) else \
        float(torch.where(valid, (o - centre).norm(dim=-1), -math.inf).max())

    n = scene.num_walls
    poly = torch.as_tensor(scene.polygon, dtype=dtype, device=device)
    columns = column_rays(o, d, (H, W), (o_t, d_t))
    room = cast_room(o, d, poly, scene.height, grid=(H, W), columns=columns, components=(o_t, d_t))
    boxes = torch.as_tensor(scene.boxes, dtype=dtype, device=device)
    groups = _box_groups(scene.boxes)
    batches, candidates = groups, None
    if groups:
        # objects culled per pixel tile, consecutive objects batched into one slab pass (same result)
        tiles = ray_tiles(camera)
        pose64 = torch.as_tensor(pose, dtype=torch.float64)
        near = tile_mask(tiles, *group_spheres(boxes, groups), pose64[:3, :3], pose64[:3, 3])
        joined = tile_batches(tiles, near, [len(g) for g in groups])
        batches = [torch.cat([groups[i] for i in gs]) for gs, _ in joined]
        candidates = [rays.to(d.device) for _, rays in joined]
    t, box_id = cast_boxes(o, d, boxes, batches, room.t, centre, rig, candidates=candidates)
    hit = valid & torch.isfinite(t)
    t = torch.where(hit, t, torch.zeros_like(t))
    # component-major (3, P) from here on: 3-vector products are several times faster than on (P, 3)
    # rows and give the same bits (the same operations in the same order on each element). Contiguous rows
    # also for non-central rays (o_t is then a transposed view): a BLAS sums the shading's products over a
    # transposed operand in another order
    point = torch.addcmul(o_t, t[None], d_t).contiguous()                      # (3, P)
    R = torch.as_tensor(pose[:3, :3], dtype=dtype, device=device)
    shadow = _shadows(scene, point, hit, boxes, groups) if shadows and len(scene.boxes) else None
    image, sem, inst, normal_cam = surface_shade(point, d_t, hit, box_id, room.kind, room.wall, room.s,
                                                 *_shading_tables(scene, boxes), R, shadow)

    out = {
        "image": image.reshape(3, H, W).to(torch.float32),
        "depth": t.reshape(1, H, W).to(torch.float32),
        "semantic": sem.reshape(H, W),
        "instance": inst.reshape(H, W),
        "normal": normal_cam.reshape(3, H, W).to(torch.float32),
        "valid": hit.reshape(H, W),
    }
    meta = {"camera": camera.to_config(), "manhattan": bool(scene.manhattan), "num_walls": int(n),
            "rig_radius": float(rig), "scene_seed": int(scene.seed)}
    if layout:
        kind_map = (room.kind * hit).reshape(H, W)
        out["layout_seg"] = kind_map
        out.update(layout_ground_truth(scene, camera, pose, kind_map, room.wall.reshape(H, W),
                                       vertical_columns=columns is not None))
        r_up = upright_rotation(torch.as_tensor(pose[:3, :3], dtype=torch.float64))
        out["pose"] = torch.as_tensor(pose, dtype=torch.float32)
        out["rotation"] = torch.as_tensor(r_up, dtype=torch.float32)
        out["horizon_normal"] = torch.as_tensor(pose[:3, :3].T @ np.array([0.0, 0.0, 1.0]), dtype=torch.float32)
        out["camera_height"] = torch.tensor(float(pose[2, 3]), dtype=torch.float32)
        out["ceiling_height"] = torch.tensor(float(scene.height), dtype=torch.float32)
        # the layout ground truth is a few (W,)-wide float64 passes on the CPU (bisections along columns);
        # every map of the sample is on the render's device
        out = {k: v.to(image.device) for k, v in out.items()}
    out["meta"] = meta
    return out


def _shading_tables(scene: Scene, boxes: Tensor) -> SurfaceTables:
    """The scene's operands of :func:`omnidl.ops.surface_shade.surface_shade` in the dtype and on the device of
    ``boxes (B, 9)`` (the scene's box rows); the openings' extents are differences taken in float64."""
    dtype, device = boxes.dtype, boxes.device
    sem_t, inst_t, mat_t, nrm_t = _surface_tables(scene, dtype, device)
    dec = np.asarray(scene.decals, np.float64).reshape(-1, 7)                  # [wall, s0, s1, z0, z1, ...]
    openings = np.stack([dec[:, 1], dec[:, 2], dec[:, 3], dec[:, 4], dec[:, 2] - dec[:, 1], dec[:, 4] - dec[:, 3]], 1)
    m = scene.materials
    panel = np.asarray(m["texture"])[np.asarray(scene.decal_material, np.int64)] == PANEL
    yaw = boxes[:, 6]
    as_t = lambda x, dt=dtype: torch.as_tensor(x, dtype=dt, device=device)  # noqa: E731
    return SurfaceTables(
        n_walls=int(scene.num_walls), openings=as_t(openings), opening_wall=as_t(dec[:, 0]).to(torch.int64),
        opening_panel=as_t(panel, torch.bool),
        boxes=torch.cat([boxes[:, :6], torch.cos(yaw)[:, None], torch.sin(yaw)[:, None]], 1),
        semantic=sem_t, instance=inst_t, material=mat_t, normal=nrm_t.contiguous(),
        colour=as_t(np.concatenate([m["c1"], m["c2"]], 1)), texture=as_t(m["texture"], torch.int64),
        scale=as_t(m["scale"], torch.float64).to(dtype), emissive=as_t(m["emissive"], torch.bool),
        lights=as_t(scene.lights), ambient=float(scene.ambient))


def _shadows(scene: Scene, point: Tensor, hit: Tensor, boxes: Tensor, groups) -> Tensor:
    """``(L, P)`` light factors of the hit points ``point (3, P)``: :func:`_shadow` of each light (1 without a hit)."""
    lp = torch.as_tensor(scene.lights, dtype=point.dtype, device=point.device)[:, :3]
    hits = hit.nonzero()[:, 0]
    p_rows = point.index_select(1, hits).T.contiguous()
    out = torch.ones(len(lp), point.shape[1], dtype=point.dtype, device=point.device)
    for j in range(len(lp)):
        v = lp[j] - p_rows
        dist = v.norm(dim=-1).clamp_min(1e-6)
        out[j].index_copy_(0, hits, _shadow(p_rows, lp[j], v, dist, boxes, groups))
    return out


def _shadow(p: Tensor, lp: Tensor, v: Tensor, dist: Tensor, boxes: Tensor, groups) -> Tensor:
    """1 where the segment from ``p`` to the light is free of boxes, else 0.35 (soft-ish shadow)."""
    # rays from the light towards the points: a central "camera" at the light position
    d = -v / dist[:, None]
    t, bid = cast_boxes(lp[None], d, boxes, groups, dist - 1e-3, lp, 0.0)
    blocked = bid >= 0
    return torch.where(blocked, torch.full_like(dist, 0.35), torch.ones_like(dist))
