/* Batch norm in training, forward, on a contiguous (B, C, H, W) float32 map: per channel the batch's mean and
 * biased variance over B * H * W values, y = (x - mean) * invstd * w + b with invstd = 1 / sqrt(var + eps), and the
 * running statistics' update.
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

/* sum over x[0..n) of (x - hi) - lo, or of its square (`square`): float lanes, added into float64 every BN_CHUNK
 * values. Shifted by (an estimate of) the mean, the terms stay small where the values are far from zero: x - hi is
 * exact near hi, and (x - hi) - lo keeps the digits that x * scale + shift would cancel. */
static double plane_sum(const float *x, int64_t n, float hi, float lo, int square) {
    double s = 0.0;
    for (int64_t i0 = 0; i0 < n; i0 += BN_CHUNK) {
        const int64_t i1 = n - i0 < BN_CHUNK ? n : i0 + BN_CHUNK;
        float acc[BN_LANES] = {0};
        int64_t i = i0;
        if (square) {
            for (; i + BN_LANES <= i1; i += BN_LANES)
                for (int l = 0; l < BN_LANES; ++l) {
                    const float d = (x[i + l] - hi) - lo;
                    acc[l] += d * d;
                }
            for (int l = 0; i < i1; ++i, ++l) acc[l] += ((x[i] - hi) - lo) * ((x[i] - hi) - lo);
        } else {
            for (; i + BN_LANES <= i1; i += BN_LANES)
                for (int l = 0; l < BN_LANES; ++l) acc[l] += (x[i + l] - hi) - lo;
            for (int l = 0; i < i1; ++i, ++l) acc[l] += (x[i] - hi) - lo;
        }
        for (int l = 0; l < BN_LANES; ++l) s += acc[l];
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
