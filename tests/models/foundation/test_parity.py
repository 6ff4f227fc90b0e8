"""Parity with the reference implementations: omnidl's ViT / Depth-Anything-V2, loaded from a state dict that timm or
transformers saved (tiny random configurations, nothing downloaded), gives their outputs to 1e-5.

timm and transformers are test oracles only (the ``dev`` extra); without them these tests are skipped."""
from __future__ import annotations

import pytest
import torch

from omnidl.models import create_model
from omnidl.models.foundation.convert import load_strict, read_state_dict, vit_state_dict
from omnidl.models.foundation.vit import VisionTransformer

TOL = dict(atol=1e-5, rtol=1e-5)
MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)


def _randomize(module: torch.nn.Module, seed: int) -> None:
    """Every parameter random (layer scales and biases too, so that no term of the forward is a no-op)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            fan_in = p[0].numel() if p.dim() > 1 else 100
            p.copy_(torch.randn(p.shape, generator=g) / fan_in ** 0.5)


def _save(sd: dict, path, fmt: str) -> None:
    if fmt == "safetensors":
        from safetensors.torch import save_file
        save_file({k: v.contiguous() for k, v in sd.items()}, str(path))
    else:
        torch.save(sd, path)


def _ours_from(path, **kw) -> VisionTransformer:
    vit_sd, interp = vit_state_dict(read_state_dict(path))
    dim = vit_sd["cls_token"].shape[-1]
    depth = 1 + max(int(k.split(".")[1]) for k in vit_sd if k.startswith("blocks."))
    grid = int((vit_sd["pos_embed"].shape[1] - 1) ** 0.5)
    model = VisionTransformer(size=None, embed_dim=dim, depth=depth, pos_interp=interp, img_size=14 * grid, **kw)
    load_strict(model, vit_sd, str(path))
    return model.eval()


@pytest.mark.parametrize("variant", ["mlp", "swiglu"])
@pytest.mark.parametrize("fmt", ["pth", "safetensors"])
def test_timm_dinov2_parity(tmp_path, variant, fmt):
    timm = pytest.importorskip("timm")
    if fmt == "safetensors":
        pytest.importorskip("safetensors")
    name = "vit_small_patch14_dinov2" if variant == "mlp" else "vit_giant_patch14_dinov2"
    ref = timm.create_model(name, pretrained=False, img_size=42, embed_dim=48, depth=3, num_heads=2,
                            dynamic_img_size=True).eval()
    _randomize(ref, 0)
    path = tmp_path / f"vit.{fmt}"
    _save(ref.state_dict(), path, fmt)
    ours = _ours_from(path, num_heads=2, ffn=variant)
    assert ours.pos_interp == "timm"
    for size in [(42, 42), (42, 70), (56, 28)]:
        x = torch.randn(2, 3, *size, generator=torch.Generator().manual_seed(1))
        with torch.no_grad():
            want, got = ref.forward_features(x), ours(x)
        err = (got - want).abs().max().item()
        assert err <= 1e-5, f"{name} at {size}: max abs error {err:.2e}"


@pytest.mark.parametrize("layout", ["new", "old"])
def test_hf_dinov2_parity(tmp_path, layout):
    transformers = pytest.importorskip("transformers")
    cfg = transformers.Dinov2Config(hidden_size=48, num_hidden_layers=3, num_attention_heads=2, image_size=42,
                                    patch_size=14, intermediate_size=192)
    ref = transformers.Dinov2Model(cfg).eval()
    _randomize(ref, 1)
    sd = dict(ref.state_dict())
    if layout == "old":  # the names of the published checkpoints (transformers < 5)
        sd = {k.replace("attention.q_proj", "attention.attention.query").replace(
            "attention.k_proj", "attention.attention.key").replace("attention.v_proj", "attention.attention.value")
            .replace("attention.o_proj", "attention.output.dense"): v for k, v in sd.items()}
    path = tmp_path / "pytorch_model.bin"
    torch.save(sd, path)
    ours = _ours_from(path, num_heads=2)
    assert ours.pos_interp == "hf"
    for size in [(42, 42), (42, 70)]:
        x = torch.randn(2, 3, *size, generator=torch.Generator().manual_seed(2))
        with torch.no_grad():
            want = ref(pixel_values=x).last_hidden_state
            got = ours(x)
        err = (got - want).abs().max().item()
        assert err <= 1e-5, f"transformers Dinov2 at {size}: max abs error {err:.2e}"


def _hf_depth_anything(transformers, metric: bool):
    backbone = transformers.Dinov2Config(hidden_size=48, num_hidden_layers=4, num_attention_heads=2, image_size=28,
                                         patch_size=14, intermediate_size=192, out_indices=[1, 2, 3, 4],
                                         apply_layernorm=True, reshape_hidden_states=False)
    kw = dict(depth_estimation_type="metric", max_depth=20) if metric else {}
    cfg = transformers.DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=48, patch_size=14,
                                           neck_hidden_sizes=[8, 16, 24, 32], fusion_hidden_size=16,
                                           head_hidden_size=32, **kw)
    ref = transformers.DepthAnythingForDepthEstimation(cfg).eval()
    _randomize(ref, 3)
    return ref


@pytest.mark.parametrize("metric", [False, True], ids=["relative", "metric"])
def test_hf_depth_anything_parity(tmp_path, metric):
    transformers = pytest.importorskip("transformers")
    pytest.importorskip("safetensors")
    ref = _hf_depth_anything(transformers, metric)
    ref.save_pretrained(tmp_path / "hf")
    ours = create_model("depth_anything_v2", encoder=dict(embed_dim=48, depth=4, num_heads=2, img_size=28,
                                                          layers=(0, 1, 2, 3)),
                        pretrained=str(tmp_path / "hf")).eval()
    assert ours.max_depth == (20.0 if metric else None)
    for size in [(28, 28), (42, 70)]:
        x = torch.rand(2, 3, *size, generator=torch.Generator().manual_seed(4))
        with torch.no_grad():
            want = ref(pixel_values=(x - MEAN) / STD).predicted_depth
            got = ours(x)["depth" if metric else "disparity"][:, 0]
        err = (got - want).abs().max().item()
        assert err <= 1e-5, f"DepthAnything at {size}: max abs error {err:.2e} (|ref| {want.abs().max():.2f})"


def test_published_layout_roundtrip(tmp_path):
    """The published ``.pth`` layout (Depth-Anything-V2 code names, with its never-used ``mask_token`` and
    ``refinenet4.resConfUnit1``) loads strictly and computes the same as the transformers model it was mapped from."""
    transformers = pytest.importorskip("transformers")
    ref = _hf_depth_anything(transformers, metric=False)
    from omnidl.models.foundation.convert import depth_anything_from_hf
    conv = depth_anything_from_hf(ref.state_dict())
    conv["pretrained.mask_token"] = torch.zeros(1, 48)
    for name, shape in [("conv1.weight", (16, 16, 3, 3)), ("conv1.bias", (16,)), ("conv2.weight", (16, 16, 3, 3)),
                        ("conv2.bias", (16,))]:
        conv[f"depth_head.scratch.refinenet4.resConfUnit1.{name}"] = torch.zeros(shape)
    torch.save(conv, tmp_path / "depth_anything_v2_custom.pth")
    ours = create_model("depth_anything_v2", encoder=dict(embed_dim=48, depth=4, num_heads=2, img_size=28,
                                                          layers=(0, 1, 2, 3)),
                        pretrained=str(tmp_path / "depth_anything_v2_custom.pth"), pos_interp="hf").eval()
    x = torch.rand(1, 3, 42, 56, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        want = ref(pixel_values=(x - MEAN) / STD).predicted_depth
        got = ours(x)["disparity"][:, 0]
    assert (got - want).abs().max().item() <= 1e-5


def test_dinov2_code_position_interpolation():
    """The Depth-Anything-V2 / DINOv2 code resamples with ``scale_factor = (grid + 0.1) / 37`` (no anti-aliasing) and
    keeps the table for a square input of the pre-training grid; transformers and timm resample to the grid size."""
    import math

    import torch.nn.functional as F

    from omnidl.models.foundation.vit import resample_pos_embed
    pe = torch.randn(1, 1 + 37 * 37, 8, generator=torch.Generator().manual_seed(0))
    assert resample_pos_embed(pe, 518, 518, 14, "dinov2") is pe
    got = resample_pos_embed(pe, 518, 1036, 14, "dinov2")
    grid = pe[:, 1:].reshape(1, 37, 37, 8).permute(0, 3, 1, 2)
    want = F.interpolate(grid, scale_factor=(37.1 / math.sqrt(1369), 74.1 / math.sqrt(1369)), mode="bicubic",
                         antialias=False).permute(0, 2, 3, 1).reshape(1, -1, 8)
    torch.testing.assert_close(got[:, 1:], want, atol=0, rtol=0)
    hf = resample_pos_embed(pe, 518, 1036, 14, "hf")
    assert hf.shape == got.shape and not torch.equal(hf, got)


@pytest.mark.parametrize("variant", ["mlp", "swiglu"])
def test_timm_dinov2_reg4_parity(tmp_path, variant):
    """timm's ``*_reg4_dinov2`` (``reg_token``; ``no_embed_class``: a position table without the class row, timm
    having folded that row into ``cls_token``)."""
    timm = pytest.importorskip("timm")
    name = "vit_small_patch14_reg4_dinov2" if variant == "mlp" else "vit_giant_patch14_reg4_dinov2"
    ref = timm.create_model(name, pretrained=False, img_size=42, embed_dim=48, depth=3, num_heads=2,
                            dynamic_img_size=True).eval()
    _randomize(ref, 5)
    torch.save(ref.state_dict(), tmp_path / "reg4.pth")
    ours = _ours_from(tmp_path / "reg4.pth", num_heads=2, ffn=variant, num_registers=4)
    assert ours.pos_interp == "timm" and ours.num_registers == 4
    for size in [(42, 42), (42, 70), (56, 28)]:
        x = torch.randn(2, 3, *size, generator=torch.Generator().manual_seed(6))
        with torch.no_grad():
            want, got = ref.forward_features(x), ours(x)
        err = (got - want).abs().max().item()
        assert err <= 1e-5, f"{name} at {size}: max abs error {err:.2e}"
    with torch.no_grad():
        want = ref.forward_intermediates(x, indices=[0, 2], norm=True, output_fmt="NLC", intermediates_only=True)
        got = [tok for tok, _cls in ours.intermediate(x, [0, 2])]
    assert max((g - w).abs().max().item() for g, w in zip(got, want)) <= 1e-5


def _hf_dinov2_reg(transformers):
    cfg = transformers.Dinov2WithRegistersConfig(hidden_size=48, num_hidden_layers=3, num_attention_heads=2,
                                                 image_size=42, patch_size=14, num_register_tokens=4)
    ref = transformers.Dinov2WithRegistersModel(cfg).eval()
    _randomize(ref, 7)
    return ref


def test_hf_dinov2_with_registers_parity(tmp_path):
    transformers = pytest.importorskip("transformers")
    ref = _hf_dinov2_reg(transformers)
    torch.save(ref.state_dict(), tmp_path / "pytorch_model.bin")
    ours = _ours_from(tmp_path / "pytorch_model.bin", num_heads=2, num_registers=4)
    assert ours.pos_interp == "dinov2_reg"
    for size in [(42, 42), (42, 70), (56, 28)]:
        x = torch.randn(2, 3, *size, generator=torch.Generator().manual_seed(8))
        with torch.no_grad():
            want, got = ref(pixel_values=x).last_hidden_state, ours(x)
        err = (got - want).abs().max().item()
        assert err <= 1e-5, f"transformers Dinov2WithRegisters at {size}: max abs error {err:.2e}"


def test_dinov2_reg_code_layout(tmp_path):
    """The DINOv2 code's ``dinov2_vits14_reg4_pretrain.pth`` layout (not checkable against that code here): built
    key by key from the transformers model (``register_tokens``, ``mask_token``, the class token's position row in
    ``pos_embed``), it loads strictly, resamples like the DINOv2 code for ``*_reg`` models (``interpolate_offset=0``,
    anti-aliased: the same as transformers') and gives transformers' outputs."""
    transformers = pytest.importorskip("transformers")
    ref = _hf_dinov2_reg(transformers)
    from omnidl.models.foundation.convert import vit_from_hf
    code = vit_from_hf(ref.state_dict())
    code["mask_token"] = torch.zeros(1, 48)
    torch.save(code, tmp_path / "dinov2_vits14_reg4_pretrain.pth")
    ours = _ours_from(tmp_path / "dinov2_vits14_reg4_pretrain.pth", num_heads=2, num_registers=4)
    assert ours.pos_interp == "dinov2_reg"
    x = torch.randn(1, 3, 56, 28, generator=torch.Generator().manual_seed(9))
    with torch.no_grad():
        assert (ours(x) - ref(pixel_values=x).last_hidden_state).abs().max().item() <= 1e-5
