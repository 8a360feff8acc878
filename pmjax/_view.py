"""What the refinement tests need of one camera, computed once per view.

Every per-pcol test compares the pcol against a few numbers that depend on the
camera alone: the eye, the camera axes, the frustum's slopes and offsets, the
size of ``tau`` pixels. They are computed once per view and kept in one array,
and the batched predicate reads each as a contiguous row of per-camera values.
Both matter on the CPU: recomputed per pcol (XLA fuses them into the per-pcol
loop) or read as strided columns of a ``[K, n]`` array, they would dominate the
predicate's cost.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._camera import Camera
from ._scalars import check_camera_type, checked_tau

# Layout of View.values: eye, the rows right/up/forward, the frustum constants
# of Camera.frustum_frame, one pixel, kappa squared.
_EYE, _AXES, _FRUSTUM, _ONE_PIXEL, _KAPPA2 = 0, 3, 12, 20, 21


def one_pixel(camera: Camera) -> Float[Array, "*K"]:
    """One pixel of the image height as an angle at unit distance
    (``2 tan(φ/2) / H``), or as a world size (orthographic)."""
    height = camera.height.astype(jnp.result_type(camera.fov_y))
    if camera.orthographic:
        return camera.ortho_height / height
    return 2.0 * jnp.tan(0.5 * camera.fov_y) / height


def kappa(camera: Camera, tau) -> Float[Array, "*K"]:
    """Screen-space tolerance ``tau`` pixels as an angle (or a world size):
    ``one_pixel(camera) * tau``, a single rounding, so it is monotone in ``tau``
    (:func:`pmjax.critical_tau` relies on it).

    Args:
        camera: one :class:`Camera` or a batch (leading axis K).
        tau: tolerance, pixels of the image height (one number >= 0).

    Returns:
        radians per unit distance (perspective) or world units
        (orthographic), shaped like ``camera.fov_y`` (``[]`` or ``[K]``).
    """
    check_camera_type(camera, "kappa")
    return one_pixel(camera) * checked_tau(tau, "kappa")


def kappa_squared(unit, tau):
    """``kappa²`` from :func:`one_pixel` and ``tau``: the one expression both the
    screen test (through :class:`View`) and the bisection of
    :func:`pmjax.critical_tau` evaluate, so they agree bit for bit."""
    k = unit * tau
    return k * k


def _values(camera: Camera, tau) -> list:
    """The 22 constants of one camera, as scalars."""
    axes, consts = camera.frustum_frame()
    unit = one_pixel(camera)
    return [camera.eye[i] for i in range(3)] + [axes[i, j] for i in range(3) for j in range(3)] + \
        [consts[i] for i in range(8)] + [unit, kappa_squared(unit, tau)]


class View(eqx.Module):
    """One camera's constants for the per-pcol tests (or ``[22, K]`` for K cameras,
    see :meth:`batch`).

    Attributes:
        values: ``[22]`` eye (3), right, up and forward axes (3 × 3), the
            frustum constants of :meth:`Camera.frustum_frame` (8),
            :func:`one_pixel`, ``kappa(camera, tau)²``.
        orthographic: static, as the camera.
    """

    values: Float[Array, " 22"]
    orthographic: bool = eqx.field(static=True, default=False)

    @staticmethod
    def of(camera: Camera, tau) -> "View":
        """The constants of one camera for tolerance ``tau`` pixels."""
        # The barrier keeps XLA from fusing this per-camera arithmetic (tan,
        # sqrt) into every pcol's test.
        return View(jax.lax.optimization_barrier(jnp.stack(_values(camera, tau))), camera.orthographic)

    @staticmethod
    def batch(cameras: Camera, tau) -> "View":
        """The constants of K cameras as rows, ``values[22, K]``, for one
        ``tau`` or one per camera (``[K]``); map a test over the cameras with
        :meth:`map`."""
        # Stacked from per-constant rows: a transpose of ``[K, 22]`` would be
        # turned into a column-major layout of the same memory, whose rows are
        # strided.
        values = jnp.stack(jax.vmap(_values, in_axes=(0, 0 if jnp.ndim(tau) else None))(cameras, tau))
        return View(jax.lax.optimization_barrier(values), cameras.orthographic)

    def map(self, fn):
        """``fn(view)`` for each camera of a :meth:`batch`, stacked on a leading axis."""
        return jax.vmap(lambda v: fn(View(v, self.orthographic)), in_axes=1)(self.values)

    @property
    def eye(self):
        return tuple(self.values[_EYE + i] for i in range(3))

    def axis(self, i: int):
        """Row ``i`` of the camera frame (0 right, 1 up, 2 forward) as three scalars."""
        return tuple(self.values[_AXES + 3 * i + j] for j in range(3))

    @property
    def forward(self):
        return self.axis(2)

    def frustum(self, i: int):
        """Constant ``i`` of :meth:`Camera.frustum_frame`."""
        return self.values[_FRUSTUM + i]

    @property
    def one_pixel(self):
        """:func:`one_pixel` of the camera."""
        return self.values[_ONE_PIXEL]

    @property
    def kappa2(self):
        """``kappa(camera, tau)²``."""
        return self.values[_KAPPA2]
