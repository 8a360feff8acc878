"""faces_for_budget_batch on camera paths (``path=True``): guesses seeded along
the path and the first exact counts through the coherent path engine.

Every answer must be faces_for_budget's, bit for bit: the dense sort of the
critical tolerances, and the counts of a refine at the answer.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

import pmjax
from pmjax import _refine
from pmjax._camera import index_camera, stack_cameras
from pmjax._predicate import ALL_TESTS
from pmjax.engines import _core, _dense
from pmjax.engines._tables import derived

pytestmark = pytest.mark.core


def _paths(data, n, seed):
    """An orbit, a fly-through past and into the model, and the orbit with
    its eyes and targets jittered frame to frame (a shaky hand-held path)."""
    v0 = data.vertices[: data.n_original_vertices]
    c, r = v0.mean(0), float(np.linalg.norm(np.ptp(v0, 0)))
    orbit = pmjax.standard_orbit(v0, n)
    fly = pmjax.fly_through([(c + [2 * r, 0.3 * r, 0], c), (c + [0.2 * r, 0.1 * r, 0.1 * r], c),
                             (c + [-0.3 * r, 0, 0.4 * r], c + [-r, 0, 0])], n)
    rng = np.random.default_rng(seed)
    eyes, targets = np.asarray(orbit.eye, float), np.tile(c, (n, 1))
    jittered = stack_cameras([pmjax.look_at(e + rng.normal(0, 0.02 * r, 3), t + rng.normal(0, 0.02 * r, 3))
                              for e, t in zip(eyes, targets)])
    return {"orbit": orbit, "fly": fly, "jittered": jittered}


def _budgets(pm, cams):
    """Budgets across the range: below the base mesh, at it, between, at and
    above the finest view."""
    full = pm.n_faces
    base = full - int(np.sum(np.asarray(pm.kills)))
    some = pmjax.refine_batch(pm, cams, 1.0)["faces"]
    return sorted({0, max(base - 1, 0), base, int(np.median(some)), int(some.min()), full, full + 7})


def _assert_dense(pm, cams, budget, out):
    """``out`` (a path's answers) against the dense sort per frame and the
    counts of a refine at the answer."""
    for k in range(len(out["tau"])):
        cam = index_camera(cams, k)
        b = int(np.broadcast_to(budget, (len(out["tau"]),))[k])
        tau, faces = _dense.budget_sort(pm, pmjax.critical_tolerances(pm, cam), b)
        assert np.float32(out["tau"][k]).tobytes() == np.float32(tau).tobytes(), (k, b)
        assert out["faces"][k] == faces, (k, b)
        r = pmjax.refine(pm, cam, out["tau"][k])
        assert (out["faces"][k], out["vertices"][k], out["executed_count"][k]) == \
            (int(r.n_faces), int(r.n_vertices), int(r.n_executed)), (k, b)


def _assert_same(a, b, why):
    for key in a:
        assert a[key].tobytes() == b[key].tobytes(), (why, key)


@pytest.mark.slow
def test_paths_equal_the_dense_sort_on_the_cow(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    for name, cams in _paths(data, 20, seed=1).items():
        budgets = _budgets(pm, cams)
        for b in budgets:
            out = pmjax.faces_for_budget_batch(pm, cams, b, path=True, chunk=32, method="front")
            _assert_dense(pm, cams, b, out)
        # A budget per frame, changing along the path.
        per_frame = np.resize(np.array(budgets), 20)
        out = pmjax.faces_for_budget_batch(pm, cams, per_frame, path=True, method="front")
        _assert_dense(pm, cams, per_frame, out)


@pytest.mark.slow
def test_wrong_guesses_on_a_path_still_give_the_exact_answer(built, monkeypatch):
    """Any guess, for the sampled frames or the others, far off in either
    direction, at 0 or past inf, gives the same answers."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _paths(data, 20, seed=2)["jittered"]
    budgets = _budgets(pm, cams)
    want = {b: pmjax.faces_for_budget_batch(pm, cams, b, method="front") for b in budgets[1::2]}
    rng = np.random.default_rng(0)
    original = _refine._core_guesses
    for bad in (lambda g: g * 0, lambda g: g * 0 + 0x7F800001, lambda g: g + rng.integers(-10 ** 7, 10 ** 7, g.shape),
                lambda g: g - 1, lambda g: rng.integers(0, 0x7F800002, g.shape)):
        monkeypatch.setattr(_refine, "_core_guesses", lambda *a, **k: tuple(
            bad(np.asarray(g, np.int64)).astype(np.int32) for g in original(*a, **k)))
        for b, out in want.items():
            _assert_same(out, pmjax.faces_for_budget_batch(pm, cams, b, path=True, method="front"), b)
    monkeypatch.setattr(_refine, "_core_guesses", original)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["bunny.ply", "terrain_gcanyon.ply"])
def test_paths_equal_the_dense_sort(built, name):
    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    for kind, cams in _paths(data, 36, seed=len(name)).items():
        for b in _budgets(pm, cams):
            out = pmjax.faces_for_budget_batch(pm, cams, b, path=True)
            _assert_dense(pm, cams, b, out)
            _assert_same(out, pmjax.faces_for_budget_batch(pm, cams, b), (kind, b))


def test_a_path_gives_the_batch_answers(built):
    """Along an orbit, a budget below the base mesh, one between and one above
    the full mesh: the answers of the cameras as a batch."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _paths(data, 20, seed=3)["orbit"]
    budgets = _budgets(pm, cams)
    for b in (budgets[1], budgets[3], budgets[-1]):
        _assert_same(pmjax.faces_for_budget_batch(pm, cams, b, method="front"),
                     pmjax.faces_for_budget_batch(pm, cams, b, path=True, method="front"), b)


def test_evaluation_runs_paths_as_paths_with_the_same_answers(built, tmp_path, monkeypatch):
    """A budget job on an orbit sends the orbit's frames as one path, in
    order, and its rows are faces_for_budget's."""
    pytest.importorskip("pyarrow")
    import pyarrow.dataset as ds

    data = built("cow.ply")
    model = str(tmp_path / "cow.pmz")
    pmjax.save_pm(data, model)
    pm = pmjax.load(model)
    seen = []
    original = _refine._path_budgets
    monkeypatch.setattr(_refine, "_path_budgets", lambda pm_, host, *a: seen.append(len(host.eye)) or
                        original(pm_, host, *a))
    pmjax.evaluate([model], ["orbit:40"], str(tmp_path / "b"), budgets=[600], method="front",
                   compile_cache=None, progress=False)
    assert seen and set(seen) == {40}
    table = ds.dataset(str(tmp_path / "b"), format="parquet").to_table()
    order = np.argsort(table.column("camera").to_numpy())
    got = {c: table.column(c).to_numpy()[order] for c in ("tau", "faces", "executed")}
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 40)
    want = pmjax.faces_for_budget_batch(pm, cams, 600, method="front")
    assert got["tau"].astype(np.float32).tobytes() == want["tau"].tobytes()
    assert np.array_equal(got["faces"], want["faces"])
    assert np.array_equal(got["executed"], want["executed_count"])


@pytest.mark.parametrize("name", ["cow.ply", "terrain_gcanyon.ply"])
def test_fat_camera_decisions_hold_with_a_tolerance_per_frame(built, name):
    """A word's frames at their own tolerances (a budget's, along a path):
    where the fat camera says "whole", every frame's subtree collapses under
    the float32 predicate at its tolerance; where it says "no", no frame's
    predicate collapses the pcol. Along the orbit it still decides pcols."""
    import jax.numpy as jnp

    from pmjax.engines import _core
    from pmjax.engines._tables import derived

    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    d = derived(pm)
    kids, table = d.children, d.jax.table
    v0 = data.vertices[: data.n_original_vertices]
    orbit = pmjax.standard_orbit(v0, 240)
    rng = np.random.default_rng(5)
    for start in (0, 96):
        word = index_camera(orbit, np.arange(start, start + 16))
        for taus in (np.float32(1.0) + np.float32(0.05) * rng.random(16, np.float32),
                     np.geomspace(0.3, 3.0, 16).astype(np.float32)):
            views = _core.views(_core.camera_rows(word, taus, d.exponent), word.orthographic)
            fat = _core.fat_cameras(views[None])[0]
            got = np.asarray(_core.decide_fat_all(table, views, fat, _core.flags_of(pmjax.ALL_TESTS, False)))
            assert np.any(got == _core.FAT_NO) and np.any(got == _core.FAT_WHOLE), (start, taus[0])
            for f in range(16):
                want = np.asarray(pmjax.collapse_mask(pm.attributes, index_camera(word, f), jnp.float32(taus[f]),
                                                      pmjax.ALL_TESTS))
                assert not np.any(want[got == _core.FAT_NO]), (start, f)
                all_below = want.copy()
                for lo, hi in zip(pm.batch_offsets[:-1], pm.batch_offsets[1:]):
                    for k in kids[lo:hi].T:
                        has = k >= 0
                        all_below[lo:hi][has] &= all_below[k[has]]
                assert np.all(all_below[got == _core.FAT_WHOLE]), (start, f)


def test_several_budgets_on_an_orbit_equal_one_at_a_time(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _paths(data, 20, seed=5)["orbit"]
    budgets = np.array(_budgets(pm, cams))[[1, 3, 5]]
    got = pmjax.faces_for_budget_batch(pm, cams, np.tile(budgets, (20, 1)), path=True, method="front")
    for j, b in enumerate(budgets):
        _assert_same({k: v[:, j].copy() for k, v in got.items()},
                     pmjax.faces_for_budget_batch(pm, cams, int(b), path=True, method="front"), j)


@pytest.mark.slow
def test_several_budgets_on_paths_equal_one_at_a_time(built):
    """A ``[K, B]`` budget along an orbit, a fly-through into the model and a
    jittered orbit (one guess traversal per frame for its budgets, each
    budget's counts through the path engine): column by column the answers
    of one budget at a time, on the path and as a batch."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    for name, cams in _paths(data, 20, seed=4).items():
        budgets = np.array(_budgets(pm, cams))
        mixed = np.stack([np.roll(budgets, k) for k in range(20)])  # budgets mixed across the columns
        got = pmjax.faces_for_budget_batch(pm, cams, mixed, path=True, method="front")
        for j in range(mixed.shape[1]):
            for path in (True, False):
                one = pmjax.faces_for_budget_batch(pm, cams, mixed[:, j], path=path, method="front")
                _assert_same({k: v[:, j].copy() for k, v in got.items()}, one, (name, j, path))


@pytest.mark.slow
def test_several_budgets_on_a_path_equal_the_dense_sort(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _paths(data, 20, seed=6)["fly"]
    budgets = np.array(_budgets(pm, cams))
    got = pmjax.faces_for_budget_batch(pm, cams, np.tile(budgets, (20, 1)), path=True, method="front")
    for j, b in enumerate(budgets):
        _assert_dense(pm, cams, int(b), {k: v[:, j] for k, v in got.items()})


@pytest.mark.slow
def test_several_budgets_with_wrong_path_guesses_give_the_exact_answers(built, monkeypatch):
    """Guesses far off (the sampled frames' too, so the other frames start
    their traversals at bad tolerances) still give the exact answers."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _paths(data, 20, seed=7)["jittered"]
    budgets = np.tile(np.array(_budgets(pm, cams)[1:5]), (20, 1))
    want = pmjax.faces_for_budget_batch(pm, cams, budgets, method="front")
    rng = np.random.default_rng(2)
    original = _refine._core_guesses
    for bad in (lambda g: g * 0, lambda g: g * 0 + 0x7F800001, lambda g: g + rng.integers(-10 ** 6, 10 ** 6, g.shape),
                lambda g: rng.integers(0, 0x7F800002, g.shape)):
        monkeypatch.setattr(_refine, "_core_guesses", lambda *a, **k: tuple(
            bad(np.asarray(g, np.int64)).astype(np.int32) for g in original(*a, **k)))
        _assert_same(want, pmjax.faces_for_budget_batch(pm, cams, budgets, path=True, method="front"), "bad")
    monkeypatch.setattr(_refine, "_core_guesses", original)


def _assert_one_at_a_time(pm, cams, budgets, got):
    """``got`` (a path's ``[K, B]`` answers) against ``faces_for_budget`` of
    each frame and budget alone, and the counts of a refine at the answer."""
    for k in range(budgets.shape[0]):
        cam = index_camera(cams, k)
        for j in range(budgets.shape[1]):
            tau, faces = pmjax.faces_for_budget(pm, cam, int(budgets[k, j]), method="front")
            assert np.float32(got["tau"][k, j]).tobytes() == np.float32(tau).tobytes(), (k, j)
            assert got["faces"][k, j] == int(faces), (k, j)
            r = pmjax.refine(pm, cam, got["tau"][k, j], method="front")
            assert (got["vertices"][k, j], got["executed_count"][k, j]) == (int(r.n_vertices),
                                                                           int(r.n_executed)), (k, j)


@pytest.mark.parametrize("kind", ["orbit", "fly"])
def test_word_guessed_paths_equal_faces_for_budget_per_frame(built, kind):
    """An orbit and a fly-through into the model of 40 frames (three words,
    sampled frames between them), several budgets per frame (below the base
    mesh, at it, between, above the full mesh): every answer is
    faces_for_budget's for that frame alone."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _paths(data, 40, seed=8)[kind]
    budgets = np.tile(np.array(_budgets(pm, cams)), (40, 1))
    got = pmjax.faces_for_budget_batch(pm, cams, budgets, path=True, method="front")
    _assert_one_at_a_time(pm, cams, budgets, got)


@pytest.mark.parametrize("kind", ["orbit", "fly"])
def test_word_guesses_equal_one_camera_guesses(built, kind, simd):
    """A word's frames traversed together at their own tolerances guess what
    each frame's own traversal at that tolerance guesses first (a word has
    no second guess: its alt is its guess); a frame whose answers lie below
    its tolerance gets -1 where its own traversal would have to go lower."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _paths(data, 48, seed=9)[kind]
    host = jax.tree.map(np.asarray, cams)
    d, counts_of = derived(pm), _refine._Counts.of(pm)
    budgets = np.tile(np.array(_budgets(pm, cams)[2:5]), (48, 1)).astype(np.int64)
    frames = np.arange(48)
    first, _ = _refine._guesses(d, counts_of, host, frames, np.zeros(48, np.float32), budgets, ALL_TESTS, 64)
    answer = first[:, np.argmax(budgets[0])].view(np.float32)
    # Below the answers (a traversal finds them at once), and above them on
    # every third frame (where the answers lie below: -1).
    start = np.where(frames % 3 == 0, 2 * answer, 0.9 * answer).astype(np.float32)
    words = _refine._word_guesses(d, counts_of, host, start, budgets, ALL_TESTS)
    alone = _refine._guesses(d, counts_of, host, frames, start, budgets, ALL_TESTS, 64)
    left = (words[0] == -1).all(axis=1)
    assert left[frames % 3 == 0].any() and not left[frames % 3 != 0].any()
    np.testing.assert_array_equal(words[0][~left], alone[0][~left])
    np.testing.assert_array_equal(words[1], words[0])


def test_orthographic_word_guesses_equal_one_camera_guesses(built, simd):
    """An orthographic orbit: a word's frames (the screen test's terms of
    the orthographic projection, all frames of a row at once) guess what
    each frame's own traversal at its tolerance guesses first."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    v0 = data.vertices[: data.n_original_vertices]
    c, r = v0.mean(0), float(np.linalg.norm(np.ptp(v0, 0)))
    angles = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    cams = stack_cameras([pmjax.look_at(c + r * np.array([np.cos(a), 0.3, np.sin(a)]), c, orthographic=True,
                                        ortho_height=0.6 * r, near=1e-3, far=10 * r) for a in angles])
    host = jax.tree.map(np.asarray, cams)
    d, counts_of = derived(pm), _refine._Counts.of(pm)
    budgets = np.tile(np.array(_budgets(pm, cams)[2:5]), (32, 1)).astype(np.int64)
    frames = np.arange(32)
    first, _ = _refine._guesses(d, counts_of, host, frames, np.zeros(32, np.float32), budgets, ALL_TESTS, 32)
    start = (0.9 * first[:, np.argmax(budgets[0])].view(np.float32)).astype(np.float32)
    words = _refine._word_guesses(d, counts_of, host, start, budgets, ALL_TESTS)
    alone = _refine._guesses(d, counts_of, host, frames, start, budgets, ALL_TESTS, 32)
    assert (words[0] > 0).all()
    np.testing.assert_array_equal(words[0], alone[0])


def test_word_frames_without_a_budget_to_meet_leave_the_others_guesses_alone(built, simd):
    """A word whose frames alternate between budgets to meet and budgets all
    below the base mesh (frames the word's tally leaves out): the latter
    guess inf, the others what each frame's own traversal at its tolerance
    guesses first."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _paths(data, 32, seed=5)["orbit"]
    host = jax.tree.map(np.asarray, cams)
    d, counts_of = derived(pm), _refine._Counts.of(pm)
    wanted = np.array(_budgets(pm, cams)[2:5], np.int64)
    frames = np.arange(32)
    met = frames % 2 == 0
    budgets = np.where(met[:, None], wanted[None, :], 0).astype(np.int64)
    first, _ = _refine._guesses(d, counts_of, host, frames, np.zeros(32, np.float32),
                                np.tile(wanted, (32, 1)), ALL_TESTS, 32)
    start = (0.9 * first[:, np.argmax(wanted)].view(np.float32)).astype(np.float32)
    words = _refine._word_guesses(d, counts_of, host, start, budgets, ALL_TESTS)
    alone = _refine._guesses(d, counts_of, host, frames, start, budgets, ALL_TESTS, 32)
    assert (words[0][~met] == _refine._INF_BITS + 1).all()
    assert (words[0][met] > 0).all()
    np.testing.assert_array_equal(words[0][met], alone[0][met])


@pytest.mark.parametrize("kind", ["orbit", "fly"])
def test_path_guesses_are_mostly_the_answers(built, monkeypatch, kind):
    """The guesses a path's answers are confirmed from (sampled frames alone,
    the others word by word) are the exact answers for most frames and
    budgets, and every answer is faces_for_budget's."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    K = 48
    cams = _paths(data, K, seed=10)[kind]
    budgets = np.tile(np.array(_budgets(pm, cams)[3:5]), (K, 1))
    seen = []
    original = _refine._exact_from_guess
    monkeypatch.setattr(_refine, "_exact_from_guess", lambda *a, **k: seen.append(a[3].copy()) or original(*a, **k))
    got = pmjax.faces_for_budget_batch(pm, cams, budgets, path=True, method="front")
    _assert_one_at_a_time(pm, cams, budgets, got)
    # The guesses come budget by budget, each the path's frames in order.
    guess = seen[0].reshape(budgets.shape[1], K).T.astype(np.int64)
    exact = np.where(np.isinf(got["tau"]), _refine._INF_BITS + 1, got["tau"].view(np.int32)).astype(np.int64)
    in_words = np.arange(K) % _refine.PATH_SAMPLE != 0
    assert (guess[in_words] == exact[in_words]).mean() >= 0.75, (guess - exact)[in_words]


def test_frames_left_to_their_own_traversal_still_get_the_exact_answers(built, monkeypatch):
    """With every frame's start above its answers, the word guesses give -1
    and the frames are guessed alone: the answers stay faces_for_budget's."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = _paths(data, 36, seed=10)["fly"]
    budgets = np.tile(np.array(_budgets(pm, cams)[1:5]), (36, 1))
    seen = []
    original = _refine._word_guesses
    monkeypatch.setattr(_refine, "PATH_START", 4.0)
    monkeypatch.setattr(_refine, "_word_guesses", lambda *a: seen.append(original(*a)) or seen[-1])
    got = pmjax.faces_for_budget_batch(pm, cams, budgets, path=True, method="front")
    assert seen and any((g < 0).any() for g, _ in seen)
    _assert_one_at_a_time(pm, cams, budgets, got)


def test_frames_past_the_last_sampled_frame_get_the_exact_answers(built, monkeypatch):
    """Only every PATH_SAMPLE-th frame is guessed alone first (not the last
    frame); the frames after the last sampled one, here closing in on the
    model, start where that frame predicts: their answers stay
    faces_for_budget's."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    v0 = data.vertices[: data.n_original_vertices]
    c, r = v0.mean(0), float(np.linalg.norm(np.ptp(v0, 0)))
    cams = pmjax.fly_through([(c + [2 * r, 0.3 * r, 0], c), (c + [1.5 * r, 0.2 * r, 0], c),
                              (c + [0.3 * r, 0.1 * r, 0.1 * r], c)], 44)
    budgets = np.tile(np.array(_budgets(pm, cams)[2:5]), (44, 1))
    calls = []
    original = _refine._guesses
    monkeypatch.setattr(_refine, "_guesses", lambda d, c_, h, frames, *a: calls.append(frames.copy()) or
                        original(d, c_, h, frames, *a))
    got = pmjax.faces_for_budget_batch(pm, cams, budgets, path=True, method="front")
    np.testing.assert_array_equal(calls[0], np.arange(0, 44, _refine.PATH_SAMPLE))
    _assert_one_at_a_time(pm, cams, budgets, got)


def test_guesses_far_off_are_guessed_again_alone(built, monkeypatch):
    """Word guesses far above the answers (as an unsure decision read as
    "keep" makes them) are not settled by the patterns next to them: their
    frames are guessed again alone, and every answer stays
    faces_for_budget's."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    K = 40
    cams = _paths(data, K, seed=11)["fly"]
    budgets = np.tile(np.array(_budgets(pm, cams)[2:5]), (K, 1))
    original_words, original = _refine._word_guesses, _refine._guesses
    far = np.arange(K) % 5 == 1

    def words(*a):
        g, alt = original_words(*a)
        g = np.where(far[:, None] & (g > 0) & (g < _refine._INF_BITS), g + 5000, g).astype(np.int32)
        return g, g.copy()

    calls = []
    monkeypatch.setattr(_refine, "_word_guesses", words)
    monkeypatch.setattr(_refine, "_guesses", lambda d, c_, h, frames, *a: calls.append(frames.copy()) or
                        original(d, c_, h, frames, *a))
    got = pmjax.faces_for_budget_batch(pm, cams, budgets, path=True, method="front")
    _assert_one_at_a_time(pm, cams, budgets, got)
    # The sampled frames first, the frames without a word guess next, and
    # last only frames whose word guesses were moved.
    np.testing.assert_array_equal(calls[0], np.arange(0, K, _refine.PATH_SAMPLE))
    assert len(calls) == 3 and len(calls[-1]) and far[calls[-1]].all(), calls


@pytest.mark.parametrize("kind", ["orbit", "fly"])
def test_two_tolerances_per_frame_in_one_pass_count_each_frame_alone(built, kind):
    """A path with each frame twice in a row at its own tolerances, jumping
    from lane to lane (an answer and the pattern below it, 0, inf, far
    apart), as the confirming counts run: every lane's counts are those of
    a refine of that frame at that tolerance."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    K = 24
    cams = _paths(data, K, seed=12)[kind]
    host = jax.tree.map(np.asarray, cams)
    d, counts_of = derived(pm), _refine._Counts.of(pm)
    rng = np.random.default_rng(3)
    tau = np.float32(rng.choice([0.3, 0.7, 1.0, 4.0], K)).astype(np.float32)
    tau[::7], tau[3::7] = 0.0, np.inf
    below = np.where(np.isfinite(tau) & (tau > 0), (tau.view(np.int32) - 1).view(np.float32), tau)
    rows = np.repeat(_core.host_camera_rows(host, np.zeros(K, np.float32), d.exponent), 2, axis=0)
    rows[0::2, -1], rows[1::2, -1] = tau, below
    counted = _refine._word_set_counts(d, counts_of, rows, rows[None, :, -1].view(np.int32), ALL_TESTS,
                                       host.orthographic)[0]
    for k in range(2 * K):
        r = pmjax.refine(pm, index_camera(cams, k // 2), float(rows[k, -1]), method="front")
        assert tuple(counted[k]) == (int(r.n_faces), int(r.n_vertices), int(r.n_executed)), k


# -- word sets: the confirming counts' words at several tolerances in one pass --


def _set_tolerances(K, rng):
    """Per frame a tolerance that jumps about, with 0 and inf among them
    except in the second word (frames 16 to 31: all finite and positive, so
    that its frames share a fat camera), then the pattern just below it (0
    and inf kept)."""
    tau = rng.choice(np.float32([0.3, 0.7, 1.0, 4.0]), K).astype(np.float32)
    tau[::7], tau[3::7] = 0.0, np.inf
    F = _core.FRAMES
    tau[F:2 * F] = rng.choice(np.float32([0.3, 0.7, 1.0, 4.0]), F)
    below = np.where(np.isfinite(tau) & (tau > 0), (tau.view(np.int32) - 1).view(np.float32), tau)
    return tau, below.astype(np.float32)


def _set_bits(tau):
    return tau.view(np.int32).astype(np.int64)


@pytest.mark.parametrize("kind", ["orbit", "fly", "jittered"])
def test_word_sets_count_each_frame_at_each_tolerance(built, kind, simd):
    """Two sets (a tolerance and the pattern below it) and three (with a
    coarser one, and one set at the first's tolerance: a tie) counted in one
    pass: each (frame, tolerance) as a refine counts it."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    K = 40  # not a whole number of words: the last word repeats its last frame
    cams = _paths(data, K, seed=21)[kind]
    host = jax.tree.map(np.asarray, cams)
    d, counts_of = derived(pm), _refine._Counts.of(pm)
    rows = _core.host_camera_rows(host, np.zeros(K, np.float32), d.exponent)
    tau, below = _set_tolerances(K, np.random.default_rng(4))
    coarse = np.where(np.isfinite(tau), 3 * tau, tau).astype(np.float32)
    for taus in ([tau, below], [below, coarse, tau, tau]):
        got = _refine._word_set_counts(d, counts_of, rows, np.stack([_set_bits(t) for t in taus]), ALL_TESTS,
                                       host.orthographic)
        for t, at in enumerate(taus):
            for k in range(K):
                r = pmjax.refine(pm, index_camera(cams, k), float(at[k]), method="front")
                assert tuple(got[t, k]) == (int(r.n_faces), int(r.n_vertices), int(r.n_executed)), (t, k)


@pytest.mark.parametrize("name", ["bunny.ply", "terrain_gcanyon.ply"])
def test_word_sets_give_the_counts_of_each_word_alone(built, name):
    """The core's counts of a set of words equal those of each of its words
    traversed alone (pcols that did not run, the faces they keep), for sets
    whose tolerances differ by one pattern (the terrain's grid has many pcols
    whose switches tie) and by a factor, and for sets whose frames differ
    (traversed word by word)."""
    data = built(name)
    pm = pmjax.ProgressiveMesh.from_data(data)
    K = 32
    paths = _paths(data, K, seed=8)
    d = derived(pm)
    rng = np.random.default_rng(6)
    F = _core.FRAMES
    for kind, other in (("orbit", "orbit"), ("fly", "fly"), ("orbit", "fly")):
        tau, below = _set_tolerances(K, rng)
        sets = [(kind, tau), (other, below), (kind, (2 * tau).astype(np.float32))]
        rows = [_core.host_camera_rows(jax.tree.map(np.asarray, paths[p]), t, d.exponent) for p, t in sets]
        # Word j's set: its frames in each set in turn.
        T = len(sets)
        grouped = np.stack([r.reshape(K // F, F, -1) for r in rows], axis=1).reshape(K * T, -1)
        together, at_once = jax.jit(lambda a, b, r: _core.refine_words(a, b, r, ALL_TESTS, False, False, sets=T)[:2])(
            d.core_words, d.core, grouped)
        together = np.asarray(together).reshape(K // F, T, F, 4)
        # The second word's frames are all finite: where its sets share one
        # fat camera, it decides slots for every frame at once.
        if kind == other:
            assert (np.asarray(at_once).reshape(K // F, T)[1] > 0).all(), (kind, np.asarray(at_once))
        for t in range(T):
            alone = np.asarray(_refine._core_word_counts(d.core_words, d.core, rows[t], ALL_TESTS, False))
            np.testing.assert_array_equal(together[:, t].reshape(K, 4)[:, 1:3], alone[:, 1:3], err_msg=(kind, t))


def test_word_sets_refuse_lists_and_sets_that_do_not_divide_the_words(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    d = derived(pm)
    cams = _paths(data, 48, seed=1)["orbit"]
    rows = _core.host_camera_rows(jax.tree.map(np.asarray, cams), np.ones(48, np.float32), d.exponent)
    with pytest.raises(ValueError, match="no lists"):
        _core.refine_words(d.core_words, d.core, rows, ALL_TESTS, False, True, sets=3)
    with pytest.raises(Exception, match="divide"):
        np.asarray(_refine._core_word_counts(d.core_words, d.core, rows, ALL_TESTS, False, sets=2))


def test_path_budgets_confirm_through_word_sets(built, monkeypatch):
    """The confirming counts of a path's budgets (several per frame, below
    the base mesh and above F among them) run as word sets, one pass per
    budget with both patterns, and give faces_for_budget_batch's answers
    without a path."""
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    K = 48
    cams = _paths(data, K, seed=3)["fly"]
    full = pm.n_faces
    base = full - int(np.sum(np.asarray(pm.kills)))
    some = int(np.median(pmjax.refine_batch(pm, cams, 1.0)["faces"]))
    budgets = np.tile(np.array([max(base - 1, 0), some, full + 5]), (K, 1))
    shapes = []
    original = _refine._word_set_counts
    monkeypatch.setattr(_refine, "_word_set_counts",
                        lambda d, c, rows, bits, *a: shapes.append(bits.shape) or original(d, c, rows, bits, *a))
    got = pmjax.faces_for_budget_batch(pm, cams, budgets, path=True, method="front")
    # One set of both patterns per budget; then any probes, one tolerance each.
    assert shapes[:3] == [(2, K)] * 3 and all(t == 1 for t, _ in shapes[3:]), shapes
    want = pmjax.faces_for_budget_batch(pm, cams, budgets, method="front")
    for key in want:
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)
