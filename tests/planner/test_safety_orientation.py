"""A head whose face looks along -y is refused, whatever brought it there.

An LPS (DICOM) frame read as RAS turns the head 180 degrees about the vertical axis: the face
looks along -y. `planner.case.face_direction` tells it from the anatomy -- the skin's nose is
its narrow extreme, the back of the head a broad cap -- so it works on a CT's skin (where the
one `bone` surface gives no anterior direction) and on a skin given alone (no landmarks to
contradict it). Checked on the embedded demo head as a CT phantom (NIfTI with an LPS or a
front-to-back affine, a DICOM series with flipped orientation) and as surfaces (the skin alone
in LPS, no landmarks), and on heads of other seeds than the demo's (held out) in both
directions.
"""
import shutil

import numpy as np
import pytest
import trimesh

from planner.case import face_direction, load_case
from planner.errors import InputError
from planner.pipeline import DEMO_HEAD, write_demo_case

LPS = np.diag([-1.0, -1.0, 1.0, 1.0])
Y_FLIP = np.diag([1.0, -1.0, 1.0, 1.0])


def _demo_surfaces():
    d = np.load(DEMO_HEAD)
    skin = trimesh.Trimesh(d["skin_vertices"].astype(float), d["skin_faces"])
    bones = {k[5:-9]: trimesh.Trimesh(d[k].astype(float), d[k[:-9] + "_faces"])
             for k in d.files if k.startswith("bone_") and k.endswith("_vertices")}
    return skin, bones


@pytest.fixture(scope="module")
def phantom():
    from facemodel.ct_phantom import ct_volume_from_surfaces

    skin, bones = _demo_surfaces()
    # 3 mm voxels: coarse, but the nose (~25 mm across) spans eight of them
    return ct_volume_from_surfaces(skin, bones, spacing=(3.0, 3.0, 3.0), margin=6, seed=1)


def _ct_case(root, hu, affine, dicom=False):
    from facemodel.ct_phantom import write_dicom_series, write_nifti

    (root / "preop").mkdir(parents=True)
    if dicom:
        write_dicom_series(root / "preop" / "ct", hu, affine)
    else:
        write_nifti(root / "preop" / "ct.nii.gz", hu, affine)
    (root / "plan.yaml").write_text("faceplan: 1\nframe: RAS\nsegments: {}\n")
    return root


def test_ras_ct_is_accepted(phantom, tmp_path):
    hu, affine = phantom
    case = load_case(_ct_case(tmp_path / "c", hu, affine), cache=False)
    assert face_direction(case.skin)[0] == 1


def test_backwards_dicom_is_refused(phantom, tmp_path):
    hu, affine = phantom
    case = _ct_case(tmp_path / "c", hu, Y_FLIP @ affine, dicom=True)
    with pytest.raises(InputError, match="looks along -y") as info:
        load_case(case, cache=False)
    assert info.value.file.endswith("preop/ct") and info.value.field == "ImageOrientationPatient"


def test_lps_nifti_exits_2_before_work(phantom, tmp_path, capsys, monkeypatch):
    from planner.cli import main

    monkeypatch.setenv("FACEPLAN_CACHE", str(tmp_path / "cache"))
    hu, affine = phantom
    case = _ct_case(tmp_path / "c", hu, LPS @ affine)
    assert main(["register", str(case), "--resolution", "coarse", "--no-images"]) == 2
    err = capsys.readouterr().err
    assert "ct.nii.gz" in err and "field affine" in err and "looks along -y" in err and "sform" in err
    assert "Traceback" not in err and not (case / "register").exists()


@pytest.fixture
def demo_case(tmp_path_factory, tmp_path):
    template = tmp_path_factory.getbasetemp() / "orientation-demo"
    if not template.exists():
        write_demo_case(template)
    c = tmp_path / "case"
    shutil.copytree(template, c)
    return c


@pytest.mark.parametrize("shift", [0.0, 15.0])
def test_lps_skin_with_ras_bones_and_no_landmarks(demo_case, shift):
    # the flipped closed skin still encloses the bones: only the anatomy tells
    f = demo_case / "preop" / "skin.stl"
    m = trimesh.load(f, force="mesh", process=False)
    trimesh.Trimesh(m.vertices * [-1.0, -1.0, 1.0] + [0.0, shift, 0.0], m.faces, process=False).export(f)
    (demo_case / "preop" / "landmarks.json").unlink()
    with pytest.raises(InputError, match="looks along -y") as info:
        load_case(demo_case)
    assert info.value.file.endswith("skin.stl") and info.value.field == "skin"


@pytest.mark.parametrize("seed", [3, 11, 40])
def test_face_direction_of_held_out_heads(seed):
    from facemodel.synthetic import synthetic_head

    skin = synthetic_head(seed, size=6.0).skin
    assert face_direction(skin)[0] == 1
    for flip in (LPS, Y_FLIP):
        assert face_direction(trimesh.Trimesh(skin.vertices @ flip[:3, :3], skin.faces[:, ::-1]))[0] == -1


def test_no_verdict_without_evidence():
    # a symmetric head-sized ellipsoid and an open face-only surface: nothing is concluded
    ball = trimesh.creation.icosphere(subdivisions=3)
    ball.vertices = ball.vertices * [70.0, 90.0, 110.0]
    assert face_direction(ball)[0] == 0
    skin, _ = _demo_surfaces()
    face = skin.submesh([skin.triangles_center[:, 1] > 20.0], append=True)
    assert not face.is_watertight and face_direction(face)[0] == 0
