"""DINOv3 ViTs (RoPE, registers, masked k bias, SwiGLU): omnidl's ViT loaded from a state dict that timm or
transformers saved (tiny random configurations, nothing downloaded) gives their outputs to 1e-5; the official
facebookresearch/dinov3 layout (not installed here) is checked by a hand-built state dict in its names, mapped from
the timm model key by key."""
from __future__ import annotations

import math
import re

import pytest
import torch

from omnidl.models.foundation.convert import (
    detect_layout,
    load_vit,
    read_vit,
    vit_config_of,
    vit_state_dict,
)
from omnidl.models.foundation.rope import rope_periods, rope_sin_cos
from omnidl.models.foundation.vit import VisionTransformer

from .test_parity import _randomize, _save

SIZES = [(64, 64), (48, 80), (32, 16)]


def _sharpen(module: torch.nn.Module, seed: int) -> None:
    """Random weights (:func:`_randomize`) with q/k projections x4 and layer scales x5: attention far from uniform,
    so that a wrong rotation shows (with plain random weights a 1 % error in the RoPE periods moves the outputs by
    only 5e-6)."""
    _randomize(module, seed)
    with torch.no_grad():
        for n, p in module.named_parameters():
            if re.search(r"(qkv|q_proj|k_proj)\.weight$", n):
                p.mul_(4)
            elif re.search(r"(gamma_[12]|lambda1)$", n):
                p.mul_(5)


def _ours(vit_sd: dict, interp: str, heads: int = 2) -> VisionTransformer:
    model = VisionTransformer(**vit_config_of(vit_sd, num_heads=heads), pos_interp=interp)
    load_vit(model, vit_sd, "test")
    return model.eval()


def _timm_dinov3(name: str, seed: int = 0):
    timm = pytest.importorskip("timm")
    ref = timm.create_model(name, pretrained=False, embed_dim=32, depth=2, num_heads=2, num_classes=0,
                            img_size=64).eval()
    _sharpen(ref, seed)
    return ref


def _max_err(ref_fn, ours: VisionTransformer, sizes=SIZES) -> float:
    err = 0.0
    for i, size in enumerate(sizes):
        x = torch.randn(2, 3, *size, generator=torch.Generator().manual_seed(10 + i))
        with torch.no_grad():
            err = max(err, (ours(x) - ref_fn(x)).abs().max().item())
    return err


@pytest.mark.parametrize("name,fmt", [("vit_small_patch16_dinov3", "pth"), ("vit_small_patch16_dinov3_qkvb", "pth"),
                                      ("vit_small_plus_patch16_dinov3", "safetensors"),
                                      ("vit_huge_plus_patch16_dinov3_qkvb", "pth")])
def test_timm_dinov3_parity(tmp_path, name, fmt):
    if fmt == "safetensors":
        pytest.importorskip("safetensors")
    ref = _timm_dinov3(name)
    _save(ref.state_dict(), tmp_path / f"w.{fmt}", fmt)
    vit_sd, interp = read_vit(tmp_path / f"w.{fmt}")
    assert detect_layout(ref.state_dict()) == "timm_dinov3"
    ours = _ours(vit_sd, interp)
    assert ours.use_rope and ours.num_registers == 4 and ours.patch_size == 16
    assert ("blocks.0.attn.qkv.bias" in ours.state_dict()) == name.endswith("_qkvb")
    err = _max_err(ref.forward_features, ours)
    assert err <= 1e-5, f"{name}: max abs error {err:.2e}"
    x = torch.randn(1, 3, 48, 80, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        want = ref.forward_intermediates(x, indices=[0, 1], norm=True, output_fmt="NLC", intermediates_only=True)
        got = [tok for tok, _cls in ours.intermediate(x, [0, 1])]
    assert max((g - w).abs().max().item() for g, w in zip(got, want)) <= 1e-5


def test_rope_is_used():
    """Negative controls: the same weights with periods 1 % off, or without the rotation, give other outputs."""
    ref = _timm_dinov3("vit_small_patch16_dinov3")
    vit_sd, interp = vit_state_dict(ref.state_dict())
    ours = _ours(vit_sd, interp)
    x = torch.randn(1, 3, 48, 80, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        want = ref.forward_features(x)
        assert (ours(x) - want).abs().max() <= 1e-5
        ours.rope.periods.mul_(1.01)
        assert (ours(x) - want).abs().max() > 1e-4                # periods 1 % off: 40x the tolerance
        ours.rope = None
        assert (ours(x) - want).abs().max() > 1e-2


def _hf_dinov3(transformers, gated: bool, seed: int = 1):
    cfg = transformers.DINOv3ViTConfig(hidden_size=32, num_hidden_layers=2, num_attention_heads=2,
                                       intermediate_size=64, num_register_tokens=4, use_gated_mlp=gated,
                                       hidden_act="silu" if gated else "gelu", image_size=64)
    ref = transformers.DINOv3ViTModel(cfg).eval()
    _sharpen(ref, seed)
    return ref


@pytest.mark.parametrize("gated,names", [(False, "v5"), (True, "published")])
def test_hf_dinov3_parity(tmp_path, gated, names):
    transformers = pytest.importorskip("transformers")
    pytest.importorskip("safetensors")
    ref = _hf_dinov3(transformers, gated)
    ref.save_pretrained(tmp_path / "hf")
    if names == "published":  # the hub files (transformers 4.56): layer.i.*, not model.layer.i.*
        from safetensors.torch import load_file, save_file
        sd = load_file(str(tmp_path / "hf" / "model.safetensors"))
        save_file({k.removeprefix("model."): v for k, v in sd.items()}, str(tmp_path / "hf" / "model.safetensors"))
    vit_sd, interp = read_vit(tmp_path / "hf")
    assert detect_layout(ref.state_dict()) == "hf_dinov3"
    ours = _ours(vit_sd, interp)
    err = _max_err(lambda x: ref(pixel_values=x).last_hidden_state, ours, SIZES[:2])
    assert err <= 1e-5, f"transformers DINOv3 (gated={gated}): max abs error {err:.2e}"
    x = torch.randn(1, 3, 48, 80, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        hidden = ref(pixel_values=x, output_hidden_states=True).hidden_states  # (embeddings, block 0, block 1)
        got = ours.intermediate(x, [0, 1])
    for i, (tok, cls) in enumerate(got):
        want = ref.norm(hidden[i + 1])
        assert (tok - want[:, 5:]).abs().max() <= 1e-5 and (cls - want[:, 0]).abs().max() <= 1e-5


def test_hf_config_that_omnidl_does_not_compute_is_refused(tmp_path):
    transformers = pytest.importorskip("transformers")
    pytest.importorskip("safetensors")
    ref = _hf_dinov3(transformers, gated=True)
    ref.config.hidden_act = "gelu"
    ref.save_pretrained(tmp_path / "hf")
    with pytest.raises(ValueError, match=r"config\.json: hidden_act = 'gelu'.*computes 'silu'"):
        read_vit(tmp_path / "hf")


def _official_from_timm(ref, seed: int = 7) -> dict[str, torch.Tensor]:
    """The facebookresearch/dinov3 names of a timm ``_qkvb`` SwiGLU model, key by key (``qkv.bias`` with a random
    k third and its ``bias_mask``, ``w1``/``w2``/``w3``, ``storage_tokens``, bfloat16-rounded ``periods``, and the
    ``mask_token`` / ``local_cls_norm`` that are not used at inference)."""
    g = torch.Generator().manual_seed(seed)
    sd = ref.state_dict()
    d = sd["cls_token"].shape[-1]
    out = {"cls_token": sd["cls_token"], "storage_tokens": sd["reg_token"], "mask_token": torch.zeros(1, d),
           "rope_embed.periods": rope_periods(d // 2).to(torch.bfloat16).float(),
           "local_cls_norm.weight": torch.ones(d), "local_cls_norm.bias": torch.zeros(d)}
    for k, v in sd.items():
        if k in ("cls_token", "reg_token"):
            continue
        if k.endswith("attn.q_bias"):
            pre = k[:-len("q_bias")]
            out[pre + "qkv.bias"] = torch.cat([v, torch.randn(d, generator=g), sd[pre + "v_bias"]])
            out[pre + "qkv.bias_mask"] = torch.cat([torch.ones(d), torch.zeros(d), torch.ones(d)])
        elif k.endswith("attn.v_bias"):
            continue
        elif ".mlp.fc1_g." in k:
            out[k.replace(".mlp.fc1_g.", ".mlp.w1.")] = v
        elif ".mlp.fc1_x." in k:
            out[k.replace(".mlp.fc1_x.", ".mlp.w2.")] = v
        elif ".mlp.fc2." in k:
            out[k.replace(".mlp.fc2.", ".mlp.w3.")] = v
        else:
            out[k.replace(".gamma_1", ".ls1.gamma").replace(".gamma_2", ".ls2.gamma")] = v
    return out


def test_official_dinov3_layout(tmp_path):
    """Not checkable against the official code (not installed): a hand-built official-layout file loads strictly,
    uses its stored periods, ignores the masked k bias, and equals timm where the periods agree."""
    ref = _timm_dinov3("vit_huge_plus_patch16_dinov3_qkvb", seed=4)
    official = _official_from_timm(ref)
    torch.save(official, tmp_path / "dinov3_vith16plus_pretrain_lvd1689m-7c1da9a5.pth")
    assert detect_layout(official) == "dinov3"
    vit_sd, interp = read_vit(tmp_path / "dinov3_vith16plus_pretrain_lvd1689m-7c1da9a5.pth")
    ours = _ours(vit_sd, interp)
    torch.testing.assert_close(ours.rope.periods, official["rope_embed.periods"], atol=0, rtol=0)
    assert vit_sd["blocks.0.attn.qkv.bias"][32:64].abs().max() == 0
    with torch.no_grad():
        ours.rope.periods.copy_(rope_periods(16))  # timm's float32 periods
    err = _max_err(ref.forward_features, ours)
    assert err <= 1e-5, f"official DINOv3 layout: max abs error {err:.2e}"


def test_refused_checkpoints(tmp_path):
    with pytest.raises(ValueError, match="ConvNeXt.*vits16, vits16plus"):
        detect_layout({"downsample_layers.0.0.weight": torch.zeros(1), "stages.0.0.dwconv.weight": torch.zeros(1)})
    big = {"cls_token": torch.zeros(1, 1, 4096), "storage_tokens": torch.zeros(1, 4, 4096)}
    with pytest.raises(ValueError, match="ViT-7B"):
        vit_state_dict(big)
    transformers = pytest.importorskip("transformers")
    ref = _hf_dinov3(transformers, gated=False)
    sd = dict(ref.state_dict(), **{"model.layer.0.attention.k_proj.bias": torch.ones(32)})
    with pytest.raises(ValueError, match="non-zero key bias"):
        vit_state_dict(sd)
    torch.save(ref.state_dict(), tmp_path / "dinov3.pth")
    from omnidl.models import create_model
    with pytest.raises(ValueError, match="bare hf_dinov3 encoder"):
        create_model("depth_anything_v2", pretrained=str(tmp_path / "dinov3.pth"))


def test_rope_coordinates_and_training_rescale():
    """Patch centres in [-1, 1] per axis (``separate``), periods ``100 ** (4k / d)``; the optional training-time
    rescale acts only in train mode."""
    periods = rope_periods(8)
    torch.testing.assert_close(periods, torch.tensor([1.0, 10.0]))
    sin, cos = rope_sin_cos(periods, 2, 4)
    y, x = -0.5, 2 * (2 + 0.5) / 4 - 1                               # token (row 0, col 2)
    want = torch.tensor([2 * math.pi * y / 1, 2 * math.pi * y / 10, 2 * math.pi * x / 1, 2 * math.pi * x / 10])
    torch.testing.assert_close(sin[2], torch.sin(want).repeat(2))
    torch.testing.assert_close(cos[2], torch.cos(want).repeat(2))
    vit = VisionTransformer(None, family="dinov3", embed_dim=32, depth=1, num_heads=2, layer_scale=1.0,
                            rope_rescale=2.0)
    x = torch.randn(1, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    vit.eval()
    with torch.no_grad():
        a, b = vit(x), vit(x)
        vit.train()
        torch.manual_seed(0)
        c = vit(x)
    assert torch.equal(a, b) and not torch.allclose(a, c)
