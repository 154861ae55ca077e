"""The superquadric head family (facemodel.synthetic_alt): closed skin, bones under it,
landmarks on it, face crops that are open and end where asked, deterministic by seed."""
import dataclasses

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")
from facemodel import synthetic_alt as sa  # noqa: E402


@pytest.fixture(scope="module")
def head():
    return sa.alt_head(7, subdivisions=5)


def test_skin_closed_and_bones_inside(head):
    assert head.skin.is_watertight and head.skin.volume > 0
    for seg, b in head.bones.items():
        assert b.is_watertight and b.volume > 0, seg
        # every bone vertex under the skin: the thickness map is at least 4 mm
        assert head.skin.contains(b.vertices[::29]).all(), seg
        _, d, _ = trimesh.proximity.closest_point(head.skin, b.vertices[::7])
        # 4 mm along the ray from the centre; where the ray meets the skin obliquely (the skull
        # top) the normal distance is smaller, by cos 45 deg at most on these shells
        assert d.min() > 4.0 * np.cos(np.radians(45.0)), seg


def test_landmarks_on_skin_and_in_anatomical_order(head):
    pts = np.array(list(head.landmarks.values()))
    _, d, _ = trimesh.proximity.closest_point(head.skin, pts)
    assert d.max() < 1e-6
    lm = head.landmarks
    # the profile from top to bottom, in the head's frame (a few degrees of pose at most)
    z = [lm[k][2] for k in ("Prn", "Sn", "Ls", "Stms", "Stmi", "Li", "Pog", "Me")]
    assert all(a > b for a, b in zip(z, z[1:]))
    assert lm["Prn"][1] > lm["Sn"][1] + 5.0          # the nose stands out of the lip
    assert 30.0 < np.linalg.norm(lm["ChL"] - lm["ChR"]) < 70.0


def test_deterministic_and_varied():
    a, b = sa.random_alt_shape(3), sa.random_alt_shape(3)
    assert a == b and a != sa.random_alt_shape(4)


@pytest.mark.parametrize("cut", list(sa.CUTS))
def test_crop_is_open_face_below_the_cut(head, cut):
    c = sa.crop_face(head, cut)
    v = np.asarray(c.skin.vertices)
    local = sa.CENTRE + (v - sa.CENTRE) @ sa._pose(head.shape)
    assert local[:, 2].max() < sa.CUTS[cut] and local[:, 1].min() > 30.0
    assert not c.skin.is_watertight and len(c.skin.split(only_watertight=False)) == 1
    # the face down under the chin is there: menton is on the cropped skin
    _, d, _ = trimesh.proximity.closest_point(c.skin, head.landmarks["Me"][None])
    assert d[0] < 1e-6


def test_written_case_loads(tmp_path, head):
    from planner.case import load_case
    from planner.commands import synth

    folder = tmp_path / "alt_case"
    folder.mkdir()
    # the writer of `faceplan synth --head-family alt`, with the plan it draws for such heads
    synth.write_case(folder, sa.crop_face(head, "below_eyes"), plan=synth.bone_plan(head, head.seed))
    case = load_case(folder)
    assert set(case.bones) == {"skull", "maxilla", "mandible", "chin"}
    assert set(case.landmarks) == set(head.landmarks) - set(head.ill_defined)
    # a landmark whose definition has no anatomical answer on the head is not given
    flagged = dataclasses.replace(sa.crop_face(head, "below_eyes"), ill_defined=("Li",))
    (tmp_path / "flagged").mkdir()
    synth.write_case(tmp_path / "flagged", flagged, plan=synth.bone_plan(head, head.seed))
    assert set(load_case(tmp_path / "flagged").landmarks) == set(head.landmarks) - {"Li"}


def test_labrale_inferius_flagged_where_the_lower_lip_has_no_prominence():
    """Li, "the most anterior point of the lower lip", has no anatomical answer where the lower
    lip's roll stands behind the fissure's lower edge: the definition gives that edge, and the
    head flags it (benchmarks judge it apart). On the exact profile of 40 shapes: a flagged
    head's Li is the fissure's edge and the profile recedes from it; an unflagged head's Li is
    a prominence more than 2 mm below the fissure, in front of its edge. Both kinds occur
    (about a quarter of the heads are flagged)."""
    kinds = set()
    for seed in range(40):
        s = sa.random_alt_shape(seed)
        flagged = "Li" in sa.ill_defined_landmarks(s)
        kinds.add(flagged)
        _, pts = sa._profile(s)
        i_li, prominent = sa._labrale_inferius(pts, s)
        assert flagged == (not prominent)
        top = np.flatnonzero(pts[:, 2] < s.mouth_z - 0.4)[0]       # the fissure's lower edge
        if flagged:
            assert i_li == top
            assert pts[top + 1, 1] < pts[top, 1]                      # receding from the edge
        else:
            assert pts[top, 2] - pts[i_li, 2] > 2.0
            assert pts[i_li, 1] > pts[top, 1]
    assert kinds == {True, False}
