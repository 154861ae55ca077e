"""Benchmark: `faceplan predict` at standard resolution with contact and muscle, registration cached.

The embedded synthetic head of the demo (`planner.pipeline.write_demo_case`) gets the demo's
bimaxillary plan (Le Fort I advancement, mandibular setback, genioplasty) with a resting orbicularis oris / mentalis tone. The prediction
is timed after a first registration has filled the registration cache. Prints the time of
every stage and the peak resident memory; the last line is
`solve_s=<t> total_s=<t> peak_mb=<m>` (targets: solve < 30 s, total < 60 s on 2 cores).
`--no-contact` and `--resolution` change the set-up; a failed solve prints why and exits 3.
"""
from __future__ import annotations

import argparse
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

def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", default="standard", choices=("coarse", "standard", "fine"))
    parser.add_argument("--no-contact", action="store_true", help="solve without lip contact")
    args = parser.parse_args()
    plan = dict(DEMO_PLAN, muscles={"orbicularis_oris": 0.05, "mentalis": 0.05},
                model={"resolution": args.resolution, "contact": not args.no_contact})
    print(f"resolution {args.resolution}, contact {'off' if args.no_contact else 'on'}, muscle tone 0.05")
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
    timings = report["timings_s"]
    print("stage times (s):")
    for k, v in timings.items():
        print(f"  {k:16s} {v:8.2f}")
    print(f"elements: {report['soft_tissue']['n_elements']}, nodes: {report['soft_tissue']['n_nodes']}")
    solver = report.get("solver", {})
    print(f"Newton iterations: {solver.get('iterations')}, load steps: {solver.get('steps')}, "
          f"cut-backs: {solver.get('info', {}).get('cutbacks')}")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    solve = timings.get("solve", float("nan"))
    print(f"solve_s={solve:.2f} total_s={total:.2f} peak_mb={peak_mb:.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
