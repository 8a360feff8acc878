"""The front engine's C core (XLA FFI calls): certified decisions, exact refinements, batches and meshes.

Every test compares with the float32 predicate, the dense engine or the
JAX traversal; none checks the core against itself. Tests that take the
``simd`` fixture run with each SIMD level the processor has.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmjax
from pmjax import engines
from pmjax._camera import index_camera, stack_cameras
from pmjax._predicate import Tests
from pmjax._units import camera_in_model_units
from pmjax._view import View
from pmjax.engines import _core
from pmjax.engines._tables import derived

pytestmark = pytest.mark.core

TAUS = (0.0, 1e-3, 1.0, 4.0, 1e6)
# An FFI target's error: a ValueError where the call ran alone, a
# JaxRuntimeError from inside a compiled program.
CORE_ERRORS = (jax.errors.JaxRuntimeError, ValueError)


def views_of(data, n, seed):
    v0 = data.vertices[: data.n_original_vertices]
    return pmjax.random_views(v0, n, seed=seed, min_scale=0.05, max_scale=6.0)


def orthographic_views(data):
    v0 = data.vertices[: data.n_original_vertices]
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    return [pmjax.look_at(c + d, c, orthographic=True, ortho_height=h, near=1e-3, far=10 * r)
            for d, h in (([0, 0, r], 0.5 * r), ([r, 0.3 * r, 0], 2 * r))]


def assert_refinements_equal(a, b, where):
    for field in ("executed", "active", "rep"):
        assert np.array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field))), (where, field)
    for field in ("n_faces", "n_vertices", "n_executed"):
        assert int(getattr(a, field)) == int(getattr(b, field)), (where, field)


@functools.partial(jax.jit, static_argnames=("exponent",))
def _xla_view(cam, tau, exponent):
    return View.of(camera_in_model_units(cam, exponent), tau).values


def xla_view(cam, tau, exponent=0):
    """The view constants the dense engine computes, the camera in the model
    unit ``2^exponent`` (compiled once per exponent and projection)."""
    return np.asarray(_xla_view(cam, jnp.float32(tau), exponent=exponent))


def decide_every_pcol(pm, cam, tau, tests):
    """``uint8 [P]`` by pcol: the core's certified decision of every pcol
    (``NO``, ``YES``, ``UNSURE``) | ``WHOLE`` where the bound over its subtree
    decides everything below."""
    d = derived(pm)
    return np.asarray(_core.decide_all(d.jax.table, xla_view(cam, tau, d.exponent),
                                       _core.flags_of(tests, cam.orthographic)))


TESTS = (pmjax.ALL_TESTS, pmjax.Tests(frustum=False), pmjax.Tests(orientation=False), pmjax.Tests(screen=False))


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply", "terrain_gcanyon.ply"])
@pytest.mark.slow
def test_certified_decisions_equal_the_float32_predicate(built, name, simd):
    """Over every pcol: a decision the core is sure of is the float32
    predicate's bit, and a bound that says "whole" holds for every pcol
    below (each of them collapses). Unsure decisions are rare."""
    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    kids = derived(pm).children
    cams = [index_camera(views_of(data, 6, seed=3), i) for i in range(6)] + orthographic_views(data)
    checked = unsure = 0
    for cam in cams:
        for tests in TESTS:
            for tau in (0.0, 1.0, 4.0):
                got = decide_every_pcol(pm, cam, tau, tests)
                want = np.asarray(pmjax.collapse_mask(pm.attributes, cam, jnp.float32(tau), tests))
                own = got & 3
                sure = own != _core.UNSURE
                assert np.array_equal(own[sure] == _core.YES, want[sure]), (cam.orthographic, tests, tau)
                checked += int(sure.sum())
                unsure += int((~sure).sum())
                # "whole" at p: every pcol of p's subtree collapses (children
                # come from earlier batches, so one pass from the first batch
                # gives "the whole subtree collapses" per pcol).
                all_below = want.copy()
                for lo, hi in zip(pm.batch_offsets[:-1], pm.batch_offsets[1:]):
                    for k in (kids[lo:hi, 0], kids[lo:hi, 1]):
                        all_below[lo:hi] &= np.where(k >= 0, all_below[np.maximum(k, 0)], True)
                whole = (got & _core.WHOLE) != 0
                assert np.all(all_below[whole]), (cam.orthographic, tests, tau)
    assert checked > 0 and unsure <= 1e-4 * checked


@pytest.mark.parametrize("name, pair_distance", [("cow.ply", 0.0), ("bunny.ply", 0.0), ("cessna.ply", 0.02),
                                                 ("terrain_gcanyon.ply", 0.0)])
@pytest.mark.slow
def test_core_refine_equals_dense(built, name, pair_distance, simd):
    data = built(name, pair_distance)
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = [index_camera(views_of(data, 6, seed=len(name)), i) for i in range(6)] + orthographic_views(data)
    for i, cam in enumerate(cams):
        for tau in TAUS:
            core = pmjax.refine(pm, cam, tau, method="front")
            assert core.core_ran is not None  # the core ran
            assert_refinements_equal(core, pmjax.refine(pm, cam, tau, method="dense"), (i, tau))


@pytest.mark.slow
def test_unsure_decisions_are_asked_of_the_float32_predicate(built, simd):
    """At tau equal to pcols' critical tolerances the screen test is a float
    tie: the core must leave those pcols unsure, and the answer is still the
    dense engine's, one float step below, at and above the tie."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4), 1)
    t = np.asarray(pmjax.critical_tau(pm.attributes, cam))
    picks = np.random.default_rng(1).choice(np.flatnonzero(np.isfinite(t) & (t > 0.2) & (t < 5)), 8, replace=False)
    unsure = 0
    for p in picks:
        for tau in (np.nextafter(t[p], np.float32(0)), t[p], np.nextafter(t[p], np.float32(np.inf))):
            unsure += int(decide_every_pcol(pm, cam, tau, pmjax.ALL_TESTS)[p] & 3 == _core.UNSURE)
            assert_refinements_equal(pmjax.refine(pm, cam, tau, method="front"),
                                     pmjax.refine(pm, cam, tau, method="dense"), tau)
    assert unsure >= len(picks)  # at least the tie itself is never guessed


@pytest.mark.slow
def test_extreme_scales_fall_back_to_the_float32_predicate(built):
    """A model scaled to 1e-18 or 1e15 units (float32 products near the
    smallest normal, or huge): many decisions are unsure, and the
    refinement is still exact (eagerly and under jit)."""
    data = built("cow.ply")
    for scale in (1e-18, 1e15):
        scaled = dataclasses.replace(data, vertices=(data.vertices * scale).astype(np.float32),
                                     radius=(data.radius * scale).astype(np.float32),
                                     delta=(data.delta * scale).astype(np.float32),
                                     mu=(data.mu * scale).astype(np.float32))
        pm = pmjax.ProgressiveMesh.from_data(scaled)
        v0 = scaled.vertices[: scaled.n_original_vertices].astype(np.float64)
        compiled = jax.jit(lambda c, t: pmjax.refine(pm, c, t, method="front").n_faces)
        for i in range(3):
            cam = index_camera(pmjax.random_views(v0, 3, seed=i, min_scale=0.5, max_scale=3.0), i)
            for tau in (0.0, 1.0, 8.0):
                want = pmjax.refine(pm, cam, tau, method="dense")
                assert_refinements_equal(pmjax.refine(pm, cam, tau, method="front"), want, (scale, tau))
                assert int(compiled(cam, jnp.float32(tau))) == int(want.n_faces), (scale, tau)


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply", "cessna.ply", "terrain_gcanyon.ply"])
@pytest.mark.slow
def test_core_mesh_equals_dense_mesh(built, name):
    data = built(name, 0.02 if name == "cessna.ply" else 0.0)
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = [index_camera(views_of(data, 5, seed=9), i) for i in range(5)] + orthographic_views(data)
    for i, cam in enumerate(cams):
        for tau in (0.0, 1.0, 16.0, np.inf):
            got = pmjax.refine(pm, cam, tau, method="front").mesh()
            want = pmjax.refine(pm, cam, tau, method="dense").mesh(pm)
            for a, b in zip(got, want):
                assert a.dtype == b.dtype and np.array_equal(a, b), (i, tau)


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply"])
def test_tables_hold_no_subnormal_floats(built, name):
    """The bounds of pcols with nothing below (or one centre) are exact zeros,
    not zero rounded up to the smallest subnormal float (a microcode assist in
    every vector operation that reads one); the other bounds are still
    rounded up."""
    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    d = derived(pm)
    for table in (d.jax.table, d.core.rows, d.core_words.rows):
        values = np.abs(np.asarray(table)[:, :-1].astype(np.float64))  # the core's last column holds integers
        assert not np.any((values > 0) & (values < np.finfo(np.float32).tiny))
    spread = d.bounds["spread"]
    assert spread.dtype == np.float32 and np.any(spread == 0) and np.all(spread >= 0)
    leaves = (d.children < 0).all(axis=1)
    assert np.all(spread[leaves] == 0)
    # A positive bound, however small, is still rounded up.
    from pmjax._subtree import _rounded_up

    up = _rounded_up(np.array([0.0, 1e-300, 1.0]))
    assert up.dtype == np.float32 and up[0] == 0 and up[1] > 0 and up[2] > 1


def test_tables_start_on_cache_lines_and_link_the_forest(built):
    """Every row the core reads is one 64-byte cache line, the rows hold the
    mesh's values in breadth-first order, and their last column links each
    row to its children (the core checks the links: a forest laid out
    breadth first)."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    d = derived(pm)
    table, core = np.asarray(d.jax.table), d.core
    rows, order = np.asarray(core.rows), np.asarray(core.order)
    assert core.rows.unsafe_buffer_pointer() % 64 == 0 and rows.shape[1] * rows.itemsize == 64
    assert np.array_equal(np.asarray(d.core_words.rows)[:, :-1], table[order, :-1])
    assert np.array_equal(rows[:, :11], table[order, :11])  # the attributes; the bounds are those below
    # The last column: the first child's position, the number of children and
    # (sign bit) whether the pcol kills other than two faces.
    kids = rows[:, -1].view(np.uint32).astype(np.int64)
    children = d.children[order]
    count = (children >= 0).sum(1)
    assert np.array_equal(kids & 3, count)
    at = np.empty(pm.n_pcols, np.int64)
    at[order] = np.arange(pm.n_pcols)
    has = count > 0
    first = np.where(children[:, 0] >= 0, children[:, 0], children[:, 1])  # the first created child
    assert np.array_equal((kids[has] >> 2) & (2**29 - 1), at[first[has]])
    assert np.array_equal(kids >> 31, np.asarray(pm.kills)[order] != 2)
    _core.check_hierarchy(core)
    bad = dataclasses.replace(core, rows=core.rows.at[0, -1].set(jnp.float32(np.uint32(5 << 2 | 2).view(np.float32))))
    with pytest.raises(CORE_ERRORS, match="not a forest"):
        _core.check_hierarchy(bad)


@pytest.mark.slow
def test_core_batch_equals_dense(built, simd):
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = stack_cameras([index_camera(views_of(data, 70, seed=2), i) for i in range(70)])
    for tau in (0.0, 1.0, 4.0):
        core = pmjax.refine_batch(pm, cams, tau, chunk=64, return_masks=True, method="front")
        dense = pmjax.refine_batch(pm, cams, tau, chunk=64, return_masks=True, method="dense")
        for key in dense:
            assert np.array_equal(core[key], dense[key]), (tau, key)
    rows = _core.camera_rows(cams, jnp.ones(70, jnp.float32), derived(pm).exponent)
    counts = [np.asarray(_core.many_cameras(pmjax.ALL_TESTS, False, True, True, threads)(derived(pm).core, rows)[0])
              for threads in (1, 2, 3)]
    assert all(np.array_equal(counts[0], c) for c in counts[1:])


def test_subnormals_come_back_after_the_core(built):
    """The core reads and writes subnormal floats as zero while it decides
    (the thread's floating-point mode), and gives the caller's mode back."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    views = views_of(data, 4, seed=4)
    tiny = np.array([2.0 ** -126], np.float32)
    calls = [lambda: pmjax.refine(pm, index_camera(views, 0), 1.0, method="front"),
             lambda: pmjax.refine_batch(pm, views, 1.0, method="front"),
             lambda: decide_every_pcol(pm, index_camera(views, 1), 1.0, pmjax.ALL_TESTS),
             lambda: pmjax.path_counts(pm, views, 1.0)]
    for i, call in enumerate(calls):
        call()
        # Compared as bits: with subnormals as zero, 0 == 2^-128 holds too.
        assert (tiny * np.float32(0.25)).view(np.int32)[0] == 1 << 21, i  # 2^-128


def test_core_batches_from_several_threads_at_once(built):
    """Batches started together from user threads share XLA's thread pool (a
    helper that starts after its batch is done does nothing) and each gets
    its own cameras' results."""
    import concurrent.futures

    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    views = views_of(data, 48, seed=9)
    batches = [stack_cameras([index_camera(views, i) for i in range(j, 48, 4)]) for j in range(4)]
    alone = [pmjax.refine_batch(pm, b, 1.0, return_masks=True, method="front") for b in batches]
    with concurrent.futures.ThreadPoolExecutor(4) as users:
        together = list(users.map(lambda b: pmjax.refine_batch(pm, b, 1.0, return_masks=True, method="front"),
                                  batches * 3))
    for i, got in enumerate(together):
        assert all(np.array_equal(alone[i % 4][k], got[k]) for k in got), i


@pytest.mark.slow
def test_dragon_front_visits_a_small_share(built):
    """Structural: on the dragon at tau = 1 the front engine visits a few
    percent of the pcols (about twice those not executed), with the dense
    engine's results."""
    data = built("dragon.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 3)
    for i in range(3):
        cam = index_camera(cams, i)
        front = pmjax.refine(pm, cam, 1.0)  # "auto" is the front engine here
        assert front.dense is None
        if i == 0:
            assert_refinements_equal(front, pmjax.refine(pm, cam, 1.0, method="dense"), "dragon")
        not_run = data.n_pcols - int(front.n_executed)
        assert front.n_visited < 0.08 * data.n_pcols
        assert not_run < front.n_visited < 4 * not_run


def fat_words(data):
    """Words of frames for the fat camera: stretches of the standard orbit,
    a random walk with a jump inside the word, a flight through the model's
    bounding sphere, and unrelated random views (a fat camera that decides
    little)."""
    v0 = data.vertices[: data.n_original_vertices]
    c, r = v0.mean(0), 0.5 * np.linalg.norm(np.ptp(v0, 0))
    orbit = pmjax.standard_orbit(v0, 240)
    words = {f"orbit {s}": jax.tree.map(lambda a: np.asarray(a)[s:s + 16], orbit) for s in (0, 96)}
    rng = np.random.default_rng(7)
    eyes = c + 2.5 * r * np.array([0.3, 0.4, 1.0]) + np.cumsum(0.03 * r * rng.normal(size=(16, 3)), 0)
    eyes[9:] += 1.5 * r * np.array([1.0, -0.5, 0.2])  # a cut
    words["walk with a cut"] = stack_cameras([pmjax.look_at(e, c + 0.1 * r * rng.normal(size=3)) for e in eyes])
    line = c + r * np.linspace(2.0, -2.0, 16)[:, None] * np.array([0.2, 0.1, 1.0])
    words["through the model"] = stack_cameras([pmjax.look_at(e, e - np.array([0.2, 0.1, 1.0]), near=1e-3 * r,
                                                               far=20 * r) for e in line])
    words["random views"] = views_of(data, 16, seed=11)
    return words


def core_views(word, taus, exponent=0):
    """The view constants the core computes for a word's frames, in the
    model unit ``2^exponent``."""
    return _core.views(_core.camera_rows(word, taus, exponent), word.orthographic)


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply", "terrain_gcanyon.ply"])
def test_fat_camera_decisions_hold_for_every_frame(built, name):
    """Over every pcol, for words of frames: where the fat camera says
    "whole", every frame's subtree collapses under the float32 predicate;
    where it says "no", no frame's predicate collapses the pcol; where it
    says "yes", every frame's does (and its screen bound does not hold); where it
    settles tests ("inside": the frustum test, "screen": the frustum and
    orientation tests), no frame's predicate with only those tests on
    collapses the pcol, nor does their subtree bound hold for any frame.
    Along an orbit it decides most pcols and settles tests of others; with a
    tolerance of 0 (not a usual view) it decides none, nor does a fat camera
    that is not finite."""
    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    kids, table = derived(pm).children, derived(pm).jax.table
    for label, word in fat_words(data).items():
        for tau in (1e-3, 1.0, 4.0, 0.0):
            taus = np.full(16, tau, np.float32)
            views = core_views(word, taus, derived(pm).exponent)
            fat = _core.fat_cameras(views[None])[0]
            got = np.asarray(_core.decide_fat_all(table, views, fat, _core.flags_of(pmjax.ALL_TESTS, False)))
            if tau == 0.0:
                assert not np.any(got), label
                continue
            for f in range(16):
                cam = index_camera(word, f)
                want = np.asarray(pmjax.collapse_mask(pm.attributes, cam, jnp.float32(tau), pmjax.ALL_TESTS))
                assert not np.any(want[got == _core.FAT_NO]), (label, tau, f)
                # "yes": every frame's predicate collapses the pcol, its screen
                # test's certified decision is not "no", and that test's
                # subtree bound does not hold (the frames take the pcol as
                # collapsing, its children visited).
                assert np.all(want[got == _core.FAT_YES]), (label, tau, f)
                screen = decide_every_pcol(pm, cam, tau, Tests(frustum=False, orientation=False))
                assert not np.any((screen[got == _core.FAT_YES] & 3) == _core.NO), (label, tau, f)
                assert not np.any(screen[got == _core.FAT_YES] & _core.WHOLE), (label, tau, f)
                for tests, settled in ((Tests(orientation=False, screen=False),
                                        (_core.FAT_INSIDE, _core.FAT_SCREEN, _core.FAT_YES)),
                                       (Tests(frustum=False, screen=False), (_core.FAT_SCREEN, _core.FAT_YES))):
                    by = np.asarray(pmjax.collapse_mask(pm.attributes, cam, jnp.float32(tau), tests))
                    assert not np.any(by[np.isin(got, settled)]), (label, tau, f, tests)
                    # Nor do those tests' subtree bounds hold there (the frames leave them out).
                    code = decide_every_pcol(pm, cam, tau, tests)
                    assert not np.any(code[np.isin(got, settled)] & _core.WHOLE), (label, tau, f, tests)
                # Every pcol of the subtree collapses: batch by batch (children
                # come from earlier batches).
                all_below = want.copy()
                for lo, hi in zip(pm.batch_offsets[:-1], pm.batch_offsets[1:]):
                    for k in kids[lo:hi].T:
                        has = k >= 0
                        all_below[lo:hi][has] &= all_below[k[has]]
                assert np.all(all_below[got == _core.FAT_WHOLE]), (label, tau, f)
            if label.startswith("orbit") and tau == 1.0:
                assert np.mean(got == 1) > 0.3 and np.any(got == 2), (label, np.bincount(got, minlength=6))
                # Both settled codes and "yes" occur, so every way of leaving
                # tests out is exercised (on the terrain, whose surface faces the orbit's
                # eyes, the orientation test is settled wherever the frustum is).
                counts = np.bincount(got, minlength=6)
                assert counts[_core.FAT_SCREEN] > 0 and counts[_core.FAT_YES] > 0, (label, counts)
                assert counts[_core.FAT_INSIDE] > 0 or name.startswith("terrain"), (label, counts)
                if name == "bunny.ply":
                    # The chord's range of v . n settles the orientation test
                    # on most pcols near the silhouette: fewer are left open
                    # on it than have it settled and the screen test open.
                    assert counts[_core.FAT_INSIDE] < counts[_core.FAT_SCREEN] + counts[_core.FAT_YES], (label, counts)
                nan = jnp.full(_core.FAT, jnp.nan, jnp.float32)
                unused = _core.decide_fat_all(table, views, nan, _core.flags_of(pmjax.ALL_TESTS, False))
                assert not np.any(np.asarray(unused)), label


def test_fat_camera_bounds_hold(built):
    """The fat camera's bounds (recomputed here in float64) hold for every
    frame of a word: eyes within rho of the centre and within the capsule of
    the chord, rotations within eps, the pivot's camera coordinates within
    tau."""
    data = built("cow.ply")
    for label, word in fat_words(data).items():
        views = np.asarray(core_views(word, np.ones(16, np.float32)))
        fat = np.asarray(_core.fat_cameras(views[None])[0]).astype(np.float64)
        eyes, rot = views[:, 0:3].astype(np.float64), views[:, 3:12].astype(np.float64).reshape(-1, 3, 3)
        eye, rho, pivot, ref, t, eps, tau = fat[0:3], fat[3], fat[4:7], fat[7:16].reshape(3, 3), fat[16:19], \
            fat[19], fat[20]
        start, step, capsule = fat[21:24], fat[24:27], fat[28]
        assert np.all(np.linalg.norm(eyes - eye, axis=1) <= rho), label
        assert np.all(np.linalg.svd(rot - ref, compute_uv=False)[:, 0] <= eps), label
        assert np.all(np.linalg.norm(np.einsum("fij,fj->fi", rot, pivot - eyes) - t, axis=1) <= tau), label
        along = np.clip((eyes - start) @ step / max(step @ step, 1e-300), 0, 1)
        assert np.all(np.linalg.norm(eyes - start - along[:, None] * step, axis=1) <= capsule), label
        assert rho < 10 * max(np.linalg.norm(eyes - eye, axis=1).max(), 1e-30), label  # bounds, not infinities


@pytest.mark.parametrize("orthographic", [False, True])
def test_core_view_constants_are_within_the_allowance(orthographic):
    """The core computes each view's constants from the camera (in double,
    rounded once); the certification allows them 2^-20 relative from XLA's
    (VIEW in certify.h). They must stay well inside it."""
    v0 = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    cams = pmjax.random_views(v0, 400, seed=1, min_scale=0.05, max_scale=6.0)
    if orthographic:
        cams = pmjax.Camera(cams.eye, cams.rotation, cams.fov_y, cams.near, cams.far, cams.ortho_height, cams.width,
                            cams.height, orthographic=True)
    for tau in (0.0, 1e-3, 1.0, 4.0, 1e6):
        core = np.asarray(_core.views(_core.camera_rows(cams, jnp.full(400, tau, jnp.float32), 0), orthographic))
        xla = np.asarray(View.batch(cams, jnp.float32(tau)).values).T
        rel = np.abs(core.astype(np.float64) - xla) / np.maximum(np.abs(xla.astype(np.float64)),
                                                                 np.finfo(np.float32).tiny)
        assert np.all(rel <= 2.0 ** -21), (tau, np.log2(rel.max()))


@pytest.mark.parametrize("room", [None, 4])
@pytest.mark.slow
def test_batch_at_a_float_tie_asks_the_predicate_once_per_batch(built, room, simd):
    """A batch refined at a pcol's critical tolerance has unsure decisions in
    many cameras; they are answered for the whole batch and the cameras'
    counts and masks corrected from their records: the same bits as the
    dense engine; also with room for 4 int32 of records (less than one),
    when each such camera is refined alone."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    orbit = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4)
    cam = index_camera(orbit, 1)
    t = np.asarray(pmjax.critical_tau(pm.attributes, cam))
    p = np.flatnonzero(np.isfinite(t) & (t > 0.5) & (t < 4))[0]
    cams = stack_cameras([cam] * 40 + [index_camera(orbit, i) for i in range(4)])
    assert decide_every_pcol(pm, cam, t[p], pmjax.ALL_TESTS)[p] & 3 == _core.UNSURE
    assert p in np.asarray(pmjax.refine(pm, cam, t[p], method="front").visited)  # so 40 cameras have a record
    dense = pmjax.refine_batch(pm, cams, t[p], chunk=64, return_masks=True, method="dense")
    rows = _core.camera_rows(cams, jnp.full(44, t[p], jnp.float32), derived(pm).exponent)
    counts, masks, (pcols, ran, positions) = _core.many_cameras(pmjax.ALL_TESTS, False, True, True, 0, room)(
        derived(pm).core, rows)
    counts = np.asarray(counts)
    assert np.array_equal(np.asarray(masks).view(bool), dense["executed"])
    P = pm.n_pcols
    assert np.array_equal(P - counts[:, 1], dense["executed_count"])
    for k in (0, 41):  # each camera's lists: the dense engine's executed set
        n = counts[k, 0]
        executed = np.ones(P, bool)
        executed[np.asarray(pcols)[k, :n]] = np.asarray(ran)[k, :n].astype(bool)
        assert np.array_equal(executed, dense["executed"][k]), k
    if room is None:
        got = pmjax.refine_batch(pm, cams, t[p], chunk=64, return_masks=True, method="front")
        for key in dense:
            assert np.array_equal(got[key], dense[key]), key


def test_refinement_is_a_pytree_of_its_arrays(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(views_of(data, 2, seed=5), 0)
    r = pmjax.refine(pm, cam, 1.0, method="front")
    copy = jax.tree.map(lambda x: x, r)
    assert isinstance(copy, pmjax.Refinement) and copy is not r
    assert np.array_equal(copy.visited, r.visited) and int(copy.n_faces) == int(r.n_faces)
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.n_faces = 0


def test_an_eager_refinement_holds_what_it_visited(built):
    """An eager refinement's lists are arrays of their own of exactly the
    slots it used (the call's P + 16 buffers shrunk in place, not views of
    them), and its mesh is read from them."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(views_of(data, 2, seed=5), 0)
    r = pmjax.refine(pm, cam, 1.0, method="front")
    n = int(r.n_slots)
    assert 0 < n < pm.n_pcols // 2 and r.visited.shape == (n,) and r.visited.base is None
    for held in (r.front_positions, r.core_ran):
        assert isinstance(held, np.ndarray) and held.shape == (n,) and held.base is None
    want = pmjax.refine(pm, cam, 1.0, method="dense").mesh(pm)
    for a, b in zip(r.mesh(), want):
        assert np.array_equal(a, b)


def test_meshes_of_fine_and_coarse_views_in_turn_equal_the_dense_mesh(built, simd):
    """A mesh's bitmaps are counted and cleared over only the words a call
    set where few are: a fine mesh (most of the model), a coarse one (a few
    dozen faces beyond the base mesh's) and the base mesh, in turn on one
    model with the same working memory, each equal to the dense engine's, so
    that a bit one call left would show in the next."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    orbit = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4)
    cams = [index_camera(orbit, i) for i in range(4)]
    taus = (0.0, 100.0, 1e9, 1.0)
    wants = {(i, tau): pmjax.refine(pm, cam, tau, method="dense").mesh(pm) for i, cam in enumerate(cams)
             for tau in taus}
    for i in range(len(cams)):
        fine, coarse, base = (len(wants[i, tau][1]) for tau in taus[:3])
        assert fine > len(data.faces) // 2 and base < coarse < len(data.faces) // 1000
    for _ in range(2):
        for i, cam in enumerate(cams):
            for tau in taus:
                got = pmjax.refine(pm, cam, tau, method="front").mesh()
                for a, b in zip(got, wants[i, tau]):
                    assert a.dtype == b.dtype and np.array_equal(a, b), (i, tau)


@pytest.fixture(params=["bitmaps", "sorts", "rule"])
def mesh_ranks(request):
    """Each test that takes it runs with every way the core's mesh takes its
    ranks (a bitmap each, a sort of faces and vertex ids, the ratio's
    choice): the same mesh from each."""
    was = engines.mesh_ranks(request.param)
    assert engines.mesh_ranks() == request.param
    yield request.param
    engines.mesh_ranks(was)


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply"])
def test_meshes_ranked_each_way_equal_the_dense_mesh(built, name, mesh_ranks):
    """Frames of an orbit and random views, fine to coarse, the base mesh, a
    view that sees nothing and the full original, eagerly and under jit
    (padded rows), in turn with the same working memory: each equal to the
    dense engine's mesh whether faces and vertex ids are ranked in bitmaps or
    by sorting them. The sorts take byte-wide digits below 4,096 items and
    wider ones above: the cow's 13-bit face ids in one pass or two, the
    bunny's 17-bit face and vertex ids in two or three."""
    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    v0 = data.vertices[: data.n_original_vertices]
    orbit = pmjax.standard_orbit(v0, 3)
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    away = pmjax.look_at(c + [0, 0, 3 * r], c + [0, 0, 6 * r])
    cams = [index_camera(orbit, i) for i in range(3)] + [index_camera(views_of(data, 2, seed=4), i)
                                                         for i in range(2)] + [away]
    everything = Tests(frustum=False, orientation=False, screen=True)
    cases = [(i, tau, True) for i in range(len(cams)) for tau in (0.0, 1.0, 16.0, 1e9)] + [(0, 0.0, False)]
    meshed = jax.jit(lambda cam, tau: pmjax.refine(pm, cam, tau, method="front").mesh())
    sizes = set()
    for i, tau, all_tests in cases:
        tests = pmjax.ALL_TESTS if all_tests else everything
        want = pmjax.refine(pm, cams[i], tau, tests=tests, method="dense").mesh(pm)
        got = pmjax.refine(pm, cams[i], tau, tests=tests, method="front").mesh()
        for a, b in zip(got, want):
            assert a.dtype == b.dtype and np.array_equal(a, b), (i, tau, all_tests)
        if all_tests:
            padded = [np.asarray(a) for a in meshed(cams[i], jnp.float32(tau))]
            n, m = len(want[0]), len(want[1])
            assert np.array_equal(padded[0][:n], want[0]) and np.array_equal(padded[1][:m], want[1])
            assert np.array_equal(padded[2][:n], want[2]) and (padded[1][m:] == -1).all()
        sizes.add(len(want[1]))
    assert len(want[1]) == len(data.faces)  # the full original
    assert min(sizes) < len(data.faces) // 100 and len(sizes) > 4
    assert min(sizes) < 4096 <= max(sizes)  # both digit widths of the sorts


def test_mesh_ranks_names_its_ways():
    was = engines.mesh_ranks()
    with pytest.raises(ValueError, match="mesh ranks must be one of"):
        engines.mesh_ranks("radix")
    assert engines.mesh_ranks() == was


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply"])
@pytest.mark.slow
def test_budget_by_search_equals_the_sort(built, name):
    """faces_for_budget from the core's counts (a search over the float32
    patterns of tau, one compiled loop) gives the dense sort's tau and face
    count, bit for bit, at budgets across the whole range and at its ends."""
    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = [index_camera(views_of(data, 3, seed=11), i) for i in range(3)] + orthographic_views(data)[:1]
    for cam in cams:
        finest = int(pmjax.refine(pm, cam, 0.0, method="dense").n_faces)
        coarsest = int(pmjax.refine(pm, cam, np.inf, method="dense").n_faces)
        budgets = sorted({0, coarsest - 1, coarsest, finest, finest + 5,
                          *np.linspace(coarsest, finest, 7).astype(int).tolist()})
        for budget in budgets:
            want = pmjax.faces_for_budget(pm, cam, budget, method="dense")
            got = pmjax.faces_for_budget(pm, cam, budget, method="front")
            assert got[1] == want[1] and np.float32(got[0]).tobytes() == np.float32(want[0]).tobytes(), budget
            assert int(pmjax.refine(pm, cam, got[0], method="dense").n_faces) == got[1]


def test_bad_buffers_are_errors_that_name_the_argument(built):
    """The core's FFI targets check every buffer against the hierarchy it
    claims to come from: a wrong shape, dtype or capacity, or tables of two
    meshes, is an exception naming the argument, not a write past a buffer."""
    cow = pmjax.ProgressiveMesh.from_data(built("cow.ply"))
    bunny = pmjax.ProgressiveMesh.from_data(built("bunny.ply"))
    tables = derived(cow).core
    cam = index_camera(views_of(built("cow.ply"), 2, seed=1), 0)
    row = _core.camera_rows(cam, jnp.float32(1.0), tables.exponent)
    P = tables.n_pcols
    S = jax.ShapeDtypeStruct
    one = lambda rows, kills, order, camera, results=None: _core._call(
        "pmx_refine_one", results or (S((0,), jnp.int32), S((0,), jnp.uint8), S((0,), jnp.int32),
                                      S((P + 16,), jnp.int32), S((P + 16,), jnp.int32), S((5,), jnp.int32)),
        rows, kills, order, camera, flags=np.int32(7), n_roots=np.int64(tables.n_roots))
    cases = {
        "kills": lambda: one(tables.rows, derived(bunny).core.kills, tables.order, row),  # another mesh's
        "rows": lambda: one(tables.rows[:, :8], tables.kills, tables.order, row),
        "camera": lambda: one(tables.rows, tables.kills, tables.order, row[:10]),
        "unsure": lambda: one(tables.rows, tables.kills, tables.order, row,
                              (S((0,), jnp.int32), S((0,), jnp.uint8), S((0,), jnp.int32), S((16,), jnp.int32),
                               S((P + 16,), jnp.int32), S((5,), jnp.int32))),
        "pcols": lambda: one(tables.rows, tables.kills, tables.order, row,
                             (S((P,), jnp.int32), S((0,), jnp.uint8), S((0,), jnp.int32), S((P + 16,), jnp.int32),
                              S((P + 16,), jnp.int32), S((5,), jnp.int32))),
    }
    for name, call in cases.items():
        with pytest.raises(CORE_ERRORS, match=name):
            jax.block_until_ready(call())
    with pytest.raises(Exception, match="F32|float32|dtype|type"):  # a typed buffer
        jax.block_until_ready(one(tables.rows.astype(jnp.float16), tables.kills, tables.order, row))
    # A refinement's mesh asked of another mesh's tables.
    r = pmjax.refine(cow, cam, 1.0, method="front")
    with pytest.raises(CORE_ERRORS):
        jax.block_until_ready(_core.front_mesh(derived(bunny).core_mesh, r.core_ran, r.front_positions,
                                               jnp.asarray(r.core_counts).at[2].set(10 ** 6)))
    # Mesh buffers too small for the refinement's faces, or for the vertices it uses.
    n_faces, n_vertices = int(r.n_faces), int(r.n_vertices)
    mesh_tables = derived(cow).core_mesh
    with pytest.raises(CORE_ERRORS, match="faces do not fit"):
        jax.block_until_ready(_core.front_mesh(mesh_tables, r.core_ran, r.front_positions, r.core_counts, 0,
                                               n_faces - 1, n_vertices))
    with pytest.raises(CORE_ERRORS, match="size|capacity"):
        jax.block_until_ready(_core.front_mesh(mesh_tables, r.core_ran, r.front_positions, r.core_counts, 0,
                                               n_faces, 3))
    # Buffers that fit exactly hold the whole-capacity call's mesh.
    exact = _core.front_mesh(mesh_tables, r.core_ran, r.front_positions, r.core_counts, 0, n_faces, n_vertices)
    whole = _core.front_mesh(mesh_tables, r.core_ran, r.front_positions, r.core_counts)
    k = int(whole[3])
    assert int(exact[3]) == k and np.array_equal(exact[0], whole[0][:n_faces])
    assert np.array_equal(exact[1][:k], whole[1][:k]) and np.array_equal(exact[2][:k], whole[2][:k])


def test_the_eager_entry_checks_every_array(built):
    """The eager entry (``_pmx.refine_one``) reads NumPy arrays with the FFI
    targets' checks: a wrong dtype, shape, layout or capacity, a read-only
    output, another mesh's tables or answers out of order is a ValueError
    naming the argument; a good call gives the FFI target's lists and counts."""
    cow = pmjax.ProgressiveMesh.from_data(built("cow.ply"))
    bunny = pmjax.ProgressiveMesh.from_data(built("bunny.ply"))
    tables = derived(cow).core
    host = tuple(np.asarray(a) for a in (tables.rows, tables.kills, tables.order))
    cam = index_camera(views_of(built("cow.ply"), 2, seed=1), 0)
    row = _core.eager_camera_row(cam, 1.0, tables.exponent)
    L = tables.n_pcols + 16

    def outputs():
        return dict(pcols=np.empty(L, np.int32), ran=np.empty(L, np.uint8), positions=np.empty(L, np.int32),
                    counts=np.empty(5, np.int32), unsure=np.empty(L, np.int32))

    def call(rows=host[0], kills=host[1], order=host[2], camera=row, **changed):
        out = outputs() | changed
        _core._pmx.refine_one(rows, kills, order, camera, 7, tables.n_roots, **out)
        return out

    read_only = np.empty(L, np.int32)
    read_only.flags.writeable = False
    cases = {
        "rows": dict(rows=host[0].astype(np.float64)),
        "rows ": dict(rows=np.asfortranarray(host[0])),
        "rows  ": dict(rows=host[0][:, :8].copy()),
        "kills": dict(kills=np.asarray(derived(bunny).core.kills)),
        "camera": dict(camera=row[:10].copy()),
        "pcols": dict(pcols=np.empty(L - 1, np.int32)),
        "pcols ": dict(pcols=read_only),
        "ran": dict(ran=np.empty(L, np.int32)),
        "counts": dict(counts=np.empty(4, np.int32)),
        "unsure": dict(unsure=np.empty(16, np.int32)),
        "answered and answers": dict(answered=np.arange(3, dtype=np.int32)),
        "answered": dict(answered=np.array([2, 1], np.int32), answers=np.zeros(2, np.int32)),
        "answered ": dict(answered=np.array([L], np.int32), answers=np.zeros(1, np.int32)),
        "answers": dict(answered=np.array([1, 2], np.int32), answers=np.zeros(3, np.int32)),
        "level": dict(level=7),
    }
    for name, change in cases.items():
        with pytest.raises(ValueError, match=name.strip()):
            call(**change)
    # A good call: the FFI target's lists and counts, bit for bit.
    got = call()
    first = _core.refine_one_first(tables, jnp.asarray(row), pmjax.Tests(), False, True)
    n = int(got["counts"][0])
    assert np.array_equal(got["counts"], np.asarray(first[5])) and n > 0
    for k, name in enumerate(("pcols", "ran", "positions")):
        assert np.array_equal(got[name][:n], np.asarray(first[k])[:n]), name


def test_the_eager_mesh_entry_checks_its_arrays(built):
    """The eager mesh entry (``_pmx.front_mesh``) has the FFI target's checks
    (outputs too small for the refinement, lists of another shape, wrong
    dtypes are ValueErrors naming what is wrong, nothing written past a
    buffer) and gives the FFI target's mesh."""
    cow = pmjax.ProgressiveMesh.from_data(built("cow.ply"))
    cam = index_camera(views_of(built("cow.ply"), 2, seed=1), 0)
    r = pmjax.refine(cow, cam, 1.0, method="front")
    mesh = derived(cow).core_mesh
    tables = tuple(np.asarray(a) for a in (mesh.pcols, mesh.kill_data, mesh.base, mesh.tops, mesh.top_at))
    n_faces, n_vertices = int(r.n_faces), int(r.n_vertices)

    def call(faces=n_faces, ids=n_vertices, ran=r.core_ran, positions=r.front_positions, counts=r.core_counts,
             vertex_dtype=np.float32):
        return _core.front_mesh_eager(tables, ran, positions, counts, 0, mesh.n_original, mesh.n_faces,
                                      np.empty((faces, 3), np.int32), np.empty(ids, np.int32),
                                      np.empty((ids, 3), vertex_dtype))

    cases = {"faces do not fit": dict(faces=n_faces - 1), "size|capacity": dict(ids=3),
             "same shape": dict(positions=r.front_positions[:-1]), "ran": dict(ran=r.core_ran.astype(np.int32)),
             "vertex_positions": dict(vertex_dtype=np.float64), "counts": dict(counts=r.core_counts[:3])}
    for match, change in cases.items():
        with pytest.raises(ValueError, match=match):
            call(**change)
    # Slots that are not a refinement's, none ran: one position in every slot
    # (more front vertices than the model has), or a pcol whose children are
    # split there and itself in every other slot (its kill list more often
    # than the model with boundaries has faces; as often as the closed cow
    # has faces, where a face in two rows of either mode's ranks is refused).
    # The mesh is refused, with nothing written past a buffer.
    bunny = derived(pmjax.ProgressiveMesh.from_data(built("bunny.ply"))).core_mesh
    was = engines.mesh_ranks()
    try:
        for m in (mesh, bunny):
            held = tuple(np.asarray(a) for a in (m.pcols, m.kill_data, m.base, m.tops, m.top_at))
            pcols, n_base, P = held[0], len(held[2]), len(held[0])
            split = np.flatnonzero((pcols[:, 6] >= 0) & (pcols[:, 7] >= 0) & (pcols[:, 1] == 2))[0]
            again = np.full(P, split, np.int32)
            children = again.copy()
            children[:2] = pcols[split, 6:8]
            counts = np.asarray(r.core_counts).copy()
            counts[0], counts[2] = P, m.n_faces - n_base
            if m is bunny:
                assert 2 * (P - 2) + n_base > m.n_faces  # past the room for faces
            # A pcol's slot given twice with the counts of what it then
            # draws (no face count to tell): its front vertices' starts
            # twice, refused before any rank is written.
            drawing = np.flatnonzero(pcols[:, 1] > 0)[:2]
            twice = drawing[[0, 1, 1]].astype(np.int32)
            twice_counts = counts.copy()
            twice_counts[0], twice_counts[2] = 3, int(pcols[drawing, 1] @ np.array([1, 2]))
            for way in ("bitmaps", "sorts"):
                engines.mesh_ranks(way)
                with pytest.raises(ValueError, match="start at one original vertex"):
                    _core.front_mesh_eager(held, np.zeros(3, np.uint8), twice, twice_counts, 0, m.n_original,
                                           m.n_faces, np.empty((m.n_faces, 3), np.int32),
                                           np.empty(m.n_original, np.int32), np.empty((m.n_original, 3), np.float32))
                # Every rank mode refuses both: the front past the model's
                # vertices, and (past the room, or in the ranks of either
                # mode) a face drawn twice.
                for positions, match in ((again, "front holds more vertices"), (children, "face is drawn twice")):
                    with pytest.raises(ValueError, match=match):
                        _core.front_mesh_eager(held, np.zeros(P, np.uint8), positions, counts, 0, m.n_original,
                                               m.n_faces, np.empty((m.n_faces, 3), np.int32),
                                               np.empty(m.n_original, np.int32),
                                               np.empty((m.n_original, 3), np.float32))
    finally:
        engines.mesh_ranks(was)
    vertices, faces, ids = r.mesh()
    whole = _core.front_mesh(mesh, r.core_ran, r.front_positions, r.core_counts)
    k = int(whole[3])
    assert faces.shape == (n_faces, 3) and len(ids) == k == len(vertices)
    assert np.array_equal(faces, whole[0][:n_faces]) and np.array_equal(ids, whole[1][:k])
    assert np.array_equal(vertices, whole[2][:k])


# The mesh tables' records (pmx.h), as structured dtypes over int32 rows.
PCOL_RECORD = np.dtype([("kill_first", "<i4"), ("kill_count", "<i4"), ("vertex", "<i4", 2), ("start", "<i4", 2),
                        ("made_at", "<i4", 2), ("position", "<f4", (2, 3))])
FACE_RECORD = np.dtype([("face", "<i4"), ("start", "<i4", 3)])
TOP_RECORD = np.dtype([("start", "<i4"), ("vertex", "<i4"), ("position", "<f4", 3)])


def small_mesh_tables():
    """Mesh tables of five original vertices (starts 0..4), four faces and
    four pcols by position: 0 splits vertex 7 into 5 and 6 (made at
    positions 1 and 2, starts 1 and 3), 1 splits 5 into originals 0 and 1,
    2 splits 6 into 2 and 3, 3 (in no refinement's slots) 4 into itself;
    each kills one face; the tops are original 4 (start 0) and 7."""
    pcols = np.zeros(4, PCOL_RECORD)
    pcols[0] = (0, 1, (5, 6), (1, 3), (1, 2), 0)
    pcols[1] = (1, 1, (0, 1), (1, 2), (-1, -1), 0)
    pcols[2] = (2, 1, (2, 3), (3, 4), (-1, -1), 0)
    pcols[3] = (3, 1, (4, 4), (0, 0), (-1, -1), 0)
    kill_data = np.array([(0, (1, 3, 0)), (1, (1, 2, 0)), (2, (3, 4, 0)), (3, (0, 1, 3))], FACE_RECORD)
    tops = np.array([(0, 4, 0), (1, 7, 0)], TOP_RECORD)
    return pcols, kill_data, np.zeros(0, FACE_RECORD), tops, np.array([-1, 0], np.int32)


def int32_tables(tables):
    """Record tables as the core takes them: int32 [n, fields]."""
    width = {PCOL_RECORD: 14, FACE_RECORD: 4, TOP_RECORD: 5}
    return tuple(t.view(np.int32).reshape(-1, width[t.dtype]) if t.dtype in width else t for t in tables)


def small_mesh(tables, positions, n_faces_drawn, n_original=5, n_faces=4, rows=4):
    """The mesh of the small tables' slots (none ran; room for `rows`
    faces): (n_ids, faces, ids)."""
    held = int32_tables(tables)
    positions = np.asarray(positions, np.int32)
    counts = np.array([len(positions), len(positions), n_faces_drawn, 0], np.int32)
    faces, ids = np.full((rows, 3), -7, np.int32), np.full(n_original, -7, np.int32)
    k = _core.front_mesh_eager(held, np.zeros(len(positions), np.uint8), positions, counts, 0, n_original, n_faces,
                               faces, ids, np.zeros((n_original, 3), np.float32))
    return k, faces[:n_faces_drawn].tolist(), ids[:k].tolist()


def test_the_mesh_refuses_slots_and_tables_that_are_not_a_refinements():
    """In both rank modes the core gives a small refinement's mesh, and
    refuses (a ValueError saying why, naming a bad record) a face drawn
    twice, a vertex id used twice, a front not starting at vertex 0, a face
    count that differs and records pointing outside the tables."""
    was = engines.mesh_ranks()
    try:
        for way in ("bitmaps", "sorts"):
            engines.mesh_ranks(way)
            tables = small_mesh_tables()
            assert small_mesh(tables, [0, 1, 2], 3) == (5, [[0, 2, 4], [0, 1, 4], [2, 3, 4]], [0, 1, 2, 3, 4])
            with pytest.raises(ValueError, match="face is drawn twice"):
                small_mesh(tables, [0, 0, 1, 2], 4)
            with pytest.raises(ValueError, match="faces drawn do not match"):
                small_mesh(tables, [0, 1, 2], 2)
            pcols, kill_data, base, tops, top_at = small_mesh_tables()
            pcols[2]["vertex"] = (2, 2)
            with pytest.raises(ValueError, match="vertex id is used by two"):
                small_mesh((pcols, kill_data, base, tops, top_at), [0, 1, 2], 3)
            with pytest.raises(ValueError, match="does not start at original vertex 0"):
                small_mesh((*tables[:3], tops[1:], top_at[1:]), [0, 1, 2], 3)
            for table, index, field, value in ((0, 1, "kill_first", 10**9), (0, 2, "made_at", 1), (0, 1, "start", 5),
                                               (1, 1, "face", 4), (1, 1, "start", -1), (3, 0, "start", 5),
                                               (3, 1, "vertex", 9)):
                forged = list(small_mesh_tables())
                forged[table][index][field] = value
                name = ("pcol_records", "kill_data", "base", "tops")[table]
                with pytest.raises(ValueError, match=rf"{name}\[{index}\]: .* outside"):
                    small_mesh(forged, [0, 1, 2], 3)
            forged = list(small_mesh_tables())
            forged[4] = np.array([-1, 4], np.int32)
            with pytest.raises(ValueError, match=r"tops\[1\]: .* outside"):
                small_mesh(forged, [0, 1, 2], 3)
            # A face's corners are numbered in int32: more faces than
            # INT32_MAX / 3 are refused by both entries.
            with pytest.raises(ValueError, match="faces are more than"):
                small_mesh(tables, [0, 1, 2], 3, n_faces=2**31 // 3 + 1)
            P = len(tables[0])

            def stream(tables, n_faces=4):
                return _core._pmx.mesh_stream_new(*int32_tables(tables), np.zeros(P, np.int32), np.zeros(P, np.int32),
                                                  np.zeros((P, 3), np.float32), np.full(P + 5, -1, np.int32),
                                                  np.zeros((4, 3), np.int32), 5, n_faces)

            with pytest.raises(ValueError, match="faces are more than"):
                stream(tables, 2**31 // 3 + 1)
            # The stream's tables are checked whole by the same checks.
            forged = list(small_mesh_tables())
            forged[1][1]["start"] = (0, 0, 5)
            with pytest.raises(ValueError, match=r"kill_data\[1\]: .* outside"):
                stream(forged)
    finally:
        engines.mesh_ranks(was)
