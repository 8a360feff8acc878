"""Shading normals fitted to the original surface: the rule recomputed by
brute force, unit length, stored in the .pmz (old files still read), checked
on load, and no effect on refinement."""

from __future__ import annotations

import dataclasses
import json
import os
import zipfile

import numpy as np
import pytest

import pmjax


@pytest.fixture(scope="module")
def cow(built):
    return built("cow.ply")


def _mesh_after_batch(data, u):
    """The live faces of the mesh just after ``u``'s batch, and each original
    vertex's ancestor in it, from the definitions, vertex by vertex."""
    V0, P = data.n_original_vertices, data.n_pcols
    b = int(np.searchsorted(data.batch_offsets, u - V0, side="right") - 1)
    lo, limit = V0 + int(data.batch_offsets[b]), V0 + int(data.batch_offsets[b + 1])
    parent = np.full(V0 + P, -1)
    parent[data.v1], parent[data.v2] = np.arange(P) + V0, np.arange(P) + V0
    rep = np.arange(V0 + P)
    for x in range(V0 + P):
        while parent[rep[x]] >= 0 and parent[rep[x]] < limit:
            rep[x] = parent[rep[x]]
    corners = rep[data.faces.astype(np.int64)]
    live = corners[(corners[:, 0] != corners[:, 1]) & (corners[:, 1] != corners[:, 2])
                   & (corners[:, 0] != corners[:, 2])]
    return live, rep[:V0], lo, limit


def _brute_force(data, fitted, u):
    """The fitted normal of created vertex ``u`` (whose fan holds no other
    vertex of its batch) from its definition: the least-squares normal over
    the original vertices standing under ``u``, each on the face of ``u``'s
    fan its projection lies in most deeply, the other corners' normals
    fixed at ``fitted``."""
    V0 = data.n_original_vertices
    v = data.vertices.astype(np.float64)
    live, ancestor, lo, limit = _mesh_after_batch(data, u)
    fan = [row for row in live if u in row]
    assert all(w == u or not lo <= w < limit for row in fan for w in row)
    f = data.faces.astype(np.int64)
    cross = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    top, bottom = np.zeros(3), 0.0
    for p in np.flatnonzero(ancestor == u):
        weight = cross[(f == p).any(axis=1)].sum() / 6.0
        best = None
        for row in fan:
            a, b, c = v[row]
            # barycentric coordinates of p's projection on the face's plane
            m = np.stack([b - a, c - a], axis=1)
            b1, b2 = np.linalg.lstsq(m, v[p] - a, rcond=None)[0]
            bary = np.array([1 - b1 - b2, b1, b2])
            if best is None or bary.min() > best[0].min():
                best = (bary, row)
        bary = np.clip(best[0], 0, None)
        bary /= bary.sum()
        k = list(best[1]).index(u)
        rest = sum(bary[j] * fitted[best[1][j]] for j in range(3) if j != k)
        top += weight * bary[k] * (_vertex_normal(data, p) - rest)
        bottom += weight * bary[k] ** 2
    return top / np.linalg.norm(top)


def _vertex_normal(data, w):
    v = data.vertices.astype(np.float64)
    f = data.faces.astype(np.int64)
    around = f[(f == w).any(axis=1)]
    n = np.cross(v[around[:, 1]] - v[around[:, 0]], v[around[:, 2]] - v[around[:, 0]]).sum(axis=0)
    return n / np.linalg.norm(n)


def test_fitted_normals_follow_their_rule(cow):
    fitted = pmjax.fitted_normals(cow)
    V0 = cow.n_original_vertices
    assert fitted.shape == (len(cow.vertices), 3) and fitted.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(fitted, axis=1), 1.0, atol=1e-6)
    # Original vertices keep their own area-weighted normals.
    for w in (0, V0 // 2, V0 - 1):
        np.testing.assert_allclose(fitted[w], _vertex_normal(cow, w), atol=1e-5)
    # Created vertices from the first, a middle and the last batch whose fans
    # hold no other vertex of their batch.
    off = np.asarray(cow.batch_offsets)
    checked = 0
    for b in (0, len(off) // 2, len(off) - 2):
        for p in range(int(off[b]), int(off[b + 1])):
            live, _, lo, limit = _mesh_after_batch(cow, V0 + p)
            fan = live[(live == V0 + p).any(axis=1)]
            if len(fan) and not ((fan >= lo) & (fan < limit) & (fan != V0 + p)).any():
                np.testing.assert_allclose(fitted[V0 + p], _brute_force(cow, fitted, V0 + p), atol=1e-5)
                checked += 1
                break
    assert checked == 3
    # The same normals from the device mesh (parents instead of v1, v2), and
    # the fitted ones are not the plain subtree means.
    pm = pmjax.ProgressiveMesh.from_data(cow)
    np.testing.assert_array_equal(pmjax.fitted_normals(pm), fitted)
    assert np.abs(fitted[V0:] - pmjax.hierarchy_normals(pm)[V0:]).max() > 0.01


def _reference_fitted_normals(data):
    """:func:`pmjax.fitted_normals` in float64 (before rounding) the
    straightforward way, the same arithmetic in the same order: every batch relabels all live faces and
    all samples, locates every sample in one pass with ``[S, 3]`` arrays, and
    sums with ``np.add.at``."""
    V0 = data.n_original_vertices
    v, f = data.vertices.astype(np.float64), data.faces.astype(np.int64)
    parent = np.full(len(v), -1)
    parent[data.v1], parent[data.v2] = np.arange(data.n_pcols), np.arange(data.n_pcols)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    total, area = np.zeros_like(v), np.zeros(len(v))
    for k in range(3):
        np.add.at(total, f[:, k], cross)
        np.add.at(area, f[:, k], np.linalg.norm(cross, axis=1) / 6.0)
    unit = _unit_rows
    target = unit(total[:V0])
    rep, corners, ancestor, out = np.arange(len(v)), f, np.arange(V0), unit(total)
    for b in range(data.n_batches):
        lo, hi = V0 + int(data.batch_offsets[b]), V0 + int(data.batch_offsets[b + 1])
        kids = np.flatnonzero((parent >= lo - V0) & (parent < hi - V0))
        kids = kids[np.argsort(parent[kids], kind="stable")]
        np.add.at(total, V0 + parent[kids], total[kids])
        out[lo:hi] = start = unit(total[lo:hi])
        rep[kids] = V0 + parent[kids]
        corners = rep[corners]
        corners = corners[(corners[:, 0] != corners[:, 1]) & (corners[:, 1] != corners[:, 2])
                          & (corners[:, 0] != corners[:, 2])]
        ancestor = rep[ancestor]
        # Each created vertex's fan, grouped by vertex.
        slot_of, face_of = [], []
        for k in range(3):
            on = np.flatnonzero(corners[:, k] >= lo)
            slot_of.append(corners[on, k] - lo)
            face_of.append(on)
        slot_of, face_of = np.concatenate(slot_of), np.concatenate(face_of)
        fan = face_of[np.argsort(slot_of, kind="stable")]
        size = np.bincount(slot_of, minlength=hi - lo)
        first = np.concatenate([[0], np.cumsum(size)])
        sample = np.flatnonzero(ancestor >= lo)
        sample = sample[size[ancestor[sample] - lo] > 0]
        if not len(sample):
            continue
        # Every sample paired with every face of its fan.
        n = size[ancestor[sample] - lo]
        group = np.concatenate([[0], np.cumsum(n)[:-1]])
        pair = np.repeat(np.arange(len(sample)), n)
        face = fan[np.repeat(first[ancestor[sample] - lo] - group, n) + np.arange(len(pair))]
        tri = corners[face]
        a = v[tri[:, 0]]
        e0, e1, e2 = v[tri[:, 1]] - a, v[tri[:, 2]] - a, v[sample][pair] - a
        d00, d01, d11 = (e0 * e0).sum(1), (e0 * e1).sum(1), (e1 * e1).sum(1)
        d20, d21 = (e2 * e0).sum(1), (e2 * e1).sum(1)
        det = d00 * d11 - d01 * d01
        det = np.where(det > 0, det, 1.0)
        b1, b2 = (d11 * d20 - d01 * d21) / det, (d00 * d21 - d01 * d20) / det
        bary = np.stack([1.0 - b1 - b2, b1, b2], axis=1)
        depth = bary.min(axis=1)
        deepest = np.flatnonzero(depth >= np.maximum.reduceat(depth, group)[pair])
        own = deepest[np.unique(pair[deepest], return_index=True)[1]]
        tri, bary = tri[own], np.clip(bary[own], 0.0, None)
        bary /= np.maximum(bary.sum(axis=1, keepdims=True), np.finfo(float).tiny)
        # Jacobi sweeps, the other corners fixed.
        weight, goal = area[sample], target[sample]
        created = tri >= lo
        slot = np.where(created, tri - lo, 0)
        diagonal = np.zeros(hi - lo)
        for k in range(3):
            on = created[:, k]
            np.add.at(diagonal, slot[on, k], weight[on] * bary[on, k] ** 2)
        fitted = start.copy()
        for _ in range(pmjax._normals.FIT_SWEEPS):
            values = np.where(created[..., None], fitted[slot], out[tri])
            residual = goal - (bary[..., None] * values).sum(axis=1)
            rhs = np.zeros((hi - lo, 3))
            for k in range(3):
                on = created[:, k]
                np.add.at(rhs, slot[on, k], (weight[on] * bary[on, k])[:, None]
                          * (residual[on] + bary[on, k, None] * values[on, k]))
            solved = diagonal > 0
            fitted = np.where(solved[:, None], rhs / np.where(solved, diagonal, 1.0)[:, None], start)
        out[lo:hi] = unit(fitted)
    return out


def _unit_rows(n):
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


def _same_bits(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.fixture(params=["C loops", "NumPy"])
def fit_path(request, monkeypatch):
    """The fit by its C loops (``pmjax/_normals_native.c``, where built) or
    by its NumPy steps."""
    import pmjax._normals

    if request.param == "NumPy":
        monkeypatch.setattr(pmjax._normals, "native", None)
    elif pmjax._normals.native is None:
        if os.environ.get("PMJAX_REQUIRE_CORE") == "1":
            pytest.fail("pmjax._normals_native is not built (python setup.py build_ext --inplace)")
        pytest.skip("the fit's C loops (pmjax._normals_native) are not built")
    return request.param


def test_fitted_normals_equal_the_reference_bit_for_bit(cow, monkeypatch, fit_path):
    """The same bits as the straightforward computation, in float64 before
    the rounding to float32 and after it, by the C loops and by NumPy: on
    the cow, on the cow with its coordinates snapped to a coarse grid
    (degenerate faces, coincident vertices, equally deep faces), with
    samples located a few at a time (NumPy), and with every step of the C
    loops split over one, two and three threads."""
    import pmjax._normals

    def same_as_reference(data):
        expected = _reference_fitted_normals(data)
        by_axis = pmjax._normals._fitted_by_axis(data)
        return (_same_bits(np.ascontiguousarray(by_axis.T), expected)
                and _same_bits(pmjax.fitted_normals(data), expected.astype(np.float32)))

    # The C loops take these hierarchies (they do not hand them to NumPy).
    assert (pmjax._normals._fitted_native(cow) is None) == (fit_path == "NumPy")
    assert same_as_reference(cow)
    snapped = dataclasses.replace(cow, vertices=np.round(cow.vertices * 8.0) / 8.0)
    assert not _same_bits(pmjax.fitted_normals(snapped), pmjax.fitted_normals(cow))
    assert same_as_reference(snapped)
    monkeypatch.setattr(pmjax._normals, "SAMPLE_BLOCK", 5)
    monkeypatch.setattr(pmjax._normals, "FIT_MIN_SPLIT", 1)
    for threads in (1, 2, 3):
        monkeypatch.setattr(pmjax._normals, "FIT_THREADS", threads)
        assert same_as_reference(cow)
    # The positions as float64 (the C loops read them so, not as float32).
    wide = dataclasses.replace(cow, vertices=cow.vertices.astype(np.float64) + 1e-9)
    assert same_as_reference(wide)
    # The hierarchy normals (the fit's starting point) too.
    V0 = cow.n_original_vertices
    v, f = cow.vertices.astype(np.float64), cow.faces.astype(np.int64)
    total = np.zeros_like(v)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    for k in range(3):
        np.add.at(total, f[:, k], cross)
    for p in range(cow.n_pcols):
        total[V0 + p] = total[V0 + p] + total[min(cow.v1[p], cow.v2[p])] + total[max(cow.v1[p], cow.v2[p])]
    assert _same_bits(pmjax.hierarchy_normals(cow), _unit_rows(total).astype(np.float32))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_position_that_is_not_finite_is_refused(cow, fit_path, bad):
    """No fit is defined at a NaN or infinite position: both ways refuse it,
    naming the vertex, instead of returning NaN normals or failing elsewhere."""
    vertices = cow.vertices.copy()
    vertices[17, 1] = bad
    with pytest.raises(ValueError, match="vertex 17 has a position that is not finite"):
        pmjax.fitted_normals(dataclasses.replace(cow, vertices=vertices))


def test_faces_outside_int32_go_to_numpy_with_its_bits(cow):
    """Face ids the C loops cannot take as given (int64 beyond int32, which a
    cast would wrap into range) leave the fit to NumPy: no C call on wrapped
    ids, NumPy's bits for a hierarchy it takes."""
    import pmjax._normals

    if pmjax._normals.native is None:
        pytest.skip("the fit's C loops (pmjax._normals_native) are not built")
    wrapped = np.asarray(cow.faces, np.int64).copy()
    wrapped[0, 0] += 2**32  # wraps to the same id as int32
    assert pmjax._normals._fitted_native(dataclasses.replace(cow, faces=wrapped)) is None
    wide = np.asarray(cow.faces, np.int64)
    assert _same_bits(pmjax._normals._fitted_native(dataclasses.replace(cow, faces=wide)),
                      pmjax._normals._fitted_native(cow))


def test_build_stores_them_and_the_file_round_trips(cow, tmp_path):
    np.testing.assert_array_equal(cow.shading_normals, pmjax.fitted_normals(cow))
    path = tmp_path / "cow.pmz"
    pmjax.save_pm(cow, path)
    back = pmjax.read_pm(path)
    for name, a in cow.arrays().items():
        np.testing.assert_array_equal(getattr(back, name), a, err_msg=name)
    assert "shading_normals" in back.arrays()
    np.testing.assert_array_equal(np.asarray(pmjax.load(path).shading_normals), cow.shading_normals)


def test_a_file_without_them_reads_and_draws_fitted_normals(cow, tmp_path):
    from pmjax.render._offscreen import shading_normals

    old = dataclasses.replace(cow, shading_normals=None)
    path = tmp_path / "old.pmz"
    pmjax.save_pm(old, path, version=1)
    with zipfile.ZipFile(path) as zf:
        assert "shading_normals.npy" not in zf.namelist()
        assert "shading_normals" not in json.loads(zf.read("header.json"))["array_sha256"]
    back = pmjax.read_pm(path)
    assert back.shading_normals is None and "shading_normals" not in back.arrays()
    pm = pmjax.load(path)
    assert pm.shading_normals is None
    np.testing.assert_array_equal(shading_normals(pm), cow.shading_normals)


def test_refinement_is_unchanged_by_them(cow):
    """The cone axes are the stored vertex normals, not the shading normals:
    refining with or without them gives the same bits."""
    with_them = pmjax.ProgressiveMesh.from_data(cow)
    without = pmjax.ProgressiveMesh.from_data(dataclasses.replace(cow, shading_normals=None))
    V0 = cow.n_original_vertices
    np.testing.assert_array_equal(np.asarray(with_them.attributes.axis), cow.normals[V0:].T)
    cams = pmjax.standard_orbit(cow.vertices[:V0], 4, width=320, height=240)
    for i in range(4):
        cam = pmjax.index_camera(cams, i)
        for tau in (0.5, 2.0, 8.0):
            a, b = pmjax.refine(with_them, cam, tau), pmjax.refine(without, cam, tau)
            np.testing.assert_array_equal(np.asarray(a.executed), np.asarray(b.executed))
            assert int(a.n_faces) == int(b.n_faces)


def test_bad_shading_normals_are_refused(cow, tmp_path):
    bad = cow.shading_normals.copy()
    bad[7] *= 2.0
    with pytest.raises(pmjax.PMFormatError, match=r"x\.pmz: shading normal neither unit length nor zero .*index 7\)"):
        pmjax.save_pm(dataclasses.replace(cow, shading_normals=bad), tmp_path / "x.pmz")
    bad[7] = np.nan
    with pytest.raises(pmjax.PMFormatError, match=r"non-finite shading normal \(first at index 7\)"):
        pmjax.validate_pm(dataclasses.replace(cow, shading_normals=bad))
    with pytest.raises(pmjax.PMFormatError, match=r"shading_normals has shape \(5, 3\)"):
        pmjax.validate_pm(dataclasses.replace(cow, shading_normals=bad[:5]))
    # An entry the header's checksums name must be in the archive.
    path = tmp_path / "cow.pmz"
    pmjax.save_pm(cow, path, version=1)
    stripped = tmp_path / "stripped.pmz"
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(stripped, "w") as dst:
        for item in src.infolist():
            if item.filename != "shading_normals.npy":
                dst.writestr(item, src.read(item))
    with pytest.raises(pmjax.PMFormatError, match=r"array 'shading_normals' is missing \(the header has its checksum\)"):
        pmjax.read_pm(stripped)
