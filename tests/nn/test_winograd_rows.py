"""omnidl.nn.winograd_rows: 3x3 inference convolutions of stride (2, 1) by the row Winograd F(2, 3).

Every case against ``F.conv2d`` (zero padding) or the wrapped convolution (1e-5 of the output's scale, float32);
the kernel's stride-1 form too; the rule's verdicts in a table; the inference path and HorizonNet's towers taking
it; the AVX2 and BLAS builds."""
from __future__ import annotations

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

import omnidl.nn.inference as inf
from omnidl.nn import native, winograd_rows
from omnidl.nn.inference import conv_bn_act
from omnidl.nn.padding import CircularConv2d, pad_panorama

from .conftest import close_to_scale

CL = torch.channels_last


@pytest.fixture(autouse=True)
def _native():
    if native.library() is None:
        pytest.skip("native kernels unavailable (no C compiler)")


def _reference(x, w, b, wrap, relu, stride=(2, 1)):
    if wrap:
        y = F.conv2d(pad_panorama(x, 1), w, b, stride=stride, padding=(1, 0))
    else:
        y = F.conv2d(x, w, b, stride=stride, padding=1)
    return F.relu(y) if relu else y


# (name, batch, C, Cout, H, W, wrap, bias, relu)
CASES = [
    ("64 -> 32 channels, wrap (a tower's last layers)", 1, 64, 32, 16, 32, 1, True, True),
    ("zero padding", 1, 16, 32, 8, 12, 0, True, False),
    ("odd height (last output row: one input row below is padding)", 1, 8, 12, 7, 10, 0, True, True),
    ("odd width with wrap (a tile of one output)", 1, 8, 12, 6, 7, 1, True, True),
    ("odd width, zero padding", 1, 8, 12, 5, 9, 0, True, False),
    ("channels off the kernel's panels and rows", 1, 33, 65, 6, 10, 1, True, True),
    ("no bias, no ReLU", 1, 16, 16, 6, 8, 0, False, False),
    ("batch 3", 3, 12, 20, 6, 10, 1, True, True),
    ("2 columns", 1, 4, 8, 4, 2, 1, True, False),
    ("one row", 1, 4, 8, 1, 6, 0, True, False),
    ("two rows", 1, 4, 8, 2, 6, 1, True, True),
    ("few tiles, many output channels (threads split the channels)", 1, 64, 256, 2, 4, 1, True, True),
    ("channels split on 3 threads, many tiles (several blocks each with a 1 MB L2)", 1, 64, 256, 20, 48, 1, True, True),
    ("3C a multiple of 1024 (rows padded off one cache set)", 1, 1024, 40, 4, 6, 1, True, True),
]


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("name,B,C,cout,H,W,wrap,bias,relu", CASES, ids=[c[0] for c in CASES])
def test_equals_the_direct_convolution(name, B, C, cout, H, W, wrap, bias, relu, threads):
    g = torch.Generator().manual_seed(C + cout + H + W)
    x = torch.randn(B, C, H, W, generator=g).contiguous(memory_format=CL)
    w = torch.randn(cout, C, 3, 3, generator=g)
    b = torch.randn(cout, generator=g) if bias else None
    ref = _reference(x, w, b, wrap, relu)
    lib = native.library()
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        got = winograd_rows.forward(lib, x, wrap, winograd_rows.pack(lib, w), cout, b, relu)
    finally:
        torch.set_num_threads(prev)
    assert got.is_contiguous(memory_format=CL)
    close_to_scale(got, ref, name)


@pytest.mark.parametrize("wrap", [0, 1])
def test_the_kernels_stride_1_form(wrap):
    """The C entry point takes a vertical stride of 1 as well (the Python side uses 2)."""
    lib = native.library()
    g = torch.Generator().manual_seed(7)
    x = torch.randn(2, 24, 7, 9, generator=g).contiguous(memory_format=CL)
    w, b = torch.randn(40, 24, 3, 3, generator=g), torch.randn(40, generator=g)
    out = torch.empty(2, 40, 7, 9).contiguous(memory_format=CL)
    packed = winograd_rows.pack(lib, w)
    rc = lib.omnidl_wino_rows_forward(x.data_ptr(), 2, 7, 9, 24, 1, wrap, packed.data_ptr(), 40, b.data_ptr(),
                                      out.data_ptr(), 0, winograd_rows.block_tiles(24, 40), 2)
    assert rc == 0
    close_to_scale(out, _reference(x, w, b, wrap, False, stride=1), "stride 1")


def test_a_nan_pixel_reaches_only_its_neighbourhood():
    """A NaN input spreads to the outputs whose 3x3 window holds it and to their tile partners (each tile's
    transform mixes its 4 columns); far outputs stay finite. ReLU keeps a NaN."""
    lib = native.library()
    x = torch.randn(1, 4, 12, 12).contiguous(memory_format=CL)
    x[0, 1, 6, 6] = float("nan")
    w = torch.randn(5, 4, 3, 3)
    out = winograd_rows.forward(lib, x, 0, winograd_rows.pack(lib, w), 5, None, True)
    nan = torch.isnan(out[0, 0])
    assert nan[3:4, 5:8].all() and not nan[:2].any() and not nan[5:].any() and not nan[:, :4].any()


# (name, module, input, verdict)
RULE = [
    ("3x3 stride (2, 1), padding 1", lambda: nn.Conv2d(32, 32, 3, stride=(2, 1), padding=1), (1, 32, 12, 12), 0),
    ("CircularConv2d stride (2, 1)", lambda: CircularConv2d(32, 32, 3, stride=(2, 1), padding=1), (1, 32, 12, 12), 1),
    ("stride 1 (the 2-d Winograd's)", lambda: nn.Conv2d(32, 32, 3, padding=1), (1, 32, 12, 12), None),
    ("stride 2", lambda: nn.Conv2d(32, 32, 3, stride=2, padding=1), (1, 32, 12, 12), None),
    ("stride (1, 2)", lambda: nn.Conv2d(32, 32, 3, stride=(1, 2), padding=1), (1, 32, 12, 12), None),
    ("dilation 2", lambda: nn.Conv2d(32, 32, 3, stride=(2, 1), padding=2, dilation=2), (1, 32, 12, 12), None),
    ("groups 2", lambda: nn.Conv2d(32, 32, 3, stride=(2, 1), padding=1, groups=2), (1, 32, 12, 12), None),
    ("padding 0", lambda: nn.Conv2d(32, 32, 3, stride=(2, 1)), (1, 32, 12, 12), None),
    ("reflect padding", lambda: nn.Conv2d(32, 32, 3, stride=(2, 1), padding=1, padding_mode="reflect"),
     (1, 32, 12, 12), None),
    ("CircularConv2d with padding (1, 0)", lambda: CircularConv2d(32, 32, 3, stride=(2, 1), padding=(1, 0)),
     (1, 32, 12, 12), None),
    ("one column", lambda: nn.Conv2d(32, 32, 3, stride=(2, 1), padding=1), (1, 32, 48, 1), None),
    ("16 input channels (fewer than 32)", lambda: nn.Conv2d(16, 64, 3, stride=(2, 1), padding=1), (1, 16, 12, 12),
     None),
    ("16 output channels", lambda: nn.Conv2d(64, 16, 3, stride=(2, 1), padding=1), (1, 64, 12, 12), None),
    ("2048 -> 1024 on 8x16 (32 tiles, 48 needed)", lambda: nn.Conv2d(2048, 1024, 3, stride=(2, 1), padding=1),
     (1, 2048, 8, 16), None),
    ("2048 -> 1024 on 16x16 (64 tiles: enough)", lambda: nn.Conv2d(2048, 1024, 3, stride=(2, 1), padding=1),
     (1, 2048, 16, 16), 0),
    ("512 -> 256 on 1x16 (8 tiles, 18 needed)", lambda: nn.Conv2d(512, 256, 3, stride=(2, 1), padding=1),
     (1, 512, 1, 16), None),
    ("the batch's tiles count", lambda: nn.Conv2d(512, 256, 3, stride=(2, 1), padding=1), (3, 512, 1, 16), 0),
]


@pytest.mark.parametrize("name,make,shape,verdict", RULE, ids=[r[0] for r in RULE])
def test_the_rule(name, make, shape, verdict):
    x = torch.randn(shape).contiguous(memory_format=CL)
    assert winograd_rows.row_mode(x, make()) == verdict


def test_the_rule_needs_channels_last_float32_cpu():
    conv = nn.Conv2d(32, 32, 3, stride=(2, 1), padding=1)
    x = torch.randn(1, 32, 12, 12)
    assert winograd_rows.row_mode(x, conv) is None                                   # NCHW
    assert winograd_rows.row_mode(x.double().contiguous(memory_format=CL), conv) is None
    assert winograd_rows.row_mode(x.contiguous(memory_format=CL), conv) == 0


def test_the_inference_path_takes_it_and_can_be_turned_off(monkeypatch):
    torch.manual_seed(3)
    conv = CircularConv2d(32, 48, 3, stride=(2, 1), padding=1).eval()
    bn = nn.BatchNorm2d(48).eval()
    bn.running_mean.uniform_(-1, 1)
    bn.running_var.uniform_(0.5, 2)
    x = torch.randn(1, 32, 9, 16).contiguous(memory_format=CL)
    with torch.no_grad():
        ref = F.relu(bn(conv(x)))
        with torch.profiler.profile() as prof:
            y = conv_bn_act(x, conv, bn, "relu")
        assert "mkldnn::_convolution_pointwise" not in [e.name for e in prof.events()]
        assert inf._CACHE[conv].wino_rows is not None
        close_to_scale(y, ref, "rows path")
        monkeypatch.setattr(winograd_rows, "ENABLED", False)
        with torch.profiler.profile() as prof:
            z = conv_bn_act(x, conv, bn, "relu")
        assert "mkldnn::_convolution_pointwise" in [e.name for e in prof.events()]
        close_to_scale(z, ref, "oneDNN path")


def test_horizonnet_towers_take_it(monkeypatch):
    """HorizonNet's eval forward (towers of stride-(2, 1) layers) equals the one with the path turned off."""
    from omnidl.models import create_model
    torch.manual_seed(5)
    model = create_model("horizonnet", backbone="resnet18", rnn=False).eval()
    x = torch.rand(1, 3, 64, 128)
    calls = []
    real = winograd_rows.forward
    monkeypatch.setattr(winograd_rows, "forward", lambda *a: calls.append(1) or real(*a))
    with torch.no_grad():
        y = model(x)["boundary"]
        assert calls
        monkeypatch.setattr(winograd_rows, "ENABLED", False)
        z = model(x)["boundary"]
    close_to_scale(y, z, "HorizonNet")


@pytest.mark.parametrize("build", ["generic_x86_build", "avx2_build"])
def test_other_builds(build, request):
    """The AVX2 build (6x16 tile on 16-column panels) gives the same results; the BLAS build has no register
    kernel (``pack`` gives ``None``) and the inference path then takes oneDNN."""
    request.getfixturevalue(build)
    torch.manual_seed(4)
    conv, bn = nn.Conv2d(32, 40, 3, stride=(2, 1), padding=1).eval(), nn.BatchNorm2d(40).eval()
    x = torch.randn(2, 32, 9, 11).contiguous(memory_format=CL)
    assert winograd_rows.row_mode(x, conv) == 0
    lib = native.library()
    assert (winograd_rows.pack(lib, conv.weight) is None) == (build == "generic_x86_build")
    with torch.no_grad():
        close_to_scale(conv_bn_act(x, conv, bn, "relu"), F.relu(bn(conv(x))), build)
