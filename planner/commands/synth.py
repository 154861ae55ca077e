"""`faceplan synth`: synthetic case folders from random plausible heads, with post-op scans.

Each case (seed S + i) is a head of `facemodel.synthetic` written as the contract's case
folder: preop/skin.stl (closed), preop/bone/<segment>.stl (skull, maxilla, mandible, chin),
preop/teeth/<arch>.stl, preop/landmarks.json, a sample bimaxillary plan.yaml that corrects
the head's jaw discrepancy (Le Fort I, BSSO, genioplasty when the chin is off), case.yaml,
and with --ct a CT-like volume preop/ct.nii.gz of the same head. With `--head-family alt` the
head comes from a second, differently built generator (`facemodel.synthetic_alt`: no teeth),
its plan drawn from its bones and landmarks (`bone_plan`).

With `--withheld-effect NAME[=VALUE] | random | none` each case also gets postop/skin.stl: the
plan's prediction WITH that effect (none: without any), made on a model that is not the one a
diagnosis fits (the generic face at `--truth-resolution`, its dermis and deep layers 0.8-1.2
times as thick, its moduli 0.85-1.15 times the generic ones per layer, its bulk modulus
500-2000 times the shear modulus, registered onto the head; a fine truth is registered at the
standard resolution and carried to the fine mesh, `prolonged_patient`, its effect value set on
the standard model), seen as a frontal surface scanner
sees it (`facemodel.synthetic.scan_like_surface`: a range image on a 0.6 mm grid, median edge
~0.8 mm, the front of the face only, holes at the mouth slit, nostrils and under the chin, 0.2 mm noise along the
normals, a rigid offset up to 2 mm / 2 deg; `--scanner wide`: a multi-pod system's patches,
ear to ear and under the chin); with `--truth-neck held` / `--truth-floor held` the truth
model holds the neck cut / the floor of the mouth, boundary conditions the predicting model
leaves free; case.yaml gets `follow_up_months` (3-12), and
postop/plan_actual.yaml is written for a random half of the bone_execution cases. Effect
values are drawn per case from published ranges (`draw_effect`; swelling, posture and tone from
a skin-change target met where the scan sees the skin, with one secant correction when the change reached leaves the range, and
a recorded reduction when the truth solve fails, `solve_reducing`). The effect, its value and the
perturbations go only to the --key file (a JSON list, one record per case, contract fields).
The cases with post-op scans run as tasks on dask.distributed: a LocalCluster of `--workers`
processes, or the cluster at `--scheduler ADDRESS` (its workers must see the output folder);
each case draws from its own seed, so a cohort is the same whatever the number of workers.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from facemodel.model import FLOOR_CONDITIONS, NECK_CONDITIONS
from planner.errors import InputError, SolveError

# Ranges of the withheld effects (skin change where the post-op scan sees the skin, the largest
# over the effect's regions, mm, or the parameter itself). The published ranges are measured
# on surface images, so a target is met where a frontal scan shows the face (`_region_ids`):
# - posture: the upright face against the supine one differs by 0.8-1.4 mm over the lateral and
#   lower face (cheeks, jowls, lips and chin: subnasale to menton; supine vs upright 3D
#   photographs and CT/MRI, e.g. Ozsoy U. et al., 2015, and the soft-tissue sag reported
#   between supine CT and upright surface scans);
# - swelling: residual oedema changes the skin by 0.5-2 mm at 3-12 months (van der Vlis et al.
#   2014, J Oral Maxillofac Surg 72:2241; Kau et al. 2006);
# - bone execution: planned-to-achieved differences of 0.5-2 mm and 1-3 deg (e.g. Hsu S.S. et
#   al., J Oral Maxillofac Surg 71:128, 2013; Stokbro K. et al., Int J Oral Maxillofac Surg
#   43:957, 2014, systematic review of virtual-planning accuracy);
# - lip posture (resting tone): 0.3-2 mm of lip position between relaxed and habitual lip
#   postures (e.g. Ayoub A.F. et al., 2003, reproducibility of lip posture in 3D imaging);
# - stiffness: one layer 0.5-0.7x or 1.5-2.5x the generic (the spread of published facial soft
#   tissue moduli, Joodaki & Panzer 2018 review);
# - sliding at the lips (maxilla) and chin: the tissue the operation degloves.
SKIN_CHANGE_MM = {"swelling": (0.5, 2.0), "gravity": (0.8, 1.4), "muscle_tone": (0.3, 2.0)}
SKIN_CHANGE_REGIONS = {
    "swelling": None,                                                  # the whole skin
    "gravity": ("cheek_left", "cheek_right", "submandibular_left", "submandibular_right",
                "submental", "upper_lip", "lower_lip", "chin", "preauricular_left", "preauricular_right"),
    "muscle_tone": ("upper_lip", "lower_lip", "chin"),
}
BONE_TRANSLATION_MM = (0.5, 2.0)
BONE_ROTATION_DEG = (1.0, 3.0)
STIFF_LAYERS = ("dermis", "hypodermis", "muscle")
SOFTER, STIFFER = (0.5, 0.7), (1.5, 2.5)
FOLLOW_UP_MONTHS = (3.0, 12.0)
# a target-set value whose truth solve fails is reduced along its load path (`solve_reducing`)
MAX_REDUCTIONS = 2
REDUCTION_MARGIN = 0.9      # of the load fraction reached: the last converged state had it
MIN_REDUCTION = 0.25        # never below a quarter of the value in one reduction
TRUTH_RESOLUTION = "standard"   # fine: beyond the 2-minute budget per case (docs/effects.md)
# a fine truth is registered at the standard resolution and carried to the fine mesh (the same
# generic tissue, `prolonged_patient`): a fine registration of its own costs minutes, and each
# fine solve several standard ones, so the effect's value is set on the standard model
REGISTERED_AT = {"fine": "standard"}
# carrying a registration to a finer mesh (`prolonged_patient`): push, separate and repair
# rounds at most; the nodes within CLEARANCE_HOLD_MM beyond the teeth clearance are held in
# the repair; the lip gap is reached to separate_lips' tolerance
CARRY_PASSES = 4
CLEARANCE_HOLD_MM = 0.1
LIP_GAP_TOL = 0.05
# the head generators a case can come from: faceplan's own, and a second family built
# otherwise (a model tuned on one must be judged on the other)
HEAD_FAMILIES = ("own", "alt")


def add_arguments(parser) -> None:
    parser.add_argument("--out", required=True, help="folder that receives the case folders")
    parser.add_argument("--count", type=int, default=1, help="number of cases (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first case (default 0)")
    parser.add_argument("--withheld-effect", default=None, metavar="NAME[=VALUE]|random|none",
                        help="write postop/skin.stl predicted WITH this effect (random: one drawn "
                             "per case; none: no effect); without the option no post-op scan")
    parser.add_argument("--key", default=None, help="JSON file receiving the ground truth of every case")
    parser.add_argument("--truth-resolution", choices=("coarse", "standard", "fine"), default=TRUTH_RESOLUTION,
                        help=f"face model resolution of the post-op truth (default {TRUTH_RESOLUTION})")
    parser.add_argument("--truth-neck", choices=(*NECK_CONDITIONS, "random"), default="free",
                        help="boundary condition of the truth model's neck cut (default free, as the "
                             "model faceplan predicts with; held: the cut held in place, a model-form "
                             "difference the diagnosis does not share; random: either, per case)")
    parser.add_argument("--truth-floor", choices=(*FLOOR_CONDITIONS, "random"), default="free",
                        help="boundary condition of the truth model's floor of the mouth (default "
                             "free, as the model faceplan predicts with; held: the free deep surface "
                             "under the mandible held in place, a model-form difference the diagnosis "
                             "does not share; random: either, per case)")
    parser.add_argument("--scanner", choices=("frontal", "wide"), default="frontal",
                        help="the post-op scan's scanner (default frontal: one range camera in "
                             "front of the face; wide: a multi-pod stereophotogrammetry system, ear "
                             "to ear and under the chin)")
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="dask scheduler to run the cases on (default: a local cluster)")
    parser.add_argument("--workers", type=int, default=2, help="local cluster worker processes (default 2)")
    parser.add_argument("--case-max-minutes", type=float, default=None, metavar="M",
                        help="time budget of each case's truth solves: a case whose solves are still "
                             "running after M minutes (a plan creeping at a limit point of the lips) "
                             "fails with the load it reached (default: no limit)")
    parser.add_argument("--solve-log", default=None, metavar="DIR",
                        help="write each case's truth solves (its stages and every Newton iteration, "
                             "as they run, and the failure of a case that fails) to DIR/CASE.log; the "
                             "lines name the withheld effect, so DIR must lie outside --out, as the "
                             "key does")
    parser.add_argument("--ct", action="store_true", help="also write a CT-like volume preop/ct.nii.gz")
    parser.add_argument("--ct-spacing", type=float, default=1.0, help="CT voxel size in mm (default 1)")
    parser.add_argument("--surface-size", type=float, default=1.0,
                        help="skin facet size over the face in mm (default 1, the density of a "
                             "skin segmented from a 1 mm CT; coarser towards the back of the head)")
    parser.add_argument("--mesher", choices=("sphere", "pygalmesh"), default="sphere",
                        help="skin mesher: projected geodesic sphere (default, reproducible) or "
                             "CGAL's Delaunay surface mesher via pygalmesh")
    parser.add_argument("--head-family", choices=HEAD_FAMILIES, default="own",
                        help="own (default): faceplan's head generator (facemodel.synthetic), "
                             "with teeth; alt: another, differently built family "
                             "(facemodel.synthetic_alt: superquadric skull and face, other "
                             "soft-tissue thickness maps, no teeth), its plan drawn from its "
                             "bones (bone_plan)")


def parse_withheld(text: str | None):
    """None (no post-op scan), ("none", None), ("random", None) or (NAME, flat value dict or
    None to draw one); InputError for anything else."""
    from facemodel import effects as fe

    if text is None:
        return None
    t = str(text).strip()
    if t.lower() in ("none", "random"):
        return t.lower(), None
    name, sep, _ = t.partition("=")
    head = name.split(".")[0].strip()
    if head not in fe.EFFECT_NAMES:
        raise InputError(f"unknown effect {name!r} (known: {', '.join(fe.EFFECT_NAMES)}, or random, none)",
                         field="--withheld-effect")
    if not sep:
        if "." in name:
            raise InputError("a dotted effect name needs a value (NAME.PART=VALUE)", field="--withheld-effect")
        return head, None
    try:
        eff = fe.parse_effects([t])
    except fe.EffectError as exc:
        raise InputError(str(exc), field="--withheld-effect") from None
    return head, eff.as_dict()


def _check(args) -> None:
    if args.count < 1 or args.count > 1000:
        raise InputError(f"--count must be between 1 and 1000, got {args.count}", field="--count")
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}", field="--seed")
    parse_withheld(args.withheld_effect)
    if not 1 <= args.workers <= 64:
        raise InputError(f"--workers must be between 1 and 64, got {args.workers}", field="--workers")
    if not (0.2 <= args.ct_spacing <= 5.0):
        raise InputError(f"--ct-spacing must be in [0.2, 5] mm, got {args.ct_spacing}", field="--ct-spacing")
    if not (1.0 <= args.surface_size <= 10.0):
        raise InputError(f"--surface-size must be in [1, 10] mm, got {args.surface_size}", field="--surface-size")
    if args.head_family == "alt" and (args.surface_size != 1.0 or args.mesher != "sphere"):
        raise InputError("--surface-size and --mesher apply to faceplan's own head family only",
                         field="--head-family")
    if args.solve_log is not None:
        if args.withheld_effect is None:
            raise InputError("--solve-log needs --withheld-effect: without a post-op scan there is no "
                             "truth solve to log", field="--solve-log")
        log_dir, out = Path(args.solve_log).resolve(), Path(args.out).resolve()
        if log_dir == out or out in log_dir.parents:
            raise InputError("--solve-log lies inside --out: its lines name the withheld effect, so it "
                             "must be kept apart from the case folders (as the key is)",
                             file=str(args.solve_log), field="--solve-log")
        if log_dir.exists() and not log_dir.is_dir():
            raise InputError("--solve-log exists and is not a folder", file=str(args.solve_log),
                             field="--solve-log")
    if args.case_max_minutes is not None and not args.case_max_minutes > 0:
        raise InputError(f"--case-max-minutes must be > 0, got {args.case_max_minutes}",
                         field="--case-max-minutes")


def sample_plan(shape) -> dict:
    """A bimaxillary plan that brings the head's jaws towards the norm: maxillary advancement
    (at least 2 mm) with 1 mm impaction and a 2 deg pitch about A point; the mandible follows
    the maxilla and corrects its own discrepancy; a genioplasty when the chin is off by more
    than 1.5 mm (otherwise the chin moves with the mandible)."""
    from facemodel import head_geometry as hg

    adv = float(np.clip(2.0 - shape.maxilla_ap, 2.0, 7.0))
    mand = float(np.clip(adv - shape.mandible_ap + shape.maxilla_ap, -8.0, 10.0))
    a_point = hg.to_cartesian(0.0, -9.0, float(hg.bone_radius(0.0, -9.0, shape, side=1)), shape)
    segs = {
        "maxilla": {"translation": [0.0, round(adv, 2), 1.0],
                    "rotation": {"axis": [1, 0, 0], "angle_deg": -2.0,
                                 "center": [round(float(c), 2) for c in a_point]}},
        "mandible": {"translation": [0.0, round(mand, 2), 0.0]},
    }
    # the chin is a separate bone surface: without a genioplasty it moves with the mandible
    # (distal segment); with one (chin off by more than 1.5 mm) it is also brought back
    chin = mand - float(shape.chin_projection) if abs(shape.chin_projection) > 1.5 else mand
    segs["chin"] = {"translation": [0.0, round(chin, 2), 0.0]}
    return _plan(segs)


def _plan(segments: dict) -> dict:
    """A synthetic case's plan.yaml content: the segments' motions, muscles at rest."""
    return {"faceplan": 1, "frame": "RAS", "segments": segments,
            "muscles": {"orbicularis_oris": 0.0, "mentalis": 0.0},
            "model": {"resolution": "standard"}}


def bone_plan(head, seed: int) -> dict:
    """A bimaxillary plan from the head's bone surfaces and soft-tissue landmarks alone (no
    shape parameters: for heads of another family, `facemodel.synthetic_alt`), drawn from the
    seed on a stream of its own: maxillary advancement 2-6 mm with 0-2 mm impaction and a
    2 deg pitch about the maxilla's point nearest subnasale (A point's neighbourhood); the
    mandible follows the maxilla and corrects a discrepancy of -4..+4 mm of its own; a
    genioplasty of 2-5 mm in half the cases (otherwise the chin moves with the mandible).
    The ranges are the common one-jaw to bimaxillary corrections (sample_plan's, drawn rather
    than read off a shape)."""
    rng = np.random.default_rng([int(seed), 23])
    adv, imp, own = rng.uniform(2.0, 6.0), rng.uniform(0.0, 2.0), rng.uniform(-4.0, 4.0)
    genio = rng.uniform(2.0, 5.0) if rng.uniform() < 0.5 else 0.0
    maxilla = np.asarray(head.bones["maxilla"].vertices, float)
    sn = np.asarray(head.landmarks["Sn"], float)
    a_point = maxilla[int(np.argmin(np.linalg.norm(maxilla - sn, axis=1)))]
    mand = adv + own
    segs = {
        "maxilla": {"translation": [0.0, round(float(adv), 2), round(float(imp), 2)],
                    "rotation": {"axis": [1, 0, 0], "angle_deg": -2.0,
                                 "center": [round(float(c), 2) for c in a_point]}},
        "mandible": {"translation": [0.0, round(float(mand), 2), 0.0]},
        "chin": {"translation": [0.0, round(float(mand + genio), 2), 0.0]},
    }
    return _plan(segs)


def write_case(folder: Path, head, *, ct: bool = False, ct_spacing: float = 1.0,
               follow_up_months: float | None = None, plan: dict | None = None) -> dict:
    """Write one synthetic head as a case folder (into an existing empty folder); plan: the
    plan.yaml content (default `sample_plan` of the head's shape, faceplan's own family)."""
    import yaml

    preop = folder / "preop"
    (preop / "bone").mkdir(parents=True)
    (preop / "teeth").mkdir()
    head.skin.export(preop / "skin.stl")
    for seg, mesh in head.bones.items():
        mesh.export(preop / "bone" / f"{seg}.stl")
    import trimesh

    for arch, (v, f, _) in head.teeth.items():
        trimesh.Trimesh(v, f, process=False).export(preop / "teeth" / f"{arch}.stl")
    # a landmark whose definition has no anatomical answer on this head (`AltHead.ill_defined`)
    # is not one a clinician would place: the case does not give it
    skip = set(getattr(head, "ill_defined", ()))
    (preop / "landmarks.json").write_text(json.dumps(
        {k: [round(float(x), 4) for x in v] for k, v in head.landmarks.items() if k not in skip}, indent=1))
    if plan is None:
        plan = sample_plan(head.shape)
    segs = plan["segments"]
    genio = segs["chin"]["translation"] != segs["mandible"]["translation"]
    (folder / "plan.yaml").write_text(
        "# faceplan synth: sample bimaxillary plan (Le Fort I, BSSO"
        + (", genioplasty" if genio else "") + ")\n"
        + yaml.safe_dump(plan, sort_keys=False))
    info = {"id": folder.name, "synthetic": True, "seed": int(head.seed)}
    if follow_up_months is not None:
        info["follow_up_months"] = round(float(follow_up_months), 2)
    (folder / "case.yaml").write_text(yaml.safe_dump(info, sort_keys=False))
    if ct:
        from facemodel.ct_phantom import ct_volume_from_surfaces, write_nifti

        hu, affine = ct_volume_from_surfaces(head.skin, head.bones, spacing=ct_spacing,
                                             seed=int(head.seed))
        write_nifti(preop / "ct.nii.gz", hu, affine)
    return {"id": folder.name, "seed": int(head.seed), "shape": head.shape.as_dict(),
            "withheld_effect": None, "plan": plan}


# --------------------------------------------------------------------------- the post-op truth

def _rng(seed: int):
    """The case's own random stream (post-op draws), independent of the head's."""
    return np.random.default_rng([int(seed), 19])


def draw_effect(name: str, rng, moved: tuple) -> tuple:
    """(effect name, flat value dict or None when it is set from a skin-change target,
    plan_actual flag) drawn from the ranges above."""
    if name == "random":
        from facemodel.effects import EFFECT_NAMES

        name = str(rng.choice(EFFECT_NAMES))
    if name == "sliding":
        # the lips ride on the maxilla (upper) and mandible (lower); the chin on its segment
        options = [s for s in ("maxilla", "chin") if s in moved] + ["1"]
        pick = str(rng.choice(options))
        return name, {"sliding": 1.0 if pick == "1" else pick}, False
    if name == "bone_execution":
        seg = str(rng.choice([s for s in ("maxilla", "mandible") if s in moved] or list(moved)))
        d = rng.normal(size=3)
        t = d / np.linalg.norm(d) * rng.uniform(*BONE_TRANSLATION_MM)
        a = rng.normal(size=3)
        r = a / np.linalg.norm(a) * rng.uniform(*BONE_ROTATION_DEG)
        value = {f"bone_execution.{seg}": [round(float(v), 4) for v in (*t, *r)]}
        return name, value, bool(rng.uniform() < 0.5)
    if name == "stiffness":
        layer = str(rng.choice(STIFF_LAYERS))
        f = rng.uniform(*SOFTER) if rng.uniform() < 0.5 else rng.uniform(*STIFFER)
        return name, {f"stiffness.{layer}": round(float(f), 4)}, False
    if name in SKIN_CHANGE_MM:
        return name, None, False
    return None, None, False


def _region_ids(model, regions, seen):
    """The model's skin nodes and the mask of those in `regions` (None: all) among `seen` (the
    skin nodes the post-op scan sees, `_seen_nodes`): a skin-change target is a change a scan
    can show."""
    from planner.pipeline import skin_surface

    _, _, ids = skin_surface(model)
    mask = np.asarray(seen, bool).copy()
    if regions is not None:
        chosen = np.concatenate([np.asarray(model.regions[r], np.int64) for r in regions if r in model.regions])
        mask &= np.isin(ids, chosen)
    return ids, mask


def _seen_nodes(model, case, scanner: str = "frontal") -> np.ndarray:
    """The model's skin nodes (pre-op, in `skin_surface` order) the `scanner`'s scan of the
    case's pre-op skin sees (`facemodel.synthetic.scan_coverage`)."""
    from facemodel import synthetic as sy
    from planner.pipeline import skin_surface

    x, _, _ = skin_surface(model)
    return sy.scan_coverage(x, case.skin.vertices, case.skin.faces, case.landmarks, scanner=scanner)


def _skin_change(pred, base, seen, regions=None) -> dict:
    ids, mask = _region_ids(pred.model, regions, seen)
    d = np.linalg.norm(pred.displacement[ids] - base.displacement[ids], axis=1)[mask]
    return {"rms_mm": round(float(np.sqrt(np.mean(d * d))), 4), "max_mm": round(float(d.max()), 4)}


def _solve_record(kind: str, pred) -> dict:
    """Newton counts of one truth solve (for the bench and the progress log)."""
    info = pred.solver.get("info", {})
    t = info.get("timings") or {}
    return {"solve": kind, "nodes": int(len(pred.model.nodes)), "steps": pred.solver.get("steps"),
            "iterations": pred.solver.get("iterations"), "cutbacks": info.get("cutbacks"),
            "factorizations": info.get("factorizations"),
            # contacts the augmentations left deeper than twice their tolerance (mm)
            "contact_unmet_mm": info.get("contact_unmet_mm") or {},
            # where a solve's time goes: residual and tangent assembly (contact terms
            # included), linear solves, the whole Newton run
            "assembly_s": t.get("assembly"), "linear_s": t.get("solve"), "newton_s": t.get("total")}


def solve_reducing(solve, effects, name: str | None, attempts: int = MAX_REDUCTIONS):
    """(prediction, effects used, reductions) of `solve(effects)`; when the solve fails and
    `name` is an effect whose value was set from a skin-change target (a value the truth model
    may not be able to reach: large growth pressing the lips together), the effect's distance
    from "none" is reduced and the solve repeated, `attempts` times at most. The reduction
    follows the load path: a solve that failed after converging at load fraction L had the
    effect at L of its value (it is ramped with the load), so the next value is
    REDUCTION_MARGIN x L of the distance (at least MIN_REDUCTION, a half when L is not known);
    each reduction is recorded ({"from", "to", "load_reached", "reason"}) for the key. Any
    other failure, or one still failing after `attempts`, is raised."""
    from facemodel import effects as fe

    reductions = []
    while True:
        try:
            return solve(effects), effects, reductions
        except SolveError as exc:
            if name is None or len(reductions) >= attempts:
                raise
            reached = getattr(exc.__cause__, "last_converged_load", None)
            factor = 0.5
            if reached is not None and 0.0 < float(reached) < 1.0:
                factor = max(MIN_REDUCTION, REDUCTION_MARGIN * float(reached))
            p = fe.parameters(name)[0]
            v0 = effects.value(name)
            v = round(p.none + factor * (v0 - p.none), 5)      # the key's value is the one used
            reductions.append({"from": round(v0, 5), "to": v,
                               "load_reached": None if reached is None else round(float(reached), 4),
                               "reason": str(exc)[:300]})
            effects = effects.with_value(name, v)


def lip_groups(nodes, hexes=None):
    """Side of the mouth slit of generic nodes (hexes None) or elements: 1 below the mouth
    line (lower lip), 2 above, 0 on it (nodes outside the slit, where the lips join). The
    generic meshes are built along rays of the mean head (`generic_mesh.builder`), so a
    node's elevation in that frame is its chart row's; every resolution has a row on the
    mouth line, so no element straddles it."""
    from facemodel import head_geometry as hg

    _, phi, _ = hg.from_cartesian(np.asarray(nodes, float), hg.GENERIC)
    if hexes is not None:
        return np.where(phi[np.asarray(hexes)].mean(axis=1) < hg.PHI_STOMION, 1, 2)
    tol = 1e-7                  # deg: round-off of the ray frame, far below any row spacing
    return np.where(phi < hg.PHI_STOMION - tol, 1, np.where(phi > hg.PHI_STOMION + tol, 2, 0))


def prolonged_patient(generic, companion_generic, companion):
    """The patient model of `generic` (a finer generic mesh, e.g. fine) from the registration
    `companion` of `companion_generic` (e.g. standard) without registering it again: every
    node of `generic` located in `companion_generic` (both are meshes of the same generic
    tissue, `registration.prolong`; each lip's nodes in that lip's elements) and carried by the
    companion's registered positions. The finer mesh's free nodes that the coarser elements'
    chords bring within the teeth clearance are pushed clear (`registration.teeth.
    clear_teeth`: the skin and the attached nodes held, the elements kept above the
    registration's scaled-Jacobian threshold, a lip node pushed only away from the other
    lip), the lips separated where the pushes made them cross (`registration.lips.
    separate_lips`, to the registration's gap) and any element still below the threshold
    repaired (`registration.repair.repair_mesh`, the nodes at the teeth clearance held),
    in rounds until the clearance, the gap and the quality hold together (CARRY_PASSES at
    most). Returns (patient model, location, report)."""
    import dataclasses
    import time

    from registration.face import reorient_fibres
    from registration.lips import lip_overlap, quad_vertex_normals, separate_lips
    from registration.mesh_match import MatchOptions
    from registration.prolong import carry, locate_points
    from registration.quality import min_scaled_jacobian
    from registration.repair import repair_mesh
    from registration.teeth import Arch, clear_teeth, union_distance

    t0 = time.perf_counter()
    X, H = np.asarray(generic.nodes, float), np.asarray(generic.hexes, np.int64)
    loc = locate_points(X, companion_generic.nodes, companion_generic.hexes, point_group=lip_groups(X),
                        element_group=lip_groups(companion_generic.nodes, companion_generic.hexes))
    x = carry(loc, companion_generic.hexes, companion.nodes)
    report = {"companion_nodes": int(len(companion.nodes)), "nodes": int(len(x)),
              "outside_companion_mm": round(float(loc.outside_mm.max()), 4),
              "min_scaled_jacobian_carried": round(float(min_scaled_jacobian(x, H).min()), 4)}
    opt = MatchOptions()
    held = np.concatenate([np.asarray(generic.node_sets["skin"], np.int64)]
                          + [np.asarray(v, np.int64) for k, v in generic.node_sets.items()
                             if k.startswith("attach_")])
    attached = np.concatenate([np.asarray(v, np.int64) for k, v in generic.node_sets.items()
                               if k.startswith("attach_")] or [np.zeros(0, np.int64)])
    lips = None
    if {"lip_upper_contact", "lip_lower_contact"} <= set(generic.facet_sets):
        lips = (np.asarray(generic.facet_sets["lip_upper_contact"]),
                np.asarray(generic.facet_sets["lip_lower_contact"]))
    arches = [Arch(k, v, f, seg) for k, (v, f, seg) in (companion.teeth or {}).items()]
    movable = np.setdiff1d(np.arange(len(x)), held)
    away = None
    if arches and lips is not None:     # a lip node pushed off the teeth not into the other lip
        away = -(quad_vertex_normals(x, lips[0]) + quad_vertex_normals(x, lips[1]))
        away[np.intersect1d(np.unique(lips[0]), np.unique(lips[1]))] = 0.0

    def clearance(x):
        return float(union_distance(arches, x[movable], opt.teeth_clearance_mm + 1.0)[0].min()) \
            if arches else np.inf

    def gap(x):
        return float(lip_overlap(x, *lips)["min_gap_mm"]) if lips is not None else np.inf

    # the three conditions hold together (the pushes, the separation and the repair each move
    # nodes the others placed): push off the teeth, separate the lips, repair with the nodes at
    # the teeth clearance held, and again until the teeth clearance, the lip gap (to
    # separate_lips' tolerance) and the element quality all hold at once
    pushes, gap0, held_together = [], gap(x), False
    for rounds in range(1, CARRY_PASSES + 1):
        if arches and clearance(x) < opt.teeth_clearance_mm:
            x, rep = clear_teeth(x, H, arches, held, clearance=opt.teeth_clearance_mm,
                                 threshold=opt.threshold, away=away)
            pushes.append(rep)
        if lips is not None and gap(x) < opt.lip_gap_mm - 1e-3:
            x, _ = separate_lips(x, H, lips[0], lips[1], attached,
                                 skin_nodes=np.asarray(generic.node_sets["skin"], np.int64),
                                 gap=opt.lip_gap_mm, threshold=opt.threshold, arches=arches or None,
                                 teeth_clearance=opt.teeth_clearance_mm)
        if min_scaled_jacobian(x, H).min() < opt.threshold:
            # a finer element across a kink between two coarser ones, or one the pushes
            # squeezed, is repaired as the registration repairs (skin and bone held), with the
            # nodes within CLEARANCE_HOLD_MM of the teeth clearance held too: the repair does
            # not take them back towards a tooth
            near = movable[union_distance(arches, x[movable], opt.teeth_clearance_mm + 1.0)[0]
                           < opt.teeth_clearance_mm + CLEARANCE_HOLD_MM] if arches else movable[:0]
            x, rep = repair_mesh(x, H, threshold=opt.threshold, fixed=np.union1d(held, near))
            if rep["elements_still_below_threshold"]:       # the held nodes leave no room
                x, _ = repair_mesh(x, H, threshold=opt.threshold, fixed=held)
        if (clearance(x) >= opt.teeth_clearance_mm and gap(x) >= opt.lip_gap_mm - LIP_GAP_TOL
                and min_scaled_jacobian(x, H).min() >= opt.threshold):
            held_together = True
            break
    # False: the rounds ran out with one condition short (the report's figures say which)
    report["start"] = {"rounds": rounds, "conditions_hold": held_together}
    if arches:
        report["teeth"] = {"nodes_inside_before": int(pushes[0].get("nodes_inside_before", 0)) if pushes else 0,
                           "nodes_pushed": int(sum(r.get("nodes_pushed", 0) for r in pushes)),
                           "min_distance_after_mm": round(clearance(x), 4)}
    if lips is not None:
        report["lips"] = {"min_gap_before_mm": round(gap0, 4), "min_gap_mm": round(gap(x), 4)}
    q = min_scaled_jacobian(x, H)
    report["min_scaled_jacobian"] = round(float(q.min()), 4)
    if q.min() <= 0.0:
        raise SolveError(f"the {len(x)}-node model carried from the registered companion has "
                         f"{int(np.sum(q <= 0))} inverted element(s)")
    fibres = reorient_fibres(X, x, H, generic.fibres)
    report["time_s"] = round(time.perf_counter() - t0, 2)
    return dataclasses.replace(generic, nodes=x, fibres=fibres, teeth=companion.teeth), loc, report


def make_postop(folder: str, seed: int, withheld: tuple, truth_resolution: str,
                contact: bool = True, timings: dict | None = None, log=None,
                deadline: float | None = None, neck: str = "free", floor: str = "free",
                scanner: str = "frontal") -> dict:
    """Predict and write `folder`/postop/skin.stl (and plan_actual.yaml) for an existing case
    folder; return the key record's post-op fields. contact: lip contact in the truth model
    (on for every case the command makes; off only to keep tests on coarse meshes short).
    A truth resolution listed in REGISTERED_AT is registered at its companion resolution and
    carried to its own mesh (`prolonged_patient`); the effect's value is set and its skin
    change measured on the companion, and the finer model solved once with that value.
    timings: a dict that receives the stages' times (s) and the solves' Newton counts (kept
    when a solve fails); log: a callable receiving the truth solves' progress lines (one per
    Newton iteration); deadline: `time.perf_counter()` by which every truth solve must have
    ended (each gets what is left as its budget; a `SolveError` when it is spent); neck: the
    truth model's neck cut, "free" (the predicting model's), "held" or "random" (either, drawn
    from the seed on a stream of its own, so the rest of the case is the same); floor: the truth
    model's floor of the mouth, likewise (a stream of its own too); scanner: the post-op scan's
    (`facemodel.synthetic.SCANNERS`), whose view the skin-change targets are met in."""
    import dataclasses

    import trimesh
    import yaml

    import generic_mesh
    import registration
    from registration import errors as reg_errors
    from facemodel import effects as fe
    from facemodel import synthetic as sy
    from generic_mesh.builder import RESOLUTIONS
    from planner.case import load_case
    from planner.pipeline import Progress, skin_sensitivities, skin_surface, unmet_text
    from planner.pipeline import solve_plan as _solve_plan
    from planner.plan import load_plan, parse_plan

    # one progress clock for the whole case: its lines (stages, each truth solve's Newton
    # iterations) then read as one time line
    progress = None if log is None else Progress(echo=log)

    def say(message):
        if progress is not None:
            progress.say(message)

    def solve_plan(*a, what: str, **kw):
        left = None
        if deadline is not None:
            left = deadline - time.perf_counter()
            if left <= 0.0:
                raise SolveError(f"{Path(folder).name}: the case's time budget is spent before its next solve")
        say(f"truth solve: {what}" + ("" if left is None else f" (budget left {left:.0f} s)"))
        with _records_to(progress):
            return _solve_plan(*a, progress=progress, max_seconds=left, **kw)

    folder = Path(folder)
    rng = _rng(seed)
    case = load_case(folder, cache=False)
    plan = load_plan(folder / "plan.yaml")
    fu = case.info.follow_up_months
    moved = tuple(plan.motions())
    name, value, want_actual = draw_effect(withheld[0], rng, moved) if withheld[0] != "none" else (None, None, False)
    if withheld[1] is not None:                 # the value given on the command line
        value = withheld[1]
    # the truth model: generic layers re-proportioned, moduli perturbed, registered
    dermis, deep = (float(rng.uniform(1 - sy.PERTURB_LAYER, 1 + sy.PERTURB_LAYER)) for _ in range(2))

    def perturbed(resolution):
        return sy.perturb_layers(generic_mesh.load(resolution), RESOLUTIONS[resolution][3],
                                 dermis=dermis, deep=deep)

    overrides, mat_record = sy.perturbed_materials(rng)
    if neck == "random":
        neck = ("free", "held")[int(_rng(seed + 2 * 10**6).integers(2))]
    if floor == "random":
        floor = ("free", "held")[int(_rng(seed + 3 * 10**6).integers(2))]
    truth_plan = dataclasses.replace(plan, model=dataclasses.replace(plan.model, materials=overrides,
                                                                     contact=bool(contact), neck=neck,
                                                                     floor=floor))
    timings = {} if timings is None else timings
    companion = REGISTERED_AT.get(truth_resolution, truth_resolution)
    clock = time.perf_counter()
    say(f"truth model: registering the perturbed generic model (layers dermis x{dermis:.3f}, deep "
        f"x{deep:.3f}; moduli x{json.dumps(mat_record['modulus_factors'])}; neck {neck}; floor {floor}) at "
        f"{companion}")
    try:
        patient, _ = registration.mesh_match_and_repair(
            perturbed(companion), case.skin, case.bones, landmarks=case.landmarks or None,
            teeth=case.teeth or None, cache=False)
    except (reg_errors.RegistrationInputError, reg_errors.RegistrationFailure) as exc:
        raise SolveError(f"{folder.name}: registration of the truth model failed: {exc}") from exc
    timings[f"register_{companion}_s"] = time.perf_counter() - clock
    say(f"truth model: registered in {timings[f'register_{companion}_s']:.1f} s")
    finer = None
    if companion != truth_resolution:
        # the value is set, and its skin change measured, on the registered model; the finer
        # truth is solved once, with the value found (the scan is made from it)
        clock = time.perf_counter()
        finer, _, carried = prolonged_patient(perturbed(truth_resolution), perturbed(companion), patient)
        timings[f"carry_to_{truth_resolution}_s"] = time.perf_counter() - clock
        say(f"truth model: carried to {truth_resolution} ({carried['nodes']} nodes) in "
            f"{timings[f'carry_to_{truth_resolution}_s']:.1f} s")
    clock = time.perf_counter()
    base = solve_plan(patient, truth_plan, case.bones, follow_up_months=fu,
                      what=f"the plan without the effect on the {companion} model")
    timings["solve_base_s"] = time.perf_counter() - clock
    solves = [_solve_record("base", base)]
    timings["solves"] = solves
    seen = _seen_nodes(base.model, case, scanner)
    target = None
    if name is not None and value is None:
        # the value that changes the skin by a target drawn from the published range, from
        # the truth model's own sensitivity (linear estimate; the change reached is recorded)
        target = float(rng.uniform(*SKIN_CHANGE_MM[name]))
        clock = time.perf_counter()
        ids, sens = skin_sensitivities(base, [name])
        timings["sensitivity_s"] = time.perf_counter() - clock
        _, mask = _region_ids(base.model, SKIN_CHANGE_REGIONS[name], seen)
        per_unit = float(np.linalg.norm(sens[name], axis=1)[mask].max())
        p = fe.parameters(name)[0]
        v = float(np.clip(p.none + target / max(per_unit, 1e-9), p.lower, p.upper))
        value = {name: round(v, 5)}
    effects = fe.parse_effects(value or {})
    plan_actual = None
    if name == "bone_execution":
        from planner.pipeline import effect_motions

        motions = effect_motions(truth_plan, effects, base.setup["centroids"])
        if want_actual:
            actual = {"faceplan": 1, "frame": "RAS",
                      "segments": {s: {"matrix": np.round(T, 9).tolist()} for s, T in motions.items()}}
            (folder / "postop").mkdir(exist_ok=True)
            (folder / "postop" / "plan_actual.yaml").write_text(
                "# faceplan synth: the movements achieved in surgery\n" + yaml.safe_dump(actual, sort_keys=False))
            plan_actual = parse_plan(actual, "plan_actual.yaml")
            effects = fe.parse_effects({"bone_execution": 1})
    pred = base
    def truth(eff):
        clock = time.perf_counter()
        try:
            # from the base solution: the effect changes the problem by a little
            out = solve_plan(patient, truth_plan, case.bones, effects=eff, plan_actual=plan_actual,
                             follow_up_months=fu, guess=base.displacement,
                             what=f"with {json.dumps(eff.as_dict())} on the {companion} model")
        finally:
            timings["solve_effect_s"] = timings.get("solve_effect_s", 0.0) + time.perf_counter() - clock
        solves.append(_solve_record("effect", out))
        return out

    reductions = []
    if effects.active:
        requested = value
        pred, effects, reductions = solve_reducing(truth, effects, name if name in SKIN_CHANGE_MM else None)
        if reductions:
            value = {name: round(effects.value(name), 5)}
            print(f"faceplan synth: {folder.name}: warning: the truth solve of {name}={requested[name]} "
                  f"failed; the effect was reduced to {value[name]} ({len(reductions)} reduction(s), "
                  "recorded in the key)", file=sys.stderr, flush=True)
    region = SKIN_CHANGE_REGIONS.get(name) if name else None
    change = _skin_change(pred, base, seen, region)
    corrections = []
    if target is not None and not reductions:
        # the linear estimate misses where the response is not linear (muscle tone, contact):
        # a change reached outside the published range gets one secant correction towards the
        # target, v' = none + (v - none) target / reached (bounded), recorded in the key
        lo, hi = SKIN_CHANGE_MM[name]
        if not lo <= change["max_mm"] <= hi and change["max_mm"] > 0:
            p = fe.parameters(name)[0]
            v0 = effects.value(name)
            v = round(float(np.clip(p.none + (v0 - p.none) * target / change["max_mm"], p.lower,
                                    p.upper)), 5)
            if v != v0:
                try:
                    eff1 = effects.with_value(name, v)
                    pred1 = truth(eff1)
                except SolveError as exc:       # keep the first value: its solve converged
                    corrections.append({"from": round(v0, 5), "to": None, "reason": str(exc)[:300]})
                else:
                    pred, effects = pred1, eff1
                    value = {name: round(v, 5)}
                    change1 = _skin_change(pred, base, seen, region)
                    corrections.append({"from": round(v0, 5), "to": round(v, 5),
                                        "max_mm_before": change["max_mm"]})
                    change = change1
    if finer is not None:
        clock = time.perf_counter()
        try:
            pred = solve_plan(finer, truth_plan, case.bones, effects=effects, plan_actual=plan_actual,
                              follow_up_months=fu,
                              what=f"with {json.dumps(effects.as_dict())} on the {truth_resolution} model")
        except SolveError as exc:
            raise SolveError(f"{folder.name}: the {truth_resolution} truth solve failed "
                             f"(effects {json.dumps(effects.as_dict())}): {exc}") from exc
        finally:
            timings[f"solve_{truth_resolution}_s"] = time.perf_counter() - clock
        solves.append(_solve_record(truth_resolution, pred))
    # a truth whose lips or teeth overlap beyond the contact tolerance is still a converged
    # solution of the truth model, but not the contact state it asks for: the key says so
    unmet = pred.contact_unmet
    if unmet:
        print(f"faceplan synth: {folder.name}: warning: the truth solve ended with " + unmet_text(unmet)
              + " of penetration (recorded in the key, truth_contact_unmet_mm)", file=sys.stderr, flush=True)
    # the post-op skin: the patient's skin moved with the truth model's skin, scanned
    clock = time.perf_counter()
    x_pre, tris, ids = skin_surface(pred.model)
    moved_skin = sy.displaced_surface(case.skin.vertices, x_pre, tris, pred.displacement[ids])
    V, F, scan = sy.scan_like_surface(moved_skin, case.skin.faces, case.landmarks, rng, scanner=scanner)
    (folder / "postop").mkdir(exist_ok=True)
    trimesh.Trimesh(V, F, process=False).export(folder / "postop" / "skin.stl")
    timings["scan_s"] = time.perf_counter() - clock
    return {"effect": name, "value": value if name else None,
            "perturbation": {"truth_resolution": truth_resolution, "registered_at": companion,
                             "layer_thickness_factors": {"dermis": round(dermis, 4), "deep": round(deep, 4)},
                             "neck": neck, "floor": floor,
                             **mat_record, "scan": scan},
            "plan_actual": plan_actual is not None, "value_reductions": reductions,
            "value_corrections": corrections,
            "truth_contact_unmet_mm": {k: round(float(v), 4) for k, v in unmet.items()},
            "effect_skin_change_mm": {"regions": list(region) if region else "skin", "where": "seen by the scan",
                                      **change,
                                      "measured_at": companion,
                                      "target_max_mm": None if target is None else round(target, 4)}}


def make_case(root: str, seed: int, options: dict) -> dict:
    """One case folder `root`/synth_SEED (head, plan, case.yaml; the post-op scan when asked);
    its key record. A task of the dask cohort: everything it draws comes from `seed`."""
    import shutil

    from facemodel.synthetic import synthetic_head

    start = time.perf_counter()
    name = f"synth_{seed:04d}"
    target = Path(root) / name
    if target.exists():
        shutil.rmtree(target)
    target.mkdir(parents=True)
    withheld = options.get("withheld")
    fu = None
    if withheld is not None:
        fu = float(_rng(seed + 10**6).uniform(*FOLLOW_UP_MONTHS))
    family = options.get("head_family", "own")
    if family == "alt":
        from facemodel.synthetic_alt import alt_head

        head = alt_head(seed)
        plan = bone_plan(head, seed)
    else:
        head = synthetic_head(seed, size=options["surface_size"], distance=options["surface_size"] / 12.0,
                              mesher=options["mesher"])
        plan = None
    rec = write_case(target, head, ct=options["ct"], ct_spacing=options["ct_spacing"], follow_up_months=fu,
                     plan=plan)
    record = {"case": name, "seed": int(seed), "head_family": family,
              "effect": None, "value": None, "perturbation": None,
              "follow_up_months": None if fu is None else round(fu, 2), "plan_actual": False,
              "shape": rec["shape"], "plan": rec["plan"]}
    if withheld is not None:
        budget = options.get("case_max_minutes")
        with _SolveLog(options.get("solve_log"), name) as log:
            record.update(make_postop(str(target), seed, tuple(withheld), options["truth_resolution"],
                                      contact=options.get("contact", True), neck=options.get("truth_neck", "free"),
                                      floor=options.get("truth_floor", "free"),
                                      scanner=options.get("scanner", "frontal"),
                                      deadline=None if budget is None else start + 60.0 * float(budget),
                                      log=log))
    return record


class _records_to:
    """Within the context, the solver's and the face model's warnings (a load step cut back,
    continuation switched on, the soft-contact fallback) also go to `progress` (a
    `planner.pipeline.Progress`, or None: nothing), on its clock."""

    LOGGERS = ("solver", "facemodel")

    def __init__(self, progress):
        import logging

        self.handler = None
        if progress is not None:
            class _Handler(logging.Handler):
                def emit(self, record):
                    progress.say(f"{record.levelname.lower()}: {record.getMessage()}")

            self.handler = _Handler(level=logging.WARNING)

    def __enter__(self):
        import logging

        for name in self.LOGGERS if self.handler is not None else ():
            logging.getLogger(name).addHandler(self.handler)
        return self

    def __exit__(self, *exc):
        import logging

        for name in self.LOGGERS if self.handler is not None else ():
            logging.getLogger(name).removeHandler(self.handler)
        return False


class _SolveLog:
    """`--solve-log`: a context giving the callable that writes one case's truth-solve lines to
    `folder`/`name`.log as they come (line-buffered, so that a creeping solve can be followed
    with `tail -f`), or None without a folder. A case that fails ends its log with the failure;
    the exception goes on."""

    def __init__(self, folder, name: str):
        self.path = None if folder is None else Path(folder) / f"{name}.log"
        self.fh = None

    def __enter__(self):
        if self.path is None:
            return None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fh = open(self.path, "w", buffering=1, encoding="utf-8")
        return lambda line: self.fh.write(line + "\n")

    def __exit__(self, exc_type, exc, tb):
        if self.fh is not None:
            if exc is not None:
                self.fh.write(f"failed: {type(exc).__name__}: {exc}\n")
            self.fh.close()
        return False


def run_cases(root: Path, seeds: list, options: dict, scheduler: str | None, workers: int,
              echo=print) -> list:
    """The cases as dask.distributed tasks (a LocalCluster of `workers` processes unless a
    scheduler address is given); records in seed order."""
    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    if scheduler:
        client = Client(scheduler)
    else:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=":0")
        client = Client(cluster)
    try:
        futures = {client.submit(make_case, str(root), s, options, pure=False): s for s in seeds}
        out = {}
        for fut in as_completed(futures):
            rec = fut.result()
            out[futures[fut]] = rec
            echo(f"faceplan synth: {rec['case']} done (effect {rec['effect']})")
        return [out[s] for s in seeds]
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run(args) -> int:
    import sys

    from planner.atomic import atomic_output_dir, atomic_write_file

    _check(args)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("--out exists and is not a folder", file=str(out), field="--out")
    options = {"withheld": parse_withheld(args.withheld_effect), "truth_resolution": args.truth_resolution,
               "surface_size": args.surface_size, "mesher": args.mesher, "ct": args.ct,
               "ct_spacing": args.ct_spacing, "case_max_minutes": args.case_max_minutes,
               "truth_neck": args.truth_neck, "truth_floor": args.truth_floor, "scanner": args.scanner,
               "head_family": args.head_family,
               "solve_log": None if args.solve_log is None else str(Path(args.solve_log).resolve())}
    seeds = [args.seed + i for i in range(args.count)]
    with atomic_output_dir(out) as tmp:
        if out.is_dir():          # keep what the folder already holds
            import shutil

            shutil.copytree(out, tmp, dirs_exist_ok=True)
        if options["withheld"] is None and not args.scheduler:
            records = []          # pre-op folders only: quick, in this process
            for s in seeds:
                records.append(make_case(str(tmp), s, options))
                print(f"faceplan synth: {out / records[-1]['case']} (seed {s})")
        else:
            records = run_cases(tmp, seeds, options, args.scheduler, args.workers,
                                echo=lambda m: print(m, file=sys.stderr, flush=True))
            for r in records:
                print(f"faceplan synth: {out / r['case']} (seed {r['seed']})")
    if args.key:
        with atomic_write_file(args.key) as fh:
            json.dump(records, fh, indent=1)
    return 0
