"""Foundation encoders inside FreDSNet and HorizonNet (``encoder=``), freezing, loading local weights, and the main job
never importing timm/transformers."""
from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from omnidl.models import create_model
from omnidl.models.foundation.encoder import ViTFeatures

TINY = dict(name=None, vit=dict(embed_dim=32, depth=4, num_heads=2, img_size=28, layers=(0, 1, 2, 3)),
            channels=(8, 16, 16, 32))


def test_vit_features_shapes_and_strides():
    enc = ViTFeatures(**{k: v for k, v in TINY.items() if k != "name"}, name=None)
    feats = enc(torch.rand(1, 3, 64, 160))
    assert [tuple(f.shape[-2:]) for f in feats] == [(16, 40), (8, 20), (4, 10), (2, 5)]
    assert [f.shape[1] for f in feats] == list(enc.channels) and enc.strides == (4, 8, 16, 32)
    with pytest.raises(ValueError, match="not divisible by the network stride 32"):
        enc(torch.rand(1, 3, 60, 160))


@pytest.mark.parametrize("freeze,trainable_vit", [("none", True), ("all", False), (2, "partial")])
def test_fredsnet_with_vit_encoder_trains(freeze, trainable_vit):
    model = create_model("fredsnet", backbone="resnet18", width=0.0625, head_width=64,
                         encoder=dict(TINY, freeze=freeze))
    out = model(torch.rand(2, 3, 64, 128))
    assert out["depth"].shape == (2, 1, 64, 128) and out["semantic"].shape == (2, 14, 64, 128)
    sum(v.mean() for v in out.values()).backward()
    vit = model.backbone.vit
    grads = {n: p.grad is not None for n, p in vit.named_parameters()}
    if trainable_vit is True:
        assert all(grads.values())
    elif trainable_vit is False:
        assert not any(grads.values()) and all(p.grad is not None for p in model.backbone.projects.parameters())
    else:
        assert not grads["blocks.0.attn.qkv.weight"] and not grads["blocks.1.mlp.fc1.weight"]
        assert grads["blocks.2.attn.qkv.weight"] and not grads["pos_embed"]
    assert not any(k.startswith("backbone.body.") for k in model.state_dict())


def test_default_fredsnet_keys_unchanged():
    keys = set(create_model("fredsnet", backbone="resnet18", width=0.0625, head_width=64).state_dict())
    assert "backbone.body.conv1.weight" in keys and not any(".vit." in k for k in keys)


def test_horizonnet_with_vit_encoder():
    model = create_model("horizonnet", hidden=16, encoder=TINY)
    out = model(torch.rand(1, 3, 64, 128))
    assert out["boundary"].shape == (1, 2, 128) and out["corner"].shape == (1, 1, 128)


def test_encoder_loads_timm_weights(tmp_path):
    timm = pytest.importorskip("timm")
    ref = timm.create_model("vit_small_patch14_dinov2", pretrained=False, img_size=28, embed_dim=32, depth=4,
                            num_heads=2)
    torch.save(ref.state_dict(), tmp_path / "dinov2_tiny.pth")
    enc = ViTFeatures(name=None, vit=TINY["vit"], channels=TINY["channels"], pretrained=tmp_path / "dinov2_tiny.pth")
    assert enc.vit.pos_interp == "timm"
    torch.testing.assert_close(enc.vit.pos_embed, ref.pos_embed)
    bad = dict(ref.state_dict(), extra=torch.zeros(1))
    torch.save(bad, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match="bad.pth.*unexpected \\['extra'\\]"):
        ViTFeatures(name=None, vit=TINY["vit"], channels=TINY["channels"], pretrained=tmp_path / "bad.pth")


def test_missing_weights_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing is downloaded"):
        create_model("depth_anything_v2", pretrained=str(tmp_path / "depth_anything_v2_vits.pth"))
    with pytest.raises(ValueError, match="unknown encoder 'dinov9'"):
        create_model("fredsnet", backbone="resnet18", width=0.0625, encoder="dinov2_x".replace("2_x", "9"))


@pytest.mark.slow  # a fresh interpreter importing omnidl.engine: ~10-30 s on 2 busy cores
def test_main_job_does_not_import_timm_or_transformers():
    code = ("import sys, torch; from omnidl.models import create_model; import omnidl.engine, omnidl.models.foundation;"
            "m = create_model('fredsnet', backbone='resnet18', width=0.0625, head_width=64);"
            "m(torch.rand(1, 3, 64, 128));"
            "bad = [k for k in ('timm', 'transformers', 'safetensors') if k in sys.modules];"
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)
