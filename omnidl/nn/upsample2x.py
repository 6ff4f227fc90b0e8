"""Bilinear up-sampling by 2 plus a weighted skip map, in one native pass each way (``csrc/upsample2x.c``).

FreDSNet's decoder blocks compute ``up(y) + w * skip`` (``F.interpolate(y, scale_factor=2.0, mode="bilinear",
align_corners=False)``, ``w`` a learned scalar): as PyTorch ops three passes over the large map forward and three
backward (the up-sampling's adjoint, the skip's gradient ``w g``, the weight's ``sum(g * skip)``). :func:`up2_add`
computes the same in one pass each way for contiguous float32 CPU maps; the up-sampling's weights are PyTorch's
(output row ``2i`` reads rows ``i`` and ``i - 1`` with 3/4 and 1/4, clamped at the edges), the sums in another
order (float32 rounding). Everything else (other dtypes or layouts, ``torch.compile``/export capture, the switch)
and second derivatives (``create_graph``) are PyTorch's own ops.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from . import native
from .capture import capturing

#: ``False``: always PyTorch's ops (benchmarks' in-process A/B)
ENABLED = True


def reference(y: Tensor, skip: Tensor | None = None, weight: Tensor | None = None) -> Tensor:
    """``F.interpolate(y, scale_factor=2.0, mode="bilinear", align_corners=False) (+ weight * skip)``."""
    up = F.interpolate(y, scale_factor=2.0, mode="bilinear", align_corners=False)
    return up if skip is None else up + weight * skip


def applies(y: Tensor, skip: Tensor | None, weight: Tensor | None) -> bool:
    """Whether :func:`up2_add` runs natively: ``y (B, C, h, w)`` and ``skip (B, C, 2h, 2w)`` (or none)
    contiguous float32 CPU maps, ``weight`` a one-value float32 CPU tensor (with a skip), the native library
    built, not captured."""
    if not (ENABLED and y.dim() == 4 and y.dtype == torch.float32 and y.device.type == "cpu" and y.is_contiguous()
            and y.numel() > 0 and not capturing()):
        return False
    if skip is not None:
        B, C, h, w = y.shape
        if not (isinstance(weight, Tensor) and weight.numel() == 1 and weight.dtype == torch.float32
                and weight.device.type == "cpu" and skip.dtype == torch.float32 and skip.device.type == "cpu"
                and skip.is_contiguous() and tuple(skip.shape) == (B, C, 2 * h, 2 * w)):
            return False
    return native.library() is not None


def up2_add(y: Tensor, skip: Tensor | None = None, weight: Tensor | None = None) -> Tensor:
    """:func:`reference`'s value: ``y (B, C, h, w)`` -> ``(B, C, 2h, 2w)`` contiguous; differentiable in ``y``,
    ``skip`` and ``weight``."""
    if not applies(y, skip, weight):
        return reference(y, skip, weight)
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (y, skip, weight)):
        return _Up2Add.apply(y, skip, weight)
    return _forward(y, skip, weight)


def _forward(y: Tensor, skip: Tensor | None, weight: Tensor | None) -> Tensor:
    B, C, h, w = y.shape
    out = y.new_empty(B, C, 2 * h, 2 * w)
    rc = native.library().omnidl_up2_forward(y.data_ptr(), B * C, h, w, native.ptr(skip),
                                              0.0 if weight is None else float(weight), out.data_ptr(),
                                              max(1, torch.get_num_threads()))
    if rc:
        raise MemoryError(f"omnidl up-sampling by 2: could not allocate a scratch row of {w} values")
    return out


class _Up2Add(torch.autograd.Function):
    @staticmethod
    def forward(ctx, y: Tensor, skip: Tensor | None, weight: Tensor | None) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(y, skip, weight)
        return _forward(y, skip, weight)

    @staticmethod
    def backward(ctx, g: Tensor):  # type: ignore[override]
        y, skip, weight = ctx.saved_tensors
        need_y, need_skip, need_w = ctx.needs_input_grad
        if torch.is_grad_enabled():                       # create_graph: a differentiable backward
            with torch.enable_grad():
                inputs = [t for t, need in ((y, need_y), (skip, need_skip), (weight, need_w)) if need]
                grads = iter(torch.autograd.grad(reference(y, skip, weight), inputs, g, create_graph=True))
            return tuple(next(grads) if need else None for need in (need_y, need_skip, need_w))
        B, C, h, w = y.shape
        g = g.contiguous()
        gy = y.new_empty(B, C, h, w) if need_y else None
        gskip = torch.empty_like(g) if need_skip else None
        dots = torch.empty(B * C, dtype=torch.float64) if need_w else None
        rc = native.library().omnidl_up2_backward(
            g.data_ptr(), B * C, h, w, native.ptr(skip),
            0.0 if weight is None else float(weight), native.ptr(gy),
            native.ptr(gskip), native.ptr(dots),
            max(1, torch.get_num_threads()))
        if rc:
            raise MemoryError(f"omnidl up-sampling by 2: could not allocate a scratch row of {w} values")
        gw = dots.sum().to(weight.dtype).reshape(weight.shape) if need_w else None
        return gy, gskip, gw
