"""Camera file for the SrMesh driver (``srmesh_adapt``), written from pmjax cameras.

Usage: python benchmarks/srmesh/cameras.py MODEL OUT.txt [--frames 240]
       (the standard orbit of the model's default build)

One line per camera after ``#`` comments:
``eye_x eye_y eye_z look_x look_y look_z up_x up_y up_z fov_y_deg near far width height``,
floats written with 9 significant digits, so a float32 camera reads back exactly.
The look-at point is the eye plus the camera's forward axis (minus its back
column), the up vector its up column.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

HEADER = "# eye_x eye_y eye_z look_x look_y look_z up_x up_y up_z fov_y_deg near far width height\n"


def write_cameras(cams, path: str) -> int:
    """Write a batch of perspective cameras as the driver's camera file.

    Args:
        cams: ``pmjax.Camera`` batch ``[K]`` (perspective; an orthographic
            camera has no field of view for SrMesh and is refused).
        path: file to write.

    Returns:
        K, the number of cameras written.
    """
    if np.any(np.asarray(cams.orthographic)):
        raise ValueError("SrMesh's driver takes perspective cameras only")
    eye = np.asarray(cams.eye, np.float64).reshape(-1, 3)
    rot = np.asarray(cams.rotation, np.float64).reshape(-1, 3, 3)
    # Columns of the rotation: right, up, back (camera to world).
    look = eye - rot[:, :, 2]
    up = rot[:, :, 1]
    fov = np.degrees(np.asarray(cams.fov_y, np.float64)).reshape(-1)
    K = len(eye)
    near = np.broadcast_to(np.asarray(cams.near, np.float64), (K,))
    far = np.broadcast_to(np.asarray(cams.far, np.float64), (K,))
    width = np.broadcast_to(np.asarray(cams.width), (K,))
    height = np.broadcast_to(np.asarray(cams.height), (K,))
    with open(path, "w") as f:
        f.write(HEADER)
        for k in range(K):
            floats = [*eye[k], *look[k], *up[k], fov[k], near[k], far[k]]
            f.write(" ".join(f"{x:.9g}" for x in floats) + f" {int(width[k])} {int(height[k])}\n")
    return K


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", help="a model name of benchmarks/refine.py (its default build)")
    ap.add_argument("out")
    ap.add_argument("--frames", type=int, default=240)
    args = ap.parse_args()
    sys.path.insert(0, __file__.rsplit("/", 2)[0])
    from refine import pm_file

    import pmjax

    pm = pmjax.load(pm_file(args.model))
    cams = pmjax.standard_orbit(np.asarray(pm.vertices)[: pm.n_original_vertices], args.frames)
    print(f"{write_cameras(cams, args.out)} cameras written to {args.out}")


if __name__ == "__main__":
    main()
