/* The training march's compositing of deferred colour in one compiled pass, forward and
 * backward (nerf_backend/model_components/compiled_composite.py; the PyTorch reference is
 * volume_rendering.composite_features_packed, which computes the same sums).
 *
 * Samples are packed per ray: ray r's are starts[r] .. starts[r + 1] - 1, in order along it.
 * A sample's weight is w_i = T_i (1 - exp(-σ_i δ_i)), its transmittance T_i = exp(-Σ_{j<i} σ_j δ_j)
 * with the optical depth summed in double (in float, a batch of opaque rays' sums lose a
 * translucent sample's own digits). Per ray, forward gives the opacity Σ w_i, the depth Σ w_i t_i,
 * and over the coloured samples (feature_row[i] >= 0: their row of `features`) the coloured
 * weight Σ w_i and the features composited, Σ w_i f_i.
 *
 * Backward: with g_i = dL/dw_i (from the four outputs' gradients),
 *   dL/dσ_i = δ_i (T_{i+1} g_i - Σ_{j>i} w_j g_j),   dL/df_i = w_i dL/d(Σ w f)_r,
 * the suffix sum taken in double, one backward pass a ray.
 *
 * Threads take runs of whole rays with about as many samples each, so no two write one row:
 * no atomics. Through PyTorch the same work was a dozen passes over memory and their autograd
 * nodes (bench-step's "composite" stage and part of "backward"). */

#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <string.h>

#include "grid_common.h"

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

static void *forward_work(void *arg) {
    const CompositeWork *w = (const CompositeWork *)arg;
    const Composite *c = w->c;
    const int64_t K = c->channels;
    for (int64_t r = w->first_ray; r < w->end_ray; ++r) {
        double depth_before = 0.0, opacity = 0.0, depth = 0.0, coloured = 0.0;
        float *acc = c->accumulated + r * K;
        memset(acc, 0, sizeof(float) * K);
        for (int64_t i = c->starts[r]; i < c->starts[r + 1]; ++i) {
            const double optical = (double)(c->density[i] * c->deltas[i]);
            const float weight = (float)exp(-depth_before) * -expm1f(-c->density[i] * c->deltas[i]);
            depth_before += optical;
            c->weights[i] = weight;
            opacity += weight;
            depth += (double)weight * c->t_mid[i];
            const int64_t row = c->feature_row[i];
            if (row >= 0) {
                coloured += weight;
                const float *f = c->features + row * K;
                for (int64_t k = 0; k < K; ++k) acc[k] += weight * f[k];
            }
        }
        c->opacity[r] = (float)opacity;
        c->depth[r] = (float)depth;
        c->coloured_weight[r] = (float)coloured;
    }
    return NULL;
}

static void *backward_work(void *arg) {
    const CompositeWork *w = (const CompositeWork *)arg;
    const Composite *c = w->c;
    const int64_t K = c->channels;
    for (int64_t r = w->first_ray; r < w->end_ray; ++r) {
        const int64_t begin = c->starts[r], end = c->starts[r + 1];
        const float *g_acc = c->grad_accumulated + r * K;
        /* T_{i+1}, each sample's transmittance behind it, kept in grad_density until the
         * reverse pass overwrites it with the gradient. */
        double depth_before = 0.0;
        for (int64_t i = begin; i < end; ++i) {
            depth_before += (double)(c->density[i] * c->deltas[i]);
            c->grad_density[i] = (float)exp(-depth_before);
        }
        double behind = 0.0;  /* Σ_{j>i} w_j g_j */
        for (int64_t i = end - 1; i >= begin; --i) {
            double g = (double)c->grad_opacity[r] + (double)c->grad_depth[r] * c->t_mid[i];
            const int64_t row = c->feature_row[i];
            if (row >= 0) {
                const float *f = c->features + row * K;
                float *g_f = c->grad_features + row * K;
                float dot = 0.0f;
                for (int64_t k = 0; k < K; ++k) {
                    dot += g_acc[k] * f[k];
                    g_f[k] = c->weights[i] * g_acc[k];
                }
                g += (double)c->grad_coloured_weight[r] + dot;
            }
            const double after = (double)c->grad_density[i];
            c->grad_density[i] = (float)(c->deltas[i] * (after * g - behind));
            behind += (double)c->weights[i] * g;
        }
    }
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
