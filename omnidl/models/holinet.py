"""HoLiNet: horizon-line and vertical-vanishing-point heat maps from a panorama in any orientation
(thesis §6.2.1; Berenguel-Baeta et al.). Architecture (input ``H x W``, ``d`` = decoder widths)::

    ResNet encoder (ResNet-50 by default): stem /2, layer1 /4, layer2 /8, layer3 /16, layer4 /32
    up(conv3x3(layer4) -> d0)                                          /16
    x16 = conv3x3(cat(., layer3)) -> d1 ;   aux_16 = conv3x3(x16) -> 2  /16
    x8  = conv3x3(cat(up x16, layer2, up aux_16)) -> d2 ; aux_8 -> 2     /8
    x4  = conv3x3(cat(up x8, layer1, up aux_8)) -> d3 ;   aux_4 -> 2     /4
    x2  = conv5x5(cat(up x4, stem, up aux_4)) -> d4 ; out = conv3x3 -> 2 /2
    (ReLU after every decoder conv except the 2-channel outputs; bilinear x2 up-sampling)

Outputs (logits): ``"horizon"`` ``(B, 1, H/2, W/2)``, ``"vp"`` ``(B, 1, H/2, W/2)`` (the reference
resolution: half the input) and the intermediate maps ``"aux_16"``, ``"aux_8"``, ``"aux_4"``
``(B, 2, H/s, W/s)`` (channel 0 horizon, 1 VP) used by :class:`omnidl.losses.heatmap.HeatmapLoss`.
Channel order of the public model is VP first; here the two maps are named.

``conv="projected"`` (default, as the thesis: every convolution with a kernel > 1, encoder and decoder)
turns the convolutions into :class:`omnidl.nn.ProjectedConv2d` on an equirectangular camera via
:func:`omnidl.nn.convert_conv2d`; ``conv="standard"`` keeps standard convolutions (horizontal padding is
then circular in the decoder). Decoder widths at ``width=1`` are the public model's
(512, 256, 128, 64, 64). Input sides must be multiples of 32.

Differences from the public code: intermediate maps are predicted at 1/16, 1/8, 1/4 of the input
(public: 1/8, 1/4, 1/2 after each up-sampling); the encoder is torchvision's ResNet (1x1 convs without
bias, no dropout in the last block); ``pretrained`` really loads (the public ``load_resnet50`` silently
keeps random weights).
"""
from __future__ import annotations

from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from omnidl.cameras import Equirectangular
from omnidl.cameras.resolve import resolve_camera
from omnidl.nn import convert_conv2d
from omnidl.nn.conv_switch import conv_choice

from ._backbone import ResNetFeatures
from ._checks import check_image
from ._memory_format import MemoryFormat
from .registry import register_model

DECODER_WIDTHS = (512, 256, 128, 64, 64)

torch.fx.wrap("check_image")


class _ConvAct(nn.Sequential):
    def __init__(self, cin: int, cout: int, k: int, act: bool, circular: bool) -> None:
        mode = "circular" if circular else "zeros"
        layers: list[nn.Module] = []
        if circular:  # wrap longitude, zero-pad latitude
            layers.append(_HorizontalWrap(k // 2))
            layers.append(nn.Conv2d(cin, cout, k, padding=(k // 2, 0)))
        else:
            layers.append(nn.Conv2d(cin, cout, k, padding=k // 2, padding_mode=mode))
        if act:
            layers.append(nn.ReLU())  # not in place: ProjectedConv2d may return a view
        super().__init__(*layers)


class _HorizontalWrap(nn.Module):
    def __init__(self, pad: int) -> None:
        super().__init__()
        self.pad = pad

    def forward(self, x: Tensor) -> Tensor:
        return F.pad(x, (self.pad, self.pad, 0, 0), mode="circular") if self.pad else x


def _up(x: Tensor) -> Tensor:
    return F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)


class HoLiNet(MemoryFormat, nn.Module):
    """Horizon / vanishing-point heat-map network.

    Args:
        backbone: torchvision ResNet name (``resnet50`` as the thesis; ``resnet18``/``resnet34`` smaller).
        pretrained: local path of torchvision ImageNet weights for the backbone (``None``: random init).
        width: multiplier of the decoder widths (1 = public model).
        conv: ``"projected"`` (ProjectedConv2d everywhere) or ``"standard"``; ``"equi"``/``"std"`` are
            deprecated aliases (:mod:`omnidl.nn.conv_switch`).
        camera: camera of the input image for ``conv="projected"`` (``Camera`` or config; default full equirect).
        channels_last: run in ``torch.channels_last`` memory format (weights and activations; outputs are
            returned contiguous; :mod:`omnidl.models._memory_format`). Results equal up to float rounding.
    """

    def __init__(self, backbone: str = "resnet50", pretrained: str | None = None, width: float = 1.0,
                 conv: str = "projected", camera: Any = None, channels_last: bool = False) -> None:
        super().__init__()
        conv = self.conv = conv_choice(conv, "HoLiNet")
        if width <= 0:
            raise ValueError(f"HoLiNet: width must be positive, got {width}")
        self.encoder = ResNetFeatures(backbone, pretrained=pretrained, out_indices=(0, 1, 2, 3, 4))
        c0, c1, c2, c3, c4 = self.encoder.channels
        d0, d1, d2, d3, d4 = (max(8, int(round(c * width))) for c in DECODER_WIDTHS)
        circ = conv == "standard"
        self.dec32 = _ConvAct(c4, d0, 3, True, circ)
        self.dec16 = _ConvAct(d0 + c3, d1, 3, True, circ)
        self.out16 = _ConvAct(d1, 2, 3, False, circ)
        self.dec8 = _ConvAct(d1 + c2 + 2, d2, 3, True, circ)
        self.out8 = _ConvAct(d2, 2, 3, False, circ)
        self.dec4 = _ConvAct(d2 + c1 + 2, d3, 3, True, circ)
        self.out4 = _ConvAct(d3, 2, 3, False, circ)
        self.dec2 = _ConvAct(d3 + c0 + 2, d4, 5, True, circ)
        self.out2 = _ConvAct(d4, 2, 3, False, circ)
        if conv == "projected":
            convert_conv2d(self, camera=resolve_camera(camera, default=Equirectangular(width=256, height=128),
                                                       allow_files=False))
        self.set_memory_format(channels_last, "HoLiNet")

    def forward(self, image: Tensor) -> dict[str, Tensor]:
        """``image (B, 3, H, W)`` RGB in ``[0, 1]`` -> dict of logits (see the module docstring)."""
        check_image(image, "HoLiNet", 32)
        image = self.to_model_format(image)
        f0, f1, f2, f3, f4 = self.encoder(image)
        x = _up(self.dec32(f4))
        x16 = self.dec16(torch.cat([x, f3], 1))
        a16 = self.out16(x16)
        x8 = self.dec8(torch.cat([_up(x16), f2, _up(a16)], 1))
        a8 = self.out8(x8)
        x4 = self.dec4(torch.cat([_up(x8), f1, _up(a8)], 1))
        a4 = self.out4(x4)
        x2 = self.dec2(torch.cat([_up(x4), f0, _up(a4)], 1))
        out = self.out2(x2)
        out, a16, a8, a4 = (t.contiguous() for t in (out, a16, a8, a4))
        return {"horizon": out[:, :1], "vp": out[:, 1:], "aux_16": a16, "aux_8": a8, "aux_4": a4}


@register_model(smoke_kwargs=dict(backbone="resnet18", width=0.125, conv="standard"), smoke_size=(64, 128))
def holinet(**kwargs: Any) -> HoLiNet:
    """HoLiNet (thesis ch. 6): ``create_model("holinet")`` is ResNet-50 + full decoder with EquiConvs;
    ``create_model("holinet", backbone="resnet18", width=0.25, conv="standard")`` is a small CPU model."""
    return HoLiNet(**kwargs)
