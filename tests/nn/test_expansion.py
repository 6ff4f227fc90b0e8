"""omnidl.nn.expansion: a thin 1x1 convolution + batch norm (batch statistics) + activation, fused for training.

Every case against the modules' own composition (``act(bn(conv(x)))`` on deep copies): the output, the input's
and every parameter's gradient (1e-5 of their scale, float32), the running statistics and ``num_batches_tracked``;
the convolution's bias, which cancels in batch norm, gets a zero gradient where the modules' is rounding noise.
Second derivatives run through the modules' ops; the rule's verdict on a table of cases that must stay with the
modules."""
from __future__ import annotations

import copy

import pytest
import torch
import torch.nn as nn

import omnidl.nn.expansion as E
from omnidl.nn import native
from omnidl.nn.prelu import PReLU
from omnidl.nn.wconv import WConv

pytestmark = pytest.mark.skipif(native.library() is None, reason="no native library in this build")


def _close(a, b, tol=1e-5):
    scale = b.abs().max().clamp_min(1e-30)
    torch.testing.assert_close(a / scale, b / scale, rtol=0, atol=tol)


def _modules(cin, cout, act, bias=True, momentum=0.1, seed=0):
    torch.manual_seed(seed)
    conv = nn.Conv2d(cin, cout, 1, bias=bias)
    bn = nn.BatchNorm2d(cout, momentum=momentum)
    with torch.no_grad():
        bn.weight.uniform_(0.5, 1.5)
        bn.bias.normal_()
        bn.running_mean.normal_()
        bn.running_var.uniform_(0.5, 2.0)
        if isinstance(act, nn.PReLU):
            act.weight.uniform_(0.05, 0.4)
    return conv, bn, act


ACTS = {"PReLU per channel": lambda c: PReLU(c), "one shared PReLU": lambda c: PReLU(), "nn.PReLU": nn.PReLU,
        "ReLU": lambda c: nn.ReLU(), "none": lambda c: nn.Identity()}
# (name, input shape, output channels, activation, conv bias, momentum)
CASES = [
    ("FreDSNet's 4 -> 128 at 64x128, PReLU", (1, 4, 64, 128), 128, "PReLU per channel", True, 0.1),
    ("ReLU", (1, 4, 64, 128), 128, "ReLU", True, 0.1),
    ("no activation, no bias", (1, 4, 64, 128), 64, "none", False, 0.1),
    ("one slope, batch 2, ragged chunks", (2, 3, 47, 61), 40, "one shared PReLU", True, 0.1),
    ("nn.PReLU, 8 channels in, cumulative average", (1, 8, 70, 73), 24, "nn.PReLU", True, None),
    ("two channels in", (1, 2, 64, 70), 16, "ReLU", True, 0.3),
]


@pytest.mark.parametrize("name,shape,cout,act,bias,momentum", CASES, ids=[c[0] for c in CASES])
def test_equals_the_modules(name, shape, cout, act, bias, momentum):
    conv, bn, a = _modules(shape[1], cout, ACTS[act](cout), bias, momentum)
    ref = copy.deepcopy(nn.Sequential(conv, bn, a)).train()
    g = torch.Generator().manual_seed(1)
    x = (torch.randn(shape, generator=g) * 2 + 0.5).requires_grad_()
    xr = x.detach().clone().requires_grad_()
    assert E.applies(x, conv, bn, a)
    for step in range(2):                                          # running statistics over two updates
        y, yr = E.expansion(x, conv, bn, a), ref(xr)
        _close(y, yr)
        gy = torch.randn(yr.shape, generator=g)
        y.backward(gy)
        yr.backward(gy)
    _close(x.grad, xr.grad)
    for (n, p), (_, q) in zip(nn.Sequential(conv, bn, a).named_parameters(), ref.named_parameters()):
        if n == "0.bias":                                        # cancels in batch norm: zero, the modules' noise
            assert torch.count_nonzero(p.grad) == 0
            assert q.grad.abs().max() < 1e-4 * ref[0].weight.grad.abs().max()
        else:
            _close(p.grad, q.grad)
    torch.testing.assert_close(bn.running_mean, ref[1].running_mean, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(bn.running_var, ref[1].running_var, rtol=1e-5, atol=1e-6)
    assert int(bn.num_batches_tracked) == int(ref[1].num_batches_tracked) == 2


def test_second_derivatives_run_through_the_modules():
    conv, bn, a = _modules(4, 32, PReLU(32))
    ref = copy.deepcopy(nn.Sequential(conv, bn, a)).train()
    x = torch.randn(1, 4, 64, 64, requires_grad=True)
    xr = x.detach().clone().requires_grad_()
    (gx,) = torch.autograd.grad(E.expansion(x, conv, bn, a).square().sum(), x, create_graph=True)
    (gxr,) = torch.autograd.grad(ref(xr).square().sum(), xr, create_graph=True)
    _close(gx, gxr)
    (ggw,) = torch.autograd.grad(gx.square().sum(), conv.weight)
    (ggwr,) = torch.autograd.grad(gxr.square().sum(), ref[0].weight)
    _close(ggw, ggwr, 1e-4)


def test_nan_in_the_input_gives_nan_as_the_modules():
    conv, bn, a = _modules(4, 16, nn.ReLU())
    x = torch.randn(1, 4, 64, 64)
    x[0, 1, 3, 3] = float("nan")
    y, ref = E.expansion(x, conv, bn, a), copy.deepcopy(nn.Sequential(conv, bn, a))(x)
    assert torch.isnan(y).all() and torch.isnan(ref).all()


def test_wconv_in_training_takes_it(monkeypatch):
    torch.manual_seed(0)
    w = WConv(16, 128).train()
    ref = copy.deepcopy(w)
    x = torch.randn(1, 16, 64, 96)
    calls = []
    real = E._Expansion.apply
    monkeypatch.setattr(E._Expansion, "apply", lambda *args: calls.append(1) or real(*args))
    y = w(x)
    assert calls == [1]                                            # the 4 -> 128 expansion
    monkeypatch.setattr(E, "ENABLED", False)
    _close(y, ref(x))


def _hooked(m):
    m.register_forward_hook(lambda *a: None)
    return m


# (name, input, conv, bn in training, activation, verdict)
RULE = [
    ("the case itself", (1, 4, 64, 64), lambda: nn.Conv2d(4, 32, 1), True, nn.ReLU, True),
    ("batch norm in eval", (1, 4, 64, 64), lambda: nn.Conv2d(4, 32, 1), False, nn.ReLU, False),
    ("9 input channels", (1, 9, 64, 64), lambda: nn.Conv2d(9, 32, 1), True, nn.ReLU, False),
    ("3x3", (1, 4, 64, 64), lambda: nn.Conv2d(4, 32, 3, padding=1), True, nn.ReLU, False),
    ("stride 2", (1, 4, 64, 64), lambda: nn.Conv2d(4, 32, 1, stride=2), True, nn.ReLU, False),
    ("too few pixels", (1, 4, 32, 64), lambda: nn.Conv2d(4, 32, 1), True, nn.ReLU, False),
    ("another activation", (1, 4, 64, 64), lambda: nn.Conv2d(4, 32, 1), True, nn.GELU, False),
    ("a hooked convolution", (1, 4, 64, 64), lambda: _hooked(nn.Conv2d(4, 32, 1)), True, nn.ReLU, False),
    ("float64", (1, 4, 64, 64), lambda: nn.Conv2d(4, 32, 1).double(), True, nn.ReLU, False),
    ("channels-last input", (1, 4, 64, 64), lambda: nn.Conv2d(4, 32, 1), True, nn.ReLU, False),
]


@pytest.mark.parametrize("name,shape,make,training,act,verdict", RULE, ids=[r[0] for r in RULE])
def test_the_rule(name, shape, make, training, act, verdict):
    conv = make()
    dtype = conv.weight.dtype
    bn = nn.BatchNorm2d(32).to(dtype).train(training)
    x = torch.randn(shape, dtype=dtype)
    if name.startswith("channels-last"):
        x = x.contiguous(memory_format=torch.channels_last)
    assert E.applies(x, conv, bn, act()) is verdict
    if not verdict:                                                # the modules themselves
        y = E.expansion(x, conv, bn, act())
        assert y.shape == (shape[0], 32) + tuple(y.shape[2:])


def test_the_switch(monkeypatch):
    monkeypatch.setattr(E, "ENABLED", False)
    conv, bn, a = _modules(4, 32, nn.ReLU())
    assert not E.applies(torch.randn(1, 4, 64, 64), conv, bn, a)
