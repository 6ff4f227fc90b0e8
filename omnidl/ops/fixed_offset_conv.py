"""``torch.ops.omnidl.fixed_offset_conv2d``: a convolution whose taps sample the input at fixed positions.

For an input ``x (B, C, H, W)``, a weight ``(Cout, C, kh, kw)`` and, per output position ``(i, j)`` of an
``Ho x Wo`` map and tap ``k = a * kw + b``, a position ``positions[i, j, k] = (y, x)`` in input pixels and a weight
``mask[i, j, k]``::

    out[n, o, i, j] = bias[o] + sum_{c, k} weight[o, c, k] * mask[i, j, k] * bilinear(x[n, c], positions[i, j, k])

``bilinear`` reads zero outside the image, as ``torchvision.ops.deform_conv2d`` does; with ``wrap`` a column is
taken modulo ``W`` (a 360-degree image has no left or right border). This is ``deform_conv2d`` with offsets fixed
for the whole batch: the op :class:`omnidl.nn.ProjectedConv2d` runs, its positions coming from a camera model.

Registered with ``torch.library`` (schema, fake kernel, autograd; :func:`torch.library.opcheck` tests it). Kernels,
by device only:

* CPU: the native C kernel (``csrc/fixed_offset_conv.c``: the taps gathered block by block into the cache and
  multiplied there) for float32; other dtypes, and a machine where the kernel cannot be built, the PyTorch
  implementation (:mod:`._fixed_offset_cpu`).
* CUDA: one ``grid_sample`` of every tap and one 1x1 convolution (cuDNN, under ``nn.Conv2d``'s TF32 policy;
  :mod:`._fixed_offset_cuda`).
* any other device: the PyTorch implementation (corner gathers and one product; :mod:`._fixed_offset_torch`).

The backward is a second op, ``omnidl::fixed_offset_conv2d_backward``, whose own autograd is written with the two
ops, so gradients of any order exist (``gradgradcheck`` passes). Under autocast the op computes in float32.
"""
from __future__ import annotations

import torch
from torch import Tensor

from . import _fixed_offset_cpu
from ._fixed_offset_cpu import LIBRARY, native_library, native_status
from ._fixed_offset_cuda import grid_backward, grid_forward
from ._fixed_offset_torch import check_arguments, memory_format, torch_backward, torch_forward

__all__ = ["fixed_offset_conv2d", "fixed_offset_conv2d_backward", "torch_forward", "torch_backward",
           "grid_forward", "grid_backward", "native_library", "native_status", "LIBRARY"]


@torch.library.custom_op("omnidl::fixed_offset_conv2d", mutates_args=())
def fixed_offset_conv2d(input: Tensor, weight: Tensor, bias: Tensor | None, positions: Tensor, mask: Tensor,
                        wrap: bool) -> Tensor:
    """``(B, C, H, W) -> (B, Cout, Ho, Wo)``; see the module docstring (this body: devices without a kernel)."""
    return torch_forward(input, weight, bias, positions, mask, wrap)


@torch.library.custom_op("omnidl::fixed_offset_conv2d_backward", mutates_args=())
def fixed_offset_conv2d_backward(grad: Tensor, input: Tensor, weight: Tensor, positions: Tensor, mask: Tensor,
                                 wrap: bool, input_grad: bool, weight_grad: bool) -> tuple[Tensor, Tensor]:
    """``(grad_input, grad_weight)`` of :func:`fixed_offset_conv2d` for ``grad (B, Cout, Ho, Wo)``; a gradient not
    asked for (``input_grad`` / ``weight_grad`` false) is an empty tensor."""
    return torch_backward(grad, input, weight, positions, mask, wrap, input_grad, weight_grad)


@fixed_offset_conv2d.register_fake
def _forward_fake(input, weight, bias, positions, mask, wrap):
    check_arguments(input, weight, bias, positions, mask)
    B, Ho, Wo = input.shape[0], positions.shape[0], positions.shape[1]
    return input.new_empty(B, weight.shape[0], Ho, Wo).contiguous(memory_format=memory_format(input))


@fixed_offset_conv2d_backward.register_fake
def _backward_fake(grad, input, weight, positions, mask, wrap, input_grad, weight_grad):
    return (torch.empty_like(input, memory_format=memory_format(input)) if input_grad else input.new_empty(0),
            weight.new_empty(weight.shape) if weight_grad else weight.new_empty(0))


def _setup_forward(ctx, inputs, output) -> None:
    input, weight, bias, positions, mask, wrap = inputs
    ctx.save_for_backward(input, weight, positions, mask)
    ctx.wrap, ctx.has_bias = wrap, bias is not None


def _forward_backward(ctx, grad: Tensor):
    input, weight, positions, mask = ctx.saved_tensors
    need_x, need_w, need_b = ctx.needs_input_grad[:3]
    gx = gw = gb = None
    if need_x or need_w:
        gx, gw = fixed_offset_conv2d_backward(grad, input, weight, positions, mask, ctx.wrap, need_x, need_w)
    if need_b and ctx.has_bias:
        gb = grad.sum((0, 2, 3))
    return (gx if need_x else None), (gw if need_w else None), gb, None, None, None


def _setup_backward(ctx, inputs, output) -> None:
    grad, input, weight, positions, mask, wrap, input_grad, weight_grad = inputs
    ctx.save_for_backward(grad, input, weight, positions, mask)
    ctx.wrap, ctx.asked = wrap, (input_grad, weight_grad)


def _backward_backward(ctx, ggx: Tensor, ggw: Tensor):
    """Gradients of the backward: gx = J_x^T g and gw = J_w(x)^T g are bilinear in (g, w) and (g, x), so
    d<ggx, gx>/dg = conv(ggx, w), d<ggx, gx>/dw = weight gradient of conv at ggx for g,
    d<ggw, gw>/dg = conv(x, ggw), d<ggw, gw>/dx = input gradient of conv with weight ggw for g."""
    grad, input, weight, positions, mask = ctx.saved_tensors
    need_g, need_x, need_w = ctx.needs_input_grad[:3]
    ggx = ggx if ctx.asked[0] and ggx is not None and ggx.numel() else None
    ggw = ggw if ctx.asked[1] and ggw is not None and ggw.numel() else None
    dg = dx = dw = None
    if need_g:
        parts = [fixed_offset_conv2d(t, w, None, positions, mask, ctx.wrap)
                 for t, w in ((ggx, weight), (input, ggw)) if t is not None and w is not None]
        dg = sum(parts[1:], parts[0]) if parts else None
    if need_x and ggw is not None:
        dx = fixed_offset_conv2d_backward(grad, input, ggw, positions, mask, ctx.wrap, True, False)[0]
    if need_w and ggx is not None:
        dw = fixed_offset_conv2d_backward(grad, ggx, weight, positions, mask, ctx.wrap, False, True)[1]
    return dg, dx, dw, None, None, None, None, None


fixed_offset_conv2d.register_autograd(_forward_backward, setup_context=_setup_forward)
fixed_offset_conv2d_backward.register_autograd(_backward_backward, setup_context=_setup_backward)
torch.library.register_autocast("omnidl::fixed_offset_conv2d", "cuda", torch.float32)
torch.library.register_autocast("omnidl::fixed_offset_conv2d", "cpu", torch.float32)


fixed_offset_conv2d.register_kernel("cpu")(_fixed_offset_cpu.cpu_forward)
fixed_offset_conv2d_backward.register_kernel("cpu")(_fixed_offset_cpu.cpu_backward)
fixed_offset_conv2d.register_kernel("cuda")(grid_forward)
fixed_offset_conv2d_backward.register_kernel("cuda")(grid_backward)
