/* Face budgets of camera batches: per camera and budget, a guess of the
 * smallest float32 tau whose face count is within the budget, from one
 * traversal per camera for all its budgets.
 *
 * A pcol runs at tau exactly when tau > eps(p), eps(p) = max(t_p, eps of its
 * children), t_p its own critical tolerance (docs/design.md). A traversal at
 * a tolerance lo visits every pcol that does not run at lo; every pcol it
 * does not visit runs (eps < lo). So the visited slots' eps, computed
 * bottom-up, give the face count of every tau >= lo at once:
 * faces(tau) = base faces + the kills of the pcols with eps >= tau. One
 * weighted selection over the slots with eps >= lo then gives the answer.
 *
 * t_p is the screen test's switch, from its closed form corrected by the
 * float32 test itself evaluated on terms computed as the predicate computes
 * them, which an evaluation with other roundings (or an unsure frustum or
 * orientation decision) can move: the result is a guess, which the caller
 * turns into the exact answer by exact counts at it and just below it
 * (pmjax/_refine.py).
 *
 * Along a path the frames of a word (words.c) are traversed together, each
 * at its own lo, most pcols decided for all of them under the fat camera;
 * every frame's eps is then folded at once (a slot's 16 frames in one
 * vector) and each frame's answers come from its own lane as above. */
#include <float.h>
#include <stdlib.h>

#include "internal.h"

#define INF_BITS 0x7F800000
/* A camera's first tolerance, as a multiple of the answer its neighbour
 * predicts (a traversal above the answer is cheap, one below costs the
 * pcols between), and the next ones, as a share of the answer extrapolated
 * from the counts at the last. */
#define START 2.0
#define MARGIN 0.85

static int32_t bits_of(float x)
{
    int32_t b;
    memcpy(&b, &x, sizeof b);
    return b;
}

/* The screen test at tau as the float32 predicate evaluates it from its
 * terms (products only: no evaluation contracts them differently). */
static int small_at(float mu2, float normal2, float s, float unit, float tau)
{
    const float k = unit * tau, kappa2 = k * k, limit = kappa2 * s;
    return (mu2 < limit) & (normal2 < limit * s);
}

/* Steps of one float32 pattern taken at most to correct the closed form. */
#define STEPS 8

/* The float32 just above and just below a finite x >= 0 (non-negative floats
 * are ordered as their bit patterns). */
static float up(float x)
{
    int32_t b;
    memcpy(&b, &x, sizeof b);
    b++;
    memcpy(&x, &b, sizeof b);
    return x;
}

static float down(float x)
{
    int32_t b;
    memcpy(&b, &x, sizeof b);
    b -= b > 0;
    memcpy(&x, &b, sizeof b);
    return x;
}

/* The screen test's terms of a pcol's row under a view, in the
 * predicate's order of operations (ex..fz: the view's eye and forward). */
PMX_INLINE void screen_terms(const float *row, float ex, float ey, float ez, float fx, float fy, float fz, int ortho,
                             float *mu2, float *normal2, float *s)
{
    const float m = row[MU], d = row[DELTA], delta2 = d * d;
    *mu2 = m * m;
    if (ortho) {
        const float h = fmaf(row[NZ], fz, fmaf(row[NY], fy, row[NX] * fx));
        *s = 1.0f, *normal2 = delta2 * fmaf(-h, h, 1.0f);
    } else {
        const float vx = row[CX] - ex, vy = row[CY] - ey, vz = row[CZ] - ez;
        const float d2 = fmaf(vz, vz, fmaf(vy, vy, vx * vx)), h = fmaf(vz, row[NZ], fmaf(vy, row[NY], vx * row[NX]));
        *s = d2, *normal2 = delta2 * fmaf(-h, h, d2);
    }
}

/* The largest float32 tau at which the pcol of `row` is not small on screen
 * under `view` with one pixel `unit` (+inf when it never is): the screen
 * test's terms in float32 in the predicate's order of operations, the
 * closed form, then corrected by a few steps of the float32 test itself. */
static float own_tolerance(const float *row, const float *view, float unit, int ortho)
{
    float mu2, normal2, s;
    screen_terms(row, view[EYE], view[EYE + 1], view[EYE + 2], view[FORWARD], view[FORWARD + 1], view[FORWARD + 2],
                 ortho, &mu2, &normal2, &s);
    if (!small_at(mu2, normal2, s, unit, INFINITY))
        return INFINITY;
    /* small <=> mu^2 < (unit tau)^2 s and normal^2 < (unit tau)^2 s^2 */
    const float m = mu2 * s > normal2 ? mu2 * s : normal2;
    float f = sqrtf(m > 0 ? m : 0.0f) / (s * unit);
    if (!(f <= FLT_MAX))
        f = FLT_MAX;
    if (small_at(mu2, normal2, s, unit, f)) {
        for (int i = 0; i < STEPS && f > 0 && small_at(mu2, normal2, s, unit, f); i++)
            f = down(f);
    } else {
        for (int i = 0; i < STEPS && f < FLT_MAX && !small_at(mu2, normal2, s, unit, up(f)); i++)
            f = up(f);
    }
    return f;
}

/* Pcols a block of the vectorized pass takes. */
#define LANES 256
/* Slots between a row's prefetch and its use by a word's pairs (about one
 * block of LANES pairs; one camera's pass looks FRAMES times farther). */
#define AHEAD_ROWS 16

/* The switches of n <= LANES pairs from their screen test's terms (mu2,
 * normal2, s) and one pixel unit, as loops the compiler vectorizes: the
 * closed form (in double: sqrt(max(mu2 s, normal2)) / (s unit), whose
 * products of floats are exact) and the float32 test at it and at the two
 * patterns on either side (the switch is the pattern not small whose next
 * one is) into out; 0 in settled[j] where the switch lies farther (rare:
 * the caller takes own_tolerance's scalar steps). Returns the number of
 * pairs not settled. */
PMX_INLINE int32_t own_switch(const float *mu2, const float *normal2, const float *s, const float *unit, int64_t n,
                              float *out, int32_t *settled)
{
    float f[LANES];
    int32_t open = 0;
    for (int64_t j = 0; j < n; j++) {
        const double ds = s[j], nn = normal2[j] > 0 ? normal2[j] : 0.0f, mm = (double)mu2[j] * ds;
        double t = sqrt(mm > nn ? mm : nn) / (ds * unit[j]);
        t = t <= FLT_MAX ? t : FLT_MAX;
        const float tf = (float)t;
        memcpy(&f[j], &tf, sizeof tf);
    }
    for (int64_t j = 0; j < n; j++) {
        int32_t b0;
        memcpy(&b0, &f[j], sizeof b0);
        const int32_t bm2 = b0 - 2 > 0 ? b0 - 2 : 0, bm1 = b0 - 1 > 0 ? b0 - 1 : 0, bp1 = b0 + 1, bp2 = b0 + 2;
        float tm2, tm1, tp1, tp2;
        memcpy(&tm2, &bm2, 4), memcpy(&tm1, &bm1, 4), memcpy(&tp1, &bp1, 4), memcpy(&tp2, &bp2, 4);
        const float m = mu2[j], q = normal2[j], sj = s[j], u = unit[j];
        const float k0 = u * tm2, k1 = u * tm1, k2 = u * f[j], k3 = u * tp1, k4 = u * tp2;
        const float l0 = k0 * k0 * sj, l1 = k1 * k1 * sj, l2 = k2 * k2 * sj, l3 = k3 * k3 * sj, l4 = k4 * k4 * sj;
        const int s0 = (m < l0) & (q < l0 * sj), s1 = (m < l1) & (q < l1 * sj), s2 = (m < l2) & (q < l2 * sj);
        const int s3 = (m < l3) & (q < l3 * sj), s4 = (m < l4) & (q < l4 * sj);
        const float ki = u * INFINITY, li = ki * ki * sj;
        const int never = !((m < li) & (q < li * sj));
        /* The last pattern not small before one that is (the test is
         * monotone in tau: at most one such pair). */
        const int e3 = (1 - s3) & s4, e2 = (1 - s2) & s3, e1 = (1 - s1) & s2, e0 = (1 - s0) & s1 & (b0 >= 2);
        const int32_t bt = e3 ? bp1 : e2 ? b0 : e1 ? bm1 : bm2;
        float fu;
        memcpy(&fu, &bt, sizeof bt);
        settled[j] = never | e3 | e2 | e1 | e0;
        out[j] = never ? INFINITY : fu;
        open += 1 - settled[j];
    }
    return open;
}

/* The switch points (the largest float32 tau at which a pcol is not small
 * on screen, +inf when it never is) of the pcols at positions pos[0..n)
 * (n <= LANES) into out, each under its view view[j] with one pixel
 * unit[j]: the screen test's terms, then own_switch, whose settled pairs
 * get the exact float32 switch from the closed form and the float32 test
 * around it; only a pcol whose switch lies farther falls back to
 * own_tolerance (its scalar steps). */
PMX_INLINE void own_block_body(const float *rows, const int32_t *pos, int64_t n, const float *const *view,
                               const float *unit, int ortho, float *out)
{
    float mu2[LANES], normal2[LANES], s[LANES];
    int32_t settled[LANES];
    for (int64_t j = 0; j < n; j++) {
        const float *v = view[j];
        screen_terms(rows + (int64_t)pos[j] * ROW, v[EYE], v[EYE + 1], v[EYE + 2], v[FORWARD], v[FORWARD + 1],
                     v[FORWARD + 2], ortho, &mu2[j], &normal2[j], &s[j]);
    }
    if (!own_switch(mu2, normal2, s, unit, n, out, settled))
        return;
    for (int64_t j = 0; j < n; j++)
        if (!settled[j])
            out[j] = own_tolerance(rows + (int64_t)pos[j] * ROW, view[j], unit[j], ortho);
}

static void own_block_plain(const float *rows, const int32_t *pos, int64_t n, const float *const *view,
                            const float *unit, int ortho, float *out)
{
    own_block_body(rows, pos, n, view, unit, ortho, out);
}

#if PMX_X86
PMX_TARGET_AVX2 static void own_block_avx2(const float *rows, const int32_t *pos, int64_t n, const float *const *view,
                                           const float *unit, int ortho, float *out)
{
    own_block_body(rows, pos, n, view, unit, ortho, out);
}

PMX_TARGET_AVX512 static void own_block_avx512(const float *rows, const int32_t *pos, int64_t n,
                                               const float *const *view, const float *unit, int ortho, float *out)
{
    own_block_body(rows, pos, n, view, unit, ortho, out);
}
#endif

typedef void (*OwnBlock)(const float *, const int32_t *, int64_t, const float *const *, const float *, int, float *);

/* A word's frames as the own tolerances read them: their eyes, forwards
 * and one pixel units, one array per quantity (a frame per entry). */
typedef struct {
    float ex[FRAMES], ey[FRAMES], ez[FRAMES], fx[FRAMES], fy[FRAMES], fz[FRAMES];
    float unit[LANES]; /* frame j % FRAMES's unit at j: a block's pairs */
    const float *views;
} WordViews;

/* screen_terms of one pcol row under each of a word's FRAMES frames into
 * m, nn, sq (frame l at l), in one vector: called with a literal ortho so
 * that the projection's branch folds away. */
PMX_INLINE void frame_screen_terms(const float *row, const WordViews *w, int ortho, float *m, float *nn, float *sq)
{
#pragma omp simd
    for (int l = 0; l < FRAMES; l++)
        screen_terms(row, w->ex[l], w->ey[l], w->ez[l], w->fx[l], w->fy[l], w->fz[l], ortho, &m[l], &nn[l], &sq[l]);
}

/* The switch points of k <= LANES / FRAMES pcols (rows at positions
 * pos[0..k)) under each of a word's FRAMES frames into out (pcol q's frame
 * l at q * FRAMES + l), as own_block computes them (own_switch's exact
 * float32 switch where it settles, own_tolerance's scalar steps only
 * where it does not), each row read once for its frames. */
PMX_INLINE void own_slots_body(const float *rows, const int32_t *pos, int64_t k, const WordViews *w, int ortho,
                               float *out)
{
    float mu2[LANES], normal2[LANES], s[LANES];
    int32_t settled[LANES];
    for (int64_t q = 0; q < k; q++) {
        const float *row = rows + (int64_t)pos[q] * ROW;
        float *m = mu2 + q * FRAMES, *nn = normal2 + q * FRAMES, *sq = s + q * FRAMES;
        /* The projection's branch outside the frames' loop (a literal 1
         * or 0 into the helper), which then takes all FRAMES frames in
         * one vector. */
        if (ortho)
            frame_screen_terms(row, w, 1, m, nn, sq);
        else
            frame_screen_terms(row, w, 0, m, nn, sq);
    }
    if (!own_switch(mu2, normal2, s, w->unit, k * FRAMES, out, settled))
        return;
    for (int64_t j = 0; j < k * FRAMES; j++)
        if (!settled[j])
            out[j] = own_tolerance(rows + (int64_t)pos[j / FRAMES] * ROW, w->views + (j % FRAMES) * PMX_VIEW,
                                   w->unit[j], ortho);
}

static void own_slots_plain(const float *rows, const int32_t *pos, int64_t k, const WordViews *w, int ortho,
                            float *out)
{
    own_slots_body(rows, pos, k, w, ortho, out);
}

#if PMX_X86
PMX_TARGET_AVX2 static void own_slots_avx2(const float *rows, const int32_t *pos, int64_t k, const WordViews *w,
                                           int ortho, float *out)
{
    own_slots_body(rows, pos, k, w, ortho, out);
}

PMX_TARGET_AVX512 static void own_slots_avx512(const float *rows, const int32_t *pos, int64_t k, const WordViews *w,
                                               int ortho, float *out)
{
    own_slots_body(rows, pos, k, w, ortho, out);
}
#endif

typedef void (*OwnSlots)(const float *, const int32_t *, int64_t, const WordViews *, int, float *);

#if PMX_X86
/* The SIMD level in use (PMX_SIMD_PLAIN, AVX2 or AVX512: the index of a
 * kernel in this file's tables of three). */
static int simd_level(void)
{
    int level = PMX_SIMD_PLAIN;
    (void)pmx_kernels_at(-1, &level);
    return level;
}
#endif

/* The block kernel of the SIMD level in use (the same bits at every level:
 * fmaf, sqrtf and the division are exactly rounded). */
static OwnBlock own_block(void)
{
#if PMX_X86
    static const OwnBlock at_level[] = {own_block_plain, own_block_avx2, own_block_avx512};
    return at_level[simd_level()];
#else
    return own_block_plain;
#endif
}

/* The slot kernel of the SIMD level in use (own_block's bits). */
static OwnSlots own_slots(void)
{
#if PMX_X86
    static const OwnSlots at_level[] = {own_slots_plain, own_slots_avx2, own_slots_avx512};
    return at_level[simd_level()];
#else
    return own_slots_plain;
#endif
}

/* The largest value v of val[0..n) with the weights of the values >= v
 * above `over` (the total weight is above it): a three-way quickselect. */
static float crossing(float *val, int32_t *wt, int64_t n, int64_t over)
{
    int64_t lo = 0, hi = n;
    for (;;) {
        const float p = val[lo + (hi - lo) / 2];
        /* Partition [lo, hi) into > p, == p, < p. */
        int64_t gt = lo, i = lo, lt = hi;
        int64_t w_gt = 0, w_eq = 0;
        while (i < lt) {
            const float v = val[i];
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

/* Buckets of the values above lo: 128 per octave (the top 7 bits of the
 * mantissa), 16 octaves, the last holding everything above. */
#define BUCKETS 2048
/* Spare entries past them (a power of two). */
#define SPREAD 8

static int64_t bucket_of(float v, int32_t lo_bits)
{
    const int64_t q = ((int64_t)bits_of(v) - lo_bits) >> 16;
    return q < BUCKETS - 1 ? q : BUCKETS - 1;
}

/* bucket_of in 32 unsigned bits, for the frames' vector loops: the same
 * bucket for v >= lo (lo_bits: lo's bits), another for v below lo, which
 * its callers do not take. */
PMX_INLINE uint32_t bucket_u32(float v, int32_t lo_bits)
{
    uint32_t x;
    memcpy(&x, &v, sizeof x);
    const uint32_t q = (x - (uint32_t)lo_bits) >> 16;
    return q < BUCKETS - 1 ? q : BUCKETS - 1;
}

/* Working memory of one thread beyond its scratch: the slots' eps (eps[-1]
 * valid, -inf) and own tolerances, the values and weights selected from
 * (val, wt: every slot's; sel, sel_wt: one bucket's, taken by a selection),
 * the buckets' weights (faces, which a count's int32 holds). */
typedef struct {
    float *eps, *own, *val, *sel;
    int32_t *wt, *sel_wt;
    int32_t *bucket;
} Budget;

/* The own tolerances of the m slots listed in b->wt into b->own (inf for
 * all when the screen test is off). */
static void flush_block(const PmxHierarchy *h, const PmxScratch *s, Budget *b, int64_t m, const float *view,
                        float unit, int ortho, int screen, OwnBlock own)
{
    /* Lanes past m are never read; zeroed so that no compiler sees them unset. */
    int32_t pos[LANES] = {0};
    float out[LANES], units[LANES] = {0};
    const float *views[LANES] = {0};
    /* Without the screen test every own tolerance is infinite. */
    if (!screen) {
        for (int64_t j = 0; j < m; j++)
            b->own[b->wt[j]] = INFINITY;
        return;
    }
    for (int64_t j = 0; j < m; j++)
        pos[j] = s->ids[b->wt[j]], views[j] = view, units[j] = unit;
    own(h->rows, pos, m, views, units, ortho, out);
    for (int64_t j = 0; j < m; j++)
        b->own[b->wt[j]] = out[j];
}

/* The tally of a traversal at lo: the values >= lo with their kills
 * (b->val, b->wt; count of them), their kills per bucket (b->bucket), the
 * counts at lo and at twice lo. The first bucket, which takes the values
 * at lo and the slots below it one after another, is summed in `zero`,
 * the adds it would take spread over spare entries past the buckets (a
 * chain of adds to one entry waits on each store). */
typedef struct {
    int64_t count, total, total2, zero;
} Tally;

static Tally tally_start(Budget *b, int64_t base_faces)
{
    memset(b->bucket, 0, sizeof(int32_t) * (BUCKETS + SPREAD));
    return (Tally){0, base_faces, base_faces, 0};
}

/* Slot i's eps e (kills `kill`) into the tally t. */
PMX_INLINE void tally(Budget *b, Tally *t, int64_t i, float e, int32_t kill, float lo, int32_t lo_bits)
{
    const int in = e >= lo;
    kill = in ? kill : 0;
    b->val[t->count] = e, b->wt[t->count] = kill;
    const int64_t q = in ? bucket_of(e, lo_bits) : 0;
    t->zero += q ? 0 : kill;
    b->bucket[q ? q : BUCKETS + (i & (SPREAD - 1))] += kill;
    t->total += kill, t->count += in;
    t->total2 += e >= 2 * lo ? kill : 0;
}

static void tally_end(Budget *b, const Tally *t) { b->bucket[0] = (int32_t)t->zero; }

/* The counts of a traversal at lo from its n slots and their own
 * tolerances: eps bottom-up over the slots that did not run (children sit
 * after their parents; a slot that ran at lo, and every pcol under it, runs
 * at every tau >= lo and counts as -inf), the values >= lo with their kills
 * (b->val, b->wt; their number is returned) and their kills per bucket. An
 * unsure own decision counts as a collapse where unsure_collapses.
 * *total: the count at lo; *at_twice: the count at 2 lo. */
static int64_t eps_pass(const PmxScratch *s, Budget *b, int64_t n, float lo, int64_t base_faces,
                        int unsure_collapses, int64_t *total_out, int64_t *at_twice)
{
    const int32_t lo_bits = bits_of(lo);
    Tally t = tally_start(b, base_faces);
    /* Branch-free: a child not visited reads eps[-1] = -inf. */
    for (int64_t i = n - 1; i >= 0; i--) {
        const int st = s->state[i] & 3;
        const float own_e = st == YES || (st == UNSURE && unsure_collapses) ? -INFINITY : b->own[i];
        /* A sure "keep" at lo puts the switch at lo or above. */
        float e = st == NO ? (own_e > lo ? own_e : lo) : (own_e >= lo ? own_e : -INFINITY);
        const float e0 = b->eps[s->kid[2 * i]], e1 = b->eps[s->kid[2 * i + 1]];
        e = e0 > e ? e0 : e;
        e = e1 > e ? e1 : e;
        e = s->ran[i] ? -INFINITY : e;
        b->eps[i] = e;
        tally(b, &t, i, e, s->kill[i], lo, lo_bits);
    }
    tally_end(b, &t);
    *total_out = t.total;
    *at_twice = t.total2;
    return t.count;
}

/* Budgets whose answers one scan of the values finds (a group's buckets
 * compared with each value's at once). */
#define GROUP 8

/* The bucket (of b_bucket, the kills per bucket above lo) where the faces
 * kept by the pcols above a value pass `budget`, and in *over the weight
 * left to pass inside it. */
static int64_t crossing_bucket(const int32_t *b_bucket, int64_t budget, int64_t base_faces, int64_t *over)
{
    int64_t left = budget - base_faces, q = BUCKETS - 1;
    while (b_bucket[q] <= left) {
        left -= b_bucket[q];
        q--;
    }
    *over = left;
    return q;
}

/* The answer's bit pattern of a budget whose crossing lies in bucket q
 * with `over` left to pass in it, from the m values sel (weights sel_wt)
 * that hold every value of that bucket: those values moved to the front
 * (a selection only reorders values of one bucket), then selected from:
 * just above the largest eps whose pcols, with those above, keep too many
 * faces. */
static int64_t answer_in_bucket(float *sel, int32_t *sel_wt, int64_t m, int64_t q, int32_t lo_bits, int64_t over)
{
    int64_t c = 0;
    for (int64_t i = 0; i < m; i++)
        if (bucket_of(sel[i], lo_bits) == q) {
            const float v = sel[i];
            const int32_t w = sel_wt[i];
            sel[i] = sel[c], sel_wt[i] = sel_wt[c];
            sel[c] = v, sel_wt[c] = w;
            c++;
        }
    const float v = crossing(sel, sel_wt, c, over);
    return v == INFINITY ? (int64_t)INF_BITS + 1 : (int64_t)bits_of(v) + 1;
}

/* The answers for the B budgets from an eps_pass at lo (count values, the
 * count `total` at lo) into out: each budget's bit pattern, or -2 when the
 * count at lo is within it (budgets below base_faces are left alone). Per
 * budget, the bucket where its crossing lies; one scan of the values per
 * GROUP budgets gathers those buckets' values (b->sel), and each budget's
 * answer comes from its bucket's (answer_in_bucket). */
static void answers_of(Budget *b, int64_t count, float lo, int64_t total, const int32_t *budgets, int64_t B,
                       int64_t base_faces, int64_t *out)
{
    const int32_t lo_bits = bits_of(lo);
    for (int64_t j0 = 0; j0 < B; j0 += GROUP) {
        /* The group's budgets that the count at lo exceeds: their buckets
         * and the weight left to pass inside them. */
        int64_t at[GROUP], over_in[GROUP], q_of[GROUP];
        int n_at = 0;
        for (int64_t j = j0; j < B && j < j0 + GROUP; j++) {
            if (budgets[j] < base_faces)
                continue;
            if (total <= budgets[j]) {
                out[j] = -2;
                continue;
            }
            at[n_at] = j;
            q_of[n_at] = crossing_bucket(b->bucket, budgets[j], base_faces, &over_in[n_at]);
            n_at++;
        }
        if (!n_at)
            continue;
        /* The values in any of those buckets. */
        int64_t m = 0;
        for (int64_t i = 0; i < count; i++) {
            const int64_t q = bucket_of(b->val[i], lo_bits);
            int hit = 0;
            for (int t = 0; t < n_at; t++)
                hit |= q == q_of[t];
            b->sel[m] = b->val[i], b->sel_wt[m] = b->wt[i];
            m += hit;
        }
        for (int t = 0; t < n_at; t++)
            out[at[t]] = answer_in_bucket(b->sel, b->sel_wt, m, q_of[t], lo_bits, over_in[t]);
    }
}

/* The tolerance at which a count that is `a` (faces above the base, plus
 * one) at lo reaches the largest budget `top`, the count taken as a power
 * of tau (clamped to [0.5, 4]), times MARGIN. */
static double extrapolated(float lo, double a, double power, int64_t top, int64_t base_faces)
{
    power = power < 0.5 ? 0.5 : power > 4.0 ? 4.0 : power;
    return lo * MARGIN * pow(a / (double)(top - base_faces + 1), 1.0 / power);
}

/* Whether the largest budget's (`top`) answer lies below lo, from the
 * counts of a traversal at lo (total, at_twice at 2 lo; the pcols that did
 * not run keep `kept` faces; last_count: the count at the tolerance
 * traversed before, -1: none), and then in *next_lo the tolerance to
 * traverse at next. It does unless the view is as fine as it gets: the
 * counts at lo and 2 lo give the count's power of tau, extrapolated to the
 * largest budget, times MARGIN; a count that does not change from 2 lo (or
 * from the last lo) says the view is as fine as it gets. */
static int answers_below(int64_t total, int64_t at_twice, int64_t kept, float lo, int64_t top, int64_t base_faces,
                         int64_t last_count, float *next_lo)
{
    const int64_t count_at_lo = base_faces + kept;
    if (total <= top && lo != 0.0f && count_at_lo != last_count && at_twice != count_at_lo) {
        const double a = (double)(count_at_lo - base_faces + 1), a2 = (double)(at_twice - base_faces + 1);
        const double next = extrapolated(lo, a, a > a2 ? log(a / a2) / log(2.0) : 1.0, top, base_faces);
        if (next >= 1e-30) {
            *next_lo = (float)(next < lo * 0.9 ? next : lo * 0.9);
            return 1;
        }
    }
    return 0;
}

/* The guesses of one camera from the tally of its traversal at lo (count
 * values, the counts total at lo and at_twice at 2 lo; the pcols that did
 * not run keep `kept` faces) for its B budgets, the largest `top`: each
 * budget's guessed answer's bit pattern in guess, and in alt the guess with
 * the m unsure decisions taken as collapses (a second eps_pass over the n
 * slots in s). Returns 1, or 0 where the largest budget's answer lies below
 * lo and a lower tolerance may find it: *next_lo is then the tolerance to
 * traverse at next. last_count: the count at the tolerance traversed before
 * (-1: none). */
static int answers_from(PmxScratch *s, Budget *b, int64_t n, int64_t m, int64_t count, int64_t total,
                        int64_t at_twice, int64_t kept, float lo, const int32_t *budgets, int64_t B, int64_t top,
                        int64_t base_faces, int64_t last_count, float *next_lo, int64_t *guess, int64_t *alt)
{
    /* The largest budget's answer below lo: traverse again lower. */
    if (answers_below(total, at_twice, kept, lo, top, base_faces, last_count, next_lo))
        return 0;
    /* Each budget's answer from the same eps; those met at lo: 0. */
    answers_of(b, count, lo, total, budgets, B, base_faces, guess);
    for (int64_t j = 0; j < B; j++)
        if (budgets[j] >= base_faces)
            guess[j] = alt[j] = guess[j] == -2 ? 0 : guess[j];
    if (m) {
        /* The second guesses (alt holds the first until replaced; a budget
         * met at lo keeps 0: the count with collapses is no larger). */
        int64_t total_alt = 0, unused = 0;
        count = eps_pass(s, b, n, lo, base_faces, 1, &total_alt, &unused);
        answers_of(b, count, lo, total_alt, budgets, B, base_faces, alt);
        for (int64_t j = 0; j < B; j++)
            if (budgets[j] >= base_faces)
                alt[j] = guess[j] == 0 || alt[j] == -2 ? guess[j] : alt[j];
    }
    return 1;
}

/* answers_from of one camera's traversal at lo (n slots in s: ids, kid,
 * state, kill, ran; m of them unsure), its own tolerances computed here. */
static int answers_at(const PmxHierarchy *h, PmxScratch *s, Budget *b, int64_t n, int64_t m, int64_t kept, float lo,
                      const float *view, float unit, int flags, OwnBlock own, const int32_t *budgets, int64_t B,
                      int64_t top, int64_t base_faces, int64_t last_count, float *next_lo, int64_t *guess,
                      int64_t *alt)
{
    const int ortho = (flags & PMX_ORTHOGRAPHIC) != 0, screen = (flags & PMX_SCREEN) != 0;
    /* Own tolerances of the slots that did not run and whose own decision
     * is not a sure collapse, a block of positions at a time. */
    int64_t k = 0;
    for (int64_t i = 0; i < n; i++) {
        /* The rows a block ahead, so that they arrive in time (the
         * traversal's reads of them left the cache). */
        if (i + AHEAD_ROWS * FRAMES < n)
            __builtin_prefetch(h->rows + (int64_t)s->ids[i + AHEAD_ROWS * FRAMES] * ROW);
        b->own[i] = -INFINITY;
        b->wt[k] = (int32_t)i;
        k += !s->ran[i] & ((s->state[i] & 3) != YES);
        if (k == LANES) {
            flush_block(h, s, b, k, view, unit, ortho, screen, own);
            k = 0;
        }
    }
    if (k)
        flush_block(h, s, b, k, view, unit, ortho, screen, own);
    /* An unsure decision (mostly a sphere on a frustum plane) is taken as
     * "keep"; the second guess takes it as a collapse. */
    int64_t total = 0, at_twice = 0;
    const int64_t count = eps_pass(s, b, n, lo, base_faces, 0, &total, &at_twice);
    return answers_from(s, b, n, m, count, total, at_twice, kept, lo, budgets, B, top, base_faces, last_count,
                        next_lo, guess, alt);
}

/* The budgets a camera can meet (those at or above the coarsest mesh's
 * faces; the others are never met: inf in guess and alt) and the largest
 * of them, or -1 when there is none. */
static int64_t largest_budget(const int32_t *budgets, int64_t B, int64_t base_faces, int64_t *guess, int64_t *alt)
{
    int64_t top = -1;
    for (int64_t j = 0; j < B; j++) {
        guess[j] = alt[j] = (int64_t)INF_BITS + 1;
        if (budgets[j] >= base_faces)
            top = budgets[j] > top ? budgets[j] : top;
    }
    return top;
}

/* The guess of the largest budget (`top`) among B. */
static int64_t top_guess(const int32_t *budgets, int64_t B, int64_t top, const int64_t *guess)
{
    int64_t g_top = 0;
    for (int64_t j = 0; j < B; j++)
        if (budgets[j] == top)
            g_top = guess[j];
    return g_top;
}

/* The count's power of tau assumed where only one count is known: low, so
 * that the extrapolation lands below the answer rather than above it (where
 * the camera would traverse again); the fine views' counts grow about as
 * the square of 1 / tau. */
#define POWER 1.0

/* The next tolerance of a camera whose count at lo, count_at_lo, is within
 * its largest budget `top`: the count extrapolated to top as a power of tau
 * (from the count at the last, higher tolerance last_lo, else POWER), times
 * MARGIN, at most 0.9 lo. */
static double lower(float lo, int64_t count_at_lo, float last_lo, int64_t last_count, int64_t top,
                    int64_t base_faces)
{
    const double a = (double)(count_at_lo - base_faces + 1);
    double power = POWER;
    if (last_count >= 0 && last_count < count_at_lo && last_lo > lo)
        power = log(a / (double)(last_count - base_faces + 1)) / log((double)last_lo / lo);
    const double next = extrapolated(lo, a, power, top, base_faces);
    return next < lo * 0.9 ? next : lo * 0.9;
}

/* One camera and its B budgets: each budget's guessed answer's bit pattern
 * in guess (INF_BITS + 1: tau = inf), and in alt the guess with the unsure
 * decisions taken as collapses, from one traversal at `lo` (lowered while
 * the count there is within the largest budget, whose answer is the
 * smallest), the screen test with one pixel `unit`. Returns the largest
 * budget's guess, or -1 on a table that is not a forest. */
static int64_t budget_one(const Kernels *kern, const PmxHierarchy *h, const float *camera, float unit, float lo,
                          int flags, const int32_t *budgets, int64_t B, int64_t base_faces, PmxScratch *s, Budget *b,
                          int64_t *guess, int64_t *alt)
{
    const int ortho = (flags & PMX_ORTHOGRAPHIC) != 0;
    const OwnBlock own = own_block();
    float row[PMX_CAMERA], view[PMX_VIEW];
    memcpy(row, camera, sizeof row);
    /* A budget below the coarsest mesh is never met: inf. The largest
     * budget drives the traversal. */
    const int64_t top = largest_budget(budgets, B, base_faces, guess, alt);
    if (top < 0)
        return (int64_t)INF_BITS + 1;
    int64_t last_count = -1;
    float last_lo = 0.0f;
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
        /* Within the largest budget, and the count still changing: lower lo
         * from the counts alone, without the own tolerances of this front. */
        const int64_t count_at_lo = base_faces + kept;
        if (count_at_lo <= top && lo != 0.0f && count_at_lo != last_count) {
            const double next_lo = lower(lo, count_at_lo, last_lo, last_count, top, base_faces);
            if (next_lo >= 1e-30) {
                last_count = count_at_lo, last_lo = lo;
                lo = (float)next_lo;
                continue;
            }
        }
        float next = lo;
        if (answers_at(h, s, b, n, m, kept, lo, view, unit, flags, own, budgets, B, top, base_faces, last_count,
                       &next, guess, alt))
            return top_guess(budgets, B, top, guess);
        last_count = count_at_lo, last_lo = lo;
        lo = next;
    }
}

/* A batch shared by its threads (cursor), as in traverse.c: cameras, or
 * words of FRAMES consecutive frames of a path. */
typedef struct {
    const PmxHierarchy *h;
    const float *cameras, *units;
    const int32_t *budgets;
    int64_t K, B, cursor, base_faces;
    int flags;
    float centre[3];
    int32_t *guess, *guess_alt;
    PmxStatus status;
} Batch;

/* A thread's working memory: its scratch (with a word's frame masks where
 * `words`), the Budget arrays, a word's eps (lanes_room) and every frame's
 * tally of it (where `words`: lane_bucket, and
 * lane_val, lane_wt with room for lane_room values per frame, grown with
 * the words' slots, and every frame's guesses lane_g, B each), and one
 * camera's guesses (g, alt: B each); 0 when out
 * of memory (what was taken is given back by budget_give). */
typedef struct {
    PmxScratch *s;
    Budget b;
    float *eps_room, *lanes_room, *lane_val;
    int32_t *lane_wt;
    int32_t *lane_bucket;
    int64_t lane_room;
    int64_t *g, *alt, *lane_g;
} Work;

static int budget_take(Work *k, const PmxHierarchy *h, int64_t B, int words)
{
    const int64_t room = h->n_pcols + PMX_SPARE;
    k->s = pmx_scratch_take(h->n_pcols);
    k->eps_room = malloc(sizeof(float) * (size_t)(room + 1));
    k->b = (Budget){k->eps_room ? k->eps_room + 1 : NULL, malloc(sizeof(float) * (size_t)room),
                    malloc(sizeof(float) * (size_t)room), malloc(sizeof(float) * (size_t)room),
                    malloc(sizeof(int32_t) * (size_t)room), malloc(sizeof(int32_t) * (size_t)room),
                    malloc(sizeof(int32_t) * (BUCKETS + SPREAD))};
    k->lanes_room = words ? malloc(sizeof(float) * FRAMES * (size_t)(room + 1)) : NULL;
    k->lane_bucket = words ? malloc(sizeof(int32_t) * FRAMES * (BUCKETS + SPREAD)) : NULL;
    k->lane_val = NULL, k->lane_wt = NULL, k->lane_room = 0;
    k->lane_g = words ? malloc(sizeof(int64_t) * FRAMES * (size_t)B) : NULL;
    if (k->lanes_room)
        for (int l = 0; l < FRAMES; l++)
            k->lanes_room[l] = -INFINITY; /* a child not visited */
    k->g = malloc(sizeof(int64_t) * (size_t)(2 * B));
    k->alt = k->g ? k->g + B : NULL;
    if (k->eps_room)
        k->eps_room[0] = -INFINITY; /* eps[-1]: a child not visited */
    const Budget *b = &k->b;
    return k->s && scratch_slots(k->s) &&
           (!words || (scratch_words(k->s) && k->lanes_room && k->lane_bucket && k->lane_g)) &&
           b->eps && b->own &&
           b->val && b->sel && b->wt && b->sel_wt && b->bucket && k->g;
}

static void budget_give(Work *k)
{
    free(k->eps_room), free(k->b.own), free(k->b.val), free(k->b.sel), free(k->b.wt), free(k->b.sel_wt);
    free(k->b.bucket), free(k->lanes_room), free(k->g);
    free(k->lane_bucket), free(k->lane_val), free(k->lane_wt), free(k->lane_g);
    if (k->s)
        pmx_scratch_give(k->s);
}

/* Camera c's guesses into the batch's outputs (INF_BITS + 1 at most). */
static void put_guesses(Batch *bt, int64_t c, const int64_t *g, const int64_t *alt)
{
    for (int64_t j = 0; j < bt->B; j++) {
        bt->guess[c * bt->B + j] = (int32_t)(g[j] > (int64_t)INF_BITS + 1 ? (int64_t)INF_BITS + 1 : g[j]);
        bt->guess_alt[c * bt->B + j] = (int32_t)(alt[j] > (int64_t)INF_BITS + 1 ? (int64_t)INF_BITS + 1 : alt[j]);
    }
}

/* A thread's working memory for bt (with the word arrays when `words`);
 * 0, with bt's status set and nothing held, when it cannot be had. */
static int work_start(Batch *bt, Work *k, int words)
{
    if (budget_take(k, bt->h, bt->B, words))
        return 1;
    __atomic_store_n(&bt->status, PMX_NO_MEMORY, __ATOMIC_RELAXED);
    budget_give(k);
    return 0;
}

static void batch_work(void *arg)
{
    Batch *bt = arg;
    const PmxHierarchy *h = bt->h;
    const int64_t B = bt->B;
    Work k;
    if (!work_start(bt, &k, 0))
        return;
    const unsigned mode = subnormals_off();
    const Kernels *kern = pmx_kernels();
    /* The first tolerance of a camera: its row's, or where that is 0, the
     * last answer (of its largest budget) of this thread times its eye's
     * distance to the model's centre, over this eye's (the screen error
     * falls as the distance grows), times START; a camera whose answer lies
     * below it lowers it and traverses again. */
    const int ortho = (bt->flags & PMX_ORTHOGRAPHIC) != 0;
    double scaled = -1.0;
    for (int64_t c; (c = __atomic_fetch_add(&bt->cursor, 1, __ATOMIC_RELAXED)) < bt->K;) {
        const float *camera = bt->cameras + c * PMX_CAMERA;
        const double dx = camera[0] - bt->centre[0], dy = camera[1] - bt->centre[1], dz = camera[2] - bt->centre[2];
        const double dist = sqrt(dx * dx + dy * dy + dz * dz) + 1e-30;
        float lo = camera[PMX_CAMERA - 1];
        if (!(lo > 0.0f))
            lo = scaled > 0 ? (float)(ortho ? START * scaled : START * scaled / dist) : 1.0f;
        if (!(lo > 0.0f) || lo > 1e30f)
            lo = 1.0f;
        const int64_t top = budget_one(kern, h, camera, bt->units[c], lo, bt->flags, bt->budgets + c * B, B,
                                       bt->base_faces, k.s, &k.b, k.g, k.alt);
        if (top < 0) {
            __atomic_store_n(&bt->status, PMX_BAD_TABLE, __ATOMIC_RELAXED);
            break;
        }
        put_guesses(bt, c, k.g, k.alt);
        if (top > 0 && top <= INF_BITS) {
            float t;
            const int32_t gb = (int32_t)top;
            memcpy(&t, &gb, sizeof t);
            scaled = ortho ? t : t * dist;
        }
    }
    subnormals_back(mode);
    budget_give(&k);
}

/* Every frame's eps of a word's n slots at once, bottom-up (eps[i * FRAMES
 * + l] for frame l of slot i, row -1 all -inf): on entry each slot's own
 * part (-inf where its own decision is a sure collapse), then the larger
 * of it and the children's, -inf where the frame ran the slot. */
PMX_INLINE void lanes_up_body(float *eps, int64_t n, const int32_t *kid, const Lanes *ran)
{
    for (int64_t i = n - 1; i >= 0; i--) {
        float *e = eps + i * FRAMES;
        const float *e0 = eps + (int64_t)kid[2 * i] * FRAMES, *e1 = eps + (int64_t)kid[2 * i + 1] * FRAMES;
        const uint32_t r = ran[i];
#pragma omp simd
        for (int l = 0; l < FRAMES; l++) {
            float x = e[l] > e0[l] ? e[l] : e0[l];
            x = x > e1[l] ? x : e1[l];
            e[l] = (r >> l) & 1 ? -INFINITY : x;
        }
    }
}

static void lanes_up_plain(float *eps, int64_t n, const int32_t *kid, const Lanes *ran)
{
    lanes_up_body(eps, n, kid, ran);
}
#if PMX_X86
PMX_TARGET_AVX2 static void lanes_up_avx2(float *eps, int64_t n, const int32_t *kid, const Lanes *ran)
{
    lanes_up_body(eps, n, kid, ran);
}
PMX_TARGET_AVX512 static void lanes_up_avx512(float *eps, int64_t n, const int32_t *kid, const Lanes *ran)
{
    lanes_up_body(eps, n, kid, ran);
}
#endif

typedef void (*LanesUp)(float *, int64_t, const int32_t *, const Lanes *);

static LanesUp lanes_up(void)
{
#if PMX_X86
    static const LanesUp at_level[] = {lanes_up_plain, lanes_up_avx2, lanes_up_avx512};
    return at_level[simd_level()];
#else
    return lanes_up_plain;
#endif
}

/* Slots whose own tolerances a block of the word pass takes (each with
 * all its frames: the block's pairs follow the eps layout). */
#define SLOTS_PER_BLOCK (LANES / FRAMES)

/* The own part of every frame's eps of k slots (slot[0..k) at positions
 * pos) into eps: the own tolerance under the frame's view raised to the
 * frame's lo (inf with the screen test off) where the frame needs it
 * (need[q] bit l), else -inf. */
static void lanes_flush(const PmxHierarchy *h, const int32_t *pos, const int64_t *slot, const Lanes *need, int64_t k,
                        const WordViews *w, int ortho, int screen, OwnSlots own, const float *lo, float *eps)
{
    float out[LANES];
    if (screen)
        own(h->rows, pos, k, w, ortho, out);
    for (int64_t q = 0; q < k; q++) {
        float *e = eps + slot[q] * FRAMES;
        const float *o = out + q * FRAMES;
        for (int l = 0; l < FRAMES; l++) {
            const float x = screen ? o[l] : INFINITY, v = x > lo[l] ? x : lo[l];
            e[l] = (need[q] >> l) & 1 ? v : -INFINITY;
        }
    }
}

/* The own part of every frame's eps of a word's n slots into eps (layout
 * of lanes_up): -inf where the frame ran the slot or its own decision is a
 * sure collapse, else the larger of the own tolerance under the frame's
 * view and the frame's lo (a "keep" at lo puts the switch at lo or above;
 * an unsure decision is read so too). A slot that some frame needs takes all its
 * frames at once (the frames that do not need it computed and dropped, so
 * that a slot's row is read once and no list of pairs is kept),
 * SLOTS_PER_BLOCK slots a block. */
static void lanes_own(const PmxHierarchy *h, const PmxScratch *s, int64_t n, const WordViews *w, const float *lo,
                      int flags, OwnSlots own, float *eps)
{
    const int ortho = (flags & PMX_ORTHOGRAPHIC) != 0, screen = (flags & PMX_SCREEN) != 0;
    int32_t pos[SLOTS_PER_BLOCK];
    int64_t slot[SLOTS_PER_BLOCK];
    Lanes need[SLOTS_PER_BLOCK];
    int64_t k = 0;
    for (int64_t i = 0; i < n; i++) {
        /* The rows a block of slots ahead, so that they arrive in time (the
         * traversal's reads of them left the cache). */
        if (i + AHEAD_ROWS < n)
            __builtin_prefetch(h->rows + (int64_t)s->ids[i + AHEAD_ROWS] * ROW);
        const Lanes wanted = (Lanes) ~(s->ran_frames[i] | s->yes[i]);
        if (!wanted) {
            for (int l = 0; l < FRAMES; l++)
                eps[i * FRAMES + l] = -INFINITY;
            continue;
        }
        pos[k] = s->ids[i], slot[k] = i, need[k] = wanted;
        if (++k == SLOTS_PER_BLOCK) {
            lanes_flush(h, pos, slot, need, k, w, ortho, screen, own, lo, eps);
            k = 0;
        }
    }
    if (k)
        lanes_flush(h, pos, slot, need, k, w, ortho, screen, own, lo, eps);
}

/* Room for n values per frame in k's lane tallies (grown by half again,
 * never past `room`, the slots a traversal can list, and at least one);
 * 0 when out of memory. */
static int lane_room(Work *k, int64_t n, int64_t room)
{
    if (n <= k->lane_room && k->lane_room > 0)
        return 1;
    free(k->lane_val), free(k->lane_wt);
    const int64_t grown = n + n / 2 < room ? n + n / 2 : room;
    k->lane_room = grown > n ? grown : (n > 0 ? n : 1);
    k->lane_val = malloc(sizeof(float) * FRAMES * (size_t)k->lane_room);
    k->lane_wt = malloc(sizeof(int32_t) * FRAMES * (size_t)k->lane_room);
    if (k->lane_val && k->lane_wt)
        return 1;
    k->lane_room = 0;
    return 0;
}

/* The tallies of the frames in `frames` from a word's folded eps (n slots,
 * layout of lanes_up; kills kill[i]) at their lo, in one pass over the
 * slots (each slot's frames compared at once, in one vector): frame l's
 * kills per bucket (bucket + l (BUCKETS + SPREAD)) and its counts at lo
 * (total[l], of the frames in `frames`) and at twice lo (total2[l]), both
 * added to what they hold. */
PMX_INLINE void tally_body(const float *eps, const int32_t *kill, int64_t n, const float *lo,
                           const int32_t *lo_bits, Lanes frames, int32_t *bucket, int64_t *total, int64_t *total2)
{
    float twice[FRAMES];
    int32_t asked[FRAMES];
    for (int l = 0; l < FRAMES; l++)
        twice[l] = 2 * lo[l], asked[l] = (frames >> l) & 1;
    for (int64_t i = 0; i < n; i++) {
        const float *e = eps + i * FRAMES;
        const int32_t w = kill[i];
        const int32_t spare = BUCKETS + (int32_t)(i & (SPREAD - 1));
        /* The frames whose eps reach lo (and twice lo): their counts, and
         * each frame's entry to add to: its bucket (bucket_of in unsigned
         * 32 bits, the same for the values >= lo), else one of its spare
         * entries, given 0. */
        int32_t at_entry[FRAMES], add[FRAMES];
#pragma omp simd
        for (int l = 0; l < FRAMES; l++) {
            const int32_t in = e[l] >= lo[l];
            const int32_t at = in & asked[l];
            total[l] += at ? w : 0;
            total2[l] += (in & (e[l] >= twice[l])) ? w : 0; /* as tally: within lo first */
            const uint32_t q = bucket_u32(e[l], lo_bits[l]);
            at_entry[l] = l * (BUCKETS + SPREAD) + (at ? (int32_t)q : spare);
            add[l] = at ? w : 0;
        }
        /* Every frame's add, the same FRAMES adds for every slot (about
         * half of them 0: a branch per asked frame mispredicts more than
         * the adds of 0 cost). */
        for (int l = 0; l < FRAMES; l++)
            bucket[at_entry[l]] += add[l];
    }
}

static void tally_plain(const float *eps, const int32_t *kill, int64_t n, const float *lo, const int32_t *lo_bits,
                        Lanes frames, int32_t *bucket, int64_t *total, int64_t *total2)
{
    tally_body(eps, kill, n, lo, lo_bits, frames, bucket, total, total2);
}
#if PMX_X86
PMX_TARGET_AVX2 static void tally_avx2(const float *eps, const int32_t *kill, int64_t n, const float *lo,
                                       const int32_t *lo_bits, Lanes frames, int32_t *bucket, int64_t *total,
                                       int64_t *total2)
{
    tally_body(eps, kill, n, lo, lo_bits, frames, bucket, total, total2);
}
PMX_TARGET_AVX512 static void tally_avx512(const float *eps, const int32_t *kill, int64_t n, const float *lo,
                                           const int32_t *lo_bits, Lanes frames, int32_t *bucket, int64_t *total,
                                           int64_t *total2)
{
    tally_body(eps, kill, n, lo, lo_bits, frames, bucket, total, total2);
}
#endif

typedef void (*LanesTally)(const float *, const int32_t *, int64_t, const float *, const int32_t *, Lanes, int32_t *,
                           int64_t *, int64_t *);

static LanesTally tally_kernel(void)
{
#if PMX_X86
    static const LanesTally at_level[] = {tally_plain, tally_avx2, tally_avx512};
    return at_level[simd_level()];
#else
    return tally_plain;
#endif
}

/* The tallies of the frames in `frames` from a word's folded eps (n slots,
 * layout of lanes_up; kills kill[i]) at their lo: frame l's kills per
 * bucket (lane_bucket + l (BUCKETS + SPREAD)), the counts at lo and at
 * twice lo: what tally gives frame by frame, less the values themselves
 * (lanes_answers gathers the few that an answer needs) and their number
 * (t[l].count is -1: nothing reads it for a frame). */
static void lanes_tally(Work *k, const float *eps, const int32_t *kill, int64_t n, const float *lo, Lanes frames,
                        int64_t base_faces, Tally *t)
{
    int32_t lo_bits[FRAMES];
    int64_t total[FRAMES], total2[FRAMES];
    for (int l = 0; l < FRAMES; l++) {
        lo_bits[l] = bits_of(lo[l]);
        total[l] = total2[l] = base_faces;
    }
    memset(k->lane_bucket, 0, sizeof(int32_t) * FRAMES * (BUCKETS + SPREAD));
    tally_kernel()(eps, kill, n, lo, lo_bits, frames, k->lane_bucket, total, total2);
    for (int l = 0; l < FRAMES; l++)
        t[l] = (Tally){-1, total[l], total2[l], 0};
}

/* No bucket (the buckets are 0 .. BUCKETS - 1). */
#define NO_BUCKET 0xFFFFFFFFu

/* The values >= lo[l] of a word's folded eps (n slots, layout of lanes_up;
 * kills kill[i]) in any of frame l's buckets q_of[.][l] appended to frame
 * l's val, wt + l room (m[l] of them): a slot's frames in one vector
 * (bucket_of in unsigned 32 bits, the same for the values >= lo, the others
 * dropped). */
PMX_INLINE void hits_body(const float *eps, int64_t n, const float *lo, const int32_t *lo_bits,
                          const uint32_t (*q_of)[FRAMES], const int32_t *kill, float *val, int32_t *wt, int64_t room,
                          int64_t *m)
{
    for (int64_t i = 0; i < n; i++) {
        const float *e = eps + i * FRAMES;
        int32_t hv[FRAMES], any = 0;
#pragma omp simd reduction(| : any)
        for (int l = 0; l < FRAMES; l++) {
            const uint32_t q = bucket_u32(e[l], lo_bits[l]);
            int h = 0;
            for (int g = 0; g < GROUP; g++)
                h |= q == q_of[g][l];
            hv[l] = h & (e[l] >= lo[l]);
            any |= hv[l];
        }
        /* Most slots hold no frame's value in its buckets. */
        if (!any)
            continue;
        uint32_t hit = 0;
        for (int l = 0; l < FRAMES; l++)
            hit |= (uint32_t)hv[l] << l;
        while (hit) {
            const int l = __builtin_ctz(hit);
            hit &= hit - 1;
            const int64_t at = (int64_t)l * room + m[l]++;
            val[at] = e[l], wt[at] = kill[i];
        }
    }
}

static void hits_plain(const float *eps, int64_t n, const float *lo, const int32_t *lo_bits,
                       const uint32_t (*q_of)[FRAMES], const int32_t *kill, float *val, int32_t *wt, int64_t room,
                       int64_t *m)
{
    hits_body(eps, n, lo, lo_bits, q_of, kill, val, wt, room, m);
}
#if PMX_X86
PMX_TARGET_AVX2 static void hits_avx2(const float *eps, int64_t n, const float *lo, const int32_t *lo_bits,
                                      const uint32_t (*q_of)[FRAMES], const int32_t *kill, float *val, int32_t *wt,
                                      int64_t room, int64_t *m)
{
    hits_body(eps, n, lo, lo_bits, q_of, kill, val, wt, room, m);
}
PMX_TARGET_AVX512 static void hits_avx512(const float *eps, int64_t n, const float *lo, const int32_t *lo_bits,
                                          const uint32_t (*q_of)[FRAMES], const int32_t *kill, float *val,
                                          int32_t *wt, int64_t room, int64_t *m)
{
    hits_body(eps, n, lo, lo_bits, q_of, kill, val, wt, room, m);
}
#endif

typedef void (*Hits)(const float *, int64_t, const float *, const int32_t *, const uint32_t (*)[FRAMES],
                     const int32_t *, float *, int32_t *, int64_t, int64_t *);

static Hits hits_kernel(void)
{
#if PMX_X86
    static const Hits at_level[] = {hits_plain, hits_avx2, hits_avx512};
    return at_level[simd_level()];
#else
    return hits_plain;
#endif
}

/* Every frame's answers from a word's folded eps (n slots, layout of
 * lanes_up; kills kill[i]) and its tallies t at lo, for the frames in
 * `frames` and their B budgets (budgets + l B) into out + l B, as
 * answers_of gives them from the frame's own values: per GROUP budgets,
 * the bucket where each one's crossing lies in each frame, then one pass
 * over the slots (a slot's frames compared at once) gathering the values
 * in those buckets into the frame's lane_val, lane_wt (rarely more than a
 * few per frame), and each budget's answer from its bucket's. */
static void lanes_answers(Work *k, const float *eps, const int32_t *kill, int64_t n, const float *lo,
                          const Tally *t, Lanes frames, const int32_t *budgets, int64_t B, int64_t base_faces,
                          int64_t *out)
{
    const Hits hits = hits_kernel();
    int32_t lo_bits[FRAMES];
    for (int l = 0; l < FRAMES; l++)
        lo_bits[l] = bits_of(lo[l]);
    for (int64_t j0 = 0; j0 < B; j0 += GROUP) {
        /* Each frame's buckets of the group's budgets that its count at lo
         * exceeds (NO_BUCKET: none), and the weight left to pass inside them. */
        uint32_t q_of[GROUP][FRAMES];
        int64_t over_in[GROUP][FRAMES];
        const int n_at = (int)(B - j0 < GROUP ? B - j0 : GROUP);
        Lanes wanted = 0;
        for (int g = 0; g < GROUP; g++)
            for (int l = 0; l < FRAMES; l++) {
                q_of[g][l] = NO_BUCKET;
                const int64_t budget = g < n_at ? budgets[l * B + j0 + g] : -1;
                if (g >= n_at || !((frames >> l) & 1) || budget < base_faces)
                    continue;
                if (t[l].total <= budget) {
                    out[l * B + j0 + g] = -2;
                    continue;
                }
                q_of[g][l] = (uint32_t)crossing_bucket(k->lane_bucket + (int64_t)l * (BUCKETS + SPREAD), budget,
                                                       base_faces, &over_in[g][l]);
                wanted |= (Lanes)(1u << l);
            }
        if (!wanted)
            continue;
        /* The values >= lo in any of a frame's buckets, frame by frame. */
        int64_t m[FRAMES] = {0};
        hits(eps, n, lo, lo_bits, (const uint32_t(*)[FRAMES])q_of, kill, k->lane_val, k->lane_wt, k->lane_room, m);
        for (int l = 0; l < FRAMES; l++)
            for (int g = 0; g < n_at; g++)
                if (q_of[g][l] != NO_BUCKET)
                    out[l * B + j0 + g] = answer_in_bucket(k->lane_val + (int64_t)l * k->lane_room,
                                                           k->lane_wt + (int64_t)l * k->lane_room, m[l], q_of[g][l],
                                                           lo_bits[l], over_in[g][l]);
    }
}

/* A word's frames (views, one pixel units) as the own tolerances read them. */
static void word_views(const float *views, const float *units, WordViews *w)
{
    for (int l = 0; l < FRAMES; l++) {
        const float *v = views + l * PMX_VIEW;
        w->ex[l] = v[EYE], w->ey[l] = v[EYE + 1], w->ez[l] = v[EYE + 2];
        w->fx[l] = v[FORWARD], w->fy[l] = v[FORWARD + 1], w->fz[l] = v[FORWARD + 2];
    }
    for (int j = 0; j < LANES; j++)
        w->unit[j] = units[j % FRAMES];
    w->views = views;
}

/* The guesses of a word's frames: the word traversed once at each frame's
 * own tolerance lo (its row's; most pcols decided for all the frames at
 * once under the fat camera, words.c), every frame's eps folded bottom-up
 * at once (lanes_own, lanes_up), then per frame the tally of its eps and
 * the answers gathered from the crossing buckets of all its frames in one
 * pass over the word's slots (lanes_answers). An unsure
 * decision is read as a "keep" at lo, and a frame has one guess (its alt
 * the same): the second guess of one camera, with its unsure decisions as
 * collapses, would fold the frame's lane again for the few guesses it
 * mends, which the exact counts mend along the path for less. A frame
 * whose largest budget's answer lies below its lo gets -1 (a guess left to
 * its own traversal). */
static void words_work(void *arg)
{
    Batch *bt = arg;
    const PmxHierarchy *h = bt->h;
    const int64_t B = bt->B;
    Work k;
    if (!work_start(bt, &k, 1))
        return;
    PmxScratch *s = k.s;
    const unsigned mode = subnormals_off();
    const Kernels *kern = pmx_kernels();
    const LanesUp up = lanes_up();
    const OwnSlots own = own_slots();
    const int ortho = (bt->flags & PMX_ORTHOGRAPHIC) != 0;
    float *eps = k.lanes_room + FRAMES; /* row -1: -inf */
    for (int64_t w; (w = __atomic_fetch_add(&bt->cursor, 1, __ATOMIC_RELAXED)) < bt->K / FRAMES;) {
        const float *cameras = bt->cameras + w * FRAMES * PMX_CAMERA;
        const float *units = bt->units + w * FRAMES;
        float views[FRAMES * PMX_VIEW], fat[PMX_FAT], lo[FRAMES];
        for (int l = 0; l < FRAMES; l++) {
            pmx_view_of(cameras + l * PMX_CAMERA, ortho, views + l * PMX_VIEW);
            lo[l] = cameras[l * PMX_CAMERA + PMX_CAMERA - 1];
        }
        const int have_fat = pmx_fat_cameras(views, 1, FRAMES, fat) == PMX_OK;
        /* The word's traversal and per frame the faces the pcols that did
         * not run keep (unsure decisions as "keep"). */
        int64_t m = 0, at_once = 0;
        const int64_t n = traverse_word(kern, h, views, FRAMES, bt->flags, have_fat ? fat : NULL, s->ids, s->kid,
                                        s->visit, s->whole, s->yes, s->unsure, s->unsure_lanes, &m, &at_once);
        if (n < 0) {
            __atomic_store_n(&bt->status, PMX_BAD_TABLE, __ATOMIC_RELAXED);
            break;
        }
        PmxCounts counts[FRAMES];
        kern->resolve_word(h->kills, h->order, n, s->ids, s->kid, s->visit, s->whole, s->yes, s->ran_frames, NULL,
                           counts);
        /* Each slot's faces killed; every frame's eps. */
        for (int64_t i = 0; i < n; i++)
            s->kill[i] = h->kills[s->ids[i]];
        WordViews wv;
        word_views(views, units, &wv);
        lanes_own(h, s, n, &wv, lo, bt->flags, own, eps);
        up(eps, n, s->kid, s->ran_frames);
        /* Every frame's largest budget (its guesses start at inf) and its
         * tally (of the frames with a budget to meet). */
        const int32_t *budgets = bt->budgets + w * FRAMES * B;
        int64_t top[FRAMES];
        Lanes asked = 0;
        for (int l = 0; l < FRAMES; l++) {
            top[l] = largest_budget(budgets + l * B, B, bt->base_faces, k.lane_g + l * B, k.lane_g + l * B);
            asked |= (Lanes)((top[l] >= 0) << l);
        }
        if (!lane_room(&k, n, h->n_pcols + PMX_SPARE)) {
            __atomic_store_n(&bt->status, PMX_NO_MEMORY, __ATOMIC_RELAXED);
            break;
        }
        Tally tallies[FRAMES];
        lanes_tally(&k, eps, s->kill, n, lo, asked, bt->base_faces, tallies);
        /* The frames whose largest budget's answer does not lie below their
         * lo (answers_from's test): their answers, all frames at once. */
        Lanes found = 0, below = 0;
        for (int l = 0; l < FRAMES; l++) {
            float next = 0;
            const Tally t = tallies[l];
            if (top[l] >= 0 &&
                answers_below(t.total, t.total2, counts[l].kept, lo[l], top[l], bt->base_faces, -1, &next))
                below |= (Lanes)(1u << l);
            else if (top[l] >= 0)
                found |= (Lanes)(1u << l);
        }
        lanes_answers(&k, eps, s->kill, n, lo, tallies, found, budgets, B, bt->base_faces, k.lane_g);
        for (int l = 0; l < FRAMES; l++) {
            int64_t *g = k.lane_g + l * B;
            for (int64_t j = 0; j < B; j++) {
                if ((below >> l) & 1)
                    g[j] = -1;
                else if (((found >> l) & 1) && budgets[l * B + j] >= bt->base_faces && g[j] == -2)
                    g[j] = 0; /* met at lo */
            }
            put_guesses(bt, w * FRAMES + l, g, g);
        }
    }
    subnormals_back(mode);
    budget_give(&k);
}

PmxStatus pmx_budget_many(const PmxHierarchy *h, const float *cameras, const float *units, int64_t K, int flags,
                          const int32_t *budgets, int64_t B, int64_t base_faces, int32_t *guess, int32_t *guess_alt,
                          int words, const PmxRunner *run)
{
    if (words && K % FRAMES)
        return PMX_BAD_SIZE;
    Batch bt = {h, cameras, units, budgets, K, B, 0, base_faces, flags, {0, 0, 0}, guess, guess_alt, PMX_OK};
    /* The model's centre: the mean of the roots' centres. */
    double c[3] = {0, 0, 0};
    for (int64_t q = 0; q < h->n_roots; q++)
        for (int a = 0; a < 3; a++)
            c[a] += h->rows[q * ROW + CX + a];
    for (int a = 0; a < 3; a++)
        bt.centre[a] = (float)(h->n_roots ? c[a] / (double)h->n_roots : 0.0);
    run_shared(run, words ? words_work : batch_work, &bt);
    return bt.status;
}
