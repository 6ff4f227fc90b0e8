/* The synthetic renderer's layout maps from its room-class map in one pass each (omnidl/synth/layout.py):
 * per column, the first ceiling -> wall and the last wall -> floor transition between pixel rows, and the
 * structural edge map. Integer work only: the results are the tensor path's exactly. */
#include <stdint.h>

enum { CEILING = 1, WALL = 2, FLOOR = 3 };

/* kind (H, W) room classes (0 none, CEILING, WALL, FLOOR). For each column x: has_c[x] = 1 if some row r < H - 1 has
 * kind[r][x] == CEILING and kind[r + 1][x] == WALL, i_c[x] = the first such r (0 if none); has_f, i_f the same for
 * WALL then FLOOR with the last such r (H - 2 if none). Returns 0. */
int omnidl_layout_brackets(const int64_t *kind, int64_t H, int64_t W, int64_t *i_c, uint8_t *has_c, int64_t *i_f,
                           uint8_t *has_f) {
    for (int64_t x = 0; x < W; ++x) {
        i_c[x] = 0;
        has_c[x] = 0;
        i_f[x] = H - 2;
        has_f[x] = 0;
    }
    for (int64_t r = 0; r + 1 < H; ++r) {
        const int64_t *a = kind + r * W, *b = a + W;
#pragma omp simd
        for (int64_t x = 0; x < W; ++x) {
            const int c = a[x] == CEILING && b[x] == WALL, f = a[x] == WALL && b[x] == FLOOR;
            i_c[x] = c && !has_c[x] ? r : i_c[x];
            has_c[x] |= (uint8_t)c;
            i_f[x] = f ? r : i_f[x];
            has_f[x] |= (uint8_t)f;
        }
    }
    return 0;
}

/* edges (H, W) = 1 where a wall pixel's right neighbour (column x + 1, wrapped when wraps, else the last column
 * repeated) is a wall pixel with another key, key = kind * 64 + max(wall, 0) on walls, kind elsewhere; and, when the
 * camera does not wrap, also where the pixel below (the last row repeated) has another key and both keys are > 0;
 * else 0. Returns 0. */
int omnidl_layout_edges(const int64_t *kind, const int64_t *wall, int64_t H, int64_t W, int wraps, float *edges,
                        int nthreads) {
#pragma omp parallel for num_threads(nthreads) schedule(static) if (H * W > 65536)
    for (int64_t r = 0; r < H; ++r) {
        const int64_t *k = kind + r * W, *w = wall + r * W;
        const int64_t rb = r + 1 < H ? r + 1 : H - 1;
        const int64_t *kb = kind + rb * W, *wb = wall + rb * W;
        float *e = edges + r * W;
        for (int64_t x = 0; x < W; ++x) {
            const int64_t xr = x + 1 < W ? x + 1 : (wraps ? 0 : W - 1);
            const int is_w = k[x] == WALL, right_w = k[xr] == WALL;
            const int64_t key = k[x] * 64 + (is_w ? (w[x] > 0 ? w[x] : 0) : 0);
            const int64_t right = k[xr] * 64 + (right_w ? (w[xr] > 0 ? w[xr] : 0) : 0);
            int edge = key != right && is_w && right_w;
            if (!wraps) {
                const int64_t below = kb[x] * 64 + (kb[x] == WALL ? (wb[x] > 0 ? wb[x] : 0) : 0);
                edge |= key != below && key > 0 && below > 0;
            }
            e[x] = edge ? 1.0f : 0.0f;
        }
    }
    return 0;
}
