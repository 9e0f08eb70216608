/* Instant-NGP's multiresolution hash encoding, read and differentiated on the CPU
 * (nerf_backend/field_components/hash_encoding.py does the same with PyTorch's tensors).
 *
 * A point u in [0, 1]^3 reads, at each level, the 8 corners of its cell: rows of the level's
 * table of `table_size` rows, indexed directly on the coarse levels whose vertices fit
 * (x + y*side + z*side^2) and through the spatial hash on the others
 * ((x*1) xor (y*2654435761) xor (z*805459861) mod table_size). Its features at a level are
 * the trilinear blend of those rows.
 *
 * PyTorch's path forms every corner's index, weight and row as tensors of [points, levels, 8]
 * (a pass through memory each: 0.5 s for 65 536 points on one core); here each point's 128
 * corners are formed in registers and read once. backward forms the same corners again
 * (cheaper than keeping 1 KB a point) and adds w * g into the rows. Threads split the points in
 * forward and the levels in backward: each level has its own table, so no two threads ever add
 * into one row, with no atomics.
 *
 * Plain C and POSIX threads, no Python API: built by nerf_backend/kernels/build.py and called
 * through ctypes (which releases the GIL).
 */

#include <math.h>
#include <stdint.h>

#include "grid_common.h"

#define CORNERS 8
#define MAX_FEATURES 8

typedef struct {
    const float *tables;        /* [levels * table_size, features] */
    const float *resolutions;   /* [levels]: cells a side */
    int64_t levels, table_size, features, dense_levels;
} HashTables;

/* The corner rows (the level's offset included) and trilinear weights of point u at `level`,
 * in PyTorch's order: x's near and far vertex outermost, z's innermost. */
static inline void corners_at(const HashTables *h, const float u[3], int64_t level, int64_t rows[CORNERS],
                              float weights[CORNERS]) {
    const float resolution = h->resolutions[level];
    int64_t near[3];
    float fraction[3];
    for (int axis = 0; axis < 3; ++axis) {
        float x = u[axis];
        x = x > 1.0f ? 1.0f : (x >= 0.0f ? x : 0.0f);  /* clamped; NaN reads the origin */
        const float scaled = x * resolution;
        float cell = floorf(scaled);
        if (cell > resolution - 1.0f) cell = resolution - 1.0f;
        near[axis] = (int64_t)cell;
        fraction[axis] = scaled - cell;
    }
    const int64_t offset = level * h->table_size, mask = h->table_size - 1;
    int64_t term[3][2];
    if (level < h->dense_levels) {
        const int64_t side = (int64_t)resolution + 1;
        const int64_t stride[3] = {1, side, side * side};
        for (int axis = 0; axis < 3; ++axis)
            for (int far = 0; far < 2; ++far) term[axis][far] = (near[axis] + far) * stride[axis];
        for (int i = 0; i < CORNERS; ++i)
            rows[i] = offset + term[0][(i >> 2) & 1] + term[1][(i >> 1) & 1] + term[2][i & 1];
    } else {
        const uint32_t primes[3] = {1u, 2654435761u, 805459861u};
        for (int axis = 0; axis < 3; ++axis)
            for (int far = 0; far < 2; ++far)
                term[axis][far] = (int64_t)((uint32_t)(near[axis] + far) * primes[axis]) & mask;
        for (int i = 0; i < CORNERS; ++i)
            rows[i] = (term[0][(i >> 2) & 1] | offset) ^ term[1][(i >> 1) & 1] ^ term[2][i & 1];
    }
    for (int i = 0; i < CORNERS; ++i) {
        const int ix = (i >> 2) & 1, iy = (i >> 1) & 1, iz = i & 1;
        weights[i] = (ix ? fraction[0] : 1.0f - fraction[0]) * (iy ? fraction[1] : 1.0f - fraction[1])
                   * (iz ? fraction[2] : 1.0f - fraction[2]);
    }
}

typedef struct {
    const HashTables *h;
    const float *u;             /* [P, 3] */
    float *encoded;             /* forward: [P, levels * features] */
    const float *grad;          /* backward: [P, levels * features] */
    float *tables_grad;         /* [levels * table_size, features], added into */
    int64_t points, begin, end, owner, owners;
} Work;

static void *forward_work(void *arg) {
    const Work *w = (const Work *)arg;
    const HashTables *h = w->h;
    const int64_t F = h->features, L = h->levels;
    for (int64_t p = w->begin; p < w->end; ++p) {
        float *out = w->encoded + p * L * F;
        for (int64_t level = 0; level < L; ++level) {
            int64_t rows[CORNERS];
            float weights[CORNERS];
            corners_at(h, w->u + 3 * p, level, rows, weights);
            float sum[MAX_FEATURES] = {0};
            for (int i = 0; i < CORNERS; ++i) {
                const float *row = h->tables + rows[i] * F;
                for (int64_t f = 0; f < F; ++f) sum[f] += weights[i] * row[f];
            }
            for (int64_t f = 0; f < F; ++f) out[level * F + f] = sum[f];
        }
    }
    return NULL;
}

static void *backward_work(void *arg) {
    const Work *w = (const Work *)arg;
    const HashTables *h = w->h;
    const int64_t F = h->features, L = h->levels;
    for (int64_t level = w->owner; level < L; level += w->owners) {
        for (int64_t p = 0; p < w->points; ++p) {
            const float *g = w->grad + p * L * F + level * F;
            int nonzero = 0;
            for (int64_t f = 0; f < F; ++f) nonzero |= g[f] != 0.0f;
            if (!nonzero) continue;
            int64_t rows[CORNERS];
            float weights[CORNERS];
            corners_at(h, w->u + 3 * p, level, rows, weights);
            for (int i = 0; i < CORNERS; ++i) {
                float *into = w->tables_grad + rows[i] * F;
                for (int64_t f = 0; f < F; ++f) into[f] += weights[i] * g[f];
            }
        }
    }
    return NULL;
}

static int readable(const HashTables *h) {
    /* The hash multiplies in 32 bits: exact modulo tables of up to 2^32 rows. */
    return h->features >= 1 && h->features <= MAX_FEATURES && h->levels >= 1 && h->table_size >= 1
        && h->table_size <= ((int64_t)1 << 32) && (h->table_size & (h->table_size - 1)) == 0 && h->dense_levels >= 0 && h->dense_levels <= h->levels;
}

/* encoded [P, levels * features] of the points u [P, 3] (clamped to [0, 1]). */
int hash_forward(const HashTables *h, const float *u, int64_t points, float *encoded, int64_t threads) {
    if (!readable(h)) return -1;
    threads = clamp_threads(threads, (points + 511) / 512);
    Work work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        Work one = {h, u, encoded, NULL, NULL, points, points * t / threads, points * (t + 1) / threads, t, threads};
        work[t] = one;
    }
    run_all(forward_work, work, sizeof work[0], threads);
    return 0;
}

/* Adds grad [P, levels * features] into tables_grad through each point's corners. */
int hash_backward(const HashTables *h, const float *u, int64_t points, const float *grad, float *tables_grad,
                  int64_t threads) {
    if (!readable(h)) return -1;
    threads = clamp_threads(threads, h->levels < (points + 255) / 256 ? h->levels : (points + 255) / 256);
    Work work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        Work one = {h, u, NULL, grad, tables_grad, points, 0, points, t, threads};
        work[t] = one;
    }
    run_all(backward_work, work, sizeof work[0], threads);
    return 0;
}
