"""Fuzz: random small meshes through clean → build → check → save → load →
refine → oracle.

Every mesh is built on its own and checked (the linear structure check and
the slow replay of check_invariants, both on the builder's output and after a
save/read round trip). The engine's compile depends on the hierarchy's batch
structure, so the refine-against-oracle step builds groups of meshes side by
side as one multi-part model (one compile per group).

``PMJAX_FUZZ=N`` sets the number of meshes (default 300, about a minute);
``PMJAX_FUZZ_SEED`` the seed. A long manual run::

    PMJAX_FUZZ=5000 PMJAX_FUZZ_SEED=1 pytest tests/test_fuzz.py -q
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import ConvexHull

import pmjax
from pmjax._oracle import oracle_refine
from pmjax.builders import BuildOptions, build_pm

N = int(os.environ.get("PMJAX_FUZZ", "300"))
SEED = int(os.environ.get("PMJAX_FUZZ_SEED", "0"))
GROUP = 60


def _blob(rng):
    """A closed, bumpy convex-hull surface."""
    p = rng.normal(size=(int(rng.integers(8, 120)), 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    p *= 1 + 0.3 * rng.random((len(p), 1))
    return p, ConvexHull(p).simplices


def _sheet(rng):
    """An open grid patch with noise (a border everywhere)."""
    n, m = (int(x) for x in rng.integers(2, 12, 2))
    x, y = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    p = np.stack([x.ravel(), y.ravel(), 0.2 * rng.normal(size=n * m)], 1).astype(float)
    i = (x[:-1, :-1] * m + y[:-1, :-1]).ravel()
    faces = np.concatenate([np.stack([i, i + m, i + 1], 1), np.stack([i + 1, i + m, i + m + 1], 1)])
    return p, faces


def _tangle(rng):
    """Random triangles over few vertices: non-manifold edges, repeated and
    degenerate faces, unused vertices."""
    p = rng.normal(size=(int(rng.integers(4, 30)), 3))
    return p, rng.integers(0, len(p), size=(int(rng.integers(1, 60)), 3))


def _soup(rng):
    """A blob stored as a triangle soup (one vertex per corner, like STL)."""
    p, f = _blob(rng)
    return p[f.ravel()], np.arange(3 * len(f)).reshape(-1, 3)


def random_mesh(rng):
    """One random mesh: a shape, then a random scale, offset (up to 60 sizes
    from the origin), duplicated vertices and NaN coordinates."""
    p, f = [_blob, _sheet, _tangle, _soup][int(rng.integers(4))](rng)
    p = p * 10.0 ** rng.uniform(-3, 3)
    size = np.ptp(p, axis=0).max()
    if rng.random() < 0.3:
        p = p + rng.uniform(-60, 60, 3) * size
    if rng.random() < 0.2:  # duplicate a few vertices and point some faces at the copies
        k = int(rng.integers(1, len(p) + 1))
        src = rng.integers(0, len(p), k)
        copy = np.full(len(p), -1)
        copy[src] = len(p) + np.arange(k)
        f = np.where((rng.random(f.shape) < 0.3) & (copy[f] >= 0), copy[f], f)
        p = np.concatenate([p, p[src]])
    if rng.random() < 0.1:
        p = p.copy()
        p[rng.integers(0, len(p))] = np.nan
    return p, np.asarray(f, np.int64)


def _cleaned_meshes():
    rng = np.random.default_rng(SEED)
    out, refused = [], 0
    for _ in range(N):
        p, f = random_mesh(rng)
        try:
            v, faces, _, _ = pmjax.clean_mesh(p, f)
        except pmjax.MeshError:
            refused += 1  # nothing usable left: a clear refusal is the right outcome
            continue
        out.append((v, faces, BuildOptions(pair_distance=float(rng.choice([0.0, 0.0, 0.1])))))
    return out, refused


@pytest.fixture(scope="module")
def meshes():
    return _cleaned_meshes()


@pytest.mark.slow
def test_every_random_mesh_builds_a_valid_hierarchy(meshes, tmp_path):
    cleaned, refused = meshes
    assert len(cleaned) > 0.7 * N  # most random meshes are usable
    for i, (v, f, options) in enumerate(cleaned):
        data = build_pm(v, f, options)
        pmjax.check_structure(data, source=f"mesh {i}")
        pmjax.check_invariants(data)
        path = tmp_path / "m.pmz"
        pmjax.save_pm(data, path)
        back = pmjax.read_pm(path)
        for name, a in data.arrays().items():
            assert np.array_equal(a, getattr(back, name)), (i, name)


def _side_by_side(group):
    """Meshes of a group laid out along x, one part each, scaled to unit size."""
    vs, fs, x, n = [], [], 0.0, 0
    for v, f, _ in group:
        v = v - v.min(axis=0)
        v = v / max(np.ptp(v, axis=0).max(), 1e-30)
        vs.append(v + [x, 0.0, 0.0])
        fs.append(f + n)
        x += 1.5
        n += len(v)
    return np.concatenate(vs), np.concatenate(fs)


@pytest.mark.slow
def test_refinement_of_random_meshes_equals_the_oracle(meshes, tmp_path):
    cleaned, _ = meshes
    rng = np.random.default_rng(SEED + 1)
    partial = 0
    for g in range(0, len(cleaned), GROUP):
        v, f = _side_by_side(cleaned[g:g + GROUP])
        v, f, _, _ = pmjax.clean_mesh(v, f)
        data = build_pm(v, f, BuildOptions(pair_distance=float(rng.choice([0.0, 0.02]))))
        path = tmp_path / "group.pmz"
        pmjax.save_pm(data, path)
        pm = pmjax.load(path)
        cams = pmjax.random_views(v, 4, seed=g)
        for k in range(4):
            cam = pmjax.index_camera(cams, k)
            tau = float(rng.choice([0.0, 0.5, 1.0, 4.0, 1e6]))
            collapse = np.asarray(pmjax.collapse_mask(pm.attributes, cam, jnp.float32(tau)))
            want_exec, want_faces = oracle_refine(data, collapse)
            for method in ("dense", "front"):
                r = pmjax.refine(pm, cam, tau, method=method)
                assert np.array_equal(np.asarray(r.executed), want_exec), (g, k, method)
                assert int(r.n_faces) == len(want_faces), (g, k, method)
            partial += 0 < want_exec.sum() < data.n_pcols
        # Each group's batch structure compiles its own kernels: free them, or a
        # long run exhausts the process's memory maps (as pmjax eval's model LRU does).
        jax.clear_caches()
    assert partial >= 3
