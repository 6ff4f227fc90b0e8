"""ProjectedConv2d's fused CUDA backend: implicit GEMM over the precomputed bilinear taps (Triton).

:mod:`.grid_conv` writes the gathered columns ``(B, C*K, Ho, Wo)`` with ``grid_sample`` and multiplies them in a
second pass; its backward scatters with atomics. Here (kernels in :mod:`.triton_kernels`):

* forward: one kernel gathers each tile of columns from the plan's corners into registers and multiplies it by the
  weight (``tl.dot``), bias included: no pad of the panorama (the wrap is in the corner indices), no columns in
  memory, one launch;
* input gradient: the columns' gradient ``G (B, P, K, C)`` (one GEMM kernel), then a gather over the plan's
  transpose (sliced ELL, built on the first backward and kept with the plan): no atomics, deterministic;
* weight and bias gradient: columns gathered again and multiplied by the output gradient in row splits, whose
  partial sums one ``sum`` adds (deterministic).

Products follow ``nn.Conv2d``'s precision policy: TF32 where ``torch.backends.cudnn.allow_tf32`` (PyTorch's default)
on CUDA, float32 elsewhere. Float32 only (float64 and the rest run :mod:`.grid_conv`; under autocast the layer
computes in float32, see :class:`~omnidl.nn.ProjectedConv2d`). On CPU tensors the same kernels run in Triton's
interpreter (slow; the tests use it).

Status: correct in Triton's interpreter against ``deform_conv2d`` and built for sm_90 without register spills; not yet
run or timed on a GPU (no GPU was lent when it was written). It is therefore off by default: ``OMNIDL_TRITON=1`` in the environment (or :data:`ENABLED`)
turns it on, and a self-check on first use (:func:`usable`) falls back to :mod:`.grid_conv` with a warning where the
kernels do not compile or give wrong values. The plan of the taps and its transpose: :mod:`.triton_plan`.
"""
from __future__ import annotations

import functools
import importlib.util
import math
import os
import warnings

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from .sampling import _is_channels_last
from .triton_plan import _INT32, TILE_Q, TritonPlan, build_plan

__all__ = ["ENABLED", "TUNE", "TILE_Q", "TritonPlan", "applies", "available", "build_plan", "triton_conv2d", "usable"]

#: whether :func:`applies` may choose this backend: off unless ``OMNIDL_TRITON=1`` is in the environment (or this is
#: set to ``True``) until its speed has been measured on a GPU (``benchmarks/gpu.py`` times it beside :mod:`.grid_conv`)
ENABLED = os.environ.get("OMNIDL_TRITON", "0") == "1"
#: block sizes forced per kernel (``{"fwd": {"BLOCK_P": 64, ...}, ...}``; benchmarks' A/B), else :func:`_config`
TUNE: dict[str, dict] = {}


def available() -> bool:
    """Whether Triton is installed (found, not imported: importing it costs every CPU user start-up time)."""
    return importlib.util.find_spec("triton") is not None


_AVAILABLE = available()


def applies(x: Tensor, weight: Tensor) -> bool:
    """Whether :func:`triton_conv2d` runs for ``x (B, C, H, W)`` and ``weight``: a CUDA float32 input and weight, not
    empty, Triton installed, :data:`ENABLED`, every index within int32, and the kernels passed their self-check on
    this device (:func:`usable`)."""
    if not (ENABLED and _AVAILABLE and x.is_cuda and x.dtype == torch.float32 and weight.dtype == torch.float32):
        return False
    B, C, H, W = x.shape
    fits = 0 < x.numel() < _INT32 and B * H * W * C * weight.shape[2] * weight.shape[3] < _INT32 and \
        weight.numel() * 2 < _INT32
    return fits and usable(x.device)


_USABLE: dict[str, bool] = {}


def usable(device: torch.device) -> bool:
    """Whether the kernels compile and give the right values on ``device``: checked once per device (a small
    convolution, forward and the three gradients, against the same sums in plain torch ops). A failure -- no
    compiler, a Triton too old, a wrong value -- warns once and leaves :class:`~omnidl.nn.ProjectedConv2d` on
    :mod:`.grid_conv` there. Not checked while a CUDA graph is being captured (then ``False`` until checked)."""
    name = str(device)
    hit = _USABLE.get(name)
    if hit is None:
        if device.type == "cuda" and torch.cuda.is_current_stream_capturing():
            return False
        try:
            err = _self_check(device)
            hit = err <= 1e-2
            reason = f"largest relative error {err:.2e}"
        except Exception as e:  # noqa: BLE001 -- any failure means: do not use the kernels here
            hit, reason = False, f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
        if not hit:
            warnings.warn(f"omnidl: the fused Triton kernels of ProjectedConv2d failed their self-check on {name} "
                          f"({reason}); ProjectedConv2d samples with grid_sample there (omnidl.nn.grid_conv)",
                          RuntimeWarning, stacklevel=3)
        _USABLE[name] = hit
    return hit


def _self_check(device: torch.device) -> float:
    """Largest relative error of :func:`triton_conv2d`'s output and gradients on a random plan of 2 x 3 x 6 x 20
    inputs, 5 output channels, 3x3 taps, against a gather-and-einsum of the same taps in float64 (TF32's rounding
    is about 1e-3 of it; :func:`usable` allows 1e-2)."""
    g = torch.Generator().manual_seed(0)
    B, C, N, H, W, K = 2, 3, 5, 6, 20, 9
    P = H * W
    idx = torch.randint(0, H * W, (K, 4, P), generator=g, dtype=torch.int32)
    wt = torch.rand(K, 4, P, generator=g) * (torch.rand(K, 4, P, generator=g) > 0.2)
    plan = TritonPlan(idx.to(device), wt.to(device), (H, W), (H, W), (3, 3))
    x = torch.randn(B, C, H, W, generator=g).to(device).requires_grad_(True)
    w = torch.randn(N, C, 3, 3, generator=g).to(device).requires_grad_(True)
    b = torch.randn(N, generator=g).to(device).requires_grad_(True)
    go = torch.randn(B, N, H, W, generator=g).to(device)
    y = triton_conv2d(x, w, b, plan)            # under the current TF32 policy: the variant the layers will run
    grads = torch.autograd.grad(y, (x, w, b), go)
    xr, wr, br = (t.detach().double().requires_grad_(True) for t in (x, w, b))
    cols = (xr.flatten(2)[:, :, plan.idx.long()] * plan.wt.double()).sum(3)            # (B, C, K, P)
    ref = torch.einsum("bckp,nck->bnp", cols, wr.flatten(2)).view(B, N, H, W) + br.view(1, N, 1, 1)
    refs = torch.autograd.grad(ref, (xr, wr, br), go.double())
    return max(float((a.detach().double() - r.detach()).abs().max() / r.detach().abs().max())
               for a, r in zip((y, *grads), (ref, *refs)))


def _precision(x: Tensor) -> str:
    return "tf32" if x.is_cuda and torch.backends.cudnn.allow_tf32 else "ieee"


def _pow2(n: int, lo: int, hi: int) -> int:
    return max(lo, min(hi, 1 << max(0, math.ceil(math.log2(max(1, n))))))


@functools.lru_cache(maxsize=None)
def _device_sms(device: torch.device) -> int:
    return torch.cuda.get_device_properties(device).multi_processor_count


def _sms(x: Tensor) -> int:
    """Multiprocessors of ``x``'s GPU (4 elsewhere: the interpreter), read once per device."""
    return _device_sms(x.device) if x.is_cuda else 4


def _config(kernel: str, x: Tensor, B: int, P: int, C: int, N: int, K: int) -> dict:
    """Block sizes, warps and pipeline stages of ``kernel`` for this problem (or :data:`TUNE`'s). Chosen so that the
    sm_90 build spills no registers (``tests/nn/test_triton_conv.py`` compiles them with Triton's ``ptxas``): the
    gathered loads are not pipelined (``num_stages=1``), whose prefetch doubled the live registers and spilled."""
    if kernel in TUNE:
        return dict(TUNE[kernel])
    if kernel == "fwd":
        bn = _pow2(N, 16, 128)
        big = B * -(-P // 64) * -(-N // bn) >= 8 * _sms(x)
        return dict(BLOCK_P=128 if big else 64, BLOCK_N=bn, BLOCK_C=16, num_warps=8 if big else 4, num_stages=1)
    if kernel == "gcols":
        return dict(BLOCK_P=64, BLOCK_C=_pow2(C, 16, 64), BLOCK_N=_pow2(N, 16, 32), num_warps=4, num_stages=2)
    if kernel == "sell":
        return dict(BLOCK_C=_pow2(C, 16, 64), num_warps=4)
    return dict(BLOCK_R=32, BLOCK_C=_pow2(C, 16, 64), BLOCK_N=_pow2(N, 16, 64), num_warps=4, num_stages=1)


def _pixels(t: Tensor) -> Tensor:
    """``t (B, C, H, W)`` addressable at flat pixel offsets (``stride(2) == W * stride(3)``), copied if not."""
    return t if t.stride(2) == t.shape[3] * t.stride(3) else t.contiguous()


def _taps_weight(weight: Tensor) -> Tensor:
    """``weight (N, C, kh, kw)`` addressable as ``(N, C, K)`` strides (taps flat), copied if not."""
    return weight if weight.stride(2) == weight.shape[3] * weight.stride(3) else weight.contiguous()


def _kernels(x: Tensor):
    """:mod:`.triton_kernels` (imported on first use). CPU tensors run in Triton's interpreter, which Triton chooses
    when it is imported: ``TRITON_INTERPRET=1`` must be in the environment before that (the tests run such checks in
    a process of their own)."""
    if not x.is_cuda and os.environ.get("TRITON_INTERPRET") != "1":
        raise RuntimeError("triton_conv2d on CPU tensors runs Triton's interpreter: set TRITON_INTERPRET=1 in the "
                           "environment before triton is imported")
    from . import triton_kernels
    return triton_kernels


def _forward(x: Tensor, weight: Tensor, bias: Tensor | None, plan: TritonPlan) -> Tensor:
    B, C, H, W = x.shape
    N = weight.shape[0]
    Ho, Wo = plan.out_hw
    P, K = Ho * Wo, plan.taps
    cl = _is_channels_last(x)
    y = torch.empty(B, N, Ho, Wo, dtype=torch.float32, device=x.device,
                    memory_format=torch.channels_last if cl else torch.contiguous_format)
    cfg = _config("fwd", x, B, P, C, N, K)
    grid = (-(-P // cfg["BLOCK_P"]), -(-N // cfg["BLOCK_N"]), B)
    _kernels(x).fwd[grid](x, weight, bias if bias is not None else weight, plan.idx, plan.wt, y, C, N, P, K,
                          x.stride(0), x.stride(1), x.stride(3), weight.stride(0), weight.stride(1), weight.stride(3),
                          y.stride(0), y.stride(1), y.stride(3), HAS_BIAS=bias is not None, CL=cl,
                          PREC=_precision(x), **cfg)
    return y


def _input_grad(gy: Tensor, weight: Tensor, plan: TritonPlan, x: Tensor) -> Tensor:
    B, C, H, W = x.shape
    N = weight.shape[0]
    P, K = plan.out_hw[0] * plan.out_hw[1], plan.taps
    ker = _kernels(x)
    g = torch.empty(B, P, K, C, dtype=torch.float32, device=x.device)
    cfg = _config("gcols", x, B, P, C, N, K)
    ker.gcols[(-(-P // cfg["BLOCK_P"]), -(-C // cfg["BLOCK_C"]), B * K)](
        gy, weight, g, C, N, P, K, gy.stride(0), gy.stride(1), gy.stride(3), weight.stride(0), weight.stride(1),
        weight.stride(3), PREC=_precision(x), **cfg)
    start, length, rows, vals = plan.transpose()
    gx = torch.empty_like(x, memory_format=torch.channels_last if _is_channels_last(x) else torch.contiguous_format)
    cfg = _config("sell", x, B, P, C, N, K)
    ker.sell[(start.numel(), -(-C // cfg["BLOCK_C"]), B)](
        g, rows, vals, start, length, gx, C, H * W, P * K * C, gx.stride(0), gx.stride(1), gx.stride(3),
        BLOCK_Q=TILE_Q, **cfg)
    return gx


def _weight_grad(x: Tensor, gy: Tensor, weight: Tensor, plan: TritonPlan, has_bias: bool) -> tuple[Tensor, Tensor]:
    B, C, H, W = x.shape
    N, _, kh, kw = weight.shape
    P, K = plan.out_hw[0] * plan.out_hw[1], plan.taps
    cfg = _config("wgrad", x, B, P, C, N, K)
    R, br = B * P, cfg["BLOCK_R"]
    tiles = K * -(-C // cfg["BLOCK_C"]) * -(-N // cfg["BLOCK_N"])
    splits = max(1, min(-(-R // br), -(-2 * _sms(x) // tiles)))
    rows = -(-R // (splits * br)) * br
    splits = -(-R // rows)
    part = torch.empty(splits, N * C * K + N, dtype=torch.float32, device=x.device)
    _kernels(x).wgrad[(K * -(-C // cfg["BLOCK_C"]), -(-N // cfg["BLOCK_N"]), splits)](
        x, plan.idx, plan.wt, gy, part, C, N, P, K, R, rows, -(-C // cfg["BLOCK_C"]), x.stride(0), x.stride(1),
        x.stride(3), gy.stride(0), gy.stride(1), gy.stride(3), HAS_BIAS=has_bias, CL=_is_channels_last(x),
        PREC=_precision(x), **cfg)
    total = part[0] if splits == 1 else part.sum(0)
    return total[:N * C * K].view(N, C, kh, kw), total[N * C * K:]


class _TritonConv(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor | None,  # type: ignore[override]
                plan: TritonPlan) -> Tensor:
        ctx.plan = plan
        ctx.has_bias = bias is not None
        ctx.save_for_backward(x, weight)
        return _forward(x, weight, bias, plan)

    @staticmethod
    @once_differentiable
    def backward(ctx, gy: Tensor):  # type: ignore[override]
        x, weight = ctx.saved_tensors
        gy = _pixels(gy.float())
        need_x, need_w, need_b = ctx.needs_input_grad[:3]
        gx = _input_grad(gy, weight, ctx.plan, x) if need_x else None
        gw = gb = None
        if need_w:
            gw, gb = _weight_grad(x, gy, weight, ctx.plan, ctx.has_bias and need_b)
        elif need_b and ctx.has_bias:
            gb = gy.sum((0, 2, 3))
        return gx, gw, gb if need_b and ctx.has_bias else None, None


def triton_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, plan: TritonPlan) -> Tensor:
    """Convolution of ``x (B, C, H, W)`` with ``weight (Cout, C, kh, kw)`` at the taps of ``plan`` (groups = 1):
    ``(B, Cout, Ho, Wo)``, channels-last where ``x`` is. Differentiable in ``x``, ``weight`` and ``bias`` (once: the
    backward is not itself differentiable, a second derivative raises)."""
    if x.dim() != 4 or tuple(x.shape[-2:]) != tuple(plan.in_hw):
        raise ValueError(f"triton_conv2d: input of shape {tuple(x.shape)} does not fit the plan's {plan.in_hw}")
    if weight.dim() != 4 or weight.shape[1] != x.shape[1] or weight.shape[2] * weight.shape[3] != plan.taps:
        raise ValueError(f"triton_conv2d: weight of shape {tuple(weight.shape)} does not fit {x.shape[1]} input "
                         f"channels and {plan.taps} taps (groups=1 only)")
    if x.dtype != torch.float32 or weight.dtype != torch.float32:
        raise TypeError(f"triton_conv2d computes in float32; got input {x.dtype}, weight {weight.dtype}")
    return _TritonConv.apply(_pixels(x), _taps_weight(weight), None if bias is None else bias.contiguous(), plan)
