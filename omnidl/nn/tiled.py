"""Fixed-offset convolution as a dense strided convolution of its gathered taps (portable CPU float32 path).

:class:`~omnidl.nn.ProjectedConv2d` takes this path where the native kernel of :mod:`.fused` is unavailable (no C
compiler, ``OMNIDL_NATIVE=0``) and under ``torch.compile``/``torch.export``, which trace its torch ops.

The taps of ``r`` whole output rows are gathered into a channels-last *tile* ``(1, C, r*kh, Wo*kw)``
whose pixel ``(oy*kh + i, ox*kw + j)`` holds tap ``(i, j)`` of output ``(oy, ox)``. The layer's weight
convolved over that tile with kernel ``(kh, kw)`` and stride ``(kh, kw)`` is exactly the fixed-offset
convolution of those rows. It computes the same sums as the column GEMM of :mod:`.sampling`, but runs on
oneDNN's direct convolution kernels, which are faster here than the BLAS GEMM of a (positions, K*C) column
matrix (see ``benchmarks/projected_conv.py``); only the summation order differs (float32 rounding).

Backward: the input gradient is a transposed convolution of each chunk's output gradient into the tile layout,
scattered back through the chunk's CSR transpose of the tiled plan; the weight gradient is the column GEMM on
recomputed columns. Nothing but the input is kept between forward and backward.

Threads: as the column path, the (image, tile) tasks are split among single-threaded workers, one join per
call (measured here as fast as intra-op threads inside each tile's ops, or faster: 64 channels 128x256
forward 30-33 vs 37-39 ms on 2 threads, and far steadier when another process competes for the cores).
"""
from __future__ import annotations

import torch
from torch import Tensor

from .sampling import (SamplingPlan, _FixedOffsetConv, _gather, _is_channels_last, _rows, _run_split,
                       chunk_positions, finish_backward, new_accumulators, save_columns_context)

#: target size (bytes) of one gathered tile: oneDNN's stride-k convolution ran fastest with tiles of a few
#: MB here (1-row tiles of 64 channels were 35 % slower, 16-row tiles of 64 channels 35 % slower)
TILE_BYTES = 3_000_000
#: the same for the backward's tiles (transposed convolution of the output gradient)
BWD_TILE_BYTES = 5_000_000
#: a tile holds at least this many times the weight's bytes (see :func:`tile_rows`)
WEIGHT_TILES = 8
#: ``"tiles"`` (input gradient by a transposed convolution into the tile layout) or ``"columns"`` (the column
#: path's backward); measured alike at 64 channels, tiles 5-7 % faster at 256
BACKWARD = "tiles"


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


def tile_rows(plan: SamplingPlan, channels: int, element_size: int, target: int | None = None,
              weight_numel: int = 0) -> int:
    """Output rows per tile so that one tile is about ``max(target, WEIGHT_TILES * weight bytes)`` bytes
    (``target`` default :data:`TILE_BYTES`): oneDNN re-lays the weight out on every call, so wide layers
    (256 channels: a 2.4 MB weight) need taller tiles to amortise it."""
    row = plan.taps * plan.out_hw[1] * channels * element_size
    want = max(TILE_BYTES if target is None else target, WEIGHT_TILES * weight_numel * element_size)
    return max(1, min(plan.out_hw[0], want // max(1, row)))


def _tile(tp: SamplingPlan, xb: Tensor, s: int, e: int) -> Tensor:
    """Channels-last tile ``(1, C, r*kh, Wo*kw)`` of output positions ``[s, e)`` (whole rows) of ``xb (H*W, C)``."""
    kh, kw = tp.kernel_size
    Wo = tp.out_hw[1]
    C = xb.shape[1]
    return _gather(tp, xb, s, e).view(1, (e - s) // Wo * kh, Wo * kw, C).permute(0, 3, 1, 2)


class _TiledConv(_FixedOffsetConv):
    """Forward by tiles. Backward: :data:`BACKWARD` (the column GEMM of the weight gradient ran 2x faster here
    than oneDNN's stride-k weight gradient, so both modes keep it)."""

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
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        result = torch.empty(B, Cout, Ho, Wo, dtype=x.dtype, device=x.device, memory_format=fmt)

        def work(part: list) -> None:
            for b, s, e in part:
                y = torch.nn.functional.conv2d(_tile(tp, xr[b], s, e), w, b_, stride=(kh, kw))
                result[b, :, s // Wo:e // Wo].copy_(y[0])
        P, n = Ho * Wo, rows * Wo  # the forward needs no chunk transposes: plain position ranges
        _run_split([(b, s, min(P, s + n)) for b in range(B) for s in range(0, P, n)], work, x.device)
        save_columns_context(ctx, x, weight, bias, plan, chunk_positions(plan, C, x.element_size()), xr)
        ctx.weight = w
        ctx.bwd_rows = tile_rows(plan, C, x.element_size(), BWD_TILE_BYTES, weight.numel())
        return result

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        if BACKWARD == "columns":
            return _FixedOffsetConv.backward.__wrapped__(ctx, grad_out)  # type: ignore[attr-defined]
        plan: SamplingPlan = ctx.plan
        tp = tiled_plan(plan)
        xr, _ = ctx.saved_tensors
        w = ctx.weight
        B, C = ctx.in_shape[:2]
        Cout = w.shape[0]
        kh, kw = plan.kernel_size
        Wo = plan.out_hw[1]
        need_x, need_w = ctx.needs_input_grad[0], ctx.needs_input_grad[1]

        def work(part: list) -> tuple[Tensor | None, Tensor | None]:
            gx, gwm = new_accumulators(ctx, Cout, grad_out)
            for b, s, e, lo, hi, st in part:
                gy = grad_out[b:b + 1, :, s // Wo:e // Wo].contiguous(memory_format=torch.channels_last)
                if need_w:  # columns in (position, tap) order against the (P_c, Cout) gradient rows
                    gwm.addmm_(_gather(plan, xr[b], s, e).t(), gy[0].permute(1, 2, 0).reshape(e - s, Cout))
                if need_x:  # tile gradient (transposed convolution), scattered through the tiled transpose
                    gt = torch.nn.functional.conv_transpose2d(gy, w, stride=(kh, kw))
                    gx[b, lo:hi].addmm_(st, gt[0].permute(1, 2, 0).reshape(-1, C))
            return gx, gwm

        return finish_backward(ctx, grad_out,
                               _run_split([(b, *c) for b in range(B) for c in tp.chunks(ctx.bwd_rows * Wo)], work,
                                          grad_out.device))


def tiled_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan, rows: int | None = None) -> Tensor:
    """Fixed-offset convolution of ``x (B, C, H, W)`` (CPU) by tiles of ``rows`` output rows (default:
    :func:`tile_rows`); same contract and output memory format as :func:`.sampling.fixed_offset_conv2d`."""
    if rows is None:
        rows = tile_rows(plan, x.shape[1], x.element_size(), weight_numel=weight.numel())
    return _TiledConv.apply(x, weight, bias, plan, int(rows))


def tiled_supported(x: Tensor, weight: Tensor) -> bool:
    """True where the tiled path runs on oneDNN kernels: CPU float32 input and weight."""
    return (x.device.type == "cpu" and x.dtype == torch.float32 and weight.dtype == torch.float32
            and torch.backends.mkldnn.is_available())
