"""The checks every public refinement call makes of its arguments.

Each says which call and which argument is wrong and what was expected, before
any work, so a wrong type never surfaces as an error from deep inside JAX.
They cost a few attribute reads (the calls are hot: a refine is a fraction of
a millisecond). Camera values are checked when a :class:`pmjax.Camera` is made;
a camera's type and scalar arguments by :mod:`pmjax._scalars`.
"""

from __future__ import annotations

import collections
import threading
import weakref

import jax
import numpy as np

from ._model import ProgressiveMesh, kill_summary
from ._pmdata import PMData
from ._scalars import check_camera_type


def check_mesh(pm, call: str) -> None:
    """``pm`` is a :class:`ProgressiveMesh` (``TypeError`` otherwise, with the
    remedy) whose face-kill counts agree (:func:`check_kills`)."""
    if isinstance(pm, ProgressiveMesh):
        check_kills(pm, call)
        return
    if isinstance(pm, PMData):
        raise TypeError(f"{call}: pm is a PMData (host arrays, as read_pm gives); the refinement needs a "
                        "ProgressiveMesh: pmjax.load(path), or pmjax.ProgressiveMesh.from_data(data)")
    raise TypeError(f"{call}: pm must be a ProgressiveMesh (pmjax.load(path)), got {type(pm).__name__}")


def check_camera(camera, call: str, *, batch: bool) -> int:
    """``camera`` is a :class:`Camera`: one (``batch=False``, eye ``[3]``) or a
    non-empty batch (eye ``[K, 3]``). Returns K (0 for one camera)."""
    check_camera_type(camera, call)
    shape = np.shape(camera.eye)
    if batch:
        if len(shape) != 2 or shape[1] != 3:
            raise ValueError(f"{call}: needs a camera batch (eye of shape [K, 3]), got eye of shape {list(shape)}; "
                             "stack cameras with pmjax.stack_cameras, or call refine for one camera")
        if shape[0] == 0:
            raise ValueError(f"{call}: the camera batch is empty (0 cameras)")
        return int(shape[0])
    if shape != (3,):
        what = f"a batch of {shape[0]} cameras" if len(shape) == 2 else f"eye of shape {list(shape)}"
        raise ValueError(f"{call}: takes one camera (eye of shape [3]), got {what}; use refine_batch or "
                         "path_counts for many, or pmjax.index_camera(cameras, i) for one of them")
    return 0


# Content keys of meshes whose kill counts were found consistent (a few: the
# meshes a study refines at once).
_KILLS_CHECKED: collections.OrderedDict = collections.OrderedDict()
_KILLS_CHECKED_SIZE = 64
_KILLS_LOCK = threading.Lock()
_last_checked = None


def check_kills(pm: ProgressiveMesh, call: str) -> None:
    """``pm.kills`` counts the faces each pcol kills in ``pm.killer``, and the
    static summary the face counts use (``uncommon``, ``max_kills``,
    ``min_kills``, ``common_kills``) is that of ``pm.kills``: an
    ``eqx.tree_at`` of one without the others would make the engines count
    faces differently. Checked once per content (the arrays' digests); a mesh
    being traced (its arrays abstract) cannot be checked.

    Raises:
        ValueError: naming the call, what disagrees and the remedy.
    """
    from .engines._content import digest, is_traced

    global _last_checked
    # Read from the instance's fields directly: a Module's attribute lookup
    # costs several times more, and this runs on every call.
    f = vars(pm)
    arrays = (f["kills"], f["killer"], f["uncommon"])
    static = (f["max_kills"], f["min_kills"], f["common_kills"])
    # The mesh last checked, by the identity of its (immutable) arrays: the
    # hot path of a call repeated on one mesh.
    last = _last_checked
    if last is not None and last[1] == static and all(r() is a for r, a in zip(last[0], arrays)):
        return
    if any(is_traced(x) for x in arrays):
        return
    key = (*(digest(a) for a in arrays), *static)
    with _KILLS_LOCK:
        if key in _KILLS_CHECKED:
            _KILLS_CHECKED.move_to_end(key)
            _last_checked = _identity(arrays, static)
            return
    kills, killer, uncommon = (np.asarray(a) for a in arrays)
    counted = np.bincount(killer[killer >= 0], minlength=len(kills))
    if len(counted) != len(kills) or not np.array_equal(counted, kills):
        p = int(np.flatnonzero(counted[:len(kills)] != kills)[0]) if len(counted) == len(kills) else len(kills)
        raise ValueError(f"{call}: pm.kills is not the count of faces each pcol kills in pm.killer (pcol {p}); "
                         "update both together (and the summary, with pm.with_kills), or rebuild the mesh with "
                         "pmjax.ProgressiveMesh.from_data")
    want = kill_summary(kills, static[2])
    have = dict(uncommon=uncommon, max_kills=static[0], min_kills=static[1])
    if not all(np.array_equal(np.asarray(want[k]), v) for k, v in have.items()):
        raise ValueError(f"{call}: the mesh's kill summary (uncommon, max_kills, min_kills, common_kills) is not "
                         "that of pm.kills: update kills with pm.with_kills(kills), not eqx.tree_at")
    with _KILLS_LOCK:
        _KILLS_CHECKED[key] = True
        while len(_KILLS_CHECKED) > _KILLS_CHECKED_SIZE:
            _KILLS_CHECKED.popitem(last=False)
    _last_checked = _identity(arrays, static)


def _identity(arrays, static):
    """Weak references to a checked mesh's kill arrays (JAX arrays; a NumPy
    array, mutable, is never remembered by identity), and its statics."""
    if not all(isinstance(a, jax.Array) for a in arrays):
        return None
    return tuple(weakref.ref(a) for a in arrays), static
