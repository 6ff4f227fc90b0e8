"""HorizonNet: shapes at several sizes, bias init, no-RNN variant, circular padding, converter."""
import re

import pytest
import torch
import torch.nn.functional as F

from omnidl.models import create_model
from omnidl.models.horizonnet import BIAS_INIT, HorizonNet, convert_official_state_dict, load_official_checkpoint


@pytest.mark.parametrize("hw,rnn", [((64, 128), True), ((128, 256), False), ((32, 192), True)])
def test_output_shapes_any_size(hw, rnn):
    torch.manual_seed(0)
    m = HorizonNet(backbone="resnet18", hidden=16, rnn=rnn).eval()
    out = m(torch.rand(2, 3, *hw))
    assert out["boundary"].shape == (2, 2, hw[1]) and out["corner"].shape == (2, 1, hw[1])
    assert m.feat_dim == 64 // 8 * 8 + 128 // 8 * 4 + 256 // 8 * 2 + 512 // 8 * 1
    assert torch.isfinite(out["boundary"]).all()


def test_reference_sizes_feature_dim_and_bias_init():
    m = HorizonNet(backbone="resnet50", hidden=512)
    assert m.feat_dim == 1024                      # the reference LSTM input at 1024x512
    n_rnn = sum(p.numel() for p in m.rnn.parameters())
    assert n_rnn == 12_599_296                     # reference: BiLSTM 12,599,296 parameters
    assert sum(p.numel() for p in m.head.parameters()) == 12_300
    b = m.head.bias.view(3, 4)
    for k, v in enumerate(BIAS_INIT):
        assert torch.allclose(b[k], torch.full((4,), v))


def test_horizontal_wrap_equivariance():
    # rolling the panorama by a multiple of the total stride rolls the column features exactly (every
    # conv and the max-pool wrap around); the BiLSTM itself is sequential, so only features are tested
    torch.manual_seed(0)
    m = HorizonNet(backbone="resnet18", hidden=8).eval()
    x = torch.rand(1, 3, 32, 128)
    with torch.no_grad():
        a = m.features(x)
        b = m.features(torch.roll(x, 64, -1))
    assert torch.allclose(torch.roll(a, 64 // m.step_cols, -1), b, atol=1e-5)
    m0 = HorizonNet(backbone="resnet18", hidden=8, circular=False).eval()
    m0.load_state_dict(m.state_dict())
    with torch.no_grad():
        a0, b0 = m0.features(x), m0.features(torch.roll(x, 64, -1))
    assert not torch.allclose(torch.roll(a0, 16, -1), b0, atol=1e-3)      # zero padding breaks it


def test_bad_size_raises_clear_error():
    m = HorizonNet(backbone="resnet18", hidden=8)
    with pytest.raises(ValueError, match="divisible"):
        m(torch.rand(1, 3, 60, 128))


def _official_from(model: HorizonNet) -> dict:
    """Synthesise the official key layout from our keys (the inverse of the converter)."""
    out = {}
    for k, v in model.state_dict().items():
        if k.startswith("encoder.body."):
            rest = k[len("encoder.body."):]
            mod = rest.rsplit(".", 1)[0]
            conv = dict(model.encoder.body.named_modules())[mod]
            if isinstance(conv, torch.nn.Conv2d) and conv.kernel_size[1] > 1:
                rest = rest.rsplit(".", 1)[0] + ".1." + rest.rsplit(".", 1)[1]
            out["feature_extractor.encoder." + rest] = v.clone() + 1
        elif k.startswith("reduce_height."):
            i, j, part, p = re.match(r"reduce_height\.(\d+)\.(\d+)\.(conv|bn)\.(.+)", k).groups()
            out[f"reduce_height_module.ghc_lst.{i}.layer.{j}.layers.{'0.1' if part == 'conv' else '1'}.{p}"] = v.clone() + 1
        elif k.startswith("rnn."):
            out["bi_rnn." + k[4:]] = v.clone() + 1
        elif k.startswith("head."):
            out["linear." + k[5:]] = v.clone() + 1
        else:
            raise AssertionError(k)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("rnn", [True, False])
def test_official_checkpoint_converter(rnn, tmp_path):
    torch.manual_seed(0)
    m = HorizonNet(backbone="resnet18", hidden=16, rnn=rnn)
    off = _official_from(m)
    assert "feature_extractor.encoder.conv1.1.weight" in off and "feature_extractor.encoder.layer1.0.conv2.1.weight" in off
    conv = convert_official_state_dict({"state_dict": off, "kwargs": {"backbone": "resnet18"}})
    m2 = HorizonNet(backbone="resnet18", hidden=16, rnn=rnn)
    m2.load_state_dict(conv, strict=True)
    for k, v in m2.state_dict().items():
        assert torch.equal(v, m.state_dict()[k] + 1), k
    torch.save({"state_dict": off}, tmp_path / "hn.pth")
    m3 = create_model("horizonnet", backbone="resnet18", hidden=16, rnn=rnn, official_checkpoint=str(tmp_path / "hn.pth"))
    assert torch.equal(m3.head.state_dict()["bias" if rnn else "3.bias"], m.head.state_dict()["bias" if rnn else "3.bias"] + 1)
    with pytest.raises(ValueError):
        load_official_checkpoint(HorizonNet(backbone="resnet34", hidden=16, rnn=rnn), tmp_path / "hn.pth")
    with pytest.raises(FileNotFoundError):
        load_official_checkpoint(m, tmp_path / "missing.pth")


@pytest.mark.parametrize("width", [16, 17, 2, 3])
def test_circular_max_pool_is_the_pool_of_the_wrapped_map(width):
    from omnidl.models.horizonnet import CircularMaxPool2d
    torch.manual_seed(0)
    x = torch.randn(2, 3, 9, width)
    ref = F.max_pool2d(torch.cat([x[..., -1:], x, x[..., :1]], -1), 3, 2, padding=(1, 0))
    torch.testing.assert_close(CircularMaxPool2d()(x), ref, rtol=0, atol=0)
    torch.testing.assert_close(CircularMaxPool2d()(x.contiguous(memory_format=torch.channels_last)), ref,
                               rtol=0, atol=0)


def test_channels_last_gives_the_same_outputs_in_every_mode():
    torch.manual_seed(1)
    m = HorizonNet("resnet18", hidden=16, channels_last=True)
    assert m.channels_last and m.encoder.body.conv1.weight.is_contiguous(memory_format=torch.channels_last)
    b = HorizonNet("resnet18", hidden=16, channels_last=False)
    b.load_state_dict(m.state_dict())
    x = torch.rand(1, 3, 64, 128)
    for net in (m, b):
        net.eval()
    with torch.no_grad():
        a, ref = m(x), b(x)
    for k in ref:
        torch.testing.assert_close(a[k], ref[k], rtol=1e-5, atol=1e-5)
    m.train()
    assert m.encoder.body.conv1.weight.is_contiguous(memory_format=torch.channels_last)   # no switch by mode
    with pytest.raises(ValueError, match="channels_last"):
        HorizonNet("resnet18", hidden=16, channels_last="yes")
