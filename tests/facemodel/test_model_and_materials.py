"""FaceModel I/O and derived data, the materials table, the parametric head geometry."""
import numpy as np
import pytest

import generic_mesh
from facemodel import head_geometry as hg
from facemodel import materials
from facemodel.model import LABEL_NAMES, MUSCLES, FaceModel


@pytest.fixture(scope="module")
def coarse():
    return generic_mesh.load("coarse")


def test_save_load_roundtrip(coarse, tmp_path):
    path = tmp_path / "face.vtu"
    coarse.save(path)
    back = FaceModel.load(path)
    np.testing.assert_array_equal(back.nodes, coarse.nodes)
    np.testing.assert_array_equal(back.hexes, coarse.hexes)
    np.testing.assert_array_equal(back.labels, coarse.labels)
    np.testing.assert_array_equal(back.fibres, coarse.fibres)
    assert back.label_names == coarse.label_names and back.segments == coarse.segments
    for d in ("node_sets", "facet_sets", "regions"):
        a, b = getattr(back, d), getattr(coarse, d)
        assert set(a) == set(b)
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
    assert back.landmarks == coarse.landmarks
    for k, (v, f, s) in coarse.teeth.items():
        np.testing.assert_allclose(back.teeth[k][0], v, atol=1e-6)   # stored to 1e-6 mm
        np.testing.assert_array_equal(back.teeth[k][1], f)
        assert back.teeth[k][2] == s


def test_frozen_and_derived(coarse):
    with pytest.raises(AttributeError):
        coarse.nodes = coarse.nodes
    skin = coarse.skin_surface
    assert len(skin.faces) == 2 * len(coarse.facet_sets["skin"])
    moved = coarse.with_nodes(coarse.nodes + [0.0, 1.0, 0.0])
    assert moved.landmark_positions["Prn"][1] == pytest.approx(coarse.landmark_positions["Prn"][1] + 1.0)
    with pytest.raises(ValueError):
        coarse.with_nodes(coarse.nodes[:10])
    reg = coarse.skin_region_of_node
    assert np.all(reg[coarse.node_sets["skin"]] >= 0)
    assert coarse.region_names[reg[coarse.landmarks["Ls"]]] == "upper_lip"


def test_materials_table():
    assert set(materials.MATERIALS) == set(LABEL_NAMES)
    tissue = materials.material("hypodermis").parameters
    assert tissue["C10"] == 2.5 and tissue["C20"] == 1.175
    for label, entry in materials.MATERIALS.items():
        p = entry.parameters
        # K ~ 1000 x the initial shear modulus 2 C10 (nearly incompressible)
        assert p["K"] == pytest.approx(1000.0 * 2.0 * p["C10"])
        assert set(entry.sources) == set(p), label          # every number has a source
        assert all(k in materials.SOURCES for k in entry.sources.values())
        assert entry.law == ("Muscle" if label in MUSCLES else "Yeoh")
    assert materials.material("dermis").shear_modulus > materials.material("hypodermis").shear_modulus
    assert materials.material("orbicularis_oris").parameters["T_max"] == 100.0
    soft = materials.parameters("dermis", stiffness=0.5)
    assert soft["C10"] == pytest.approx(0.5 * materials.material("dermis").parameters["C10"])
    with pytest.raises(KeyError):
        materials.material("bone")


def test_materials_build_solver_laws(coarse):
    mats = materials.default_materials(coarse)
    assert set(mats) == set(coarse.label_names)
    for label, mat in mats.items():
        # the law's initial shear modulus is 2 C10 of the table
        assert mat.shear_modulus == pytest.approx(materials.material(label).shear_modulus)
        assert type(mat).__name__ == materials.material(label).law
    soft = materials.default_materials(stiffness=0.5)
    assert soft["dermis"].shear_modulus == pytest.approx(0.5 * mats["dermis"].shear_modulus)


def test_cartesian_roundtrip_with_warps():
    shape = hg.HeadShape(width=1.07, height=0.95, asymmetry=2.0)
    rng = np.random.default_rng(0)
    th, ph, rho = rng.uniform(-80, 80, 200), rng.uniform(-70, 30, 200), rng.uniform(40, 120, 200)
    t2, p2, r2 = hg.from_cartesian(hg.to_cartesian(th, ph, rho, shape), shape)
    np.testing.assert_allclose(np.c_[t2, p2, r2], np.c_[th, ph, rho], atol=1e-9)


def test_shape_parameters_move_what_they_name():
    base = hg.HeadShape()
    pog = hg.LANDMARK_ANGLES["Pog"]

    def skin_point(shape, key):
        t, p, s = hg.LANDMARK_ANGLES[key]
        return hg.to_cartesian(t, p, hg.skin_radius(t, p, shape, side=s), shape)

    # a class III mandible (+5 mm) brings the soft pogonion forward by ~5 mm (ray ~ along y)
    d = skin_point(hg.HeadShape(mandible_ap=5.0), "Pog") - skin_point(base, "Pog")
    assert 3.0 < d[1] < 6.0
    assert abs(skin_point(hg.HeadShape(mandible_ap=5.0), "Prn")[1] - skin_point(base, "Prn")[1]) < 1e-6
    d = skin_point(hg.HeadShape(maxilla_ap=4.0), "Ls") - skin_point(base, "Ls")
    assert 3.0 < d[1] < 4.5
    t, p, s = pog
    assert hg.soft_tissue_thickness(t, p, hg.HeadShape(soft_tissue=1.2)) == pytest.approx(
        1.2 * hg.soft_tissue_thickness(t, p, base))
    assert skin_point(hg.HeadShape(asymmetry=3.0), "Me")[0] > 2.0


def test_teeth_move_with_their_jaw():
    up0, _ = hg.teeth_arch("upper")
    up1, _ = hg.teeth_arch("upper", hg.HeadShape(maxilla_ap=3.0))
    lo1, _ = hg.teeth_arch("lower", hg.HeadShape(maxilla_ap=3.0))
    lo0, _ = hg.teeth_arch("lower")
    # the arch translates with its jaw; the front crowns follow the lips' deep surface, which
    # moves by slightly more than the jaw on oblique rays: centroid within 0.3 mm of 3 mm
    np.testing.assert_allclose((up1 - up0).mean(0), [0.0, 3.0, 0.0], atol=0.3)
    # the other arch stays, but for the crowns near the commissures that follow the lips'
    # deep surface, which blends the two jaws outside the mouth slit: < 1 mm
    assert np.abs(lo1 - lo0).max() < 1.0
    assert np.median(np.abs(lo1 - lo0)) < 1e-9
