"""Fixed-offset deformable convolution: a precomputed bilinear sampling plan and its backends.

A :class:`SamplingPlan` holds, for every (output position ``p``, kernel tap ``k``) pair —
row ``n = p * K + k`` with ``p = oy * Wo + ox`` and ``k = i * kw + j`` — the 4 bilinear
corners ``idx (N, 4)`` (flat input pixel ``y * W + x``) and weights ``weight (N, 4)``.
Corners outside the image get weight 0 (zero padding, as ``deform_conv2d``); with
``wrap`` the column index is taken modulo ``W`` (360° cameras, no seam); the validity
mask is folded into the weights. Together they are the sparse sampling matrix
``S (N, H*W)`` (4 non-zeros per row).

Fast backend (:func:`fixed_offset_conv2d`, groups = 1), per image of the batch and per
chunk of output positions (so that each chunk's columns stay in cache)::

    cols = S_c @ X                      # embedding_bag over channels-last rows: (P_c, K*C)
    out_c = cols @ Wm                   # GEMM, Wm = weight as (K*C, Cout)
    grad_X[band] += S_c^T @ (grad_out_c @ Wm^T)   # GEMM + precomputed CSR transpose of the chunk
    grad_W += cols^T @ grad_out_c       # columns recomputed in backward (nothing big is saved)

On CPU the (image, chunk) tasks are split among ``torch.get_num_threads()`` worker threads
whose ops run single-threaded: one fork/join per call instead of one per small op, which
matters on a busy machine. No offsets are expanded over the batch: the plan is shared by
every image. Outputs and
input gradients keep the memory format of the input (channels-last is copy-free; NCHW costs
one layout copy of the input, one per output chunk and one of the input gradient).

On CPU float32, :class:`~omnidl.nn.ProjectedConv2d` runs the native fused kernel of :mod:`.fused` instead
(gather and product in one pass over cache-resident blocks); where that kernel cannot be built, the forward of
:mod:`.tiled` (the same taps convolved by oneDNN) and this backward.

:func:`deform_conv2d_reference` runs ``torchvision.ops.deform_conv2d`` with the same
offsets and mask (circular padding of the input for ``wrap``): the test reference.
"""
from __future__ import annotations

import os
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor

from . import thin_layout
from .offsets import Pair, output_size


#: target size (bytes) of one chunk of gathered columns (gather -> GEMM -> scatter stay in L2/L3;
#: measured here: ~4k positions of 64 channels beat both 1k and 16k)
CHUNK_BYTES = 10_000_000
#: the same on CUDA, where this path runs only under ``torch.use_deterministic_algorithms`` or for a wrap wider than
#: the image (:mod:`.grid_conv` elsewhere): a whole image per chunk at the usual sizes (each chunk costs its gather
#: and product launches; on an H200 eight chunks of 10 MB ran 6.1x cuDNN's convolution, one chunk 4.4x)
CUDA_CHUNK_BYTES = 512_000_000


@dataclass(frozen=True, eq=False)
class SamplingPlan:
    """Bilinear taps of a fixed-offset convolution on one input size (see module docstring).

    ``idx (N, 4)`` flat input pixels (int32; int64 for huge images) and ``weight (N, 4)``
    bilinear weights (0 for corners that read zero), ``N = Ho * Wo * kh * kw``. Chunked sparse transposes are
    built on first use per chunk length and kept in ``chunk_cache``; plans derived from this one (the tiled
    row order of :mod:`.tiled`) are kept in ``derived``.
    """

    in_hw: Pair
    out_hw: Pair
    kernel_size: Pair
    idx: Tensor
    weight: Tensor
    chunk_cache: dict = field(default_factory=dict, repr=False)
    derived: dict = field(default_factory=dict, repr=False)  # e.g. the tiled reordering (:mod:`.tiled`)

    @property
    def taps(self) -> int:
        return self.kernel_size[0] * self.kernel_size[1]

    def chunks(self, positions: int) -> list[tuple[int, int, int, int, Tensor]]:
        """Chunks of ``positions`` output positions: ``(start, end, lo, hi, st)`` with ``st`` the CSR
        ``(hi - lo, (end - start) * K)`` transpose of the chunk's rows of ``S``, restricted to the
        input pixels ``[lo, hi)`` they touch."""
        hit = self.chunk_cache.get(positions)
        if hit is not None:
            return hit
        P = self.out_hw[0] * self.out_hw[1]
        K = self.taps
        out = []
        for s in range(0, P, positions):
            e = min(P, s + positions)
            w = self.weight[s * K:e * K].reshape(-1)
            nz = w != 0
            inp = self.idx[s * K:e * K].reshape(-1)[nz]
            col = torch.arange((e - s) * K, device=inp.device).repeat_interleave(4)[nz]
            w = w[nz]
            lo, hi = (int(inp.min()), int(inp.max()) + 1) if inp.numel() else (0, 1)
            inp = inp.long() - lo
            order = torch.argsort(inp * ((e - s) * K) + col)
            itype = torch.int32 if w.numel() < 2 ** 31 - 1 else torch.int64
            crow = torch.zeros(hi - lo + 1, dtype=torch.int64, device=inp.device)
            crow[1:] = torch.cumsum(torch.bincount(inp, minlength=hi - lo), 0)
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=".*Sparse CSR tensor support is in beta.*")
                st = torch.sparse_csr_tensor(crow.to(itype), col[order].to(itype), w[order], (hi - lo, (e - s) * K),
                                             check_invariants=False)
            out.append((s, e, lo, hi, st))
        self.chunk_cache[positions] = out
        return out

    def nbytes(self) -> int:
        """Memory held by the plan's tensors, built chunk transposes included (bytes)."""
        n = self.idx.numel() * self.idx.element_size() + self.weight.numel() * self.weight.element_size()
        for chunks in self.chunk_cache.values():
            for *_, st in chunks:
                n += sum(t.numel() * t.element_size() for t in (st.crow_indices(), st.col_indices(), st.values()))
        return n + sum(p.nbytes() for p in self.derived.values())

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "SamplingPlan":
        """A copy on ``device`` with weights of ``dtype`` (chunk transposes are rebuilt lazily)."""
        return SamplingPlan(self.in_hw, self.out_hw, self.kernel_size, self.idx.to(device),
                            self.weight.to(device=device, dtype=dtype))


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
    idx = idx.to(torch.int32 if H * W < 2 ** 31 - 1 else torch.int64)
    return SamplingPlan((H, W), (Ho, Wo), tuple(kernel_size), idx.reshape(-1, 4).contiguous(),
                        w.reshape(-1, 4).contiguous())


def _rows(x: Tensor) -> Tensor:
    """``(B, C, H, W)`` -> contiguous channels-last ``(B, H*W, C)`` (no copy if already channels-last)."""
    B, C, H, W = x.shape
    return x.permute(0, 2, 3, 1).contiguous().view(B, H * W, C)


def _gather(plan: SamplingPlan, xb: Tensor, start: int, end: int) -> Tensor:
    """Columns ``(end - start, K * C)`` of output positions ``[start, end)`` for one image ``xb (H*W, C)``."""
    K = plan.taps
    cols = F.embedding_bag(plan.idx[start * K:end * K], xb, per_sample_weights=plan.weight[start * K:end * K],
                           mode="sum")
    return cols.view(end - start, K * xb.shape[1])


def chunk_positions(plan: SamplingPlan, channels: int, element_size: int, device: torch.device | None = None) -> int:
    """Output positions per chunk so that one chunk of columns is about :data:`CHUNK_BYTES`
    (:data:`CUDA_CHUNK_BYTES` on a CUDA ``device``)."""
    target = CUDA_CHUNK_BYTES if device is not None and device.type == "cuda" else CHUNK_BYTES
    return max(16, target // (plan.taps * channels * element_size))


def _is_channels_last(t: Tensor) -> bool:
    """True when ``t (B, C, H, W)`` stores channels innermost (channels-last, also a channel slice of a
    channels-last map, which is not contiguous in either format) and is not plain contiguous."""
    return t.dim() == 4 and t.shape[1] > 1 and t.stride(1) == 1 and not t.is_contiguous()


def weight_channels_last(weight: Tensor) -> bool:
    """True for a channels-last ``weight (Cout, C, kh, kw)``, ``(Cout, kh, kw, C)`` in memory, that is not also
    contiguous (a 1x1 weight is both: it counts as contiguous)."""
    return weight.is_contiguous(memory_format=torch.channels_last) and not weight.is_contiguous()


# -- CPU execution: chunks run on single-threaded workers ------------------------------------------
# Parallelising inside every small op (gather, GEMM, CSR product of one chunk) means hundreds of
# fork/join points per call; on a busy machine each one waits for a descheduled thread. Instead,
# the chunks are split among ``torch.get_num_threads()`` Python workers whose torch ops run
# single-threaded (the ops release the GIL), so there is one join per call.
_POOL: dict = {}
_POOL_LOCK = threading.Lock()


def _single_thread_init() -> None:
    torch.set_num_threads(1)  # per-thread OpenMP/MKL setting of this worker


def _cpu_pool(workers: int) -> ThreadPoolExecutor:
    key = (os.getpid(), workers)  # a fork (e.g. DataLoader workers) gets its own pool
    with _POOL_LOCK:
        pool = _POOL.get(key)
        if pool is None:
            main_threads = torch.get_num_threads()
            pool = ThreadPoolExecutor(workers, thread_name_prefix="omnidl-conv", initializer=_single_thread_init)
            list(pool.map(lambda _: None, range(4 * workers)))  # start the workers now
            torch.set_num_threads(main_threads)  # the workers' setting must not leak into new threads
            _POOL[key] = pool
    return pool


def _run_split(tasks: list, fn, device: torch.device) -> list:
    """``fn(part)`` on contiguous parts of ``tasks``: one part per worker on CPU, one part elsewhere."""
    workers = torch.get_num_threads() if device.type == "cpu" else 1
    workers = min(workers, len(tasks))
    if workers <= 1 or threading.current_thread().name.startswith("omnidl-conv"):
        return [fn(tasks)]
    bounds = [round(i * len(tasks) / workers) for i in range(workers + 1)]
    parts = [tasks[bounds[i]:bounds[i + 1]] for i in range(workers)]

    def run(part: list):
        with torch.no_grad():  # grad mode is per thread: the workers must not record either
            return fn(part)
    return list(_cpu_pool(workers).map(run, parts))


def weight_matrix(weight: Tensor) -> Tensor:
    """``weight (Cout, C, kh, kw)`` as the contiguous ``(kh*kw*C, Cout)`` matrix ``Wm`` of the column products."""
    Cout, C, kh, kw = weight.shape
    return weight.detach().permute(2, 3, 1, 0).reshape(kh * kw * C, Cout).contiguous()


def save_columns_context(ctx, x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan, positions: int,
                         xr: Tensor, wm: Tensor | None = None) -> None:
    """Store on ``ctx`` what :meth:`_FixedOffsetConv.backward` needs (``xr``: the input as ``(B, H*W, C)`` rows;
    ``wm``: the form of the weight the caller's backward reads, default :func:`weight_matrix` of ``weight``)."""
    ctx.plan = plan
    ctx.positions = positions
    ctx.has_bias = bias is not None
    ctx.channels_last = _is_channels_last(x)
    ctx.weight_channels_last = weight_channels_last(weight)
    ctx.save_for_backward(xr if weight.requires_grad else None, weight_matrix(weight) if wm is None else wm)
    ctx.in_shape = tuple(x.shape)


def new_accumulators(ctx, out_channels: int, like: Tensor) -> tuple[Tensor | None, Tensor | None]:
    """One worker's private gradient accumulators (input bands of neighbouring chunks overlap): input rows
    ``(B, H*W, C)`` and weight ``(kh*kw*C, Cout)`` zeros, each ``None`` when that gradient is not needed."""
    B, C, H, W = ctx.in_shape
    kh, kw = ctx.plan.kernel_size
    opts = dict(dtype=like.dtype, device=like.device)
    return (torch.zeros(B, H * W, C, **opts) if ctx.needs_input_grad[0] else None,
            torch.zeros(kh * kw * C, out_channels, **opts) if ctx.needs_input_grad[1] else None)


def finish_backward(ctx, grad_out: Tensor, parts: list[tuple[Tensor | None, Tensor | None]]) -> tuple:
    """The gradients a fixed-offset convolution's ``backward`` returns, from the workers' private
    accumulators ``parts``: ``[(grad of the input rows (B, H*W, C) or None, grad of the weight as
    (kh*kw*C, Cout) or None), ...]`` (summed here), in the input's memory format, plus the bias gradient."""
    C = ctx.in_shape[1]
    kh, kw = ctx.plan.kernel_size
    gx, gwm = parts[0]
    for px, pw in parts[1:]:
        if gx is not None:
            gx += px
        if gwm is not None:
            gwm += pw
    gw = gb = None
    if gx is not None:
        gx = rows_as_map(gx, ctx.in_shape, ctx.channels_last)
    if gwm is not None:
        gw = _weight_layout(gwm, kh, kw, C, ctx.weight_channels_last)
    if ctx.needs_input_grad[2] and ctx.has_bias:
        gb = grad_out.sum((0, 2, 3))
    return gx, gw, gb, None, None


def rows_as_map(rows: Tensor, shape: tuple[int, int, int, int], channels_last: bool) -> Tensor:
    """Input-gradient rows ``(B, H*W, C)`` as the map ``shape = (B, C, H, W)``: a channels-last view, or (not
    ``channels_last``) contiguous memory by :func:`omnidl.nn.thin_layout.to_nchw`."""
    B, C, H, W = shape
    gx = rows.view(B, H, W, C).permute(0, 3, 1, 2)
    return gx if channels_last else thin_layout.to_nchw(gx)


def _weight_layout(gwm: Tensor, kh: int, kw: int, C: int, channels_last: bool) -> Tensor:
    """The weight gradient ``gwm (kh*kw*C, Cout)`` as ``(Cout, C, kh, kw)`` in its weight's memory format, so that
    autograd keeps it as ``.grad`` without a copy of its own: for a channels-last weight one native transposing
    pass (:func:`omnidl.nn.thin_layout.nhwc_into_nchw`; torch's copy in this direction took 46 against 26 ms for
    1024 -> 1024 channels, 3x3, 5.1 against 1.9 ms for 512 channels, 2 threads); for a contiguous one a view
    (autograd's own copy runs as fast as two native passes would)."""
    Cout = gwm.shape[1]
    gw = gwm.view(kh, kw, C, Cout).permute(3, 2, 0, 1)
    if not (channels_last and thin_layout.native_pass(gwm)):
        return gw
    out = torch.empty(gw.shape, dtype=gw.dtype, memory_format=torch.channels_last)
    thin_layout.nhwc_into_nchw(gwm.view(1, kh * kw, C, Cout), out.permute(0, 2, 3, 1).view(1, Cout, kh * kw, C))
    return out


class _FixedOffsetConv(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan,  # type: ignore[override]
                positions: int) -> Tensor:
        B, C, H, W = x.shape
        Cout = weight.shape[0]
        K = plan.taps
        Ho, Wo = plan.out_hw
        P = Ho * Wo
        channels_last = _is_channels_last(x)
        xr = _rows(x)
        wm = weight.permute(2, 3, 1, 0).reshape(K * C, Cout)
        wmt = wm.t()
        tasks = [(b, s, e) for b in range(B) for s, e, *_ in plan.chunks(positions)]
        # ``result`` is allocated as the returned tensor itself (never a view of an internal buffer), so that
        # in-place ops after the convolution (e.g. ReLU(inplace=True)) work with autograd
        if channels_last:  # output rows (B, P, Cout), written in place chunk by chunk
            result = torch.empty(B, Cout, Ho, Wo, dtype=x.dtype, device=x.device, memory_format=torch.channels_last)
            out = result.permute(0, 2, 3, 1).view(B, P, Cout)

            def work(part: list) -> None:
                for b, s, e in part:
                    cols = _gather(plan, xr[b], s, e)
                    if bias is not None:
                        torch.addmm(bias, cols, wm, out=out[b, s:e])
                    else:
                        torch.mm(cols, wm, out=out[b, s:e])
        else:  # NCHW output (B, Cout, P): each chunk computed transposed, straight into its strided slice
            result = torch.empty(B, Cout, Ho, Wo, dtype=x.dtype, device=x.device)
            out = result.view(B, Cout, P)
            bcol = None if bias is None else bias.unsqueeze(1)

            def work(part: list) -> None:
                for b, s, e in part:
                    cols = _gather(plan, xr[b], s, e)
                    if bcol is None:  # written in place: the (Cout, P_c) slice is a BLAS matrix with ld = P
                        torch.mm(wmt, cols.t(), out=out[b, :, s:e])
                    else:
                        torch.addmm(bcol, wmt, cols.t(), out=out[b, :, s:e])
        _run_split(tasks, work, x.device)
        save_columns_context(ctx, x, weight, bias, plan, positions, xr)
        return result

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        plan: SamplingPlan = ctx.plan
        xr, wm = ctx.saved_tensors
        B, C = ctx.in_shape[:2]
        Cout = wm.shape[1]
        P = plan.out_hw[0] * plan.out_hw[1]
        if _is_channels_last(grad_out):
            g = _rows(grad_out)  # (B, P, Cout)

            def gchunk(b: int, s: int, e: int) -> Tensor:
                return g[b, s:e]
        else:
            g = grad_out.contiguous().view(B, Cout, P)

            def gchunk(b: int, s: int, e: int) -> Tensor:
                return g[b, :, s:e].t()  # strided (P_c, Cout) view, BLAS-compatible
        need_x, need_w = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        wmt = wm.t()
        tasks = [(b, s, e, lo, hi, st) for b in range(B) for s, e, lo, hi, st in plan.chunks(ctx.positions)]

        def work(part: list) -> tuple[Tensor | None, Tensor | None]:
            gx, gwm = new_accumulators(ctx, Cout, g)
            for b, s, e, lo, hi, st in part:
                gc = gchunk(b, s, e)
                if need_w:  # recompute the chunk's columns (cheap gather, stays in cache)
                    gwm.addmm_(_gather(plan, xr[b], s, e).t(), gc)
                if need_x:
                    gx[b, lo:hi].addmm_(st, torch.mm(gc, wmt).view(-1, C))
            return gx, gwm

        return finish_backward(ctx, grad_out, _run_split(tasks, work, g.device))


def fixed_offset_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, plan: SamplingPlan,
                        positions: int | None = None) -> Tensor:
    """Convolution of ``x (B, C, H, W)`` with ``weight (Cout, C, kh, kw)`` sampled by ``plan`` (groups = 1).

    Work is done in chunks of ``positions`` output positions (default: about
    :data:`CHUNK_BYTES` of columns per chunk, :data:`CUDA_CHUNK_BYTES` on CUDA): gather, GEMM and scatter of a
    chunk stay in cache, and the columns are recomputed in backward instead of being stored (no
    ``Ho*Wo*K*C`` buffer is kept between forward and backward).
    Returns ``(B, Cout, Ho, Wo)`` in the memory format of ``x`` (channels-last input ->
    channels-last output without any copy; that is the fastest layout on CPU).
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
    if positions is None:
        positions = chunk_positions(plan, x.shape[1], x.element_size(), x.device)
    return _FixedOffsetConv.apply(x, weight, bias, plan, int(positions))


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


def circular_offsets(offsets: Tensor, in_hw: Pair, kernel_size: Pair, stride: Pair, padding: Pair,
                     dilation: Pair) -> tuple[Tensor, int]:
    """Offsets ``(1, 2K, Ho, Wo)`` rewritten for :func:`deform_conv2d_circular`: every sample column taken
    modulo ``W`` (a representative in ``[0, W)``) on an input circularly padded by ``P = max(1, padding[1])``
    columns per side. Returns ``(offsets', P)``; compute once per geometry."""
    kh, kw = kernel_size
    W = in_hw[1]
    P = max(1, padding[1])
    Ho, Wo = offsets.shape[-2:]
    off = offsets.clone()
    ox = (torch.arange(Wo, dtype=off.dtype, device=off.device) * stride[1]).view(1, 1, 1, Wo)
    tj = (torch.arange(kw, dtype=off.dtype, device=off.device) * dilation[1]).repeat(kh).view(1, -1, 1, 1)
    x = ox - padding[1] + tj + off[:, 1::2]  # absolute sample columns
    off[:, 1::2] = torch.remainder(x, W) + P - ox - tj
    return off, P


def deform_conv2d_circular(x: Tensor, weight: Tensor, bias: Tensor | None, offsets_wrapped: Tensor,
                           mask: Tensor | None, P: int, stride: Pair, padding: Pair, dilation: Pair) -> Tensor:
    """Wrap-correct ``torchvision.ops.deform_conv2d`` with the output size of the plain call: the input is
    circularly pre-padded by ``P`` columns (not tiled 3x) and the offsets come from :func:`circular_offsets`.
    The honest baseline of the fast backend (same result as :func:`deform_conv2d_reference` with ``wrap``)."""
    from torchvision.ops import deform_conv2d

    B = x.shape[0]
    Ho, Wo = offsets_wrapped.shape[-2:]
    xp = F.pad(x, (P, P, 0, 0), mode="circular")
    kw = weight.shape[-1]
    wo_big = (x.shape[-1] + 2 * P - dilation[1] * (kw - 1) - 1) // stride[1] + 1
    off = offsets_wrapped.to(x.dtype)
    m = None if mask is None else mask.to(x.dtype)
    if wo_big != Wo:  # padding[1] == 0: one extra column each side, cropped below
        off = F.pad(off, (0, wo_big - Wo))
        m = None if m is None else F.pad(m, (0, wo_big - Wo))
    off = off.expand(B, -1, -1, -1)
    m = None if m is None else m.expand(B, -1, -1, -1)
    y = deform_conv2d(xp, off, weight, bias, stride=stride, padding=(padding[0], 0), dilation=dilation, mask=m)
    return y[..., :Wo] if wo_big != Wo else y
