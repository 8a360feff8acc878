"""Batched pair-contraction builder: a whole batch of independent collapses per
vectorized step (docs/design.md). The output is a :class:`pmjax.PMData`."""

from __future__ import annotations

import dataclasses
import math
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.spatial import cKDTree

from pmjax._pmfile import METRICS, PMData, file_sha256  # noqa: F401 (re-exported)
from pmjax._meshio import FLOAT32_MAX, check_float32_precision, rows_outside_float32
from pmjax._normals import fitted_normals

from . import _native as native
from . import _quadrics as qd
from ._attributes import HierarchyAttributes
from ._independent import domain_of_independent, select_independent
from ._metrics import CACHEABLE, METRIC_NAMES, evaluate_metric
from ._rows import any3, unit
from ._threads import split_pairs
from ._topology import VertexFaces, border_vertices, contains_edge, edge_keys, unique_edges
from ._validity import KnownInvalid, collapse_is_valid


# Validity is checked up front for all of a batch's candidates, rather than
# lazily for the greedy winners, when there are at most this many of them and
# at least this share of the last batch's checks failed. Late batches full of
# permanently invalid candidates (closed fragments, pinches) then cost no
# greedy rounds, while the mostly valid sets of early batches are not checked
# twice over (the greedy checks its winners anyway).
EAGER_VALIDITY = 20_000
EAGER_INVALID_SHARE = 0.1

# Batches the attribute thread may trail the batch choice by.
LAG_BATCHES = 1


@dataclasses.dataclass(frozen=True)
class BuildOptions:
    """Parameters of :func:`build_pm`.

    Attributes:
        metric: a metric name, or a schedule ``"edge:2,quadric"`` (metric
            ``edge`` for the first 2 batches, then ``quadric``). Names:
            quadric, quadric-memoryless, edge, pm, hybrid.
        pair_distance: vertex pairs closer than this fraction of the
            bounding-box diagonal that share no edge are candidates too
            (Visualizer's virtual pairs; topology may change). 0: edges only.
        target_faces: stop once at most this many faces are left (0: no target).
        target_vertices: stop once at most this many vertices are left.
        max_error: collapses costing more than this are never taken.
        batch_share: share of the cheapest candidates a batch may take from
            (quality knob, ``0 < s <= 1``).
        linear: one collapse per batch in strict cost order (slow reference).
        allow_topology_change: skip the link test for edges too.
        boundary_weight: weight of the border-preserving quadric planes.
        max_batches: safety cap on the number of batches.
    """

    metric: str = "quadric"
    pair_distance: float = 0.0
    target_faces: int = 0
    target_vertices: int = 0
    max_error: float = math.inf
    batch_share: float = 0.5
    linear: bool = False
    allow_topology_change: bool = False
    boundary_weight: float = 1.0
    max_batches: int = 100_000

    def __post_init__(self):
        # NumPy scalars become Python numbers: the header that stores the
        # options is JSON, and the build's arithmetic then does not depend on
        # a NumPy type's precision (a float32 distance, say).
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, np.generic):
                object.__setattr__(self, field.name, value.item())

    def schedule(self) -> list[tuple[str, int | None]]:
        """Parsed metric schedule: ``[(name, batches or None for the rest)]``."""
        out = []
        parts = [p.strip() for p in self.metric.split(",") if p.strip()]
        for i, part in enumerate(parts):
            name, _, count = part.partition(":")
            if name not in METRIC_NAMES:
                raise ValueError(f"unknown metric {name!r}; choose from {', '.join(METRIC_NAMES)}")
            if count:
                # isdecimal, not isdigit: int() refuses superscripts such as "²".
                if not count.isdecimal() or int(count) < 1:
                    raise ValueError(f"metric schedule {self.metric!r}: batch count {count!r} of {name!r} must be a "
                                     "positive integer")
                out.append((name, int(count)))
            elif i != len(parts) - 1:
                raise ValueError(f"metric schedule {self.metric!r}: only the last entry may omit ':N'")
            else:
                out.append((name, None))
        if not out:
            raise ValueError("empty metric schedule")
        return out

    def metric_for_batch(self, batch: int) -> str:
        start = 0
        for name, count in self.schedule():
            if count is None or batch < start + count:
                return name
            start += count
        return self.schedule()[-1][0]

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first option out of its range
        (NaN is out of every range)."""
        self.schedule()
        if not 0 < self.batch_share <= 1:
            raise ValueError(f"batch_share must be in (0, 1], got {self.batch_share}")
        # Beyond 1 diagonal every pair is a candidate already; the candidate
        # count, and the build time, grow with the square of this distance.
        if not 0 <= self.pair_distance <= 1:
            raise ValueError(f"pair_distance must be in [0, 1] (a fraction of the diagonal), got {self.pair_distance}")
        if not self.max_error >= 0:
            raise ValueError(f"max_error must be >= 0 (inf: no limit), got {self.max_error}")
        if not (math.isfinite(self.boundary_weight) and self.boundary_weight >= 0):
            raise ValueError(f"boundary_weight must be finite and >= 0, got {self.boundary_weight}")
        for name in ("target_faces", "target_vertices", "max_batches"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"{name} must be a whole number >= 0, got {value!r}")


def vertex_normals(pos: np.ndarray, faces: np.ndarray, n: int, chunk: int | None = None) -> np.ndarray:
    """Area-weighted unit vertex normals (zero where a vertex has no face).

    Args:
        pos: ``(V, 3)`` positions; faces: ``(F, 3)`` ids below ``n``.
        chunk: faces summed per step where the C loops are built (``None``:
            ``builders._quadrics.CHUNK_FACES``); the same sums in the same
            order as one step.

    Returns:
        ``float64[n, 3]``.
    """
    total = np.zeros((n, 3))
    for part in qd.face_parts(faces, chunk, sums=True):
        qd.scatter_add(qd.face_cross(pos, part), part.ravel(), n, repeat=3, out=total)
    return unit(total)


def build_pm(
    vertices: np.ndarray,
    faces: np.ndarray,
    options: BuildOptions = BuildOptions(),
    *,
    progress: bool = False,
    source_sha256: str | None = None,
) -> PMData:
    """Build a progressive mesh by batched pair contraction.

    Args:
        vertices: ``(V0, 3)`` positions of a cleaned mesh (see
            :func:`pmjax.clean_mesh`), model units.
        faces: ``(F, 3)`` int vertex ids, no degenerate or duplicate faces.
        options: see :class:`BuildOptions`.
        progress: show a tqdm bar (batch, faces, elapsed).
        source_sha256: checksum of the source file, stored in the header.

    Returns:
        :class:`pmjax.PMData` with monotone attributes and per-face killers.
    """
    options.validate()
    t0 = time.perf_counter()
    v0 = np.asarray(vertices, np.float64)
    f0 = _checked_input(v0, np.asarray(faces))
    check_float32_precision(v0)
    V0, F = len(v0), len(f0)
    cap = 2 * V0  # every pcol consumes two vertices and makes one: P < V0
    pos = np.zeros((cap, 3))
    pos[:V0] = v0
    normals = np.zeros((cap, 3))
    diag = float(np.linalg.norm(np.ptp(v0, axis=0)))
    # Current faces in current vertex ids. Ids stay below 2 V0, so int32:
    # half the memory traffic of int64 in every face gather. A batch makes
    # new face arrays and never writes into the old ones, so the build
    # starts from the input's own array.
    cur = f0
    # The first batch's edges give the quadrics and the attributes their
    # border edges too.
    first_edges = unique_edges(cur)
    quadric = np.zeros((cap, 10))
    # Whether every batch takes from all candidates (no cost limit): then
    # the candidates within the limit need no index array.
    no_limit = math.isinf(options.max_error) and options.max_error > 0
    # Doubled-area² under which a face counts as degenerate.
    min_area2 = (1e-12 * diag * diag) ** 2

    fid = np.arange(F)  # their original face ids
    killer = np.full(F, -1, np.int32)
    v1s, v2s, costs, metric_ids, offsets = [], [], [], [], [0]
    next_id = V0
    cache = None
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=F, unit="face", desc="build", dynamic_ncols=True)

    # Normals and refinement attributes play no part in choosing collapses,
    # so a second thread computes them batch by batch while the next batch is
    # chosen. They start while the quadrics are summed: on small meshes the
    # thread otherwise trails the last batch.
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="pmjax-attributes") as beside:
        jobs = [beside.submit(_start_attributes, pos, normals, f0, V0, first_edges)]
        qd.vertex_quadrics(v0, f0, V0, options.boundary_weight, first_edges, out=quadric[:V0])
        invalid_share = 0.0  # of the last validity checks
        known_invalid = KnownInvalid()
        last_metric = None
        # Buffers of the C loops, once for the whole build.
        scratch = native.Scratch(cap, F) if native.available() else None
        for batch in range(options.max_batches):
            n_faces = len(cur)
            # Live vertices (those with a face) matter only for a vertex target.
            n_verts = 0
            if options.target_vertices and n_faces:
                n_verts = int(np.count_nonzero(np.bincount(cur.ravel(), minlength=next_id)))
            enough_vertices = options.target_vertices and n_verts <= options.target_vertices
            if n_faces == 0 or n_faces <= options.target_faces or enough_vertices:
                break
            metric = options.metric_for_batch(batch)
            # A verdict holds for one metric's placements only: where the
            # schedule moves on, every pair is placed anew.
            if metric != last_metric:
                known_invalid = KnownInvalid()
                last_metric = metric

            # Candidates: every edge, plus close vertex pairs that share no edge.
            # Last batch's candidates go before the edges are recounted (the
            # cost cache keeps what it needs).
            a = b = ea = eb = ecount = is_edge = link_test = x = cost = None
            ea, eb, ecount, keys = first_edges or unique_edges(cur)
            first_edges = None
            a, b = ea, eb
            if options.pair_distance > 0:
                live = np.unique(cur)
                near = cKDTree(pos[live]).query_pairs(options.pair_distance * diag, output_type="ndarray")
                if len(near):
                    pa, pb = live[near[:, 0]], live[near[:, 1]]
                    pkeys = edge_keys(pa, pb)
                    new = ~contains_edge(keys, pkeys)
                    a = np.concatenate([ea, np.minimum(pa, pb)[new]])
                    b = np.concatenate([eb, np.maximum(pa, pb)[new]])
                    keys = np.concatenate([keys, pkeys[new]])
            is_edge = np.zeros(len(a), bool)
            is_edge[:len(ea)] = True

            # Cost and placement under this batch's metric. Memory-resident costs
            # depend only on the two endpoints, so pairs seen last batch (same ids,
            # hence same quadrics) keep theirs.
            if metric in CACHEABLE and cache is not None and cache[0] == metric:
                # The cache list is emptied once its rows are carried.
                x, cost = _cached_costs(cache, keys, metric, pos, cur, quadric, a, b, options.boundary_weight)
            else:
                x, cost = evaluate_metric(metric, pos, cur, quadric, a, b, options.boundary_weight)
            cache = None  # last batch's rows go before this batch's are sorted
            cache = [metric, *_sorted_by_key(keys, x, cost)] if metric in CACHEABLE else None

            boundary_vertex = border_vertices(ea, eb, ecount, next_id)
            link_test = is_edge & (not options.allow_topology_change)
            within = None  # all of them
            if not (no_limit and not np.isnan(cost).any()):
                within = np.flatnonzero(cost <= options.max_error)
                if len(within) == 0:
                    break
            n_within = len(cost) if within is None else len(within)
            # A batch takes from the cheapest share. When none of those is valid,
            # the dearer rest may still hold valid collapses: try all of them
            # before giving up, so that the share limits a batch's size and
            # never where the build stops.
            shares = [1.0] if options.linear else sorted({options.batch_share, 1.0})
            # The C loops read the faces around each vertex, built once a batch.
            mesh = native.Mesh(cur, next_id, pos, scratch) if scratch is not None and not options.linear else None
            for share in shares:
                n_take = max(1, int(math.ceil(share * n_within)))
                elig = _cheapest(cost, n_take) if within is None else within[_cheapest(cost[within], n_take)]
                eager = not options.linear and len(elig) <= EAGER_VALIDITY and invalid_share >= EAGER_INVALID_SHARE
                skip = known_invalid.of(keys[elig]) if eager else None
                chosen, invalid, invalid_share = _select_batch(
                    a, b, x, link_test, elig, cur, next_id, pos, min_area2, boundary_vertex, options.linear, skip, mesh
                )
                if eager:
                    known_invalid.add(keys[invalid])
                if len(chosen):
                    break
            mesh = None  # holds the faces before the batch
            if len(chosen) == 0:
                break

            # Stop exactly at a face or vertex target: keep the cheapest prefix.
            ca, cb = a[chosen], b[chosen]
            keep = len(chosen)
            if options.target_faces:
                pair, face = domain_of_independent(ca, cb, cur, np.arange(n_faces), np.full(next_id, -1, np.int32))
                tri = cur[face]
                both = np.any(tri == ca[pair, None], 1) & np.any(tri == cb[pair, None], 1)
                left = n_faces - np.cumsum(np.bincount(pair, both, minlength=keep))
                keep = min(keep, int(np.searchsorted(-left, -options.target_faces)) + 1)
            if options.target_vertices:
                keep = min(keep, max(1, n_verts - options.target_vertices))
            chosen, ca, cb = chosen[:keep], ca[:keep], cb[:keep]

            # Apply the batch: new vertices, remapped faces, killers.
            k = len(chosen)
            new = next_id + np.arange(k)
            pos[new] = x[chosen]
            known_invalid.forget_around(cur, np.concatenate([ca, cb]), next_id)
            if scratch is not None:
                cur, fid = native.apply_batch(scratch, cur, fid, ca, cb, next_id, V0, killer, quadric)
            else:
                quadric[new] = quadric[ca] + quadric[cb]
                remap = np.arange(next_id + k, dtype=np.int32)
                remap[ca] = new
                remap[cb] = new
                cur = remap[cur]
                c0, c1, c2 = cur[:, 0], cur[:, 1], cur[:, 2]
                dead = (c0 == c1) | (c1 == c2) | (c0 == c2)
                merged = np.where((c0 == c1) | (c0 == c2), c0, c1)
                killer[fid[dead]] = (merged[dead] - V0).astype(np.int32)
                cur, fid = cur[~dead], fid[~dead]
            # Normals and attributes of the new vertices, beside the next batch.
            # Each waiting job holds its batch's faces, so the second thread
            # may trail by at most LAG_BATCHES batches: the faces held stay
            # a few copies at any pace of the two threads.
            if len(jobs) > LAG_BATCHES:
                jobs[-LAG_BATCHES].result()
            maybe_border = boundary_vertex[ca] | boundary_vertex[cb]
            jobs.append(beside.submit(_attribute_batch, jobs[0], pos, normals, cur, next_id, ca, cb, maybe_border))
            v1s.append(ca)
            v2s.append(cb)
            costs.append(cost[chosen])
            metric_ids.append(np.full(k, METRICS.index(metric), np.uint8))
            next_id += k
            offsets.append(next_id - V0)
            if bar is not None:
                bar.update(n_faces - len(cur))
                bar.set_postfix(batch=batch, faces=len(cur), metric=metric)
        for job in jobs:
            job.result()  # re-raises what failed on the second thread
    if bar is not None:
        # The base mesh keeps some faces: end the bar at what was removed.
        bar.total = bar.n
        bar.refresh()
        bar.close()

    base_faces = int(len(cur))
    P = next_id - V0
    # The batch state goes before the hierarchy is put together: the
    # quadrics alone are 80 bytes per vertex id, and the shading normals'
    # fit below needs room of its own.
    quadric = scratch = mesh = cache = known_invalid = cur = fid = None
    a = b = ea = eb = ecount = keys = is_edge = link_test = x = cost = None
    boundary_vertex = within = elig = chosen = invalid = ca = cb = None
    v1 = np.concatenate(v1s).astype(np.int32) if v1s else np.zeros(0, np.int32)
    v2 = np.concatenate(v2s).astype(np.int32) if v2s else np.zeros(0, np.int32)
    v1s = v2s = None
    batch_offsets = np.asarray(offsets, np.int64)
    attrs = {k: v.astype(np.float32) for k, v in jobs[0].result().result(P).items()}
    jobs = None
    header = dict(
        build=dict(
            dataclasses.asdict(options),
            seconds=None,  # set below, once the shading normals are fitted
            base_faces=base_faces,
        ),
        source_sha256=source_sha256,
        bbox_diagonal=diag,
    )
    header["build"]["max_error"] = None if math.isinf(options.max_error) else options.max_error
    vertices_out = pos[:next_id].astype(np.float32)
    pos = None
    normals_out = normals[:next_id].astype(np.float32)
    normals = None
    data = PMData(
        vertices=vertices_out,
        normals=normals_out,
        faces=f0.astype(np.int32),
        v1=v1,
        v2=v2,
        radius=attrs["radius"],
        alpha=attrs["alpha"],
        delta=attrs["delta"],
        mu=attrs["mu"],
        cost=np.concatenate(costs).astype(np.float64) if costs else np.zeros(0),
        metric=np.concatenate(metric_ids) if metric_ids else np.zeros(0, np.uint8),
        batch_offsets=batch_offsets,
        killer=killer,
        header=header,
    )
    # Shading normals fitted to the original surface, for drawing
    # refinements: a least-squares fit over the finished hierarchy, after the
    # build's own arrays are gone.
    shading_normals = fitted_normals(data)
    # The build's time, as the header reports it, includes that fit.
    header["build"]["seconds"] = round(time.perf_counter() - t0, 3)
    return dataclasses.replace(data, shading_normals=shading_normals)


def _checked_input(v0: np.ndarray, f0: np.ndarray) -> np.ndarray:
    """The input checks of :func:`build_pm`, before any work: shapes, sizes the
    int32 steps can address, finite float32 positions and face ids in range.

    Args:
        v0: ``float64[V0, 3]`` vertices; f0: ``(F, 3)`` faces, any integer type.

    Returns:
        ``int32[F, 3]`` faces (``f0`` itself if it is int32 already).

    Raises:
        ValueError: naming the first bad vertex or face and its value.
    """
    # The arrays should come from clean_mesh; say so rather than fail deep inside.
    if v0.ndim != 2 or v0.shape[1] != 3 or f0.ndim != 2 or f0.shape[1] != 3 or len(f0) == 0:
        raise ValueError(f"build_pm needs vertices (V, 3) and at least one face (F, 3), got {v0.shape} and "
                         f"{f0.shape}; clean the mesh with pmjax.clean_mesh first")
    V0, F = len(v0), len(f0)
    if not np.issubdtype(f0.dtype, np.integer):
        raise ValueError(f"build_pm needs integer faces, got {f0.dtype} faces")
    # Vertex ids up to 2 V0 and face slots up to 3 F must fit int32: every
    # step reads int32 faces, and the C loops index their slots in int32.
    if 2 * V0 >= 2**31:
        raise ValueError(f"build_pm takes fewer than 2**30 vertices (new vertex ids reach twice their count and "
                         f"must fit int32), got {V0} vertices")
    if 3 * F >= 2**31:
        raise ValueError(f"build_pm takes fewer than 2**31 / 3 faces (their corner slots must fit int32), got {F} "
                         "faces")
    # Positions are stored as float32: beyond its largest value (or NaN) a
    # position is lost, and the build would only fail late, or not at all.
    # Min and max first: NaN carries through both, and no temporary is made.
    if len(v0) and not (-FLOAT32_MAX <= v0.min() and v0.max() <= FLOAT32_MAX):
        bad = int(np.flatnonzero(rows_outside_float32(v0))[0])
        raise ValueError(f"build_pm: vertex {bad} has a coordinate that is not finite or beyond float32's range "
                         f"(|x| <= {FLOAT32_MAX:.8g}), which pmjax stores: {v0[bad].tolist()}")
    if int(f0.min()) < 0 or int(f0.max()) >= V0:
        out = (f0 < 0) | (f0 >= V0)
        bad = int(np.flatnonzero(np.any(out, axis=1))[0])
        raise ValueError(f"build_pm: face {bad} holds vertex id {int(f0[bad][out[bad]][0])}, outside 0 .. {V0 - 1}; "
                         "clean the mesh with pmjax.clean_mesh first")
    return f0 if f0.dtype == np.int32 else f0.astype(np.int32)


def _select_batch(a, b, x, link_test, elig, cur, n_vertices, pos, min_area2, boundary_vertex, linear, eager_skip,
                  mesh):
    """Independent valid collapses among the eligible candidates.

    Args:
        a, b, x, link_test: all candidates' endpoints, placements ``(C, 3)``
            and whether the link test applies.
        elig: ids of the eligible candidates, cheapest first (order = priority).
        cur: ``(F, 3)`` current faces; n_vertices: ids in use.
        linear: take only the cheapest valid candidate.
        eager_skip: ``None`` to check only the greedy winners' validity;
            else every eligible candidate's is checked up front, except where
            this ``bool`` mask over ``elig`` says it is known invalid.
        mesh: the current mesh for the C loops (:class:`builders._native.Mesh`),
            or ``None`` for the NumPy path.

    Returns:
        ``(chosen, invalid, invalid_share)``: ids of the chosen candidates,
        cheapest first; ids of those found invalid; and the share of the
        checked candidates that were invalid (known invalid ones included).
    """
    if not linear and mesh is not None:
        return _select_batch_native(a, b, x, link_test, elig, min_area2, boundary_vertex, eager_skip, mesh)
    checked, invalid = [0], [np.zeros(0, np.int64)]

    def is_valid_one(idx, pair, face):
        return collapse_is_valid(
            pos, cur, a[idx], b[idx], x[idx], pair, face,
            min_area2=min_area2, link_test=link_test[idx], boundary_vertex=boundary_vertex,
        )

    def is_valid(idx, pair, face):
        ok = split_pairs(is_valid_one, idx, pair, face)
        checked[0] += len(ok)
        invalid.append(idx[~ok])
        return ok

    check = is_valid
    skipped = 0
    if eager_skip is not None:
        skipped = int(np.count_nonzero(eager_skip))
        idx = elig[~eager_skip]
        elig = idx[is_valid(idx, *VertexFaces(cur, n_vertices).of_pairs(a[idx], b[idx], cur))]
        # All left are valid: the greedy need not check them again.
        check = lambda idx, pair, face: np.ones(len(idx), bool)  # noqa: E731
    ea, eb = a[elig], b[elig]
    if linear:
        chosen = _first_valid(lambda i, p, f: check(elig[i], p, f), ea, eb, cur, n_vertices)
    else:
        chosen = select_independent(ea, eb, cur, n_vertices, lambda i, p, f: check(elig[i], p, f))
    invalid = np.concatenate(invalid)
    return elig[chosen], invalid, (len(invalid) + skipped) / max(checked[0] + skipped, 1)


def _select_batch_native(a, b, x, link_test, elig, min_area2, boundary_vertex, eager_skip, mesh):
    """:func:`_select_batch` as the C loops: the same chosen set, invalid set
    and share."""
    cand = native.Candidates(a, b, x, link_test)
    invalid, checked, skipped = np.zeros(0, np.int64), 0, 0
    if eager_skip is not None:
        # Every eligible candidate not known invalid is checked up front.
        skipped = int(np.count_nonzero(eager_skip))
        idx = elig[~eager_skip]
        # Checked in id order (edges are in vertex order): neighbouring checks
        # share cache lines, where cost order jumps across the mesh.
        order = np.argsort(idx)
        ok = np.empty(len(idx), bool)
        ok[order] = native.collapse_is_valid(mesh, cand, idx[order], boundary_vertex, min_area2)
        invalid, checked, elig = idx[~ok], len(idx), idx[ok]
    chosen, bad, n_checked = native.select_independent(
        mesh, cand, elig, boundary_vertex, min_area2, assume_valid=eager_skip is not None
    )
    invalid = np.concatenate([invalid, elig[bad]])
    checked += n_checked
    return elig[chosen], invalid, (len(invalid) + skipped) / max(checked + skipped, 1)


def _start_attributes(pos, normals, faces, V0, edges):
    """Normals of the original vertices, then their attribute state
    (``edges``: :func:`unique_edges` of ``faces``)."""
    normals[:V0] = vertex_normals(pos[:V0], faces, V0)
    return HierarchyAttributes(pos, normals, faces, V0, edges)


def _attribute_batch(start, pos, normals, cur, first, ca, cb, maybe_border):
    """Normals and refinement attributes of the batch's new vertices
    ``first .. first+k-1``; ``cur`` are the faces after the batch;
    ``maybe_border`` flags new vertices with a child on an open border."""
    k = len(ca)
    new = slice(first, first + k)
    # Normals from the faces around the new vertices only.
    ring = cur[any3(cur >= first)]
    vn = _new_vertex_normals(pos, ring, first, k)
    # A vertex left without faces inherits its children's mean normal.
    lonely = np.linalg.norm(vn, axis=1) == 0
    if lonely.any():
        s = normals[ca[lonely]] + normals[cb[lonely]]
        sl = np.linalg.norm(s, axis=1)
        vn[lonely] = np.where(sl[:, None] > 0, s / np.where(sl > 0, sl, 1)[:, None], [0.0, 0.0, 1.0])
    normals[new] = vn
    start.result().add_batch(first, ca, cb, ring, maybe_border)


def _new_vertex_normals(pos, faces, first, k):
    """Area-weighted unit normals of vertices ``first .. first+k-1``."""
    if native.available():
        # Face normals made and summed in one pass (C), older corners skipped.
        return unit(native.new_vertex_normals(pos, faces, first, k))
    corner = faces.ravel() - first
    new = corner >= 0
    cross = np.repeat(qd.face_cross(pos, faces), 3, axis=0)
    return unit(qd.scatter_add(cross[new], corner[new], k))


def _cheapest(cost: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` cheapest entries in stable cost order: the first
    ``k`` of ``np.argsort(cost, kind="stable")``, without sorting the rest
    (a batch takes the cheapest share; sorting all candidates would be the
    builder's largest single cost)."""
    if k >= len(cost) and not native.available():
        return _stable_argsort(cost)
    kth = np.partition(cost, k - 1)[k - 1]
    if native.available():
        # Picked in index order and their ties put back in it (C), around
        # NumPy's quicksort of the picked costs.
        pick = native.cheapest(cost, k, kth)
        if pick is not None:
            return pick
    # Everything cheaper than the k-th cost, then its ties by index.
    below = np.flatnonzero(cost < kth)
    ties = np.flatnonzero(cost == kth)[: k - len(below)]
    pick = np.concatenate([below, ties])
    pick.sort()
    return pick[_stable_argsort(cost[pick])]


def _stable_argsort(x: np.ndarray) -> np.ndarray:
    """``np.argsort(x, kind="stable")`` for floats, faster: NumPy's
    quicksort, which has SIMD kernels where its stable merge sort has none,
    then each run of equal values put back in index order."""
    order = np.argsort(x, kind="quicksort")
    if len(order) < 2:
        return order
    same = x[order[1:]] == x[order[:-1]]
    if not same.any():
        return order
    # Positions inside runs of equal values; sort them by (run, index).
    in_run = np.zeros(len(order), bool)
    in_run[1:] |= same
    in_run[:-1] |= same
    run = np.cumsum(np.r_[True, ~same])  # run number of every position
    pos = np.flatnonzero(in_run)
    key = run[pos].astype(np.int64) * len(order) + order[pos]
    order[pos] = order[pos][np.argsort(key)]
    return order


def _sorted_by_key(keys, x, cost):
    # Edge-only candidates come out of unique_edges already in key order.
    if np.all(keys[1:] > keys[:-1]):
        return keys, x, cost
    order = np.argsort(keys)
    return keys[order], x[order], cost[order]


def _cached_costs(cache, keys, metric, pos, cur, quadric, a, b, boundary_weight):
    """Costs from ``cache = [metric, keys, x, cost]`` where the pair is known.
    The list is emptied once its rows are carried, so that the fresh pairs
    are placed without last batch's arrays held."""
    _, old_keys, old_x, old_cost = cache
    # Edges come in key order: a merge carries the known rows (C).
    carried = native.carry_costs(old_keys, old_x, old_cost, keys) if native.available() else None
    if carried is not None:
        cache.clear()
        old_keys = old_x = old_cost = None
        x, cost, fresh = carried
        if metric == "quadric":
            native.quadric_placement(quadric, pos, a, b, rows=fresh, x=x, cost=cost)
        else:
            x[fresh], cost[fresh] = evaluate_metric(metric, pos, cur, quadric, a[fresh], b[fresh], boundary_weight)
        return x, cost
    i = np.minimum(np.searchsorted(old_keys, keys), len(old_keys) - 1)
    known = old_keys[i] == keys
    x = old_x[i]
    cost = old_cost[i]
    fresh = ~known
    if fresh.any():
        x[fresh], cost[fresh] = evaluate_metric(metric, pos, cur, quadric, a[fresh], b[fresh], boundary_weight)
    return x, cost


def _first_valid(is_valid, a, b, cur, n_vertices) -> np.ndarray:
    """The cheapest valid candidate (linear mode); candidates are in cost order."""
    every_face = np.arange(len(cur))
    owner = np.full(n_vertices, -1, np.int32)
    for i in range(len(a)):
        idx = np.array([i])
        pair, face = domain_of_independent(a[idx], b[idx], cur, every_face, owner)
        if is_valid(idx, pair, face)[0]:
            return idx
    return np.zeros(0, np.int64)


