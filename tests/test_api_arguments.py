"""Wrong arguments to the public refinement calls: a TypeError or ValueError
that names the call and the argument, before any work."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmjax


@pytest.fixture(scope="module")
def models(built):
    data = built("cow.ply")
    return data, pmjax.ProgressiveMesh.from_data(data)


@pytest.fixture(scope="module")
def cameras():
    one = pmjax.look_at(eye=[0.0, 0.0, 3.0], target=[0.0, 0.0, 0.0])
    return one, pmjax.stack_cameras([one, one])


CALLS = {
    "refine": lambda pm, one, many: pmjax.refine(pm, one, 1.0),
    "refine_batch": lambda pm, one, many: pmjax.refine_batch(pm, many, 1.0),
    "faces_for_budget": lambda pm, one, many: pmjax.faces_for_budget(pm, one, 100),
    "path_counts": lambda pm, one, many: pmjax.path_counts(pm, many, 1.0),
    "soft_refine": lambda pm, one, many: pmjax.soft_refine(pm, one, 1.0),
    "soft_tau_for_budget": lambda pm, one, many: pmjax.soft_tau_for_budget(pm, many, 1000),
}


@pytest.mark.parametrize("call", sorted(CALLS))
def test_host_arrays_instead_of_a_mesh_say_how_to_load_one(models, cameras, call):
    data, _ = models
    with pytest.raises(TypeError, match=rf"^{call}: pm is a PMData .*pmjax\.load\(path\)"):
        CALLS[call](data, *cameras)
    with pytest.raises(TypeError, match=rf"^{call}: pm must be a ProgressiveMesh .*got str"):
        CALLS[call]("cow.pmz", *cameras)


@pytest.mark.parametrize("call", ["refine", "faces_for_budget", "soft_refine"])
def test_a_batch_where_one_camera_is_expected(models, cameras, call):
    _, pm = models
    one, many = cameras
    with pytest.raises(ValueError, match=rf"^{call}: takes one camera .*a batch of 2 cameras.*index_camera"):
        CALLS[call](pm, many, many)


@pytest.mark.parametrize("call", ["refine_batch", "soft_tau_for_budget"])
def test_one_camera_or_none_where_a_batch_is_expected(models, cameras, call):
    _, pm = models
    one, many = cameras
    with pytest.raises(ValueError, match=rf"^{call}: needs a camera batch .*got eye of shape \[3\]"):
        CALLS[call](pm, one, one)
    empty = pmjax.index_camera(many, slice(0, 0))
    with pytest.raises(ValueError, match=rf"^{call}: the camera batch is empty"):
        CALLS[call](pm, empty, empty)


@pytest.mark.parametrize("call", ["refine", "faces_for_budget", "refine_batch", "path_counts"])
def test_a_camera_that_is_not_a_camera(models, call):
    _, pm = models
    with pytest.raises(TypeError, match=rf"^{call}: cameras? must be a pmjax\.Camera.*got ndarray"):
        CALLS[call](pm, np.zeros(3), np.zeros((2, 3)))


@pytest.mark.parametrize("tau,error", [(None, TypeError), ([1, 2], TypeError), ("1", TypeError), (True, TypeError),
                                       (np.array([1.0, 2.0]), ValueError), (float("nan"), ValueError),
                                       (-1.0, ValueError)])
@pytest.mark.parametrize("call", ["refine", "soft_refine"])
def test_bad_tolerances_are_named(models, cameras, call, tau, error):
    _, pm = models
    one, _ = cameras
    f = pmjax.refine if call == "refine" else pmjax.soft_refine
    with pytest.raises(error, match=r"tau must be"):
        f(pm, one, tau)


def test_refine_batch_takes_one_tolerance(models, cameras):
    _, pm = models
    _, many = cameras
    with pytest.raises(TypeError, match=r"^refine_batch: tau \(one for all cameras\) must be a number, got list"):
        pmjax.refine_batch(pm, many, [1.0, 2.0])
    import jax.numpy as jnp

    with pytest.raises(ValueError, match=r"^refine_batch: tau \(one for all cameras\) must be one number, got"):
        pmjax.refine_batch(pm, many, jnp.ones(8))
    assert np.array_equal(pmjax.refine_batch(pm, many, jnp.float32(2.0))["faces"],
                          pmjax.refine_batch(pm, many, 2.0)["faces"])


def test_soft_refine_refuses_a_bad_temperature(models, cameras):
    _, pm = models
    one, _ = cameras
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match=r"^soft_refine: temperature must be > 0"):
            pmjax.soft_refine(pm, one, 1.0, temperature=bad)


# -- the soft calls' other arguments -------------------------------------------------

SOFT_BUDGET_BAD = [
    (dict(temperature=-1.0), ValueError, r"temperature must be > 0 and finite"),
    (dict(temperature=0.0), ValueError, r"temperature must be > 0 and finite"),
    (dict(temperature=float("nan")), ValueError, r"temperature must be > 0 and finite"),
    (dict(temperature=float("inf")), ValueError, r"temperature must be > 0 and finite"),
    (dict(temperature=[0.1, 0.2]), TypeError, r"temperature must be a number"),
    (dict(budget=float("nan")), ValueError, r"budget must be >= 0 faces and finite, got nan"),
    (dict(budget=[100, -1]), ValueError, r"budget must be >= 0 faces and finite, got -1 for camera 1"),
    (dict(budget=[100, 200, 300]), ValueError, r"budget must be one number or one per camera \(\[2\]\), got shape \[3\]"),
    (dict(budget=np.ones((2, 1))), ValueError, r"budget must be one number or one per camera"),
    (dict(budget="100"), TypeError, r"budget must be numbers of faces"),
    (dict(tau_range=(1e4, 1e-3)), ValueError, r"tau_range must be \(lowest, highest\) with 0 < lowest < highest"),
    (dict(tau_range=(0.0, 1e3)), ValueError, r"tau_range must be \(lowest, highest\) with 0 < lowest < highest"),
    (dict(tau_range=(1e-3, float("inf"))), ValueError, r"tau_range must be .* finite"),
    (dict(tau_range=(1e-3, 1.0, 1e3)), ValueError, r"tau_range must be \(lowest, highest\) pixels, got shape \[3\]"),
]


@pytest.mark.parametrize("bad,error,message", SOFT_BUDGET_BAD)
def test_soft_tau_for_budget_refuses_bad_arguments(models, cameras, bad, error, message):
    _, pm = models
    _, many = cameras
    args = dict(budget=1000, temperature=0.05, tau_range=(1e-3, 1e4)) | bad
    with pytest.raises(error, match=rf"^soft_tau_for_budget: {message}"):
        pmjax.soft_tau_for_budget(pm, many, **args)


def test_soft_tau_for_budget_refuses_bad_traced_arguments(models, cameras):
    _, pm = models
    _, many = cameras
    solve = jax.jit(lambda b, t, r: pmjax.soft_tau_for_budget(pm, many, b, t, tau_range=(r[0], r[1])).tau)
    good = (jnp.array([1000.0, 2000.0]), jnp.float32(0.05), jnp.array([1e-3, 1e4], jnp.float32))
    assert np.asarray(solve(*good)).shape == (2,)
    for i, bad, message in [(0, jnp.array([1000.0, jnp.nan]), "budget must be >= 0 faces and finite"),
                            (1, jnp.float32(-1.0), "temperature must be > 0 and finite"),
                            (2, jnp.array([1e4, 1e-3], jnp.float32), "tau_range must be"),]:
        args = list(good)
        args[i] = bad
        with pytest.raises(Exception, match=rf"soft_tau_for_budget: {message}"):
            jax.block_until_ready(solve(*args))
    with pytest.raises(ValueError, match=r"^soft_tau_for_budget: budget must be one number or one per camera"):
        solve(jnp.ones(3), *good[1:])


def test_soft_refine_checks_scale(models, cameras):
    _, pm = models
    one, _ = cameras
    P = pm.n_pcols
    with pytest.raises(ValueError, match=rf"^soft_refine: scale must be \[P\] = \[{P}\] .*got shape \[3\]"):
        pmjax.soft_refine(pm, one, 1.0, scale=jnp.ones(3))
    with pytest.raises(ValueError, match=rf"^soft_refine: scale must be finite, got nan at pcol 5 \(1 of {P}"):
        pmjax.soft_refine(pm, one, 1.0, scale=_with_nan(P, 5))
    with pytest.raises(TypeError, match=r"^soft_refine: scale must be numbers"):
        pmjax.soft_refine(pm, one, 1.0, scale=np.array(["1"] * P))
    soft = jax.jit(lambda s: pmjax.soft_refine(pm, one, 1.0, scale=s).faces)
    assert np.isfinite(float(soft(jnp.ones(P))))
    with pytest.raises(Exception, match=r"soft_refine: scale must be finite"):
        jax.block_until_ready(soft(jnp.asarray(_with_nan(P, 5))))
    with pytest.raises(ValueError, match=r"^soft_refine: scale must be \[P\]"):
        soft(jnp.ones(P + 1))


def _with_nan(n, i):
    out = np.ones(n, np.float32)
    out[i] = np.nan
    return out


def test_soft_refine_takes_one_tolerance_as_a_jax_array_too(models, cameras):
    _, pm = models
    one, _ = cameras
    with pytest.raises(ValueError, match=r"^soft_refine: tau must be one number, .*shape \[3\]"):
        pmjax.soft_refine(pm, one, jnp.ones(3))
    with pytest.raises(ValueError, match=r"^soft_refine: tau must be >= 0 pixels \(not NaN\), got nan"):
        pmjax.soft_refine(pm, one, jnp.float32(jnp.nan))
    with pytest.raises(ValueError, match=r"^soft_refine: tau must be one number, got an array of shape \[3\]"):
        jax.jit(lambda t: pmjax.soft_refine(pm, one, t).faces)(jnp.ones(3))
    with pytest.raises(ValueError, match=r"^soft_refine: temperature must be one number"):
        jax.jit(lambda t: pmjax.soft_refine(pm, one, 1.0, t).faces)(jnp.ones(3))
    # A concrete JAX tolerance is the same refinement as the number.
    assert float(pmjax.soft_refine(pm, one, jnp.float32(2.0)).faces) == float(pmjax.soft_refine(pm, one, 2.0).faces)


# -- the predicates -------------------------------------------------------------------

PREDICATES = {
    "collapse_mask": lambda A, camera, tau: pmjax.collapse_mask(A, camera, tau),
    "small_on_screen": lambda A, camera, tau: pmjax.small_on_screen(A, camera, tau),
    "critical_tau": lambda A, camera, tau: pmjax.critical_tau(A, camera),
    "outside_frustum": lambda A, camera, tau: pmjax.outside_frustum(A, camera),
    "oriented_away": lambda A, camera, tau: pmjax.oriented_away(A, camera),
}


@pytest.mark.parametrize("call", sorted(PREDICATES))
def test_predicates_take_one_camera(models, cameras, call):
    _, pm = models
    one, many = cameras
    assert PREDICATES[call](pm.attributes, one, 1.0).shape == (pm.n_pcols,)
    with pytest.raises(ValueError, match=rf"^{call}: takes one camera .*a batch of 2 cameras"):
        PREDICATES[call](pm.attributes, many, 1.0)
    with pytest.raises(TypeError, match=rf"^{call}: camera must be a pmjax\.Camera.*got ndarray"):
        PREDICATES[call](pm.attributes, np.zeros(3), 1.0)


@pytest.mark.parametrize("tau,error", [(float("nan"), ValueError), (-1.0, ValueError), (None, TypeError),
                                       (np.array([1.0, 2.0]), ValueError), (jnp.float32(-1.0), ValueError)])
@pytest.mark.parametrize("call", ["collapse_mask", "small_on_screen", "kappa"])
def test_predicates_refuse_a_bad_tolerance(models, cameras, call, tau, error):
    _, pm = models
    one, _ = cameras
    f = (lambda camera, t: pmjax.kappa(camera, t)) if call == "kappa" else \
        (lambda camera, t: PREDICATES[call](pm.attributes, camera, t))
    with pytest.raises(error, match=rf"^{call}: tau must be"):
        f(one, tau)
    # Traced, the same rule inside the compiled call.
    if isinstance(tau, float):
        with pytest.raises(Exception, match=rf"{call}: tau must be >= 0 \(and not NaN\)"):
            jax.block_until_ready(jax.jit(lambda t: f(one, t))(tau))


def test_predicates_take_every_tolerance_refine_takes(models, cameras):
    _, pm = models
    one, many = cameras
    # inf: every pcol the screen test can collapse; 0: none; kappa of a batch.
    assert bool(np.all(np.asarray(pmjax.collapse_mask(pm.attributes, one, float("inf")))))
    assert not np.any(np.asarray(pmjax.small_on_screen(pm.attributes, one, 0.0)))
    assert np.asarray(pmjax.kappa(many, 1.0)).shape == (2,)
    with pytest.raises(TypeError, match=r"^kappa: camera must be a pmjax\.Camera"):
        pmjax.kappa(np.zeros(3), 1.0)


def test_soft_tests_checks_its_camera_tau_and_temperature(models, cameras):
    _, pm = models
    one, many = cameras
    with pytest.raises(ValueError, match=r"^soft_tests: takes one camera"):
        pmjax.soft_tests(pm.attributes, many, 1.0, 0.1)
    with pytest.raises(ValueError, match=r"^soft_tests: tau must be >= 0"):
        pmjax.soft_tests(pm.attributes, one, -1.0, 0.1)
    with pytest.raises(ValueError, match=r"^soft_tests: temperature must be > 0"):
        pmjax.soft_tests(pm.attributes, one, 1.0, 0.0)
    collapse, visible, t = pmjax.soft_tests(pm.attributes, one, 1.0, 0.1)
    assert collapse.shape == visible.shape == t.shape == pm.attributes.radius.shape

