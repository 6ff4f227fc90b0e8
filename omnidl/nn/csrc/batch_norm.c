/* Batch norm in training on a contiguous (B, C, H, W) float32 map: per channel the batch's mean and biased
 * variance over B * H * W values, y = (x - mean) * invstd * w + b with invstd = 1 / sqrt(var + eps), the running
 * statistics' update, and the backward (omnidl_bn_train_backward).
 *
 * PyTorch's CPU kernel for this layout took 0.95 ms for 128 channels on 64x128 on 2 threads, against 0.09 ms for
 * its eval-mode pass over the same map. Here each channel's planes are read three times, from the cache after the
 * first: the sum of x - x0 (x0 the channel's first value), the squared deviations from the mean (two passes, for
 * an exact variance), and the output (x - mean) * scale + b; the threads split the channels. The sums run in 16
 * float lanes, added into float64 every BN_CHUNK values.
 *
 * An activation may follow in the same passes (`act`): ReLU, or PReLU with one slope per channel or one for all. The
 * forward then writes only the activation's output, and the backward recomputes the normalised value from x with the
 * forward's own per-channel constants (`affine`: the mean's two floats, the scale and the shift, so that each value
 * and hence each side of the kink is the forward's) instead of reading a saved map.
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>

#define BN_LANES 16
#define BN_CHUNK 4096

/* 16 float lanes (one zmm with AVX-512; GCC splits it into narrower vectors elsewhere), loaded unaligned */
typedef float lanes __attribute__((vector_size(BN_LANES * sizeof(float))));
typedef float lanes_u __attribute__((vector_size(BN_LANES * sizeof(float)), aligned(sizeof(float))));

/* the activation after the normalisation (`act` of the functions below) */
enum { BN_ACT_NONE = 0, BN_ACT_RELU = 1, BN_ACT_PRELU = 2 };

/* the normalised value of x: the one expression of the forward and the fused backward (the same rounding in both) */
static inline float bn_value(float x, float hi, float lo, float scale, float shift) {
    return ((x - hi) - lo) * scale + shift;
}

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

/* y = v, max(v, 0) or PReLU(v) of the normalised values v of one plane (act; slope s for PReLU) */
static void plane_out(const float *restrict xp, float *restrict yp, int64_t hw, float hi, float lo, float scale,
                      float shift, int act, float s) {
    if (act == BN_ACT_RELU)
        for (int64_t j = 0; j < hw; ++j) {
            const float v = bn_value(xp[j], hi, lo, scale, shift);
            yp[j] = v <= 0.f ? 0.f : v;                /* PyTorch's: NaN stays NaN */
        }
    else if (act == BN_ACT_PRELU)
        for (int64_t j = 0; j < hw; ++j) {
            const float v = bn_value(xp[j], hi, lo, scale, shift);
            yp[j] = v > 0.f ? v : s * v;
        }
    else
        for (int64_t j = 0; j < hw; ++j) yp[j] = bn_value(xp[j], hi, lo, scale, shift);
}

/* x, y (B, C, hw) contiguous; w, b: C values or NULL (1 and 0); save_mean, save_invstd: C values written;
 * running_mean, running_var: C values updated with factor `momentum` (the unbiased variance), or NULL. act: the
 * activation written (BN_ACT_*), slope: PReLU's C slopes (per_channel) or one; save_affine: NULL or 4 C values
 * written, per channel the constants of bn_value (hi, lo, scale, shift) for the fused backward. Returns 0; 2 when
 * there are no values per channel. */
int omnidl_bn_train(const float *x, int64_t B, int64_t C, int64_t hw, const float *w, const float *b, double eps,
                    double momentum, float *running_mean, float *running_var, float *y, float *save_mean,
                    float *save_invstd, int act, const float *slope, int per_channel, float *save_affine,
                    int nthreads) {
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
        const float a = act == BN_ACT_PRELU ? slope[per_channel ? c : 0] : 0.0f;
        for (int64_t i = 0; i < B; ++i)
            plane_out(x + (i * C + c) * hw, y + (i * C + c) * hw, hw, hi, lo, scale, shift, act, a);
        if (save_affine) {
            save_affine[c] = hi;
            save_affine[C + c] = lo;
            save_affine[2 * C + c] = scale;
            save_affine[3 * C + c] = shift;
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

/* the activation's gradient e = g act'(v) at the normalised value v, and the PReLU slope's term (v g where v is
 * not > 0): PyTorch's sides of the kink (ReLU: 0 where the output is <= 0; PReLU: the slope where the input is not
 * > 0), so that NaN takes the same side. `act` is a constant at each call (the loops below are compiled per
 * activation). */
#define ACT_GRAD(act, v, g, s, e, term)                                                                            \
    do {                                                                                                           \
        if ((act) == BN_ACT_RELU) {                                                                                \
            (e) = (v) <= 0.f ? 0.f : (g);                                                                          \
        } else if ((act) == BN_ACT_PRELU) {                                                                        \
            (e) = (v) > 0.f ? (g) : (s) * (g);                                                                     \
            (term) = (v) > 0.f ? 0.f : (v) * (g);                                                                  \
        } else {                                                                                                   \
            (e) = (g);                                                                                             \
        }                                                                                                          \
    } while (0)

/* sums[0..3) += sum e, sum e (x - mean), sum of PReLU's terms over the n values of one plane (float lanes added into
 * float64 every BN_CHUNK values); x - mean = (x - hi) - lo, the value bn_value(x, hi, lo, scale, shift) */
static inline __attribute__((always_inline)) void grad_sums(const float *restrict xp, const float *restrict gp,
                                                            int64_t n, int act, float hi, float lo, float scale,
                                                            float shift, float s, double sums[3]) {
    for (int64_t j0 = 0; j0 < n; j0 += BN_CHUNK) {
        const int64_t j1 = n - j0 < BN_CHUNK ? n : j0 + BN_CHUNK;
        float a[BN_LANES] = {0}, d[BN_LANES] = {0}, q[BN_LANES] = {0};
        int64_t j = j0;
        if (act == BN_ACT_NONE)        /* explicit vectors: GCC vectorises the loop below across j for this case */
            for (; j + BN_LANES <= j1; j += BN_LANES) {
                const lanes gv = LOAD(gp + j);
                *(lanes_u *)a += gv;
                *(lanes_u *)d += gv * ((LOAD(xp + j) - hi) - lo);
            }
        for (; j + BN_LANES <= j1; j += BN_LANES)
            for (int l = 0; l < BN_LANES; ++l) {
                const float xv = xp[j + l], gv = gp[j + l], v = bn_value(xv, hi, lo, scale, shift);
                float e, term = 0.f;
                ACT_GRAD(act, v, gv, s, e, term);
                a[l] += e;
                d[l] += e * ((xv - hi) - lo);
                q[l] += term;
            }
        for (; j < j1; ++j) {
            const float xv = xp[j], gv = gp[j], v = bn_value(xv, hi, lo, scale, shift);
            float e, term = 0.f;
            ACT_GRAD(act, v, gv, s, e, term);
            sums[0] += e;
            sums[1] += (double)(e * ((xv - hi) - lo));
            sums[2] += term;
        }
        for (int l = 0; l < BN_LANES; ++l) {
            sums[0] += a[l];
            sums[1] += d[l];
            sums[2] += q[l];
        }
    }
}

/* gx = k1 (e - shift_g) - k2 (x - mean) over the n values of one plane */
static inline __attribute__((always_inline)) void grad_input(const float *restrict xp, const float *restrict gp,
                                                             float *restrict op, int64_t n, int act, float hi,
                                                             float lo, float scale, float shift, float s, float k1,
                                                             float shift_g, float k2) {
    for (int64_t j = 0; j < n; ++j) {
        const float xv = xp[j], gv = gp[j], v = bn_value(xv, hi, lo, scale, shift);
        float e, term = 0.f;
        ACT_GRAD(act, v, gv, s, e, term);
        (void)term;
        op[j] = k1 * (e - shift_g) - k2 * ((xv - hi) - lo);
    }
}

/* one channel's backward (see omnidl_bn_train_backward), compiled once per activation: `act` a constant */
static inline __attribute__((always_inline)) void channel_backward(
        const float *x, const float *gy, int64_t B, int64_t C, int64_t hw, int64_t c, int act, float hi, float lo,
        float scale, float shift, float s, double is, double wc, float *gx, float *gw, float *gb, double *gslope) {
    const int64_t n = B * hw;
    double sums[3] = {0.0, 0.0, 0.0};              /* sum e, sum e (x - mean), PReLU's slope */
    for (int64_t i = 0; i < B; ++i)
        grad_sums(x + (i * C + c) * hw, gy + (i * C + c) * hw, hw, act, hi, lo, scale, shift, s, sums);
    const double sg = sums[0], sgd = sums[1];
    if (gb) gb[c] = (float)sg;
    if (gw) gw[c] = (float)(sgd * is);
    if (gslope) gslope[c] = sums[2];
    if (!gx) return;
    /* gx = k1 (e - sg / n) - k2 (x - mean) with k1 = w invstd, k2 = w invstd^3 sgd / n */
    const float k1 = (float)(wc * is), shift_g = (float)(sg / (double)n);
    const float k2 = (float)(wc * is * is * is * sgd / (double)n);
    for (int64_t i = 0; i < B; ++i)
        grad_input(x + (i * C + c) * hw, gy + (i * C + c) * hw, gx + (i * C + c) * hw, hw, act, hi, lo, scale,
                   shift, s, k1, shift_g, k2);
}

/* The backward of omnidl_bn_train (training statistics): with xh = (x - mean) invstd and e = gy act'(value) (gy
 * itself without an activation), per channel
 *     gb = sum e,   gw = sum e xh,   gx = w invstd (e - gb / n - xh gw / n),   gslope = sum of value gy where the
 *     value is not > 0 (PReLU)
 * (w = 1 without affine parameters). x, gy, gx (B, C, hw) contiguous; w: C values or NULL; mean, invstd: the
 * forward's; act, slope, per_channel: the forward's activation, affine: its save_affine (used with an activation);
 * gx, gw, gb, gslope (C doubles, PReLU): written where not NULL. One pass for the sums, one for gx. Returns 0; 2
 * when there are no values per channel; 3 for an activation without `affine`. */
int omnidl_bn_train_backward(const float *x, const float *gy, int64_t B, int64_t C, int64_t hw, const float *w,
                             const float *mean, const float *invstd, float *gx, float *gw, float *gb, int act,
                             const float *slope, int per_channel, const float *affine, double *gslope,
                             int nthreads) {
    const int64_t n = B * hw;
    if (n < 1) return 2;
    if (act != BN_ACT_NONE && !affine) return 3;
#pragma omp parallel for num_threads(nthreads) schedule(static)
    for (int64_t c = 0; c < C; ++c) {
        const double is = invstd[c], wc = w ? (double)w[c] : 1.0;
        if (act == BN_ACT_NONE) {
            channel_backward(x, gy, B, C, hw, c, BN_ACT_NONE, mean[c], 0.f, 0.f, 0.f, 0.f, is, wc, gx, gw, gb, NULL);
            continue;
        }
        const float hi = affine[c], lo = affine[C + c], scale = affine[2 * C + c], shift = affine[3 * C + c];
        if (act == BN_ACT_RELU)
            channel_backward(x, gy, B, C, hw, c, BN_ACT_RELU, hi, lo, scale, shift, 0.f, is, wc, gx, gw, gb, NULL);
        else
            channel_backward(x, gy, B, C, hw, c, BN_ACT_PRELU, hi, lo, scale, shift, slope[per_channel ? c : 0], is,
                             wc, gx, gw, gb, gslope);
    }
    return 0;
}
