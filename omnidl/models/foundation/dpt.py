"""Depth-Anything-V2 (Yang et al., NeurIPS 2024): a DINOv2 encoder and a DPT head, re-implemented in plain PyTorch.

The module tree and parameter names are those of the published code (``depth_anything_v2/dpt.py``), so the
published ``depth_anything_v2_vit{s,b,l}.pth`` and ``depth_anything_v2_metric_{hypersim,vkitti}_vit{s,b,l}.pth``
load as they are (:mod:`omnidl.models.foundation.convert` also maps transformers' ``model.safetensors``)::

    image (B, 3, H, W) RGB in [0, 1] -> ImageNet normalisation (inside) -> pretrained: DINOv2 ViT (patch 14)
    tokens of 4 blocks (vits/vitb: 2, 5, 8, 11; vitl: 4, 11, 17, 23; vitg: 9, 19, 29, 39), final norm
    depth_head (DPT):  projects.i  1x1 conv -> out_channels[i]
                       resize_layers  ConvTranspose x4, ConvTranspose x2, Identity, 3x3 conv stride 2
                       scratch.layer{1..4}_rn  3x3 conv (no bias) -> features
                       scratch.refinenet4..1  fusion blocks (residual conv units, bilinear x2, 1x1 out_conv)
                       scratch.output_conv1 (3x3, features/2) -> bilinear to (H, W) -> output_conv2:
                       3x3 conv (32), ReLU, 1x1 conv (1), ReLU (relative) | Sigmoid * max_depth (metric)

Outputs: relative models (``max_depth=None``) return ``{"disparity": (B, 1, H, W)}``, the affine-invariant inverse
depth the published relative models predict (larger = nearer; scale and shift unknown); metric models return
``{"depth": (B, 1, H, W)}`` in metres (z-depth along the optical axis of a perspective image). ``H`` and ``W`` must
be multiples of 14; the published models were trained at 518 px (shorter side).

Configurations of the published models (:data:`DA2_CONFIGS`): vits features 64, out_channels (48, 96, 192, 384);
vitb 128, (96, 192, 384, 768); vitl 256, (256, 512, 1024, 1024); vitg 384, (1536,) * 4.

Differences from the published code, none of which changes an output: the never-used ``resConfUnit1`` of
``refinenet4`` and the DINOv2 ``mask_token`` are not created (the converter drops them); the final ``F.relu`` of the
relative model, a no-op after the head's ReLU, is not repeated.
"""
from __future__ import annotations

import logging
import os
from typing import Any, Mapping, Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from .._checks import check_image
from ..registry import register_model
from .vit import VisionTransformer

log = logging.getLogger(__name__)

torch.fx.wrap("check_image")

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: encoder -> (features, out_channels) of the published models
DA2_CONFIGS = {"vits": (64, (48, 96, 192, 384)), "vitb": (128, (96, 192, 384, 768)),
               "vitl": (256, (256, 512, 1024, 1024)), "vitg": (384, (1536, 1536, 1536, 1536))}
#: encoder -> the four blocks whose tokens feed the head
DA2_LAYERS = {"vits": (2, 5, 8, 11), "vitb": (2, 5, 8, 11), "vitl": (4, 11, 17, 23), "vitg": (9, 19, 29, 39)}


class ResidualConvUnit(nn.Module):
    """``x + conv2(act(conv1(act(x))))`` (BN after each conv with ``bn=True``)."""

    def __init__(self, features: int, bn: bool) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1, bias=True)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1, bias=True)
        self.bn1 = nn.BatchNorm2d(features) if bn else nn.Identity()
        self.bn2 = nn.BatchNorm2d(features) if bn else nn.Identity()
        self.act1 = nn.ReLU()
        self.act2 = nn.ReLU()

    def forward(self, x: Tensor) -> Tensor:
        out = self.bn1(self.conv1(self.act1(x)))
        return self.bn2(self.conv2(self.act2(out))) + x


class FeatureFusionBlock(nn.Module):
    """``out_conv(up(rcu2(x + rcu1(skip))))``; ``up`` is bilinear (align_corners) to ``size`` or x2."""

    def __init__(self, features: int, bn: bool, skip: bool) -> None:
        super().__init__()
        self.resConfUnit1 = ResidualConvUnit(features, bn) if skip else None
        self.resConfUnit2 = ResidualConvUnit(features, bn)
        self.out_conv = nn.Conv2d(features, features, 1)

    def forward(self, x: Tensor, skip: Tensor | None = None, size: Any = None) -> Tensor:
        if self.resConfUnit1 is not None:
            if skip is None:
                raise ValueError("FeatureFusionBlock built with a skip input needs one")
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        if size is None:
            x = F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=True)
        else:
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class _Scratch(nn.Module):
    """Container with the published names (``layer{1..4}_rn``, ``refinenet{1..4}``, ``output_conv{1,2}``)."""


class DPTHead(nn.Module):
    """DPT head of Depth-Anything-V2 (module docstring). ``forward(tokens, patch_h, patch_w) -> (B, 1, 14 h, 14 w)``.

    ``tokens``: four ``(patch tokens (B, h*w, D), class token (B, D))`` pairs from :meth:`VisionTransformer.intermediate`.
    """

    def __init__(self, in_channels: int, features: int = 256, use_bn: bool = False,
                 out_channels: Sequence[int] = (256, 512, 1024, 1024), use_clstoken: bool = False,
                 metric: bool = False, patch_size: int = 14) -> None:
        super().__init__()
        oc = [int(c) for c in out_channels]
        if len(oc) != 4:
            raise ValueError(f"DPTHead: out_channels needs 4 entries, got {out_channels}")
        self.patch_size = int(patch_size)
        self.use_clstoken = bool(use_clstoken)
        self.projects = nn.ModuleList(nn.Conv2d(in_channels, c, 1) for c in oc)
        self.resize_layers = nn.ModuleList([nn.ConvTranspose2d(oc[0], oc[0], 4, stride=4),
                                            nn.ConvTranspose2d(oc[1], oc[1], 2, stride=2), nn.Identity(),
                                            nn.Conv2d(oc[3], oc[3], 3, stride=2, padding=1)])
        if self.use_clstoken:
            self.readout_projects = nn.ModuleList(nn.Sequential(nn.Linear(2 * in_channels, in_channels), nn.GELU())
                                                  for _ in oc)
        s = _Scratch()
        for i, c in enumerate(oc, start=1):
            setattr(s, f"layer{i}_rn", nn.Conv2d(c, features, 3, padding=1, bias=False))
        for i in range(1, 5):
            setattr(s, f"refinenet{i}", FeatureFusionBlock(features, use_bn, skip=i < 4))
        s.output_conv1 = nn.Conv2d(features, features // 2, 3, padding=1)
        s.output_conv2 = nn.Sequential(nn.Conv2d(features // 2, 32, 3, padding=1), nn.ReLU(True),
                                       nn.Conv2d(32, 1, 1), nn.Sigmoid() if metric else nn.ReLU(True), nn.Identity())
        self.scratch = s

    def forward(self, tokens: Sequence[tuple[Tensor, Tensor]], patch_h: Any, patch_w: Any) -> Tensor:
        maps = []
        for i, (x, cls) in enumerate(tokens):
            if self.use_clstoken:
                x = self.readout_projects[i](torch.cat([x, cls.unsqueeze(1).expand_as(x)], -1))
            x = x.permute(0, 2, 1).reshape(x.shape[0], x.shape[-1], patch_h, patch_w)
            maps.append(self.resize_layers[i](self.projects[i](x)))
        s = self.scratch
        l1, l2, l3, l4 = s.layer1_rn(maps[0]), s.layer2_rn(maps[1]), s.layer3_rn(maps[2]), s.layer4_rn(maps[3])
        p4 = s.refinenet4(l4, size=l3.shape[2:])
        p3 = s.refinenet3(p4, l3, size=l2.shape[2:])
        p2 = s.refinenet2(p3, l2, size=l1.shape[2:])
        p1 = s.refinenet1(p2, l1)
        out = s.output_conv1(p1)
        out = F.interpolate(out, size=(patch_h * self.patch_size, patch_w * self.patch_size), mode="bilinear",
                            align_corners=True)
        return s.output_conv2(out)


class DepthAnythingV2(nn.Module):
    """Depth-Anything-V2 (module docstring). ``forward(image (B, 3, H, W) in [0, 1])`` ->
    ``{"disparity": (B, 1, H, W)}`` (relative) or ``{"depth": (B, 1, H, W)}`` metres (``max_depth`` given).

    Args:
        encoder: ``"vits"``, ``"vitb"``, ``"vitl"``, ``"vitg"``, or a mapping of :class:`VisionTransformer`
            arguments (``embed_dim``, ``depth``, ``num_heads``, ...; tiny test models) with ``layers`` (the four
            block indices).
        features, out_channels: DPT widths (default: the published configuration of ``encoder``).
        max_depth: ``None`` for the relative models; 20 (Hypersim, indoor) or 80 (Virtual KITTI 2) for the metric
            ones.
        use_bn, use_clstoken: DPT options of the published code (both ``False`` in the published models).
        pos_interp: how the position embedding is resampled (:mod:`.vit`); ``"dinov2"`` for the published
            ``.pth`` files, ``"hf"`` for transformers' checkpoints (set by :func:`depth_anything_v2` from the file).
    """

    def __init__(self, encoder: str | Mapping[str, Any] = "vits", features: int | None = None,
                 out_channels: Sequence[int] | None = None, max_depth: float | None = None, use_bn: bool = False,
                 use_clstoken: bool = False, pos_interp: str = "dinov2") -> None:
        super().__init__()
        if isinstance(encoder, Mapping):
            vit_kwargs = dict(encoder)
            layers = vit_kwargs.pop("layers", None)
            if layers is None:
                raise ValueError("DepthAnythingV2: a custom encoder mapping needs 'layers' (four block indices)")
            self.pretrained = VisionTransformer(size=None, pos_interp=pos_interp, **vit_kwargs)
            default_features, default_oc = 64, (48, 96, 192, 384)
        else:
            if encoder not in DA2_CONFIGS:
                raise ValueError(f"DepthAnythingV2: unknown encoder {encoder!r}; choose one of {sorted(DA2_CONFIGS)}")
            self.pretrained = VisionTransformer(size=encoder, pos_interp=pos_interp)
            layers = DA2_LAYERS[encoder]
            default_features, default_oc = DA2_CONFIGS[encoder]
        self.layers = tuple(int(i) for i in layers)
        if len(self.layers) != 4:
            raise ValueError(f"DepthAnythingV2: layers needs 4 block indices, got {layers}")
        if max_depth is not None and not float(max_depth) > 0:
            raise ValueError(f"DepthAnythingV2: max_depth must be > 0 metres or None (relative), got {max_depth}")
        self.max_depth = None if max_depth is None else float(max_depth)
        self.patch_size = self.pretrained.patch_size
        self.depth_head = DPTHead(self.pretrained.embed_dim, features or default_features, use_bn,
                                  out_channels or default_oc, use_clstoken, metric=self.max_depth is not None,
                                  patch_size=self.patch_size)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    @property
    def output(self) -> str:
        """``"depth"`` (metric) or ``"disparity"`` (relative)."""
        return "disparity" if self.max_depth is None else "depth"

    def check_input(self, x: Tensor) -> None:
        """Raise a ``ValueError`` unless ``x`` is ``(B, 3, H, W)`` with ``H, W`` multiples of 14."""
        check_image(x, "DepthAnythingV2", self.patch_size)

    def forward_normalized(self, x: Tensor) -> Tensor:
        """The published model's ``forward`` on an ImageNet-normalised batch: ``(B, 1, H, W)`` (before
        ``max_depth``)."""
        ph, pw = x.shape[-2] // self.patch_size, x.shape[-1] // self.patch_size
        return self.depth_head(self.pretrained.intermediate(x, self.layers), ph, pw)

    def forward(self, x: Tensor) -> dict[str, Tensor]:
        check_image(x, "DepthAnythingV2", self.patch_size)
        y = self.forward_normalized((x - self.mean.to(x.dtype)) / self.std.to(x.dtype))
        if self.max_depth is not None:
            return {"depth": y * self.max_depth}
        return {"disparity": y}


_SMOKE = dict(encoder=dict(embed_dim=32, depth=4, num_heads=2, img_size=28, layers=(0, 1, 2, 3)), features=16,
              out_channels=(8, 16, 16, 32), use_bn=True)


@register_model(smoke_kwargs=_SMOKE, smoke_size=(28, 56))
def depth_anything_v2(encoder: str | Mapping[str, Any] = "vits", pretrained: str | os.PathLike | None = None,
                      max_depth: float | None = None, pos_interp: str | None = None, **kwargs: Any) -> DepthAnythingV2:
    """Depth-Anything-V2 from a local checkpoint: ``create_model("depth_anything_v2", encoder="vits",
    pretrained="checkpoints/depth_anything_v2_vits.pth")``.

    ``pretrained``: the published ``.pth`` (relative or metric; metric ones need ``max_depth=20`` or ``80``), a
    transformers ``model.safetensors`` / ``pytorch_model.bin``, or a folder holding one (with its
    ``config.json``, whose ``max_depth``/``depth_estimation_type`` are then used). ``pos_interp`` defaults to the
    loaded file's implementation (``"dinov2"`` without a file).
    """
    if not pretrained:
        return DepthAnythingV2(encoder, max_depth=max_depth, pos_interp=pos_interp or "dinov2", **kwargs)
    from .convert import load_depth_anything
    return load_depth_anything(pretrained, encoder=encoder, max_depth=max_depth, pos_interp=pos_interp, **kwargs)


__all__ = ["DepthAnythingV2", "DPTHead", "FeatureFusionBlock", "ResidualConvUnit", "depth_anything_v2",
           "DA2_CONFIGS", "DA2_LAYERS"]
