"""Benchmark: `faceplan predict` at standard resolution with contact and muscle, registration cached.

The embedded synthetic head of the demo (`planner.pipeline.write_demo_case`) gets the demo's
bimaxillary plan (Le Fort I advancement, mandibular setback, genioplasty) with a resting orbicularis oris / mentalis tone. The prediction
is timed after a first registration has filled the registration cache. Prints the time of
every stage and the peak resident memory; the last line is
`solve_s=<t> total_s=<t> peak_mb=<m>` (targets: solve < 30 s, total < 60 s on 2 cores).
`--no-contact` and `--resolution` change the set-up; a failed solve prints why and exits 3.
The solver line gives Newton iterations, load steps, cut-backs, factorisations and Krylov
iterations, and the Newton loop's split (assembly, linear solves); the load average is printed
because the machine may be shared. `--sensitivities` also times the derivatives of the
predicted nodes with respect to every effect parameter (the diagnosis' linear sensitivities)
with the default linear solver against SciPy's SuperLU in the same run.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

# `python bench/pipeline.py` puts bench/ first on sys.path, where bench/registration.py would
# shadow the registration package: drop it.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from planner.case import load_case  # noqa: E402
from planner.errors import SolveError  # noqa: E402
from planner.pipeline import DEMO_PLAN, Progress, predict_case, register_case, write_demo_case  # noqa: E402

def _time_sensitivities(case_dir) -> None:
    """du/dp of every effect parameter at the converged prediction
    (`planner.pipeline.effect_sensitivities`: one tangent factorisation, one substitution per
    parameter), with the default linear solver and with SciPy's SuperLU; prints both times,
    their ratio and the largest difference of the derivatives."""
    import numpy as np

    import solver.sensitivity as sens
    from planner.pipeline import effect_sensitivities, load_plan, solve_plan

    case = load_case(case_dir)
    model, _ = register_case(case, load_plan(case.require_plan()).model.resolution,
                             Progress(echo=False))
    pred = solve_plan(model, load_plan(case.require_plan()), case.bones)
    original = sens.linear_response
    out = {}
    for backend in ("auto", "scipy"):
        sens.linear_response = lambda *a, _b=backend, **k: original(*a, backend=_b, **k)
        t0 = time.perf_counter()
        out[backend] = (effect_sensitivities(pred), time.perf_counter() - t0)
    sens.linear_response = original
    fast, slow = out["auto"], out["scipy"]
    diff = max(float(np.abs(fast[0][k] - slow[0][k]).max()) for k in fast[0])
    scale = max(float(np.abs(slow[0][k]).max()) for k in slow[0])
    print(f"effect sensitivities ({len(fast[0])} parameters): {fast[1]:.2f} s "
          f"(symmetric solver), SuperLU {slow[1]:.2f} s, ratio {slow[1] / fast[1]:.1f}, largest "
          f"difference {diff:.2e} of {scale:.2e} (load average {os.getloadavg()[0]:.1f})")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", default="standard", choices=("coarse", "standard", "fine"))
    parser.add_argument("--no-contact", action="store_true", help="solve without lip contact")
    parser.add_argument("--sensitivities", action="store_true",
                        help="also time the effect sensitivities du/dp of every effect parameter "
                             "at the prediction (PARDISO, against SciPy's SuperLU in the same run)")
    args = parser.parse_args()
    plan = dict(DEMO_PLAN, muscles={"orbicularis_oris": 0.05, "mentalis": 0.05},
                model={"resolution": args.resolution, "contact": not args.no_contact})
    print(f"resolution {args.resolution}, contact {'off' if args.no_contact else 'on'}, muscle tone 0.05; "
          f"load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory(prefix="faceplan-bench-") as tmp:
        tmp = Path(tmp)
        case = write_demo_case(tmp / "case", plan)
        t0 = time.perf_counter()
        register_case(load_case(case), args.resolution, Progress(echo=False))
        print(f"registration (fills the cache): {time.perf_counter() - t0:.1f} s")
        lines: list[str] = []
        t0 = time.perf_counter()
        try:
            predict_case(case, tmp / "predict", render=True, echo=lines.append)
        except SolveError as exc:
            print("\n".join(ln for ln in lines if " it " not in ln))
            print(f"the prediction failed after {time.perf_counter() - t0:.1f} s: {exc}")
            return 3
        total = time.perf_counter() - t0
        import json

        report = json.loads((tmp / "predict" / "report.json").read_text())
        if args.sensitivities:
            _time_sensitivities(case)
    timings = report["timings_s"]
    print("stage times (s):")
    for k, v in timings.items():
        print(f"  {k:16s} {v:8.2f}")
    print(f"elements: {report['soft_tissue']['n_elements']}, nodes: {report['soft_tissue']['n_nodes']}")
    solver = report.get("solver", {})
    info = solver.get("info", {})
    print(f"Newton iterations: {solver.get('iterations')}, load steps: {solver.get('steps')}, "
          f"cut-backs: {info.get('cutbacks')}, factorisations: {info.get('factorizations')}, "
          f"Krylov iterations: {info.get('krylov_iterations')}")
    t = info.get("timings", {})
    if t:
        print(f"Newton loop {t.get('total', 0):.2f} s: assembly {t.get('assembly', 0):.2f} s, "
              f"linear solves {t.get('solve', 0):.2f} s (PARDISO factorisations "
              f"{t.get('pardiso_factorization', 0):.2f} s, substitutions "
              f"{t.get('pardiso_substitution', 0):.2f} s)")
    print(f"load average {os.getloadavg()[0]:.1f} (1 min) at the end")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    solve = timings.get("solve", float("nan"))
    print(f"solve_s={solve:.2f} total_s={total:.2f} peak_mb={peak_mb:.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
