"""From a case folder and its plan to a predicted face: the faceplan prediction pipeline.

Stages (Payan et al., "Facial soft-tissue prediction in orthognathic surgery" method): load the
case and the plan -> Mesh-Match-and-Repair of the generic face mesh onto the patient (cached by
input hash, reused on re-runs) -> assignment of the attachment nodes to the patient's bone
segments (`planner.segments`) -> the plan's rigid segment movements imposed on the attached nodes
(tied, or sliding on the bone as an option), teeth moved with their segments, muscles at the
plan's activations, lip contact on; for a genioplasty (the chin segment moved on the mandible)
the tissue the operation degloves slides on its bone instead of being tied
(`facemodel.attachments.genioplasty_sliding`: the anterior mandible between the vestibule and
the osteotomy and the chin segment's anterior face; the pedicle on the chin's inferior border
stays tied) -> nonlinear FE solve (`facemodel.simulation.simulate`, load
steps with a convergence log) -> outputs written into a temporary folder and moved into place
only when complete (`planner.atomic`): `prediction.vtu`, `skin_predicted.{stl,ply,vtp}` (the model's
skin patch), the predicted whole face `face_predicted.{glb,obj}`, `landmarks_predicted.mrk.json`,
`model.feb` (`planner.export`), renders of the whole face, `report.json` and `report.html`.
Solver failures become `SolveError` (exit 3), bad input `InputError` (exit 2).
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from planner import report as rep
from planner.errors import InputError, SolveError
from planner.plan import EFFECTS, Plan, check_against_bones, load_plan
from planner.segments import as_trimesh, assign_segments, with_segments
from solver.loads import BodyForce as _BodyForce
from facemodel import effects as fe
from facemodel.effects import EFFECT_NAMES, Effects
from solver.mechanics import von_mises

# Effects `--effect NAME=VALUE` and `model.effects` add to a prediction (contract, "Effect
# names"; definitions, parameters and sources in `facemodel.effects`).
SUPPORTED_EFFECTS = EFFECT_NAMES
# muscle_tone: the resting tone of the lip sphincter and the chin/lower-lip muscles.
TONE_MUSCLES = ("orbicularis_oris", "mentalis", "depressor_labii_inferioris")


def parse_effects(items: list[str] | dict | None) -> Effects:
    """`NAME=VALUE` strings (VALUE defaults to 1; dotted names set one part of an effect) or a
    mapping -> `facemodel.effects.Effects`; InputError naming the effect otherwise."""
    try:
        return fe.parse_effects(items)
    except fe.EffectError as exc:
        raise InputError(str(exc), field=f"--effect {exc.field}") from None


def check_effects(plan: Plan, effects=None) -> Effects:
    """The plan's `model.effects` overridden by the command line's (an `Effects`, a list of
    `NAME=VALUE` strings or a mapping); InputError naming the file and field for a bad one."""
    try:
        base = fe.parse_effects(dict(plan.model.effects))
    except fe.EffectError as exc:
        raise InputError(str(exc), file=plan.path, field=f"model.effects.{exc.field}") from None
    if effects is None:
        return base
    if not isinstance(effects, Effects):
        effects = parse_effects(effects)
    return fe.merge(base, effects)


class Progress:
    """Stage timings and a one-line-per-event progress display on stderr."""

    def __init__(self, echo: bool | Callable[[str], None] = True):
        self.timings: dict[str, float] = {}
        self.log: list[str] = []
        self._echo = echo
        self._t0 = time.perf_counter()

    def say(self, message: str) -> None:
        line = f"[{time.perf_counter() - self._t0:6.1f} s] {message}"
        self.log.append(line)
        if callable(self._echo):
            self._echo(line)
        elif self._echo:
            print(line, file=sys.stderr, flush=True)

    def stage(self, name: str):
        progress = self

        class _Stage:
            def __enter__(self):
                progress.say(f"{name} ...")
                self.t = time.perf_counter()
                return self

            def __exit__(self, exc_type, exc, tb):
                dt = time.perf_counter() - self.t
                progress.timings[name] = progress.timings.get(name, 0.0) + dt
                if exc_type is None:
                    progress.say(f"{name} done in {dt:.2f} s")
                return False

        return _Stage()


@dataclass
class Prediction:
    """A solved prediction on a patient model."""

    model: object                         # patient FaceModel with attachment sets per segment
    plan: Plan
    displacement: np.ndarray              # (n, 3) mm
    stress: np.ndarray | None             # (m, 3, 3) Cauchy stress per element, kPa, if given
    solver: dict
    bone_vertices: dict[str, np.ndarray] = field(default_factory=dict)
    assignment: dict = field(default_factory=dict)
    effects: dict = field(default_factory=dict)       # the effects applied, flat (`Effects.as_dict`)
    setup: dict = field(default_factory=dict, repr=False)   # what `effect_sensitivities` rebuilds from

    @property
    def predicted_nodes(self) -> np.ndarray:
        return np.asarray(self.model.nodes, float) + self.displacement

    @property
    def contact_unmet(self) -> dict[str, float]:
        """The contacts the converged solve left deeper than twice their tolerance ({name: mm};
        `facemodel.simulation`): the state the contact tolerance asks for was not reached there."""
        return dict((self.solver.get("info") or {}).get("contact_unmet_mm") or {})


def unmet_text(unmet: dict) -> str:
    """"lips 0.12 mm, teeth 0.30 mm": the contacts left unmet and their depth, for warnings."""
    return ", ".join(f"{k} {v:.2f} mm" for k, v in sorted(unmet.items()))


# --------------------------------------------------------------------------- model options

def face_materials(model, overrides: dict[str, dict[str, float]] | None = None, stiffness: float = 1.0,
                   label_factors: dict[str, float] | None = None):
    """Solver materials per tissue label from the default table (`facemodel.materials`: Yeoh for
    passive tissue, the active transversely isotropic `Muscle` for muscles), with the plan's
    parameter overrides and the `stiffness` effect (a factor on every modulus, active stress
    excepted, as `facemodel.materials.parameters` defines it; `label_factors` one per label,
    `Effects.label_factors`, times the uniform `stiffness`)."""
    from facemodel import materials as fm

    overrides = overrides or {}
    for label in overrides:
        if label not in model.label_names:
            raise InputError(f"unknown tissue label {label!r} (labels: {', '.join(model.label_names)})",
                             field=f"model.materials.{label}")
    out = {}
    for label in model.label_names:
        factor = stiffness * (label_factors or {}).get(label, 1.0)
        params = dict(fm.parameters(label, factor))
        for k, v in overrides.get(label, {}).items():
            if k not in params:
                raise InputError(f"material {label!r} has no parameter {k!r} "
                                 f"(parameters: {', '.join(params)})", field=f"model.materials.{label}.{k}")
            # a user's value is the generic value of the patient: the effect scales it too
            params[k] = v * (factor if k in fm.MODULI else 1.0)
        try:
            out[label] = fm.solver_material(label, params)
        except (TypeError, ValueError) as exc:
            raise InputError(f"material {label!r}: {exc}", field=f"model.materials.{label}") from None
    return out


def _sliding_sets(model, segments: tuple[str, ...]) -> tuple[str, ...]:
    return tuple(s for s in segments if len(model.node_sets.get("attach_" + s, ())) > 0)


# --------------------------------------------------------------------------- solve

def _call_simulate(model, motions, *, activations, progress: Progress, **kw):
    """`facemodel.simulation.simulate` with every Newton iteration sent to the progress log."""
    from facemodel.simulation import simulate

    return simulate(model, motions, activations, log=progress.say, **kw)


def _unpack_result(result, model) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """(displacement (n, 3), element Cauchy stress (m, 3, 3), solver statistics) of a
    `facemodel.simulation.SimulationResult`."""
    u = np.asarray(result.displacement, float).reshape(len(model.nodes), 3)
    stress = None if result.cauchy is None else np.asarray(result.cauchy, float)
    stats = {"converged": bool(result.converged), "load": float(result.load),
             "iterations": int(result.iterations), "steps": int(result.steps),
             "time_s": round(float(result.time_s), 3), "info": _jsonable(result.info)}
    return u, stress, stats


def _jsonable(v, depth=0):
    if depth > 4:
        return str(v)
    if isinstance(v, dict):
        return {str(k): _jsonable(x, depth + 1) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x, depth + 1) for x in v][:1000]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist(), depth + 1) if v.size <= 1000 else f"array{v.shape}"
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        return v.item()
    if isinstance(v, (int, float, str, bool)) or v is None:
        return v
    if dataclasses.is_dataclass(v):
        return _jsonable(dataclasses.asdict(v), depth + 1)
    return str(v)


def segment_centroids(model, plan: Plan, bone_vertices: dict) -> dict:
    """Pre-op centroid of each segment of the model: of its bone surface points (cut by the
    plan's cut planes) when given, else of its attachment nodes. A bone_execution correction
    turns about the centroid carried by the segment's movement."""
    out = {}
    X = np.asarray(model.nodes, float)
    for seg in model.segments:
        sp = plan.segments.get(seg)
        source = (sp.source if sp is not None and sp.source else seg)
        pts = None
        if source in bone_vertices:
            pts = np.asarray(bone_vertices[source], float)
            for cp in (sp.cut_planes if sp is not None else ()):
                pts = pts[cp.keeps(pts)]
        if pts is None or not len(pts):
            ids = np.asarray(model.node_sets.get("attach_" + seg, ()), np.int64)
            pts = X[ids] if len(ids) else None
        if pts is not None:
            out[seg] = pts.mean(axis=0)
    return out


def effect_motions(plan: Plan, effects: Effects, centroids: dict, plan_actual: Plan | None = None) -> dict:
    """Segment -> 4x4 movement with the bone_execution effect: the achieved movements of
    `plan_actual` when `effects.plan_actual`, then each segment's correction (tx, ty, tz, rx,
    ry, rz) about its centroid as moved, composed after the movement; a segment fixed to a
    corrected one (the chin to the mandible) follows its correction (`facemodel.effects.
    executed_motions`)."""
    source = plan
    if effects.plan_actual:
        if plan_actual is None:
            raise InputError("effect bone_execution=1 needs the achieved movements "
                             "postop/plan_actual.yaml", field="bone_execution")
        source = plan_actual
    motions = {k: np.asarray(v, float) for k, v in source.motions(include_identity=True).items()}
    for seg, p in effects.bone_execution:
        if any(v != 0.0 for v in p) and seg not in centroids:
            raise InputError(f"effect bone_execution.{seg}: the model has no segment {seg!r} "
                             "with attachment nodes or a bone surface", field=f"bone_execution.{seg}")
    # the chin rides on the mandible: a mandible correction carries it (`executed_motions`)
    return fe.executed_motions(motions, effects.bone_execution, centroids)


def model_inputs(setup: dict, effects: Effects) -> dict:
    """Keyword arguments of `facemodel.simulation.simulate` for the effects, from the fixed
    part of a prediction's set-up (`Prediction.setup`): motions (bone_execution), activations
    (muscle_tone), materials (stiffness), growth (swelling, about the operated segments),
    body force (gravity), sliding segments (sliding)."""
    model, plan = setup["model"], setup["plan"]
    motions = effect_motions(plan, effects, setup["centroids"], setup.get("plan_actual"))
    operated = tuple(k for k, m in motions.items() if not np.allclose(m, np.eye(4), atol=1e-12))
    sliding = tuple(plan.model.sliding)
    if effects.sliding == ("*",):     # the tissue slides on every moved segment
        sliding = operated
    elif effects.sliding:
        sliding = tuple(dict.fromkeys(sliding + tuple(effects.sliding)))
    sliding = _sliding_sets(model, sliding)
    activations = dict(plan.muscles)
    if effects.muscle_tone > 0:
        for m in TONE_MUSCLES:
            if m in model.label_names:
                activations[m] = max(activations.get(m, 0.0), effects.muscle_tone)
    layers = dict(effects.stiffness_layers)
    materials = face_materials(model, plan.model.materials, effects.stiffness,
                               {label: layers.get(layer, 1.0) for layer, labels in fe.LAYERS.items()
                                for label in labels})
    growth = fe.growth_field(model, operated, effects.swelling, setup.get("follow_up_months"))
    degloved = {s: ids for s, ids in setup["degloved"].items() if s not in sliding}
    return dict(motions=motions, activations=activations, contact=plan.model.contact,
                sliding=sliding, sliding_nodes=degloved, materials=materials, growth=growth,
                body_force=fe.gravity_density(effects.gravity, effects.gravity_pitch),
                neck=plan.model.neck, floor=plan.model.floor, proximal=plan.model.proximal,
                sliding_hold=effects.sliding_hold)


def solve_plan(model, plan: Plan, bones: dict | None = None, *, effects=None,
               plan_actual: Plan | None = None, follow_up_months: float | None = None,
               progress: Progress | None = None, guess=None,
               max_seconds: float | None = None) -> Prediction:
    """Assign attachments, impose the plan's movements and solve. `bones`: surfaces by name.
    effects: an `Effects`, `NAME=VALUE` strings or a mapping (over the plan's
    `model.effects`); plan_actual: the achieved movements (postop/plan_actual.yaml) for
    `bone_execution=1`; follow_up_months: the post-op scan's time (swelling resolution);
    guess: the displacement field (n, 3) of a nearby solution of this model (the same plan
    with other effect values), solved from at full load first (`facemodel.simulation.
    simulate`); max_seconds: the solve's wall-clock budget (a `SolveError` naming the load
    reached when it is spent; None: none)."""
    progress = progress or Progress(echo=False)
    effects = check_effects(plan, effects)
    bone_vertices = {k: np.asarray(as_trimesh(v).vertices, float) for k, v in (bones or {}).items()}
    assignment = {}
    if bones:
        with progress.stage("segments"):
            check_against_bones(plan, bone_vertices)
            a = assign_segments(model, bones, plan)
            model = with_segments(model, a)
            assignment = a.summary()
            for seg, s in assignment.items():
                progress.say(f"  {seg}: {s['nodes']} attachment nodes (median {s['median_distance_mm']} mm from bone)")
    from facemodel.errors import ModelInputError
    from solver import errors as solver_errors

    teeth_shift = {}
    if plan.model.contact and getattr(model, "teeth", None):
        # Contact must start without penetration: after registration some lip nodes can lie
        # inside the rigid arches; each arch is moved back by the measured depth
        # (`facemodel.teeth.clear_teeth`), reported.
        from facemodel.teeth import clear_teeth

        try:
            model, teeth_shift = clear_teeth(model)
        except ValueError as exc:
            raise SolveError(f"lip/teeth contact cannot start: {exc}") from exc
        moved = {k: round(v, 3) for k, v in teeth_shift.items() if v > 0}
        if moved:
            progress.say(f"  teeth moved back to start contact clear of the lips (mm): {moved}")
    # a genioplasty degloves the anterior mandible and chin: that tissue slides on its bone
    # (segments that slide as a whole, `sliding`, keep their own treatment)
    from facemodel.attachments import PROXIMAL, attachment_sets, genioplasty_sliding, osteotomy_bridges

    setup = {"model": model, "plan": plan, "plan_actual": plan_actual,
             "follow_up_months": follow_up_months,
             "centroids": segment_centroids(model, plan, bone_vertices),
             "degloved": genioplasty_sliding(model, plan.motions(include_identity=True))}
    inputs = model_inputs(setup, effects)
    motions, activations, sliding = inputs["motions"], inputs["activations"], inputs["sliding"]
    degloved = inputs["sliding_nodes"]
    # the degloved nodes that bridge a cut are tied to no bone, sliding or not
    owned = attachment_sets(model, motions, bridge_width=0.0, proximal=inputs["proximal"])
    bridges = osteotomy_bridges(model, owned, motions)
    if PROXIMAL in owned:
        progress.say(f"  sagittal split: the proximal segments (ramus, angle) stay with the skull "
                     f"({len(owned[PROXIMAL])} attached nodes; model.proximal: moved for a mandible "
                     "moved as one body)")
    if degloved:
        progress.say("  genioplasty: degloved tissue slides on the bone ("
                     + ", ".join(f"{s} {len(np.setdiff1d(ids, bridges))} nodes"
                                 for s, ids in degloved.items()) + ")")
    if len(bridges):
        progress.say(f"  osteotomies: {len(bridges)} attached nodes bridge the cuts, tied to no bone")
    if effects.active:
        progress.say(f"  effects: {json.dumps(effects.as_dict())}")
    moving = {k: m for k, m in motions.items() if not np.allclose(m, np.eye(4), atol=1e-12)}
    if (not moving and not any(a > 0 for a in activations.values()) and inputs["growth"] is None
            and inputs["body_force"] is None):
        # No bone moves, no muscle contracts, no load: the stress-free reference configuration
        # is in equilibrium whatever the materials, so it is the exact solution.
        progress.say("  nothing moves and no muscle is active: the prediction is the pre-op face")
        u = np.zeros_like(np.asarray(model.nodes, float))
        stats = {"converged": True, "steps": 0, "iterations": 0,
                 "note": "no movement planned: the rest state is the solution"}
        return Prediction(model, plan, u, np.zeros((len(model.hexes), 3, 3)), stats, bone_vertices,
                          assignment, effects.as_dict(), setup)
    with progress.stage("solve"):
        try:
            result = _call_simulate(model, progress=progress, guess=guess, max_seconds=max_seconds,
                                    **inputs)
        except solver_errors.SolveFailed as exc:
            label = ""
            if exc.worst_element is not None and 0 <= exc.worst_element < len(model.labels):
                label = f", worst element {exc.worst_element} ({model.label_names[model.labels[exc.worst_element]]})"
            raise SolveError(f"Newton failed at load step {exc.step} (load {exc.load:.3g}, last converged "
                             f"{exc.last_converged_load:.3g}{label}): {exc}") from exc
        except solver_errors.MaterialError as exc:
            if not plan.model.materials:     # the default table itself: not the user's doing
                raise SolveError(f"material table: {exc}") from exc
            raise InputError(f"material: {exc}", file=plan.path,
                             field=f"model.materials ({exc.parameter})" if exc.parameter else "model.materials") from exc
        except solver_errors.SolverError as exc:
            raise SolveError(f"{type(exc).__name__}: {exc}") from exc
        except ModelInputError as exc:   # simulate refuses input it cannot use; any other
            # exception is a bug and surfaces as one
            raise InputError(f"the face model refused the plan: {exc}", file=plan.path) from exc
        u, stress, stats = _unpack_result(result, model)
    if not stats["converged"] or stats["load"] < 1.0 - 1e-9:
        raise SolveError(f"the solver stopped at load fraction {stats['load']:.3g} without converging; "
                         "a partial state is not a prediction")
    if not np.all(np.isfinite(u)):
        raise SolveError("the solution contains NaN or infinite displacements")
    bad = rep.inverted_elements(np.asarray(model.nodes, float) + u, model.hexes)
    if bad.size:
        raise SolveError(_inverted_message(model, bad))
    folded = rep.folded_corners(np.asarray(model.nodes, float) + u, model.hexes)
    if folded.size:
        progress.say(f"  warning: {folded.size} element(s) have a folded corner (corner Jacobian <= 0) "
                     "but are valid at their Gauss points")
    fallback = (stats.get("info") or {}).get("contact_fallback")
    if fallback:
        progress.say(f"  warning: the solve failed at load {fallback['failed_at_load']:.3g} with the lips' "
                     f"nominal contact and was made again with a softer lip-lip penalty (x "
                     f"{fallback['lip_penalty_factor']:g}), its final contact not augmented to the "
                     "tolerance (report.json: solver.info.contact_fallback)")
    unmet = (stats.get("info") or {}).get("contact_unmet_mm") or {}
    if unmet:
        progress.say("  warning: the contact augmentations stopped with " + unmet_text(unmet)
                     + f" of penetration (tolerance {stats['info']['contact_tolerance_mm']:g} mm): "
                     "the prediction is converged, but its lips or teeth overlap there")
    stats["sliding"] = list(sliding)
    stats["degloved_sliding_nodes"] = {s: int(len(ids)) for s, ids in degloved.items()}
    stats["activations"] = activations
    stats["teeth_clearance_shift_mm"] = {k: round(float(v), 4) for k, v in teeth_shift.items()}
    setup["problem"] = result.problem
    setup["effects"] = effects
    return Prediction(model, plan, u, stress, stats, bone_vertices, assignment, effects.as_dict(), setup)


# central-difference steps of the residual per parameter kind (the residual is smooth in
# each; these are far above round-off of forces ~1e-3 mN and far below the parameters' scales)
_FD_STEP = {"mm": 1e-3, "deg": 1e-3, "-": 1e-4}


def effect_parameter_names(pred: Prediction, effects: tuple = fe.EFFECT_NAMES) -> list:
    """Flat names of the continuous parameters of `effects` for this prediction
    (bone_execution: six per segment the plan moves)."""
    moved = tuple(pred.plan.motions())
    return [p.name for e in effects for p in fe.parameters(e, moved)]


def effect_sensitivities(pred: Prediction, names=None) -> dict:
    """d(node positions)/dp (n, 3) at the converged prediction for each flat effect parameter
    name (default: every continuous parameter, `effect_parameter_names`): the direct
    differentiation du/dp = -K^-1 dR/dp (`solver.sensitivity.linear_response`) with the
    converged tangent (contact included), dR/dp at the converged positions by central
    differences of the residual (body force and growth, materials and activations rebuild the
    body; bone_execution moves the constrained nodes and the teeth). A derivative of the
    linearised problem: exact at the prediction, not across a change of contact state."""
    import copy

    from facemodel.simulation import build_problem, moved_constraints
    from solver.sensitivity import constraint_set, linear_response

    setup = pred.setup
    if "problem" not in setup:
        raise ValueError("the prediction has no solved problem (nothing moved): no sensitivities")
    body, constraints, terms = setup["problem"]
    effects = setup["effects"]
    model = setup["model"]
    names = effect_parameter_names(pred) if names is None else list(names)
    X = np.asarray(model.nodes, float)
    x = X + pred.displacement
    cons0 = constraint_set(body, constraints)
    owners = body.constraint_segments
    dr = np.zeros((x.size, len(names)))
    duc = np.zeros((len(cons0.dofs), len(names)))
    base = model_inputs(setup, effects)

    def residual_parts(eff):
        """(body internal force or None, term forces, constrained targets) for effects `eff`."""
        inp = model_inputs(setup, eff)
        f_body = None
        if (eff.swelling != effects.swelling or eff.stiffness != effects.stiffness
                or eff.stiffness_layers != effects.stiffness_layers
                or eff.muscle_tone != effects.muscle_tone):
            b = build_problem(model, inp["motions"], inp["activations"], contact=False,
                              sliding=inp["sliding"], sliding_nodes=inp["sliding_nodes"],
                              materials=inp["materials"], growth=inp["growth"])[0]
            f_body = b.evaluate(x, 1.0, tangent=False).force
        f_terms = np.zeros(x.size)
        changed = {k: T for k, T in inp["motions"].items()
                   if not np.array_equal(T, base["motions"].get(k, np.eye(4)))}
        for t in terms:
            seg = getattr(t, "segment", None)       # a rigid teeth arch follows its segment
            if seg in changed:
                t = copy.copy(t)
                t.motion = changed[seg]
            if isinstance(t, _BodyForce):
                continue
            f_terms += t.assemble(x, 1.0)[0]
        rho_b = inp["body_force"]
        if rho_b is not None:
            f_terms += _BodyForce(X, model.hexes, rho_b).f_unit
        cons = moved_constraints(X, constraints, owners, changed) if changed else constraints
        return f_body, f_terms, constraint_set(body, cons).targets(1.0, X)

    for j, name in enumerate(names):
        head = name.split(".")[0]
        v0 = effects.value(name)            # KeyError for a name that is no parameter
        unit = ("deg" if name.rsplit(".", 1)[-1].startswith("r") else "mm") \
            if head == "bone_execution" else "-"
        h = _FD_STEP[unit]
        lo = 0.0 if head == "muscle_tone" else -np.inf    # activations cannot be negative
        steps = (h, -h) if v0 - h >= lo else (h, 0.0)
        parts = [residual_parts(effects.with_value(name, v0 + d)) for d in steps]
        span = steps[0] - steps[1]
        fb = [p[0] for p in parts]
        if fb[0] is not None:
            f0 = fb[1] if fb[1] is not None else _internal_force(body, x)
            dr[:, j] += (fb[0] - f0) / span
        dr[:, j] += (parts[0][1] - parts[1][1]) / span
        duc[:, j] = (parts[0][2] - parts[1][2]) / span
    du = linear_response(body, constraints, terms, x, dr, duc)
    return {name: du[:, j].reshape(-1, 3) for j, name in enumerate(names)}


def _internal_force(body, x):
    saved, body.mixed = body.mixed, None      # the displacement-based residual
    try:
        return body.evaluate(x, 1.0, tangent=False).force
    finally:
        body.mixed = saved


def skin_sensitivities(pred: Prediction, names=None) -> tuple:
    """(skin node ids (k,), {name: d(skin node positions)/dp (k, 3)}) at the prediction;
    see `effect_sensitivities`."""
    _, _, ids = skin_surface(pred.model)
    sens = effect_sensitivities(pred, names)
    return ids, {k: v[ids] for k, v in sens.items()}


def _inverted_message(model, bad: np.ndarray) -> str:
    x = np.asarray(model.nodes, float)
    where = []
    for e in bad[:4]:
        hx = np.asarray(model.hexes[e])
        segs = [s for s in model.segments if np.isin(hx, model.node_sets.get("attach_" + s, ())).any()]
        where.append(f"element {int(e)} ({model.label_names[model.labels[e]]}, at "
                     f"{np.round(x[hx].mean(axis=0), 1).tolist()} mm, attached to {'+'.join(segs) or 'no bone'})")
    return (f"{bad.size} element(s) of the predicted face are inverted (Jacobian <= 0 at a Gauss point): "
            + "; ".join(where) + ". The relative movement of neighbouring bone segments shears the "
            "soft tissue between them more than this mesh resolution can follow: use a finer "
            "--resolution, --effect sliding=1, or a smaller relative movement")


# --------------------------------------------------------------------------- outputs

def skin_surface(model, positions: np.ndarray | None = None):
    """Skin triangles from the model's skin quads: (vertices, faces, node ids of the vertices)."""
    quads = np.asarray(model.facet_sets["skin"], int)
    ids, inverse = np.unique(quads, return_inverse=True)
    local = inverse.reshape(quads.shape)
    tris = np.concatenate([local[:, [0, 1, 2]], local[:, [0, 2, 3]]])
    x = np.asarray(model.nodes if positions is None else positions, float)[ids]
    return x, tris, ids


def region_of_nodes(model, ids: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Per skin vertex its region index into the returned names (-1 for none)."""
    names = list(model.regions)
    region = np.full(len(ids), -1, dtype=np.int32)
    pos = {int(n): i for i, n in enumerate(ids)}
    # Smaller regions first so that a node in two regions gets the more specific one.
    for r in sorted(range(len(names)), key=lambda r: -len(model.regions[names[r]])):
        for n in np.asarray(model.regions[names[r]], int):
            i = pos.get(int(n))
            if i is not None:
                region[i] = r
    return region, names


def write_volume(pred: Prediction, path: Path) -> None:
    """`prediction.vtu` (meshio): predicted node positions, displacement, labels, stress.

    Label names are not stored in the VTU (string arrays are not portable across VTU readers);
    they are in report.json under `label_names`, indexed by the cell data `label`."""
    import meshio

    model = pred.model
    hexes = np.asarray(model.hexes, np.int64)
    point_data = {"displacement": pred.displacement,
                  "displacement_magnitude": np.linalg.norm(pred.displacement, axis=1)}
    cell_data = {"label": [np.asarray(model.labels, np.int32)]}
    if pred.stress is not None and len(pred.stress) == len(hexes):
        cell_data["stress"] = [pred.stress.reshape(len(hexes), 9)]
        cell_data["von_mises"] = [von_mises(pred.stress)]
    meshio.Mesh(pred.predicted_nodes, [("hexahedron", hexes)], point_data=point_data,
                cell_data=cell_data).write(path)


def write_skin(pred: Prediction, out: Path) -> dict:
    """The model's skin patch: `skin_predicted.{stl,ply,vtp}` (the vtp with region, node id and
    displacement point data) and `region_names.json`."""
    import pyvista as pv
    import trimesh

    model = pred.model
    x_pre, tris, ids = skin_surface(model)
    x_post = pred.predicted_nodes[ids]
    mesh = trimesh.Trimesh(x_post, tris, process=False)
    mesh.export(out / "skin_predicted.stl")
    mesh.export(out / "skin_predicted.ply")
    region, names = region_of_nodes(model, ids)
    cells = np.hstack([np.full((len(tris), 1), 3), tris]).ravel()
    poly = pv.PolyData(x_post, cells)
    poly.point_data["region"] = region
    poly.point_data["node_id"] = ids.astype(np.int64)
    poly.point_data["displacement"] = pred.displacement[ids]
    poly.point_data["displacement_magnitude"] = np.linalg.norm(pred.displacement[ids], axis=1)
    poly.field_data["region_names"] = np.array(names)
    poly.save(str(out / "skin_predicted.vtp"))
    (out / "region_names.json").write_text(json.dumps(names))
    return {"pre": (x_pre, tris), "post": (x_post, tris), "magnitude": poly.point_data["displacement_magnitude"]}


def midline_profile(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Segments (k, 2, 3) where the skin surface crosses the mid-sagittal plane x = 0."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    return np.asarray(trimesh.intersections.mesh_plane(mesh, [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]))


# Landmarks on the facial midline: their mean fixes the mid-sagittal plane of the profile.
MIDLINE_LANDMARKS = ("Prn", "Sn", "Ls", "Stms", "Stmi", "Li", "Pog", "Me")
# Views of the pre-op and predicted faces, and those of the displacement map.
FACE_VIEWS = ("frontal", "profile", "profile_left", "three_quarter", "three_quarter_left", "submental")
DISPLACEMENT_VIEWS = ("frontal", "profile", "three_quarter")
ISOLINES_MM = (1.0, 2.0, 3.0)


def head_frame_of(model, resolution: str | None) -> np.ndarray:
    """The patient's head axes in the scan: the rotation of the best rigid fit of the generic
    model of `resolution` (built in the canonical RAS pose) onto the registered patient model
    (`render.head_frame`); the identity when the generic model does not match node for node."""
    from planner import render

    if resolution is None:
        return np.eye(3)
    try:
        import generic_mesh

        generic = generic_mesh.load(resolution)
    except (ValueError, KeyError, FileNotFoundError):
        return np.eye(3)
    if np.shape(generic.nodes) != np.shape(model.nodes):
        return np.eye(3)
    return render.head_frame(generic.nodes, model.nodes)


def whole_face(pred: Prediction, patient_skin=None):
    """The pre-op whole face (the patient's skin, or the model's skin patch without one) and
    the predicted whole face (`export.blend_face`)."""
    from planner.export import BlendedFace, blend_face

    x_pre, tris, ids = skin_surface(pred.model)
    u = pred.displacement[ids]
    if patient_skin is None:
        return (x_pre, tris), BlendedFace(x_pre + u, tris, u, np.ones(len(ids)))
    v = np.asarray(patient_skin.vertices, float)
    f = np.asarray(patient_skin.faces, np.int64)
    return (v, f), blend_face(v, f, x_pre, tris, u)


def profile_chart(pre, post, path: Path, landmarks_pre=None, landmarks_post=None, notes=None,
                  frame=None) -> Path | None:
    """The mid-sagittal skin profile before and after, seen from the patient's right (anterior
    to the right, superior up), equal axes in mm, with the landmarks named and `notes` (the
    soft-to-hard tissue ratios) beside them. The plane: the head frame's sagittal plane
    through the mean of the midline landmarks (x = 0 without them)."""
    from planner import render

    frame = np.eye(3) if frame is None else np.asarray(frame, float)
    origin = np.zeros(3)
    mid = [landmarks_pre[n] for n in MIDLINE_LANDMARKS if landmarks_pre and n in landmarks_pre]
    if mid:
        origin = np.mean(np.asarray(mid, float), axis=0)
    sets = [{n: p for n, p in d.items() if n in MIDLINE_LANDMARKS} for d in (landmarks_pre, landmarks_post)
            if d is not None]
    return render.landmark_profile_chart([pre, post], path, labels=("pre-op", "predicted"),
                                         landmarks=sets, notes=notes, frame=frame, origin=origin)


def _ratio_notes(landmarks: dict) -> dict[str, str]:
    return {n: f"soft/hard {e['soft_to_hard_ratio_ap']:.2f}" for n, e in landmarks.items()
            if e.get("soft_to_hard_ratio_ap") is not None}


def write_images(pre_face, post_face, images: Path, *, frame=None, landmarks_pre=None,
                 landmarks_post=None, notes=None, patch=None):
    """Pictures of the whole face: pre-op and predicted from every view with the same camera,
    the displacement map with iso-lines, the landmark profile, an overlay and a turntable GIF.
    Returns (list of (path, caption), list of (view, pre-op path, predicted path))."""
    from planner import render

    images.mkdir(parents=True, exist_ok=True)
    out: list[tuple[Path, str]] = []
    pre_v, pre_f = pre_face
    box = render.union_bounds([render.to_polydata(pre_face), render.to_polydata((post_face.vertices, post_face.faces))])
    pre_imgs = render.render_views(pre_face, images / "preop", title="pre-op face", views=FACE_VIEWS,
                                   frame=frame, bounds=box, landmarks=landmarks_pre)
    post_imgs = render.render_views((post_face.vertices, post_face.faces), images / "predicted",
                                    title="predicted face", views=FACE_VIEWS, frame=frame, bounds=box,
                                    landmarks=landmarks_post, title_position="upper_right")
    pairs = [(view, pre_imgs[view], post_imgs[view]) for view in FACE_VIEWS]
    mag = post_face.magnitude
    top = max(float(mag.max()), 1e-6)
    for view, path in render.render_views((post_face.vertices, post_face.faces), images / "displacement",
                                          scalars=mag, cmap="YlOrRd", clim=(0.0, top),
                                          scalar_bar_title="mm", title="soft-tissue displacement (mm)",
                                          views=DISPLACEMENT_VIEWS, frame=frame, bounds=box,
                                          isolines=[v for v in ISOLINES_MM if v < top]).items():
        out.append((path, f"displacement magnitude (mm, lines at 1, 2, 3 mm), "
                          f"{render.VIEW_TITLES[view]}"))
    path = profile_chart(pre_face, (post_face.vertices, post_face.faces), images / "profile_midline.png",
                         landmarks_pre, landmarks_post, notes, frame)
    if path is not None:
        out.append((path, "mid-sagittal profile: pre-op vs predicted, landmarks with the "
                          "soft-to-hard tissue ratio of their antero-posterior movement"))
    # the predicted face where the model moved it, over the pre-op face: elsewhere the two
    # coincide and the pre-op one is shown
    moved = (post_face.magnitude > 0.05)[np.asarray(post_face.faces)].any(axis=1)
    overlay = [pre_face] + ([(post_face.vertices, np.asarray(post_face.faces)[moved])] if moved.any() else [])
    for view, path in render.render_overlay(overlay, images / "overlay", labels=["pre-op", "predicted"][:len(overlay)],
                                            views=("profile",), frame=frame, opacity=[1.0, 1.0],
                                            title="profile: predicted (orange) where in front of pre-op (grey)").items():
        out.append((path, f"overlay pre-op vs predicted, {render.VIEW_TITLES[view]}"))
    gif = render.render_turntable((post_face.vertices, post_face.faces), images / "turntable.gif", frame=frame)
    out.append((gif, "predicted face, turntable"))
    return out, pairs


def write_exports(pred: Prediction, post_face, out: Path) -> dict[str, str]:
    """Files other tools open: the predicted whole face (GLB, OBJ), the predicted landmarks
    (3D Slicer markups) and the model with the plan (FEBio 4 input)."""
    from facemodel import materials as fm
    from planner import export

    export.write_mesh_glb(post_face.vertices, post_face.faces, out / "face_predicted.glb")
    export.write_mesh_obj(post_face.vertices, post_face.faces, out / "face_predicted.obj")
    export.write_markups(rep.predicted_landmarks(pred.model, pred.displacement),
                         out / "landmarks_predicted.mrk.json")
    model = pred.model
    stiffness = float(pred.effects.get("stiffness", 1.0)) if pred.effects else 1.0
    overrides = pred.plan.model.materials or {}
    materials = {}
    for label in model.label_names:
        p = dict(fm.parameters(label, stiffness))
        p.update(overrides.get(label, {}))
        materials[label] = p
    motions = {s: np.eye(4) for s in getattr(model, "segments", ())}
    motions.update(pred.plan.motions(include_identity=True))
    export.write_feb(model, motions, materials, out / "model.feb", proximal=pred.plan.model.proximal,
                     neck=pred.plan.model.neck, floor=pred.plan.model.floor)
    return {"face_glb": "face_predicted.glb", "face_obj": "face_predicted.obj",
            "landmarks": "landmarks_predicted.mrk.json", "febio": "model.feb"}


def build_report(pred: Prediction, progress: Progress, inputs: dict, registration: dict | None) -> dict:
    model, u = pred.model, pred.displacement
    jac = rep.corner_jacobians(pred.predicted_nodes, model.hexes)
    ref = rep.corner_jacobians(model.nodes, model.hexes)
    gjac = rep.gauss_jacobians(pred.predicted_nodes, model.hexes)
    gref = rep.gauss_jacobians(model.nodes, model.hexes)
    return {
        "faceplan": 1,
        "inputs": inputs,
        "plan": pred.plan.as_dict(),
        "effects": pred.effects,
        "segments": rep.segment_movements(pred.plan, pred.bone_vertices),
        "attachment_assignment": pred.assignment,
        "regions": rep.region_movements(model, u),
        "landmarks": rep.landmark_movements(model, u, pred.plan, pred.bone_vertices),
        "landmarks_predicted": rep.predicted_landmarks(model, u),
        "label_names": list(model.label_names),
        "soft_tissue": {"max_displacement_mm": round(float(np.linalg.norm(u, axis=1).max()), 4),
                        "n_nodes": int(len(u)), "n_elements": int(len(model.hexes))},
        "mesh_quality": {"inverted_elements": int((gjac <= 0).any(axis=1).sum()),
                         "min_gauss_jacobian_ratio": round(float((gjac / gref).min()), 4),
                         "folded_corner_elements": int((jac <= 0).any(axis=1).sum()),
                         "min_corner_jacobian_ratio": round(float((jac / ref).min()), 4)},
        "registration": registration or {},
        "solver": pred.solver,
        "timings_s": {k: round(v, 3) for k, v in progress.timings.items()},
        "log": progress.log[-200:],
    }


def check_solution(pred: Prediction) -> None:
    """Refuse (SolveError) to treat as a prediction a state the solver did not finish: not
    converged, short of the full load, NaN/infinite displacements or stresses, or an element
    inverted at a Gauss point."""
    s = pred.solver or {}
    if s.get("converged") is False or float(s.get("load", 1.0)) < 1.0 - 1e-9:
        raise SolveError(f"the solution is not converged (load fraction {s.get('load')}); nothing written")
    if not np.all(np.isfinite(pred.displacement)) or (
            pred.stress is not None and not np.all(np.isfinite(pred.stress))):
        raise SolveError("the solution contains NaN or infinite values; nothing written")
    bad = rep.inverted_elements(pred.predicted_nodes, pred.model.hexes)
    if bad.size:
        raise SolveError(_inverted_message(pred.model, bad) + "; nothing written")


def write_outputs(pred: Prediction, out_dir: Path, progress: Progress, inputs: dict,
                  registration: dict | None = None, render: bool = True,
                  extra: Callable[[Path], None] | None = None, kind: str = "predict",
                  patient_skin=None) -> Path:
    """Write every output into `out_dir` atomically (whole or not at all); `extra(tmp)` may add
    files to the folder before it is moved into place. kind: the command named in the output
    marker (`planner.atomic`: only a previous output of that command is replaced).
    `patient_skin` (a trimesh): the case's pre-op skin, the base of the predicted whole face
    (the model's skin patch without it)."""
    from planner.atomic import atomic_output_dir
    from planner.export import face_for_pictures
    from planner.html_report import write_html_report

    out_dir = Path(out_dir)
    check_solution(pred)
    t_start = time.perf_counter()
    with atomic_output_dir(out_dir, kind, inputs=[inputs.get("case")]) as tmp:
        with progress.stage("write meshes"):
            write_volume(pred, tmp / "prediction.vtu")
            write_skin(pred, tmp)
            pre_face, post_face = whole_face(pred, patient_skin)
            files = write_exports(pred, post_face, tmp)
        lm = rep.landmark_movements(pred.model, pred.displacement, pred.plan, pred.bone_vertices)
        images, pairs = [], []
        if render:
            with progress.stage("render"):
                frame = head_frame_of(pred.model, inputs.get("resolution"))
                pre_pic, post_pic = face_for_pictures(pre_face, post_face)
                images, pairs = write_images(
                    pre_pic, post_pic, tmp / "images", frame=frame,
                    landmarks_pre={n: e["preop"] for n, e in lm.items()},
                    landmarks_post={n: e["predicted"] for n, e in lm.items()}, notes=_ratio_notes(lm))
        progress.timings["outputs"] = time.perf_counter() - t_start
        progress.timings["total"] = time.perf_counter() - progress._t0
        report = build_report(pred, progress, inputs, registration)
        report["files"] = dict(files, html="report.html")
        report["whole_face"] = {"base": "patient pre-op skin" if patient_skin is not None else "model skin patch",
                                "vertices": int(len(post_face.vertices)),
                                "vertices_moved_by_model": int((post_face.weight > 0).sum()),
                                "max_displacement_mm": round(float(post_face.magnitude.max()), 4)}
        (tmp / "report.json").write_text(json.dumps(report, indent=2))
        tables = {"Landmarks (soft tissue, mm)": (
            ["landmark", "dx", "dy (AP)", "dz", "|d|", "soft/hard AP ratio"],
            [[n, *e["displacement_mm"], e["magnitude_mm"], e.get("soft_to_hard_ratio_ap", "")]
             for n, e in report["landmarks"].items()])}
        from planner import render as _render

        write_html_report(tmp / "report.html", "faceplan prediction",
                          {k: v for k, v in report.items() if k != "log"},
                          images=[(p, c) for p, c in images], tables=tables,
                          before_after=[(_render.VIEW_TITLES[v], a, b) for v, a, b in pairs])
        if extra is not None:
            extra(tmp)
    progress.say(f"prediction written to {out_dir}")
    return out_dir


# --------------------------------------------------------------------------- case level

def _file_digest(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    p = Path(path)
    files = sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else [p]
    for q in files:
        h.update(q.read_bytes())
    return h.hexdigest()[:16]


def register_case(case, resolution: str, progress: Progress, threshold: float | None = None):
    """The generic model of `resolution` registered onto the case (Mesh-Match-and-Repair; the
    registration caches its result by input hash, so a re-run reuses it). threshold: the
    repair's scaled-Jacobian threshold (None: the registration's default, 0.2)."""
    import generic_mesh
    import registration
    from registration import errors as reg_errors

    generic = generic_mesh.load(resolution)
    try:
        patient, reg_report = registration.mesh_match_and_repair(
            generic, case.skin, case.bones, landmarks=case.landmarks or None,
            teeth=case.teeth or None, threshold=threshold)
    except (InputError, SolveError):
        raise
    except reg_errors.RegistrationInputError as exc:
        raise InputError(f"registration: {exc}", file=exc.file or str(case.root),
                         field=exc.field or "registration") from exc
    except reg_errors.RegistrationFailure as exc:
        raise SolveError(f"registration of the generic face onto the patient failed: {exc}") from exc
    summary = _jsonable(reg_report) if reg_report is not None else {}
    if isinstance(summary, dict):
        from planner.registration_gate import registration_notes

        summary["quality_gate"] = registration_notes(summary)
        for note in summary["quality_gate"]:     # shown even with --quiet
            print(f"faceplan: warning: registration: {note}", file=sys.stderr)
        cached = summary.get("cached", summary.get("cache_hit"))
        if cached is not None:
            progress.say(f"  registration {'reused from cache' if cached else 'computed'}")
    return patient, summary


def predict_case(case_dir, out: str | Path | None = None, *, resolution: str | None = None,
                 effects: dict[str, float] | None = None, max_translation_mm: float | None = None,
                 max_rotation_deg: float | None = None, render: bool = True,
                 echo: bool | Callable[[str], None] = True,
                 extra: Callable[[Path], None] | None = None, kind: str = "predict",
                 materials: dict[str, dict[str, float]] | None = None) -> Path:
    """Run the whole prediction for a case folder; return the output folder (checked before
    any work by `planner.atomic.prepare_output`; kind: the command named in its marker).
    `materials` (e.g. `planner.calibration.materials.read_materials`) is merged into the
    plan's model.materials."""
    from planner.atomic import prepare_output
    from planner.case import load_case
    from planner.output_size import PREDICT_FLOOR_MB

    out_dir = prepare_output(out if out is not None else Path(case_dir) / "predict", kind,
                             inputs=[case_dir], min_free_mb=PREDICT_FLOOR_MB)
    progress = Progress(echo)
    with progress.stage("load case"):
        case = load_case(case_dir)
        plan_path = case.require_plan()
        plan = load_plan(plan_path, max_translation_mm=max_translation_mm, max_rotation_deg=max_rotation_deg)
        if materials:
            from planner.calibration.materials import with_materials
            plan = with_materials(plan, materials)
        bone_vertices = {k: np.asarray(v.vertices, float) for k, v in case.bones.items()}
        check_against_bones(plan, bone_vertices)
        merged = check_effects(plan, effects)
        plan_actual = None
        if merged.plan_actual:
            actual_path = Path(case_dir) / "postop" / "plan_actual.yaml"
            if not actual_path.is_file():
                raise InputError("effect bone_execution=1 needs the achieved movements in "
                                 "postop/plan_actual.yaml (same format as plan.yaml)",
                                 file=str(actual_path), field="bone_execution")
            plan_actual = load_plan(actual_path, max_translation_mm=max_translation_mm,
                                    max_rotation_deg=max_rotation_deg)
            check_against_bones(plan_actual, bone_vertices)
        res = resolution or plan.model.resolution
        progress.say(f"  case {case.info.id}: {len(case.bones)} bone surface(s), plan moves "
                     f"{', '.join(plan.motions()) or 'nothing'}; resolution {res}")
        from planner.output_size import check_prediction_space
        check_prediction_space(out_dir, res, case.skin, render=render)
    with progress.stage("registration"):
        patient, reg = register_case(case, res, progress)
    pred = solve_plan(patient, plan, case.bones, effects=merged, plan_actual=plan_actual,
                      follow_up_months=case.info.follow_up_months, progress=progress)
    inputs = {
        "case": str(Path(case_dir).resolve()), "case_id": case.info.id,
        "skin": str(case.skin_path) if case.skin_path else None,
        "bones": sorted(case.bones), "landmarks": sorted(case.landmarks),
        "plan": str(plan_path), "resolution": res,
        "sha256": {"plan": _file_digest(plan_path),
                   **({"skin": _file_digest(case.skin_path)} if case.skin_path else {})},
    }
    return write_outputs(pred, out_dir, progress, inputs, reg, render=render, extra=extra, kind=kind,
                         patient_skin=case.skin)


# --------------------------------------------------------------------------- demo

DEMO_PLAN = {
    "faceplan": 1,
    "frame": "RAS",
    "segments": {
        # Le Fort I: 5 mm advancement, 1 mm up, and a 2 deg pitch about the upper incisor
        # region that raises the posterior maxilla (rotation about +x, right-hand rule).
        "maxilla": {"translation": [0.0, 5.0, 1.0],
                    "rotation": {"axis": [1, 0, 0], "angle_deg": -2.0, "center": [0.0, 60.0, -25.0]}},
        # BSSO: 3 mm mandibular setback of the distal segment.
        "mandible": {"translation": [0.0, -3.0, 0.0]},
        # Genioplasty: the chin segment rides with the mandible and is advanced 5 mm and raised
        # 1 mm on it; movements are pre-op -> post-op, so 2 mm forward overall.
        "chin": {"translation": [0.0, 2.0, 1.0]},
    },
    "muscles": {"orbicularis_oris": 0.0, "mentalis": 0.0},
    "model": {"contact": True},
}


DEMO_HEAD = Path(__file__).parent / "data" / "demo_head.npz"


def write_demo_case(folder: str | Path, plan: dict | None = None) -> Path:
    """Write the embedded synthetic head (`facemodel.synthetic.synthetic_head(7)`, stored in
    `planner/data/demo_head.npz`: skin, bone segments, landmarks) as a case folder with a plan
    (default: the bimaxillary demo plan)."""
    import trimesh
    import yaml

    folder = Path(folder)
    data = np.load(DEMO_HEAD)
    (folder / "preop" / "bone").mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(data["skin_vertices"].astype(float), data["skin_faces"], process=False).export(
        folder / "preop" / "skin.stl")
    for key in data.files:
        if key.startswith("bone_") and key.endswith("_vertices"):
            seg = key[len("bone_"):-len("_vertices")]
            trimesh.Trimesh(data[key].astype(float), data[f"bone_{seg}_faces"], process=False).export(
                folder / "preop" / "bone" / f"{seg}.stl")
    landmarks = {str(n): [float(c) for c in p] for n, p in zip(data["landmark_names"], data["landmark_points"])}
    (folder / "preop" / "landmarks.json").write_text(json.dumps(landmarks, indent=1))
    (folder / "case.yaml").write_text(yaml.safe_dump({"id": f"synthetic-{int(data['seed'])}", "synthetic": True,
                                                      "seed": int(data["seed"]),
                                                      "notes": "embedded synthetic head of the faceplan demo"}))
    (folder / "plan.yaml").write_text(
        "# faceplan demo: bimaxillary surgery (Le Fort I advancement, BSSO setback, genioplasty)\n"
        + yaml.safe_dump(plan or DEMO_PLAN, sort_keys=False))
    return folder


def run_demo(out_dir: str | Path, *, resolution: str = "coarse", render: bool = True,
             echo: bool | Callable[[str], None] = True) -> Path:
    """The bimaxillary demo on the embedded synthetic head: the whole prediction into
    `out_dir`, with the case folder it was made from in `out_dir/case`."""
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory(prefix="faceplan-demo-") as tmp:
        case = write_demo_case(Path(tmp) / "case",
                               dict(DEMO_PLAN, model=dict(DEMO_PLAN["model"], resolution=resolution)))

        def keep_case(folder: Path) -> None:
            shutil.copytree(case, folder / "case", ignore=shutil.ignore_patterns("predict", ".*"))

        return predict_case(case, out_dir, resolution=resolution, render=render, echo=echo,
                            extra=keep_case, kind="demo")
