"""FFC / Fourier block: closed forms of the Fourier unit, shapes over channel ratios, gradients everywhere."""
import pytest
import torch
import torch.nn as nn

from omnidl.nn.ffc import FFC, FourierBlock, FourierUnit, SpectralTransform


def _identity_unit(c, layout, norm):
    fu = FourierUnit(c, c, fft_norm=norm, spectrum_layout=layout, activation="none").double().eval()
    k = c if layout == "width" else 2 * c
    with torch.no_grad():
        fu.conv.weight.copy_(torch.eye(k, dtype=torch.float64).view(k, k, 1, 1))
        fu.conv.bias.zero_()
    return fu


@pytest.mark.parametrize("layout", ["width", "channels"])
@pytest.mark.parametrize("norm", ["backward", "ortho"])
@pytest.mark.parametrize("size", [(7, 13), (8, 16), (5, 6)])
def test_fourier_unit_identity_round_trip(layout, norm, size):
    # identity 1x1 conv, fresh BN in eval (mean 0, var 1), no activation: rfft2 -> irfft2 recovers x
    torch.manual_seed(0)
    x = torch.randn(2, 3, *size, dtype=torch.float64)
    y = _identity_unit(3, layout, norm)(x)
    assert y.shape == x.shape
    torch.testing.assert_close(y, x / (1 + 1e-5) ** 0.5, atol=1e-10, rtol=1e-10)  # BN eps only


def test_fourier_unit_width_layout_is_complex_linear():
    # FreDSNet layout: the same real matrix A (plus bias b) acts on Re and Im: Y = A X + b (1 + i)
    torch.manual_seed(1)
    c, h, w = 3, 6, 10
    fu = FourierUnit(c, c, spectrum_layout="width", activation="none", norm=False).double()
    x = torch.randn(1, c, h, w, dtype=torch.float64)
    A = fu.conv.weight[:, :, 0, 0].detach()
    b = fu.conv.bias.detach()
    X = torch.fft.rfft2(x)
    Y = torch.einsum("oc,bchw->bohw", A.to(X.dtype), X) + (b * (1 + 1j)).view(1, c, 1, 1)
    expect = torch.fft.irfft2(Y, s=(h, w))
    torch.testing.assert_close(fu(x), expect, atol=1e-10, rtol=1e-10)


def test_fourier_unit_channels_layout_mixes_re_im():
    # LaMa layout: channel 2c = Re X_c, 2c+1 = Im X_c; a 2C x 2C real matrix
    torch.manual_seed(2)
    c, h, w = 2, 5, 9
    fu = FourierUnit(c, c, spectrum_layout="channels", fft_norm="ortho", activation="none", norm=False).double()
    x = torch.randn(1, c, h, w, dtype=torch.float64)
    M = fu.conv.weight[:, :, 0, 0].detach()
    b = fu.conv.bias.detach()
    X = torch.fft.rfft2(x, norm="ortho")
    z = torch.stack([X.real, X.imag], 2).reshape(1, 2 * c, h, -1)
    z = torch.einsum("oc,bchw->bohw", M, z) + b.view(1, -1, 1, 1)
    Y = torch.complex(z[:, 0::2], z[:, 1::2])
    torch.testing.assert_close(fu(x), torch.fft.irfft2(Y, s=(h, w), norm="ortho"), atol=1e-10, rtol=1e-10)


def test_fourier_unit_gradcheck():
    torch.manual_seed(3)
    fu = FourierUnit(2, 2, norm=False).double()
    x = torch.randn(1, 2, 4, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(fu, (x,))


def test_spectral_transform_closed_form_and_stride():
    torch.manual_seed(4)
    st = SpectralTransform(6, 8).eval()
    x = torch.randn(2, 6, 6, 10)
    h = st.conv_in(x)
    torch.testing.assert_close(st(x), st.conv_out(h + st.fourier(h)))
    assert SpectralTransform(6, 8, stride=2)(x).shape == (2, 8, 3, 5)


@pytest.mark.parametrize("rin,rout", [(0.0, 0.0), (0.0, 0.5), (0.5, 0.0), (0.25, 0.75), (0.5, 0.5), (1.0, 1.0)])
def test_ffc_shapes_for_ratios(rin, rout):
    ffc = FFC(8, 12, 3, rin, rout)
    y_l, y_g = ffc(torch.randn(2, 8, 7, 11))
    cg = int(12 * rout)
    assert (y_l is None) == (cg == 12) and (y_g is None) == (cg == 0)
    if y_l is not None:
        assert y_l.shape == (2, 12 - cg, 7, 11)
    if y_g is not None:
        assert y_g.shape == (2, cg, 7, 11)


def test_ffc_stride_two_and_tuple_input():
    ffc = FFC(8, 8, 3, 0.5, 0.5, stride=2)
    y_l, y_g = ffc((torch.randn(1, 4, 8, 12), torch.randn(1, 4, 8, 12)))
    assert y_l.shape == y_g.shape == (1, 4, 4, 6)


def test_ffc_paths_route_local_and_global_channels():
    # l->g / g->l wiring: zero the cross paths and the global input -> the global output is g2g(0) only
    torch.manual_seed(5)
    ffc = FFC(4, 4, 3, 0.5, 0.5, spectral=False).eval()
    for conv in (ffc.conv_l2g, ffc.conv_g2l):
        nn.init.zeros_(conv.weight)
        nn.init.zeros_(conv.bias)
    x_l, x_g = torch.randn(1, 2, 5, 6), torch.randn(1, 2, 5, 6)
    y_l, y_g = ffc((x_l, x_g))
    torch.testing.assert_close(y_l, ffc.conv_l2l(x_l))
    torch.testing.assert_close(y_g, ffc.conv_g2g(x_g))


@pytest.mark.parametrize("spectral", [True, False])
@pytest.mark.parametrize("size", [(6, 10), (7, 9)])
def test_fourier_block_gradients_reach_every_parameter(spectral, size):
    torch.manual_seed(6)
    fb = FourierBlock(8, spectral=spectral).train()
    x = torch.randn(2, 8, *size, requires_grad=True)
    y = fb(x)
    assert y.shape == x.shape
    (y * torch.randn_like(y)).sum().backward()
    missing = [n for n, p in fb.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not missing, missing
    assert torch.isfinite(x.grad).all()


def test_spectral_skip_is_not_detached():
    # kill the Fourier path (zero conv + zero bias -> spectrum 0): conv_in still learns via the skip
    torch.manual_seed(7)
    st = SpectralTransform(4, 4).train()
    nn.init.zeros_(st.fourier.conv.weight)
    nn.init.zeros_(st.fourier.conv.bias)
    nn.init.zeros_(st.fourier.norm.bias)
    st(torch.randn(2, 4, 6, 8)).pow(2).sum().backward()
    assert st.conv_in[0].weight.grad.abs().sum() > 0


def test_fourier_block_parameter_count_matches_fredsnet():
    # FreDSNet's FourierBlock(1, 256): 3 * (128*128*9 + 128) + Spectra(128) + 2 * (BN 128 + PReLU 128) = 464,640
    assert sum(p.numel() for p in FourierBlock(256).parameters()) == 464_640


def test_fourier_block_residual_and_split_order():
    # with the FFC output forced to 0 (zero convs, BN beta 0, PReLU(0)=0) the block is the identity
    fb = FourierBlock(4, spectral=False).eval()
    for m in fb.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.zeros_(m.weight)
            nn.init.zeros_(m.bias)
    x = torch.randn(1, 4, 5, 7)
    torch.testing.assert_close(fb(x), x)


def test_conv_layer_and_camera_are_forwarded():
    calls = []

    class StandIn(nn.Conv2d):
        def __init__(self, *a, camera=None, **k):
            calls.append(camera)
            super().__init__(*a, **k)

    cam = object()
    fb = FourierBlock(8, camera=cam, conv_layer=StandIn)
    assert calls == [cam, cam, cam]                       # l2l, l2g, g2l (g2g is spectral)
    assert fb(torch.randn(1, 8, 4, 6)).shape == (1, 8, 4, 6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fourier_block_dtypes(dtype):
    fb = FourierBlock(6).to(dtype)
    assert fb(torch.randn(1, 6, 4, 8, dtype=dtype)).dtype == dtype


def test_fourier_unit_under_bfloat16_autocast():
    fu = FourierUnit(4, 4)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = fu(torch.randn(1, 4, 6, 7))
    assert torch.isfinite(y.float()).all() and y.shape == (1, 4, 6, 7)
