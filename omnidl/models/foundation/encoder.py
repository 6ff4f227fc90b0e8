"""A DINOv2 / DINOv3 ViT as the multi-scale encoder of FreDSNet / HorizonNet (``model.encoder=dinov2_s``,
``model.encoder=dinov3_s``).

Same interface as :class:`omnidl.models._backbone.ResNetFeatures`: ``(B, 3, H, W)`` RGB in ``[0, 1]`` ->
four maps at strides ``(4, 8, 16, 32)`` of the input, with ``channels``, ``strides`` and ``reduction`` attributes::

    image (H x W, multiples of 32) -> patch 14 (DINOv2): bilinear (anti-aliased) to (14 H/16) x (14 W/16), one
    14-px patch per 16 input pixels | patch 16 (DINOv3): the image as it is, one patch per 16 pixels
    -> ImageNet normalisation -> ViT tokens of four blocks (final norm; class and register tokens dropped) on the
    (H/16) x (W/16) grid
    -> DPT reassembly: 1x1 conv to channels[i], then ConvTranspose x4 | ConvTranspose x2 | identity | 3x3 conv
    stride 2  -> (H/4, W/4), (H/8, W/8), (H/16, W/16), (H/32, W/32)

so any panorama size the ResNet takes works (the patch grid is the stride-16 map; a learned position embedding is
resampled to it, RoPE is computed for it). ``freeze``: ``"none"`` (fine-tune everything), ``"all"`` (the ViT is
frozen; the reassembly layers train) or an int ``k`` (patch/position embeddings, class and register tokens and the
first ``k`` blocks frozen). Frozen parameters have ``requires_grad=False``; the modules stay in the model (and its
state dict) and run in every mode.

Encoders (:data:`ENCODERS`; the four blocks read are the DPT / DINOv3 choice of evenly spaced blocks ending at the
last one: ``i * depth/4 - 1``, i.e. 2, 5, 8, 11 for 12 blocks, 7, 15, 23, 31 for 32; 24 blocks: 4, 11, 17, 23,
the indices of Depth-Anything-V2 and of DINOv3's own dense evaluations; 40 blocks (ViT-g): 9, 19, 29, 39):

* ``dinov2_s``, ``dinov2_b``, ``dinov2_l``, ``dinov2_g``: DINOv2 ViT-S/B/L/g, patch 14.
* ``dinov2_s_reg``, ``dinov2_b_reg``, ``dinov2_l_reg``, ``dinov2_g_reg``: the same with 4 registers
  (``dinov2_vit*14_reg4_pretrain.pth``, timm ``*_reg4_dinov2``, transformers ``Dinov2WithRegistersModel``).
* ``dinov3_s``, ``dinov3_s_plus``, ``dinov3_b``, ``dinov3_l``, ``dinov3_l_plus``, ``dinov3_h_plus``: DINOv3
  ViT-S/16, S+/16, B/16, L/16, L+/16, H+/16 (patch 16, RoPE, 4 registers).

``pretrained``: a local DINOv2 / DINOv3 / timm / transformers / Depth-Anything-V2 checkpoint
(:mod:`omnidl.models.foundation.convert`; a Depth-Anything-V2 file gives its fine-tuned encoder). A file of another
family or register count than ``name`` is refused with the encoder name that fits it; whether the qkv projection
has a bias is taken from the file (timm's DINOv3 models without ``_qkvb`` have none).
"""
from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .._checks import check_image
from .vit import DINOV3_SIZES, FAMILY_DEFAULTS, VIT_SIZES, VisionTransformer

log = logging.getLogger(__name__)

torch.fx.wrap("check_image")

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
_S, _B, _L = (48, 96, 192, 384), (96, 192, 384, 768), (256, 512, 1024, 1024)
_L12, _L24, _L32, _L40 = (2, 5, 8, 11), (4, 11, 17, 23), (7, 15, 23, 31), (9, 19, 29, 39)
#: name -> (VisionTransformer arguments, the four blocks read, reassembly channels)
ENCODERS: dict[str, tuple[dict[str, Any], tuple[int, ...], tuple[int, ...]]] = {
    "dinov2_s": ({"size": "vits"}, _L12, _S),
    "dinov2_b": ({"size": "vitb"}, _L12, _B),
    "dinov2_l": ({"size": "vitl"}, _L24, _L),
    "dinov2_g": ({"size": "vitg"}, _L40, (1536,) * 4),
    "dinov2_s_reg": ({"size": "vits", "num_registers": 4}, _L12, _S),
    "dinov2_b_reg": ({"size": "vitb", "num_registers": 4}, _L12, _B),
    "dinov2_l_reg": ({"size": "vitl", "num_registers": 4}, _L24, _L),
    "dinov2_g_reg": ({"size": "vitg", "num_registers": 4}, _L40, (1536,) * 4),
    "dinov3_s": ({"size": "vits16"}, _L12, _S),
    "dinov3_s_plus": ({"size": "vits16plus"}, _L12, _S),
    "dinov3_b": ({"size": "vitb16"}, _L12, _B),
    "dinov3_l": ({"size": "vitl16"}, _L24, _L),
    "dinov3_l_plus": ({"size": "vitl16plus"}, _L24, _L),
    "dinov3_h_plus": ({"size": "vith16plus"}, _L32, (320, 640, 1280, 1280)),
}
STRIDES = (4, 8, 16, 32)


def _file_kind(state: Mapping[str, Tensor]) -> tuple[str, int, int, int]:
    """``(family, registers, embed_dim, depth)`` of a converted ViT state dict (read by
    :func:`~omnidl.models.foundation.convert.vit_config_of`)."""
    from .convert import vit_config_of
    cfg = vit_config_of(state)
    return cfg["family"], cfg["num_registers"], cfg["embed_dim"], cfg["depth"]


def _fitting_encoders(kind: tuple[str, int, int, int]) -> list[str]:
    out = []
    for name, (args, _layers, _ch) in ENCODERS.items():
        size = args["size"]
        dim, depth = (VIT_SIZES[size][:2] if size in VIT_SIZES else DINOV3_SIZES[size][:2])
        family = "dinov2" if size in VIT_SIZES else "dinov3"
        regs = args.get("num_registers", FAMILY_DEFAULTS[family]["num_registers"])
        if (family, regs, dim, depth) == kind:
            out.append(name)
    return out


class ViTFeatures(nn.Module):
    """DINOv2 / DINOv3 encoder with DPT reassembly (module docstring).

    Args:
        name: a key of :data:`ENCODERS`, or ``None`` with ``vit`` (a mapping of :class:`VisionTransformer`
            arguments plus ``layers``) and ``channels`` (tiny test configurations).
        pretrained: local checkpoint path or ``None`` (random initialisation).
        freeze: ``"none"``, ``"all"`` or the number of leading blocks to freeze.
        channels: output channels of the four levels (default: the DPT widths of the size).
        pos_interp: how a learned position embedding is resampled (default: as the implementation that saved
            ``pretrained``; without a file ``"dinov2"``, with registers ``"dinov2_reg"``).
    """

    strides = STRIDES

    def __init__(self, name: str | None = "dinov2_s", pretrained: str | os.PathLike | None = None,
                 freeze: str | int = "none", channels: Sequence[int] | None = None,
                 vit: Mapping[str, Any] | None = None, pos_interp: str | None = None) -> None:
        super().__init__()
        state, file_interp = None, None
        if pretrained:
            from .convert import read_vit
            state, file_interp = read_vit(pretrained)
        if name is not None:
            if name not in ENCODERS:
                raise ValueError(f"unknown encoder {name!r}; choose one of {sorted(ENCODERS)} (or 'resnet')")
            args, layers, default_ch = ENCODERS[name]
            kw = dict(args)
        else:
            if vit is None:
                raise ValueError("ViTFeatures: give name= or vit= (a mapping of ViT sizes with 'layers')")
            kw = dict(vit)
            layers = kw.pop("layers", None)
            if layers is None:
                raise ValueError("ViTFeatures: the vit mapping needs 'layers' (four block indices)")
            kw.setdefault("size", None)
            default_ch = (48, 96, 192, 384)
        self.name = name or "custom"
        if state is not None:
            kw.setdefault("qkv_bias", "blocks.0.attn.qkv.bias" in state)
        interp = pos_interp or file_interp or ("dinov2_reg" if kw.get("num_registers") else "dinov2")
        self.vit = VisionTransformer(pos_interp=interp, **kw)
        self.layers = tuple(int(i) for i in layers)
        if len(self.layers) != 4 or max(self.layers) != self.vit.depth - 1:
            raise ValueError(f"ViTFeatures: layers must be four block indices ending at the last block "
                             f"({self.vit.depth - 1}), got {self.layers}")
        if state is not None:
            self._check_file(state, pretrained)
            from .convert import load_vit
            load_vit(self.vit, state, os.fspath(pretrained))
            log.info("encoder %s: loaded %s", self.name, pretrained)
        else:
            log.info("encoder %s: random initialisation (set model.pretrained=/path/to/%s weights)", self.name,
                     self.vit.family)
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

    def _check_file(self, state: Mapping[str, Tensor], pretrained: str | os.PathLike) -> None:
        """A file of another family or register count than the encoder: a ``ValueError`` naming what fits."""
        family, regs, dim, depth = kind = _file_kind(state)
        if (family, regs) == (self.vit.family, self.vit.num_registers):
            return
        fits = _fitting_encoders(kind)
        what = f"{family} ViT ({dim} wide, {depth} blocks, {regs} registers)"
        hint = f"use model.encoder={fits[0]}" if fits else "no encoder of ENCODERS fits it"
        raise ValueError(f"{os.fspath(pretrained)}: holds a {what}, but encoder {self.name!r} is a "
                         f"{self.vit.family} ViT with {self.vit.num_registers} registers; {hint}")

    def _apply_freeze(self, freeze: str | int) -> None:
        if freeze in ("none", None, 0, False):
            return
        if freeze == "all" or freeze is True:
            for p in self.vit.parameters():
                p.requires_grad_(False)
            return
        if isinstance(freeze, int) and 0 < freeze <= self.vit.depth:
            for p in self.vit.patch_embed.parameters():
                p.requires_grad_(False)
            for p in (self.vit.cls_token, self.vit.pos_embed, self.vit.register_tokens):
                if p is not None:
                    p.requires_grad_(False)
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
        if p != 16:
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


__all__ = ["ENCODERS", "STRIDES", "ViTFeatures", "build_encoder"]
