"""Closest points against brute force; boundary flags; orientation of flipped surfaces."""
import numpy as np
import pytest

from registration.surface import TargetSurface
from shell import ellipsoid_radius, surface_grid


def _brute_force(points, v, f):
    from solver.geometry import _closest_over_candidates
    cand = np.tile(np.arange(len(f)), (len(points), 1))
    return _closest_over_candidates(points, v, f, cand)


def test_closest_points_equal_brute_force():
    v, f = surface_grid(ellipsoid_radius(80, 100, 110), n_theta=30, n_phi=20)
    s = TargetSurface(v, f)
    rng = np.random.default_rng(1)
    p = s.sample(300, seed=2) + rng.normal(0, 6.0, (300, 3))
    got = s.closest(p)
    _, _, _, d = _brute_force(p, s.vertices, s.faces)
    # same exact projection routine on the same triangles: equal to round-off
    assert np.allclose(got.distance, d, atol=1e-9)


def test_points_on_surface_have_zero_distance_and_border_is_flagged():
    v, f = surface_grid(ellipsoid_radius(80, 100, 110), n_theta=30, n_phi=20)
    s = TargetSurface(v, f)
    on = s.sample(200, seed=0)
    c = s.closest(on)
    assert c.distance.max() < 1e-9 and not c.on_boundary.any()
    # far beyond the top border (phi_max = 65 deg): the closest point lies on the border
    above = np.array([[0.0, 20.0, 400.0], [0.0, -300.0, 0.0]])
    assert s.closest(above).on_boundary.all()


def test_flipped_and_mixed_winding_gives_same_outward_normals():
    v, f = surface_grid(ellipsoid_radius(80, 100, 110), n_theta=30, n_phi=20)
    a = TargetSurface(v, f)
    b = TargetSurface(v, f[:, ::-1])
    mixed = f.copy()
    mixed[::3] = mixed[::3, ::-1]
    c = TargetSurface(v, mixed)
    centre_dir = a.centroids / np.linalg.norm(a.centroids, axis=1)[:, None]
    assert np.mean(np.einsum("ij,ij->i", a.face_normals, centre_dir) > 0) > 0.99
    assert np.allclose(a.face_normals, b.face_normals) and np.allclose(a.face_normals, c.face_normals)


def test_duplicated_stl_vertices_are_merged():
    v, f = surface_grid(ellipsoid_radius(80, 100, 110), n_theta=10, n_phi=8)
    soup_v = v[f].reshape(-1, 3)
    soup_f = np.arange(len(soup_v)).reshape(-1, 3)
    s = TargetSurface(soup_v, soup_f)
    assert len(s.vertices) == len(v)
    assert s.face_edge_boundary.sum() == TargetSurface(v, f).face_edge_boundary.sum()


def test_transformed_copy_answers_as_a_rebuilt_surface():
    """A similarity maps the surface without cleaning and orienting it anew: closest points,
    distances, normals and border flags of the mapped copy equal those of a surface built from
    the mapped vertices (to 1e-9 mm: the same projections, the vertices rounded differently)."""
    from scipy.spatial.transform import Rotation

    v, f = surface_grid(ellipsoid_radius(80, 100, 110), n_theta=30, n_phi=20)
    s = TargetSurface(v, f)
    r = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    t = np.array([4.0, -20.0, 7.5])
    moved, rebuilt = s.transformed(1.13, r, t), TargetSurface(1.13 * v @ r.T + t, f)
    q = np.random.default_rng(2).normal(scale=90.0, size=(300, 3)) + t
    a, b = moved.closest(q), rebuilt.closest(q)
    np.testing.assert_allclose(a.points, b.points, atol=1e-9)
    np.testing.assert_allclose(a.distance, b.distance, atol=1e-9)
    np.testing.assert_allclose(a.normal, b.normal, atol=1e-9)
    np.testing.assert_array_equal(a.on_boundary, b.on_boundary)
    assert moved.area == pytest.approx(rebuilt.area, rel=1e-12)
