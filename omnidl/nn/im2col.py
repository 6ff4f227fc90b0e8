"""``F.unfold`` (im2col) with its backward ``F.fold`` (col2im) on a native pass (``csrc/unfold.c``).

PyTorch's CPU kernels for these run at 4-6 GB/s on the small deep maps of the weight-heavy layers
(:mod:`omnidl.nn.unfold_conv`): 1024 channels on 4x8, 3x3, 0.19 ms to unfold and 0.30 ms to fold 1.2 MB of
columns; 512 channels on 8x16 0.38 and 0.50 ms (2 threads). A FreDSNet training step at 256x128 unfolds and folds
about 19 maps each. :func:`unfold` is ``F.unfold(x, kernel_size, dilation, padding, stride)`` for a 4-d tensor; a
contiguous float32 CPU map runs natively (the threads split the image's channels; for stride 1 a row of the
columns is one shifted copy of a row of the map), its gradient by the native col2im (or by ``F.fold`` under
``create_graph``, differentiable again). Everything else (float64, channels-last or strided maps, capture by
``torch.compile``/export, the switch) is ``F.unfold``.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from . import native
from .capture import capturing
from .offsets import _pair, output_size

#: ``False``: always ``F.unfold`` (benchmarks' in-process A/B)
ENABLED = True

_Pair = int | tuple[int, int]


def applies(x: Tensor) -> bool:
    """Whether :func:`unfold` runs natively: a contiguous (NCHW) float32 CPU map with at least one value, the
    native library built, not captured."""
    return (ENABLED and x.dim() == 4 and x.dtype == torch.float32 and x.device.type == "cpu" and x.is_contiguous()
            and x.numel() > 0 and not capturing() and native.library() is not None)


def unfold(x: Tensor, kernel_size: _Pair, dilation: _Pair = 1, padding: _Pair = 0, stride: _Pair = 1) -> Tensor:
    """``F.unfold(x, kernel_size, dilation, padding, stride)``: ``x (B, C, H, W)`` -> ``(B, C*kh*kw, Ho*Wo)``."""
    if not applies(x):
        return F.unfold(x, kernel_size, dilation=dilation, padding=padding, stride=stride)
    try:
        k, d, p, s = (_pair(v, name) for v, name in ((kernel_size, "kernel_size"), (dilation, "dilation"),
                                                     (padding, "padding"), (stride, "stride")))
        ho, wo = output_size(tuple(x.shape[-2:]), k, s, p, d)
        valid = min(*k, *d, *s) >= 1 and min(p) >= 0
    except (TypeError, ValueError):
        valid = False
    if not valid:                                           # F.unfold gives its own error
        return F.unfold(x, kernel_size, dilation=dilation, padding=padding, stride=stride)
    return _Unfold.apply(x, (*k, *s, *p, *d, ho, wo))


def _run(name: str, src: Tensor, dst: Tensor, shape: tuple[int, int, int, int], geometry: tuple[int, ...]) -> None:
    rc = getattr(native.library(), name)(src.data_ptr(), *shape, *geometry, dst.data_ptr(),
                                         max(1, torch.get_num_threads()))
    if rc:
        raise RuntimeError(f"omnidl {name}: the native pass returned {rc}")


class _Unfold(torch.autograd.Function):
    """``x (B, C, H, W)`` -> ``cols (B, C*kh*kw, Ho*Wo)``; ``geometry`` = ``(kh, kw, sh, sw, ph, pw, dh, dw, Ho,
    Wo)``."""

    @staticmethod
    def forward(ctx, x: Tensor, geometry: tuple[int, ...]) -> Tensor:   # type: ignore[override]
        B, C, H, W = x.shape
        kh, kw, ho, wo = geometry[0], geometry[1], geometry[8], geometry[9]
        cols = x.new_empty(B, C * kh * kw, ho * wo)
        _run("omnidl_im2col", x, cols, (B, C, H, W), geometry)
        ctx.shape, ctx.geometry = (B, C, H, W), geometry
        return cols

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor, None]:   # type: ignore[override]
        B, C, H, W = ctx.shape
        kh, kw, sh, sw, ph, pw, dh, dw = ctx.geometry[:8]
        if torch.is_grad_enabled() or g.dtype != torch.float32:      # create_graph: differentiable
            return F.fold(g, (H, W), (kh, kw), dilation=(dh, dw), padding=(ph, pw), stride=(sh, sw)), None
        gx = g.new_empty(B, C, H, W)
        _run("omnidl_col2im", g.contiguous(), gx, ctx.shape, ctx.geometry)
        return gx, None
