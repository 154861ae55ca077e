"""`planner.diagnosis` on withheld-effect scans of the generic coarse face.

The truths are made on a model that is not the diagnosed one (`planner.diagnosis.synthetic`:
moduli +-15 %, bulk modulus 500-2000 x the shear modulus, layer thicknesses +-20 %), then made
scan-like (subdivided, front only, 0.2 mm normal noise, a rigid offset of up to 2 mm / 2 deg).
All scenarios diagnose the same patient and plan, so they share one `Forward` (its baseline and
finite-difference solves are made once): Le Fort I advancement, lip contact off to stay in the
test budget.
"""
import numpy as np
import pytest

from planner.compare.inputs import Surface
from planner.diagnosis import discrepancy, fit
from planner.diagnosis.effects import available_effects, effect_strings
from planner.diagnosis.forward import Forward, prepare_case, solve_skin
from planner.diagnosis.run import diagnose_data
from planner.diagnosis.synthetic import perturbed_case, scan_like
from planner.errors import InputError

EFFECTS = ("sliding", "muscle_tone", "stiffness")
PLAN = {"faceplan": 1, "segments": {"maxilla": {"translation": [0.0, 4.0, 0.0]},
                                    "mandible": {"translation": [0.0, 2.0, 0.0]},
                                    "chin": {"translation": [0.0, 2.0, 0.0]}},
        "model": {"resolution": "coarse", "contact": False}}


@pytest.fixture(scope="module")
def patient():
    import generic_mesh
    from planner.plan import parse_plan

    plan = parse_plan(PLAN)
    return prepare_case("generic", generic_mesh.load("coarse"), plan, None)


@pytest.fixture(scope="module")
def forward(patient):
    # the patient twice: single-case diagnoses use index 0, the two-case one both; solves are
    # stored by case object, so both indices share them
    return Forward([patient, patient])


def _scan(case, strings, seed, perturb=True, forward=None, **kw):
    if perturb or forward is None:
        skin, _ = solve_skin(perturbed_case(case, seed, **kw) if perturb else case, tuple(strings))
    else:
        skin = forward.solve([(0, effect_strings(dict(s.split("=") for s in strings)))])[0]
    assert not isinstance(skin, str), skin
    v, f = scan_like(skin, case.skin_faces, seed=seed)
    return Surface(v, f, __import__("pathlib").Path(f"synthetic-{seed}.stl"))


_RESULTS = {}


def _diagnose(patient, forward, name, strings, seed, effects=EFFECTS, **kw):
    if name not in _RESULTS:
        scan = _scan(patient, strings, seed, forward=forward, **kw)
        _RESULTS[name + "_scan"] = scan
        _RESULTS[name] = diagnose_data([patient], [scan], forward=forward, effect_names=effects)
    return _RESULTS[name]


def test_withheld_muscle_tone_is_named(patient, forward):
    out = _diagnose(patient, forward, "tone", ["muscle_tone=0.15"], seed=1)
    rec = out["record"]
    assert rec["verdict"]["effect"] == "muscle_tone"
    assert rec["verdict"]["confidence"] > 0.9
    best = rec["effects"][0]
    assert best["name"] == "muscle_tone" and best["significant"]
    # the target for identifiable values: within 25 % of the truth (perturbed model)
    assert best["params"]["muscle_tone"] == pytest.approx(0.15, rel=0.25)
    assert best["heldout_shrink_pct"] >= 25.0
    assert {"upper_lip", "lower_lip"} & set(rec["verdict"]["regions"])
    # the baseline was also solved with the neck cut held (the plan's is free): its difference
    # is in the error model, and the field the baseline gap holds along it is reported
    em = rec["error_model"]
    assert em["boundary_direction"] == "neck held" and em["boundary_mm"] is not None
    assert 0.0 <= em["boundary_mm"] <= em["discrepancy_mm"] + 1e-9
    # the layer-proportion directions are asked for (`layers=True`), not solved by default
    assert em["layer_directions"] is None and em["layer_mm"] is None
    # the scan's pose is integrated out: its spread is reported, three rotations and three
    # translations, each positive (a least-squares pose on the upper face is never exact)
    sd = em["pose_sd"]
    assert len(sd["rotation_deg"]) == 3 and len(sd["translation_mm"]) == 3
    assert min(sd["rotation_deg"] + sd["translation_mm"]) > 0.0
    # the winning effect's fitted gap is smaller than the baseline's in every explained region
    for region in rec["verdict"]["regions"]:
        r = rec["shrinkage"]["regions"][region]
        assert r["after_mm"] < r["before_mm"]


def test_the_named_tone_is_also_given_with_the_moduli_unknown(patient, forward):
    """The tone truth was made on a model with other moduli (+-15 %). The named effect's
    values also come with intervals marginal over the patient's layer moduli
    (`analysis.moduli_marginal`): one solve at the fitted tone with the stiffness factors'
    tangent sensitivities there, integrated under the library's range. They are wider than
    the intervals at the model's moduli and hold the withheld tone. The solve's skin is the
    prediction with that tone (checked against an independent solve, 1e-6 mm: the same
    problem to Newton's tolerance)."""
    rec = _diagnose(patient, forward, "tone", ["muscle_tone=0.15"], seed=1)["record"]
    named = next(e for e in rec["effects"] if e["name"] == rec["verdict"]["effect"])
    assert named["name"] == "muscle_tone"
    marginal = named["marginal_over_moduli"]
    assert set(marginal["over"]) == {f"stiffness.{k}" for k in ("dermis", "hypodermis", "muscle", "mucosa", "nose")}
    q = named["parameters"]["muscle_tone"]
    assert q["standard_error_marginal"] > q["standard_error_with_discrepancy"]
    lo, hi = q["interval_95_marginal"]
    assert lo <= 0.15 <= hi and lo <= q["interval_95"][0] and hi >= q["interval_95"][1]
    strings = tuple(marginal["at"][0])
    assert strings == effect_strings({"muscle_tone": q["value"]})
    skin = forward.solve([(0, strings)])[0]
    again, _ = solve_skin(patient, strings)
    assert np.abs(np.asarray(skin) - again).max() < 1e-6
    # the other effects' values are not integrated: only the named effect's
    assert all(e["marginal_over_moduli"] is None for e in rec["effects"] if e is not named)


def test_fitted_values_extrapolated_with_the_truths_model_as_the_second_mesh(patient, forward):
    """The muscle-tone scan of the test above was made on the perturbed model (moduli +-15 %,
    layers +-20 %), which responds to tone otherwise than the diagnosed one. Given that model
    as the second mesh (`references`: the mesh-error direction is then exactly the models'
    difference at the baseline, whose true coefficient is 1), the tone fitted on the response
    extrapolated with the reference's tangent lies within the 25 % the issue allows.

    The coefficient kappa itself is barely informed here: the two models' baselines differ by
    about a hundredth of a millimetre RMS on the scan points, under 0.2 mm of scan noise, so
    its posterior (prior standard deviation `MESH_ERROR_SD`, Gaussian error model of the
    baseline fit) keeps a standard deviation of about half its prior's and its mean shrinks
    towards the prior's 0. The test asks that the truth lies within 2.5 posterior standard
    deviations (a 99 % credible band) and that the data did inform it (posterior narrower
    than the prior)."""
    _diagnose(patient, forward, "tone", ["muscle_tone=0.15"], seed=1)      # makes and keeps the scan
    scan = _RESULTS["tone_scan"]
    ref = perturbed_case(patient, 1)
    out = diagnose_data([patient], [scan], forward=forward, effect_names=("muscle_tone",),
                        references=[ref], reference_names=["perturbed"])
    rec = out["record"]
    tone = next(e for e in rec["effects"] if e["name"] == "muscle_tone")
    kappa = tone["mesh_extrapolation_factor"][0]
    sd = tone["mesh_extrapolation_factor_sd"][0]
    assert sd < 0.9 * discrepancy.MESH_ERROR_SD, sd
    assert abs(kappa - 1.0) <= 2.5 * sd, (kappa, sd)
    assert tone["params"]["muscle_tone"] == pytest.approx(0.15, rel=0.25), tone["params"]


def test_uniform_stiffness_is_not_identifiable(patient, forward):
    """Displacement-only loading: the solution does not depend on a uniform stiffness factor,
    so its Fisher information is nil and it is not ranked."""
    rec = _diagnose(patient, forward, "tone", ["muscle_tone=0.15"], seed=1)["record"]
    stiff = next(e for e in rec["effects"] if e["name"] == "stiffness")
    # per-layer factors: one layer (the uniform direction) is left out, the others fitted
    # relative to it
    assert not all(p["identifiable"] for p in stiff["parameters"].values())
    uniform = available_effects(("maxilla",), ("stiffness",), stiffness_layers=False)
    rec = diagnose_data([patient], [_RESULTS["tone_scan"]], forward=forward, effects=uniform)["record"]
    e = rec["effects"][0]
    assert list(e["parameters"]) == ["stiffness"]
    assert e["identifiable"] is False and not e["significant"] and e["params"] == {}


def test_withheld_sliding_is_named(patient, forward):
    rec = _diagnose(patient, forward, "sliding", ["sliding=1"], seed=2)["record"]
    assert rec["verdict"]["effect"] == "sliding"
    assert rec["effects"][0]["name"] == "sliding"
    assert rec["effects"][0]["heldout_shrink_pct"] >= 25.0


# The effects whose skin change exceeds the scan noise at a mid-range value (docs/effects.md,
# bench/effects.py), each withheld on the perturbed model and diagnosed against every effect
# the model can add. A layer's stiffness alone, under bone motion only, stays below the noise
# there and is judged by the identifiability test instead (test_uniform_stiffness_...).
ALL_EFFECTS = ("sliding", "muscle_tone", "swelling", "gravity", "stiffness", "bone_execution")


@pytest.mark.parametrize("name, strings, seed", [
    # peak growth 1.15 with no follow-up time: about 1 mm of skin at most, inside the published
    # residual range (0.5-2 mm at 3-12 months) that `faceplan synth` draws from
    ("swelling", ["swelling=1.15"], 11),
    ("gravity", ["gravity=1.0"], 12),
    ("bone_execution", ["bone_execution.maxilla=[0.8, 1.0, -0.5, 1.5, 0.0, 0.0]"], 13),
])
def test_each_withheld_effect_is_named(patient, forward, name, strings, seed):
    rec = _diagnose(patient, forward, f"all_{name}", strings, seed=seed, effects=ALL_EFFECTS)["record"]
    assert rec["verdict"]["effect"] == name
    assert rec["verdict"]["confidence"] > 0.5
    entry = next(e for e in rec["effects"] if e["name"] == name)
    assert entry["significant"]
    if name == "bone_execution":
        # the plan's chin moves with the mandible (no genioplasty): uncut, no correction of its own
        assert patient.executed_segments == ("maxilla", "mandible")
        assert set(entry["params"]) == {"bone_execution.maxilla", "bone_execution.mandible"}
    # held-out: the effect predicts regions it was not fitted on; a quarter of the gap at least
    # (the scan noise, 0.2 mm, stays in the held-out gap whatever the effect)
    assert entry["heldout_shrink_pct"] >= 25.0
    _check_intervals(entry)


def _check_intervals(entry: dict) -> None:
    """Each identifiable fitted value comes with its standard error under noise + discrepancy
    and the 95 % interval from it, which holds the value (the interval's calibration is
    checked where the error model is known: tests/planner/test_diagnosis_discrepancy.py). The
    interval is conditional on the generic model's moduli and thicknesses: the truth here is
    another model, so it is not asked to hold the withheld value (a softer face sags more
    under the same posture)."""
    fitted = [q for q in entry["parameters"].values() if q["identifiable"]]
    assert fitted
    for q in fitted:
        lo, hi = q["interval_95"]
        assert lo <= q["value"] <= hi and lo < hi
        assert q["standard_error_with_discrepancy"] > 0


def test_two_withheld_effects_are_named_as_a_pair(patient, forward):
    """Tone and sliding together: the best single effect leaves a significant gap, the greedy
    pair removes it. Alone, sliding fits best at one segment; beside the tone the pair re-chooses
    the switch (`analysis._pairs_with`) and finds the truth's, every moved segment's tissue
    sliding, with the tone within the issue's 25 %."""
    rec = _diagnose(patient, forward, "pair", ["muscle_tone=0.15", "sliding=1"], seed=9)["record"]
    assert set(rec["verdict"]["effect"].split("+")) == {"muscle_tone", "sliding"}
    pair = next(e for e in rec["effects"] if set(e["name"].split("+")) == {"muscle_tone", "sliding"})
    assert pair["params"]["sliding"] == 1
    assert pair["params"]["muscle_tone"] == pytest.approx(0.15, rel=0.25)
    singles = [e for e in rec["effects"] if e["name"] in ("muscle_tone", "sliding")]
    assert pair["heldout_shrink_pct"] >= max(e["heldout_shrink_pct"] for e in singles) + 10.0


def test_none_gives_null(patient, forward):
    """The diagnosed model itself with scan noise and offset only: nothing beats the noise."""
    rec = _diagnose(patient, forward, "none", [], seed=3, perturb=False)["record"]
    assert rec["verdict"]["effect"] is None
    assert not any(r["significant"] for r in rec["localization"])
    assert not any(e["significant"] for e in rec["effects"])
    _check_supported_not_named(rec)
    # the floor is the scan's noise (0.2 mm along the normals), as the superimposition sees it:
    # the roughness estimate of a noisy subdivided surface within 30 %
    assert 0.14 <= rec["noise_floor_mm"] <= 0.3
    assert rec["alignment"]["residual_rms_mm"] < 0.4


def test_perturbation_only_is_not_forced_onto_an_effect(patient, forward):
    """A generic-model perturbation without any effect: null or unexplained, never an effect
    with confidence > 0.5."""
    rec = _diagnose(patient, forward, "perturbed", [], seed=4, modulus_pct=15.0, thickness_pct=20.0)["record"]
    v = rec["verdict"]
    assert v["effect"] in (None, "unexplained") or v["confidence"] <= 0.5
    if v["effect"] in (None, "unexplained"):
        _check_supported_not_named(rec)


def test_a_held_floor_of_the_mouth_is_carried_by_the_neck_direction(patient, forward):
    """A truth that holds the floor of the mouth (`model.floor: held`: a boundary choice the
    diagnosed model does not share; perturbed model), no effect, scanned under the chin too.
    Its submental skin lags the advanced mandible as a held neck cut's does (the two changes are
    nearly parallel: `tests/facemodel/test_simulation.py`), so the neck's direction, solved by
    default, carries it:
    the error model puts a boundary field into the gap, and the verdict is null or
    unexplained, never an effect with confidence > 0.5 (the issue's rule for a model-form gap)."""
    import dataclasses
    from pathlib import Path

    truth = perturbed_case(patient, 5)
    truth = dataclasses.replace(truth, plan=dataclasses.replace(
        truth.plan, model=dataclasses.replace(truth.plan.model, floor="held")))
    skin, _ = solve_skin(truth, ())
    v, f = scan_like(skin, patient.skin_faces, seed=5, front_only=False)
    rec = diagnose_data([patient], [Surface(v, f, Path("synthetic-floor.stl"))], forward=forward,
                        effect_names=EFFECTS)["record"]
    em = rec["error_model"]
    assert em["boundary_direction"] == "neck held" and em["boundary_mm"] > 0.1
    verdict = rec["verdict"]
    assert verdict["effect"] in (None, "unexplained") or verdict["confidence"] <= 0.5


def _check_supported_not_named(rec):
    """A verdict without an effect lists the effects that hold the probability the baseline
    does not (strong evidence and held-out gain, too little held-out shrinkage to be named):
    their probabilities and the confidence add up to 1 (pseudo-BMA+ weights; rounding 1e-3)."""
    v = rec["verdict"]
    prob = {e["name"]: e["probability"] for e in rec["effects"]}
    assert set(v["supported_not_named"]) == {e["name"] for e in rec["effects"]
                                             if e["probability"] and not e["significant"]}
    assert v["confidence"] + sum(prob[n] for n in v["supported_not_named"]) == pytest.approx(1.0, abs=1e-3)


def test_two_cases(patient, forward):
    """Two scans of the patient with different resting tones: the case-specific tone is fitted
    per case (spatial cross-validation in each), the shared stiffness leaving one case out; the
    verdict names the tone and the record lists both cases."""
    first = _diagnose(patient, forward, "tone", ["muscle_tone=0.15"], seed=1)
    scan2 = _scan(patient, ["muscle_tone=0.1"], seed=8)
    scan1 = _RESULTS["tone_scan"]
    rec = diagnose_data([patient, patient], [scan1, scan2], forward=forward, effect_names=EFFECTS)["record"]
    assert rec["verdict"]["effect"] == "muscle_tone"
    assert len(rec["cases"]) == 2 and all("localization" in c and "baseline" in c for c in rec["cases"])
    tone = next(e for e in rec["effects"] if e["name"] == "muscle_tone")
    fitted = [c["muscle_tone"] for c in tone["params"]["per_case"]]
    assert fitted[0] == pytest.approx(first["record"]["effects"][0]["params"]["muscle_tone"], rel=1e-6)
    assert fitted[1] == pytest.approx(0.1, rel=0.25)
    stiff = next(e for e in rec["effects"] if e["name"] == "stiffness")
    assert stiff["shared"] is True


def test_another_patient_is_refused(patient, forward):
    """Scans of other faces: another synthetic patient's front (it superimposes within 3 mm
    but most of it lies more than 2 mm off), and this one 30 % larger."""
    import trimesh

    from facemodel.synthetic import synthetic_head
    from planner.diagnosis.gap import measure_gap

    head = synthetic_head(3, size=2.0)
    v, f = np.asarray(head.skin.vertices), np.asarray(head.skin.faces)
    front = trimesh.Trimesh(v, f, process=False).face_normals[:, 1] > 0.05
    with pytest.raises(InputError, match="another-3.stl.*another patient"):
        measure_gap(patient, forward.baseline(0), Surface(v, f[front], __import__("pathlib").Path("another-3.stl")))
    scan = _scan(patient, [], seed=5, perturb=False, forward=forward)
    c = scan.vertices.mean(axis=0)
    with pytest.raises(InputError, match="synthetic-5.stl"):
        measure_gap(patient, forward.baseline(0), Surface((scan.vertices - c) * 1.3 + c, scan.faces, scan.path))


def test_partial_scan_warns_and_reports_uncovered_regions(patient, forward):
    from planner.diagnosis.gap import measure_gap

    scan = _scan(patient, [], seed=6, perturb=False, forward=forward)
    v = scan.vertices
    keep_v = v[:, 2] > np.percentile(v[:, 2], 80)          # the upper band of the face only
    keep_f = keep_v[scan.faces].all(axis=1)
    gap = measure_gap(patient, forward.baseline(0), Surface(v, scan.faces[keep_f], scan.path))
    assert gap.coverage < 0.2
    assert any("covers only" in w for w in gap.warnings)
    assert {"chin", "lower_lip"} <= set(gap.uncovered_regions)


def test_a_baseline_with_a_contact_left_unmet_is_a_warning(patient, forward):
    """A baseline solve that converged with a contact deeper than twice its tolerance
    (`facemodel.simulation`'s contact_unmet_mm) is not silently diagnosed: diagnosis.json's
    warnings name the contact and its depth. The shared solves are reused; the stand-in runner
    only adds the report of an unmet lip contact to the baseline."""
    from planner.diagnosis.forward import SENSITIVITIES

    class Reported:
        n_workers = 1

        def map(self, cases, requests, on_done=None, guesses=None):
            out = []
            for k, (i, s) in enumerate(requests):
                res = forward.solve([(0, s)])[0]
                unmet = {"lip_contact": 0.31} if not s or s[0] == SENSITIVITIES else {}
                out.append((*res, unmet) if s and s[0] == SENSITIVITIES else (res, unmet))
                if on_done:
                    on_done(k)
            return out

    scan = _scan(patient, [], seed=3, perturb=False, forward=forward)
    fwd = Forward([patient], Reported())
    rec = diagnose_data([patient], [scan], forward=fwd, effect_names=("muscle_tone",))["record"]
    assert fwd.contact_unmet(0) == {"lip_contact": 0.31}
    assert any("lip_contact 0.31 mm" in w for w in rec["warnings"]), rec["warnings"]
    # an effect solve that met its contacts reports nothing
    assert fwd.contact_unmet(0, ("muscle_tone=0.5",)) == {}


class _DoneCluster:
    """A runner whose futures are done at submission: `result(cases, i, strings, guess)` gives
    each; `submitted` records (case index, strings) in submission order."""

    n_workers = 2

    def __init__(self, result):
        self.result = result
        self.submitted = []

    def submit(self, cases, requests, guesses=None):
        from types import SimpleNamespace

        guesses = guesses or {}
        self.submitted.extend(requests)
        return [SimpleNamespace(key=len(self.submitted) + k, value=self.result(cases, i, s, guesses.get(i)))
                for k, (i, s) in enumerate(requests)]

    def gather(self, futures, on_done=None):
        for k in range(len(futures)):
            if on_done:
                on_done(k)
        return [f.value for f in futures]

    def map(self, cases, requests, on_done=None, guesses=None):
        return self.gather(self.submit(cases, requests, guesses), on_done)


def test_prefetched_solves_are_collected_once_with_the_same_results():
    """`Forward.prefetch` starts solves without waiting; the later `solve` collects them: each
    request is submitted once, and the results are those of solving when asked. A runner
    that cannot submit (solves in this process) makes prefetch a no-op."""
    from types import SimpleNamespace

    cluster = _DoneCluster(lambda cases, i, s, guess: (np.full((2, 3), float(i) + len(s)), {}))
    submitted = cluster.submitted
    cases = [SimpleNamespace(name="a"), SimpleNamespace(name="b")]
    fwd = Forward(cases, cluster)
    fwd.prefetch([(0, ()), (1, ("gravity=1",)), (0, ())])
    assert submitted == [(0, ()), (1, ("gravity=1",))]          # a repeated request once
    out = fwd.solve([(1, ("gravity=1",)), (0, ()), (1, ())])
    assert submitted == [(0, ()), (1, ("gravity=1",)), (1, ())]  # only the new one submitted
    assert [float(o[0, 0]) for o in out] == [2.0, 0.0, 1.0]
    fwd.prefetch([(0, ())])                                     # already solved: nothing starts
    assert len(submitted) == 3 and fwd.n_solves == 3

    class InProcess:                            # no submit: prefetch does nothing
        n_workers = 1

        def map(self, cases, requests, on_done=None, guesses=None):
            return [(np.zeros((2, 3)), {}) for _ in requests]

    local = Forward(cases, InProcess())
    local.prefetch([(0, ())])
    assert not local._pending
    assert np.all(local.solve([(0, ())])[0] == 0.0)


def test_a_solve_with_sensitivities_serves_the_plain_solve_of_the_same_effects():
    """A sensitivity request (at the baseline or with effects, as a refinement's solve asks)
    stores its skin as the plain solve of the same effects: asking for that plain solve later
    submits nothing more, and the contacts it left unmet are those of the plain solve too."""
    from types import SimpleNamespace

    from planner.diagnosis.forward import SENSITIVITIES

    def result(cases, i, s, guess):
        strings = s[2] if len(s) > 2 else ()
        skin = np.full((2, 3), float(i) + len(strings))
        return (skin, {"gravity": np.ones((2, 3))}, None, {"lip_contact": 0.3} if strings else {})

    cluster = _DoneCluster(result)
    cases = [SimpleNamespace(name="a")]
    fwd = Forward(cases, cluster)
    (skin, sens, _), = fwd.solve([(0, (SENSITIVITIES, ("gravity",), ("gravity=1",)))])    # as `refine` asks
    assert isinstance(sens, dict)
    fwd.sensitivities([("gravity",)])
    n = len(cluster.submitted)
    plain = fwd.solve([(0, ("gravity=1",)), (0, ())])
    assert len(cluster.submitted) == n == 2
    assert np.array_equal(plain[0], skin) and float(plain[1][0, 0]) == 0.0
    assert fwd.contact_unmet(0, ("gravity=1",)) == {"lip_contact": 0.3}


def test_the_early_refinement_asks_for_exactly_the_solves_refine_collects(patient, forward):
    """On a cluster the first refinement of an effect the tangent alone sets up (tone) starts
    with the switch solves (`analysis.first_refinement_requests`): the very requests `refine`
    then makes. A runner that solves at submission and records the order shows it: no request
    is submitted twice, none is left uncollected, tone's first refinement is submitted before
    the sliding switch's settings (which wait for the switch solves). The solves being the ones
    `refine` asks for, the diagnosis is the one without the early start (the cluster against
    this process: `test_diagnose_cli`)."""
    from planner.diagnosis.forward import _solve_task

    _diagnose(patient, forward, "tone", ["muscle_tone=0.15"], seed=1)      # makes and keeps the scan
    scan = _RESULTS["tone_scan"]
    cluster = _DoneCluster(lambda cases, i, s, guess: _solve_task(cases[i], s, guess))
    fwd = Forward([patient], cluster)
    effects = ("sliding", "muscle_tone")
    rec = diagnose_data([patient], [scan], forward=fwd, effect_names=effects, boundary=())["record"]
    submitted = cluster.submitted
    assert len(submitted) == len(set(submitted)) and not fwd._pending
    # the effect strings of every solve, in submission order (a refinement's solve of an effect
    # with tangents brings them: a sensitivity request with the strings last)
    mine = [s if all(isinstance(x, str) for x in s) else s[2] for _, s in submitted
            if all(isinstance(x, str) for x in s) or len(s) > 2]
    tone = next(k for k, s in enumerate(mine) if any(x.startswith("muscle_tone=") for x in s))
    hold = next(k for k, s in enumerate(mine) if any(x.startswith("sliding.hold=") for x in s))
    assert tone < hold
    assert rec["verdict"]["effect"] == "muscle_tone"


# --------------------------------------------------------------------------- parts

def test_effect_strings_parse_and_none_is_the_baseline(patient):
    from planner.pipeline import parse_effects

    for e in available_effects(("maxilla",)):
        if e.parameters:
            assert e.values(e.origin) == {}                # "none" adds nothing: the baseline
            parse_effects(list(effect_strings(e.values(e.origin + np.array([p.step for p in e.parameters])))))
        for choice in e.choices:
            parse_effects(list(effect_strings(dict(choice))))


def test_fitted_ranges_lie_in_the_models_and_reach_what_synth_can_draw():
    # A fit bounded below a value the model takes stops short and leaves the rest of the gap to
    # other effects; `faceplan synth` sets posture and swelling from a published skin change,
    # clipped only to the model's own bounds, so the diagnosis must reach those bounds.
    from facemodel import effects as fe

    moved = ("maxilla", "mandible", "chin")
    lib = {p.key: p for e in available_effects(moved) for p in e.parameters}
    model = {q.name: q for name in fe.EFFECT_NAMES for q in fe.parameters(name, moved)}
    for key, p in lib.items():
        q = model[key]
        assert q.lower <= p.lower <= p.none < p.upper <= q.upper and p.none == q.none, key
    assert lib["gravity"].upper == fe.GRAVITY_MAX
    assert lib["swelling"].upper == fe.SWELLING_MAX


def test_linearised_gap_matches_finite_differences(patient, forward):
    """ScanGap.linearised against central differences of the exact distances for a smooth
    skin motion (0.01 mm steps: where the closest point stays on its triangle the quotient
    agrees to second order, ~1e-8; points whose closest point crosses an edge within the step,
    ~1 %, differ by the kink of the distance function there)."""
    from planner.diagnosis.gap import measure_gap

    scan = _scan(patient, [], seed=7, perturb=False, forward=forward)
    skin = forward.baseline(0)
    gap = measure_gap(patient, skin, scan)
    v = np.sin(skin / 20.0) * np.array([0.3, 1.0, 0.5])
    lin = gap.linearised(skin, v, pose=False)
    h = 0.01
    fd = (gap.distances(skin + h * v, pose=False) - gap.distances(skin - h * v, pose=False)) / (2 * h)
    assert np.median(np.abs(lin - fd)) < 1e-5
    assert np.mean(np.abs(lin - fd) < 2e-2) > 0.98
    raw = np.sqrt(np.mean((lin - fd) ** 2))
    # with the pose re-fitted on the unoperated regions (linear in the gap, so the derivative
    # is corrected as the distances are): the kinks' few differences on the unoperated regions
    # are spread by the six-parameter pose fit over the face, so the comparison is in RMS: the
    # error stays of the order of the kinks' own (at most twice theirs)
    lin = gap.linearised(skin, v)
    fd = (gap.distances(skin + h * v) - gap.distances(skin - h * v)) / (2 * h)
    assert np.sqrt(np.mean((lin - fd) ** 2)) < 2.0 * raw


def test_the_pose_is_refitted_to_a_prediction_that_moves_the_superimposed_regions(patient, forward):
    """A prediction that moves the unoperated regions needs the scan's pose re-fitted to it,
    as compare superimposes a scan on a prediction. Here the prediction is the baseline
    itself moved rigidly, so the scan's gap to it, once re-posed, is the baseline's gap:
    `ScanGap.distances` gives it within 0.002 mm RMS whether the motion is 0.1 mm and 0.1
    degree or 1.5 mm and 1.5 degrees (the iteration's tolerance is a micrometre). The
    point-to-plane fit about the baseline's closest points (`realign`, kept for the
    Jacobians) cannot see a motion along the superimposed surfaces, which changes the
    distances at second order only, and leaves a rest that grows with the motion: more than
    ten times the re-posed one at 1.5 mm and 1.5 degrees."""
    from planner.compare.alignment import rotation_matrix
    from planner.diagnosis.gap import measure_gap

    scan = _scan(patient, [], seed=8, perturb=False, forward=forward)
    skin = np.asarray(forward.baseline(0), float)
    gap = measure_gap(patient, skin, scan)
    r0 = gap.distances(skin)
    centre = skin.mean(axis=0)

    def moved(mm, deg):
        axis = np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])
        return (skin - centre) @ rotation_matrix(axis * np.radians(deg)).T + centre + mm * np.array([0.0, 0.6, 0.8])

    for mm_deg in (0.1, 1.5):
        assert gap.rms(gap.distances(moved(mm_deg, mm_deg)) - r0) < 0.002, mm_deg
    far = moved(1.5, 1.5)
    linear = gap.rms(gap.realign(gap.distances(far, pose=False)) - gap.realign(gap.distances(skin, pose=False)))
    assert linear > 10 * gap.rms(gap.distances(far) - r0) and linear > 0.05, linear


def test_linearised_on_another_face_matches_finite_differences(patient, forward):
    """ScanGap.linearised_on (a second mesh's predicted face) is the same linearisation as
    `linearised`: on the model's own face it agrees with it to round-off, and against central
    differences of the exact distances it meets the same bounds (see the test above)."""
    from planner.diagnosis.gap import measure_gap

    scan = _scan(patient, [], seed=7, perturb=False, forward=forward)
    skin = forward.baseline(0)
    gap = measure_gap(patient, skin, scan)
    v = np.cos(skin / 15.0) * np.array([0.5, 0.8, 0.3])
    verts, faces = patient.predicted_surface(skin)
    dv = v if patient.surface is None else patient.surface.carry_velocity(v)
    on = gap.linearised_on(verts, faces, dv, pose=False)
    assert np.allclose(on, gap.linearised(skin, v, pose=False), atol=1e-12)
    h = 0.01
    fd = (gap.distances_to(verts + h * dv, faces, pose=False)
          - gap.distances_to(verts - h * dv, faces, pose=False)) / (2 * h)
    assert np.median(np.abs(on - fd)) < 1e-5
    assert np.mean(np.abs(on - fd) < 2e-2) > 0.98


def test_fitted_values_are_those_of_the_converged_mesh():
    """The diagnosis mesh responds to an effect 30 % less than the converged model
    (J_true = 1.3 J_d on the gap) and the second mesh lies between them as a first-order
    Richardson pair does (J_ref = J_d + (J_true - J_d) / kappa, kappa = 4/3: a mesh twice as
    fine). On J_d alone the fit finds 1.3x the true coordinates; with the Jacobian's mesh
    correction C = kappa (J_ref - J_d) the candidate's Jacobian is J_true and the fit gives the
    true coordinates back exactly (linear algebra: 1e-10), a fixed parameter staying at its
    origin. A full solve on the diagnosis mesh (here linear: r_d(theta) = r0 + J_d theta)
    corrected by `Candidate.corrected` is the converged model's gap, r0 + J_true theta, in
    both of its forms."""
    from types import SimpleNamespace

    from planner.diagnosis.analysis import Candidate, _fit_theta
    from planner.diagnosis.effects import Parameter

    rng = np.random.default_rng(3)
    n = 300
    Jd = rng.normal(size=(n, 3))
    w = rng.uniform(0.5, 2.0, n)
    true = np.array([0.4, -0.25, 0.0])
    free = np.array([True, True, False])
    kappa = 4.0 / 3.0
    J_true = 1.3 * Jd
    Jr = Jd + (J_true - Jd) / kappa
    r0 = -J_true @ true                       # the gap the effect leaves at the origin
    params = tuple(Parameter(f"p{k}", 0.0, -1.0, 1.0, 0.01) for k in range(3))
    data = [SimpleNamespace(gap=SimpleNamespace(weights=w), r0=r0, mesh_coef=-kappa)]

    def candidate(C):
        cand = Candidate("e", (), False, 1, params)
        cand.theta, cand.anchor_r, cand.J, cand.C = [np.zeros(3)], [r0], [Jd + C], [C]
        cand.free = free
        return cand

    plain = _fit_theta(candidate(np.zeros((n, 3))), data, [0])
    assert np.allclose(plain[free], 1.3 * true[free], atol=1e-10)
    cand = candidate(kappa * (Jr - Jd))
    got = _fit_theta(cand, data, [0])
    assert np.allclose(got, true, atol=1e-10)
    theta = np.array([0.3, 0.1, 0.0])
    assert np.allclose(cand.corrected(0, data[0], r0 + Jd @ theta, theta), r0 + J_true @ theta, atol=1e-10)
    # without a correction the gap is left as solved
    assert candidate(np.zeros((n, 3))).corrected(0, data[0], r0, theta) is r0
    # every parameter with a reference tangent and no discrete choice: the solve's own change
    # from the origin is replaced, to the factor kappa, by the reference's linear one. On a
    # linear response that is the same correction; a nonlinear part q of the diagnosis mesh's
    # response is kept to the factor 1 - kappa (the converged response r_d + kappa (r_ref - r_d)
    # with r_ref linear)
    cand.KR = [kappa * Jr]
    assert np.allclose(cand.corrected(0, data[0], r0 + Jd @ theta, theta), r0 + J_true @ theta, atol=1e-10)
    q = 0.05 * rng.normal(size=n)
    assert np.allclose(cand.corrected(0, data[0], r0 + Jd @ theta + q, theta), r0 + J_true @ theta + (1 - kappa) * q,
                       atol=1e-10)
    # a coarser second mesh corrects the baseline's gap only: the effects keep the diagnosis
    # mesh's response (no extrapolation away from the coarser mesh)
    from planner.diagnosis.analysis import mesh_corrections

    coarser = SimpleNamespace(mesh_coef=-kappa, reference_sens={"p0": np.zeros((4, 3))}, reference_coarser=True)
    assert mesh_corrections(coarser, None, {"p0": np.zeros((4, 3))}) == {}


def test_linear_fit_recovers_parameters_within_bounds():
    rng = np.random.default_rng(0)
    J = rng.normal(size=(200, 2))
    w = rng.uniform(0.5, 2.0, 200)
    theta = np.array([0.3, -0.2])
    r_a = -J @ theta                        # r(theta) = r_a + J theta vanishes at theta
    got = fit.linear_fit(r_a, J, w, np.zeros(2), np.array([-1, -1]), np.array([1, 1]))
    assert np.allclose(got, theta, atol=1e-10)
    # a bound: the constrained optimum of a convex quadratic lies on it
    got = fit.linear_fit(r_a, J, w, np.zeros(2), np.array([-1, 0.0]), np.array([1, 1]))
    assert got[1] == pytest.approx(0.0, abs=1e-12)


def test_linear_fit_with_a_prior_is_the_ridge_solution():
    """A Gaussian prior about the fixed value: the unbounded optimum of sum w r^2 + lam sum
    ((theta - c) / sd)^2 is the ridge solution (J^T W J + lam P^-1)^-1 (J^T W (J theta_a - r_a)
    + lam P^-1 c) (1e-9: one linear system solved two ways); a flat prior (inf) is the plain
    fit, and a parameter without a prior beside one with a prior keeps the data's pull."""
    rng = np.random.default_rng(3)
    J = rng.normal(size=(200, 2))
    w = rng.uniform(0.5, 2.0, 200)
    theta_a, c = np.array([0.1, -0.1]), np.array([0.0, 0.2])
    r_a = -J @ (np.array([0.3, -0.2]) - theta_a) + rng.normal(0, 0.05, 200)
    lo, hi = np.array([-5.0, -5.0]), np.array([5.0, 5.0])
    sd, lam = np.array([0.05, 0.1]), 0.7
    got = fit.linear_fit(r_a, J, w, theta_a, lo, hi, fixed_value=c, prior_sd=sd, prior_weight=lam)
    Pinv = np.diag(lam / sd ** 2)
    want = np.linalg.solve((J.T * w) @ J + Pinv, (J.T * w) @ (J @ theta_a - r_a) + Pinv @ c)
    assert np.allclose(got, want, atol=1e-9)
    plain = fit.linear_fit(r_a, J, w, theta_a, lo, hi, fixed_value=c)
    flat = fit.linear_fit(r_a, J, w, theta_a, lo, hi, fixed_value=c, prior_sd=np.full(2, np.inf), prior_weight=lam)
    assert np.allclose(flat, plain, atol=1e-12)
    half = fit.linear_fit(r_a, J, w, theta_a, lo, hi, fixed_value=c, prior_sd=np.array([np.inf, 0.1]),
                          prior_weight=lam)
    Pinv = np.diag([0.0, lam / 0.1 ** 2])
    want = np.linalg.solve((J.T * w) @ J + Pinv, (J.T * w) @ (J @ theta_a - r_a) + Pinv @ c)
    assert np.allclose(half, want, atol=1e-9)


def test_finite_difference_jacobian_is_second_order():
    """Central and one-sided second-order differences of r(t) = exp(t) at t = 0: errors fall
    as h^2 (ratio ~4 when h halves)."""
    def err(h, one_sided):
        r0 = np.array([1.0])
        a, b = (h, 2 * h) if one_sided else (-h, h)
        J = fit.finite_difference_jacobian(r0, [(a, b, np.exp([a]), np.exp([b]))])
        return abs(J[0, 0] - 1.0)
    for one_sided in (False, True):
        assert err(0.1, one_sided) / err(0.05, one_sided) == pytest.approx(4.0, rel=0.1)


def test_standard_errors_match_least_squares_covariance():
    """With independent points (n_eff = n, unit weights) the Cramer-Rao error is the textbook
    sigma sqrt((J^T J)^-1)_kk; a zero column is undetermined."""
    rng = np.random.default_rng(1)
    J = rng.normal(size=(50, 2))
    se = fit.standard_errors(J, np.ones(50), 0.3, 50)
    assert np.allclose(se, 0.3 * np.sqrt(np.diag(np.linalg.inv(J.T @ J))), rtol=1e-10)
    se = fit.standard_errors(np.column_stack([J[:, 0], np.zeros(50)]), np.ones(50), 0.3, 50)
    assert np.isfinite(se[0]) and np.isinf(se[1])


def test_broyden_update_satisfies_the_secant_condition():
    rng = np.random.default_rng(2)
    J = rng.normal(size=(30, 2))
    d, dr = rng.normal(size=2), rng.normal(size=30)
    assert np.allclose(fit.broyden(J, d, dr) @ d, dr)


def test_bic_prefers_the_true_model_and_penalises_noise_fits():
    rng = np.random.default_rng(3)
    n = 400
    noise = rng.normal(0, 0.2, n)
    w = np.ones(n)
    # a parameter that only fits noise lowers the RSS by about sigma^2 per parameter: BIC worse
    x = rng.normal(size=n)
    beta = (x @ noise) / (x @ x)
    rss0, rss1 = np.sum(noise ** 2), np.sum((noise - beta * x) ** 2)
    assert fit.bic(rss1, n, n, 1) > fit.bic(rss0, n, n, 0)
    p = fit.model_probabilities({"a": 0.0, "b": 2 * np.log(3.0)})
    assert p["a"] == pytest.approx(0.75) and p["b"] == pytest.approx(0.25)


def test_predictive_weights_are_pseudo_bma_plus():
    # a constant gain d per fold over n folds: every Bayesian-bootstrap draw sums it to n d
    # exactly (the Dirichlet weights sum to one), so the weights are softmax of the totals,
    # exp(n d) / (1 + exp(n d)), to round-off
    n, d = 12, 0.1
    w = fit.predictive_weights({"base": np.zeros(n), "effect": np.full(n, d)})
    assert w["effect"] == pytest.approx(1.0 / (1.0 + np.exp(-n * d)), rel=1e-12)
    assert sum(w.values()) == pytest.approx(1.0, abs=1e-12)
    # equal predictions share the weight
    lpd = np.random.default_rng(0).normal(size=n)
    w = fit.predictive_weights({"a": lpd, "b": lpd.copy()})
    assert w["a"] == pytest.approx(0.5, abs=1e-12)
    # the same total gain of 6 nats carried by one fold only: the draws weight that fold by
    # alpha_0 ~ Beta(1, n - 1), so the weight is E[sigmoid(6 n alpha_0)] (quadrature below),
    # well short of the exp(6) / (1 + exp(6)) = 0.9975 the sums alone give; the Monte Carlo
    # mean over 1000 draws is within 0.02 of it (the sigmoid's spread is ~0.2, so 3 standard
    # errors), while a gain spread over every fold keeps the full weight
    from scipy import integrate, stats

    one = np.zeros(n)
    one[0] = 6.0
    expected = integrate.quad(lambda a: stats.beta.pdf(a, 1, n - 1) / (1.0 + np.exp(-6.0 * n * a)), 0, 1)[0]
    w_one = fit.predictive_weights({"base": np.zeros(n), "effect": one})["effect"]
    w_all = fit.predictive_weights({"base": np.zeros(n), "effect": np.full(n, 6.0 / n)})["effect"]
    assert w_one == pytest.approx(expected, abs=0.02)
    assert w_all == pytest.approx(1.0 / (1.0 + np.exp(-6.0)), rel=1e-9)
    assert w_one < 0.95 < w_all
    # the weights depend on the data only (a fixed bootstrap seed): the same call, the same answer
    assert fit.predictive_weights({"base": np.zeros(n), "effect": one})["effect"] == w_one


def test_heldout_gain_probability_keeps_the_skew_of_few_folds():
    # A gain d = (-L, g, ..., g) over n folds: a Bayesian-bootstrap draw sums it to
    # n(-L a0 + g (1 - a0)) with a0 ~ Beta(1, n - 1), positive when a0 < g / (g + L), so the
    # probability is 1 - (L / (g + L))^(n - 1) exactly. The Monte Carlo share of 4000 draws is
    # within 0.027 of it (4 standard errors of a proportion near 0.77).
    n, g, L = 9, 4.0, 20.0
    exact = 1.0 - (L / (g + L)) ** (n - 1)
    assert fit.gain_probability([-L] + [g] * (n - 1)) == pytest.approx(exact, abs=0.027)
    # a gain carried by the one region an effect acts on, with no region losing, is certain,
    # where the normal rule (sum >= 2 sqrt(n) sd) rejects it: 48 against 2 x 37
    one = np.array([40.0] + [1.0] * 8)
    assert one.sum() < 2.0 * np.sqrt(len(one)) * one.std()
    assert fit.gain_probability(one) == 1.0
    # no gain, or a single fold: the sign decides
    assert fit.gain_probability([]) == 0.0
    assert fit.gain_probability([2.0]) == 1.0 and fit.gain_probability([-2.0]) == 0.0
    # a function of the data alone
    d = np.random.default_rng(3).normal(0.2, 1.0, 9)
    assert fit.gain_probability(d) == fit.gain_probability(d.copy())


@pytest.mark.parametrize("seed", range(3))
def test_heldout_gain_probability_is_the_normal_one_for_many_folds(seed):
    # with many exchangeable folds the bootstrapped sum is nearly normal with the standard
    # error sqrt(n) sd, so the probability approaches Phi(sum / se): within 0.03 for 400 folds
    # (the Monte Carlo standard error is at most 0.008 at 4000 draws, and the bootstrap's
    # variance is the sample's times n / (n + 1))
    from scipy import stats

    d = np.random.default_rng(seed).normal(0.1, 1.0, 400)
    normal = stats.norm.cdf(d.sum() / (np.sqrt(len(d)) * d.std()))
    assert fit.gain_probability(d) == pytest.approx(normal, abs=0.03)


def test_a_gain_in_one_region_with_none_lost_wins_on_heldout_data():
    # the judging of one effect from its per-region held-out densities: strong evidence (BIC
    # gain 150), a held-out shrinkage beyond the noise well above 10 %, and a density gain of
    # 48 carried by the one region the effect acts on. It is significant; with that region's
    # gain turned into a loss outweighing the rest it is not.
    from planner.diagnosis import analysis

    def judged(diff):
        s = analysis.Scored(None, 0.2, 0.25, 30.0, 25.0, 5.0, 0.0, True, [], [])
        s.gp_bic, s.noise_shrink_pct, s.noise_spread_pct = -150.0, 40.0, 5.0
        s.lpd = np.asarray(diff, float)
        analysis._judge([s], 0.0, np.zeros(len(diff)))
        return s

    s = judged([40.0] + [1.0] * 8)
    assert s.wins_heldout and s.significant and s.lpd_gain == pytest.approx(48.0)
    s = judged([-40.0] + [1.0] * 8)
    assert not s.wins_heldout and not s.significant


def test_a_switch_is_fitted_with_its_converged_mesh_response():
    """A discrete choice (`sliding=1`) has no derivative to extrapolate: it is solved on the
    second mesh too. Here the diagnosis mesh's switch changes the gap by 0.6 T, T the converged
    model's change, and the second mesh lies between them as a Richardson pair does
    (dr_ref = dr_d + (T - dr_d) / kappa, kappa = 4/3). The choice's correction kappa (dr_ref -
    dr_d) makes the candidate's gap the converged model's, r0 + T, to round-off (1e-12: sums of
    the same vectors); a scan made with the switch on is then matched exactly, where the
    diagnosis mesh alone leaves 0.4 T. Every later solve with the choice gets the same
    correction (`Candidate.corrected`), a pair carries it, and without a finer second mesh
    nothing is corrected."""
    from types import SimpleNamespace

    from planner.diagnosis import analysis
    from planner.diagnosis.effects import Effect

    rng = np.random.default_rng(5)
    n, kappa = 200, 4.0 / 3.0
    T = rng.normal(0.0, 0.5, n)
    r0 = -T                                      # the scan was made with the switch on
    dr_d = 0.6 * T
    dr_ref = dr_d + (T - dr_d) / kappa
    base_ref = rng.normal(0.0, 0.3, n)           # the second mesh's own baseline gap
    key = ("sliding=1",)

    class Fwd:                                   # skins are the gaps themselves
        def __init__(self, skins):
            self.skins = skins

        def solve(self, reqs):
            return [self.skins[k] for _, k in reqs]

        def baseline(self, c):
            return self.skins[()]

    gap = SimpleNamespace(weights=np.ones(n), distances=lambda s: np.asarray(s, float),
                          distances_to=lambda v, f: np.asarray(v, float), rms=lambda r: float(np.sqrt(np.mean(r * r))))
    ref = SimpleNamespace(predicted_surface=lambda s: (s, None))

    def case(second=True, coarser=False):
        return SimpleNamespace(case=SimpleNamespace(name="case"), gap=gap, r0=r0,
                               mesh_coef=-kappa if second else None, reference=ref,
                               reference_skin=base_ref, reference_coarser=coarser, reference_index=0,
                               reference_forward=Fwd({(): base_ref, key: base_ref + dr_ref}) if second else None,
                               choice_mesh={}, mesh_jac={})

    forward = Fwd({(): r0, key: r0 + dr_d})
    sliding = Effect("sliding", choices=((("sliding", 1),),))
    d = case()
    analysis.choice_corrections([d], [sliding], forward)
    assert np.allclose(d.choice_mesh[key], T - dr_d, atol=1e-12)
    cand = analysis._single_candidate(sliding, [d], forward, [{}])
    assert np.allclose(cand.anchor_r[0], 0.0, atol=1e-12)
    assert np.allclose(cand.corrected(0, d, r0 + dr_d, np.zeros(0)), 0.0, atol=1e-12)
    other = analysis.Candidate("tone", (), False, 1)
    other.theta, other.J, other.C, other.KR, other.M = [np.zeros(0)], [np.zeros((n, 0))], [np.zeros((n, 0))], [None], [None]
    pair = analysis._pair(cand, other, [d])
    assert np.allclose(pair.M[0], T - dr_d, atol=1e-12)
    # without a second mesh, or with a coarser one, the diagnosis mesh's response stays
    for other in (case(second=False), case(coarser=True)):
        analysis.choice_corrections([other], [sliding], forward)
        assert other.choice_mesh == {}
        plain = analysis._single_candidate(sliding, [other], forward, [{}])
        assert np.allclose(plain.anchor_r[0], r0 + dr_d, atol=1e-12)
        assert plain.M == [None]


def _saturating_case(jump_after=None):
    """A one-parameter effect whose gap along a pattern phi is a(theta) - b, a(theta) =
    1 - exp(-theta / 0.1) (a response that saturates, as a muscle's tone against the lips), and
    past `jump_after` 0.8 lower (another equilibrium branch). The fake forward returns the gap
    itself as the skin and, asked for sensitivities, da/dtheta phi."""
    from types import SimpleNamespace

    from planner.diagnosis import analysis
    from planner.diagnosis.effects import Effect, Parameter
    from planner.diagnosis.forward import SENSITIVITIES

    n, b, tau = 200, 0.6, 0.1
    phi = np.sin(np.linspace(0.0, np.pi, n))

    def a(t):
        return 1.0 - np.exp(-t / tau) - (0.8 if jump_after is not None and t > jump_after else 0.0)

    def slope(t):
        return np.exp(-t / tau) / tau

    def theta_of(strings):
        return float(strings[0].split("=")[1]) if strings else 0.0

    class Fwd:
        def __init__(self):
            self.asked = []

        def solve(self, reqs):
            out = []
            for _, s in reqs:
                if s and s[0] == SENSITIVITIES:
                    t = theta_of(s[2])
                    self.asked.append(t)
                    out.append(((a(t) - b) * phi, {"tone": slope(t) * phi}, None))
                else:
                    t = theta_of(s)
                    self.asked.append(t)
                    out.append((a(t) - b) * phi)
            return out

        def baseline(self, c):
            return (a(0.0) - b) * phi

    gap = SimpleNamespace(weights=np.ones(n), distances=lambda s: np.asarray(s, float),
                          linearised=lambda skin, ds: np.asarray(ds, float), noise_floor_mm=0.01,
                          noise_n_eff=lambda: 50.0)
    d = SimpleNamespace(case=SimpleNamespace(name="case"), gap=gap, r0=(a(0.0) - b) * phi,
                        mesh_jac={}, choice_mesh={}, mesh_coef=None)
    effect = Effect("tone", (Parameter("tone", 0.0, 0.0, 0.35, 0.02),))
    return analysis, effect, d, Fwd(), phi, slope, -tau * np.log(1.0 - b)


def test_refinement_steps_take_the_tangent_at_the_new_anchor():
    """Where the model gives the tangent, an accepted refinement step's Jacobian is the
    tangent at the new anchor (a Gauss-Newton step on the exact local model: on a saturating
    response two steps from the origin land within 6 % of the optimum, 0.0916, where the secant
    of Broyden's update, which lags behind the flattening, stops 13 % short); without it the
    secant stays. The figures are those of Newton's and the secant method's second iterate on
    this function, computed by hand: 0.0871 and 0.0798."""
    analysis, effect, d, fwd, phi, slope, best = _saturating_case()
    exact = analysis._single_candidate(effect, [d], fwd, [{"tone": slope(0.0) * phi}])
    assert exact.tangent == [True]
    analysis.refine([exact], [d], fwd)
    t = float(exact.theta[0][0])
    assert abs(t - 0.0871) < 1e-3 and abs(t - best) < 0.06 * best
    # the solve is made at the value written with six digits (`Candidate.values`): the tangent
    # there differs from that at t by |t - round(t, 6)| / 0.1 < 1e-5 relative
    assert np.allclose(exact.J[0][:, 0], slope(t) * phi, rtol=1e-5)
    # no tangent (finite differences, here the baseline's tangent given but marked as not
    # available at other values): Broyden's secant
    secant = analysis._single_candidate(effect, [d], fwd, [{"tone": slope(0.0) * phi}])
    secant.tangent = [False]
    analysis.refine([secant], [d], fwd)
    ts = float(secant.theta[0][0])
    assert abs(ts - 0.0798) < 1e-3 and abs(ts - best) > 0.1 * best


def test_the_tangent_at_a_new_anchor_is_the_derivative_of_the_mesh_corrected_gap():
    """`Candidate.jacobian_at` is d/dtheta of `Candidate.corrected` (the gap extrapolated to
    the converged mesh) at a point away from the origin, with the second mesh's tangent (the
    solve's own change scaled by 1 + kappa, plus kappa J_ref) and without it (the linear mesh
    correction C added): against central differences of `corrected` over full solves.
    Tolerance 1e-4 relative: the step h = 1e-4 leaves a truncation error of h^2 a3 / (6 a1)
    = h^2 / (6 tau^2), about 2e-7 relative, on this response (a1, a3 its first and third
    derivatives, tau = 0.1), and rounding in the differences is below 1e-10."""
    analysis, effect, d, fwd, phi, slope, _ = _saturating_case()
    d.mesh_jac = {"tone": 0.3 * np.cos(np.linspace(0.0, np.pi, len(phi)))}
    d.mesh_coef = 0.5
    t, h = 0.04, 1e-4

    def gap_at(theta):
        return np.asarray(fwd.solve([(0, (f"tone={theta:.10g}",))])[0], float)

    for with_reference in (True, False):
        cand = analysis._single_candidate(effect, [d], fwd, [{"tone": slope(0.0) * phi}])
        assert (cand.KR[0] is not None) and np.any(cand.C[0])
        if not with_reference:
            cand.KR = [None]
        skin, sens, _ = fwd.solve([(0, ("sensitivities", ("tone",), (f"tone={t:.10g}",)))])[0]
        J = cand.jacobian_at(0, d, skin, sens, np.array([t]))
        fd = (cand.corrected(0, d, gap_at(t + h), np.array([t + h]))
              - cand.corrected(0, d, gap_at(t - h), np.array([t - h]))) / (2.0 * h)
        assert np.allclose(J[:, 0], fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())


def test_a_refused_refinement_step_is_halved_where_the_tangent_is_known():
    """A step onto another equilibrium branch (past 0.05 the response drops by 0.8: a worse
    gap than the anchor's) is refused, the anchor and its tangent stay, and the next step is
    half as long: the point half-way, 0.03, then lowers the gap and becomes the anchor, with
    the tangent there. The refused point's secant is never used."""
    analysis, effect, d, fwd, phi, slope, _ = _saturating_case(jump_after=0.05)
    cand = analysis._single_candidate(effect, [d], fwd, [{"tone": slope(0.0) * phi}])
    analysis.refine([cand], [d], fwd)
    assert np.allclose(fwd.asked, [0.06, 0.03], atol=1e-6)
    assert abs(float(cand.theta[0][0]) - 0.03) < 1e-6
    assert np.allclose(cand.J[0][:, 0], slope(0.03) * phi, rtol=1e-9)


def test_a_switch_setting_is_chosen_by_the_evidence_not_the_residual():
    """`Effect.settings` (how freely the tissue slides): each value is solved with the chosen
    switch and kept when its gap is more likely under noise + discrepancy than the switch's
    default. Here the free slide leaves the smallest gap but a rough one (white structure at
    twice the noise), a held slide a larger but smooth one; an error model that prices
    rough structure as noise keeps the held one. A setting that fails to solve is skipped, the
    setting counts as one more discrete choice in the penalty, and without settings the
    switch is as it was."""
    from types import SimpleNamespace

    from planner.diagnosis import analysis
    from planner.diagnosis.effects import Effect

    rng = np.random.default_rng(3)
    n = 400
    x = np.linspace(0.0, 1.0, n)
    r0 = 0.8 * np.sin(np.pi * x)
    rough = 0.3 * rng.standard_normal(n)               # the free slide's residual
    smooth = 0.5 * np.sin(np.pi * x)                     # the held slide's residual
    skins = {(): r0, ("sliding=1",): rough, ("sliding.hold=0.5", "sliding=1"): smooth,
             ("sliding.hold=0.8", "sliding=1"): "solve failed"}

    class Fwd:
        def solve(self, reqs):
            return [skins[k] for _, k in reqs]

        def baseline(self, c):
            return r0

    def loglik(r):                                       # smooth fields are cheap, roughness is noise
        smooth_part = np.convolve(r, np.ones(41) / 41, mode="same")
        return -0.5 * float(np.sum((r - smooth_part) ** 2) / 0.1 ** 2 + 0.1 * np.sum(smooth_part ** 2))

    d = SimpleNamespace(case=SimpleNamespace(name="case"), r0=r0, choice_mesh={}, mesh_jac={},
                        gap=SimpleNamespace(weights=np.ones(n), distances=lambda s: np.asarray(s, float)),
                        error=SimpleNamespace(fit=lambda r: SimpleNamespace(loglik=loglik(r))))
    held = Effect("sliding", choices=((("sliding", 1),),), settings=(("sliding.hold", (0.5, 0.8)),))
    cand = analysis._single_candidate(held, [d], Fwd(), [{}])
    assert float(np.sum(rough ** 2)) < float(np.sum(smooth ** 2))      # the free slide fits closer
    assert cand.choices[0] == (("sliding", 1), ("sliding.hold", 0.5))
    assert np.array_equal(cand.anchor_r[0], smooth)
    assert cand.strings(0, cand.theta[0]) == ("sliding.hold=0.5", "sliding=1")
    assert analysis._discrete(cand) == 2 and held.n_parameters == 2
    free = Effect("sliding", choices=((("sliding", 1),),))
    plain = analysis._single_candidate(free, [d], Fwd(), [{}])
    assert plain.choices[0] == (("sliding", 1),) and analysis._discrete(plain) == 1
