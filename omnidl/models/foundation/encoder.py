"""A DINOv2 ViT as the multi-scale encoder of FreDSNet / HorizonNet (``model.encoder=dinov2_s``).

Same interface as :class:`omnidl.models._backbone.ResNetFeatures`: ``(B, 3, H, W)`` RGB in ``[0, 1]`` ->
four maps at strides ``(4, 8, 16, 32)`` of the input, with ``channels``, ``strides`` and ``reduction`` attributes::

    image (H x W, multiples of 32) -> bilinear (anti-aliased) to (14 H/16) x (14 W/16): one 14-px patch per
    16 input pixels -> ImageNet normalisation -> ViT tokens of four blocks (final norm) on the (H/16) x (W/16) grid
    -> DPT reassembly: 1x1 conv to channels[i], then ConvTranspose x4 | ConvTranspose x2 | identity | 3x3 conv
    stride 2  -> (H/4, W/4), (H/8, W/8), (H/16, W/16), (H/32, W/32)

so any panorama size the ResNet takes works (the patch grid is the stride-16 map; the position embedding is
resampled to it). ``freeze``: ``"none"`` (fine-tune everything), ``"all"`` (the ViT is frozen; the reassembly
layers train) or an int ``k`` (patch/position embeddings and the first ``k`` blocks frozen). Frozen parameters have
``requires_grad=False``; the modules stay in the model (and its state dict) and run in every mode.

Encoders (:data:`ENCODERS`): ``dinov2_s``, ``dinov2_b``, ``dinov2_l``, ``dinov2_g`` (DINOv2 ViT-S/B/L/g, patch 14).
``pretrained``: a local DINOv2 / timm / transformers / Depth-Anything-V2 checkpoint
(:mod:`omnidl.models.foundation.convert`; a Depth-Anything-V2 file gives its fine-tuned encoder).
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
from .vit import VisionTransformer

log = logging.getLogger(__name__)

torch.fx.wrap("check_image")

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: name -> (ViT size, the four blocks read, reassembly channels)
ENCODERS = {"dinov2_s": ("vits", (2, 5, 8, 11), (48, 96, 192, 384)),
            "dinov2_b": ("vitb", (2, 5, 8, 11), (96, 192, 384, 768)),
            "dinov2_l": ("vitl", (4, 11, 17, 23), (256, 512, 1024, 1024)),
            "dinov2_g": ("vitg", (9, 19, 29, 39), (1536, 1536, 1536, 1536))}
STRIDES = (4, 8, 16, 32)


class ViTFeatures(nn.Module):
    """DINOv2 encoder with DPT reassembly (module docstring).

    Args:
        name: a key of :data:`ENCODERS`, or ``None`` with ``vit`` (a mapping of :class:`VisionTransformer`
            arguments plus ``layers``) and ``channels`` (tiny test configurations).
        pretrained: local checkpoint path or ``None`` (random initialisation).
        freeze: ``"none"``, ``"all"`` or the number of leading blocks to freeze.
        channels: output channels of the four levels (default: the DPT widths of the size).
    """

    strides = STRIDES

    def __init__(self, name: str | None = "dinov2_s", pretrained: str | os.PathLike | None = None,
                 freeze: str | int = "none", channels: Sequence[int] | None = None,
                 vit: Mapping[str, Any] | None = None, pos_interp: str | None = None) -> None:
        super().__init__()
        state, file_interp = None, None
        if pretrained:
            from .convert import read_state_dict, vit_state_dict
            state, file_interp = vit_state_dict(read_state_dict(pretrained))
        interp = pos_interp or file_interp or "dinov2"
        if name is not None:
            if name not in ENCODERS:
                raise ValueError(f"unknown encoder {name!r}; choose one of {sorted(ENCODERS)} (or 'resnet')")
            size, layers, default_ch = ENCODERS[name]
            self.vit = VisionTransformer(size=size, pos_interp=interp)
        else:
            if vit is None:
                raise ValueError("ViTFeatures: give name= or vit= (a mapping of ViT sizes with 'layers')")
            kw = dict(vit)
            layers = kw.pop("layers", None)
            if layers is None:
                raise ValueError("ViTFeatures: the vit mapping needs 'layers' (four block indices)")
            self.vit = VisionTransformer(size=None, pos_interp=interp, **kw)
            default_ch = (48, 96, 192, 384)
        self.name = name or "custom"
        self.layers = tuple(int(i) for i in layers)
        if len(self.layers) != 4 or max(self.layers) != self.vit.depth - 1:
            raise ValueError(f"ViTFeatures: layers must be four block indices ending at the last block "
                             f"({self.vit.depth - 1}), got {self.layers}")
        if state is not None:
            from .convert import load_strict
            load_strict(self.vit, state, os.fspath(pretrained))
            log.info("encoder %s: loaded %s", self.name, pretrained)
        else:
            log.info("encoder %s: random initialisation (set model.pretrained=/path/to/dinov2 weights)", self.name)
        self.channels = tuple(int(c) for c in (channels or default_ch))
        d = self.vit.embed_dim
        c = self.channels
        self.projects = nn.ModuleList(nn.Conv2d(d, ci, 1) for ci in c)
        self.resize_layers = nn.ModuleList([nn.ConvTranspose2d(c[0], c[0], 4, stride=4),
                                            nn.ConvTranspose2d(c[1], c[1], 2, stride=2), nn.Identity(),
                                            nn.Conv2d(c[3], c[3], 3, stride=2, padding=1)])
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.freeze = freeze
        self._apply_freeze(freeze)

    def _apply_freeze(self, freeze: str | int) -> None:
        if freeze in ("none", None, 0, False):
            return
        if freeze == "all" or freeze is True:
            for p in self.vit.parameters():
                p.requires_grad_(False)
            return
        if isinstance(freeze, int) and 0 < freeze <= self.vit.depth:
            for mod in (self.vit.patch_embed,):
                for p in mod.parameters():
                    p.requires_grad_(False)
            self.vit.cls_token.requires_grad_(False)
            self.vit.pos_embed.requires_grad_(False)
            for block in self.vit.blocks[:freeze]:
                for p in block.parameters():
                    p.requires_grad_(False)
            return
        raise ValueError(f"encoder freeze must be 'none', 'all' or a number of blocks in 1..{self.vit.depth}, "
                         f"got {freeze!r}")

    @property
    def reduction(self) -> int:
        return 32

    def forward(self, x: Tensor) -> list[Tensor]:
        check_image(x, f"ViTFeatures({self.name})", 32)
        h, w = x.shape[-2] // 16, x.shape[-1] // 16
        p = self.vit.patch_size
        x = F.interpolate(x, size=(h * p, w * p), mode="bilinear", align_corners=False, antialias=True)
        x = (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)
        feats = []
        for i, (tok, _cls) in enumerate(self.vit.intermediate(x, self.layers)):
            m = tok.permute(0, 2, 1).reshape(tok.shape[0], tok.shape[-1], h, w)
            feats.append(self.resize_layers[i](self.projects[i](m)))
        return feats


def build_encoder(encoder: str | Mapping[str, Any], pretrained: str | os.PathLike | None = None) -> ViTFeatures:
    """:class:`ViTFeatures` from ``model.encoder``: a name of :data:`ENCODERS` or a mapping
    ``{name: ..., freeze: ..., channels: ..., vit: {...}}``."""
    if isinstance(encoder, str):
        return ViTFeatures(encoder, pretrained=pretrained)
    if isinstance(encoder, Mapping):
        kw = dict(encoder)
        return ViTFeatures(kw.pop("name", None), pretrained=kw.pop("pretrained", pretrained), **kw)
    raise ValueError(f"encoder must be a name ({sorted(ENCODERS)}) or a mapping, got {encoder!r}")


__all__ = ["ViTFeatures", "build_encoder", "ENCODERS", "STRIDES"]
