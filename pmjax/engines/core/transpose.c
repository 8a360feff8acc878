/* Rows into columns: the rows of a block of BLOCK pcols (ROW floats each)
 * as the columns the decisions read. A row is ROW = 16 floats and a block
 * BLOCK = 16 rows, so this is a 16 x 16 transpose: in registers where the
 * processor has AVX-512 or AVX2 (a third of the time of element copies,
 * which also stall the column loads after them). */
#include "internal.h"

#if PMX_X86
#include <immintrin.h>
#endif

void gather_plain(const float *const *rows, Columns col)
{
    for (int j = 0; j < BLOCK; j++)
        for (int c = 0; c < ROW; c++)
            col[c][j] = rows[j][c];
}

#if PMX_X86

PMX_TARGET_AVX512 void gather_avx512(const float *const *rows, Columns col)
{
    __m512 r[16], t[16];
    for (int j = 0; j < 16; j++)
        r[j] = _mm512_loadu_ps(rows[j]);
    /* Pairs of rows interleaved, then pairs of pairs, then 128-bit lanes twice. */
    for (int j = 0; j < 16; j += 2) {
        t[j] = _mm512_unpacklo_ps(r[j], r[j + 1]);
        t[j + 1] = _mm512_unpackhi_ps(r[j], r[j + 1]);
    }
    for (int j = 0; j < 16; j += 4) {
        __m512d a = _mm512_castps_pd(t[j]), b = _mm512_castps_pd(t[j + 1]);
        __m512d c = _mm512_castps_pd(t[j + 2]), d = _mm512_castps_pd(t[j + 3]);
        r[j] = _mm512_castpd_ps(_mm512_unpacklo_pd(a, c));
        r[j + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(a, c));
        r[j + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(b, d));
        r[j + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(b, d));
    }
    for (int j = 0; j < 4; j++) {
        t[j] = _mm512_shuffle_f32x4(r[j], r[j + 4], 0x88);
        t[j + 4] = _mm512_shuffle_f32x4(r[j], r[j + 4], 0xdd);
        t[j + 8] = _mm512_shuffle_f32x4(r[j + 8], r[j + 12], 0x88);
        t[j + 12] = _mm512_shuffle_f32x4(r[j + 8], r[j + 12], 0xdd);
    }
    for (int j = 0; j < 8; j++) {
        _mm512_storeu_ps(col[j], _mm512_shuffle_f32x4(t[j], t[j + 8], 0x88));
        _mm512_storeu_ps(col[j + 8], _mm512_shuffle_f32x4(t[j], t[j + 8], 0xdd));
    }
}

/* One 8 x 8 quarter: rows[0..8) from column c0 into col[c0..c0+8)[j0..j0+8). */
PMX_TARGET_AVX2 static inline void transpose8(const float *const *rows, int c0, Columns col, int j0)
{
    __m256 r[8], t[8], u[8];
    for (int j = 0; j < 8; j++)
        r[j] = _mm256_loadu_ps(rows[j] + c0);
    for (int j = 0; j < 8; j += 2) {
        t[j] = _mm256_unpacklo_ps(r[j], r[j + 1]);
        t[j + 1] = _mm256_unpackhi_ps(r[j], r[j + 1]);
    }
    for (int j = 0; j < 8; j += 4) {
        u[j] = _mm256_shuffle_ps(t[j], t[j + 2], _MM_SHUFFLE(1, 0, 1, 0));
        u[j + 1] = _mm256_shuffle_ps(t[j], t[j + 2], _MM_SHUFFLE(3, 2, 3, 2));
        u[j + 2] = _mm256_shuffle_ps(t[j + 1], t[j + 3], _MM_SHUFFLE(1, 0, 1, 0));
        u[j + 3] = _mm256_shuffle_ps(t[j + 1], t[j + 3], _MM_SHUFFLE(3, 2, 3, 2));
    }
    for (int j = 0; j < 4; j++) {
        _mm256_storeu_ps(col[c0 + j] + j0, _mm256_permute2f128_ps(u[j], u[j + 4], 0x20));
        _mm256_storeu_ps(col[c0 + j + 4] + j0, _mm256_permute2f128_ps(u[j], u[j + 4], 0x31));
    }
}

PMX_TARGET_AVX2 void gather_avx2(const float *const *rows, Columns col)
{
    transpose8(rows, 0, col, 0);
    transpose8(rows, 8, col, 0);
    transpose8(rows + 8, 0, col, 8);
    transpose8(rows + 8, 8, col, 8);
}
#endif

