/* The certified decisions of blocks of pcols under the lanes' cameras
 * (certify.h), compiled once per SIMD level, and the whole-table pass the
 * tests compare with the float32 predicate. */
#include "certify.h"
#if PMX_X86
#include <immintrin.h>
#endif

/* The usual view, for which decide_one is compiled with its uniform
 * conditions as constants (GCC builds the mask of a condition that is uniform
 * over the lanes bit by bit, 15 shifts and ors each): every test on, a finite
 * kappa2 above LOW, view factors below 2^16. */
static inline int fast_view(const View *w)
{
    return (w->flags & 7) == 7 && !isinf(w->kappa2) && w->kappa2 > LOW && w->kabs < 0x1p16f;
}

void load_frames(Frames *fr, const float *views, int n_frames, int flags)
{
    for (int l = 0; l < BLOCK; l++) {
        View w;
        load_view(&w, views + PMX_VIEW * (l < n_frames ? l : 0), flags); /* spare lanes repeat the first */
        Lane L = lane_of(&w);
        fr->ex[l] = L.ex, fr->ey[l] = L.ey, fr->ez[l] = L.ez;
        fr->R[0][l] = L.R0, fr->R[1][l] = L.R1, fr->R[2][l] = L.R2;
        fr->U[0][l] = L.U0, fr->U[1][l] = L.U1, fr->U[2][l] = L.U2;
        fr->F[0][l] = L.F0, fr->F[1][l] = L.F1, fr->F[2][l] = L.F2;
        fr->aR[0][l] = L.aR0, fr->aR[1][l] = L.aR1, fr->aR[2][l] = L.aR2;
        fr->aU[0][l] = L.aU0, fr->aU[1][l] = L.aU1, fr->aU[2][l] = L.aU2;
        fr->aF[0][l] = L.aF0, fr->aF[1][l] = L.aF1, fr->aF[2][l] = L.aF2;
        const float k[8] = {L.k0, L.k1, L.k2, L.k3, L.k4, L.k5, L.k6, L.k7};
        const float ak[8] = {L.ak0, L.ak1, L.ak2, L.ak3, L.ak4, L.ak5, L.ak6, L.ak7};
        for (int i = 0; i < 8; i++)
            fr->k[i][l] = k[i], fr->ak[i][l] = ak[i];
        fr->kappa2[l] = L.kappa2, fr->kabs[l] = L.kabs, fr->kfac[l] = L.kfac, fr->kpad[l] = L.kpad;
        fr->frustum = L.frustum, fr->orientation = L.orientation, fr->screen = L.screen;
        fr->fast = (l == 0 || fr->fast) && fast_view(&w);
    }
    fr->ortho = (flags & ORTHOGRAPHIC) != 0;
}

static inline Lane frame_at(const Frames *fr, int l)
{
    Lane L = {fr->ex[l],    fr->ey[l],    fr->ez[l],    fr->R[0][l],   fr->R[1][l],   fr->R[2][l],
              fr->U[0][l],  fr->U[1][l],  fr->U[2][l],  fr->F[0][l],   fr->F[1][l],   fr->F[2][l],
              fr->k[0][l],  fr->k[1][l],  fr->k[2][l],  fr->k[3][l],   fr->k[4][l],   fr->k[5][l],
              fr->k[6][l],  fr->k[7][l],  fr->kappa2[l], fr->kabs[l],  fr->kfac[l],   fr->kpad[l],
              fr->frustum,  fr->orientation, fr->screen,
              fr->aR[0][l], fr->aR[1][l], fr->aR[2][l], fr->aU[0][l], fr->aU[1][l], fr->aU[2][l],
              fr->aF[0][l], fr->aF[1][l], fr->aF[2][l], fr->ak[0][l], fr->ak[1][l], fr->ak[2][l],
              fr->ak[3][l], fr->ak[4][l], fr->ak[5][l], fr->ak[6][l], fr->ak[7][l]};
    return L;
}

/* Lane l: pcol col[.][l] (by_row: the one row q for every lane, the frames
 * of a word) under camera l; by_row, ortho and settled are constants
 * (decide_one). */
static inline __attribute__((always_inline)) void decide_each_lane(const Frames *restrict fr,
                                                                   float (*restrict col)[BLOCK], const Pcol q,
                                                                   const int by_row, int32_t *restrict code,
                                                                   const int ortho, const int settled)
{
    if (fr->fast) {
#pragma omp simd
        for (int l = 0; l < BLOCK; l++) {
            const Lane L = frame_at(fr, l);
            code[l] = decide_one(&L, by_row ? q : pcol_at(col, l), ortho, 1, settled);
        }
    } else {
#pragma omp simd
        for (int l = 0; l < BLOCK; l++) {
            const Lane L = frame_at(fr, l);
            code[l] = decide_one(&L, by_row ? q : pcol_at(col, l), ortho, 0, settled);
        }
    }
}
static inline __attribute__((always_inline)) void decide_lanes(const Frames *restrict fr, float (*restrict col)[BLOCK],
                                                               int32_t *restrict code, const int ortho)
{
    const Pcol unused = {0};
    decide_each_lane(fr, col, unused, 0, code, ortho, 0);
}

/* The frames' decisions code[] as masks (one bit per frame: WHOLE, YES,
 * UNSURE). */
static inline __attribute__((always_inline)) void masks_of(const int32_t *code, Lanes *masks)
{
    Lanes wh = 0, y = 0, u = 0;
    for (int l = 0; l < BLOCK; l++) {
        wh |= (Lanes)(((code[l] & WHOLE) != 0) << l);
        y |= (Lanes)(((code[l] & 3) == YES) << l);
        u |= (Lanes)(((code[l] & 3) == UNSURE) << l);
    }
    masks[0] = wh, masks[1] = y, masks[2] = u;
}
#if PMX_X86
/* The same with AVX-512's compares into mask registers (GCC builds the
 * loop's masks as a reduction of shifted bits, a fifth of a row's cost). */
static inline PMX_TARGET_AVX512 void masks_of_avx512(const int32_t *code, Lanes *masks)
{
    const __m512i c = _mm512_loadu_si512(code), own = _mm512_and_si512(c, _mm512_set1_epi32(3));
    masks[0] = (Lanes)_mm512_test_epi32_mask(c, _mm512_set1_epi32(WHOLE));
    masks[1] = (Lanes)_mm512_cmpeq_epi32_mask(own, _mm512_set1_epi32(YES));
    masks[2] = (Lanes)_mm512_cmpeq_epi32_mask(own, _mm512_set1_epi32(UNSURE));
}
#endif

/* One pcol's row under every lane's camera (the frames of a word): the row
 * read once as scalars, which the decision broadcasts at its vector width;
 * the frames' decisions as masks (masks_of, or with wide, a constant, at
 * the AVX-512 level, masks_of_avx512). */
static inline __attribute__((always_inline)) void decide_row_lanes(const Frames *fr, const float *row, Lanes *masks,
                                                                   const int ortho, const int settled, const int wide)
{
    const Pcol q = {row[CX],     row[CY],    row[CZ],    row[NX],     row[NY],    row[NZ],
                    row[RADIUS], row[SIN_A], row[COS_A], row[DELTA],  row[MU],    row[REACH],
                    row[SPREAD], row[FACING], row[ERROR]};
    int32_t code[BLOCK];
    decide_each_lane(fr, NULL, q, 1, code, ortho, settled);
#if PMX_X86
    if (wide) {
        masks_of_avx512(code, masks);
        return;
    }
#else
    (void)wide;
#endif
    masks_of(code, masks);
}

/* A word's row under its frames (perspective, the fat camera applying) with
 * the tests the fat camera settled (fat_code FAT_INSIDE or FAT_SCREEN) left
 * out. */
static inline __attribute__((always_inline)) void decide_row_settled(const Frames *fr, const float *row,
                                                                     int32_t fat_code, Lanes *masks, const int wide)
{
    if (fat_code == FAT_SCREEN)
        decide_row_lanes(fr, row, masks, 0, SETTLED_FRUSTUM | SETTLED_ORIENTATION, wide);
    else
        decide_row_lanes(fr, row, masks, 0, SETTLED_FRUSTUM, wide);
}

/* The level wrappers: the loops above at each level's vector width. */
void decide_perspective_plain(const Frames *fr, Columns col, int32_t *code)
{
    decide_lanes(fr, col, code, 0);
}
void decide_orthographic_plain(const Frames *fr, Columns col, int32_t *code)
{
    decide_lanes(fr, col, code, 1);
}
void decide_row_perspective_plain(const Frames *fr, const float *row, Lanes *masks)
{
    decide_row_lanes(fr, row, masks, 0, 0, 0);
}
void decide_row_orthographic_plain(const Frames *fr, const float *row, Lanes *masks)
{
    decide_row_lanes(fr, row, masks, 1, 0, 0);
}
void decide_row_settled_plain(const Frames *fr, const float *row, int32_t fat_code, Lanes *masks)
{
    decide_row_settled(fr, row, fat_code, masks, 0);
}
#if PMX_X86
PMX_TARGET_AVX2 void decide_perspective_avx2(const Frames *fr, Columns col, int32_t *code)
{
    decide_lanes(fr, col, code, 0);
}
PMX_TARGET_AVX2 void decide_orthographic_avx2(const Frames *fr, Columns col, int32_t *code)
{
    decide_lanes(fr, col, code, 1);
}
PMX_TARGET_AVX2 void decide_row_perspective_avx2(const Frames *fr, const float *row, Lanes *masks)
{
    decide_row_lanes(fr, row, masks, 0, 0, 0);
}
PMX_TARGET_AVX2 void decide_row_orthographic_avx2(const Frames *fr, const float *row, Lanes *masks)
{
    decide_row_lanes(fr, row, masks, 1, 0, 0);
}
PMX_TARGET_AVX2 void decide_row_settled_avx2(const Frames *fr, const float *row, int32_t fat_code, Lanes *masks)
{
    decide_row_settled(fr, row, fat_code, masks, 0);
}
PMX_TARGET_AVX512 void decide_perspective_avx512(const Frames *fr, Columns col, int32_t *code)
{
    decide_lanes(fr, col, code, 0);
}
PMX_TARGET_AVX512 void decide_orthographic_avx512(const Frames *fr, Columns col, int32_t *code)
{
    decide_lanes(fr, col, code, 1);
}
PMX_TARGET_AVX512 void decide_row_perspective_avx512(const Frames *fr, const float *row, Lanes *masks)
{
    decide_row_lanes(fr, row, masks, 0, 0, 1);
}
PMX_TARGET_AVX512 void decide_row_orthographic_avx512(const Frames *fr, const float *row, Lanes *masks)
{
    decide_row_lanes(fr, row, masks, 1, 0, 1);
}
PMX_TARGET_AVX512 void decide_row_settled_avx512(const Frames *fr, const float *row, int32_t fat_code, Lanes *masks)
{
    decide_row_settled(fr, row, fat_code, masks, 1);
}
#endif

void pmx_decide_all(const float *rows, int64_t n_pcols, const float *view, int flags, uint8_t *out)
{
    const unsigned mode = subnormals_off();
    const Kernels *kern = pmx_kernels();
    Frames fr;
    load_frames(&fr, view, 1, flags);
    Columns col;
    int32_t code[BLOCK], ids[BLOCK];
    for (int64_t p = 0; p < n_pcols; p += BLOCK) {
        const int64_t nb = n_pcols - p < BLOCK ? n_pcols - p : BLOCK;
        for (int64_t j = 0; j < nb; j++)
            ids[j] = (int32_t)(p + j);
        gather_block(kern, rows, ids, nb, col);
        (fr.ortho ? kern->decide_orthographic : kern->decide_perspective)(&fr, col, code);
        for (int64_t j = 0; j < nb; j++)
            out[p + j] = (uint8_t)code[j];
    }
    subnormals_back(mode);
}
