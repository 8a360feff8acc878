"""Camera bitsets: packing, the 32×32 bit transpose and weighted popcounts."""

import jax.numpy as jnp
import numpy as np
import pytest

from pmjax._bitsets import camera_major, pack_cameras, unpack_cameras, weight_bits_for, weighted_counts


@pytest.mark.parametrize("K,P", [(32, 1), (32, 45), (64, 1000), (96, 33)])
def test_pack_roundtrip_and_weighted_counts(K, P):
    rng = np.random.default_rng(K * P)
    mask = rng.random((K, P)) < 0.6
    weights = rng.integers(0, 7, P).astype(np.int32)
    words = pack_cameras(jnp.asarray(mask))
    assert words.shape == (P, K // 32) and words.dtype == jnp.uint32
    np.testing.assert_array_equal(np.asarray(unpack_cameras(words)), mask)
    got = weighted_counts(camera_major(words), jnp.asarray(weights), weight_bits_for(int(weights.max())))
    np.testing.assert_array_equal(np.asarray(got), mask.astype(np.int64) @ weights)


def test_weight_bits():
    assert [weight_bits_for(w) for w in (0, 1, 2, 3, 4, 255, 256)] == [1, 1, 2, 2, 3, 8, 9]
