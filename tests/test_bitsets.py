"""Camera bitsets: packing and per-camera popcounts."""

import jax.numpy as jnp
import numpy as np
import pytest

from pmjax._bitsets import column_popcounts, pack_cameras, unpack_cameras, weight_bits_for


@pytest.mark.parametrize("K,P", [(32, 1), (32, 45), (64, 1000), (96, 33)])
def test_pack_roundtrip(K, P):
    rng = np.random.default_rng(K * P)
    mask = rng.random((K, P)) < 0.6
    words = pack_cameras(jnp.asarray(mask))
    assert words.shape == (P, K // 32) and words.dtype == jnp.uint32
    np.testing.assert_array_equal(np.asarray(unpack_cameras(words)), mask)
    np.testing.assert_array_equal(np.asarray(column_popcounts(words)), mask.sum(1))


# Row counts around each widening step's group (15, 15·17 = 255, 255·257 =
# 65,535), with random words and with all bits set (the largest counts: no
# lane may overflow).
@pytest.mark.parametrize("P", [0, 1, 14, 15, 16, 254, 255, 256, 4001, 65535, 65536, 70001])
@pytest.mark.parametrize("fill", ["random", "ones"])
def test_column_popcounts(P, fill):
    rng = np.random.default_rng(P)
    W = 3
    if fill == "ones":
        words = np.full((P, W), 0xFFFFFFFF, np.uint32)
    else:
        words = rng.integers(0, 2**32, (P, W), dtype=np.uint32)
    bits = (words[:, :, None] >> np.arange(32, dtype=np.uint32)) & 1
    got = np.asarray(column_popcounts(jnp.asarray(words)))
    np.testing.assert_array_equal(got, bits.sum(0).reshape(-1))


def test_weight_bits():
    assert [weight_bits_for(w) for w in (0, 1, 2, 3, 4, 255, 256)] == [1, 1, 2, 2, 3, 8, 9]
