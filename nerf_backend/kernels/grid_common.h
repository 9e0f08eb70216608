#ifndef GRID_COMMON_H
#define GRID_COMMON_H
/* What the grid kernels share (vm_grid.c, sparse_grid.c): the linear read along one axis and
 * running a function on several POSIX threads (distance_transform.c's passes too). build.py
 * hashes the headers with each kernel. */

#include <math.h>
#include <pthread.h>
#include <stddef.h>
#include <stdint.h>

#define MAX_THREADS 64

typedef struct {
    float low_weight, high_weight;
    int64_t lower;
} AxisCorner;

/* The lower of the two vertices read around coordinate x in [-1, 1] on an axis of n vertices
 * (kept inside the grid) and the hat weights of both: linear inside, fading to 0 within a cell
 * outside the grid (grid_sample's zero padding). NaN reads nothing. */
static inline AxisCorner axis_corner(float x, int64_t n) {
    AxisCorner corner = {0.0f, 0.0f, 0};
    float position = (x + 1.0f) * (0.5f * (float)(n - 1));
    if (!(position == position)) return corner;
    float lower = floorf(position);
    if (!(lower >= 0.0f)) lower = 0.0f;
    if (lower > (float)(n - 2)) lower = (float)(n - 2);
    const float from_lower = position - lower;
    corner.lower = (int64_t)lower;
    const float low = 1.0f - fabsf(from_lower), high = 1.0f - fabsf(from_lower - 1.0f);
    corner.low_weight = low > 0.0f ? low : 0.0f;
    corner.high_weight = high > 0.0f ? high : 0.0f;
    return corner;
}

static inline int64_t clamp_threads(int64_t threads, int64_t most) {
    if (threads > most) threads = most;
    if (threads > MAX_THREADS) threads = MAX_THREADS;
    return threads < 1 ? 1 : threads;
}

/* Runs fn on each of `threads` work items (`size` bytes apart from `work`): the first on the
 * calling thread, the others on new threads; a thread that cannot be started runs its share
 * here. */
static inline void run_all(void *(*fn)(void *), void *work, size_t size, int64_t threads) {
    pthread_t handles[MAX_THREADS];
    int started[MAX_THREADS] = {0};
    char *items = (char *)work;
    for (int64_t t = 1; t < threads; ++t)
        started[t] = pthread_create(&handles[t], NULL, fn, items + t * size) == 0;
    fn(items);
    for (int64_t t = 1; t < threads; ++t) {
        if (started[t]) pthread_join(handles[t], NULL);
        else fn(items + t * size);
    }
}

#endif
