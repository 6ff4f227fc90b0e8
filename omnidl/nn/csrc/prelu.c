/* The backward of PReLU on contiguous (B, C, N) float32 maps (N = H*W), one slope per channel or one for all:
 *
 *     gx[b, c, i] = g          where x > 0,  else  a[c] * g
 *     ga[b, c]    = sum_i x g  over the i where x <= 0          (the caller sums over b, and over c for one slope)
 *
 * These are PyTorch's formulas (at x = 0 the slope's side, which adds nothing to ga). One pass reads x and g and
 * writes gx; the sums are kept per plane in float lanes over blocks of BLOCK elements and added up in double, so
 * their rounding stays far below float32's over a whole plane. The planes are split across the OpenMP threads.
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
    for (; i + BLOCK <= n; i += BLOCK) {
        float acc[LANES] = {0};
        for (int64_t j = i; j < i + BLOCK; j += LANES)
            for (int l = 0; l < LANES; ++l) {
                const float xv = x[j + l], gv = g[j + l];
                const int pos = xv > 0.f;
                gx[j + l] = pos ? gv : s * gv;
                acc[l] += pos ? 0.f : xv * gv;
            }
        for (int l = 0; l < LANES; ++l)
            total += acc[l];
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
