#ifndef LIT_PASS_H
#define LIT_PASS_H

/* The grid field's training pass over the training march's lit samples with deferred colour,
 * forward and backward, in one compiled call each (nerf_backend/field_components/
 * compiled_lit_pass.py). Included by vm_grid.c after train_march.h: it reads the appearance
 * grid with forward_sample and adds into both grids' rows with backward_sample's arithmetic.
 *
 * What PyTorch did between the march and the colour network, each a pass over the samples and
 * an autograd node: the points and intervals from the lit indices, which samples get a colour
 * (marcher.colour_worthy), the density grid read again and its softplus, the appearance grid
 * read at the coloured samples, the compositing (packed_composite.c), and backward the same in
 * reverse. Here the march's record (train_march.h: each lit sample's midpoint, length, density
 * pre-activation and point) stands for the first three; the density is not read again.
 *
 * Forward, per ray (rays packed: ray r's samples are starts[r] .. starts[r + 1] - 1):
 *   sigma_i = scale * softplus(s_i + shift), w_i = T_i (1 - exp(-sigma_i delta_i)),
 *   opacity = sum w_i, depth = sum w_i t_i, and over the coloured samples (the march's weight at
 *   least min(1e-4, a hundredth of the ray's heaviest)) coloured weight = sum w_i and
 *   accumulated = sum w_i f_i, f_i the appearance grid's features at the sample (each ray
 *   composited by ray_composite.h).
 * Backward: ray_composite.h's dL/dsigma_i and dL/df_i = w_i dL/daccumulated, then
 *   dL/ds_i = dL/dsigma_i * scale * sigmoid(s_i + shift), added into every channel of the density
 *   grid's rows the sample read (the density is the sum of its features), and dL/df_i into the
 *   appearance grid's; the rows touched are marked for the sparse optimiser.
 * Threads: forward and the compositing's backward take runs of whole rays; the grids' backward
 * gives each thread whole components, as vm_backward does (no two threads add into one row). */

#include "ray_composite.h"

typedef struct {
    int64_t rays, samples, steps;
    const int64_t *lit;          /* [N]: ray * steps + step, sorted (march_train's order) */
    const float *march_weight;   /* [N]: the march's weights, without gradients */
    const float *record;         /* [N, RECORD_WIDTH]: train_march.h's rows */
    float density_scale, density_shift;
    float coloured_weight_floor, coloured_weight_share;  /* marcher.TRAIN_COLOURED_WEIGHT, TRAIN_RELATIVE_WEIGHT */
    Component density[3];        /* backward: plane_grad, line_grad, marks */
    Component appearance[3];     /* forward: plane, line; backward: and the grads and marks */
    int64_t width;               /* the appearance features a sample: the sum of its components' channels */
    /* forward's outputs, kept for backward */
    int64_t *starts;             /* [R + 1] */
    int64_t *feature_row;        /* [N]: the sample's row of features, or -1 */
    float *coloured_points;      /* [N, 3] room: the coloured samples' points, in feature row order */
    float *features;             /* [N, width] room */
    float *weights;              /* [N] */
    float *sigma;                /* [N]: each sample's density */
    float *opacity, *depth, *coloured_weight, *accumulated;  /* [R], [R], [R], [R, width] */
    int64_t coloured;            /* the coloured samples */
    /* backward's inputs and scratch */
    const float *grad_opacity, *grad_depth, *grad_coloured_weight, *grad_accumulated;
    float *grad_sum;             /* [N]: dL/ds_i */
    float *grad_features;        /* [N, width] room */
} LitPass;

typedef struct {
    LitPass *p;
    int64_t first_ray, end_ray;
} LitRays;

static inline float softplus_of(float v) { return v > 20.0f ? v : log1pf(expf(v)); }

static RaySamples lit_samples_of(const LitPass *p) {
    RaySamples s = {p->sigma, p->record + 1, p->record, RECORD_WIDTH, p->feature_row, p->features, p->width};
    return s;
}

/* The appearance rows of the coloured sample this many samples on, asked of memory before it
 * is reached: the forward waited on them (lego's ten-minute model, two builds chosen at random a
 * step, 600 steps: the call 2.62 -> 1.72 ms, 0.655x, twice; 4 and 16 ahead within 1 % of 8). */
#define LIT_FORWARD_AHEAD 8

static void *lit_forward_work(void *arg) {
    const LitRays *w = (const LitRays *)arg;
    LitPass *p = w->p;
    const RaySamples samples = lit_samples_of(p);
    const int64_t last = p->starts[w->end_ray];
    for (int64_t r = w->first_ray; r < w->end_ray; ++r) {
        for (int64_t i = p->starts[r]; i < p->starts[r + 1]; ++i) {
            const int64_t ahead = i + LIT_FORWARD_AHEAD;
            if (LIT_FORWARD_AHEAD && ahead < last && p->feature_row[ahead] >= 0)
                for (int c = 0; c < 3; ++c) prefetch_rows(&p->appearance[c], p->record + ahead * RECORD_WIDTH + 3, 0);
            const float *rec = p->record + i * RECORD_WIDTH;
            p->sigma[i] = p->density_scale * softplus_of(rec[2] + p->density_shift);
            const int64_t row = p->feature_row[i];
            if (row < 0) continue;
            memcpy(p->coloured_points + 3 * row, rec + 3, 3 * sizeof(float));
            int64_t column = 0;
            for (int c = 0; c < 3; ++c) {
                forward_sample(&p->appearance[c], rec + 3, p->features + row * p->width + column);
                column += p->appearance[c].channels;
            }
        }
        const RayTotals totals = composite_ray(&samples, p->starts[r], p->starts[r + 1], p->weights,
                                               p->accumulated + r * p->width);
        p->opacity[r] = totals.opacity;
        p->depth[r] = totals.depth;
        p->coloured_weight[r] = totals.coloured_weight;
    }
    return NULL;
}

static void *lit_composite_backward_work(void *arg) {
    const LitRays *w = (const LitRays *)arg;
    LitPass *p = w->p;
    const RaySamples samples = lit_samples_of(p);
    for (int64_t r = w->first_ray; r < w->end_ray; ++r) {
        const int64_t begin = p->starts[r], end = p->starts[r + 1];
        composite_ray_backward(&samples, begin, end, p->weights, p->grad_opacity[r], p->grad_depth[r],
                               p->grad_coloured_weight[r], p->grad_accumulated + r * p->width, p->grad_sum,
                               p->grad_features);
        for (int64_t i = begin; i < end; ++i) {  /* dL/dsigma to dL/ds: softplus' is the sigmoid */
            const float v = p->record[i * RECORD_WIDTH + 2] + p->density_shift;
            p->grad_sum[i] *= p->density_scale / (1.0f + expf(-v));
        }
    }
    return NULL;
}

typedef struct {
    const LitPass *p;
    int32_t owned[6];            /* 0-2: the density's components, 3-5: the appearance's */
    int32_t owned_count;
} LitGrids;

/* The backward adds into rows (values read, gradients read and written) and waits on them more
 * than the forward, which reads: asked 12 samples ahead, not vm_grid.c's 6 (lego's ten-minute
 * model continued for 4 000 steps, the builds chosen at random a step: 0.964× and 0.970× the
 * backward's time in two runs, the forward's within 1 %; 9 and 16 ahead 0.98×). Less than
 * vm_grid.c's CORNER_RING. */
#define LIT_BACKWARD_AHEAD 12
typedef char lit_backward_ahead_within_the_ring[LIT_BACKWARD_AHEAD < CORNER_RING ? 1 : -1];

static void *lit_grids_backward_work(void *arg) {
    const LitGrids *w = (const LitGrids *)arg;
    const LitPass *p = w->p;
    for (int32_t j = 0; j < w->owned_count; ++j) {
        const int32_t index = w->owned[j];
        if (index < 3) {
            backward_samples(&p->density[index], p->record + 3, RECORD_WIDTH, p->grad_sum, 1, p->samples, 1,
                             LIT_BACKWARD_AHEAD);
        } else {
            int64_t column = 0;
            for (int c = 0; c < index - 3; ++c) column += p->appearance[c].channels;
            backward_samples(&p->appearance[index - 3], p->coloured_points, 3, p->grad_features + column, p->width,
                             p->coloured, 0, LIT_BACKWARD_AHEAD);
        }
    }
    return NULL;
}

/* Runs of whole rays with about samples / threads samples each. */
static int64_t lit_split_rays(LitPass *p, LitRays *work, int64_t threads) {
    threads = clamp_threads(threads, (p->samples + 2047) / 2048);
    int64_t ray = 0;
    for (int64_t t = 0; t < threads; ++t) {
        const int64_t until = p->samples * (t + 1) / threads;
        work[t].p = p;
        work[t].first_ray = ray;
        while (ray < p->rays && (t == threads - 1 || p->starts[ray + 1] <= until)) ++ray;
        work[t].end_ray = ray;
    }
    return threads;
}

static int lit_components_readable(const Component *components) {
    for (int c = 0; c < 3; ++c)
        if (components[c].channels < 1 || components[c].channels % BLOCK != 0) return 0;
    return 1;
}

/* Forward: fills starts, feature_row, coloured_points, features, weights and the four outputs;
 * returns the coloured samples' count, or -1 for grids it cannot read. */
int64_t lit_pass_forward(LitPass *p, int64_t threads) {
    if (!lit_components_readable(p->appearance) || !lit_components_readable(p->density)) return -1;
    /* The rays' runs, and which samples get a colour (marcher.colour_worthy): a pass over the
     * samples, in order, so the coloured ones' rows follow the samples'. */
    int64_t coloured = 0;
    int64_t i = 0;
    for (int64_t r = 0; r < p->rays; ++r) {
        p->starts[r] = i;
        int64_t end = i;
        float heaviest = 0.0f;
        while (end < p->samples && p->lit[end] / p->steps == r) {
            if (p->march_weight[end] > heaviest) heaviest = p->march_weight[end];
            ++end;
        }
        float threshold = heaviest * p->coloured_weight_share;
        if (threshold > p->coloured_weight_floor) threshold = p->coloured_weight_floor;
        for (; i < end; ++i) p->feature_row[i] = p->march_weight[i] >= threshold ? coloured++ : -1;
    }
    p->starts[p->rays] = i;
    if (i != p->samples) return -2;  /* not sorted by ray, or a ray out of range */
    p->coloured = coloured;
    LitRays work[MAX_THREADS];
    run_all(lit_forward_work, work, sizeof work[0], lit_split_rays(p, work, threads));
    return coloured;
}

/* Backward: adds into both grids' gradient rows (and marks them) from the outputs' gradients. */
int lit_pass_backward(LitPass *p, int64_t threads) {
    LitRays rays[MAX_THREADS];
    run_all(lit_composite_backward_work, rays, sizeof rays[0], lit_split_rays(p, rays, threads));
    /* Whole components to threads, the largest work first to the least loaded. */
    threads = clamp_threads(threads, 6);
    LitGrids work[MAX_THREADS];
    int64_t load[MAX_THREADS] = {0};
    int taken[6] = {0};
    for (int64_t t = 0; t < threads; ++t) {
        work[t].p = p;
        work[t].owned_count = 0;
    }
    for (int round = 0; round < 6; ++round) {
        int largest = -1;
        int64_t largest_load = -1;
        for (int c = 0; c < 6; ++c) {
            const int64_t cost = c < 3 ? p->density[c].channels * p->samples
                                       : p->appearance[c - 3].channels * p->coloured;
            if (!taken[c] && cost > largest_load) {
                largest = c;
                largest_load = cost;
            }
        }
        taken[largest] = 1;
        int64_t least = 0;
        for (int64_t t = 1; t < threads; ++t)
            if (load[t] < load[least]) least = t;
        work[least].owned[work[least].owned_count++] = largest;
        load[least] += largest_load;
    }
    run_all(lit_grids_backward_work, work, sizeof work[0], threads);
    return 0;
}

#endif
