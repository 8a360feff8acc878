/* The slots' bookkeeping (slots_plain.c) with AVX-512 masks. */
#include "internal.h"

#if PMX_X86
#include <immintrin.h>

/* The sixteen slots first, first + 1, ..., first + 15, lane by lane. */
PMX_INLINE PMX_TARGET_AVX512 __m512i slots_from(int64_t first)
{
    const __m512i lane = _mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0);
    return _mm512_add_epi32(lane, _mm512_set1_epi32((int32_t)first));
}

/* Lanes j of a and b interleaved (a_0, b_0, a_1, b_1, ...) in queue order
 * and compressed: the block's first eight lanes' pairs by lo into *at_lo, the
 * last eight's by hi into *at_hi. */
PMX_INLINE PMX_TARGET_AVX512 void spread_pairs(__m512i a, __m512i b, __mmask16 lo, __mmask16 hi, __m512i *at_lo,
                                               __m512i *at_hi)
{
    const __m512i pick_lo = _mm512_set_epi32(23, 7, 22, 6, 21, 5, 20, 4, 19, 3, 18, 2, 17, 1, 16, 0);
    const __m512i pick_hi = _mm512_add_epi32(pick_lo, _mm512_set1_epi32(8));
    *at_lo = _mm512_maskz_compress_epi32(lo, _mm512_permutex2var_epi32(a, pick_lo, b));
    *at_hi = _mm512_maskz_compress_epi32(hi, _mm512_permutex2var_epi32(a, pick_hi, b));
}

/* The children of the open lanes of block [i, i + nb) (k: their rows' KIDS
 * column) pushed behind the queue at n: their slots into kid[] (-1 where no
 * child is visited), their positions into ids[]; *lo, *hi: the children in
 * queue order (bit 2j: lane j's first, 2j + 1: its second) of the first and
 * the last eight lanes, *n_lo, *n_hi their numbers. Returns the new end of
 * the queue, or -1 (nothing pushed) where it would pass limit. */
PMX_INLINE PMX_TARGET_AVX512 int64_t push_children(__m512i k, __mmask16 open, int64_t i, int64_t nb, int64_t n,
                                                   int64_t limit, int32_t *kid, int32_t *ids, __mmask16 *lo,
                                                   __mmask16 *hi, int *n_lo, int *n_hi)
{
    /* Lanes with at least one / two children to visit. */
    const __m512i count = _mm512_and_si512(k, _mm512_set1_epi32(3));
    const __mmask16 one = _mm512_mask_cmpgt_epi32_mask(open, count, _mm512_setzero_si512());
    const __mmask16 two = _mm512_mask_cmpgt_epi32_mask(open, count, _mm512_set1_epi32(1));
    const uint32_t pushed = _pdep_u32(one, 0x55555555u) | _pdep_u32(two, 0xAAAAAAAAu);
    *lo = (__mmask16)pushed, *hi = (__mmask16)(pushed >> 16);
    *n_lo = _mm_popcnt_u32(*lo), *n_hi = _mm_popcnt_u32(*hi);
    if (n + *n_lo + *n_hi > limit)
        return -1;
    /* Their slots (-1 where no child is visited): n, n + 1, ... expanded. */
    const __m512i none = _mm512_set1_epi32(-1);
    const __m512i slot_lo = _mm512_mask_expand_epi32(none, *lo, slots_from(n));
    const __m512i slot_hi = _mm512_mask_expand_epi32(none, *hi, slots_from(n + *n_lo));
    const uint32_t kid_valid = nb == BLOCK ? 0xFFFFFFFFu : (1u << (2 * nb)) - 1;
    _mm512_mask_storeu_epi32(kid + 2 * i, (__mmask16)kid_valid, slot_lo);
    _mm512_mask_storeu_epi32(kid + 2 * i + BLOCK, (__mmask16)(kid_valid >> 16), slot_hi);
    /* Their positions: (first, first + 1) of each lane interleaved, compressed. */
    const __m512i first = _mm512_and_si512(_mm512_srli_epi32(k, 2), _mm512_set1_epi32(KIDS_FIRST));
    __m512i at_lo, at_hi;
    spread_pairs(first, _mm512_add_epi32(first, _mm512_set1_epi32(1)), *lo, *hi, &at_lo, &at_hi);
    _mm512_mask_storeu_epi32(ids + n, (__mmask16)((1u << *n_lo) - 1), at_lo);
    _mm512_mask_storeu_epi32(ids + n + *n_lo, (__mmask16)((1u << *n_hi) - 1), at_hi);
    return n + *n_lo + *n_hi;
}

/* The same two steps with AVX-512 masks, sixteen slots at a time: the
 * scalar versions store, shift and count slot by slot, where masks do a
 * block's sixteen in a few instructions. Same results, bit for bit. */
PMX_TARGET_AVX512 int64_t push_block_avx512(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n,
                                              const int32_t *decided, const float *kids, uint8_t *state,
                                              int32_t *kill, int32_t *kid, int32_t *ids, int32_t *parent,
                                              int32_t *unsure, int64_t *m)
{
    const __mmask16 valid = (__mmask16)((1u << nb) - 1);
    const __m512i code = _mm512_loadu_si512(decided);
    const __m512i own = _mm512_and_si512(code, _mm512_set1_epi32(YES | UNSURE));
    _mm512_mask_cvtepi32_storeu_epi8(state + i, valid, own);
    const __mmask16 unsure_lanes = _mm512_mask_cmpeq_epi32_mask(valid, own, _mm512_set1_epi32(UNSURE));
    if (unsure_lanes) { /* rare: decided by the caller (the float32 predicate) */
        _mm512_mask_compressstoreu_epi32(unsure + *m, unsure_lanes, slots_from(i));
        *m += _mm_popcnt_u32(unsure_lanes);
    }
    /* The rows' KIDS column. */
    const __m512i k = _mm512_loadu_si512(kids);
    /* Two faces killed, but where the sign bit says otherwise (rare). */
    const __mmask16 odd = _mm512_mask_cmplt_epi32_mask(valid, k, _mm512_setzero_si512());
    __m512i kills = _mm512_set1_epi32(2);
    if (odd)
        kills = _mm512_mask_i32gather_epi32(kills, odd, _mm512_maskz_loadu_epi32(odd, ids + i), h->kills, 4);
    _mm512_mask_storeu_epi32(kill + i, valid, kills);
    const __mmask16 open = _mm512_mask_testn_epi32_mask(valid, code, _mm512_set1_epi32(WHOLE));
    __mmask16 lo, hi;
    int n_lo, n_hi;
    const int64_t end = push_children(k, open, i, nb, n, h->n_pcols, kid, ids, &lo, &hi, &n_lo, &n_hi);
    if (end < 0)
        return -1;
    if (parent) { /* each child's parent slot, the same way */
        const __m512i slot = slots_from(i);
        __m512i at_lo, at_hi;
        spread_pairs(slot, slot, lo, hi, &at_lo, &at_hi);
        _mm512_mask_storeu_epi32(parent + n, (__mmask16)((1u << n_lo) - 1), at_lo);
        _mm512_mask_storeu_epi32(parent + n + n_lo, (__mmask16)((1u << n_hi) - 1), at_hi);
    }
    return end;
}

/* push_word_block_plain with AVX-512 masks, the sixteen slots of a block at
 * once (the frame masks widened to int32 lanes): the scalar loop's branches
 * on whether a slot is open are coin tosses. Same results, bit for bit. */
PMX_TARGET_AVX512 int64_t push_word_block_avx512(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n,
                                                   const Lanes (*masks)[BLOCK], const float *kids, Lanes *visit,
                                                   Lanes *whole, Lanes *yes, int32_t *kid, int32_t *ids,
                                                   int32_t *unsure_slots, Lanes *unsure_lanes, int64_t *m)
{
    const __mmask16 valid = (__mmask16)((1u << nb) - 1);
    const __m512i v = _mm512_cvtepu16_epi32(_mm256_maskz_loadu_epi16(valid, visit + i));
    const __m512i wh = _mm512_cvtepu16_epi32(_mm256_loadu_si256((const __m256i *)masks[0]));
    const __m512i y = _mm512_cvtepu16_epi32(_mm256_loadu_si256((const __m256i *)masks[1]));
    const __m512i u = _mm512_cvtepu16_epi32(_mm256_loadu_si256((const __m256i *)masks[2]));
    /* The visiting frames the bound decided, and those it left open. */
    const __m512i open_frames = _mm512_andnot_si512(wh, v);
    _mm512_mask_cvtepi32_storeu_epi16(whole + i, valid, _mm512_and_si512(v, wh));
    _mm512_mask_cvtepi32_storeu_epi16(yes + i, valid, _mm512_and_si512(open_frames, y));
    const __m512i un = _mm512_and_si512(open_frames, u);
    const __mmask16 unsure = _mm512_mask_test_epi32_mask(valid, un, un);
    if (unsure) { /* rare: decided by the caller (the float32 predicate) */
        const __mmask16 first_ones = (__mmask16)((1u << _mm_popcnt_u32(unsure)) - 1);
        _mm512_mask_compressstoreu_epi32(unsure_slots + *m, unsure, slots_from(i));
        _mm512_mask_cvtepi32_storeu_epi16(unsure_lanes + *m, first_ones, _mm512_maskz_compress_epi32(unsure, un));
        *m += _mm_popcnt_u32(unsure);
    }
    /* The children of the slots some visiting frame left open. */
    const __mmask16 open = _mm512_mask_test_epi32_mask(valid, open_frames, open_frames);
    const __m512i k = _mm512_loadu_si512(kids);
    __mmask16 lo, hi;
    int n_lo, n_hi;
    const int64_t end = push_children(k, open, i, nb, n, h->n_pcols, kid, ids, &lo, &hi, &n_lo, &n_hi);
    if (end < 0)
        return -1;
    /* Their frames, the parent's open ones, the same way. */
    __m512i at_lo, at_hi;
    spread_pairs(open_frames, open_frames, lo, hi, &at_lo, &at_hi);
    _mm512_mask_cvtepi32_storeu_epi16(visit + n, (__mmask16)((1u << n_lo) - 1), at_lo);
    _mm512_mask_cvtepi32_storeu_epi16(visit + n + n_lo, (__mmask16)((1u << n_hi) - 1), at_hi);
    return end;
}

/* resolve_plain_range over all n slots, sixteen at a time on the traversal's
 * blocks (groups aligned to multiples of sixteen from slot 0, visited from
 * the end, whose children all sit in later blocks; a block of the rare
 * stretch where the queue ran short of sixteen may hold its own children
 * and goes through resolve_plain_range). ran[] needs 3 bytes past n: the
 * children's ran bits are gathered as int32. */
PMX_TARGET_AVX512 void resolve_avx512(const PmxHierarchy *h, int64_t n, const int32_t *ids, const int32_t *kid,
                                        const uint8_t *state, const int32_t *kill, uint8_t *ran, int32_t *pcols,
                                        int64_t *n_not_run, int64_t *kept)
{
    const __m512i none = _mm512_set1_epi32(-1), zero = _mm512_setzero_si512();
    __m512i keep = zero; /* per lane: no sum exceeds the face count (int32) */
    int64_t not_run = 0, keep_plain = 0;
    for (int64_t s = (n - 1) & ~(int64_t)(BLOCK - 1); s >= 0; s -= BLOCK) {
        const int64_t nb = n - s < BLOCK ? n - s : BLOCK;
        const __mmask16 valid = (__mmask16)((1u << nb) - 1);
        const uint32_t kid_valid = nb == BLOCK ? 0xFFFFFFFFu : (1u << (2 * nb)) - 1;
        const __m512i k_lo = _mm512_mask_loadu_epi32(none, (__mmask16)kid_valid, kid + 2 * s);
        const __m512i k_hi = _mm512_mask_loadu_epi32(none, (__mmask16)(kid_valid >> 16), kid + 2 * s + BLOCK);
        const __mmask16 has_lo = _mm512_cmpge_epi32_mask(k_lo, zero), has_hi = _mm512_cmpge_epi32_mask(k_hi, zero);
        const __m512i end = _mm512_set1_epi32((int32_t)(s + nb));
        if (_mm512_mask_cmplt_epi32_mask(has_lo, k_lo, end) | _mm512_mask_cmplt_epi32_mask(has_hi, k_hi, end)) {
            resolve_plain_range(h, s, s + nb, ids, kid, state, kill, ran, pcols, &not_run, &keep_plain);
            continue;
        }
        /* The children's ran bits (1 where there is no child), both of a
         * slot together: bits 2j and 2j + 1 of one mask. */
        const __m512i one = _mm512_set1_epi32(1), byte = _mm512_set1_epi32(0xFF);
        const __m512i r_lo = _mm512_mask_i32gather_epi32(one, has_lo, k_lo, ran, 1);
        const __m512i r_hi = _mm512_mask_i32gather_epi32(one, has_hi, k_hi, ran, 1);
        const uint32_t children = (uint32_t)_mm512_test_epi32_mask(r_lo, byte) |
                                  ((uint32_t)_mm512_test_epi32_mask(r_hi, byte) << 16);
        const __mmask16 below = (__mmask16)_pext_u32(children & (children >> 1), 0x55555555u);
        const __mmask16 yes =
            _mm_mask_cmpeq_epi8_mask(valid, _mm_maskz_loadu_epi8(valid, state + s), _mm_set1_epi8(YES));
        const __mmask16 r = yes & below, failed = valid & (__mmask16)~r;
        _mm_mask_storeu_epi8(ran + s, valid, _mm_maskz_mov_epi8(r, _mm_set1_epi8(1)));
        not_run += _mm_popcnt_u32(failed);
        keep = _mm512_mask_add_epi32(keep, failed, keep, _mm512_maskz_loadu_epi32(failed, kill + s));
        if (pcols) /* not for counts alone: order[] is read at random */
            _mm512_mask_storeu_epi32(pcols + s, valid,
                                     _mm512_mask_i32gather_epi32(zero, valid, _mm512_maskz_loadu_epi32(valid, ids + s),
                                                                 h->order, 4));
    }
    *n_not_run = not_run;
    *kept = keep_plain + _mm512_reduce_add_epi32(keep);
}

#endif
