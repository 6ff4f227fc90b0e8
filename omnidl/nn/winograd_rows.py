"""Row Winograd F(2, 3) for 3x3 inference convolutions of vertical stride 2 on the native kernel (``csrc/fixed_conv.c``).

HorizonNet's height towers halve the height with 3x3 convolutions of stride ``(2, 1)``: the 2-d F(2x2, 3x3) of
:mod:`omnidl.nn.winograd` needs stride 1 both ways, but along a row the stride is 1, so the 1-d transform applies
there. A tile is 2 adjacent outputs of one row; its 3 input rows' transformed 4-column patches lie side by side, so
the layer becomes 4 matrix products ``(tiles, 3C) @ (3C, Cout)``: 12 multiplications per 2 outputs and channel
pair against 18 for the direct sum (1.5x fewer). The transforms add or subtract 2-3 terms, so results differ from
the direct sum by a few float32 ulps of the operands' scale (well inside 1e-5 relative).

:func:`row_mode` says whether a layer qualifies: ``nn.Conv2d`` with zero padding 1 or
:class:`~omnidl.nn.padding.CircularConv2d` with wrap padding 1; 3x3, stride ``(2, 1)``, no dilation or groups;
:data:`omnidl.nn.winograd.MIN_CHANNELS` or more channels each way; enough tiles in the batch for the weight
(:data:`MIN_TILES`). :func:`pack` transforms and packs a weight once; :func:`forward` runs a layer.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from . import native, winograd

#: the fewest tiles (pairs of outputs) in the batch are ``MIN_TILES + C * Cout // TILES_PER_WEIGHT``: with fewer,
#: the transformed weight (4/3 of the weight) is read for too few products. Measured on 2 threads (AVX-512 host)
#: against oneDNN's folded convolution + ReLU: 1024 -> 1024 channels on 16 tiles 6.2 against 5.8 ms, 2048 -> 1024
#: on 32 tiles 0.83-1.04x over four runs (both not taken: 32 and 48 tiles needed), 2048 -> 1024 on 128 tiles
#: 0.93-0.98x, 512 -> 256 on 8 tiles 0.87x (18 needed: left to oneDNN, a few microseconds).
MIN_TILES = 16
TILES_PER_WEIGHT = 65536
#: ``False`` leaves every layer to oneDNN (benchmarks' in-process A/B)
ENABLED = True


def row_mode(x: Tensor, conv: nn.Module) -> int | None:
    """``1`` (horizontal wrap) or ``0`` (zero padding) where :func:`forward` computes ``conv`` on ``x``
    (channels-last float32 on the CPU), else ``None``."""
    if not (ENABLED and winograd.native_3x3(x, conv, (2, 1))
            and tiles(x) >= MIN_TILES + conv.in_channels * conv.out_channels // TILES_PER_WEIGHT):
        return None
    return winograd.padding_mode(conv)


def out_height(h: int) -> int:
    """Output rows of a stride-2 3x3 convolution with padding 1 on ``h`` rows."""
    return (h - 1) // 2 + 1


def tiles(x: Tensor) -> int:
    """The tiles (2 outputs of one row) of a stride-(2, 1) 3x3 convolution with padding 1 of ``x (B, C, H, W)``."""
    return x.shape[0] * out_height(x.shape[-2]) * ((x.shape[-1] + 1) // 2)


def pack(lib, weight: Tensor) -> Tensor | None:
    """The transformed, packed weight of ``weight (Cout, C, 3, 3)`` for :func:`forward` (``None`` on the BLAS
    build, which has no register kernel)."""
    return winograd.pack(lib, weight, "wino_rows")


def block_tiles(C: int, cout: int) -> int:
    """Tiles per block (:func:`omnidl.nn.winograd.block_tiles` for 4 planes of 3C transformed inputs and of cout
    products per tile)."""
    return winograd.block_tiles(3 * C, cout, planes=4)


def forward(lib, x: Tensor, wrap: int, packed: Tensor, cout: int, bias: Tensor | None, relu: bool) -> Tensor:
    """``[relu](conv(x) + bias)`` for ``x (B, C, H, W)`` channels-last -> ``(B, cout, Ho, W)`` channels-last,
    ``Ho = (H - 1) // 2 + 1``; ``packed`` from :func:`pack`."""
    B, C, H, W = x.shape
    out = torch.empty((B, cout, out_height(H), W), dtype=x.dtype, memory_format=torch.channels_last)
    rc = lib.omnidl_wino_rows_forward(x.data_ptr(), B, H, W, C, 2, int(wrap), packed.data_ptr(), cout,
                                      native.ptr(bias), out.data_ptr(), int(relu),
                                      block_tiles(C, cout), torch.get_num_threads())
    winograd.check(rc, "row Winograd convolution")
    return out
