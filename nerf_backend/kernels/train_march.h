#ifndef TRAIN_MARCH_H
#define TRAIN_MARCH_H
/* Included by a kernel's .c file (build.py hashes the headers with it), after grid_common.h and
 * <string.h>. */

#include "occupancy_bricks.h"
#include "step_lanes.h"

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

/* A ray's steps are looked up 8 at a time (step_lanes.h), as the render march's are: their
 * bounds, midpoints, whether they lie in the box, their cells, blocks and bits. One at a time,
 * each step was a chain of scalar operations and an unpredictable branch, and 88 % of lego's
 * steps hold nothing. */
typedef struct {
    float near, far, offset, step;
    float origin[3], direction[3], box_min[3], box_max[3], inverse_extent[3], cell_count[3], last_cell[3];
    int32_t bricks_y, bricks_z, block_shift, blocks_y, blocks_z;
} TrainRay;

/* The steps first .. first + 7 of a ray: bit j set where step first + j is occupied (its length
 * above 0, its midpoint in the box, its block and its cell occupied), with its midpoint, length
 * and point in [-1, 1] in `found` (lane j); *ended set where the ray ends among them (the steps
 * from there on not taken). */
typedef struct {
    float t[STEP_LANES], delta[STEP_LANES], x[3][STEP_LANES];
} StepLanes;

static inline uint32_t occupied_train_steps(const TrainRay *f, const uint8_t *occupied, const uint8_t *blocks,
                                            int64_t first, int64_t steps, StepLanes *found, int *ended) {
    const step_lanes_i lane = {0, 1, 2, 3, 4, 5, 6, 7};
    const step_lanes_f i = __builtin_convertvector((int32_t)first + lane, step_lanes_f);
    const step_lanes_f zero = step_splat(0.0f), far = step_splat(f->far);
    step_lanes_f a = i - 1.0f + f->offset, b = i + f->offset;  /* as march_edges */
    a = step_select(a > 0.0f, a, zero);
    b = step_select(b > 0.0f, b, zero);
    step_lanes_f lo = f->near + a * f->step, hi = f->near + b * f->step;
    lo = step_select(lo < far, lo, far);
    hi = step_select(hi < far, hi, far);
    const step_lanes_f delta = hi - lo;
    const step_lanes_f t = 0.5f * (lo + hi);
    step_lanes_i keep = delta > 0.0f;
    step_lanes_i cell[3];
    for (int axis = 0; axis < 3; ++axis) {
        const step_lanes_f p = f->origin[axis] + f->direction[axis] * t;
        keep &= (p >= f->box_min[axis]) & (p <= f->box_max[axis]);
        const step_lanes_f unit = (p - f->box_min[axis]) * f->inverse_extent[axis];
        const step_lanes_f units = unit * f->cell_count[axis];
        const step_lanes_f last = step_splat(f->last_cell[axis]);
        /* floor, then into the grid (NaN to 0), as one step at a time did: for units >= 0 floor is the cast */
        const step_lanes_f clamped = step_select(units >= 0.0f, step_select(units > last, last, units), zero);
        cell[axis] = __builtin_convertvector(clamped, step_lanes_i);
        const step_lanes_f x = unit * 2.0f - 1.0f;
        memcpy(found->x[axis], &x, sizeof x);
    }
    memcpy(found->t, &t, sizeof t);
    memcpy(found->delta, &delta, sizeof delta);
    const step_lanes_i shift = {f->block_shift, f->block_shift, f->block_shift, f->block_shift,
                                f->block_shift, f->block_shift, f->block_shift, f->block_shift};
    const step_lanes_i block = ((cell[0] >> shift) * f->blocks_y + (cell[1] >> shift)) * f->blocks_z + (cell[2] >> shift);
    const step_lanes_i byte = ((((cell[0] >> 3) * f->bricks_y + (cell[1] >> 3)) * f->bricks_z + (cell[2] >> 3)) << 6)
                              + ((cell[0] & 7) << 3) + (cell[1] & 7);
    const step_lanes_i bit = cell[2] & 7;
    const step_lanes_i ends = lo < far;
    const int64_t left = steps - first;
    const int lanes = left < STEP_LANES ? (int)left : STEP_LANES;
    uint32_t occupied_lanes = 0;
    for (int j = 0; j < lanes; ++j) {
        /* The steps run to the longest ray's count; this ray ends here (lego: a ray that
         * crosses the box spans 163 of its 472 steps on average). */
        if (!ends[j]) {
            *ended = 1;
            break;
        }
        if (keep[j] && blocks[block[j]]) occupied_lanes |= (uint32_t)((occupied[byte[j]] >> bit[j]) & 1) << j;
    }
#if defined(__AVX__)
    /* The upper halves cleared before the march calls expf and log1pf (march_render.c's
     * occupied_steps says why). */
    __builtin_ia32_vzeroupper();
#endif
    return occupied_lanes;
}

static void *train_march_work(void *arg) {
    TrainMarchWork *w = (TrainMarchWork *)arg;
    const TrainMarch *s = w->s;
    int64_t found = 0;
    TrainRay frame;
    frame.step = s->step;
    for (int axis = 0; axis < 3; ++axis) {
        frame.box_min[axis] = s->box_min[axis];
        frame.box_max[axis] = s->box_max[axis];
        frame.inverse_extent[axis] = 1.0f / (s->box_max[axis] - s->box_min[axis]);
        frame.cell_count[axis] = (float)s->cells[axis];
        frame.last_cell[axis] = (float)(s->cells[axis] - 1);
    }
    frame.bricks_y = (int32_t)((s->cells[1] + 7) >> 3);
    frame.bricks_z = (int32_t)((s->cells[2] + 7) >> 3);
    frame.block_shift = (int32_t)s->block_shift;
    frame.blocks_y = (int32_t)s->blocks[1];
    frame.blocks_z = (int32_t)s->blocks[2];
    for (int64_t r = w->begin; r < w->end; ++r) {
        for (int axis = 0; axis < 3; ++axis) {
            frame.origin[axis] = w->origins[3 * r + axis];
            frame.direction[axis] = w->directions[3 * r + axis];
        }
        frame.near = w->t_near[r];
        frame.far = w->t_far[r];
        frame.offset = w->offset[r];
        float transmittance = 1.0f;
        int count = 0, ended = 0, opaque = 0;
        Waiting waiting[WAITING];
        StepLanes lanes;
        for (int64_t first = 0; first < s->steps && !ended && !opaque; first += STEP_LANES) {
            for (uint32_t occupied = occupied_train_steps(&frame, w->occupied, w->blocks, first, s->steps, &lanes, &ended);
                 occupied; occupied &= occupied - 1) {
                const int j = __builtin_ctz(occupied);
                Waiting *next = &waiting[count];
                next->t = lanes.t[j];
                next->delta = lanes.delta[j];
                next->step = first + j;
                for (int axis = 0; axis < 3; ++axis) next->x[axis] = lanes.x[axis][j];
                density_prefetch(w->density, next->x);
                if (++count < WAITING) continue;
                count = 0;
                if ((opaque = composite_waiting(w, r, waiting, WAITING, &transmittance, &found))) break;
            }
        }
        if (!opaque) composite_waiting(w, r, waiting, count, &transmittance, &found);
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
