"""Wrong arguments to the public refinement calls: a TypeError or ValueError
that names the call and the argument, before any work."""

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
