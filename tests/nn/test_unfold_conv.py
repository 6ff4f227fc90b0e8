"""omnidl.nn.unfold_conv: weight-heavy convolutions as one product over the unfolded input.

Outputs and all gradients against ``F.conv2d`` (1e-5 of their scale in float32, 1e-12 in float64, gradcheck
in float64); the weight gradient's kept memory (handed out again only once nothing holds it); the rule's verdict
on a table of shapes; the callers (FFC, CircularConv2d) and the cases that must call ``F.conv2d`` itself."""
from __future__ import annotations

import gc

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

import omnidl.nn.unfold_conv as U
from omnidl.nn.ffc import FFC
from omnidl.nn.padding import CircularConv2d
from omnidl.nn.unfold_conv import conv2d, module_conv2d, unfold_conv2d, weight_heavy

CL = torch.channels_last


def _close(a, b, tol):
    scale = b.abs().max().clamp_min(1e-30)
    torch.testing.assert_close(a / scale, b / scale, rtol=0, atol=tol)


# (name, input shape, weight shape, stride, padding, dilation, bias, channels-last)
CASES = [
    ("3x3 same, bias", (1, 6, 4, 5), (80, 6, 3, 3), 1, 1, 1, True, False),
    ("no bias", (1, 6, 4, 5), (80, 6, 3, 3), 1, 1, 1, False, False),
    ("batch 2", (2, 5, 3, 4), (96, 5, 3, 3), 1, 1, 1, True, False),
    ("batch 2, no bias", (2, 5, 3, 4), (96, 5, 3, 3), 1, 1, 1, False, False),
    ("stride (2, 1), padding (1, 0)", (1, 4, 6, 7), (60, 4, 3, 3), (2, 1), (1, 0), 1, True, False),
    ("dilation 2, rectangular kernel", (1, 3, 6, 7), (168, 3, 3, 2), 1, (2, 1), 2, True, False),
    ("1x1", (1, 7, 2, 3), (25, 7, 1, 1), 1, 0, 1, True, False),
    ("channels-last input and weight", (1, 6, 4, 5), (80, 6, 3, 3), 1, 1, 1, True, True),
    ("channels-last, batch 2", (2, 6, 3, 4), (96, 6, 3, 3), 1, 1, 1, True, True),
]


def _operands(shape, wshape, bias, cl, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(shape, generator=g, dtype=dtype)
    w = torch.randn(wshape, generator=g, dtype=dtype)
    b = torch.randn(wshape[0], generator=g, dtype=dtype) if bias else None
    if cl:
        x, w = x.contiguous(memory_format=CL), w.contiguous(memory_format=CL)
    return [t.requires_grad_() if t is not None else None for t in (x, w, b)]


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)], ids=["f32", "f64"])
@pytest.mark.parametrize("name,shape,wshape,stride,padding,dilation,bias,cl", CASES, ids=[c[0] for c in CASES])
def test_equals_conv2d_with_gradients(name, shape, wshape, stride, padding, dilation, bias, cl, dtype, tol):
    x, w, b = _operands(shape, wshape, bias, cl, dtype)
    assert weight_heavy(x, w, stride, padding, dilation)
    y = unfold_conv2d(x, w, b, stride, padding, dilation)
    ref = F.conv2d(x, w, b, stride, padding, dilation)
    assert y.shape == ref.shape
    assert y.is_contiguous(memory_format=CL if cl else torch.contiguous_format)
    _close(y, ref, tol)
    g = torch.randn_like(ref)
    params = [t for t in (x, w, b) if t is not None]
    for a, r, what in zip(torch.autograd.grad(y, params, g), torch.autograd.grad(ref, params, g), ("x", "w", "b")):
        _close(a, r, tol)


def test_gradcheck_and_second_derivatives():
    x, w, b = _operands((1, 3, 3, 4), (20, 3, 3, 3), True, False, torch.float64, seed=1)
    fn = lambda x, w, b: unfold_conv2d(x, w, b, 1, 1, 1)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (x, w, b))
    assert torch.autograd.gradgradcheck(fn, (x, w, b))



def _weight_grad_ref(x, w, b, g):
    return torch.autograd.grad(F.conv2d(x, w, b, 1, 1), w, g)[0]


@pytest.mark.parametrize("cl", [False, True], ids=["contiguous weight", "channels-last weight"])
@pytest.mark.parametrize("batch", [1, 2])
def test_weight_gradient_memory_is_handed_out_again_only_once_released(cl, batch):
    x, w, b = _operands((batch, 6, 4, 5), (80 * batch, 6, 3, 3), True, cl, torch.float32)
    g1, g2 = torch.randn(batch, 80 * batch, 4, 5), torch.randn(batch, 80 * batch, 4, 5)
    unfold_conv2d(x, w, b, 1, 1).backward(g1)
    first = w.grad
    assert first.stride() == w.stride()          # the weight's own layout: autograd kept it without a copy
    _close(first, _weight_grad_ref(x, w, b, g1), 1e-5)
    kept = first.clone()
    w.grad = None                                # zero_grad(set_to_none=True), but `first` is still held
    unfold_conv2d(x, w, b, 1, 1).backward(g2)
    assert w.grad.data_ptr() != first.data_ptr()
    torch.testing.assert_close(first, kept, rtol=0, atol=0)
    _close(w.grad, _weight_grad_ref(x, w, b, g2), 1e-5)
    ptr = w.grad.data_ptr()
    del first
    w.grad = None                                # now nothing holds it: the same memory again
    unfold_conv2d(x, w, b, 1, 1).backward(g1)
    assert w.grad.data_ptr() == ptr
    _close(w.grad, _weight_grad_ref(x, w, b, g1), 1e-5)


def test_kept_gradients_accumulate_and_zeroed_ones_restart():
    x, w, b = _operands((1, 6, 4, 5), (80, 6, 3, 3), True, False, torch.float32)
    g1, g2 = torch.randn(1, 80, 4, 5), torch.randn(1, 80, 4, 5)
    unfold_conv2d(x, w, b, 1, 1).backward(g1)
    unfold_conv2d(x, w, b, 1, 1).backward(g2)
    _close(w.grad, _weight_grad_ref(x, w, b, g1) + _weight_grad_ref(x, w, b, g2), 1e-5)
    w.grad.zero_()                               # zero_grad(set_to_none=False)
    unfold_conv2d(x, w, b, 1, 1).backward(g2)
    _close(w.grad, _weight_grad_ref(x, w, b, g2), 1e-5)


def test_non_leaf_weights_and_the_switch_use_fresh_memory(monkeypatch):
    x, w, b = _operands((1, 6, 4, 5), (80, 6, 3, 3), True, False, torch.float64)
    g = torch.randn(1, 80, 4, 5, dtype=torch.float64)
    scaled = w * 2.0                             # e.g. a re-parametrised weight: its gradient flows on to w
    unfold_conv2d(x, scaled, b, 1, 1).backward(g)
    _close(w.grad, 2 * _weight_grad_ref(x, w, b, g), 1e-12)
    assert id(scaled) not in U._buffers
    monkeypatch.setattr(U, "REUSE_GRAD_BUFFERS", False)
    w.grad = None
    unfold_conv2d(x, w, b, 1, 1).backward(g)
    _close(w.grad, _weight_grad_ref(x, w, b, g), 1e-12)
    assert id(w) not in U._buffers


def test_the_kept_memory_goes_with_its_weight():
    x, w, b = _operands((1, 6, 4, 5), (80, 6, 3, 3), True, False, torch.float32)
    unfold_conv2d(x, w, b, 1, 1).backward(torch.ones(1, 80, 4, 5))
    key = id(w)
    assert key in U._buffers
    del w
    gc.collect()
    assert key not in U._buffers


# (name, input shape, weight shape, stride, padding, groups, dtype, device, verdict)
RULE = [
    ("FreDSNet Fourier block: 1024 ch on 4x8", (1, 1024, 4, 8), (1024, 1024, 3, 3), 1, 1, 1, "f32", "cpu", True),
    ("out channels = 4x positions", (1, 8, 8, 16), (512, 8, 3, 3), 1, 1, 1, "f32", "cpu", True),
    ("out channels just below 4x positions", (1, 8, 8, 16), (511, 8, 3, 3), 1, 1, 1, "f32", "cpu", False),
    ("batch counts: 2 images of 8x16", (2, 8, 8, 16), (512, 8, 3, 3), 1, 1, 1, "f32", "cpu", False),
    ("stride counts: 8x16 -> 4x8", (1, 8, 8, 16), (128, 8, 3, 3), 2, 1, 1, "f32", "cpu", True),
    ("256 ch on 16x32 (not a small map)", (1, 256, 16, 32), (256, 256, 3, 3), 1, 1, 1, "f32", "cpu", False),
    ("float64", (1, 8, 2, 2), (64, 8, 3, 3), 1, 1, 1, "f64", "cpu", True),
    ("grouped", (1, 8, 2, 2), (64, 4, 3, 3), 1, 1, 2, "f32", "cpu", False),
    ("padding given as a string", (1, 8, 2, 2), (64, 8, 3, 3), 1, "same", 1, "f32", "cpu", False),
    ("float16", (1, 8, 2, 2), (64, 8, 3, 3), 1, 1, 1, "f16", "cpu", False),
    ("CUDA (cuDNN's own)", (1, 8, 2, 2), (64, 8, 3, 3), 1, 1, 1, "f32", "meta", False),
    ("no output positions", (1, 8, 1, 1), (64, 8, 3, 3), 1, 0, 1, "f32", "cpu", False),
]
DTYPES = {"f32": torch.float32, "f64": torch.float64, "f16": torch.float16}


@pytest.mark.parametrize("name,shape,wshape,stride,padding,groups,dtype,device,verdict", RULE,
                         ids=[r[0] for r in RULE])
def test_the_rule(name, shape, wshape, stride, padding, groups, dtype, device, verdict):
    x = torch.empty(shape, dtype=DTYPES[dtype], device=device)
    w = torch.empty(wshape, dtype=DTYPES[dtype], device=device)
    assert weight_heavy(x, w, stride, padding, 1, groups) is verdict


# (name, input shape, weight shape, stride, padding, groups, dtype, grad mode, verdict) of pointwise()
POINTWISE = [
    ("ResNet 1024 -> 256 on 8x16, training", (1, 1024, 8, 16), (256, 1024, 1, 1), 1, 0, 1, "f32", True, True),
    ("2048 positions", (2, 64, 32, 32), (256, 64, 1, 1), 1, 0, 1, "f32", True, True),
    ("2049 positions (not thin)", (1, 64, 1, 2049), (256, 64, 1, 1), 1, 0, 1, "f32", True, False),
    ("a full-resolution thin reduction 16 -> 4", (1, 16, 128, 256), (4, 16, 1, 1), 1, 0, 1, "f32", True, True),
    ("a full-resolution 17 -> 17", (1, 17, 128, 256), (17, 17, 1, 1), 1, 0, 1, "f32", True, False),
    ("float64", (1, 8, 8, 8), (8, 8, 1, 1), 1, 0, 1, "f64", True, True),
    ("inference (no autograd)", (1, 1024, 8, 16), (256, 1024, 1, 1), 1, 0, 1, "f32", False, False),
    ("stride 2", (1, 64, 16, 16), (128, 64, 1, 1), 2, 0, 1, "f32", True, False),
    ("padded", (1, 64, 16, 16), (128, 64, 1, 1), 1, 1, 1, "f32", True, False),
    ("grouped", (1, 64, 16, 16), (128, 32, 1, 1), 1, 0, 2, "f32", True, False),
    ("3x3", (1, 64, 16, 16), (128, 64, 3, 3), 1, 1, 1, "f32", True, False),
    ("float16", (1, 64, 16, 16), (128, 64, 1, 1), 1, 0, 1, "f16", True, False),
]


@pytest.mark.parametrize("name,shape,wshape,stride,padding,groups,dtype,grad,verdict", POINTWISE,
                         ids=[r[0] for r in POINTWISE])
def test_the_pointwise_rule(name, shape, wshape, stride, padding, groups, dtype, grad, verdict, monkeypatch):
    x = torch.empty(shape, dtype=DTYPES[dtype])
    w = torch.empty(wshape, dtype=DTYPES[dtype])
    with torch.set_grad_enabled(grad):
        assert U.pointwise(x, w, stride, padding, groups) is verdict
        monkeypatch.setattr(U, "POINTWISE", False)
        assert U.pointwise(x, w, stride, padding, groups) is False


@pytest.mark.parametrize("shape,wshape", [((1, 256, 8, 16), (64, 256, 1, 1)), ((2, 16, 32, 64), (4, 16, 1, 1))])
def test_pointwise_layers_equal_f_conv2d_with_gradients(shape, wshape):
    x, w, b = _operands(shape, wshape, True, False, torch.float32)
    for t in (x, w, b):
        t.requires_grad_(True)
    y = conv2d(x, w, b)
    up = torch.randn(y.shape, generator=torch.Generator().manual_seed(3))
    grads = torch.autograd.grad(y, (x, w, b), up)
    ref = F.conv2d(x, w, b)
    ref_grads = torch.autograd.grad(ref, (x, w, b), up)
    for a, r in zip((y, *grads), (ref, *ref_grads)):
        _close(a.double(), r.double(), 1e-5)


def test_disabled_and_light_calls_are_f_conv2d_exactly(monkeypatch):
    x, w, b = _operands((1, 6, 4, 5), (80, 6, 3, 3), True, False, torch.float32)
    ref = F.conv2d(x, w, b, 1, 1)
    monkeypatch.setattr(U, "ENABLED", False)
    assert not weight_heavy(x, w, 1, 1)
    torch.testing.assert_close(conv2d(x, w, b, 1, 1), ref, rtol=0, atol=0)
    monkeypatch.setattr(U, "ENABLED", True)
    light = torch.randn(4, 6, 3, 3)
    torch.testing.assert_close(conv2d(x, light, None, 1, 1), F.conv2d(x, light, None, 1, 1), rtol=0, atol=0)


def test_module_conv2d_keeps_hooks_and_other_classes():
    torch.manual_seed(0)
    x = torch.randn(1, 6, 4, 5)
    conv = nn.Conv2d(6, 80, 3, padding=1)
    assert weight_heavy(x, conv.weight, 1, 1)
    _close(module_conv2d(conv, x), conv(x), 1e-5)
    seen = []
    conv.register_forward_hook(lambda m, i, o: seen.append(o.shape))
    module_conv2d(conv, x)
    assert seen == [torch.Size([1, 80, 4, 5])]                         # hooked: called as a module
    reflect = nn.Conv2d(6, 80, 3, padding=1, padding_mode="reflect")
    torch.testing.assert_close(module_conv2d(reflect, x), reflect(x), rtol=0, atol=0)


def test_circular_conv_and_ffc_take_it_with_the_same_results(monkeypatch):
    torch.manual_seed(1)
    circ = CircularConv2d(6, 64, 3, padding=1)
    x = torch.randn(1, 6, 2, 8, requires_grad=True)
    y = circ(x)
    monkeypatch.setattr(U, "ENABLED", False)
    ref = circ(x)
    _close(y, ref, 1e-5)
    _close(torch.autograd.grad(y.sum(), x)[0], torch.autograd.grad(ref.sum(), x)[0], 1e-5)
    monkeypatch.setattr(U, "ENABLED", True)
    ffc = FFC(64, 64, 3, spectral=False)
    xf = torch.randn(1, 64, 2, 4)
    assert weight_heavy(xf[:, :32], ffc.conv_l2l.weight, 1, 1)
    out = ffc(xf)
    monkeypatch.setattr(U, "ENABLED", False)
    for a, b in zip(out, ffc(xf)):
        _close(a, b, 1e-5)


def test_a_channel_slice_of_a_channels_last_map_keeps_the_format():
    """FFC hands its paths channel slices of a channels-last map: the output's format is F.conv2d's."""
    x = torch.randn(1, 16, 3, 4).contiguous(memory_format=CL)[:, :8]
    w = torch.randn(64, 8, 3, 3)
    assert weight_heavy(x, w, 1, 1)
    y, ref = unfold_conv2d(x, w, None, 1, 1), F.conv2d(x, w, None, 1, 1)
    assert y.is_contiguous(memory_format=CL) == ref.is_contiguous(memory_format=CL) is True
    _close(y, ref, 1e-5)


def _native_gemm_counter(monkeypatch):
    """Records ``(kernel, m, n, k)`` of each product a native kernel computed (the register kernel's
    ``omnidl_gemm`` or the few-column ``omnidl_gemm_narrow``); skips where the build has no register kernel."""
    from omnidl.nn import native
    lib = native.library()
    if lib is None or lib.omnidl_fc_kernel() == 0:
        pytest.skip("no native register kernel in this build (the products are PyTorch's)")
    calls = []
    for name in ("omnidl_gemm", "omnidl_gemm_narrow"):
        def counted(*args, real=getattr(lib, name), name=name):
            rc = real(*args)
            if rc == 0:
                calls.append((name, *args[:3]))
            return rc
        monkeypatch.setattr(lib, name, counted)
    return calls


# (name, m, k, n, a transposed, b transposed, out's leading dimension padded, bias, native): the register kernel's
# product against float64, or PyTorch's exactly where it must not run
PRODUCTS = [
    ("forward of 1024 channels on 4x8: one panel, used in place", 1024, 1152, 32, False, False, False, True, True),
    ("input gradient: a weight's transpose", 1152, 96, 32, True, False, False, False, True),
    ("input gradient: 3 blocks of copied rows, 3 chunks of k, ragged", 421, 600, 45, True, False, False, False, True),
    ("input gradient on one panel, read in place: 3 blocks, 3 chunks of k, ragged", 421, 600, 29, True, False, False,
     False, True),
    ("a's transpose against many panels (panels outer)", 200, 300, 2000, True, False, False, False, True),
    ("a's transpose into rows of a wider matrix, bias", 50, 70, 40, True, False, True, True, True),
    ("weight gradient: columns transposed, packed", 96, 32, 1152, False, True, False, False, True),
    ("ragged slivers and panels", 37, 301, 45, False, False, False, True, True),
    ("into rows of a wider matrix", 40, 70, 50, False, True, True, False, True),
    ("one pass over k, written past the caches (non-temporal)", 1024, 32, 4128, False, True, False, False, True),
    ("rows 2 KB apart: copied one sliver at a time (b's chunk in L2), ragged", 37, 512, 45, False, False, False, True,
     True),
    ("rows 4 KB apart, many panels: copied in blocks of slivers, ragged, into a wider matrix", 200, 1024, 2000, False,
     False, True, True, True),
    ("too few rows: PyTorch's", 31, 64, 64, False, False, False, True, False),
    ("too few columns: PyTorch's", 64, 64, 15, True, False, False, False, False),
    ("weight gradient summed over 2047 positions: the register kernel", 64, 2047, 96, False, True, False, False, True),
    ("weight gradient summed over 2048 positions: PyTorch's", 64, 2048, 96, False, True, False, False, False),
]


# (name, m, k, n, a transposed, out's leading dimension padded, bias, a is a weight, the kernel that computes it or
# None for PyTorch's): products on few columns (a small map), where only a weight operand takes a native kernel, the
# few-column one (csrc/narrow_gemm.c), on 1 to 11 columns (unfold_conv.NATIVE_WEIGHT_COLUMNS), a weight's transpose
# on 1 to 24 (NATIVE_WEIGHT_T_COLUMNS)
NARROW = "omnidl_gemm_narrow"
FEW_COLUMNS = [
    ("a weight on 2 columns (a 1x2 map)", 96, 1152, 2, False, False, False, True, NARROW),
    ("a weight on 11 columns, k ragged, bias, into a wider matrix", 37, 601, 11, False, True, True, True, NARROW),
    ("a weight, an odd row count, k shorter than a vector", 33, 7, 5, False, False, True, True, NARROW),
    ("a weight's transpose on 8 columns (a 2x4 map)", 1152, 96, 8, True, False, False, True, NARROW),
    ("a weight's transpose on 11 columns, m ragged", 421, 600, 11, True, False, False, True, NARROW),
    ("a weight's transpose on 3 columns, bias, into a wider matrix", 100, 33, 3, True, True, True, True, NARROW),
    ("a weight on one column", 96, 1152, 1, False, False, False, True, NARROW),
    ("a weight's transpose on one column", 1152, 96, 1, True, False, False, True, NARROW),
    ("a weight's transpose on 12 columns: groups of 11 and 1", 1152, 96, 12, True, False, False, True, NARROW),
    ("a weight's transpose on 24 columns, 3 chunks of k, m ragged, bias, into a wider matrix", 421, 600, 24, True,
     True, True, True, NARROW),
    ("a weight's transpose on 25 columns: the register kernel", 1152, 96, 25, True, False, False, True,
     "omnidl_gemm"),
    ("a weight on 12 columns: PyTorch's", 96, 1152, 12, False, False, False, True, None),
    ("not a weight on 4 columns: PyTorch's", 128, 4096, 4, False, False, False, False, None),
]


@pytest.mark.parametrize("name,m,k,n,at,wide,bias,weight,kernel", FEW_COLUMNS, ids=[p[0] for p in FEW_COLUMNS])
def test_products_on_few_columns(name, m, k, n, at, wide, bias, weight, kernel, monkeypatch):
    # a weight's transpose on the few-column kernel sums each output over all k in one float32 accumulator (600
    # terms: about 1e-6 of the largest output)
    tol = 4e-6 if at and kernel == NARROW else 1e-6
    _check_product(m, k, n, at, False, wide, bias, kernel, monkeypatch, weight=weight, tol=tol)


@pytest.mark.parametrize("name,m,k,n,at,bt,wide,bias,native", PRODUCTS, ids=[p[0] for p in PRODUCTS])
def test_products_on_the_register_kernel(name, m, k, n, at, bt, wide, bias, native, monkeypatch):
    _check_product(m, k, n, at, bt, wide, bias, native, monkeypatch)


def _product_operands(m, k, n, at, bt, wide, bias):
    """``a (m, k)`` (a transpose's view where ``at``), ``b (k, n)`` (likewise ``bt``), ``c`` (rows of a wider
    matrix where ``wide``, else None) and a bias of ``m`` values (or None), seeded by the shape."""
    g = torch.Generator().manual_seed(m + n)
    a = torch.randn(k, m, generator=g).t() if at else torch.randn(m, k, generator=g)
    b = torch.randn(n, k, generator=g).t() if bt else torch.randn(k, n, generator=g)
    c = torch.randn(m, n + 7, generator=g)[:, 3:3 + n] if wide else None
    bb = torch.randn(m, generator=g) if bias else None
    return a, b, c, bb


def _check_product(m, k, n, at, bt, wide, bias, native, monkeypatch, weight=False, tol=1e-6):
    calls = _native_gemm_counter(monkeypatch)
    a, b, c, bb = _product_operands(m, k, n, at, bt, wide, bias)
    with torch.no_grad():                                  # as in autograd's forward and backward
        y = U._product(a, b, out=c, bias=bb, weight=weight)
    assert len(calls) == int(bool(native))
    if isinstance(native, str):
        assert calls[0][0] == native
    if c is not None:
        assert y.data_ptr() == c.data_ptr()
    ref = a.double() @ b.double() + (bb.double().unsqueeze(1) if bias else 0)
    if native:
        _close(y.double(), ref, tol)
    else:
        torch.testing.assert_close(y, a @ b + (bb.unsqueeze(1) if bias else 0), rtol=0, atol=0)


def test_products_under_create_graph_and_the_switch_are_pytorchs(monkeypatch):
    calls = _native_gemm_counter(monkeypatch)
    a, b = torch.randn(64, 64), torch.randn(64, 32)
    with torch.enable_grad():
            U._product(a, b)                               # builds a graph: must stay differentiable
    with torch.no_grad():
        U._product(a.double(), b.double())
        monkeypatch.setattr(U, "NATIVE_PRODUCTS", False)
        U._product(a, b)
    assert calls == []


@pytest.mark.parametrize("size", [(4, 8), (2, 4)])
def test_weight_heavy_layer_runs_every_product_on_a_native_kernel(size, monkeypatch):
    calls = _native_gemm_counter(monkeypatch)
    x, w, b = _operands((1, 64, *size), (512, 64, 3, 3), True, False, torch.float32)
    y = unfold_conv2d(x, w, b, 1, 1)
    y.backward(torch.ones_like(y))
    # forward, input gradient, weight gradient; on the 2x4 map the weight's two products have 8 columns
    narrow = size == (2, 4)
    assert [c[0] for c in calls] == [NARROW if narrow else "omnidl_gemm"] * 2 + ["omnidl_gemm"]
    xr, wr, br = (t.detach().clone().requires_grad_() for t in (x, w, b))
    ref = F.conv2d(xr, wr, br, 1, 1)
    ref.backward(torch.ones_like(ref))
    _close(y, ref, 1e-5)
    for got, want in ((x.grad, xr.grad), (w.grad, wr.grad), (b.grad, br.grad)):
        _close(got, want, 1e-5)


@pytest.mark.parametrize("build", ["generic_x86_build", "avx2_build"])
def test_the_few_column_kernel_of_other_builds(build, request):
    """``omnidl_gemm_narrow`` built without AVX-512 (8 lanes with AVX2, 4 on plain x86-64; one row or vector at a
    time): every case of the few-column table against float64."""
    from omnidl.nn import native
    request.getfixturevalue(build)
    lib = native.library()
    if lib is None:
        pytest.skip("no native library in this build")
    for name, m, k, n, at, wide, bias, weight, kernel in FEW_COLUMNS:
        if kernel != NARROW:
            continue
        a, b, c, bb = _product_operands(m, k, n, at, False, wide, bias)
        c = torch.empty(m, n) if c is None else c
        if bb is not None:
            c.copy_(bb.unsqueeze(1).expand(m, n))
        rc = lib.omnidl_gemm_narrow(m, n, k, a.data_ptr(), a.stride(0), a.stride(1), b.data_ptr(), b.stride(0),
                                    b.stride(1), c.data_ptr(), c.stride(0), int(bias), 2)
        assert rc == 0, name
        # as test_products_on_few_columns; with 8 or 4 lanes a weight's rows are also summed over fewer partial sums
        _close(c.double(), a.double() @ b.double() + (bb.double().unsqueeze(1) if bias else 0), 4e-6)
    a, b, c = torch.randn(64, 64), torch.randn(64, 12), torch.empty(64, 12)
    args = (a.data_ptr(), 64, 1, b.data_ptr(), 12, 1, c.data_ptr(), 12, 0, 2)
    assert lib.omnidl_gemm_narrow(64, 12, 64, *args) == 2          # a weight on 12 columns: another product's
    a, b, c = torch.randn(64, 64), torch.randn(64, 25), torch.empty(64, 25)
    args = (a.data_ptr(), 1, 64, b.data_ptr(), 25, 1, c.data_ptr(), 25, 0, 2)
    assert lib.omnidl_gemm_narrow(64, 25, 64, *args) == 2          # a weight's transpose on 25
    args = (a.data_ptr(), 128, 2, b.data_ptr(), 12, 1, c.data_ptr(), 12, 0, 2)
    assert lib.omnidl_gemm_narrow(32, 4, 32, *args) == 2           # neither a's rows nor its columns contiguous
