"""Batch-1 LSTM inference on the native kernel (``csrc/lstm.c``): each core keeps its share of ``W_hh`` in cache.

:func:`lstm_forward` ``(lstm, x)`` returns what ``lstm(x)`` returns. Where :func:`lstm_supported` (CPU float32,
no gradient to record, batch 1, no ``proj_size``, no dropout to apply, the native library built) each layer's input
part of the gates is one matrix product over the whole sequence (``x W_ih^T + b_ih + b_hh``, both directions at
once) and the recurrence runs in C. At batch 1 a step is a matrix-vector product that reads all of ``W_hh`` (4 MB
at hidden 512), so the layer is bound by how fast the cores read it. The kernel splits each direction's hidden
units across the threads (one barrier per step) and alternates the row order from step to step, so each core
re-reads its own slice mostly from its L2 cache: about 1.2x oneDNN's layer and 2.3x one thread per direction
(HorizonNet's 2-layer BiLSTM, hidden 512, 128 steps, 2 threads; ``benchmarks/public_models.py`` times the whole
network). Elsewhere it calls ``lstm(x)`` -- on CUDA in eval mode with a gradient to record without cuDNN, whose
RNN backward exists in training mode only (an eval-mode backward: saliency maps, test-time optimisation).
"""
from __future__ import annotations

import threading
import weakref

import torch
from torch import Tensor, nn

from . import fused, native
from .capture import capturing


def lstm_supported(lstm: nn.Module, x: Tensor) -> bool:
    """Whether :func:`lstm_forward` runs the native recurrence for ``x``."""
    if type(lstm) is not nn.LSTM or lstm.proj_size or (lstm.training and lstm.dropout and lstm.num_layers > 1):
        return False
    if not (fused.ENABLED and type(x) is torch.Tensor and x.device.type == "cpu" and x.dtype == torch.float32
            and x.dim() == 3 and x.shape[1 if not lstm.batch_first else 0] == 1 and x.shape[-1] == lstm.input_size):
        return False
    if capturing():
        return False
    params = lstm._flat_weights
    if any(p.dtype != torch.float32 or p.device.type != "cpu" for p in params):
        return False
    if _records_grad(lstm, x):
        return False
    return native.library() is not None


def _records_grad(lstm: nn.LSTM, x: Tensor) -> bool:
    """Whether ``lstm(x)`` would record a gradient (of the input or of a weight)."""
    return torch.is_grad_enabled() and (x.requires_grad or any(p.requires_grad for p in lstm._flat_weights))


_LOCK = threading.Lock()
_CACHE: "weakref.WeakKeyDictionary[nn.LSTM, tuple[tuple, list]]" = weakref.WeakKeyDictionary()


def _layer_weights(lstm: nn.LSTM, layer: int) -> tuple[Tensor, Tensor | None, Tensor]:
    """``(W_ih (D*4H, In), b_ih + b_hh (D*4H,) or None, W_hh (D, 4H, n) zero-padded to the kernel's row width)`` of
    one layer, directions stacked."""
    dirs = [""] + (["_reverse"] if lstm.bidirectional else [])
    w_ih = torch.cat([getattr(lstm, f"weight_ih_l{layer}{s}") for s in dirs])
    bias = None
    if lstm.bias:
        bias = torch.cat([getattr(lstm, f"bias_ih_l{layer}{s}") + getattr(lstm, f"bias_hh_l{layer}{s}") for s in dirs])
    H = lstm.hidden_size
    w_hh = torch.zeros(len(dirs), 4 * H, native.library().omnidl_lstm_padded_width(H))
    for d, s in enumerate(dirs):
        w_hh[d, :, :H] = getattr(lstm, f"weight_hh_l{layer}{s}")
    return w_ih, bias, w_hh


def _weights(lstm: nn.LSTM) -> list:
    """:func:`_layer_weights` of every layer, kept until a parameter changes (storage or ``_version``) or the
    library's row width does."""
    key = (native.library().omnidl_lstm_padded_width(lstm.hidden_size),) + tuple(
        (p.data_ptr(), p._version) for p in lstm._flat_weights)                       # the row width is the build's
    with _LOCK:
        hit = _CACHE.get(lstm)
    if hit is None or hit[0] != key:
        with torch.no_grad():
            hit = (key, [_layer_weights(lstm, layer) for layer in range(lstm.num_layers)])
        with _LOCK:
            _CACHE[lstm] = hit
    return hit[1]


def _input_gates(seq: Tensor, w_ih: Tensor, bias: Tensor | None) -> Tensor:
    """``seq W_ih^T + bias``: ``(S, In) -> (S, D*4H)``, on oneDNN's inner product where PyTorch has it (on 2 threads
    about 1.7x ``torch.addmm`` with a transposed weight at 128 x 1024 x 4096)."""
    if torch.backends.mkldnn.is_available() and torch.backends.mkldnn.enabled:
        try:
            return torch.ops.mkldnn._linear_pointwise(seq, w_ih, bias, "none", [], "")
        except (RuntimeError, AttributeError):  # a build without this oneDNN op: the plain product below
            pass
    return torch.addmm(bias, seq, w_ih.t()) if bias is not None else seq @ w_ih.t()


def lstm_forward(lstm: nn.LSTM, x: Tensor, hx: tuple[Tensor, Tensor] | None = None
                 ) -> tuple[Tensor, tuple[Tensor, Tensor]]:
    """``lstm(x, hx)``: ``x (S, 1, In)`` (``(1, S, In)`` with ``batch_first``) -> ``(out (S, 1, D*H), (h_n, c_n)
    (L*D, 1, H) each)``; on the native recurrence where :func:`lstm_supported`, else ``lstm(x, hx)`` itself."""
    if not lstm_supported(lstm, x):
        if x.is_cuda and not lstm.training and _records_grad(lstm, x):
            with torch.backends.cudnn.flags(enabled=False):
                return lstm(x, hx)
        return lstm(x, hx)
    lib = native.library()
    D, H, L = 2 if lstm.bidirectional else 1, lstm.hidden_size, lstm.num_layers
    seq = (x[0] if lstm.batch_first else x[:, 0]).contiguous()                    # (S, In)
    S = seq.shape[0]
    if hx is None:
        h0 = torch.zeros(L * D, H)
        c0 = torch.zeros(L * D, H)
    else:
        h0, c0 = (t.reshape(L * D, H).float().contiguous() for t in hx)
    hn, cn = torch.empty(L * D, H), torch.empty(L * D, H)
    threads = max(1, torch.get_num_threads())
    with torch.no_grad():
        for layer, (w_ih, bias, w_hh) in enumerate(_weights(lstm)):
            gx = _input_gates(seq, w_ih, bias)                                              # (S, D*4H)
            out = torch.empty(S, D * H)
            ptr = [t.data_ptr() for t in (gx, w_hh, h0[layer * D:], c0[layer * D:], out, hn[layer * D:],
                                          cn[layer * D:])]
            err = lib.omnidl_lstm_layer(S, D, H, *ptr, threads)
            if err:
                raise MemoryError("omnidl LSTM kernel: could not allocate its scratch memory")
            seq = out
    y = seq.unsqueeze(0) if lstm.batch_first else seq.unsqueeze(1)
    return y, (hn.unsqueeze(1), cn.unsqueeze(1))
