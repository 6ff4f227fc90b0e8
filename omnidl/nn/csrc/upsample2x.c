/* Bilinear up-sampling by 2 with align_corners=False (F.interpolate(x, scale_factor=2.0, mode="bilinear")), plus
 * an optional scaled skip map, and its backward, for P contiguous float32 planes.
 *
 * Output row Y = 2i reads input rows i and i - 1 (clamped at 0) with weights 3/4 and 1/4, row 2i + 1 rows i and
 * i + 1 (clamped at h - 1); columns likewise. FreDSNet's decoder up-samples each block's map and adds the weighted
 * skip map: as PyTorch ops that is three passes over the large map forward and three backward (the up-sampling's
 * adjoint, the skip's gradient, the weight's dot product); here one each. The threads split the planes.
 */
#include <stdint.h>
#include <stdlib.h>

static inline int64_t lo_nb(int64_t i) { return i > 0 ? i - 1 : 0; }
static inline int64_t hi_nb(int64_t i, int64_t n) { return i + 1 < n ? i + 1 : n - 1; }

/* y (P, 2h, 2w) = up2(x (P, h, w)) + s * skip (skip NULL: none). Returns 0, 1 when a scratch row cannot be
 * allocated. */
int omnidl_up2_forward(const float *x, int64_t P, int64_t h, int64_t w, const float *skip, float s, float *y,
                       int nthreads) {
    int err = 0;
#pragma omp parallel num_threads(nthreads) reduction(| : err)
    {
        float *t = (float *)malloc(sizeof(float) * (size_t)w);
        if (!t) err = 1;
#pragma omp for schedule(static)
        for (int64_t p = 0; p < P; ++p) {
            if (!t) continue;
            const float *xp = x + p * h * w;
            for (int64_t Y = 0; Y < 2 * h; ++Y) {
                const int64_t i = Y / 2, k = Y % 2 ? hi_nb(i, h) : lo_nb(i);
                const float *a = xp + i * w, *b = xp + k * w;
                for (int64_t j = 0; j < w; ++j) t[j] = 0.75f * a[j] + 0.25f * b[j];
                float *out = y + (p * 2 * h + Y) * 2 * w;
                for (int64_t j = 0; j < w; ++j) {
                    out[2 * j] = 0.75f * t[j] + 0.25f * t[lo_nb(j)];
                    out[2 * j + 1] = 0.75f * t[j] + 0.25f * t[hi_nb(j, w)];
                }
                if (skip) {
                    const float *sk = skip + (p * 2 * h + Y) * 2 * w;
                    for (int64_t X = 0; X < 2 * w; ++X) out[X] += s * sk[X];
                }
            }
        }
        free(t);
    }
    return err;
}

/* The backward of omnidl_up2_forward, from g (P, 2h, 2w): gx (P, h, w) = the up-sampling's adjoint of g (or NULL),
 * gskip = s * g (or NULL), dots[p] = sum of g * skip over plane p (or NULL; skip given). Returns 0, 1 when a scratch
 * row cannot be allocated. */
int omnidl_up2_backward(const float *g, int64_t P, int64_t h, int64_t w, const float *skip, float s, float *gx,
                        float *gskip, double *dots, int nthreads) {
    int err = 0;
#pragma omp parallel num_threads(nthreads) reduction(| : err)
    {
        float *u = (float *)malloc(sizeof(float) * (size_t)w);
        if (!u) err = 1;
#pragma omp for schedule(static)
        for (int64_t p = 0; p < P; ++p) {
            if (!u) continue;
            float *xp = gx ? gx + p * h * w : NULL;
            if (xp)
                for (int64_t q = 0; q < h * w; ++q) xp[q] = 0.0f;
            double dot = 0.0;
            for (int64_t Y = 0; Y < 2 * h; ++Y) {
                const float *gr = g + (p * 2 * h + Y) * 2 * w;
                if (gskip) {
                    float *o = gskip + (p * 2 * h + Y) * 2 * w;
                    for (int64_t X = 0; X < 2 * w; ++X) o[X] = s * gr[X];
                }
                if (dots) {
                    const float *sk = skip + (p * 2 * h + Y) * 2 * w;
                    float acc = 0.0f;
                    for (int64_t X = 0; X < 2 * w; ++X) acc += gr[X] * sk[X];
                    dot += acc;
                }
                if (!xp) continue;
                for (int64_t j = 0; j < w; ++j) u[j] = 0.75f * (gr[2 * j] + gr[2 * j + 1]);
                for (int64_t j = 0; j < w; ++j) {
                    u[lo_nb(j)] += 0.25f * gr[2 * j];
                    u[hi_nb(j, w)] += 0.25f * gr[2 * j + 1];
                }
                const int64_t i = Y / 2, k = Y % 2 ? hi_nb(i, h) : lo_nb(i);
                float *a = xp + i * w, *b = xp + k * w;
                for (int64_t j = 0; j < w; ++j) a[j] += 0.75f * u[j];
                for (int64_t j = 0; j < w; ++j) b[j] += 0.25f * u[j];
            }
            if (dots) dots[p] = dot;
        }
        free(u);
    }
    return err;
}
