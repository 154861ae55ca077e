"""End to end: a case folder holding only a CT loads to the same skin as the surfaces the CT
came from.

Two case folders are written from one synthetic patient (`facemodel.synthetic`, coarse
meshing): one as planning software exports it (`preop/skin.stl`, `preop/bone/*.stl`,
landmarks), one with only `preop/ct.nii.gz` (a CT-like volume of the same surfaces,
`facemodel.ct_phantom`) and the landmarks. `load_case` must give the same skin from both.
"""
import json

import numpy as np
import pytest
import trimesh

synthetic = pytest.importorskip("facemodel.synthetic")

from facemodel.ct_phantom import ct_volume_from_surfaces, write_nifti  # noqa: E402
from planner.case import load_case  # noqa: E402


def ellipsoid(axes, centre):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    mesh.vertices = mesh.vertices * np.asarray(axes, float) + np.asarray(centre, float)
    return mesh


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    shape = synthetic.random_shape(5)
    skin = synthetic.skin_surface(shape, size=6.0, distance=0.5, seed=5)
    # Bone stand-ins well inside the head (cranium and mandible): the test is about the skin;
    # the CT route only needs bone to be present.
    bones = {"skull": ellipsoid((50, 65, 60), (0, -5, 30)),
             "mandible": ellipsoid((28, 18, 9), (0, 50, -72))}
    landmarks = {k: [float(x) for x in v] for k, v in synthetic.landmarks(shape).items()}
    root = tmp_path_factory.mktemp("e2e")
    surf, from_ct = root / "surfaces", root / "ct_only"
    (surf / "preop" / "bone").mkdir(parents=True)
    (from_ct / "preop").mkdir(parents=True)
    skin.export(surf / "preop" / "skin.stl")
    for name, mesh in bones.items():
        mesh.export(surf / "preop" / "bone" / f"{name}.stl")
    hu, affine = ct_volume_from_surfaces(skin, bones, spacing=(1.5, 1.5, 1.5), margin=8, seed=5)
    write_nifti(from_ct / "preop" / "ct.nii.gz", hu, affine)
    for case in (surf, from_ct):
        (case / "preop" / "landmarks.json").write_text(json.dumps(landmarks))
        (case / "plan.yaml").write_text("faceplan: 1\nframe: RAS\nsegments: {}\n")
    return load_case(surf), load_case(from_ct, cache=False)


def test_ct_only_case_has_the_same_skin(cases):
    surfaces, ct_only = cases
    assert not surfaces.from_ct and ct_only.from_ct
    assert ct_only.skin_path.name == "ct.nii.gz" and list(ct_only.bones) == ["bone"]
    assert sorted(ct_only.landmarks) == sorted(surfaces.landmarks)
    assert ct_only.plan_path is not None
    # 0.5 mm mean both ways (the figure; observed ~0.15 mm on 1.5 mm voxels), and the
    # 95th percentile within a voxel so that no part of the face (nose, lips) is lost.
    a, b = surfaces.skin, ct_only.skin
    sample = b.vertices[np.random.default_rng(0).choice(len(b.vertices), 3000, replace=False)]
    _, forward, _ = trimesh.proximity.closest_point(a, sample)
    _, backward, _ = trimesh.proximity.closest_point(b, a.vertices)
    for d in (forward, backward):
        assert d.mean() < 0.5 and np.percentile(d, 95) < 1.5, (d.mean(), np.percentile(d, 95))
    # The landmarks lie on both skins alike: no farther from the CT skin than from the source
    # skin plus one voxel (1.5 mm). The worst is stomion inferius (observed +0.9 mm): the
    # slit between the lips is narrower than a voxel, so the CT closes it, as real CTs do.
    names = sorted(surfaces.landmarks)
    points = np.array([surfaces.landmarks[n] for n in names])
    _, on_ct_skin, _ = trimesh.proximity.closest_point(b, points)
    _, on_skin, _ = trimesh.proximity.closest_point(a, points)
    assert np.all(on_ct_skin < on_skin + 1.5), dict(zip(names, on_ct_skin - on_skin))
    # Bone volume: the two stand-ins' union plus the +300 HU threshold's outward offset
    # ((520 - 300) / 960 * 1.5 = 0.34 mm over their area), to 3 %.
    bones = list(surfaces.bones.values())
    expected = sum(m.volume + 0.34 * m.area for m in bones)
    assert ct_only.bones["bone"].volume == pytest.approx(expected, rel=0.03)
