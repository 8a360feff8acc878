/* The output-sensitive traversal of one camera, and of camera batches.
 *
 * From the roots, breadth first, each visited pcol is decided (its own
 * certified decision, and the bound over the pcols strictly below it) a
 * block of BLOCK slots at a time; the children of a slot whose bound did not
 * decide everything below it are pushed behind the queue. Then, bottom-up, a
 * slot ran if it collapses and both children ran (a child not visited lies
 * under a decided bound: it ran). Every pcol not visited ran, so the visited
 * slots and their ran bits are the whole refinement, and the work follows
 * the refined mesh, not the hierarchy. */
#include <stdlib.h>

#include "internal.h"

/* Slot i holds position ids[i] with its own decision state[i] and the faces
 * it kills kill[i]; kid[2i], kid[2i+1] are the slots of its children (-1:
 * not visited). Returns the number of slots, or -1 if the queue would pass
 * the table (a hierarchy whose links are not a forest). unsure[] receives
 * the slots whose own decision is UNSURE (in slot order), *n_unsure their
 * number, and parent[] (optional) each slot's parent slot from slot n_roots
 * on. Capacity: n_pcols + PMX_SPARE slots (ids, kid pairs, parent). */
int64_t traverse(const Kernels *kern, const PmxHierarchy *h, const Frames *w, int32_t *ids, int32_t *kid,
                 uint8_t *state, int32_t *kill, int32_t *parent, int32_t *unsure, int64_t *n_unsure)
{
    int64_t n = 0, m = 0;
    Columns col;
    int32_t decided[BLOCK];
    for (int64_t i = 0; i < h->n_roots; i++)
        ids[n++] = (int32_t)i;
    void (*decide)(const Frames *, Columns, int32_t *) = w->ortho ? kern->decide_orthographic : kern->decide_perspective;
    for (int64_t i = 0; i < n;) {
        const int64_t nb = n - i < BLOCK ? n - i : BLOCK;
        /* The rows a few blocks ahead in the queue, so that they arrive in
         * time without more requests in flight than the memory system holds. */
        for (int64_t j = i + AHEAD; j < i + AHEAD + nb && j < n; j++)
            __builtin_prefetch(h->rows + (int64_t)ids[j] * ROW);
        gather_block(kern, h->rows, ids + i, nb, col);
        decide(w, col, decided);
        n = kern->push_block(h, i, nb, n, decided, col[KIDS], state, kill, kid, ids, parent, unsure, &m);
        /* Each position is visited at most once in a forest: more slots
         * than pcols means links that are not one (checked, not trusted);
         * -1: the block found so before storing its children. */
        if (n < 0 || n > h->n_pcols)
            return -1;
        i += nb;
    }
    *n_unsure = m;
    return n;
}

PmxStatus pmx_check_hierarchy(const PmxHierarchy *h)
{
    if (h->n_pcols < 0 || h->n_pcols > PMX_MAX_PCOLS || h->n_roots < 0 || h->n_roots > h->n_pcols ||
        (h->n_pcols > 0 && h->n_roots == 0))
        return PMX_BAD_SIZE;
    /* Breadth first: the children of the positions before q fill the
     * positions from n_roots on, in order, each once. */
    int64_t next = h->n_roots;
    for (int64_t q = 0; q < h->n_pcols; q++) {
        int32_t kids;
        memcpy(&kids, h->rows + q * ROW + KIDS, sizeof kids);
        const int64_t count = kids & 3;
        if (count > 2 || (count > 0 && kids_first(kids) != next))
            return PMX_BAD_TABLE;
        next += count;
        if (next > h->n_pcols || h->order[q] < 0 || h->order[q] >= h->n_pcols || h->kills[q] < 0 ||
            (kids < 0) != (h->kills[q] != 2))
            return PMX_BAD_TABLE;
    }
    return next == h->n_pcols ? PMX_OK : PMX_BAD_TABLE;
}

/* The unsure slots answered: answered[] holds positions in increasing order,
 * as the unsure slots come (a pruned breadth-first walk visits positions in
 * increasing order), so one cursor pairs them. Those not answered keep
 * UNSURE (read as "keep" by the bottom-up pass) and their positions go to
 * left[] (if given). Returns their number. */
static int64_t answer_unsure(const int32_t *ids, uint8_t *state, const int32_t *unsure, int64_t m,
                             const int32_t *answered, const int32_t *answers, int64_t n_answered, int32_t *left)
{
    int64_t n_left = 0, c = 0;
    for (int64_t q = 0; q < m; q++) {
        const int32_t slot = unsure[q], at = ids[slot];
        while (c < n_answered && answered[c] < at)
            c++;
        if (c < n_answered && answered[c] == at) {
            state[slot] = answers[c] ? YES : NO;
        } else {
            if (left)
                left[n_left] = at;
            n_left++;
        }
    }
    return n_left;
}

PmxStatus pmx_refine_one(const PmxHierarchy *h, const float *view, int flags, int level, const int32_t *answered,
                         const int32_t *answers, int64_t n_answered, PmxLists lists, int32_t *unsure,
                         PmxCounts *counts, int *level_used, PmxScratch *s)
{
    if (!scratch_slots(s))
        return PMX_NO_MEMORY;
    const unsigned mode = subnormals_off();
    const Kernels *kern = pmx_kernels_at(level, level_used);
    Frames w;
    load_frames(&w, view, 1, flags);
    /* The positions and ran bytes straight into the caller's lists. */
    int32_t *ids = lists.positions ? lists.positions : s->ids;
    uint8_t *ran = lists.ran ? lists.ran : s->ran;
    int64_t m = 0;
    const int64_t n = traverse(kern, h, &w, ids, s->kid, s->state, s->kill, NULL, s->unsure, &m);
    if (n < 0) {
        subnormals_back(mode);
        return PMX_BAD_TABLE;
    }
    counts->visited = (int32_t)n;
    counts->unsure = m ? (int32_t)answer_unsure(ids, s->state, s->unsure, m, answered, answers, n_answered, unsure) : 0;
    int64_t not_run = 0, kept = 0;
    kern->resolve(h, n, ids, s->kid, s->state, s->kill, ran, lists.pcols, &not_run, &kept);
    counts->not_run = (int32_t)not_run, counts->kept = (int32_t)kept;
    subnormals_back(mode);
    return PMX_OK;
}

/* ---- camera batches ------------------------------------------------------ */

/* A batch shared by its threads: the cameras in Morton order, taken one at a
 * time from a cursor (the threads finish together however the cameras'
 * costs differ). */
typedef struct {
    const PmxHierarchy *h;
    const float *views;
    int flags;
    const int64_t *order;
    int64_t K, cursor;
    PmxCounts *counts;
    uint8_t *masks, *overflow;
    PmxLists lists;
    PmxRecords *records;
    PmxStatus status;
} Batch;

static void batch_work(void *arg)
{
    Batch *b = arg;
    const PmxHierarchy *h = b->h;
    const int64_t P = h->n_pcols, stride = P + PMX_SPARE;
    PmxScratch *s = pmx_scratch_take(P);
    if (!s || !scratch_slots(s)) {
        __atomic_store_n(&b->status, PMX_NO_MEMORY, __ATOMIC_RELAXED);
        if (s)
            pmx_scratch_give(s);
        return;
    }
    const unsigned mode = subnormals_off();
    const Kernels *kern = pmx_kernels();
    for (int64_t c; (c = __atomic_fetch_add(&b->cursor, 1, __ATOMIC_RELAXED)) < b->K;) {
        const int64_t k = b->order[c];
        Frames w;
        load_frames(&w, b->views + PMX_VIEW * k, 1, b->flags);
        int32_t *ids = b->lists.positions ? b->lists.positions + k * stride : s->ids;
        uint8_t *ran = b->lists.ran ? b->lists.ran + k * stride : s->ran;
        int32_t *pcols = b->lists.pcols ? b->lists.pcols + k * stride : (b->masks ? s->pcols : NULL);
        int64_t m = 0;
        const int64_t n = traverse(kern, h, &w, ids, s->kid, s->state, s->kill, s->parent, s->unsure, &m);
        if (n < 0) {
            __atomic_store_n(&b->status, PMX_BAD_TABLE, __ATOMIC_RELAXED);
            break;
        }
        /* An unsure slot's state is UNSURE, which resolve reads as "keep". */
        int64_t not_run = 0, kept = 0;
        kern->resolve(h, n, ids, s->kid, s->state, s->kill, ran, pcols, &not_run, &kept);
        b->counts[k] = (PmxCounts){(int32_t)n, (int32_t)not_run, (int32_t)kept, (int32_t)m};
        b->overflow[k] = 0;
        if (m > 0) {
            const int64_t count = record_chain(n, h->n_roots, s->kid, s->unsure, m, s->parent, 1, s->chain, s->mark);
            const int64_t at = records_reserve(b->records, 2 + count * PMX_NODE);
            if (at < 0) {
                b->overflow[k] = 1;
            } else {
                const SlotBits bits = {NULL, NULL, NULL, NULL, NULL, s->state, ran};
                record_write(b->records->records + at, k, count, s->chain, ids, s->kid, &bits, h->kills, s->unsure,
                             m);
            }
        }
        if (b->masks) {
            uint8_t *row = b->masks + k * P;
            memset(row, 1, (size_t)P);
            for (int64_t i = 0; i < n; i++)
                if (!ran[i])
                    row[pcols[i]] = 0;
        }
    }
    subnormals_back(mode);
    pmx_scratch_give(s);
}

/* The order of K eyes (views [K, PMX_VIEW]) in which consecutive ones are
 * close: their Morton (Z-order) codes in the eyes' bounding box, 10 bits per
 * axis, sorted stably. Cameras that see the model from nearby share most of
 * their front, so running them one after another keeps it in cache. */
typedef struct {
    uint64_t code;
    int64_t index;
} Coded;

static int by_code(const void *a, const void *b)
{
    const Coded *x = a, *y = b;
    if (x->code != y->code)
        return x->code < y->code ? -1 : 1;
    return (x->index > y->index) - (x->index < y->index);
}

static int nearby_order(const float *views, int64_t K, int64_t *order)
{
    Coded *coded = malloc(sizeof(Coded) * (size_t)(K > 0 ? K : 1));
    if (!coded)
        return 0;
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (int64_t k = 0; k < K; k++)
        for (int a = 0; a < 3; a++) {
            const double e = views[PMX_VIEW * k + EYE + a];
            lo[a] = e < lo[a] ? e : lo[a];
            hi[a] = e > hi[a] ? e : hi[a];
        }
    for (int64_t k = 0; k < K; k++) {
        uint64_t code = 0;
        for (int a = 0; a < 3; a++) {
            const double span = hi[a] > lo[a] ? hi[a] - lo[a] : 1.0;
            double x = (views[PMX_VIEW * k + EYE + a] - lo[a]) / span * 1023.0;
            const uint64_t cell = x >= 0 && x <= 1023 ? (uint64_t)x : 0; /* NaN and inf: cell 0 */
            for (int bit = 0; bit < 10; bit++)
                code |= ((cell >> bit) & 1) << (3 * bit + a);
        }
        coded[k].code = code, coded[k].index = k;
    }
    qsort(coded, (size_t)K, sizeof(Coded), by_code);
    for (int64_t k = 0; k < K; k++)
        order[k] = coded[k].index;
    free(coded);
    return 1;
}

PmxStatus pmx_refine_many(const PmxHierarchy *h, const float *views, int64_t K, int flags, PmxCounts *counts,
                          uint8_t *masks, PmxLists lists, PmxRecords *records, uint8_t *overflow,
                          const PmxRunner *run)
{
    int64_t *order = malloc(sizeof(int64_t) * (size_t)(K > 0 ? K : 1));
    if (!order || !nearby_order(views, K, order)) {
        free(order);
        return PMX_NO_MEMORY;
    }
    Batch b = {h, views, flags, order, K, 0, counts, masks, overflow, lists, records, PMX_OK};
    run_shared(run, batch_work, &b);
    free(order);
    return b.status;
}
