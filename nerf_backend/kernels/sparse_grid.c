/* The Plenoxels field's sparse voxel grid, read and differentiated over packed samples on the
 * CPU (nerf_backend/field_components/sparse_grid.py does the same with PyTorch's gathers).
 *
 * The grid's vertices [nx, ny, nz] (z fastest) hold a link each: the row of `values` that
 * vertex keeps, or -1 for a vertex pruned as empty, which reads as zeros. A row holds the
 * vertex's channels (density, then the colour's spherical-harmonic coefficients, padded to a
 * multiple of BLOCK: one vector load a block, rows on whole cache lines). A sample's features
 * are the trilinear blend of its cell's 8 corner rows: 8 random rows, one gather each, and no
 * arithmetic beyond the blend (no network).
 *
 * forward writes each sample's features and, for backward, its corners' rows and weights.
 * backward adds  w_i * g  into the rows' gradient and marks them (a byte a row), so the
 * optimiser updates only those (vm_grid.c's sparse_adam). Threads split the samples in
 * forward; in backward every thread reads every sample's corners but adds only into the rows
 * of its own blocks of rows (row / ROWS_PER_OWNER modulo the threads): no two threads ever add
 * into one row, with no atomics and no per-thread copy of the gradient.
 *
 * Plain C and POSIX threads, no Python API: built by nerf_backend/kernels/build.py and called
 * through ctypes (which releases the GIL).
 */

#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <string.h>

#include "grid_common.h"

#define BLOCK 8
#define CORNERS 8
/* Rows a thread owns together in backward: 16 rows of 32 floats, 2 KB, so two threads never
 * write into one cache line. */
#define ROWS_PER_OWNER 16

typedef float vec __attribute__((vector_size(BLOCK * sizeof(float))));
static inline vec load(const float *p) { vec v; memcpy(&v, p, sizeof v); return v; }
static inline void store(float *p, vec v) { memcpy(p, &v, sizeof v); }
static inline vec splat(float x) { vec v = {x, x, x, x, x, x, x, x}; return v; }

typedef struct {
    const int32_t *links;   /* [nx, ny, nz]: a vertex's row of values, or -1 (reads zeros) */
    const float *values;    /* [rows, channels] */
    int64_t n[3];           /* vertices along x, y, z */
    int64_t channels;       /* a multiple of BLOCK */
} SparseGrid;

/* The sample's 8 corner rows (-1: pruned, weight 0) and trilinear weights. */
static inline void corners_of(const SparseGrid *g, const float *x, int32_t *rows, float *weights) {
    const AxisCorner a = axis_corner(x[0], g->n[0]), b = axis_corner(x[1], g->n[1]), c = axis_corner(x[2], g->n[2]);
    const int64_t base = (a.lower * g->n[1] + b.lower) * g->n[2] + c.lower;
    const int64_t step[3] = {g->n[1] * g->n[2], g->n[2], 1};
    for (int i = 0; i < CORNERS; ++i) {
        const int ia = (i >> 2) & 1, ib = (i >> 1) & 1, ic = i & 1;
        const int32_t row = g->links[base + ia * step[0] + ib * step[1] + ic * step[2]];
        const float w = (ia ? a.high_weight : a.low_weight) * (ib ? b.high_weight : b.low_weight)
                      * (ic ? c.high_weight : c.low_weight);
        rows[i] = (row >= 0 && w > 0.0f) ? row : -1;
        weights[i] = rows[i] >= 0 ? w : 0.0f;
    }
}

typedef struct {
    const SparseGrid *g;
    const float *x;
    float *features;        /* forward: [P, channels]; NULL: the density channel only, to density */
    float *density;         /* [P] or NULL */
    int32_t *rows;          /* [P, 8] or NULL: kept for backward */
    float *weights;         /* [P, 8] or NULL */
    const float *grad;      /* backward: [P, channels] */
    float *values_grad;     /* [rows, channels], added into */
    uint8_t *touched;       /* [rows] or NULL */
    int64_t begin, end, owner, owners;
} Work;

/* Rows a sample reads, asked of memory this many samples ahead: a sample's corners are
 * random rows of a grid larger than the caches. */
#define PREFETCH_AHEAD 4

static void *forward_work(void *arg) {
    const Work *w = (const Work *)arg;
    const SparseGrid *g = w->g;
    const int64_t C = g->channels;
    for (int64_t p = w->begin; p < w->end; ++p) {
        int32_t rows[CORNERS];
        float weights[CORNERS];
        corners_of(g, w->x + 3 * p, rows, weights);
        if (w->rows) {
            memcpy(w->rows + CORNERS * p, rows, sizeof rows);
            memcpy(w->weights + CORNERS * p, weights, sizeof weights);
        }
        if (!w->features) {  /* the density: each corner's first channel */
            float sum = 0.0f;
            for (int i = 0; i < CORNERS; ++i)
                if (rows[i] >= 0) sum += weights[i] * g->values[(int64_t)rows[i] * C];
            w->density[p] = sum;
            continue;
        }
        for (int i = 0; i < CORNERS; ++i)
            if (rows[i] >= 0) __builtin_prefetch(g->values + (int64_t)rows[i] * C + 16, 0, 3);
        float *out = w->features + p * C;
        for (int64_t k = 0; k < C; k += BLOCK) {
            vec sum = splat(0.0f);
            for (int i = 0; i < CORNERS; ++i)
                if (rows[i] >= 0) sum += splat(weights[i]) * load(g->values + (int64_t)rows[i] * C + k);
            store(out + k, sum);
        }
    }
    return NULL;
}

static void *backward_work(void *arg) {
    const Work *w = (const Work *)arg;
    const int64_t C = w->g->channels;
    for (int64_t p = 0; p < w->end; ++p) {
        const int32_t *rows = w->rows + CORNERS * p;
        const float *weights = w->weights + CORNERS * p;
        const float *gp = w->grad + p * C;
        for (int i = 0; i < CORNERS; ++i) {
            const int32_t row = rows[i];
            if (row < 0 || (row / ROWS_PER_OWNER) % w->owners != w->owner) continue;
            float *into = w->values_grad + (int64_t)row * C;
            const vec weight = splat(weights[i]);
            for (int64_t k = 0; k < C; k += BLOCK) store(into + k, load(into + k) + weight * load(gp + k));
            if (w->touched) w->touched[row] = 1;
        }
    }
    return NULL;
}



static int readable(const SparseGrid *g) {
    return g->channels >= BLOCK && g->channels % BLOCK == 0 && g->n[0] >= 2 && g->n[1] >= 2 && g->n[2] >= 2;
}

/* Features [P, channels] of `points` samples x [P, 3] in [-1, 1], or (features NULL) the
 * density channel alone into density [P]; rows and weights [P, 8] (may be NULL) keep each
 * sample's corners for backward. */
int sparse_forward(const SparseGrid *g, const float *x, int64_t points, float *features, float *density,
                   int32_t *rows, float *weights, int64_t threads) {
    if (!readable(g) || (!features && !density)) return -1;
    threads = clamp_threads(threads, (points + 1023) / 1024);
    Work work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        Work one = {g, x, features, density, rows, weights, NULL, NULL, NULL,
                    points * t / threads, points * (t + 1) / threads, t, threads};
        work[t] = one;
    }
    run_all(forward_work, work, sizeof work[0], threads);
    return 0;
}

/* Adds grad [P, channels] into values_grad through the corners forward kept, marking rows. */
int sparse_backward(const SparseGrid *g, const int32_t *rows, const float *weights, int64_t points,
                    const float *grad, float *values_grad, uint8_t *touched, int64_t threads) {
    if (!readable(g)) return -1;
    threads = clamp_threads(threads, (points + 255) / 256);
    Work work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        Work one = {g, NULL, NULL, NULL, (int32_t *)rows, (float *)weights, grad, values_grad, touched,
                    0, points, t, threads};
        work[t] = one;
    }
    run_all(backward_work, work, sizeof work[0], threads);
    return 0;
}

/* The training march reads the density channel. */
typedef SparseGrid DensitySource;

static inline float density_at(const DensitySource *g, const float x[3]) {
    int32_t rows[CORNERS];
    float weights[CORNERS];
    corners_of(g, x, rows, weights);
    float sum = 0.0f;
    for (int i = 0; i < CORNERS; ++i)
        if (rows[i] >= 0) sum += weights[i] * g->values[(int64_t)rows[i] * g->channels];
    return sum;
}

static inline int density_readable(const DensitySource *g) { return readable(g); }

/* Nothing asked ahead: a sparse grid's corner rows are found through its index, itself a read
 * that would have to be waited for. */
static inline void density_prefetch(const DensitySource *g, const float x[3]) { (void)g; (void)x; }

#include "train_march.h"
