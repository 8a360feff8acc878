/* A camera's view constants (the 22 floats the decisions read,
 * pmjax/_view.py View.values), from its parameters.
 *
 * Eye, axes and clip distances are the camera's own float32 values, as in
 * View; the slopes, plane scales and kappa squared are computed in double
 * here and rounded once, where XLA computes them in float32, so they differ
 * by a few float32 ulps: well inside the 2^-20 relative the certification
 * allows (VIEW in certify.h). The unsure decisions are asked of the float32
 * predicate with XLA's own constants. */
#include "internal.h"

/* Layout of a camera (PMX_CAMERA floats). */
enum { CAM_EYE = 0, CAM_ROTATION = 3, CAM_FOV = 12, CAM_NEAR = 13, CAM_FAR = 14, CAM_ORTHO = 15, CAM_WIDTH = 16,
       CAM_HEIGHT = 17, CAM_TAU = 18 };

void pmx_view_of(const float *camera, int orthographic, float *view)
{
    const double width = camera[CAM_WIDTH], height = camera[CAM_HEIGHT];
    const double aspect = width / height;
    double consts[6], unit;
    if (orthographic) {
        const double b_y = 0.5 * (double)camera[CAM_ORTHO];
        const double c[6] = {0.0, 0.0, b_y * aspect, b_y, 1.0, 1.0};
        memcpy(consts, c, sizeof consts);
        unit = (double)camera[CAM_ORTHO] / height;
    } else {
        const double a_y = tan(0.5 * (double)camera[CAM_FOV]), a_x = a_y * aspect;
        const double c[6] = {a_x, a_y, 0.0, 0.0, sqrt(1 + a_x * a_x), sqrt(1 + a_y * a_y)};
        memcpy(consts, c, sizeof consts);
        unit = 2 * a_y / height;
    }
    const double kappa = unit * (double)camera[CAM_TAU];
    /* rotation is camera-to-world, row-major: its columns are right, up and back. */
    const float *rot = camera + CAM_ROTATION;
    for (int i = 0; i < 3; i++) {
        view[EYE + i] = camera[CAM_EYE + i];
        view[RIGHT + i] = rot[3 * i];
        view[UP + i] = rot[3 * i + 1];
        view[FORWARD + i] = -rot[3 * i + 2];
    }
    for (int i = 0; i < 6; i++)
        view[K + i] = (float)consts[i];
    view[K + 6] = camera[CAM_NEAR];
    view[K + 7] = camera[CAM_FAR];
    view[ONE_PIXEL] = (float)unit;
    view[KAPPA2] = (float)(kappa * kappa); /* inf where it overflows float32 (tau = inf) */
}

void pmx_views_of(const float *cameras, int64_t n, int orthographic, float *views)
{
    for (int64_t k = 0; k < n; k++)
        pmx_view_of(cameras + k * PMX_CAMERA, orthographic, views + k * PMX_VIEW);
}
