"""A convolution's inference epilogue in one native pass: ``out = act(bn(y)) + residual`` (``csrc/prelu.c``).

FreDSNet's Fourier blocks end each part with BatchNorm, PReLU and the residual sum, and its W-convolutions end
with PReLU after the (folded) BatchNorm. Run as modules, each step is a pass over the map that writes a new one:
at 1024x512 the decoder's parts are 16 MB maps, and glibc returns freed memory of that size to the system often
enough that a fresh map page-faults on most calls (a 32 MB map's BatchNorm took 13 ms against 0.9 ms for a 16 MB
one it could reuse, 2 threads). Here the running statistics are folded into a per-channel scale and shift, the
slope applied and the residual added as the map is read once, and the result is written where the caller says: a
channel slice of the block's output, or ``y`` itself.

:func:`affine_act` returns ``None`` where it does not apply, and the caller composes its modules: autograd
recording, tracing or compiling, not CPU float32, a BatchNorm that normalises with batch statistics, an activation
other than ``nn.PReLU`` / ``nn.ReLU`` / ``nn.Identity``, maps whose positions are not evenly spaced, layouts that
differ between the maps, or the native library missing. Results equal the modules' up to float rounding of the
folded statistics (tests: 1e-5 relative).
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from . import native
from .capture import capturing
from .inference import bn_scale_shift, foldable, same_storage
from .prelu import PReLU

#: ``False``: the modules run as they are (benchmarks' in-process A/B)
ENABLED = True
#: maps of fewer elements run on one thread: waking a second one cost about 40 us a call (2 threads; a 1024 x 8 x 16
#: map took 55 us on one thread against 88 us on two, 256 x 32 x 64 225 against 134 us)
SERIAL_NUMEL = 1 << 18

_ACTIVATIONS = {nn.PReLU.forward, PReLU.forward, nn.ReLU.forward, nn.Identity.forward}


def _strides(t: Tensor) -> tuple[int, int, int] | None:
    """``(batch, channel, position)`` strides of a ``(B, C, H, W)`` map whose ``H*W`` positions are evenly spaced
    (contiguous, channels-last, or a channel slice of either), else ``None``."""
    sb, sc, sh, sw = t.stride()
    _, C, H, W = t.shape
    if H > 1 and W > 1 and sh != W * sw:
        return None
    sn = sw if W > 1 else (sh if H > 1 else 1)
    return sb, (1 if C == 1 else sc), sn


def _slopes(act: nn.Module, C: int) -> Tensor | None:
    """Per-channel slopes of the negative side ``(C,)`` float32: PReLU's weight, 0 for ReLU, 1 for identity."""
    if type(act).forward not in _ACTIVATIONS:
        return None
    if isinstance(act, nn.PReLU):
        w = act.weight
        if w.dtype != torch.float32 or w.device.type != "cpu" or w.numel() not in (1, C):
            return None
        return w.detach().reshape(-1).expand(C).contiguous()
    return torch.full((C,), 0.0 if isinstance(act, nn.ReLU) else 1.0)


def _plain(t: Tensor | None, y: Tensor) -> bool:
    return t is None or (type(t) is torch.Tensor and t.shape == y.shape and t.dtype == torch.float32
                         and t.device.type == "cpu")


def _records(*tensors: Tensor | None) -> bool:
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def _aliases(a: Tensor, b: Tensor) -> bool:
    """``a`` and ``b`` share memory other than element for element (the same pointer and strides is allowed)."""
    if not same_storage(a, b):
        return False
    return not (a.data_ptr() == b.data_ptr() and a.stride() == b.stride())


def affine_act(y: Tensor, act: nn.Module, bn: nn.Module | None = None, residual: Tensor | None = None,
               out: Tensor | None = None) -> Tensor | None:
    """``act(bn(y)) + residual`` (``bn``, ``residual`` optional) written into ``out``: ``y``, ``residual``, ``out``
    ``(B, C, H, W)``; ``out`` default a new map in ``y``'s memory format, and may be ``y`` itself (in place) or a
    view of a larger map. Returns ``out``, or ``None`` where the native pass does not apply (see the module
    docstring; nothing is written then)."""
    if not ENABLED or capturing() or y.dim() != 4 or not (_plain(y, y) and _plain(residual, y) and _plain(out, y)):
        return None
    B, C, H, W = y.shape
    if bn is not None and not (foldable(bn) and bn.num_features == C and bn.running_var.dtype == torch.float32):
        return None
    params = [act.weight] if isinstance(act, nn.PReLU) else []
    if bn is not None:
        params += [bn.weight, bn.bias]
    if _records(y, residual, out, *params):
        return None
    if out is not None and (_aliases(out, y) or (residual is not None and _aliases(out, residual))):
        return None
    lib = native.library()
    a = _slopes(act, C)
    if lib is None or a is None or y.numel() == 0:
        return None
    strides = [_strides(t) for t in (y, residual if residual is not None else y)]
    if out is None:
        out = torch.empty_like(y) if strides[0] is not None else None
    strides.append(None if out is None else _strides(out))
    if any(s is None for s in strides):
        return None
    (ysb, ysc, ysn), (rsb, rsc, rsn), (osb, osc, osn) = strides
    if bn is None:
        s, t = torch.ones(C), torch.zeros(C)
    else:
        with torch.no_grad():
            s, t = (v.detach().contiguous() for v in bn_scale_shift(None, bn))
    rc = lib.omnidl_affine_prelu_add(y.data_ptr(), ysb, ysc, ysn, native.ptr(residual),
                                     rsb, rsc, rsn, out.data_ptr(), osb, osc, osn, B, C, H * W, s.data_ptr(),
                                     t.data_ptr(), a.data_ptr(),
                                     1 if y.numel() < SERIAL_NUMEL else max(1, torch.get_num_threads()))
    return None if rc else out


def over_output(y: Tensor, source: Tensor, act: nn.Module, bn: nn.Module | None = None) -> Tensor | None:
    """:func:`affine_act` written over ``y``, a layer's new output computed from ``source`` (no second map); ``None``
    where it does not apply, or where ``y`` shares ``source``'s memory (a layer that returned its input)."""
    if not (ENABLED and type(y) is torch.Tensor and type(source) is torch.Tensor) or capturing():
        return None                           # (before any data pointer: fake tensors of torch.export have none)
    if same_storage(y, source):
        return None
    return affine_act(y, act, bn, out=y)


__all__ = ["affine_act", "over_output"]
