"""Weight-heavy fixed-offset convolutions in training: the plan's columns, then the unfolded product.

A layer whose weight dwarfs its input (FreDSNet's 1024 -> 1024 channel 3x3 Fourier-block convolutions on an 8x16
map: 37.7 MB of weight against 4.7 MB of taps) spends its training step moving the weight, not multiplying. The
fused kernel (:mod:`.fused`) packs the weight into panels twice per step (``Wm``, then ``Wm^T``), accumulates the
weight gradient in fresh ``(kh*kw*C, Cout)`` zeros and then lays it out as the weight: passes over freshly mapped
weight-sized memory, which page faults make slow. Here the taps of every position are gathered once into rows
``A (B, P, kh*kw*C)`` (:func:`omnidl_fc_gather`, the fused kernel's gather) and the rest is the standard path's product
(:class:`omnidl.nn.unfold_conv._Product`): the weight read where it lies, the weight gradient written into kept
memory in the weight's own layout; the backward scatters the columns' gradient back onto the input
(:func:`omnidl_fc_scatter`, threads split by channels). Measured for 1024 -> 1024 channels, 3x3 on 8x16,
channels-last, forward + backward (2 threads, an AMD host): 159-184 ms fused, 52-53 ms here (and 52-55 ms
for the same layer as a plain convolution on the standard path); see :data:`RATIO` for where it pays.

The columns' order is the weight's: taps then channels for a channels-last weight (``A`` itself, transposed as a
view), channels then taps for a contiguous one (one copy of the small operand, as :func:`~omnidl.nn.unfold_conv.
unfold_conv2d` re-orders its columns for a channels-last weight).
"""
from __future__ import annotations

import torch
from torch import Tensor

from . import native
from .fused import _call
from .sampling import SamplingPlan, _is_channels_last, _rows, rows_as_map, weight_channels_last
from .unfold_conv import _Product

#: ``False``: weight-heavy layers take the fused kernel in training too (benchmarks' in-process A/B)
ENABLED = True
#: the columns run where ``Cout >= RATIO * B * Ho * Wo``. Measured (forward + backward, 3x3, 2 threads, an AMD host,
#: channels-last and NCHW; columns / fused): 1024 channels on 8x16 (ratio 8) 0.32-0.42x, 512 on 8x16 (4)
#: 0.48-0.60x, 1024 on 16x32 (2) 0.67-0.75x, 512 on 16x32 (1) 0.98-1.11x, 256 on 16x32 (0.5) 1.23-1.26x, 256 on
#: 32x64 1.60x
RATIO = 2


def pays(x: Tensor, weight: Tensor, plan: SamplingPlan) -> bool:
    """Whether :func:`columns_conv2d` runs: enabled, autograd recording a weight that needs its gradient, and
    ``Cout >= RATIO * B * Ho * Wo`` (the weight at least ``RATIO`` times the columns, as
    :func:`omnidl.nn.unfold_conv.weight_heavy`'s rule); the operands as :func:`omnidl.nn.fused.fused_supported`
    requires (checked by the caller)."""
    return (ENABLED and torch.is_grad_enabled() and weight.requires_grad
            and weight.shape[0] >= RATIO * x.shape[0] * plan.out_hw[0] * plan.out_hw[1])


def columns_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan) -> Tensor:
    """Fixed-offset convolution of ``x (B, C, H, W)`` (CPU float32) as ``rows(weight) @ columns``: same result as
    :func:`omnidl.nn.fused.fused_conv2d` to float32 rounding, ``(B, Cout, Ho, Wo)`` in ``x``'s memory format."""
    B, C = x.shape[:2]
    Cout = weight.shape[0]
    Ho, Wo = plan.out_hw
    P, K = Ho * Wo, plan.taps
    A = _Columns.apply(x, plan)                                           # (B, P, K*C), taps then channels
    if weight_channels_last(weight):
        cols = A.transpose(1, 2)                                          # (B, K*C, P): a view
    else:
        cols = A.view(B, P, K, C).permute(0, 3, 2, 1).reshape(B, C * K, P)   # channels then taps: a copy
    y = _Product.apply(weight, cols, bias).contiguous().view(B, Cout, Ho, Wo)
    return y.contiguous(memory_format=torch.channels_last) if _is_channels_last(x) else y


class _Columns(torch.autograd.Function):
    """``x (B, C, H, W)`` -> the plan's taps as rows ``(B, P, K*C)``; backward: their scatter (the adjoint)."""

    @staticmethod
    def forward(ctx, x: Tensor, plan: SamplingPlan) -> Tensor:  # type: ignore[override]
        B, C, H, W = x.shape
        P = plan.out_hw[0] * plan.out_hw[1]
        xr = _rows(x)
        A = torch.empty(B, P, plan.taps * C, dtype=x.dtype)
        _call(native.library().omnidl_fc_gather(xr.data_ptr(), H * W * C, C, plan.idx.data_ptr(),
                                                plan.weight.data_ptr(), plan.taps, P, B, A.data_ptr(),
                                                torch.get_num_threads()), "gather")
        ctx.plan, ctx.in_shape, ctx.channels_last = plan, (B, C, H, W), _is_channels_last(x)
        return A

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gA: Tensor):  # type: ignore[override]
        plan: SamplingPlan = ctx.plan
        B, C, H, W = ctx.in_shape
        gA = gA.contiguous()
        gx = torch.zeros(B, H * W, C, dtype=gA.dtype)
        _call(native.library().omnidl_fc_scatter(gx.data_ptr(), H * W * C, C, plan.idx.data_ptr(),
                                                 plan.weight.data_ptr(), plan.taps, plan.out_hw[0] * plan.out_hw[1],
                                                 B, gA.data_ptr(), torch.get_num_threads()), "scatter")
        return rows_as_map(gx, ctx.in_shape, ctx.channels_last), None
