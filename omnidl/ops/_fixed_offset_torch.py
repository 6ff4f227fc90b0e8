"""The PyTorch implementation of ``omnidl::fixed_offset_conv2d`` (any device, any floating dtype): the kernel of
devices without one of their own, the CPU's for dtypes other than float32, and the reference the other kernels are
tested against (together with torchvision's ``deform_conv2d``)."""
from __future__ import annotations

import torch
from torch import Tensor


def memory_format(input: Tensor) -> torch.memory_format:
    """The layout of the op's output and input gradient: channels-last for a channels-last input (as PyTorch's
    convolutions), else contiguous."""
    channels_last = input.shape[1] > 1 and input.is_contiguous(memory_format=torch.channels_last)
    return torch.channels_last if channels_last and not input.is_contiguous() else torch.contiguous_format


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


#: a coordinate this far from 0 (or not finite) reads zero: no position (the C kernel's FAR_COORD)
FAR_COORD = 4.5e15
#: tap rows per chunk of the PyTorch implementation (bounds its column buffer: rows x C per image)
CHUNK_ROWS = 1 << 16


def corners(positions: Tensor, mask: Tensor, in_hw: tuple[int, int], wrap: bool) -> tuple[Tensor, Tensor]:
    """The bilinear corners of every tap (float64 arithmetic): ``idx (N, 4)`` flat input pixels (int64) and
    ``coeff (N, 4)`` float64 weights, ``N = Ho * Wo * K``; ``coeff = 0`` where a corner reads zero (outside the
    image, a zero mask, a non-finite or absurdly far position) - the rule of the C kernel and of ``deform_conv2d``."""
    H, W = in_hw
    pos = positions.reshape(-1, 2).double()
    m = mask.reshape(-1, 1).double()
    finite = (pos.abs() < FAR_COORD).all(1, keepdim=True) & torch.isfinite(m)
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
    return out.reshape(B, Ho, Wo, Cout).permute(0, 3, 1, 2).contiguous(memory_format=memory_format(input))


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
        gx = gx.reshape(B, H, W, C).permute(0, 3, 1, 2).contiguous(memory_format=memory_format(input))
    gw = gwm.reshape(kh, kw, C, Cout).permute(3, 2, 0, 1).contiguous() if weight_grad else weight.new_empty(0)
    return gx, gw
