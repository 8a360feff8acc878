"""The builder's C loops against its NumPy path: the same hierarchy bit for bit,
and each loop against the NumPy function it replaces (including the round cap
of the parallel greedy, invalid winners, and placements at the solvability
threshold)."""

from __future__ import annotations

import numpy as np
import pytest

import pmjax
from pmjax.builders import BuildOptions, build_pm
from pmjax.builders import _native as native

pytestmark = pytest.mark.core


def numpy_build(v, f, options=BuildOptions()):
    with native.use_native(False):
        assert not native.available()
        return build_pm(v, f, options)


def test_bunny_hierarchy_is_the_numpy_builders(built, data_path, assert_same_pm):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("bunny.ply"))
    assert native.available()
    assert_same_pm(built("bunny.ply"), numpy_build(v, f))


@pytest.mark.parametrize(
    "name, options",
    [
        ("cow", dict(batch_share=0.15, target_faces=300)),
        ("cow", dict(metric="edge:2,quadric", allow_topology_change=True, target_vertices=400)),
        ("cow", dict(metric="quadric-memoryless:3,pm:3,hybrid:3,quadric", target_faces=1000)),
        ("cessna", dict(pair_distance=0.02)),
        ("terrain_gcanyon", dict(batch_share=1.0)),
    ],
)
@pytest.mark.slow
def test_other_builds_are_the_numpy_builders(data_path, name, options, assert_same_pm):
    """Targets, metric schedules (costs from NumPy with the C batch choice,
    quadrics rebuilt from the faces every batch), virtual pairs (no link
    test), open borders."""
    v, f, _, _ = pmjax.load_clean_mesh(data_path(f"{name}.ply"))
    assert_same_pm(build_pm(v, f, BuildOptions(**options)), numpy_build(v, f, BuildOptions(**options)))


@pytest.fixture(scope="module")
def first_batch(data_path):
    """The bunny's first batch: current faces, positions, candidates with
    placements and costs, eligible ids (cheapest half), border flags."""
    from pmjax.builders import _quadrics as qd
    from pmjax.builders._build import _cheapest
    from pmjax.builders._topology import unique_edges

    v, f, _, _ = pmjax.load_clean_mesh(data_path("bunny.ply"))
    V0 = len(v)
    pos = np.zeros((2 * V0, 3))
    pos[:V0] = v
    quadric = np.zeros((2 * V0, 10))
    quadric[:V0] = qd.vertex_quadrics(v, f, V0)
    cur = f.astype(np.int32)
    ea, eb, ecount, _ = unique_edges(cur)
    x, cost = qd.optimal_placement(quadric[ea] + quadric[eb], pos[ea], pos[eb])
    elig = _cheapest(cost, len(cost) // 2)
    boundary = np.zeros(V0, bool)
    boundary[ea[ecount == 1]] = boundary[eb[ecount == 1]] = True
    diag = float(np.linalg.norm(np.ptp(v, 0)))
    return dict(pos=pos, quadric=quadric, cur=cur, a=ea, b=eb, x=x, elig=elig, boundary=boundary,
                min_area2=(1e-12 * diag * diag) ** 2, n=V0)


def numpy_validity(batch, x, link):
    """builders/_validity.py's check as select_independent calls it, over
    candidate ids into batch["elig"]; records what it found invalid."""
    from pmjax.builders._validity import collapse_is_valid

    e = batch["elig"]
    invalid = []

    def check(ids, pair, face):
        k = e[ids]
        ok = collapse_is_valid(batch["pos"], batch["cur"], batch["a"][k], batch["b"][k], x[k], pair, face,
                               min_area2=batch["min_area2"], link_test=link[k], boundary_vertex=batch["boundary"])
        invalid.append(ids[~ok])
        return ok

    return check, invalid


def spoiled_placements(batch, share, seed):
    """Placements with ``share`` of the candidates thrown far off (their
    faces flip: invalid winners), the cheapest ones among them."""
    rng = np.random.default_rng(seed)
    x = batch["x"].copy()
    e = batch["elig"]
    far = e[rng.random(len(e)) < share]
    x[far] += 10.0 * rng.normal(size=(len(far), 3))
    return x


@pytest.mark.parametrize("max_rounds", [1, 2, 3, 64])
@pytest.mark.parametrize("share", [0.0, 0.2])
def test_greedy_takes_the_parallel_rounds_set_under_every_cap(first_batch, max_rounds, share):
    from pmjax.builders._independent import select_independent

    batch = first_batch
    x = spoiled_placements(batch, share, seed=max_rounds)
    link = np.random.default_rng(1).random(len(batch["a"])) < 0.8
    e = batch["elig"]
    check, invalid = numpy_validity(batch, x, link)
    want = select_independent(batch["a"][e], batch["b"][e], batch["cur"], batch["n"], check, max_rounds=max_rounds)
    mesh = native.Mesh(batch["cur"], batch["n"], batch["pos"], native.Scratch(batch["n"], len(batch["cur"])))
    cand = native.Candidates(batch["a"], batch["b"], x, link)
    chosen, bad, checked = native.select_independent(mesh, cand, e, batch["boundary"], batch["min_area2"],
                                                     assume_valid=False, max_rounds=max_rounds)
    want_invalid = np.sort(np.concatenate(invalid))
    assert np.array_equal(chosen, want)
    assert np.array_equal(bad, want_invalid)
    assert checked == len(want) + len(want_invalid)
    assert len(want) > 0 and (share == 0 or len(want_invalid) > 0)

    # Known valid up front: no check, the same rounds.
    want_all = select_independent(batch["a"][e], batch["b"][e], batch["cur"], batch["n"],
                                  lambda ids, pair, face: np.ones(len(ids), bool), max_rounds=max_rounds)
    chosen, bad, checked = native.select_independent(mesh, cand, e, batch["boundary"], batch["min_area2"],
                                                     assume_valid=True, max_rounds=max_rounds)
    assert np.array_equal(chosen, want_all) and len(bad) == 0 and checked == 0


def test_greedy_goes_past_the_cap_until_something_is_taken(first_batch):
    """When every winner of the first rounds is invalid, the parallel rounds
    run on until a round takes something; so must the C greedy. Three
    candidates around one vertex, the first two invalid: rounds 1 and 2 take
    nothing, round 3 takes the third, under a cap of 1 round."""
    from pmjax.builders._independent import select_independent

    batch = first_batch
    u = np.flatnonzero(np.bincount(batch["a"]) >= 3)[0]
    e = np.flatnonzero(batch["a"] == u)[:3]
    x = batch["x"].copy()
    x[e[:2]] += 50.0  # their faces flip
    link = np.ones(len(batch["a"]), bool)
    check, invalid = numpy_validity(dict(batch, elig=e), x, link)
    want = select_independent(batch["a"][e], batch["b"][e], batch["cur"], batch["n"], check, max_rounds=1)
    mesh = native.Mesh(batch["cur"], batch["n"], batch["pos"], native.Scratch(batch["n"], len(batch["cur"])))
    cand = native.Candidates(batch["a"], batch["b"], x, link)
    chosen, bad, checked = native.select_independent(mesh, cand, e, batch["boundary"], batch["min_area2"],
                                                     assume_valid=False, max_rounds=1)
    assert want.tolist() == [2] and chosen.tolist() == [2]
    assert bad.tolist() == [0, 1] == np.sort(np.concatenate(invalid)).tolist() and checked == 3


def test_validity_is_the_numpy_validity(first_batch):
    from pmjax.builders._topology import VertexFaces
    from pmjax.builders._validity import collapse_is_valid

    batch = first_batch
    x = spoiled_placements(batch, 0.1, seed=7)
    link = np.random.default_rng(2).random(len(batch["a"])) < 0.5
    idx = np.sort(batch["elig"])
    a, b = batch["a"][idx], batch["b"][idx]
    pair, face = VertexFaces(batch["cur"], batch["n"]).of_pairs(a, b, batch["cur"])
    want = collapse_is_valid(batch["pos"], batch["cur"], a, b, x[idx], pair, face, min_area2=batch["min_area2"],
                             link_test=link[idx], boundary_vertex=batch["boundary"])
    mesh = native.Mesh(batch["cur"], batch["n"], batch["pos"], native.Scratch(batch["n"], len(batch["cur"])))
    got = native.collapse_is_valid(mesh, native.Candidates(batch["a"], batch["b"], x, link), idx,
                                   batch["boundary"], batch["min_area2"])
    assert np.array_equal(got, want)
    assert 0 < np.count_nonzero(~want) < len(want)


def test_placement_is_the_numpy_placement(first_batch):
    """Real pairs, then random quadrics with singular, rank-deficient,
    NaN and infinite rows."""
    from pmjax.builders import _quadrics as qd

    batch = first_batch
    a, b = batch["a"], batch["b"]
    want = qd.optimal_placement(batch["quadric"][a] + batch["quadric"][b], batch["pos"][a], batch["pos"][b])
    got = native.quadric_placement(batch["quadric"], batch["pos"], a, b)
    assert all(u.tobytes() == w.tobytes() for u, w in zip(got, want))

    rng = np.random.default_rng(4)
    n = 4000
    quadric = rng.normal(size=(2 * n, 10))
    quadric[: n // 4] = 0.0  # zero sums: no solution
    plane = rng.normal(size=(n // 4, 4))
    quadric[n // 4 : n // 2] = plane[:, [0, 0, 0, 0, 1, 1, 1, 2, 2, 3]] * plane[:, [0, 1, 2, 3, 1, 2, 3, 2, 3, 3]]
    quadric[n // 2 : n // 2 + 10, 3] = np.nan
    quadric[n // 2 + 10 : n // 2 + 20, 0] = np.inf
    # Thresholds near underflow and overflow (left to NumPy's power).
    for at, scale in ((n // 2 + 20, 1e-110), (n // 2 + 30, 1e-200), (n // 2 + 40, 1e110)):
        quadric[at : at + 10] *= scale
    pos = rng.normal(size=(2 * n, 3))
    pa, pb = np.arange(n, dtype=np.int32), (np.arange(n, dtype=np.int32) + n)
    quadric[n:] = 0.0  # the second endpoints add nothing: the rows above are the pairs' sums
    with np.errstate(invalid="ignore", over="ignore"):  # the NaN, infinite and huge rows
        want = qd.optimal_placement(quadric[pa] + quadric[pb], pos[pa], pos[pb])
        got = native.quadric_placement(quadric, pos, pa, pb)
    assert all(u.tobytes() == w.tobytes() for u, w in zip(got, want))


def test_placement_at_the_solvability_threshold_uses_numpys_power():
    """A determinant equal to 1e-9 scale^3 up to rounding: the C loop leaves
    it to NumPy's power, and the result is optimal_placement's."""
    from pmjax.builders import _quadrics as qd

    e = 1e-9 * (2 / 3) ** 3
    for _ in range(5):  # e = 1e-9 ((2 + e) / 3)^3, the fixed point
        e = 1e-9 * ((2 + e) / 3) ** 3
    rows = []
    for scale in (1.0, 1 + 2**-40, 1 - 2**-40, 1 + 2**-30):
        q = np.zeros(10)
        q[[0, 4]] = 1.0
        q[7] = e * scale
        q[3], q[6], q[8], q[9] = 0.1, -0.2, 1e-12, 1.0
        rows.append(q)
    quadric = np.concatenate([np.array(rows), np.zeros((len(rows), 10))])
    pos = np.random.default_rng(0).normal(size=(2 * len(rows), 3))
    a = np.arange(len(rows), dtype=np.int32)
    b = a + len(rows)
    x, cost, unsure = np.empty((len(a), 3)), np.empty(len(a)), np.empty(len(a), np.int64)
    n_unsure = native._LIB.pmx_quadric_placement(len(a), None, a.ctypes.data, b.ctypes.data, quadric.ctypes.data,
                                                 pos.ctypes.data, None, x.ctypes.data, cost.ctypes.data,
                                                 unsure.ctypes.data)
    assert n_unsure == len(rows)
    want = qd.optimal_placement(quadric[a] + quadric[b], pos[a], pos[b])
    got = native.quadric_placement(quadric, pos, a, b)
    assert all(u.tobytes() == w.tobytes() for u, w in zip(got, want))


def test_known_costs_are_carried_and_the_rest_placed_in_place(first_batch):
    """Rows known from the last batch are copied by key (a merge), the fresh
    ones found; placing only the fresh rows in place gives the full result."""
    batch = first_batch
    a, b, keys = batch["a"], batch["b"], (batch["a"].astype(np.int64) << 32) | batch["b"]
    x, cost = native.quadric_placement(batch["quadric"], batch["pos"], a, b)
    rng = np.random.default_rng(6)
    known = np.sort(rng.choice(len(keys), len(keys) // 2, replace=False))
    extra = keys.max() + 1 + np.arange(5)  # keys of pairs gone since
    old_keys = np.sort(np.concatenate([keys[known], extra]))
    at = np.searchsorted(old_keys, keys[known])
    old_x, old_cost = np.full((len(old_keys), 3), np.nan), np.full(len(old_keys), np.nan)
    old_x[at], old_cost[at] = x[known], cost[known]
    cx, ccost, fresh = native.carry_costs(old_keys, old_x, old_cost, keys)
    assert np.array_equal(fresh, np.setdiff1d(np.arange(len(keys)), known))
    native.quadric_placement(batch["quadric"], batch["pos"], a, b, rows=fresh, x=cx, cost=ccost)
    assert cx.tobytes() == x.tobytes() and ccost.tobytes() == cost.tobytes()
    assert native.carry_costs(old_keys, old_x, old_cost, keys[::-1]) is None
    with pytest.raises(ValueError, match="outside"):
        native.quadric_placement(batch["quadric"], batch["pos"], a, b, rows=[len(a)], x=cx, cost=ccost)


def test_scatter_add_is_the_bincount_sums():
    """One pass over the rows gives bincount's sums per column, bit for bit
    (the same additions in the same order); bad indices are refused."""
    from pmjax.builders import _quadrics as qd

    rng = np.random.default_rng(8)
    values = rng.normal(size=(5000, 10)) * 10.0 ** rng.integers(-8, 8, (5000, 1))
    for repeat in (1, 3):
        index = rng.integers(0, 700, repeat * len(values)).astype(np.int32)
        got = qd.scatter_add(values, index, 800, repeat)
        with native.use_native(False):
            want = qd.scatter_add(values, index, 800, repeat)
        assert got.shape == want.shape == (800, 10) and got.tobytes() == want.tobytes()
    with pytest.raises(ValueError, match="outside"):
        native.scatter_add(values.T, np.array([0, 800]), 800, 1)


def test_leaf_climb_is_the_numpy_climb():
    """The leaves' climb of a batch gives NumPy's moved leaves, new tops and
    largest tangent-plane distances bit for bit, NaN included (np.maximum
    propagates it), over a random forest climbed batch by batch."""
    from pmjax.builders._attributes import HierarchyAttributes

    rng = np.random.default_rng(11)
    V0, batches, k = 3000, 12, 200
    n = V0 + batches * k
    pos = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-6, 6, (n, 1))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    pos[rng.integers(0, V0, 5)] = np.nan  # a few leaves off the scale
    faces = np.stack([np.arange(0, V0 - 2), np.arange(1, V0 - 1), np.arange(2, V0)], 1)
    # A random forest: each batch pairs up vertices that have no parent yet.
    schedule, free = [], np.arange(V0)
    for b in range(batches):
        lo = V0 + b * k
        pick = rng.permutation(free)[: 2 * k]
        schedule.append((lo, pick[:k], pick[k:]))
        free = np.concatenate([np.setdiff1d(free, pick), np.arange(lo, lo + k)])
    states = []
    for on in (True, False):
        with native.use_native(on), np.errstate(invalid="ignore"):  # the NaN leaves
            attrs = HierarchyAttributes(pos, normals, faces, V0)
            for lo, c1, c2 in schedule:
                attrs.add_batch(lo, c1, c2, np.zeros((0, 3), np.int64), np.zeros(k, bool))
            states.append([a.tobytes() for a in (attrs.top, attrs.delta, attrs.mu, attrs.radius)])
    assert states[0] == states[1]
    assert np.isnan(attrs.delta).any()  # the NaN leaves reached the check


def test_uncovered_distance_is_the_numpy_distance():
    """How far leaves lie off the coarse surface sideways: the C pass gives
    NumPy's distances bit for bit on an open grid whose vertices were merged
    into new vertices (borders, owners left without faces, faces seen edge-on
    from tilted tangent planes, repeated positions)."""
    from pmjax.builders._attributes import uncovered_distance

    rng = np.random.default_rng(5)
    side = 40
    gx, gy = np.meshgrid(np.arange(side, dtype=float), np.arange(side, dtype=float))
    V0 = side * side
    grid = np.stack([gx.ravel(), gy.ravel(), 0.1 * rng.normal(size=V0)], 1)
    grid[rng.integers(0, V0, 20)] = grid[rng.integers(0, V0, 20)]  # repeated positions
    q = (np.arange(side - 1)[:, None] * side + np.arange(side - 1)[None, :]).ravel()
    faces = np.concatenate([np.stack([q, q + 1, q + side], 1), np.stack([q + 1, q + side + 1, q + side], 1)])
    # New vertices: each takes one or two neighbouring grid vertices' place.
    k = 300
    picked = rng.choice(V0 - side - 1, k, replace=False)
    rename = np.arange(V0 + k)
    rename[picked] = V0 + np.arange(k)
    pair = rng.random(k) < 0.5
    rename[picked[pair] + 1] = V0 + np.arange(k)[pair]
    lo, hi = V0, V0 + k + 10  # ten new vertices own no face
    pos = np.concatenate([grid, grid[picked], rng.normal(size=(10, 3)) * 5])
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (V0, 1)), rng.normal(size=(k + 10, 3))])
    normals[V0:V0 + k // 3] = [0.0, 0.0, 1.0]
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    cur = rename[faces]
    live = (cur[:, 0] != cur[:, 1]) & (cur[:, 1] != cur[:, 2]) & (cur[:, 0] != cur[:, 2])
    cur = cur[live]
    ring = cur[(cur >= lo).any(axis=1)].astype(np.int32)
    leaves = rng.integers(0, V0, 4000)
    owner = lo + rng.integers(0, hi - lo, len(leaves))
    maybe_border = rng.random(hi - lo) < 0.8
    on_border = rng.random(len(leaves)) < 0.7
    args = (pos, normals, leaves, owner, ring, lo, hi, maybe_border, on_border)
    got = uncovered_distance(*args)
    with native.use_native(False):
        ref = uncovered_distance(*args)
    assert got.tobytes() == ref.tobytes()
    alone = owner >= V0 + k
    assert (ref[alone] > 0).all() and (ref[~alone] > 0).sum() > 50 and (ref[~alone] == 0).sum() > 50
    empty = uncovered_distance(pos, normals, leaves[:0], owner[:0], ring, lo, hi, maybe_border, on_border[:0])
    assert empty.shape == (0,)


def test_numpy_distances_do_not_depend_on_the_memory_layout():
    """The NumPy distances sum their dot products in the C loops' order
    written out: the same bits for row-major and column-major inputs (an
    einsum takes another order over column-major rows)."""
    from pmjax._distance import dot_rows, point_triangle_distance

    rng = np.random.default_rng(3)
    p, a, b, c = (rng.normal(size=(5000, 3)) * 10.0 ** rng.integers(-3, 4, (5000, 1)) for _ in range(4))
    rows = point_triangle_distance(p, a, b, c)
    columns = point_triangle_distance(*(np.asfortranarray(x) for x in (p, a, b, c)))
    assert rows.tobytes() == columns.tobytes()
    assert dot_rows(p, a).tobytes() == dot_rows(np.asfortranarray(p), np.asfortranarray(a)).tobytes()


def test_edges_are_the_numpy_edges(first_batch):
    """Keys made, sorted and counted in C: unique_edges' arrays, dtypes
    included, on a real mesh and on an open fan with repeated edges."""
    from pmjax.builders import _topology

    fan = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [4, 2, 1], [4, 1, 2]], np.int32)
    for faces in (first_batch["cur"], fan, fan[:0]):
        got = _topology.unique_edges(faces)
        with native.use_native(False):
            want = _topology.unique_edges(faces)
        assert all(u.dtype == w.dtype and np.array_equal(u, w) for u, w in zip(got, want))


@pytest.mark.parametrize("bits", [1, 11, 12, 13, 22, 25, 31])
def test_key_sort_is_numpys(bits):
    """The radix sort of edge keys against NumPy's sort, for ids of every
    width up to 31 bits (one to three digits per half, digits the same in
    every key skipped), with repeated keys; keys that are no edge keys of
    int32 ids are refused, untouched."""
    if not native.available():
        pytest.skip("the C loops are not built")
    rng = np.random.default_rng(bits)
    ids = rng.integers(0, 1 << bits, (2, 30_011))
    keys = (ids.min(0).astype(np.int64) << 32) | ids.max(0)
    keys = np.concatenate([keys, keys[:500]])
    got = keys.copy()
    native.sort_keys(got)
    assert got.tobytes() == np.sort(keys).tobytes()
    same_low = (np.arange(100, dtype=np.int64) << 32) | (1 << bits) - 1
    got = same_low[::-1].copy()
    native.sort_keys(got)
    assert got.tobytes() == same_low.tobytes()
    for bad in ([3, -1, 2], [1, -(1 << 63)], [1 << 31], [5, (1 << 31) | (7 << 32)]):
        bad = np.array(bad, np.int64)
        kept = bad.copy()
        with pytest.raises(ValueError, match="not an edge key"):
            native.sort_keys(bad)
        assert bad.tobytes() == kept.tobytes()


@pytest.mark.parametrize("module", ["pmjax._pmz_native", "pmjax.builders._build_native", "pmjax._normals_native"])
def test_a_library_built_from_another_text_of_its_source_is_not_used(tmp_path, monkeypatch, module):
    """Each ctypes library carries the SHA-256 of the source it was built
    from; beside another text of that source (an edit not yet rebuilt) it is
    not loaded, with a warning, and the NumPy steps run."""
    import importlib.util
    import shutil
    import sys

    from pmjax._clib import built_from, open_library

    built = importlib.util.find_spec(module).origin
    name = module.rsplit(".", 1)[-1]
    real = built.rsplit("/", 1)[0] + f"/{name}.c"
    assert open_library(module) is not None and built_from(open_library(module), real)
    # The same library beside an edited copy of its source, as another package.
    pkg = tmp_path / "stalepkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    shutil.copy(built, pkg / built.rsplit("/", 1)[-1])
    (pkg / f"{name}.c").write_text(open(real).read() + "\n/* an edit */\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("stalepkg", None)
    with pytest.warns(RuntimeWarning, match=f"was built from another version of .*{name}.c: rebuild it"):
        assert open_library(f"stalepkg.{name}") is None
