/* The training march's compositing of deferred colour in one compiled pass, forward and
 * backward (nerf_backend/model_components/compiled_composite.py; the PyTorch reference is
 * volume_rendering.composite_features_packed, which computes the same sums).
 *
 * Samples are packed per ray: ray r's are starts[r] .. starts[r + 1] - 1, in order along it;
 * each ray is composited, forward and backward, by ray_composite.h (its notes give the maths).
 *
 * Threads take runs of whole rays with about as many samples each, so no two write one row:
 * no atomics. Through PyTorch the same work was a dozen passes over memory and their autograd
 * nodes (bench-step's "composite" stage and part of "backward"). */

#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <string.h>

#include "grid_common.h"
#include "ray_composite.h"

typedef struct {
    int64_t rays;
    const int64_t *starts;       /* [rays + 1] */
    const float *density;        /* [N] */
    const float *deltas;         /* [N] */
    const float *t_mid;          /* [N] */
    const int64_t *feature_row;  /* [N]: the sample's row of features, or -1 */
    const float *features;       /* [M, channels] */
    int64_t channels;
    float *weights;              /* [N] out (forward), in (backward) */
    float *opacity, *depth, *coloured_weight, *accumulated;  /* forward's outputs: [R], [R], [R], [R, channels] */
    const float *grad_opacity, *grad_depth, *grad_coloured_weight, *grad_accumulated;  /* backward's inputs */
    float *grad_density;         /* [N] */
    float *grad_features;        /* [M, channels] */
} Composite;

typedef struct {
    const Composite *c;
    int64_t first_ray, end_ray;
} CompositeWork;

static RaySamples samples_of(const Composite *c) {
    RaySamples s = {c->density, c->deltas, c->t_mid, 1, c->feature_row, c->features, c->channels};
    return s;
}

static void *forward_work(void *arg) {
    const CompositeWork *w = (const CompositeWork *)arg;
    const Composite *c = w->c;
    const RaySamples samples = samples_of(c);
    for (int64_t r = w->first_ray; r < w->end_ray; ++r) {
        const RayTotals totals = composite_ray(&samples, c->starts[r], c->starts[r + 1], c->weights,
                                               c->accumulated + r * c->channels);
        c->opacity[r] = totals.opacity;
        c->depth[r] = totals.depth;
        c->coloured_weight[r] = totals.coloured_weight;
    }
    return NULL;
}

static void *backward_work(void *arg) {
    const CompositeWork *w = (const CompositeWork *)arg;
    const Composite *c = w->c;
    const RaySamples samples = samples_of(c);
    for (int64_t r = w->first_ray; r < w->end_ray; ++r)
        composite_ray_backward(&samples, c->starts[r], c->starts[r + 1], c->weights, c->grad_opacity[r],
                               c->grad_depth[r], c->grad_coloured_weight[r], c->grad_accumulated + r * c->channels,
                               c->grad_density, c->grad_features);
    return NULL;
}

/* Split the rays into `threads` runs of about N / threads samples each. */
static int64_t split_rays(const Composite *c, CompositeWork *work, int64_t threads) {
    const int64_t samples = c->starts[c->rays];
    threads = clamp_threads(threads, (samples + 2047) / 2048);
    int64_t ray = 0;
    for (int64_t t = 0; t < threads; ++t) {
        const int64_t until = samples * (t + 1) / threads;
        work[t].c = c;
        work[t].first_ray = ray;
        while (ray < c->rays && (t == threads - 1 || c->starts[ray + 1] <= until)) ++ray;
        work[t].end_ray = ray;
    }
    return threads;
}

int composite_forward(const Composite *c, int64_t threads) {
    CompositeWork work[MAX_THREADS];
    run_all(forward_work, work, sizeof work[0], split_rays(c, work, threads));
    return 0;
}

int composite_backward(const Composite *c, int64_t threads) {
    CompositeWork work[MAX_THREADS];
    run_all(backward_work, work, sizeof work[0], split_rays(c, work, threads));
    return 0;
}
