"""A thin 1x1 convolution, batch norm with the batch's statistics and an activation, fused for training.

FreDSNet's W-convs end in a 1x1 expansion, batch norm and PReLU (ReLU in the semantic branch); at full resolution
that is 4 -> 128 channels at 128x256, and each of the three ops reads and writes a 16.8 MB map forward and again
backward (on 2 threads about 25 ms per branch and step). With at most :data:`MAX_IN_CHANNELS` input channels the
batch statistics of the expanded map follow from the input's mean ``mu`` and covariance ``S`` (``Cin x Cin``)::

    z_c = w_c . x + b_c          mean_c = w_c . mu + b_c          var_c = w_c^T S w_c      (biased, as batch norm)

so the forward is ``act(k_c (z_c - mean_c) + beta_c)`` with ``k_c = gamma_c / sqrt(var_c + eps)``: one native pass
(``csrc/expansion.c``) that writes the output, the normalisation folded into the weights. The backward needs per
channel the sums of ``e = g act'(pre)`` and of ``e x`` (one pass over the output's gradient ``g``); batch norm's
and the convolution's gradients follow from them in closed form (float64), and the input's gradient, linear in
``e`` and ``x``, is a second pass. No map of the output's size is written backward. The convolution's bias
cancels in batch norm: its gradient is zero. Running statistics are updated as ``nn.BatchNorm2d`` does
(unbiased variance, ``momentum`` or the cumulative average).

:func:`applies` says where it runs (CPU float32 contiguous maps with the native library, a plain 1x1
``nn.Conv2d``, a training ``BatchNorm2d``, PReLU, ReLU or no activation, at least :data:`MIN_PIXELS` pixels in the
batch, no hooks, not captured); everything else, and second derivatives, are the modules' own ops.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from . import batch_norm, native
from .capture import capturing

#: the most input channels taken (the native passes keep the input's pixel chunk in registers and cache)
MAX_IN_CHANNELS = 8
#: the fewest pixels (batch x height x width) taken: below, the float64 statistics cost more than the passes save
MIN_PIXELS = 4096
#: ``False``: always the modules' own ops (benchmarks' in-process A/B)
ENABLED = True


def _act_code(act: nn.Module) -> int | None:
    """0 (none), 1 (ReLU) or 2 (PReLU), as ``csrc/expansion.c`` numbers them (those of batch norm's fused
    activations); ``None`` for another module."""
    return batch_norm.ACTIVATIONS.get(type(act))


def applies(x: Tensor, conv: nn.Module, bn: nn.Module, act: nn.Module) -> bool:
    """Whether :func:`expansion` runs ``act(bn(conv(x)))`` natively (see the module docstring)."""
    if not (ENABLED and type(conv) is nn.Conv2d and type(bn) in (nn.BatchNorm2d, batch_norm.BatchNorm2d)
            and bn.training):
        return False
    if not (conv.kernel_size == (1, 1) and conv.stride == (1, 1) and conv.padding == (0, 0)
            and conv.groups == 1 and conv.padding_mode == "zeros" and conv.in_channels <= MAX_IN_CHANNELS):
        return False
    if _act_code(act) is None or any(m._forward_hooks or m._forward_pre_hooks for m in (conv, bn, act)):
        return False
    if not (x.dim() == 4 and x.device.type == "cpu" and x.dtype == torch.float32 and x.is_contiguous()
            and x.shape[0] * x.shape[2] * x.shape[3] >= MIN_PIXELS):
        return False
    params = [conv.weight, conv.bias, bn.weight, bn.bias, getattr(act, "weight", None)]
    if any(p is not None and (p.dtype != torch.float32 or p.device.type != "cpu") for p in params):
        return False
    return not capturing() and native.library() is not None


def expansion(x: Tensor, conv: nn.Conv2d, bn: nn.BatchNorm2d, act: nn.Module, ready: bool = False) -> Tensor:
    """``act(bn(conv(x)))`` for ``x (B, Cin, H, W)`` -> ``(B, Cout, H, W)``, where :func:`applies` (else the
    modules themselves); updates ``bn``'s running statistics as its own forward does. ``ready``: the caller has
    just found :func:`applies` true for these arguments."""
    if not (ready or applies(x, conv, bn, act)):
        return act(bn(conv(x)))
    code = _act_code(act)
    slope = act.weight if code == 2 else None
    eps = bn.eps
    stats = _batch_statistics(x, conv.weight, conv.bias)
    if bn.track_running_stats:
        _update_running(bn, *stats[1:3], x.shape[0] * x.shape[2] * x.shape[3])
    return _Expansion.apply(x, conv.weight, conv.bias, bn.weight, bn.bias, slope, code, eps, stats)


def _batch_statistics(x: Tensor, weight: Tensor, bias: Tensor | None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """float64 ``(mu (Cin,), mean (Cout,), var (Cout,), S (Cin, Cin))`` of the input and of the expanded map."""
    B, cin = x.shape[:2]
    xd = x.detach().reshape(B, cin, -1).transpose(0, 1).reshape(cin, -1).double()       # (Cin, n)
    mu = xd.mean(1)
    xc = xd - mu.unsqueeze(1)
    cov = xc @ xc.t() / xd.shape[1]
    w = weight.detach().reshape(weight.shape[0], cin).double()
    mean = w @ mu + (bias.detach().double() if bias is not None else 0.0)
    var = ((w @ cov) * w).sum(1).clamp_min(0.0)
    return mu, mean, var, cov


def _update_running(bn: nn.BatchNorm2d, mean: Tensor, var: Tensor, n: int) -> None:
    """``nn.BatchNorm2d``'s update in training: ``num_batches_tracked += 1``, then running mean and unbiased
    variance with ``momentum`` (or the cumulative average when it is ``None``)."""
    with torch.no_grad():
        bn.num_batches_tracked.add_(1)
        f = bn.momentum if bn.momentum is not None else 1.0 / float(bn.num_batches_tracked)
        unbiased = var * (n / max(n - 1, 1))
        bn.running_mean.mul_(1 - f).add_(mean.to(bn.running_mean.dtype), alpha=f)
        bn.running_var.mul_(1 - f).add_(unbiased.to(bn.running_var.dtype), alpha=f)


def _folded(weight: Tensor, bias: Tensor | None, gamma: Tensor | None, beta: Tensor | None, mean: Tensor,
            var: Tensor, eps: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """float64 ``(w (Cout, Cin), invstd, k = gamma * invstd, b')``: batch norm folded into the convolution is
    ``(k w) x + b'``."""
    w = weight.detach().reshape(weight.shape[0], -1).double()
    invstd = (var + eps).rsqrt()
    k = invstd * (gamma.detach().double() if gamma is not None else 1.0)
    b = bias.detach().double() if bias is not None else torch.zeros_like(mean)
    shift = beta.detach().double() if beta is not None else 0.0
    return w, invstd, k, k * (b - mean) + shift


class _Expansion(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, weight, bias, gamma, beta, slope, code, eps, stats):   # type: ignore[override]
        mu, mean, var, cov = stats
        w, invstd, k, bf = _folded(weight, bias, gamma, beta, mean, var, eps)
        wf = (k.unsqueeze(1) * w).float().contiguous()
        bf = bf.float().contiguous()
        B, cin, H, W = x.shape
        cout = w.shape[0]
        y = x.new_empty(B, cout, H, W)
        sl = slope.detach().contiguous() if slope is not None else None
        lib = native.library()
        rc = lib.omnidl_expand_forward(x.data_ptr(), B, cin, H * W, wf.data_ptr(), bf.data_ptr(), cout, code,
                                       native.ptr(sl), int(sl is not None and sl.numel() > 1),
                                       y.data_ptr(), max(1, torch.get_num_threads()))
        if rc:
            raise RuntimeError(f"omnidl expansion: the native kernel returned {rc}")
        ctx.save_for_backward(x, weight, bias, gamma, beta, slope)
        ctx.code, ctx.eps, ctx.stats = code, eps, (mu, cov, w, invstd, k, wf, bf, sl)
        return y

    @staticmethod
    def backward(ctx, g):   # type: ignore[override]
        x, weight, bias, gamma, beta, slope = ctx.saved_tensors
        if torch.is_grad_enabled():                    # create_graph: the modules' ops, differentiable again
            return _composite_backward(ctx, g, x, weight, bias, gamma, beta, slope)
        mu, cov, w, invstd, k, wf, bf, sl = ctx.stats
        B, cin, H, W = x.shape
        cout, n, P = w.shape[0], B * H * W, H * W
        g = g.contiguous()
        lib = native.library()
        common = (B, cin, P, wf.data_ptr(), bf.data_ptr(), cout, ctx.code, native.ptr(sl),
                  int(sl is not None and sl.numel() > 1))
        sums = torch.empty(cout, cin + 2, dtype=torch.float64)
        rc = lib.omnidl_expand_sums(x.data_ptr(), g.data_ptr(), *common, sums.data_ptr(),
                                    max(1, torch.get_num_threads()))
        if rc:
            raise MemoryError("omnidl expansion: the native kernel could not allocate its buffers")
        s1, G, sa = sums[:, 0], sums[:, 1:cin + 1], sums[:, cin + 1]
        m1 = s1 / n
        e_xhat = ((G - s1.unsqueeze(1) * mu) * w).sum(1) * invstd                # sum_p e x_hat, per channel
        m2 = e_xhat / n
        cov_w = w @ cov                                                            # (Cout, Cin): S w_c per row
        gx = None
        if ctx.needs_input_grad[0]:
            c = k * m2 * invstd
            m = -(w.t() * c) @ w                                                   # (Cin, Cin)
            q = -(w * (k * m1).unsqueeze(1)).sum(0) - m @ mu
            a = (w * k.unsqueeze(1)).float().contiguous()
            mf, qf = m.float().contiguous(), q.float().contiguous()
            gx = torch.empty_like(x)
            lib.omnidl_expand_input_grad(x.data_ptr(), g.data_ptr(), *common, a.data_ptr(), mf.data_ptr(),
                                         qf.data_ptr(), gx.data_ptr(), max(1, torch.get_num_threads()))
        gw = gb = ggamma = gbeta = gslope = None
        if ctx.needs_input_grad[1]:
            gwd = k.unsqueeze(1) * (G - (m1 * n).unsqueeze(1) * mu - (m2 * invstd * n).unsqueeze(1) * cov_w)
            gw = gwd.to(weight.dtype).view(weight.shape)
        if bias is not None and ctx.needs_input_grad[2]:
            gb = torch.zeros_like(bias)                 # the bias cancels in batch norm
        if gamma is not None and ctx.needs_input_grad[3]:
            ggamma = e_xhat.to(gamma.dtype)
        if beta is not None and ctx.needs_input_grad[4]:
            gbeta = s1.to(beta.dtype)
        if slope is not None and ctx.needs_input_grad[5]:
            gslope = (sa if slope.numel() > 1 else sa.sum().reshape(1)).to(slope.dtype).view(slope.shape)
        return gx, gw, gb, ggamma, gbeta, gslope, None, None, None


def _composite_backward(ctx, g, x, weight, bias, gamma, beta, slope):
    """The backward through the modules' own ops (batch statistics, no running update), differentiable again."""
    with torch.enable_grad():
        z = F.batch_norm(F.conv2d(x, weight, bias), None, None, gamma, beta, True, 0.0, ctx.eps)
        y = z if ctx.code == 0 else F.relu(z) if ctx.code == 1 else F.prelu(z, slope)
    inputs = (x, weight, bias, gamma, beta, slope)
    wanted = [i for i, t in enumerate(inputs) if t is not None and ctx.needs_input_grad[i]]
    grads = torch.autograd.grad(y, [inputs[i] for i in wanted], g, create_graph=True, allow_unused=True)
    out: list = [None] * 9
    for i, gr in zip(wanted, grads):
        out[i] = gr
    return tuple(out)
