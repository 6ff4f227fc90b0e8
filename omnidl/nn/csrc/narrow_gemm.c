/* A weight's product on few columns: c (m, n) (+)= a (m, k) b (k, n) for n <= NARROW_MAX (WIDE_MAX for a weight's
 * transpose), float32.
 *
 * On a small feature map (2x4 positions at the bottom of ResNet-50 for a 128x64 input) the products of a
 * convolution's weight have only a few columns, one per output position: c = W x (the forward) and c = W^T g
 * (the input gradient). They read the whole weight for a handful of multiply-adds per element, so they are bound
 * by that read. The blocked register kernel of fixed_conv.c (32-column panels) then runs mostly on zero lanes,
 * and the BLAS's product from a transposed weight runs as a slow strided loop. Here every element of a is
 * loaded once and multiplied into all n columns from registers:
 *
 *   rows  (a's rows contiguous, acs == 1: a weight W): NROWS rows at a time, the vector lanes along k; b is
 *         first copied transposed (n, k) so that each column is a contiguous vector; each row's n sums are
 *         reduced across the lanes at the end;
 *   cols  (a's columns contiguous, ars == 1: a weight's transpose W^T, rows of W side by side): NROWS vectors of
 *         consecutive rows of c at a time, the lanes along m; each step over k loads a piece of one weight row
 *         and multiplies it by n broadcast values of b; up to WIDE_MAX columns, in groups of NARROW_MAX over
 *         chunks of k, a chunk's piece of the weight read again from L2 by the later groups (no copy of the
 *         weight, where the register kernel copies it block by block and runs its 32-column panels partly on zero
 *         lanes).
 *
 * The threads split the rows of c. `accumulate` adds to c (a bias written there first) instead of writing it.
 * Vectors are GCC's generic vectors: 16 lanes (one zmm) with AVX-512, 8 with AVX, else 4 (SSE, NEON); with
 * AVX-512, two rows (or vectors) of n <= NARROW_MAX accumulators fill at most 22 of the 32 registers; with 16
 * registers, one.
 */
#include <stdint.h>
#include <stdlib.h>

/* the most columns taken (as many cases as NARROW_CASES below lists) */
#define NARROW_MAX 11
#if defined(__AVX512F__)
#define NVL 16
#define NROWS 2
#elif defined(__AVX__)
#define NVL 8
#define NROWS 1
#else
#define NVL 4
#define NROWS 1
#endif
/* weight rows fetched ahead in the cols form (their stride is a whole weight row) */
#ifndef NARROW_AHEAD
#define NARROW_AHEAD 8
#endif

typedef float vec __attribute__((vector_size(NVL * sizeof(float))));
typedef float vec_u __attribute__((vector_size(NVL * sizeof(float)), aligned(sizeof(float))));

static inline vec load_u(const float *p) { return *(const vec_u *)p; }

static inline float lane_sum(vec v) {
    float s = 0.0f;
    for (int l = 0; l < NVL; ++l) s += v[l];
    return s;
}

static inline void put(float *c, float v, int accumulate) { *c = accumulate ? *c + v : v; }

/* F(N, ...) for the number of columns v in 1..NARROW_MAX, N a constant (a loop over N columns unrolled) */
#define NARROW_CASES(v, F, ...)                                                                                    \
    switch (v) {                                                                                                   \
    case 1: F(1, __VA_ARGS__); break;                                                                              \
    case 2: F(2, __VA_ARGS__); break;                                                                              \
    case 3: F(3, __VA_ARGS__); break;                                                                              \
    case 4: F(4, __VA_ARGS__); break;                                                                              \
    case 5: F(5, __VA_ARGS__); break;                                                                              \
    case 6: F(6, __VA_ARGS__); break;                                                                              \
    case 7: F(7, __VA_ARGS__); break;                                                                              \
    case 8: F(8, __VA_ARGS__); break;                                                                              \
    case 9: F(9, __VA_ARGS__); break;                                                                              \
    case 10: F(10, __VA_ARGS__); break;                                                                            \
    default: F(11, __VA_ARGS__); break;                                                                            \
    }

/* rows i0 .. i0 + NROWS - 1 (those below m) of the rows form; bt (n, k) is b transposed */
static inline __attribute__((always_inline)) void rows_block(const int n, int m, int k, int i0, const float *a,
                                                             int64_t ars, const float *bt, float *c, int64_t ldc,
                                                             int accumulate) {
    vec acc[NROWS][NARROW_MAX];
    const float *row[NROWS];
#pragma GCC unroll 4
    for (int r = 0; r < NROWS; ++r) {
        row[r] = a + (int64_t)(i0 + r < m ? i0 + r : i0) * ars;
#pragma GCC unroll 16
        for (int j = 0; j < n; ++j) acc[r][j] = (vec){0};
    }
    int p = 0;
    for (; p + NVL <= k; p += NVL) {
        vec x[NROWS];
#pragma GCC unroll 4
        for (int r = 0; r < NROWS; ++r) x[r] = load_u(row[r] + p);
#pragma GCC unroll 16
        for (int j = 0; j < n; ++j) {
            const vec y = load_u(bt + (int64_t)j * k + p);
#pragma GCC unroll 4
            for (int r = 0; r < NROWS; ++r) acc[r][j] += x[r] * y;
        }
    }
    for (int r = 0; r < NROWS && i0 + r < m; ++r)
        for (int j = 0; j < n; ++j) {
            float s = lane_sum(acc[r][j]);
            for (int q = p; q < k; ++q) s += row[r][q] * bt[(int64_t)j * k + q];
            put(c + (int64_t)(i0 + r) * ldc + j, s, accumulate);
        }
}

/* the cols form (up to WIDE_MAX columns): per block of NROWS * NVL rows of c, the k-steps run in chunks of
 * KC_WIDE and, within each chunk, the columns in groups of at most NARROW_MAX, the block's sums kept transposed in
 * `ct` (n, NROWS * NVL). The chunk's piece of the weight (KC_WIDE pieces of rows, 32 KB with AVX-512) comes from
 * memory for the first group (fetched ahead) and from L2 for the others: no copy of the weight is made. */
#define KC_WIDE 256
#define WIDE_MAX 24
static inline __attribute__((always_inline)) void cols_group(const int nj, int p0, int p1, int k, int i0,
                                                             const float *a, int64_t acs, const float *b, int64_t brs,
                                                             int64_t bcs, float *ct, int first, int fetch) {
    vec acc[NROWS][NARROW_MAX];
#pragma GCC unroll 4
    for (int r = 0; r < NROWS; ++r)
#pragma GCC unroll 16
        for (int j = 0; j < nj; ++j) acc[r][j] = first ? (vec){0} : *(const vec *)(ct + (j * NROWS + r) * NVL);
    for (int p = p0; p < p1; ++p) {
        const float *src = a + i0 + (int64_t)p * acs;
        if (fetch && p + NARROW_AHEAD < k) {
#pragma GCC unroll 4
            for (int r = 0; r < NROWS; ++r) __builtin_prefetch(src + NARROW_AHEAD * acs + r * NVL);
        }
        vec x[NROWS];
#pragma GCC unroll 4
        for (int r = 0; r < NROWS; ++r) x[r] = load_u(src + r * NVL);
#pragma GCC unroll 16
        for (int j = 0; j < nj; ++j) {
            const float y = b[(int64_t)p * brs + (int64_t)j * bcs];
#pragma GCC unroll 4
            for (int r = 0; r < NROWS; ++r) acc[r][j] += x[r] * y;
        }
    }
#pragma GCC unroll 4
    for (int r = 0; r < NROWS; ++r)
#pragma GCC unroll 16
        for (int j = 0; j < nj; ++j) *(vec *)(ct + (j * NROWS + r) * NVL) = acc[r][j];
}

/* one block of the cols form: rows i0 .. i0 + NROWS * NVL - 1 of c (all below m) */
static void cols_wide(int n, int k, int i0, const float *a, int64_t acs, const float *b, int64_t brs, int64_t bcs,
                      float *c, int64_t ldc, int accumulate) {
    vec ctv[WIDE_MAX * NROWS];
    float *ct = (float *)ctv;
    for (int p0 = 0; p0 < k; p0 += KC_WIDE) {
        const int p1 = k - p0 < KC_WIDE ? k : p0 + KC_WIDE;
        for (int j0 = 0; j0 < n; j0 += NARROW_MAX) {
            const int nj = n - j0 < NARROW_MAX ? n - j0 : NARROW_MAX;
            const float *bj = b + (int64_t)j0 * bcs;
            float *cj = ct + (int64_t)j0 * NROWS * NVL;
            const int first = p0 == 0, fetch = j0 == 0;
#define GROUP(N, ...) cols_group(N, __VA_ARGS__)
            NARROW_CASES(nj, GROUP, p0, p1, k, i0, a, acs, bj, brs, bcs, cj, first, fetch)
#undef GROUP
        }
    }
    for (int r = 0; r < NROWS; ++r)
        for (int l = 0; l < NVL; ++l)
            for (int j = 0; j < n; ++j)
                put(c + (int64_t)(i0 + r * NVL + l) * ldc + j, ct[(j * NROWS + r) * NVL + l], accumulate);
}

/* the rows of c from i0 (fewer than a whole cols block) in the cols form, one at a time */
static void cols_tail(int n, int m, int k, int i0, const float *a, int64_t acs, const float *b, int64_t brs,
                      int64_t bcs, float *c, int64_t ldc, int accumulate) {
    for (int i = i0; i < m; ++i)
        for (int j = 0; j < n; ++j) {
            float s = 0.0f;
            for (int p = 0; p < k; ++p) s += a[i + (int64_t)p * acs] * b[(int64_t)p * brs + (int64_t)j * bcs];
            put(c + (int64_t)i * ldc + j, s, accumulate);
        }
}

/* Returns 0; 1 when a buffer cannot be allocated; 2 when the product is not one of the two forms (n outside
 * 1..NARROW_MAX, or 1..WIDE_MAX for the cols form, or neither a's rows nor its columns contiguous): the caller
 * takes another product. */
int omnidl_gemm_narrow(int m, int n, int k, const float *a, int64_t ars, int64_t acs, const float *b, int64_t brs,
                       int64_t bcs, float *c, int64_t ldc, int accumulate, int nthreads) {
    if (n < 1 || m < 1 || k < 1) return 2;
    if (ars == 1 && acs > 1 && n <= WIDE_MAX) {
        const int width = NROWS * NVL, blocks = m / width;
#pragma omp parallel for num_threads(nthreads) schedule(static)
        for (int s = 0; s < blocks; ++s) cols_wide(n, k, s * width, a, acs, b, brs, bcs, c, ldc, accumulate);
        cols_tail(n, m, k, blocks * width, a, acs, b, brs, bcs, c, ldc, accumulate);
        return 0;
    }
    if (n > NARROW_MAX) return 2;
    if (acs == 1) {
        float *bt = (float *)malloc(sizeof(float) * (size_t)n * (size_t)k);
        if (!bt) return 1;
        for (int j = 0; j < n; ++j)
            for (int p = 0; p < k; ++p) bt[(int64_t)j * k + p] = b[(int64_t)p * brs + (int64_t)j * bcs];
        const int blocks = (m + NROWS - 1) / NROWS;
#pragma omp parallel for num_threads(nthreads) schedule(static)
        for (int s = 0; s < blocks; ++s) {
#define ROWS_CASE(N, ...) rows_block(N, __VA_ARGS__)
            NARROW_CASES(n, ROWS_CASE, m, k, s * NROWS, a, ars, bt, c, ldc, accumulate)
#undef ROWS_CASE
        }
        free(bt);
        return 0;
    }
    return 2;
}
