/* The fixed-offset convolution on the CPU (float32): the CPU kernel of the op omnidl::fixed_offset_conv2d
 * (omnidl/ops/fixed_offset_conv.py).
 *
 * Output position p (row-major over Ho x Wo) has K taps; tap row r = p * K + t samples the input at pos[r] = (y, x)
 * (input pixels, float64) with weight mask[r]. Its four bilinear corners are computed here from the position, as
 * deform_conv2d does: a corner outside the image reads zero; with `wrap` the column is taken modulo W (a 360 degree
 * image). For a block of m output positions the taps are interpolated into a column block A (m, K*C), which stays
 * in the core's cache, and multiplied at once by Wm (K*C, cout); the full (P, K*C) column matrix never exists.
 *
 * Layouts (row-major): x (H*W, C) channels-last input rows of one image, images x_img floats apart; wt (cout, K*C),
 * wt[o][t*C + c] = weight[o][c][t] (the weight in channels-last order: a channels-last weight as it lies), i.e.
 * Wm = wt^T; gw (K*C, cout) is accumulated into (+=). out, gout and gx are the layout of the input tensor: with
 * `planes` 0 channels-last rows ((P, cout) per image for out and gout, (H*W, C) for gx, accumulated into), with
 * `planes` 1 channel planes (NCHW: (cout, P) and (C, H*W) per image; gx written, not accumulated). The kernel
 * writes and reads the planes itself (a block's output transposed from the cache, a block of gout read in
 * place), so a network in NCHW memory pays no layout copies for them.
 *
 * Threads: each call is one OpenMP parallel region of `nthreads` threads on PyTorch's own team (libgomp is the copy
 * PyTorch loaded), split by output positions, or for few positions (small deep maps) by output channels.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#include "gemm_tiles.h"

#if !HAVE_KERNEL
extern void sgemm_(const char *ta, const char *tb, const int *m, const int *n, const int *k, const float *alpha,
                   const float *a, const int *lda, const float *b, const int *ldb, const float *beta, float *c,
                   const int *ldc);
/* MKL's per-thread thread count (weak: absent from other BLAS libraries): one BLAS thread inside our own threads */
extern int MKL_Set_Num_Threads_Local(int n) __attribute__((weak));

/* row-major c (m, n) = beta c + op(a) op(b), through the column-major BLAS (a row-major matrix is its transpose) */
static void blas_rows(char ta, char tb, int m, int n, int k, float beta, const float *a, int lda, const float *b,
                      int ldb, float *c, int ldc) {
    const float one = 1.0f;
    sgemm_(&tb, &ta, &n, &m, &k, &one, b, &ldb, a, &lda, &beta, c, &ldc);
}
#endif

/* where the taps sample: positions (rows, 2) as (y, x) and mask (rows) of one image size H x W */
typedef struct {
    const double *pos, *mask;
    int H, W, wrap;
    double inv_w;  /* 1 / W */
} taps_t;

/* a coordinate this far from 0 (or not finite) is no position: beyond it floor() and the integer conversion would
 * not be exact */
#define FAR_COORD 4.5e15

/* the four bilinear corners of tap row r: flat input pixels idx[j] and weights q[j]; q[j] = 0 for a corner that
 * reads zero (outside the image, a zero weight, a non-finite position). The weights are computed in float64 and
 * rounded once; with wrap the corner columns are taken modulo W. */
static inline void corners(const taps_t *tp, int64_t r, int64_t idx[4], float q[4]) {
    const double y = tp->pos[2 * r], x = tp->pos[2 * r + 1], m = tp->mask[r];
    for (int j = 0; j < 4; ++j) {
        idx[j] = 0;
        q[j] = 0.0f;
    }
    if (!(fabs(y) < FAR_COORD && fabs(x) < FAR_COORD && fabs(m) <= 1e300)) return;
    const double y0 = floor(y), x0 = floor(x), ly = y - y0, lx = x - x0;
    const double w[4] = {(1 - ly) * (1 - lx) * m, (1 - ly) * lx * m, ly * (1 - lx) * m, ly * lx * m};
    const int64_t iy = (int64_t)y0, W = tp->W;
    int64_t cx[2] = {(int64_t)x0, (int64_t)x0 + 1};
    int okx[2];
    if (tp->wrap) {  /* x0 mod W without a division per corner */
        int64_t c = (int64_t)x0 - (int64_t)floor(x0 * tp->inv_w) * W;
        while (c >= W) c -= W;
        while (c < 0) c += W;
        cx[0] = c;
        cx[1] = c + 1 == W ? 0 : c + 1;
        okx[0] = okx[1] = 1;
    } else {
        okx[0] = cx[0] >= 0 && cx[0] < W;
        okx[1] = cx[1] >= 0 && cx[1] < W;
    }
    for (int j = 0; j < 4; ++j) {
        const int64_t cy = iy + (j >> 1);
        if (w[j] == 0.0 || cy < 0 || cy >= tp->H || !okx[j & 1]) continue;
        idx[j] = cy * W + cx[j & 1];
        q[j] = (float)w[j];
    }
}

/* A[(r - r0) * C + c] = sum_j q[j] * x[idx[j] * C + c] for tap rows r in [r0, r1); corners of weight 0 are not read,
 * so a non-finite pixel reaches only the taps that sample it */
static void gather(const float *x, int C, const taps_t *tp, int64_t r0, int64_t r1, float *A) {
    int64_t i[4];
    float q[4];
    for (int64_t r = r0; r < r1; ++r) {
        corners(tp, r, i, q);
        float *a = A + (r - r0) * C;
#if defined(__AVX512F__)
        const __mmask16 tail = (__mmask16)((1u << (C % 16)) - 1u);
        const int whole = C - C % 16;
        const __m512 w0 = _mm512_set1_ps(q[0]), w1 = _mm512_set1_ps(q[1]), w2 = _mm512_set1_ps(q[2]);
        const __m512 w3 = _mm512_set1_ps(q[3]);
        for (int c = 0; c < C; c += 16) {
            const __mmask16 m = c < whole ? (__mmask16)0xFFFF : tail;
            __m512 v = _mm512_setzero_ps();
            if (q[0] != 0.0f) v = _mm512_mul_ps(w0, _mm512_maskz_loadu_ps(m, x + i[0] * C + c));
            if (q[1] != 0.0f) v = _mm512_fmadd_ps(w1, _mm512_maskz_loadu_ps(m, x + i[1] * C + c), v);
            if (q[2] != 0.0f) v = _mm512_fmadd_ps(w2, _mm512_maskz_loadu_ps(m, x + i[2] * C + c), v);
            if (q[3] != 0.0f) v = _mm512_fmadd_ps(w3, _mm512_maskz_loadu_ps(m, x + i[3] * C + c), v);
            _mm512_mask_storeu_ps(a + c, m, v);
        }
#else
        if (q[0] != 0.0f && q[1] != 0.0f && q[2] != 0.0f && q[3] != 0.0f) {
            const float *x0 = x + i[0] * C, *x1 = x + i[1] * C, *x2 = x + i[2] * C, *x3 = x + i[3] * C;
            for (int c = 0; c < C; ++c) a[c] = q[0] * x0[c] + q[1] * x1[c] + q[2] * x2[c] + q[3] * x3[c];
            continue;
        }
        memset(a, 0, sizeof(float) * (size_t)C);
        for (int j = 0; j < 4; ++j) {
            if (q[j] == 0.0f) continue;
            const float *xj = x + i[j] * C;
            for (int c = 0; c < C; ++c) a[c] += q[j] * xj[c];
        }
#endif
    }
}

/* the adjoint of gather: gx[idx[j] * C + c] += q[j] * A[(r - r0) * C + c] for tap rows r in [r0, r1) */
static void scatter(float *gx, int C, const taps_t *tp, int64_t r0, int64_t r1, const float *A) {
    int64_t i[4];
    float q[4];
    for (int64_t r = r0; r < r1; ++r) {
        corners(tp, r, i, q);
        const float *a = A + (r - r0) * C;
        for (int j = 0; j < 4; ++j) {
            if (q[j] == 0.0f) continue;
            float *g = gx + i[j] * C;
            for (int c = 0; c < C; ++c) g[c] += q[j] * a[c];
        }
    }
}

/* which products run: 2 this file's AVX-512 kernel, 1 its AVX2/FMA kernel, 0 the BLAS sgemm_ */
int omnidl_foc_kernel(void) {
#if defined(__AVX512F__)
    return 2;
#else
    return HAVE_KERNEL;
#endif
}

/* 1 when built with OpenMP (the calls run on several threads), else 0 */
int omnidl_foc_openmp(void) {
#ifdef _OPENMP
    return 1;
#else
    return 0;
#endif
}

static int64_t min64(int64_t a, int64_t b) { return a < b ? a : b; }

/* start of thread t's share of `total` (t == nt gives the end) */
static int64_t span_edge(int64_t total, int t, int nt) { return t >= nt ? total : total * t / nt; }

/* this thread's number and the team's size (0 and 1 without OpenMP) */
static void team(int *t, int *nt) {
#ifdef _OPENMP
    *t = omp_get_thread_num();
    *nt = omp_get_num_threads();
#else
    *t = 0;
    *nt = 1;
#endif
}

/* few positions for the threads (small deep maps): split the output channels' panels instead */
static int split_channels(int64_t total, int64_t block, int nthreads, int cout) {
    return HAVE_KERNEL && nthreads > 1 && total < 2 * block * nthreads && (cout + NR - 1) / NR >= nthreads;
}

/* thread t's output channels [*c0, *c1) when the panels are split among nt threads */
static void channel_share(int cout, int t, int nt, int *c0, int *c1) {
    const int panels = (cout + NR - 1) / NR;
    *c0 = NR * (panels * t / nt);
    *c1 = (int)min64(cout, NR * (panels * (t + 1) / nt));
}

/* Forward of B images: out = bias + gathered taps @ Wm, in blocks of `block` positions (`planes`: out is NCHW,
 * each block computed into the thread's buffer, then written transposed). Returns 0, or 1 when a buffer cannot be
 * allocated. */
int omnidl_foc_forward(const float *x, int64_t x_img, int C, int H, int W, const double *pos, const double *mask,
                       int wrap, int K, int64_t P, int B, const float *wt, int cout, const float *bias, float *out,
                       int planes, int64_t block, int nthreads) {
    const taps_t tp = {pos, mask, H, W, wrap, 1.0 / W};
    const int KC = K * C;
    const int64_t total = (int64_t)B * P;
    const int by_channels = split_channels(total, block, nthreads, cout);
    int err = 0;
#if HAVE_KERNEL
    float *wp = (float *)malloc(sizeof(float) * (size_t)packed_floats(KC, cout));
    if (!wp) return 1;
#endif
    (void)nthreads;  /* unused without OpenMP */
#pragma omp parallel num_threads(nthreads) reduction(| : err)
    {
#if HAVE_KERNEL
        pack_b(KC, cout, wt, 1, KC, wp);  /* Wm = wt^T; an implicit barrier: every panel is packed before use */
#endif
        int t, nt;
        team(&t, &nt);
        int64_t s0 = 0, s1 = total;
        int c0 = 0, c1 = cout;
        if (by_channels) {
            channel_share(cout, t, nt, &c0, &c1);
        } else {
            s0 = span_edge(total, t, nt);
            s1 = span_edge(total, t + 1, nt);
        }
        const int nc = c1 - c0;
        float *A = NULL, *ob = NULL;
        if (s1 > s0 && nc > 0 && !(A = (float *)malloc(sizeof(float) * (size_t)(block * KC)))) err = 1;
        if (A && planes && !(ob = (float *)malloc(sizeof(float) * (size_t)(block * nc)))) err = 1;
#if !HAVE_KERNEL
        const int prev = MKL_Set_Num_Threads_Local ? MKL_Set_Num_Threads_Local(1) : -1;
#endif
        for (int64_t s = s0; A && (ob || !planes) && s < s1;) {
            const int64_t b = s / P, p = s % P;
            const int m = (int)min64(block, min64(s1 - s, P - p));
            float *o = planes ? ob : out + (b * P + p) * cout + c0;  /* rows (m, nc), leading dimension ldo */
            const int64_t ldo = planes ? nc : cout;
            gather(x + b * x_img, C, &tp, p * K, (p + m) * K, A);
#if HAVE_KERNEL  /* o (m, c1 - c0) = A (m, KC) Wm[:, c0:c1] + bias[c0:c1] */
            gemm_packed(m, nc, KC, A, KC, 1, wp + (int64_t)(c0 / NR) * KC * NR, o, ldo, 0, bias ? bias + c0 : NULL);
#else
            if (bias)
                for (int i = 0; i < m; ++i) memcpy(o + (int64_t)i * ldo, bias, sizeof(float) * (size_t)cout);
            blas_rows('N', 'T', m, cout, KC, bias ? 1.0f : 0.0f, A, KC, wt, KC, o, (int)ldo);
#endif
            if (planes)  /* the block's rows, transposed into the channel planes while in the cache */
                for (int c = 0; c < nc; ++c) {
                    float *dst = out + (b * cout + c0 + c) * P + p;
                    for (int i = 0; i < m; ++i) dst[i] = ob[(int64_t)i * nc + c];
                }
            s += m;
        }
#if !HAVE_KERNEL
        if (MKL_Set_Num_Threads_Local && prev >= 0) MKL_Set_Num_Threads_Local(prev);
#endif
        free(A);
        free(ob);
    }
#if HAVE_KERNEL
    free(wp);
#endif
    return err;
}

/* gout's rows of positions [p, p + m) of one image (`g`: the image's gout): in place for rows (`planes` 0), else the
 * block of the channel planes copied into `buf` (m, cout), channel by channel. Read in place, the planes' values of
 * one position lie P floats apart, a power of two for most maps: every one in the same L1 set. */
static const float *gout_rows(const float *g, int planes, int64_t P, int64_t p, int m, int cout, float *buf) {
    if (!planes) return g + p * cout;
    for (int c = 0; c < cout; ++c) {
        const float *src = g + c * P + p;
        for (int r = 0; r < m; ++r) buf[(int64_t)r * cout + c] = src[r];
    }
    return buf;
}

/* The input rows (flat over the batch: b * pixels + pixel) that positions [s0, s1) of the batch touch: [*lo, *hi) */
static void touched_rows(const taps_t *tp, int K, int64_t P, int64_t s0, int64_t s1, int64_t *lo, int64_t *hi) {
    const int64_t pixels = (int64_t)tp->H * tp->W;
    int64_t i[4];
    float q[4];
    *lo = INT64_MAX;
    *hi = 0;
    for (int64_t s = s0; s < s1; ++s) {
        const int64_t b = s / P, p = s % P;
        for (int64_t r = p * K; r < (p + 1) * K; ++r) {
            corners(tp, r, i, q);
            for (int j = 0; j < 4; ++j) {
                if (q[j] == 0.0f) continue;
                if (b * pixels + i[j] < *lo) *lo = b * pixels + i[j];
                if (b * pixels + i[j] + 1 > *hi) *hi = b * pixels + i[j] + 1;
            }
        }
    }
    if (*hi <= *lo) *lo = *hi = 0;
}

/* Backward of B images, each thread over its share of the positions in two passes: gw += A^T gout on re-gathered
 * taps, then gx += S^T (gout Wm^T) scattered straight from the block. Thread 0 accumulates into gw/gx, the others
 * into private copies (of gx only the band of input rows their positions touch), added in at the end. With few
 * positions the weight gradient is split by output channels instead, straight into gw. gx (B images of x_img
 * floats) or gw (K*C, cout) may be NULL when not needed. With `planes`, gout is read and gx written as channel
 * planes (the scatter accumulates into channels-last rows of this call's own, transposed into gx at the end).
 * Returns 0, or 1 when a buffer cannot be allocated. */
int omnidl_foc_backward(const float *x, int64_t x_img, int C, int H, int W, const double *pos, const double *mask,
                        int wrap, int K, int64_t P, int B, const float *wt, int cout, const float *gout, float *gx,
                        float *gw, int planes, int64_t block, int nthreads) {
    const taps_t tp = {pos, mask, H, W, wrap, 1.0 / W};
    const int KC = K * C;
    const int64_t total = (int64_t)B * P;
    const int gw_by_channels = split_channels(total, block, nthreads, cout);
    float *gxr = planes && gx ? (float *)calloc((size_t)(B * x_img), sizeof(float)) : gx;  /* rows accumulated */
    float **pgw = (float **)calloc((size_t)nthreads, sizeof(float *));
    float **pgx = (float **)calloc((size_t)nthreads, sizeof(float *));
    int64_t *lo = (int64_t *)calloc((size_t)nthreads, sizeof(int64_t));
    int64_t *hi = (int64_t *)calloc((size_t)nthreads, sizeof(int64_t));
#if HAVE_KERNEL
    float *wtp = gx ? (float *)malloc(sizeof(float) * (size_t)packed_floats(cout, KC)) : NULL;  /* Wm^T panels */
    int err = !pgw || !pgx || !lo || !hi || (gx && !wtp) || (gx && !gxr);
#else
    int err = !pgw || !pgx || !lo || !hi || (gx && !gxr);
#endif
    if (!err) {
#pragma omp parallel num_threads(nthreads) reduction(| : err)
        {
#if HAVE_KERNEL
            if (gx) pack_b(cout, KC, wt, KC, 1, wtp);  /* Wm^T = wt; an implicit barrier follows */
#endif
            int t, nt;
            team(&t, &nt);
            const int64_t s0 = span_edge(total, t, nt), s1 = span_edge(total, t + 1, nt);
            float *A = (float *)malloc(sizeof(float) * (size_t)(block * KC));
            float *gb = planes ? (float *)malloc(sizeof(float) * (size_t)(block * cout)) : NULL;
#if HAVE_KERNEL
            float *gp = (float *)malloc(sizeof(float) * (size_t)packed_floats(block, cout));
            int ok = A && gp && (gb || !planes);
#else
            int ok = A && (gb || !planes);
#endif
            /* thread 0 writes the results directly, the others private copies (none for an empty share) */
            float *mygw = t == 0 || gw_by_channels ? gw : NULL, *mygx = t == 0 ? gxr : NULL;
            int64_t mylo = 0, myhi = 0;
            if (ok && gw && !gw_by_channels && t > 0 && s1 > s0)
                ok = (mygw = (float *)calloc((size_t)KC * (size_t)cout, sizeof(float))) != NULL;
            if (ok && gxr && t > 0 && s1 > s0) {
                touched_rows(&tp, K, P, s0, s1, &mylo, &myhi);
                if (myhi > mylo) ok = (mygx = (float *)calloc((size_t)((myhi - mylo) * C), sizeof(float))) != NULL;
            }
            if (!ok) err = 1;
            if (ok) {
#if !HAVE_KERNEL
                const int prev = MKL_Set_Num_Threads_Local ? MKL_Set_Num_Threads_Local(1) : -1;
#endif
                const int64_t w0 = gw_by_channels ? 0 : s0, w1 = gw_by_channels ? total : s1;
                int c0 = 0, c1 = cout;
                if (gw_by_channels) channel_share(cout, t, nt, &c0, &c1);
                for (int64_t s = w0; mygw && c1 > c0 && s < w1;) {
                    const int64_t b = s / P, p = s % P;
                    const int m = (int)min64(block, min64(w1 - s, P - p));
                    const float *g = gout_rows(gout + b * P * cout, planes, P, p, m, cout, gb);
                    gather(x + b * x_img, C, &tp, p * K, (p + m) * K, A);
#if HAVE_KERNEL  /* gw[:, c0:c1] (KC, cout) += A^T g[:, c0:c1] */
                    for (int q = 0; q < (c1 - c0 + NR - 1) / NR; ++q) {  /* this thread's panels of g, packed */
                        const int nr = c1 - c0 - q * NR < NR ? c1 - c0 - q * NR : NR;
                        float *d = gp + (int64_t)q * m * NR;
                        for (int r = 0; r < m; ++r) {
                            int j = 0;
                            for (; j < nr; ++j) d[r * NR + j] = g[(int64_t)r * cout + c0 + q * NR + j];
                            for (; j < NR; ++j) d[r * NR + j] = 0.0f;
                        }
                    }
                    gemm_packed(KC, c1 - c0, m, A, 1, KC, gp, mygw + c0, cout, 1, NULL);
#else
                    blas_rows('T', 'N', KC, cout, m, 1.0f, A, KC, g, cout, mygw, cout);
#endif
                    s += m;
                }
                /* input gradient rows of image b start at base + b * x_img (private copies are offset by mylo) */
                float *base = (t == 0 || !mygx) ? mygx : mygx - mylo * C;
                for (int64_t s = s0; base && s < s1;) {
                    const int64_t b = s / P, p = s % P;
                    const int m = (int)min64(block, min64(s1 - s, P - p));
                    const float *g = gout_rows(gout + b * P * cout, planes, P, p, m, cout, gb);
#if HAVE_KERNEL
                    gemm_packed(m, KC, cout, g, cout, 1, wtp, A, KC, 0, NULL);  /* A (m, KC) = g Wm^T */
#else
                    blas_rows('N', 'N', m, KC, cout, 0.0f, g, cout, wt, KC, A, KC);
#endif
                    scatter(base + b * x_img, C, &tp, p * K, (p + m) * K, A);
                    s += m;
                }
#if !HAVE_KERNEL
                if (MKL_Set_Num_Threads_Local && prev >= 0) MKL_Set_Num_Threads_Local(prev);
#endif
            }
            if (t > 0) {
                pgw[t] = gw_by_channels ? NULL : mygw;
                pgx[t] = mygx;
                lo[t] = mylo;
                hi[t] = myhi;
            }
#pragma omp barrier
            for (int k = 1; k < nt; ++k) {  /* add the private copies in, every thread on a slice of each */
                if (pgw[k]) {
                    const float *src = pgw[k];
#pragma omp for schedule(static)
                    for (int64_t e = 0; e < (int64_t)KC * cout; ++e) gw[e] += src[e];
                }
                if (pgx[k]) {
                    const float *src = pgx[k];
                    float *dst = gxr + lo[k] * C;
#pragma omp for schedule(static)
                    for (int64_t e = 0; e < (hi[k] - lo[k]) * C; ++e) dst[e] += src[e];
                }
            }
            if (planes && gx) {  /* the rows into gx's channel planes, 64 pixels (a block in the cache) at a time */
                const int64_t HW = x_img / C, blocks = (HW + 63) / 64;
#pragma omp for schedule(static)
                for (int64_t e = 0; e < B * blocks; ++e) {
                    const int64_t b = e / blocks, q0 = (e % blocks) * 64, q1 = min64(HW, q0 + 64);
                    const float *src = gxr + b * x_img;
                    for (int c = 0; c < C; ++c) {
                        float *dst = gx + (b * C + c) * HW;
                        for (int64_t q = q0; q < q1; ++q) dst[q] = src[q * C + c];
                    }
                }
            }
            free(A);
            free(gb);
#if HAVE_KERNEL
            free(gp);
#endif
            if (t > 0) {
                if (!gw_by_channels) free(mygw);
                free(mygx);
            }
        }
    }
#if HAVE_KERNEL
    free(wtp);
#endif
    if (gxr != gx) free(gxr);
    free(pgw);
    free(pgx);
    free(lo);
    free(hi);
    return err;
}
