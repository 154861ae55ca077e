"""Benchmark: `faceplan diagnose` on a blind cohort of withheld-effect cases (issue 20).

The cohort comes from seeds used nowhere else (default 9901..., the `none` cases from the seed +
500; seeds already taken by reported runs: 9101-9103, 9201-9202, 9501-9510, 9601, 9701,
9801-9804, 10001-10003, 10301-10302 and the cohorts of docs/diagnosis.md, 10401-18206, each
with its `none` seeds): `--random` cases with a random
withheld effect and `--none` cases without any, written by `faceplan synth --withheld-effect
random|none --key KEY` (its perturbed generic model on a finer mesh, scan-like surfaces), one
synth per seed, `--workers` at a time; a seed whose truth cannot be solved is reported and left
out. Each case is then diagnosed on its own (every effect the model can add) with its solves on
one dask LocalCluster, and the figures are printed: the confusion matrix (withheld effect
against verdict), the shrinkage table (baseline RMS gap, held-out RMS with the named effect,
held-out shrinkage of the whole gap and of the gap beyond noise + discrepancy), the fitted
values of identifiable parameters against the key, and the times. Targets: withheld effect named in >= 10 of 12, `none` -> null in >= 3 of 4,
held-out shrinkage >= 50 % with the named effect, identifiable values within 25 % of the key;
one case with six effects at standard resolution in <= 3 min.

    python bench/diagnosis.py                      # 3 random + 1 none, coarse (a short run)
    python bench/diagnosis.py --random 12 --none 4 --resolution standard --workers 2   # full
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facemodel.effects import BONE_DOF  # noqa: E402

SEED_BASE = 9901


def _synth_one(root: Path, kind: str, seed: int, truth_resolution: str, max_minutes: float | None = None,
               neck: str = "free", family: str = "own", floor: str = "free", scanner: str = "frontal"):
    """A subprocess writing one case with `faceplan synth` (its own folder and key), its truth
    solves within `max_minutes` (`--case-max-minutes`)."""
    import os
    import subprocess

    out = root / kind / str(seed)
    cmd = [sys.executable, "-m", "planner.cli", "synth", "--out", str(out), "--count", "1", "--seed", str(seed),
           "--withheld-effect", kind, "--key", str(root / kind / f"key_{seed}.json"),
           "--truth-resolution", truth_resolution, "--workers", "1", "--truth-neck", neck,
           "--truth-floor", floor, "--scanner", scanner,
           "--head-family", family, "--solve-log", str(root / kind / "solve_logs")]
    if max_minutes:
        cmd += ["--case-max-minutes", str(max_minutes)]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]) + os.pathsep
               + os.environ.get("PYTHONPATH", ""))
    log = open(root / kind / f"synth_{seed}.log", "w")
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)


def make_cohort(root: Path, n_random: int, n_none: int, seed: int, resolution: str,
                truth_resolution: str, workers: int, skip: tuple[int, ...] = (), make: bool = True,
                max_minutes: float | None = None, neck: str = "free", family: str = "own",
                floor: str = "free", scanner: str = "frontal") -> list[dict]:
    """Case folders with post-op scans and their key, one `faceplan synth` per seed (`workers`
    at a time). A seed whose truth cannot be solved, or whose synth runs longer than
    `max_minutes` (a plan whose solve creeps at a limit point of the lips), is reported and
    left out (its verdict would say nothing about the diagnosis). Cases already in `root` (an
    earlier run with --keep) are read back instead of made again."""
    jobs = []
    for kind, count, s0 in (("random", n_random, seed), ("none", n_none, seed + 500)):
        (root / kind).mkdir(parents=True, exist_ok=True)
        jobs += [(kind, s) for s in range(s0, s0 + count) if s not in skip]
    running: list = []
    todo = [j for j in jobs if not (root / j[0] / f"key_{j[1]}.json").exists()] if make else []
    while todo or running:
        while todo and len(running) < max(workers, 1):
            kind, s = todo.pop(0)
            running.append((kind, s, _synth_one(root, kind, s, truth_resolution, max_minutes, neck, family, floor,
                                                    scanner),
                            time.perf_counter()))
        time.sleep(2.0)
        for job in list(running):
            # synth ends such a case itself (`--case-max-minutes`); the kill is the backstop
            # for a stage outside the solves' budget
            if job[2].poll() is None and max_minutes and time.perf_counter() - job[3] > 60.0 * max_minutes + 120.0:
                job[2].kill()
                job[2].wait()
                print(f"synth {job[0]} seed {job[1]}: stopped after {max_minutes:g} + 2 min "
                      "(--synth-max-minutes); left out", file=sys.stderr, flush=True)
                running.remove(job)
                continue
            if job[2].poll() is not None:
                running.remove(job)
                print(f"synth {job[0]} seed {job[1]}: exit {job[2].returncode}", file=sys.stderr, flush=True)
    key = []
    for kind, s in jobs:
        kf = root / kind / f"key_{s}.json"
        if not kf.exists() and not make:
            print(f"seed {s} ({kind}): not made yet; left out of this run", file=sys.stderr)
            continue
        if not kf.exists():
            print(f"seed {s} ({kind}): faceplan synth could not make the case (see {kind}/synth_{s}.log and "
                  f"{kind}/solve_logs/synth_{s:04d}.log); "
                  "left out", file=sys.stderr)
            continue
        for r in json.loads(kf.read_text()):
            r["case"] = str(root / kind / str(s) / r["case"])
            key.append(r)
    return key


# the code a stored solve depends on: the mesh, the registration, the model and its effects,
# the solver, and the steps from a plan to a solve; a change there makes every solve afresh
SOLVE_CODE = ("solver", "facemodel", "generic_mesh", "registration", "planner/pipeline.py",
              "planner/segments.py", "planner/plan.py", "planner/diagnosis/forward.py")


def _solve_code_digest(root: Path = Path(__file__).resolve().parents[1]) -> str:
    """SHA-1 over the Python sources of `SOLVE_CODE` (paths and contents, in sorted order)."""
    import hashlib

    h = hashlib.sha1()
    for part in SOLVE_CODE:
        p = root / part
        for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
            h.update(str(f.relative_to(root)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()


class _StoredForward:
    """A `Forward` whose solves are also kept on disk by (case folder, resolution, request, the
    digest of the code a solve depends on), so that a second run over the same cohort (--keep)
    repeats no solve while the model and solver are the same; the record's solve count and
    times are then those of the solves actually run."""

    def __new__(cls, cases, runner, say, folder: Path, tag: str):
        import hashlib
        import pickle

        from planner.diagnosis.forward import Forward

        code = _solve_code_digest()

        class Stored(Forward):
            def _file(self, r):
                h = hashlib.sha1(repr((tag, code, r[1])).encode()).hexdigest()[:20]
                return folder / f"{h}.pkl"

            def _load(self, requests):
                for r in requests:
                    if self._key(r) not in self._store and self._file(r).exists():
                        self._store[self._key(r)] = pickle.loads(self._file(r).read_bytes())

            def prefetch(self, requests):
                self._load(requests)
                super().prefetch(requests)

            def solve(self, requests):
                self._load(requests)
                out = super().solve(requests)
                for r, skin in zip(requests, out):
                    if not self._file(r).exists():
                        self._file(r).write_bytes(pickle.dumps(skin))
                return out

        folder.mkdir(parents=True, exist_ok=True)
        return Stored(cases, runner, say)


def _none(key: str) -> float:
    """The value of a scalar effect parameter that means "none": 1 for the factors (stiffness,
    swelling's growth ratio), 0 for the others."""
    return 1.0 if key.startswith(("stiffness", "swelling")) else 0.0


def _relative_errors(fitted: dict, value: dict) -> list[float]:
    """|fitted - key| / |key - none| per identifiable value (factors: none = 1); a bone
    correction's translation and rotation each as a vector norm. When the diagnosis used the
    achieved movements of `postop/plan_actual.yaml` (`bone_execution: 1`), which hold the key's
    correction, its fitted correction is what remains on top of them: the truth is zero there,
    and the error is that remainder against the key."""
    out = []
    achieved = fitted.get("bone_execution") == 1
    for k, v in (value or {}).items():
        if k not in fitted or k == "sliding":
            continue
        if isinstance(v, list):
            f, t = np.asarray(fitted[k], float), np.asarray(v, float)
            if achieved:
                f = f + t
            for sl in (slice(0, 3), slice(3, 6)):
                out.append(float(np.linalg.norm(f[sl] - t[sl]) / max(np.linalg.norm(t[sl]), 1e-9)))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out.append(abs(float(fitted[k]) - float(v)) / max(abs(float(v) - _none(k)), 1e-9))
    return out


def _interval_hits(r: dict, field: str = "intervals") -> list[bool]:
    """Per identifiable parameter of the named effect: does its 95 % interval under noise +
    discrepancy (`parameters.<key>.interval_95`; `field` "intervals_marginal": with the layer
    moduli integrated out, `interval_95_marginal`) hold the key's value? A parameter the key
    does not set has its "none" value as truth (a segment the key did not move: no correction;
    factors 1); with the achieved movements of `postop/plan_actual.yaml` in the fit
    (`bone_execution: 1`), which hold the key's correction, the truth of what remains is 0."""
    value = r.get("value") or {}
    achieved = (r.get("fitted") or {}).get("bone_execution") == 1
    hits = []
    for k, (lo, hi) in (r.get(field) or {}).items():
        head, _, comp = k.rpartition(".")
        if comp in BONE_DOF and head.startswith("bone_execution."):
            vec = value.get(head)
            truth = 0.0 if achieved or vec is None else float(vec[BONE_DOF.index(comp)])
        else:
            truth = float(value[k]) if isinstance(value.get(k), (int, float)) else _none(k)
        hits.append(bool(lo - 1e-9 <= truth <= hi + 1e-9))
    return hits


def _ceiling(r: dict):
    """The largest whole-gap shrinkage the scan noise allows: 1 - noise / RMS0 (percent)."""
    if not isinstance(r.get("noise"), (int, float)) or not r.get("rms0"):
        return None
    return 100.0 * (1.0 - min(r["noise"] / r["rms0"], 1.0))


def _print_row(r: dict) -> None:
    print(f"{r['case']}: withheld {r['truth']} {json.dumps(r['value'])} -> {r['verdict']} "
          f"(confidence {r['confidence']:.2f}"
          + (f"; supported, not named: {', '.join(r['supported'])}" if r.get("supported") else "")
          + (f"; a surface cannot tell it from: {', '.join(r['confounded'])}" if r.get("confounded") else "")
          + f"); RMS gap {r['rms0']:.2f} mm, held-out shrink "
          f"{r['heldout_shrink']}% (attributable {r['attributable']}%); discrepancy "
          f"{r['discrepancy0']} mm; fitted {json.dumps(r['fitted'])}"
          + (f" (on the response extrapolated to the converged mesh, kappa {r['kappa']})" if r.get("kappa") else "")
          + f"; {r['solves']} solves, "
          f"{r['time_s']:.0f} s", flush=True)
    # (rows stored before the gain's probability was recorded have six fields)
    print("    held-out %, BIC gain, held-out log density gain (P > 0): "
          + "; ".join(f"{e[0]} {e[1]}% {e[2]} {e[3]}±{e[4]}" + (f" ({e[6]})" if len(e) > 6 else "")
                      + (" *" if e[5] else "") for e in r["effects"]),
          flush=True)


def _effect_change(rec: dict):
    """The withheld effect's own RMS change (mm) of the skin the scan sees, from its key record
    (None for a case without an effect): a miss is read against the noise floor, and a change
    below it is not there to be found."""
    return (rec.get("effect_skin_change_mm") or {}).get("rms_mm") if rec.get("effect") else None


def main_bench(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--random", type=int, default=3, help="random-effect cases (issue target: 12)")
    ap.add_argument("--none", type=int, default=1, help="cases without an effect (issue target: 4)")
    ap.add_argument("--seed", type=int, default=SEED_BASE, help="first seed (used nowhere else)")
    ap.add_argument("--resolution", default="coarse", choices=("coarse", "standard", "fine"))
    ap.add_argument("--truth-resolution", choices=("coarse", "standard", "fine"),
                    help="mesh of the synthetic truths (default: one finer than --resolution)")
    ap.add_argument("--workers", type=int, default=2, help="LocalCluster workers (0: in process)")
    ap.add_argument("--keep", metavar="DIR", help="keep the cohort, its solves and the diagnoses in DIR "
                    "(a second run over DIR reuses the cohort, and every solve while the code of "
                    "the model and solver, SOLVE_CODE, is unchanged)")
    ap.add_argument("--verbose", action="store_true", help="the diagnosis's progress on stderr")
    ap.add_argument("--make-only", action="store_true", help="only make the cohort (with --keep: diagnose "
                    "it later)")
    ap.add_argument("--no-make", action="store_true", help="with --keep: diagnose only the cases DIR already "
                    "holds (another run, e.g. with --make-only, is making the others)")
    ap.add_argument("--resume", action="store_true", help="with --keep: a case whose figures a previous run "
                    "over DIR stored (bench_row.json beside its diagnosis.json) is read back, not diagnosed again")
    ap.add_argument("--mesh-reference", default="auto", choices=("auto", "none", "coarse", "standard", "fine"),
                    help="second mesh whose baseline estimates the model mesh's discretisation error "
                         "(as faceplan diagnose --mesh-reference; default auto: the next coarser, none at coarse)")
    ap.add_argument("--synth-max-minutes", type=float, default=None,
                    help="each case's faceplan synth gets this many minutes for its truth solves "
                         "(its --case-max-minutes; a case over it fails and its seed is left out); "
                         "default: no limit")
    ap.add_argument("--truth-neck", default="free", choices=("free", "held", "random"),
                    help="the truths' neck cut (faceplan synth --truth-neck; held: a boundary condition "
                         "the diagnosis's model does not share)")
    ap.add_argument("--truth-floor", default="free", choices=("free", "held", "random"),
                    help="the truths' floor of the mouth (faceplan synth --truth-floor; held: a boundary "
                         "condition the diagnosis's model does not share)")
    ap.add_argument("--scanner", default="frontal", choices=("frontal", "wide"),
                    help="the post-op scans' scanner (faceplan synth --scanner; wide: ear to ear and "
                         "under the chin)")
    ap.add_argument("--head-family", default="own", choices=("own", "alt"),
                    help="the heads' generator (faceplan synth --head-family; alt: a second, "
                         "differently built family without teeth, anatomy the method was not made on)")
    ap.add_argument("--boundary-uncertainty", default="neck", metavar="neck[,floor]|none",
                    help="as faceplan diagnose --boundary-uncertainty")
    ap.add_argument("--layer-uncertainty", default="none", choices=("thicker", "none"),
                    help="as faceplan diagnose --layer-uncertainty")
    ap.add_argument("--skip-seeds", default="", help="comma-separated seeds whose truth synth cannot solve "
                    "(left out, and said so)")
    args = ap.parse_args(argv)

    from planner.diagnosis.forward import Runner
    from planner.diagnosis.run import diagnose_data, load_diagnosis_case, mesh_reference, parse_boundaries

    boundaries = parse_boundaries(args.boundary_uncertainty)

    t_all = time.perf_counter()
    tmp = None if args.keep else tempfile.TemporaryDirectory(prefix="faceplan-bench-diagnosis-")
    root = Path(args.keep or tmp.name)
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    finer = {"coarse": "standard", "standard": "fine", "fine": "fine"}
    key = make_cohort(root, args.random, args.none, args.seed, args.resolution,
                      args.truth_resolution or finer[args.resolution], args.workers,
                      tuple(int(x) for x in args.skip_seeds.split(",") if x.strip()), make=not args.no_make,
                      max_minutes=args.synth_max_minutes, neck=args.truth_neck, family=args.head_family,
                      floor=args.truth_floor, scanner=args.scanner)
    if args.skip_seeds:
        print(f"seeds left out (their truth could not be solved by synth): {args.skip_seeds}", flush=True)
    t_cohort = time.perf_counter() - t0
    if args.make_only:
        print(f"cohort of {len(key)} case(s) in {root} made in {t_cohort:.0f} s", flush=True)
        return 0
    client, closing = None, []
    if args.workers > 0:
        import logging

        from distributed import Client, LocalCluster

        cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                               dashboard_address=":0", silence_logs=logging.ERROR)
        client = Client(cluster)
        closing = [client, cluster]
    from planner.errors import InputError, SolveError

    rows, not_diagnosed = [], []
    try:
        for rec in key:
            t = time.perf_counter()
            stored = Path(rec["case"]) / "bench_row.json"
            if args.resume and args.keep and stored.exists():
                rows.append(json.loads(stored.read_text()))
                # rows stored before the effect's skin change was recorded: from the key
                rows[-1].setdefault("change_rms", _effect_change(rec))
                # rows stored before the verdict's surface confounds were recorded: from its diagnosis
                stored_d = Path(rec["case"]) / "diagnosis.json"
                if "confounded" not in rows[-1] and stored_d.exists():
                    rows[-1]["confounded"] = json.loads(stored_d.read_text())["verdict"].get(
                        "confounded_on_surface") or []
                _print_row(rows[-1])
                continue
            say = (lambda m: print(m, file=sys.stderr, flush=True)) if args.verbose else (lambda m: None)
            try:
                patient, scan, res, ref = load_diagnosis_case(Path(rec["case"]), args.resolution, say,
                                                              args.mesh_reference)
            except (SolveError, InputError) as exc:
                # a case faceplan cannot register or load is a failure of the method on that
                # head, counted and named, not a reason to stop the cohort
                not_diagnosed.append((Path(rec["case"]).name, rec["effect"], str(exc)))
                print(f"{Path(rec['case']).name}: not diagnosed: {exc}", flush=True)
                continue
            fwd = _StoredForward([patient], Runner(client), say, root / "solves",
                                 f"{Path(rec['case']).resolve()}|{res}")
            ref_name = mesh_reference(res, args.mesh_reference)
            ref_fwd = None if ref is None else _StoredForward(
                [ref], Runner(client), say, root / "solves", f"{Path(rec['case']).resolve()}|{ref_name}")
            try:
                out = diagnose_data([patient], [scan], forward=fwd, say=say,
                                    references=None if ref is None else [ref], reference_names=[ref_name],
                                    reference_forward=ref_fwd, boundary=boundaries,
                                    layers=args.layer_uncertainty == "thicker")
            except (SolveError, InputError) as exc:
                # refused (the scan judged another patient's) or not solved: as above, a
                # failure on that case, counted and named
                not_diagnosed.append((Path(rec["case"]).name, rec["effect"], str(exc)))
                print(f"{Path(rec['case']).name}: not diagnosed: {exc}", flush=True)
                continue
            d = out["record"]
            if args.keep:
                (Path(rec["case"]) / "diagnosis.json").write_text(json.dumps(d, indent=1, default=str))
            v = d["verdict"]
            entry = next((e for e in d["effects"] if e["name"] == v["effect"]), {})
            fitted = entry.get("params", {})
            # the factor of the response's extrapolation to the converged mesh, where a second
            # mesh gave it (the fitted values are then the converged mesh's)
            kappa = entry.get("mesh_extrapolation_factor")
            shrink = d.get("shrinkage") or {}
            rows.append({"case": Path(rec["case"]).name, "truth": rec["effect"], "value": rec["value"],
                         "change_rms": _effect_change(rec),
                         "verdict": v["effect"], "confidence": v["confidence"],
                         "supported": v.get("supported_not_named") or [],
                         "confounded": v.get("confounded_on_surface") or [],
                         "rms0": d["method"]["baseline_rms_mm"],
                         "heldout_after": (shrink.get("overall") or {}).get("heldout_after_mm"),
                         "heldout_shrink": (shrink.get("overall") or {}).get("heldout_shrink_pct"),
                         "attributable": (shrink.get("overall") or {}).get("attributable_shrink_pct"),
                         "level": (shrink.get("overall") or {}).get("error_level_mm"),
                         "discrepancy0": d["error_model"]["discrepancy_mm"],
                         "noise": d["noise_floor_mm"],
                         "effects": [(e["name"], e["heldout_shrink_pct"],
                                      None if e["bic"] is None else round(d["method"]["baseline_bic"] - e["bic"], 1),
                                      e.get("heldout_lpd_gain"), e.get("heldout_lpd_gain_se"),
                                      e["significant"], e.get("heldout_lpd_gain_probability"))
                                     for e in d["effects"]],
                         "fitted": fitted, "kappa": kappa, "time_s": time.perf_counter() - t,
                         "intervals": {k: p["interval_95"] for k, p in (entry.get("parameters") or {}).items()
                                       if p.get("identifiable") and p.get("interval_95") is not None},
                         "intervals_marginal": {k: p["interval_95_marginal"]
                                                for k, p in (entry.get("parameters") or {}).items()
                                                if p.get("identifiable") and p.get("interval_95_marginal") is not None},
                         "solves": d["solves"]["count"], "sensitivity": d["method"]["sensitivity"]})
            if args.keep:
                stored.write_text(json.dumps(rows[-1], default=str))
            _print_row(rows[-1])
    finally:
        for obj in closing:
            obj.close()
    labels = sorted({str(r["truth"]) for r in rows} | {str(r["verdict"]) for r in rows})
    print("\nconfusion matrix (rows: withheld effect, columns: verdict)")
    print(" " * 16 + "".join(f"{c[:14]:>15}" for c in labels))
    for t in labels:
        if not any(str(r["truth"]) == t for r in rows):
            continue
        print(f"{t[:15]:<16}" + "".join(f"{sum(str(r['truth']) == t and str(r['verdict']) == c for r in rows):>15}"
                                        for c in labels))
    print("\nshrinkage table (held-out RMS gap with the named effect; total = of the whole gap, "
          "attributable = of the gap beyond noise + discrepancy, see diagnosis.json method.shrinkage)")
    print("(noise mm: the noise floor; ceiling %: 1 - noise / RMS0, the most the whole gap can shrink when the "
          "effect is found exactly, the scan noise staying)")
    print("(effect mm: the withheld effect's own RMS change of the skin the scan sees, from the key)")
    print(f"{'case':<12}{'withheld':<16}{'verdict':<16}{'conf':>6}{'RMS0 mm':>9}{'held-out mm':>12}"
          f"{'total %':>9}{'noise mm':>9}{'ceiling %':>10}{'e mm':>7}{'attrib %':>9}{'effect mm':>10}")

    def _f(x, w, d=1):
        return f"{x:>{w}.{d}f}" if isinstance(x, (int, float)) else f"{'-':>{w}}"

    for r in rows:
        print(f"{r['case']:<12}{str(r['truth']):<16}{str(r['verdict']):<16}{_f(r['confidence'], 6, 2)}"
              f"{_f(r['rms0'], 9, 3)}{_f(r['heldout_after'], 12, 3)}{_f(r['heldout_shrink'], 9)}"
              f"{_f(r.get('noise'), 9, 3)}{_f(_ceiling(r), 10)}{_f(r['level'], 7, 2)}{_f(r['attributable'], 9)}"
              f"{_f(r.get('change_rms'), 10, 3)}")
    effect_rows = [r for r in rows if r["truth"] is not None]
    none_rows = [r for r in rows if r["truth"] is None]
    named = sum(r["verdict"] == r["truth"] for r in effect_rows)
    nulls = sum(r["verdict"] is None for r in none_rows)
    shr = [r["heldout_shrink"] for r in effect_rows if r["verdict"] == r["truth"] and r["heldout_shrink"] is not None]
    att = [r["attributable"] for r in effect_rows if r["verdict"] == r["truth"] and r["attributable"] is not None]
    errs = [e for r in effect_rows if r["verdict"] == r["truth"] for e in _relative_errors(r["fitted"], r["value"])]
    print(f"\nnamed {named}/{len(effect_rows)} (target >= 10/12); none -> null {nulls}/{len(none_rows)} "
          f"(target >= 3/4); held-out shrinkage when named: median "
          f"{np.median(shr) if shr else float('nan'):.1f}% of the total gap, {np.median(att) if att else float('nan'):.1f}% "
          f"of the attributable gap (target >= 50%; >= 50 % in {sum(a >= 50 for a in att)}/{len(att)}); "
          f"perturbed model alone named with confidence > 0.5: "
          f"{sum(r['verdict'] not in (None, 'unexplained') and r['confidence'] > 0.5 for r in none_rows)}/{len(none_rows)}; "
          "fitted values within 25% of the key: "
          f"{sum(e <= 0.25 for e in errs)}/{len(errs)}")
    wrong = [r for r in effect_rows if r["verdict"] not in (r["truth"], None, "unexplained")]
    flagged = [r for r in effect_rows if r.get("confounded")]
    print(f"verdicts flagged as confounded on the surface (confounded_on_surface): {len(flagged)}, "
          f"{sum(r['verdict'] == r['truth'] for r in flagged)} of them right; wrong verdicts whose "
          f"withheld effect the flag names: {sum(r['truth'] in (r.get('confounded') or ()) for r in wrong)}"
          f"/{len(wrong)}")
    hits = [h for r in effect_rows if r["verdict"] == r["truth"] for h in _interval_hits(r)]
    with_iv = sum(1 for r in effect_rows if r["verdict"] == r["truth"] and r.get("intervals"))
    print(f"key values inside the fitted 95 % intervals (noise + discrepancy), named cases: {sum(hits)}/{len(hits)} "
          f"parameters over {with_iv} case(s) with intervals")
    named_rows = [r for r in effect_rows if r["verdict"] == r["truth"]]
    for label, bone in (("bone corrections", True), ("the other values", False)):
        def hits_of(field):
            return [h for r in named_rows for h in _interval_hits(
                dict(r, **{field: {k: v for k, v in (r.get(field) or {}).items()
                                   if k.startswith("bone_execution.") == bone}}), field)]
        at, marg = hits_of("intervals"), hits_of("intervals_marginal")
        print(f"  {label}: {sum(at)}/{len(at)} at the model's moduli, {sum(marg)}/{len(marg)} with the layer "
              "moduli unknown (interval_95_marginal)")
    faint = [r for r in effect_rows if isinstance(r.get("change_rms"), (int, float))
             and isinstance(r.get("noise"), (int, float)) and r["change_rms"] < r["noise"]]
    listed = ", ".join(f"{r['case']} {r['truth']}" for r in faint) or "none"
    print(f"withheld effects changing the seen skin by less than the noise floor (RMS): {len(faint)}/"
          f"{len(effect_rows)} ({listed}), named {sum(r['verdict'] == r['truth'] for r in faint)} of them")
    if not_diagnosed:
        print(f"not diagnosed (faceplan could not register, load, accept or solve the case): {len(not_diagnosed)}: "
              + "; ".join(f"{c} ({t}): {why}" for c, t, why in not_diagnosed))
    times = [r["time_s"] for r in rows]
    print(f"cohort made in {t_cohort:.0f} s; diagnosis per case median {np.median(times) if times else 0:.0f} s, "
          f"max {max(times) if times else 0:.0f} s, sum {sum(times):.0f} s (cases read back with --resume count "
          f"their first run); total {time.perf_counter() - t_all:.0f} s on "
          f"{max(args.workers, 1)} worker(s), resolution {args.resolution}")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main_bench())
