"""Per-pcol camera bitsets: 32 cameras per ``uint32`` word.

Many cameras share the hierarchy, so their executed sets are propagated
together: one word carries 32 cameras and the AND of the propagation is one
bitwise AND, i.e. a 32-way SIMD over cameras with 1/8 of the memory traffic of
bools. Counting needs, per camera, a weighted sum over pcols; a 32×32 bit
transpose turns the pcol-major words into camera-major words so that sum is a
population count.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Int, UInt32

WORD = 32


def pack_cameras(mask: Bool[Array, "K P"]) -> UInt32[Array, "P W"]:
    """Pack ``mask[k, p]`` into ``words[p, k // 32]`` bit ``k % 32``; ``K`` a multiple of 32."""
    K, P = mask.shape
    shifted = mask.reshape(K // WORD, WORD, P).astype(jnp.uint32) << _bit_ids()[None, :, None]
    return jnp.sum(shifted, axis=1, dtype=jnp.uint32).T


def unpack_cameras(words: UInt32[Array, "P W"]) -> Bool[Array, "K P"]:
    """Inverse of :func:`pack_cameras`."""
    P, W = words.shape
    bits = (words.T[:, None, :] >> _bit_ids()[None, :, None]) & 1
    return bits.reshape(W * WORD, P).astype(bool)


def _bit_ids():
    return jnp.arange(WORD, dtype=jnp.uint32)


def _transpose32(a: UInt32[Array, "... 32"]) -> UInt32[Array, "... 32"]:
    """Transpose 32×32 bit matrices (rows = words): out row ``31 − j`` bit
    ``31 − i`` = in row ``i`` bit ``j`` (Hacker's Delight, 5 swap rounds)."""
    lead = a.shape[:-1]
    half, mask = 16, jnp.uint32(0x0000FFFF)
    while half:
        pairs = a.reshape(lead + (WORD // (2 * half), 2, half))
        lo, hi = pairs[..., 0, :], pairs[..., 1, :]
        swap = (lo ^ (hi >> half)) & mask
        a = jnp.stack([lo ^ swap, hi ^ (swap << half)], axis=-2).reshape(lead + (WORD,))
        half //= 2
        mask = mask ^ (mask << half)
    return a


def camera_major(words: UInt32[Array, "P W"]) -> UInt32[Array, "N W 32"]:
    """Bit-transpose pcol-major words so each camera's bits run over 32 pcols.

    ``out[n, w, 31 - c]`` bit ``31 - i`` is camera ``32w + c`` at pcol ``32n + i``
    (``P`` padded with zero bits to a multiple of 32).
    """
    P, W = words.shape
    padded = -(-P // WORD) * WORD
    words = jnp.pad(words, ((0, padded - P), (0, 0)))
    return _transpose32(words.reshape(padded // WORD, WORD, W).transpose(0, 2, 1))


def weighted_counts(by_camera: UInt32[Array, "N W 32"], weights: Int[Array, " P"], weight_bits: int) -> Int[Array, " K"]:
    """``out[k] = sum_p weights[p] * bit(words[p], k)`` for ``0 <= weights < 2**weight_bits``,
    from ``by_camera = camera_major(words)``:
    ``sum_b 2**b * popcount(camera word & weight bit-plane b)``.
    """
    padded = by_camera.shape[0] * WORD
    weights = jnp.pad(weights, (0, padded - weights.shape[0]))
    pcol_bit = (WORD - 1) - _bit_ids()  # pcol i sits at bit 31 - i
    total = jnp.zeros(by_camera.shape[1:], jnp.int32)
    for b in range(weight_bits):
        plane_bits = ((weights.reshape(-1, WORD) >> b) & 1).astype(jnp.uint32) << pcol_bit
        plane = jnp.sum(plane_bits, axis=1, dtype=jnp.uint32)
        hits = jax.lax.population_count(by_camera & plane[:, None, None]).astype(jnp.int32)
        total = total + (jnp.sum(hits, axis=0) << b)
    # Row r of each transposed block is camera 31 - r.
    return total[:, ::-1].reshape(-1)


def weight_bits_for(max_weight: int) -> int:
    """Bit planes needed for non-negative weights up to ``max_weight``."""
    return max(1, int(np.int64(max_weight)).bit_length())
