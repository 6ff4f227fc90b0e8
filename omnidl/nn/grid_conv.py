"""The fast backend of :class:`~omnidl.nn.ProjectedConv2d` on CUDA: one ``grid_sample`` of every tap, one product.

A fixed-offset convolution samples tap ``k`` of output position ``p`` bilinearly at a position known in advance
(``y, x`` of :func:`omnidl.nn.sampling.sample_positions`) and multiplies the sampled columns by the weight. On a GPU
the CPU's chunked gather (``embedding_bag`` per chunk, then a small product each) is launch- and gather-bound: 4-6x
cuDNN's convolution on an H200. Here the taps are rows of one sampling grid ``(1, K*Ho, Wo, 2)``: ``F.grid_sample``
writes the columns ``(B, C, K*Ho, Wo)`` = ``(B, C*K, Ho, Wo)`` in one pass, and one product with the weight
``(Cout, C*K)`` -- a 1x1 convolution, so cuDNN runs it under ``nn.Conv2d``'s precision policy (TF32 where
``torch.backends.cudnn.allow_tf32``) -- gives the output. Autograd differentiates both ops (``grid_sample``'s input
gradient is its scatter).

* the horizontal wrap of a panorama is a circular pad of ``pad`` columns each side (one copy of the input), the
  grid's positions shifted by ``pad``;
* a binary tap mask (what the cameras give: 0 for taps whose ray leaves the image) moves masked taps far outside
  the image, where ``padding_mode="zeros"`` reads zero; another mask multiplies the columns;
* positions are normalised for ``align_corners=False`` (any size, also 1 pixel), built in float64 and cast once to
  the input's dtype. In float32 the position of a sample ``x`` pixels from the left carries a rounding error of
  about ``x * 6e-8`` pixels (``1.5e-5`` at ``x = 256``); float64 agrees with ``deform_conv2d`` to ``1e-12``.

Elsewhere (the CPU, ``torch.use_deterministic_algorithms``, whose ``grid_sample`` backward on CUDA has no
deterministic kernel, a wrap wider than the image) the plan path of :mod:`omnidl.nn.sampling` runs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from .offsets import Pair
from .padding import pad_panorama
from .sampling import sample_positions

#: channels per ``grid_sample`` image (:func:`grid_conv2d`; the channels are split into groups of their gcd with it)
SAMPLE_CHANNELS = 8
#: normalised coordinate of a masked tap: far outside ``[-1, 1]``, so every corner reads zero
FAR = -4.0


@dataclass(frozen=True, eq=False)
class GridPlan:
    """``grid (1, K*Ho, Wo, 2)``: normalised ``(x, y)`` of tap ``k`` of output ``(i, j)`` at row ``k*Ho + i`` of the
    input padded by ``pad`` columns each side (circularly); ``scale (K*Ho, Wo)``: tap weights where the mask is not
    binary (else ``None``)."""

    grid: Tensor
    pad: int
    scale: Tensor | None
    in_hw: Pair
    out_hw: Pair
    taps: int

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "GridPlan":
        return GridPlan(self.grid.to(device=device, dtype=dtype), self.pad,
                        None if self.scale is None else self.scale.to(device=device, dtype=dtype),
                        self.in_hw, self.out_hw, self.taps)


def build_grid_plan(offsets: Tensor, mask: Tensor | None, in_hw: Pair, kernel_size: Pair, stride: Pair,
                    padding: Pair, dilation: Pair, wrap: bool = False) -> GridPlan | None:
    """The :class:`GridPlan` (float64, on ``offsets.device``) of deform_conv2d ``offsets``/``mask`` ``(1, ., Ho, Wo)``;
    ``None`` where a wrap would need more padding than the image is wide (the plan path then runs)."""
    H, W = in_hw
    y, x = sample_positions(offsets.double(), in_hw, kernel_size, stride, padding, dilation)   # (Ho, Wo, K) each
    Ho, Wo, K = y.shape
    m = None if mask is None else mask[0].double().permute(1, 2, 0)                           # (Ho, Wo, K)
    live = torch.isfinite(x) & torch.isfinite(y)
    if m is not None:
        live &= m != 0
    pad = 0
    if wrap and bool(live.any()):
        xs = x[live]
        # a sample in (-1, 0) reads column -1 (= W - 1): one column more than the sample's own distance
        pad = max(0, math.ceil(max(-float(xs.min()), float(xs.max()) - (W - 1)))) + 1
        if pad > W:
            return None
    gx = (2 * (x + pad) + 1) / (W + 2 * pad) - 1
    gy = (2 * y + 1) / H - 1
    scale = None
    if m is not None and not bool(((m == 0) | (m == 1)).all()):
        scale = m.permute(2, 0, 1).reshape(K * Ho, Wo)
    gx = torch.where(live, gx, torch.full_like(gx, FAR))
    gy = torch.where(live, gy, torch.full_like(gy, FAR))
    grid = torch.stack([gx, gy], -1).permute(2, 0, 1, 3).reshape(1, K * Ho, Wo, 2).contiguous()
    return GridPlan(grid, pad, scale, (H, W), (Ho, Wo), K)


def grid_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, plan: GridPlan) -> Tensor:
    """Convolution of ``x (B, C, H, W)`` with ``weight (Cout, C, kh, kw)`` at the taps of ``plan`` (groups = 1):
    ``(B, Cout, Ho, Wo)``. Differentiable in ``x``, ``weight`` and ``bias``."""
    if x.dim() != 4 or tuple(x.shape[-2:]) != tuple(plan.in_hw):
        raise ValueError(f"grid_conv2d: input of shape {tuple(x.shape)} does not fit the plan's {plan.in_hw}")
    B, C = x.shape[:2]
    Cout, K = weight.shape[0], plan.taps
    if weight.shape[1] != C or weight.shape[2] * weight.shape[3] != K:
        raise ValueError(f"grid_conv2d: weight of shape {tuple(weight.shape)} does not fit {C} input channels and "
                         f"{K} taps (groups=1 only)")
    Ho, Wo = plan.out_hw
    if plan.pad:
        x = pad_panorama(x, plan.pad)
    grid = plan.grid if plan.grid.dtype == x.dtype else plan.grid.to(x.dtype)
    # grid_sample runs one thread per sample and loops over the channels: groups of ``g`` channels as images of
    # their own give it C/g times the threads (the same memory: (B*C/g, g, .) is (B, C, .))
    g = math.gcd(C, max(1, int(SAMPLE_CHANNELS)))
    xs = x.reshape(B * C // g, g, x.shape[2], x.shape[3])
    cols = F.grid_sample(xs, grid.expand(B * C // g, -1, -1, -1), mode="bilinear", padding_mode="zeros",
                         align_corners=False).view(B, C, K * Ho, Wo)           # (B, C, K*Ho, Wo)
    if plan.scale is not None:
        cols = cols * plan.scale.to(cols.dtype)
    # the product as a 1x1 convolution of the columns: cuDNN's GEMM, with nn.Conv2d's precision policy (TF32 where
    # torch.backends.cudnn.allow_tf32, the default) and its bias in the same call
    return F.conv2d(cols.reshape(B, C * K, Ho, Wo), weight.reshape(Cout, C * K, 1, 1), bias)


def applies(x: Tensor) -> bool:
    """Whether :class:`~omnidl.nn.ProjectedConv2d`'s fast backend samples with :func:`grid_conv2d`: a CUDA input,
    deterministic algorithms not requested."""
    return x.is_cuda and not torch.are_deterministic_algorithms_enabled()
