"""U-Net (Ronneberger et al. 2015) for depth and/or semantic segmentation, with standard or calibrated
convolutions (thesis ch. 7, §7.4).

``conv="projected"`` (the calibrated convolution of the thesis; ``"calibrated"`` is a deprecated alias)
swaps every 3×3 convolution for a :class:`omnidl.nn.ProjectedConv2d` built
from the camera of the network's input image (:func:`omnidl.nn.convert_conv2d`). The layers keep
the same ``Parameter`` objects, so the state-dict keys are identical: weights trained with
``conv="standard"`` on perspective images load unchanged into the calibrated network (the
protocol of §7.4: train on perspective, evaluate/fine-tune on fisheye).

Shapes: ``forward(image (B, 3, H, W)) -> {"depth": (B, 1, H, W) metres (>= 0), "semantic":
(B, num_classes, H, W) logits}`` (only the heads of ``tasks``). Any ``H, W`` works (skips are
resized when a level has an odd size). With a camera, the input must show the camera's image,
possibly uniformly resized: its aspect ratio must match the calibration (a clear error otherwise).
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from omnidl.cameras.base import Camera
from omnidl.cameras.resolve import check_image_size, resolve_camera
from omnidl.nn import ProjectedConv2d, convert_conv2d
from omnidl.nn.conv_switch import conv_choice

from ._checks import check_image
from ._weights import load_weights
from .registry import register_model

TASKS = ("depth", "semantic")

torch.fx.wrap("check_image")
torch.fx.wrap("check_image_size")


class DoubleConv(nn.Sequential):
    """(3×3 conv → BatchNorm → ReLU) × 2."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class Up(nn.Module):
    """Bilinear ×2 upsampling, concatenation with the skip, :class:`DoubleConv`."""

    def __init__(self, cin: int, cskip: int, cout: int) -> None:
        super().__init__()
        self.conv = DoubleConv(cin + cskip, cout)

    def forward(self, x: Tensor, skip: Tensor) -> Tensor:
        x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.conv(torch.cat([x, skip], 1))


class UNet(nn.Module):
    """U-Net encoder–decoder with one head per task.

    Args:
        tasks: ``["depth"]``, ``["semantic"]`` or both.
        num_classes: semantic classes including unknown (14 for Stanford2D3DS).
        base_channels: channels of the first level (doubled at each of the ``levels`` downsamplings).
        levels: number of 2× max-pool downsamplings (the input is reduced ``2**levels`` times).
        conv: ``"standard"`` (``nn.Conv2d``) or ``"projected"`` (``ProjectedConv2d`` from ``camera``, the
            calibrated convolution); ``"calibrated"`` is a deprecated alias (:mod:`omnidl.nn.conv_switch`).
        camera: the camera of the input image (needed for ``"projected"``): a ``Camera``, a config
            mapping, a ``configs/camera`` name, a YAML file or a KB calibration text file.
        pretrained: optional local checkpoint (omnidl checkpoint or bare state dict) to load.
        pretrained_strict: fail when the checkpoint's keys do not match exactly.
        max_depth: optional upper bound of the depth head (metres); ``None``: softplus only.
        conv_kwargs: extra options of ``ProjectedConv2d`` (``backend``, ``kernel``, ``image_padding``).
    """

    def __init__(self, tasks: Sequence[str] = TASKS, num_classes: int = 14, base_channels: int = 32,
                 levels: int = 4, conv: str = "standard", camera: Any = None,
                 pretrained: str | os.PathLike | None = None, pretrained_strict: bool = True,
                 max_depth: float | None = None, conv_kwargs: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        tasks = tuple(tasks)
        if not tasks or set(tasks) - set(TASKS):
            raise ValueError(f"unet: tasks must be a non-empty subset of {TASKS}, got {tasks}")
        conv = conv_choice(conv, "unet")
        if levels < 1 or base_channels < 1:
            raise ValueError(f"unet: levels and base_channels must be >= 1, got {levels}, {base_channels}")
        self.tasks, self.num_classes, self.max_depth = tasks, int(num_classes), max_depth
        ch = [base_channels * 2 ** i for i in range(levels + 1)]
        self.inc = DoubleConv(3, ch[0])
        self.down = nn.ModuleList(DoubleConv(ch[i], ch[i + 1]) for i in range(levels))
        self.up = nn.ModuleList(Up(ch[i + 1], ch[i], ch[i]) for i in reversed(range(levels)))
        self.heads = nn.ModuleDict()
        if "depth" in tasks:
            self.heads["depth"] = nn.Conv2d(ch[0], 1, 1)
        if "semantic" in tasks:
            self.heads["semantic"] = nn.Conv2d(ch[0], num_classes, 1)
        if pretrained:
            self.load_pretrained(pretrained, strict=pretrained_strict)
        self.conv = "standard"
        self.camera: Camera | None = None
        if conv == "projected":
            self.calibrate(camera, **dict(conv_kwargs or {}))

    def load_pretrained(self, path: str | os.PathLike, strict: bool = True) -> None:
        """Load weights from a local checkpoint (nothing is downloaded)."""
        if not os.path.isfile(path):
            raise FileNotFoundError(f"unet: pretrained weights {str(path)!r} do not exist; set model.pretrained to "
                                    "a local checkpoint (e.g. the Pers baseline of the fisheye protocol) or null")
        load_weights(self, path, strict=strict)

    def calibrate(self, camera: Any, **conv_kwargs: Any) -> "UNet":
        """Turn every 3×3 convolution into a calibrated one for ``camera`` (in place; weights kept)."""
        cam = resolve_camera(camera, default=None)
        if cam is None:
            raise ValueError("unet: conv='projected' needs the camera of the input images (model.camera: a camera "
                             "config, a configs/camera name or a calibration file)")
        already = [m for m in self.modules() if isinstance(m, ProjectedConv2d)]
        for m in already:  # re-calibration for another camera
            m.camera = cam
        convert_conv2d(self, cam, **conv_kwargs)
        self.conv, self.camera = "projected", cam
        return self

    def standardize(self) -> "UNet":
        """Back to standard convolutions (the layers keep their type; without a camera they are ``nn.Conv2d``)."""
        for m in self.modules():
            if isinstance(m, ProjectedConv2d):
                m.camera = None
        self.conv, self.camera = "standard", None
        return self

    def forward(self, image: Tensor) -> dict[str, Tensor]:
        check_image(image, "unet")
        if self.camera is not None:
            check_image_size(image.shape[-2:], self.camera, "unet input")
        x = self.inc(image)
        skips = [x]
        for block in self.down:
            x = block(F.max_pool2d(x, 2, ceil_mode=True))
            skips.append(x)
        skips.pop()
        for block in self.up:
            x = block(x, skips.pop())
        out: dict[str, Tensor] = {}
        if "depth" in self.heads:
            d = F.softplus(self.heads["depth"](x))
            out["depth"] = d.clamp_max(self.max_depth) if self.max_depth else d
        if "semantic" in self.heads:
            out["semantic"] = self.heads["semantic"](x)
        return out


@register_model(smoke_kwargs={"base_channels": 4, "levels": 2}, smoke_size=(32, 48))
def unet(**kwargs: Any) -> UNet:
    """U-Net for depth/semantic segmentation; ``conv="standard"|"projected"`` (see :class:`UNet`)."""
    return UNet(**kwargs)
