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

/* This OpenMP thread's share [*lo, *hi) of n items in a parallel region (all of them outside one). */
static void thread_share(int64_t n, int64_t *lo, int64_t *hi) {
    int t = 0, nt = 1;
#ifdef _OPENMP
    t = omp_get_thread_num();
    nt = omp_get_num_threads();
#endif
    *lo = n * t / nt;
    *hi = n * (t + 1) / nt;
}

/* The same on channels-last (B, N, C) maps (x, g, gx; ga as above): each OpenMP thread takes a share of the
 * channels (whole steps of CL_STEP) for every position, so no two threads add into one channel's sum, and runs
 * them in chunks of at most CL_STEP channels with float sums per channel flushed into double every CL_FLUSH
 * positions. Returns 0. */
#define CL_STEP 64
#define CL_FLUSH 64
int omnidl_prelu_backward_cl(const float *x, const float *g, const float *a, int per_channel, int64_t B, int64_t C,
                             int64_t N, float *gx, double *ga, int nthreads) {
    const int64_t steps = (C + CL_STEP - 1) / CL_STEP;
#ifdef _OPENMP
#pragma omp parallel num_threads(nthreads)
#endif
    {
        int64_t s0, s1;
        thread_share(steps, &s0, &s1);
        for (int64_t b = 0; b < B; ++b)
            for (int64_t c0 = s0 * CL_STEP; c0 < C && c0 < s1 * CL_STEP; c0 += CL_STEP) {
                const int64_t w = C - c0 < CL_STEP ? C - c0 : CL_STEP;
                float s[CL_STEP], acc[CL_STEP];
                double total[CL_STEP];
                for (int64_t c = 0; c < w; ++c) {
                    s[c] = a[per_channel ? c0 + c : 0];
                    acc[c] = 0.f;
                    total[c] = 0.0;
                }
                for (int64_t i = 0; i < N; ++i) {
                    const int64_t o = (b * N + i) * C + c0;
                    const float *restrict xi = x + o, *restrict gi = g + o;
                    float *restrict gxi = gx + o;
                    for (int64_t c = 0; c < w; ++c) {
                        const float xv = xi[c], gv = gi[c], sg = s[c] * gv, xg = xv * gv;
                        const int pos = xv > 0.f;
                        gxi[c] = pos ? gv : sg;
                        acc[c] += pos ? 0.f : xg;
                    }
                    if ((i + 1) % CL_FLUSH == 0 || i + 1 == N)
                        for (int64_t c = 0; c < w; ++c) {
                            total[c] += acc[c];
                            acc[c] = 0.f;
                        }
                }
                for (int64_t c = 0; c < w; ++c) ga[b * C + c0 + c] = total[c];
            }
    }
    (void)nthreads;
    return 0;
}

/* Inference epilogue of a convolution: out = prelu(y * s + t) + r, per channel c (slope a[c]; s, t: a folded
 * BatchNorm, ones and zeros without one; r optional). Each map is (B, C, N) addressed by its own strides in
 * elements (batch, channel, position), so channel slices of a larger map are read and written where they lie;
 * out may be y itself (in place: every element is read before it is written, by the same thread).
 * Two layouts: channels innermost (every channel stride 1: the positions are split across the threads and each
 * runs its channels as one vector loop) or positions innermost (every position stride 1: the (b, c) planes are
 * split). Returns 0, or 1 for any other layout (the caller composes the modules instead). */
int omnidl_affine_prelu_add(const float *y, int64_t ysb, int64_t ysc, int64_t ysn, const float *r, int64_t rsb,
                            int64_t rsc, int64_t rsn, float *out, int64_t osb, int64_t osc, int64_t osn, int64_t B,
                            int64_t C, int64_t N, const float *s, const float *t, const float *a, int nthreads) {
    if (ysc == 1 && osc == 1 && (!r || rsc == 1)) {
        const int64_t rows = B * N;
#ifdef _OPENMP
#pragma omp parallel num_threads(nthreads)
#endif
        {
            int64_t q0, q1;
            thread_share(rows, &q0, &q1);
            int64_t b = q0 / N, n = q0 % N;   /* this thread's rows q0 .. q1-1, walked as (b, n) */
            for (int64_t q = q0; q < q1; ++q) {
                const float *yq = y + b * ysb + n * ysn;
                float *oq = out + b * osb + n * osn;
                if (r) {
                    const float *rq = r + b * rsb + n * rsn;
                    for (int64_t c = 0; c < C; ++c) {
                        const float v = yq[c] * s[c] + t[c];
                        oq[c] = (v > 0.f ? v : a[c] * v) + rq[c];
                    }
                } else {
                    for (int64_t c = 0; c < C; ++c) {
                        const float v = yq[c] * s[c] + t[c];
                        oq[c] = v > 0.f ? v : a[c] * v;
                    }
                }
                if (++n == N) {
                    n = 0;
                    ++b;
                }
            }
        }
    } else if (ysn == 1 && osn == 1 && (!r || rsn == 1)) {
        const int64_t planes = B * C;
#ifdef _OPENMP
#pragma omp parallel for schedule(static) num_threads(nthreads)
#endif
        for (int64_t q = 0; q < planes; ++q) {
            const int64_t b = q / C, c = q % C;
            const float sc = s[c], tc = t[c], ac = a[c];
            const float *yq = y + b * ysb + c * ysc;
            float *oq = out + b * osb + c * osc;
            if (r) {
                const float *rq = r + b * rsb + c * rsc;
                for (int64_t n = 0; n < N; ++n) {
                    const float v = yq[n] * sc + tc;
                    oq[n] = (v > 0.f ? v : ac * v) + rq[n];
                }
            } else {
                for (int64_t n = 0; n < N; ++n) {
                    const float v = yq[n] * sc + tc;
                    oq[n] = v > 0.f ? v : ac * v;
                }
            }
        }
    } else {
        return 1;
    }
    (void)nthreads;
    return 0;
}
