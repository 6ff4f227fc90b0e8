"""Weighted sums of bilinearly up-sampled maps, evaluated by row blocks (FreDSNet's task branches).

A FreDSNet branch computes ``conv(sum_i w_i up(m_i))`` where every ``m_i (B, C, h_i, w_i)`` is
up-sampled (bilinear, ``align_corners=True``) to the size ``(H, W)`` of the largest map. Done
literally, every term writes a full-resolution map twice (the up-sampled map, then the running sum):
at 512x256 with 128 channels that is 67 MB per buffer, and on CPU the memory traffic and the page
faults of such buffers cost more than the arithmetic.

Bilinear up-sampling is separable, ``up(m) = A_h m A_w^T``. :class:`UpsampleSum` resizes each map
along the width only (``h_i`` rows instead of ``H``); any block of output rows is then one small
matrix product per map with the block's rows of its ``(H, h_i)`` interpolation matrix, restricted to
the input rows they touch. :func:`blocked_conv` runs a "same" stride-1 convolution over such a
row-addressable map block by block (with a halo), so the full-resolution sum never exists at once.
Results equal ``F.interpolate`` + sum (+ conv) up to float rounding; gradients flow to the maps,
the weights and the convolution.
"""
from __future__ import annotations

import ctypes
import functools
from typing import Callable, NamedTuple, Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from . import native, thin_layout
from .capture import capturing
from .padding import CircularConv2d, pad_panorama, wrapped_conv2d

#: ``f(a, b) -> (B, C, b - a, W)``: rows ``a:b`` of a full-size map, computed on demand
RowSource = Callable[[int, int], Tensor]


class RowMap(NamedTuple):
    """A map of any size given by its rows: ``rows(a, b) -> (B, C, b - a, width)`` for ``0 <= a < b <= height``.

    :class:`UpsampleSum` then reads only the source rows each output block needs, so that a map that is itself
    large (FreDSNet's 128-channel branch map at half the output size, 64 MB at 1024x512) never exists at once."""
    rows: RowSource
    height: int
    width: int


#: bytes of one row block of the full-resolution sum (fits in a core's L2 cache on current CPUs)
BLOCK_BYTES = 4 << 20

#: fewest output rows of a block. Each block recomputes ``2 * pad`` halo rows of the sum and of the
#: convolution, and pays per-call costs: with a floor of 8 rows a 1024-wide, 128-channel map got 8-row blocks
#: (25 % halo, 64 blocks) against 16-row blocks at 512 wide (12.5 %, 16 blocks), which made the branch cost
#: grow faster than the pixels (x4.3-4.7 for x4, 1 thread). 16 rows keep the halo share fixed for widths >= 512.
MIN_BLOCK_ROWS = 16


def interpolation_matrix(n_out: int, n_in: int, *, dtype: torch.dtype = torch.float32,
                         device: torch.device | str | None = None) -> Tensor:
    """``(n_out, n_in)`` matrix of 1-D linear interpolation with ``align_corners=True``.

    Row ``r`` samples position ``r (n_in - 1) / (n_out - 1)`` of the input: weight ``1 - f`` on
    ``floor`` and ``f`` on the next sample (``F.interpolate``'s rule).
    """
    args = (int(n_out), int(n_in), dtype, torch.device(device) if device is not None else torch.device("cpu"))
    return _build_matrix(*args) if capturing() else _cached_matrix(*args)


def _build_matrix(n_out: int, n_in: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    i0, i1, f = _linear_taps(n_out, n_in)
    A = torch.zeros(n_out, n_in, dtype=torch.float64)
    rows = torch.arange(n_out)
    A.index_put_((rows, i0), 1.0 - f, accumulate=True)
    A.index_put_((rows, i1), f, accumulate=True)
    return A.to(dtype=dtype, device=device)


#: :func:`interpolation_matrix` built once per size, dtype and device (a CUDA network then copies nothing from the
#: host per call, and a CUDA graph can capture it); callers never write it. Not while tracing (fake tensors).
_cached_matrix = functools.lru_cache(maxsize=64)(_build_matrix)


@functools.lru_cache(maxsize=64)
def _tap_rows(n_out: int, n_in: int) -> tuple[list[int], list[int]]:
    """The first and last input row (``i0``, ``i1``) that each output row of :func:`interpolation_matrix` reads."""
    i0, i1, _ = _linear_taps(n_out, n_in)
    return i0.tolist(), i1.tolist()


def _linear_taps(n_out: int, n_in: int) -> tuple[Tensor, Tensor, Tensor]:
    """``(i0, i1, f)`` of :func:`interpolation_matrix`: output ``r`` reads inputs ``i0[r]``, ``i1[r]`` (int64) with
    weights ``1 - f[r]``, ``f[r]`` (float64)."""
    if n_out < 1 or n_in < 1:
        raise ValueError(f"interpolation_matrix: sizes must be >= 1, got {n_out} x {n_in}")
    scale = (n_in - 1) / (n_out - 1) if n_out > 1 else 0.0
    src = torch.arange(n_out, dtype=torch.float64) * scale
    i0 = src.floor().long().clamp(max=n_in - 1)
    return i0, (i0 + 1).clamp(max=n_in - 1), src - i0


class UpsampleSum:
    """``S = sum_i w_i * F.interpolate(m_i, (H, W), mode="bilinear", align_corners=True)``, by rows.

    Args:
        maps: ``(B, C, h_i, w_i)`` tensors with the same ``B, C``, dtype and device (contiguous or
            channels-last; blocks come back in the memory format of the first one). A full-size map may
            instead be a *row source*, a callable ``f(a, b) -> (B, C, b - a, W)`` giving its rows ``a:b``, and a
            map of any size a :class:`RowMap`, so that it too is only ever materialised block by block (``size`` is
            then required; at least one map must be a tensor). Adjacent blocks of an up-sampled row map share a
            source row or two, which are computed for each.
        weights: one per map: a scalar tensor (``()`` or ``(1,)``, may require grad), a number, or
            ``None`` for 1.
        size: ``(H, W)``; default the size of the largest map.

    ``rows(a, b)`` returns ``S[:, :, a:b]`` as ``(B, C, b - a, W)``; ``full()`` is ``rows(0, H)``.
    """

    def __init__(self, maps: Sequence[Tensor | RowSource | RowMap], weights: Sequence[Tensor | float | None],
                 size: tuple[int, int] | None = None) -> None:
        if not maps or len(maps) != len(weights):
            raise ValueError(f"UpsampleSum: need one weight per map, got {len(maps)} maps, {len(weights)} weights")
        tensors = [m for m in maps if isinstance(m, Tensor)]
        if not tensors or (size is None and len(tensors) < len(maps)):
            raise ValueError("UpsampleSum: need at least one tensor map, and `size` when some maps are row sources")
        B, C = tensors[0].shape[:2]
        if any(m.dim() != 4 or m.shape[:2] != (B, C) for m in tensors):
            raise ValueError(f"UpsampleSum: maps must be (B, C, h, w) with the same B, C; got "
                             f"{[tuple(m.shape) for m in tensors]}")
        H, W = size if size is not None else max((tuple(m.shape[-2:]) for m in maps), key=lambda s: s[0] * s[1])
        self.shape = (B, C, int(H), int(W))
        self.channels_last = tensors[0].is_contiguous(memory_format=torch.channels_last) and C > 1
        self.flat_batch = B if self.channels_last else B * C       # leading size of the flat maps (:meth:`_flat`)
        # (rows (N, h, L) or a row source, matrix (H, h) or None at full size, weight, width)
        self.terms: list[tuple] = []
        for m, w in zip(maps, weights):
            if isinstance(m, RowMap):                     # rows of a map of any size, evaluated per block
                if m.height < 1 or m.width < 1:
                    raise ValueError(f"UpsampleSum: a row map needs a size of at least 1x1, got "
                                     f"{m.height}x{m.width}")
                A = None if m.height == H else interpolation_matrix(H, m.height, dtype=tensors[0].dtype,
                                                                    device=tensors[0].device)
                self.terms.append((m.rows, A, w, m.width))
                continue
            if not isinstance(m, Tensor):                 # full-size row source, evaluated per block
                self.terms.append((m, None, w, W))
                continue
            h = m.shape[-2]
            if m.shape[-1] != W and (h == H or m.numel() * W // m.shape[-1] * m.element_size() <= 2 * BLOCK_BYTES):
                # width pass now (only h rows, a small buffer); larger maps get it per block in rows()
                m = F.interpolate(m, size=(h, W), mode="bilinear", align_corners=True)
            A = None if h == H else interpolation_matrix(H, h, dtype=m.dtype, device=m.device)
            self.terms.append((self._flat(m), A, w, m.shape[-1]))

    def _flat(self, m: Tensor) -> Tensor:
        """``(B, C, h, w)`` -> ``(B, h, w*C)`` (channels-last, a view) or ``(B*C, h, w)``."""
        B, C, h, w = m.shape
        return m.permute(0, 2, 3, 1).reshape(B, h, w * C) if self.channels_last else m.reshape(B * C, h, w)

    def _unflat(self, flat: Tensor) -> Tensor:
        """Inverse of :meth:`_flat`."""
        B, C = self.shape[:2]
        if self.channels_last:
            return flat.view(B, flat.shape[1], flat.shape[2] // C, C).permute(0, 3, 1, 2)
        return flat.view(B, C, flat.shape[1], flat.shape[2])

    def rows(self, a: int, b: int) -> Tensor:
        """Rows ``a:b`` of the sum: ``(B, C, b - a, W)``.

        The running sum is a buffer of this call's own, updated in place (no backward needs the outputs
        of the products and sums that write it, so this is autograd-safe).
        """
        W = self.shape[3]
        acc = None
        for flat, A, w, width in self.terms:
            fresh = False                                 # term is a buffer of this call's own
            if A is None:                                 # a full-size map: its rows
                term = _rows_of(flat, a, b) if isinstance(flat, Tensor) else self._flat(flat(a, b))
                if width != W:
                    term, w, fresh = self._flat(F.interpolate(self._unflat(term), size=(b - a, W), mode="bilinear",
                                                              align_corners=True)), w, True
            else:                                         # height pass on the rows it needs
                i0, i1 = _tap_rows(*A.shape)              # the source rows a:b read (no device sync)
                lo, hi = i0[a], i1[b - 1] + 1
                block = A[a:b, lo:hi] if w is None else A[a:b, lo:hi] * w
                src = _rows_of(flat, lo, hi) if isinstance(flat, Tensor) else self._flat(flat(lo, hi))
                block = block.to(src.dtype).expand(self.flat_batch, -1, -1)   # maps of another dtype (autocast)
                if width == W:
                    acc = (torch.bmm(block, src) if acc is None
                           else acc.baddbmm_(block.to(acc.dtype), src.to(acc.dtype)))
                    continue
                term = F.interpolate(self._unflat(torch.bmm(block, src)), size=(b - a, W),
                                     mode="bilinear", align_corners=True)     # deferred width pass
                term, w, fresh = self._flat(term), None, True                 # (weight already applied)
            if acc is None:
                acc = (term if fresh else term.clone()) if w is None else term * w
            elif isinstance(w, Tensor):
                acc.addcmul_(term, w)
            else:
                acc.add_(term, alpha=1.0 if w is None else float(w))
        assert acc is not None
        return self._unflat(acc)

    def full(self) -> Tensor:
        """The whole sum ``(B, C, H, W)``."""
        return self.rows(0, self.shape[2])


def _rows_of(flat: Tensor, a: int, b: int) -> Tensor:
    """``flat[:, a:b]``, or ``flat`` itself for all rows (a slice's backward writes a zero-filled copy)."""
    return flat if (a, b) == (0, flat.shape[1]) else flat[:, a:b]


def upsample_sum(maps: Sequence[Tensor], weights: Sequence[Tensor | float | None],
                 size: tuple[int, int] | None = None, wrap: int = 0) -> Tensor:
    """``sum_i w_i * F.interpolate(m_i, size, mode="bilinear", align_corners=True)`` (see :class:`UpsampleSum`).

    ``wrap > 0``: the sum with the panorama's horizontal wrap, ``wrap`` columns each side (the last ``wrap`` columns
    first, the first ``wrap`` last), in channels-last memory: ``(B, C, H, wrap + W + wrap)``, the input a thin
    wrapped convolution takes (:meth:`omnidl.nn.padding.CircularConv2d.channels_last_wrap`).

    For contiguous float32 CPU maps with the native library built (:func:`native_applies`) the sum is one native
    pass (``csrc/upsample.c``) that writes each output value once, in either layout. Under autograd its backward is
    the adjoint of each up-sampling: ``r_i = A_h^T g A_w`` once per map, from which the map's gradient is ``w_i r_i``
    and the weight's ``<r_i, m_i>``. Autograd's own backward of the row-block products computes the gradient of each
    map's whole expanded interpolation matrix just to reduce it to the scalar weight's (the backward of FreDSNet's
    semantic-branch sum at 256x128: about 15 against 41 ms)."""
    if wrap < 0:
        raise ValueError(f"upsample_sum: wrap must be >= 0 columns, got {wrap}")
    if maps and size is None:
        size = max((tuple(m.shape[-2:]) for m in maps), key=lambda s: s[0] * s[1])
    if native_applies(maps, weights) and wrap <= size[1]:
        H, W = int(size[0]), int(size[1])
        recorded = torch.is_grad_enabled() and any(t.requires_grad for t in [*maps, *weights] if isinstance(t, Tensor))
        if not recorded:
            return _native_sum(maps, weights, (H, W), wrap)
        if ADJOINT_BACKWARD:
            return _UpsampleSumFunction.apply((H, W), int(wrap), len(maps), *maps, *weights)
    total = UpsampleSum(maps, weights, size).full()
    return pad_panorama(total, wrap).contiguous(memory_format=torch.channels_last) if wrap else total


#: ``False``: autograd's own backward for :func:`upsample_sum` (benchmarks' in-process A/B)
ADJOINT_BACKWARD = True
#: ``False``: :func:`upsample_sum` never takes the native pass (benchmarks' in-process A/B)
NATIVE_SUM = True


def native_applies(maps: Sequence, weights: Sequence) -> bool:
    """Whether :func:`upsample_sum` runs natively: contiguous float32 CPU maps ``(B, C, h, w)`` with the same
    ``B, C``, one weight each (``None``, a number or a one-value CPU tensor), the native library built, not captured
    by ``torch.compile``/export."""
    if not (NATIVE_SUM and maps and len(maps) == len(weights)):
        return False
    if not all(isinstance(m, Tensor) for m in maps) or capturing():
        return False
    B, C = maps[0].shape[:2]
    return (all(m.dim() == 4 and m.shape[:2] == (B, C) and m.dtype == torch.float32 and m.device.type == "cpu"
                and m.is_contiguous() and m.numel() > 0 for m in maps)
            and native.library() is not None
            and all(w is None or not isinstance(w, Tensor) or (w.numel() == 1 and w.device.type == "cpu")
                    for w in weights))


@functools.lru_cache(maxsize=256)
def _taps32(n_out: int, n_in: int) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_linear_taps` with float32 weights (kept: the tables are read only)."""
    i0, i1, f = _linear_taps(n_out, n_in)
    return i0, i1, f.float()


def _native_sum(maps: Sequence[Tensor], weights: Sequence[Tensor | float | None], size: tuple[int, int],
                wrap: int) -> Tensor:
    """The sum of :func:`upsample_sum` in one native pass (where :func:`native_applies`), without autograd."""
    B, C = maps[0].shape[:2]
    H, W = size
    rows = [_taps32(H, m.shape[-2]) for m in maps]
    cols = [_taps32(W, m.shape[-1]) for m in maps]
    ri0, ri1, rf = (torch.cat([t[k] for t in rows]) for k in range(3))
    ci0, ci1, cf = (torch.cat([t[k] for t in cols]) for k in range(3))
    hs = torch.tensor([m.shape[-2] for m in maps], dtype=torch.int64)
    ws = torch.tensor([m.shape[-1] for m in maps], dtype=torch.int64)
    wts = torch.tensor([1.0 if w is None else float(w) for w in weights], dtype=torch.float32)
    ptrs = (ctypes.c_void_p * len(maps))(*[m.data_ptr() for m in maps])
    if wrap:
        out = torch.empty((B, C, H, W + 2 * wrap), dtype=torch.float32, memory_format=torch.channels_last)
    else:
        out = torch.empty((B, C, H, W), dtype=torch.float32)
    rc = native.library().omnidl_upsample_sum(
        ptrs, len(maps), hs.data_ptr(), ws.data_ptr(), wts.data_ptr(), B, C, H, W, ri0.data_ptr(), ri1.data_ptr(),
        rf.data_ptr(), ci0.data_ptr(), ci1.data_ptr(), cf.data_ptr(), int(bool(wrap)), wrap, wrap, out.data_ptr(),
        max(1, torch.get_num_threads()))
    if rc:
        raise MemoryError(f"omnidl up-sampled sum: could not allocate its {C}x{W} scratch row")
    return out


class _UpsampleSumFunction(torch.autograd.Function):
    """:func:`_native_sum` of ``maps`` then ``weights`` (``args``); the backward by the adjoint of each map's
    up-sampling."""

    @staticmethod
    def forward(ctx, size: tuple[int, int], wrap: int, n: int, *args):   # type: ignore[override]
        maps, weights = args[:n], args[n:]
        ctx.size, ctx.wrap, ctx.n = size, wrap, n
        ctx.numbers = [None if isinstance(w, Tensor) else (1.0 if w is None else float(w)) for w in weights]
        ctx.save_for_backward(*maps, *[w for w in weights if isinstance(w, Tensor)])
        return _native_sum(maps, weights, size, wrap)

    @staticmethod
    def backward(ctx, g: Tensor):   # type: ignore[override]
        n, saved = ctx.n, ctx.saved_tensors
        maps, tensor_weights = saved[:n], iter(saved[n:])
        need = ctx.needs_input_grad
        given = g
        if ctx.wrap:      # the adjoint of the wrap and of the layout change first: (B, C, H, W) contiguous
            g = thin_layout.wrap_adjoint(g, ctx.wrap, ctx.wrap)
        g = g.contiguous()
        # a lone full-size map's gradient w * g is written into g itself once nothing else reads it, when g is this
        # backward's own buffer (a fresh full-size product page-faulted 16.8 MB: up to 28 ms at 128x256 and 128
        # channels, against about 2 ms in place)
        full = [i for i, m in enumerate(maps) if m.shape[-2:] == tuple(ctx.size)]
        in_place = g is not given and len(full) == 1 and not torch.is_grad_enabled()
        grads_m: list[Tensor | None] = []
        grads_w: list[Tensor | None] = []
        last = None
        for i, (m, number) in enumerate(zip(maps, ctx.numbers)):
            w = next(tensor_weights) if number is None else number
            need_m, need_w = need[3 + i], isinstance(w, Tensor) and need[3 + n + i]
            r = None
            if need_m or need_w:
                if i in full:
                    r = g
                elif torch.is_grad_enabled():              # create_graph: PyTorch's adjoint, differentiable
                    r = torch.ops.aten.upsample_bilinear2d_backward(g, list(ctx.size), list(m.shape), True)
                else:
                    r = _adjoint(g, m.shape[-2], m.shape[-1])
            grads_w.append(torch.dot(r.reshape(-1), m.reshape(-1)).reshape(w.shape) if need_w else None)
            scale = w.reshape(()) if isinstance(w, Tensor) else w
            if need_m and in_place and i in full and not (number == 1.0):
                grads_m.append(None)
                last = (i, scale)                          # after every other map has read g
            else:
                grads_m.append(None if not need_m else r if number == 1.0 else r * scale)
        if last is not None:
            grads_m[last[0]] = g.mul_(last[1])
        return (None, None, None, *grads_m, *grads_w)


def _adjoint(g: Tensor, h: int, w: int) -> Tensor:
    """``A_h^T g A_w``: ``g (B, C, H, W)`` (contiguous float32) -> ``(B, C, h, w)``, the adjoint of bilinear
    ``align_corners=True`` up-sampling from ``(h, w)`` (``csrc/upsample.c``)."""
    B, C, H, W = g.shape
    rows, cols = _linear_taps(H, h), _linear_taps(W, w)
    ri0, ri1, rf = rows[0], rows[1], rows[2].float()
    ci0, ci1, cf = cols[0], cols[1], cols[2].float()
    r = g.new_empty(B, C, h, w)
    err = native.library().omnidl_upsample_adjoint(
        g.data_ptr(), B * C, H, W, h, w, ri0.data_ptr(), ri1.data_ptr(), rf.data_ptr(), ci0.data_ptr(),
        ci1.data_ptr(), cf.data_ptr(), r.data_ptr(), max(1, torch.get_num_threads()))
    if err:
        raise MemoryError(f"omnidl up-sampling adjoint: could not allocate its {h}x{W} scratch rows")
    return r


def can_block(conv: nn.Module) -> bool:
    """Whether :func:`blocked_conv` can run ``conv``: a stride-1, "same" ``nn.Conv2d`` with zero padding or a
    :class:`CircularConv2d` (position-dependent convolutions such as ``ProjectedConv2d`` cannot)."""
    if type(conv) not in (nn.Conv2d, CircularConv2d) or conv.stride != (1, 1) or conv.padding_mode != "zeros":
        return False
    pad = conv.wrap_padding if isinstance(conv, CircularConv2d) else conv.padding
    if isinstance(pad, str):
        return False
    return all(2 * p == d * (k - 1) for p, d, k in zip(pad, conv.dilation, conv.kernel_size))


def blocked_conv(conv: nn.Module, rows: Callable[[int, int], Tensor], height: int, block_rows: int) -> Tensor:
    """``conv(X)`` for a map ``X`` that is only ever materialised as row blocks ``rows(a, b) (B, C, b - a, W)``.

    Each block is computed with the ``pad_h`` halo rows the convolution needs and convolved with the
    convolution's own vertical zero padding: exact at the image's top and bottom; elsewhere only the halo
    rows' outputs see those zeros, and they are dropped. The output blocks are concatenated:
    ``(B, C_out, height, W)``.
    ``conv`` must satisfy :func:`can_block`.
    """
    if not can_block(conv):
        raise ValueError(f"blocked_conv: {conv!r} is not a stride-1 'same' convolution")
    ph, pw = conv.wrap_padding if isinstance(conv, CircularConv2d) else conv.padding
    out = []
    for r0 in range(0, height, block_rows):
        r1 = min(height, r0 + block_rows)
        a, b = max(0, r0 - ph), min(height, r1 + ph)
        x = rows(a, b)
        if isinstance(conv, CircularConv2d) and pw and not torch.is_grad_enabled() and x.shape[-1] >= 4 * pw:
            y = wrapped_conv2d(x, conv.weight, conv.bias, (ph, pw), conv.dilation, conv.groups)   # no padded copy
        else:
            y = conv(x)
        out.append(y if (a, b) == (r0, r1) else y[:, :, r0 - a:r1 - a])
    return torch.cat(out, dim=2) if len(out) > 1 else out[0]


def rows_per_block(batch: int, channels: int, width: int, element_size: int = 4) -> int:
    """Rows of a ``(batch, channels, rows, width)`` block of about :data:`BLOCK_BYTES`, at least
    :data:`MIN_BLOCK_ROWS`."""
    return max(MIN_BLOCK_ROWS, BLOCK_BYTES // max(1, batch * channels * width * element_size))


__all__ = ["interpolation_matrix", "RowMap", "UpsampleSum", "upsample_sum", "can_block", "blocked_conv",
           "rows_per_block"]
