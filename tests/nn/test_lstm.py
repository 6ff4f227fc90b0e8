"""omnidl.nn.lstm: the native batch-1 LSTM recurrence against nn.LSTM (1e-5 of the output's scale, float32);
every case it does not take must return nn.LSTM's own result exactly."""
from __future__ import annotations

import pytest
import torch
from torch import nn

import omnidl.nn.lstm as L
from omnidl.nn import fused, native
from omnidl.nn.lstm import lstm_forward, lstm_supported

# (name, nn.LSTM arguments, sequence length, pass an initial state)
CASES = [
    ("HorizonNet-like bidirectional 2 layers", dict(input_size=24, hidden_size=16, num_layers=2, bidirectional=True,
                                                    dropout=0.5), 9, False),
    ("one layer, one direction", dict(input_size=5, hidden_size=8), 7, False),
    ("hidden not a multiple of 8 (padded rows)", dict(input_size=6, hidden_size=13, num_layers=2,
                                                      bidirectional=True), 5, False),
    ("no bias", dict(input_size=6, hidden_size=8, bias=False, bidirectional=True), 5, False),
    ("batch_first", dict(input_size=6, hidden_size=8, batch_first=True, bidirectional=True), 5, False),
    ("initial state", dict(input_size=6, hidden_size=11, num_layers=3, bidirectional=True), 6, True),
    ("one step", dict(input_size=4, hidden_size=8, num_layers=2, bidirectional=True), 1, True),
    ("hidden 512", dict(input_size=32, hidden_size=512, bidirectional=True), 4, False),
    ("hidden 100: units split unevenly, rows off the 4-row passes", dict(input_size=9, hidden_size=100, num_layers=2,
                                                                      bidirectional=True), 7, True),
]


def _close(a, b, tol=1e-5):
    scale = b.abs().max().clamp_min(1e-12)
    torch.testing.assert_close(a / scale, b / scale, rtol=0, atol=tol)


def _inputs(lstm: nn.LSTM, S: int, state: bool, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(S, 1, lstm.input_size, generator=g) * 2
    if lstm.batch_first:
        x = x.transpose(0, 1).contiguous()
    D = 2 if lstm.bidirectional else 1
    hx = None
    if state:
        hx = (torch.randn(lstm.num_layers * D, 1, lstm.hidden_size, generator=g),
              torch.randn(lstm.num_layers * D, 1, lstm.hidden_size, generator=g))
    return x, hx


@pytest.fixture(autouse=True)
def _native():
    if native.library() is None:
        pytest.skip("native kernels unavailable (no C compiler)")


@pytest.mark.parametrize("name,kwargs,S,state", CASES, ids=[c[0] for c in CASES])
@pytest.mark.parametrize("threads", [1, 2, 3])
def test_native_recurrence_equals_nn_lstm(name, kwargs, S, state, threads):
    torch.manual_seed(0)
    lstm = nn.LSTM(**kwargs).eval()
    x, hx = _inputs(lstm, S, state)
    prev = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with torch.no_grad():
            assert lstm_supported(lstm, x)
            out, (h, c) = lstm_forward(lstm, x, hx)
            ref, (hr, cr) = lstm(x, hx)
            again, _ = lstm_forward(lstm, x, hx)                     # kept weights
    finally:
        torch.set_num_threads(prev)
    assert out.shape == ref.shape and h.shape == hr.shape and c.shape == cr.shape
    _close(out, ref)
    _close(h, hr)
    _close(c, cr)
    torch.testing.assert_close(again, out, rtol=0, atol=0)


FALLBACKS = [
    ("training with dropout between layers", lambda m, x: (m.train(), x, torch.no_grad)),
    ("autograd", lambda m, x: (m, x, torch.enable_grad)),
    ("batch 2", lambda m, x: (m, torch.cat([x, x], 1), torch.no_grad)),
    ("float64", lambda m, x: (m.double(), x.double(), torch.no_grad)),
    ("GRU is not an LSTM", lambda m, x: (nn.GRU(6, 8, 2, bidirectional=True).eval(), x, torch.no_grad)),
]


@pytest.mark.parametrize("name,setup", FALLBACKS, ids=[f[0] for f in FALLBACKS])
def test_fallbacks_return_nn_lstm_exactly(name, setup):
    torch.manual_seed(1)
    lstm, x, mode = setup(nn.LSTM(6, 8, 2, bidirectional=True, dropout=0.3).eval(), torch.randn(5, 1, 6))
    with mode():
        assert not lstm_supported(lstm, x)
        torch.manual_seed(2)
        out = lstm_forward(lstm, x)[0]
        torch.manual_seed(2)
        ref = lstm(x)[0]
    torch.testing.assert_close(out, ref, rtol=0, atol=0)


def test_disabled_native_kernels_fall_back(monkeypatch):
    lstm, x = nn.LSTM(6, 8).eval(), torch.randn(5, 1, 6)
    monkeypatch.setattr(fused, "ENABLED", False)
    with torch.no_grad():
        assert not lstm_supported(lstm, x)
        torch.testing.assert_close(lstm_forward(lstm, x)[0], lstm(x)[0], rtol=0, atol=0)


def test_kept_weights_follow_parameter_changes():
    torch.manual_seed(3)
    lstm, x = nn.LSTM(6, 8, 2, bidirectional=True).eval(), torch.randn(5, 1, 6)
    with torch.no_grad():
        before = lstm_forward(lstm, x)[0]
        lstm.weight_hh_l1_reverse.mul_(-1)
        after = lstm_forward(lstm, x)[0]
        _close(after, lstm(x)[0])
        lstm.load_state_dict(nn.LSTM(6, 8, 2, bidirectional=True).state_dict())
        _close(lstm_forward(lstm, x)[0], lstm(x)[0])
    assert not torch.allclose(before, after)


def test_the_build_without_avx2(generic_x86_build):
    """The scalar recurrence of a plain x86-64 build gives the same results."""
    try:
        assert native.status()["kernel"] == "blas"
        lstm = nn.LSTM(6, 13, 2, bidirectional=True).eval()
        x, hx = _inputs(lstm, 6, True)
        with torch.no_grad():
            _close(lstm_forward(lstm, x, hx)[0], lstm(x, hx)[0])
    finally:
        L._CACHE.clear()


def test_the_avx2_build(avx2_build):
    """The AVX2 recurrence (8-float rows; a machine with AVX-512 builds 16-float ones) gives the same results."""
    assert native.status()["kernel"] == "avx2"
    lstm = nn.LSTM(6, 37, 2, bidirectional=True).eval()
    x, hx = _inputs(lstm, 6, True)
    prev = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with torch.no_grad():
            _close(lstm_forward(lstm, x, hx)[0], lstm(x, hx)[0])
    finally:
        torch.set_num_threads(prev)
