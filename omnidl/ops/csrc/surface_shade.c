/* omnidl::surface_shade's CPU kernel (omnidl/ops/surface_shade.py): the synthetic renderer's per-pixel surface pass
 * in one call, from the ray-cast hits to the surface id (walls, floor, ceiling, wall openings, boxes), its semantic
 * and instance labels, the normal facing the ray (world and camera frame), the procedural texture and the Lambertian
 * shading.
 *
 * It is the op's PyTorch implementation (surface_shade.torch_surface_shade, texture_mix, box_faces) written per
 * pixel: the same float32 operations in the same order, each rounded on its own (no contracted multiply-adds:
 * -std=c11 keeps GCC from contracting, the pragma below Clang), so every discrete decision (which opening, which box
 * face, which texture cell) is the PyTorch implementation's one. Its three matrix products (lights . normal,
 * lights . 2 p, R^T n) are summed as sgemm sums three terms (dot3); a BLAS that sums otherwise changes the image and
 * the camera-frame normal by float32 rounding only. */
#include <math.h>
#include <stdint.h>

#if defined(__clang__)
#pragma STDC FP_CONTRACT OFF
#endif

enum { CEILING = 1, WALL = 2, FLOOR = 3 };
enum { BLOCK = 256 }; /* pixels per block: its arrays stay in L1 */
enum { PLAIN = 0, STRIPES = 1, CHECKER = 2, NOISE = 3, PLANKS = 4, PANEL = 5 };

/* surface_shade._hash: a value in [0, 1) per integer cell, int64 arithmetic wrapping as PyTorch's */
static inline float cell_hash(int64_t i, int64_t j) {
    int64_t h = (int64_t)(((uint64_t)i * 73856093u) ^ ((uint64_t)j * 19349663u));
    h = (int64_t)((uint64_t)(h ^ (h >> 13)) * 1274126177u);
    int64_t r = h % 1021;
    r = r < 0 ? r + 1021 : r; /* torch.remainder: the sign of the divisor */
    return (float)r / 1021.0f;
}

/* a . b as the BLAS sgemm of the PyTorch implementation sums a product with three terms: a0 b0, then two fused
 * multiply-adds (the matrix products lights @ normal, lights @ 2 p and R^T @ normal there) */
static inline float dot3(float a0, float a1, float a2, float b0, float b1, float b2) {
    return fmaf(a2, b2, fmaf(a1, b1, a0 * b0));
}

static inline int64_t floor_mod2(int64_t a) { return a & 1; } /* Python's a % 2, two's complement */

/* surface_shade.texture_mix for one point: texture kind, scale s (> 0, clamped), surface coordinates u, v */
static float texture_weight(int64_t kind, float s, float u, float v) {
    if (kind == PLAIN) return 0.0f;
    if (kind == PANEL)
        return (u < 0.08f || u > 0.92f || v < 0.06f || v > 0.94f || (v > 0.48f && v < 0.52f)) ? 1.0f : 0.0f;
    const int64_t iu = (int64_t)floorf(u / s), iv = (int64_t)floorf(v / s);
    if (kind == STRIPES) return (float)floor_mod2(iu);
    if (kind == CHECKER) return (float)floor_mod2(iu + iv);
    if (kind == NOISE) return cell_hash(iu, iv);
    /* PLANKS (and any other kind, as texture_mix's last branch) */
    const float off = cell_hash(iv, iv + 7) * 4.0f * s;
    const float x = (u + off) / (4.0f * s);
    const float col = floorf(x);
    const int seam = (v / s - (float)iv < 0.05f) || (x - col < 0.012f);
    return seam ? 1.0f : 0.6f * cell_hash(iv, (int64_t)col);
}

/* surface_shade.box_faces for one hit point p on box b (rows x, y, z, hx, hy, hz, cos yaw, sin yaw): the outward
 * world normal n and the face coordinates (u, v) */
static void box_face(const float *b, float px, float py, float pz, float n[3], float *u, float *v) {
    const float c = b[6], s = b[7];
    const float qx = px - b[0], qy = py - b[1];
    const float l[3] = {c * qx + s * qy, -s * qx + c * qy, pz - b[2]};
    float best = 0.0f;
    int axis = 0;
    for (int k = 0; k < 3; ++k) { /* argmax: the first of equal maxima, NaN counts as the largest */
        const float h = b[3 + k] < 1e-9f ? 1e-9f : b[3 + k]; /* clamp_min: NaN stays */
        const float r = fabsf(l[k]) / h;
        if (k == 0 || (!isnan(best) && (r > best || isnan(r)))) {
            best = r;
            axis = k;
        }
    }
    const float a = l[axis];
    float sg = a > 0.0f ? 1.0f : (a < 0.0f ? -1.0f : (a == 0.0f ? 1.0f : a)); /* sign, 0 -> 1, NaN stays */
    const float m[3] = {axis == 0 ? sg : 0.0f, axis == 1 ? sg : 0.0f, axis == 2 ? sg : 0.0f};
    n[0] = c * m[0] - s * m[1];
    n[1] = s * m[0] + c * m[1];
    n[2] = m[2];
    *u = axis == 1 ? l[0] : (axis == 0 ? l[1] : l[0]);
    *v = axis == 2 ? l[1] : l[2];
}

/* Per pixel p < P (component-major point, dir (3, P); hit (P,) 0/1; box (P,) hit box or -1; room kind, wall (P,)
 * and wall_s (P,) metres along the wall):
 *   surface: walls 0..n-1, floor n, ceiling n+1 (also for pixels without a hit), opening k n+2+k (the last of the
 *     openings dec_wall (K,), dec (K, 6) rows s0, s1, z0, z1, s1 - s0, z1 - z0 that contains a wall pixel without a
 *     box; a PANEL opening (dec_panel) sets the texture coordinates), box j n+2+K+j (boxes (B, 8) rows of
 *     box_face);
 *   labels: sem, inst = surf_sem, surf_inst of the surface, times hit;
 *   normal: surf_normal (S, 3) or the box face's, negated where it points along the ray, times hit; normal_cam =
 *     R^T normal (R (3, 3) row-major), component-major;
 *   image (3, P): albedo c1 (1 - w) + c2 w of the surface's material (mat_colour (M, 6), mat_texture, mat_scale,
 *     texture weight w), times the light ambient + sum over lights (L, 4) rows x, y, z, power of
 *     power max(n.(l - p) / |l - p|, 0) / (1 + |l - p|^2 / 4) (|l - p|^2 at least 1e-12), times shadow (L, P)
 *     where given (NULL: 1), rolled off as
 *     1.25 light / (1 + light / 4), unless the material is emissive; clamped to [0, 1]; 0 without a hit.
 * Returns 0, or 3 when a box index is n_boxes or more, or a wall pixel without a box has a wall outside
 * [0, n_walls) (such a pixel is shaded as ceiling, so nothing is read out of bounds). */
int omnidl_surface_shade(int64_t P, const float *point, const float *dir, const uint8_t *hit, const int64_t *box,
                         const int64_t *kind, const int64_t *wall, const float *wall_s, int64_t n_walls,
                         int64_t K, const int64_t *dec_wall, const float *dec, const uint8_t *dec_panel,
                         const float *boxes, int64_t n_boxes, const int64_t *surf_sem, const int64_t *surf_inst,
                         const int64_t *surf_mat, const float *surf_normal, const float *mat_colour,
                         const int64_t *mat_texture, const float *mat_scale, const uint8_t *mat_emissive, int L,
                         const float *lights, const float *shadow, float ambient, const float *R, float *image,
                         int64_t *sem, int64_t *inst, float *normal_cam, int nthreads) {
    const float *px_ = point, *py_ = point + P, *pz_ = point + 2 * P;
    const int64_t blocks = (P + BLOCK - 1) / BLOCK;
    int bad = 0;
#pragma omp parallel for num_threads(nthreads) schedule(static) reduction(| : bad)
    for (int64_t blk = 0; blk < blocks; ++blk) {
        const int64_t p0 = blk * BLOCK, nb = P - p0 < BLOCK ? P - p0 : BLOCK;
        /* per pixel of the block: the normal facing the ray (times hit), the albedo, emissive, hit */
        float nx[BLOCK], ny[BLOCK], nz[BLOCK], ar[BLOCK], ag[BLOCK], ab[BLOCK], em[BLOCK], hf[BLOCK];
        for (int64_t i = 0; i < nb; ++i) { /* surfaces and textures: branches per pixel */
            const int64_t p = p0 + i;
            const float px = px_[p], py = py_[p], pz = pz_[p];
            const int64_t kd = kind[p];
            int64_t bi = box[p];
            int is_wall = kd == WALL;
            if (bi >= n_boxes || (bi < 0 && is_wall && (wall[p] < 0 || wall[p] >= n_walls))) {
                bad = 1;
                bi = -1;
                is_wall = 0;
            }
            int64_t sf = is_wall ? wall[p] : (kd == FLOOR ? n_walls : n_walls + 1);
            float tu = is_wall ? wall_s[p] : px, tv = is_wall ? pz : py;
            float n[3];
            if (bi >= 0) {
                box_face(boxes + 8 * bi, px, py, pz, n, &tu, &tv);
                sf = n_walls + 2 + K + bi;
            } else {
                if (is_wall) {
                    const int64_t w = wall[p];
                    const float s = wall_s[p];
                    for (int64_t k = 0; k < K; ++k) {
                        const float *d = dec + 6 * k;
                        if (dec_wall[k] == w && s >= d[0] && s <= d[1] && pz >= d[2] && pz <= d[3]) {
                            sf = n_walls + 2 + k;
                            if (dec_panel[k]) {
                                tu = (s - d[0]) / d[4];
                                tv = (pz - d[2]) / d[5];
                            }
                        }
                    }
                }
                n[0] = surf_normal[3 * sf];
                n[1] = surf_normal[3 * sf + 1];
                n[2] = surf_normal[3 * sf + 2];
            }
            const float h = hit[p] ? 1.0f : 0.0f;
            sem[p] = hit[p] ? surf_sem[sf] : 0;
            inst[p] = hit[p] ? surf_inst[sf] : 0;
            const int flip = n[0] * dir[p] + n[1] * dir[P + p] + n[2] * dir[2 * P + p] > 0.0f;
            nx[i] = (flip ? -n[0] : n[0]) * h;
            ny[i] = (flip ? -n[1] : n[1]) * h;
            nz[i] = (flip ? -n[2] : n[2]) * h;
            const int64_t m = surf_mat[sf];
            const float *c = mat_colour + 6 * m;
            const float sc = mat_scale[m] < 1e-3f ? 1e-3f : mat_scale[m];
            const float w = texture_weight(mat_texture[m], sc, tu, tv);
            ar[i] = c[0] * (1.0f - w) + c[3] * w;
            ag[i] = c[1] * (1.0f - w) + c[4] * w;
            ab[i] = c[2] * (1.0f - w) + c[5] * w;
            em[i] = mat_emissive[m] ? 1.0f : 0.0f;
            hf[i] = h;
        }
        float light[BLOCK];
#pragma omp simd
        for (int64_t i = 0; i < nb; ++i) {
            const int64_t p = p0 + i;
            for (int k = 0; k < 3; ++k) normal_cam[k * P + p] = dot3(R[k], R[3 + k], R[6 + k], nx[i], ny[i], nz[i]);
            light[i] = 0.0f;
        }
        for (int j = 0; j < L; ++j) { /* the lights: vectorised over the block */
            const float *l = lights + 4 * j;
            const float ll = l[0] * l[0] + l[1] * l[1] + l[2] * l[2];
#pragma omp simd
            for (int64_t i = 0; i < nb; ++i) {
                const int64_t p = p0 + i;
                const float px = px_[p], py = py_[p], pz = pz_[p];
                const float np_ = nx[i] * px + ny[i] * py + nz[i] * pz, pp = px * px + py * py + pz * pz;
                const float ndl = dot3(l[0], l[1], l[2], nx[i], ny[i], nz[i]) - np_;
                float d2 = (pp - dot3(l[0], l[1], l[2], 2.0f * px, 2.0f * py, 2.0f * pz)) + ll;
                d2 = d2 < 1e-12f ? 1e-12f : d2;
                float lam = ndl * (1.0f / sqrtf(d2));
                lam = lam < 0.0f ? 0.0f : lam;
                const float c = l[3] * lam / (1.0f + 0.25f * d2);
                light[i] += shadow ? c * shadow[(int64_t)j * P + p] : c;
            }
        }
#pragma omp simd
        for (int64_t i = 0; i < nb; ++i) {
            const int64_t p = p0 + i;
            float g = ambient + light[i];
            g = 1.25f * g / (1.0f + 0.25f * g);
            const float a[3] = {ar[i], ag[i], ab[i]};
            for (int k = 0; k < 3; ++k) {
                float v = em[i] != 0.0f ? a[k] : a[k] * g;
                v = v < 0.0f ? 0.0f : (v > 1.0f ? 1.0f : v);
                image[k * P + p] = hf[i] != 0.0f ? v : 0.0f;
            }
        }
    }
    return bad ? 3 : 0;
}
