/* Output-sensitive refinement on the CPU: the front traversal and the front
 * mesh as plain C loops over the flat arrays of a progressive mesh.
 *
 * The JAX front engine (pmjax/_front.py) pays a fixed cost of about a dozen
 * XLA kernels per generation of the forest; here a generation costs nothing
 * and a visited pcol costs its own arithmetic. The results are the bits of
 * the dense engine:
 *
 *  - a pcol's subtree bound is evaluated in float64 with the margins of
 *    pmjax/_subtree.py (sound: "whole" guarantees that every pcol below
 *    collapses under the float32 predicate);
 *  - a pcol's own decision is certified: every comparison of the float32
 *    predicate (pmjax/_predicate.py) is evaluated in float64 together with a
 *    bound on how far ANY float32 evaluation of the same formula can be from
 *    the exact value (fused multiply-adds or not, any association, flush to
 *    zero). When the exact margin exceeds that bound, the float32 predicate
 *    must return the same bit; otherwise the pcol is "uncertain" and the
 *    caller decides it with the float32 predicate itself;
 *  - the bottom-up recurrence is the dense engine's.
 *
 * Struct of arrays as in the rest of pmjax; one 64-byte row per pcol (the
 * traversal reads scattered pcols). Every entry point takes its scratch from
 * the caller and leaves it as it found it, so threads with their own scratch
 * may call concurrently. No allocation, no global state.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <string.h>

/* Columns of ProgressiveMesh.table (pmjax/_front.py TABLE_ATTRIBUTES, TABLE_BOUNDS). */
enum { CX, CY, CZ, NX, NY, NZ, RADIUS, SIN_A, COS_A, DELTA, MU, REACH, SPREAD, FACING, ERROR, AXIS_SCALE, ROW };

/* Layout of View.values (pmjax/_view.py). */
enum { EYE = 0, RIGHT = 3, UP = 6, FORWARD = 9, K = 12, ONE_PIXEL = 20, KAPPA2 = 21 };

/* Flags of a call. */
enum { TEST_FRUSTUM = 1, TEST_ORIENTATION = 2, TEST_SCREEN = 4, ORTHOGRAPHIC = 8 };

/* State of a visited slot: its own decision in the low bits, WHOLE when the
 * subtree bound decided it. */
enum { NO = 0, YES = 1, UNSURE = 2, WHOLE = 4 };

/* Margins of the subtree bounds: pmjax/_subtree.py MARGIN, SCREEN_MARGIN. */
static const double MARGIN = 0x1p-16;
static const double SCREEN_MARGIN = 0x1p-14;

/* Forward error of a float32 evaluation: every comparison below has at most
 * 16 roundings on any path from its inputs, so a float32 value lies within
 * GAMMA * M of the exact one, M being the same formula over absolute values
 * (Higham, Accuracy and Stability, ch. 3). The unit is inflated by 2^-50 to
 * cover this file's own float64 rounding of the value and of M. */
static const double U32 = 0x1p-24 + 0x1p-50;
#define GAMMA (16.0 * U32 / (1.0 - 16.0 * U32))
/* With flush to zero (XLA on the CPU) an operation can also lose up to the
 * smallest normal float32, scaled by at most two downstream factors; FLUSH
 * times the pcol's factor bound covers the 64 operations of the predicate. */
static const double FLUSH = 256.0 * 0x1p-126;

/* Float32 rounding is relative only between underflow and overflow: a
 * comparison whose magnitudes leave [LOW, HIGH] is not certified, and a
 * subtree bound decides nothing where a descendant's test could leave it. */
static const double LOW = 0x1p-100, HIGH = 0x1p100;

/* Is a < b, for the float32 evaluation, given d = a - b and the magnitude m? */
static inline int less(double d, double m, double slack)
{
    if (!(m < HIGH)) /* overflow possible, or not finite */
        return UNSURE;
    double bound = GAMMA * m + slack;
    if (d < -bound)
        return YES;
    if (d > bound)
        return NO;
    if (m == 0.0 && d == 0.0) /* every term exactly zero: 0 < 0 */
        return NO;
    return UNSURE; /* too close, or not finite */
}

/* Three-valued or / and. */
static inline int or3(int a, int b) { return (a == YES || b == YES) ? YES : (a == NO && b == NO) ? NO : UNSURE; }
static inline int and3(int a, int b) { return (a == NO || b == NO) ? NO : (a == YES && b == YES) ? YES : UNSURE; }

typedef struct {
    const float *table;     /* [P, ROW] */
    const int32_t *children; /* [P, 2], -1: an original vertex */
    const int32_t *kills;   /* [P] */
    int64_t n_pcols;
} Mesh;

/* One camera's constants in float64 (exact copies of the float32 values). */
typedef struct {
    double e[3], r[3], u[3], f[3], k[8], kappa2;
    double kabs; /* 1 + |a_x| + |a_y| + l_x + l_y + kappa2: the view's factor bound */
    int flags;
} View;

static void load_view(View *v, const float *values, int flags)
{
    for (int i = 0; i < 3; i++) {
        v->e[i] = values[EYE + i];
        v->r[i] = values[RIGHT + i];
        v->u[i] = values[UP + i];
        v->f[i] = values[FORWARD + i];
    }
    for (int i = 0; i < 8; i++)
        v->k[i] = values[K + i];
    v->kappa2 = values[KAPPA2];
    v->kabs = 1.0 + fabs(v->k[0]) + fabs(v->k[1]) + fabs(v->k[4]) + fabs(v->k[5]) + fabs(v->kappa2);
    v->flags = flags;
}

static inline double dot3(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
static inline double adot3(const double *a, const double *b)
{
    return fabs(a[0] * b[0]) + fabs(a[1] * b[1]) + fabs(a[2] * b[2]);
}

/* Subtree bound (pmjax/_subtree.py subtree_collapses, in float64): does every
 * pcol below collapse? v is centre - eye, d2 = |v|^2. Each bound also asks
 * that the descendants' own comparisons stay within [LOW, HIGH] (as
 * subtree_collapses does), where float32 rounding is relative. */
static int whole(const View *w, const float *row, const double *v, double d2)
{
    const double reach = row[REACH], spread = row[SPREAD], error = row[ERROR];
    const double *k = w->k;
    if (w->flags & TEST_FRUSTUM) {
        double x = dot3(v, w->r), y = dot3(v, w->u), z = dot3(v, w->f);
        double sx = z * k[0] + k[2], sy = z * k[1] + k[3];
        double size = (fabs(x) + fabs(y) + fabs(z) + reach) * (1 + fabs(k[0]) + fabs(k[1]) + k[4] + k[5]);
        double m = MARGIN * (size + fabs(k[2]) + fabs(k[3]) + fabs(k[6]) + fabs(k[7]));
        if (m > LOW && m < HIGH &&
            (z + reach < k[6] - m || z - reach > k[7] + m || sx - fabs(x) + reach * k[4] < -m ||
             sy - fabs(y) + reach * k[5] < -m))
            return 1;
    }
    const double n[3] = {row[NX], row[NY], row[NZ]};
    if (w->flags & ORTHOGRAPHIC) {
        if ((w->flags & TEST_ORIENTATION) && dot3(n, w->f) * row[AXIS_SCALE] > row[FACING])
            return 1;
        if ((w->flags & TEST_SCREEN) && w->kappa2 > LOW && error * error < HIGH &&
            error * error < w->kappa2 * (1 - SCREEN_MARGIN))
            return 1;
        return 0;
    }
    double d = sqrt(d2);
    if (w->flags & TEST_ORIENTATION) {
        double a = dot3(v, n) * row[AXIS_SCALE];
        double gap = d - reach, far = d + reach;
        if (d2 > reach * reach && a > 0 && gap * gap > 0x1p-80 && far * far < HIGH) {
            double lhs = a * sqrt(fmax(d2 - reach * reach, 0.0)) - reach * sqrt(fmax(d2 - a * a, 0.0));
            if (lhs > d2 * row[FACING])
                return 1;
        }
    }
    if (w->flags & TEST_SCREEN) {
        double room = d - spread - SCREEN_MARGIN * (d + spread);
        double room2 = room * room, far2 = (d + spread) * (d + spread);
        if (room > 0 && w->kappa2 * fmin(room2, room2 * room2) > LOW && w->kappa2 * far2 * far2 < HIGH &&
            error * error * far2 < HIGH && error * error < w->kappa2 * room2 * (1 - SCREEN_MARGIN))
            return 1;
    }
    return 0;
}

/* The pcol's own decision (pmjax/_predicate.py view_collapse_mask), certified
 * against every float32 evaluation: YES, NO or UNSURE. */
static int collapse(const View *w, const float *row, const double *v, double d2)
{
    const double r = row[RADIUS], ar = fabs(r), sa = row[SIN_A], ca = row[COS_A], delta = row[DELTA], mu = row[MU];
    const double n[3] = {row[NX], row[NY], row[NZ]};
    const double *k = w->k;
    const double av = fabs(v[0]) + fabs(v[1]) + fabs(v[2]);
    const double an = fabs(n[0]) + fabs(n[1]) + fabs(n[2]);
    /* Flush slack: the smallest normal times a bound on any two factors that
     * can multiply a flushed intermediate downstream. */
    const double scale = 1 + av + ar + an + fabs(sa) + fabs(ca) + fabs(delta) + fabs(mu);
    const double slack = FLUSH * scale * scale * scale * scale * w->kabs * w->kabs;
    if (!(scale < 0x1p40 && w->kabs < 0x1p40 && d2 < HIGH)) /* intermediates could overflow */
        return UNSURE;
    int out = NO;
    if (w->flags & TEST_FRUSTUM) {
        /* (z + r < near) | (z - r > far) | (sx - |x| < -r lx) | (sy - |y| < -r ly) */
        double x = dot3(v, w->r), y = dot3(v, w->u), z = dot3(v, w->f);
        double mx = adot3(v, w->r), my = adot3(v, w->u), mz = adot3(v, w->f);
        double sx = z * k[0] + k[2], sy = z * k[1] + k[3];
        double msx = mz * fabs(k[0]) + fabs(k[2]), msy = mz * fabs(k[1]) + fabs(k[3]);
        out = or3(out, less(z + r - k[6], mz + ar + fabs(k[6]), slack));
        out = or3(out, less(k[7] - (z - r), fabs(k[7]) + mz + ar, slack));
        out = or3(out, less(sx - fabs(x) + r * k[4], msx + mx + ar * fabs(k[4]), slack));
        out = or3(out, less(sy - fabs(y) + r * k[5], msy + my + ar * fabs(k[5]), slack));
        if (out == YES)
            return YES;
    }
    double h, mh, s, ms, normal2, mnormal2;
    if (w->flags & ORTHOGRAPHIC) {
        h = dot3(n, w->f);
        mh = adot3(n, w->f);
        s = 1.0;
        ms = 1.0;
        normal2 = delta * delta * (1.0 - h * h);
        mnormal2 = delta * delta * (1.0 + mh * mh);
    } else {
        h = dot3(v, n);
        mh = adot3(v, n);
        s = d2; /* d2 is a sum of squares: its magnitude is itself */
        ms = d2;
        normal2 = delta * delta * (d2 - h * h);
        mnormal2 = delta * delta * (d2 + mh * mh);
    }
    if (w->flags & TEST_ORIENTATION) {
        int away;
        if (w->flags & ORTHOGRAPHIC) {
            /* (ca > 0) & (h > sa) */
            away = and3(ca > 0 ? YES : NO, less(sa - h, fabs(sa) + mh, slack));
        } else {
            /* (t2 > 0) & (ca > 0) & (ca ca t2 > sr sr) & (g > 0) & (g g > sa sa t2) */
            double t2 = d2 - r * r, mt2 = d2 + r * r;
            double sr = sa * r, g = h - ca * r, mg = mh + fabs(ca) * ar;
            away = ca > 0 ? YES : NO;
            away = and3(away, less(-t2, mt2, slack));
            away = and3(away, less(sr * sr - ca * ca * t2, sr * sr + ca * ca * mt2, slack));
            away = and3(away, less(-g, mg, slack));
            away = and3(away, less(sa * sa * t2 - g * g, sa * sa * mt2 + mg * mg, slack));
        }
        out = or3(out, away);
        if (out == YES)
            return YES;
    }
    if (w->flags & TEST_SCREEN) {
        /* (mu2 < kappa2 s) & (normal2 < kappa2 s s) */
        double kappa2 = w->kappa2, limit = kappa2 * s;
        int small = less(mu * mu - limit, mu * mu + kappa2 * ms, slack);
        small = and3(small, less(normal2 - limit * s, mnormal2 + kappa2 * ms * ms, slack));
        out = or3(out, small);
    }
    return out;
}

/* Top-down traversal from the roots, breadth first: slot i holds pcol ids[i]
 * with state[i]; kid[2i], kid[2i+1] are the slots of its children (-1: not
 * visited, which means original or decided, and so executed). Returns the
 * number of slots; unsure[] receives the slots whose own decision is
 * UNSURE, *n_unsure their number. Capacity: P slots. */
static int64_t traverse(const Mesh *pm, const View *w, const int32_t *roots, int64_t n_roots, int32_t *ids,
                        int32_t *kid, uint8_t *state, int32_t *unsure, int64_t *n_unsure)
{
    int64_t n = 0, m = 0;
    for (int64_t i = 0; i < n_roots; i++)
        ids[n++] = roots[i];
    for (int64_t i = 0; i < n; i++) {
        const float *row = pm->table + (int64_t)ids[i] * ROW;
        double v[3] = {(double)row[CX] - w->e[0], (double)row[CY] - w->e[1], (double)row[CZ] - w->e[2]};
        double d2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
        kid[2 * i] = kid[2 * i + 1] = -1;
        if (whole(w, row, v, d2)) {
            state[i] = WHOLE | YES;
            continue;
        }
        int own = collapse(w, row, v, d2);
        state[i] = (uint8_t)own;
        if (own == UNSURE)
            unsure[m++] = (int32_t)i;
        /* The children are visited whatever this pcol does: each may run
         * on its own. Their rows are fetched ahead of their turn. */
        const int32_t *c = pm->children + 2 * (int64_t)ids[i];
        for (int j = 0; j < 2; j++) {
            if (c[j] >= 0) {
                __builtin_prefetch(pm->table + (int64_t)c[j] * ROW);
                kid[2 * i + j] = (int32_t)n;
                ids[n++] = c[j];
            }
        }
    }
    *n_unsure = m;
    return n;
}

/* Bottom-up: a slot ran if its subtree was decided, or it collapses and both
 * children ran (children always sit in later slots). Writes ran[] (0/1) and
 * the counts: pcols that did not run and the faces they keep. */
static void resolve(const Mesh *pm, int64_t n, const int32_t *ids, const int32_t *kid, const uint8_t *state,
                    uint8_t *ran, int64_t *n_not_run, int64_t *kept)
{
    int64_t not_run = 0, keep = 0;
    for (int64_t i = n - 1; i >= 0; i--) {
        int r;
        if (state[i] & WHOLE)
            r = 1;
        else {
            int k1 = kid[2 * i], k2 = kid[2 * i + 1];
            r = (state[i] == YES) && (k1 < 0 || ran[k1]) && (k2 < 0 || ran[k2]);
        }
        ran[i] = (uint8_t)r;
        if (!r) {
            not_run++;
            keep += pm->kills[ids[i]];
        }
    }
    *n_not_run = not_run;
    *kept = keep;
}

/* ---- entry points (ctypes) ---------------------------------------------- */

/* One camera. Traverses, and resolves unless a decision is unsure; returns
 * the number of visited slots. out[0] = unsure slots (then call
 * pmx_resolve after deciding them), out[1] = pcols not run, out[2] = faces
 * they keep. */
int64_t pmx_refine(const float *table, const int32_t *children, const int32_t *kills, int64_t n_pcols,
                   const int32_t *roots, int64_t n_roots, const float *view, int flags, int32_t *ids, int32_t *kid,
                   uint8_t *state, uint8_t *ran, int32_t *unsure, int64_t *out)
{
    Mesh pm = {table, children, kills, n_pcols};
    View w;
    load_view(&w, view, flags);
    int64_t m = 0;
    int64_t n = traverse(&pm, &w, roots, n_roots, ids, kid, state, unsure, &m);
    out[0] = m;
    out[1] = out[2] = 0;
    if (m == 0)
        resolve(&pm, n, ids, kid, state, ran, &out[1], &out[2]);
    return n;
}

/* The bottom-up pass after the unsure decisions were written into state[]
 * (YES or NO). */
void pmx_resolve(const int32_t *kills, int64_t n, const int32_t *ids, const int32_t *kid, const uint8_t *state,
                 uint8_t *ran, int64_t *out)
{
    Mesh pm = {NULL, NULL, kills, 0};
    resolve(&pm, n, ids, kid, state, ran, &out[0], &out[1]);
}

/* Cameras k0..k1-1 of views [K, 22], each traversed and resolved with the
 * same scratch. counts[3k..3k+2] = visited slots, pcols not run, faces they
 * keep; status[k] = 1 when the camera had an unsure decision (its counts are
 * then not written: the caller refines it alone). masks: optional [K, P]
 * executed bytes. */
void pmx_refine_many(const float *table, const int32_t *children, const int32_t *kills, int64_t n_pcols,
                     const int32_t *roots, int64_t n_roots, const float *views, int flags, int64_t k0, int64_t k1,
                     int32_t *ids, int32_t *kid, uint8_t *state, uint8_t *ran, int32_t *unsure, int64_t *counts,
                     uint8_t *status, uint8_t *masks)
{
    Mesh pm = {table, children, kills, n_pcols};
    for (int64_t c = k0; c < k1; c++) {
        View w;
        load_view(&w, views + 22 * c, flags);
        int64_t m = 0;
        int64_t n = traverse(&pm, &w, roots, n_roots, ids, kid, state, unsure, &m);
        status[c] = m > 0;
        if (m > 0)
            continue;
        resolve(&pm, n, ids, kid, state, ran, &counts[3 * c + 1], &counts[3 * c + 2]);
        counts[3 * c] = n;
        if (masks) {
            uint8_t *row = masks + c * n_pcols;
            memset(row, 1, (size_t)n_pcols);
            for (int64_t i = 0; i < n; i++)
                if (!ran[i])
                    row[ids[i]] = 0;
        }
    }
}

/* Every pcol's own decision (YES, NO or UNSURE) and subtree bound (out[p]
 * |= WHOLE), for tests that compare the certification with the float32
 * predicate over whole hierarchies. */
void pmx_decide_all(const float *table, int64_t n_pcols, const float *view, int flags, uint8_t *out)
{
    View w;
    load_view(&w, view, flags);
    for (int64_t p = 0; p < n_pcols; p++) {
        const float *row = table + p * ROW;
        double v[3] = {(double)row[CX] - w.e[0], (double)row[CY] - w.e[1], (double)row[CZ] - w.e[2]};
        double d2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
        out[p] = (uint8_t)(collapse(&w, row, v, d2) | (whole(&w, row, v, d2) ? WHOLE : 0));
    }
}

/* ---- the mesh from the front --------------------------------------------- */

static inline void set_bit(uint64_t *bits, int64_t i) { bits[i >> 6] |= (uint64_t)1 << (i & 63); }

/* The refined mesh from the pcols that did not run (pmjax/_front_mesh.py):
 * drawn faces are the base faces and those pcols' kill lists; each corner's
 * representative is the front vertex whose depth-first interval holds the
 * corner's position, found by a rank query on a bitmap of the front's
 * interval starts. faces_out [n_faces, 3] (indices into ids_out), ids_out
 * [<= front size] the vertex ids used, increasing. Returns the number of
 * ids, or -1 if the faces found are not n_faces (inconsistent input).
 *
 * Scratch (zero on entry, zero again on return): mark [P] bytes,
 * start_bits [V0/64 + 1], face_bits [F/64 + 1], vertex_bits [(V0+P)/64 + 1]
 * words; free scratch: rank_base [V0/64 + 1], owner_at [V0], sorted
 * [front], new_index [V0 + P] int32. */
int64_t pmx_front_mesh(int64_t n_original, int64_t n_pcols, int64_t n_faces_total, const int32_t *not_run,
                       int64_t n_not_run, const int64_t *kill_starts, const int32_t *kill_faces,
                       const int32_t *base_faces, int64_t n_base, const int32_t *pair, const int32_t *roots,
                       int64_t n_roots, const int32_t *lone, int64_t n_lone, const int32_t *start,
                       const int32_t *face_start, int64_t n_faces, int32_t *faces_out, int32_t *ids_out,
                       uint8_t *mark, uint64_t *start_bits, uint64_t *face_bits, uint64_t *vertex_bits,
                       int32_t *rank_base, int32_t *owner_at, int32_t *sorted, int32_t *new_index)
{
    const int64_t V0 = n_original;
    /* The front: below each pcol that did not run, its vertices that are
     * original or whose own pcol ran; the roots that ran; the lone originals.
     * Each marks its depth-first start. */
    for (int64_t i = 0; i < n_not_run; i++)
        mark[not_run[i]] = 1;
    int64_t n_front = 0;
#define ADD_FRONT(u)                                                                                               \
    do {                                                                                                           \
        int64_t s_ = start[(u)];                                                                                   \
        set_bit(start_bits, s_);                                                                                   \
        owner_at[s_] = (int32_t)(u);                                                                               \
        n_front++;                                                                                                 \
    } while (0)
    for (int64_t i = 0; i < n_not_run; i++)
        for (int j = 0; j < 2; j++) {
            int64_t u = pair[2 * (int64_t)not_run[i] + j];
            if (u < V0 || !mark[u - V0])
                ADD_FRONT(u);
        }
    for (int64_t i = 0; i < n_roots; i++)
        if (!mark[roots[i]])
            ADD_FRONT(V0 + roots[i]);
    for (int64_t i = 0; i < n_lone; i++)
        ADD_FRONT(lone[i]);
#undef ADD_FRONT
    /* Ranks: the front in depth-first order, and the starts before each word. */
    const int64_t words = V0 / 64 + 1;
    int64_t rank = 0;
    for (int64_t wd = 0; wd < words; wd++) {
        rank_base[wd] = (int32_t)rank;
        uint64_t b = start_bits[wd];
        while (b) {
            int bit = __builtin_ctzll(b);
            sorted[rank++] = owner_at[wd * 64 + bit];
            b &= b - 1;
        }
    }
    /* Drawn faces, in increasing order through a bitmap. */
    for (int64_t i = 0; i < n_base; i++)
        set_bit(face_bits, base_faces[i]);
    for (int64_t i = 0; i < n_not_run; i++) {
        int64_t p = not_run[i];
        for (int64_t j = kill_starts[p]; j < kill_starts[p + 1]; j++)
            set_bit(face_bits, kill_faces[j]);
    }
    /* Each corner's front vertex; the vertices used, marked by id. */
    int64_t n_drawn = 0;
    const int64_t face_words = n_faces_total / 64 + 1;
    for (int64_t wd = 0; wd < face_words; wd++) {
        uint64_t b = face_bits[wd];
        face_bits[wd] = 0;
        while (b) {
            int64_t f = wd * 64 + __builtin_ctzll(b);
            b &= b - 1;
            if (n_drawn < n_faces)
                for (int j = 0; j < 3; j++) {
                    int64_t pos = face_start[3 * f + j];
                    uint64_t below = start_bits[pos >> 6] & ((((uint64_t)2) << (pos & 63)) - 1);
                    int32_t u = sorted[rank_base[pos >> 6] + __builtin_popcountll(below) - 1];
                    faces_out[3 * n_drawn + j] = u;
                    set_bit(vertex_bits, u);
                }
            n_drawn++;
        }
    }
    /* Output ids in increasing order, and each one's index. */
    int64_t n_ids = 0;
    const int64_t vertex_words = (V0 + n_pcols) / 64 + 1;
    for (int64_t wd = 0; wd < vertex_words; wd++) {
        uint64_t b = vertex_bits[wd];
        if (!b)
            continue;
        vertex_bits[wd] = 0;
        while (b) {
            int64_t u = wd * 64 + __builtin_ctzll(b);
            b &= b - 1;
            new_index[u] = (int32_t)n_ids;
            ids_out[n_ids++] = (int32_t)u;
        }
    }
    int64_t corners = 3 * (n_drawn < n_faces ? n_drawn : n_faces);
    for (int64_t i = 0; i < corners; i++)
        faces_out[i] = new_index[faces_out[i]];
    /* Leave the scratch as found. */
    for (int64_t i = 0; i < n_not_run; i++)
        mark[not_run[i]] = 0;
    memset(start_bits, 0, sizeof(uint64_t) * (size_t)words);
    return n_drawn == n_faces ? n_ids : -1;
}

/* A module, so that setuptools builds and installs this file like any
 * extension; the functions are called through ctypes (pmjax/_native.py). */
static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_front_native",
                                    "C loops of the output-sensitive engine (called through ctypes).", -1, NULL, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__front_native(void) { return PyModule_Create(&module); }
