"""The native inference epilogue act(bn(y)) + residual (omnidl.nn.epilogue) against the modules it replaces, on a
table of layouts and modules, and a table of the cases it must leave to the modules."""
import pytest
import torch
import torch.nn as nn

from omnidl.nn import epilogue, native
from omnidl.nn.prelu import PReLU

pytestmark = pytest.mark.skipif(native.library() is None, reason="needs the native library (a C compiler)")

CL = torch.channels_last


def _bn(C: int) -> nn.BatchNorm2d:
    bn = nn.BatchNorm2d(C).eval()
    with torch.no_grad():
        bn.running_mean.normal_()
        bn.running_var.uniform_(0.5, 2.0)
        bn.weight.normal_()
        bn.bias.normal_()
    return bn


def _prelu(C: int, n: int | None = None) -> PReLU:
    act = PReLU(C if n is None else n)
    with torch.no_grad():
        act.weight.uniform_(-1.0, 1.5)
    return act


def _layout(t: torch.Tensor, fmt) -> torch.Tensor:
    return t.contiguous(memory_format=fmt)


# (name, shape (B, C, H, W), memory format, activation, with BatchNorm, residual: None / "map" / "slice",
#  output: "new" / "slice" / "in place")
APPLIES = [
    ("fourier part, NCHW", (1, 6, 5, 7), torch.contiguous_format, "prelu", True, "slice", "slice"),
    ("fourier part, channels-last", (1, 6, 5, 7), CL, "prelu", True, "slice", "slice"),
    ("global part of a channels-last block", (2, 6, 4, 9), CL, "prelu", True, "slice", "slice"),
    ("W-conv PReLU in place, NCHW", (2, 5, 6, 8), torch.contiguous_format, "prelu", False, None, "in place"),
    ("W-conv PReLU in place, channels-last", (2, 5, 6, 8), CL, "prelu", False, None, "in place"),
    ("one slope for all channels", (1, 4, 3, 5), CL, "prelu1", True, "map", "new"),
    ("ReLU", (1, 4, 3, 5), torch.contiguous_format, "relu", True, "map", "new"),
    ("identity", (1, 4, 3, 5), CL, "identity", True, "map", "new"),
    ("one row", (1, 3, 1, 9), CL, "prelu", True, "map", "new"),
    ("one column", (1, 3, 9, 1), torch.contiguous_format, "prelu", True, "map", "new"),
    ("one channel", (2, 1, 4, 4), CL, "prelu", True, "slice", "slice"),
    ("new map from a channel slice", (1, 6, 4, 4), CL, "prelu", False, "slice", "new"),
]


def _act(kind: str, C: int) -> nn.Module:
    return {"prelu": lambda: _prelu(C), "prelu1": lambda: _prelu(C, 1), "relu": nn.ReLU,
            "identity": nn.Identity}[kind]()


@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("name,shape,fmt,act,with_bn,residual,output", APPLIES, ids=[c[0] for c in APPLIES])
def test_equals_the_modules(name, shape, fmt, act, with_bn, residual, output, threads, monkeypatch):
    """Each case on one thread and split across three (the split walks across batch and plane boundaries)."""
    monkeypatch.setattr(epilogue, "SERIAL_NUMEL", 0)
    kept = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        _check_case(shape, fmt, act, with_bn, residual, output)
    finally:
        torch.set_num_threads(kept)


def _check_case(shape, fmt, act, with_bn, residual, output):
    torch.manual_seed(0)
    B, C, H, W = shape
    act, bn = _act(act, C), (_bn(C) if with_bn else None)
    y = _layout(torch.randn(shape), fmt)
    big = _layout(torch.randn(B, 2 * C + 1, H, W), fmt)
    res = {None: None, "map": _layout(torch.randn(shape), fmt), "slice": big[:, C + 1:]}[residual]
    with torch.no_grad():
        expect = act(bn(y) if bn is not None else y)
        if res is not None:
            expect = expect + res
        holder = _layout(torch.full((B, 2 * C, H, W), float("nan")), fmt)
        out = {"new": None, "slice": holder[:, C:], "in place": y}[output]
        got = epilogue.affine_act(y, act, bn, res, out)
    assert got is not None
    if out is not None:
        assert got is out
    torch.testing.assert_close(got, expect, rtol=1e-5, atol=1e-6)
    if output == "slice":                          # nothing written outside the slice
        assert torch.isnan(holder[:, :C]).all()


def test_nan_propagates_as_in_the_modules():
    act, bn = _prelu(3), _bn(3)
    y = torch.randn(1, 3, 4, 4)
    y[0, 1, 2, 3] = float("nan")
    with torch.no_grad():
        got = epilogue.affine_act(y, act, bn)
        expect = act(bn(y))
    assert torch.equal(torch.isnan(got), torch.isnan(expect))
    torch.testing.assert_close(got.nan_to_num(), expect.nan_to_num())


def _refusal(case: str):
    """(y, act, bn, residual, out) of a case the native pass must leave to the modules."""
    torch.manual_seed(1)
    C = 4
    y, act, bn = torch.randn(1, C, 5, 6), _prelu(C), _bn(C)
    res = torch.randn(1, C, 5, 6)
    if case == "y records a gradient":
        y.requires_grad_()
    elif case == "slope records a gradient":
        pass                                       # (the PReLU weight requires grad; autograd is on in this case)
    elif case == "BatchNorm in training":
        bn.train()
    elif case == "float64":
        y, res, act, bn = y.double(), res.double(), act.double(), bn.double()
    elif case == "layouts differ":
        res = res.contiguous(memory_format=CL)
        y = torch.randn(1, C, 5, 6)
    elif case == "a width slice":
        y = torch.randn(1, C, 5, 8)[..., :6]
    elif case == "BatchNorm of other width":
        bn = _bn(C + 1)
    elif case == "other activation":
        act = nn.GELU()
    elif case == "PReLU subclass with its own forward":
        class Shifted(nn.PReLU):
            def forward(self, x):
                return super().forward(x) + 1.0
        act = Shifted(C)
    elif case == "slope count neither 1 nor C":
        act = _prelu(C, 2)
    elif case == "output overlaps the residual":
        big = torch.randn(1, C + 1, 5, 6)
        return y, act, bn, big[:, :C], big[:, 1:]
    elif case == "switched off":
        pass
    return y, act, bn, res, None


REFUSED = ["y records a gradient", "slope records a gradient", "BatchNorm in training", "float64", "layouts differ",
           "a width slice", "BatchNorm of other width", "other activation", "PReLU subclass with its own forward",
           "slope count neither 1 nor C", "output overlaps the residual", "switched off"]


@pytest.mark.parametrize("case", REFUSED)
def test_leaves_to_the_modules(case, monkeypatch):
    y, act, bn, res, out = _refusal(case)
    if case == "switched off":
        monkeypatch.setattr(epilogue, "ENABLED", False)
    before = None if out is None else out.clone()
    if case in ("y records a gradient", "slope records a gradient"):
        assert epilogue.affine_act(y, act, bn, res, out) is None
        return
    with torch.no_grad():
        assert epilogue.affine_act(y, act, bn, res, out) is None
    if out is not None:
        assert torch.equal(out, before)            # nothing written


@pytest.mark.parametrize("fmt", [torch.contiguous_format, CL])
def test_fredsnet_modules_in_eval_equal_their_modules(fmt, monkeypatch):
    """FreDSNet's Fourier block, its spectral transform and the W-convolution without autograd, with the native
    epilogue and with the modules (float32)."""
    from omnidl.nn.ffc import FourierBlock, SpectralTransform
    from omnidl.nn.wconv import WConv
    torch.manual_seed(2)
    calls = []
    native_pass = epilogue.affine_act
    monkeypatch.setattr(epilogue, "affine_act", lambda *a, **k: calls.append(1) or native_pass(*a, **k))
    for module, x in ((FourierBlock(8), torch.randn(2, 8, 6, 10)), (WConv(8, 12), torch.randn(2, 8, 6, 10)),
                      (SpectralTransform(8, 6), torch.randn(2, 8, 6, 10))):
        for m in module.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.running_mean.normal_()
                m.running_var.uniform_(0.5, 2.0)
            if isinstance(m, nn.PReLU):
                m.weight.data.uniform_(-1.0, 1.0)
        module = module.eval().to(memory_format=fmt)
        x = x.contiguous(memory_format=fmt)
        with torch.no_grad():
            calls.clear()
            got = module(x)
            ran = len(calls)
            monkeypatch.setattr(epilogue, "ENABLED", False)
            expect = module(x)
            monkeypatch.setattr(epilogue, "ENABLED", True)
        assert ran > 0
        torch.testing.assert_close(got, expect, rtol=1e-5, atol=1e-6)


def test_over_output_writes_over_a_new_output_only():
    """over_output: written over y (same storage returned) for a layer's new output; refused where y shares its
    source's memory (a layer that returned its input, or a view of it)."""
    act, bn = _prelu(3), _bn(3)
    x = torch.randn(1, 3, 4, 5)
    y = torch.randn(1, 3, 4, 5)
    with torch.no_grad():
        expect = act(bn(y))
        got = epilogue.over_output(y, x, act, bn)
        assert got is y
        torch.testing.assert_close(y, expect, rtol=1e-5, atol=1e-6)
        kept = x.clone()
        assert epilogue.over_output(x, x, act, bn) is None
        assert epilogue.over_output(x[:, :2], x, _prelu(2)) is None
        assert torch.equal(x, kept)


def test_torch_export_traces_through_the_callers():
    """torch.export traces with tensors that have no data pointer: the callers refuse them before touching memory,
    and the exported program gives the eager outputs."""
    from omnidl.nn.ffc import SpectralTransform
    from omnidl.nn.wconv import WConv
    torch.manual_seed(3)
    for module in (SpectralTransform(8, 6), WConv(8, 12)):
        module = module.eval()
        x = torch.randn(1, 8, 6, 10)
        with torch.no_grad():
            ref = module(x)
        ep = torch.export.export(module, (x,))
        with torch.no_grad():
            torch.testing.assert_close(ep.module()(x), ref, rtol=1e-5, atol=1e-6)
