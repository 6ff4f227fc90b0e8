/* The backward of PReLU on contiguous (B, C, N) float32 maps (N = H*W), one slope per channel or one for all:
 *
 *     gx[b, c, i] = g          where x > 0,  else  a[c] * g
 *     ga[b, c]    = sum_i x g  over the i where x <= 0          (the caller sums over b, and over c for one slope)
 *
 * These are PyTorch's formulas (at x = 0 the slope's side, which adds nothing to ga). One pass reads x and g and
 * writes gx; the sums are kept per plane in float lanes over blocks of at most BLOCK elements and added up in
 * double, so their rounding stays far below float32's over a whole plane. Planes shorter than a block (a deep
 * layer's 16x32 or 8x16 map) run in whole lanes too: element by element, with a double sum, a 256 x 16 x 32 map
 * took 0.62 ms against 0.03 ms. The planes are split across the OpenMP threads.
 */
#include <stdint.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#define LANES 16
#define BLOCK (LANES * 64)

static double plane(const float *restrict x, const float *restrict g, float *restrict gx, float s, int64_t n) {
    double total = 0.0;
    int64_t i = 0;
    while (i + LANES <= n) {  /* whole lanes, in blocks of at most BLOCK */
        const int64_t end = i + BLOCK <= n ? i + BLOCK : i + (n - i) / LANES * LANES;
        float acc[LANES] = {0};
        for (int64_t j = i; j < end; j += LANES)
            for (int l = 0; l < LANES; ++l) {
                /* both sides computed either way: GCC does not vectorise a conditional float product */
                const float xv = x[j + l], gv = g[j + l], sg = s * gv, xg = xv * gv;
                const int pos = xv > 0.f;
                gx[j + l] = pos ? gv : sg;
                acc[l] += pos ? 0.f : xg;
            }
        for (int l = 0; l < LANES; ++l)
            total += acc[l];
        i = end;
    }
    for (; i < n; ++i) {
        const float xv = x[i], gv = g[i];
        gx[i] = xv > 0.f ? gv : s * gv;
        total += xv > 0.f ? 0.0 : (double)(xv * gv);
    }
    return total;
}

/* x, g, gx: (B, C, N); a: C slopes (per_channel) or one; ga: (B, C) doubles. Returns 0. */
int omnidl_prelu_backward(const float *x, const float *g, const float *a, int per_channel, int64_t B, int64_t C,
                          int64_t N, float *gx, double *ga, int nthreads) {
    const int64_t planes = B * C;
#ifdef _OPENMP
#pragma omp parallel for schedule(static) num_threads(nthreads)
#endif
    for (int64_t p = 0; p < planes; ++p) {
        const float s = a[per_channel ? p % C : 0];
        ga[p] = plane(x + p * N, g + p * N, gx + p * N, s, N);
    }
    (void)nthreads;
    return 0;
}
