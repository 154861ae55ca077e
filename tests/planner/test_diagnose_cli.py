"""`faceplan diagnose` end to end: a case folder (the embedded demo head, coarse, lip contact
off to stay in the test budget) whose post-op scan was made with tissue sliding on a perturbed
model; the forward solves on a real 2-worker dask LocalCluster give the same diagnosis as in
this process; bad input exits with status 2 and writes nothing."""
import json
import shutil

import numpy as np
import pytest
import trimesh

from planner.cli import main
from planner.pipeline import write_demo_case

PLAN = {"faceplan": 1, "segments": {"maxilla": {"translation": [0.0, 4.0, 0.0]}},
        "model": {"resolution": "coarse", "contact": False}}


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


@pytest.fixture(scope="module")
def case(tmp_path_factory, monkeypatch_module):
    from planner.case import load_case
    from planner.diagnosis.forward import prepare_case, solve_skin
    from planner.diagnosis.synthetic import perturbed_case, scan_like
    from planner.pipeline import Progress, register_case
    from planner.plan import load_plan

    root = tmp_path_factory.mktemp("diagnose")
    monkeypatch_module.setenv("FACEPLAN_CACHE", str(root / "cache"))
    folder = write_demo_case(root / "case", PLAN)
    c = load_case(folder)
    plan = load_plan(c.require_plan())
    model, _ = register_case(c, "coarse", Progress(echo=False))
    patient = prepare_case("case", model, plan, c.bones)
    skin, _ = solve_skin(perturbed_case(patient, 21, modulus_pct=5.0, thickness_pct=5.0), ("sliding=1",))
    assert not isinstance(skin, str), skin
    v, f = scan_like(skin, patient.skin_faces, seed=21)
    (folder / "postop").mkdir()
    trimesh.Trimesh(v, f, process=False).export(folder / "postop" / "skin.stl")
    return folder


def test_cluster_and_in_process_agree(case, tmp_path):
    from planner.diagnosis.forward import Runner
    from planner.diagnosis.run import diagnose_cases

    out = tmp_path / "diag"
    code = main(["diagnose", str(case), "--out", str(out), "--workers", "2", "--effects", "sliding",
                 "--quiet"])
    assert code == 0
    rec = json.loads((out / "diagnosis.json").read_text())
    winner = rec["verdict"]["effect"] not in (None, "unexplained")
    for name in ("diagnosis.json", "report.html", "images/gap_before_frontal.png",
                 "images/heldout_shrinkage.png") + (("images/gap_after_frontal.png",) if winner else ()):
        assert (out / name).is_file(), name
    # the contract's fields
    for key in ("baseline", "localization", "noise_floor_mm", "effects", "verdict", "cases"):
        assert key in rec
    assert {"overall", "regions"} <= set(rec["baseline"])
    assert {"region", "rms_mm", "significant"} <= set(rec["localization"][0])
    e = rec["effects"][0]
    assert {"name", "params", "identifiable", "rms_after_mm", "shrink_pct", "heldout_shrink_pct",
            "significant"} <= set(e)
    assert {"effect", "confidence", "regions"} <= set(rec["verdict"])
    assert rec["effects"][0]["name"] == "sliding"
    assert rec["solves"]["workers"] == 2
    html = (out / "report.html").read_text()
    assert "data:image/png;base64," in html and "sliding" in html
    assert set(rec["files"]["images"]) == {str(p.relative_to(out)) for p in (out / "images").iterdir()}
    # the same diagnosis in this process: the result does not depend on the workers
    local = diagnose_cases([case], resolution="coarse", runner=Runner(None), effect_names=("sliding",))["record"]
    assert local["verdict"]["effect"] == rec["verdict"]["effect"]
    assert local["verdict"]["confidence"] == pytest.approx(rec["verdict"]["confidence"], abs=1e-9)
    for a, b in zip(local["effects"], rec["effects"]):
        assert a["name"] == b["name"]
        # the same solves on either side, each converged to the Newton tolerance (states within
        # ~1e-3 mm of each other, whichever process runs them): an RMS within 2e-3 mm, and a
        # shrinkage of a ~0.5 mm gap within 100 * 2e-3 / 0.5 = 0.4 percentage points
        assert a["rms_after_mm"] == pytest.approx(b["rms_after_mm"], abs=2e-3)
        for k in ("shrink_pct", "heldout_shrink_pct"):
            assert a[k] == pytest.approx(b[k], abs=0.5), k


def test_no_postop_scan_exits_2(case, tmp_path, capsys):
    bare = tmp_path / "bare"
    shutil.copytree(case, bare, ignore=shutil.ignore_patterns("postop", "diagnose"))
    assert main(["diagnose", str(bare), "--workers", "0", "--quiet"]) == 2
    assert "postop/skin.stl" in capsys.readouterr().err
    assert not (bare / "diagnose").exists()


def test_scan_of_another_patient_exits_2(case, tmp_path, capsys):
    from facemodel.synthetic import synthetic_head

    other = tmp_path / "other"
    shutil.copytree(case, other, ignore=shutil.ignore_patterns("postop", "diagnose"))
    head = synthetic_head(3, size=2.0)
    v, f = np.asarray(head.skin.vertices), np.asarray(head.skin.faces)
    front = trimesh.Trimesh(v, f, process=False).face_normals[:, 1] > 0.05
    (other / "postop").mkdir()
    trimesh.Trimesh(v, f[front], process=False).export(other / "postop" / "skin.stl")
    assert main(["diagnose", str(other), "--workers", "0", "--effects", "sliding", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "postop/skin.stl" in err and "another patient" in err
    assert not (other / "diagnose").exists()


def test_existing_cluster_via_scheduler_address(case, tmp_path):
    import logging

    from distributed import Client, LocalCluster

    # an existing cluster, as a user would start one: the command connects to its address,
    # sends the solves there and leaves the cluster running
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0",
                      silence_logs=logging.ERROR) as cluster:
        out = tmp_path / "diag"
        code = main(["diagnose", str(case), "--out", str(out), "--scheduler", cluster.scheduler_address,
                     "--effects", "sliding", "--no-images", "--quiet"])
        assert code == 0
        rec = json.loads((out / "diagnosis.json").read_text())
        assert rec["solves"]["workers"] == 1 and rec["solves"]["count"] >= 2
        assert rec["effects"][0]["name"] == "sliding"
        with Client(cluster) as client:
            assert len(client.scheduler_info()["workers"]) == 1


def test_scheduler_and_workers_exclude_each_other(case, capsys):
    assert main(["diagnose", str(case), "--scheduler", "tcp://127.0.0.1:1", "--workers", "2", "--quiet"]) == 2
    assert "--workers" in capsys.readouterr().err


def test_calibrated_materials_are_taken_and_a_bad_file_exits_2(case, tmp_path, capsys):
    """`--materials calibration.json`: the models take its moduli (the baseline then differs
    from the generic one) and the record names the file; a missing file or one without the
    pooled interval exits 2 naming it, before any work, nothing written."""
    out = tmp_path / "diag"
    assert main(["diagnose", str(case), "--out", str(out), "--workers", "0", "--materials",
                 str(tmp_path / "missing.json"), "--quiet"]) == 2
    assert "--materials" in capsys.readouterr().err and not out.exists()
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"materials": {"hypodermis": {"C10": 5.0}}}))
    assert main(["diagnose", str(case), "--out", str(out), "--workers", "0", "--materials", str(bad),
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "bad.json" in err and "pooled" in err and not out.exists()
    cal = tmp_path / "calibration.json"
    cal.write_text(json.dumps({"materials": {"hypodermis": {"C10": 5.0, "C20": 2.35, "K": 10000.0}},
                               "pooled": {"C10_kpa": {"estimate": 5.0, "interval_90": [4.0, 6.0]},
                                          "dermis_ratio": {"estimate": 4.0, "interval_90": None,
                                                           "identifiable": False}}}))
    assert main(["diagnose", str(case), "--out", str(out), "--workers", "0", "--effects", "sliding",
                 "--mesh-reference", "none", "--boundary-uncertainty", "none", "--no-images", "--quiet",
                 "--materials", str(cal)]) == 0
    rec = json.loads((out / "diagnosis.json").read_text())
    assert rec["materials"] == str(cal)
    generic = tmp_path / "generic"
    assert main(["diagnose", str(case), "--out", str(generic), "--workers", "0", "--effects", "sliding",
                 "--mesh-reference", "none", "--boundary-uncertainty", "none", "--no-images", "--quiet"]) == 0
    base = json.loads((generic / "diagnosis.json").read_text())
    # a hypodermis twice as stiff changes what the face does under the same movement
    assert abs(rec["baseline"]["overall"]["rms_mm"] - base["baseline"]["overall"]["rms_mm"]) > 1e-3


def test_mesh_reference_equal_to_the_resolution_exits_2(case, tmp_path, capsys):
    # the second mesh must be another mesh: refused before any registration, nothing written
    out = tmp_path / "diag"
    assert main(["diagnose", str(case), "--out", str(out), "--workers", "0", "--resolution", "coarse",
                 "--mesh-reference", "coarse", "--quiet"]) == 2
    assert "--mesh-reference" in capsys.readouterr().err
    assert not out.exists()


def test_the_report_lists_the_named_effects_values_with_their_intervals(tmp_path):
    """report.html shows each identifiable fitted value of the verdict's effect with its 95 %
    interval and both standard errors, the interval and error with the patient's moduli
    unknown, and its prior's standard deviation; a parameter held at "none" is not listed."""
    from planner.diagnosis.outputs import write_diagnosis

    def param(value, interval, identifiable=True):
        return {"identifiable": identifiable, "value": value, "standard_error": 0.0086,
                "standard_error_with_discrepancy": 0.0341, "interval_95": interval,
                "coordinate": "value", "unit": "", "bounds": [0.0, 2.5], "none": 0.0}

    effect = {"name": "gravity", "params": {"gravity": 1.088}, "identifiable": True, "rms_after_mm": 0.3,
              "shrink_pct": 40.0, "heldout_shrink_pct": 38.0, "heldout_shrink_spread_pct": 5.0,
              "probability": 1.0, "significant": True,
              "parameters": {"gravity": dict(param(1.087978, [1.021, 1.155]), standard_error_marginal=0.3117,
                                             interval_95_marginal=[0.477, 1.5], prior_sd=0.7654),
                             "gravity.other": param(0.0, None, identifiable=False)}}
    record = {"effects": [effect], "localization": [], "noise_floor_mm": 0.2,
              "verdict": {"effect": "gravity", "confidence": 1.0, "regions": []}}
    write_diagnosis({"record": record}, tmp_path / "d", render_images=False)
    html = (tmp_path / "d" / "report.html").read_text()
    assert "Fitted values of gravity, with their 95 % intervals" in html
    assert "[1.021, 1.155]" in html and "0.0341" in html and "1.087978" in html
    assert "95 % interval, moduli unknown" in html and "[0.477, 1.5]" in html and "0.3117" in html
    assert "standard deviation of the prior" in html and "0.7654" in html
    assert "<td>gravity</td>" in html and "<td>gravity.other</td>" not in html


def test_the_report_shows_the_alternatives_and_the_surface_confound(tmp_path):
    """A named verdict's alternatives are tabled in report.html, and one a surface scan cannot
    separate from the verdict is said so in the verdict's sentence with what would settle it."""
    from planner.diagnosis.outputs import write_diagnosis

    effect = {"name": "bone_execution", "params": {}, "identifiable": True, "rms_after_mm": 0.47,
              "shrink_pct": 3.0, "heldout_shrink_pct": 30.4, "heldout_shrink_spread_pct": 5.0,
              "probability": 1.0, "significant": True}
    alts = [{"effect": "sliding", "bic_gain": 61.1, "heldout_shrink_pct": 14.02, "heldout_lpd_gain": 14.28,
             "heldout_lpd_gain_probability": 0.7175, "significant": False},
            {"effect": "stiffness", "bic_gain": 16.6, "heldout_shrink_pct": 4.66, "heldout_lpd_gain": 6.49,
             "heldout_lpd_gain_probability": 0.8548, "significant": False}]
    record = {"effects": [effect], "localization": [], "noise_floor_mm": 0.27,
              "verdict": {"effect": "bone_execution", "confidence": 1.0, "regions": ["upper_lip"],
                          "alternatives": alts, "confounded_on_surface": ["sliding"]}}
    write_diagnosis({"record": record}, tmp_path / "d", render_images=False)
    html = (tmp_path / "d" / "report.html").read_text()
    assert "Other effects that explain the gap with strong evidence in-sample, not named" in html
    assert "<td>61.1</td>" in html and "<td>16.6</td>" in html
    assert "cannot tell it from sliding" in html and "plan_actual.yaml" in html


def test_the_verdict_sentence_says_why_a_supported_effect_is_not_named(tmp_path):
    """A `null` verdict reads as no effect named with the probability of the prediction without
    one, and each effect the data support but do not name comes with the share of the held-out
    gap it removes and the share naming asks: 10 % and twice its bootstrap spread
    (`analysis._judge`); the effects' values read as words and numbers, not JSON."""
    from planner.diagnosis.outputs import params_text, verdict_text, write_diagnosis

    sliding = {"name": "sliding", "params": {"sliding": 1, "sliding.hold": 0.8}, "identifiable": True,
               "rms_after_mm": 0.398, "shrink_pct": 31.2, "heldout_shrink_pct": 31.2,
               "heldout_shrink_spread_pct": 16.0, "heldout_noise_shrink_pct": 42.71,
               "heldout_noise_shrink_spread_pct": 23.09, "probability": 1.0, "significant": False}
    bone = {"name": "bone_execution", "identifiable": True, "rms_after_mm": 0.34, "shrink_pct": 40.7,
            "heldout_shrink_pct": 38.0, "heldout_shrink_spread_pct": 8.9, "probability": 0.0,
            "significant": False,
            "params": {"bone_execution.maxilla": [0.015952, -1.437634, -2.902737, 1.992344, -0.246527, 0.522332]}}
    record = {"effects": [bone, sliding], "localization": [], "noise_floor_mm": 0.27,
              "verdict": {"effect": None, "confidence": 0.0, "regions": [], "supported_not_named": ["sliding"]}}
    text = verdict_text(record)
    assert text.startswith("no effect named") and "without an effect 0.00" in text
    # 2 x 23.09 = 46.2 % needed, above the 10 % floor
    assert "sliding (43 ± 23 % of the held-out gap beyond the noise removed, 46 % needed)" in text
    assert params_text(bone["params"]) == "maxilla corrected by (+0.02, -1.44, -2.90) mm and (+1.99, -0.25, +0.52) deg"
    assert params_text({"per_case": [{"gravity": 1.08797}, {}]}) == "case 1: gravity 1.09; case 2: -"
    assert params_text({"sliding": "maxilla"}) == "the tissue slides on the maxilla"
    write_diagnosis({"record": record}, tmp_path / "d", render_images=False)
    html = (tmp_path / "d" / "report.html").read_text()
    assert "46 % needed" in html and "interface hold 0.8" in html
    assert "<td>maxilla corrected by (+0.02, -1.44, -2.90) mm and (+1.99, -0.25, +0.52) deg</td>" in html
