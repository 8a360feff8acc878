/* Unsure decisions decided later: records of the chains they can change.
 *
 * A camera (or word) with unsure (frame, pcol) pairs is resolved at once as
 * if each were "keep" (its yes bit clear), and its chains are recorded: the
 * unsure slots and their ancestors up to the roots, the only slots whose ran
 * bits can change when a pair turns out "collapse". Once the pairs are
 * decided (one call of the float32 predicate for many items), the chains are
 * resolved again and the item's counts corrected. A record is [item, nodes]
 * and then PMX_NODE int32 per node, the nodes by decreasing slot (children
 * first). */
#include "internal.h"

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

static inline int32_t bits_visit(const SlotBits *b, int64_t s) { return b->visit ? b->visit[s] : 1; }
static inline int32_t bits_whole(const SlotBits *b, int64_t s) { return b->whole ? b->whole[s] : 0; }
static inline int32_t bits_yes(const SlotBits *b, int64_t s) { return b->yes ? b->yes[s] : b->state[s] == YES; }
static inline int32_t bits_ran(const SlotBits *b, int64_t s) { return b->ran ? b->ran[s] : b->ran_byte[s]; }

int64_t record_chain(int64_t n, int64_t n_roots, const int32_t *kid, const int32_t *unsure_slots, int64_t m,
                     int32_t *parent, int parent_known, int32_t *chain, uint8_t *mark)
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
    sort_descending(chain, count);
    return count;
}

void record_write(int32_t *rec, int64_t item, int64_t count, const int32_t *chain, const int32_t *ids,
                  const int32_t *kid, const SlotBits *b, const int32_t *kills, const int32_t *unsure_slots, int64_t m)
{
    rec[0] = (int32_t)item, rec[1] = (int32_t)count;
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
}

int64_t records_reserve(PmxRecords *records, int64_t size)
{
    int64_t used = __atomic_load_n(&records->used, __ATOMIC_RELAXED);
    do {
        if (size > records->capacity - used)
            return -1;
    } while (!__atomic_compare_exchange_n(&records->used, &used, used + size, 1, __ATOMIC_RELAXED,
                                          __ATOMIC_RELAXED));
    return used;
}

int64_t pmx_unsure_pairs(const int32_t *records, int64_t used, int64_t *at, int32_t *item, int32_t *position,
                         int32_t *frames)
{
    int64_t c = 0;
    for (int64_t r = 0; r < used; r += 2 + records[r + 1] * NODE_N)
        for (int64_t j = 0; j < records[r + 1]; j++) {
            const int32_t *node = records + r + 2 + j * NODE_N;
            if (node[NODE_UNSURE]) {
                at[c] = r + 2 + j * NODE_N + NODE_YES;
                item[c] = records[r], position[c] = node[NODE_POSITION], frames[c++] = node[NODE_UNSURE];
            }
        }
    return c;
}

void pmx_apply_unsure(int32_t *records, int64_t used, const int64_t *at, const int32_t *yes, int64_t n,
                      int frames, PmxCounts *counts, const int32_t *order, int64_t n_pcols, uint8_t *masks,
                      PmxLists lists)
{
    const int64_t stride = n_pcols + PMX_SPARE;
    const Lanes lanes = (Lanes)(frames >= 16 ? 0xFFFF : (1u << frames) - 1);
    for (int64_t i = 0; i < n; i++)
        records[at[i]] |= yes[i];
    /* The chains resolved again, children first; each frame whose slot now
     * runs has one pcol fewer that did not run, and its kills fewer kept
     * (yes bits only grow, so ran bits only turn on). */
    for (int64_t r = 0; r < used; r += 2 + records[r + 1] * NODE_N) {
        int32_t *nodes = records + r + 2;
        const int64_t item = records[r];
        PmxCounts *c = counts + item * frames;
        for (int64_t j = 0; j < records[r + 1]; j++) {
            int32_t *node = nodes + j * NODE_N;
            const Lanes r1 = (Lanes)(node[NODE_K1] >= 0 ? nodes[node[NODE_K1] * NODE_N + NODE_RAN] : node[NODE_RAN_K1]);
            const Lanes r2 = (Lanes)(node[NODE_K2] >= 0 ? nodes[node[NODE_K2] * NODE_N + NODE_RAN] : node[NODE_RAN_K2]);
            const Lanes now = (Lanes)(~node[NODE_VISIT] | node[NODE_WHOLE] | (node[NODE_YES] & r1 & r2));
            const Lanes turned = (Lanes)(now & ~node[NODE_RAN] & lanes);
            node[NODE_RAN] = now;
            if (!turned)
                continue;
            const int64_t slot = item * stride + node[NODE_SLOT];
            if (frames == 1) {
                if (lists.ran)
                    lists.ran[slot] = 1;
                if (masks)
                    masks[item * n_pcols + order[node[NODE_POSITION]]] = 1;
            } else if (lists.ran_frames) {
                lists.ran_frames[slot] |= turned;
            }
            for (int l = 0; l < frames; l++)
                if ((turned >> l) & 1)
                    c[l].not_run -= 1, c[l].kept -= node[NODE_KILLS];
        }
    }
}
