"""Benchmark: registration and prediction on held-out synthetic patients.

The solver and registration settings were chosen on a handful of heads (the demo head, synth
seeds 7, 11, 13 and the benchmarks' cases). This bench judges them on patients never used to
choose anything: synthetic heads (`facemodel.synthetic.synthetic_head`) of seeds 1000-1029
(no test, bench or default uses them), each with a plan drawn over the clinical range of
bimaxillary surgery -- Le Fort I advancement 0-8 mm and impaction 0-4 mm, mandibular
(BSSO) movement -10..+10 mm, genioplasty advancement 0-8 mm on the mandible, each segment
pitched by -3..+3 deg about a transverse axis through it (the maxilla's through A point). The
case folders are written by `faceplan synth`'s own writer (`planner.commands.synth.write_case`)
and run through the pipeline's functions (`planner.pipeline.register_case`, `predict_case`),
at each resolution asked.

Per case and resolution: success or the failure (exception type and message), Newton
iterations, load steps, cut-backs, whether the soft-contact fallback made the prediction, the
contacts the prediction left deeper than twice their tolerance (a warning of `faceplan
predict`), minimum scaled Jacobian of the registered and of the predicted mesh, inverted and
corner-folded elements (the fields of `planner.report.solve_summary`), landmark errors (registered landmark nodes against the
head's true landmarks, mm) and the time of each stage; then per resolution the success rate,
median / max iterations, total cut-backs, the worst scaled Jacobian, landmark error median /
max, median stage times, and a summary line
`heldout <res>: ok=<k>/<n> newton_median=.. newton_max=.. cutbacks=.. fallbacks=.. contact_unmet=..
min_sj=.. inverted=.. folded=.. lm_median_mm=.. lm_max_mm=.. registration_median_s=.. predict_median_s=..`.

Flags: `--count N` patients (default 30), `--first-seed S` (default 1000), `--seeds A,B,..`
(these seeds instead, e.g. the cohort's failures run again), `--log FILE` (the solver's
per-step log, logger "solver.newton" at INFO, appended to FILE), `--resolutions
coarse,standard`, `--cuts whole,scan,below_eyes,mid_nose` (the skins: the whole head's, default, or cut to the
face as a face scan, a CBCT ending below the eyes or one ending at mid-nose sees it --
`facemodel.synthetic_alt.crop_face`, as `bench/heads.py` cuts them; the plan is the same for
every cut; the regions the registration reports not fitted are listed), `--given-landmarks`
(the cases give their true landmarks; by default they
give none and the registration locates them on the skin, so that the landmark errors measure
the located landmarks' settings too), `--json FILE` (every record, rewritten after each case),
`--summarise FILE...` (run nothing: the summaries of records written by --json, e.g. a cohort
run in parts), `--teeth-increment-fraction F` (the peer run with another floor of the contact
nodes' increment limit). Registrations use a private cache (no result of an earlier run is reused; within
a run the prediction reuses the registration just made, as `faceplan predict` would on a second
call).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

from _peers import add_teeth_increment_fraction, apply_teeth_increment_fraction

# `python bench/heldout.py` puts bench/ first on sys.path, where bench/registration.py would
# shadow the registration package: drop it.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

FIRST_SEED = 1000
PLAN_STREAM = 20261125     # the plans' own random stream (independent of the head's shape)


def _rotation_x(deg: float) -> np.ndarray:
    t = np.radians(deg)
    c, s = np.cos(t), np.sin(t)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rigid(deg: float, centre: np.ndarray, translation) -> np.ndarray:
    """4x4: a pitch of `deg` about the transverse axis through `centre`, then `translation`."""
    m = np.eye(4)
    r = _rotation_x(deg)
    m[:3, :3] = r
    m[:3, 3] = centre - r @ centre + np.asarray(translation, float)
    return m


def draw_plan(head, seed: int) -> tuple[dict, dict]:
    """A plan over the clinical range for `head` (module docstring); returns (plan dict for
    plan.yaml, the drawn values)."""
    from facemodel import head_geometry as hg

    rng = np.random.default_rng(np.random.SeedSequence([PLAN_STREAM, int(seed)]))
    d = {"maxilla_advance_mm": rng.uniform(0.0, 8.0), "maxilla_impaction_mm": rng.uniform(0.0, 4.0),
         "maxilla_pitch_deg": rng.uniform(-3.0, 3.0), "mandible_mm": rng.uniform(-10.0, 10.0),
         "mandible_pitch_deg": rng.uniform(-3.0, 3.0), "chin_advance_mm": rng.uniform(0.0, 8.0),
         "chin_pitch_deg": rng.uniform(-3.0, 3.0)}
    shape = head.shape
    a_point = np.asarray(hg.to_cartesian(0.0, -9.0, float(hg.bone_radius(0.0, -9.0, shape, side=1)), shape),
                         float)
    maxilla = _rigid(d["maxilla_pitch_deg"], a_point,
                     [0.0, d["maxilla_advance_mm"], d["maxilla_impaction_mm"]])
    mand_c = np.asarray(head.bones["mandible"].vertices, float).mean(axis=0)
    mandible = _rigid(d["mandible_pitch_deg"], mand_c, [0.0, d["mandible_mm"], 0.0])
    # the chin rides on the mandible: the genioplasty's own motion, then the mandible's
    chin_c = np.asarray(head.bones["chin"].vertices, float).mean(axis=0)
    chin = mandible @ _rigid(d["chin_pitch_deg"], chin_c, [0.0, d["chin_advance_mm"], 0.0])
    segs = {name: {"matrix": [[round(float(v), 9) for v in row] for row in m]}
            for name, m in (("maxilla", maxilla), ("mandible", mandible), ("chin", chin))}
    plan = {"faceplan": 1, "frame": "RAS", "segments": segs,
            "muscles": {"orbicularis_oris": 0.0, "mentalis": 0.0}, "model": {"contact": True}}
    return plan, {k: round(float(v), 3) for k, v in d.items()}


def _predicted_quality(folder: Path) -> float:
    """Minimum scaled Jacobian (corners, centres and Gauss points, `registration.quality`) of
    the elements of prediction.vtu."""
    import meshio

    from registration.quality import scaled_jacobians

    m = meshio.read(folder / "prediction.vtu")
    hexes = m.cells_dict["hexahedron"]
    q = scaled_jacobians(np.asarray(m.points, float), np.asarray(hexes))
    return float(q.min())


def run_case(seed: int, resolution: str, root: Path, landmarks: bool, cut: str = "whole") -> dict:
    """Register and predict patient `seed` at `resolution`, its skin cut to the face at `cut`
    ("whole": uncut; `facemodel.synthetic_alt.crop_face`'s heights otherwise); a record of what
    happened."""
    import generic_mesh
    import yaml

    from facemodel.synthetic import synthetic_head
    from planner.case import load_case
    from planner.commands.synth import write_case
    from planner.pipeline import Progress, predict_case, register_case
    from planner.report import solve_summary
    from registration.quality import min_scaled_jacobian

    rec: dict = {"seed": seed, "resolution": resolution, "cut": cut, "ok": False}
    t0 = time.perf_counter()
    head = synthetic_head(seed)
    plan, drawn = draw_plan(head, seed)     # from the whole head: the same plan for every cut
    if cut != "whole":
        from facemodel.synthetic_alt import crop_face

        head = crop_face(head, cut)
    folder = root / f"heldout_{seed:04d}_{resolution}_{cut}"
    folder.mkdir()
    write_case(folder, head)
    (folder / "plan.yaml").write_text("# bench/heldout.py: a plan drawn over the clinical range\n"
                                      + yaml.safe_dump(plan, sort_keys=False))
    if not landmarks:
        (folder / "preop" / "landmarks.json").unlink()
    rec["plan"] = drawn
    rec["times_s"] = {"make_case": time.perf_counter() - t0}
    stage = "registration"
    try:
        t1 = time.perf_counter()
        patient, reg = register_case(load_case(folder), resolution, Progress(echo=False))
        rec["times_s"]["registration"] = time.perf_counter() - t1
        rec["registration_stages_s"] = {k: round(float(v), 2) for k, v in reg.get("time", {}).items()}
        generic = generic_mesh.load(resolution)
        rec["registered_min_sj"] = float(min_scaled_jacobian(patient.nodes, patient.hexes).min())
        rec["skin_fit_mean_mm"] = reg["fit"]["skin"]["mean_mm"]
        rec["skin_fit_max_mm"] = reg["fit"]["skin_nodes"]["max_mm"]
        search = reg.get("landmark_search") or {}
        rec["landmarks_not_found"] = search.get("not_found", [])
        rec["head_frame_rotation_deg"] = search.get("head_frame_rotation_deg")
        rec["landmark_error_mm"] = {k: float(np.linalg.norm(patient.nodes[i] - head.landmarks[k]))
                                    for k, i in generic.landmarks.items() if k in head.landmarks}
        rec["regions_not_fitted"] = sorted(k for k, v in (reg.get("regions") or {}).items()
                                           if not v.get("fitted", True))
        stage = "prediction"
        t2 = time.perf_counter()
        out = predict_case(folder, root / f"predict_{seed:04d}_{resolution}_{cut}", resolution=resolution,
                           render=False, echo=False)
        rec["times_s"]["predict"] = time.perf_counter() - t2
        report = json.loads((out / "report.json").read_text())
        rec.update(solve_summary(report))
        rec["predict_stages_s"] = report.get("timings_s", {})
        rec["predicted_min_sj"] = _predicted_quality(out)
        rec["ok"] = True
    except Exception as exc:  # a bench records every failure mode and goes on
        rec["failed_in"] = stage
        rec["error"] = f"{type(exc).__name__}: {exc}"
        tb = traceback.extract_tb(exc.__traceback__)
        if tb:
            rec["where"] = f"{Path(tb[-1].filename).name}:{tb[-1].lineno} ({tb[-1].name})"
    rec["times_s"]["total"] = time.perf_counter() - t0
    return rec


def _median(v):
    return float(np.median(v)) if len(v) else float("nan")


def summarise(records: list[dict], resolution: str, cut: str = "whole") -> str:
    rs = [r for r in records if r["resolution"] == resolution and r.get("cut", "whole") == cut]
    label = resolution if cut == "whole" else f"{resolution}/{cut}"
    ok = [r for r in rs if r["ok"]]
    its = [r["newton_iterations"] for r in ok if r.get("newton_iterations") is not None]
    cut = [r["cutbacks"] or 0 for r in ok]
    sj = [r["predicted_min_sj"] for r in ok] + [r["registered_min_sj"] for r in rs if "registered_min_sj" in r]
    inv = sum(r["inverted_elements"] for r in ok)
    folded = sum(r["folded_corner_elements"] for r in ok)
    lm = [e for r in rs for e in r.get("landmark_error_mm", {}).values()]
    print(f"\n== {label}: {len(ok)}/{len(rs)} succeeded")
    for r in rs:
        if not r["ok"]:
            print(f"  FAILED seed {r['seed']} in {r['failed_in']}: {r['error']} [{r.get('where', '')}] plan {r['plan']}")
    if its:
        cont = [r for r in ok if r.get("continuation_from_load") is not None]
        print(f"  Newton iterations: median {_median(its):.0f}, max {max(its)}; cut-backs: total {sum(cut)}, "
              f"cases with any {sum(c > 0 for c in cut)}; pseudo-transient continuation in "
              f"{len(cont)} case(s)" + (" (seeds " + ", ".join(
                  f"{r['seed']} from load {r['continuation_from_load']:.3g}" for r in cont) + ")"
                                        if cont else ""))
        soft = [r for r in ok if r.get("contact_fallback")]
        print(f"  soft-contact fallback (the nominal solve failed; a softer lip contact, warned): "
              f"{len(soft)} case(s)" + (" (seeds " + ", ".join(str(r["seed"]) for r in soft) + ")" if soft else ""))
        unmet = [r for r in ok if r.get("contact_unmet_mm")]
        print(f"  contact deeper than twice its tolerance at the end (converged, reported as a "
              f"warning): {len(unmet)} case(s)" + (" (" + "; ".join(
                  f"seed {r['seed']}: " + ", ".join(f"{k} {v:.2f} mm" for k, v in sorted(r["contact_unmet_mm"].items()))
                  for r in unmet) + ")" if unmet else ""))
    if sj:
        print(f"  minimum scaled Jacobian: registered {min(r['registered_min_sj'] for r in rs if 'registered_min_sj' in r):.3f}"
              + (f", predicted {min(r['predicted_min_sj'] for r in ok):.3f}" if ok else "")
              + f"; after prediction: {inv} inverted element(s) (a Gauss-point Jacobian <= 0), "
              f"{folded} with a folded corner only")
    if lm:
        print(f"  landmark error (registered node vs truth): median {_median(lm):.2f} mm, "
              f"p90 {np.percentile(lm, 90):.2f} mm, max {max(lm):.2f} mm")
        names = sorted({k for r in rs for k in r.get("landmark_error_mm", {})})
        print("    per landmark (median / max mm): " + ", ".join(
            f"{k} {_median([r['landmark_error_mm'][k] for r in rs if k in r.get('landmark_error_mm', {})]):.2f}/"
            f"{max(r['landmark_error_mm'][k] for r in rs if k in r.get('landmark_error_mm', {})):.2f}"
            for k in names))
    stages: dict[str, list] = {}
    for r in rs:
        for k, v in r["times_s"].items():
            stages.setdefault(k, []).append(v)
        for k, v in r.get("predict_stages_s", {}).items():
            stages.setdefault(f"predict.{k}", []).append(v)
    print("  time per stage (median / max s): " + ", ".join(
        f"{k} {_median(v):.1f}/{max(v):.1f}" for k, v in stages.items()))
    unfit = sorted({k for r in rs for k in r.get("regions_not_fitted", [])})
    if unfit:
        print("  regions reported not fitted (cases): " + ", ".join(
            f"{k} ({sum(k in r.get('regions_not_fitted', []) for r in rs)})" for k in unfit))
    line = (f"heldout {label}: ok={len(ok)}/{len(rs)} "
            f"newton_median={_median(its):.0f} newton_max={max(its) if its else 'nan'} "
            f"cutbacks={sum(cut)} fallbacks={sum(bool(r.get('contact_fallback')) for r in ok)} contact_unmet={sum(bool(r.get('contact_unmet_mm')) for r in ok)} min_sj={min(sj) if sj else float('nan'):.3f} inverted={inv} folded={folded} "
            f"lm_median_mm={_median(lm):.2f} lm_max_mm={max(lm) if lm else float('nan'):.2f} "
            f"registration_median_s={_median(stages.get('registration', [])):.1f} "
            f"predict_median_s={_median(stages.get('predict', [])):.1f}")
    return line


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=30, help="patients (default 30)")
    parser.add_argument("--first-seed", type=int, default=FIRST_SEED,
                        help=f"first patient seed (default {FIRST_SEED}; held out: used nowhere else)")
    parser.add_argument("--seeds", help="comma-separated seeds to run instead of --first-seed/--count")
    parser.add_argument("--log", help="append the solver's per-step log (INFO) to this file")
    parser.add_argument("--resolutions", default="coarse,standard",
                        help="comma-separated: coarse, standard, fine (default coarse,standard)")
    parser.add_argument("--given-landmarks", action="store_true",
                        help="the cases give their true landmarks (default: none given, the "
                             "registration locates them on the skin)")
    parser.add_argument("--cuts", default="whole",
                        help="comma-separated skins: whole (default), and partial ones cut to the "
                             "face as bench/heads.py cuts them: scan, below_eyes, mid_nose")
    parser.add_argument("--json", help="write every record to this file")
    add_teeth_increment_fraction(parser)
    parser.add_argument("--summarise", nargs="+", metavar="JSON",
                        help="run nothing: print the summaries of the records in these files "
                             "(written by --json; e.g. a cohort run in parts)")
    args = parser.parse_args()
    if args.summarise:
        records = [r for f in args.summarise for r in json.loads(Path(f).read_text())]
        order = [r for r in ("coarse", "standard", "fine") if any(x["resolution"] == r for x in records)]
        cuts = list(dict.fromkeys(x.get("cut", "whole") for x in records))
        lines = [summarise(records, res, c) for res in order for c in cuts
                 if any(x["resolution"] == res and x.get("cut", "whole") == c for x in records)]
        print()
        for ln in lines:
            print(ln)
        return 0 if all(r["ok"] for r in records) else 1
    apply_teeth_increment_fraction(args.teeth_increment_fraction)
    resolutions = [r.strip() for r in args.resolutions.split(",") if r.strip()]
    cuts = [c.strip() for c in args.cuts.split(",") if c.strip()]
    from facemodel.synthetic_alt import CUTS

    bad_cuts = [c for c in cuts if c != "whole" and c not in CUTS]
    if bad_cuts or not cuts:
        parser.error(f"--cuts: unknown cut(s) {bad_cuts} (whole, {', '.join(CUTS)})")
    bad = [r for r in resolutions if r not in ("coarse", "standard", "fine")]
    if bad or args.count < 1:
        parser.error(f"unknown resolution(s) {bad}" if bad else "--count must be at least 1")
    seeds = list(range(args.first_seed, args.first_seed + args.count))
    if args.seeds:
        try:
            seeds = [int(v) for v in args.seeds.split(",") if v.strip()]
        except ValueError:
            parser.error(f"--seeds must be comma-separated integers, got {args.seeds!r}")
    if args.log:
        import logging

        handler = logging.FileHandler(args.log)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        newton_log = logging.getLogger("solver.newton")
        newton_log.addHandler(handler)
        newton_log.setLevel(logging.INFO)
    print(f"held-out patients: seeds {', '.join(map(str, seeds)) if args.seeds else f'{seeds[0]}-{seeds[-1]}'}, resolutions {', '.join(resolutions)}, "
          f"skins {', '.join(cuts)}, landmarks {'given' if args.given_landmarks else 'located'}", flush=True)
    records: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="faceplan-heldout-") as tmp:
        root = Path(tmp)
        os.environ["XDG_CACHE_HOME"] = str(root / "cache")   # registrations of this run only
        for res in resolutions:
            for seed, cut in [(s, c) for s in seeds for c in cuts]:
                rec = run_case(seed, res, root, landmarks=args.given_landmarks, cut=cut)
                records.append(rec)
                if rec["ok"]:
                    lm = rec["landmark_error_mm"]
                    worst = max(lm, key=lm.get)
                    print(f"  {res} {cut} seed {seed}: ok, Newton {rec['newton_iterations']} its "
                          f"({rec['load_steps']} steps, {rec['cutbacks']} cut-backs), min SJ reg "
                          f"{rec['registered_min_sj']:.3f} / pred {rec['predicted_min_sj']:.3f}, "
                          f"landmarks max {lm[worst]:.2f} mm ({worst}), registration "
                          f"{rec['times_s']['registration']:.1f} s, predict {rec['times_s']['predict']:.1f} s",
                          flush=True)
                else:
                    print(f"  {res} {cut} seed {seed}: FAILED in {rec['failed_in']}: {rec['error']}", flush=True)
                if args.json:  # every record so far (a long run can be read while it goes on)
                    Path(args.json).write_text(json.dumps(records, indent=1, default=float))
    lines = [summarise(records, res, c) for res in resolutions for c in cuts]
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print()
    for ln in lines:
        print(ln)
    print(f"peak_mb={peak_mb:.0f}")
    if args.json:
        Path(args.json).write_text(json.dumps(records, indent=1, default=float))
    return 0 if all(r["ok"] for r in records) else 1


if __name__ == "__main__":
    sys.exit(main())
