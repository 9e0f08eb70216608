/* The exact Euclidean distance transform of a 3-D mask (field_components/distance_transform.py):
 * at each cell where the mask is set, the distance in cells (between cell centres) to the
 * nearest cell where it is not; 0 there, INFINITY everywhere when no cell is unset.
 *
 * Felzenszwalb and Huttenlocher's separable transform: the squared distance along z (0 or
 * INFINITY), then along y and along x the lower envelope of the parabolas (q - i)² + f(i) of
 * the line's finite values, each pass over whole lines split between threads. Squared distances
 * are integers up to 2^24 for any grid under 2 365 cells a side, so float holds them exactly;
 * the envelope's crossings are computed in double. scipy's distance_transform_edt (the
 * fallback) computes the same distances and their nearest cells besides, on one thread: about
 * five times as long for a 256³ prior. */

#include <stdlib.h>

#include "grid_common.h"

typedef struct {
    float *values;            /* [nx][ny][nz], transformed in place along `axis` */
    int64_t sizes[3];
    int axis;                 /* 1: y, 2: x (z is the first pass, from the mask) */
    const uint8_t *mask;      /* the first pass only */
    int64_t first_line, end_line;
    int failed;
} Job;

/* The lower envelope of the parabolas of f[0 .. n) (INFINITY: none), written to out. */
static void envelope(const float *f, float *out, int64_t n, int64_t *site, double *bound) {
    int64_t k = -1;
    for (int64_t q = 0; q < n; ++q) {
        if (!(f[q] < INFINITY)) continue;
        double crossing = -INFINITY;
        while (k >= 0) {
            int64_t p = site[k];
            crossing = ((f[q] + (double)q * q) - (f[p] + (double)p * p)) / (2.0 * (double)(q - p));
            if (crossing > bound[k]) break;
            --k;
        }
        ++k;
        site[k] = q;
        bound[k] = k == 0 ? -INFINITY : crossing;
    }
    if (k < 0) {
        for (int64_t q = 0; q < n; ++q) out[q] = INFINITY;
        return;
    }
    int64_t j = 0;
    for (int64_t q = 0; q < n; ++q) {
        while (j < k && bound[j + 1] < (double)q) ++j;
        double d = (double)(q - site[j]);
        out[q] = (float)(d * d + f[site[j]]);
    }
}

static void *work(void *argument) {
    Job *job = argument;
    int64_t nx = job->sizes[0], ny = job->sizes[1], nz = job->sizes[2];
    if (job->axis == 0) { /* along z, from the mask: 0 where unset, INFINITY where set */
        for (int64_t line = job->first_line; line < job->end_line; ++line) {
            const uint8_t *m = job->mask + line * nz;
            float *v = job->values + line * nz;
            float last = INFINITY;
            for (int64_t z = 0; z < nz; ++z) {
                last = m[z] ? (last < INFINITY ? last + 1.0f : INFINITY) : 0.0f;
                v[z] = last;
            }
            last = INFINITY;
            for (int64_t z = nz - 1; z >= 0; --z) {
                last = m[z] ? (last < INFINITY ? last + 1.0f : INFINITY) : 0.0f;
                if (last < v[z]) v[z] = last;
            }
            for (int64_t z = 0; z < nz; ++z) v[z] = v[z] * v[z];
        }
        return 0;
    }
    int64_t n = job->axis == 1 ? ny : nx;
    int64_t stride = job->axis == 1 ? nz : ny * nz;
    float *f = malloc(sizeof(float) * n), *out = malloc(sizeof(float) * n);
    int64_t *site = malloc(sizeof(int64_t) * n);
    double *bound = malloc(sizeof(double) * n);
    if (!f || !out || !site || !bound) {
        job->failed = 1;
    } else {
        for (int64_t line = job->first_line; line < job->end_line; ++line) {
            /* Lines along y: (x, z) = (line / nz, line % nz); along x: (y, z) = (line / nz, line % nz). */
            int64_t outer = line / nz, z = line % nz;
            float *start = job->values + (job->axis == 1 ? outer * ny * nz : outer * nz) + z;
            for (int64_t i = 0; i < n; ++i) f[i] = start[i * stride];
            envelope(f, out, n, site, bound);
            for (int64_t i = 0; i < n; ++i) start[i * stride] = out[i];
        }
    }
    free(f); free(out); free(site); free(bound);
    return 0;
}

/* One pass over `lines` lines, shared out between the jobs; whether a job lacked scratch memory. */
static int run_pass(Job *jobs, int64_t threads, int64_t lines) {
    for (int64_t i = 0; i < threads; ++i) {
        jobs[i].first_line = lines * i / threads;
        jobs[i].end_line = lines * (i + 1) / threads;
        jobs[i].failed = 0;
    }
    run_all(work, jobs, sizeof(Job), threads);
    int failed = 0;
    for (int64_t i = 0; i < threads; ++i) failed |= jobs[i].failed;
    return failed;
}

/* The distances of `mask` [nx][ny][nz] (non-zero: set) into `out` (same shape) on `threads`
 * threads; 0 on success, 1 where scratch memory could not be had. */
int distance_transform(const uint8_t *mask, int64_t nx, int64_t ny, int64_t nz, float *out, int64_t threads) {
    threads = clamp_threads(threads, MAX_THREADS);
    Job jobs[MAX_THREADS];
    for (int64_t i = 0; i < threads; ++i) {
        jobs[i] = (Job){out, {nx, ny, nz}, 0, mask, 0, 0, 0};
    }
    if (run_pass(jobs, threads, nx * ny)) return 1;
    for (int64_t i = 0; i < threads; ++i) jobs[i].axis = 1;
    if (run_pass(jobs, threads, nx * nz)) return 1;
    for (int64_t i = 0; i < threads; ++i) jobs[i].axis = 2;
    if (run_pass(jobs, threads, ny * nz)) return 1;
    int64_t cells = nx * ny * nz;
    for (int64_t i = 0; i < cells; ++i) out[i] = sqrtf(out[i]);
    return 0;
}
