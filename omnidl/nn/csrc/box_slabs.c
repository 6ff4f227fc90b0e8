/* The synthetic renderer's nearest box hits in one call (omnidl/synth/native_cast.py): the slab test of rays
 * against yaw-rotated boxes, batch after batch, each batch a list of boxes and the list of rays that may reach them.
 *
 * It is the tensor-op loop of omnidl/synth/raycast.py (cast_boxes over _box_frames and _slab) written per (ray, box):
 * the same float32 operations in the same order, each rounded on its own (-std=c11 keeps GCC from contracting
 * multiply-adds, the pragma below Clang), with torch.minimum / maximum's NaN propagation, so ranges and box ids are
 * the tensor path's bit for bit. Ties go to the earlier batch (a later one must be strictly closer) and inside a
 * batch to the earlier box in its list (torch.min's first index). */
#include <math.h>
#include <stdint.h>

#if defined(__clang__)
#pragma STDC FP_CONTRACT OFF
#endif

static inline float nan_min(float a, float b) { return (a != a || b != b) ? NAN : (b < a ? b : a); }
static inline float nan_max(float a, float b) { return (a != a || b != b) ? NAN : (b > a ? b : a); }

/* raycast._safe_inverse (float32): 1 / g with |g| < 1e-12 replaced by +-1e-12 (+ for zeros); NaN stays NaN */
static inline float safe_inverse(float g) {
    const float v = g >= 0.0f ? (g < 1e-12f ? 1e-12f : g) : (g > -1e-12f ? -1e-12f : g);
    return 1.0f / (g != g ? g : v);
}

/* Entry range of the ray (o, d) into box b (rows x, y, z, hx, hy, hz, cos yaw, sin yaw), inv_z = safe_inverse(d_z);
 * inf where it misses or enters at a range <= 1e-6 */
static inline float slab(const float *o, const float *d, float inv_z, const float *b) {
    const float c = b[6], s = b[7];
    const float px = o[0] - b[0], py = o[1] - b[1];
    const float lx = c * px + s * py, ly = -s * px + c * py, lz = o[2] - b[2];
    const float hx = b[3], hy = b[4], hz = b[5];
    const float g0 = c * d[0] + s * d[1], g1 = -s * d[0] + c * d[1];
    const float i0 = safe_inverse(g0), i1 = safe_inverse(g1);
    const float a0 = (-hx - lx) * i0, a1 = (-hy - ly) * i1, b0 = (hx - lx) * i0, b1 = (hy - ly) * i1;
    const float z1 = (-hz - lz) * inv_z, z2 = (hz - lz) * inv_z;
    const float t_near = nan_max(nan_max(nan_min(a0, b0), nan_min(a1, b1)), nan_min(z1, z2));
    const float t_far = nan_min(nan_min(nan_max(a0, b0), nan_max(a1, b1)), nan_max(z1, z2));
    return (t_far >= t_near && t_near > 1e-6f) ? t_near : INFINITY;
}

/* For each batch k < n_batches, in order: the boxes box_idx[box_start[k] .. box_start[k + 1]) of boxes (B, 8) against
 * the rays ray_idx[ray_start[k] .. ray_start[k + 1]) (distinct within a batch) with origins origin + r *
 * origin_stride (stride 0: one shared origin) and directions dir (P, 3) row-major. A ray's nearest entry range
 * over the batch replaces t_best[r] and its box index box_id[r] when it is strictly smaller. Returns 0. */
int omnidl_box_slabs(const float *origin, int64_t origin_stride, const float *dir, const float *boxes,
                     int64_t n_batches, const int64_t *box_start, const int64_t *box_idx, const int64_t *ray_start,
                     const int64_t *ray_idx, float *t_best, int64_t *box_id, int nthreads) {
    for (int64_t k = 0; k < n_batches; ++k) {
        const int64_t b0 = box_start[k], b1 = box_start[k + 1], r0 = ray_start[k], r1 = ray_start[k + 1];
        if (b1 <= b0 || r1 <= r0) continue;
#pragma omp parallel for num_threads(nthreads) schedule(static) if (r1 - r0 > 2048)
        for (int64_t q = r0; q < r1; ++q) {
            const int64_t r = ray_idx[q];
            const float *o = origin + r * origin_stride, *d = dir + 3 * r;
            const float inv_z = safe_inverse(d[2]);
            float best = INFINITY;
            int64_t at = b0;
            for (int64_t j = b0; j < b1; ++j) {
                const float t = slab(o, d, inv_z, boxes + 8 * box_idx[j]);
                if (t < best) {
                    best = t;
                    at = j;
                }
            }
            if (best < t_best[r]) {
                t_best[r] = best;
                box_id[r] = box_idx[at];
            }
        }
    }
    return 0;
}
