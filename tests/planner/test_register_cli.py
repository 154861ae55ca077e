"""`faceplan register`: outputs on a synthetic case, exit 2 and nothing written on bad input."""
import json

import numpy as np
import pytest

from planner.cli import main

synthetic = pytest.importorskip("facemodel.synthetic")


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    root = tmp_path_factory.mktemp("cases")
    assert main(["synth", "--out", str(root), "--count", "1", "--seed", "6"]) == 0
    return next(p for p in root.iterdir() if p.is_dir())


def test_register_writes_mesh_report_and_images(case, tmp_path, monkeypatch):
    monkeypatch.setenv("FACEPLAN_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "reg"
    assert main(["register", str(case), "--out", str(out), "--resolution", "coarse"]) == 0
    from facemodel.model import FaceModel
    from registration.quality import min_scaled_jacobian

    model = FaceModel.load(out / "patient_mesh.vtu")
    assert min_scaled_jacobian(model.nodes, model.hexes).min() >= 0.2
    rep = json.loads((out / "report.json").read_text())
    for side in ("skin", "bone"):
        assert {"mean_mm", "p95_mm", "max_mm"} <= set(rep["fit"][side])
    assert rep["fit"]["skin"]["mean_mm"] < 0.3 and rep["fit"]["bone"]["mean_mm"] < 0.5
    assert rep["quality"]["n_inverted"] == 0 and "histogram" in rep["quality"]
    assert "elements_repaired" in rep and {"align_s", "elastic_s", "repair_s"} <= set(rep["time"])
    assert rep["outputs"]["images"] and all((out / p).is_file() for p in rep["outputs"]["images"])


def test_skin_in_metres_is_refused_and_nothing_written(case, tmp_path, capsys):
    import shutil

    import trimesh

    bad = tmp_path / "metres"
    shutil.copytree(case, bad)
    skin = trimesh.load(bad / "preop" / "skin.stl")
    skin.apply_scale(1e-3)
    skin.export(bad / "preop" / "skin.stl")
    out = tmp_path / "out"
    assert main(["register", str(bad), "--out", str(out), "--resolution", "coarse", "--no-images"]) == 2
    assert "metres" in capsys.readouterr().err and not out.exists()


def test_landmarks_in_another_frame_are_refused(case, tmp_path, capsys):
    import shutil

    bad = tmp_path / "lps"
    shutil.copytree(case, bad)
    f = bad / "preop" / "landmarks.json"
    data = json.loads(f.read_text())
    # mirrored left-right: no rigid motion maps them onto the skin's landmark positions
    mirrored = {k: [-v[0] + (3.0 if k in ("ChL", "Prn") else 0.0), v[1], v[2]] for k, v in data.items()}
    f.write_text(json.dumps(mirrored))
    out = tmp_path / "out"
    rc = main(["register", str(bad), "--out", str(out), "--resolution", "coarse", "--no-images", "--no-cache"])
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists(), err


def test_command_registers_as_the_pipeline_does(case, tmp_path, monkeypatch):
    """`faceplan register` goes through `planner.pipeline.register_case`: a prediction of the
    same case then finds the very registration in the cache (same inputs, teeth and options),
    and the report carries the lip separation (lips apart, before/after)."""
    from planner.case import load_case
    from planner.pipeline import Progress, register_case

    monkeypatch.setenv("FACEPLAN_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "reg"
    assert main(["register", str(case), "--out", str(out), "--resolution", "coarse", "--no-images"]) == 0
    rep = json.loads((out / "report.json").read_text())
    patient, summary = register_case(load_case(case), "coarse", Progress(echo=False))
    assert summary["cached"] is True and summary["cache_key"] == rep["cache_key"]
    from facemodel.model import FaceModel

    # the saved mesh is the pipeline's mesh (vtu round trip in float64: exact)
    np.testing.assert_array_equal(FaceModel.load(out / "patient_mesh.vtu").nodes, patient.nodes)
    lips = rep["lip_separation"]
    assert lips["after"]["lower_in_upper_mm"] == 0.0 and lips["after"]["upper_in_lower_mm"] == 0.0
    # --no-cache registers afresh (a private cache for the call) and leaves the cache as it was
    before = sorted(p.name for p in (tmp_path / "cache" / "registration").iterdir())
    out2 = tmp_path / "reg2"
    assert main(["register", str(case), "--out", str(out2), "--resolution", "coarse", "--no-images",
                 "--no-cache", "--no-landmarks"]) == 0
    rep2 = json.loads((out2 / "report.json").read_text())
    assert rep2["cached"] is False and rep2["alignment"]["method"] == "surfaces"
    assert sorted(p.name for p in (tmp_path / "cache" / "registration").iterdir()) == before


def test_a_stricter_threshold_is_applied(case, tmp_path, monkeypatch):
    """--threshold 0.3 reaches the repair through the pipeline's register_case: every element
    of the written mesh has a scaled Jacobian of at least 0.3."""
    from facemodel.model import FaceModel
    from registration.quality import min_scaled_jacobian

    monkeypatch.setenv("FACEPLAN_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "out"
    assert main(["register", str(case), "--out", str(out), "--resolution", "coarse",
                 "--no-images", "--threshold", "0.3"]) == 0
    model = FaceModel.load(out / "patient_mesh.vtu")
    assert min_scaled_jacobian(model.nodes, model.hexes).min() >= 0.3 - 1e-9


def test_threshold_outside_0_1_is_refused(case, tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["register", str(case), "--out", str(out), "--resolution", "coarse", "--threshold", "1.5"])
    assert rc == 2 and not out.exists()
    assert "--threshold" in capsys.readouterr().err
