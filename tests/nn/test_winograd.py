"""omnidl.nn.winograd: stride-1 3x3 inference convolutions by Winograd F(2x2, 3x3) on the native kernel.

Every case against ``F.conv2d`` (zero padding) or the wrapped convolution (1e-5 of the output's scale, float32);
the rule's verdicts in a table; the inference path taking it; the AVX2 and BLAS builds."""
from __future__ import annotations

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

import omnidl.nn.inference as inf
from omnidl.nn import native, winograd
from omnidl.nn.inference import conv_bn_act
from omnidl.nn.padding import CircularConv2d, pad_panorama

CL = torch.channels_last


@pytest.fixture(autouse=True)
def _native():
    if native.library() is None:
        pytest.skip("native kernels unavailable (no C compiler)")


def _close(a, b, tol=1e-5):
    scale = b.abs().max().clamp_min(1e-12)
    torch.testing.assert_close(a / scale, b / scale, rtol=0, atol=tol)


def _reference(x, w, b, wrap, residual, relu):
    y = F.conv2d(pad_panorama(x, 1), w, b, padding=(1, 0)) if wrap else F.conv2d(x, w, b, padding=1)
    if residual is not None:
        y = y + residual
    return F.relu(y) if relu else y


# (name, batch, C, Cout, H, W, wrap, bias, residual, relu)
CASES = [
    ("64 channels, wrap", 1, 64, 64, 16, 32, 1, True, False, True),
    ("zero padding", 1, 16, 32, 8, 12, 0, True, False, False),
    ("odd height and width (partial tiles)", 1, 8, 12, 7, 9, 0, True, False, True),
    ("odd sizes with wrap", 1, 8, 12, 5, 7, 1, True, False, True),
    ("channels off the kernel's panels and rows", 1, 33, 65, 6, 10, 1, True, False, True),
    ("no bias", 1, 16, 16, 6, 8, 0, False, False, False),
    ("residual written over", 1, 16, 24, 6, 8, 1, True, True, True),
    ("residual, no ReLU", 1, 16, 24, 5, 6, 0, True, True, False),
    ("batch 3", 3, 12, 20, 6, 10, 1, True, False, True),
    ("2 columns", 1, 4, 8, 4, 2, 1, True, False, False),
    ("one row", 1, 4, 8, 1, 6, 0, True, False, False),
    ("512 x 512 channels (the rule's largest)", 1, 512, 512, 4, 8, 1, True, False, True),
]


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("name,B,C,cout,H,W,wrap,bias,res,relu", CASES, ids=[c[0] for c in CASES])
def test_equals_the_direct_convolution(name, B, C, cout, H, W, wrap, bias, res, relu, threads):
    g = torch.Generator().manual_seed(C + cout + H)
    x = torch.randn(B, C, H, W, generator=g).contiguous(memory_format=CL)
    w = torch.randn(cout, C, 3, 3, generator=g)
    b = torch.randn(cout, generator=g) if bias else None
    residual = torch.randn(B, cout, H, W, generator=g).contiguous(memory_format=CL) if res else None
    ref = _reference(x, w, b, wrap, residual, relu)
    lib = native.library()
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        packed = winograd.pack(lib, w)
        out = residual.clone() if res else torch.empty(B, cout, H, W).contiguous(memory_format=CL)
        got = winograd.forward(lib, x, wrap, packed, cout, b, out, res, relu)
    finally:
        torch.set_num_threads(prev)
    assert got.data_ptr() == out.data_ptr() and got.is_contiguous(memory_format=CL)
    _close(got, ref)


def test_a_nan_pixel_reaches_only_its_neighbourhood():
    """A NaN input spreads to the outputs whose 3x3 window holds it, and to the rest of its 2x2 tiles' outputs
    (each tile's transform mixes its 4x4 patch); far outputs stay finite."""
    lib = native.library()
    x = torch.randn(1, 4, 12, 12).contiguous(memory_format=CL)
    x[0, 1, 6, 6] = float("nan")
    w = torch.randn(5, 4, 3, 3)
    out = winograd.forward(lib, x, 0, winograd.pack(lib, w), 5, None, torch.empty(1, 5, 12, 12).contiguous(
        memory_format=CL), False, False)
    nan = torch.isnan(out[0, 0])
    assert nan[5:8, 5:8].all() and not nan[:4].any() and not nan[10:].any()


# (name, module, input, verdict)
RULE = [
    ("plain 3x3, padding 1", lambda: nn.Conv2d(32, 32, 3, padding=1), (1, 32, 12, 12), 0),
    ("CircularConv2d 3x3, padding 1", lambda: CircularConv2d(32, 32, 3, padding=1), (1, 32, 12, 12), 1),
    ("stride 2", lambda: nn.Conv2d(32, 32, 3, stride=2, padding=1), (1, 32, 12, 12), None),
    ("dilation 2", lambda: nn.Conv2d(32, 32, 3, padding=2, dilation=2), (1, 32, 12, 12), None),
    ("groups 2", lambda: nn.Conv2d(32, 32, 3, padding=1, groups=2), (1, 32, 12, 12), None),
    ("padding 0", lambda: nn.Conv2d(32, 32, 3), (1, 32, 12, 12), None),
    ("reflect padding", lambda: nn.Conv2d(32, 32, 3, padding=1, padding_mode="reflect"), (1, 32, 12, 12), None),
    ("5x5", lambda: nn.Conv2d(32, 32, 5, padding=2), (1, 32, 12, 12), None),
    ("CircularConv2d with padding (1, 0)", lambda: CircularConv2d(32, 32, 3, padding=(1, 0)), (1, 32, 12, 12), None),
    ("one column", lambda: nn.Conv2d(32, 32, 3, padding=1), (1, 32, 48, 1), None),
    ("16 input channels (fewer than 32)", lambda: nn.Conv2d(16, 64, 3, padding=1), (1, 16, 12, 12), None),
    ("16 output channels", lambda: nn.Conv2d(64, 16, 3, padding=1), (1, 64, 12, 12), None),
    ("1024 x 512 channels (over the largest product)", lambda: nn.Conv2d(1024, 512, 3, padding=1),
     (1, 1024, 32, 32), None),
    ("512 x 512 on 24x24 (144 tiles: enough)", lambda: nn.Conv2d(512, 512, 3, padding=1), (1, 512, 24, 24), 0),
    ("512 x 512 on 8x16 (32 tiles, 144 needed)", lambda: nn.Conv2d(512, 512, 3, padding=1), (1, 512, 8, 16), None),
    ("256 x 256 on 16x20 (80 tiles: just enough)", lambda: nn.Conv2d(256, 256, 3, padding=1), (1, 256, 16, 20), 0),
    ("256 x 256 on 16x18 (72 tiles)", lambda: nn.Conv2d(256, 256, 3, padding=1), (1, 256, 16, 18), None),
    ("the batch's tiles count", lambda: nn.Conv2d(256, 256, 3, padding=1), (2, 256, 8, 20), 0),
]


@pytest.mark.parametrize("name,make,shape,verdict", RULE, ids=[r[0] for r in RULE])
def test_the_rule(name, make, shape, verdict):
    x = torch.randn(shape).contiguous(memory_format=CL)
    assert winograd.wrap_mode(x, make()) == verdict


def test_the_rule_needs_channels_last_float32_cpu():
    conv = nn.Conv2d(32, 32, 3, padding=1)
    x = torch.randn(1, 32, 12, 12)
    assert winograd.wrap_mode(x, conv) is None                                   # NCHW
    assert winograd.wrap_mode(x.double().contiguous(memory_format=CL), conv) is None
    assert winograd.wrap_mode(x.contiguous(memory_format=CL), conv) == 0


def test_the_inference_path_takes_it_and_can_be_turned_off(monkeypatch):
    torch.manual_seed(3)
    conv = CircularConv2d(32, 48, 3, padding=1).eval()
    bn = nn.BatchNorm2d(48).eval()
    x = torch.randn(1, 32, 8, 16).contiguous(memory_format=CL)
    assert winograd.wrap_mode(x, conv) == 1
    with torch.no_grad():
        ref = F.relu(bn(conv(x)))
        with torch.profiler.profile() as prof:
            y = conv_bn_act(x, conv, bn, "relu")
        assert "mkldnn::_convolution_pointwise" not in [e.name for e in prof.events()]
        assert inf._CACHE[conv].wino is not None
        _close(y, ref)
        monkeypatch.setattr(winograd, "ENABLED", False)
        with torch.profiler.profile() as prof:
            z = conv_bn_act(x, conv, bn, "relu")
        assert "mkldnn::_convolution_pointwise" in [e.name for e in prof.events()]
        _close(z, ref)


@pytest.mark.parametrize("build", ["generic_x86_build", "avx2_build"])
def test_other_builds(build, request):
    """The AVX2 build (6x16 tile on 16-column panels) gives the same results; the BLAS build has no Winograd
    (``pack`` gives ``None``) and the inference path then takes oneDNN."""
    request.getfixturevalue(build)
    torch.manual_seed(4)
    conv, bn = nn.Conv2d(32, 40, 3, padding=1).eval(), nn.BatchNorm2d(40).eval()
    x = torch.randn(2, 32, 8, 11).contiguous(memory_format=CL)
    assert winograd.wrap_mode(x, conv) == 0
    lib = native.library()
    assert (winograd.pack(lib, conv.weight) is None) == (build == "generic_x86_build")
    with torch.no_grad():
        _close(conv_bn_act(x, conv, bn, "relu"), F.relu(bn(conv(x))))
