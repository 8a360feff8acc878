"""The engines behind one seam: every public call under jax.jit and jax.vmap gives the eager bits, and
no derived table survives an update of the arrays it was derived from."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmjax
from pmjax import engines
from pmjax._camera import index_camera, stack_cameras

ENGINES = ["core", "jax", "dense"]


def method_of(engine):
    """``(method, context)`` that makes a call run ``engine``."""
    import contextlib

    if engine == "dense":
        return "dense", contextlib.nullcontext()
    if engine == "jax":
        return "front", engines.without_core()
    if not engines.core_built():
        pytest.skip("the C core is not built")
    return "front", contextlib.nullcontext()


@pytest.fixture(scope="module")
def cow(built):
    data = built("cow.ply")
    return data, pmjax.ProgressiveMesh.from_data(data)


def views(data, n, seed=0):
    v0 = data.vertices[: data.n_original_vertices]
    return pmjax.random_views(v0, n, seed=seed, min_scale=0.3, max_scale=4.0)


def test_select_decides_in_one_place(cow):
    data, pm = cow
    cam = index_camera(views(data, 1), 0)
    assert engines.select(pm, "dense") == "dense"
    assert engines.select(pm, "auto", predicate=lambda a, c: a.radius > 0) == "dense"
    if engines.core_enabled():
        assert engines.select(pm, "auto") == "core"
        assert engines.select(pm, "auto", traced=True) == "core"  # a closed-over mesh under jit
        assert engines.select(pm, "auto", batch=True) == "dense"  # a small hierarchy's batch
    with engines.without_core():
        assert engines.select(pm, "front") == "jax"
        assert engines.select(pm, "front", traced=True) == "dense"  # the JAX traversal adapts on the host
    # A mesh being traced has no contents to derive tables from.
    kinds = []
    jax.jit(lambda m: kinds.append(engines.select(m, "front")) or m.vertices.sum())(pm)
    assert kinds == ["dense"]
    with pytest.raises(ValueError, match="method must be"):
        engines.select(pm, "fastest")
    info = engines.info()
    assert pmjax.engine_info() == info
    assert set(info) == {"dense", "core", "jax"} and all(isinstance(v, str) for v in info.values())


@pytest.mark.core
@pytest.mark.slow
def test_refine_under_jit_and_vmap_gives_the_eager_bits(cow, simd):
    """refine with default arguments: eager, jit, vmap over cameras, jit of
    vmap, vmap over tolerances; counts and the executed set (from the lists),
    the front engine's (one batched call under vmap) as the dense engine's."""
    data, pm = cow
    cams = views(data, 12, seed=3)
    taus = jnp.asarray([0.0, 0.5, 1.0, 4.0] * 3, jnp.float32)
    eager = [pmjax.refine(pm, index_camera(cams, i), float(taus[i]), method="dense") for i in range(12)]
    faces = np.array([int(r.n_faces) for r in eager])
    executed = np.stack([np.asarray(r.executed) for r in eager])
    one = lambda c, t: pmjax.refine(pm, c, t)
    assert int(jax.jit(one)(index_camera(cams, 5), taus[5]).n_faces) == faces[5]
    for f in (jax.vmap(one), jax.jit(jax.vmap(one))):
        got = f(cams, taus)
        assert np.array_equal(np.asarray(got.n_faces), faces)
        assert np.array_equal(np.asarray(got.n_vertices), [int(r.n_vertices) for r in eager])
    got = jax.jit(jax.vmap(lambda c, t: one(c, t).executed))(cams, taus)
    assert np.array_equal(np.asarray(got), executed)
    # vmap over the tolerances of one camera, and nested vmaps.
    cam = index_camera(cams, 2)
    got = jax.vmap(lambda t: one(cam, t).n_faces)(taus)
    assert np.array_equal(np.asarray(got), [int(pmjax.refine(pm, cam, float(t), method="dense").n_faces)
                                            for t in taus])
    grid = jax.tree.map(lambda a: a.reshape((3, 4) + a.shape[1:]), cams)
    got = jax.vmap(jax.vmap(one))(grid, taus.reshape(3, 4))
    assert np.array_equal(np.asarray(got.n_faces).reshape(-1), faces)


@pytest.mark.parametrize("engine", ENGINES)
def test_mesh_under_jit_is_the_eager_mesh_padded(cow, engine):
    data, pm = cow
    method, context = method_of(engine)
    cam = index_camera(views(data, 2, seed=1), 1)
    want = pmjax.refine(pm, cam, 1.0, method="dense").mesh()
    with context:
        if engine == "jax":  # the JAX traversal runs eagerly only: under jit, the dense engine
            got = jax.jit(lambda c: pmjax.refine(pm, c, 1.0, method=method).mesh())(cam)
        else:
            got = jax.jit(lambda c: pmjax.refine(pm, c, 1.0, method=method).mesh())(cam)
    vertices, faces, ids = (np.asarray(x) for x in got)
    n, k = len(want[1]), len(want[2])
    assert faces.shape == (pm.n_faces, 3) and ids.shape == (pm.n_original_vertices,)
    assert np.array_equal(faces[:n], want[1]) and np.all(faces[n:] == -1)
    assert np.array_equal(ids[:k], want[2]) and np.all(ids[k:] == -1)
    assert np.array_equal(vertices[:k], want[0]) and np.all(vertices[k:] == 0)


@pytest.mark.core
@pytest.mark.slow
def test_batches_paths_and_budgets_under_jit_and_vmap(cow):
    data, pm = cow
    cams = views(data, 40, seed=5)
    want = pmjax.refine_batch(pm, cams, 1.0, method="dense", return_masks=True)
    got = jax.jit(lambda c: pmjax.refine_batch(pm, c, 1.0, method="front", return_masks=True))(cams)
    for key in want:
        assert np.array_equal(np.asarray(got[key]), want[key]), key
    # Paths: one path, K paths (paths=True), vmap over paths; the frames of refine_path.
    orbit = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 48)
    eager = pmjax.path_counts(pm, orbit, 1.0, coherent=False, method="dense")
    traced = jax.jit(lambda c: pmjax.path_counts(pm, c, 1.0))(orbit)
    assert all(np.array_equal(np.asarray(traced[k]), eager[k]) for k in ("faces", "vertices", "executed_count"))
    grid = jax.tree.map(lambda a: a.reshape((3, 16) + a.shape[1:]), orbit)
    batched = jax.vmap(lambda c: pmjax.path_counts(pm, c, 1.0)["faces"])(grid)
    assert np.array_equal(np.asarray(batched).reshape(-1), eager["faces"])
    paths = jax.jit(lambda c: pmjax.path_counts(pm, c, 1.0, paths=True)["faces"])(grid)
    assert np.array_equal(np.asarray(paths).reshape(-1), eager["faces"])
    frames = jax.jit(lambda c: jnp.stack([r.n_faces for r in pmjax.refine_path(pm, c, 1.0)]))(
        index_camera(orbit, slice(0, 8)))
    assert np.array_equal(np.asarray(frames), eager["faces"][:8])
    # Budgets: the search and the sort, eager, jit and vmap.
    cam = index_camera(cams, 3)
    budget = int(want["faces"][3])
    tau, faces = pmjax.faces_for_budget(pm, cam, budget, method="dense")
    for method in ("front", "dense"):
        t, f = jax.jit(lambda c, b: pmjax.faces_for_budget(pm, c, b, method=method))(cam, budget)
        assert np.float32(t).tobytes() == np.float32(tau).tobytes() and int(f) == faces, method
    budgets = jnp.asarray(want["faces"][:6])
    ts, fs = jax.vmap(lambda c, b: pmjax.faces_for_budget(pm, c, b, method="front"))(index_camera(cams, slice(0, 6)),
                                                                                       budgets)
    for i in range(6):
        t, f = pmjax.faces_for_budget(pm, index_camera(cams, i), int(budgets[i]), method="dense")
        assert np.float32(ts[i]).tobytes() == np.float32(t).tobytes() and int(fs[i]) == f, i
    # The critical tolerances and critical_tau compose too.
    eps = jax.vmap(lambda c: pmjax.critical_tolerances(pm, c))(index_camera(cams, slice(0, 3)))
    assert np.array_equal(np.asarray(eps[1]), np.asarray(pmjax.critical_tolerances(pm, index_camera(cams, 1))))
    ct = jax.jit(jax.vmap(lambda c: pmjax.critical_tau(pm.attributes, c)))(index_camera(cams, slice(0, 3)))
    assert np.array_equal(np.asarray(ct[2]), np.asarray(pmjax.critical_tau(pm.attributes, index_camera(cams, 2))))


def test_a_traced_mesh_is_refined_by_the_dense_engine(cow):
    """A mesh passed as an argument of a compiled function (differentiable
    in its attributes) is refined by the dense engine, with the same bits."""
    data, pm = cow
    cam = index_camera(views(data, 1, seed=8), 0)
    want = pmjax.refine(pm, cam, 1.0)
    got = jax.jit(lambda m, c: pmjax.refine(m, c, 1.0).n_faces)(pm, cam)
    assert int(got) == int(want.n_faces)


UPDATES = {
    "mu": lambda a: (a.mu, a.mu * 0),
    "delta": lambda a: (a.delta, a.delta * 4),
    "radius": lambda a: (a.radius, a.radius * 0.5),
    "center": lambda a: (a.center, a.center + 0.05),
    "axis": lambda a: (a.axis, -a.axis),
    "cone": lambda a: (a.sin_alpha, jnp.zeros_like(a.sin_alpha)),
    "cos": lambda a: (a.cos_alpha, jnp.ones_like(a.cos_alpha)),
}


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("field", sorted(UPDATES))
@pytest.mark.slow
def test_no_table_survives_an_update(cow, engine, field):
    """After an ``eqx.tree_at`` update of an attribute (or the positions),
    every engine gives the dense engine's bits for the updated mesh: no table
    derived from the old arrays is used (they are keyed by content)."""
    data, pm = cow
    method, context = method_of(engine)
    cams = views(data, 4, seed=2)
    with context:
        for i in range(4):  # the tables of the original mesh, made and cached
            pmjax.refine(pm, index_camera(cams, i), 1.0, method=method).mesh()
        old, new = UPDATES[field](pm.attributes)
        pm2 = eqx.tree_at(lambda m: getattr(m.attributes, {"cone": "sin_alpha", "cos": "cos_alpha"}.get(field, field)),
                          pm, new)
        if field == "center":  # the vertices move with the pcols' centres
            pm2 = eqx.tree_at(lambda m: m.vertices, pm2, pm2.vertices + 0.05)
        changed = 0
        for i in range(4):
            cam = index_camera(cams, i)
            for tau in (0.5, 2.0):
                got = pmjax.refine(pm2, cam, tau, method=method)
                want = pmjax.refine(pm2, cam, tau, method="dense")
                assert np.array_equal(np.asarray(got.executed), np.asarray(want.executed)), (i, tau)
                assert int(got.n_faces) == int(want.n_faces), (i, tau)
                assert all(np.array_equal(a, b) for a, b in zip(got.mesh(), want.mesh())), (i, tau)
                changed += int(want.n_faces) != int(pmjax.refine(pm, cam, tau, method="dense").n_faces)
        assert changed > 0  # the update matters
        if engine != "jax":
            batch = pmjax.refine_batch(pm2, cams, 1.0, method=method)
            assert np.array_equal(batch["faces"], pmjax.refine_batch(pm2, cams, 1.0, method="dense")["faces"])


def test_kill_counts_that_disagree_are_refused_by_every_engine(cow):
    """The face counts read ``kills`` and its static summary: an
    ``eqx.tree_at`` of ``kills`` alone (or a summary of other counts) is
    refused by every public call instead of counted differently by each
    engine; ``with_kills`` updates both."""
    import dataclasses

    data, pm = cow
    cam = index_camera(views(data, 1), 0)
    stale = eqx.tree_at(lambda m: m.kills, pm, jnp.ones_like(pm.kills))
    wrong_summary = dataclasses.replace(pm, max_kills=0, min_kills=0, common_kills=0)
    for mesh, message in ((stale, "pm.kills is not the count of faces each pcol kills in pm.killer"),
                          (wrong_summary, r"kill summary \(uncommon, max_kills, min_kills, common_kills\) is not")):
        for method in ("dense", "front"):
            with pytest.raises(ValueError, match=message):
                pmjax.refine(mesh, cam, 1.0, method=method)
        with pytest.raises(ValueError, match=message):
            pmjax.refine_batch(mesh, stack_cameras([cam, cam]), 1.0)
    same = pm.with_kills(np.asarray(pm.kills))
    for method in ("dense", "front"):
        assert int(pmjax.refine(same, cam, 1.0, method=method).n_faces) == int(pmjax.refine(pm, cam, 1.0).n_faces)


def test_remembered_digests_keep_no_array_alive():
    import gc
    import weakref

    from pmjax.engines import _content

    x = jnp.arange(1000.0)
    d = _content.digest(x)
    ref = weakref.ref(x)
    del x
    gc.collect()
    assert ref() is None
    assert _content.digest(jnp.arange(1000.0) + 1) != d  # a new array, whatever its identity


def test_tables_are_keyed_by_content(cow):
    """The same contents in new arrays find the same tables; a NumPy array
    updated in place (mutable) is digested again and finds new ones."""
    from pmjax.engines import _content
    from pmjax.engines._tables import derived

    data, pm = cow
    same = jax.tree.map(lambda x: jnp.array(x, copy=True) if isinstance(x, jax.Array) else x, pm)
    assert derived(same) is derived(pm)
    a = np.arange(10.0)
    key = _content.digest(a)
    a[3] = -1
    assert _content.digest(a) != key
    with pytest.raises(ValueError, match="traced"):
        jax.jit(lambda x: _content.digest(x))(jnp.ones(3))
