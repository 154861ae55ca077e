"""Benchmark: one site's calibration with its uncertainty on 2 dask workers (issue 21: <= 5 min),
and the coverage of its 90 % intervals.

A synthetic aspiration (or, with --test indentation, indentation) site of known parameters,
measured with a finer slab mesh (other wedge angle, wider slab) than the calibration's and
Gaussian noise of 1 % of the curve's range, is calibrated as `faceplan calibrate` does it
(LocalCluster of 2 processes started inside the timing, two-stage design, emulator, posterior,
FE check, Sobol table). Then the emulator is reused for --repeats noisy repeats: how often the
90 % intervals hold the true C10, C20 (and the dermis ratio when identifiable), and how often
the point estimate of C10 is within 10 %. Prints the figures; the last line is
`calibrate_s=<seconds> coverage_C10=<fraction> coverage_C20=<fraction> heldout_error_pct=<%>`.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planner.calibration.data import SiteData  # noqa: E402
from planner.calibration.emulator import dask_client  # noqa: E402
from planner.calibration.identify import identify, summarise  # noqa: E402
from planner.calibration.run import calibrate_sites  # noqa: E402
from planner.calibration.slab import MeshOptions, Site, forward_curve  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--test", choices=("aspiration", "indentation"), default="aspiration")
    ap.add_argument("--runs", type=int, default=24, help="focused-design runs (as --runs of the command)")
    ap.add_argument("--n-fine", type=int, default=8, help="mesh resolution (standard: 8)")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--truth", type=float, nargs=3, default=(4.5, 1.8, 2.5),
                    metavar=("C10", "C20", "RATIO"))
    args = ap.parse_args()
    truth = tuple(args.truth)
    if args.test == "aspiration":
        site = Site("aspiration", skin_mm=1.6, fat_mm=9.0, aperture_mm=10.0, rim_mm=3.0)
        x = np.linspace(2.0, 16.0, 8)
    else:
        site = Site("indentation", skin_mm=1.5, fat_mm=6.0, indenter_radius_mm=3.0,
                    max_depth_mm=1.4)
        x = np.linspace(0.2, 1.4, 7)
    truth_mesh = MeshOptions(n_fine=2 * args.n_fine, growth=1.15, lateral=5.0, wedge_deg=3.0)
    t = time.perf_counter()
    clean = forward_curve(site, *truth, x, truth_mesh)
    print(f"truth curve (fine mesh): {np.round(clean, 4).tolist()} in {time.perf_counter() - t:.1f} s")
    sigma = 0.01 * (clean.max() - clean.min())
    rng = np.random.default_rng(args.seed)
    sd = SiteData("site", site, x, clean + rng.normal(0.0, sigma, len(x)), sigma, "synthetic")
    t0 = time.perf_counter()
    with dask_client(None, 2) as client:
        report, extras = calibrate_sites([sd], client, opt=MeshOptions(n_fine=args.n_fine),
                                         n_stage1=max(6, 2 * args.runs // 3), n_stage2=args.runs,
                                         n_heldout=max(3, args.runs // 3), seed=args.seed)
    elapsed = time.perf_counter() - t0
    rec = report["sites"]["site"]
    print(f"one site, {args.test}, 2 dask workers: {elapsed:.1f} s (phases: {report['timings_s']})")
    print(f"estimate C10 {rec['C10_kpa']} C20 {rec['C20_kpa']} ratio {rec['dermis_ratio']} "
          f"(truth {truth})")
    print(f"emulator: {report['emulator']['n_runs']} runs, held-out error max "
          f"{report['emulator']['heldout_error_pct']} %, rms {report['emulator']['heldout_rms_pct']} %")

    em, box = extras["emulators"], extras["box"]
    hits = {"C10_kpa": 0, "C20_kpa": 0, "dermis_ratio": 0}
    n_ratio = 0
    within10 = 0
    t = time.perf_counter()
    for _ in range(args.repeats):
        y = clean + rng.normal(0.0, sigma, len(x))
        r = summarise(identify([SiteData("site", site, x, y, sigma, "synthetic")], em, box, rng))
        for j, key in enumerate(("C10_kpa", "C20_kpa")):
            lo, hi = r[key]["interval_90"]
            hits[key] += lo <= truth[j] <= hi
        if r["dermis_ratio"]["identifiable"]:
            n_ratio += 1
            lo, hi = r["dermis_ratio"]["interval_90"]
            hits["dermis_ratio"] += lo <= truth[2] <= hi
        within10 += abs(r["C10_kpa"]["estimate"] / truth[0] - 1.0) <= 0.10
    n = args.repeats
    print(f"{n} noisy repeats on the same emulator ({time.perf_counter() - t:.1f} s): "
          f"90 % intervals hold C10 {hits['C10_kpa']}/{n}, C20 {hits['C20_kpa']}/{n}, "
          f"ratio {hits['dermis_ratio']}/{n_ratio} (repeats where identifiable); "
          f"C10 within 10 %: {within10}/{n}")
    print(f"calibrate_s={elapsed:.1f} coverage_C10={hits['C10_kpa'] / n:.2f} "
          f"coverage_C20={hits['C20_kpa'] / n:.2f} heldout_error_pct={report['emulator']['heldout_error_pct']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
