"""Cameras as pytrees; a batch of K cameras is the same pytree with a leading axis.

Convention (OpenGL): ``rotation`` is camera-to-world, its columns are the
camera's right, up and backward axes, so the camera looks along
``-rotation[:, 2]``. Angles are radians, distances model units, sizes pixels.
"""

from __future__ import annotations

import csv
import json
import math
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._atomic import atomic_path


class Camera(eqx.Module):
    """A pinhole (or orthographic) camera.

    Attributes:
        eye: ``[..., 3]`` position.
        rotation: ``[..., 3, 3]`` camera-to-world rotation (columns right, up, back).
        fov_y: ``[...]`` vertical field of view, radians (perspective).
        near, far: ``[...]`` clip distances along the view direction.
        ortho_height: ``[...]`` view height in model units (orthographic).
        width, height: ``[...]`` image size in pixels (``int32``; traced, so
            one compiled kernel serves every image size).
        orthographic: static flag.
    """

    eye: Float[Array, "*K 3"]
    rotation: Float[Array, "*K 3 3"]
    fov_y: Float[Array, "*K"]
    near: Float[Array, "*K"]
    far: Float[Array, "*K"]
    ortho_height: Float[Array, "*K"]
    width: Int[Array, "*K"]
    height: Int[Array, "*K"]
    orthographic: bool = eqx.field(static=True, default=False)

    def __init__(self, eye, rotation, fov_y, near, far, ortho_height, width=800, height=600, orthographic=False):
        self.eye, self.rotation, self.fov_y = eye, rotation, fov_y
        self.near, self.far, self.ortho_height = near, far, ortho_height
        # One size per camera, whatever was given (a batch may mix sizes);
        # host arrays stay on the host, like the other fields.
        xp = np if isinstance(fov_y, np.ndarray) else jnp
        shape = np.shape(fov_y)
        self.width = xp.broadcast_to(xp.asarray(width, np.int32), shape)
        self.height = xp.broadcast_to(xp.asarray(height, np.int32), shape)
        self.orthographic = bool(orthographic)

    def aspect(self):
        """Width over height, in the dtype of the camera's angles."""
        dtype = jnp.result_type(self.fov_y)
        return self.width.astype(dtype) / self.height.astype(dtype)

    @property
    def forward(self):
        return -self.rotation[..., :, 2]

    def astype(self, dtype) -> "Camera":
        """The same camera with its array fields in ``dtype``."""
        cast = lambda x: x.astype(dtype)  # noqa: E731
        return Camera(cast(self.eye), cast(self.rotation), cast(self.fov_y), cast(self.near), cast(self.far),
                      cast(self.ortho_height), self.width, self.height, self.orthographic)

    def pose(self) -> np.ndarray:
        """4×4 camera-to-world matrix (as pyrender wants it), float64."""
        m = np.eye(4)
        m[:3, :3] = np.asarray(self.rotation)
        m[:3, 3] = np.asarray(self.eye)
        return m

    def frustum_frame(self):
        """The frustum in camera coordinates, for the sphere test.

        With ``x = right·(c − eye)``, ``y = up·(c − eye)`` and the depth
        ``z = forward·(c − eye)``, a sphere of radius ``r`` at ``c`` is
        entirely outside a frustum plane exactly when
        ``z + r < near``, ``z − r > far``,
        ``z·a_x + b_x − |x| < −r·l_x`` or ``z·a_y + b_y − |y| < −r·l_y``:
        the two side planes of each pair as one test on ``|x|`` (perspective:
        ``a = tan(half angle)``, ``b = 0``, ``l = √(1 + a²)``; orthographic:
        ``a = 0``, ``b`` the half extent, ``l = 1``). The same six planes as
        :meth:`frustum_planes`, without normalizing them per camera.

        Returns:
            ``(axes [3, 3], consts [8])`` for one camera: rows right, up, forward;
            ``consts`` = ``(a_x, a_y, b_x, b_y, l_x, l_y, near, far)``.
        """
        # One camera (vmap for many): written with 1-D dots, which XLA keeps
        # cheap under vmap (a sum-reduction form made the batched predicate
        # 1.8x slower, measured).
        r, u, f = self.rotation[:, 0], self.rotation[:, 1], -self.rotation[:, 2]
        aspect = self.aspect()
        if self.orthographic:
            b_y = 0.5 * self.ortho_height + 0.0 * self.near
            slope = [0.0 * b_y, 0.0 * b_y, b_y * aspect, b_y, 1.0 + 0.0 * b_y, 1.0 + 0.0 * b_y]
        else:
            a_y = jnp.tan(0.5 * self.fov_y)
            a_x = a_y * aspect
            slope = [a_x, a_y, 0.0 * a_x, 0.0 * a_y, jnp.sqrt(1.0 + a_x * a_x), jnp.sqrt(1.0 + a_y * a_y)]
        consts = jnp.stack(slope + [self.near, self.far])
        return jnp.stack([r, u, f]), consts

    def frustum_planes(self) -> Float[Array, "*K 6 4"]:
        """Six inward planes ``(n, d)``: a point ``x`` is inside when ``n·x + d >= 0``."""
        r = self.rotation[..., :, 0]
        u = self.rotation[..., :, 1]
        f = -self.rotation[..., :, 2]
        e = self.eye
        aspect = self.aspect()

        def plane(n, d):
            return jnp.concatenate([n, d[..., None]], axis=-1)

        dot = lambda a, b: jnp.sum(a * b, axis=-1)
        near = plane(f, -(dot(f, e) + self.near))
        far = plane(-f, dot(f, e) + self.far)
        if self.orthographic:
            hy = 0.5 * self.ortho_height
            hx = hy * aspect
            sides = [
                plane(-r, dot(r, e) + hx),
                plane(r, -dot(r, e) + hx),
                plane(-u, dot(u, e) + hy),
                plane(u, -dot(u, e) + hy),
            ]
        else:
            ty = jnp.tan(0.5 * self.fov_y)[..., None]
            tx = ty * aspect
            sides = []
            for n in (f * tx - r, f * tx + r, f * ty - u, f * ty + u):
                n = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
                sides.append(plane(n, -dot(n, e)))
        return jnp.stack([near, far] + sides, axis=-2)


class CameraError(ValueError):
    """A camera value out of range; the message names the value (and the file
    and camera or row it came from)."""


MAX_IMAGE_SIZE = 1 << 16


def check_camera_values(eye, fov_y_deg, near, far, ortho_height, width, height, orthographic, *,
                        name=lambda key: key, where: str = "", row: str = "") -> None:
    """Range checks shared by every way of making cameras, vectorized over N
    rows (1-D arrays, ``eye [N, 3]``).

    Raises:
        CameraError: ``{where}{row} i: {name(key)} ...`` for the first bad
            value (no row part when ``row`` is empty).
    """
    width, height = np.asarray(width), np.asarray(height)

    def fail(bad, what):
        rows = np.flatnonzero(np.broadcast_to(bad, np.shape(fov_y_deg)))
        if len(rows):
            at = f"{row} {rows[0]}: " if row else ""
            raise CameraError(f"{where}{at}{what}")

    fail(~np.all(np.isfinite(eye), axis=-1), f"{name('eye')} must be finite")
    for key, values in (("fov_y_deg", fov_y_deg), ("near", near), ("far", far), ("ortho_height", ortho_height)):
        fail(~np.isfinite(values), f"{name(key)} must be finite")
    for key, values in (("width", width), ("height", height)):
        if values.dtype.kind not in "iu":
            raise CameraError(f"{where}{name(key)} must be an integer, got {values.dtype} values")
        fail((values < 1) | (values > MAX_IMAGE_SIZE), f"{name(key)} must be an integer in [1, {MAX_IMAGE_SIZE}]")
    fail(~np.asarray(orthographic, bool) & ~((fov_y_deg > 0) & (fov_y_deg < 180)),
         f"{name('fov_y_deg')} must lie in (0, 180) degrees")
    fail(~(ortho_height > 0), f"{name('ortho_height')} must be > 0")
    fail(~(near > 0), f"{name('near')} must be > 0")
    fail(~(far > near), f"{name('far')} must be greater than {name('near')}")


def _vector(value, key):
    v = np.asarray(value, np.float64)
    if v.shape != (3,):
        raise CameraError(f"look_at: {key} must be 3 numbers, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise CameraError(f"look_at: {key} must be finite, got {v.tolist()}")
    return v


def _number(value, key) -> float:
    try:
        if isinstance(value, (bool, np.bool_, str)):
            raise TypeError
        return float(value)
    except (TypeError, ValueError):
        raise CameraError(f"look_at: {key} must be a number, got {value!r}") from None


def _size(value, key) -> int:
    number = _number(value, key)
    if not (math.isfinite(number) and number == int(number)):
        raise CameraError(f"look_at: {key} must be an integer, got {value!r}")
    return int(number)


def look_at_rotations(eye, target, up) -> np.ndarray:
    """Camera-to-world rotations ``float64[N, 3, 3]`` looking from ``eye`` at
    ``target`` (``[N, 3]`` each), columns right, up, back; when ``up``
    is along the view, another up is picked."""
    back = eye - target
    back = back / np.linalg.norm(back, axis=1, keepdims=True)
    right = np.cross(up, back)
    # Looking along up: another up, away from the view direction.
    along = np.linalg.norm(right, axis=1) < 1e-9
    if along.any():
        other = np.where(np.abs(back[along, 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
        right[along] = np.cross(other, back[along])
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    true_up = np.cross(back, right)
    return np.stack([right, true_up, back], axis=2)


def look_at(eye, target, up=(0.0, 1.0, 0.0), *, fov_y_deg=45.0, width=800, height=600, near=None, far=None,
            orthographic=False, ortho_height=1.0, host=False) -> Camera:
    """Camera at ``eye`` looking at ``target`` (numpy inputs, one camera).

    ``near``/``far`` default to 1e-3 and 1e3 times the eye–target distance.
    ``host=True`` keeps the fields as float64 NumPy values (for writing
    camera files exactly); by default they are float32 JAX arrays.

    Raises:
        CameraError: a value out of range: eye, target or up not 3 finite
            numbers, eye on target, up zero, fov not in (0°, 180°) (perspective),
            a size not an integer in [1, 65536], ``near <= 0``, ``far <= near``,
            ``ortho_height <= 0``, ``orthographic`` not a boolean.
    """
    eye, target, up = _vector(eye, "eye"), _vector(target, "target"), _vector(up, "up")
    if not isinstance(orthographic, (bool, np.bool_)):
        raise CameraError(f"look_at: orthographic must be true or false, got {orthographic!r}")
    width, height = _size(width, "width"), _size(height, "height")
    dist = np.linalg.norm(eye - target)
    if not dist > 0:
        raise CameraError("look_at: eye and target coincide")
    if not np.linalg.norm(up) > 0:
        raise CameraError("look_at: up is zero")
    near = 1e-3 * dist if near is None else _number(near, "near")
    far = 1e3 * dist if far is None else _number(far, "far")
    fov_y_deg, ortho_height = _number(fov_y_deg, "fov_y_deg"), _number(ortho_height, "ortho_height")
    check_camera_values(eye[None], np.array([fov_y_deg]), np.array([near]), np.array([far]),
                        np.array([ortho_height]), np.array([width]), np.array([height]),
                        np.array([orthographic]), where="look_at: ")
    rotation = look_at_rotations(eye[None], target[None], up[None])[0]
    value = (lambda x: np.asarray(x, np.float64)) if host else (lambda x: jnp.asarray(x, jnp.float32))
    return Camera(
        eye=value(eye),
        rotation=value(rotation),
        fov_y=value(math.radians(fov_y_deg)),
        near=value(near),
        far=value(far),
        ortho_height=value(ortho_height),
        width=int(width),
        height=int(height),
        orthographic=bool(orthographic),
    )


def stack_cameras(cameras: list[Camera]) -> Camera:
    """K single cameras (same projection; image sizes may differ) -> one camera batch."""
    if not cameras:
        raise ValueError("no cameras to stack")
    first = cameras[0]
    for c in cameras:
        if c.orthographic != first.orthographic:
            raise ValueError("cameras in a batch must share the projection (perspective or orthographic)")
    return Camera(
        *(jnp.stack([getattr(c, k) for c in cameras])
          for k in ("eye", "rotation", "fov_y", "near", "far", "ortho_height", "width", "height")),
        orthographic=first.orthographic,
    )


def camera_count(camera: Camera) -> int:
    """K for a batch, 0 for a single camera."""
    return int(camera.eye.shape[0]) if camera.eye.ndim == 2 else 0


def index_camera(camera: Camera, i) -> Camera:
    """Camera ``i`` (or a slice) of a batch."""
    import jax

    return jax.tree_util.tree_map(lambda a: a[i], camera)


def fly_through(keyframes: list[tuple], n_frames: int, **kw) -> Camera:
    """Cameras interpolated linearly between keyframes ``(eye, target)``."""
    if len(keyframes) < 2:
        raise ValueError("a fly-through needs at least two keyframes")
    keys = np.asarray([[np.asarray(e, float), np.asarray(t, float)] for e, t in keyframes])
    s = np.linspace(0, len(keys) - 1, n_frames)
    i = np.minimum(s.astype(int), len(keys) - 2)
    w = (s - i)[:, None, None]
    pose = keys[i] * (1 - w) + keys[i + 1] * w
    return stack_cameras([look_at(p[0], p[1], **kw) for p in pose])


_FIELDS = ("eye", "rotation", "fov_y", "near", "far", "ortho_height")


def save_cameras(camera: Camera, path) -> None:
    """Write cameras to JSON (``.json``) or CSV (``.csv``), atomically."""
    path = os.fspath(path)
    K = camera_count(camera)
    cams = [camera] if K == 0 else [index_camera(camera, i) for i in range(K)]
    rows = [
        dict(eye=np.asarray(c.eye).tolist(), rotation=np.asarray(c.rotation).tolist(),
             fov_y_deg=math.degrees(float(c.fov_y)), near=float(c.near), far=float(c.far),
             ortho_height=float(c.ortho_height), width=int(c.width), height=int(c.height))
        for c in cams
    ]
    # JSON: the image size once at the top, and per camera only in a batch that mixes sizes.
    meta = dict(width=rows[0]["width"], height=rows[0]["height"], orthographic=camera.orthographic)
    if all((r["width"], r["height"]) == (meta["width"], meta["height"]) for r in rows):
        for r in rows:
            del r["width"], r["height"]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        if path.endswith(".csv"):
            w = csv.writer(fh)
            w.writerow(["ex", "ey", "ez"] + [f"r{i}{j}" for i in range(3) for j in range(3)]
                       + ["fov_y_deg", "near", "far", "ortho_height", "width", "height", "orthographic"])
            for row in rows:
                w.writerow(row["eye"] + sum(row["rotation"], []) + [row["fov_y_deg"], row["near"], row["far"],
                           row["ortho_height"], row.get("width", meta["width"]), row.get("height", meta["height"]),
                           int(meta["orthographic"])])
        else:
            json.dump(dict(meta, cameras=rows), fh, indent=1)


# Keys of a JSON camera file: the file's, and each camera's.
FILE_KEYS = ("width", "height", "orthographic", "cameras")
CAMERA_KEYS = ("eye", "target", "up", "rotation", "fov_y_deg", "near", "far", "ortho_height", "width", "height")


def _known_keys(doc, known):
    unknown = sorted(set(doc) - set(known))
    if unknown:
        raise CameraError(f"unknown key {unknown[0]!r}; known keys: {', '.join(known)}")


def load_cameras(path) -> Camera:
    """Read cameras written by :func:`save_cameras` (or by hand: JSON with
    ``cameras: [{eye, target | rotation, fov_y_deg, ...}]``, a camera's own
    ``width``/``height`` overriding the file's). Always a batch."""
    path = os.fspath(path)
    single = None
    try:
        if path.endswith(".csv"):
            with open(path, newline="") as fh:
                rows = list(csv.DictReader(fh))
            meta = dict(width=int(rows[0]["width"]), height=int(rows[0]["height"]),
                        orthographic=bool(int(rows[0]["orthographic"])))
            items = [dict(eye=[float(r[k]) for k in ("ex", "ey", "ez")],
                          rotation=np.array([float(r[f"r{i}{j}"]) for i in range(3) for j in range(3)]).reshape(3, 3),
                          fov_y_deg=float(r["fov_y_deg"]), near=float(r["near"]), far=float(r["far"]),
                          ortho_height=float(r["ortho_height"]), width=int(r["width"]), height=int(r["height"]))
                     for r in rows]
        else:
            with open(path) as fh:
                doc = json.load(fh)
            if not isinstance(doc, dict):
                raise CameraError(f"{path}: expected a JSON object (one camera, or cameras: [...]), "
                                  f"got {type(doc).__name__}")
            try:
                _known_keys(doc, FILE_KEYS if "cameras" in doc else FILE_KEYS + CAMERA_KEYS)
            except CameraError as exc:
                raise CameraError(f"{path}: {exc}") from None
            meta = dict(width=doc.get("width", 800), height=doc.get("height", 600),
                        orthographic=doc.get("orthographic", False))
            items = doc["cameras"] if "cameras" in doc else [doc]
            single = None if "cameras" in doc else doc
            if not isinstance(items, list):
                raise CameraError(f"{path}: 'cameras' must be a list, got {type(items).__name__}")
    except CameraError:
        raise
    except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
        raise CameraError(f"{path}: cannot read cameras ({type(exc).__name__}: {exc})") from exc
    cams = []
    for i, it in enumerate(items):
        try:
            if not isinstance(it, dict):
                raise CameraError(f"expected a JSON object, got {type(it).__name__}")
            if it is not single:  # a single-camera file was checked with the file's keys
                _known_keys(it, CAMERA_KEYS)
            if "eye" not in it:
                raise CameraError("'eye' is missing")
            if ("target" in it) == ("rotation" in it):
                raise CameraError("give either 'target' (and optionally 'up') or 'rotation', "
                                  + ("not both" if "target" in it else "neither"))
            eye = np.asarray(it["eye"], float)
            size = dict(meta, width=it.get("width", meta["width"]), height=it.get("height", meta["height"]))
            if "rotation" in it:
                rot = np.asarray(it["rotation"], float)
                if rot.shape != (3, 3) or not np.allclose(rot.T @ rot, np.eye(3), atol=1e-4):
                    raise CameraError("rotation is not a 3×3 rotation matrix (orthonormal columns)")
                if np.linalg.det(rot) < 0:
                    raise CameraError("rotation is a reflection (determinant -1)")
                cam = look_at(eye, eye - rot[:, 2], rot[:, 1], fov_y_deg=it.get("fov_y_deg", 45.0), **size,
                              near=it.get("near"), far=it.get("far"), ortho_height=it.get("ortho_height", 1.0))
            else:
                cam = look_at(eye, it["target"], it.get("up", (0, 1, 0)), fov_y_deg=it.get("fov_y_deg", 45.0),
                              **size, near=it.get("near"), far=it.get("far"), ortho_height=it.get("ortho_height", 1.0))
        except (KeyError, ValueError, TypeError) as exc:
            raise CameraError(f"{path}: camera {i}: {str(exc).removeprefix('look_at: ')}") from exc
        cams.append(cam)
    return stack_cameras(cams)
