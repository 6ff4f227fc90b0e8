"""HorizonNet (Sun et al. 2019) and its non-central fine-tuning (thesis §5.3.1), size-agnostic.

``(B, 3, H, W)`` RGB in ``[0, 1]`` -> ``{"boundary": (B, 2, W), "corner": (B, 1, W)}``:

* ``boundary``: ceiling and floor boundary of every column as the angle below the horizon in
  radians (HorizonNet's convention ``theta = (v / H - 0.5) * pi`` for the continuous pixel row ``v``;
  negative = ceiling side; :func:`omnidl.geometry.boundary.rows_to_angles` / ``angles_to_rows``).
  The rays of a boundary pixel come from the camera model, so the same output serves an
  equirectangular (``camera="equirect"``) or a non-central panorama (``camera="noncentral_pano"``,
  thesis §5.3.1: every column is locally central).
* ``corner``: logits of a wall-wall corner at each column.

Architecture (as the reference, ``docs/design.md#horizonnet-architecture``): ResNet levels 1-4 ->
per level four height-compressing ``3x3`` convs (stride ``(2, 1)``, BN, ReLU; channels ``c -> c/2 ->
c/2 -> c/4 -> c/8``) with horizontal wrap-around padding -> each tower's height adaptively pooled to
``(8, 4, 2, 1)`` rows (exactly the reference's heights at 512 rows, so any input height works and
the sequence width is fixed) -> flattened and resampled to ``W / step_cols`` columns -> 2-layer
BiLSTM (or ``rnn=False``: per-step MLP) -> ``Linear(2 hidden, 3 step_cols)`` -> ``(B, 3, W)``.
Any ``H, W`` divisible by 32 (and ``W`` by ``step_cols``) works, e.g. 1024x512, 512x256, 128x64.

``convert_official_state_dict`` maps the official checkpoint layout (``feature_extractor.*``,
``reduce_height_module.*``, ``bi_rnn.*``, ``linear.*``) onto this module.
"""
from __future__ import annotations

import logging
import math
import os
import re
from typing import Any, Mapping

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from omnidl.nn.padding import CircularConv2d, pad_panorama

from ._backbone import ResNetFeatures
from ._checks import check_image
from ._memory_format import MemoryFormat
from .registry import register_model

log = logging.getLogger(__name__)

torch.fx.wrap("check_image")
torch.fx.wrap("pad_panorama")
torch.fx.wrap("resample_columns")

#: tower output heights (reference heights at 512 rows)
TOWER_HEIGHTS = (8, 4, 2, 1)
#: HorizonNet's head bias initialisation: ceiling, floor (radians), corner (logit)
BIAS_INIT = (-0.478, 0.425, -1.0)


class CompressHeight(nn.Module):
    """``3x3`` conv, stride ``(2, 1)``, horizontal wrap padding (:class:`~omnidl.nn.padding.CircularConv2d`; zeros
    with ``circular=False``), BN, ReLU: halves the height."""

    def __init__(self, cin: int, cout: int, circular: bool = True) -> None:
        super().__init__()
        self.circular = circular
        self.conv = (CircularConv2d if circular else nn.Conv2d)(cin, cout, 3, stride=(2, 1), padding=1)
        self.bn = nn.BatchNorm2d(cout)
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.act(self.bn(self.conv(x)))


class HeightTower(nn.Sequential):
    """Four :class:`CompressHeight` (channels ``c -> c/2 -> c/2 -> c/4 -> c/out_scale``)."""

    def __init__(self, c: int, out_scale: int = 8, circular: bool = True) -> None:
        super().__init__(CompressHeight(c, c // 2, circular), CompressHeight(c // 2, c // 2, circular),
                         CompressHeight(c // 2, c // 4, circular), CompressHeight(c // 4, c // out_scale, circular))


def resample_columns(x: Tensor, out_w: int) -> Tensor:
    """``(B, C, W) -> (B, C, out_w)`` linear resampling with circular boundary (pixel-centre aligned)."""
    W = x.shape[-1]
    if W == out_w:
        return x
    factor = max(1, out_w // W)
    xp = torch.cat([x[..., -1:], x, x[..., :1]], -1)
    y = F.interpolate(xp, size=out_w + 2 * factor, mode="linear", align_corners=False)
    return y[..., factor:factor + out_w]


class HorizonNet(MemoryFormat, nn.Module):
    """HorizonNet / non-central HorizonNet (see module docstring).

    Args:
        backbone: torchvision ResNet name (``resnet50`` in the thesis).
        pretrained: local path to torchvision ImageNet weights for the backbone (``None``: random).
        rnn: BiLSTM sequence model (``False``: the reference's ``--no_rnn`` MLP).
        hidden: LSTM hidden size (512 in the reference).
        step_cols: output columns per sequence step (4).
        out_scale: channel reduction of each height tower (8).
        circular: wrap-around horizontal padding in the towers and in every backbone conv.
        camera: ``"equirect"``/``"noncentral_pano"``, a camera config mapping or a ``Camera``; only
            recorded (``self.camera``): the network is per-column, geometry lives in targets and
            post-processing.
        dropout: dropout of the LSTM/head (0.5).
        channels_last: memory format of the convolutional part (:mod:`omnidl.models._memory_format`). Results equal
            up to float rounding.
        encoder: ``None`` (default): the ResNet ``backbone``. A foundation encoder instead
            (:mod:`omnidl.models.foundation.encoder`, e.g. ``"dinov2_s"`` or ``{name: dinov2_s, freeze: all}``), whose
            four maps (strides 4-32) feed the height towers; ``pretrained`` is then its local checkpoint. ``circular``
            applies to the towers only (the ViT has no padded convolutions).
    """

    def __init__(self, backbone: str = "resnet50", pretrained: str | None = None, rnn: bool = True, hidden: int = 512,
                 step_cols: int = 4, out_scale: int = 8, circular: bool = True, camera: Any = "equirect",
                 dropout: float = 0.5, channels_last: bool = False, encoder: Any = None) -> None:
        super().__init__()
        if encoder is None or encoder == "resnet":
            self.encoder = ResNetFeatures(backbone, pretrained=pretrained, out_indices=(1, 2, 3, 4))
            if circular:
                _wrap_convs(self.encoder)
                self.encoder.body.maxpool = CircularMaxPool2d()
        else:
            from .foundation.encoder import build_encoder
            self.encoder = build_encoder(encoder, pretrained)
        self.step_cols = int(step_cols)
        self.use_rnn = bool(rnn)
        chans = self.encoder.channels
        self.reduce_height = nn.ModuleList([HeightTower(c, out_scale, circular) for c in chans])
        self.feat_dim = sum((c // out_scale) * h for c, h in zip(chans, TOWER_HEIGHTS))
        if self.use_rnn:
            self.rnn = nn.LSTM(self.feat_dim, hidden, num_layers=2, dropout=dropout, batch_first=False,
                               bidirectional=True)
            self.drop = nn.Dropout(dropout)
            self.head = nn.Linear(2 * hidden, 3 * self.step_cols)
            last = self.head
        else:
            self.head = nn.Sequential(nn.Linear(self.feat_dim, hidden), nn.ReLU(inplace=True), nn.Dropout(dropout),
                                      nn.Linear(hidden, 3 * self.step_cols))
            last = self.head[3]
        with torch.no_grad():
            for k, v in enumerate(BIAS_INIT):
                last.bias[k * self.step_cols:(k + 1) * self.step_cols] = v
        self.camera = camera if not hasattr(camera, "to_config") else camera.to_config()
        self.set_memory_format(channels_last, "HorizonNet")

    def features(self, x: Tensor) -> Tensor:
        """``(B, 3, H, W) -> (B, feat_dim, W / step_cols)`` column features."""
        check_image(x, "HorizonNet", math.lcm(self.encoder.reduction, self.step_cols))
        B, W = x.shape[0], x.shape[-1]
        out_w = W // self.step_cols
        x = self.to_model_format(x)
        cols = []
        for f, tower, h in zip(self.encoder(x), self.reduce_height, TOWER_HEIGHTS):
            y = tower(f)
            y = F.adaptive_avg_pool2d(y, (h, y.shape[-1]))
            cols.append(resample_columns(y.reshape(B, -1, y.shape[-1]), out_w))
        return torch.cat(cols, 1)

    def forward(self, x: Tensor) -> dict[str, Tensor]:
        feat = self.features(x)                                   # (B, C, S)
        B, _, S = feat.shape
        if self.use_rnn:
            seq = feat.permute(2, 0, 1)                           # (S, B, C)
            out, _ = self.rnn(seq)
            out = self.head(self.drop(out))                       # (S, B, 3*step)
            out = out.permute(1, 0, 2)                            # (B, S, 3*step)
        else:
            out = self.head(feat.permute(0, 2, 1))                # (B, S, 3*step)
        out = out.reshape(B, S, 3, self.step_cols).permute(0, 2, 1, 3).reshape(B, 3, S * self.step_cols)
        return {"boundary": out[:, :2], "corner": out[:, 2:3]}


class CircularMaxPool2d(nn.Module):
    """ResNet's ``3x3`` stride-2 max-pool with horizontal wrap-around (vertical border: ``-inf``)."""

    def forward(self, x: Tensor) -> Tensor:
        return F.max_pool2d(pad_panorama(x, 1), 3, 2, padding=(1, 0))


def _wrap_convs(module: nn.Module) -> None:
    """Swap every ``nn.Conv2d`` with horizontal padding for a wrap-around one (same keys and weights)."""
    for name, child in list(module.named_children()):
        if type(child) is nn.Conv2d and child.padding != (0, 0) and isinstance(child.padding, tuple) \
                and child.padding[1] > 0:
            new = CircularConv2d(child.in_channels, child.out_channels, child.kernel_size, child.stride,
                                 child.padding, child.dilation, child.groups, child.bias is not None)
            new.load_state_dict(child.state_dict())
            setattr(module, name, new)
        else:
            _wrap_convs(child)


# ------------------------------------------------------------------------------------------------
# official checkpoint converter
# ------------------------------------------------------------------------------------------------

_RE_GHC = re.compile(r"^reduce_height_module\.ghc_lst\.(\d+)\.layer\.(\d+)\.layers\.(\d+)(?:\.1)?\.(.+)$")


def convert_official_state_dict(state: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """Map an official HorizonNet state dict onto :class:`HorizonNet` keys.

    Official layout: ``feature_extractor.encoder.<torchvision keys>`` (convs wrapped by
    ``wrap_lr_pad`` appear as ``<conv>.1.weight``), ``reduce_height_module.ghc_lst.i.layer.j.layers.
    {0[.1] conv, 1 bn}.*``, ``bi_rnn.*`` (or ``linear.{0,3}.*`` without RNN), ``linear.*``. A
    checkpoint dict with ``state_dict`` inside is accepted; ``module.`` prefixes are stripped.
    """
    if "state_dict" in state and isinstance(state["state_dict"], Mapping):
        state = state["state_dict"]
    use_rnn = any(k.startswith("bi_rnn.") for k in state)
    out: dict[str, Tensor] = {}
    for k, v in state.items():
        k = k[7:] if k.startswith("module.") else k
        if k.startswith("feature_extractor.encoder."):
            rest = k[len("feature_extractor.encoder."):]
            rest = re.sub(r"\.1\.(weight|bias)$", r".\1", rest) if re.search(r"conv\d?\.1\.(weight|bias)$", rest) \
                else rest
            out["encoder.body." + rest] = v
        elif (m := _RE_GHC.match(k)):
            i, j, part, p = m.groups()
            out[f"reduce_height.{i}.{j}.{'conv' if part == '0' else 'bn'}.{p}"] = v
        elif k.startswith("bi_rnn."):
            out["rnn." + k[len("bi_rnn."):]] = v
        elif k.startswith("linear."):
            out["head." + k[len("linear."):]] = v
        elif k in ("x_mean", "x_std"):
            continue
        else:
            raise KeyError(f"official HorizonNet checkpoint: unexpected key {k!r}")
    if not use_rnn and not any(k.startswith("head.0") for k in out):
        raise KeyError("official HorizonNet checkpoint: neither bi_rnn.* nor an MLP head found")
    return out


def load_official_checkpoint(model: HorizonNet, path: str | os.PathLike) -> None:
    """Load an official HorizonNet ``.pth`` (e.g. ``resnet50_rnn__st3d.pth``) strictly into ``model``."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"HorizonNet checkpoint {path!r} not found (download the official weights "
                                "yourself and point model.checkpoint_official=... to them)")
    try:  # weights_only: a .pth from the internet must not be able to run code when loaded
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 (truncated, not a torch file, or pickled objects)
        raise ValueError(f"{path}: could not read the HorizonNet checkpoint with torch.load(weights_only=True): "
                         f"{str(e).splitlines()[0]}") from e
    conv = convert_official_state_dict(state)
    own = model.state_dict()
    missing = [k for k in own if k not in conv]
    unexpected = [k for k in conv if k not in own]
    wrong = [k for k in conv if k in own and conv[k].shape != own[k].shape]
    if missing or unexpected or wrong:
        raise ValueError(f"{path}: checkpoint does not fit this HorizonNet (backbone/rnn options?): missing "
                         f"{missing[:6]}, unexpected {unexpected[:6]}, wrong shapes {wrong[:6]}")
    model.load_state_dict(conv, strict=True)


@register_model(smoke_kwargs=dict(backbone="resnet18", hidden=16), smoke_size=(64, 128))
def horizonnet(official_checkpoint: str | None = None, **kwargs: Any) -> HorizonNet:
    """HorizonNet (``camera="equirect"``) or non-central HorizonNet (``camera="noncentral_pano"``).

    ``official_checkpoint``: local path of an official HorizonNet ``.pth`` to start from.
    """
    model = HorizonNet(**kwargs)
    if official_checkpoint:
        load_official_checkpoint(model, official_checkpoint)
    return model
