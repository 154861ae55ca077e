"""Benchmark: `faceplan diagnose` on a blind cohort of withheld-effect cases (issue 20).

The cohort comes from seeds used nowhere else (default 9101...): `--random` cases with a random
withheld effect and `--none` cases without any, written by `faceplan synth --withheld-effect
random|none --key KEY` (its perturbed generic model, scan-like surfaces). When this build's
`synth` cannot write post-op scans, the same is made here: `faceplan synth` writes the case
folders and `planner.diagnosis.synthetic` the scans (the registered model perturbed: moduli
+-15 %, bulk modulus 500-2000 x shear, layer thickness +-20 %; effect values drawn from the
ranges of issue 19). Each case is then diagnosed on its own (every effect the model can add)
with its solves on one dask LocalCluster, and the figures are printed: the confusion matrix
(withheld effect against verdict), the shrinkage table (baseline RMS gap, held-out RMS with the
named effect, held-out shrinkage), the fitted values of identifiable parameters against the key,
and the times. Targets: withheld effect named in >= 10 of 12, `none` -> null in >= 3 of 4,
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

from planner.cli import main  # noqa: E402

SEED_BASE = 9101


def _draw(rng, moved: tuple[str, ...]) -> tuple[str, dict]:
    """A random effect and value (issue 19's ranges) for the fallback scans."""
    name = str(rng.choice(["sliding", "muscle_tone", "swelling", "gravity", "stiffness", "bone_execution"]))
    if name == "sliding":
        return name, {"sliding": 1}
    if name == "muscle_tone":
        return name, {"muscle_tone": round(float(rng.uniform(0.1, 0.3)), 3)}
    if name == "swelling":
        return name, {"swelling": round(float(rng.uniform(1.1, 1.3)), 3)}
    if name == "gravity":
        return name, {"gravity": round(float(rng.uniform(0.8, 1.4)), 3)}
    if name == "stiffness":
        layer = str(rng.choice(["dermis", "hypodermis", "muscle"]))
        f = rng.uniform(0.5, 0.7) if rng.random() < 0.5 else rng.uniform(1.5, 2.5)
        return name, {f"stiffness.{layer}": round(float(f), 3)}
    seg = str(rng.choice(list(moved)))
    t = rng.normal(size=3)
    t *= rng.uniform(0.5, 2.0) / np.linalg.norm(t)
    r = rng.normal(size=3)
    r *= rng.uniform(1.0, 3.0) / np.linalg.norm(r)
    return name, {f"bone_execution.{seg}": [round(float(x), 3) for x in (*t, *r)]}


def _fallback_scans(root: Path, folders: list[Path], kinds: list[str], seeds: list[int], resolution: str) -> list[dict]:
    import trimesh

    from planner.diagnosis.effects import effect_strings
    from planner.diagnosis.forward import solve_skin
    from planner.diagnosis.run import load_diagnosis_case
    from planner.diagnosis.synthetic import perturbed_case, scan_like

    key = []
    for folder, kind, seed in zip(folders, kinds, seeds):
        rng = np.random.default_rng(seed)
        (folder / "postop").mkdir(exist_ok=True)
        # a placeholder scan lets the case load; it is replaced below
        (folder / "postop" / "skin.stl").write_bytes((folder / "preop" / "skin.stl").read_bytes())
        patient, _, _ = load_diagnosis_case(folder, resolution, lambda s: None)
        name, value = (None, {}) if kind == "none" else _draw(rng, patient.moved_segments)
        truth = perturbed_case(patient, seed)
        skin = solve_skin(truth, effect_strings(value))
        if isinstance(skin, str):
            print(f"{folder.name}: the truth could not be solved ({skin}); case left out", file=sys.stderr)
            continue
        v, f = scan_like(skin, patient.skin_faces, seed=seed)
        trimesh.Trimesh(v, f, process=False).export(folder / "postop" / "skin.stl")
        key.append({"case": str(folder), "seed": seed, "effect": name, "value": value,
                    "perturbation": "planner.diagnosis.synthetic.perturbed_case", "plan_actual": False})
    return key


def make_cohort(root: Path, n_random: int, n_none: int, seed: int, resolution: str,
                truth_resolution: str, workers: int) -> list[dict]:
    """Case folders with post-op scans and their key (the synth command when it can). A cohort
    already in `root` (from an earlier run with --keep) is read back instead of made again."""
    done = root / "key.json"
    if done.exists():
        return json.loads(done.read_text())
    key = []
    folders, kinds, seeds = [], [], []
    for kind, count, s0 in (("random", n_random, seed), ("none", n_none, seed + 500)):
        if count == 0:
            continue
        out = root / kind
        keyfile = root / f"key_{kind}.json"
        code = main(["synth", "--out", str(out), "--count", str(count), "--seed", str(s0),
                     "--withheld-effect", kind, "--key", str(keyfile), "--truth-resolution", truth_resolution,
                     "--workers", str(max(workers, 1))])
        if code == 0 and keyfile.exists() and all((d / "postop" / "skin.stl").exists()
                                                   for d in sorted(out.iterdir()) if d.is_dir()):
            recs = json.loads(keyfile.read_text())
            for r in recs:
                r["case"] = str(out / r["case"])
            key += recs
            continue
        if code != 0:
            main(["synth", "--out", str(out), "--count", str(count), "--seed", str(s0)])
        cases = sorted(d for d in out.iterdir() if d.is_dir())
        folders += cases
        kinds += [kind] * len(cases)
        seeds += [s0 + i for i in range(len(cases))]
    if folders:
        print("this build's synth writes no post-op scans: scans made by planner.diagnosis.synthetic",
              file=sys.stderr)
        key += _fallback_scans(root, folders, kinds, seeds, resolution)
    done.write_text(json.dumps(key, indent=1))
    return key


class _StoredForward:
    """A `Forward` whose solves are also kept on disk by (case folder, resolution, request), so
    that a second run over the same cohort (--keep) repeats no solve; the record's solve count
    and times are then those of the solves actually run."""

    def __new__(cls, cases, runner, say, folder: Path, tag: str):
        import hashlib
        import pickle

        from planner.diagnosis.forward import Forward

        class Stored(Forward):
            def _file(self, r):
                h = hashlib.sha1(repr((tag, r[1])).encode()).hexdigest()[:20]
                return folder / f"{h}.pkl"

            def solve(self, requests):
                for r in requests:
                    if self._key(r) not in self._store and self._file(r).exists():
                        self._store[self._key(r)] = pickle.loads(self._file(r).read_bytes())
                out = super().solve(requests)
                for r, skin in zip(requests, out):
                    if not self._file(r).exists():
                        self._file(r).write_bytes(pickle.dumps(skin))
                return out

        folder.mkdir(parents=True, exist_ok=True)
        return Stored(cases, runner, say)


def _relative_errors(fitted: dict, value: dict) -> list[float]:
    """|fitted - key| / |key - none| per identifiable value (factors: none = 1); a bone
    correction's translation and rotation each as a vector norm."""
    out = []
    for k, v in (value or {}).items():
        if k not in fitted or k == "sliding":
            continue
        if isinstance(v, list):
            f, t = np.asarray(fitted[k], float), np.asarray(v, float)
            for sl in (slice(0, 3), slice(3, 6)):
                out.append(float(np.linalg.norm(f[sl] - t[sl]) / max(np.linalg.norm(t[sl]), 1e-9)))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            none = 1.0 if k.startswith(("stiffness", "swelling")) else 0.0
            out.append(abs(float(fitted[k]) - float(v)) / max(abs(float(v) - none), 1e-9))
    return out


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
                    "(a second run over DIR reuses the cohort and every solve)")
    ap.add_argument("--verbose", action="store_true", help="the diagnosis's progress on stderr")
    args = ap.parse_args(argv)

    from planner.diagnosis.forward import Runner
    from planner.diagnosis.run import diagnose_data, load_diagnosis_case

    t_all = time.perf_counter()
    tmp = None if args.keep else tempfile.TemporaryDirectory(prefix="faceplan-bench-diagnosis-")
    root = Path(args.keep or tmp.name)
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    finer = {"coarse": "standard", "standard": "fine", "fine": "fine"}
    key = make_cohort(root, args.random, args.none, args.seed, args.resolution,
                      args.truth_resolution or finer[args.resolution], args.workers)
    t_cohort = time.perf_counter() - t0
    client, closing = None, []
    if args.workers > 0:
        import logging

        from distributed import Client, LocalCluster

        cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                               dashboard_address=":0", silence_logs=logging.ERROR)
        client = Client(cluster)
        closing = [client, cluster]
    rows = []
    try:
        for rec in key:
            t = time.perf_counter()
            say = (lambda m: print(m, file=sys.stderr, flush=True)) if args.verbose else (lambda m: None)
            patient, scan, res = load_diagnosis_case(Path(rec["case"]), args.resolution, say)
            fwd = _StoredForward([patient], Runner(client), say, root / "solves",
                                 f"{Path(rec['case']).resolve()}|{res}")
            out = diagnose_data([patient], [scan], forward=fwd, say=say)
            d = out["record"]
            if args.keep:
                (Path(rec["case"]) / "diagnosis.json").write_text(json.dumps(d, indent=1, default=str))
            v = d["verdict"]
            fitted = next((e["params"] for e in d["effects"] if e["name"] == v["effect"]), {})
            shrink = d.get("shrinkage") or {}
            rows.append({"case": Path(rec["case"]).name, "truth": rec["effect"], "value": rec["value"],
                         "verdict": v["effect"], "confidence": v["confidence"],
                         "rms0": d["method"]["baseline_rms_mm"],
                         "heldout_after": (shrink.get("overall") or {}).get("heldout_after_mm"),
                         "heldout_shrink": (shrink.get("overall") or {}).get("heldout_shrink_pct"),
                         "attributable": (shrink.get("overall") or {}).get("attributable_shrink_pct"),
                         "level": (shrink.get("overall") or {}).get("error_level_mm"),
                         "discrepancy0": d["error_model"]["discrepancy_mm"],
                         "effects": [(e["name"], e["heldout_shrink_pct"],
                                      None if e["bic"] is None else round(d["method"]["baseline_bic"] - e["bic"], 1),
                                      e["significant"]) for e in d["effects"]],
                         "fitted": fitted, "time_s": time.perf_counter() - t,
                         "solves": d["solves"]["count"], "sensitivity": d["method"]["sensitivity"]})
            r = rows[-1]
            print(f"{r['case']}: withheld {r['truth']} {json.dumps(r['value'])} -> {r['verdict']} "
                  f"(confidence {r['confidence']:.2f}); RMS gap {r['rms0']:.2f} mm, held-out shrink "
                  f"{r['heldout_shrink']}% (attributable {r['attributable']}%); discrepancy "
                  f"{r['discrepancy0']} mm; fitted {json.dumps(fitted)}; {r['solves']} solves, "
                  f"{r['time_s']:.0f} s", flush=True)
            print("    held-out %, BIC gain: " + "; ".join(f"{n} {h}% {b}{' *' if sig else ''}"
                                                         for n, h, b, sig in r["effects"]),
                  flush=True)
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
    print(f"{'case':<12}{'withheld':<16}{'verdict':<16}{'conf':>6}{'RMS0 mm':>9}{'held-out mm':>12}"
          f"{'total %':>9}{'e mm':>7}{'attrib %':>9}")

    def _f(x, w, d=1):
        return f"{x:>{w}.{d}f}" if isinstance(x, (int, float)) else f"{'-':>{w}}"

    for r in rows:
        print(f"{r['case']:<12}{str(r['truth']):<16}{str(r['verdict']):<16}{_f(r['confidence'], 6, 2)}"
              f"{_f(r['rms0'], 9, 3)}{_f(r['heldout_after'], 12, 3)}{_f(r['heldout_shrink'], 9)}"
              f"{_f(r['level'], 7, 2)}{_f(r['attributable'], 9)}")
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
    times = [r["time_s"] for r in rows]
    print(f"cohort made in {t_cohort:.0f} s; diagnosis per case median {np.median(times) if times else 0:.0f} s, "
          f"max {max(times) if times else 0:.0f} s; total {time.perf_counter() - t_all:.0f} s on "
          f"{max(args.workers, 1)} worker(s), resolution {args.resolution}")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main_bench())
