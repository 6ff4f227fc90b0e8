"""omnidl.nn.tap_projection: a "same" convolution as a projection onto its taps and a shifted sum."""
from __future__ import annotations

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from omnidl.cameras import Equirectangular
from omnidl.nn import CircularConv2d, ProjectedConv2d
from omnidl.nn import tap_projection as tp

from .conftest import native_calls

CL = torch.channels_last

# (name, make conv, input shape, channels-last input)
CASES = [
    ("circular 3x3, 1 out", lambda: CircularConv2d(16, 1, 3, padding=1), (1, 16, 6, 9), False),
    ("circular 3x3, 2 out, batch 2", lambda: CircularConv2d(8, 2, 3, padding=1), (2, 8, 5, 7), False),
    ("zeros 3x3", lambda: nn.Conv2d(8, 2, 3, padding=1), (2, 8, 5, 7), False),
    ("zeros 3x3, no bias", lambda: nn.Conv2d(8, 2, 3, padding=1, bias=False), (1, 8, 5, 7), False),
    ("circular 5x3, dilation 2", lambda: CircularConv2d(6, 1, (5, 3), padding=(4, 2), dilation=2), (1, 6, 7, 8), False),
    ("zeros 1x3", lambda: nn.Conv2d(4, 3, (1, 3), padding=(0, 1)), (1, 4, 3, 5), False),
    ("circular 3x3, channels-last", lambda: CircularConv2d(8, 2, 3, padding=1), (2, 8, 5, 7), True),
    ("circular, wider than the map", lambda: CircularConv2d(3, 1, 5, padding=2), (1, 3, 2, 3), False),
    ("zeros, wider than the map", lambda: nn.Conv2d(3, 1, 5, padding=2), (1, 3, 2, 3), False),
]


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)], ids=["f32", "f64"])
@pytest.mark.parametrize("name,make,shape,cl", CASES, ids=[c[0] for c in CASES])
def test_equals_the_convolution_with_gradients(name, make, shape, cl, dtype, tol):
    torch.manual_seed(0)
    conv = make().to(dtype)
    x = torch.randn(shape, dtype=dtype)
    if cl:
        x = x.contiguous(memory_format=CL)
    x.requires_grad_()
    y = tp.shift_sum(conv, tp.project(conv, x))
    ref = conv(x)
    assert y.shape == ref.shape
    torch.testing.assert_close(y, ref, rtol=tol, atol=tol)
    g = torch.randn_like(ref)
    params = [x] + list(conv.parameters())
    for a, b in zip(torch.autograd.grad((y * g).sum(), params), torch.autograd.grad((ref * g).sum(), params)):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)


@pytest.mark.parametrize("wrap", [True, False])
def test_gradcheck(wrap):
    torch.manual_seed(1)
    conv = (CircularConv2d(3, 2, 3, padding=1) if wrap else nn.Conv2d(3, 2, 3, padding=1)).double()
    x = torch.randn(1, 3, 4, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: tp.shift_sum(conv, tp.project(conv, x)), (x,))
    assert torch.autograd.gradgradcheck(lambda x: tp.shift_sum(conv, tp.project(conv, x)), (x,))


def test_projection_commutes_with_upsampling_and_sums():
    """Why the depth branch may project first: P acts on each pixel alone."""
    torch.manual_seed(2)
    conv = CircularConv2d(12, 1, 3, padding=1).double()
    a, b = torch.randn(1, 12, 4, 8, dtype=torch.float64), torch.randn(1, 12, 8, 16, dtype=torch.float64)
    up = lambda m: F.interpolate(m, size=(8, 16), mode="bilinear", align_corners=True)   # noqa: E731
    first = tp.shift_sum(conv, up(tp.project(conv, a)) + 0.3 * tp.project(conv, b))
    torch.testing.assert_close(first, conv(up(a) + 0.3 * b), rtol=1e-12, atol=1e-12)


def test_projection_matrix_rows_are_the_taps():
    w = torch.arange(2 * 3 * 3 * 3, dtype=torch.float64).view(2, 3, 3, 3)
    P = tp.projection_matrix(w)
    assert P.shape == (18, 3)
    torch.testing.assert_close(P[1 * 9 + 2 * 3 + 0], w[1, :, 2, 0])


_CAM = Equirectangular(width=16, height=8)
# (name, conv, tap_offsets is None, pays for its own in_channels)
RULES = [
    ("circular 128 -> 1", CircularConv2d(128, 1, 3, padding=1), False, True),
    ("zeros 128 -> 1", nn.Conv2d(128, 1, 3, padding=1), False, True),
    ("128 -> 7: 63 * 2 <= 128", nn.Conv2d(128, 7, 3, padding=1), False, True),
    ("128 -> 8: 72 * 2 > 128", nn.Conv2d(128, 8, 3, padding=1), False, False),
    ("128 -> 14 (the semantic head)", CircularConv2d(128, 14, 3, padding=1), False, False),
    ("strided", nn.Conv2d(128, 1, 3, stride=2, padding=1), True, False),
    ("grouped", nn.Conv2d(128, 2, 3, padding=1, groups=2), True, False),
    ("not 'same'", nn.Conv2d(128, 1, 3, padding=0), True, False),
    ("padding='same'", nn.Conv2d(128, 1, 3, padding="same"), True, False),
    ("reflect padding mode", nn.Conv2d(128, 1, 3, padding=1, padding_mode="reflect"), True, False),
    ("ProjectedConv2d", ProjectedConv2d(128, 1, 3, camera=_CAM), True, False),
    ("a subclass of nn.Conv2d", type("MyConv", (nn.Conv2d,), {})(128, 1, 3, padding=1), True, False),
]


@pytest.mark.parametrize("name,conv,none,pays", RULES, ids=[r[0] for r in RULES])
def test_rule(name, conv, none, pays):
    assert (tp.tap_offsets(conv) is None) == none
    assert tp.pays(conv) == pays


def test_rule_reads_the_map_channels_and_the_switch(monkeypatch):
    conv = nn.Conv2d(8, 1, 3, padding=1)
    assert not tp.pays(conv) and tp.pays(conv, in_channels=18)
    monkeypatch.setattr(tp, "ENABLED", False)
    assert not tp.pays(nn.Conv2d(128, 1, 3, padding=1))


def test_bad_inputs_name_what_was_expected():
    with pytest.raises(ValueError, match="stride-1 'same'"):
        tp.shift_sum(nn.Conv2d(4, 1, 3, stride=2, padding=1), torch.zeros(1, 9, 4, 4))
    with pytest.raises(ValueError, match="expected 1 x 9 projected channels, got 8"):
        tp.shift_sum(nn.Conv2d(4, 1, 3, padding=1), torch.zeros(1, 8, 4, 4))


# (name, P rows, map shape (B, C, h, w), channels-last map, dtype, the native products run): project()'s products
# on omnidl's kernels (the few-column kernel's two forms, the register kernel) or PyTorch's, against float64
NATIVE_CASES = [
    ("depth head: 9 taps, 128 channels", 9, (1, 128, 16, 32), False, torch.float32, True),
    ("batch 2 (the weight gradient accumulated), ragged", 9, (2, 40, 7, 13), False, torch.float32, True),
    ("11 taps, channels fewer than a vector", 11, (1, 5, 3, 37), False, torch.float32, True),
    ("one tap", 1, (2, 33, 4, 5), False, torch.float32, True),
    ("12 taps: bmm", 12, (1, 16, 4, 5), False, torch.float32, False),
    ("channels-last map: matmul", 9, (1, 16, 4, 5), True, torch.float32, False),
    ("float64: bmm", 9, (1, 16, 4, 5), False, torch.float64, False),
]


@pytest.mark.parametrize("name,rows,shape,cl,dtype,native_run", NATIVE_CASES, ids=[c[0] for c in NATIVE_CASES])
def test_projection_products(name, rows, shape, cl, dtype, native_run, monkeypatch):
    from omnidl.nn import native
    lib = native.library()
    if lib is None:
        pytest.skip("native library not built")
    calls = native_calls(monkeypatch, "omnidl_gemm_narrow", "omnidl_gemm")
    g = torch.Generator().manual_seed(rows + shape[1])
    P = torch.randn(rows, shape[1], dtype=dtype, generator=g, requires_grad=True)
    m = torch.randn(shape, dtype=dtype, generator=g)
    if cl:
        m = m.contiguous(memory_format=CL)
    m.requires_grad_()
    conv = nn.Conv2d(shape[1], rows, 1, bias=False).to(dtype)
    monkeypatch.setattr(tp, "projection_matrix", lambda weight: P)
    z = tp.project(conv, m)
    gz = torch.randn(z.shape, dtype=dtype, generator=g)
    gp, gm = torch.autograd.grad(z, (P, m), gz)
    B, C, h, w = shape
    pd, md, gzd = P.detach().double(), m.detach().double().reshape(B, C, h * w), gz.double().reshape(B, rows, h * w)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    scale = lambda t: tol * max(1.0, float(t.abs().max()))
    want = (pd @ md).reshape(z.shape)
    torch.testing.assert_close(z.double(), want, rtol=0, atol=scale(want))
    want_p, want_m = (gzd @ md.transpose(1, 2)).sum(0), (pd.t() @ gzd).reshape(shape)
    torch.testing.assert_close(gp.double(), want_p, rtol=0, atol=scale(want_p))
    torch.testing.assert_close(gm.double(), want_m, rtol=0, atol=scale(want_m))
    assert z.shape == (B, rows, h, w) and z.is_contiguous() != cl
    expected = ["omnidl_gemm_narrow"] * B + ["omnidl_gemm_narrow"] * B + ["omnidl_gemm"] * B if native_run else []
    assert calls == expected


def test_projection_second_derivatives_under_create_graph(monkeypatch):
    torch.manual_seed(3)
    P = torch.randn(9, 6, requires_grad=True)
    m = torch.randn(2, 6, 3, 4, requires_grad=True)
    conv = nn.Conv2d(6, 9, 1, bias=False)
    monkeypatch.setattr(tp, "projection_matrix", lambda weight: P)
    out = []
    for switch in (True, False):          # native products, then bmm
        monkeypatch.setattr(tp, "NATIVE_PRODUCTS", switch)
        z = tp.project(conv, m)
        (gm,) = torch.autograd.grad((z ** 2).sum(), m, create_graph=True)
        (ggp,) = torch.autograd.grad(gm.sum(), P)
        out.append((gm.detach(), ggp))
    torch.testing.assert_close(out[0][0], out[1][0], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out[0][1], out[1][1], rtol=1e-5, atol=1e-4)
