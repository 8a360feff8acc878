"""Soft (differentiable) refinement, soft budgets and geomorphs against the hard engine."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmjax
from pmjax._camera import index_camera


# jax.enable_x64 is the newer spelling of jax.experimental.enable_x64.
if hasattr(jax, "enable_x64"):
    ENABLE_X64 = jax.enable_x64
else:  # older jax
    from jax.experimental import enable_x64 as ENABLE_X64


def _pm(built, name):
    data = built(name)
    return data, pmjax.ProgressiveMesh.from_data(data)


def _bounds(data):
    v = data.vertices[: data.n_original_vertices]
    lo, hi = v.min(0), v.max(0)
    return 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply"])
def test_zero_temperature_is_the_hard_refinement(built, name):
    data, pm = _pm(built, name)
    _, diag = _bounds(data)
    V0 = data.n_original_vertices
    cams = pmjax.random_views(data.vertices[:V0], 12, seed=3)
    ablations = [pmjax.ALL_TESTS]
    if name == "cow.ply":
        ablations += [pmjax.Tests(frustum=False), pmjax.Tests(orientation=False, screen=False)]
    partial = 0
    for i in range(12):
        cam, tests, tau = index_camera(cams, i), ablations[i % len(ablations)], [0.5, 1.0, 4.0][i % 3]
        hard = pmjax.refine(pm, cam, tau, tests)
        soft = pmjax.soft_refine(pm, cam, tau, 1e-30, tests=tests)
        w = np.asarray(soft.weight)
        assert set(np.unique(w)) <= {0.0, 1.0}, f"camera {i}: weights are not hard"
        assert np.array_equal(w == 1.0, np.asarray(hard.executed)), f"camera {i}"
        assert np.array_equal(np.asarray(soft.face_weight) == 1.0, np.asarray(hard.active)), f"camera {i}"
        assert float(soft.faces) == int(hard.n_faces)
        want = data.vertices[np.asarray(hard.rep)[:V0]]
        np.testing.assert_allclose(np.asarray(soft.positions), want, rtol=0, atol=1e-5 * diag)
        partial += 0 < int(hard.n_executed) < data.n_pcols
    assert partial >= 6


def test_soft_weights_respect_the_hierarchy(built):
    data, pm = _pm(built, "cow.ply")
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4), 1)
    soft = pmjax.soft_refine(pm, cam, 1.0, 0.3)
    w, c = np.asarray(soft.weight), np.asarray(soft.collapse)
    assert np.mean((w > 1e-3) & (w < 1 - 1e-3)) > 0.1  # really soft at this temperature
    # A pcol's weight is its own collapse times its children's weights.
    child = np.stack([data.v1, data.v2]) - data.n_original_vertices
    kids = np.where(child >= 0, w[np.maximum(child, 0)], 1.0)
    np.testing.assert_allclose(w, c * kids[0] * kids[1], rtol=1e-5)
    assert np.all(w <= np.where(child >= 0, kids, 1.0).min(0) + 1e-7)
    # Softer is not cheaper: a face count between the hard ends.
    assert len(data.faces) > float(soft.faces) > data.header["build"]["base_faces"]


# -- gradients against central differences, float64 ------------------------------------

PARAMETERS = ("eye_x", "eye_z", "fov", "yaw", "tau", "scale")
OUTPUTS = ("faces", "error", "positions")


def _yaw(a):
    c, s = jnp.cos(a), jnp.sin(a)
    return jnp.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@pytest.mark.slow
def test_gradients_match_central_differences(built):
    data, pm32 = _pm(built, "bunny.ply")
    centre, diag = _bounds(data)
    rng = np.random.default_rng(1)
    with ENABLE_X64(True):
        pm = pm32.astype(jnp.float64)
        # Close and off-centre, so the frustum, orientation and screen tests all bite.
        cam0 = pmjax.look_at(centre + np.array([0.3, 0.1, 1.0]) * 0.6 * diag, centre + [0.35 * diag, 0, 0])
        cam0 = cam0.astype(jnp.float64)
        weights = jnp.asarray(rng.normal(size=(data.n_original_vertices, 3)))
        direction = jnp.asarray(rng.normal(size=pm.n_pcols))

        @jax.jit
        def outputs(x):
            """[faces, error, Σ positions·weights] as functions of six parameters."""
            cam = eqx.tree_at(lambda c: (c.eye, c.fov_y, c.rotation), cam0,
                              (cam0.eye + jnp.array([x[0], 0.0, x[1]]) * diag, cam0.fov_y + x[2],
                               cam0.rotation @ _yaw(x[3])))
            soft = pmjax.soft_refine(pm, cam, 1.0 + x[4], 0.5, 1.0 + 0.1 * x[5] * direction)
            return jnp.stack([soft.faces, soft.error, jnp.sum(soft.positions * weights)])

        zero = jnp.zeros(6)
        jac = np.asarray(jax.jit(jax.jacfwd(outputs))(zero))  # [3 outputs, 6 parameters]
        steps = np.array([1e-6, 1e-6, 1e-6, 1e-6, 1e-5, 1e-5])
        for j, (name, h) in enumerate(zip(PARAMETERS, steps)):
            e = np.zeros(6)
            e[j] = h
            fd = (np.asarray(outputs(zero + e)) - np.asarray(outputs(zero - e))) / (2 * h)
            for i, out in enumerate(OUTPUTS):
                assert np.isfinite(jac[i, j]) and abs(fd[i]) > 1e-8, f"{name}/{out}: no signal"
                assert abs(jac[i, j] - fd[i]) <= 1e-4 * abs(fd[i]), \
                    f"d {out} / d {name}: gradient {jac[i, j]} vs central difference {fd[i]}"


@pytest.mark.slow
def test_vmap_and_grad_compose(built):
    data, pm = _pm(built, "cow.ply")
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 4)

    def faces(cam, tau):
        return pmjax.soft_refine(pm, cam, tau, 0.2).faces

    batched = jax.jit(jax.vmap(jax.value_and_grad(faces, argnums=1), in_axes=(0, None)))(cams, jnp.float32(1.0))
    for i in range(4):
        one = jax.value_and_grad(faces, argnums=1)(index_camera(cams, i), jnp.float32(1.0))
        np.testing.assert_allclose(batched[0][i], one[0], rtol=1e-5)
        np.testing.assert_allclose(batched[1][i], one[1], rtol=1e-4)
    assert np.all(np.asarray(batched[1]) < 0)  # a larger tolerance draws fewer faces


def test_bad_temperature_is_refused(built):
    data, pm = _pm(built, "cow.ply")
    cam = index_camera(pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 2), 0)
    with pytest.raises(Exception, match="temperature must be > 0"):
        pmjax.soft_refine(pm, cam, 1.0, 0.0)


# -- budgets ---------------------------------------------------------------------------


@pytest.mark.slow
def test_soft_budget_lanes_converge_alone_and_together(built):
    """Every camera is a lane of one solve: budgets from 0.5 % to 70 % of the
    faces converge to the budget, and a camera's answer does not depend on
    the other cameras of its chunk."""
    data, pm = _pm(built, "cow.ply")
    cams = pmjax.random_views(data.vertices[: data.n_original_vertices], 12, seed=3)
    budgets = np.linspace(0.005, 0.7, 12) * pm.n_faces
    sol = pmjax.soft_tau_for_budget(pm, cams, budgets, chunk=5)  # chunks of 5, the last padded
    steps, ok, faces = np.asarray(sol.steps), np.asarray(sol.converged), np.asarray(sol.soft_faces)
    assert ok.all() and steps.max() <= 12
    solved = steps > 0  # the others were met at the finest tolerance
    assert solved.sum() >= 6
    assert np.all(np.abs(faces[solved] / budgets[solved] - 1) <= 1e-4)
    alone = pmjax.soft_tau_for_budget(pm, index_camera(cams, slice(7, 8)), budgets[7:8])
    assert float(alone.tau[0]) == pytest.approx(float(sol.tau[7]), rel=1e-5)


@pytest.mark.parametrize("budget", [500, 2000, 6000])
@pytest.mark.slow
def test_soft_budget_matches_the_exact_budget(built, budget):
    data, pm = _pm(built, "bunny.ply")
    cams = pmjax.random_views(data.vertices[: data.n_original_vertices], 16, seed=7)
    sol = pmjax.soft_tau_for_budget(pm, cams, budget)
    steps, ok = np.asarray(sol.steps), np.asarray(sol.converged)
    assert ok.all() and steps.max() <= 20
    checked = 0
    for i in range(16):
        cam = index_camera(cams, i)
        tau_exact, faces_exact = pmjax.faces_for_budget(pm, cam, budget)
        finest = int(pmjax.refine(pm, cam, 0.0).n_faces)
        if finest <= budget:  # met without simplifying: both answer the finest tolerance
            assert faces_exact == finest and float(sol.tau[i]) <= 1e-3 * 1.0001
            continue
        checked += 1
        assert abs(float(sol.soft_faces[i]) - budget) <= 1e-3 * budget
        # The hard count at the soft answer lands near the budget, and the two
        # tolerances agree to the softness used (5 % of tau).
        hard = int(pmjax.refine(pm, cam, float(sol.tau[i])).n_faces)
        assert abs(hard - budget) <= 0.1 * budget + 5, f"camera {i}: {hard} faces for a budget of {budget}"
        assert abs(np.log(float(sol.tau[i]) / float(tau_exact))) < 0.15, f"camera {i}"
    assert checked >= 4


# -- geomorphs -------------------------------------------------------------------------


def test_geomorph_at_rest_is_the_hard_mesh_and_reaches_its_target(built):
    data, pm = _pm(built, "bunny.ply")
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 24)
    a = pmjax.refine(pm, index_camera(cams, 0), 1.0)
    b = pmjax.refine(pm, index_camera(cams, 6), 0.5)
    v, f, ids = a.mesh(pm)
    gv, gf, gids = pmjax.geomorph_mesh(pm, pmjax.geomorph_start(a.executed))
    assert np.array_equal(ids, gids) and np.array_equal(f, gf) and np.array_equal(v, gv)
    state, frames = pmjax.geomorph_start(a.executed), 4
    child = np.stack([data.v1, data.v2]) - data.n_original_vertices
    for k in range(frames):
        state = pmjax.geomorph_step(pm, state, b.executed, frames)
        w = np.asarray(state.weight)
        moving = np.asarray(a.executed) != np.asarray(b.executed)
        if k < frames - 1:
            assert np.all((w[moving] > 0) & (w[moving] < 1))
        # Never more collapsed than its children: the blend is a valid state.
        kids = np.where(child >= 0, w[np.maximum(child, 0)], 1.0)
        assert np.all(w <= kids.min(0) + 1e-7)
    assert np.array_equal(np.asarray(state.weight) == 1.0, np.asarray(b.executed))
    v, f, ids = b.mesh(pm)
    gv, gf, gids = pmjax.geomorph_mesh(pm, state)
    assert np.array_equal(ids, gids) and np.array_equal(f, gf)
    np.testing.assert_allclose(gv, v, atol=1e-6)


def test_geomorph_jumps_out_of_sight_and_stays_a_valid_state(built):
    """Pcols culled in this frame or the last jump to their target (they are
    out of sight); the visible ones walk; the clamp keeps every pcol no more
    collapsed than its children; after ``frames`` steps the state is the target."""
    data, pm = _pm(built, "bunny.ply")
    cams = pmjax.standard_orbit(data.vertices[: data.n_original_vertices], 24)
    ca, cb = index_camera(cams, 0), index_camera(cams, 6)
    a, b = pmjax.refine(pm, ca, 1.0), pmjax.refine(pm, cb, 0.5)
    ha, hb = np.asarray(pmjax.hidden_pcols(pm, ca)), np.asarray(pmjax.hidden_pcols(pm, cb))
    # Hidden means collapsed whatever tau, so hidden pcols are executed.
    assert ha.any() and np.all(np.asarray(a.executed)[ha]) and np.all(np.asarray(b.executed)[hb])
    target = np.asarray(b.executed, np.float32)
    moving = np.asarray(a.executed) != np.asarray(b.executed)
    jump = ha | hb
    assert (moving & jump).sum() > 10 and (moving & ~jump).sum() > 10
    child = np.stack([data.v1, data.v2]) - data.n_original_vertices
    state, frames = pmjax.geomorph_start(a.executed, ha), 4
    for k in range(frames):
        state = pmjax.geomorph_step(pm, state, b.executed, frames, hb)
        w = np.asarray(state.weight)
        assert np.array_equal(w[jump], target[jump])
        kids = np.where(child >= 0, w[np.maximum(child, 0)], 1.0)
        assert np.all(w <= kids.min(0))
        if k == 0:
            # The visible changes walk (or are held open by a child that jumped open).
            walked = moving & ~jump & (w > 0) & (w < 1)
            assert walked.sum() > 0.5 * (moving & ~jump).sum()
    assert np.array_equal(np.asarray(state.weight), target)
