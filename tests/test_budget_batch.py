"""faces_for_budget_batch: exact face budgets for camera batches.

Every answer must be faces_for_budget's, bit for bit: the dense sort of the
critical tolerances (method="dense") and the core's search (method="front"),
with the counts of a refine at the answer.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

import pmjax
from pmjax import _refine
from pmjax._camera import index_camera, stack_cameras
from pmjax.engines import _dense

pytestmark = pytest.mark.core


def _views(data, n, seed):
    v0 = data.vertices[: data.n_original_vertices]
    cams = pmjax.random_views(v0, n, seed=seed, min_scale=0.05, max_scale=6.0)
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    # Views away from the model (everything culled) and from inside it.
    away = pmjax.look_at(c + [3 * r, 0, 0], c + [6 * r, 0, 0])
    inside = pmjax.look_at(c, c + [0, 0, r])
    return stack_cameras([index_camera(cams, i) for i in range(n)] + [away, inside])


def _orthographic(data):
    v0 = data.vertices[: data.n_original_vertices]
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    return stack_cameras([pmjax.look_at(c + d, c, orthographic=True, ortho_height=h, near=1e-3, far=10 * r)
                          for d, h in (([0, 0, r], 0.5 * r), ([r, 0.3 * r, 0], 2 * r), ([0, r, 0.1 * r], 0.1 * r))])


def _budgets(pm, cams):
    """Budgets across the range: below the base mesh, at it, between, at and
    above the finest view."""
    full = pm.n_faces
    base = full - int(np.sum(np.asarray(pm.kills)))
    some = pmjax.refine_batch(pm, cams, 1.0)["faces"]
    return sorted({0, max(base - 1, 0), base, base + 1, int(np.median(some)), int(some.min()), full // 3, full,
                   full + 7})


def _assert_same(pm, cams, budgets, run, tests=pmjax.ALL_TESTS, front=True):
    """``run(budget)`` (a batch's answers) against faces_for_budget per camera
    and budget: the dense sort (one sort per camera's critical tolerances)
    and, with ``front``, the core's search; and the counts of a refine at
    the answer."""
    outs = [run(b) for b in budgets]
    for k in range(len(outs[0]["tau"])):
        cam = index_camera(cams, k)
        eps = pmjax.critical_tolerances(pm, cam, tests)
        for budget, out in zip(budgets, outs):
            b = int(np.broadcast_to(budget, (len(out["tau"]),))[k])
            want = [_dense.budget_sort(pm, eps, b)]
            if front:
                want.append(pmjax.faces_for_budget(pm, cam, b, tests, method="front"))
            for tau, faces in want:
                assert np.float32(out["tau"][k]).tobytes() == np.float32(tau).tobytes(), (k, b)
                assert out["faces"][k] == faces, (k, b)
            r = pmjax.refine(pm, cam, out["tau"][k], tests=tests)
            assert (out["faces"][k], out["vertices"][k], out["executed_count"][k]) == \
                (int(r.n_faces), int(r.n_vertices), int(r.n_executed)), (k, b)


@pytest.mark.slow
def test_batch_equals_the_dense_sort_on_the_cow(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 4, seed=5)
    _assert_same(pm, cams, _budgets(pm, cams), lambda b: pmjax.faces_for_budget_batch(pm, cams, b, method="front"),
                 front=False)


@pytest.mark.slow
def test_orthographic_ablations_and_budgets_per_camera(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _orthographic(data)
    budgets = _budgets(pm, cams)
    _assert_same(pm, cams, budgets, lambda b: pmjax.faces_for_budget_batch(pm, cams, b, method="front"))
    persp = _views(data, 6, seed=9)
    per_camera = np.array(budgets * 2)[: 8]
    for tests in (pmjax.Tests(frustum=False), pmjax.Tests(orientation=False), pmjax.Tests(screen=False),
                  pmjax.Tests(frustum=False, orientation=False)):
        _assert_same(pm, persp, [per_camera, per_camera[::-1]],
                     lambda b: pmjax.faces_for_budget_batch(pm, persp, b, tests=tests, method="front"), tests)


def test_wrong_guesses_still_give_the_exact_answer(built, monkeypatch):
    """The exact counts make any guess exact: guesses (both of them) far off
    in both directions, at 0, at inf and past it, give the same answers."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 6, seed=2)
    want = {b: pmjax.faces_for_budget_batch(pm, cams, b, method="front") for b in _budgets(pm, cams)}
    rng = np.random.default_rng(0)
    for bad in (lambda g: g * 0, lambda g: g * 0 + 0x7F800001, lambda g: g * 0 + 0x7F800000,
                lambda g: g + rng.integers(-10 ** 7, 10 ** 7, g.shape), lambda g: g + 1, lambda g: g - 1,
                lambda g: rng.integers(0, 0x7F800002, g.shape)):
        original = _refine._core_guesses
        monkeypatch.setattr(_refine, "_core_guesses", lambda *a, **k: tuple(
            bad(np.asarray(g, np.int64)).astype(np.int32) for g in original(*a, **k)))
        for b, out in want.items():
            got = pmjax.faces_for_budget_batch(pm, cams, b, method="front")
            for key in out:
                assert out[key].tobytes() == got[key].tobytes(), (b, key)
        monkeypatch.setattr(_refine, "_core_guesses", original)


@pytest.mark.slow
@pytest.mark.parametrize(
    "per_side, budgets",
    [
        (4, [100, 900, 5000, 40, 2000, 10 ** 6]),  # one budget per camera
        (2, [[100, 900, 10 ** 6]] * 4),  # several budgets per camera
    ],
)
def test_under_jit(built, per_side, budgets):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, per_side, seed=3)
    budgets = np.array(budgets, np.int32)
    want = pmjax.faces_for_budget_batch(pm, cams, budgets, method="front")
    got = jax.jit(lambda c, b: pmjax.faces_for_budget_batch(pm, c, b))(cams, budgets)
    for key in want:
        assert np.array_equal(np.asarray(got[key]), want[key]), key


def test_bad_budgets_are_refused(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 4, seed=3)
    for bad in (-1, 2.5, float("nan"), "10", np.array([1, 2])):
        with pytest.raises(ValueError, match="budget"):
            pmjax.faces_for_budget_batch(pm, cams, bad)


def test_budgets_past_int32_are_every_face_and_traced_budgets_are_checked(built):
    """A budget of F or more means every face fits, whatever its size (2**31
    and up do not fit the kernels' int32: capped at F first); a traced budget
    must be an integer, and a negative one raises inside the computation."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 4, seed=3)
    cam = index_camera(cams, 0)
    F = pm.n_faces
    for method in ("front", "dense"):
        assert pmjax.faces_for_budget(pm, cam, 2 ** 40, method=method) == pmjax.faces_for_budget(pm, cam, F,
                                                                                                 method=method)
        got = jax.jit(lambda c: pmjax.faces_for_budget(pm, c, 2 ** 31, method=method))(cam)
        assert (float(got[0]), int(got[1])) == pmjax.faces_for_budget(pm, cam, F, method=method)
    want = pmjax.faces_for_budget_batch(pm, cams, F)["faces"]
    assert np.array_equal(np.asarray(jax.jit(lambda c: pmjax.faces_for_budget_batch(pm, c, 2 ** 31))(cams)["faces"]),
                          want)
    assert np.array_equal(pmjax.path_counts(pm, cams, budget=2 ** 31)["faces"], want)
    with pytest.raises(Exception, match="faces_for_budget: a face budget must be >= 0"):
        jax.block_until_ready(jax.jit(lambda b: pmjax.faces_for_budget(pm, cam, b))(jax.numpy.int32(-5)))
    with pytest.raises(TypeError, match="faces_for_budget: a traced face budget must be an integer array"):
        jax.jit(lambda b: pmjax.faces_for_budget(pm, cam, b))(jax.numpy.float32(2500.9))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["bunny.ply", "terrain_gcanyon.ply"])
def test_batch_equals_faces_for_budget(built, name):
    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 24, seed=len(name))
    _assert_same(pm, cams, _budgets(pm, cams), lambda b: pmjax.faces_for_budget_batch(pm, cams, b, chunk=32),
                 front=False)


def test_guesses_are_the_same_at_every_simd_level(built):
    """The vectorized switch points are exactly rounded operations: every
    SIMD level guesses the same (with the first tolerance given, so that no
    thread's order enters)."""
    from pmjax import engines
    from pmjax.engines import _core
    from pmjax.engines._tables import derived

    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 8, seed=4)
    d, counts_of = derived(pm), _refine._Counts.of(pm)
    rows = _core.host_camera_rows(jax.tree.map(np.asarray, cams), np.full(10, 0.7, np.float32), d.exponent)
    was = engines.simd()
    try:
        got = []
        for level in ("plain", "avx2", "avx512"):
            engines.simd(level)
            got.append([np.asarray(g) for g in _refine._core_guesses(d.core, rows, np.full((10, 1), 900, np.int32),
                                                                     pmjax.ALL_TESTS, False, counts_of.base_faces)])
    finally:
        engines.simd(was)
    for other in got[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(got[0], other))


def test_padded_guesses_are_the_guesses_of_their_cameras(built, monkeypatch):
    """A call padded past its cameras (repeats of its last camera, with no
    budget to meet) guesses each camera as a call of exactly its cameras
    does: the core is given each camera's own budgets and -1 (below every
    mesh) on every padding row, and a row with no budget to meet makes no
    guess of its own: inf, with no traversal (with the first tolerances
    given, so that no thread's order enters)."""
    from pmjax.engines import _core
    from pmjax.engines._tables import derived

    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 8, seed=6)
    host = jax.tree.map(np.asarray, cams)
    d, counts_of = derived(pm), _refine._Counts.of(pm)
    K = len(host.eye)
    base = counts_of.base_faces
    budgets = np.stack([np.full(K, base), np.full(K, base + 40), np.full(K, 900), np.full(K, pm.n_faces)], 1)
    start = np.full(K, 0.7, np.float32)
    frames = np.arange(K - 3)
    # The budgets each call hands the core, recorded on the way through.
    given, core_guesses = [], _refine._core_guesses

    def recording(tables, rows, want, *rest, **named):
        given.append(np.array(want))
        return core_guesses(tables, rows, want, *rest, **named)

    monkeypatch.setattr(_refine, "_core_guesses", recording)
    padded = _refine._guesses(d, counts_of, host, frames, start, budgets, pmjax.ALL_TESTS, 32)
    monkeypatch.undo()
    assert len(given) == 1 and given[0].shape == (32, budgets.shape[1])
    assert np.array_equal(given[0][:len(frames)], budgets[frames])
    assert (given[0][len(frames):] == -1).all()
    rows = _core.host_camera_rows(host, start, d.exponent)[frames]
    exact = [np.asarray(g) for g in _refine._core_guesses(d.core, rows, budgets[frames].astype(np.int32),
                                                          pmjax.ALL_TESTS, False, base)]
    assert all(np.array_equal(a, b) for a, b in zip(padded, exact))
    # A row with no budget to meet (all below every mesh) is answered inf.
    none = [np.asarray(g) for g in _refine._core_guesses(d.core, rows[:1], np.full((1, 2), -1, np.int32),
                                                         pmjax.ALL_TESTS, False, base)]
    assert all((g == _refine._INF_BITS + 1).all() for g in none)


def _columns(pm, cams, budgets):
    """Per camera, every budget of ``budgets`` (a row per camera: its order
    rotated by the camera's index, so that columns mix budgets)."""
    return np.stack([np.roll(budgets, k) for k in range(camera_count_of(cams))])


def camera_count_of(cams):
    return len(np.asarray(cams.eye))


def _column_of(got, cols):
    """``run`` for _assert_same: the columns ``cols`` of ``got``, in turn."""
    it = iter(cols)

    def run(_):
        j = next(it)
        return {k: v[:, j] for k, v in got.items()}

    return run


def test_several_budgets_per_camera_equal_one_at_a_time(built):
    """A ``[K, B]`` budget (one guess traversal per camera for its B budgets)
    gives, column by column, the answers of the budgets one at a time, which
    equal faces_for_budget's: budgets below the base mesh, at it, between,
    at the finest view and beyond the full mesh, mixed across the columns."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 6, seed=8)
    budgets = _columns(pm, cams, np.array(_budgets(pm, cams)))
    got = pmjax.faces_for_budget_batch(pm, cams, budgets, method="front")
    assert all(v.shape == budgets.shape for v in got.values())
    for j in range(budgets.shape[1]):
        one = pmjax.faces_for_budget_batch(pm, cams, budgets[:, j], method="front")
        for key in one:
            assert got[key][:, j].tobytes() == one[key].tobytes(), (j, key)
    # And against the dense sort, for a few columns.
    _assert_same(pm, cams, [budgets[:, 0], budgets[:, 3]], _column_of(got, [0, 3]), front=False)
    # One column is the [K] form; under jit, the same answers.
    col = pmjax.faces_for_budget_batch(pm, cams, budgets[:, :1], method="front")
    assert col["tau"].shape == (len(budgets), 1)
    assert col["tau"][:, 0].tobytes() == got["tau"][:, 0].tobytes()


def test_budget_arrays_of_another_shape_are_refused(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 4, seed=3)  # 6 cameras
    for bad in (np.zeros((6, 0), np.int64), np.zeros((5, 2), np.int64), np.zeros((6, 2, 1), np.int64),
                np.array([[1, -1]] * 6)):
        with pytest.raises(ValueError, match="budget"):
            pmjax.faces_for_budget_batch(pm, cams, bad)


def test_several_budgets_with_wrong_guesses_give_the_exact_answers(built, monkeypatch):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 4, seed=9)
    budgets = _columns(pm, cams, np.array(_budgets(pm, cams)[1:5]))
    want = pmjax.faces_for_budget_batch(pm, cams, budgets, method="front")
    rng = np.random.default_rng(1)
    original = _refine._core_guesses
    for bad in (lambda g: g * 0, lambda g: g + rng.integers(-10 ** 6, 10 ** 6, g.shape),
                lambda g: rng.integers(0, 0x7F800002, g.shape)):
        monkeypatch.setattr(_refine, "_core_guesses", lambda *a, **k: tuple(
            bad(np.asarray(g, np.int64)).astype(np.int32) for g in original(*a, **k)))
        got = pmjax.faces_for_budget_batch(pm, cams, budgets, method="front")
        for key in want:
            assert want[key].tobytes() == got[key].tobytes(), key
    monkeypatch.setattr(_refine, "_core_guesses", original)


def _moved(data, scale, offset):
    """``data`` scaled about the origin, then moved by ``offset`` model sizes."""
    import dataclasses

    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    size = scale * float(np.ptp(data.vertices[: data.n_original_vertices], axis=0).max())
    lengths = {k: (f64(getattr(data, k)) * scale).astype(np.float32) for k in ("radius", "delta", "mu")}
    return dataclasses.replace(data, vertices=(f64(data.vertices) * scale + offset * size).astype(np.float32),
                               **lengths), size


@pytest.mark.slow
@pytest.mark.parametrize("scale,offset", [(1e-6, 3.0), (1e6, -5.0)])
def test_batch_budgets_at_any_scale(built, scale, offset):
    """The model and its cameras scaled and moved: the batch's answers (one
    and several budgets per camera, as a batch and as a path) keep the
    unscaled model's face counts and equal the dense sort at that scale."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 12)
    moved, size = _moved(data, scale, offset)
    pm_s = pmjax.ProgressiveMesh.from_data(moved)
    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    cams_s = pmjax.Camera(f64(cams.eye) * scale + offset * size, np.asarray(cams.rotation), np.asarray(cams.fov_y),
                          f64(cams.near) * scale, f64(cams.far) * scale, f64(cams.ortho_height) * scale,
                          np.asarray(cams.width), np.asarray(cams.height), cams.orthographic)
    budgets = _columns(pm, cams, np.array(_budgets(pm, cams)[1:6]))
    unit = pmjax.faces_for_budget_batch(pm, cams, budgets, method="front")
    for path in (False, True):
        got = pmjax.faces_for_budget_batch(pm_s, cams_s, budgets, method="front", path=path)
        assert np.array_equal(got["faces"], unit["faces"]), path
        for j in (0, 2):
            one = pmjax.faces_for_budget_batch(pm_s, cams_s, budgets[:, j], method="front", path=path)
            assert one["tau"].tobytes() == got["tau"][:, j].tobytes(), (path, j)
    _assert_same(pm_s, cams_s, [budgets[:, 0], budgets[:, 4]], _column_of(got, [0, 4]))


@pytest.mark.slow
def test_counts_in_several_calls_equal_refines(built, monkeypatch):
    """Exact counts of more probes than one call takes: calls of 32 times a
    power of 4 that cover the probes once each, the last padded by fewer than
    32 rows, with each probe's counts those of a refine at its tolerance."""
    for m in (1, 31, 32, 33, 160, 2047, 2048, 2049, 10 ** 4 + 3):
        calls = _refine._count_calls(m)
        assert [s for s, _ in calls] == list(np.cumsum([0] + [n for _, n in calls])[:-1]), m
        assert all(n in (32, 128, 512, 2048) for _, n in calls), m
        assert 0 <= sum(n for _, n in calls) - m < 32, m
    monkeypatch.setattr(_refine, "MOST_PROBES", 128)
    assert [n for _, n in _refine._count_calls(300)] == [128, 128, 32, 32]
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 8, seed=4)  # 10 cameras
    d, counts_of = _refine.derived(pm), _refine._Counts.of(pm)
    rows = _refine._core.host_camera_rows(jax.tree.map(np.asarray, cams), np.zeros(10, np.float32), d.exponent)
    rng = np.random.default_rng(3)
    which = rng.integers(0, 10, 300)
    taus = np.float32(10.0) ** rng.uniform(-2, 1.5, 300).astype(np.float32)
    taus[:5] = [0, np.inf, 0, 1, np.inf]
    got = _refine._counts_at(d.core, rows, which, taus.view(np.int32).astype(np.int64), pmjax.ALL_TESTS, False,
                             counts_of)
    for q in range(0, 300, 3):
        r = pmjax.refine(pm, index_camera(cams, int(which[q])), taus[q])
        assert (got[0][q], got[1][q], got[2][q]) == (int(r.n_faces), int(r.n_vertices), int(r.n_executed)), q


@pytest.mark.slow
def test_chunks_pooled_for_the_counts_give_the_same_answers(built, monkeypatch):
    """The exact counts of several chunks run together: small chunks, each
    alone, pooled two by two or all at once, give the answers of one chunk
    for all cameras, which are faces_for_budget's."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _views(data, 70, seed=12)  # 72 cameras: 3 chunks of 32, pooled 2 + 1
    budgets = _columns(pm, cams, np.array(_budgets(pm, cams)))[:, :4]
    one = pmjax.faces_for_budget_batch(pm, cams, budgets, method="front", chunk=96)
    for pooled in (16, 64, 4096):
        monkeypatch.setattr(_refine, "POOLED", pooled)
        got = pmjax.faces_for_budget_batch(pm, cams, budgets, method="front", chunk=32)
        for key in one:
            assert one[key].tobytes() == got[key].tobytes(), (pooled, key)
    for k in range(0, 72, 7):
        for j in range(budgets.shape[1]):
            tau, faces = pmjax.faces_for_budget(pm, index_camera(cams, k), int(budgets[k, j]), method="front")
            assert np.float32(one["tau"][k, j]).tobytes() == np.float32(tau).tobytes(), (k, j)
            assert one["faces"][k, j] == faces, (k, j)


@pytest.mark.slow
def test_budgets_between_tied_switch_tolerances(data_path):
    """A mirrored cow seen from its plane of symmetry: mirrored pcols switch
    at the same tolerance, so the count drops by both at once. A budget
    between the counts on either side of such a tie is met just above it
    (the next float32), as faces_for_budget finds it."""
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cow.ply"))
    v = (v - v.mean(0)).astype(np.float32)
    v[:, 0] -= v[:, 0].min() - 0.05 * np.ptp(v[:, 0])  # x > 0: the mirror image apart
    from pmjax.builders import BuildOptions, build_pm

    mirrored = np.concatenate([v, v * np.array([-1, 1, 1], np.float32)])
    pm = pmjax.ProgressiveMesh.from_data(build_pm(mirrored, np.concatenate([f, f[:, ::-1] + len(v)]),
                                                  BuildOptions()))
    r = float(np.linalg.norm(np.ptp(mirrored, 0)))
    eyes = [[0, 0.2 * r, 1.5 * r], [0, -0.5 * r, 0.6 * r], [0, 0.1 * r, 8 * r]]
    cams = stack_cameras([pmjax.look_at(np.array(e, np.float32), np.zeros(3, np.float32)) for e in eyes])
    budgets, above = [], []
    for k in range(len(eyes)):
        eps = np.asarray(pmjax.critical_tolerances(pm, index_camera(cams, k)))
        value, count = np.unique(eps[np.isfinite(eps) & (eps > 0)], return_counts=True)
        tied = value[count > 1][::max(1, int(np.sum(count > 1)) // 4)][:4]
        assert len(tied) == 4, k
        up = np.nextafter(tied, np.float32(np.inf)).astype(np.float32)
        faces_up, faces_at = (np.array([int(pmjax.refine(pm, index_camera(cams, k), t).n_faces) for t in taus])
                              for taus in (up, tied))
        assert np.all(faces_at >= faces_up + 2), k  # both pcols of the tie at once
        budgets.append(faces_up + 1)
        above.append(up)
    budgets = np.array(budgets)
    got = pmjax.faces_for_budget_batch(pm, cams, budgets, method="front")
    assert got["tau"].tobytes() == np.array(above, np.float32).tobytes()
    _assert_same(pm, cams, [budgets[:, j] for j in range(4)], _column_of(got, range(4)))
