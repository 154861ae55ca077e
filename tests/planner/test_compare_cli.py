"""`faceplan compare` from the command line: outputs, cohort summary, bad input -> exit 2."""
import csv
import json

import numpy as np
import pytest
import trimesh

from planner.cli import main
from planner.compare.distances import TriangleSurface
from planner.compare.phantom import face_phantom, write_prediction_folder


@pytest.fixture(scope="module")
def phantoms():
    # coarser than the known-answer tests: these tests check files and messages, not accuracy
    return face_phantom(2.5), face_phantom(2.0, jitter=0.5, seed=1, offset=0.3)


def _case(root, name, pred, scan, chin_offset=0.0, scan_vertices=None, scan_faces=None):
    case = root / name
    v = pred.vertices
    if chin_offset:
        chin = pred.region_names.index("chin")
        v = v + chin_offset * (pred.region == chin)[:, None] * TriangleSurface(v, pred.faces).vertex_normals
    write_prediction_folder(case / "predict", v, pred.faces, pred.region, pred.region_names,
                            pred.landmarks, pred.unoperated_regions)
    (case / "postop").mkdir(parents=True)
    sv = scan.vertices if scan_vertices is None else scan_vertices
    sf = scan.faces if scan_faces is None else scan_faces
    trimesh.Trimesh(sv + [0.7, -1.2, 0.9], sf, process=False).export(case / "postop" / "skin.stl")
    return case


def test_single_case_outputs(tmp_path, phantoms, capsys):
    pred, scan = phantoms
    case = _case(tmp_path, "P01", pred, scan, chin_offset=1.0)
    assert main(["compare", str(case)]) == 0
    out = case / "compare"
    report = json.loads((out / "report.json").read_text())
    m = report["metrics"]
    for block in [m["overall"], *[m["regions"][r] for r in ("upper_lip", "lower_lip", "chin", "nose",
                                                             "cheek_left", "cheek_right")]]:
        assert set(block) >= {"mean_abs_mm", "rms_mm", "p90_mm", "p95_mm", "within_2mm_pct", "n_points"}
        assert block["n_points"] > 0
    # 2.0/2.5 mm triangulations: chord error ~0.03 mm, border band wider than at 1.5 mm
    assert m["regions"]["chin"]["mean_abs_mm"] == pytest.approx(1.0, abs=0.1)
    assert m["regions"]["forehead"]["mean_abs_mm"] < 0.1
    assert set(m["landmarks"]) == {"Sn", "Ls", "Li", "Pog", "Me", "ChL", "ChR", "Prn"}
    assert all("error_mm" in v for v in m["landmarks"].values())
    assert report["alignment"]["residual_rms_mm"] < 0.1
    import pyvista as pv

    d = pv.read(str(out / "distances.vtp"))
    assert {"signed_distance_mm", "region", "valid"} <= set(d.point_data.keys())
    assert np.isfinite(d.point_data["signed_distance_mm"]).mean() > 0.9
    images = sorted(p.name for p in (out / "images").iterdir())
    for name in ("distance_postop_frontal.png", "distance_postop_profile.png",
                 "distance_postop_three_quarter.png", "histogram.png", "regions.png"):
        assert name in images and (out / "images" / name).stat().st_size > 5000
    html = (out / "report.html").read_text()
    assert "data:image/png;base64," in html and "chin" in html
    assert "within 2 mm" in capsys.readouterr().out


def test_cohort_summary(tmp_path, phantoms):
    pred, scan = phantoms
    a = _case(tmp_path, "A", pred, scan, chin_offset=0.0)
    b = _case(tmp_path, "B", pred, scan, chin_offset=1.0)
    out = tmp_path / "summary"
    assert main(["compare", str(a), str(b), "--out", str(out), "--no-images"]) == 0
    ra = json.loads((a / "compare" / "report.json").read_text())["metrics"]["regions"]["chin"]["mean_abs_mm"]
    rb = json.loads((b / "compare" / "report.json").read_text())["metrics"]["regions"]["chin"]["mean_abs_mm"]
    rows = {(r["region"], r["metric"]): r for r in csv.DictReader(open(out / "summary.csv"))}
    chin = rows[("chin", "mean_abs_mm")]
    # mean and sample SD of two numbers, exactly
    assert float(chin["mean"]) == pytest.approx((ra + rb) / 2, rel=1e-5)
    assert float(chin["sd"]) == pytest.approx(abs(ra - rb) / np.sqrt(2), rel=1e-5)
    assert chin["n_cases"] == "2"
    assert ("landmark Pog", "error_mm") in rows
    assert (out / "summary.html").read_text().count("±") > 5
    assert (out / "summary_regions.png").stat().st_size > 5000
    assert len(list(csv.DictReader(open(out / "cases.csv")))) > 20


def _bad(tmp_path, capsys, case, *extra):
    code = main(["compare", str(case), *extra])
    err = capsys.readouterr().err
    assert code == 2
    assert "Traceback" not in err and "error" in err
    assert not (case / "compare").exists()
    assert [p.name for p in case.iterdir()] != [] and not any(
        p.name.startswith(".compare") for p in case.iterdir())
    return err


def test_scan_in_metres(tmp_path, phantoms, capsys):
    pred, scan = phantoms
    case = _case(tmp_path, "m", pred, scan, scan_vertices=scan.vertices / 1000.0)
    err = _bad(tmp_path, capsys, case)
    assert "metre" in err.lower() or "mm" in err


def test_scan_with_flipped_normals(tmp_path, phantoms, capsys):
    pred, scan = phantoms
    case = _case(tmp_path, "f", pred, scan, scan_faces=scan.faces[:, ::-1])
    err = _bad(tmp_path, capsys, case)
    assert "normals" in err


def test_empty_scan(tmp_path, phantoms, capsys):
    pred, scan = phantoms
    case = _case(tmp_path, "e", pred, scan)
    (case / "postop" / "skin.stl").write_text("solid empty\nendsolid empty\n")
    err = _bad(tmp_path, capsys, case)
    assert "empty" in err


def test_scan_not_overlapping(tmp_path, phantoms, capsys):
    pred, scan = phantoms
    case = _case(tmp_path, "n", pred, scan, scan_vertices=scan.vertices + [400.0, 0.0, 0.0])
    err = _bad(tmp_path, capsys, case)
    assert "overlap" in err


def test_missing_prediction_and_scan(tmp_path, phantoms, capsys):
    pred, scan = phantoms
    case = _case(tmp_path, "x", pred, scan)
    import shutil

    shutil.rmtree(case / "predict")
    assert "faceplan predict" in _bad(tmp_path, capsys, case)
    case2 = _case(tmp_path, "y", pred, scan)
    (case2 / "postop" / "skin.stl").unlink()
    assert "post-op" in _bad(tmp_path, capsys, case2)
    # a bare surface without a registered model has no regions: refused
    assert "regions" in _bad(tmp_path, capsys, case2, "--prediction",
                             str(case2 / "predict" / "skin_predicted.stl"))


def test_scan_in_its_own_frame_needs_global_init(tmp_path, phantoms, capsys):
    from planner.compare.alignment import apply, rotation_matrix

    pred, scan = phantoms
    T = np.eye(4)
    T[:3, :3] = rotation_matrix(np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5]) * np.radians(130))
    T[:3, 3] = [250.0, -40.0, 600.0]
    case = _case(tmp_path, "cam", pred, scan, scan_vertices=apply(T, scan.vertices))
    # by default the scan must be in the patient's frame: refused as not overlapping
    assert "overlap" in _bad(tmp_path, capsys, case)
    assert main(["compare", str(case), "--global-init", "--no-images"]) == 0
    report = json.loads((case / "compare" / "report.json").read_text())
    # found the pose: as good as a scan given in the patient's frame (2.0/2.5 mm meshes)
    assert report["metrics"]["overall"]["mean_abs_mm"] < 0.05


def test_manual_postop_landmarks(tmp_path, phantoms, capsys):
    pred, scan = phantoms
    case = _case(tmp_path, "L", pred, scan)
    # hand-placed post-op landmarks in the scan's frame (the scan file is shifted by
    # [0.7, -1.2, 0.9] in _case): Pog placed 2 mm below the predicted one
    shift = np.array([0.7, -1.2, 0.9])
    pog = np.asarray(pred.landmarks["Pog"]) + shift + [0.0, 0.0, -2.0]
    (case / "postop" / "landmarks.json").write_text(json.dumps({"Pog": pog.tolist()}))
    assert main(["compare", str(case), "--no-images"]) == 0
    lm = json.loads((case / "compare" / "report.json").read_text())["metrics"]["landmarks"]
    assert lm["Pog"]["postop_source"] == "manual" and lm["Prn"]["postop_source"] == "located"
    # the predicted Pog is refined on the prediction (within ~0.1 mm of the phantom's point),
    # the manual one is 2 mm below it after superimposition
    assert lm["Pog"]["error_mm"] == pytest.approx(2.0, abs=0.2)
    # landmarks far off the scan are refused
    (case / "postop" / "landmarks.json").write_text(json.dumps({"Pog": (pog + [0, 40.0, 0]).tolist()}))
    import shutil

    shutil.rmtree(case / "compare")
    assert "off the post-op scan" in _bad(tmp_path, capsys, case)


def test_large_rigid_motion_is_found_by_the_global_search(phantoms):
    # beyond the ICP's basin (a 70 degree turn): the local fit is recognised as wrong (too
    # little of the scan within 2 mm of the face) and the 24-start search finds the pose
    from pathlib import Path

    from planner.compare.alignment import apply, rotation_matrix
    from planner.compare.comparison import compare_surfaces
    from planner.compare.inputs import Prediction, Surface

    pred, scan = phantoms
    T = np.eye(4)
    T[:3, :3] = rotation_matrix(np.array([0.6, 0.0, 0.8]) * np.radians(70))
    T[:3, 3] = [20.0, -30.0, 25.0]
    p = Prediction(pred.vertices, pred.faces, pred.region, pred.region_names,
                   pred.unoperated_regions, {}, Path("p"))
    r = compare_surfaces(p, Surface(apply(T, scan.vertices), scan.faces, Path("s")), landmarks=False)
    assert r.alignment.strategy == "global"
    assert any("global search" in w for w in r.warnings)
    # 2.0/2.5 mm triangulations of one surface: chord error ~0.02 mm
    assert r.metrics["overall"]["mean_abs_mm"] < 0.05
