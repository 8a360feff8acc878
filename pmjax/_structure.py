"""Linear-time check of a hierarchy's structure, run on every load and save.

:func:`pmjax.validate_pm` checks dtypes, shapes and index ranges. This module
checks what the engine relies on beyond them, so that a forged or damaged file
that passes its checksums is still refused rather than drawn wrong:

- faces: no repeated corner, no two faces on the same three vertices;
- killers: each face's killer is the first pcol that merges two of its corners
  (``-1`` when none does), which fixes every face count and face mask;
- batch independence: at the start of a batch, no live face touches the
  endpoints of two different pcols of that batch;
- normals: unit length (an original vertex with no net face area may be zero);
- monotone attributes: each pcol's sphere holds its children's spheres, its
  cone holds theirs, its ``delta``, ``mu`` and ``alpha`` are at least theirs,
  within the float32 rounding of the stored values (:func:`sphere_slack`).

Everything is vectorized NumPy: one pass over the pcols per batch (``B``
slices whose sizes sum to ``P``) and a constant number of passes over the
faces. The killer and independence checks share one idea: a vertex's chain
is the list of pcols from it to its root, at most one per batch (a pcol only
consumes vertices made by earlier batches), recorded as a bitmask of batches.
Two corners of a face meet first at pcol ``k`` exactly when both lie in
``k``'s subtree (pre-order intervals) and their chains share no batch below
``k``'s; a batch shared by two chains at or before the face's killer is two
different pcols of one batch touching the face, unless it is the killer.
:func:`pmjax.check_invariants` recomputes the same facts by other means.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ._atomic import atomic_path
from ._pmdata import PMData, PMFormatError

# Bumped whenever check_structure checks more: older records of passed files
# then no longer count.
CHECK_VERSION = 1
EPS32 = float(np.finfo(np.float32).eps)
# Cone test slack (radians): arccos amplifies the float32 rounding of unit
# normals near a zero angle to about sqrt(eps32) = 3.5e-4.
CONE_SLACK = 1e-3
# Normal length tolerance: float32 unit vectors are within a few eps of 1.
NORMAL_SLACK = 1e-4


def sphere_slack(vertices: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Per-pcol slack (model units) of the sphere containment test.

    The builder computes radii in float64 and stores positions and radii in
    float32. Rounding moves each stored coordinate by at most ``eps32/2·|x|``,
    so a parent–child distance by at most ``eps32·√3·s`` (``s`` the largest
    coordinate magnitude), and each radius by ``eps32/2`` of itself. The slack
    is twice the sum.
    """
    scale = float(np.abs(vertices).max(initial=0.0))
    return 2.0 * EPS32 * (np.sqrt(3.0) * scale + radius.astype(np.float64))


def known_structures_dir() -> str | None:
    """Folder recording the content fingerprints of files that passed
    :func:`check_structure` (``$PMJAX_KNOWN_STRUCTURES``, by default
    ``~/.cache/pmjax/known-structures``; an empty value turns the record off)."""
    folder = os.environ.get("PMJAX_KNOWN_STRUCTURES")
    if folder is None:
        folder = os.path.join(os.path.expanduser("~"), ".cache", "pmjax", "known-structures")
    return folder or None


def structure_known(fingerprint: str) -> bool:
    """Whether content with this fingerprint (a SHA-256 over the arrays'
    verified checksums, from :func:`pmjax.read_arrays`) passed
    :func:`check_structure` on this machine. A forged file has other bytes,
    hence another fingerprint, so the record can only skip repeating a check
    on identical content."""
    folder = known_structures_dir()
    return folder is not None and os.path.exists(os.path.join(folder, f"{fingerprint}.v{CHECK_VERSION}"))


def remember_structure(fingerprint: str) -> None:
    """Record that content with this fingerprint passed :func:`check_structure`
    (an empty file; silently skipped where the folder cannot be written)."""
    folder = known_structures_dir()
    if folder is None:
        return
    try:
        os.makedirs(folder, exist_ok=True)
        open(os.path.join(folder, f"{fingerprint}.v{CHECK_VERSION}"), "a").close()
    except OSError:
        pass


def decoding_known(key: str) -> str | None:
    """The content fingerprint that a version 2 file with decoding key
    ``key`` (a SHA-256 over its verified bytes and the decoder, from
    :func:`pmjax.read_arrays`) decoded to on this machine, its arrays then
    matching their checksums and passing :func:`pmjax.validate_pm`; ``None``
    if no such decoding is recorded. Other bytes or another decoder give
    another key, so the record can only skip repeating those checks on the
    same decoding of the same bytes."""
    folder = known_structures_dir()
    if folder is None:
        return None
    try:
        with open(os.path.join(folder, f"{key}.decoded"), "rb") as fh:
            text = fh.read(65).decode("ascii")
    except (OSError, UnicodeDecodeError):
        return None
    # A record is the 64 hex digits of a fingerprint (written whole, by rename).
    return text if len(text) == 64 and all(c in "0123456789abcdef" for c in text) else None


def remember_decoding(key: str, fingerprint: str) -> None:
    """Record that the version 2 file with decoding key ``key`` decoded to
    arrays with content ``fingerprint`` that passed their checks (silently
    skipped where the folder cannot be written)."""
    folder = known_structures_dir()
    if folder is None:
        return
    # Written beside, then renamed (pmjax._atomic): a reader sees no record
    # or a whole one; a writer killed meanwhile leaves a temporary file that
    # the next write of the record removes.
    try:
        os.makedirs(folder, exist_ok=True)
        with atomic_path(os.path.join(folder, f"{key}.decoded")) as tmp:
            with open(tmp, "w", encoding="ascii") as fh:
                fh.write(fingerprint)
    except OSError:
        pass


def check_structure(pm: PMData, *, source: str = "<memory>", threads: int = 2, nesting: bool = True) -> None:
    """Refuse a hierarchy whose structure the engine cannot trust.

    Assumes :func:`pmjax.validate_pm` passed (ranges, consumption once, batch
    order). See the module docstring for what is checked.

    Args:
        pm: the hierarchy.
        source: the name errors give (usually the file path).
        threads: 2 runs the face checks beside the attribute checks (NumPy
            releases the GIL); 1 runs them in the calling thread.
        nesting: also check the normals and that each pcol's attributes
            hold its created children's. ``pmjax.load`` turns it off here: it
            checks the normals first and the nesting inside the subtree bounds
            it computes anyway (:class:`NestingCheck`), which gather the same
            parent-child pairs.

    Raises:
        PMFormatError: naming ``source`` and the first offending face or pcol.
    """
    # Gathers index with intp: NumPy converts int32 indices on every call.
    corners = np.ascontiguousarray(pm.faces.T, dtype=np.intp)  # [3, F]: one row per corner

    def attributes():
        if nesting:
            check_normals(pm, source)
        check = NestingCheck(pm, source)
        check.original_children()
        if nesting:
            check.created_children()

    if threads < 2:
        _check_faces_and_killers(pm, corners, source)
        attributes()
        return
    with ThreadPoolExecutor(max_workers=1) as pool:
        faces = pool.submit(_check_faces_and_killers, pm, corners, source)
        attributes()
        faces.result()


def _fail(mask: np.ndarray, source: str, what: str) -> None:
    if mask.any():
        raise PMFormatError(f"{source}: {what.format(int(np.flatnonzero(mask)[0]))}")


def _check_faces_and_killers(pm: PMData, corners: np.ndarray, source: str) -> None:
    f0, f1, f2 = corners
    # A repeated corner: the face has no area and its killer is undefined.
    _fail((f0 == f1) | (f1 == f2) | (f0 == f2), source, "face {} repeats a vertex")
    _check_duplicates(f0, f1, f2, pm.n_original_vertices, source)
    tin, size, chains = _forest(pm)
    _check_killers(pm, corners, tin, size, chains, source)


def _check_duplicates(f0, f1, f2, V0: int, source: str) -> None:
    """Refuse two faces on the same three vertices, in expected linear time.

    Each face's sorted corner triple is one 64-bit key. Rounds of a hash table
    (about 2 slots per face, last writer wins) pair every face with the
    face holding its slot: an equal key is a duplicate; faces that lost their
    slot to a different key try again next round with another hash, and they
    are a shrinking fraction.
    """
    u = np.uint64
    lo = np.minimum(np.minimum(f0, f1), f2)
    hi = np.maximum(np.maximum(f0, f1), f2)
    mid = f0 + f1 + f2 - lo - hi
    exact = V0 < 2 ** 21  # three 21-bit ids fit one key
    if exact:
        key = (lo.astype(u) * u(V0) + mid.astype(u)) * u(V0) + hi.astype(u)
    else:  # a 64-bit mix; equal keys are confirmed on the corners
        key = (lo.astype(u) * u(0x9E3779B97F4A7C15)) ^ (mid.astype(u) * u(0xC2B2AE3D27D4EB4F)) ^ hi.astype(u)
    todo = np.arange(len(key))
    mix = 0x9E3779B97F4A7C15
    while len(todo):
        bits = max(int(np.ceil(np.log2(2 * len(todo)))), 1)
        k = key[todo]
        slot = ((k * u(mix)) >> u(64 - bits)).astype(np.intp)
        table = np.empty(1 << bits, np.intp)  # every slot read below is written first
        table[slot] = todo
        owner = table[slot]
        lost = owner != todo
        same = np.flatnonzero(lost & (key[owner] == k))
        for i in same:
            a, b = int(todo[i]), int(owner[i])
            if exact or (lo[a] == lo[b] and mid[a] == mid[b] and hi[a] == hi[b]):
                raise PMFormatError(f"{source}: faces {min(a, b)} and {max(a, b)} have the same three vertices")
        # (Two different faces with one 64-bit mixed key, odds ~F²/2⁶⁴, leave here.)
        lost[same] = False
        todo = todo[lost]
        mix = (mix * 0xD1B54A32D192ED03 + 2) % 2 ** 64 | 1


def _forest(pm: PMData):
    """Pre-order intervals and batch chains of every vertex of the forest.

    Returns ``(tin, size, chains)``, int32 and uint64 arrays over the ``V0 + P``
    vertices: ``u`` lies in the subtree of ``w`` iff ``0 <= tin[u] - tin[w] <
    size[w]``; ``chains`` is a list of words, bit ``b`` of word ``b // 64`` set
    when the chain from the vertex to its root holds a pcol of batch ``b``.
    """
    V0, P = pm.n_original_vertices, pm.n_pcols
    off = pm.batch_offsets
    v1, v2 = pm.v1.astype(np.intp), pm.v2.astype(np.intp)
    # Subtree sizes bottom-up: a batch's children are final before it.
    size = np.ones(V0 + P, np.int32)
    for b in range(pm.n_batches):
        lo, hi = int(off[b]), int(off[b + 1])
        size[V0 + lo:V0 + hi] += size.take(v1[lo:hi]) + size.take(v2[lo:hi])
    # Roots get consecutive pre-order ranges; children inherit top-down.
    consumed = np.zeros(V0 + P, bool)
    consumed[v1] = True
    consumed[v2] = True
    roots = np.flatnonzero(~consumed)
    tin = np.zeros(V0 + P, np.int32)
    tin[roots] = np.cumsum(size[roots]) - size[roots]
    chains = [np.zeros(V0 + P, np.uint64) for _ in range((pm.n_batches + 63) // 64)]
    for b in range(pm.n_batches - 1, -1, -1):
        lo, hi = int(off[b]), int(off[b + 1])
        a, c = v1[lo:hi], v2[lo:hi]
        first = tin[V0 + lo:V0 + hi] + 1
        tin[a] = first
        tin[c] = first + size.take(a)
        for w, chain in enumerate(chains):
            bits = chain[V0 + lo:V0 + hi]
            if w == b // 64:
                bits = bits | np.uint64(1 << (b % 64))
            chain[a] = bits
            chain[c] = bits
    return tin, size, chains


def _check_killers(pm: PMData, corners, tin, size, chains, source: str) -> None:
    """Killers and batch independence, per face (see the module docstring).

    With ``K`` the face's killer and ``b`` its batch: exactly two corners lie
    in ``K``'s subtree; a corner's chain holds batch ``b`` iff it is one of
    those two; and the batches up to ``b`` that two chains share are ``{b}``
    (nothing for a face never killed).
    """
    V0, P = pm.n_original_vertices, pm.n_pcols
    killer = pm.killer.astype(np.intp)
    killed = killer >= 0
    # Per pcol, then per face through the killer (index P: never killed).
    batch = np.repeat(np.arange(pm.n_batches), np.diff(pm.batch_offsets))
    start = np.append(tin[V0:], 0).take(killer)
    extent = np.append(size[V0:], 0).take(killer)
    inside = [(tin.take(f) - start).astype(np.uint32) < extent.astype(np.uint32) for f in corners]
    _fail(killed & (inside[0].astype(np.int8) + inside[1] + inside[2] != 2), source,
          "face {}: its killer's subtree does not hold exactly two of its corners")
    bad = np.zeros(len(killer), bool)
    for w, chain in enumerate(chains):
        r = batch - 64 * w  # the killer's bit in this word, if 0 <= r < 64
        own = np.where((r >= 0) & (r < 64), np.uint64(1) << np.clip(r, 0, 63).astype(np.uint64), np.uint64(0))
        low = np.where(r >= 63, ~np.uint64(0), (np.uint64(2) << np.clip(r, 0, 62).astype(np.uint64)) - np.uint64(1))
        low = np.where(r < 0, np.uint64(0), low)
        own = np.append(own, np.uint64(0)).take(killer)
        low = np.append(low, ~np.uint64(0)).take(killer)
        m = [chain.take(f) for f in corners]
        here = own != 0  # faces whose killer's batch is in this word
        for i in range(3):
            bad |= here & (((m[i] & own) != 0) != inside[i])
        bad |= ((m[0] & m[1]) | (m[0] & m[2]) | (m[1] & m[2])) & low != own
    nonzero = np.flatnonzero(bad)
    if len(nonzero):
        f = int(nonzero[0])
        if killer[f] < 0:
            raise PMFormatError(f"{source}: face {f}: killer -1 but two of its corners merge")
        raise PMFormatError(
            f"{source}: face {f}: killer {int(killer[f])} is not the first pcol merging two of its "
            "corners, or two pcols of one batch touch the face (batches not independent)"
        )


def check_normals(pm: PMData, source: str) -> None:
    """Unit normals (an original vertex with no net face area may have zero)."""
    V0 = pm.n_original_vertices
    length = np.sqrt(np.einsum("ij,ij->i", pm.normals, pm.normals))
    off_unit = np.abs(length - 1.0) > NORMAL_SLACK
    off_unit[:V0] &= length[:V0] != 0.0
    _fail(off_unit, source, "vertex {}: normal is not of unit length")


class NestingCheck:
    """Each pcol's attributes hold its children's, within float32 rounding.

    Sphere: ``|x_p − x_c| + r_c <= r_p + slack`` (:func:`sphere_slack`); cone
    (created children): ``angle(n_p, n_c) + alpha_c <= alpha_p + CONE_SLACK``
    unless ``alpha_p`` is already π; ``delta``, ``mu``, ``alpha`` at least the
    child's. Made once per hierarchy (it first checks that normals are unit);
    :meth:`original_children` checks the pcols' original children and
    :meth:`created_children` the created ones, which ``pmjax.load`` does
    instead by passing the object to :func:`pmjax._subtree.subtree_bounds`.
    """

    def __init__(self, pm: PMData, source: str, exponent: int = 0):
        self.pm, self.source = pm, source
        # The bounds pass may run in model units (pmjax._units): its gaps are
        # brought back to world units, exactly (a power of two).
        self.unit = 2.0 ** exponent
        self.radius = pm.radius.astype(np.float64)
        self.limit = sphere_slack(pm.vertices, pm.radius) + self.radius
        alpha = pm.alpha.astype(np.float64)
        self.alpha = alpha
        self.cone_limit = np.where(alpha < np.pi - CONE_SLACK, alpha + CONE_SLACK, np.inf)
        self.deviations = (("delta", pm.delta), ("mu", pm.mu), ("alpha", pm.alpha))

    def _raise(self, bad, p, which, what):
        first = int(p[np.flatnonzero(bad)[0]])
        raise PMFormatError(f"{self.source}: pcol {first}: {what.format(child=f'its v{which} child')}")

    def __call__(self, p, q, gap, turn, which) -> None:
        """Check parents ``p`` against created children ``q`` (pcol ids)."""
        bad = gap * self.unit + self.radius[q] > self.limit[p]
        if bad.any():
            self._raise(bad, p, which, "sphere does not contain {child}'s sphere")
        bad = turn + self.alpha[q] > self.cone_limit[p]
        if bad.any():
            self._raise(bad, p, which, "normal cone does not contain {child}'s cone")
        for name, a in self.deviations:
            bad = a[q] > a[p]
            if bad.any():
                self._raise(bad, p, which, f"{name} smaller than {{child}}'s")

    def original_children(self) -> None:
        """Spheres around original children (they have no cone or deviation)."""
        pm, V0 = self.pm, self.pm.n_original_vertices
        x = np.ascontiguousarray(pm.vertices.T, dtype=np.float64)  # [3, V]
        for which, v in ((1, pm.v1), (2, pm.v2)):
            p = np.flatnonzero(v < V0)
            c = v[p].astype(np.intp)
            d = [x[k][V0 + p] - x[k][c] for k in range(3)]
            bad = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) > self.limit[p]
            if bad.any():
                self._raise(bad, p, which, "sphere does not contain {child}'s sphere")

    def created_children(self) -> None:
        """The created children, through the same pass as the subtree bounds."""
        from ._subtree import subtree_bounds

        pm, V0 = self.pm, self.pm.n_original_vertices
        child = [np.where(v >= V0, v - V0, -1) for v in (pm.v1, pm.v2)]
        subtree_bounds(pm.vertices[V0:], pm.normals[V0:], pm.radius, np.sin(self.alpha), np.cos(self.alpha),
                       pm.delta, pm.mu, *child, pm.batch_offsets, nesting=self)
