"""Winograd F(2x2, 3x3) for stride-1 3x3 inference convolutions on the native kernel (``csrc/fixed_conv.c``).

Each 2x2 block of outputs is ``A^T [U (.) V] A`` with ``V = B^T d B`` from its 4x4 input patch and ``U = G g G^T``
from the filter, so a 3x3 convolution becomes 16 matrix products ``(tiles, C) @ (C, Cout)``: 2.25x fewer
multiplications than the direct sum. The products run on omnidl's register kernel, per block of tiles whose
transformed inputs and products stay in the core's cache; the transforms add and subtract up to 4 terms each way,
so results differ from the direct sum by a few float32 ulps of the operands' scale (well inside 1e-5 relative).
Measured on 2 threads (AVX-512 host), against the folded, prepacked oneDNN convolution + ReLU of
:mod:`omnidl.nn.inference`: 64 channels on 64x128 1.15 against 1.72 ms, 128 on 32x64 0.9 against 1.6 ms, 256 on
16x32 0.93 against 1.52 ms, 512 on 8x16 1.37 against 1.58 ms; at 128x256, 64 channels 4.7 against 5.9 ms.

:func:`wrap_mode` says whether a layer qualifies: ``nn.Conv2d`` with zero padding 1 or
:class:`~omnidl.nn.padding.CircularConv2d` with wrap padding 1; 3x3, stride 1, no dilation or groups; 32 to 512
channels each way; and at least ``max(C, Cout) / 4 + 16`` tiles (2x2 outputs) in the batch. On fewer tiles the 16
transformed weights (1.8x the weight) are read for too few products: 512 channels on 4x8 took 2.2 against 0.87 ms,
256 on 8x16 0.76 against 0.58 ms, where 256 on 16x32 took 0.93 against 1.52 ms.
:func:`pack` transforms and packs a weight once; :func:`forward` runs a layer.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from . import fused, native

#: the largest ``in_channels * out_channels`` taken (the transformed weight is 16 / 9 of the weight's size)
MAX_CHANNEL_PRODUCT = 512 * 512
#: the fewest input and output channels taken: with fewer the transforms outweigh the saved products (16 channels
#: on 64x128 ran 1.22x oneDNN's time)
MIN_CHANNELS = 32
#: ``False`` leaves every layer to oneDNN (benchmarks' in-process A/B)
ENABLED = True


def wrap_mode(x: Tensor, conv: nn.Module, any_layout: bool = False) -> int | None:
    """``1`` (horizontal wrap) or ``0`` (zero padding) where :func:`forward` computes ``conv`` on ``x``
    (channels-last float32 on the CPU; ``any_layout``: on ``x`` once copied into channels-last memory), else
    ``None``."""
    if not (ENABLED and native_3x3(x, conv, (1, 1), any_layout)
            and conv.in_channels * conv.out_channels <= MAX_CHANNEL_PRODUCT
            and tiles(x) >= max(conv.in_channels, conv.out_channels) // 4 + 16):
        return None
    return padding_mode(conv)


def native_3x3(x: Tensor, conv: nn.Module, stride: tuple[int, int], any_layout: bool = False) -> bool:
    """What the native Winograd kernels (this module's and :mod:`omnidl.nn.winograd_rows`) share: the native paths
    on, a 3x3 ``conv`` of ``stride`` without dilation or groups, :data:`MIN_CHANNELS` or more channels each way,
    and ``x`` a 4-d channels-last (or, with ``any_layout``, any) float32 CPU map of 2 or more columns."""
    return (fused.ENABLED and conv.kernel_size == (3, 3) and conv.stride == stride and conv.dilation == (1, 1)
            and conv.groups == 1 and x.dim() == 4 and MIN_CHANNELS <= min(conv.in_channels, conv.out_channels)
            and x.dtype == torch.float32 and x.device.type == "cpu"
            and (any_layout or x.is_contiguous(memory_format=torch.channels_last)) and x.shape[-1] >= 2)


def padding_mode(conv: nn.Module) -> int | None:
    """``1`` for a :class:`~omnidl.nn.padding.CircularConv2d` with wrap padding 1, ``0`` for an ``nn.Conv2d``
    with zero padding 1, else ``None`` (the paddings the native Winograd kernels take)."""
    from .padding import CircularConv2d   # here: padding imports unfold_conv, which imports winograd_train and this
    if type(conv) is CircularConv2d:
        return 1 if tuple(conv.wrap_padding) == (1, 1) else None
    if type(conv) is nn.Conv2d:
        return 0 if tuple(conv.padding) == (1, 1) and conv.padding_mode == "zeros" else None
    return None


def tiles(x: Tensor) -> int:
    """The 2x2 output tiles of a stride-1 3x3 convolution with padding 1 of ``x (B, C, H, W)``, over the batch."""
    return x.shape[0] * ((x.shape[-2] + 1) // 2) * ((x.shape[-1] + 1) // 2)


def pack(lib, weight: Tensor, kind: str = "wino") -> Tensor | None:
    """The transformed, packed weight of ``weight (Cout, C, 3, 3)`` for :func:`forward` (``kind="wino_rows"``: for
    :func:`omnidl.nn.winograd_rows.forward`); ``None`` on the BLAS build, which has no register kernel."""
    cout, C = weight.shape[:2]
    n = getattr(lib, f"omnidl_{kind}_packed_floats")(C, cout)
    if n == 0:
        return None
    w = weight.detach().contiguous()
    up = torch.empty(n, dtype=torch.float32)
    rc = getattr(lib, f"omnidl_{kind}_pack")(w.data_ptr(), cout, C, up.data_ptr(), torch.get_num_threads())
    if rc == 1:
        check(rc)
    return up if rc == 0 else None


def block_tiles(C: int, cout: int, planes: int = 16) -> int:
    """Tiles per block: their transformed inputs and products (``planes`` of each, C and cout floats per tile)
    about :data:`omnidl.nn.fused.BLOCK_BYTES`, a multiple of :data:`omnidl.nn.fused.TILE_ROWS`, at least 24."""
    t = fused.TILE_ROWS
    return max(24, fused.BLOCK_BYTES // (4 * planes * (C + cout)) // t * t)


def check(rc: int, what: str = "Winograd convolution") -> None:
    """Raises for a native Winograd kernel's return code: 1 out of memory, any other but 0 an error."""
    if rc == 1:
        raise MemoryError(f"omnidl {what}: the native kernel could not allocate its buffers")
    if rc:
        raise RuntimeError(f"omnidl {what}: the native kernel returned {rc}")


def forward(lib, x: Tensor, wrap: int, packed: Tensor, cout: int, bias: Tensor | None, out: Tensor,
            accumulate: bool, relu: bool) -> Tensor:
    """``out = [relu](conv(x) + bias [+ out])`` for ``x (B, C, H, W)`` and ``out (B, cout, H, W)``, both
    channels-last; ``packed`` from :func:`pack`."""
    B, C, H, W = x.shape
    rc = lib.omnidl_wino_forward(x.data_ptr(), B, H, W, C, int(wrap), packed.data_ptr(), cout,
                                 native.ptr(bias), out.data_ptr(), int(accumulate),
                                 int(relu), block_tiles(C, cout), torch.get_num_threads())
    check(rc)
    return out
