"""A finer truth model carried from a registration at a coarser resolution
(`planner.commands.synth.prolonged_patient`, `registration.prolong`)."""
import dataclasses

import numpy as np
import pytest

from planner.commands import synth

generic_mesh = pytest.importorskip("generic_mesh")


def _quads_as_triangles(quads):
    q = np.asarray(quads)
    return np.vstack([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])


def test_an_affine_registration_is_carried_exactly_and_each_lip_keeps_its_side():
    # an affine "registration" of the coarse generic face is reproduced exactly on the standard
    # mesh (trilinear interpolation and extrapolation reproduce affine maps; 1e-8 mm covers
    # the Newton inversion's round-off on a 200 mm head), and every lip node is located in an
    # element of its own lip
    coarse, standard = generic_mesh.load("coarse"), generic_mesh.load("standard")
    A = np.array([[1.05, 0.02, 0.0], [-0.03, 0.97, 0.04], [0.01, 0.0, 1.08]])
    b = np.array([1.5, -2.0, 3.0])
    registered = dataclasses.replace(coarse, nodes=np.asarray(coarse.nodes) @ A.T + b, teeth={})
    patient, loc, report = synth.prolonged_patient(standard, coarse, registered)
    np.testing.assert_allclose(patient.nodes, np.asarray(standard.nodes) @ A.T + b, atol=1e-8)
    assert report["min_scaled_jacobian"] > 0.0
    side = synth.lip_groups(standard.nodes)
    elem_side = synth.lip_groups(coarse.nodes, coarse.hexes)[loc.element]
    assert np.all((side == 0) | (elem_side == side))
    # the lower lip's contact nodes lie on the far side of the 1 mm slit from the upper lip's
    # elements: a located lip node is at most the chord difference outside its element
    lips = np.unique(np.asarray(standard.facet_sets["lip_lower_contact"]))
    assert loc.outside_mm[lips].max() < 0.5
    f = np.linalg.norm(patient.fibres, axis=1)
    assert np.allclose(f[f > 0], 1.0)


def test_a_registration_carried_to_the_finer_mesh_stays_on_the_patient(tmp_path):
    """A coarse registration of a synthetic head carried to the standard mesh: no inverted
    element, every movable node clear of the teeth, the skin on the patient's skin."""
    import registration
    from facemodel.synthetic import synthetic_head
    from planner.case import load_case
    from registration.lips import lip_overlap
    from registration.mesh_match import MatchOptions
    from registration.surface import TargetSurface
    from registration.teeth import Arch, union_distance

    folder = tmp_path / "synth_0021"
    folder.mkdir()
    synth.write_case(folder, synthetic_head(21, size=4.0, distance=4.0 / 12.0))
    case = load_case(folder, cache=False)
    coarse, standard = generic_mesh.load("coarse"), generic_mesh.load("standard")
    patient_c, _ = registration.mesh_match_and_repair(coarse, case.skin, case.bones,
                                                      landmarks=case.landmarks, teeth=case.teeth,
                                                      cache=False)
    opt = MatchOptions()
    held = np.concatenate([np.asarray(v) for k, v in standard.node_sets.items()
                           if k == "skin" or k.startswith("attach_")])

    def check_start(patient, report):
        # no element below the registration's scaled-Jacobian threshold (0.2); every node the
        # push may move outside the teeth and the lips apart across the slit as the
        # registration leaves them (gap 0.1 mm, worked to within separate_lips' 0.05 mm
        # tolerance): contact cannot start from crossed lips or lips inside the teeth. The
        # teeth clearance itself (0.25 mm) is a margin the pushes aim at, not a condition of
        # the solve: where a lip node has room for the lip gap or the margin but not both,
        # the alternation of pushes and separations can end short of it (by 0.07 mm with
        # other BLAS kernels on this head), which the report must then say.
        x = np.asarray(patient.nodes)
        assert report["min_scaled_jacobian"] >= opt.threshold
        movable = np.setdiff1d(np.arange(len(x)), held)
        arches = [Arch(k, v, f, s) for k, (v, f, s) in patient.teeth.items()]
        clearance = union_distance(arches, x[movable], 2.0)[0].min()
        assert clearance > 0.0
        assert report["teeth"]["min_distance_after_mm"] == pytest.approx(clearance, abs=1e-4)
        gap = lip_overlap(x, np.asarray(standard.facet_sets["lip_upper_contact"]),
                          np.asarray(standard.facet_sets["lip_lower_contact"]))["min_gap_mm"]
        assert gap >= opt.lip_gap_mm - 0.05
        assert report["start"]["conditions_hold"] == (clearance >= opt.teeth_clearance_mm)
        return x

    patient, _, report = synth.prolonged_patient(standard, coarse, patient_c)
    x = check_start(patient, report)
    # the three hold together whatever the carried start: with the arches 0.6 mm further
    # forward (into the lips: more nodes to push, more elements for the repair, which must not
    # undo the pushes) they still hold
    forward = {k: (np.asarray(v) + [0.0, 0.6, 0.0], f, s) for k, (v, f, s) in patient_c.teeth.items()}
    check_start(*synth.prolonged_patient(standard, coarse,
                                         dataclasses.replace(patient_c, teeth=forward))[::2])
    # the carried skin is where the coarse registered skin is (its facets are the coarse
    # registration's fit, gated at skin_mean_gate_mm = 1 mm on average; the synthetic skin is
    # closed, so every skin node has skin under it): on average within that gate, and its
    # median within the sag of a coarse facet (~8 mm wide on a >= 30 mm radius of the face:
    # h^2 / 8R ~ 0.3 mm) of the coarse skin nodes' own median distance
    skin = TargetSurface(case.skin.vertices, case.skin.faces, "skin")
    d_fine = np.abs(skin.closest(x[np.asarray(standard.node_sets["skin"])]).distance)
    d_coarse = np.abs(skin.closest(np.asarray(patient_c.nodes)[np.asarray(coarse.node_sets["skin"])]).distance)
    assert np.mean(d_fine) <= opt.skin_mean_gate_mm
    assert np.median(d_fine) <= np.median(d_coarse) + 0.3
