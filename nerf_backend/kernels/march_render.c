/* The inference march of a marched field with a dense density volume, one ray at a time, in
 * one pass: skip-grid spans, fine steps, occupancy, the density's trilinear read and its
 * activation, compositing and the early stop. What the PyTorch march does in rounds of many
 * small tensor operations (nerf_backend/model_components/marcher.py,
 * render_marched_stopping_early) is here a loop over a ray's own steps, so a ray stops at its
 * surface and nothing is written for steps that hold no density.
 *
 * Out: each ray's transmittance, expected depth, the weight left uncoloured and the weight
 * coloured, and the samples to colour, packed (ray, position, weight). The colour field (an
 * MLP) stays in PyTorch. Plain C and POSIX threads, no Python API: built by
 * nerf_backend/kernels/build.py with the system's C compiler, called through ctypes (which
 * releases the GIL). The call marches its rays on its own threads: Python threads woke too
 * late to share the few milliseconds of a chunk of rays.
 *
 * Layouts (row-major, contiguous): origins/directions [R, 3]; t_near/t_far [R]; skip and
 * occupied as bricks of 8³ bits (occupancy_bricks.h); volume [Nz, Ny, Nx] floats (grid_sample's
 * layout: x fastest), vertices at the box's corners (align_corners).
 */

#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <string.h>

#include "occupancy_bricks.h"
#include "step_lanes.h"

enum { ACTIVATION_SOFTPLUS = 0, ACTIVATION_LAPLACE = 1, ACTIVATION_NEUS = 2 };

typedef struct {
    float step;
    int64_t steps;          /* march intervals: u in [0, steps - 1) */
    int64_t span;           /* intervals a skip-grid lookup vouches for */
    int64_t cells[3];       /* Gx, Gy, Gz of skip and occupied */
    int64_t vertices[3];    /* Nx, Ny, Nz of the volume */
    float box_min[3];
    float box_max[3];
    int32_t activation;     /* ACTIVATION_* */
    float a, b;             /* softplus: sigma = a * softplus(v + b); laplace, neus: beta = a */
    float opaque_transmittance;
    float skipped_weight;   /* weight a ray may leave uncoloured */
} MarchSettings;

/* NaN goes to lo: a float cast to an integer must be in range (anything else is undefined). */
static inline float clampf(float v, float lo, float hi) { return !(v >= lo) ? lo : (v > hi ? hi : v); }

/* Whether the cell holding `units` (cell units, clamped to the grid; NaN to cell 0) is marked;
 * last[axis] = cells[axis] - 1 as a float. */
static inline int marked(const uint8_t *bricks, const float units[3], const int64_t cells[3], const float last[3]) {
    int64_t ijk[3];
    for (int axis = 0; axis < 3; ++axis)  /* clamped to the grid before the cast, NaN to 0 */
        ijk[axis] = (int64_t)clampf(units[axis], 0.0f, last[axis]);
    return brick_bit(bricks, ijk, cells);
}

static float activate(const MarchSettings *s, float v) {
    if (s->activation == ACTIVATION_SOFTPLUS) {
        float x = v + s->b;  /* softplus as PyTorch's (threshold 20: linear above) */
        /* Below -15, log1p(e^x) = e^x to within e^x / 2 (a relative 2e-7): one call, not two
         * (the faint reads around a surface, where the shift leaves most values). Below -5,
         * log1p(y) = y - y²/2 + y³/3 - y⁴/4 to within y⁵/5 (a relative 3e-10 at y = e^-5).
         * Above, log(1 + y): y >= e^-5 leaves 1 + y's rounding a relative 1e-5 of the result at
         * most, and glibc's logf took the march 0.93 times log1pf's time on lego. */
        if (x > 20.0f) return s->a * x;
        const float y = expf(x);
        if (x < -15.0f) return s->a * y;
        if (x < -5.0f) return s->a * (y * (1.0f - y * (0.5f - y * (1.0f / 3.0f - 0.25f * y))));
        return s->a * logf(1.0f + y);
    }
    float tail = 0.5f * expf(-fabsf(v) / s->a);
    return (v > 0.0f ? tail : 1.0f - tail) / s->a;
}

/* to_vertex[axis] = (vertices - 1) / (box_max - box_min): a multiplication a read, not a division. */
static float trilinear(const MarchSettings *s, const float *volume, const float p[3], const float to_vertex[3]) {
    float frac[3];
    int64_t lower[3];
    for (int axis = 0; axis < 3; ++axis) {
        int64_t n = s->vertices[axis];
        float x = (p[axis] - s->box_min[axis]) * to_vertex[axis];
        x = clampf(x, 0.0f, (float)(n - 1));
        int64_t i = (int64_t)floorf(x);
        if (i > n - 2) i = n - 2;
        lower[axis] = i;
        frac[axis] = x - (float)i;
    }
    const int64_t nx = s->vertices[0], ny = s->vertices[1];
    const float *c = volume + (lower[2] * ny + lower[1]) * nx + lower[0];
    const int64_t dy = nx, dz = nx * ny;
    float fx = frac[0], fy = frac[1], fz = frac[2];
    float c00 = c[0] + fx * (c[1] - c[0]);
    float c10 = c[dy] + fx * (c[dy + 1] - c[dy]);
    float c01 = c[dz] + fx * (c[dz + 1] - c[dz]);
    float c11 = c[dz + dy] + fx * (c[dz + dy + 1] - c[dz + dy]);
    float c0 = c00 + fy * (c10 - c00), c1 = c01 + fy * (c11 - c01);
    return c0 + fz * (c1 - c0);
}

static inline float softplusf(float x) { return x > 20.0f ? x : log1pf(expf(x)); }

/* The density of the sample at p on a ray along d: the activated volume there, or for NeuS's
 * opacity the step's -ln(Phi(s_out) / Phi(s_in)) / step, s read half a step before and after p
 * (surface_field.py's _step_density). */
static float density_at(const MarchSettings *s, const float *volume, const float p[3], const float d[3],
                        const float to_vertex[3]) {
    if (s->activation != ACTIVATION_NEUS) return activate(s, trilinear(s, volume, p, to_vertex));
    float in[3], out[3];
    for (int axis = 0; axis < 3; ++axis) {
        in[axis] = p[axis] - 0.5f * s->step * d[axis];
        out[axis] = p[axis] + 0.5f * s->step * d[axis];
    }
    const float optical = softplusf(-trilinear(s, volume, out, to_vertex) / s->a)
                          - softplusf(-trilinear(s, volume, in, to_vertex) / s->a);
    return optical > 0.0f ? optical / s->step : 0.0f;
}

typedef struct {
    const MarchSettings *s;
    const float *origins, *directions, *t_near, *t_far, *volume;
    const uint8_t *skip, *occupied;
    const int64_t *ray_index;     /* the rays to march (NULL: 0 .. count - 1) */
    int64_t count;
    int64_t next;                 /* the next block of ray_index to take (atomic) */
    float *transmittance, *depth, *skipped, *coloured;
    uint8_t *done;                /* 1 for each ray marched whole */
    int64_t region;               /* packed samples a thread may write */
    int64_t *sample_ray;
    float *sample_position, *sample_weight;
} MarchJob;

typedef struct {
    MarchJob *job;
    int64_t first;                /* the thread's region starts at this packed sample */
    int64_t written, looked_up, read;
    char padding[64];             /* each thread's counters on cache lines of their own */
} MarchThread;

/* A march's steps are looked up 8 at a time (step_lanes.h): their midpoints, whether they lie
 * in the grid, their cells' bricks and bits. One at a time, each step's lookup was a chain of
 * scalar operations and an unpredictable branch, about 40 % of lego's render march. */

typedef struct {
    float near, far, step;
    float start[3], along[3], cell_count[3], last_cell[3];
    int32_t bricks_y, bricks_z;  /* occupancy_bricks.h's By and Bz */
} RaySteps;

/* Bit j set where step first + j (j < lanes) lies in an occupied cell with a length above 0;
 * *ended is set where a step of length 0 (the ray's far end) is among them, *valid counts the
 * steps before it. */
static inline uint32_t occupied_steps(const RaySteps *f, const uint8_t *occupied, int64_t first, int32_t lanes,
                                      int *ended, int64_t *valid) {
    const step_lanes_i offsets = {0, 1, 2, 3, 4, 5, 6, 7};
    const step_lanes_f u = __builtin_convertvector((int32_t)first + offsets, step_lanes_f);
    const step_lanes_f far = step_splat(f->far), zero = step_splat(0.0f);
    step_lanes_f t_lo = f->near + u * f->step;
    t_lo = step_select(t_lo > far, far, t_lo);
    step_lanes_f t_hi = t_lo + f->step;
    t_hi = step_select(t_hi > far, far, t_hi);
    const step_lanes_f delta = t_hi - t_lo;
    const step_lanes_f t_mid = t_lo + 0.5f * delta;
    step_lanes_i keep = delta > 0.0f;
    step_lanes_i cell[3];
    for (int axis = 0; axis < 3; ++axis) {
        const step_lanes_f units = f->start[axis] + f->along[axis] * t_mid;
        keep &= (units >= 0.0f) & (units <= f->cell_count[axis]);
        const step_lanes_f last = step_splat(f->last_cell[axis]);
        const step_lanes_f clamped = step_select(units >= 0.0f, step_select(units > last, last, units), zero);
        cell[axis] = __builtin_convertvector(clamped, step_lanes_i);  /* NaN went to 0, as clampf's */
    }
    const step_lanes_i byte = ((((cell[0] >> 3) * f->bricks_y + (cell[1] >> 3)) * f->bricks_z + (cell[2] >> 3)) << 6)
                         + ((cell[0] & 7) << 3) + (cell[1] & 7);
    const step_lanes_i bit = cell[2] & 7;
    uint32_t found = 0;
    int64_t counted = 0;
    for (int j = 0; j < lanes; ++j) {
        if (!(delta[j] > 0.0f)) {
            *ended = 1;
            break;
        }
        ++counted;
        if (keep[j]) found |= (uint32_t)((occupied[byte[j]] >> bit[j]) & 1) << j;
    }
    *valid += counted;
#if defined(__AVX__)
    /* The upper halves cleared before the march calls expf and logf: left dirty (GCC put no
     * vzeroupper before those calls), lego's march took 3.2 times as long. */
    __builtin_ia32_vzeroupper();
#endif
    return found;
}

/* One ray into the thread's region; 0 if the region is full (nothing of the ray kept). */
static int march_ray(MarchJob *job, MarchThread *thread, int64_t r) {
    const MarchSettings *s = job->s;
    /* What every step reads, in locals: read through s, the compiler reloaded and converted
     * the grid's sizes at every step (a sample's int64_t store may alias s->cells). */
    float side[3], to_vertex[3], cell_count[3], last_cell[3];
    int64_t cells[3];
    for (int axis = 0; axis < 3; ++axis) {
        side[axis] = (s->box_max[axis] - s->box_min[axis]) / (float)s->cells[axis];
        to_vertex[axis] = (float)(s->vertices[axis] - 1) / (s->box_max[axis] - s->box_min[axis]);
        cells[axis] = s->cells[axis];
        cell_count[axis] = (float)cells[axis];
        last_cell[axis] = (float)(cells[axis] - 1);
    }
    const float step = s->step;
    const int64_t steps = s->steps, span = s->span;
    const uint8_t *skip = job->skip, *occupied = job->occupied;
    const int64_t spans = (steps - 1 + span - 1) / span;
    const int64_t end = thread->first + job->region, ray_start = thread->written;
    int64_t count = ray_start;
    const float *o = job->origins + 3 * r, *d = job->directions + 3 * r;
    const float near = job->t_near[r], far = job->t_far[r];
    float start[3], along[3];
    for (int axis = 0; axis < 3; ++axis) {
        start[axis] = (o[axis] - s->box_min[axis]) / side[axis];
        along[axis] = d[axis] / side[axis];
    }
    RaySteps frame = {near, far, step, {start[0], start[1], start[2]}, {along[0], along[1], along[2]},
                      {cell_count[0], cell_count[1], cell_count[2]}, {last_cell[0], last_cell[1], last_cell[2]},
                      (int32_t)((cells[1] + 7) >> 3), (int32_t)((cells[2] + 7) >> 3)};
    float transmittance = 1.0f, depth = 0.0f, skipped = 0.0f, coloured = 0.0f;
    int64_t looked_up = 0, read = 0;
    int stopped = 0;
    for (int64_t k = 0; k < spans && far > near && !stopped; ++k) {
        const float span_start = (float)(k * span) * step;
        if (!(span_start < far - near)) break;
        const float t_span = near + (span_start + 0.5f * (float)span * step);
        float units[3];
        for (int axis = 0; axis < 3; ++axis) units[axis] = start[axis] + along[axis] * t_span;
        if (!marked(skip, units, cells, last_cell)) continue;
        int64_t last = (k + 1) * span;
        if (last > steps - 1) last = steps - 1;
        int ended = 0;
        for (int64_t first = k * span; first < last && !ended && !stopped; first += STEP_LANES) {
          const int32_t lanes = last - first < STEP_LANES ? (int32_t)(last - first) : STEP_LANES;
          for (uint32_t found = occupied_steps(&frame, occupied, first, lanes, &ended, &looked_up); found;
               found &= found - 1) {
            const int64_t u = first + __builtin_ctz(found);
            float t_lo = near + (float)u * step;
            if (t_lo > far) t_lo = far;
            float t_hi = t_lo + step;
            if (t_hi > far) t_hi = far;
            const float delta = t_hi - t_lo;
            const float t_mid = t_lo + 0.5f * delta;
            float p[3];
            for (int axis = 0; axis < 3; ++axis) p[axis] = o[axis] + d[axis] * t_mid;
            const float sigma = density_at(s, job->volume, p, d, to_vertex);
            ++read;
            if (!(sigma > 0.0f)) continue;
            const float optical = sigma * delta;
            /* 1 - e^-x, its series where the difference would cancel (relative error x² / 6),
             * and there e^-x from it without a call (its error x³ / 6 is under float32's step). */
            float passed, absorbed;
            if (optical < 1e-3f) {
                absorbed = optical * (1.0f - 0.5f * optical);
                passed = 1.0f - absorbed;
            } else {
                passed = expf(-optical);
                absorbed = 1.0f - passed;
            }
            const float weight = transmittance * absorbed;
            if (weight < s->skipped_weight && skipped + weight <= s->skipped_weight) {
                skipped += weight;  /* the faintest: given the ray's mean colour at the end */
            } else {
                if (count >= end) return 0;  /* no room: the caller marches this ray again */
                job->sample_ray[count] = r;
                memcpy(job->sample_position + 3 * count, p, sizeof p);
                job->sample_weight[count] = weight;
                coloured += weight;
                ++count;
            }
            depth += weight * t_mid;
            transmittance *= passed;
            if (transmittance <= s->opaque_transmittance) { stopped = 1; break; }
          }
        }
    }
    job->transmittance[r] = transmittance;
    job->depth[r] = depth;
    job->skipped[r] = skipped;
    job->coloured[r] = coloured;
    job->done[r] = 1;
    thread->written = count;
    thread->looked_up += looked_up;
    thread->read += read;
    return 1;
}

enum { RAYS_PER_BLOCK = 64 };  /* taken at a time: neighbouring pixels share cache lines */

static void *march_rays(void *argument) {
    MarchThread *thread = argument;
    MarchJob *job = thread->job;
    for (;;) {
        const int64_t block = __atomic_fetch_add(&job->next, RAYS_PER_BLOCK, __ATOMIC_RELAXED);
        if (block >= job->count) return NULL;
        const int64_t end = block + RAYS_PER_BLOCK < job->count ? block + RAYS_PER_BLOCK : job->count;
        for (int64_t i = block; i < end; ++i)
            if (!march_ray(job, thread, job->ray_index ? job->ray_index[i] : i))
                return NULL;  /* region full: this thread stops, the others go on */
    }
}

/* core/cameras.py's camera_rays of pixel_centres: the rays of pixels first .. first + count - 1
 * (row-major, `width` a row) of a pinhole camera, camera[0..3] = fl_x, fl_y, cx, cy, then the
 * pose's rotation (row-major 3 × 3) and position: origins [count, 3] at the position,
 * directions [count, 3] of unit length. The same operations but for the rotation's sums (a
 * matrix product there), so within a float32 step or two of PyTorch's. */
void pixel_rays(const float camera[16], int64_t width, int64_t first, int64_t count, float *origins,
                float *directions) {
    const float *rotation = camera + 4, *position = camera + 13;
    for (int64_t i = 0; i < count; ++i) {
        const int64_t pixel = first + i;
        const float x = (float)(pixel % width) + 0.5f, y = (float)(pixel / width) + 0.5f;
        const float along[3] = {(x - camera[2]) / camera[0], -((y - camera[3]) / camera[1]), -1.0f};
        float world[3];
        for (int row = 0; row < 3; ++row)
            world[row] = rotation[3 * row] * along[0] + rotation[3 * row + 1] * along[1] + rotation[3 * row + 2] * along[2];
        const float length = sqrtf(world[0] * world[0] + world[1] * world[1] + world[2] * world[2]);
        for (int axis = 0; axis < 3; ++axis) {
            origins[3 * i + axis] = position[axis];
            directions[3 * i + axis] = world[axis] / length;
        }
    }
}

/* torch.minimum and torch.maximum: NaN wins. */
static inline float min_or_nan(float a, float b) { return a != a || b != b ? NAN : (a < b ? a : b); }
static inline float max_or_nan(float a, float b) { return a != a || b != b ? NAN : (a > b ? a : b); }

/* core/cameras.py's ray_box_intersection for `count` float32 rays [count, 3] through the box
 * box[0..2] - box[3..5], its operations in its order (the slab test, entry clamped at 0, a miss
 * at t_far = t_near, NaN kept), into t_near and t_far; with `narrow`, [t_near, t_far] as given
 * narrowed to the ray's stretch in the box instead (MarchedModel._within_field_box). Through
 * PyTorch the same took about twelve passes over [R, 3] tensors, 4-5 ms for 65 536 rays on this
 * project's 2 cores (its reductions over 3 values are slow), twice for each chunk a view renders. */
void rays_through_box(const float *origins, const float *directions, int64_t count, const float box[6],
                     float *t_near, float *t_far, int32_t narrow) {
    for (int64_t r = 0; r < count; ++r) {
        float entry = -INFINITY, exit_ = INFINITY;
        for (int axis = 0; axis < 3; ++axis) {
            const float d = directions[3 * r + axis], o = origins[3 * r + axis];
            /* An axis-parallel ray's component: a huge finite reciprocal, not inf (0 · inf is NaN). */
            const float inverse = 1.0f / (fabsf(d) < 1e-12f ? copysignf(1e-12f, d) : d);
            const float t0 = (box[axis] - o) * inverse, t1 = (box[3 + axis] - o) * inverse;
            entry = axis ? max_or_nan(entry, min_or_nan(t0, t1)) : min_or_nan(t0, t1);
            exit_ = axis ? min_or_nan(exit_, max_or_nan(t0, t1)) : max_or_nan(t0, t1);
        }
        entry = entry != entry ? entry : (entry < 0.0f ? 0.0f : entry);
        if (!(exit_ > entry)) exit_ = entry;
        if (narrow) {
            const float near = max_or_nan(t_near[r], entry);
            t_far[r] = max_or_nan(min_or_nan(t_far[r], exit_), near);
            t_near[r] = near;
        } else {
            t_near[r] = entry;
            t_far[r] = exit_;
        }
    }
}

/* Marches `count` rays (`ray_index`, or 0 .. count - 1 when NULL) on `threads` threads. Thread
 * t packs its samples from t·region on and returns how many in written[t]; a ray marched
 * whole gets done[r] = 1 and its per-ray outputs, the rest (a thread's region filled) are left
 * for another call with more room. counters[0] and [1] gain the fine steps looked up and the
 * density reads (for the profile). Returns the number of threads that failed to start (the
 * others take their rays). */
int64_t march_render(const MarchSettings *s, const float *origins, const float *directions, const float *t_near,
                     const float *t_far, const uint8_t *skip, const uint8_t *occupied, const float *volume,
                     const int64_t *ray_index, int64_t count, int64_t threads, float *transmittance_out,
                     float *depth_out, float *skipped_out, float *coloured_out, uint8_t *done, int64_t region,
                     int64_t *sample_ray, float *sample_position, float *sample_weight, int64_t *written,
                     int64_t *counters) {
    MarchJob job = {s, origins, directions, t_near, t_far, volume, skip, occupied, ray_index, count, 0,
                    transmittance_out, depth_out, skipped_out, coloured_out, done, region,
                    sample_ray, sample_position, sample_weight};
    enum { MAX_THREADS = 256 };
    MarchThread state[MAX_THREADS];
    pthread_t handles[MAX_THREADS];
    int started[MAX_THREADS];
    if (threads < 1) threads = 1;
    if (threads > MAX_THREADS) threads = MAX_THREADS;
    int64_t failed = 0;
    for (int64_t t = 0; t < threads; ++t) {
        state[t] = (MarchThread){&job, t * region, t * region, 0, 0, {0}};
        /* The calling thread takes the last share itself. */
        started[t] = t + 1 < threads && pthread_create(&handles[t], NULL, march_rays, &state[t]) == 0;
        if (t + 1 < threads && !started[t]) ++failed;
    }
    march_rays(&state[threads - 1]);
    for (int64_t t = 0; t < threads; ++t) {
        if (started[t]) pthread_join(handles[t], NULL);
        written[t] = state[t].written - state[t].first;
        counters[0] += state[t].looked_up;
        counters[1] += state[t].read;
    }
    return failed;
}
