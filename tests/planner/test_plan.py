"""The plan file: movement forms agree with hand-computed rigid motions, LPS and ITK (3D Slicer)
conventions, and every class of bad input is an InputError naming the file and the field.

Tolerances: matrices are built from at most a few trigonometric calls, so 1e-12 (a few ulps of
the mm-sized entries) is what exact agreement means; plan values typed with 6 decimals are
compared at 1e-6.
"""
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from planner.errors import InputError
from planner.itk_transform import format_itk_transform, parse_itk_transform
from planner.plan import axis_angle_matrix, check_against_bones, euler_matrix, load_plan, parse_plan


def write_plan(tmp_path: Path, data, name="plan.yaml") -> Path:
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return p


def plan_of(segments, **extra):
    return parse_plan({"faceplan": 1, "segments": segments, **extra})


def test_translation_and_rotation_about_a_centre():
    c = np.array([0.0, 62.0, -18.0])
    plan = plan_of({"maxilla": {"translation": [0.0, 4.0, 1.5],
                                "rotation": {"axis": [1, 0, 0], "angle_deg": -3.0, "center": c.tolist()}}})
    m = plan.segments["maxilla"].matrix
    # The centre moves by exactly the translation.
    assert np.allclose(m[:3, :3] @ c + m[:3, 3], c + [0, 4, 1.5], atol=1e-12)
    # A point 10 mm below the centre turns about +x by -3 deg (right-hand rule): y decreases
    # by 10 sin(3deg)... sign: R_x(-a) (0, 0, -10) = (0, -10 sin a, -10 cos a).
    a = math.radians(3.0)
    p = c + [0, 0, -10]
    expected = c + [0, -10 * math.sin(a), -10 * math.cos(a)] + [0, 4, 1.5]
    assert np.allclose(plan.segments["maxilla"].apply(p[None])[0], expected, atol=1e-12)
    assert plan.segments["maxilla"].rotation_deg == pytest.approx(3.0, abs=1e-9)


def test_euler_order_is_extrinsic_in_written_order():
    r = euler_matrix([10.0, 20.0, 0.0], "xyz")
    assert np.allclose(r, axis_angle_matrix([0, 1, 0], 20) @ axis_angle_matrix([1, 0, 0], 10), atol=1e-12)
    r = euler_matrix([10.0, 20.0, 5.0], "zyx")
    expected = axis_angle_matrix([1, 0, 0], 5) @ axis_angle_matrix([0, 1, 0], 20) @ axis_angle_matrix([0, 0, 1], 10)
    assert np.allclose(r, expected, atol=1e-12)
    plan = plan_of({"chin": {"rotation": {"euler_deg": [0, 0, 7], "center": [1, 2, 3]}}})
    assert np.allclose(plan.segments["chin"].matrix[:3, :3], axis_angle_matrix([0, 0, 1], 7), atol=1e-12)


def test_matrix_form_and_lps_frame():
    m = [[1, 0, 0, 0], [0, 1, 0, 6.0], [0, 0, 1, 0], [0, 0, 0, 1]]
    assert np.allclose(plan_of({"mandible": {"matrix": m}}).segments["mandible"].matrix, m)
    # In LPS +y is posterior and +x the patient's left: a 6 mm LPS +y shift is a 6 mm setback
    # (RAS -y), and a point at LPS (10, 0, 0) is RAS (-10, 0, 0).
    plan = plan_of({"mandible": {"matrix": m}}, frame="LPS")
    assert np.allclose(plan.segments["mandible"].matrix[:3, 3], [0, -6, 0])
    plan = plan_of({"maxilla": {"rotation": {"axis": [0, 0, 1], "angle_deg": 20, "center": [10, 0, 0]}}},
                   frame="LPS")
    # RAS centre (-10, 0, 0) is fixed; rotation about +z keeps its sense (the LPS<->RAS change
    # of basis is a proper rotation by 180 deg about z).
    sp = plan.segments["maxilla"]
    assert np.allclose(sp.apply(np.array([[-10.0, 0, 0]])), [[-10, 0, 0]], atol=1e-12)
    assert np.allclose(sp.matrix[:3, :3], axis_angle_matrix([0, 0, 1], 20), atol=1e-12)


def test_itk_transform_as_slicer_saves_it(tmp_path):
    # Slicer saves the inverse (resampling) transform in LPS. A model moved 5 mm anteriorly
    # (RAS +y) is, in LPS, moved by (0, -5, 0); the resampling inverse is (0, +5, 0).
    (tmp_path / "chin.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 0 5 0\nFixedParameters: 0 0 0\n")
    p = write_plan(tmp_path, {"faceplan": 1, "segments": {"chin": {"itk_transform": "chin.tfm"}}})
    plan = load_plan(p)
    assert np.allclose(plan.segments["chin"].matrix[:3, 3], [0, 5, 0], atol=1e-12)
    assert plan.segments["chin"].form == "itk_transform"
    # Also with plan frame LPS: ITK files are LPS whatever the plan says, so the same result.
    p = write_plan(tmp_path, {"faceplan": 1, "frame": "LPS", "segments": {"chin": {"itk_transform": "chin.tfm"}}})
    assert np.allclose(load_plan(p).segments["chin"].matrix[:3, 3], [0, 5, 0], atol=1e-12)


def test_itk_rotation_classes_agree():
    # A rotation of +10 deg about RAS +z (= LPS +z) about the LPS centre (20, -30, 5), saved
    # inverted: the resampling rotation is -10 deg about z.
    a = math.radians(-10.0)
    euler = ("#Insight Transform File V1.0\n#Transform 0\nTransform: Euler3DTransform_double_3_3\n"
             f"Parameters: 0 0 {a!r} 0 0 0\nFixedParameters: 20 -30 5 0\n")
    versor = ("#Insight Transform File V1.0\n#Transform 0\nTransform: VersorRigid3DTransform_double_3_3\n"
              f"Parameters: 0 0 {math.sin(a / 2)!r} 0 0 0\nFixedParameters: 20 -30 5\n")
    m1, m2 = parse_itk_transform(euler), parse_itk_transform(versor)
    assert np.allclose(m1, m2, atol=1e-12)
    assert np.allclose(m1[:3, :3], axis_angle_matrix([0, 0, 1], 10), atol=1e-12)
    centre_ras = np.array([-20.0, 30.0, 5.0])
    assert np.allclose(m1[:3, :3] @ centre_ras + m1[:3, 3], centre_ras, atol=1e-12)
    # Euler3D composes Rz Rx Ry by default and Rz Ry Rx with ComputeZYX.
    ax, ay = 0.1, 0.2
    base = "#Insight Transform File V1.0\n#Transform 0\nTransform: Euler3DTransform_double_3_3\n"
    zxy = parse_itk_transform(base + f"Parameters: {ax} {ay} 0 0 0 0\nFixedParameters: 0 0 0 0\n")
    zyx = parse_itk_transform(base + f"Parameters: {ax} {ay} 0 0 0 0\nFixedParameters: 0 0 0 1\n")
    f = np.diag([-1.0, -1, 1])
    rx, ry = axis_angle_matrix([1, 0, 0], math.degrees(ax)), axis_angle_matrix([0, 1, 0], math.degrees(ay))
    assert np.allclose(zxy[:3, :3], f @ (rx @ ry).T @ f, atol=1e-12)
    assert np.allclose(zyx[:3, :3], f @ (ry @ rx).T @ f, atol=1e-12)


def test_itk_round_trip():
    m = np.eye(4)
    m[:3, :3] = euler_matrix([3, -4, 5])
    m[:3, 3] = [1, 2, 3]
    assert np.allclose(parse_itk_transform(format_itk_transform(m)), m, atol=1e-12)


def test_options_muscles_model_and_cut_planes():
    plan = plan_of({"chin": {"translation": [0, 3, 0], "from": "mandible",
                             "cut_planes": [{"point": [0, 0, -40], "normal": [0, 0, -2]}]}},
                   muscles={"mentalis": 0.2}, model={"resolution": "coarse", "sliding": ["maxilla"]})
    sp = plan.segments["chin"]
    assert sp.source == "mandible" and np.allclose(sp.cut_planes[0].normal, [0, 0, -1])
    assert sp.cut_planes[0].keeps(np.array([[0, 0, -50.0], [0, 0, -30.0]])).tolist() == [True, False]
    assert plan.muscles == {"mentalis": 0.2}
    assert plan.model.resolution == "coarse" and plan.model.sliding == ("maxilla",)
    assert plan.model.neck == "free"                      # the default: the cut is traction-free
    assert plan_of({}, model={"neck": "held"}).model.neck == "held"
    assert plan.model.floor == "free"                     # the floor of the mouth likewise
    assert plan_of({}, model={"floor": "held"}).model.floor == "held"
    assert plan.model.proximal == "seated"                # a moved mandible is a sagittal split
    assert plan_of({}, model={"proximal": "moved"}).model.proximal == "moved"
    assert set(plan.motions()) == {"chin"}
    assert plan_of({}).motions() == {}


BAD = [
    ({"faceplan": 1, "segmnts": {}}, "segmnts"),
    ({"faceplan": 1, "segments": {"maxila": {"translation": [0, 1, 0]}}}, "segments.maxila"),
    ({"faceplan": 1, "segments": {"maxilla": {"translaton": [0, 1, 0]}}}, "segments.maxilla.translaton"),
    ({"faceplan": 1, "segments": {"mandible": {"matrix": [[1, 0.1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}}},
     "segments.mandible.matrix"),
    ({"faceplan": 1, "segments": {"mandible": {"matrix": [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}}},
     "segments.mandible.matrix"),
    ({"faceplan": 1, "segments": {"mandible": {"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}}},
     "segments.mandible.matrix"),
    ({"faceplan": 1, "segments": {"maxilla": {"translation": [0, float("nan"), 0]}}}, "segments.maxilla.translation[1]"),
    ({"faceplan": 1, "segments": {"maxilla": {"translation": [0, float("inf"), 0]}}}, "segments.maxilla.translation[1]"),
    ({"faceplan": 1, "segments": {"maxilla": {"translation": [0, 30, 0]}}}, "segments.maxilla.translation"),
    ({"faceplan": 1, "segments": {"maxilla": {"rotation": {"axis": [1, 0, 0], "angle_deg": 31}}}}, "segments.maxilla"),
    ({"faceplan": 2, "segments": {}}, "faceplan"),
    ({"segments": {}}, "faceplan"),
    ({"faceplan": 1, "frame": "RAI"}, "frame"),
    ({"faceplan": 1, "muscles": {"mentalis": 1.5}}, "muscles.mentalis"),
    ({"faceplan": 1, "muscles": {"masseter": 0.5}}, "muscles.masseter"),
    ({"faceplan": 1, "model": {"resolution": "ultra"}}, "model.resolution"),
    ({"faceplan": 1, "model": {"neck": "fixed"}}, "model.neck"),
    ({"faceplan": 1, "model": {"floor": "tied"}}, "model.floor"),
    ({"faceplan": 1, "model": {"proximal": "fixed"}}, "model.proximal"),
    ({"faceplan": 1, "segments": {"skull": {"translation": [0, 1, 0]}}}, "segments.skull"),
    ({"faceplan": 1, "segments": {"chin": {"matrix": [[1, 0, 0, 0]] * 4, "translation": [0, 1, 0]}}}, "segments.chin"),
    ({"faceplan": 1, "segments": {"chin": {"itk_transform": "missing.tfm"}}}, "segments.chin.itk_transform"),
    ({"faceplan": 1, "segments": {"chin": {"rotation": {"axis": [0, 0, 0], "angle_deg": 3}}}}, "segments.chin.rotation.axis"),
]


@pytest.mark.parametrize("data,fieldname", BAD)
def test_bad_plans_name_file_and_field(tmp_path, data, fieldname):
    p = write_plan(tmp_path, data)
    with pytest.raises(InputError) as err:
        load_plan(p)
    assert err.value.file == "plan.yaml"
    assert err.value.field == fieldname
    assert "plan.yaml" in str(err.value) and fieldname in str(err.value)


def test_limits_can_be_raised_explicitly(tmp_path):
    data = {"faceplan": 1, "segments": {"maxilla": {"translation": [0, 30, 0]}}}
    with pytest.raises(InputError):
        load_plan(write_plan(tmp_path, data))
    assert load_plan(write_plan(tmp_path, data), max_translation_mm=40).segments["maxilla"].matrix[1, 3] == 30
    data["limits"] = {"translation_mm": 35}
    assert load_plan(write_plan(tmp_path, data)).max_translation_mm == 35


def test_yaml_syntax_error_and_empty_file(tmp_path):
    for text in ["faceplan: 1\nsegments: {maxilla: [\n", "", "just text"]:
        with pytest.raises(InputError) as err:
            load_plan(write_plan(tmp_path, text))
        assert "plan.yaml" in str(err.value)


def test_check_against_bones():
    bones = {"skull": np.zeros((1, 3)), "maxilla": np.array([[0.0, 60, -20], [0, 70, -25]])}
    plan = plan_of({"maxilla": {"translation": [0, 4, 0]}})
    assert check_against_bones(plan, bones)["maxilla"] == pytest.approx(4.0, abs=1e-12)
    with pytest.raises(InputError) as err:
        check_against_bones(plan_of({"chin": {"translation": [0, 4, 0]}}), bones)
    assert err.value.field == "segments.chin" and "bone surface" in str(err.value)
    # 20 deg about a centre 100 mm away moves the bone ~34 mm although the translation is 0.
    far = plan_of({"maxilla": {"rotation": {"axis": [1, 0, 0], "angle_deg": 20, "center": [0, -40, -20]}}})
    with pytest.raises(InputError, match="beyond anatomical sense"):
        check_against_bones(far, bones)
    # A segment cut from another surface uses that surface.
    cut = plan_of({"chin": {"translation": [0, 2, 0], "from": "maxilla",
                            "cut_planes": [{"point": [0, 0, -22], "normal": [0, 0, -1]}]}})
    assert check_against_bones(cut, bones)["chin"] == pytest.approx(2.0)
