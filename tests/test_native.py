"""The front engine's C loops: certified decisions, exact refinements and meshes.

Every test compares with the float32 predicate, the dense engine or the
JAX traversal; none checks the C code against itself.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmjax
from pmjax import _native
from pmjax._camera import index_camera, stack_cameras

pytestmark = pytest.mark.skipif(not _native.available(), reason="the C loops are not built (no C compiler)")

TAUS = (0.0, 1e-3, 1.0, 4.0, 1e6)


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


TESTS = (pmjax.ALL_TESTS, pmjax.Tests(frustum=False), pmjax.Tests(orientation=False), pmjax.Tests(screen=False))


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply", "terrain_gcanyon.ply"])
def test_certified_decisions_equal_the_float32_predicate(built, name):
    """Over every pcol: a decision the C code is sure of is the float32
    predicate's bit, and a subtree bound that says "whole" holds for every
    pcol below (each of them collapses). Unsure decisions are rare."""
    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    kids = np.asarray(pm.children)
    cams = [index_camera(views_of(data, 6, seed=3), i) for i in range(6)] + orthographic_views(data)
    checked = unsure = 0
    for cam in cams:
        for tests in TESTS:
            for tau in (0.0, 1.0, 4.0):
                got = _native.decide_all(pm, cam, tau, tests)
                want = np.asarray(pmjax.collapse_mask(pm.attributes, cam, jnp.float32(tau), tests))
                own = got & 3
                sure = own != _native.UNSURE
                assert np.array_equal(own[sure] == _native.YES, want[sure]), (cam.orthographic, tests, tau)
                checked += int(sure.sum())
                unsure += int((~sure).sum())
                # "whole" at p: every pcol of p's subtree collapses (children
                # come from earlier batches, so one pass from the first batch
                # gives "the whole subtree collapses" per pcol).
                all_below = want.copy()
                for p in range(pm.n_pcols):
                    for k in kids[p]:
                        if k >= 0:
                            all_below[p] &= all_below[k]
                whole = (got & 4) != 0
                assert np.all(all_below[whole]), (cam.orthographic, tests, tau)
    assert checked > 0 and unsure <= 1e-4 * checked


@pytest.mark.parametrize("name, pair_distance", [("cow.ply", 0.0), ("bunny.ply", 0.0), ("cessna.ply", 0.02),
                                                 ("terrain_gcanyon.ply", 0.0)])
def test_native_refine_equals_dense(built, name, pair_distance, slots):
    data = built(name, pair_distance)
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = [index_camera(views_of(data, 6, seed=len(name)), i) for i in range(6)] + orthographic_views(data)
    for i, cam in enumerate(cams):
        for tau in TAUS:
            native = pmjax.refine(pm, cam, tau, method="front")
            assert isinstance(native.visited, np.ndarray)  # the C loops ran
            assert_refinements_equal(native, pmjax.refine(pm, cam, tau, method="dense"), (i, tau))


def test_unsure_decisions_are_asked_of_the_float32_predicate(built, slots):
    """At tau equal to pcols' critical tolerances the screen test is a float
    tie: the C code must leave those pcols unsure, and the answer is still the
    dense engine's, one float step below, at and above the tie."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4), 1)
    t = np.asarray(pmjax.critical_tau(pm.attributes, cam))
    picks = np.random.default_rng(1).choice(np.flatnonzero(np.isfinite(t) & (t > 0.2) & (t < 5)), 8, replace=False)
    unsure = 0
    for p in picks:
        for tau in (np.nextafter(t[p], np.float32(0)), t[p], np.nextafter(t[p], np.float32(np.inf))):
            unsure += int(_native.decide_all(pm, cam, tau, pmjax.ALL_TESTS)[p] & 3 == _native.UNSURE)
            assert_refinements_equal(pmjax.refine(pm, cam, tau, method="front"),
                                     pmjax.refine(pm, cam, tau, method="dense"), tau)
    assert unsure >= len(picks)  # at least the tie itself is never guessed


def test_extreme_scales_fall_back_to_the_float32_predicate(built):
    """A model scaled to 1e-18 or 1e15 units (float32 products near the
    smallest normal, or huge): the certification stays exact."""
    data = built("cow.ply")
    for scale in (1e-18, 1e15):
        scaled = dataclasses.replace(data, vertices=(data.vertices * scale).astype(np.float32),
                                     radius=(data.radius * scale).astype(np.float32),
                                     delta=(data.delta * scale).astype(np.float32),
                                     mu=(data.mu * scale).astype(np.float32))
        pm = pmjax.ProgressiveMesh.from_data(scaled)
        v0 = scaled.vertices[: scaled.n_original_vertices].astype(np.float64)
        for i in range(3):
            cam = index_camera(pmjax.random_views(v0, 3, seed=i, min_scale=0.5, max_scale=3.0), i)
            for tau in (0.0, 1.0, 8.0):
                assert_refinements_equal(pmjax.refine(pm, cam, tau, method="front"),
                                         pmjax.refine(pm, cam, tau, method="dense"), (scale, tau))


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply", "cessna.ply", "terrain_gcanyon.ply"])
def test_native_mesh_equals_dense_mesh(built, name):
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
    host = _native.native_mesh(pm)
    for table in ("table", "bfs_table", "below_table"):
        values = np.abs(getattr(host, table)[:, :-1].astype(np.float64))  # the last column holds integers
        assert not np.any((values > 0) & (values < np.finfo(np.float32).tiny)), table
    spread = np.asarray(pm.subtree.spread)
    assert spread.dtype == np.float32 and np.any(spread == 0) and np.all(spread >= 0)
    leaves = (np.asarray(pm.children) < 0).all(axis=1)
    assert np.all(spread[leaves] == 0)
    # A positive bound, however small, is still rounded up.
    from pmjax._subtree import _rounded_up

    up = _rounded_up(np.array([0.0, 1e-300, 1.0]))
    assert up.dtype == np.float32 and up[0] == 0 and up[1] > 0 and up[2] > 1


def test_tables_start_on_cache_lines(built):
    """Every row the C loops read is one 64-byte cache line, and the tables
    hold the mesh's values (in breadth-first order)."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    host = _native.native_mesh(pm)
    for name in ("table", "bfs_table", "below_table"):
        t = getattr(host, name)
        assert t.ctypes.data % 64 == 0 and t.shape[1] * t.itemsize == 64 and t.flags.c_contiguous, name
    assert np.array_equal(host.table, np.asarray(pm.table, np.float32))
    assert np.array_equal(host.bfs_table[:, :-1], host.table[host.order, :-1])
    # The last column: the first child's position, the number of children and
    # (sign bit) whether the pcol kills other than two faces.
    kids = host.bfs_table[:, -1].view(np.uint32).astype(np.int64)
    children = np.asarray(pm.children)[host.order]
    count = (children >= 0).sum(1)
    assert np.array_equal(kids & 3, count)
    at = np.empty(pm.n_pcols, np.int64)
    at[host.order] = np.arange(pm.n_pcols)
    has = count > 0
    first = np.where(children[:, 0] >= 0, children[:, 0], children[:, 1])  # the first created child
    assert np.array_equal((kids[has] >> 2) & (2**29 - 1), at[first[has]])
    assert np.array_equal(kids >> 31, np.asarray(pm.kills)[host.order] != 2)


_BEST = _native.slot_loops()
SLOTS = ["plain"] + [pytest.param(kind, marks=pytest.mark.skipif(
    _native.SLOT_LOOPS.index(_BEST) < _native.SLOT_LOOPS.index(kind),
    reason=f"no {kind} here (or no C loops)")) for kind in ("avx2", "avx512")]


@pytest.fixture(params=SLOTS)
def slots(request):
    """Each test that takes it runs with the slots kept by each kind of loop
    the processor has (AVX-512 masks, AVX2, plain)."""
    was = _native.slot_loops(request.param)
    assert _native.slot_loops() == request.param
    yield request.param
    _native.slot_loops(was)


def test_native_batch_equals_dense(built, slots):
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = stack_cameras([index_camera(views_of(data, 70, seed=2), i) for i in range(70)])
    for tau in (0.0, 1.0, 4.0):
        native = pmjax.refine_batch(pm, cams, tau, chunk=64, return_masks=True, method="front")
        dense = pmjax.refine_batch(pm, cams, tau, chunk=64, return_masks=True, method="dense")
        for key in dense:
            assert np.array_equal(native[key], dense[key]), (tau, key)
    one = _native.refine_many(pm, cams, np.float32(1.0), pmjax.ALL_TESTS, False, threads=1)
    for threads in (2, 3):
        many = _native.refine_many(pm, cams, np.float32(1.0), pmjax.ALL_TESTS, False, threads=threads)
        assert all(np.array_equal(a, b) for a, b in zip(one, many)), threads


def test_subnormals_come_back_after_the_c_loops(built):
    """The C loops read and write subnormal floats as zero while they run
    (the thread's floating-point mode), and give the caller's mode back."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    views = views_of(data, 4, seed=4)
    tiny = np.array([2.0 ** -126], np.float32)
    calls = [lambda: pmjax.refine(pm, index_camera(views, 0), 1.0, method="front"),
             lambda: _native.refine_many(pm, views, np.float32(1.0), pmjax.ALL_TESTS, False, threads=1),
             lambda: _native.decide_all(pm, index_camera(views, 1), 1.0, pmjax.ALL_TESTS),
             lambda: pmjax.path_counts(pm, views, 1.0)]
    for i, call in enumerate(calls):
        call()
        # Compared as bits: with subnormals as zero, 0 == 2^-128 holds too.
        assert (tiny * np.float32(0.25)).view(np.int32)[0] == 1 << 21, i  # 2^-128


def test_native_batches_from_several_threads_at_once(built):
    """Batches started together from user threads share the helper threads
    (a helper busy with another batch is not waited for) and each gets its
    own cameras' results."""
    import concurrent.futures

    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    views = views_of(data, 48, seed=9)
    batches = [stack_cameras([index_camera(views, i) for i in range(j, 48, 4)]) for j in range(4)]
    alone = [_native.refine_many(pm, b, np.float32(1.0), pmjax.ALL_TESTS, True, threads=1) for b in batches]
    with concurrent.futures.ThreadPoolExecutor(4) as users:
        together = list(users.map(lambda b: _native.refine_many(pm, b, np.float32(1.0), pmjax.ALL_TESTS, True),
                                  batches * 3))
    for i, got in enumerate(together):
        assert all(np.array_equal(a, b) for a, b in zip(alone[i % 4], got)), i


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


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply", "terrain_gcanyon.ply"])
def test_fat_camera_decisions_hold_for_every_frame(built, name):
    """Over every pcol, for words of frames: where the fat camera says
    "whole", every frame's subtree collapses under the float32 predicate;
    where it says "no", no frame's predicate collapses the pcol. Along an
    orbit it decides most pcols; with a tolerance of 0 (not a usual view) it
    decides none."""
    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    kids = np.asarray(pm.children)
    for label, word in fat_words(data).items():
        for tau in (1e-3, 1.0, 4.0, 0.0):
            taus = np.full(16, tau, np.float32)
            got = _native.decide_fat_all(pm, word, taus, pmjax.ALL_TESTS)
            if tau == 0.0:
                assert not np.any(got), label
                continue
            for f in range(16):
                cam = index_camera(word, f)
                want = np.asarray(pmjax.collapse_mask(pm.attributes, cam, jnp.float32(tau), pmjax.ALL_TESTS))
                assert not np.any(want[got == 2]), (label, tau, f)
                # Every pcol of the subtree collapses: batch by batch (children
                # come from earlier batches).
                all_below = want.copy()
                for lo, hi in zip(pm.batch_offsets[:-1], pm.batch_offsets[1:]):
                    for k in kids[lo:hi].T:
                        has = k >= 0
                        all_below[lo:hi][has] &= all_below[k[has]]
                assert np.all(all_below[got == 1]), (label, tau, f)
            if label.startswith("orbit") and tau == 1.0:
                assert np.mean(got == 1) > 0.3 and np.any(got == 2), (label, np.bincount(got, minlength=3))


def test_fat_camera_bounds_hold(built):
    """The fat camera's bounds (recomputed here in float64) hold for every
    frame of a word: eyes within rho of the centre and within the capsule of
    the chord, rotations within eps, the pivot's camera coordinates within
    tau."""
    data = built("cow.ply")
    for label, word in fat_words(data).items():
        views = _native.host_views(jax.tree.map(np.asarray, word), np.ones(16, np.float32))
        fat = _native.fat_cameras(views[None])[0].astype(np.float64)
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


def test_a_fat_camera_that_is_not_finite_is_not_used(built):
    """A fat camera with a non-finite bound decides nothing at once: the
    word's frames are decided one by one, with the same counts and lists as
    without a fat camera (and as with a finite one)."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    word = fat_words(data)["orbit 0"]
    taus = np.ones(16, np.float32)
    bad = np.full(_native.FAT_VALUES, np.nan, np.float32)
    alone = _native.refine_word(pm, word, taus, pmjax.ALL_TESTS, True, fat=False)
    unused = _native.refine_word(pm, word, taus, pmjax.ALL_TESTS, True, fat=bad)
    used = _native.refine_word(pm, word, taus, pmjax.ALL_TESTS, True, fat=True)
    assert unused[3] == 0 and used[3] > 0
    for got in (unused, used):
        for a, b in zip(got[0], alone[0]):
            assert np.array_equal(a, b)
        for (v1, r1, _), (v2, r2, _) in zip(got[1], alone[1]):
            assert np.array_equal(np.sort(v1[~r1]), np.sort(v2[~r2]))
    for x, y in zip(unused[1], alone[1]):  # frame by frame: the very same lists
        assert all(np.array_equal(a, b) for a, b in zip(x, y))


@pytest.mark.parametrize("orthographic", [False, True])
def test_host_view_constants_are_within_the_allowance(orthographic):
    """The C loops read view constants computed on the host; the
    certification allows them 2^-20 relative from XLA's (VIEW in
    _front_native.c). They must stay well inside it, for one camera and for
    batches."""
    v0 = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    cams = pmjax.random_views(v0, 400, seed=1, min_scale=0.05, max_scale=6.0)
    if orthographic:
        cams = pmjax.Camera(cams.eye, cams.rotation, cams.fov_y, cams.near, cams.far, cams.ortho_height, cams.width,
                            cams.height, orthographic=True)
    for tau in (0.0, 1e-3, 1.0, 4.0, 1e6):
        batch = _native.host_views(cams, tau).astype(np.float64)
        for i in range(0, 400, 8):
            cam = index_camera(cams, i)
            xla = _native.view_values(cam, tau).astype(np.float64)
            one = _native.host_view(cam, tau).astype(np.float64)
            for host in (batch[i], one):
                rel = np.abs(host - xla) / np.maximum(np.abs(xla), np.finfo(np.float32).tiny)
                assert np.all(rel <= 2.0 ** -21), (tau, i, np.log2(rel.max()))


@pytest.mark.parametrize("room", [None, 4])
def test_batch_at_a_float_tie_asks_the_predicate_once_per_batch(built, monkeypatch, room, slots):
    """A batch refined at a pcol's critical tolerance has unsure decisions in
    many cameras; they are answered for the whole batch and the cameras'
    counts and masks corrected from their records: the same bits as the
    dense engine, also when the records outgrow their first room (4 int32,
    less than one record: every such camera grows it and is traversed
    again)."""
    if room is not None:
        monkeypatch.setattr(_native, "RECORD_ROOM", room)
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    orbit = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4)
    cam = index_camera(orbit, 1)
    t = np.asarray(pmjax.critical_tau(pm.attributes, cam))
    p = np.flatnonzero(np.isfinite(t) & (t > 0.5) & (t < 4))[0]
    cams = stack_cameras([cam] * 40 + [index_camera(orbit, i) for i in range(4)])
    assert _native.decide_all(pm, cam, t[p], pmjax.ALL_TESTS)[p] & 3 == _native.UNSURE
    assert p in np.asarray(pmjax.refine(pm, cam, t[p], method="front").visited)  # so 40 cameras have a record
    native = pmjax.refine_batch(pm, cams, t[p], chunk=64, return_masks=True, method="front")
    dense = pmjax.refine_batch(pm, cams, t[p], chunk=64, return_masks=True, method="dense")
    for key in dense:
        assert np.array_equal(native[key], dense[key]), key


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


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply"])
def test_budget_by_search_equals_the_sort(built, name):
    """faces_for_budget from output-sensitive counts (a search over the
    float32 patterns of tau) gives the dense sort's tau and face count, bit
    for bit, at budgets across the whole range and at its ends."""
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
