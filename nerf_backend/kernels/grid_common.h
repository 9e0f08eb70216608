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

/* A pause between a spinning thread's reads of a shared word (spares the core's other thread). */
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

/* Spins until *word is 0 or POOL_SPIN_NS pass; returns whether it came to 0. */
static inline int spin_until_zero(const int64_t *word) {
    const int64_t until = monotonic_ns() + POOL_SPIN_NS;
    for (;;) {
        for (int i = 0; i < 64; ++i) {
            if (__atomic_load_n(word, __ATOMIC_ACQUIRE) == 0) return 1;
            CPU_RELAX();
        }
        if (monotonic_ns() > until) return 0;
        sched_yield();
    }
}

/* One call of run_all as the workers read it: item 0 is the caller's, worker w runs item w
 * where w < threads. */
typedef struct {
    void *(*fn)(void *);
    char *items;
    size_t size;
    int64_t threads;
} PoolJob;

/* Workers kept between calls of run_all (one pool per library): starting threads for each call
 * cost 27-47 us on 2 cores, more than some of a training step's kernels take. `generation`
 * counts the jobs; job g lies in jobs[g % 2], and a worker that found g reads it there and then
 * reads the generation again, so that a worker late to a job it has no item in (nobody waits
 * for it) never takes the next job's fields, which are written to the other slot, for g's.
 * Only a job's own workers are woken, and the caller waits for them alone: on a machine of
 * many cores a job of two items costs one worker, not all of them. A worker spins
 * POOL_SPIN_NS after each job it ran, then sleeps on its own condition variable. */
typedef struct {
    pthread_mutex_t busy; /* held by the caller whose job the pool runs */
    pthread_mutex_t lock; /* with the conditions: sleeping workers and the waiting caller */
    pthread_cond_t job_done;
    pthread_cond_t wake[MAX_THREADS];
    int64_t generation, unfinished, workers;
    PoolJob jobs[2];
} WorkerPool;

/* Its wake conditions are initialised at the first job (worker_pool_start). */
static WorkerPool worker_pool = {.busy = PTHREAD_MUTEX_INITIALIZER, .lock = PTHREAD_MUTEX_INITIALIZER,
                                 .job_done = PTHREAD_COND_INITIALIZER};
/* The generation each worker was started at: the job it was started for is new to it. */
static int64_t worker_first_generation[MAX_THREADS];
static pthread_once_t worker_pool_once = PTHREAD_ONCE_INIT;

/* The next job's generation after `seen`: spun for until `spin_until` (ns), then slept for. */
static int64_t pool_next_generation(WorkerPool *pool, int64_t index, int64_t seen, int64_t spin_until) {
    int64_t generation;
    for (;;) {
        for (int i = 0; i < 64; ++i) {
            if ((generation = __atomic_load_n(&pool->generation, __ATOMIC_ACQUIRE)) != seen) return generation;
            CPU_RELAX();
        }
        if (monotonic_ns() > spin_until) break;
        sched_yield();
    }
    pthread_mutex_lock(&pool->lock);
    while ((generation = __atomic_load_n(&pool->generation, __ATOMIC_ACQUIRE)) == seen)
        pthread_cond_wait(&pool->wake[index], &pool->lock);
    pthread_mutex_unlock(&pool->lock);
    return generation;
}

static void *pool_worker(void *argument) {
    const int64_t index = (int64_t)(intptr_t)argument;
    WorkerPool *pool = &worker_pool;
    int64_t seen = worker_first_generation[index], spin_until = 0;
    for (;;) {
        const int64_t generation = pool_next_generation(pool, index, seen, spin_until);
        const PoolJob job = pool->jobs[generation & 1];
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        if (__atomic_load_n(&pool->generation, __ATOMIC_RELAXED) != generation) continue;  /* late: read again */
        seen = generation;
        if (index >= job.threads) continue;
        job.fn(job.items + index * job.size);
        if (__atomic_sub_fetch(&pool->unfinished, 1, __ATOMIC_ACQ_REL) == 0) {
            pthread_mutex_lock(&pool->lock);
            pthread_cond_signal(&pool->job_done);
            pthread_mutex_unlock(&pool->lock);
        }
        spin_until = monotonic_ns() + POOL_SPIN_NS;
    }
    return NULL;
}

/* A forked child has none of the parent's workers. */
static void worker_pool_after_fork(void) {
    WorkerPool *pool = &worker_pool;
    pthread_mutex_init(&pool->busy, NULL);
    pthread_mutex_init(&pool->lock, NULL);
    pthread_cond_init(&pool->job_done, NULL);
    for (int w = 0; w < MAX_THREADS; ++w) pthread_cond_init(&pool->wake[w], NULL);
    pool->workers = 0;
    pool->unfinished = 0;
}

static void worker_pool_start(void) {
    for (int w = 0; w < MAX_THREADS; ++w) pthread_cond_init(&worker_pool.wake[w], NULL);
    pthread_atfork(NULL, NULL, worker_pool_after_fork);
}

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
    pthread_once(&worker_pool_once, worker_pool_start);
    while (pool->workers + 1 < threads) {
        const int64_t index = pool->workers + 1;
        pthread_t handle;
        worker_first_generation[index] = pool->generation;
        if (pthread_create(&handle, NULL, pool_worker, (void *)(intptr_t)index) != 0) break;
        pthread_detach(handle);
        pool->workers = index;
    }
    const int64_t pooled = threads - 1 < pool->workers ? threads - 1 : pool->workers;
    const int64_t generation = pool->generation + 1;
    /* The slot is written after every earlier store (the last generation's among them) is seen. */
    __atomic_thread_fence(__ATOMIC_SEQ_CST);
    PoolJob *job = &pool->jobs[generation & 1];
    job->fn = fn;
    job->items = items;
    job->size = size;
    job->threads = pooled + 1;
    __atomic_store_n(&pool->unfinished, pooled, __ATOMIC_RELAXED);
    pthread_mutex_lock(&pool->lock);
    __atomic_store_n(&pool->generation, generation, __ATOMIC_RELEASE);
    for (int64_t w = 1; w <= pooled; ++w) pthread_cond_signal(&pool->wake[w]);
    pthread_mutex_unlock(&pool->lock);
    fn(items);
    for (int64_t t = pooled + 1; t < threads; ++t) fn(items + t * size);
    if (!spin_until_zero(&pool->unfinished)) {
        pthread_mutex_lock(&pool->lock);
        while (__atomic_load_n(&pool->unfinished, __ATOMIC_ACQUIRE) != 0)
            pthread_cond_wait(&pool->job_done, &pool->lock);
        pthread_mutex_unlock(&pool->lock);
    }
    pthread_mutex_unlock(&pool->busy);
}

#endif
