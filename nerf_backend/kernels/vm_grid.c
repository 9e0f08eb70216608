/* The factorised (vector-matrix) feature grid of the grid field, read and differentiated over
 * packed samples on the CPU: what nerf_backend/field_components/grid_encodings.py does with
 * PyTorch's embedding_bag (one gather and one scatter of a table per plane and line, a dense
 * gradient the size of the grid filled through a sort of the indices) is here one pass over
 * the samples per component.
 *
 * A component m of a grid holds a plane P[a, b, C] and a line L[c, C] (channel-last: a
 * corner's C channels are one contiguous row, one or two cache lines), and a sample's features
 * are  F[k] = (sum_i w_i P[row_i, k]) * (u_0 L[c_0, k] + u_1 L[c_0 + 1, k])  over its 4 plane
 * corners and 2 line corners. Backward scatters  w_i * g[k] * line[k]  into the plane's rows and
 * u_j * g[k] * plane[k]  into the line's, and marks each row it touched (a byte a row), so
 * the optimiser can update only those rows (sparse_adam below).
 *
 * Threads: forward splits the samples (outputs are disjoint); backward gives each thread whole
 * components (a component's plane and line belong to one thread, so no two threads ever add
 * into the same row: no atomics, no per-thread copies of the grid), balanced by channels.
 *
 * Plain C and POSIX threads, no Python API: built by nerf_backend/kernels/build.py and called
 * through ctypes (which releases the GIL).
 */

#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "grid_common.h"

#define MAX_TASKS 16

typedef struct {
    const float *plane;     /* [na * nb, channels] */
    const float *line;      /* [nc, channels] */
    float *features;        /* forward: out + this component's first column */
    const float *grad;      /* backward: grad_out + this component's first column */
    float *plane_grad;      /* [na * nb, channels], added into */
    float *line_grad;       /* [nc, channels], added into */
    uint8_t *plane_touched; /* [na * nb] or NULL: set to 1 where a row got gradient */
    uint8_t *line_touched;  /* [nc] or NULL */
    int64_t row_stride;     /* floats between two samples' rows of features / grad */
    int32_t axis_a, axis_b, axis_c;
    int32_t na, nb, nc;
    int32_t channels;
    int32_t pad;
} Component;


typedef struct {
    AxisCorner a, b, c;
    int64_t row;            /* the plane's lower corner row */
} SampleCorners;

static inline SampleCorners corners_of(const Component *m, const float *x) {
    SampleCorners s;
    s.a = axis_corner(x[m->axis_a], m->na);
    s.b = axis_corner(x[m->axis_b], m->nb);
    s.c = axis_corner(x[m->axis_c], m->nc);
    s.row = (int64_t)s.a.lower * m->nb + s.b.lower;
    return s;
}

/* Channels go in blocks of 8 floats, each one vector (GCC's and Clang's vector extension:
 * AVX2 on x86, NEON pairs on ARM). Written out, not left to the auto-vectoriser: it made the
 * gradient's adds scalar stores, which the next sample's vector loads of the same row could
 * not take from the store buffer (a stall on every row, 6x slower here). A component's
 * channels must be a multiple of BLOCK (the caller checks; others train through PyTorch). */
#define BLOCK 8
typedef float vec __attribute__((vector_size(BLOCK * sizeof(float))));

static inline vec load(const float *p) { vec v; memcpy(&v, p, sizeof v); return v; }
static inline void store(float *p, vec v) { memcpy(p, &v, sizeof v); }
static inline vec splat(float x) { vec v = {x, x, x, x, x, x, x, x}; return v; }

/* A component's features at a sample whose three corners are found: forward_sample's read, and
 * colour_network.h's features_at, which finds each axis's corners once for all three components. */
static inline void component_features(const Component *m, AxisCorner a, AxisCorner b, AxisCorner c, float *out) {
    const int32_t C = m->channels;
    const vec w00 = splat(a.low_weight * b.low_weight), w01 = splat(a.low_weight * b.high_weight);
    const vec w10 = splat(a.high_weight * b.low_weight), w11 = splat(a.high_weight * b.high_weight);
    const vec u0 = splat(c.low_weight), u1 = splat(c.high_weight);
    const float *p00 = m->plane + ((int64_t)a.lower * m->nb + b.lower) * C, *p01 = p00 + C;
    const float *p10 = p00 + (int64_t)m->nb * C, *p11 = p10 + C;
    const float *l0 = m->line + c.lower * C, *l1 = l0 + C;
    for (int32_t k = 0; k < C; k += BLOCK) {
        vec plane = w00 * load(p00 + k) + w01 * load(p01 + k) + w10 * load(p10 + k) + w11 * load(p11 + k);
        store(out + k, plane * (u0 * load(l0 + k) + u1 * load(l1 + k)));
    }
}

static void forward_sample(const Component *m, const float *x, float *out) {
    const SampleCorners s = corners_of(m, x);
    component_features(m, s.a, s.b, s.c, out);
}

static inline void add_into(float *p, vec v) { store(p, load(p) + v); }

/* A sample's gradient into a component's rows: the incoming gradient `g` a row of its channels
 * (`broadcast` 0), or one value for every channel (1: the lit pass's density, a sum of them). */
static inline void backward_at(const Component *m, SampleCorners s, const float *g, int broadcast) {
    const int32_t C = m->channels;
    const vec w00 = splat(s.a.low_weight * s.b.low_weight), w01 = splat(s.a.low_weight * s.b.high_weight);
    const vec w10 = splat(s.a.high_weight * s.b.low_weight), w11 = splat(s.a.high_weight * s.b.high_weight);
    const vec u0 = splat(s.c.low_weight), u1 = splat(s.c.high_weight);
    const int64_t r00 = s.row, r01 = r00 + 1, r10 = r00 + m->nb, r11 = r10 + 1;
    const int64_t c0 = s.c.lower, c1 = c0 + 1;
    const float *p00 = m->plane + r00 * C, *p01 = m->plane + r01 * C;
    const float *p10 = m->plane + r10 * C, *p11 = m->plane + r11 * C;
    const float *l0 = m->line + c0 * C, *l1 = m->line + c1 * C;
    float *gp00 = m->plane_grad + r00 * C, *gp01 = m->plane_grad + r01 * C;
    float *gp10 = m->plane_grad + r10 * C, *gp11 = m->plane_grad + r11 * C;
    float *gl0 = m->line_grad + c0 * C, *gl1 = m->line_grad + c1 * C;
    const vec g_all = splat(g[0]);
    for (int32_t k = 0; k < C; k += BLOCK) {
        const vec gk = broadcast ? g_all : load(g + k);  /* d out / d plane = g * line; d out / d line = g * plane */
        const vec to_plane = gk * (u0 * load(l0 + k) + u1 * load(l1 + k));
        const vec to_line = gk * (w00 * load(p00 + k) + w01 * load(p01 + k) + w10 * load(p10 + k) + w11 * load(p11 + k));
        add_into(gp00 + k, w00 * to_plane);
        add_into(gp01 + k, w01 * to_plane);
        add_into(gp10 + k, w10 * to_plane);
        add_into(gp11 + k, w11 * to_plane);
        add_into(gl0 + k, u0 * to_line);
        add_into(gl1 + k, u1 * to_line);
    }
    if (m->plane_touched) {
        m->plane_touched[r00] = m->plane_touched[r01] = m->plane_touched[r10] = m->plane_touched[r11] = 1;
    }
    if (m->line_touched) m->line_touched[c0] = m->line_touched[c1] = 1;
}

static inline void backward_sample(const Component *m, const float *x, const float *g, int broadcast) {
    backward_at(m, corners_of(m, x), g, broadcast);
}

typedef struct {
    const Component *components;
    int32_t count;
    const float *x;
    int64_t begin, end;     /* forward: the samples of this thread */
    int32_t owned[MAX_TASKS];  /* backward: the components of this thread */
    int32_t owned_count;
} Work;

/* The rows a sample will read, asked of memory PREFETCH_AHEAD samples before it is reached:
 * samples of different rays land on rows far apart in a grid larger than the caches, and the
 * loads of one sample alone leave most of that latency waiting. */
#define PREFETCH_AHEAD 6

/* Always inlined: a function of prefetches alone is side-effect free to GCC ("looping pure"),
 * and GCC 12 at -O1 and above dropped every call to it, so none of these prefetches reached the
 * machine code (tests/test_kernel_prefetch.py checks that they do). */
static inline __attribute__((always_inline)) void prefetch_rows_at(const Component *m, SampleCorners s, int write) {
    const int64_t C = m->channels;
    const float *plane = write ? m->plane_grad : m->plane, *line = write ? m->line_grad : m->line;
    const float *rows[4] = {plane + s.row * C, plane + (s.row + m->nb) * C, line + (int64_t)s.c.lower * C, NULL};
    for (int i = 0; i < 3; ++i)  /* each pair of neighbouring rows: 2C floats from its first */
        for (int64_t offset = 0; offset < 2 * C; offset += 16) {
            if (write) __builtin_prefetch(rows[i] + offset, 1, 3);
            else __builtin_prefetch(rows[i] + offset, 0, 3);
        }
}

static inline __attribute__((always_inline)) void prefetch_rows(const Component *m, const float *x, int write) {
    prefetch_rows_at(m, corners_of(m, x), write);
}

/* A component's backward over n samples (points x + i * x_stride, gradients g + i * g_stride),
 * the rows of the sample `ahead` on asked of memory (values and gradients), each sample's
 * corners found once for both (a ring of the next ones) where they were found three times. */
#define CORNER_RING 16
static inline __attribute__((always_inline)) void backward_samples(const Component *m, const float *x,
                                                                   int64_t x_stride, const float *g, int64_t g_stride,
                                                                   int64_t n, int broadcast, int ahead) {
    SampleCorners ring[CORNER_RING];
    for (int64_t i = 0; i < n && i < ahead; ++i) ring[i % CORNER_RING] = corners_of(m, x + i * x_stride);
    for (int64_t i = 0; i < n; ++i) {
        if (i + ahead < n) {
            const SampleCorners s = corners_of(m, x + (i + ahead) * x_stride);
            ring[(i + ahead) % CORNER_RING] = s;
            prefetch_rows_at(m, s, 0);
            prefetch_rows_at(m, s, 1);
        }
        backward_at(m, ring[i % CORNER_RING], g + i * g_stride, broadcast);
    }
}

static void *forward_work(void *arg) {
    const Work *w = (const Work *)arg;
    for (int64_t p = w->begin; p < w->end; ++p) {
        if (PREFETCH_AHEAD && p + PREFETCH_AHEAD < w->end)
            for (int32_t i = 0; i < w->count; ++i) prefetch_rows(&w->components[i], w->x + 3 * (p + PREFETCH_AHEAD), 0);
        for (int32_t i = 0; i < w->count; ++i) {
            const Component *m = &w->components[i];
            forward_sample(m, w->x + 3 * p, m->features + p * m->row_stride);
        }
    }
    return NULL;
}

/* Samples outer, the thread's components inner: each sample's row of the incoming gradient is
 * read in one piece (component by component over all samples, the strided reads missed the
 * cache on every sample: 5x slower). */
static void *backward_work(void *arg) {
    const Work *w = (const Work *)arg;
    for (int64_t p = w->begin; p < w->end; ++p) {
        if (PREFETCH_AHEAD && p + PREFETCH_AHEAD < w->end)
            for (int32_t j = 0; j < w->owned_count; ++j) {
                const Component *m = &w->components[w->owned[j]];
                prefetch_rows(m, w->x + 3 * (p + PREFETCH_AHEAD), 0);
                prefetch_rows(m, w->x + 3 * (p + PREFETCH_AHEAD), 1);
            }
        for (int32_t j = 0; j < w->owned_count; ++j) {
            const Component *m = &w->components[w->owned[j]];
            backward_sample(m, w->x + 3 * p, m->grad + p * m->row_stride, 0);
        }
    }
    return NULL;
}



/* Features of `points` samples x [P, 3] in [-1, 1] for each component. */
int vm_forward(const Component *components, int32_t count, const float *x, int64_t points, int64_t threads) {
    if (count < 1 || count > MAX_TASKS) return -1;
    for (int32_t i = 0; i < count; ++i)
        if (components[i].channels < 1 || components[i].channels % BLOCK != 0) return -2;
    threads = clamp_threads(threads, (points + 1023) / 1024);
    Work work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        work[t].components = components;
        work[t].count = count;
        work[t].x = x;
        work[t].begin = points * t / threads;
        work[t].end = points * (t + 1) / threads;
        work[t].owned_count = 0;
    }
    run_all(forward_work, work, sizeof work[0], threads);
    return 0;
}

/* Adds each component's gradient into its plane_grad and line_grad (and marks the rows). Each
 * component goes whole to one thread: the largest first, to the least loaded thread. */
int vm_backward(const Component *components, int32_t count, const float *x, int64_t points, int64_t threads) {
    if (count < 1 || count > MAX_TASKS) return -1;
    for (int32_t i = 0; i < count; ++i)
        if (components[i].channels < 1 || components[i].channels % BLOCK != 0) return -2;
    threads = clamp_threads(threads, count);
    Work work[MAX_THREADS];
    int64_t load[MAX_THREADS] = {0};
    int32_t taken[MAX_TASKS] = {0};
    for (int64_t t = 0; t < threads; ++t) {
        work[t].components = components;
        work[t].count = count;
        work[t].x = x;
        work[t].begin = 0;
        work[t].end = points;
        work[t].owned_count = 0;
    }
    for (int32_t round = 0; round < count; ++round) {
        int32_t largest = -1;
        for (int32_t i = 0; i < count; ++i)
            if (!taken[i] && (largest < 0 || components[i].channels > components[largest].channels)) largest = i;
        taken[largest] = 1;
        int64_t least = 0;
        for (int64_t t = 1; t < threads; ++t)
            if (load[t] < load[least]) least = t;
        work[least].owned[work[least].owned_count++] = largest;
        load[least] += components[largest].channels;
    }
    run_all(backward_work, work, sizeof work[0], threads);
    return 0;
}

/* Adam on the rows of a [rows, width] parameter that the step touched (touched[r] = 1), the
 * others left as they are (DVGO's and Instant-NGP's masked Adam). A row last updated at step
 * last[r] has skipped step - last[r] - 1 steps whose gradient was zero: its moments decay by
 * beta^skipped first, as dense Adam's would have (its value's drift over those steps, which
 * dense Adam would also have made, is not). Then the row's gradient is zeroed and its mark
 * cleared, so the buffers are ready for the next step without a pass over the whole grid.
 * `step` counts from 1; bias correction uses it, as dense Adam's does. */
#define DECAY_TABLE 256
#define ROWS_AHEAD 8

typedef struct {
    float *param, *grad, *exp_avg, *exp_avg_sq;
    uint8_t *touched;
    float *last;            /* the step each row was last updated at (exact below 2^24 steps) */
    int64_t rows, width, step;
    float lr, beta1, beta2, eps;
    int64_t begin, end;
    int64_t updated;
    const float *decay1, *decay2;  /* beta^k for k < DECAY_TABLE: powf a row cost more than its update */
} AdamWork;

static void *adam_work(void *arg) {
    AdamWork *w = (AdamWork *)arg;
    const float correction1 = 1.0f - powf(w->beta1, (float)w->step);
    const float correction2_root = sqrtf(1.0f - powf(w->beta2, (float)w->step));
    const float step_size = w->lr / correction1;
    int64_t updated = 0;
    /* The touched rows lie scattered: the next ROWS_AHEAD of them are asked of memory while
     * this one is updated (a touched row's four arrays missed the cache otherwise). */
    int64_t ahead = w->begin, pending = 0;
    for (int64_t r = w->begin; r < w->end; ++r) {
        for (; ahead < w->end && pending < ROWS_AHEAD; ++ahead)
            if (w->touched[ahead]) {
                ++pending;
                for (int64_t k = 0; k < w->width; k += 16) {
                    __builtin_prefetch(w->param + ahead * w->width + k, 1, 3);
                    __builtin_prefetch(w->grad + ahead * w->width + k, 1, 3);
                    __builtin_prefetch(w->exp_avg + ahead * w->width + k, 1, 3);
                    __builtin_prefetch(w->exp_avg_sq + ahead * w->width + k, 1, 3);
                }
            }
        if (!w->touched[r]) continue;
        --pending;
        w->touched[r] = 0;
        ++updated;
        int64_t skipped = w->step - (int64_t)w->last[r] - 1;
        float decay1 = 1.0f, decay2 = 1.0f;
        if (skipped > 0 && skipped < DECAY_TABLE) {
            decay1 = w->decay1[skipped];
            decay2 = w->decay2[skipped];
        } else if (skipped > 0) {
            decay1 = powf(w->beta1, (float)skipped);
            decay2 = powf(w->beta2, (float)skipped);
        }
        w->last[r] = (float)w->step;
        float *p = w->param + r * w->width, *g = w->grad + r * w->width;
        float *m = w->exp_avg + r * w->width, *v = w->exp_avg_sq + r * w->width;
        for (int64_t k = 0; k < w->width; ++k) {
            float mk = w->beta1 * (decay1 * m[k]) + (1.0f - w->beta1) * g[k];
            float vk = w->beta2 * (decay2 * v[k]) + (1.0f - w->beta2) * g[k] * g[k];
            m[k] = mk;
            v[k] = vk;
            p[k] -= step_size * mk / (sqrtf(vk) / correction2_root + w->eps);
            g[k] = 0.0f;
        }
    }
    w->updated = updated;
    return NULL;
}

/* Returns the number of rows updated. */
int64_t sparse_adam(float *param, float *grad, float *exp_avg, float *exp_avg_sq, uint8_t *touched, float *last,
                    int64_t rows, int64_t width, int64_t step, float lr, float beta1, float beta2, float eps,
                    int64_t threads) {
    threads = clamp_threads(threads, (rows + 4095) / 4096);
    AdamWork work[MAX_THREADS];
    float decay1[DECAY_TABLE], decay2[DECAY_TABLE];
    decay1[0] = decay2[0] = 1.0f;
    for (int k = 1; k < DECAY_TABLE; ++k) {
        decay1[k] = decay1[k - 1] * beta1;
        decay2[k] = decay2[k - 1] * beta2;
    }
    for (int64_t t = 0; t < threads; ++t) {
        AdamWork w = {param, grad, exp_avg, exp_avg_sq, touched, last, rows, width, step, lr, beta1, beta2, eps,
                      rows * t / threads, rows * (t + 1) / threads, 0, decay1, decay2};
        work[t] = w;
    }
    run_all(adam_work, work, sizeof work[0], threads);
    int64_t updated = 0;
    for (int64_t t = 0; t < threads; ++t) updated += work[t].updated;
    return updated;
}

/* The grid's features summed at every vertex, out[nz][ny][nx] (x fastest: the volume the render
 * march reads, and the occupancy's vertex sums):
 *   out[z][y][x] = sum_c yz[y][z][c] X[c][x] + z_line[z][c] XY[y][c][x] + y_line[y][c] XZ[z][c][x]
 * with the x line and the two planes that hold x given x-fastest (X, XY, XZ: the caller's
 * transposes of 11 and 7 MB on lego's thirty-minute grid), so that a row of x is 8 vertices a
 * vector and every load contiguous. Each output is written once, its sum kept in registers over
 * the channels: through PyTorch it was three matrix products of 16-long rows, each a pass
 * over the volume's 226 MB: 0.38-0.47 s on 2 AVX2 cores (lego's thirty-minute grid), here
 * 0.11-0.13 s, and 0.07-0.13 s more for the first touch of the volume's pages. Its 5.4 GFLOP
 * take 42 ms at the machine's 128 GFLOP/s of fused products, 84 ms as the separate products and
 * sums ISO C compiles to: 1.4 times that. Row by row over every y for each z, the (x, y) plane's
 * 11 MB were read again for each z: 0.3-0.8 s. Tiles of z, y and x that keep a run's columns in
 * L1 measured slower (0.26 s). Threads take shares of y. */
typedef struct {
    const float *x_columns, *xy_columns, *xz_columns; /* [C][nx], [ny][C][nx], [nz][C][nx] */
    const float *yz, *y_line, *z_line;                /* [ny][nz][C], [ny][C], [nz][C] */
    float *out;
    int64_t nx, ny, nz, channels, first_y, end_y;
} DenseSum;

#define DENSE_VECTORS 4 /* runs of 4 vectors: 12 loads and 12 products a channel */
/* A share of y is summed in tiles of y rows whose (x, y) plane columns (20 KB a row at 16
 * channels and 310 vertices along x) fill this much of L2 while every z passes over them. */
#define DENSE_TILE_BYTES (256 * 1024)

/* out[z][y][0 .. nx): the vertices' sums over the channels, held in registers. */
static void dense_row(const DenseSum *d, int64_t z, int64_t y) {
    const int64_t C = d->channels, nx = d->nx;
    const float *a = d->yz + (y * d->nz + z) * C, *b = d->z_line + z * C, *e = d->y_line + y * C;
    const float *xy = d->xy_columns + y * C * nx, *xz = d->xz_columns + z * C * nx;
    float *row = d->out + (z * d->ny + y) * nx;
    int64_t x = 0;
    for (; x + DENSE_VECTORS * BLOCK <= nx; x += DENSE_VECTORS * BLOCK) {
        vec sum[DENSE_VECTORS] = {{0}};
        for (int64_t c = 0; c < C; ++c) {
            const vec ac = splat(a[c]), bc = splat(b[c]), ec = splat(e[c]);
            const float *p = d->x_columns + c * nx + x, *q = xy + c * nx + x, *r = xz + c * nx + x;
            for (int k = 0; k < DENSE_VECTORS; ++k)
                sum[k] += ac * load(p + k * BLOCK) + bc * load(q + k * BLOCK) + ec * load(r + k * BLOCK);
        }
        for (int k = 0; k < DENSE_VECTORS; ++k) store(row + x + k * BLOCK, sum[k]);
    }
    for (; x + BLOCK <= nx; x += BLOCK) {
        vec sum = {0};
        for (int64_t c = 0; c < C; ++c)
            sum += splat(a[c]) * load(d->x_columns + c * nx + x) + splat(b[c]) * load(xy + c * nx + x)
                   + splat(e[c]) * load(xz + c * nx + x);
        store(row + x, sum);
    }
    for (; x < nx; ++x) {
        float sum = 0.0f;
        for (int64_t c = 0; c < C; ++c)
            sum += a[c] * d->x_columns[c * nx + x] + b[c] * xy[c * nx + x] + e[c] * xz[c * nx + x];
        row[x] = sum;
    }
}

static void *dense_work(void *argument) {
    const DenseSum *d = argument;
    int64_t tile = DENSE_TILE_BYTES / (int64_t)(sizeof(float) * d->channels * d->nx);
    if (tile < 1) tile = 1;
    for (int64_t y0 = d->first_y; y0 < d->end_y; y0 += tile) {
        const int64_t y1 = y0 + tile < d->end_y ? y0 + tile : d->end_y;
        for (int64_t z = 0; z < d->nz; ++z)
            for (int64_t y = y0; y < y1; ++y) dense_row(d, z, y);
    }
    return NULL;
}

void vm_dense_sum(const float *x_columns, const float *xy_columns, const float *xz_columns, const float *yz,
                  const float *y_line, const float *z_line, int64_t nx, int64_t ny, int64_t nz, int64_t channels,
                  float *out, int64_t threads) {
    threads = clamp_threads(threads, ny);
    DenseSum work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        DenseSum d = {x_columns, xy_columns, xz_columns, yz, y_line, z_line, out, nx, ny, nz, channels,
                      ny * t / threads, ny * (t + 1) / threads};
        work[t] = d;
    }
    run_all(dense_work, work, sizeof work[0], threads);
}

/* The training march reads the density grid: its 3 components, the density the sum of their
 * features (a Component[3]). */
typedef Component DensitySource;

static inline float density_at(const DensitySource *density, const float x[3]) {
    float features[MAX_TASKS * 64];
    float sum = 0.0f;
    for (int i = 0; i < 3; ++i) {
        const Component *m = &density[i];
        forward_sample(m, x, features);
        for (int32_t k = 0; k < m->channels; ++k) sum += features[k];
    }
    return sum;
}

static inline __attribute__((always_inline)) void density_prefetch(const DensitySource *density, const float x[3]) {
    for (int i = 0; i < 3; ++i) prefetch_rows(&density[i], x, 0);
}

static inline int density_readable(const DensitySource *density) {
    for (int i = 0; i < 3; ++i)
        if (density[i].channels < 1 || density[i].channels % BLOCK != 0 || density[i].channels > 64) return 0;
    return 1;
}

#include "train_march.h"
#include "lit_pass.h"
#include "colour_network.h"
