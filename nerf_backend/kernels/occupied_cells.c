/* The occupancy grid's cells from a grid field's dense pre-activation sums in one pass
 * (model_components/occupancy.py's `cells_over`).
 *
 * sums [nz][ny][nx] (x fastest) are the density's pre-activation at the grid's vertices; a
 * cell's largest corner sum bounds the sum inside it (it is trilinear there), and the density
 * activation increases with the sum, so "the cell's largest density exceeds a threshold" is
 * "its largest corner sum exceeds the threshold's sum", `above`. Written to occupied
 * [nx-1][ny-1][nz-1] (z fastest: OccupancyGrid's layout), and-ed with `allowed` (the same
 * layout) where given. A NaN corner leaves its cell unmarked, as torch.maximum's NaN would.
 *
 * Beside it, for the threshold's rule "never above the mean density": the sums over the
 * vertices and over the cells' largest corners of max(0, sum + shift), which softplus(sum +
 * shift) never falls below. Through PyTorch (the maxima of eight corners, the activation, a
 * transposed compare) lego's thirty-minute grid of 309 × 532 × 344 vertices took 0.54-0.78 s
 * on 2 cores, here 0.09-0.11 s: about half of it the tiles' writes, each x's cells a page apart.
 *
 * Threads take shares of the cells' y; each works through tiles of Z_TILE cells along z, the
 * largest corner of a (y, y + 1) × (x, x + 1) face first, row by row, then two faces a cell,
 * then the tile's flags turned to z fastest through a buffer that stays in L1. */

#include <stdlib.h>
#include <string.h>

#include "grid_common.h"

#define Z_TILE 64
#define LANES 8
#ifndef PREFETCH_ROWS
#define PREFETCH_ROWS 2
#endif

typedef struct {
    const float *sums;
    int64_t nz, ny, nx;
    double above;
    float shift;
    const uint8_t *allowed; /* may be NULL */
    uint8_t *occupied;
    int64_t first_y, end_y; /* this share's cells along y */
    double vertex_excess, cell_excess;
    int failed;
} Job;

/* NaN wins, as torch.maximum's does. */
static inline float max_nan(float a, float b) { return (a > b || a != a) ? a : b; }

/* The sum over row[0 .. n) of max(0, row[x] + shift), in LANES float lanes, then double. */
static double row_excess(const float *row, int64_t n, float shift) {
    float lane[LANES] = {0};
    int64_t x = 0;
    for (; x + LANES <= n; x += LANES)
        for (int k = 0; k < LANES; ++k) {
            const float e = row[x + k] + shift;
            lane[k] += e > 0.0f ? e : 0.0f;
        }
    double total = 0.0;
    for (; x < n; ++x) {
        const float e = row[x] + shift;
        total += e > 0.0f ? e : 0.0f;
    }
    for (int k = 0; k < LANES; ++k) total += lane[k];
    return total;
}

/* An 8 × 8 byte matrix, a row a word (byte j of word i at bits 8j: little-endian, as every
 * target here is), transposed in place: blocks of 4, 2, then 1 bytes swapped across the
 * diagonal. */
static inline void transpose_bytes(uint64_t a[8]) {
    static const uint64_t low[3] = {0x00000000FFFFFFFFull, 0x0000FFFF0000FFFFull, 0x00FF00FF00FF00FFull};
    for (int stage = 0, s = 4; s >= 1; s >>= 1, ++stage)
        for (int i = 0; i < 8; ++i) {
            if (i & s) continue;
            const uint64_t t = ((a[i] >> (8 * s)) ^ a[i + s]) & low[stage];
            a[i + s] ^= t;
            a[i] ^= t << (8 * s);
        }
}

/* The tile's flags [depth][gx] (x fastest) into occupied's [gx][gy][gz] at (y, z0), and-ed
 * with allowed's where given: 8 × 8 blocks of bytes through transpose_bytes, the edges a byte
 * at a time. */
static void write_tile(const Job *job, const uint8_t *flag, int64_t y, int64_t z0, int64_t depth) {
    const int64_t gx = job->nx - 1, gy = job->ny - 1, gz = job->nz - 1;
    const int64_t full_x = gx / 8 * 8, full_r = depth / 8 * 8;
    for (int64_t x = 0; x < gx; x += 8) {
        for (int64_t r = 0; r < depth; r += 8) {
            if (x < full_x && r < full_r) {
                uint64_t a[8];
                for (int i = 0; i < 8; ++i) memcpy(&a[i], flag + (r + i) * gx + x, 8);
                transpose_bytes(a);
                for (int j = 0; j < 8; ++j) {
                    const int64_t at = ((x + j) * gy + y) * gz + z0 + r;
                    if (job->allowed) {
                        uint64_t may;
                        memcpy(&may, job->allowed + at, 8);
                        a[j] &= may;
                    }
                    memcpy(job->occupied + at, &a[j], 8);
                }
                continue;
            }
            for (int64_t j = x; j < x + 8 && j < gx; ++j)
                for (int64_t i = r; i < r + 8 && i < depth; ++i) {
                    const int64_t at = (j * gy + y) * gz + z0 + i;
                    job->occupied[at] = flag[i * gx + j] & (job->allowed ? job->allowed[at] : 1);
                }
        }
    }
}

static void *work(void *argument) {
    Job *job = argument;
    const int64_t nz = job->nz, ny = job->ny, nx = job->nx;
    const int64_t gz = nz - 1, gy = ny - 1, gx = nx - 1;
    const float shift = job->shift;
    /* The largest float not above `above`: for a float m, m > above exactly where m > this. */
    float above = (float)job->above;
    if ((double)above > job->above) above = nextafterf(above, -INFINITY);
    float *face = malloc(sizeof(float) * (size_t)((Z_TILE + 1) * gx));
    float *cell = malloc(sizeof(float) * (size_t)(Z_TILE * gx));
    uint8_t *flag = malloc((size_t)(Z_TILE * gx));
    if (!face || !cell || !flag) {
        free(face), free(cell), free(flag);
        job->failed = 1;
        return NULL;
    }
    double vertex_excess = 0.0, cell_excess = 0.0;
    for (int64_t y = job->first_y; y < job->end_y; ++y) {
        const int last_y = y + 1 == gy; /* this share also counts the vertices at y + 1 */
        for (int64_t z0 = 0; z0 < gz; z0 += Z_TILE) {
            const int64_t depth = gz - z0 < Z_TILE ? gz - z0 : Z_TILE; /* cells in this tile */
            const int last_z = z0 + depth == gz;
            for (int64_t r = 0; r <= depth; ++r) {
                const float *low = job->sums + ((z0 + r) * ny + y) * nx, *high = low + nx;
                /* The rows are a plane apart: fetched PREFETCH_ROWS rows ahead, the hardware's
                 * prefetch being no help at each row's start (half the pass's time stalled there). */
                if (z0 + r + PREFETCH_ROWS < nz)
                    for (int64_t x = 0; x < 2 * nx; x += 16) __builtin_prefetch(low + PREFETCH_ROWS * ny * nx + x);
                float *out = face + r * gx;
                for (int64_t x = 0; x < gx; ++x)
                    out[x] = max_nan(max_nan(low[x], low[x + 1]), max_nan(high[x], high[x + 1]));
                if (r < depth || last_z) { /* each vertex once: the tile's last row is the next tile's first */
                    vertex_excess += row_excess(low, nx, shift);
                    if (last_y) vertex_excess += row_excess(high, nx, shift);
                }
            }
            for (int64_t r = 0; r < depth; ++r) {
                const float *a = face + r * gx, *b = a + gx;
                float *m = cell + r * gx;
                uint8_t *f = flag + r * gx;
                for (int64_t x = 0; x < gx; ++x) {
                    m[x] = max_nan(a[x], b[x]);
                    f[x] = m[x] > above;
                }
                cell_excess += row_excess(m, gx, shift);
            }
            write_tile(job, flag, y, z0, depth);
        }
    }
    job->vertex_excess = vertex_excess;
    job->cell_excess = cell_excess;
    free(face), free(cell), free(flag);
    return NULL;
}

/* Returns 0, or 1 where a thread found no scratch memory (then `occupied` is partly written).
 * excess[0]: over the vertices, excess[1]: over the cells. Needs nz, ny, nx >= 2. */
int cells_over(const float *sums, int64_t nz, int64_t ny, int64_t nx, double above, float shift,
               const uint8_t *allowed, uint8_t *occupied, double *excess, int64_t threads) {
    const int64_t gy = ny - 1;
    threads = clamp_threads(threads, gy);
    Job jobs[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        Job job = {sums, nz, ny, nx, above, shift, allowed, occupied,
                   gy * t / threads, gy * (t + 1) / threads, 0.0, 0.0, 0};
        jobs[t] = job;
    }
    run_all(work, jobs, sizeof(Job), threads);
    int failed = 0;
    excess[0] = excess[1] = 0.0;
    for (int64_t t = 0; t < threads; ++t) {
        failed |= jobs[t].failed;
        excess[0] += jobs[t].vertex_excess;
        excess[1] += jobs[t].cell_excess;
    }
    return failed;
}
