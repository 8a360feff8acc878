"""Exact point-to-triangle and surface distances against brute force."""

import numpy as np

import pmjax


def brute_point_triangle(p, a, b, c, n=400):
    # Dense barycentric sampling: an upper bound within the grid spacing.
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    pts = a + u[:, None] * (b - a) + v[:, None] * (c - a)
    return np.linalg.norm(pts - p, axis=1).min()


def test_point_triangle_distance_matches_brute_force():
    rng = np.random.default_rng(1)
    tris = rng.normal(size=(60, 3, 3))
    pts = rng.normal(size=(60, 3)) * 2
    d = pmjax.point_triangle_distance(pts, tris[:, 0], tris[:, 1], tris[:, 2])
    for i in range(60):
        ref = brute_point_triangle(pts[i], *tris[i])
        assert d[i] <= ref + 1e-9 and d[i] >= ref - 0.02, i
    # Exact known values: above the interior, beyond a vertex, a degenerate triangle.
    a, b, c = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])
    assert np.isclose(pmjax.point_triangle_distance(np.array([[0.2, 0.2, 3.0]]), a, b, c)[0], 3.0)
    assert np.isclose(pmjax.point_triangle_distance(np.array([[-3.0, -4.0, 0]]), a, b, c)[0], 5.0)
    assert np.isclose(pmjax.point_triangle_distance(np.array([[0.5, 1.0, 0]]), a, b, a)[0], 1.0)


def test_distance_to_surface_equals_min_over_all_triangles(data_path):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("motor.ply"))
    rng = np.random.default_rng(2)
    pts = v[rng.integers(0, len(v), 300)] + rng.normal(scale=0.05, size=(300, 3))
    d = pmjax.distance_to_surface(pts, v, f, chunk=128)
    tri = v[f]
    brute = np.array(
        [pmjax.point_triangle_distance(np.repeat(p[None], len(f), 0), tri[:, 0], tri[:, 1], tri[:, 2]).min() for p in pts]
    )
    assert np.allclose(d, brute, rtol=0, atol=1e-12)


def test_surface_distance_of_a_mesh_to_itself_is_zero_and_grows_with_offset(data_path):
    v, f, _, _ = pmjax.load_clean_mesh(data_path("cow.ply"))
    same = pmjax.surface_distance((v, f), (v, f), n_samples=5000)
    assert same["hausdorff"] < 1e-9
    moved = pmjax.surface_distance((v, f), (v + [0, 0.01, 0], f), n_samples=5000)
    assert 0 < moved["rms"] <= 0.01 + 1e-9
