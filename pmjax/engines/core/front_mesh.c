/* The refined mesh read off the front: cost proportional to the faces drawn.
 *
 * A face is drawn when its killer did not run: a base face (no killer) or
 * one that a visited pcol that did not run would kill. The front, the
 * vertices drawn, is read off the same pcols: a child vertex of a pcol that
 * did not run is on the front if it is original or its own pcol ran; so is
 * the vertex of a root that ran, and an original vertex nothing consumes.
 * With the original vertices numbered in depth-first order of the forest,
 * the ones below any vertex form an interval, and the front's intervals tile
 * [0, V0): a corner's representative is the front vertex whose interval
 * holds the corner's position. */
#include "internal.h"

/* How ranks are taken (pmx_mesh_ranks): 0 by the rule below, 1 bitmaps
 * always, 2 sorts always. */
static int ranks_in_use = 0;

int pmx_mesh_ranks(int mode)
{
    const int was = __atomic_load_n(&ranks_in_use, __ATOMIC_ACQUIRE);
    if (mode >= 0 && mode <= 2)
        __atomic_store_n(&ranks_in_use, mode, __ATOMIC_RELEASE);
    return was;
}

/* Whether n items are ranked by sorting them rather than in a bitmap of
 * that many words. A bitmap costs a pass to count and one to clear over
 * every word, and a scattered store and load per item in an array that may
 * not fit the caches; a sort, one or two passes over the items (digits of
 * up to RANK_DIGIT_MOST bits, sort_plan) in arrays of their size:
 * the sort wins once the words outnumber the items RANKS_SORTED times, as
 * where a model far larger than the caches draws few of its faces. The
 * front's starts stay in a bitmap either way (below). */
#ifndef RANKS_SORTED
#define RANKS_SORTED 4
#endif
PMX_INLINE int ranks_sorted(int mode, int64_t n, int64_t words)
{
    return mode == 2 || (mode == 0 && n * RANKS_SORTED < words);
}

/* A sort's plan: `passes` digits of `digit` bits, as even as they go,
 * cover ids up to max_id. Once the items outnumber 2^12, digits of up to
 * RANK_DIGIT_MOST bits (two passes over ids up to 2^26: faces or vertex ids
 * of models of up to 67 M), else of up to a byte (small tables of counts
 * for few items). */
typedef struct {
    int passes, digit;
} SortPlan;

PMX_INLINE SortPlan sort_plan(int64_t n, int64_t max_id)
{
    /* The ids are int32, so at most 31 bits: a larger max_id is capped
     * there, not cut to its low bits. */
    const uint64_t top = max_id < 0 ? 0 : max_id > INT32_MAX ? INT32_MAX : (uint64_t)max_id;
    int bits = 1;
    while (bits < 31 && (top >> bits) > 0)
        bits++;
    const int most = n >= ((int64_t)1 << 12) ? RANK_DIGIT_MOST : 8;
    const int passes = (bits + most - 1) / most;
    return (SortPlan){passes, (bits + passes - 1) / passes};
}

/* The set bits of a bitmap after prefix_marked: those before its last
 * marked word (every word where dense) and in it. */
PMX_INLINE int64_t marked_count(const uint64_t *bits, const uint64_t *sum, const int32_t *prefix, int64_t words,
                                int dense)
{
    int64_t last = dense ? words - 1 : -1;
    for (int64_t b = words / 64; !dense && b >= 0 && last < 0; b--)
        if (sum[b])
            last = 64 * b + 63 - __builtin_clzll(sum[b]);
    return last < 0 ? 0 : prefix[last] + __builtin_popcountll(bits[last]);
}

/* Digit p of an id under plan. */
PMX_INLINE int32_t id_digit(int32_t id, SortPlan plan, int p)
{
    return (int32_t)(((uint32_t)id >> (p * plan.digit)) & ((1u << plan.digit) - 1));
}

/* The digits of `passes` passes of the ids id_of [n] counted into count
 * (pass p's table at p << digit). */
PMX_INLINE void count_digits(const int32_t *id_of, int64_t n, int32_t *count, SortPlan plan, int passes)
{
    for (int64_t i = 0; i < n; i++)
        for (int p = 0; p < passes; p++)
            count[((int64_t)p << plan.digit) + id_digit(id_of[i], plan, p)]++;
}

/* Each item's row, its place in increasing id order: a stable radix sort
 * of the ids id_of [n] (gathered while the items are read), with every
 * pass's digit counts taken in one read (count: pass p's table at
 * p << digit, zero on entry and on return), the first pass reading the ids
 * themselves and the last writing each item's row rather than the sorted
 * entries, and each id at its row in the rows' buffer past them (its free
 * half: a buffer of n IdSlot holds 2 n int32), so that one read in order
 * finds an id given twice. Returns the rows, int32 [n] by item, over a's
 * or b's room (two buffers of n entries; id_of may lie in b: only the
 * first pass reads it); NULL (the rows not all written) where an id comes
 * twice: the items must all differ. */
static int32_t *rows_by_id(const int32_t *id_of, int64_t n, int32_t *count, SortPlan plan, IdSlot *a, IdSlot *b)
{
    const int32_t buckets = (int32_t)1 << plan.digit;
    /* Every pass's digits counted in one read (the loop over passes
     * unrolled for one and two). */
    if (plan.passes == 1)
        count_digits(id_of, n, count, plan, 1);
    else if (plan.passes == 2)
        count_digits(id_of, n, count, plan, 2);
    else
        count_digits(id_of, n, count, plan, plan.passes);
    /* Each count to the first place of its digit, in each pass. */
    for (int p = 0; p < plan.passes; p++) {
        int32_t below = 0, *at = count + ((int64_t)p << plan.digit);
        for (int32_t d = 0; d < buckets; d++) {
            const int32_t here = at[d];
            at[d] = below;
            below += here;
        }
    }
    const int last = plan.passes - 1;
    int32_t *row;
    if (last == 0) {
        /* One pass: each item straight to its row. */
        row = (int32_t *)a;
        for (int64_t i = 0; i < n; i++) {
            const int32_t r = count[id_digit(id_of[i], plan, 0)]++;
            row[i] = r;
            row[n + r] = id_of[i];
        }
    } else {
        /* The first pass from the ids, the middle ones between the
         * buffers, the last to the rows. */
        for (int64_t i = 0; i < n; i++)
            a[count[id_digit(id_of[i], plan, 0)]++] = (IdSlot){id_of[i], (int32_t)i};
        IdSlot *from = a, *to = b;
        for (int p = 1; p < last; p++) {
            int32_t *at = count + ((int64_t)p << plan.digit);
            for (int64_t k = 0; k < n; k++)
                to[at[id_digit(from[k].id, plan, p)]++] = from[k];
            IdSlot *t = from;
            from = to;
            to = t;
        }
        row = (int32_t *)to;
        int32_t *at = count + ((int64_t)last << plan.digit);
        for (int64_t k = 0; k < n; k++) {
            const int32_t r = at[id_digit(from[k].id, plan, last)]++;
            row[from[k].slot] = r;
            row[n + r] = from[k].id;
        }
    }
    memset(count, 0, sizeof(int32_t) * ((size_t)plan.passes << plan.digit));
    /* The ids in sorted order increase strictly unless one comes twice (a
     * reduction without branches). */
    const int32_t *const sorted = row + n;
    int twice = 0;
    for (int64_t k = 1; k < n; k++)
        twice |= sorted[k] <= sorted[k - 1];
    return twice ? NULL : row;
}

/* The refined mesh from the pcols that did not run:
 * drawn faces are the base faces and those pcols' kill lists; each corner's
 * representative is the front vertex whose depth-first interval holds the
 * corner's position. Every order and index comes from a rank in a bitmap
 * (faces, front starts, vertex ids), so that besides those small bitmaps a
 * pcol that did not run costs one record and its kill data, and nothing reads
 * an array over all faces or vertices at random. Each bitmap has a summary
 * of its words set (set_marked), so that where few are set its ranks are
 * counted and it is cleared over those words only: a coarse mesh costs what
 * it draws, not the model's size. Faces and vertex ids that are few for
 * their bitmap's words (ranks_sorted) are ranked by sorting them instead:
 * their ranks then cost what is drawn, not a pass over the model's words.
 *
 * ran (or bit `frame` of ran_frames), positions: whether each of a
 * refinement's n visited slots ran, and their positions, the index of the
 * pcol records (breadth-first, so that the records are read in nearly
 * increasing order). Writes faces [n_faces_drawn, 3] (indices into ids and
 * vertex_positions, faces in increasing order), ids and vertex_positions
 * (the vertices used, by increasing id; *n_ids of them, room for
 * id_capacity). Slots that are not a refinement's give no mesh and a
 * status saying how (pmx_front_mesh), PMX_FACES_DIFFER where the faces
 * found are not n_faces_drawn; a record read that points outside the
 * tables, PMX_BAD_*_RECORD and its index in *n_ids; PMX_BAD_SIZE (ids and
 * vertex_positions not written) if more vertices are used than
 * id_capacity.
 *
 * Scratch (scratch_mesh): mark [P] bytes (by breadth-first position),
 * start_bits [V0/64+1], face_bits [F/64+1], vertex_bits [(V0+P)/64+1] words
 * and their summaries start_sum, face_sum, vertex_sum (a word per 64; all
 * zero on entry and on return); start_prefix, face_prefix, vertex_prefix
 * int32 as their bitmaps, start_block as start_sum; front [V0 + 1] (the
 * vertices not kept are written one slot past the front), front_rank [V0];
 * drawn [F]; front_index [V0]; pairs[2] [max(F, V0 + 1)] (the sorts'; the
 * ids to sort gathered in pairs[1]);
 * sort_counts [RANK_COUNTS] (zero on entry and on return). */
PMX_INLINE PmxStatus front_mesh_body(const PmxMeshTables *m, const uint8_t *ran, const uint16_t *ran_frames,
                                     int frame, const int32_t *positions, int64_t n, int64_t n_faces_drawn,
                                     int32_t *faces, int32_t *ids, float *vertex_positions, int64_t id_capacity,
                                     int64_t *n_ids, PmxScratch *s)
{
    const int64_t V0 = m->n_original, n_pcols = m->n_pcols, n_faces_total = m->n_faces;
    /* The tables and the scratch as local pointers: the loops store bytes,
     * which may alias any field of the structs, so fields read in a loop
     * would be read again after every store. */
    const PmxPcolRecord *const records = m->pcols;
    const PmxFaceRecord *const kill_data = m->kill_data, *const base = m->base;
    const PmxFrontVertex *const tops = m->tops;
    const int32_t *const top_at = m->top_at;
    const int64_t n_tops = m->n_tops, n_base = m->n_base, n_kill = m->n_kill_data;
    int32_t *const not_run_at = s->not_run_at, *const start_prefix = s->start_prefix;
    int32_t *const face_prefix = s->face_prefix, *const vertex_prefix = s->vertex_prefix;
    int32_t *const front_index = s->front_index;
    uint8_t *const mark = s->mark;
    int32_t *const start_block = s->start_block;
    uint64_t *const start_bits = s->start_bits, *const face_bits = s->face_bits, *const vertex_bits = s->vertex_bits;
    uint64_t *const start_sum = s->start_sum, *const face_sum = s->face_sum, *const vertex_sum = s->vertex_sum;
    PmxFrontVertex *const front = s->front;
    int32_t *const front_rank = s->front_rank;
    PmxFaceRecord *const drawn = s->drawn;
    const int64_t start_words = V0 / 64 + 1, face_words = n_faces_total / 64 + 1;
    const int64_t vertex_words = (V0 + n_pcols) / 64 + 1;
    /* The records and kill lists of the pcols that did not run are sparse in
     * arrays far larger than the cache, so each is a miss: requested
     * MESH_AHEAD pcols early (both cache lines of a record that straddles
     * two), then, from the record, its kill list and its vertices' marks
     * MESH_AHEAD / 2 pcols early, the misses overlap. Where the faces are
     * sorted (a model large for what it draws), the start bitmap's words
     * of a face's corners are requested FACE_AHEAD faces early too. */
    const int64_t MESH_AHEAD = 32, FACE_AHEAD = 8;
    /* Without branches: whether a visited pcol ran is a coin toss to the
     * branch predictor. Every slot is written, the count advances on those
     * that did not run (mark is zero on entry, so a pcol that ran keeps 0). */
    int64_t n_not_run = 0;
    for (int64_t i = 0; i < n; i++) {
        const int32_t at = positions[i];
        const uint8_t not_ran = ran ? !ran[i] : !((ran_frames[i] >> frame) & 1);
        not_run_at[n_not_run] = at;
        n_not_run += not_ran;
        mark[at] = not_ran;
    }
    /* Each rank from a bitmap or, where the items are few for its words,
     * from sorting them (ranks_sorted); the bitmaps' summaries are kept
     * where few bits will be set: the front is at most two vertices per
     * pcol that did not run and the tops. */
    const int mode = __atomic_load_n(&ranks_in_use, __ATOMIC_ACQUIRE);
    const int face_sorted = ranks_sorted(mode, n_faces_drawn, face_words);
    const int face_dense = marked_dense(n_faces_drawn, face_words);
    const SortPlan face_plan = sort_plan(n_faces_drawn, n_faces_total > 0 ? n_faces_total - 1 : 0);
    int32_t *const sort_counts = s->sort_counts;
    int32_t *const face_of = (int32_t *)s->pairs[1];
    /* The front and the drawn faces. Below each pcol that did not run: its
     * vertices that are original or whose own pcol ran, and its kill list
     * (where faces are sorted, their ids gathered too: the sort then reads
     * a quarter of the bytes). */
    int64_t n_front = 0, n_drawn = 0;
    /* The room: a refinement draws each face at most once (drawn, and the
     * face ids in pairs[1], hold F) and its front tiles [0, V0) (front
     * holds V0 + 1). Its slots visit a pcol before its children's, so each
     * pcol that did not run (and each top kept) has a front vertex still to
     * come: before it the front is below V0.
     * Slots that are not a refinement's (a position twice, ran that does
     * not match) can find more: the reading stops there and the mesh is
     * refused (found: why), with nothing written past the room. Each
     * record is checked as it is read (pmx_*_fits; bad_at: the first that
     * points outside the tables), so that every index it gives stays
     * inside the scratch and the tables. */
    PmxStatus found = PMX_OK;
    int64_t bad_at = 0;
    for (int64_t i = 0; i < n_not_run; i++) {
        if (i + MESH_AHEAD < n_not_run) {
            const char *ahead = (const char *)(records + not_run_at[i + MESH_AHEAD]);
            __builtin_prefetch(ahead);
            __builtin_prefetch(ahead + sizeof(PmxPcolRecord) - 1);
        }
        if (i + MESH_AHEAD / 2 < n_not_run) { /* its record was requested MESH_AHEAD / 2 steps ago */
            const PmxPcolRecord *q = records + not_run_at[i + MESH_AHEAD / 2];
            __builtin_prefetch(kill_data + q->kill_first);
            __builtin_prefetch(kill_data + q->kill_first + (q->kill_count > 0 ? q->kill_count - 1 : 0));
            __builtin_prefetch(mark + (q->made_at[0] < 0 ? 0 : q->made_at[0]));
            __builtin_prefetch(mark + (q->made_at[1] < 0 ? 0 : q->made_at[1]));
        }
        const PmxPcolRecord *r = records + not_run_at[i];
        if (!pmx_pcol_record_fits(r, not_run_at[i], n_kill, V0, n_pcols)) {
            found = PMX_BAD_PCOL_RECORD, bad_at = not_run_at[i];
            break;
        }
        /* Past the room: a front past V0, or more faces than F (one of
         * them drawn twice). */
        if (n_front >= V0 || n_drawn + r->kill_count > n_faces_total) {
            found = n_front >= V0 ? PMX_FRONT_PAST : PMX_FACE_TWICE;
            break;
        }
        for (int j = 0; j < 2; j++) {
            /* Without branches too: the vertex is written, and kept when it is
             * original or its own pcol ran. */
            const int32_t made = r->made_at[j];
            const int kept = (made < 0) | !mark[made < 0 ? 0 : made];
            PmxFrontVertex *f = front + n_front;
            f->start = r->start[j];
            f->vertex = r->vertex[j];
            memcpy(f->position, r->position[j], sizeof f->position);
            n_front += kept;
        }
        for (int32_t j = 0; j < r->kill_count; j++) {
            drawn[n_drawn] = kill_data[r->kill_first + j];
            if (!pmx_face_record_fits(drawn + n_drawn, n_faces_total, V0)) {
                found = PMX_BAD_KILL_RECORD, bad_at = r->kill_first + j;
                break;
            }
            if (face_sorted)
                face_of[n_drawn] = drawn[n_drawn].face;
            else
                set_marked(face_bits, face_sum, drawn[n_drawn].face, 1, face_dense);
            n_drawn++;
        }
        if (found != PMX_OK)
            break;
    }
    /* The tops: the roots that ran (top_at >= 0) and the lone originals. */
    for (int64_t i = 0; i < n_tops && found == PMX_OK; i++) {
        if (!pmx_top_fits(tops + i, top_at[i], V0, n_pcols))
            found = PMX_BAD_TOP_RECORD, bad_at = i;
        else if (top_at[i] < 0 || !mark[top_at[i]]) {
            if (n_front >= V0)
                found = PMX_FRONT_PAST;
            else
                front[n_front++] = tops[i];
        }
    }
    if (found == PMX_OK && n_drawn + n_base > n_faces_total)
        found = PMX_FACE_TWICE;
    for (int64_t i = 0; i < n_base && found == PMX_OK; i++)
        if (!pmx_face_record_fits(base + i, n_faces_total, V0))
            found = PMX_BAD_BASE_RECORD, bad_at = i;
        else if (face_sorted)
            face_of[n_drawn + i] = base[i].face;
        else
            set_marked(face_bits, face_sum, base[i].face, 1, face_dense);
    const int64_t total = n_drawn + n_base;
    IdSlot *const pairs = s->pairs[0], *const pairs_to = s->pairs[1];
    /* The front in depth-first order: each vertex's rank is the rank of its
     * start, kept beside it (front_rank, written in order) rather than the
     * vertex moved there (a scattered store of the whole vertex). (Its starts
     * stay in a bitmap: a corner's front vertex is then two independent
     * loads, where a search among sorted starts is a chain of them.) */
    const int start_dense = marked_dense(n_front, start_words);
    PmxStatus status = found != PMX_OK ? found : total == n_faces_drawn ? PMX_OK : PMX_FACES_DIFFER;
    if (status == PMX_OK) {
        for (int64_t i = 0; i < n_front; i++)
            set_marked(start_bits, start_sum, front[i].start, 1, start_dense);
        prefix_marked(start_bits, start_sum, start_words, start_dense, start_prefix, start_block);
        /* A refinement's front has distinct starts, at most V0 of them: a
         * start given twice is no refinement's, and the ranks below
         * (front_rank and front_index hold V0) are not written for it. */
        if (marked_count(start_bits, start_sum, start_prefix, start_words, start_dense) != n_front)
            status = PMX_START_TWICE;
    }
    if (status == PMX_OK) {
        for (int64_t i = 0; i < n_front; i++)
            front_rank[i] = (int32_t)rank_of(start_bits, start_prefix, front[i].start);
        /* A front that tiles [0, V0) starts at 0, so every corner has a
         * front vertex at or before its position (a rank in [0, n_front));
         * one that does not is no refinement's front. */
        if (V0 > 0 && !(start_bits[0] & 1))
            status = PMX_FRONT_NOT_AT_0;
    }
    const int vertex_sorted = ranks_sorted(mode, n_front, vertex_words);
    const int vertex_dense = marked_dense(n_front, vertex_words);
    /* Each drawn face at its rank (in the bitmap, or its place among the
     * drawn faces sorted by id); each corner first the rank of the front
     * vertex holding it (front_index: -1 unused, 0 used). */
    int64_t n_id_count = 0;
    int32_t *row_at = NULL;
    if (status == PMX_OK) {
        memset(front_index, 0xff, sizeof(int32_t) * (size_t)n_front);
        /* Where the faces are sorted, each drawn face's row is its place in
         * the sorted order (row_at, in the sort's other buffer): the faces
         * are then read in the order drawn, and only their rows are written
         * out of order (a store does not wait for its line, where a face
         * read at random would hold up its corners' look-ups). */
        if (face_sorted) {
            row_at = rows_by_id(face_of, total, sort_counts, face_plan, pairs, pairs_to);
            if (!row_at)
                status = PMX_FACE_TWICE;
        } else {
            prefix_marked(face_bits, face_sum, face_words, face_dense, face_prefix, NULL);
            /* Each face's row is its rank: a face drawn twice would leave
             * a row unwritten, so the faces must all differ. */
            if (marked_count(face_bits, face_sum, face_prefix, face_words, face_dense) != total)
                status = PMX_FACE_TWICE;
        }
    }
    if (status == PMX_OK) {
        for (int64_t i = 0; i < total; i++) {
            if (face_sorted && i + FACE_AHEAD < total) {
                const int64_t ahead = i + FACE_AHEAD;
                const PmxFaceRecord *g = ahead < n_drawn ? drawn + ahead : base + (ahead - n_drawn);
                for (int c = 0; c < 3; c++) {
                    __builtin_prefetch(start_bits + (g->start[c] >> 6));
                    __builtin_prefetch(start_prefix + (g->start[c] >> 6));
                }
            }
            const PmxFaceRecord *f = i < n_drawn ? drawn + i : base + (i - n_drawn);
            int32_t *row = faces + 3 * (face_sorted ? (int64_t)row_at[i] : rank_of(face_bits, face_prefix, f->face));
            for (int c = 0; c < 3; c++) {
                int32_t k = (int32_t)(start_dense ? rank_of(start_bits, start_prefix, f->start[c])
                                                  : rank_at_or_before(start_bits, start_sum, start_prefix,
                                                                      start_block, f->start[c]));
                row[c] = k;
                front_index[k] = 0;
            }
        }
        /* The vertices used in increasing id order (the ids' bitmap, or the
         * used ones sorted by id), each front vertex's output index, then
         * the corners through it. The front is read in the order found, each
         * vertex's use looked up at its rank. */
        int64_t n_used = 0;
        int32_t *const id_of = (int32_t *)pairs_to;
        for (int64_t i = 0; i < n_front; i++)
            if (front_index[front_rank[i]] == 0) {
                if (vertex_sorted)
                    id_of[n_used] = front[i].vertex;
                else
                    set_marked(vertex_bits, vertex_sum, front[i].vertex, 1, vertex_dense);
                n_used++;
            }
        /* The outputs' room is checked before anything is written there. */
        if (n_used > id_capacity) {
            status = PMX_BAD_SIZE;
        } else if (vertex_sorted) {
            /* Each used vertex's output index is its row among their ids
             * sorted, the used ones met in the same order as above (the
             * ids must all differ). */
            const int32_t *out_of = rows_by_id(id_of, n_used, sort_counts,
                                               sort_plan(n_used, V0 + n_pcols - 1), pairs, pairs_to);
            int64_t u = 0;
            if (!out_of)
                status = PMX_VERTEX_TWICE;
            for (int64_t i = 0; i < n_front && out_of; i++)
                if (front_index[front_rank[i]] == 0) {
                    const int32_t out = out_of[u++];
                    front_index[front_rank[i]] = out;
                    ids[out] = front[i].vertex;
                    memcpy(vertex_positions + 3 * (int64_t)out, front[i].position, 3 * sizeof(float));
                }
            n_id_count = out_of ? n_used : 0;
        } else {
            prefix_marked(vertex_bits, vertex_sum, vertex_words, vertex_dense, vertex_prefix, NULL);
            /* Each used vertex's output index is its rank: the ids must
             * all differ (an id twice would leave an output unwritten). */
            if (marked_count(vertex_bits, vertex_sum, vertex_prefix, vertex_words, vertex_dense) != n_used)
                status = PMX_VERTEX_TWICE;
            for (int64_t i = 0; i < n_front && status == PMX_OK; i++)
                if (front_index[front_rank[i]] == 0) {
                    int64_t out = rank_of(vertex_bits, vertex_prefix, front[i].vertex);
                    front_index[front_rank[i]] = (int32_t)out;
                    ids[out] = front[i].vertex;
                    memcpy(vertex_positions + 3 * out, front[i].position, 3 * sizeof(float));
                    n_id_count++;
                }
        }
        if (status == PMX_OK)
            for (int64_t i = 0; i < 3 * n_faces_drawn; i++)
                faces[i] = front_index[faces[i]];
    }
    /* Leave the scratch as found (the bitmaps of sorted ranks were not set). */
    for (int64_t i = 0; i < n_not_run; i++)
        mark[not_run_at[i]] = 0;
    clear_marked(start_bits, start_sum, start_words, start_dense);
    if (!face_sorted)
        clear_marked(face_bits, face_sum, face_words, face_dense);
    if (!vertex_sorted)
        clear_marked(vertex_bits, vertex_sum, vertex_words, vertex_dense);
    /* The PMX_BAD_*_RECORD statuses come last (pmx.h). */
    *n_ids = status >= PMX_BAD_PCOL_RECORD ? bad_at : n_id_count;
    return status;
}

/* The level wrappers: popcount in one instruction where the processor has it. */
PmxStatus front_mesh_plain(const PmxMeshTables *m, const uint8_t *ran, const uint16_t *ran_frames, int frame,
                           const int32_t *positions, int64_t n, int64_t n_faces_drawn, int32_t *faces, int32_t *ids,
                           float *vertex_positions, int64_t id_capacity, int64_t *n_ids, PmxScratch *s)
{
    return front_mesh_body(m, ran, ran_frames, frame, positions, n, n_faces_drawn, faces, ids, vertex_positions,
                           id_capacity, n_ids, s);
}
#if PMX_X86
PMX_TARGET_AVX2 PmxStatus front_mesh_avx2(const PmxMeshTables *m, const uint8_t *ran, const uint16_t *ran_frames,
                                          int frame, const int32_t *positions, int64_t n, int64_t n_faces_drawn,
                                          int32_t *faces, int32_t *ids, float *vertex_positions, int64_t id_capacity,
                                          int64_t *n_ids, PmxScratch *s)
{
    return front_mesh_body(m, ran, ran_frames, frame, positions, n, n_faces_drawn, faces, ids, vertex_positions,
                           id_capacity, n_ids, s);
}
PMX_TARGET_AVX512 PmxStatus front_mesh_avx512(const PmxMeshTables *m, const uint8_t *ran, const uint16_t *ran_frames,
                                              int frame, const int32_t *positions, int64_t n, int64_t n_faces_drawn,
                                              int32_t *faces, int32_t *ids, float *vertex_positions,
                                              int64_t id_capacity, int64_t *n_ids, PmxScratch *s)
{
    return front_mesh_body(m, ran, ran_frames, frame, positions, n, n_faces_drawn, faces, ids, vertex_positions,
                           id_capacity, n_ids, s);
}
#endif

PmxStatus pmx_front_mesh(const PmxMeshTables *m, const uint8_t *ran, const uint16_t *ran_frames, int frame,
                         const int32_t *positions, int64_t n, int64_t n_faces_drawn, int32_t *faces, int32_t *ids,
                         float *vertex_positions, int64_t id_capacity, int64_t *n_ids, PmxScratch *s)
{
    if (!scratch_slots(s) || !scratch_mesh(s, m->n_original, m->n_faces))
        return PMX_NO_MEMORY;
    return pmx_kernels()->front_mesh(m, ran, ran_frames, frame, positions, n, n_faces_drawn, faces, ids,
                                     vertex_positions, id_capacity, n_ids, s);
}
