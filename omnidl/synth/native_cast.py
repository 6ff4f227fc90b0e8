"""The renderer's box slab tests in one native call (``omnidl/nn/csrc/box_slabs.c``).

:func:`omnidl.synth.raycast.cast_boxes` tests each batch of boxes against the rays that may reach it; on tensor ops
that is ~25 calls per batch (gathers, the slab's minima and maxima over ``(rays, boxes)`` arrays, the update of
the nearest hits). Here every batch runs in one loop over its rays with the same float32 operations in the same
order, so ranges and box ids are the tensor path's bit for bit (``tests/synth/test_native_cast.py``).

It runs for float32 CPU tensors with the native library built (:mod:`omnidl.nn.native`); elsewhere (float64,
CUDA, ``OMNIDL_NATIVE=0``) :func:`cast_boxes` keeps its tensor ops.
"""
from __future__ import annotations

import torch
from torch import Tensor

from omnidl.nn import native

#: ``False``: always the tensor ops (benchmarks' in-process A/B, tests)
ENABLED = True


def applies(*tensors: Tensor) -> bool:
    """Whether the native slab tests run for these tensors (float32 on the CPU, library built)."""
    return ENABLED and native.accepts(*tensors)


def _starts(parts: list[Tensor]) -> tuple[Tensor, Tensor]:
    """The concatenation of int64 index lists and the offsets ``(len + 1,)`` where each starts."""
    sizes = torch.tensor([0] + [int(p.numel()) for p in parts], dtype=torch.int64)
    flat = torch.cat([p.reshape(-1).to(torch.int64) for p in parts]) if parts else torch.zeros(0, dtype=torch.int64)
    return flat.contiguous(), sizes.cumsum(0)


def box_table(boxes: Tensor) -> Tensor:
    """``(B, 8)`` rows ``x, y, z, hx, hy, hz, cos yaw, sin yaw`` of scene box rows ``(B, 9)``: the native passes'
    box table. The yaw column is read strided, as ``raycast._box_frames`` reads it (the same cos and sin values)."""
    yaw = boxes[:, 6]
    return torch.cat([boxes[:, :6], torch.cos(yaw)[:, None], torch.sin(yaw)[:, None]], 1).contiguous()


def box_slabs(origin: Tensor, direction: Tensor, boxes: Tensor, groups: list[Tensor], rays: list[Tensor],
              t_best: Tensor, box_id: Tensor) -> None:
    """Update ``t_best (P,)`` and ``box_id (P,)`` in place with the nearest entries of rays ``origin (P or 1, 3)``,
    ``direction (P, 3)`` into ``boxes (B, 9)`` (scene rows): ``groups[k]`` (box indices) against the rays
    ``rays[k]`` (ray indices), batch after batch, as :func:`omnidl.synth.raycast.cast_boxes` does."""
    P = direction.shape[0]
    for name, t, shape in (("origin", origin, (origin.shape[0], 3)), ("direction", direction, (P, 3)),
                           ("boxes", boxes, (boxes.shape[0], 9)), ("t_best", t_best, (P,))):
        if t.dtype != torch.float32 or t.device.type != "cpu" or tuple(t.shape) != shape or \
                (name == "origin" and shape[0] not in (1, P)):
            raise ValueError(f"box_slabs: {name} must be a float32 CPU tensor of shape {shape} (origin: 1 or {P} "
                             f"rows), got {t.dtype} on {t.device} with shape {tuple(t.shape)}")
    if box_id.dtype != torch.int64 or tuple(box_id.shape) != (P,) or not box_id.is_contiguous() or \
            not t_best.is_contiguous():
        raise ValueError(f"box_slabs: t_best and box_id must be contiguous (P,) = ({P},) float32 / int64 tensors, "
                         f"got {t_best.dtype} {tuple(t_best.shape)} and {box_id.dtype} {tuple(box_id.shape)}")
    if len(groups) != len(rays):
        raise ValueError(f"box_slabs: {len(groups)} box groups but {len(rays)} ray lists")
    table = box_table(boxes)
    box_idx, box_start = _starts(groups)
    ray_idx, ray_start = _starts(rays)
    if box_idx.numel() and not (0 <= int(box_idx.min()) and int(box_idx.max()) < len(boxes)):
        raise ValueError(f"box_slabs: box indices must lie in [0, {len(boxes)})")
    if ray_idx.numel() and not (0 <= int(ray_idx.min()) and int(ray_idx.max()) < P):
        raise ValueError(f"box_slabs: ray indices must lie in [0, {P})")
    o = origin.contiguous()
    d = direction.contiguous()
    native.library().omnidl_box_slabs(o.data_ptr(), 0 if o.shape[0] == 1 else 3, d.data_ptr(), table.data_ptr(),
                                      len(groups), box_start.data_ptr(), box_idx.data_ptr(), ray_start.data_ptr(),
                                      ray_idx.data_ptr(), t_best.data_ptr(), box_id.data_ptr(),
                                      max(1, torch.get_num_threads()))
