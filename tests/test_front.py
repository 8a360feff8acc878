"""The front engine as JAX kernels (pmjax/engines/_front_jax.py, used where
the C core is not built) against the dense engine and the oracle. The C core,
which ``method="front"`` runs where it is built, has the wider matrix of
tests/test_core.py."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmjax
from pmjax import engines
from pmjax.engines import _front_jax
from pmjax.engines._tables import derived
from pmjax._camera import index_camera, stack_cameras
from pmjax._oracle import oracle_refine

TAUS = (0.0, 1e-3, 1.0, 4.0, 1e6)


@pytest.fixture(scope="module", autouse=True)
def jax_traversal():
    """Every test here runs the front engine as JAX kernels. The kernels are
    large (one program per generation buffer set): they are released after
    this module, so that the executables compiled by one long test process
    stay within the memory maps the system allows (XLA otherwise fails with
    "Cannot allocate memory" in later modules)."""
    with engines.without_core():
        yield
    jax.clear_caches()


# Each hierarchy compiles its own traversal (6-10 s per buffer set): a mesh whose
# parts merge; the C loops' tests cover the other models.
CASES = [("cessna.ply", 0.02)]


def assert_same(front, dense, where):
    assert front.dense is None and dense.dense is not None
    for field in ("executed", "active", "rep"):
        assert np.array_equal(np.asarray(getattr(front, field)), np.asarray(getattr(dense, field))), (where, field)
    for field in ("n_faces", "n_vertices", "n_executed"):
        assert int(getattr(front, field)) == int(getattr(dense, field)), (where, field)


def views_of(data, n, seed):
    """Random views around and inside the model, plus two orthographic ones."""
    v0 = data.vertices[: data.n_original_vertices]
    return pmjax.random_views(v0, n, seed=seed, min_scale=0.05, max_scale=6.0)


@pytest.mark.parametrize("name, pair_distance", CASES)
@pytest.mark.slow
def test_front_equals_dense_and_oracle(built, name, pair_distance):
    data = built(name, pair_distance)
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = views_of(data, 6, seed=len(name))
    partial = 0
    for i in range(6):
        cam = index_camera(cams, i)
        for tau in TAUS:
            front = pmjax.refine(pm, cam, tau, method="front")
            dense = pmjax.refine(pm, cam, tau, method="dense")
            assert_same(front, dense, (i, tau))
            collapse = np.asarray(pmjax.collapse_mask(pm.attributes, cam, jnp.float32(tau)))
            want, _ = oracle_refine(data, collapse)
            assert np.array_equal(np.asarray(front.executed), want), (i, tau)
            partial += 0 < want.sum() < data.n_pcols
    assert partial >= 6


@pytest.mark.slow
def test_front_orthographic_and_tests_switched_off(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    v0 = data.vertices[: data.n_original_vertices]
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    orthos = [pmjax.look_at(c + d, c, orthographic=True, ortho_height=h, near=1e-3, far=10 * r)
              for d, h in (([0, 0, r], 0.5 * r), ([r, 0.3 * r, 0], 2 * r))]
    perspective = index_camera(views_of(data, 2, seed=4), 0)
    # Each set of tests and projection compiles its own traversal: all of them
    # orthographic, and the screen test off (the frustum and orientation bounds
    # alone) in perspective; the C loops' tests switch each off.
    for tests, cams in ((pmjax.ALL_TESTS, orthos), (pmjax.Tests(screen=False), [perspective])):
        for cam in cams:
            for tau in (0.0, 1.0, 8.0):
                front = pmjax.refine(pm, cam, tau, tests=tests, method="front")
                assert_same(front, pmjax.refine(pm, cam, tau, tests=tests, method="dense"), (tests, tau))


@pytest.mark.slow
def test_front_at_the_critical_tolerances(built):
    """At tau equal to a pcol's critical tolerance (the float tie of its own
    test) and one step above, the front engine decides as the dense one."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4), 1)
    t = np.asarray(pmjax.critical_tau(pm.attributes, cam))
    picks = np.random.default_rng(0).choice(np.flatnonzero(np.isfinite(t) & (t > 0.2) & (t < 5)), 4, replace=False)
    for p in picks:
        for tau in (t[p], np.nextafter(t[p], np.float32(np.inf))):
            assert_same(pmjax.refine(pm, cam, tau, method="front"), pmjax.refine(pm, cam, tau, method="dense"), tau)


@pytest.mark.slow
def test_capacity_overflow_still_exact(built):
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4), 0)
    kind = ("one", pmjax.ALL_TESTS, False)
    plan = _front_jax.plan_of(derived(pm))
    assert plan.capacities(kind) == plan.full  # before any call: the whole forest
    small = tuple(min(g, 16) for g in plan.full)
    plan._capacities[kind] = small
    front = pmjax.refine(pm, cam, 1.0, method="front")
    assert_same(front, pmjax.refine(pm, cam, 1.0, method="dense"), "overflow")
    grown = plan.capacities(kind)
    assert sum(grown) > sum(small) and all(g >= s for g, s in zip(grown, small))
    assert sum(grown) < sum(plan.full)
    # The grown buffers hold this view: the next call needs no redo.
    assert front.n_visited <= sum(grown)
    calls = []
    jt = derived(pm).jax
    plan.run(kind, lambda caps: calls.append(caps) or _front_jax.refine_chunk(pm, jt, cam, 1.0, pmjax.ALL_TESTS, caps))
    assert calls == [grown]


@pytest.mark.slow
def test_user_predicate_uses_the_dense_engine(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4), 0)
    pred = lambda attrs, ctx: attrs.position[:, 0] > ctx
    r = pmjax.refine(pm, cam, 1.0, predicate=pred, context=jnp.float32(0.0))
    assert r.dense is not None and r.n_visited == data.n_pcols
    with pytest.raises(ValueError, match="no subtree bound"):
        pmjax.refine(pm, cam, 1.0, predicate=pred, context=jnp.float32(0.0), method="front")
    with pytest.raises(ValueError, match="method must be"):
        pmjax.refine(pm, cam, 1.0, method="fast")


@pytest.mark.parametrize("name", ["cow.ply"])
def test_front_mesh_equals_dense_mesh(built, name):
    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = views_of(data, 6, seed=9)
    for i in range(6):
        cam = index_camera(cams, i)
        for tau in (0.0, 1.0, 16.0):
            got = pmjax.refine(pm, cam, tau, method="front").mesh()
            want = pmjax.refine(pm, cam, tau, method="dense").mesh(pm)
            for a, b in zip(got, want):
                assert a.dtype == b.dtype and np.array_equal(a, b), (i, tau)


@pytest.mark.slow
def test_refine_batch_front_equals_dense(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    v0 = data.vertices[: data.n_original_vertices]
    cams = stack_cameras([index_camera(views_of(data, 40, seed=2), i) for i in range(40)])
    for tau in (0.0, 4.0):
        front = pmjax.refine_batch(pm, cams, tau, chunk=32, return_masks=True, method="front")
        dense = pmjax.refine_batch(pm, cams, tau, chunk=32, return_masks=True, method="dense")
        for key in dense:
            assert np.array_equal(front[key], dense[key]), (tau, key)
    assert 0 < dense["executed"].sum() < dense["executed"].size
    order = pmjax._refine.nearby_order(np.asarray(pmjax.standard_orbit(v0, 64).eye))
    assert sorted(order.tolist()) == list(range(64))


def test_subtree_bounds_hold_over_every_subtree(built):
    """Brute force: each pcol's bounds hold for every pcol below it."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    a = pm.attributes
    unit = 2.0 ** -derived(pm).exponent  # the bounds are in model units
    c, n = unit * np.asarray(a.center, np.float64).T, np.asarray(a.axis, np.float64).T
    r, alpha = unit * np.asarray(a.radius, np.float64), np.asarray(a.alpha, np.float64)
    err = unit * np.maximum(np.asarray(a.mu, np.float64), np.asarray(a.delta, np.float64))
    b = {k: np.asarray(derived(pm).bounds[k], np.float64) for k in ("reach", "spread", "cone", "error")}
    kids = derived(pm).children
    for p in range(data.n_pcols):
        below, stack = [], [p]
        while stack:
            q = stack.pop()
            below.append(q)
            stack += [k for k in kids[q] if k >= 0]
        below = np.array(below)
        gap = np.linalg.norm(c[below] - c[p], axis=1)
        unit_n = n / np.linalg.norm(n, axis=1, keepdims=True)
        turn = np.arccos(np.clip(unit_n[below] @ unit_n[p], -1, 1))
        assert np.all(gap + r[below] <= b["reach"][p]) and np.all(gap <= b["spread"][p])
        assert np.all(err[below] <= b["error"][p])
        unit = np.abs(np.linalg.norm(n[below], axis=1) - 1) < 1e-3
        # Cones are capped at 4 rad: from π/2 on a cone never faces away.
        assert np.all(np.minimum(turn[unit] + alpha[below][unit], 4.0) <= b["cone"][p] + 1e-6)
