"""No silent bad state: a state the solver did not finish is never a prediction.

`solve_plan` refuses an unconverged or partial-load result, NaN displacements and inverted
elements (SolveError, exit 3); `write_outputs` re-checks the prediction it is given and writes
nothing for such a state. The solver itself raises rather than returns on failure
(tests/solver/test_robustness.py); here the face-level guards are tested with the simulation
replaced by stand-ins returning each bad state.
"""
import types

import numpy as np
import pytest

import planner.pipeline as pipeline
from planner.errors import SolveError
from planner.pipeline import Prediction, Progress, check_solution, solve_plan, write_outputs
from planner.plan import load_plan


@pytest.fixture(scope="module")
def model():
    generic_mesh = pytest.importorskip("generic_mesh")
    return generic_mesh.load("coarse")


@pytest.fixture
def plan(tmp_path):
    f = tmp_path / "plan.yaml"
    f.write_text("faceplan: 1\nsegments:\n  maxilla: {translation: [0, 3, 0]}\nmodel: {contact: false}\n")
    return load_plan(f)


def _result(model, u, converged=True, load=1.0):
    return types.SimpleNamespace(displacement=u, cauchy=None, converged=converged, load=load,
                                 iterations=5, steps=2, time_s=0.1, info={})


def _inverting(model):
    """A displacement that pushes one node of element 0 through the opposite face."""
    x = np.asarray(model.nodes, float)
    hx = np.asarray(model.hexes[0])
    u = np.zeros_like(x)
    u[hx[0]] = 3.0 * (x[hx[6]] - x[hx[0]])
    return u


@pytest.mark.parametrize("bad", ["unconverged", "partial", "nan", "inverted"])
def test_solve_plan_refuses_bad_states(bad, model, plan, monkeypatch):
    zero = np.zeros((len(model.nodes), 3))
    result = {"unconverged": lambda: _result(model, zero, converged=False),
              "partial": lambda: _result(model, zero, load=0.6),
              "nan": lambda: _result(model, np.full_like(zero, np.nan)),
              "inverted": lambda: _result(model, _inverting(model))}[bad]()
    monkeypatch.setattr(pipeline, "_call_simulate", lambda *a, **k: result)
    with pytest.raises(SolveError):
        solve_plan(model, plan, None, progress=Progress(echo=False))


@pytest.mark.parametrize("bad", ["unconverged", "nan_u", "nan_stress", "inverted"])
def test_write_outputs_writes_nothing_for_a_bad_state(bad, model, plan, tmp_path):
    n, m = len(model.nodes), len(model.hexes)
    u, stress, stats = np.zeros((n, 3)), np.zeros((m, 3, 3)), {"converged": True, "load": 1.0}
    if bad == "unconverged":
        stats = {"converged": False, "load": 0.4}
    elif bad == "nan_u":
        u[7, 1] = np.nan
    elif bad == "nan_stress":
        stress[3] = np.inf
    else:
        u = _inverting(model)
    pred = Prediction(model, plan, u, stress, stats)
    with pytest.raises(SolveError, match="nothing written"):
        write_outputs(pred, tmp_path / "out", Progress(echo=False), {"case": None}, render=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.yaml"]


def test_a_finished_state_passes(model, plan):
    n, m = len(model.nodes), len(model.hexes)
    check_solution(Prediction(model, plan, np.zeros((n, 3)), np.zeros((m, 3, 3)),
                              {"converged": True, "load": 1.0}))


def test_a_contact_left_unmet_is_a_warning_not_a_silent_prediction(model, plan, monkeypatch):
    """A converged state whose contact the augmentations left deeper than twice its tolerance
    is still a prediction (converged, full load, no inverted element), but the user is told:
    the progress log names the contact, its depth and the tolerance."""
    zero = np.zeros((len(model.nodes), 3))
    result = _result(model, zero)
    result.info = {"penetration_mm": {"lip_contact": 0.45}, "contact_tolerance_mm": 0.05,
                   "contact_unmet_mm": {"lip_contact": 0.45}}
    result.problem = None
    monkeypatch.setattr(pipeline, "_call_simulate", lambda *a, **k: result)
    progress = Progress(echo=False)
    pred = solve_plan(model, plan, None, progress=progress)
    assert pred.solver["info"]["contact_unmet_mm"] == {"lip_contact": 0.45}
    warned = [line for line in progress.log if "warning" in line and "lip_contact 0.45 mm" in line]
    assert warned and "tolerance 0.05 mm" in warned[0]
