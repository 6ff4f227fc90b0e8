"""Panorama-aware padding and a "same"-size convolution factory.

An equirectangular panorama is periodic in longitude only: column ``W`` is column ``0``
again, but the top row (north pole) is *not* the neighbour of the bottom row. So the
padding used here wraps **horizontally** and pads vertically with zeros (or replicates /
reflects). The public FreDSNet code uses ``padding_mode='circular'``, which wraps both
axes (top row sees the bottom row) — a bug that omnidl does not reproduce.

* :func:`pad_panorama` / :class:`PanoramaPad2d` — the functional core and its module.
* :class:`CircularConv2d` — an ``nn.Conv2d`` (same state-dict keys) with horizontal wrap.
* :func:`make_conv2d` — one factory for every "same" convolution of a block:
  standard (zero padding), horizontally circular, or distortion-aware
  (``omnidl.nn.projected_conv.ProjectedConv2d`` when a ``camera`` is given).
"""
from __future__ import annotations

from typing import Any, Callable, Literal

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from .projected_conv import ProjectedConv2d

PaddingMode = Literal["zeros", "circular"]
VerticalMode = Literal["zeros", "replicate", "reflect"]


def pad_panorama(x: Tensor, pad_w: int | tuple[int, int], pad_h: int | tuple[int, int] = 0,
                 vertical: VerticalMode = "zeros") -> Tensor:
    """Pad ``x (..., H, W)`` with a horizontal wrap-around and a non-periodic vertical border.

    Args:
        x: ``(B, C, H, W)`` (or any ``(..., H, W)`` with at least 3 dims) feature map.
        pad_w: columns added on the left and right (``int`` or ``(left, right)``), copied
            from the opposite side (longitude wraps).
        pad_h: rows added on the top and bottom (``int`` or ``(top, bottom)``), never wrapped.
        vertical: ``"zeros"`` | ``"replicate"`` | ``"reflect"`` for the rows.

    Returns:
        ``(..., H + top + bottom, W + left + right)``.
    """
    left, right = (pad_w, pad_w) if isinstance(pad_w, int) else pad_w
    top, bottom = (pad_h, pad_h) if isinstance(pad_h, int) else pad_h
    w = x.shape[-1]
    if left > w or right > w:
        raise ValueError(f"pad_panorama: horizontal padding ({left}, {right}) larger than the width {w}")
    if left or right:
        x = torch.cat([p for p in (x[..., w - left:] if left else None, x, x[..., :right] if right else None)
                       if p is not None], dim=-1)
    if top or bottom:
        if vertical == "zeros":
            x = F.pad(x, (0, 0, top, bottom))
        elif vertical in ("replicate", "reflect"):
            x = F.pad(x, (0, 0, top, bottom), mode=vertical)
        else:
            raise ValueError(f"pad_panorama: vertical must be 'zeros', 'replicate' or 'reflect', got {vertical!r}")
    return x


torch.fx.wrap("pad_panorama")   # torch.fx.symbolic_trace records it as one call (it checks the width)


class PanoramaPad2d(nn.Module):
    """Module form of :func:`pad_panorama` (horizontal wrap, vertical ``zeros``/``replicate``/``reflect``)."""

    def __init__(self, pad_w: int | tuple[int, int], pad_h: int | tuple[int, int] = 0,
                 vertical: VerticalMode = "zeros") -> None:
        super().__init__()
        self.pad_w, self.pad_h, self.vertical = pad_w, pad_h, vertical

    def forward(self, x: Tensor) -> Tensor:
        return pad_panorama(x, self.pad_w, self.pad_h, self.vertical)

    def extra_repr(self) -> str:
        return f"pad_w={self.pad_w}, pad_h={self.pad_h}, vertical={self.vertical!r}"


class CircularConv2d(nn.Conv2d):
    """``nn.Conv2d`` whose horizontal padding wraps around (360° panoramas); vertical padding is zeros.

    Same constructor, parameters and state-dict keys (``weight``, ``bias``) as ``nn.Conv2d``;
    ``padding`` must be an int or ``(pad_h, pad_w)`` tuple (``"same"`` is resolved for odd kernels).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | tuple[int, int],
                 stride: int | tuple[int, int] = 1, padding: int | tuple[int, int] | str = 0,
                 dilation: int | tuple[int, int] = 1, groups: int = 1, bias: bool = True,
                 device: Any = None, dtype: Any = None) -> None:
        super().__init__(in_channels, out_channels, kernel_size, stride, 0, dilation, groups, bias,
                         device=device, dtype=dtype)
        kh, kw = self.kernel_size
        dh, dw = self.dilation
        if padding == "same":
            if kh % 2 == 0 or kw % 2 == 0:
                raise ValueError(f"CircularConv2d: padding='same' needs an odd kernel, got {self.kernel_size}")
            padding = (dh * (kh - 1) // 2, dw * (kw - 1) // 2)
        elif isinstance(padding, str):
            raise ValueError(f"CircularConv2d: padding must be an int, a (pad_h, pad_w) tuple or 'same', got {padding!r}")
        self.wrap_padding = (padding, padding) if isinstance(padding, int) else tuple(padding)

    def _conv_forward(self, x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        ph, pw = self.wrap_padding
        return F.conv2d(pad_panorama(x, pw) if pw else x, weight, bias, self.stride, (ph, 0), self.dilation,
                        self.groups)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", wrap_padding={self.wrap_padding} (horizontal wrap)"


def make_conv2d(in_channels: int, out_channels: int, kernel_size: int = 3, *, stride: int = 1,
                dilation: int = 1, bias: bool = True, padding: PaddingMode = "zeros", camera: Any = None,
                conv_layer: Callable[..., nn.Module] | None = None) -> nn.Module:
    """A "same"-padded convolution (output size = input size / stride).

    Args:
        padding: ``"zeros"`` (``nn.Conv2d``) or ``"circular"`` (:class:`CircularConv2d`, horizontal wrap).
            Ignored for distortion-aware convolutions, which take the wrap from the camera.
        camera: a :class:`omnidl.cameras.Camera` (or camera config mapping). When given and
            ``kernel_size > 1``, the convolution is ``ProjectedConv2d(..., camera=camera)``
            (EquiConv for an equirectangular camera). ``None``: a standard convolution.
        conv_layer: overrides the class used for ``kernel_size > 1`` (called with ``nn.Conv2d``'s
            arguments, plus ``camera=`` when a camera is given).

    1x1 convolutions are always plain ``nn.Conv2d`` (there is nothing to deform).
    """
    pad = dilation * (kernel_size - 1) // 2
    kw = dict(stride=stride, padding=pad, dilation=dilation, bias=bias)
    if kernel_size == 1:
        return nn.Conv2d(in_channels, out_channels, 1, stride=stride, bias=bias)
    if conv_layer is not None:
        if camera is not None:
            return conv_layer(in_channels, out_channels, kernel_size, camera=camera, **kw)
        return conv_layer(in_channels, out_channels, kernel_size, **kw)
    if camera is not None:
        return ProjectedConv2d(in_channels, out_channels, kernel_size, camera=camera, **kw)
    if padding == "circular":
        return CircularConv2d(in_channels, out_channels, kernel_size, **kw)
    if padding == "zeros":
        return nn.Conv2d(in_channels, out_channels, kernel_size, **kw)
    raise ValueError(f"make_conv2d: padding must be 'zeros' or 'circular', got {padding!r}")
