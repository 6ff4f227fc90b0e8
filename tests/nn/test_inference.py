"""omnidl.nn.inference: conv -> BN -> (+ residual) -> ReLU in one oneDNN call with a folded, prepacked weight.

Every fast-path result is compared with the modules' own composition (1e-5 relative to the output's scale,
float32); the fallbacks (autograd, training, float64, disabled) must give the modules' results exactly."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

import omnidl.nn.inference as inf
from omnidl.cameras import Equirectangular
from omnidl.nn import winograd
from omnidl.nn.inference import conv_bn_act, fold_batchnorm, inference_ready
from omnidl.nn.padding import CircularConv2d
from omnidl.nn.projected_conv import ProjectedConv2d

CL = torch.channels_last


def _bn(c: int, seed: int = 0) -> nn.BatchNorm2d:
    g = torch.Generator().manual_seed(seed)
    bn = nn.BatchNorm2d(c)
    with torch.no_grad():
        bn.running_mean.copy_(torch.randn(c, generator=g) * 0.3)
        bn.running_var.copy_(torch.rand(c, generator=g) + 0.5)
        bn.weight.copy_(torch.randn(c, generator=g))
        bn.bias.copy_(torch.randn(c, generator=g))
    return bn.eval()


def _reference(x, conv, bn, act, residual):
    y = conv(x)
    if bn is not None:
        y = bn(y)
    if residual is not None:
        y = y + residual
    return F.relu(y) if act == "relu" else y


def _close(a, b, tol=1e-5):
    assert a.shape == b.shape
    scale = b.abs().max().clamp_min(1e-12)
    torch.testing.assert_close(a / scale, b / scale, rtol=0, atol=tol)


# (name, constructor of the convolution, input (C, H, W))
CONVS = [
    ("3x3", lambda: nn.Conv2d(8, 12, 3, padding=1), (8, 10, 16)),
    ("3x3 no bias", lambda: nn.Conv2d(8, 12, 3, padding=1, bias=False), (8, 10, 16)),
    ("1x1", lambda: nn.Conv2d(8, 24, 1), (8, 10, 16)),
    ("1x1 stride 2", lambda: nn.Conv2d(8, 24, 1, stride=2), (8, 10, 16)),
    ("7x7 stride 2", lambda: nn.Conv2d(3, 16, 7, stride=2, padding=3), (3, 20, 32)),
    ("3x3 stride (2, 1)", lambda: nn.Conv2d(8, 12, 3, stride=(2, 1), padding=(1, 0)), (8, 10, 18)),
    ("3x3 dilation 2", lambda: nn.Conv2d(8, 12, 3, padding=2, dilation=2), (8, 10, 16)),
    ("grouped", lambda: nn.Conv2d(8, 16, 3, padding=1, groups=4), (8, 10, 16)),
    ("5x3 rectangular", lambda: nn.Conv2d(8, 12, (5, 3), padding=(2, 1)), (8, 10, 16)),
    ("circular 3x3", lambda: CircularConv2d(8, 12, 3, padding=1), (8, 10, 16)),
    ("circular 5x5", lambda: CircularConv2d(8, 12, 5, padding=2), (8, 10, 40)),
    ("circular map smaller than the weight (padded copy)", lambda: CircularConv2d(8, 64, 3, padding=1), (8, 4, 8)),
    ("circular stride (2, 1)", lambda: CircularConv2d(8, 12, 3, stride=(2, 1), padding=1), (8, 10, 16)),
    ("circular stride 2 (padded copy)", lambda: CircularConv2d(8, 12, 3, stride=2, padding=1), (8, 10, 16)),
    ("circular narrow map (padded copy)", lambda: CircularConv2d(8, 12, 3, padding=1), (8, 6, 3)),
    ("circular dilation 2", lambda: CircularConv2d(8, 12, 3, padding=2, dilation=2), (8, 10, 16)),
    ("padding_mode circular (folded, not packed)",
     lambda: nn.Conv2d(8, 12, 3, padding=1, padding_mode="circular"), (8, 10, 16)),
    ("'same' padding (folded, not packed)", lambda: nn.Conv2d(8, 12, 3, padding="same"), (8, 10, 16)),
    ("ProjectedConv2d without camera", lambda: ProjectedConv2d(8, 12, 3, padding=1), (8, 10, 16)),
    ("ProjectedConv2d equirect (folded, own kernel)",
     lambda: ProjectedConv2d(8, 12, 3, padding=1, camera=Equirectangular(width=16, height=8)), (8, 8, 16)),
]


@pytest.mark.parametrize("name,make,shape", CONVS, ids=[c[0] for c in CONVS])
@pytest.mark.parametrize("bn", [True, False], ids=["bn", "no-bn"])
@pytest.mark.parametrize("act", ["relu", None])
@pytest.mark.parametrize("residual", [False, True], ids=["", "residual"])
@pytest.mark.parametrize("fmt", ["channels_last", "nchw"])
def test_fast_path_equals_the_modules(name, make, shape, bn, act, residual, fmt):
    torch.manual_seed(0)
    conv = make().eval()
    norm = _bn(conv.out_channels) if bn else None
    x = torch.randn(2, *shape)
    if fmt == "channels_last":
        x = x.contiguous(memory_format=CL)
    with torch.no_grad():
        assert inference_ready(x, conv, norm)
        ref0 = _reference(x, conv, norm, None, None)
        res = torch.randn_like(ref0) if residual else None
        ref = _reference(x, conv, norm, act, res)
        out = conv_bn_act(x, conv, norm, act, res)
        again = conv_bn_act(x, conv, norm, act, res)           # kept (folded, packed) weights
    _close(out, ref)
    torch.testing.assert_close(again, out, rtol=0, atol=0)


def test_packed_path_runs_one_onednn_call_and_keeps_channels_last(monkeypatch):
    monkeypatch.setattr(winograd, "ENABLED", False)       # a 3x3 stride-1 layer otherwise takes Winograd
    conv, bn = nn.Conv2d(8, 12, 3, padding=1).eval(), _bn(12)
    x = torch.randn(1, 8, 10, 16).contiguous(memory_format=CL)
    with torch.no_grad(), torch.profiler.profile() as prof:
        y = conv_bn_act(x, conv, bn, "relu")
    names = [e.name for e in prof.events()]
    assert "mkldnn::_convolution_pointwise" in names
    assert not any("batch_norm" in n or n in ("aten::relu", "aten::relu_", "aten::clamp_min") for n in names)
    assert y.is_contiguous(memory_format=CL)


def test_fold_batchnorm_matches_batchnorm_in_float64():
    torch.manual_seed(1)
    conv = nn.Conv2d(4, 6, 3, padding=1).double()
    bn = _bn(6).double()
    x = torch.randn(2, 4, 5, 7, dtype=torch.float64)
    w, b = fold_batchnorm(conv.weight, conv.bias, bn)
    torch.testing.assert_close(F.conv2d(x, w, b, padding=1), bn(conv(x)), rtol=1e-12, atol=1e-12)
    w, b = fold_batchnorm(conv.weight, None, bn)
    torch.testing.assert_close(F.conv2d(x, w, b, padding=1), bn(F.conv2d(x, conv.weight, None, padding=1)),
                               rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------------------------------------
# where the fast path must not run: the modules' own results, exactly
# ------------------------------------------------------------------------------------------------------------

FALLBACKS = [
    ("autograd: parameters require grad", lambda c, b, x: (c, b, x, torch.enable_grad)),
    ("autograd: input requires grad",
     lambda c, b, x: (c.requires_grad_(False), b.requires_grad_(False), x.requires_grad_(True), torch.enable_grad)),
    ("float64", lambda c, b, x: (c.double(), b.double(), x.double(), torch.no_grad)),
    ("BatchNorm in training", lambda c, b, x: (c, b.train(), x, torch.no_grad)),
    ("BatchNorm without running statistics",
     lambda c, b, x: (c, nn.BatchNorm2d(12, track_running_stats=False).eval(), x, torch.no_grad)),
    ("3-d input", lambda c, b, x: (nn.Conv1d(8, 12, 3, padding=1), None, x[:, :, 0], torch.no_grad)),
]


@pytest.mark.parametrize("name,setup", FALLBACKS, ids=[f[0] for f in FALLBACKS])
def test_fallbacks_give_the_modules_results(name, setup):
    torch.manual_seed(2)
    conv, bn, x, mode = setup(nn.Conv2d(8, 12, 3, padding=1).eval(), _bn(12),
                              torch.randn(2, 8, 6, 10).contiguous(memory_format=CL))
    with mode():
        assert not inference_ready(x, conv, bn)
        out = conv_bn_act(x, conv, bn, "relu")
        ref = _reference(x, conv, bn, "relu", None)
    torch.testing.assert_close(out, ref, rtol=0, atol=0)
    if out.requires_grad:
        out.sum().backward()
        assert (x.grad if x.requires_grad else conv.weight.grad) is not None


def test_disabled_flag_and_environment_variable(monkeypatch):
    conv, bn = nn.Conv2d(8, 12, 3, padding=1).eval(), _bn(12)
    x = torch.randn(1, 8, 6, 10).contiguous(memory_format=CL)
    monkeypatch.setattr(inf, "ENABLED", False)
    with torch.no_grad():
        assert not inference_ready(x, conv, bn)
        torch.testing.assert_close(conv_bn_act(x, conv, bn), bn(conv(x)), rtol=0, atol=0)
    code = "import omnidl.nn.inference as m; print(m.ENABLED)"
    for value, expect in (("0", "False"), ("off", "False"), ("1", "True")):
        env = dict(os.environ, OMNIDL_PACKED_CONV=value)
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
        assert out.stdout.strip() == expect


def test_a_conv_with_its_own_forward_is_called_as_it_is():
    class Doubled(nn.Conv2d):
        def forward(self, x):
            return 2 * super().forward(x)

    conv, bn = Doubled(8, 12, 3, padding=1).eval(), _bn(12)
    x = torch.randn(1, 8, 6, 10).contiguous(memory_format=CL)
    with torch.no_grad():
        torch.testing.assert_close(conv_bn_act(x, conv, bn, "relu"), F.relu(bn(conv(x))), rtol=0, atol=0)


def test_bad_activation_is_an_error():
    with pytest.raises(ValueError, match="act must be 'relu' or None"):
        conv_bn_act(torch.randn(1, 2, 4, 4), nn.Conv2d(2, 2, 1), None, "gelu")


# ------------------------------------------------------------------------------------------------------------
# kept weights follow every change of the parameters and statistics
# ------------------------------------------------------------------------------------------------------------

def _changes():
    def optimiser_step(conv, bn):
        opt = torch.optim.SGD(list(conv.parameters()) + list(bn.parameters()), lr=0.1)
        for p in opt.param_groups[0]["params"]:
            p.grad = torch.ones_like(p)
        opt.step()

    def load_state(conv, bn):
        other = nn.Conv2d(8, 12, 3, padding=1)
        conv.load_state_dict(other.state_dict())

    def train_step_updates_statistics(conv, bn):
        bn.train()
        bn(conv(torch.randn(4, 8, 6, 10) * 3 + 1))
        bn.eval()

    def in_place_under_no_grad(conv, bn):
        with torch.no_grad():
            conv.weight.mul_(-0.5)

    def bn_eps(conv, bn):
        bn.eps = 0.5

    def new_storage(conv, bn):
        conv.to(memory_format=CL)
        bn.running_var.data = bn.running_var.data * 4

    return [optimiser_step, load_state, train_step_updates_statistics, in_place_under_no_grad, bn_eps, new_storage]


@pytest.mark.parametrize("change", _changes(), ids=lambda f: f.__name__)
def test_kept_weights_are_rebuilt_when_the_module_changes(change):
    torch.manual_seed(3)
    conv, bn = nn.Conv2d(8, 12, 3, padding=1).eval(), _bn(12)
    x = torch.randn(1, 8, 6, 10).contiguous(memory_format=CL)
    with torch.no_grad():
        before = conv_bn_act(x, conv, bn, "relu")
    change(conv, bn)
    with torch.no_grad():
        after = conv_bn_act(x, conv, bn, "relu")
        ref = F.relu(bn(conv(x)))
    assert not torch.allclose(after, before)
    _close(after, ref)


def test_one_conv_with_another_batchnorm_and_several_input_sizes():
    torch.manual_seed(4)
    conv = nn.Conv2d(8, 12, 3, padding=1).eval()
    bns = (_bn(12, 1), _bn(12, 2))
    with torch.no_grad():
        for hw in [(6, 10), (8, 12), (6, 10), (4, 4), (10, 6), (12, 20), (6, 10)]:   # > MAX_SHAPES sizes
            x = torch.randn(1, 8, *hw).contiguous(memory_format=CL)
            for bn in bns:
                _close(conv_bn_act(x, conv, bn, "relu"), F.relu(bn(conv(x))))
    assert len(inf._CACHE[conv].packed) <= inf.MAX_SHAPES


def test_cache_is_dropped_with_its_layer_and_by_clear_cache():
    import gc
    conv = nn.Conv2d(8, 12, 3, padding=1).eval()
    with torch.no_grad():
        conv_bn_act(torch.randn(1, 8, 6, 10).contiguous(memory_format=CL), conv)
    assert conv in inf._CACHE
    inf.clear_cache()
    assert conv not in inf._CACHE
    with torch.no_grad():
        conv_bn_act(torch.randn(1, 8, 6, 10).contiguous(memory_format=CL), conv)
    n = len(inf._CACHE)
    del conv
    gc.collect()
    assert len(inf._CACHE) == n - 1


def test_weights_are_packed_per_thread_count(monkeypatch):
    """oneDNN chooses the blocked layout for the thread count: a weight packed for 2 threads and used on 1 would
    be re-laid out on every call, so each thread count gets its own packing (same results)."""
    monkeypatch.setattr(winograd, "ENABLED", False)
    conv, bn = nn.Conv2d(8, 12, 3, padding=1).eval(), _bn(12)
    x = torch.randn(1, 8, 6, 10).contiguous(memory_format=CL)
    prev = torch.get_num_threads()
    outs = []
    try:
        with torch.no_grad():
            for n in (2, 1, 2):
                torch.set_num_threads(n)
                outs.append(conv_bn_act(x, conv, bn, "relu"))
    finally:
        torch.set_num_threads(prev)
    assert len(inf._CACHE[conv].packed) == 2
    _close(outs[1], outs[0])
    torch.testing.assert_close(outs[2], outs[0], rtol=0, atol=0)


DENSE = [  # (name, Cin, Cout, act, batch)
    ("expansion with ReLU", 8, 24, "relu", 1),
    ("reduction without activation", 24, 8, None, 1),
    ("channels off the 16-column panels", 5, 19, "relu", 2),
    ("few rows: output channels split between threads", 16, 64, "relu", 1),
]


@pytest.mark.parametrize("name,cin,cout,act,batch", DENSE, ids=[d[0] for d in DENSE])
@pytest.mark.parametrize("threads", [1, 2, 3])
def test_dense_1x1_written_over_the_residual(name, cin, cout, act, batch, threads):
    from omnidl.nn import native
    if native.library() is None:
        pytest.skip("native kernels unavailable (no C compiler)")
    torch.manual_seed(5)
    conv, bn = nn.Conv2d(cin, cout, 1, bias=False).eval(), _bn(cout)
    hw = (2, 3) if "few rows" in name else (7, 9)
    x = torch.randn(batch, cin, *hw).contiguous(memory_format=CL)
    res = torch.randn(batch, cout, *hw).contiguous(memory_format=CL)
    ref = _reference(x, conv, bn, act, res)
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with torch.no_grad():
            buf = res.clone()
            out = conv_bn_act(x, conv, bn, act, buf, into_residual=True)
    finally:
        torch.set_num_threads(prev)
    assert out.data_ptr() == buf.data_ptr()                       # written over the residual, nothing new
    _close(out, ref)


def test_dense_path_keeps_nan_and_is_skipped_where_it_does_not_apply():
    conv = nn.Conv2d(8, 8, 1).eval()
    x = torch.randn(1, 8, 4, 6).contiguous(memory_format=CL)
    x[0, :, 1, 2] = float("nan")
    with torch.no_grad():
        out = conv_bn_act(x, conv, None, "relu", torch.zeros(1, 8, 4, 6).contiguous(memory_format=CL),
                          into_residual=True)
        assert torch.isnan(out[0, :, 1, 2]).all() and not torch.isnan(out[0, :, 0]).any()   # ReLU keeps NaN
        same = x.clone().nan_to_num_()
        res = conv_bn_act(same, conv, None, "relu", same, into_residual=True)  # residual is the input: not in place
        assert res.data_ptr() != same.data_ptr()
        _close(res, F.relu(conv(same) + same))
        nchw = torch.randn(1, 8, 4, 6)
        res = conv_bn_act(nchw, conv, None, None, torch.zeros(1, 8, 4, 6), into_residual=True)
        _close(res, conv(nchw))


def test_a_failing_onednn_op_falls_back_for_good_with_one_warning(monkeypatch):
    """A PyTorch build without these oneDNN ops: the block still gives the modules' result, warns once and the
    packed path stays off; a genuinely bad input still raises the modules' own error."""
    def broken(*args, **kwargs):
        raise RuntimeError("mkldnn::_convolution_pointwise: not available in this build")

    monkeypatch.setattr(inf, "ENABLED", True)
    monkeypatch.setattr(inf, "_pointwise", broken)
    monkeypatch.setattr(winograd, "ENABLED", False)
    conv, bn = nn.Conv2d(8, 12, 3, padding=1).eval(), _bn(12)
    x = torch.randn(1, 8, 6, 10).contiguous(memory_format=CL)
    with torch.no_grad():
        with pytest.warns(RuntimeWarning, match="packed inference convolutions failed .*not available in this build"):
            out = conv_bn_act(x, conv, bn, "relu")
        torch.testing.assert_close(out, F.relu(bn(conv(x))), rtol=0, atol=0)
        assert not inf.ENABLED and not inference_ready(x, conv, bn)
        monkeypatch.setattr(inf, "ENABLED", True)
        with pytest.raises(RuntimeError, match="channels"):
            conv_bn_act(torch.randn(1, 5, 6, 10).contiguous(memory_format=CL), conv, bn, "relu")
        assert inf.ENABLED


@pytest.mark.parametrize("build", ["generic_x86_build", "avx2_build"])
def test_dense_1x1_on_other_builds(build, request):
    """The native dense 1x1 convolution built for plain x86-64 (BLAS) and for AVX2 without AVX-512 (the 6x16
    kernel): same results."""
    from omnidl.nn import native
    request.getfixturevalue(build)
    assert native.status()["kernel"] == {"generic_x86_build": "blas", "avx2_build": "avx2"}[build]
    torch.manual_seed(6)
    conv, bn = nn.Conv2d(12, 40, 1, bias=False).eval(), _bn(40)
    x = torch.randn(2, 12, 5, 7).contiguous(memory_format=CL)
    res = torch.randn(2, 40, 5, 7).contiguous(memory_format=CL)
    ref = _reference(x, conv, bn, "relu", res)
    with torch.no_grad():
        buf = res.clone()
        out = conv_bn_act(x, conv, bn, "relu", buf, into_residual=True)
    assert out.data_ptr() == buf.data_ptr()
    _close(out, ref)
