"""Read foundation-model checkpoints from disk and map their parameter names onto omnidl's modules.

Nothing is downloaded. Accepted files (``path`` may also be a folder holding exactly one of them), by layout
(:func:`detect_layout`, from the parameter names) and the ``pos_interp`` it gives:

* ``depth_anything_v2``: ``depth_anything_v2_vit{s,b,l}.pth``, ``depth_anything_v2_metric_{hypersim,vkitti}_vit
  {s,b,l}.pth`` (Depth-Anything-V2 code: ``pretrained.*``, ``depth_head.*``, :class:`DepthAnythingV2` names
  exactly); ``dinov2``.
* ``hf_depth_anything``: transformers ``DepthAnythingForDepthEstimation`` (``model.safetensors`` /
  ``pytorch_model.bin`` + ``config.json``, e.g. ``depth-anything/Depth-Anything-V2-Small-hf``; ``backbone.*``,
  ``neck.*``, ``head.*``; old ``attention.attention.query`` and new ``attention.q_proj`` names); ``hf``.
* ``dinov2``: the DINOv2 code, ``dinov2_vit{s,b,l,g}14_pretrain.pth`` (``blocks.i.*``, ``mask_token``);
  ``dinov2``. With registers, ``dinov2_vit{s,b,l,g}14_reg4_pretrain.pth`` (``register_tokens``): ``dinov2_reg``.
* ``timm``: timm ``vit_*_patch14_dinov2`` and ``vit_*_patch14_reg4_dinov2`` (``reg_token``, a class-less
  ``pos_embed``), e.g. ``model.safetensors`` of ``timm/vit_small_patch14_dinov2.lvd142m``; ``timm``.
* ``hf_dinov2``: transformers ``Dinov2Model`` (``embeddings.*``, ``encoder.layer.i.*``; ``hf``) and
  ``Dinov2WithRegistersModel`` (``embeddings.register_tokens``, e.g. ``facebook/dinov2-with-registers-small``;
  ``dinov2_reg``).
* ``dinov3``: facebookresearch/dinov3 ``dinov3_vit{s16,s16plus,b16,l16,h16plus}_pretrain_lvd1689m-<hash>.pth``
  (also ``vitl16`` ``sat493m``): ``storage_tokens``, ``rope_embed.periods``, ``qkv.bias_mask``, SwiGLU
  ``w1``/``w2``/``w3``.
* ``timm_dinov3``: timm ``vit_{small,small_plus,base,large,huge_plus}_patch16_dinov3[_qkvb]`` (``Eva``:
  ``reg_token``, ``gamma_1``, ``q_bias``/``v_bias``, SwiGLU ``fc1_g``/``fc1_x``).
* ``hf_dinov3``: transformers ``DINOv3ViTModel`` (``facebook/dinov3-vits16-pretrain-lvd1689m``: ``layer.i.*``;
  saved by transformers >= 5: ``model.layer.i.*``).
* ``omnidl_dinov3``: omnidl's own names (a saved DINOv3 :class:`~omnidl.models.foundation.vit.VisionTransformer`,
  ``rope.periods``). omnidl's DINOv2 names are those of the DINOv2 code (``dinov2``).

DINOv3 has no position table (RoPE): ``pos_interp`` is unused. Refused by name: a ConvNeXt (DINOv3's ConvNeXt
backbones), the DINOv3 ViT-7B, and Depth-Anything-V2 on anything but a DINOv2 encoder (the published models).

A ``.safetensors`` file is read with the ``safetensors`` package (the ``foundation`` extra); ``.pth``/``.bin``/
``.pt`` with ``torch.load(weights_only=True)`` (a file holding pickled code is refused, never run).
"""
from __future__ import annotations

import json
import logging
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

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
        except Exception as e:
            raise ValueError(f"{p}: not a readable safetensors file ({str(e).splitlines()[0]})") from e
    else:
        try:
            sd = torch.load(str(p), map_location="cpu", weights_only=True)
        except Exception as e:
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

_CONVNEXT_KEYS = ("dwconv", "conv_dw", "depthwise_conv", "downsample_layers.")
_DINOV3_SUPPORTED = ("vits16", "vits16plus", "vitb16", "vitl16", "vitl16plus", "vith16plus")


def detect_layout(sd: Mapping[str, Tensor]) -> str:
    """``"depth_anything_v2"``, ``"hf_depth_anything"``, ``"dinov2"``, ``"timm"``, ``"hf_dinov2"`` (DINOv2, with
    or without registers), ``"dinov3"``, ``"timm_dinov3"`` or ``"hf_dinov3"`` (DINOv3 ViTs); a DINOv3 ConvNeXt is
    refused by name."""
    keys = list(sd)
    if any(any(c in k for c in _CONVNEXT_KEYS) for k in keys):
        raise ValueError("checkpoint is a ConvNeXt (e.g. a DINOv3 ConvNeXt): omnidl implements only ViT encoders: "
                         "DINOv2 (with or without registers) and the DINOv3 ViTs " + ", ".join(_DINOV3_SUPPORTED))
    if any(k.startswith("depth_head.") for k in keys) and any(k.startswith("pretrained.") for k in keys):
        return "depth_anything_v2"
    if any(k.startswith("backbone.embeddings.") for k in keys) and any(k.startswith("neck.") for k in keys):
        return "hf_depth_anything"
    if any(k.startswith(("embeddings.", "dinov2.embeddings.", "dinov2_with_registers.embeddings.")) for k in keys):
        if "embeddings.patch_embeddings.weight" in sd or any(re.match(r"(model\.)?layer\.\d+\.", k) for k in keys):
            return "hf_dinov3"
        return "hf_dinov2"
    if "storage_tokens" in sd or "rope_embed.periods" in sd:
        return "dinov3"
    if "rope.periods" in sd:
        return "omnidl_dinov3"
    if "pos_embed" not in sd and any(re.match(r"blocks\.\d+\.gamma_1$", k) for k in keys):
        return "timm_dinov3"
    if "pos_embed" in sd and any(k.startswith("blocks.") for k in keys):
        if ("mask_token" in sd or "register_tokens" in sd or any(".mlp.w12." in k for k in keys)
                or any(re.match(r"blocks\.\d+\.\d+\.", k) for k in keys)):
            return "dinov2"
        return "timm"
    raise ValueError(f"unrecognised checkpoint layout (first keys: {keys[:5]}); expected Depth-Anything-V2, "
                     "transformers DepthAnything / Dinov2 / Dinov2WithRegisters / DINOv3ViT, DINOv2 or DINOv3 code, "
                     "or timm ViT weights")


POS_INTERP_OF_LAYOUT = {"depth_anything_v2": "dinov2", "dinov2": "dinov2", "timm": "timm", "hf_dinov2": "hf",
                        "hf_depth_anything": "hf", "dinov3": "dinov2", "timm_dinov3": "dinov2",
                        "hf_dinov3": "dinov2", "omnidl_dinov3": "dinov2"}
DINOV3_LAYOUTS = ("dinov3", "timm_dinov3", "hf_dinov3", "omnidl_dinov3")


def vit_from_dinov2(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """DINOv2 code / timm keys -> :class:`~omnidl.models.foundation.vit.VisionTransformer` keys (drops
    ``mask_token`` and a classifier ``head``; flattens chunked blocks; ``w12``/``w3`` -> ``fc1``/``fc2``).

    Registers: the DINOv2 code's ``register_tokens`` keep their name; timm's ``reg_token`` becomes
    ``register_tokens`` and timm's class-less ``pos_embed (1, g*g, D)`` (``no_embed_class``, into which timm folded
    the class token's position when converting) gets a zero class row: ``(1, 1 + g*g, D)``."""
    out = {}
    for k, v in sd.items():
        if k in ("mask_token",) or k.startswith(("head.", "fc_norm.")):
            continue
        if k == "reg_token":
            k = "register_tokens"
        elif k == "pos_embed" and math.isqrt(v.shape[1]) ** 2 == v.shape[1]:
            v = torch.cat([v.new_zeros(1, 1, v.shape[-1]), v], dim=1)
        k = re.sub(r"^blocks\.\d+\.(\d+)\.", r"blocks.\1.", k)
        k = k.replace(".mlp.w12.", ".mlp.fc1.").replace(".mlp.w3.", ".mlp.fc2.")
        out[k] = v
    return out


def _refuse_dinov3_7b(dim: int, what: str) -> None:
    if dim == 4096:
        raise ValueError(f"{what}: a DINOv3 ViT-7B (embed_dim 4096) is not supported by omnidl; supported DINOv3 "
                         f"ViTs: {', '.join(_DINOV3_SUPPORTED)}")


def _qkv_bias(q: Tensor | None, k: Tensor | None, v: Tensor | None, what: str) -> Tensor | None:
    """One ``qkv.bias`` from separate q/k/v biases (absent ones zero); ``None`` when none is given. DINOv3 never
    uses a k bias (omnidl masks it): a non-zero one is refused."""
    parts = [q, k, v]
    if all(p is None for p in parts):
        return None
    if k is not None and bool(k.ne(0).any()):
        raise ValueError(f"{what}: a non-zero key bias is no DINOv3 setting (its k bias is masked to 0); "
                         "omnidl's DINOv3 attention would ignore it")
    like = next(p for p in parts if p is not None)
    return torch.cat([p if p is not None else torch.zeros_like(like) for p in parts])


def vit_from_dinov3(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """facebookresearch/dinov3 ``.pth`` keys (``dinov3_vits16_pretrain_lvd1689m-08c60483.pth``, ...) -> ViT keys:
    ``storage_tokens`` -> ``register_tokens``, ``rope_embed.periods`` -> ``rope.periods`` (float32; the stored
    periods are used), ``qkv.bias * qkv.bias_mask`` -> ``qkv.bias`` (k third zero), SwiGLU ``w1``/``w2``/``w3`` ->
    ``fc1`` (``[w1; w2]``)/``fc2``; drops ``mask_token`` and the training-only ``local_cls_norm``. An untied class
    norm (``cls_norm``) is refused."""
    dim = int(sd["cls_token"].shape[-1])
    _refuse_dinov3_7b(dim, "DINOv3 checkpoint")
    if any(k.startswith("cls_norm.") for k in sd):
        raise ValueError("DINOv3 checkpoint with an untied class-token norm (cls_norm): not supported by omnidl")
    out: dict[str, Tensor] = {}
    glu: dict[str, dict[int, Tensor]] = {}
    for k, v in sd.items():
        if k == "mask_token" or k.startswith(("local_cls_norm.", "head.")) or k.endswith(".bias_mask"):
            continue
        if k == "storage_tokens":
            out["register_tokens"] = v
        elif k == "rope_embed.periods":
            out["rope.periods"] = v.to(torch.float32)
        elif k.endswith(".attn.qkv.bias"):
            mask = sd.get(k + "_mask")
            if mask is None:
                mask = torch.ones_like(v)
                mask[dim:2 * dim] = 0
            out[k] = v * mask.to(v.dtype)
        elif (m := re.match(r"(blocks\.\d+\.mlp\.)w([123])\.(weight|bias)$", k)):
            pre, w, p = m.groups()
            if w == "3":
                out[f"{pre}fc2.{p}"] = v
            else:
                glu.setdefault(f"{pre}fc1.{p}", {})[int(w) - 1] = v
        else:
            out[k] = v
    for k, pieces in glu.items():
        if sorted(pieces) != [0, 1]:
            raise KeyError(f"DINOv3 checkpoint: incomplete SwiGLU projections w1/w2 for {k!r}")
        out[k] = torch.cat([pieces[0], pieces[1]], 0)
    return out


def vit_from_timm_dinov3(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """timm ``vit_*_patch16_dinov3[_qkvb]`` (``Eva``) keys -> ViT keys: ``reg_token`` -> ``register_tokens``,
    ``gamma_1``/``gamma_2`` -> ``ls1``/``ls2.gamma``, ``attn.q_bias``/``attn.v_bias`` -> ``attn.qkv.bias`` (k third
    zero; the non-``qkvb`` models have none), SwiGLU ``fc1_g``/``fc1_x`` -> ``fc1``; drops a classifier ``head``.
    timm stores no RoPE periods (omnidl computes the same ones)."""
    _refuse_dinov3_7b(int(sd["cls_token"].shape[-1]), "timm DINOv3 checkpoint")
    out: dict[str, Tensor] = {}
    biases: dict[str, dict[str, Tensor]] = {}
    glu: dict[str, dict[int, Tensor]] = {}
    for k, v in sd.items():
        if k.startswith(("head.", "fc_norm.")) or k == "mask_token":
            continue
        if k == "reg_token":
            out["register_tokens"] = v
        elif (m := re.match(r"(blocks\.\d+)\.gamma_([12])$", k)):
            out[f"{m.group(1)}.ls{m.group(2)}.gamma"] = v
        elif (m := re.match(r"(blocks\.\d+\.attn\.)([qkv])_bias$", k)):
            biases.setdefault(m.group(1) + "qkv.bias", {})[m.group(2)] = v
        elif (m := re.match(r"(blocks\.\d+\.mlp\.)fc1_([gx])\.(weight|bias)$", k)):
            glu.setdefault(f"{m.group(1)}fc1.{m.group(3)}", {})[0 if m.group(2) == "g" else 1] = v
        elif re.match(r"blocks\.\d+\.attn\.(norm|q_norm|k_norm)\.", k):
            raise ValueError(f"timm DINOv3 checkpoint: {k!r} belongs to an EVA variant (attention norms) that "
                             "DINOv3 does not have")
        else:
            out[k] = v
    for k, b in biases.items():
        out[k] = _qkv_bias(b.get("q"), b.get("k"), b.get("v"), "timm DINOv3 checkpoint")
    for k, pieces in glu.items():
        if sorted(pieces) != [0, 1]:
            raise KeyError(f"timm DINOv3 checkpoint: incomplete SwiGLU projections fc1_g/fc1_x for {k!r}")
        out[k] = torch.cat([pieces[0], pieces[1]], 0)
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
    """transformers ``Dinov2Model``/``Dinov2Backbone``/``Dinov2WithRegistersModel`` keys (under ``prefix``) -> ViT
    keys; separate q/k/v (and SwiGLU gate/up) projections are concatenated into ``qkv`` (``fc1``);
    ``embeddings.register_tokens`` -> ``register_tokens``."""
    out: dict[str, Tensor] = {}
    parts: dict[str, dict[int, Tensor]] = {}
    for k, v in sd.items():
        if not k.startswith(prefix):
            continue
        k = k[len(prefix):]
        if k == "embeddings.cls_token":
            out["cls_token"] = v
        elif k == "embeddings.register_tokens":
            out["register_tokens"] = v
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


_HF3_LAYER = {"norm1.": "norm1.", "norm2.": "norm2.", "layer_scale1.lambda1": "ls1.gamma",
              "layer_scale2.lambda1": "ls2.gamma", "attention.o_proj.": "attn.proj.", "mlp.down_proj.": "mlp.fc2."}


def vit_from_hf_dinov3(sd: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """transformers ``DINOv3ViTModel``/``DINOv3ViTBackbone`` keys (``facebook/dinov3-vits16-pretrain-lvd1689m``:
    ``layer.i.*``; transformers >= 5: ``model.layer.i.*``) -> ViT keys: ``q_proj``/``k_proj``/``v_proj`` ->
    ``qkv`` (absent biases zero; ``key_bias`` is off in every published model), ``up_proj`` -> ``fc1`` (plain MLP)
    or ``[gate_proj; up_proj]`` -> ``fc1`` (SwiGLU), ``down_proj`` -> ``fc2``, ``layer_scale{1,2}.lambda1`` ->
    ``ls{1,2}.gamma``. transformers stores no RoPE periods (omnidl computes the same ones)."""
    what = "transformers DINOv3 checkpoint"
    _refuse_dinov3_7b(int(sd["embeddings.cls_token"].shape[-1]), what)
    out: dict[str, Tensor] = {}
    layers: dict[str, dict[str, Tensor]] = {}
    for k, v in sd.items():
        if k in ("embeddings.mask_token",):
            continue
        if k == "embeddings.cls_token":
            out["cls_token"] = v
        elif k == "embeddings.register_tokens":
            out["register_tokens"] = v
        elif (m := re.match(r"embeddings\.patch_embeddings\.(weight|bias)$", k)):
            out["patch_embed.proj." + m.group(1)] = v
        elif (m := re.match(r"norm\.(weight|bias)$", k)):
            out["norm." + m.group(1)] = v
        elif (m := re.match(r"(?:model\.)?layer\.(\d+)\.(.+)$", k)):
            layers.setdefault(m.group(1), {})[m.group(2)] = v
        else:
            raise KeyError(f"{what}: unexpected key {k!r}")
    for i, lay in layers.items():
        b = f"blocks.{i}."
        for p in ("weight", "bias"):
            qkv = [lay.pop(f"attention.{n}_proj.{p}", None) for n in "qkv"]
            if p == "weight":
                if any(t is None for t in qkv):
                    raise KeyError(f"{what}: layer {i} lacks one of q_proj/k_proj/v_proj weights")
                out[b + "attn.qkv.weight"] = torch.cat(qkv, 0)
            elif (bias := _qkv_bias(*qkv, what)) is not None:
                out[b + "attn.qkv.bias"] = bias
            gate, up = lay.pop(f"mlp.gate_proj.{p}", None), lay.pop(f"mlp.up_proj.{p}", None)
            if gate is not None and up is not None:
                out[b + f"mlp.fc1.{p}"] = torch.cat([gate, up], 0)
            elif up is not None:
                out[b + f"mlp.fc1.{p}"] = up
            elif gate is not None:
                raise KeyError(f"{what}: layer {i} has mlp.gate_proj without mlp.up_proj")
        for rest, v in lay.items():
            for pat, rep in _HF3_LAYER.items():
                if rest.startswith(pat):
                    out[b + rep + rest[len(pat):]] = v
                    break
            else:
                raise KeyError(f"{what}: unexpected key {'layer.' + i + '.' + rest!r}")
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
    """A ViT state dict in omnidl's names from any supported layout, and how its learned position embedding is
    resampled (``pos_interp``; DINOv2 with registers from the DINOv2 code or transformers: ``"dinov2_reg"``).

    A Depth-Anything checkpoint gives its encoder (``pretrained.*`` / ``backbone.*``). A DINOv3 state dict holds
    ``rope.periods`` only when the file stores them (the official ``.pth``); :func:`load_vit` fills them in
    otherwise."""
    layout = detect_layout(sd)
    if layout == "depth_anything_v2":
        full = depth_anything_from_original(sd)
        vit = {k[len("pretrained."):]: v for k, v in full.items() if k.startswith("pretrained.")}
    elif layout == "hf_depth_anything":
        vit = vit_from_hf(sd, prefix="backbone.")
    elif layout == "hf_dinov2":
        prefix = next((p for p in ("dinov2.", "dinov2_with_registers.") if any(k.startswith(p) for k in sd)), "")
        vit = vit_from_hf({k: v for k, v in sd.items() if not k.startswith("classifier.")}, prefix=prefix)
    elif layout == "dinov3":
        vit = vit_from_dinov3(sd)
    elif layout == "timm_dinov3":
        vit = vit_from_timm_dinov3(sd)
    elif layout == "hf_dinov3":
        vit = vit_from_hf_dinov3(sd)
    elif layout == "omnidl_dinov3":
        vit = dict(sd)
    else:
        vit = vit_from_dinov2(sd)
    interp = POS_INTERP_OF_LAYOUT[layout]
    if layout in ("dinov2", "hf_dinov2") and "register_tokens" in vit:
        interp = "dinov2_reg"
    return vit, interp


#: transformers ``config.json`` fields that omnidl's ViT fixes: field -> {family: required value}
_HF_FIXED = {"layer_norm_eps": {"dinov2": 1e-6, "dinov3": 1e-5}, "rope_theta": {"dinov3": 100.0},
             "key_bias": {"dinov3": False}}


def read_vit(path: str | os.PathLike) -> tuple[dict[str, Tensor], str]:
    """:func:`vit_state_dict` of the file at ``path``; for a transformers checkpoint the settings of its
    ``config.json`` that the weights do not show (activation, LayerNorm eps, RoPE base) are checked against what
    omnidl's ViT computes, with an error naming the file, field, value and what was expected."""
    file = find_weights(path)
    vit, interp = vit_state_dict(read_state_dict(file))
    cfg = read_hf_config(file)
    if cfg.get("model_type") in ("dinov2", "dinov2_with_registers", "dinov3_vit"):
        family = "dinov3" if cfg["model_type"] == "dinov3_vit" else "dinov2"
        fc1, fc2 = vit["blocks.0.mlp.fc1.weight"], vit["blocks.0.mlp.fc2.weight"]
        swiglu = int(fc1.shape[0]) == 2 * int(fc2.shape[1])
        expected: dict[str, Any] = {k: v[family] for k, v in _HF_FIXED.items() if family in v}
        if not (family == "dinov2" and swiglu):  # transformers' DINOv2 SwiGLU is SiLU whatever hidden_act says
            expected["hidden_act"] = "silu" if swiglu else "gelu"
        for field, want in expected.items():
            got = cfg.get(field, want)
            if got != want and not (isinstance(want, float) and isinstance(got, (int, float))
                                    and abs(got - want) <= 1e-12 * max(1.0, abs(want))):
                raise ValueError(f"{file.parent / 'config.json'}: {field} = {got!r}, but omnidl's {family} ViT "
                                 f"computes {want!r} for these weights (a configuration no published model uses)")
    return vit, interp


def vit_config_of(vit_sd: Mapping[str, Tensor], num_heads: int | None = None) -> dict[str, Any]:
    """:class:`~omnidl.models.foundation.vit.VisionTransformer` arguments that fit a ViT state dict in omnidl's
    names (from :func:`vit_state_dict`): family, widths, depth, FFN, patch size, registers, qkv bias, and the
    pre-training grid of a learned position embedding. ``num_heads`` is not stored in weights: default
    ``embed_dim // 64`` (the head width of every published DINOv2 / DINOv3 model)."""
    dim = int(vit_sd["cls_token"].shape[-1])
    depth = 1 + max(int(k.split(".")[1]) for k in vit_sd if k.startswith("blocks."))
    fc1, fc2 = vit_sd["blocks.0.mlp.fc1.weight"], vit_sd["blocks.0.mlp.fc2.weight"]
    hidden = int(fc2.shape[1])
    patch = int(vit_sd["patch_embed.proj.weight"].shape[-1])
    regs = int(vit_sd["register_tokens"].shape[1]) if "register_tokens" in vit_sd else 0
    rope = "pos_embed" not in vit_sd
    cfg: dict[str, Any] = {
        "size": None, "family": "dinov3" if rope else "dinov2", "embed_dim": dim, "depth": depth,
        "num_heads": int(num_heads) if num_heads else max(1, dim // 64),
        "ffn": "swiglu" if int(fc1.shape[0]) == 2 * hidden else "mlp", "ffn_hidden": hidden, "patch_size": patch,
        "num_registers": regs, "qkv_bias": "blocks.0.attn.qkv.bias" in vit_sd}
    if not rope:
        cfg["img_size"] = patch * math.isqrt(int(vit_sd["pos_embed"].shape[1]) - 1)
    return cfg


def load_vit(model: nn.Module, vit_sd: Mapping[str, Tensor], what: str) -> None:
    """:func:`load_strict` of a ViT state dict from :func:`vit_state_dict` into ``model``
    (:class:`~omnidl.models.foundation.vit.VisionTransformer`); RoPE periods that the file does not store (timm,
    transformers) are the model's own, computed as those libraries do."""
    sd = dict(vit_sd)
    rope = getattr(model, "rope", None)
    if rope is not None and "rope.periods" not in sd:
        from .rope import rope_periods
        sd["rope.periods"] = rope_periods(rope.head_dim, rope.base)
    if rope is None and "rope.periods" in sd:
        raise ValueError(f"{what}: holds a DINOv3 (RoPE) ViT, the model is a {getattr(model, 'family', '?')} ViT "
                         "with a learned position embedding")
    load_strict(model, sd, what)


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


__all__ = ["DINOV3_LAYOUTS", "depth_anything_from_hf", "depth_anything_from_original", "detect_layout", "find_weights",
           "load_depth_anything", "load_strict", "load_vit", "read_hf_config", "read_state_dict", "read_vit",
           "vit_config_of", "vit_from_dinov2", "vit_from_dinov3", "vit_from_hf", "vit_from_hf_dinov3",
           "vit_from_timm_dinov3", "vit_size_of", "vit_state_dict"]
