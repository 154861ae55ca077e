"""The case-folder reader: a good case loads in every surface format, each class of bad input
is refused with an `InputError` naming the file and the field, and 3D Slicer markups in LPS
and RAS give the same RAS landmarks."""
import json
import shutil

import numpy as np
import pytest
import trimesh

from planner.case import Case, load_case, load_landmarks, load_surface
from planner.errors import InputError


def ellipsoid(axes, centre, subdivisions=3):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    mesh.vertices = mesh.vertices * np.asarray(axes, float) + np.asarray(centre, float)
    return mesh


SKIN = ellipsoid((70, 90, 110), (0, 0, 0))                       # a head-sized skin
BONES = {"skull": ellipsoid((55, 70, 60), (0, -5, 35)),
         "maxilla": ellipsoid((25, 15, 12), (0, 55, -20)),
         "mandible": ellipsoid((35, 20, 15), (0, 45, -60))}
# On the skin: the anterior pole (y = +90) and points of the ellipsoid surface.
LANDMARKS = {"Prn": [0.0, 90.0, 0.0], "Pog": [0.0, 90 * np.sqrt(1 - 0.6 ** 2), -66.0],
             "ChR": [70 * 0.3, 90 * np.sqrt(1 - 0.3 ** 2), 0.0]}


def write_case(root, skin_ext="stl"):
    (root / "preop" / "bone").mkdir(parents=True)
    SKIN.export(root / "preop" / f"skin.{skin_ext}") if skin_ext in ("stl", "ply", "obj", "off") \
        else _vtk_export(SKIN, root / "preop" / f"skin.{skin_ext}")
    for name, mesh in BONES.items():
        mesh.export(root / "preop" / "bone" / f"{name}.stl")
    (root / "preop" / "landmarks.json").write_text(json.dumps(LANDMARKS))
    (root / "plan.yaml").write_text("faceplan: 1\nframe: RAS\nsegments: {}\n")
    (root / "case.yaml").write_text("id: P001\nfollow_up_months: 12\nnotes: bimaxillary\n")
    return root


def _vtk_export(mesh, path):
    import pyvista as pv

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel()
    poly = pv.PolyData(np.asarray(mesh.vertices), faces)
    if path.suffix == ".vtu":
        poly = poly.cast_to_unstructured_grid()
    poly.save(str(path))


@pytest.fixture()
def case_dir(tmp_path):
    return write_case(tmp_path / "case")


def test_good_case(case_dir):
    case = load_case(case_dir)
    assert isinstance(case, Case)
    assert case.root == case_dir
    assert sorted(case.bones) == ["mandible", "maxilla", "skull"]
    assert case.skin.is_watertight
    # Surfaces come back vertex for vertex (STL keeps float32: 1e-5 mm).
    np.testing.assert_allclose(np.sort(case.skin.vertices, axis=0), np.sort(SKIN.vertices, axis=0),
                               atol=1e-4)
    assert case.skin.volume == pytest.approx(SKIN.volume, rel=1e-6)
    np.testing.assert_allclose(case.landmarks["Prn"], LANDMARKS["Prn"])
    assert case.plan_path == case_dir / "plan.yaml"
    assert case.info.id == "P001" and case.info.follow_up_months == 12.0
    assert case.info.notes == "bimaxillary"
    assert case.postop_skin is None and case.postop_plan_path is None and not case.from_ct
    assert case.teeth == {}


def test_teeth_are_optional_parts(case_dir):
    (case_dir / "preop" / "teeth").mkdir()
    arch = ellipsoid((25, 20, 5), (0, 60, -40))
    arch.export(case_dir / "preop" / "teeth" / "upper.stl")
    case = load_case(case_dir)
    assert list(case.teeth) == ["upper"]
    assert case.teeth["upper"].volume == pytest.approx(arch.volume, rel=1e-6)
    (case_dir / "preop" / "teeth" / "lower.txt").write_text("x")
    refused(case_dir, "not a surface file", field="teeth")


def test_postop_is_loaded_lazily(case_dir):
    (case_dir / "postop").mkdir()
    partial = SKIN.copy()
    partial.update_faces(partial.triangles_center[:, 1] > 0)   # a front-only scan, open
    partial.export(case_dir / "postop" / "skin.stl")
    (case_dir / "postop" / "plan_actual.yaml").write_text("faceplan: 1\nsegments: {}\n")
    case = load_case(case_dir)
    assert "postop_skin" not in case.__dict__
    assert case.postop_skin is not None and not case.postop_skin.is_watertight
    assert case.postop_skin.area == pytest.approx(partial.area, rel=1e-6)
    assert case.postop_plan_path.name == "plan_actual.yaml"


@pytest.mark.parametrize("ext", ["ply", "obj", "off", "vtk", "vtp", "vtu"])
def test_every_surface_format(tmp_path, ext):
    case = load_case(write_case(tmp_path / "c", ext))
    # Same closed surface whatever the format: area to 1e-6 (float32 storage in some).
    assert case.skin.area == pytest.approx(SKIN.area, rel=1e-6)
    assert len(case.skin.faces) == len(SKIN.faces)


# ---------------------------------------------------------------------------------- bad input
def refused(path, *words, field=None):
    with pytest.raises(InputError) as err:
        load_case(path)
    for w in words:
        assert w in str(err.value), str(err.value)
    if field is not None:
        assert err.value.field == field, err.value.field
    assert err.value.file
    return err.value


def test_missing_folder_and_files(case_dir, tmp_path):
    refused(tmp_path / "nowhere", "no such case folder")
    (tmp_path / "a_file").write_text("x")
    refused(tmp_path / "a_file", "a case is a folder")
    shutil.rmtree(case_dir / "preop" / "bone")
    refused(case_dir, "bone", field="bone")
    (case_dir / "preop" / "bone").mkdir()
    refused(case_dir, "no bone surface", field="bone")
    (case_dir / "preop" / "skin.stl").unlink()
    refused(case_dir, "no pre-op skin", field="skin")
    shutil.rmtree(case_dir / "preop")
    refused(case_dir, "no preop/", field="preop")


def test_unreadable_and_empty_surfaces(case_dir):
    skin = case_dir / "preop" / "skin.stl"
    skin.write_bytes(b"\x00\x01garbage" * 7)
    refused(case_dir, "skin", field="skin")
    skin.write_text("solid empty\nendsolid empty\n")
    refused(case_dir, "empty", field="skin")
    skin.unlink()
    SKIN.export(case_dir / "preop" / "skin.stl")
    bad_bone = case_dir / "preop" / "bone" / "chin.ply"
    bad_bone.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n")
    refused(case_dir, "bone.chin", field="bone.chin")
    bad_bone.unlink()
    (case_dir / "preop" / "bone" / "notes.txt").write_text("hello")
    refused(case_dir, "not a surface file", field="bone")


def test_nan_coordinates(case_dir):
    bone = BONES["maxilla"].copy()
    vertices = bone.vertices.copy()
    vertices[5] = np.nan
    with open(case_dir / "preop" / "bone" / "maxilla.obj", "w") as f:
        f.writelines(f"v {x} {y} {z}\n" for x, y, z in vertices)
        f.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in bone.faces)
    (case_dir / "preop" / "bone" / "maxilla.stl").unlink()
    refused(case_dir, "NaN", field="bone.maxilla")


def test_metres_are_refused(case_dir):
    metres = SKIN.copy()
    metres.vertices = metres.vertices / 1000.0
    metres.export(case_dir / "preop" / "skin.stl")
    err = refused(case_dir, "looks like metres: multiply by 1000", field="skin")
    assert err.file.endswith("skin.stl")
    # load_surface is usable alone (compare/registration read scans through it).
    with pytest.raises(InputError, match="looks like metres"):
        load_surface(case_dir / "preop" / "skin.stl", "postop skin")
    with pytest.raises(InputError, match="unsupported surface format"):
        load_surface(case_dir / "plan.yaml", "scan")


def test_two_skin_files_are_ambiguous(case_dir):
    SKIN.export(case_dir / "preop" / "skin.ply")
    refused(case_dir, "several files", field="skin")


@pytest.mark.parametrize("text, words", [
    ("id: P1\nfollow_up: 12\n", "unknown key(s) follow_up"),
    ("follow_up_months: -3\n", "follow_up_months must be"),
    ("follow_up_months: .nan\n", "follow_up_months must be"),
    ("- a list\n", "expected a mapping"),
    ("id: [1, 2]\n", "id must be"),
    ("id: P1\n  bad: indentation: here\n", "unreadable YAML"),
    ("ct: {skin_hu: low}\n", "ct.skin_hu must be a number"),
    ("ct: {level: 3}\n", "ct: unknown key level"),
    ("ct: {skin_hu: 500, bone_hu: 300}\n", "must be below"),
    ("ct: [1, 2]\n", "ct must be a mapping"),
])
def test_bad_case_yaml(case_dir, text, words):
    (case_dir / "case.yaml").write_text(text)
    refused(case_dir, words)


@pytest.mark.parametrize("content, words", [
    ({"Prn": [0, 90]}, "three coordinates"),
    ({"Prn": [0, "a", 1]}, "three coordinates"),
    ({"Prn": [0, float("nan"), 1]}, "NaN"),
    ([[0, 90, 0]], "expected an object"),
    ({}, "expected an object"),
    ({"Prn": [0, 290, 0]}, "wrong coordinate system"),      # 200 mm in front of the nose
])
def test_malformed_landmarks(case_dir, content, words):
    (case_dir / "preop" / "landmarks.json").write_text(json.dumps(content))
    refused(case_dir, words)


def test_landmarks_not_json(case_dir):
    (case_dir / "preop" / "landmarks.json").write_text("{Prn: 1,")
    refused(case_dir, "unreadable json", field="landmarks")


# ---------------------------------------------------------------------------- Slicer markups
def markups(points, system=None, **extra):
    markup = {"type": "Fiducial", "coordinateUnits": "mm", "controlPoints": [
        {"id": str(i + 1), "label": name, "position": list(p), "positionStatus": "defined"}
        for i, (name, p) in enumerate(points.items())], **extra}
    if system is not None:
        markup["coordinateSystem"] = system
    return {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
                       "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
            "markups": [markup]}


def lps(p):
    return [-p[0], -p[1], p[2]]


@pytest.mark.parametrize("system", ["LPS", "RAS", None])
def test_slicer_markups_in_both_frames(case_dir, system):
    points = LANDMARKS if system == "RAS" else {k: lps(v) for k, v in LANDMARKS.items()}
    (case_dir / "preop" / "landmarks.json").unlink()
    (case_dir / "preop" / "landmarks.mrk.json").write_text(json.dumps(markups(points, system)))
    case = load_case(case_dir)   # a missing coordinateSystem means LPS, as in Slicer
    assert sorted(case.landmarks) == sorted(LANDMARKS)
    for name, p in LANDMARKS.items():
        np.testing.assert_allclose(case.landmarks[name], p, atol=1e-12)


def test_slicer_markups_lps_read_as_ras_is_caught_on_a_face_surface(case_dir):
    # Planning software often exports the face only (an open surface): the same LPS
    # coordinates declared RAS then fall behind the face, far from any skin, and are refused.
    face = SKIN.copy()
    face.update_faces(face.triangles_center[:, 1] > 20)
    face.export(case_dir / "preop" / "skin.stl")
    points = {k: lps(v) for k, v in LANDMARKS.items()}
    (case_dir / "preop" / "landmarks.json").write_text(json.dumps(markups(points, "RAS")))
    refused(case_dir, "wrong coordinate system", field="landmarks.Prn")
    (case_dir / "preop" / "landmarks.json").write_text(json.dumps(markups(points, "LPS")))
    np.testing.assert_allclose(load_case(case_dir).landmarks["Prn"], LANDMARKS["Prn"])


def test_slicer_markups_details(tmp_path):
    path = tmp_path / "l.mrk.json"
    data = markups({"Prn": [0, -90, 0], "Sn": [1, -80, -10]}, "LPS")
    data["markups"][0]["controlPoints"].append(
        {"id": "3", "label": "Pog", "position": [0, 0, 0], "positionStatus": "undefined"})
    path.write_text(json.dumps(data))
    got = load_landmarks(path)
    assert sorted(got) == ["Prn", "Sn"]      # the unplaced point is skipped
    np.testing.assert_allclose(got["Sn"], [-1, 80, -10])
    data = markups({"Prn": [0, -90000, 0]}, "LPS", coordinateUnits="um")
    path.write_text(json.dumps(data))
    np.testing.assert_allclose(load_landmarks(path)["Prn"], [0, 90, 0])
    for bad, words in [
        (markups({"Prn": [0, 1, 2]}, "XYZ"), "neither LPS nor RAS"),
        (markups({"Prn": [0, 1, 2]}, "LPS", coordinateUnits="m"), "coordinateUnits"),
        (markups({"": [0, 1, 2]}, "LPS"), "without a label"),
        (markups({"Prn": [0, 1]}, "LPS"), "three coordinates"),
        ({"markups": [{"controlPoints": []}]}, "no placed control point"),
        ({"markups": "x"}, "must be a list"),
    ]:
        path.write_text(json.dumps(bad))
        with pytest.raises(InputError, match=words):
            load_landmarks(path)
    twice = markups({"Prn": [0, 1, 2]}, "LPS")
    twice["markups"][0]["controlPoints"] *= 2
    path.write_text(json.dumps(twice))
    with pytest.raises(InputError, match="appears twice"):
        load_landmarks(path)


# ------------------------------------------------------------------------------------ CT cases
@pytest.fixture(scope="module")
def ct_case(tmp_path_factory):
    from facemodel.ct_phantom import ct_volume_from_surfaces, write_nifti

    root = tmp_path_factory.mktemp("ctcase") / "case"
    (root / "preop").mkdir(parents=True)
    hu, affine = ct_volume_from_surfaces(SKIN_FINE, BONES, spacing=(2.0, 2.0, 2.0), margin=6,
                                         seed=4)
    write_nifti(root / "preop" / "ct.nii.gz", hu, affine)
    (root / "preop" / "landmarks.json").write_text(json.dumps(LANDMARKS))
    return root, hu.shape, affine


@pytest.fixture(scope="module")
def ct_loaded(ct_case):
    return load_case(ct_case[0], cache=False)


# The CT phantom's skin: the same ellipsoid finely facetted (chord error 0.02 mm), so that
# the extracted skin can be compared with the analytic ellipsoid.
SKIN_AXES = np.array([70.0, 90.0, 110.0])
SKIN_FINE = ellipsoid(SKIN_AXES, (0, 0, 0), subdivisions=5)


def signed_distance_to_skin(points):
    """(F - 1) / |grad F|, F = sum (x/a)^2: the signed distance to the ellipsoid up to
    d^2 / (2 R) with R >= 70^2 / 110 = 44 mm, i.e. < 0.02 mm for |d| < 1.3 mm."""
    u = points / SKIN_AXES
    return ((u ** 2).sum(axis=1) - 1.0) / np.linalg.norm(2 * u / SKIN_AXES, axis=1)


def test_case_from_ct_only(ct_case, ct_loaded):
    from facemodel.ct_phantom import occupancy

    root, shape, affine = ct_case
    case = ct_loaded
    assert case.from_ct and case.ct_path.name == "ct.nii.gz"
    assert list(case.bones) == ["bone"] and case.plan_path is None
    # 2 mm voxels: the skin comes back within 0.5 mm mean (observed ~0.2 mm; the -400 HU
    # threshold alone shifts it 0.15 mm inwards at this spacing), both ways.
    assert np.abs(signed_distance_to_skin(case.skin.vertices)).mean() < 0.5
    _, back, _ = trimesh.proximity.closest_point(case.skin, SKIN.vertices)   # 642 points
    assert back.mean() < 0.5
    # One bone surface for the union of the three (disjoint) segments: three closed parts, and
    # the volume it adds to the union's exact partial-volume integral, spread over its area, is
    # the +300 HU threshold's outward offset on 2 mm voxels, (520 - 300) / 960 * 2 = 0.46 mm,
    # within 0.15 mm (observed 0.52 mm); losing the maxilla would move it by 0.3 mm.
    bone = case.bones["bone"]
    assert len(bone.split(only_watertight=False)) == 3
    union = occupancy(list(BONES.values()), shape, affine).sum() * np.prod(np.diag(affine)[:3])
    assert (bone.volume - union) / bone.area == pytest.approx(0.46, abs=0.15)
    with pytest.raises(InputError, match="no plan.yaml"):
        case.require_plan()


def test_bad_ct_is_an_input_error(tmp_path):
    (tmp_path / "c" / "preop").mkdir(parents=True)
    (tmp_path / "c" / "preop" / "ct.nii.gz").write_bytes(b"not a volume" * 30)
    err = refused(tmp_path / "c", "cannot read NIfTI", field="preop CT")
    assert err.file.endswith("ct.nii.gz")


@pytest.mark.parametrize("system", ["LPS", "RAS", "1", "0"])
def test_slicer_fcsv(case_dir, system):
    lps_file = system in ("LPS", "1")
    lines = ["# Markups fiducial file version = 4.11", f"# CoordinateSystem = {system}",
             "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID"]
    for k, (name, p) in enumerate(LANDMARKS.items()):
        x, y, z = lps(p) if lps_file else p
        lines.append(f"vtkMRMLMarkupsFiducialNode_{k},{x},{y},{z},0,0,0,1,1,1,0,{name},,")
    (case_dir / "preop" / "landmarks.json").unlink()
    (case_dir / "preop" / "landmarks.fcsv").write_text("\n".join(lines) + "\n")
    case = load_case(case_dir)
    for name, p in LANDMARKS.items():
        np.testing.assert_allclose(case.landmarks[name], p, atol=1e-9)


def test_two_landmark_files_are_ambiguous(case_dir):
    (case_dir / "preop" / "landmarks.mrk.json").write_text(json.dumps(markups(LANDMARKS, "RAS")))
    refused(case_dir, "two landmark files", field="landmarks")


def test_inward_closed_surfaces_are_turned_outward(case_dir):
    inward = BONES["maxilla"].copy()
    inward.invert()
    assert inward.volume < 0
    inward.export(case_dir / "preop" / "bone" / "maxilla.stl")
    case = load_case(case_dir)
    assert case.bones["maxilla"].volume == pytest.approx(BONES["maxilla"].volume, rel=1e-6)


def test_ct_thresholds_from_case_yaml(ct_case, ct_loaded, tmp_path):
    # At the half-maximum level of the phantom's air/tissue edge, (-1000 + 40) / 2 = -480 HU,
    # the skin has no partial-volume offset: its mean signed distance is within 0.1 mm of 0,
    # while the default -400 HU puts it (80 / 1040) * 2 mm = 0.15 mm inside (2 mm voxels).
    case_dir = tmp_path / "cbct"
    shutil.copytree(ct_case[0], case_dir)
    (case_dir / "case.yaml").write_text("id: cbct\nct: {skin_hu: -480}\n")
    half_max = signed_distance_to_skin(load_case(case_dir, cache=False).skin.vertices).mean()
    default = signed_distance_to_skin(ct_loaded.skin.vertices).mean()
    assert abs(half_max) < 0.1
    assert default == pytest.approx(-0.15, abs=0.1)


def test_ct_surfaces_are_cached_by_content(tmp_path):
    import planner.case as case_module
    from facemodel.ct_phantom import ct_volume_from_surfaces, write_nifti

    cache = tmp_path / "cache"
    root = tmp_path / "case"
    (root / "preop").mkdir(parents=True)
    small_head = ellipsoid((30, 35, 40), (0, 0, 0))
    hu, affine = ct_volume_from_surfaces(small_head, {"b": ellipsoid((15, 15, 15), (0, 0, 5))},
                                         spacing=2.0, margin=4)
    write_nifti(root / "preop" / "ct.nii.gz", hu, affine)
    first = load_case(root, cache_dir=cache)
    stored = sorted(cache.glob("*.npz"))
    assert len(stored) == 1
    np.testing.assert_array_equal(first.skin.vertices, load_case(root, cache=False).skin.vertices)
    # A hit returns the stored arrays exactly; the extraction is not run again.
    calls = []
    original = case_module._surfaces_from_ct.__globals__["_cache_load"]

    def spy(path):
        calls.append(path)
        return original(path)

    case_module._cache_load = spy
    try:
        again = load_case(root, cache_dir=cache)
    finally:
        case_module._cache_load = original
    assert calls == stored
    np.testing.assert_array_equal(again.skin.faces, first.skin.faces)
    np.testing.assert_array_equal(again.bones["bone"].vertices, first.bones["bone"].vertices)
    # Other thresholds: another key. A damaged entry is re-extracted and rewritten.
    (root / "case.yaml").write_text("ct: {bone_hu: 350}\n")
    load_case(root, cache_dir=cache)
    assert len(list(cache.glob("*.npz"))) == 2
    (root / "case.yaml").unlink()
    stored[0].write_bytes(b"damaged")
    np.testing.assert_array_equal(load_case(root, cache_dir=cache).skin.vertices,
                                  first.skin.vertices)
    assert stored[0].stat().st_size > 1000
