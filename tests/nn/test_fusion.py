"""Row-blocked up-sample sums and convolutions (omnidl.nn.fusion) against the literal F.interpolate + conv."""
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

import omnidl.nn.fusion as fusion
from omnidl.nn.fusion import UpsampleSum, blocked_conv, can_block, interpolation_matrix, upsample_sum
from omnidl.nn.padding import CircularConv2d

SIZES = [(2, 4), (4, 8), (8, 16), (16, 32)]


def _maps(channels_last: bool, sizes=SIZES, B=2, C=5):
    ms = [torch.randn(B, C, h, w, dtype=torch.float64) for h, w in sizes]
    if channels_last:
        ms = [m.contiguous(memory_format=torch.channels_last) for m in ms]
    return [m.requires_grad_() for m in ms]


def _literal(ms, ws, size):
    return sum((1.0 if w is None else w) * F.interpolate(m, size=size, mode="bilinear", align_corners=True)
               for m, w in zip(ms, ws))


@pytest.mark.parametrize("n_out,n_in", [(16, 4), (7, 3), (5, 5), (1, 3), (9, 1)])
def test_interpolation_matrix_matches_interpolate(n_out, n_in):
    x = torch.randn(n_in, dtype=torch.float64)
    ref = F.interpolate(x.view(1, 1, n_in), size=n_out, mode="linear", align_corners=True).view(-1)
    torch.testing.assert_close(interpolation_matrix(n_out, n_in, dtype=torch.float64) @ x, ref)


@pytest.mark.parametrize("channels_last", [True, False])
@pytest.mark.parametrize("deferred", [False, True])
def test_upsample_sum_values_and_gradients(channels_last, deferred, monkeypatch):
    if deferred:       # every width pass done per row block
        monkeypatch.setattr(fusion, "BLOCK_BYTES", 1)
    torch.manual_seed(0)
    ms = _maps(channels_last)
    ws = [None, torch.randn(1, dtype=torch.float64, requires_grad=True), 0.5,
          torch.randn((), dtype=torch.float64, requires_grad=True)]
    out, ref = upsample_sum(ms, ws), _literal(ms, ws, (16, 32))
    torch.testing.assert_close(out, ref)
    assert out.is_contiguous(memory_format=torch.channels_last) == channels_last
    g = torch.randn_like(ref)
    params = ms + [ws[1], ws[3]]
    for a, b in zip(torch.autograd.grad((out * g).sum(), params), torch.autograd.grad((ref * g).sum(), params)):
        torch.testing.assert_close(a, b)


def test_rows_and_row_sources():
    torch.manual_seed(1)
    ms = _maps(True)
    full = ms[-1].detach()
    ws = [None, 2.0, None, 0.25]
    s = UpsampleSum(ms[:-1] + [lambda a, b: full[:, :, a:b]], ws, size=(16, 32))
    ref = _literal(ms, ws, (16, 32))
    torch.testing.assert_close(s.full(), ref)
    torch.testing.assert_close(s.rows(3, 11), ref[:, :, 3:11])
    with pytest.raises(ValueError, match="size"):
        UpsampleSum([lambda a, b: full[:, :, a:b]] + ms[:1], [None, None])
    with pytest.raises(ValueError, match="one weight per map"):
        UpsampleSum(ms, [None])
    with pytest.raises(ValueError, match="same B, C"):
        UpsampleSum([ms[0], torch.randn(2, 3, 4, 4)], [None, None])


def test_full_height_narrow_map():
    m = torch.randn(1, 3, 8, 4, dtype=torch.float64)
    torch.testing.assert_close(upsample_sum([m], [None], size=(8, 16)), _literal([m], [None], (8, 16)))


@pytest.mark.parametrize("conv", [CircularConv2d(5, 3, 3, padding=1), CircularConv2d(5, 2, 5, padding=4, dilation=2),
                                  nn.Conv2d(5, 3, 3, padding=1), nn.Conv2d(5, 4, (3, 5), padding=(1, 2))])
@pytest.mark.parametrize("block", [1, 3, 16])
def test_blocked_conv_equals_conv_of_the_whole_map(conv, block):
    torch.manual_seed(2)
    conv = conv.double()
    ms = _maps(True)
    ws = [None, torch.randn(1, dtype=torch.float64, requires_grad=True), None, 1.5]
    ref = conv(_literal(ms, ws, (16, 32)))
    out = blocked_conv(conv, UpsampleSum(ms, ws).rows, 16, block)
    torch.testing.assert_close(out, ref)
    with torch.no_grad():                     # without autograd the wrap comes from thin strips, not a copy
        torch.testing.assert_close(blocked_conv(conv, UpsampleSum(ms, ws).rows, 16, block), ref)
    g = torch.randn_like(ref)
    params = ms + [ws[1], conv.weight, conv.bias]
    for a, b in zip(torch.autograd.grad((out * g).sum(), params), torch.autograd.grad((ref * g).sum(), params)):
        torch.testing.assert_close(a, b)


def test_can_block():
    assert can_block(CircularConv2d(2, 2, 3, padding="same"))
    assert can_block(nn.Conv2d(2, 2, 3, padding=1))
    assert not can_block(nn.Conv2d(2, 2, 3, padding=1, stride=2))
    assert not can_block(nn.Conv2d(2, 2, 3, padding=0))
    assert not can_block(nn.Conv2d(2, 2, 3, padding=1, padding_mode="reflect"))
    with pytest.raises(ValueError, match="same"):
        blocked_conv(nn.Conv2d(2, 2, 3, stride=2), lambda a, b: None, 4, 2)
