"""Horizontal circular padding, CircularConv2d and the W-conv bottleneck."""
import numpy as np
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from omnidl.nn.padding import CircularConv2d, PanoramaPad2d, make_conv2d, pad_panorama
from omnidl.nn.wconv import WConv


@pytest.mark.parametrize("pw,ph", [(1, 1), (2, 0), ((1, 3), (2, 1))])
def test_pad_panorama_matches_numpy_wrap_and_zero(pw, ph):
    x = torch.arange(2 * 3 * 4 * 5, dtype=torch.float64).reshape(2, 3, 4, 5)
    l, r = (pw, pw) if isinstance(pw, int) else pw
    t, b = (ph, ph) if isinstance(ph, int) else ph
    expect = np.pad(x.numpy(), ((0, 0), (0, 0), (0, 0), (l, r)), mode="wrap")
    expect = np.pad(expect, ((0, 0), (0, 0), (t, b), (0, 0)), mode="constant")
    np.testing.assert_array_equal(pad_panorama(x, pw, ph).numpy(), expect)
    np.testing.assert_array_equal(PanoramaPad2d(pw, ph)(x).numpy(), expect)


# (left, right, width, channels-last): the widest wraps take the whole width
WRAP_CASES = [(1, 1, 5, False), (2, 0, 5, False), (0, 3, 4, False), (4, 4, 4, False), (1, 2, 3, True), (1, 1, 6, True)]


@pytest.mark.parametrize("left,right,width,cl", WRAP_CASES)
def test_pad_panorama_gradient_equals_the_concatenations(left, right, width, cl):
    """With autograd the wrap has its own backward (one buffer, the strips added where they came from): the same
    gradient as autograd's backward of the concatenation, in the input's memory format; gradcheck and
    gradgradcheck."""
    torch.manual_seed(0)
    x = torch.randn(2, 3, 4, width, dtype=torch.float64)
    if cl:
        x = x.contiguous(memory_format=torch.channels_last)
    x.requires_grad_()
    y = pad_panorama(x, (left, right), 1)
    literal = F.pad(torch.cat([x[..., width - left:], x, x[..., :right]], -1), (0, 0, 1, 1))
    torch.testing.assert_close(y, literal, rtol=0, atol=0)
    g = torch.randn_like(y)
    (got,) = torch.autograd.grad((y * g).sum(), x)
    (expect,) = torch.autograd.grad((literal * g).sum(), x)
    torch.testing.assert_close(got, expect, rtol=1e-15, atol=1e-15)
    assert got.is_contiguous(memory_format=torch.channels_last if cl else torch.contiguous_format)
    assert torch.autograd.gradcheck(lambda x: pad_panorama(x, (left, right), 1), (x,))
    assert torch.autograd.gradgradcheck(lambda x: pad_panorama(x, (left, right), 1), (x,))


def test_pad_panorama_vertical_replicate():
    x = torch.randn(1, 1, 3, 4)
    y = pad_panorama(x, 1, 1, vertical="replicate")
    torch.testing.assert_close(y[..., 0, 1:-1], x[..., 0, :])
    torch.testing.assert_close(y[..., -1, 1:-1], x[..., -1, :])


def test_circular_conv_equals_conv_on_padded_input():
    torch.manual_seed(0)
    conv = CircularConv2d(3, 4, 3, padding=1).double()
    x = torch.randn(2, 3, 6, 9, dtype=torch.float64)
    ref = F.conv2d(pad_panorama(x, 1, 1), conv.weight, conv.bias)
    torch.testing.assert_close(conv(x), ref)
    assert set(conv.state_dict()) == {"weight", "bias"}


def test_circular_conv_wraps_horizontally_only():
    torch.manual_seed(1)
    conv = CircularConv2d(2, 2, 3, padding="same")
    x = torch.randn(1, 2, 6, 10)
    # equivariant to horizontal rolls (no seam) ...
    torch.testing.assert_close(conv(torch.roll(x, 3, -1)), torch.roll(conv(x), 3, -1), atol=1e-6, rtol=1e-6)
    # ... while the top row never sees the bottom row (the reference code wraps both axes: a bug)
    x2 = x.clone()
    x2[..., -1, :] += 5.0
    torch.testing.assert_close(conv(x2)[..., 0, :], conv(x)[..., 0, :])
    ref_both = nn.Conv2d(2, 2, 3, padding=1, padding_mode="circular")
    ref_both.load_state_dict(conv.state_dict())
    assert not torch.allclose(ref_both(x2)[..., 0, :], ref_both(x)[..., 0, :])


def test_make_conv2d_kinds():
    assert type(make_conv2d(4, 4, 3)) is nn.Conv2d
    assert isinstance(make_conv2d(4, 4, 3, padding="circular"), CircularConv2d)
    assert type(make_conv2d(4, 4, 1, padding="circular", camera=object())) is nn.Conv2d
    with pytest.raises(ValueError, match="padding"):
        make_conv2d(4, 4, 3, padding="reflect")
    y = make_conv2d(4, 6, 3, stride=2, padding="circular")(torch.randn(1, 4, 8, 10))
    assert y.shape == (1, 6, 4, 5)


def test_wconv_shape_parameter_count_and_gradients():
    # FreDSNet's WConv(256, 512): 3 x (conv + bias + BN + PReLU) with bottleneck 64 = 88,576 parameters
    assert sum(p.numel() for p in WConv(256, 512).parameters()) == 88_576
    torch.manual_seed(2)
    w = WConv(8, 12, dropout=0.4).train()
    x = torch.randn(2, 8, 5, 7)
    y = w(x)
    assert y.shape == (2, 12, 5, 7)
    y.sum().backward()
    assert all(p.grad is not None for p in w.parameters())


def test_wconv_is_roll_equivariant_in_eval():
    torch.manual_seed(3)
    w = WConv(8, 4).eval()
    x = torch.randn(1, 8, 4, 12)
    torch.testing.assert_close(w(torch.roll(x, -5, -1)), torch.roll(w(x), -5, -1), atol=1e-6, rtol=1e-6)


def test_wconv_relu_variant_has_no_prelu():
    w = WConv(8, 4, activation="relu")
    assert not any(isinstance(m, nn.PReLU) for m in w.modules())


@pytest.mark.parametrize("padding_mode", ["zeros", "circular", "equi"])
def test_conv_norm_act_is_conv_then_norm_then_act_in_every_mode(padding_mode):
    from omnidl.cameras import Equirectangular
    from omnidl.nn.wconv import ConvNormAct
    torch.manual_seed(5)
    camera = Equirectangular(width=10, height=8) if padding_mode == "equi" else None
    block = ConvNormAct(3, 6, 3, padding="zeros" if camera else padding_mode, activation="relu",
                        camera=camera).double()
    block.norm.running_mean.normal_()
    block.norm.running_var.uniform_(0.5, 2.0)
    nn.init.normal_(block.norm.weight)
    nn.init.normal_(block.norm.bias)
    x = torch.randn(2, 3, 8, 10, dtype=torch.float64)
    block.eval()
    ref = F.relu(block.norm(block.conv(x)))
    torch.testing.assert_close(block(x), ref)
    with torch.no_grad():
        torch.testing.assert_close(block(x), ref)
    block.train()
    torch.testing.assert_close(block(x), F.relu(F.batch_norm(block.conv(x), None, None, block.norm.weight,
                                                             block.norm.bias, training=True)))
    block.norm = nn.GroupNorm(2, 6).double()                      # a swapped norm runs in every mode
    for train, grad in ((True, True), (False, True), (False, False)):
        block.train(train)
        with torch.set_grad_enabled(grad):
            torch.testing.assert_close(block(x), F.relu(block.norm(block.conv(x))))
