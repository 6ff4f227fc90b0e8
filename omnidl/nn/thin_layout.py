"""Thin convolutions on large maps run on channels-last memory in training (oneDNN's own layout for them).

oneDNN's NCHW convolutions work on channels blocked by 16: a layer with fewer than 16 output channels has its
input re-laid out (its channels padded to 16) on the forward and again for the weight's gradient, and its backward
runs on the padded blocks. On channels-last memory oneDNN convolves the map as it lies. For a contiguous float32
map :func:`to_channels_last` writes that memory in one native pass (``csrc/wrap_layout.c``), a horizontal wrap
included where the convolution wraps (:class:`~omnidl.nn.padding.CircularConv2d`), and its backward writes the
gradient back in NCHW; the convolution's output is made contiguous again (it has few channels).

Measured on 2 threads, forward + backward, one image (NCHW against channels-last):

==========================================  ===============  ===============
layer                                       NCHW             channels-last
==========================================  ===============  ===============
128 -> 14, 3x3 wrapped, 128x256 (semantic)  71 ms            52 ms
128 -> 1, 3x3 wrapped, 128x256              55 ms            33 ms
4 -> 4, 3x3 wrapped, 128x256                8.6 ms           3.6 ms
8 -> 8, 3x3, 128x256                        8.0 ms           7.4 ms
16 -> 4, 1x1, 128x256                       7.2 ms           5.2 ms
8 -> 8, 3x3, 32x64 (small map)              0.6 ms           0.8 ms
16 -> 16, 3x3, 64x128 (16 outputs)          2.5 ms           3.2 ms
==========================================  ===============  ===============

hence the rule of :func:`pays`: fewer than 16 output channels on at least :data:`MIN_NUMEL` input elements.
Without autograd (inference) the NCHW paths stay: they have their own border and folding paths. A 1x1 convolution
of stride 1 takes :func:`omnidl.nn.unfold_conv.pointwise`'s product first (16 -> 4 on 128x256: 1.6 ms).
"""
from __future__ import annotations

import torch
from torch import Tensor

from . import native
from .capture import capturing

#: ``False``: always NCHW (benchmarks' in-process A/B)
ENABLED = True
#: the fewest input elements (batch x channels x pixels) for which channels-last pays
MIN_NUMEL = 1 << 17
#: oneDNN's channel block: layers with fewer output channels than this are padded to it in NCHW
BLOCK = 16


def pays(x: Tensor, weight: Tensor) -> bool:
    """Whether a convolution of ``x (B, C, H, W)`` with ``weight (Cout, C/groups, kh, kw)`` runs on channels-last
    memory: autograd recording, fewer than :data:`BLOCK` output channels, at least :data:`MIN_NUMEL` elements of a
    contiguous float32 CPU map, the native library built, not captured by ``torch.compile``/export."""
    return (ENABLED and torch.is_grad_enabled() and x.dim() == 4 and weight.dim() == 4 and weight.shape[0] < BLOCK
            and x.numel() >= MIN_NUMEL and x.is_contiguous() and native_pass(x))


def to_channels_last(x: Tensor, left: int = 0, right: int = 0) -> Tensor:
    """``x (B, C, H, W)`` -> ``(B, C, H, left + W + right)`` in channels-last memory, the last ``left`` columns
    first and the first ``right`` columns last (a horizontal wrap; ``left, right <= W``); differentiable (the
    gradient comes back contiguous). Where :func:`pays` holds."""
    return _ToChannelsLast.apply(x, left, right)


class _ToChannelsLast(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, left: int, right: int) -> Tensor:   # type: ignore[override]
        ctx.left, ctx.right = left, right
        B, C, H, W = x.shape
        out = torch.empty((B, C, H, left + W + right), dtype=x.dtype, memory_format=torch.channels_last)
        _run("omnidl_wrap_to_nhwc", x, out, left, right)
        return out

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor, None, None]:   # type: ignore[override]
        return wrap_adjoint(g, ctx.left, ctx.right), None, None


def wrap_adjoint(g: Tensor, left: int, right: int) -> Tensor:
    """The adjoint of :func:`to_channels_last`: ``g (B, C, H, left + W + right)`` (float32 CPU, any memory format;
    the native library built) -> contiguous ``(B, C, H, W)``, the wrapped strips added onto the columns they came
    from; in one native pass, or by differentiable ops when autograd records (``create_graph``)."""
    if torch.is_grad_enabled():
        return unwrap(g, left, right).contiguous()
    g = g.contiguous(memory_format=torch.channels_last)
    B, C, H, Wp = g.shape
    gx = g.new_empty((B, C, H, Wp - left - right))
    _run("omnidl_wrap_from_nhwc", gx, g, left, right)
    return gx


def to_nchw(t: Tensor) -> Tensor:
    """A channels-last map ``t (B, C, H, W)`` as contiguous (NCHW) memory: ``t.contiguous()``, for a float32 CPU map
    outside autograd with the native library built in one native pass (the wrap's adjoint without a wrap): torch's
    copy in this direction took 7.4 against 1.3 ms for 64 channels on 128x256 (2 threads), the other direction is
    as fast as the native pass. ``t`` itself when already contiguous."""
    if t.is_contiguous():
        return t
    if (t.dim() == 4 and t.is_contiguous(memory_format=torch.channels_last) and native_pass(t)
            and not (torch.is_grad_enabled() and t.requires_grad)):
        out = torch.empty(t.shape, dtype=t.dtype)
        nhwc_into_nchw(t.permute(0, 2, 3, 1), out)
        return out
    return t.contiguous()


def to_nhwc(t: Tensor) -> Tensor:
    """``t (B, C, H, W)`` in channels-last memory: ``t.contiguous(memory_format=torch.channels_last)``, for a
    contiguous float32 CPU map outside autograd with the native library built in one native pass (torch's copy took
    0.44 against 0.035 ms for 128 channels on 32x64, 2 threads). ``t`` itself when already channels-last."""
    if t.is_contiguous(memory_format=torch.channels_last):
        return t
    if (t.dim() == 4 and t.is_contiguous() and native_pass(t) and not (torch.is_grad_enabled() and t.requires_grad)):
        out = torch.empty(t.shape, dtype=t.dtype, memory_format=torch.channels_last)
        _run("omnidl_wrap_to_nhwc", t, out, 0, 0)
        return out
    return t.contiguous(memory_format=torch.channels_last)


def native_pass(*ts: Tensor) -> bool:
    """Whether the native layout pass can read and write these tensors: float32 CPU memory, the native library
    built, not captured by ``torch.compile``/export."""
    return (all(t.dtype == torch.float32 and t.device.type == "cpu" for t in ts) and not capturing()
            and native.library() is not None)


def nhwc_into_nchw(src: Tensor, out: Tensor) -> bool:
    """Writes ``src (B, H, W, C)`` into ``out (B, C, H, W)`` (both contiguous) in one native pass and returns
    ``True``; ``False``, nothing written, where that pass does not run (see :func:`native_pass`)."""
    if not (native_pass(src, out) and src.is_contiguous() and out.is_contiguous()):
        return False
    B, H, W, C = src.shape
    if tuple(out.shape) != (B, C, H, W):
        raise ValueError(f"nhwc_into_nchw: out must be {(B, C, H, W)}, got {tuple(out.shape)}")
    _run("omnidl_wrap_from_nhwc", out, src, 0, 0)
    return True


def unwrap(g: Tensor, left: int, right: int) -> Tensor:
    """The adjoint of the wrap, ``(..., left + W + right)`` -> ``(..., W)``: the middle columns copied once and the
    wrapped strips added onto the columns they came from (differentiable: autograd records the in-place adds on the
    copy). Also the backward of :func:`omnidl.nn.padding.pad_panorama`'s wrap."""
    w = g.shape[-1] - left - right
    gx = g[..., left:left + w].clone()
    if left:
        gx[..., w - left:] += g[..., :left]
    if right:
        gx[..., :right] += g[..., left + w:]
    return gx


def _run(name: str, nchw: Tensor, nhwc: Tensor, left: int, right: int) -> None:
    B, C, H, W = nchw.shape
    src, dst = (nchw, nhwc) if name == "omnidl_wrap_to_nhwc" else (nhwc, nchw)
    rc = getattr(native.library(), name)(src.data_ptr(), B, C, H, W, left, right, dst.data_ptr(),
                                         max(1, torch.get_num_threads()))
    if rc:
        raise RuntimeError(f"omnidl channels-last layout: the native kernel {name} returned {rc}")
