/* What the core's files share: the table's columns, a view as the decisions
 * read it, the kernels chosen per processor, the scratch. Not part of the
 * API (pmx.h). */
#ifndef PMX_INTERNAL_H
#define PMX_INTERNAL_H

#include <math.h>
#include <stdint.h>
#include <string.h>

#include "pmx.h"

#if defined(__x86_64__) && defined(__GNUC__)
#define PMX_X86 1
#else
#define PMX_X86 0
#endif

/* Columns of a table row. The last, KIDS, holds int32 bits: kills != 2 << 31
 * | first child's position << 2 | number of created children. */
enum { CX, CY, CZ, NX, NY, NZ, RADIUS, SIN_A, COS_A, DELTA, MU, REACH, SPREAD, FACING, ERROR, KIDS, ROW };

/* Tests of a call (pmx.h). */
enum { TEST_FRUSTUM = PMX_FRUSTUM, TEST_ORIENTATION = PMX_ORIENTATION, TEST_SCREEN = PMX_SCREEN,
       ORTHOGRAPHIC = PMX_ORTHOGRAPHIC };

/* Layout of a view (pmjax/_view.py View.values). */
enum { EYE = 0, RIGHT = 3, UP = 6, FORWARD = 9, K = 12, ONE_PIXEL = 20, KAPPA2 = 21 };

/* State of a visited slot: its own decision in the low bits, WHOLE when the
 * bound decided everything below it. */
enum { NO = 0, YES = 1, UNSURE = 2, WHOLE = 4 };

/* Decisions of the fat pass. FAT_INSIDE: every frame's frustum test surely
 * keeps the pcol; FAT_SCREEN: its orientation test too (only the screen test
 * is left to the frames); FAT_YES: no frame's subtree bound holds and the
 * float32 predicate collapses the pcol in every frame; a frame's own
 * certificate may have been unsure (unsure counts are counted after the fat
 * pass). */
enum { FAT_OPEN = 0, FAT_WHOLE = 1, FAT_NO = 2, FAT_SCREEN = 3, FAT_INSIDE = 4, FAT_YES = 5 };
/* The tests a frame's decision may leave out (decide_one's settled). */
enum { SETTLED_FRUSTUM = 1, SETTLED_ORIENTATION = 2 };

#define BLOCK 16
#define FRAMES PMX_FRAMES

/* The first child's position in a row's KIDS, and the faces a slot's pcol
 * kills (pos: its position). */
enum { KIDS_FIRST = 0x1FFFFFFF };
static inline int32_t kids_first(int32_t kids) { return (int32_t)(((uint32_t)kids >> 2) & KIDS_FIRST); }
static inline int32_t kids_kills(const PmxHierarchy *h, int32_t kids, int32_t pos)
{
    return kids < 0 ? h->kills[pos] : 2;
}

/* The rows of a block of pcols as columns: col[c][j] is column c of pcol j. */
typedef float Columns[ROW][BLOCK];

/* Frame masks of a word: bit l for frame l. */
typedef uint16_t Lanes;

/* An id and a slot: a row or change of the compacted mesh (mesh_stream.c),
 * or an item to rank (front_mesh.c). */
typedef struct {
    int32_t id, slot;
} IdSlot;

/* The cameras of the lanes of one decision pass, struct of arrays: the
 * frames of a word, or one camera in every lane (a block of pcols). Each
 * lane reads its own camera and its own pcol, so that no condition is
 * uniform over the lanes for the compiler (see fast, decide.c). */
typedef struct {
    float ex[BLOCK], ey[BLOCK], ez[BLOCK], R[3][BLOCK], U[3][BLOCK], F[3][BLOCK], k[8][BLOCK];
    float kappa2[BLOCK], kabs[BLOCK], kfac[BLOCK], kpad[BLOCK];
    float aR[3][BLOCK], aU[3][BLOCK], aF[3][BLOCK], ak[8][BLOCK]; /* absolute values */
    int frustum, orientation, screen, ortho, fast;
} Frames;

/* Frames from views [n_frames, PMX_VIEW] (the spare lanes repeat the first). */
void load_frames(Frames *fr, const float *views, int n_frames, int flags);

/* A fat camera: bounds covering the frames of a word (fat.c). */
typedef struct {
    float ex, ey, ez, rho;                            /* eye centre; |e_f - e| <= rho */
    float px, py, pz;                                 /* pivot */
    float R0, R1, R2, U0, U1, U2, F0, F1, F2;         /* reference rotation (right, up, forward) */
    float tx, ty, tz;                                 /* the pivot in reference camera coordinates */
    float eps, tau;                                   /* |R_f - R| <= eps, |R_f (p - e_f) - t| <= tau */
    float ax, ay, az, abx, aby, abz, ab_inv, capsule; /* every e_f within capsule of a + [0, 1] ab; 1 / |ab|^2 */
    float k0, k1, k2, k3, k4, k5, kfac, kabs;         /* the frames' common constants (kabs: the largest) */
    float kappa2, kappa2_hi;                          /* the smallest and largest of the frames' kappa2 */
    float near_lo, near_hi, far_lo, far_hi, kpad;     /* clip distances over the frames, the largest kpad */
} Fat;

int fat_applies(const Frames *fr, const float *fat, int n_frames);
void load_fat(Fat *W, const float *fat, const Frames *fr, int n_frames);

/* A call's working memory (scratch.c), in parts allocated when first
 * needed: the slots of a traversal (capacity n_pcols, with PMX_SPARE room
 * where the loops store whole vectors), a word's frame masks, the unsure
 * records' chains, the front mesh's bitmaps and lists. mark, the bitmaps and
 * their summaries are zero between calls. */
struct PmxScratch {
    int64_t n_pcols;
    /* slots */
    int32_t *ids, *kid, *kill, *pcols, *unsure, *parent, *chain;
    uint8_t *state, *ran, *mark;
    /* words */
    Lanes *visit, *whole, *yes, *ran_frames, *unsure_lanes;
    /* word sets: `sets` sets of the words' bits, set t's slot i at t * room + i */
    int64_t sets;
    Lanes *set_visit, *set_whole, *set_yes, *set_ran, *set_unsure_lanes;
    int32_t *set_unsure;
    /* front mesh, for n_original vertices and n_faces faces */
    int64_t n_original, n_faces;
    int32_t *not_run_at, *start_prefix, *face_prefix, *vertex_prefix, *start_block, *front_index, *front_rank;
    uint64_t *start_bits, *face_bits, *vertex_bits, *start_sum, *face_sum, *vertex_sum;
    PmxFrontVertex *front;
    PmxFaceRecord *drawn;
    IdSlot *pairs[2]; /* [max(n_faces, n_original + 1)] each: ranks by sorting */
    int32_t *sort_counts; /* [RANK_COUNTS] the sorts' digit counts */
    struct PmxScratch *next; /* in the pool */
};

/* The front mesh sorts' digit counts: at most two tables of 2^13 (front_mesh.c). */
#define RANK_DIGIT_MOST 13
#define RANK_COUNTS (2 << RANK_DIGIT_MOST)

/* The parts (0 when out of memory). */
int scratch_slots(PmxScratch *s);
int scratch_words(PmxScratch *s);
int scratch_sets(PmxScratch *s, int64_t sets); /* grown when short */
int scratch_mesh(PmxScratch *s, int64_t n_original, int64_t n_faces);

/* The slots' bookkeeping of one decided block (slots.h). */
typedef int64_t (*PushBlock)(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n, const int32_t *decided,
                             const float *kids, uint8_t *state, int32_t *kill, int32_t *kid, int32_t *ids,
                             int32_t *parent, int32_t *unsure, int64_t *m);
/* The slots' bookkeeping of one decided block of a word (slots_plain.c). */
typedef int64_t (*PushWordBlock)(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n,
                                 const Lanes (*masks)[BLOCK], const float *kids, Lanes *visit, Lanes *whole,
                                 Lanes *yes, int32_t *kid, int32_t *ids, int32_t *unsure_slots, Lanes *unsure_lanes,
                                 int64_t *m);
typedef void (*Resolve)(const PmxHierarchy *h, int64_t n, const int32_t *ids, const int32_t *kid,
                        const uint8_t *state, const int32_t *kill, uint8_t *ran, int32_t *pcols, int64_t *not_run,
                        int64_t *kept);

/* The kernels of one SIMD level. Every loop whose speed depends on the
 * vector unit is compiled once per level (a wrapper with the level's target
 * around an always-inline body); pmx_simd picks one table for all. */
typedef struct {
    void (*decide_perspective)(const Frames *fr, Columns col, int32_t *code);
    void (*decide_orthographic)(const Frames *fr, Columns col, int32_t *code);
    void (*decide_row_perspective)(const Frames *fr, const float *row, Lanes *masks);
    void (*decide_row_orthographic)(const Frames *fr, const float *row, Lanes *masks);
    void (*decide_row_settled)(const Frames *fr, const float *row, int32_t fat_code, Lanes *masks);
    void (*decide_fat)(const Fat *W, Columns col, int32_t *code);
    void (*gather)(const float *const *rows, Columns col);
    PushBlock push_block;
    PushWordBlock push_word_block;
    int (*fat_masks)(const int32_t *code, int64_t nb, Lanes (*masks)[BLOCK], uint32_t *kinds);
    Resolve resolve;
    void (*resolve_word)(const int32_t *kills, const int32_t *order, int64_t n, const int32_t *ids,
                         const int32_t *kid, const Lanes *visit, const Lanes *whole, const Lanes *yes, Lanes *ran,
                         int32_t *pcols, PmxCounts *counts);
    PmxStatus (*front_mesh)(const PmxMeshTables *m, const uint8_t *ran, const uint16_t *ran_frames, int frame,
                            const int32_t *positions, int64_t n, int64_t n_faces_drawn, int32_t *faces,
                            int32_t *ids, float *vertex_positions, int64_t id_capacity, int64_t *n_ids,
                            PmxScratch *s);
} Kernels;

const Kernels *pmx_kernels(void);
/* The kernels of a level (clamped to the processor's; -1: those in use) and that level. */
const Kernels *pmx_kernels_at(int level, int *used);

/* The level variants (defined in the algorithm files). */
#define PMX_LEVEL_DECLS(suffix)                                                                              \
    void decide_perspective_##suffix(const Frames *fr, Columns col, int32_t *code);                          \
    void decide_orthographic_##suffix(const Frames *fr, Columns col, int32_t *code);                         \
    void decide_row_perspective_##suffix(const Frames *fr, const float *row, Lanes *masks);                  \
    void decide_row_orthographic_##suffix(const Frames *fr, const float *row, Lanes *masks);                 \
    void decide_row_settled_##suffix(const Frames *fr, const float *row, int32_t fat_code, Lanes *masks);    \
    void decide_fat_##suffix(const Fat *W, Columns col, int32_t *code);                                      \
    void gather_##suffix(const float *const *rows, Columns col);                                            \
    int fat_masks_##suffix(const int32_t *code, int64_t nb, Lanes (*masks)[BLOCK], uint32_t *kinds);         \
    void resolve_word_##suffix(const int32_t *kills, const int32_t *order, int64_t n, const int32_t *ids,    \
                               const int32_t *kid, const Lanes *visit, const Lanes *whole, const Lanes *yes, \
                               Lanes *ran, int32_t *pcols, PmxCounts *counts);                               \
    PmxStatus front_mesh_##suffix(const PmxMeshTables *m, const uint8_t *ran, const uint16_t *ran_frames,    \
                                  int frame, const int32_t *positions, int64_t n, int64_t n_faces_drawn,     \
                                  int32_t *faces, int32_t *ids, float *vertex_positions,                     \
                                  int64_t id_capacity, int64_t *n_ids, PmxScratch *s);
PMX_LEVEL_DECLS(plain)
#if PMX_X86
PMX_LEVEL_DECLS(avx2)
PMX_LEVEL_DECLS(avx512)
#endif

int64_t push_block_plain(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n, const int32_t *decided,
                         const float *kids, uint8_t *state, int32_t *kill, int32_t *kid, int32_t *ids, int32_t *parent,
                         int32_t *unsure, int64_t *m);
int64_t push_word_block_plain(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n, const Lanes (*masks)[BLOCK],
                              const float *kids, Lanes *visit, Lanes *whole, Lanes *yes, int32_t *kid, int32_t *ids,
                              int32_t *unsure_slots, Lanes *unsure_lanes, int64_t *m);
void resolve_plain_range(const PmxHierarchy *h, int64_t lo, int64_t hi, const int32_t *ids, const int32_t *kid,
                         const uint8_t *state, const int32_t *kill, uint8_t *ran, int32_t *pcols, int64_t *not_run,
                         int64_t *kept);
void resolve_plain(const PmxHierarchy *h, int64_t n, const int32_t *ids, const int32_t *kid, const uint8_t *state,
                   const int32_t *kill, uint8_t *ran, int32_t *pcols, int64_t *not_run, int64_t *kept);
#if PMX_X86
int64_t push_block_avx2(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n, const int32_t *decided,
                        const float *kids, uint8_t *state, int32_t *kill, int32_t *kid, int32_t *ids, int32_t *parent,
                        int32_t *unsure, int64_t *m);
void resolve_avx2(const PmxHierarchy *h, int64_t n, const int32_t *ids, const int32_t *kid, const uint8_t *state,
                  const int32_t *kill, uint8_t *ran, int32_t *pcols, int64_t *not_run, int64_t *kept);
int64_t push_block_avx512(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n, const int32_t *decided,
                          const float *kids, uint8_t *state, int32_t *kill, int32_t *kid, int32_t *ids,
                          int32_t *parent, int32_t *unsure, int64_t *m);
int64_t push_word_block_avx512(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n, const Lanes (*masks)[BLOCK],
                               const float *kids, Lanes *visit, Lanes *whole, Lanes *yes, int32_t *kid, int32_t *ids,
                               int32_t *unsure_slots, Lanes *unsure_lanes, int64_t *m);
void resolve_avx512(const PmxHierarchy *h, int64_t n, const int32_t *ids, const int32_t *kid, const uint8_t *state,
                    const int32_t *kill, uint8_t *ran, int32_t *pcols, int64_t *not_run, int64_t *kept);
#endif

/* The targets of the levels: x86-64-v3's vector set, and AVX-512 with the
 * mask instructions and bit deposits the slots use. */
#define PMX_TARGET_AVX2 __attribute__((target("avx2,fma,popcnt")))
#define PMX_TARGET_AVX512 __attribute__((target("avx512f,avx512bw,avx512vl,avx512dq,bmi2,fma,popcnt")))
#define PMX_INLINE static inline __attribute__((always_inline))

/* Rank of bit i among the set bits (bit i set): set bits before its word
 * (prefix) plus those below it in its word. */
PMX_INLINE int64_t rank_of(const uint64_t *bits, const int32_t *prefix, int64_t i)
{
    const uint64_t below = bits[i >> 6] & ((((uint64_t)2) << (i & 63)) - 1);
    return prefix[i >> 6] + __builtin_popcountll(below) - 1;
}

/* prefix[w]: the set bits in words before w. */
PMX_INLINE void prefix_counts(const uint64_t *bits, int64_t words, int32_t *prefix)
{
    int32_t total = 0;
    for (int64_t w = 0; w < words; w++) {
        prefix[w] = total;
        total += __builtin_popcountll(bits[w]);
    }
}

/* A bitmap with a summary, so that a pass costs the words a call set rather
 * than the bitmap's size: bit w of sum is set with any bit of word w (sum
 * has words / 64 + 1 words). Where at most n bits will be set and n is not
 * below words / MARKED_DENSE, a pass over every word (streamed, no jump
 * per word) costs less, and is proportional to n: the bitmap is then used
 * without its summary ("dense"). */
#ifndef MARKED_DENSE
#define MARKED_DENSE 16
#endif

PMX_INLINE int marked_dense(int64_t n, int64_t words) { return n * MARKED_DENSE >= words; }

/* Bit i set, and its word marked unless dense. */
PMX_INLINE void set_marked(uint64_t *bits, uint64_t *sum, int64_t i, uint64_t on, int dense)
{
    bits[i >> 6] |= on << (i & 63);
    if (!dense)
        sum[i >> 12] |= on << ((i >> 6) & 63);
}

/* Dense: prefix[w] for every word (rank_of then holds for any bit). Else
 * prefix[w] for the marked words w and block[b] the set bits before word
 * 64 b (block may be NULL; rank_of holds for set bits, rank_at_or_before
 * for any). */
PMX_INLINE void prefix_marked(const uint64_t *bits, const uint64_t *sum, int64_t words, int dense, int32_t *prefix,
                              int32_t *block)
{
    if (dense) {
        prefix_counts(bits, words, prefix);
        return;
    }
    int32_t total = 0;
    for (int64_t b = 0; b < words / 64 + 1; b++) {
        if (block)
            block[b] = total;
        for (uint64_t m = sum[b]; m; m &= m - 1) {
            const int64_t w = 64 * b + __builtin_ctzll(m);
            prefix[w] = total;
            total += __builtin_popcountll(bits[w]);
        }
    }
}

/* Rank of the last set bit at or before i (there is one) among the set bits
 * of a bitmap with a summary whose prefix and block cover the marked words
 * only: in i's word, else in the last marked word before it in its block,
 * else the block's count. */
PMX_INLINE int64_t rank_at_or_before(const uint64_t *bits, const uint64_t *sum, const int32_t *prefix,
                                     const int32_t *block, int64_t i)
{
    const int64_t w = i >> 6;
    const uint64_t below = bits[w] & ((((uint64_t)2) << (i & 63)) - 1);
    if (below)
        return prefix[w] + __builtin_popcountll(below) - 1;
    const uint64_t before = sum[w >> 6] & ((((uint64_t)1) << (w & 63)) - 1);
    if (!before)
        return block[w >> 6] - 1;
    const int64_t p = (w & ~(int64_t)63) + 63 - __builtin_clzll(before);
    return prefix[p] + __builtin_popcountll(bits[p]) - 1;
}

/* The bitmap and its summary back to zero: every word where dense, else the
 * marked words. */
PMX_INLINE void clear_marked(uint64_t *bits, uint64_t *sum, int64_t words, int dense)
{
    if (dense) {
        memset(bits, 0, sizeof(uint64_t) * (size_t)words);
        return;
    }
    for (int64_t b = 0; b < words / 64 + 1; b++) {
        for (uint64_t m = sum[b]; m; m &= m - 1)
            bits[64 * b + __builtin_ctzll(m)] = 0;
        sum[b] = 0;
    }
}

/* from's n entries (ids in [0, max_id]) in increasing id, entries of one id
 * in the order they came: a stable radix sort on digits of `digit` bits (1
 * to SORT_DIGIT_MOST), as many as max_id has, through to (room n); returns
 * the sorted entries (from or to). Narrow digits keep the counts in a small
 * table for few entries, wide ones take fewer passes over many. */
#define SORT_DIGIT_MOST 12
static inline IdSlot *sort_id_slots(IdSlot *from, IdSlot *to, int64_t n, int32_t max_id, int digit)
{
    const int32_t buckets = (int32_t)1 << digit;
    int32_t count[((int32_t)1 << SORT_DIGIT_MOST) + 1];
    for (int shift = 0; n > 1 && shift < 32 && (shift == 0 || ((uint32_t)max_id >> shift) > 0); shift += digit) {
        memset(count, 0, sizeof(int32_t) * (size_t)(buckets + 1));
        for (int64_t k = 0; k < n; k++)
            count[(((uint32_t)from[k].id >> shift) & (uint32_t)(buckets - 1)) + 1]++;
        for (int32_t b = 0; b < buckets; b++)
            count[b + 1] += count[b];
        for (int64_t k = 0; k < n; k++)
            to[count[((uint32_t)from[k].id >> shift) & (uint32_t)(buckets - 1)]++] = from[k];
        IdSlot *t = from;
        from = to;
        to = t;
    }
    return from;
}

/* Rows ids[0..n) of table into columns (the rest of the block repeats the
 * first row). */
static inline void gather_block(const Kernels *kern, const float *table, const int32_t *ids, int64_t n, Columns col)
{
    const float *rows[BLOCK];
    for (int64_t j = 0; j < BLOCK; j++)
        rows[j] = table + (int64_t)ids[j < n ? j : 0] * ROW;
    kern->gather(rows, col);
}

/* The queue slots between a row's prefetch and its use. */
#define AHEAD 64

/* Subnormal floats read and written as zero (x86 MXCSR DAZ and FTZ, the
 * aarch64 FPCR FZ bit) in the calling thread while a decision loop runs; the
 * caller's mode comes back on return. A vector operation that meets a
 * subnormal can take a microcode assist of a hundred cycles or more. The
 * bits are the same: the certified own decisions allow any evaluation to
 * flush (FLUSH, certify.h), and the bounds, like pmjax/_subtree.py's for XLA
 * (which flushes too), decide nothing where a term they compare could leave
 * [LOW, HIGH]. */
unsigned subnormals_off(void);
void subnormals_back(unsigned mode);

/* Helpers of one call (workers.c): run(job) on the caller and on up to
 * threads - 1 helpers scheduled by the runner; returns when every helper
 * that started has finished (a helper that starts later does nothing). */
void run_shared(const PmxRunner *runner, void (*work)(void *job), void *job);

/* Records (records.c). SlotBits: what a record reads of a resolved word or
 * camera. */
typedef struct {
    const Lanes *visit, *whole, *yes, *ran, *unsure;
    const uint8_t *state, *ran_byte;
} SlotBits;
/* The chains of an item's unsure slots (unsure_slots[0..m)) into chain,
 * sorted by decreasing slot; returns their number (the record is then 2 +
 * PMX_NODE * count int32). parent: each slot's parent slot (built into it
 * unless parent_known); mark: zero on entry and on return. */
int64_t record_chain(int64_t n, int64_t n_roots, const int32_t *kid, const int32_t *unsure_slots, int64_t m,
                     int32_t *parent, int parent_known, int32_t *chain, uint8_t *mark);
/* The record of those chains at rec. */
void record_write(int32_t *rec, int64_t item, int64_t count, const int32_t *chain, const int32_t *ids,
                  const int32_t *kid, const SlotBits *b, const int32_t *kills, const int32_t *unsure_slots, int64_t m);
/* Room for size int32 in records, taken atomically: its offset, or -1 if it
 * does not fit. */
int64_t records_reserve(PmxRecords *records, int64_t size);

/* One word of a path traversed for its frames (words.c), for the words' face
 * budgets too (budget.c). */
int64_t traverse_word(const Kernels *kern, const PmxHierarchy *h, const float *views, int n_frames, int flags,
                      const float *fat, int32_t *ids, int32_t *kid, Lanes *visit, Lanes *whole, Lanes *yes,
                      int32_t *unsure_slots, Lanes *unsure_lanes, int64_t *n_unsure, int64_t *at_once);

/* Single-camera traversal (traverse.c), for the words' overflow-free paths too. */
int64_t traverse(const Kernels *kern, const PmxHierarchy *h, const Frames *w, int32_t *ids, int32_t *kid,
                 uint8_t *state, int32_t *kill, int32_t *parent, int32_t *unsure, int64_t *n_unsure);

#endif
