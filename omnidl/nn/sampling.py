"""Where the taps of a fixed-offset convolution sample its input, and the torchvision reference.

A fixed-offset convolution is ``torchvision.ops.deform_conv2d`` with one set of offsets (and mask) for the whole
batch: tap ``t = i * kw + j`` of output position ``(oy, ox)`` samples the input at::

    y = oy * stride_h - pad_h + i * dil_h + offsets[0, 2t, oy, ox]
    x = ox * stride_w - pad_w + j * dil_w + offsets[0, 2t + 1, oy, ox]

:func:`sample_positions` turns offsets in deform_conv2d's layout ``(1, 2K, Ho, Wo)`` into these absolute
positions, ``(Ho, Wo, K, 2)`` as ``(y, x)``, and the mask ``(1, K, Ho, Wo)`` into ``(Ho, Wo, K)``: the arguments of
the op :func:`omnidl.ops.fixed_offset_conv2d`. :func:`deform_conv2d_reference` runs torchvision's op with the same
offsets (the input tiled three times for a horizontal wrap): the reference the op is tested against, and the
backend of :class:`~omnidl.nn.ProjectedConv2d` for grouped convolutions.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .offsets import Pair, output_size


def sample_positions(offsets: Tensor, mask: Tensor | None, in_hw: Pair, kernel_size: Pair, stride: Pair,
                     padding: Pair, dilation: Pair) -> tuple[Tensor, Tensor]:
    """``(positions (Ho, Wo, K, 2), mask (Ho, Wo, K))`` of deform_conv2d ``offsets (1, 2K, Ho, Wo)`` and ``mask
    (1, K, Ho, Wo)`` (``None``: every tap 1), in the offsets' dtype and device: the absolute input position
    ``(y, x)`` (pixel indices) each tap samples, and its weight."""
    kh, kw = kernel_size
    K = kh * kw
    _, c2, Ho, Wo = offsets.shape
    if c2 != 2 * K:
        raise ValueError(f"offsets must have 2*kh*kw = {2 * K} channels, got shape {tuple(offsets.shape)}")
    expected = output_size(in_hw, kernel_size, stride, padding, dilation)
    if (Ho, Wo) != expected:
        raise ValueError(f"offsets have spatial size {(Ho, Wo)}, the convolution's output is {expected}")
    off = offsets[0].permute(1, 2, 0).reshape(Ho, Wo, K, 2)
    dt, dev = off.dtype, off.device
    oy = torch.arange(Ho, dtype=dt, device=dev) * stride[0] - padding[0]
    ox = torch.arange(Wo, dtype=dt, device=dev) * stride[1] - padding[1]
    ti = (torch.arange(kh, dtype=dt, device=dev) * dilation[0]).repeat_interleave(kw)
    tj = (torch.arange(kw, dtype=dt, device=dev) * dilation[1]).repeat(kh)
    y = oy[:, None, None] + ti + off[..., 0]
    x = ox[None, :, None] + tj + off[..., 1]
    m = torch.ones(Ho, Wo, K, dtype=dt, device=dev) if mask is None else mask[0].to(dt).permute(1, 2, 0)
    return torch.stack([y, x], -1).contiguous(), m.contiguous()


def deform_conv2d_reference(x: Tensor, weight: Tensor, bias: Tensor | None, offsets: Tensor, mask: Tensor | None,
                            stride: Pair, padding: Pair, dilation: Pair, wrap: bool = False) -> Tensor:
    """``torchvision.ops.deform_conv2d`` with fixed offsets/mask ``(1, ., Ho, Wo)`` (expanded over the batch).

    With ``wrap`` the input is tiled three times horizontally (circular padding by ``W`` on each side) and the
    column offsets shifted accordingly, so samples across the left/right border read the other side of the
    panorama. Supports ``groups`` through the weight shape, like ``deform_conv2d``.
    """
    from torchvision.ops import deform_conv2d

    B, W = x.shape[0], x.shape[-1]
    Wo = offsets.shape[-1]
    off = offsets.to(x.dtype).expand(B, -1, -1, -1)
    m = None if mask is None else mask.to(x.dtype).expand(B, -1, -1, -1)
    if not wrap:
        return deform_conv2d(x, off, weight, bias, stride=stride, padding=padding, dilation=dilation, mask=m)
    xp = torch.cat([x, x, x], -1)
    off = off.clone()
    off[:, 1::2] += W - padding[1]  # sample column in the tiled image: x + W, and no horizontal padding
    kw = weight.shape[-1]
    wo_big = (3 * W - dilation[1] * (kw - 1) - 1) // stride[1] + 1
    off = F.pad(off, (0, wo_big - Wo))
    if m is not None:
        m = F.pad(m, (0, wo_big - Wo))
    y = deform_conv2d(xp, off, weight, bias, stride=stride, padding=(padding[0], 0), dilation=dilation, mask=m)
    return y[..., :Wo]
