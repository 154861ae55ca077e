"""Benchmark: `faceplan predict` at standard resolution with contact and muscle, registration cached.

A synthetic head (`faceplan synth --seed 1`) gets a bimaxillary plan (Le Fort I advancement,
mandibular setback, genioplasty) with a resting orbicularis oris / mentalis tone. The prediction
is run twice: the first run fills the registration cache, the second is timed. Prints the time of
every stage and the peak resident memory; the last line is
`solve_s=<t> total_s=<t> peak_mb=<m>` (targets: solve < 30 s, total < 60 s on 2 cores).
"""
from __future__ import annotations

import resource
import sys
import tempfile
import time
from pathlib import Path

import yaml

from planner.cli import main as faceplan
from planner.pipeline import predict_case

PLAN = {
    "faceplan": 1,
    "segments": {
        "maxilla": {"translation": [0.0, 4.0, 1.0]},
        "mandible": {"translation": [0.0, -3.0, 0.0]},
        "chin": {"translation": [0.0, 3.0, -1.0]},
    },
    "muscles": {"orbicularis_oris": 0.05, "mentalis": 0.05},
    "model": {"resolution": "standard", "contact": True},
}


def find_case(root: Path) -> Path:
    for p in sorted(root.rglob("preop")):
        if p.is_dir():
            return p.parent
    raise SystemExit(f"no case folder written under {root}")


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="faceplan-bench-") as tmp:
        tmp = Path(tmp)
        if faceplan(["synth", "--out", str(tmp / "cases"), "--count", "1", "--seed", "1"]) != 0:
            raise SystemExit("faceplan synth failed")
        case = find_case(tmp / "cases")
        (case / "plan.yaml").write_text(yaml.safe_dump(PLAN))
        t0 = time.perf_counter()
        predict_case(case, tmp / "warm", render=False, echo=False)
        print(f"first run (fills the registration cache): {time.perf_counter() - t0:.1f} s")
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
