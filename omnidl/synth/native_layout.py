"""The layout ground truth's maps over the room-class image in one native pass each (``omnidl/nn/csrc/layout_maps.c``).

:func:`omnidl.synth.layout.column_boundaries` brackets each column's ceiling -> wall and wall -> floor transitions
and :func:`omnidl.synth.layout.layout_ground_truth` draws the structural edge map; on tensor ops those are ~25
whole-image passes (comparisons, shifts, a column-wise argmax, rolls). Here each is one pass of integer work, so
the results are the tensor path's exactly (``tests/synth/test_native_layout.py``). It runs for int64 CPU maps with
the native library built (:mod:`omnidl.nn.native`); elsewhere the tensor ops run.
"""
from __future__ import annotations

import torch
from torch import Tensor

from omnidl.nn import native

#: ``False``: always the tensor ops (benchmarks' in-process A/B, tests)
ENABLED = True


def applies(*maps: Tensor) -> bool:
    """Whether the native passes run for these ``(H, W)`` maps (int64 on the CPU, at least 2 rows, library built)."""
    return ENABLED and all(m.dim() == 2 and m.shape[0] >= 2 for m in maps) and native.accepts(*maps, dtype=torch.int64)


def _map(m: Tensor, name: str, shape=None) -> Tensor:
    if m.dtype != torch.int64 or m.device.type != "cpu" or m.dim() != 2 or m.shape[0] < 2 or \
            (shape is not None and tuple(m.shape) != shape):
        raise ValueError(f"layout maps: {name} must be an int64 CPU map of shape {shape or '(H >= 2, W)'}, got "
                         f"{m.dtype} on {m.device} with shape {tuple(m.shape)}")
    return m.contiguous()


def brackets(kind_map: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``i_c, i_f (W,)`` int64 and ``has_c, has_f (W,)`` bool of :func:`omnidl.synth.layout._brackets`."""
    k = _map(kind_map, "kind_map")
    H, W = k.shape
    i_c, i_f = torch.empty(W, dtype=torch.int64), torch.empty(W, dtype=torch.int64)
    has_c, has_f = torch.empty(W, dtype=torch.bool), torch.empty(W, dtype=torch.bool)
    native.library().omnidl_layout_brackets(k.data_ptr(), H, W, i_c.data_ptr(), has_c.data_ptr(), i_f.data_ptr(),
                                            has_f.data_ptr())
    return i_c, i_f, has_c, has_f


def edges(kind_map: Tensor, wall_map: Tensor, wraps: bool) -> Tensor:
    """The ``(H, W)`` float32 edge map of :func:`omnidl.synth.layout._edge_map`."""
    k = _map(kind_map, "kind_map")
    w = _map(wall_map, "wall_map", tuple(k.shape))
    out = torch.empty(k.shape, dtype=torch.float32)
    native.library().omnidl_layout_edges(k.data_ptr(), w.data_ptr(), k.shape[0], k.shape[1], int(bool(wraps)),
                                         out.data_ptr(), max(1, torch.get_num_threads()))
    return out
