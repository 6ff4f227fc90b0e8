/* The recurrence of one LSTM layer on the CPU (float32, inference), every direction at once.
 *
 * The input part of the gates, x_t W_ih^T + b_ih + b_hh, is one matrix product for the whole sequence and is
 * done by the caller; what is left is sequential: for t along the direction,
 *     g = gx[t] + W_hh h,   i = s(g_i), f = s(g_f), c~ = tanh(g_g), o = s(g_o)   (PyTorch's gate order i, f, g, o)
 *     c = f c + i c~,       h = o tanh(c)
 * At batch 1 each step is a matrix-vector product that reads all of W_hh (4H x H: 4 MB at H = 512) for 4H*H
 * multiply-adds, so the layer is bound by how fast a core streams W_hh from its caches. The directions of a
 * bidirectional layer are independent: each runs on its own thread (its own core, its own stream), with no
 * synchronisation between steps.
 *
 * Layouts (row-major): gx (S, D, 4H) for D directions; whh (D, 4H, H); h0, c0 (D, H); out (S, D*H) with
 * direction d in columns d*H .. d*H+H-1 (direction 1 runs from t = S-1 down to 0); hn, cn (D, H).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#if defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>

static float hsum(__m256 v) {
    __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    s = _mm_add_ss(s, _mm_movehdup_ps(s));
    return _mm_cvtss_f32(s);
}

/* g[r] += dot(w[r, :], h) for r < rows; w rows of length n (n a multiple of 8 here), four rows per pass so each
 * load of h serves four rows */
static void matvec_add(int64_t rows, int64_t n, const float *w, const float *h, float *g) {
    int64_t r = 0;
    for (; r + 4 <= rows; r += 4) {
        const float *w0 = w + r * n, *w1 = w0 + n, *w2 = w1 + n, *w3 = w2 + n;
        __m256 a0 = _mm256_setzero_ps(), a1 = a0, a2 = a0, a3 = a0;
        for (int64_t k = 0; k < n; k += 8) {
            const __m256 hk = _mm256_loadu_ps(h + k);
            a0 = _mm256_fmadd_ps(_mm256_loadu_ps(w0 + k), hk, a0);
            a1 = _mm256_fmadd_ps(_mm256_loadu_ps(w1 + k), hk, a1);
            a2 = _mm256_fmadd_ps(_mm256_loadu_ps(w2 + k), hk, a2);
            a3 = _mm256_fmadd_ps(_mm256_loadu_ps(w3 + k), hk, a3);
        }
        g[r] += hsum(a0);
        g[r + 1] += hsum(a1);
        g[r + 2] += hsum(a2);
        g[r + 3] += hsum(a3);
    }
    for (; r < rows; ++r) {
        __m256 a = _mm256_setzero_ps();
        for (int64_t k = 0; k < n; k += 8) a = _mm256_fmadd_ps(_mm256_loadu_ps(w + r * n + k), _mm256_loadu_ps(h + k), a);
        g[r] += hsum(a);
    }
}
#define VEC_WIDTH 8
#else
static void matvec_add(int64_t rows, int64_t n, const float *w, const float *h, float *g) {
    for (int64_t r = 0; r < rows; ++r) {
        float a = 0.f;
        for (int64_t k = 0; k < n; ++k) a += w[r * n + k] * h[k];
        g[r] += a;
    }
}
#define VEC_WIDTH 1
#endif

static float sigmoid(float v) { return 1.f / (1.f + expf(-v)); }

/* one direction: d = 0 forward in time, d = 1 backward. hp: the hidden state padded to a multiple of
 * VEC_WIDTH with zeros (and W_hh rows read with the padded stride n), g: 4H scratch */
static void run_direction(int64_t S, int D, int d, int64_t H, const float *gx, const float *whh, int64_t n,
                          const float *h0, const float *c0, float *out, float *hn, float *cn, float *hp, float *c,
                          float *g) {
    memset(hp, 0, sizeof(float) * n);
    memcpy(hp, h0 + d * H, sizeof(float) * H);
    memcpy(c, c0 + d * H, sizeof(float) * H);
    const float *w = whh + (int64_t)d * 4 * H * n;
    for (int64_t s = 0; s < S; ++s) {
        const int64_t t = d ? S - 1 - s : s;
        memcpy(g, gx + (t * D + d) * 4 * H, sizeof(float) * 4 * H);
        matvec_add(4 * H, n, w, hp, g);
        float *o = out + t * D * H + d * H;
        for (int64_t j = 0; j < H; ++j) {
            const float ig = sigmoid(g[j]), fg = sigmoid(g[H + j]), cg = tanhf(g[2 * H + j]), og = sigmoid(g[3 * H + j]);
            c[j] = fg * c[j] + ig * cg;
            hp[j] = og * tanhf(c[j]);
            o[j] = hp[j];
        }
    }
    memcpy(hn + d * H, hp, sizeof(float) * H);
    memcpy(cn + d * H, c, sizeof(float) * H);
}

/* W_hh rows padded to n = padded_width(H) floats (zeros beyond H): the layout omnidl_lstm_layer reads */
int64_t omnidl_lstm_padded_width(int64_t H) { return (H + VEC_WIDTH - 1) / VEC_WIDTH * VEC_WIDTH; }

/* Returns 0, or 1 when scratch memory could not be allocated. whh: (D, 4H, n) with n = omnidl_lstm_padded_width(H).
 * nthreads: at most this many threads (one per direction). */
int omnidl_lstm_layer(int64_t S, int D, int64_t H, const float *gx, const float *whh, const float *h0,
                      const float *c0, float *out, float *hn, float *cn, int nthreads) {
    const int64_t n = omnidl_lstm_padded_width(H);
    int err = 0;
    int nt = nthreads < D ? nthreads : D;
    if (nt < 1) nt = 1;
#pragma omp parallel for num_threads(nt) schedule(static, 1) reduction(| : err)
    for (int d = 0; d < D; ++d) {
        float *scratch = (float *)malloc(sizeof(float) * (n + H + 4 * H));
        if (!scratch) {
            err |= 1;
            continue;
        }
        run_direction(S, D, d, H, gx, whh, n, h0, c0, out, hn, cn, scratch, scratch + n, scratch + n + H);
        free(scratch);
    }
    return err;
}
