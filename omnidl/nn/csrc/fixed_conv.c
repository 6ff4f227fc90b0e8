/* Fused fixed-offset convolution on the CPU (float32): the gather of the bilinear taps fused with the product.
 *
 * The sampling plan of omnidl.nn.sampling gives, for output position p and tap t (row r = p*K + t), four
 * input pixels idx[r][0..3] and bilinear weights w[r][0..3]. For a block of m output positions the taps are
 * interpolated into a small column block A (m, K*C), which stays in the core's cache, and multiplied at once
 * by the weight matrix Wm (K*C, Cout); the full (P, K*C) column matrix never exists.
 *
 * Layouts (row-major): x (H*W, C) channels-last input rows of one image; out/gout (P, Cout) rows with leading
 * dimension ldo/ldg; gx (H*W, C) and gw (K*C, Cout) are accumulated into (+=).
 *
 * Products: on x86-64 with AVX-512, this file's 12x32 register-blocked kernel on packed 32-column panels; with
 * AVX2/FMA, a 6x16 one on 16-column panels (each measured near the core's FMA peak, as fast as oneDNN's dense
 * convolution on the same shapes); elsewhere the Fortran BLAS
 * sgemm_ that libtorch_cpu exports (column-major: a row-major (rows, cols) matrix is a column-major (cols, rows)
 * one, so each of those calls is written transposed).
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

extern void sgemm_(const char *ta, const char *tb, const int *m, const int *n, const int *k, const float *alpha,
                   const float *a, const int *lda, const float *b, const int *ldb, const float *beta, float *c,
                   const int *ldc);
/* MKL's per-thread thread count, the C entry point behind mkl_service.h's mkl_set_num_threads_local macro (the
 * lower-case symbol is the Fortran one, taking a pointer); weak: absent from other BLAS libraries */
extern int MKL_Set_Num_Threads_Local(int n) __attribute__((weak));

/* cache lines to fetch into L2 while tiles run (the next block of an operand copied block by block, so that the
 * copy finds it there): `lines` in all, `cols` per row, rows `rs` floats apart from `base`; line l is at
 * base + (l / cols) * rs + (l % cols) * 16. kernel_tile takes lines [from, to), one per k-step (the rest after its
 * last step): fetched all at once, they stalled the loads of the copy that follows (AVX2: all at the start). */
typedef struct {
    const float *base;
    int64_t rs;
    int cols, lines;
} ahead_t;

/* the lines of `rows` runs of `width` floats, rs floats apart from base (one line more per run than width / 16:
 * a run need not start on a line) */
static inline ahead_t ahead_rows(const float *base, int64_t rs, int rows, int width) {
    const int cols = (width + 15) / 16 + 1;
    return (ahead_t){base, rs, cols, rows > 0 && width > 0 ? rows * cols : 0};
}

/* line l of ah */
static inline const char *ahead_line(const ahead_t *ah, int l) {
    return (const char *)(ah->base + (int64_t)(l / ah->cols) * ah->rs + (l % ah->cols) * 16);
}

#if defined(__AVX512F__)
#include <immintrin.h>
#define MR 12
#define NR 32
#ifndef KC_BLOCK
#define KC_BLOCK 256
#endif
/* k-steps ahead at which a panel's rows are prefetched on its first pass (`prefetch`; B_PREFETCH 0: never). A
 * weight streamed from memory past few rows of a (a deep layer on a small map) waits on its loads otherwise: on a
 * Zen 4 host, 2048 -> 512 channels 3x3 on 4x8 took 5.8 against 6.4 ms, a 2048 -> 1024 row Winograd on 16x32 52.9
 * against 56.3 ms. Later passes find the panel in the cache and take no prefetches (with them on every pass a
 * FreDSNet training step ran 2-5 % slower) */
#ifndef B_PREFETCH
#define B_PREFETCH 16
#endif

/* c (mr, nr) (+)= a (mr, k) b (k, 32) (+ bias): a[i * rs + p * cs], b[p * 32 + j] (a packed panel, zero beyond nr);
 * `prefetch`: the panel's rows B_PREFETCH k-steps ahead are prefetched (its first pass in gemm_chunk); lines
 * [from, to) of `ah` (or none: NULL) are fetched into L2, one per k-step.
 * 24 zmm accumulators; rows beyond mr re-read row 0 and are not stored. `accumulate`: 0 writes c, 1 adds to it, 2
 * writes it with non-temporal stores where a row is whole and aligned (see STREAMING). `bias` (nr values, or NULL)
 * is added to every row, with c first when accumulating: the sum is a b + (c + bias), as when the bias was added to
 * c before the call, without a pass over c to do so. */
static void kernel_tile(int k, const float *a, int64_t rs, int64_t cs, const float *b, float *c, int64_t ldc,
                        int accumulate, int mr, int nr, const float *bias, int prefetch, const ahead_t *ah, int from,
                        int to) {
    __m512 acc[MR][2];
    int row = ah && from < to ? from / ah->cols : 0, col = ah && from < to ? from % ah->cols : 0;
    int64_t off[MR];
    for (int i = 0; i < MR; ++i) {
        acc[i][0] = acc[i][1] = _mm512_setzero_ps();
        off[i] = i < mr ? i * rs : 0;
    }
    /* the k-steps, compiled twice: with the fetches of `ah` (one line per step while from < to) and without */
#define TILE_STEPS(FETCH)                                                                                          \
    for (int p = 0; p < k; ++p) {                                                                                  \
        const __m512 b0 = _mm512_loadu_ps(b + NR * p), b1 = _mm512_loadu_ps(b + NR * p + 16);                      \
        if (B_PREFETCH > 0 && prefetch) { /* a hint: never faults past the panel's end */                          \
            _mm_prefetch((const char *)(b + NR * (p + B_PREFETCH)), _MM_HINT_T0);                                  \
            _mm_prefetch((const char *)(b + NR * (p + B_PREFETCH) + 16), _MM_HINT_T0);                             \
        }                                                                                                          \
        if (FETCH && from < to) {                                                                                  \
            _mm_prefetch((const char *)(ah->base + row * ah->rs + col * 16), _MM_HINT_T1);                         \
            ++from;                                                                                                \
            if (++col == ah->cols) {                                                                               \
                col = 0;                                                                                           \
                ++row;                                                                                             \
            }                                                                                                      \
        }                                                                                                          \
        const float *ap = a + p * cs;                                                                              \
        _Pragma("GCC unroll 12") for (int i = 0; i < MR; ++i) {                                                    \
            const __m512 t = _mm512_set1_ps(ap[off[i]]);                                                           \
            acc[i][0] = _mm512_fmadd_ps(t, b0, acc[i][0]);                                                         \
            acc[i][1] = _mm512_fmadd_ps(t, b1, acc[i][1]);                                                         \
        }                                                                                                          \
    }
    if (ah && from < to) {
        TILE_STEPS(1)
    } else {
        TILE_STEPS(0)
    }
#undef TILE_STEPS
    for (; from < to; ++from) _mm_prefetch(ahead_line(ah, from), _MM_HINT_T1);
    const __mmask16 m0 = nr >= 16 ? (__mmask16)0xFFFF : (__mmask16)((1u << nr) - 1u);
    const __mmask16 m1 = nr >= 32 ? (__mmask16)0xFFFF : nr <= 16 ? (__mmask16)0 : (__mmask16)((1u << (nr - 16)) - 1u);
    const __m512 bias0 = bias ? _mm512_maskz_loadu_ps(m0, bias) : _mm512_setzero_ps();
    const __m512 bias1 = bias ? _mm512_maskz_loadu_ps(m1, bias + 16) : _mm512_setzero_ps();
    for (int i = 0; i < mr; ++i) {
        float *ci = c + i * ldc;
        __m512 r0 = acc[i][0], r1 = acc[i][1];
        if (accumulate == 1) {
            __m512 c0 = _mm512_maskz_loadu_ps(m0, ci), c1 = _mm512_maskz_loadu_ps(m1, ci + 16);
            if (bias) {
                c0 = _mm512_add_ps(c0, bias0);
                c1 = _mm512_add_ps(c1, bias1);
            }
            r0 = _mm512_add_ps(r0, c0);
            r1 = _mm512_add_ps(r1, c1);
        } else if (bias) {
            r0 = _mm512_add_ps(r0, bias0);
            r1 = _mm512_add_ps(r1, bias1);
        }
        if (accumulate == 2 && nr == NR && ((uintptr_t)ci & 63) == 0) {
            _mm512_stream_ps(ci, r0);
            _mm512_stream_ps(ci + 16, r1);
        } else {
            _mm512_mask_storeu_ps(ci, m0, r0);
            _mm512_mask_storeu_ps(ci + 16, m1, r1);
        }
    }
}
#define HAVE_TILE 1
#elif defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
#define MR 6
#define NR 16
#ifndef KC_BLOCK
#define KC_BLOCK 256
#endif

/* c (mr, nr) (+)= a (mr, k) b (k, 16) (+ bias): a[i * rs + p * cs], b[p * 16 + j] (a packed panel, zero beyond nr).
 * `accumulate` and `bias` as the AVX-512 kernel's. */
static void kernel_tile(int k, const float *a, int64_t rs, int64_t cs, const float *b, float *c, int64_t ldc,
                        int accumulate, int mr, int nr, const float *bias, int prefetch, const ahead_t *ah, int from,
                        int to) {
    (void)prefetch;   /* the AVX-512 kernel's B_PREFETCH only */
    for (; ah && from < to; ++from) _mm_prefetch(ahead_line(ah, from), _MM_HINT_T1);
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
    if (nr == NR) {
        const __m256 bias0 = bias ? _mm256_loadu_ps(bias) : _mm256_setzero_ps();
        const __m256 bias1 = bias ? _mm256_loadu_ps(bias + 8) : _mm256_setzero_ps();
        for (int i = 0; i < mr; ++i) {
            float *ci = c + i * ldc;
            if (accumulate == 1) {
                __m256 c0 = _mm256_loadu_ps(ci), c1 = _mm256_loadu_ps(ci + 8);
                if (bias) {
                    c0 = _mm256_add_ps(c0, bias0);
                    c1 = _mm256_add_ps(c1, bias1);
                }
                r[i][0] = _mm256_add_ps(r[i][0], c0);
                r[i][1] = _mm256_add_ps(r[i][1], c1);
            } else if (bias) {
                r[i][0] = _mm256_add_ps(r[i][0], bias0);
                r[i][1] = _mm256_add_ps(r[i][1], bias1);
            }
            if (accumulate == 2 && ((uintptr_t)ci & 31) == 0) {
                _mm256_stream_ps(ci, r[i][0]);
                _mm256_stream_ps(ci + 8, r[i][1]);
            } else {
                _mm256_storeu_ps(ci, r[i][0]);
                _mm256_storeu_ps(ci + 8, r[i][1]);
            }
        }
    } else {
        float tmp[NR];
        for (int i = 0; i < mr; ++i) {
            float *ci = c + i * ldc;
            _mm256_storeu_ps(tmp, r[i][0]);
            _mm256_storeu_ps(tmp + 8, r[i][1]);
            for (int j = 0; j < nr; ++j) {
                float v = tmp[j];
                if (accumulate == 1)
                    v += bias ? ci[j] + bias[j] : ci[j];
                else if (bias)
                    v += bias[j];
                ci[j] = v;
            }
        }
    }
}

#define HAVE_TILE 1
#endif

#ifdef HAVE_TILE
/* c (m, n) (+)= a (m, k) b (k, n) (+ bias): a[i * rs + p * cs]; b packed in ceil(n / NR) panels of (k, NR), panel q
 * holding columns NR*q.. (zero-padded); c row-major with leading dimension ldc; `accumulate` and `bias` (n values,
 * or NULL; added in the first chunk of k) as kernel_tile's (2, non-temporal stores, only for k <= KC_BLOCK: the later
 * chunks of k would read c back).
 * Per chunk of KC_BLOCK k-values: when the chunk of b is small enough to stay in L2 (B_RESIDENT bytes), each
 * MR-row sliver of a is loaded once and run against every panel (rows outer); otherwise each panel's chunk stays
 * in L1 while every sliver of a runs against it (panels outer). */
#ifndef B_RESIDENT
#define B_RESIDENT (192 * 1024)
#endif
/* one chunk of kb k-values of gemm_packed: MR-row sliver s of a starts at a + s * ss, element (i, p) of it at
 * [i * rs + p * cs]; panel q of b (this chunk's kb rows) at bp + q * ps; the lines of `ah` (or NULL) shared out
 * over the tiles in the order they run */
static void gemm_chunk(int m, int n, int kb, const float *a, int64_t ss, int64_t rs, int64_t cs, const float *bp,
                       int64_t ps, float *c, int64_t ldc, int accumulate, const float *bias, const ahead_t *ah) {
    const int panels = (n + NR - 1) / NR, slivers = (m + MR - 1) / MR, tiles = panels * slivers;
    const int lines = ah ? ah->lines : 0;
    const int rows_outer = (int64_t)kb * panels * NR * (int64_t)sizeof(float) <= B_RESIDENT;
    for (int outer = 0; outer < (rows_outer ? slivers : panels); ++outer) {
        for (int inner = 0; inner < (rows_outer ? panels : slivers); ++inner) {
            const int s = rows_outer ? outer : inner, q = rows_outer ? inner : outer;
            const int i = s * MR, nr = n - q * NR < NR ? n - q * NR : NR;
            const int t = outer * (rows_outer ? panels : slivers) + inner;   /* tiles run before this one */
            kernel_tile(kb, a + s * ss, rs, cs, bp + q * ps, c + i * ldc + q * NR, ldc, accumulate,
                        m - i < MR ? m - i : MR, nr, bias ? bias + q * NR : NULL, rows_outer ? outer == 0 : inner == 0,
                        ah, (int)((int64_t)lines * t / tiles), (int)((int64_t)lines * (t + 1) / tiles));
        }
    }
}

static void gemm_packed(int m, int n, int k, const float *a, int64_t rs, int64_t cs, const float *bp, float *c,
                        int64_t ldc, int accumulate, const float *bias) {
    for (int p0 = 0; p0 < k; p0 += KC_BLOCK) {
        const int kb = k - p0 < KC_BLOCK ? k - p0 : KC_BLOCK;
        gemm_chunk(m, n, kb, a + p0 * cs, MR * rs, rs, cs, bp + (int64_t)p0 * NR, (int64_t)k * NR, c, ldc,
                   p0 > 0 ? 1 : accumulate, p0 > 0 ? NULL : bias, NULL);
    }
}

/* gemm_packed for an `a` whose rows lie side by side (a[i + p * cs], large cs: a transposed weight, one weight row
 * per k-step). Read where it lies, each MR-row sliver would take a short piece of every weight row: a stride the
 * hardware prefetchers do not follow, and the rows of a weight whose length is a multiple of 1024 floats all fall
 * in one L1 set (1024 -> 1024 channels, 3x3: W^T g took 16-17 ms against 5 ms for the forward W x on one host).
 * So a runs in blocks of A_BLOCK slivers x KC_BLOCK k-values, in gemm_packed's order, and while a block runs, the
 * next block's weight rows are fetched into L2, one cache line per k-step of its tiles (ahead_t; ROWS_AHEAD 0 turns
 * it off). Against more than one panel of b (n > NR), each block is first copied into `ap` (A_BLOCK * MR *
 * KC_BLOCK floats: sliver by sliver, MR values per k-step, contiguous) and run from there; against one panel each
 * value of a is used once, and is read where it lies, from L2.
 * The copy takes COPY_GROUP weight rows at a time, sliver by sliver, so that each sliver's destination is written
 * in whole cache lines (row by row, the A_BLOCK destinations of one row lie 12 KB apart, in one L1 set, and their
 * partly written lines were evicted and read back), the rows PACK_AHEAD ahead prefetched. W^T g from memory on 2
 * threads of a Zen 4 guest (A/B of builds in one process), 1024 -> 1024 channels 3x3 on 4x8 (32 columns: one
 * panel): 3.3-3.4 ms read in place from L2, against 3.8-4.1 copied with the next block fetched, 4.1 with the grouped
 * copy alone and 4.6-4.7 before all three; 512 -> 512 on 4x8 0.84 against 0.96-1.0, 1.09 and 1.20; on 8x16 (128
 * columns, copied) 3.1 against 3.2 and 3.35. (-D overrides: A/B builds of the benchmarks; A_BLOCK 0 reads a where
 * it lies without blocks or fetches.) */
#ifndef PACK_AHEAD
#define PACK_AHEAD 8
#endif
#ifndef A_BLOCK
#define A_BLOCK 16
#endif
#define COPY_GROUP 8
#ifndef ROWS_AHEAD
#define ROWS_AHEAD 1
#endif
/* the first `rows` values of kb weight rows (cs floats apart) from a, sliver by sliver, into ap */
static void copy_rows_block(int rows, int kb, const float *a, int64_t cs, float *ap) {
    const int slivers = (rows + MR - 1) / MR;
    for (int pg = 0; pg < kb; pg += COPY_GROUP) {
        const int gr = kb - pg < COPY_GROUP ? kb - pg : COPY_GROUP;
        for (int r = 0; r < gr; ++r) {        /* a hint: never faults past the weight's end */
            const float *ahead = a + (int64_t)(pg + r + PACK_AHEAD) * cs;
            for (int j = 0; j < rows; j += 16) _mm_prefetch((const char *)(ahead + j), _MM_HINT_T0);
        }
        for (int s = 0; s < slivers; ++s) {
            const int w = rows - s * MR >= MR ? MR : rows - s * MR;
            float *d = ap + ((int64_t)s * kb + pg) * MR;
            const float *src = a + (int64_t)pg * cs + s * MR;
            if (w == MR)
                for (int r = 0; r < gr; ++r) memcpy(d + r * MR, src + r * cs, MR * sizeof(float));
            else
                for (int r = 0; r < gr; ++r) memcpy(d + r * MR, src + r * cs, (size_t)w * sizeof(float));
        }
    }
}

static void gemm_packed_rows(int m, int n, int k, const float *a, int64_t cs, const float *bp, float *c, int64_t ldc,
                             int accumulate, float *ap) {
    for (int i0 = 0; i0 < m; i0 += A_BLOCK * MR) {
        const int rows = m - i0 < A_BLOCK * MR ? m - i0 : A_BLOCK * MR;
        for (int p0 = 0; p0 < k; p0 += KC_BLOCK) {
            const int kb = k - p0 < KC_BLOCK ? k - p0 : KC_BLOCK;
            /* one panel: each value of a is used once, read where it lies; else the block's copy */
            const int copied = n > NR;
            const float *block = a + i0 + (int64_t)p0 * cs;
            if (copied) copy_rows_block(rows, kb, block, cs, ap);
            /* the next block: the next chunk of k, or the first of the next rows */
            const int q0 = p0 + KC_BLOCK < k ? p0 + KC_BLOCK : 0, n0 = q0 ? i0 : i0 + A_BLOCK * MR;
            const int nrows = n0 >= m ? 0 : m - n0 < A_BLOCK * MR ? m - n0 : A_BLOCK * MR;
            const int nkb = k - q0 < KC_BLOCK ? k - q0 : KC_BLOCK;
            const ahead_t next = ahead_rows(a + n0 + (int64_t)q0 * cs, cs, ROWS_AHEAD ? nkb : 0, nrows);
            gemm_chunk(rows, n, kb, copied ? ap : block, copied ? (int64_t)kb * MR : MR, 1, copied ? MR : cs,
                       bp + (int64_t)p0 * NR, (int64_t)k * NR, c + (int64_t)i0 * ldc, ldc, p0 > 0 ? 1 : accumulate,
                       NULL, &next);
        }
    }
}

/* Whether the MR rows of an a read where it lies (cs == 1) fall in at most two L1 sets: a row stride that is a
 * multiple of 2 KB (the L1 cache's sets repeat every 4 KB). A weight of 1024 -> 1024 channels, 3x3, has rows of
 * 9216 floats: the tile's 12 rows then share one 8-way set and evict each other before a cache line's 16 k-steps
 * are read. 1024 x 9216 by 9216 x 128 on 2 threads of a Zen 4 guest: 193 GFLOP/s read in place, 197 copied, 208 on
 * the same rows 16 floats apart in a quiet period; 134, 157 and 185 in a busy one (the misses then reach contended
 * caches). (-DCOPY_ALIASED=0: reads them where they lie, for A/B builds.) */
#ifndef COPY_ALIASED
#define COPY_ALIASED 1
#endif
static int rows_alias(int64_t rs, int64_t cs) {
    return COPY_ALIASED && A_BLOCK > 0 && cs == 1 && rs >= KC_BLOCK && (rs * (int64_t)sizeof(float)) % 2048 == 0;
}

#ifndef COPY_AHEAD
#define COPY_AHEAD 1
#endif
/* floats of gemm_packed_copied's buffer: A_BLOCK slivers of MR rows, each KC_BLOCK values and a 16-float pad */
#define COPY_LDA (KC_BLOCK + 16)

/* gemm_packed for an `a` with rows_alias: per chunk of KC_BLOCK k-values, each block of rows is first copied row by
 * row into `ap` (A_BLOCK * MR * COPY_LDA floats) at the padded stride COPY_LDA and run from there, while the next
 * block's rows are fetched into L2, one cache line per k-step of its tiles (ahead_t; 1024 x 9216 by 9216 x 32 from
 * memory on 2 threads of a Zen 4 guest: 3.8-3.9 ms against 4.1-4.2 with the lines fetched all at once before the
 * tiles, 4.9 without; 3.1 ms on rows 16 floats apart, read in place; these rows read in place with the same fetches
 * were level, 3.4-3.7 ms). A block is one sliver where the chunk of b stays in L2 (gemm_chunk's rows-outer order:
 * the copy then sits in L1; 1024 x 9216 by 9216 x 128 on 2 threads, 8 % slower than the same product on rows 16
 * floats apart, against 11 % with blocks of 16 slivers), else A_BLOCK slivers (each runs past every panel held in
 * L1). */
static void gemm_packed_copied(int m, int n, int k, const float *a, int64_t rs, const float *bp, float *c, int64_t ldc,
                               int accumulate, const float *bias, float *ap) {
    const int panels = (n + NR - 1) / NR;
    for (int p0 = 0; p0 < k; p0 += KC_BLOCK) {
        const int kb = k - p0 < KC_BLOCK ? k - p0 : KC_BLOCK;
        const int block = (int64_t)kb * panels * NR * (int64_t)sizeof(float) <= B_RESIDENT ? MR : A_BLOCK * MR;
        for (int i0 = 0; i0 < m; i0 += block) {
            const int rows = m - i0 < block ? m - i0 : block;
            const int last = i0 + block >= m, n0 = last ? 0 : i0 + block, q0 = last ? p0 + KC_BLOCK : p0;
            const int nrows = q0 >= k ? 0 : m - n0 < block ? m - n0 : block;
            const int nkb = q0 >= k ? 0 : k - q0 < KC_BLOCK ? k - q0 : KC_BLOCK;
            for (int i = 0; i < rows; ++i)
                memcpy(ap + (int64_t)i * COPY_LDA, a + (int64_t)(i0 + i) * rs + p0, sizeof(float) * (size_t)kb);
            const ahead_t next = ahead_rows(a + (int64_t)n0 * rs + q0, rs, COPY_AHEAD ? nrows : 0, nkb);
            gemm_chunk(rows, n, kb, ap, (int64_t)MR * COPY_LDA, COPY_LDA, 1, bp + (int64_t)p0 * NR, (int64_t)k * NR,
                       c + (int64_t)i0 * ldc, ldc, p0 > 0 ? 1 : accumulate, p0 > 0 ? NULL : bias, &next);
        }
    }
}

/* floats of the packed panels of a (k, n) matrix */
static int64_t packed_floats(int k, int n) { return (int64_t)k * ((n + NR - 1) / NR) * NR; }

/* b (k, n), element (p, j) at b[p * rs + j * cs] -> the packed panels of gemm_packed */
static void pack_b(int k, int n, const float *b, int64_t rs, int64_t cs, float *bp) {
    const int panels = (n + NR - 1) / NR;
    for (int q = 0; q < panels; ++q) {
        const int nr = n - q * NR < NR ? n - q * NR : NR;
        float *d = bp + (int64_t)q * k * NR;
        for (int p = 0; p < k; ++p) {
            const float *s = b + p * rs + q * NR * cs;
            int j = 0;
            for (; j < nr; ++j) d[p * NR + j] = s[j * cs];
            for (; j < NR; ++j) d[p * NR + j] = 0.0f;
        }
    }
}
#define HAVE_KERNEL 1
#define PANEL NR
#else
#define HAVE_KERNEL 0
#define PANEL 16
#endif

#if !HAVE_KERNEL
static void blas_gemm(char ta, char tb, int m, int n, int k, float beta, const float *a, int lda, const float *b,
                      int ldb, float *c, int ldc) {
    const float one = 1.0f;
    sgemm_(&ta, &tb, &m, &n, &k, &one, a, &lda, b, &ldb, &beta, c, &ldc);
}

static int single_blas_thread(void) { return MKL_Set_Num_Threads_Local ? MKL_Set_Num_Threads_Local(1) : -1; }
static void restore_blas_threads(int prev) {
    if (MKL_Set_Num_Threads_Local && prev >= 0) MKL_Set_Num_Threads_Local(prev);
}
#endif

/* A[(r - r0) * C + c] = sum_j w[r][j] * x[idx[r][j] * C + c] for plan rows r in [r0, r1); corners of weight 0
 * (outside the image, or exactly on a pixel) are not read, so a non-finite pixel reaches only the taps that
 * sample it, as in deform_conv2d */
#if defined(__AVX512F__)
/* 16 channels per step, the first corner's product then fused multiply-adds, corners of weight 0 skipped (one pass
 * per row also for the third of an equirectangular 3x3 plan's rows that have one or two corners); the last step of
 * a row masks C % 16 channels, so nothing beyond C is read or written (a 3-channel stem is one masked step). */
static void gather(const float *x, int C, const int32_t *idx, const float *w, int64_t r0, int64_t r1, float *A) {
    const __mmask16 tail = (__mmask16)((1u << (C % 16)) - 1u);
    const int whole = C - C % 16;
    for (int64_t r = r0; r < r1; ++r) {
        const int32_t *i = idx + 4 * r;
        const float *q = w + 4 * r;
        float *a = A + (r - r0) * C;
        const int nz = _mm_movemask_ps(_mm_cmp_ps(_mm_loadu_ps(q), _mm_setzero_ps(), _CMP_NEQ_UQ));
        const __m512 w0 = _mm512_set1_ps(q[0]), w1 = _mm512_set1_ps(q[1]), w2 = _mm512_set1_ps(q[2]);
        const __m512 w3 = _mm512_set1_ps(q[3]);
        for (int c = 0; c < C; c += 16) {
            const __mmask16 m = c < whole ? (__mmask16)0xFFFF : tail;
            __m512 v = _mm512_setzero_ps();
            if (nz & 1) v = _mm512_mul_ps(w0, _mm512_maskz_loadu_ps(m, x + (int64_t)i[0] * C + c));
            if (nz & 2) v = _mm512_fmadd_ps(w1, _mm512_maskz_loadu_ps(m, x + (int64_t)i[1] * C + c), v);
            if (nz & 4) v = _mm512_fmadd_ps(w2, _mm512_maskz_loadu_ps(m, x + (int64_t)i[2] * C + c), v);
            if (nz & 8) v = _mm512_fmadd_ps(w3, _mm512_maskz_loadu_ps(m, x + (int64_t)i[3] * C + c), v);
            _mm512_mask_storeu_ps(a + c, m, v);
        }
    }
}
#else
static void gather(const float *x, int C, const int32_t *idx, const float *w, int64_t r0, int64_t r1, float *A) {
    for (int64_t r = r0; r < r1; ++r) {
        const int32_t *i = idx + 4 * r;
        const float *q = w + 4 * r;
        float *a = A + (r - r0) * C;
        if (q[0] != 0.0f && q[1] != 0.0f && q[2] != 0.0f && q[3] != 0.0f) {
            const float *x0 = x + (int64_t)i[0] * C, *x1 = x + (int64_t)i[1] * C;
            const float *x2 = x + (int64_t)i[2] * C, *x3 = x + (int64_t)i[3] * C;
            const float w0 = q[0], w1 = q[1], w2 = q[2], w3 = q[3];
            for (int c = 0; c < C; ++c) a[c] = w0 * x0[c] + w1 * x1[c] + w2 * x2[c] + w3 * x3[c];
            continue;
        }
        memset(a, 0, sizeof(float) * (size_t)C);
        for (int j = 0; j < 4; ++j) {
            if (q[j] == 0.0f) continue;
            const float *xj = x + (int64_t)i[j] * C;
            const float wj = q[j];
            for (int c = 0; c < C; ++c) a[c] += wj * xj[c];
        }
    }
}
#endif

/* gx[idx[r][j] * C + c] += w[r][j] * A[(r - r0) * C + c] for the channels c in [c0, c1) (corners of weight 0
 * skipped; corner after corner, so corners of one row on the same pixel add up) */
static void scatter_span(float *gx, int C, int c0, int c1, const int32_t *idx, const float *w, int64_t r0, int64_t r1,
                         const float *A) {
#if defined(__AVX512F__)
    const __mmask16 tail = (__mmask16)((1u << ((c1 - c0) % 16)) - 1u);
    const int whole = c1 - (c1 - c0) % 16;
#endif
    for (int64_t r = r0; r < r1; ++r) {
        const float *a = A + (r - r0) * C;
        for (int j = 0; j < 4; ++j) {
            const float q = w[4 * r + j];
            if (q == 0.0f) continue;
            float *g = gx + (int64_t)idx[4 * r + j] * C;
#if defined(__AVX512F__)
            const __m512 qv = _mm512_set1_ps(q);
            for (int c = c0; c < c1; c += 16) {
                const __mmask16 m = c < whole ? (__mmask16)0xFFFF : tail;
                _mm512_mask_storeu_ps(g + c, m, _mm512_fmadd_ps(qv, _mm512_maskz_loadu_ps(m, a + c),
                                                                _mm512_maskz_loadu_ps(m, g + c)));
            }
#else
            for (int c = c0; c < c1; ++c) g[c] += q * a[c];
#endif
        }
    }
}

static void scatter(float *gx, int C, const int32_t *idx, const float *w, int64_t r0, int64_t r1, const float *A) {
    scatter_span(gx, C, 0, C, idx, w, r0, r1, A);
}

/* which products run: 2 on this file's AVX-512 kernel, 1 on its AVX2/FMA kernel, 0 BLAS sgemm */
int omnidl_fc_kernel(void) {
#if defined(__AVX512F__)
    return 2;
#else
    return HAVE_KERNEL;
#endif
}

/* 1 when built with OpenMP (the calls run on several threads), else 0 */
int omnidl_fc_openmp(void) {
#ifdef _OPENMP
    return 1;
#else
    return 0;
#endif
}

/* floats of the packed panels of a (k, n) matrix (0 without this file's kernel: the BLAS path packs nothing) */
int64_t omnidl_fc_packed_floats(int k, int n) {
#if HAVE_KERNEL
    return packed_floats(k, n);
#else
    (void)k; (void)n;
    return 0;
#endif
}

/* The layer's weight (cout, C, K), i.e. Wm[t * C + c][co] = wt[(co * C + c) * K + t] (contiguous) or
 * wt[(co * K + t) * C + c] (`cl`: a channels-last weight, (cout, K, C) in memory), packed for the kernel:
 * transpose = 0, Wm (K*C, cout) in NR-column panels (forward); transpose = 1, Wm^T (cout, K*C) in panels of NR of
 * its K*C columns (input gradient). `wp` holds omnidl_fc_packed_floats of that shape. Contiguous weight rows are
 * re-ordered (c, t) -> (t, c) in a per-thread buffer (NR rows for a forward panel, one row for the transposed
 * packing; a channels-last weight's rows are already in that order), so that every cache line of `wp` is written
 * whole, once; `nthreads` OpenMP threads share the
 * panels (forward) or rows (transposed). Returns 0, or 1 when a buffer cannot be allocated. No-op on the BLAS
 * path. */
int omnidl_fc_pack(const float *wt, int cout, int C, int K, int cl, int transpose, float *wp, int nthreads) {
    int err = 0;
    (void)nthreads;  /* unused without OpenMP */
#if HAVE_KERNEL
    const int64_t KC = (int64_t)K * C;
#pragma omp parallel num_threads(nthreads) reduction(| : err)
    {
        float *buf = (float *)malloc(sizeof(float) * (size_t)(KC * (transpose ? 1 : NR)));
        if (!buf) err = 1;
        if (!transpose) {
            const int panels = (cout + NR - 1) / NR;
#pragma omp for schedule(static)
            for (int q = 0; q < panels; ++q) {
                if (!buf) continue;
                float *d = wp + (int64_t)q * KC * NR;
                const int nr = cout - q * NR < NR ? cout - q * NR : NR;
                for (int j = 0; j < nr; ++j) {  /* rows of this panel, (t, c) order */
                    const float *src = wt + (int64_t)(q * NR + j) * KC;
                    if (cl)
                        memcpy(buf + j * KC, src, sizeof(float) * (size_t)KC);
                    else
                        for (int c = 0; c < C; ++c)
                            for (int t = 0; t < K; ++t) buf[j * KC + (int64_t)t * C + c] = src[(int64_t)c * K + t];
                }
                for (int64_t p = 0; p < KC; ++p) {
                    int j = 0;
                    for (; j < nr; ++j) d[p * NR + j] = buf[j * KC + p];
                    for (; j < NR; ++j) d[p * NR + j] = 0.0f;
                }
            }
        } else {
            const int64_t panels = (KC + NR - 1) / NR;
#pragma omp for schedule(static)
            for (int co = 0; co < cout; ++co) {
                if (!buf) continue;
                const float *src = wt + co * KC, *row = buf;
                if (cl)
                    row = src;
                else
                    for (int c = 0; c < C; ++c)
                        for (int t = 0; t < K; ++t) buf[(int64_t)t * C + c] = src[(int64_t)c * K + t];
                for (int64_t q = 0; q < panels; ++q) {
                    float *d = wp + q * cout * NR + (int64_t)co * NR;
                    const int nr = KC - q * NR < NR ? (int)(KC - q * NR) : NR;
                    int j = 0;
                    for (; j < nr; ++j) d[j] = row[q * NR + j];
                    for (; j < NR; ++j) d[j] = 0.0f;
                }
            }
        }
        free(buf);
    }
#else
    (void)wt; (void)cout; (void)C; (void)K; (void)cl; (void)transpose; (void)wp; (void)nthreads;
#endif
    return err;
}

static int64_t min64(int64_t a, int64_t b) { return a < b ? a : b; }

/* start of thread t's share of `total` positions (t == nt gives the end); blocks run within each share */
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
    return HAVE_KERNEL && nthreads > 1 && total < 2 * block * nthreads && (cout + PANEL - 1) / PANEL >= nthreads;
}

/* thread t's output channels [*c0, *c1) when the panels are split among nt threads */
static void channel_share(int cout, int t, int nt, int *c0, int *c1) {
    const int panels = (cout + PANEL - 1) / PANEL;
    *c0 = PANEL * (panels * t / nt);
    *c1 = (int)min64(cout, PANEL * (panels * (t + 1) / nt));
}

/* The taps of B images (x: B images of x_img floats, channels-last rows of C) as one row per output position:
 * A[((b * P + p) * K + t) * C + c] for the plan's P positions of K taps, on `nthreads` OpenMP threads split by
 * positions (omnidl.nn.plan_columns: the columns of a weight-heavy layer in training). Returns 0. */
int omnidl_fc_gather(const float *x, int64_t x_img, int C, const int32_t *idx, const float *w, int K, int64_t P, int B,
                     float *A, int nthreads) {
    (void)nthreads;  /* unused without OpenMP */
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t s = 0; s < (int64_t)B * P; ++s) {
        const int64_t b = s / P, p = s % P;
        gather(x + b * x_img, C, idx, w, p * K, (p + 1) * K, A + s * K * (int64_t)C);
    }
    return 0;
}

/* The adjoint of omnidl_fc_gather: gx (B images of gx_img floats, zeroed or accumulated into) += S^T A, on
 * `nthreads` OpenMP threads, each over every position for its share of the channels (channel_share's panels of
 * 16 or 32: no two threads write one float, nor one cache line where C is a multiple of 16). Returns 0. */
int omnidl_fc_scatter(float *gx, int64_t gx_img, int C, const int32_t *idx, const float *w, int K, int64_t P, int B,
                      const float *A, int nthreads) {
    (void)nthreads;
#pragma omp parallel num_threads(nthreads)
    {
        int t, nt, c0, c1;
        team(&t, &nt);
        channel_share(C, t, nt, &c0, &c1);
        for (int b = 0; c1 > c0 && b < B; ++b)
            scatter_span(gx + b * gx_img, C, c0, c1, idx, w, 0, P * K, A + (int64_t)b * P * K * C);
    }
    return 0;
}

/* The calling OpenMP thread's share of a forward: rows [*s0, *s1) of `total` and output channels [*c0, *c1), split
 * by rows, or by output channels (every row) when `by_channels` */
static void forward_share(int64_t total, int by_channels, int cout, int64_t *s0, int64_t *s1, int *c0, int *c1) {
    int t, nt;
    team(&t, &nt);
    *s0 = 0, *s1 = total, *c0 = 0, *c1 = cout;
    if (by_channels) {
        channel_share(cout, t, nt, c0, c1);
    } else {
        *s0 = span_edge(total, t, nt);
        *s1 = span_edge(total, t + 1, nt);
    }
}

/* Forward of B images: out rows = bias + gathered taps @ Wm, in blocks of `block` positions, on `nthreads`
 * OpenMP threads (the process's OpenMP runtime: PyTorch's, so this is one more parallel region of its thread
 * team). Each thread takes a share of the B*P positions, or, when there are too few positions for that
 * (small deep feature maps), runs every position for its share of the output channels, so that each thread
 * streams only its part of the weight. The kernel path reads `wp` (omnidl_fc_pack, transpose = 0), the BLAS
 * path `wm` (K*C, cout) row-major. Image b's input rows start at x + b*x_img, its output rows at
 * out + b*out_img. Returns 0, 1 when a buffer cannot be allocated, 2 when the operand is missing. */
int omnidl_fc_forward(const float *x, int64_t x_img, int C, const int32_t *idx, const float *w, int K, int64_t P,
                      int B, const float *wm, const float *wp, int cout, const float *bias, float *out,
                      int64_t out_img, int64_t ldo, int64_t block, int nthreads) {
    const int KC = K * C;
    if (HAVE_KERNEL ? !wp : !wm) return 2;
    const int64_t total = (int64_t)B * P;
    const int by_channels = split_channels(total, block, nthreads, cout);
    int err = 0;
#pragma omp parallel num_threads(nthreads) reduction(| : err)
    {
        int64_t s0, s1;
        int c0, c1;
        forward_share(total, by_channels, cout, &s0, &s1, &c0, &c1);
        float *A = NULL;
        if (s1 > s0 && c1 > c0 && !(A = (float *)malloc(sizeof(float) * (size_t)(block * KC)))) err = 1;
        if (A) {
#if !HAVE_KERNEL
            const int prev = single_blas_thread();
#endif
            for (int64_t s = s0; s < s1;) {
                const int64_t b = s / P, p = s % P;
                const int m = (int)min64(block, min64(s1 - s, P - p));
                float *o = out + b * out_img + p * ldo + c0;
                gather(x + b * x_img, C, idx, w, p * K, (p + m) * K, A);
#if HAVE_KERNEL
                (void)wm;  /* o (m, c1 - c0) = A (m, KC) Wm[:, c0:c1] + bias[c0:c1] */
                gemm_packed(m, c1 - c0, KC, A, KC, 1, wp + (int64_t)(c0 / NR) * KC * NR, o, ldo, 0,
                            bias ? bias + c0 : NULL);
#else
                (void)wp;
                int acc = 0;
                if (bias) {
                    for (int i = 0; i < m; ++i) memcpy(o + i * ldo, bias + c0, sizeof(float) * (size_t)(c1 - c0));
                    acc = 1;
                }
                blas_gemm('N', 'N', cout, m, KC, acc ? 1.0f : 0.0f, wm, cout, A, KC, o, (int)ldo);
#endif
                s += m;
            }
#if !HAVE_KERNEL
            restore_blas_threads(prev);
#endif
            free(A);
        }
    }
    return err;
}

/* A dense 1x1 convolution (a product with the input rows as they are, no gather) written over a residual:
 * out (n, cout) rows (leading dimension ldo) = act(out + bias + x Wm) with x (n, C) rows (leading dimension ldx),
 * or act(bias + x Wm) without `accumulate`; act = ReLU when `relu`. The sum and the ReLU are applied to each
 * block while it is in the cache, so the output is read and written once, and no new buffer is needed when
 * `out` holds a residual that the caller no longer needs. Threads split rows, or output channels for few
 * rows, as omnidl_fc_forward; `wp` is omnidl_fc_pack's (K = 1, transpose = 0), the BLAS path reads `wm` (C, cout).
 * Returns 0, or 2 when the operand is missing. */
int omnidl_dense_forward(const float *x, int64_t ldx, int C, int64_t n, const float *wm, const float *wp, int cout,
                         const float *bias, float *out, int64_t ldo, int accumulate, int relu, int64_t block,
                         int nthreads) {
    if (HAVE_KERNEL ? !wp : !wm) return 2;
    const int by_channels = split_channels(n, block, nthreads, cout);
#pragma omp parallel num_threads(nthreads)
    {
        int64_t s0, s1;
        int c0, c1;
        forward_share(n, by_channels, cout, &s0, &s1, &c0, &c1);
#if !HAVE_KERNEL
        const int prev = single_blas_thread();
#endif
        for (int64_t s = s0; s < s1 && c1 > c0;) {
            const int m = (int)min64(block, s1 - s);
            float *o = out + s * ldo + c0;
#if HAVE_KERNEL
            (void)wm;  /* o (m, c1 - c0) (+)= x rows (m, C) Wm[:, c0:c1] + bias[c0:c1] */
            gemm_packed(m, c1 - c0, C, x + s * ldx, ldx, 1, wp + (int64_t)(c0 / NR) * C * NR, o, ldo, accumulate,
                        bias ? bias + c0 : NULL);
#else
            (void)wp;
            int acc = accumulate;
            if (bias) {
                for (int i = 0; i < m; ++i) {
                    float *oi = o + i * ldo;
                    if (acc)
                        for (int j = 0; j < c1 - c0; ++j) oi[j] += bias[c0 + j];
                    else
                        memcpy(oi, bias + c0, sizeof(float) * (size_t)(c1 - c0));
                }
                acc = 1;
            }
            blas_gemm('N', 'N', c1 - c0, m, C, acc ? 1.0f : 0.0f, wm + c0, cout, x + s * ldx, (int)ldx, o, (int)ldo);
#endif
            if (relu)
                for (int i = 0; i < m; ++i) {
                    float *oi = o + i * ldo;
                    for (int j = 0; j < c1 - c0; ++j) oi[j] = oi[j] < 0.0f ? 0.0f : oi[j];  /* NaN stays NaN */
                }
            s += m;
        }
#if !HAVE_KERNEL
        restore_blas_threads(prev);
#endif
    }
    return 0;
}

/* Backward of B images on `nthreads` OpenMP threads, each over its share of the positions in two passes (each
 * keeps its large operand warm in the cache): gw += A^T gout on re-gathered taps, then gx += S^T (gout Wm^T)
 * scattered straight from the block. Thread 0 accumulates into gw/gx; the others into private copies (of gx:
 * only the band of input rows their positions touch), added in afterwards. With few positions (as the forward)
 * the weight gradient is split by output channels instead, straight into gw. gx (B images of gx_img floats) or gw
 * (K*C, cout) may be NULL when that gradient is not needed. The kernel path reads `wtp` (omnidl_fc_pack,
 * transpose = 1), the BLAS path `wm`. Returns 0, 1 when a buffer cannot be allocated, 2 when the operand is
 * missing. */
int omnidl_fc_backward(const float *x, int64_t x_img, int C, const int32_t *idx, const float *w, int K, int64_t P,
                       int B, const float *wm, const float *wtp, int cout, const float *gout, int64_t g_img,
                       int64_t ldg, float *gx, int64_t gx_img, float *gw, int64_t block, int nthreads) {
    const int KC = K * C;
    if (gx && (HAVE_KERNEL ? !wtp : !wm)) return 2;
    const int64_t total = (int64_t)B * P, pixels = gx_img / C;
    /* few positions (small deep maps, large weights): each thread runs the weight gradient of every position for
     * its share of the output channels, so no thread holds a private copy of a large weight gradient */
    const int gw_by_channels = split_channels(total, block, nthreads, cout);
    float **pgw = (float **)calloc((size_t)nthreads, sizeof(float *));
    float **pgx = (float **)calloc((size_t)nthreads, sizeof(float *));
    int64_t *lo = (int64_t *)calloc((size_t)nthreads, sizeof(int64_t));
    int64_t *hi = (int64_t *)calloc((size_t)nthreads, sizeof(int64_t));
    int err = !pgw || !pgx || !lo || !hi;
    if (!err) {
#pragma omp parallel num_threads(nthreads) reduction(| : err)
        {
            int t, nt;
            team(&t, &nt);
            const int64_t s0 = span_edge(total, t, nt), s1 = span_edge(total, t + 1, nt);
            float *A = (float *)malloc(sizeof(float) * (size_t)(block * KC));
#if HAVE_KERNEL
            (void)wm;
            float *gp = (float *)malloc(sizeof(float) * (size_t)packed_floats((int)block, cout));
#else
            (void)wtp;
            float *gp = NULL;
#endif
            int ok = A && (!HAVE_KERNEL || gp);
            /* thread 0 writes the results directly, the others private copies (none for an empty share) */
            float *mygw = t == 0 ? gw : NULL, *mygx = t == 0 ? gx : NULL;
            int64_t mylo = 0, myhi = 0;  /* band of flat input rows (b * pixels + pixel) of this thread */
            if (gw_by_channels)
                mygw = gw;  /* columns c0..c1 of the result itself */
            else if (ok && gw && t > 0 && s1 > s0)
                ok = (mygw = (float *)calloc((size_t)KC * (size_t)cout, sizeof(float))) != NULL;
            if (ok && gx && t > 0 && s1 > s0) {
                mylo = INT64_MAX;
                myhi = 0;
                for (int64_t s = s0; s < s1; ++s) {
                    const int64_t b = s / P, r0 = (s % P) * K;
                    for (int64_t j = 4 * r0; j < 4 * (r0 + K); ++j) {
                        if (w[j] == 0.0f) continue;
                        const int64_t v = b * pixels + idx[j];
                        if (v < mylo) mylo = v;
                        if (v + 1 > myhi) myhi = v + 1;
                    }
                }
                if (myhi <= mylo) mylo = myhi = 0;
                if (myhi > mylo)
                    ok = (mygx = (float *)calloc((size_t)((myhi - mylo) * C), sizeof(float))) != NULL;
            }
            if (!ok) err = 1;
            if (ok) {
#if !HAVE_KERNEL
                const int prev = single_blas_thread();
#endif
                const int64_t w0 = gw_by_channels ? 0 : s0, w1 = gw_by_channels ? total : s1;
                int c0 = 0, c1 = cout;
                if (gw_by_channels) channel_share(cout, t, nt, &c0, &c1);
                for (int64_t s = w0; mygw && c1 > c0 && s < w1;) {
                    const int64_t b = s / P, p = s % P;
                    const int m = (int)min64(block, min64(w1 - s, P - p));
                    const float *g = gout + b * g_img + p * ldg;
                    gather(x + b * x_img, C, idx, w, p * K, (p + m) * K, A);
#if HAVE_KERNEL  /* gw[:, c0:c1] (KC, cout) += A^T g[:, c0:c1] */
                    pack_b(m, c1 - c0, g + c0, ldg, 1, gp);
                    gemm_packed(KC, c1 - c0, m, A, 1, KC, gp, mygw + c0, cout, 1, NULL);
#else
                    blas_gemm('N', 'T', cout, KC, m, 1.0f, g, (int)ldg, A, KC, mygw, cout);
#endif
                    s += m;
                }
                /* input gradient rows of image b start at base + b * gx_img (private copies are offset by mylo) */
                float *base = (t == 0 || !mygx) ? mygx : mygx - mylo * C;
                for (int64_t s = s0; base && s < s1;) {
                    const int64_t b = s / P, p = s % P;
                    const int m = (int)min64(block, min64(s1 - s, P - p));
                    const float *g = gout + b * g_img + p * ldg;
#if HAVE_KERNEL
                    gemm_packed(m, KC, cout, g, ldg, 1, wtp, A, KC, 0, NULL);  /* A (m, KC) = g Wm^T */
#else
                    blas_gemm('T', 'N', KC, m, cout, 0.0f, wm, cout, g, (int)ldg, A, KC);
#endif
                    scatter(base + b * gx_img, C, idx, w, p * K, (p + m) * K, A);
                    s += m;
                }
#if !HAVE_KERNEL
                restore_blas_threads(prev);
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
                    float *dst = gx + lo[k] * C;
#pragma omp for schedule(static)
                    for (int64_t e = 0; e < (hi[k] - lo[k]) * C; ++e) dst[e] += src[e];
                }
            }
            free(A);
            free(gp);
            if (t > 0) {
                if (!gw_by_channels) free(mygw);
                free(mygx);
            }
        }
    }
    free(pgw);
    free(pgx);
    free(lo);
    free(hi);
    return err;
}

/* ---- a plain product for the weight-heavy convolutions of omnidl.nn.unfold_conv ---------------------------------
 *
 * c (m, n) (+)= a (m, k) b (k, n), with a[i * ars + p * acs] read where it lies (a weight, or its transpose) and
 * b[p * brs + j * bcs] packed once into NR-column panels shared by the threads (used as it is when it already is
 * one panel: n == NR, brs == NR, bcs == 1); c row-major with leading dimension ldc, added to when `accumulate`.
 * The threads split the rows of c in MR-row slivers, so each streams only its part of a; an a whose rows lie side
 * by side (ars == 1: a transposed weight) is copied block by block first (gemm_packed_rows). A c of at least
 * STREAMING bytes written in one pass over k (k <= KC_BLOCK: a weight-heavy layer's weight gradient) goes straight
 * to memory with non-temporal stores: the step does not read it again before the optimiser, and ordinary stores
 * would first read every line of it (37.7 MB for 1024 -> 1024 channels, 3x3: 3.5-3.7 against 6.3-6.6 ms on 2
 * threads; 9.4 MB for 512 -> 512: 1.3 against 2.2 ms). Returns 0, 1 when a buffer cannot be allocated, 2 without
 * this file's register kernel (the caller keeps its BLAS product). */
#ifndef STREAMING
#define STREAMING (2 << 20)
#endif
int omnidl_gemm(int m, int n, int k, const float *a, int64_t ars, int64_t acs, const float *b, int64_t brs,
                int64_t bcs, float *c, int64_t ldc, int accumulate, int nthreads) {
#if HAVE_KERNEL
    const int direct = n == NR && brs == NR && bcs == 1;
    float *bp = direct ? NULL : (float *)malloc(sizeof(float) * (size_t)packed_floats(k, n));
    if (!direct && !bp) return 1;
    const int panels = (n + NR - 1) / NR, slivers = (m + MR - 1) / MR;
    const int mode = accumulate ? 1 : k <= KC_BLOCK && (int64_t)m * n * (int64_t)sizeof(float) >= STREAMING ? 2 : 0;
    const int64_t a_floats = (int64_t)A_BLOCK * MR * COPY_LDA;
    const int side_by_side = A_BLOCK > 0 && ars == 1 && acs > 1, aliased = rows_alias(ars, acs);
    const int copied = (side_by_side && n > NR) || aliased;
    float *ap = copied ? (float *)malloc(sizeof(float) * (size_t)(a_floats * nthreads)) : NULL;
    if (copied && !ap) {
        free(bp);
        return 1;
    }
#pragma omp parallel num_threads(nthreads)
    {
        if (!direct) {
#pragma omp for schedule(static)
            for (int q = 0; q < panels; ++q) {
                const int nr = n - q * NR < NR ? n - q * NR : NR;
                pack_b(k, nr, b + (int64_t)q * NR * bcs, brs, bcs, bp + (int64_t)q * k * NR);
            }
        }
        int t, nt;
        team(&t, &nt);
        const int i0 = MR * (int)span_edge(slivers, t, nt), i1 = (int)min64(m, MR * span_edge(slivers, t + 1, nt));
        if (i1 > i0 && side_by_side)
            gemm_packed_rows(i1 - i0, n, k, a + i0, acs, direct ? b : bp, c + i0 * ldc, ldc, mode,
                             ap ? ap + t * a_floats : NULL);
        else if (i1 > i0 && aliased)
            gemm_packed_copied(i1 - i0, n, k, a + i0 * ars, ars, direct ? b : bp, c + i0 * ldc, ldc, mode, NULL,
                               ap + t * a_floats);
        else if (i1 > i0)
            gemm_packed(i1 - i0, n, k, a + i0 * ars, ars, acs, direct ? b : bp, c + i0 * ldc, ldc, mode, NULL);
    }
    _mm_sfence();  /* the non-temporal stores are visible to every thread before the caller reads c */
    free(ap);
    free(bp);
    return 0;
#else
    (void)m; (void)n; (void)k; (void)a; (void)ars; (void)acs; (void)b; (void)brs; (void)bcs; (void)c; (void)ldc;
    (void)accumulate; (void)nthreads;
    return 2;
#endif
}

/* ---- Winograd F(2x2, 3x3): a stride-1 3x3 convolution with 2.25x fewer multiplications ----------------------
 *
 * Each 2x2 block of outputs ("tile") is Y = A^T [ U (.) V ] A with V = B^T d B from the tile's 4x4 input patch d
 * and U = G g G^T from the 3x3 filter g (per input and output channel); summed over the input channels, the 16
 * element-wise products become 16 matrix products M[xi] (tiles, cout) = V[xi] (tiles, C) @ U[xi] (C, cout), run on
 * the register kernel. Per block of tiles the transformed inputs and products stay in the core's cache.
 *     B^T = [1 0 -1 0; 0 1 1 0; 0 -1 1 0; 0 1 0 -1]   G = [1 0 0; .5 .5 .5; .5 -.5 .5; 0 0 1]   A^T = [1 1 1 0; 0 1 -1 -1]
 * Padding: one row of zeros above and below; one column each side of zeros, or the wrapped column (wrap = 1).
 * Rounding differs from the direct sum by a few float32 ulps of the operands' scale (the transforms add and
 * subtract up to 4 terms before the product).
 * Training (omnidl.nn.winograd_train): the input gradient is the same forward on the filters turned by 180 degrees
 * with the channel axes swapped (omnidl_wino_pack_flip); the weight gradient is the sum over tiles of
 * V[xi]^T (A gY A^T)[xi], transformed back by G^T . G (omnidl_wino_weight_grad).
 */

/* floats of omnidl_wino_pack's output for C input and cout output channels (0 on the BLAS build) */
int64_t omnidl_wino_packed_floats(int C, int cout) {
#if HAVE_KERNEL
    return 16 * packed_floats(C, cout);
#else
    (void)C; (void)cout;
    return 0;
#endif
}

#if HAVE_KERNEL
/* u[xi][j] = (G g_j G^T)[xi] for the filters g_j = src + j * js (nine values; flip: taken in reverse order),
 * j < nr, vectorised over j (the loads are gathers) */
static inline __attribute__((always_inline)) void wino_filters(const float *src, int64_t js, int flip, int nr,
                                                                float u[16][NR]) {
#pragma omp simd
    for (int j = 0; j < nr; ++j) {
        const float *g = src + j * js;
        float t[4][3];                                       /* G g */
        for (int k = 0; k < 3; ++k) {
            const float a = g[flip ? 8 - k : k], b = g[flip ? 5 - k : 3 + k], c = g[flip ? 2 - k : 6 + k];
            t[0][k] = a;
            t[1][k] = 0.5f * (a + b + c);
            t[2][k] = 0.5f * (a - b + c);
            t[3][k] = c;
        }
        for (int i = 0; i < 4; ++i) {                        /* (G g) G^T */
            u[4 * i][j] = t[i][0];
            u[4 * i + 1][j] = 0.5f * (t[i][0] + t[i][1] + t[i][2]);
            u[4 * i + 2][j] = 0.5f * (t[i][0] - t[i][1] + t[i][2]);
            u[4 * i + 3][j] = t[i][2];
        }
    }
    for (int xi = 0; xi < 16; ++xi)
        for (int j = nr; j < NR; ++j) u[xi][j] = 0.0f;
}
#endif

/* w (cout, C, 3, 3) contiguous -> the 16 packed panel sets of U[xi] (C, cout), U = G g G^T per filter g.
 * flip = 1: those of the input gradient's filter instead, w' (C, cout, 3, 3) with w'[c][co] = w[co][c] turned by
 * 180 degrees (U[xi] (cout, C): the adjoint of a stride-1 3x3 convolution with padding 1, zero or wrapped, is the
 * same convolution with w'). Written straight into the panels (panel q of U[xi] at up + xi * stride + q * rows * NR,
 * row r of it NR values), the threads taking whole panels. Returns 0, 2 on the BLAS build. */
int omnidl_wino_pack_flip(const float *w, int cout, int C, int flip, float *up, int nthreads) {
#if HAVE_KERNEL
    const int rows = flip ? cout : C, cols = flip ? C : cout;     /* U[xi] (rows, cols) */
    const int panels = (cols + NR - 1) / NR;
    const int64_t stride = packed_floats(rows, cols);
#pragma omp parallel for num_threads(nthreads) schedule(static)
    for (int q = 0; q < panels; ++q) {
        const int nr = cols - q * NR < NR ? cols - q * NR : NR;
        for (int r = 0; r < rows; ++r) {
            /* the panel row's 16 x NR values, then each xi's NR in one run (the 16 destinations lie `stride` apart,
             * in the same cache sets: written value by value they evicted each other) */
            float u[16][NR];
            if (flip)   /* row r = output channel r of w, column = its input channel */
                wino_filters(w + ((int64_t)r * C + q * NR) * 9, 9, 1, nr, u);
            else        /* row r = input channel r, column = output channel */
                wino_filters(w + ((int64_t)q * NR * C + r) * 9, (int64_t)C * 9, 0, nr, u);
            float *d = up + (int64_t)q * rows * NR + (int64_t)r * NR;
            for (int xi = 0; xi < 16; ++xi) memcpy(d + xi * stride, u[xi], sizeof(u[xi]));
        }
    }
    return 0;
#else
    (void)w; (void)cout; (void)C; (void)flip; (void)up; (void)nthreads;
    return 2;
#endif
}

/* omnidl_wino_pack_flip without the flip (inference: omnidl.nn.winograd.pack) */
int omnidl_wino_pack(const float *w, int cout, int C, float *up, int nthreads) {
    return omnidl_wino_pack_flip(w, cout, C, 0, up, nthreads);
}

#if HAVE_KERNEL
/* floats between the 16 planes of a block's transformed tiles: a cache line more than the plane, so the 16
 * streams do not fall into the same cache sets (planes of a multiple of 4 kB would) */
static int64_t wino_plane(int m, int n) { return (int64_t)m * n + 16; }

/* V[xi][i][c] (at V[xi * plane + i * C + c]) of the tiles t0..t0+m-1 of image rows x (H, W, C); zero: C zeros */
static void wino_input(const float *x, int H, int W, int C, int wrap, const float *zero, int64_t t0, int m, int tw,
                       float *V, int64_t plane) {
    for (int i = 0; i < m; ++i) {
        const int64_t t = t0 + i;
        const int ty = (int)(t / tw), tx = (int)(t % tw);
        const float *p[4][4];
        for (int a = 0; a < 4; ++a) {
            const int r = 2 * ty - 1 + a;
            for (int b = 0; b < 4; ++b) {
                int col = 2 * tx - 1 + b;
                if (wrap) col = (col + W) % W;
                p[a][b] = (r < 0 || r >= H || col < 0 || col >= W) ? zero : x + ((int64_t)r * W + col) * C;
            }
        }
        float *v = V + (int64_t)i * C;
        const float *restrict p00 = p[0][0], *restrict p01 = p[0][1], *restrict p02 = p[0][2], *restrict p03 = p[0][3];
        const float *restrict p10 = p[1][0], *restrict p11 = p[1][1], *restrict p12 = p[1][2], *restrict p13 = p[1][3];
        const float *restrict p20 = p[2][0], *restrict p21 = p[2][1], *restrict p22 = p[2][2], *restrict p23 = p[2][3];
        const float *restrict p30 = p[3][0], *restrict p31 = p[3][1], *restrict p32 = p[3][2], *restrict p33 = p[3][3];
        float *restrict v0 = v, *restrict v1 = v + plane, *restrict v2 = v + 2 * plane, *restrict v3 = v + 3 * plane;
        float *restrict v4 = v + 4 * plane, *restrict v5 = v + 5 * plane, *restrict v6 = v + 6 * plane;
        float *restrict v7 = v + 7 * plane, *restrict v8 = v + 8 * plane, *restrict v9 = v + 9 * plane;
        float *restrict v10 = v + 10 * plane, *restrict v11 = v + 11 * plane, *restrict v12 = v + 12 * plane;
        float *restrict v13 = v + 13 * plane, *restrict v14 = v + 14 * plane, *restrict v15 = v + 15 * plane;
#pragma omp simd
        for (int c = 0; c < C; ++c) {
            /* rows of B^T d: s_a_b */
            const float s00 = p00[c] - p20[c], s01 = p01[c] - p21[c], s02 = p02[c] - p22[c], s03 = p03[c] - p23[c];
            const float s10 = p10[c] + p20[c], s11 = p11[c] + p21[c], s12 = p12[c] + p22[c], s13 = p13[c] + p23[c];
            const float s20 = p20[c] - p10[c], s21 = p21[c] - p11[c], s22 = p22[c] - p12[c], s23 = p23[c] - p13[c];
            const float s30 = p10[c] - p30[c], s31 = p11[c] - p31[c], s32 = p12[c] - p32[c], s33 = p13[c] - p33[c];
            v0[c] = s00 - s02; v1[c] = s01 + s02; v2[c] = s02 - s01; v3[c] = s01 - s03;
            v4[c] = s10 - s12; v5[c] = s11 + s12; v6[c] = s12 - s11; v7[c] = s11 - s13;
            v8[c] = s20 - s22; v9[c] = s21 + s22; v10[c] = s22 - s21; v11[c] = s21 - s23;
            v12[c] = s30 - s32; v13[c] = s31 + s32; v14[c] = s32 - s31; v15[c] = s31 - s33;
        }
    }
}

/* out rows of tiles t0..: Y = A^T M A (+ bias) (+ out when accumulate) (ReLU) */
static void wino_output(const float *M, int m, int cout, const float *bias, float *out, int H, int W, int64_t t0,
                        int tw, int accumulate, int relu) {
    const int64_t plane = wino_plane(m, cout);
    for (int i = 0; i < m; ++i) {
        const int64_t t = t0 + i;
        const int ty = (int)(t / tw), tx = (int)(t % tw);
        const float *mm = M + (int64_t)i * cout;
        float *o[2][2];
        for (int a = 0; a < 2; ++a)
            for (int b = 0; b < 2; ++b) {
                const int r = 2 * ty + a, col = 2 * tx + b;
                o[a][b] = (r < H && col < W) ? out + ((int64_t)r * W + col) * cout : NULL;
            }
        const float *restrict q0 = mm, *restrict q1 = mm + plane, *restrict q2 = mm + 2 * plane, *restrict q3 = mm + 3 * plane;
        const float *restrict q4 = mm + 4 * plane, *restrict q5 = mm + 5 * plane, *restrict q6 = mm + 6 * plane;
        const float *restrict q7 = mm + 7 * plane, *restrict q8 = mm + 8 * plane, *restrict q9 = mm + 9 * plane;
        const float *restrict q10 = mm + 10 * plane, *restrict q11 = mm + 11 * plane, *restrict q12 = mm + 12 * plane;
        const float *restrict q13 = mm + 13 * plane, *restrict q14 = mm + 14 * plane, *restrict q15 = mm + 15 * plane;
        float y[4][64];
        for (int c0 = 0; c0 < cout; c0 += 64) {
            const int n = cout - c0 < 64 ? cout - c0 : 64;
            for (int j = 0; j < n; ++j) {
                const int co = c0 + j;
                /* A^T q: u_a_b */
                const float u00 = q0[co] + q4[co] + q8[co], u01 = q1[co] + q5[co] + q9[co];
                const float u02 = q2[co] + q6[co] + q10[co], u03 = q3[co] + q7[co] + q11[co];
                const float u10 = q4[co] - q8[co] - q12[co], u11 = q5[co] - q9[co] - q13[co];
                const float u12 = q6[co] - q10[co] - q14[co], u13 = q7[co] - q11[co] - q15[co];
                const float bb = bias ? bias[co] : 0.0f;
                y[0][j] = u00 + u01 + u02 + bb;
                y[1][j] = u01 - u02 - u03 + bb;
                y[2][j] = u10 + u11 + u12 + bb;
                y[3][j] = u11 - u12 - u13 + bb;
            }
            for (int k = 0; k < 4; ++k) {
                float *ok = o[k / 2][k % 2];
                if (!ok) continue;
                ok += c0;
                for (int j = 0; j < n; ++j) {
                    const float v = y[k][j] + (accumulate ? ok[j] : 0.0f);
                    ok[j] = relu && v < 0.0f ? 0.0f : v;   /* NaN stays NaN */
                }
            }
        }
    }
}
#endif

/* Stride-1 3x3 convolution of B images x (B, H, W, C) channels-last into out (B, H, W, cout) by Winograd F(2x2, 3x3)
 * with `up` from omnidl_wino_pack; bias may be NULL; accumulate: add into out (a residual); relu. Tiles are split
 * among `nthreads` OpenMP threads in blocks of `block` tiles. Returns 0, 1 when out of memory, 2 on the BLAS build. */
int omnidl_wino_forward(const float *x, int B, int H, int W, int C, int wrap, const float *up, int cout,
                        const float *bias, float *out, int accumulate, int relu, int block, int nthreads) {
#if HAVE_KERNEL
    const int th = (H + 1) / 2, tw = (W + 1) / 2;
    const int64_t T = (int64_t)th * tw, total = (int64_t)B * T, stride = packed_floats(C, cout);
    int err = 0;
#pragma omp parallel num_threads(nthreads) reduction(| : err)
    {
        int t, nt;
        team(&t, &nt);
        const int64_t s0 = span_edge(total, t, nt), s1 = span_edge(total, t + 1, nt);
        float *V = (float *)malloc(sizeof(float) * 16 * (size_t)(wino_plane(block, C) + wino_plane(block, cout)));
        float *zero = (float *)calloc((size_t)C, sizeof(float));
        if (!V || !zero) {
            err = 1;
        } else {
            float *M = V + 16 * wino_plane(block, C);
            for (int64_t s = s0; s < s1;) {
                const int64_t b = s / T, t0 = s % T;
                const int m = (int)min64(block, min64(s1 - s, T - t0));
                const float *xb = x + b * (int64_t)H * W * C;
                wino_input(xb, H, W, C, wrap, zero, t0, m, tw, V, wino_plane(m, C));
                for (int xi = 0; xi < 16; ++xi)
                    gemm_packed(m, cout, C, V + xi * wino_plane(m, C), C, 1, up + xi * stride, M + xi * wino_plane(m, cout),
                                cout, 0, NULL);
                wino_output(M, m, cout, bias, out + b * (int64_t)H * W * cout, H, W, t0, tw, accumulate, relu);
                s += m;
            }
        }
        free(V);
        free(zero);
    }
    return err;
#else
    (void)x; (void)B; (void)H; (void)W; (void)C; (void)wrap; (void)up; (void)cout; (void)bias; (void)out;
    (void)accumulate; (void)relu; (void)block; (void)nthreads;
    return 2;
#endif
}

/* ---- Row Winograd F(2, 3): a 3x3 convolution of vertical stride sy (1 or 2) with 1.5x fewer multiplications ------
 *
 * HorizonNet's height towers halve the height with 3x3 convolutions of stride (2, 1), which F(2x2, 3x3) cannot take.
 * Along each row the stride is 1, so the 1-d transform applies there: a tile is 2 horizontally adjacent outputs of
 * one output row; for each of its 3 input rows (sy * oy - 1 + ky) the 4 input columns d give v = b^T d and the
 * filter's row g_ky gives u = G g_ky; the tile's outputs are y = a^T [sum over ky and channels of u (.) v]. Per
 * tile the 3 rows' transformed inputs lie side by side (3C values), so the 4 sums are 4 matrix products
 * M[xi] (tiles, cout) = V[xi] (tiles, 3C) @ U[xi] (3C, cout) on the register kernel: 4 x 3 multiplications per
 * 2 outputs and (channel, output channel) against 9 x 2 for the direct sum.
 *     b^T = [1 0 -1 0; 0 1 1 0; 0 -1 1 0; 0 1 0 -1]   G = [1 0 0; .5 .5 .5; .5 -.5 .5; 0 0 1]   a^T = [1 1 1 0; 0 1 -1 -1]
 * Padding: one row of zeros above (and below where the rows reach it); one column each side of zeros, or the
 * wrapped column (wrap = 1). Output (Ho, W) with Ho = (H - 1) / sy + 1, as the padded 3x3 convolution's.
 */

/* floats of omnidl_wino_rows_pack's output for C input and cout output channels (0 on the BLAS build) */
int64_t omnidl_wino_rows_packed_floats(int C, int cout) {
#if HAVE_KERNEL
    return 4 * packed_floats(3 * C, cout);
#else
    (void)C; (void)cout;
    return 0;
#endif
}

/* w (cout, C, 3, 3) contiguous -> the 4 packed panel sets of U[xi] (3C, cout): row ky * C + c of U[xi] holds
 * (G w[co][c][ky][.])[xi] for every output channel co. Threads take whole panels. Returns 0, 2 on the BLAS build. */
int omnidl_wino_rows_pack(const float *w, int cout, int C, float *up, int nthreads) {
#if HAVE_KERNEL
    const int rows = 3 * C, panels = (cout + NR - 1) / NR;
    const int64_t stride = packed_floats(rows, cout);
    (void)nthreads;
#pragma omp parallel for num_threads(nthreads) schedule(static)
    for (int q = 0; q < panels; ++q) {
        const int nr = cout - q * NR < NR ? cout - q * NR : NR;
        for (int r = 0; r < rows; ++r) {
            const int ky = r / C, c = r % C;
            float u[4][NR];
            for (int j = 0; j < NR; ++j) {
                if (j >= nr) {
                    u[0][j] = u[1][j] = u[2][j] = u[3][j] = 0.0f;
                    continue;
                }
                const float *g = w + (((int64_t)(q * NR + j) * C + c) * 3 + ky) * 3;
                u[0][j] = g[0];
                u[1][j] = 0.5f * (g[0] + g[1] + g[2]);
                u[2][j] = 0.5f * (g[0] - g[1] + g[2]);
                u[3][j] = g[2];
            }
            float *d = up + (int64_t)q * rows * NR + (int64_t)r * NR;
            for (int xi = 0; xi < 4; ++xi) memcpy(d + xi * stride, u[xi], sizeof(u[xi]));
        }
    }
    return 0;
#else
    (void)w; (void)cout; (void)C; (void)up; (void)nthreads;
    return 2;
#endif
}

#if HAVE_KERNEL
/* V[xi][i][ky * C + c] (at V[xi * plane + i * ldv + ky * C + c]) of the tiles t0..t0+m-1 (tw tiles per output
 * row) of image rows x (H, W, C); zero: C zeros */
static void wino_rows_input(const float *x, int H, int W, int C, int sy, int wrap, const float *zero, int64_t t0,
                            int m, int tw, float *V, int64_t ldv, int64_t plane) {
    for (int i = 0; i < m; ++i) {
        const int64_t t = t0 + i;
        const int oy = (int)(t / tw), tx = (int)(t % tw);
        for (int ky = 0; ky < 3; ++ky) {
            const int r = sy * oy - 1 + ky;
            const float *p[4];
            for (int b = 0; b < 4; ++b) {
                int col = 2 * tx - 1 + b;
                if (wrap) col = (col + W) % W;
                p[b] = (r < 0 || r >= H || col < 0 || col >= W) ? zero : x + ((int64_t)r * W + col) * C;
            }
            const float *restrict p0 = p[0], *restrict p1 = p[1], *restrict p2 = p[2], *restrict p3 = p[3];
            float *v = V + (int64_t)i * ldv + (int64_t)ky * C;
            float *restrict v0 = v, *restrict v1 = v + plane, *restrict v2 = v + 2 * plane, *restrict v3 = v + 3 * plane;
#pragma omp simd
            for (int c = 0; c < C; ++c) {
                v0[c] = p0[c] - p2[c];
                v1[c] = p1[c] + p2[c];
                v2[c] = p2[c] - p1[c];
                v3[c] = p1[c] - p3[c];
            }
        }
    }
}

/* out (Ho, W, cout) pixels of tiles t0..: y = a^T M (+ bias) (ReLU), output channels [c0, c1) (M's rows ldm apart) */
static void wino_rows_output(const float *M, int64_t plane, int64_t ldm, int m, int c0, int c1, int cout,
                             const float *bias, float *out, int W, int64_t t0, int tw, int relu) {
    for (int i = 0; i < m; ++i) {
        const int64_t t = t0 + i;
        const int oy = (int)(t / tw), tx = (int)(t % tw);
        float *o0 = out + ((int64_t)oy * W + 2 * tx) * cout;
        float *o1 = 2 * tx + 1 < W ? o0 + cout : NULL;
        const float *restrict q0 = M + i * ldm, *restrict q1 = q0 + plane, *restrict q2 = q0 + 2 * plane;
        const float *restrict q3 = q0 + 3 * plane;
#pragma omp simd
        for (int co = c0; co < c1; ++co) {
            const float bb = bias ? bias[co] : 0.0f;
            float y0 = q0[co] + q1[co] + q2[co] + bb;
            if (relu && y0 < 0.0f) y0 = 0.0f;   /* NaN stays NaN */
            o0[co] = y0;
        }
        if (o1) {
#pragma omp simd
            for (int co = c0; co < c1; ++co) {
                const float bb = bias ? bias[co] : 0.0f;
                float y1 = q1[co] - q2[co] - q3[co] + bb;
                if (relu && y1 < 0.0f) y1 = 0.0f;
                o1[co] = y1;
            }
        }
    }
}
#endif

/* 3x3 convolution of vertical stride sy, horizontal stride 1, padding 1 (zero, or wrapped columns when wrap) of B
 * images x (B, H, W, C) channels-last into out (B, Ho, W, cout) by the row Winograd F(2, 3), with `up` from
 * omnidl_wino_rows_pack; bias may be NULL; relu. Tiles are split among `nthreads` OpenMP threads in blocks of
 * `block` tiles, or, with too few tiles for that, the output channels' panels are (each thread then streams its
 * part of the weight). Returns 0, 1 when out of memory, 2 on the BLAS build. */
int omnidl_wino_rows_forward(const float *x, int B, int H, int W, int C, int sy, int wrap, const float *up, int cout,
                             const float *bias, float *out, int relu, int block, int nthreads) {
#if HAVE_KERNEL
    const int Ho = (H - 1) / sy + 1, tw = (W + 1) / 2;
    const int64_t T = (int64_t)Ho * tw, total = (int64_t)B * T, stride = packed_floats(3 * C, cout);
    const int by_channels = split_channels(total, block, nthreads, cout);
    /* split by channels, every thread runs every tile: in one block where there are up to 4 blocks' worth (all of
     * them on 2 threads: fewer than 2 * block * nthreads), so that each thread streams its share of the
     * transformed weight once; the cap bounds each thread's buffers on many-core hosts */
    if (by_channels) block = (int)min64(total, 4 * (int64_t)block);
    int err = 0;
#pragma omp parallel num_threads(nthreads) reduction(| : err)
    {
        int64_t s0, s1;
        int c0, c1;
        forward_share(total, by_channels, cout, &s0, &s1, &c0, &c1);
        /* a row of V a cache line longer than its 3C values: rows a multiple of 4 kB apart (3C = 1024 k) would all
         * fall into one L1 set, and the kernel reads 12 of them at once */
        const int64_t ldv = 3 * (int64_t)C + 16, vplane = wino_plane(block, ldv), mplane = wino_plane(block, cout);
        float *V = (float *)malloc(sizeof(float) * 4 * (size_t)(vplane + mplane));
        float *zero = (float *)calloc((size_t)C, sizeof(float));
        if (!V || !zero) {
            err = 1;
        } else if (c1 > c0) {
            float *M = V + 4 * vplane;
            for (int64_t s = s0; s < s1;) {
                const int64_t b = s / T, t0 = s % T;
                const int m = (int)min64(block, min64(s1 - s, T - t0));
                wino_rows_input(x + b * (int64_t)H * W * C, H, W, C, sy, wrap, zero, t0, m, tw, V, ldv, vplane);
                for (int xi = 0; xi < 4; ++xi)
                    gemm_packed(m, c1 - c0, 3 * C, V + xi * vplane, ldv, 1, up + xi * stride + (int64_t)c0 * 3 * C,
                                M + xi * mplane + c0, cout, 0, NULL);
                wino_rows_output(M, mplane, cout, m, c0, c1, cout, bias, out + b * (int64_t)Ho * W * cout, W, t0, tw,
                                 relu);
                s += m;
            }
        }
        free(V);
        free(zero);
    }
    return err;
#else
    (void)x; (void)B; (void)H; (void)W; (void)C; (void)sy; (void)wrap; (void)up; (void)cout; (void)bias; (void)out;
    (void)relu; (void)block; (void)nthreads;
    return 2;
#endif
}

#if HAVE_KERNEL
/* M = A gy A^T, A = [1 0; 1 1; 1 -1; 0 -1] (the adjoint of the forward's output transform), of the tiles t0..t0+n-1
 * of image rows gy (H, W, cout), zero beyond the map, into rows i0.. of NR-column panels of mp rows: element (xi, i,
 * co) at G[xi * gplane + (co / NR) * mp * NR + (i0 + i) * NR + co % NR], zero beyond cout; zero: cout zeros */
static void wino_grad_tiles(const float *gy, int H, int W, int cout, const float *zero, int64_t t0, int n, int tw,
                            float *G, int64_t gplane, int i0, int mp) {
    const int panels = (cout + NR - 1) / NR;
    for (int i = 0; i < n; ++i) {
        const int64_t t = t0 + i;
        const int ty = (int)(t / tw), tx = (int)(t % tw);
        const float *g[2][2];
        for (int a = 0; a < 2; ++a)
            for (int b = 0; b < 2; ++b) {
                const int r = 2 * ty + a, col = 2 * tx + b;
                g[a][b] = (r < H && col < W) ? gy + ((int64_t)r * W + col) * cout : zero;
            }
        for (int q = 0; q < panels; ++q) {
            const int c0 = q * NR, nr = cout - c0 < NR ? cout - c0 : NR;
            const float *restrict y00 = g[0][0] + c0, *restrict y01 = g[0][1] + c0;
            const float *restrict y10 = g[1][0] + c0, *restrict y11 = g[1][1] + c0;
            float *restrict d = G + (int64_t)q * mp * NR + (int64_t)(i0 + i) * NR;
#pragma omp simd
            for (int j = 0; j < nr; ++j) {
                /* rows of A gy: h_r_b */
                const float h00 = y00[j], h01 = y01[j];
                const float h10 = y00[j] + y10[j], h11 = y01[j] + y11[j];
                const float h20 = y00[j] - y10[j], h21 = y01[j] - y11[j];
                const float h30 = -y10[j], h31 = -y11[j];
                d[j] = h00; d[gplane + j] = h00 + h01; d[2 * gplane + j] = h00 - h01; d[3 * gplane + j] = -h01;
                d[4 * gplane + j] = h10; d[5 * gplane + j] = h10 + h11; d[6 * gplane + j] = h10 - h11;
                d[7 * gplane + j] = -h11;
                d[8 * gplane + j] = h20; d[9 * gplane + j] = h20 + h21; d[10 * gplane + j] = h20 - h21;
                d[11 * gplane + j] = -h21;
                d[12 * gplane + j] = h30; d[13 * gplane + j] = h30 + h31; d[14 * gplane + j] = h30 - h31;
                d[15 * gplane + j] = -h31;
            }
            for (int j = nr; j < NR; ++j)
                for (int xi = 0; xi < 16; ++xi) d[xi * gplane + j] = 0.0f;
        }
    }
}

/* gw (cout, C, 3, 3) = G^T gU G per filter, from gU[xi] (C, cout) at U + xi * plane. The threads split C in blocks
 * of WO_C channels; per block and WO_CO output channels the filters are made in a small buffer (vectors over the
 * output channels, which lie side by side in gU) and written out as one run per output channel (written filter by
 * filter, each output channel's run lay C * 9 floats from the next: 1.1 ms for 256 x 256 channels) */
#define WO_C 16
#define WO_CO 16
static void wino_weight_output(const float *U, int64_t plane, int C, int cout, float *gw) {
    const int blocks = (C + WO_C - 1) / WO_C;
#pragma omp for schedule(static)
    for (int cb = 0; cb < blocks; ++cb) {
        const int c0 = cb * WO_C, nc = C - c0 < WO_C ? C - c0 : WO_C;
        for (int o0 = 0; o0 < cout; o0 += WO_CO) {
            const int no = cout - o0 < WO_CO ? cout - o0 : WO_CO;
            float f[WO_C * 9][WO_CO];                        /* f[ci * 9 + k][l]: filter (o0 + l, c0 + ci) */
            for (int ci = 0; ci < nc; ++ci) {
                const float *restrict u = U + (int64_t)(c0 + ci) * cout + o0;
                float *restrict f0 = f[ci * 9], *restrict f1 = f[ci * 9 + 1], *restrict f2 = f[ci * 9 + 2];
                float *restrict f3 = f[ci * 9 + 3], *restrict f4 = f[ci * 9 + 4], *restrict f5 = f[ci * 9 + 5];
                float *restrict f6 = f[ci * 9 + 6], *restrict f7 = f[ci * 9 + 7], *restrict f8 = f[ci * 9 + 8];
#pragma omp simd
                for (int l = 0; l < no; ++l) {
                    /* gU G, row r: e_r_k */
                    const float a1 = u[plane + l], a2 = u[2 * plane + l], b1 = u[5 * plane + l], b2 = u[6 * plane + l];
                    const float c1 = u[9 * plane + l], c2 = u[10 * plane + l], d1 = u[13 * plane + l];
                    const float d2 = u[14 * plane + l];
                    const float e00 = u[l] + 0.5f * (a1 + a2), e01 = 0.5f * (a1 - a2);
                    const float e02 = 0.5f * (a1 + a2) + u[3 * plane + l];
                    const float e10 = u[4 * plane + l] + 0.5f * (b1 + b2), e11 = 0.5f * (b1 - b2);
                    const float e12 = 0.5f * (b1 + b2) + u[7 * plane + l];
                    const float e20 = u[8 * plane + l] + 0.5f * (c1 + c2), e21 = 0.5f * (c1 - c2);
                    const float e22 = 0.5f * (c1 + c2) + u[11 * plane + l];
                    const float e30 = u[12 * plane + l] + 0.5f * (d1 + d2), e31 = 0.5f * (d1 - d2);
                    const float e32 = 0.5f * (d1 + d2) + u[15 * plane + l];
                    /* G^T (gU G) */
                    f0[l] = e00 + 0.5f * (e10 + e20);
                    f1[l] = e01 + 0.5f * (e11 + e21);
                    f2[l] = e02 + 0.5f * (e12 + e22);
                    f3[l] = 0.5f * (e10 - e20);
                    f4[l] = 0.5f * (e11 - e21);
                    f5[l] = 0.5f * (e12 - e22);
                    f6[l] = 0.5f * (e10 + e20) + e30;
                    f7[l] = 0.5f * (e11 + e21) + e31;
                    f8[l] = 0.5f * (e12 + e22) + e32;
                }
            }
            for (int l = 0; l < no; ++l) {
                float *dst = gw + ((int64_t)(o0 + l) * C + c0) * 9;
                for (int idx = 0; idx < nc * 9; ++idx) dst[idx] = f[idx][l];
            }
        }
    }
}
#endif

#if HAVE_KERNEL
/* floats between the planes of the weight gradient's gU: a cache line more than C * cout (planes of a multiple of
 * 4 kB fall into the same cache sets) */
static int64_t wgrad_uplane(int C, int cout) { return (int64_t)C * cout + 16; }

/* omnidl_wino_weight_grad's chunk (block tiles, at most one image's T) and its buffers' sizes in floats */
static void wgrad_sizes(int H, int W, int C, int cout, int block, int nthreads, int *cap, int64_t *vplane,
                        int64_t *gplane, int64_t *total) {
    const int64_t T = (int64_t)((H + 1) / 2) * ((W + 1) / 2);
    *cap = (int)min64(block < 1 ? 1 : block, T);
    *vplane = wino_plane(*cap, C);
    *gplane = packed_floats(*cap, cout) + 16;
    const int64_t a_floats = (int64_t)A_BLOCK * MR * KC_BLOCK;
    *total = 16 * (*vplane + *gplane + wgrad_uplane(C, cout)) + (C > cout ? C : cout)
             + (a_floats > 0 ? a_floats : 1) * (nthreads < 1 ? 1 : nthreads);
}
#endif

/* floats of the workspace of omnidl_wino_weight_grad (0 on the BLAS build) */
int64_t omnidl_wino_weight_grad_floats(int H, int W, int C, int cout, int block, int nthreads) {
#if HAVE_KERNEL
    int cap;
    int64_t vplane, gplane, total;
    wgrad_sizes(H, W, C, cout, block, nthreads, &cap, &vplane, &gplane, &total);
    return total;
#else
    (void)H; (void)W; (void)C; (void)cout; (void)block; (void)nthreads;
    return 0;
#endif
}

/* The weight gradient of omnidl_wino_forward's convolution: gw (cout, C, 3, 3) = the sum over B images x (B, H, W, C)
 * and output gradients gy (B, H, W, cout), both channels-last, of gy times the 3x3 neighbourhoods of x (zero or
 * wrapped columns: `wrap` as the forward's), written (not added). By F(2x2, 3x3): y = A^T [U (.) V] A per tile, so
 * the gradient of U[xi] (C, cout) is the sum over tiles of V[xi]^T M[xi] with M = A gy A^T, and gw = G^T gU G. Per
 * chunk of `block` tiles of one image the threads transform their share of the tiles, then run the 16 products
 * (V[xi]^T (C, tiles) @ M[xi] (tiles, cout), accumulated into gU[xi]) split by xi. `work`: the caller's
 * omnidl_wino_weight_grad_floats floats (kept between calls: fresh memory of that size is page-faulted on every
 * call, which cost as much as the products). Returns 0, 2 on the BLAS build. */
int omnidl_wino_weight_grad(const float *x, const float *gy, int B, int H, int W, int C, int cout, int wrap,
                            float *gw, int block, float *work, int nthreads) {
#if HAVE_KERNEL
    const int tw = (W + 1) / 2;
    const int64_t T = (int64_t)((H + 1) / 2) * tw;
    int cap;
    int64_t vplane, gplane, total;
    wgrad_sizes(H, W, C, cout, block, nthreads, &cap, &vplane, &gplane, &total);
    const int64_t a_floats = (int64_t)A_BLOCK * MR * KC_BLOCK, uplane = wgrad_uplane(C, cout);
    float *V = work, *G = V + 16 * vplane, *U = G + 16 * gplane, *zero = U + 16 * uplane;
    float *ap = zero + (C > cout ? C : cout);
    memset(zero, 0, sizeof(float) * (size_t)(C > cout ? C : cout));
#pragma omp parallel num_threads(nthreads)
    {
        int t, nt;
        team(&t, &nt);
        for (int b = 0; b < B; ++b) {
            const float *xb = x + (int64_t)b * H * W * C, *gb = gy + (int64_t)b * H * W * cout;
            for (int64_t t0 = 0; t0 < T; t0 += cap) {
                const int m = (int)min64(cap, T - t0);
                const int i0 = (int)span_edge(m, t, nt), i1 = (int)span_edge(m, t + 1, nt);
                if (i1 > i0) {
                    wino_input(xb, H, W, C, wrap, zero, t0 + i0, i1 - i0, tw, V + (int64_t)i0 * C, vplane);
                    wino_grad_tiles(gb, H, W, cout, zero, t0 + i0, i1 - i0, tw, G, gplane, i0, m);
                }
#pragma omp barrier
                const int add = b > 0 || t0 > 0;
                for (int xi = t; xi < 16; xi += nt) {
#if A_BLOCK > 0
                    gemm_packed_rows(C, cout, m, V + xi * vplane, C, G + xi * gplane, U + xi * uplane, cout, add,
                                     ap + t * a_floats);
#else
                    gemm_packed(C, cout, m, V + xi * vplane, 1, C, G + xi * gplane, U + xi * uplane, cout, add, NULL);
#endif
                }
#pragma omp barrier
            }
        }
        wino_weight_output(U, uplane, C, cout, gw);
    }
    (void)ap;
    return 0;
#else
    (void)x; (void)gy; (void)B; (void)H; (void)W; (void)C; (void)cout; (void)wrap; (void)gw; (void)block;
    (void)work; (void)nthreads;
    return 2;
#endif
}
