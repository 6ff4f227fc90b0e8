"""The CUDA kernel of ``omnidl::fixed_offset_conv2d``: one ``grid_sample`` of every tap into columns and one 1x1
convolution (cuDNN, under ``nn.Conv2d``'s TF32 policy); its backward ``grid_sample``'s own input gradient and one
product. Written in PyTorch operations, so it runs (and is tested) on any device."""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from ._fixed_offset_torch import check_arguments, memory_format, torch_backward


#: channels per ``grid_sample`` image: groups of channels as images of their own give ``grid_sample``, which runs
#: one thread per sample and loops over channels, more threads (the same memory)
SAMPLE_CHANNELS = 8
#: normalised coordinate of a tap that reads zero: far outside ``[-1, 1]``
FAR = -4.0


def sampling_grid(positions: Tensor, mask: Tensor, in_hw: tuple[int, int], wrap: bool,
                  dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``grid (1, K*Ho, Wo, 2)`` of ``grid_sample`` (``align_corners=False``) for the taps - tap ``k`` of output
    ``(i, j)`` at row ``k*Ho + i`` - on the input with one wrapped column appended when ``wrap`` (positions taken
    modulo ``W``: a corner at column ``W`` is column 0), and the mask as ``scale (K*Ho, Wo)``. Built in float64,
    cast once; no value is read back to the host (a CUDA graph can capture it)."""
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
    scale = torch.where(live, m, torch.zeros_like(m)).permute(2, 0, 1).reshape(K * Ho, Wo).to(dtype)
    return grid, scale


def _grid_columns(input: Tensor, grid: Tensor, scale: Tensor, wrap: bool) -> Tensor:
    B, C = input.shape[:2]
    if wrap:
        input = torch.cat([input, input[..., :1]], -1)
    g = math.gcd(C, SAMPLE_CHANNELS)
    xs = input.reshape(B * C // g, g, *input.shape[2:])
    cols = F.grid_sample(xs, grid.expand(B * C // g, -1, -1, -1), mode="bilinear", padding_mode="zeros",
                         align_corners=False).view(B, C, *grid.shape[1:3])
    return cols * scale


def grid_forward(input: Tensor, weight: Tensor, bias: Tensor | None, positions: Tensor, mask: Tensor,
                 wrap: bool) -> Tensor:
    """The CUDA kernel (any device): columns ``(B, C*K, Ho, Wo)`` by one ``grid_sample``, then a 1x1 convolution."""
    check_arguments(input, weight, bias, positions, mask)
    B, C, H, W = input.shape
    Cout, Ho, Wo, K = weight.shape[0], *positions.shape[:3]
    grid, scale = sampling_grid(positions, mask, (H, W), wrap, input.dtype)
    cols = _grid_columns(input, grid, scale, wrap).reshape(B, C * K, Ho, Wo)
    return F.conv2d(cols, weight.reshape(Cout, C * K, 1, 1), bias).contiguous(memory_format=memory_format(input))


def grid_backward(grad: Tensor, input: Tensor, weight: Tensor, positions: Tensor, mask: Tensor, wrap: bool,
                  input_grad: bool, weight_grad: bool) -> tuple[Tensor, Tensor]:
    """The backward of :func:`grid_forward`: ``grid_sample``'s own input gradient for ``gx``, one product for
    ``gw`` (columns re-sampled). ``grid_sample``'s CUDA backward has no deterministic kernel: under
    ``torch.use_deterministic_algorithms`` the PyTorch implementation (``index_add``) runs instead."""
    if input.is_cuda and torch.are_deterministic_algorithms_enabled():
        return torch_backward(grad, input, weight, positions, mask, wrap, input_grad, weight_grad)
    B, C, H, W = input.shape
    Cout, Ho, Wo, K = weight.shape[0], *positions.shape[:3]
    grid, scale = sampling_grid(positions, mask, (H, W), wrap, input.dtype)
    gx, gw = input.new_empty(0), weight.new_empty(0)
    if weight_grad:
        cols = _grid_columns(input, grid, scale, wrap).reshape(B, C * K, Ho * Wo)
        gw = torch.einsum("bop,bkp->ok", grad.reshape(B, Cout, Ho * Wo), cols).reshape(weight.shape).contiguous()
    if input_grad:
        gcols = torch.einsum("ok,bop->bkp", weight.reshape(Cout, C * K), grad.reshape(B, Cout, Ho * Wo))
        gcols = gcols.reshape(B, C, K * Ho, Wo) * scale
        g = math.gcd(C, SAMPLE_CHANNELS)
        xs = torch.cat([input, input[..., :1]], -1) if wrap else input
        xs = xs.reshape(B * C // g, g, *xs.shape[2:])
        gxs = torch.ops.aten.grid_sampler_2d_backward(
            gcols.reshape(B * C // g, g, K * Ho, Wo), xs, grid.expand(B * C // g, -1, -1, -1), 0, 0, False,
            [True, False])[0].reshape(B, C, H, -1)
        gx = (gxs[..., :W] if wrap else gxs).contiguous(memory_format=memory_format(input))
        if wrap:
            gx[..., :1] += gxs[..., W:]
    return gx, gw
