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

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from . import batch_norm, epilogue, expansion
from .inference import conv_bn_act, fold_batchnorm, inference_ready
from .padding import PaddingMode, make_conv2d
from .prelu import PReLU
from .unfold_conv import module_conv2d

Activation = Literal["prelu", "relu", "none"]


def make_activation(name: Activation, channels: int) -> nn.Module:
    """``"prelu"`` (one slope per channel, as FreDSNet; :class:`omnidl.nn.prelu.PReLU`, whose backward is one
    pass), ``"relu"`` or ``"none"`` (identity)."""
    if name == "prelu":
        return PReLU(channels)
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
        bn = self.norm if isinstance(self.norm, nn.BatchNorm2d) else None
        if inference_ready(x, self.conv, bn):   # eval without autograd: folded, kept, one oneDNN call when it can
            relu = type(self.act) is nn.ReLU
            y = conv_bn_act(x, self.conv, bn, "relu" if relu else None, ready=True)
            # y is this call's own new map: the activation written over it (omnidl.nn.epilogue), no second map
            return y if relu or epilogue.over_output(y, x, self.act) is not None else self.act(y)
        if expansion.applies(x, self.conv, self.norm, self.act):   # a thin 1x1 expansion in training: fused
            return expansion.expansion(x, self.conv, self.norm, self.act, ready=True)
        folded = self._folded_params(x)
        if folded is None:
            y = module_conv2d(self.conv, x)
            out = batch_norm.with_activation(y, self.norm, self.act)    # in training: one native batch norm pass
            if out is not None:
                return out
            y = self.norm(y)
        else:
            y = self.conv._conv_forward(x, *folded)
        if type(self.act) is nn.ReLU:
            return F.relu_(y)          # y is a fresh conv/BN output that no backward needs: no extra buffer
        return self.act(y)

    def _folded_params(self, x: Tensor) -> tuple[Tensor, Tensor] | None:
        """In eval mode, the convolution's weight and bias with the BatchNorm folded in, when that is cheaper
        than normalising the output (weights smaller than the output map); ``None`` otherwise.

        ``conv(x, w * s, (b - mean) * s + beta)`` with ``s = gamma / sqrt(var + eps)`` equals
        ``BN(conv(x, w, b))`` with running statistics; it is recomputed from the live parameters on every
        call (differentiable, never stale) and saves one pass and one buffer of the size of the output. (Without
        autograd, :func:`omnidl.nn.inference.conv_bn_act` keeps the folded weights between calls instead.)
        """
        conv, bn = self.conv, self.norm
        if (self.training or not isinstance(bn, nn.BatchNorm2d) or bn.running_var is None
                or not isinstance(conv, nn.Conv2d) or conv.padding_mode != "zeros"):
            return None
        out_numel = x.numel() // max(1, x.shape[1]) * conv.out_channels // (conv.stride[0] * conv.stride[1])
        if conv.weight.numel() > out_numel:
            return None
        return fold_batchnorm(conv.weight, conv.bias, bn)


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

    def row_source(self, x: Tensor) -> Callable[[int, int], Tensor]:
        """Eval mode only: ``f(a, b)`` = ``self(x)[:, :, a:b]``, with the wide last 1x1 stage computed per call.

        Everything up to the bottleneck runs once (``hidden`` channels); the expansion to ``out_channels``
        is pointwise, so rows can be produced block by block (see :mod:`omnidl.nn.fusion`) and the
        full-width output never exists at once. In training mode BatchNorm needs the whole batch.
        """
        if self.training:
            raise RuntimeError("WConv.row_source needs eval mode (BatchNorm statistics of the whole map otherwise)")
        hidden = self.drop2(self.conv(self.drop1(self.reduce(x))))
        return lambda a, b: self.expand(hidden[:, :, a:b])
