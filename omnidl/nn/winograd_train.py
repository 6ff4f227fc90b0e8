"""Winograd F(2x2, 3x3) in training: a stride-1 3x3 convolution and both its gradients on the native kernel.

The forward is :mod:`omnidl.nn.winograd`'s (16 matrix products ``(tiles, C) @ (C, Cout)`` between the transformed
input tiles ``V = B^T d B`` and the transformed filters ``U = G g G^T``, then ``Y = A^T M A``). The backward uses
the same algebra:

* input gradient: the adjoint of a stride-1 3x3 convolution with padding 1 (zero, or a horizontal wrap) is the same
  convolution of the output gradient with each filter turned by 180 degrees and the channel axes swapped, so it is
  the Winograd forward again, on filters packed that way (``omnidl_wino_pack_flip``);
* weight gradient: ``Y = A^T [U (.) V] A`` per tile, so ``dL/dU[xi] = sum over tiles of V[xi]^T M[xi]`` with
  ``M = A gY A^T``, 16 products ``(C, tiles) @ (tiles, Cout)``, and ``dL/dg = G^T dL/dU G``
  (``omnidl_wino_weight_grad``); the bias gradient is the sum of ``gY``.

Each product has 2.25x fewer multiplications than the direct sum; the transforms add and subtract up to 4 terms
each way, so results differ from oneDNN's by a few float32 ulps of the operands' scale. The filters are transformed
on every call (they change every step). Where :func:`applies` does not hold, the caller runs ``F.conv2d``; under
``create_graph`` the backward is autograd's own over ``F.conv2d`` (differentiable again).
"""
from __future__ import annotations

import threading

import torch
import torch.nn.functional as F
from torch import Tensor

from . import native, thin_layout, winograd
from .capture import capturing
from .offsets import _pair
from .sampling import _is_channels_last, weight_channels_last

CL = torch.channels_last
#: ``False`` leaves every layer to oneDNN (benchmarks' in-process A/B)
ENABLED = True
#: the fewest input and output channels taken (32 on 64x128 ran 1.06-1.14x oneDNN's forward + backward)
MIN_CHANNELS = 64
#: the fewest tiles (2x2 outputs, over the batch) taken
MIN_TILES = 64


def applies(x: Tensor, weight: Tensor, stride=1, padding=1, dilation=1, groups: int = 1) -> bool:
    """Whether :func:`conv2d` computes this convolution with autograd: ``padding`` is the padding given to
    ``F.conv2d``, which must be 1 (a :class:`~omnidl.nn.padding.CircularConv2d` with wrap padding 1 passes 1 here
    and ``wrap=1`` to :func:`conv2d`, with the unwrapped map). At most :data:`omnidl.nn.winograd.MAX_CHANNEL_PRODUCT`
    channel pairs, as the inference path."""
    if not (ENABLED and torch.is_grad_enabled() and not torch.is_autocast_enabled("cpu") and x.dim() == 4
            and weight.dim() == 4 and tuple(weight.shape[-2:]) == (3, 3) and groups == 1
            and not isinstance(padding, str) and _pair(stride, "stride") == (1, 1)
            and _pair(dilation, "dilation") == (1, 1) and _pair(padding, "padding") == (1, 1) and x.device.type == "cpu"
            and x.dtype == torch.float32 and weight.dtype == torch.float32 and weight.device.type == "cpu"
            and (x.requires_grad or weight.requires_grad)):
        return False
    C, cout = x.shape[1], weight.shape[0]
    if not (C == weight.shape[1] and MIN_CHANNELS <= min(C, cout) and C * cout <= winograd.MAX_CHANNEL_PRODUCT
            and winograd.tiles(x) >= MIN_TILES and x.shape[-1] >= 2):
        return False
    lib = native.library()
    return lib is not None and lib.omnidl_wino_packed_floats(1, 1) > 0 and not capturing()


def conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, wrap: int) -> Tensor:
    """``F.conv2d(x, weight, bias, padding=1)`` (``wrap=0``) or the same with the columns wrapped horizontally
    (``wrap=1``, :class:`~omnidl.nn.padding.CircularConv2d` with padding 1): ``x (B, C, H, W)``, ``weight (Cout,
    C, 3, 3)`` -> ``(B, Cout, H, W)`` in ``x``'s memory format; differentiable. Where :func:`applies` holds. A bias
    that is not a float32 CPU vector of ``Cout`` values goes to ``F.conv2d``, which gives its own error."""
    if bias is not None and not (bias.dtype == torch.float32 and bias.device.type == "cpu"
                                 and tuple(bias.shape) == (weight.shape[0],)):
        return _reference(x, weight, bias, wrap)
    return _WinogradConv.apply(x, weight, bias, int(wrap))


_local = threading.local()


def _scratch(slot: str, n: int) -> Tensor:
    """``n`` float32 values of memory kept per thread and ``slot`` between calls (grown when too small): a fresh
    buffer of a few MB is page-faulted on every call, which cost as much as the products it feeds."""
    buf = getattr(_local, slot, None)
    if buf is None or buf.numel() < n:
        buf = torch.empty(n, dtype=torch.float32)
        setattr(_local, slot, buf)
    return buf


def _pack(lib, weight: Tensor, flip: bool) -> Tensor:
    """The transformed filters of ``weight`` (``flip``: those of the input gradient) in per-thread scratch memory:
    valid until the next call on this thread."""
    cout, C = weight.shape[:2]
    n = lib.omnidl_wino_packed_floats(cout, C) if flip else lib.omnidl_wino_packed_floats(C, cout)
    up = _scratch("packed", n)
    w = weight.detach().contiguous()
    rc = lib.omnidl_wino_pack_flip(w.data_ptr(), cout, C, int(flip), up.data_ptr(), torch.get_num_threads())
    if rc:
        raise RuntimeError(f"omnidl Winograd convolution: packing the filters returned {rc}")
    return up


def _like(t: Tensor, x: Tensor) -> Tensor:
    """``t`` (channels-last) in the memory format of ``x`` (as ``F.conv2d``: channels-last also for a channel slice
    of such a map; NCHW by :func:`~omnidl.nn.thin_layout.to_nchw`)."""
    return t if _is_channels_last(x) else thin_layout.to_nchw(t)


def _reference(x: Tensor, weight: Tensor, bias: Tensor | None, wrap: int) -> Tensor:
    """The same convolution by ``F.conv2d`` (with autograd: the ``create_graph`` backward)."""
    if wrap:
        return F.conv2d(F.pad(x, (1, 1, 0, 0), mode="circular"), weight, bias, padding=(1, 0))
    return F.conv2d(x, weight, bias, padding=1)


class _WinogradConv(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor | None, wrap: int) -> Tensor:  # type: ignore[override]
        lib = native.library()
        B, C, H, W = x.shape
        cout = weight.shape[0]
        xc = thin_layout.to_nhwc(x)
        out = torch.empty((B, cout, H, W), dtype=x.dtype, memory_format=CL)
        b = None if bias is None else bias.detach().contiguous()
        winograd.forward(lib, xc, wrap, _pack(lib, weight, False), cout, b, out, False, False)
        ctx.save_for_backward(x, weight, bias)    # x as given, as F.conv2d (its channels-last copy is made again)
        ctx.wrap = wrap
        return _like(out, x)

    @staticmethod
    def backward(ctx, gy: Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None, None]:  # type: ignore[override]
        x, weight, bias = ctx.saved_tensors
        need_x, need_w, need_b, _ = ctx.needs_input_grad
        if torch.is_grad_enabled():                 # create_graph: a differentiable backward
            with torch.enable_grad():
                inputs = [t for t, need in ((x, need_x), (weight, need_w), (bias, need_b)) if need]
                y = _reference(x, weight, bias, ctx.wrap)
                grads = iter(torch.autograd.grad(y, inputs, gy, create_graph=True))
            return (next(grads) if need_x else None, next(grads) if need_w else None,
                    next(grads) if need_b else None, None)
        lib = native.library()
        B, C, H, W = x.shape
        cout = weight.shape[0]
        g = thin_layout.to_nhwc(gy)
        gx = gw = gb = None
        if need_x:
            gxc = torch.empty((B, C, H, W), dtype=gy.dtype, memory_format=CL)
            winograd.forward(lib, g, ctx.wrap, _pack(lib, weight, True), C, None, gxc, False, False)
            gx = _like(gxc, x)
        if need_w:
            gw = torch.empty(weight.shape, dtype=weight.dtype)
            block, threads = weight_block(C, cout), torch.get_num_threads()
            work = _scratch("work", lib.omnidl_wino_weight_grad_floats(H, W, C, cout, block, threads))
            xc = thin_layout.to_nhwc(x.detach())
            rc = lib.omnidl_wino_weight_grad(xc.data_ptr(), g.data_ptr(), B, H, W, C, cout, ctx.wrap, gw.data_ptr(),
                                             block, work.data_ptr(), threads)
            if rc:
                raise RuntimeError(f"omnidl Winograd convolution: the weight gradient returned {rc}")
            if weight_channels_last(weight):
                gw = gw.contiguous(memory_format=CL)
        if need_b:
            gb = gy.sum((0, 2, 3))
        return gx, gw, gb, None


def weight_block(C: int, cout: int) -> int:
    """Tiles per chunk of the weight gradient: their 16 transformed input and gradient tiles about 4 MB."""
    return max(32, (1 << 16) // (C + cout))
