"""The batched builder on real models: invariants, replay, topology change, options."""

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.csgraph

import pmjax
from pmjax.builders import METRIC_NAMES, BuildOptions, build_pm
from pmjax._replay import active_faces, representatives


def components(vertices, faces) -> int:
    """Connected components of the faces (through shared vertices)."""
    n = len(vertices)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    g = scipy.sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, labels = scipy.sparse.csgraph.connected_components(g, directed=False)
    return len(np.unique(labels[faces.ravel()]))


@pytest.mark.parametrize(
    "name, pair_distance", [("cow.ply", 0.0), ("bunny.ply", 0.0), ("cessna.ply", 0.02), ("motor.ply", 0.02),
                            ("terrain_gcanyon.ply", 0.0), ("footbones.ply", 0.0)]
)
def test_invariants_hold_on_real_models(built, name, pair_distance):
    pm = built(name, pair_distance)
    pmjax.check_invariants(pm)
    assert pm.n_batches > 5
    # Each batch is a real batch, not one collapse at a time.
    assert np.diff(pm.batch_offsets)[0] > 0.05 * pm.n_original_vertices


def test_killer_check_catches_a_wrong_killer(built):
    pm = built("cow.ply")
    forged = pmjax.PMData(**{**pm.arrays(), "killer": np.roll(pm.killer, 1)}, header=pm.header)
    with pytest.raises(pmjax.PMFormatError, match="killer"):
        pmjax.check_invariants(forged)


def test_replay_all_pcols_gives_the_base_mesh_and_vertex_count_drops_by_P(built):
    pm = built("bunny.ply")
    v, f, ids = pmjax.lod_mesh(pm, pm.n_batches - 1)
    assert len(f) == pm.header["build"]["base_faces"]
    for k in (0, 3, pm.n_batches // 2, pm.n_batches - 1):
        n = int(pm.batch_offsets[k + 1])
        executed = pmjax.prefix_executed(pm, n)
        rep = representatives(pm, executed)
        # Every executed pcol removes exactly one vertex from the front.
        assert len(np.unique(rep[: pm.n_original_vertices])) == pm.n_original_vertices - n
        lv, lf, _ = pmjax.lod_mesh(pm, k)
        assert len(lf) == int(active_faces(pm, executed).sum())


def test_replay_never_flips_a_face(built):
    pm = built("bunny.ply")
    V0 = pm.n_original_vertices
    x = pm.vertices.astype(np.float64)
    prev = None
    for k in range(-1, pm.n_batches):
        n = int(pm.batch_offsets[k + 1])
        executed = pmjax.prefix_executed(pm, n)
        alive = active_faces(pm, executed)
        tri = x[representatives(pm, executed)[pm.faces]]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        if prev is not None:
            both = alive & prev_alive
            dots = np.einsum("ij,ij->i", normal[both], prev[both])
            assert np.all(dots > 0), f"batch {k}: {int((dots <= 0).sum())} faces flipped"
        prev, prev_alive = normal, alive
    assert V0 > 0


@pytest.mark.slow
def test_pair_distance_merges_separate_parts(data_path):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cessna.ply"))
    assert components(v, f) == 11
    target = 600
    counts = {}
    for t in (0.0, 0.05):
        pm = build_pm(v, f, BuildOptions(pair_distance=t, target_faces=target))
        lv, lf, _ = pmjax.lod_mesh(pm, pm.n_batches - 1)
        assert len(lf) <= target
        counts[t] = components(lv, lf)
    assert counts[0.05] < counts[0.0], counts


@pytest.mark.parametrize("metric", METRIC_NAMES)
def test_every_metric_builds_a_valid_hierarchy(metric, data_path):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cow.ply"))
    pm = build_pm(v, f, BuildOptions(metric=metric))
    pmjax.check_invariants(pm)
    assert np.all(pm.metric == pmjax.METRICS.index(metric))
    assert pm.header["build"]["base_faces"] < 0.05 * len(f)


def test_metric_schedule_switches_between_batches(data_path):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cow.ply"))
    pm = build_pm(v, f, BuildOptions(metric="edge:2,quadric"))
    first_two = pm.batch_offsets[2]
    assert np.all(pm.metric[:first_two] == pmjax.METRICS.index("edge"))
    assert np.all(pm.metric[first_two:] == pmjax.METRICS.index("quadric"))
    pmjax.check_invariants(pm)
    with pytest.raises(ValueError, match="unknown metric"):
        BuildOptions(metric="edge:2,nope").validate()
    with pytest.raises(ValueError, match="only the last"):
        BuildOptions(metric="edge,quadric").validate()


def test_a_schedule_count_must_be_decimal_digits():
    """A superscript is a digit to str.isdigit but not to int(): refused,
    naming the schedule, like any other bad count."""
    for schedule in ("edge:\u00b2,quadric", "edge:0,quadric", "edge:x,quadric", "edge:-1,quadric"):
        with pytest.raises(ValueError, match=f"metric schedule '{schedule}': batch count"):
            BuildOptions(metric=schedule).validate()
    assert BuildOptions(metric="edge:12,quadric").schedule() == [("edge", 12), ("quadric", None)]


def test_numpy_scalar_options_build_and_save(tmp_path, data_path):
    """Options given as NumPy scalars are kept as Python numbers: the header
    that stores them is JSON, and the build is the one of the same numbers."""
    v, f, _, _ = pmjax.load_clean_mesh(data_path("motor.ply"))
    plain = BuildOptions(target_faces=1000, pair_distance=0.015625, batch_share=0.25, linear=False)
    numpy = BuildOptions(target_faces=np.int64(1000), pair_distance=np.float32(0.015625),
                         batch_share=np.float64(0.25), linear=np.bool_(False))
    assert numpy == plain and type(numpy.target_faces) is int and type(numpy.pair_distance) is float
    pm = build_pm(v, f, numpy)
    pmjax.save_pm(pm, tmp_path / "motor.pmz")
    back = pmjax.read_pm(tmp_path / "motor.pmz")
    assert back.header["build"]["target_faces"] == 1000 and back.header["build"]["pair_distance"] == 0.015625
    for key, value in build_pm(v, f, plain).arrays().items():
        assert np.array_equal(getattr(back, key), value), key


@pytest.mark.parametrize("on", [True, False])
def test_bad_input_is_refused_before_any_work(monkeypatch, on):
    """Non-finite or float32-overflowing positions and face ids outside the
    vertices, of any integer type, are refused up front, naming the first
    bad vertex or face and its value."""
    from pmjax.builders import _build, _native

    def no_work(*args, **kwargs):
        raise AssertionError("the build started")

    monkeypatch.setattr(_build, "unique_edges", no_work)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.1]], float)
    f = np.array([[0, 1, 2], [1, 3, 2]], np.int32)
    with _native.use_native(on):
        for bad in (np.nan, np.inf, -np.inf, 1e39, -1e100):
            vb = v.copy()
            vb[3, 2] = bad
            with pytest.raises(ValueError, match=r"vertex 3 has a coordinate that is not finite or beyond float32.*"
                                                 r"\[1\.0, 1\.0, "):
                build_pm(vb, f)
        for dtype in (np.int32, np.int64, np.uint32):
            for bad_id in (4, -1):
                if bad_id < 0 and dtype == np.uint32:
                    continue
                fb = f.astype(dtype)
                fb[1, 1] = bad_id
                with pytest.raises(ValueError, match=rf"face 1 holds vertex id {bad_id}, outside 0 \.\. 3"):
                    build_pm(v, fb)


def test_sizes_the_int32_steps_cannot_address_are_refused(monkeypatch):
    """Vertex ids reach twice the vertex count and face slots three times the
    face count, both in int32: larger inputs are refused by their size alone
    (views of one row, so nothing is allocated; a build that started anyway
    stops at its first step)."""
    from pmjax.builders import _build

    def no_work(*args, **kwargs):
        raise AssertionError("the build started")

    monkeypatch.setattr(_build, "unique_edges", no_work)
    strided = np.lib.stride_tricks.as_strided
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    f = np.array([0, 1, 2], np.int32)
    with pytest.raises(ValueError, match=r"fewer than 2\*\*31 / 3 faces .* got 715827883 faces"):
        build_pm(v, strided(f, shape=(2**31 // 3 + 1, 3), strides=(0, 4)))
    with pytest.raises(ValueError, match=r"fewer than 2\*\*30 vertices .* got 1073741824 vertices"):
        build_pm(strided(v, shape=(2**30, 3), strides=(0, 8)), f[None])


def test_subset_metrics_place_at_an_endpoint(data_path):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cow.ply"))
    for metric in ("pm", "hybrid"):
        pm = build_pm(v, f, BuildOptions(metric=metric, target_faces=4000))
        x = pm.vertices[pm.n_original_vertices:]
        at_end = np.all(x == pm.vertices[pm.v1], 1) | np.all(x == pm.vertices[pm.v2], 1)
        assert at_end.all()
    pm = build_pm(v, f, BuildOptions(metric="edge", target_faces=4000))
    mid = 0.5 * (pm.vertices[pm.v1].astype(np.float64) + pm.vertices[pm.v2])
    assert np.allclose(pm.vertices[pm.n_original_vertices:], mid, atol=1e-5)


def test_targets_stop_where_asked(data_path):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cow.ply"))
    pm = build_pm(v, f, BuildOptions(target_faces=1000))
    base = pm.header["build"]["base_faces"]
    assert 990 <= base <= 1000
    pm = build_pm(v, f, BuildOptions(target_vertices=700))
    assert pm.n_original_vertices - pm.n_pcols == 700
    pm = build_pm(v, f, BuildOptions(max_error=1e-9))
    assert np.all(pm.cost <= 1e-9)


def test_linear_mode_takes_the_cheapest_valid_collapse_each_step(data_path):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cow.ply"))
    linear = build_pm(v, f, BuildOptions(linear=True, target_vertices=len(v) - 40))
    batched = build_pm(v, f, BuildOptions(target_faces=len(f) - 2))
    assert linear.n_pcols == 40 and np.all(np.diff(linear.batch_offsets) == 1)
    # The first step of both is the globally cheapest valid collapse.
    assert {linear.v1[0], linear.v2[0]} == {batched.v1[0], batched.v2[0]}
    pmjax.check_invariants(linear)


def test_batch_share_caps_each_batch(data_path):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cow.ply"))
    small = build_pm(v, f, BuildOptions(batch_share=0.05, target_faces=3000))
    large = build_pm(v, f, BuildOptions(batch_share=1.0, target_faces=3000))
    assert np.diff(small.batch_offsets)[0] < np.diff(large.batch_offsets)[0]
    assert small.n_batches > large.n_batches
    with pytest.raises(ValueError, match="batch_share"):
        BuildOptions(batch_share=0).validate()


def test_a_small_share_still_simplifies_until_nothing_is_valid(data_path):
    # When a batch's cheapest share holds no valid collapse, the dearer rest is
    # tried before the build stops; stopping there left the cow at 240 faces
    # with a 5 % share, against 12 with the whole candidate set.
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cow.ply"))
    bases = {s: build_pm(v, f, BuildOptions(batch_share=s)).header["build"]["base_faces"] for s in (0.05, 1.0)}
    assert bases[0.05] == bases[1.0] < 100


def test_tiny_and_odd_inputs(data_path):
    tri_v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    with pytest.raises(ValueError, match="at least one face"):
        build_pm(tri_v, np.zeros((0, 3), int))
    pm = build_pm(tri_v, np.array([[0, 1, 2]]))
    pmjax.check_invariants(pm)
    assert pm.n_pcols == 1 and pm.killer[0] == 0
    # Refined: the one pcol runs only when tau allows, and vref follows it.
    view = pmjax.look_at([0.3, 0.3, 3.0], [0.3, 0.3, 0.0], fov_y_deg=45, width=800, height=600)
    fine, coarse = (pmjax.refine(pmjax.ProgressiveMesh.from_data(pm), view, t) for t in (0.0, 1e9))
    assert int(fine.n_faces) == 1 and np.array_equal(np.asarray(fine.rep), np.arange(4))
    assert int(coarse.n_faces) == 0 and int(coarse.n_executed) == 1
    v1, v2 = int(pm.v1[0]), int(pm.v2[0])
    assert np.asarray(coarse.rep)[v1] == np.asarray(coarse.rep)[v2] == 3
    # Two triangles sharing only a vertex (non-manifold bow tie).
    bow_v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)
    pm = build_pm(bow_v, np.array([[0, 1, 2], [0, 3, 4]]))
    pmjax.check_invariants(pm)
    # Duplicate vertex positions (unmerged seams) are fine.
    v, f, _, _ = pmjax.load_clean_mesh(data_path("motor.ply"))
    pm = build_pm(v, f, BuildOptions(pair_distance=0.0))
    pmjax.check_invariants(pm)


def test_attributes_bound_what_they_claim(built):
    pm = built("bunny.ply")
    V0 = pm.n_original_vertices
    x = pm.vertices.astype(np.float64)
    # Every original vertex lies in the sphere of each of its ancestors.
    parent = pmjax._replay.parents(pm)
    v = np.arange(V0)
    up = parent[v]
    diag = np.linalg.norm(np.ptp(x[:V0], 0))
    while np.any(up >= 0):
        ok = up >= 0
        p = up[ok] - V0
        d = np.linalg.norm(x[v[ok]] - x[up[ok]], axis=1)
        assert np.all(d <= pm.radius[p] + 1e-5 * diag)
        # Tangent-plane deviation is bounded by delta.
        h = np.abs(np.einsum("ij,ij->i", pm.normals[up[ok]].astype(np.float64), x[v[ok]] - x[up[ok]]))
        assert np.all(h <= pm.delta[p] + 1e-5 * diag)
        up = np.where(ok, parent[np.maximum(up, 0)], -1)


def test_uncovered_distance_sees_borders_and_vanished_parts():
    """A leaf off its owner's faces counts only where the coarse surface ends:
    at an open border (distance in the tangent plane) or where the owner has
    no faces left (whole distance); an owner inside a closed fan gives 0."""
    from pmjax.builders._attributes import uncovered_distance

    # Neighbours 0-3 around the origin in the plane, leaves 4-6, and the owner
    # 7 at the origin with normal +z: the batch's one new vertex (ids >= lo).
    ring_xy = [(1, 0), (0, 1), (-1, 0), (0, -1)]
    vertices = np.array([[x, y, 0.0] for x, y in ring_xy]
                        + [[0.2, 0.3, 0.5], [0.0, -2.0, 0.1], [3.0, 4.0, 0.0], [0.0, 0.0, 0.0]])
    normals = np.tile([0.0, 0.0, 1.0], (len(vertices), 1))
    inside, below, far, o = 4, 5, 6, 7
    half_fan = np.array([[o, 0, 1], [o, 1, 2]])  # covers y >= 0: the owner is on a border
    closed_fan = np.array([[o, 0, 1], [o, 1, 2], [o, 2, 3], [o, 3, 0]])
    leaves, owner = np.array([inside, below]), np.array([o, o])

    maybe = np.array([True])  # checked, not assumed: the counts decide
    edge = np.array([True, True])  # leaves on the original border
    d = uncovered_distance(vertices, normals, leaves, owner, half_fan, o, o + 1, maybe, edge)
    np.testing.assert_allclose(d, [0.0, 2.0])  # in the plane: (0, -2) to the border y = 0
    d = uncovered_distance(vertices, normals, leaves, owner, closed_fan, o, o + 1, maybe, edge)
    np.testing.assert_allclose(d, [0.0, 0.0])  # the leaf beyond is some neighbour's business
    d = uncovered_distance(vertices, normals, np.array([far]), np.array([o]), np.zeros((0, 3), int), o, o + 1,
                           np.array([False]), np.array([False]))
    np.testing.assert_allclose(d, [5.0])  # the part vanished into the point


def test_flat_open_parts_keep_their_extent_on_screen(tmp_path):
    """On a flat open grid the normal sees no deviation at all; the border must
    still stop the refinement from shrinking the grid while it is large on
    screen, and a single triangle must not vanish while it is seen big."""
    n = 21
    xs, ys = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], 1)
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    f = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])
    near = pmjax.look_at(eye=[0.5, 0.5, 1.5], target=[0.5, 0.5, 0.0])
    far = pmjax.look_at(eye=[0.5, 0.5, 1e4], target=[0.5, 0.5, 0.0], far=2e4)

    def area(vv, ff):
        return 0.5 * np.linalg.norm(np.cross(vv[ff[:, 1]] - vv[ff[:, 0]], vv[ff[:, 2]] - vv[ff[:, 0]]), axis=1).sum()

    data = build_pm(v, f)
    assert np.all(data.delta == 0)  # flat: nothing along the normal
    pm = pmjax.ProgressiveMesh.from_data(data)
    vv, ff, _ = pmjax.refine(pm, near, 1.0).mesh(pm)
    assert len(ff) < len(f) // 4  # the inside still simplifies
    assert abs(area(vv, ff) - 1.0) < 0.05
    np.testing.assert_allclose(vv[np.unique(ff)].min(0)[:2], [0, 0], atol=0.02)
    np.testing.assert_allclose(vv[np.unique(ff)].max(0)[:2], [1, 1], atol=0.02)

    tri = pmjax.ProgressiveMesh.from_data(build_pm(v[[0, n - 1, n * n - 1]], np.array([[0, 1, 2]])))
    assert int(pmjax.refine(tri, near, 1.0).n_faces) == 1
    assert int(pmjax.refine(tri, far, 1.0).n_faces) == 0  # a speck far away may go


def test_cheapest_is_the_stable_sort_prefix():
    """The batch's eligible candidates (partial selection) equal the first k of
    a full stable sort, ties included."""
    from pmjax.builders._build import _cheapest

    rng = np.random.default_rng(3)
    for n, k in [(1, 1), (10, 3), (1000, 500), (1000, 1000), (50, 1), (200, 199), (5000, 5000)]:
        for cost in (rng.integers(0, 7, n).astype(np.float64), rng.random(n), np.zeros(n)):  # ties, none, all
            assert np.array_equal(_cheapest(cost, k), np.argsort(cost, kind="stable")[:k]), (n, k)


def test_threaded_splits_equal_one_call(monkeypatch):
    """Row halves on two threads give the same bits as one call: placements of
    random quadrics, and a per-pair check over its incidence rows."""
    from pmjax.builders import _quadrics as qd
    from pmjax.builders import _threads

    monkeypatch.setattr(_threads, "MIN_ROWS", 10)
    monkeypatch.setattr(_threads, "_two_cores", lambda: True)
    rng = np.random.default_rng(5)
    n = 1001
    q = rng.random((n, 10))
    q[:, [0, 4, 7]] += 3.0
    a, b = rng.random((n, 3)), rng.random((n, 3))
    whole = qd.optimal_placement(q, a, b)
    halves = _threads.split_rows(qd.optimal_placement, q, a, b)
    assert all(np.array_equal(u, v) for u, v in zip(whole, halves))

    ids = np.arange(50, 150)
    pair = rng.integers(0, len(ids), 5000)
    face = rng.integers(0, 10_000, 5000)

    def check(i, p, f):  # per id: its id plus the sum of its faces' ids, odd?
        return (i + np.bincount(p, f, minlength=len(i)).astype(np.int64)) % 2 == 1

    assert np.array_equal(_threads.split_pairs(check, ids, pair, face), check(ids, pair, face))


def test_validity_shortcuts_change_nothing(monkeypatch, data_path):
    """Checking validity up front or only for greedy winners, and reusing
    verdicts of pairs whose domain did not change, give the same hierarchy
    as checking everything afresh."""
    from pmjax.builders import _build, _validity

    v, f, _, _ = pmjax.load_clean_mesh(data_path("bunny.ply"))
    reference = build_pm(v, f)
    # Up front for every batch small enough, never remembering a verdict.
    monkeypatch.setattr(_build, "EAGER_INVALID_SHARE", 0.0)
    monkeypatch.setattr(_validity.KnownInvalid, "of", lambda self, keys: np.zeros(len(keys), bool))
    eager = build_pm(v, f)
    # Only for winners, always.
    monkeypatch.setattr(_build, "EAGER_INVALID_SHARE", 2.0)
    lazy = build_pm(v, f)
    for other in (eager, lazy):
        for key, value in reference.arrays().items():
            assert np.array_equal(getattr(other, key), value), key


@pytest.mark.parametrize("on", [True, False])
@pytest.mark.parametrize("metric", ["quadric:12,edge", "edge:14,quadric"])
def test_known_invalid_verdicts_do_not_outlive_their_metric(monkeypatch, data_path, assert_same_pm, metric, on):
    """A verdict remembered under one metric's placement says nothing about
    another's: a schedule that moves on builds what checking every
    candidate afresh builds (on the motor, verdicts carried over refused
    collapses valid under the next metric)."""
    from pmjax.builders import _build, _native, _validity

    v, f, _, _ = pmjax.load_clean_mesh(data_path("motor.ply"))
    with _native.use_native(on):
        reference = build_pm(v, f, BuildOptions(metric=metric))
        monkeypatch.setattr(_validity.KnownInvalid, "of", lambda self, keys: np.zeros(len(keys), bool))
        afresh = build_pm(v, f, BuildOptions(metric=metric))
    assert_same_pm(afresh, reference)
    assert set(np.unique(reference.metric)) == {pmjax.METRICS.index("quadric"), pmjax.METRICS.index("edge")}


def test_an_error_on_the_attribute_thread_reaches_the_caller(monkeypatch, data_path):
    """Normals and attributes are computed on a second thread; a failure there
    must surface from build_pm, not be lost or hang the build."""
    from pmjax.builders import _attributes

    def fail(self, lo, c1, c2, ring, maybe_border):
        raise FloatingPointError(f"attributes of batch at {lo}")

    monkeypatch.setattr(_attributes.HierarchyAttributes, "add_batch", fail)
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cow.ply"))
    with pytest.raises(FloatingPointError, match="attributes of batch"):
        build_pm(v, f)
