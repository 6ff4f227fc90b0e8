"""omnidl.nn.winograd_train: stride-1 3x3 convolutions in training by Winograd F(2x2, 3x3), both gradients included.

Every case against autograd over ``F.conv2d`` (zero padding) or the wrapped convolution: output, input, weight and
bias gradients at 1e-5 of their scale (float32); ``create_graph`` against the reference's second derivatives; the
rule's verdicts in a table; the layers that take it in training and not in inference; the AVX2 and BLAS builds."""
from __future__ import annotations

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from omnidl.nn import unfold_conv, winograd_train as wt
from omnidl.nn.padding import CircularConv2d, pad_panorama

from .test_winograd import _close, _native  # noqa: F401  (the autouse skip without a compiler, the scaled check)

CL = torch.channels_last


def _reference(x, w, b, wrap):
    return F.conv2d(pad_panorama(x, 1), w, b, padding=(1, 0)) if wrap else F.conv2d(x, w, b, padding=1)


def _grads(conv, x, w, b, gy):
    inputs = [t for t in (x, w, b) if t is not None]
    y = conv(x, w, b)
    return [y] + list(torch.autograd.grad(y, inputs, gy))


# (name, batch, C, Cout, H, W, wrap, bias, channels_last input)
CASES = [
    ("64 channels, wrap", 1, 64, 64, 16, 32, 1, True, False),
    ("zero padding", 1, 32, 48, 8, 12, 0, True, False),
    ("odd height and width (partial tiles)", 1, 32, 40, 7, 9, 0, True, False),
    ("odd sizes with wrap", 1, 36, 32, 5, 7, 1, True, False),
    ("channels off the kernel's panels and rows", 1, 33, 65, 6, 10, 1, True, False),
    ("no bias", 1, 32, 32, 6, 8, 0, False, False),
    ("batch 3", 3, 40, 36, 6, 10, 1, True, False),
    ("channels-last input", 2, 48, 32, 6, 8, 1, True, True),
    ("2 columns", 1, 32, 32, 4, 2, 1, True, False),
    ("one row", 1, 32, 32, 1, 6, 0, True, False),
    ("256 channels, more tiles than one chunk", 1, 256, 256, 16, 40, 0, True, False),
    ("512 x 512 channels (the rule's largest)", 1, 512, 512, 4, 8, 1, True, False),
]


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("name,B,C,cout,H,W,wrap,bias,cl", CASES, ids=[c[0] for c in CASES])
def test_equals_autograd_over_the_direct_convolution(name, B, C, cout, H, W, wrap, bias, cl, threads):
    g = torch.Generator().manual_seed(C + cout + H)
    x = torch.randn(B, C, H, W, generator=g)
    if cl:
        x = x.contiguous(memory_format=CL)
    x.requires_grad_()
    w = (torch.randn(cout, C, 3, 3, generator=g) / (3 * C ** 0.5)).requires_grad_()
    b = torch.randn(cout, generator=g).requires_grad_() if bias else None
    gy = torch.randn(B, cout, H, W, generator=g)
    ref = _grads(lambda x, w, b: _reference(x, w, b, wrap), x, w, b, gy)
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        got = _grads(lambda x, w, b: wt.conv2d(x, w, b, wrap), x, w, b, gy)
    finally:
        torch.set_num_threads(prev)
    for a, r in zip(got, ref):
        assert a.shape == r.shape
        _close(a, r)
    assert got[0].is_contiguous(memory_format=CL if cl else torch.contiguous_format)
    assert got[1].is_contiguous(memory_format=CL if cl else torch.contiguous_format)


def test_the_weight_gradient_keeps_a_channels_last_weight_layout():
    torch.manual_seed(0)
    x = torch.randn(1, 32, 8, 8, requires_grad=True)
    w = torch.randn(32, 32, 3, 3).contiguous(memory_format=CL).requires_grad_()
    wt.conv2d(x, w, None, 0).sum().backward()
    assert w.grad.is_contiguous(memory_format=CL)
    ref = torch.autograd.grad(F.conv2d(x, w, padding=1).sum(), w)[0]
    _close(w.grad, ref)


def test_second_derivatives_under_create_graph():
    """Under ``create_graph`` the backward is autograd's over the direct convolution: differentiable again, with the
    reference's second derivatives."""
    g = torch.Generator().manual_seed(1)
    x = torch.randn(1, 32, 6, 8, generator=g, requires_grad=True)
    w = (torch.randn(32, 32, 3, 3, generator=g) * 0.1).requires_grad_()
    b = torch.randn(32, generator=g, requires_grad=True)

    def penalty(conv):
        y = conv(x, w, b)
        gx, gw = torch.autograd.grad((y ** 2).sum(), (x, w), create_graph=True)
        return torch.autograd.grad((gx ** 2).sum() + (gw ** 2).sum(), (x, w, b))

    for a, r in zip(penalty(lambda x, w, b: wt.conv2d(x, w, b, 1)),
                    penalty(lambda x, w, b: _reference(x, w, b, 1))):
        _close(a, r)


def test_scratch_memory_grows_and_is_reused():
    """The per-thread filter and workspace memory serves layers of every size in turn (grown when too small)."""
    g = torch.Generator().manual_seed(2)
    for C, H in ((32, 8), (256, 16), (48, 10), (256, 16)):
        x = torch.randn(1, C, H, 2 * H, generator=g, requires_grad=True)
        w = (torch.randn(C, C, 3, 3, generator=g) / (3 * C ** 0.5)).requires_grad_()
        gy = torch.randn(1, C, H, 2 * H, generator=g)
        for a, r in zip(_grads(lambda x, w, b: wt.conv2d(x, w, b, 0), x, w, None, gy),
                        _grads(lambda x, w, b: _reference(x, w, b, 0), x, w, None, gy)):
            _close(a, r)


@pytest.mark.parametrize("bias", [torch.zeros(64, dtype=torch.float64), torch.zeros(63), torch.zeros(1, 64)],
                         ids=["float64", "63 values", "2-d"])
def test_a_bad_bias_gets_f_conv2d_s_error(bias):
    """A bias ``F.conv2d`` rejects is never read as float32 memory: ``F.conv2d`` gives its own error."""
    x = torch.randn(1, 64, 16, 16, requires_grad=True)
    w = torch.randn(64, 64, 3, 3, requires_grad=True)
    assert wt.applies(x, w)
    with pytest.raises(RuntimeError):
        wt.conv2d(x, w, bias, 0)
    with pytest.raises(RuntimeError):
        F.conv2d(x, w, bias, padding=1)


def test_a_nan_input_stays_in_its_outputs_and_gradients():
    """A NaN pixel makes NaN outputs near it (its tiles mix their 4x4 patch) and a NaN weight gradient, as the
    direct convolution does; far outputs stay finite."""
    x = torch.randn(1, 32, 12, 12)
    x[0, 3, 6, 6] = float("nan")
    x.requires_grad_()
    w = torch.randn(32, 32, 3, 3, requires_grad=True)
    y = wt.conv2d(x, w, None, 0)
    nan = torch.isnan(y[0, 0])
    assert nan[5:8, 5:8].all() and not nan[:4].any() and not nan[10:].any()
    y.sum().backward()
    assert torch.isnan(w.grad).any()


def _spec(C=64, cout=64, H=16, W=16, B=1, stride=1, padding=1, dilation=1, groups=1, k=3, dtype=torch.float32,
          grad=True):
    return dict(x=torch.randn(B, C, H, W, dtype=dtype, requires_grad=grad),
                w=torch.randn(cout, C // groups, k, k, dtype=dtype), stride=stride, padding=padding,
                dilation=dilation, groups=groups)


# (name, arguments, verdict)
RULE = [
    ("3x3, stride 1, padding 1, 64 tiles", _spec(), True),
    ("a tuple padding", _spec(padding=(1, 1)), True),
    ("the batch's tiles count (2 x 32)", _spec(B=2, H=8, W=16), True),
    ("32 tiles", _spec(H=8, W=16), False),
    ("stride 2", _spec(stride=2), False),
    ("padding 0", _spec(padding=0), False),
    ("padding (1, 0)", _spec(padding=(1, 0)), False),
    ("dilation 2", _spec(dilation=2, padding=2), False),
    ("groups 2", _spec(groups=2), False),
    ("5x5", _spec(k=5, padding=2), False),
    ("float64", _spec(dtype=torch.float64), False),
    ("32 input channels", _spec(C=32), False),
    ("32 output channels", _spec(cout=32), False),
    ("1024 x 512 channels (over the largest product)", _spec(C=1024, cout=512), False),
    ("one column", _spec(H=128, W=1), False),
    ("nothing needs a gradient", _spec(grad=False), False),
]


@pytest.mark.parametrize("name,spec,verdict", RULE, ids=[r[0] for r in RULE])
def test_the_rule(name, spec, verdict):
    args = (spec["x"], spec["w"], spec["stride"], spec["padding"], spec["dilation"], spec["groups"])
    assert wt.applies(*args) == verdict


def test_the_rule_needs_autograd_and_no_autocast(monkeypatch):
    spec = _spec()
    args = (spec["x"], spec["w"], 1, 1, 1, 1)
    assert wt.applies(*args)
    with torch.no_grad():
        assert not wt.applies(*args)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert not wt.applies(*args)
    monkeypatch.setattr(wt, "ENABLED", False)
    assert not wt.applies(*args)


@pytest.mark.parametrize("layer,wrap", [(lambda: nn.Conv2d(64, 72, 3, padding=1), 0),
                                        (lambda: CircularConv2d(64, 72, 3, padding=1), 1)], ids=["Conv2d", "circular"])
def test_layers_take_it_in_training_only(layer, wrap, monkeypatch):
    """``unfold_conv.module_conv2d`` (FFC's convolutions) and ``CircularConv2d`` take the Winograd path with autograd
    and give the module's own result; without autograd they do not."""
    torch.manual_seed(5)
    conv = layer()
    x = torch.randn(1, 64, 16, 16, requires_grad=True)          # 64 tiles
    calls = []
    real = wt.conv2d
    monkeypatch.setattr(wt, "conv2d", lambda *a, **k: calls.append(a[3] if len(a) > 3 else k["wrap"]) or real(*a, **k))
    y = unfold_conv.module_conv2d(conv, x)
    assert calls == [wrap]
    ref = _reference(x, conv.weight, conv.bias, wrap)
    _close(y, ref)
    gx, gw = torch.autograd.grad(y.sum(), (x, conv.weight))
    rx, rw = torch.autograd.grad(ref.sum(), (x, conv.weight))
    _close(gx, rx)
    _close(gw, rw)
    with torch.no_grad():
        unfold_conv.module_conv2d(conv, x)
    assert calls == [wrap]


@pytest.mark.parametrize("build", ["generic_x86_build", "avx2_build"])
def test_other_builds(build, request):
    """The AVX2 build (6x16 tile on 16-column panels) gives the same results; the BLAS build has no Winograd, so the
    rule says no and the layer stays with ``F.conv2d``."""
    request.getfixturevalue(build)
    g = torch.Generator().manual_seed(6)
    x = torch.randn(2, 64, 8, 15, generator=g, requires_grad=True)   # 64 tiles
    w = (torch.randn(72, 64, 3, 3, generator=g) * 0.05).requires_grad_()
    b = torch.randn(72, generator=g, requires_grad=True)
    assert wt.applies(x, w) == (build == "avx2_build")
    if build == "avx2_build":
        gy = torch.randn(2, 72, 8, 15, generator=g)
        for a, r in zip(_grads(lambda x, w, b: wt.conv2d(x, w, b, 1), x, w, b, gy),
                        _grads(lambda x, w, b: _reference(x, w, b, 1), x, w, b, gy)):
            _close(a, r)
