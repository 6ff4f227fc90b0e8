"""omnidl.nn.tap_projection: a "same" convolution as a projection onto its taps and a shifted sum."""
from __future__ import annotations

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from omnidl.cameras import Equirectangular
from omnidl.nn import CircularConv2d, ProjectedConv2d
from omnidl.nn import tap_projection as tp

CL = torch.channels_last

# (name, make conv, input shape, channels-last input)
CASES = [
    ("circular 3x3, 1 out", lambda: CircularConv2d(16, 1, 3, padding=1), (1, 16, 6, 9), False),
    ("circular 3x3, 2 out, batch 2", lambda: CircularConv2d(8, 2, 3, padding=1), (2, 8, 5, 7), False),
    ("zeros 3x3", lambda: nn.Conv2d(8, 2, 3, padding=1), (2, 8, 5, 7), False),
    ("zeros 3x3, no bias", lambda: nn.Conv2d(8, 2, 3, padding=1, bias=False), (1, 8, 5, 7), False),
    ("circular 5x3, dilation 2", lambda: CircularConv2d(6, 1, (5, 3), padding=(4, 2), dilation=2), (1, 6, 7, 8), False),
    ("zeros 1x3", lambda: nn.Conv2d(4, 3, (1, 3), padding=(0, 1)), (1, 4, 3, 5), False),
    ("circular 3x3, channels-last", lambda: CircularConv2d(8, 2, 3, padding=1), (2, 8, 5, 7), True),
    ("circular, wider than the map", lambda: CircularConv2d(3, 1, 5, padding=2), (1, 3, 2, 3), False),
    ("zeros, wider than the map", lambda: nn.Conv2d(3, 1, 5, padding=2), (1, 3, 2, 3), False),
]


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)], ids=["f32", "f64"])
@pytest.mark.parametrize("name,make,shape,cl", CASES, ids=[c[0] for c in CASES])
def test_equals_the_convolution_with_gradients(name, make, shape, cl, dtype, tol):
    torch.manual_seed(0)
    conv = make().to(dtype)
    x = torch.randn(shape, dtype=dtype)
    if cl:
        x = x.contiguous(memory_format=CL)
    x.requires_grad_()
    y = tp.shift_sum(conv, tp.project(conv, x))
    ref = conv(x)
    assert y.shape == ref.shape
    torch.testing.assert_close(y, ref, rtol=tol, atol=tol)
    g = torch.randn_like(ref)
    params = [x] + list(conv.parameters())
    for a, b in zip(torch.autograd.grad((y * g).sum(), params), torch.autograd.grad((ref * g).sum(), params)):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)


@pytest.mark.parametrize("wrap", [True, False])
def test_gradcheck(wrap):
    torch.manual_seed(1)
    conv = (CircularConv2d(3, 2, 3, padding=1) if wrap else nn.Conv2d(3, 2, 3, padding=1)).double()
    x = torch.randn(1, 3, 4, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: tp.shift_sum(conv, tp.project(conv, x)), (x,))
    assert torch.autograd.gradgradcheck(lambda x: tp.shift_sum(conv, tp.project(conv, x)), (x,))


def test_projection_commutes_with_upsampling_and_sums():
    """Why the depth branch may project first: P acts on each pixel alone."""
    torch.manual_seed(2)
    conv = CircularConv2d(12, 1, 3, padding=1).double()
    a, b = torch.randn(1, 12, 4, 8, dtype=torch.float64), torch.randn(1, 12, 8, 16, dtype=torch.float64)
    up = lambda m: F.interpolate(m, size=(8, 16), mode="bilinear", align_corners=True)   # noqa: E731
    first = tp.shift_sum(conv, up(tp.project(conv, a)) + 0.3 * tp.project(conv, b))
    torch.testing.assert_close(first, conv(up(a) + 0.3 * b), rtol=1e-12, atol=1e-12)


def test_projection_matrix_rows_are_the_taps():
    w = torch.arange(2 * 3 * 3 * 3, dtype=torch.float64).view(2, 3, 3, 3)
    P = tp.projection_matrix(w)
    assert P.shape == (18, 3)
    torch.testing.assert_close(P[1 * 9 + 2 * 3 + 0], w[1, :, 2, 0])


_CAM = Equirectangular(width=16, height=8)
# (name, conv, tap_offsets is None, pays for its own in_channels)
RULES = [
    ("circular 128 -> 1", CircularConv2d(128, 1, 3, padding=1), False, True),
    ("zeros 128 -> 1", nn.Conv2d(128, 1, 3, padding=1), False, True),
    ("128 -> 7: 63 * 2 <= 128", nn.Conv2d(128, 7, 3, padding=1), False, True),
    ("128 -> 8: 72 * 2 > 128", nn.Conv2d(128, 8, 3, padding=1), False, False),
    ("128 -> 14 (the semantic head)", CircularConv2d(128, 14, 3, padding=1), False, False),
    ("strided", nn.Conv2d(128, 1, 3, stride=2, padding=1), True, False),
    ("grouped", nn.Conv2d(128, 2, 3, padding=1, groups=2), True, False),
    ("not 'same'", nn.Conv2d(128, 1, 3, padding=0), True, False),
    ("padding='same'", nn.Conv2d(128, 1, 3, padding="same"), True, False),
    ("reflect padding mode", nn.Conv2d(128, 1, 3, padding=1, padding_mode="reflect"), True, False),
    ("ProjectedConv2d", ProjectedConv2d(128, 1, 3, camera=_CAM), True, False),
    ("a subclass of nn.Conv2d", type("MyConv", (nn.Conv2d,), {})(128, 1, 3, padding=1), True, False),
]


@pytest.mark.parametrize("name,conv,none,pays", RULES, ids=[r[0] for r in RULES])
def test_rule(name, conv, none, pays):
    assert (tp.tap_offsets(conv) is None) == none
    assert tp.pays(conv) == pays


def test_rule_reads_the_map_channels_and_the_switch(monkeypatch):
    conv = nn.Conv2d(8, 1, 3, padding=1)
    assert not tp.pays(conv) and tp.pays(conv, in_channels=18)
    monkeypatch.setattr(tp, "ENABLED", False)
    assert not tp.pays(nn.Conv2d(128, 1, 3, padding=1))


def test_bad_inputs_name_what_was_expected():
    with pytest.raises(ValueError, match="stride-1 'same'"):
        tp.shift_sum(nn.Conv2d(4, 1, 3, stride=2, padding=1), torch.zeros(1, 9, 4, 4))
    with pytest.raises(ValueError, match="expected 1 x 9 projected channels, got 8"):
        tp.shift_sum(nn.Conv2d(4, 1, 3, padding=1), torch.zeros(1, 8, 4, 4))
