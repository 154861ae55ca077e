"""Parts of `faceplan compare` against independent answers: closest points (trimesh),
boundaries, areas, metrics on known samples, ICP on a known motion, landmarks on the analytic
profile."""
from pathlib import Path

import numpy as np
import pytest
import trimesh

from planner.compare import phantom
from planner.compare.alignment import apply, rotation_matrix, trimmed_icp
from planner.compare.distances import TriangleSurface, vertex_areas
from planner.compare.inputs import _merge_coincident
from planner.compare.landmarks import RULES, LandmarkLocator
from planner.compare.metrics import distance_metrics, weighted_percentile


def test_closest_points_match_trimesh():
    rng = np.random.default_rng(0)
    m = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    m.vertices = m.vertices * (1 + 0.1 * rng.uniform(-1, 1, (len(m.vertices), 1)))
    surf = TriangleSurface(m.vertices, m.faces)
    pts = rng.normal(size=(300, 3)) * 20.0
    cp = surf.closest(pts)
    ref_pt, ref_d, _ = trimesh.proximity.closest_point(m, pts)
    # exact geometry on both sides: agreement to round-off
    np.testing.assert_allclose(cp.distance, ref_d, atol=1e-9)
    np.testing.assert_allclose(cp.point, ref_pt, atol=1e-7)
    # inside the closed surface the signed distance is negative, outside positive
    inside = m.contains(pts)
    assert np.all(cp.signed[inside] < 0) and np.all(cp.signed[~inside] > 0)
    assert not cp.on_boundary.any()


def test_closest_points_are_exact_beside_large_triangles():
    # A decimated CT skin: broad facets beside fine ones. Above a 40 mm facet near a fine grid
    # the nearest vertices and centroids are the grid's; the closest triangle is the facet.
    # The comparison's surface must still find it (trimesh, every triangle a candidate, is
    # the reference).
    xs = np.arange(0.0, 10.01, 0.5)
    gx, gy = np.meshgrid(xs + 41.0, xs)
    n = len(xs)
    grid = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    i = np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :] + 3
    fine = np.vstack([np.column_stack([i.ravel(), i.ravel() + 1, i.ravel() + n]),
                      np.column_stack([i.ravel() + 1, i.ravel() + n + 1, i.ravel() + n])])
    v = np.vstack([[[0.0, 0.0, 0.0], [40.0, 0.0, 0.0], [0.0, 40.0, 0.0]], grid])
    f = np.vstack([[[0, 1, 2]], fine])
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(-5, 55, 400), rng.uniform(-5, 45, 400), rng.uniform(-1, 1, 400)])
    pts[:3] = [[35.0, 2.0, 0.1], [20.0, 12.0, 0.1], [30.0, 5.0, -0.3]]
    _, ref_d, _ = trimesh.proximity.closest_point(trimesh.Trimesh(v, f, process=False), pts)
    np.testing.assert_allclose(ref_d[:3], [0.1, 0.1, 0.3], atol=1e-12)
    # exact on both sides: the same distances to round-off
    np.testing.assert_allclose(TriangleSurface(v, f).closest(pts).distance, ref_d, atol=1e-9)


def test_boundary_flags_and_sign_on_a_flat_patch():
    xs = np.arange(0.0, 11.0)
    X, Y = np.meshgrid(xs, xs)
    v = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    i = np.arange(10)[:, None] * 11 + np.arange(10)[None, :]
    f = np.vstack([np.column_stack([i.ravel(), i.ravel() + 1, i.ravel() + 12]),
                   np.column_stack([i.ravel(), i.ravel() + 12, i.ravel() + 11])])
    surf = TriangleSurface(v, f)
    assert len(surf.boundary_edges) == 40
    inner = np.array([[3.3, 4.7, 0.5], [5.0, 5.0, -2.0], [9.9, 0.1, 1.0]])
    outer = np.array([[12.0, 5.0, 0.3], [-1.0, -1.0, 0.0], [5.0, 10.5, 2.0]])
    cp = surf.closest(np.vstack([inner, outer]))
    np.testing.assert_allclose(cp.signed[:3], inner[:, 2], atol=1e-12)
    assert not cp.on_boundary[:3].any() and cp.on_boundary[3:].all()
    assert cp.beyond_boundary[3:].all()
    # right above an edge (offset along the normal) is on the boundary but not beyond it
    edge = surf.closest(np.array([[10.0, 5.0, 0.7]]))
    assert edge.on_boundary[0] and not edge.beyond_boundary[0]
    assert vertex_areas(v, f).sum() == pytest.approx(100.0)


def test_metrics_on_known_samples():
    d = np.array([-3.0, -1.0, 0.0, 1.0, 3.0])
    m = distance_metrics(d)
    assert m["mean_abs_mm"] == pytest.approx(1.6)
    assert m["rms_mm"] == pytest.approx(2.0)
    assert m["within_2mm_pct"] == pytest.approx(60.0)
    assert m["n_points"] == 5
    # weights act as repetitions: weight 2 on a value equals listing it twice
    w = np.array([2.0, 1.0, 1.0, 1.0, 1.0])
    rep = np.array([-3.0, -3.0, -1.0, 0.0, 1.0, 3.0])
    assert distance_metrics(d, w)["rms_mm"] == pytest.approx(distance_metrics(rep)["rms_mm"])
    assert weighted_percentile(np.abs(d), w, 90) == pytest.approx(np.percentile(np.abs(rep), 90, method="hazen"))
    # percentiles of a large normal sample: |N(0,1)| has p90 = 1.6449, p95 = 1.9600
    z = np.random.default_rng(1).normal(size=200000)
    m = distance_metrics(z)
    assert m["p90_mm"] == pytest.approx(1.6449, abs=0.02) and m["p95_mm"] == pytest.approx(1.96, abs=0.02)
    assert distance_metrics(np.array([np.nan]))["n_points"] == 0


def test_merge_coincident_vertices_of_a_triangle_soup():
    m = trimesh.creation.icosphere(subdivisions=1, radius=40.0)
    soup_v = m.vertices[m.faces].reshape(-1, 3)
    soup_f = np.arange(len(soup_v)).reshape(-1, 3)
    v, f = _merge_coincident(soup_v, soup_f)
    assert len(v) == len(m.vertices)
    assert len(TriangleSurface(v, f).boundary_edges) == 0
    np.testing.assert_allclose(v[f], soup_v[soup_f])


@pytest.fixture(scope="module")
def face():
    return phantom.face_phantom(2.0)


def test_icp_recovers_a_known_motion(face):
    surf = TriangleSurface(face.vertices, face.faces)
    T = np.eye(4)
    T[:3, :3] = rotation_matrix(np.radians([4.0, -3.0, 6.0]))
    T[:3, 3] = [3.0, -6.0, 4.0]
    moved = apply(T, face.vertices)
    unop = np.isin(face.region, [face.region_names.index(n) for n in face.unoperated_regions])
    allowed = np.all(unop[face.faces], axis=1)
    coarse = trimmed_icp(moved, surf, None, keep=0.6, gate=25.0)
    fine = trimmed_icp(moved, surf, allowed, init=coarse.matrix, keep=0.9, gate=5.0)
    assert fine.converged
    # same vertices on both sides: the exact inverse, to the convergence tolerance
    np.testing.assert_allclose(apply(fine.matrix, moved), face.vertices, atol=1e-3)
    assert fine.residual_rms_mm < 1e-3


def test_profile_landmarks_match_the_analytic_profile(face):
    # dense analytic mid-sagittal profile (0.01 degree steps) -> the exact extremes
    el = np.radians(np.arange(-78.0, 58.0, 0.01))
    prof, _ = phantom._surface(phantom._directions(np.zeros_like(el), el))
    locator = LandmarkLocator(phantom.face_phantom(0.8).vertices)
    for name, sel, key in (("Prn", prof[:, 2] > 0, lambda p: p[:, 1]),
                           ("Pog", (prof[:, 2] < -60) & (prof[:, 2] > -85), lambda p: p[:, 1]),
                           ("Li", (prof[:, 2] < -33) & (prof[:, 2] > -50), lambda p: p[:, 1]),
                           ("Me", (prof[:, 2] < -85) & (prof[:, 1] > 60),
                            lambda p: p @ np.array(RULES["Me"][1]))):
        exact = prof[sel][np.argmax(key(prof[sel]))]
        found = locator.locate(name, face.landmarks[name])
        assert found is not None, name
        # the height at the extreme is flat to first order, so it agrees better (0.05 mm)
        # than the position along the profile (0.5 mm on a 0.8 mm triangulation)
        assert abs(key(found[None])[0] - key(exact[None])[0]) < 0.05, name
        assert np.linalg.norm(found - exact) < 0.5, name
