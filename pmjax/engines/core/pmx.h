/* pmx: the front engine's core, the output-sensitive refinement of a
 * progressive mesh as plain C loops (docs/front.md).
 *
 * The core reads a hierarchy laid out for it (PmxHierarchy: one 64-byte row
 * per pcol in the breadth-first order of the pcol forest), decides pcols for
 * one camera or many, and writes counts, lists, masks and meshes into
 * buffers the caller owns, each with its capacity. Its decisions are the
 * float32 predicate's bits: a decision the core cannot certify is left
 * "unsure" and the caller asks the float32 predicate (answers, records).
 *
 * Every function is reentrant: working memory comes from pmx_scratch_take
 * (a pool, one scratch per concurrent call) and the only globals are the
 * SIMD kernels chosen once (pmx_simd). No function calls back into Python.
 *
 * Errors: the functions that can meet bad input return a PmxStatus; the
 * message of a status is pmx_status_text.
 */
#ifndef PMX_H
#define PMX_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Layout constants shared with pmjax/engines (the Python side asserts them
 * through pmx_layout). */
enum {
    PMX_ROW = 16,       /* float32 per table row */
    PMX_VIEW = 22,      /* float32 per view (pmjax/_view.py View.values) */
    PMX_CAMERA = 19,    /* float32 per camera: eye 3, rotation 9 (row-major), fov_y, near, far, ortho_height,
                           width, height, tau */
    PMX_FRAMES = 16,    /* frames of a word (one bit each) */
    PMX_FAT = 29,       /* float32 per fat camera */
    PMX_NODE = 12,      /* int32 per node of an unsure record */
    PMX_SPARE = 16,     /* room past n_pcols in every list (the loops store whole vectors) */
    PMX_MAX_PCOLS = 1 << 29
};

/* Tests of a call. */
enum { PMX_FRUSTUM = 1, PMX_ORIENTATION = 2, PMX_SCREEN = 4, PMX_ORTHOGRAPHIC = 8 };

/* SIMD kernels (pmx_simd). */
enum { PMX_SIMD_PLAIN = 0, PMX_SIMD_AVX2 = 1, PMX_SIMD_AVX512 = 2 };

typedef enum {
    PMX_OK = 0,
    PMX_BAD_SIZE,      /* a size or capacity that does not fit the hierarchy */
    PMX_BAD_TABLE,     /* a row's children outside the table */
    PMX_NO_MEMORY,     /* scratch could not be allocated */
    PMX_FACES_DIFFER,  /* a mesh whose faces are not the refinement's count */
    PMX_FRONT_PAST,    /* a front of more vertices than the original ones */
    PMX_START_TWICE,   /* two front vertices at one depth-first start */
    PMX_FRONT_NOT_AT_0, /* a front that does not start at original vertex 0 */
    PMX_FACE_TWICE,    /* a face drawn twice */
    PMX_VERTEX_TWICE,  /* a vertex id used by two front vertices */
    PMX_BAD_PCOL_RECORD, /* a pcol record pointing outside the tables */
    PMX_BAD_KILL_RECORD, /* a kill_data record outside the faces or original vertices */
    PMX_BAD_BASE_RECORD, /* a base record outside the faces or original vertices */
    PMX_BAD_TOP_RECORD   /* a top (or its top_at) outside the positions or vertices */
} PmxStatus;

const char *pmx_status_text(PmxStatus status);

/* The hierarchy in breadth-first order of its forest: position q holds pcol
 * order[q]; the roots are positions 0 .. n_roots - 1 and the created children
 * of a position sit side by side at a later position. rows[q] holds the
 * pcol's attributes and the bounds over the pcols below it (columns: centre 3,
 * axis 3, radius, sin, cos, delta, mu, reach, spread, facing, error) and, as
 * int32 bits in the last column, KIDS: kills != 2 << 31 | first child's
 * position << 2 | number of created children. */
typedef struct {
    const float *rows;     /* [n_pcols, PMX_ROW], 64-byte aligned rows */
    const int32_t *kills;  /* [n_pcols] faces each position's pcol kills */
    const int32_t *order;  /* [n_pcols] pcol at each position */
    int64_t n_pcols, n_roots;
} PmxHierarchy;

/* O(n_pcols) check of a hierarchy's links (every child inside the table,
 * after its parent, every position reached once). */
PmxStatus pmx_check_hierarchy(const PmxHierarchy *h);

/* Working memory for calls on hierarchies of up to n_pcols pcols, taken
 * from a pool and given back (the pool keeps it for the next call of any
 * thread; its parts are allocated when a call first needs them). NULL when
 * out of memory. */
typedef struct PmxScratch PmxScratch;
PmxScratch *pmx_scratch_take(int64_t n_pcols);
void pmx_scratch_give(PmxScratch *s);
void pmx_scratch_drain(void); /* frees the pool's idle scratch */

/* How a call runs helpers: schedule(ctx, task, arg) runs task(arg) some time
 * later on another thread (or at once on this one); threads: how many
 * threads may work on the call, this one included (1: no helper). */
typedef struct {
    void (*schedule)(void *ctx, void (*task)(void *), void *arg);
    void *ctx;
    int64_t threads;
} PmxRunner;

/* One camera's visited slots, each list with room for n_pcols + PMX_SPARE
 * entries (any pointer may be NULL): the pcol of each slot, whether it ran
 * (0/1; for a word, ran_frames: one bit per frame) and its position. In a
 * batch, item k's lists start at k * (n_pcols + PMX_SPARE). */
typedef struct {
    int32_t *pcols;
    uint8_t *ran;
    uint16_t *ran_frames;
    int32_t *positions;
} PmxLists;

/* Counts of one camera (or frame): slots visited, pcols that did not run,
 * the faces those keep, unsure decisions taken as "keep". */
typedef struct {
    int32_t visited, not_run, kept, unsure;
} PmxCounts;

/* One camera (view: PMX_VIEW floats) with the SIMD kernels of `level` (-1:
 * those in use; *level_used: the level run). An unsure decision at position q
 * takes answers[i] (non-zero: collapse) where answered[i] == q (answered:
 * n_answered positions, increasing); one not answered is taken as "keep",
 * listed by position in unsure (room for n_pcols; may be NULL; increasing)
 * and counted in counts->unsure. The traversal visits the same slots whatever
 * the own decisions, so a second call at the same level with the first's
 * unsure positions answered is exact. */
PmxStatus pmx_refine_one(const PmxHierarchy *h, const float *view, int flags, int level, const int32_t *answered,
                         const int32_t *answers, int64_t n_answered, PmxLists lists, int32_t *unsure,
                         PmxCounts *counts, int *level_used, PmxScratch *s);

/* Records of unsure decisions: a camera (or word) whose decisions include
 * unsure ones is counted as if each were "keep" and leaves a record: [item,
 * nodes], then PMX_NODE int32 per node (the unsure slots and their ancestors,
 * children first), so that once the unsure pairs are decided the counts can
 * be corrected without another traversal (pmx_apply_unsure). Records go to
 * records[0 .. capacity); *used of them are used; an item whose record does
 * not fit is flagged in overflow[] (refine it alone with pmx_refine_one). */
typedef struct {
    int32_t *records;
    int64_t capacity;
    int64_t used;
} PmxRecords;

/* K cameras (views [K, PMX_VIEW]); counts[k]; masks [K, n_pcols] executed
 * bytes and lists optional (NULL). The runner's threads take the cameras in
 * Morton order of their eyes (nearby cameras share cache lines). */
PmxStatus pmx_refine_many(const PmxHierarchy *h, const float *views, int64_t K, int flags, PmxCounts *counts,
                          uint8_t *masks, PmxLists lists, PmxRecords *records, uint8_t *overflow,
                          const PmxRunner *run);

/* Face budgets of K cameras (cameras [K, PMX_CAMERA], the tau column a first
 * tolerance to traverse at, 0: one from the answers before; units [K] each
 * camera's one pixel as the float32 predicate computes it; budgets [K, B],
 * B budgets per camera; base_faces: the coarsest mesh's faces): guess[k, j]
 * the float32 bit pattern of a guess of the smallest tau whose face count
 * is within budgets[k, j] (0x7F800001: tau = inf), from the critical
 * tolerances of the pcols that do not run at a tolerance below the smallest
 * of the camera's answers (one traversal serves its B budgets), and
 * guess_alt[k, j] the same with the unsure decisions taken as collapses
 * rather than "keep" (budget.c). The caller makes them exact by counts.
 * words: the cameras are words of PMX_FRAMES consecutive frames of a path
 * (tables with bounds over whole subtrees, K a multiple of PMX_FRAMES,
 * PMX_BAD_SIZE otherwise), each frame's tolerance > 0 where to traverse:
 * each word traversed once for its frames, and a frame whose answers lie
 * below its tolerance gets -1 in guess and guess_alt; a word's frame makes
 * one guess (unsure decisions as "keep"), so its guess_alt equals its guess. */
PmxStatus pmx_budget_many(const PmxHierarchy *h, const float *cameras, const float *units, int64_t K, int flags,
                          const int32_t *budgets, int64_t B, int64_t base_faces, int32_t *guess, int32_t *guess_alt,
                          int words, const PmxRunner *run);

/* Words of PMX_FRAMES consecutive frames of a path (views [W * PMX_FRAMES,
 * PMX_VIEW]; a word's spare frames repeat one of its own): each word
 * traversed once for its frames, most pcols decided for all of them at once
 * under a fat camera. counts[w * PMX_FRAMES + l] for frame l of word w;
 * lists (ran_frames the frames' bits) optional; at_once[w] (optional):
 * the slots the fat camera decided. */
PmxStatus pmx_refine_words(const PmxHierarchy *h, const float *views, int64_t W, int flags, PmxCounts *counts,
                           PmxLists lists, int32_t *at_once, PmxRecords *records, uint8_t *overflow,
                           const PmxRunner *run);

/* Words pmx_refine_word_sets traverses together at most. */
#define PMX_MOST_SETS 8

/* pmx_refine_words without lists, for W words in groups of `sets` (1 to PMX_MOST_SETS)
 * consecutive words: a group whose words hold the same frames, differing
 * only in their tolerances, is traversed once for all of them (word_sets.c);
 * any other group word by word. Each word's faces and pcols run are
 * pmx_refine_words' once its unsure pairs are decided; its visited slots and
 * records may differ (another set's sure decisions settle some pairs, and
 * the set then walks below slots its own "whole" would have stopped at), and
 * at_once counts the fat camera of the whole group; PMX_BAD_SIZE unless W is
 * a multiple of sets. */
PmxStatus pmx_refine_word_sets(const PmxHierarchy *h, const float *views, int64_t W, int sets, int flags,
                               PmxCounts *counts, int32_t *at_once, PmxRecords *records, uint8_t *overflow,
                               const PmxRunner *run);

/* The unsure pairs of records: per unsure node its place in records (at),
 * item, position and unsure frames (bit l: frame l; 1 for a camera).
 * Returns their number (at most used / PMX_NODE). */
int64_t pmx_unsure_pairs(const int32_t *records, int64_t used, int64_t *at, int32_t *item, int32_t *position,
                         int32_t *frames);

/* Sets yes[i] (bits of the frames whose decision is collapse) at records[at[i]]
 * for the n pairs, resolves the records' chains again and corrects the
 * counts of their items (frames: PMX_FRAMES for words, 1 for cameras;
 * counts of item k's frame l at k * frames + l), masks and lists as the
 * pcols turn executed. */
void pmx_apply_unsure(int32_t *records, int64_t used, const int64_t *at, const int32_t *yes, int64_t n,
                      int frames, PmxCounts *counts, const int32_t *order, int64_t n_pcols, uint8_t *masks,
                      PmxLists lists);

/* Every pcol of rows [n_pcols, PMX_ROW] under one view: its own decision
 * (0 keep, 1 collapse, 2 unsure) | 4 where its bound decides everything below. */
void pmx_decide_all(const float *rows, int64_t n_pcols, const float *view, int flags, uint8_t *out);

/* The fat cameras of n_words words of n_frames frames (views [W, F,
 * PMX_VIEW]) into out [W, PMX_FAT]; NaN where not finite. */
PmxStatus pmx_fat_cameras(const float *views, int64_t n_words, int n_frames, float *out);

/* Every pcol under the fat camera of n_frames frames: 0 open, 1 every
 * frame's subtree collapses, 2 no frame collapses it; all 0 where the fat
 * camera does not apply. */
void pmx_decide_fat_all(const float *rows, int64_t n_pcols, const float *views, int n_frames, int flags,
                        const float *fat, uint8_t *out);

/* The mesh's records for pmx_front_mesh (one per pcol by position, per killed
 * face in kill order, per base face, per top). All fields 4 bytes. */
typedef struct {
    int32_t kill_first, kill_count, vertex[2], start[2], made_at[2];
    float position[2][3];
} PmxPcolRecord;
typedef struct {
    int32_t face, start[3];
} PmxFaceRecord;
typedef struct {
    int32_t start, vertex;
    float position[3];
} PmxFrontVertex;

typedef struct {
    const PmxPcolRecord *pcols; /* [n_pcols] by position */
    const PmxFaceRecord *kill_data;
    const PmxFaceRecord *base;
    const PmxFrontVertex *tops;
    const int32_t *top_at;      /* [n_tops] the top's position, -1 for a lone original */
    int64_t n_kill_data, n_base, n_tops, n_original, n_pcols, n_faces;
} PmxMeshTables;

/* Whether a record of the mesh's tables points inside them: pmx_front_mesh
 * checks each record it reads, mesh_stream_new every record. A value v is
 * inside [0, n) when (uint64_t)(int64_t)v < n (a negative one wraps past). */
#define PMX_INSIDE(v, n) ((uint64_t)(int64_t)(v) < (uint64_t)(n))

/* The pcol at position q: its kill list inside kill_data [n_kill], each
 * vertex's start an original vertex, its id an original one where it is
 * original (made_at < 0), else below n_original + n_pcols and made at a
 * later position (children follow their parent breadth first). */
static inline int pmx_pcol_record_fits(const PmxPcolRecord *r, int64_t q, int64_t n_kill, int64_t n_original,
                                       int64_t n_pcols)
{
    int ok = r->kill_first >= 0 && r->kill_count >= 0 && r->kill_first + (int64_t)r->kill_count <= n_kill;
    for (int j = 0; j < 2; j++)
        ok &= PMX_INSIDE(r->start[j], n_original) &
              (r->made_at[j] < 0 ? PMX_INSIDE(r->vertex[j], n_original)
                                 : r->made_at[j] > q && r->made_at[j] < n_pcols &&
                                       PMX_INSIDE(r->vertex[j], n_original + n_pcols));
    return ok;
}

/* A face record (kill_data's or base's): a face, its corners' starts
 * original vertices. */
static inline int pmx_face_record_fits(const PmxFaceRecord *f, int64_t n_faces, int64_t n_original)
{
    return PMX_INSIDE(f->face, n_faces) & PMX_INSIDE(f->start[0], n_original) &
           PMX_INSIDE(f->start[1], n_original) & PMX_INSIDE(f->start[2], n_original);
}

/* A top: a position or -1 (top_at), a start among the original vertices
 * and an id below n_original + n_pcols. */
static inline int pmx_top_fits(const PmxFrontVertex *t, int32_t top_at, int64_t n_original, int64_t n_pcols)
{
    return (top_at >= -1) & (top_at < n_pcols) & PMX_INSIDE(t->start, n_original) &
           PMX_INSIDE(t->vertex, n_original + n_pcols);
}

/* The refined mesh of a refinement's visited slots (ran, positions: n of
 * them): faces [n_faces_drawn, 3] as indices into ids/positions (the
 * vertices used, increasing id; room for id_capacity). *n_ids: their number.
 * PMX_BAD_SIZE (nothing written to ids/positions) when more are used; a
 * status of its own for each way the slots are not a refinement's, and
 * PMX_BAD_*_RECORD with *n_ids the index of a record it read that points
 * outside the tables (pcol records by position). */
PmxStatus pmx_front_mesh(const PmxMeshTables *m, const uint8_t *ran, const uint16_t *ran_frames, int frame,
                         const int32_t *positions, int64_t n, int64_t n_faces_drawn, int32_t *faces,
                         int32_t *ids, float *vertex_positions, int64_t id_capacity, int64_t *n_ids,
                         PmxScratch *s);

/* Drawable front meshes along a path (mesh_stream.c): one frame's mesh in
 * stable slots, each frame applied as a change against the last. */
typedef struct PmxMeshStream PmxMeshStream;
typedef struct {
    const PmxPcolRecord *pcols; /* [n_pcols] by position (pmx_front_mesh's) */
    const PmxFaceRecord *kill_data, *base;
    const PmxFrontVertex *tops;
    const int32_t *top_at;       /* [n_tops] the top's position, -1 for a lone original */
    const int32_t *own_vertex;   /* [n_pcols] by position: the pcol's own vertex id */
    const int32_t *own_end;      /* [n_pcols] the end of its depth-first interval of original vertices */
    const float *own_position;   /* [n_pcols, 3] its position */
    const int32_t *up;           /* [n_pcols + n_original] the consuming pcol's position (-1: a top) of each
                                  * position's vertex, then of each original vertex */
    const int32_t *corners;      /* [n_faces, 3] each face's original vertices */
    int64_t n_kill_data, n_base, n_tops, n_original, n_pcols, n_faces;
} PmxStreamTables;
typedef struct {                 /* a frame: its n visited slots' positions and ran bits */
    const int32_t *positions;
    const uint8_t *ran8;         /* one byte per slot, or */
    const uint16_t *ran16;       /* a word's frame bits, bit `frame` */
    int frame;
    int64_t n;
    int64_t key;                 /* >= 0: frames with one key share these lists (a word); -1: none */
} PmxStreamFrame;
typedef struct {                 /* the stream's arrays (valid until it grows: generation) */
    const int32_t *face_vertex;  /* [face_cap, 3] vertex slots, -1 in free slots */
    const int32_t *face_id;      /* [face_cap] face drawn, -1 free */
    const int32_t *vertex_id;    /* [vertex_cap] vertex id, -1 free */
    const float *vertex_position;
    int64_t face_cap, vertex_cap, n_face_slots, n_vertex_slots, n_face_changes, n_vertex_changes, n_faces,
        n_vertices, n_used, generation;
} PmxStreamState;

/* A stream at the fully collapsed mesh (the tops and base faces); NULL with
 * *status on failure. The tables must outlive it. */
PmxMeshStream *pmx_mesh_stream_new(const PmxStreamTables *t, PmxStatus *status);
void pmx_mesh_stream_free(PmxMeshStream *s);
/* From the frame the stream holds to `next` (whose arrays the caller keeps
 * until the step after): the change's slots are those touched.
 * PMX_BAD_SIZE (nothing changed) when next's positions do not increase
 * inside [0, P); PMX_BAD_TABLE when its flips are not a refinement's (the
 * stream is then broken: every later step fails). */
PmxStatus pmx_mesh_stream_step(PmxMeshStream *s, const PmxStreamFrame *next);
/* pmx_mesh_stream_step to another frame of the word the stream holds (its
 * lists, bit `frame`); PMX_BAD_SIZE (nothing changed) when the frame held
 * is not a word's. */
PmxStatus pmx_mesh_stream_lane(PmxMeshStream *s, int frame);
void pmx_mesh_stream_state(const PmxMeshStream *s, PmxStreamState *out);
/* The ways corners of new faces found their vertex since the stream was
 * made, counted in out[PMX_SEARCHES]: at the split's two vertices, from the
 * vertex the face's third corner had when last removed, among the split's
 * neighbours, or up from the corner's original vertex (the base faces, and
 * any corner the others miss). */
enum { PMX_SEARCH_SPLIT, PMX_SEARCH_HAD, PMX_SEARCH_AROUND, PMX_SEARCH_UP, PMX_SEARCHES };
void pmx_mesh_stream_searches(const PmxMeshStream *s, int64_t out[PMX_SEARCHES]);
/* The last step's change packed side by side in out (4 * (4 * n_face_changes
 * + 5 * n_vertex_changes) bytes, 4-aligned): int32 face slots [k], their
 * vertex slots [k, 3], int32 vertex slots [u], their ids [u], float32
 * positions [u, 3]. */
void pmx_mesh_stream_pack(const PmxMeshStream *s, void *out);
/* The mesh held, compacted as Refinement.mesh() gives it: faces [n_faces, 3]
 * in increasing face id, ids and positions [n_used(, 3)] the vertices the
 * faces use in increasing id. The stream keeps the rows (ids and slots)
 * for the next compaction, which merges the changes logged since into
 * them (a merge that does not give the mesh's counts is replaced by a
 * ranking afresh). PMX_NO_MEMORY (nothing written, the stream as it was)
 * or PMX_BAD_TABLE (the stream is broken: nothing written) on failure. */
PmxStatus pmx_mesh_stream_compact(PmxMeshStream *s, int32_t *faces, int32_t *ids, float *positions);

/* The view constants (PMX_VIEW floats) of a camera (PMX_CAMERA floats), and
 * of n cameras. */
void pmx_view_of(const float *camera, int orthographic, float *view);
void pmx_views_of(const float *cameras, int64_t n, int orthographic, float *views);

/* SIMD kernels: the best the processor has up to `level` (level < 0: leave
 * them); returns the kernels in use before. pmx_simd_best: the processor's. */
int pmx_simd(int level);
int pmx_simd_best(void);

/* How pmx_front_mesh takes its ranks (mode < 0: leave it; 0 by the ratio of
 * items to bitmap words, 1 bitmaps always, 2 sorts always; every way gives
 * the same mesh); returns the mode in use before. */
int pmx_mesh_ranks(int mode);

#ifdef __cplusplus
}
#endif

#endif
