"""Thin convolutions on large maps through channels-last memory (omnidl.nn.thin_layout)."""
from __future__ import annotations

import pytest
import torch
import torch.nn as nn

from omnidl.nn import native, thin_layout
from omnidl.nn.padding import CircularConv2d, pad_panorama
from omnidl.nn.unfold_conv import module_conv2d

needs_native = pytest.mark.skipif(native.library() is None, reason="no native library")


@needs_native
@pytest.mark.parametrize("B,C,H,W,left,right", [(2, 19, 3, 37, 2, 1), (1, 16, 2, 16, 1, 1), (1, 5, 4, 9, 0, 3),
                                                (1, 3, 2, 6, 6, 6), (2, 7, 3, 20, 0, 0),
                                                # whole 16 x 16 register blocks, with and without partial edges
                                                (1, 32, 2, 48, 0, 0), (2, 48, 3, 35, 17, 16), (1, 33, 2, 64, 16, 1)])
def test_the_layout_kernels_equal_the_wrap_and_its_adjoint(B, C, H, W, left, right):
    g = torch.Generator().manual_seed(C * W)
    x = torch.randn(B, C, H, W, generator=g, requires_grad=True)
    y = thin_layout.to_channels_last(x, left, right)
    ref = pad_panorama(x.detach(), (left, right))
    assert y.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(y, ref, rtol=0, atol=0)
    up = torch.randn(ref.shape, generator=g)
    y.backward(up)
    xr = x.detach().clone().requires_grad_()
    pad_panorama(xr, (left, right)).backward(up)
    torch.testing.assert_close(x.grad, xr.grad, rtol=1e-6, atol=1e-6)
    assert x.grad.is_contiguous()


# (shape, dtype, requires grad, takes the native pass)
TO_NCHW = [((2, 19, 3, 37), torch.float32, False, True), ((1, 64, 8, 16), torch.float32, False, True),
           ((1, 3, 1, 5), torch.float32, False, True), ((1, 8, 4, 6), torch.float64, False, False),
           ((1, 8, 4, 6), torch.float32, True, False)]


@needs_native
@pytest.mark.parametrize("shape,dtype,grad,native_pass", TO_NCHW)
def test_to_nchw_equals_contiguous(shape, dtype, grad, native_pass, monkeypatch):
    g = torch.Generator().manual_seed(shape[1])
    t = torch.randn(shape, generator=g, dtype=dtype).contiguous(memory_format=torch.channels_last)
    t.requires_grad_(grad)
    calls = []
    run = thin_layout._run
    monkeypatch.setattr(thin_layout, "_run", lambda *a: (calls.append(a[0]), run(*a)))
    out = thin_layout.to_nchw(t)
    assert out.is_contiguous() and out.dtype == dtype
    torch.testing.assert_close(out, t.contiguous(), rtol=0, atol=0)
    assert calls == (["omnidl_wrap_from_nhwc"] if native_pass else [])


def test_to_nchw_keeps_a_contiguous_map():
    t = torch.randn(1, 4, 3, 5)
    assert thin_layout.to_nchw(t) is t


# (shape, dtype, requires grad, takes the native pass)
TO_NHWC = [((2, 19, 3, 37), torch.float32, False, True), ((1, 64, 8, 16), torch.float32, False, True),
           ((1, 128, 32, 64), torch.float32, False, True), ((1, 3, 1, 5), torch.float32, False, True),
           ((1, 8, 4, 6), torch.float64, False, False), ((1, 8, 4, 6), torch.float32, True, False)]


@needs_native
@pytest.mark.parametrize("shape,dtype,grad,native_pass", TO_NHWC)
def test_to_nhwc_equals_contiguous(shape, dtype, grad, native_pass, monkeypatch):
    g = torch.Generator().manual_seed(shape[1])
    t = torch.randn(shape, generator=g, dtype=dtype).requires_grad_(grad)
    calls = []
    run = thin_layout._run
    monkeypatch.setattr(thin_layout, "_run", lambda *a: (calls.append(a[0]), run(*a)))
    out = thin_layout.to_nhwc(t)
    assert out.is_contiguous(memory_format=torch.channels_last) and out.dtype == dtype
    torch.testing.assert_close(out, t.contiguous(memory_format=torch.channels_last), rtol=0, atol=0)
    assert calls == (["omnidl_wrap_to_nhwc"] if native_pass else [])
    cl = t.detach().contiguous(memory_format=torch.channels_last)
    assert thin_layout.to_nhwc(cl) is cl


# (name, module, x shape, takes channels-last)
LAYERS = [
    ("semantic-like head: 32 -> 14, 3x3 wrapped at 128x256",
     lambda: CircularConv2d(32, 14, 3, padding="same"), (1, 32, 128, 256), True),
    ("batch 2, 5x5 wrapped (2 columns each side)", lambda: CircularConv2d(16, 3, 5, padding="same"), (2, 16, 64, 128),
     True),
    ("stride 2, dilation 2, wrapped", lambda: CircularConv2d(32, 8, 3, stride=2, padding="same", dilation=2),
     (1, 32, 64, 128), True),
    ("FFC's 8 -> 8, 3x3 zero-padded", lambda: nn.Conv2d(8, 8, 3, padding=1), (1, 8, 128, 256), True),
    ("1x1 stride 2, 16 -> 4 (stride 1 takes the product)", lambda: nn.Conv2d(16, 4, 1, stride=2), (1, 16, 128, 256),
     True),
    ("grouped 8 -> 8, 2 groups", lambda: nn.Conv2d(8, 8, 3, padding=1, groups=2), (1, 8, 128, 256), True),
    ("16 output channels: NCHW", lambda: CircularConv2d(32, 16, 3, padding="same"), (1, 32, 128, 256), False),
    ("a small map: NCHW", lambda: nn.Conv2d(8, 8, 3, padding=1), (1, 8, 32, 64), False),
]


@needs_native
@pytest.mark.parametrize("name,make,shape,cl", LAYERS, ids=[c[0] for c in LAYERS])
def test_thin_layers_take_channels_last_with_the_same_result(name, make, shape, cl, monkeypatch):
    torch.manual_seed(0)
    conv = make()
    x = torch.randn(shape, requires_grad=True)
    assert thin_layout.pays(x, conv.weight) == cl
    calls = []
    real = thin_layout._ToChannelsLast.apply
    monkeypatch.setattr(thin_layout._ToChannelsLast, "apply", lambda *a: calls.append(1) or real(*a))

    def run(enabled: bool):
        monkeypatch.setattr(thin_layout, "ENABLED", enabled)
        x.grad = None
        conv.zero_grad()
        y = module_conv2d(conv, x)
        y.backward(torch.linspace(-1, 1, y.numel()).view(y.shape))
        return y.detach(), x.grad.clone(), conv.weight.grad.clone(), conv.bias.grad.clone()

    fast = run(True)
    assert len(calls) == int(cl)
    ref = run(False)
    assert len(calls) == int(cl)
    assert fast[0].is_contiguous() and fast[1].is_contiguous()
    for a, b in zip(fast, ref):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5 * float(b.abs().max()))


# (name, x, weight, grad mode, takes channels-last where the native library is built)
RULES = [
    ("a thin head in training", (1, 32, 128, 256), (14, 32, 3, 3), True, True),
    ("at MIN_NUMEL elements", (1, 8, 128, 128), (4, 8, 3, 3), True, True),
    ("just below MIN_NUMEL", (1, 8, 127, 128), (4, 8, 3, 3), True, False),
    ("inference (no autograd): NCHW's own paths", (1, 32, 128, 256), (14, 32, 3, 3), False, False),
    ("16 output channels", (1, 32, 128, 256), (16, 32, 3, 3), True, False),
]


@pytest.mark.parametrize("name,xs,ws,grad,cl", RULES, ids=[r[0] for r in RULES])
def test_the_rule(name, xs, ws, grad, cl):
    with torch.set_grad_enabled(grad):
        assert thin_layout.pays(torch.empty(xs), torch.empty(ws)) == (cl and native.library() is not None)


def test_the_rule_keeps_other_inputs_on_nchw(monkeypatch):
    x, w = torch.randn(1, 32, 128, 256), torch.randn(14, 32, 3, 3)
    assert not thin_layout.pays(x.double(), w.double())
    assert not thin_layout.pays(x.contiguous(memory_format=torch.channels_last), w)
    assert not thin_layout.pays(x[..., :200], w)                                   # not contiguous
    assert not thin_layout.pays(x[0], w[0])                                        # not 4-d
    monkeypatch.setattr(thin_layout, "ENABLED", False)
    assert not thin_layout.pays(x, w)


@needs_native
def test_differentiable_twice():
    """Under ``create_graph`` the gradient (linear in the upstream gradient) is built from differentiable ops: its
    derivative with respect to that upstream gradient is the wrap again."""
    x = torch.randn(1, 3, 4, 5, requires_grad=True)
    v = torch.randn(1, 3, 4, 5)

    def grads(wrap):
        up = torch.randn(1, 3, 4, 8, generator=torch.Generator().manual_seed(2), requires_grad=True)
        (gx,) = torch.autograd.grad(wrap(x), x, up, create_graph=True)
        (gup,) = torch.autograd.grad((gx * v).sum(), up)
        return gx.detach(), gup

    fast = grads(lambda t: thin_layout.to_channels_last(t, 2, 1))
    ref = grads(lambda t: pad_panorama(t, (2, 1)))
    for a, b in zip(fast, ref):
        torch.testing.assert_close(a, b)
    torch.testing.assert_close(fast[1], pad_panorama(v, (2, 1)))


def test_nhwc_into_nchw_writes_the_transpose_or_declines():
    src = torch.randn(2, 3, 5, 7)
    out = torch.empty(2, 7, 3, 5)
    assert thin_layout.nhwc_into_nchw(src, out) == (native.library() is not None)
    if native.library() is not None:
        assert torch.equal(out, src.permute(0, 3, 1, 2))
        with pytest.raises(ValueError, match=r"out must be \(2, 7, 3, 5\)"):
            thin_layout.nhwc_into_nchw(src, torch.empty(2, 3, 5, 7))
    assert not thin_layout.nhwc_into_nchw(src.double(), out.double())          # float32 only: nothing written
