"""Convolution as one matrix product over the unfolded input, for weight-heavy layers on small maps.

On a small deep feature map the weight of a convolution is far larger than its input: FreDSNet's Fourier blocks
run ``1024 -> 1024`` channels, ``3x3``, on a ``4x8`` map, a 37.7 MB weight against 1.2 MB of unfolded input
columns. ``F.conv2d`` on the CPU hands that weight to oneDNN, which re-lays it out on every call (forward and
both backward products) into new buffers; glibc maps each buffer over 32 MB afresh, so every call also
page-faults it. Here the product reads the weight where it lies::

    cols = unfold(x)                      (B, C*kh*kw, L)   L = Ho*Wo output positions
    y    = W (Cout, C*kh*kw) @ cols + b   (B, Cout, L) -> (B, Cout, Ho, Wo)

with a batch as one product, the images' columns side by side. Its backward is the direct one (``gW = g @
cols^T`` over all images at once, ``gcols = W^T @ g`` folded back into the input, ``gb = sum g``), differentiable
again under ``create_graph``. A weight gradient that large is above glibc's largest mmap threshold (32 MB), so
fresh memory for it is mapped and page-faulted on every backward (13 ms for 37.7 MB on 2 cores, twice the product
itself): the memory is kept per weight and handed out again once nothing else holds it (:func:`_grad_buffer`).
Measured on 2 threads (forward + backward, one image): 1024 channels on 4x8 19 ms against 49 ms for ``F.conv2d``,
on 8x16 38 against 66 ms; 512 channels on 8x16 7 against 7-12 ms; 256 channels on 16x32, where the map is no
longer small, 7.5 against 6.0 ms, hence the rule of :func:`weight_heavy`. Two images of 1024 channels on 4x8:
28-30 ms, against 37-48 ms for a broadcast product per image and 70 ms for ``F.conv2d``.

In training, 1x1 convolutions on small or thin maps take the same product (:func:`pointwise`: their columns are
the input itself, and the product skips oneDNN's NCHW re-layouts).

:func:`conv2d` is ``F.conv2d`` with that choice made; :func:`module_conv2d` is ``conv(x)`` with it, for plain
``nn.Conv2d`` modules (other classes are called as they are: :class:`~omnidl.nn.padding.CircularConv2d` makes
the choice itself).
"""
from __future__ import annotations

import functools
import threading
import weakref

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from . import im2col, native, thin_layout, winograd_train
from .capture import capturing
from .offsets import _pair, output_size
from .sampling import _is_channels_last, weight_channels_last

#: the unfolded product runs where ``out_channels >= WEIGHT_HEAVY_RATIO * B * Ho * Wo`` (the weight at least this
#: many times the unfolded input, which has ``B * Ho * Wo`` columns of the same length as a weight row)
WEIGHT_HEAVY_RATIO = 4
#: ``False`` always calls ``F.conv2d`` (benchmarks' in-process A/B)
ENABLED = True
#: ``False``: 1x1 convolutions take the product only where weight-heavy (benchmarks' in-process A/B of
#: :func:`pointwise`)
POINTWISE = True
#: a 1x1 convolution in training takes the product on at most this many positions (batch x output pixels), or
#: on any number when it has at most POINTWISE_THIN input or output channels. Forward + backward on 2 threads
#: against ``F.conv2d`` (oneDNN): 1024 -> 256 channels on 8x16 3.7 against 5.5-6.1 ms, 512 -> 128 on 16x32 4.2-4.7
#: against 4.8-5.2 ms, 256 -> 64 on 32x64 4.6-5.2 against 5.2-6.1 ms; 16 -> 4 on 128x256 1.6 against 3.9 ms,
#: 128 -> 4 15 against 21 ms; but 64 -> 256 on 64x128 14.8 against 13.1 ms, 128 -> 128 on 128x256 level.
POINTWISE_MAX_POSITIONS = 2048
POINTWISE_THIN = 16
#: ``False``: every weight gradient in fresh memory (benchmarks' in-process A/B of :func:`_grad_buffer`)
REUSE_GRAD_BUFFERS = True
#: ``False``: every product on PyTorch's BLAS (benchmarks' in-process A/B of :func:`_product`)
NATIVE_PRODUCTS = True
#: the register kernel runs products of at least this many rows (the threads split them in 12-row slivers) and
#: columns (a packed panel is 32 wide); measured on the backward of a 1x1 convolution from 4 channels, a 4-row
#: product ran on one thread and a 4-column one on an eighth of the vector lanes, 3-8x slower than the BLAS
NATIVE_MIN_ROWS, NATIVE_MIN_COLUMNS = 32, 16
#: a product whose first operand is the weight (the forward's ``W @ cols``, the input gradient's ``W^T @ g``) on
#: this many columns (a small map: 2x4 positions for a 128x64 input to ResNet-50) runs on the few-column kernel
#: (``omnidl_gemm_narrow``, ``csrc/narrow_gemm.c``): bound by reading the weight, it loads each element once and
#: multiplies it into every column from registers, where the register kernel's 32-column panels run mostly on zero
#: lanes and the BLAS's product from a transposed weight on 2-11 columns runs as a slow strided loop. 2 threads, an
#: AMD host, 1024 -> 1024 channels 3x3 (37.7 MB) on 2 / 8 columns: ``W^T g`` 1.6 / 1.9 ms against 4.6 (register
#: kernel) and 17 / 16 ms (MKL), ``W c`` 1.1 / 1.9 ms against 4.2 and 5.7 / 5.6 ms; on one column 1.5 and 0.75 ms
#: against MKL's matrix-vector products' 1.3 and 1.6 ms.
NATIVE_WEIGHT_COLUMNS = range(1, 12)
#: a weight's transpose (the input gradient's ``W^T @ g``) takes the few-column kernel on this many columns: from 12
#: it runs the columns in groups of 11 over chunks of the weight's rows, each chunk read again from L2, where the
#: register kernel copies the weight and runs its 32-column panels partly on zero lanes (1024 -> 1024 channels 3x3
#: on 12 / 16 / 24 columns: 2.4 / 2.6 / 3.6 ms against 4.6 / 6.0 / 5.8 ms; level from 28 to 32)
NATIVE_WEIGHT_T_COLUMNS = range(1, 25)
#: a product that is not a weight's (the weight gradient ``g @ cols^T``, a sum over the positions) runs on the
#: register kernel only while that sum is shorter than this; longer ones run on the BLAS, which was faster on every
#: such product of FreDSNet's training step (2 threads, an AMD host, timed inside the step at 64x128, 128x256 and
#: 256x512): 64 rows, 2048 positions, 256 columns 0.58 against 0.91 ms; 128 rows, 8192 positions, 16 columns 0.31
#: against 0.69 ms; 128 rows, 2048 positions, 512 columns 1.85 against 2.64 ms. Sums over 128 positions (a 1024- or
#: 512-channel layer's on 8x16) stay, 1.3-1.5x faster than the BLAS's
NATIVE_MAX_GRADIENT_SUM = 2048
_HAS_USE_COUNT = hasattr(torch._C, "_storage_Use_Count")

_Pair = int | tuple[int, int]


def weight_heavy(x: Tensor, weight: Tensor, stride: _Pair = 1, padding: _Pair | str = 0, dilation: _Pair = 1,
                 groups: int = 1) -> bool:
    """Whether :func:`conv2d` takes the unfolded product for these arguments: CPU, float32/float64, 4-d input,
    no groups, numeric padding, no autocast (its products would run in the autocast dtype and its backward
    would meet them with the float32 weight), and ``out_channels >= WEIGHT_HEAVY_RATIO * B * Ho * Wo``."""
    if not (ENABLED and groups == 1 and not isinstance(padding, str) and x.dim() == 4 and weight.dim() == 4
            and x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64) and weight.dtype == x.dtype
            and not torch.is_autocast_enabled("cpu")):
        return False
    if capturing():
        return False
    try:
        ho, wo = output_size(tuple(x.shape[-2:]), tuple(weight.shape[-2:]), _pair(stride, "stride"),
                             _pair(padding, "padding"), _pair(dilation, "dilation"))
    except ValueError:                                    # no output position: F.conv2d gives its own error
        return False
    return weight.shape[0] >= WEIGHT_HEAVY_RATIO * x.shape[0] * ho * wo


def pointwise(x: Tensor, weight: Tensor, stride: _Pair = 1, padding: _Pair | str = 0, groups: int = 1) -> bool:
    """Whether :func:`conv2d` takes the product for a 1x1 convolution in training: stride 1, no padding, no groups,
    a float32/float64 CPU map of at most :data:`POINTWISE_MAX_POSITIONS` positions (batch x pixels) or with at
    most :data:`POINTWISE_THIN` input or output channels, autograd recording, no autocast. Its columns are the input
    itself (a view), so the product skips oneDNN's re-layouts of the input, the weight, the output and each gradient
    in NCHW."""
    if not (ENABLED and POINTWISE and groups == 1 and weight.dim() == 4 and tuple(weight.shape[-2:]) == (1, 1)
            and x.dim() == 4 and torch.is_grad_enabled() and _pair(stride, "stride") == (1, 1)
            and not isinstance(padding, str) and _pair(padding, "padding") == (0, 0)):
        return False
    return (x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64) and weight.dtype == x.dtype
            and not torch.is_autocast_enabled("cpu")
            and (x.shape[0] * x.shape[2] * x.shape[3] <= POINTWISE_MAX_POSITIONS
                 or min(weight.shape[0], weight.shape[1]) <= POINTWISE_THIN) and not capturing())


def unfold_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None = None, stride: _Pair = 1, padding: _Pair = 0,
                  dilation: _Pair = 1) -> Tensor:
    """``F.conv2d(x, weight, bias, stride, padding, dilation)`` (no groups) as ``weight @ unfold(x)``:
    ``x (B, C, H, W)``, ``weight (Cout, C, kh, kw)`` -> ``(B, Cout, Ho, Wo)``, in ``x``'s memory format."""
    B, C, H, W = x.shape
    cout, _, kh, kw = weight.shape
    stride, padding, dilation = _pair(stride, "stride"), _pair(padding, "padding"), _pair(dilation, "dilation")
    ho, wo = output_size((H, W), (kh, kw), stride, padding, dilation)
    if (kh, kw) == (1, 1) and padding == (0, 0):
        # a 1x1 convolution's columns are its (strided) pixels: a view for stride 1 and a contiguous x
        cols = (x if stride == (1, 1) else x[:, :, ::stride[0], ::stride[1]]).reshape(B, C, ho * wo)
    else:
        cols = im2col.unfold(x, (kh, kw), dilation, padding, stride)                        # (B, C*kh*kw, L)
    if weight_channels_last(weight):
        # a channels-last weight is (Cout, kh, kw, C) in memory: a view of it as rows, the columns re-ordered to
        # match (a copy of the small operand, not of the weight)
        cols = cols.view(B, C, kh * kw, -1).transpose(1, 2).reshape(B, kh * kw * C, -1)
    y = _Product.apply(weight, cols, bias).contiguous().view(B, cout, ho, wo)
    if _is_channels_last(x):                               # as F.conv2d: also for a channel slice of such a map
        y = y.contiguous(memory_format=torch.channels_last)
    return y


def _rows(weight: Tensor) -> Tensor:
    """``weight (Cout, C, kh, kw)`` as the matrix ``(Cout, K)`` whose rows lie in memory as the weight's: a view
    (``K`` runs over ``(C, kh, kw)``, or over ``(kh, kw, C)`` for a channels-last weight)."""
    if weight_channels_last(weight):
        return weight.permute(0, 2, 3, 1).reshape(weight.shape[0], -1)
    return weight.reshape(weight.shape[0], -1)


_buffers: dict[int, tuple[weakref.ref, torch.UntypedStorage]] = {}
_buffers_lock = threading.Lock()


def _forget(key: int, ref: weakref.ref) -> None:
    """The weight of ``_buffers[key]`` is gone: let its memory go (a dictionary pop, atomic without the lock)."""
    if _buffers.get(key, (None,))[0] is ref:
        _buffers.pop(key, None)


def _grad_buffer(weight: Tensor) -> Tensor:
    """An uninitialised tensor with ``weight``'s shape and strides for its gradient, on memory kept per weight.

    A weight-heavy layer's gradient (37.7 MB for FreDSNet's 1024-channel 3x3 convolutions) is above glibc's
    largest mmap threshold (32 MB), so a fresh one is mapped and page-faulted on every backward (about 13 ms
    each on 2 cores, twice its matrix product). The memory is kept here and handed out again once nothing
    else holds it (``optimizer.zero_grad()`` has dropped ``.grad``); while anything does (a kept ``.grad``, a
    reference held by the user), a new one is made, so no gradient handed out is ever overwritten.
    """
    key = id(weight)
    with _buffers_lock:
        entry = _buffers.get(key)
        if entry is not None and entry[0]() is weight and torch._C._storage_Use_Count(entry[1]._cdata) == 1:
            storage = entry[1]
        else:
            storage = torch.empty_strided(weight.shape, weight.stride(), dtype=weight.dtype).untyped_storage()
            _buffers[key] = (weakref.ref(weight, functools.partial(_forget, key)), storage)
        return weight.new_empty(0).set_(storage, 0, weight.shape, weight.stride())


def _side_by_side(t: Tensor) -> Tensor:
    """``(B, R, L)`` -> ``(R, B*L)``, the images' columns side by side (a view for ``B = 1``)."""
    return t[0] if t.shape[0] == 1 else t.transpose(0, 1).reshape(t.shape[1], -1)


def _product(a: Tensor, b: Tensor, out: Tensor | None = None, bias: Tensor | None = None,
             weight: bool = False) -> Tensor:
    """``a (m, k) @ b (k, n)`` plus ``bias (m,)`` per row when given, into ``out (m, n)`` when given; ``weight``:
    ``a`` is a weight or its transpose (:data:`NATIVE_WEIGHT_COLUMNS`).

    Float32 products that build no autograd graph run on omnidl's register kernel (``omnidl_gemm`` of
    ``csrc/fixed_conv.c``, :mod:`omnidl.nn.native`; a weight's products on :data:`NATIVE_WEIGHT_COLUMNS`, or
    its transpose's on :data:`NATIVE_WEIGHT_T_COLUMNS`, on ``omnidl_gemm_narrow``), which reads ``a`` where it lies
    when it is a weight and copies it block by block first when it is a weight's transpose, and splits its rows
    among the threads. These
    products have few columns (one per output position, 32 for a ``4x8`` map), where the BLAS runs well below its
    peak: for ``1024 -> 1024`` channels on ``4x8`` (2 threads, an AMD host) the forward took 3.4 against 4.9 ms,
    the input gradient's ``W^T g`` 3.1 against 6.6 ms, the weight gradient 4.3 against 5.7 ms. Everything else
    (float64, ``create_graph``, no native library or a build without the register kernel, a product that is not a
    weight's over a sum of :data:`NATIVE_MAX_GRADIENT_SUM` or more) is PyTorch's product. Sums run in another order
    than the BLAS's: the results agree to float32 rounding.
    """
    narrow = weight and b.shape[1] in (NATIVE_WEIGHT_T_COLUMNS if a.stride(0) == 1 and a.stride(1) > 1
                                       else NATIVE_WEIGHT_COLUMNS)
    lib = (native.library() if NATIVE_PRODUCTS and a.dtype == b.dtype == torch.float32 and a.shape[1]
           and a.shape[0] >= NATIVE_MIN_ROWS and not torch.is_grad_enabled()
           and (b.shape[1] >= NATIVE_MIN_COLUMNS or narrow) and (weight or a.shape[1] < NATIVE_MAX_GRADIENT_SUM)
           else None)
    if lib is not None and (out is None or out.stride(1) == 1):
        (m, k), n = a.shape, b.shape[1]
        c = a.new_empty(m, n) if out is None else out
        if bias is not None:
            c.copy_(bias.unsqueeze(1).expand(m, n))
        args = (m, n, k, a.data_ptr(), a.stride(0), a.stride(1), b.data_ptr(), b.stride(0), b.stride(1),
                c.data_ptr(), c.stride(0), int(bias is not None), max(1, torch.get_num_threads()))
        rc = lib.omnidl_gemm_narrow(*args) if narrow else 2                    # a weight's few columns
        if rc == 2:
            rc = lib.omnidl_gemm(*args)
        if rc == 0:
            return c
        if rc == 1:
            raise MemoryError("omnidl unfolded convolution: the native kernel could not allocate its buffers")
    if out is None:
        return a @ b if bias is None else torch.addmm(bias.unsqueeze(1), a, b)
    return torch.mm(a, b, out=out) if bias is None else torch.addmm(bias.unsqueeze(1), a, b, out=out)


class _Product(torch.autograd.Function):
    """``rows(weight) @ cols + bias`` as one matrix product over the batch: ``cols (B, K, L)`` -> ``(B, Cout, L)``
    (a view; for ``B > 1`` the columns of all images are put side by side, a copy of the small operand).

    The backward is the direct one (``gW = g @ cols^T`` over all images at once, no per-image products summed),
    differentiable under ``create_graph``; without it, a leaf weight's gradient is written into
    :func:`_grad_buffer` memory, in the weight's own layout (so autograd keeps it as ``.grad`` without a copy)."""

    @staticmethod
    def forward(ctx, weight: Tensor, cols: Tensor, bias: Tensor | None) -> Tensor:  # type: ignore[override]
        B, _, L = cols.shape
        ctx.save_for_backward(weight, cols)       # inputs, not the side-by-side copy: differentiable again
        ctx.has_bias = bias is not None
        w, c = _rows(weight), _side_by_side(cols)
        y = _product(w, c, bias=bias, weight=True)
        return y.unsqueeze(0) if B == 1 else y.view(-1, B, L).transpose(0, 1)

    @staticmethod
    def backward(ctx, gy: Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None]:  # type: ignore[override]
        weight, cols = ctx.saved_tensors
        need_w, need_cols, need_b = ctx.needs_input_grad
        B, cout, L = gy.shape
        g = _side_by_side(gy)
        gcols = None
        if need_cols:
            gc = _product(_rows(weight).t(), g, weight=True)                              # (K, B*L)
            gcols = gc.unsqueeze(0) if B == 1 else gc.view(-1, B, L).transpose(0, 1)
        gw = None
        if need_w:
            if torch.is_grad_enabled() or not (REUSE_GRAD_BUFFERS and weight.is_leaf and _HAS_USE_COUNT):
                gw = _product(g, _side_by_side(cols).t())  # differentiable under create_graph; shaped as the weight
                gw = (gw.view(cout, weight.shape[2], weight.shape[3], weight.shape[1]).permute(0, 3, 1, 2)
                      if weight_channels_last(weight) else gw.view(weight.shape))
            else:
                gw = _grad_buffer(weight)
                _product(g, _side_by_side(cols).t(), out=_rows(gw))
        gb = g.sum(1) if need_b and ctx.has_bias else None
        return gw, gcols, gb


def conv2d(x: Tensor, weight: Tensor, bias: Tensor | None = None, stride: _Pair = 1, padding: _Pair | str = 0,
           dilation: _Pair = 1, groups: int = 1) -> Tensor:
    """``F.conv2d`` with the same arguments; :func:`unfold_conv2d` where :func:`weight_heavy` or :func:`pointwise`,
    :func:`omnidl.nn.winograd_train.conv2d` where that :func:`~omnidl.nn.winograd_train.applies`, on channels-last
    memory where :func:`omnidl.nn.thin_layout.pays`."""
    if weight_heavy(x, weight, stride, padding, dilation, groups) or pointwise(x, weight, stride, padding, groups):
        return unfold_conv2d(x, weight, bias, stride, padding, dilation)  # type: ignore[arg-type]
    if winograd_train.applies(x, weight, stride, padding, dilation, groups):   # a 3x3 layer in training
        return winograd_train.conv2d(x, weight, bias, wrap=0)
    if thin_layout.pays(x, weight):                 # few output channels on a large map: channels-last memory
        return F.conv2d(thin_layout.to_channels_last(x), weight, bias, stride, padding, dilation, groups).contiguous()
    return F.conv2d(x, weight, bias, stride, padding, dilation, groups)


def module_conv2d(conv: nn.Module, x: Tensor) -> Tensor:
    """``conv(x)``; for a plain ``nn.Conv2d`` with zero padding and no hooks through :func:`conv2d` (the same
    result)."""
    if type(conv) is nn.Conv2d and conv.padding_mode == "zeros" and not (conv._forward_hooks or conv._forward_pre_hooks):
        return conv2d(x, conv.weight, conv.bias, conv.stride, conv.padding, conv.dilation, conv.groups)
    return conv(x)
