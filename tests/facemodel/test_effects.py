"""The sim-to-real effects of the face model (`facemodel.effects`, `planner.pipeline`):
parsing, the "none" values, gravity, swelling, bone execution, per-layer stiffness and the
parameter sensitivities against central finite differences of full solves.

Small blocks carry the quantitative checks (fast, analytic answers); the coarse generic face,
without lip contact (as tests/planner/test_predict.py, for time), checks the anatomy: the
posture sign at the cheeks and the bone corrections.
"""
import numpy as np
import pytest

from facemodel import effects as fe
from facemodel.model import LABEL_NAMES, FaceModel
from planner.errors import InputError
from planner.plan import parse_plan
from planner.pipeline import (effect_motions, effect_sensitivities, parse_effects, skin_sensitivities,
                              solve_plan)
from solver.examples import block


# ------------------------------------------------------------------ parsing
def test_parse_forms_and_round_trip():
    e = parse_effects(["stiffness.hypodermis=0.6", "sliding=chin", "gravity=1", "swelling=1.05",
                       "bone_execution.maxilla=[0, 1, 0, 0, 0, 2]", "muscle_tone=0.3", "stiffness=2",
                       "sliding.hold=0.4"])
    assert e.sliding == ("chin",) and e.layer_factor("hypodermis") == pytest.approx(1.2)
    assert e.sliding_hold == 0.4 and e.value("sliding.hold") == 0.4
    assert e.with_value("sliding.hold", 0.7).sliding_hold == 0.7
    assert e.correction("maxilla") == (0, 1, 0, 0, 0, 2)
    # the flat form is what --effect and model.effects take: parsing it gives the same values
    assert parse_effects(e.as_dict()) == e
    nested = parse_effects({"stiffness": {"hypodermis": 0.6}, "bone_execution": {"maxilla": [0, 1, 0, 0, 0, 2]}})
    assert nested.stiffness_layers == (("hypodermis", 0.6),)
    assert parse_effects(["sliding"]).sliding == ("*",) and parse_effects(["bone_execution=1"]).plan_actual
    # the values meaning "none" are the baseline
    none = parse_effects(["sliding=0", "sliding.hold=0", "muscle_tone=0", "swelling=1", "gravity=0", "stiffness=1",
                          "stiffness.dermis=1", "bone_execution=0", "bone_execution.chin=[0,0,0,0,0,0]"])
    assert none.active == () and none.as_dict() == {}


@pytest.mark.parametrize("item, field", [
    ("stiffness.bone=2", "stiffness.bone"), ("gravity=x", "gravity"), ("swelling=0.9", "swelling"),
    ("bone_execution.maxilla=[1,2]", "bone_execution.maxilla"), ("sliding=jaw", "sliding"),
    ("sliding.hold=1.5", "sliding.hold"), ("sliding.grip=0.5", "sliding.grip"),
    ("bone_execution.maxilla=[0,0,30,0,0,0]", "bone_execution.maxilla"), ("wind=1", "wind")])
def test_bad_effects_name_the_field(item, field):
    with pytest.raises(InputError) as exc:
        parse_effects([item])
    assert exc.value.field == f"--effect {field}"
    with pytest.raises(InputError) as exc:
        parse_plan({"faceplan": 1, "segments": {}, "model": {"effects": {item.split("=")[0]: item.split("=")[1]}}})
    assert exc.value.field == f"model.effects.{field}"


def test_parameters_and_flat_values():
    names = [p.name for p in fe.parameters("bone_execution", ("maxilla",))]
    assert names == [f"bone_execution.maxilla.{d}" for d in ("tx", "ty", "tz", "rx", "ry", "rz")]
    e = fe.Effects()
    for eff in fe.EFFECT_NAMES:
        for p in fe.parameters(eff, ("chin",)):
            assert e.value(p.name) == p.none and p.lower <= p.none <= p.upper
            assert e.with_value(p.name, p.none + 0.5).value(p.name) == p.none + 0.5


def test_correction_matrix_round_trip():
    c = np.array([3.0, 60.0, -20.0])
    p = (0.5, -1.0, 2.0, 1.5, -2.5, 3.0)
    T = fe.correction_matrix(p, c)
    assert np.allclose(T[:3, :3] @ c + T[:3, 3], c + p[:3])        # the centre moves by t only
    assert np.allclose(fe.correction_params(T, c), p, atol=1e-12)


def test_swelling_resolution_curve():
    # van der Vlis et al. 2014: ~half gone at 3 weeks, ~80 % at 3 months, ~93 % at 12 months
    assert fe.swelling_residual(None) == 1.0 and fe.swelling_residual(0) == 1.0
    assert fe.swelling_residual(0.7) == pytest.approx(0.5)
    assert fe.swelling_residual(3) == pytest.approx(0.2) and fe.swelling_residual(12) == pytest.approx(0.07)
    r = [fe.swelling_residual(t) for t in np.linspace(0, 24, 50)]
    assert np.all(np.diff(r) <= 0)


# ------------------------------------------------------------------ a block as a face model
def _block_model(size=(10, 10, 10), div=(2, 2, 2), label="hypodermis", muscle_top=False,
                 maxilla=True):
    """A block of one tissue tied to the skull at its base (z = 0); the maxilla holds the
    edge z = top, x = max (when `maxilla`)."""
    nodes, hexes, s = block(size, div)
    labels = np.full(len(hexes), LABEL_NAMES.index(label))
    fibres = np.zeros((len(hexes), 3))
    if muscle_top:     # the upper half is orbicularis oris with fibres along x
        top = nodes[hexes].mean(axis=1)[:, 2] > size[2] / 2
        labels[top] = LABEL_NAMES.index("orbicularis_oris")
        fibres[top] = [1, 0, 0]
    node_sets = {"attach_skull": s["zmin"]}
    if maxilla:
        node_sets["attach_maxilla"] = np.intersect1d(s["zmax"], s["xmax"])
    return FaceModel(nodes, hexes, labels, LABEL_NAMES, fibres, node_sets=node_sets,
                     facet_sets={"skin": np.zeros((0, 4), np.int64)})


def _plan(segments=None, contact=False):
    return parse_plan({"faceplan": 1, "segments": segments or {},
                       "model": {"resolution": "coarse", "contact": contact}})


def test_column_under_gravity_matches_small_strain_solution():
    """A column of hypodermis tied at its base under the vertical part of the posture load,
    rho g m (`gravity_density`, z component; the forward part is checked on the face): it
    shortens by rho g m H^2 / (2 E) (small strain; E = 9 K mu / (3 K + mu))."""
    from facemodel.simulation import simulate

    H, m = 80.0, 0.1
    model = _block_model((4, 4, H), (2, 2, 16), maxilla=False)
    rho_b = fe.gravity_density(m)
    assert np.allclose(rho_b, [0.0, 1.05e-6 * 9810 * m, -1.05e-6 * 9810 * m])
    res = simulate(model, contact=False, body_force=np.array([0.0, 0.0, rho_b[2]]))
    mu = 2 * 2.5
    K = 1000 * mu
    E = 9 * K * mu / (3 * K + mu)
    top = np.abs(model.nodes[:, 2] - H) < 1e-9
    expected = -fe.RHO * fe.G * m * H ** 2 / (2 * E)
    # strain <= 6e-3 at the base: geometric non-linearity (~strain) and the tied base (no
    # lateral contraction there, over ~one width of a column 20 widths high: ~2-3 %) within 4 %
    assert res.displacement[top, 2].mean() == pytest.approx(expected, rel=0.04)
    assert fe.gravity_density(0.0) is None
    model_short = _block_model(maxilla=False)
    zero = solve_plan(model_short, _plan(), effects=["gravity=0"])
    assert np.abs(zero.displacement).max() == 0.0


def test_layer_stiffness_scales_gravity_response():
    """Homogeneous block under gravity: a stiffness factor f on its only layer scales the
    displacement by 1/f (linear regime: strain ~1e-4, so the non-linear part is ~1e-4 too)."""
    model = _block_model()
    u1 = solve_plan(model, _plan(), effects=["gravity=0.2"]).displacement
    for f in (0.6, 2.0):
        uf = solve_plan(model, _plan(), effects=["gravity=0.2", f"stiffness.hypodermis={f}"]).displacement
        assert np.abs(uf * f - u1).max() < 2e-3 * np.abs(u1).max()
    # the dermis factor does not touch a hypodermis block; a uniform factor does
    ud = solve_plan(model, _plan(), effects=["gravity=0.2", "stiffness.dermis=3"]).displacement
    assert np.abs(ud - u1).max() < 1e-9
    # under displacement-only loading a uniform factor changes nothing (scale invariance)
    move = _plan({"maxilla": {"translation": [0, 1, 0]}})
    a = solve_plan(model, move).displacement
    b = solve_plan(model, move, effects=["stiffness=3"]).displacement
    assert np.abs(a - b).max() < 1e-6


def test_swelling_on_block_grows_near_the_operated_bone():
    model = _block_model()
    plan = _plan({"maxilla": {"translation": [0, 0.5, 0]}})
    base = solve_plan(model, plan)
    sw = solve_plan(model, plan, effects=["swelling=1.1"])
    late = solve_plan(model, plan, effects=["swelling=1.1"], follow_up_months=12)
    x0 = model.nodes + base.displacement
    vol = lambda p: np.sum(p.setup["problem"][0].volume * p.setup["problem"][0].volume_ratio(model.nodes + p.displacement))
    v0, v1, v12 = vol(base), vol(sw), vol(late)
    assert v1 > v0 and v0 < v12 < v1
    # at 12 months 7 % of the swelling is left: the volume gain scales with it (to 5 %: the
    # weights and elastic compression are the same, the response linear at these amplitudes)
    assert (v12 - v0) / (v1 - v0) == pytest.approx(0.07, rel=0.05)
    assert np.abs(sw.displacement - base.displacement).max() > 0.05 and np.isfinite(x0).all()


@pytest.mark.parametrize("name", ["gravity", "swelling", "stiffness.hypodermis", "muscle_tone",
                                  "bone_execution.maxilla.ty", "bone_execution.maxilla.rz"])
def test_sensitivities_match_central_differences(name):
    """du/dp from the converged tangent against central differences of full solves at
    p +- h (h = 0.02 of the parameter's scale). Truncation O(h^2) ~ 1e-4 relative; Newton
    tolerances ~1e-7: 2 % of the largest sensitivity bounds both with margin."""
    model = _block_model(muscle_top=True)
    plan = _plan({"maxilla": {"translation": [0, 1.0, 0.5]}})
    eff = parse_effects(["gravity=0.5", "swelling=1.05", "muscle_tone=0.1"])
    pred = solve_plan(model, plan, effects=eff)
    d = effect_sensitivities(pred, [name])[name]
    h = 0.02
    v = eff.value(name)
    up = solve_plan(model, plan, effects=eff.with_value(name, v + h)).displacement
    dn = solve_plan(model, plan, effects=eff.with_value(name, v - h)).displacement
    fd = (up - dn) / (2 * h)
    assert np.abs(fd).max() > 1e-3
    assert np.abs(d - fd).max() < 0.02 * np.abs(fd).max()


# ------------------------------------------------------------------ the coarse face
@pytest.fixture(scope="module")
def face():
    generic_mesh = pytest.importorskip("generic_mesh")
    return generic_mesh.load("coarse")


def test_posture_drops_the_cheeks(face):
    pred = solve_plan(face, _plan(), effects=["gravity=1"])
    u = pred.displacement
    for region in ("cheek_left", "cheek_right"):
        ids = np.asarray(face.regions[region])
        assert u[ids, 2].mean() < -0.05          # mm: the cheeks drop upright
    # mirror symmetry of the load and the face: left and right drop alike (1 %)
    l, r = (u[np.asarray(face.regions[k]), 2].mean() for k in ("cheek_left", "cheek_right"))
    assert l == pytest.approx(r, rel=0.01)


def test_bone_corrections(face):
    seg = {"maxilla": {"translation": [0.0, 3.0, 1.0],
                       "rotation": {"axis": [1, 0, 0], "angle_deg": -2.0, "center": [0, 60, -25]}}}
    plan = _plan(seg)
    base = solve_plan(face, plan)
    # a correction equal to the inverse of the plan leaves the bones where they were
    T = plan.motions()["maxilla"]
    c0 = base.setup["centroids"]["maxilla"]
    c = T[:3, :3] @ c0 + T[:3, 3]
    undo = fe.correction_params(np.linalg.inv(T), c)
    eff = parse_effects([f"bone_execution.maxilla={list(undo)}"])
    motions = effect_motions(plan, eff, base.setup["centroids"])
    assert np.allclose(motions["maxilla"], np.eye(4), atol=1e-12)
    assert np.abs(solve_plan(face, plan, effects=eff).displacement).max() < 1e-9
    # plan_actual with other matrices gives the prediction of a plan with those matrices
    other = _plan({"maxilla": {"translation": [0.5, 2.0, 1.0]}})
    actual = solve_plan(face, plan, effects=["bone_execution=1"], plan_actual=other)
    direct = solve_plan(face, other)
    assert np.abs(actual.displacement - direct.displacement).max() < 1e-9
    with pytest.raises(InputError, match="plan_actual"):
        solve_plan(face, plan, effects=["bone_execution=1"])
    # the none values give the baseline: the same model and the same solve, so equal to the
    # round-off of a repeated solve (a threaded direct solver may sum in another order; the
    # bound 1e-9 mm is far below any effect's 1e-2 mm scale and above double round-off)
    none = solve_plan(face, plan, effects=["swelling=1", "gravity=0", "stiffness.nose=1",
                                           "bone_execution.maxilla=[0,0,0,0,0,0]"])
    assert none.effects == {}
    assert np.abs(none.displacement - base.displacement).max() < 1e-9
    # skin sensitivity to the maxilla's forward correction: the lip follows the bone forward
    ids, sens = skin_sensitivities(base, ["bone_execution.maxilla.ty"])
    lip = np.isin(ids, np.asarray(face.regions["upper_lip"]))
    assert 0.3 < sens["bone_execution.maxilla.ty"][lip, 1].mean() < 1.1


@pytest.mark.parametrize("name", ["bone_execution.maxilla.ty", "bone_execution.maxilla.rx"])
def test_bone_sensitivities_move_a_partly_held_interface_with_the_bone(face, name):
    """With the tissue half-held on a sliding maxilla (`sliding.hold`, an elastic interface
    anchored to the bone's motion) a bone correction moves the interface's anchors too: the
    tangent's du/dp (`skin_sensitivities`, the anchors re-set from the corrected motion)
    against central differences of full solves at p +- 0.05 (mm or deg). Contact off: the
    response is smooth, truncation O(h^2) and Newton's tolerance keep the difference near
    1e-5 of the largest sensitivity; leaving the anchors where the plan put them is off by
    5-12 %. 0.5 % separates the two with a wide margin either way."""
    plan = _plan({"maxilla": {"translation": [0.0, 3.0, 1.0]}})
    eff = parse_effects(["sliding=maxilla", "sliding.hold=0.5"])
    ids, sens = skin_sensitivities(solve_plan(face, plan, effects=eff), [name])
    h = 0.05
    up, dn = (solve_plan(face, plan, effects=eff.with_value(name, v)).predicted_nodes[ids] for v in (h, -h))
    fd = (up - dn) / (2 * h)
    assert np.abs(fd).max() > 0.02
    assert np.abs(sens[name] - fd).max() < 5e-3 * np.abs(fd).max()


# ------------------------------------------------------------------ gravity: head pitch
def test_gravity_pitch_direction_and_magnitude():
    """The upright gravity rotated by the head pitch phi about the left-right axis:
    g_up = (0, sin phi, -cos phi) (+ = chin down). Pitch 0 is the unpitched load rho g m
    (0, +1, -1); the upright part keeps its magnitude rho g m at any pitch (a rotation); chin
    down gives gravity a forward (+y, anterior) component, chin up a backward one. Tolerances:
    double round-off of sin/cos (1e-12 relative)."""
    m = 0.8
    rg = fe.RHO * fe.G * m
    assert np.allclose(fe.gravity_density(m, 0.0), rg * np.array([0.0, 1.0, -1.0]), rtol=1e-12, atol=0)
    assert np.array_equal(fe.gravity_density(m), fe.gravity_density(m, 0.0))
    supine = rg * np.array([0.0, -1.0, 0.0])
    for phi in (-30.0, -7.5, 0.0, 12.0, 30.0):
        upright = fe.gravity_density(m, phi) + supine
        assert np.linalg.norm(upright) == pytest.approx(rg, rel=1e-12)
        assert upright[0] == 0.0                                   # no left-right component
        assert np.sign(upright[1]) == np.sign(phi)                 # chin down: forward
        assert upright[2] < 0                                      # still downward
    # a quarter turn face down: straight forward
    assert np.allclose(fe.gravity_direction(90.0), [0.0, 1.0, 0.0], atol=1e-15)
    assert fe.gravity_density(0.0, 20.0) is None                   # no gravity, no load
    e = parse_effects(["gravity=1", "gravity.pitch=-10"])
    assert e.gravity_pitch == -10.0 and parse_effects(e.as_dict()) == e
    assert e.value("gravity.pitch") == -10.0 and e.with_value("gravity.pitch", 5).gravity_pitch == 5.0
    assert parse_effects(["gravity.pitch=10"]).active == ()         # pitch alone is no effect
    with pytest.raises(InputError) as exc:
        parse_effects(["gravity.pitch=45"])
    assert exc.value.field == "--effect gravity.pitch"


def test_gravity_pitch_on_the_block():
    """A block tied at its base under the posture load: with the chin down (pitch +20 deg) the
    tissue moves further forward (+y) and drops less (-z) than at pitch 0, chin up the
    reverse; pitch 0 gives the prediction of the unpitched load. Linear regime (strain ~1e-4):
    the response to each load component is linear, so the y and z means follow the load's
    components (1 + sin phi, cos phi) to 1 % (non-linearity ~strain, plus the coupling of the
    two directions through the tied base, which the linear superposition keeps exact)."""
    model = _block_model(maxilla=False)
    plan = _plan()
    u0 = solve_plan(model, plan, effects=["gravity=0.5"]).displacement
    uy = solve_plan(model, plan, effects=["gravity=0.5", "gravity.pitch=0"]).displacement
    assert np.abs(uy - u0).max() == 0.0           # the same load vector, the same solve
    # the response to each load component alone (m = 0.5): y part and z part
    from facemodel.simulation import simulate
    rg = fe.RHO * fe.G * 0.5
    uy1 = simulate(model, contact=False, body_force=np.array([0.0, rg, 0.0])).displacement
    uz1 = simulate(model, contact=False, body_force=np.array([0.0, 0.0, -rg])).displacement
    assert np.abs(uy1 + uz1 - uy).max() < 0.01 * np.abs(uy).max()
    for phi in (20.0, -20.0):
        u = solve_plan(model, plan, effects=["gravity=0.5", f"gravity.pitch={phi}"]).displacement
        a = np.radians(phi)
        expect = (1 + np.sin(a)) * uy1 + np.cos(a) * uz1
        assert np.abs(u - expect).max() < 0.01 * np.abs(u).max()
        top = np.abs(model.nodes[:, 2] - 10.0) < 1e-9
        if phi > 0:
            assert u[top, 1].mean() > u0[top, 1].mean() and u[top, 2].mean() > u0[top, 2].mean()
        else:
            assert u[top, 1].mean() < u0[top, 1].mean() and u[top, 2].mean() > u0[top, 2].mean()


# ------------------------------------------------------------------ bone execution: the chin rides on the mandible
def test_mandible_correction_carries_the_chin():
    """executed_motions: chin_actual = C_mandible . plan_chin (then the chin's own correction
    about its centroid as carried), for a plan with a genioplasty (chin moved relative to the
    mandible) and without one; the maxilla is not carried. Exact rigid algebra: 1e-12."""

    plan = _plan({"maxilla": {"translation": [0, 3, 1]}, "mandible": {"translation": [0, 5, 0]},
                  "chin": {"translation": [0, 8, 2], "rotation": {"axis": [1, 0, 0], "angle_deg": 4,
                                                                  "center": [0, 70, -60]}}})
    cen = {"maxilla": np.array([0, 60.0, -25]), "mandible": np.array([0, 40.0, -55]),
           "chin": np.array([0, 72.0, -62])}
    pm = (0.8, -1.2, 0.6, 2.0, -1.0, 1.5)
    eff = parse_effects([f"bone_execution.mandible={list(pm)}"])
    mot = effect_motions(plan, eff, cen)
    T = plan.motions(include_identity=True)
    c_m = T["mandible"][:3, :3] @ cen["mandible"] + T["mandible"][:3, 3]
    C = fe.correction_matrix(pm, c_m)
    assert np.allclose(mot["mandible"], C @ T["mandible"], atol=1e-12)
    assert np.allclose(mot["chin"], C @ T["chin"], atol=1e-12)
    assert np.allclose(mot["maxilla"], T["maxilla"], atol=1e-12)
    # chin and mandible keep their planned relative pose (the plate holds)
    rel = lambda M: np.linalg.inv(M["mandible"]) @ M["chin"]
    assert np.allclose(rel(mot), rel(T), atol=1e-12)
    # the chin's own correction comes after, about its centroid as carried
    pc = (0.3, 0.0, -0.5, 0.0, 1.0, 0.0)
    both = effect_motions(plan, parse_effects([f"bone_execution.mandible={list(pm)}",
                                               f"bone_execution.chin={list(pc)}"]), cen)
    carried = C @ T["chin"]
    c_c = carried[:3, :3] @ cen["chin"] + carried[:3, 3]
    assert np.allclose(both["chin"], fe.correction_matrix(pc, c_c) @ carried, atol=1e-12)
    # a chin the plan does not list rides on the mandible's correction alone
    noc = _plan({"mandible": {"translation": [0, 5, 0]}})
    assert np.allclose(effect_motions(noc, eff, cen)["chin"], C, atol=1e-12)
    # a chin correction alone leaves the mandible as planned
    only = effect_motions(plan, parse_effects([f"bone_execution.chin={list(pc)}"]), cen)
    assert np.allclose(only["mandible"], T["mandible"], atol=1e-12)


def test_an_uncut_chin_has_no_execution_of_its_own():
    """executed_segments: the chin planned to move as the mandible does (no genioplasty) is
    part of the mandible's distal segment, so only a genioplasty gives it a correction of its
    own; the equality allows a transform file's rounding (1e-4 mm) but not a 0.05 mm move."""
    rot = {"axis": [1, 0, 0], "angle_deg": -2.0, "center": [0, 70, -40]}
    mand = {"translation": [0, 4.0, 0], "rotation": rot}
    cases = [({"chin": mand}, ("maxilla", "mandible")),
             ({"chin": {"translation": [0, 4.0001, 0], "rotation": rot}}, ("maxilla", "mandible")),
             ({"chin": {"translation": [0, 4.05, 0], "rotation": rot}}, ("maxilla", "mandible", "chin")),
             ({"chin": {"translation": [0, 4.0, 0]}}, ("maxilla", "mandible", "chin")),
             ({}, ("maxilla", "mandible"))]
    for chin, expect in cases:
        plan = _plan({"maxilla": {"translation": [0, 3, 1]}, "mandible": mand, **chin})
        assert fe.executed_segments(plan.motions()) == expect, chin
    # a chin moved alone (the mandible stays) is a genioplasty
    assert fe.executed_segments(_plan({"chin": {"translation": [0, 5, 0]}}).motions()) == ("chin",)



def test_mandible_correction_moves_the_chin_nodes_rigidly(face):
    """On the coarse face with a genioplasty in the plan: a mandible correction moves the chin
    segment's tied attachment nodes by exactly C_mandible . plan_chin (prescribed displacements:
    to the solver's constraint round-off, 1e-9 mm) and the mandible's by C_mandible . plan
    (the distal segment's: the split's proximal segments stay with the skull)."""
    from facemodel.attachments import PROXIMAL, attachment_sets

    plan = _plan({"mandible": {"translation": [0, 4, 0]},
                  "chin": {"translation": [0, 6, 1]}})
    pm = [0.5, 1.0, -0.5, 1.5, 0.0, -1.0]
    pred = solve_plan(face, plan, effects=[f"bone_execution.mandible={pm}"])
    X = np.asarray(pred.model.nodes, float)
    T = plan.motions(include_identity=True)
    c0 = pred.setup["centroids"]["mandible"]
    c = T["mandible"][:3, :3] @ c0 + T["mandible"][:3, 3]
    C = fe.correction_matrix(pm, c)
    slide = set()
    for ids in pred.setup["degloved"].values():
        slide |= set(np.asarray(ids).tolist())
    owned = attachment_sets(pred.model, T)
    for seg, M in (("chin", C @ T["chin"]), ("mandible", C @ T["mandible"]), (PROXIMAL, np.eye(4))):
        ids = np.array([i for i in owned[seg] if i not in slide])
        assert len(ids) > 5
        want = X[ids] @ M[:3, :3].T + M[:3, 3]
        assert np.abs(X[ids] + pred.displacement[ids] - want).max() < 1e-9
