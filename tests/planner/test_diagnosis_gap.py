"""The gap the diagnosis measures: the scan's pose and the surface the prediction is carried on.

No forward solve: the generic coarse face at rest stands for the baseline prediction, and a
known displacement field for an effect. Noise-free scans (`synthetic.scan_like` with no noise
lies on the subdivided surface itself), so what is left of the gap is the method's error.
"""
import numpy as np
import pytest

from planner.compare.inputs import Surface
from planner.diagnosis.forward import patient_surface, prepare_case
from planner.diagnosis.gap import measure_gap
from planner.diagnosis.synthetic import scan_like


@pytest.fixture(scope="module")
def patient():
    import generic_mesh
    from planner.plan import parse_plan

    plan = parse_plan({"faceplan": 1, "segments": {"maxilla": {"translation": [0.0, 4.0, 0.0]}},
                       "model": {"resolution": "coarse", "contact": False}})
    return prepare_case("generic", generic_mesh.load("coarse"), plan, None)


def _rest(case):
    return np.asarray(case.model.nodes, float)[case.skin_ids]


def _sag(x, amplitude=0.8):
    """A smooth field over the whole face, unoperated regions included (a posture-like sag that
    grows downwards and sideways): 0.8 mm at most."""
    c = x.mean(axis=0)
    s = 0.5 * (1.0 + np.tanh((c[2] - x[:, 2]) / 25.0)) * (0.5 + 0.5 * np.tanh(np.abs(x[:, 0] - c[0]) / 30.0))
    return amplitude * s[:, None] * np.array([0.0, -0.3, -1.0])


def test_pose_is_refitted_for_a_prediction_that_moves_the_unoperated_regions(patient):
    """The scan of the face moved by a field that also moves the unoperated regions, with a
    rigid offset of up to 2 mm / 2 deg: superimposed on the baseline (the rest face), whose
    unoperated regions do not move. The prediction with the exact field must then have no gap:
    the pose is re-fitted on its unoperated regions (linearised, so the residual is second
    order in the pose change, rotation^2 x lever arm ~ (0.01 rad)^2 x 100 mm = 0.01 mm; 0.03 mm
    allowed), while keeping the baseline's pose leaves a tilt of the order of the field on the
    unoperated regions (> 0.05 mm RMS)."""
    from planner.compare.distances import TriangleSurface

    rest = _rest(patient)
    moved = rest + _sag(rest)
    v, f = scan_like(moved, patient.skin_faces, seed=11, noise_mm=0.0)
    gap = measure_gap(patient, rest, Surface(v, f, __import__("pathlib").Path("sag.stl")))
    r = gap.distances(moved)
    assert gap.rms(r) < 0.03
    fixed = TriangleSurface(moved, gap.faces).closest(gap.points).signed
    assert gap.rms(fixed) > 0.05 and gap.rms(fixed) > 3.0 * gap.rms(r)


def test_patient_surface_carries_linear_fields_exactly(patient):
    """Points on the model's skin triangles take the model's displacement by barycentric
    interpolation: a linear field u = A x + b is reproduced to round-off, and a translation
    moves every vertex by itself (the weights sum to one)."""
    rest = _rest(patient)
    faces = np.asarray(patient.skin_faces)
    rng = np.random.default_rng(0)
    tri = rng.choice(len(faces), 400)
    w = rng.dirichlet(np.ones(3), 400)
    pts = np.einsum("mj,mjk->mk", w, rest[faces[tri]])
    # a triangulation of those points is not needed for the mapping: reuse the model's faces
    # over the rest positions followed by the sampled points (faces index the first block)
    V = np.concatenate([rest, pts])
    surf = patient_surface(rest, faces, np.zeros(len(rest), int), V, faces)
    assert surf is not None
    A = np.array([[0.01, 0.02, 0.0], [0.0, -0.01, 0.03], [0.02, 0.0, 0.01]])
    b = np.array([0.5, -1.0, 0.25])
    got = surf.carry(rest + rest @ A.T + b)
    assert np.allclose(got, surf.vertices + surf.vertices @ A.T + b, atol=1e-9)


def test_prediction_on_the_patients_skin_removes_the_pre_op_misfit(patient):
    """The patient's pre-op skin differs from the registered model's by a smooth 0.3 mm bump
    along the normals (a registration residual); the post-op face is that skin moved by the
    field. Carried on the patient's skin, the exact prediction has no gap (< 0.03 mm RMS, the
    closest-point interpolation of a smooth field); on the model's own skin the bump stays in
    the gap (> 0.1 mm RMS), and no effect could remove it."""
    import dataclasses

    import trimesh

    from planner.compare.distances import TriangleSurface
    from facemodel.synthetic import displaced_surface

    rest = _rest(patient)
    faces = np.asarray(patient.skin_faces)
    mesh = trimesh.Trimesh(rest, faces, process=False)
    V, F = trimesh.remesh.subdivide(mesh.vertices, mesh.faces)
    n = trimesh.Trimesh(V, F, process=False).vertex_normals
    c = V.mean(axis=0)
    bump = 0.3 * np.sin((V[:, 0] - c[0]) / 12.0) * np.cos((V[:, 2] - c[2]) / 15.0)
    Vp = V + bump[:, None] * n
    case = dataclasses.replace(patient, surface=patient_surface(rest, faces, patient.region, Vp, F))
    field = _sag(rest)
    post = displaced_surface(case.surface.vertices, rest, faces, field)
    v, f = scan_like(post, case.surface.faces, seed=12, noise_mm=0.0, edge_mm=3.0)
    gap = measure_gap(case, rest, Surface(v, f, __import__("pathlib").Path("patient.stl")))
    assert gap.rms(gap.distances(rest + field)) < 0.03
    on_model = TriangleSurface(rest + field, faces).closest(gap.points).signed
    ok = np.isfinite(on_model)
    assert np.sqrt(np.average(on_model[ok] ** 2, weights=gap.weights[ok])) > 0.1
