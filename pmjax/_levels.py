"""Dependency levels: the fewest sequential steps any refinement schedule needs.

The engine resolves the executed set and ``vref`` one batch at a time, because
a pcol's vertices come from earlier batches. The builder's batches are finer
than that dependency needs (GeMS batches also keep collapse domains apart): a
pcol's level, one more than its children's, is what truly orders it, and the
hierarchy's height is the length of the longest chain, shorter than the list
of batches (`pmjax info` reports both).
"""

from __future__ import annotations

import numpy as np

from ._pmfile import PMData


def dependency_levels(pm: PMData) -> np.ndarray:
    """Per pcol, its level in the dependency forest: 1 when both vertices are
    original, else one more than the higher level of the pcols making them.

    Pcols of one level depend on lower levels only, so ``max(levels)`` (the
    height) sequential steps suffice for the executed set and ``vref``, and no
    fewer do.

    Args:
        pm: host progressive mesh (:func:`pmjax.read_pm`).

    Returns:
        ``int32[P]``; the height is ``levels.max(initial=0)``, at most the
        number of batches.
    """
    V0 = pm.n_original_vertices
    level = np.zeros(V0 + pm.n_pcols, np.int32)
    # Batch by batch: children come from earlier batches, so they are final.
    off = pm.batch_offsets
    for lo, hi in zip(off[:-1], off[1:]):
        level[V0 + lo:V0 + hi] = 1 + np.maximum(level[pm.v1[lo:hi]], level[pm.v2[lo:hi]])
    return level[V0:]
