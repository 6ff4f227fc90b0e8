/* Register-blocked float32 products for the fixed-offset convolution (fixed_offset_conv.c).
 *
 * c (m, n) (+)= a (m, k) b (k, n) (+ bias), a read where it lies (a[i * rs + p * cs]), b packed into panels of NR
 * columns (pack_b). On x86-64 with AVX-512 a 12x32 tile kernel, with AVX2/FMA a 6x16 one (HAVE_KERNEL 1); elsewhere
 * HAVE_KERNEL is 0 and the caller uses the BLAS sgemm_ that libtorch_cpu exports.
 */
#ifndef OMNIDL_GEMM_TILES_H
#define OMNIDL_GEMM_TILES_H

#include <stdint.h>
#include <string.h>

#if defined(__AVX512F__)
#include <immintrin.h>
#define MR 12
#define NR 32
#define KC_BLOCK 256
/* k-steps ahead at which a panel's rows are prefetched on its first pass: a weight streamed from memory past few
 * rows of a (a deep layer on a small map) waits on its loads otherwise */
#define B_PREFETCH 16

/* c (mr, nr) (+)= a (mr, k) b (k, 32) (+ bias), b one packed panel (zero beyond nr); 24 zmm accumulators, rows
 * beyond mr re-read row 0 and are not stored. `accumulate`: add to c. `bias` (nr values or NULL) is added to every
 * row. `prefetch`: the panel's rows B_PREFETCH k-steps ahead are prefetched. */
static void kernel_tile(int k, const float *a, int64_t rs, int64_t cs, const float *b, float *c, int64_t ldc,
                        int accumulate, int mr, int nr, const float *bias, int prefetch) {
    __m512 acc[MR][2];
    int64_t off[MR];
    for (int i = 0; i < MR; ++i) {
        acc[i][0] = acc[i][1] = _mm512_setzero_ps();
        off[i] = i < mr ? i * rs : 0;
    }
    for (int p = 0; p < k; ++p) {
        const __m512 b0 = _mm512_loadu_ps(b + NR * p), b1 = _mm512_loadu_ps(b + NR * p + 16);
        if (prefetch) { /* a hint: never faults past the panel's end */
            _mm_prefetch((const char *)(b + NR * (p + B_PREFETCH)), _MM_HINT_T0);
            _mm_prefetch((const char *)(b + NR * (p + B_PREFETCH) + 16), _MM_HINT_T0);
        }
        const float *ap = a + p * cs;
#pragma GCC unroll 12
        for (int i = 0; i < MR; ++i) {
            const __m512 t = _mm512_set1_ps(ap[off[i]]);
            acc[i][0] = _mm512_fmadd_ps(t, b0, acc[i][0]);
            acc[i][1] = _mm512_fmadd_ps(t, b1, acc[i][1]);
        }
    }
    const __mmask16 m0 = nr >= 16 ? (__mmask16)0xFFFF : (__mmask16)((1u << nr) - 1u);
    const __mmask16 m1 = nr >= 32 ? (__mmask16)0xFFFF : nr <= 16 ? (__mmask16)0 : (__mmask16)((1u << (nr - 16)) - 1u);
    const __m512 bias0 = bias ? _mm512_maskz_loadu_ps(m0, bias) : _mm512_setzero_ps();
    const __m512 bias1 = bias ? _mm512_maskz_loadu_ps(m1, bias + 16) : _mm512_setzero_ps();
    for (int i = 0; i < mr; ++i) {
        float *ci = c + i * ldc;
        __m512 r0 = _mm512_add_ps(acc[i][0], bias0), r1 = _mm512_add_ps(acc[i][1], bias1);
        if (accumulate) {
            r0 = _mm512_add_ps(r0, _mm512_maskz_loadu_ps(m0, ci));
            r1 = _mm512_add_ps(r1, _mm512_maskz_loadu_ps(m1, ci + 16));
        }
        _mm512_mask_storeu_ps(ci, m0, r0);
        _mm512_mask_storeu_ps(ci + 16, m1, r1);
    }
}
#define HAVE_KERNEL 1

#elif defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
#define MR 6
#define NR 16
#define KC_BLOCK 256

/* c (mr, nr) (+)= a (mr, k) b (k, 16) (+ bias); as the AVX-512 kernel's (no prefetch). Twelve named ymm
 * accumulators, so that they stay in registers. */
static void kernel_tile(int k, const float *a, int64_t rs, int64_t cs, const float *b, float *c, int64_t ldc,
                        int accumulate, int mr, int nr, const float *bias, int prefetch) {
    (void)prefetch;
    __m256 c00 = _mm256_setzero_ps(), c01 = c00, c10 = c00, c11 = c00, c20 = c00, c21 = c00;
    __m256 c30 = c00, c31 = c00, c40 = c00, c41 = c00, c50 = c00, c51 = c00;
    const float *a0 = a, *a1 = a + (mr > 1 ? rs : 0), *a2 = a + (mr > 2 ? 2 * rs : 0);
    const float *a3 = a + (mr > 3 ? 3 * rs : 0), *a4 = a + (mr > 4 ? 4 * rs : 0), *a5 = a + (mr > 5 ? 5 * rs : 0);
    for (int p = 0; p < k; ++p) {
        const __m256 b0 = _mm256_loadu_ps(b + 16 * p), b1 = _mm256_loadu_ps(b + 16 * p + 8);
        const int64_t o = p * cs;
        __m256 t = _mm256_broadcast_ss(a0 + o);
        c00 = _mm256_fmadd_ps(t, b0, c00); c01 = _mm256_fmadd_ps(t, b1, c01);
        t = _mm256_broadcast_ss(a1 + o);
        c10 = _mm256_fmadd_ps(t, b0, c10); c11 = _mm256_fmadd_ps(t, b1, c11);
        t = _mm256_broadcast_ss(a2 + o);
        c20 = _mm256_fmadd_ps(t, b0, c20); c21 = _mm256_fmadd_ps(t, b1, c21);
        t = _mm256_broadcast_ss(a3 + o);
        c30 = _mm256_fmadd_ps(t, b0, c30); c31 = _mm256_fmadd_ps(t, b1, c31);
        t = _mm256_broadcast_ss(a4 + o);
        c40 = _mm256_fmadd_ps(t, b0, c40); c41 = _mm256_fmadd_ps(t, b1, c41);
        t = _mm256_broadcast_ss(a5 + o);
        c50 = _mm256_fmadd_ps(t, b0, c50); c51 = _mm256_fmadd_ps(t, b1, c51);
    }
    __m256 r[MR][2] = {{c00, c01}, {c10, c11}, {c20, c21}, {c30, c31}, {c40, c41}, {c50, c51}};
    const __m256 bias0 = bias && nr == NR ? _mm256_loadu_ps(bias) : _mm256_setzero_ps();
    const __m256 bias1 = bias && nr == NR ? _mm256_loadu_ps(bias + 8) : _mm256_setzero_ps();
    for (int i = 0; i < mr; ++i) {
        float *ci = c + i * ldc;
        if (nr == NR) {
            __m256 r0 = _mm256_add_ps(r[i][0], bias0), r1 = _mm256_add_ps(r[i][1], bias1);
            if (accumulate) {
                r0 = _mm256_add_ps(r0, _mm256_loadu_ps(ci));
                r1 = _mm256_add_ps(r1, _mm256_loadu_ps(ci + 8));
            }
            _mm256_storeu_ps(ci, r0);
            _mm256_storeu_ps(ci + 8, r1);
        } else {
            float tmp[NR];
            _mm256_storeu_ps(tmp, r[i][0]);
            _mm256_storeu_ps(tmp + 8, r[i][1]);
            for (int j = 0; j < nr; ++j) ci[j] = tmp[j] + (bias ? bias[j] : 0.0f) + (accumulate ? ci[j] : 0.0f);
        }
    }
}
#define HAVE_KERNEL 1

#else
#define HAVE_KERNEL 0
#define NR 16
#endif

#if HAVE_KERNEL
/* panels of b held in L2 at once: below this size each MR-row sliver of a runs against every panel (rows outer),
 * otherwise each panel stays in L1 while every sliver runs against it (panels outer) */
#define B_RESIDENT (192 * 1024)

/* c (m, n) (+)= a (m, k) b (k, n) (+ bias), b packed by pack_b (k rows); `bias` is added with the first chunk of k */
static void gemm_packed(int m, int n, int k, const float *a, int64_t rs, int64_t cs, const float *bp, float *c,
                        int64_t ldc, int accumulate, const float *bias) {
    const int panels = (n + NR - 1) / NR, slivers = (m + MR - 1) / MR;
    for (int p0 = 0; p0 < k; p0 += KC_BLOCK) {
        const int kb = k - p0 < KC_BLOCK ? k - p0 : KC_BLOCK;
        const int rows_outer = (int64_t)kb * panels * NR * (int64_t)sizeof(float) <= B_RESIDENT;
        for (int outer = 0; outer < (rows_outer ? slivers : panels); ++outer) {
            for (int inner = 0; inner < (rows_outer ? panels : slivers); ++inner) {
                const int s = rows_outer ? outer : inner, q = rows_outer ? inner : outer;
                const int i = s * MR, nr = n - q * NR < NR ? n - q * NR : NR;
                kernel_tile(kb, a + i * rs + p0 * cs, rs, cs, bp + (int64_t)q * k * NR + (int64_t)p0 * NR,
                            c + i * ldc + q * NR, ldc, p0 > 0 ? 1 : accumulate, m - i < MR ? m - i : MR, nr,
                            p0 > 0 || !bias ? NULL : bias + q * NR, rows_outer ? outer == 0 : inner == 0);
            }
        }
    }
}
#endif

/* floats of the packed panels of a (k, n) matrix */
static int64_t packed_floats(int64_t k, int n) { return k * ((n + NR - 1) / NR) * NR; }

/* b (k, n), element (p, j) at b[p * rs + j * cs] -> ceil(n / NR) panels of (k, NR), panel q holding columns NR*q..
 * (zero-padded), on the calling OpenMP team (one panel per iteration) */
static void pack_b(int64_t k, int n, const float *b, int64_t rs, int64_t cs, float *bp) {
    const int panels = (n + NR - 1) / NR;
#pragma omp for schedule(static)
    for (int q = 0; q < panels; ++q) {
        const int nr = n - q * NR < NR ? n - q * NR : NR;
        float *d = bp + (int64_t)q * k * NR;
        for (int64_t p = 0; p < k; ++p) {
            const float *s = b + p * rs + (int64_t)q * NR * cs;
            int j = 0;
            for (; j < nr; ++j) d[p * NR + j] = s[j * cs];
            for (; j < NR; ++j) d[p * NR + j] = 0.0f;
        }
    }
}

#endif
