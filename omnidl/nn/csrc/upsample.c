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
