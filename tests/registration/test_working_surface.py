"""Large surfaces: the row hash, the simplified working surface
and a registration run on one (judged on the full-resolution skin)."""
import numpy as np
import pytest
import trimesh

from registration import surface as rs
from registration.surface import TargetSurface, unique_rows, working_surface


def test_unique_rows_matches_the_row_sort():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(500, 3))
    a = base[rng.integers(0, 500, 4000)]
    a[::7, 0] = -0.0           # -0.0 and 0.0 have other bits: distinct unless the caller folds them
    first, inverse = unique_rows(a)
    assert np.array_equal(a[first][inverse], a)
    assert len(first) == len(np.unique(a, axis=0))


def test_unique_rows_survives_hash_collisions(monkeypatch):
    # every row hashed alike: the verification must notice and fall back to the exact sort
    monkeypatch.setattr(rs, "_mix64", lambda x: np.zeros_like(x))
    a = np.array([[1, 2, 3], [4, 5, 6], [1, 2, 3], [7, 8, 9]], dtype=np.int64)
    first, inverse = unique_rows(a)
    assert np.array_equal(a[first][inverse], a) and len(first) == 3


def test_working_surface_stays_on_the_surface():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=60.0)   # 20,480 triangles
    v, f = working_surface(sphere.vertices, sphere.faces, max_faces=2000)
    assert 1800 <= len(f) <= 2000
    # the closed shape stays closed (edge collapse keeps the topology)
    assert trimesh.Trimesh(v, f, process=False).is_watertight
    # bound: a triangle of circumradius rho inscribed in the sphere leaves a cap of depth
    # R - sqrt(R^2 - rho^2) over it; quadric placement keeps the vertices on the sphere to
    # within a small part of that, hence a margin of 50 % on the largest cap
    tri = v[f]
    a = np.linalg.norm(tri[:, 1] - tri[:, 2], axis=1)
    b = np.linalg.norm(tri[:, 2] - tri[:, 0], axis=1)
    c = np.linalg.norm(tri[:, 0] - tri[:, 1], axis=1)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rho = a * b * c / (4 * area)
    cap = float(np.max(60.0 - np.sqrt(np.maximum(60.0 ** 2 - rho ** 2, 0.0))))
    dev = rs.surface_deviation(sphere.vertices, TargetSurface(v, f))
    assert dev["max_mm"] <= 1.5 * cap, (dev, cap)
    # up to twice the budget the surface is returned as it is
    v2, f2 = working_surface(sphere.vertices, sphere.faces, max_faces=len(sphere.faces) // 2)
    assert v2 is sphere.vertices or np.array_equal(v2, sphere.vertices)
    assert np.array_equal(f2, sphere.faces)


generic_mesh = pytest.importorskip("generic_mesh")
synthetic = pytest.importorskip("facemodel.synthetic")


def test_registration_on_a_working_surface_fits_the_full_skin(generic, tmp_path):
    """The synthetic head's skin (82k triangles) registered through a working surface of 20k
    (the bones, under twice that, as given):
    the fit measured on the full skin meets the registration's own targets (mean < 0.3 mm, p95
    < 1.0 mm: tests/registration/test_mesh_match.py), and exceeds the fit on the working
    surface by no more than the working surface's own deviation from the full one (the nodes
    are placed on the working surface, which lies that close to the full one)."""
    from registration import mesh_match_and_repair
    from registration.quality import min_scaled_jacobian

    head = synthetic.synthetic_head(2)
    patient, report = mesh_match_and_repair(generic, head.skin, head.bones, head.landmarks,
                                            cache_dir=tmp_path, working_faces=20_000)
    work = report["working_surfaces"]["skin"]
    assert work["triangles_given"] == len(head.skin.faces) and work["triangles_working"] <= 20_000
    full, fit = report["fit"]["skin_full_resolution"], report["fit"]["skin"]
    assert full["mean_mm"] < 0.3 and full["p95_mm"] < 1.0, full
    assert full["mean_mm"] <= fit["mean_mm"] + work["deviation"]["max_mm"] + 1e-6, (full, fit, work)
    assert min_scaled_jacobian(patient.nodes, patient.hexes).min() >= 0.2
    # the landmark nodes end on the given landmarks as without simplification (1.5 mm: the
    # registration's landmark target)
    for name, node in generic.landmarks.items():
        assert np.linalg.norm(patient.nodes[node] - np.asarray(head.landmarks[name])) < 1.5, name
