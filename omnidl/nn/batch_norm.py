"""Batch norm in training on CPU: forward and backward in native passes per channel (``csrc/batch_norm.c``).

PyTorch's CPU kernel for a training batch norm on a contiguous (NCHW) map is slow next to its eval pass over the
same map: 0.95 against 0.09 ms for 128 channels on 64x128, 0.13 against 0.015 ms for 64 channels on 32x64 (2
threads). A FreDSNet training step at 256x128 runs about 145 of them, most on NCHW maps: 23 ms of its 0.6 s.
:class:`BatchNorm2d` is ``nn.BatchNorm2d`` (same parameters, buffers and state dict) whose training forward, where
:func:`applies`, computes each channel's mean and biased variance over the batch (float64 sums), writes the
normalised map and updates the running statistics as ``nn.BatchNorm2d`` does (``num_batches_tracked``, the
unbiased variance, ``momentum`` or the cumulative average). Its backward, from the saved mean and inverse
standard deviation, is one native pass for the two sums per channel and one for the input's gradient (0.11 against
0.19-1.3 ms for PyTorch's ``native_batch_norm_backward`` at 128 channels on 64x128), that backward for a gradient in
another layout, and autograd's over ``F.batch_norm`` under ``create_graph`` (differentiable again). Everything else
is ``nn.BatchNorm2d``'s forward.

:func:`convert` turns a model's plain ``nn.BatchNorm2d`` modules into this class in place (every registered model
does so when built).
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.graph import increment_version

from . import native
from .capture import capturing

#: ``False``: always ``nn.BatchNorm2d``'s own forward (benchmarks' in-process A/B)
ENABLED = True


def _plain(t: Tensor | None) -> bool:
    """A float32 CPU vector in contiguous memory, or none."""
    return t is None or (t.dtype == torch.float32 and t.device.type == "cpu" and t.is_contiguous())


def applies(bn: nn.BatchNorm2d, x: Tensor) -> bool:
    """Whether :class:`BatchNorm2d`'s forward of ``x`` runs natively: training mode, a contiguous float32 CPU map
    ``(B, C, H, W)`` with ``C = num_features`` and more than one value per channel, contiguous float32 CPU
    parameters and running statistics (or none), the native library built, not captured by
    ``torch.compile``/export."""
    if not (ENABLED and bn.training and x.dim() == 4 and x.dtype == torch.float32 and x.device.type == "cpu"
            and x.is_contiguous() and x.shape[1] == bn.num_features and x.shape[0] * x.shape[2] * x.shape[3] > 1):
        return False
    params, buffers = bn._parameters, bn._buffers
    rm, rv = buffers.get("running_mean"), buffers.get("running_var")
    return (_plain(params.get("weight")) and _plain(params.get("bias")) and _plain(rm) and _plain(rv)
            and (rm is None) == (rv is None) and not capturing() and native.library() is not None)


class BatchNorm2d(nn.BatchNorm2d):
    """``nn.BatchNorm2d`` with the native training forward where :func:`applies` (see the module docstring)."""

    def forward(self, x: Tensor) -> Tensor:
        if not applies(self, x):
            return super().forward(x)
        factor = 0.0 if self.momentum is None else self.momentum
        if self.track_running_stats and self.num_batches_tracked is not None:      # as nn.BatchNorm2d
            self.num_batches_tracked.add_(1)
            if self.momentum is None:
                factor = 1.0 / float(self.num_batches_tracked)
        return _TrainingBatchNorm.apply(x, self.weight, self.bias, self.running_mean, self.running_var, self.eps,
                                        factor)


def convert(module: nn.Module) -> nn.Module:
    """``module`` with every submodule of type ``nn.BatchNorm2d`` (exactly; subclasses keep their own forward) made
    a :class:`BatchNorm2d` in place: the same parameters, buffers, hooks and state dict keys."""
    for m in module.modules():
        if type(m) is nn.BatchNorm2d:
            m.__class__ = BatchNorm2d
    return module


class _TrainingBatchNorm(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor | None, bias: Tensor | None,  # type: ignore[override]
                running_mean: Tensor | None, running_var: Tensor | None, eps: float, factor: float) -> Tensor:
        B, C, H, W = x.shape
        y = torch.empty_like(x, memory_format=torch.contiguous_format)
        mean, invstd = x.new_empty(2, C).unbind()
        rc = native.library().omnidl_bn_train(
            x.data_ptr(), B, C, H * W, native.ptr(weight), native.ptr(bias), float(eps), float(factor),
            native.ptr(running_mean), native.ptr(running_var), y.data_ptr(), mean.data_ptr(), invstd.data_ptr(),
            max(1, torch.get_num_threads()))
        for t in (running_mean, running_var):             # updated in place: their versions move, as PyTorch's
            if t is not None:
                increment_version(t)
        if rc:
            raise RuntimeError(f"omnidl batch norm: the native pass returned {rc} for a map of shape {tuple(x.shape)}")
        ctx.save_for_backward(x, weight, bias, mean, invstd)
        ctx.eps = eps
        return y

    @staticmethod
    def backward(ctx, gy: Tensor):  # type: ignore[override]
        x, weight, bias, mean, invstd = ctx.saved_tensors
        need_x, need_w, need_b = ctx.needs_input_grad[:3]
        if torch.is_grad_enabled():                       # create_graph: a differentiable backward
            with torch.enable_grad():
                inputs = [t for t, need in ((x, need_x), (weight, need_w), (bias, need_b)) if need]
                y = F.batch_norm(x, None, None, weight, bias, True, 0.0, ctx.eps)
                grads = iter(torch.autograd.grad(y, inputs, gy, create_graph=True))
            gx, gw, gb = (next(grads) if need else None for need in (need_x, need_w, need_b))
            return gx, gw, gb, None, None, None, None
        if not gy.is_contiguous():                        # PyTorch's for another layout of the gradient
            gx, gw, gb = torch.ops.aten.native_batch_norm_backward(
                gy, x, weight, None, None, mean, invstd, True, ctx.eps, [need_x, need_w and weight is not None,
                                                                       need_b and bias is not None])
            return (gx if need_x else None, gw if need_w else None, gb if need_b else None, None, None, None, None)
        B, C, H, W = x.shape
        gx = torch.empty_like(x) if need_x else None
        gw = x.new_empty(C) if need_w and weight is not None else None
        gb = x.new_empty(C) if need_b and bias is not None else None
        rc = native.library().omnidl_bn_train_backward(
            x.data_ptr(), gy.data_ptr(), B, C, H * W, native.ptr(weight), mean.data_ptr(), invstd.data_ptr(),
            native.ptr(gx), native.ptr(gw), native.ptr(gb), max(1, torch.get_num_threads()))
        if rc:
            raise RuntimeError(f"omnidl batch norm: the native backward returned {rc} for a map of shape "
                               f"{tuple(x.shape)}")
        return gx, gw, gb, None, None, None, None
