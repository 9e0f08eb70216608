#ifndef STEP_LANES_H
#define STEP_LANES_H
/* A march's steps looked up 8 at a time, in GCC's and Clang's vector extension (AVX2 on x86,
 * two 4-float halves at x86-64's SSE, NEON pairs on ARM): the vectors and the two operations
 * the render march (march_render.c's occupied_steps) and the training march (train_march.h's
 * occupied_train_steps) build their lookups from. Each lookup does the same float operations as
 * one step at a time (-std=c99 contracts none into FMAs), so the same steps are found. */

#include <stdint.h>

#define STEP_LANES 8
typedef float step_lanes_f __attribute__((vector_size(STEP_LANES * sizeof(float))));
typedef int32_t step_lanes_i __attribute__((vector_size(STEP_LANES * sizeof(int32_t))));

/* a where take's lane is all ones, else b (take: a comparison's result). */
static inline step_lanes_f step_select(step_lanes_i take, step_lanes_f a, step_lanes_f b) {
    return (step_lanes_f)((take & (step_lanes_i)a) | (~take & (step_lanes_i)b));
}

static inline step_lanes_f step_splat(float x) {
    const step_lanes_f v = {x, x, x, x, x, x, x, x};
    return v;
}

#endif
