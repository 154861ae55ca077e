"""The mistakes real users make are named, not computed from (exit 2, file and field named).

Each test starts from the embedded demo head written as a case folder and makes one mistake:
a skin in metres, surfaces in LPS read as RAS, a skin in another frame far from the bones, an
inside-out face-only skin, maxilla and mandible files swapped, landmarks in LPS, unrecognised
landmark names; and plan files with a key given twice, `-3e0`, or 10 MB of content.
"""
import json
import shutil

import numpy as np
import pytest
import trimesh

from planner.case import load_case, load_landmarks
from planner.errors import InputError
from planner.plan import load_plan
from planner.pipeline import write_demo_case


@pytest.fixture(scope="module")
def template(tmp_path_factory):
    return write_demo_case(tmp_path_factory.mktemp("demo") / "case")


@pytest.fixture
def case(template, tmp_path):
    c = tmp_path / "case"
    shutil.copytree(template, c)
    return c


def _transform(path, fn, faces=None):
    m = trimesh.load(path, force="mesh", process=False)
    v = fn(np.asarray(m.vertices, float))
    trimesh.Trimesh(v, m.faces if faces is None else faces(m.faces), process=False).export(path)


def _refused(case, *words):
    with pytest.raises(InputError) as info:
        load_case(case)
    msg = str(info.value)
    for w in words:
        assert w in msg, msg
    return info.value


def test_the_demo_case_passes(case):
    c = load_case(case)
    assert set(c.landmarks) >= {"Prn", "Sn", "Pog"}


def test_skin_in_metres(case):
    _transform(case / "preop" / "skin.stl", lambda v: v / 1000.0)
    _refused(case, "metres", "skin.stl")


def test_surfaces_in_lps(case):
    lps = lambda v: v * [-1.0, -1.0, 1.0]      # noqa: E731
    _transform(case / "preop" / "skin.stl", lps)
    for f in (case / "preop" / "bone").iterdir():
        _transform(f, lps)
    (case / "preop" / "landmarks.json").unlink()
    err = _refused(case, "-y", "LPS")
    assert err.file.endswith("skin.stl")


def test_skin_far_from_the_bones(case):
    _transform(case / "preop" / "skin.stl", lambda v: v + [0.0, 0.0, 250.0])
    (case / "preop" / "landmarks.json").unlink()
    _refused(case, "mm from the skin", "frame")


def test_inside_out_face_only_skin(case):
    m = trimesh.load(case / "preop" / "skin.stl", force="mesh", process=False)
    keep = m.triangles_center[:, 1] > 20.0              # the face only: an open surface
    face = trimesh.Trimesh(m.vertices, m.faces[keep], process=False)
    face.remove_unreferenced_vertices()
    face.export(case / "preop" / "skin.stl")
    load_case(case)                                    # the face alone is accepted
    trimesh.Trimesh(face.vertices, face.faces[:, ::-1], process=False).export(case / "preop" / "skin.stl")
    _refused(case, "inside-out", "skin.stl")


def test_maxilla_and_mandible_swapped(case):
    bone = case / "preop" / "bone"
    (bone / "maxilla.stl").rename(bone / "tmp.stl")
    (bone / "mandible.stl").rename(bone / "maxilla.stl")
    (bone / "tmp.stl").rename(bone / "mandible.stl")
    _refused(case, "swapped", "maxilla.stl", "mandible.stl")


def test_landmarks_in_lps(case):
    f = case / "preop" / "landmarks.json"
    data = json.loads(f.read_text())
    f.write_text(json.dumps({k: [-v[0], -v[1], v[2]] for k, v in data.items()}))
    err = _refused(case, "landmarks.json")
    assert "LPS" in str(err) or "frame" in str(err)


def test_landmark_names_any_case_unknown_refused(case, tmp_path):
    f = case / "preop" / "landmarks.json"
    data = json.loads(f.read_text())
    f.write_text(json.dumps({k.lower(): v for k, v in data.items()}))     # prn, sn, ...
    assert set(load_case(case).landmarks) == set(data)
    f.write_text(json.dumps({"nose_tip": data["Prn"], "prm": data["Prn"], "Sn": data["Sn"]}))
    err = _refused(case, "unrecognised", "'nose_tip'", "Prn")
    assert err.field == "landmarks.nose_tip"
    f.write_text('{"Prn": [0, 1, 2], "Prn": [0, 1, 3]}')
    with pytest.raises(InputError, match="twice"):
        load_landmarks(f)


def test_slicer_markups_names_checked_too(tmp_path):
    f = tmp_path / "lm.mrk.json"
    f.write_text(json.dumps({"markups": [{"coordinateSystem": "RAS", "controlPoints": [
        {"label": "PRN", "position": [0, 90, 0]}, {"label": "F-1", "position": [0, 80, -20]}]}]}))
    with pytest.raises(InputError, match="'F-1'") as info:
        load_landmarks(f)
    assert info.value.file == str(f)


PLAN = "faceplan: 1\nsegments:\n  maxilla:\n    translation: [0, 2, 0]\n"


def test_duplicate_yaml_keys_refused(tmp_path):
    f = tmp_path / "plan.yaml"
    f.write_text("faceplan: 1\nsegments:\n  mandible: {translation: [0, 1, 0]}\n"
                 "  mandible: {translation: [0, -6, 0]}\n")
    with pytest.raises(InputError, match="'mandible' appears twice") as info:
        load_plan(f)
    assert info.value.file == "plan.yaml" and "line" in str(info.value)
    c = tmp_path / "case.yaml"
    c.write_text("id: a\nid: b\n")
    from planner.case import load_case_info

    with pytest.raises(InputError, match="twice"):
        load_case_info(c, "x")


def test_exponent_numbers_read_as_numbers(tmp_path):
    f = tmp_path / "plan.yaml"
    f.write_text("faceplan: 1\nsegments:\n  maxilla:\n    translation: [0, -3e0, 1e-3]\n")
    plan = load_plan(f)
    np.testing.assert_allclose(plan.segments["maxilla"].matrix[:3, 3], [0.0, -3.0, 1e-3])


def test_plan_size_limit(tmp_path):
    f = tmp_path / "plan.yaml"
    f.write_text(PLAN + "muscles: [" + ", ".join(["0.0"] * 300_000) + "]\n")
    with pytest.raises(InputError, match="MB") as info:
        load_plan(f)
    assert info.value.file == "plan.yaml"


# ------------------------------------------------------------------ post-op scan mistakes
@pytest.fixture(scope="module")
def phantoms():
    from planner.compare.phantom import face_phantom

    return face_phantom(2.5), face_phantom(2.0, jitter=0.5, seed=1, offset=0.3)


def _compare_case(root, pred, scan_vertices, scan_faces, preop=None):
    from planner.compare.phantom import write_prediction_folder

    write_prediction_folder(root / "predict", pred.vertices, pred.faces, pred.region, pred.region_names,
                            pred.landmarks, pred.unoperated_regions)
    (root / "postop").mkdir(parents=True)
    trimesh.Trimesh(scan_vertices, scan_faces, process=False).export(root / "postop" / "skin.stl")
    if preop is not None:
        (root / "preop").mkdir()
        trimesh.Trimesh(*preop, process=False).export(root / "preop" / "skin.stl")
    return root


def test_preop_skin_given_as_postop_scan(tmp_path, phantoms, capsys):
    from planner.cli import main

    pred, scan = phantoms
    case = _compare_case(tmp_path / "c", pred, scan.vertices, scan.faces, preop=(scan.vertices, scan.faces))
    assert main(["compare", str(case), "--no-images"]) == 2
    err = capsys.readouterr().err
    assert "is the pre-op skin" in err and "postop/skin.stl" in err
    assert not (case / "compare").exists()


def test_another_patients_scan_is_refused(tmp_path, phantoms, capsys):
    from planner.cli import main

    pred, scan = phantoms
    c = np.array([0.0, 0.0, -10.0])
    # another head: 7 % wider, 5 % shallower, 4 % taller than the predicted patient
    other = (scan.vertices - c) * [1.07, 0.95, 1.04] + c
    case = _compare_case(tmp_path / "o", pred, other, scan.faces)
    assert main(["compare", str(case), "--no-images"]) == 2
    err = capsys.readouterr().err
    assert "another patient" in err and "postop/skin.stl" in err
    # the patient's own scan, with 0.5 mm of scanner noise along the normals, is compared
    rng = np.random.default_rng(3)
    n = trimesh.Trimesh(scan.vertices, scan.faces, process=False).vertex_normals
    own = scan.vertices + n * rng.normal(0.0, 0.5, (len(n), 1))
    case = _compare_case(tmp_path / "s", pred, own, scan.faces)
    assert main(["compare", str(case), "--no-images"]) == 0
    rep = json.loads((case / "compare" / "report.json").read_text())
    assert rep["alignment"]["unoperated_median_mm"] < 0.6


def test_skin_alone_in_lps(case):
    # bones and landmarks in RAS, the skin in LPS: the skin's nose is at its back, and the skin
    # (not the landmarks, which no longer lie on it) is named
    _transform(case / "preop" / "skin.stl", lambda v: v * [-1.0, -1.0, 1.0])
    err = _refused(case, "looks along -y", "LPS")
    assert err.file.endswith("skin.stl")
