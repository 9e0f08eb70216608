#ifndef TRAIN_MARCH_H
#define TRAIN_MARCH_H
/* Included by a kernel's .c file (build.py hashes the headers with it), after grid_common.h and
 * <string.h>. */

#include "occupancy_bricks.h"

/* The training march of a grid field, in one pass a ray, shared by the kernels of the fields
 * whose density it reads (vm_grid.c, sparse_grid.c). The including file defines, before
 * including this:
 *   DensitySource                        what the density is read from;
 *   float density_at(const DensitySource *, const float x[3])  its pre-activation at x in [-1, 1];
 *   int density_readable(const DensitySource *)                 whether it can be read at all;
 *   void density_prefetch(const DensitySource *, const float x[3])  asks memory for what
 *                                                 density_at(x) will read, without waiting.
 *
 * The march: the fixed steps of nerf_backend/model_components/marcher.py's march_edges (first
 * step shortened by the ray's offset, cut at t_far), the occupancy grid's test of each step's
 * midpoint, the density there (scale * softplus(gain * density_at + shift)) and the
 * transmittance in front of each sample. Out: the flat indices (ray * steps + step) of the
 * samples in occupied cells that light still reaches (transmittance in front above
 * opaque_transmittance), sorted by ray, then along it, and each one's weight (without
 * gradients: which samples need a colour): what marcher.occupied_samples and
 * marcher.lit_samples find through tensors of every step of every ray. The field's pass with
 * gradients then runs on those. Where `record` is given, each lit sample's row of
 * RECORD_WIDTH floats there holds its interval's midpoint and length along the ray, the
 * density's pre-activation read there (density_at, before gain and shift) and the point in
 * [-1, 1]: what the field's pass would compute again (vm_grid.c's lit pass takes them). */
#define RECORD_WIDTH 6
typedef struct {
    float step;
    int64_t steps;
    int64_t cells[3];
    float box_min[3];
    float box_max[3];
    float density_scale, density_shift, density_gain;
    float opaque_transmittance;
    int64_t block_shift;        /* a block is 2^block_shift cells a side */
    int64_t blocks[3];
} TrainMarch;

typedef struct {
    const TrainMarch *s;
    const float *origins, *directions, *t_near, *t_far, *offset;
    const uint8_t *occupied, *blocks;  /* cells' bits (occupancy_bricks.h); blocks holding an occupied cell */
    const DensitySource *density;
    int64_t begin, end;         /* rays */
    int64_t *lit;               /* room for (end - begin) * steps indices */
    float *weight;              /* and their weights (transmittance in front times alpha) */
    float *record;              /* NULL, or room for RECORD_WIDTH floats a lit sample */
    int64_t found;
} TrainMarchWork;

/* Where the point t along a ray falls: its cell of the occupancy grid (`ijk`, kept inside) and
 * its place `x` in [-1, 1] of the box; returns whether it lies in the box. */
static inline int march_point(const TrainMarch *s, const float o[3], const float d[3], float t,
                              const float inverse_extent[3], int64_t ijk[3], float x[3]) {
    int inside = 1;
    for (int axis = 0; axis < 3; ++axis) {
        const float p = o[axis] + d[axis] * t;
        inside &= p >= s->box_min[axis] && p <= s->box_max[axis];
        const float unit = (p - s->box_min[axis]) * inverse_extent[axis];
        float cell = floorf(unit * (float)s->cells[axis]);
        if (!(cell >= 0.0f)) cell = 0.0f;
        if (cell > (float)(s->cells[axis] - 1)) cell = (float)(s->cells[axis] - 1);
        ijk[axis] = (int64_t)cell;
        x[axis] = unit * 2.0f - 1.0f;
    }
    return inside;
}

static inline int block_occupied(const TrainMarch *s, const uint8_t *blocks, const int64_t ijk[3]) {
    const int64_t sh = s->block_shift;
    return blocks[((ijk[0] >> sh) * s->blocks[1] + (ijk[1] >> sh)) * s->blocks[2] + (ijk[2] >> sh)];
}

/* A ray's occupied samples wait in fours: each one's density rows are asked of memory when it
 * is found, and the four are read and composited in order once found (up to where the ray turns
 * opaque). Read one at a time as found, each waited on its own misses: the branches of the
 * steps between two reads kept the processor from starting the next one's loads early (lego at
 * 800×800: 159 k steps a batch of 2 048 rays, 56 % in empty blocks, 32 % in empty cells of
 * occupied ones, 12 % read). */
#define WAITING 4

typedef struct {
    float t, delta, x[3];
    int64_t step;
} Waiting;

/* Reads the density of ray r's `count` waiting samples in order and writes each one's index,
 * weight and record; returns 1 where the ray turned opaque (the samples after it dropped). */
static inline int composite_waiting(TrainMarchWork *w, int64_t r, const Waiting *waiting, int count,
                                    float *transmittance, int64_t *found) {
    const TrainMarch *s = w->s;
    for (int j = 0; j < count; ++j) {
        const Waiting *sample = &waiting[j];
        const float summed = density_at(w->density, sample->x);
        const float v = s->density_gain * summed + s->density_shift;
        const float sigma = s->density_scale * (v > 20.0f ? v : log1pf(expf(v)));
        const float through = expf(-sigma * sample->delta);
        if (w->record) {
            float *row = w->record + *found * RECORD_WIDTH;
            row[0] = sample->t;
            row[1] = sample->delta;
            row[2] = summed;
            row[3] = sample->x[0];
            row[4] = sample->x[1];
            row[5] = sample->x[2];
        }
        w->weight[*found] = *transmittance * (1.0f - through);
        w->lit[(*found)++] = r * s->steps + sample->step;
        *transmittance *= through;
        if (!(*transmittance > s->opaque_transmittance)) return 1;  /* nothing behind is lit */
    }
    return 0;
}

static void *train_march_work(void *arg) {
    TrainMarchWork *w = (TrainMarchWork *)arg;
    const TrainMarch *s = w->s;
    int64_t found = 0;
    float inverse_extent[3];
    for (int a = 0; a < 3; ++a) inverse_extent[a] = 1.0f / (s->box_max[a] - s->box_min[a]);
    for (int64_t r = w->begin; r < w->end; ++r) {
        const float *o = w->origins + 3 * r, *d = w->directions + 3 * r;
        const float near = w->t_near[r], far = w->t_far[r], offset = w->offset[r];
        float transmittance = 1.0f;
        int64_t last_cell = -1;  /* steps are half a cell: most fall in the cell the last one did */
        int last_occupied = 0, count = 0;
        Waiting waiting[WAITING];
        for (int64_t i = 0; i < s->steps; ++i) {
            float a = (float)i - 1.0f + offset, b = (float)i + offset;  /* as march_edges */
            a = a > 0.0f ? a : 0.0f;
            b = b > 0.0f ? b : 0.0f;
            float lo = near + a * s->step, hi = near + b * s->step;
            lo = lo < far ? lo : far;
            hi = hi < far ? hi : far;
            /* The steps run to the longest ray's count; this ray ends here (lego: a ray that
             * crosses the box spans 163 of its 472 steps on average; each step past its far
             * bound was an empty turn of this loop). */
            if (!(lo < far)) break;
            const float delta = hi - lo;
            if (!(delta > 0.0f)) continue;
            const float t = 0.5f * (lo + hi);
            Waiting *next = &waiting[count];
            int64_t ijk[3];
            if (!march_point(s, o, d, t, inverse_extent, ijk, next->x) || !block_occupied(s, w->blocks, ijk)) continue;
            const int64_t cell = (ijk[0] * s->cells[1] + ijk[1]) * s->cells[2] + ijk[2];
            if (cell != last_cell) {
                last_cell = cell;
                last_occupied = brick_bit(w->occupied, ijk, s->cells);
            }
            if (!last_occupied) continue;
            next->t = t;
            next->delta = delta;
            next->step = i;
            density_prefetch(w->density, next->x);
            if (++count < WAITING) continue;
            count = 0;
            if (composite_waiting(w, r, waiting, WAITING, &transmittance, &found)) break;
        }
        composite_waiting(w, r, waiting, count, &transmittance, &found);
    }
    w->found = found;
    return NULL;
}

/* Returns the number of lit samples written to the front of `lit` (room for rays * steps), or
 * -1 for a density it cannot read; `occupied_count` receives the density reads made. `record`
 * (NULL, or room for rays * steps rows) receives each lit sample's row, as `weight` its weight. */
int64_t march_train(const TrainMarch *s, const float *origins, const float *directions, const float *t_near,
                    const float *t_far, const float *offset, int64_t rays, const uint8_t *occupied, const uint8_t *blocks,
                    const DensitySource *density, int64_t *lit, float *weight, float *record, int64_t *occupied_count,
                    int64_t threads) {
    if (!density_readable(density)) return -1;
    threads = clamp_threads(threads, (rays + 63) / 64);
    TrainMarchWork work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        TrainMarchWork w = {s, origins, directions, t_near, t_far, offset, occupied, blocks, density,
                            rays * t / threads, rays * (t + 1) / threads, lit + (rays * t / threads) * s->steps,
                            weight + (rays * t / threads) * s->steps,
                            record ? record + (rays * t / threads) * s->steps * RECORD_WIDTH : NULL, 0};
        work[t] = w;
    }
    run_all(train_march_work, work, sizeof work[0], threads);
    int64_t total = work[0].found;
    for (int64_t t = 1; t < threads; ++t) {
        memmove(lit + total, work[t].lit, (size_t)work[t].found * sizeof(int64_t));  /* after the ones before */
        memmove(weight + total, work[t].weight, (size_t)work[t].found * sizeof(float));
        if (record)
            memmove(record + total * RECORD_WIDTH, work[t].record,
                    (size_t)work[t].found * RECORD_WIDTH * sizeof(float));
        total += work[t].found;
    }
    *occupied_count = total;  /* each density read is a lit sample: the ray stops at the one it turns opaque at */
    return total;
}

#endif
