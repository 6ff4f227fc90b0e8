"""FreDSNet: joint monocular depth and semantic segmentation from one equirectangular panorama.

Thesis chapter 4 (§4.3); Berenguel-Baeta et al., ICRA 2023. Architecture (``W`` = width multiplier)::

    image (B,3,H,W) -> ResNet layer1..4  (strides 4, 8, 16, 32)
    encoder  FBC-N x4 : FourierBlock -> [skip] -> bilinear /2 -> W-conv, + next backbone level
                        (last stage: FourierBlock -> W-conv to the latent, no down-scaling)
    decoder  CFB-N x6 : W-conv -> bilinear x2 -> + w_i * skip (stages 1-4) -> FourierBlock
    depth    head over the last 3 decoder maps, semantic head over the last 5:
             W-conv + bilinear up-sampling per map, learned-weighted sum, 3x3 conv
             (depth: ReLU, metric range in metres; semantic: logits)

Widths at ``width=1`` (the thesis / public model, ResNet-50): encoder 256, 512, 1024, 2048, latent 1024,
decoder 2048, 1024, 512, 256, 64, 16, heads 128. Other widths scale all of these; a 1x1 lateral
convolution adapts the backbone's channels where they differ (e.g. ResNet-18 at ``width=0.25`` needs none).

Ablation codes of §4.5.1: ``spectral=True/False`` ("F"/"X"), ``conv="standard"/"projected"`` ("Std"/"Equi":
3x3 convolutions become ``omnidl.nn.ProjectedConv2d`` on an equirectangular camera, resized by the
layer to every feature map). Input sides must be multiples of 32.

Differences from the public code (see ``docs/fredsnet.md``): the spectral skip keeps its gradient;
circular padding wraps horizontally only; learned skip/branch weights start at 1 (public: ``randn``);
no never-used parameters are created; semantic logits are plain conv outputs unless
``semantic_bn_relu=True`` (the public model ends with BN + ReLU); the depth output bias starts at 1 m.
Same compute as the public model: 100.5 GFLOP (conv/matmul) at 512x256 with ResNet-50, width 1.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from omnidl.cameras import Equirectangular
from omnidl.cameras.resolve import resolve_camera
from omnidl.nn import convert_conv2d
from omnidl.nn.conv_switch import conv_choice
from omnidl.nn.ffc import FourierBlock
from omnidl.nn.wconv import ConvNormAct, WConv

from ._backbone import ResNetFeatures
from ._checks import check_image
from ._memory_format import MemoryFormat
from .registry import register_model

torch.fx.wrap("check_image")

#: widths of the public model (ResNet-50, width 1)
ENCODER_WIDTHS = (256, 512, 1024, 2048)
LATENT_WIDTH = 1024
DECODER_WIDTHS = (2048, 1024, 512, 256, 64, 16)
HEAD_WIDTH = 128
EQUI_PARTS = ("fourier", "wconv", "heads")


def _scaled(c: int, width: float, minimum: int = 8) -> int:
    """``c * width`` rounded to an even number, at least ``minimum`` (exact at ``width=1``)."""
    return max(minimum, 2 * int(round(c * width / 2)))


class EncoderBlock(nn.Module):
    """FBC-N: ``f = FourierBlock(x)`` (the decoder skip), ``y = WConv(down(f))``; returns ``(f, y)``."""

    def __init__(self, channels: int, out_channels: int, *, downscale: bool, dropout: float,
                 fb_kwargs: Mapping[str, Any], wconv_kwargs: Mapping[str, Any]) -> None:
        super().__init__()
        self.fourier = FourierBlock(channels, **fb_kwargs)
        self.downscale = downscale
        self.conv = WConv(channels, out_channels, dropout=dropout, **wconv_kwargs)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        f = self.fourier(x)
        y = F.interpolate(f, scale_factor=0.5, mode="bilinear", align_corners=False) if self.downscale else f
        return f, self.conv(y)


class DecoderBlock(nn.Module):
    """CFB-N: ``FourierBlock(up(WConv(x)) + w * skip)`` (``w`` a learned scalar, initialised to 1)."""

    def __init__(self, in_channels: int, channels: int, *, upscale: bool, skip: bool,
                 fb_kwargs: Mapping[str, Any], wconv_kwargs: Mapping[str, Any]) -> None:
        super().__init__()
        self.conv = WConv(in_channels, channels, **wconv_kwargs)
        self.upscale = upscale
        self.skip_weight = nn.Parameter(torch.ones(1)) if skip else None
        self.fourier = FourierBlock(channels, **fb_kwargs)

    def forward(self, x: Tensor, skip: Tensor | None = None) -> Tensor:
        if self.skip_weight is not None and skip is None:
            raise ValueError("DecoderBlock built with a skip connection needs a skip tensor")
        y = self.conv(x)
        if self.upscale:
            y = F.interpolate(y, scale_factor=2.0, mode="bilinear", align_corners=False)
        if self.skip_weight is not None:
            y = y + self.skip_weight * skip
        return self.fourier(y)


class FusionHead(nn.Module):
    """Task branch: ``out(m_0 + sum_i w_i m_i)`` with ``m_i = up(WConv_i(d_i))`` at the size of the last map.

    ``w_i`` (``i >= 1``) are learned scalars initialised to 1; ``m_0`` has the fixed weight 1
    (as the public code, whose ``alphas[0]`` is never used).
    """

    def __init__(self, in_channels: Sequence[int], mid_channels: int, out_channels: int, *,
                 activation: str, out_activation: str, out_norm: bool,
                 wconv_kwargs: Mapping[str, Any], out_camera: Any = None) -> None:
        super().__init__()
        self.mediators = nn.ModuleList(WConv(c, mid_channels, activation=activation, **wconv_kwargs)
                                       for c in in_channels)
        self.branch_weights = nn.Parameter(torch.ones(len(in_channels) - 1))
        self.out = ConvNormAct(mid_channels, out_channels, 3, norm=out_norm, activation=out_activation,
                               padding="circular", camera=out_camera)

    def forward(self, maps: Sequence[Tensor]) -> Tensor:
        """``maps`` from coarse to fine; the last one sets the output size and needs no up-sampling. Each weight
        ``w_i`` multiplies ``m_i`` before its up-sampling (the same: up-sampling is linear), on the smaller map."""
        size = (maps[-1].shape[-2], maps[-1].shape[-1])
        fused = None
        for i, (mediator, d) in enumerate(zip(self.mediators, maps)):
            m = mediator(d)
            if i > 0:
                m = self.branch_weights[i - 1] * m
            if i < len(maps) - 1:
                m = F.interpolate(m, size=size, mode="bilinear", align_corners=True)
            fused = m if fused is None else fused + m
        return self.out(fused)


class FreDSNet(MemoryFormat, nn.Module):
    """FreDSNet (see the module docstring). ``forward(image (B,3,H,W) in [0,1])`` returns
    ``{"depth": (B,1,H,W) >= 0 metres, "semantic": (B,num_classes,H,W) logits}``.

    Args:
        num_classes: semantic classes including unknown (14 = Stanford2D3DS 13 + unknown).
        backbone: torchvision ResNet name (``resnet18`` ... ``resnet152``, ``resnext*``).
        pretrained: local path to torchvision backbone weights; ``None``: random init.
        width: width multiplier of every FreDSNet layer (1 = thesis model).
        spectral: Fourier blocks with the spectral transform ("F") or a 3x3 conv instead ("X").
        conv: ``"standard"`` or ``"projected"`` (distortion-aware ``ProjectedConv2d`` 3x3 convolutions, the
            thesis' EquiConv); ``"std"``/``"equi"`` are deprecated aliases (:mod:`omnidl.nn.conv_switch`).
        camera: camera for ``conv="projected"`` (``Camera`` or config mapping; default full equirect).
        equi_parts: which 3x3 convs become Equi: any of ``"fourier"`` (the Fourier blocks' spatial
            paths, thesis §4.3.1), ``"wconv"`` (the W-convs' 3x3), ``"heads"`` (branch W-convs and
            output convs), ``"backbone"`` (every k>1 conv of the ResNet, via ``convert_conv2d``).
        fourier_padding: padding of the Fourier blocks' 3x3 convs (``"zeros"`` as the public code,
            or ``"circular"``: horizontal wrap).
        encoder_dropout: ``Dropout2d`` inside the encoder W-convs (public code: 0.4).
        head_width: intermediate width of both branches before ``width`` scaling (128).
        fft_norm, spectrum_layout: Fourier unit options (see :class:`omnidl.nn.ffc.FourierUnit`).
        semantic_bn_relu: end the semantic branch with BN + ReLU as the public model (for converted
            official weights); default plain logits.
        outputs: which heads to build/run (``("depth", "semantic")``, or one of them).
        depth_bias_init: initial bias (metres) of the depth output conv, so that the final ReLU starts
            active on most pixels (a dead ReLU output never learns); the public code uses the default init.
        channels_last: run the network in ``torch.channels_last`` memory format (weights and activations; outputs
            are returned contiguous), see :mod:`omnidl.models._memory_format`. Results equal up to float rounding.
        encoder: ``None`` (default): the ResNet ``backbone``. A foundation encoder instead
            (:mod:`omnidl.models.foundation.encoder`): ``"dinov2_s"``/``"dinov2_b"``/``"dinov2_l"``/``"dinov2_g"`` or a
            mapping ``{name: dinov2_s, freeze: all|none|<blocks>}``; ``pretrained`` is then its local checkpoint
            (DINOv2, timm, transformers or Depth-Anything-V2). Its four maps (strides 4-32) enter the encoder blocks
            through the lateral 1x1 convolutions. ``equi_parts`` may not hold ``"backbone"`` then.
    """

    stride = 32

    def __init__(self, num_classes: int = 14, backbone: str = "resnet50", pretrained: str | None = None,
                 width: float = 1.0, spectral: bool = True, conv: str = "standard", camera: Any = None,
                 equi_parts: Sequence[str] = ("fourier", "wconv"), fourier_padding: str = "zeros",
                 encoder_dropout: float = 0.4, head_width: int = HEAD_WIDTH, fft_norm: str = "backward",
                 spectrum_layout: str = "width", semantic_bn_relu: bool = False,
                 outputs: Sequence[str] = ("depth", "semantic"), depth_bias_init: float = 1.0,
                 channels_last: bool = False, encoder: str | Mapping[str, Any] | None = None) -> None:
        super().__init__()
        conv = conv_choice(conv, "FreDSNet")
        if not width > 0:
            raise ValueError(f"FreDSNet: width must be > 0, got {width}")
        bad = set(equi_parts) - set(EQUI_PARTS) - {"backbone"}
        if bad:
            raise ValueError(f"FreDSNet: unknown equi_parts {sorted(bad)}; choose from {list(EQUI_PARTS) + ['backbone']}")
        outputs = tuple(outputs)
        if not outputs or set(outputs) - {"depth", "semantic"}:
            raise ValueError(f"FreDSNet: outputs must be a non-empty subset of ('depth', 'semantic'), got {outputs}")
        self.num_classes, self.outputs = int(num_classes), outputs
        cam = (resolve_camera(camera, default=Equirectangular(width=512, height=256), allow_files=False)
               if conv == "projected" else None)
        parts = set(equi_parts) if cam is not None else set()

        if encoder is None or encoder == "resnet":
            self.backbone = ResNetFeatures(backbone, pretrained=pretrained)
            if "backbone" in parts:
                convert_conv2d(self.backbone.body, camera=cam)
        else:
            if "backbone" in parts:
                raise ValueError("FreDSNet: equi_parts 'backbone' converts the ResNet's convolutions; it does not "
                                 f"apply to encoder={encoder!r}")
            from .foundation.encoder import build_encoder
            self.backbone = build_encoder(encoder, pretrained)

        enc = [_scaled(c, width) for c in ENCODER_WIDTHS]
        latent = _scaled(LATENT_WIDTH, width)
        dec = [_scaled(c, width) for c in DECODER_WIDTHS]
        head = _scaled(head_width, width)
        self.widths = {"encoder": enc, "latent": latent, "decoder": dec, "head": head}
        self.lateral = nn.ModuleList(nn.Identity() if cb == ce else nn.Conv2d(cb, ce, 1)
                                     for cb, ce in zip(self.backbone.channels, enc))

        fb = dict(spectral=spectral, padding=fourier_padding, fft_norm=fft_norm, spectrum_layout=spectrum_layout,
                  camera=cam if "fourier" in parts else None)
        wc = dict(camera=cam if "wconv" in parts else None)
        hc = dict(camera=cam if "heads" in parts else None)
        self.encoder = nn.ModuleList(
            EncoderBlock(enc[i], enc[i + 1] if i < 3 else latent, downscale=i < 3, dropout=encoder_dropout,
                         fb_kwargs=fb, wconv_kwargs=wc) for i in range(4))
        ins = [latent] + dec[:-1]
        self.decoder = nn.ModuleList(
            DecoderBlock(ins[i], dec[i], upscale=i > 0, skip=i < 4, fb_kwargs=fb, wconv_kwargs=wc)
            for i in range(6))
        self.depth_head = FusionHead(dec[-3:], head, 1, activation="prelu", out_activation="relu", out_norm=False,
                                     wconv_kwargs=hc, out_camera=hc["camera"]) if "depth" in outputs else None
        self.semantic_head = FusionHead(dec[-5:], head, self.num_classes, activation="relu",
                                        out_activation="relu" if semantic_bn_relu else "none",
                                        out_norm=semantic_bn_relu, wconv_kwargs=hc,
                                        out_camera=hc["camera"]) if "semantic" in outputs else None
        if self.depth_head is not None:
            nn.init.constant_(self.depth_head.out.conv.bias, float(depth_bias_init))
        self.set_memory_format(channels_last, "FreDSNet")

    def check_input(self, x: Tensor) -> None:
        """Raise a ``ValueError`` unless ``x`` is ``(B, 3, H, W)`` with ``H, W`` multiples of 32."""
        check_image(x, "FreDSNet", self.stride)

    def decode_features(self, x: Tensor) -> list[Tensor]:
        """The six decoder maps ``[d1 (1/32), d2 (1/16), d3 (1/8), d4 (1/4), d5 (1/2), d6 (1/1)]``."""
        check_image(x, "FreDSNet", self.stride)
        x = self.to_model_format(x)
        feats = [lat(f) for lat, f in zip(self.lateral, self.backbone(x))]
        skips = []
        flow = feats[0]
        for i, block in enumerate(self.encoder):
            f, flow = block(flow)
            skips.append(f)
            if i < 3:
                flow = flow + feats[i + 1]
        maps = []
        y = flow
        for i, block in enumerate(self.decoder):
            y = block(y, skips[3 - i] if i < 4 else None)
            maps.append(y)
        return maps

    def forward(self, x: Tensor) -> dict[str, Tensor]:
        maps = self.decode_features(x)
        out: dict[str, Tensor] = {}
        if self.depth_head is not None:
            out["depth"] = self.depth_head(maps[-3:]).contiguous()
        if self.semantic_head is not None:
            out["semantic"] = self.semantic_head(maps[-5:]).contiguous()
        return out


@register_model(smoke_kwargs=dict(backbone="resnet18", width=0.0625, head_width=64), smoke_size=(64, 128))
def fredsnet(**kwargs: Any) -> FreDSNet:
    """FreDSNet (thesis ch. 4). ``create_model("fredsnet", backbone="resnet50", width=1)`` is the thesis
    model (115.9 M parameters); see :class:`FreDSNet` for the options."""
    return FreDSNet(**kwargs)


def count_parameters(model: nn.Module) -> int:
    """Number of parameters (shared ones counted once)."""
    return sum(p.numel() for p in model.parameters())


__all__ = ["FreDSNet", "fredsnet", "count_parameters", "EncoderBlock", "DecoderBlock", "FusionHead"]

