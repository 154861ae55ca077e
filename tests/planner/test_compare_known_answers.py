"""`faceplan compare` known answers on the analytic face phantom (planner.compare.phantom).

The prediction is the phantom triangulated at 1.5 mm, the "post-op scan" the same analytic
surface re-triangulated independently (1.1 mm, jittered, shifted grid), so the two differ only
by the chord error h^2 kappa / 8 (< 0.01 mm on average here) before any motion, offset or noise
is applied.
"""
from pathlib import Path

import numpy as np
import pytest

from planner.compare.alignment import apply, rotation_matrix
from planner.compare.comparison import compare_surfaces
from planner.compare.distances import TriangleSurface
from planner.compare.inputs import Prediction, Surface
from planner.compare.phantom import face_phantom

NOT_NEAR_CHIN = ("forehead", "nasal_bridge", "infraorbital_left", "infraorbital_right", "nose",
                 "upper_lip")


def _prediction(ph, vertices=None):
    return Prediction(ph.vertices if vertices is None else vertices, ph.faces, ph.region,
                      ph.region_names, ph.unoperated_regions,
                      {k: np.asarray(v) for k, v in ph.landmarks.items()}, Path("prediction"))


def _rigid(seed, angle_deg=5.0, shift_mm=5.0):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    T = np.eye(4)
    T[:3, :3] = rotation_matrix(axis / np.linalg.norm(axis) * np.radians(angle_deg))
    t = rng.normal(size=3)
    T[:3, 3] = t / np.linalg.norm(t) * shift_mm
    return T


@pytest.fixture(scope="module")
def phantoms():
    return face_phantom(1.5), face_phantom(1.1, jitter=0.6, seed=3, offset=0.37)


@pytest.fixture(scope="module")
def chin_offset(phantoms):
    """Prediction with the chin moved 1.0 mm outwards along the normals; scan = true face."""
    pred, scan = phantoms
    chin = pred.region_names.index("chin")
    normals = TriangleSurface(pred.vertices, pred.faces).vertex_normals
    moved = pred.vertices + 1.0 * (pred.region == chin)[:, None] * normals
    T = _rigid(11)
    result = compare_surfaces(_prediction(pred, moved), Surface(apply(T, scan.vertices), scan.faces, Path("scan")))
    return result, T


def test_rigidly_moved_retriangulated_prediction_gives_zero(phantoms):
    pred, scan = phantoms
    T = _rigid(7)
    result = compare_surfaces(_prediction(pred), Surface(apply(T, scan.vertices), scan.faces, Path("scan")))
    # issue 7: < 0.05 mm mean error; the chord error alone is ~0.01 mm
    assert result.metrics["overall"]["mean_abs_mm"] < 0.05
    assert result.metrics["overall"]["within_2mm_pct"] == pytest.approx(100.0)
    for name, m in result.metrics["regions"].items():
        assert m["n_points"] > 50, name
        assert m["mean_abs_mm"] < 0.05, name
    assert result.alignment.residual_rms_mm < 0.05
    # the recovered motion undoes the applied one (points moved back to within 0.05 mm)
    back = apply(result.alignment.matrix @ T, scan.vertices)
    assert np.max(np.linalg.norm(back - scan.vertices, axis=1)) < 0.05
    # the reverse direction agrees
    assert result.metrics_reverse["overall"]["mean_abs_mm"] < 0.05
    # every landmark is found, and with the same operator on both surfaces it agrees to 0.15 mm
    # (sub-vertex quadratic refinement on 1.1 and 1.5 mm triangulations)
    lm = result.metrics["landmarks"]
    assert set(lm) == {"Sn", "Ls", "Li", "Pog", "Me", "ChL", "ChR", "Prn"}
    for name, v in lm.items():
        assert v["error_mm"] < 0.15, name


def test_one_mm_offset_in_one_region(chin_offset):
    result, _ = chin_offset
    chin = result.metrics["regions"]["chin"]
    # issue 7: 1.0 +- 0.05 mm there (the band of triangles straddling the region border,
    # about one edge wide, is the only place with less)
    assert chin["mean_abs_mm"] == pytest.approx(1.0, abs=0.05)
    # the real chin lies 1 mm inside the predicted one: negative signed distance
    assert chin["mean_signed_mm"] == pytest.approx(-1.0, abs=0.05)
    assert chin["p90_mm"] == pytest.approx(1.0, abs=0.03)
    for name in NOT_NEAR_CHIN:
        assert result.metrics["regions"][name]["mean_abs_mm"] < 0.05, name
    # the superimposition ignores the operated chin
    assert result.alignment.residual_rms_mm < 0.05
    # soft-tissue pogonion moved 1 mm along the (mostly anterior) chin normal
    assert result.metrics["landmarks"]["Pog"]["error_mm"] == pytest.approx(1.0, abs=0.1)
    assert result.metrics["landmarks"]["Prn"]["error_mm"] < 0.15


def test_partial_front_scan_gives_same_regional_figures(phantoms, chin_offset):
    full, T = chin_offset
    pred, scan = phantoms
    chin = pred.region_names.index("chin")
    normals = TriangleSurface(pred.vertices, pred.faces).vertex_normals
    moved = pred.vertices + 1.0 * (pred.region == chin)[:, None] * normals
    # a 3D photograph sees only the front: keep triangles facing the camera within 60 degrees
    # and in front of y = 40 mm, and punch a hole in the cheek
    v = scan.vertices
    tri_n = np.cross(v[scan.faces[:, 1]] - v[scan.faces[:, 0]], v[scan.faces[:, 2]] - v[scan.faces[:, 0]])
    tri_n /= np.linalg.norm(tri_n, axis=1, keepdims=True)
    c = v[scan.faces].mean(axis=1)
    hole = np.linalg.norm(c - [45.0, 70.0, -20.0], axis=1) < 8.0
    keep = (tri_n[:, 1] > 0.5) & (c[:, 1] > 40.0) & ~hole
    faces = scan.faces[keep]
    used = np.unique(faces)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    partial = compare_surfaces(_prediction(pred, moved),
                               Surface(apply(T, v[used]), remap[faces], Path("partial")))
    assert partial.metrics["overall"]["n_points"] < 0.8 * full.metrics["overall"]["n_points"]
    for name in ("nose", "upper_lip", "lower_lip", "chin"):
        a, b = partial.metrics["regions"][name], full.metrics["regions"][name]
        assert b["n_points"] > 100
        # same surface, same alignment up to ICP convergence (~1e-3 mm): regions covered
        # completely agree to 0.02 mm; the chin loses its underside, which is also 1 mm off
        assert a["mean_abs_mm"] == pytest.approx(b["mean_abs_mm"], abs=0.02), name


def test_noise_is_reported_as_its_mean_absolute_value(phantoms):
    pred, scan = phantoms
    rng = np.random.default_rng(5)
    sigma = 0.2
    noisy = scan.vertices + rng.normal(scale=sigma, size=scan.vertices.shape)
    result = compare_surfaces(_prediction(pred), Surface(apply(_rigid(3), noisy), scan.faces, Path("noisy")))
    # E|N(0, sigma)| = sigma sqrt(2/pi) = 0.1596 mm; the normal component of isotropic noise
    # has the same law. Sampling error with ~4e4 points is < 0.001 mm; the tolerance 0.012 mm
    # covers the area weighting of a noisy mesh and the chord error (< 0.01 mm).
    assert result.metrics["overall"]["mean_abs_mm"] == pytest.approx(sigma * np.sqrt(2 / np.pi), abs=0.012)
    assert result.metrics["overall"]["rms_mm"] == pytest.approx(sigma, abs=0.015)
    # the ICP residual of the trimmed inliers is the noise floor: below sigma (trimmed), above 0
    assert 0.05 < result.alignment.residual_rms_mm < sigma


def test_reused_alignment_gives_the_same_figures(phantoms, chin_offset):
    # diagnosis compares many candidate predictions with one scan: the superimposition found
    # once can be passed back in, and then the figures are those of a full run
    full, T = chin_offset
    pred, scan = phantoms
    chin = pred.region_names.index("chin")
    normals = TriangleSurface(pred.vertices, pred.faces).vertex_normals
    moved = pred.vertices + 1.0 * (pred.region == chin)[:, None] * normals
    again = compare_surfaces(_prediction(pred, moved), Surface(apply(T, scan.vertices), scan.faces, Path("scan")),
                             alignment=full.alignment, landmarks=False)
    for name, m in full.metrics["regions"].items():
        assert again.metrics["regions"][name]["mean_abs_mm"] == pytest.approx(m["mean_abs_mm"], abs=1e-12)
    assert again.metrics["landmarks"] == {}
