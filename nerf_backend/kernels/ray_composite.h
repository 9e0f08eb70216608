#ifndef RAY_COMPOSITE_H
#define RAY_COMPOSITE_H
/* One ray's compositing of deferred colour, forward and backward, for the kernels that
 * composite samples packed per ray (packed_composite.c, lit_pass.h). Included after <math.h>,
 * <stdint.h> and <string.h>.
 *
 * The ray's samples are begin .. end - 1, in order along it; sample i's density sigma[i], and its
 * interval's length and midpoint at delta[i * stride] and t_mid[i * stride] (stride: the floats
 * between two samples' values, 1 in arrays of their own). A sample's weight is
 * w_i = T_i (1 - exp(-sigma_i delta_i)), its transmittance T_i = exp(-sum_{j<i} sigma_j delta_j)
 * with the optical depth summed in double (in float, a batch of opaque rays' sums lose a
 * translucent sample's own digits). Forward gives the opacity sum w_i, the depth sum w_i t_i, and
 * over the coloured samples (feature_row[i] >= 0: their row of `features`) the coloured weight
 * sum w_i and the features composited, sum w_i f_i.
 *
 * Backward: with g_i = dL/dw_i (from the four outputs' gradients),
 *   dL/dsigma_i = delta_i (T_{i+1} g_i - sum_{j>i} w_j g_j),   dL/df_i = w_i dL/d(sum w f),
 * the suffix sum taken in double, one backward pass. */

typedef struct {
    const float *sigma, *delta, *t_mid;
    int64_t stride;
    const int64_t *feature_row;  /* [N]: the sample's row of features, or -1 */
    const float *features;       /* [M, channels] */
    int64_t channels;
} RaySamples;

typedef struct {
    float opacity, depth, coloured_weight;
} RayTotals;

/* Fills weights[begin .. end) and accumulated [channels] (sum w_i f_i). */
static inline RayTotals composite_ray(const RaySamples *s, int64_t begin, int64_t end, float *weights,
                                      float *accumulated) {
    const int64_t K = s->channels;
    double depth_before = 0.0, opacity = 0.0, depth = 0.0, coloured = 0.0;
    memset(accumulated, 0, sizeof(float) * K);
    for (int64_t i = begin; i < end; ++i) {
        const float sigma = s->sigma[i], delta = s->delta[i * s->stride];
        const float weight = (float)exp(-depth_before) * -expm1f(-sigma * delta);
        depth_before += (double)(sigma * delta);
        weights[i] = weight;
        opacity += weight;
        depth += (double)weight * s->t_mid[i * s->stride];
        const int64_t row = s->feature_row[i];
        if (row < 0) continue;
        coloured += weight;
        const float *f = s->features + row * K;
        for (int64_t k = 0; k < K; ++k) accumulated[k] += weight * f[k];
    }
    RayTotals totals = {(float)opacity, (float)depth, (float)coloured};
    return totals;
}

/* dL/dsigma into grad_sigma[begin .. end) and dL/df into grad_features' coloured rows, from the
 * gradients of the ray's opacity, depth, coloured weight and accumulated [channels]. */
static inline void composite_ray_backward(const RaySamples *s, int64_t begin, int64_t end, const float *weights,
                                          float grad_opacity, float grad_depth, float grad_coloured_weight,
                                          const float *grad_accumulated, float *grad_sigma, float *grad_features) {
    const int64_t K = s->channels;
    /* T_{i+1}, each sample's transmittance behind it, kept in grad_sigma until the reverse pass
     * overwrites it with the gradient. */
    double depth_before = 0.0;
    for (int64_t i = begin; i < end; ++i) {
        depth_before += (double)(s->sigma[i] * s->delta[i * s->stride]);
        grad_sigma[i] = (float)exp(-depth_before);
    }
    double behind = 0.0;  /* sum_{j>i} w_j g_j */
    for (int64_t i = end - 1; i >= begin; --i) {
        double g = (double)grad_opacity + (double)grad_depth * s->t_mid[i * s->stride];
        const int64_t row = s->feature_row[i];
        if (row >= 0) {
            const float *f = s->features + row * K;
            float *g_f = grad_features + row * K;
            float dot = 0.0f;
            for (int64_t k = 0; k < K; ++k) {
                dot += grad_accumulated[k] * f[k];
                g_f[k] = weights[i] * grad_accumulated[k];
            }
            g += (double)grad_coloured_weight + dot;
        }
        const double after = (double)grad_sigma[i];
        grad_sigma[i] = (float)(s->delta[i * s->stride] * (after * g - behind));
        behind += (double)weights[i] * g;
    }
}

#endif
