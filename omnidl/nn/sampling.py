"""Fixed-offset deformable convolution: a precomputed bilinear sampling plan and its backends.

A :class:`SamplingPlan` holds, for every (output position ``p``, kernel tap ``k``) pair —
row ``n = p * K + k`` with ``p = oy * Wo + ox`` and ``k = i * kw + j`` — the 4 bilinear
corners ``idx (N, 4)`` (flat input pixel ``y * W + x``) and weights ``weight (N, 4)``.
Corners outside the image get weight 0 (zero padding, as ``deform_conv2d``); with
``wrap`` the column index is taken modulo ``W`` (360° cameras, no seam); the validity
mask is folded into the weights. ``st`` is the sparse transpose ``S^T (H*W, N)`` (CSR)
of the sampling matrix ``S (N, H*W)``.

Fast backend (:func:`fixed_offset_conv2d`, groups = 1), per image of the batch::

    cols = S @ X                        # embedding_bag over channels-last rows: (Ho*Wo*K, C)
    out  = cols.view(Ho*Wo, K*C) @ Wm   # one GEMM, Wm = weight as (K*C, Cout)
    grad_X = S^T @ (grad_out @ Wm^T)    # GEMM + precomputed CSR product
    grad_W = cols^T @ grad_out          # GEMM with the saved (or recomputed) columns

No offsets are expanded over the batch: the plan is shared by every image. Outputs
and input gradients come back as NCHW tensors with channels-last strides.

:func:`deform_conv2d_reference` runs ``torchvision.ops.deform_conv2d`` with the same
offsets and mask (circular padding of the input for ``wrap``): the test reference.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from .offsets import Pair, output_size


@dataclass(frozen=True, eq=False)
class SamplingPlan:
    """Bilinear taps of a fixed-offset convolution on one input size (see module docstring)."""

    in_hw: Pair
    out_hw: Pair
    kernel_size: Pair
    idx: Tensor  # (N, 4) int64
    weight: Tensor  # (N, 4) float
    st: Tensor  # (H*W, N) sparse CSR

    @property
    def taps(self) -> int:
        return self.kernel_size[0] * self.kernel_size[1]

    def nbytes(self) -> int:
        """Memory held by the plan's tensors (bytes)."""
        n = self.idx.numel() * self.idx.element_size() + self.weight.numel() * self.weight.element_size()
        st = self.st
        n += sum(t.numel() * t.element_size() for t in (st.crow_indices(), st.col_indices(), st.values()))
        return n

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "SamplingPlan":
        st = self.st
        if dtype is not None and dtype != st.dtype:
            st = torch.sparse_csr_tensor(st.crow_indices(), st.col_indices(), st.values().to(dtype), st.shape)
        return SamplingPlan(self.in_hw, self.out_hw, self.kernel_size, self.idx.to(device),
                            self.weight.to(device=device, dtype=dtype), st.to(device))


def sample_positions(offsets: Tensor, in_hw: Pair, kernel_size: Pair, stride: Pair, padding: Pair,
                     dilation: Pair) -> tuple[Tensor, Tensor]:
    """Absolute sample positions ``(y, x)``, each ``(Ho, Wo, K)``, of deform_conv2d offsets ``(1, 2K, Ho, Wo)``."""
    kh, kw = kernel_size
    K = kh * kw
    _, c2, Ho, Wo = offsets.shape
    if c2 != 2 * K:
        raise ValueError(f"offsets must have 2*kh*kw = {2 * K} channels, got shape {tuple(offsets.shape)}")
    exp = output_size(in_hw, kernel_size, stride, padding, dilation)
    if (Ho, Wo) != exp:
        raise ValueError(f"offsets have spatial size {(Ho, Wo)}, the convolution's output is {exp}")
    off = offsets[0].permute(1, 2, 0).reshape(Ho, Wo, K, 2)
    dt = off.dtype
    oy = torch.arange(Ho, dtype=dt, device=off.device) * stride[0] - padding[0]
    ox = torch.arange(Wo, dtype=dt, device=off.device) * stride[1] - padding[1]
    ti = (torch.arange(kh, dtype=dt, device=off.device) * dilation[0]).repeat_interleave(kw)
    tj = (torch.arange(kw, dtype=dt, device=off.device) * dilation[1]).repeat(kh)
    y = oy[:, None, None] + ti + off[..., 0]
    x = ox[None, :, None] + tj + off[..., 1]
    return y, x


def build_plan(offsets: Tensor, mask: Tensor | None, in_hw: Pair, kernel_size: Pair, stride: Pair, padding: Pair,
               dilation: Pair, wrap: bool = False) -> SamplingPlan:
    """Bilinear sampling plan (float64, on ``offsets.device``) from deform_conv2d offsets/mask ``(1, ., Ho, Wo)``."""
    H, W = in_hw
    y, x = sample_positions(offsets.double(), in_hw, kernel_size, stride, padding, dilation)
    Ho, Wo, K = y.shape
    y0 = torch.floor(y)
    x0 = torch.floor(x)
    ly, lx = y - y0, x - x0
    w = torch.stack([(1 - ly) * (1 - lx), (1 - ly) * lx, ly * (1 - lx), ly * lx], -1)
    cy = torch.stack([y0, y0, y0 + 1, y0 + 1], -1)
    cx = torch.stack([x0, x0 + 1, x0, x0 + 1], -1)
    ok = (cy >= 0) & (cy <= H - 1)
    if wrap:
        cx = torch.remainder(cx, W)
    else:
        ok = ok & (cx >= 0) & (cx <= W - 1)
    # deform_conv2d reads zero when the sample itself is at/after -1 or H/W (matches per-corner rule)
    if mask is not None:
        w = w * mask[0].double().permute(1, 2, 0).reshape(Ho, Wo, K, 1)
    ok = ok & (w != 0)
    w = torch.where(ok, w, torch.zeros_like(w))
    idx = torch.where(ok, cy * W + cx, torch.zeros_like(cy)).long()
    idx = idx.reshape(-1, 4)
    w = w.reshape(-1, 4)
    N = idx.shape[0]
    rows = torch.arange(N, device=idx.device).repeat_interleave(4)
    keep = ok.reshape(-1)
    coo = torch.sparse_coo_tensor(torch.stack([idx.reshape(-1)[keep], rows[keep]]), w.reshape(-1)[keep],
                                  (H * W, N), check_invariants=False).coalesce()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*Sparse CSR tensor support is in beta.*")
        st = coo.to_sparse_csr()
    return SamplingPlan((H, W), (Ho, Wo), tuple(kernel_size), idx.contiguous(), w.contiguous(), st)


def _rows(x: Tensor) -> Tensor:
    """``(B, C, H, W)`` -> contiguous channels-last ``(B, H*W, C)`` (no copy if already channels-last)."""
    B, C, H, W = x.shape
    return x.permute(0, 2, 3, 1).contiguous().view(B, H * W, C)


def _gather(plan: SamplingPlan, xb: Tensor) -> Tensor:
    """``cols (N, C) = S @ xb`` for one image ``xb (H*W, C)``."""
    return F.embedding_bag(plan.idx, xb, per_sample_weights=plan.weight, mode="sum")


class _FixedOffsetConv(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan,  # type: ignore[override]
                save_columns: bool) -> Tensor:
        B, C, H, W = x.shape
        Cout = weight.shape[0]
        K = plan.taps
        Ho, Wo = plan.out_hw
        xr = _rows(x)
        wm = weight.permute(2, 3, 1, 0).reshape(K * C, Cout)
        out = torch.empty(B, Ho * Wo, Cout, dtype=x.dtype, device=x.device)
        cols_all = []
        for b in range(B):
            cols = _gather(plan, xr[b]).view(Ho * Wo, K * C)
            if bias is not None:
                torch.addmm(bias, cols, wm, out=out[b])
            else:
                torch.mm(cols, wm, out=out[b])
            if save_columns and weight.requires_grad:
                cols_all.append(cols)
        ctx.plan = plan
        ctx.cols = cols_all
        ctx.has_bias = bias is not None
        ctx.save_for_backward(xr if (weight.requires_grad and not save_columns) else None, wm)
        ctx.in_shape = (B, C, H, W)
        return out.view(B, Ho, Wo, Cout).permute(0, 3, 1, 2)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        plan: SamplingPlan = ctx.plan
        xr, wm = ctx.saved_tensors
        B, C, H, W = ctx.in_shape
        K = plan.taps
        kh, kw = plan.kernel_size
        Ho, Wo = plan.out_hw
        Cout = wm.shape[1]
        g = _rows(grad_out)  # (B, Ho*Wo, Cout)
        need_x, need_w, need_b = ctx.needs_input_grad[0], ctx.needs_input_grad[1], ctx.needs_input_grad[2]
        gx = gw = gb = None
        if need_x:
            gx = torch.empty(B, H * W, C, dtype=g.dtype, device=g.device)
        if need_w:
            gwm = torch.zeros(K * C, Cout, dtype=g.dtype, device=g.device)
        for b in range(B):
            if need_w:
                cols = ctx.cols[b] if ctx.cols else _gather(plan, xr[b]).view(Ho * Wo, K * C)
                gwm.addmm_(cols.t(), g[b])
            if need_x:
                gcols = torch.mm(g[b], wm.t()).view(Ho * Wo * K, C)
                gx[b] = plan.st @ gcols
        ctx.cols = None
        if need_x:
            gx = gx.view(B, H, W, C).permute(0, 3, 1, 2)
        if need_w:
            gw = gwm.view(kh, kw, C, Cout).permute(3, 2, 0, 1)
        if need_b and ctx.has_bias:
            gb = g.sum((0, 1))
        return gx, gw, gb, None, None


def fixed_offset_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan,
                        save_columns: bool = True) -> Tensor:
    """Convolution of ``x (B, C, H, W)`` with ``weight (Cout, C, kh, kw)`` sampled by ``plan`` (groups = 1).

    ``save_columns=False`` recomputes the gathered columns in backward instead of keeping
    them (``B * Ho*Wo * K * C`` values) between forward and backward.
    Returns ``(B, Cout, Ho, Wo)`` with channels-last strides.
    """
    if x.dim() != 4:
        raise ValueError(f"expected a (B, C, H, W) input, got shape {tuple(x.shape)}")
    if tuple(x.shape[-2:]) != tuple(plan.in_hw):
        raise ValueError(f"input spatial size {tuple(x.shape[-2:])} does not match the plan's {plan.in_hw}")
    if weight.shape[1] != x.shape[1] or tuple(weight.shape[-2:]) != tuple(plan.kernel_size):
        raise ValueError(f"weight of shape {tuple(weight.shape)} does not fit input channels {x.shape[1]} and "
                         f"kernel {plan.kernel_size} (the fast backend supports groups=1 only)")
    if plan.weight.dtype != x.dtype or plan.idx.device != x.device:
        raise ValueError(f"plan is {plan.weight.dtype} on {plan.idx.device}, input is {x.dtype} on {x.device}")
    return _FixedOffsetConv.apply(x, weight, bias, plan, save_columns)


def deform_conv2d_reference(x: Tensor, weight: Tensor, bias: Tensor | None, offsets: Tensor, mask: Tensor | None,
                            stride: Pair, padding: Pair, dilation: Pair, wrap: bool = False) -> Tensor:
    """``torchvision.ops.deform_conv2d`` with fixed offsets/mask ``(1, ., Ho, Wo)`` (expanded over the batch).

    With ``wrap`` the input is tiled three times horizontally (circular padding by ``W``
    on each side) and the column offsets shifted accordingly, so samples across the
    left/right border read the other side of the panorama. Supports ``groups`` through
    the weight shape, like ``deform_conv2d``.
    """
    from torchvision.ops import deform_conv2d

    B = x.shape[0]
    W = x.shape[-1]
    Ho, Wo = offsets.shape[-2:]
    off = offsets.to(x.dtype).expand(B, -1, -1, -1)
    m = None if mask is None else mask.to(x.dtype).expand(B, -1, -1, -1)
    if not wrap:
        return deform_conv2d(x, off, weight, bias, stride=stride, padding=padding, dilation=dilation, mask=m)
    xp = torch.cat([x, x, x], -1)
    off = off.clone()
    off[:, 1::2] += W - padding[1]  # sample column in the tiled image: x + W, and no horizontal padding
    kw = weight.shape[-1]
    wo_big = (3 * W - dilation[1] * (kw - 1) - 1) // stride[1] + 1
    off = F.pad(off, (0, wo_big - Wo))
    if m is not None:
        m = F.pad(m, (0, wo_big - Wo))
    y = deform_conv2d(xp, off, weight, bias, stride=stride, padding=(padding[0], 0), dilation=dilation, mask=m)
    return y[..., :Wo]
