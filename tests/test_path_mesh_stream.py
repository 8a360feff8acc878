"""Drawable meshes along a path: each frame's change, applied to the last
frame's slots, gives exactly that frame's Refinement.mesh()."""

import contextlib
import dataclasses
import pickle

import equinox as eqx
import jax
import numpy as np
import pytest

import pmjax
from pmjax import _path, engines
from pmjax._camera import index_camera, stack_cameras
from pmjax.engines import _core

_MESHES = {}


def model(built, name):
    if name not in _MESHES:
        data = built(name)
        _MESHES[name] = data, pmjax.ProgressiveMesh.from_data(data)
    return _MESHES[name]


@pytest.fixture(scope="module", autouse=True)
def release_meshes():
    yield
    _MESHES.clear()


def originals(data):
    return data.vertices[: data.n_original_vertices]


def hand_held(data, n, seed, cuts=()):
    """The standard orbit shaken as if hand-held (eye 1 %, aim 2 % of the
    model's size per frame), jumping elsewhere at ``cuts``."""
    v0 = originals(data)
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    rng = np.random.default_rng(seed)
    orbit = pmjax.standard_orbit(v0, n)
    eyes = np.asarray(orbit.eye) + 0.01 * r * rng.normal(size=(n, 3))
    for i in cuts:
        d = rng.normal(size=3)
        eyes[i:] += rng.uniform(0.2, 1.5) * r * d / np.linalg.norm(d)
    return stack_cameras([pmjax.look_at(e, c + 0.02 * r * rng.normal(size=3)) for e in eyes])


def fly_through(data, n):
    """From far in front, through the model, out the back."""
    v0 = originals(data)
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    return pmjax.fly_through([(c + [0, 0, 2 * r], c), (c + [0, 0.02 * r, 0.05 * r], c), (c - [0, 0, 2 * r], c)], n)


class Replay:
    """A renderer's buffers: the change's rows written in place."""

    def __init__(self):
        self.faces = np.zeros((0, 3), np.int32)
        self.ids = np.zeros(0, np.int32)
        self.positions = np.zeros((0, 3), np.float32)

    def apply(self, change: pmjax.MeshChange):
        grow = change.n_face_slots - len(self.faces)
        if grow > 0:
            self.faces = np.concatenate([self.faces, np.full((grow, 3), -1, np.int32)])
        grow = change.n_vertex_slots - len(self.ids)
        if grow > 0:
            self.ids = np.concatenate([self.ids, np.full(grow, -1, np.int32)])
            self.positions = np.concatenate([self.positions, np.zeros((grow, 3), np.float32)])
        assert len(np.unique(change.face_slots)) == len(change.face_slots)
        assert len(np.unique(change.vertex_slots)) == len(change.vertex_slots)
        self.faces[change.face_slots] = change.faces
        self.ids[change.vertex_slots] = change.vertex_ids
        self.positions[change.vertex_slots] = change.vertex_positions

    def face_set(self):
        """The faces held as (id, id, id) rows, corners in their order."""
        live = self.faces[np.all(self.faces >= 0, axis=1)]
        assert np.all(self.ids[live] >= 0)
        return {tuple(row) for row in self.ids[live].tolist()}


def assert_same_mesh(replay, stream, r, where):
    v, f, ids = r.mesh()
    # As a set of faces over the same vertex positions, from the change alone.
    assert replay.face_set() == {tuple(row) for row in ids[f].tolist()}, where
    live = replay.ids >= 0
    assert np.array_equal(replay.positions[live], np.asarray(r.pm.vertices)[replay.ids[live]]), where
    assert int(live.sum()) == int(r.n_vertices), where  # the whole front, one slot per vertex
    assert int(np.all(replay.faces >= 0, axis=1).sum()) == int(r.n_faces), where
    # The stream's own arrays are the replayed ones; compacted, they are mesh() bit for bit.
    assert np.array_equal(stream.faces, replay.faces) and np.array_equal(stream.vertex_ids, replay.ids), where
    v2, f2, ids2 = stream.mesh()
    assert np.array_equal(ids, ids2) and np.array_equal(f, f2) and np.array_equal(v, v2), where


def follow(pm, frames, stream=None, replay=None, where=""):
    """Feed refinements to a stream (and the buffers replaying its changes),
    checking every frame; with a new stream, the slots' high water marks
    against the largest mesh seen (freed slots are reused first)."""
    fresh = stream is None
    stream, replay = stream or pmjax.MeshStream(pm), replay or Replay()
    most_faces = most_vertices = 0
    for i, r in enumerate(frames):
        change = stream.update(r)
        replay.apply(change)
        assert_same_mesh(replay, stream, r, (where, i))
        most_faces, most_vertices = max(most_faces, int(r.n_faces)), max(most_vertices, int(r.n_vertices))
        if fresh and stream._stream is not None:
            assert change.n_face_slots == most_faces and change.n_vertex_slots == most_vertices, (where, i)
    return stream, replay


@pytest.mark.parametrize("name", ["cow.ply", "bunny.ply"])
def test_change_stream_equals_mesh_on_paths(built, name):
    data, pm = model(built, name)
    paths = {"orbit": pmjax.standard_orbit(originals(data), 48), "fly-through": fly_through(data, 40),
             "hand-held with cuts": hand_held(data, 48, seed=3, cuts=(9, 10, 33))}
    for label, cams in paths.items():
        follow(pm, pmjax.refine_path(pm, cams, 1.0), where=label)


def test_change_stream_through_tau_and_image_size_changes(built):
    """One stream across paths: a tolerance changing each frame, then the
    image size changing mid-way (a second path), then single views of other
    engines, then back to a path."""
    data, pm = model(built, "cow.ply")
    cams = pmjax.standard_orbit(originals(data), 40)
    taus = np.geomspace(0.05, 40, 40).astype(np.float32)
    taus[5] = 0.0
    taus[20] = np.inf
    small = eqx.tree_at(lambda c: (c.width, c.height), cams,
                        (np.full(40, 320, np.int32), np.full(40, 200, np.int32)))

    def frames():
        yield from pmjax.refine_path(pm, cams, taus)
        yield from pmjax.refine_path(pm, small, 2.0)
        for i in (3, 30):
            yield pmjax.refine(pm, index_camera(cams, i), 1.0)
            yield pmjax.refine(pm, index_camera(cams, i), 1.0, method="dense")
        yield from pmjax.refine_path(pm, cams, 0.5, coherent=False)
        yield from pmjax.refine_path(pm, cams, 1.0)

    follow(pm, frames(), where="tau, size, engines")


@pytest.mark.parametrize("core", [True, False])
def test_change_stream_empty_then_same_frame_twice(built, core):
    """A stream given nothing holds an empty mesh; a frame given twice
    changes nothing the second time; the arrays mesh() returned stay as
    they were when later frames come (they are the caller's)."""
    data, pm = model(built, "cow.ply")
    cams = pmjax.standard_orbit(originals(data), 20)
    frames = list(pmjax.refine_path(pm, cams, 1.0))
    with engines.without_core() if not core else contextlib.nullcontext():
        stream = pmjax.MeshStream(pm)
        v, f, ids = stream.mesh()
        assert (v.shape, v.dtype, f.shape, f.dtype, ids.shape, ids.dtype) == (
            (0, 3), np.float32, (0, 3), np.int32, (0,), np.int32)
        replay = Replay()
        replay.apply(stream.update(frames[7]))
        held = stream.mesh()
        kept = tuple(a.copy() for a in held)
        again = stream.update(frames[7])
        assert len(again.face_slots) == len(again.vertex_slots) == 0
        replay.apply(again)
        assert_same_mesh(replay, stream, frames[7], "the same frame twice")
        follow(pm, frames[8:], stream, replay, where="after it")
        for a, b in zip(held, kept):
            assert np.array_equal(a, b)


def test_change_stream_frames_in_any_order(built):
    """A path's frames given one by one in a shuffled order, with single
    views of another engine among them: each mesh is that frame's."""
    data, pm = model(built, "cow.ply")
    cams = hand_held(data, 32, seed=19, cuts=(8, 20))
    frames = list(pmjax.refine_path(pm, cams, 1.5))
    order = np.random.default_rng(23).permutation(len(frames))

    def shuffled():
        for n, i in enumerate(order):
            yield frames[i]
            if n % 7 == 3:
                yield pmjax.refine(pm, index_camera(cams, int(i)), 1.5, method="dense")

    follow(pm, shuffled(), where="shuffled")


@pytest.mark.parametrize("name", ["cow.ply", pytest.param("bunny.ply", marks=pytest.mark.slow)])
def test_compacted_mesh_after_frames_not_compacted(built, name):
    """mesh() after any number of frames it was not asked for (the rows of
    the last compaction merged with the changes since; after the finest and
    the coarsest meshes in turn, more changes than rows: ranked afresh),
    and twice for one frame: always the last frame's mesh. The cow's ids
    sort in two byte digits, the bunny's in three (the sorted log in the
    other buffer)."""
    data, pm = model(built, name)
    n = 64
    cams = hand_held(data, n, seed=29, cuts=(15, 40))
    taus = np.geomspace(0.1, 20, n).astype(np.float32)
    taus[[10, 12, 30, 50]] = 0.0
    taus[[11, 13, 31, 51]] = np.inf
    frames = list(pmjax.refine_path(pm, cams, taus))
    stream, i = pmjax.MeshStream(pm), -1
    assert (stream._stream is not None) == _core.enabled()
    for gap in (1, 1, 2, 5, 1, 3, 8, 1, 1, 2, 15, 1, 4, 19):
        for _ in range(gap):
            i += 1
            stream.update(frames[i] if i % 9 else pmjax.refine(pm, index_camera(cams, i), taus[i], method="dense"))
        want = frames[i].mesh()
        for _ in range(1 + (gap == 2)):
            got = stream.mesh()
            assert all(np.array_equal(a, b) for a, b in zip(got, want)), i
    assert i == n - 1


def test_compacted_meshes_kept_by_the_caller_in_any_order(built):
    """Frames of a path with cuts and single views of another engine, in a
    shuffled order, mesh() asked 0, 1 or 2 times after each: every mesh
    returned is kept, and at the end each still equals its frame's
    Refinement.mesh() (later updates and compactions, merged or ranked
    afresh, write into arrays of their own)."""
    data, pm = model(built, "cow.ply")
    cams = hand_held(data, 30, seed=41, cuts=(7, 19))
    frames = list(pmjax.refine_path(pm, cams, 1.0))
    rng = np.random.default_rng(43)
    stream, kept = pmjax.MeshStream(pm), []
    for n, i in enumerate(rng.permutation(len(frames))):
        r = frames[i] if n % 5 else pmjax.refine(pm, index_camera(cams, int(i)), 1.0, method="dense")
        stream.update(r)
        for _ in range(int(rng.integers(0, 3))):
            kept.append((r, stream.mesh()))
    assert len({id(r) for r, _ in kept}) > 10
    for n, (r, got) in enumerate(kept):
        assert all(np.array_equal(a, b) for a, b in zip(got, r.mesh())), n


@pytest.mark.skipif(not _core.built(), reason="the C core is not built")
def test_compacted_mesh_every_frame_at_each_simd_level(built, simd):
    """mesh() after every frame of a long path (teleports, a tolerance and
    an image size changing, the coarsest and the finest meshes, a frame
    given twice), with the faces written four at a time (vector levels) or
    one by one (plain): each is the frame's own ``refine(...).mesh()`` bit
    for bit, asked twice in a row it is the same, and every mesh returned
    stays as it was while the later ones are made."""
    data, pm = model(built, "cow.ply")
    n = 72
    cams = hand_held(data, n, seed=47, cuts=(6, 7, 25, 26, 50))
    cams = eqx.tree_at(lambda c: (c.width, c.height), cams,
                       (np.where(np.arange(n) < 40, 640, 200).astype(np.int32),
                        np.where(np.arange(n) < 40, 480, 150).astype(np.int32)))
    taus = np.geomspace(0.2, 8, n).astype(np.float32)
    taus[[12, 60]] = np.inf  # the coarsest mesh: the fewest faces
    taus[[13, 61]] = 0.0  # the finest
    stream, kept = pmjax.MeshStream(pm), []
    order = list(range(n))
    order.insert(31, 30)  # frame 30 twice: nothing changes, nothing logged
    for n_asked, i in enumerate(order):
        cam = index_camera(cams, i)
        stream.update(pmjax.refine(pm, cam, taus[i]))
        want = pmjax.refine(pm, cam, taus[i], method="dense").mesh()
        got = stream.mesh()
        assert all(np.array_equal(a, b) for a, b in zip(got, want)), (simd, i)
        if i % 5 == 0:  # twice in a row: the rows just kept, an empty log
            again = stream.mesh()
            assert all(np.array_equal(a, b) for a, b in zip(again, want)), (simd, i)
            assert all(a is not b and not np.shares_memory(a, b) for a, b in zip(again, got))
        kept.append((want, got))
    # Whole blocks of four faces, and blocks and a tail (a closed mesh's
    # faces are even in number).
    assert {len(want[1]) % 4 for want, _ in kept} >= {0, 2}
    for n_asked, (want, got) in enumerate(kept):
        assert all(np.array_equal(a, b) for a, b in zip(got, want)), (simd, n_asked)


def test_refine_path_changes_yields_each_frame_with_its_change(built):
    data, pm = model(built, "cow.ply")
    cams = hand_held(data, 36, seed=5, cuts=(17,))
    stream = pmjax.MeshStream(pm)
    replay = Replay()
    got = list(pmjax.path_mesh_changes(pm, cams, 1.0, stream=stream))
    assert len(got) == 36
    for i, ((r, change), want) in enumerate(zip(got, pmjax.refine_path(pm, cams, 1.0), strict=True)):
        assert np.array_equal(np.asarray(r.executed), np.asarray(want.executed)), i
        replay.apply(change)
    assert_same_mesh(replay, stream, got[-1][0], "last")


def follow_changes(pm, cams, tau, where=""):
    """``path_mesh_changes`` frame by frame: each change replayed and the
    stream's own mesh checked at that frame against ``refine`` of the frame
    alone. Returns each frame's faces (rows of vertex ids)."""
    stream, replay, faces = pmjax.MeshStream(pm), Replay(), []
    alone = pmjax.refine_path(pm, cams, tau, coherent=False)
    for i, ((r, change), want) in enumerate(zip(pmjax.path_mesh_changes(pm, cams, tau, stream=stream), alone, strict=True)):
        assert np.array_equal(np.asarray(r.executed), np.asarray(want.executed)), (where, i)
        replay.apply(change)
        assert_same_mesh(replay, stream, want, (where, i))
        faces.append(replay.face_set())
    assert len(faces) == len(cams.eye), where
    return faces


@pytest.mark.parametrize("name,n", [("cow.ply", 36), pytest.param("bunny.ply", 70, marks=pytest.mark.slow)])
def test_path_mesh_changes_every_frame(built, name, n):
    """Words of 16 frames in blocks of words: frames within a word, across
    words (and blocks, on the bunny), cuts inside and at the edge of a word,
    a tolerance changing each frame; the stream holds each frame's mesh as
    it is given."""
    data, pm = model(built, name)
    cams = hand_held(data, n, seed=13, cuts=(16, 23, 64))
    taus = np.geomspace(0.3, 6.0, n).astype(np.float32)
    follow_changes(pm, cams, taus, f"{name} hand-held")


@pytest.mark.core
def test_path_mesh_changes_in_a_padded_last_call(built, monkeypatch):
    """Seven words stream as one call of eight, the eighth repeating the
    last frame (never yielded): every frame and change as the frame alone
    gives them."""
    data, pm = model(built, "cow.ply")
    sizes = []
    real = _path._core_words
    monkeypatch.setattr(_path, "_core_words", lambda tables, one, rows, *a: sizes.append(len(rows)) or
                        real(tables, one, rows, *a))
    faces = follow_changes(pm, hand_held(data, 112, seed=5, cuts=(40,)), 1.0, "cow, seven words")
    assert sizes == [128] and len(faces) == 112


def _moved(data, scale, offset):
    """``data`` scaled about the origin, then moved by ``offset`` model sizes
    (as tests/test_scale.py moves it)."""
    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    size = scale * float(np.ptp(data.vertices[: data.n_original_vertices], axis=0).max())
    lengths = {k: (f64(getattr(data, k)) * scale).astype(np.float32) for k in ("radius", "delta", "mu")}
    return dataclasses.replace(data, vertices=(f64(data.vertices) * scale + offset * size).astype(np.float32),
                               **lengths)


def _moved_cameras(data, scale, offset, n):
    cams = hand_held(data, n, seed=17, cuts=(21,))
    size = scale * float(np.ptp(data.vertices[: data.n_original_vertices], axis=0).max())
    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    return pmjax.Camera(f64(cams.eye) * scale + offset * size, np.asarray(cams.rotation), np.asarray(cams.fov_y),
                        f64(cams.near) * scale, f64(cams.far) * scale, f64(cams.ortho_height) * scale,
                        np.asarray(cams.width), np.asarray(cams.height), cams.orthographic)


@pytest.mark.slow
@pytest.mark.parametrize("scale,offset", [(1e-6, 3.0), (1e6, -2.0)])
def test_path_mesh_changes_at_any_scale(built, scale, offset):
    """The model scaled and moved, the cameras with it: frame by frame the
    same faces as at unit scale, each frame's mesh that of refine alone."""
    data, pm = model(built, "cow.ply")
    unit = follow_changes(pm, _moved_cameras(data, 1.0, 0.0, 40), 1.0, "unit")
    moved = pmjax.ProgressiveMesh.from_data(_moved(data, scale, offset))
    got = follow_changes(moved, _moved_cameras(data, scale, offset, 40), 1.0, f"scale {scale}")
    for i, (a, b) in enumerate(zip(unit, got)):
        assert a == b, (scale, i)


@pytest.mark.skipif(not _core.built(), reason="the C core is not built")
def test_core_stream_lane_needs_a_word(built):
    """The step to another frame of the word held is refused, nothing
    changed, when the stream holds one camera's lists or the bit is not one
    of the word's."""
    data, pm = model(built, "cow.ply")
    cams = pmjax.standard_orbit(originals(data), 20)
    stream = pmjax.MeshStream(pm)
    stream.update(pmjax.refine(pm, index_camera(cams, 0), 1.0))
    before = stream.faces
    with pytest.raises(ValueError, match="holds no word"):
        _core._pmx.mesh_stream_lane(stream._stream, 1)
    assert np.array_equal(stream.faces, before)
    frames = list(pmjax.refine_path(pm, cams, 1.0))
    stream, replay = pmjax.MeshStream(pm), Replay()
    replay.apply(stream.update(frames[0]))
    with pytest.raises(ValueError, match="not one of its 16 bits"):
        _core._pmx.mesh_stream_lane(stream._stream, 16)
    replay.apply(stream.update(frames[5]))  # the same word: the step by its bit alone, from frame 0's mesh
    assert_same_mesh(replay, stream, frames[5], "frame 5")
    follow(pm, frames[6:], stream, replay, where="after the refusals")


def test_change_stream_without_the_core(built):
    """Without the C core the stream compares meshes by ids: the same meshes."""
    data, pm = model(built, "cow.ply")
    cams = hand_held(data, 24, seed=7, cuts=(12,))
    with engines.without_core():
        stream = pmjax.MeshStream(pm)
        assert stream._stream is None
        stream, replay = follow(pm, pmjax.refine_path(pm, cams, 1.0), stream, where="no core")
        follow(pm, pmjax.refine_path(pm, cams, 4.0), stream, replay, where="no core, tau 4")


def test_change_stream_refuses_other_meshes_and_traced_refinements(built):
    _, cow = model(built, "cow.ply")
    data, bunny = model(built, "bunny.ply")
    stream = pmjax.MeshStream(cow)
    cam = pmjax.standard_orbit(originals(data), 2)
    with pytest.raises(ValueError, match="another mesh"):
        stream.update(pmjax.refine(bunny, index_camera(cam, 0), 1.0))

    @jax.jit
    def traced(c):
        stream.update(pmjax.refine(cow, c, 1.0))
        return 0

    with pytest.raises(ValueError, match="being traced"):
        traced(index_camera(cam, 0))


@pytest.mark.skipif(not _core.built(), reason="the C core is not built")
def test_core_stream_refuses_lists_out_of_order(built):
    """Positions that do not increase are refused before anything changes:
    the stream still holds its frame."""
    data, pm = model(built, "cow.ply")
    stream = pmjax.MeshStream(pm)
    r = pmjax.refine(pm, index_camera(pmjax.standard_orbit(originals(data), 2), 0), 1.0)
    stream.update(r)
    before = stream.faces
    positions = np.ascontiguousarray(np.asarray(r.front_positions)[::-1])
    with pytest.raises(ValueError, match="do not increase"):
        _core._pmx.mesh_stream_step(stream._stream, positions, np.asarray(r.core_ran)[::-1].copy(), 0,
                                    len(positions), -1)
    assert np.array_equal(stream.faces, before)
    with pytest.raises(ValueError, match="frame 3 is not a bit"):
        _core._pmx.mesh_stream_step(stream._stream, np.asarray(r.front_positions), np.asarray(r.core_ran), 3,
                                    len(positions), -1)


@pytest.mark.skipif(not _core.built(), reason="the C core is not built")
def test_core_stream_checks_other_lists_under_a_key_it_has_seen(built):
    """A key names a word's lists only with the arrays it came with: lists
    given again under that key but in other arrays (here with a position
    outside the hierarchy) are checked, and refused before anything
    changes."""
    data, pm = model(built, "cow.ply")
    stream = pmjax.MeshStream(pm)
    r = pmjax.refine(pm, index_camera(pmjax.standard_orbit(originals(data), 2), 0), 1.0)
    positions = np.asarray(r.front_positions).copy()
    n = len(positions)
    ran = np.asarray(r.core_ran)[:n].astype(np.uint16)
    _core._pmx.mesh_stream_step(stream._stream, positions, ran, 0, n, 5)
    before = _core._pmx.mesh_stream_step(stream._stream, positions, ran, 0, n, 5)[:8]
    other, other_ran = positions.copy(), ran.copy()
    other[-1] = 1 << 30
    other_ran[-1] ^= 2
    with pytest.raises(ValueError, match="do not increase"):
        _core._pmx.mesh_stream_step(stream._stream, other, other_ran, 1, n, 5)
    assert _core._pmx.mesh_stream_step(stream._stream, positions, ran, 0, n, 5)[4:7] == before[4:7]


@pytest.mark.slow
def test_change_stream_on_the_dragon(built):
    data, pm = model(built, "dragon.ply")
    follow(pm, pmjax.refine_path(pm, pmjax.standard_orbit(originals(data), 64), 1.0), where="dragon orbit")
    follow(pm, pmjax.refine_path(pm, hand_held(data, 48, seed=11, cuts=(20,)), 1.0), where="dragon hand-held")


def _away_from_the_model(data, n):
    """Frames whose eyes circle the model looking away from it (nothing in
    the frustum: every pcol culled)."""
    v0 = originals(data)
    c, r = v0.mean(0), np.linalg.norm(np.ptp(v0, 0))
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    eyes = c + 1.5 * r * np.stack([np.cos(angles), 0.2 * np.ones(n), np.sin(angles)], 1)
    return stack_cameras([pmjax.look_at(e, e + (e - c)) for e in eyes])


def test_path_mesh_changes_continued_across_calls(built):
    """One stream across calls of path_mesh_changes: a hand-held path with
    a cut, a path that leaves the frustum (the model behind the camera) and
    comes back, a fly-through through the model with a tolerance changing
    each frame, then a path at another image size and tolerance. Each call's
    first change is from the last call's mesh; each change's arrays, read
    only after the call has made every frame, replay each frame's mesh."""
    data, pm = model(built, "cow.ply")
    cams = hand_held(data, 40, seed=23, cuts=(29,))
    away = _away_from_the_model(data, 20)
    back = stack_cameras([index_camera(cams, i) for i in range(8)] + [index_camera(away, i) for i in range(20)]
                         + [index_camera(cams, i) for i in range(8, 20)])
    fly = fly_through(data, 36)
    small = eqx.tree_at(lambda c: (c.width, c.height), fly, (np.full(36, 320, np.int32), np.full(36, 200, np.int32)))
    calls = [(cams, 1.0), (back, 2.0), (fly, np.geomspace(0.2, 8.0, 36).astype(np.float32)), (small, 0.7)]
    stream, replay = pmjax.MeshStream(pm), Replay()
    for k, (path, tau) in enumerate(calls):
        frames = list(pmjax.path_mesh_changes(pm, path, tau, stream=stream))  # every frame made first
        alone = pmjax.refine_path(pm, path, tau, coherent=False)
        for i, ((r, change), want) in enumerate(zip(frames, alone, strict=True)):
            assert np.array_equal(np.asarray(r.executed), np.asarray(want.executed)), (k, i)
            replay.apply(change)
            v, f, ids = want.mesh()
            assert replay.face_set() == {tuple(row) for row in ids[f].tolist()}, (k, i)
            assert int(np.count_nonzero(replay.ids >= 0)) == int(want.n_vertices), (k, i)
        assert_same_mesh(replay, stream, frames[-1][0], k)
    # The frames that look away draw the coarsest mesh the view allows: all culled.
    culled = pmjax.refine(pm, index_camera(away, 3), 2.0)
    assert int(culled.n_faces) == int(pmjax.refine(pm, index_camera(away, 3), np.inf).n_faces)


@pytest.mark.skipif(not _core.built(), reason="the C core is not built")
def test_core_change_arrays_are_the_changes_own(built):
    """A change's arrays are made from the core's packed change when read:
    read at once, read after later frames, or read in another order, they
    are the same arrays, and later frames do not change them."""
    data, pm = model(built, "cow.ply")
    cams = hand_held(data, 40, seed=29, cuts=(20,))
    fields = ("face_slots", "faces", "vertex_slots", "vertex_ids", "vertex_positions")
    stream, early, changes = pmjax.MeshStream(pm), [], []
    for _, change in pmjax.path_mesh_changes(pm, cams, 1.0, stream=stream):
        early.append([getattr(change, name).copy() for name in fields])
        changes.append(change)
    # The same path again, its changes' arrays first read after every frame
    # is made, in reverse order: the same arrays as those read at once.
    late = [change for _, change in pmjax.path_mesh_changes(pm, cams, 1.0, stream=pmjax.MeshStream(pm))]
    for i, (change, want) in reversed(list(enumerate(zip(late, early, strict=True)))):
        for name, a in reversed(list(zip(fields, want))):
            assert np.array_equal(getattr(change, name), a), (i, name)
    for i, (change, want) in enumerate(zip(changes, early, strict=True)):
        for name, a in reversed(list(zip(fields, want))):
            b = getattr(change, name)
            assert b.dtype == a.dtype and b.shape == a.shape and np.array_equal(a, b), (i, name)
            assert getattr(change, name) is b  # made once
        k, u = len(change.face_slots), len(change.vertex_slots)
        assert change.faces.shape == (k, 3) and change.vertex_positions.shape == (u, 3), i
        assert change.face_slots.max(initial=-1) < change.n_face_slots, i
        assert change.vertex_slots.max(initial=-1) < change.n_vertex_slots, i
    # A change made from arrays (the stream without the core) reads them back.
    made = pmjax.MeshChange(*early[3], changes[3].n_face_slots, changes[3].n_vertex_slots)
    assert all(np.array_equal(getattr(made, name), a) for name, a in zip(fields, early[3]))
    assert made.n_face_slots == changes[3].n_face_slots
    # A change is also the tuple of its seven fields: unpacked, indexed,
    # pickled, replaced, and a JAX tree whose leaves are those fields.
    for change in (changes[3], made):
        face_slots, faces, vertex_slots, vertex_ids, positions, n_f, n_v = change
        assert len(change) == 7 and change[1] is faces and change[-1] == n_v == change.n_vertex_slots
        assert list(change._asdict()) == list(fields) + ["n_face_slots", "n_vertex_slots"]
        for other in (pickle.loads(pickle.dumps(change, protocol=0)), pickle.loads(pickle.dumps(change)),
                      jax.tree.unflatten(*reversed(jax.tree.flatten(change))), change._replace()):
            assert type(other) is pmjax.MeshChange and (other.n_face_slots, other.n_vertex_slots) == (n_f, n_v)
            assert all(np.array_equal(a, b) for a, b in zip(list(other)[:5], early[3]))
        assert len(jax.tree.leaves(change)) == 7
        assert change._replace(n_face_slots=n_f + 1).n_face_slots == n_f + 1


@pytest.mark.skipif(not _core.built(), reason="the C core is not built")
def test_a_stream_whose_step_failed_takes_no_more_steps(built):
    """A step that fails (here the core's call raising MemoryError) leaves a
    stream whose core may hold the failed frame's lists: they are kept, and
    later steps are refused with a clear error instead of reading them."""
    data, pm = model(built, "cow.ply")
    cams = hand_held(data, 4, seed=5)
    stream = pmjax.MeshStream(pm)
    first, second = (pmjax.refine(pm, index_camera(cams, i), 1.0) for i in range(2))
    stream.update(first)
    step = stream._step

    def failing(*args):
        raise MemoryError("out of memory")

    stream._step = failing
    with pytest.raises(MemoryError):
        stream.update(second)
    assert stream._kept is not None
    stream._step = step
    with pytest.raises(ValueError, match="an earlier step failed; make a new MeshStream"):
        stream.update(second)


@pytest.mark.parametrize("name", ["cow.ply", pytest.param("bunny.ply", marks=pytest.mark.slow)])
def test_faces_killed_and_drawn_again_many_times(built, name):
    """A tolerance jumping between fine and coarse every frame (a face
    killed by one frame is drawn again by a later one, its corners' vertices
    split or collapsed meanwhile, many times over), along a fly-through
    through the model and a hand-held path with cuts, one stream continued
    across the calls of path_mesh_changes: each frame's mesh is exactly its
    refinement's. The corners of the faces drawn again find their vertex
    at the split's two vertices or from the third corner's last vertex;
    the walk among the split's neighbours (faces drawn for the first time)
    is a small minority of the third corners."""
    data, pm = model(built, name)
    n = 48
    taus = np.resize(np.asarray([0.3, 8.0, 1.0, 40.0, 0.1, 3.0, 0.6, np.inf, 0.2], np.float32), n)
    stream, replay = pmjax.MeshStream(pm), Replay()
    for k, cams in enumerate((fly_through(data, n), hand_held(data, n, seed=41, cuts=(12, 13, 30)))):
        for i, (r, change) in enumerate(pmjax.path_mesh_changes(pm, cams, taus, stream=stream)):
            replay.apply(change)
            assert_same_mesh(replay, stream, r, (k, i))
    searches = stream._corner_searches()
    if searches is not None:
        assert searches["split"] > 0 and searches["had"] > 0, searches
        assert searches["around"] * 4 < searches["had"], searches
