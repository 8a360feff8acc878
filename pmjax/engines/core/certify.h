/* The certified decision of one pcol under one camera, and the bounds
 * that decide everything below a pcol: inline, so that each SIMD level's
 * loops (decide.c, fat.c) compile them at their own width.
 *
 * The results are the bits of the dense engine:
 *
 *  - a pcol's bound over the pcols below it is pmjax/_subtree.py's, with its
 *    margins and range guards (sound: "whole" guarantees that every pcol
 *    below collapses under the float32 predicate);
 *  - a pcol's own decision is certified: every comparison of the float32
 *    predicate (pmjax/_predicate.py) is evaluated here (in float32) together
 *    with a bound on how far ANY float32 evaluation of the same formula can be
 *    from the exact value (fused multiply-adds or not, any association, flush
 *    to zero), this one included. When the margin exceeds twice that bound,
 *    the float32 predicate must return the same bit; otherwise the pcol is
 *    "unsure" and the caller decides it with the float32 predicate itself.
 */
#ifndef PMX_CERTIFY_H
#define PMX_CERTIFY_H

#include "internal.h"

/* The orientation bound projects the eye vector on the unit axis. It bounds
 * something only where the pcol's axis is unit within 1e-3 (elsewhere facing
 * is 2, pmjax/_subtree.py), so 1 / |axis| > AXIS_LOW, and the bound only grows
 * with the projection: the projection on the axis times AXIS_LOW is a lower
 * bound that keeps it sound. */
#define AXIS_LOW 0.998f

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
 * XLA's; the view constants may also come from another evaluation than
 * XLA's (the host's, in tests), off XLA's by at most VIEW relative in any one
 * factor of a term. So |d| > REL * m (+ the flush
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

/* One camera's constants (float32; see VIEW). */
typedef struct {
    float e[3], r[3], u[3], f[3], k[8], kappa2;
    float kabs; /* 1 + |a_x| + |a_y| + l_x + l_y + |b_x| + |b_y| + kappa2: the view's factor bound */
    int flags;
} View;

static inline void load_view(View *v, const float *values, int flags)
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

/* max(x, 0) as a select (fmaxf is a library call for its NaN rules). */
static inline float pos(float x) { return x > 0.0f ? x : 0.0f; }

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
    Lane L = {.ex = w->e[0], .ey = w->e[1], .ez = w->e[2], .R0 = w->r[0], .R1 = w->r[1], .R2 = w->r[2],
              .U0 = w->u[0], .U1 = w->u[1], .U2 = w->u[2], .F0 = w->f[0], .F1 = w->f[1], .F2 = w->f[2],
              .k0 = k[0], .k1 = k[1], .k2 = k[2], .k3 = k[3], .k4 = k[4], .k5 = k[5], .k6 = k[6], .k7 = k[7],
              .kappa2 = w->kappa2, .kabs = w->kabs};
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
 * all_tests (a constant), the view is a fast_view. settled (a constant,
 * SETTLED_FRUSTUM | SETTLED_ORIENTATION) names tests known to keep the pcol
 * under this frame (the fat camera's FAT_INSIDE, FAT_SCREEN): their own
 * decisions are "no", and their bounds, which would collapse the pcol itself
 * (its reach and cone hold its own sphere and cone), cannot hold, so neither
 * is evaluated (the same bits). */
static inline __attribute__((always_inline)) int32_t decide_one(const Lane *L, const Pcol q, const int ortho,
                                                                const int all_tests, const int settled)
{
    const float R0 = L->R0, R1 = L->R1, R2 = L->R2, U0 = L->U0, U1 = L->U1, U2 = L->U2;
    const float F0 = L->F0, F1 = L->F1, F2 = L->F2;
    const float k0 = L->k0, k1 = L->k1, k2 = L->k2, k3 = L->k3, k4 = L->k4, k5 = L->k5, k6 = L->k6, k7 = L->k7;
    const float kappa2 = L->kappa2, kabs = L->kabs, kfac = L->kfac, kpad = L->kpad;
    const _Bool frustum = (!(settled & SETTLED_FRUSTUM)) & (all_tests | L->frustum);
    const _Bool orientation = (!(settled & SETTLED_ORIENTATION)) & (all_tests | L->orientation);
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

#endif
