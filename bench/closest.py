"""Benchmark: exact closest points on a skin (`solver.geometry.TriangleTree`, which `faceplan
compare`, `diagnose`, the whole predicted face and the synthetic scan use).

The skin of synthetic head `--seed` (`facemodel.synthetic.synthetic_head`, ~80k triangles) and
its quadric decimation to a tenth (`fast_simplification`: broad triangles beside fine ones, as a
decimated CT skin), each queried with `--points` points scattered 0.3 mm and 1 mm about the
surface. Prints the triangles, the seconds per query (after one warm-up that compiles the numba
kernel) and, on 2000 of the points, the largest difference from every-triangle brute force
(0 when the search is exact). Only the public `TriangleTree(vertices, faces).closest(points)`
is called, so the same script times an earlier version of the tree.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=4242)
    ap.add_argument("--points", type=int, default=300_000)
    args = ap.parse_args()
    import fast_simplification

    from facemodel.synthetic import synthetic_head
    from solver import geometry

    head = synthetic_head(args.seed)
    v, f = np.asarray(head.skin.vertices, float), np.asarray(head.skin.faces, np.int64)
    vd, fd = fast_simplification.simplify(v.astype(np.float32), f.astype(np.int32), target_reduction=0.9)
    rng = np.random.default_rng(0)
    geometry.TriangleTree(v, f).closest(v[:10])
    for name, (vv, ff) in (("skin", (v, f)), ("decimated to 10 %", (np.asarray(vd, float), np.asarray(fd, np.int64)))):
        for sd in (0.3, 1.0):
            p = vv[rng.integers(0, len(vv), args.points)] + rng.normal(0.0, sd, (args.points, 3))
            t = time.perf_counter()
            tree = geometry.TriangleTree(vv, ff)
            d = tree.closest(p)[3]
            dt = time.perf_counter() - t
            cand = np.tile(np.arange(len(ff)), (2000, 1))
            d0 = geometry._closest_over_candidates(np.ascontiguousarray(p[:2000]), vv, ff, cand)[3]
            print(f"{name}: {len(ff)} triangles, {args.points} points {sd} mm about it: {dt:.2f} s "
                  f"(build and query), brute-force difference {np.abs(d[:2000] - d0).max():.1e} mm", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
