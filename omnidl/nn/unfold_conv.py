"""Convolution as one matrix product over the unfolded input, for weight-heavy layers on small maps.

On a small deep feature map the weight of a convolution is far larger than its input: FreDSNet's Fourier blocks
run ``1024 -> 1024`` channels, ``3x3``, on a ``4x8`` map, a 37.7 MB weight against 1.2 MB of unfolded input
columns. ``F.conv2d`` on the CPU hands that weight to oneDNN, which re-lays it out on every call (forward and
both backward products) into new buffers; glibc maps each buffer over 32 MB afresh, so every call also
page-faults it. Here the product reads the weight where it lies::

    cols = unfold(x)                      (B, C*kh*kw, L)   L = Ho*Wo output positions
    y    = W (Cout, C*kh*kw) @ cols + b   (B, Cout, L) -> (B, Cout, Ho, Wo)

and autograd's own backward of these ops is the direct one (``gW = g @ cols^T``, ``gcols = W^T @ g`` folded back
into the input, ``gb = sum g``), so second derivatives work too. Measured on 2 threads (forward + backward, one
image): 1024 channels on 4x8 19 ms against 49 ms for ``F.conv2d``, on 8x16 38 against 66 ms; 512 channels on
8x16 7 against 7-12 ms; 256 channels on 16x32, where the map is no longer small, 7.5 against 6.0 ms, hence the
rule of :func:`weight_heavy`.

:func:`conv2d` is ``F.conv2d`` with that choice made; :func:`module_conv2d` is ``conv(x)`` with it, for plain
``nn.Conv2d`` modules (other classes are called as they are: :class:`~omnidl.nn.padding.CircularConv2d` makes
the choice itself).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .offsets import _pair, output_size
from .sampling import _is_channels_last

#: the unfolded product runs where ``out_channels >= WEIGHT_HEAVY_RATIO * B * Ho * Wo`` (the weight at least this
#: many times the unfolded input, which has ``B * Ho * Wo`` columns of the same length as a weight row)
WEIGHT_HEAVY_RATIO = 4
#: ``False`` always calls ``F.conv2d`` (benchmarks' in-process A/B)
ENABLED = True

_Pair = int | tuple[int, int]


def weight_heavy(x: Tensor, weight: Tensor, stride: _Pair = 1, padding: _Pair | str = 0, dilation: _Pair = 1,
                 groups: int = 1) -> bool:
    """Whether :func:`conv2d` takes the unfolded product for these arguments: CPU, float32/float64, 4-d input,
    no groups, numeric padding, and ``out_channels >= WEIGHT_HEAVY_RATIO * B * Ho * Wo``."""
    if not (ENABLED and groups == 1 and not isinstance(padding, str) and x.dim() == 4 and weight.dim() == 4
            and x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64) and weight.dtype == x.dtype):
        return False
    if torch.jit.is_tracing() or torch.jit.is_scripting() or torch.compiler.is_compiling():
        return False
    try:
        ho, wo = output_size(tuple(x.shape[-2:]), tuple(weight.shape[-2:]), _pair(stride, "stride"),
                             _pair(padding, "padding"), _pair(dilation, "dilation"))
    except ValueError:                                    # no output position: F.conv2d gives its own error
        return False
    return weight.shape[0] >= WEIGHT_HEAVY_RATIO * x.shape[0] * ho * wo


def unfold_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None = None, stride: _Pair = 1, padding: _Pair = 0,
                  dilation: _Pair = 1) -> Tensor:
    """``F.conv2d(x, weight, bias, stride, padding, dilation)`` (no groups) as ``weight @ unfold(x)``:
    ``x (B, C, H, W)``, ``weight (Cout, C, kh, kw)`` -> ``(B, Cout, Ho, Wo)``, in ``x``'s memory format."""
    B, C, H, W = x.shape
    cout, _, kh, kw = weight.shape
    stride, padding, dilation = _pair(stride, "stride"), _pair(padding, "padding"), _pair(dilation, "dilation")
    ho, wo = output_size((H, W), (kh, kw), stride, padding, dilation)
    cols = F.unfold(x, (kh, kw), dilation=dilation, padding=padding, stride=stride)        # (B, C*kh*kw, L)
    if weight.is_contiguous(memory_format=torch.channels_last) and not weight.is_contiguous():
        # a channels-last weight is (Cout, kh, kw, C) in memory: a view of it as rows, the columns re-ordered to
        # match (a copy of the small operand, not of the weight)
        w = weight.permute(0, 2, 3, 1).reshape(cout, -1)
        cols = cols.view(B, C, kh * kw, -1).transpose(1, 2).reshape(B, kh * kw * C, -1)
    else:
        w = weight.reshape(cout, -1)
    if B == 1:      # one matrix product (its backward: two, no reduction over a batch)
        y = w @ cols[0] if bias is None else torch.addmm(bias.unsqueeze(1), w, cols[0])
    else:
        y = torch.matmul(w, cols)
        if bias is not None:
            y = y + bias.view(1, cout, 1)
    y = y.view(B, cout, ho, wo)
    if _is_channels_last(x):                               # as F.conv2d: also for a channel slice of such a map
        y = y.contiguous(memory_format=torch.channels_last)
    return y


def conv2d(x: Tensor, weight: Tensor, bias: Tensor | None = None, stride: _Pair = 1, padding: _Pair | str = 0,
           dilation: _Pair = 1, groups: int = 1) -> Tensor:
    """``F.conv2d`` with the same arguments; :func:`unfold_conv2d` where :func:`weight_heavy`."""
    if weight_heavy(x, weight, stride, padding, dilation, groups):
        return unfold_conv2d(x, weight, bias, stride, padding, dilation)  # type: ignore[arg-type]
    return F.conv2d(x, weight, bias, stride, padding, dilation, groups)


def module_conv2d(conv: nn.Module, x: Tensor) -> Tensor:
    """``conv(x)``; for a plain ``nn.Conv2d`` with zero padding and no hooks through :func:`conv2d` (the same
    result)."""
    if type(conv) is nn.Conv2d and conv.padding_mode == "zeros" and not (conv._forward_hooks or conv._forward_pre_hooks):
        return conv2d(x, conv.weight, conv.bias, conv.stride, conv.padding, conv.dilation, conv.groups)
    return conv(x)
