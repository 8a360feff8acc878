/* The slots' bookkeeping (slots_plain.c) with AVX2. */
#include "internal.h"

#if PMX_X86
#include <immintrin.h>

/* The same two steps with AVX2, eight slots at a time, for processors
 * without AVX-512: compress and expand through small tables made once
 * (racing threads write the same values), no BMI2 (slow on some AMD
 * processors). Same results, bit for bit. */
static int32_t compress8[256][8]; /* mask x: the lanes of its set bits, in order */
static uint8_t rank8[256][8];     /* mask x: set bits of x below each lane */
static uint16_t spread8[256];     /* mask x: bit j moved to bit 2j */
static int tables8 = 0;

static void make_tables8(void)
{
    for (int x = 0; x < 256; x++) {
        int c = 0;
        spread8[x] = 0;
        for (int j = 0; j < 8; j++) {
            rank8[x][j] = (uint8_t)c;
            if (x >> j & 1) {
                compress8[x][c++] = j;
                spread8[x] |= (uint16_t)(1u << (2 * j));
            }
        }
        for (; c < 8; c++)
            compress8[x][c] = 0;
    }
    __atomic_store_n(&tables8, 1, __ATOMIC_RELEASE);
}

/* Lanes below `count` as a mask vector. */
PMX_TARGET_AVX2 static inline __m256i first_lanes(int count)
{
    return _mm256_cmpgt_epi32(_mm256_set1_epi32(count), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
}

/* Bits of an 8-bit mask as a mask vector. */
PMX_TARGET_AVX2 static inline __m256i lanes_of(int bits)
{
    const __m256i bit = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
    return _mm256_cmpeq_epi32(_mm256_and_si256(_mm256_set1_epi32(bits), bit), bit);
}

/* The set lanes (mask x) of v, in order, at out[0..popcount(x)); out[..8)
 * is written (a masked store is slow on some AMD processors), so the
 * queue's arrays have 8 spare slots past P + 2. */
PMX_TARGET_AVX2 static inline void compress_store8(int32_t *out, __m256i v, int x)
{
    _mm256_storeu_si256((__m256i *)out,
                        _mm256_permutevar8x32_epi32(v, _mm256_loadu_si256((const __m256i *)compress8[x])));
}

PMX_TARGET_AVX2 int64_t push_block_avx2(const PmxHierarchy *h, int64_t i, int64_t nb, int64_t n, const int32_t *decided,
                                           const float *kids, uint8_t *state, int32_t *kill, int32_t *kid,
                                           int32_t *ids, int32_t *parent, int32_t *unsure, int64_t *m)
{
    if (!__atomic_load_n(&tables8, __ATOMIC_ACQUIRE))
        make_tables8();
    const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    for (int64_t part = 0; part < nb; part += 8) {
        /* A queue past the table (links that are not a forest) stops before
         * the part's sixteen stores could pass the spare room; the caller
         * checks n. */
        if (n > h->n_pcols)
            return n;
        const int cnt = (int)(nb - part < 8 ? nb - part : 8);
        const int valid = (1 << cnt) - 1;
        const int64_t j0 = i + part;
        const __m256i code = _mm256_loadu_si256((const __m256i *)(decided + part));
        const __m256i k = _mm256_loadu_si256((const __m256i *)(kids + part));
        const __m256i own = _mm256_and_si256(code, _mm256_set1_epi32(YES | UNSURE));
        /* Own decisions as bytes (byte 0 of each lane, both 128-bit halves). */
        const __m256i pick = _mm256_setr_epi8(0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, 0, 4, 8,
                                              12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1);
        const __m256i bytes = _mm256_shuffle_epi8(own, pick);
        const uint64_t packed = (uint64_t)(uint32_t)_mm_cvtsi128_si32(_mm256_castsi256_si128(bytes)) |
                                (uint64_t)(uint32_t)_mm_cvtsi128_si32(_mm256_extracti128_si256(bytes, 1)) << 32;
        if (cnt == 8)
            memcpy(state + j0, &packed, 8);
        else
            memcpy(state + j0, &packed, (size_t)cnt);
        int rare = _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(own, _mm256_set1_epi32(UNSURE)))) & valid;
        for (; rare; rare &= rare - 1) /* rare: decided by the caller (the float32 predicate) */
            unsure[(*m)++] = (int32_t)(j0 + __builtin_ctz((unsigned)rare));
        /* Two faces killed, but where the sign bit says otherwise (rare). */
        if (cnt == 8)
            _mm256_storeu_si256((__m256i *)(kill + j0), _mm256_set1_epi32(2));
        else
            _mm256_maskstore_epi32(kill + j0, first_lanes(cnt), _mm256_set1_epi32(2));
        for (int odd = _mm256_movemask_ps(_mm256_castsi256_ps(k)) & valid; odd; odd &= odd - 1) {
            const int64_t j = j0 + __builtin_ctz((unsigned)odd);
            kill[j] = h->kills[ids[j]];
        }
        /* Lanes with at least one / two children to visit, as one mask of
         * the children in queue order (bit 2j: lane j's first, 2j + 1: its
         * second). */
        const __m256i open = _mm256_cmpeq_epi32(_mm256_and_si256(code, _mm256_set1_epi32(WHOLE)),
                                                _mm256_setzero_si256());
        const __m256i count = _mm256_and_si256(k, _mm256_set1_epi32(3));
        const int one = _mm256_movemask_ps(_mm256_castsi256_ps(
                            _mm256_and_si256(open, _mm256_cmpgt_epi32(count, _mm256_setzero_si256())))) & valid;
        const int two = _mm256_movemask_ps(_mm256_castsi256_ps(
                            _mm256_and_si256(open, _mm256_cmpgt_epi32(count, _mm256_set1_epi32(1))))) & valid;
        const unsigned pushed = spread8[one] | (unsigned)spread8[two] << 1;
        const int lo = (int)(pushed & 0xFF), hi = (int)(pushed >> 8);
        const int n_lo = _mm_popcnt_u32((unsigned)lo), n_hi = _mm_popcnt_u32((unsigned)hi);
        /* Their slots (-1 where no child is visited): n + the pushed bits below. */
        const __m256i none = _mm256_set1_epi32(-1);
        const __m256i rank_lo = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)rank8[lo]));
        const __m256i rank_hi = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)rank8[hi]));
        const __m256i slot_lo = _mm256_blendv_epi8(none, _mm256_add_epi32(rank_lo, _mm256_set1_epi32((int32_t)n)),
                                                   lanes_of(lo));
        const __m256i slot_hi = _mm256_blendv_epi8(
            none, _mm256_add_epi32(rank_hi, _mm256_set1_epi32((int32_t)n + n_lo)), lanes_of(hi));
        if (cnt == 8) {
            _mm256_storeu_si256((__m256i *)(kid + 2 * j0), slot_lo);
            _mm256_storeu_si256((__m256i *)(kid + 2 * j0 + 8), slot_hi);
        } else {
            _mm256_maskstore_epi32(kid + 2 * j0, first_lanes(2 * cnt), slot_lo);
            _mm256_maskstore_epi32(kid + 2 * j0 + 8, first_lanes(2 * cnt - 8), slot_hi);
        }
        /* Their positions: (first, first + 1) of each lane interleaved, compressed. */
        const __m256i first = _mm256_and_si256(_mm256_srli_epi32(k, 2), _mm256_set1_epi32(KIDS_FIRST));
        const __m256i second = _mm256_add_epi32(first, _mm256_set1_epi32(1));
        const __m256i a = _mm256_unpacklo_epi32(first, second), b = _mm256_unpackhi_epi32(first, second);
        compress_store8(ids + n, _mm256_permute2x128_si256(a, b, 0x20), lo);
        compress_store8(ids + n + n_lo, _mm256_permute2x128_si256(a, b, 0x31), hi);
        if (parent) { /* each child's parent slot, the same way */
            const __m256i slot = _mm256_add_epi32(lane, _mm256_set1_epi32((int32_t)j0));
            const __m256i c = _mm256_unpacklo_epi32(slot, slot), d = _mm256_unpackhi_epi32(slot, slot);
            compress_store8(parent + n, _mm256_permute2x128_si256(c, d, 0x20), lo);
            compress_store8(parent + n + n_lo, _mm256_permute2x128_si256(c, d, 0x31), hi);
        }
        n += n_lo + n_hi;
    }
    return n;
}

/* resolve_plain_range over all n slots, sixteen at a time as resolve_avx512
 * (a block that holds its own children goes through resolve_plain_range). */
PMX_TARGET_AVX2 void resolve_avx2(const PmxHierarchy *h, int64_t n, const int32_t *ids, const int32_t *kid,
                                     const uint8_t *state, const int32_t *kill, uint8_t *ran, int32_t *pcols,
                                     int64_t *n_not_run, int64_t *kept)
{
    const __m256i zero = _mm256_setzero_si256(), one = _mm256_set1_epi32(1), byte = _mm256_set1_epi32(0xFF);
    __m256i keep = zero; /* per lane: no sum exceeds the face count (int32) */
    int64_t not_run = 0, keep_plain = 0;
    for (int64_t s = (n - 1) & ~(int64_t)(BLOCK - 1); s >= 0; s -= BLOCK) {
        const int64_t nb = n - s < BLOCK ? n - s : BLOCK;
        /* The children's slots, four vectors of four slots' two children. */
        __m256i kv[4], has[4];
        int inside = 0;
        for (int q = 0; q < 4; q++) {
            const int left = (int)(2 * nb - 8 * q); /* children of this block in vector q */
            const __m256i live = first_lanes(left < 0 ? 0 : left);
            kv[q] = _mm256_blendv_epi8(_mm256_set1_epi32(-1), _mm256_maskload_epi32(kid + 2 * s + 8 * q, live), live);
            has[q] = _mm256_cmpgt_epi32(kv[q], _mm256_set1_epi32(-1));
            inside |= _mm256_movemask_ps(_mm256_castsi256_ps(
                _mm256_and_si256(has[q], _mm256_cmpgt_epi32(_mm256_set1_epi32((int32_t)(s + nb)), kv[q]))));
        }
        if (inside) {
            resolve_plain_range(h, s, s + nb, ids, kid, state, kill, ran, pcols, &not_run, &keep_plain);
            continue;
        }
        /* Both children ran (1 where there is no child): bit j for slot s + j. */
        int below = 0;
        for (int q = 0; q < 4; q++) {
            const __m256i r = _mm256_mask_i32gather_epi32(one, (const int *)ran, kv[q], has[q], 1);
            const __m256i child = _mm256_cmpgt_epi32(_mm256_and_si256(r, byte), zero);
            /* Each lane and its pair's lane: both children of a slot. */
            const __m256i both = _mm256_and_si256(child, _mm256_shuffle_epi32(child, _MM_SHUFFLE(2, 3, 0, 1)));
            const int bits = _mm256_movemask_ps(_mm256_castsi256_ps(both)); /* even bits: slots */
            below |= ((bits & 1) | (bits >> 1 & 2) | (bits >> 2 & 4) | (bits >> 3 & 8)) << (4 * q);
        }
        /* The block's own decisions and ran bytes (whole blocks but the last). */
        __m128i st;
        if (nb == BLOCK) {
            st = _mm_loadu_si128((const __m128i *)(state + s));
        } else {
            uint8_t part[BLOCK] = {0};
            memcpy(part, state + s, (size_t)nb);
            st = _mm_loadu_si128((const __m128i *)part);
        }
        const int yes = _mm_movemask_epi8(_mm_cmpeq_epi8(st, _mm_set1_epi8(YES)));
        const int valid = (int)((1u << nb) - 1);
        const int r = yes & below & valid, failed = valid & ~r;
        const __m128i bit = _mm_setr_epi8(1, 2, 4, 8, 16, 32, 64, -128, 1, 2, 4, 8, 16, 32, 64, -128);
        const __m128i spread = _mm_shuffle_epi8(_mm_cvtsi32_si128(r), _mm_setr_epi8(0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1,
                                                                                     1, 1, 1, 1, 1));
        const __m128i out = _mm_and_si128(_mm_cmpeq_epi8(_mm_and_si128(spread, bit), bit), _mm_set1_epi8(1));
        if (nb == BLOCK) {
            _mm_storeu_si128((__m128i *)(ran + s), out);
        } else {
            uint8_t part[BLOCK];
            _mm_storeu_si128((__m128i *)part, out);
            memcpy(ran + s, part, (size_t)nb);
        }
        not_run += _mm_popcnt_u32((unsigned)failed);
        for (int q = 0; q < 2; q++) {
            const __m256i f = lanes_of(failed >> (8 * q) & 0xFF);
            keep = _mm256_add_epi32(keep, _mm256_maskload_epi32(kill + s + 8 * q, f));
            if (pcols) { /* not for counts alone: order[] is read at random */
                const __m256i v = lanes_of(valid >> (8 * q) & 0xFF);
                const __m256i at = _mm256_maskload_epi32(ids + s + 8 * q, v);
                const __m256i got = _mm256_mask_i32gather_epi32(zero, h->order, at, v, 4);
                if (nb == BLOCK)
                    _mm256_storeu_si256((__m256i *)(pcols + s + 8 * q), got);
                else
                    _mm256_maskstore_epi32(pcols + s + 8 * q, v, got);
            }
        }
    }
    const __m128i sum4 = _mm_add_epi32(_mm256_castsi256_si128(keep), _mm256_extracti128_si256(keep, 1));
    const __m128i sum2 = _mm_add_epi32(sum4, _mm_shuffle_epi32(sum4, _MM_SHUFFLE(1, 0, 3, 2)));
    *n_not_run = not_run;
    *kept = keep_plain + _mm_cvtsi128_si32(_mm_add_epi32(sum2, _mm_shuffle_epi32(sum2, _MM_SHUFFLE(2, 3, 0, 1))));
}

#endif
