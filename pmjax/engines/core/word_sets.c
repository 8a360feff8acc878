/* Word sets: one word's frames at several tolerances traversed together.
 *
 * A face budget's exact counts along a path count each frame at a few
 * tolerances (a guess and the pattern below it, for each budget). A set of
 * words that hold the same frames and differ only in their tolerances is
 * traversed once: each slot is visited for the frames of every set that
 * reaches it, its row read and its fat camera decision made once for all
 * the sets (the fat camera's kappa2 range spans every set's frames), and
 * only the frames' own decisions are made set by set, less those another
 * set's sure decisions imply (the screen test is monotone in kappa2, the
 * other tests do not depend on it). Each set keeps its own bits (visit,
 * whole, yes, unsure), and its counts of faces and pcols run, once its
 * unsure pairs are decided, are those of pmx_refine_words on its word alone:
 * a slot that a set does not visit ran for all its frames, as a slot decided
 * above it does in the word alone. Its visited slots and unsure pairs may
 * differ from the word alone's: another set's sure decisions settle some of
 * its unsure pairs, and where they settle every frame of a slot as a
 * collapse, the set's own decision (whose "whole" would have stopped the walk
 * there) is not made and the set walks on below it. */
#include <stdlib.h>

#include "internal.h"

/* Sets a word is traversed with at most. */
#define MOST_SETS PMX_MOST_SETS

/* Whether the words at views a and b (FRAMES frames each) differ only in
 * their frames' tolerances (kappa2), bit for bit. */
static int same_but_tolerance(const float *a, const float *b)
{
    for (int64_t i = 0; i < (int64_t)FRAMES * PMX_VIEW; i++)
        if (i % PMX_VIEW != KAPPA2 && memcmp(a + i, b + i, sizeof(float)) != 0)
            return 0;
    return 1;
}

/* Per-set bits of a traversal, set by set (set t's slot i at t * room + i). */
typedef struct {
    Lanes *visit, *whole, *yes, *ran, *unsure_lanes;
    int32_t *unsure;  /* set t's unsure slots from unsure + t * room */
    int64_t room, sets; /* slots and sets held */
} SetBits;

/* The T words at views (T * FRAMES views, set by set; fat: the fat camera
 * of set 0's frames, or NULL) traversed together. Returns the number of
 * slots (-1: links that are not a forest); n_unsure[t], at_once[t] as
 * traverse_word's for set t. */
static inline __attribute__((always_inline)) int64_t traverse_sets(const Kernels *kern, const PmxHierarchy *h, const float *views, int T, int flags,
                             const float *fat, int32_t *ids, int32_t *kid, SetBits *sb, int64_t room,
                             int64_t *n_unsure, int64_t *at_once, int64_t *visited)
{
    if (T < 1 || T > MOST_SETS)
        return -1;
    Frames fr[MOST_SETS];
    int use_fat = fat != NULL;
    for (int t = 0; t < T; t++) {
        load_frames(&fr[t], views + (int64_t)t * FRAMES * PMX_VIEW, FRAMES, flags);
        use_fat &= fat_applies(&fr[t], fat, FRAMES);
        n_unsure[t] = at_once[t] = visited[t] = 0;
    }
    /* One fat camera for every set: the sets' frames share everything but
     * kappa2 (and kabs, which grows with it), so their ranges widen. */
    Fat W;
    if (use_fat) {
        load_fat(&W, fat, &fr[0], FRAMES);
        for (int t = 1; t < T; t++)
            for (int l = 0; l < FRAMES; l++) {
                W.kappa2 = fminf(W.kappa2, fr[t].kappa2[l]), W.kappa2_hi = fmaxf(W.kappa2_hi, fr[t].kappa2[l]);
                W.kabs = fmaxf(W.kabs, fr[t].kabs[l]);
            }
    }
    /* The sets are decided in order; a caller lists the finest first:
     * near the front, where the fat camera leaves slots open, most
     * decisions are collapses, which a finer set's imply for the coarser
     * ones. Per pair of sets (u before t), the frames where u's tolerance is at
     * least t's (coarser: a sure "keep" at u is one at t, the frustum and
     * orientation tests being the same and the screen test monotone in
     * kappa2) and at most t's (finer: a sure collapse, or a subtree that
     * collapses whole, at u is one at t). */
    Lanes coarser[MOST_SETS][MOST_SETS] = {{0}}, finer[MOST_SETS][MOST_SETS] = {{0}};
    for (int t = 0; t < T; t++)
        for (int u = 0; u < t; u++)
            for (int l = 0; l < FRAMES; l++) {
                coarser[u][t] |= (Lanes)((fr[u].kappa2[l] >= fr[t].kappa2[l]) << l);
                finer[u][t] |= (Lanes)((fr[u].kappa2[l] <= fr[t].kappa2[l]) << l);
            }
    void (*decide_row)(const Frames *, const float *, Lanes *) =
        fr[0].ortho ? kern->decide_row_orthographic : kern->decide_row_perspective;
    const Lanes active = (Lanes)((1u << FRAMES) - 1);
    const float *table = h->rows;
    int32_t fat_code[BLOCK];
    Columns col;
    int64_t n = 0;
    for (int64_t i = 0; i < h->n_roots; i++) {
        ids[n] = (int32_t)i;
        for (int t = 0; t < T; t++)
            sb->visit[t * room + n] = active;
        n++;
    }
    for (int64_t i0 = 0; i0 < n;) {
        /* A block of slots under the fat camera first, for every set at once. */
        const int64_t nb = n - i0 < BLOCK ? n - i0 : BLOCK;
        if (use_fat) {
            gather_block(kern, table, ids + i0, nb, col);
            kern->decide_fat(&W, col, fat_code);
        }
        for (int64_t i = i0; i < i0 + nb; i++) {
            if (i + AHEAD < n)
                __builtin_prefetch(table + (int64_t)ids[i + AHEAD] * ROW);
            const float *row = table + (int64_t)ids[i] * ROW;
            const int32_t fc = use_fat ? fat_code[i - i0] : FAT_OPEN;
            Lanes open[MOST_SETS], no[MOST_SETS], sure_whole[MOST_SETS], sure_yes[MOST_SETS], any = 0;
            /* Each set's frames that reach the slot decide it, less what the
             * fat camera decided for all of them and what the sets decided
             * before imply (monotone). */
            for (int t = 0; t < T; t++) {
                const Lanes v = sb->visit[t * room + i];
                open[t] = no[t] = sure_whole[t] = sure_yes[t] = 0;
                sb->whole[t * room + i] = sb->yes[t * room + i] = 0;
                if (!v)
                    continue;
                visited[t]++;
                /* The fat camera's verdicts for every frame (as traverse_word's
                 * fat masks); the frames decide only the slots it left open. */
                at_once[t] += (fc == FAT_WHOLE) | (fc == FAT_NO) | (fc == FAT_YES);
                Lanes masks[3] = {fc == FAT_WHOLE ? (Lanes)0xFFFF : 0, fc == FAT_YES ? (Lanes)0xFFFF : 0, 0};
                if (fc == FAT_OPEN || fc == FAT_SCREEN || fc == FAT_INSIDE) {
                    Lanes known_no = 0, known_whole = 0, known_yes = 0;
                    for (int u = 0; u < t; u++) {
                        known_no |= no[u] & coarser[u][t];
                        known_whole |= sure_whole[u] & finer[u][t];
                        known_yes |= sure_yes[u] & finer[u][t];
                    }
                    const Lanes known = (Lanes)((known_no | known_whole | known_yes) & v);
                    if (v & (Lanes)~known) {
                        if (fc == FAT_OPEN)
                            decide_row(&fr[t], row, masks);
                        else
                            kern->decide_row_settled(&fr[t], row, fc, masks);
                    }
                    /* A frame keeps its own "whole" unless a coarser set's sure
                     * "keep" rules it out (a finer set's sure collapse does not). */
                    masks[0] = (Lanes)((masks[0] & ~known_no) | (known_whole & v));
                    masks[1] = (Lanes)((masks[1] & ~known) | (known_yes & v));
                    masks[2] = (Lanes)(masks[2] & ~known);
                }
                open[t] = v & (Lanes)~masks[0];
                sb->whole[t * room + i] = v & masks[0];
                sb->yes[t * room + i] = open[t] & masks[1];
                sure_whole[t] = v & masks[0];
                sure_yes[t] = open[t] & masks[1] & (Lanes)~masks[2];
                no[t] = open[t] & (Lanes)~(masks[1] | masks[2]);
                if (open[t] & masks[2]) {
                    sb->unsure[t * room + n_unsure[t]] = (int32_t)i;
                    sb->unsure_lanes[t * room + n_unsure[t]++] = open[t] & masks[2];
                }
                any |= open[t];
            }
            kid[2 * i] = kid[2 * i + 1] = -1;
            if (!any)
                continue;
            /* The children, for each set's frames that did not decide this subtree. */
            int32_t kids;
            memcpy(&kids, row + KIDS, sizeof kids);
            const int32_t first = kids_first(kids), count = kids & 3;
            if (n + count > h->n_pcols)
                return -1;
            for (int c = 0; c < count; c++) {
                kid[2 * i + c] = (int32_t)n;
                for (int t = 0; t < T; t++)
                    sb->visit[t * room + n] = open[t];
                ids[n++] = first + c;
            }
        }
        i0 += nb;
    }
    return n;
}

/* traverse_sets with T a constant for the usual two sets (a budget's two
 * patterns), whose loops over the sets the compiler unrolls. */
static int64_t traverse_two(const Kernels *kern, const PmxHierarchy *h, const float *views, int flags,
                            const float *fat, int32_t *ids, int32_t *kid, SetBits *sb, int64_t room, int64_t *n_unsure,
                            int64_t *at_once, int64_t *visited)
{
    return traverse_sets(kern, h, views, 2, flags, fat, ids, kid, sb, room, n_unsure, at_once, visited);
}

static int64_t traverse_any(const Kernels *kern, const PmxHierarchy *h, const float *views, int T, int flags,
                            const float *fat, int32_t *ids, int32_t *kid, SetBits *sb, int64_t room, int64_t *n_unsure,
                            int64_t *at_once, int64_t *visited)
{
    if (T == 2)
        return traverse_two(kern, h, views, flags, fat, ids, kid, sb, room, n_unsure, at_once, visited);
    return traverse_sets(kern, h, views, T, flags, fat, ids, kid, sb, room, n_unsure, at_once, visited);
}

/* Words shared by a call's threads, a set of them at a time. */
typedef struct {
    const PmxHierarchy *h;
    const float *views;
    int flags, sets;
    int64_t W, cursor;
    PmxCounts *counts;
    int32_t *at_once;
    PmxRecords *records;
    uint8_t *overflow;
    PmxStatus status;
} Sets;

/* The records of set t's unsure slots (as records.c writes a word's, item
 * `word`), or its overflow flag. parent_known: the slots' parents are built. */
static void record_set(Sets *b, PmxScratch *s, const SetBits *sb, int64_t n, int64_t room, int t, int64_t m,
                       int64_t word, int parent_known)
{
    const int32_t *unsure = sb->unsure + t * room;
    const int64_t count = record_chain(n, b->h->n_roots, s->kid, unsure, m, s->parent, parent_known, s->chain,
                                       s->mark);
    const int64_t at = records_reserve(b->records, 2 + count * PMX_NODE);
    if (at < 0) {
        b->overflow[word] = 1;
        return;
    }
    const SlotBits bits = {sb->visit + t * room, sb->whole + t * room, sb->yes + t * room,
                           sb->ran + t * room,   sb->unsure_lanes + t * room, NULL, NULL};
    record_write(b->records->records + at, word, count, s->chain, s->ids, s->kid, &bits, b->h->kills, unsure, m);
}

static void sets_work(void *arg)
{
    Sets *b = arg;
    const PmxHierarchy *h = b->h;
    const int64_t room = h->n_pcols + PMX_SPARE;
    const int64_t groups = b->W / b->sets;
    int64_t g = __atomic_fetch_add(&b->cursor, 1, __ATOMIC_RELAXED);
    /* A thread that finds no group left takes no scratch. */
    if (g >= groups)
        return;
    PmxScratch *s = pmx_scratch_take(h->n_pcols);
    const int ok = s && scratch_slots(s) && scratch_sets(s, b->sets);
    if (!ok) {
        __atomic_store_n(&b->status, PMX_NO_MEMORY, __ATOMIC_RELAXED);
        if (s)
            pmx_scratch_give(s);
        return;
    }
    SetBits sb = {s->set_visit, s->set_whole, s->set_yes, s->set_ran, s->set_unsure_lanes, s->set_unsure,
                  room, s->sets};
    const unsigned mode = subnormals_off();
    const Kernels *kern = pmx_kernels();
    for (; g < groups; g = __atomic_fetch_add(&b->cursor, 1, __ATOMIC_RELAXED)) {
        const int64_t first = g * b->sets;
        /* Sets that differ in more than their tolerances (or whose frames
         * the fat camera cannot share) are traversed one by one. */
        int together = 1;
        for (int t = 1; t < b->sets; t++)
            together &= same_but_tolerance(b->views + first * FRAMES * PMX_VIEW,
                                           b->views + (first + t) * FRAMES * PMX_VIEW);
        for (int64_t w0 = first; w0 < first + b->sets;) {
            const int T = together ? b->sets : 1;
            const float *views = b->views + w0 * FRAMES * PMX_VIEW;
            float fat[PMX_FAT];
            const int have_fat = pmx_fat_cameras(views, 1, FRAMES, fat) == PMX_OK;
            int64_t m[MOST_SETS], at_once[MOST_SETS], visited[MOST_SETS];
            const int64_t n = traverse_any(kern, h, views, T, b->flags, have_fat ? fat : NULL, s->ids, s->kid, &sb,
                                            room, m, at_once, visited);
            if (n < 0) {
                __atomic_store_n(&b->status, PMX_BAD_TABLE, __ATOMIC_RELAXED);
                break;
            }
            int parents = 0; /* built by the first set with records */
            for (int t = 0; t < T; t++) {
                const int64_t w = w0 + t;
                PmxCounts *counts = b->counts + w * FRAMES;
                /* Unsure pairs are taken as "keep" (their yes bits clear); a
                 * slot the set did not visit ran for all its frames, as one
                 * decided above it does in the word alone. */
                kern->resolve_word(h->kills, h->order, n, s->ids, s->kid, sb.visit + t * room, sb.whole + t * room,
                                   sb.yes + t * room, sb.ran + t * room, NULL, counts);
                for (int l = 0; l < FRAMES; l++)
                    counts[l].visited = (int32_t)visited[t], counts[l].unsure = 0;
                for (int64_t q = 0; q < m[t]; q++)
                    for (int l = 0; l < FRAMES; l++)
                        counts[l].unsure += (sb.unsure_lanes[t * room + q] >> l) & 1;
                if (b->at_once)
                    b->at_once[w] = (int32_t)at_once[t];
                b->overflow[w] = 0;
                if (m[t] > 0) {
                    record_set(b, s, &sb, n, room, t, m[t], w, parents);
                    parents = 1;
                }
            }
            w0 += T;
        }
        if (__atomic_load_n(&b->status, __ATOMIC_RELAXED) != PMX_OK)
            break;
    }
    subnormals_back(mode);
    pmx_scratch_give(s);
}

PmxStatus pmx_refine_word_sets(const PmxHierarchy *h, const float *views, int64_t W, int sets, int flags,
                               PmxCounts *counts, int32_t *at_once, PmxRecords *records, uint8_t *overflow,
                               const PmxRunner *run)
{
    if (sets < 1 || sets > MOST_SETS || W % sets != 0)
        return PMX_BAD_SIZE;
    Sets b = {h, views, flags, sets, W, 0, counts, at_once, records, overflow, PMX_OK};
    run_shared(run, sets_work, &b);
    return b.status;
}
