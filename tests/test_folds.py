"""The hierarchy's folds (up and down the batches) against sequential loops,
their window plan, and the compile-once property: the traced program does
not grow with the number of batches."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmjax
from pmjax._replay import representatives as host_representatives
from pmjax._soft import geomorph_blend, soft_weights
from pmjax.engines import _dense


def _pm(built, name):
    data = built(name)
    return data, pmjax.ProgressiveMesh.from_data(data)


@pytest.mark.parametrize("seed", range(6))
def test_window_plan_gives_each_batch_one_wide_enough_window(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 80))
    sizes = rng.integers(0, 3000, n) * (rng.random(n) < 0.9)  # some empty batches
    if seed == 0:
        sizes = np.sort(sizes)[::-1]  # the usual shape: batches shrink
    runs = _dense.window_plan(tuple(int(s) for s in sizes))
    index = np.concatenate([i for _, i in runs]) if runs else np.zeros(0, int)
    assert np.array_equal(index, np.nonzero(sizes)[0])  # every non-empty batch once, in order
    widths = [w for w, _ in runs]
    assert len(set(widths)) == len(widths) <= _dense.MAX_WIDTHS
    assert widths == sorted(widths, reverse=True)  # never growing along the batches
    for w, i in runs:
        assert (w >= sizes[i]).all()
        # A window covers every batch from it to the end (widths never grow).
        assert all(w >= sizes[j:].max() for j in i)


@pytest.mark.slow
def test_folds_equal_sequential_loops(built):
    data, pm = _pm(built, "bunny.ply")
    V0, P = data.n_original_vertices, data.n_pcols
    rng = np.random.default_rng(3)
    own = rng.random(P).astype(np.float32)
    c1 = np.asarray(data.v1) - V0
    c2 = np.asarray(data.v2) - V0

    # Up: out[p] = own[p] * value(child1) * value(child2), pcol by pcol in order.
    want = own.copy()
    for p in range(P):
        a = want[c1[p]] if c1[p] >= 0 else np.float32(1.0)
        b = want[c2[p]] if c2[p] >= 0 else np.float32(1.0)
        want[p] = own[p] * a * b
    got = np.asarray(jax.jit(lambda x: soft_weights(pm, x))(own))
    # XLA flushes subnormal products to zero; numpy keeps them.
    np.testing.assert_allclose(got, want, rtol=2e-6, atol=1e-37)

    # Bitwise folds are exact: the executed sets of random decisions.
    collapse = rng.random(P) < 0.7
    executed = collapse.copy()
    for p in range(P):
        executed[p] &= (c1[p] < 0 or executed[c1[p]]) and (c2[p] < 0 or executed[c2[p]])
    assert np.array_equal(np.asarray(_dense.propagate(pm, jnp.asarray(collapse))), executed)
    words = rng.integers(0, 2**32, (P, 3), dtype=np.uint64).astype(np.uint32)
    got = np.asarray(_dense.propagate(pm, jnp.asarray(words)))
    for bit in (0, 17, 31):
        lane = ((words[:, 1] >> bit) & 1).astype(bool)
        ran = lane.copy()
        for p in range(P):
            ran[p] &= (c1[p] < 0 or ran[c1[p]]) and (c2[p] < 0 or ran[c2[p]])
        assert np.array_equal(((got[:, 1] >> bit) & 1).astype(bool), ran)

    # Down: representatives of the executed set against the host replay.
    rep = np.asarray(_dense.representatives(pm, jnp.asarray(executed)))
    assert np.array_equal(rep, host_representatives(data, executed))

    # Down, floats: the geomorph blend against a walk up each vertex's chain.
    weight = rng.random(P).astype(np.float32)
    values = np.asarray(data.vertices, np.float32)
    parent = np.full(V0 + P, -1)
    parent[data.v1], parent[data.v2] = V0 + np.arange(P), V0 + np.arange(P)
    want = values.astype(np.float64).copy()
    for v in range(V0 + P):
        u, p = v, parent[v]
        while p >= 0:
            want[v] += weight[p - V0] * (values[p].astype(np.float64) - values[u])
            u, p = p, parent[p]
    got = np.asarray(geomorph_blend(pm, jnp.asarray(weight), jnp.asarray(values)))
    scale = np.abs(values).max()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * scale)


def _size(jaxpr):
    """Equations in a jaxpr, nested ones included."""
    total = 0
    for eqn in jaxpr.eqns:
        total += 1
        for v in eqn.params.values():
            for sub in v if isinstance(v, (tuple, list)) else (v,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    total += _size(inner)
    return total


@pytest.mark.slow
def test_the_program_does_not_grow_with_the_batches(built):
    """Soft refinement and its gradient trace to programs of the same size on
    hierarchies of 41 and 57 batches: the folds are loops, not unrolled."""
    sizes = {}
    for name in ("cow.ply", "bunny.ply"):
        data, pm = _pm(built, name)
        v = data.vertices[: data.n_original_vertices]
        c = 0.5 * (v.min(0) + v.max(0))
        r = float(np.linalg.norm(v.max(0) - v.min(0)))
        cam = pmjax.look_at(eye=c + np.array([0.0, 0.2, 1.5]) * r, target=c)
        soft = lambda t: pmjax._soft.soft_refine_unchecked(pm, cam, t, 0.1)
        grad = jax.grad(lambda t: soft(t).faces + jnp.sum(soft(t).positions))
        sizes[name] = (len(pm.batch_offsets) - 1, _size(jax.make_jaxpr(soft)(1.0).jaxpr),
                       _size(jax.make_jaxpr(grad)(1.0).jaxpr))
    (b_cow, fwd_cow, grad_cow), (b_bunny, fwd_bunny, grad_bunny) = sizes["cow.ply"], sizes["bunny.ply"]
    assert b_bunny > b_cow + 10
    assert fwd_bunny <= fwd_cow + 10 and grad_bunny <= grad_cow + 20, sizes
