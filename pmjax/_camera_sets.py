"""Camera sets made from a model's vertices: the standard orbit and random views."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._camera import Camera
from ._camera_table import orbit_rows, random_rows


def standard_orbit(vertices, n_frames: int = 240, *, elevation_deg=20.0, width=800, height=600,
                   fov_y_deg=45.0) -> Camera:
    """The standard orbit, the camera set of every published comparison, as a
    batch of ``n_frames`` cameras.

    Orbits the bounding-box centre at distance ``r / sin(22.5°)`` (``r`` = half
    the bounding-box diagonal) at 20° elevation, up axis +y.
    """
    table = orbit_rows(vertices, n_frames, 0, n_frames, elevation_deg=elevation_deg, width=width, height=height,
                       fov_y_deg=fov_y_deg)
    return jax.tree.map(jnp.asarray, table.camera())


def random_views(vertices, n: int, *, seed=0, min_scale=0.05, max_scale=4.0, width=800, height=600,
                 fov_y_deg=45.0) -> Camera:
    """``n`` cameras at random directions and distances around the model,
    each looking at a random point near it (inside, outside, close-up, far):
    the first ``n`` rows of the random view set with ``seed`` that
    ``pmjax eval --random`` uses (directions uniform on the sphere, distances
    log-uniform in ``[min_scale, max_scale]`` times the half diagonal)."""
    table = random_rows(vertices, seed, 0, n, min_scale=min_scale, max_scale=max_scale, width=width,
                        height=height, fov_y_deg=fov_y_deg)
    return jax.tree.map(jnp.asarray, table.camera())
