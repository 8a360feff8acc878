/* The slots' bookkeeping of a traversal, plain loops (the specification the
 * vector versions, slots_avx2.c and slots_avx512.c, reproduce bit for bit):
 * a decided block's slots pushed onto the queue, and the bottom-up pass. */
#include "internal.h"

/* The slots of one decided block [i, i + nb) (decided[]: decide_block's
 * codes, kids[]: their rows' KIDS column): each slot's own decision goes to
 * state[], the faces its pcol kills to kill[], the unsure ones to
 * unsure[*m...], and the children of the open slots (those whose bound did
 * not decide everything below them) are pushed behind the queue at n, their
 * slots written to kid[] (and, where parent is not NULL, the slot of each
 * child's parent to parent[]). Returns the new end of the queue (past
 * n_pcols: links that are not a forest). The children of an open slot are
 * visited whatever it does (each may run on its own); a
 * slot is closed when everything below it collapses: its children ran, and it
 * runs when it collapses itself. */
int64_t push_block_plain(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n, const int32_t *decided,
                                       const float *kids, uint8_t *state, int32_t *kill, int32_t *kid, int32_t *ids,
                                       int32_t *parent, int32_t *unsure, int64_t *m)
{
    for (int64_t j = i; j < i + nb; j++) {
        /* A queue past the table (links that are not a forest) stops before
         * its two stores could pass the spare room; the caller checks n. */
        if (n > h->n_pcols)
            return n;
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
        kill[j] = kids_kills(h, k, ids[j]);
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

/* The slots of one decided block [i, i + nb) of a word (traverse_word):
 * masks[0][j], masks[1][j], masks[2][j] are the frames whose bound decided
 * slot i + j, whose own decision is yes, and which are unsure; kids[] their
 * rows' KIDS column. Each slot's whole[] and yes[] frames (of those that
 * visit it) are written, its unsure frames go to unsure_slots[*m...] and
 * unsure_lanes[*m...], and the children of a slot that some visiting frame
 * left open are pushed behind the queue at n, visited by those frames (their
 * slots in kid[], -1 where none). Returns the new end of the queue, or -1
 * where it would pass n_pcols (links that are not a forest). */
int64_t push_word_block_plain(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n, const Lanes (*masks)[BLOCK],
                              const float *kids, Lanes *visit, Lanes *whole, Lanes *yes, int32_t *kid, int32_t *ids,
                              int32_t *unsure_slots, Lanes *unsure_lanes, int64_t *m)
{
    for (int64_t j = i; j < i + nb; j++) {
        const Lanes wh = masks[0][j - i], y = masks[1][j - i], u = masks[2][j - i];
        const Lanes v = visit[j], open = v & (Lanes)~wh;
        whole[j] = v & wh;
        yes[j] = open & y;
        if (open & u) {
            unsure_slots[*m] = (int32_t)j;
            unsure_lanes[(*m)++] = open & u;
        }
        /* The children (at most two, as push_block counts them), for the
         * frames that did not decide this subtree. */
        int32_t k;
        memcpy(&k, &kids[j - i], sizeof k);
        const int32_t first = kids_first(k), count = open ? ((k & 3) > 1 ? 2 : k & 3) : 0;
        if (n + count > h->n_pcols)
            return -1;
        kid[2 * j] = kid[2 * j + 1] = -1;
        for (int t = 0; t < count; t++) {
            kid[2 * j + t] = (int32_t)n;
            visit[n] = open;
            ids[n++] = first + t;
        }
    }
    return n;
}

/* Bottom-up over slots [lo, hi), from the end: a slot ran if it collapses
 * and both children ran (a child not visited ran). Counts the slots that
 * did not run and the faces they keep into *not_run, *keep. */
void resolve_plain_range(const PmxHierarchy *h, int64_t lo, int64_t hi, const int32_t *ids, const int32_t *kid,
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
            pcols[i] = h->order[ids[i]];
    }
}

/* resolve_plain_range over all n slots. */
void resolve_plain(const PmxHierarchy *h, int64_t n, const int32_t *ids, const int32_t *kid, const uint8_t *state,
                   const int32_t *kill, uint8_t *ran, int32_t *pcols, int64_t *not_run, int64_t *kept)
{
    *not_run = *kept = 0;
    resolve_plain_range(h, 0, n, ids, kid, state, kill, ran, pcols, not_run, kept);
}
