"""FreDSNet: outputs, size checks, ablation options, parameter count, backbone weights, official converter."""
import copy

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from omnidl.cameras import Equirectangular
from omnidl.models import create_model
from omnidl.models._backbone import ResNetFeatures
from omnidl.apps.convert_fredsnet import (convert_key, convert_state_dict, load_official_checkpoint,
                                            official_state_dict_shapes)
from omnidl.models.fredsnet import FreDSNet, count_parameters
from omnidl.nn import FourierBlock, ProjectedConv2d
from omnidl.nn.padding import CircularConv2d

SMALL = dict(backbone="resnet18", width=0.0625, head_width=64)
REFERENCE_PARAMS = 115_940_584     # public FDS(14, 'resnet50'), measured (reference facts §1.8)
REFERENCE_UNUSED = 1_595           # parameters of the public model that never get a gradient


@pytest.fixture(scope="module")
def full_model():
    torch.manual_seed(0)
    return FreDSNet(backbone="resnet50", width=1.0, semantic_bn_relu=True)


def test_outputs_and_ranges():
    torch.manual_seed(0)
    model = create_model("fredsnet", **SMALL).eval()
    with torch.no_grad():
        out = model(torch.rand(1, 3, 32, 96))
    assert out["depth"].shape == (1, 1, 32, 96) and (out["depth"] >= 0).all()
    assert out["semantic"].shape == (1, 14, 32, 96)
    assert out["semantic"].min() < 0          # plain logits (no BN+ReLU unless semantic_bn_relu)
    torch.testing.assert_close(model.depth_head.out.conv.bias, torch.ones(1))   # ReLU output starts active


@pytest.mark.parametrize("size", [(64, 100), (48, 64), (64, 64 + 16)])
def test_bad_input_size_names_size_and_stride(size):
    model = FreDSNet(**SMALL)
    with pytest.raises(ValueError, match=rf"{size[0]}x{size[1]}.*stride 32"):
        model(torch.rand(1, 3, *size))


def test_single_task_and_spectral_off():
    torch.manual_seed(1)
    model = FreDSNet(**SMALL, spectral=False, outputs=("depth",), num_classes=5)
    out = model(torch.rand(1, 3, 32, 64))
    assert set(out) == {"depth"} and model.semantic_head is None
    assert not any("conv_g2g.fourier" in n for n, _ in model.named_parameters())
    with pytest.raises(ValueError, match="outputs"):
        FreDSNet(**SMALL, outputs=("normals",))


def test_width_scales_layers_and_laterals():
    m = FreDSNet(backbone="resnet18", width=0.25)
    assert m.widths["encoder"] == [64, 128, 256, 512]          # = resnet18 widths: no lateral projection
    assert all(isinstance(lat, nn.Identity) for lat in m.lateral)
    m = FreDSNet(backbone="resnet18", width=0.125)
    assert all(isinstance(lat, nn.Conv2d) for lat in m.lateral)


def test_full_size_parameter_count(full_model):
    # the public model minus exactly the parameters it never uses (see docs/fredsnet.md)
    n = count_parameters(full_model)
    assert n == REFERENCE_PARAMS - REFERENCE_UNUSED
    assert abs(n - REFERENCE_PARAMS) / REFERENCE_PARAMS < 0.02
    assert full_model.widths["decoder"] == [2048, 1024, 512, 256, 64, 16]


def test_horizontal_wrap_in_heads():
    m = FreDSNet(**SMALL)
    assert isinstance(m.depth_head.out.conv, CircularConv2d)
    assert isinstance(m.decoder[0].conv.conv.conv, CircularConv2d)


def test_equi_variant_uses_projected_convs():
    cam = Equirectangular(width=128, height=64)
    m = FreDSNet(**SMALL, conv="projected", camera=cam, equi_parts=("fourier", "wconv"))
    fb = m.encoder[0].fourier.ffc
    assert isinstance(fb.conv_l2l, ProjectedConv2d) and fb.conv_l2l.camera == cam
    assert isinstance(m.encoder[0].conv.conv.conv, ProjectedConv2d)
    assert not isinstance(m.depth_head.out.conv, ProjectedConv2d)
    std = FreDSNet(**SMALL)
    assert count_parameters(m) == count_parameters(std)       # same weights, only the sampling differs
    with pytest.raises(ValueError, match="equi_parts"):
        FreDSNet(**SMALL, conv="projected", equi_parts=("everything",))


def test_equi_fourier_block_forward_backward():
    torch.manual_seed(2)
    fb = FourierBlock(8, camera=Equirectangular(width=32, height=16))
    x = torch.randn(1, 8, 8, 16, requires_grad=True)
    fb(x).pow(2).sum().backward()
    assert all(p.grad is not None for p in fb.parameters()) and torch.isfinite(x.grad).all()


def test_backbone_local_weights_round_trip(tmp_path):
    torch.manual_seed(3)
    src = ResNetFeatures("resnet18")
    path = tmp_path / "resnet18.pth"
    sd = {f"module.{k}": v for k, v in src.body.state_dict().items()}
    sd["fc.weight"] = torch.zeros(1000, 512)                   # torchvision checkpoints carry fc: ignored
    torch.save({"state_dict": sd}, path)
    dst = ResNetFeatures("resnet18", pretrained=str(path))
    for (k, a), b in zip(src.body.state_dict().items(), dst.body.state_dict().values()):
        assert torch.equal(a, b), k
    x = torch.rand(1, 3, 32, 32)
    src.eval(), dst.eval()
    assert [f.shape[1] for f in dst(x)] == list(dst.channels) == [64, 128, 256, 512]
    with pytest.raises(FileNotFoundError, match="model.pretrained"):
        ResNetFeatures("resnet18", pretrained=str(tmp_path / "missing.pth"))
    torch.save({"conv1.weight": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match="missing"):
        ResNetFeatures("resnet18", pretrained=str(tmp_path / "bad.pth"))


def test_backbone_levels_and_normalisation():
    bb = ResNetFeatures("resnet18", out_indices=(0, 4)).eval()
    feats = bb(torch.rand(1, 3, 64, 64))
    assert [tuple(f.shape[1:]) for f in feats] == [(64, 32, 32), (512, 2, 2)] and bb.strides == (2, 32)
    assert "mean" not in bb.state_dict()
    with pytest.raises(ValueError, match="backbone"):
        ResNetFeatures("vgg16")


# --- official checkpoint converter ----------------------------------------------------------------
def _random_official_state_dict(seed=0, prefix=""):
    """Random tensors in the official layout; big tensors get a constant distinct per key (cheap)."""
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for i, (k, shape) in enumerate(official_state_dict_shapes().items()):
        if not k.startswith(prefix):
            continue
        if torch.Size(shape).numel() > 100_000:
            sd[k] = torch.full(shape, 1e-4 * i)
        elif k.endswith("num_batches_tracked"):
            sd[k] = torch.tensor(7)
        elif k.endswith("running_var"):
            sd[k] = torch.rand(shape, generator=g) + 0.5
        else:
            sd[k] = torch.randn(shape, generator=g) * 0.1
    # shared modules: the duplicate views hold the same tensors
    for k in list(sd):
        for dup, orig in ((".AF1.", ".bnaf1.1."), (".AF2.", ".bnaf2.1.")):
            if dup in k and ".conv_gg." not in k:
                sd[k] = sd[k.replace(dup, orig)]
        for dup, orig in (("conv_gg.AF1.", "conv_gg.inConv.2."), ("conv_gg.AF2.", "conv_gg.midConv.2.")):
            if dup in k:
                sd[k] = sd[k.replace(dup, orig)]
    return sd


def test_official_layout_parameter_count():
    shapes = official_state_dict_shapes()
    dup = (".AF1.", ".AF2.", "running_", "num_batches")
    n = sum(torch.Size(s).numel() for k, s in shapes.items() if not any(d in k for d in dup))
    assert n == REFERENCE_PARAMS


@pytest.mark.slow
def test_convert_official_state_dict_loads_strictly(full_model, tmp_path, monkeypatch):
    official = _random_official_state_dict()
    converted = convert_state_dict(official)
    full_model.load_state_dict(converted, strict=True)
    sd = full_model.state_dict()
    torch.testing.assert_close(sd["decoder.0.skip_weight"], official["Decoder.alpha4"])
    torch.testing.assert_close(sd["semantic_head.branch_weights"],
                               torch.cat([official[f"SemanticSegmentator.alphas.{i}"] for i in range(1, 5)]))
    torch.testing.assert_close(sd["encoder.3.fourier.ffc.conv_g2l.weight"], official["Encoder.FB4.block.0.conv_gl.weight"])
    torch.testing.assert_close(sd["backbone.body.layer4.2.conv3.weight"],
                               official["feature_extractor.encoder.layer4.2.conv3.weight"])
    # the file form {'args', 'kargs', 'state_dict'} (torch.load stubbed: no 460 MB file in a unit test)
    ckpt = {"args": {"lr": 1e-5}, "kargs": {"num_classes": 14, "backbone": "resnet50"}, "state_dict": official}
    monkeypatch.setattr(torch, "load", lambda *a, **k: ckpt)
    model, args = load_official_checkpoint("FreDSNet_weights.pth")
    assert args == {"lr": 1e-5} and model.num_classes == 14
    monkeypatch.undo()
    with pytest.raises(FileNotFoundError, match="official FreDSNet checkpoint"):
        load_official_checkpoint(str(tmp_path / "missing.pth"))
    with pytest.raises(KeyError, match="unexpected key"):
        convert_key("Encoder.something.weight")


def _official_fastfc(sd, p, x):
    """FreDSNet's FastFC forward written from the reference description, on official keys (eval BN)."""
    def bn(t, q):
        return F.batch_norm(t, sd[f"{q}.running_mean"], sd[f"{q}.running_var"], sd[f"{q}.weight"], sd[f"{q}.bias"],
                            False, 0.0, 1e-5)

    def conv(t, q, pad=0):
        return F.conv2d(t, sd[f"{q}.weight"], sd[f"{q}.bias"], padding=pad)

    mid = x.shape[1] // 2
    xl, xg = x[:, :mid], x[:, mid:]
    s = f"{p}.conv_gg"
    h = F.prelu(bn(conv(xg, f"{s}.inConv.0"), f"{s}.inConv.1"), sd[f"{s}.inConv.2.weight"])
    spec = torch.fft.rfft2(h)
    z = torch.cat([spec.real, spec.imag], -1)
    z = F.prelu(bn(conv(z, f"{s}.midConv.0"), f"{s}.midConv.1"), sd[f"{s}.midConv.2.weight"])
    w = z.shape[-1] // 2
    g2g = conv(torch.fft.irfft2(torch.complex(z[..., :w], z[..., w:])) + h, f"{s}.outConv")
    out_l = F.prelu(bn(conv(xl, f"{p}.conv_ll", 1) + conv(xg, f"{p}.conv_gl", 1), f"{p}.bnaf1.0"),
                    sd[f"{p}.bnaf1.1.weight"]) + xl
    out_g = F.prelu(bn(g2g + conv(xl, f"{p}.conv_lg", 1), f"{p}.bnaf2.0"), sd[f"{p}.bnaf2.1.weight"]) + xg
    return torch.cat([out_l, out_g], 1)


def test_converted_fourier_block_matches_official_formula():
    prefix = "Decoder.U1.2"                                  # FourierBlock(64)
    official = _random_official_state_dict(seed=1, prefix=prefix + ".")
    ours = {convert_key(k)[len("decoder.4.fourier."):]: v for k, v in official.items()
            if k.startswith(prefix + ".") and convert_key(k) is not None}
    fb = FourierBlock(64).eval()
    fb.load_state_dict(ours, strict=True)
    x = torch.randn(1, 64, 8, 16)
    with torch.no_grad():
        torch.testing.assert_close(fb(x), _official_fastfc(official, prefix + ".block.0", x), atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("overrides", [["model=fredsnet"], ["model=fredsnet_small", "loss=fredsnet_depth"],
                                       ["model=fredsnet", "loss=fredsnet_recall", "loss.alpha_depth=3"]])
def test_hydra_configs_compose_and_build(overrides):
    import os

    from hydra import compose, initialize_config_dir

    from omnidl.engine.build import build_loss, build_metrics
    from omnidl.engine.config import register_configs
    from omnidl.losses.joint import JointLoss

    register_configs()
    root = os.path.join(os.path.dirname(__file__), "..", "..", "configs")
    with initialize_config_dir(config_dir=os.path.abspath(root), version_base="1.3"):
        cfg = compose("train", overrides=overrides + ["data=folder"])
    assert cfg.model.name == "fredsnet" and cfg.model.backbone == "resnet18"
    loss = build_loss(cfg)
    assert isinstance(loss, JointLoss)
    if "loss=fredsnet_depth" in overrides:
        assert loss.active == ["depth"]
    if "loss.alpha_depth=3" in overrides:
        assert loss.alpha["depth"] == 3.0 and loss.seg.kind == "recall"
    metrics = build_metrics(cfg)
    metrics.update({"depth": torch.ones(1, 1, 2, 2), "semantic": torch.zeros(1, 14, 2, 2)},
                   {"depth": torch.ones(1, 1, 2, 2), "semantic": torch.ones(1, 2, 2, dtype=torch.long)})
    assert {"mre", "delta1", "miou", "macc"} <= set(metrics.compute())


@pytest.mark.parametrize("train", [False, True])
def test_fusion_head_is_the_weighted_sum_of_upsampled_maps(train):
    """The task head is the literal formula ``out(m_0 + sum_i w_i up(WConv_i(d_i)))``, outputs and gradients."""
    from omnidl.models.fredsnet import FusionHead
    torch.manual_seed(4)
    head = FusionHead([8, 6, 4], 4, 3, activation="prelu", out_activation="relu", out_norm=True,
                      wconv_kwargs={}).double().train(train)
    with torch.no_grad():
        head.branch_weights.copy_(torch.tensor([-0.7, 1.3]))
    maps = [torch.randn(2, 8, 4, 8), torch.randn(2, 6, 8, 16), torch.randn(2, 4, 16, 32)]
    maps = [m.double().requires_grad_() for m in maps]
    literal = copy.deepcopy(head)
    up = [F.interpolate(med(d), size=(16, 32), mode="bilinear", align_corners=True)
          for med, d in zip(literal.mediators, maps)]
    expect = literal.out(up[0] + literal.branch_weights[0] * up[1] + literal.branch_weights[1] * up[2])
    got = head(maps)
    torch.testing.assert_close(got, expect)
    g = torch.randn_like(expect)
    ga = torch.autograd.grad((got * g).sum(), maps + list(head.parameters()))
    gb = torch.autograd.grad((expect * g).sum(), maps + list(literal.parameters()))
    for a, b in zip(ga, gb):
        torch.testing.assert_close(a, b)


def test_channels_last_matches_contiguous_layout():
    torch.manual_seed(5)
    a = FreDSNet(**SMALL, channels_last=True).eval()
    b = FreDSNet(**SMALL, channels_last=False).eval()
    b.load_state_dict(a.state_dict())
    x = torch.rand(1, 3, 32, 64)
    with torch.no_grad():
        oa, ob = a(x), b(x)
    for k in oa:
        assert oa[k].is_contiguous()
        torch.testing.assert_close(oa[k], ob[k], atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("channels_last", [False, True])
def test_eval_without_autograd_equals_the_autograd_composition(channels_last):
    """Eval with and without autograd compute the same outputs (one network in every mode)."""
    torch.manual_seed(7)
    m = FreDSNet(**SMALL, channels_last=channels_last).eval().double()
    with torch.no_grad():
        for i, blk in enumerate(m.decoder):
            if blk.skip_weight is not None:
                blk.skip_weight.fill_(0.5 + 0.25 * i)
    x = torch.rand(1, 3, 32, 64, dtype=torch.float64)
    with torch.no_grad():
        a = m(x)
    with torch.enable_grad():
        b = m(x.clone().requires_grad_())
    for k in a:
        torch.testing.assert_close(a[k], b[k].detach(), rtol=1e-12, atol=1e-12)
