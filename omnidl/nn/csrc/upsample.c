/* The adjoint of bilinear up-sampling, (h, w) -> (H, W), for P planes (float32, row-major):
 *
 *     r[p] = A_h^T g[p] A_w          g (P, H, W) -> r (P, h, w)
 *
 * where output row y of the up-sampling reads input rows ri0[y], ri1[y] with weights 1 - rf[y], rf[y], and
 * output column x reads input columns ci0[x], ci1[x] with weights 1 - cf[x], cf[x]. This is the gradient of an
 * up-sampled map with respect to the small map. The height pass runs first, adding whole rows of g into an
 * (h, W) scratch (vectorised along the row); the width pass then scatters only h rows instead of H. The
 * planes are split across the OpenMP threads, each with its own scratch.
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

static void add_scaled(float *dst, const float *src, float s, int64_t n) {
    for (int64_t x = 0; x < n; ++x)
        dst[x] += s * src[x];
}

/* Returns 0, or 1 when a thread could not allocate its scratch (then r is incomplete). */
int omnidl_upsample_adjoint(const float *g, int64_t P, int64_t H, int64_t W, int64_t h, int64_t w,
                            const int64_t *ri0, const int64_t *ri1, const float *rf, const int64_t *ci0,
                            const int64_t *ci1, const float *cf, float *r, int nthreads) {
    int err = 0;
#ifdef _OPENMP
#pragma omp parallel num_threads(nthreads) reduction(| : err)
#endif
    {
        float *tmp = (float *)malloc((size_t)(h * W) * sizeof(float));
        if (!tmp)
            err = 1;
#ifdef _OPENMP
#pragma omp for schedule(static)
#endif
        for (int64_t p = 0; p < P; ++p) {
            if (!tmp)
                continue;                   /* every thread still takes part in the loop */
            const float *gp = g + p * H * W;
            memset(tmp, 0, (size_t)(h * W) * sizeof(float));
            for (int64_t y = 0; y < H; ++y) {
                const float f = rf[y];
                add_scaled(tmp + ri0[y] * W, gp + y * W, 1.f - f, W);
                if (f != 0.f)
                    add_scaled(tmp + ri1[y] * W, gp + y * W, f, W);
            }
            float *rp = r + p * h * w;
            memset(rp, 0, (size_t)(h * w) * sizeof(float));
            for (int64_t i = 0; i < h; ++i) {
                const float *t = tmp + i * W;
                float *o = rp + i * w;
                for (int64_t x = 0; x < W; ++x) {
                    o[ci0[x]] += (1.f - cf[x]) * t[x];
                    o[ci1[x]] += cf[x] * t[x];
                }
            }
        }
        free(tmp);
    }
    (void)nthreads;
    return err;
}

/* dst[j * dc + c] = src[c * sc + j] for j < n, c < C (wrap_layout.c) */
void omnidl_turn(const float *restrict src, int64_t sc, int64_t C, int64_t n, float *restrict dst, int64_t dc);

/* row[x] (+)= s * src[x] over n values; assigns when first */
static void put_scaled(float *restrict row, const float *restrict src, float s, int64_t n, int first) {
    if (!first) {
        add_scaled(row, src, s, n);
        return;
    }
    for (int64_t x = 0; x < n; ++x) row[x] = s * src[x];
}

/* The weighted sum of n maps, each bilinearly up-sampled (align_corners=True) to (H, W):
 *
 *     s[b, c, y, x] = sum_i wts[i] up_i(m_i)[b, c, y, x]          m_i (B, C, hs[i], ws[i]), row-major float32
 *
 * where output row y of map i reads its rows ri0[i H + y], ri1[i H + y] with weights 1 - rf, rf, and output column
 * x reads columns ci0[i W + x], ci1[i W + x] with 1 - cf, cf (a map of the output's size is read as it lies). The
 * sum is written NCHW (nhwc = 0: out (B, C, H, W), left = right = 0) or as the rows of a channels-last map with the
 * panorama's horizontal wrap (nhwc = 1: out (B, H, left + W + right, C), as omnidl_wrap_to_nhwc writes).
 *
 * One work item is one (image, output row), summed as a (W, C) row: each small map's two rows are blended at the
 * map's own width (all channels, vectorised along the row), turned to (w_i, C), then widened by its column taps,
 * each output column a weighted sum of two C-vectors (vectorised along the channels, no gathers); a map of the
 * output's size is turned into the row. Each output value is written once. Returns 0, or 1 when a thread could not
 * allocate its scratch (then out is incomplete). */
int omnidl_upsample_sum(const float *const *maps, int64_t n, const int64_t *hs, const int64_t *ws, const float *wts,
                        int64_t B, int64_t C, int64_t H, int64_t W, const int64_t *ri0, const int64_t *ri1,
                        const float *rf, const int64_t *ci0, const int64_t *ci1, const float *cf, int nhwc,
                        int64_t left, int64_t right, float *out, int nthreads) {
    int err = 0;
    int64_t wmax = W;
    for (int64_t i = 0; i < n; ++i)
        wmax = ws[i] > wmax ? ws[i] : wmax;
    const int64_t Wp = left + W + right;
#ifdef _OPENMP
#pragma omp parallel num_threads(nthreads) reduction(| : err)
#endif
    {
        float *blend = (float *)malloc((size_t)(C * wmax) * sizeof(float));     /* (C, w_i), then turned */
        float *turned = (float *)malloc((size_t)(C * wmax) * sizeof(float));    /* (w_i, C) */
        float *rowbuf = nhwc ? NULL : (float *)malloc((size_t)(C * W) * sizeof(float));
        const int ok = blend && turned && (rowbuf || nhwc);
        if (!ok)
            err = 1;
#ifdef _OPENMP
#pragma omp for schedule(static)
#endif
        for (int64_t r = 0; r < B * H; ++r) {
            if (!ok)
                continue;                   /* every thread still takes part in the loop */
            const int64_t b = r / H, y = r % H;
            float *restrict row = nhwc ? out + (r * Wp + left) * C : rowbuf;       /* (W, C) */
            if (n == 0)
                memset(row, 0, (size_t)(W * C) * sizeof(float));
            for (int64_t i = 0; i < n; ++i) {
                const int64_t h = hs[i], w = ws[i];
                const float *base = maps[i] + b * C * h * w;
                const float s = wts[i];
                if (h == H && w == W) {                            /* a map of the output's size: its row turned */
                    omnidl_turn(base + y * W, H * W, C, W, turned, C);
                    put_scaled(row, turned, s, W * C, i == 0);
                    continue;
                }
                const float f = rf[i * H + y], a0 = s * (1.f - f), a1 = s * f;
                const int64_t y0 = ri0[i * H + y] * w, y1 = ri1[i * H + y] * w;
                for (int64_t c = 0; c < C; ++c) {                  /* the two rows blended, per channel */
                    const float *restrict p0 = base + c * h * w + y0, *restrict p1 = base + c * h * w + y1;
                    float *restrict t = blend + c * w;
                    for (int64_t u = 0; u < w; ++u) t[u] = a0 * p0[u] + a1 * p1[u];
                }
                omnidl_turn(blend, w, C, w, turned, C);
                for (int64_t x = 0; x < W; ++x) {                  /* widened: two C-vectors per column */
                    const float g = cf[i * W + x], g0 = 1.f - g;
                    const float *restrict t0 = turned + ci0[i * W + x] * C, *restrict t1 = turned + ci1[i * W + x] * C;
                    float *restrict o = row + x * C;
                    if (i == 0)
                        for (int64_t c = 0; c < C; ++c) o[c] = g0 * t0[c] + g * t1[c];
                    else
                        for (int64_t c = 0; c < C; ++c) o[c] += g0 * t0[c] + g * t1[c];
                }
            }
            if (nhwc) {                                            /* the wrapped strips */
                float *dst = out + r * Wp * C;
                memcpy(dst, row + (W - left) * C, (size_t)(left * C) * sizeof(float));
                memcpy(dst + (left + W) * C, row, (size_t)(right * C) * sizeof(float));
            } else {
                omnidl_turn(row, C, W, C, out + b * C * H * W + y * W, H * W);
            }
        }
        free(blend);
        free(turned);
        free(rowbuf);
    }
    (void)nthreads;
    return err;
}
