"""Cameras as pytrees; a batch of K cameras is the same pytree with a leading axis.

Convention (OpenGL): ``rotation`` is camera-to-world, its columns are the
camera's right, up and backward axes, so the camera looks along
``-rotation[:, 2]``. Angles are radians, distances model units, sizes pixels.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

# A JAX tracer: a value inside jit, vmap or grad, unknown until run.
_Tracer = jax.core.Tracer


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

    The constructor refuses only what it cannot keep: an image size that is
    not a whole number within ``int32`` (the cast would change it) and a
    flag that is not a boolean (or 0 or 1). :func:`check_camera` checks the
    rest of the values (finite, in range, an orthonormal rotation).

    Raises:
        CameraError: a size or flag as above (``Camera: width ...``).
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
        self.width = xp.broadcast_to(xp.asarray(_pixel_counts(width, "width"), np.int32), shape)
        self.height = xp.broadcast_to(xp.asarray(_pixel_counts(height, "height"), np.int32), shape)
        self.orthographic = _flag(orthographic, "Camera: orthographic")
        # A camera made by hand is checked once, here (not at every refine);
        # under tracing its values are unknown and trusted (check_camera).
        check_camera(self, what="Camera")

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
        # cheap under vmap (a sum-reduction form batches worse).
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


def _show(value):
    """A value for a message: Python numbers and lists rather than NumPy reprs."""
    if isinstance(value, (list, tuple)):
        return [_show(x) for x in value]
    if isinstance(value, (np.ndarray, np.generic)) and value.dtype.kind in "biuf":
        return value.tolist()
    return value


# Rules are written once, as "ok" expressions (True where the rule holds)
# that hold for Python numbers (one camera: cheap, no NumPy call per rule)
# and for NumPy arrays over rows (a batch: vectorized) alike.


def _first_fault(rules, scalar: bool):
    """``(row, message)`` of the first row breaking a rule (its first rule
    broken, in order), or ``None``.

    Args:
        rules: ``[(ok, message)]``: ``ok`` a bool (``scalar``) or bool arrays
            over the rows (broadcast); ``message(pick)`` the text for a row,
            ``pick`` taking a value to the row's.
    """
    if scalar:
        for ok, message in rules:
            if not ok:
                return 0, message(lambda x: x)
        return None
    oks = np.broadcast_arrays(*[ok for ok, _ in rules])
    bad = np.flatnonzero(~np.logical_and.reduce(oks))
    if not len(bad):
        return None
    i = int(bad[0])
    message = next(text for ok, (_, text) in zip(oks, rules) if not ok[i])
    return i, message(lambda x: x[i] if np.ndim(x) else x)


def _value_rules(v: dict, finite, name, top: float, unit: str) -> list:
    """The range rules of :func:`check_camera_values` over values ``v``
    (``eye`` as its three coordinates)."""
    e = v["eye"]
    rules = [(finite(e[0]) & finite(e[1]) & finite(e[2]),
              lambda p: f"{name('eye')} must be finite, got {_show([p(x) for x in e])}")]
    for key in ("fov_y_deg", "near", "far", "ortho_height"):
        rules.append((finite(v[key]), lambda p, key=key: f"{name(key)} must be finite, got {_show(p(v[key]))}"))
    for key in ("width", "height"):
        rules.append(((v[key] >= 1) & (v[key] <= MAX_IMAGE_SIZE), lambda p, key=key:
                      f"{name(key)} must be an integer in [1, {MAX_IMAGE_SIZE}], got {_show(p(v[key]))}"))
    fov, near, far = v["fov_y_deg"], v["near"], v["far"]
    return rules + [
        (v["orthographic"] | ((fov > 0) & (fov < top)),
         lambda p: f"{name('fov_y_deg')} must lie in {unit}, got {_show(p(fov))}"),
        (v["ortho_height"] > 0, lambda p: f"{name('ortho_height')} must be > 0, got {_show(p(v['ortho_height']))}"),
        (near > 0, lambda p: f"{name('near')} must be > 0, got {_show(p(near))}"),
        (far > near, lambda p: f"{name('far')} must be greater than {name('near')}, "
                               f"got {_show(p(far))} <= {_show(p(near))}"),
    ]


def check_camera_values(eye, fov_y_deg, near, far, ortho_height, width, height, orthographic, *,
                        name=lambda key: key, where: str = "", row: str = "", label=None,
                        radians: bool = False) -> None:
    """Range checks shared by every way of making cameras, vectorized over N
    rows (1-D arrays, ``eye [N, 3]``).

    Args:
        eye: ``[N, 3]`` positions; the other values ``[N]`` (or broadcast to it).
        fov_y_deg: vertical field of view, degrees (radians with ``radians``);
            checked for perspective rows only.
        width, height: integers.
        orthographic: a flag, or one per row.
        name: the name of a value in messages, from its key (``"eye"``,
            ``"fov_y_deg"``, ``"near"``, ...).
        where: prefix of every message (a file name and ``": "``).
        row: the word before a row's index (``"row"``, ``"frame"``); empty:
            no index in messages.
        label: a function of a row's index giving its name (``"cameras[3]"``),
            instead of ``row``.
        radians: ``fov_y_deg`` holds radians, checked in (0, pi).

    Raises:
        CameraError: ``{where}{row} i: {name(key)} ...`` for the first bad row
            (its first bad value: eye finite, the other values finite, sizes in
            [1, 65536], the field of view, ``ortho_height > 0``, ``near > 0``,
            ``far > near``), with the value found.
    """
    width, height = np.asarray(width), np.asarray(height)
    for key, values in (("width", width), ("height", height)):
        if values.dtype.kind not in "iu":
            raise CameraError(f"{where}{name(key)} must be an integer, got {values.dtype} values")
    eye = np.asarray(eye)
    values = dict(fov_y_deg=fov_y_deg, near=near, far=far, ortho_height=ortho_height, width=width, height=height,
                  orthographic=orthographic)
    scalar = eye.size == 3 and all(np.size(a) == 1 for a in values.values())
    if scalar:  # one row: Python numbers
        values = {k: np.asarray(a).reshape(-1)[0].item() for k, a in values.items()}
        values["eye"] = eye.reshape(3).tolist()
        finite = math.isfinite
    else:
        values = {k: np.asarray(a) for k, a in values.items()}
        values["eye"] = (eye[..., 0], eye[..., 1], eye[..., 2])
        finite = np.isfinite
    values["orthographic"] = bool(values["orthographic"]) if scalar else np.asarray(values["orthographic"], bool)
    top, unit = (math.pi, "(0, pi) radians") if radians else (180, "(0, 180) degrees")
    fault = _first_fault(_value_rules(values, finite, name, top, unit), scalar)
    if fault is not None:
        i, message = fault
        at = f"{label(i)}: " if label else f"{row} {i}: " if row else ""
        raise CameraError(f"{where}{at}{message}")


# Accepted spellings of a flag in a CSV file.
_FLAG_WORDS = {"true": True, "false": False, "1": True, "0": False}


def _flag(value, key, words: bool = False) -> bool:
    """A flag: a boolean or the integer 0 or 1; with ``words`` (a CSV field)
    the text true, false, 1 or 0 (any case, blanks around it ignored)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)) and value in (0, 1):
        return bool(value)
    if words and isinstance(value, str) and value.strip().lower() in _FLAG_WORDS:
        return _FLAG_WORDS[value.strip().lower()]
    spelled = "write true, false, 1 or 0" if words else "a bool, or the integer 0 or 1"
    raise CameraError(f"{key} must be true or false, got {value!r} ({spelled})")


def _pixel_counts(value, key):
    """``value`` (an image size, one or per camera) unchanged, after refusing
    what the cast to ``int32`` would silently change: booleans, fractions,
    non-finite values and values beyond ``int32``. Tracers and JAX integer
    arrays pass unchecked (no copy from the device)."""
    dtype = getattr(value, "dtype", None)
    if dtype is not None and np.dtype(dtype) == np.bool_:
        raise CameraError(f"Camera: {key} must be integers (pixels), got booleans")
    if isinstance(value, _Tracer) or (isinstance(value, jax.Array) and np.dtype(dtype).kind in "iu"
                                              and np.dtype(dtype).itemsize <= 4 and dtype != np.uint32):
        return value
    if isinstance(value, (bool, np.bool_)):
        raise CameraError(f"Camera: {key} must be an integer (pixels), got {value!r}")
    host = np.asarray(value)
    if host.dtype.kind not in "iuf":
        raise CameraError(f"Camera: {key} must be integers (pixels), got {host.dtype} values")
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(host) | (host != np.round(host)) if host.dtype.kind == "f" else np.zeros(host.shape, bool)
        bad |= (host < np.iinfo(np.int32).min) | (host > np.iinfo(np.int32).max)
    if bad.any():
        at = np.unravel_index(int(np.flatnonzero(bad)[0]), host.shape)
        index = f"[{', '.join(map(str, at))}]" if host.ndim else ""
        raise CameraError(f"Camera: {key}{index} must be an integer in [1, {MAX_IMAGE_SIZE}] (pixels), "
                          f"got {_show(host[at])}")
    return value


def _numbers(value, key, shape, text):
    """``value`` as a float64 array of ``shape``: numbers only (no booleans,
    strings or None, also inside lists, where NumPy would convert them)."""
    def has_non_number(v):
        if isinstance(v, (list, tuple)):
            return any(has_non_number(x) for x in v)
        return v is None or isinstance(v, (bool, np.bool_, str, bytes))

    a = None if has_non_number(value) else np.asarray(value)
    if a is None or a.dtype.kind not in "iuf":
        raise CameraError(f"look_at: {key} must be {text}, got {value!r}")
    if a.shape != shape:
        raise CameraError(f"look_at: {key} must be {text}, got shape {a.shape}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise CameraError(f"look_at: {key} must be finite, got {a.tolist()}")
    return a


def _vector(value, key):
    return _numbers(value, key, (3,), "3 numbers")


def _number(value, key) -> float:
    try:
        if isinstance(value, (bool, np.bool_, str, bytes)):
            raise TypeError
        return float(value)
    except (TypeError, ValueError):
        raise CameraError(f"look_at: {key} must be a number, got {value!r}") from None


def _size(value, key) -> int:
    number = _number(value, key)
    if not (math.isfinite(number) and number == int(number)):
        raise CameraError(f"look_at: {key} must be an integer, got {value!r}")
    return int(number)


# How far a rotation's columns may be from orthonormal (largest entry of
# RᵀR − I): float32 look-at rotations are within 1e-6; narrower dtypes are
# allowed a few units in their last place.
ROTATION_TOLERANCE = 1e-4

_ARRAY_FIELDS = ("eye", "rotation", "fov_y", "near", "far", "ortho_height", "width", "height")


def _rotation_rules(r, finite, largest, tolerance: float) -> list:
    """The rules of a rotation ``r`` (``r[i][j]`` a number, or an array over
    rows): finite, orthonormal within ``tolerance`` (largest entry of
    ``RᵀR − I``), not a reflection; for :func:`_first_fault`."""
    entries = [x for row in r for x in row]
    ok = finite(entries[0])
    for x in entries[1:]:
        ok = ok & finite(x)
    col = [[r[0][j], r[1][j], r[2][j]] for j in range(3)]

    def dot(a, b):
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

    error = largest([abs(dot(col[i], col[j]) - (i == j)) for i in range(3) for j in range(i, 3)])
    a, b, c = col
    det = dot(a, [b[1] * c[2] - b[2] * c[1], b[2] * c[0] - b[0] * c[2], b[0] * c[1] - b[1] * c[0]])
    return [
        (ok, lambda p: f"rotation must be finite, got {_show([[p(x) for x in row] for row in r])}"),
        (error <= tolerance, lambda p: "rotation is not orthonormal (its columns right, up and back must be unit "
         f"vectors at right angles; largest entry of RᵀR − I: {p(error):.3g}, allowed {tolerance:.3g}): make "
         "it with look_at or look_at_rotations"),
        (det > 0, lambda p: "rotation is a reflection (determinant -1)"),
    ]


def check_camera(camera, *, what: str = "camera") -> None:
    """Check a camera (or a batch) made by hand, as :func:`look_at` and the
    camera files check theirs.

    Checked: the fields' shapes (``eye [*K, 3]``, ``rotation [*K, 3, 3]``,
    the others ``[*K]``) and kinds (numbers, not booleans; integers for the
    image size); the rotation finite, orthonormal (``|RᵀR − I| <= 1e-4``, or
    a few units in the last place of a narrower dtype) and not a
    reflection; then :func:`check_camera_values`: eye and values finite,
    ``fov_y`` in (0, pi) radians (perspective), ``width`` and ``height`` in
    [1, 65536], ``0 < near < far``, ``ortho_height > 0``. The fields are
    copied to the host once; a batch is checked with vectorized NumPy, one
    camera with Python numbers.

    Under tracing (``jit``, ``vmap``, ``grad``: any field a JAX tracer)
    nothing is checked: the values are unknown, and the caller's are
    trusted.

    Args:
        camera: a :class:`Camera`, one or a batch with leading axes ``*K``.
        what: the camera's name in messages (the argument it came from).

    Raises:
        CameraError: ``{what}: {field} ...`` for one camera; for a batch
            ``{what}[i]: {field} ...`` (``[i, j]`` with two leading axes),
            ``i`` the first bad camera; the message names the rule and the
            value found.
    """
    if not isinstance(camera, Camera):
        raise CameraError(f"{what} must be a pmjax.Camera, got {type(camera).__name__}")
    fields = vars(camera)  # plain reads: an equinox module's attribute access runs Python code
    values = [fields[k] for k in _ARRAY_FIELDS]
    for v in values:
        if isinstance(v, _Tracer):
            return
    host = {}
    for key, value in zip(_ARRAY_FIELDS, values):
        a = np.asarray(value)
        # (kind "V": bfloat16 and the other ml_dtypes floats JAX uses)
        if not (a.dtype.kind in "iuf" or (a.dtype.kind == "V" and jnp.issubdtype(a.dtype, jnp.floating))):
            got = f"{a.dtype} values" if a.dtype != object else type(value).__name__
            raise CameraError(f"{what}: {key} must be numbers, got {got}")
        host[key] = a
    eye = host["eye"]
    if eye.ndim < 1 or eye.shape[-1] != 3:
        raise CameraError(f"{what}: eye must have shape [..., 3] (one position per camera), got shape {eye.shape}")
    lead = eye.shape[:-1]
    for key in _ARRAY_FIELDS[1:]:
        want = lead + (3, 3) if key == "rotation" else lead
        if host[key].shape != want:
            raise CameraError(f"{what}: {key} has shape {host[key].shape}, expected {want} "
                              f"(eye has shape {eye.shape})")
    n = int(np.prod(lead, dtype=np.int64))
    flat = {k: a.reshape((n,) + a.shape[len(lead):]) for k, a in host.items()}
    if not lead:
        where, label = f"{what}: ", None
    elif len(lead) == 1:
        where, label = "", lambda i: f"{what}[{i}]"
    else:
        where, label = "", lambda i: f"{what}[{', '.join(str(int(j)) for j in np.unravel_index(i, lead))}]"
    rotation = flat["rotation"]
    eps = float(jnp.finfo(rotation.dtype).eps) if rotation.dtype.kind in "fV" else 0.0
    tolerance = max(ROTATION_TOLERANCE, 16 * eps)
    scalar = n == 1
    if scalar:
        rules = _rotation_rules(rotation[0].astype(np.float64).tolist(), math.isfinite, max, tolerance)
    else:
        r = rotation.astype(np.float64)
        with np.errstate(invalid="ignore", over="ignore"):
            rules = _rotation_rules([[r[:, i, j] for j in range(3)] for i in range(3)], np.isfinite,
                                    np.maximum.reduce, tolerance)
    # Image sizes stored as floats (a camera rebuilt with eqx.tree_at, not
    # the constructor): whole numbers in range only.
    for key in ("width", "height"):
        a = flat[key]
        if a.dtype.kind not in "iu":
            with np.errstate(invalid="ignore"):
                ok = (a == np.round(a)) & (a >= 1) & (a <= MAX_IMAGE_SIZE)
            got = a[0].item() if scalar else a
            rules.append((bool(ok[0]) if scalar else ok, lambda p, key=key, got=got:
                          f"{key} must be an integer in [1, {MAX_IMAGE_SIZE}], got {_show(p(got))}"))
            flat[key] = np.where(ok, a, 1).astype(np.int64)
    fault = _first_fault(rules, scalar)
    end = n if fault is None else fault[0]
    # The values of the cameras before the first fault found so far, so that
    # the error names the first bad camera.
    check_camera_values(flat["eye"][:end], flat["fov_y"][:end], flat["near"][:end], flat["far"][:end],
                        flat["ortho_height"][:end], flat["width"][:end], flat["height"][:end], camera.orthographic,
                        name=lambda key: "fov_y" if key == "fov_y_deg" else key, where=where, label=label,
                        radians=True)
    if fault is not None:
        raise CameraError(f"{where}{label(end) + ': ' if label else ''}{fault[1]}")


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
            ``ortho_height <= 0``, ``orthographic`` not a boolean (or 0 or 1);
            a boolean or a string where a number belongs.
    """
    eye, target, up = _vector(eye, "eye"), _vector(target, "target"), _vector(up, "up")
    orthographic = _flag(orthographic, "look_at: orthographic")
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
    """K single cameras -> one camera batch.

    Args:
        cameras: ``K >= 1`` cameras of one projection (perspective or
            orthographic), each eye ``[3]``; image sizes may differ.

    Returns:
        A :class:`Camera` whose fields have a leading axis ``[K]`` (eye
        ``[K, 3]``, rotation ``[K, 3, 3]``).

    Raises:
        ValueError: no cameras, or projections that differ.
    """
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
    """Camera ``i`` (or a slice) of a batch.

    Args:
        camera: a camera batch (eye ``[K, 3]``).
        i: an index (one camera: eye ``[3]``), a slice or an index array (a
            batch), as NumPy indexes the leading axis.
    """
    import jax

    return jax.tree_util.tree_map(lambda a: a[i], camera)


def fly_through(keyframes: list[tuple], n_frames: int, **kw) -> Camera:
    """Cameras interpolated linearly between keyframes ``(eye, target)``.

    Args:
        keyframes: two or more ``(eye, target)`` pairs of 3 numbers each
            (model units), passed through in order.
        n_frames: cameras in all, the first at the first keyframe and the
            last at the last, evenly spaced in keyframe steps between.
        **kw: :func:`look_at`'s keywords for every camera (``up``,
            ``fov_y_deg``, ``width``, ``height``, ``near``, ``far``, ...).

    Returns:
        A camera batch (eye ``[n_frames, 3]``).

    Raises:
        ValueError: fewer than two keyframes; CameraError: a value
            :func:`look_at` refuses.
    """
    if len(keyframes) < 2:
        raise ValueError("a fly-through needs at least two keyframes")
    keys = np.asarray([[np.asarray(e, float), np.asarray(t, float)] for e, t in keyframes])
    s = np.linspace(0, len(keys) - 1, n_frames)
    i = np.minimum(s.astype(int), len(keys) - 2)
    w = (s - i)[:, None, None]
    pose = keys[i] * (1 - w) + keys[i + 1] * w
    return stack_cameras([look_at(p[0], p[1], **kw) for p in pose])
