/* im2col and col2im (torch.nn.functional.unfold and fold) for contiguous float32 (B, C, H, W) maps.
 *
 * The unfolded ("columns") matrix of a kh x kw convolution is cols (B, C*kh*kw, Ho*Wo) with
 *     cols[b, (c*kh + i)*kw + j, oy*Wo + ox] = x[b, c, oy*sh - ph + i*dh, ox*sw - pw + j*dw]   (0 outside)
 * and col2im is its adjoint: every column value added back onto the pixel it was read from. PyTorch's CPU
 * kernels for these ran at 4-6 GB/s on small deep maps (1024 channels on 4x8, 3x3: 0.19 ms unfold, 0.30 ms fold
 * for 1.2 MB of columns, 2 threads). Here the threads split the (image, channel) planes, and a row of the output
 * is, for stride 1, one shifted copy (or add) of a row of the input with its out-of-range ends zero (or skipped).
 */
#include <stdint.h>

/* output columns ox of [lo, hi) read input column ox * sw - pw + j * dw inside [0, W) */
static void valid_range(int64_t Wo, int64_t W, int64_t sw, int64_t off, int64_t *lo, int64_t *hi) {
    /* ox * sw + off >= 0 and ox * sw + off < W */
    int64_t a = off >= 0 ? 0 : (-off + sw - 1) / sw;
    int64_t b = W - off <= 0 ? 0 : (W - off + sw - 1) / sw;
    if (b > Wo) b = Wo;
    if (a > b) a = b;
    *lo = a;
    *hi = b;
}

/* one row of the columns of a stride-1 convolution whose output is as wide as its input (Wo == W): the row is the
 * plane shifted by (dy, dx) = (i*dh - ph, j*dw - pw), i.e. row[t] = xp[t + dy*W + dx] over the flat index t: one
 * contiguous copy (where the source lies inside the plane), then zeros on the rows outside and on the dx columns
 * at the edges, whose copied values came from the neighbouring row. Small maps (4x8) have rows of a few values,
 * where copying each alone cost more than the copy. */
/* zeros on the values of a shifted row (Ho rows of W) read from outside the (H, W) plane: whole rows above or
 * below it, the dx columns at its left (dx < 0) or right (dx > 0) edge */
static void zero_outside(float *row, int64_t H, int64_t W, int64_t Ho, int64_t dy, int64_t dx) {
    for (int64_t oy = 0; oy < Ho; ++oy) {
        float *r = row + oy * W;
        if (oy + dy < 0 || oy + dy >= H) {
            for (int64_t ox = 0; ox < W; ++ox) r[ox] = 0.0f;
            continue;
        }
        for (int64_t ox = 0; ox < -dx && ox < W; ++ox) r[ox] = 0.0f;
        for (int64_t ox = W - dx > 0 ? W - dx : 0; ox < W; ++ox) r[ox] = 0.0f;
    }
}

static void shifted_row(const float *xp, int64_t H, int64_t W, int64_t Ho, int64_t dy, int64_t dx, float *row) {
    const int64_t L = Ho * W, shift = dy * W + dx;
    int64_t t0 = -shift > 0 ? -shift : 0, t1 = H * W - shift < L ? H * W - shift : L;
    for (int64_t t = 0; t < (t0 < L ? t0 : L); ++t) row[t] = 0.0f;
    for (int64_t t = t0; t < t1; ++t) row[t] = xp[t + shift];
    for (int64_t t = t1 > t0 ? t1 : t0; t < L; ++t) row[t] = 0.0f;
    zero_outside(row, H, W, Ho, dy, dx);
}

int omnidl_im2col(const float *x, int64_t B, int64_t C, int64_t H, int64_t W, int64_t kh, int64_t kw, int64_t sh,
                  int64_t sw, int64_t ph, int64_t pw, int64_t dh, int64_t dw, int64_t Ho, int64_t Wo, float *cols,
                  int nthreads) {
    const int64_t L = Ho * Wo;
    const int flat = sh == 1 && sw == 1 && Wo == W;
#pragma omp parallel for num_threads(nthreads) schedule(static)
    for (int64_t bc = 0; bc < B * C; ++bc) {
        const float *xp = x + bc * H * W;
        for (int64_t i = 0; i < kh; ++i)
            for (int64_t j = 0; j < kw; ++j) {
                float *row = cols + (bc * kh * kw + i * kw + j) * L;
                const int64_t off = j * dw - pw;
                if (flat) {
                    shifted_row(xp, H, W, Ho, i * dh - ph, off, row);
                    continue;
                }
                int64_t lo, hi;
                valid_range(Wo, W, sw, off, &lo, &hi);
                for (int64_t oy = 0; oy < Ho; ++oy) {
                    float *r = row + oy * Wo;
                    const int64_t iy = oy * sh - ph + i * dh;
                    if (iy < 0 || iy >= H || hi <= lo) {
                        for (int64_t ox = 0; ox < Wo; ++ox) r[ox] = 0.0f;
                        continue;
                    }
                    const float *src = xp + iy * W;      /* input column ox * sw + off */
                    for (int64_t ox = 0; ox < lo; ++ox) r[ox] = 0.0f;
                    if (sw == 1)
                        for (int64_t ox = lo; ox < hi; ++ox) r[ox] = src[ox + off];
                    else
                        for (int64_t ox = lo; ox < hi; ++ox) r[ox] = src[ox * sw + off];
                    for (int64_t ox = hi; ox < Wo; ++ox) r[ox] = 0.0f;
                }
            }
    }
    return 0;
}

/* the adjoint of shifted_row, for rows of at most FLAT_MAX values: the row copied into `tmp` with the values read
 * from outside the plane zeroed, then added onto the plane in one contiguous pass (a zero adds nothing) */
#define FLAT_MAX 4096
static void shifted_row_add(const float *row, int64_t H, int64_t W, int64_t Ho, int64_t dy, int64_t dx, float *tmp,
                            float *xp) {
    const int64_t L = Ho * W, shift = dy * W + dx;
    for (int64_t t = 0; t < L; ++t) tmp[t] = row[t];
    zero_outside(tmp, H, W, Ho, dy, dx);
    const int64_t t0 = -shift > 0 ? -shift : 0, t1 = H * W - shift < L ? H * W - shift : L;
    for (int64_t t = t0; t < t1; ++t) xp[t + shift] += tmp[t];
}

int omnidl_col2im(const float *cols, int64_t B, int64_t C, int64_t H, int64_t W, int64_t kh, int64_t kw, int64_t sh,
                  int64_t sw, int64_t ph, int64_t pw, int64_t dh, int64_t dw, int64_t Ho, int64_t Wo, float *x,
                  int nthreads) {
    const int64_t L = Ho * Wo;
    const int flat = sh == 1 && sw == 1 && Wo == W && L <= FLAT_MAX;
#pragma omp parallel for num_threads(nthreads) schedule(static)
    for (int64_t bc = 0; bc < B * C; ++bc) {
        float *xp = x + bc * H * W;
        float tmp[FLAT_MAX];
        for (int64_t q = 0; q < H * W; ++q) xp[q] = 0.0f;
        for (int64_t i = 0; i < kh; ++i)
            for (int64_t j = 0; j < kw; ++j) {
                const float *row = cols + (bc * kh * kw + i * kw + j) * L;
                const int64_t off = j * dw - pw;
                if (flat) {
                    shifted_row_add(row, H, W, Ho, i * dh - ph, off, tmp, xp);
                    continue;
                }
                int64_t lo, hi;
                valid_range(Wo, W, sw, off, &lo, &hi);
                if (hi <= lo) continue;
                for (int64_t oy = 0; oy < Ho; ++oy) {
                    const int64_t iy = oy * sh - ph + i * dh;
                    if (iy < 0 || iy >= H) continue;
                    const float *r = row + oy * Wo;
                    float *dst = xp + iy * W;            /* input column ox * sw + off */
                    if (sw == 1)
                        for (int64_t ox = lo; ox < hi; ++ox) dst[ox + off] += r[ox];
                    else
                        for (int64_t ox = lo; ox < hi; ++ox) dst[ox * sw + off] += r[ox];
                }
            }
    }
    return 0;
}
