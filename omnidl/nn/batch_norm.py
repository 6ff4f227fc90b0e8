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
does so when built). :func:`with_activation` runs ``act(bn(x))`` for a ReLU or PReLU in the same native passes (FreDSNet's
``ConvNormAct`` and Fourier blocks call it in training): the normalised map is never written, and the backward
recomputes it from ``x``.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.graph import increment_version

from . import native
from .capture import capturing
from .prelu import PReLU

#: ``False``: always ``nn.BatchNorm2d``'s own forward (benchmarks' in-process A/B)
ENABLED = True
#: ``False``: the activation after a batch norm runs as its own module (:func:`with_activation`; in-process A/B)
FUSE_ACTIVATION = True

#: the activations :func:`with_activation` fuses, as ``csrc/batch_norm.c`` numbers them (no activation is 0)
ACTIVATIONS = {nn.Identity: 0, nn.ReLU: 1, nn.PReLU: 2, PReLU: 2}


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
        return _train(self, x, 0, None)


def with_activation(x: Tensor, norm: nn.Module, act: nn.Module) -> Tensor | None:
    """``act(norm(x))`` in the native passes of one batch norm where that applies: ``norm`` a :class:`BatchNorm2d`
    for which :func:`applies`, ``act`` an ``nn.Identity``, ``nn.ReLU`` or PReLU (one float32 slope per channel or one
    for all), neither with hooks, :data:`FUSE_ACTIVATION` on. The output ``(B, C, H, W)`` is then the activation's
    alone: no normalised map is written forward, and the backward recomputes the normalised values from ``x`` (the
    sides of the kink as the forward's, the slope's gradient in float64). ``None`` where it does not apply (the
    caller runs the modules)."""
    code = ACTIVATIONS.get(type(act))
    if not (FUSE_ACTIVATION and code is not None and type(norm) is BatchNorm2d and applies(norm, x)):
        return None
    if any(m._forward_hooks or m._forward_pre_hooks for m in (norm, act)) or nn.modules.module._global_forward_hooks \
            or nn.modules.module._global_forward_pre_hooks:
        return None
    slope = getattr(act, "weight", None) if code == 2 else None
    if slope is not None and not (_plain(slope) and slope.numel() in (1, x.shape[1])):
        return None
    return _train(norm, x, code, slope)


def norm_act(x: Tensor, norm: nn.Module, act: nn.Module) -> Tensor:
    """``act(norm(x))``: :func:`with_activation` where it applies, else the two modules."""
    out = with_activation(x, norm, act)
    return act(norm(x)) if out is None else out


def _train(bn: nn.BatchNorm2d, x: Tensor, code: int, slope: Tensor | None) -> Tensor:
    """The native training forward of ``bn`` (and activation ``code``, ``slope``) where :func:`applies`."""
    factor = 0.0 if bn.momentum is None else bn.momentum
    if bn.track_running_stats and bn.num_batches_tracked is not None:      # as nn.BatchNorm2d
        bn.num_batches_tracked.add_(1)
        if bn.momentum is None:
            factor = 1.0 / float(bn.num_batches_tracked)
    return _TrainingBatchNorm.apply(x, bn.weight, bn.bias, bn.running_mean, bn.running_var, bn.eps, factor, code,
                                    slope)


def convert(module: nn.Module) -> nn.Module:
    """``module`` with every submodule of type ``nn.BatchNorm2d`` (exactly; subclasses keep their own forward) made
    a :class:`BatchNorm2d` in place: the same parameters, buffers, hooks and state dict keys."""
    for m in module.modules():
        if type(m) is nn.BatchNorm2d:
            m.__class__ = BatchNorm2d
    return module


def _activation(y: Tensor, code: int, slope: Tensor | None) -> Tensor:
    """The activation ``code`` of :data:`ACTIVATIONS` applied to ``y`` by PyTorch's ops (differentiable)."""
    if code == 1:
        return F.relu(y)
    return F.prelu(y, slope) if code == 2 else y


class _TrainingBatchNorm(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor | None, bias: Tensor | None,  # type: ignore[override]
                running_mean: Tensor | None, running_var: Tensor | None, eps: float, factor: float, code: int,
                slope: Tensor | None) -> Tensor:
        B, C, H, W = x.shape
        y = torch.empty_like(x, memory_format=torch.contiguous_format)
        mean, invstd = x.new_empty(2, C).unbind()
        affine = x.new_empty(4, C) if code else None
        rc = native.library().omnidl_bn_train(
            x.data_ptr(), B, C, H * W, native.ptr(weight), native.ptr(bias), float(eps), float(factor),
            native.ptr(running_mean), native.ptr(running_var), y.data_ptr(), mean.data_ptr(), invstd.data_ptr(),
            code, native.ptr(slope), int(slope is not None and slope.numel() > 1), native.ptr(affine),
            max(1, torch.get_num_threads()))
        for t in (running_mean, running_var):             # updated in place: their versions move, as PyTorch's
            if t is not None:
                increment_version(t)
        if rc:
            raise RuntimeError(f"omnidl batch norm: the native pass returned {rc} for a map of shape {tuple(x.shape)}")
        ctx.save_for_backward(x, weight, bias, mean, invstd, slope, affine)
        ctx.eps, ctx.code = eps, code
        return y

    @staticmethod
    def backward(ctx, gy: Tensor):  # type: ignore[override]
        x, weight, bias, mean, invstd, slope, affine = ctx.saved_tensors
        need_x, need_w, need_b = ctx.needs_input_grad[:3]
        need_s = ctx.needs_input_grad[8] and slope is not None
        code = ctx.code
        if torch.is_grad_enabled():                       # create_graph: a differentiable backward
            with torch.enable_grad():
                pairs = [(t, need) for t, need in ((x, need_x), (weight, need_w), (bias, need_b), (slope, need_s))]
                y = _activation(F.batch_norm(x, None, None, weight, bias, True, 0.0, ctx.eps), code, slope)
                grads = iter(torch.autograd.grad(y, [t for t, need in pairs if need], gy, create_graph=True))
            gx, gw, gb, gs = (next(grads) if need else None for _, need in pairs)
            return gx, gw, gb, None, None, None, None, None, gs
        if not gy.is_contiguous():
            if not code:                                  # PyTorch's for another layout of the gradient
                gx, gw, gb = torch.ops.aten.native_batch_norm_backward(
                    gy, x, weight, None, None, mean, invstd, True, ctx.eps,
                    [need_x, need_w and weight is not None, need_b and bias is not None])
                return (gx if need_x else None, gw if need_w else None, gb if need_b else None, None, None, None,
                        None, None, None)
            gy = gy.contiguous()
        B, C, H, W = x.shape
        gx = torch.empty_like(x) if need_x else None
        gw = x.new_empty(C) if need_w and weight is not None else None
        gb = x.new_empty(C) if need_b and bias is not None else None
        gs = torch.empty(C, dtype=torch.float64) if need_s else None
        rc = native.library().omnidl_bn_train_backward(
            x.data_ptr(), gy.data_ptr(), B, C, H * W, native.ptr(weight), mean.data_ptr(), invstd.data_ptr(),
            native.ptr(gx), native.ptr(gw), native.ptr(gb), code, native.ptr(slope),
            int(slope is not None and slope.numel() > 1), native.ptr(affine), native.ptr(gs),
            max(1, torch.get_num_threads()))
        if rc:
            raise RuntimeError(f"omnidl batch norm: the native backward returned {rc} for a map of shape "
                               f"{tuple(x.shape)}")
        if gs is not None:
            gs = (gs if slope.numel() > 1 else gs.sum().reshape(1)).to(slope.dtype).view(slope.shape)
        return gx, gw, gb, None, None, None, None, None, gs
