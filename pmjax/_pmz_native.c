/* Decoding of a version 2 .pmz file's chunks (docs/format.md), as plain C
 * loops: a batch chunk in one pass (unplaning, the checks, leaf ranges,
 * positions from parents, encoding 2's predictions) and its face ranks and
 * killers in a second (which may run beside the next chunks' first), the
 * faces in file order from the groups, the area-weighted normals, and float
 * residuals.
 *
 * Each loop is a NumPy step of pmjax/_codec.py with its arithmetic in the
 * same order (no contraction), so a read with these loops gives the NumPy
 * read's arrays bit for bit (tests/test_pmz_native.py). The checks are the
 * NumPy reader's, in its order; a failed one returns its code (and the
 * offending index in info[0]) and pmjax/_codec.py words the message. The
 * caller's arrays may be left half written then: the read is abandoned.
 * Every pointer is a C-contiguous array of the dtype named.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <string.h>

/* The digest of the text this library was built from (setup.py defines it),
 * which pmjax compares with the source beside the library to catch a stale
 * build (pmjax/_clib.py). */
#ifndef PMJAX_SOURCE_DIGEST
#define PMJAX_SOURCE_DIGEST ""
#endif
const char *pmjax_source_digest(void);
const char *pmjax_source_digest(void) { return PMJAX_SOURCE_DIGEST; }

/* Rows that the loops below read or write by a child's, parent's or rank's
 * id are scattered over arrays larger than the caches: each loop asks for
 * the rows of the element AHEAD places on while it works on this one. */
#define AHEAD 16
#if defined(__GNUC__)
#define PREFETCH(p) __builtin_prefetch(p)
#else
#define PREFETCH(p) ((void)0)
#endif

/* Outcomes of pmz_read_batch and pmz_batch_faces (pmjax/_codec.py words each). */
enum { OK = 0, SHORT = 1, BAD_V1 = 2, BAD_V2 = 3, CHILD_SEEN = 4, PARENT_UNSEEN = 5, BAD_COUNTS = 6,
       LEFT_OVER = 7, BAD_RANK = 8 };

/* Element i of a byte-planed array of n 4-byte elements: its bytes in
 * memory order (any host byte order). */
static uint32_t get32(const uint8_t *src, int64_t n, int64_t i) {
    uint8_t b[4] = {src[i], src[n + i], src[2 * n + i], src[3 * n + i]};
    uint32_t u;
    memcpy(&u, b, 4);
    return u;
}

static void unplane(const uint8_t *src, int64_t n, int64_t size, uint8_t *out) {
    /* Output written in order, one byte plane read per byte of an element. */
    if (size == 1) {
        memcpy(out, src, (size_t)n);
    } else if (size == 4) {
        for (int64_t i = 0; i < n; i++) {
            out[4 * i] = src[i];
            out[4 * i + 1] = src[n + i];
            out[4 * i + 2] = src[2 * n + i];
            out[4 * i + 3] = src[3 * n + i];
        }
    } else {
        for (int64_t i = 0; i < n; i++)
            for (int64_t k = 0; k < size; k++) out[size * i + k] = src[k * n + i];
    }
}

/* Inverse of _codec.planes: n elements of size bytes. */
void pmz_unplane(const uint8_t *src, int64_t n, int64_t size, uint8_t *out) { unplane(src, n, size, out); }

static uint32_t unzigzag(uint32_t z) { return (z >> 1) ^ (0u - (z & 1u)); }

/* float32 bits -> order-preserving uint32 image, and back (_codec.ordered). */
static uint32_t ordered(uint32_t b) { return b ^ ((0u - (b >> 31)) | 0x80000000u); }
static uint32_t unordered(uint32_t u) { return u ^ (((u >> 31) - 1u) | 0x80000000u); }

static uint32_t float_bits(float x) {
    uint32_t u;
    memcpy(&u, &x, 4);
    return u;
}

static float bits_float(uint32_t u) {
    float x;
    memcpy(&x, &u, 4);
    return x;
}

/* One float32 from its uint32 residual against a prediction. */
static float from_residual(uint32_t residual, float prediction) {
    return bits_float(unordered(unzigzag(residual) + ordered(float_bits(prediction))));
}

/* _codec.float_from_residual: n float32 from uint32 residuals against predictions. */
void pmz_float_from_residual(int64_t n, const uint32_t *residual, const float *prediction, float *out) {
    for (int64_t i = 0; i < n; i++)
        out[i] = from_residual(residual[i], prediction[i]);
}

/* _codec.unit_from_residual for one vector: the two components other than
 * the guide's largest (first of equal magnitudes; never a NaN) against the
 * guide's, then the largest against the unit length of those two, float64
 * arithmetic in _codec._unit_component's order. r(k) is the residual of
 * component k. */
#define UNIT_FROM_RESIDUAL(r, guide, out)                                                                 \
    do {                                                                                              \
        float g0 = fabsf((guide)[0]), g1 = fabsf((guide)[1]), g2 = fabsf((guide)[2]);                   \
        int k = g1 > g0 ? 1 : 0;                                                                      \
        if (g2 > (k ? g1 : g0)) k = 2;                                                                \
        int j1 = (k + 1) % 3, j2 = (k + 2) % 3;                                                       \
        (out)[j1] = from_residual(r(j1), (guide)[j1]);                                                \
        (out)[j2] = from_residual(r(j2), (guide)[j2]);                                                \
        double x1 = (double)(out)[j1], x2 = (double)(out)[j2];                                        \
        double sq = 1.0 - (x1 * x1 + x2 * x2);                                                        \
        float pk = copysignf((float)(sq > 0 ? sqrt(sq) : 0.0), (guide)[k]);                           \
        (out)[k] = from_residual(r(k), pk);                                                           \
    } while (0)

/* _codec.unit_from_residual: m unit vectors from uint32 residuals [m, 3]
 * against guides float32 [m, 3]. */
void pmz_unit_from_residual(int64_t m, const uint32_t *residual, const float *guide, float *out) {
    for (int64_t i = 0; i < m; i++) {
#define ROW(k) residual[3 * i + (k)]
        UNIT_FROM_RESIDUAL(ROW, guide + 3 * i, out + 3 * i);
#undef ROW
    }
}

/* pmz_float_from_residual with the residuals still byte-planed (uint32
 * planes of n elements): the unplaning folded into the decoding pass. */
void pmz_float_from_planed(int64_t n, const uint8_t *planed, const float *prediction, float *out) {
    for (int64_t i = 0; i < n; i++) out[i] = from_residual(get32(planed, n, i), prediction[i]);
}

/* pmz_unit_from_residual with the residuals [m, 3] still byte-planed. */
void pmz_unit_from_planed(int64_t m, const uint8_t *planed, const float *guide, float *out) {
    for (int64_t i = 0; i < m; i++) {
#define ROW(k) get32(planed, 3 * m, 3 * i + (k))
        UNIT_FROM_RESIDUAL(ROW, guide + 3 * i, out + 3 * i);
#undef ROW
    }
}

/* Element i of a byte-planed array of n 8-byte elements. */
static uint64_t get64(const uint8_t *src, int64_t n, int64_t i) {
    uint8_t b[8];
    for (int k = 0; k < 8; k++) b[k] = src[k * n + i];
    uint64_t u;
    memcpy(&u, b, 8);
    return u;
}

/* What the reader knows of a vertex's place in the collapse forest
 * (_codec.RANGE_DTYPE): its leaf range, its parent (-1 for roots) and
 * whether it is a vertex of the mesh read so far. One record per vertex, so
 * that the first pass touches one scattered line per child, not four. */
typedef struct {
    int32_t start, count, parent, seen;
} Range;

/* Batch chunk of pcols lo .. hi-1 (ids V0+lo .. V0+hi-1) into the reader's
 * state (_codec.read_batch), arrays stored in encoding 1 or 2: range[V]
 * (Range), vertices and normals float32[V, 3], v1 .. metric at [lo, hi);
 * the chunk's size is checked whole, its face ranks left to
 * pmz_batch_faces. */
int64_t pmz_read_batch(const uint8_t *raw, int64_t len, int64_t V0, int64_t lo, int64_t hi, int64_t n_faces,
                       int64_t encoding, Range *range, float *vertices, float *normals, int32_t *v1, int32_t *v2,
                       float *radius, float *alpha, float *delta, float *mu, double *cost, uint8_t *metric,
                       int64_t *info) {
    const int64_t n = hi - lo, first = V0 + lo;
    int32_t *a = v1 + lo, *d = v2 + lo;
    /* The children and the count under v1, checked in the NumPy reader's
     * order. A failed check abandons the read, so the children's ranges may
     * be written while their marks are checked: the checks after that read
     * only the parents' records (ids of this batch, above every child). */
    if (len < 12 * n) return SHORT;
    unplane(raw, n, 4, (uint8_t *)a);
    unplane(raw + 4 * n, n, 4, (uint8_t *)d);
    const uint8_t *c1_planes = raw + 8 * n;
    for (int64_t i = 0; i < n; i++)
        if (a[i] < 0 || a[i] >= first) return info[0] = lo + i, BAD_V1;
    for (int64_t i = 0; i < n; i++)
        if (d[i] < 0 || d[i] >= first) return info[0] = lo + i, BAD_V2;
    /* A child seen before, or twice in this batch (marked seen while
     * checking, in one pass: v1 then v2 of each pcol in order), is an error
     * naming that pcol; the children split their parent's leaf range
     * (counts checked below). */
    for (int64_t i = 0; i < n; i++) {
        if (i + AHEAD < n) {
            PREFETCH(range + a[i + AHEAD]);
            PREFETCH(range + d[i + AHEAD]);
        }
        const Range *ru = range + first + i;
        Range *ra = range + a[i], *rd = range + d[i];
        if (ra->seen) return info[0] = lo + i, CHILD_SEEN;
        ra->seen = 1;
        if (rd->seen) return info[0] = lo + i, CHILD_SEEN;
        rd->seen = 1;
        const int32_t c1 = (int32_t)get32(c1_planes, n, i);
        ra->count = c1;
        rd->count = (int32_t)((uint32_t)ru->count - (uint32_t)c1);
        ra->start = ru->start;
        rd->start = (int32_t)((uint32_t)ru->start + (uint32_t)c1);
        ra->parent = rd->parent = (int32_t)(first + i);
    }
    for (int64_t i = 0; i < n; i++)
        if (!range[first + i].seen) return info[0] = lo + i, PARENT_UNSEEN;
    int64_t made = 0;
    for (int64_t i = 0; i < n; i++) {
        int64_t c1 = (int32_t)get32(c1_planes, n, i), c2 = range[first + i].count - c1;
        if (c1 < 1 || c2 < 1 || (a[i] < V0 && c1 != 1) || (d[i] < V0 && c2 != 1))
            return info[0] = lo + i, BAD_COUNTS;
        made += (a[i] >= V0) + (d[i] >= V0);
    }
    /* The chunk holds exactly the arrays these counts give (as
     * _codec.batch_bytes computes them). */
    const int64_t need = n * (12 + 16 + 8 + 1 + 24) + made * 12 + n_faces * 12;
    if (len < need) return SHORT;
    if (len > need) return info[0] = len - need, LEFT_OVER;
    /* The parents are split: no longer vertices of the mesh read. */
    for (int64_t i = 0; i < n; i++) range[first + i].seen = 0;
    /* The attributes: as stored (encoding 1), or the radius and half-angle
     * against their parent's less the distance and angle between them, and
     * the costs against the previous pcol's (_codec.cost_decode). */
    const uint8_t *at = raw + 12 * n;
    if (encoding == 1) {
        unplane(at, n, 4, (uint8_t *)(radius + lo));
        unplane(at + 4 * n, n, 4, (uint8_t *)(alpha + lo));
        unplane(at + 16 * n, n, 8, (uint8_t *)(cost + lo));
    } else {
        /* _codec.radius_prediction and _codec.alpha_prediction. */
        for (int64_t i = 0; i < n; i++) {
            int64_t u = first + i, w = range[u].parent;
            if (i + AHEAD < n && range[u + AHEAD].parent >= 0) {
                int64_t ahead = range[u + AHEAD].parent;
                PREFETCH(vertices + 3 * ahead);
                PREFETCH(normals + 3 * ahead);
                PREFETCH(radius + ahead - V0);
                PREFETCH(alpha + ahead - V0);
            }
            float pr = 0.0f, pa = 0.0f;
            if (w >= 0) {
                const float *x = vertices + 3 * u, *y = vertices + 3 * w;
                double dx = (double)y[0] - (double)x[0], dy = (double)y[1] - (double)x[1],
                       dz = (double)y[2] - (double)x[2];
                double q = (double)radius[w - V0] - sqrt((dx * dx + dy * dy) + dz * dz);
                pr = q > 0 ? (float)q : 0.0f;
                x = normals + 3 * u, y = normals + 3 * w;
                dx = (double)y[0] - (double)x[0], dy = (double)y[1] - (double)x[1], dz = (double)y[2] - (double)x[2];
                double c = sqrt((dx * dx + dy * dy) + dz * dz);
                q = (double)alpha[w - V0] - (c + c * c * c / 24.0);
                pa = q > 0 ? (float)q : 0.0f;
            }
            radius[lo + i] = from_residual(get32(at, n, i), pr);
            alpha[lo + i] = from_residual(get32(at + 4 * n, n, i), pa);
        }
        uint64_t prev = 0;
        for (int64_t i = 0; i < n; i++) {
            uint64_t z = get64(at + 16 * n, n, i);
            prev += (z >> 1) ^ (0u - (z & 1u));
            uint64_t b = prev ^ (((prev >> 63) - 1u) | 0x8000000000000000ull);
            memcpy(cost + lo + i, &b, 8);
        }
    }
    unplane(at + 8 * n, n, 4, (uint8_t *)(delta + lo));
    unplane(at + 12 * n, n, 4, (uint8_t *)(mu + lo));
    unplane(at + 24 * n, n, 1, metric + lo);
    at += 25 * n;
    /* Children's positions from residuals against their parent's. */
    for (int side = 0; side < 2; side++) {
        const int32_t *child = side ? d : a;
        for (int64_t i = 0; i < n; i++)
            for (int k = 0; k < 3; k++) {
                if (k == 0 && i + AHEAD < n) PREFETCH(vertices + 3 * (int64_t)child[i + AHEAD]);
                vertices[3 * (int64_t)child[i] + k] = from_residual(get32(at, 3 * n, 3 * i + k), vertices[3 * (first + i) + k]);
            }
        at += 12 * n;
    }
    /* Normals of the children made by pcols, v1 children then v2 children:
     * as stored (encoding 1), or against their parent's (encoding 2). */
    for (int side = 0; side < 2; side++) {
        const int32_t *child = side ? d : a;
        int64_t m = 0;
        for (int64_t i = 0; i < n; i++) m += child[i] >= V0;
        for (int64_t i = 0, j = 0; i < n; i++) {
            if (i + AHEAD < n) PREFETCH(normals + 3 * (int64_t)child[i + AHEAD]);
            if (child[i] < V0) continue;
            float *out = normals + 3 * (int64_t)child[i];
            if (encoding == 1) {
                for (int k = 0; k < 3; k++) out[k] = bits_float(get32(at, 3 * m, 3 * j + k));
            } else {
#define STORED(k) get32(at, 3 * m, 3 * j + (k))
                UNIT_FROM_RESIDUAL(STORED, normals + 3 * (first + i), out);
#undef STORED
            }
            j++;
        }
        at += 12 * m;
    }
    return OK;
}

/* The face ranks and killers of the batch of pcols lo .. hi-1, from the
 * byte-planed face codes that end its chunk (sizes checked by
 * pmz_read_batch): ranks int32[n_faces, 3], killers int32[n_faces]. It
 * reads only the start and count of the batch's own vertices, which no
 * finer batch changes, so it may run beside the decoding of the next
 * chunks; owner int32[V0] is scratch kept across the batches of a read (no
 * entry in [lo, hi) before the call), so one batch's call at a time. */
int64_t pmz_batch_faces(const uint8_t *at, int64_t n_faces, int64_t V0, int64_t lo, int64_t hi, const Range *range,
                        int32_t *ranks, int32_t *killer, int32_t *owner) {
    const int64_t n = hi - lo, first = V0 + lo;
    /* Face code -> corner ranks, each within [0, V0) (so int32). */
    int64_t r0 = 0;
    for (int64_t f = 0; f < n_faces; f++) {
        r0 += (int32_t)unzigzag(get32(at, 3 * n_faces, 3 * f));
        int64_t r1 = r0 + (int32_t)unzigzag(get32(at, 3 * n_faces, 3 * f + 1));
        int64_t r2 = r0 + (int32_t)unzigzag(get32(at, 3 * n_faces, 3 * f + 2));
        if (r0 < 0 || r0 >= V0 || r1 < 0 || r1 >= V0 || r2 < 0 || r2 >= V0) return BAD_RANK;
        ranks[3 * f] = (int32_t)r0;
        ranks[3 * f + 1] = (int32_t)r1;
        ranks[3 * f + 2] = (int32_t)r2;
    }
    /* Killers: per corner the pcol whose range holds it (the batch's ranges
     * are disjoint: each rank of a range is stamped with its pcol, and an
     * entry of another batch is no pcol of this one), then the pcol holding
     * two corners, else -1. */
    for (int64_t i = 0; i < n; i++)
        for (int64_t r = range[first + i].start, end = r + range[first + i].count; r < end; r++)
            owner[r] = (int32_t)(lo + i);
    for (int64_t f = 0; f < n_faces; f++) {
        int64_t cand[3];
        if (f + AHEAD < n_faces)
            for (int k = 0; k < 3; k++) PREFETCH(owner + ranks[3 * (f + AHEAD) + k]);
        for (int k = 0; k < 3; k++) {
            int64_t o = owner[ranks[3 * f + k]];
            cand[k] = o >= lo && o < hi ? o : -1;
        }
        killer[f] = (int32_t)(cand[0] >= 0 && (cand[0] == cand[1] || cand[0] == cand[2]) ? cand[0]
                              : cand[1] >= 0 && cand[1] == cand[2]                       ? cand[1]
                                                                                         : -1);
    }
    return OK;
}

/* Faces f0 .. f1-1 and their killers in file order (_codec.finish_full):
 * face f is the next face of its group (groups read base first, then
 * batches B-1 .. 0), its corners the original vertices at its ranks.
 * cursor[i] holds the faces of read group i before f0 (so that two calls
 * may place two spans at once) and is advanced past f1. The groups' sizes
 * were checked against the chunks'. */
void pmz_place_faces(int64_t f0, int64_t f1, int64_t B, const void *group, int64_t group_size,
                     const int32_t *const *ranks, const int32_t *const *killers, const int32_t *orig_of_rank,
                     int64_t *cursor, int32_t *faces, int32_t *killer) {
    for (int64_t f = f0; f < f1; f++) {
        int64_t g = group_size == 1 ? ((const uint8_t *)group)[f]
                    : group_size == 2 ? ((const uint16_t *)group)[f]
                                      : ((const uint32_t *)group)[f];
        int64_t i = B - g, j = cursor[i]++;
        const int32_t *r = ranks[i] + 3 * j;
        faces[3 * f] = orig_of_rank[r[0]];
        faces[3 * f + 1] = orig_of_rank[r[1]];
        faces[3 * f + 2] = orig_of_rank[r[2]];
        killer[f] = killers[i][j];
    }
}

/* _codec.area_normals: unit area-weighted normals of n vertices, float64
 * cross products summed per vertex in face order (total: double[n, 3],
 * scratch), zero where the sum has no length. */
void pmz_area_normals(int64_t n_faces, const int32_t *faces, const float *vertices, int64_t n, double *total,
                      float *out) {
    memset(total, 0, (size_t)n * 3 * sizeof(double));
    for (int64_t f = 0; f < n_faces; f++) {
        const float *p = vertices + 3 * (int64_t)faces[3 * f], *q = vertices + 3 * (int64_t)faces[3 * f + 1],
                    *s = vertices + 3 * (int64_t)faces[3 * f + 2];
        double ax = (double)q[0] - (double)p[0], ay = (double)q[1] - (double)p[1], az = (double)q[2] - (double)p[2];
        double bx = (double)s[0] - (double)p[0], by = (double)s[1] - (double)p[1], bz = (double)s[2] - (double)p[2];
        double cx = ay * bz - az * by, cy = az * bx - ax * bz, cz = ax * by - ay * bx;
        for (int k = 0; k < 3; k++) {
            double *t = total + 3 * (int64_t)faces[3 * f + k];
            t[0] += cx;
            t[1] += cy;
            t[2] += cz;
        }
    }
    for (int64_t v = 0; v < n; v++) {
        const double *t = total + 3 * v;
        double length = sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2]);
        double scale = length > 0 ? length : 1.0;
        for (int k = 0; k < 3; k++) out[3 * v + k] = (float)(t[k] / scale);
    }
}

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_pmz_native",
                                    "The .pmz version 2 decoder's C loops (called through ctypes).", -1, NULL};

PyMODINIT_FUNC PyInit__pmz_native(void) { return PyModule_Create(&module); }
