#ifndef GRID_COMMON_H
#define GRID_COMMON_H
/* What the grid kernels share (vm_grid.c, sparse_grid.c): the linear read along one axis and
 * running a function on several POSIX threads (distance_transform.c's passes too). build.py
 * hashes the headers with each kernel. */

#include <math.h>
#include <pthread.h>
#include <sched.h>
#include <stddef.h>
#include <stdint.h>
#include <time.h>

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

/* Waits of a few microseconds between spins on a shared word. */
#if defined(__x86_64__) || defined(__i386__)
#define CPU_RELAX() __builtin_ia32_pause()
#elif defined(__aarch64__)
#define CPU_RELAX() __asm__ __volatile__("yield")
#else
#define CPU_RELAX() ((void)0)
#endif

/* How long a kept worker spins for its next job before it sleeps. A training step calls the
 * kernels every 0.1-2 ms with Python in between: a worker that slept would be woken through the
 * kernel each time (tens of microseconds, measured), one that spins this long is there at once;
 * longer spins cost the caller's core on the render's longer gaps (docs/benchmarks_lego.md). */
#define POOL_SPIN_NS 500000

static inline int64_t monotonic_ns(void) {
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return (int64_t)now.tv_sec * 1000000000 + now.tv_nsec;
}

/* Spins until (*word == value) is `equal`, or POOL_SPIN_NS pass; returns whether it came true. */
static inline int spin_until(const int64_t *word, int64_t value, int equal) {
    const int64_t until = monotonic_ns() + POOL_SPIN_NS;
    for (;;) {
        for (int i = 0; i < 64; ++i) {
            if ((__atomic_load_n(word, __ATOMIC_ACQUIRE) == value) == equal) return 1;
            CPU_RELAX();
        }
        if (monotonic_ns() > until) return 0;
        sched_yield();
    }
}

/* Workers kept between calls of run_all (one pool per library): starting threads for each call
 * cost 27-47 us on 2 cores, more than some of a training step's kernels take. Worker w runs
 * item w of each job that has more than w items. `generation` counts the jobs; `unfinished`
 * the workers that have not yet answered the current one: every worker answers every job, so
 * none can still be reading a job's fields when the next job writes them. */
typedef struct {
    pthread_mutex_t busy; /* held by the caller whose job the pool runs */
    pthread_mutex_t lock; /* with the two conditions, for sleeping workers and caller */
    pthread_cond_t job_posted, job_done;
    int64_t generation, unfinished, workers;
    void *(*fn)(void *);
    char *items;
    size_t size;
    int64_t threads;
} WorkerPool;

static WorkerPool worker_pool = {PTHREAD_MUTEX_INITIALIZER, PTHREAD_MUTEX_INITIALIZER,
                                 PTHREAD_COND_INITIALIZER, PTHREAD_COND_INITIALIZER, 0, 0, 0, NULL,
                                 NULL, 0, 0};
/* The generation each worker was started at: the job it was started for is new to it. */
static int64_t worker_first_generation[MAX_THREADS];
static pthread_once_t worker_pool_fork_once = PTHREAD_ONCE_INIT;

static void *pool_worker(void *argument) {
    const int64_t index = (int64_t)(intptr_t)argument;
    WorkerPool *pool = &worker_pool;
    int64_t seen = worker_first_generation[index];
    for (;;) {
        if (!spin_until(&pool->generation, seen, 0)) {
            pthread_mutex_lock(&pool->lock);
            while (__atomic_load_n(&pool->generation, __ATOMIC_ACQUIRE) == seen)
                pthread_cond_wait(&pool->job_posted, &pool->lock);
            pthread_mutex_unlock(&pool->lock);
        }
        seen = __atomic_load_n(&pool->generation, __ATOMIC_ACQUIRE);
        if (index < pool->threads) pool->fn(pool->items + index * pool->size);
        if (__atomic_sub_fetch(&pool->unfinished, 1, __ATOMIC_ACQ_REL) == 0) {
            pthread_mutex_lock(&pool->lock);
            pthread_cond_signal(&pool->job_done);
            pthread_mutex_unlock(&pool->lock);
        }
    }
    return NULL;
}

/* A forked child has none of the parent's workers. */
static void worker_pool_after_fork(void) {
    WorkerPool *pool = &worker_pool;
    pthread_mutex_init(&pool->busy, NULL);
    pthread_mutex_init(&pool->lock, NULL);
    pthread_cond_init(&pool->job_posted, NULL);
    pthread_cond_init(&pool->job_done, NULL);
    pool->workers = 0;
    pool->unfinished = 0;
}

static void worker_pool_register_fork(void) { pthread_atfork(NULL, NULL, worker_pool_after_fork); }

/* Runs fn on each of `threads` work items (`size` bytes apart from `work`): the first on the
 * calling thread, the others on the pool's workers, or on new threads while another caller has
 * the pool; an item no thread could be started for runs here. */
static inline void run_all_on_new_threads(void *(*fn)(void *), char *items, size_t size, int64_t threads) {
    pthread_t handles[MAX_THREADS];
    int started[MAX_THREADS] = {0};
    for (int64_t t = 1; t < threads; ++t)
        started[t] = pthread_create(&handles[t], NULL, fn, items + t * size) == 0;
    fn(items);
    for (int64_t t = 1; t < threads; ++t) {
        if (started[t]) pthread_join(handles[t], NULL);
        else fn(items + t * size);
    }
}

static inline void run_all(void *(*fn)(void *), void *work, size_t size, int64_t threads) {
    char *items = (char *)work;
    WorkerPool *pool = &worker_pool;
    if (threads <= 1) {
        fn(items);
        return;
    }
    if (pthread_mutex_trylock(&pool->busy) != 0) {
        run_all_on_new_threads(fn, items, size, threads);
        return;
    }
    pthread_once(&worker_pool_fork_once, worker_pool_register_fork);
    while (pool->workers + 1 < threads) {
        const int64_t index = pool->workers + 1;
        pthread_t handle;
        worker_first_generation[index] = pool->generation;
        if (pthread_create(&handle, NULL, pool_worker, (void *)(intptr_t)index) != 0) break;
        pthread_detach(handle);
        pool->workers = index;
    }
    const int64_t pooled = threads - 1 < pool->workers ? threads - 1 : pool->workers;
    pool->fn = fn;
    pool->items = items;
    pool->size = size;
    pool->threads = pooled + 1;
    __atomic_store_n(&pool->unfinished, pool->workers, __ATOMIC_RELEASE);
    pthread_mutex_lock(&pool->lock);
    __atomic_add_fetch(&pool->generation, 1, __ATOMIC_ACQ_REL);
    pthread_cond_broadcast(&pool->job_posted);
    pthread_mutex_unlock(&pool->lock);
    fn(items);
    for (int64_t t = pooled + 1; t < threads; ++t) fn(items + t * size);
    if (!spin_until(&pool->unfinished, 0, 1)) {
        pthread_mutex_lock(&pool->lock);
        while (__atomic_load_n(&pool->unfinished, __ATOMIC_ACQUIRE) != 0)
            pthread_cond_wait(&pool->job_done, &pool->lock);
        pthread_mutex_unlock(&pool->lock);
    }
    pthread_mutex_unlock(&pool->busy);
}

#endif
