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


@pytest.mark.parametrize("encoder", ["dinov2", "dinov3"])
def test_horizonnet_with_vit_encoder(encoder):
    model = create_model("horizonnet", hidden=16, encoder={"dinov2": TINY, "dinov3": TINY3}[encoder])
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


TINY3 = {"name": None, "vit": {"family": "dinov3", "embed_dim": 32, "depth": 4, "num_heads": 2, "layers": (0, 1, 2, 3)},
         "channels": (8, 16, 16, 32)}


def test_dinov3_encoder_runs_on_the_input_itself():
    """Patch 16: the ViT sees the image as it is (no 14/16 rescale), one patch per 16 pixels."""
    enc = ViTFeatures(**TINY3)
    seen = []
    enc.vit.patch_embed.register_forward_hook(lambda m, i, o: seen.append(tuple(i[0].shape)))
    feats = enc(torch.rand(1, 3, 64, 160))
    assert seen == [(1, 3, 64, 160)] and enc.vit.use_rope and enc.vit.num_registers == 4
    assert [tuple(f.shape[-2:]) for f in feats] == [(16, 40), (8, 20), (4, 10), (2, 5)]


@pytest.mark.parametrize("freeze", ["none", 2])
def test_fredsnet_with_dinov3_encoder_trains(freeze):
    model = create_model("fredsnet", backbone="resnet18", width=0.0625, head_width=64,
                         encoder=dict(TINY3, freeze=freeze))
    out = model(torch.rand(2, 3, 64, 128))
    assert out["depth"].shape == (2, 1, 64, 128) and out["semantic"].shape == (2, 14, 64, 128)
    sum(v.mean() for v in out.values()).backward()
    grads = {n: p.grad is not None for n, p in model.backbone.vit.named_parameters()}
    if freeze == "none":
        assert all(grads.values())
    else:
        assert not grads["register_tokens"] and not grads["blocks.1.attn.qkv.weight"]
        assert grads["blocks.2.attn.qkv.weight"]
    assert "backbone.vit.rope.periods" in model.state_dict()


def test_encoder_loads_timm_dinov3_weights_and_names_a_wrong_family(tmp_path):
    timm = pytest.importorskip("timm")
    ref = timm.create_model("vit_small_patch16_dinov3", pretrained=False, embed_dim=32, depth=4, num_heads=2,
                            num_classes=0).eval()
    torch.save(ref.state_dict(), tmp_path / "dinov3_tiny.pth")
    enc = ViTFeatures(**TINY3, pretrained=tmp_path / "dinov3_tiny.pth").eval()
    assert "blocks.0.attn.qkv.bias" not in enc.vit.state_dict()  # timm's non-qkvb models have no qkv bias
    x = torch.randn(1, 3, 32, 64)
    with torch.no_grad():
        assert (enc.vit(x) - ref.forward_features(x)).abs().max() <= 1e-5
    with pytest.raises(ValueError, match="dinov3_tiny.pth: holds a dinov3 ViT.*encoder 'custom' is a dinov2 ViT"):
        ViTFeatures(name=None, vit=TINY["vit"], channels=TINY["channels"], pretrained=tmp_path / "dinov3_tiny.pth")


def test_named_dinov3_encoder_and_the_name_that_fits(tmp_path):
    enc = ViTFeatures("dinov3_s")
    assert enc.vit.patch_size == 16 and enc.layers == (2, 5, 8, 11) and enc.channels == (48, 96, 192, 384)
    assert [tuple(f.shape) for f in enc(torch.rand(1, 3, 32, 64))][-1] == (1, 384, 1, 2)
    torch.save(enc.vit.state_dict(), tmp_path / "vits16.pth")
    with pytest.raises(ValueError, match="use model.encoder=dinov3_s"):
        ViTFeatures("dinov2_s_reg", pretrained=tmp_path / "vits16.pth")
