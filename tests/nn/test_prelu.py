"""omnidl.nn.prelu: PReLU with the one-pass native backward.

Outputs and both gradients against ``F.prelu`` on a table of cases (1e-5 of their scale in float32, 1e-12 in
float64), each with the path it must take; the slope's gradient against float64; zeros (the slope's side);
second derivatives; the module against ``nn.PReLU``; the fallbacks."""
from __future__ import annotations

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

import omnidl.nn.prelu as P
from omnidl.nn import native
from omnidl.nn.prelu import PReLU, prelu
from omnidl.nn.wconv import make_activation

native_built = pytest.mark.skipif(native.library() is None, reason="the native kernels could not be built here")


def _close(a, b, tol):
    scale = b.abs().max().clamp_min(1e-30)
    torch.testing.assert_close(a / scale, b / scale, rtol=0, atol=tol)


# (name, input shape, slopes, dtype, channels-last (True: map and gradient; "x only": the map), takes the native
# backward)
CASES = [
    ("a plane longer than one block, with a tail", (2, 3, 37, 41), 3, torch.float32, False, True),
    ("a plane shorter than one block", (1, 5, 3, 4), 5, torch.float32, False, True),
    ("whole lanes shorter than one block, with a tail", (1, 4, 7, 73), 4, torch.float32, False, True),
    ("a deep layer's 16x32 planes: whole lanes", (2, 6, 16, 32), 6, torch.float32, False, True),
    ("one slope for all channels", (2, 4, 9, 30), 1, torch.float32, False, True),
    ("3-d input (B, C, N)", (3, 6, 100), 6, torch.float32, False, True),
    ("one channel", (2, 1, 33, 33), 1, torch.float32, False, True),
    ("channels-last, one chunk of channels", (1, 8, 5, 6), 8, torch.float32, True, True),
    ("channels-last, chunks of channels with a tail, sums flushed", (2, 150, 9, 17), 150, torch.float32, True, True),
    ("channels-last, one slope for all channels", (1, 70, 4, 30), 1, torch.float32, True, True),
    ("channels-last map, contiguous gradient: PyTorch's own", (1, 8, 5, 6), 8, torch.float32, "x only", False),
    ("float64: PyTorch's own", (1, 4, 5, 6), 4, torch.float64, False, False),
    ("float16: PyTorch's own", (1, 4, 5, 6), 4, torch.float16, False, False),
]


@pytest.mark.parametrize("name,shape,slopes,dtype,cl,native_path", CASES, ids=[c[0] for c in CASES])
def test_equals_f_prelu_with_gradients(name, shape, slopes, dtype, cl, native_path, monkeypatch):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(shape, generator=g).to(dtype)
    if cl:
        x = x.contiguous(memory_format=torch.channels_last)
    x[..., :2] = 0                                 # exact zeros take the slope's side (and add nothing to its sum)
    x.requires_grad_()
    a = (torch.rand(slopes, generator=g) * 0.5).to(dtype).requires_grad_()
    up = torch.randn(shape, generator=g).to(dtype)
    if cl is True:                                 # the gradient in the map's layout, as the layers after it give it
        up = up.contiguous(memory_format=torch.channels_last)
    calls = []
    real = P._composite_backward
    monkeypatch.setattr(P, "_composite_backward", lambda *t: calls.append(1) or real(*t))
    y = prelu(x, a)
    assert torch.equal(y, F.prelu(x, a))
    gx, ga = torch.autograd.grad(y, (x, a), up)
    rx, ra = torch.autograd.grad(F.prelu(x, a), (x, a), up)
    tol = {torch.float32: 1e-5, torch.float64: 1e-12, torch.float16: 1e-3}[dtype]
    _close(gx.float(), rx.float(), tol)
    _close(ga.float(), ra.float(), tol)
    assert ga.dtype == a.dtype and ga.shape == a.shape
    if cl is True:
        assert gx.is_contiguous(memory_format=torch.channels_last)
    if dtype == torch.float32 and native.library() is not None:
        ran = type(y.grad_fn).__name__ == "_PReLUBackward" and not calls
        assert ran is native_path                  # the native backward ran, or PyTorch's did


@native_built
def test_slope_gradient_against_float64():
    """The sums are kept in double: over a 128 x 256 plane the slope's gradient is as close to the float64 one
    as PyTorch's own."""
    g = torch.Generator().manual_seed(1)
    x = torch.randn(1, 4, 128, 256, generator=g, requires_grad=True)
    a = torch.full((4,), 0.25, requires_grad=True)
    up = torch.randn(1, 4, 128, 256, generator=g)
    ga = torch.autograd.grad(prelu(x, a), a, up)[0]
    a64 = a.detach().double().requires_grad_()
    ref = torch.autograd.grad(F.prelu(x.detach().double(), a64), a64, up.double())[0]
    aten = torch.autograd.grad(F.prelu(x, a), a, up)[0]
    ours_err = ((ga.double() - ref).abs().max() / ref.abs().max()).item()
    aten_err = ((aten.double() - ref).abs().max() / ref.abs().max()).item()
    assert ours_err <= max(aten_err, 1e-6)


def test_second_derivatives():
    x = torch.randn(2, 3, 4, 5, dtype=torch.float64)
    x[x.abs() < 0.1] = 0.5                         # away from the kink, where finite differences hold
    x.requires_grad_()
    a = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64, requires_grad=True)
    fn = lambda x, a: P._PReLU.apply(x, a)          # noqa: E731 - the function itself, also in float64
    assert torch.autograd.gradcheck(fn, (x, a))
    assert torch.autograd.gradgradcheck(fn, (x, a))


def test_module_is_nn_prelu_with_the_same_state():
    torch.manual_seed(0)
    ref = nn.PReLU(6, init=0.2)
    ours = PReLU(6)
    ours.load_state_dict(ref.state_dict())
    assert isinstance(ours, nn.PReLU) and list(ours.state_dict()) == list(ref.state_dict()) == ["weight"]
    x = torch.randn(2, 6, 7, 8, requires_grad=True)
    y, r = ours(x), ref(x)
    assert torch.equal(y, r)
    up = torch.randn_like(r)
    for a, b in zip(torch.autograd.grad(y, (x, ours.weight), up), torch.autograd.grad(r, (x, ref.weight), up)):
        _close(a, b, 1e-5)
    assert type(make_activation("prelu", 6)) is PReLU


def test_fallbacks_are_f_prelu_exactly(monkeypatch):
    x = torch.randn(1, 3, 4, 5, requires_grad=True)
    a = torch.rand(3, requires_grad=True)
    up = torch.randn(1, 3, 4, 5)
    ref = torch.autograd.grad(F.prelu(x, a), (x, a), up)
    for flag, lib in ((False, "keep"), (True, None)):
        monkeypatch.setattr(P, "ENABLED", flag)
        if lib is None:
            monkeypatch.setattr(native, "library", lambda: None)
        out = prelu(x, a)
        assert type(out.grad_fn).__name__ != "_PReLUBackward"
        for got, want in zip(torch.autograd.grad(out, (x, a), up), ref):
            torch.testing.assert_close(got, want, rtol=0, atol=0)
    with torch.no_grad():                          # no autograd: F.prelu's output, no graph
        assert prelu(x, a).grad_fn is None
