"""Benchmark: `faceplan predict` at standard resolution with contact and muscle, registration cached.

The embedded synthetic head of the demo (`planner.pipeline.write_demo_case`) gets the demo's
bimaxillary plan (Le Fort I advancement, mandibular setback, genioplasty) with a resting orbicularis oris / mentalis tone. The prediction
is timed after a first registration has filled the registration cache. Prints the time of
every stage and the peak resident memory; the last line is
`solve_s=<t> total_s=<t> peak_mb=<m>` (targets: solve < 30 s, total < 60 s on 2 cores).
"""
from __future__ import annotations

import resource
import sys
import tempfile
import time
from pathlib import Path

from planner.case import load_case
from planner.pipeline import DEMO_PLAN, Progress, predict_case, register_case, write_demo_case

PLAN = dict(DEMO_PLAN, muscles={"orbicularis_oris": 0.05, "mentalis": 0.05},
            model={"resolution": "standard", "contact": True})


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="faceplan-bench-") as tmp:
        tmp = Path(tmp)
        case = write_demo_case(tmp / "case", PLAN)
        t0 = time.perf_counter()
        register_case(load_case(case), "standard", Progress(echo=False))
        print(f"registration (fills the cache): {time.perf_counter() - t0:.1f} s")
        lines: list[str] = []
        t0 = time.perf_counter()
        predict_case(case, tmp / "predict", render=True, echo=lines.append)
        total = time.perf_counter() - t0
        import json

        report = json.loads((tmp / "predict" / "report.json").read_text())
    timings = report["timings_s"]
    print("stage times (s):")
    for k, v in timings.items():
        print(f"  {k:16s} {v:8.2f}")
    print(f"elements: {report['soft_tissue']['n_elements']}, nodes: {report['soft_tissue']['n_nodes']}")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    solve = timings.get("solve", float("nan"))
    print(f"solve_s={solve:.2f} total_s={total:.2f} peak_mb={peak_mb:.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
