"""Triton kernels of :class:`~omnidl.nn.ProjectedConv2d`'s fused CUDA backend (driven by :mod:`.triton_conv`).

Notation: the input ``x (B, C, H, W)`` is read at flat pixel offsets (``x.stride(2) == W * x.stride(3)``: NCHW and
channels-last alike), ``P = Ho * Wo`` output positions, ``K = kh * kw`` taps, ``N`` output channels. The plan gives,
per tap ``k`` and position ``p``, four bilinear corners: ``idx (K, 4, P)`` (int32 flat input pixels) and ``wt (K, 4,
P)`` (bilinear weight times the tap mask; 0 where a corner reads zero). Every product accumulates in float32 through
``tl.dot`` with ``PREC`` ``"tf32"`` or ``"ieee"`` (the caller follows ``nn.Conv2d``'s policy).

* :func:`fwd` -- ``y[b, n, p] = bias[n] + sum_{k, c} W[n, c, k] * sum_j wt[k, j, p] * x[b, c, idx[k, j, p]]``: the
  gathered columns live only in registers (implicit GEMM; nothing of size ``C*K*P`` is written);
* :func:`gcols` -- the columns' gradient ``G[b, p, k, c] = sum_n gy[b, n, p] * W[n, c, k]`` (a GEMM);
* :func:`sell` -- the input gradient as a gather: ``gx[b, c, q] = sum_e v[e, q] * G[b, r[e, q], c]`` over the plan's
  transpose in sliced ELL form (the entries ``(r = p*K + k, v)`` of input pixel ``q``, tiles of ``BLOCK_Q`` pixels
  padded to their longest list): no atomics, so the result is deterministic;
* :func:`wgrad` -- ``gW[n, c, k] = sum_{b, p} gy[b, n, p] * cols[b, p, k, c]`` (columns gathered again) and the bias
  gradient, as ``S`` partial sums over row ranges (summed by the caller: deterministic).

Imported on first use by :mod:`.triton_conv` (Triton is an optional dependency). With ``TRITON_INTERPRET=1`` in the
environment before Triton is imported, the kernels run in Triton's interpreter on CPU tensors (the tests use it).
"""
import triton
import triton.language as tl


@triton.jit
def _gather(x, o0, o1, o2, o3, w0, w1, w2, w3, cc, mc, mp, sxc, CL: tl.constexpr, PIXELS_FIRST: tl.constexpr):
    """``sum_j w_j * x[o_j + c * sxc]`` for pixel offsets ``o_j`` (BLOCK_P) and channels ``cc`` (BLOCK_C): the
    tile ``(BLOCK_P, BLOCK_C)`` if ``PIXELS_FIRST`` else ``(BLOCK_C, BLOCK_P)``. It is built with the memory's
    contiguous axis last (``CL``: channels innermost), where the threads of a warp lie, and transposed after."""
    if CL:
        m = mp[:, None] & mc[None, :]
        c = cc[None, :] * sxc
        a = w0[:, None] * tl.load(x + o0[:, None] + c, mask=m & (w0 != 0)[:, None], other=0.0)
        a += w1[:, None] * tl.load(x + o1[:, None] + c, mask=m & (w1 != 0)[:, None], other=0.0)
        a += w2[:, None] * tl.load(x + o2[:, None] + c, mask=m & (w2 != 0)[:, None], other=0.0)
        a += w3[:, None] * tl.load(x + o3[:, None] + c, mask=m & (w3 != 0)[:, None], other=0.0)
        if not PIXELS_FIRST:
            a = tl.trans(a)
    else:
        m = mc[:, None] & mp[None, :]
        c = cc[:, None] * sxc
        a = w0[None, :] * tl.load(x + c + o0[None, :], mask=m & (w0 != 0)[None, :], other=0.0)
        a += w1[None, :] * tl.load(x + c + o1[None, :], mask=m & (w1 != 0)[None, :], other=0.0)
        a += w2[None, :] * tl.load(x + c + o2[None, :], mask=m & (w2 != 0)[None, :], other=0.0)
        a += w3[None, :] * tl.load(x + c + o3[None, :], mask=m & (w3 != 0)[None, :], other=0.0)
        if PIXELS_FIRST:
            a = tl.trans(a)
    return a


@triton.jit
def _corners(ib, wb, P, rows, live, sxp, base):
    """Tap ``k``'s four corners at positions ``rows`` (``ib``/``wb``: the tap's ``(4, P)`` block of ``idx``/``wt``):
    pixel offsets ``base + idx * sxp`` and weights (0 where not ``live``)."""
    o0 = base + tl.load(ib + rows, mask=live, other=0) * sxp
    o1 = base + tl.load(ib + P + rows, mask=live, other=0) * sxp
    o2 = base + tl.load(ib + 2 * P + rows, mask=live, other=0) * sxp
    o3 = base + tl.load(ib + 3 * P + rows, mask=live, other=0) * sxp
    w0 = tl.load(wb + rows, mask=live, other=0.0)
    w1 = tl.load(wb + P + rows, mask=live, other=0.0)
    w2 = tl.load(wb + 2 * P + rows, mask=live, other=0.0)
    w3 = tl.load(wb + 3 * P + rows, mask=live, other=0.0)
    return o0, o1, o2, o3, w0, w1, w2, w3


@triton.jit
def fwd(x, w, bias, idx, wt, y, C, N, P, K, sxb, sxc, sxp, swn, swc, swk, syb, syn, syp,
        HAS_BIAS: tl.constexpr, CL: tl.constexpr, PREC: tl.constexpr,
        BLOCK_P: tl.constexpr, BLOCK_N: tl.constexpr, BLOCK_C: tl.constexpr):
    pid_p = tl.program_id(0)
    pid_n = tl.program_id(1)
    b = tl.program_id(2)
    rp = pid_p * BLOCK_P + tl.arange(0, BLOCK_P)
    mp = rp < P
    rn = pid_n * BLOCK_N + tl.arange(0, BLOCK_N)
    mn = rn < N
    xb = x + b * sxb
    acc = tl.zeros((BLOCK_P, BLOCK_N), dtype=tl.float32)
    for k in range(K):
        o0, o1, o2, o3, w0, w1, w2, w3 = _corners(idx + k * 4 * P, wt + k * 4 * P, P, rp, mp, sxp, 0)
        for c0 in range(0, C, BLOCK_C):
            cc = c0 + tl.arange(0, BLOCK_C)
            mc = cc < C
            a = _gather(xb, o0, o1, o2, o3, w0, w1, w2, w3, cc, mc, mp, sxc, CL, True)
            wk = tl.load(w + cc[:, None] * swc + rn[None, :] * swn + k * swk, mask=mc[:, None] & mn[None, :],
                         other=0.0)
            acc = tl.dot(a, wk, acc, input_precision=PREC)
    if HAS_BIAS:
        acc += tl.load(bias + rn, mask=mn, other=0.0)[None, :]
    tl.store(y + b * syb + rp[:, None] * syp + rn[None, :] * syn, acc, mask=mp[:, None] & mn[None, :])


@triton.jit
def gcols(gy, w, out, C, N, P, K, sgb, sgn, sgp, swn, swc, swk, PREC: tl.constexpr,
          BLOCK_P: tl.constexpr, BLOCK_C: tl.constexpr, BLOCK_N: tl.constexpr):
    pid_p = tl.program_id(0)
    pid_c = tl.program_id(1)
    bk = tl.program_id(2)
    b = bk // K
    k = bk % K
    rp = pid_p * BLOCK_P + tl.arange(0, BLOCK_P)
    mp = rp < P
    cc = pid_c * BLOCK_C + tl.arange(0, BLOCK_C)
    mc = cc < C
    acc = tl.zeros((BLOCK_P, BLOCK_C), dtype=tl.float32)
    for n0 in range(0, N, BLOCK_N):
        rn = n0 + tl.arange(0, BLOCK_N)
        mn = rn < N
        g = tl.load(gy + b * sgb + rp[:, None] * sgp + rn[None, :] * sgn, mask=mp[:, None] & mn[None, :],
                    other=0.0)
        wk = tl.load(w + rn[:, None] * swn + cc[None, :] * swc + k * swk, mask=mn[:, None] & mc[None, :],
                     other=0.0)
        acc = tl.dot(g, wk, acc, input_precision=PREC)
    tl.store(out + ((b * P + rp[:, None]) * K + k) * C + cc[None, :], acc, mask=mp[:, None] & mc[None, :])


@triton.jit
def sell(g, rows, vals, tile_start, tile_len, gx, C, Q, PKC, sgxb, sgxc, sgxq,
         BLOCK_Q: tl.constexpr, BLOCK_C: tl.constexpr):
    t = tl.program_id(0)
    pid_c = tl.program_id(1)
    b = tl.program_id(2)
    rq = t * BLOCK_Q + tl.arange(0, BLOCK_Q)
    cc = pid_c * BLOCK_C + tl.arange(0, BLOCK_C)
    mc = cc < C
    start = tl.load(tile_start + t)
    n = tl.load(tile_len + t)
    gb = g + b * PKC
    acc = tl.zeros((BLOCK_Q, BLOCK_C), dtype=tl.float32)
    for e in range(0, n):
        off = start + e * BLOCK_Q + tl.arange(0, BLOCK_Q)
        r = tl.load(rows + off)
        v = tl.load(vals + off)
        acc += v[:, None] * tl.load(gb + r[:, None] * C + cc[None, :], mask=(v != 0)[:, None] & mc[None, :],
                                    other=0.0)
    tl.store(gx + b * sgxb + rq[:, None] * sgxq + cc[None, :] * sgxc, acc, mask=(rq < Q)[:, None] & mc[None, :])


@triton.jit
def wgrad(x, idx, wt, gy, part, C, N, P, K, R, ROWS, CB, sxb, sxc, sxp, sgb, sgn, sgp,
          HAS_BIAS: tl.constexpr, CL: tl.constexpr, PREC: tl.constexpr,
          BLOCK_R: tl.constexpr, BLOCK_C: tl.constexpr, BLOCK_N: tl.constexpr):
    pid_kc = tl.program_id(0)
    pid_n = tl.program_id(1)
    s = tl.program_id(2)
    k = pid_kc // CB
    pc = pid_kc % CB
    cc = pc * BLOCK_C + tl.arange(0, BLOCK_C)
    mc = cc < C
    rn = pid_n * BLOCK_N + tl.arange(0, BLOCK_N)
    mn = rn < N
    acc = tl.zeros((BLOCK_C, BLOCK_N), dtype=tl.float32)
    bacc = tl.zeros((BLOCK_N,), dtype=tl.float32)
    for r0 in range(s * ROWS, s * ROWS + ROWS, BLOCK_R):
        rr = r0 + tl.arange(0, BLOCK_R)
        mr = rr < R
        b = rr // P
        p = rr % P
        o0, o1, o2, o3, w0, w1, w2, w3 = _corners(idx + k * 4 * P, wt + k * 4 * P, P, p, mr, sxp, b * sxb)
        aT = _gather(x, o0, o1, o2, o3, w0, w1, w2, w3, cc, mc, mr, sxc, CL, False)      # (BLOCK_C, BLOCK_R)
        gt = tl.load(gy + b[:, None] * sgb + p[:, None] * sgp + rn[None, :] * sgn, mask=mr[:, None] & mn[None, :],
                     other=0.0)                                                       # (BLOCK_R, BLOCK_N)
        acc = tl.dot(aT, gt, acc, input_precision=PREC)
        if HAS_BIAS:
            bacc += tl.sum(gt, 0)
    base = part + s * (N * C * K + N)
    tl.store(base + rn[None, :] * (C * K) + cc[:, None] * K + k, acc, mask=mc[:, None] & mn[None, :])
    if HAS_BIAS:
        if (k == 0) & (pc == 0):
            tl.store(base + N * C * K + rn, bacc, mask=mn)
