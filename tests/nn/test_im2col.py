"""omnidl.nn.im2col: F.unfold and its gradient F.fold on a native pass."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from omnidl.nn import im2col, native

from .conftest import native_calls

pytestmark = pytest.mark.skipif(native.library() is None, reason="native library not built")


# (name, map shape (B, C, H, W), kernel, dilation, padding, stride): natively, equal to F.unfold and F.fold
CASES = [
    ("3x3 'same' on 4x8 (a weight-heavy layer)", (1, 64, 4, 8), 3, 1, 1, 1),
    ("3x3 'same', batch 2, ragged", (2, 5, 7, 9), 3, 1, 1, 1),
    ("stride 2", (1, 4, 9, 11), 3, 1, 1, 2),
    ("stride (2, 1), padding (0, 2)", (1, 3, 8, 6), 3, 1, (0, 2), (2, 1)),
    ("dilation 2", (2, 3, 9, 10), 3, 2, 2, 1),
    ("5x3, no padding", (1, 2, 7, 6), (5, 3), 1, 0, 1),
    ("kernel wider than the map", (1, 3, 2, 3), 5, 1, 2, 1),
    ("padding past every tap of a row", (1, 2, 3, 3), 3, 1, 3, 1),
    ("1x1", (1, 6, 4, 5), 1, 1, 0, 1),
    ("as wide, fewer rows (padding (0, 1)): one shifted copy per row", (2, 3, 6, 7), 3, 1, (0, 1), 1),
    ("as wide, rows outside the map (padding (3, 1))", (1, 2, 3, 3), 3, 1, (3, 1), 1),
    ("as wide, dilation 2, batch 2", (2, 3, 6, 9), 3, 2, 2, 1),
]


@pytest.mark.parametrize("name,shape,k,d,p,s", CASES, ids=[c[0] for c in CASES])
def test_unfold_and_gradient_equal_pytorchs(name, shape, k, d, p, s, monkeypatch):
    calls = native_calls(monkeypatch, "omnidl_im2col", "omnidl_col2im")
    g = torch.Generator().manual_seed(shape[1])
    x = torch.randn(shape, generator=g, requires_grad=True)
    cols = im2col.unfold(x, k, d, p, s)
    ref = F.unfold(x, k, dilation=d, padding=p, stride=s)
    torch.testing.assert_close(cols, ref, rtol=0, atol=0)
    gc = torch.randn(ref.shape, generator=g)
    (gx,) = torch.autograd.grad(cols, x, gc)
    (want,) = torch.autograd.grad(ref, x, gc)
    torch.testing.assert_close(gx, want, rtol=1e-6, atol=1e-6)
    assert calls == ["omnidl_im2col", "omnidl_col2im"]


def test_gradient_under_create_graph_is_differentiable():
    x = torch.randn(1, 3, 5, 6, dtype=torch.float32, requires_grad=True)
    cols = im2col.unfold(x, 3, 1, 1, 1)
    (gx,) = torch.autograd.grad((cols ** 2).sum(), x, create_graph=True)
    (ggx,) = torch.autograd.grad(gx.sum(), x)
    xr = x.detach().clone().requires_grad_()
    ref = F.unfold(xr, 3, padding=1)
    (gr,) = torch.autograd.grad((ref ** 2).sum(), xr, create_graph=True)
    (ggr,) = torch.autograd.grad(gr.sum(), xr)
    torch.testing.assert_close(gx, gr)
    torch.testing.assert_close(ggx, ggr)


# (name, how to make the input from a (1, 4, 6, 7) float32 map): F.unfold's own
FALLBACKS = [
    ("float64", lambda x: x.double()),
    ("channels-last", lambda x: x.contiguous(memory_format=torch.channels_last)),
    ("a strided slice", lambda x: x[:, :, :, ::2]),
    ("switched off", lambda x: x),
]


@pytest.mark.parametrize("name,make", FALLBACKS, ids=[c[0] for c in FALLBACKS])
def test_other_inputs_take_f_unfold(name, make, monkeypatch):
    calls = native_calls(monkeypatch, "omnidl_im2col", "omnidl_col2im")
    if name == "switched off":
        monkeypatch.setattr(im2col, "ENABLED", False)
    x = make(torch.randn(1, 4, 6, 7))
    torch.testing.assert_close(im2col.unfold(x, 3, 1, 1, 1), F.unfold(x, 3, padding=1), rtol=0, atol=0)
    assert calls == []


def test_bad_geometry_gives_f_unfolds_error():
    x = torch.randn(1, 2, 3, 3)
    with pytest.raises(RuntimeError):
        im2col.unfold(x, 5, 1, 0, 1)            # the kernel does not fit: no output positions
