/* The least-squares fit of the shading normals (pmjax.fitted_normals) as
 * plain C loops: the original surface's sums, then batch by batch up the
 * hierarchy the subtree means, the live faces relabelled, each created
 * vertex's fan, the samples located on their fans and the Jacobi sweeps.
 * The per-view fit (pmjax.ViewNormals, pmn_view_normals) runs the same fan
 * and location steps on one drawn mesh, as one batch of all its created
 * vertices.
 *
 * Each loop is a NumPy step of pmjax/_normals.py with its arithmetic in the
 * same order (no contraction): sums of a vertex's terms in the order the
 * NumPy step adds them, dot products and squared lengths summed x, y, z in
 * that order. So the fit gives the NumPy fit's normals bit for bit
 * (tests/test_shading_normals.py). Unlike NumPy, a batch's samples are
 * taken vertex by vertex from the leaf order (a vertex's originals are one
 * run of it), not by a pass over every original vertex, and each created
 * vertex's terms are sorted into the order NumPy sums them in; the steps
 * over vertices or samples are split over threads, each part writing its
 * own outputs. Every pointer is a C-contiguous array of
 * the dtype named; the caller has checked the ids (faces below V0, children
 * below their parents' batch).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <float.h>
#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* The digest of the text this library was built from (setup.py defines it),
 * which pmjax compares with the source beside the library to catch a stale
 * build (pmjax/_clib.py). */
#ifndef PMJAX_SOURCE_DIGEST
#define PMJAX_SOURCE_DIGEST ""
#endif
const char *pmjax_source_digest(void);
const char *pmjax_source_digest(void) { return PMJAX_SOURCE_DIGEST; }

/* Outcomes of pmn_fitted_normals. */
enum { OK = 0, NO_MEMORY = 1 };

/* Positions are read as float32 or float64 (both exact in double). */
typedef struct {
    const float *f32;
    const double *f64;
} Coords;

static inline double coord(Coords c, int64_t v, int k) {
    return c.f32 ? (double)c.f32[3 * v + k] : c.f64[3 * v + k];
}

/* n / |n| in place (a length that is not positive, zero or NaN, divides by 1), the squares
 * summed x, y, z in that order (np.linalg.norm along an axis of three). */
static void unit3(double *n) {
    double length = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    double scale = length > 0 ? length : 1.0;
    for (int k = 0; k < 3; k++) n[k] /= scale;
}

/* Face f's cross product of its edges from corner 0 (_face_cross). */
static void face_cross(Coords c, const int32_t *faces, int64_t f, double *out) {
    int32_t a = faces[3 * f], b = faces[3 * f + 1], d = faces[3 * f + 2];
    double u[3], v[3];
    for (int k = 0; k < 3; k++) {
        u[k] = coord(c, b, k) - coord(c, a, k);
        v[k] = coord(c, d, k) - coord(c, a, k);
    }
    out[0] = u[1] * v[2] - u[2] * v[1];
    out[1] = u[2] * v[0] - u[0] * v[2];
    out[2] = u[0] * v[1] - u[1] * v[0];
}

/* What locating a sample needs of one fan face (_face_geometry). */
typedef struct {
    double a[3], e0[3], e1[3], d00, d01, d11, det;
} Geometry;

static void face_geometry(Coords c, const int32_t *tri, Geometry *g) {
    for (int k = 0; k < 3; k++) {
        g->a[k] = coord(c, tri[0], k);
        g->e0[k] = coord(c, tri[1], k) - g->a[k];
        g->e1[k] = coord(c, tri[2], k) - g->a[k];
    }
    g->d00 = g->e0[0] * g->e0[0] + g->e0[1] * g->e0[1] + g->e0[2] * g->e0[2];
    g->d01 = g->e0[0] * g->e1[0] + g->e0[1] * g->e1[1] + g->e0[2] * g->e1[2];
    g->d11 = g->e1[0] * g->e1[0] + g->e1[1] * g->e1[1] + g->e1[2] * g->e1[2];
    double det = g->d00 * g->d11 - g->d01 * g->d01;
    g->det = det > 0 ? det : 1.0; /* a degenerate face: coordinates of no use */
}

/* Work split over threads: fn(ctx, first, end) for parts of 0 .. n, cut
 * where the running sum of weight (NULL: one per item) passes each share.
 * Every part writes only its own items' outputs, so the results are the
 * same bits for any number of threads. */
typedef void (*Part)(void *ctx, int64_t first, int64_t end);

typedef struct {
    Part fn;
    void *ctx;
    int64_t first, end;
} Job;

static void *run_job(void *arg) {
    Job *job = arg;
    job->fn(job->ctx, job->first, job->end);
    return NULL;
}

#define MAX_THREADS 8

/* Work of n items below min_split runs on the calling thread alone. */
static void split(int threads, int64_t min_split, Part fn, void *ctx, int64_t n, const int64_t *weight) {
    if (threads > MAX_THREADS) threads = MAX_THREADS;
    if (threads < 2 || n < min_split) {
        fn(ctx, 0, n);
        return;
    }
    /* Cuts: equal shares of the total weight (weight: prefix sums, n + 1). */
    Job jobs[MAX_THREADS];
    pthread_t ids[MAX_THREADS];
    int64_t cut = 0;
    for (int t = 0; t < threads; t++) {
        int64_t end = n;
        if (t + 1 < threads) {
            if (weight) {
                int64_t goal = weight[0] + (weight[n] - weight[0]) / threads * (t + 1);
                end = cut;
                while (end < n && weight[end] < goal) end++;
            } else {
                end = n / threads * (t + 1);
            }
        }
        jobs[t] = (Job){fn, ctx, cut, end};
        cut = end;
    }
    int started = 1;
    for (; started < threads; started++)
        if (pthread_create(&ids[started], NULL, run_job, &jobs[started])) break;
    /* A thread that could not start: its part runs here. */
    for (int t = started; t < threads; t++) run_job(&jobs[t]);
    run_job(&jobs[0]);
    for (int t = 1; t < started; t++) pthread_join(ids[t], NULL);
}


/* A sample's term for one slot: its corner k, in the order of the NumPy
 * fit's sums (corner by corner, then by original vertex). */
typedef struct {
    int64_t key; /* k * V0 + p */
    int32_t at;  /* the sample's leaf position */
    int32_t k;
} Term;

/* Terms t[0 .. n-1] in increasing key (keys are distinct): quicksort on
 * the median of three, the smaller side first, short runs by insertion. */
static void sort_by_key(Term *t, int64_t n) {
    while (n > 16) {
        int64_t mid = n / 2;
        Term *a = &t[0], *b = &t[mid], *c = &t[n - 1], swap;
        if (b->key < a->key) swap = *a, *a = *b, *b = swap;
        if (c->key < b->key) {
            swap = *b, *b = *c, *c = swap;
            if (b->key < a->key) swap = *a, *a = *b, *b = swap;
        }
        int64_t pivot = t[mid].key, i = 0, j = n - 1;
        while (i <= j) {
            while (t[i].key < pivot) i++;
            while (t[j].key > pivot) j--;
            if (i <= j) {
                swap = t[i], t[i] = t[j], t[j] = swap;
                i++;
                j--;
            }
        }
        /* t[0 .. j] <= pivot <= t[i .. n-1]. */
        if (j + 1 < n - i) {
            sort_by_key(t, j + 1);
            t += i;
            n -= i;
        } else {
            sort_by_key(t + i, n - i);
            n = j + 1;
        }
    }
    for (int64_t i = 1; i < n; i++)
        for (int64_t j = i; j > 0 && t[j - 1].key > t[j].key; j--) {
            Term swap = t[j];
            t[j] = t[j - 1];
            t[j - 1] = swap;
        }
}

/* The fit's state. Per original vertex, in leaf order (position L holds
 * original leaf[L]): a vertex's leaves are a run of positions, so a
 * batch's samples are runs and their arrays are read in order. */
typedef struct {
    Coords c;
    int64_t V0, sweeps;
    int threads;        /* how many share each step's parts */
    int64_t min_split;  /* below this many slots or samples, one */
    double *out;               /* [V, 3] originals' unit vertex normals, the rest fitted so far */
    const int32_t *leaf;       /* [V0] original at each leaf position */
    const int32_t *leaf_first; /* [V] each vertex's first leaf position */
    const int32_t *leaf_count; /* [V] and how many leaves it has */
    const double *position;    /* [3, V0] the samples' positions, by axis */
    const double *target;      /* [V0, 3] their unit vertex normals */
    const double *weight;      /* [V0] a third of the area of their faces */
    int32_t *own;              /* [V0, 3] corners of the face each sample lies on */
    double *bary;              /* [V0, 3] its clamped barycentric coordinates */
    double *residual;          /* [V0, 3] */
    /* The current batch: created vertices lo .. lo + k_new - 1 (slots). */
    int64_t lo, k_new;
    const int32_t *tri;        /* live faces, corners relabelled */
    const int64_t *fan_start;  /* [k_new + 1] */
    const int32_t *fan;        /* live face ids, grouped by slot */
    int64_t longest;           /* the largest fan */
    const int64_t *samples;    /* [k_new + 1] running count of the slots' samples */
    const int64_t *term_start; /* [k_new + 1] */
    Term *term;                /* the terms of each slot, sorted */
    double *diagonal, *fitted; /* [k_new], [k_new, 3] */
    int failed;
} Fit;

/* The samples of slot u (with a fan): leaf positions first .. first+n-1. */
static inline int64_t slot_samples(const Fit *fit, int64_t u, int64_t *first) {
    *first = fit->leaf_first[fit->lo + u];
    return fit->samples[u + 1] - fit->samples[u];
}

/* Samples located a tile at a time: every face of the fan tried on a tile
 * of samples (a loop the compiler can run on vector lanes). */
#define TILE 256

/* Barycentric coordinates b0, b1, b2 of the projection of (x, y, z) on
 * face g's plane, and the smallest of them (_own_faces: the dot products
 * summed x, y, z in that order). */
static inline double on_face(const Geometry *g, double x, double y, double z, double *b0, double *b1, double *b2) {
    double e0 = x - g->a[0], e1 = y - g->a[1], e2 = z - g->a[2];
    double d20 = e0 * g->e0[0] + e1 * g->e0[1] + e2 * g->e0[2];
    double d21 = e0 * g->e1[0] + e1 * g->e1[1] + e2 * g->e1[2];
    *b1 = (g->d11 * d20 - g->d01 * d21) / g->det;
    *b2 = (g->d00 * d21 - g->d01 * d20) / g->det;
    *b0 = 1.0 - *b1 - *b2;
    double m = *b0 <= *b1 ? *b0 : *b1;
    return m <= *b2 ? m : *b2;
}

/* For the samples x, y, z[0 .. n-1] (n <= TILE), the deepest of the fan's
 * size faces: pick and the coordinates on it, the first of equals (faces
 * tried in fan order, a later one taken only if strictly deeper). Plain
 * IEEE operations (no contraction), so any vector width gives the scalar
 * loop's bits; built for AVX2 too where the CPU has it. */
#if defined(__GNUC__) && !defined(__clang__) && (defined(__x86_64__) || defined(__i386__))
__attribute__((target_clones("avx2", "default")))
#endif
static void deepest(const Geometry *geometry, int64_t size, const double *restrict x, const double *restrict y,
                    const double *restrict z, int64_t n, int64_t *restrict pick, double *restrict c0,
                    double *restrict c1, double *restrict c2, double *restrict depth) {
    for (int64_t s = 0; s < n; s++) {
        depth[s] = on_face(&geometry[0], x[s], y[s], z[s], &c0[s], &c1[s], &c2[s]);
        pick[s] = 0;
    }
    for (int64_t j = 1; j < size; j++) {
        const Geometry g = geometry[j];
        for (int64_t s = 0; s < n; s++) {
            double b0, b1, b2, d = on_face(&g, x[s], y[s], z[s], &b0, &b1, &b2);
            int better = d > depth[s];
            depth[s] = better ? d : depth[s];
            pick[s] = better ? j : pick[s];
            c0[s] = better ? b0 : c0[s];
            c1[s] = better ? b1 : c1[s];
            c2[s] = better ? b2 : c2[s];
        }
    }
}

/* Samples of slots first .. end-1 located on their fans: the face whose
 * projection the sample falls into most deeply (the first of equals), the
 * coordinates clamped to the face (_own_faces). */
static void locate(void *arg, int64_t first, int64_t end) {
    Fit *fit = arg;
    Geometry *geometry = malloc((size_t)(fit->longest > 0 ? fit->longest : 1) * sizeof *geometry);
    if (!geometry) {
        /* Any thread may fail: the flag is stored atomically, and read after
         * the threads are joined. */
        __atomic_store_n(&fit->failed, 1, __ATOMIC_RELAXED);
        return;
    }
    int64_t pick[TILE];
    double c[3][TILE], depth[TILE];
    const double *px = fit->position, *py = px + fit->V0, *pz = py + fit->V0;
    for (int64_t u = first; u < end; u++) {
        int64_t at, n = slot_samples(fit, u, &at);
        if (!n) continue;
        int64_t f0 = fit->fan_start[u], size = fit->fan_start[u + 1] - f0;
        for (int64_t j = 0; j < size; j++) face_geometry(fit->c, fit->tri + 3 * (int64_t)fit->fan[f0 + j], &geometry[j]);
        for (int64_t t0 = at; t0 < at + n; t0 += TILE) {
            int64_t m = at + n - t0 < TILE ? at + n - t0 : TILE;
            deepest(geometry, size, px + t0, py + t0, pz + t0, m, pick, c[0], c[1], c[2], depth);
            for (int64_t i = 0; i < m; i++) {
                int64_t s = t0 + i;
                double best[3];
                for (int k = 0; k < 3; k++) best[k] = c[k][i] > 0 ? c[k][i] : 0.0;
                double sum = best[0] + best[1] + best[2];
                if (sum < DBL_MIN) sum = DBL_MIN; /* np.maximum(sum, tiny) */
                const int32_t *face = fit->tri + 3 * (int64_t)fit->fan[f0 + pick[i]];
                for (int k = 0; k < 3; k++) {
                    fit->own[3 * s + k] = face[k];
                    fit->bary[3 * s + k] = best[k] / sum;
                }
            }
        }
    }
    free(geometry);
}

/* Slots first .. end-1: their terms sorted into the sums' order, and the
 * diagonal of the least squares, w b², summed in that order. */
static void sort_terms(void *arg, int64_t first, int64_t end) {
    Fit *fit = arg;
    for (int64_t u = first; u < end; u++) {
        Term *t = fit->term + fit->term_start[u];
        int64_t n = fit->term_start[u + 1] - fit->term_start[u];
        sort_by_key(t, n);
        double diagonal = 0.0;
        for (int64_t i = 0; i < n; i++) {
            double w = fit->weight[t[i].at], b = fit->bary[3 * (int64_t)t[i].at + t[i].k];
            diagonal += w * (b * b);
        }
        fit->diagonal[u] = diagonal;
    }
}

/* Samples of slots first .. end-1: target minus the interpolated normal,
 * with every corner's current value (fixed, or the created slots' last
 * sweep). */
static void residuals(void *arg, int64_t first, int64_t end) {
    Fit *fit = arg;
    for (int64_t u = first; u < end; u++) {
        int64_t at, n = slot_samples(fit, u, &at);
        for (int64_t s = at; s < at + n; s++) {
            double t[3][3];
            for (int k = 0; k < 3; k++) {
                int64_t c = fit->own[3 * s + k];
                const double *value = c >= fit->lo ? fit->fitted + 3 * (c - fit->lo) : fit->out + 3 * c;
                for (int x = 0; x < 3; x++) t[k][x] = fit->bary[3 * s + k] * value[x];
            }
            for (int x = 0; x < 3; x++)
                fit->residual[3 * s + x] = fit->target[3 * s + x] - (t[0][x] + t[1][x] + t[2][x]);
        }
    }
}

/* Slots first .. end-1: one Jacobi step, each term the residual without
 * this corner, weighted; a slot without terms keeps its start. */
static void solve(void *arg, int64_t first, int64_t end) {
    Fit *fit = arg;
    for (int64_t u = first; u < end; u++) {
        double *fitted = fit->fitted + 3 * u, rhs[3] = {0.0, 0.0, 0.0};
        for (int64_t i = fit->term_start[u]; i < fit->term_start[u + 1]; i++) {
            const Term *t = &fit->term[i];
            const double *residual = fit->residual + 3 * (int64_t)t->at;
            double b = fit->bary[3 * (int64_t)t->at + t->k], share = fit->weight[t->at] * b;
            for (int x = 0; x < 3; x++) rhs[x] += share * (residual[x] + b * fitted[x]);
        }
        const double *start = fit->out + 3 * (fit->lo + u);
        for (int x = 0; x < 3; x++) fitted[x] = fit->diagonal[u] > 0 ? rhs[x] / fit->diagonal[u] : start[x];
    }
}

/* A batch's scratch arrays, kept from batch to batch (grown as needed):
 * the first batches are the largest, so later ones map no new pages. */
typedef struct {
    void *buf;
    size_t bytes;
} Buffer;

enum { FAN_START, FAN, CURSOR, SAMPLES, TERM_START, TERM, DIAGONAL, FITTED, N_BUFFERS };
/* The per-view fit's arrays besides (pmn_view_normals). */
enum { SLOT_OF = N_BUFFERS, SLOT_ID, COORDS, START, FIRST, COUNT, TAKEN, WEIGHT, OWN, BARY, TRI, TOUCHED, O_OWN,
       O_BARY, O_WEIGHT, O_TARGET, O_RESIDUAL, O_FITTED, O_RHS, O_DIAGONAL, N_VIEW_BUFFERS };

static void *room(Buffer *b, size_t bytes) {
    if (bytes > b->bytes) {
        free(b->buf);
        b->bytes = bytes + bytes / 4;
        b->buf = malloc(b->bytes);
        if (!b->buf) b->bytes = 0;
    }
    return b->buf;
}

/* Steps 1 and 2 of the fit of the created slots lo .. lo + k_new - 1
 * (_fit_batch): their fans, and their samples located on them (fit->own,
 * fit->bary at the samples' leaf positions; fit->samples the running
 * count per slot, none where *located is 0 on return). fan_start:
 * [k_new + 1], entry u + 1 the fan size of slot u; touched: the n_touched
 * faces with a created corner, in mesh order. Returns OK or NO_MEMORY. */
static int locate_samples(Fit *fit, const int32_t *touched, int64_t n_touched, int64_t *fan_start, Buffer *scratch,
                          int *located) {
    int threads = fit->threads;
    int64_t min_split = fit->min_split;
    int64_t k_new = fit->k_new, lo = fit->lo;
    *located = 0;
    if (!n_touched) return OK;
    /* Step 1: each created vertex's fan: the live faces with it as a corner,
     * grouped by vertex; in a group the faces where it is corner 0, then
     * corner 1, then corner 2, each in mesh order (a counting sort). */
    fit->longest = 0;
    for (int64_t u = 0; u < k_new; u++) {
        if (fan_start[u + 1] > fit->longest) fit->longest = fan_start[u + 1];
        fan_start[u + 1] += fan_start[u];
    }
    size_t slots = (size_t)(k_new + 1) * sizeof(int64_t);
    int32_t *fan = room(&scratch[FAN], (size_t)fan_start[k_new] * sizeof *fan);
    int64_t *cursor = room(&scratch[CURSOR], slots);
    int64_t *samples = room(&scratch[SAMPLES], slots);
    int64_t *term_start = room(&scratch[TERM_START], slots);
    if (!fan || !cursor || !samples || !term_start) return NO_MEMORY;
    memset(term_start, 0, slots);
    memcpy(cursor, fan_start, (size_t)k_new * sizeof *cursor);
    for (int k = 0; k < 3; k++)
        for (int64_t i = 0; i < n_touched; i++) {
            int32_t c = fit->tri[3 * (int64_t)touched[i] + k];
            if (c >= lo) fan[cursor[c - lo]++] = touched[i];
        }
    fit->fan_start = fan_start;
    fit->fan = fan;
    /* Step 2: the samples: the originals standing under a created vertex
     * with a fan (its leaves), each located on the face of that fan it
     * lies on. */
    samples[0] = 0;
    for (int64_t u = 0; u < k_new; u++)
        samples[u + 1] = samples[u] + (fan_start[u + 1] > fan_start[u] ? fit->leaf_count[lo + u] : 0);
    if (!samples[k_new]) return OK;
    fit->samples = samples;
    fit->failed = 0;
    split(threads, min_split, locate, fit, k_new, samples);
    if (fit->failed) return NO_MEMORY;
    *located = 1;
    return OK;
}

/* The fit of one batch's created vertices (_fit_batch), their subtree
 * means in out on entry, the fitted unit normals on return (arguments as
 * locate_samples). Returns OK or NO_MEMORY. */
static int fit_batch(Fit *fit, const int32_t *touched, int64_t n_touched, int64_t *fan_start, Buffer *scratch) {
    int threads = fit->threads, located;
    int64_t min_split = fit->min_split;
    int64_t k_new = fit->k_new, lo = fit->lo, V0 = fit->V0;
    if (locate_samples(fit, touched, n_touched, fan_start, scratch, &located) != OK) return NO_MEMORY;
    if (!located) return OK;
    const int64_t *samples = fit->samples;
    int64_t *cursor = scratch[CURSOR].buf, *term_start = scratch[TERM_START].buf;
    /* Step 3: Jacobi sweeps of the weighted least squares over the created
     * vertices' normals, the other corners fixed. A sample's terms go to
     * the slots of its created corners, each slot's summed in the NumPy
     * fit's order: corner by corner, then by original vertex. */
    for (int64_t u = 0; u < k_new; u++) {
        int64_t at, n = slot_samples(fit, u, &at);
        for (int64_t s = at; s < at + n; s++)
            for (int k = 0; k < 3; k++)
                if (fit->own[3 * s + k] >= lo) term_start[fit->own[3 * s + k] - lo + 1]++;
    }
    for (int64_t u = 0; u < k_new; u++) term_start[u + 1] += term_start[u];
    Term *term = room(&scratch[TERM], (size_t)(term_start[k_new] > 0 ? term_start[k_new] : 1) * sizeof *term);
    double *diagonal = room(&scratch[DIAGONAL], (size_t)k_new * sizeof *diagonal);
    double *fitted = room(&scratch[FITTED], (size_t)k_new * 3 * sizeof *fitted);
    if (!term || !diagonal || !fitted) return NO_MEMORY;
    memcpy(cursor, term_start, (size_t)k_new * sizeof *cursor);
    for (int64_t u = 0; u < k_new; u++) {
        int64_t at, n = slot_samples(fit, u, &at);
        for (int64_t s = at; s < at + n; s++)
            for (int k = 0; k < 3; k++) {
                int64_t c = fit->own[3 * s + k];
                if (c >= lo) term[cursor[c - lo]++] = (Term){k * V0 + fit->leaf[s], (int32_t)s, k};
            }
    }
    fit->term_start = term_start;
    fit->term = term;
    fit->diagonal = diagonal;
    fit->fitted = fitted;
    split(threads, min_split, sort_terms, fit, k_new, term_start);
    memcpy(fitted, fit->out + 3 * lo, (size_t)k_new * 3 * sizeof *fitted);
    for (int64_t sweep = 0; sweep < fit->sweeps; sweep++) {
        split(threads, min_split, residuals, fit, k_new, samples);
        split(threads, min_split, solve, fit, k_new, term_start);
    }
    for (int64_t u = 0; u < k_new; u++) {
        unit3(fitted + 3 * u);
        memcpy(fit->out + 3 * (lo + u), fitted + 3 * u, 3 * sizeof(double));
    }
    return OK;
}

/* The originals in leaf order: every vertex's leaves (the originals it
 * stands for) a run of positions, its first child's then its second's;
 * leaf[L] the original at position L, leaf_first[v] and leaf_count[v]
 * vertex v's run. Counts up the hierarchy, then runs handed down from the
 * roots (the vertices no pcol consumes; mark[V] notes the consumed ones). */
static void leaf_order(int64_t V0, int64_t V, const int64_t *kid_lo, const int64_t *kid_hi, int32_t *leaf,
                       int32_t *leaf_first, int32_t *leaf_count, int32_t *mark) {
    int64_t P = V - V0;
    for (int64_t v = 0; v < V; v++) {
        leaf_count[v] = v < V0;
        mark[v] = 0;
    }
    for (int64_t i = 0; i < P; i++) {
        leaf_count[V0 + i] = leaf_count[kid_lo[i]] + leaf_count[kid_hi[i]];
        mark[kid_lo[i]] = mark[kid_hi[i]] = 1;
    }
    int64_t run = 0;
    for (int64_t v = 0; v < V; v++)
        if (!mark[v]) {
            leaf_first[v] = (int32_t)run;
            run += leaf_count[v];
        }
    for (int64_t i = P - 1; i >= 0; i--) {
        leaf_first[kid_lo[i]] = leaf_first[V0 + i];
        leaf_first[kid_hi[i]] = leaf_first[V0 + i] + leaf_count[kid_lo[i]];
    }
    for (int64_t p = 0; p < V0; p++) leaf[leaf_first[p]] = (int32_t)p;
}

/* The per-view fit's samples in original-id order, the order the NumPy fit
 * takes them in (its sums: corner by corner, then by original vertex), so
 * each slot's sums run in that order by a pass over them, with no sort. */
typedef struct {
    const Fit *fit;
    int64_t n;            /* samples */
    const int32_t *own;   /* [n, 3] slots of the corners of each one's face */
    const double *bary;   /* [n, 3] its clamped barycentric coordinates */
    const double *weight; /* [n] */
    const double *target; /* [n, 3] */
    double *residual;     /* [n, 3] */
    const double *fitted; /* [k_new, 3] the created slots' last sweep */
    double *rhs;          /* [k_new, 3] */
    double *diagonal;     /* [k_new] */
} Ordered;

/* Samples first .. end-1: target minus the interpolated normal (residuals). */
static void ordered_residuals(void *arg, int64_t first, int64_t end) {
    Ordered *o = arg;
    int64_t lo = o->fit->lo;
    for (int64_t i = first; i < end; i++) {
        double t[3][3];
        for (int k = 0; k < 3; k++) {
            int64_t c = o->own[3 * i + k];
            const double *value = c >= lo ? o->fitted + 3 * (c - lo) : o->fit->out + 3 * c;
            for (int x = 0; x < 3; x++) t[k][x] = o->bary[3 * i + k] * value[x];
        }
        for (int x = 0; x < 3; x++) o->residual[3 * i + x] = o->target[3 * i + x] - (t[0][x] + t[1][x] + t[2][x]);
    }
}

/* Created slots first .. end-1: the diagonal, w b², summed corner by
 * corner, then by sample (a pass over every sample, keeping this part's
 * slots' terms). */
static void ordered_diagonal(void *arg, int64_t first, int64_t end) {
    Ordered *o = arg;
    int64_t lo = o->fit->lo;
    for (int64_t u = first; u < end; u++) o->diagonal[u] = 0.0;
    for (int k = 0; k < 3; k++)
        for (int64_t i = 0; i < o->n; i++) {
            int64_t u = o->own[3 * i + k] - lo;
            if (u < first || u >= end) continue;
            double b = o->bary[3 * i + k];
            o->diagonal[u] += o->weight[i] * (b * b);
        }
}

/* Created slots first .. end-1: the right-hand side of one Jacobi step,
 * each term the residual without this corner, weighted, summed as the
 * diagonal. */
static void ordered_rhs(void *arg, int64_t first, int64_t end) {
    Ordered *o = arg;
    int64_t lo = o->fit->lo;
    for (int64_t u = first; u < end; u++)
        for (int x = 0; x < 3; x++) o->rhs[3 * u + x] = 0.0;
    for (int k = 0; k < 3; k++)
        for (int64_t i = 0; i < o->n; i++) {
            int64_t u = o->own[3 * i + k] - lo;
            if (u < first || u >= end) continue;
            double b = o->bary[3 * i + k], share = o->weight[i] * b;
            const double *residual = o->residual + 3 * i, *fitted = o->fitted + 3 * u;
            for (int x = 0; x < 3; x++) o->rhs[3 * u + x] += share * (residual[x] + b * fitted[x]);
        }
}

/* Step 3 of the per-view fit, after locate_samples: the located samples
 * (taken[L] = 2 at their leaf positions; at[p] the leaf position of
 * original p) gathered in original-id order, then the Jacobi sweeps of
 * fit_batch, each moving a normal the share relax of the way to its
 * step's solution (weighted Jacobi; 1: the whole way), the unit normals
 * into fit->out. Returns OK or NO_MEMORY. */
static int fit_in_vertex_order(Fit *fit, double relax, const int32_t *at, const unsigned char *taken, Buffer *work) {
    int64_t V0 = fit->V0, lo = fit->lo, k_new = fit->k_new, n = fit->samples[k_new];
    int32_t *own = room(&work[O_OWN], (size_t)n * 3 * sizeof *own);
    double *bary = room(&work[O_BARY], (size_t)n * 3 * sizeof *bary);
    double *weight = room(&work[O_WEIGHT], (size_t)n * sizeof *weight);
    double *target = room(&work[O_TARGET], (size_t)n * 3 * sizeof *target);
    double *residual = room(&work[O_RESIDUAL], (size_t)n * 3 * sizeof *residual);
    double *fitted = room(&work[O_FITTED], (size_t)k_new * 3 * sizeof *fitted);
    double *rhs = room(&work[O_RHS], (size_t)k_new * 3 * sizeof *rhs);
    double *diagonal = room(&work[O_DIAGONAL], (size_t)k_new * sizeof *diagonal);
    if (!own || !bary || !weight || !target || !residual || !fitted || !rhs || !diagonal) return NO_MEMORY;
    int64_t i = 0;
    for (int64_t p = 0; p < V0; p++) {
        int64_t L = at[p];
        if (taken[L] != 2) continue;
        memcpy(own + 3 * i, fit->own + 3 * L, 3 * sizeof *own);
        memcpy(bary + 3 * i, fit->bary + 3 * L, 3 * sizeof *bary);
        memcpy(target + 3 * i, fit->target + 3 * L, 3 * sizeof *target);
        weight[i++] = fit->weight[L];
    }
    Ordered o = {fit, n, own, bary, weight, target, residual, fitted, rhs, diagonal};
    split(fit->threads, fit->min_split, ordered_diagonal, &o, k_new, NULL);
    const double *start = fit->out + 3 * lo;
    memcpy(fitted, start, (size_t)k_new * 3 * sizeof *fitted);
    for (int64_t sweep = 0; sweep < fit->sweeps; sweep++) {
        split(fit->threads, fit->min_split, ordered_residuals, &o, n, NULL);
        split(fit->threads, fit->min_split, ordered_rhs, &o, k_new, NULL);
        for (int64_t u = 0; u < k_new; u++)
            for (int x = 0; x < 3; x++) {
                double step = rhs[3 * u + x] / diagonal[u];
                /* Weighted Jacobi: the step's share relax, the rest kept. */
                if (relax != 1.0) step = (1.0 - relax) * fitted[3 * u + x] + relax * step;
                fitted[3 * u + x] = diagonal[u] > 0 ? step : start[3 * u + x];
            }
    }
    for (int64_t u = 0; u < k_new; u++) {
        unit3(fitted + 3 * u);
        memcpy(fit->out + 3 * (lo + u), fitted + 3 * u, 3 * sizeof(double));
    }
    return OK;
}

/* pmjax.fitted_normals into out ([V, 3] float64, before the rounding to
 * float32). coords: [V, 3] float32 (coords_f64 = 0) or float64; faces:
 * [F, 3] original faces (ids below V0); pcol i (vertex V0 + i) consumes
 * kid_lo[i] < kid_hi[i], each vertex consumed once and made before the
 * pcol's batch; batch b makes pcols offsets[b] .. offsets[b+1]-1; threads:
 * how many share the work (the same bits for any), a step of fewer than
 * min_split slots or samples on one. Returns OK or NO_MEMORY. */
int64_t pmn_fitted_normals(int64_t V0, int64_t V, const void *coords, int64_t coords_f64, int64_t F,
                           const int32_t *faces, const int64_t *kid_lo, const int64_t *kid_hi, int64_t B,
                           const int64_t *offsets, int64_t sweeps, int64_t threads, int64_t min_split,
                           double *out) {
    Coords c = {coords_f64 ? NULL : (const float *)coords, coords_f64 ? (const double *)coords : NULL};
    int64_t W0 = V0 > 0 ? V0 : 1;
    int rc = NO_MEMORY;
    double *total = calloc((size_t)V * 3, sizeof *total);
    double *area = calloc((size_t)W0, sizeof *area);
    int32_t *rep = malloc((size_t)(V > 0 ? V : 1) * sizeof *rep);
    int32_t *leaf = malloc((size_t)W0 * sizeof *leaf);
    int32_t *leaf_first = malloc((size_t)(V > 0 ? V : 1) * sizeof *leaf_first);
    int32_t *leaf_count = malloc((size_t)(V > 0 ? V : 1) * sizeof *leaf_count);
    double *position = malloc((size_t)W0 * 3 * sizeof *position);
    double *target = malloc((size_t)W0 * 3 * sizeof *target);
    double *weight = malloc((size_t)W0 * sizeof *weight);
    int32_t *own = malloc((size_t)W0 * 3 * sizeof *own);
    double *bary = malloc((size_t)W0 * 3 * sizeof *bary);
    double *residual = malloc((size_t)W0 * 3 * sizeof *residual);
    int32_t *tri = malloc((size_t)(F > 0 ? F : 1) * 3 * sizeof *tri);
    int32_t *touched = malloc((size_t)(F > 0 ? F : 1) * sizeof *touched);
    Buffer scratch[N_BUFFERS] = {{0}};
    if (!total || !area || !rep || !leaf || !leaf_first || !leaf_count || !position || !target || !weight || !own
        || !bary || !residual || !tri || !touched)
        goto done;
    /* The original surface: per vertex the sum of its faces' cross products
     * and a third of their area, each vertex's terms added corner 0 of
     * every face, then corner 1, then corner 2 (_corner_sums). */
    for (int k = 0; k < 3; k++)
        for (int64_t f = 0; f < F; f++) {
            double cross[3];
            face_cross(c, faces, f, cross);
            int64_t v = faces[3 * f + k];
            for (int x = 0; x < 3; x++) total[3 * v + x] += cross[x];
            area[v] += sqrt(cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]) / 6.0;
        }
    /* Every vertex's unit sum: the originals' vertex normals (the samples'
     * targets, and kept), zero for the created ones until their batch. */
    for (int64_t v = 0; v < V; v++) {
        memcpy(out + 3 * v, total + 3 * v, 3 * sizeof(double));
        unit3(out + 3 * v);
    }
    leaf_order(V0, V, kid_lo, kid_hi, leaf, leaf_first, leaf_count, rep);
    /* The samples' data in leaf order. */
    for (int64_t s = 0; s < V0; s++) {
        int64_t p = leaf[s];
        for (int x = 0; x < 3; x++) {
            position[x * V0 + s] = coord(c, p, x);
            target[3 * s + x] = out[3 * p + x];
        }
        weight[s] = area[p];
    }
    free(area);
    area = NULL;
    /* rep[x]: the vertex standing for x after the current batch. */
    for (int64_t v = 0; v < V; v++) rep[v] = (int32_t)v;
    memcpy(tri, faces, (size_t)F * 3 * sizeof *tri);
    int64_t n = F;
    Fit fit = {.c = c, .V0 = V0, .sweeps = sweeps, .threads = (int)threads, .min_split = min_split, .out = out, .leaf = leaf, .leaf_first = leaf_first,
               .leaf_count = leaf_count, .position = position, .target = target, .weight = weight, .own = own,
               .bary = bary, .residual = residual, .tri = tri};
    for (int64_t b = 0; b < B; b++) {
        int64_t lo = V0 + offsets[b], k_new = offsets[b + 1] - offsets[b];
        /* The batch's subtree means: a created vertex sums its two
         * children's sums, the smaller id first; its start is their unit. */
        for (int64_t i = offsets[b]; i < offsets[b + 1]; i++) {
            double *t = total + 3 * (V0 + i);
            for (int x = 0; x < 3; x++) {
                t[x] += total[3 * kid_lo[i] + x];
                t[x] += total[3 * kid_hi[i] + x];
            }
            memcpy(out + 3 * (V0 + i), t, 3 * sizeof(double));
            unit3(out + 3 * (V0 + i));
            rep[kid_lo[i]] = rep[kid_hi[i]] = (int32_t)(V0 + i);
        }
        /* The mesh just after the batch: corners relabelled, faces two of
         * whose corners meet dropped, the rest kept in order; the faces
         * with a created corner noted, and each created vertex's count. */
        int64_t *fan_start = room(&scratch[FAN_START], (size_t)(k_new + 1) * sizeof *fan_start);
        if (!fan_start) goto done;
        memset(fan_start, 0, (size_t)(k_new + 1) * sizeof *fan_start);
        int64_t m = 0, n_touched = 0;
        for (int64_t f = 0; f < n; f++) {
            int32_t x = rep[tri[3 * f]], y = rep[tri[3 * f + 1]], z = rep[tri[3 * f + 2]];
            if (x != y && y != z && x != z) {
                tri[3 * m] = x;
                tri[3 * m + 1] = y;
                tri[3 * m + 2] = z;
                if (x >= lo || y >= lo || z >= lo) {
                    touched[n_touched++] = (int32_t)m;
                    if (x >= lo) fan_start[x - lo + 1]++;
                    if (y >= lo) fan_start[y - lo + 1]++;
                    if (z >= lo) fan_start[z - lo + 1]++;
                }
                m++;
            }
        }
        n = m;
        fit.lo = lo;
        fit.k_new = k_new;
        if (fit_batch(&fit, touched, n_touched, fan_start, scratch) != OK) goto done;
    }
    rc = OK;
done:
    free(total);
    free(area);
    free(rep);
    free(leaf);
    free(leaf_first);
    free(leaf_count);
    free(position);
    free(target);
    free(weight);
    free(own);
    free(bary);
    free(residual);
    free(tri);
    free(touched);
    for (int i = 0; i < N_BUFFERS; i++) free(scratch[i].buf);
    return rc;
}

/* The leaf order of a hierarchy (leaf_order) for pmn_view_normals: pcol i
 * (vertex V0 + i) consumes kid_lo[i] < kid_hi[i]. Returns OK or
 * NO_MEMORY. */
int64_t pmn_leaf_order(int64_t V0, int64_t V, const int64_t *kid_lo, const int64_t *kid_hi, int32_t *leaf,
                       int32_t *leaf_first, int32_t *leaf_count) {
    int32_t *mark = malloc((size_t)(V > 0 ? V : 1) * sizeof *mark);
    if (!mark) return NO_MEMORY;
    leaf_order(V0, V, kid_lo, kid_hi, leaf, leaf_first, leaf_count, mark);
    free(mark);
    return OK;
}

/* Outcome of pmn_view_normals when a drawn vertex stands above another (or
 * is listed twice): the drawn vertices are not a front of the hierarchy,
 * and the caller fits them by NumPy. */
enum { NOT_FRONT = 2 };

/* pmjax.ViewNormals on one drawn mesh: its created vertices fitted
 * together by fit_batch, as one batch whose slots are the mesh's vertices,
 * the originals first, then the created ones (the unknowns), each group in
 * the given order; a created vertex's samples are the run of its leaves
 * (a front's runs do not overlap, checked), so no original vertex is
 * climbed from: the samples are located from the drawn created vertices'
 * leaves; putting them in original-id order (the sums' order) is one pass
 * over a byte per original vertex.
 *
 * Hierarchy: positions [V, 3] float64; normals [V, 3] float32 (the stored
 * ones); leaf, leaf_first, leaf_count from pmn_leaf_order; the samples in
 * leaf order: position [3, V0] by axis, target [V0, 3] (the originals'
 * stored normals), area [V0] (a third of their faces'). Mesh: ids [N]
 * hierarchy ids, faces [F, 3] indices into ids, eye [3] or NULL (weights
 * then times the cosine toward it over the squared distance); sweeps of
 * weighted Jacobi, each by the share relax. out: [N, 3]
 * float64, row i for ids[i]; workspace from pmn_view_workspace. Returns
 * OK, NO_MEMORY or NOT_FRONT. */
int64_t pmn_view_normals(int64_t V0, const double *positions, const float *normals, const int32_t *leaf,
                         const int32_t *leaf_first, const int32_t *leaf_count, const double *position,
                         const double *target, const double *area, int64_t N, const int64_t *ids, int64_t F,
                         const int64_t *faces, const double *eye, int64_t sweeps, double relax, int64_t threads,
                         int64_t min_split, void *workspace, double *out) {
    int64_t W0 = V0 > 0 ? V0 : 1, W = N > 0 ? N : 1, WF = F > 0 ? F : 1;
    Buffer *work = workspace;
    int64_t *slot_of = room(&work[SLOT_OF], (size_t)W * sizeof *slot_of);
    int64_t *slot_id = room(&work[SLOT_ID], (size_t)W * sizeof *slot_id);
    double *coords = room(&work[COORDS], (size_t)W * 3 * sizeof *coords);
    double *start = room(&work[START], (size_t)W * 3 * sizeof *start);
    int32_t *first = room(&work[FIRST], (size_t)W * sizeof *first);
    int32_t *count = room(&work[COUNT], (size_t)W * sizeof *count);
    unsigned char *taken = room(&work[TAKEN], (size_t)W0);
    double *weight = room(&work[WEIGHT], (size_t)W0 * sizeof *weight);
    int32_t *own = room(&work[OWN], (size_t)W0 * 3 * sizeof *own);
    double *bary = room(&work[BARY], (size_t)W0 * 3 * sizeof *bary);
    int32_t *tri = room(&work[TRI], (size_t)WF * 3 * sizeof *tri);
    int32_t *touched = room(&work[TOUCHED], (size_t)WF * sizeof *touched);
    if (!slot_of || !slot_id || !coords || !start || !first || !count || !taken || !weight || !own || !bary || !tri
        || !touched)
        return NO_MEMORY;
    memset(taken, 0, (size_t)W0);
    /* Slots: the originals first, then the created vertices, each group in
     * the given order; per slot its position, stored normal (the fit's
     * start; kept for the originals) and leaf run. */
    int64_t lo = 0;
    for (int64_t i = 0; i < N; i++) lo += ids[i] < V0;
    int64_t next[2] = {0, lo};
    for (int64_t i = 0; i < N; i++) {
        int64_t s = next[ids[i] >= V0]++;
        slot_of[i] = s;
        slot_id[s] = ids[i];
    }
    for (int64_t s = 0; s < N; s++) {
        int64_t v = slot_id[s];
        for (int x = 0; x < 3; x++) {
            coords[3 * s + x] = positions[3 * v + x];
            start[3 * s + x] = (double)normals[3 * v + x];
        }
        first[s] = leaf_first[v];
        count[s] = leaf_count[v];
    }
    /* A front: no two drawn vertices share a leaf. */
    for (int64_t s = 0; s < N; s++)
        for (int64_t L = first[s]; L < first[s] + count[s]; L++) {
            if (taken[L]) return NOT_FRONT;
            taken[L] = 1;
        }
    if (lo < N && F > 0) {
        /* The samples' weights: their area, or with an eye the area seen
         * from there, times the cosine of their normal toward it (zero
         * facing away) over the squared distance (the sums x, y, z in that
         * order). */
        for (int64_t s = lo; s < N; s++)
            for (int64_t L = first[s]; L < first[s] + count[s]; L++) {
                if (!eye) {
                    weight[L] = area[L];
                    continue;
                }
                double to[3], dot = 0.0, squares = 0.0;
                for (int x = 0; x < 3; x++) to[x] = eye[x] - position[x * V0 + L];
                for (int x = 0; x < 3; x++) squares += to[x] * to[x];
                for (int x = 0; x < 3; x++) dot += target[3 * L + x] * to[x];
                double distance = sqrt(squares);
                distance = distance > 0 ? distance : 1.0;
                double facing = dot / distance;
                if (facing < 0.0) facing = 0.0; /* np.maximum(x, 0.0): NaN and -0.0 kept */
                weight[L] = area[L] * facing / (distance * distance);
            }
        /* The mesh in slots; the faces with a created corner, and each
         * created slot's fan size. */
        int64_t *fan_start = room(&work[FAN_START], (size_t)(N - lo + 1) * sizeof *fan_start);
        if (!fan_start) return NO_MEMORY;
        memset(fan_start, 0, (size_t)(N - lo + 1) * sizeof *fan_start);
        int64_t n_touched = 0;
        for (int64_t f = 0; f < F; f++) {
            int64_t x = slot_of[faces[3 * f]], y = slot_of[faces[3 * f + 1]], z = slot_of[faces[3 * f + 2]];
            tri[3 * f] = (int32_t)x;
            tri[3 * f + 1] = (int32_t)y;
            tri[3 * f + 2] = (int32_t)z;
            if (x >= lo || y >= lo || z >= lo) {
                touched[n_touched++] = (int32_t)f;
                if (x >= lo) fan_start[x - lo + 1]++;
                if (y >= lo) fan_start[y - lo + 1]++;
                if (z >= lo) fan_start[z - lo + 1]++;
            }
        }
        Fit fit = {.c = {NULL, coords}, .V0 = V0, .sweeps = sweeps, .threads = (int)threads,
                   .min_split = min_split, .out = start, .leaf = leaf, .leaf_first = first, .leaf_count = count,
                   .position = position, .target = target, .weight = weight, .own = own, .bary = bary,
                   .tri = tri, .lo = lo, .k_new = N - lo};
        int located;
        if (locate_samples(&fit, touched, n_touched, fan_start, work, &located) != OK) return NO_MEMORY;
        if (located) {
            for (int64_t u = 0; u < N - lo; u++)
                if (fit.samples[u + 1] > fit.samples[u])
                    memset(taken + first[lo + u], 2, (size_t)count[lo + u]);
            if (fit_in_vertex_order(&fit, relax, leaf_first, taken, work) != OK) return NO_MEMORY;
        }
    }
    for (int64_t i = 0; i < N; i++) memcpy(out + 3 * i, start + 3 * slot_of[i], 3 * sizeof(double));
    return OK;
}

/* A workspace for pmn_view_normals: its arrays, kept from call to call
 * (grown as needed), so a frame maps no new pages; NULL when out of
 * memory. One call at a time uses it. */
void *pmn_view_workspace(void) { return calloc(N_VIEW_BUFFERS, sizeof(Buffer)); }

void pmn_view_workspace_free(void *workspace) {
    Buffer *work = workspace;
    if (!work) return;
    for (int i = 0; i < N_VIEW_BUFFERS; i++) free(work[i].buf);
    free(work);
}

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_normals_native",
                                    "The shading normals' least-squares fit as C loops (called through ctypes).", -1,
                                    NULL};

PyMODINIT_FUNC PyInit__normals_native(void) { return PyModule_Create(&module); }
