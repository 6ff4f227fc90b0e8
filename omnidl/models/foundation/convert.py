"""Read foundation-model checkpoints from disk and map their parameter names onto omnidl's modules.

Nothing is downloaded. Accepted files (``path`` may also be a folder holding exactly one of them):

=============================================  ==========================================  ===================
file (as published)                            layout                                      ``pos_interp``
=============================================  ==========================================  ===================
``depth_anything_v2_vit{s,b,l}.pth``           Depth-Anything-V2 code: ``pretrained.*``,   ``dinov2``
``depth_anything_v2_metric_{hypersim,vkitti}`` ``depth_head.*`` (:class:`DepthAnythingV2`
``_vit{s,b,l}.pth``                            names exactly)
``model.safetensors`` / ``pytorch_model.bin``  transformers ``DepthAnythingForDepthEstimation``  ``hf``
(+ ``config.json``), e.g. the                  (``backbone.*``, ``neck.*``, ``head.*``; old
``depth-anything/Depth-Anything-V2-Small-hf``  ``attention.attention.query`` and new
repository                                     ``attention.q_proj`` names)
``dinov2_vit{s,b,l,g}14_pretrain.pth``         DINOv2 code (``blocks.i.*``, ``mask_token``)  ``dinov2``
timm ``vit_*_patch14_dinov2`` state dict       timm (``blocks.i.*``)                        ``timm``
(``model.safetensors`` / ``pytorch_model.bin``
of ``timm/vit_small_patch14_dinov2.lvd142m``)
transformers ``Dinov2Model``                   ``embeddings.*``, ``encoder.layer.i.*``      ``hf``
=============================================  ==========================================  ===================

A ``.safetensors`` file is read with the ``safetensors`` package (the ``foundation`` extra); ``.pth``/``.bin``/
``.pt`` with ``torch.load(weights_only=True)`` (a file holding pickled code is refused, never run). Checkpoints with
register tokens (``*_reg4``) or DINOv3's RoPE are refused with their name: omnidl does not implement them.
"""
from __future__ import annotations

import json
import logging
import os
import re
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import Tensor

from .._weights import load_strict

log = logging.getLogger(__name__)

WEIGHT_SUFFIXES = (".safetensors", ".pth", ".pt", ".bin")
#: embed_dim -> ViT size name
_SIZE_OF_DIM = {384: "vits", 768: "vitb", 1024: "vitl", 1536: "vitg"}


# ------------------------------------------------------------------------------------------------------------------
# files
# ------------------------------------------------------------------------------------------------------------------

def find_weights(path: str | os.PathLike) -> Path:
    """The weights file ``path`` names: the file itself, or the one weights file inside a folder."""
    p = Path(path)
    if p.is_file():
        return p
    if p.is_dir():
        found = sorted(f for f in p.iterdir() if f.is_file() and f.suffix in WEIGHT_SUFFIXES)
        preferred = [f for f in found if f.name in ("model.safetensors", "pytorch_model.bin")]
        if len(preferred) == 1:
            return preferred[0]
        if len(found) == 1:
            return found[0]
        raise FileNotFoundError(f"{p}: expected one weights file ({', '.join(WEIGHT_SUFFIXES)}) in the folder, found "
                                f"{[f.name for f in found] or 'none'}; pass the file itself")
    raise FileNotFoundError(f"weights {str(p)!r} do not exist (nothing is downloaded: download the checkpoint "
                            "yourself, see docs/foundation.md)")


def read_state_dict(path: str | os.PathLike) -> dict[str, Tensor]:
    """The tensors of a ``.safetensors``/``.pth``/``.pt``/``.bin`` file (a ``state_dict``/``model`` entry is
    unwrapped, ``module.`` prefixes removed), with errors naming the file."""
    p = find_weights(path)
    if p.suffix == ".safetensors":
        try:
            from safetensors.torch import load_file
        except ImportError as e:  # pragma: no cover - depends on the environment
            raise ImportError(f"{p}: reading .safetensors needs the 'safetensors' package: "
                              "pip install 'omnidl[foundation]'") from e
        try:
            sd = load_file(str(p), device="cpu")
        except Exception as e:  # noqa: BLE001 (truncated or not safetensors)
            raise ValueError(f"{p}: not a readable safetensors file ({str(e).splitlines()[0]})") from e
    else:
        try:
            sd = torch.load(str(p), map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 (truncated, not torch, or pickled code)
            raise ValueError(f"{p}: could not read it with torch.load(weights_only=True): "
                             f"{str(e).splitlines()[0]}") from e
        for key in ("state_dict", "model"):
            if isinstance(sd, dict) and isinstance(sd.get(key), dict):
                sd = sd[key]
    if not isinstance(sd, dict) or not sd or not all(isinstance(v, Tensor) for v in sd.values()):
        raise ValueError(f"{p}: expected a state dict of tensors, got {type(sd).__name__}")
    return {k.removeprefix("module."): v for k, v in sd.items()}


def read_hf_config(path: str | os.PathLike) -> dict[str, Any]:
    """``config.json`` beside a transformers weights file (``{}`` when there is none)."""
    p = find_weights(path).parent / "config.json"
    if not p.is_file():
        return {}
    try:
        return json.loads(p.read_text())
    except ValueError as e:
        raise ValueError(f"{p}: not valid JSON ({e})") from e


# ------------------------------------------------------------------------------------------------------------------
# layouts
# ------------------------------------------------------------------------------------------------------------------

def detect_layout(sd: Mapping[str, Tensor]) -> str:
    """``"depth_anything_v2"``, ``"hf_depth_anything"``, ``"dinov2"``, ``"timm"`` or ``"hf_dinov2"``."""
    keys = list(sd)
    if any(k.startswith(("register_tokens", "reg_token")) or ".register_tokens" in k for k in keys):
        raise ValueError("checkpoint has register tokens (DINOv2 *_reg4): not supported by omnidl's ViT")
    if any("rope" in k or k.startswith("storage_tokens") for k in keys):
        raise ValueError("checkpoint looks like DINOv3 (RoPE / storage tokens): not supported by omnidl's ViT")
    if any(k.startswith("depth_head.") for k in keys) and any(k.startswith("pretrained.") for k in keys):
        return "depth_anything_v2"
    if any(k.startswith("backbone.embeddings.") for k in keys) and any(k.startswith("neck.") for k in keys):
        return "hf_depth_anything"
    if any(k.startswith(("embeddings.", "dinov2.embeddings.")) for k in keys):
        return "hf_dinov2"
    if "pos_embed" in sd and any(k.startswith("blocks.") for k in keys):
        if "mask_token" in sd or any(".mlp.w12." in k for k in keys) or any(re.match(r"blocks\.\d+\.\d+\.", k)
                                                                            for k in keys):
            return "dinov2"
        return "timm"
    raise ValueError(f"unrecognised checkpoint layout (first keys: {keys[:5]}); expected Depth-Anything-V2, "
                     "transformers DepthAnything / Dinov2, DINOv2 or timm ViT weights")


POS_INTERP_OF_LAYOUT = {"depth_anything_v2": "dinov2", "dinov2": "dinov2", "timm": "timm", "hf_dinov2": "hf",
                        "hf_depth_anything": "hf"}


def vit_from_dinov2(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """DINOv2 code / timm keys -> :class:`~omnidl.models.foundation.vit.VisionTransformer` keys (drops
    ``mask_token`` and a classifier ``head``; flattens chunked blocks; ``w12``/``w3`` -> ``fc1``/``fc2``)."""
    out = {}
    for k, v in sd.items():
        if k in ("mask_token",) or k.startswith(("head.", "fc_norm.")):
            continue
        k = re.sub(r"^blocks\.\d+\.(\d+)\.", r"blocks.\1.", k)
        k = k.replace(".mlp.w12.", ".mlp.fc1.").replace(".mlp.w3.", ".mlp.fc2.")
        out[k] = v
    return out


_HF_LAYER = [
    (r"norm1\.", "norm1."), (r"norm2\.", "norm2."),
    (r"layer_scale1\.lambda1$", "ls1.gamma"), (r"layer_scale2\.lambda1$", "ls2.gamma"),
    (r"attention\.output\.dense\.", "attn.proj."), (r"attention\.o_proj\.", "attn.proj."),
    (r"mlp\.fc1\.", "mlp.fc1."), (r"mlp\.fc2\.", "mlp.fc2."),
    (r"mlp\.weights_in\.", "mlp.fc1."), (r"mlp\.weights_out\.", "mlp.fc2."), (r"mlp\.down_proj\.", "mlp.fc2."),
]
_HF_QKV = {"attention.attention.query.": 0, "attention.attention.key.": 1, "attention.attention.value.": 2,
           "attention.q_proj.": 0, "attention.k_proj.": 1, "attention.v_proj.": 2}
_HF_GLU = {"mlp.gate_proj.": 0, "mlp.up_proj.": 1}


def vit_from_hf(sd: Mapping[str, Tensor], prefix: str = "") -> dict[str, Tensor]:
    """transformers ``Dinov2Model``/``Dinov2Backbone`` keys (under ``prefix``) -> ViT keys; separate q/k/v (and
    SwiGLU gate/up) projections are concatenated into ``qkv`` (``fc1``)."""
    out: dict[str, Tensor] = {}
    parts: dict[str, dict[int, Tensor]] = {}
    for k, v in sd.items():
        if not k.startswith(prefix):
            continue
        k = k[len(prefix):]
        if k == "embeddings.cls_token":
            out["cls_token"] = v
        elif k == "embeddings.position_embeddings":
            out["pos_embed"] = v
        elif k.startswith("embeddings.patch_embeddings.projection."):
            out["patch_embed.proj." + k.rsplit(".", 1)[1]] = v
        elif k == "embeddings.mask_token":
            continue
        elif k.startswith("layernorm."):
            out["norm." + k.rsplit(".", 1)[1]] = v
        elif (m := re.match(r"encoder\.layer\.(\d+)\.(.+)$", k)):
            i, rest = m.groups()
            for pat, idx in list(_HF_QKV.items()) + list(_HF_GLU.items()):
                if rest.startswith(pat):
                    target = "attn.qkv." if pat in _HF_QKV else "mlp.fc1."
                    parts.setdefault(f"blocks.{i}.{target}{rest[len(pat):]}", {})[idx] = v
                    break
            else:
                for pat, rep in _HF_LAYER:
                    if re.match(pat, rest):
                        out[f"blocks.{i}." + re.sub("^" + pat, rep, rest)] = v
                        break
                else:
                    raise KeyError(f"transformers DINOv2 checkpoint: unexpected key {prefix + k!r}")
        else:
            raise KeyError(f"transformers DINOv2 checkpoint: unexpected key {prefix + k!r}")
    for k, pieces in parts.items():
        n = 3 if ".attn.qkv." in k else 2
        if sorted(pieces) != list(range(n)):
            raise KeyError(f"transformers DINOv2 checkpoint: incomplete projections for {k!r}")
        out[k] = torch.cat([pieces[j] for j in range(n)], 0)
    return out


def depth_anything_from_original(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """Published Depth-Anything-V2 ``.pth`` -> :class:`DepthAnythingV2` keys (drops the never-used
    ``pretrained.mask_token`` and ``depth_head.scratch.refinenet4.resConfUnit1.*``)."""
    out = {}
    for k, v in sd.items():
        if k == "pretrained.mask_token" or k.startswith("depth_head.scratch.refinenet4.resConfUnit1."):
            continue
        if k.startswith("pretrained."):
            k = "pretrained." + next(iter(vit_from_dinov2({k[len("pretrained."):]: v})), k[len("pretrained."):])
        out[k] = v
    return out


_HF_NECK_RCU = {"convolution1": "conv1", "convolution2": "conv2"}


def depth_anything_from_hf(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """transformers ``DepthAnythingForDepthEstimation`` -> :class:`DepthAnythingV2` keys.

    ``neck.reassemble_stage.layers.i.{projection,resize}`` -> ``depth_head.{projects,resize_layers}.i``,
    ``neck.convs.i`` -> ``scratch.layer{i+1}_rn``, ``neck.fusion_stage.layers.j`` -> ``scratch.refinenet{4-j}``
    (``residual_layer{1,2}.convolution{1,2}`` -> ``resConfUnit{1,2}.conv{1,2}``, ``projection`` -> ``out_conv``;
    the never-used ``residual_layer1`` of layer 0 is dropped), ``head.conv1`` -> ``scratch.output_conv1``,
    ``head.conv2``/``conv3`` -> ``scratch.output_conv2.0``/``.2``."""
    out = {"pretrained." + k: v for k, v in vit_from_hf(sd, prefix="backbone.").items()}
    for k, v in sd.items():
        if k.startswith("backbone."):
            continue
        if (m := re.match(r"neck\.reassemble_stage\.layers\.(\d)\.(projection|resize)\.(weight|bias)$", k)):
            i, part, p = m.groups()
            out[f"depth_head.{'projects' if part == 'projection' else 'resize_layers'}.{i}.{p}"] = v
        elif (m := re.match(r"neck\.convs\.(\d)\.weight$", k)):
            out[f"depth_head.scratch.layer{int(m.group(1)) + 1}_rn.weight"] = v
        elif (m := re.match(r"neck\.fusion_stage\.layers\.(\d)\.(.+)$", k)):
            j, rest = int(m.group(1)), m.group(2)
            r = f"depth_head.scratch.refinenet{4 - j}."
            if (m2 := re.match(r"residual_layer([12])\.(convolution[12])\.(weight|bias)$", rest)):
                unit, conv, p = m2.groups()
                if j == 0 and unit == "1":
                    continue
                out[f"{r}resConfUnit{unit}.{_HF_NECK_RCU[conv]}.{p}"] = v
            elif (m2 := re.match(r"projection\.(weight|bias)$", rest)):
                out[f"{r}out_conv.{m2.group(1)}"] = v
            else:
                raise KeyError(f"transformers DepthAnything checkpoint: unexpected key {k!r}")
        elif (m := re.match(r"head\.conv([123])\.(weight|bias)$", k)):
            c, p = m.groups()
            name = {"1": "output_conv1", "2": "output_conv2.0", "3": "output_conv2.2"}[c]
            out[f"depth_head.scratch.{name}.{p}"] = v
        else:
            raise KeyError(f"transformers DepthAnything checkpoint: unexpected key {k!r}")
    return out


def vit_state_dict(sd: Mapping[str, Tensor]) -> tuple[dict[str, Tensor], str]:
    """A ViT state dict in omnidl's names from any supported layout, and the layout's ``pos_interp``.

    A Depth-Anything checkpoint gives its encoder (``pretrained.*`` / ``backbone.*``)."""
    layout = detect_layout(sd)
    if layout == "depth_anything_v2":
        full = depth_anything_from_original(sd)
        vit = {k[len("pretrained."):]: v for k, v in full.items() if k.startswith("pretrained.")}
    elif layout == "hf_depth_anything":
        vit = vit_from_hf(sd, prefix="backbone.")
    elif layout == "hf_dinov2":
        prefix = "dinov2." if any(k.startswith("dinov2.") for k in sd) else ""
        vit = vit_from_hf({k: v for k, v in sd.items() if not k.startswith("classifier.")}, prefix=prefix)
    else:
        vit = vit_from_dinov2(sd)
    return vit, POS_INTERP_OF_LAYOUT[layout]


def vit_size_of(vit_sd: Mapping[str, Tensor]) -> str | None:
    """``"vits"``/... from the embedding width and block count of a ViT state dict (``None``: not a published
    size)."""
    dim = int(vit_sd["cls_token"].shape[-1])
    depth = 1 + max(int(k.split(".")[1]) for k in vit_sd if k.startswith("blocks."))
    size = _SIZE_OF_DIM.get(dim)
    from .vit import VIT_SIZES
    return size if size is not None and VIT_SIZES[size][1] == depth else None


def _max_depth_from_name(name: str) -> float | None:
    if "metric_hypersim" in name:
        return 20.0
    if "metric_vkitti" in name:
        return 80.0
    return None


def load_depth_anything(path: str | os.PathLike, encoder: Any = "vits", max_depth: float | None = None,
                        pos_interp: str | None = None, **kwargs: Any):
    """A :class:`~omnidl.models.foundation.dpt.DepthAnythingV2` built to fit the checkpoint at ``path`` and loaded
    strictly (see the module docstring for the files).

    The encoder size comes from the weights; ``max_depth`` from the argument, else from a transformers
    ``config.json`` (``depth_estimation_type: metric``), else from a published metric file name
    (``..._metric_hypersim_...``: 20 m, ``..._metric_vkitti_...``: 80 m, as the Depth-Anything-V2 README).
    """
    from .dpt import DA2_CONFIGS, DepthAnythingV2
    file = find_weights(path)
    sd = read_state_dict(file)
    layout = detect_layout(sd)
    if layout == "depth_anything_v2":
        conv = depth_anything_from_original(sd)
    elif layout == "hf_depth_anything":
        conv = depth_anything_from_hf(sd)
        cfg = read_hf_config(file)
        if max_depth is None and cfg.get("depth_estimation_type") == "metric":
            max_depth = float(cfg.get("max_depth") or 0) or None
            if max_depth is None:
                raise ValueError(f"{file.parent / 'config.json'}: a metric model without max_depth")
    else:
        raise ValueError(f"{file}: holds a bare {layout} encoder, not a Depth-Anything-V2 model (use it as "
                         "model.encoder with model.pretrained=... instead)")
    if max_depth is None:
        max_depth = _max_depth_from_name(file.name)
        if max_depth is not None:
            log.info("%s: metric Depth-Anything-V2 with max_depth %.0f m (from the file name)", file, max_depth)
    vit = {k[len("pretrained."):]: v for k, v in conv.items() if k.startswith("pretrained.")}
    size = vit_size_of(vit)
    if isinstance(encoder, str):
        if size is None:
            raise ValueError(f"{file}: encoder of width {vit['cls_token'].shape[-1]} is no published ViT size; pass "
                             "encoder= as a mapping of its sizes")
        if size != encoder:
            log.info("%s: the weights are a %s model (encoder=%r ignored)", file, size, encoder)
        encoder = size
    oc = [int(conv[f"depth_head.projects.{i}.weight"].shape[0]) for i in range(4)]
    feats = int(conv["depth_head.scratch.layer1_rn.weight"].shape[0])
    if not isinstance(encoder, str) or (feats, tuple(oc)) != DA2_CONFIGS[encoder]:
        kwargs.setdefault("features", feats)
        kwargs.setdefault("out_channels", oc)
    if "depth_head.scratch.refinenet1.resConfUnit1.bn1.weight" in conv:
        kwargs.setdefault("use_bn", True)
    if "depth_head.readout_projects.0.0.weight" in conv:
        kwargs.setdefault("use_clstoken", True)
    model = DepthAnythingV2(encoder, max_depth=max_depth, pos_interp=pos_interp or POS_INTERP_OF_LAYOUT[layout],
                            **kwargs)
    load_strict(model, conv, str(file))
    log.info("Depth-Anything-V2 (%s, %s): loaded %s", encoder if isinstance(encoder, str) else "custom",
             "relative" if max_depth is None else f"metric, max {max_depth:g} m", file)
    return model


__all__ = ["read_state_dict", "read_hf_config", "find_weights", "detect_layout", "vit_from_dinov2", "vit_from_hf",
           "depth_anything_from_original", "depth_anything_from_hf", "vit_state_dict", "vit_size_of", "load_strict",
           "load_depth_anything"]
