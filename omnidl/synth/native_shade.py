"""The renderer's per-pixel surface pass in one native call (``omnidl/nn/csrc/surface_shade.c``).

From the ray-cast hits, :func:`omnidl.synth.render.render` finds each pixel's surface (wall, floor, ceiling,
wall opening, box face), its labels, the normal facing the ray and the shaded colour. On the tensor ops that is
~250 calls over whole images (gathers per surface table, a mask per opening, a pass per texture kind and per
light); here it is one pass per pixel with the same float32 operations in the same order, so labels, surfaces
and texture cells are the tensor path's. The image and the camera-frame normal agree with it to float32
rounding (its products with the lights and with ``R^T`` are matrix products that may sum in another order).

It runs for float32 CPU tensors with the native library built (:mod:`omnidl.nn.native`) and without shadows;
elsewhere (float64, CUDA, ``OMNIDL_NATIVE=0``, ``shadows=True``) the renderer keeps its tensor ops
(``tests/synth/test_native_shade.py`` compares the two).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from omnidl.nn import native

#: ``False``: always the tensor ops (benchmarks' in-process A/B, tests)
ENABLED = True


class SurfaceTables(NamedTuple):
    """The scene's tables as the tensor path reads them (float32 where it casts to float32)."""
    n_walls: int
    openings: Tensor     # (K, 6) float32 rows s0, s1, z0, z1, s1 - s0, z1 - z0 (differences taken in float64)
    opening_wall: Tensor  # (K,) int64 wall of each opening
    opening_panel: Tensor  # (K,) bool: the opening's texture is PANEL (its own [0, 1] coordinates)
    boxes: Tensor        # (B, 8) float32 rows x, y, z, half sizes, cos yaw, sin yaw
    semantic: Tensor     # (S,) int64 per surface
    instance: Tensor     # (S,) int64 per surface
    material: Tensor     # (S,) int64 per surface
    normal: Tensor       # (n_walls + 2 + K, 3) float32 per structural surface (boxes use their faces)
    colour: Tensor       # (M, 6) float32 colour 1 | colour 2 per material
    texture: Tensor      # (M,) int64 texture kind per material
    scale: Tensor        # (M,) float32 texture scale per material
    emissive: Tensor     # (M,) bool per material
    lights: Tensor       # (L, 4) float32 rows x, y, z, power
    ambient: float


def applies(*tensors: Tensor) -> bool:
    """Whether the native pass runs for these tensors (float32 on the CPU, library built)."""
    return ENABLED and native.accepts(*tensors)


def _operand(t: Tensor, dtype: torch.dtype, shape: tuple, name: str) -> Tensor:
    if t.dtype != dtype or t.device.type != "cpu" or tuple(t.shape) != shape:
        raise ValueError(f"surface_shade: {name} must be a {dtype} CPU tensor of shape {shape}, "
                         f"got {t.dtype} on {t.device} with shape {tuple(t.shape)}")
    return t.contiguous()


def surface_shade(point: Tensor, direction: Tensor, hit: Tensor, box_id: Tensor, kind: Tensor, wall: Tensor,
                  wall_s: Tensor, tables: SurfaceTables, R: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per pixel (``point``, ``direction (3, P)`` world, component-major; ``hit (P,)`` bool; ``box_id (P,)`` int64,
    -1 = no box; the room hit's ``kind``, ``wall (P,)`` int64 and ``wall_s (P,)`` metres along the wall):
    ``image (3, P)``, ``semantic (P,)``, ``instance (P,)`` (0 without a hit) and the camera-frame normal
    ``(3, P)`` (``R (3, 3)`` camera-to-world), as the renderer's tensor path computes them."""
    P = hit.shape[0]
    f32, i64 = torch.float32, torch.int64
    ops = [_operand(point, f32, (3, P), "point"), _operand(direction, f32, (3, P), "direction"),
           _operand(hit, torch.bool, (P,), "hit"), _operand(box_id, i64, (P,), "box_id"),
           _operand(kind, i64, (P,), "kind"), _operand(wall, i64, (P,), "wall"), _operand(wall_s, f32, (P,), "wall_s")]
    tb = tables
    K, B, M, L = len(tb.openings), len(tb.boxes), len(tb.colour), len(tb.lights)
    S = tb.n_walls + 2 + K + B          # walls, floor, ceiling, openings, boxes
    openings = [_operand(tb.opening_wall, i64, (K,), "opening_wall"), _operand(tb.openings, f32, (K, 6), "openings"),
                _operand(tb.opening_panel, torch.bool, (K,), "opening_panel"), _operand(tb.boxes, f32, (B, 8), "boxes")]
    surfaces = [_operand(tb.semantic, i64, (S,), "semantic"), _operand(tb.instance, i64, (S,), "instance"),
                _operand(tb.material, i64, (S,), "material"),
                _operand(tb.normal, f32, (tb.n_walls + 2 + K, 3), "normal"),
                _operand(tb.colour, f32, (M, 6), "colour"),
                _operand(tb.texture, i64, (M,), "texture"), _operand(tb.scale, f32, (M,), "scale"),
                _operand(tb.emissive, torch.bool, (M,), "emissive")]
    if S and not (0 <= int(tb.material.min()) and int(tb.material.max()) < M):
        raise ValueError(f"surface_shade: material holds an index outside [0, {M}) (the colour table's rows)")
    lights = _operand(tb.lights, f32, (L, 4), "lights")
    Rm = _operand(R, f32, (3, 3), "R")
    image = torch.empty(3, P, dtype=f32)
    sem = torch.empty(P, dtype=i64)
    inst = torch.empty(P, dtype=i64)
    normal = torch.empty(3, P, dtype=f32)
    status = native.library().omnidl_surface_shade(
        P, *(t.data_ptr() for t in ops), tb.n_walls, K, *(t.data_ptr() for t in openings), B,
        *(t.data_ptr() for t in surfaces), L, lights.data_ptr(), float(tb.ambient), Rm.data_ptr(), image.data_ptr(),
        sem.data_ptr(), inst.data_ptr(), normal.data_ptr(), max(1, torch.get_num_threads()))
    if status:
        raise ValueError(f"surface_shade: box_id holds a box index of {B} or more, or a wall pixel without a box "
                         f"has a wall outside [0, {tb.n_walls})")
    return image, sem, inst, normal
