"""W-conv: FreDSNet's bottleneck of three Conv–BN–activation blocks with panorama padding (thesis §4.3.1).

``WConv(c_in, c_out)`` = ``1x1 (c_in -> c_in/4)`` → ``3x3 (c_in/4 -> c_in/4)`` → ``1x1 (c_in/4 -> c_out)``,
each followed by BatchNorm and an activation (PReLU by default), optional ``Dropout2d`` between
them, no residual (the ResNet *bottleneck* shape without the skip, as in the public code).
The 3x3 convolution pads with a horizontal wrap only (:class:`omnidl.nn.padding.CircularConv2d`),
never top↔bottom (the public code wraps both axes, a bug), or is a distortion-aware
``ProjectedConv2d`` when a ``camera`` is given.
"""
from __future__ import annotations

from typing import Any, Callable, Literal

import torch.nn as nn
from torch import Tensor

from .padding import PaddingMode, make_conv2d

Activation = Literal["prelu", "relu", "none"]


def make_activation(name: Activation, channels: int) -> nn.Module:
    """``"prelu"`` (``nn.PReLU`` with one slope per channel, as FreDSNet), ``"relu"`` or ``"none"`` (identity)."""
    if name == "prelu":
        return nn.PReLU(channels)
    if name == "relu":
        return nn.ReLU(inplace=False)
    if name in ("none", None):
        return nn.Identity()
    raise ValueError(f"activation must be 'prelu', 'relu' or 'none', got {name!r}")


class ConvNormAct(nn.Module):
    """``conv`` → ``norm`` (BatchNorm or identity) → ``act``; a "same" convolution (see :func:`make_conv2d`)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, *, norm: bool = True,
                 activation: Activation = "prelu", bias: bool = True, padding: PaddingMode = "circular",
                 camera: Any = None, conv_layer: Callable[..., nn.Module] | None = None) -> None:
        super().__init__()
        self.conv = make_conv2d(in_channels, out_channels, kernel_size, bias=bias, padding=padding,
                                camera=camera, conv_layer=conv_layer)
        self.norm = nn.BatchNorm2d(out_channels) if norm else nn.Identity()
        self.act = make_activation(activation, out_channels)

    def forward(self, x: Tensor) -> Tensor:
        return self.act(self.norm(self.conv(x)))


class WConv(nn.Module):
    """The W-conv bottleneck: ``(B, C_in, H, W) -> (B, C_out, H, W)``.

    Args:
        in_channels, out_channels: widths; the bottleneck width is ``hidden`` (default ``in_channels // 4``,
            at least 1).
        activation: ``"prelu"`` (encoder/decoder/depth branch) or ``"relu"`` (semantic branch).
        norm: BatchNorm after each convolution (FreDSNet: always).
        dropout: ``Dropout2d`` probability after the first two blocks (FreDSNet's encoder: 0.4).
        padding: ``"circular"`` (horizontal wrap, default) or ``"zeros"`` for the 3x3 convolution.
        camera: makes the 3x3 convolution distortion-aware (``ProjectedConv2d``); ``None``: standard.
        conv_layer: custom class for the 3x3 convolution (see :func:`omnidl.nn.padding.make_conv2d`).
    """

    def __init__(self, in_channels: int, out_channels: int, *, hidden: int | None = None,
                 activation: Activation = "prelu", norm: bool = True, dropout: float = 0.0,
                 padding: PaddingMode = "circular", camera: Any = None,
                 conv_layer: Callable[..., nn.Module] | None = None) -> None:
        super().__init__()
        hidden = max(1, in_channels // 4) if hidden is None else int(hidden)
        common = dict(norm=norm, activation=activation)
        self.reduce = ConvNormAct(in_channels, hidden, 1, **common)
        self.drop1 = nn.Dropout2d(dropout) if dropout > 0 else nn.Identity()
        self.conv = ConvNormAct(hidden, hidden, 3, padding=padding, camera=camera, conv_layer=conv_layer, **common)
        self.drop2 = nn.Dropout2d(dropout) if dropout > 0 else nn.Identity()
        self.expand = ConvNormAct(hidden, out_channels, 1, **common)

    def forward(self, x: Tensor) -> Tensor:
        return self.expand(self.drop2(self.conv(self.drop1(self.reduce(x)))))
