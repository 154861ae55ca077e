"""`faceplan predict` from the command line: every bad-input class gives exit status 2, a
message naming the file/field, and no output folder. These are refused before registration, so
a small hand-made case folder (spheres and boxes in mm) is enough."""
import shutil

import numpy as np
import pytest
import trimesh
import yaml

from planner.cli import main

GOOD_PLAN = {"faceplan": 1, "segments": {"maxilla": {"translation": [0.0, 4.0, 0.0]}},
             "model": {"resolution": "coarse"}}


@pytest.fixture(scope="module")
def case_template(tmp_path_factory):
    root = tmp_path_factory.mktemp("case") / "case"
    (root / "preop" / "bone").mkdir(parents=True)
    skin = trimesh.creation.icosphere(subdivisions=3, radius=80.0)
    skin.export(root / "preop" / "skin.stl")
    for name, centre in {"skull": [0, 0, 30], "maxilla": [0, 50, -20], "mandible": [0, 45, -55]}.items():
        box = trimesh.creation.box(extents=[40, 20, 15], transform=trimesh.transformations.translation_matrix(centre))
        box.export(root / "preop" / "bone" / f"{name}.stl")
    (root / "plan.yaml").write_text(yaml.safe_dump(GOOD_PLAN))
    return root


def _case(tmp_path, template, plan=None, remove=()):
    case = tmp_path / "case"
    shutil.copytree(template, case)
    if plan is not None:
        (case / "plan.yaml").write_text(plan if isinstance(plan, str) else yaml.safe_dump(plan))
    for r in remove:
        (case / r).unlink()
    return case


def _with(**segments):
    return {"faceplan": 1, "segments": segments}


BAD_PLANS = {
    "unknown key": ({"faceplan": 1, "segments": {}, "surgeon": "X"}, "surgeon"),
    "unknown segment": (_with(maxila={"translation": [0, 3, 0]}), "segments.maxila"),
    "segment without bone": (_with(chin={"translation": [0, 3, 0]}), "segments.chin"),
    "non-orthonormal matrix": (_with(mandible={"matrix": [[1, 0, 0, 0], [0, 1.1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}),
                               "segments.mandible.matrix"),
    "reflection": (_with(mandible={"matrix": [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}),
                   "segments.mandible.matrix"),
    "NaN": ("faceplan: 1\nsegments:\n  maxilla:\n    translation: [0, .nan, 0]\n", "segments.maxilla.translation[1]"),
    "infinity": ("faceplan: 1\nsegments:\n  maxilla:\n    translation: [.inf, 0, 0]\n", "segments.maxilla.translation[0]"),
    "too far": (_with(maxilla={"translation": [0, 26, 0]}), "segments.maxilla.translation"),
    "too much rotation": (_with(mandible={"rotation": {"axis": [1, 0, 0], "angle_deg": 35, "center": [0, 0, 0]}}),
                          "segments.mandible"),
    "rotation moving bone too far": (_with(mandible={"rotation": {"axis": [1, 0, 0], "angle_deg": 25,
                                                                  "center": [0, -60, 30]}}), "segments.mandible"),
    "wrong version": ({"faceplan": 3, "segments": {}}, "faceplan"),
    "missing ITK file": (_with(maxilla={"itk_transform": "nope.tfm"}), "segments.maxilla.itk_transform"),
    "not YAML": ("faceplan: 1\nsegments: [\n", None),
}


@pytest.mark.parametrize("name", list(BAD_PLANS))
def test_bad_plan_exit_2_no_output(tmp_path, case_template, capsys, name):
    plan, fieldname = BAD_PLANS[name]
    case = _case(tmp_path, case_template, plan)
    out = tmp_path / "out" / "predict"
    assert main(["predict", str(case), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "plan.yaml" in err and "Traceback" not in err
    if fieldname:
        assert fieldname in err
    assert not out.exists() and not (tmp_path / "out").exists()
    assert not (case / "predict").exists()


def test_bad_command_line_and_case(tmp_path, case_template, capsys):
    case = _case(tmp_path, case_template)
    out = tmp_path / "out"
    for argv, words in [
        (["predict", str(case), "--out", str(out), "--effect", "swelling=0.5"], "swelling"),
        (["predict", str(case), "--out", str(out), "--effect", "nonsense=1"], "nonsense"),
        (["predict", str(tmp_path / "no-such-case"), "--out", str(out)], "no-such-case"),
    ]:
        assert main(argv + ["--quiet"]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err
        assert not out.exists()
    (case / "plan.yaml").unlink()
    assert main(["predict", str(case), "--out", str(out), "--quiet"]) == 2
    assert "plan.yaml" in capsys.readouterr().err and not out.exists()


def test_large_movement_accepted_when_asked_explicitly(tmp_path, case_template):
    """The limit is a safety net, not a ban: with --allow-large-movements a 26 mm plan passes
    validation (it then fails later here only because this case has no face to register)."""
    from planner.plan import check_against_bones, load_plan

    case = _case(tmp_path, case_template, _with(maxilla={"translation": [0, 26, 0]}))
    plan = load_plan(case / "plan.yaml", max_translation_mm=1e3)
    bones = {"maxilla": np.asarray(trimesh.load(case / "preop" / "bone" / "maxilla.stl").vertices)}
    assert check_against_bones(plan, bones)["maxilla"] == pytest.approx(26.0)


def test_unavailable_effect_in_the_plan(tmp_path, case_template, capsys):
    plan = dict(GOOD_PLAN, model={"resolution": "coarse", "effects": {"gravity": 5.0}})
    case = _case(tmp_path, case_template, plan)
    assert main(["predict", str(case), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "model.effects.gravity" in err and "plan.yaml" in err
    assert not (tmp_path / "out").exists()


class _ReachedRegistration(Exception):
    pass


def test_malformed_plans_through_the_cli(tmp_path_factory, case_template, monkeypatch):
    """Property-based, through `faceplan predict`: whatever the plan file holds, the command
    either refuses it with exit 2 and a one-line message naming plan.yaml, or accepts it and
    goes on to registration (stopped here); never a traceback, never an output folder."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    import planner.pipeline as pipeline

    scalars = (st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats()
               | st.text(max_size=6) | st.sampled_from(["maxilla", "chin", "RAS", "LPS", "translation"]))
    trees = st.recursive(scalars, lambda kids: st.lists(kids, max_size=4)
                         | st.dictionaries(st.text(max_size=6) | st.sampled_from(["maxilla", "matrix"]),
                                           kids, max_size=4), max_leaves=20)

    def stop(*args, **kwargs):
        raise _ReachedRegistration

    monkeypatch.setattr(pipeline, "register_case", stop)
    root = tmp_path_factory.mktemp("fuzzcli")
    case = root / "case"
    shutil.copytree(case_template, case)
    keys = ["faceplan", "frame", "segments", "muscles", "model", "limits"]

    @settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(st.sampled_from(keys), trees)
    def check(key, value):
        data = {"faceplan": 1, "segments": {"maxilla": {"translation": [0, 3, 0]}},
                "model": {"resolution": "coarse"}}
        data[key] = value
        try:
            text = yaml.safe_dump(data)
        except yaml.YAMLError:
            return
        (case / "plan.yaml").write_text(text)
        out = root / "out"
        try:
            code = main(["predict", str(case), "--out", str(out), "--quiet"])
        except _ReachedRegistration:
            return
        assert code == 2
        assert not out.exists()

    check()
