#ifndef COLOUR_NETWORK_H
#define COLOUR_NETWORK_H
/* Included by vm_grid.c (after Component, forward_sample and prefetch_rows): inference's colour
 * of packed samples in one compiled pass, the grid field's appearance grid read and its colour
 * network run together (nerf_backend/field_components/compiled_colour.py).
 *
 * The network is GridAppearance.ray_colour's: hidden = relu(per_ray[ray] + features · W1),
 * hidden = relu(b2 + hidden · W2), colour = sigmoid(b3 + hidden · W3), where per_ray holds the
 * viewing direction's share of the first layer (and its bias), computed once a ray, and W1 has
 * the appearance basis folded in. In float32 (the wide layers aside, below), so it matches
 * PyTorch's float32 sums to rounding.
 *
 * Samples go through in tiles of TILE: each weight row is loaded once a tile and multiplied
 * into every sample of it, the tile's sums held in vector registers (a sample at a time, every
 * row was loaded for one sample's few multiply-adds, and the pass ran slower than oneDNN's
 * bfloat16 products with PyTorch's passes around them).
 *
 * On a CPU with AVX512-BF16 the two wide layers multiply in bfloat16 (their inputs and weights
 * rounded to 8 bits of mantissa, the sums in float32: what oneDNN's bfloat16 products do), two
 * products an instruction; elsewhere everything is float32. colour_precision() says which. */

/* Multiply-adds as single fused instructions (GCC's -std=c99 keeps them apart; Clang fuses
 * them by default): the layers are nothing else. */
#pragma GCC optimize("fp-contract=fast")

#define HIDDEN 64                   /* the network's width: other widths colour through PyTorch */
/* A vector is the widest the CPU has: 16 floats with AVX-512, 8 with AVX2, 4 elsewhere (SSE,
 * NEON). A vector type wider than the CPU's registers is no native type to GCC: with 16-float
 * vectors on an AVX2 CPU every vector went through general registers and the stack, and the
 * pass took 1.85 µs a sample of lego's thirty-minute model, 0.72 µs with 8-float vectors.
 * Samples a tile: their sums (TILE × HIDDEN_VECTORS vectors) and one row of weights fit the
 * vector registers (32 with AVX-512); with 16 registers the weights are read from memory by
 * the multiply-adds themselves (on AVX2, tiles of 1 to 4 samples measured 720-865 ns a sample:
 * 2 kept). */
#if defined(__AVX512F__)
#define LANES 16
#define TILE 6
#elif defined(__AVX__)
#define LANES 8
#define TILE 2
#else
#define LANES 4
#define TILE 2
#endif
#define HIDDEN_VECTORS (HIDDEN / LANES)
#define MAX_FEATURES (MAX_TASKS * 64)

#if defined(__AVX512F__) && defined(__AVX512BF16__)
#include <immintrin.h>
#define COLOUR_BF16 1
#else
#define COLOUR_BF16 0
#endif
/* Features and hidden values are rounded to bfloat16 16 at a time: the layers' inputs, padded. */
#define PADDED(n) (((n) + 15) / 16 * 16)

typedef float wide __attribute__((vector_size(LANES * sizeof(float))));
typedef int32_t wide_mask __attribute__((vector_size(LANES * sizeof(int32_t))));

static inline wide load_wide(const float *p) { wide v; memcpy(&v, p, sizeof v); return v; }
static inline void store_wide(float *p, wide v) { memcpy(p, &v, sizeof v); }
static inline wide splat_wide(float x) {  /* a scalar operand is broadcast (lane stores became masked loads) */
    /* x + -0 is x for every x, so the addition folds away (x + +0 is not, for x = -0: GCC had
     * kept a scalar addition before each broadcast). */
    const wide negative_zero = -(wide){0.0f};  /* -0 in every lane */
    return negative_zero + x;
}
static inline wide relu_wide(wide v) {
    return (wide)((wide_mask)v & (v > splat_wide(0.0f)));  /* C's vectors have no lane-wise ?: */
}

typedef struct {
    Component grid[3];      /* the appearance grid's components (their `features` unused) */
    const float *per_ray;   /* [rays, HIDDEN] */
    const float *w1;        /* [features, HIDDEN]: row k multiplies feature k */
    const float *w2;        /* [HIDDEN, HIDDEN] */
    const float *b2;        /* [HIDDEN] */
    const float *w3;        /* [3, HIDDEN]: row c gives colour channel c */
    const float *b3;        /* [3] */
    float box_min[3];
    float scale[3];         /* normalised x = (x - box_min) * scale - 1 */
    int32_t features;       /* the grid's features: 3 × its channels */
    int32_t hidden;         /* HIDDEN, checked */
    /* composite_samples only: each component's plane and line rows in IEEE half precision (the
     * same layouts as grid[i].plane and .line), or NULL to read the float32 tables. */
    const uint16_t *half_plane[3];
    const uint16_t *half_line[3];
} ColourNetwork;

/* Sums of one layer for a tile: sums[t] += Σ_k inputs[t][k] · weights[k] (rows of HIDDEN). */
static inline void layer_tile(wide sums[TILE][HIDDEN_VECTORS], const float *inputs, int64_t input_stride,
                              const float *weights, int32_t count) {
    for (int32_t k = 0; k < count; ++k) {
        wide row[HIDDEN_VECTORS];
        for (int j = 0; j < HIDDEN_VECTORS; ++j) row[j] = load_wide(weights + (int64_t)k * HIDDEN + j * LANES);
        for (int t = 0; t < TILE; ++t) {
            const wide x = splat_wide(inputs[t * input_stride + k]);
            for (int j = 0; j < HIDDEN_VECTORS; ++j) sums[t][j] += x * row[j];
        }
    }
}

static inline float sigmoid(float x) { return 1.0f / (1.0f + expf(-x)); }

/* Colour channel c from the last hidden layer h (after its ReLU): sigmoid(bias + h · w3[c]). */
static inline float colour_channel(const wide h[HIDDEN_VECTORS], const float *w3, float bias, int c) {
    wide dot = h[0] * load_wide(w3 + c * HIDDEN);
    for (int j = 1; j < HIDDEN_VECTORS; ++j) dot += h[j] * load_wide(w3 + c * HIDDEN + j * LANES);
    float sum = bias;
    for (int i = 0; i < LANES; ++i) sum += dot[i];
    return sigmoid(sum);
}

#if COLOUR_BF16
/* A layer's weights for the bfloat16 products: for each pair of inputs (2k, 2k + 1) and each
 * block of 16 outputs, the 16 outputs' two weights side by side (32 bfloat16, one vector), what
 * vdpbf16ps multiplies a broadcast pair of inputs by. Inputs past `count` weigh 0. */
static inline uint16_t to_bf16(float f) {  /* round to nearest even (the weights are finite) */
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return (uint16_t)((u + 0x7FFFu + ((u >> 16) & 1u)) >> 16);
}

static void pack_bf16(uint16_t *packed, const float *weights, int32_t count) {
    for (int32_t pair = 0; pair < PADDED(count) / 2; ++pair)
        for (int j = 0; j < HIDDEN_VECTORS; ++j)
            for (int o = 0; o < LANES; ++o)
                for (int r = 0; r < 2; ++r) {
                    const int32_t k = 2 * pair + r;
                    packed[((int64_t)pair * HIDDEN_VECTORS + j) * 2 * LANES + 2 * o + r] =
                        k < count ? to_bf16(weights[(int64_t)k * HIDDEN + j * LANES + o]) : 0;
                }
}

/* inputs [TILE][stride] floats (zero past `count` up to PADDED(count)) rounded to bfloat16,
 * pairs [TILE][stride / 2] of them. */
static inline void round_tile(uint32_t *pairs, const float *inputs, int64_t stride, int32_t count) {
    for (int t = 0; t < TILE; ++t)
        for (int32_t k = 0; k < PADDED(count); k += 16) {
            const __m256bh rounded = _mm512_cvtneps_pbh(_mm512_loadu_ps(inputs + t * stride + k));
            memcpy(pairs + t * (stride / 2) + k / 2, &rounded, sizeof rounded);
        }
}

static inline void layer_tile_bf16(wide sums[TILE][HIDDEN_VECTORS], const uint32_t *pairs, int64_t stride,
                                   const uint16_t *packed, int32_t count) {
    for (int32_t pair = 0; pair < PADDED(count) / 2; ++pair) {
        __m512bh row[HIDDEN_VECTORS];
        for (int j = 0; j < HIDDEN_VECTORS; ++j)
            row[j] = (__m512bh)_mm512_loadu_si512(packed + ((int64_t)pair * HIDDEN_VECTORS + j) * 2 * LANES);
        for (int t = 0; t < TILE; ++t) {
            const __m512bh x = (__m512bh)_mm512_set1_epi32((int)pairs[t * (stride / 2) + pair]);
            for (int j = 0; j < HIDDEN_VECTORS; ++j)
                sums[t][j] = (wide)_mm512_dpbf16_ps((__m512)sums[t][j], x, row[j]);
        }
    }
}
#endif

typedef struct {
    const ColourNetwork *net;
    const uint16_t *w1_bf16, *w2_bf16;  /* pack_bf16's, where COLOUR_BF16 */
    const float *x;
    const int64_t *ray;
    float *rgb;
    int64_t begin, end;
} ColourWork;

static void *colour_work(void *arg) {
    const ColourWork *w = (const ColourWork *)arg;
    const ColourNetwork *net = w->net;
    const int32_t F = net->features;
    float features[TILE][MAX_FEATURES];
    float hidden[TILE][HIDDEN];
    float normalised[TILE][3];
    memset(features, 0, sizeof features);  /* the padding past F stays 0 */
#if COLOUR_BF16
    uint32_t pairs[TILE][MAX_FEATURES / 2];
#endif
    for (int64_t first = w->begin; first < w->end; first += TILE) {
        const int64_t count = w->end - first < TILE ? w->end - first : TILE;
        int64_t ray[TILE];
        /* A short last tile repeats its last sample (computed, not written). */
        for (int t = 0; t < TILE; ++t) {
            const int64_t p = first + (t < count ? t : count - 1);
            ray[t] = w->ray[p];
            for (int a = 0; a < 3; ++a) normalised[t][a] = (w->x[3 * p + a] - net->box_min[a]) * net->scale[a] - 1.0f;
        }
        if (first + TILE < w->end)  /* the next tile's first sample's rows, asked of memory now */
            for (int i = 0; i < 3; ++i) {
                float ahead[3];
                for (int a = 0; a < 3; ++a)
                    ahead[a] = (w->x[3 * (first + TILE) + a] - net->box_min[a]) * net->scale[a] - 1.0f;
                prefetch_rows(&net->grid[i], ahead, 0);
            }
        for (int t = 0; t < TILE; ++t) {
            int32_t column = 0;
            for (int i = 0; i < 3; ++i) {
                forward_sample(&net->grid[i], normalised[t], features[t] + column);
                column += net->grid[i].channels;
            }
        }
        wide sums[TILE][HIDDEN_VECTORS];
        for (int t = 0; t < TILE; ++t)
            for (int j = 0; j < HIDDEN_VECTORS; ++j) sums[t][j] = load_wide(net->per_ray + ray[t] * HIDDEN + j * LANES);
#if COLOUR_BF16
        round_tile(&pairs[0][0], &features[0][0], MAX_FEATURES, F);
        layer_tile_bf16(sums, &pairs[0][0], MAX_FEATURES, w->w1_bf16, F);
#else
        layer_tile(sums, &features[0][0], MAX_FEATURES, net->w1, F);
#endif
        for (int t = 0; t < TILE; ++t)
            for (int j = 0; j < HIDDEN_VECTORS; ++j) store_wide(hidden[t] + j * LANES, relu_wide(sums[t][j]));
        for (int t = 0; t < TILE; ++t)
            for (int j = 0; j < HIDDEN_VECTORS; ++j) sums[t][j] = load_wide(net->b2 + j * LANES);
#if COLOUR_BF16
        round_tile(&pairs[0][0], &hidden[0][0], HIDDEN, HIDDEN);
        layer_tile_bf16(sums, &pairs[0][0], HIDDEN, w->w2_bf16, HIDDEN);
#else
        layer_tile(sums, &hidden[0][0], HIDDEN, net->w2, HIDDEN);
#endif
        for (int t = 0; t < count; ++t) {
            wide h[HIDDEN_VECTORS];
            for (int j = 0; j < HIDDEN_VECTORS; ++j) h[j] = relu_wide(sums[t][j]);
            for (int c = 0; c < 3; ++c) w->rgb[3 * (first + t) + c] = colour_channel(h, net->w3, net->b3[c], c);
        }
    }
    return NULL;
}

/* rgb [points, 3] = the colour of each sample x [points, 3] (world space) of ray ray[p], on
 * `threads` threads over the samples. 0, or below 0 where the network is not one this pass
 * takes (the caller colours through PyTorch). */
int colour_samples(const ColourNetwork *net, const float *x, const int64_t *ray, int64_t points, float *rgb,
                   int64_t threads) {
    if (net->hidden != HIDDEN || net->features < 1 || net->features > MAX_FEATURES) return -1;
    int32_t features = 0;
    for (int i = 0; i < 3; ++i) {
        if (net->grid[i].channels < 1 || net->grid[i].channels % BLOCK != 0) return -2;
        features += net->grid[i].channels;
    }
    if (features != net->features) return -3;
    if (PADDED(features) > MAX_FEATURES) return -1;
    uint16_t *w1_bf16 = NULL, *w2_bf16 = NULL;
#if COLOUR_BF16
    w1_bf16 = malloc(sizeof(uint16_t) * PADDED(features) * HIDDEN);
    w2_bf16 = malloc(sizeof(uint16_t) * HIDDEN * HIDDEN);
    if (w1_bf16 == NULL || w2_bf16 == NULL) {
        free(w1_bf16);
        free(w2_bf16);
        return -4;
    }
    pack_bf16(w1_bf16, net->w1, features);
    pack_bf16(w2_bf16, net->w2, HIDDEN);
#endif
    threads = clamp_threads(threads, (points + 4095) / 4096);
    ColourWork work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        ColourWork item = {net, w1_bf16, w2_bf16, x, ray, rgb, points * t / threads, points * (t + 1) / threads};
        work[t] = item;
    }
    run_all(colour_work, work, sizeof work[0], threads);
    free(w1_bf16);
    free(w2_bf16);
    return 0;
}

/* Deferred colour (GridAppearance's deferred_colour): no network a sample; each packed sample's
 * appearance features, times its weight, added to its ray's row of out [rays, features]. The
 * samples' rays ascend, and each thread takes a run of whole rays, so no two write one row.
 * With `fresh`, each ray's samples are all in the call and its row holds nothing yet: the row is
 * set at the ray's first sample, not added to, so that the caller need not zero a row a ray
 * (lego's view zeroed 10 × 19 MB, 14-22 ms a view, for rows mostly written again at once).
 * Nothing is asked of memory ahead: a ray's next samples read mostly the rows its last ones did,
 * and asking for the rows 6 samples on cost lego's views 30-70 ms of colour each (0.14-0.20 s
 * against 0.12-0.13 s without, AVX2 code, the two in turn) for rows already in the caches. */
typedef struct {
    const ColourNetwork *net;  /* the grid and its box alone are read */
    const float *x, *weight;
    const int64_t *ray;
    float *out;
    int64_t begin, end;
    int32_t vertices[3];       /* each axis's, the same in every component (composite_samples checks) */
    int32_t fresh;             /* each ray's row set at its first sample (composite_samples) */
} FeatureWork;

/* A sample's features from its three axes' corners, each found once: every component reads two
 * of them for its plane and the third for its line. Found a component at a time (nine, through
 * forward_sample, a call each), the pass spent about 450 instructions a sample, and it ran as
 * fast on a few rows as on lego's 20 MB of them: it was the instructions, not the memory. */
static inline void features_at(const Component grid[3], const AxisCorner corner[3], float *out) {
    for (int i = 0; i < 3; ++i) {
        const Component *m = &grid[i];
        component_features(m, corner[m->axis_a], corner[m->axis_b], corner[m->axis_c], out);
        out += m->channels;
    }
}

/* Half-precision tables (F16C's conversions; x86-64-v3 has them): lego's thirty-minute appearance
 * grid is 44 MB of float32 rows, more than the 32 MB of L3 of this project's AMD EPYCs, and the
 * feature pass waited on its plane rows; in half precision it is 22 MB. A feature's relative
 * rounding is 2^-11, under what the colour's 8 bits show. */
#if defined(__F16C__) && defined(__AVX__)
#include <immintrin.h>
#define HALF_TABLES 1
static inline vec load_half(const uint16_t *p) {
    const __m256 v = _mm256_cvtph_ps(_mm_loadu_si128((const __m128i *)p));
    vec out;
    memcpy(&out, &v, sizeof out);
    return out;
}

/* component_features of half-precision rows: the same sums, each row rounded to half once. */
static inline void component_features_half(const Component *m, const uint16_t *plane, const uint16_t *line,
                                           AxisCorner a, AxisCorner b, AxisCorner c, float *out) {
    const int32_t C = m->channels;
    const vec w00 = splat(a.low_weight * b.low_weight), w01 = splat(a.low_weight * b.high_weight);
    const vec w10 = splat(a.high_weight * b.low_weight), w11 = splat(a.high_weight * b.high_weight);
    const vec u0 = splat(c.low_weight), u1 = splat(c.high_weight);
    const uint16_t *p00 = plane + ((int64_t)a.lower * m->nb + b.lower) * C, *p01 = p00 + C;
    const uint16_t *p10 = p00 + (int64_t)m->nb * C, *p11 = p10 + C;
    const uint16_t *l0 = line + c.lower * C, *l1 = l0 + C;
    for (int32_t k = 0; k < C; k += BLOCK) {
        vec plane_sum = w00 * load_half(p00 + k) + w01 * load_half(p01 + k) + w10 * load_half(p10 + k)
                        + w11 * load_half(p11 + k);
        store(out + k, plane_sum * (u0 * load_half(l0 + k) + u1 * load_half(l1 + k)));
    }
}
#else
#define HALF_TABLES 0
#endif

static void *feature_work(void *arg) {
    const FeatureWork *w = (const FeatureWork *)arg;
    const ColourNetwork *net = w->net;
    const int32_t F = net->features;
    float features[MAX_FEATURES];
    for (int64_t p = w->begin; p < w->end; ++p) {
        AxisCorner corner[3];
        for (int a = 0; a < 3; ++a)
            corner[a] = axis_corner((w->x[3 * p + a] - net->box_min[a]) * net->scale[a] - 1.0f, w->vertices[a]);
#if HALF_TABLES
        if (net->half_plane[0]) {
            float *out = features;
            for (int i = 0; i < 3; ++i) {
                const Component *m = &net->grid[i];
                component_features_half(m, net->half_plane[i], net->half_line[i], corner[m->axis_a], corner[m->axis_b],
                                        corner[m->axis_c], out);
                out += m->channels;
            }
        } else
#endif
        features_at(net->grid, corner, features);
        float *row = w->out + w->ray[p] * F;
        const vec weight = splat(w->weight[p]);
        if (w->fresh && (p == w->begin || w->ray[p] != w->ray[p - 1]))
            for (int32_t k = 0; k < F; k += BLOCK) store(row + k, weight * load(features + k));
        else
            for (int32_t k = 0; k < F; k += BLOCK) store(row + k, load(row + k) + weight * load(features + k));
    }
    return NULL;
}

/* out[ray[p]] += weight[p] · features(x[p]) for `points` samples (world space, rays ascending),
 * on `threads` threads over runs of whole rays; with `fresh`, each ray's row is set to its sum
 * (FeatureWork's fresh). 0, or below 0 where the grid is not one this
 * pass reads (-4: an axis with different vertices in two components; -5: half-precision tables
 * given to a build without HALF_TABLES). */
int composite_samples(const ColourNetwork *net, const float *x, const int64_t *ray, const float *weight,
                      int64_t points, float *out, int64_t threads, int32_t fresh) {
    int32_t features = 0, vertices[3] = {0, 0, 0};
    for (int i = 0; i < 3; ++i) {
        const Component *m = &net->grid[i];
        if (m->channels < 1 || m->channels % BLOCK != 0) return -2;
        features += m->channels;
        const int32_t axes[3] = {m->axis_a, m->axis_b, m->axis_c}, sizes[3] = {m->na, m->nb, m->nc};
        for (int k = 0; k < 3; ++k) {
            if (axes[k] < 0 || axes[k] > 2 || (vertices[axes[k]] && vertices[axes[k]] != sizes[k])) return -4;
            vertices[axes[k]] = sizes[k];
        }
    }
    if (features != net->features || features > MAX_FEATURES) return -3;
    if (!vertices[0] || !vertices[1] || !vertices[2]) return -4;
    if (net->half_plane[0] && !HALF_TABLES) return -5;
    threads = clamp_threads(threads, (points + 4095) / 4096);
    FeatureWork work[MAX_THREADS];
    int64_t begin = 0;
    for (int64_t t = 0; t < threads; ++t) {
        int64_t end = t == threads - 1 ? points : points * (t + 1) / threads;
        while (end > begin && end < points && ray[end] == ray[end - 1]) ++end;  /* a ray stays whole */
        if (end < begin) end = begin;
        FeatureWork item = {net, x, weight, ray, out, begin, end, {vertices[0], vertices[1], vertices[2]}, fresh};
        work[t] = item;
        begin = end;
    }
    run_all(feature_work, work, sizeof work[0], threads);
    return 0;
}

/* Deferred colour's network once a ray, at inference (GridAppearance.shade_fn through
 * volume_rendering.shade_rays): each shaded ray's mean features (its composited sum over its
 * coloured weight) and its direction's encoding, (d, sin 2^0 d, cos 2^0 d, ..., sin 2^(L-1) d,
 * cos 2^(L-1) d) as PositionalEncoding orders it, through the three layers, the sigmoid, times
 * the ray's weight. Through PyTorch the same rays took a gather of their sums, a division, the
 * encoding, the basis, a concatenation and three products, each a pass over memory (lego's view
 * at 800×800: 0.16 s for 202 000 rays, 0.06 s of them the products); here a tile of rays stays
 * in the caches from its sums to its colour. Always float32, as the PyTorch path at inference. */
#define MAX_BANDS 8
#define MAX_SHADE_INPUTS (MAX_FEATURES + 3 * (1 + 2 * MAX_BANDS))

typedef struct {
    const float *w1;        /* [features + 3(1 + 2·bands), HIDDEN]: the features' rows (the appearance
                               basis folded in), then the encoding's */
    const float *b1;        /* [HIDDEN] */
    const float *w2;        /* [HIDDEN, HIDDEN] */
    const float *b2;        /* [HIDDEN] */
    const float *w3;        /* [3, HIDDEN]: row c gives colour channel c */
    const float *b3;        /* [3] */
    int32_t features;       /* the composited features a ray */
    int32_t bands;          /* the direction encoding's frequencies */
    int32_t hidden;         /* HIDDEN, checked */
} ShadeNetwork;

typedef struct {
    const ShadeNetwork *net;
    const float *accumulated, *coloured, *weight, *directions;
    const int64_t *shaded;
    float *rgb;
    int64_t begin, end;
} ShadeWork;

/* The encoding of direction d into out[0 .. 3(1 + 2·bands)). The first band's sine and cosine
 * come from sinf and cosf; each later band's, its angles double the last's, from the double-angle
 * formulas (sin 2a = 2 sin a cos a, cos 2a = (cos a - sin a)(cos a + sin a), which keeps its
 * precision where cos 2a is near 0): a call a coordinate rather than one a band, within a few
 * float32 steps of torch.sin and torch.cos of the scaled direction. */
static inline void encode_direction(const float d[3], int32_t bands, float *out) {
    for (int a = 0; a < 3; ++a) out[a] = d[a];
    if (bands < 1) return;
    for (int a = 0; a < 3; ++a) {  /* one sincosf call (GCC pairs the two) */
        out[3 + a] = sinf(d[a]);
        out[6 + a] = cosf(d[a]);
    }
    for (int32_t band = 1; band < bands; ++band)
        for (int a = 0; a < 3; ++a) {
            const float sine = out[6 * band - 3 + a], cosine = out[6 * band + a];
            out[3 + 6 * band + a] = 2.0f * sine * cosine;
            out[6 + 6 * band + a] = (cosine - sine) * (cosine + sine);
        }
}

/* The shading's layers as a matrix product's kernel does them: SHADE_ROWS rays by a block of
 * OUT_BLOCK vectors of outputs, their sums in registers (with AVX2's 16 vector registers, 6 × 2
 * sums, 2 weight vectors and a broadcast; with AVX-512's 32, 6 × 4 sums); each weight vector is
 * loaded once for the block's rays, each input once for its vectors. (Holding all of a ray's
 * 64 sums, as colour_work's tiles do, leaves AVX2 2 rays a tile and spills its registers.) */
#define SHADE_ROWS 6
#if LANES == 16
#define OUT_BLOCK 4
#else
#define OUT_BLOCK 2
#endif

/* out[t][0, width) = bias + Σ_k in[t][k] · w[k] for the tile's SHADE_ROWS rays, through ReLU
 * where `relu`: w's rows and bias (NULL: none) `width` floats, a whole number of vectors; in's
 * rows in_stride apart, out's out_stride. Blocks of OUT_BLOCK vectors, then single vectors. */
static inline void dense_rows(float *out, int64_t out_stride, const float *in, int64_t in_stride, const float *w,
                              int32_t width, const float *bias, int32_t count, int relu) {
    const int32_t vectors = width / LANES;
    int32_t block = 0;
    for (; block + OUT_BLOCK <= vectors; block += OUT_BLOCK) {
        wide sums[SHADE_ROWS][OUT_BLOCK];
        for (int t = 0; t < SHADE_ROWS; ++t)
            for (int j = 0; j < OUT_BLOCK; ++j)
                sums[t][j] = bias ? load_wide(bias + (block + j) * LANES) : splat_wide(0.0f);
        for (int32_t k = 0; k < count; ++k) {
            wide row[OUT_BLOCK];
            for (int j = 0; j < OUT_BLOCK; ++j) row[j] = load_wide(w + (int64_t)k * width + (block + j) * LANES);
            for (int t = 0; t < SHADE_ROWS; ++t) {
                const wide x = splat_wide(in[t * in_stride + k]);
                for (int j = 0; j < OUT_BLOCK; ++j) sums[t][j] += x * row[j];
            }
        }
        for (int t = 0; t < SHADE_ROWS; ++t)
            for (int j = 0; j < OUT_BLOCK; ++j)
                store_wide(out + t * out_stride + (block + j) * LANES, relu ? relu_wide(sums[t][j]) : sums[t][j]);
    }
    for (; block < vectors; ++block) {
        wide sums[SHADE_ROWS];
        for (int t = 0; t < SHADE_ROWS; ++t) sums[t] = bias ? load_wide(bias + block * LANES) : splat_wide(0.0f);
        for (int32_t k = 0; k < count; ++k) {
            const wide row = load_wide(w + (int64_t)k * width + block * LANES);
            for (int t = 0; t < SHADE_ROWS; ++t) sums[t] += splat_wide(in[t * in_stride + k]) * row;
        }
        for (int t = 0; t < SHADE_ROWS; ++t)
            store_wide(out + t * out_stride + block * LANES, relu ? relu_wide(sums[t]) : sums[t]);
    }
}

static void *shade_work(void *arg) {
    const ShadeWork *w = (const ShadeWork *)arg;
    const ShadeNetwork *net = w->net;
    const int32_t F = net->features, inputs = F + 3 * (1 + 2 * net->bands);
    float tile[SHADE_ROWS][MAX_SHADE_INPUTS];
    float hidden[SHADE_ROWS][HIDDEN], second[SHADE_ROWS][HIDDEN];
    for (int64_t first = w->begin; first < w->end; first += SHADE_ROWS) {
        const int64_t count = w->end - first < SHADE_ROWS ? w->end - first : SHADE_ROWS;
        /* The next tile's sums asked of memory now: the shaded rays are a third of a view's,
         * their rows too far apart for the hardware's own prefetch. */
        for (int64_t next = first + SHADE_ROWS; next < first + 2 * SHADE_ROWS && next < w->end; ++next) {
            const char *row = (const char *)(w->accumulated + w->shaded[next] * F);
            for (int64_t byte = 0; byte < (int64_t)F * (int64_t)sizeof(float); byte += 64) __builtin_prefetch(row + byte);
        }
        int64_t ray[SHADE_ROWS];
        for (int t = 0; t < SHADE_ROWS; ++t) {  /* a short last tile repeats its last ray (not written) */
            const int64_t r = w->shaded[first + (t < count ? t : count - 1)];
            ray[t] = r;
            const float *sum = w->accumulated + r * F, coloured = w->coloured[r];
            for (int32_t k = 0; k < F; ++k) tile[t][k] = sum[k] / coloured;
            encode_direction(w->directions + 3 * r, net->bands, tile[t] + F);
        }
        dense_rows(&hidden[0][0], HIDDEN, &tile[0][0], MAX_SHADE_INPUTS, net->w1, HIDDEN, net->b1, inputs, 1);
        dense_rows(&second[0][0], HIDDEN, &hidden[0][0], HIDDEN, net->w2, HIDDEN, net->b2, HIDDEN, 1);
        for (int t = 0; t < count; ++t) {
            wide h[HIDDEN_VECTORS];
            for (int j = 0; j < HIDDEN_VECTORS; ++j) h[j] = load_wide(second[t] + j * LANES);
            for (int c = 0; c < 3; ++c) w->rgb[3 * ray[t] + c] = colour_channel(h, net->w3, net->b3[c], c) * w->weight[ray[t]];
        }
    }
    return NULL;
}

/* rgb[r] = weight[r] · colour(accumulated[r] / coloured[r], directions[r]) for the `count` rays
 * of `shaded` (rgb's other rows untouched), on `threads` threads over them. 0, or below 0 where
 * the network is not one this pass takes (the caller shades through PyTorch). */
int shade_rays(const ShadeNetwork *net, const float *accumulated, const float *coloured, const float *weight,
               const float *directions, const int64_t *shaded, int64_t count, float *rgb, int64_t threads) {
    if (net->hidden != HIDDEN || net->features < 1 || net->features > MAX_FEATURES) return -1;
    if (net->bands < 0 || net->bands > MAX_BANDS) return -2;
    threads = clamp_threads(threads, (count + 2047) / 2048);
    ShadeWork work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        ShadeWork item = {net, accumulated, coloured, weight, directions, shaded, rgb,
                          count * t / threads, count * (t + 1) / threads};
        work[t] = item;
    }
    run_all(shade_work, work, sizeof work[0], threads);
    return 0;
}

/* Training's deferred shading, forward and backward each in one compiled call with no PyTorch
 * autograd inside (compiled_colour.py's CompiledShadeTraining): GridAppearance's network as it
 * trains, the appearance basis a = mean · Bᵀ (no bias), then the three layers over [a, the
 * direction's encoding], the sigmoid. Through PyTorch a step's 2 048 rays took some thirty
 * operators and their autograd records. Widths are padded to whole vectors with zeros: APAD
 * the basis's outputs, FPAD the features; forward keeps each ray's layer inputs for backward. */
typedef struct {
    const float *basis_t;   /* [features, apad]: Bᵀ */
    const float *basis;     /* [apad, fpad]: B, the features' gradient from the basis's */
    const float *w1_t;      /* [apad + encoding, HIDDEN]: W1ᵀ, the basis's rows (zero past its
                               outputs), then the encoding's */
    const float *w1_a;      /* [HIDDEN, apad]: W1's basis columns, the basis's gradient from the first layer's */
    const float *b1;        /* [HIDDEN] */
    const float *w2_t;      /* [HIDDEN, HIDDEN]: W2ᵀ */
    const float *w2;        /* [HIDDEN, HIDDEN]: W2 */
    const float *b2;        /* [HIDDEN] */
    const float *w3;        /* [3, HIDDEN] */
    const float *b3;        /* [3] */
    int32_t features, fpad, apad, bands, hidden;
} ShadeTraining;

/* The network's weights as PyTorch holds them (nn.Linear's [out, in], row-major, contiguous). */
typedef struct {
    const float *basis, *w1, *b1, *w2, *b2, *w3, *b3;
    int32_t appearance, features, encoding, bands;
} ShadeWeights;

/* The floats shade_training_prepare lays the padded and transposed weights out in. */
int64_t shade_training_room_floats(const ShadeWeights *w) {
    const int64_t apad = PADDED(w->appearance), fpad = PADDED(w->features);
    return (int64_t)w->features * apad + apad * fpad + (apad + w->encoding) * HIDDEN + HIDDEN * apad + HIDDEN * HIDDEN;
}

/* net over w for a step: Bᵀ, B, W1ᵀ, W1's basis columns and W2ᵀ padded with zeros and transposed
 * into room (shade_training_room_floats), the biases, W2 and W3 read where they are. A pass over
 * 56 KB (lego's network); through PyTorch the same was ten operators, 0.15 ms in a step. */
void shade_training_prepare(const ShadeWeights *w, float *room, ShadeTraining *net) {
    const int32_t A = w->appearance, F = w->features, E = w->encoding, inputs = A + E;
    const int32_t apad = PADDED(A), fpad = PADDED(F);
    float *basis_t = room, *basis = basis_t + (int64_t)F * apad, *w1_t = basis + (int64_t)apad * fpad;
    float *w1_a = w1_t + (int64_t)(apad + E) * HIDDEN, *w2_t = w1_a + (int64_t)HIDDEN * apad;
    memset(room, 0, sizeof(float) * shade_training_room_floats(w));
    for (int32_t a = 0; a < A; ++a)
        for (int32_t f = 0; f < F; ++f) {
            basis[a * fpad + f] = w->basis[a * F + f];
            basis_t[f * apad + a] = w->basis[a * F + f];
        }
    for (int32_t h = 0; h < HIDDEN; ++h) {
        for (int32_t a = 0; a < A; ++a) w1_t[a * HIDDEN + h] = w1_a[h * apad + a] = w->w1[h * inputs + a];
        for (int32_t e = 0; e < E; ++e) w1_t[(apad + e) * HIDDEN + h] = w->w1[h * inputs + A + e];
        for (int32_t k = 0; k < HIDDEN; ++k) w2_t[k * HIDDEN + h] = w->w2[h * HIDDEN + k];
    }
    net->basis_t = basis_t, net->basis = basis, net->w1_t = w1_t, net->w1_a = w1_a, net->b1 = w->b1;
    net->w2_t = w2_t, net->w2 = w->w2, net->b2 = w->b2, net->w3 = w->w3, net->b3 = w->b3;
    net->features = F, net->fpad = fpad, net->apad = apad, net->bands = w->bands, net->hidden = HIDDEN;
}

/* A thread's gradient sums, one after the other in one buffer: W1ᵀ's, b1's, W2ᵀ's, b2's, W3's,
 * b3's (B3_FLOATS, whatever the vector width) and Bᵀ's. */
#define B3_FLOATS 16
static int64_t shade_gradient_floats(const ShadeTraining *net) {
    const int64_t inputs = net->apad + 3 * (1 + 2 * net->bands);
    return inputs * HIDDEN + HIDDEN + HIDDEN * HIDDEN + HIDDEN + 3 * HIDDEN + B3_FLOATS + (int64_t)net->features * net->apad;
}

/* g[k][0, width) += Σ_t in[t][k] · dz[t][0, width) for k < count: a layer's weight gradient over a
 * tile's rays, in the blocks dense_rows uses (the tile's dz in registers). */
static inline void outer_accumulate(float *g, int32_t width, const float *in, int64_t in_stride, int32_t count,
                                    const float *dz, int64_t dz_stride) {
    const int32_t vectors = width / LANES;
    int32_t block = 0;
    for (; block + OUT_BLOCK <= vectors; block += OUT_BLOCK) {
        wide d[SHADE_ROWS][OUT_BLOCK];
        for (int t = 0; t < SHADE_ROWS; ++t)
            for (int j = 0; j < OUT_BLOCK; ++j) d[t][j] = load_wide(dz + t * dz_stride + (block + j) * LANES);
        for (int32_t k = 0; k < count; ++k) {
            float *row = g + (int64_t)k * width + block * LANES;
            wide sums[OUT_BLOCK];
            for (int j = 0; j < OUT_BLOCK; ++j) sums[j] = load_wide(row + j * LANES);
            for (int t = 0; t < SHADE_ROWS; ++t) {
                const wide x = splat_wide(in[t * in_stride + k]);
                for (int j = 0; j < OUT_BLOCK; ++j) sums[j] += x * d[t][j];
            }
            for (int j = 0; j < OUT_BLOCK; ++j) store_wide(row + j * LANES, sums[j]);
        }
    }
    for (; block < vectors; ++block) {
        wide d[SHADE_ROWS];
        for (int t = 0; t < SHADE_ROWS; ++t) d[t] = load_wide(dz + t * dz_stride + block * LANES);
        for (int32_t k = 0; k < count; ++k) {
            float *row = g + (int64_t)k * width + block * LANES;
            wide sum = load_wide(row);
            for (int t = 0; t < SHADE_ROWS; ++t) sum += splat_wide(in[t * in_stride + k]) * d[t];
            store_wide(row, sum);
        }
    }
}

/* A tile's rows of src ([rays][width] floats, rows `stride` apart), the last repeated past `count`. */
static inline void tile_rows(float *dst, int64_t dst_stride, const float *src, int64_t stride, int64_t first,
                             int64_t count, int32_t width) {
    for (int t = 0; t < SHADE_ROWS; ++t)
        memcpy(dst + t * dst_stride, src + (first + (t < count ? t : count - 1)) * stride, sizeof(float) * width);
}

#define MAX_APAD 64
#define MAX_TRAIN_INPUTS (MAX_APAD + 3 * (1 + 2 * MAX_BANDS))
#define MAX_FPAD (MAX_FEATURES + 16)

/* A thread's share of a step's shaded rays, i in [begin, end): ray shaded[i] of the step's. */
typedef struct {
    const ShadeTraining *net;
    const int64_t *shaded;
    const float *accumulated, *coloured_weight, *weight, *directions;   /* [rays, ...]: the step's */
    float *mean, *inputs, *hidden1, *hidden2, *colour;  /* [count, ...]: forward's, kept for backward */
    float *rgb;                                        /* forward: [rays, 3] */
    const float *grad_rgb;                             /* backward: [rays, 3] */
    float *grad_accumulated, *grad_coloured_weight, *grad_weight;      /* backward: [rays, ...] */
    float *gradients;                                  /* backward: this thread's sums (shade_gradient_floats) */
    int64_t begin, end;
} ShadeTrainingWork;

/* The rays of a tile (its last repeated past `count`: their results are not written). */
static inline int64_t tile_ray(const ShadeTrainingWork *w, int64_t first, int64_t count, int t) {
    return w->shaded[first + (t < count ? t : count - 1)];
}

static void *shade_training_forward_work(void *arg) {
    const ShadeTrainingWork *w = (const ShadeTrainingWork *)arg;
    const ShadeTraining *net = w->net;
    const int32_t F = net->features, A = net->apad, inputs = A + 3 * (1 + 2 * net->bands);
    float mean[SHADE_ROWS][MAX_FPAD], x1[SHADE_ROWS][MAX_TRAIN_INPUTS];
    float h1[SHADE_ROWS][HIDDEN], h2[SHADE_ROWS][HIDDEN];
    for (int64_t first = w->begin; first < w->end; first += SHADE_ROWS) {
        const int64_t count = w->end - first < SHADE_ROWS ? w->end - first : SHADE_ROWS;
        for (int t = 0; t < SHADE_ROWS; ++t) {  /* the ray's mean features, the encoding of its direction */
            const int64_t s = tile_ray(w, first, count, t);
            const float inverse = 1.0f / w->coloured_weight[s];
            for (int32_t f = 0; f < F; ++f) mean[t][f] = w->accumulated[s * F + f] * inverse;
            encode_direction(w->directions + 3 * s, net->bands, x1[t] + A);
        }
        dense_rows(&x1[0][0], MAX_TRAIN_INPUTS, &mean[0][0], MAX_FPAD, net->basis_t, A, NULL, F, 0);
        dense_rows(&h1[0][0], HIDDEN, &x1[0][0], MAX_TRAIN_INPUTS, net->w1_t, HIDDEN, net->b1, inputs, 1);
        dense_rows(&h2[0][0], HIDDEN, &h1[0][0], HIDDEN, net->w2_t, HIDDEN, net->b2, HIDDEN, 1);
        for (int t = 0; t < count; ++t) {
            const int64_t i = first + t, s = w->shaded[i];
            wide h[HIDDEN_VECTORS];
            for (int j = 0; j < HIDDEN_VECTORS; ++j) h[j] = load_wide(h2[t] + j * LANES);
            for (int c = 0; c < 3; ++c) {
                const float colour = colour_channel(h, net->w3, net->b3[c], c);
                w->colour[3 * i + c] = colour;
                w->rgb[3 * s + c] = w->weight[s] * colour;
            }
            memcpy(w->mean + i * F, mean[t], sizeof(float) * F);
            memcpy(w->inputs + i * inputs, x1[t], sizeof(float) * inputs);
            memcpy(w->hidden1 + i * HIDDEN, h1[t], sizeof h1[t]);
            memcpy(w->hidden2 + i * HIDDEN, h2[t], sizeof h2[t]);
        }
    }
    return NULL;
}

static void *shade_training_backward_work(void *arg) {
    const ShadeTrainingWork *w = (const ShadeTrainingWork *)arg;
    const ShadeTraining *net = w->net;
    const int32_t F = net->features, A = net->apad, FP = net->fpad, inputs = A + 3 * (1 + 2 * net->bands);
    float *g_w1_t = w->gradients, *g_b1 = g_w1_t + (int64_t)inputs * HIDDEN, *g_w2_t = g_b1 + HIDDEN;
    float *g_b2 = g_w2_t + HIDDEN * HIDDEN, *g_w3 = g_b2 + HIDDEN, *g_b3 = g_w3 + 3 * HIDDEN, *g_basis_t = g_b3 + B3_FLOATS;
    float mean[SHADE_ROWS][MAX_FPAD], x1[SHADE_ROWS][MAX_TRAIN_INPUTS];
    float h1[SHADE_ROWS][HIDDEN], h2[SHADE_ROWS][HIDDEN], dz2[SHADE_ROWS][HIDDEN], dz1[SHADE_ROWS][HIDDEN];
    float da[SHADE_ROWS][MAX_APAD], dmean[SHADE_ROWS][MAX_FPAD];
    for (int64_t first = w->begin; first < w->end; first += SHADE_ROWS) {
        const int64_t count = w->end - first < SHADE_ROWS ? w->end - first : SHADE_ROWS;
        tile_rows(&mean[0][0], MAX_FPAD, w->mean, F, first, count, F);
        tile_rows(&x1[0][0], MAX_TRAIN_INPUTS, w->inputs, inputs, first, count, inputs);
        tile_rows(&h1[0][0], HIDDEN, w->hidden1, HIDDEN, first, count, HIDDEN);
        tile_rows(&h2[0][0], HIDDEN, w->hidden2, HIDDEN, first, count, HIDDEN);
        /* Through the weighting (rgb = weight · colour), the sigmoid and the third layer; a
         * repeated ray past `count` carries nothing. */
        for (int t = 0; t < SHADE_ROWS; ++t) {
            wide dh[HIDDEN_VECTORS];
            for (int j = 0; j < HIDDEN_VECTORS; ++j) dh[j] = splat_wide(0.0f);
            if (t < count) {
                const int64_t i = first + t, s = w->shaded[i];
                float along = 0.0f;
                for (int c = 0; c < 3; ++c) {
                    const float grad = w->grad_rgb[3 * s + c], colour = w->colour[3 * i + c];
                    along += grad * colour;
                    const float dz = w->weight[s] * grad * colour * (1.0f - colour);
                    g_b3[c] += dz;
                    for (int j = 0; j < HIDDEN_VECTORS; ++j) {
                        const wide x = splat_wide(dz);
                        store_wide(g_w3 + c * HIDDEN + j * LANES,
                                   load_wide(g_w3 + c * HIDDEN + j * LANES) + x * load_wide(h2[t] + j * LANES));
                        dh[j] += x * load_wide(net->w3 + c * HIDDEN + j * LANES);
                    }
                }
                w->grad_weight[s] = along;
            }
            for (int j = 0; j < HIDDEN_VECTORS; ++j) {  /* through the second ReLU: h2 > 0 where it passed */
                const wide kept = (wide)((wide_mask)dh[j] & (load_wide(h2[t] + j * LANES) > splat_wide(0.0f)));
                store_wide(dz2[t] + j * LANES, kept);
            }
        }
        for (int t = 0; t < SHADE_ROWS; ++t)
            for (int j = 0; j < HIDDEN_VECTORS; ++j)
                store_wide(g_b2 + j * LANES, load_wide(g_b2 + j * LANES) + load_wide(dz2[t] + j * LANES));
        outer_accumulate(g_w2_t, HIDDEN, &h1[0][0], HIDDEN, HIDDEN, &dz2[0][0], HIDDEN);
        dense_rows(&dz1[0][0], HIDDEN, &dz2[0][0], HIDDEN, net->w2, HIDDEN, NULL, HIDDEN, 0);
        for (int t = 0; t < SHADE_ROWS; ++t)
            for (int j = 0; j < HIDDEN_VECTORS; ++j) {  /* through the first ReLU */
                const wide kept = (wide)((wide_mask)load_wide(dz1[t] + j * LANES) &
                                         (load_wide(h1[t] + j * LANES) > splat_wide(0.0f)));
                store_wide(dz1[t] + j * LANES, kept);
                store_wide(g_b1 + j * LANES, load_wide(g_b1 + j * LANES) + kept);
            }
        outer_accumulate(g_w1_t, HIDDEN, &x1[0][0], MAX_TRAIN_INPUTS, inputs, &dz1[0][0], HIDDEN);
        dense_rows(&da[0][0], MAX_APAD, &dz1[0][0], HIDDEN, net->w1_a, A, NULL, HIDDEN, 0);
        outer_accumulate(g_basis_t, A, &mean[0][0], MAX_FPAD, F, &da[0][0], MAX_APAD);
        dense_rows(&dmean[0][0], MAX_FPAD, &da[0][0], MAX_APAD, net->basis, FP, NULL, A, 0);
        /* Into the ray's sums: with m = a / w_c, dL/da = dL/dm / w_c and dL/dw_c = -(dL/dm · m) / w_c. */
        for (int t = 0; t < count; ++t) {
            const int64_t s = w->shaded[first + t];
            const float inverse = 1.0f / w->coloured_weight[s];
            float along = 0.0f;
            for (int32_t f = 0; f < F; ++f) {
                along += dmean[t][f] * mean[t][f];
                w->grad_accumulated[s * F + f] = dmean[t][f] * inverse;
            }
            w->grad_coloured_weight[s] = -along * inverse;
        }
    }
    return NULL;
}

static int shade_training_checked(const ShadeTraining *net) {
    if (net->hidden != HIDDEN || net->features < 1 || net->fpad > MAX_FPAD || net->fpad % LANES
        || net->fpad < net->features) return -1;
    if (net->apad < LANES || net->apad > MAX_APAD || net->apad % LANES || net->bands < 0 || net->bands > MAX_BANDS)
        return -2;
    return 0;
}

/* Threads for `rays` shaded rays: at most one a 512. */
static int64_t shade_training_threads(int64_t threads, int64_t rays) {
    return clamp_threads(threads, (rays + 511) / 512);
}

/* Training's deferred shading of whole rays (volume_rendering.shade_rays), forward and backward
 * each in one call, the gathers and scatters inside the threads' tiles: for each of `count`
 * rays s = shaded[i] (each at most once), its mean features m_i = accumulated[s] /
 * coloured_weight[s] (kept in mean [count, features]), its colour c_i seen along directions[s]
 * (colour [count, 3], the sigmoid's; the layers' inputs [count, apad + encoding] and hidden1,
 * hidden2 [count, HIDDEN] kept for backward), and rgb[s] = weight[s] c_i; rgb [rays, 3] is zero
 * on entry, and stays so for rays not shaded. */
int shade_rays_training_forward(const ShadeTraining *net, const float *accumulated, const float *coloured_weight,
                                const float *weight, const float *directions, const int64_t *shaded, int64_t count,
                                float *mean, float *inputs, float *hidden1, float *hidden2, float *colour, float *rgb,
                                int64_t threads) {
    const int status = shade_training_checked(net);
    if (status) return status;
    threads = shade_training_threads(threads, count);
    ShadeTrainingWork work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        ShadeTrainingWork item = {.net = net, .shaded = shaded, .accumulated = accumulated,
                                  .coloured_weight = coloured_weight, .weight = weight, .directions = directions,
                                  .mean = mean, .inputs = inputs, .hidden1 = hidden1, .hidden2 = hidden2,
                                  .colour = colour, .rgb = rgb, .begin = count * t / threads,
                                  .end = count * (t + 1) / threads};
        work[t] = item;
    }
    run_all(shade_training_forward_work, work, sizeof work[0], threads);
    return 0;
}

/* Its backward from grad_rgb [rays, 3]: grad_accumulated [rays, features], grad_coloured_weight
 * and grad_weight [rays] (zero for the rays not shaded), and the parameters' gradients summed
 * into gradients (shade_gradient_floats(net) floats, zero on entry: W1ᵀ, b1, W2ᵀ, b2, W3, b3 in
 * B3_FLOATS, Bᵀ); scratch holds (threads - 1) more such sums. The zeros are written here, on
 * the calling thread: PyTorch's zeros of lego's [2 048, 72] woke a sleeping OpenMP thread, 75 µs
 * on 2 cores against 9 on one. */
int shade_rays_training_backward(const ShadeTraining *net, const float *coloured_weight, const float *weight,
                                 const int64_t *shaded, int64_t count, int64_t rays, const float *mean,
                                 const float *inputs, const float *hidden1, const float *hidden2,
                                 const float *colour, const float *grad_rgb, float *gradients, float *scratch,
                                 float *grad_accumulated, float *grad_coloured_weight, float *grad_weight,
                                 int64_t threads) {
    const int status = shade_training_checked(net);
    if (status) return status;
    memset(grad_accumulated, 0, sizeof(float) * rays * net->features);
    memset(grad_coloured_weight, 0, sizeof(float) * rays);
    memset(grad_weight, 0, sizeof(float) * rays);
    threads = shade_training_threads(threads, count);
    const int64_t size = shade_gradient_floats(net);
    ShadeTrainingWork work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        float *sums = t == 0 ? gradients : scratch + (t - 1) * size;
        if (t > 0) memset(sums, 0, sizeof(float) * size);
        ShadeTrainingWork item = {.net = net, .shaded = shaded, .coloured_weight = coloured_weight, .weight = weight,
                                  .mean = (float *)mean, .inputs = (float *)inputs, .hidden1 = (float *)hidden1,
                                  .hidden2 = (float *)hidden2, .colour = (float *)colour, .grad_rgb = grad_rgb,
                                  .grad_accumulated = grad_accumulated, .grad_coloured_weight = grad_coloured_weight,
                                  .grad_weight = grad_weight, .gradients = sums, .begin = count * t / threads,
                                  .end = count * (t + 1) / threads};
        work[t] = item;
    }
    run_all(shade_training_backward_work, work, sizeof work[0], threads);
    for (int64_t t = 1; t < threads; ++t)
        for (int64_t i = 0; i < size; ++i) gradients[i] += scratch[(t - 1) * size + i];
    return 0;
}

/* The floats shade_training_backward's gradients hold (its scratch: that times threads - 1). */
int64_t shade_training_gradient_floats(const ShadeTraining *net) { return shade_gradient_floats(net); }

/* 1 where composite_samples reads half-precision tables (ColourNetwork's half_plane, half_line). */
int half_tables(void) { return HALF_TABLES; }

/* 16 where the wide layers multiply in bfloat16, 32 where in float32. */
int colour_precision(void) { return COLOUR_BF16 ? 16 : 32; }

#endif
