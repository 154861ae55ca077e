"""Benchmark: an effect's solve from the baseline solution against the same solve from rest.

For one synthetic patient (`--seed`, the case folder of `faceplan synth`: head, sample plan)
registered at `--resolution`, the baseline prediction is solved, then each effect of `--effects`
twice in the same process: stepping the load from rest (as without a guess) and from the
baseline's displacement at full load (`solver.newton.newton_solve(guess=...)`, what the
diagnosis's effect solves and `faceplan synth`'s truth with its effect do). Prints per effect
the time, Newton iterations and factorisations of both, whether the full load converged from
the baseline (else the load was stepped after the attempt), the ratio of times and the largest
difference of the two displacement fields, over all nodes and over the skin (the same
equilibrium within the solver's tolerance, or, where lip mucosa touches the teeth, another
contact state inside the mouth). The machine's load average is printed: seconds depend on it, counts do not.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

EFFECTS = ("gravity=1.2", "stiffness.hypodermis=0.6", "sliding=mandible",
           "bone_execution.mandible=[0.5,1.0,0.5,1.0,0.5,0.5]", "swelling=1.2", "muscle_tone=0.3")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--resolution", default="standard", choices=("coarse", "standard", "fine"))
    ap.add_argument("--effects", default=";".join(EFFECTS),
                    help="NAME=VALUE items separated by ';'")
    args = ap.parse_args()

    import numpy as np

    from facemodel.synthetic import synthetic_head
    from planner.case import load_case
    from planner.commands.synth import write_case
    from planner.errors import SolveError
    from planner.pipeline import Progress, parse_effects, register_case, skin_surface, solve_plan
    from planner.plan import load_plan

    print(f"load average {os.getloadavg()[0]:.1f} (2 cores)", flush=True)
    with tempfile.TemporaryDirectory(prefix="faceplan-bench-effects-") as tmp:
        folder = Path(tmp) / f"synth_{args.seed:04d}"
        folder.mkdir()
        write_case(folder, synthetic_head(args.seed))
        case = load_case(folder, cache=False)
        plan = load_plan(folder / "plan.yaml")
        patient, _ = register_case(case, args.resolution, Progress(echo=False))
        t = time.perf_counter()
        base = solve_plan(patient, plan, case.bones)
        print(f"baseline ({args.resolution}, {len(patient.nodes)} nodes): {time.perf_counter() - t:.1f} s, "
              f"{base.solver['iterations']} Newton iterations", flush=True)
        skin = skin_surface(base.model)[2]
        ratios = []
        for item in [e.strip() for e in args.effects.split(";") if e.strip()]:
            runs = []
            for guess in (None, base.displacement):
                t = time.perf_counter()
                try:
                    p = solve_plan(patient, plan, case.bones, effects=parse_effects([item]), guess=guess)
                except SolveError as exc:
                    runs.append((time.perf_counter() - t, None, None, None, f"failed: {exc}"[:160]))
                    continue
                info = p.solver.get("info", {})
                runs.append((time.perf_counter() - t, p.solver["iterations"], info.get("factorizations"),
                             p.displacement, (info.get("guess") or {}).get("converged")))
            (t0, i0, f0, u0, how0), (t1, i1, f1, u1, how1) = runs

            def said(how):
                if isinstance(how, str):
                    return how
                return "converged at full load" if how else "load stepped after the attempt"

            if u0 is None or u1 is None:
                print(f"  {item:48s} from rest {t0:6.1f} s ({how0 if u0 is None else 'solved'}) | from the "
                      f"baseline {t1:6.1f} s ({said(how1) if u1 is not None else how1})", flush=True)
                continue
            ratios.append(t0 / t1)
            print(f"  {item:48s} from rest {t0:6.1f} s, {i0} it, {f0} fact | from the baseline "
                  f"{t1:6.1f} s, {i1} it, {f1} fact ({said(how1)}) | ratio {t0 / t1:.2f} | largest "
                  f"difference {float(np.linalg.norm(u0 - u1, axis=1).max()):.4f} mm, on the skin "
                  f"{float(np.linalg.norm(u0 - u1, axis=1)[skin].max()):.4f} mm", flush=True)
        print(f"time ratio (from rest / from the baseline): median {float(np.median(ratios)):.2f} over "
              f"the {len(ratios)} effects solved both ways; load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
