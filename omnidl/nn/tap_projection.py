"""A "same" convolution with few output channels as a per-pixel projection onto its taps, then a shifted sum.

A stride-1 convolution with kernel ``kh x kw`` and weight ``(Cout, C, kh, kw)`` is, for every tap ``k = (a, b)``,
a ``1x1`` product with the slice ``W[:, :, a, b]`` read at the pixel shifted by the tap's offset::

    z = P m            P (Cout*K, C) = the weight with its taps as rows, K = kh*kw     (B, Cout*K, h, w)
    y = sum_k shift_k(z_k) + bias                                                      (B, Cout, H, W)

``P`` acts on each pixel alone, so it commutes with every per-channel linear map of the pixels: bilinear
up-sampling, a weighted sum of maps. FreDSNet's depth branch computes ``conv(sum_i w_i up(m_i))`` with
``C = 128`` and ``Cout = 1``: projected first, the up-sampling and the sum run on ``K = 9`` channels instead of
128, the ``128``-channel full-resolution sum never exists, and the convolution with one output channel (which
oneDNN runs at a few GFLOP/s on the CPU) becomes a ``9 x 128`` matrix product and nine shifted adds.
:func:`pays` says where that is cheaper: ``Cout * K * 2 <= C``.

The shifted sum follows the convolution's padding: a :class:`~omnidl.nn.padding.CircularConv2d` wraps the
columns (longitude) and zero-pads the rows, a zero-padded ``nn.Conv2d`` zero-pads both. Results equal the
convolution up to float rounding (the sums run in another order); gradients flow to the maps and to the
weight through ``P``.
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn as nn
from torch import Tensor

from . import native
from .capture import capturing
from .fusion import can_block
from .padding import CircularConv2d
from .sampling import _is_channels_last

#: project first where ``Cout * kh * kw * PROJECTION_RATIO <= in_channels``
PROJECTION_RATIO = 2
#: ``False``: :func:`pays` always says no (benchmarks' in-process A/B)
ENABLED = True
#: ``False``: :func:`project` multiplies on PyTorch's ``bmm`` always (benchmarks' in-process A/B)
NATIVE_PRODUCTS = True
#: the most projected channels (``Cout * K``) the native products take (the few-column kernel's rows form)
NATIVE_MAX_TAPS = 11

_Offsets = tuple[tuple[int, int], ...]


def tap_offsets(conv: nn.Conv2d) -> _Offsets | None:
    """``(dy, dx)`` of each tap of a stride-1 "same" convolution without groups, in the order of
    :func:`projection_matrix`'s rows; ``None`` for any other convolution (strided, grouped, not "same", another
    class such as ``ProjectedConv2d``, a padding mode other than zeros: :func:`omnidl.nn.fusion.can_block`'s rule)."""
    if not can_block(conv) or conv.groups != 1:
        return None
    pad = conv.wrap_padding if isinstance(conv, CircularConv2d) else conv.padding
    (kh, kw), (dh, dw) = conv.kernel_size, conv.dilation
    return tuple((a * dh - pad[0], b * dw - pad[1]) for a in range(kh) for b in range(kw))


def pays(conv: nn.Module, in_channels: int | None = None) -> bool:
    """Whether projecting onto ``conv``'s taps is cheaper than convolving a map with ``in_channels`` channels
    (default the convolution's own): a convolution :func:`tap_offsets` accepts, with
    ``Cout * kh * kw * PROJECTION_RATIO <= in_channels``."""
    offsets = tap_offsets(conv) if ENABLED else None   # type: ignore[arg-type]
    if offsets is None:
        return False
    c = conv.in_channels if in_channels is None else in_channels
    return conv.out_channels * len(offsets) * PROJECTION_RATIO <= c


def projection_matrix(weight: Tensor) -> Tensor:
    """``(Cout, C, kh, kw)`` -> ``P (Cout*kh*kw, C)``: row ``o*K + a*kw + b`` is ``weight[o, :, a, b]``."""
    cout, c, kh, kw = weight.shape
    return weight.permute(0, 2, 3, 1).reshape(cout * kh * kw, c)


def project(conv: nn.Conv2d, m: Tensor) -> Tensor:
    """``z = P m``: ``m (B, C, h, w)`` -> ``(B, Cout*K, h, w)`` in ``m``'s memory format (a channels-last map is
    read in place as ``(B, h*w, C)`` rows)."""
    P = projection_matrix(conv.weight)
    B, C, h, w = m.shape
    if _is_channels_last(m):
        return (m.permute(0, 2, 3, 1).reshape(B, h * w, C) @ P.t()).view(B, h, w, -1).permute(0, 3, 1, 2)
    if _native(P, m):
        return _Projection.apply(P, m)
    # bmm, not matmul: matmul folds (Cout*K, C) @ (B, C, h*w) into one product with the map transposed, which
    # MKL runs 3x slower (depth branch at 256x128: 27-29 against 8.5-10 ms forward + backward)
    return torch.bmm(P.expand(B, -1, -1), m.reshape(B, C, h * w)).view(B, -1, h, w)


def _native(P: Tensor, m: Tensor) -> bool:
    """Whether :class:`_Projection` computes ``P m``: float32 CPU, ``m`` contiguous (NCHW), at most
    :data:`NATIVE_MAX_TAPS` rows of ``P``, the native library built, not captured."""
    return (NATIVE_PRODUCTS and P.dtype == m.dtype == torch.float32 and P.device.type == m.device.type == "cpu"
            and m.is_contiguous() and 0 < P.shape[0] <= NATIVE_MAX_TAPS and m.numel() > 0 and not capturing()
            and native.library() is not None)


def _check(rc: int, what: str) -> None:
    if rc == 1:
        raise MemoryError(f"omnidl tap projection: the native {what} could not allocate its buffers")
    if rc:
        raise RuntimeError(f"omnidl tap projection: the native {what} returned {rc}")


class _Projection(torch.autograd.Function):
    """``z = P m`` per image: ``P (R, C)``, ``m (B, C, h, w)`` contiguous -> ``z (B, R, h, w)``, on omnidl's
    kernels (:mod:`omnidl.nn.native`). Few rows (a depth head's 9 taps) against a long map run well below MKL's peak
    (9 x 128 by 128 x 32768, 2 threads: 3.5 ms from memory); here ``z`` is ``(m^T P^T)^T``, the few-column kernel's
    columns form (``omnidl_gemm_narrow``, 1.1 ms), the weight gradient ``(m gz^T)^T`` its rows form (1.1 against
    2.0 ms), the map's gradient ``P^T gz`` the register kernel (``omnidl_gemm``, 0.7 against 1.8 ms). Under
    ``create_graph`` the backward is autograd's over ``bmm`` (differentiable again)."""

    @staticmethod
    def forward(ctx, P: Tensor, m: Tensor) -> Tensor:   # type: ignore[override]
        lib, threads = native.library(), max(1, torch.get_num_threads())
        B, C, h, w = m.shape
        R, n = P.shape[0], h * w
        p = P.detach().contiguous()
        zt = m.new_empty(B, n, R)
        for b in range(B):           # (n, R) = m[b]^T (n, C) @ p^T (C, R)
            _check(lib.omnidl_gemm_narrow(n, R, C, m[b].data_ptr(), 1, n, p.data_ptr(), 1, C, zt[b].data_ptr(), R,
                                          0, threads), "projection")
        ctx.save_for_backward(P, m)
        return zt.transpose(1, 2).contiguous().view(B, R, h, w)

    @staticmethod
    def backward(ctx, gz: Tensor) -> tuple[Tensor | None, Tensor | None]:   # type: ignore[override]
        P, m = ctx.saved_tensors
        need_p, need_m = ctx.needs_input_grad
        B, C, h, w = m.shape
        R, n = P.shape[0], h * w
        if torch.is_grad_enabled():                       # create_graph: a differentiable backward
            with torch.enable_grad():
                z = torch.bmm(P.expand(B, -1, -1), m.reshape(B, C, n))
                inputs = [t for t, need in ((P, need_p), (m, need_m)) if need]
                grads = iter(torch.autograd.grad(z, inputs, gz.reshape(B, R, n), create_graph=True))
            return (next(grads) if need_p else None, next(grads) if need_m else None)
        lib, threads = native.library(), max(1, torch.get_num_threads())
        g = gz.contiguous()
        gp = gm = None
        if need_p:
            gpt = m.new_empty(C, R)
            for b in range(B):       # (C, R) (+)= m[b] (C, n) @ g[b]^T (n, R)
                _check(lib.omnidl_gemm_narrow(C, R, n, m[b].data_ptr(), n, 1, g[b].data_ptr(), 1, n,
                                              gpt.data_ptr(), R, int(b > 0), threads), "weight gradient")
            gp = gpt.t()
        if need_m:
            p = P.detach().contiguous()
            gm = torch.empty_like(m)
            for b in range(B):       # (C, n) = p^T (C, R) @ g[b] (R, n); a build without the register kernel: mm
                rc = lib.omnidl_gemm(C, n, R, p.data_ptr(), 1, C, g[b].data_ptr(), n, 1, gm[b].data_ptr(), n, 0,
                                     threads)
                if rc == 2:
                    torch.mm(p.t(), g[b].view(R, n), out=gm[b].view(C, n))
                else:
                    _check(rc, "map gradient")
        return gp, gm


def shift_sum(conv: nn.Conv2d, z: Tensor) -> Tensor:
    """``conv``'s output from the projected taps ``z (B, Cout*K, H, W)`` (:func:`project` of its input, or any
    per-pixel linear map of such projections): ``(B, Cout, H, W)``, bias added."""
    offsets = tap_offsets(conv)
    if offsets is None:
        raise ValueError(f"shift_sum: {conv!r} is not a stride-1 'same' convolution without groups")
    B, n, H, W = z.shape
    if n != conv.out_channels * len(offsets):
        raise ValueError(f"shift_sum: expected {conv.out_channels} x {len(offsets)} projected channels, got {n}")
    y = _ShiftSum.apply(z.unflatten(1, (conv.out_channels, len(offsets))), offsets,
                        isinstance(conv, CircularConv2d))
    return y if conv.bias is None else y + conv.bias.view(1, -1, 1, 1)


class _ShiftSum(torch.autograd.Function):
    """``y[b, o, i, j] = sum_k z[b, o, k, i + dy_k, j + dx_k]``; rows outside are zero, columns wrap (``wrap``)
    or are zero. ``z (B, Cout, K, H, W)`` -> ``y (B, Cout, H, W)``; the backward scatters ``gy`` the other way."""

    @staticmethod
    def forward(ctx, z: Tensor, offsets: _Offsets, wrap: bool) -> Tensor:   # type: ignore[override]
        ctx.offsets, ctx.wrap = offsets, wrap
        B, O, _, H, W = z.shape
        y = z.new_zeros(B, O, H, W)
        for k, dst, src in _segments(offsets, H, W, wrap):
            y[:, :, dst[0], dst[1]] += z[:, :, k, src[0], src[1]]
        return y

    @staticmethod
    def backward(ctx, gy: Tensor) -> tuple[Tensor, None, None]:   # type: ignore[override]
        B, O, H, W = gy.shape
        gz = gy.new_zeros(B, O, len(ctx.offsets), H, W)
        for k, dst, src in _segments(ctx.offsets, H, W, ctx.wrap):
            gz[:, :, k, src[0], src[1]] += gy[:, :, dst[0], dst[1]]
        return gz, None, None


def _segments(offsets: Sequence[tuple[int, int]], H: int, W: int, wrap: bool):
    """``(k, (dst rows, dst cols), (src rows, src cols))`` slices: output pixel ``(i, j)`` reads tap ``k`` at
    ``(i + dy, j + dx)`` (the column modulo ``W`` when ``wrap``); pixels whose source is outside are left out."""
    for k, (dy, dx) in enumerate(offsets):
        i0, i1 = max(0, -dy), min(H, H - dy)
        if i1 <= i0:
            continue
        rows = (slice(i0, i1), slice(i0 + dy, i1 + dy))
        if wrap:
            s = dx % W
            cols = [(0, W - s, s), (W - s, W, s - W)] if s else [(0, W, 0)]
        else:
            cols = [(max(0, -dx), min(W, W - dx), dx)]
        for j0, j1, d in cols:
            if j1 > j0:
                yield k, (rows[0], slice(j0, j1)), (rows[1], slice(j0 + d, j1 + d))


__all__ = ["PROJECTION_RATIO", "tap_offsets", "pays", "projection_matrix", "project", "shift_sum"]
