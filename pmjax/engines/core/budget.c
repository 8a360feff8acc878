/* Face budgets of camera batches: per camera, a guess of the smallest
 * float32 tau whose face count is within the budget, from one traversal.
 *
 * A pcol runs at tau exactly when tau > eps(p), eps(p) = max(t_p, eps of its
 * children), t_p its own critical tolerance (docs/design.md). A traversal at
 * a tolerance lo visits every pcol that does not run at lo; every pcol it
 * does not visit runs (eps < lo). So the visited slots' eps, computed
 * bottom-up, give the face count of every tau >= lo at once:
 * faces(tau) = base faces + the kills of the pcols with eps >= tau. One
 * weighted selection over the slots with eps >= lo then gives the answer.
 *
 * t_p is estimated in double from the screen test's closed form, where the
 * float32 predicate's switch can lie an ulp or two away: the result is a
 * guess, which the caller turns into the exact answer by exact counts at it
 * and just below it (pmjax/_refine.py). */
#include <float.h>
#include <stdlib.h>

#include "internal.h"

#define INF_BITS 0x7F800000
/* The first tolerance of a camera, as a share of the answer predicted for it. */
#define MARGIN 0.6

static int32_t bits_of(float x)
{
    int32_t b;
    memcpy(&b, &x, sizeof b);
    return b;
}

/* The square of the largest float32 tau at which the pcol of `row` is not
 * small on screen under `view` (+inf when it never is): the screen test's
 * terms in float32 in the predicate's order of operations (so that a
 * cancellation in d^2 - h^2 comes out as the predicate's does, to rounding),
 * then the closed form in double. Squares keep the order of the tolerances
 * and cost no root per pcol. */
static double own_squared(const float *row, const float *view, int ortho)
{
    float s, normal2;
    const float mu2 = row[MU] * row[MU], delta2 = row[DELTA] * row[DELTA];
    if (ortho) {
        const float h = fmaf(row[NZ], view[FORWARD + 2], fmaf(row[NY], view[FORWARD + 1], row[NX] * view[FORWARD]));
        s = 1.0f, normal2 = delta2 * fmaf(-h, h, 1.0f);
    } else {
        const float vx = row[CX] - view[EYE], vy = row[CY] - view[EYE + 1], vz = row[CZ] - view[EYE + 2];
        const float d2 = fmaf(vz, vz, fmaf(vy, vy, vx * vx)), h = fmaf(vz, row[NZ], fmaf(vy, row[NY], vx * row[NX]));
        s = d2, normal2 = delta2 * fmaf(-h, h, d2);
    }
    if (!(s > 0))
        return INFINITY;
    /* small <=> mu^2 < (unit tau)^2 s and normal^2 < (unit tau)^2 s^2 */
    const double ds = s, unit = view[ONE_PIXEL];
    const double x = fmax((double)mu2 * ds, normal2 > 0 ? (double)normal2 : 0.0) / (ds * ds * unit * unit);
    return x == x ? x : INFINITY;
}

/* The float32 tolerance of a squared one, rounded down. */
static float tolerance_of(double squared)
{
    const double t = sqrt(squared);
    if (!(t < (double)FLT_MAX))
        return t > (double)FLT_MAX ? INFINITY : FLT_MAX;
    float f = (float)t;
    if ((double)f > t)
        f = nextafterf(f, 0.0f);
    return f;
}

/* The largest value v of val[0..n) with the weights of the values >= v
 * above `over` (the total weight is above it): a three-way quickselect. */
static double crossing(double *val, int32_t *wt, int64_t n, int64_t over)
{
    int64_t lo = 0, hi = n;
    for (;;) {
        const double p = val[lo + (hi - lo) / 2];
        /* Partition [lo, hi) into > p, == p, < p. */
        int64_t gt = lo, i = lo, lt = hi;
        int64_t w_gt = 0, w_eq = 0;
        while (i < lt) {
            const double v = val[i];
            const int32_t w = wt[i];
            if (v > p) {
                val[i] = val[gt], wt[i] = wt[gt], val[gt] = v, wt[gt] = w;
                gt++, i++, w_gt += w;
            } else if (v < p) {
                lt--;
                val[i] = val[lt], wt[i] = wt[lt], val[lt] = v, wt[lt] = w;
            } else {
                i++, w_eq += w;
            }
        }
        if (w_gt > over) {
            hi = gt;
        } else if (w_gt + w_eq > over) {
            return p;
        } else {
            over -= w_gt + w_eq;
            lo = lt;
        }
    }
}

/* Working memory of one thread beyond its scratch: the slots' eps and the
 * values and weights selected from. */
typedef struct {
    double *eps, *val;
    int32_t *wt;
} Budget;

/* One camera: the guessed answer's bit pattern (INF_BITS + 1: tau = inf),
 * from a traversal at `lo` (lowered while the count there is within the
 * budget); -1 on a table that is not a forest. */
static int64_t budget_one(const Kernels *kern, const PmxHierarchy *h, const float *camera, float lo, int flags,
                          int64_t budget, int64_t base_faces, PmxScratch *s, Budget *b)
{
    const int ortho = (flags & PMX_ORTHOGRAPHIC) != 0, screen = (flags & PMX_SCREEN) != 0;
    float row[PMX_CAMERA], view[PMX_VIEW];
    memcpy(row, camera, sizeof row);
    if (budget < base_faces) /* even the coarsest mesh keeps more */
        return (int64_t)INF_BITS + 1;
    int64_t last_count = -1;
    for (;;) {
        /* Traverse at lo. */
        row[PMX_CAMERA - 1] = lo;
        pmx_view_of(row, ortho, view);
        Frames w;
        load_frames(&w, view, 1, flags);
        int64_t m = 0;
        const int64_t n = traverse(kern, h, &w, s->ids, s->kid, s->state, s->kill, NULL, s->unsure, &m);
        if (n < 0)
            return -1;
        /* The count at lo (unsure decisions as "keep"): within the budget,
         * the answer lies below lo. */
        int64_t not_run = 0, kept = 0;
        kern->resolve(h, n, s->ids, s->kid, s->state, s->kill, s->ran, NULL, &not_run, &kept);
        if (base_faces + kept > budget) {
            /* eps^2 bottom-up over the slots that did not run (children sit
             * after their parents); a slot that ran at lo, and every pcol
             * under it, runs at every tau >= lo and counts as -inf. */
            const double lo2 = (double)lo * lo;
            int64_t total = base_faces, count = 0;
            for (int64_t i = n - 1; i >= 0; i--) {
                if (s->ran[i]) {
                    b->eps[i] = -INFINITY;
                    continue;
                }
                const int st = s->state[i] & 3;
                double e = -INFINITY;
                if (st != YES) {
                    const double t = screen ? own_squared(h->rows + (int64_t)s->ids[i] * ROW, view, ortho) : INFINITY;
                    /* A sure "keep" at lo puts the switch at lo or above. */
                    e = st == NO ? (t > lo2 ? t : lo2) : (t >= lo2 ? t : -INFINITY);
                }
                const int32_t k0 = s->kid[2 * i], k1 = s->kid[2 * i + 1];
                if (k0 >= 0 && b->eps[k0] > e)
                    e = b->eps[k0];
                if (k1 >= 0 && b->eps[k1] > e)
                    e = b->eps[k1];
                b->eps[i] = e;
                if (e >= lo2) {
                    b->val[count] = e, b->wt[count] = s->kill[i];
                    total += s->kill[i], count++;
                }
            }
            if (total > budget) {
                /* The answer: just above the largest eps whose pcols, with
                 * those above, keep too many faces. */
                const double v = crossing(b->val, b->wt, count, budget - base_faces);
                return v == INFINITY ? (int64_t)INF_BITS + 1 : (int64_t)bits_of(tolerance_of(v)) + 1;
            }
        }
        if (lo == 0.0f)
            return 0;
        /* Within the budget at lo: lower lo, by the face count's rough
         * inverse proportion to tau (a margin of 2). A count that did not
         * change from the last lo says the view is as fine as it gets: 0. */
        const int64_t count_at_lo = base_faces + kept;
        double next = lo * 0.5 * (double)(count_at_lo - base_faces + 1) / (double)(budget - base_faces + 1);
        if (count_at_lo == last_count || next < 1e-30)
            return 0;
        last_count = count_at_lo;
        lo = (float)next;
    }
}

/* A batch shared by its threads (cursor), as in traverse.c. */
typedef struct {
    const PmxHierarchy *h;
    const float *cameras;
    const int32_t *budgets;
    int64_t K, cursor, base_faces;
    int flags;
    float centre[3];
    int32_t *guess;
    PmxStatus status;
} Batch;

static void batch_work(void *arg)
{
    Batch *bt = arg;
    const PmxHierarchy *h = bt->h;
    const int64_t room = h->n_pcols + PMX_SPARE;
    PmxScratch *s = pmx_scratch_take(h->n_pcols);
    Budget b = {malloc(sizeof(double) * (size_t)room), malloc(sizeof(double) * (size_t)room),
                malloc(sizeof(int32_t) * (size_t)room)};
    if (!s || !scratch_slots(s) || !b.eps || !b.val || !b.wt) {
        __atomic_store_n(&bt->status, PMX_NO_MEMORY, __ATOMIC_RELAXED);
        goto done;
    }
    const unsigned mode = subnormals_off();
    const Kernels *kern = pmx_kernels();
    /* The first tolerance of a camera: its row's, or where that is 0, the
     * last answer of this thread times its eye's distance to the model's
     * centre, over this eye's (the screen error falls as the distance
     * grows), times MARGIN; a camera whose answer lies below it lowers it
     * and traverses again. */
    const int ortho = (bt->flags & PMX_ORTHOGRAPHIC) != 0;
    double scaled = -1.0;
    for (int64_t c; (c = __atomic_fetch_add(&bt->cursor, 1, __ATOMIC_RELAXED)) < bt->K;) {
        const float *camera = bt->cameras + c * PMX_CAMERA;
        const double dx = camera[0] - bt->centre[0], dy = camera[1] - bt->centre[1], dz = camera[2] - bt->centre[2];
        const double dist = sqrt(dx * dx + dy * dy + dz * dz) + 1e-30;
        float lo = camera[PMX_CAMERA - 1];
        if (!(lo > 0.0f))
            lo = scaled > 0 ? (float)(ortho ? MARGIN * scaled : MARGIN * scaled / dist) : 1.0f;
        if (!(lo > 0.0f) || lo > 1e30f)
            lo = 1.0f;
        const int64_t g = budget_one(kern, h, camera, lo, bt->flags, bt->budgets[c], bt->base_faces, s, &b);
        if (g < 0) {
            __atomic_store_n(&bt->status, PMX_BAD_TABLE, __ATOMIC_RELAXED);
            break;
        }
        bt->guess[c] = (int32_t)(g > (int64_t)INF_BITS + 1 ? (int64_t)INF_BITS + 1 : g);
        if (g > 0 && g <= INF_BITS) {
            float t;
            const int32_t gb = (int32_t)g;
            memcpy(&t, &gb, sizeof t);
            scaled = ortho ? t : t * dist;
        }
    }
    subnormals_back(mode);
done:
    free(b.eps), free(b.val), free(b.wt);
    if (s)
        pmx_scratch_give(s);
}

PmxStatus pmx_budget_many(const PmxHierarchy *h, const float *cameras, int64_t K, int flags, const int32_t *budgets,
                          int64_t base_faces, int32_t *guess, const PmxRunner *run)
{
    Batch bt = {h, cameras, budgets, K, 0, base_faces, flags, {0, 0, 0}, guess, PMX_OK};
    /* The model's centre: the mean of the roots' centres. */
    double c[3] = {0, 0, 0};
    for (int64_t q = 0; q < h->n_roots; q++)
        for (int a = 0; a < 3; a++)
            c[a] += h->rows[q * ROW + CX + a];
    for (int a = 0; a < 3; a++)
        bt.centre[a] = (float)(h->n_roots ? c[a] / (double)h->n_roots : 0.0);
    run_shared(run, batch_work, &bt);
    return bt.status;
}
