"""Benchmark: a prediction from input surfaces of real size.

A CT-derived skin or bone surface has 10^5-10^6 triangles, a synthetic one 10^4. This bench
writes a synthetic patient (`facemodel.synthetic.synthetic_head`, seed 7; written by `faceplan
synth`'s writer) whose skin is subdivided to ~1M triangles and whose bone segments to ~500k in
all (midpoint subdivision: the same shapes, four times the triangles per level), then runs
`faceplan predict` on it end to end (`planner.pipeline.predict_case`, registration included,
no cache) and prints the time of every stage, the registration's own stages, and the peak
resident memory (`resource.getrusage`), the working surfaces registration simplified the input
to and the skin fit on them and on the full-resolution skin. The FE solve is printed apart (it
is the solver's; `total_s` includes it). The last two lines are
`realsize: skin_tris=.. bone_tris=.. solve_s=.. other_s=..` and `total_s=.. peak_mb=..`
(targets: <= 60 s, <= 4096 MB at standard on 2 cores).

Flags: `--skin-triangles N` (default 1e6), `--bone-triangles N` (default 5e5, over all
segments), `--resolution coarse|standard|fine` (default standard), `--seed S`, `--render` (the
images too; off by default, as in the targets), `--out DIR` (keep the prediction there).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# `python bench/realsize.py` puts bench/ first on sys.path, where bench/registration.py would
# shadow the registration package: drop it.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]


def subdivided(mesh, target: int):
    """`mesh` midpoint-subdivided until it has at least ~target / 2 triangles (x4 per level)."""
    while len(mesh.faces) * 2 < target:
        mesh = mesh.subdivide()
    return mesh


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skin-triangles", type=float, default=1e6)
    parser.add_argument("--bone-triangles", type=float, default=5e5)
    parser.add_argument("--resolution", default="standard", choices=("coarse", "standard", "fine"))
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--render", action="store_true")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    from facemodel.synthetic import synthetic_head
    from planner.commands.synth import write_case
    from planner.errors import SolveError
    from planner.pipeline import predict_case

    with tempfile.TemporaryDirectory(prefix="faceplan-realsize-") as tmp:
        root = Path(tmp)
        os.environ["XDG_CACHE_HOME"] = str(root / "cache")   # no registration reused
        t0 = time.perf_counter()
        head = synthetic_head(args.seed)
        case = root / "case"
        case.mkdir()
        write_case(case, head)
        skin = subdivided(head.skin, int(args.skin_triangles))
        skin.export(case / "preop" / "skin.stl")
        skin_tris = len(skin.faces)
        total = sum(len(b.faces) for b in head.bones.values())
        bone_tris = 0
        for name, bone in head.bones.items():
            b = subdivided(bone, int(args.bone_triangles * len(bone.faces) / total))
            b.export(case / "preop" / "bone" / f"{name}.stl")
            bone_tris += len(b.faces)
        print(f"case: skin {len(skin.faces)} triangles (synthetic {len(head.skin.faces)}), bones "
              f"{bone_tris} triangles in {len(head.bones)} segments (synthetic {total}); written in "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
        del skin, head
        lines: list[str] = []
        cpu: dict[str, float] = {}       # stage -> CPU seconds of this process (the wall time
        started: dict[str, float] = {}   # on a shared machine counts the other jobs' too)

        def echo(line: str) -> None:
            lines.append(line)
            text = line.split("] ", 1)[-1].strip()
            if text.endswith(" ...") and "done in" not in text:
                started[text[:-4]] = time.process_time()
            elif " done in " in text:
                name = text.split(" done in ")[0]
                if name in started:
                    cpu[name] = cpu.get(name, 0.0) + time.process_time() - started.pop(name)

        cpu0 = time.process_time()
        t1 = time.perf_counter()
        try:
            out = predict_case(case, Path(args.out) if args.out else root / "predict",
                               resolution=args.resolution, render=args.render, echo=echo)
        except SolveError as exc:
            print(f"the prediction failed after {time.perf_counter() - t1:.1f} s: {exc}")
            return 3
        wall = time.perf_counter() - t1
        cpu_total = time.process_time() - cpu0
        report = json.loads((out / "report.json").read_text())
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"predict at {args.resolution}: stage times (s): wall, CPU of this process")
    for k, v in report["timings_s"].items():
        print(f"  {k:16s} {v:8.2f} {cpu[k]:8.2f}" if k in cpu else f"  {k:16s} {v:8.2f}")
    reg = report.get("registration", {}).get("time", {})
    if reg:
        print("registration stages (s): " + ", ".join(f"{k} {v:.2f}" for k, v in reg.items()))
    registration = report.get("registration", {})
    for name, w in registration.get("working_surfaces", {}).items():
        dev = w["deviation"]
        print(f"working surface {name}: {w['triangles_given']} -> {w['triangles_working']} triangles, "
              f"given vertices off it by mean {dev['mean_mm']:.4f} / p99 {dev['p99_mm']:.4f} / "
              f"max {dev['max_mm']:.4f} mm")
    fit = registration.get("fit", {})
    for key in ("skin", "skin_full_resolution"):
        if fit.get(key):
            print(f"fit {key}: mean {fit[key]['mean_mm']:.4f} mm, p95 {fit[key]['p95_mm']:.4f} mm, "
                  f"max {fit[key]['max_mm']:.4f} mm over {fit[key]['n_points']} points")
    solver = report.get("solver", {})
    print(f"Newton iterations {solver.get('iterations')}, load steps {solver.get('steps')}; "
          f"elements {report['soft_tissue']['n_elements']}")
    solve_s = float(report["timings_s"].get("solve", 0.0))
    print(f"realsize: skin_tris={skin_tris} bone_tris={bone_tris} solve_s={solve_s:.1f} "
          f"other_s={wall - solve_s:.1f}")
    print(f"cpu_s={cpu_total:.1f} (CPU time of this process; wall / CPU > 1 means it waited for "
          f"the processor: load average {os.getloadavg()[0]:.1f})")
    print(f"total_s={wall:.1f} peak_mb={peak_mb:.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
