"""Benchmark: how much each sim-to-real effect changes the predicted skin, region by region.

For `--count` synthetic patients (`faceplan synth` heads and their sample bimaxillary plans;
seeds from `--seed`), the generic face of `--resolution` is registered onto the head and the
plan predicted without and with each effect at a mid-range value (`EFFECTS`); the skin change
(node displacement difference on the skin) is summarised per region as RMS and max over the
patients' skin nodes, next to the scan noise (0.2 mm, `faceplan synth`). An effect whose
change stays below the noise in a region cannot be seen there. A row of `REFERENCE` is
measured against another row's prediction (the head pitch against the level upright head);
the mandible's execution error carries the chin segment (`facemodel.effects.executed_motions`). Also prints the time of one
`skin_sensitivities` call for every continuous parameter. Prints one table; lip contact is
off unless `--contact` (the coarse face with contact takes minutes per solve).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import numpy as np  # noqa: E402

# mid-range values (docs/effects.md gives the ranges): posture supine -> upright, and the
# upright head pitched 10 deg chin down; a peak swelling of 2 (residual 14 % at 6 months:
# growth 1.14 at the scan); the maxilla, or the mandible carrying the chin segment, 1.25 mm and
# 2 deg off; a light resting tone; the lips and chin sliding; one layer softer / stiffer
EFFECTS = {
    "gravity": ["gravity=1"],
    "gravity, pitch +10 deg": ["gravity=1", "gravity.pitch=10"],
    "pitch +10 deg vs pitch 0": ["gravity=1", "gravity.pitch=10"],
    "swelling": ["swelling=2"],
    "bone_execution": ["bone_execution.maxilla=[0.72, 0.72, 0.72, 2, 0, 0]"],
    "bone_execution.mandible+chin": ["bone_execution.mandible=[0.72, 0.72, 0.72, 2, 0, 0]"],
    "muscle_tone": ["muscle_tone=0.1"],
    "sliding": ["sliding=1"],
    "stiffness.hypodermis=0.6": ["stiffness.hypodermis=0.6"],
    "stiffness.dermis=2": ["stiffness.dermis=2"],
    "stiffness=2 (uniform)": ["stiffness=2"],
}
# rows measured against another row's prediction instead of the baseline: the pitch's own
# share of the posture change
REFERENCE = {"pitch +10 deg vs pitch 0": "gravity"}
REGIONS = ("upper_lip", "lower_lip", "chin", "nose", "cheek_left", "cheek_right", "submental")
NOISE_MM = 0.2
FOLLOW_UP = 6.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=5, help="synthetic patients (default 5)")
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--resolution", default="coarse", choices=("coarse", "standard", "fine"))
    parser.add_argument("--contact", action="store_true", help="lip contact on")
    parser.add_argument("--rows", default=None, metavar="TEXT[,TEXT]",
                        help="only the rows whose name contains one of these (default: all)")
    args = parser.parse_args()
    rows = [k for k in EFFECTS if args.rows is None or any(t in k for t in args.rows.split(","))]
    effects = {k: EFFECTS[k] for k in EFFECTS
               if k in rows or any(REFERENCE.get(r) == k for r in rows)}

    from facemodel.synthetic import synthetic_head
    from planner.case import load_case
    from planner.commands.synth import write_case
    from planner.pipeline import (Progress, effect_parameter_names, register_case, skin_sensitivities,
                                  skin_surface, solve_plan)
    from planner.plan import load_plan

    changes = {k: {r: [] for r in REGIONS + ("all",)} for k in effects}
    times = []
    with tempfile.TemporaryDirectory(prefix="faceplan-bench-effects-") as tmp:
        for i in range(args.count):
            seed = args.seed + i
            folder = Path(tmp) / f"synth_{seed}"
            folder.mkdir()
            write_case(folder, synthetic_head(seed), follow_up_months=FOLLOW_UP)
            case = load_case(folder)
            plan = load_plan(folder / "plan.yaml")
            plan = dataclasses.replace(plan, model=dataclasses.replace(plan.model, contact=args.contact))
            patient, _ = register_case(case, args.resolution, Progress(echo=False))
            base = solve_plan(patient, plan, case.bones, follow_up_months=FOLLOW_UP)
            _, _, ids = skin_surface(base.model)
            t0 = time.perf_counter()
            names = effect_parameter_names(base)
            skin_sensitivities(base, names)
            times.append((time.perf_counter() - t0, len(names)))
            preds = {}
            for key, eff in effects.items():
                same = next((k for k in preds if effects[k] == eff), None)
                preds[key] = preds[same] if same else solve_plan(patient, plan, case.bones, effects=eff,
                                                                 follow_up_months=FOLLOW_UP)
                ref = preds[REFERENCE[key]] if key in REFERENCE else base
                d = np.linalg.norm(preds[key].displacement[ids] - ref.displacement[ids], axis=1)
                changes[key]["all"].append(d)
                for r in REGIONS:
                    mask = np.isin(ids, np.asarray(base.model.regions.get(r, ()), np.int64))
                    changes[key][r].append(d[mask])
            print(f"patient {seed} done", file=sys.stderr, flush=True)
    cols = REGIONS + ("all",)
    print(f"skin change RMS / max (mm) per region, {args.count} patients, {args.resolution} face, "
          f"contact {'on' if args.contact else 'off'}; scan noise {NOISE_MM} mm; * = RMS above the noise")
    print(f"{'effect':28s}" + "".join(f"{c:>16s}" for c in cols))
    for key in rows:
        row = f"{key:28s}"
        for c in cols:
            d = np.concatenate(changes[key][c]) if changes[key][c] else np.zeros(0)
            if not len(d):
                row += f"{'-':>16s}"
                continue
            rms = float(np.sqrt(np.mean(d * d)))
            row += f"{rms:7.2f} /{d.max():5.2f}{'*' if rms > NOISE_MM else ' ':1s} "
        print(row)
    t = np.array([a for a, _ in times])
    print(f"skin_sensitivities for all {times[0][1]} continuous parameters: mean {t.mean():.1f} s, "
          f"max {t.max():.1f} s per patient")
    return 0


if __name__ == "__main__":
    sys.exit(main())
