"""Per-pcol camera bitsets: 32 cameras per ``uint32`` word.

Many cameras share the hierarchy, so their executed sets are propagated
together: one word carries 32 cameras and the AND of the propagation is one
bitwise AND, i.e. a 32-way SIMD over cameras with 1/8 of the memory traffic of
bools. Counting needs, per camera, a sum over pcols of one bit of each word:
:func:`column_popcounts`.
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


def _group_sum(x: UInt32[Array, "N W"], group: int) -> UInt32[Array, "M W"]:
    """Sums of consecutive groups of ``group`` rows (the last group zero-padded)."""
    x = jnp.pad(x, ((0, -x.shape[0] % group), (0, 0)))
    return jnp.sum(x.reshape(-1, group, x.shape[1]), axis=1, dtype=jnp.uint32)


def column_popcounts(words: UInt32[Array, "P W"]) -> Int[Array, " K"]:
    """``out[32w + c]`` = how many rows have bit ``c`` of word ``w`` set: per
    camera, the pcols whose bit is set (``K = 32 W``).

    SIMD within a register, widening the counters step by step: ``(x >> j) &
    0x11111111`` leaves bits ``c ≡ j (mod 4)`` one per 4-bit lane, and 15
    such words add up without a lane overflowing; then lanes are split and
    widened to 8 bits (groups of 17 sums ≤ 255), 16 bits (groups of 257) and
    32 bits. About a dozen word operations per input word and one pass over
    it, where a 32×32 bit transpose and a popcount take several.
    """
    W = words.shape[1]
    lanes = []  # (camera bit c, [W] counts)
    for j in range(4):
        by4 = _group_sum((words >> j) & jnp.uint32(0x11111111), 15)
        for odd4 in range(2):
            by8 = _group_sum((by4 >> (4 * odd4)) & jnp.uint32(0x0F0F0F0F), 17)
            for odd8 in range(2):
                by16 = _group_sum((by8 >> (8 * odd8)) & jnp.uint32(0x00FF00FF), 257)
                for odd16 in range(2):
                    count = jnp.sum((by16 >> (16 * odd16)) & jnp.uint32(0xFFFF), axis=0, dtype=jnp.uint32)
                    lanes.append((16 * odd16 + 8 * odd8 + 4 * odd4 + j, count))
    by_bit = jnp.stack([count for _, count in sorted(lanes, key=lambda lane: lane[0])], axis=1)
    return by_bit.reshape(W * WORD).astype(jnp.int32)


def weight_bits_for(max_weight: int) -> int:
    """Bit planes needed for non-negative weights up to ``max_weight``."""
    return max(1, int(np.int64(max_weight)).bit_length())
