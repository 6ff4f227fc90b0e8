"""The taps of :mod:`.triton_conv`'s fused CUDA kernels: the plan, tap-major, and its transpose in sliced ELL form.

Built once per geometry from the :class:`~omnidl.nn.sampling.SamplingPlan` of the CPU path (the same corners and
weights): ``idx (K, 4, P)`` and ``wt (K, 4, P)``, so that consecutive output positions of one tap and corner lie
together in memory (the forward and weight-gradient kernels read them per tile of positions). The transpose lists,
per input pixel, the ``(row, weight)`` entries that sample it: the input gradient gathers over it instead of
scattering with atomics.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from .offsets import Pair
from .sampling import SamplingPlan, build_plan as build_sampling_plan

#: pixels per tile of the transposed plan (:meth:`TritonPlan.transpose`; the ``sell`` kernel's ``BLOCK_Q``)
TILE_Q = 64
_INT32 = 2 ** 31 - 1  # the kernels index with int32


@dataclass(frozen=True, eq=False)
class TritonPlan:
    """The taps of one geometry: ``idx (K, 4, P)`` int32 flat input pixels, ``wt (K, 4, P)`` their weights (mask
    folded in; 0 where a corner reads zero); the transpose (:meth:`transpose`) is built on first use."""

    idx: Tensor
    wt: Tensor
    in_hw: Pair
    out_hw: Pair
    kernel_size: Pair
    cache: dict = field(default_factory=dict, repr=False)

    @property
    def taps(self) -> int:
        return self.kernel_size[0] * self.kernel_size[1]

    @staticmethod
    def from_sampling(plan: SamplingPlan) -> "TritonPlan":
        P, K = plan.out_hw[0] * plan.out_hw[1], plan.taps
        idx = plan.idx.view(P, K, 4).permute(1, 2, 0).to(torch.int32).contiguous()
        wt = plan.weight.view(P, K, 4).permute(1, 2, 0).contiguous()
        return TritonPlan(idx, wt, plan.in_hw, plan.out_hw, plan.kernel_size)

    def to(self, device=None, dtype=None) -> "TritonPlan":
        return TritonPlan(self.idx.to(device), self.wt.to(device=device, dtype=dtype), self.in_hw, self.out_hw,
                          self.kernel_size)

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.idx, self.wt, *self.cache.get("transpose", ())))

    def transpose(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The plan's transpose in sliced ELL form: for tiles of :data:`TILE_Q` input pixels, ``start (T,)`` and
        ``length (T,)`` (int32; the tile's longest entry list), and ``rows``/``vals`` (int32/float): entry ``e`` of
        pixel ``q`` of tile ``t`` at ``start[t] + e * TILE_Q + q % TILE_Q``, naming row ``p * K + k`` of the columns'
        gradient and its weight (padding: row 0, weight 0). Entries keep the plan's order (deterministic sums). Built
        on the CPU (``bincount`` has no deterministic CUDA kernel) and moved to the plan's device."""
        hit = self.cache.get("transpose")
        if hit is None:
            dev = self.idx.device
            built = _sliced_ell(TritonPlan(self.idx.cpu(), self.wt.cpu(), self.in_hw, self.out_hw, self.kernel_size))
            hit = self.cache["transpose"] = tuple(t.to(dev) for t in built)
        return hit


def _sliced_ell(plan: TritonPlan) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    K, _, P = plan.idx.shape
    Q = plan.in_hw[0] * plan.in_hw[1]
    dev = plan.idx.device
    q = plan.idx.permute(2, 0, 1).reshape(-1).long()                   # entry (p, k, j) in row-major order
    v = plan.wt.permute(2, 0, 1).reshape(-1)
    r = torch.arange(P * K, device=dev).repeat_interleave(4)           # row p * K + k of the columns' gradient
    live = v != 0
    q, v, r = q[live], v[live], r[live]
    order = torch.sort(q, stable=True).indices
    q, v, r = q[order], v[order], r[order]
    counts = torch.bincount(q, minlength=Q)
    first = torch.cumsum(counts, 0) - counts
    rank = torch.arange(q.numel(), device=dev) - first[q]              # position in the pixel's list
    T = -(-Q // TILE_Q)
    length = torch.nn.functional.pad(counts, (0, T * TILE_Q - Q)).view(T, TILE_Q).amax(1)
    start = torch.cumsum(length * TILE_Q, 0) - length * TILE_Q
    total = int((length * TILE_Q).sum())
    if total >= _INT32:
        raise ValueError(f"the transposed plan of a {plan.in_hw} input has {total} entries: more than int32 indexes")
    dest = start[q // TILE_Q] + rank * TILE_Q + q % TILE_Q
    rows = torch.zeros(max(total, 1), dtype=torch.int32, device=dev)
    vals = torch.zeros(max(total, 1), dtype=plan.wt.dtype, device=dev)
    rows[dest] = r.to(torch.int32)
    vals[dest] = v
    return start.to(torch.int32), length.to(torch.int32), rows, vals


def build_plan(offsets: Tensor, mask: Tensor | None, in_hw: Pair, kernel_size: Pair, stride: Pair, padding: Pair,
               dilation: Pair, wrap: bool = False) -> TritonPlan:
    """The :class:`TritonPlan` (float64, on ``offsets.device``) of deform_conv2d ``offsets``/``mask``."""
    return TritonPlan.from_sampling(build_sampling_plan(offsets, mask, in_hw, kernel_size, stride, padding, dilation,
                                                        wrap=wrap))
