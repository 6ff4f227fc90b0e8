/* A thin 1x1 convolution (at most MAX_IN input channels) and an activation on contiguous float32 maps, for
 * omnidl.nn.expansion, which folds batch norm with the batch's statistics into the weights (they follow from the
 * input's mean and covariance) before the forward, and turns the backward's sums into the gradients:
 *
 *     pre[c, p] = w[c, :] . x[:, p] + bias[c]          act: 0 none, 1 ReLU, 2 PReLU (slope[c], or slope[0])
 *     forward    y[c, p] = act(pre[c, p])
 *     sums       e = g * act'(pre);  per channel c:  s1 = sum_p e,  sx[k] = sum_p e x[k, p],  sa = sum_{pre <= 0} g pre
 *     input      gx[k, p] = q[k] + sum_j m[k, j] x[j, p] + sum_c a[c, k] e[c, p]
 *
 * with x (B, cin, P), y and g (B, cout, P), gx (B, cin, P). The forward is one pass that writes y; the backward
 * two passes over g (pre is recomputed from x, which stays in the cache) that write nothing of g's size. The
 * activations are PyTorch's (ReLU keeps NaN; the slope's side at pre = 0). Pixels run in chunks of CHUNK, the
 * OpenMP threads on their share of the (image, chunk) items; the sums are kept in float lanes over a chunk and
 * added up in double.
 */
#include <stdint.h>
#include <stdlib.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#define MAX_IN 8
#define LANES 16
#define CHUNK (LANES * 32)

/* out[0..n) = w . x[:, 0..n) + b, x's rows P apart */
static void pre_chunk(const float *restrict x, int64_t P, int cin, const float *restrict w, float b, int n,
                      float *restrict out) {
    for (int i = 0; i < n; ++i) out[i] = b;
    for (int k = 0; k < cin; ++k) {
        const float wk = w[k];
        const float *restrict xk = x + k * P;
        for (int i = 0; i < n; ++i) out[i] += wk * xk[i];
    }
}

/* act'(pre) g, PyTorch's: ReLU's gradient passes where the output is not <= 0, PReLU's slope side is pre <= 0 */
static inline __attribute__((always_inline)) float grad_of(int act, float pre, float g, float s) {
    const float sg = s * g;  /* computed either way: a conditional product would keep the loops from vectorising */
    return act == 0 ? g : act == 1 ? (pre <= 0.f ? 0.f : g) : (pre > 0.f ? g : sg);
}

/* work item `it` of B * chunks: its image *b and first pixel *p0; returns its number of pixels */
static int chunk_of(int64_t it, int64_t chunks, int64_t P, int64_t *b, int64_t *p0) {
    *b = it / chunks;
    *p0 = (it % chunks) * CHUNK;
    return P - *p0 < CHUNK ? (int)(P - *p0) : CHUNK;
}

static float slope_of(const float *slope, int per_channel, int c) { return slope ? slope[per_channel ? c : 0] : 0.f; }

int omnidl_expand_forward(const float *x, int64_t B, int cin, int64_t P, const float *w, const float *bias, int cout,
                          int act, const float *slope, int per_channel, float *y, int nthreads) {
    if (cin > MAX_IN || cin < 1) return 2;
    const int64_t chunks = (P + CHUNK - 1) / CHUNK, items = B * chunks;
    (void)nthreads;
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t it = 0; it < items; ++it) {
        int64_t b, p0;
        const int n = chunk_of(it, chunks, P, &b, &p0);
        const float *xb = x + b * cin * P + p0;
        float pre[CHUNK];
        for (int c = 0; c < cout; ++c) {
            pre_chunk(xb, P, cin, w + c * cin, bias[c], n, pre);
            float *restrict yc = y + (b * cout + c) * P + p0;
            const float s = slope_of(slope, per_channel, c);
            if (act == 0)
                for (int i = 0; i < n; ++i) yc[i] = pre[i];
            else if (act == 1)  /* ReLU keeps NaN (NaN < 0 is false) */
                for (int i = 0; i < n; ++i) yc[i] = pre[i] < 0.f ? 0.f : pre[i];
            else
                for (int i = 0; i < n; ++i) {
                    const float sp = s * pre[i];
                    yc[i] = pre[i] > 0.f ? pre[i] : sp;
                }
        }
    }
    return 0;
}

/* e[0..n) = act'(pre) g over pre[0..n), in place; `act` a constant at each call (the loop vectorises) */
static inline __attribute__((always_inline)) void derivative(const int act, float *restrict pre_e,
                                                             const float *restrict g, float s, int n) {
    for (int i = 0; i < n; ++i) pre_e[i] = grad_of(act, pre_e[i], g[i], s);
}

/* sum of a[0..n) b[0..n), in float lanes */
static float dot(const float *restrict a, const float *restrict b, int n) {
    float acc[LANES] = {0};
    int i = 0;
    for (; i + LANES <= n; i += LANES)
        for (int l = 0; l < LANES; ++l) acc[l] += a[i + l] * b[i + l];
    for (; i < n; ++i) acc[0] += a[i] * b[i];
    float t = 0.f;
    for (int l = 0; l < LANES; ++l) t += acc[l];
    return t;
}

/* sum of a[0..n), in float lanes */
static float total(const float *restrict a, int n) {
    float acc[LANES] = {0};
    int i = 0;
    for (; i + LANES <= n; i += LANES)
        for (int l = 0; l < LANES; ++l) acc[l] += a[i + l];
    for (; i < n; ++i) acc[0] += a[i];
    float t = 0.f;
    for (int l = 0; l < LANES; ++l) t += acc[l];
    return t;
}

/* PReLU's slope sum over a chunk: sum of g pre where pre <= 0 */
static float slope_sum(const float *restrict pre, const float *restrict g, int n) {
    float acc[LANES] = {0};
    int i = 0;
    for (; i + LANES <= n; i += LANES)
        for (int l = 0; l < LANES; ++l) {
            const float gp = g[i + l] * pre[i + l];
            acc[l] += pre[i + l] > 0.f ? 0.f : gp;
        }
    for (; i < n; ++i) acc[0] += pre[i] > 0.f ? 0.f : g[i] * pre[i];
    float t = 0.f;
    for (int l = 0; l < LANES; ++l) t += acc[l];
    return t;
}

/* sums (cout, cin + 2) doubles: s1, sx[0..cin), sa per channel. Returns 0, 1 when a buffer cannot be allocated. */
int omnidl_expand_sums(const float *x, const float *g, int64_t B, int cin, int64_t P, const float *w,
                       const float *bias, int cout, int act, const float *slope, int per_channel, double *sums,
                       int nthreads) {
    if (cin > MAX_IN || cin < 1) return 2;
    const int64_t chunks = (P + CHUNK - 1) / CHUNK, items = B * chunks, width = (int64_t)cout * (cin + 2);
    int err = 0;
    for (int64_t j = 0; j < width; ++j) sums[j] = 0.0;
    (void)nthreads;
#pragma omp parallel num_threads(nthreads) reduction(| : err)
    {
        double *mine = (double *)calloc((size_t)width, sizeof(double));
        if (!mine) err = 1;
#pragma omp for schedule(static)
        for (int64_t it = 0; it < items; ++it) {
            if (!mine) continue;
            int64_t b, p0;
            const int n = chunk_of(it, chunks, P, &b, &p0);
            const float *restrict xb = x + b * cin * P + p0;
            float e[CHUNK];
            for (int c = 0; c < cout; ++c) {
                const float *gc = g + (b * cout + c) * P + p0;
                const float s = slope_of(slope, per_channel, c);
                double *row = mine + (int64_t)c * (cin + 2);
                pre_chunk(xb, P, cin, w + c * cin, bias[c], n, e);
                if (act == 2) row[cin + 1] += slope_sum(e, gc, n);
                if (act == 0) derivative(0, e, gc, s, n);
                else if (act == 1) derivative(1, e, gc, s, n);
                else derivative(2, e, gc, s, n);
                row[0] += total(e, n);
                for (int k = 0; k < cin; ++k) row[1 + k] += dot(e, xb + k * P, n);
            }
        }
#pragma omp critical
        if (mine)
            for (int64_t j = 0; j < width; ++j) sums[j] += mine[j];
        free(mine);
    }
    return err;
}

/* gx (B, cin, P) from a (cout, cin), m (cin, cin), q (cin). Returns 0. */
int omnidl_expand_input_grad(const float *x, const float *g, int64_t B, int cin, int64_t P, const float *w,
                             const float *bias, int cout, int act, const float *slope, int per_channel,
                             const float *a, const float *m, const float *q, float *gx, int nthreads) {
    if (cin > MAX_IN || cin < 1) return 2;
    const int64_t chunks = (P + CHUNK - 1) / CHUNK, items = B * chunks;
    (void)nthreads;
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t it = 0; it < items; ++it) {
        int64_t b, p0;
        const int n = chunk_of(it, chunks, P, &b, &p0);
        const float *xb = x + b * cin * P + p0;
        float acc[MAX_IN][CHUNK], e[CHUNK];
        for (int k = 0; k < cin; ++k) pre_chunk(xb, P, cin, m + k * cin, q[k], n, acc[k]);
        for (int c = 0; c < cout; ++c) {
            pre_chunk(xb, P, cin, w + c * cin, bias[c], n, e);
            const float *restrict gc = g + (b * cout + c) * P + p0;
            const float s = slope_of(slope, per_channel, c);
            if (act == 0) derivative(0, e, gc, s, n);
            else if (act == 1) derivative(1, e, gc, s, n);
            else derivative(2, e, gc, s, n);
            for (int k = 0; k < cin; ++k) {
                const float ak = a[c * cin + k];
                for (int i = 0; i < n; ++i) acc[k][i] += ak * e[i];
            }
        }
        for (int k = 0; k < cin; ++k) {
            float *restrict out = gx + (b * cin + k) * P + p0;
            for (int i = 0; i < n; ++i) out[i] = acc[k][i];
        }
    }
    return 0;
}
