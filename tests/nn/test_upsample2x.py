"""omnidl.nn.upsample2x: bilinear up-sampling by 2 plus a weighted skip map, against PyTorch's ops."""
from __future__ import annotations

import re

import pytest
import torch

from omnidl.nn import native, upsample2x

from .conftest import native_calls

pytestmark = pytest.mark.skipif(native.library() is None, reason="native library not built")


# (name, y shape (B, C, h, w), with a skip map): natively, equal to F.interpolate (+ w * skip) with gradients
CASES = [
    ("a decoder block: skip", (1, 8, 8, 16), True),
    ("batch 2, ragged, skip", (2, 3, 5, 7), True),
    ("no skip", (1, 4, 6, 9), False),
    ("one row, one column (both edges clamped)", (2, 2, 1, 1), True),
    ("one row", (1, 3, 1, 6), False),
]


@pytest.mark.parametrize("name,shape,with_skip", CASES, ids=[c[0] for c in CASES])
def test_up2_add_equals_pytorch(name, shape, with_skip, monkeypatch):
    calls = native_calls(monkeypatch, "omnidl_up2_forward", "omnidl_up2_backward")
    g = torch.Generator().manual_seed(shape[1] + shape[3])
    B, C, h, w = shape
    y = torch.randn(shape, generator=g, requires_grad=True)
    skip = torch.randn(B, C, 2 * h, 2 * w, generator=g, requires_grad=True) if with_skip else None
    weight = torch.tensor([0.7], requires_grad=True) if with_skip else None
    out = upsample2x.up2_add(y, skip, weight)
    ref = upsample2x.reference(y, skip, weight)
    torch.testing.assert_close(out, ref, rtol=1e-6, atol=1e-6)
    assert out.is_contiguous()
    gout = torch.randn(ref.shape, generator=g)
    inputs = [t for t in (y, skip, weight) if t is not None]
    for a, b in zip(torch.autograd.grad(out, inputs, gout), torch.autograd.grad(ref, inputs, gout)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    assert calls == ["omnidl_up2_forward", "omnidl_up2_backward"]


def test_without_autograd_one_forward_pass(monkeypatch):
    calls = native_calls(monkeypatch, "omnidl_up2_forward", "omnidl_up2_backward")
    y, skip, weight = torch.randn(1, 2, 3, 4), torch.randn(1, 2, 6, 8), torch.tensor([1.5])
    with torch.no_grad():
        out = upsample2x.up2_add(y, skip, weight)
    torch.testing.assert_close(out, upsample2x.reference(y, skip, weight), rtol=1e-6, atol=1e-6)
    assert calls == ["omnidl_up2_forward"]


def test_second_derivatives_under_create_graph():
    y = torch.randn(1, 2, 3, 4, dtype=torch.float32, requires_grad=True)
    skip = torch.randn(1, 2, 6, 8, requires_grad=True)
    weight = torch.tensor([0.5], requires_grad=True)
    out = []
    for f in (upsample2x.up2_add, upsample2x.reference):
        z = f(y, skip, weight)
        gs, gw = torch.autograd.grad((z ** 2).sum(), (skip, weight), create_graph=True)
        (ggy,) = torch.autograd.grad(gs.sum() + gw.sum(), y)
        out.append((gs.detach(), gw.detach(), ggy))
    for a, b in zip(*out):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


# (name, how to make (y, skip, weight) from float32 ones): PyTorch's ops
FALLBACKS = [
    ("float64", lambda y, s, w: (y.double(), s.double(), w.double())),
    ("channels-last map", lambda y, s, w: (y.contiguous(memory_format=torch.channels_last), s, w)),
    ("skip of another size", lambda y, s, w: (y, s[:, :, :-2], w)),
    ("a weight of two values", lambda y, s, w: (y, s, torch.tensor([0.5, 0.5]))),
    ("switched off", lambda y, s, w: (y, s, w)),
]


@pytest.mark.parametrize("name,make", FALLBACKS, ids=[c[0] for c in FALLBACKS])
def test_other_inputs_take_pytorchs_ops(name, make, monkeypatch):
    calls = native_calls(monkeypatch, "omnidl_up2_forward", "omnidl_up2_backward")
    if name == "switched off":
        monkeypatch.setattr(upsample2x, "ENABLED", False)
    y, skip, weight = make(torch.randn(1, 2, 3, 4), torch.randn(1, 2, 6, 8), torch.tensor([0.5]))
    try:
        want = upsample2x.reference(y, skip, weight)
    except RuntimeError as e:                      # PyTorch's own error, given by up2_add too
        with pytest.raises(RuntimeError, match=re.escape(str(e))):
            upsample2x.up2_add(y, skip, weight)
    else:
        torch.testing.assert_close(upsample2x.up2_add(y, skip, weight), want, rtol=0, atol=0)
    assert calls == []
