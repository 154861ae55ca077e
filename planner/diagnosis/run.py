"""`faceplan diagnose` from case folders to the diagnosis record.

Per case: the case and its plan are read, the post-op scan is required (`postop/skin.*`), the
generic model is registered onto the patient (`planner.pipeline.register_case`, cached), the
baseline prediction is solved (`planner.diagnosis.forward`) and the scan is measured against it
(`planner.diagnosis.gap`); then every available effect is fitted, ranked and judged over all
cases together (`planner.diagnosis.analysis`). Everything is computed before anything is
written. `diagnose_data` runs the same on cases already prepared (tests, benchmarks).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from planner.diagnosis import analysis, discrepancy, fit
from planner.diagnosis.effects import available_effects
from planner.diagnosis.forward import Forward, Runner, prepare_case
from planner.diagnosis.gap import measure_gap, region_table
from planner.diagnosis.outputs import verdict_text
from planner.errors import InputError

__all__ = ["load_diagnosis_case", "diagnose_cases", "diagnose_data", "build_record", "mesh_reference",
           "BOUNDARIES", "DEFAULT_BOUNDARIES", "parse_boundaries"]

# the boundary conditions the model chooses and an independent model may choose otherwise
# (`facemodel.simulation`, `discrepancy` "Boundary conditions"): plan option (`model.<option>`,
# "free" or "held") -> the node set it holds, which the case model must have
BOUNDARIES = {"neck": "neck", "floor": "floor_of_mouth"}
# the boundaries carried by default: the floor of the mouth held changes the skin nearly as the
# neck held does (the same submental tissue held back from an advanced mandible), so the neck's
# direction carries it too and its own solve adds little (docs/diagnosis.md)
DEFAULT_BOUNDARIES = ("neck",)


def mesh_reference(resolution: str, choice: str | None = "auto") -> str | None:
    """The second mesh whose baseline estimates the diagnosis mesh's discretisation error
    (`discrepancy`, "The mesh's own error"): "auto" takes the next coarser resolution (cheap:
    a fraction of the diagnosis's time) and none at the coarsest; "none" or None: no estimate;
    a resolution name: that one (the next finer one gives the better estimate at the cost of
    its solve)."""
    from generic_mesh import RESOLUTIONS

    if choice in (None, "none"):
        return None
    if choice == "auto":
        i = RESOLUTIONS.index(resolution)
        return RESOLUTIONS[i - 1] if i > 0 else None
    if choice not in RESOLUTIONS:
        raise InputError(f"unknown mesh reference {choice!r} (auto, none, {', '.join(RESOLUTIONS)})",
                         field="--mesh-reference")
    if choice == resolution:
        raise InputError(f"the mesh reference must differ from the diagnosis resolution ({resolution})",
                         field="--mesh-reference")
    return choice


def load_diagnosis_case(case_dir: Path, resolution: str | None, say, reference: str | None = "none",
                        materials: dict | None = None):
    """(CaseModel, post-op Surface, resolution, reference CaseModel or None) of one case
    folder; InputError when unusable. `reference` (`mesh_reference`): the same case registered
    on a second mesh as well. `materials`: merged into the plan's model.materials
    (`planner.calibration.materials.with_materials`)."""
    from planner.calibration.materials import with_materials
    from planner.case import load_case
    from planner.compare.inputs import find_postop, load_surface
    from planner.pipeline import Progress, register_case
    from planner.plan import check_against_bones, load_plan

    case_dir = Path(case_dir)
    case = load_case(case_dir)
    scan = load_surface(find_postop(case_dir), "post-op scan")
    plan = with_materials(load_plan(case.require_plan()), materials)
    check_against_bones(plan, {k: np.asarray(v.vertices, float) for k, v in case.bones.items()})
    res = resolution or plan.model.resolution
    ref = mesh_reference(res, reference)
    progress = Progress(echo=lambda s: None)
    plan_actual = None
    if case.postop_plan_path is not None:
        plan_actual = load_plan(case.postop_plan_path)
        check_against_bones(plan_actual, {k: np.asarray(v.vertices, float) for k, v in case.bones.items()})
    skin = (np.asarray(case.skin.vertices, float), np.asarray(case.skin.faces, np.int64))
    out = []
    for r in (res, ref):
        if r is None:
            out.append(None)
            continue
        say(f"{case_dir.name}: registering the {r} model onto the patient")
        model, _ = register_case(case, r, progress)
        out.append(prepare_case(case_dir.resolve().name, model, plan, case.bones, plan_actual,
                                case.info.follow_up_months, preop_skin=skin))
    return out[0], scan, res, out[1]


def diagnose_cases(case_dirs: list[Path], *, resolution: str | None = None, runner: Runner | None = None,
                   say=lambda s: None, effect_names: tuple[str, ...] | None = None,
                   tangent: bool = True, reference: str | None = "auto",
                   boundary: tuple[str, ...] = DEFAULT_BOUNDARIES, layers: bool = False,
                   materials: Path | None = None) -> dict:
    """The diagnosis of case folders; `materials`: a calibration.json whose moduli the models
    take and whose spread the named effect's marginal intervals use."""
    t0 = time.perf_counter()
    mats = spread = None
    if materials is not None:
        from planner.calibration.materials import read_materials, read_moduli_spread

        mats, spread = read_materials(materials), read_moduli_spread(materials)
    loaded = [load_diagnosis_case(Path(c), resolution, say, reference, mats) for c in case_dirs]
    refs = [x[3] for x in loaded]
    out = diagnose_data([x[0] for x in loaded], [x[1] for x in loaded], runner=runner, say=say,
                        effect_names=effect_names, tangent=tangent,
                        references=refs if any(r is not None for r in refs) else None,
                        reference_names=[mesh_reference(x[2], reference) for x in loaded],
                        boundary=boundary, layers=layers, moduli_spread=spread)
    out["record"]["resolution"] = sorted({x[2] for x in loaded})
    out["record"]["materials"] = None if materials is None else str(materials)
    out["record"]["timings_s"]["total"] = round(time.perf_counter() - t0, 2)
    return out


def new_reference_forward(references: list, runner: Runner | None) -> Forward:
    """The `Forward` of the cases' reference meshes (`mesh_errors`), those given only."""
    return Forward([r for r in references if r is not None], runner, lambda s: None)


def reference_requests(references: list, params: tuple[str, ...] = ()) -> list:
    """The requests `mesh_errors` makes of `new_reference_forward` (for `Forward.prefetch`)."""
    n = sum(r is not None for r in references)
    if params:
        return Forward.sensitivity_requests([tuple(params)] * n)
    return [(j, ()) for j in range(n)]


def mesh_errors(data: list, references: list, runner: Runner | None, say, names: list,
                forward: Forward | None = None, params: tuple[str, ...] = ()) -> None:
    """Per case the change of the gap when the baseline is solved on the reference mesh
    (`CaseData.mesh_error`, the direction of the discretisation error: `discrepancy`), on the
    same scan points and pose, and with `params` (effect parameter keys) the reference
    baseline's tangent sensitivities to them (`CaseData.reference_sens`: the fitted values'
    extrapolation to the converged mesh, `analysis.mesh_corrections`). A reference that cannot be solved
    leaves the case without either."""
    idx = [i for i, r in enumerate(references) if r is not None]
    if not idx:
        return
    say(f"baseline on the reference mesh ({', '.join(sorted({names[i] for i in idx}))}) of {len(idx)} "
        "case(s): the mesh's own error")
    fwd = forward or new_reference_forward(references, runner)
    if params:
        out = fwd.sensitivities([tuple(params)] * len(idx))
        skins, sens = [o[0] for o in out], [o[1] for o in out]
    else:
        skins, sens = fwd.solve([(j, ()) for j in range(len(idx))]), [None] * len(idx)
    for j, i in enumerate(idx):
        d, name = data[i], names[i]
        if isinstance(skins[j], str):
            say(f"  {d.case.name}: the {name} baseline failed ({skins[j]}); no mesh-error estimate")
            continue
        v, f = references[i].predicted_surface(skins[j])
        r_ref = d.gap.distances_to(v, f)
        if np.all(np.isfinite(r_ref)):
            d.mesh_error = r_ref - d.r0
            d.mesh_reference = name
            d.reference, d.reference_skin = references[i], skins[j]
            d.reference_coarser = len(references[i].model.nodes) < len(d.case.model.nodes)
            d.reference_sens = sens[j] if isinstance(sens[j], dict) else None
            d.reference_forward, d.reference_index = fwd, j
            rms = float(np.sqrt(np.average(d.mesh_error ** 2, weights=d.gap.weights)))
            say(f"  {d.case.name}: the gap changes by {rms:.2f} mm RMS on the {name} mesh")


def other_boundary(case, option: str):
    """The case model with the other condition (free <-> held) of the boundary `option`
    (`BOUNDARIES`); None when the model lacks the boundary's node set."""
    import dataclasses

    if BOUNDARIES[option] not in case.model.node_sets:
        return None
    other = "held" if getattr(case.plan.model, option) == "free" else "free"
    plan = dataclasses.replace(case.plan, model=dataclasses.replace(case.plan.model, **{option: other}))
    return dataclasses.replace(case, plan=plan)


def parse_boundaries(text: str) -> tuple[str, ...]:
    """`--boundary-uncertainty` text -> boundary options: a comma-separated list of
    `BOUNDARIES` names, or "none"; ValueError for anything else."""
    names = tuple(dict.fromkeys(t.strip() for t in str(text).split(",") if t.strip()))
    if names == ("none",):
        return ()
    bad = [n for n in names if n not in BOUNDARIES]
    if bad or not names:
        raise ValueError(f"boundary conditions are a comma-separated list of {', '.join(BOUNDARIES)} "
                         f"or none, got {text!r}")
    return names


# the layer groups of the layer-proportion directions (`discrepancy`, "Layer proportions"):
# name -> `facemodel.synthetic.perturb_layers` keyword
LAYER_GROUPS = {"dermis": "dermis", "deep layers": "deep"}


def thicker_layer(case, group: str):
    """The case model with the layer group `group` (`LAYER_GROUPS`) `discrepancy.LAYER_STEP`
    thicker along every column from bone to skin, skin and bone surfaces unchanged; None when
    the model has no column structure (a mesh not made by `generic_mesh`)."""
    import dataclasses

    from facemodel.synthetic import perturb_layers
    from generic_mesh.builder import RESOLUTIONS

    H = np.asarray(case.model.hexes)
    for nk in sorted({int(r[3]) for r in RESOLUTIONS.values()}):
        # the generic mesh's columns (node id = column * (nk + 1) + layer): every hexahedron
        # spans two consecutive layers of its columns
        layer = H % (nk + 1)
        if len(case.model.nodes) % (nk + 1) == 0 and np.all(layer.max(axis=1) - layer.min(axis=1) == 1):
            model = perturb_layers(case.model, nk, **{LAYER_GROUPS[group]: 1.0 + discrepancy.LAYER_STEP})
            return dataclasses.replace(case, model=model, name=f"{case.name} ({group} thicker)")
    return None


class Alternatives(Forward):
    """The case models of the model-uncertainty directions (`boundary_errors`): `jobs` lists
    (case index, kind "boundary" | "layers", label, alternative case model), the k-th solved
    as this `Forward`'s case k."""

    def __init__(self, jobs: list, runner: Runner | None):
        super().__init__([j[3] for j in jobs], runner, lambda s: None)
        self.jobs = jobs

    def from_rest(self) -> list:
        """The requests solved from rest (every boundary alternative: its held nodes have
        moved in the baseline), which need nothing of the baseline (for `prefetch`)."""
        return [(k, ()) for k, j in enumerate(self.jobs) if j[1] == "boundary"]


def model_alternatives(cases: list, runner: Runner | None, boundaries: tuple[str, ...] = DEFAULT_BOUNDARIES,
                       layers: bool = False) -> Alternatives:
    """The alternative models of `boundary_errors` for `cases`: each case with the other
    condition of each boundary in `boundaries` and, with `layers`, each layer group thicker."""
    jobs = []
    for i, case in enumerate(cases):
        for option in boundaries:
            alt = other_boundary(case, option)
            if alt is not None:
                jobs.append((i, "boundary", f"{option} {getattr(alt.plan.model, option)}", alt))
        for group in (LAYER_GROUPS if layers else ()):
            alt = thicker_layer(case, group)
            if alt is not None:
                jobs.append((i, "layers", f"{group} x{1.0 + discrepancy.LAYER_STEP:g}", alt))
    return Alternatives(jobs, runner)


def boundary_errors(data: list, runner: Runner | None, say, boundaries: tuple[str, ...] = DEFAULT_BOUNDARIES,
                    layers: bool = False, guesses: dict | None = None,
                    alternatives: Alternatives | None = None) -> None:
    """Per case the change of the gap when the baseline is solved with the other condition of
    each boundary in `boundaries` (`BOUNDARIES`; `CaseData.boundary`, one column each) and with
    each layer group thicker (`CaseData.layers`, with `layers`): model-uncertainty directions
    of the error model (`discrepancy`, "Boundary conditions" and "Layer proportions"), on the
    same scan points and pose, all in one batch of solves; before the mesh error is taken out
    of the gap (its estimate then integrates these directions out). A case whose model lacks a
    boundary's node set, or whose alternative cannot be solved, goes without that direction.
    guesses: {case index: the baseline's displacement}, from which the thicker-layer solves
    start (the same mesh, its interior nodes moved by a fraction of a layer); a boundary's is
    solved from rest (the held nodes have moved in the baseline). alternatives: the
    `model_alternatives` of the cases, when their solves were started earlier."""
    alternatives = alternatives or model_alternatives([d.case for d in data], runner, boundaries, layers)
    jobs = alternatives.jobs
    if not jobs:
        return
    n = len({j[0] for j in jobs})
    what = [w for w, on in ((f"the other {' and '.join(boundaries)} condition", bool(boundaries)),
                            ("each layer group thicker", layers)) if on]
    say(f"baseline of {n} case(s) with {' and with '.join(what)}: model-uncertainty directions")
    for k, (i, kind, _, _) in enumerate(jobs):
        if kind == "layers" and (guesses or {}).get(i) is not None:
            alternatives.start_from(k, guesses[i])
    skins = alternatives.solve([(k, ()) for k in range(len(jobs))])
    found = {}
    for (i, kind, label, alt), skin in zip(jobs, skins):
        d = data[i]
        if isinstance(skin, str):
            say(f"  {d.case.name}: the baseline with the {label} failed ({skin}); no direction for it")
            continue
        v, f = alt.predicted_surface(skin)
        r_alt = d.gap.distances_to(v, f)
        if not np.all(np.isfinite(r_alt)):
            continue
        col = r_alt - d.r0
        found.setdefault((i, kind), []).append((label, col))
        rms = float(np.sqrt(np.average(col ** 2, weights=d.gap.weights)))
        say(f"  {d.case.name}: the gap changes by {rms:.2f} mm RMS with the {label}")
    for (i, kind), cols in found.items():
        d = data[i]
        if kind == "boundary":
            d.boundary = np.column_stack([c for _, c in cols])
            d.boundary_condition = ", ".join(label for label, _ in cols)
        else:
            d.layers = np.column_stack([c for _, c in cols])
            d.layer_directions = tuple(label for label, _ in cols)
        d._error = None


def diagnose_data(cases: list, scans: list, *, runner: Runner | None = None, say=lambda s: None,
                  effect_names: tuple[str, ...] | None = None, forward: Forward | None = None,
                  effects: list | None = None, tangent: bool = True, references: list | None = None,
                  reference_names: list | None = None, reference_forward: Forward | None = None,
                  boundary: tuple[str, ...] = DEFAULT_BOUNDARIES, layers: bool = False,
                  moduli_spread: dict[str, float] | None = None) -> dict:
    """The diagnosis of prepared cases (`forward.CaseModel`) against their scans; returns
    {"record": the diagnosis.json content, "data": per-case gap data, "analysis": ...}.
    `moduli_spread`: the patient's measured layer moduli spread (`analysis.moduli_marginal`)."""
    from planner.pipeline import unmet_text

    t0 = time.perf_counter()
    forward = forward or Forward(cases, runner, say)
    moved = tuple(dict.fromkeys(s for c in cases for s in c.moved_segments))
    if effects is None:
        # a segment cut in any case keeps its correction in all (the parameters are one set)
        executed = tuple(dict.fromkeys(s for c in cases for s in c.executed_segments))
        effects = available_effects(moved, effect_names, executed_segments=executed,
                                    plan_actual=all(c.plan_actual is not None for c in cases))
    names = tuple(p.key for e in effects for p in e.parameters)
    # the baseline, the boundary alternatives and the reference meshes' baselines need nothing
    # of each other: on a cluster they start together, the baseline first; with the tangent,
    # the baseline and its sensitivities are one solve per case (the analysis asks for the
    # same request again and gets it from the store)
    with_tangent = bool(tangent and names)
    forward.prefetch(forward.sensitivity_requests([names] * len(cases)) if with_tangent
                     else [(i, ()) for i in range(len(cases))])
    alternatives = None
    if boundary or layers:
        alternatives = model_alternatives(cases, forward.runner, tuple(boundary), layers)
        alternatives.prefetch(alternatives.from_rest())
    if references is not None:
        reference_forward = reference_forward or new_reference_forward(references, forward.runner)
        reference_forward.prefetch(reference_requests(references, names if tangent else ()))
    if with_tangent:
        say(f"baseline prediction of {len(cases)} case(s) with the tangent sensitivities of {len(names)} parameter(s)")
        forward.sensitivities([names] * len(cases))
    else:
        say(f"baseline prediction of {len(cases)} case(s)")
        forward.solve([(i, ()) for i in range(len(cases))])
    data = []
    for i, (case, scan) in enumerate(zip(cases, scans)):
        skin = forward.baseline(i)
        gap = measure_gap(case, skin, scan)
        unmet = forward.contact_unmet(i)
        if unmet:
            gap.warnings.append("the baseline prediction converged with " + unmet_text(unmet)
                                + " of penetration (beyond twice the contact tolerance): its lips "
                                "or teeth overlap there, and the gap near the mouth includes it")
        r0 = gap.distances(skin)
        data.append(analysis.CaseData(case, gap, r0))
        say(f"{case.name}: baseline RMS gap {gap.rms(r0):.2f} mm on {len(r0)} scan points; noise floor "
            f"{gap.noise_floor_mm:.2f} mm (superimposition residual {gap.alignment['residual_rms_mm']:.2f} mm, "
            f"scan roughness {gap.roughness_mm:.2f} mm); correlation length {gap.correlation_mm:.1f} mm")
        for w in gap.warnings:
            say(f"  warning: {w}")
    if boundary or layers:
        boundary_errors(data, forward.runner, say, boundaries=tuple(boundary), layers=layers,
                        guesses={i: forward.baseline_displacement(i) for i in range(len(data))},
                        alternatives=alternatives)
    if references is not None:
        mesh_errors(data, references, forward.runner, say, reference_names, reference_forward,
                    params=names if tangent else ())
        for d in data:
            if analysis.remove_mesh_error(d) is not None:
                say(f"  {d.case.name}: estimated mesh error {d.gap.mesh_error_mm:.2f} mm RMS taken out of "
                    f"the gap: {d.gap.rms(d.r0):.2f} mm left")
    t_fit = time.perf_counter()
    result = analysis.analyse(data, effects, forward, say, tangent=tangent, moduli_spread=moduli_spread)
    record = build_record(data, result, effects)
    record["timings_s"] = {"baseline_and_gap": round(t_fit - t0, 2),
                           "effects": round(time.perf_counter() - t_fit, 2)}
    record["solves"] = {"count": forward.n_solves, "time_s": round(forward.solve_time_s, 2),
                        "workers": forward.runner.n_workers}
    say(f"verdict: {verdict_text(record)}")
    return {"record": record, "data": data, "analysis": result}


def _r(x, n=4):
    return None if x is None or not np.isfinite(x) else round(float(x), n)


def _params(s, thetas: list | None = None) -> dict | None:
    """Values in the form `--effect` takes them (per case when case-specific): by default the
    estimates under noise + discrepancy; `thetas` (per case coordinates): those, e.g. the
    refined least-squares fit (`cand.theta`)."""
    from planner.diagnosis.effects import collect_effects

    cand = s.cand
    return _per_case(cand, [collect_effects(s.values(c) if thetas is None else cand.values(c, thetas[c]))
                            for c in range(cand.n_cases)])


def _effect_entry(s: analysis.Scored) -> dict:
    c = s.cand
    entry = {
        "name": c.name,
        "params": _params(s),
        "params_least_squares": _params(s, c.theta),
        "mesh_extrapolation_factor": ([_r(k, 3) for k in s.mesh_kappa] if s.mesh_kappa else None),
        "mesh_extrapolation_factor_sd": ([_r(k, 3) for k in s.mesh_kappa_sd] if s.mesh_kappa_sd else None),
        "identifiable": s.identifiable,
        "rms_after_mm": _r(s.rms_after),
        "shrink_pct": _r(s.shrink_pct, 2),
        "heldout_shrink_pct": _r(s.heldout_shrink_pct, 2),
        "significant": s.significant,
        "heldout_rms_mm": _r(s.heldout_rms),
        "heldout_shrink_spread_pct": _r(s.spread_pct, 2),
        "heldout_noise_shrink_pct": _r(s.noise_shrink_pct, 2),
        "heldout_noise_shrink_spread_pct": _r(s.noise_spread_pct, 2),
        "bic": _r(s.gp_bic, 3),
        "bic_noise_only": _r(s.bic, 3),
        "discrepancy_mm": _r(float(np.sqrt(np.mean([f.discrepancy_mm ** 2 for f in s.gp]))) if s.gp else None),
        "heldout_lpd_gain": _r(s.lpd_gain, 2),
        "heldout_lpd_gain_se": _r(s.lpd_gain_se, 2),
        "heldout_lpd_gain_probability": _r(s.lpd_gain_prob, 4),
        "wins_heldout": s.wins_heldout,
        "probability": _r(s.probability, 4),
        "shared": c.shared,
        "sensitivity": c.sensitivity,
        "solves": c.solves,
        "marginal_over_moduli": s.marginal,
    }
    if c.params:
        # the standard errors are in the fit's coordinate: the value, or its logarithm for
        # factors. `standard_error`: under the scan noise alone (the identifiability test);
        # `standard_error_with_discrepancy`: under noise + model-form discrepancy, the error
        # model the reported value was estimated under, and `interval_95` from it;
        # `standard_error_marginal` and `interval_95_marginal` (the named effect): with the
        # patient's layer moduli integrated out too (`analysis.moduli_marginal`)
        entry["parameters"] = {}
        for i, (p, f, se) in enumerate(zip(c.params, c.free, c.se)):
            se_m = [float(x[i]) for x in s.se_model] if s.se_model else []
            se_g = [float(x[i]) for x in s.se_marginal] if s.se_marginal else []
            coords = [(s.theta[k] if s.theta else c.theta[k])[i] for k in range(c.n_cases)]
            entry["parameters"][p.key] = {
                "identifiable": bool(f),
                "value": _per_case(c, [round(p.value(float(x)), 6) for x in coords]),
                "standard_error": _r(se, 4),
                "standard_error_with_discrepancy": _per_case(c, [_r(x, 4) for x in se_m]),
                "interval_95": _per_case(c, [_interval(p, coords[k], x) for k, x in enumerate(se_m)]),
                "standard_error_marginal": _per_case(c, [_r(x, 4) for x in se_g]),
                "interval_95_marginal": _per_case(c, [_interval(p, coords[k], x) for k, x in enumerate(se_g)]),
                # the standard deviation of the parameter's Gaussian prior about "none" (fit
                # coordinate), null where flat; with a measured effect the measurement's accuracy
                "prior_sd": _per_case(c, [_r(x, 4) if np.isfinite(x) else None
                                          for x in (c.prior_sd(k)[i] for k in range(c.n_cases))]),
                "coordinate": "log" if p.log else "value", "unit": p.unit,
                "bounds": [p.lower, p.upper], "none": p.none}
    return entry


def _per_case(cand, values: list):
    """One value for a single case or a shared parameter, else {"per_case": [...]}."""
    if not values:
        return None
    if cand.shared or cand.n_cases == 1:
        return values[0]
    return {"per_case": values}


def _interval(p, coordinate: float, se: float, z: float = 1.96) -> list | None:
    """The 95 % interval of a parameter's value, estimate +- z se in its fit coordinate
    (normal: the linearised estimate under a Gaussian error model), clipped to its bounds;
    None for a parameter held at "none"."""
    if not (np.isfinite(se) and np.isfinite(coordinate)):
        return None
    lo, hi = p.bounds
    return [round(p.value(float(np.clip(coordinate - z * se, lo, hi))), 6),
            round(p.value(float(np.clip(coordinate + z * se, lo, hi))), 6)]


def build_record(data: list, result: dict, effects) -> dict:
    r0s = [d.r0 for d in data]
    single = len(data) == 1
    scored = result["scored"] + result["pairs"]
    # best first: identifiable effects and pairs by held-out shrinkage, the others after
    ranked = sorted([s for s in scored if s.identifiable], key=lambda s: -s.heldout_shrink_pct)
    ranked += [s for s in scored if not s.identifiable]
    winner = result["winner"]
    verdict = {k: v for k, v in result["verdict"].items() if not k.startswith("_")}
    case_records = []
    for c, d in enumerate(data):
        rec = {"case": d.case.name, "baseline": d.gap.baseline_metrics,
               "localization": region_table(d.gap, d.r0), "noise_floor_mm": _r(d.gap.noise_floor_mm),
               "roughness_mm": _r(d.gap.roughness_mm), "alignment": d.gap.alignment,
               "coverage_pct": _r(100 * d.gap.coverage, 2), "uncovered_regions": d.gap.uncovered_regions,
               "correlation_length_mm": _r(d.gap.correlation_mm, 2), "n_eff": _r(d.gap.n_eff(), 1),
               "scan": d.gap.scan_path, "warnings": d.gap.warnings,
               "fitted": {s.cand.name: s.values(c) for s in scored if s.identifiable}}
        rec["error_model"] = _error_entry(d, result["baseline_error"][c])
        if winner is not None:
            rec["shrinkage"] = _shrinkage(d, d.r0, winner.fitted[c], winner.heldout[c], winner.gp[c])
        case_records.append(rec)
    floor = float(np.sqrt(np.mean([d.gap.noise_floor_mm ** 2 for d in data])))
    if single:
        baseline = data[0].gap.baseline_metrics
        localization = case_records[0]["localization"]
    else:
        baseline = _pooled_metrics(data, r0s)
        localization = _pooled_localization(data, r0s)
    record = {
        "faceplan": 1,
        "command": "diagnose",
        "baseline": baseline,
        "localization": localization,
        "noise_floor_mm": _r(floor),
        "error_model": (case_records[0]["error_model"] if single else
                        {r["case"]: r["error_model"] for r in case_records}),
        "effects": [_effect_entry(s) for s in ranked],
        "verdict": verdict,
        "shrinkage": (_pooled_shrinkage(data, r0s, winner) if winner is not None else None),
        "effects_failed": [{"name": c.name, "reason": c.failed} for c in result["failed"]],
        "effects_tested": [e.name for e in effects],
        "method": {
            "sensitivity": sorted({s.cand.sensitivity for s in result["scored"]}),
            "sensitivity_notes": result["notes"],
            "refinement": f"bounded Gauss-Newton with up to {analysis.MAX_REFINEMENTS} full solves per fit",
            "heldout": "spatial cross-validation over regions" if single else
                       "leave one case out (shared parameters); spatial cross-validation per case (case-specific)",
            "significance": {"bic_strong_evidence": fit.STRONG_EVIDENCE,
                             "bic": "-2 log L + k ln(n_eff) under noise + two-scale model-form discrepancy "
                                    "(a Matern-3/2 Gaussian process and a linear polynomial field with Gaussian "
                                    "coefficients; amplitudes and length by maximum likelihood per model)",
                             "heldout": "log predictive density of each region given the others, effect fitted "
                                        "without it; an effect must beat the discrepancy alone by a summed gain "
                                        f"of at least {fit.STRONG_EVIDENCE / 2.0:g}, positive with a Bayesian-bootstrap probability over "
                                        f"the regions of at least {analysis.HELDOUT_GAIN_PROBABILITY}",
                             "probability": "pseudo-BMA+ weights of the held-out log predictive densities "
                                            "(Bayesian bootstrap over the folds) among the baseline and the "
                                            "models passing both checks; 0 for the others",
                             "min_heldout_noise_shrink_pct": analysis.MIN_HELDOUT_SHRINK_PCT,
                             "heldout_shrink_vs_spread": 2.0},
            "shrinkage": {
                "heldout_shrink_pct": "1 - RMS(held-out gap with the effect) / RMS(baseline gap): the total gap",
                "heldout_noise_shrink_pct": "1 - sqrt(max(RMS_heldout^2 - noise^2, 0)) / sqrt(RMS_baseline^2 - noise^2): "
                                            "the gap beyond the scan noise (noise_floor_mm), which no effect can remove",
                "attributable_shrink_pct": "1 - sqrt(max(RMS_heldout^2 - e^2, 0)) / sqrt(max(RMS_baseline^2 - e^2, 0)), "
                                           "e^2 = noise^2 + discrepancy^2 with the effect (error_model): the part of "
                                           "the gap beyond what the model's form error and the scan noise explain"},
            "n_eff": _r(result["n_eff"], 1),
            "baseline_rms_mm": _r(result["rms0"]),
            "baseline_bic": _r(result["gp_bic0"], 3),
            "baseline_bic_noise_only": _r(result["bic0"], 3),
            "baseline_probability": _r(result["probabilities"]["baseline"], 4),
        },
        "warnings": [f"{d.case.name}: {w}" for d in data for w in d.gap.warnings]
        + analysis.confound_warning(verdict),
    }
    record["cases"] = case_records if not single else [{"case": case_records[0]["case"],
                                                        "fitted": case_records[0]["fitted"]}]
    if single:
        for k in ("roughness_mm", "alignment", "coverage_pct", "uncovered_regions", "correlation_length_mm", "scan"):
            record[k] = case_records[0][k]
    return record


def _error_entry(d, f) -> dict:
    return {"noise_mm": _r(d.gap.noise_floor_mm), "discrepancy_mm": _r(f.discrepancy_mm),
            "short_scale_mm": _r(f.sigma_d), "correlation_length_mm": _r(f.ell, 1),
            # the short scale under the mandible (`discrepancy`, "Under the mandible"), null
            # where the scan holds too few points there for a field of its own
            "short_scale_under_mandible_mm": (_r(f.sigma_d * np.sqrt(1.0 + f.border_ratio))
                                              if d.error.has_border else None),
            "long_scale_mm": _r(f.long_mm), "long_scale_basis": "offset and tilts of the whole face (linear polynomial)",
            "mesh_error_mm": _r(d.gap.mesh_error_mm) if d.mesh_error is not None else None,
            "mesh_reference": d.mesh_reference,
            "boundary_mm": _r(f.boundary_mm) if d.boundary is not None else None,
            "boundary_direction": d.boundary_condition,
            "layer_mm": _r(f.layer_mm) if d.layers is not None else None,
            "layer_directions": list(d.layer_directions) or None,
            # the scan's pose integrated out (`discrepancy`, "The scan's pose"): its standard
            # deviations under the baseline's error model
            "pose_sd": None if d.pose_cov is None else
            {"rotation_deg": [_r(float(x), 3) for x in np.degrees(np.sqrt(np.diag(d.pose_cov)[:3]))],
             "translation_mm": [_r(float(x), 3) for x in np.sqrt(np.diag(d.pose_cov)[3:])]},
            "level_mm": _r(float(np.hypot(f.discrepancy_mm, d.gap.noise_floor_mm))),
            "points": int(len(d.error.idx))}


def attributable(before: float, after: float, level: float) -> tuple[float, float, float | None]:
    """(gap beyond the error level before, after, shrink %) of RMS values (see method.shrinkage)."""
    b = float(np.sqrt(max(before ** 2 - level ** 2, 0.0)))
    a = float(np.sqrt(max(after ** 2 - level ** 2, 0.0)))
    return b, a, (100.0 * (1.0 - a / b) if b > 0 else None)


def _shrinkage(d, r0, fitted, heldout, gp=None) -> dict:
    g = d.gap
    out = {"overall": {"before_mm": _r(g.rms(r0)), "after_mm": _r(g.rms(fitted)),
                       "heldout_after_mm": _r(g.rms(heldout)),
                       "heldout_shrink_pct": _r(100 * (1 - g.rms(heldout) / max(g.rms(r0), 1e-12)), 2),
                       "noise_mm": _r(g.noise_floor_mm),
                       "heldout_noise_shrink_pct": _r(attributable(g.rms(r0), g.rms(heldout), g.noise_floor_mm)[2], 2)},
           "regions": {}}
    if gp is not None:
        level = float(np.hypot(gp.discrepancy_mm, g.noise_floor_mm))
        b, a, pct = attributable(g.rms(r0), g.rms(heldout), level)
        out["overall"].update({"error_level_mm": _r(level), "attributable_before_mm": _r(b),
                               "attributable_heldout_after_mm": _r(a), "attributable_shrink_pct": _r(pct, 2)})
    for name, m in d.folds.items():
        b, h = g.rms(r0, m), g.rms(heldout, m)
        out["regions"][name] = {"before_mm": _r(b), "after_mm": _r(g.rms(fitted, m)),
                                "heldout_after_mm": _r(h), "heldout_shrink_pct": _r(100 * (1 - h / max(b, 1e-12)), 2)}
    return out


def _pooled_shrinkage(data, r0s, winner) -> dict:
    if len(data) == 1:
        return _shrinkage(data[0], r0s[0], winner.fitted[0], winner.heldout[0], winner.gp[0])
    b = analysis._pooled_rms(data, r0s)
    h = analysis._pooled_rms(data, winner.heldout)
    W = [float(d.gap.weights.sum()) for d in data]
    level = float(np.sqrt(np.average([f.discrepancy_mm ** 2 + d.gap.noise_floor_mm ** 2 for d, f in zip(data, winner.gp)],
                                     weights=W)))
    ab, aa, pct = attributable(b, h, level)
    return {"overall": {"before_mm": _r(b), "after_mm": _r(analysis._pooled_rms(data, winner.fitted)),
                        "heldout_after_mm": _r(h), "heldout_shrink_pct": _r(100 * (1 - h / max(b, 1e-12)), 2),
                        "error_level_mm": _r(level), "attributable_before_mm": _r(ab),
                        "attributable_heldout_after_mm": _r(aa), "attributable_shrink_pct": _r(pct, 2)},
            "per_case": {d.case.name: _shrinkage(d, r0, f, ho, g)["overall"]
                         for d, r0, f, ho, g in zip(data, r0s, winner.fitted, winner.heldout, winner.gp)}}


def _pooled_metrics(data, rs) -> dict:
    from planner.compare.metrics import distance_metrics

    names = []
    for d in data:
        names += [n for n in d.gap.region_names if n not in names]
    w = np.concatenate([d.gap.weights for d in data])
    r = np.concatenate(rs)
    out = {"overall": distance_metrics(r, w), "regions": {}}
    for name in names:
        sel = np.concatenate([d.gap.region == (d.gap.region_names.index(name) if name in d.gap.region_names else -2)
                              for d in data])
        out["regions"][name] = distance_metrics(r[sel], w[sel])
    return out


def _pooled_localization(data, rs) -> list[dict]:
    names = []
    for d in data:
        names += [n for n in d.gap.region_names if n not in names]
    out = []
    for name in names:
        num = den = 0.0
        sig = False
        covered = False
        for d, r in zip(data, rs):
            m = d.folds.get(name)
            if m is None:
                continue
            covered = True
            num += float(np.sum(d.gap.weights[m] * r[m] ** 2))
            den += float(np.sum(d.gap.weights[m]))
            sig = sig or d.gap.significant(d.gap.rms(r, m), m, r=r)
        out.append({"region": name, "rms_mm": _r(np.sqrt(num / den)) if den > 0 else None,
                    "significant": sig, "covered": covered})
    return out

