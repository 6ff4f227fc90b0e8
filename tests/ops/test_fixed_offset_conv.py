"""``torch.ops.omnidl.fixed_offset_conv2d``: registrations (opcheck), every kernel against torchvision's
``deform_conv2d`` (the reference), gradients of first and second order, the native kernel's builds, and the
messages a user reads."""
from __future__ import annotations

import pytest
import torch
from torchvision.ops import deform_conv2d

from omnidl.ops import _native
from omnidl.ops import fixed_offset_conv as foc
from omnidl.ops import fixed_offset_conv2d, fixed_offset_conv2d_backward

F64 = torch.float64


def case(B=2, C=5, H=7, W=9, Cout=4, k=(3, 3), stride=1, pad=1, dil=1, scale=1.5, mask="binary", seed=0):
    """Random float64 operands, offsets and mask in deform_conv2d's layout, and the op's positions and mask."""
    g = torch.Generator().manual_seed(seed)
    kh, kw = k
    Ho = (H + 2 * pad - dil * (kh - 1) - 1) // stride + 1
    Wo = (W + 2 * pad - dil * (kw - 1) - 1) // stride + 1
    x = torch.randn(B, C, H, W, generator=g, dtype=F64)
    w = torch.randn(Cout, C, kh, kw, generator=g, dtype=F64)
    b = torch.randn(Cout, generator=g, dtype=F64)
    off = torch.randn(1, 2 * kh * kw, Ho, Wo, generator=g, dtype=F64) * scale
    m = {"binary": (torch.rand(1, kh * kw, Ho, Wo, generator=g) > 0.2).to(F64),
         "soft": torch.rand(1, kh * kw, Ho, Wo, generator=g, dtype=F64),
         "ones": torch.ones(1, kh * kw, Ho, Wo, dtype=F64)}[mask]
    oy = torch.arange(Ho, dtype=F64) * stride - pad
    ox = torch.arange(Wo, dtype=F64) * stride - pad
    ti = (torch.arange(kh, dtype=F64) * dil).repeat_interleave(kw)
    tj = (torch.arange(kw, dtype=F64) * dil).repeat(kh)
    o = off[0].permute(1, 2, 0).reshape(Ho, Wo, kh * kw, 2)
    pos = torch.stack([oy[:, None, None] + ti + o[..., 0], ox[None, :, None] + tj + o[..., 1]], -1)
    ref = dict(stride=stride, padding=pad, dilation=dil)
    return x, w, b, off, m, pos, m[0].permute(1, 2, 0).contiguous(), ref


def reference(x, w, b, off, m, ref):
    B = x.shape[0]
    return deform_conv2d(x, off.expand(B, -1, -1, -1), w, b, mask=m.expand(B, -1, -1, -1), **ref)


CASES = {
    "3x3": {},
    "stride2-dil2": dict(stride=2, dil=2, pad=2, H=11, W=13),
    "1x1": dict(k=(1, 1), pad=0),
    "2x5": dict(k=(2, 5), pad=1),
    "far-outside": dict(scale=6.0),
    "soft-mask": dict(mask="soft"),
    "one-channel": dict(C=1, Cout=1),
    "channel-tails": dict(C=17, Cout=33, H=5, W=6),
    "single-image": dict(B=1),
}
KERNELS = {"torch": foc.torch_forward, "grid": foc.grid_forward}


@pytest.mark.parametrize("name", CASES)
@pytest.mark.parametrize("kernel", KERNELS)
def test_kernels_equal_deform_conv2d_float64(name, kernel):
    x, w, b, off, m, pos, mk, ref = case(**CASES[name])
    y = KERNELS[kernel](x, w, b, pos, mk, False)
    torch.testing.assert_close(y, reference(x, w, b, off, m, ref), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", CASES)
@pytest.mark.parametrize("kernel", ["torch", "grid"])
def test_backward_kernels_equal_deform_conv2d_float64(name, kernel):
    x, w, b, off, m, pos, mk, ref = case(**CASES[name])
    xr, wr = x.clone().requires_grad_(), w.clone().requires_grad_()
    y = reference(xr, wr, b, off, m, ref)
    g = torch.randn_like(y)
    y.backward(g)
    backward = foc.torch_backward if kernel == "torch" else foc.grid_backward
    gx, gw = backward(g, x, w, pos, mk, False, True, True)
    torch.testing.assert_close(gx, xr.grad, rtol=0, atol=1e-12)
    torch.testing.assert_close(gw, wr.grad, rtol=0, atol=1e-11)
    gx_only, empty = backward(g, x, w, pos, mk, False, True, False)
    assert empty.numel() == 0 and torch.equal(gx_only, gx)


@pytest.mark.parametrize("name", CASES)
def test_native_cpu_kernel_in_each_build(name, kernel_build):
    """The C kernel (float32) against the float64 PyTorch implementation: forward and both gradients within
    float32 rounding of the operands' scale, in each build of the kernel."""
    if foc.native_library() is None:
        pytest.skip(f"no native kernel here: {_native.status(foc.LIBRARY)['reason']}")
    x, w, b, off, m, pos, mk, ref = case(**CASES[name])
    for wrap in (False, True):
        y64 = foc.torch_forward(x, w, b, pos, mk, wrap)
        y = fixed_offset_conv2d(x.float(), w.float(), b.float(), pos, mk, wrap)
        assert y.dtype == torch.float32
        torch.testing.assert_close(y.double(), y64, rtol=0, atol=2e-5 * max(1.0, float(y64.abs().max())))
        g = torch.randn_like(y64)
        gx64, gw64 = foc.torch_backward(g, x, w, pos, mk, wrap, True, True)
        gx, gw = fixed_offset_conv2d_backward(g.float(), x.float(), w.float(), pos, mk, wrap, True, True)
        torch.testing.assert_close(gx.double(), gx64, rtol=0, atol=2e-5 * max(1.0, float(gx64.abs().max())))
        torch.testing.assert_close(gw.double(), gw64, rtol=0, atol=2e-5 * max(1.0, float(gw64.abs().max())))
    kind = foc.native_status()["kernel"]
    assert kind == {"x86-64": "blas", "haswell": "avx2"}.get(kernel_build, kind)


def test_wrap_reads_the_other_side():
    """With ``wrap`` a tap at column ``x`` reads column ``x mod W``: shifting every position by ``W`` changes
    nothing, and a panorama rolled by ``s`` columns, sampled at positions shifted by ``s``, gives the same output."""
    x, w, b, _, _, pos, mk, _ = case(scale=4.0, mask="soft")
    shifted = pos.clone()
    shifted[..., 1] += 9 * 3
    for kernel in (foc.torch_forward, foc.grid_forward):
        torch.testing.assert_close(kernel(x, w, b, shifted, mk, True), kernel(x, w, b, pos, mk, True))
    rolled = pos.clone()
    rolled[..., 1] += 2
    torch.testing.assert_close(foc.torch_forward(torch.roll(x, 2, -1), w, b, rolled, mk, True),
                               foc.torch_forward(x, w, b, pos, mk, True))


@pytest.mark.parametrize("kernel", ["torch", "native"])
def test_a_nonfinite_pixel_reaches_only_the_taps_that_sample_it(kernel):
    x, w, b, _, _, pos, mk, _ = case(mask="ones", scale=0.0)
    pos = torch.round(pos)                                     # taps on pixel centres: one corner each
    x[0, :, 3, 4] = float("nan")
    dtype = F64 if kernel == "torch" else torch.float32
    y = fixed_offset_conv2d(x.to(dtype), w.to(dtype), b.to(dtype), pos, mk, False)
    reads = ((pos[..., 0] == 3) & (pos[..., 1] == 4)).any(-1)   # (Ho, Wo): a tap sits on the NaN pixel
    assert torch.isnan(y[0]).any(0).equal(reads)
    assert torch.isfinite(y[1]).all()


def test_gradcheck_and_gradgradcheck():
    x, w, b, _, _, pos, mk, _ = case(B=2, C=2, H=4, W=5, Cout=2, mask="soft")
    args = (x.requires_grad_(), w.requires_grad_(), b.requires_grad_())
    for wrap in (False, True):
        f = lambda x, w, b: fixed_offset_conv2d(x, w, b, pos, mk, wrap)   # noqa: E731
        assert torch.autograd.gradcheck(f, args)
        assert torch.autograd.gradgradcheck(f, args)


def test_fixed_positions_get_no_gradient():
    x, w, b, _, _, pos, mk, _ = case()
    p = pos.clone().requires_grad_()
    y = fixed_offset_conv2d(x, w.requires_grad_(), b, p, mk, False)
    y.sum().backward()
    assert p.grad is None and w.grad is not None


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("bias", [True, False])
def test_opcheck(dtype, bias):
    x, w, b, _, _, pos, mk, _ = case(mask="soft")
    x, w, b = x.to(dtype), w.to(dtype), b.to(dtype)
    for wrap in (False, True):
        torch.library.opcheck(torch.ops.omnidl.fixed_offset_conv2d.default,
                              (x, w.requires_grad_(), b if bias else None, pos, mk, wrap))
        g = torch.randn(2, 4, 7, 9, dtype=dtype)
        for asked in ((True, True), (True, False), (False, True)):
            torch.library.opcheck(torch.ops.omnidl.fixed_offset_conv2d_backward.default,
                                  (g, x.requires_grad_(), w, pos, mk, wrap, *asked))


def test_compiles_whole_with_its_backward():
    torch._dynamo.reset()
    x, w, b, _, _, pos, mk, _ = case()
    x, w = x.float().requires_grad_(), w.float().requires_grad_()

    def step(x, w):
        return fixed_offset_conv2d(x, w, b.float(), pos, mk, True).square().sum()
    compiled = torch.compile(step, fullgraph=True)
    got = torch.autograd.grad(compiled(x, w), (x, w))
    want = torch.autograd.grad(step(x, w), (x, w))
    for a, e in zip(got, want):
        torch.testing.assert_close(a, e)


def test_autocast_computes_in_float32():
    x, w, b, _, _, pos, mk, _ = case()
    x, w, b = x.float(), w.float(), b.float()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = fixed_offset_conv2d(x.bfloat16(), w, b, pos, mk, False)
    assert y.dtype == torch.float32
    torch.testing.assert_close(y, fixed_offset_conv2d(x.bfloat16().float(), w, b, pos, mk, False))


@pytest.mark.parametrize("bad,message", [
    (lambda a: a.update(x=a["x"][0]), r"input must be \(B, C, H, W\)"),
    (lambda a: a.update(w=a["w"][:, :2]), r"weight must be \(Cout, 5, kh, kw\)"),
    (lambda a: a.update(pos=a["pos"][:, :, :4]), r"positions must be \(Ho, Wo, 9, 2\)"),
    (lambda a: a.update(mk=a["mk"][:1]), r"mask must be \(Ho, Wo, K\)"),
    (lambda a: a.update(b=a["b"][:2]), r"bias must be \(4,\)"),
    (lambda a: a.update(w=a["w"].float()), "must share a dtype"),
])
def test_errors_name_the_argument(bad, message):
    x, w, b, _, _, pos, mk, _ = case()
    a = dict(x=x, w=w, b=b, pos=pos, mk=mk)
    bad(a)
    with pytest.raises(ValueError, match=message):
        fixed_offset_conv2d(a["x"], a["w"], a["b"], a["pos"], a["mk"], False)


def test_first_build_is_announced_with_its_duration(monkeypatch, tmp_path, capfd):
    monkeypatch.setenv("OMNIDL_CACHE_DIR", str(tmp_path))
    _native.reset(foc.LIBRARY)
    try:
        if foc.native_library() is None:
            pytest.skip(f"no native kernel here: {_native.status(foc.LIBRARY)['reason']}")
        err = capfd.readouterr().err
        assert "building the native CPU kernel 'fixed_offset_conv'" in err and "built 'fixed_offset_conv' in" in err
        _native.reset(foc.LIBRARY)
        foc.native_library()                                       # cached now: found, not built, silent
        assert "building" not in capfd.readouterr().err
    finally:
        _native.reset(foc.LIBRARY)


def test_without_a_compiler_the_pytorch_kernel_runs_with_one_warning(monkeypatch, tmp_path):
    monkeypatch.setenv("OMNIDL_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    _native.reset(foc.LIBRARY)
    try:
        x, w, b, _, _, pos, mk, _ = case()
        with pytest.warns(RuntimeWarning, match="no C compiler found.*PyTorch implementation"):
            y = fixed_offset_conv2d(x.float(), w.float(), b.float(), pos, mk, False)
        assert foc.native_status()["available"] is False
        torch.testing.assert_close(y.double(), foc.torch_forward(x, w, b, pos, mk, False), rtol=0, atol=1e-5)
    finally:
        _native.reset(foc.LIBRARY)
