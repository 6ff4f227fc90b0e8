"""Row-blocked up-sample sums and convolutions (omnidl.nn.fusion) against the literal F.interpolate + conv; the
native sum and adjoint backward of upsample_sum against F.interpolate and its autograd, on tables of cases."""
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

import omnidl.nn.fusion as fusion
from omnidl.nn.fusion import RowMap, UpsampleSum, blocked_conv, can_block, interpolation_matrix, upsample_sum
from omnidl.nn import native
from omnidl.nn.padding import CircularConv2d, pad_panorama

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


def _row_map(m, reads):
    def rows(a, b):
        assert 0 <= a < b <= m.shape[-2]
        reads.append(b - a)
        return m[:, :, a:b]
    return RowMap(rows, *m.shape[-2:])


# (name, sizes of the maps, which of them are row maps, output size)
ROW_MAPS = [
    ("half-size map", SIZES, (2,), (16, 32)),
    ("every map but the first", SIZES, (1, 2, 3), (16, 32)),
    ("full-height narrow map", [(2, 4), (16, 8)], (1,), (16, 32)),
    ("odd factors", [(3, 5), (7, 11), (13, 29)], (1, 2), (13, 29)),
    ("one-row map", [(2, 4), (1, 9)], (1,), (6, 12)),
]


@pytest.mark.parametrize("channels_last", [True, False])
@pytest.mark.parametrize("name,sizes,as_rows,size", ROW_MAPS, ids=[c[0] for c in ROW_MAPS])
def test_row_maps_of_any_size_equal_the_maps(name, sizes, as_rows, size, channels_last):
    """A map given by its rows (RowMap) sums as the map itself, block by block, reading only rows near the block's
    source rows."""
    torch.manual_seed(3)
    ms = [m.detach() for m in _maps(channels_last, sizes)]
    ws = [None, torch.tensor([0.5], dtype=torch.float64), 2.0][:len(ms) - 1] + [None]
    reads = []
    s = UpsampleSum([_row_map(m, reads) if i in as_rows else m for i, m in enumerate(ms)], ws, size=size)
    ref = _literal(ms, ws, size)
    torch.testing.assert_close(s.full(), ref, rtol=1e-12, atol=1e-12)
    H = size[0]
    for a, b in [(0, 1), (0, H // 2), (H // 3, H - 1), (H - 1, H)]:
        reads.clear()
        torch.testing.assert_close(s.rows(a, b), ref[:, :, a:b], rtol=1e-12, atol=1e-12)
        for i, n in zip(as_rows, reads):        # rows a..b-1 of the output read at most (b - a) * h / H + 2 rows
            assert n <= (b - a) * sizes[i][0] / H + 2


def test_row_map_checks():
    m = torch.randn(1, 2, 4, 4)
    with pytest.raises(ValueError, match="at least 1x1"):
        UpsampleSum([m, RowMap(lambda a, b: m[:, :, a:b], 0, 4)], [None, None], size=(8, 8))
    with pytest.raises(ValueError, match="at least one tensor map"):
        UpsampleSum([RowMap(lambda a, b: m[:, :, a:b], 4, 4)], [None], size=(8, 8))


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


def _w(kind, g):
    return {"none": None, "number": 0.75, "tensor": torch.randn((), generator=g).requires_grad_(),
            "tensor (1,)": torch.randn(1, generator=g).requires_grad_(),
            "frozen tensor": torch.randn((), generator=g)}[kind]


# (name, map sizes, weight kinds, output size, batch, channels, which maps need a gradient, takes the adjoint)
ADJOINT = [
    ("FreDSNet's semantic branch, small", [(2, 4), (4, 8), (8, 16), (16, 32)], ["none", "tensor", "tensor", "tensor"],
     None, 1, 6, "all", True),
    ("numbers and (1,) weights, batch 2", [(3, 5), (7, 9), (13, 17)], ["number", "tensor (1,)", "none"], None, 2, 3,
     "all", True),
    ("one row, one column, odd factors", [(1, 7), (5, 1), (6, 11)], ["tensor", "tensor", "none"], (11, 23), 1, 4,
     "all", True),
    ("only the weights need a gradient", [(4, 8), (8, 16)], ["tensor", "tensor"], None, 1, 3, "none", True),
    ("one map frozen, one weight frozen", [(4, 8), (8, 16)], ["frozen tensor", "tensor"], None, 1, 3, "first",
     True),
    ("float64: autograd's own", [(4, 8), (8, 16)], ["none", "tensor"], None, 1, 3, "all", False),
    ("channels-last: autograd's own", [(4, 8), (8, 16)], ["none", "tensor"], None, 1, 3, "all", False),
]


@pytest.mark.parametrize("name,sizes,kinds,size,B,C,grad,adjoint", ADJOINT, ids=[a[0] for a in ADJOINT])
def test_adjoint_backward_equals_autograd_of_interpolate(name, sizes, kinds, size, B, C, grad, adjoint):
    g = torch.Generator().manual_seed(3)
    dtype = torch.float64 if "float64" in name else torch.float32
    ms = [torch.randn(B, C, h, w, generator=g, dtype=dtype) for h, w in sizes]
    if "channels-last" in name:
        ms = [m.contiguous(memory_format=torch.channels_last) for m in ms]
    for i, m in enumerate(ms):
        m.requires_grad_(grad == "all" or (grad == "first" and i == 0))
    ws = [_w(k, g) for k in kinds]
    ws = [w.to(dtype).detach().requires_grad_(w.requires_grad) if isinstance(w, torch.Tensor) else w for w in ws]
    H, W = size or max(sizes, key=lambda s: s[0] * s[1])
    y = upsample_sum(ms, ws, (H, W))
    ref = _literal(ms, ws, (H, W))
    ran = type(y.grad_fn).__name__ == "_UpsampleSumFunctionBackward"
    assert ran is (adjoint and native.library() is not None)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(y, ref, rtol=0, atol=tol * ref.abs().max().item())
    up = torch.randn(ref.shape, generator=g, dtype=dtype)
    inputs = [t for t in ms + ws if isinstance(t, torch.Tensor) and t.requires_grad]
    exact = [t.detach().double().requires_grad_() for t in inputs]          # float64 twins for the weights
    swap = dict(zip(map(id, inputs), exact))
    ref64 = _literal([swap.get(id(m), m.detach().double()) for m in ms],
                     [swap.get(id(w), w.detach().double() if isinstance(w, torch.Tensor) else w) for w in ws], (H, W))
    for t, a, b, b64 in zip(inputs, torch.autograd.grad(y, inputs, up), torch.autograd.grad(ref, inputs, up),
                            torch.autograd.grad(ref64, exact, up.double())):
        assert a.shape == b.shape
        if t.dim() == 4:
            torch.testing.assert_close(a, b, rtol=0, atol=tol * b.abs().max().item())
        else:   # a weight's gradient is one long dot product with cancellation: as close to float64 as autograd's
            assert (a.double() - b64).abs().max() <= max(2 * (b.double() - b64).abs().max(), tol * b64.abs().max())


def test_adjoint_backward_is_differentiable_again():
    """Under create_graph the adjoint is PyTorch's own (differentiable): second derivatives match the literal sum's."""
    g = torch.Generator().manual_seed(4)
    ms = [torch.randn(1, 2, h, 2 * h, generator=g).requires_grad_() for h in (2, 4, 8)]
    w = torch.tensor(0.7, requires_grad=True)
    up = torch.randn(1, 2, 8, 16, generator=g)
    outs = []
    for fn in (lambda: upsample_sum(ms, [None, w, w * 2], (8, 16)), lambda: _literal(ms, [None, w, w * 2], (8, 16))):
        first = torch.autograd.grad(fn(), ms + [w], up, create_graph=True)
        outs.append(torch.autograd.grad(sum((t * t).sum() for t in first), ms[1:] + [w]))
    for a, b in zip(*outs):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5 * b.abs().max().item())


def test_adjoint_switch_and_eval_take_the_row_blocks(monkeypatch):
    ms = [torch.randn(1, 3, h, 2 * h, requires_grad=True) for h in (4, 8)]
    assert type(upsample_sum(ms, [None, 0.5]).grad_fn).__name__ != "_UpsampleSumFunctionBackward" \
        or native.library() is not None
    monkeypatch.setattr(fusion, "ADJOINT_BACKWARD", False)
    assert type(upsample_sum(ms, [None, 0.5]).grad_fn).__name__ != "_UpsampleSumFunctionBackward"
    monkeypatch.setattr(fusion, "ADJOINT_BACKWARD", True)
    with torch.no_grad():
        assert upsample_sum(ms, [None, 0.5]).grad_fn is None


# (name, map sizes, weight kinds, output size, batch, channels, wrap)
NATIVE_SUM = [
    ("FreDSNet's semantic branch: 1 + 4 maps, wrapped", [(2, 4), (4, 8), (8, 16), (16, 32)],
     ["none", "tensor", "tensor", "tensor"], None, 1, 37, 1),
    ("the same, NCHW", [(2, 4), (4, 8), (8, 16), (16, 32)], ["none", "tensor", "tensor", "tensor"], None, 1, 37, 0),
    ("full-size map not first, batch 2", [(16, 32), (4, 8)], ["number", "tensor (1,)"], None, 2, 16, 2),
    ("one row, one column, odd factors", [(1, 7), (5, 1), (6, 11)], ["tensor", "tensor", "none"], (11, 23), 1, 5, 3),
    ("only a full-size map", [(6, 10)], ["number"], None, 1, 3, 1),
    ("one small map, none of the output's size", [(3, 4)], ["none"], (7, 9), 2, 33, 0),
    ("a wrap of the whole width", [(2, 3), (4, 6)], ["none", "number"], None, 1, 4, 6),
]


@pytest.mark.skipif(native.library() is None, reason="no native library")
@pytest.mark.parametrize("name,sizes,kinds,size,B,C,wrap", NATIVE_SUM, ids=[a[0] for a in NATIVE_SUM])
def test_native_sum_equals_interpolate_with_and_without_autograd(name, sizes, kinds, size, B, C, wrap):
    """The native pass (csrc/upsample.c), NCHW or wrapped channels-last, against F.interpolate + sum (+ the wrap);
    under autograd its backward against autograd's of the literal sum."""
    g = torch.Generator().manual_seed(len(name))
    ms = [torch.randn(B, C, h, w, generator=g) for h, w in sizes]
    ws = [_w(k, g) for k in kinds]
    H, W = size or max(sizes, key=lambda s: s[0] * s[1])
    ref = _literal(ms, ws, (H, W))
    ref = pad_panorama(ref, wrap) if wrap else ref
    with torch.no_grad():
        out = upsample_sum(ms, ws, (H, W), wrap=wrap)
    assert out.shape == ref.shape and out.grad_fn is None
    assert out.is_contiguous(memory_format=torch.channels_last) if wrap else out.is_contiguous()
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-5 * ref.abs().max().item())
    for m in ms:
        m.requires_grad_()
    y = upsample_sum(ms, ws, (H, W), wrap=wrap)
    assert type(y.grad_fn).__name__ == "_UpsampleSumFunctionBackward"
    torch.testing.assert_close(y, out, rtol=0, atol=0)
    ref = _literal(ms, ws, (H, W))
    ref = pad_panorama(ref, wrap) if wrap else ref
    up = torch.randn(ref.shape, generator=g)
    inputs = [t for t in ms + ws if isinstance(t, torch.Tensor) and t.requires_grad]
    for a, b in zip(torch.autograd.grad(y, inputs, up), torch.autograd.grad(ref, inputs, up)):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * b.abs().max().item())


def test_wrapped_sum_without_the_native_pass_and_bad_wraps(monkeypatch):
    g = torch.Generator().manual_seed(9)
    ms = [torch.randn(1, 3, h, 2 * h, generator=g, dtype=torch.float64) for h in (2, 4)]
    ref = pad_panorama(_literal(ms, [None, 0.5], (4, 8)), 2)
    out = upsample_sum(ms, [None, 0.5], wrap=2)                 # float64: the row blocks, then the wrap
    assert out.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)
    monkeypatch.setattr(fusion, "NATIVE_SUM", False)
    ms32 = [m.float() for m in ms]
    torch.testing.assert_close(upsample_sum(ms32, [None, 0.5], wrap=2), ref.float(), rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="wrap must be >= 0"):
        upsample_sum(ms32, [None, 0.5], wrap=-1)


def test_circular_conv_takes_a_sum_written_wrapped():
    """CircularConv2d.channels_last_wrap / conv_wrapped: the thin head's convolution of a map written wrapped in
    channels-last memory equals the module's own call (and the other paths answer 0)."""
    g = torch.Generator().manual_seed(5)
    conv = CircularConv2d(16, 3, 3, padding=1)
    x = torch.randn(1, 16, 64, 128, generator=g, requires_grad=True)
    pw = conv.channels_last_wrap(x)
    assert pw == (1 if native.library() is not None else 0)
    if pw:
        torch.testing.assert_close(conv.conv_wrapped(pad_panorama(x, pw).contiguous(memory_format=torch.channels_last)),
                                   conv(x), rtol=1e-5, atol=1e-5)
    with torch.no_grad():
        assert conv.channels_last_wrap(x) == 0                  # no autograd: the border strips
    assert CircularConv2d(16, 32, 3, padding=1).channels_last_wrap(x) == 0     # 32 outputs: not thin
