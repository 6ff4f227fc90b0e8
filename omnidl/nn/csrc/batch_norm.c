/* Batch norm in training on a contiguous (B, C, H, W) float32 map: per channel the batch's mean and biased
 * variance over B * H * W values, y = (x - mean) * invstd * w + b with invstd = 1 / sqrt(var + eps), the running
 * statistics' update, and the backward (omnidl_bn_train_backward).
 *
 * PyTorch's CPU kernel for this layout took 0.95 ms for 128 channels on 64x128 on 2 threads, against 0.09 ms for
 * its eval-mode pass over the same map. Here each channel's planes are read three times, from the cache after the
 * first: the sum of x - x0 (x0 the channel's first value), the squared deviations from the mean (two passes, for
 * an exact variance), and the output (x - mean) * scale + b; the threads split the channels. The sums run in 16
 * float lanes, added into float64 every BN_CHUNK values.
 */
#include <math.h>
#include <stdint.h>

#define BN_LANES 16
#define BN_CHUNK 4096

/* 16 float lanes (one zmm with AVX-512; GCC splits it into narrower vectors elsewhere), loaded unaligned */
typedef float lanes __attribute__((vector_size(BN_LANES * sizeof(float))));
typedef float lanes_u __attribute__((vector_size(BN_LANES * sizeof(float)), aligned(sizeof(float))));

/* (macros: a function passing such a vector by value changes the ABI on builds without AVX-512) */
#define LOAD(p) (*(const lanes_u *)(p))
#define ADD_LANES(s, v)                                                                                            \
    for (int l_ = 0; l_ < BN_LANES; ++l_) (s) += (v)[l_]

/* sum over x[0..n) of (x - hi) - lo, or of its square (`square`): float lanes, added into float64 every BN_CHUNK
 * values. Shifted by (an estimate of) the mean, the terms stay small where the values are far from zero: x - hi is
 * exact near hi, and (x - hi) - lo keeps the digits that x * scale + shift would cancel. */
static double plane_sum(const float *x, int64_t n, float hi, float lo, int square) {
    double s = 0.0;
    for (int64_t i0 = 0; i0 < n; i0 += BN_CHUNK) {
        const int64_t i1 = n - i0 < BN_CHUNK ? n : i0 + BN_CHUNK;
        lanes acc = {0};
        int64_t i = i0;
        if (square) {
            for (; i + BN_LANES <= i1; i += BN_LANES) {
                const lanes d = (LOAD(x + i) - hi) - lo;
                acc += d * d;
            }
            for (; i < i1; ++i) s += (double)(((x[i] - hi) - lo) * ((x[i] - hi) - lo));
        } else {
            for (; i + BN_LANES <= i1; i += BN_LANES) acc += (LOAD(x + i) - hi) - lo;
            for (; i < i1; ++i) s += (double)((x[i] - hi) - lo);
        }
        ADD_LANES(s, acc);
    }
    return s;
}

/* x, y (B, C, hw) contiguous; w, b: C values or NULL (1 and 0); save_mean, save_invstd: C values written;
 * running_mean, running_var: C values updated with factor `momentum` (the unbiased variance), or NULL. Returns 0; 2
 * when there are no values per channel. */
int omnidl_bn_train(const float *x, int64_t B, int64_t C, int64_t hw, const float *w, const float *b, double eps,
                    double momentum, float *running_mean, float *running_var, float *y, float *save_mean,
                    float *save_invstd, int nthreads) {
    const int64_t n = B * hw;
    if (n < 1) return 2;
#pragma omp parallel for num_threads(nthreads) schedule(static)
    for (int64_t c = 0; c < C; ++c) {
        const float pivot = x[c * hw];             /* the first value: the sums of x - pivot stay small */
        double s = 0.0;
        for (int64_t i = 0; i < B; ++i) s += plane_sum(x + (i * C + c) * hw, hw, pivot, 0.0f, 0);
        const double mean = (double)pivot + s / (double)n;
        const float hi = (float)mean, lo = (float)(mean - (double)hi);
        double q = 0.0;
        for (int64_t i = 0; i < B; ++i) q += plane_sum(x + (i * C + c) * hw, hw, hi, lo, 1);
        const double var = q / (double)n, invstd = 1.0 / sqrt(var + eps);
        const float scale = (float)((w ? (double)w[c] : 1.0) * invstd), shift = b ? b[c] : 0.0f;
        for (int64_t i = 0; i < B; ++i) {
            const float *xp = x + (i * C + c) * hw;
            float *yp = y + (i * C + c) * hw;
            for (int64_t j = 0; j < hw; ++j) yp[j] = ((xp[j] - hi) - lo) * scale + shift;
        }
        save_mean[c] = (float)mean;
        save_invstd[c] = (float)invstd;
        if (running_mean) {
            running_mean[c] = (float)((1.0 - momentum) * (double)running_mean[c] + momentum * mean);
            running_var[c] = (float)((1.0 - momentum) * (double)running_var[c] +
                                     momentum * var * (double)n / (double)(n > 1 ? n - 1 : 1));
        }
    }
    return 0;
}

/* The backward of omnidl_bn_train (training statistics): with xh = (x - mean) invstd, per channel
 *     gb = sum gy,   gw = sum gy xh,   gx = w invstd (gy - gb / n - xh gw / n)
 * (w = 1 without affine parameters). x, gy, gx (B, C, hw) contiguous; w: C values or NULL; mean, invstd: the
 * forward's; gx, gw, gb: written where not NULL. One pass for the two sums (float lanes into float64 every BN_CHUNK
 * values), one for gx. Returns 0; 2 when there are no values per channel. */
int omnidl_bn_train_backward(const float *x, const float *gy, int64_t B, int64_t C, int64_t hw, const float *w,
                             const float *mean, const float *invstd, float *gx, float *gw, float *gb, int nthreads) {
    const int64_t n = B * hw;
    if (n < 1) return 2;
#pragma omp parallel for num_threads(nthreads) schedule(static)
    for (int64_t c = 0; c < C; ++c) {
        const double m = mean[c];
        const float hi = (float)m, lo = (float)(m - (double)hi);
        double sg = 0.0, sgd = 0.0;                   /* sum gy, sum gy (x - mean) */
        for (int64_t i = 0; i < B; ++i) {
            const float *xp = x + (i * C + c) * hw, *gp = gy + (i * C + c) * hw;
            for (int64_t j0 = 0; j0 < hw; j0 += BN_CHUNK) {
                const int64_t j1 = hw - j0 < BN_CHUNK ? hw : j0 + BN_CHUNK;
                lanes a = {0}, d = {0};
                int64_t j = j0;
                for (; j + BN_LANES <= j1; j += BN_LANES) {
                    const lanes gv = LOAD(gp + j);
                    a += gv;
                    d += gv * ((LOAD(xp + j) - hi) - lo);
                }
                for (; j < j1; ++j) {
                    sg += gp[j];
                    sgd += (double)(gp[j] * ((xp[j] - hi) - lo));
                }
                ADD_LANES(sg, a);
                ADD_LANES(sgd, d);
            }
        }
        const double is = invstd[c], wc = w ? (double)w[c] : 1.0;
        if (gb) gb[c] = (float)sg;
        if (gw) gw[c] = (float)(sgd * is);
        if (!gx) continue;
        /* gx = k (gy - sg / n) - k' (x - mean) with k = w invstd, k' = w invstd^3 sgd / n */
        const float k = (float)(wc * is), shift = (float)(sg / (double)n);
        const float k2 = (float)(wc * is * is * is * sgd / (double)n);
        for (int64_t i = 0; i < B; ++i) {
            const float *xp = x + (i * C + c) * hw, *gp = gy + (i * C + c) * hw;
            float *op = gx + (i * C + c) * hw;
            for (int64_t j = 0; j < hw; ++j) op[j] = k * (gp[j] - shift) - k2 * ((xp[j] - hi) - lo);
        }
    }
    return 0;
}
