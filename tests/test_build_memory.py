"""The builder's memory-bounded steps against the one-step ones: the initial
quadrics, normals and cone angles summed over faces in chunks, the edges
counted into arrays of their exact size, and faces taken in any integer
type, all give the same hierarchy bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

import pmjax
from pmjax.builders import BuildOptions, build_pm
from pmjax.builders import _attributes, _quadrics, _topology
from pmjax.builders import _native as native
from pmjax.builders._build import vertex_normals

pytestmark = pytest.mark.core


@pytest.fixture(scope="module")
def bunny(data_path):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("bunny.ply"))
    return v, f


def test_chunked_build_is_the_one_step_build(built, bunny, monkeypatch, assert_same_pm):
    """The bunny (open borders: the border planes' rows too) built with the
    initial sums in chunks of 1,000 faces, against one step (its 69,451
    faces are below the default chunk)."""
    v, f = bunny
    assert len(f) < _quadrics.CHUNK_FACES
    monkeypatch.setattr(_quadrics, "CHUNK_FACES", 1000)
    assert_same_pm(built("bunny.ply"), build_pm(v, f))


def test_chunked_build_with_options_is_the_one_step_build(data_path, monkeypatch, assert_same_pm):
    """Border weight and a metric schedule, chunks that do not divide the faces."""
    v, f, _, _ = pmjax.load_clean_mesh(data_path("terrain_gcanyon.ply"))
    options = BuildOptions(metric="edge:2,quadric", boundary_weight=2.5, target_faces=2000)
    one = build_pm(v, f, options)
    monkeypatch.setattr(_quadrics, "CHUNK_FACES", 997)
    assert_same_pm(one, build_pm(v, f, options))


@pytest.mark.parametrize("chunk", [101, 10_000])
def test_initial_sums_in_chunks(bunny, chunk):
    """Quadrics (with border planes), vertex normals and cone angles: chunks
    against one step, and against the NumPy sums where the C loops are off."""
    v, f = bunny
    n = len(v)
    edges = _topology.unique_edges(f)
    whole = _quadrics.vertex_quadrics(v, f, n, 1.5, edges, chunk=len(f))
    parts = _quadrics.vertex_quadrics(v, f, n, 1.5, edges, chunk=chunk)
    assert parts.tobytes() == whole.tobytes()
    out = np.zeros((n, 10))
    assert _quadrics.vertex_quadrics(v, f, n, 1.5, edges, out=out, chunk=chunk) is out
    assert out.tobytes() == whole.tobytes()
    normals = vertex_normals(v, f, n, chunk=len(f))
    assert vertex_normals(v, f, n, chunk=chunk).tobytes() == normals.tobytes()
    cones = _attributes.original_cone_angles(v, normals, f, chunk=len(f))
    assert _attributes.original_cone_angles(v, normals, f, chunk=chunk).tobytes() == cones.tobytes()
    with native.use_native(False):
        assert _quadrics.vertex_quadrics(v, f, n, 1.5, edges, chunk=chunk).tobytes() == whole.tobytes()
        assert vertex_normals(v, f, n).tobytes() == normals.tobytes()


def test_vertex_quadrics_refuses_a_wrong_out(bunny):
    v, f = bunny
    with pytest.raises(ValueError, match="contiguous float64"):
        _quadrics.vertex_quadrics(v, f, len(v), out=np.zeros((len(v), 9)))


def test_scatter_add_in_steps_is_one_step():
    """Sums into one ``out`` over consecutive parts of the index: the same
    bits as one call (the order of the additions per row is kept)."""
    if not native.available():
        pytest.skip("the C loops are not built")
    rng = np.random.default_rng(3)
    values = rng.normal(size=(4, 500))
    index = rng.integers(0, 37, 1500)
    whole = native.scatter_add(values, index, 37, repeat=3)
    out = np.zeros((37, 4))
    for lo in range(0, 500, 77):
        native.scatter_add(values[:, lo:lo + 77], index[3 * lo:3 * (lo + 77)], 37, repeat=3, out=out)
    assert out.tobytes() == whole.tobytes()
    with pytest.raises(ValueError, match="contiguous float64"):
        native.scatter_add(values, index, 37, repeat=3, out=np.zeros((37, 4), np.float32))


def test_edges_come_in_their_own_arrays(bunny):
    """The counted edges own arrays of the distinct count (no view keeps the
    three keys per face alive), equal to NumPy's ``np.unique``."""
    _, f = bunny
    got = _topology.unique_edges(f)
    with native.use_native(False):
        want = _topology.unique_edges(f)
    for g, w in zip(got, want):
        assert g.tobytes() == w.tobytes() and g.dtype == w.dtype
        assert g.base is None and g.shape == (len(want[3]),)


def test_faces_of_any_integer_type(built, bunny, assert_same_pm):
    """int64 and uint32 faces build the int32 faces' hierarchy; ids outside
    the vertices and non-integer faces are refused, naming the remedy."""
    v, f = bunny
    ref = built("bunny.ply")
    assert_same_pm(ref, build_pm(v, f.astype(np.int64)))
    assert_same_pm(ref, build_pm(v, f.astype(np.uint32)))
    bad = f.astype(np.int64)
    bad[5, 1] = len(v)
    with pytest.raises(ValueError, match="outside 0 .. .*clean_mesh"):
        build_pm(v, bad)
    bad[5, 1] = -1
    with pytest.raises(ValueError, match="outside 0 .. "):
        build_pm(v, bad)
    with pytest.raises(ValueError, match="integer faces"):
        build_pm(v, f.astype(np.float64))


@pytest.mark.parametrize(
    "name, options",
    [
        ("bunny.ply", dict()),
        ("cow.ply", dict(batch_share=0.15, target_faces=300)),
    ],
)
def test_shading_normals_are_fitted_normals(data_path, name, options, monkeypatch):
    """The shading normals a build stores are ``fitted_normals`` of the
    finished hierarchy, bit for bit, also where a target stops the build
    inside a batch and where the initial sums are made in chunks."""
    from pmjax._normals import fitted_normals

    monkeypatch.setattr(_quadrics, "CHUNK_FACES", 1000)
    v, f, _, _ = pmjax.load_clean_mesh(data_path(name))
    pm = build_pm(v, f, BuildOptions(**options))
    want = fitted_normals(pm)
    assert pm.shading_normals.dtype == want.dtype and pm.shading_normals.shape == want.shape
    assert pm.shading_normals.tobytes() == want.tobytes()
    assert np.abs(np.linalg.norm(want[pm.n_original_vertices:], axis=1) - 1).max() < 1e-6
