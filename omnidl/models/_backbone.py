"""Shared torchvision ResNet feature extractor (FreDSNet, HorizonNet, HoLiNet, U-Net).

Usage::

    from omnidl.models._backbone import ResNetFeatures
    bb = ResNetFeatures("resnet50", pretrained=None)      # random init (default)
    bb = ResNetFeatures("resnet50", pretrained="weights/resnet50-0676ba61.pth")  # local ImageNet weights
    feats = bb(x)            # x: (B, 3, H, W) RGB in [0, 1]; list of (B, C_i, H/s_i, W/s_i)
    bb.channels, bb.strides  # per returned level, e.g. (256, 512, 1024, 2048), (4, 8, 16, 32)

Levels: ``0`` = stem (conv1-bn-relu, stride 2, before max-pool), ``1..4`` = ``layer1..layer4``
(strides 4, 8, 16, 32); ``out_indices`` picks them (default ``(1, 2, 3, 4)``).
The input is ImageNet-normalised inside (``normalize=True``; buffers are not saved in the state dict).

Nothing is downloaded: ``pretrained`` is a path to a local torchvision checkpoint (the files
torchvision's ``ResNet50_Weights.IMAGENET1K_V1`` etc. download, or any state dict with the
torchvision key names, optionally under ``"state_dict"``/``"model"`` and/or prefixed by
``"module."``/``"encoder."``). ``fc.*`` keys are ignored; any other missing/unexpected key is an error.
"""
from __future__ import annotations

import logging
import os
from typing import Sequence

import torch
import torch.nn as nn
import torchvision
from torch import Tensor

from ._checks import check_image
from ._weights import load_strict

log = logging.getLogger(__name__)

RESNETS = ("resnet18", "resnet34", "resnet50", "resnet101", "resnet152",
           "resnext50_32x4d", "resnext101_32x8d", "wide_resnet50_2", "wide_resnet101_2")
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
_STRIDES = (2, 4, 8, 16, 32)

torch.fx.wrap("check_image")


def build_resnet(name: str) -> nn.Module:
    """A randomly initialised torchvision ResNet ``name`` without ``fc`` and ``avgpool``."""
    if name not in RESNETS:
        raise ValueError(f"unknown backbone {name!r}; choose one of {list(RESNETS)}")
    net = getattr(torchvision.models, name)(weights=None)
    del net.fc, net.avgpool
    return net


def load_backbone_weights(net: nn.Module, path: str | os.PathLike) -> None:
    """Load a local torchvision ResNet checkpoint into ``net`` (from :func:`build_resnet`), strictly.

    Raises ``FileNotFoundError`` / ``ValueError`` naming the file and the offending keys.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(
            f"backbone weights {path!r} not found. Download torchvision's ImageNet checkpoint for this "
            "backbone yourself (e.g. resnet50-0676ba61.pth) and set model.pretrained=/path/to/it, "
            "or set model.pretrained=null for random initialisation")
    state = torch.load(path, map_location="cpu", weights_only=True)
    for key in ("state_dict", "model"):
        if isinstance(state, dict) and key in state and isinstance(state[key], dict):
            state = state[key]
    if not isinstance(state, dict):
        raise ValueError(f"backbone weights {path!r}: expected a state dict, got {type(state).__name__}")
    cleaned = {}
    for k, v in state.items():
        for prefix in ("module.", "encoder.", "backbone.", "body."):
            if k.startswith(prefix):
                k = k[len(prefix):]
        if not k.startswith("fc."):
            cleaned[k] = v
    load_strict(net, cleaned, f"backbone weights file {path!r}")


class ResNetFeatures(nn.Module):
    """Multi-scale features of a torchvision ResNet: ``(B, 3, H, W) -> [(B, C_i, H/s_i, W/s_i), ...]``.

    Args:
        name: torchvision model name (see ``RESNETS``).
        pretrained: path to local torchvision weights, or ``None`` for random initialisation.
        out_indices: levels to return (0 = stem, 1..4 = layer1..layer4).
        normalize: subtract the ImageNet mean / divide by std inside (input RGB in ``[0, 1]``).

    Attributes ``channels`` and ``strides`` describe the returned levels. The torchvision
    modules live under ``self.body`` (``body.conv1``, ``body.layer1``, ...).
    """

    def __init__(self, name: str = "resnet50", pretrained: str | os.PathLike | None = None,
                 out_indices: Sequence[int] = (1, 2, 3, 4), normalize: bool = True) -> None:
        super().__init__()
        self.name = name
        self.body = build_resnet(name)
        if pretrained:
            load_backbone_weights(self.body, pretrained)
            log.info("backbone %s: loaded weights from %s", name, pretrained)
        else:
            log.info("backbone %s: random initialisation (set model.pretrained=/path/to/%s.pth, a local "
                     "torchvision checkpoint, to start from ImageNet weights)", name, name)
        self.out_indices = tuple(sorted({int(i) for i in out_indices}))
        if not self.out_indices or any(i not in range(5) for i in self.out_indices):
            raise ValueError(f"out_indices must be a non-empty subset of 0..4, got {out_indices}")
        all_ch = self._level_channels()
        self.channels = tuple(all_ch[i] for i in self.out_indices)
        self.strides = tuple(_STRIDES[i] for i in self.out_indices)
        self.normalize = normalize
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def _level_channels(self) -> list[int]:
        b = self.body
        chans = [b.conv1.out_channels]
        for layer in (b.layer1, b.layer2, b.layer3, b.layer4):
            last = layer[-1]
            conv = getattr(last, "conv3", None) or last.conv2
            chans.append(conv.out_channels)
        return chans

    @property
    def reduction(self) -> int:
        """The largest stride among the returned levels (input sides must be multiples of it)."""
        return max(self.strides)

    def forward(self, x: Tensor) -> list[Tensor]:
        check_image(x, "ResNetFeatures")
        if self.normalize:
            x = (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)
        b = self.body
        x = b.relu(b.bn1(b.conv1(x)))
        feats = [x] if 0 in self.out_indices else []
        x = b.maxpool(x)
        for i, layer in enumerate((b.layer1, b.layer2, b.layer3, b.layer4), start=1):
            if i > max(self.out_indices):
                break
            x = layer(x)
            if i in self.out_indices:
                feats.append(x)
        return feats
