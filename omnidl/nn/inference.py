"""Inference-time convolution blocks: ``act(BN(conv(x)) + residual)`` on oneDNN with a folded, prepacked weight.

``conv_bn_act(x, conv, bn, act, residual)`` is what a Conv–BatchNorm–(residual sum)–ReLU block computes. In
eval mode without autograd, on CPU float32 (:func:`inference_ready`):

* BatchNorm's running statistics are folded into the convolution (:func:`fold_batchnorm`);
* the folded weight is reordered once into oneDNN's blocked layout (``torch.ops.mkldnn._reorder_convolution_weight``)
  and kept until a parameter or a running statistic changes (the key is the storage and ``_version`` of each
  parameter and buffer, and ``num_batches_tracked``, which a training forward bumps; an edit through ``.data``
  bypasses versions: call :func:`clear_cache` after one);
* the convolution, bias and ReLU run as one ``torch.ops.mkldnn._convolution_pointwise`` call (with a residual, the sum
  and the ReLU are one more in-place pass: oneDNN's fused sum ran slower);
* a dense 1x1 convolution over a residual the caller no longer needs (``into_residual``) runs on omnidl's native
  kernel instead, written over the residual with the sum and the ReLU applied per block in the cache: no new
  output buffer (at 1024x512 a ResNet's layer-1 outputs are 33 MB, which glibc maps and page-faults afresh);
* 3x3 layers of stride 1 run Winograd F(2x2, 3x3) (:mod:`omnidl.nn.winograd`), those of stride ``(2, 1)`` (HorizonNet's
  height towers) the row Winograd F(2, 3) (:mod:`omnidl.nn.winograd_rows`) on the native kernel, where they pay.

``F.conv2d`` hands oneDNN the weight in PyTorch's layout, and oneDNN re-lays it out on every call; on the
weight-heavy layers of a ResNet at panorama sizes that costs more than the arithmetic (2 threads: a 75 MB
``2048 -> 1024`` 3x3 weight on a 16x32 map, 83 ms through ``F.conv2d`` + ReLU against 51 ms prepacked, i.e. 116
against 189 GFLOP/s; ``benchmarks/public_models.py`` and ``benchmarks/gyroscope.py`` time whole networks).
The results are the same convolution up to float rounding of the folded weights (tests: 1e-5 relative).

Layers whose convolution is not a plain one (a ``ProjectedConv2d`` with a camera) get the folded weight, kept
between calls as well, through their own ``_conv_forward``; a horizontally wrapping
:class:`~omnidl.nn.padding.CircularConv2d` is convolved zero-padded and its border columns recomputed from a thin
wrapped strip (no padded copy of the map) where the map is larger than the weight. Everything else — training,
autograd, float64, CUDA, tracing and compiling, ``OMNIDL_PACKED_CONV=0`` — runs the modules' own composition.
"""
from __future__ import annotations

import os
import threading
import warnings
import weakref
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from . import fused, native, winograd, winograd_rows
from .capture import capturing
from .padding import CircularConv2d, border_strip_conv, pad_panorama
from .projected_conv import ProjectedConv2d

Activation = Literal["relu"] | None

#: the prepacked path is used where :func:`inference_ready` allows it (``OMNIDL_PACKED_CONV=0`` turns it off)
ENABLED = os.environ.get("OMNIDL_PACKED_CONV", "1").strip().lower() not in ("0", "false", "no", "off")
#: prepacked weights kept per layer (one per input shape and thread count it meets; the oldest is dropped beyond this)
MAX_SHAPES = 4

#: ``relu(y + r)`` written into ``y`` in one pass (an ATen op of the JIT fuser), where this PyTorch has it
_ADD_RELU = getattr(getattr(torch.ops.aten, "_add_relu_", None), "Tensor", None)

CL = torch.channels_last
_MKLDNN = torch.backends.mkldnn.is_available()

_LOCK = threading.Lock()
_CACHE: "weakref.WeakKeyDictionary[nn.Module, _Entry]" = weakref.WeakKeyDictionary()


class _Entry:
    """What is kept of one (conv, bn) pair: the folded bias, oneDNN's packed weights by (input shape, padding,
    threads), the native kernel's packing for the dense path, and the folded weight itself only where a call
    needs it as such (a layer's own ``_conv_forward``): packed copies alone keep the memory at one extra copy of
    the weights."""

    def __init__(self, key: tuple, conv: nn.Module, bn: nn.Module | None, bias: Tensor | None) -> None:
        self.key, self.bn, self.bias = key, bn, bias
        self.conv = weakref.ref(conv)
        self.weight: Tensor | None = None
        self.packed: dict[tuple, Tensor] = {}
        self.dense: tuple[int, tuple[Tensor | None, Tensor | None]] | None = None   # (kernel kind, packing)
        self.wino: tuple[int, Tensor | None] | None = None
        self.wino_rows: tuple[int, Tensor | None] | None = None

    def folded_weight(self, keep: bool) -> Tensor:
        """The folded weight ``(Cout, Cin/groups, kh, kw)``, contiguous; kept with ``keep``."""
        if self.weight is not None:
            return self.weight
        conv = self.conv()
        with torch.no_grad():
            w = conv.weight if self.bn is None else fold_batchnorm(conv.weight, conv.bias, self.bn)[0]
            w = w.detach().contiguous()
        if keep:
            self.weight = w
        return w


def fold_batchnorm(weight: Tensor, bias: Tensor | None, bn: nn.BatchNorm2d) -> tuple[Tensor, Tensor]:
    """``(weight * s, (bias - mean) * s + beta)`` with ``s = gamma / sqrt(var + eps)`` from BN's running statistics.

    ``conv(x, *fold_batchnorm(w, b, bn))`` equals ``bn(conv(x, w, b))`` in eval mode. ``weight (Cout, ...)``,
    ``bias (Cout,)`` or ``None``; differentiable in every input."""
    scale, folded = bn_scale_shift(bias, bn)
    return weight * scale.reshape(-1, *([1] * (weight.dim() - 1))), folded


def bn_scale_shift(bias: Tensor | None, bn: nn.BatchNorm2d) -> tuple[Tensor, Tensor]:
    """``(s, (bias - mean) * s + beta)`` of :func:`fold_batchnorm` (the weight's per-channel scale, the bias)."""
    scale = torch.rsqrt(bn.running_var + bn.eps)
    if bn.weight is not None:
        scale = scale * bn.weight
    folded = -bn.running_mean * scale if bias is None else (bias - bn.running_mean) * scale
    if bn.bias is not None:
        folded = folded + bn.bias
    return scale, folded


def foldable(bn: nn.Module | None) -> bool:
    """Whether ``bn`` normalises with running statistics now (eval mode), so it can be folded into the conv."""
    return (isinstance(bn, nn.BatchNorm2d) and not bn.training and bn._buffers.get("running_mean") is not None
            and bn._buffers.get("running_var") is not None)


def inference_ready(x: Tensor, *modules: nn.Module | None) -> bool:
    """Whether :func:`conv_bn_act` takes its fast path for input ``x`` and these modules: enabled, CPU float32
    4-d plain tensor, no gradient to record, every BatchNorm foldable, not traced or compiled."""
    if not (ENABLED and type(x) is torch.Tensor and x.dim() == 4 and not x.is_cuda and x.dtype == torch.float32
            and x.device.type == "cpu" and _MKLDNN and torch.backends.mkldnn.enabled):
        return False
    if capturing():
        return False
    grad = torch.is_grad_enabled()
    if grad and x.requires_grad:
        return False
    for m in modules:
        if m is None:
            continue
        if isinstance(m, nn.modules.batchnorm._BatchNorm) and not foldable(m):
            return False
        for p in m._parameters.values():
            if p is not None and ((grad and p.requires_grad) or p.dtype != torch.float32 or p.is_cuda
                                  or p.device.type != "cpu"):
                return False
    return True


def packable(conv: nn.Module) -> bool:
    """A convolution oneDNN runs as it is: a plain ``nn.Conv2d`` (or a camera-less ``ProjectedConv2d``) with
    numeric zero padding, or a :class:`CircularConv2d`."""
    if not isinstance(conv, nn.Conv2d) or isinstance(conv.padding, str) or conv.padding_mode != "zeros":
        return False
    if isinstance(conv, CircularConv2d):
        return True
    if type(conv)._conv_forward is nn.Conv2d._conv_forward:
        return True
    return type(conv)._conv_forward is ProjectedConv2d._conv_forward and conv.camera is None


def _state_key(conv: nn.Module, bn: nn.Module | None) -> tuple:
    p = conv._parameters                          # (the dicts directly: nn.Module.__getattr__ is slow per call)
    tensors = [p["weight"], p.get("bias")]
    if bn is not None:
        # a training forward updates the running statistics without bumping their version; it does bump
        # num_batches_tracked's
        q, b = bn._parameters, bn._buffers
        tensors += [q.get("weight"), q.get("bias"), b.get("running_mean"), b.get("running_var"),
                    b.get("num_batches_tracked")]
    return tuple((t.data_ptr(), t._version) if t is not None else None for t in tensors) + (
        None if bn is None else bn.eps,)


def _entry(conv: nn.Module, bn: nn.Module | None) -> _Entry:
    """The folded parameters of ``(conv, bn)``, recomputed when any of their tensors changed."""
    key = _state_key(conv, bn)
    hit = _CACHE.get(conv)                        # a read needs no lock (the GIL); writes take it
    if hit is None or hit.key != key or hit.bn is not bn:
        with torch.no_grad():
            b = conv.bias if bn is None else bn_scale_shift(conv.bias, bn)[1]
        hit = _Entry(key, conv, bn, None if b is None else b.detach().contiguous())
        with _LOCK:
            _CACHE[conv] = hit
    return hit


def _packed_weight(entry: _Entry, conv: nn.Conv2d, padding: tuple[int, int], x: Tensor) -> Tensor:
    # oneDNN picks the blocked weight layout for the thread count too: packed for 2 threads, a 1-thread call
    # would re-lay the weight out on every call (3x slower HoLiNet-small forward)
    shape = (tuple(x.shape), padding, torch.get_num_threads())
    packed = entry.packed.get(shape)
    if packed is None:
        packed = torch.ops.mkldnn._reorder_convolution_weight(
            entry.folded_weight(keep=False), list(padding), list(conv.stride), list(conv.dilation), conv.groups,
            list(x.shape))
        if len(entry.packed) >= MAX_SHAPES:
            entry.packed.pop(next(iter(entry.packed)))
        entry.packed[shape] = packed
    return packed


def _pointwise(x: Tensor, conv: nn.Conv2d, entry: _Entry, padding: tuple[int, int], act: Activation,
               residual: Tensor | None) -> Tensor:
    """``act(conv(x; padding) + residual)`` with the entry's folded, prepacked weight (``x`` and the result
    channels-last): one oneDNN call, plus one in-place pass for a residual."""
    w = _packed_weight(entry, conv, padding, x)
    args = (list(padding), list(conv.stride), list(conv.dilation), conv.groups)
    if residual is None:
        return torch.ops.mkldnn._convolution_pointwise(x, w, entry.bias, *args, act or "none", [], "")
    # oneDNN's fused sum (the .binary overload) ran 15-25 % slower here than a separate in-place pass
    y = torch.ops.mkldnn._convolution_pointwise(x, w, entry.bias, *args, "none", [], "")
    if act is None:
        return y.add_(residual)
    return _ADD_RELU(y, residual) if _ADD_RELU is not None else y.add_(residual).relu_()


def _wrapped(x: Tensor, conv: CircularConv2d, entry: _Entry, act: Activation, residual: Tensor | None) -> Tensor:
    """:class:`CircularConv2d` through :func:`_pointwise`: zero-padded, then the ``pw`` border columns on each side
    recomputed from the wrapped strip of columns ``W-2pw .. W-1, 0 .. 2pw-1`` (no padded copy of ``x``); a
    padded copy where that does not apply (stride across the width, a kernel that is not centred, a narrow map)
    or costs less (a map smaller than the weight: the strip's convolution streams the whole weight again)."""
    ph, pw = conv.wrap_padding
    kw, dw = conv.kernel_size[1], conv.dilation[1]
    if not pw:
        return _pointwise(x, conv, entry, (ph, 0), act, residual)
    if conv.stride[1] != 1 or 2 * pw != dw * (kw - 1) or x.shape[-1] < 4 * pw or x[0].numel() < conv.weight.numel():
        return _pointwise(pad_panorama(x, pw), conv, entry, (ph, 0), act, residual)
    res = None if residual is None else torch.cat([residual[..., -pw:], residual[..., :pw]], dim=-1)
    return border_strip_conv(x, pw, lambda t, p: _pointwise(t.contiguous(memory_format=CL), conv, entry, (ph, p), act,
                                                            residual if p else res))


#: rows per block of :func:`_dense_into` (a multiple of :data:`omnidl.nn.fused.TILE_ROWS`)
DENSE_BLOCK = 96


def _native_packing(entry: _Entry, slot: str, pack) -> tuple:
    """``(library, entry.<slot>'s kept packing)``, the packing made by ``pack(library)`` when missing or made for
    another build's kernel (packings depend on it); ``(None, None)`` without the native library."""
    lib = native.library()
    if lib is None:
        return None, None
    kind = lib.omnidl_fc_kernel()
    kept = getattr(entry, slot)
    if kept is None or kept[0] != kind:
        kept = (kind, pack(lib))
        setattr(entry, slot, kept)
    return lib, kept[1]


def same_storage(a: Tensor, b: Tensor) -> bool:
    """Whether ``a`` and ``b`` are views of one storage (so a write into one may change the other)."""
    return a.untyped_storage().data_ptr() == b.untyped_storage().data_ptr()


def _writable_residual(x: Tensor, residual: Tensor, cout: int) -> bool:
    """Whether a native kernel may write a stride-1 layer's output over ``residual`` while it reads ``x``: a plain
    channels-last tensor of the output's shape and dtype, outside autograd, not sharing ``x``'s storage."""
    return (type(residual) is torch.Tensor and residual.shape == (x.shape[0], cout) + tuple(x.shape[2:])
            and residual.dtype == x.dtype and residual.is_contiguous(memory_format=CL) and not residual.requires_grad
            and not same_storage(residual, x))


def _dense_into(x: Tensor, conv: nn.Conv2d, entry: _Entry, act: Activation, residual: Tensor) -> Tensor | None:
    """``act(conv(x) + residual)`` for a dense 1x1, stride-1 convolution, written over ``residual`` by the native
    kernel (``omnidl_dense_forward``: the product straight from the channels-last rows of ``x``, the sum and the
    ReLU applied per block in the cache); ``None`` where it does not apply (other convolutions, layouts or
    shapes, the native kernels disabled or unavailable)."""
    B, C, H, W = x.shape
    cout = conv.out_channels
    if not (fused.ENABLED and conv.kernel_size == (1, 1) and conv.stride == (1, 1) and tuple(conv.padding) == (0, 0)
            and conv.groups == 1 and type(conv) is nn.Conv2d and x.is_contiguous(memory_format=CL)
            and _writable_residual(x, residual, cout)):
        return None

    def pack(lib) -> tuple[Tensor | None, Tensor | None]:                    # (kernel's packing, BLAS build's Wm)
        w = entry.folded_weight(keep=False)
        wp = fused._packed(lib, w, transpose=False, keep=False)
        return wp, (w.reshape(cout, C).t().contiguous() if wp is None else None)
    lib, packing = _native_packing(entry, "dense", pack)
    if lib is None:
        return None
    wp, wm = packing
    rc = lib.omnidl_dense_forward(x.data_ptr(), C, C, B * H * W, native.ptr(wm), native.ptr(wp), cout,
                                  native.ptr(entry.bias), residual.data_ptr(), cout, 1, int(act == "relu"),
                                  DENSE_BLOCK, torch.get_num_threads())
    if rc:
        raise RuntimeError(f"omnidl dense 1x1 convolution: the native kernel returned {rc} (missing operand)")
    return residual


def _winograd(x: Tensor, conv: nn.Conv2d, entry: _Entry, act: Activation, residual: Tensor | None) -> Tensor | None:
    """``act(conv(x) [+ residual])`` for a stride-1 3x3 layer by Winograd F(2x2, 3x3) on the native kernel
    (:mod:`omnidl.nn.winograd`), written over ``residual`` when given (the caller no longer needs it); ``None``
    where it does not apply."""
    wrap = winograd.wrap_mode(x, conv)
    if wrap is None or (residual is not None and not _writable_residual(x, residual, conv.out_channels)):
        return None
    lib, packed = _native_packing(entry, "wino", lambda lib: winograd.pack(lib, entry.folded_weight(keep=False)))
    if lib is None or packed is None:                     # no native library, or the BLAS build
        return None
    out = residual if residual is not None else torch.empty(
        (x.shape[0], conv.out_channels) + x.shape[2:], dtype=x.dtype, memory_format=CL)
    return winograd.forward(lib, x, wrap, packed, conv.out_channels, entry.bias, out, residual is not None,
                            act == "relu")


def _winograd_rows(x: Tensor, conv: nn.Conv2d, entry: _Entry, act: Activation) -> Tensor | None:
    """``act(conv(x))`` for a 3x3 layer of stride ``(2, 1)`` by the row Winograd F(2, 3) on the native kernel
    (:mod:`omnidl.nn.winograd_rows`); ``None`` where it does not apply."""
    wrap = winograd_rows.row_mode(x, conv)
    if wrap is None:
        return None
    lib, packed = _native_packing(entry, "wino_rows",
                                  lambda lib: winograd_rows.pack(lib, entry.folded_weight(keep=False)))
    if lib is None or packed is None:                     # no native library, or the BLAS build
        return None
    return winograd_rows.forward(lib, x, wrap, packed, conv.out_channels, entry.bias, act == "relu")


def conv_bn_act(x: Tensor, conv: nn.Conv2d, bn: nn.Module | None = None, act: Activation = None,
                residual: Tensor | None = None, into_residual: bool = False, ready: bool = False) -> Tensor:
    """``act(bn(conv(x)) + residual)``: ``x (B, Cin, H, W)``, ``residual`` ``None`` or ``(B, Cout, Ho, Wo)`` ->
    ``(B, Cout, Ho, Wo)``. ``bn``: a ``BatchNorm2d`` or ``None``; ``act``: ``"relu"`` or ``None``.
    ``into_residual``: the caller no longer needs ``residual``; a dense 1x1 convolution may then be written over
    it by the native kernel (:func:`_dense_into`), which saves allocating (and page-faulting) a new output.
    ``ready``: the caller has just found :func:`inference_ready` true for ``x``, ``conv`` and ``bn`` (or for its
    block's input and modules, when ``x`` is an output of this function), so it is not checked again.

    Fast path (see the module docstring) where :func:`inference_ready` and ``conv`` is an ``nn.Conv2d`` whose
    ``forward`` is ``nn.Conv2d``'s (so its ``_conv_forward`` is the whole layer); otherwise the modules are called as
    they are (``conv(x)``, ``bn(.)``, ``+ residual``, ``relu``), so training and autograd are untouched."""
    if act not in ("relu", None):
        raise ValueError(f"conv_bn_act: act must be 'relu' or None, got {act!r}")
    if not ((ready or inference_ready(x, conv, bn)) and isinstance(conv, nn.Conv2d)
            and type(conv).forward is nn.Conv2d.forward):
        return _composition(x, conv, bn, act, residual)
    try:
        return _fast(x, conv, bn, act, residual, into_residual)
    except RuntimeError as error:  # a build without these oneDNN ops (or a bad input: the modules then raise)
        y = _composition(x, conv, bn, act, residual)
        _disable(error)
        return y


def _composition(x: Tensor, conv: nn.Module, bn: nn.Module | None, act: Activation,
                 residual: Tensor | None) -> Tensor:
    """The modules as they are: ``act(bn(conv(x)) + residual)``."""
    y = conv(x)
    if bn is not None:
        y = bn(y)
    if residual is not None:
        y = y + residual
    return F.relu(y) if act == "relu" else y


def _disable(error: Exception) -> None:
    """The fast path failed where the modules themselves ran: turn it off for the process, with one warning."""
    global ENABLED
    if ENABLED:
        ENABLED = False
        warnings.warn(f"omnidl: the packed inference convolutions failed ({type(error).__name__}: "
                      f"{str(error).splitlines()[0] if str(error) else ''}); the modules run as they are from now on",
                      RuntimeWarning, stacklevel=3)


def _fast(x: Tensor, conv: nn.Conv2d, bn: nn.Module | None, act: Activation, residual: Tensor | None,
          into_residual: bool) -> Tensor:
    """:func:`conv_bn_act` where :func:`inference_ready`: the native dense path, oneDNN with the packed weight, or
    the layer's own ``_conv_forward`` with the folded weight."""
    entry = _entry(conv, bn)
    if into_residual and residual is not None and (y := _dense_into(x, conv, entry, act, residual)) is not None:
        return y
    if (residual is None or into_residual) and (y := _winograd(x, conv, entry, act, residual)) is not None:
        return y
    if residual is None and (y := _winograd_rows(x, conv, entry, act)) is not None:
        return y
    if packable(conv) and x.is_contiguous(memory_format=torch.channels_last):
        if isinstance(conv, CircularConv2d):
            return _wrapped(x, conv, entry, act, residual)
        return _pointwise(x, conv, entry, tuple(conv.padding), act, residual)
    y = conv._conv_forward(x, entry.folded_weight(keep=True), entry.bias)
    if residual is not None:
        y = y.add_(residual)
    return F.relu_(y) if act == "relu" else y


def clear_cache() -> None:
    """Drop every kept folded and prepacked weight (they are also dropped with their layer)."""
    with _LOCK:
        _CACHE.clear()
