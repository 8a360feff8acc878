/* Words: consecutive frames of a camera path traversed together.
 *
 * A word holds PMX_FRAMES consecutive frames of a path, one bit each. A pcol
 * is visited once for the frames whose traversal reaches it, its row read
 * once, and each frame's own decision and bound evaluated in one vectorized
 * pass over the frames; most pcols are decided for all the frames at once
 * under the word's fat camera (fat.c). Consecutive frames share most of their
 * front, so the word visits little more than one frame alone (docs/path.md).
 * Every frame gets the bits of its own refinement. */
#include <stdlib.h>

#include "internal.h"
#if PMX_X86
#include <immintrin.h>
#endif

/* One word (views [n_frames, PMX_VIEW]; fat: its fat camera or NULL). Slot i
 * holds position ids[i], visited by the frames visit[i]; whole[i], yes[i]
 * are the frames whose bound decided it (its own or the fat camera's) and
 * whose own decision is yes. Returns the number of slots (-1: links that
 * are not a forest); the slots with unsure frames go to unsure_slots[] with
 * the frames in unsure_lanes[] (*n_unsure of them), *at_once counts the
 * slots the fat camera decided. */
int64_t traverse_word(const Kernels *kern, const PmxHierarchy *h, const float *views, int n_frames, int flags,
                      const float *fat, int32_t *ids, int32_t *kid, Lanes *visit, Lanes *whole, Lanes *yes,
                      int32_t *unsure_slots, Lanes *unsure_lanes, int64_t *n_unsure, int64_t *at_once)
{
    Frames fr;
    load_frames(&fr, views, n_frames, flags);
    Fat W;
    const int use_fat = fat_applies(&fr, fat, n_frames);
    if (use_fat)
        load_fat(&W, fat, &fr, n_frames);
    void (*decide_row)(const Frames *, const float *, Lanes *) =
        fr.ortho ? kern->decide_row_orthographic : kern->decide_row_perspective;
    const Lanes active = (Lanes)((1u << n_frames) - 1);
    const float *table = h->rows;
    int32_t fat_code[BLOCK];
    Columns col;
    int64_t n = 0, m = 0, decided_at_once = 0;
    for (int64_t i = 0; i < h->n_roots; i++) {
        ids[n] = (int32_t)i;
        visit[n++] = active;
    }
    for (int64_t i0 = 0; i0 < n;) {
        /* A block of slots (children land behind the queue, after the
         * block): its rows as columns, under the fat camera first. */
        const int64_t nb = n - i0 < BLOCK ? n - i0 : BLOCK;
        for (int64_t i = i0 + AHEAD; i < i0 + AHEAD + nb && i < n; i++)
            __builtin_prefetch(table + (int64_t)ids[i] * ROW);
        gather_block(kern, table, ids + i0, nb, col);
        if (use_fat)
            kern->decide_fat(&W, col, fat_code);
        /* The frames' masks (whole, yes, unsure) of the slots the fat camera
         * decided, and the slots left to the frames by kind: every test
         * (open), or less those the fat camera settled. */
        if (!use_fat)
            for (int j = 0; j < BLOCK; j++)
                fat_code[j] = FAT_OPEN;
        Lanes masks[3][BLOCK];
        uint32_t kinds[3];
        decided_at_once += kern->fat_masks(fat_code, nb, masks, kinds);
        /* Those under every frame of the word, one by one, each kind in a
         * loop of its own (a branch on the kind per slot is a coin toss). */
        Lanes frame_masks[3];
#define DECIDE_SLOTS(bits, call)                                                                                  \
    for (uint32_t left = (bits); left; left &= left - 1) {                                                        \
        const int j = __builtin_ctz(left);                                                                         \
        const float *row = table + (int64_t)ids[i0 + j] * ROW;                                                     \
        call;                                                                                                      \
        masks[0][j] = frame_masks[0], masks[1][j] = frame_masks[1], masks[2][j] = frame_masks[2];                \
    }
        DECIDE_SLOTS(kinds[0], decide_row(&fr, row, frame_masks))
        DECIDE_SLOTS(kinds[1], kern->decide_row_settled(&fr, row, FAT_SCREEN, frame_masks))
        DECIDE_SLOTS(kinds[2], kern->decide_row_settled(&fr, row, FAT_INSIDE, frame_masks))
#undef DECIDE_SLOTS
        /* Each slot's frames, and the children of the open ones. */
        n = kern->push_word_block(h, i0, nb, n, (const Lanes(*)[BLOCK])masks, col[KIDS], visit, whole, yes, kid, ids,
                                  unsure_slots, unsure_lanes, &m);
        if (n < 0)
            return -1;
        i0 += nb;
    }
    *n_unsure = m;
    *at_once = decided_at_once;
    return n;
}

/* A block's fat codes code[0..nb) as the frames' masks (masks[0]: whole,
 * every frame where FAT_WHOLE; masks[1]: yes, every frame where FAT_YES;
 * masks[2]: unsure, none) and the slots left to the frames as bits j of
 * kinds[0] (FAT_OPEN), kinds[1] (FAT_SCREEN), kinds[2] (FAT_INSIDE).
 * Returns the number of slots decided for every frame (FAT_WHOLE, FAT_NO,
 * FAT_YES). */
PMX_INLINE int fat_masks_body(const int32_t *code, int64_t nb, Lanes (*masks)[BLOCK], uint32_t *kinds)
{
    int at_once = 0;
    kinds[0] = kinds[1] = kinds[2] = 0;
    for (int j = 0; j < BLOCK; j++) {
        const int32_t fc = code[j];
        const uint32_t here = j < nb;
        masks[0][j] = here & (fc == FAT_WHOLE) ? (Lanes)0xFFFF : 0;
        masks[1][j] = here & (fc == FAT_YES) ? (Lanes)0xFFFF : 0, masks[2][j] = 0;
        at_once += (int)(here & ((fc == FAT_WHOLE) | (fc == FAT_NO) | (fc == FAT_YES)));
        kinds[0] |= (here & (fc == FAT_OPEN)) << j;
        kinds[1] |= (here & (fc == FAT_SCREEN)) << j;
        kinds[2] |= (here & (fc == FAT_INSIDE)) << j;
    }
    return at_once;
}
int fat_masks_plain(const int32_t *code, int64_t nb, Lanes (*masks)[BLOCK], uint32_t *kinds)
{
    return fat_masks_body(code, nb, masks, kinds);
}
#if PMX_X86
PMX_TARGET_AVX2 int fat_masks_avx2(const int32_t *code, int64_t nb, Lanes (*masks)[BLOCK], uint32_t *kinds)
{
    return fat_masks_body(code, nb, masks, kinds);
}
/* The same with AVX-512's compares into mask registers (the plain loop
 * builds each mask bit by bit). */
PMX_TARGET_AVX512 int fat_masks_avx512(const int32_t *code, int64_t nb, Lanes (*masks)[BLOCK], uint32_t *kinds)
{
    const __mmask16 valid = (__mmask16)((1u << nb) - 1);
    const __m512i c = _mm512_loadu_si512(code), every = _mm512_set1_epi32(0xFFFF);
    const __mmask16 whole = _mm512_mask_cmpeq_epi32_mask(valid, c, _mm512_set1_epi32(FAT_WHOLE));
    const __mmask16 yes = _mm512_mask_cmpeq_epi32_mask(valid, c, _mm512_set1_epi32(FAT_YES));
    const __mmask16 no = _mm512_mask_cmpeq_epi32_mask(valid, c, _mm512_set1_epi32(FAT_NO));
    _mm256_storeu_si256((__m256i *)masks[0], _mm512_cvtepi32_epi16(_mm512_maskz_mov_epi32(whole, every)));
    _mm256_storeu_si256((__m256i *)masks[1], _mm512_cvtepi32_epi16(_mm512_maskz_mov_epi32(yes, every)));
    _mm256_storeu_si256((__m256i *)masks[2], _mm256_setzero_si256());
    kinds[0] = _mm512_mask_cmpeq_epi32_mask(valid, c, _mm512_set1_epi32(FAT_OPEN));
    kinds[1] = _mm512_mask_cmpeq_epi32_mask(valid, c, _mm512_set1_epi32(FAT_SCREEN));
    kinds[2] = _mm512_mask_cmpeq_epi32_mask(valid, c, _mm512_set1_epi32(FAT_INSIDE));
    return _mm_popcnt_u32((uint32_t)(whole | yes | no));
}
#endif

/* Bottom-up for a word: per frame, a slot ran if the frame did not visit it
 * (decided above), its bound decided it, or it collapses and both children
 * ran. Writes ran[], pcols[] (each slot's pcol; optional) and per frame the
 * pcols that did not run and the faces they keep (counts[FRAMES]). */
PMX_INLINE void resolve_word_range(const int32_t *kills, const int32_t *order, int64_t lo, int64_t hi,
                                   const int32_t *ids, const int32_t *kid, const Lanes *visit, const Lanes *whole,
                                   const Lanes *yes, Lanes *ran, int32_t *pcols, int32_t *failures, int32_t *keeps)
{
    /* Per-frame counts as int32 lanes (one vector add per slot that failed
     * somewhere; no count exceeds P or F). */
    for (int64_t i = hi - 1; i >= lo; i--) {
        const int32_t k1 = kid[2 * i], k2 = kid[2 * i + 1];
        const Lanes below = (Lanes)((k1 < 0 ? 0xFFFF : ran[k1]) & (k2 < 0 ? 0xFFFF : ran[k2]));
        const Lanes r = (Lanes)(~visit[i] | whole[i] | (yes[i] & below));
        ran[i] = r;
        if (pcols) /* not for counts alone: order[] is read at random */
            pcols[i] = order[ids[i]];
        const uint32_t failed = (Lanes)~r;
        if (failed) {
            const int32_t k = kills[ids[i]];
#pragma omp simd
            for (int l = 0; l < FRAMES; l++) {
                const int32_t bit = (int32_t)((failed >> l) & 1);
                failures[l] += bit;
                keeps[l] += bit * k;
            }
        }
    }
}

PMX_INLINE void resolve_word_body(const int32_t *kills, const int32_t *order, int64_t n, const int32_t *ids,
                                  const int32_t *kid, const Lanes *visit, const Lanes *whole, const Lanes *yes,
                                  Lanes *ran, int32_t *pcols, PmxCounts *counts)
{
    int32_t failures[FRAMES] = {0}, keeps[FRAMES] = {0};
    resolve_word_range(kills, order, 0, n, ids, kid, visit, whole, yes, ran, pcols, failures, keeps);
    for (int l = 0; l < FRAMES; l++)
        counts[l].not_run = failures[l], counts[l].kept = keeps[l];
}

void resolve_word_plain(const int32_t *kills, const int32_t *order, int64_t n, const int32_t *ids, const int32_t *kid,
                        const Lanes *visit, const Lanes *whole, const Lanes *yes, Lanes *ran, int32_t *pcols,
                        PmxCounts *counts)
{
    resolve_word_body(kills, order, n, ids, kid, visit, whole, yes, ran, pcols, counts);
}
#if PMX_X86
PMX_TARGET_AVX2 void resolve_word_avx2(const int32_t *kills, const int32_t *order, int64_t n, const int32_t *ids,
                                       const int32_t *kid, const Lanes *visit, const Lanes *whole, const Lanes *yes,
                                       Lanes *ran, int32_t *pcols, PmxCounts *counts)
{
    resolve_word_body(kills, order, n, ids, kid, visit, whole, yes, ran, pcols, counts);
}
/* The same sixteen slots at a time with AVX-512 (the scalar loop's branch on
 * whether a slot failed somewhere is a coin toss): groups of slots aligned
 * to multiples of sixteen from slot 0, visited from the end, whose children
 * all sit in later groups (a group of the rare stretch where the queue ran
 * short of a block may hold its own children and goes through the scalar
 * loop). ran[] needs 2 bytes past n:
 * the children's frames are gathered as int32. Same results, bit for bit. */
PMX_TARGET_AVX512 void resolve_word_avx512(const int32_t *kills, const int32_t *order, int64_t n, const int32_t *ids,
                                           const int32_t *kid, const Lanes *visit, const Lanes *whole,
                                           const Lanes *yes, Lanes *ran, int32_t *pcols, PmxCounts *counts)
{
    int32_t failures[FRAMES] = {0}, keeps[FRAMES] = {0};
    const __m512i none = _mm512_set1_epi32(-1), zero = _mm512_setzero_si512(), every = _mm512_set1_epi32(0xFFFF);
    const __m512i frame_bit = _mm512_sllv_epi32(_mm512_set1_epi32(1), _mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8,
                                                                                       7, 6, 5, 4, 3, 2, 1, 0));
    /* Each slot's first and second child out of the pairs kid[2j], kid[2j + 1]. */
    const __m512i even = _mm512_set_epi32(30, 28, 26, 24, 22, 20, 18, 16, 14, 12, 10, 8, 6, 4, 2, 0);
    const __m512i odd = _mm512_add_epi32(even, _mm512_set1_epi32(1));
    __m512i not_run = zero, kept = zero; /* lane l: frame l */
    for (int64_t s = (n - 1) & ~(int64_t)(BLOCK - 1); s >= 0; s -= BLOCK) {
        const int64_t nb = n - s < BLOCK ? n - s : BLOCK;
        const __mmask16 valid = (__mmask16)((1u << nb) - 1);
        const uint32_t kid_valid = nb == BLOCK ? 0xFFFFFFFFu : (1u << (2 * nb)) - 1;
        const __m512i pairs_lo = _mm512_mask_loadu_epi32(none, (__mmask16)kid_valid, kid + 2 * s);
        const __m512i pairs_hi = _mm512_mask_loadu_epi32(none, (__mmask16)(kid_valid >> 16), kid + 2 * s + BLOCK);
        const __m512i k1 = _mm512_permutex2var_epi32(pairs_lo, even, pairs_hi);
        const __m512i k2 = _mm512_permutex2var_epi32(pairs_lo, odd, pairs_hi);
        const __mmask16 has1 = _mm512_cmpge_epi32_mask(k1, zero), has2 = _mm512_cmpge_epi32_mask(k2, zero);
        const __m512i end = _mm512_set1_epi32((int32_t)(s + nb));
        if (_mm512_mask_cmplt_epi32_mask(has1, k1, end) | _mm512_mask_cmplt_epi32_mask(has2, k2, end)) {
            resolve_word_range(kills, order, s, s + nb, ids, kid, visit, whole, yes, ran, pcols, failures, keeps);
            continue;
        }
        /* The children's frames (every frame where there is no child). */
        const __m512i r1 = _mm512_mask_i32gather_epi32(every, has1, k1, ran, 2);
        const __m512i r2 = _mm512_mask_i32gather_epi32(every, has2, k2, ran, 2);
        const __m512i below = _mm512_and_si512(_mm512_and_si512(r1, r2), every);
        const __m512i v = _mm512_cvtepu16_epi32(_mm256_maskz_loadu_epi16(valid, visit + s));
        const __m512i wh = _mm512_cvtepu16_epi32(_mm256_maskz_loadu_epi16(valid, whole + s));
        const __m512i y = _mm512_cvtepu16_epi32(_mm256_maskz_loadu_epi16(valid, yes + s));
        /* r = ~visit | whole | (yes & below), and the frames where it failed. */
        const __m512i r = _mm512_ternarylogic_epi32(wh, y, below, 0xF8); /* wh | (y & below) */
        const __m512i failed = _mm512_andnot_si512(r, v);
        _mm512_mask_cvtepi32_storeu_epi16(ran + s, valid, _mm512_xor_si512(failed, every));
        const __m512i at = _mm512_maskz_loadu_epi32(valid, ids + s);
        if (pcols) /* not for counts alone: order[] is read at random */
            _mm512_mask_storeu_epi32(pcols + s, valid, _mm512_mask_i32gather_epi32(zero, valid, at, order, 4));
        __mmask16 some = _mm512_mask_test_epi32_mask(valid, failed, failed);
        if (!some)
            continue;
        int32_t f[BLOCK], k[BLOCK];
        _mm512_storeu_si512(f, failed);
        _mm512_storeu_si512(k, _mm512_mask_i32gather_epi32(zero, some, at, kills, 4));
        /* Each failing slot into its frames' counts. */
        for (uint32_t left = some; left; left &= left - 1) {
            const int j = __builtin_ctz(left);
            const __mmask16 frames = _mm512_test_epi32_mask(_mm512_set1_epi32(f[j]), frame_bit);
            not_run = _mm512_mask_add_epi32(not_run, frames, not_run, _mm512_set1_epi32(1));
            kept = _mm512_mask_add_epi32(kept, frames, kept, _mm512_set1_epi32(k[j]));
        }
    }
    int32_t nr[FRAMES], kp[FRAMES];
    _mm512_storeu_si512(nr, not_run);
    _mm512_storeu_si512(kp, kept);
    for (int l = 0; l < FRAMES; l++)
        counts[l].not_run = failures[l] + nr[l], counts[l].kept = keeps[l] + kp[l];
}
#endif

/* Words shared by a call's threads, taken one at a time from a cursor. */
typedef struct {
    const PmxHierarchy *h;
    const float *views;
    int flags;
    int64_t W, cursor;
    PmxCounts *counts;
    int32_t *at_once;
    PmxLists lists;
    PmxRecords *records;
    uint8_t *overflow;
    PmxStatus status;
} Words;

static void words_work(void *arg)
{
    Words *b = arg;
    const PmxHierarchy *h = b->h;
    const int64_t stride = h->n_pcols + PMX_SPARE;
    PmxScratch *s = pmx_scratch_take(h->n_pcols);
    if (!s || !scratch_slots(s) || !scratch_words(s)) {
        __atomic_store_n(&b->status, PMX_NO_MEMORY, __ATOMIC_RELAXED);
        if (s)
            pmx_scratch_give(s);
        return;
    }
    const unsigned mode = subnormals_off();
    const Kernels *kern = pmx_kernels();
    for (int64_t w; (w = __atomic_fetch_add(&b->cursor, 1, __ATOMIC_RELAXED)) < b->W;) {
        const float *views = b->views + w * FRAMES * PMX_VIEW;
        float fat[PMX_FAT];
        const int have_fat = pmx_fat_cameras(views, 1, FRAMES, fat) == PMX_OK;
        int32_t *ids = b->lists.positions ? b->lists.positions + w * stride : s->ids;
        Lanes *ran = b->lists.ran_frames ? b->lists.ran_frames + w * stride : s->ran_frames;
        int32_t *pcols = b->lists.pcols ? b->lists.pcols + w * stride : NULL;
        int64_t m = 0, at_once = 0;
        const int64_t n = traverse_word(kern, h, views, FRAMES, b->flags, have_fat ? fat : NULL, ids, s->kid,
                                        s->visit, s->whole, s->yes, s->unsure, s->unsure_lanes, &m, &at_once);
        if (n < 0) {
            __atomic_store_n(&b->status, PMX_BAD_TABLE, __ATOMIC_RELAXED);
            break;
        }
        PmxCounts *counts = b->counts + w * FRAMES;
        /* Unsure pairs are taken as "keep" (their yes bits clear). They are
         * counted after the fat pass: a FAT_YES pcol, which the float32
         * predicate collapses in every frame, is not among them even where
         * a frame's own certificate may have been unsure. */
        kern->resolve_word(h->kills, h->order, n, ids, s->kid, s->visit, s->whole, s->yes, ran, pcols, counts);
        for (int l = 0; l < FRAMES; l++)
            counts[l].visited = (int32_t)n, counts[l].unsure = 0;
        for (int64_t q = 0; q < m; q++)
            for (int l = 0; l < FRAMES; l++)
                counts[l].unsure += (s->unsure_lanes[q] >> l) & 1;
        if (b->at_once)
            b->at_once[w] = (int32_t)at_once;
        b->overflow[w] = 0;
        if (m > 0) {
            const int64_t count = record_chain(n, h->n_roots, s->kid, s->unsure, m, s->parent, 0, s->chain, s->mark);
            const int64_t at = records_reserve(b->records, 2 + count * PMX_NODE);
            if (at < 0) {
                b->overflow[w] = 1;
            } else {
                const SlotBits bits = {s->visit, s->whole, s->yes, ran, s->unsure_lanes, NULL, NULL};
                record_write(b->records->records + at, w, count, s->chain, ids, s->kid, &bits, h->kills, s->unsure, m);
            }
        }
    }
    subnormals_back(mode);
    pmx_scratch_give(s);
}

PmxStatus pmx_refine_words(const PmxHierarchy *h, const float *views, int64_t W, int flags, PmxCounts *counts,
                           PmxLists lists, int32_t *at_once, PmxRecords *records, uint8_t *overflow,
                           const PmxRunner *run)
{
    Words b = {h, views, flags, W, 0, counts, at_once, lists, records, overflow, PMX_OK};
    run_shared(run, words_work, &b);
    return b.status;
}
