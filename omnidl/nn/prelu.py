"""PReLU whose backward is one pass over the map (``csrc/prelu.c``) in training on the CPU.

``y = x`` where ``x > 0``, else ``a_c x`` (``a`` one slope per channel, or one for all). PyTorch's CPU backward
writes the input's gradient and a second full-size tensor, the slope's gradient per element, which it then
sums; for a ``128 x 128 x 256`` map that is 11.6 ms where the forward takes 0.4 ms (2 threads). Here one pass
reads ``x`` and the output's gradient ``g`` and writes::

    gx = g where x > 0, else a_c g          (B, C, H, W)
    ga = sum of x g over the pixels where x <= 0, per channel (summed over channels for one slope)

the same formulas as PyTorch's, with the sums kept in double. It runs for contiguous and channels-last float32
maps on the CPU with the native library built (:mod:`omnidl.nn.native`; a channels-last map's gradient must come
channels-last too, as the layers after it give it); everything else (other strides, float64, CUDA, ``create_graph``,
tracing and compiling) is PyTorch's own ``F.prelu``, as is the forward. Channels-last maps are the Equi networks'
(their projected convolutions keep the channels-last rows they compute): FreDSNet-Equi's 128-channel map at
128x256 took 35 ms in PyTorch's backward.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from . import native
from .capture import capturing

#: ``False``: always ``F.prelu`` (benchmarks' in-process A/B)
ENABLED = True


def _layout(x: Tensor) -> str | None:
    """``"nchw"`` for a contiguous map, ``"nhwc"`` for a channels-last ``(B, C, H, W)`` one, else ``None``."""
    if x.is_contiguous():
        return "nchw"
    return "nhwc" if x.dim() == 4 and x.is_contiguous(memory_format=torch.channels_last) else None


def _native_backward(x: Tensor, weight: Tensor) -> bool:
    return (ENABLED and x.device.type == "cpu" and x.dtype == torch.float32 and weight.dtype == torch.float32
            and x.dim() >= 2 and _layout(x) is not None and weight.is_contiguous()
            and weight.numel() in (1, x.shape[1]) and x.numel() > 0)


def prelu(x: Tensor, weight: Tensor) -> Tensor:
    """``F.prelu(x, weight)``: ``x (B, C, ...)``, ``weight (C,)`` or ``(1,)``; with the one-pass backward where it
    applies (see the module docstring)."""
    if (torch.is_grad_enabled() and (x.requires_grad or weight.requires_grad) and _native_backward(x, weight)
            and not capturing() and native.library() is not None):
        return _PReLU.apply(x, weight)
    return F.prelu(x, weight)


class _PReLU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor) -> Tensor:   # type: ignore[override]
        ctx.save_for_backward(x, weight)
        return F.prelu(x, weight)

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor | None, Tensor | None]:   # type: ignore[override]
        x, weight = ctx.saved_tensors
        lib = native.library()
        layout = _layout(x)
        if torch.is_grad_enabled() or lib is None or not (_native_backward(x, weight) and _layout(g) == layout):
            return _composite_backward(x, weight, g)       # differentiable (create_graph), any layout and dtype
        B, C = x.shape[0], x.shape[1]
        gx = torch.empty_like(x)                           # x's memory format
        ga = torch.empty(B, C, dtype=torch.float64)
        fn = lib.omnidl_prelu_backward if layout == "nchw" else lib.omnidl_prelu_backward_cl
        fn(x.data_ptr(), g.data_ptr(), weight.data_ptr(), int(weight.numel() > 1), B, C, x[0, 0].numel(),
           gx.data_ptr(), ga.data_ptr(), max(1, torch.get_num_threads()))
        ga = ga.sum(0) if weight.numel() > 1 else ga.sum().reshape(1)
        return gx, ga.to(weight.dtype).view(weight.shape)


def _composite_backward(x: Tensor, weight: Tensor, g: Tensor) -> tuple[Tensor, Tensor]:
    """The same formulas from differentiable tensor operations."""
    a = weight.view(1, -1, *([1] * (x.dim() - 2))) if weight.numel() > 1 else weight.reshape(())
    pos = x > 0
    gx = torch.where(pos, g, a * g)
    ga_full = torch.where(pos, torch.zeros_like(x), x * g)
    ga = ga_full.sum([d for d in range(x.dim()) if d != 1]) if weight.numel() > 1 else ga_full.sum().reshape(1)
    return gx, ga.view(weight.shape)


class PReLU(nn.PReLU):
    """``nn.PReLU`` (same parameters, state dict and forward) with the one-pass backward of :func:`prelu`."""

    def forward(self, x: Tensor) -> Tensor:
        return prelu(x, self.weight)


__all__ = ["PReLU", "prelu"]
