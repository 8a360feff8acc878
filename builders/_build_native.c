/* The builder's per-batch steps that walk the mesh, as plain C loops: the
 * faces around each vertex, edge keys, costs carried by key and quadric
 * placements, the cheapest share, validity, the choice of independent
 * collapses, applying a batch, and new vertices' normals.
 *
 * Each loop is a NumPy step of builders/ with its arithmetic in the same
 * order (no contraction), so a build with these loops is the NumPy build,
 * bit for bit. builders/_independent.py chooses the set in parallel rounds
 * of array reductions; with fixed priorities those rounds take exactly what
 * a sequential greedy over the candidates in cost order takes. Here the
 * greedy runs sequentially, and also works out the round in which the
 * parallel version decides each candidate, so that its round cap (late
 * rounds are left to the next batch) keeps the same set.
 *
 * Two candidates conflict when their domains (the faces touching either
 * endpoint) share a face, i.e. when one has an endpoint on a face of the
 * other's domain.
 *  - A candidate with a cheaper taken conflicting candidate is dead: it is
 *    removed at the end of the earliest such candidate's round.
 *  - Any other candidate is a round winner: the round after every cheaper
 *    conflicting candidate has been removed. Its validity decides whether
 *    it is taken; an invalid winner is removed without blocking anything.
 *
 * The buffers are the caller's, allocated once per build (no allocation
 * here, and no fresh pages to fault in every batch).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
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

/* What a candidate became (builders/_native.py). */
enum { DEAD = 0, TAKEN = 1, INVALID = 2, UNCHECKED = 3 };

#define NEVER INT32_MAX

/* How many candidates ahead the greedy prefetches, per stage. */
#define AHEAD 8

/* The greedy's state of a vertex: the earliest round of a taken candidate
 * with the vertex on a face of its domain (NEVER: none), and the latest
 * removal round of a processed candidate with an endpoint there. One row,
 * so that a candidate's two checks cost two cache lines. */
typedef struct {
    int32_t blocked, round;
} Vertex;

/* The faces around a vertex: face[first .. first + count). */
typedef struct {
    int32_t first, count;
} Around;

/* The caller's buffers (builders/_native.py Scratch), sized for every
 * vertex id and face of the build. Only the rows of vertices with a face
 * are ever set or read, so a batch costs its faces, not the ids so far.
 * around and face are the current faces around each vertex
 * (pmx_vertex_faces); the link-test stamps only grow, from call to call
 * (stamp[0] is the last one used). */
typedef struct {
    Around *around;  /* [n_vertices] */
    int32_t *face;   /* [3 F], ascending face ids per vertex */
    Vertex *vertex;  /* [n_vertices] */
    int32_t *side_a; /* [n_vertices]: link-test stamps */
    int32_t *side_b; /* [n_vertices] */
    int32_t *stamp;  /* [1] */
} Scratch;

typedef struct {
    int64_t n_vertices;
    const int32_t *faces;
    const double *pos;
    const uint8_t *boundary;
    double min_area2;
    Scratch s;
} Mesh;

/* The faces around each vertex with a face: its count, then its first slot
 * (in order of first appearance), then a fill that counts again. */
void pmx_vertex_faces(int64_t n_faces, const int32_t *faces, Around *around, int32_t *face) {
    int64_t n = 3 * n_faces;
    for (int64_t i = 0; i < n; i++) around[faces[i]] = (Around){-1, 0};
    for (int64_t i = 0; i < n; i++) around[faces[i]].count++;
    int32_t next = 0;
    for (int64_t i = 0; i < n; i++) {
        Around *r = around + faces[i];
        if (r->first < 0) {
            r->first = next;
            next += r->count;
            r->count = 0;
        }
    }
    for (int64_t f = 0; f < n_faces; f++)
        for (int k = 0; k < 3; k++) {
            Around *r = around + faces[3 * f + k];
            face[r->first + r->count++] = (int32_t)f;
        }
}

/* Costs and placements of the pairs known from the last batch: keys[i]
 * found in old_keys (both ascending, a merge) copies its row; the others'
 * positions go to fresh. Returns how many are fresh, or -1 if keys are not
 * ascending. */
int64_t pmx_carry_costs(int64_t n_old, const int64_t *old_keys, const double *old_x, const double *old_cost, int64_t n,
                        const int64_t *keys, double *x, double *cost, int64_t *fresh) {
    for (int64_t i = 1; i < n; i++)
        if (keys[i] <= keys[i - 1]) return -1;
    int64_t j = 0, n_fresh = 0;
    for (int64_t i = 0; i < n; i++) {
        while (j < n_old && old_keys[j] < keys[i]) j++;
        if (j < n_old && old_keys[j] == keys[i]) {
            for (int k = 0; k < 3; k++) x[3 * i + k] = old_x[3 * j + k];
            cost[i] = old_cost[j];
        } else {
            fresh[n_fresh++] = i;
        }
    }
    return n_fresh;
}

/* The current mesh, for the validity test and the greedy. */
static void start_mesh(Mesh *m, const int32_t *faces, int64_t n_vertices, const double *pos, const uint8_t *boundary,
                       double min_area2, Scratch s) {
    m->n_vertices = n_vertices;
    m->faces = faces;
    m->pos = pos;
    m->boundary = boundary;
    m->min_area2 = min_area2;
    m->s = s;
}

/* A fresh link-test stamp; once they run out, every stamp starts again. */
static int32_t next_stamp(Mesh *m) {
    if (*m->s.stamp == INT32_MAX) {
        memset(m->s.side_a, 0, (size_t)m->n_vertices * sizeof(int32_t));
        memset(m->s.side_b, 0, (size_t)m->n_vertices * sizeof(int32_t));
        *m->s.stamp = 0;
    }
    return ++*m->s.stamp;
}

static void cross(const double u[3], const double v[3], double out[3]) {
    out[0] = u[1] * v[2] - u[2] * v[1];
    out[1] = u[2] * v[0] - u[0] * v[2];
    out[2] = u[0] * v[1] - u[1] * v[0];
}

static double dot(const double u[3], const double v[3]) { return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]; }

/* A dot product of rows of three in pmjax/_distance.py dot_rows's order (the
 * order of np.einsum("ij,ij->i") here): the first and third terms, then the
 * second. */
static double einsum_dot(const double u[3], const double v[3]) { return (u[0] * v[0] + u[2] * v[2]) + u[1] * v[1]; }

static int has(const int32_t *t, int32_t v) { return t[0] == v || t[1] == v || t[2] == v; }

/* builders/_validity.py collapse_is_valid for one candidate: no domain face
 * flips or degenerates when a and b move to x; with the link test, the
 * common neighbours of a and b are exactly the apexes of the faces on edge
 * ab, and no interior edge joins two border vertices. */
static int collapse_is_valid(Mesh *m, int32_t a, int32_t b, const double *x, int link_test) {
    const Around *around = m->s.around;
    const int32_t *face = m->s.face;
    int64_t apexes = 0;
    for (int side = 0; side < 2; side++) {
        Around r = around[side ? b : a];
        for (int32_t j = r.first; j < r.first + r.count; j++) {
            const int32_t *t = m->faces + 3 * (int64_t)face[j];
            int with_a = has(t, a), with_b = has(t, b);
            if (side && with_a) continue; /* seen from a's side already */
            if (with_a && with_b) {       /* vanishes with the collapse */
                apexes++;
                continue;
            }
            /* Rotate the moving corner to the front; compare the doubled-area
             * normal before and after it moves to x. */
            int c = (t[0] == a || t[0] == b) ? 0 : (t[1] == a || t[1] == b) ? 1 : 2;
            const double *q0 = m->pos + 3 * (int64_t)t[c];
            const double *q1 = m->pos + 3 * (int64_t)t[(c + 1) % 3];
            const double *q2 = m->pos + 3 * (int64_t)t[(c + 2) % 3];
            double e1[3] = {q1[0] - q0[0], q1[1] - q0[1], q1[2] - q0[2]};
            double e2[3] = {q2[0] - q0[0], q2[1] - q0[1], q2[2] - q0[2]};
            double n1[3] = {q1[0] - x[0], q1[1] - x[1], q1[2] - x[2]};
            double n2[3] = {q2[0] - x[0], q2[1] - x[1], q2[2] - x[2]};
            double before[3], after[3];
            cross(e1, e2, before);
            cross(n1, n2, after);
            if (dot(after, before) <= 0.0 || dot(after, after) <= m->min_area2) return 0;
        }
    }
    if (!link_test) return 1;
    /* Distinct vertices other than a and b on faces holding a, then those
     * of them also on faces holding b. */
    int32_t stamp = next_stamp(m);
    int64_t common = 0;
    Around ra = around[a], rb = around[b];
    for (int32_t j = ra.first; j < ra.first + ra.count; j++) {
        const int32_t *t = m->faces + 3 * (int64_t)face[j];
        for (int k = 0; k < 3; k++)
            if (t[k] != a && t[k] != b) m->s.side_a[t[k]] = stamp;
    }
    for (int32_t j = rb.first; j < rb.first + rb.count; j++) {
        const int32_t *t = m->faces + 3 * (int64_t)face[j];
        for (int k = 0; k < 3; k++) {
            int32_t u = t[k];
            if (u != a && u != b && m->s.side_a[u] == stamp && m->s.side_b[u] != stamp) {
                m->s.side_b[u] = stamp;
                common++;
            }
        }
    }
    int pinch = apexes >= 2 && m->boundary[a] && m->boundary[b];
    return common == apexes && !pinch;
}

/* ok[i] = validity of moving candidate k = idx[i] (a[k], b[k]) to x[k] (3
 * doubles) on the current faces. */
void pmx_collapse_valid(int64_t n, const int64_t *idx, const int32_t *a, const int32_t *b, const double *x,
                        const uint8_t *link_test, int64_t n_faces, const int32_t *faces, int64_t n_vertices,
                        const double *pos, const uint8_t *boundary, double min_area2, Around *around,
                        int32_t *face, Vertex *vertex, int32_t *side_a, int32_t *side_b, int32_t *stamp, uint8_t *ok) {
    Mesh m;
    start_mesh(&m, faces, n_vertices, pos, boundary, min_area2,
               (Scratch){around, face, vertex, side_a, side_b, stamp});
    for (int64_t i = 0; i < n; i++) {
        int64_t k = idx[i];
        ok[i] = (uint8_t)collapse_is_valid(&m, a[k], b[k], x + 3 * k, link_test[k]);
    }
}

/* The greedy over candidates idx[0 .. n-1] (cheapest first). For each, state
 * (DEAD, TAKEN, INVALID, or UNCHECKED: a winner after max_rounds, once a
 * candidate was taken within them, so never chosen) and round (the round
 * of the parallel version in which it is removed). assume_valid: the
 * candidates were found valid already. Returns the last round the parallel
 * version runs: max_rounds, or the first round that takes something if
 * that is later; NEVER if nothing is taken.
 *
 * Conflicts are found through vertices: j conflicts with i when an endpoint
 * of j is a corner of a face around an endpoint of i. A dead candidate
 * therefore costs two vertex rows; only winners walk their faces. */
int64_t pmx_select_independent(int64_t n, const int64_t *idx, const int32_t *a, const int32_t *b, const double *x,
                               const uint8_t *link_test, int64_t n_faces, const int32_t *faces, int64_t n_vertices,
                               const double *pos, const uint8_t *boundary, double min_area2, Around *around,
                               int32_t *face, Vertex *vertex, int32_t *side_a, int32_t *side_b, int32_t *stamp,
                               int assume_valid, int64_t max_rounds, uint8_t *state, int32_t *round) {
    Mesh m;
    start_mesh(&m, faces, n_vertices, pos, boundary, min_area2,
               (Scratch){around, face, vertex, side_a, side_b, stamp});
    for (int64_t i = 0; i < 3 * n_faces; i++) vertex[faces[i]] = (Vertex){NEVER, 0};
    int64_t first_taken = NEVER;
    for (int64_t i = 0; i < n; i++) {
        /* Candidates come in cost order, scattered over the mesh: fetch what
         * the next ones read while this one runs. Their endpoints, then their
         * vertex rows; then, for those not blocked so far (likely winners,
         * which walk their faces), their faces, then their corners' rows. */
        if (i + 3 * AHEAD < n) __builtin_prefetch(a + idx[i + 3 * AHEAD]), __builtin_prefetch(b + idx[i + 3 * AHEAD]);
        if (i + 2 * AHEAD < n) {
            int64_t k2 = idx[i + 2 * AHEAD];
            __builtin_prefetch(vertex + a[k2]);
            __builtin_prefetch(vertex + b[k2]);
            __builtin_prefetch(around + a[k2]);
            __builtin_prefetch(around + b[k2]);
        }
        if (i + AHEAD < n) {
            int64_t k1 = idx[i + AHEAD];
            if (vertex[a[k1]].blocked == NEVER && vertex[b[k1]].blocked == NEVER)
                for (int e = 0; e < 2; e++) {
                    Around re = around[e ? b[k1] : a[k1]];
                    for (int32_t j = re.first; j < re.first + re.count; j++)
                        __builtin_prefetch(faces + 3 * (int64_t)face[j]);
                }
        }
        if (i + AHEAD / 2 < n) {
            int64_t k1 = idx[i + AHEAD / 2];
            if (vertex[a[k1]].blocked == NEVER && vertex[b[k1]].blocked == NEVER)
                for (int e = 0; e < 2; e++) {
                    Around re = around[e ? b[k1] : a[k1]];
                    for (int32_t j = re.first; j < re.first + re.count; j++) {
                        const int32_t *t = faces + 3 * (int64_t)face[j];
                        for (int c = 0; c < 3; c++) {
                            __builtin_prefetch(vertex + t[c]);
                            __builtin_prefetch(pos + 3 * (int64_t)t[c]);
                        }
                    }
                }
        }
        int64_t k = idx[i];
        int32_t ends[2] = {a[k], b[k]};
        Vertex *va = vertex + ends[0], *vb = vertex + ends[1];
        int32_t r = va->blocked < vb->blocked ? va->blocked : vb->blocked;
        if (r != NEVER) {
            state[i] = DEAD;
        } else {
            /* A winner the round after its cheaper conflicting candidates left. */
            r = 0;
            for (int e = 0; e < 2; e++) {
                Around re = around[ends[e]];
                for (int32_t j = re.first; j < re.first + re.count; j++) {
                    const int32_t *t = faces + 3 * (int64_t)face[j];
                    for (int c = 0; c < 3; c++)
                        if (vertex[t[c]].round > r) r = vertex[t[c]].round;
                }
            }
            r++;
            if (assume_valid)
                state[i] = TAKEN;
            else if (r > max_rounds && first_taken <= max_rounds)
                state[i] = UNCHECKED;
            else
                state[i] = collapse_is_valid(&m, ends[0], ends[1], x + 3 * k, link_test[k]) ? TAKEN : INVALID;
            if (state[i] == TAKEN) {
                if (r < first_taken) first_taken = r;
                /* Every vertex of its domain is blocked from this round on. */
                for (int e = 0; e < 2; e++) {
                    Around re = around[ends[e]];
                    for (int32_t j = re.first; j < re.first + re.count; j++) {
                        const int32_t *t = faces + 3 * (int64_t)face[j];
                        for (int c = 0; c < 3; c++)
                            if (vertex[t[c]].blocked > r) vertex[t[c]].blocked = r;
                    }
                }
            }
        }
        round[i] = r;
        if (va->round < r) va->round = r;
        if (vb->round < r) vb->round = r;
    }
    if (first_taken == NEVER) return NEVER;
    return first_taken > max_rounds ? first_taken : max_rounds;
}

/* builders/_quadrics.py evaluate: x^T A x + 2 b^T x + c of a packed quadric,
 * term by term in its order. */
static double evaluate(const double *q, const double *x) {
    double X = x[0], Y = x[1], Z = x[2];
    return q[0] * X * X + 2 * q[1] * X * Y + 2 * q[2] * X * Z + 2 * q[3] * X + q[4] * Y * Y + 2 * q[5] * Y * Z +
           2 * q[6] * Y + q[7] * Z * Z + 2 * q[8] * Z + q[9];
}

/* NumPy's minimum and maximum: NaN wins. */
static double np_minimum(double u, double v) { return (u <= v || isnan(u)) ? u : v; }
static double np_maximum(double u, double v) { return (u >= v || isnan(u)) ? u : v; }

static double norm3(const double u[3]) { return sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]); }

static void sum_quadrics(const double *quadric, int32_t a, int32_t b, double q[10]) {
    for (int k = 0; k < 10; k++) q[k] = quadric[10 * (int64_t)a + k] + quadric[10 * (int64_t)b + k];
}

/* scale[i] = trace / 3 of the summed quadric of pair (a[i], b[i]), for
 * callers that raise it to the third power themselves. */
void pmx_quadric_scale(int64_t n, const int32_t *a, const int32_t *b, const double *quadric, double *scale) {
    for (int64_t i = 0; i < n; i++) {
        double q[10];
        sum_quadrics(quadric, a[i], b[i], q);
        scale[i] = (q[0] + q[4] + q[7]) / 3.0;
    }
}

/* Where the solvability threshold 1e-9 scale^3 is not given, it is NumPy's
 * power, whose rounding is NumPy's own (its SIMD kernels differ from the C
 * library's pow in the last bits). scale * scale * scale is within a few
 * units in the last place of it while the threshold stays far from
 * underflow and overflow; a determinant closer to it than this relative
 * margin, or a threshold outside that range, is left to the caller, who
 * applies NumPy's power. */
#define THRESHOLD_MARGIN 1e-9
#define THRESHOLD_LOW 0x1p-900
#define THRESHOLD_HIGH 0x1p900

/* builders/_quadrics.py optimal_placement of the summed quadrics of pairs
 * (a[r], b[r]) for the rows r = rows[i] (rows NULL: r = i), i < n: the
 * adjugate solution where |det| > the threshold and it lands within the
 * pair's length of its midpoint and is no dearer than an endpoint, else the
 * best of the two endpoints and the midpoint (first of equals). Writes
 * x[r] (3 doubles) and cost[r] >= 0.
 * threshold: [n] given thresholds (by i), or NULL: then rows whose
 * determinant is too close to the threshold to decide are skipped and
 * written to unsure; returns how many (0 when threshold is given). */
int64_t pmx_quadric_placement(int64_t n, const int64_t *rows, const int32_t *a, const int32_t *b,
                              const double *quadric, const double *pos, const double *threshold, double *x,
                              double *cost, int64_t *unsure) {
    int64_t n_unsure = 0;
    for (int64_t i = 0; i < n; i++) {
        /* The pairs' quadric rows are scattered over the hierarchy: fetch
         * those of the pairs ahead (two cache lines a row). */
        if (i + AHEAD < n) {
            int64_t r = rows ? rows[i + AHEAD] : i + AHEAD;
            const double *qa = quadric + 10 * (int64_t)a[r], *qb = quadric + 10 * (int64_t)b[r];
            __builtin_prefetch(qa), __builtin_prefetch(qa + 9), __builtin_prefetch(qb), __builtin_prefetch(qb + 9);
            __builtin_prefetch(pos + 3 * (int64_t)a[r]), __builtin_prefetch(pos + 3 * (int64_t)b[r]);
        }
        int64_t r = rows ? rows[i] : i;
        double q[10];
        sum_quadrics(quadric, a[r], b[r], q);
        double a00 = q[0], a01 = q[1], a02 = q[2], b0 = q[3], a11 = q[4], a12 = q[5], b1 = q[6], a22 = q[7], b2 = q[8];
        double c00 = a11 * a22 - a12 * a12;
        double c01 = a02 * a12 - a01 * a22;
        double c02 = a01 * a12 - a02 * a11;
        double c11 = a00 * a22 - a02 * a02;
        double c12 = a01 * a02 - a00 * a12;
        double c22 = a00 * a11 - a01 * a01;
        double det = a00 * c00 + a01 * c01 + a02 * c02;
        int solvable;
        if (threshold) {
            solvable = fabs(det) > threshold[i];
        } else {
            double scale = (a00 + a11 + a22) / 3.0;
            double t = 1e-9 * (scale * scale * scale), d = fabs(det);
            /* Decided when the margin holds, with t far from underflow and
             * overflow (where the rounding is not relative; NaN compares
             * false everywhere). */
            int in_range = fabs(t) > THRESHOLD_LOW && fabs(t) < THRESHOLD_HIGH;
            if (in_range && d > t + THRESHOLD_MARGIN * fabs(t))
                solvable = 1;
            else if (in_range && d < t - THRESHOLD_MARGIN * fabs(t))
                solvable = 0;
            else {
                unsure[n_unsure++] = r;
                continue;
            }
        }
        double inv_det = solvable ? 1.0 / det : 0.0;
        double *xi = x + 3 * r;
        xi[0] = -(c00 * b0 + c01 * b1 + c02 * b2) * inv_det;
        xi[1] = -(c01 * b0 + c11 * b1 + c12 * b2) * inv_det;
        xi[2] = -(c02 * b0 + c12 * b1 + c22 * b2) * inv_det;
        const double *pa = pos + 3 * (int64_t)a[r], *pb = pos + 3 * (int64_t)b[r];
        double mid[3], edge[3], off[3];
        for (int k = 0; k < 3; k++) {
            mid[k] = 0.5 * (pa[k] + pb[k]);
            edge[k] = pb[k] - pa[k];
            off[k] = xi[k] - mid[k];
        }
        solvable = solvable && norm3(off) <= norm3(edge);
        double c = evaluate(q, xi);
        if (!solvable || c > np_minimum(evaluate(q, pa), evaluate(q, pb))) {
            /* The first of the cheapest options; a NaN cost is picked first. */
            const double *option[3] = {pa, pb, mid};
            int pick = 0;
            double best = evaluate(q, pa);
            for (int o = 1; o < 3 && !isnan(best); o++) {
                double e = evaluate(q, option[o]);
                if (e < best || isnan(e)) {
                    best = e;
                    pick = o;
                }
            }
            for (int k = 0; k < 3; k++) xi[k] = option[pick][k];
            c = np_maximum(best, 0.0);
        }
        cost[r] = np_maximum(c, 0.0);
    }
    return n_unsure;
}

/* builders/_build.py _cheapest, first half: the ids of the k cheapest of
 * cost[0 .. n-1] in index order, given kth, the k-th smallest cost: those
 * below it, then the first ties at it. Returns 0, or -1 if a cost is NaN. */
int64_t pmx_pick_cheapest(int64_t n, const double *cost, int64_t k, double kth, int64_t *out) {
    int64_t below = 0;
    for (int64_t i = 0; i < n; i++) {
        if (isnan(cost[i])) return -1;
        below += cost[i] < kth;
    }
    int64_t ties = k - below, m = 0;
    for (int64_t i = 0; i < n && m < k; i++)
        if (cost[i] < kth || (cost[i] == kth && ties-- > 0)) out[m++] = i;
    return 0;
}

static int by_value(const void *p, const void *q) {
    int64_t u = *(const int64_t *)p, v = *(const int64_t *)q;
    return (u > v) - (u < v);
}

/* Second half: order[] sorts value[] (not stably); put each run of equal
 * values back in ascending order[] (= index order), which makes the sort
 * stable. */
void pmx_stable_ties(int64_t n, const double *value, int64_t *order) {
    int64_t i = 0;
    while (i < n) {
        int64_t j = i + 1;
        while (j < n && value[order[j]] == value[order[i]]) j++;
        if (j - i > 16) {
            qsort(order + i, (size_t)(j - i), sizeof *order, by_value);
        } else {
            for (int64_t u = i + 1; u < j; u++) {
                int64_t o = order[u], w = u;
                for (; w > i && order[w - 1] > o; w--) order[w] = order[w - 1];
                order[w] = o;
            }
        }
        i = j;
    }
}

/* builders/_quadrics.py scatter_add: out[index[i]][c] += columns[c][i / repeat]
 * for every i in order, column by column the order of NumPy's bincount (so
 * the same sums, bit for bit), all k columns in one pass. columns: k
 * contiguous columns of n_rows; out: (n_out, k), zero on entry. */
void pmx_scatter_add(int64_t n_index, const int64_t *index, int64_t k, const double *columns, int64_t n_rows,
                     int64_t repeat, double *out) {
    for (int64_t i = 0; i < n_index; i++) {
        double *row = out + index[i] * k;
        const double *value = columns + i / repeat;
        for (int64_t c = 0; c < k; c++) row[c] += value[c * n_rows];
    }
}

/* The three edge keys of each face (builders/_topology.py edge_keys of
 * corners k and k + 1): min << 32 | max. */
void pmx_edge_keys(int64_t n_faces, const int32_t *faces, int64_t *keys) {
    for (int64_t f = 0; f < n_faces; f++)
        for (int k = 0; k < 3; k++) {
            int64_t u = faces[3 * f + k], w = faces[3 * f + (k + 1) % 3];
            keys[3 * f + k] = u < w ? (u << 32 | w) : (w << 32 | u);
        }
}

/* Sort edge keys (min << 32 | max, ids below 2^31) ascending: a least
 * significant digit radix sort, the same order as NumPy's sort of the keys
 * (integers sort to one order) at a few passes over them. Digits of at most
 * RADIX_BITS bits cover the bits the largest id uses in each half of the
 * key; the other bits are zero in every key. tmp: n int64 of room; counts:
 * RADIX_PASSES << RADIX_BITS int64 of room. The result is in keys; returns
 * 0, or -1 (keys untouched) where a key is negative or an id reaches 2^31. */
#define RADIX_BITS 12
#define RADIX_PASSES 6
int pmx_sort_keys(int64_t n, int64_t *keys, int64_t *tmp, int64_t *counts) {
    /* The bits the ids use, in either half. */
    uint64_t used = 0;
    for (int64_t i = 0; i < n; i++) used |= ((uint64_t)keys[i] & 0xFFFFFFFFu) | ((uint64_t)keys[i] >> 32);
    if (used >> 31) return -1;
    int bits = 1;
    while (bits < 32 && (used >> bits)) bits++;
    int per_half = (bits + RADIX_BITS - 1) / RADIX_BITS;
    int width = (bits + per_half - 1) / per_half;
    int n_pass = 2 * per_half;
    int shift[RADIX_PASSES];
    for (int d = 0; d < per_half; d++) {
        shift[d] = d * width;
        shift[per_half + d] = 32 + d * width;
    }
    uint64_t mask = ((uint64_t)1 << width) - 1;
    /* Every pass's digit histogram from one read of the keys. */
    memset(counts, 0, sizeof(int64_t) * ((int64_t)n_pass << width));
    for (int64_t i = 0; i < n; i++) {
        uint64_t k = (uint64_t)keys[i];
        for (int d = 0; d < n_pass; d++) counts[((int64_t)d << width) + ((k >> shift[d]) & mask)]++;
    }
    /* Each pass moves the keys, stably by its digit, to the other buffer;
     * a digit the same in every key moves nothing. */
    int64_t *src = keys, *dst = tmp;
    for (int d = 0; d < n_pass; d++) {
        int64_t *count = counts + ((int64_t)d << width);
        int64_t start = 0, one_bucket = 0;
        for (uint64_t b = 0; b <= mask; b++) {
            int64_t c = count[b];
            if (c == n) one_bucket = 1;
            count[b] = start;
            start += c;
        }
        if (one_bucket) continue;
        for (int64_t i = 0; i < n; i++) {
            uint64_t k = (uint64_t)src[i];
            dst[count[(k >> shift[d]) & mask]++] = (int64_t)k;
        }
        int64_t *swap = src;
        src = dst;
        dst = swap;
    }
    if (src != keys) memcpy(keys, src, sizeof(int64_t) * n);
    return 0;
}

/* The distinct keys of sorted keys[0 .. n-1], with their ends and counts.
 * Returns how many. unique may be keys itself: a run's key is written at or
 * before the place it was read from. */
int64_t pmx_key_runs(int64_t n, const int64_t *keys, int64_t *unique, int32_t *lo, int32_t *hi, int64_t *count) {
    int64_t m = 0;
    for (int64_t i = 0; i < n; i++) {
        if (m && unique[m - 1] == keys[i]) {
            count[m - 1]++;
            continue;
        }
        unique[m] = keys[i];
        lo[m] = (int32_t)(keys[i] >> 32);
        hi[m] = (int32_t)(keys[i] & 0xFFFFFFFF);
        count[m++] = 1;
    }
    return m;
}

/* builders/_build.py _new_vertex_normals before the unit scaling: for each
 * face in order, its doubled-area normal (builders/_quadrics.py face_cross,
 * the same arithmetic) added to each of its corners with an id >= first
 * (out row id - first). out: (k, 3), zero on entry. */
void pmx_new_vertex_normals(int64_t n_faces, const int32_t *faces, const double *pos, int64_t first, double *out) {
    for (int64_t f = 0; f < n_faces; f++) {
        const int32_t *t = faces + 3 * f;
        if (t[0] < first && t[1] < first && t[2] < first) continue;
        const double *p0 = pos + 3 * (int64_t)t[0], *p1 = pos + 3 * (int64_t)t[1], *p2 = pos + 3 * (int64_t)t[2];
        double u[3] = {p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]};
        double v[3] = {p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2]};
        double c[3];
        cross(u, v, c);
        for (int k = 0; k < 3; k++)
            if (t[k] >= first) {
                double *row = out + 3 * (t[k] - first);
                row[0] += c[0];
                row[1] += c[1];
                row[2] += c[2];
            }
    }
}

/* builders/_attributes.py HierarchyAttributes.add_batch, the leaves' climb:
 * each original vertex whose topmost vertex top[leaf] got a parent in this
 * batch (parent >= lo) moves up to it; its distance from the parent's
 * tangent plane, |n . (x_leaf - x_parent)| summed as the NumPy path does
 * (first and third terms, then the second), raises height[parent - lo]
 * (NaN wins, as np.maximum). moving and owner
 * receive the leaves that moved and their new tops, in increasing order of
 * leaf; returns their number. height: (hi - lo), zero on entry. */
int64_t pmx_climb_leaves(int64_t n_leaves, int64_t *top, const int64_t *parent, int64_t lo, const double *pos,
                         const double *normals, int64_t *moving, int64_t *owner, double *height) {
    int64_t m = 0;
    for (int64_t leaf = 0; leaf < n_leaves; leaf++) {
        const int64_t up = parent[top[leaf]];
        if (up < lo) continue;
        top[leaf] = up;
        moving[m] = leaf;
        owner[m] = up;
        m++;
        const double *n = normals + 3 * up, *x = pos + 3 * up, *y = pos + 3 * leaf;
        const double d[3] = {y[0] - x[0], y[1] - x[1], y[2] - x[2]};
        double *h = height + (up - lo);
        *h = np_maximum(*h, fabs(einsum_dot(n, d)));
    }
    return m;
}

/* The batch applied to the faces. The corners of pair i (a[i], b[i]) become
 * first + i (rename: the caller's identity map over all ids, left as it
 * was); a face two of whose corners meet dies, and its killer is the pcol
 * of the vertex they meet in (merged - V0, as builders/_build.py names it);
 * the living faces and their ids are written in order to out_faces and
 * out_fid. quadric rows first + i get the sums of their pairs' rows.
 * Returns how many faces live. */
int64_t pmx_apply_batch(int64_t n_faces, const int32_t *faces, const int64_t *fid, int64_t k, const int32_t *a,
                        const int32_t *b, int64_t first, int32_t *rename, int64_t V0, int32_t *killer,
                        double *quadric, int32_t *out_faces, int64_t *out_fid) {
    for (int64_t i = 0; i < k; i++) {
        rename[a[i]] = rename[b[i]] = (int32_t)(first + i);
        double *q = quadric + 10 * (first + i);
        const double *qa = quadric + 10 * (int64_t)a[i], *qb = quadric + 10 * (int64_t)b[i];
        for (int c = 0; c < 10; c++) q[c] = qa[c] + qb[c];
    }
    int64_t m = 0;
    for (int64_t f = 0; f < n_faces; f++) {
        int32_t c0 = rename[faces[3 * f]], c1 = rename[faces[3 * f + 1]], c2 = rename[faces[3 * f + 2]];
        if (c0 == c1 || c1 == c2 || c0 == c2) {
            int32_t merged = (c0 == c1 || c0 == c2) ? c0 : c1;
            killer[fid[f]] = (int32_t)(merged - V0);
        } else {
            out_faces[3 * m] = c0;
            out_faces[3 * m + 1] = c1;
            out_faces[3 * m + 2] = c2;
            out_fid[m++] = fid[f];
        }
    }
    for (int64_t i = 0; i < k; i++) rename[a[i]] = a[i], rename[b[i]] = b[i];
    return m;
}

/* ---- how far leaves lie off the coarse surface, sideways ---------------- */

/* builders/_attributes.py uncovered_distance, bit for bit: the same
 * operations in NumPy's order (np.cross's products as cross, dot_rows as
 * einsum_dot, np.linalg.norm's (s0 + s1) + s2 as norm3). */
static void sub3(const double *x, const double *y, double *out)
{
    out[0] = x[0] - y[0], out[1] = x[1] - y[1], out[2] = x[2] - y[2];
}

/* pmjax/_distance.py _seg_dist. */
static double segment_distance(const double *p, const double *a, const double *b)
{
    double ab[3], pa[3], q[3], d[3];
    sub3(b, a, ab);
    sub3(p, a, pa);
    const double ll = einsum_dot(ab, ab);
    const double t = np_minimum(np_maximum(einsum_dot(pa, ab) / (ll > 0 ? ll : 1.0), 0.0), 1.0);
    for (int j = 0; j < 3; j++)
        q[j] = a[j] + ab[j] * t;
    sub3(p, q, d);
    return norm3(d);
}

/* pmjax/_distance.py point_triangle_distance. */
static double triangle_distance(const double *p, const double *a, const double *b, const double *c)
{
    double ab[3], ac[3], ap[3], n[3], u[3], v[3];
    sub3(b, a, ab);
    sub3(c, a, ac);
    sub3(p, a, ap);
    cross(ab, ac, n);
    const double nn = einsum_dot(n, n), safe = nn > 0 ? nn : 1.0;
    cross(ap, ac, u);
    cross(ab, ap, v);
    const double w_b = einsum_dot(u, n) / safe, w_c = einsum_dot(v, n) / safe;
    const int inside = (nn > 0) & (w_b >= 0) & (w_c >= 0) & (w_b + w_c <= 1);
    const double plane = fabs(einsum_dot(ap, n)) / sqrt(safe);
    const double border =
        np_minimum(np_minimum(segment_distance(p, a, b), segment_distance(p, a, c)), segment_distance(p, b, c));
    return inside ? plane : border;
}

/* A point relative to origin, its part along the unit normal n removed. */
static void flatten(const double *x, const double *origin, const double *n, double *out)
{
    double rel[3];
    sub3(x, origin, rel);
    const double h = einsum_dot(rel, n);
    for (int j = 0; j < 3; j++)
        out[j] = rel[j] - h * n[j];
}

static int compare_int32(const void *x, const void *y)
{
    const int32_t u = *(const int32_t *)x, v = *(const int32_t *)y;
    return (u > v) - (u < v);
}

/* out[i] for leaf i (original vertex leaves[i], now under owner[i], lo <=
 * owner < hi): an owner without faces in ring (n_ring faces after the
 * batch touching the new vertices) is a point, the whole distance counts;
 * an owner that maybe_border flags and that lies on an open border of
 * ring (an edge to a neighbour in one of its faces only) gives its
 * leaf_on_border leaves their distance to its faces, all flattened onto its
 * tangent plane; else 0. Scratch: start[hi - lo + 1] (int64), slots[3
 * n_ring], around[2 * 3 n_ring] (int32), border[hi - lo] (int8). */
void pmx_uncovered_distance(int64_t n_leaves, const int64_t *leaves, const int64_t *owner,
                            const uint8_t *leaf_on_border, const int32_t *ring, int64_t n_ring, int64_t lo,
                            int64_t hi, const uint8_t *maybe_border, const double *pos, const double *normals,
                            int64_t *start, int32_t *slots, int32_t *around, int8_t *border, double *out)
{
    const int64_t k = hi - lo;
    /* The faces of each new vertex, in ring order (CSR over the corners). */
    memset(start, 0, (size_t)(k + 1) * sizeof *start);
    for (int64_t c = 0; c < 3 * n_ring; c++)
        if (ring[c] >= lo)
            start[ring[c] - lo + 1]++;
    for (int64_t v = 0; v < k; v++)
        start[v + 1] += start[v];
    for (int64_t c = 0; c < 3 * n_ring; c++)
        if (ring[c] >= lo)
            slots[start[ring[c] - lo]++] = (int32_t)c;
    for (int64_t v = k; v > 0; v--)
        start[v] = start[v - 1];
    start[0] = 0;
    memset(border, -1, (size_t)k); /* not known yet */
    for (int64_t i = 0; i < n_leaves; i++) {
        const int64_t o = owner[i] - lo, n_faces = start[o + 1] - start[o];
        const double *x = pos + 3 * owner[i], *y = pos + 3 * leaves[i];
        out[i] = 0.0;
        if (n_faces == 0) { /* a point: the leaf's whole distance to it */
            double d[3];
            sub3(y, x, d);
            out[i] = norm3(d);
            continue;
        }
        if (!maybe_border[o] || !leaf_on_border[i])
            continue;
        if (border[o] < 0) {
            /* On a border: a neighbour that only one of the owner's faces
             * has (every face holding an edge at the owner holds it). */
            int32_t *nb = around;
            for (int64_t s = start[o]; s < start[o + 1]; s++) {
                const int64_t c = slots[s], f = c / 3, at = c % 3;
                *nb++ = ring[3 * f + (at + 1) % 3];
                *nb++ = ring[3 * f + (at + 2) % 3];
            }
            const int64_t m = nb - around;
            qsort(around, (size_t)m, sizeof *around, compare_int32);
            border[o] = 0;
            for (int64_t s = 0; s < m;) {
                int64_t e = s;
                while (e < m && around[e] == around[s])
                    e++;
                if (e - s == 1)
                    border[o] = 1;
                s = e;
            }
        }
        if (!border[o])
            continue;
        /* The leaf against each of the owner's faces on its tangent plane. */
        const double *n = normals + 3 * owner[i];
        double p[3], a[3], b[3], c[3], best = INFINITY;
        flatten(y, x, n, p);
        for (int64_t s = start[o]; s < start[o + 1]; s++) {
            const int32_t *face = ring + 3 * (slots[s] / 3);
            flatten(pos + 3 * (int64_t)face[0], x, n, a);
            flatten(pos + 3 * (int64_t)face[1], x, n, b);
            flatten(pos + 3 * (int64_t)face[2], x, n, c);
            best = np_minimum(best, triangle_distance(p, a, b, c));
        }
        out[i] = best;
    }
}

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_build_native",
                                    "The builder's per-batch C loops (called through ctypes).", -1, NULL};

PyMODINIT_FUNC PyInit__build_native(void) { return PyModule_Create(&module); }

