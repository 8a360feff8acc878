"""Coherent camera paths: every frame exactly as pmjax.refine gives it alone."""

import equinox as eqx
import jax
import numpy as np
import pytest

import pmjax
from pmjax import _path, engines
from pmjax.engines import _front_jax
from pmjax.engines._choose import select
from pmjax._camera import index_camera, stack_cameras


@pytest.fixture(scope="module", autouse=True)
def release_compiled_kernels():
    """The word traversal's programs are large: release them after this module
    (see tests/test_front.py)."""
    yield
    _MESHES.clear()
    jax.clear_caches()


_MESHES = {}


def model(built, name, pair_distance=0.0):
    """One device mesh per model for the module: its traversal buffers, once
    fitted, serve every test (each new buffer set is a compilation)."""
    key = (name, pair_distance)
    if key not in _MESHES:
        data = built(name, pair_distance)
        _MESHES[key] = data, pmjax.ProgressiveMesh.from_data(data)
    return _MESHES[key]


def originals(data):
    return data.vertices[: data.n_original_vertices]


def assert_frame_equal(r, cam, tau, pm, where, full=False):
    want = pmjax.refine(pm, cam, tau, method="dense")
    for field in ("n_faces", "n_vertices", "n_executed"):
        assert int(getattr(r, field)) == int(getattr(want, field)), (where, field)
    assert np.array_equal(np.asarray(r.executed), np.asarray(want.executed)), where
    if full:
        assert np.array_equal(np.asarray(r.active), np.asarray(want.active)), where
        assert np.array_equal(np.asarray(r.rep), np.asarray(want.rep)), where


def walk(data, n, seed, step=0.02, cuts=()):
    """A random path of small steps round the model, with jumps at ``cuts``."""
    v0 = originals(data)
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    rng = np.random.default_rng(seed)
    eye = c + 1.5 * r * np.array([0.3, 0.4, 1.0])
    eyes = []
    for i in range(n):
        if i in cuts:
            d = rng.normal(size=3)
            eye = c + rng.uniform(0.3, 3.0) * r * d / np.linalg.norm(d)
        eye = eye + step * r * rng.normal(size=3)
        eyes.append(eye)
    return stack_cameras([pmjax.look_at(e, c + 0.05 * r * rng.normal(size=3)) for e in eyes])


def paths_of(data, kinds):
    """Paths of 32 frames (one word: one compiled shape for the whole module)."""
    v0 = originals(data)
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    make = {
        "orbit": lambda: pmjax.standard_orbit(v0, 32),
        # Enters the bounding sphere and passes through the model.
        "fly": lambda: pmjax.fly_through([(c + [0, 0, 2 * r], c), (c + [0, 0, 0.1 * r], c), (c - [0, 0, 2 * r], c)],
                                         32),
        "walk with cuts": lambda: walk(data, 32, seed=len(kinds), cuts=(10, 11, 25)),
    }
    return {k: make[k]() for k in kinds}


@pytest.mark.parametrize("name, pair_distance, kinds", [
    ("cow.ply", 0.0, ("orbit", "fly", "walk with cuts")),
    ("cessna.ply", 0.02, ("walk with cuts",)),  # parts merged by virtual pairs
    ("terrain_gcanyon.ply", 0.0, ("fly",)),
])
def test_path_equals_refine_per_frame(built, name, pair_distance, kinds):
    data, pm = model(built, name, pair_distance)
    for label, cams in paths_of(data, kinds).items():
        got = list(pmjax.refine_path(pm, cams, 1.0))
        assert len(got) == pmjax.camera_count(cams)
        for i, res in enumerate(got):
            assert_frame_equal(res, index_camera(cams, i), 1.0, pm, (label, i), full=i % 9 == 0)
        counts = pmjax.path_counts(pm, cams, 1.0)
        assert counts["faces"].tolist() == [int(x.n_faces) for x in got]
        assert counts["executed_count"].tolist() == [int(x.n_executed) for x in got]


def test_tau_along_the_path_budgets_and_orthographic(built):
    data, pm = model(built, "cow.ply")
    v0 = originals(data)
    cams = pmjax.standard_orbit(v0, 32)
    taus = np.geomspace(1e-3, 64, 32).astype(np.float32)
    taus[7] = 0.0
    for i, res in enumerate(pmjax.refine_path(pm, cams, taus)):
        assert_frame_equal(res, index_camera(cams, i), taus[i], pm, i)
    budgets = np.linspace(100, 3000, 32).astype(int)
    counts = pmjax.path_counts(pm, cams, budget=budgets)
    for i in range(0, 32, 10):
        tau, faces = pmjax.faces_for_budget(pm, index_camera(cams, i), int(budgets[i]))
        assert counts["tau"][i] == tau and counts["faces"][i] == faces, i
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    ortho = stack_cameras([pmjax.look_at(c + r * np.array([np.cos(a), 0.3, np.sin(a)]), c, orthographic=True,
                                         ortho_height=h * r, near=1e-3, far=10 * r)
                           for a, h in zip(np.linspace(0, 2, 32), np.linspace(0.3, 2.0, 32))])
    for i, res in enumerate(pmjax.refine_path(pm, ortho, 2.0)):
        assert_frame_equal(res, index_camera(ortho, i), 2.0, pm, ("ortho", i))


def test_words_give_every_frame_its_bits_at_every_simd_level(built, simd):
    """Each SIMD level of the C core's word traversal (its own mask
    building among them): the orbit's slots settled by the fat camera, the
    walk's decided frame by frame, an orthographic orbit's by the
    orthographic rows; every frame's executed bits as the dense engine's."""
    data, pm = model(built, "cow.ply")
    v0 = originals(data)
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    cams = paths_of(data, ("orbit", "walk with cuts"))
    cams["ortho"] = stack_cameras([pmjax.look_at(c + r * np.array([np.cos(a), 0.3, np.sin(a)]), c, orthographic=True,
                                                 ortho_height=r, near=1e-3, far=10 * r)
                                   for a in np.linspace(0, 2, 32)])
    for label, path in cams.items():
        got = list(pmjax.refine_path(pm, path, 1.0))
        for i, res in enumerate(got):
            assert_frame_equal(res, index_camera(path, i), 1.0, pm, (simd, label, i))
        counts = pmjax.path_counts(pm, path, 1.0)
        assert counts["executed_count"].tolist() == [int(x.n_executed) for x in got], (simd, label)


@pytest.mark.parametrize("name, pair_distance, seed", [
    ("cow.ply", 0.0, 1),
    ("bunny.ply", 0.0, 2),
    ("cessna.ply", 0.02, 3),  # parts merged by virtual pairs
    ("terrain_gcanyon.ply", 0.0, 4),
])
@pytest.mark.slow
def test_many_random_paths_on_several_models(built, name, pair_distance, seed):
    """Property test: K random paths (small steps, random cuts, a tolerance
    drawn per frame) advanced together; every frame's counts as the dense
    engine's for that camera alone, and one path's executed sets bit for bit."""
    data, pm = model(built, name, pair_distance)
    rng = np.random.default_rng(seed)
    K, T = 3, 21  # each path padded to one word (32 frames)
    flat = [walk(data, T, seed=seed * 10 + k, step=float(rng.uniform(0.005, 0.08)),
                 cuts=tuple(rng.choice(T, 2, replace=False))) for k in range(K)]
    cams = jax.tree.map(lambda *a: np.stack(a), *flat)
    levels = np.array([0.0, 0.5, 1.0, 4.0], np.float32)
    tau = levels[rng.integers(len(levels), size=(K, T))]
    counts = pmjax.path_counts(pm, cams, tau, paths=True)
    assert counts["faces"].shape == (K, T)
    # The oracle: the dense engine per camera, one batch per tolerance.
    everything = jax.tree.map(lambda a: a.reshape((K * T,) + a.shape[2:]), cams)
    for level in levels:
        at = np.flatnonzero(tau.reshape(-1) == level)
        if len(at) == 0:
            continue
        want = pmjax.refine_batch(pm, index_camera(everything, at), float(level), method="dense")
        for field in ("faces", "vertices", "executed_count"):
            assert counts[field].reshape(-1)[at].tolist() == want[field].tolist(), (name, level, field)
    for t, res in enumerate(pmjax.refine_path(pm, flat[0], tau[0])):
        if t % 4 == 0:
            assert_frame_equal(res, index_camera(flat[0], t), tau[0, t], pm, (name, t))
    per_frame = pmjax.path_counts(pm, flat[0], tau[0], coherent=False)
    assert np.array_equal(per_frame["faces"], counts["faces"][0])


def test_hidden_pcols_are_the_tau_zero_refinement(built):
    """A geomorphed path takes the hidden pcols from the refinement at tau 0."""
    data, pm = model(built, "cow.ply")
    cams = pmjax.standard_orbit(originals(data), 32)
    for i, (at_tau, at_zero) in enumerate(_path.path_refinement_pairs(pm, cams, 1.0)):
        if i % 8:
            continue
        cam = index_camera(cams, i)
        assert np.array_equal(np.asarray(at_zero.executed), np.asarray(pmjax.hidden_pcols(pm, cam))), i
        assert_frame_equal(at_tau, cam, 1.0, pm, i)


def streams(monkeypatch, owner, name, pm, cams, size, ahead=0):
    """Record the cameras of each call of ``owner.name`` while ``refine_path``
    is consumed: parts of ``size`` frames, computed as the frames are taken,
    at most ``ahead`` parts ahead of the consumer. Returns the record."""
    sizes = []
    real = getattr(owner, name)
    monkeypatch.setattr(owner, name, lambda pm, part, *a, **k: sizes.append(
        pmjax.camera_count(part)) or real(pm, part, *a, **k))
    frames = pmjax.refine_path(pm, cams, 1.0)
    first = next(frames)
    assert 1 <= len(sizes) <= 1 + ahead and int(first.n_faces) > 0  # a few parts computed, not the path
    for _ in range(size):
        next(frames)
    assert 2 <= len(sizes) <= 2 + ahead and set(sizes) == {size}
    return sizes


needs_core = pytest.mark.core


@needs_core
def test_long_path_streams_word_by_word(built, monkeypatch):
    """With the C core, refine_path's frames are computed a few words of 16
    frames at a time, one block ahead of the consumer; path_counts takes
    blocks of words, whole ones and then the rest in powers of two."""
    data, pm = model(built, "cow.ply")
    cams = pmjax.standard_orbit(originals(data), 200)
    sizes = []
    real = _path._core_words
    monkeypatch.setattr(_path, "_core_words", lambda tables, one, rows, *a: sizes.append(len(rows)) or
                        real(tables, one, rows, *a))
    default = _path.WORDS_STREAMED
    monkeypatch.setattr(_path, "WORDS_STREAMED", (4, 4))
    frames = pmjax.refine_path(pm, cams, 1.0)
    first = next(frames)
    block = 16 * 4
    assert int(first.n_faces) > 0 and sizes == [block] * 2  # this block and the next, not the path
    for _ in range(block):
        next(frames)
    assert sizes == [block] * 3
    rest = list(frames)
    assert [int(r.n_faces) for r in rest] == [int(pmjax.refine(pm, index_camera(cams, i), 1.0).n_faces)
                                              for i in range(block + 1, 200)]
    sizes.clear()
    monkeypatch.setattr(_path, "WORDS_PER_CALL", 4)
    counts = pmjax.path_counts(pm, cams, 1.0)
    # 200 frames padded to 208: thirteen words in blocks of 4, 4, 4 and 1.
    assert len(counts["faces"]) == 200 and sizes == [64, 64, 64, 16]
    assert counts["faces"].tolist() == [int(r.n_faces) for r in pmjax.refine_path(pm, cams, 1.0)]
    sizes.clear()
    monkeypatch.setattr(_path, "WORDS_STREAMED", default)
    frames = list(pmjax.refine_path(pm, cams, 1.0))
    # The cow's lists fit 16 words: thirteen words in blocks of 8, 4 and 1, every frame its bits.
    assert sizes == [128, 64, 16]
    for i, r in enumerate(frames):
        assert_frame_equal(r, index_camera(cams, i), 1.0, pm, i)


def test_streamed_words_per_call_follow_the_model_size():
    """A block of streamed words takes the most words whose lists fit
    STREAM_BYTES, halved down to the fewest."""
    fewest, most = _path.WORDS_STREAMED
    # The pcols whose lists (10 bytes a slot, P + SPARE slots a word) fill STREAM_BYTES in `words`.
    filling = lambda words: _path.STREAM_BYTES // (10 * words) - engines._core.SPARE
    assert _path.words_streamed(1000) == most == 16
    assert _path.words_streamed(filling(16)) == 16 and _path.words_streamed(filling(16) + 1) == 8
    assert _path.words_streamed(filling(8)) == 8 and _path.words_streamed(filling(8) + 1) == fewest == 4
    assert _path.words_streamed(10 ** 7) == fewest


def test_streamed_tail_is_one_call_where_it_adds_a_word_per_two_calls_saved():
    """After the whole blocks, the rest of a path's words is one call of the
    next power of two where that adds at most one word per two calls saved;
    the added words repeat the last frame and are not real."""
    for words, most, want in [(15, 16, [(0, 16)]), (7, 16, [(0, 8)]), (31, 16, [(0, 16), (16, 16)]),
                              (13, 16, [(0, 8), (8, 4), (12, 1)]), (3, 16, [(0, 2), (2, 1)]),
                              (15, 4, [(0, 4), (4, 4), (8, 4), (12, 2), (14, 1)]), (1, 16, [(0, 1)])]:
        order, real = np.arange(words * 16) // 2, np.ones(words * 16, bool)
        got_order, got_real, spans = _path._rounded_tail(order, real, engines._core.word_spans(words, most), most)
        assert spans == want, (words, most)
        n = 16 * sum(k for _, k in spans)
        assert got_order.tolist() == order.tolist() + [order[-1]] * (n - len(order)), (words, most)
        assert got_real.tolist() == [True] * len(order) + [False] * (n - len(order)), (words, most)


@needs_core
@pytest.mark.parametrize("room", [None, 16])
@pytest.mark.slow
def test_path_at_a_float_tie_decides_the_unsure_pairs(built, monkeypatch, room, simd):
    """At every SIMD level (each has its own branch for unsure pairs), a
    path that holds a pcol's critical tolerance (a float tie) in many
    frames: each word with unsure pairs is counted as if they kept and leaves
    a record of the slots they can change; the pairs are decided by the
    float32 predicate and the counts corrected. With room for 16 int32 of
    records (less than one), every such word overflows and its frames are
    refined alone. Either way, one float step below, at and above the tie:
    the counts of dense per-frame refines, and refine_path's frames are theirs."""
    data, pm = model(built, "bunny.ply")
    orbit = pmjax.standard_orbit(originals(data), 8)
    cam = index_camera(orbit, 1)
    t = np.asarray(pmjax.critical_tau(pm.attributes, cam))
    p = np.flatnonzero(np.isfinite(t) & (t > 0.5) & (t < 4))[0]
    cams = stack_cameras([cam] * 40 + [index_camera(orbit, i) for i in range(8)])
    monkeypatch.setattr(_path, "RECORD_ROOM", room)
    d = engines.derived(pm)
    rows = engines._core.camera_rows(cams, np.full(48, t[p], np.float32), d.exponent)
    overflow = np.asarray(_path._core_words(d.core_words, d.core, rows, pmjax.ALL_TESTS, False, False, room)[3])
    assert overflow.any() == (room is not None)
    for tau in (np.nextafter(t[p], np.float32(0)), t[p], np.nextafter(t[p], np.float32(np.inf))):
        got = pmjax.path_counts(pm, cams, tau)
        alone = [pmjax.refine(pm, c, tau, method="dense") for c in [cam] + [index_camera(orbit, i) for i in range(8)]]
        for i, frame in enumerate(pmjax.refine_path(pm, cams, tau)):
            r = alone[0] if i < 40 else alone[i - 39]
            assert (got["faces"][i], got["vertices"][i], got["executed_count"][i]) == (
                int(r.n_faces), int(r.n_vertices), int(r.n_executed)), (tau, i)
            if i % 8 == 0:
                assert_frame_equal(frame, cam if i < 40 else index_camera(orbit, i - 40), tau, pm, i, full=i == 40)
                assert all(np.array_equal(a, b) for a, b in zip(frame.mesh(), r.mesh())), i


@pytest.mark.slow
def test_path_as_jax_kernels_is_exact_and_streams(built, monkeypatch):
    """The word traversal as JAX kernels (where the C core is not built): 32
    frames per word, each as refine alone; the refinements are computed one
    chunk of frames at a time, as they are consumed, and counts of a long path
    never hold more than one chunk."""
    data, pm = model(built, "cow.ply")
    monkeypatch.setattr(_path, "CHUNK", 64)  # small chunks: few compiled shapes
    walked = walk(data, 64, seed=5, cuts=(10, 11, 40))  # one chunk: the streaming's compiled shape
    with engines.without_core():
        got = list(pmjax.refine_path(pm, walked, 1.0))
        assert got[0].front_positions is None  # not the C core
        for i, res in enumerate(got):
            assert_frame_equal(res, index_camera(walked, i), 1.0, pm, i, full=i % 9 == 0)
        assert pmjax.path_counts(pm, walked, 1.0)["faces"].tolist() == [int(x.n_faces) for x in got]
        streams(monkeypatch, _front_jax, "counts", pm, pmjax.standard_orbit(originals(data), 200), 64)


def test_bad_paths_name_the_frame(built):
    data, pm = model(built, "cow.ply")
    cams = pmjax.standard_orbit(originals(data), 12)
    with pytest.raises(pmjax.PathError, match="empty"):
        next(pmjax.refine_path(pm, index_camera(cams, slice(0, 0)), 1.0))
    with pytest.raises(pmjax.PathError, match="leading axes"):
        pmjax.path_counts(pm, index_camera(cams, 0), 1.0)
    host = jax.tree.map(np.asarray, cams)
    eye = host.eye.copy()
    eye[7, 1] = np.nan
    with pytest.raises(pmjax.PathError, match="frame 7: eye must be finite"):
        pmjax.path_counts(pm, eqx.tree_at(lambda c: c.eye, host, eye), 1.0)
    width = host.width.copy()
    width[5] = 640
    with pytest.raises(pmjax.PathError, match="frame 5: image size 640x600 differs"):
        list(pmjax.refine_path(pm, eqx.tree_at(lambda c: c.width, host, width), 1.0))
    rotation = host.rotation.copy()
    rotation[4, 0, 0] = np.inf
    with pytest.raises(pmjax.PathError, match="frame 4: the camera rotation"):
        pmjax.path_counts(pm, eqx.tree_at(lambda c: c.rotation, host, rotation), 1.0)
    taus = np.ones(12, np.float32)
    taus[3] = np.nan
    with pytest.raises(pmjax.PathError, match="frame 3: tau must be >= 0"):
        pmjax.path_counts(pm, cams, taus)
    with pytest.raises(pmjax.PathError, match="one per frame"):
        pmjax.path_counts(pm, cams, np.ones(5))
    with pytest.raises(pmjax.PathError, match="frame 2: a face budget"):
        pmjax.path_counts(pm, cams, budget=[10, 10, -1] + [10] * 9)


def test_path_frames_are_whole_refinements(built):
    """A path frame from the C core's words holds its ran bits as its
    word's until they are read: then (and through copies, pickling,
    dataclasses.replace, equality, JAX's tree functions) they are the
    frame's own, equal to refine's."""
    import copy
    import dataclasses
    import pickle

    data, pm = model(built, "cow.ply")
    cams = walk(data, 32, seed=31, cuts=(9,))
    frames = list(pmjax.refine_path(pm, cams, 1.0))
    for i in (0, 5, 15, 16, 31):
        r, want = frames[i], pmjax.refine(pm, index_camera(cams, i), 1.0)
        if select(pm, "front", batch=True) == "core":
            assert "_lane" in vars(r), i  # the bits are still the word's
        same = lambda x: np.array_equal(np.asarray(x.executed), np.asarray(want.executed))  # noqa: E731
        assert same(pickle.loads(pickle.dumps(r))), i  # before visited_executed is read
        assert same(copy.copy(r)) and same(dataclasses.replace(r, n_faces=r.n_faces)), i
        leaves, tree = jax.tree.flatten(r)
        again = jax.tree.unflatten(tree, leaves)
        assert same(again) and same(r) and r == r, i
        bits = r.visited_executed
        assert bits.dtype == bool and bits.shape == r.visited.shape and r.visited_executed is bits, i
        ran = np.ones(pm.n_pcols, bool)
        ran[r.visited] = bits
        assert np.array_equal(ran, np.asarray(want.executed)), i
    with pytest.raises(AttributeError, match="no attribute 'missing'"):
        frames[3].missing
