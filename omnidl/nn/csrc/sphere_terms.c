/* Bilinear reads of equirectangular images at directions, and the Gauss-Newton sums of the photometric
 * gyroscopes over them in one pass (omnidl/postprocess/gyroscope/native_terms.py): PVG's normal equations over
 * the icosahedron vertices, and MPP's whole yaw loop over its table.
 *
 * A read is the one of SphereImage.read_grid (omnidl/postprocess/gyroscope/photometric.py), i.e.
 * torch.nn.functional.grid_sample (bilinear, border, align_corners = False) of the image padded by one wrapped
 * column on each side: longitude = atan2(x, z) (0 where x^2 + z^2 <= 1e-30), latitude = atan2(y, |(x, z)|), the
 * same float32 grid formulas, then padded column c read as image column c - 1 (0 -> W - 1, W + 1 -> 0), rows
 * clamped to [0, H - 1]. atan2 is a polynomial here (relative error 1.4e-8 before float rounding, so within a
 * few float32 ulps of PyTorch's), so that the loops vectorize (with the library's -fno-math-errno -fno-trapping-math:
 * otherwise a square root that may set errno, or a comparison that may trap, is a branch; divisions have a safe
 * operand on every lane). A non-finite direction reads NaN. */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

/* atan(t) = t P(t^2) on [0, 1]: a weighted least-squares fit of degree 8 in t^2 (made for this file) */
static inline float atan_unit(float t) {
    const float s = t * t;
    float p = 2.903697277e-03f;
    p = p * s - 1.628361901e-02f;
    p = p * s + 4.304042837e-02f;
    p = p * s - 7.533773562e-02f;
    p = p * s + 1.065472833e-01f;
    p = p * s - 1.420714871e-01f;
    p = p * s + 1.999305646e-01f;
    p = p * s - 3.333309412e-01f;
    p = p * s + 9.999999864e-01f;
    return t * p;
}

static inline float poly_atan2f(float y, float x) {
    const float ax = fabsf(x), ay = fabsf(y);
    const float mx = ax > ay ? ax : ay, mn = ax > ay ? ay : ax;
    float a = atan_unit(mn / (mx > 1e-30f ? mx : 1e-30f));  /* 0 at (0, 0), as atan2 */
    a = ay > ax ? (float)(M_PI / 2) - a : a;
    a = x < 0.0f ? (float)M_PI - a : a;
    return copysignf(a, y);
}

/* The four pixels around direction (x, y, z) of an H x W image: rows r0, r1, columns c0, c1 and the weights
 * fy, fx of r1 and c1 (see the file's comment). sx, ox: SphereImage's longitude scale and offset. */
static inline void sphere_corners(float x, float y, float z, int H, int W, float sx, float ox, int *r0, int *r1,
                                  int *c0, int *c1, float *fy, float *fx) {
    const float sq = x * x + z * z;
    const float at = poly_atan2f(x, z), lon = sq <= 1e-30f ? 0.0f : at;
    const float lat = poly_atan2f(y, sqrtf(sq));
    float ix = ((lon * sx + ox + 1.0f) * (float)(W + 2) - 1.0f) * 0.5f;
    float iy = ((lat * (float)(2.0 / M_PI) + 1.0f) * (float)H - 1.0f) * 0.5f;
    ix = ix > 0.0f ? (ix < (float)(W + 1) ? ix : (float)(W + 1)) : 0.0f;  /* NaN -> 0: the index stays valid */
    iy = iy > 0.0f ? (iy < (float)(H - 1) ? iy : (float)(H - 1)) : 0.0f;
    const float x0 = floorf(ix), y0 = floorf(iy);
    const int xi = (int)x0, yi = (int)y0;
    *fx = ix - x0;
    *fy = iy - y0;
    *c0 = xi == 0 ? W - 1 : xi - 1;
    *c1 = xi >= W ? xi - W : xi;
    *r0 = yi;
    *r1 = yi + 1 < H ? yi + 1 : H - 1;
}

/* the bilinear value of an image (rows W floats long) at the corners of sphere_corners */
static inline float bilinear(const float *img, int W, int r0, int r1, int c0, int c1, float fy, float fx) {
    const float *a = img + (int64_t)r0 * W, *b = img + (int64_t)r1 * W;
    const float top = a[c0] + fx * (a[c1] - a[c0]), bottom = b[c0] + fx * (b[c1] - b[c0]);
    return top + fy * (bottom - top);
}

/* image (H, W) at direction (x, y, z); NaN when a component is not finite */
static inline float sphere_read(const float *img, int H, int W, float sx, float ox, float x, float y, float z) {
    int r0, r1, c0, c1;
    float fy, fx;
    sphere_corners(x, y, z, H, W, sx, ox, &r0, &r1, &c0, &c1, &fy, &fx);
    return bilinear(img, W, r0, r1, c0, c1, fy, fx) + ((x - x) + (y - y) + (z - z));
}

static void scale_offset(int W, float *sx, float *ox) {
    const double s = (double)W / (M_PI * (W + 2));
    *sx = (float)s;
    *ox = (float)(M_PI * s + 2.0 / (W + 2) - 1.0);
}

/* out[c * n + i] = channel c of the image (C planes of H x W, plane floats apart) at direction (x[i], y[i], z[i]),
 * for i < n. Returns 0. */
int omnidl_sphere_read(const float *img, int64_t plane, int C, int H, int W, const float *x, const float *y,
                       const float *z, int64_t n, float *out, int nthreads) {
    float sx, ox;
    scale_offset(W, &sx, &ox);
    for (int c = 0; c < C; ++c) {
        const float *im = img + c * plane;
        float *o = out + c * n;
#pragma omp parallel for simd num_threads(nthreads) schedule(static)
        for (int64_t i = 0; i < n; ++i) o[i] = sphere_read(im, H, W, sx, ox, x[i], y[i], z[i]);
    }
    return 0;
}

/* PVG's terms for one rotation (PVGTerms in omnidl/postprocess/gyroscope/pvg.py, summed at once): for each vertex
 * X_i (N, 3) and p = R^T X_i (R row-major), the tangent basis t1 = a x p / |a x p| (a = e_x where |p_x| < 0.9, else
 * e_y), t2 = p x t1, the five reads v0..v4 of the image (H, W) at p, p +- h t1, p +- h t2, g1 = (v1 - v2) / (2 atan h),
 * g2 = (v3 - v4) / (2 atan h), u = g2 t1 - g1 t2 and e = v0 - ref_i; Q (4, 4) row-major = the sums of
 * [u; e][u; e]^T, in double. */
static void pvg_sums(const float *im, int H, int W, const float *r, const float *X, int N, const float *rf, float h,
                     double *Q, int nthreads) {
    float sx, ox;
    scale_offset(W, &sx, &ox);
    const float inv = (float)(1.0 / (2.0 * atan((double)h)));
    double s0 = 0, s1 = 0, s2 = 0, s3 = 0, s4 = 0, s5 = 0, s6 = 0, s7 = 0, s8 = 0, s9 = 0;
#pragma omp parallel for simd num_threads(nthreads) schedule(static) reduction(+ : s0, s1, s2, s3, s4, s5, s6, s7, s8, s9)
    for (int i = 0; i < N; ++i) {
        const float X0 = X[3 * i], X1 = X[3 * i + 1], X2 = X[3 * i + 2];
        const float px = r[0] * X0 + r[3] * X1 + r[6] * X2;
        const float py = r[1] * X0 + r[4] * X1 + r[7] * X2;
        const float pz = r[2] * X0 + r[5] * X1 + r[8] * X2;
        const int use_x = fabsf(px) < 0.9f;
        const float sel = use_x ? py : px;
        float nrm = sqrtf(pz * pz + sel * sel);
        nrm = nrm > 1e-12f ? nrm : 1e-12f;
        const float a1 = (use_x ? 0.0f : pz) / nrm, a2 = (use_x ? -pz : 0.0f) / nrm, a3 = (use_x ? py : -px) / nrm;
        const float b1 = py * a3 - pz * a2, b2 = pz * a1 - px * a3, b3 = px * a2 - py * a1;
        const float v0 = sphere_read(im, H, W, sx, ox, px, py, pz);
        const float v1 = sphere_read(im, H, W, sx, ox, px + h * a1, py + h * a2, pz + h * a3);
        const float v2 = sphere_read(im, H, W, sx, ox, px - h * a1, py - h * a2, pz - h * a3);
        const float v3 = sphere_read(im, H, W, sx, ox, px + h * b1, py + h * b2, pz + h * b3);
        const float v4 = sphere_read(im, H, W, sx, ox, px - h * b1, py - h * b2, pz - h * b3);
        const float g1 = (v1 - v2) * inv, g2 = (v3 - v4) * inv;
        const double u0 = g2 * a1 - g1 * b1, u1 = g2 * a2 - g1 * b2, u2 = g2 * a3 - g1 * b3, e = v0 - rf[i];
        s0 += u0 * u0;
        s1 += u0 * u1;
        s2 += u0 * u2;
        s3 += u0 * e;
        s4 += u1 * u1;
        s5 += u1 * u2;
        s6 += u1 * e;
        s7 += u2 * u2;
        s8 += u2 * e;
        s9 += e * e;
    }
    const double sum[10] = {s0, s1, s2, s3, s4, s5, s6, s7, s8, s9};
    static const int at[4][4] = {{0, 1, 2, 3}, {1, 4, 5, 6}, {2, 5, 7, 8}, {3, 6, 8, 9}};
    for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) Q[4 * i + j] = sum[at[i][j]];
}

/* pvg_sums for B rotations R (B, 3, 3) of images img_stride floats apart, reference rows ref_stride apart, into
 * Q (B, 4, 4). Returns 0. */
int omnidl_pvg_terms(const float *img, int64_t img_stride, int H, int W, const float *R, const float *X, int N,
                     const float *ref, int64_t ref_stride, int B, float h, double *Q, int nthreads) {
    for (int b = 0; b < B; ++b)
        pvg_sums(img + b * img_stride, H, W, R + 9 * b, X, N, ref + b * ref_stride, h, Q + 16 * b, nthreads);
    return 0;
}

/* y = A^-1 c for a symmetric 3x3 A (row-major) by cofactors; 0 when A is singular */
static int solve3(const double *A, const double *c, double *y) {
    const double k00 = A[4] * A[8] - A[5] * A[7], k01 = A[5] * A[6] - A[3] * A[8], k02 = A[3] * A[7] - A[4] * A[6];
    const double det = A[0] * k00 + A[1] * k01 + A[2] * k02;
    if (det == 0.0) return 0;
    const double k10 = A[2] * A[7] - A[1] * A[8], k11 = A[0] * A[8] - A[2] * A[6], k12 = A[1] * A[6] - A[0] * A[7];
    const double k20 = A[1] * A[5] - A[2] * A[4], k21 = A[2] * A[3] - A[0] * A[5], k22 = A[0] * A[4] - A[1] * A[3];
    y[0] = (k00 * c[0] + k10 * c[1] + k20 * c[2]) / det;
    y[1] = (k01 * c[0] + k11 * c[1] + k21 * c[2]) / det;
    y[2] = (k02 * c[0] + k12 * c[1] + k22 * c[2]) / det;
    return 1;
}

/* One blur stage of PVG on all three axes (_pvg_fast in omnidl/postprocess/gyroscope/pvg.py, all dofs): per
 * iteration and rotation b, Q = pvg_sums, M = Q[:3, :3], c = Q[:3, 3], y = (M + 1e-9 mean(diag M) I)^-1 c,
 * n = |y|, w = R (y max(-0.35 / n, -1)) (a step of at most 0.35 rad), R <- exp([w]x) R (Rodrigues; R kept in
 * float32 between iterations), until every n < tol or after max_iter iterations. R (B, 3, 3) is updated in place;
 * Q (B, 4, 4) holds the last sums. Returns the number of iterations run, or -1 when a system is singular (R is
 * then left at its last value). */
int omnidl_pvg_stage(const float *img, int64_t img_stride, int H, int W, float *R, const float *X, int N,
                     const float *ref, int64_t ref_stride, int B, float h, int max_iter, float tol, double *Q,
                     int nthreads) {
    int it = 0;
    while (it < max_iter) {
        ++it;
        int done = 1;
        for (int b = 0; b < B; ++b) {
            float *r = R + 9 * b;
            double *q = Q + 16 * b;
            pvg_sums(img + b * img_stride, H, W, r, X, N, ref + b * ref_stride, h, q, nthreads);
            double scale = (q[0] + q[5] + q[10]) / 3.0;
            scale = scale > 1e-30 ? scale : 1e-30;
            const double A[9] = {q[0] + 1e-9 * scale, q[1], q[2], q[4], q[5] + 1e-9 * scale, q[6], q[8], q[9],
                                 q[10] + 1e-9 * scale};
            const double c[3] = {q[3], q[7], q[11]};
            double y[3];
            if (!solve3(A, c, y)) return -1;
            const double n = sqrt(y[0] * y[0] + y[1] * y[1] + y[2] * y[2]);
            double f = -0.35 / n;
            f = f < -1.0 ? -1.0 : f;  /* NaN stays NaN */
            double w[3];
            for (int i = 0; i < 3; ++i) w[i] = (r[3 * i] * y[0] + r[3 * i + 1] * y[1] + r[3 * i + 2] * y[2]) * f;
            const double t = sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]);
            const double sa = t > 1e-12 ? sin(t) / t : 1.0 - t * t / 6.0;
            const double sb = t > 1e-6 ? (1.0 - cos(t)) / (t * t) : 0.5 - t * t / 24.0;
            const double K[9] = {0, -w[2], w[1], w[2], 0, -w[0], -w[1], w[0], 0};
            double E[9];
            for (int i = 0; i < 3; ++i)
                for (int j = 0; j < 3; ++j) {
                    const double kk = K[3 * i] * K[j] + K[3 * i + 1] * K[3 + j] + K[3 * i + 2] * K[6 + j];
                    E[3 * i + j] = (i == j) + sa * K[3 * i + j] + sb * kk;
                }
            float out[9];
            for (int i = 0; i < 3; ++i)
                for (int j = 0; j < 3; ++j)
                    out[3 * i + j] = (float)(E[3 * i] * r[j] + E[3 * i + 1] * r[3 + j] + E[3 * i + 2] * r[6 + j]);
            for (int i = 0; i < 9; ++i) r[i] = out[i];
            done &= n < tol;
        }
        if (done) break;
    }
    return it;
}

/* MPP's Gauss-Newton loop on the yaw (_mpp_fast in omnidl/postprocess/gyroscope/mpp.py): for each image b and
 * start t, with k = (1, sin theta, 1 - cos theta), the M rotated centres and Jacobian directions are the rows
 * k . basis[b] ((3, 6M): the x, y, z rows of p, then of D, for each of the three terms); the table b (4, h, 2h:
 * G and its ambient gradient; tables table_stride floats apart) is read at p, J = grad . D, e = G - gref[b]
 * (rows gref_stride apart); the cost e.e is the start's when it is its lowest so far, and
 * theta -= clamp(J.e / max(J.J, 1e-30), -0.5, 0.5), until every step is below tol or after max_iter iterations.
 * theta (B, T) holds the starts on entry and the angle of least cost on return, cost (B, T) that cost.
 * Returns the number of iterations run, or -1 when a buffer cannot be allocated. */
int omnidl_mpp_yaw(const float *table, int64_t table_stride, int h, const float *basis, int M, const float *gref,
                   int64_t gref_stride, int B, int T, int max_iter, float tol, float *theta, float *cost) {
    const int W = 2 * h;
    const int64_t plane = (int64_t)h * W;
    float sx, ox;
    scale_offset(W, &sx, &ox);
    float *cur = (float *)malloc(sizeof(float) * (size_t)(B * T > 0 ? B * T : 1));
    if (!cur) return -1;
    for (int j = 0; j < B * T; ++j) {
        cur[j] = theta[j];
        cost[j] = INFINITY;
    }
    int it = 0;
    while (it < max_iter) {
        ++it;
        float qmax = 0.0f;
        for (int b = 0; b < B; ++b) {
            const float *tb = table + b * table_stride, *P = basis + (int64_t)b * 18 * M, *g = gref + b * gref_stride;
            for (int t = 0; t < T; ++t) {
                const int j = b * T + t;
                const float ks = sinf(cur[j]), kc = 1.0f - cosf(cur[j]);
                double jj = 0, je = 0, ee = 0;
#pragma omp simd reduction(+ : jj, je, ee)
                for (int m = 0; m < M; ++m) {
                    float q[6];
                    for (int r = 0; r < 6; ++r)
                        q[r] = P[r * M + m] + ks * P[(6 + r) * M + m] + kc * P[(12 + r) * M + m];
                    int r0, r1, c0, c1;
                    float fy, fx;
                    sphere_corners(q[0], q[1], q[2], h, W, sx, ox, &r0, &r1, &c0, &c1, &fy, &fx);
                    const float nan = (q[0] - q[0]) + (q[1] - q[1]) + (q[2] - q[2]);
                    float v[4];
                    for (int c = 0; c < 4; ++c) v[c] = bilinear(tb + c * plane, W, r0, r1, c0, c1, fy, fx) + nan;
                    const double J = v[1] * q[3] + v[2] * q[4] + v[3] * q[5], e = v[0] - g[m];
                    jj += J * J;
                    je += J * e;
                    ee += e * e;
                }
                const float c = (float)ee;
                if (c < cost[j]) {  /* the cost of the angle just evaluated */
                    cost[j] = c;
                    theta[j] = cur[j];
                }
                float step = (float)je / ((float)jj > 1e-30f ? (float)jj : 1e-30f);
                step = step > 0.5f ? 0.5f : (step < -0.5f ? -0.5f : step);
                cur[j] -= step;
                const float as = fabsf(step);
                qmax = as > qmax || as != as ? as : qmax;
            }
        }
        if (qmax < tol) break;
    }
    free(cur);
    return it;
}
