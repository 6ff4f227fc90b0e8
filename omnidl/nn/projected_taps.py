"""Fixed-offset convolutions with few output channels: the product onto the taps first, then the sampled sum.

A fixed-offset convolution ``y[p] = sum_k W_k sum_j w[p, k, j] x[idx[p, k, j]] + b`` (``K`` taps, 4 bilinear corners
``j``; :class:`~omnidl.nn.sampling.SamplingPlan`) is linear in the pixels, so the taps' weights ``W_k (Cout, C)``
can act first, on every input pixel: ``z[q, k] = W_k x[q]`` is one dense product ``(H·W, C) @ (C, K·Cout)``, and
``y[p] = sum_{k, j} w[p, k, j] z[idx[p, k, j], k] + b`` is a weighted sum of ``K·4`` rows of ``Cout`` values per
output (``F.embedding_bag``). With ``Cout`` of 1 or 2 (prediction heads: depth, horizon and vanishing-point maps)
the native kernel's register tile, 32 output channels wide, computes 16-32 columns for each one kept, and its
gather interpolates all ``C`` channels of every tap; here the gather moves ``Cout`` values per corner instead.
HoLiNet-ResNet-50-Equi's two-channel heads, 2 threads, 64x128: 0.7 against 2.3-3.4 ms (64 channels); 64 -> 1 at
128x256: 2.4 against 11.5-12.5 ms.

The rule (:func:`pays`): ``2 Cout K <= C`` (the products onto the taps are then at most half the input's width, as
in :mod:`.tap_projection`), on the CPU (on CUDA the column path stays), float32 or float64, and no autograd graph:
``embedding_bag``'s backward made training slower (64 -> 2 channels at 64x128, forward + backward 35 against 9 ms),
so training keeps the native kernel. The sum's indexes (``idx * K + k``, corners of weight 0 sent to a row of
zeros so that a non-finite pixel reaches only the outputs that sample it, as in the native kernel) are kept on the
plan (``plan.derived["taps"]``). Outputs equal the other paths to float rounding
(``tests/nn/test_projected_taps.py``).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .sampling import SamplingPlan, _is_channels_last

#: ``False``: the layer keeps its other paths (benchmarks' in-process A/B, tests)
ENABLED = True


def pays(x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan) -> bool:
    """Whether the sum over projected taps runs for this layer (see the module docstring)."""
    cout, C = weight.shape[0], weight.shape[1]
    graph = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (x, weight, bias))
    return (ENABLED and not graph and x.device.type == "cpu" and weight.device.type == "cpu"
            and x.dtype == weight.dtype and x.dtype in (torch.float32, torch.float64)
            and 2 * cout * plan.taps <= C and tuple(weight.shape[-2:]) == tuple(plan.kernel_size))


def _sum_plan(plan: SamplingPlan) -> SamplingPlan:
    """``plan`` with each corner's index turned into its row of ``z (H·W·K + 1, Cout)``: ``idx * K + k``, or the last
    row (zeros) for a corner of weight 0; kept on the plan."""
    hit = plan.derived.get("taps")
    if hit is None:
        (H, W), K = plan.in_hw, plan.taps
        idx = plan.idx.view(-1, K, 4).long()
        k = torch.arange(K, device=idx.device).view(1, K, 1)
        rows = torch.where(plan.weight.view(-1, K, 4) != 0, idx * K + k, torch.full_like(idx, H * W * K))
        itype = torch.int32 if H * W * K < 2 ** 31 - 1 else torch.int64
        hit = plan.derived.setdefault("taps", SamplingPlan(plan.in_hw, plan.out_hw, plan.kernel_size,
                                                           rows.reshape(-1, 4).to(itype), plan.weight))
    return hit


def projected_taps_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan) -> Tensor:
    """``x (B, C, H, W)`` convolved with ``weight (Cout, C, kh, kw)`` at ``plan``'s taps -> ``(B, Cout, Ho, Wo)`` in
    ``x``'s memory format; for calls without an autograd graph (:func:`pays`: the products are written in place)."""
    B, C, H, W = x.shape
    cout, K = weight.shape[0], plan.taps
    Ho, Wo = plan.out_hw
    sums = _sum_plan(plan)
    rows = sums.idx.view(-1, 4 * K)
    corner_w = plan.weight.view(-1, 4 * K)  # the plan is built for x's dtype
    taps = weight.permute(1, 2, 3, 0).reshape(C, K * cout)  # column k * Cout + o = W_k[o]
    pixels = x.permute(0, 2, 3, 1).reshape(B, H * W, C)  # a view for channels-last input
    z = x.new_empty(H * W * K + 1, cout)  # the taps' products of one image, then a row of zeros
    z[-1] = 0
    outs = []
    for b in range(B):
        torch.mm(pixels[b], taps, out=z[:-1].view(H * W, K * cout))  # no graph (see pays): written in place
        outs.append(F.embedding_bag(rows, z, per_sample_weights=corner_w, mode="sum"))
    y = torch.stack(outs) if B > 1 else outs[0].unsqueeze(0)  # (B, Ho·Wo, Cout)
    if bias is not None:
        y = y + bias
    y = y.view(B, Ho, Wo, cout).permute(0, 3, 1, 2)  # channels-last memory
    return y if _is_channels_last(x) else y.contiguous()  # as the layer's other paths


__all__ = ["ENABLED", "pays", "projected_taps_conv2d"]
