"""``torch.ops.omnidl.fixed_offset_conv2d``: a convolution whose taps sample the input at fixed positions.

For an input ``x (B, C, H, W)``, a weight ``(Cout, C, kh, kw)`` and, per output position ``(i, j)`` of an
``Ho x Wo`` map and tap ``k = a * kw + b``, a position ``positions[i, j, k] = (y, x)`` in input pixels and a weight
``mask[i, j, k]``::

    out[n, o, i, j] = bias[o] + sum_{c, k} weight[o, c, k] * mask[i, j, k] * bilinear(x[n, c], positions[i, j, k])

``bilinear`` reads zero outside the image, as ``torchvision.ops.deform_conv2d`` does; with ``wrap`` a column is
taken modulo ``W`` (a 360-degree image has no left or right border). This is ``deform_conv2d`` with offsets fixed
for the whole batch: the op :class:`omnidl.nn.ProjectedConv2d` runs, its positions coming from a camera model.

Registered with ``torch.library`` (schema, fake kernel, autograd; :func:`torch.library.opcheck` tests it). Kernels,
by device only:

* CPU: the native C kernel (``csrc/fixed_offset_conv.c``: the taps gathered block by block into the cache and
  multiplied there) for float32; other dtypes, and a machine where the kernel cannot be built, the PyTorch
  implementation below.
* CUDA: one ``grid_sample`` of every tap and one 1x1 convolution (cuDNN, under ``nn.Conv2d``'s TF32 policy).
* any other device: the PyTorch implementation (``embedding_bag``-style corner gathers and one product).

The backward is a second op, ``omnidl::fixed_offset_conv2d_backward``, whose own autograd is written with the two
ops, so gradients of any order exist (``gradgradcheck`` passes). Under autocast the op computes in float32.
"""
from __future__ import annotations

import ctypes
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from . import _native

LIBRARY = "fixed_offset_conv"
_SIGNATURES = {
    "omnidl_foc_forward": (_native.INT, [_native.POINTER, _native.INT64, _native.INT, _native.INT, _native.INT,
                                         _native.POINTER, _native.POINTER, _native.INT, _native.INT, _native.INT64,
                                         _native.INT, _native.POINTER, _native.INT, _native.POINTER, _native.POINTER,
                                         _native.INT64, _native.INT]),
    "omnidl_foc_backward": (_native.INT, [_native.POINTER, _native.INT64, _native.INT, _native.INT, _native.INT,
                                          _native.POINTER, _native.POINTER, _native.INT, _native.INT, _native.INT64,
                                          _native.INT, _native.POINTER, _native.INT, _native.POINTER, _native.POINTER,
                                          _native.POINTER, _native.INT64, _native.INT]),
    "omnidl_foc_kernel": (_native.INT, []),
    "omnidl_foc_openmp": (_native.INT, []),
}
#: what ``omnidl_foc_kernel()`` returns, by name
KERNELS = ("blas", "avx2", "avx512")


def native_library() -> ctypes.CDLL | None:
    """The CPU kernel's library (built on first use), or ``None`` where it cannot be built."""
    return _native.load(LIBRARY, ["fixed_offset_conv.c"], _SIGNATURES)


def native_status() -> dict:
    """``{"available", "kernel" ("avx512" | "avx2" | "blas" | None), "openmp", "path", "reason"}``."""
    lib = native_library()
    return {**_native.status(LIBRARY), "kernel": None if lib is None else KERNELS[lib.omnidl_foc_kernel()],
            "openmp": lib is not None and bool(lib.omnidl_foc_openmp())}


# ---- the ops ---------------------------------------------------------------------------------------------------

@torch.library.custom_op("omnidl::fixed_offset_conv2d", mutates_args=())
def fixed_offset_conv2d(input: Tensor, weight: Tensor, bias: Tensor | None, positions: Tensor, mask: Tensor,
                        wrap: bool) -> Tensor:
    """``(B, C, H, W) -> (B, Cout, Ho, Wo)``; see the module docstring (this body: devices without a kernel)."""
    return torch_forward(input, weight, bias, positions, mask, wrap)


@torch.library.custom_op("omnidl::fixed_offset_conv2d_backward", mutates_args=())
def fixed_offset_conv2d_backward(grad: Tensor, input: Tensor, weight: Tensor, positions: Tensor, mask: Tensor,
                                 wrap: bool, input_grad: bool, weight_grad: bool) -> tuple[Tensor, Tensor]:
    """``(grad_input, grad_weight)`` of :func:`fixed_offset_conv2d` for ``grad (B, Cout, Ho, Wo)``; a gradient not
    asked for (``input_grad`` / ``weight_grad`` false) is an empty tensor."""
    return torch_backward(grad, input, weight, positions, mask, wrap, input_grad, weight_grad)


@fixed_offset_conv2d.register_fake
def _forward_fake(input, weight, bias, positions, mask, wrap):
    check_arguments(input, weight, bias, positions, mask)
    B, Ho, Wo = input.shape[0], positions.shape[0], positions.shape[1]
    return input.new_empty(B, weight.shape[0], Ho, Wo)


@fixed_offset_conv2d_backward.register_fake
def _backward_fake(grad, input, weight, positions, mask, wrap, input_grad, weight_grad):
    return (input.new_empty(input.shape) if input_grad else input.new_empty(0),
            weight.new_empty(weight.shape) if weight_grad else weight.new_empty(0))


def _setup_forward(ctx, inputs, output) -> None:
    input, weight, bias, positions, mask, wrap = inputs
    ctx.save_for_backward(input, weight, positions, mask)
    ctx.wrap, ctx.has_bias = wrap, bias is not None


def _forward_backward(ctx, grad: Tensor):
    input, weight, positions, mask = ctx.saved_tensors
    need_x, need_w, need_b = ctx.needs_input_grad[:3]
    gx = gw = gb = None
    if need_x or need_w:
        gx, gw = fixed_offset_conv2d_backward(grad, input, weight, positions, mask, ctx.wrap, need_x, need_w)
    if need_b and ctx.has_bias:
        gb = grad.sum((0, 2, 3))
    return (gx if need_x else None), (gw if need_w else None), gb, None, None, None


def _setup_backward(ctx, inputs, output) -> None:
    grad, input, weight, positions, mask, wrap, input_grad, weight_grad = inputs
    ctx.save_for_backward(grad, input, weight, positions, mask)
    ctx.wrap, ctx.asked = wrap, (input_grad, weight_grad)


def _backward_backward(ctx, ggx: Tensor, ggw: Tensor):
    """Gradients of the backward: gx = J_x^T g and gw = J_w(x)^T g are bilinear in (g, w) and (g, x), so
    d<ggx, gx>/dg = conv(ggx, w), d<ggx, gx>/dw = weight gradient of conv at ggx for g,
    d<ggw, gw>/dg = conv(x, ggw), d<ggw, gw>/dx = input gradient of conv with weight ggw for g."""
    grad, input, weight, positions, mask = ctx.saved_tensors
    need_g, need_x, need_w = ctx.needs_input_grad[:3]
    ggx = ggx if ctx.asked[0] and ggx is not None and ggx.numel() else None
    ggw = ggw if ctx.asked[1] and ggw is not None and ggw.numel() else None
    dg = dx = dw = None
    if need_g:
        parts = [fixed_offset_conv2d(t, w, None, positions, mask, ctx.wrap)
                 for t, w in ((ggx, weight), (input, ggw)) if t is not None and w is not None]
        dg = sum(parts[1:], parts[0]) if parts else None
    if need_x and ggw is not None:
        dx = fixed_offset_conv2d_backward(grad, input, ggw, positions, mask, ctx.wrap, True, False)[0]
    if need_w and ggx is not None:
        dw = fixed_offset_conv2d_backward(grad, ggx, weight, positions, mask, ctx.wrap, False, True)[1]
    return dg, dx, dw, None, None, None, None, None


fixed_offset_conv2d.register_autograd(_forward_backward, setup_context=_setup_forward)
fixed_offset_conv2d_backward.register_autograd(_backward_backward, setup_context=_setup_backward)
torch.library.register_autocast("omnidl::fixed_offset_conv2d", "cuda", torch.float32)
torch.library.register_autocast("omnidl::fixed_offset_conv2d", "cpu", torch.float32)


def check_arguments(input: Tensor, weight: Tensor, bias: Tensor | None, positions: Tensor, mask: Tensor) -> None:
    """Raise a ``ValueError`` naming the argument whose shape, dtype or device does not fit the others."""
    if input.dim() != 4:
        raise ValueError(f"fixed_offset_conv2d: input must be (B, C, H, W), got shape {tuple(input.shape)}")
    if weight.dim() != 4 or weight.shape[1] != input.shape[1]:
        raise ValueError(f"fixed_offset_conv2d: weight must be (Cout, {input.shape[1]}, kh, kw) for an input of "
                         f"{input.shape[1]} channels (groups=1), got shape {tuple(weight.shape)}")
    K = weight.shape[2] * weight.shape[3]
    if positions.dim() != 4 or positions.shape[2:] != (K, 2):
        raise ValueError(f"fixed_offset_conv2d: positions must be (Ho, Wo, {K}, 2) for a {tuple(weight.shape[2:])} "
                         f"kernel, got shape {tuple(positions.shape)}")
    if mask.shape != positions.shape[:3]:
        raise ValueError(f"fixed_offset_conv2d: mask must be (Ho, Wo, K) = {tuple(positions.shape[:3])}, got "
                         f"{tuple(mask.shape)}")
    if bias is not None and bias.shape != (weight.shape[0],):
        raise ValueError(f"fixed_offset_conv2d: bias must be ({weight.shape[0]},), got {tuple(bias.shape)}")
    if weight.dtype != input.dtype or (bias is not None and bias.dtype != input.dtype):
        raise ValueError(f"fixed_offset_conv2d: input, weight and bias must share a dtype, got {input.dtype}, "
                         f"{weight.dtype}{'' if bias is None else ', ' + str(bias.dtype)}")
    if not (positions.dtype.is_floating_point and mask.dtype.is_floating_point):
        raise ValueError(f"fixed_offset_conv2d: positions and mask must be floating point, got {positions.dtype}, "
                         f"{mask.dtype}")
    devices = {t.device for t in (input, weight, positions, mask) + (() if bias is None else (bias,))}
    if len(devices) > 1:
        raise ValueError(f"fixed_offset_conv2d: every tensor must be on one device, got {sorted(map(str, devices))}")


# ---- the PyTorch implementation (any device, any floating dtype) ------------------------------------------------

#: tap rows per chunk of the PyTorch implementation (bounds its column buffer: rows x C per image)
CHUNK_ROWS = 1 << 16


def corners(positions: Tensor, mask: Tensor, in_hw: tuple[int, int], wrap: bool) -> tuple[Tensor, Tensor]:
    """The bilinear corners of every tap (float64 arithmetic): ``idx (N, 4)`` flat input pixels (int64) and
    ``coeff (N, 4)`` float64 weights, ``N = Ho * Wo * K``; ``coeff = 0`` where a corner reads zero (outside the
    image, a zero mask, a non-finite position) - the rule of the C kernel and of ``deform_conv2d``."""
    H, W = in_hw
    pos = positions.reshape(-1, 2).double()
    m = mask.reshape(-1, 1).double()
    finite = torch.isfinite(pos).all(1, keepdim=True) & torch.isfinite(m)
    pos = torch.where(finite, pos, torch.zeros_like(pos))
    y, x = pos[:, :1], pos[:, 1:]
    y0, x0 = torch.floor(y), torch.floor(x)
    ly, lx = y - y0, x - x0
    w = torch.cat([(1 - ly) * (1 - lx) * m, (1 - ly) * lx * m, ly * (1 - lx) * m, ly * lx * m], 1)
    cy = torch.cat([y0, y0, y0 + 1, y0 + 1], 1)
    cx = torch.cat([x0, x0 + 1, x0, x0 + 1], 1)
    ok = finite & (w != 0) & (cy >= 0) & (cy <= H - 1)
    if wrap:
        cx = torch.remainder(cx, W)
    else:
        ok &= (cx >= 0) & (cx <= W - 1)
    coeff = torch.where(ok, w, torch.zeros_like(w))
    idx = torch.where(ok, cy * W + cx, torch.zeros_like(cy)).long()
    return idx, coeff


def _chunks(rows: int, K: int):
    step = max(K, CHUNK_ROWS // K * K)
    return [(s, min(rows, s + step)) for s in range(0, rows, step)]


def _gather(xr: Tensor, idx: Tensor, coeff: Tensor) -> Tensor:
    """Columns ``(B, N, C)`` of the taps of ``idx``/``coeff (N, 4)`` on rows ``xr (B, H*W, C)``; a corner of weight
    0 is not read (a non-finite pixel reaches only the taps that sample it)."""
    return sum(torch.where(coeff[:, j, None] != 0, xr[:, idx[:, j]] * coeff[:, j, None], 0) for j in range(4))


def torch_forward(input: Tensor, weight: Tensor, bias: Tensor | None, positions: Tensor, mask: Tensor,
                  wrap: bool) -> Tensor:
    """The op in PyTorch operations: per chunk of tap rows, the four corners gathered and summed into columns
    ``(B, rows, C)``, then one product with ``Wm (K*C, Cout)``."""
    check_arguments(input, weight, bias, positions, mask)
    B, C, H, W = input.shape
    Cout, K = weight.shape[0], weight.shape[2] * weight.shape[3]
    Ho, Wo = positions.shape[:2]
    idx, coeff = corners(positions, mask, (H, W), wrap)
    coeff = coeff.to(input.dtype)
    xr = input.permute(0, 2, 3, 1).reshape(B, H * W, C)
    wm = weight.permute(2, 3, 1, 0).reshape(K * C, Cout)
    out = input.new_empty(B, Ho * Wo, Cout)
    for s, e in _chunks(idx.shape[0], K):
        cols = _gather(xr, idx[s:e], coeff[s:e])                                        # (B, e - s, C)
        out[:, s // K:e // K] = cols.reshape(B, (e - s) // K, K * C) @ wm
    if bias is not None:
        out += bias
    return out.reshape(B, Ho, Wo, Cout).permute(0, 3, 1, 2).contiguous()


def torch_backward(grad: Tensor, input: Tensor, weight: Tensor, positions: Tensor, mask: Tensor, wrap: bool,
                   input_grad: bool, weight_grad: bool) -> tuple[Tensor, Tensor]:
    """The backward in PyTorch operations: ``gw = sum cols^T g`` on re-gathered columns, ``gx = S^T (g Wm^T)`` by
    ``index_add_`` of each corner."""
    B, C, H, W = input.shape
    Cout, K = weight.shape[0], weight.shape[2] * weight.shape[3]
    kh, kw = weight.shape[2:]
    idx, coeff = corners(positions, mask, (H, W), wrap)
    coeff = coeff.to(input.dtype)
    xr = input.permute(0, 2, 3, 1).reshape(B, H * W, C)
    g = grad.permute(0, 2, 3, 1).reshape(B, -1, Cout)
    wm = weight.permute(2, 3, 1, 0).reshape(K * C, Cout)
    gx = torch.zeros_like(xr) if input_grad else input.new_empty(0)
    gwm = weight.new_zeros(K * C, Cout) if weight_grad else None
    for s, e in _chunks(idx.shape[0], K):
        gc = g[:, s // K:e // K]                                                       # (B, P_c, Cout)
        if weight_grad:
            cols = _gather(xr, idx[s:e], coeff[s:e])
            gwm += torch.einsum("bpk,bpo->ko", cols.reshape(B, -1, K * C), gc)
        if input_grad:
            gcols = (gc @ wm.t()).reshape(B, e - s, C)
            for j in range(4):
                gx.index_add_(1, idx[s:e, j], gcols * coeff[s:e, j, None])
    if input_grad:
        gx = gx.reshape(B, H, W, C).permute(0, 3, 1, 2).contiguous()
    gw = gwm.reshape(kh, kw, C, Cout).permute(3, 2, 0, 1).contiguous() if weight_grad else weight.new_empty(0)
    return gx, gw


# ---- CPU: the native kernel --------------------------------------------------------------------------------------

def l2_cache_bytes(root: str = "/sys/devices/system/cpu/cpu0/cache") -> int | None:
    """Size of a core's level-2 cache from Linux's sysfs (``None`` where it is not listed)."""
    for d in sorted(Path(root).glob("index*")):
        try:
            level, kind = (d / "level").read_text().strip(), (d / "type").read_text().strip()
            size = (d / "size").read_text().strip().upper()
        except OSError:
            continue
        if level == "2" and kind in ("Unified", "Data") and size[:-1].isdigit() and size[-1] in "KM":
            return int(size[:-1]) * (1024 if size[-1] == "K" else 1024 ** 2)
    return None


#: bytes of one block of gathered taps, kept in a core's L2 cache while the weight's panels stream past it
BLOCK_BYTES = max(224 * 1024, (l2_cache_bytes() or 0) // 3)
#: a weight larger than this is streamed from memory once per block: its blocks take every position (up to
#: BIG_BLOCK_BYTES of taps), so that it is read once per call
BIG_WEIGHT_BYTES = BIG_BLOCK_BYTES = 8 << 20


def block_positions(channels: int, taps: int, out_channels: int, positions: int) -> int:
    """Output positions per block of the native kernel: a multiple of 12 (both register kernels' tile rows) with
    the block's taps about :data:`BLOCK_BYTES`, at least 24."""
    row = 4 * taps * channels
    block = max(24, BLOCK_BYTES // row // 12 * 12)
    if row * out_channels > BIG_WEIGHT_BYTES:
        block = max(block, min(-(-positions // 12) * 12, max(12, BIG_BLOCK_BYTES // row // 12 * 12)))
    return block


def _native_arguments(input: Tensor, weight: Tensor, positions: Tensor, mask: Tensor):
    B, C, H, W = input.shape
    Cout, K = weight.shape[0], weight.shape[2] * weight.shape[3]
    P = positions.shape[0] * positions.shape[1]
    xr = input.permute(0, 2, 3, 1).contiguous()                                       # (B, H, W, C) rows
    wm = weight.permute(2, 3, 1, 0).reshape(K * C, Cout).contiguous()
    pos = positions.detach().to(torch.float64).contiguous()
    m = mask.detach().to(torch.float64).contiguous()
    return xr, wm, pos, m, (B, C, H, W, Cout, K, P, block_positions(C, K, Cout, B * P))


def _native_call(rc: int, what: str) -> None:
    if rc:
        raise MemoryError(f"fixed_offset_conv2d ({what}): the native kernel could not allocate its buffers")


def _uses_native(*tensors: Tensor) -> bool:
    return all(t.dtype == torch.float32 for t in tensors) and native_library() is not None


@fixed_offset_conv2d.register_kernel("cpu")
def _forward_cpu(input, weight, bias, positions, mask, wrap):
    check_arguments(input, weight, bias, positions, mask)
    if not _uses_native(input, weight):
        return torch_forward(input, weight, bias, positions, mask, wrap)
    xr, wm, pos, m, (B, C, H, W, Cout, K, P, block) = _native_arguments(input, weight, positions, mask)
    b = None if bias is None else bias.contiguous()
    out = torch.empty(B, Cout, *positions.shape[:2], dtype=input.dtype, memory_format=torch.channels_last)
    _native_call(native_library().omnidl_foc_forward(
        xr.data_ptr(), H * W * C, C, H, W, pos.data_ptr(), m.data_ptr(), int(wrap), K, P, B, wm.data_ptr(), Cout,
        _native.pointer(b), out.data_ptr(), block, torch.get_num_threads()), "forward")
    return out.contiguous()


@fixed_offset_conv2d_backward.register_kernel("cpu")
def _backward_cpu(grad, input, weight, positions, mask, wrap, input_grad, weight_grad):
    if not _uses_native(grad, input, weight):
        return torch_backward(grad, input, weight, positions, mask, wrap, input_grad, weight_grad)
    xr, wm, pos, m, (B, C, H, W, Cout, K, P, block) = _native_arguments(input, weight, positions, mask)
    g = grad.permute(0, 2, 3, 1).contiguous()                                        # (B, Ho, Wo, Cout) rows
    gx = torch.zeros(B, H, W, C, dtype=input.dtype) if input_grad else None                 # rows
    gwm = torch.zeros(K * C, Cout, dtype=weight.dtype) if weight_grad else None
    _native_call(native_library().omnidl_foc_backward(
        xr.data_ptr(), H * W * C, C, H, W, pos.data_ptr(), m.data_ptr(), int(wrap), K, P, B, wm.data_ptr(), Cout,
        g.data_ptr(), _native.pointer(gx), _native.pointer(gwm), block, torch.get_num_threads()), "backward")
    gx = input.new_empty(0) if gx is None else gx.permute(0, 3, 1, 2).contiguous()
    kh, kw = weight.shape[2:]
    gw = gwm.reshape(kh, kw, C, Cout).permute(3, 2, 0, 1).contiguous() if weight_grad else weight.new_empty(0)
    return gx, gw


# ---- CUDA: one grid_sample of every tap, one 1x1 convolution -----------------------------------------------------

#: channels per ``grid_sample`` image: groups of channels as images of their own give ``grid_sample``, which runs
#: one thread per sample and loops over channels, more threads (the same memory)
SAMPLE_CHANNELS = 8
#: normalised coordinate of a tap that reads zero: far outside ``[-1, 1]``
FAR = -4.0


def sampling_grid(positions: Tensor, mask: Tensor, in_hw: tuple[int, int], wrap: bool,
                  dtype: torch.dtype) -> tuple[Tensor, Tensor | None]:
    """``grid (1, K*Ho, Wo, 2)`` of ``grid_sample`` (``align_corners=False``) for the taps - tap ``k`` of output
    ``(i, j)`` at row ``k*Ho + i`` - on the input with one wrapped column appended when ``wrap`` (positions taken
    modulo ``W``: a corner at column ``W`` is column 0), and the mask as ``scale (K*Ho, Wo)`` where it is not
    binary (else ``None``). Built in float64, cast once."""
    H, W = in_hw
    Ho, Wo, K, _ = positions.shape
    pos = positions.double()
    m = mask.double()
    y, x = pos[..., 0], pos[..., 1]
    live = torch.isfinite(x) & torch.isfinite(y) & (m != 0)
    if wrap:
        x = torch.remainder(x, W)
    width = W + 1 if wrap else W
    gx = torch.where(live, (2 * x + 1) / width - 1, torch.full_like(x, FAR))
    gy = torch.where(live, (2 * y + 1) / H - 1, torch.full_like(y, FAR))
    grid = torch.stack([gx, gy], -1).permute(2, 0, 1, 3).reshape(1, K * Ho, Wo, 2).to(dtype).contiguous()
    binary = bool(((m == 0) | (m == 1)).all())
    scale = None if binary else m.permute(2, 0, 1).reshape(K * Ho, Wo).to(dtype)
    return grid, scale


def _grid_columns(input: Tensor, grid: Tensor, scale: Tensor | None, wrap: bool) -> Tensor:
    B, C = input.shape[:2]
    if wrap:
        input = torch.cat([input, input[..., :1]], -1)
    g = math.gcd(C, SAMPLE_CHANNELS)
    xs = input.reshape(B * C // g, g, *input.shape[2:])
    cols = F.grid_sample(xs, grid.expand(B * C // g, -1, -1, -1), mode="bilinear", padding_mode="zeros",
                         align_corners=False).view(B, C, *grid.shape[1:3])
    return cols if scale is None else cols * scale


def grid_forward(input: Tensor, weight: Tensor, bias: Tensor | None, positions: Tensor, mask: Tensor,
                 wrap: bool) -> Tensor:
    """The CUDA kernel (any device): columns ``(B, C*K, Ho, Wo)`` by one ``grid_sample``, then a 1x1 convolution."""
    check_arguments(input, weight, bias, positions, mask)
    B, C, H, W = input.shape
    Cout, Ho, Wo, K = weight.shape[0], *positions.shape[:3]
    grid, scale = sampling_grid(positions, mask, (H, W), wrap, input.dtype)
    cols = _grid_columns(input, grid, scale, wrap).reshape(B, C * K, Ho, Wo)
    return F.conv2d(cols, weight.reshape(Cout, C * K, 1, 1), bias)


def grid_backward(grad: Tensor, input: Tensor, weight: Tensor, positions: Tensor, mask: Tensor, wrap: bool,
                  input_grad: bool, weight_grad: bool) -> tuple[Tensor, Tensor]:
    """The backward of :func:`grid_forward`: ``grid_sample``'s own input gradient for ``gx``, one product for
    ``gw`` (columns re-sampled)."""
    B, C, H, W = input.shape
    Cout, Ho, Wo, K = weight.shape[0], *positions.shape[:3]
    grid, scale = sampling_grid(positions, mask, (H, W), wrap, input.dtype)
    gx, gw = input.new_empty(0), weight.new_empty(0)
    if weight_grad:
        cols = _grid_columns(input, grid, scale, wrap).reshape(B, C * K, Ho * Wo)
        gw = torch.einsum("bop,bkp->ok", grad.reshape(B, Cout, Ho * Wo), cols).reshape(weight.shape).contiguous()
    if input_grad:
        gcols = torch.einsum("ok,bop->bkp", weight.reshape(Cout, C * K), grad.reshape(B, Cout, Ho * Wo))
        gcols = gcols.reshape(B, C, K * Ho, Wo)
        if scale is not None:
            gcols = gcols * scale
        g = math.gcd(C, SAMPLE_CHANNELS)
        xs = torch.cat([input, input[..., :1]], -1) if wrap else input
        xs = xs.reshape(B * C // g, g, *xs.shape[2:])
        gxs = torch.ops.aten.grid_sampler_2d_backward(
            gcols.reshape(B * C // g, g, K * Ho, Wo), xs, grid.expand(B * C // g, -1, -1, -1), 0, 0, False,
            [True, False])[0].reshape(B, C, H, -1)
        gx = gxs[..., :W].contiguous() if wrap else gxs.contiguous()
        if wrap:
            gx[..., :1] += gxs[..., W:]
    return gx, gw


fixed_offset_conv2d.register_kernel("cuda")(grid_forward)
fixed_offset_conv2d_backward.register_kernel("cuda")(grid_backward)
