"""Mesh-Match-and-Repair on synthetic heads whose truth is known (coarse generic mesh).

Targets of issue 4 checked here on a few heads (the 10-head sweep at coarse and standard
resolution is bench/registration.py): skin fit mean < 0.3 mm and p95 < 1.0 mm, bone fit mean
< 0.5 mm, no inverted element, min scaled Jacobian >= 0.2, landmarks within 1.5 mm of the
true ones; and the model's sets, fibres and teeth carried along.
"""
import numpy as np
import pytest

from registration import mesh_match_and_repair
from registration.quality import min_scaled_jacobian
from registration.surface import TargetSurface

generic_mesh = pytest.importorskip("generic_mesh")
synthetic = pytest.importorskip("facemodel.synthetic")


@pytest.fixture(scope="module")
def head_a():
    return synthetic.synthetic_head(2)


@pytest.fixture(scope="module")
def head_b():
    return synthetic.synthetic_head(5)


@pytest.fixture(scope="module")
def registered_a(generic, head_a, tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    patient, report = mesh_match_and_repair(generic, head_a.skin, head_a.bones, head_a.landmarks,
                                            cache_dir=cache)
    return patient, report, cache


def _check_targets(generic, patient, report, head, landmark_tol=1.5):
    fit = report["fit"]
    assert fit["skin"]["mean_mm"] < 0.3 and fit["skin"]["p95_mm"] < 1.0, fit["skin"]
    assert fit["bone"]["mean_mm"] < 0.5, fit["bone"]
    q = min_scaled_jacobian(patient.nodes, patient.hexes)
    assert q.min() >= 0.2 and report["quality"]["n_inverted"] == 0
    # independently of the report: most attached nodes sit on their own segment's surface
    for seg in generic.segments:
        bone = TargetSurface(np.asarray(head.bones[seg].vertices), np.asarray(head.bones[seg].faces))
        d = bone.closest(patient.nodes[generic.node_sets[f"attach_{seg}"]]).distance
        assert np.median(d) < 0.5, (seg, np.median(d))
    skin = TargetSurface(head.skin.vertices, head.skin.faces)
    for name, node in generic.landmarks.items():
        truth = np.asarray(head.landmarks[name])
        # the true landmarks are points of the patient's skin surface (synthetic.landmarks)
        assert float(skin.closest(truth[None]).distance[0]) < 1e-6
        err = float(np.linalg.norm(patient.nodes[node] - truth))
        assert err < landmark_tol, (name, err)


def test_registration_meets_targets_with_landmarks(generic, head_a, registered_a):
    patient, report, _ = registered_a
    assert report["alignment"]["method"] == "landmarks"
    _check_targets(generic, patient, report, head_a)
    assert set(report["time"]) >= {"align_s", "elastic_s", "snap_s", "repair_s", "total_s"}
    assert report["quality"]["histogram"]["counts"] and report["cached"] is False
    for name, node in generic.landmarks.items():  # the report's landmark errors are the real ones
        want = np.linalg.norm(patient.nodes[node] - head_a.landmarks[name])
        assert abs(report["landmarks"][name]["error_mm"] - want) < 1e-9


def test_registration_meets_targets_from_surfaces_alone(generic, head_b):
    patient, report = mesh_match_and_repair(generic, head_b.skin, head_b.bones, None, cache=False)
    assert report["alignment"]["method"] == "surfaces"
    # without landmarks nothing but the regularised surface fit fixes where features slide
    # along the skin (the nose tip and subnasale move by a few mm): a looser landmark bound
    _check_targets(generic, patient, report, head_b, landmark_tol=6.0)


@pytest.fixture(scope="module")
def class_iii():
    """A strong class III head (maxilla 4 mm back, mandible 7 mm forward): the lower lip 8.5 mm
    in front of the upper one, the opposite of the generic lips."""
    hg = pytest.importorskip("facemodel.head_geometry")
    shape = hg.HeadShape(maxilla_ap=-4.0, mandible_ap=7.0, chin_projection=2.0)
    skin = synthetic.skin_surface(shape)
    return synthetic.SyntheticHead(seed=-1, shape=shape, skin=skin, bones=synthetic.bone_surfaces(shape),
                                   teeth={}, landmarks=synthetic.landmarks(shape, skin))


def test_coarse_fit_and_landmarks_on_a_strong_class_iii(generic, class_iii):
    head = class_iii
    patient, report = mesh_match_and_repair(generic, head.skin, head.bones, head.landmarks, cache=False)
    # the coarse facets straddle the skin (nodes alone would leave them sagging ~0.3 mm)
    _check_targets(generic, patient, report, head)
    ff = report["facet_fit"]
    assert ff["rms_after_mm"] < 0.75 * ff["rms_before_mm"], ff
    # the smooth elastic stage leaves the upper-lip end on the skin between the lips (the
    # generic upper lip is in front of the lower one): the landmark correction had real work
    assert report["landmark_correction"]["max_correction_mm"] > 1.5
    skin = TargetSurface(head.skin.vertices, head.skin.faces)
    lm_nodes = np.array(list(generic.landmarks.values()))
    # landmark nodes stay skin points (pinned in the facet fit; closest-point precision)
    assert skin.closest(patient.nodes[lm_nodes]).distance.max() < 1e-6
    # stomion superius behind the lower lip's front, stomion inferius in front: lips not swapped
    st_s, st_i = patient.nodes[generic.landmarks["Stms"]], patient.nodes[generic.landmarks["Stmi"]]
    assert st_i[1] - st_s[1] > 4.0 and st_s[2] > st_i[2]


def test_everything_is_carried(generic, registered_a):
    patient, _, _ = registered_a
    assert np.array_equal(patient.hexes, generic.hexes) and np.array_equal(patient.labels, generic.labels)
    for k in generic.node_sets:
        assert np.array_equal(patient.node_sets[k], generic.node_sets[k])
    assert patient.landmarks == generic.landmarks and patient.regions.keys() == generic.regions.keys()
    muscle = np.linalg.norm(generic.fibres, axis=1) > 0
    assert np.allclose(np.linalg.norm(patient.fibres[muscle], axis=1), 1.0)
    assert np.all(np.linalg.norm(patient.fibres[~muscle], axis=1) == 0)
    for name, (v, f, seg) in generic.teeth.items():
        pv = patient.teeth[name][0]
        assert pv.shape == np.asarray(v).shape and patient.teeth[name][2] == seg
        # the teeth move rigidly (with scale) with their segment: edge lengths scale uniformly
        e0 = np.linalg.norm(np.diff(np.asarray(v)[np.asarray(f)[:, :2]], axis=1), axis=-1)
        e1 = np.linalg.norm(np.diff(pv[np.asarray(f)[:, :2]], axis=1), axis=-1)
        ratio = e1[e0 > 1e-6] / e0[e0 > 1e-6]
        assert np.ptp(ratio) < 1e-9


def test_fibre_reorientation_is_exact_for_an_affine_map(generic):
    from registration.face import reorient_fibres

    a = np.array([[1.1, 0.2, 0.0], [0.0, 0.9, 0.3], [0.1, 0.0, 1.2]])
    moved = generic.nodes @ a.T + [3.0, -2.0, 1.0]
    f = reorient_fibres(generic.nodes, moved, generic.hexes, generic.fibres)
    muscle = np.linalg.norm(generic.fibres, axis=1) > 0
    want = generic.fibres[muscle] @ a.T
    want /= np.linalg.norm(want, axis=1)[:, None]
    # trilinear elements reproduce an affine map exactly: F = A to round-off
    assert np.allclose(f[muscle], want, atol=1e-10)


def test_cache_returns_the_same_model(generic, head_a, registered_a):
    patient, report, cache = registered_a
    again, rep2 = mesh_match_and_repair(generic, head_a.skin, head_a.bones, head_a.landmarks, cache_dir=cache)
    assert rep2["cached"] is True and rep2["cache_key"] == report["cache_key"]
    assert np.array_equal(again.nodes, patient.nodes) and np.array_equal(again.fibres, patient.fibres)
