"""`faceplan predict` end to end on a synthetic head (the embedded demo head, written as a case
folder): registration, segment assignment, solve, every output, the report's figures, and the
registration cache on a re-run. Coarse resolution, lip contact off to stay in the test budget
(see test_predict.py)."""
import json

import meshio
import numpy as np
import pytest
import pyvista as pv
import trimesh

from planner.cli import main
from planner.pipeline import write_demo_case

PLAN = {"faceplan": 1, "segments": {"maxilla": {"translation": [0.0, 5.0, 0.0]}},
        "model": {"resolution": "coarse", "contact": False}}


@pytest.fixture(scope="module")
def run(tmp_path_factory, monkeypatch_module):
    root = tmp_path_factory.mktemp("e2e")
    monkeypatch_module.setenv("FACEPLAN_CACHE", str(root / "cache"))   # a fresh registration cache
    case = write_demo_case(root / "case", PLAN)
    code = main(["predict", str(case), "--resolution", "coarse", "--quiet"])
    return case, code


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


def test_outputs_exist(run):
    case, code = run
    assert code == 0
    out = case / "predict"
    for name in ["prediction.vtu", "skin_predicted.stl", "skin_predicted.ply", "skin_predicted.vtp",
                 "report.json", "report.html", "images/preop_frontal.png", "images/predicted_profile.png",
                 "images/displacement_three_quarter.png", "images/overlay_profile.png",
                 "images/profile_midline.png"]:
        assert (out / name).is_file(), name
    assert not [p for p in case.iterdir() if p.name.startswith(".predict")]   # no temporary left


def test_report_figures(run):
    case, _ = run
    report = json.loads((case / "predict" / "report.json").read_text())
    assert set(report["landmarks_predicted"]) == {"Prn", "Sn", "Ls", "Stms", "Stmi", "Li", "ChL", "ChR", "Pog", "Me"}
    ls = report["landmarks"]["Ls"]
    # Le Fort I advancement on a registered synthetic head: Ls follows the maxilla by the
    # published 0.5-0.9 ratio (see test_predict.py for the source).
    assert 0.5 <= ls["soft_to_hard_ratio_ap"] <= 0.9
    assert report["mesh_quality"]["inverted_elements"] == 0
    assert report["segments"]["maxilla"]["centroid_displacement_mm"] == pytest.approx([0, 5, 0], abs=1e-9)
    assert report["attachment_assignment"]["maxilla"]["nodes"] > 0
    assert report["regions"]["upper_lip"]["max_mm"] > report["regions"]["infraorbital_left"]["max_mm"]
    for stage in ("load case", "registration", "segments", "solve", "render"):
        assert stage in report["timings_s"]
    assert report["solver"]["converged"] is True
    assert report["plan"]["segments"]["maxilla"]["matrix_ras"][1][3] == 5.0


def test_surfaces_in_the_input_frame(run):
    case, _ = run
    out = case / "predict"
    vtp = pv.read(out / "skin_predicted.vtp")
    stl = trimesh.load(out / "skin_predicted.stl")            # STL repeats vertices: merged
    ply = trimesh.load(out / "skin_predicted.ply", process=False)
    # PLY keeps the vertices as written; STL stores float32: 1e-4 mm on ~100 mm coordinates.
    assert np.allclose(ply.vertices, np.asarray(vtp.points), atol=1e-9)
    assert np.allclose(np.sort(stl.vertices, axis=0), np.sort(ply.vertices, axis=0), atol=1e-4)
    names = list(vtp.field_data["region_names"])
    region = np.asarray(vtp.point_data["region"])
    assert {"upper_lip", "lower_lip", "chin", "nose"} <= set(names)
    assert region.min() >= -1 and region.max() < len(names)
    # Away from the surgery the predicted skin lies on the patient's pre-op skin: registration
    # fits the skin to < 0.3 mm mean (its target), and the infra-orbital region barely moves.
    skin = trimesh.load(case / "preop" / "skin.stl")
    sel = np.isin(region, [names.index(r) for r in ("infraorbital_left", "infraorbital_right")])
    _, d, _ = trimesh.proximity.closest_point(skin, np.asarray(vtp.points)[sel])
    assert np.median(d) < 0.5
    vol = meshio.read(out / "prediction.vtu")
    assert vol.cells[0].type == "hexahedron" and "displacement" in vol.point_data
    assert "von_mises" in vol.cell_data and "label" in vol.cell_data


def test_demo_bimaxillary_reuses_the_registration(run, tmp_path):
    """`faceplan demo`: the same embedded head with the bimaxillary plan; the registration of
    the first run (same skin, bones and landmarks) is reused from the cache."""
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--quiet", "--no-images"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["registration"]["cached"] is True
    assert set(report["plan"]["segments"]) == {"maxilla", "mandible", "chin"}
    assert report["mesh_quality"]["inverted_elements"] == 0
    lm = report["landmarks"]
    # Directions a surgeon expects: the upper lip comes forward with the maxilla, the lower lip
    # goes back with the mandibular setback, the chin comes forward with the genioplasty.
    assert lm["Ls"]["displacement_mm"][1] > 1.0
    assert lm["Li"]["displacement_mm"][1] < -1.0
    assert lm["Pog"]["displacement_mm"][1] > 1.0
    assert (out / "case" / "plan.yaml").is_file() and (out / "case" / "preop" / "skin.stl").is_file()
