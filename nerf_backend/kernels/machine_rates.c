/* What bench-step measures this machine's random reads by (nerf_backend/bench/hardware.py):
 * rows of a table gathered at random, one 64-byte cache line a row, by every thread at once and
 * with many lines in flight (each asked of memory GATHER_AHEAD rows before it is read), as the
 * compiled kernels read a grid. PyTorch's index_select copies each row through a general loop:
 * on the machines here it reached a fifth of the rate below, so a reference made from it was
 * no lower bound.
 *
 * Plain C and POSIX threads, built by nerf_backend/kernels/build.py and called through ctypes. */

#include <pthread.h>
#include <stdint.h>
#include <string.h>

#include "grid_common.h"

#define ROW_FLOATS 16
#define GATHER_AHEAD 16

typedef struct {
    const float *table;
    const int64_t *index;
    int64_t begin, end;
    float sum[ROW_FLOATS];  /* what was read, so that no read can be left out */
} GatherWork;

static void *gather_work(void *arg) {
    GatherWork *w = (GatherWork *)arg;
    float sum[ROW_FLOATS] = {0};
    for (int64_t i = w->begin; i < w->end; ++i) {
        if (i + GATHER_AHEAD < w->end) __builtin_prefetch(w->table + w->index[i + GATHER_AHEAD] * ROW_FLOATS, 0, 0);
        const float *row = w->table + w->index[i] * ROW_FLOATS;
        for (int k = 0; k < ROW_FLOATS; ++k) sum[k] += row[k];
    }
    memcpy(w->sum, sum, sizeof sum);
    return NULL;
}

/* Reads the rows index[0 .. count) of `table` (rows of 16 floats) on `threads` threads and
 * returns the sum of their first values (the caller discards it). */
float gather_lines(const float *table, const int64_t *index, int64_t count, int64_t threads) {
    threads = clamp_threads(threads, (count + 4095) / 4096);
    GatherWork work[MAX_THREADS];
    for (int64_t t = 0; t < threads; ++t) {
        work[t].table = table;
        work[t].index = index;
        work[t].begin = count * t / threads;
        work[t].end = count * (t + 1) / threads;
    }
    run_all(gather_work, work, sizeof work[0], threads);
    float total = 0.0f;
    for (int64_t t = 0; t < threads; ++t) total += work[t].sum[0];
    return total;
}
