"""Input cleaning: every kind of bad input is cleaned with a report or refused clearly."""

import numpy as np
import pytest

import pmjax
from pmjax import MeshError, clean_mesh

SQUARE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


def test_clean_mesh_keeps_a_good_mesh():
    v, f, kept, report = clean_mesh(SQUARE_V, SQUARE_F)
    assert np.array_equal(v, SQUARE_V) and np.array_equal(f, SQUARE_F)
    assert report.messages() == []
    assert f.dtype == np.int32 and v.dtype == np.float64


def test_nan_and_inf_vertices_are_removed_with_their_faces():
    v = np.vstack([SQUARE_V, [[np.nan, 0, 0]], [[0, np.inf, 0]]])
    f = np.vstack([SQUARE_F, [[0, 1, 4]], [[1, 2, 5]]])
    cv, cf, kept, report = clean_mesh(v, f)
    assert len(cf) == 2 and np.all(np.isfinite(cv))
    assert report.nonfinite_vertices == 2 and report.faces_on_nonfinite_vertices == 2
    assert set(kept) == {0, 1, 2, 3}


def test_out_of_range_degenerate_duplicate_and_unreferenced():
    v = np.vstack([SQUARE_V, [[5, 5, 5]], [[2, 0, 0]]])  # 4 unreferenced, 5 collinear
    f = np.array([[0, 1, 2], [0, 2, 3], [2, 1, 0], [0, 1, 9], [-1, 0, 1], [1, 1, 2], [0, 1, 5]])
    cv, cf, kept, report = clean_mesh(v, f)
    assert len(cf) == 2
    assert report.out_of_range_faces == 2
    assert report.duplicate_faces == 1  # [2, 1, 0] is [0, 1, 2] reversed
    assert report.degenerate_faces == 2  # repeated corner; zero area (0, 1, 5 collinear)
    assert report.unreferenced_vertices == 2
    assert len(report.messages()) == 4


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6])
def test_a_stray_point_far_away_does_not_make_small_faces_degenerate(scale):
    """The zero-area threshold follows the faces' extent, not that of
    points no face uses: a 50 x 50 grid with one unreferenced vertex a
    million grid sizes away keeps every face, at any scale."""
    n = 50
    x, y = np.meshgrid(np.arange(n + 1), np.arange(n + 1))
    grid = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1) * scale
    ids = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    a, b, c, d = ids[:-1, :-1].ravel(), ids[:-1, 1:].ravel(), ids[1:, 1:].ravel(), ids[1:, :-1].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    v = np.vstack([grid, [[1e6 * n * scale, 0, 0]]])
    _, cf, _, report = clean_mesh(v, f)
    assert len(cf) == len(f) and report.degenerate_faces == 0 and report.unreferenced_vertices == 1


def test_single_triangle_is_kept():
    v, f, _, _ = clean_mesh(SQUARE_V[:3], SQUARE_F[:1])
    assert f.shape == (1, 3)


@pytest.mark.parametrize(
    "vertices, faces, message",
    [
        (SQUARE_V, np.zeros((0, 3), int), "no faces"),
        (SQUARE_V[:, :2], SQUARE_F, "shape (V, 3)"),
        (SQUARE_V, np.array([[0, 1, 2, 3]]), "triangles"),
        (SQUARE_V, SQUARE_F.astype(float), "integers"),
        (np.full((3, 3), np.nan), np.array([[0, 1, 2]]), "no valid face"),
        (SQUARE_V, np.array([[0, 0, 1]]), "no valid face"),
    ],
)
def test_unusable_meshes_are_refused_with_a_specific_error(vertices, faces, message):
    with pytest.raises(MeshError, match=message.replace("(", r"\(").replace(")", r"\)")) as err:
        clean_mesh(vertices, faces, source="in.ply")
    assert "in.ply" in str(err.value)


def test_read_errors_name_the_file(tmp_path):
    with pytest.raises(MeshError) as err:
        pmjax.read_mesh(tmp_path / "missing.ply")
    assert str(err.value) == f"{tmp_path}/missing.ply: no such file"
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    with pytest.raises(MeshError) as err:
        pmjax.load_clean_mesh(junk)
    assert str(err.value) == f"{junk}: PLY header has no end_header line"
    with pytest.raises(MeshError) as err:
        pmjax.read_mesh(tmp_path)
    assert str(err.value) == f"{tmp_path}: is a folder; give a mesh file"


def test_default_model_ships_in_the_package():
    v, f, _, report = pmjax.load_clean_mesh(pmjax.default_model_path())
    assert len(f) == 5856 and len(v) == 2930
