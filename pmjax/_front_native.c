/* Output-sensitive refinement on the CPU: the front traversal and the front
 * mesh as plain C loops over the flat arrays of a progressive mesh.
 *
 * The JAX front engine (pmjax/_front.py) pays a fixed cost of about a dozen
 * XLA kernels per generation of the forest; here a generation costs nothing
 * and a visited pcol costs its own arithmetic. The results are the bits of
 * the dense engine:
 *
 *  - a pcol's subtree bound is pmjax/_subtree.py's, with its margins and
 *    range guards (sound: "whole" guarantees that every pcol below collapses
 *    under the float32 predicate);
 *  - a pcol's own decision is certified: every comparison of the float32
 *    predicate (pmjax/_predicate.py) is evaluated here (in float32) together
 *    with a bound on how far ANY float32 evaluation of the same formula can be
 *    from the exact value (fused multiply-adds or not, any association, flush
 *    to zero), this one included. When the margin exceeds twice that bound,
 *    the float32 predicate must return the same bit; otherwise the pcol is
 *    "unsure" and the caller decides it with the float32 predicate itself;
 *  - the bottom-up recurrence is the dense engine's.
 *
 * One 64-byte row per pcol (the traversal reads scattered pcols), in the
 * forest's breadth-first order. Every entry point takes its scratch from the
 * caller and leaves it as it found it, so threads with their own scratch may
 * call concurrently. No allocation; the only global is the transpose chosen
 * for the processor, set once.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <string.h>

/* Columns of ProgressiveMesh.table (pmjax/_front.py TABLE_ATTRIBUTES, TABLE_BOUNDS).
 * The last, 1 / |axis| there, is not read: in the breadth-first table
 * (pmjax/_native.py NativeMesh) it holds the pcol's KIDS (int32 bits), so that
 * a visit reads one cache line. */
enum { CX, CY, CZ, NX, NY, NZ, RADIUS, SIN_A, COS_A, DELTA, MU, REACH, SPREAD, FACING, ERROR, KIDS, ROW };

/* The orientation bound projects the eye vector on the unit axis. It bounds
 * something only where the pcol's axis is unit within 1e-3 (elsewhere facing
 * is 2, pmjax/_subtree.py), so 1 / |axis| > AXIS_LOW, and the bound only grows
 * with the projection: the projection on the axis times AXIS_LOW is a lower
 * bound that keeps it sound. */
#define AXIS_LOW 0.998f

/* Layout of View.values (pmjax/_view.py). */
enum { EYE = 0, RIGHT = 3, UP = 6, FORWARD = 9, K = 12, ONE_PIXEL = 20, KAPPA2 = 21 };

/* Flags of a call. */
enum { TEST_FRUSTUM = 1, TEST_ORIENTATION = 2, TEST_SCREEN = 4, ORTHOGRAPHIC = 8 };

/* State of a visited slot: its own decision in the low bits, WHOLE when the
 * subtree bound decided it. */
enum { NO = 0, YES = 1, UNSURE = 2, WHOLE = 4 };

/* Margins of the subtree bounds: pmjax/_subtree.py MARGIN, SCREEN_MARGIN. */
#define MARGIN 0x1p-16f
#define SCREEN_MARGIN 0x1p-14f

/* Float32 rounding is relative only between underflow and overflow: a
 * comparison whose magnitudes leave [LOW, HIGH] is not certified, and a
 * subtree bound decides nothing where a descendant's test could leave it
 * (pmjax/_subtree.py LOW, HIGH). */
#define LOW 0x1p-100f
#define HIGH 0x1p100f

/* Certification. A comparison a < b of the float32 predicate is evaluated
 * here as d = a - b with the magnitude m (the same formula over absolute
 * values). Any float32 evaluation of it with at most 16 roundings on a path
 * (fused multiply-adds or not, any association) lies within GAMMA16 * m of the
 * exact value (Higham, Accuracy and Stability, ch. 3), this one as much as
 * XLA's; the view constants here are computed on the host, off XLA's by at most
 * VIEW relative in any one factor of a term. So |d| > REL * m (+ the flush
 * slack) fixes the sign of XLA's d. REL covers m's own rounding too. */
#define GAMMA16 (16.0f * 0x1p-24f / (1.0f - 16.0f * 0x1p-24f))
#define VIEW 0x1p-20f
#define REL ((2.0f * GAMMA16 + VIEW) * (1.0f + 0x1p-18f))
/* With flush to zero (XLA on the CPU) an operation can also lose up to the
 * smallest normal float32, which downstream factors scale: FLUSH times the
 * square of a bound on those factors covers the predicate's operations. */
#define FLUSH 0x1p-118f

/* Two sure-bits per decision: Y (surely true), N (surely false); neither:
 * unsure. */
typedef struct {
    _Bool y, n;
} Sure;

/* exact_zero: also certify d = m = 0 (every term zero: a < b is false in any
 * evaluation). The usual perspective views leave it out: there it takes a
 * zero radius or cosine together with an eye vector orthogonal to the axis
 * coordinate by coordinate, and such a pcol goes to the float32 predicate as
 * unsure (there the certificate cost a tenth of the decision's instructions). */
static inline Sure less_than(float d, float m, float slack, const int exact_zero)
{
    float bound = REL * m + slack;
    _Bool ok = m < HIGH; /* false for an overflow, inf or NaN */
    _Bool zero = exact_zero && ((m == 0.0f) & (d == 0.0f));
    Sure s = {ok & (d < -bound), ok & ((d > bound) | zero)};
    return s;
}
static inline Sure less(float d, float m, float slack) { return less_than(d, m, slack, 1); }
static inline Sure sure_or(Sure a, Sure b) { Sure s = {a.y | b.y, a.n & b.n}; return s; }
static inline Sure sure_and(Sure a, Sure b) { Sure s = {a.y & b.y, a.n | b.n}; return s; }

/* The hierarchy in breadth-first order of its forest (pmjax/_native.py
 * NativeMesh): position q holds pcol order[q]; the created children of q sit
 * side by side at kids_first(kids) (their number in the low two bits, kids
 * the row's KIDS column), so a pruned breadth-first walk reads the table in
 * increasing order. The sign bit of KIDS says that the pcol kills other than
 * two faces (two: an inner edge of a manifold, nearly every pcol), so that the
 * traversal knows what a slot keeps without reading kills[]. */
typedef struct {
    const float *table;   /* [P, ROW], by position; KIDS: kills != 2 << 31 | first child's position << 2 | number
                             of created children */
    const int32_t *kills; /* [P] by position */
    const int32_t *order; /* [P] pcol at each position */
    int64_t n_pcols;
} Mesh;

/* The first child's position in a row's KIDS, and the faces a slot's pcol
 * kills (pos: its position). */
enum { KIDS_FIRST = 0x1FFFFFFF };
static inline int32_t kids_first(int32_t kids) { return (int32_t)(((uint32_t)kids >> 2) & KIDS_FIRST); }
static inline int32_t kids_kills(const Mesh *pm, int32_t kids, int32_t pos) { return kids < 0 ? pm->kills[pos] : 2; }

/* One camera's constants (float32, host-computed, see VIEW). */
typedef struct {
    float e[3], r[3], u[3], f[3], k[8], kappa2;
    float kabs; /* 1 + |a_x| + |a_y| + l_x + l_y + |b_x| + |b_y| + kappa2: the view's factor bound */
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
    /* An infinite kappa2 (tau = inf) enters only the screen test, which treats
     * it apart: it does not bound the other tests' factors. */
    v->kabs = 1.0f + fabsf(v->k[0]) + fabsf(v->k[1]) + fabsf(v->k[2]) + fabsf(v->k[3]) + fabsf(v->k[4]) +
              fabsf(v->k[5]) + (isinf(v->kappa2) ? 0.0f : fabsf(v->kappa2));
    v->flags = flags;
}

#define BLOCK 16
#ifndef AHEAD
#define AHEAD 64 /* queue slots between a row's prefetch and its use */
#endif

/* max(x, 0) as a select (fmaxf is a library call for its NaN rules). */
static inline float pos(float x) { return x > 0.0f ? x : 0.0f; }

/* The rows of a block of pcols as columns: col[c][j] is column c of pcol j. */
typedef float Columns[ROW][BLOCK];

/* Every pcol of a block at once, without branches (the compiler vectorizes
 * the loop over the block): its subtree bound (pmjax/_subtree.py
 * subtree_collapses: does every pcol below collapse?) and its own decision
 * (pmjax/_predicate.py view_collapse_mask), certified. state[j] = own
 * decision (YES, NO, UNSURE) | WHOLE. */
/* One camera's constants as the per-lane decision reads them. */
typedef struct {
    float ex, ey, ez;
    float R0, R1, R2, U0, U1, U2, F0, F1, F2; /* right, up, forward */
    float k0, k1, k2, k3, k4, k5, k6, k7;     /* Camera.frustum_frame constants */
    float kappa2, kabs;
    float kfac; /* 1 + |a_x| + |a_y| + l_x + l_y */
    float kpad; /* |b_x| + |b_y| + |near| + |far| */
    int frustum, orientation, screen;
    /* Absolute values of the axes and constants (the certificates' magnitudes). */
    float aR0, aR1, aR2, aU0, aU1, aU2, aF0, aF1, aF2;
    float ak0, ak1, ak2, ak3, ak4, ak5, ak6, ak7;
} Lane;

static inline Lane lane_of(const View *w)
{
    const float *k = w->k;
    Lane L = {w->e[0], w->e[1], w->e[2], w->r[0], w->r[1], w->r[2], w->u[0], w->u[1], w->u[2], w->f[0], w->f[1],
              w->f[2], k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7], w->kappa2, w->kabs, 0, 0, 0, 0, 0};
    L.kfac = 1 + fabsf(w->k[0]) + fabsf(w->k[1]) + w->k[4] + w->k[5];
    L.kpad = fabsf(w->k[2]) + fabsf(w->k[3]) + fabsf(w->k[6]) + fabsf(w->k[7]);
    L.frustum = (w->flags & TEST_FRUSTUM) != 0, L.orientation = (w->flags & TEST_ORIENTATION) != 0;
    L.screen = (w->flags & TEST_SCREEN) != 0;
    L.aR0 = fabsf(L.R0), L.aR1 = fabsf(L.R1), L.aR2 = fabsf(L.R2);
    L.aU0 = fabsf(L.U0), L.aU1 = fabsf(L.U1), L.aU2 = fabsf(L.U2);
    L.aF0 = fabsf(L.F0), L.aF1 = fabsf(L.F1), L.aF2 = fabsf(L.F2);
    L.ak0 = fabsf(k[0]), L.ak1 = fabsf(k[1]), L.ak2 = fabsf(k[2]), L.ak3 = fabsf(k[3]);
    L.ak4 = fabsf(k[4]), L.ak5 = fabsf(k[5]), L.ak6 = fabsf(k[6]), L.ak7 = fabsf(k[7]);
    return L;
}

/* One pcol's row as named scalars (the vectorizer keeps a struct of scalars
 * in registers, where an array would be memory). */
typedef struct {
    float cx, cy, cz, nx, ny, nz, radius, sin_a, cos_a, delta, mu, reach, spread, facing, error;
} Pcol;

static inline Pcol pcol_at(float (*restrict col)[BLOCK], int j)
{
    Pcol q = {col[CX][j],     col[CY][j],    col[CZ][j],     col[NX][j],    col[NY][j],     col[NZ][j],
              col[RADIUS][j], col[SIN_A][j], col[COS_A][j],  col[DELTA][j], col[MU][j],     col[REACH][j],
              col[SPREAD][j], col[FACING][j], col[ERROR][j]};
    return q;
}

/* The subtree bounds (pmjax/_subtree.py subtree_collapses), each "does every
 * pcol below collapse?" by one test, for an eye at distance d (d2 = d * d in
 * float32) and camera coordinates x, y, z of the pcol's centre. A bound's
 * reach or spread may be grown to cover several eyes at once (decide_fat). */

/* The reach sphere outside a frustum plane, by the margin. */
static inline _Bool bound_outside(float x, float y, float z, float reach, float k0, float k1, float k2, float k3,
                                  float k4, float k5, float k6, float k7, float kfac, float kpad)
{
    const float sx = z * k0 + k2, sy = z * k1 + k3;
    const float size = (fabsf(x) + fabsf(y) + fabsf(z) + reach) * kfac;
    const float m = MARGIN * (size + kpad);
    const _Bool out = (z + reach < k6 - m) | (z - reach > k7 + m) | (sx - fabsf(x) + reach * k4 < -m) |
                      (sy - fabsf(y) + reach * k5 < -m);
    return out & (m > LOW) & (m < HIGH);
}

/* Every cone below facing away from every eye ray into the reach sphere
 * (perspective; hv the eye vector along the axis). */
static inline _Bool bound_away(float hv, float d2, float d, float reach, float facing)
{
    const float a = hv * AXIS_LOW;
    const float lhs = a * sqrtf(pos(d2 - reach * reach)) - reach * sqrtf(pos(d2 - a * a));
    const float gap = d - reach, far = d + reach;
    return (d2 > reach * reach) & (a > 0) & (lhs > d2 * facing) & (gap * gap > 0x1p-80f) & (far * far < HIGH);
}

/* Every error below under the screen tolerance (perspective; false for an
 * infinite kappa2, which decide_one treats apart), for eyes at distances
 * between d_lo and d_hi (one eye: both d). */
static inline _Bool bound_small(float d_lo, float d_hi, float spread, float e2, float kappa2)
{
    const float room = d_lo - spread - SCREEN_MARGIN * (d_hi + spread);
    const float room2 = room * room, far2 = (d_hi + spread) * (d_hi + spread);
    return (room > 0) & (e2 < kappa2 * room2 * (1 - SCREEN_MARGIN)) &
           (kappa2 * (room2 < 1.0f ? room2 * room2 : room2) > LOW) & (kappa2 * far2 * far2 < HIGH) &
           (e2 * far2 < HIGH);
}

/* One pcol (q) under one camera (L): its subtree bound (pmjax/_subtree.py
 * subtree_collapses: does every pcol below collapse?) and its own decision
 * (pmjax/_predicate.py view_collapse_mask), certified. Returns the own
 * decision (YES, NO, UNSURE) | WHOLE. No branches: the loops that call it, over
 * the pcols of a block or over the frames of a word, are vectorized. With
 * all_tests (a constant), the view is a fast_view. */
static inline __attribute__((always_inline)) int32_t decide_one(const Lane *L, const Pcol q, const int ortho,
                                                                const int all_tests)
{
    const float R0 = L->R0, R1 = L->R1, R2 = L->R2, U0 = L->U0, U1 = L->U1, U2 = L->U2;
    const float F0 = L->F0, F1 = L->F1, F2 = L->F2;
    const float k0 = L->k0, k1 = L->k1, k2 = L->k2, k3 = L->k3, k4 = L->k4, k5 = L->k5, k6 = L->k6, k7 = L->k7;
    const float kappa2 = L->kappa2, kabs = L->kabs, kfac = L->kfac, kpad = L->kpad;
    const _Bool frustum = all_tests | L->frustum, orientation = all_tests | L->orientation;
    const _Bool screen = all_tests | L->screen;
    const _Bool kinf = !all_tests & (kappa2 == INFINITY);
    const int exact_zero = (!all_tests) | ortho;
    {
        const float vx = q.cx - L->ex, vy = q.cy - L->ey, vz = q.cz - L->ez;
        const float nx = q.nx, ny = q.ny, nz = q.nz;
        const float r = q.radius, ar = fabsf(r), sa = q.sin_a, ca = q.cos_a;
        const float delta = q.delta, mu = q.mu;
        const float reach = q.reach, spread = q.spread, error = q.error;
        const float d2 = vx * vx + vy * vy + vz * vz;
        const float d = sqrtf(d2);
        const float avx = fabsf(vx), avy = fabsf(vy), avz = fabsf(vz);
        const float x = vx * R0 + vy * R1 + vz * R2;
        const float y = vx * U0 + vy * U1 + vz * U2;
        const float z = vx * F0 + vy * F1 + vz * F2;
        const float mx = avx * L->aR0 + avy * L->aR1 + avz * L->aR2;
        const float my = avx * L->aU0 + avy * L->aU1 + avz * L->aU2;
        const float mz = avx * L->aF0 + avy * L->aF1 + avz * L->aF2;
        const float sx = z * k0 + k2, sy = z * k1 + k3;
        const float hf = nx * F0 + ny * F1 + nz * F2; /* axis along the view (orthographic) */
        const float mhf = fabsf(nx * F0) + fabsf(ny * F1) + fabsf(nz * F2);
        const float hv = vx * nx + vy * ny + vz * nz; /* eye vector along the axis (perspective) */
        const float mhv = fabsf(vx * nx) + fabsf(vy * ny) + fabsf(vz * nz);

        /* -- subtree bound -- */
        _Bool whole = frustum & bound_outside(x, y, z, reach, L->k0, L->k1, L->k2, L->k3, L->k4, L->k5, L->k6,
                                              L->k7, kfac, kpad);
        const float e2 = error * error;
        if (ortho) {
            whole |= orientation & (hf * AXIS_LOW > q.facing);
            whole |= screen & (e2 < kappa2 * (1 - SCREEN_MARGIN)) & (all_tests | (kappa2 > LOW)) & (e2 < HIGH);
            whole |= screen & kinf & (e2 < HIGH); /* every finite deviation is below inf */
        } else {
            whole |= orientation & bound_away(hv, d2, d, reach, q.facing);
            whole |= screen & bound_small(d, d, spread, e2, kappa2);
            /* tau = inf: a pcol below is small when its distance squared is
             * positive in float32 (then inf * d2 is inf) and its terms finite. */
            float room = d - spread - SCREEN_MARGIN * (d + spread);
            whole |= screen & kinf & (room > 0) & (room * room > LOW) & (e2 * (d + spread) * (d + spread) < HIGH);
        }

        /* -- own decision, certified -- */
        /* Flush slack: the smallest normal scaled by a bound on the factors
         * that can multiply a flushed intermediate downstream (squared: at
         * most two such factors). Beyond the guard nothing is certified. */
        const float scale = 1 + avx + avy + avz + ar + fabsf(nx) + fabsf(ny) + fabsf(nz) + fabsf(sa) + fabsf(ca) +
                            fabsf(delta) + fabsf(mu);
        const float factor = scale * scale * kabs;
        const float slack = FLUSH * factor * factor;
        const _Bool guard = (scale < 0x1p24f) & (all_tests | (kabs < 0x1p16f)) & (d2 < HIGH);
        Sure out = {0, 1};
        {
            /* (z + r < near) | (z - r > far) | (sx - |x| < -r lx) | (sy - |y| < -r ly) */
            const float msx = mz * L->ak0 + L->ak2, msy = mz * L->ak1 + L->ak3;
            Sure f = less_than(z + r - k6, mz + ar + L->ak6, slack, exact_zero);
            f = sure_or(f, less_than(k7 - (z - r), L->ak7 + mz + ar, slack, exact_zero));
            f = sure_or(f, less_than(sx - fabsf(x) + r * k4, msx + mx + ar * L->ak4, slack, exact_zero));
            f = sure_or(f, less_than(sy - fabsf(y) + r * k5, msy + my + ar * L->ak5, slack, exact_zero));
            out.y = frustum & f.y;
            out.n = (!frustum) | f.n;
        }
        const float h = ortho ? hf : hv, mh = ortho ? mhf : mhv;
        const float s = ortho ? 1.0f : d2; /* d2 is a sum of squares: its magnitude is itself */
        {
            /* ca > 0 is exact, but XLA reads a subnormal ca as 0. */
            const Sure cos_positive = {ca >= 0x1p-126f, ca <= 0.0f};
            Sure away;
            if (ortho) {
                /* (ca > 0) & (h > sa) */
                away = sure_and(cos_positive, less_than(sa - h, fabsf(sa) + mh, slack, exact_zero));
            } else {
                /* (t2 > 0) & (ca > 0) & (ca ca t2 > sr sr) & (g > 0) & (g g > sa sa t2) */
                float t2 = d2 - r * r, mt2 = d2 + r * r;
                float sr = sa * r, g = h - ca * r, mg = mh + fabsf(ca) * ar;
                away = sure_and(cos_positive, less_than(-t2, mt2, slack, exact_zero));
                away = sure_and(away, less_than(sr * sr - ca * ca * t2, sr * sr + ca * ca * mt2, slack, exact_zero));
                away = sure_and(away, less_than(-g, mg, slack, exact_zero));
                away = sure_and(away, less_than(sa * sa * t2 - g * g, sa * sa * mt2 + mg * mg, slack, exact_zero));
            }
            away.y &= orientation;
            away.n |= !orientation;
            out = sure_or(out, away);
        }
        {
            /* (mu2 < kappa2 s) & (normal2 < kappa2 s s) */
            const float normal2 = delta * delta * (s - h * h), mnormal2 = delta * delta * (s + mh * mh);
            Sure small = less_than(mu * mu - kappa2 * s, mu * mu + kappa2 * s, slack, exact_zero);
            small = sure_and(small, less_than(normal2 - kappa2 * s * s, mnormal2 + kappa2 * s * s, slack, exact_zero));
            /* tau = inf: small exactly when s > 0 in float32 (inf * s is inf, inf
             * * 0 is NaN) and mu2, normal2 are finite. */
            const _Bool positive = ortho | (d2 > LOW), finite = (mu * mu + mnormal2) < HIGH;
            small.y = (kinf & positive & finite) | ((!kinf) & small.y);
            small.n = (!kinf) & small.n;
            small.y &= screen;
            small.n |= !screen;
            out = sure_or(out, small);
        }
        /* YES = 1, NO = 0, UNSURE = 2, WHOLE = 4, without branches. */
        const _Bool yes = guard & out.y, sure = guard & (out.y | out.n);
        return yes | (!sure << 1) | ((whole != 0) << 2);
    }
}

/* The usual view, for which decide_one is compiled with its uniform
 * conditions as constants (GCC builds the mask of a condition that is uniform
 * over the lanes bit by bit, 15 shifts and ors each): every test on, a finite
 * kappa2 above LOW, view factors below 2^16. */
static inline int fast_view(const View *w)
{
    return (w->flags & 7) == 7 && !isinf(w->kappa2) && w->kappa2 > LOW && w->kabs < 0x1p16f;
}

/* The cameras of the lanes of one decision pass, struct of arrays: the
 * frames of a word, or one camera in every lane (a block of pcols). Each lane
 * reads its own camera and its own pcol, so that no condition is uniform over
 * the lanes for the compiler (see fast_view). */
typedef struct {
    float ex[BLOCK], ey[BLOCK], ez[BLOCK], R[3][BLOCK], U[3][BLOCK], F[3][BLOCK], k[8][BLOCK];
    float kappa2[BLOCK], kabs[BLOCK], kfac[BLOCK], kpad[BLOCK];
    float aR[3][BLOCK], aU[3][BLOCK], aF[3][BLOCK], ak[8][BLOCK]; /* absolute values */
    int frustum, orientation, screen, ortho, fast;
} Frames;

static void load_frames(Frames *fr, const float *views, int n_frames, int flags)
{
    for (int l = 0; l < BLOCK; l++) {
        View w;
        load_view(&w, views + 22 * (l < n_frames ? l : 0), flags); /* spare lanes repeat the first */
        Lane L = lane_of(&w);
        fr->ex[l] = L.ex, fr->ey[l] = L.ey, fr->ez[l] = L.ez;
        fr->R[0][l] = L.R0, fr->R[1][l] = L.R1, fr->R[2][l] = L.R2;
        fr->U[0][l] = L.U0, fr->U[1][l] = L.U1, fr->U[2][l] = L.U2;
        fr->F[0][l] = L.F0, fr->F[1][l] = L.F1, fr->F[2][l] = L.F2;
        fr->aR[0][l] = L.aR0, fr->aR[1][l] = L.aR1, fr->aR[2][l] = L.aR2;
        fr->aU[0][l] = L.aU0, fr->aU[1][l] = L.aU1, fr->aU[2][l] = L.aU2;
        fr->aF[0][l] = L.aF0, fr->aF[1][l] = L.aF1, fr->aF[2][l] = L.aF2;
        const float k[8] = {L.k0, L.k1, L.k2, L.k3, L.k4, L.k5, L.k6, L.k7};
        const float ak[8] = {L.ak0, L.ak1, L.ak2, L.ak3, L.ak4, L.ak5, L.ak6, L.ak7};
        for (int i = 0; i < 8; i++)
            fr->k[i][l] = k[i], fr->ak[i][l] = ak[i];
        fr->kappa2[l] = L.kappa2, fr->kabs[l] = L.kabs, fr->kfac[l] = L.kfac, fr->kpad[l] = L.kpad;
        fr->frustum = L.frustum, fr->orientation = L.orientation, fr->screen = L.screen;
        fr->fast = (l == 0 || fr->fast) && fast_view(&w);
    }
    fr->ortho = (flags & ORTHOGRAPHIC) != 0;
}

static inline Lane frame_at(const Frames *fr, int l)
{
    Lane L = {fr->ex[l],    fr->ey[l],    fr->ez[l],    fr->R[0][l],   fr->R[1][l],   fr->R[2][l],
              fr->U[0][l],  fr->U[1][l],  fr->U[2][l],  fr->F[0][l],   fr->F[1][l],   fr->F[2][l],
              fr->k[0][l],  fr->k[1][l],  fr->k[2][l],  fr->k[3][l],   fr->k[4][l],   fr->k[5][l],
              fr->k[6][l],  fr->k[7][l],  fr->kappa2[l], fr->kabs[l],  fr->kfac[l],   fr->kpad[l],
              fr->frustum,  fr->orientation, fr->screen,
              fr->aR[0][l], fr->aR[1][l], fr->aR[2][l], fr->aU[0][l], fr->aU[1][l], fr->aU[2][l],
              fr->aF[0][l], fr->aF[1][l], fr->aF[2][l], fr->ak[0][l], fr->ak[1][l], fr->ak[2][l],
              fr->ak[3][l], fr->ak[4][l], fr->ak[5][l], fr->ak[6][l], fr->ak[7][l]};
    return L;
}

/* Lane l: pcol col[.][l] under camera l; all_tests a constant (decide_one). */
static inline __attribute__((always_inline)) void decide_each_lane(const Frames *restrict fr,
                                                                   float (*restrict col)[BLOCK],
                                                                   int32_t *restrict code, const int ortho,
                                                                   const int all_tests)
{
#pragma omp simd
    for (int l = 0; l < BLOCK; l++) {
        const Lane L = frame_at(fr, l);
        code[l] = decide_one(&L, pcol_at(col, l), ortho, all_tests);
    }
}
static inline __attribute__((always_inline)) void decide_lanes(const Frames *restrict fr, float (*restrict col)[BLOCK],
                                                               int32_t *restrict code, const int ortho)
{
    if (fr->fast)
        decide_each_lane(fr, col, code, ortho, 1);
    else
        decide_each_lane(fr, col, code, ortho, 0);
}

/* The two projections, each a loop without branches, compiled for the
 * vector units the processor has; the usual views (fast_view) with their
 * uniform conditions as constants. */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define VECTOR_CLONES __attribute__((target_clones("avx512f", "arch=x86-64-v3", "avx2", "default")))
#else
#define VECTOR_CLONES
#endif
VECTOR_CLONES static void decide_perspective(const Frames *fr, Columns col, int32_t *code)
{
    decide_lanes(fr, col, code, 0);
}
VECTOR_CLONES static void decide_orthographic(const Frames *fr, Columns col, int32_t *code)
{
    decide_lanes(fr, col, code, 1);
}
/* One pcol's row in every lane (the frames of a word), broadcast here at the
 * vector width of the decision that reads it; the frames' decisions as
 * masks (one bit per frame: WHOLE, YES, UNSURE), built at that width too. */
typedef uint16_t Lanes;
static inline __attribute__((always_inline)) void decide_row_lanes(const Frames *fr, const float *row, Lanes *masks,
                                                                   const int ortho)
{
    Columns col;
    int32_t code[BLOCK];
    for (int c = 0; c < ROW; c++)
        for (int l = 0; l < BLOCK; l++)
            col[c][l] = row[c];
    decide_lanes(fr, col, code, ortho);
    Lanes wh = 0, y = 0, u = 0;
    for (int l = 0; l < BLOCK; l++) {
        wh |= (Lanes)(((code[l] & WHOLE) != 0) << l);
        y |= (Lanes)(((code[l] & 3) == YES) << l);
        u |= (Lanes)(((code[l] & 3) == UNSURE) << l);
    }
    masks[0] = wh, masks[1] = y, masks[2] = u;
}
VECTOR_CLONES static void decide_row_perspective(const Frames *fr, const float *row, Lanes *masks)
{
    decide_row_lanes(fr, row, masks, 0);
}
VECTOR_CLONES static void decide_row_orthographic(const Frames *fr, const float *row, Lanes *masks)
{
    decide_row_lanes(fr, row, masks, 1);
}

/* ---- the frames of a word at once: a "fat" camera ------------------------ */

/* Consecutive frames of a path see nearly the same thing, so most pcols of a
 * word are decided alike by all its frames. A fat camera covers the word's
 * frames (pmx_fat_cameras below; all of them perspective views with every
 * test on and the same intrinsics and tolerance, the clip distances free):
 *
 *  - every frame's eye lies within rho of the eye centre e, so every
 *    distance from a frame's eye is within rho of the distance from e, and
 *    the rays from a frame's eye into a sphere are rays from e into the
 *    sphere grown by rho;
 *  - every frame's eye lies within a capsule (a segment a + [0, 1] ab, the
 *    path's chord, grown by its radius), so every distance from a frame's eye
 *    is at least the distance from the segment less the radius, and at most
 *    the distance from its farther end plus the radius (tighter than the
 *    ball for the distance tests along a path);
 *  - in camera coordinates a point c of frame f is R_f (c - p) + t_f for a
 *    pivot p (the point the frames look at, where there is one); with
 *    |R_f - R| <= eps (spectral norm) and |t_f - t| <= tau, it lies within
 *    shift(c) = tau + eps |c - p| of R (c - p) + t.
 *
 * A pcol is decided for all the frames in one pass over 16 pcols when either
 *
 *  - FAT_WHOLE: a subtree bound holds with the sphere grown to cover every
 *    frame (the geometric facts above; the bounds' margins cover this
 *    evaluation's rounding as they cover a frame's), so every frame's
 *    subtree collapses; or
 *  - FAT_NO: for every frame, every test of the float32 predicate surely
 *    says "keep": each comparison is bounded over the frames by a value
 *    computed here from the fat camera, with a magnitude that bounds both
 *    this evaluation's and any frame's (so `less` certifies it as it
 *    certifies a frame's comparison).
 *
 * Otherwise (about one slot in six along the dragon's orbit) the frames are
 * decided one by one. Either way every frame gets the bits of its own
 * refinement. */
typedef struct {
    float ex, ey, ez, rho;                            /* eye centre; |e_f - e| <= rho */
    float px, py, pz;                                 /* pivot */
    float R0, R1, R2, U0, U1, U2, F0, F1, F2;         /* reference rotation (right, up, forward) */
    float tx, ty, tz;                                 /* the pivot in reference camera coordinates */
    float eps, tau;                                   /* |R_f - R| <= eps, |R_f (p - e_f) - t| <= tau */
    float ax, ay, az, abx, aby, abz, ab_inv, capsule; /* every e_f within capsule of a + [0, 1] ab; 1 / |ab|^2 */
    float k0, k1, k2, k3, k4, k5, kappa2, kfac, kabs; /* the frames' common constants */
    float near_lo, near_hi, far_lo, far_hi, kpad;     /* clip distances over the frames, the largest kpad */
} Fat;

/* Layout of a fat camera (pmjax/_native.py FAT_VALUES). */
enum {
    FAT_EYE = 0, FAT_RHO = 3, FAT_PIVOT = 4, FAT_ROTATION = 7, FAT_T = 16, FAT_EPS = 19, FAT_TAU = 20,
    FAT_SEGMENT = 21, FAT_STEP = 24, FAT_STEP_INV = 27, FAT_CAPSULE = 28, FAT_N = 29
};

/* Decisions of the fat pass. */
enum { FAT_OPEN = 0, FAT_WHOLE = 1, FAT_NO = 2 };

/* Frames can share the fat camera fat (FAT_N floats, or NULL): it is given
 * and finite, and they are perspective views of the usual kind (fast_view)
 * with the same constants (intrinsics and tolerance) but for the clip
 * distances. */
static int fat_applies(const Frames *fr, const float *fat, int n_frames)
{
    if (!fat || !fr->fast || fr->ortho)
        return 0;
    for (int i = 0; i < FAT_N; i++)
        if (!isfinite(fat[i]))
            return 0;
    for (int l = 1; l < n_frames; l++) {
        for (int i = 0; i < 6; i++)
            if (fr->k[i][l] != fr->k[i][0])
                return 0;
        if (fr->kappa2[l] != fr->kappa2[0])
            return 0;
    }
    return 1;
}

static void load_fat(Fat *W, const float *fat, const Frames *fr, int n_frames)
{
    W->ex = fat[FAT_EYE], W->ey = fat[FAT_EYE + 1], W->ez = fat[FAT_EYE + 2], W->rho = fat[FAT_RHO];
    W->px = fat[FAT_PIVOT], W->py = fat[FAT_PIVOT + 1], W->pz = fat[FAT_PIVOT + 2];
    const float *R = fat + FAT_ROTATION;
    W->R0 = R[0], W->R1 = R[1], W->R2 = R[2], W->U0 = R[3], W->U1 = R[4], W->U2 = R[5];
    W->F0 = R[6], W->F1 = R[7], W->F2 = R[8];
    W->tx = fat[FAT_T], W->ty = fat[FAT_T + 1], W->tz = fat[FAT_T + 2];
    W->eps = fat[FAT_EPS], W->tau = fat[FAT_TAU];
    W->ax = fat[FAT_SEGMENT], W->ay = fat[FAT_SEGMENT + 1], W->az = fat[FAT_SEGMENT + 2];
    W->abx = fat[FAT_STEP], W->aby = fat[FAT_STEP + 1], W->abz = fat[FAT_STEP + 2];
    W->ab_inv = fat[FAT_STEP_INV], W->capsule = fat[FAT_CAPSULE];
    W->k0 = fr->k[0][0], W->k1 = fr->k[1][0], W->k2 = fr->k[2][0], W->k3 = fr->k[3][0];
    W->k4 = fr->k[4][0], W->k5 = fr->k[5][0];
    W->kappa2 = fr->kappa2[0], W->kfac = fr->kfac[0], W->kabs = fr->kabs[0];
    W->near_lo = W->near_hi = fr->k[6][0], W->far_lo = W->far_hi = fr->k[7][0], W->kpad = fr->kpad[0];
    for (int l = 1; l < n_frames; l++) {
        W->near_lo = fminf(W->near_lo, fr->k[6][l]), W->near_hi = fmaxf(W->near_hi, fr->k[6][l]);
        W->far_lo = fminf(W->far_lo, fr->k[7][l]), W->far_hi = fmaxf(W->far_hi, fr->k[7][l]);
        W->kpad = fmaxf(W->kpad, fr->kpad[l]);
    }
}

/* Grows a float32 sum of a few rounded terms past its exact value. */
#define GROW (1.0f + 0x1p-22f)
/* Grows a float32 bound on a frame's magnitude (computed with a few
 * roundings from d, which is within a few ulps of the exact distance). */
#define GROW_M (1.0f + 0x1p-18f)

/* One pcol under every frame of the fat camera W: FAT_WHOLE, FAT_NO or
 * FAT_OPEN (decide the frames one by one). No branches (vectorized over the
 * pcols of a block). */
static inline __attribute__((always_inline)) int32_t decide_fat_one(const Fat *W, const Pcol q)
{
    const float rho = W->rho, eps = W->eps, tau = W->tau, kappa2 = W->kappa2, kfac = W->kfac, kpad = W->kpad;
    const float k0 = W->k0, k1 = W->k1, k2 = W->k2, k3 = W->k3, k4 = W->k4, k5 = W->k5;
    const float nx = q.nx, ny = q.ny, nz = q.nz, r = q.radius, ar = fabsf(r), sa = q.sin_a, ca = q.cos_a;
    const float delta = q.delta, mu = q.mu;
    /* Distances from the eye centre: a frame's is within rho. */
    const float vx = q.cx - W->ex, vy = q.cy - W->ey, vz = q.cz - W->ez;
    const float d2 = vx * vx + vy * vy + vz * vz, d = sqrtf(d2);
    const float dhi = d + rho, dlo = pos(d - rho), dhi2 = dhi * dhi;
    const float v1 = fabsf(vx) + fabsf(vy) + fabsf(vz);
    /* Tighter along a path: the distance from the capsule's segment, less
     * the rounding of the projection (the point found is within
     * 2^-18 (|c - a|_1 + |ab|_1) of the nearest), less the capsule radius;
     * and the farther end, plus the radius. */
    const float ox = q.cx - W->ax, oy = q.cy - W->ay, oz = q.cz - W->az;
    const float along = (ox * W->abx + oy * W->aby + oz * W->abz) * W->ab_inv;
    const float at = along > 0.0f ? (along < 1.0f ? along : 1.0f) : 0.0f;
    const float fx = ox - at * W->abx, fy = oy - at * W->aby, fz = oz - at * W->abz;
    const float bx = ox - W->abx, by = oy - W->aby, bz = oz - W->abz;
    const float slop = 0x1p-18f * (fabsf(ox) + fabsf(oy) + fabsf(oz) + fabsf(W->abx) + fabsf(W->aby) + fabsf(W->abz));
    const float path_lo = pos(sqrtf(fx * fx + fy * fy + fz * fz) - slop - W->capsule);
    const float end_a = ox * ox + oy * oy + oz * oz, end_b = bx * bx + by * by + bz * bz;
    const float path_hi = sqrtf(end_a > end_b ? end_a : end_b) + W->capsule;
    /* Either bound holds: the tighter of each. */
    const float near_d = dlo > path_lo ? dlo : path_lo, far_d = dhi < path_hi ? dhi : path_hi;
    const float far_d2 = far_d * far_d;
    /* Camera coordinates about the pivot: a frame's are within shift of these. */
    const float px = q.cx - W->px, py = q.cy - W->py, pz = q.cz - W->pz;
    const float dp = sqrtf(px * px + py * py + pz * pz);
    const float x = px * W->R0 + py * W->R1 + pz * W->R2 + W->tx;
    const float y = px * W->U0 + py * W->U1 + pz * W->U2 + W->ty;
    const float z = px * W->F0 + py * W->F1 + pz * W->F2 + W->tz;
    const float shift = (tau + eps * dp) * GROW; /* of the centre */
    const float hv = vx * nx + vy * ny + vz * nz, mhv = fabsf(vx * nx) + fabsf(vy * ny) + fabsf(vz * nz);
    const float n1 = fabsf(nx) + fabsf(ny) + fabsf(nz); /* >= |n| */

    /* -- every frame's subtree bound, the spheres grown to cover the frames -- */
    /* (outside the nearest near plane or beyond the farthest far plane) */
    const float e2 = q.error * q.error;
    const _Bool whole = bound_outside(x, y, z, (q.reach + tau + eps * (dp + q.reach)) * GROW, k0, k1, k2, k3, k4,
                                      k5, W->near_lo, W->far_hi, kfac, kpad) |
                        bound_away(hv, d2, d, (q.reach + rho) * GROW, q.facing) |
                        bound_small(near_d, far_d, q.spread, e2, kappa2);

    /* -- every frame's own decision surely "keep" -- */
    /* Each comparison's bound over the frames, with the magnitude of this
     * evaluation plus a bound on a frame's (factors as in decide_one, the
     * eye's coordinates grown by rho). */
    const float scale = (1 + v1 + 3 * rho + ar + n1 + fabsf(sa) + fabsf(ca) + fabsf(delta) + fabsf(mu)) * GROW_M;
    const float factor = scale * scale * W->kabs;
    const float slack = 2 * FLUSH * factor * factor;
    const _Bool guard = (scale < 0x1p24f) & (dhi2 < HIGH);
    /* Inside every frame's frustum: each plane's value at the centre, less
     * its change over the frames (a plane's normal has length 1, or k4, k5
     * for the side planes; the farthest near and nearest far plane), surely
     * positive. kpad bounds every frame's clip distances. */
    const float frame_m = (3 * dhi * GROW_M + ar) * kfac + kpad;
    const float fat_m =
        ((fabsf(px) + fabsf(py) + fabsf(pz)) * 3 + fabsf(W->tx) + fabsf(W->ty) + fabsf(W->tz) + ar + shift) *
            kfac * GROW_M + kpad;
    const float mf = frame_m + fat_m;
    const _Bool inside = less(z + r - W->near_hi - shift, mf, slack).n & less(W->far_lo - (z - r) - shift, mf, slack).n &
                         less(z * k0 + k2 - fabsf(x) + r * k4 - shift * k4 * GROW_M, mf, slack).n &
                         less(z * k1 + k3 - fabsf(y) + r * k5 - shift * k5 * GROW_M, mf, slack).n;
    /* Not facing away from any frame: the cone's cosine is not positive, or
     * g = h - ca r is surely negative, or g^2 <= sa^2 t2 surely (h = v . n
     * moves by at most rho |n| <= rho n1, t2 = d^2 - r^2). */
    const float hshift = rho * n1 * GROW;
    const float glo = hv - hshift - ca * r, ghi = hv + hshift - ca * r;
    const float mg_fat = mhv + hshift + fabsf(ca) * ar, mg_frame = dhi * n1 * GROW_M + fabsf(ca) * ar;
    const float g2 = glo * glo > ghi * ghi ? glo * glo : ghi * ghi;
    const _Bool toward = (ca <= 0.0f) | less(ghi, mg_fat + mg_frame, slack).y |
                         less(sa * sa * (dlo * dlo - r * r) - g2,
                              2 * sa * sa * (dhi2 * GROW_M + r * r) + mg_fat * mg_fat + mg_frame * mg_frame, slack)
                             .n;
    /* Too coarse for every frame: mu^2 >= kappa2 d^2 surely, or delta^2 (d^2 -
     * h^2) >= kappa2 d^4 surely, with d^2 - h^2 = |v x n|^2 + d^2 (1 - |n|^2)
     * and |v x n| moving by at most rho |n|. */
    const float wx = vy * nz - vz * ny, wy = vz * nx - vx * nz, wz = vx * ny - vy * nx;
    const float wlo = pos(sqrtf(wx * wx + wy * wy + wz * wz) - hshift), mw = v1 * n1 + hshift;
    const float nn = nx * nx + ny * ny + nz * nz;
    const _Bool coarse =
        less(mu * mu - kappa2 * far_d2, 2 * mu * mu + 2 * kappa2 * far_d2 * GROW_M, slack).n |
        less(delta * delta * (wlo * wlo - dhi2 * pos(nn - 1)) - kappa2 * far_d2 * far_d2,
             delta * delta * (mw * mw + dhi2 * (nn + 1) + dhi2 * (1 + n1 * n1) * GROW_M) +
                 2 * kappa2 * far_d2 * far_d2 * GROW_M,
             slack)
            .n;
    const _Bool keep = guard & inside & toward & coarse;
    return whole ? FAT_WHOLE : (keep ? FAT_NO : FAT_OPEN);
}

VECTOR_CLONES static void decide_fat(const Fat *W, Columns col, int32_t *code)
{
#pragma omp simd
    for (int l = 0; l < BLOCK; l++)
        code[l] = decide_fat_one(W, pcol_at(col, l));
}

/* The lanes of a block: code[l] = WHOLE where the subtree bound decides, |
 * the own decision (YES, NO, UNSURE). Lane results as int32, so that the
 * loops run at the floats' vector width (byte results made the compiler pick
 * 16-byte vectors). */
static void decide_block(const Frames *fr, Columns col, int32_t *code)
{
    (fr->ortho ? decide_orthographic : decide_perspective)(fr, col, code);
}

/* Rows ids[0..n) into columns; the rest of the block repeats the first row,
 * whose decisions are not read (arbitrary values there could be subnormal,
 * which costs the vector unit a microcode assist per instruction). A row is
 * ROW = 16 floats and a block BLOCK = 16 rows, so this is a 16 x 16
 * transpose: in registers where the processor has AVX-512 or AVX2 (a third of
 * the time of element copies, which also stall the column loads after them). */
static void gather_scalar(const float *const *rows, Columns col)
{
    for (int j = 0; j < BLOCK; j++)
        for (int c = 0; c < ROW; c++)
            col[c][j] = rows[j][c];
}

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>

__attribute__((target("avx512f"))) static void gather_avx512(const float *const *rows, Columns col)
{
    __m512 r[16], t[16];
    for (int j = 0; j < 16; j++)
        r[j] = _mm512_loadu_ps(rows[j]);
    /* Pairs of rows interleaved, then pairs of pairs, then 128-bit lanes twice. */
    for (int j = 0; j < 16; j += 2) {
        t[j] = _mm512_unpacklo_ps(r[j], r[j + 1]);
        t[j + 1] = _mm512_unpackhi_ps(r[j], r[j + 1]);
    }
    for (int j = 0; j < 16; j += 4) {
        __m512d a = _mm512_castps_pd(t[j]), b = _mm512_castps_pd(t[j + 1]);
        __m512d c = _mm512_castps_pd(t[j + 2]), d = _mm512_castps_pd(t[j + 3]);
        r[j] = _mm512_castpd_ps(_mm512_unpacklo_pd(a, c));
        r[j + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(a, c));
        r[j + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(b, d));
        r[j + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(b, d));
    }
    for (int j = 0; j < 4; j++) {
        t[j] = _mm512_shuffle_f32x4(r[j], r[j + 4], 0x88);
        t[j + 4] = _mm512_shuffle_f32x4(r[j], r[j + 4], 0xdd);
        t[j + 8] = _mm512_shuffle_f32x4(r[j + 8], r[j + 12], 0x88);
        t[j + 12] = _mm512_shuffle_f32x4(r[j + 8], r[j + 12], 0xdd);
    }
    for (int j = 0; j < 8; j++) {
        _mm512_storeu_ps(col[j], _mm512_shuffle_f32x4(t[j], t[j + 8], 0x88));
        _mm512_storeu_ps(col[j + 8], _mm512_shuffle_f32x4(t[j], t[j + 8], 0xdd));
    }
}

/* One 8 x 8 quarter: rows[0..8) from column c0 into col[c0..c0+8)[j0..j0+8). */
__attribute__((target("avx2"))) static inline void transpose8(const float *const *rows, int c0, Columns col, int j0)
{
    __m256 r[8], t[8], u[8];
    for (int j = 0; j < 8; j++)
        r[j] = _mm256_loadu_ps(rows[j] + c0);
    for (int j = 0; j < 8; j += 2) {
        t[j] = _mm256_unpacklo_ps(r[j], r[j + 1]);
        t[j + 1] = _mm256_unpackhi_ps(r[j], r[j + 1]);
    }
    for (int j = 0; j < 8; j += 4) {
        u[j] = _mm256_shuffle_ps(t[j], t[j + 2], _MM_SHUFFLE(1, 0, 1, 0));
        u[j + 1] = _mm256_shuffle_ps(t[j], t[j + 2], _MM_SHUFFLE(3, 2, 3, 2));
        u[j + 2] = _mm256_shuffle_ps(t[j + 1], t[j + 3], _MM_SHUFFLE(1, 0, 1, 0));
        u[j + 3] = _mm256_shuffle_ps(t[j + 1], t[j + 3], _MM_SHUFFLE(3, 2, 3, 2));
    }
    for (int j = 0; j < 4; j++) {
        _mm256_storeu_ps(col[c0 + j] + j0, _mm256_permute2f128_ps(u[j], u[j + 4], 0x20));
        _mm256_storeu_ps(col[c0 + j + 4] + j0, _mm256_permute2f128_ps(u[j], u[j + 4], 0x31));
    }
}

__attribute__((target("avx2"))) static void gather_avx2(const float *const *rows, Columns col)
{
    transpose8(rows, 0, col, 0);
    transpose8(rows, 8, col, 0);
    transpose8(rows + 8, 0, col, 8);
    transpose8(rows + 8, 8, col, 8);
}
#endif

typedef void (*GatherFn)(const float *const *, Columns);

static GatherFn gather_for_this_cpu(void)
{
#if defined(__x86_64__) && defined(__GNUC__)
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx512f"))
        return gather_avx512;
    if (__builtin_cpu_supports("avx2"))
        return gather_avx2;
#endif
    return gather_scalar;
}

static inline void gather_block(const float *table, const int32_t *ids, int64_t n, Columns col)
{
    static GatherFn gather = NULL; /* set once; racing threads write the same value */
    if (!gather)
        gather = gather_for_this_cpu();
    const float *rows[BLOCK];
    for (int64_t j = 0; j < BLOCK; j++)
        rows[j] = table + (int64_t)ids[j < n ? j : 0] * ROW;
    gather(rows, col);
}

/* The slots of one decided block [i, i + nb) (decided[]: decide_block's
 * codes, kids[]: their rows' KIDS column): each slot's own decision goes to
 * state[], the faces its pcol kills to kill[], the unsure ones to
 * unsure[*m...], and the children of the open slots (those whose bound did
 * not decide everything below them) are pushed behind the queue at n, their
 * slots written to kid[] (and, where parent is not NULL, the slot of each
 * child's parent to parent[]). Returns the new end of the queue. The children
 * of an open slot are visited whatever it does (each may run on its own); a
 * slot is closed when everything below it collapses: its children ran, and it
 * runs when it collapses itself. */
static inline int64_t push_block_plain(const Mesh *pm, int64_t i, int64_t nb, int64_t n, const int32_t *decided,
                                       const float *kids, uint8_t *state, int32_t *kill, int32_t *kid, int32_t *ids,
                                       int32_t *parent, int32_t *unsure, int64_t *m)
{
    for (int64_t j = i; j < i + nb; j++) {
        /* Without branches but for the rare unsure decisions: whether the
         * bound decided a slot is a coin toss to the branch predictor. */
        const int32_t own = decided[j - i] & (YES | UNSURE);
        const int open = !(decided[j - i] & WHOLE);
        state[j] = (uint8_t)own;
        if (own == UNSURE) /* rare: decided by the caller (the float32 predicate) */
            unsure[(*m)++] = (int32_t)j;
        /* Two children are written and those that exist counted (2 spare
         * slots), as masks (-1 or 0), which the compiler keeps as arithmetic
         * where conditionals became branches. */
        int32_t k;
        memcpy(&k, &kids[j - i], sizeof k);
        kill[j] = kids_kills(pm, k, ids[j]);
        const int32_t first = kids_first(k), count = (k & 3) & -open;
        const int32_t one = -(count > 0), two = -(count > 1);
        kid[2 * j] = ((int32_t)n & one) | ~one;
        kid[2 * j + 1] = (((int32_t)n + 1) & two) | ~two;
        ids[n] = first;
        ids[n + 1] = first + 1;
        if (parent)
            parent[n] = parent[n + 1] = (int32_t)j;
        n += count;
    }
    return n;
}

/* Bottom-up over slots [lo, hi), from the end: a slot ran if it collapses
 * and both children ran (a child not visited ran). Counts the slots that
 * did not run and the faces they keep into *not_run, *keep. */
static inline void resolve_plain(const Mesh *pm, int64_t lo, int64_t hi, const int32_t *ids, const int32_t *kid,
                                 const uint8_t *state, const int32_t *kill, uint8_t *ran, int32_t *pcols,
                                 int64_t *not_run, int64_t *keep)
{
    for (int64_t i = hi - 1; i >= lo; i--) {
        /* Without branches: whether a slot ran is a coin toss too. */
        const int32_t k1 = kid[2 * i], k2 = kid[2 * i + 1];
        const int below = ((k1 < 0) | ran[k1 < 0 ? 0 : k1]) & ((k2 < 0) | ran[k2 < 0 ? 0 : k2]);
        const int r = (state[i] == YES) & below;
        ran[i] = (uint8_t)r;
        *not_run += !r;
        *keep += (!r) * kill[i];
        if (pcols) /* not for counts alone: order[] is read at random */
            pcols[i] = pm->order[ids[i]];
    }
}

#if defined(__x86_64__) && defined(__GNUC__)
/* The same two steps with AVX-512 masks, sixteen slots at a time: the
 * scalar versions spend a third of a camera's time on per-slot stores,
 * shifts and counts. Same results, bit for bit. */
#define SLOTS_TARGET __attribute__((target("avx512f,avx512bw,avx512vl,bmi2,popcnt")))

SLOTS_TARGET static int64_t push_block_avx512(const Mesh *pm, int64_t i, int64_t nb, int64_t n,
                                              const int32_t *decided, const float *kids, uint8_t *state,
                                              int32_t *kill, int32_t *kid, int32_t *ids, int32_t *parent,
                                              int32_t *unsure, int64_t *m)
{
    const __mmask16 valid = (__mmask16)((1u << nb) - 1);
    const __m512i lane = _mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0);
    const __m512i code = _mm512_loadu_si512(decided);
    const __m512i own = _mm512_and_si512(code, _mm512_set1_epi32(YES | UNSURE));
    _mm512_mask_cvtepi32_storeu_epi8(state + i, valid, own);
    const __mmask16 unsure_lanes = _mm512_mask_cmpeq_epi32_mask(valid, own, _mm512_set1_epi32(UNSURE));
    if (unsure_lanes) { /* rare: decided by the caller (the float32 predicate) */
        const __m512i slots = _mm512_add_epi32(lane, _mm512_set1_epi32((int32_t)i));
        _mm512_mask_compressstoreu_epi32(unsure + *m, unsure_lanes, slots);
        *m += _mm_popcnt_u32(unsure_lanes);
    }
    /* Lanes with at least one / two children to visit, as one mask of the
     * children in queue order (bit 2j: lane j's first, 2j + 1: its second). */
    const __m512i k = _mm512_loadu_si512(kids);
    /* Two faces killed, but where the sign bit says otherwise (rare). */
    const __mmask16 odd = _mm512_mask_cmplt_epi32_mask(valid, k, _mm512_setzero_si512());
    __m512i kills = _mm512_set1_epi32(2);
    if (odd)
        kills = _mm512_mask_i32gather_epi32(kills, odd, _mm512_maskz_loadu_epi32(odd, ids + i), pm->kills, 4);
    _mm512_mask_storeu_epi32(kill + i, valid, kills);
    const __mmask16 open = _mm512_mask_testn_epi32_mask(valid, code, _mm512_set1_epi32(WHOLE));
    const __m512i count = _mm512_and_si512(k, _mm512_set1_epi32(3));
    const __mmask16 one = _mm512_mask_cmpgt_epi32_mask(open, count, _mm512_setzero_si512());
    const __mmask16 two = _mm512_mask_cmpgt_epi32_mask(open, count, _mm512_set1_epi32(1));
    const uint32_t pushed = _pdep_u32(one, 0x55555555u) | _pdep_u32(two, 0xAAAAAAAAu);
    const __mmask16 lo = (__mmask16)pushed, hi = (__mmask16)(pushed >> 16);
    const int n_lo = _mm_popcnt_u32(lo), n_hi = _mm_popcnt_u32(hi);
    /* Their slots (-1 where no child is visited): n, n + 1, ... expanded. */
    const __m512i none = _mm512_set1_epi32(-1);
    const __m512i slot_lo = _mm512_mask_expand_epi32(none, lo, _mm512_add_epi32(lane, _mm512_set1_epi32((int32_t)n)));
    const __m512i slot_hi =
        _mm512_mask_expand_epi32(none, hi, _mm512_add_epi32(lane, _mm512_set1_epi32((int32_t)n + n_lo)));
    const uint32_t kid_valid = nb == BLOCK ? 0xFFFFFFFFu : (1u << (2 * nb)) - 1;
    _mm512_mask_storeu_epi32(kid + 2 * i, (__mmask16)kid_valid, slot_lo);
    _mm512_mask_storeu_epi32(kid + 2 * i + BLOCK, (__mmask16)(kid_valid >> 16), slot_hi);
    /* Their positions: (first, first + 1) of each lane interleaved, compressed. */
    const __m512i first = _mm512_and_si512(_mm512_srli_epi32(k, 2), _mm512_set1_epi32(KIDS_FIRST));
    const __m512i second = _mm512_add_epi32(first, _mm512_set1_epi32(1));
    const __m512i pick_lo = _mm512_set_epi32(23, 7, 22, 6, 21, 5, 20, 4, 19, 3, 18, 2, 17, 1, 16, 0);
    const __m512i pick_hi = _mm512_add_epi32(pick_lo, _mm512_set1_epi32(8));
    const __m512i at_lo = _mm512_maskz_compress_epi32(lo, _mm512_permutex2var_epi32(first, pick_lo, second));
    const __m512i at_hi = _mm512_maskz_compress_epi32(hi, _mm512_permutex2var_epi32(first, pick_hi, second));
    _mm512_mask_storeu_epi32(ids + n, (__mmask16)((1u << n_lo) - 1), at_lo);
    _mm512_mask_storeu_epi32(ids + n + n_lo, (__mmask16)((1u << n_hi) - 1), at_hi);
    if (parent) { /* each child's parent slot, the same way */
        const __m512i slot = _mm512_add_epi32(lane, _mm512_set1_epi32((int32_t)i));
        _mm512_mask_storeu_epi32(parent + n, (__mmask16)((1u << n_lo) - 1),
                                 _mm512_maskz_compress_epi32(lo, _mm512_permutex2var_epi32(slot, pick_lo, slot)));
        _mm512_mask_storeu_epi32(parent + n + n_lo, (__mmask16)((1u << n_hi) - 1),
                                 _mm512_maskz_compress_epi32(hi, _mm512_permutex2var_epi32(slot, pick_hi, slot)));
    }
    return n + n_lo + n_hi;
}

/* resolve_plain over all n slots, sixteen at a time on the traversal's
 * blocks (whose children all sit in later blocks; a block of the rare
 * stretch where the queue ran short of sixteen may hold its own children
 * and goes through resolve_plain). ran[] needs 3 bytes past n: the
 * children's ran bits are gathered as int32. */
SLOTS_TARGET static void resolve_avx512(const Mesh *pm, int64_t n, const int32_t *ids, const int32_t *kid,
                                        const uint8_t *state, const int32_t *kill, uint8_t *ran, int32_t *pcols,
                                        int64_t *n_not_run, int64_t *kept)
{
    const __m512i none = _mm512_set1_epi32(-1), zero = _mm512_setzero_si512();
    __m512i keep = zero; /* per lane: no sum exceeds the face count (int32) */
    int64_t not_run = 0, keep_plain = 0;
    for (int64_t s = (n - 1) & ~(int64_t)(BLOCK - 1); s >= 0; s -= BLOCK) {
        const int64_t nb = n - s < BLOCK ? n - s : BLOCK;
        const __mmask16 valid = (__mmask16)((1u << nb) - 1);
        const uint32_t kid_valid = nb == BLOCK ? 0xFFFFFFFFu : (1u << (2 * nb)) - 1;
        const __m512i k_lo = _mm512_mask_loadu_epi32(none, (__mmask16)kid_valid, kid + 2 * s);
        const __m512i k_hi = _mm512_mask_loadu_epi32(none, (__mmask16)(kid_valid >> 16), kid + 2 * s + BLOCK);
        const __mmask16 has_lo = _mm512_cmpge_epi32_mask(k_lo, zero), has_hi = _mm512_cmpge_epi32_mask(k_hi, zero);
        const __m512i end = _mm512_set1_epi32((int32_t)(s + nb));
        if (_mm512_mask_cmplt_epi32_mask(has_lo, k_lo, end) | _mm512_mask_cmplt_epi32_mask(has_hi, k_hi, end)) {
            resolve_plain(pm, s, s + nb, ids, kid, state, kill, ran, pcols, &not_run, &keep_plain);
            continue;
        }
        /* The children's ran bits (1 where there is no child), both of a
         * slot together: bits 2j and 2j + 1 of one mask. */
        const __m512i one = _mm512_set1_epi32(1), byte = _mm512_set1_epi32(0xFF);
        const __m512i r_lo = _mm512_mask_i32gather_epi32(one, has_lo, k_lo, ran, 1);
        const __m512i r_hi = _mm512_mask_i32gather_epi32(one, has_hi, k_hi, ran, 1);
        const uint32_t children = (uint32_t)_mm512_test_epi32_mask(r_lo, byte) |
                                  ((uint32_t)_mm512_test_epi32_mask(r_hi, byte) << 16);
        const __mmask16 below = (__mmask16)_pext_u32(children & (children >> 1), 0x55555555u);
        const __mmask16 yes =
            _mm_mask_cmpeq_epi8_mask(valid, _mm_maskz_loadu_epi8(valid, state + s), _mm_set1_epi8(YES));
        const __mmask16 r = yes & below, failed = valid & (__mmask16)~r;
        _mm_mask_storeu_epi8(ran + s, valid, _mm_maskz_mov_epi8(r, _mm_set1_epi8(1)));
        not_run += _mm_popcnt_u32(failed);
        keep = _mm512_mask_add_epi32(keep, failed, keep, _mm512_maskz_loadu_epi32(failed, kill + s));
        if (pcols) /* not for counts alone: order[] is read at random */
            _mm512_mask_storeu_epi32(pcols + s, valid,
                                     _mm512_mask_i32gather_epi32(zero, valid, _mm512_maskz_loadu_epi32(valid, ids + s),
                                                                 pm->order, 4));
    }
    *n_not_run = not_run;
    *kept = keep_plain + _mm512_reduce_add_epi32(keep);
}

/* The same two steps with AVX2, eight slots at a time, for processors
 * without AVX-512: compress and expand through small tables made once
 * (racing threads write the same values), no BMI2 (slow on some AMD
 * processors). Same results, bit for bit. */
#define AVX2_TARGET __attribute__((target("avx2,popcnt")))

static int32_t compress8[256][8]; /* mask x: the lanes of its set bits, in order */
static uint8_t rank8[256][8];     /* mask x: set bits of x below each lane */
static uint16_t spread8[256];     /* mask x: bit j moved to bit 2j */
static int tables8 = 0;

static void make_tables8(void)
{
    for (int x = 0; x < 256; x++) {
        int c = 0;
        spread8[x] = 0;
        for (int j = 0; j < 8; j++) {
            rank8[x][j] = (uint8_t)c;
            if (x >> j & 1) {
                compress8[x][c++] = j;
                spread8[x] |= (uint16_t)(1u << (2 * j));
            }
        }
        for (; c < 8; c++)
            compress8[x][c] = 0;
    }
    __atomic_store_n(&tables8, 1, __ATOMIC_RELEASE);
}

/* Lanes below `count` as a mask vector. */
AVX2_TARGET static inline __m256i first_lanes(int count)
{
    return _mm256_cmpgt_epi32(_mm256_set1_epi32(count), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
}

/* Bits of an 8-bit mask as a mask vector. */
AVX2_TARGET static inline __m256i lanes_of(int bits)
{
    const __m256i bit = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
    return _mm256_cmpeq_epi32(_mm256_and_si256(_mm256_set1_epi32(bits), bit), bit);
}

/* The set lanes (mask x) of v, in order, at out[0..popcount(x)); out[..8)
 * is written (a masked store is slow on some AMD processors), so the
 * queue's arrays have 8 spare slots past P + 2. */
AVX2_TARGET static inline void compress_store8(int32_t *out, __m256i v, int x)
{
    _mm256_storeu_si256((__m256i *)out,
                        _mm256_permutevar8x32_epi32(v, _mm256_loadu_si256((const __m256i *)compress8[x])));
}

AVX2_TARGET static int64_t push_block_avx2(const Mesh *pm, int64_t i, int64_t nb, int64_t n, const int32_t *decided,
                                           const float *kids, uint8_t *state, int32_t *kill, int32_t *kid,
                                           int32_t *ids, int32_t *parent, int32_t *unsure, int64_t *m)
{
    if (!__atomic_load_n(&tables8, __ATOMIC_ACQUIRE))
        make_tables8();
    const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    for (int64_t h = 0; h < nb; h += 8) {
        const int cnt = (int)(nb - h < 8 ? nb - h : 8);
        const int valid = (1 << cnt) - 1;
        const int64_t j0 = i + h;
        const __m256i code = _mm256_loadu_si256((const __m256i *)(decided + h));
        const __m256i k = _mm256_loadu_si256((const __m256i *)(kids + h));
        const __m256i own = _mm256_and_si256(code, _mm256_set1_epi32(YES | UNSURE));
        /* Own decisions as bytes (byte 0 of each lane, both 128-bit halves). */
        const __m256i pick = _mm256_setr_epi8(0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, 0, 4, 8,
                                              12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1);
        const __m256i bytes = _mm256_shuffle_epi8(own, pick);
        const uint64_t packed = (uint64_t)(uint32_t)_mm_cvtsi128_si32(_mm256_castsi256_si128(bytes)) |
                                (uint64_t)(uint32_t)_mm_cvtsi128_si32(_mm256_extracti128_si256(bytes, 1)) << 32;
        if (cnt == 8)
            memcpy(state + j0, &packed, 8);
        else
            memcpy(state + j0, &packed, (size_t)cnt);
        int rare = _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(own, _mm256_set1_epi32(UNSURE)))) & valid;
        for (; rare; rare &= rare - 1) /* rare: decided by the caller (the float32 predicate) */
            unsure[(*m)++] = (int32_t)(j0 + __builtin_ctz((unsigned)rare));
        /* Two faces killed, but where the sign bit says otherwise (rare). */
        if (cnt == 8)
            _mm256_storeu_si256((__m256i *)(kill + j0), _mm256_set1_epi32(2));
        else
            _mm256_maskstore_epi32(kill + j0, first_lanes(cnt), _mm256_set1_epi32(2));
        for (int odd = _mm256_movemask_ps(_mm256_castsi256_ps(k)) & valid; odd; odd &= odd - 1) {
            const int64_t j = j0 + __builtin_ctz((unsigned)odd);
            kill[j] = pm->kills[ids[j]];
        }
        /* Lanes with at least one / two children to visit, as one mask of
         * the children in queue order (bit 2j: lane j's first, 2j + 1: its
         * second). */
        const __m256i open = _mm256_cmpeq_epi32(_mm256_and_si256(code, _mm256_set1_epi32(WHOLE)),
                                                _mm256_setzero_si256());
        const __m256i count = _mm256_and_si256(k, _mm256_set1_epi32(3));
        const int one = _mm256_movemask_ps(_mm256_castsi256_ps(
                            _mm256_and_si256(open, _mm256_cmpgt_epi32(count, _mm256_setzero_si256())))) & valid;
        const int two = _mm256_movemask_ps(_mm256_castsi256_ps(
                            _mm256_and_si256(open, _mm256_cmpgt_epi32(count, _mm256_set1_epi32(1))))) & valid;
        const unsigned pushed = spread8[one] | (unsigned)spread8[two] << 1;
        const int lo = (int)(pushed & 0xFF), hi = (int)(pushed >> 8);
        const int n_lo = _mm_popcnt_u32((unsigned)lo), n_hi = _mm_popcnt_u32((unsigned)hi);
        /* Their slots (-1 where no child is visited): n + the pushed bits below. */
        const __m256i none = _mm256_set1_epi32(-1);
        const __m256i rank_lo = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)rank8[lo]));
        const __m256i rank_hi = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)rank8[hi]));
        const __m256i slot_lo = _mm256_blendv_epi8(none, _mm256_add_epi32(rank_lo, _mm256_set1_epi32((int32_t)n)),
                                                   lanes_of(lo));
        const __m256i slot_hi = _mm256_blendv_epi8(
            none, _mm256_add_epi32(rank_hi, _mm256_set1_epi32((int32_t)n + n_lo)), lanes_of(hi));
        if (cnt == 8) {
            _mm256_storeu_si256((__m256i *)(kid + 2 * j0), slot_lo);
            _mm256_storeu_si256((__m256i *)(kid + 2 * j0 + 8), slot_hi);
        } else {
            _mm256_maskstore_epi32(kid + 2 * j0, first_lanes(2 * cnt), slot_lo);
            _mm256_maskstore_epi32(kid + 2 * j0 + 8, first_lanes(2 * cnt - 8), slot_hi);
        }
        /* Their positions: (first, first + 1) of each lane interleaved, compressed. */
        const __m256i first = _mm256_and_si256(_mm256_srli_epi32(k, 2), _mm256_set1_epi32(KIDS_FIRST));
        const __m256i second = _mm256_add_epi32(first, _mm256_set1_epi32(1));
        const __m256i a = _mm256_unpacklo_epi32(first, second), b = _mm256_unpackhi_epi32(first, second);
        compress_store8(ids + n, _mm256_permute2x128_si256(a, b, 0x20), lo);
        compress_store8(ids + n + n_lo, _mm256_permute2x128_si256(a, b, 0x31), hi);
        if (parent) { /* each child's parent slot, the same way */
            const __m256i slot = _mm256_add_epi32(lane, _mm256_set1_epi32((int32_t)j0));
            const __m256i c = _mm256_unpacklo_epi32(slot, slot), d = _mm256_unpackhi_epi32(slot, slot);
            compress_store8(parent + n, _mm256_permute2x128_si256(c, d, 0x20), lo);
            compress_store8(parent + n + n_lo, _mm256_permute2x128_si256(c, d, 0x31), hi);
        }
        n += n_lo + n_hi;
    }
    return n;
}

/* resolve_plain over all n slots, sixteen at a time as resolve_avx512
 * (a block that holds its own children goes through resolve_plain). */
AVX2_TARGET static void resolve_avx2(const Mesh *pm, int64_t n, const int32_t *ids, const int32_t *kid,
                                     const uint8_t *state, const int32_t *kill, uint8_t *ran, int32_t *pcols,
                                     int64_t *n_not_run, int64_t *kept)
{
    const __m256i zero = _mm256_setzero_si256(), one = _mm256_set1_epi32(1), byte = _mm256_set1_epi32(0xFF);
    __m256i keep = zero; /* per lane: no sum exceeds the face count (int32) */
    int64_t not_run = 0, keep_plain = 0;
    for (int64_t s = (n - 1) & ~(int64_t)(BLOCK - 1); s >= 0; s -= BLOCK) {
        const int64_t nb = n - s < BLOCK ? n - s : BLOCK;
        /* The children's slots, four vectors of four slots' two children. */
        __m256i kv[4], has[4];
        int inside = 0;
        for (int q = 0; q < 4; q++) {
            const int left = (int)(2 * nb - 8 * q); /* children of this block in vector q */
            const __m256i live = first_lanes(left < 0 ? 0 : left);
            kv[q] = _mm256_blendv_epi8(_mm256_set1_epi32(-1), _mm256_maskload_epi32(kid + 2 * s + 8 * q, live), live);
            has[q] = _mm256_cmpgt_epi32(kv[q], _mm256_set1_epi32(-1));
            inside |= _mm256_movemask_ps(_mm256_castsi256_ps(
                _mm256_and_si256(has[q], _mm256_cmpgt_epi32(_mm256_set1_epi32((int32_t)(s + nb)), kv[q]))));
        }
        if (inside) {
            resolve_plain(pm, s, s + nb, ids, kid, state, kill, ran, pcols, &not_run, &keep_plain);
            continue;
        }
        /* Both children ran (1 where there is no child): bit j for slot s + j. */
        int below = 0;
        for (int q = 0; q < 4; q++) {
            const __m256i r = _mm256_mask_i32gather_epi32(one, (const int *)ran, kv[q], has[q], 1);
            const __m256i child = _mm256_cmpgt_epi32(_mm256_and_si256(r, byte), zero);
            /* Each lane and its pair's lane: both children of a slot. */
            const __m256i both = _mm256_and_si256(child, _mm256_shuffle_epi32(child, _MM_SHUFFLE(2, 3, 0, 1)));
            const int bits = _mm256_movemask_ps(_mm256_castsi256_ps(both)); /* even bits: slots */
            below |= ((bits & 1) | (bits >> 1 & 2) | (bits >> 2 & 4) | (bits >> 3 & 8)) << (4 * q);
        }
        /* The block's own decisions and ran bytes (whole blocks but the last). */
        __m128i st;
        if (nb == BLOCK) {
            st = _mm_loadu_si128((const __m128i *)(state + s));
        } else {
            uint8_t part[BLOCK] = {0};
            memcpy(part, state + s, (size_t)nb);
            st = _mm_loadu_si128((const __m128i *)part);
        }
        const int yes = _mm_movemask_epi8(_mm_cmpeq_epi8(st, _mm_set1_epi8(YES)));
        const int valid = (int)((1u << nb) - 1);
        const int r = yes & below & valid, failed = valid & ~r;
        const __m128i bit = _mm_setr_epi8(1, 2, 4, 8, 16, 32, 64, -128, 1, 2, 4, 8, 16, 32, 64, -128);
        const __m128i spread = _mm_shuffle_epi8(_mm_cvtsi32_si128(r), _mm_setr_epi8(0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1,
                                                                                     1, 1, 1, 1, 1));
        const __m128i out = _mm_and_si128(_mm_cmpeq_epi8(_mm_and_si128(spread, bit), bit), _mm_set1_epi8(1));
        if (nb == BLOCK) {
            _mm_storeu_si128((__m128i *)(ran + s), out);
        } else {
            uint8_t part[BLOCK];
            _mm_storeu_si128((__m128i *)part, out);
            memcpy(ran + s, part, (size_t)nb);
        }
        not_run += _mm_popcnt_u32((unsigned)failed);
        for (int q = 0; q < 2; q++) {
            const __m256i f = lanes_of(failed >> (8 * q) & 0xFF);
            keep = _mm256_add_epi32(keep, _mm256_maskload_epi32(kill + s + 8 * q, f));
            if (pcols) { /* not for counts alone: order[] is read at random */
                const __m256i v = lanes_of(valid >> (8 * q) & 0xFF);
                const __m256i at = _mm256_maskload_epi32(ids + s + 8 * q, v);
                const __m256i got = _mm256_mask_i32gather_epi32(zero, pm->order, at, v, 4);
                if (nb == BLOCK)
                    _mm256_storeu_si256((__m256i *)(pcols + s + 8 * q), got);
                else
                    _mm256_maskstore_epi32(pcols + s + 8 * q, v, got);
            }
        }
    }
    const __m128i sum4 = _mm_add_epi32(_mm256_castsi256_si128(keep), _mm256_extracti128_si256(keep, 1));
    const __m128i sum2 = _mm_add_epi32(sum4, _mm_shuffle_epi32(sum4, _MM_SHUFFLE(1, 0, 3, 2)));
    *n_not_run = not_run;
    *kept = keep_plain + _mm_cvtsi128_si32(_mm_add_epi32(sum2, _mm_shuffle_epi32(sum2, _MM_SHUFFLE(2, 3, 0, 1))));
}

static int avx2_here(void)
{
    static int has = -1; /* set once; racing threads write the same value */
    if (has < 0) {
        __builtin_cpu_init();
        has = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("popcnt");
    }
    return has;
}

static int avx512_here(void)
{
    static int has = -1; /* set once; racing threads write the same value */
    if (has < 0) {
        __builtin_cpu_init();
        has = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
              __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("bmi2") &&
              __builtin_cpu_supports("popcnt");
    }
    return has;
}
#else
static int avx512_here(void) { return 0; }
static int avx2_here(void) { return 0; }
#endif

/* How the slots' bookkeeping runs: SLOTS_AVX512 or SLOTS_AVX2 where the
 * processor has them, else SLOTS_PLAIN, unless pmx_slot_loops said
 * otherwise (the tests run each). */
enum { SLOTS_PLAIN = 0, SLOTS_AVX2 = 1, SLOTS_AVX512 = 2 };
static int slot_loops_here(void) { return avx512_here() ? SLOTS_AVX512 : avx2_here() ? SLOTS_AVX2 : SLOTS_PLAIN; }
static int slot_loops = -1;
static int slots_kind(void)
{
    if (slot_loops < 0)
        slot_loops = slot_loops_here();
    return slot_loops;
}

/* Sets the slots' bookkeeping to `kind` (or the best below it that the
 * processor has), or leaves it (kind < 0); returns the previous kind. */
int pmx_slot_loops(int kind)
{
    const int was = slots_kind();
    if (kind >= 0) {
        const int here = slot_loops_here();
        slot_loops = kind < here ? kind : here;
        if (slot_loops == SLOTS_AVX2 && !avx2_here())
            slot_loops = SLOTS_PLAIN;
    }
    return was;
}

/* Top-down traversal from the roots, breadth first, over a table whose
 * bounds are those of the pcols strictly below each pcol (NativeMesh
 * below_table): slot i holds pcol ids[i] with its own decision state[i]
 * and the faces it kills kill[i];
 * kid[2i], kid[2i+1] are the slots of its children (-1: not visited, which
 * means original or below a slot whose bound decided, and so executed).
 * Against bounds over whole subtrees, this leaves unvisited the children of
 * the pcols that do not run themselves but whose children do (a third of
 * the visits on the dragon). Returns the
 * number of slots; unsure[] receives the slots whose own decision is
 * UNSURE, *n_unsure their number, and parent[] (optional) each slot's
 * parent slot from slot n_roots on. Capacity: P slots, and ids[] and
 * parent[] P + 10 (the plain loop writes 2 spare slots, the AVX2 one 8).
 * Slots are decided a block at a time; the children of a block are pushed
 * behind the queue. */
static int64_t traverse(const Mesh *pm, const Frames *w, const int32_t *roots, int64_t n_roots, int32_t *ids,
                        int32_t *kid, uint8_t *state, int32_t *kill, int32_t *parent, int32_t *unsure,
                        int64_t *n_unsure)
{
    int64_t n = 0, m = 0;
    Columns col;
    int32_t decided[BLOCK];
    const int kind = slots_kind();
    for (int64_t i = 0; i < n_roots; i++)
        ids[n++] = roots[i];
    for (int64_t i = 0; i < n;) {
        int64_t nb = n - i < BLOCK ? n - i : BLOCK;
        /* The rows a few blocks ahead in the queue, so that they arrive in
         * time without more requests in flight than the memory system holds. */
        for (int64_t j = i + AHEAD; j < i + AHEAD + nb && j < n; j++) {
            __builtin_prefetch(pm->table + (int64_t)ids[j] * ROW);
        }
        gather_block(pm->table, ids + i, nb, col);
        decide_block(w, col, decided);
#if defined(__x86_64__) && defined(__GNUC__)
        if (kind == SLOTS_AVX512)
            n = push_block_avx512(pm, i, nb, n, decided, col[KIDS], state, kill, kid, ids, parent, unsure, &m);
        else if (kind == SLOTS_AVX2)
            n = push_block_avx2(pm, i, nb, n, decided, col[KIDS], state, kill, kid, ids, parent, unsure, &m);
        else
#endif
            n = push_block_plain(pm, i, nb, n, decided, col[KIDS], state, kill, kid, ids, parent, unsure, &m);
        i += nb;
    }
    *n_unsure = m;
    return n;
}

/* Bottom-up: a slot ran if it collapses and both children ran (children
 * always sit in later slots; one not visited ran). Writes ran[] (0/1; 3
 * bytes past n may be read), the counts (pcols that did not run, the faces
 * they keep) and pcols[], the pcol of each slot (ids[] holds positions;
 * optional). */
static void resolve(const Mesh *pm, int64_t n, const int32_t *ids, const int32_t *kid, const uint8_t *state,
                    const int32_t *kill, uint8_t *ran, int32_t *pcols, int64_t *n_not_run, int64_t *kept)
{
#if defined(__x86_64__) && defined(__GNUC__)
    if (slots_kind() == SLOTS_AVX512) {
        resolve_avx512(pm, n, ids, kid, state, kill, ran, pcols, n_not_run, kept);
        return;
    }
    if (slots_kind() == SLOTS_AVX2) {
        resolve_avx2(pm, n, ids, kid, state, kill, ran, pcols, n_not_run, kept);
        return;
    }
#endif
    *n_not_run = *kept = 0;
    resolve_plain(pm, 0, n, ids, kid, state, kill, ran, pcols, n_not_run, kept);
}

/* ---- entry points (ctypes) ---------------------------------------------- */

/* Subnormal floats read and written as zero (MXCSR DAZ and FTZ) in the
 * calling thread while a decision loop runs; the caller's mode comes back on
 * return. On x86 a vector operation that meets a subnormal takes a microcode
 * assist of a hundred cycles or more, for the whole vector. The tables hold
 * none (pmjax/_subtree.py keeps zero bounds zero), but products of tiny
 * terms make them (fine pcols' squared deviations, models in tiny units).
 * The bits are the same: the certified own decisions allow any evaluation
 * to flush (FLUSH), and the subtree bounds, like pmjax/_subtree.py's for XLA
 * (which flushes too), decide nothing where a term they compare could leave
 * [LOW, HIGH]. */
static inline unsigned subnormals_off(void)
{
#if defined(__x86_64__) && defined(__GNUC__)
    const unsigned mode = _mm_getcsr();
    _mm_setcsr(mode | 0x8040); /* FTZ (bit 15) and DAZ (bit 6) */
    return mode;
#else
    return 0;
#endif
}
static inline void subnormals_back(unsigned mode)
{
#if defined(__x86_64__) && defined(__GNUC__)
    _mm_setcsr(mode);
#else
    (void)mode;
#endif
}

/* One camera. Traverses, and resolves unless a decision is unsure; returns
 * the number of visited slots (ids[]: their positions). out[0] = unsure
 * slots (decide them, then call pmx_resolve), out[1] = pcols not run,
 * out[2] = faces they keep; pcols[]: the slots' pcols once resolved. */
int64_t pmx_refine(const float *table, const int32_t *kills, const int32_t *order,
                   int64_t n_pcols, const int32_t *roots, int64_t n_roots, const float *view, int flags, int32_t *ids,
                   int32_t *kid, uint8_t *state, int32_t *kill, uint8_t *ran, int32_t *pcols, int32_t *unsure,
                   int64_t *out)
{
    const unsigned mode = subnormals_off();
    Mesh pm = {table, kills, order, n_pcols};
    Frames w;
    load_frames(&w, view, 1, flags);
    int64_t m = 0;
    int64_t n = traverse(&pm, &w, roots, n_roots, ids, kid, state, kill, NULL, unsure, &m);
    out[0] = m;
    out[1] = out[2] = 0;
    if (m == 0)
        resolve(&pm, n, ids, kid, state, kill, ran, pcols, &out[1], &out[2]);
    subnormals_back(mode);
    return n;
}

/* The bottom-up pass after the unsure decisions were written into state[]
 * (YES or NO). */
void pmx_resolve(const int32_t *kills, const int32_t *order, int64_t n, const int32_t *ids, const int32_t *kid,
                 const uint8_t *state, const int32_t *kill, uint8_t *ran, int32_t *pcols, int64_t *out)
{
    Mesh pm = {NULL, kills, order, 0};
    resolve(&pm, n, ids, kid, state, kill, ran, pcols, &out[0], &out[1]);
}

/* ---- words: consecutive frames of a camera path together ---------------- */

/* A word holds FRAMES consecutive frames of a path, one bit each. A pcol is
 * visited once for the frames whose traversal reaches it, its row read once,
 * and each frame's own decision and subtree bound evaluated in one vectorized
 * pass over the frames: consecutive frames share most of their front, so the
 * word visits little more than one frame alone (docs/path.md). */
#define FRAMES BLOCK

/* One word. Slot i holds position ids[i], visited by the frames visit[i];
 * whole[i], yes[i] are the frames whose subtree bound decided it (its own or
 * the fat camera's) and whose own decision is yes. fat: the word's fat camera
 * (FAT_N floats) or NULL; it is used where fat_applies. Returns the number of
 * slots; the slots with unsure frames go to unsure_slots[] with the frames in
 * unsure_lanes[] (out[0] of them): decide them, set their yes[] bits and call
 * pmx_resolve_word. out[2]: the slots the fat camera decided. out: 3 slots. */
int64_t pmx_refine_word(const float *table, const int32_t *order, const int32_t *roots,
                        int64_t n_roots, const float *views, int n_frames, int flags, const float *fat,
                        int32_t *ids, int32_t *kid, Lanes *visit, Lanes *whole, Lanes *yes, int32_t *unsure_slots,
                        Lanes *unsure_lanes, int64_t *out)
{
    const unsigned mode = subnormals_off();
    Frames fr;
    load_frames(&fr, views, n_frames, flags);
    Fat W;
    const int use_fat = fat_applies(&fr, fat, n_frames);
    if (use_fat)
        load_fat(&W, fat, &fr, n_frames);
    const Lanes active = (Lanes)((1u << n_frames) - 1);
    int32_t fat_code[BLOCK];
    Columns col;
    int64_t n = 0, m = 0, at_once = 0;
    for (int64_t i = 0; i < n_roots; i++) {
        ids[n] = roots[i];
        visit[n++] = active;
    }
    for (int64_t i0 = 0; i0 < n;) {
        /* A block of slots under the fat camera first (children land behind
         * the queue, after the block). */
        const int64_t nb = n - i0 < BLOCK ? n - i0 : BLOCK;
        if (use_fat) {
            gather_block(table, ids + i0, nb, col);
            decide_fat(&W, col, fat_code);
        }
        for (int64_t i = i0; i < i0 + nb; i++) {
            if (i + AHEAD < n)
                __builtin_prefetch(table + (int64_t)ids[i + AHEAD] * ROW);
            const float *row = table + (int64_t)ids[i] * ROW;
            const int32_t fc = use_fat ? fat_code[i - i0] : FAT_OPEN;
            at_once += fc != FAT_OPEN;
            Lanes masks[3] = {fc == FAT_WHOLE ? (Lanes)0xFFFF : 0, 0, 0};
            if (fc == FAT_OPEN) /* the pcol under every frame of the word, one by one */
                (fr.ortho ? decide_row_orthographic : decide_row_perspective)(&fr, row, masks);
            const Lanes wh = masks[0], y = masks[1], u = masks[2];
            const Lanes v = visit[i], open = v & (Lanes)~wh;
            whole[i] = v & wh;
            yes[i] = open & y;
            if (open & u) {
                unsure_slots[m] = (int32_t)i;
                unsure_lanes[m++] = open & u;
            }
            kid[2 * i] = kid[2 * i + 1] = -1;
            if (!open)
                continue;
            /* The children, for the frames that did not decide this subtree. */
            int32_t kids;
            memcpy(&kids, row + KIDS, sizeof kids);
            const int32_t first = kids_first(kids), count = kids & 3;
            for (int t = 0; t < count; t++) {
                kid[2 * i + t] = (int32_t)n;
                visit[n] = open;
                ids[n++] = first + t;
            }
        }
        i0 += nb;
    }
    out[0] = m;
    out[2] = at_once;
    subnormals_back(mode);
    return n;
}

/* Bottom-up for a word: per frame, a slot ran if the frame did not visit it
 * (decided above), its bound decided it, or it collapses and both children
 * ran. Writes ran[], pcols[] (each slot's pcol; optional) and per frame the
 * pcols that did not run (not_run[FRAMES]) and the faces they keep
 * (kept[FRAMES]). */
VECTOR_CLONES static void resolve_word(const int32_t *kills, const int32_t *order, int64_t n, const int32_t *ids,
                                       const int32_t *kid, const Lanes *visit, const Lanes *whole, const Lanes *yes,
                                       Lanes *ran, int32_t *pcols, int64_t *not_run, int64_t *kept)
{
    /* Per-frame counts as int32 lanes (one vector add per slot that failed
     * somewhere; no count exceeds P or F). */
    int32_t failures[FRAMES] = {0}, keeps[FRAMES] = {0};
    for (int64_t i = n - 1; i >= 0; i--) {
        int32_t k1 = kid[2 * i], k2 = kid[2 * i + 1];
        Lanes below = (Lanes)((k1 < 0 ? 0xFFFF : ran[k1]) & (k2 < 0 ? 0xFFFF : ran[k2]));
        Lanes r = (Lanes)(~visit[i] | whole[i] | (yes[i] & below));
        ran[i] = r;
        if (pcols) /* not for counts alone: order[] is read at random */
            pcols[i] = order[ids[i]];
        const uint32_t failed = (Lanes)~r;
        if (failed) {
            const int32_t k = kills[ids[i]];
#pragma omp simd
            for (int l = 0; l < FRAMES; l++) {
                const int32_t bit = (int32_t)((failed >> l) & 1);
                failures[l] += bit;
                keeps[l] += bit * k;
            }
        }
    }
    for (int l = 0; l < FRAMES; l++)
        not_run[l] = failures[l], kept[l] = keeps[l];
}
void pmx_resolve_word(const int32_t *kills, const int32_t *order, int64_t n, const int32_t *ids, const int32_t *kid,
                      const Lanes *visit, const Lanes *whole, const Lanes *yes, Lanes *ran, int32_t *pcols,
                      int64_t *not_run, int64_t *kept)
{
    resolve_word(kills, order, n, ids, kid, visit, whole, yes, ran, pcols, not_run, kept);
}

/* ---- unsure pairs of counted words, decided later ------------------------ */

/* A word with unsure (frame, pcol) pairs is resolved at once as if each were
 * "keep" (its yes bit clear), and its chains are recorded: the unsure slots
 * and their ancestors up to the roots, the only slots whose ran bits can
 * change when a pair turns out "collapse". Once the pairs are decided (one
 * call of the float32 predicate for many words), the chains are resolved
 * again and the word's counts corrected. A record is [word, nodes] and then
 * NODE_N int32 per node, the nodes by decreasing slot (children first). */
enum {
    NODE_SLOT, NODE_K1, NODE_K2, /* the slot; its children's nodes in the record (-1: not a node) */
    NODE_RAN_K1, NODE_RAN_K2,    /* the children's ran bits (all set: no child) */
    NODE_VISIT, NODE_WHOLE, NODE_YES, NODE_RAN, NODE_KILLS, NODE_POSITION, NODE_UNSURE, NODE_N
};

/* a[0..n) in decreasing order (heapsort: in place, no allocation, n log n
 * even for the many unsure slots of a float tie). */
static void sort_descending(int32_t *a, int64_t n)
{
    /* A min-heap, whose smallest goes to the back each round. */
    for (int64_t end = n, start = n / 2; end > 1;) {
        if (start > 0)
            start--;
        else {
            end--;
            const int32_t t = a[0];
            a[0] = a[end], a[end] = t;
        }
        for (int64_t root = start, child; (child = 2 * root + 1) < end; root = child) {
            if (child + 1 < end && a[child + 1] < a[child])
                child++;
            if (a[root] <= a[child])
                break;
            const int32_t t = a[root];
            a[root] = a[child], a[child] = t;
        }
    }
}

/* The node of slot s among the record's sorted slots (chain[0..count),
 * decreasing), or -1. */
static int32_t node_of(const int32_t *chain, int64_t count, int32_t s)
{
    int64_t lo = 0, hi = count;
    while (lo < hi) {
        const int64_t mid = (lo + hi) / 2;
        if (chain[mid] == s)
            return (int32_t)mid;
        if (chain[mid] > s)
            lo = mid + 1;
        else
            hi = mid;
    }
    return -1;
}

/* What a record reads of a resolved slot: a word's frame masks, or a single
 * camera's bytes (visited: yes, whole: no, its own decision, whether it ran).
 * unsure: the unsure frames of each unsure slot (NULL: one camera). */
typedef struct {
    const Lanes *visit, *whole, *yes, *ran, *unsure;
    const uint8_t *state, *ran_byte;
} SlotBits;
static inline int32_t bits_visit(const SlotBits *b, int64_t s) { return b->visit ? b->visit[s] : 1; }
static inline int32_t bits_whole(const SlotBits *b, int64_t s) { return b->whole ? b->whole[s] : 0; }
static inline int32_t bits_yes(const SlotBits *b, int64_t s) { return b->yes ? b->yes[s] : b->state[s] == YES; }
static inline int32_t bits_ran(const SlotBits *b, int64_t s) { return b->ran ? b->ran[s] : b->ran_byte[s]; }

/* The record of a resolved word or camera (n slots, m unsure) at rec, if it
 * fits in room int32; returns its size, or -1. parent [n] int32: each slot's
 * parent slot from n_roots on, or scratch to build it in when
 * parent_known is 0; chain [n] int32, mark [n] bytes (zero on entry and on
 * return): scratch. */
static int64_t record_unsure(int64_t word, int64_t n, int64_t n_roots, const int32_t *ids, const int32_t *kid,
                             const SlotBits *b, const int32_t *kills, const int32_t *unsure_slots, int64_t m,
                             int32_t *parent, int parent_known, int32_t *chain, uint8_t *mark, int32_t *rec,
                             int64_t room)
{
    if (!parent_known)
        for (int64_t i = 0; i < n; i++)
            for (int t = 0; t < 2; t++)
                if (kid[2 * i + t] >= 0)
                    parent[kid[2 * i + t]] = (int32_t)i;
    /* Each unsure slot and its ancestors, once (the roots are slots 0..n_roots). */
    int64_t count = 0;
    for (int64_t q = 0; q < m; q++)
        for (int32_t s = unsure_slots[q]; !mark[s]; s = parent[s]) {
            mark[s] = 1;
            chain[count++] = s;
            if (s < n_roots)
                break;
        }
    for (int64_t j = 0; j < count; j++)
        mark[chain[j]] = 0;
    const int64_t size = 2 + count * NODE_N;
    if (size > room)
        return -1;
    sort_descending(chain, count);
    rec[0] = (int32_t)word, rec[1] = (int32_t)count;
    for (int64_t j = 0; j < count; j++) {
        const int32_t s = chain[j], k1 = kid[2 * s], k2 = kid[2 * s + 1];
        int32_t *node = rec + 2 + j * NODE_N;
        node[NODE_SLOT] = s;
        node[NODE_K1] = k1 < 0 ? -1 : node_of(chain, count, k1);
        node[NODE_K2] = k2 < 0 ? -1 : node_of(chain, count, k2);
        node[NODE_RAN_K1] = k1 < 0 ? 0xFFFF : bits_ran(b, k1);
        node[NODE_RAN_K2] = k2 < 0 ? 0xFFFF : bits_ran(b, k2);
        node[NODE_VISIT] = bits_visit(b, s), node[NODE_WHOLE] = bits_whole(b, s), node[NODE_YES] = bits_yes(b, s);
        node[NODE_RAN] = bits_ran(b, s), node[NODE_KILLS] = kills[ids[s]], node[NODE_POSITION] = ids[s];
        node[NODE_UNSURE] = 0;
    }
    for (int64_t q = 0; q < m; q++)
        rec[2 + node_of(chain, count, unsure_slots[q]) * NODE_N + NODE_UNSURE] = b->unsure ? b->unsure[q] : 1;
    return size;
}

/* Words of FRAMES frames each, counts only: views [n_words * FRAMES, 22],
 * fat [n_words, FAT_N] (or NULL). From word `first` on, each word is
 * traversed and resolved, its frames' counts written to not_run[w * FRAMES
 * ...] and kept[w * FRAMES ...] (as pmx_resolve_word), its unsure pairs taken
 * as "keep". A word with unsure pairs also gets a record (word_base + w, its
 * chains) appended to records (capacity int32, *used of them used); where a
 * record does not fit, the loop stops and returns that word's index (make
 * room and call again from it). Returns n_words when every word is counted.
 * Scratch as pmx_refine_word, and ran, parent, chain [P], mark [P] (zero).
 * One call per block of words keeps the interpreter out of the loop. */
int64_t pmx_count_words(const float *table, const int32_t *kills, const int32_t *order, const int32_t *roots,
                        int64_t n_roots, const float *views, const float *fat, int64_t first, int64_t n_words,
                        int flags, int32_t *ids, int32_t *kid, Lanes *visit, Lanes *whole, Lanes *yes, Lanes *ran,
                        int32_t *unsure_slots, Lanes *unsure_lanes, int64_t *out, int64_t *not_run, int64_t *kept,
                        int32_t *parent, int32_t *chain, uint8_t *mark, int64_t word_base, int32_t *records,
                        int64_t capacity, int64_t *used)
{
    for (int64_t w = first; w < n_words; w++) {
        const int64_t n = pmx_refine_word(table, order, roots, n_roots, views + w * FRAMES * 22, FRAMES, flags,
                                          fat ? fat + w * FAT_N : NULL, ids, kid, visit, whole, yes, unsure_slots,
                                          unsure_lanes, out);
        resolve_word(kills, order, n, ids, kid, visit, whole, yes, ran, NULL, not_run + w * FRAMES,
                     kept + w * FRAMES);
        if (out[0] > 0) {
            const SlotBits b = {visit, whole, yes, ran, unsure_lanes, NULL, NULL};
            const int64_t size = record_unsure(word_base + w, n, n_roots, ids, kid, &b, kills, unsure_slots, out[0],
                                               parent, 0, chain, mark, records + *used, capacity - *used);
            if (size < 0)
                return w;
            *used += size;
        }
    }
    return n_words;
}

/* The camera after c: the next of a shared cursor (threads that take
 * cameras one at a time finish together, whatever each camera costs), or
 * c + 1 without one. */
static inline int64_t next_camera(int64_t *cursor, int64_t c)
{
    return cursor ? __atomic_fetch_add(cursor, 1, __ATOMIC_RELAXED) : c + 1;
}

/* Cameras of views [K, 22] below k1, each traversed and resolved with the
 * same scratch: k0 first (k0 < 0: none), then the next ones (next_camera).
 * counts[3k..3k+2] = visited slots, pcols not run, faces they keep; masks:
 * optional [K, P] executed bytes. A camera with unsure decisions is
 * resolved as if each were "keep" and leaves a record (camera k, its
 * chains; pmx_count_words's records with one frame, visit bits 1) in
 * records (capacity int32, *used of them used): decide the pairs, set their
 * yes bits and call pmx_apply_unsure with frames 1. Where a record does not
 * fit, returns that camera (make room and call again with it as k0); k1
 * when this caller has no camera left. Scratch: the traversal's
 * (pmx_refine) and, for the records, parent [P + 10], chain [P] int32 and
 * mark [P] bytes (zero). */
int64_t pmx_refine_many(const float *table, const int32_t *kills, const int32_t *order, int64_t n_pcols,
                        const int32_t *roots, int64_t n_roots, const float *views, int flags, int64_t k0,
                        int64_t k1, int64_t *cursor, int32_t *ids, int32_t *kid, uint8_t *state, int32_t *kill,
                        uint8_t *ran, int32_t *pcols, int32_t *unsure, int64_t *counts, uint8_t *masks,
                        int32_t *parent, int32_t *chain, uint8_t *mark, int32_t *records, int64_t capacity,
                        int64_t *used)
{
    Mesh pm = {table, kills, order, n_pcols};
    const unsigned mode = subnormals_off();
    for (int64_t c = k0 >= 0 ? k0 : next_camera(cursor, k0); c < k1; c = next_camera(cursor, c)) {
        Frames w;
        load_frames(&w, views + 22 * c, 1, flags);
        int64_t m = 0;
        const int64_t n = traverse(&pm, &w, roots, n_roots, ids, kid, state, kill, parent, unsure, &m);
        /* An unsure slot's state is UNSURE, which resolve reads as "keep". */
        resolve(&pm, n, ids, kid, state, kill, ran, masks ? pcols : NULL, &counts[3 * c + 1], &counts[3 * c + 2]);
        counts[3 * c] = n;
        if (m > 0) {
            const SlotBits b = {NULL, NULL, NULL, NULL, NULL, state, ran};
            const int64_t size = record_unsure(c, n, n_roots, ids, kid, &b, kills, unsure, m, parent, 1, chain, mark,
                                               records + *used, capacity - *used);
            if (size < 0) {
                subnormals_back(mode);
                return c;
            }
            *used += size;
        }
        if (masks) {
            uint8_t *row = masks + c * n_pcols;
            memset(row, 1, (size_t)n_pcols);
            for (int64_t i = 0; i < n; i++)
                if (!ran[i])
                    row[pcols[i]] = 0;
        }
    }
    subnormals_back(mode);
    return k1;
}

/* The unsure pairs of records [used]: per unsure node, where its yes bits
 * are in records (at[]), its word, position and unsure frames. Returns
 * their number. */
int64_t pmx_unsure_nodes(const int32_t *records, int64_t used, int64_t *at, int32_t *word, int32_t *position,
                         int32_t *lanes)
{
    int64_t c = 0;
    for (int64_t r = 0; r < used; r += 2 + records[r + 1] * NODE_N)
        for (int64_t j = 0; j < records[r + 1]; j++) {
            const int32_t *node = records + r + 2 + j * NODE_N;
            if (node[NODE_UNSURE]) {
                at[c] = r + 2 + j * NODE_N + NODE_YES;
                word[c] = records[r], position[c] = node[NODE_POSITION], lanes[c++] = node[NODE_UNSURE];
            }
        }
    return c;
}

/* The records' chains resolved again once their unsure pairs' yes bits are
 * set, children first; each frame whose slot now runs has one pcol fewer
 * that did not run, and its kills fewer kept (yes bits only grow, so ran bits
 * only turn on). not_run, kept: per lane, word w at (w - first_word) *
 * frames (FRAMES, or 1 for the single cameras of pmx_refine_many); masks:
 * NULL, or per lane the executed bytes of n_pcols pcols, set where a pcol now
 * runs. */
void pmx_apply_unsure(int32_t *records, int64_t used, int64_t first_word, int frames, int64_t *not_run,
                      int64_t *kept, const int32_t *order, uint8_t *masks, int64_t n_pcols)
{
    for (int64_t r = 0; r < used; r += 2 + records[r + 1] * NODE_N) {
        int32_t *nodes = records + r + 2;
        const int64_t lane = (records[r] - first_word) * frames;
        int64_t *nr = not_run + lane, *kp = kept + lane;
        for (int64_t j = 0; j < records[r + 1]; j++) {
            int32_t *node = nodes + j * NODE_N;
            const Lanes r1 = (Lanes)(node[NODE_K1] >= 0 ? nodes[node[NODE_K1] * NODE_N + NODE_RAN] : node[NODE_RAN_K1]);
            const Lanes r2 = (Lanes)(node[NODE_K2] >= 0 ? nodes[node[NODE_K2] * NODE_N + NODE_RAN] : node[NODE_RAN_K2]);
            const Lanes now = (Lanes)(~node[NODE_VISIT] | node[NODE_WHOLE] | (node[NODE_YES] & r1 & r2));
            const Lanes turned = (Lanes)(now & ~node[NODE_RAN]);
            node[NODE_RAN] = now;
            for (int l = 0; l < frames; l++)
                if ((turned >> l) & 1) {
                    nr[l] -= 1, kp[l] -= node[NODE_KILLS];
                    if (masks)
                        masks[(lane + l) * n_pcols + order[node[NODE_POSITION]]] = 1;
                }
        }
    }
}

/* Every pcol of the table, a block at a time: under the cameras fr (one in
 * every lane) or, with W, under the fat camera. */
static void decide_every_block(const float *table, int64_t n_pcols, const Frames *fr, const Fat *W, uint8_t *out)
{
    Columns col;
    int32_t code[BLOCK], ids[BLOCK];
    for (int64_t p = 0; p < n_pcols; p += BLOCK) {
        int64_t nb = n_pcols - p < BLOCK ? n_pcols - p : BLOCK;
        for (int64_t j = 0; j < nb; j++)
            ids[j] = (int32_t)(p + j);
        gather_block(table, ids, nb, col);
        if (W)
            decide_fat(W, col, code);
        else
            decide_block(fr, col, code);
        for (int64_t j = 0; j < nb; j++)
            out[p + j] = (uint8_t)code[j];
    }
}

/* Every pcol's own decision (YES, NO or UNSURE) and subtree bound (out[p]
 * |= WHOLE), for tests that compare the certification with the float32
 * predicate over whole hierarchies. */
void pmx_decide_all(const float *table, int64_t n_pcols, const float *view, int flags, uint8_t *out)
{
    const unsigned mode = subnormals_off();
    Frames w;
    load_frames(&w, view, 1, flags);
    decide_every_block(table, n_pcols, &w, NULL, out);
    subnormals_back(mode);
}

/* Every pcol under the fat camera of views [n_frames, 22] (FAT_WHOLE,
 * FAT_NO or FAT_OPEN; all FAT_OPEN where the fat camera does not apply), for
 * tests that compare it with every frame's float32 predicate. */
void pmx_decide_fat_all(const float *table, int64_t n_pcols, const float *views, int n_frames, int flags,
                        const float *fat, uint8_t *out)
{
    const unsigned mode = subnormals_off();
    Frames fr;
    load_frames(&fr, views, n_frames, flags);
    if (!fat_applies(&fr, fat, n_frames)) {
        memset(out, FAT_OPEN, (size_t)n_pcols);
        subnormals_back(mode);
        return;
    }
    Fat W;
    load_fat(&W, fat, &fr, n_frames);
    decide_every_block(table, n_pcols, &fr, &W, out);
    subnormals_back(mode);
}

/* ---- the fat camera of a word, from its frames --------------------------- */

/* The bounds of the fat camera above, from the frames' float32 constants.
 * Each is computed in double and rounded up to float32 with room for the
 * double rounding, so it holds for the exact values. Only the bounds'
 * soundness matters for exactness; the eye centre (the eyes' box centre), the
 * reference rotation (the middle frame's), the pivot (the point the view axes
 * pass closest to, least squares; an orbit's centre, so that turning the
 * camera moves the points near it little) and t (the box centre of the
 * pivot's camera coordinates) are free choices that only make the bounds
 * tighter or looser. eps bounds the spectral norm by Gershgorin's circles. */

/* Relative room above a double bound before rounding up to float32: covers
 * the double arithmetic (about 2^-50 relative) many times over. */
#define FAT_ROOM 0x1p-16

/* A float32 value at least x (1 + FAT_ROOM). */
static float fat_up(double x) { return nextafterf((float)(x * (1 + FAT_ROOM)), INFINITY); }

/* x rounded to float32, held in double (exactly). */
static double fat_f32(double x) { return (double)(float)x; }

/* max and min that keep a NaN (fmax and fmin drop it, which would hide a
 * frame that is not finite). */
static double max_nan(double a, double b) { return a != a || a > b ? a : b; }
static double min_nan(double a, double b) { return a != a || a < b ? a : b; }

static double norm3(const double *v) { return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

/* The float32 centre of the box lo..hi of points p[0..n) (into centre), and
 * the largest distance of a point from it. */
static double ball_about_box(const double (*p)[3], int n, const double *lo, const double *hi, double *centre)
{
    double radius = 0;
    for (int i = 0; i < 3; i++)
        centre[i] = fat_f32(0.5 * (lo[i] + hi[i]));
    for (int f = 0; f < n; f++) {
        const double d[3] = {p[f][0] - centre[0], p[f][1] - centre[1], p[f][2] - centre[2]};
        radius = max_nan(radius, norm3(d));
    }
    return radius;
}

/* The smallest eigenvalue of the symmetric 3 x 3 matrix a (trigonometric
 * closed form; NaN for a matrix that is not finite). */
static double smallest_eigenvalue(const double a[3][3])
{
    const double p1 = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
    const double q = (a[0][0] + a[1][1] + a[2][2]) / 3;
    if (p1 == 0)
        return min_nan(a[0][0], min_nan(a[1][1], a[2][2]));
    const double p = sqrt(((a[0][0] - q) * (a[0][0] - q) + (a[1][1] - q) * (a[1][1] - q) +
                           (a[2][2] - q) * (a[2][2] - q) + 2 * p1) / 6);
    double b[3][3];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            b[i][j] = (a[i][j] - (i == j ? q : 0)) / p;
    double r = (b[0][0] * (b[1][1] * b[2][2] - b[1][2] * b[2][1]) - b[0][1] * (b[1][0] * b[2][2] - b[1][2] * b[2][0]) +
                b[0][2] * (b[1][0] * b[2][1] - b[1][1] * b[2][0])) / 2;
    r = r < -1 ? -1 : r > 1 ? 1 : r;
    return q + 2 * p * cos(acos(r) / 3 + 2.0943951023931957);
}

/* The point closest to every view axis of the frames (least squares), or
 * fallback where the axes are too near parallel to meet (a camera moving
 * forward): sum over the frames of (I - n n^T) x = sum of (I - n n^T) e, n
 * the forward row of each frame's rotation. */
static void fat_pivot(const double (*eyes)[3], const double (*rot)[3][3], int n, const double *fallback,
                      double *pivot)
{
    double a[3][3] = {{0}}, b[3] = {0};
    for (int f = 0; f < n; f++)
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) {
                const double across = (i == j) - rot[f][2][i] * rot[f][2][j];
                a[i][j] += across;
                b[i] += across * eyes[f][j];
            }
    int meet = smallest_eigenvalue(a) > 1e-3 * n;
    /* Cramer's rule: the adjugate's rows over the determinant. */
    const double c0 = a[1][1] * a[2][2] - a[1][2] * a[2][1], c1 = a[1][2] * a[2][0] - a[1][0] * a[2][2];
    const double c2 = a[1][0] * a[2][1] - a[1][1] * a[2][0];
    const double det = a[0][0] * c0 + a[0][1] * c1 + a[0][2] * c2;
    const double x[3] = {
        (b[0] * c0 + a[0][1] * (b[2] * a[1][2] - b[1] * a[2][2]) + a[0][2] * (b[1] * a[2][1] - b[2] * a[1][1])) / det,
        (a[0][0] * (b[1] * a[2][2] - b[2] * a[1][2]) + b[0] * c1 + a[0][2] * (b[2] * a[1][0] - b[1] * a[2][0])) / det,
        (a[0][0] * (b[2] * a[1][1] - b[1] * a[2][1]) + a[0][1] * (b[1] * a[2][0] - b[2] * a[1][0]) + b[0] * c2) / det};
    meet &= isfinite(x[0]) && isfinite(x[1]) && isfinite(x[2]);
    for (int i = 0; i < 3; i++)
        pivot[i] = meet ? x[i] : fallback[i];
}

/* The fat cameras of n_words words of n_frames frames (views [W, F, 22],
 * the host's view constants) into out [W, FAT_N]; a word whose bounds are not
 * finite gets NaN ones (under which nothing is decided at once). Returns -1
 * (and writes nothing) unless 1 <= n_frames <= FAT_MAX_FRAMES. */
#define FAT_MAX_FRAMES 64
int pmx_fat_cameras(const float *views, int64_t n_words, int n_frames, float *out)
{
    if (n_frames < 1 || n_frames > FAT_MAX_FRAMES)
        return -1;
    const int F = n_frames;
    double eyes[FAT_MAX_FRAMES][3], rot[FAT_MAX_FRAMES][3][3], t[FAT_MAX_FRAMES][3];
    for (int64_t w = 0; w < n_words; w++) {
        const float *v = views + w * n_frames * 22;
        float *o = out + w * FAT_N;
        double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
        for (int f = 0; f < F; f++)
            for (int i = 0; i < 3; i++) {
                eyes[f][i] = v[22 * f + EYE + i];
                for (int j = 0; j < 3; j++)
                    rot[f][i][j] = v[22 * f + RIGHT + 3 * i + j];
                lo[i] = min_nan(lo[i], eyes[f][i]), hi[i] = max_nan(hi[i], eyes[f][i]);
            }
        /* The eye ball: about the box's centre. */
        double eye[3];
        const double rho = ball_about_box((const double (*)[3])eyes, F, lo, hi, eye);
        /* The rotations about the middle frame's: |D|_2^2 is the largest
         * eigenvalue of D^T D, at most its largest absolute row sum
         * (Gershgorin; exact for a turn about one axis). */
        const double (*ref)[3] = rot[F / 2];
        double gersh = 0;
        for (int f = 0; f < F; f++) {
            double d[3][3];
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++)
                    d[i][j] = rot[f][i][j] - ref[i][j];
            for (int i = 0; i < 3; i++) {
                double row = 0;
                for (int j = 0; j < 3; j++)
                    row += fabs(d[0][i] * d[0][j] + d[1][i] * d[1][j] + d[2][i] * d[2][j]);
                gersh = max_nan(gersh, row);
            }
        }
        /* The pivot, and its camera coordinates over the frames about their
         * box's centre. The double products and sums of t round by at most
         * 2^-50 of |pivot - eye|_1. */
        double pivot[3];
        fat_pivot((const double (*)[3])eyes, (const double (*)[3][3])rot, F, eye, pivot);
        for (int i = 0; i < 3; i++)
            pivot[i] = fat_f32(pivot[i]);
        double tlo[3] = {INFINITY, INFINITY, INFINITY}, thi[3] = {-INFINITY, -INFINITY, -INFINITY}, spread1 = 0;
        for (int f = 0; f < F; f++) {
            const double d[3] = {pivot[0] - eyes[f][0], pivot[1] - eyes[f][1], pivot[2] - eyes[f][2]};
            spread1 = max_nan(spread1, fabs(d[0]) + fabs(d[1]) + fabs(d[2]));
            for (int i = 0; i < 3; i++) {
                t[f][i] = rot[f][i][0] * d[0] + rot[f][i][1] * d[1] + rot[f][i][2] * d[2];
                tlo[i] = min_nan(tlo[i], t[f][i]), thi[i] = max_nan(thi[i], t[f][i]);
            }
        }
        double centre[3];
        const double tau = ball_about_box((const double (*)[3])t, F, tlo, thi, centre);
        /* The capsule about the chord: each eye's distance from its nearest
         * point of the (float32) segment the decisions use. */
        const double *start = eyes[0];
        double step[3], length2 = 0, capsule = 0, size1 = 0;
        for (int i = 0; i < 3; i++) {
            step[i] = fat_f32(eyes[F - 1][i] - start[i]);
            length2 += step[i] * step[i];
        }
        for (int f = 0; f < F; f++) {
            double along = 0;
            for (int i = 0; i < 3; i++)
                along += (eyes[f][i] - start[i]) * step[i];
            along /= length2 > 0 ? length2 : 1.0;
            along = along < 0 ? 0 : along > 1 ? 1 : along;
            const double d[3] = {eyes[f][0] - (start[0] + along * step[0]), eyes[f][1] - (start[1] + along * step[1]),
                                 eyes[f][2] - (start[2] + along * step[2])};
            capsule = max_nan(capsule, norm3(d));
            size1 = max_nan(size1, fabs(eyes[f][0]) + fabs(eyes[f][1]) + fabs(eyes[f][2]));
        }
        /* Any step inverse will do (the decisions allow for the projection's
         * error); 0 for one point. */
        const double step_inv = length2 > 0x1p-100 ? 1.0 / length2 : 0.0;
        for (int i = 0; i < 3; i++) {
            o[FAT_EYE + i] = (float)eye[i], o[FAT_PIVOT + i] = (float)pivot[i], o[FAT_T + i] = (float)centre[i];
            o[FAT_SEGMENT + i] = (float)start[i], o[FAT_STEP + i] = (float)step[i];
            for (int j = 0; j < 3; j++)
                o[FAT_ROTATION + 3 * i + j] = (float)ref[i][j];
        }
        o[FAT_RHO] = fat_up(rho), o[FAT_EPS] = fat_up(sqrt(gersh));
        o[FAT_TAU] = fat_up(tau + 0x1p-48 * spread1);
        o[FAT_STEP_INV] = (float)step_inv, o[FAT_CAPSULE] = fat_up(capsule + 0x1p-48 * size1);
        int finite = 1;
        for (int i = 0; i < FAT_N; i++)
            finite &= isfinite(o[i]) != 0;
        if (!finite)
            for (int i = 0; i < FAT_N; i++)
                o[i] = NAN;
    }
    return 0;
}

/* ---- the mesh from the front --------------------------------------------- */

/* Per pcol, what the mesh needs of it, in one record (pmjax/_native.py
 * MeshArrays): its two vertices, their depth-first starts and positions, and
 * where its kill list starts in the kill data, and the breadth-first position
 * of the pcol that made each vertex (-1: an original). */
typedef struct {
    int32_t kill_first, kill_count, vertex[2], start[2], made_at[2];
    float position[2][3];
} PcolRecord;

/* A face with the depth-first starts of its corners. */
typedef struct {
    int32_t face, start[3];
} FaceRecord;

/* A front vertex: its depth-first start, id and position. */
typedef struct {
    int32_t start, vertex;
    float position[3];
} FrontVertex;

static inline void set_bit(uint64_t *bits, int64_t i) { bits[i >> 6] |= (uint64_t)1 << (i & 63); }

/* Rank of bit i among the set bits (bit i set): set bits before word i/64
 * (prefix[]) plus those below it in its word. */
static inline int64_t rank_of(const uint64_t *bits, const int32_t *prefix, int64_t i)
{
    uint64_t below = bits[i >> 6] & ((((uint64_t)2) << (i & 63)) - 1);
    return prefix[i >> 6] + __builtin_popcountll(below) - 1;
}

static void prefix_counts(const uint64_t *bits, int64_t words, int32_t *prefix)
{
    int32_t total = 0;
    for (int64_t w = 0; w < words; w++) {
        prefix[w] = total;
        total += __builtin_popcountll(bits[w]);
    }
}

/* The refined mesh from the pcols that did not run (pmjax/_front_mesh.py):
 * drawn faces are the base faces and those pcols' kill lists; each corner's
 * representative is the front vertex whose depth-first interval holds the
 * corner's position. Every order and index comes from a rank in a bitmap
 * (faces, front starts, vertex ids), so that besides those small bitmaps a
 * pcol that did not run costs one record and its kill data, and nothing reads
 * an array over all faces or vertices at random.
 *
 * visited_ran, visited_at: whether each of a refinement's visited pcols ran,
 * and their positions, the index of records[] (breadth-first, so that the
 * records are read in nearly increasing order). not_run_at: scratch [P].
 * Writes faces_out [n_faces, 3] (indices into ids_out, faces in increasing
 * order), ids_out and positions_out (the vertices used, by increasing id).
 * Returns their number, or -1 if the faces found are not n_faces.
 *
 * Scratch: mark [P] bytes (by breadth-first position), start_bits [V0/64+1],
 * face_bits [F/64+1], vertex_bits [(V0+P)/64+1] words (zero on entry and on return);
 * start_prefix, face_prefix, vertex_prefix int32 as their bitmaps; front
 * [V0 + 1] (the vertices not kept are written one slot past the front),
 * sorted [V0] FrontVertex; drawn [F] FaceRecord; front_index [V0] int32. */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
__attribute__((target_clones("popcnt", "default"))) /* popcount in one instruction, not a call */
#endif
int64_t pmx_front_mesh(int64_t n_original, int64_t n_pcols, int64_t n_faces_total, const uint8_t *visited_ran,
                       const int32_t *visited_at, int64_t n_visited,
                       int32_t *not_run_at, const PcolRecord *records, const FaceRecord *kill_data,
                       const FaceRecord *base, int64_t n_base, const FrontVertex *tops, const int32_t *top_at,
                       int64_t n_tops, int64_t n_faces, int32_t *faces_out, int32_t *ids_out, float *positions_out,
                       uint8_t *mark, uint64_t *start_bits, uint64_t *face_bits, uint64_t *vertex_bits,
                       int32_t *start_prefix, int32_t *face_prefix, int32_t *vertex_prefix, FrontVertex *front,
                       FrontVertex *sorted, FaceRecord *drawn, int32_t *front_index)
{
    const int64_t V0 = n_original;
    const int64_t start_words = V0 / 64 + 1, face_words = n_faces_total / 64 + 1;
    const int64_t vertex_words = (V0 + n_pcols) / 64 + 1;
    /* The records and kill lists of the pcols that did not run are sparse in
     * arrays far larger than the cache, so each is a miss: requested
     * MESH_AHEAD pcols early, the misses overlap. */
    const int64_t MESH_AHEAD = 16;
    /* Without branches: whether a visited pcol ran is a coin toss to the
     * branch predictor. Every slot is written, the count advances on those
     * that did not run (mark is zero on entry, so a pcol that ran keeps 0). */
    int64_t n_not_run = 0;
    for (int64_t i = 0; i < n_visited; i++) {
        const int32_t at = visited_at[i];
        const uint8_t not_ran = !visited_ran[i];
        not_run_at[n_not_run] = at;
        n_not_run += not_ran;
        mark[at] = not_ran;
    }
    /* The front and the drawn faces. Below each pcol that did not run: its
     * vertices that are original or whose own pcol ran, and its kill list. */
    int64_t n_front = 0, n_drawn = 0;
    for (int64_t i = 0; i < n_not_run; i++) {
        if (i + MESH_AHEAD < n_not_run)
            __builtin_prefetch(records + not_run_at[i + MESH_AHEAD]);
        if (i + MESH_AHEAD / 2 < n_not_run) /* its record was requested MESH_AHEAD / 2 steps ago */
            __builtin_prefetch(kill_data + records[not_run_at[i + MESH_AHEAD / 2]].kill_first);
        const PcolRecord *r = records + not_run_at[i];
        for (int j = 0; j < 2; j++) {
            /* Without branches too: the vertex is written, and kept when it is
             * original or its own pcol ran. */
            const int32_t made = r->made_at[j];
            const int kept = (made < 0) | !mark[made < 0 ? 0 : made];
            FrontVertex *f = front + n_front;
            f->start = r->start[j];
            f->vertex = r->vertex[j];
            memcpy(f->position, r->position[j], sizeof f->position);
            n_front += kept;
            start_bits[r->start[j] >> 6] |= (uint64_t)kept << (r->start[j] & 63);
        }
        for (int32_t j = 0; j < r->kill_count; j++) {
            drawn[n_drawn] = kill_data[r->kill_first + j];
            set_bit(face_bits, drawn[n_drawn].face);
            n_drawn++;
        }
    }
    /* The tops: the roots that ran (top_at >= 0) and the lone originals. */
    for (int64_t i = 0; i < n_tops; i++)
        if (top_at[i] < 0 || !mark[top_at[i]]) {
            front[n_front++] = tops[i];
            set_bit(start_bits, tops[i].start);
        }
    for (int64_t i = 0; i < n_base; i++)
        set_bit(face_bits, base[i].face);
    const int64_t total = n_drawn + n_base;
    /* The front in depth-first order: each vertex goes to the rank of its start. */
    prefix_counts(start_bits, start_words, start_prefix);
    for (int64_t i = 0; i < n_front; i++)
        sorted[rank_of(start_bits, start_prefix, front[i].start)] = front[i];
    /* Each drawn face at its rank; each corner first the rank of the front
     * vertex holding it (front_index: -1 unused, 0 used). */
    int64_t n_ids = 0;
    if (total == n_faces) {
        memset(front_index, 0xff, sizeof(int32_t) * (size_t)n_front);
        prefix_counts(face_bits, face_words, face_prefix);
        for (int64_t i = 0; i < total; i++) {
            const FaceRecord *f = i < n_drawn ? drawn + i : base + (i - n_drawn);
            int32_t *row = faces_out + 3 * rank_of(face_bits, face_prefix, f->face);
            for (int c = 0; c < 3; c++) {
                int32_t k = (int32_t)rank_of(start_bits, start_prefix, f->start[c]);
                row[c] = k;
                front_index[k] = 0;
            }
        }
        /* The vertices used in increasing id order (the ids' bitmap), each
         * front vertex's output index, then the corners through it. */
        for (int64_t k = 0; k < n_front; k++)
            if (front_index[k] == 0)
                set_bit(vertex_bits, sorted[k].vertex);
        prefix_counts(vertex_bits, vertex_words, vertex_prefix);
        for (int64_t k = 0; k < n_front; k++)
            if (front_index[k] == 0) {
                int64_t out = rank_of(vertex_bits, vertex_prefix, sorted[k].vertex);
                front_index[k] = (int32_t)out;
                ids_out[out] = sorted[k].vertex;
                memcpy(positions_out + 3 * out, sorted[k].position, 3 * sizeof(float));
                n_ids++;
            }
        for (int64_t i = 0; i < 3 * n_faces; i++)
            faces_out[i] = front_index[faces_out[i]];
    }
    /* Leave the scratch as found. */
    for (int64_t i = 0; i < n_not_run; i++)
        mark[not_run_at[i]] = 0;
    memset(start_bits, 0, sizeof(uint64_t) * (size_t)start_words);
    memset(face_bits, 0, sizeof(uint64_t) * (size_t)face_words);
    memset(vertex_bits, 0, sizeof(uint64_t) * (size_t)vertex_words);
    return total == n_faces ? n_ids : -1;
}

/* A module, so that setuptools builds and installs this file like any
 * extension; the functions are called through ctypes (pmjax/_native.py). */
static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_front_native",
                                    "C loops of the output-sensitive engine (called through ctypes).", -1, NULL, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__front_native(void) { return PyModule_Create(&module); }
