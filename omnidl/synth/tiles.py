"""Pixel tiles with bounding cones: object culling for a whole tile of camera rays at once.

A tile is a ``th x tw`` block of pixels. Its rays (camera frame) leave origins within ``rho`` of
``centre`` in directions within ``spread`` radians of ``axis``. A ray of the tile can only reach a
sphere ``(c, r)`` if ``c`` lies in the cone of half-angle ``spread + asin((r + rho) / |c - centre|)``
about ``axis`` from ``centre`` (or ``centre`` is within ``r + rho`` of ``c``): the rays of the tiles that
pass this test are a superset of the rays that hit the object, which is all
:func:`omnidl.synth.raycast.cast_boxes` needs to give the same result as testing every ray.
The tiles depend only on the camera and are cached; per frame only the sphere centres move.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

_MARGIN_RAD = 1e-4   # angular slack for float32 world rays vs the float64 tile cones
_MARGIN_M = 1e-3     # metres of slack on every sphere radius


class RayTiles(NamedTuple):
    rays: Tensor     # (T, n) int64 pixel indices (row-major image order) of each tile
    axis: Tensor     # (T, 3) float64 unit mean direction, camera frame
    spread: Tensor   # (T,) float64 largest angle between axis and a ray of the tile (+ margin)
    centre: Tensor   # (T, 3) float64 mean ray origin, camera frame
    rho: Tensor      # (T,) float64 largest distance of a ray origin from centre (+ margin)
    always: Tensor   # (T,) bool: test every ray of the tile (invalid rays, or a cone wider than 1 rad)


_TILES: dict = {}


def _side(n: int, target: int) -> int:
    """The largest divisor of ``n`` not above ``target``."""
    return max(k for k in range(1, min(n, target) + 1) if n % k == 0)


def ray_tiles(camera, target: int | None = None) -> RayTiles:
    """The tiles of ``camera``'s pixel grid (cached per camera). ``target``: tile side in pixels (default:
    1/64 of the image width, at least 8: the fastest of 4-32 px at 256 and 1024 wide), shrunk to divide
    the image size."""
    key = (camera, target)
    tiles = _TILES.get(key)
    if tiles is not None:
        return tiles
    W, H = camera.width, camera.height
    side = target or max(8, W // 64)
    th, tw = _side(H, side), _side(W, side)
    r = camera.unproject_grid(dtype=torch.float64)

    def blocks(x: Tensor) -> Tensor:          # (H, W, ...) -> (T, th * tw, ...)
        x = x.reshape(H // th, th, W // tw, tw, *x.shape[2:]).transpose(1, 2)
        return x.reshape((H // th) * (W // tw), th * tw, *x.shape[4:])

    rays = blocks(torch.arange(H * W).reshape(H, W))
    o, d, ok = blocks(r.origin), blocks(r.direction), blocks(r.valid)
    mean = d.sum(1)
    norm = mean.norm(dim=-1)
    axis = mean / norm.clamp_min(1e-12)[:, None]
    cos = ((d * axis[:, None]).sum(-1) / d.norm(dim=-1).clamp_min(1e-12)).clamp(-1.0, 1.0)
    spread = torch.acos(cos.amin(1)) + _MARGIN_RAD
    centre = o.mean(1)
    rho = (o - centre[:, None]).norm(dim=-1).amax(1) + _MARGIN_M
    always = ~ok.all(1) | (norm < 1e-6 * th * tw) | (spread > 1.0)
    tiles = RayTiles(rays, axis, spread, centre, rho, always)
    if len(_TILES) > 8:
        _TILES.clear()
    _TILES[key] = tiles
    return tiles


def tile_mask(tiles: RayTiles, mids: Tensor, radius: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """``(G, T)`` bool: the tiles whose rays may reach each sphere (world centres ``mids (G, 3)``,
    ``radius (G,)``) for the pose ``R (3, 3)``, ``t (3,)`` (camera-to-world, float64)."""
    c = (mids.to(torch.float64) - t) @ R                              # (G, 3) camera frame
    w = c[:, None, :] - tiles.centre[None]                            # (G, T, 3)
    dist = w.norm(dim=-1)
    reach = radius.to(torch.float64)[:, None] + tiles.rho[None] + _MARGIN_M
    cos_w = (w * tiles.axis[None]).sum(-1) / dist.clamp_min(1e-12)
    angle = torch.acos(cos_w.clamp(-1.0, 1.0))
    cone = torch.asin((reach / dist.clamp_min(1e-12)).clamp(max=1.0)) + tiles.spread[None] + _MARGIN_RAD
    return (dist <= reach) | (angle <= cone) | tiles.always[None]


def tile_candidates(tiles: RayTiles, mids: Tensor, radius: Tensor, R: Tensor, t: Tensor) -> list[Tensor]:
    """Per sphere (see :func:`tile_mask`), the ray indices ``(K_g,)`` of the tiles that may reach it."""
    near = tile_mask(tiles, mids, radius, R, t)
    counts = near.sum(1).tolist()
    which = near.nonzero()[:, 1]
    return [tiles.rays[ix].reshape(-1) for ix in which.split(counts)]


def tile_batches(tiles: RayTiles, near: Tensor, sizes: list[int], slack: int = 4096) -> list[tuple[list[int], Tensor]]:
    """Consecutive groups (``near (G, T)`` from :func:`tile_mask`, ``sizes``: boxes per group) joined into
    batches that are slab-tested in one pass: the rays of the union of their tiles against all their boxes.

    A group joins the open batch while that costs at most ``slack`` more (ray, box) tests than testing
    it on its own (one pass over a few thousand pairs costs about as much as the fixed cost of a pass).
    Only consecutive groups are joined, so the first-group-wins order of ties is kept. Returns
    ``(group indices, ray indices)`` per batch.
    """
    m = near.numpy()
    n = tiles.rays.shape[1]
    batches: list[tuple[list[int], np.ndarray]] = []
    cur, mask, boxes, cost = [], None, 0, 0
    for g in range(len(sizes)):
        own = int(m[g].sum()) * n * sizes[g]
        if cur:
            union = mask | m[g]
            joined = int(union.sum()) * n * (boxes + sizes[g])
            if joined <= cost + own + slack:
                cur.append(g)
                mask, boxes, cost = union, boxes + sizes[g], joined
                continue
            batches.append((cur, mask))
        cur, mask, boxes, cost = [g], m[g], sizes[g], own
    if cur:
        batches.append((cur, mask))
    return [(gs, tiles.rays[torch.from_numpy(np.nonzero(mk)[0])].reshape(-1)) for gs, mk in batches]
