/* Drawable front meshes along a path, each frame a change against the last.
 *
 * The stream holds one frame's mesh in slots that stay put: a face slot per
 * face drawn (its three vertex slots), a vertex slot per front vertex (its
 * id and position). A frame is given by its visited slots and ran bits (the
 * refinement's lists); the pcols whose executed bit differs from the last
 * frame's are found from the two lists (within a word) or from the new list
 * against a bit per pcol not executed in the mesh held, and each is applied
 * as one collapse or one split, so the work follows the change, not the mesh
 * (besides, between lists of different words, a pass over the bits):
 *
 * - a split of p (executed before, not now) hands p's vertex slot to its
 *   first child, gives the second child a new slot, moves the corners lying
 *   in the second child's depth-first interval to it, and draws p's kill list;
 * - a collapse of p (the reverse) removes p's kill list, moves the second
 *   child's corners to the first child's slot, which becomes p's vertex.
 *
 * Collapses run children first (decreasing breadth-first position), splits
 * parents first (increasing): every intermediate state is the refinement of
 * a set closed under children, so each vertex a step reads has its slot.
 * Corners are kept in one list per vertex slot (linked through the corners),
 * so a split or collapse touches only the corners of its vertex. A new
 * face's corner finds its vertex, the front vertex above its original
 * vertex, among the split's two, else from the vertex it had when the face
 * was last removed (still on the front, or split or collapsed since: down
 * or up from it), else among the split's neighbours, else by walking up
 * from its original vertex to the first vertex with a slot.
 *
 * Memory: the slots of one frame's mesh (grown to the largest frame seen,
 * freed slots reused first), the change's slot lists, and maps over the
 * hierarchy (a slot per position and per original vertex, a slot and its
 * third corner's last vertex per killed face, a bit per face and per vertex
 * id), whatever the path's length; for the compaction, its rows (two buffers of an id and a slot per slot) and,
 * once one ran, the log of changes since (at most twice the rows and 1024
 * more). */
#include <stdlib.h>

#include "internal.h"
#if PMX_X86
#include <immintrin.h>
#endif

/* A row of the compacted mesh as the stream keeps it between compactions
 * (a face drawn or a vertex id used: its id and slot), or an entry of the
 * log of changes since (slot -1: the id went): an IdSlot (internal.h). */

/* A corner of a face slot: its depth-first start and its links in its
 * vertex's list, side by side (a split or collapse walks the list reading
 * both); a face's first corner also holds the stamp of the last change
 * that touched the face (beside the corner an edit reads, not in an array
 * of its own). */
typedef struct {
    int32_t start, next, prev;
    uint32_t stamp;
} Corner;

/* A killed face's entry (by its place in kill_data): its face slot while
 * drawn (-1 if not), and the map index of the front vertex of its one
 * corner on neither of the split's two vertices when it was last removed
 * (-1: never drawn), side by side. Its other two corners lie under the
 * split's two children, where a split drawing it again finds them first;
 * the third's search starts from the vertex kept: that vertex is on the
 * front still, or split since (the corner's vertex is below it), or
 * collapsed since (above it). */
typedef struct {
    int32_t slot, index;
} KillEntry;

/* A vertex slot's depth-first interval [lo, hi) of the original vertices
 * below, its first corner and the stamp of the last change that touched
 * it, side by side (a new face's corner reads the intervals of the
 * vertices around it; an edit of the vertex reads them all). */
typedef struct {
    int32_t lo, hi, head;
    uint32_t stamp;
} VertexLinks;

/* The lists a key names: the key with the arrays and length it came with. */
typedef struct {
    int64_t key, n;
    const int32_t *positions;
    const uint16_t *ran16;
} ListsSeen;

PMX_INLINE ListsSeen lists_of(const PmxStreamFrame *f) { return (ListsSeen){f->key, f->n, f->positions, f->ran16}; }

/* Whether two frames' lists are one word's: a key >= 0 given with the same
 * arrays and length (a key given again with other lists names other lists). */
PMX_INLINE int same_lists(ListsSeen a, ListsSeen b)
{
    return a.key >= 0 && a.key == b.key && a.n == b.n && a.positions == b.positions && a.ran16 == b.ran16;
}

struct PmxMeshStream {
    PmxStreamTables t;
    /* Face slots: vertex slots per corner (-1 free), face id (-1 free), each
     * corner's depth-first start and its links in its vertex's list. */
    int32_t *face_vertex, *face_id, *face_free;
    Corner *corner;
    int64_t face_cap, n_face_slots, n_face_free;
    /* Vertex slots: id (-1 free), map index, position, first corner,
     * corners held, the depth-first interval [lo, hi) of the original
     * vertices below. */
    int32_t *vertex_id, *vertex_index, *vertex_free, *vertex_uses, *vertex_rank;
    VertexLinks *links;
    float *vertex_position;
    int64_t vertex_cap, n_vertex_slots, n_vertex_free;
    /* The change since the last step: the slots touched, each once
     * (pmx_mesh_stream_pack writes them with their contents after it). */
    int32_t *face_changes, *vertex_changes;
    int64_t n_face_changes, n_vertex_changes;
    uint32_t stamp;
    int started; /* a step has run: the next one starts a new change */
    /* Maps: the vertex slot at each index (positions, then P + original
     * vertex; -1 off the front), the face slot of each killed face (by its
     * place in kill_data: a pcol's kill list side by side), with its
     * corners' vertices when last removed. */
    int32_t *slot_at;
    KillEntry *kill;
    /* How many corners found their vertex each way (pmx_mesh_stream_searches). */
    int64_t searches[PMX_SEARCHES];
    /* The steps' collapses and splits (positions). */
    int32_t *collapse, *split;
    int64_t step_cap;
    /* The last frame (its arrays held by the caller) and the flips of the
     * word events_of, frame by frame. */
    PmxStreamFrame last;
    int has_last, broken;
    int64_t events_first[FRAMES + 1], events_cap, flipped_cap;
    /* The lists whose positions were checked last (same_lists: a key
     * given with other lists is checked again). */
    ListsSeen checked_lists, events_of;
    int32_t *events, *flipped;
    /* A bit per position: the pcols not executed in the mesh held (split),
     * and those of the next frame's lists while its flips are found. */
    uint64_t *split_bits, *next_split_bits;
    /* For the compacted mesh: a bit per face drawn and per vertex id some
     * face uses (ranks in them are the rows of Refinement.mesh()), and their
     * words' prefix counts. */
    uint64_t *face_bits, *used_bits;
    int32_t *face_prefix, *used_prefix;
    int64_t n_used;
    uint16_t *flipped_bits;
    int64_t n_faces_live, n_vertices_live, generation;
    /* Once a compaction ran: its rows in increasing id (two buffers each:
     * the last and the next), and the log of faces drawn or gone and of
     * vertex ids used or unused since, in the order they came. */
    IdSlot *face_rows[2], *vertex_rows[2], *face_log, *vertex_log, *sorted;
    int64_t n_face_rows, n_vertex_rows, n_face_log, n_vertex_log, face_log_cap, vertex_log_cap, sorted_cap;
    int rows_at, rows_kept;
};

/* An array grown to `cap` elements of `size` bytes, the new part zeroed. */
static int grow(void **p, int64_t old_cap, int64_t cap, size_t size)
{
    void *q = realloc(*p, (size_t)cap * size);
    if (!q)
        return 0;
    memset((char *)q + (size_t)old_cap * size, 0, (size_t)(cap - old_cap) * size);
    *p = q;
    return 1;
}

static int grow_faces(PmxMeshStream *s, int64_t need)
{
    if (need <= s->face_cap)
        return 1;
    int64_t cap = s->face_cap * 2 > need ? s->face_cap * 2 : need < 256 ? 256 : need;
    const int64_t old = s->face_cap;
    if (!grow((void **)&s->face_vertex, 3 * old, 3 * cap, 4) || !grow((void **)&s->face_id, old, cap, 4) ||
        !grow((void **)&s->corner, 3 * old, 3 * cap, sizeof(Corner)) || !grow((void **)&s->face_free, old, cap, 4) ||
        !grow((void **)&s->face_changes, old, cap, 4) ||
        !grow((void **)&s->face_rows[0], old, cap, sizeof(IdSlot)) ||
        !grow((void **)&s->face_rows[1], old, cap, sizeof(IdSlot)))
        return 0;
    s->face_cap = cap;
    s->generation++;
    return 1;
}

static int grow_vertices(PmxMeshStream *s, int64_t need)
{
    if (need <= s->vertex_cap)
        return 1;
    int64_t cap = s->vertex_cap * 2 > need ? s->vertex_cap * 2 : need < 256 ? 256 : need;
    const int64_t old = s->vertex_cap;
    if (!grow((void **)&s->vertex_id, old, cap, 4) || !grow((void **)&s->vertex_index, old, cap, 4) ||
        !grow((void **)&s->links, old, cap, sizeof(VertexLinks)) ||
        !grow((void **)&s->vertex_free, old, cap, 4) || !grow((void **)&s->vertex_position, 3 * old, 3 * cap, 4) ||
        !grow((void **)&s->vertex_changes, old, cap, 4) ||
        !grow((void **)&s->vertex_uses, old, cap, 4) || !grow((void **)&s->vertex_rank, old, cap, 4) ||
        !grow((void **)&s->vertex_rows[0], old, cap, sizeof(IdSlot)) ||
        !grow((void **)&s->vertex_rows[1], old, cap, sizeof(IdSlot)))
        return 0;
    s->vertex_cap = cap;
    s->generation++;
    return 1;
}

PMX_INLINE void touch_face(PmxMeshStream *s, int32_t slot)
{
    if (s->corner[3 * (int64_t)slot].stamp != s->stamp) {
        s->corner[3 * (int64_t)slot].stamp = s->stamp;
        s->face_changes[s->n_face_changes++] = slot;
    }
}

PMX_INLINE void touch_vertex(PmxMeshStream *s, int32_t slot)
{
    if (s->links[slot].stamp != s->stamp) {
        s->links[slot].stamp = s->stamp;
        s->vertex_changes[s->n_vertex_changes++] = slot;
    }
}

PMX_INLINE void flip_bit(uint64_t *bits, int64_t i) { bits[i >> 6] ^= (uint64_t)1 << (i & 63); }
PMX_INLINE void set_bit(uint64_t *bits, int64_t i) { bits[i >> 6] |= (uint64_t)1 << (i & 63); }
PMX_INLINE void clear_bit(uint64_t *bits, int64_t i) { bits[i >> 6] &= ~((uint64_t)1 << (i & 63)); }

/* A change since the last compaction, logged while its rows are kept: a
 * log of twice the rows (and 1024 more), or no memory for it, stops
 * keeping them, and the next compaction ranks afresh. */
static void log_change(PmxMeshStream *s, IdSlot **log, int64_t *n, int64_t *cap, int64_t rows, int32_t id,
                       int32_t slot)
{
    if (*n >= 2 * rows + 1024) { /* past the log's bound: the next compaction ranks */
        s->rows_kept = 0;
        return;
    }
    if (*n == *cap) {
        /* Doubled, but never past the log's bound. */
        const int64_t bound = 2 * rows + 1024, more = *cap ? (2 * *cap < bound ? 2 * *cap : bound) : 1024;
        if (!grow((void **)log, *cap, more, sizeof(IdSlot))) {
            s->rows_kept = 0;
            return;
        }
        *cap = more;
    }
    (*log)[(*n)++] = (IdSlot){id, slot};
}

PMX_INLINE void log_face(PmxMeshStream *s, int32_t id, int32_t slot)
{
    if (s->rows_kept)
        log_change(s, &s->face_log, &s->n_face_log, &s->face_log_cap, s->n_face_rows, id, slot);
}

PMX_INLINE void log_vertex(PmxMeshStream *s, int32_t id, int32_t slot)
{
    if (s->rows_kept)
        log_change(s, &s->vertex_log, &s->n_vertex_log, &s->vertex_log_cap, s->n_vertex_rows, id, slot);
}

/* Vertex slot v holds one corner more (delta 1) or less (-1): its id is
 * used by some face exactly while it holds corners. */
PMX_INLINE void use(PmxMeshStream *s, int32_t v, int32_t delta)
{
    const int32_t before = s->vertex_uses[v];
    s->vertex_uses[v] = before + delta;
    if ((before == 0) != (before + delta == 0)) {
        flip_bit(s->used_bits, s->vertex_id[v]);
        log_vertex(s, s->vertex_id[v], delta > 0 ? v : -1);
        s->n_used += delta > 0 ? 1 : -1;
    }
}

/* Corner c at the head of vertex slot v's list. */
PMX_INLINE void link(PmxMeshStream *s, int32_t c, int32_t v)
{
    const int32_t head = s->links[v].head;
    s->face_vertex[c] = v;
    s->corner[c].prev = -1;
    s->corner[c].next = head;
    if (head >= 0)
        s->corner[head].prev = c;
    s->links[v].head = c;
    use(s, v, 1);
}

PMX_INLINE void unlink(PmxMeshStream *s, int32_t c)
{
    const int32_t prev = s->corner[c].prev, next = s->corner[c].next;
    if (prev >= 0)
        s->corner[prev].next = next;
    else
        s->links[s->face_vertex[c]].head = next;
    if (next >= 0)
        s->corner[next].prev = prev;
    use(s, s->face_vertex[c], -1);
}

PMX_INLINE void set_vertex(PmxMeshStream *s, int32_t slot, int32_t id, const float *position, int32_t lo,
                           int32_t hi)
{
    if (s->vertex_uses[slot] > 0) { /* a used id changes */
        flip_bit(s->used_bits, s->vertex_id[slot]);
        flip_bit(s->used_bits, id);
        log_vertex(s, s->vertex_id[slot], -1);
        log_vertex(s, id, slot);
    }
    s->vertex_id[slot] = id;
    s->links[slot].lo = lo;
    s->links[slot].hi = hi;
    memcpy(s->vertex_position + 3 * (int64_t)slot, position, 3 * sizeof(float));
    touch_vertex(s, slot);
}

/* A vertex slot for the vertex at map index `index`: a freed one first. */
static int32_t new_vertex(PmxMeshStream *s, int64_t index, int32_t id, const float *position, int32_t lo,
                          int32_t hi)
{
    int32_t slot;
    if (s->n_vertex_free)
        slot = s->vertex_free[--s->n_vertex_free];
    else {
        if (!grow_vertices(s, s->n_vertex_slots + 1))
            return -1;
        slot = (int32_t)s->n_vertex_slots++;
    }
    s->links[slot].head = -1;
    s->vertex_uses[slot] = 0;
    s->slot_at[index] = slot;
    s->vertex_index[slot] = (int32_t)index;
    set_vertex(s, slot, id, position, lo, hi);
    s->n_vertices_live++;
    return slot;
}

static void free_vertex(PmxMeshStream *s, int32_t slot)
{
    s->vertex_id[slot] = -1;
    s->links[slot].lo = s->links[slot].hi = 0;
    memset(s->vertex_position + 3 * (int64_t)slot, 0, 3 * sizeof(float));
    s->vertex_free[s->n_vertex_free++] = slot;
    touch_vertex(s, slot);
    s->n_vertices_live--;
}

/* The vertex slot at map index `index` or, off the front, up from it to
 * the first vertex on the front (-1 if none: the state is not a
 * refinement's). */
PMX_INLINE int32_t up_slot(const PmxMeshStream *s, int64_t index)
{
    int32_t slot;
    while ((slot = s->slot_at[index]) < 0) {
        index = s->t.up[index];
        if (index < 0)
            return -1;
    }
    return slot;
}

/* The vertex slot above original vertex v. */
PMX_INLINE int32_t front_slot(const PmxMeshStream *s, int32_t v) { return up_slot(s, s->t.n_pcols + v); }

/* The map index of a pcol record's child j: its pcol's position, or
 * P + the original vertex. */
PMX_INLINE int64_t child_index(const PmxMeshStream *s, const PmxPcolRecord *r, int j)
{
    return r->made_at[j] >= 0 ? r->made_at[j] : s->t.n_pcols + r->vertex[j];
}

/* The vertex slot above the corner at depth-first position `start` whose
 * front vertex was once the one at map index `index`: that vertex if on
 * the front; if split since (its pcol's bit in split_bits), down through
 * the children whose interval holds `start` (the second child's starts at
 * r->start[1]) to the first on the front; else collapsed since, up from it
 * (-1 if none is found: the state is not a refinement's). */
PMX_INLINE int32_t slot_from(const PmxMeshStream *s, int64_t index, int32_t start)
{
    int32_t slot = s->slot_at[index];
    if (slot >= 0)
        return slot;
    if (index < s->t.n_pcols && ((s->split_bits[index >> 6] >> (index & 63)) & 1)) {
        do {
            const PmxPcolRecord *r = s->t.pcols + index;
            index = child_index(s, r, start >= r->start[1]);
            slot = s->slot_at[index];
        } while (slot < 0 && index < s->t.n_pcols);
        return slot;
    }
    return up_slot(s, index);
}

/* The vertex slot above the corner at depth-first position `start`: one of
 * the split's two vertices (v, w; -1 for none), else found from the map
 * index its face's third corner had when last removed (`had`, -1 for none)
 * if the vertex found holds `start` in its interval (anything else, a table
 * that breaks the rule, falls back to the searches below, never to a wrong
 * vertex), else a neighbour of v's or w's (a face killed by a split joins
 * its two vertices to vertices already around them), else up from the
 * corner's original vertex. Each way found counts in s->searches. */
PMX_INLINE int32_t corner_slot(PmxMeshStream *s, int32_t start, int64_t face, int c, int32_t v, int32_t w,
                               int32_t had)
{
    if (v >= 0) {
        if (start >= s->links[v].lo && start < s->links[v].hi) {
            s->searches[PMX_SEARCH_SPLIT]++;
            return v;
        }
        if (start >= s->links[w].lo && start < s->links[w].hi) {
            s->searches[PMX_SEARCH_SPLIT]++;
            return w;
        }
        if (had >= 0) {
            const int32_t u = slot_from(s, had, start);
            if (u >= 0 && start >= s->links[u].lo && start < s->links[u].hi) {
                s->searches[PMX_SEARCH_HAD]++;
                return u;
            }
        }
        const int32_t around[2] = {v, w};
        for (int k = 0; k < 2; k++)
            for (int32_t c = s->links[around[k]].head; c >= 0; c = s->corner[c].next) {
                const int32_t *face = s->face_vertex + 3 * (int64_t)(c / 3);
                for (int j = 0; j < 3; j++) /* -1: a corner of the face being drawn, not linked yet */
                    if (face[j] >= 0 && start >= s->links[face[j]].lo && start < s->links[face[j]].hi) {
                        s->searches[PMX_SEARCH_AROUND]++;
                        return face[j];
                    }
            }
    }
    s->searches[PMX_SEARCH_UP]++;
    return front_slot(s, s->t.corners[3 * (int64_t)face + c]);
}

/* Draws face record f: a face slot (a freed one first, written to its
 * kill entry unless NULL), each corner linked to the front vertex above it
 * (v, w: the vertices of the split drawing it, where two corners lie; the
 * entry's index of the third corner's vertex when it was last removed: the
 * third is searched from there). */
static PmxStatus add_face(PmxMeshStream *s, const PmxFaceRecord *f, KillEntry *at, int32_t v, int32_t w)
{
    int32_t slot;
    if (s->n_face_free)
        slot = s->face_free[--s->n_face_free];
    else {
        /* A refinement draws at most n_faces faces at once, so its slots
         * (freed ones taken first) stay below n_faces: the corners'
         * indices 3 * slot + c then fit int32 (the entries refuse
         * n_faces > INT32_MAX / 3). */
        if (s->n_face_slots >= s->t.n_faces)
            return PMX_BAD_TABLE;
        if (!grow_faces(s, s->n_face_slots + 1))
            return PMX_NO_MEMORY;
        slot = (int32_t)s->n_face_slots++;
    }
    int32_t *const rows = s->face_vertex + 3 * (int64_t)slot;
    rows[0] = rows[1] = rows[2] = -1;
    for (int c = 0; c < 3; c++) {
        const int32_t u = corner_slot(s, f->start[c], f->face, c, v, w, at ? at->index : -1);
        if (u < 0)
            return PMX_BAD_TABLE;
        s->corner[3 * (int64_t)slot + c].start = f->start[c];
        link(s, 3 * slot + c, u);
    }
    s->face_id[slot] = f->face;
    flip_bit(s->face_bits, f->face);
    log_face(s, f->face, slot);
    if (at)
        at->slot = slot;
    touch_face(s, slot);
    s->n_faces_live++;
    return PMX_OK;
}

/* Removes the face of a kill entry, noting in it the map index of the
 * vertex of its corner on neither v nor w (the collapse's two vertices;
 * -1 if every corner is on them). */
static PmxStatus remove_face(PmxMeshStream *s, KillEntry *at, int32_t v, int32_t w)
{
    const int32_t slot = at->slot;
    if (slot < 0)
        return PMX_BAD_TABLE;
    at->slot = -1;
    at->index = -1;
    for (int c = 0; c < 3; c++) {
        const int32_t u = s->face_vertex[3 * (int64_t)slot + c];
        if (u != v && u != w)
            at->index = s->vertex_index[u];
        unlink(s, 3 * slot + c);
        s->face_vertex[3 * (int64_t)slot + c] = -1;
    }
    flip_bit(s->face_bits, s->face_id[slot]);
    log_face(s, s->face_id[slot], -1);
    s->face_id[slot] = -1;
    s->face_free[s->n_face_free++] = slot;
    touch_face(s, slot);
    s->n_faces_live--;
    return PMX_OK;
}

/* The pcol at position `at` not executed any more: its vertex splits in two. */
static PmxStatus split(PmxMeshStream *s, int32_t at)
{
    const PmxPcolRecord *r = s->t.pcols + at;
    const int32_t v = s->slot_at[at];
    if (v < 0)
        return PMX_BAD_TABLE;
    s->slot_at[at] = -1;
    set_bit(s->split_bits, at);
    /* The first child keeps the slot; the second gets one. */
    s->vertex_index[v] = (int32_t)child_index(s, r, 0);
    s->slot_at[s->vertex_index[v]] = v;
    /* The first child's interval ends where the second's starts. */
    const int32_t end = s->links[v].hi;
    set_vertex(s, v, r->vertex[0], r->position[0], r->start[0], r->start[1]);
    const int32_t w = new_vertex(s, child_index(s, r, 1), r->vertex[1], r->position[1], r->start[1], end);
    if (w < 0)
        return PMX_NO_MEMORY;
    /* The corners in the second child's interval (it follows the first's)
     * move to it; their faces change. One walk of v's list splits it: the
     * corners kept stay in order, each one moved goes to the head of w's
     * (the lists one unlink and link per corner would give), and the uses
     * move at once. */
    const int32_t second = r->start[1];
    Corner *const corner = s->corner;
    int32_t kept = -1, moved = -1, n_moved = 0;
    for (int32_t c = s->links[v].head, next; c >= 0; c = next) {
        next = corner[c].next;
        if (corner[c].start >= second) {
            s->face_vertex[c] = w;
            corner[c].prev = -1;
            corner[c].next = moved;
            if (moved >= 0)
                corner[moved].prev = c;
            moved = c;
            n_moved++;
            touch_face(s, c / 3);
        } else {
            corner[c].prev = kept;
            if (kept >= 0)
                corner[kept].next = c;
            else
                s->links[v].head = c;
            kept = c;
        }
    }
    if (kept >= 0)
        corner[kept].next = -1;
    else
        s->links[v].head = -1;
    s->links[w].head = moved;
    if (n_moved) {
        use(s, w, n_moved);
        use(s, v, -n_moved);
    }
    /* Its kill list is drawn again. */
    for (int32_t j = 0; j < r->kill_count; j++) {
        PmxStatus status = add_face(s, s->t.kill_data + r->kill_first + j, s->kill + r->kill_first + j, v, w);
        if (status != PMX_OK)
            return status;
    }
    return PMX_OK;
}

/* The pcol at position `at` executed again: its two vertices merge. */
static PmxStatus collapse(PmxMeshStream *s, int32_t at)
{
    const PmxPcolRecord *r = s->t.pcols + at;
    const int64_t first = child_index(s, r, 0), second = child_index(s, r, 1);
    const int32_t v = s->slot_at[first], w = s->slot_at[second];
    if (v < 0 || w < 0)
        return PMX_BAD_TABLE;
    /* Its kill list goes. */
    for (int32_t j = 0; j < r->kill_count; j++) {
        PmxStatus status = remove_face(s, s->kill + r->kill_first + j, v, w);
        if (status != PMX_OK)
            return status;
    }
    /* The second child's corners join the first's list, whose slot becomes
     * the pcol's vertex. */
    int32_t last = -1;
    for (int32_t c = s->links[w].head; c >= 0; c = s->corner[c].next) {
        s->face_vertex[c] = v;
        touch_face(s, c / 3);
        last = c;
    }
    if (last >= 0) {
        const int32_t moved = s->vertex_uses[w];
        use(s, w, -moved);
        use(s, v, moved);
        const int32_t head = s->links[v].head;
        s->corner[last].next = head;
        if (head >= 0)
            s->corner[head].prev = last;
        s->links[v].head = s->links[w].head;
        s->links[w].head = -1;
    }
    const int32_t end = s->links[w].hi;
    free_vertex(s, w);
    s->slot_at[second] = -1;
    s->slot_at[first] = -1;
    s->slot_at[at] = v;
    s->vertex_index[v] = at;
    clear_bit(s->split_bits, at);
    set_vertex(s, v, s->t.own_vertex[at], s->t.own_position + 3 * (int64_t)at, s->links[v].lo, end);
    return PMX_OK;
}

void pmx_mesh_stream_free(PmxMeshStream *s)
{
    if (!s)
        return;
    void *arrays[] = {s->face_vertex, s->face_id, s->corner, s->face_free, s->vertex_id, s->vertex_index,
                      s->links, s->vertex_free, s->vertex_uses, s->vertex_rank, s->vertex_position,
                      s->face_changes, s->vertex_changes, s->slot_at, s->kill,
                      s->collapse, s->split, s->events, s->flipped, s->flipped_bits, s->split_bits,
                      s->next_split_bits, s->face_bits,
                      s->used_bits, s->face_prefix, s->used_prefix, s->face_rows[0], s->face_rows[1], s->vertex_rows[0],
                      s->vertex_rows[1], s->face_log, s->vertex_log, s->sorted};
    for (size_t i = 0; i < sizeof arrays / sizeof arrays[0]; i++)
        free(arrays[i]);
    free(s);
}

PmxMeshStream *pmx_mesh_stream_new(const PmxStreamTables *t, PmxStatus *status)
{
    PmxMeshStream *s = calloc(1, sizeof *s);
    *status = PMX_NO_MEMORY;
    if (!s)
        return NULL;
    s->t = *t;
    s->stamp = 1;
    s->events_of.key = -1;
    s->checked_lists.key = -1;
    const int64_t P = t->n_pcols, V0 = t->n_original;
    s->slot_at = malloc(sizeof(int32_t) * (size_t)(P + V0 + 1));
    s->kill = malloc(sizeof(KillEntry) * (size_t)(t->n_kill_data + 1));
    const size_t face_words = (size_t)t->n_faces / 64 + 1, used_words = (size_t)(V0 + P) / 64 + 1;
    s->face_bits = calloc(face_words, sizeof(uint64_t));
    s->used_bits = calloc(used_words, sizeof(uint64_t));
    s->split_bits = calloc((size_t)P / 64 + 1, sizeof(uint64_t));
    s->next_split_bits = calloc((size_t)P / 64 + 1, sizeof(uint64_t));
    s->face_prefix = malloc(face_words * sizeof(int32_t));
    s->used_prefix = malloc(used_words * sizeof(int32_t));
    if (!s->slot_at || !s->kill || !s->face_bits || !s->used_bits || !s->face_prefix || !s->used_prefix ||
        !s->split_bits || !s->next_split_bits) {
        pmx_mesh_stream_free(s);
        return NULL;
    }
    memset(s->slot_at, 0xff, sizeof(int32_t) * (size_t)(P + V0 + 1));
    memset(s->kill, 0xff, sizeof(KillEntry) * (size_t)(t->n_kill_data + 1));
    /* The start: every pcol executed, the tops on the front, the base faces. */
    for (int64_t i = 0; i < t->n_tops; i++) {
        const int64_t index = t->top_at[i] >= 0 ? t->top_at[i] : P + t->tops[i].vertex;
        const int32_t end = t->top_at[i] >= 0 ? t->own_end[t->top_at[i]] : t->tops[i].start + 1;
        if (new_vertex(s, index, t->tops[i].vertex, t->tops[i].position, t->tops[i].start, end) < 0) {
            pmx_mesh_stream_free(s);
            return NULL;
        }
    }
    for (int64_t i = 0; i < t->n_base; i++)
        if ((*status = add_face(s, t->base + i, NULL, -1, -1)) != PMX_OK) {
            pmx_mesh_stream_free(s);
            return NULL;
        }
    *status = PMX_OK;
    return s;
}

PMX_INLINE int ran_of(const PmxStreamFrame *f, int64_t i)
{
    return f->ran8 ? f->ran8[i] != 0 : (f->ran16[i] >> f->frame) & 1;
}

static int grow_steps(PmxMeshStream *s, int64_t need)
{
    if (need <= s->step_cap)
        return 1;
    if (!grow((void **)&s->collapse, s->step_cap, need, 4) || !grow((void **)&s->split, s->step_cap, need, 4))
        return 0;
    s->step_cap = need;
    return 1;
}

/* Whether a list's n positions increase inside [0, P): its ends inside,
 * each step up (a reduction without branches, vectorized). */
static int increasing(const int32_t *positions, int64_t n, int64_t P)
{
    if (n == 0)
        return 1;
    int ok = (positions[0] >= 0) & (positions[n - 1] < P);
    for (int64_t i = 1; i < n; i++)
        ok &= positions[i] > positions[i - 1];
    return ok;
}

/* increasing() of a frame's list, once per key: the frames of a word share
 * their lists. */
static int checked(PmxMeshStream *s, const PmxStreamFrame *f)
{
    if (same_lists(lists_of(f), s->checked_lists))
        return 1;
    if (!increasing(f->positions, f->n, s->t.n_pcols))
        return 0;
    s->checked_lists = lists_of(f);
    return 1;
}

/* A word's flips: for each frame f > 0, the slots whose bit differs from
 * frame f - 1's, in slot order (events_first[f] .. events_first[f + 1]).
 * One pass over the word's slots serves its 16 frames. */
static PmxStatus word_events(PmxMeshStream *s, const PmxStreamFrame *f)
{
    if (!checked(s, f))
        return PMX_BAD_SIZE;
    int64_t n_flipped = 0;
    /* The slots that flip in some frame, with their frames' bits: most
     * slots do not, and are passed over without a branch. */
    if (f->n + 1 > s->flipped_cap) {
        if (!grow((void **)&s->flipped, s->flipped_cap, f->n + 1, 4) ||
            !grow((void **)&s->flipped_bits, s->flipped_cap, f->n + 1, 2))
            return PMX_NO_MEMORY;
        s->flipped_cap = f->n + 1;
    }
    for (int64_t i = 0; i < f->n; i++) {
        const uint16_t bits = f->ran16[i];
        const uint16_t flips = (uint16_t)((bits ^ (bits << 1)) & 0xfffe);
        s->flipped[n_flipped] = (int32_t)i;
        s->flipped_bits[n_flipped] = flips;
        n_flipped += flips != 0;
    }
    /* Bucketed by frame: counts, offsets, then the slots in order. */
    int64_t count[FRAMES + 1] = {0}, total = 0;
    for (int64_t k = 0; k < n_flipped; k++)
        for (uint32_t d = s->flipped_bits[k]; d; d &= d - 1)
            count[__builtin_ctz(d)]++;
    for (int j = 0; j < FRAMES; j++) {
        s->events_first[j] = total;
        total += count[j];
    }
    s->events_first[FRAMES] = total;
    if (total > s->events_cap) {
        if (!grow((void **)&s->events, s->events_cap, total, 4))
            return PMX_NO_MEMORY;
        s->events_cap = total;
    }
    int64_t at[FRAMES];
    memcpy(at, s->events_first, sizeof at);
    for (int64_t k = 0; k < n_flipped; k++)
        for (uint32_t d = s->flipped_bits[k]; d; d &= d - 1)
            s->events[at[__builtin_ctz(d)]++] = s->flipped[k];
    s->events_of = lists_of(f);
    return PMX_OK;
}

/* The collapses and splits from frame `last` to `next`, in increasing
 * position. */
static PmxStatus flips(PmxMeshStream *s, const PmxStreamFrame *last, const PmxStreamFrame *next,
                       int64_t *n_collapses, int64_t *n_splits)
{
    int32_t *const collapses = s->collapse, *const splits = s->split;
    int64_t nc = 0, ns = 0;
    if (last && next->ran16 && same_lists(lists_of(next), lists_of(last))) {
        /* The same word: its flips once for all its frames; the next frame
         * reads its own. Frames further apart compare their bits. */
        if (!same_lists(lists_of(next), s->events_of)) {
            PmxStatus status = word_events(s, next);
            if (status != PMX_OK)
                return status;
        }
        if (next->frame == last->frame + 1) {
            for (int64_t k = s->events_first[next->frame]; k < s->events_first[next->frame + 1]; k++) {
                const int32_t i = s->events[k];
                collapses[nc] = splits[ns] = next->positions[i];
                const int ran = ran_of(next, i);
                nc += ran;
                ns += !ran;
            }
        } else {
            for (int64_t i = 0; i < next->n; i++) {
                const int a = ran_of(last, i), b = ran_of(next, i);
                collapses[nc] = splits[ns] = next->positions[i];
                nc += (!a) & b;
                ns += a & (!b);
            }
        }
    } else {
        /* Other lists: the next frame's pcols that did not run, as bits
         * (a pcol its list leaves out ran: it lies under a decided
         * subtree), against the bits of the mesh held; a position set in
         * one only flips, and a pass over the words finds them in
         * increasing position. */
        if (!checked(s, next))
            return PMX_BAD_SIZE;
        const int64_t n_words = s->t.n_pcols / 64 + 1;
        uint64_t *const held = s->split_bits, *const bits = s->next_split_bits;
        memset(bits, 0, sizeof(uint64_t) * (size_t)n_words);
        /* The positions increase: a word's bits gather in a register,
         * stored at every slot without a branch (its last store holds
         * them all), with no read of the word back. */
        const int32_t *const b = next->positions;
        uint64_t gathered = 0;
        int64_t at = -1;
        if (next->ran8)
            for (int64_t j = 0; j < next->n; j++) {
                const int64_t word = b[j] >> 6;
                gathered = (word == at ? gathered : 0) | (uint64_t)(next->ran8[j] == 0) << (b[j] & 63);
                bits[word] = gathered;
                at = word;
            }
        else
            for (int64_t j = 0; j < next->n; j++) {
                const int64_t word = b[j] >> 6;
                gathered = (word == at ? gathered : 0) |
                           (uint64_t)(((next->ran16[j] >> next->frame) & 1) ^ 1) << (b[j] & 63);
                bits[word] = gathered;
                at = word;
            }
        for (int64_t k = 0; k < n_words; k++) {
            for (uint64_t d = held[k] & ~bits[k]; d; d &= d - 1)
                collapses[nc++] = (int32_t)(64 * k + __builtin_ctzll(d));
            for (uint64_t d = bits[k] & ~held[k]; d; d &= d - 1)
                splits[ns++] = (int32_t)(64 * k + __builtin_ctzll(d));
        }
    }
    *n_collapses = nc;
    *n_splits = ns;
    return PMX_OK;
}

/* Requests the rows of vertex slot v (-1: none) that a flip reads. */
PMX_INLINE void prefetch_vertex(const PmxMeshStream *s, int32_t v)
{
    if (v < 0)
        return;
    __builtin_prefetch(s->links + v);
    __builtin_prefetch(s->vertex_id + v);
    __builtin_prefetch(s->vertex_uses + v);
    __builtin_prefetch(s->vertex_position + 3 * (int64_t)v);
}

/* Requests what a collapse at `at` reads once its record is in: its kill
 * list's slots and its children's vertex slots. */
PMX_INLINE void prefetch_collapse_lists(const PmxMeshStream *s, int32_t at)
{
    const PmxPcolRecord *r = s->t.pcols + at;
    __builtin_prefetch(s->kill + r->kill_first);
    __builtin_prefetch(s->slot_at + child_index(s, r, 0));
    __builtin_prefetch(s->slot_at + child_index(s, r, 1));
}

/* Requests the rows a collapse at `at` reads once its lists are in: its
 * children's vertex rows and its kill list's face slots. */
PMX_INLINE void prefetch_collapse_slots(const PmxMeshStream *s, int32_t at)
{
    const PmxPcolRecord *r = s->t.pcols + at;
    prefetch_vertex(s, s->slot_at[child_index(s, r, 0)]);
    prefetch_vertex(s, s->slot_at[child_index(s, r, 1)]);
    for (int32_t j = 0; j < r->kill_count && j < 4; j++) {
        const int32_t slot = s->kill[r->kill_first + j].slot;
        if (slot >= 0) {
            __builtin_prefetch(s->corner + 3 * (int64_t)slot);
            __builtin_prefetch(s->face_vertex + 3 * (int64_t)slot);
        }
    }
}

PmxStatus pmx_mesh_stream_step(PmxMeshStream *s, const PmxStreamFrame *next)
{
    if (s->broken)
        return PMX_BAD_TABLE;
    /* A new change: the slots touched from here on. */
    if (s->started) {
        if (++s->stamp == 0) { /* wrapped: no slot may hold the new stamp */
            for (int64_t i = 0; i < s->face_cap; i++)
                s->corner[3 * i].stamp = 0;
            for (int64_t i = 0; i < s->vertex_cap; i++)
                s->links[i].stamp = 0;
            s->stamp = 1;
        }
        s->n_face_changes = s->n_vertex_changes = 0;
    }
    s->started = 1;
    const PmxStreamFrame *last = s->has_last ? &s->last : NULL;
    if (!grow_steps(s, (last ? last->n : 0) + next->n + 1))
        return PMX_NO_MEMORY;
    int64_t n_collapses = 0, n_splits = 0;
    PmxStatus status = flips(s, last, next, &n_collapses, &n_splits);
    if (status != PMX_OK)
        return status; /* nothing changed yet: the stream still holds the last frame */
    /* Children collapse before their parents, parents split before their
     * children. A failure here leaves a state no frame has: the stream is
     * broken. */
    const PmxPcolRecord *const records = s->t.pcols;
    const int32_t *const collapses = s->collapse, *const splits = s->split;
    /* Each flip's record, kill list and slots are misses in tables far
     * larger than the cache: requested in stages ahead of the flip, each
     * once what it needs is in (a record FLIPS_AHEAD flips early, with its
     * position's slot; its kill list and children's slots half as early;
     * the rows of the slots it reads a quarter as early), so the misses
     * overlap. A stage reads the stream as the earlier flips leave it,
     * which only makes a request useless, never wrong. */
    enum { FLIPS_AHEAD = 8 };
    for (int64_t i = n_collapses - 1; i >= n_collapses - FLIPS_AHEAD && i >= 0; i--)
        __builtin_prefetch(records + collapses[i]);
    for (int64_t i = n_collapses - 1; i >= 0 && status == PMX_OK; i--) {
        if (i >= FLIPS_AHEAD)
            __builtin_prefetch(records + collapses[i - FLIPS_AHEAD]);
        if (i >= FLIPS_AHEAD / 2)
            prefetch_collapse_lists(s, collapses[i - FLIPS_AHEAD / 2]);
        if (i >= FLIPS_AHEAD / 4)
            prefetch_collapse_slots(s, collapses[i - FLIPS_AHEAD / 4]);
        status = collapse(s, collapses[i]);
    }
    for (int64_t i = 0; i < FLIPS_AHEAD && i < n_splits; i++) {
        __builtin_prefetch(records + splits[i]);
        __builtin_prefetch(s->slot_at + splits[i]);
    }
    for (int64_t i = 0; i < n_splits && status == PMX_OK; i++) {
        if (i + FLIPS_AHEAD < n_splits) {
            __builtin_prefetch(records + splits[i + FLIPS_AHEAD]);
            __builtin_prefetch(s->slot_at + splits[i + FLIPS_AHEAD]);
        }
        if (i + FLIPS_AHEAD / 2 < n_splits) {
            const int32_t first = records[splits[i + FLIPS_AHEAD / 2]].kill_first;
            __builtin_prefetch(s->t.kill_data + first);
            __builtin_prefetch(s->kill + first);
        }
        if (i + FLIPS_AHEAD / 4 < n_splits)
            prefetch_vertex(s, s->slot_at[splits[i + FLIPS_AHEAD / 4]]);
        status = split(s, splits[i]);
    }
    if (status != PMX_OK) {
        s->broken = 1;
        return status;
    }
    s->last = *next;
    s->has_last = 1;
    return PMX_OK;
}

PmxStatus pmx_mesh_stream_lane(PmxMeshStream *s, int frame)
{
    /* The lists of the frame held, read at another of its word's bits. */
    if (!s->has_last || !s->last.ran16 || s->last.key < 0 || frame < 0 || frame >= FRAMES)
        return PMX_BAD_SIZE;
    PmxStreamFrame next = s->last;
    next.frame = frame;
    return pmx_mesh_stream_step(s, &next);
}

void pmx_mesh_stream_pack(const PmxMeshStream *s, void *out)
{
    /* The slots touched, then their rows (read through the slots), each
     * array after the last: int32 face slots [k], faces [k, 3], vertex
     * slots [u], ids [u], float positions [u, 3]. */
    const int64_t k = s->n_face_changes, u = s->n_vertex_changes;
    int32_t *const face_slots = out, *const faces = face_slots + k, *const vertex_slots = faces + 3 * k,
                   *const ids = vertex_slots + u;
    float *const positions = (float *)(ids + u);
    if (k)
        memcpy(face_slots, s->face_changes, (size_t)k * sizeof(int32_t));
    for (int64_t i = 0; i < k; i++)
        memcpy(faces + 3 * i, s->face_vertex + 3 * (int64_t)s->face_changes[i], 3 * sizeof(int32_t));
    if (u)
        memcpy(vertex_slots, s->vertex_changes, (size_t)u * sizeof(int32_t));
    for (int64_t i = 0; i < u; i++) {
        const int32_t v = s->vertex_changes[i];
        ids[i] = s->vertex_id[v];
        memcpy(positions + 3 * i, s->vertex_position + 3 * (int64_t)v, 3 * sizeof(float));
    }
}

void pmx_mesh_stream_state(const PmxMeshStream *s, PmxStreamState *out)
{
    out->face_vertex = s->face_vertex;
    out->face_id = s->face_id;
    out->vertex_id = s->vertex_id;
    out->vertex_position = s->vertex_position;
    out->face_cap = s->face_cap;
    out->vertex_cap = s->vertex_cap;
    out->n_face_slots = s->n_face_slots;
    out->n_vertex_slots = s->n_vertex_slots;
    out->n_face_changes = s->n_face_changes;
    out->n_vertex_changes = s->n_vertex_changes;
    out->n_faces = s->n_faces_live;
    out->n_vertices = s->n_vertices_live;
    out->n_used = s->n_used;
    out->generation = s->generation;
}

void pmx_mesh_stream_searches(const PmxMeshStream *s, int64_t out[PMX_SEARCHES])
{
    memcpy(out, s->searches, sizeof s->searches);
}

/* The stream keeps a bit per face drawn and per vertex id used: a face's row
 * is the rank of its id among the faces drawn, a vertex's the rank of its id
 * among those used, as Refinement.mesh() orders them. The first compaction
 * (or one after a long log) ranks every slot in the two bitmaps' words and
 * keeps the rows (id and slot, in increasing id); the next ones merge the
 * rows kept with the log of changes since, so that they read the mesh's
 * rows in order and the changes, not the bitmaps. */
PMX_INLINE void rank_rows(PmxMeshStream *s, IdSlot *restrict face_rows, IdSlot *restrict vertex_rows)
{
    /* The stream's arrays and counts in locals: the rows written cannot
     * change them, so nothing is read again after each store. */
    const uint64_t *const face_bits = s->face_bits, *const used_bits = s->used_bits;
    int32_t *const face_prefix = s->face_prefix, *const used_prefix = s->used_prefix;
    const int32_t *const face_id = s->face_id, *const vertex_id = s->vertex_id, *const uses = s->vertex_uses;
    const int64_t n_vertex_slots = s->n_vertex_slots, n_face_slots = s->n_face_slots;
    prefix_counts(face_bits, s->t.n_faces / 64 + 1, face_prefix);
    prefix_counts(used_bits, (s->t.n_original + s->t.n_pcols) / 64 + 1, used_prefix);
    for (int64_t slot = 0; slot < n_vertex_slots; slot++)
        if (vertex_id[slot] >= 0 && uses[slot] > 0)
            vertex_rows[rank_of(used_bits, used_prefix, vertex_id[slot])] = (IdSlot){vertex_id[slot], (int32_t)slot};
    for (int64_t slot = 0; slot < n_face_slots; slot++)
        if (face_id[slot] >= 0)
            face_rows[rank_of(face_bits, face_prefix, face_id[slot])] = (IdSlot){face_id[slot], (int32_t)slot};
}

/* Popcount in one instruction where the processor has it. */
static void rank_rows_plain(PmxMeshStream *s, IdSlot *face_rows, IdSlot *vertex_rows)
{
    rank_rows(s, face_rows, vertex_rows);
}
#if PMX_X86
__attribute__((target("popcnt"))) static void rank_rows_popcnt(PmxMeshStream *s, IdSlot *face_rows,
                                                               IdSlot *vertex_rows)
{
    rank_rows(s, face_rows, vertex_rows);
}
#endif

/* The log's n entries in increasing id, entries of one id in the order
 * they came, through s->sorted, whose room the caller made (byte digits: a
 * log usually holds a few frames' changes, at most twice the rows and 1024
 * more, and its ids need up to four passes); returns the sorted entries
 * (the log or s->sorted). */
static IdSlot *sort_log(PmxMeshStream *s, IdSlot *log, int64_t n, int32_t max_id)
{
    return sort_id_slots(log, s->sorted, n, max_id, 8);
}

/* The next rows (at most cap): the last ones (n_last, increasing id)
 * merged with the sorted log's ids, an id's row now (its last entry, which
 * drew it) where its bit is set, none where it is not. Their count; -1
 * where the log does not match the bits (more rows than cap, or an id set
 * whose last entry is not a slot). */
static int64_t merge_log(const IdSlot *last, int64_t n_last, const IdSlot *log, int64_t n_log,
                         const uint64_t *bits, IdSlot *rows, int64_t cap)
{
    enum { SKIP = 8 };
    int64_t i = 0, n = 0;
    for (int64_t k = 0; k < n_log; k++) {
        const int32_t id = log[k].id;
        if (k + 1 < n_log && log[k + 1].id == id)
            continue; /* a later entry of the id: its slot now */
        /* The last rows below the id, kept: found a run of SKIP rows at a
         * time (the log is sparse among the rows, so most runs are passed
         * whole), then row by row. */
        int64_t j = i;
        while (j + SKIP < n_last && last[j + SKIP].id < id)
            j += SKIP;
        while (j < n_last && last[j].id < id)
            j++;
        if (n + j - i > cap)
            return -1;
        memcpy(rows + n, last + i, (size_t)(j - i) * sizeof *rows);
        n += j - i;
        i = j + (j < n_last && last[j].id == id);
        if ((bits[id >> 6] >> (id & 63)) & 1) {
            if (n == cap || log[k].slot < 0)
                return -1;
            rows[n++] = log[k];
        }
    }
    if (n + n_last - i > cap)
        return -1;
    memcpy(rows + n, last + i, (size_t)(n_last - i) * sizeof *rows);
    return n + n_last - i;
}

/* Vertices out, rows `from` to n: row k is the vertex id and position of
 * slot rows[k].slot, and the slot's row is noted (rank). */
static void vertex_rows_out_plain(const IdSlot *rows, int64_t from, int64_t n, const float *vertex_position,
                                  int32_t *restrict ids, float *restrict positions, int32_t *restrict rank)
{
    for (int64_t k = from; k < n; k++) {
        const int32_t slot = rows[k].slot;
        ids[k] = rows[k].id;
        memcpy(positions + 3 * k, vertex_position + 3 * (int64_t)slot, 3 * sizeof(float));
        rank[slot] = (int32_t)k;
    }
}

#if PMX_X86
/* The same rows four vertices at a time: four ids in one store, the twelve
 * coordinates loaded into three vectors (no load past a slot's three) and
 * stored whole. */
__attribute__((target("sse4.1"))) static void vertex_rows_out_sse(const IdSlot *rows, int64_t n,
                                                                const float *vertex_position, int32_t *restrict ids,
                                                                float *restrict positions, int32_t *restrict rank)
{
    int64_t k = 0;
    for (; k + 4 <= n; k += 4) {
        const __m128i lo = _mm_loadu_si128((const __m128i *)(rows + k)),
                      hi = _mm_loadu_si128((const __m128i *)(rows + k + 2));
        /* rows: id, slot, id, slot | id, slot, id, slot */
        _mm_storeu_si128((__m128i *)(ids + k), _mm_castps_si128(_mm_shuffle_ps(_mm_castsi128_ps(lo),
                                                                               _mm_castsi128_ps(hi), 0x88)));
        const int32_t s0 = _mm_extract_epi32(lo, 1), s1 = _mm_extract_epi32(lo, 3), s2 = _mm_extract_epi32(hi, 1),
                      s3 = _mm_extract_epi32(hi, 3);
        const float *a = vertex_position + 3 * (int64_t)s0, *b = vertex_position + 3 * (int64_t)s1,
                    *c = vertex_position + 3 * (int64_t)s2, *d = vertex_position + 3 * (int64_t)s3;
        /* a.xyz b.x | b.yz c.xy | c.z d.xyz */
        __m128 x = _mm_castsi128_ps(_mm_loadl_epi64((const __m128i *)a));
        x = _mm_insert_ps(x, _mm_load_ss(a + 2), 0x20);
        x = _mm_insert_ps(x, _mm_load_ss(b), 0x30);
        const __m128 y = _mm_castsi128_ps(
            _mm_unpacklo_epi64(_mm_loadl_epi64((const __m128i *)(b + 1)), _mm_loadl_epi64((const __m128i *)c)));
        __m128 z = _mm_load_ss(c + 2);
        z = _mm_insert_ps(z, _mm_load_ss(d), 0x10);
        z = _mm_insert_ps(z, _mm_load_ss(d + 1), 0x20);
        z = _mm_insert_ps(z, _mm_load_ss(d + 2), 0x30);
        _mm_storeu_ps(positions + 3 * k, x);
        _mm_storeu_ps(positions + 3 * k + 4, y);
        _mm_storeu_ps(positions + 3 * k + 8, z);
        rank[s0] = (int32_t)k;
        rank[s1] = (int32_t)k + 1;
        rank[s2] = (int32_t)k + 2;
        rank[s3] = (int32_t)k + 3;
    }
    vertex_rows_out_plain(rows, k, n, vertex_position, ids, positions, rank);
}
#endif

/* Faces out: row k is the face in slot rows[k].slot, its corners as the
 * rows of their vertex slots (rank). */
static void face_rows_out_plain(const IdSlot *rows, int64_t n, const int32_t *face_vertex, const int32_t *rank,
                                int32_t *restrict faces)
{
    for (int64_t k = 0; k < n; k++) {
        const int32_t *corner = face_vertex + 3 * (int64_t)rows[k].slot;
        faces[3 * k] = rank[corner[0]];
        faces[3 * k + 1] = rank[corner[1]];
        faces[3 * k + 2] = rank[corner[2]];
    }
}

#if PMX_X86
/* The same rows four faces at a time: their twelve corners' rows loaded
 * straight into three vectors, stored whole (three stores, not twelve: the
 * loop does no arithmetic, only loads and stores). */
__attribute__((target("sse4.1"))) static void face_rows_out_sse(const IdSlot *rows, int64_t n,
                                                              const int32_t *face_vertex, const int32_t *rank,
                                                              int32_t *restrict faces)
{
    int64_t k = 0;
    for (; k + 4 <= n; k += 4) {
        const int32_t *a = face_vertex + 3 * (int64_t)rows[k].slot, *b = face_vertex + 3 * (int64_t)rows[k + 1].slot,
                      *c = face_vertex + 3 * (int64_t)rows[k + 2].slot, *d = face_vertex + 3 * (int64_t)rows[k + 3].slot;
        __m128i x = _mm_cvtsi32_si128(rank[a[0]]), y = _mm_cvtsi32_si128(rank[b[1]]),
                z = _mm_cvtsi32_si128(rank[c[2]]);
        x = _mm_insert_epi32(x, rank[a[1]], 1);
        x = _mm_insert_epi32(x, rank[a[2]], 2);
        x = _mm_insert_epi32(x, rank[b[0]], 3);
        y = _mm_insert_epi32(y, rank[b[2]], 1);
        y = _mm_insert_epi32(y, rank[c[0]], 2);
        y = _mm_insert_epi32(y, rank[c[1]], 3);
        z = _mm_insert_epi32(z, rank[d[0]], 1);
        z = _mm_insert_epi32(z, rank[d[1]], 2);
        z = _mm_insert_epi32(z, rank[d[2]], 3);
        _mm_storeu_si128((__m128i *)(faces + 3 * k), x);
        _mm_storeu_si128((__m128i *)(faces + 3 * k + 4), y);
        _mm_storeu_si128((__m128i *)(faces + 3 * k + 8), z);
    }
    face_rows_out_plain(rows + k, n - k, face_vertex, rank, faces + 3 * k);
}
#endif

PmxStatus pmx_mesh_stream_compact(PmxMeshStream *s, int32_t *restrict faces, int32_t *restrict ids,
                                  float *restrict positions)
{
    if (s->broken)
        return PMX_BAD_TABLE;
    /* The next rows in the buffers not holding the last ones. */
    const int next = !s->rows_at;
    IdSlot *const face_rows = s->face_rows[next], *const vertex_rows = s->vertex_rows[next];
    int merged = 0;
    if (s->rows_kept) {
        /* Room to sort the longer log first: a failure changes nothing. */
        const int64_t need = s->n_face_log > s->n_vertex_log ? s->n_face_log : s->n_vertex_log;
        if (need > s->sorted_cap) {
            if (!grow((void **)&s->sorted, s->sorted_cap, need, sizeof(IdSlot)))
                return PMX_NO_MEMORY;
            s->sorted_cap = need;
        }
        const IdSlot *log = sort_log(s, s->vertex_log, s->n_vertex_log,
                                     (int32_t)(s->t.n_original + s->t.n_pcols));
        s->n_vertex_rows = merge_log(s->vertex_rows[s->rows_at], s->n_vertex_rows, log, s->n_vertex_log,
                                     s->used_bits, vertex_rows, s->vertex_cap);
        log = sort_log(s, s->face_log, s->n_face_log, (int32_t)s->t.n_faces);
        s->n_face_rows = merge_log(s->face_rows[s->rows_at], s->n_face_rows, log, s->n_face_log, s->face_bits,
                                   face_rows, s->face_cap);
        merged = s->n_face_rows == s->n_faces_live && s->n_vertex_rows == s->n_used;
    }
    /* No rows kept, or a merge that does not give as many rows as the
     * output holds (the faces drawn, the ids used): ranked afresh. */
    if (!merged) {
#if PMX_X86
        if (__builtin_cpu_supports("popcnt"))
            rank_rows_popcnt(s, face_rows, vertex_rows);
        else
#endif
            rank_rows_plain(s, face_rows, vertex_rows);
        s->n_face_rows = s->n_faces_live;
        s->n_vertex_rows = s->n_used;
    }
    s->n_face_log = s->n_vertex_log = 0;
    s->rows_at = next;
    s->rows_kept = 1;
    /* The rows out: each vertex's id and position, its slot's row noted
     * (a face's corners then read their rows from one small array), then
     * each face's corners' rows. Each row is a few loads and stores and no
     * arithmetic, so the vector levels move four rows' values in whole
     * vectors (fewer instructions, the same bits). */
    int32_t *const rank = s->vertex_rank;
#if PMX_X86
    if (pmx_simd(-1) >= PMX_SIMD_AVX2) {
        vertex_rows_out_sse(vertex_rows, s->n_vertex_rows, s->vertex_position, ids, positions, rank);
        face_rows_out_sse(face_rows, s->n_face_rows, s->face_vertex, rank, faces);
    } else
#endif
    {
        vertex_rows_out_plain(vertex_rows, 0, s->n_vertex_rows, s->vertex_position, ids, positions, rank);
        face_rows_out_plain(face_rows, s->n_face_rows, s->face_vertex, rank, faces);
    }
    return PMX_OK;
}
