"""Fixed-offset convolution as a dense strided convolution of its gathered taps (CPU float32 path).

The taps of ``r`` whole output rows are gathered into a channels-last *tile* ``(1, C, r*kh, Wo*kw)``
whose pixel ``(oy*kh + i, ox*kw + j)`` holds tap ``(i, j)`` of output ``(oy, ox)``. The layer's weight
convolved over that tile with kernel ``(kh, kw)`` and stride ``(kh, kw)`` is exactly the fixed-offset
convolution of those rows. It computes the same sums as the column GEMM of :mod:`.sampling`, but runs on
oneDNN's direct convolution kernels, which are faster here than the BLAS GEMM of a (positions, K*C) column
matrix (see ``benchmarks/projected_conv.py``); only the summation order differs (float32 rounding).

Backward is the column path's (GEMMs on recomputed columns): nothing but the input is kept.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .sampling import (SamplingPlan, _FixedOffsetConv, _gather, _is_channels_last, _rows, _run_split, chunk_positions,
                       save_columns_context)

#: target size (bytes) of one gathered tile: oneDNN's stride-k convolution ran fastest with tiles of a few
#: MB here (1-row tiles of 64 channels were 35 % slower, 16-row tiles of 64 channels 35 % slower)
TILE_BYTES = 3_000_000


def tiled_plan(plan: SamplingPlan) -> SamplingPlan:
    """``plan`` with its rows reordered ``(oy, i, ox, j)`` (the tile layout), cached on the plan.

    Rows of one output row stay within that row, so chunks of whole output rows touch the same input
    pixels as in ``plan``; the chunk transposes of the tiled plan are built lazily as for any plan.
    """
    hit = plan.derived.get("tiled")
    if hit is None:
        Ho, Wo = plan.out_hw
        kh, kw = plan.kernel_size

        def reorder(t: Tensor) -> Tensor:
            return t.view(Ho, Wo, kh, kw, 4).permute(0, 2, 1, 3, 4).reshape(-1, 4).contiguous()
        hit = plan.derived.setdefault("tiled", SamplingPlan(plan.in_hw, plan.out_hw, plan.kernel_size,
                                                            reorder(plan.idx), reorder(plan.weight)))
    return hit


def tile_rows(plan: SamplingPlan, channels: int, element_size: int) -> int:
    """Output rows per tile so that one tile is about :data:`TILE_BYTES`."""
    row = plan.taps * plan.out_hw[1] * channels * element_size
    return max(1, min(plan.out_hw[0], TILE_BYTES // max(1, row)))


def _tile(tp: SamplingPlan, xb: Tensor, s: int, e: int) -> Tensor:
    """Channels-last tile ``(1, C, r*kh, Wo*kw)`` of output positions ``[s, e)`` (whole rows) of ``xb (H*W, C)``."""
    kh, kw = tp.kernel_size
    Wo = tp.out_hw[1]
    C = xb.shape[1]
    return _gather(tp, xb, s, e).view(1, (e - s) // Wo * kh, Wo * kw, C).permute(0, 3, 1, 2)


class _TiledConv(_FixedOffsetConv):
    """Forward by tiles; backward inherited from the column path (its weight gradient GEMM ran 2x faster here
    than oneDNN's stride-k weight gradient, and its input gradient within 15 % of the transposed convolution)."""

    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan,  # type: ignore[override]
                rows: int) -> Tensor:
        B, C, H, W = x.shape
        Cout = weight.shape[0]
        Ho, Wo = plan.out_hw
        kh, kw = plan.kernel_size
        tp = tiled_plan(plan)
        channels_last = _is_channels_last(x)
        xr = _rows(x)
        w = weight.detach()
        b_ = None if bias is None else bias.detach()
        tasks = [(b, s, e) for b in range(B) for s, e, *_ in tp.chunks(rows * Wo)]
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        result = torch.empty(B, Cout, Ho, Wo, dtype=x.dtype, device=x.device, memory_format=fmt)

        def work(part: list) -> None:
            for b, s, e in part:
                y = torch.nn.functional.conv2d(_tile(tp, xr[b], s, e), w, b_, stride=(kh, kw))
                result[b, :, s // Wo:e // Wo].copy_(y[0])
        _run_split(tasks, work, x.device)
        save_columns_context(ctx, x, weight, bias, plan, chunk_positions(plan, C, x.element_size()), xr)
        return result


def tiled_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan, rows: int | None = None) -> Tensor:
    """Fixed-offset convolution of ``x (B, C, H, W)`` (CPU) by tiles of ``rows`` output rows (default:
    :func:`tile_rows`); same contract and output memory format as :func:`.sampling.fixed_offset_conv2d`."""
    if rows is None:
        rows = tile_rows(plan, x.shape[1], x.element_size())
    return _TiledConv.apply(x, weight, bias, plan, int(rows))


def tiled_supported(x: Tensor, weight: Tensor) -> bool:
    """True where the tiled path runs on oneDNN kernels: CPU float32 input and weight."""
    return (x.device.type == "cpu" and x.dtype == torch.float32 and weight.dtype == torch.float32
            and torch.backends.mkldnn.is_available())
