/* Each ray's nearest crossing of a triangle mesh, through a bounding volume hierarchy, and the
 * paths of rays through glass (model_components/glass.py: the same optics as its torch code,
 * which tests/test_glass.py holds this to; the BVH is built in core/refraction.py).
 *
 * Nodes: lo, hi [N][3] bounds; child [N][2]: an inner node's two children, or for a leaf
 * (-(first + 1), count): its triangles tri[first .. first + count) ([T][9]: three corners).
 * Out: t (INFINITY where none), the crossed triangle's index in tri (-1 there), and the
 * crossing's barycentric u, v (the weights of the second and third corners). Möller-Trumbore,
 * both sides of a triangle count; only crossings beyond t_min. */

#include <math.h>
#include <pthread.h>
#include <stdint.h>

#define STACK_DEPTH 64

typedef struct {
    const float *origins, *directions, *lo, *hi, *tri;
    const int32_t *child;
    float t_min;
    float *t_out, *uv_out;
    int32_t *face_out;
    int64_t begin, end;
} Job;

/* The nearest crossing beyond t_min of the ray o + t d: its t (INFINITY: none), triangle and u, v. */
static float crossing(const Job *job, const float *o, const float *d, float t_min, int32_t *face_out, float *u_out,
                      float *v_out) {
    float inv[3];
    for (int a = 0; a < 3; ++a) inv[a] = 1.0f / (fabsf(d[a]) < 1e-30f ? copysignf(1e-30f, d[a]) : d[a]);
    float best = INFINITY, best_u = 0.0f, best_v = 0.0f;
    int32_t best_face = -1;
    int32_t stack[STACK_DEPTH];
    int depth = 0;
    stack[depth++] = 0;
    while (depth > 0) {
        int32_t n = stack[--depth];
        float near = t_min, far = best;
        for (int a = 0; a < 3; ++a) {
            float t0 = (job->lo[3 * n + a] - o[a]) * inv[a], t1 = (job->hi[3 * n + a] - o[a]) * inv[a];
            if (t0 > t1) { float s = t0; t0 = t1; t1 = s; }
            near = t0 > near ? t0 : near;
            far = t1 < far ? t1 : far;
        }
        if (near > far) continue;
        int32_t first = job->child[2 * n], second = job->child[2 * n + 1];
        if (first >= 0) {
            if (depth + 2 > STACK_DEPTH) continue; /* deeper than any BVH core/refraction.py builds */
            stack[depth++] = second;
            stack[depth++] = first;
            continue;
        }
        for (int32_t k = -first - 1, stop = -first - 1 + second; k < stop; ++k) {
            const float *v = job->tri + 9 * (int64_t)k;
            float e1[3] = {v[3] - v[0], v[4] - v[1], v[5] - v[2]};
            float e2[3] = {v[6] - v[0], v[7] - v[1], v[8] - v[2]};
            float p[3] = {d[1] * e2[2] - d[2] * e2[1], d[2] * e2[0] - d[0] * e2[2], d[0] * e2[1] - d[1] * e2[0]};
            float det = e1[0] * p[0] + e1[1] * p[1] + e1[2] * p[2];
            if (fabsf(det) < 1e-20f) continue;
            float inverse = 1.0f / det;
            float s[3] = {o[0] - v[0], o[1] - v[1], o[2] - v[2]};
            float u = (s[0] * p[0] + s[1] * p[1] + s[2] * p[2]) * inverse;
            if (u < 0.0f || u > 1.0f) continue;
            float q[3] = {s[1] * e1[2] - s[2] * e1[1], s[2] * e1[0] - s[0] * e1[2], s[0] * e1[1] - s[1] * e1[0]};
            float w = (d[0] * q[0] + d[1] * q[1] + d[2] * q[2]) * inverse;
            if (w < 0.0f || u + w > 1.0f) continue;
            float t = (e2[0] * q[0] + e2[1] * q[1] + e2[2] * q[2]) * inverse;
            if (t > t_min && t < best) {
                best = t;
                best_face = k;
                best_u = u;
                best_v = w;
            }
        }
    }
    *face_out = best_face;
    *u_out = best_u;
    *v_out = best_v;
    return best;
}

static void nearest(const Job *job, int64_t r) {
    job->t_out[r] = crossing(job, job->origins + 3 * r, job->directions + 3 * r, job->t_min, job->face_out + r,
                             job->uv_out + 2 * r, job->uv_out + 2 * r + 1);
}

static float dot3(const float *a, const float *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

static void normalise(float *a) {
    float length = sqrtf(dot3(a, a));
    float scale = length > 1e-30f ? 1.0f / length : 0.0f;
    for (int k = 0; k < 3; ++k) a[k] *= scale;
}

/* The smooth normal at a crossing: its triangle's corner normals weighted by (1 - u - v, u, v). */
static void smooth_normal(const float *normals, int32_t face, float u, float v, float n[3]) {
    const float *c = normals + 9 * (int64_t)face;
    for (int k = 0; k < 3; ++k) n[k] = (1.0f - u - v) * c[k] + u * c[3 + k] + v * c[6 + k];
    normalise(n);
}

/* Snell's law from index n1 into n2 (eta = n1 / n2), either side of the surface; returns 1 and
 * the mirror direction where the light is totally reflected. core/refraction.py's refract. */
static int refract3(const float d[3], const float normal[3], float eta, float out[3]) {
    float n[3] = {normal[0], normal[1], normal[2]};
    if (dot3(d, n) > 0.0f) for (int k = 0; k < 3; ++k) n[k] = -n[k];
    float cos_i = -dot3(d, n);
    float sin2_t = eta * eta * fmaxf(0.0f, 1.0f - cos_i * cos_i);
    int total = sin2_t >= 1.0f;
    if (total) {
        for (int k = 0; k < 3; ++k) out[k] = d[k] + 2.0f * cos_i * n[k];
    } else {
        float cos_t = sqrtf(fmaxf(0.0f, 1.0f - sin2_t));
        for (int k = 0; k < 3; ++k) out[k] = eta * d[k] + (eta * cos_i - cos_t) * n[k];
    }
    normalise(out);
    return total;
}

/* core/refraction.py's fresnel_reflectance. */
static float fresnel(const float d[3], const float n[3], float eta) {
    float cos_i = fminf(fabsf(dot3(d, n)), 1.0f);
    float sin2_t = eta * eta * (1.0f - cos_i * cos_i);
    if (sin2_t >= 1.0f) return 1.0f;
    float cos_t = sqrtf(fmaxf(0.0f, 1.0f - sin2_t));
    float rs = (eta * cos_i - cos_t) / fmaxf(eta * cos_i + cos_t, 1e-12f);
    float rp = (eta * cos_t - cos_i) / fmaxf(eta * cos_t + cos_i, 1e-12f);
    return 0.5f * (rs * rs + rp * rp);
}

typedef struct {
    Job walk;
    const float *normals, *ior;
    float offset;
    int32_t crossings;
    uint8_t *met;
    int32_t *entry_face;
    float *t_entry, *fresnel_out, *leave, *reflected; /* leave, reflected: [R][6] origin then direction */
} PathJob;

/* GlassSurfaces.trace's path of one ray: entry, Fresnel's share, the mirror ray, and where and
 * along which direction it leaves the glass (total internal reflection followed up to
 * `crossings` times; an open mesh lets it through unbent). */
static void path(const PathJob *job, int64_t r) {
    const float *o = job->walk.origins + 3 * r, *d = job->walk.directions + 3 * r;
    int32_t face;
    float u, v, n[3];
    float t = crossing(&job->walk, o, d, 0.0f, &face, &u, &v);
    job->met[r] = isfinite(t) ? 1 : 0;
    if (!job->met[r]) return;
    float entry[3] = {o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]};
    job->entry_face[r] = face;
    smooth_normal(job->normals, face, u, v, n);
    float eta = 1.0f / job->ior[face], off = job->offset;
    job->t_entry[r] = t;
    job->fresnel_out[r] = fresnel(d, n, eta);
    float mirror[3], along[3], at[3] = {entry[0], entry[1], entry[2]};
    float dn = dot3(d, n);
    for (int k = 0; k < 3; ++k) mirror[k] = d[k] - 2.0f * dn * n[k];
    float *reflected = job->reflected + 6 * r, *leave = job->leave + 6 * r;
    for (int k = 0; k < 3; ++k) {
        reflected[k] = entry[k] + off * mirror[k];
        reflected[3 + k] = mirror[k];
        leave[k] = entry[k] + off * d[k]; /* an open mesh: through, unbent */
        leave[3 + k] = d[k];
    }
    refract3(d, n, eta, along);
    int trapped = 1;
    for (int32_t c = 0; c < job->crossings && trapped; ++c) {
        float s = crossing(&job->walk, at, along, off, &face, &u, &v);
        if (!isfinite(s)) {
            if (c > 0) /* lost inside (a broken mesh): leave from the last crossing */
                for (int k = 0; k < 3; ++k) { leave[k] = at[k] + off * along[k]; leave[3 + k] = along[k]; }
            trapped = 0;
            break;
        }
        float point[3] = {at[0] + s * along[0], at[1] + s * along[1], at[2] + s * along[2]}, out[3];
        smooth_normal(job->normals, face, u, v, n);
        int total = refract3(along, n, job->ior[face], out);
        for (int k = 0; k < 3; ++k) { at[k] = point[k]; along[k] = out[k]; }
        if (!total) {
            for (int k = 0; k < 3; ++k) { leave[k] = point[k] + off * out[k]; leave[3 + k] = out[k]; }
            trapped = 0;
        }
    }
    if (trapped)
        for (int k = 0; k < 3; ++k) { leave[k] = at[k] + off * along[k]; leave[3 + k] = along[k]; }
}

static void *run(void *argument) {
    const Job *job = (const Job *)argument;
    for (int64_t r = job->begin; r < job->end; ++r) nearest(job, r);
    return 0;
}

static void *run_paths(void *argument) {
    const PathJob *job = (const PathJob *)argument;
    for (int64_t r = job->walk.begin; r < job->walk.end; ++r) path(job, r);
    return 0;
}

/* Threads to share `rays` rays: one below a few thousand (a thread's start costs more). */
static int64_t thread_count(int64_t threads, int64_t rays) {
    if (rays < 4096 || threads < 1) return 1;
    return threads > 64 ? 64 : threads;
}

/* `work` over jobs[0 .. threads) (each `size` bytes), jobs 1.. on threads of their own; a job
 * whose thread could not start runs here. */
static void run_all(void *(*work)(void *), char *jobs, size_t size, int64_t threads) {
    pthread_t handles[64];
    int64_t started = 0;
    for (int64_t i = 1; i < threads; ++i) {
        if (pthread_create(&handles[i], 0, work, jobs + i * size) != 0) break;
        started = i;
    }
    work(jobs);
    for (int64_t i = 1; i <= started; ++i) pthread_join(handles[i], 0);
    for (int64_t i = started + 1; i < threads; ++i) work(jobs + i * size);
}

int glass_paths(const float *origins, const float *directions, int64_t rays, const float *lo, const float *hi,
                const int32_t *child, const float *tri, const float *normals, const float *ior, float offset,
                int32_t crossings, uint8_t *met, int32_t *entry_face, float *t_entry, float *fresnel_out, float *leave,
                float *reflected, int64_t threads) {
    threads = thread_count(threads, rays);
    PathJob jobs[64];
    for (int64_t i = 0; i < threads; ++i) {
        jobs[i] = (PathJob){{origins, directions, lo, hi, tri, child, 0.0f, 0, 0, 0, rays * i / threads,
                             rays * (i + 1) / threads},
                            normals, ior, offset, crossings, met, entry_face, t_entry, fresnel_out, leave, reflected};
    }
    run_all(run_paths, (char *)jobs, sizeof(PathJob), threads);
    return 0;
}

int ray_mesh_nearest(const float *origins, const float *directions, int64_t rays, float t_min, const float *lo,
                     const float *hi, const int32_t *child, const float *tri, float *t_out, int32_t *face_out,
                     float *uv_out, int64_t threads) {
    threads = thread_count(threads, rays);
    Job jobs[64];
    for (int64_t i = 0; i < threads; ++i) {
        jobs[i] = (Job){origins, directions, lo, hi, tri, child, t_min, t_out, uv_out, face_out,
                        rays * i / threads, rays * (i + 1) / threads};
    }
    run_all(run, (char *)jobs, sizeof(Job), threads);
    return 0;
}
