/* Fat cameras: the frames of a word decided at once.
 *
 * Consecutive frames of a path see nearly the same thing, so most pcols of a
 * word are decided alike by all its frames. A fat camera covers the word's
 * frames (pmx_fat_cameras below; all of them perspective views with every
 * test on and the same intrinsics, the clip distances and tolerances free):
 *
 *  - every frame's eye lies within rho of the eye centre e, so every
 *    distance from a frame's eye is within rho of the distance from e, and
 *    the rays from a frame's eye into a sphere are rays from e into the
 *    sphere grown by rho;
 *  - every frame's eye lies within a capsule (a segment a + [0, 1] ab, the
 *    path's chord, grown by its radius), so every distance from a frame's eye
 *    is at least the distance from the segment less the radius, and at most
 *    the distance from its farther end plus the radius, and every frame's
 *    v . n (v the eye vector) lies in the segment's exact range of it
 *    widened by the radius |n| (tighter than the ball for the distance tests
 *    and the orientation test along a path);
 *  - in camera coordinates a point c of frame f is R_f (c - p) + t_f for a
 *    pivot p (the point the frames look at, where there is one); with
 *    |R_f - R| <= eps (spectral norm) and |t_f - t| <= tau, it lies within
 *    shift(c) = tau + eps |c - p| of R (c - p) + t.
 *
 * A pcol is decided for all the frames in one pass over 16 pcols when either
 *
 *  - FAT_WHOLE: a subtree bound holds with the sphere grown to cover every
 *    frame (the geometric facts above; the bounds' margins cover this
 *    evaluation's rounding as they cover a frame's), so every frame's
 *    subtree collapses; or
 *  - FAT_NO: for every frame, every test of the float32 predicate surely
 *    says "keep": each comparison is bounded over the frames by a value
 *    computed here from the fat camera, with a magnitude that bounds both
 *    this evaluation's and any frame's (so `less` certifies it as it
 *    certifies a frame's comparison).
 *
 * The frames' tolerances may differ (a face budget's per frame): the screen
 * test is monotone in kappa2 = (unit tau)^2 (rounded products are monotone),
 * so a subtree small at the smallest kappa2 is small for every frame, and a
 * pcol surely too coarse at the largest is too coarse for every frame; the
 * magnitudes take the largest.
 *
 * Otherwise the frames are decided one by one, less the tests settled for
 * all of them: FAT_INSIDE where every frame's frustum test surely keeps the
 * pcol, FAT_SCREEN where its orientation test does too (the bounds of
 * FAT_NO's first two parts). Where those two are settled, the pcol is
 * decided for all the frames once more as
 *
 *  - FAT_YES: every frame's screen test surely collapses it (its own
 *    decision "yes", the bounds as FAT_NO's with the other ends of the
 *    ranges), and no frame's screen bound can hold (its error is at least
 *    the largest tolerance at the largest room any frame's float32 bound
 *    can compute), so that the float32 predicate collapses it in every
 *    frame, "yes" and not "whole"; a frame's own certificate may have been
 *    unsure. The unsure counts are counted after the fat pass, so such a
 *    pcol is not among them.
 * Either way every frame gets the bits of its own refinement. */
#include "certify.h"

/* Layout of a fat camera (PMX_FAT floats). */
enum {
    FAT_EYE = 0, FAT_RHO = 3, FAT_PIVOT = 4, FAT_ROTATION = 7, FAT_T = 16, FAT_EPS = 19, FAT_TAU = 20,
    FAT_SEGMENT = 21, FAT_STEP = 24, FAT_STEP_INV = 27, FAT_CAPSULE = 28, FAT_N = 29
};

/* Frames can share the fat camera fat (FAT_N floats, or NULL): it is given
 * and finite, and they are perspective views of the usual kind (fast_view)
 * with the same intrinsics; the clip distances and tolerances are free. */
int fat_applies(const Frames *fr, const float *fat, int n_frames)
{
    if (!fat || !fr->fast || fr->ortho)
        return 0;
    for (int i = 0; i < FAT_N; i++)
        if (!isfinite(fat[i]))
            return 0;
    for (int l = 1; l < n_frames; l++) {
        for (int i = 0; i < 6; i++)
            if (fr->k[i][l] != fr->k[i][0])
                return 0;
    }
    return 1;
}

void load_fat(Fat *W, const float *fat, const Frames *fr, int n_frames)
{
    W->ex = fat[FAT_EYE], W->ey = fat[FAT_EYE + 1], W->ez = fat[FAT_EYE + 2], W->rho = fat[FAT_RHO];
    W->px = fat[FAT_PIVOT], W->py = fat[FAT_PIVOT + 1], W->pz = fat[FAT_PIVOT + 2];
    const float *R = fat + FAT_ROTATION;
    W->R0 = R[0], W->R1 = R[1], W->R2 = R[2], W->U0 = R[3], W->U1 = R[4], W->U2 = R[5];
    W->F0 = R[6], W->F1 = R[7], W->F2 = R[8];
    W->tx = fat[FAT_T], W->ty = fat[FAT_T + 1], W->tz = fat[FAT_T + 2];
    W->eps = fat[FAT_EPS], W->tau = fat[FAT_TAU];
    W->ax = fat[FAT_SEGMENT], W->ay = fat[FAT_SEGMENT + 1], W->az = fat[FAT_SEGMENT + 2];
    W->abx = fat[FAT_STEP], W->aby = fat[FAT_STEP + 1], W->abz = fat[FAT_STEP + 2];
    W->ab_inv = fat[FAT_STEP_INV], W->capsule = fat[FAT_CAPSULE];
    W->k0 = fr->k[0][0], W->k1 = fr->k[1][0], W->k2 = fr->k[2][0], W->k3 = fr->k[3][0];
    W->k4 = fr->k[4][0], W->k5 = fr->k[5][0];
    W->kappa2 = W->kappa2_hi = fr->kappa2[0], W->kfac = fr->kfac[0], W->kabs = fr->kabs[0];
    W->near_lo = W->near_hi = fr->k[6][0], W->far_lo = W->far_hi = fr->k[7][0], W->kpad = fr->kpad[0];
    for (int l = 1; l < n_frames; l++) {
        W->kappa2 = fminf(W->kappa2, fr->kappa2[l]), W->kappa2_hi = fmaxf(W->kappa2_hi, fr->kappa2[l]);
        W->kabs = fmaxf(W->kabs, fr->kabs[l]);
        W->near_lo = fminf(W->near_lo, fr->k[6][l]), W->near_hi = fmaxf(W->near_hi, fr->k[6][l]);
        W->far_lo = fminf(W->far_lo, fr->k[7][l]), W->far_hi = fmaxf(W->far_hi, fr->k[7][l]);
        W->kpad = fmaxf(W->kpad, fr->kpad[l]);
    }
}

/* Grows a float32 sum of a few rounded terms past its exact value. */
#define GROW (1.0f + 0x1p-22f)
/* Grows a float32 bound on a frame's magnitude (computed with a few
 * roundings from d, which is within a few ulps of the exact distance). */
#define GROW_M (1.0f + 0x1p-18f)

/* One pcol under every frame of the fat camera W: FAT_WHOLE, FAT_NO,
 * FAT_YES, or the tests left to the frames (FAT_SCREEN, FAT_INSIDE,
 * FAT_OPEN). No branches
 * (vectorized over the pcols of a block). */
static inline __attribute__((always_inline)) int32_t decide_fat_one(const Fat *W, const Pcol q)
{
    const float rho = W->rho, eps = W->eps, tau = W->tau, kappa2 = W->kappa2, kfac = W->kfac, kpad = W->kpad;
    const float kappa2_hi = W->kappa2_hi;
    const float k0 = W->k0, k1 = W->k1, k2 = W->k2, k3 = W->k3, k4 = W->k4, k5 = W->k5;
    const float nx = q.nx, ny = q.ny, nz = q.nz, r = q.radius, ar = fabsf(r), sa = q.sin_a, ca = q.cos_a;
    const float delta = q.delta, mu = q.mu;
    /* Distances from the eye centre: a frame's is within rho. */
    const float vx = q.cx - W->ex, vy = q.cy - W->ey, vz = q.cz - W->ez;
    const float d2 = vx * vx + vy * vy + vz * vz, d = sqrtf(d2);
    const float dhi = d + rho, dlo = pos(d - rho), dhi2 = dhi * dhi;
    const float v1 = fabsf(vx) + fabsf(vy) + fabsf(vz);
    /* Tighter along a path: the distance from the capsule's segment, less
     * the rounding of the projection (the point found is within
     * 2^-18 (|c - a|_1 + |ab|_1) of the nearest), less the capsule radius;
     * and the farther end, plus the radius. */
    const float ox = q.cx - W->ax, oy = q.cy - W->ay, oz = q.cz - W->az;
    const float along = (ox * W->abx + oy * W->aby + oz * W->abz) * W->ab_inv;
    const float at = along > 0.0f ? (along < 1.0f ? along : 1.0f) : 0.0f;
    const float fx = ox - at * W->abx, fy = oy - at * W->aby, fz = oz - at * W->abz;
    const float bx = ox - W->abx, by = oy - W->aby, bz = oz - W->abz;
    const float slop = 0x1p-18f * (fabsf(ox) + fabsf(oy) + fabsf(oz) + fabsf(W->abx) + fabsf(W->aby) + fabsf(W->abz));
    const float path_lo = pos(sqrtf(fx * fx + fy * fy + fz * fz) - slop - W->capsule);
    const float end_a = ox * ox + oy * oy + oz * oz, end_b = bx * bx + by * by + bz * bz;
    const float path_hi = sqrtf(end_a > end_b ? end_a : end_b) + W->capsule;
    /* Either bound holds: the tighter of each. */
    const float near_d = dlo > path_lo ? dlo : path_lo, far_d = dhi < path_hi ? dhi : path_hi;
    const float far_d2 = far_d * far_d;
    /* Camera coordinates about the pivot: a frame's are within shift of these. */
    const float px = q.cx - W->px, py = q.cy - W->py, pz = q.cz - W->pz;
    const float dp = sqrtf(px * px + py * py + pz * pz);
    const float x = px * W->R0 + py * W->R1 + pz * W->R2 + W->tx;
    const float y = px * W->U0 + py * W->U1 + pz * W->U2 + W->ty;
    const float z = px * W->F0 + py * W->F1 + pz * W->F2 + W->tz;
    const float shift = (tau + eps * dp) * GROW; /* of the centre */
    const float hv = vx * nx + vy * ny + vz * nz, mhv = fabsf(vx * nx) + fabsf(vy * ny) + fabsf(vz * nz);
    const float n1 = fabsf(nx) + fabsf(ny) + fabsf(nz); /* >= |n| */

    /* -- every frame's subtree bound, the spheres grown to cover the frames -- */
    /* (outside the nearest near plane or beyond the farthest far plane) */
    const float e2 = q.error * q.error;
    const _Bool whole = bound_outside(x, y, z, (q.reach + tau + eps * (dp + q.reach)) * GROW, k0, k1, k2, k3, k4,
                                      k5, W->near_lo, W->far_hi, kfac, kpad) |
                        bound_away(hv, d2, d, (q.reach + rho) * GROW, q.facing) |
                        bound_small(near_d, far_d, q.spread, e2, kappa2);

    /* -- every frame's own decision surely "keep" -- */
    /* Each comparison's bound over the frames, with the magnitude of this
     * evaluation plus a bound on a frame's (factors as in decide_one, the
     * eye's coordinates grown by rho). */
    const float scale = (1 + v1 + 3 * rho + ar + n1 + fabsf(sa) + fabsf(ca) + fabsf(delta) + fabsf(mu)) * GROW_M;
    const float factor = scale * scale * W->kabs;
    const float slack = 2 * FLUSH * factor * factor;
    const _Bool guard = (scale < 0x1p24f) & (dhi2 < HIGH);
    /* Inside every frame's frustum: each plane's value at the centre, less
     * its change over the frames (a plane's normal has length 1, or k4, k5
     * for the side planes; the farthest near and nearest far plane), surely
     * positive. kpad bounds every frame's clip distances. */
    const float frame_m = (3 * dhi * GROW_M + ar) * kfac + kpad;
    const float fat_m =
        ((fabsf(px) + fabsf(py) + fabsf(pz)) * 3 + fabsf(W->tx) + fabsf(W->ty) + fabsf(W->tz) + ar + shift) *
            kfac * GROW_M + kpad;
    const float mf = frame_m + fat_m;
    const _Bool inside = less(z + r - W->near_hi - shift, mf, slack).n & less(W->far_lo - (z - r) - shift, mf, slack).n &
                         less(z * k0 + k2 - fabsf(x) + r * k4 - shift * k4 * GROW_M, mf, slack).n &
                         less(z * k1 + k3 - fabsf(y) + r * k5 - shift * k5 * GROW_M, mf, slack).n;
    /* Not facing away from any frame: the cone's cosine is not positive, or
     * g = h - ca r is surely negative, or g^2 <= sa^2 t2 surely (h = v . n
     * moves by at most rho |n| <= rho n1, t2 = d^2 - r^2 at least the
     * nearest distance's square less r^2). */
    const float hshift = rho * n1 * GROW;
    /* Along a path h is tighter: with e = a + t ab + delta (t in [0, 1],
     * |delta| <= capsule), h = (c - a) . n - t (ab . n) - delta . n, whose
     * range over t is exact; the tighter end of either range bounds h. */
    const float ha = ox * nx + oy * ny + oz * nz, hab = W->abx * nx + W->aby * ny + W->abz * nz;
    const float cshift = W->capsule * n1 * GROW;
    const float mha = fabsf(ox * nx) + fabsf(oy * ny) + fabsf(oz * nz) + fabsf(W->abx * nx) + fabsf(W->aby * ny) +
                      fabsf(W->abz * nz) + cshift;
    const float hlo_path = ha - pos(hab) - cshift, hhi_path = ha + pos(-hab) + cshift;
    const float hlo = hv - hshift > hlo_path ? hv - hshift : hlo_path;
    const float hhi = hv + hshift < hhi_path ? hv + hshift : hhi_path;
    const float glo = hlo - ca * r, ghi = hhi - ca * r;
    const float mg_fat = mhv + hshift + mha + fabsf(ca) * ar, mg_frame = dhi * n1 * GROW_M + fabsf(ca) * ar;
    const float g2 = glo * glo > ghi * ghi ? glo * glo : ghi * ghi;
    const _Bool toward = (ca <= 0.0f) | less(ghi, mg_fat + mg_frame, slack).y |
                         less(sa * sa * (near_d * near_d - r * r) - g2,
                              2 * sa * sa * (dhi2 * GROW_M + r * r) + mg_fat * mg_fat + mg_frame * mg_frame, slack)
                             .n;
    /* Too coarse for every frame (at the largest kappa2, kappa2_hi):
     * mu^2 >= kappa2_hi d^2 surely, or delta^2 (d^2 - h^2) >= kappa2_hi d^4
     * surely, with d^2 - h^2 = |v x n|^2 + d^2 (1 - |n|^2) and |v x n|
     * moving by at most rho |n|. */
    const float wx = vy * nz - vz * ny, wy = vz * nx - vx * nz, wz = vx * ny - vy * nx;
    const float wlen = sqrtf(wx * wx + wy * wy + wz * wz);
    /* Along a path, v x n = P - t Q - delta x n with P = (c - a) x n, Q = ab
     * x n: |v x n| is at least the distance from P to the segment [0, Q]
     * (less the rounding of the projection, as path_lo's) less capsule |n|;
     * its largest is at an end (a norm is convex in t), at most the larger
     * of |P| and |P - Q| = |(c - b) x n| plus capsule |n|. */
    const float px0 = oy * nz - oz * ny, py0 = oz * nx - ox * nz, pz0 = ox * ny - oy * nx;
    const float px1 = by * nz - bz * ny, py1 = bz * nx - bx * nz, pz1 = bx * ny - by * nx;
    const float qx = px0 - px1, qy = py0 - py1, qz = pz0 - pz1, qq = qx * qx + qy * qy + qz * qz;
    const float tq = qq > 0x1p-100f ? (px0 * qx + py0 * qy + pz0 * qz) / qq : 0.0f;
    const float tc = tq > 0.0f ? (tq < 1.0f ? tq : 1.0f) : 0.0f;
    const float rx = px0 - tc * qx, ry = py0 - tc * qy, rz = pz0 - tc * qz;
    const float pslop = 0x1p-18f * (fabsf(px0) + fabsf(py0) + fabsf(pz0) + fabsf(qx) + fabsf(qy) + fabsf(qz));
    const float p0 = px0 * px0 + py0 * py0 + pz0 * pz0, p1 = px1 * px1 + py1 * py1 + pz1 * pz1;
    /* Where Q is too short to project on (tc left 0), the distance to the
     * segment can be smaller than |P| by up to |Q|. */
    const float qshort = qq > 0x1p-100f ? 0.0f : sqrtf(qq);
    const float wpath_lo = sqrtf(rx * rx + ry * ry + rz * rz) - pslop - cshift - qshort;
    const float wpath_hi = sqrtf(p0 > p1 ? p0 : p1) + cshift;
    /* The magnitudes bound either way's terms. */
    const float mw = v1 * n1 + hshift +
                     (fabsf(ox) + fabsf(oy) + fabsf(oz) + fabsf(W->abx) + fabsf(W->aby) + fabsf(W->abz)) * n1 * 2 +
                     cshift;
    const float wlo = pos(wlen - hshift > wpath_lo ? wlen - hshift : wpath_lo);
    const float nn = nx * nx + ny * ny + nz * nz;
    /* The magnitudes of the two tests' differences, shared by coarse and
     * small (both bounded at the largest kappa2 and distance). */
    const float mag_mu = 2 * mu * mu + 2 * kappa2_hi * far_d2 * GROW_M;
    const float mag_w = delta * delta * (mw * mw + dhi2 * (nn + 1) + dhi2 * (1 + n1 * n1) * GROW_M) +
                        2 * kappa2_hi * far_d2 * far_d2 * GROW_M;
    const _Bool coarse =
        less(mu * mu - kappa2_hi * far_d2, mag_mu, slack).n |
        less(delta * delta * (wlo * wlo - dhi2 * pos(nn - 1)) - kappa2_hi * far_d2 * far_d2, mag_w, slack).n;
    /* Small for every frame (at the smallest kappa2, the nearest distance):
     * mu^2 < kappa2 d^2 surely, and delta^2 (d^2 - h^2) < kappa2 d^4 surely,
     * with |v x n| at most |w| + rho |n| or the path's bound, the smaller;
     * the magnitudes as coarse's. */
    const float whi = wlen + hshift < wpath_hi ? wlen + hshift : wpath_hi, near_d2 = near_d * near_d;
    const _Bool small =
        less(mu * mu - kappa2 * near_d2, mag_mu, slack).y &
        less(delta * delta * (whi * whi + dhi2 * pos(1 - nn)) - kappa2 * near_d2 * near_d2, mag_w, slack).y;
    /* No frame's screen bound (bound_small at its own distance) holds: its
     * room, d - spread less a nonnegative margin in float32, is at most
     * room_hi (far_d and the rounding of the frame's d and of room_hi's own
     * operations covered by 2^-16 twice), and e2 is at least every frame's
     * kappa2 room^2 (1 - SCREEN_MARGIN) in float32 (2^-16 covers its three
     * roundings and this product's). */
    const float room_hi = pos(far_d * (1 + 0x1p-16f) - q.spread) * (1 + 0x1p-16f);
    const _Bool unbounded = (q.spread >= 0) & (e2 > kappa2_hi * room_hi * room_hi * (1 + 0x1p-16f));
    /* Otherwise the tests settled for every frame (FAT_INSIDE, FAT_SCREEN)
     * are left out of the frames' own decisions. */
    const _Bool seen = guard & inside;
    return whole    ? FAT_WHOLE
           : !seen  ? FAT_OPEN
           : !toward ? FAT_INSIDE
           : coarse ? FAT_NO
           : small & unbounded ? FAT_YES
                               : FAT_SCREEN;
}

/* The level wrappers of the fat pass over a block. */
static inline __attribute__((always_inline)) void decide_fat_block(const Fat *W, Columns col, int32_t *code)
{
#pragma omp simd
    for (int l = 0; l < BLOCK; l++)
        code[l] = decide_fat_one(W, pcol_at(col, l));
}
void decide_fat_plain(const Fat *W, Columns col, int32_t *code) { decide_fat_block(W, col, code); }
#if PMX_X86
PMX_TARGET_AVX2 void decide_fat_avx2(const Fat *W, Columns col, int32_t *code) { decide_fat_block(W, col, code); }
PMX_TARGET_AVX512 void decide_fat_avx512(const Fat *W, Columns col, int32_t *code) { decide_fat_block(W, col, code); }
#endif

/* Every pcol under the fat camera of views [n_frames, PMX_VIEW] (FAT_WHOLE,
 * FAT_NO, FAT_YES, FAT_SCREEN, FAT_INSIDE or FAT_OPEN; all FAT_OPEN where the fat
 * camera does not apply), for
 * tests that compare it with every frame's float32 predicate. */
void pmx_decide_fat_all(const float *rows, int64_t n_pcols, const float *views, int n_frames, int flags,
                        const float *fat, uint8_t *out)
{
    const unsigned mode = subnormals_off();
    const Kernels *kern = pmx_kernels();
    Frames fr;
    load_frames(&fr, views, n_frames, flags);
    if (!fat_applies(&fr, fat, n_frames)) {
        memset(out, FAT_OPEN, (size_t)n_pcols);
        subnormals_back(mode);
        return;
    }
    Fat W;
    load_fat(&W, fat, &fr, n_frames);
    Columns col;
    int32_t code[BLOCK], ids[BLOCK];
    for (int64_t p = 0; p < n_pcols; p += BLOCK) {
        const int64_t nb = n_pcols - p < BLOCK ? n_pcols - p : BLOCK;
        for (int64_t j = 0; j < nb; j++)
            ids[j] = (int32_t)(p + j);
        gather_block(kern, rows, ids, nb, col);
        kern->decide_fat(&W, col, code);
        for (int64_t j = 0; j < nb; j++)
            out[p + j] = (uint8_t)code[j];
    }
    subnormals_back(mode);
}

/* The bounds of the fat camera above, from the frames' float32 constants.
 * Each is computed in double and rounded up to float32 with room for the
 * double rounding, so it holds for the exact values. Only the bounds'
 * soundness matters for exactness; the eye centre (the eyes' box centre), the
 * reference rotation (the middle frame's), the pivot (the point the view axes
 * pass closest to, least squares; an orbit's centre, so that turning the
 * camera moves the points near it little) and t (the box centre of the
 * pivot's camera coordinates) are free choices that only make the bounds
 * tighter or looser. eps bounds the spectral norm by Gershgorin's circles. */

/* Relative room above a double bound before rounding up to float32: covers
 * the double arithmetic (about 2^-50 relative) many times over. */
#define FAT_ROOM 0x1p-16

/* A float32 value at least x (1 + FAT_ROOM). */
static float fat_up(double x) { return nextafterf((float)(x * (1 + FAT_ROOM)), INFINITY); }

/* x rounded to float32, held in double (exactly). */
static double fat_f32(double x) { return (double)(float)x; }

/* max and min that keep a NaN (fmax and fmin drop it, which would hide a
 * frame that is not finite). */
static double max_nan(double a, double b) { return a != a || a > b ? a : b; }
static double min_nan(double a, double b) { return a != a || a < b ? a : b; }

static double norm3(const double *v) { return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

/* The float32 centre of the box lo..hi of points p[0..n) (into centre), and
 * the largest distance of a point from it. */
static double ball_about_box(const double (*p)[3], int n, const double *lo, const double *hi, double *centre)
{
    double radius = 0;
    for (int i = 0; i < 3; i++)
        centre[i] = fat_f32(0.5 * (lo[i] + hi[i]));
    for (int f = 0; f < n; f++) {
        const double d[3] = {p[f][0] - centre[0], p[f][1] - centre[1], p[f][2] - centre[2]};
        radius = max_nan(radius, norm3(d));
    }
    return radius;
}

/* The smallest eigenvalue of the symmetric 3 x 3 matrix a (trigonometric
 * closed form; NaN for a matrix that is not finite). */
static double smallest_eigenvalue(const double a[3][3])
{
    const double p1 = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
    const double q = (a[0][0] + a[1][1] + a[2][2]) / 3;
    if (p1 == 0)
        return min_nan(a[0][0], min_nan(a[1][1], a[2][2]));
    const double p = sqrt(((a[0][0] - q) * (a[0][0] - q) + (a[1][1] - q) * (a[1][1] - q) +
                           (a[2][2] - q) * (a[2][2] - q) + 2 * p1) / 6);
    double b[3][3];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            b[i][j] = (a[i][j] - (i == j ? q : 0)) / p;
    double r = (b[0][0] * (b[1][1] * b[2][2] - b[1][2] * b[2][1]) - b[0][1] * (b[1][0] * b[2][2] - b[1][2] * b[2][0]) +
                b[0][2] * (b[1][0] * b[2][1] - b[1][1] * b[2][0])) / 2;
    r = r < -1 ? -1 : r > 1 ? 1 : r;
    return q + 2 * p * cos(acos(r) / 3 + 2.0943951023931957);
}

/* The point closest to every view axis of the frames (least squares), or
 * fallback where the axes are too near parallel to meet (a camera moving
 * forward): sum over the frames of (I - n n^T) x = sum of (I - n n^T) e, n
 * the forward row of each frame's rotation. */
static void fat_pivot(const double (*eyes)[3], const double (*rot)[3][3], int n, const double *fallback,
                      double *pivot)
{
    double a[3][3] = {{0}}, b[3] = {0};
    for (int f = 0; f < n; f++)
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++) {
                const double across = (i == j) - rot[f][2][i] * rot[f][2][j];
                a[i][j] += across;
                b[i] += across * eyes[f][j];
            }
    int meet = smallest_eigenvalue(a) > 1e-3 * n;
    /* Cramer's rule: the adjugate's rows over the determinant. */
    const double c0 = a[1][1] * a[2][2] - a[1][2] * a[2][1], c1 = a[1][2] * a[2][0] - a[1][0] * a[2][2];
    const double c2 = a[1][0] * a[2][1] - a[1][1] * a[2][0];
    const double det = a[0][0] * c0 + a[0][1] * c1 + a[0][2] * c2;
    const double x[3] = {
        (b[0] * c0 + a[0][1] * (b[2] * a[1][2] - b[1] * a[2][2]) + a[0][2] * (b[1] * a[2][1] - b[2] * a[1][1])) / det,
        (a[0][0] * (b[1] * a[2][2] - b[2] * a[1][2]) + b[0] * c1 + a[0][2] * (b[2] * a[1][0] - b[1] * a[2][0])) / det,
        (a[0][0] * (b[2] * a[1][1] - b[1] * a[2][1]) + a[0][1] * (b[1] * a[2][0] - b[2] * a[1][0]) + b[0] * c2) / det};
    meet &= isfinite(x[0]) && isfinite(x[1]) && isfinite(x[2]);
    for (int i = 0; i < 3; i++)
        pivot[i] = meet ? x[i] : fallback[i];
}

/* The fat cameras of n_words words of n_frames frames (views [W, F, PMX_VIEW],
 * the host's view constants) into out [W, FAT_N]; a word whose bounds are not
 * finite gets NaN ones (under which nothing is decided at once). PMX_BAD_SIZE
 * (nothing written) unless 1 <= n_frames <= FAT_MAX_FRAMES. */
#define FAT_MAX_FRAMES 64
PmxStatus pmx_fat_cameras(const float *views, int64_t n_words, int n_frames, float *out)
{
    if (n_frames < 1 || n_frames > FAT_MAX_FRAMES)
        return PMX_BAD_SIZE;
    const int F = n_frames;
    double eyes[FAT_MAX_FRAMES][3], rot[FAT_MAX_FRAMES][3][3], t[FAT_MAX_FRAMES][3];
    for (int64_t w = 0; w < n_words; w++) {
        const float *v = views + w * n_frames * PMX_VIEW;
        float *o = out + w * FAT_N;
        double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
        for (int f = 0; f < F; f++)
            for (int i = 0; i < 3; i++) {
                eyes[f][i] = v[PMX_VIEW * f + EYE + i];
                for (int j = 0; j < 3; j++)
                    rot[f][i][j] = v[PMX_VIEW * f + RIGHT + 3 * i + j];
                lo[i] = min_nan(lo[i], eyes[f][i]), hi[i] = max_nan(hi[i], eyes[f][i]);
            }
        /* The eye ball: about the box's centre. */
        double eye[3];
        const double rho = ball_about_box((const double (*)[3])eyes, F, lo, hi, eye);
        /* The rotations about the middle frame's: |D|_2^2 is the largest
         * eigenvalue of D^T D, at most its largest absolute row sum
         * (Gershgorin; exact for a turn about one axis). */
        const double (*ref)[3] = rot[F / 2];
        double gersh = 0;
        for (int f = 0; f < F; f++) {
            double d[3][3];
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++)
                    d[i][j] = rot[f][i][j] - ref[i][j];
            for (int i = 0; i < 3; i++) {
                double row = 0;
                for (int j = 0; j < 3; j++)
                    row += fabs(d[0][i] * d[0][j] + d[1][i] * d[1][j] + d[2][i] * d[2][j]);
                gersh = max_nan(gersh, row);
            }
        }
        /* The pivot, and its camera coordinates over the frames about their
         * box's centre. The double products and sums of t round by at most
         * 2^-50 of |pivot - eye|_1. */
        double pivot[3];
        fat_pivot((const double (*)[3])eyes, (const double (*)[3][3])rot, F, eye, pivot);
        for (int i = 0; i < 3; i++)
            pivot[i] = fat_f32(pivot[i]);
        double tlo[3] = {INFINITY, INFINITY, INFINITY}, thi[3] = {-INFINITY, -INFINITY, -INFINITY}, spread1 = 0;
        for (int f = 0; f < F; f++) {
            const double d[3] = {pivot[0] - eyes[f][0], pivot[1] - eyes[f][1], pivot[2] - eyes[f][2]};
            spread1 = max_nan(spread1, fabs(d[0]) + fabs(d[1]) + fabs(d[2]));
            for (int i = 0; i < 3; i++) {
                t[f][i] = rot[f][i][0] * d[0] + rot[f][i][1] * d[1] + rot[f][i][2] * d[2];
                tlo[i] = min_nan(tlo[i], t[f][i]), thi[i] = max_nan(thi[i], t[f][i]);
            }
        }
        double centre[3];
        const double tau = ball_about_box((const double (*)[3])t, F, tlo, thi, centre);
        /* The capsule about the chord: each eye's distance from its nearest
         * point of the (float32) segment the decisions use. */
        const double *start = eyes[0];
        double step[3], length2 = 0, capsule = 0, size1 = 0;
        for (int i = 0; i < 3; i++) {
            step[i] = fat_f32(eyes[F - 1][i] - start[i]);
            length2 += step[i] * step[i];
        }
        for (int f = 0; f < F; f++) {
            double along = 0;
            for (int i = 0; i < 3; i++)
                along += (eyes[f][i] - start[i]) * step[i];
            along /= length2 > 0 ? length2 : 1.0;
            along = along < 0 ? 0 : along > 1 ? 1 : along;
            const double d[3] = {eyes[f][0] - (start[0] + along * step[0]), eyes[f][1] - (start[1] + along * step[1]),
                                 eyes[f][2] - (start[2] + along * step[2])};
            capsule = max_nan(capsule, norm3(d));
            size1 = max_nan(size1, fabs(eyes[f][0]) + fabs(eyes[f][1]) + fabs(eyes[f][2]));
        }
        /* Any step inverse will do (the decisions allow for the projection's
         * error); 0 for one point. */
        const double step_inv = length2 > 0x1p-100 ? 1.0 / length2 : 0.0;
        for (int i = 0; i < 3; i++) {
            o[FAT_EYE + i] = (float)eye[i], o[FAT_PIVOT + i] = (float)pivot[i], o[FAT_T + i] = (float)centre[i];
            o[FAT_SEGMENT + i] = (float)start[i], o[FAT_STEP + i] = (float)step[i];
            for (int j = 0; j < 3; j++)
                o[FAT_ROTATION + 3 * i + j] = (float)ref[i][j];
        }
        o[FAT_RHO] = fat_up(rho), o[FAT_EPS] = fat_up(sqrt(gersh));
        o[FAT_TAU] = fat_up(tau + 0x1p-48 * spread1);
        o[FAT_STEP_INV] = (float)step_inv, o[FAT_CAPSULE] = fat_up(capsule + 0x1p-48 * size1);
        int finite = 1;
        for (int i = 0; i < FAT_N; i++)
            finite &= isfinite(o[i]) != 0;
        if (!finite)
            for (int i = 0; i < FAT_N; i++)
                o[i] = NAN;
    }
    return PMX_OK;
}
