"""Fixed-offset convolution with the gather fused into the product (CPU float32, :mod:`.native` kernel).

For each block of output positions the kernel interpolates the block's taps into a small column block
``A (m, K*C)`` that stays in the core's cache and multiplies it at once by ``Wm (K*C, Cout)``; the full column
matrix, the tiles of :mod:`.tiled` and their memory traffic never exist. ``m`` is chosen so that ``A`` is about
:data:`BLOCK_BYTES`. The sums are those of the column path (:mod:`.sampling`) in another order (float32
rounding).

Backward: ``grad_W += A^T grad_out`` on re-gathered taps, then ``grad_X += S^T (grad_out Wm^T)`` scattered
straight from each block (no CSR transposes are built). Nothing but the input rows and the weight is kept
between forward and backward.

Threads: each call is one OpenMP parallel region of ``torch.get_num_threads()`` threads on PyTorch's own
thread team (see :mod:`.native`), split by output positions (or, for small deep maps, by output channels);
the input and weight gradients of the other threads are private copies added in at the end. The weight is
packed once per call into the kernel's panels (kept, outside autograd, for an unchanged weight).
"""
from __future__ import annotations

import weakref
from pathlib import Path

import torch
from torch import Tensor

from . import native, thin_layout
from .native import ptr as _ptr
from .sampling import (SamplingPlan, _FixedOffsetConv, _is_channels_last, _rows, finish_backward, new_accumulators,
                       save_columns_context, weight_channels_last, weight_matrix)

def l2_cache_bytes(root: str = "/sys/devices/system/cpu/cpu0/cache") -> int | None:
    """Size of a core's level-2 cache from Linux's sysfs (``None`` where it is not listed)."""
    for d in sorted(Path(root).glob("index*")):
        try:
            level = (d / "level").read_text().strip()
            kind = (d / "type").read_text().strip()
            size = (d / "size").read_text().strip().upper()
        except OSError:
            continue
        if level == "2" and kind in ("Unified", "Data") and size[:-1].isdigit() and size[-1] in "KM":
            return int(size[:-1]) * (1024 if size[-1] == "K" else 1024 ** 2)
    return None


#: target size (bytes) of one block of gathered taps, kept in the core's L2 cache while the weight's panels stream
#: past it: a third of the L2 cache, at least 224 kB. Measured on 2 MB L2 caches (64 and 256 channels): 640 kB to
#: 1 MB ran 8-10 % faster than 224 kB (the weight is streamed once per block, so bigger blocks stream it less
#: often); on a host with a smaller L2, 64 and 256 channels ran equally fast from ~100 kB to ~250 kB
BLOCK_BYTES = max(224 * 1024, (l2_cache_bytes() or 0) // 3)
#: fewest output positions per block (where the image has them)
MIN_BLOCK = 24
#: blocks are a multiple of this many positions: the rows of both register kernels' tiles (6 AVX2, 12 AVX-512)
TILE_ROWS = 12
#: weights larger than this are read from memory, not cache, on every block (see :func:`block_positions`);
#: measured here: 3.5 MB (770 -> 128 channels) ran best with small blocks, 14 MB (1536 -> 256) with one block
BIG_WEIGHT_BYTES = 8 * 2 ** 20
#: the largest block of gathered taps for such weights
BIG_BLOCK_BYTES = 8 * 2 ** 20
#: ``False`` turns the fused path off (the layer then takes the tiled path): benchmarks' in-process A/B
ENABLED = True


def block_positions(plan: SamplingPlan, channels: int, out_channels: int = 0, positions: int = 0) -> int:
    """Output positions per block: a multiple of :data:`TILE_ROWS` with ``A`` about :data:`BLOCK_BYTES`, and
    at least :data:`MIN_BLOCK` (each block streams the whole weight). A weight over :data:`BIG_WEIGHT_BYTES`
    (``out_channels`` given; deep layers, not cache-resident) is streamed from memory on every block, so there
    the block takes all ``positions`` (the batch's), with ``A`` up to :data:`BIG_BLOCK_BYTES`."""
    row = 4 * plan.taps * channels
    t = TILE_ROWS
    block = max(MIN_BLOCK, BLOCK_BYTES // row // t * t)
    if row * out_channels > BIG_WEIGHT_BYTES and positions:
        block = max(block, min(-(-positions // t) * t, max(t, BIG_BLOCK_BYTES // row // t * t)))
    return block


# packed weights of inference calls, by weight tensor: (weak reference, version, data pointer, packed)
_PACKED: dict[tuple[int, bool, int], tuple[weakref.ref, int, int, Tensor]] = {}


def _blas(lib) -> bool:
    """True for a build whose products call BLAS (it reads the weight as ``Wm``, nothing is packed)."""
    return lib.omnidl_fc_packed_floats(1, 1) == 0


def _packed(lib, weight: Tensor, transpose: bool, keep: bool | None = None) -> Tensor | None:
    """``weight (Cout, C, kh, kw)`` as the kernel's panels of ``Wm (kh*kw*C, Cout)`` (or, with ``transpose``, of
    ``Wm^T``), packed once for all threads; ``None`` on the BLAS build. With ``keep`` (default: outside autograd)
    the packing of an unchanged ``weight`` is kept: inference re-uses it on every call (a wide layer's weight is
    tens of MB)."""
    if _blas(lib):
        return None
    Cout, C, kh, kw = weight.shape
    KC = kh * kw * C
    if keep is None:
        keep = not (torch.is_grad_enabled() and weight.requires_grad)
    key = (id(weight), transpose, lib.omnidl_fc_kernel())    # the panels' width depends on the build's kernel
    hit = _PACKED.get(key) if keep else None
    if hit is not None and hit[0]() is weight and hit[1] == weight._version and hit[2] == weight.data_ptr():
        return hit[3]
    cl = weight_channels_last(weight)                   # (Cout, kh, kw, C) in memory: read as it lies
    wc = weight.detach() if cl else weight.detach().contiguous()
    wp = torch.empty(lib.omnidl_fc_packed_floats(*((Cout, KC) if transpose else (KC, Cout))), dtype=torch.float32)
    _call(lib.omnidl_fc_pack(wc.data_ptr(), Cout, C, kh * kw, int(cl), int(transpose), wp.data_ptr(),
                             torch.get_num_threads()), "weight packing")
    if keep:
        _PACKED[key] = (weakref.ref(weight, lambda _, k=key: _PACKED.pop(k, None)), weight._version,
                        weight.data_ptr(), wp)
    return wp


def _call(rc: int, what: str) -> None:
    if rc == 1:
        raise MemoryError(f"fixed-offset convolution ({what}): the native kernel could not allocate its buffers")
    if rc != 0:
        raise RuntimeError(f"fixed-offset convolution ({what}): the native kernel returned {rc} (missing operand)")


class _FusedConv(_FixedOffsetConv):
    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan,  # type: ignore[override]
                block: int) -> Tensor:
        B, C, H, W = x.shape
        Cout = weight.shape[0]
        Ho, Wo = plan.out_hw
        P = Ho * Wo
        lib = native.library()
        channels_last = _is_channels_last(x)
        xr = _rows(x)
        wp = _packed(lib, weight, transpose=False)
        wm = weight_matrix(weight) if wp is None else None  # the BLAS build reads Wm itself
        b_ = None if bias is None else bias.detach().contiguous()
        # channels-last output rows written in place; an NCHW result is one layout copy of them
        rows = torch.empty(B, Cout, Ho, Wo, dtype=x.dtype, memory_format=torch.channels_last)
        _call(lib.omnidl_fc_forward(xr.data_ptr(), H * W * C, C, plan.idx.data_ptr(), plan.weight.data_ptr(),
                                    plan.taps, P, B, _ptr(wm), _ptr(wp), Cout, _ptr(b_), rows.data_ptr(), P * Cout,
                                    Cout, block, torch.get_num_threads()), "forward")
        save_columns_context(ctx, x, weight, bias, plan, block, xr, weight.detach())  # the backward packs it
        return rows if channels_last else thin_layout.to_nchw(rows)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        plan: SamplingPlan = ctx.plan
        xr, weight = ctx.saved_tensors
        B, C, H, W = ctx.in_shape
        Cout = weight.shape[0]
        P = plan.out_hw[0] * plan.out_hw[1]
        lib = native.library()
        g = _rows(grad_out)  # (B, P, Cout), copy-free for a channels-last gradient
        need_x = ctx.needs_input_grad[0]
        wtp = _packed(lib, weight, transpose=True, keep=False) if need_x else None
        wm = weight_matrix(weight) if need_x and _blas(lib) else None
        gx, gwm = new_accumulators(ctx, Cout, g)
        _call(lib.omnidl_fc_backward(_ptr(xr), H * W * C, C, plan.idx.data_ptr(), plan.weight.data_ptr(), plan.taps,
                                     P, B, _ptr(wm), _ptr(wtp), Cout, g.data_ptr(), P * Cout, Cout, _ptr(gx),
                                     H * W * C, _ptr(gwm), ctx.positions, torch.get_num_threads()), "backward")
        return finish_backward(ctx, grad_out, [(gx, gwm)])


def fused_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan, block: int | None = None) -> Tensor:
    """Fixed-offset convolution of ``x (B, C, H, W)`` (CPU float32) by the native kernel in blocks of ``block``
    output positions (default :func:`block_positions`); same contract and output memory format as
    :func:`.sampling.fixed_offset_conv2d`. Requires :func:`fused_supported`."""
    if block is None:
        block = block_positions(plan, x.shape[1], weight.shape[0], x.shape[0] * plan.out_hw[0] * plan.out_hw[1])
    return _FusedConv.apply(x, weight, bias, plan, int(block))


def fused_supported(x: Tensor, weight: Tensor, plan: SamplingPlan) -> bool:
    """True where the native kernel runs: enabled, built, CPU float32 input, weight and plan, int32 plan indices,
    real tensors (``torch.compile``/``torch.export`` trace the tiled path, made of torch ops, instead)."""
    return (ENABLED and type(x) is torch.Tensor and not torch.compiler.is_compiling()
            and x.device.type == "cpu" and x.dtype == torch.float32 and weight.dtype == torch.float32
            and plan.weight.dtype == torch.float32 and plan.idx.dtype == torch.int32 and plan.idx.is_contiguous()
            and plan.weight.is_contiguous() and native.library() is not None)
