/* A panorama's horizontal wrap together with a change of layout, for omnidl.nn.thin_layout (float32):
 *
 *     to_nhwc    xp[b, h, j, c] = x[b, c, h, (j - left) mod W]                 x (B, C, H, W) -> xp (B, H, Wp, C)
 *     from_nhwc  gx[b, c, h, w] = sum of g[b, h, j, c] over the j with (j - left) mod W == w     (its adjoint)
 *
 * with Wp = left + W + right (left, right <= W): xp is the storage of a channels-last (B, C, H, Wp) tensor, the
 * input oneDNN convolves without reordering it to its blocked layout. Each (image, row) is one work item for the
 * OpenMP threads; within it the transpose runs in TILE x TILE blocks of columns x channels, so that both sides are
 * read and written in whole cache lines. The adjoint writes the middle columns, then adds the wrapped strips onto
 * the columns they came from.
 */
#include <stdint.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#define TILE 16

static int64_t min64(int64_t a, int64_t b) { return a < b ? a : b; }

/* dst[j * C + c] = src[c * plane + col(j)] for j in [0, Wp), c in [0, C): col(j) = (j - left) mod W */
static void row_to_nhwc(const float *restrict src, int64_t plane, int64_t C, int64_t W, int64_t left, int64_t Wp,
                        float *restrict dst) {
    for (int64_t c0 = 0; c0 < C; c0 += TILE)
        for (int64_t t0 = 0; t0 < Wp; t0 += TILE) {
            const int64_t c1 = min64(c0 + TILE, C), t1 = min64(t0 + TILE, Wp);
            for (int64_t j = t0; j < t1; ++j) {
                int64_t w = j - left;
                w = w < 0 ? w + W : w >= W ? w - W : w;
                const float *s = src + w;
                float *d = dst + j * C;
                for (int64_t c = c0; c < c1; ++c) d[c] = s[c * plane];
            }
        }
}

int omnidl_wrap_to_nhwc(const float *x, int64_t B, int64_t C, int64_t H, int64_t W, int64_t left, int64_t right,
                        float *xp, int nthreads) {
    if (left > W || right > W || left < 0 || right < 0) return 2;
    const int64_t Wp = left + W + right, rows = B * H;
    (void)nthreads;
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t r = 0; r < rows; ++r) {
        const int64_t b = r / H, h = r % H;
        row_to_nhwc(x + b * C * H * W + h * W, H * W, C, W, left, Wp, xp + r * Wp * C);
    }
    return 0;
}

int omnidl_wrap_from_nhwc(const float *g, int64_t B, int64_t C, int64_t H, int64_t W, int64_t left, int64_t right,
                          float *gx, int nthreads) {
    if (left > W || right > W || left < 0 || right < 0) return 2;
    const int64_t Wp = left + W + right, rows = B * H, plane = H * W;
    (void)nthreads;
#pragma omp parallel for schedule(static) num_threads(nthreads)
    for (int64_t r = 0; r < rows; ++r) {
        const int64_t b = r / H, h = r % H;
        const float *src = g + r * Wp * C;
        float *dst = gx + b * C * plane + h * W;
        for (int64_t c0 = 0; c0 < C; c0 += TILE)
            for (int64_t w0 = 0; w0 < W; w0 += TILE) {
                const int64_t c1 = min64(c0 + TILE, C), w1 = min64(w0 + TILE, W);
                for (int64_t c = c0; c < c1; ++c) {
                    float *d = dst + c * plane;
                    for (int64_t w = w0; w < w1; ++w) d[w] = src[(w + left) * C + c];
                }
            }
        for (int64_t c = 0; c < C; ++c) {  /* the strips: columns W - left .. W - 1 and 0 .. right - 1 */
            float *d = dst + c * plane;
            for (int64_t j = 0; j < left; ++j) d[W - left + j] += src[j * C + c];
            for (int64_t j = 0; j < right; ++j) d[j] += src[(left + W + j) * C + c];
        }
    }
    return 0;
}
