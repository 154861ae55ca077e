"""Regression of the prediction on the coarse generic face (symmetric, no registration needed):
published soft-to-hard tissue ratios, no inverted element, the zero plan, mirror symmetry."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

generic_mesh = pytest.importorskip("generic_mesh")

from planner.plan import parse_plan  # noqa: E402
from planner.pipeline import solve_plan  # noqa: E402
from planner.report import inverted_elements  # noqa: E402

MIRROR = np.diag([-1.0, 1.0, 1.0, 1.0])


@pytest.fixture(scope="module")
def face():
    return generic_mesh.load("coarse")


def _plan(segments, **model):
    return parse_plan({"faceplan": 1, "segments": segments, "model": {"resolution": "coarse", **model}})


def _ap(face, pred, landmark):
    return pred.displacement[face.landmarks[landmark], 1]


@pytest.fixture(scope="module")
def le_fort(face):
    return solve_plan(face, _plan({"maxilla": {"translation": [0.0, 5.0, 0.0]}}))


@pytest.fixture(scope="module")
def genioplasty(face):
    return solve_plan(face, _plan({"chin": {"translation": [0.0, 5.0, 0.0]}}))


def test_le_fort_advancement_upper_lip_ratio(face, le_fort):
    # Published Ls : A-point ratios for a Le Fort I advancement lie in 0.5-0.9
    # (e.g. reviews of soft-to-hard tissue ratios in orthognathic surgery, Joss et al. 2010).
    ratio = _ap(face, le_fort, "Ls") / 5.0
    assert 0.5 <= ratio <= 0.9, ratio
    assert inverted_elements(le_fort.predicted_nodes, face.hexes).size == 0
    # The skull-attached soft tissue (infra-orbital rims) stays where it is: the tied nodes
    # move by exactly their bone's movement (0 for the skull, 5 mm for the maxilla).
    skull = face.node_sets["attach_skull"]
    assert np.abs(le_fort.displacement[skull]).max() < 1e-9
    maxilla = face.node_sets["attach_maxilla"]
    assert np.allclose(le_fort.displacement[maxilla], [0, 5, 0], atol=1e-9)


def test_genioplasty_pogonion_ratio(face, genioplasty):
    # Soft-tissue pogonion follows a genioplasty advancement by 0.8-1.0 (published range).
    ratio = _ap(face, genioplasty, "Pog") / 5.0
    assert 0.8 <= ratio <= 1.0, ratio
    assert inverted_elements(genioplasty.predicted_nodes, face.hexes).size == 0


def test_zero_plan_gives_zero_displacement(face):
    pred = solve_plan(face, _plan({"maxilla": {"translation": [0.0, 0.0, 0.0]},
                                   "mandible": {"matrix": np.eye(4).tolist()}}))
    # Nothing moves and no muscle is active: the rest state is the solution. 1e-9 mm is far
    # below the solver tolerance scale (it is round-off on coordinates of ~100 mm).
    assert np.abs(pred.displacement).max() < 1e-9


def test_mirrored_plan_gives_mirrored_prediction(face):
    """An asymmetric plan (maxilla to the patient's right, yawed) and its mirror image about
    x = 0 give mirror-image predictions on the symmetric generic face."""
    seg = {"maxilla": {"translation": [1.5, 3.0, 0.0],
                       "rotation": {"axis": [0, 0, 1], "angle_deg": 3.0, "center": [0.0, 60.0, -20.0]}}}
    a = solve_plan(face, _plan(seg))
    m = MIRROR @ a.plan.segments["maxilla"].matrix @ MIRROR
    b = solve_plan(face, _plan({"maxilla": {"matrix": m.tolist()}}))
    x = np.asarray(face.nodes, float)
    dist, mirror_of = cKDTree(x).query(x * [-1, 1, 1])
    assert dist.max() < 1e-6            # the generic mesh is symmetric to 1e-9 mm
    ua, ub = a.displacement, b.displacement
    # Both solves converge to the solver's residual tolerance; the mirrored problem is the same
    # discrete problem with permuted unknowns, so the predictions agree to far below 1 um of a
    # few-mm movement (1e-3 mm leaves room for the Newton tolerance).
    assert np.abs(ub[mirror_of] - ua * [-1, 1, 1]).max() < 1e-3
    assert np.abs(ua[:, 0]).max() > 0.5         # and the prediction is really asymmetric
