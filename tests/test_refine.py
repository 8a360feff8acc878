"""The refinement engine against a plain sequential oracle (the paper's Fig. 6)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmjax
from pmjax._camera import index_camera
from pmjax._model import kill_summary
from pmjax._oracle import oracle_refine as oracle
from pmjax import collapse_mask


def face_set(faces):
    return set(map(tuple, np.sort(faces, axis=1).tolist()))


CASES = [("cow.ply", 0.0), ("bunny.ply", 0.0), ("cessna.ply", 0.02), ("terrain_gcanyon.ply", 0.0)]


@pytest.mark.parametrize("name, pair_distance", CASES)
@pytest.mark.slow
def test_engine_equals_oracle_on_50_random_views(built, name, pair_distance):
    data = built(name, pair_distance)
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = pmjax.random_views(data.vertices[: data.n_original_vertices], 50, seed=len(name))
    seen_partial = 0
    for i in range(50):
        cam = index_camera(cams, i)
        tau = [0.5, 1.0, 3.0][i % 3]
        collapse = np.asarray(collapse_mask(pm.attributes, cam, jnp.float32(tau)))
        want_exec, want_faces = oracle(data, collapse)
        r = pmjax.refine(pm, cam, tau)
        assert np.array_equal(np.asarray(r.executed), want_exec), f"camera {i}"
        got = np.asarray(r.rep)[data.faces[np.asarray(r.active)]]
        assert face_set(got) == face_set(want_faces), f"camera {i}"
        assert int(r.n_faces) == len(want_faces)
        seen_partial += 0 < want_exec.sum() < data.n_pcols
    assert seen_partial > 10  # the views really exercise partial refinements


def test_tau_zero_with_tests_off_is_the_original_mesh(built):
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4), 1)
    r = pmjax.refine(pm, cam, 0.0, tests=pmjax.Tests(frustum=False, orientation=False))
    assert int(r.n_executed) == 0 and int(r.n_faces) == len(data.faces)
    v, f, _ = r.mesh(pm)
    assert len(f) == len(data.faces) and len(v) == data.n_original_vertices


def test_camera_seeing_nothing_collapses_to_the_base_mesh(built):
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    V0 = data.n_original_vertices
    centre = data.vertices[:V0].mean(0)
    cam = pmjax.look_at(centre + [0, 0, 1.0], centre + [0, 0, 2.0])  # looking away
    r = pmjax.refine(pm, cam, 1.0, tests=pmjax.Tests(orientation=False, screen=False))
    assert int(r.n_executed) == data.n_pcols
    assert int(r.n_faces) == data.header["build"]["base_faces"]


def test_ablations_and_monotonicity_in_tau(built):
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4), 0)
    faces = [int(pmjax.refine(pm, cam, t).n_faces) for t in (0.25, 0.5, 1, 2, 4, 8)]
    assert faces == sorted(faces, reverse=True) and faces[0] > faces[-1]
    full = int(pmjax.refine(pm, cam, 1.0).n_faces)
    for tests in (pmjax.Tests(frustum=False), pmjax.Tests(orientation=False), pmjax.Tests(screen=False)):
        assert int(pmjax.refine(pm, cam, 1.0, tests=tests).n_faces) >= full
    # Orbit view with the model in frame: the back faces are culled.
    no_orient = int(pmjax.refine(pm, cam, 1.0, tests=pmjax.Tests(orientation=False)).n_faces)
    assert no_orient > full


@pytest.mark.slow
def test_user_predicate_or_and_replace(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4), 0)
    # Collision-detection style: collapse everything farther than a plane.
    cut = float(np.median(data.vertices[:, 0]))
    far_side = lambda attrs, ctx: attrs.position[:, 0] - attrs.radius > ctx
    base = pmjax.refine(pm, cam, 1.0)
    ored = pmjax.refine(pm, cam, 1.0, predicate=far_side, context=jnp.float32(cut))
    only = pmjax.refine(pm, cam, 0.0, predicate=far_side, context=jnp.float32(cut), combine="replace")
    assert int(ored.n_faces) < int(base.n_faces)
    e_only = np.asarray(only.executed)
    assert e_only.any()
    assert np.all(data.vertices[data.n_original_vertices:][e_only, 0] > cut)
    # A context of any pytree: arrays are traced, other leaves (a string, an
    # axis number) are static, as in jax.jit's static arguments.
    side = lambda attrs, ctx: (attrs.position[:, ctx["axis"]] > ctx["cut"]) == (ctx["side"] == "above")
    for which in ("above", "below"):
        ctx = {"axis": 0, "cut": jnp.float32(cut), "side": which}
        got = np.asarray(pmjax.refine(pm, cam, 0.0, predicate=side, context=ctx, combine="replace").executed)
        want = np.asarray(pmjax.refine(pm, cam, 0.0, predicate=lambda a, c: side(a, ctx), combine="replace").executed)
        assert got.any() and np.array_equal(got, want)


@pytest.mark.slow
def test_critical_tolerances_reproduce_every_tau(built):
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = pmjax.random_views(data.vertices[: data.n_original_vertices], 6, seed=3)
    for i in range(6):
        cam = index_camera(cams, i)
        eps = np.asarray(pmjax.critical_tolerances(pm, cam))
        for tau in (0.3, 1.0, 2.5):
            executed = np.asarray(pmjax.refine(pm, cam, tau).executed)
            # Exact: the hard test is computed through the same tolerances.
            assert np.array_equal(executed, np.float32(tau) > eps)


@pytest.mark.slow
def test_critical_tau_is_the_exact_switch_of_the_hard_test(built):
    """At tau = t_p a pcol does not collapse, one float32 step above it does:
    the bisection finds the switch of the hard comparisons bit for bit, also
    for orthographic views (perspective views are also covered above)."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    v0 = data.vertices[: data.n_original_vertices]
    cams = [index_camera(pmjax.random_views(v0, 2, seed=11), i) for i in range(2)]
    ortho = pmjax.look_at(v0.mean(0) + [0.0, 0.0, 1.0], v0.mean(0), orthographic=True, ortho_height=0.3,
                          near=1e-3, far=10.0)
    rng = np.random.default_rng(0)
    no_cull = pmjax.Tests(frustum=False, orientation=False)
    for cam in cams + [ortho]:
        t = np.asarray(pmjax.critical_tau(pm.attributes, cam, no_cull))
        finite = np.flatnonzero(np.isfinite(t) & (t > 0))
        assert len(finite) > 100
        for p in rng.choice(finite, 12, replace=False):
            at = np.asarray(collapse_mask(pm.attributes, cam, jnp.float32(t[p]), no_cull))
            above = np.asarray(collapse_mask(pm.attributes, cam, np.nextafter(t[p], np.float32(np.inf)), no_cull))
            assert not at[p] and above[p], f"pcol {p}, t_p = {t[p]!r}"
            # Every other pcol switches consistently with its own t_p as well.
            assert np.array_equal(at, t[p] > t)


@pytest.mark.slow
def test_faces_for_budget_is_exact(built):
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4), 2)
    for budget in (800, 3000, 10000):
        tau, faces = pmjax.faces_for_budget(pm, cam, budget)
        assert faces <= budget
        assert int(pmjax.refine(pm, cam, float(tau)).n_faces) == faces
        # Any smaller tau gives more faces than the budget.
        below = np.nextafter(np.float32(tau), np.float32(0))
        assert int(pmjax.refine(pm, cam, float(below)).n_faces) > budget


@pytest.mark.parametrize("common", ["most", 0, 7])
@pytest.mark.slow
def test_batched_face_count_for_any_kills(built, common, monkeypatch):
    """The batched face count (``common_kills`` per executed pcol plus bit-plane
    corrections for the others) equals the direct sum over executed pcols,
    whatever the kills and whichever base is used. (Kills that are not the
    counts of ``killer``, as here, are refused by the public calls: that
    check is off to test the arithmetic alone.)"""
    monkeypatch.setattr(pmjax._arguments, "check_kills", lambda pm, call: None)
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = pmjax.random_views(data.vertices[: data.n_original_vertices], 40, seed=2)
    executed = pmjax.refine_batch(pm, cams, 1.0, chunk=32, return_masks=True)["executed"]
    assert 0 < executed.sum() < executed.size
    rng = np.random.default_rng(1)
    P = data.n_pcols
    for kills in (rng.integers(0, 6, P), np.full(P, 3), np.where(rng.random(P) < 0.9, 2, rng.integers(0, 9, P))):
        fake = dataclasses.replace(pm, **kill_summary(kills, None if common == "most" else common))
        got = pmjax.refine_batch(fake, cams, 1.0, chunk=32)
        assert np.array_equal(got["faces"], len(data.faces) - executed.astype(np.int64) @ kills)
        assert np.array_equal(got["executed_count"], executed.sum(1))


def test_refine_batch_equals_single_refines(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = pmjax.random_views(data.vertices[: data.n_original_vertices], 37, seed=5)
    out = pmjax.refine_batch(pm, cams, 1.0, chunk=8, return_masks=True)
    for i in range(37):
        r = pmjax.refine(pm, index_camera(cams, i), 1.0)
        assert out["faces"][i] == int(r.n_faces)
        assert out["vertices"][i] == int(r.n_vertices)
        assert np.array_equal(out["executed"][i], np.asarray(r.executed))


def test_bad_tau_and_camera_batches_are_refused(built):
    data = built("cow.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cams = pmjax.random_views(data.vertices[: data.n_original_vertices], 2)
    with pytest.raises(ValueError, match="tau"):
        pmjax.refine_batch(pm, cams, -1.0)
    with pytest.raises(ValueError, match="camera batch"):
        pmjax.refine_batch(pm, index_camera(cams, 0), 1.0)
    # A host tau is checked before the call; a device tau inside the kernel.
    with pytest.raises(ValueError, match="tau must be >= 0"):
        pmjax.refine(pm, index_camera(cams, 0), float("nan"))
    with pytest.raises(ValueError, match="tau must be >= 0"):
        pmjax.refine(pm, index_camera(cams, 0), -0.5)
    with pytest.raises(ValueError, match="tau must be one number"):
        pmjax.refine(pm, index_camera(cams, 0), np.ones(2))
    with pytest.raises(Exception, match="tau must be >= 0"):
        jax.block_until_ready(pmjax.refine(pm, index_camera(cams, 0), jnp.float32(-1.0)))


@pytest.mark.slow
def test_refined_mesh_covers_the_same_screen_area(built):
    """Projected coverage of refined vs original (software raster of the silhouette)."""
    data = built("bunny.ply")
    pm = pmjax.ProgressiveMesh.from_data(data)
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4), 0)
    r = pmjax.refine(pm, cam, 0.5)
    v, f, _ = r.mesh(pm)
    ref = coverage(cam, data.vertices[: data.n_original_vertices], data.faces)
    got = coverage(cam, v, f)
    assert len(f) < 0.3 * len(data.faces)
    assert np.sum(ref != got) / max(1, ref.sum()) < 0.02


def coverage(cam, vertices, faces, w=200, h=150):
    """Boolean image of pixels covered by any triangle (centre sampling)."""
    R = np.asarray(cam.rotation, np.float64)
    p = (np.asarray(vertices, np.float64) - np.asarray(cam.eye)) @ R  # camera coordinates
    t = np.tan(0.5 * float(cam.fov_y))
    x = p[:, 0] / (-p[:, 2] * t * cam.width / cam.height)
    y = p[:, 1] / (-p[:, 2] * t)
    px = (x + 1) * 0.5 * w
    py = (1 - y) * 0.5 * h
    img = np.zeros((h, w), bool)
    faces = np.asarray(faces)
    xs, ys = px[faces], py[faces]  # [F, 3]
    x0 = np.maximum(0, np.floor(xs.min(1))).astype(int)
    y0 = np.maximum(0, np.floor(ys.min(1))).astype(int)
    x1 = np.minimum(w, np.ceil(xs.max(1))).astype(int)
    y1 = np.minimum(h, np.ceil(ys.max(1))).astype(int)

    def inside(xs, ys, X, Y):
        # Edge functions of each triangle at pixel centres X, Y (either winding).
        d = [(xs[:, (k + 1) % 3, None] - xs[:, k, None]) * (Y - ys[:, k, None])
             - (ys[:, (k + 1) % 3, None] - ys[:, k, None]) * (X - xs[:, k, None]) for k in range(3)]
        return ((d[0] >= 0) & (d[1] >= 0) & (d[2] >= 0)) | ((d[0] <= 0) & (d[1] <= 0) & (d[2] <= 0))

    # Small triangles (bounding box within 4 x 4 pixels, nearly all of them):
    # their candidate pixel centres at once.
    small = (x1 - x0 <= 4) & (y1 - y0 <= 4) & (x1 > x0) & (y1 > y0)
    gy, gx = np.mgrid[0:4, 0:4]
    X = x0[small, None] + gx.reshape(1, -1)
    Y = y0[small, None] + gy.reshape(1, -1)
    hit = inside(xs[small], ys[small], X + 0.5, Y + 0.5) & (X < x1[small, None]) & (Y < y1[small, None])
    img[Y[hit], X[hit]] = True
    # The others one by one.
    gy, gx = np.mgrid[0:h, 0:w] + 0.5
    for f in np.flatnonzero(~small & (x1 > x0) & (y1 > y0)):
        X, Y = gx[y0[f]:y1[f], x0[f]:x1[f]].reshape(1, -1), gy[y0[f]:y1[f], x0[f]:x1[f]].reshape(1, -1)
        img[y0[f]:y1[f], x0[f]:x1[f]] |= inside(xs[f:f + 1], ys[f:f + 1], X, Y).reshape(y1[f] - y0[f], x1[f] - x0[f])
    return img


@pytest.mark.parametrize("orthographic", [False, True])
@pytest.mark.slow
def test_frustum_test_is_the_six_planes(orthographic):
    """The camera-space sphere test (one |x| test per pair of side planes)
    decides as the six frustum planes do, in float64, away from float ties."""
    from pmjax._model import PcolAttributes

    rng = np.random.default_rng(11)
    target = np.array([0.5, -0.2, 1.0])
    cam = pmjax.look_at(target + [3.0, 1.0, 4.0], target, fov_y_deg=50, width=640, height=400, near=2.0,
                        far=9.0, orthographic=orthographic, ortho_height=3.0)
    n = 40_000
    centers = target + rng.normal(scale=3.0, size=(n, 3))
    radius = rng.uniform(0.0, 1.5, n)
    planes = np.asarray(cam.frustum_planes(), np.float64)
    signed = centers @ planes[:, :3].T + planes[:, 3]  # [n, 6], positive inside
    beyond = signed < -radius[:, None]
    unit = np.zeros((n, 3))
    attrs = PcolAttributes.from_arrays(centers, unit, radius, np.zeros(n), np.zeros(n), np.zeros(n))
    got = np.asarray(pmjax.outside_frustum(attrs, cam))
    clear = np.min(np.abs(signed + radius[:, None]), axis=1) > 1e-4
    assert clear.mean() > 0.99
    # Every plane culls some spheres on its own, and some spheres are inside.
    assert np.all((beyond & (beyond.sum(1) == 1)[:, None]).any(0)) and (~beyond.any(1)).any()
    assert np.array_equal(got[clear], beyond.any(1)[clear])


@pytest.mark.parametrize("orthographic", [False, True])
def test_orientation_test_is_the_cone_angle_sum(orthographic):
    """The root-free orientation test decides as its definition, in float64:
    every normal of the cone faces away from every eye ray into the sphere,
    ``theta + alpha + beta < pi/2`` (``beta`` = 0 for orthographic views),
    away from float ties."""
    from pmjax._model import PcolAttributes

    rng = np.random.default_rng(12)
    target = np.array([0.5, -0.2, 1.0])
    cam = pmjax.look_at(target + [3.0, 1.0, 4.0], target, fov_y_deg=50, width=640, height=400,
                        orthographic=orthographic, ortho_height=3.0)
    n = 40_000
    centers = target + rng.normal(scale=3.0, size=(n, 3))
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    alpha = rng.uniform(0.0, 2.0, n)  # past pi/2 too: such a cone never faces away
    radius = rng.uniform(0.0, 2.0, n)
    eye = np.asarray(cam.eye, np.float64)
    if orthographic:
        forward = np.asarray(cam.frustum_frame()[0], np.float64)[2]
        theta, beta = np.arccos(np.clip(axes @ forward, -1, 1)), np.zeros(n)
    else:
        off = centers - eye
        d = np.linalg.norm(off, axis=1)
        theta = np.arccos(np.clip(np.sum(off * axes, 1) / d, -1, 1))
        beta = np.where(radius < d, np.arcsin(np.minimum(radius / d, 1)), np.inf)
    margin = theta + alpha + beta - np.pi / 2
    want = margin < 0
    attrs = PcolAttributes.from_arrays(centers, axes, radius, alpha, np.zeros(n), np.zeros(n))
    got = np.asarray(pmjax.oriented_away(attrs, cam))
    clear = np.abs(margin) > 1e-4
    assert clear.mean() > 0.99 and 0.05 < want.mean() < 0.95
    assert np.array_equal(got[clear], want[clear])
